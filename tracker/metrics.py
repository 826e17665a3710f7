"""Metrics of estimator runs over one sequence: one-step prediction error, NIS consistency, parameter
trajectories, error against ground truth and step timing (the numbers behind ``heartcv report``).

Pure functions on :class:`~tracker.measurements.EstimateSet` objects and arrays; no I/O. Conventions, chosen
to agree with the summary of ``heartcv track --json``:

- only the completed steps ``0 … completed_steps − 1`` of a (partial) run are used;
- overall errors use the steps k ≥ 1 (step 0 is the prediction from the prior, and its update the prior
  corrected by one frame: both say more about the prior than about the tracker); the per-step curves cover
  every completed step;
- the truth error of the estimate is that of the filtered (posterior) positions ``EstimateSet.filtered``; that
  of the one-step predictions is reported beside it. Both use only the observed (k, p) — the points seen at
  step k, a finite innovation — so that the filtered estimates, the predictions and the measurements
  themselves (:func:`measurement_truth_error_norms`) are compared over the same observations;
- the prediction error of point p at step k is the Euclidean norm ``|y_kp − ŷ_kp|`` of the innovation
  (m), over the points seen at that step (the paper's Fig. 4 uses the same deviation per coordinate);
- NIS statistics use every completed step with at least one point seen (step 0 included);
- step times use the steps k ≥ 1 (step 0 only updates the prior), or step 0 alone when there is one step.

The chi-square bands: a consistent filter's NIS at step k is χ²(d_k) with d_k = ``nis_dof[k]``; its per-step
two-sided ``level`` band is ``[χ²_ppf(a/2, d_k), χ²_ppf(1 − a/2, d_k)]`` (a = 1 − level). The innovations of
a consistent filter are white, so the sum of n NIS values is χ²(Σ d_k) and the time average lies in
``[χ²_ppf(a/2, Σ d_k) / n, χ²_ppf(1 − a/2, Σ d_k) / n]`` (Bar-Shalom, Li & Kirubarajan, *Estimation with
Applications to Tracking and Navigation*, 2001, §5.4).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
import zlib

import numpy as np
import scipy.linalg as sla

from .measurements import EstimateSet
from .params import NAMES

__all__ = [
    "completed",
    "error_norms",
    "per_step_stats",
    "pooled_stats",
    "nis_step_band",
    "nis_mean_band",
    "nis_statistics",
    "step_time_statistics",
    "LOG_LIKELIHOOD_KEYS",
    "log_likelihood_statistics",
    "measurement_noise_level",
    "mean_noise_norm", "mean_noise_norm_of_covariances",
    "truth_error_norms",
    "measurement_truth_error_norms",
    "times_mismatch",
    "sequence_mismatch",
    "estimator_metrics",
    "compare_runs",
    "theta_truth_agreement",
    "systole_mask",
    "truth_in_patch_frame",
    "pose_magnitude",
    "smooth_field_residual",
    "FieldPrediction",
    "field_ar_prediction",
    "heldout_neighbour_oracle",
    "optimal_block_length",
    "paired_ratio_interval",
    "BOOTSTRAP_RESAMPLES",
]


def completed(est: EstimateSet) -> int:
    """Number of usable steps of ``est`` (``completed_steps``)."""
    return int(est.completed_steps)


def error_norms(vectors) -> np.ndarray:
    """Euclidean norms over the last axis: (K, P, 3) -> (K, P) (NaN where a vector has a NaN)."""
    v = np.asarray(vectors, float)
    if v.ndim < 1 or v.shape[-1] != 3:
        raise ValueError(f"error_norms: array of shape (..., 3) expected, got {v.shape}")
    return np.sqrt(np.sum(v**2, axis=-1))


def per_step_stats(norms) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, variance (ddof 0) and count of the finite entries of each row.

    Parameters
    ----------
    norms : ndarray of shape (K, P)
        Error norms, NaN where undefined (point not seen).

    Returns
    -------
    mean, var : ndarray of shape (K,)
        NaN for a row without finite entries.
    count : ndarray of shape (K,) int
    """
    x = np.asarray(norms, float)
    if x.ndim != 2:
        raise ValueError(f"per_step_stats: array of shape (K, P) expected, got {x.shape}")
    ok = np.isfinite(x)
    n = ok.sum(axis=1)
    z = np.where(ok, x, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, z.sum(axis=1) / np.maximum(n, 1), np.nan)
        var = np.where(n > 0, np.where(ok, (x - mean[:, None]) ** 2, 0.0).sum(axis=1) / np.maximum(n, 1), np.nan)
    return mean, var, n


def pooled_stats(norms) -> dict:
    """Mean, standard deviation (ddof 0), RMS and count over all finite entries of ``norms``.

    Returns ``{'mean', 'std', 'rms', 'count'}``; NaN statistics when nothing is finite.
    """
    x = np.asarray(norms, float).ravel()
    x = x[np.isfinite(x)]
    if not x.size:
        return {"mean": np.nan, "std": np.nan, "rms": np.nan, "count": 0}
    return {"mean": float(x.mean()), "std": float(x.std()), "rms": float(np.sqrt(np.mean(x**2))),
            "count": int(x.size)}


