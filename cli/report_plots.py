"""Figures of ``heartcv report`` (matplotlib, Agg; no pyplot state): prediction error per step (the paper's
Fig. 4), parameter trajectories with ±2σ bands, NIS per degree of freedom with its χ² bands, error against
ground truth (filtered estimates and one-step predictions), step times.

Every function takes plain arrays keyed by a series label and returns a ``matplotlib.figure.Figure``; the
house style (colours per estimator, legend below the axes, SI prefixes) is that of :mod:`cli.plots`.
Lengths are drawn in mm, times in s and ms.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .plots import TITLES, _y_scale, si_scale

__all__ = ["prediction_error_figure", "parameter_figure", "nis_figure", "truth_error_figure",
           "step_time_figure", "series_name", "write_figures", "CAPTIONS"]

MM = 1e3  # m -> mm
_SIZE = (6.4, 4.0)
_NOISE_STYLE = {"color": "0.35", "ls": ":", "lw": 1.3}
_BOUND_STYLE = {"color": "0.35", "ls": "-.", "lw": 1.1}
_FIT_END_STYLE = {"color": "0.15", "ls": ":", "lw": 1.6}
_MEAS_STYLE = {"color": "0.15", "ls": (0, (6, 3)), "lw": 1.2}


def series_name(label: str) -> str:
    """Legend name of a series label: ``'ge'`` -> ``'GE'``, ``'ge:run2'`` -> ``'GE (run2)'``."""
    est, _, tag = label.partition(":")
    return est.upper() + (f" ({tag})" if tag else "")


def _figure(nrows=1, size=_SIZE, sharex=True):
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    axes = fig.subplots(nrows, 1, sharex=sharex, squeeze=False)[:, 0]
    return fig, axes


def _style(ax, xlabel=None):
    ax.grid(True, which="major", alpha=0.3)
    ax.spines[["top", "right"]].set_visible(False)
    if xlabel:
        ax.set_xlabel(xlabel)


def _legend(fig, handles, ncol=None):
    if handles:
        fig.legend(handles=handles, loc="outside lower center", ncol=ncol or min(len(handles), 4), fontsize=8,
                   frameon=False)


def _z(i: int) -> float:
    """zorder of series i: the first series (the estimator of interest) is drawn on top."""
    return 3.0 - i / 100.0


def _with_mean(label: str, overall: float) -> str:
    name = series_name(label)
    return f"{name} (mean {overall * MM:#.3g} mm, k ≥ 1)" if np.isfinite(overall) else name


def _hline(ax, y, t, color):
    """A dashed level (an average) over the time range of its own series (a partial run ends early)."""
    t = np.asarray(t, float)
    if t.size:
        ax.hlines(y, t[0], t[-1], colors=color, lw=1.0, ls="--", alpha=0.8, zorder=1.5)


def _xlim(ax, series_times):
    ts = [np.asarray(t, float) for t in series_times if len(t)]
    if ts:
        lo, hi = min(t[0] for t in ts), max(t[-1] for t in ts)
        if hi > lo:
            ax.set_xlim(lo, hi)


def prediction_error_figure(series: dict, colors: dict, noise_norm: float | None = None,
                            noise_bound: float | None = None, fit_end: float | None = None):
    """Mean (top) and variance (bottom) over the seen points of the one-step prediction error norm per step.

    Parameters
    ----------
    series : dict label -> (times (K,), mean (K,) m, var (K,) m^2, overall mean m)
        The overall mean (steps k ≥ 1) is drawn as a dashed line and quoted in the legend.
    colors : dict label -> colour
    noise_norm : float, optional
        Mean norm of the measurement noise, E|v| (m): a dotted reference line, the error of a perfect
        predictor.
    noise_bound : float, optional
        The tracks' own upper bound of the frame-to-frame part of E|v| (m; report ``tracks.noise_norm_bound_m``): a
        dash-dotted line.
    fit_end : float, optional
        Time (s) of the first frame after the frames that fitted the parameters (report ``fit_frames``): a vertical
        line; the predictions before it are in-sample.
    """
    from matplotlib.lines import Line2D

    fig, (top, bottom) = _figure(2, size=(6.4, 5.2))
    handles = []
    for i, (label, (t, mean, var, overall)) in enumerate(series.items()):
        c, z = colors[label], _z(i)
        top.plot(t, np.asarray(mean) * MM, color=c, lw=1.6, marker="o", ms=2.5, zorder=z)
        bottom.plot(t, np.asarray(var) * MM**2, color=c, lw=1.6, marker="o", ms=2.5, zorder=z)
        txt = _with_mean(label, overall)
        if np.isfinite(overall):
            _hline(top, overall * MM, t, c)
        handles.append(Line2D([], [], color=c, lw=1.6, marker="o", ms=2.5, label=txt))
    if noise_norm is not None and np.isfinite(noise_norm):
        top.axhline(noise_norm * MM, **_NOISE_STYLE)
        handles.append(Line2D([], [], **_NOISE_STYLE, label=f"measurement noise E|v| = {noise_norm * MM:#.3g} mm"))
    if noise_bound is not None and np.isfinite(noise_bound):
        top.axhline(noise_bound * MM, **_BOUND_STYLE)
        handles.append(Line2D([], [], **_BOUND_STYLE,
                              label=f"frame-to-frame noise E|v| ≤ {noise_bound * MM:#.3g} mm (tracks' bound)"))
    handles.append(Line2D([], [], color="0.3", lw=1.0, ls="--", label="overall mean"))
    if fit_end is not None and np.isfinite(fit_end):
        for ax in (top, bottom):
            ax.axvline(fit_end, **_FIT_END_STYLE)
        handles.append(Line2D([], [], **_FIT_END_STYLE, label="end of the fitted frames (heartcv fit)"))
    top.set_ylabel(r"mean $|y - \hat{y}|$ [mm]")
    # the variance on a log scale: one estimator's outlier frames (a baseline's, tens of mm²) would otherwise flatten
    # every other curve onto the axis
    bottom.set_ylabel(r"variance of $|y - \hat{y}|$ [mm²]")
    bottom.set_yscale("log")
    for ax in (top, bottom):
        _style(ax)
    top.set_ylim(bottom=0)
    bottom.set_xlabel("time [s]")
    _xlim(bottom, [s[0] for s in series.values()])
    _legend(fig, handles, ncol=2)
    return fig


def _identical_series(series: dict) -> list:
    """``series`` (label -> (times, mean, std)) as [(labels, (times, mean, std))]: runs whose curves are equal (e.g.
    several runs at the same fitted constant) drawn once under all their labels, not hidden under one another."""
    groups = []
    for label, curve in series.items():
        t, m, s = (np.asarray(a, float) for a in curve)
        for labels, (t0, m0, s0) in groups:
            if t.shape == t0.shape and m.shape == m0.shape and s.shape == s0.shape and np.array_equal(t, t0) \
                    and np.array_equal(m, m0, equal_nan=True) and np.array_equal(s, s0, equal_nan=True):
                labels.append(label)
                break
        else:
            groups.append(([label], (t, m, s)))
    return groups


def parameter_figure(name: str, unit: str, series: dict, colors: dict, truth=None, phases=None, reference=None):
    """Posterior mean of one parameter per estimator with its ±2σ band, and the truth if given; systole shaded
    when ``phases`` is given.

    Parameters
    ----------
    name : str
        Parameter name (``tracker.params.NAMES``).
    unit : str
        Its SI unit (``tracker.params.UNITS``); Pa and s get an SI prefix from the data.
    series : dict label -> (times (K,), mean (K,), std (K,))
    truth : (times, values), optional
    phases : (times (K,), systole (K,) bool), optional
    reference : list of (t_start, t_end, value, std), optional
        An independent estimate over windows (the tracks' own heart rate), in the figure's units before any SI
        prefix: black bars over each window with ±2σ error bars at its centre.
    """
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    values = [np.asarray(m) for _, m, _ in series.values()] + ([np.asarray(truth[1])] if truth is not None else [])
    scale, pu = si_scale(np.concatenate(values) if values else [], unit)
    fig, (ax,) = _figure()
    handles = []
    for i, (labels, (t, mean, std)) in enumerate(_identical_series(series)):
        c = colors[labels[0]]
        m, s = np.asarray(mean) * scale, np.asarray(std) * scale
        if np.nanmax(s, initial=0.0) > 0:
            ax.fill_between(t, m - 2 * s, m + 2 * s, color=c, alpha=0.18, lw=0)
        ax.plot(t, m, color=c, lw=1.8, zorder=_z(i))
        handles.append(Line2D([], [], color=c, lw=1.8, label=", ".join(series_name(lb) for lb in labels)))
    if any(np.nanmax(np.asarray(s), initial=0.0) > 0 for _, _, s in series.values()):
        handles.append(Patch(color="0.6", alpha=0.35, label="±2σ"))
    if truth is not None:
        ax.plot(truth[0], np.asarray(truth[1]) * scale, color="k", lw=1.2, ls="--", zorder=4)
        handles.append(Line2D([], [], color="k", lw=1.2, ls="--", label="truth"))
    if reference:
        for t0, t1, v, sd in reference:
            ax.hlines(v * scale, t0, t1, color="k", lw=1.4, zorder=5)
            ax.errorbar(0.5 * (t0 + t1), v * scale, yerr=2 * sd * scale, color="k", lw=1.0, capsize=3, zorder=5)
        handles.append(Line2D([], [], color="k", lw=1.4, marker="|", label="tracks' spectrum (windows)"))
    if phases is not None and np.any(phases[1]):
        t, sys_ = np.asarray(phases[0], float), np.asarray(phases[1], bool)
        half = 0.5 * float(np.median(np.diff(t))) if t.size > 1 else 0.0
        edges = np.flatnonzero(np.diff(np.r_[0, sys_.astype(int), 0]))
        for a, b in zip(edges[::2], edges[1::2]):
            ax.axvspan(t[a] - half, t[b - 1] + half, color="#d62728", alpha=0.07, lw=0, zorder=0)
        handles.append(Patch(color="#d62728", alpha=0.15, label="systole"))
    unit_txt = "" if pu in ("", "1") else f" [{pu.replace('^3', '³')}]"
    ax.set_ylabel(f"{TITLES.get(name, name)}{unit_txt}")
    ax.ticklabel_format(axis="y", useOffset=False)
    _style(ax, "time [s]")
    _xlim(ax, [s[0] for s in series.values()])
    _legend(fig, handles)
    return fig


def nis_figure(series: dict, colors: dict, step_band, mean_band=None, level: float = 0.95):
    """NIS per degree of freedom per step, with the per-step χ² band (light) and the band of the time
    average (dark); each estimator's time average Σ NIS / Σ dof as a dashed line.

    Parameters
    ----------
    series : dict label -> (times (K,), nis (K,), dof (K,), time average)
        The time average is Σ NIS / Σ dof over the steps with a point seen (``nis_mean / nis_mean_dof`` of
        :func:`tracker.metrics.estimator_metrics`), NaN if none.
    step_band : (times, lo (K,), hi (K,), dof (K,))
        Per-step band of the NIS (not divided), drawn divided by its dof.
    mean_band : (lo, hi, mean dof), optional
        Band of the time-averaged NIS and the mean dof it is divided by.
    """
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    fig, (ax,) = _figure()
    handles = []
    pct = f"{level * 100:g} %"
    t, lo, hi, dof = (np.asarray(a, float) for a in step_band)
    with np.errstate(invalid="ignore", divide="ignore"):
        lo_d, hi_d = lo / dof, hi / dof
    ax.fill_between(t, lo_d, hi_d, step="mid", color="0.9", lw=0, zorder=0)
    d_const = np.unique(dof[dof >= 1])
    dof_txt = f"χ²({int(d_const[0])})" if d_const.size == 1 else "χ²(dof_k)"
    handles.append(Patch(color="0.9", label=f"{pct} band per step, {dof_txt}"))
    if mean_band is not None:
        mlo, mhi, mdof = mean_band
        ax.axhspan(mlo / mdof, mhi / mdof, color="0.72", lw=0, zorder=0.5)
        handles.append(Patch(color="0.72", label=f"{pct} band of the time average"))
    ax.axhline(1.0, color="0.25", ls=":", lw=1.2, zorder=1)
    handles.append(Line2D([], [], color="0.25", ls=":", lw=1.2, label="expected (1)"))
    ys = [lo_d, hi_d]
    for i, (label, (ts, nis, d, avg)) in enumerate(series.items()):
        c = colors[label]
        with np.errstate(invalid="ignore", divide="ignore"):
            y = np.where(np.asarray(d) >= 1, np.asarray(nis, float) / np.asarray(d, float), np.nan)
        ax.plot(ts, y, color=c, lw=1.6, marker="o", ms=2.5, zorder=_z(i))
        if np.isfinite(avg):
            _hline(ax, avg, ts, c)
        ys.append(y)
        handles.append(Line2D([], [], color=c, lw=1.6, marker="o", ms=2.5,
                              label=f"{series_name(label)} (time average {avg:.3g})"))
    allv = np.concatenate([np.ravel(v) for v in ys])
    allv = allv[np.isfinite(allv) & (allv > 0)]
    if allv.size and allv.max() / allv.min() > 30:
        _y_scale(ax, True)
    else:
        ax.set_ylim(bottom=0)
    ax.set_ylabel("NIS / dof")
    _style(ax, "time [s]")
    _xlim(ax, [s[0] for s in series.values()])
    _legend(fig, handles, ncol=2)
    return fig


def truth_error_figure(series: dict, colors: dict, measurement_error: float | None = None,
                       noise_norm: float | None = None):
    """Error against the true positions per step and estimator, mean over the seen points with a ±1 std band:
    the filtered estimates (top) and the one-step predictions (bottom), on one y scale.

    Parameters
    ----------
    series : dict label -> (times (K,), filtered (mean (K,) m, var (K,) m^2, overall mean m),
                            predicted (mean, var, overall mean))
        The overall means (steps k ≥ 1) are drawn dashed and quoted in the legend.
    measurement_error : float, optional
        Mean error of the measurements themselves against the truth (m): a long-dashed reference line.
    noise_norm : float, optional
        Mean norm of the measurement noise, σ·sqrt(8/π) (m): a dotted reference line.
    """
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    fig, (top, bottom) = _figure(2, size=(6.4, 5.6))
    handles = []
    for i, (label, (t, filt, pred)) in enumerate(series.items()):
        c, name = colors[label], series_name(label)
        for ax, (mean, var, overall) in ((top, filt), (bottom, pred)):
            m, s = np.asarray(mean) * MM, np.sqrt(np.asarray(var)) * MM
            ax.fill_between(t, np.maximum(m - s, 0), m + s, color=c, alpha=0.15, lw=0)
            ax.plot(t, m, color=c, lw=1.6, marker="o", ms=2.5, zorder=_z(i))
            if np.isfinite(overall):
                _hline(ax, overall * MM, t, c)
        means = [f"{o * MM:#.3g} mm" if np.isfinite(o) else "–" for o in (filt[2], pred[2])]
        handles.append(Line2D([], [], color=c, lw=1.6, marker="o", ms=2.5,
                              label=f"{name} (mean, k ≥ 1: filtered {means[0]}, predicted {means[1]})"))
    handles.append(Patch(color="0.6", alpha=0.3, label="±1 std over the points"))
    refs = [(measurement_error, _MEAS_STYLE, "the measurements' own error, mean {:#.3g} mm"),
            (noise_norm, _NOISE_STYLE, "measurement noise mean norm E|v| = {:#.3g} mm")]
    refs = [(y, style, text.format(y * MM)) for y, style, text in refs if y is not None and np.isfinite(y)]
    for y, style, text in refs:
        for ax in (top, bottom):
            ax.axhline(y * MM, **style)
        handles.append(Line2D([], [], **style, label=text))
    handles.append(Line2D([], [], color="0.3", lw=1.0, ls="--", label="overall mean"))
    top.set_ylabel("filtered: mean\n" r"$|\hat{y}_{k|k} - y_{\mathrm{true}}|$ [mm]")
    bottom.set_ylabel("predicted: mean\n" r"$|\hat{y}_{k|k-1} - y_{\mathrm{true}}|$ [mm]")
    for ax in (top, bottom):
        _style(ax)
        ax.set_ylim(bottom=0)
    hi = max(top.get_ylim()[1], bottom.get_ylim()[1])
    for ax in (top, bottom):
        ax.set_ylim(0, hi)
    bottom.set_xlabel("time [s]")
    _xlim(bottom, [s[0] for s in series.values()])
    _legend(fig, handles, ncol=1)
    return fig


def step_time_figure(series: dict, colors: dict):
    """Wall time per step per estimator (ms, log axis); median and 95th percentile in the legend.

    Parameters
    ----------
    series : dict label -> (times (K,), step_time (K,) s, median s, p95 s)
    """
    from matplotlib.lines import Line2D

    fig, (ax,) = _figure()
    handles = []
    for i, (label, (t, st, med, p95)) in enumerate(series.items()):
        c = colors[label]
        y = np.asarray(st, float) * 1e3
        y = np.where(y > 0, y, np.nan)
        ax.plot(t, y, color=c, lw=1.2, marker="o", ms=2.5, zorder=_z(i))
        if np.isfinite(med):
            _hline(ax, med * 1e3, t, c)
        handles.append(Line2D([], [], color=c, lw=1.2, marker="o", ms=2.5,
                              label=f"{series_name(label)} (median {med * 1e3:.3g} ms, p95 {p95 * 1e3:.3g} ms)"))
    handles.append(Line2D([], [], color="0.3", lw=1.0, ls="--", label="median (k ≥ 1)"))
    _y_scale(ax, True)
    ax.set_ylabel("wall time per step [ms]")
    _style(ax, "time [s]")
    _xlim(ax, [s[0] for s in series.values()])
    _legend(fig, handles, ncol=2)
    return fig


# -- the report's figure set ------------------------------------------------------------------------
CAPTIONS = {
    "prediction_error.png": "One-step prediction error |y − ŷ| per frame: mean (top) and variance (bottom, log "
                            "scale) over the points seen, per estimator; dashed: the mean over frames k ≥ 1.",
    "nis.png": "Normalised innovation squared per degree of freedom with the 95 % χ² band of each frame (light) and "
               "of the time average (dark); dashed: each estimator's time average.",
    "truth_error.png": "Error against the true point positions of the filtered estimates (top, after each frame's "
                       "update) and of the one-step predictions (bottom): mean over the points seen (±1 std "
                       "shaded) per frame; dashed: the mean over frames k ≥ 1.",
    "step_time.png": "Wall time per step (prediction and update); dashed: the median over steps k ≥ 1.",
}


def run_rates(runs: dict, key: str = "heart_rate") -> dict:
    """label -> (times (c,), mean (c,), std (c,)) in Hz of each run's ``key`` (``heart_rate`` or
    ``respiration_rate``) over its completed steps: the GE's sampled posterior where it samples the rate, else the
    constant the run used (``meta.<key>_hz`` with ``meta.<key>_std_hz``, 0 when not recorded); runs without one
    are left out."""
    rates = {}
    for k, r in runs.items():
        e, t = r["est"], np.asarray(r["est"].times, float)
        c = e.completed_steps
        trace = getattr(e, key)
        if trace is not None:
            hr = np.asarray(trace, float)[:c]
            rates[k] = (t[:c], hr[:, 0], hr[:, 1])
        elif isinstance(e.meta.get(f"{key}_hz"), (int, float)):
            sd = e.meta.get(f"{key}_std_hz")
            sd = float(sd) if isinstance(sd, (int, float)) else 0.0
            rates[k] = (t[:c], np.full(c, float(e.meta[f"{key}_hz"])), np.full(c, sd))
    return rates


def write_figures(folder: Path, runs: dict, per: dict, truth, noise, dpi: int = 150,
                  level: float = 0.95, phases=None, noise_bound=None, fit_frames=None, rate_windows=None,
                  noise_norm=None) -> list:
    """Write the report's PNGs into ``folder``; returns [(file name, caption)] in report order.

    Parameters
    ----------
    runs : dict label -> {'path', 'est'}
        The estimate sets (:class:`tracker.measurements.EstimateSet`), in the order given.
    per : dict label -> dict
        :func:`tracker.metrics.estimator_metrics` of each run.
    truth : dict or None
        ``{'times', 'theta', 'positions': label -> (K, P, 3)}`` (cli/report.py).
    noise : float or None
        Per-coordinate measurement noise σ, m.
    phases : (times, systole) or None
        Systole per frame (:func:`tracker.metrics.systole_mask` of the measurements' pressure), shaded on the
        parameter figures.
    noise_bound : float or None
        The tracks' own upper bound of the frame-to-frame noise's mean norm (m), drawn on the prediction-error
        figure.
    fit_frames : int or None
        The frames that fitted the parameters (report ``fit_frames``): their end is marked on the prediction-error
        figure.
    rate_windows : list or None
        The tracks' own heart rate in windows (:func:`tracker.metrics.windowed_heart_rate`), drawn on the heart-rate
        figure.
    """

    from heartcv.tracker.metrics import mean_noise_norm
    from heartcv.tracker.params import NAMES, UNITS

    from .plots import COLORS, save_png

    # an estimator's own colour (the baselines' too, so a report's colours do not depend on the order of its
    # files); a second run of the same estimator, or an unknown one, the next colour no run uses
    colors = {}
    fallback = ("#9467bd", "#17becf", "#ff7f0e", "#8c564b", "#e377c2", "#bcbd22", "#1f77b4", "#d62728", "#2ca02c")
    for label, r in runs.items():
        c = COLORS.get(r["est"].estimator)
        if not c or c in colors.values():
            c = next((f for f in fallback if f not in colors.values()), fallback[len(colors) % len(fallback)])
        colors[label] = c
    ps = {k: m["per_step"] for k, m in per.items()}
    out = []

    def save(fig, name, caption):
        save_png(fig, folder / name, dpi=dpi)
        out.append((name, caption))

    if noise_norm is None:
        noise_norm = mean_noise_norm(noise) if noise else None
    t0 = next(iter(ps.values()))["times"]
    fit_end = float(t0[fit_frames]) if fit_frames is not None and 0 < fit_frames < len(t0) else None
    save(prediction_error_figure({k: (p["times"], p["error_mean"], p["error_var"],
                                         per[k]["prediction_error_mean_m"]) for k, p in ps.items()},
                                    colors, noise_norm, noise_bound, fit_end), "prediction_error.png",
         CAPTIONS["prediction_error.png"]
         + (" Dotted: the mean norm of the measurement noise, the error of a perfect predictor." if noise else "")
         + (" Dash-dotted: the tracks' own upper bound of its frame-to-frame part (a quadratic field's residual over "
            "one frame, over √2; a track's persistent error is not in it)."
            if noise_bound is not None else "")
         + (" Vertical dotted line: the first frame after those that fitted the parameters (heartcv fit --frames or "
            "--duration); the predictions before it are in-sample." if fit_end is not None else ""))
    for j in _shown_parameters(runs, ps, truth):
        name = NAMES[j]
        tr = (truth["times"], truth["theta"][:, j]) if truth is not None and truth["theta"] is not None else None
        fig = parameter_figure(name, UNITS[j], {k: (p["times"], p["theta"][:, j], p["theta_std"][:, j])
                                                   for k, p in ps.items() if np.isfinite(p["theta"][:, j]).any()},
                               colors, tr, phases)   # the baselines have no parameters
        held = [series_name(k) for k, r in runs.items() if name in (r["est"].meta.get("held_parameters") or [])]
        save(fig, f"parameter_{name}.png", f"{TITLES[name][0].upper()}{TITLES[name][1:]}: posterior mean per "
             "estimator with its ±2σ band" + (" and the truth (dashed)" if tr else "")
             + (f"; held at the fitted value by {', '.join(held)} (not separable from the estimated input's "
                "scale without a recorded pressure, docs/model.md §17)" if held else "")
             + ("; shaded: systole (the measured pressure above the midpoint of its range), unshaded: diastole."
                if phases is not None and np.any(phases[1]) else "."))
    for key, unit in (("heart_rate", "bpm"), ("respiration_rate", "per min")):
        rates = {k: (t, 60 * m, 60 * sd) for k, (t, m, sd) in run_rates(runs, key).items()}
        if rates:
            title = key.replace("_", " ")
            ref = [(w["t_start_s"], w["t_end_s"], 60 * w["frequency_hz"], 60 * (w["std_hz"] or 0.0))
                   for w in (rate_windows or []) if w.get("frequency_hz") is not None] if key == "heart_rate" else []
            save(parameter_figure(title, unit, rates, colors, reference=ref or None), f"{key}.png",
                 f"{title.capitalize()}: the GE's sampled posterior mean with its ±2σ band where it samples the "
                 "rate; a constant for the runs that hold it (the fit's, or harmonic's from the tracks' spectrum; "
                 "with its standard error where one is known)."
                 + (" Black: the tracks' own heart rate in windows of the measurements (heartcv fit's estimator, "
                    "no model; the bar spans the window, ±2σ its standard error)." if ref else ""))
    with_nis = {k: (p["times"], p["nis"], p["nis_dof"], per[k]["nis_mean"] / per[k]["nis_mean_dof"])
                for k, p in ps.items() if per[k]["nis_steps"]}
    if with_nis:
        ref = max(with_nis, key=lambda k: ps[k]["times"].size)
        band = per[ref]["nis_mean_band"]
        save(nis_figure(with_nis, colors, (ps[ref]["times"], ps[ref]["nis_lo"], ps[ref]["nis_hi"],
                                              ps[ref]["nis_dof"]),
                           (band[0], band[1], per[ref]["nis_mean_dof"]) if band else None, level),
             "nis.png", CAPTIONS["nis.png"] + (f" Bands of the {series_name(ref)} run." if len(with_nis) > 1
                                               else ""))
    if truth is not None and truth["positions"]:
        labels = [k for k in runs if k in truth["positions"]]
        meas_err = next((v for k in labels if (v := per[k].get("measurement_truth_error_mean_m")) is not None
                         and np.isfinite(v)), None)
        series = {k: (ps[k]["times"],
                      (ps[k]["truth_error_mean"], ps[k]["truth_error_var"], per[k]["truth_error_mean_m"]),
                      (ps[k]["prediction_truth_error_mean"], ps[k]["prediction_truth_error_var"],
                       per[k]["prediction_truth_error_mean_m"])) for k in labels}
        save(truth_error_figure(series, colors, meas_err, noise_norm),
             "truth_error.png", CAPTIONS["truth_error.png"]
             + (" Long dashes: the mean error of the measurements themselves against the truth, over the same "
                "observations." if meas_err is not None else "")
             + (" Dotted: the mean norm of the measurement noise, E|v|." if noise else ""))
    save(step_time_figure({k: (p["times"], p["step_time"], per[k]["step_time_median_s"],
                                  per[k]["step_time_p95_s"]) for k, p in ps.items()}, colors),
         "step_time.png", CAPTIONS["step_time.png"])
    return out


def _shown_parameters(runs, ps, truth) -> list:
    """Indices of the parameters worth a figure: estimated or held by some run (``meta.held_parameters``: an
    estimated parameter the run kept at its fitted value), or off the truth / varying in it."""
    import numpy as np

    from heartcv.tracker.params import NAMES

    shown = []
    for j, name in enumerate(NAMES):
        estimated = any(name in r["est"].meta.get("estimated", []) or (ps[k]["theta_std"][:, j] > 0).any()
                        or name in (r["est"].meta.get("held_parameters") or []) for k, r in runs.items())
        off = False
        if truth is not None and truth["theta"] is not None:
            tv = np.asarray(truth["theta"][:, j], float)
            scale = max(np.abs(tv).max(), 1e-300)
            off = np.ptp(tv) > 1e-9 * scale or any(
                np.nanmax(np.abs(ps[k]["theta"][:, j] - tv[0]), initial=0.0) > 1e-6 * scale for k in ps)
        if estimated or off:
            shown.append(j)
    return shown
