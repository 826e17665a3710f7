"""Baselines that need no physics (issue 16): per-point one-step predictors with the estimators' outputs.

What a physics model adds is measured against predictors that know nothing of it. Each predicts every point's
position in frame k from that point's own measurements in frames before k only (causal):

* ``hold``: the last measurement of the point;
* ``constvel``: constant velocity, ``y_{k-1} + (t_k - t_{k-1}) (y_{k-1} - y_{j}) / (t_{k-1} - t_j)`` from its last
  two measurements (``hold`` while it has only one);
* ``harmonic``: a periodic predictor at the heart rate ``f``: the point's last measurement plus the change it
  showed over the same phase interval one, two, ... ``periods`` heart periods earlier (averaged;
  :func:`predict_harmonic`); ``constvel`` until a period of history exists. The heart rate comes from the caller
  or from :func:`dominant_frequency` of the measured tracks.

The result is an :class:`~tracker.measurements.EstimateSet` like an estimator's (no state, no parameters: ``theta``
NaN, NIS NaN with 0 degrees of freedom; ``filtered`` is the measurement itself, the best a measurement-only
predictor knows after seeing it), so ``heartcv report`` compares them with the GE and the KF.
"""

from __future__ import annotations

import time

import numpy as np

from .estimator_names import BASELINES
from .measurements import EstimateSet, MeasurementSet
from .unknown_input import filled_tracks, periodic_peak, seen_share, spectral_peak

__all__ = ["BASELINES", "PERIODS", "dominant_frequency", "predict_hold", "predict_constvel",
           "predict_harmonic", "run_baseline"]

PERIODS = 2
"""Heart periods the ``harmonic`` predictor averages."""


def dominant_frequency(times, positions, lo_hz: float = 0.5, hi_hz: float = 4.0) -> float:
    """The dominant frequency (Hz) of the points' motion: the largest peak in ``[lo_hz, hi_hz]`` of the summed power
    spectrum of every point's detrended coordinates (points seen in at least 90 % of the frames, gaps filled by
    linear interpolation), refined by parabolic interpolation of the log power around the peak bin; NaN when no
    point qualifies, the sequence is shorter than two periods of ``hi_hz`` or the peak is not periodic motion
    (:func:`tracker.unknown_input.periodic_peak`: ``PEAK_RATIO`` times the band's median power, or that many
    times the power between its harmonics and prominent).

    Parameters
    ----------
    times : (K,) equally spaced seconds
    positions : (K, P, 3) with NaN where a point is not seen
    """
    t = np.asarray(times, float)
    y = np.asarray(positions, float)
    K = t.size
    if K < 8:
        return float("nan")
    dt = float(np.median(np.diff(t)))
    use = seen_share(y) >= 0.9
    if not use.any() or (K - 1) * dt < 2.0 / hi_hz:
        return float("nan")
    Y, _ = filled_tracks(t, y)
    peak, ratio, _ = spectral_peak(Y, dt, (lo_hz, hi_hz))
    if peak is None or not periodic_peak(Y, dt, peak, ratio)[0]:        # no periodic motion: a flat spectrum
        return float("nan")
    return peak


def _last_seen(y):
    """Per frame k and point: the index of the last frame < k in which the point was seen, and of the one before
    (-1 where there is none): (K, P) each."""
    K, P = y.shape[:2]
    seen = np.isfinite(y[..., 0])
    last = np.full((K, P), -1)
    prev = np.full((K, P), -1)
    cur_last = np.full(P, -1)
    cur_prev = np.full(P, -1)
    for k in range(K):
        last[k], prev[k] = cur_last, cur_prev
        s = seen[k]
        cur_prev = np.where(s, cur_last, cur_prev)
        cur_last = np.where(s, k, cur_last)
    return last, prev


def _take(y, idx):
    """``y[idx[k, p], p]`` (K, P, 3), NaN where idx < 0."""
    K, P = idx.shape
    out = y[np.clip(idx, 0, None), np.arange(P)[None, :]]
    out[idx < 0] = np.nan
    return out


def predict_hold(times, positions) -> np.ndarray:
    """One-step predictions (K, P, 3) of ``hold``."""
    y = np.asarray(positions, float)
    last, _ = _last_seen(y)
    return _take(y, last)