def nis_step_band(dof, level: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """Per-step two-sided ``level`` band of a χ²(``dof``) statistic (NaN where ``dof`` < 1).

    Parameters
    ----------
    dof : array_like of int, shape (K,)
    level : float in (0, 1)
    """
    from scipy import stats

    _check_level(level)
    d = np.asarray(dof, float)
    a = 1.0 - level
    good = d >= 1
    lo = np.full(d.shape, np.nan)
    hi = np.full(d.shape, np.nan)
    lo[good] = stats.chi2.ppf(a / 2, d[good])
    hi[good] = stats.chi2.ppf(1 - a / 2, d[good])
    return lo, hi


def nis_mean_band(dof, level: float = 0.95) -> tuple[float, float]:
    """Two-sided ``level`` band of the time average of n independent χ²(d_k) statistics, d = ``dof`` (n,):
    ``[χ²_ppf(a/2, Σ d) / n, χ²_ppf(1 − a/2, Σ d) / n]``."""
    from scipy import stats

    _check_level(level)
    d = np.asarray(dof, float).ravel()
    if not d.size or (d < 1).any():
        raise ValueError(f"nis_mean_band: at least one step and dof >= 1 expected, got {d.tolist()}")
    a = 1.0 - level
    n, total = d.size, d.sum()
    return float(stats.chi2.ppf(a / 2, total) / n), float(stats.chi2.ppf(1 - a / 2, total) / n)


def _check_level(level):
    if not 0.0 < level < 1.0:
        raise ValueError(f"level: a probability in (0, 1) expected, got {level}")


def nis_statistics(nis, dof, level: float = 0.95) -> dict:
    """NIS summary over the steps with a finite NIS and dof ≥ 1.

    Returns ``{'mean', 'mean_dof', 'mean_band': (lo, hi), 'in_band_fraction', 'steps'}``: the mean NIS,
    the mean dof, the band of the mean (:func:`nis_mean_band`), the fraction of those steps whose NIS lies
    inside its per-step band (:func:`nis_step_band`, bounds included) and their count. NaN / None when no
    step qualifies.
    """
    nis = np.asarray(nis, float).ravel()
    dof = np.asarray(dof).ravel()
    if nis.shape != dof.shape:
        raise ValueError(f"nis_statistics: nis and dof of the same shape expected, got {nis.shape}, {dof.shape}")
    ok = np.isfinite(nis) & (dof >= 1)
    if not ok.any():
        return {"mean": np.nan, "mean_dof": np.nan, "mean_band": None, "in_band_fraction": np.nan, "steps": 0}
    lo, hi = nis_step_band(dof[ok], level)
    inside = (nis[ok] >= lo) & (nis[ok] <= hi)
    return {"mean": float(nis[ok].mean()), "mean_dof": float(dof[ok].mean()),
            "mean_band": nis_mean_band(dof[ok], level), "in_band_fraction": float(inside.mean()),
            "steps": int(ok.sum())}


def step_time_statistics(step_time) -> dict:
    """Median and 95th percentile (numpy's linear interpolation) of the step wall times (s) of steps k ≥ 1,
    or of step 0 alone for a single step. ``{'median', 'p95', 'steps'}``."""
    t = np.asarray(step_time, float).ravel()
    t = t[1:] if t.size > 1 else t
    t = t[np.isfinite(t)]
    if not t.size:
        return {"median": np.nan, "p95": np.nan, "steps": 0}
    return {"median": float(np.median(t)), "p95": float(np.percentile(t, 95)), "steps": int(t.size)}


def measurement_noise_level(covariances, seen=None) -> float:
    """Per-coordinate measurement noise level σ (m): the RMS over the observations of sqrt(trace(C)/3),
    i.e. ``sqrt(mean(trace(C_kp) / 3))`` over the seen (k, p).

    Parameters
    ----------
    covariances : ndarray of shape (K, P, 3, 3)
        m^2, NaN where not seen.
    seen : ndarray of shape (K, P) bool, optional
        Defaults to the finite covariances.
    """
    c = np.asarray(covariances, float)
    if c.ndim != 4 or c.shape[-2:] != (3, 3):
        raise ValueError(f"measurement_noise_level: covariances of shape (K, P, 3, 3) expected, got {c.shape}")
    tr = np.trace(c, axis1=-2, axis2=-1)
    ok = np.isfinite(tr) if seen is None else np.asarray(seen, bool) & np.isfinite(tr)
    if not ok.any():
        return float("nan")
    return float(np.sqrt(np.mean(tr[ok] / 3.0)))


def mean_noise_norm(sigma: float) -> float:
    """Mean Euclidean norm E|v| of v ~ N(0, σ² I₃): σ·sqrt(8/π) (chi distribution with 3 dof)."""
    return float(sigma * np.sqrt(8.0 / np.pi))


def mean_noise_norm_of_covariances(covariances, seen=None, chunk: int = 1024) -> float:
    """Mean over the seen (k, p) of E|v_kp|, v_kp ~ N(0, C_kp): the mean 3-D norm of the noise that the
    covariances describe, anisotropy included (a stereo point's depth noise is often ten times its lateral noise;
    :func:`mean_noise_norm` of the RMS per-coordinate σ then overstates the floor by ~15 %).

    With the eigenvalues λ_i of C, |v|² = Σ λ_i z_i² (z standard normal) and, from √q = (1/(2√π)) ∫_0^∞ (1 − e^(−tq))
    t^(−3/2) dt and E e^(−t|v|²) = Π_i (1 + 2tλ_i)^(−1/2),

        E|v| = (1/(2√π)) ∫_0^∞ (1 − Π_i (1 + 2tλ_i)^(−1/2)) t^(−3/2) dt,

    integrated over u = ln t on [−25, 25] (801 nodes, trapezoid; λ scaled to sum 1, the result by √(Σλ)): relative
    error below 1e-5 (the tails beyond ±25 hold 2e^(−12.5) of an integral of order 2√π).

    Parameters
    ----------
    covariances : ndarray of shape (..., 3, 3)
        m², NaN where not seen.
    seen : ndarray of shape (...) bool, optional
        Defaults to the finite covariances.
    """
    c = np.asarray(covariances, float)
    ok = np.isfinite(c).all(axis=(-2, -1))
    if seen is not None:
        ok &= np.asarray(seen, bool)
    cs = c[ok]
    if not len(cs):
        return float("nan")
    u = np.linspace(-25.0, 25.0, 801)
    t = np.exp(u)
    total = 0.0
    for i in range(0, len(cs), chunk):
        ev = np.clip(np.linalg.eigvalsh(cs[i:i + chunk]), 0.0, None)
        scale = ev.sum(axis=1)
        lam = ev / np.where(scale > 0, scale, 1.0)[:, None]
        log_mgf = -0.5 * np.log1p(2.0 * t[None, :, None] * lam[:, None, :]).sum(axis=2)
        f = -np.expm1(log_mgf) * np.exp(-0.5 * u)[None, :]
        total += float(np.sqrt(scale) @ np.trapezoid(f, u, axis=1))
    return total / (2.0 * np.sqrt(np.pi) * len(cs))


def truth_error_norms(positions, truth_positions) -> np.ndarray:
    """|ŷ_kp − y_kp^true| (K, P) of estimated positions (K, P, 3) (filtered or predicted) against true
    positions (K, P, 3), same frame (m)."""
    p = np.asarray(positions, float)
    t = np.asarray(truth_positions, float)
    if p.shape != t.shape or p.ndim != 3 or p.shape[-1] != 3:
        raise ValueError(f"truth_error_norms: estimates and truth of one shape (K, P, 3) expected, got "
                         f"{p.shape} and {t.shape}")
    return error_norms(p - t)


def measurement_truth_error_norms(est: EstimateSet, truth_positions) -> np.ndarray:
    """|y_kp − y_kp^true| (c, P) of the measurements themselves against the truth, over the completed steps
    (NaN where not seen). The measured position is ``predictions + innovations`` (the innovation is the
    measurement minus the prediction), in the frame of the estimate file, so the estimate file suffices."""
    c = completed(est)
    y = np.asarray(est.predictions, float)[:c] + np.asarray(est.innovations, float)[:c]
    return truth_error_norms(y, np.asarray(truth_positions, float)[:c])


def times_mismatch(times_a, times_b, rtol: float = 1e-9) -> str | None:
    """Why two frame-time arrays are not of the same sequence (``'31 vs 16 frames'``, ``'different frame
    times'``: a value differs by more than ``rtol`` of the duration, at least of 1 s), or None if they are."""
    ta, tb = np.asarray(times_a, float).ravel(), np.asarray(times_b, float).ravel()
    if ta.shape != tb.shape:
        return f"{ta.size} vs {tb.size} frames"
    if not ta.size:
        return None
    scale = max(abs(ta[-1] - ta[0]), abs(ta[-1]), 1.0)
    if not np.allclose(ta, tb, rtol=0.0, atol=rtol * scale):
        return "different frame times"
    return None


def sequence_mismatch(a: EstimateSet, b: EstimateSet, rtol: float = 1e-9) -> str | None:
    """Why two estimate sets are not of the same sequence, or None if they are: different frame times
    (:func:`times_mismatch`), different point ids, or different ``meta['inputs_hash']['measurements']`` where
    both record one."""
    why = times_mismatch(a.times, b.times, rtol)
    if why is not None:
        return why
    ia, ib = np.asarray(a.point_ids), np.asarray(b.point_ids)
    if ia.shape != ib.shape or not np.array_equal(ia, ib):
        return f"different point ids ({ia.size} vs {ib.size} points)" if ia.shape != ib.shape else \
            "different point ids"
    ha = (a.meta.get("inputs_hash") or {}).get("measurements")
    hb = (b.meta.get("inputs_hash") or {}).get("measurements")
    if ha and hb and ha != hb:
        return "different measurement files (meta inputs_hash.measurements)"
    return None


def _last_by_name(rows) -> dict:
    """The last row of a (c, 5) parameter array by name (NaN for every name when c = 0)."""
    if not len(rows):
        return dict.fromkeys(NAMES, np.nan)
    return dict(zip(NAMES, map(float, rows[-1]), strict=True))


def _seen(est: EstimateSet, c: int) -> np.ndarray:
    """(c, P) whether each point was measured in each completed step: a finite innovation, or for a baseline (no
    prediction before a point's first measurement) a finite ``filtered``, which is the measurement itself."""
    seen = np.isfinite(np.asarray(est.innovations, float)[:c]).all(axis=2)
    if est.meta.get("baseline") and est.filtered is not None:
        seen |= np.isfinite(np.asarray(est.filtered, float)[:c]).all(axis=2)
    return seen


def _fit_split(norms, held_norms, seen, fit_frames, c) -> dict:
    """The prediction error within the fitted frames (1 <= k < N) and after them (k >= N), there also over the
    observations whose track was seen in the frame before (continuing, not re-appearing after a gap); None without
    a split."""
    keys = ("prediction_error_within_fit_mean_m", "prediction_error_within_fit_count",
            "prediction_error_after_fit_mean_m", "prediction_error_after_fit_count",
            "prediction_error_after_fit_continuing_mean_m", "prediction_error_after_fit_continuing_count",
            "heldout_prediction_error_after_fit_mean_m")
    n = None if fit_frames is None else int(fit_frames)
    if n is None or not 0 < n < c:
        return dict.fromkeys(keys)
    within, after = pooled_stats(norms[1:n]), pooled_stats(norms[n:])
    cont = pooled_stats(np.where(seen[n - 1:-1], norms[n:], np.nan))
    held = pooled_stats(held_norms[n:])["mean"] if held_norms is not None else None
    return dict(zip(keys, (within["mean"], within["count"], after["mean"], after["count"], cont["mean"],
                           cont["count"], held), strict=True))


LOG_LIKELIHOOD_KEYS = ("log_likelihood_per_point", "log_likelihood_points", "log_likelihood_within_fit_per_point",
                       "log_likelihood_after_fit_per_point")


def log_likelihood_statistics(est: EstimateSet, fit_frames: int | None = None) -> dict:
    """The one-step predictive log-likelihood of a model-based run per measured point: the sum over the completed
    steps k >= 1 of log p(y_k | y_0 .. y_(k-1)) (the file's ``log_likelihood``) over the points measured in them
    (``nis_dof / 3``; held-out points are in no update), and the same within the fitted frames (1 <= k < N) and
    after them (k >= N). A proper score of the predicted distribution, mean and covariance together; the points of
    one frame count as independent given the state, as in the filters. Densities of positions in metres, so the
    values depend on the unit; only differences between runs on the same measurements compare. None for every key
    without the array (baselines, files written before it)."""
    out = dict.fromkeys(LOG_LIKELIHOOD_KEYS)
    if est.log_likelihood is None:
        return out
    c = completed(est)
    ll = np.asarray(est.log_likelihood, float)[:c]
    pts = np.asarray(est.nis_dof, float)[:c] / 3.0
    use = np.isfinite(ll) & (pts > 0)
    use[:1] = False

    def per_point(mask):
        n = float(pts[mask].sum())
        return float(ll[mask].sum() / n) if n > 0 else None

    out["log_likelihood_per_point"] = per_point(use)
    out["log_likelihood_points"] = float(pts[use].sum())
    n = None if fit_frames is None else int(fit_frames)
    if n is not None and 0 < n < c:
        k = np.arange(c)
        out["log_likelihood_within_fit_per_point"] = per_point(use & (k < n))
        out["log_likelihood_after_fit_per_point"] = per_point(use & (k >= n))
    return out


def _split_norms(est: EstimateSet) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The prediction error norms (c, P) of the completed steps of the points used in the updates and of the
    held-out points (``meta['heldout_points']``), each NaN elsewhere, and the held-out mask (P,)."""
    c = completed(est)
    norms = error_norms(np.asarray(est.innovations)[:c])
    held = np.isin(np.asarray(est.point_ids), np.asarray(est.meta.get("heldout_points") or [], dtype=np.int64))
    return np.where(held[None, :], np.nan, norms), np.where(held[None, :], norms, np.nan), held


def estimator_metrics(est: EstimateSet, truth_positions=None, level: float = 0.95, fit_frames: int | None = None
                      ) -> dict:
    """All per-run metrics of one estimate set (only its completed steps).

    Parameters
    ----------
    est : EstimateSet
    truth_positions : ndarray of shape (K, P, 3), optional
        True positions of the same points at the same times, in the frame of the predictions (m).
    level : float
        Level of the NIS bands.
    fit_frames : int, optional
        Frames 0 .. N-1 that fitted the parameters the run used (``heartcv fit --frames``): the prediction error is
        also split into the frames within the fit (1 <= k < N, in-sample) and after it (k >= N, out-of-sample).

    Returns
    -------
    dict with, in SI units: ``completed_steps``, ``prediction_error_mean_m`` / ``_std_m`` / ``_rms_m`` /
    ``_count`` (steps k ≥ 1, seen points, the held-out points of ``meta['heldout_points']`` excluded),
    ``heldout_prediction_error_mean_m`` / ``_rms_m`` / ``_count`` and ``heldout_points`` (the same over the
    held-out points only; None / 0 without), with ``fit_frames`` N (None / 0 < N < completed steps: None for all)
    ``prediction_error_within_fit_mean_m`` / ``_count`` (1 <= k < N), ``prediction_error_after_fit_mean_m`` /
    ``_count`` (k >= N), ``prediction_error_after_fit_continuing_mean_m`` / ``_count`` (k >= N, the point also
    seen at k - 1) and ``heldout_prediction_error_after_fit_mean_m``, ``truth_error_mean_m`` / ``_std_m`` /
    ``_rms_m`` (the filtered positions ``est.filtered`` against the truth: steps k ≥ 1, seen points; NaN without
    truth or without ``filtered`` in the file), ``prediction_truth_error_mean_m`` / ``_std_m`` / ``_rms_m`` (the
    one-step predictions against the truth, over the same (k, p); NaN without truth), ``nis_mean``,
    ``nis_mean_dof``, ``nis_mean_band``, ``nis_in_band_fraction``, ``theta_final``, ``theta_std_final`` (dicts
    by parameter name, last completed step; NaN if none), ``step_time_median_s``, ``step_time_p95_s``,
    ``truncation_events``, the keys of :func:`log_likelihood_statistics` (None for a run without
    ``log_likelihood``), and the per-step arrays under ``'per_step'``: ``times``, ``error_mean``,
    ``error_var``, ``error_count``, ``truth_error_mean``, ``truth_error_var`` (filtered),
    ``prediction_truth_error_mean``, ``prediction_truth_error_var``, ``nis``, ``nis_dof``, ``nis_lo``,
    ``nis_hi``, ``theta``, ``theta_std``, ``step_time``.
    """
    c = completed(est)
    norms, held_norms, held = _split_norms(est)
    mean, var, count = per_step_stats(norms)
    pooled = pooled_stats(norms[1:])
    hp = pooled_stats(held_norms[1:]) if held.any() else {"mean": None, "rms": None, "count": 0}
    out = {
        "completed_steps": c,
        "prediction_error_mean_m": pooled["mean"],
        "prediction_error_std_m": pooled["std"],
        "prediction_error_rms_m": pooled["rms"],
        "prediction_error_count": pooled["count"],
        "heldout_prediction_error_mean_m": hp["mean"],
        "heldout_prediction_error_rms_m": hp["rms"],
        "heldout_prediction_error_count": hp["count"],
        "heldout_points": int(held.sum()),
    }
    out.update(_fit_split(norms, held_norms if held.any() else None, _seen(est, c), fit_frames, c))
    out.update(log_likelihood_statistics(est, fit_frames))
    none = {"mean": np.nan, "std": np.nan, "rms": np.nan}
    f_mean = f_var = p_mean = p_var = np.full(c, np.nan)
    f_pool = p_pool = none
    if truth_positions is not None:
        truth = np.asarray(truth_positions, float)[:c]
        seen = np.isfinite(norms)  # the observed (k, p): the measurements' own truth error covers the same
        pn = np.where(seen, truth_error_norms(np.asarray(est.predictions, float)[:c], truth), np.nan)
        p_mean, p_var, _ = per_step_stats(pn)
        p_pool = pooled_stats(pn[1:])
        if est.filtered is not None:
            fn = np.where(seen, truth_error_norms(np.asarray(est.filtered, float)[:c], truth), np.nan)
            f_mean, f_var, _ = per_step_stats(fn)
            f_pool = pooled_stats(fn[1:])
    out.update(truth_error_mean_m=f_pool["mean"], truth_error_std_m=f_pool["std"], truth_error_rms_m=f_pool["rms"],
               prediction_truth_error_mean_m=p_pool["mean"], prediction_truth_error_std_m=p_pool["std"],
               prediction_truth_error_rms_m=p_pool["rms"])
    nis = np.asarray(est.nis, float)[:c]
    dof = np.asarray(est.nis_dof)[:c]
    ns = nis_statistics(nis, dof, level)
    out.update(nis_mean=ns["mean"], nis_mean_dof=ns["mean_dof"], nis_mean_band=ns["mean_band"],
               nis_in_band_fraction=ns["in_band_fraction"], nis_steps=ns["steps"])
    theta = np.asarray(est.theta, float)[:c]
    theta_std = np.asarray(est.theta_std, float)[:c]
    out.update(theta_final=_last_by_name(theta), theta_std_final=_last_by_name(theta_std))
    st = step_time_statistics(np.asarray(est.step_time, float)[:c])
    out.update(step_time_median_s=st["median"], step_time_p95_s=st["p95"],
               truncation_events=int(np.asarray(est.truncation_events)[:c].sum()))
    lo, hi = nis_step_band(dof, level)
    out["per_step"] = {
        "times": np.asarray(est.times, float)[:c], "error_mean": mean, "error_var": var, "error_count": count,
        "truth_error_mean": f_mean, "truth_error_var": f_var, "prediction_truth_error_mean": p_mean,
        "prediction_truth_error_var": p_var, "nis": nis, "nis_dof": dof, "nis_lo": lo, "nis_hi": hi,
        "theta": theta, "theta_std": theta_std, "step_time": np.asarray(est.step_time, float)[:c],
    }
    return out


# -- confidence intervals of error ratios (a circular block bootstrap over frames) ---------------------------------
#: Bootstrap resamples of :func:`paired_ratio_interval` (``heartcv report --resamples``)
BOOTSTRAP_RESAMPLES = 2000


def optimal_block_length(x) -> float:
    """The block length (in samples, >= 1) of a circular block bootstrap of the mean of the series ``x``, chosen
    automatically: Politis & White (2004, Econometric Reviews 23:53-70) with the correction of Patton, Politis &
    White (2009, Econometric Reviews 28:372-375).

    With R(k) the sample autocovariances, the flat-top kernel ``lam(t) = 1`` for ``|t| <= 1/2``, ``2 (1 - |t|)``
    for ``1/2 < |t| <= 1``, and M twice the smallest lag m after which ``K_N = max(5, floor(sqrt(log10 n)))``
    consecutive autocorrelations are all below ``2 sqrt(log10 n / n)`` (at most ``ceil(sqrt n) + K_N``):
    ``G = sum_{|k|<=M} lam(k/M) |k| R(k)``, ``g = sum_{|k|<=M} lam(k/M) R(k)``, ``D = (4/3) g^2`` and
    ``b = (2 G^2 / D)^(1/3) n^(1/3)``, capped at ``min(3 sqrt n, n / 3)``. A white series gives 1; an AR(1)
    with coefficient phi tends to ``(6 phi^2 / (1 - phi^2)^2)^(1/3) n^(1/3)``.
    """
    x = np.asarray(x, float).reshape(-1)
    n = x.size
    if n < 4:
        return 1.0
    e = x - x.mean()
    r0 = float(e @ e) / n
    if not r0 > 0:
        return 1.0
    kn = max(5, int(np.sqrt(np.log10(n))))
    m_max = min(int(np.ceil(np.sqrt(n))) + kn, n - 1)
    acv = np.array([float(e[k:] @ e[:n - k]) / n for k in range(m_max + 1)])
    rho = np.abs(acv / r0)
    threshold = 2.0 * np.sqrt(np.log10(n) / n)
    m_hat = next((m for m in range(m_max - kn + 1) if (rho[m + 1:m + 1 + kn] < threshold).all()), None)
    M = m_max if m_hat is None else min(2 * max(m_hat, 1), m_max)
    k = np.arange(1, M + 1)
    lam = np.where(k / M <= 0.5, 1.0, 2.0 * (1.0 - k / M))
    G = 2.0 * float(np.sum(lam * k * acv[1:M + 1]))
    g = r0 + 2.0 * float(np.sum(lam * acv[1:M + 1]))
    if not g > 0:
        return 1.0
    b = (2.0 * G * G / (4.0 / 3.0 * g * g)) ** (1.0 / 3.0) * n ** (1.0 / 3.0)
    return float(np.clip(b, 1.0, max(1.0, min(3.0 * np.sqrt(n), n / 3.0))))


def paired_ratio_interval(numerator, denominator, rng: np.random.Generator, *, level: float = 0.95,
                          resamples: int = BOOTSTRAP_RESAMPLES, block: float | None = None) -> dict | None:
    """The ratio of two runs' mean errors over the observations both have, with a bootstrap confidence interval.

    Parameters
    ----------
    numerator, denominator : ndarray (K, P)
        Error norms of two runs on the same points and frames (NaN where a run has none); the rows are the frames
        to use (e.g. k >= 1).
    rng : numpy.random.Generator
    level : float
        Two-sided level of the percentile interval.
    resamples : int
        Bootstrap resamples (>= 100).
    block : float, optional
        Block length in frames; default :func:`optimal_block_length` of the ratio's linearisation
        ``A_k - r B_k`` (A_k, B_k the frame sums of the two errors, r the ratio).

    The frames are resampled, not the points: the errors of one frame share its motion, and those of nearby frames
    are correlated (a heartbeat, a drifting view), so frames are drawn in circular blocks of consecutive frames
    (Politis & Romano 1992), which keeps that correlation inside a block. Each resample's ratio is
    ``sum A* / sum B*``; the interval is its ``(1 - level)/2`` and ``(1 + level)/2`` quantiles. It covers the
    uncertainty from the frames observed, not that from which tracks were measured or held out.

    Returns
    -------
    dict or None
        ``ratio``, ``low``, ``high``, ``level``, ``block_frames``, ``resamples``, ``frames`` and ``observations``
        (the common (k, p)); None when no observation is common or the denominator's errors sum to zero.
    """
    _check_level(level)
    a, b = np.asarray(numerator, float), np.asarray(denominator, float)
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError(f"numerator, denominator: (K, P) arrays of one shape expected, got {a.shape}, {b.shape}")
    resamples = int(resamples)
    if resamples < 100:
        raise ValueError(f"resamples: at least 100 expected, got {resamples}")
    common = np.isfinite(a) & np.isfinite(b)
    A, B = np.where(common, a, 0.0).sum(axis=1), np.where(common, b, 0.0).sum(axis=1)
    K = A.size
    if not common.any() or not B.sum() > 0:
        return None
    ratio = float(A.sum() / B.sum())
    length = optimal_block_length(A - ratio * B) if block is None else float(block)
    if not (np.isfinite(length) and length >= 1):
        raise ValueError(f"block: a length of at least 1 frame expected, got {block}")
    L = min(int(round(length)), K)
    n_blocks = -(-K // L)
    starts = rng.integers(0, K, size=(resamples, n_blocks))
    idx = ((starts[:, :, None] + np.arange(L)[None, None, :]) % K).reshape(resamples, -1)[:, :K]
    num, den = A[idx].sum(axis=1), B[idx].sum(axis=1)
    ok = den > 0
    boot = num[ok] / den[ok]
    lo, hi = np.quantile(boot, [(1.0 - level) / 2.0, (1.0 + level) / 2.0])
    return {"ratio": ratio, "low": float(lo), "high": float(hi), "level": float(level), "block_frames": L,
            "resamples": resamples, "frames": int(K), "observations": int(common.sum()),
            # observations one run predicted and the other did not (NaN): a run that leaves out hard observations
            # is compared on the easier rest, so the report warns when the numerator lacks some
            "numerator_missing": int((np.isfinite(b) & ~np.isfinite(a)).sum()),
            "denominator_missing": int((np.isfinite(a) & ~np.isfinite(b)).sum())}


def _ratio(a, b) -> float | None:
    """``a / b`` for finite a and finite positive b, else None."""
    if a is None or b is None or not (np.isfinite(a) and np.isfinite(b) and b > 0):
        return None
    return float(a / b)


def systole_mask(pressure) -> np.ndarray:
    """The frames of systole (K,) bool from a ventricular pressure (K,): the pressure above the midpoint of its
    range over the sequence (isovolumic contraction, ejection and the start of relaxation: the high-pressure
    phase); diastole is the rest. All False for a pressure that does not vary (or is not finite anywhere)."""
    p = np.asarray(pressure, float).reshape(-1)
    ok = np.isfinite(p)
    if not ok.any():
        return np.zeros(p.size, bool)
    lo, hi = p[ok].min(), p[ok].max()
    if not hi > lo:
        return np.zeros(p.size, bool)
    return ok & (p > 0.5 * (lo + hi))


def theta_truth_agreement(theta, theta_std, truth_theta, estimated, *, first: int = 1) -> dict:
    """How well estimated parameter trajectories follow the true ones (issue 15).

    For each name in ``estimated`` (the parameters the run estimated), over the steps ``first .. K-1`` where both
    the estimate and the truth are finite (step 0 is the prior's):

    * ``correlation``: the Pearson correlation of the estimate with the truth over time; ``None`` where either
      trajectory is constant (a KF's theta, a constant-stiffness truth): a correlation is then undefined;
    * ``coverage_2sigma``: the fraction of those steps with ``|theta_k - truth_k| <= 2 theta_std_k`` (the truth
      inside the estimate's +-2 sigma band; 0.954 expected of a consistent Gaussian estimate).

    Parameters
    ----------
    theta, theta_std : ndarray (K, 5)        the run's parameters and their std (SI)
    truth_theta : ndarray (K_t, 5)           true parameters per step (the first ``min(K, K_t)`` steps are used)
    estimated : sequence of str              names in :data:`tracker.params.NAMES`

    Returns
    -------
    dict ``{"correlation": {name: float | None}, "coverage_2sigma": {name: float | None}}``
    """
    theta = np.asarray(theta, float)
    sd = np.asarray(theta_std, float)
    truth = np.asarray(truth_theta, float)
    K = min(len(theta), len(truth))
    corr, cover = {}, {}
    for name in estimated:
        i = NAMES.index(name)
        a, b, s = theta[first:K, i], truth[first:K, i], sd[first:K, i]
        ok = np.isfinite(a) & np.isfinite(b) & np.isfinite(s)
        if not ok.any():
            corr[name] = cover[name] = None
            continue
        a, b, s = a[ok], b[ok], s[ok]
        scale = max(np.abs(b).max(), np.abs(a).max(), 1e-300)
        flat = np.ptp(a) <= 1e-12 * scale or np.ptp(b) <= 1e-12 * scale
        corr[name] = None if flat or a.size < 3 else float(np.corrcoef(a, b)[0, 1])
        cover[name] = float(np.mean(np.abs(a - b) <= 2.0 * s))
    return {"correlation": corr, "coverage_2sigma": cover}


def compare_runs(runs: dict, truth_positions: dict | None = None, truth_theta=None, level: float = 0.95,
                 fit_frames: int | None = None, rng: np.random.Generator | None = None,
                 resamples: int = BOOTSTRAP_RESAMPLES) -> dict:
    """The metrics of several runs over one sequence (the numbers of ``heartcv report``'s metrics.json).

    Parameters
    ----------
    runs : dict of {label: EstimateSet}
        In report order; the first is the reference of the sequence summary.
    truth_positions : dict of {label: ndarray (K, P, 3)}, optional
        True positions of each run's points where known (frame of the predictions, m).
    truth_theta : ndarray (K, 5) or dict of {label: ndarray (K, 5)}, optional
        True parameters per frame (SI): of every run, or by run (a run missing from the dict has none).
    level : float
        Level of the NIS bands.
    fit_frames : int, optional
        The fitted frames, one split for every run (:func:`estimator_metrics`).
    rng : numpy.random.Generator, optional
        With it, the error ratios get 95 % bootstrap intervals (:func:`paired_ratio_interval`, ``resamples``).

    Returns
    -------
    dict
        ``per_run``: label -> :func:`estimator_metrics` plus ``measurement_truth_error_mean_m`` (the
        measurements' own truth error over the observations k >= 1, :func:`measurement_truth_error_norms`; NaN
        without truth) and ``theta_truth_final`` (the truth's theta at the run's last completed step, by name;
        None without a truth of that length), ``theta_truth_correlation`` and ``theta_truth_coverage_2sigma``
        (by estimated parameter, :func:`theta_truth_agreement`; None without a truth); ``sequence``:
        ``frames``, ``duration_s``, ``points``, ``dt_s`` (median frame interval, None for one frame) and
        ``mixed`` (some run is of another sequence, :func:`sequence_mismatch`);
        ``measurement_truth_error_mean_m`` (of the first run that has one, else None);
        ``ratio_ge_to_kf_prediction_error`` and ``ratio_ge_to_kf_truth_error`` (runs labelled ``ge`` and
        ``kf``; None without both or a non-positive denominator); ``difference_ge_minus_kf_log_likelihood_per_point``
        (the GE's :func:`log_likelihood_statistics` per point minus the KF's, None unless both ran their updates on
        the same number of points); ``fit_frames`` (as given). With ``rng``: per run ``ratio_to_hold_interval`` and
        ``heldout_ratio_to_hold_interval`` (its error over the observations it shares with the run labelled
        ``hold``, of the points used in the updates and of the held-out points, frames k >= 1), and
        ``ratio_ge_to_kf_prediction_error_interval``, each a :func:`paired_ratio_interval` or None (no such run,
        other points, nothing in common); without ``rng`` these keys are None.
    """
    truth_positions = truth_positions or {}
    per = {}
    by_run = truth_theta if isinstance(truth_theta, dict) else {label: truth_theta for label in runs}
    for label, est in runs.items():
        pos = truth_positions.get(label)
        truth_theta = by_run.get(label)
        m = estimator_metrics(est, pos, level, fit_frames)
        m["measurement_truth_error_mean_m"] = (pooled_stats(measurement_truth_error_norms(est, pos)[1:])["mean"]
                                               if pos is not None else np.nan)
        c = completed(est)
        m["theta_truth_final"] = (dict(zip(NAMES, map(float, np.asarray(truth_theta, float)[c - 1]), strict=True))
                                  if truth_theta is not None and 0 < c <= len(truth_theta) else None)
        agree = (theta_truth_agreement(np.asarray(est.theta)[:c], np.asarray(est.theta_std)[:c], truth_theta,
                                       est.meta.get("estimated") or [])
                 if truth_theta is not None and c > 1 else {"correlation": None, "coverage_2sigma": None})
        m["theta_truth_correlation"] = agree["correlation"]
        m["theta_truth_coverage_2sigma"] = agree["coverage_2sigma"]
        per[label] = m
    first = next(iter(runs.values()))
    t = np.asarray(first.times, float)
    own = [v for m in per.values() if np.isfinite(v := m["measurement_truth_error_mean_m"])]

    def ratio(key):
        ge, kf = per.get("ge"), per.get("kf")
        return None if ge is None or kf is None else _ratio(ge[key], kf[key])

    def ll_difference():
        ge, kf = per.get("ge"), per.get("kf")
        if ge is None or kf is None or ge["log_likelihood_per_point"] is None or kf["log_likelihood_per_point"] is None:
            return None
        if ge["log_likelihood_points"] != kf["log_likelihood_points"]:
            return None
        return ge["log_likelihood_per_point"] - kf["log_likelihood_per_point"]

    intervals = _ratio_intervals(runs, rng, resamples)
    after = _after_fit_ratios_to_hold(runs, fit_frames)
    for label, m in per.items():
        m["ratio_to_hold_interval"], m["heldout_ratio_to_hold_interval"] = intervals["hold"].get(label, (None, None))
        m["prediction_error_after_fit_ratio_to_hold"] = after.get(label)
    return {
        "per_run": per,
        "sequence": {"frames": int(t.size), "duration_s": float(t[-1] - t[0]), "points": int(first.point_ids.size),
                     "points_left_out": len(first.meta.get("left_out_points") or []),
                     "dt_s": float(np.median(np.diff(t))) if t.size > 1 else None,
                     "mixed": any(sequence_mismatch(first, est) is not None for est in runs.values())},
        "measurement_truth_error_mean_m": own[0] if own else None,
        "ratio_ge_to_kf_prediction_error": ratio("prediction_error_mean_m"),
        "ratio_ge_to_kf_truth_error": ratio("truth_error_mean_m"),
        "difference_ge_minus_kf_log_likelihood_per_point": ll_difference(),
        "ratio_ge_to_kf_prediction_error_interval": intervals["ge_kf"],
        "fit_frames": None if fit_frames is None else int(fit_frames),
    }


def _paired_norms(runs: dict) -> tuple[dict, callable]:
    """The error norms of steps k >= 1 per run, ``{label: (used (K-1, P), held out (K-1, P))}``, and
    ``comparable(x, y)``: whether two runs can be paired observation by observation (the same sequence, points,
    frames and held-out tracks; another --holdout or --seed holds out other tracks; runs of other recordings given
    with ``report --allow-mixed`` are never paired)."""
    norms, keys = {}, {}
    for label, est in runs.items():
        used, held, _ = _split_norms(est)
        norms[label] = (used[1:], held[1:])
        keys[label] = (np.asarray(est.point_ids).tobytes(), used.shape,
                       frozenset(int(i) for i in (est.meta.get("heldout_points") or [])))
    return norms, lambda x, y: keys[x] == keys[y] and sequence_mismatch(runs[x], runs[y]) is None


def _after_fit_ratios_to_hold(runs: dict, fit_frames: int | None) -> dict:
    """``{label: ratio}``: each run's mean prediction error from frame ``fit_frames`` on over hold's, on the
    observations both predicted (a track's first sighting, which hold cannot predict, left out of both); empty
    without a hold run or a split."""
    if "hold" not in runs or fit_frames is None or fit_frames < 1:
        return {}
    norms, comparable = _paired_norms(runs)
    den = norms["hold"][0][fit_frames - 1:]
    out = {}
    for label in runs:
        if label == "hold" or not comparable(label, "hold"):
            continue
        num = norms[label][0][fit_frames - 1:]
        both = np.isfinite(num) & np.isfinite(den)
        if both.any() and den[both].mean() > 0:
            out[label] = float(num[both].mean() / den[both].mean())
    return out


def _ratio_intervals(runs: dict, rng, resamples) -> dict:
    """``{"hold": {label: (interval used, interval held out)}, "ge_kf": interval}`` of :func:`compare_runs`;
    empty / None without ``rng``. Runs are paired only on the same points (point ids), frames and held-out tracks.
    Each pair draws its resamples from its own stream (``rng``'s first draw and the pair's names): an interval
    does not move with the other files given."""
    out = {"hold": {}, "ge_kf": None}
    if rng is None:
        return out
    norms, comparable = _paired_norms(runs)
    root = int(rng.integers(2**63))

    def pair(x, y, i):
        if not comparable(x, y):
            return None
        stream = np.random.default_rng([root, zlib.crc32(f"{x}\0{y}\0{i}".encode())])
        return paired_ratio_interval(norms[x][i], norms[y][i], stream, resamples=resamples)

    if "hold" in runs:
        out["hold"] = {label: (pair(label, "hold", 0), pair(label, "hold", 1)) for label in runs if label != "hold"}
    if "ge" in runs and "kf" in runs:
        out["ge_kf"] = pair("ge", "kf", 0)
    return out


def _apply(T, X) -> np.ndarray:
    T = np.asarray(T, float)
    return np.asarray(X, float) @ T[:3, :3].T + T[:3, 3]


def truth_in_patch_frame(true_positions, truth_from_rig, measured_ids, point_ids, patch_from_rig) -> np.ndarray:
    """True trajectories of an estimate file's points in its patch frame, from a render truth.

    Parameters
    ----------
    true_positions : ndarray (K, P_meas, 3)
        True positions of the measured points (rig measurement file's order) in the truth's world frame.
    truth_from_rig : ndarray (4, 4)
        The gauge between the calibrated rig frame and the truth's frame (fitted to the birth positions).
    measured_ids : ndarray (P_meas,)
        Point ids of the measurement file.
    point_ids : ndarray (P,)
        Point ids of the estimate file.
    patch_from_rig : ndarray (4, 4)
        The registration the estimate file records.

    Returns
    -------
    ndarray (K, P, 3)
        NaN for a point that is not in the measurement file.
    """
    true_rig = _apply(np.linalg.inv(np.asarray(truth_from_rig, float)), true_positions)
    col = {int(i): j for j, i in enumerate(np.asarray(measured_ids).ravel())}
    idx = np.array([col.get(int(i), -1) for i in np.asarray(point_ids).ravel()], int)
    have = idx >= 0
    out = np.full((true_rig.shape[0], idx.size, 3), np.nan)
    if have.any():
        out[:, have] = _apply(patch_from_rig, true_rig[:, idx[have]])
    return out


def pose_magnitude(T) -> tuple[float, float]:
    """Rotation angle (deg) and translation length (m) of a rigid transform (4, 4)."""
    T = np.asarray(T, float)
    cos = np.clip((np.trace(T[:3, :3]) - 1) / 2, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos))), float(np.linalg.norm(T[:3, 3]))


def smooth_field_residual(positions, degree: int = 2, min_points: int = 30, lag: int = 1) -> np.ndarray:
    """How much of the tracks' motion no smooth displacement field explains: per frame, the mean norm of what a
    polynomial field leaves of the points' displacements over the last ``lag`` frames.

    At frame k, the displacement ``d_p = y_k,p - y_(k-lag),p`` of every point seen in both frames is fitted by least
    squares with a polynomial of total degree ``degree`` in the two principal in-plane coordinates (of all
    positions) of its position at ``k - lag`` (degree 2: 6 coefficients per axis; a fresh field every frame). The
    residual holds the measurement noise of both frames (for noise N(0, σ² I₃) its mean norm is √2 σ √(8/π), less
    the field's share of the degrees of freedom) plus the motion no smooth field explains: motion finer than the
    field, per-point drift or sliding over the lag, jumps. With ``lag = 1`` it bounds the per-frame noise from above.

    Displacements over a common interval: a field of the displacement since each point's own first frame would
    also count, for points born at different frames, the motion between their births as misfit.

    Parameters
    ----------
    positions : (K, P, 3) with NaN where unseen (any frame, m)
    degree : int, 0..3
    min_points : int    frames with fewer points seen in both frames get NaN
    lag : int >= 1      frames between the two positions

    Returns
    -------
    (K,) mean residual norm per frame (m); NaN for the first ``lag`` frames and frames with too few points.
    """
    y = np.asarray(positions, float)
    if y.ndim != 3 or y.shape[2] != 3:
        raise ValueError(f"positions: (K, P, 3) expected, got {y.shape}")
    if not 0 <= int(degree) <= 3:
        raise ValueError(f"degree: 0..3 expected, got {degree}")
    if int(lag) < 1:
        raise ValueError(f"lag: at least 1 expected, got {lag}")
    K, P, _ = y.shape
    L = int(lag)
    seen = np.isfinite(y).all(axis=2)
    X = y[seen]
    c = X.mean(axis=0) if X.size else np.zeros(3)
    Vt = np.linalg.svd(X - c, full_matrices=False)[2] if X.shape[0] >= 3 else np.eye(3)
    powers = [(i, j) for i in range(int(degree) + 1) for j in range(int(degree) + 1 - i)]
    out = np.full(K, np.nan)
    for k in range(L, K):
        ok = seen[k] & seen[k - L]
        if ok.sum() < max(int(min_points), len(powers) + 1):
            continue
        uv = (y[k - L, ok] - c) @ Vt[:2].T
        A = np.stack([uv[:, 0] ** i * uv[:, 1] ** j for i, j in powers], axis=1)
        scale = np.abs(A).max(axis=0)
        scale[scale == 0] = 1.0
        D = y[k, ok] - y[k - L, ok]
        coef, *_ = np.linalg.lstsq(A / scale, D, rcond=None)
        out[k] = float(np.linalg.norm(D - (A / scale) @ coef, axis=1).mean())
    return out


@dataclass(frozen=True)
class FieldPrediction:
    """Result of :func:`field_ar_prediction`: per frame (K,), the mean norm over the points seen in this and the
    previous frame of the prediction error of ``hold`` (the last position), of the autoregressive field predictor,
    and of the true field (an oracle that knows the frame's best field, :func:`smooth_field_residual` at lag 1);
    NaN before ``start`` and where a frame cannot be scored."""

    hold: np.ndarray
    predicted: np.ndarray
    oracle: np.ndarray
    order: int
    ridge: float

    def ratio(self) -> float:
        """Mean predicted error over mean hold error, over the frames scored."""
        ok = np.isfinite(self.predicted) & np.isfinite(self.hold)
        return float(np.mean(self.predicted[ok]) / np.mean(self.hold[ok])) if ok.any() else float("nan")


def _field_basis(uv, powers):
    return np.stack([uv[:, 0] ** i * uv[:, 1] ** j for i, j in powers], axis=1)


def field_ar_prediction(positions, order: int = 6, ridge: float = 1.0, degree: int = 2, start: int = 60,
                        min_points: int = 30) -> FieldPrediction:
    """How predictable the tracks' smooth motion is without any physics: a causal autoregressive predictor of the
    per-frame polynomial displacement field, as a reference for the estimators on a recording without ground truth.

    Per frame k the displacement of the points seen at k-1 and k is fitted by a polynomial field of total degree
    ``degree`` in the principal in-plane coordinates of their positions at k-1 (coordinates centred and scaled by
    their RMS, both over the frames before ``start``, so the coefficients c_k (n, 3) compare across frames). At frame
    k >= ``start`` the coefficients are predicted as ``c_k = sum_i W_i c_(k-i)``, i = 1 .. ``order``, with W fitted
    by ridge regression to the frames before k only (rows with every lag known; the penalty ``ridge`` times the mean
    diagonal of the normal matrix). A point is then predicted at ``y_(k-1) + A c_k``. The fine motion the field
    misses is predicted as zero, as by ``hold``. It is a data-driven reference, not an estimator: W has
    ``order x (3 n)^2`` coefficients, refitted at every frame.

    Parameters
    ----------
    positions : (K, P, 3) with NaN where unseen (m)
    order : int >= 1
    ridge : float >= 0     relative ridge penalty
    degree : int, 0..3
    start : int            first frame predicted (the frames before it train the first prediction)
    min_points : int       frames with fewer points seen in both frames are not fitted nor scored
    """
    y = np.asarray(positions, float)
    if y.ndim != 3 or y.shape[2] != 3:
        raise ValueError(f"positions: (K, P, 3) expected, got {y.shape}")
    if not 0 <= int(degree) <= 3:
        raise ValueError(f"degree: 0..3 expected, got {degree}")
    if int(order) < 1 or not ridge >= 0 or int(start) < int(order) + 2:
        raise ValueError(f"order >= 1, ridge >= 0 and start >= order + 2 expected, got {order}, {ridge}, {start}")
    K = y.shape[0]
    p = int(order)
    seen = np.isfinite(y).all(axis=2)
    X = y[:int(start)][seen[:int(start)]]       # the coordinate frame from the frames before the first prediction
    c0 = X.mean(axis=0) if X.size else np.zeros(3)
    Vt = np.linalg.svd(X - c0, full_matrices=False)[2] if X.shape[0] >= 3 else np.eye(3)
    uv_all = (X - c0) @ Vt[:2].T
    scale = float(np.sqrt(np.mean(uv_all ** 2))) if uv_all.size else 1.0
    scale = scale if scale > 0 else 1.0
    powers = [(i, j) for i in range(int(degree) + 1) for j in range(int(degree) + 1 - i)]
    n = len(powers)
    coef = np.full((K, n * 3), np.nan)
    frames = {}
    for k in range(1, K):
        ok = seen[k] & seen[k - 1]
        if ok.sum() < max(int(min_points), n + 1):
            continue
        A = _field_basis((y[k - 1, ok] - c0) @ Vt[:2].T / scale, powers)
        D = y[k, ok] - y[k - 1, ok]
        c, *_ = np.linalg.lstsq(A, D, rcond=None)
        coef[k] = c.reshape(-1)
        frames[k] = (A, D)
    hold, pred, oracle = np.full(K, np.nan), np.full(K, np.nan), np.full(K, np.nan)
    lagged = np.full((K, p * n * 3), np.nan)
    for k in range(p + 1, K):
        lagged[k] = np.concatenate([coef[k - i] for i in range(1, p + 1)])
    # the normal equations over the rows before k, accumulated as k advances (O(K), not a refit over all k rows)
    good = np.isfinite(lagged).all(axis=1) & np.isfinite(coef).all(axis=1)
    ZtZ = np.zeros((lagged.shape[1], lagged.shape[1]))
    ZtT = np.zeros((lagged.shape[1], coef.shape[1]))
    count, added = 0, 0
    for k in range(int(start), K):
        while added < k:
            if good[added]:
                ZtZ += np.outer(lagged[added], lagged[added])
                ZtT += np.outer(lagged[added], coef[added])
                count += 1
            added += 1
        if k not in frames or not np.isfinite(lagged[k]).all():
            continue
        if count < 2:
            continue
        G = ZtZ.copy()
        G[np.diag_indices_from(G)] += ridge * float(np.mean(np.diag(G)))
        W = None
        if ridge > 0:      # G + ridge I is positive definite: a Cholesky solve, not an SVD per frame
            try:
                W = sla.cho_solve(sla.cho_factor(G, check_finite=False), ZtT, check_finite=False)
            except np.linalg.LinAlgError:
                W = None
        if W is None:
            W = np.linalg.lstsq(G, ZtT, rcond=None)[0]
        A, D = frames[k]
        c_hat = (lagged[k] @ W).reshape(n, 3)
        hold[k] = float(np.linalg.norm(D, axis=1).mean())
        pred[k] = float(np.linalg.norm(D - A @ c_hat, axis=1).mean())
        oracle[k] = float(np.linalg.norm(D - A @ coef[k].reshape(n, 3), axis=1).mean())
    return FieldPrediction(hold, pred, oracle, p, float(ridge))


def heldout_neighbour_oracle(positions, heldout, neighbours: int = 8, min_points: int = 30):
    """What other points' motion says about a held-out point, at best: an oracle (not causal) for the held-out
    prediction error of a recording without ground truth.

    A held-out point p seen at frame k, first seen at frame b < k, is predicted at ``y_b,p`` plus the mean
    displacement from b to k of its ``neighbours`` nearest points (at frame b) among the points not held out that are
    seen at both b and k, in the very frame k predicted. Any model that infers an unseen point from the motion of
    the others (a smooth or a local field) has the same information at most. Returned beside ``hold``'s error (the
    point's own previous position) on the same observations: those seen at k and k-1.

    Parameters
    ----------
    positions : (K, P, 3) with NaN where unseen (m)
    heldout : (P,) bool or indices of the held-out points
    neighbours : int >= 1
    min_points : int         frames with fewer candidate neighbours are skipped

    Returns
    -------
    (oracle, hold) : mean error norms (m) over the same observations; NaN when there are none
    """
    from scipy.spatial import cKDTree

    y = np.asarray(positions, float)
    if y.ndim != 3 or y.shape[2] != 3:
        raise ValueError(f"positions: (K, P, 3) expected, got {y.shape}")
    K, P, _ = y.shape
    h = np.asarray(heldout)
    if h.dtype == bool and h.shape != (P,):
        raise ValueError(f"heldout: a mask of shape ({P},) or point indices expected, got shape {h.shape}")
    ho = h if h.dtype == bool else np.isin(np.arange(P), h.astype(int))
    if int(neighbours) < 1:
        raise ValueError(f"neighbours: at least 1 expected, got {neighbours}")
    seen = np.isfinite(y).all(axis=2)
    birth = np.where(seen.any(axis=0), np.argmax(seen, axis=0), K)
    err_o, err_h = [], []
    for k in range(1, K):
        h = np.flatnonzero(ho & seen[k] & seen[k - 1] & (birth < k))
        for b in np.unique(birth[h]):
            hp = h[birth[h] == b]
            cand = np.flatnonzero(~ho & seen[k] & seen[b])
            if cand.size < max(int(min_points), int(neighbours)):
                continue
            _, idx = cKDTree(y[b, cand]).query(y[b, hp], k=int(neighbours))
            idx = idx.reshape(hp.size, -1)
            moved = (y[k, cand] - y[b, cand])[idx].mean(axis=1)
            err_o.append(np.linalg.norm(y[b, hp] + moved - y[k, hp], axis=1))
            err_h.append(np.linalg.norm(y[k, hp] - y[k - 1, hp], axis=1))
    if not err_o:
        return float("nan"), float("nan")
    return float(np.concatenate(err_o).mean()), float(np.concatenate(err_h).mean())


RATE_WINDOW_S = 6.0
"""Length of the windows in which :func:`windowed_heart_rate` takes the tracks' own heart rate (s): at least three
beats down to 30 bpm, short enough to see a rate change over a minute."""

RATE_STEP_S = 3.0
"""Step between those windows (s): half a window, so each frame lies in two."""


def windowed_heart_rate(times, positions, window_s: float = RATE_WINDOW_S, step_s: float = RATE_STEP_S,
                        band=None) -> list:
    """The tracks' own heart rate over sliding windows, with no model: :func:`tracker.unknown_input.
    estimate_heart_rate` (the estimator of ``heartcv fit``: spectral peak, refined by a harmonic fit, with its
    standard error) on the frames of each window ``[t0, t0 + window_s)``, t0 = first time, + ``step_s``, ... while
    the window fits in the recording.

    Returns a list of dicts ``{'t_start_s', 't_end_s', 'frequency_hz', 'std_hz', 'peak_prominence', 'reason'}``: the
    rate, its standard error and its spectral peak's prominence (:func:`tracker.unknown_input.peak_prominence`;
    below :data:`tracker.unknown_input.PEAK_PROMINENCE` the rate may be drift's) (``reason`` None), or None for
    them and ``reason`` why the window shows no clear heartbeat. Empty when the recording is shorter than one
    window. ``band``: the heart rates searched (Hz; default :data:`tracker.unknown_input.BAND_HZ`, as ``heartcv fit
    --heart-rate-band``)."""
    from .unknown_input import BAND_HZ, HARMONICS, NoHeartbeat, estimate_heart_rate

    band = BAND_HZ if band is None else tuple(band)

    t = np.asarray(times, float)
    y = np.asarray(positions, float)
    if y.ndim != 3 or y.shape[2] != 3 or y.shape[0] != t.size:
        raise ValueError(f"positions: (K, P, 3) with K = {t.size} expected, got {y.shape}")
    if not (window_s > 0 and step_s > 0):
        raise ValueError(f"window_s and step_s must be positive, got {window_s} and {step_s}")
    out = []
    if t.size < 2:
        return out
    dt = float(np.median(np.diff(t)))
    start = float(t[0])
    while start + window_s <= t[-1] + dt + 1e-9 * window_s:
        sel = (t >= start - 1e-9 * window_s) & (t < start + window_s - 1e-9 * window_s)
        entry = {"t_start_s": start, "t_end_s": start + window_s, "frequency_hz": None, "std_hz": None,
                 "peak_prominence": None, "reason": None}
        try:
            hr = estimate_heart_rate(t[sel], y[sel], HARMONICS, band)
            entry["frequency_hz"], entry["std_hz"] = float(hr.frequency_hz), float(hr.std_hz)
            entry["peak_prominence"] = float(hr.prominence) if math.isfinite(hr.prominence) else None
        except NoHeartbeat as exc:
            entry["reason"] = str(exc)
        out.append(entry)
        start += step_s
    return out


def rate_agreement(windows: list, times, mean_hz, std_hz, z: float = 2.0) -> dict | None:
    """How a run's heart rate (per frame: posterior mean ``mean_hz`` and standard deviation ``std_hz``, (K,); a
    constant for a run that holds it) agrees with the tracks' own rate in ``windows`` (:func:`windowed_heart_rate`).

    Per window with a rate: the run's mean rate over the window's frames ``f̄`` and its mean standard deviation
    ``s̄``; the window agrees when ``|f̄ - f_w| <= z sqrt(s̄² + σ_w²)``. Returns ``{'windows', 'agree', 'z',
    'mean_abs_difference_hz', 'max_abs_difference_hz'}``, or None when no window has a rate (or none overlaps the
    run's frames)."""
    t = np.asarray(times, float)
    m = np.asarray(mean_hz, float)
    s = np.asarray(std_hz, float)
    diffs, agree = [], 0
    for w in windows:
        if w.get("frequency_hz") is None:
            continue
        sel = (t >= w["t_start_s"]) & (t < w["t_end_s"]) & np.isfinite(m)
        if not sel.any():
            continue
        f_run = float(np.mean(m[sel]))
        s_run = float(np.mean(np.where(np.isfinite(s[sel]), s[sel], 0.0)))
        s_w = w["std_hz"] if w.get("std_hz") is not None and np.isfinite(w["std_hz"]) else 0.0
        d = abs(f_run - float(w["frequency_hz"]))
        diffs.append(d)
        agree += bool(d <= z * np.hypot(s_run, s_w))
    if not diffs:
        return None
    return {"windows": len(diffs), "agree": int(agree), "z": float(z),
            "mean_abs_difference_hz": float(np.mean(diffs)), "max_abs_difference_hz": float(np.max(diffs))}
