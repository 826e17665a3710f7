"""The report's figures: runs with equal parameter curves share one legend entry instead of hiding under one another;
the prediction error's variance is on a log scale."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from heartcv.cli.report_plots import _identical_series, parameter_figure, prediction_error_figure  # noqa: E402


def _legend_texts(fig):
    return [t.get_text() for legend in fig.legends for t in legend.get_texts()]


def test_equal_parameter_curves_are_drawn_once_under_all_their_labels():
    t = np.linspace(0.0, 1.0, 26)
    const = (t, np.full_like(t, 0.87), np.full_like(t, 0.007))
    walk = (t, 0.87 + 0.01 * np.sin(t), np.full_like(t, 0.005))
    series = {"ge": walk, "kf": const, "harmonic": tuple(np.copy(a) for a in const), "kf:other": const,
              "kf:nudged": (t, const[1] + 1e-12, const[2]), "kf:short": (t[:-1], const[1][:-1], const[2][:-1])}
    groups = _identical_series(series)
    assert [labels for labels, _ in groups] == [["ge"], ["kf", "harmonic", "kf:other"], ["kf:nudged"], ["kf:short"]]
    assert np.array_equal(groups[1][1][1], const[1])
    colors = {label: f"C{i}" for i, label in enumerate(series)}
    fig = parameter_figure("f_hr", "Hz", series, colors)
    try:
        texts = _legend_texts(fig)
        assert "GE" in texts and "KF, HARMONIC, KF (other)" in texts and "KF (nudged)" in texts
        assert len(fig.axes[0].lines) == 4                              # four curves drawn, not six
    finally:
        plt.close(fig)


def test_equal_curves_with_nan_are_grouped():
    t = np.arange(4.0)
    a = (t, np.array([1.0, np.nan, 2.0, 3.0]), np.zeros(4))
    assert [labels for labels, _ in _identical_series({"a": a, "b": a})] == [["a", "b"]]


def test_prediction_error_variance_on_a_log_scale():
    t = np.arange(5) / 25.0
    series = {"kf": (t, np.full(5, 3e-4), np.full(5, 1e-8), 3e-4),
              "constvel": (t, np.full(5, 6e-4), np.array([1e-6, 4.6e-5, 1e-6, 1e-6, 1e-6]), 6e-4)}
    fig = prediction_error_figure(series, {"kf": "C0", "constvel": "C1"})
    try:
        top, bottom = fig.axes[:2]
        assert top.get_yscale() == "linear" and top.get_ylim()[0] == 0
        assert bottom.get_yscale() == "log"
        lo, hi = bottom.get_ylim()
        assert lo <= 1e-8 * 1e6 and hi >= 4.6e-5 * 1e6             # mm²: both curves in view
    finally:
        plt.close(fig)