def predict_constvel(times, positions) -> np.ndarray:
    """One-step predictions (K, P, 3) of ``constvel`` (``hold`` after a point's first measurement)."""
    t = np.asarray(times, float)
    y = np.asarray(positions, float)
    last, prev = _last_seen(y)
    y1, y0 = _take(y, last), _take(y, prev)
    t1 = np.where(last >= 0, t[np.clip(last, 0, None)], np.nan)
    t0 = np.where(prev >= 0, t[np.clip(prev, 0, None)], np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = (t[:, None] - t1) / (t1 - t0)
    out = y1 + rate[..., None] * (y1 - y0)
    return np.where(np.isfinite(out), out, y1)


def _at(y, t, tq):
    """Positions (K, P, 3) interpolated linearly in time at ``tq`` (K, P) from frames at equally spaced ``t``;
    NaN outside the sequence or where either bracketing frame misses the point."""
    K, P = y.shape[:2]
    dt = (t[-1] - t[0]) / (K - 1)
    s = (tq - t[0]) / dt
    s = np.where(np.abs(s - np.round(s)) < 1e-9, np.round(s), s)      # on a frame: that frame alone
    inside = np.isfinite(s) & (s >= 0) & (s <= K - 1)
    i = np.clip(np.floor(np.where(inside, s, 0)).astype(int), 0, K - 2)
    w = np.where(inside, s - i, 0.0)[..., None]
    cols = np.arange(P)[None, :]
    a, b = y[i, cols], y[i + 1, cols]
    out = np.where(w > 0, (1 - w) * a + w * b, a)                       # w = 0: a missing next frame is not needed
    out[~inside] = np.nan
    return out


def predict_harmonic(times, positions, frequency_hz: float, periods: int = PERIODS) -> np.ndarray:
    """One-step predictions (K, P, 3) of the periodic predictor at ``frequency_hz``: the point's last measurement
    plus the change it showed over the same phase interval in each of the last ``periods`` heart periods (linear
    interpolation between frames), averaged over those periods,

        y_hat_k = y_j + mean_{n=1..N} [ y(t_k - n T) - y(t_j - n T) ],     T = 1 / f,  j the last frame seen,

    exact for a periodic motion sampled finely enough and unaffected by a slow drift; ``constvel`` where no earlier
    period has the point at both instants."""
    if not (np.isfinite(frequency_hz) and frequency_hz > 0):
        raise ValueError(f"frequency_hz: a positive frequency expected, got {frequency_hz}")
    if int(periods) != periods or periods < 1:
        raise ValueError(f"periods: an integer >= 1 expected, got {periods}")
    t = np.asarray(times, float)
    y = np.asarray(positions, float)
    K, P = y.shape[:2]
    fallback = predict_constvel(t, y)
    if K < 2:
        return fallback
    last, _ = _last_seen(y)
    y_last = _take(y, last)
    t_last = np.where(last >= 0, t[np.clip(last, 0, None)], np.nan)
    T = 1.0 / frequency_hz
    steps = []
    for n in range(1, int(periods) + 1):
        now = _at(y, t, np.broadcast_to(t[:, None] - n * T, (K, P)))
        then = _at(y, t, t_last - n * T)
        steps.append(now - then)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)              # all-NaN where no period has the point
        change = np.nanmean(np.stack(steps), axis=0)
    out = y_last + change
    return np.where(np.isfinite(out), out, fallback)


def run_baseline(name: str, meas: MeasurementSet, *, keep=None, frequency_hz: float | None = None,
                 periods: int = PERIODS, heldout=None) -> EstimateSet:
    """A baseline over a measurement set, as an :class:`EstimateSet`.

    Parameters
    ----------
    name : one of :data:`BASELINES`
    keep : (P_used,) int, optional   the points to predict (indices into ``meas``); others get NaN rows, as the
        points an estimator drops (default: every point)
    frequency_hz : the heart rate for ``harmonic`` (default: :func:`dominant_frequency` of the kept points)
    heldout : (H,) int, optional      points (indices into ``meas``) whose errors the report keeps apart
        (``meta.heldout_points``), as the model-based estimators' held-out tracks; a per-point predictor uses a
        point's own past measurements either way
    """
    if name not in BASELINES:
        raise ValueError(f"baseline: one of {BASELINES} expected, got {name!r}")
    t0 = time.perf_counter()
    K, P = meas.n_frames, meas.n_points
    keep = np.arange(P) if keep is None else np.asarray(keep, int)
    y = meas.positions[:, keep]
    meta = {"baseline": True, "dropped_points": np.setdiff1d(np.arange(P), keep).tolist(), "estimated": []}
    if heldout is not None and len(heldout):
        meta["heldout_points"] = [int(i) for i in np.asarray(meas.point_ids)[np.asarray(heldout)]]
    if name == "hold":
        pred = predict_hold(meas.times, y)
    elif name == "constvel":
        pred = predict_constvel(meas.times, y)
    else:
        f = dominant_frequency(meas.times, y) if frequency_hz is None else float(frequency_hz)
        if not np.isfinite(f):
            raise ValueError("harmonic: no heart rate (the tracks show no periodic motion in 0.5-4 Hz, or the "
                             "sequence is too short)")
        pred = predict_harmonic(meas.times, y, f, periods)
        meta.update(heart_rate_hz=f, periods=int(periods),
                    heart_rate_source="given" if frequency_hz is not None else "tracks' spectrum")
    predictions = np.full((K, P, 3), np.nan)
    predictions[:, keep] = pred
    innovations = meas.positions - predictions
    filtered = np.full((K, P, 3), np.nan)
    filtered[:, keep] = y
    wall = time.perf_counter() - t0
    nan5 = np.full((K, 5), np.nan)
    return EstimateSet(name, meas.times, meas.point_ids, np.zeros((K, 0)), np.zeros((K, 0)), nan5, nan5.copy(),
                       predictions, innovations, np.full(K, np.nan), np.zeros(K, np.int64), np.zeros(K, np.int64),
                       np.full(K, wall / max(K, 1)), K, meta=meta, filtered=filtered)
