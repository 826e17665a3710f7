"""Matplotlib (Agg) figures for study and report stages: error curves, consistency curves with a
chi-square band, SI-prefixed axes, atomic PNG output.

The helpers take plain arrays keyed by a series label (an estimator name), so a report stage can reuse
them. They build ``matplotlib.figure.Figure`` objects directly (no pyplot state, no display needed).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["COLORS", "SYMBOLS", "TITLES", "si_scale", "error_figure", "consistency_figure", "save_png"]

# fixed colours per estimator so every figure of a study (and a report) matches
COLORS = {"ge": "#1f77b4", "ukf": "#d62728", "ekf": "#2ca02c", "kf": "#7f7f7f",
          "hold": "#8c564b", "constvel": "#e377c2", "harmonic": "#bcbd22"}
_FALLBACK = ("#9467bd", "#17becf", "#ff7f0e", "#8c564b", "#e377c2", "#bcbd22")
_PREFIXES = {-9: "n", -6: "µ", -3: "m", 0: "", 3: "k", 6: "M", 9: "G"}
_PREFIXABLE = ("Pa", "m", "s")
# mathtext symbols of the model parameters (tracker.params.NAMES)
SYMBOLS = {"rho": r"\rho", "alpha1": r"\alpha_1", "alpha2": r"\alpha_2", "E": "E", "nu": r"\nu"}
TITLES = {"rho": "density ρ", "alpha1": "Rayleigh damping α₁", "alpha2": "Rayleigh damping α₂",
          "E": "Young's modulus E", "nu": "Poisson's ratio ν"}


def color_of(label: str, i: int = 0) -> str:
    return COLORS.get(label, _FALLBACK[i % len(_FALLBACK)])


def si_scale(values, unit: str) -> tuple[float, str]:
    """Scale factor and prefixed unit that put the largest finite ``|values|`` in [1, 1000).

    Only units that take SI prefixes (Pa, m, s) are scaled; ``'1'`` and compound units stay as they are.
    ``si_scale([1.5e5], 'Pa') == (1e-3, 'kPa')``: multiply the values by the factor.
    """
    if unit not in _PREFIXABLE:
        return 1.0, unit
    v = np.abs(np.asarray(values, float))
    v = v[np.isfinite(v) & (v > 0)]
    if not v.size:
        return 1.0, unit
    exp = int(math.floor(math.log10(v.max()) / 3) * 3)
    exp = min(max(exp, -9), 9)
    return 10.0 ** -exp, _PREFIXES[exp] + unit


def _unit_label(unit: str) -> str:
    return "" if unit in ("", "1") else f" [{unit}]"


def _squared(unit: str) -> str:
    return "" if unit in ("", "1") else f"{unit}²"


def _new_figure(size=(6.4, 4.0)):
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    return fig, fig.add_subplot()


def error_figure(x, series: dict, *, quantity: str, unit: str, title: str | None = None,
                 xlabel: str = "step k", log: bool = True, dt: float | None = None):
    """The paper's Fig. 2 style: mean absolute error (solid, left axis) and its variance (dashed, right
    axis) per series.

    Parameters
    ----------
    x : ndarray of shape (K,)
    series : dict label -> (mean, var), each ndarray of shape (K,) in ``unit`` and ``unit``^2 (SI)
    quantity : str
        Mathtext symbol of the parameter for the axis labels, e.g. ``'E'`` or ``r'\\nu'`` (see
        :data:`SYMBOLS`).
    unit : str
        SI unit of the parameter; a prefix is chosen from the data (e.g. kPa).
    log : bool
        Logarithmic y axes (errors typically fall by orders of magnitude).
    dt : float, optional
        Step length in s: adds a time axis on top.
    """
    from matplotlib.lines import Line2D

    fig, ax = _new_figure()
    ax2 = ax.twinx()
    means = np.concatenate([np.ravel(m) for m, _ in series.values()]) if series else np.zeros(0)
    scale, pu = si_scale(means, unit)
    handles = []
    items = list(series.items())
    for i, (label, (mean, var)) in reversed(list(enumerate(items))):  # the first series drawn on top
        c = color_of(label, i)
        ax.plot(x, np.asarray(mean) * scale, color=c, lw=2.0 if i == 0 else 1.5)
        ax2.plot(x, np.asarray(var) * scale**2, color=c, lw=1.2, ls="--")
    handles = [Line2D([], [], color=color_of(lab, i), lw=2.0, label=lab.upper()) for i, (lab, _) in
               enumerate(items)]
    handles += [Line2D([], [], color="k", lw=1.8, label="mean (left)"),
                Line2D([], [], color="k", lw=1.2, ls="--", label="variance (right)")]
    err = rf"$|\hat{{{quantity}}} - {quantity}|$"
    ax.set_ylabel(f"mean {err}{_unit_label(pu)}")
    ax2.set_ylabel(f"variance of {err}{_unit_label(_squared(pu))}")
    for a in (ax, ax2):
        _y_scale(a, log)
    _finish(fig, ax, x, xlabel, dt, title, handles)
    return fig


def consistency_figure(x, series: dict, band=None, *, ylabel: str, title: str | None = None,
                       xlabel: str = "step k", log: bool = True, reference: float | None = None,
                       band_label: str = "95 % χ² band", dt: float | None = None):
    """Consistency statistic per series (e.g. ANEES or NIS per dof) with a shaded acceptance band.

    Parameters
    ----------
    x : ndarray of shape (K,)
    series : dict label -> ndarray of shape (K,)
    band : (lo, hi), optional
        Acceptance band, shaded across the plot.
    reference : float, optional
        Expected value (dotted line), e.g. M for ANEES or 1 for NIS per dof.
    dt : float, optional
        Step length in s: adds a time axis on top.
    """
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    fig, ax = _new_figure()
    handles = []
    if band is not None:
        ax.axhspan(band[0], band[1], color="0.88", zorder=0)
        handles.append(Patch(color="0.88", label=band_label))
    if reference is not None:
        ax.axhline(reference, color="0.25", ls=":", lw=1.2, zorder=1)
        handles.append(Line2D([], [], color="0.25", ls=":", lw=1.2, label=f"expected ({reference:g})"))
    items = list(series.items())
    for i, (label, y) in reversed(list(enumerate(items))):
        ax.plot(x, y, color=color_of(label, i), lw=2.0 if i == 0 else 1.5, zorder=2)
    handles[:0] = [Line2D([], [], color=color_of(lab, i), lw=2.0, label=lab.upper()) for i, (lab, _) in
                   enumerate(items)]
    ax.set_ylabel(ylabel)
    _y_scale(ax, log)
    _finish(fig, ax, x, xlabel, dt, title, handles)
    return fig


def _y_scale(ax, log: bool) -> None:
    """Log scale with plain-number labels; minor ticks labelled too when the axis spans less than a decade,
    their 2, 3 and 5 when it spans less than two."""
    if not (log and _has_positive(ax)):
        return
    from matplotlib.ticker import FuncFormatter, NullFormatter

    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    lo, hi = ax.get_ylim()

    marks = None if hi / lo < 10 else [2, 3, 5] if hi / lo < 100 else []  # None: label every minor tick

    def minor(v, _):
        mantissa = v / 10 ** np.floor(np.log10(v) + 1e-9)
        return f"{v:g}" if marks is None or np.isclose(mantissa, marks, rtol=1e-6).any() else ""

    ax.yaxis.set_minor_formatter(FuncFormatter(minor) if marks != [] else NullFormatter())


def _finish(fig, ax, x, xlabel, dt, title, handles) -> None:
    ax.set_xlabel(xlabel)
    ax.set_xlim(x[0], x[-1])
    ax.grid(True, which="major", alpha=0.3)
    ax.grid(True, which="minor", axis="y", alpha=0.1)
    if dt:
        top = ax.secondary_xaxis("top", functions=(lambda k: k * dt, lambda t: t / dt))
        top.set_xlabel("time [s]", fontsize=9)
        top.tick_params(labelsize=8)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.legend(handles=handles, loc="outside lower center", ncol=min(len(handles), 6), fontsize=8,
               frameon=False)


def _has_positive(ax) -> bool:
    for line in ax.get_lines():
        y = np.asarray(line.get_ydata(), float)
        if (np.isfinite(y) & (y > 0)).any():
            return True
    return False


def save_png(fig, path, dpi: int = 150) -> None:
    """Write ``fig`` as a PNG atomically (temporary file, then rename)."""
    from heartcv.tracker.files import atomic_path

    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
