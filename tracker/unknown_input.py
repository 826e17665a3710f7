"""The input of a recording without a pressure signal (issue 16, docs/model.md "Unknown input").

Most recordings of real hearts come without a catheter pressure; the model is driven by one. Here the input is
estimated instead:

* the **heart rate** ``f`` from the spectrum of the tracked points' motion (:func:`estimate_heart_rate`): the peak
  of the summed power spectrum in 0.5-4 Hz, refined by a least-squares fit of ``H`` harmonics of ``f`` to the
  dominant motion signal (the first principal component of the tracks);
* the **input's harmonics**: ``u(t) = sum_h a_h cos(2 pi h f t) + b_h sin(2 pi h f t)`` on the model's pressure
  column (its mean is a constant displacement that the points' offsets absorb). ``heartcv fit`` profiles the
  amplitudes out of its weighted least squares (the states are linear in them for a given theta);
* a **rigid motion** of the observed surface (respiration, the heart's bulk motion in the view): a per-frame
  translation in the fit; in the estimators a random-walk translation plus ``H`` harmonics of ``f`` per axis, and
  when the fit's translation shows a breathing rhythm (:func:`estimate_respiration`: at least two breaths in the
  fitted frames) ``R`` harmonics of the respiration rate ``f_r`` per axis; with ``heartcv fit``'s default the
  translation is the centre of a smooth (affine) displacement field along the observed surface, whose other
  coefficients the fit takes from its residual (``InputBlock.field_degree``).

In the estimators the amplitudes and the rigid motion are states of the linear block (:class:`InputBlock`): each
harmonic is a 2-D rotation ``z_h' = R(2 pi h f dt) z_h + w`` whose first component is that harmonic's value, so
given the parameters the whole linear block stays linear-Gaussian and the Rao-Blackwellised structure and the
exact conditional propagation of the GE hold. The transition of the kinematic state couples to the block through
the first-order hold of the model's input, ``x' = A x + B0 u_k + B1 u_{k+1}`` with ``u_k = P0 e_k`` and
``u_{k+1} = P0 T e_k = P1 e_k`` (the block's own noise in ``u_{k+1}`` is neglected: a fraction ``drift sqrt(dt)``
of the input over one frame). The KF holds the fit's rates (the oscillators' random walk follows a slowly varying
rate as a slowly turning phase); the GE samples them (:class:`RatePrior`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math

import numpy as np

__all__ = ["NoHeartbeat", "HeartRate", "estimate_heart_rate", "harmonic_basis", "InputBlock", "HARMONICS",
           "DRIFT_PER_SQRT_S", "PEAK_RATIO", "PEAK_PROMINENCE", "BAND_HZ", "seen_share", "filled_tracks",
           "dominant_track", "MAX_LEFT_OUT", "spectral_peak",
           "harmonic_background_ratio", "periodic_peak", "harmonics_below_nyquist",
           "peak_prominence", "NotProminent", "heart_rate_at",
           "fit_harmonics", "input_block_from_fit", "extend_observation",
           "extend_prior", "extend_noise", "extend_transition", "prior_input", "known_inputs", "RatePrior",
           "RATE_WALK_PER_SQRT_S", "RATE_PRIOR_MIN", "Respiration", "estimate_respiration", "respiration_prior",
           "RESPIRATION_BAND_HZ", "RESPIRATION_HARMONICS", "MIN_BREATHS", "RESPIRATION_MIN_EXPLAINED",
           "fit_increment_ar", "select_increment_ar", "MAX_AR_ORDER", "field_powers", "field_basis",
           "select_field_ar", "FIELD_RIDGES", "MAX_FIELD_DEGREE", "FIELD_DEGREE", "with_rigid_dynamics",
           "MIN_RELEARN_FRAMES"]

HARMONICS = 6
"""Harmonics of the heart rate in the estimated input and in the rigid motion. An LV pressure pulse needs them: on
the paper patch at 72 bpm the KF with 3 harmonics predicts 1.39x worse than with the recorded pressure, with 6
1.10x, with 10 1.05x (tests/tracker/test_unknown_input.py)."""

DRIFT_PER_SQRT_S = 0.2
"""Random walk of each harmonic's oscillator, as a fraction of the harmonic's fitted amplitude per sqrt(s): beat-
to-beat changes of amplitude and phase (heart-rate variability) of 20 % over one second."""

PEAK_RATIO = 10.0
"""A heartbeat needs a spectral peak this many times the band's median power (a heartbeat gives 100x and more;
white noise a few), or this many times the power between its harmonics (:func:`harmonic_background_ratio`) with a
prominence of at least :data:`PEAK_PROMINENCE`: a fast heart's harmonics and breathing fill the band (the in-vivo
heart played twice as fast reads 5.2 against the band's median)."""

PEAK_PROMINENCE = 2.0
"""A heartbeat's spectral peak stands at least this many times above the spectrum half its frequency below and
above it (:func:`peak_prominence`; a power-law spectrum, drift, gives at most 1 in expectation). Below it
``heartcv fit`` refuses the rate (:class:`NotProminent`; a rate known otherwise is given with ``--heart-rate-hz``)
and ``heartcv report`` flags the window. A real heart's short window can come close (the in-vivo heart's 2.4-s
window: 2.1; its 4-s and 6-s windows 2.7-12)."""

BAND_HZ = (0.5, 4.0)
"""Heart rates searched (30-240 bpm)."""

MIN_BEATS = 2.0
"""Heartbeats a recording must hold for its heart rate to be estimated."""


RESPIRATION_BAND_HZ = (0.1, 0.7)
"""Respiration rates searched (6-42 breaths per minute; a ventilated patient breathes at 10-20), and at most half
the heart rate (the heartbeat's harmonics stay out of the band)."""

RESPIRATION_HARMONICS = 2
"""Harmonics of the respiration rate in the rigid motion (a breath is nearly sinusoidal; the second takes up the
asymmetry of inspiration and expiration)."""

MIN_BREATHS = 2.0
"""Breaths the fitted frames must hold for a respiration rate to be estimated (as :data:`MIN_BEATS`)."""

RESPIRATION_MIN_EXPLAINED = 0.5
"""A breathing rhythm is seen when the harmonics of its rate explain at least this fraction of the variance of the
fit's rigid translation (after the heartbeat's harmonics and a linear trend): white noise gives a few per cent. A
random walk (a drifting view) often gives more (median 0.62 over 12 s), but its slow peak mostly lies below
:data:`MIN_BREATHS` cycles in the window: 3 of 200 simulated random walks pass both tests."""


class NoHeartbeat(ValueError):
    """The tracks show no heartbeat: too short (fewer than :data:`MIN_BEATS` beats) or no periodic motion."""


class NotProminent(NoHeartbeat):
    """The tracks' spectral peak passes the periodicity tests but is not :data:`PEAK_PROMINENCE` prominent: the
    falling spectrum of drift, not a heartbeat, as far as the spectrum tells (:func:`estimate_heart_rate` with
    ``prominent``)."""


@dataclass(frozen=True)
class HeartRate:
    """Result of :func:`estimate_heart_rate`.

    Attributes
    ----------
    frequency_hz : float     the refined heart rate
    peak_hz : float          the spectral peak before refinement
    peak_ratio : float       the peak's power over the band's median power
    beats : float            heartbeats in the frames used
    points : int             points used (seen in at least 90 % of the frames)
    std_hz : float           standard error of ``frequency_hz``: the profile curvature of the harmonic fit's residual
                             sum of squares, ``sqrt(2 s^2 / RSS''(f))`` with ``s^2 = RSS / (K - 2H - 2)`` (white
                             residuals assumed; residuals correlated over frames make it optimistic)
    prominence : float       :func:`peak_prominence` at ``peak_hz``: how far the peak stands above the spectrum
                             half its frequency below and above it (a falling spectrum's edge, drift, is below
                             :data:`PEAK_PROMINENCE`)
    background_ratio : float :func:`harmonic_background_ratio` at ``peak_hz``: the peak's power over the median
                             power between its harmonics up to the Nyquist frequency
    left_out : tuple of int  the tracks (indices along the positions' second axis) left out because the tracks
                             showed a heartbeat, or another rate, only without them (:func:`estimate_heart_rate`)
    """

    frequency_hz: float
    peak_hz: float
    peak_ratio: float
    beats: float
    points: int
    std_hz: float = float("nan")
    prominence: float = float("nan")
    background_ratio: float = float("nan")
    left_out: tuple = ()


def _undersampled(dt: float, lo: float, what: str) -> str:
    """The reason a frame interval shows no rate in a band starting at ``lo`` Hz (above its Nyquist frequency)."""
    return (f"a frame interval of {dt:.3g} s ({1 / dt:.3g} frames per second) shows no frequency above "
            f"{0.5 / dt:.3g} Hz, below the {lo:g}-Hz low end of the {what}' band (are the times in milliseconds? "
            "measurement files hold seconds)")


def seen_share(positions) -> np.ndarray:
    """Per track (K, P, 3 with NaN where unseen): the share of the frames holding any observation in which it is
    seen. A frame where nothing is seen (a frame the recording lacks: dropped, repeated, unreadable) counts against
    no track. Zeros where no frame holds anything."""
    seen = np.isfinite(np.asarray(positions, float)[..., 0])
    some = seen.any(axis=1)
    return seen[some].mean(axis=0) if some.any() else np.zeros(seen.shape[1])


def filled_tracks(times, positions, min_seen=0.9):
    """Tracks seen in at least ``min_seen`` of the frames that hold any observation (:func:`seen_share`), gaps
    filled by linear interpolation, detrended: (K, 3 P)."""
    y = np.asarray(positions, float)
    K = y.shape[0]
    if K < 2:   # no motion in one frame (and no line through one sample)
        return np.zeros((K, 0)), 0
    seen = np.isfinite(y[..., 0])
    use = np.flatnonzero(seen_share(y) >= min_seen)
    k = np.arange(K)
    cols = []
    for p in use:
        ok = seen[:, p]
        for c in range(3):
            s = np.interp(k, k[ok], y[ok, p, c])
            cols.append(s - np.polyval(np.polyfit(k, s, 1), k))
    return (np.stack(cols, axis=1) if cols else np.zeros((K, 0))), use.size


def _power_spectrum(Y, dt: float):
    """``(frequencies (Hz), power)``: the summed Hann-windowed power spectrum of the series Y (K, n)."""
    K = Y.shape[0]
    power = (np.abs(np.fft.rfft(Y * np.hanning(K)[:, None], axis=0)) ** 2).sum(axis=1)
    return np.fft.rfftfreq(K, dt), power


def peak_prominence(Y, dt: float, peak_hz: float) -> float:
    """How far a spectral peak at ``peak_hz`` stands above its surroundings: the summed Hann-windowed power of the
    series Y (K, n) at ``peak_hz`` over the geometric mean of the power at ``peak_hz / 2`` and ``3 peak_hz / 2``
    (half a harmonic spacing below and above; linear interpolation between bins). A periodic motion's fundamental
    stands far above both (its harmonics lie at ``2 peak_hz``, ``3 peak_hz``, ...); a power-law spectrum
    ``P ~ f^-a`` gives ``(3/4)^(a/2)`` whatever the frequency (0.75 for a random walk, a = 2), so the largest "peak"
    of drift, at the low end of the band, is not prominent although it towers over the band's median. NaN when
    ``3 peak_hz / 2`` lies beyond the Nyquist frequency or a power is zero."""
    f, power = _power_spectrum(np.asarray(Y, float), dt)
    if not (peak_hz > 0 and 1.5 * peak_hz <= f[-1]):
        return float("nan")
    p0, lo, hi = np.interp([peak_hz, 0.5 * peak_hz, 1.5 * peak_hz], f, power)
    if not (lo > 0 and hi > 0):
        return float("nan")
    return float(p0 / math.sqrt(lo * hi))


def harmonic_background_ratio(Y, dt: float, peak_hz: float) -> float:
    """How far a spectral peak at ``peak_hz`` stands above the spectrum between its harmonics: the summed
    Hann-windowed power of the series Y (K, n) at ``peak_hz`` over the median of the power at ``(k + 1/2) peak_hz``,
    k = 0, 1, ..., up to the Nyquist frequency (linear interpolation between bins). Unlike the band's median
    (:data:`PEAK_RATIO`'s reference), this does not depend on where the rate lies in the band: a fast heart's
    harmonics and breathing fill a fixed band, and the band's median with them (the in-vivo heart played twice as
    fast reads 5.2 against the band's median and 50 against this; at its own rate 13 and 77). For a sinusoid of
    amplitude A in white noise of variance s^2 over K frames it is about ``1 + A^2 K / (6 s^2)`` (Hann window);
    white noise alone reads about 1. NaN with fewer than 2 such frequencies or a zero median."""
    f, power = _power_spectrum(np.asarray(Y, float), dt)
    if not peak_hz > 0:
        return float("nan")
    between = (np.arange(int(f[-1] / peak_hz + 0.5)) + 0.5) * peak_hz
    between = between[between <= f[-1]]
    if between.size < 2:
        return float("nan")
    background = float(np.median(np.interp(between, f, power)))
    return float(np.interp(peak_hz, f, power) / background) if background > 0 else float("nan")


def harmonics_below_nyquist(frequency_hz: float, dt: float, harmonics: int, std_hz: float = 0.0) -> int:
    """The harmonics of a rate ``frequency_hz`` (standard error ``std_hz``) that a recording of frame interval ``dt``
    resolves: the largest h <= ``harmonics`` with h (``frequency_hz`` + 2 ``std_hz``) below the Nyquist frequency
    1 / (2 dt), at least 1 (a NaN ``std_hz`` counts as 0). A harmonic at or above it is an alias of a lower
    frequency (at it, its sine vanishes on every frame)."""
    f = frequency_hz + (2.0 * std_hz if math.isfinite(std_hz) else 0.0)
    return max(1, min(int(harmonics), int(math.ceil(0.5 / (dt * f) - 1e-9)) - 1))


def periodic_peak(Y, dt: float, peak_hz: float, ratio: float) -> tuple[bool, float, float]:
    """``(periodic, background_ratio, prominence)`` of the spectral peak at ``peak_hz`` of series Y (K, n), ``ratio``
    its power over the band's median (:func:`spectral_peak`): periodic motion when ``ratio`` is at least
    :data:`PEAK_RATIO`, or when the peak is :data:`PEAK_RATIO` times the power between its harmonics
    (:func:`harmonic_background_ratio`) and :data:`PEAK_PROMINENCE` prominent (:func:`peak_prominence`)."""
    prominence = peak_prominence(Y, dt, peak_hz)
    background = harmonic_background_ratio(Y, dt, peak_hz)
    return bool(ratio >= PEAK_RATIO or (background >= PEAK_RATIO and prominence >= PEAK_PROMINENCE)), background, \
        prominence


def spectral_peak(Y, dt: float, band=BAND_HZ):
    """``(peak_hz, ratio, bin_hz)`` of filled, detrended series Y (K, n) (:func:`filled_tracks`): the largest peak in
    ``band`` of their summed Hann-windowed power spectrum, refined by parabolic interpolation of the log power, and
    its power over the band's median; ``(None, 0, bin_hz)`` when the band holds fewer than 3 bins."""
    f, power = _power_spectrum(Y, dt)
    df = float(f[1] - f[0])
    band_idx = np.flatnonzero((f >= band[0]) & (f <= band[1]))
    if band_idx.size < 3:
        return None, 0.0, df
    i = band_idx[np.argmax(power[band_idx])]
    ratio = float(power[i] / max(np.median(power[band_idx]), 1e-300))
    peak = float(f[i])
    if 0 < i < power.size - 1 and (power[i - 1:i + 2] > 0).all():
        a, b, c = np.log(power[i - 1:i + 2])
        den = a - 2 * b + c
        peak = float((i + (np.clip(0.5 * (a - c) / den, -0.5, 0.5) if den < 0 else 0.0)) * df)
    return peak, ratio, df


RATE_WALK_PER_SQRT_S = 0.02
"""Random walk of the GE's sampled log heart rate per square-root second: a resting heart's beat-to-beat variability
(an RMSSD of 20-50 ms at an RR interval near 1 s is 2-5 % per beat)."""
RATE_PRIOR_MIN = 0.01
"""Smallest prior standard deviation of the sampled log heart rate: the fit's standard error assumes white
residuals and is optimistic (:class:`HeartRate`)."""


RESPIRATION_WALK_PER_SQRT_S = 0.05
"""Random walk of the GE's sampled log respiration rate per square-root second: breath-to-breath variability is
larger than the heart's (5-10 % per breath in spontaneous breathing; a ventilator holds its rate)."""
RESPIRATION_PRIOR_MIN = 0.05
"""Smallest prior standard deviation of the sampled log respiration rate: two or three breaths give a rate to
several per cent at best."""


@dataclass(frozen=True)
class RatePrior:
    """A rate as a sampled parameter of the GE (docs/model.md §17): ``phi = log f`` with prior
    ``N(log f0, max(std / f0, prior_min)^2)``, a random walk of ``walk_per_sqrt_s`` per square-root second and the
    box ``log band``. The default is the heart rate's (:data:`RATE_WALK_PER_SQRT_S`, :data:`RATE_PRIOR_MIN`,
    :data:`BAND_HZ`); :func:`respiration_prior` the respiration rate's."""

    frequency_hz: float
    std_hz: float = 0.0
    name: str = "heart rate"
    band: tuple = BAND_HZ
    walk_per_sqrt_s: float = RATE_WALK_PER_SQRT_S
    prior_min: float = RATE_PRIOR_MIN

    def __post_init__(self):
        lo, hi = self.band
        if not (np.isfinite(self.frequency_hz) and lo <= self.frequency_hz <= hi):
            raise ValueError(f"{self.name}: a frequency in {lo:g}-{hi:g} Hz expected, got {self.frequency_hz}")
        if not (np.isfinite(self.std_hz) and self.std_hz >= 0):
            raise ValueError(f"{self.name}: a standard deviation >= 0 expected, got {self.std_hz}")

    @property
    def phi_mean(self) -> float:
        return math.log(self.frequency_hz)

    @property
    def phi_std(self) -> float:
        return max(self.std_hz / self.frequency_hz, self.prior_min)

    @property
    def bounds_phi(self) -> tuple:
        return math.log(self.band[0]), math.log(self.band[1])

    def walk_per_frame(self, dt: float) -> float:
        return self.walk_per_sqrt_s * math.sqrt(dt)


def respiration_prior(frequency_hz: float, std_hz: float = 0.0, band=RESPIRATION_BAND_HZ) -> RatePrior:
    """The respiration rate as a sampled parameter of the GE: :data:`RESPIRATION_WALK_PER_SQRT_S`,
    :data:`RESPIRATION_PRIOR_MIN`, the box ``band`` (default :data:`RESPIRATION_BAND_HZ`; ``fit
    --respiration-band``)."""
    return RatePrior(frequency_hz, std_hz, "respiration rate", tuple(band), RESPIRATION_WALK_PER_SQRT_S,
                     RESPIRATION_PRIOR_MIN)


def harmonic_basis(t, frequency_hz: float, harmonics: int = HARMONICS) -> np.ndarray:
    """``[cos(2 pi f t), sin(2 pi f t), cos(4 pi f t), sin(4 pi f t), ...]``, shape (K, 2 harmonics)."""
    t = np.asarray(t, float).reshape(-1)
    w = 2 * np.pi * float(frequency_hz) * np.arange(1, harmonics + 1)
    ph = t[:, None] * w[None, :]
    out = np.empty((t.size, 2 * harmonics))
    out[:, 0::2] = np.cos(ph)
    out[:, 1::2] = np.sin(ph)
    return out


def _harmonic_rss(t, s, f, harmonics):
    """Residual sum of squares of the least-squares fit of a constant and ``harmonics`` harmonics of f to s."""
    X = np.hstack([np.ones((t.size, 1)), harmonic_basis(t, f, harmonics)])
    coef, *_ = np.linalg.lstsq(X, s, rcond=None)
    r = s - X @ coef
    return float(np.sum(r * r))


def dominant_track(positions) -> int | None:
    """The track (index along the second axis of positions (K, P, 3), NaN where unseen) that carries the largest
    share of the detrended motion's variance among the tracks :func:`filled_tracks` uses; None with fewer than 3
    of them (leaving one out would leave too little to judge by)."""
    y = np.asarray(positions, float)
    use = np.flatnonzero(seen_share(y) >= 0.9)
    if use.size < 3:
        return None
    Y, _ = filled_tracks(np.arange(y.shape[0]), y[:, use])
    power = (Y.reshape(Y.shape[0], use.size, 3) ** 2).sum(axis=(0, 2))
    return int(use[int(np.argmax(power))])


# At most this many tracks are left out of a heart rate, one at a time (:func:`estimate_heart_rate`)
MAX_LEFT_OUT = 3


def _disagree(a: HeartRate, b: HeartRate) -> bool:
    """Whether two heart rates of nearly the same tracks differ by more than 3 standard errors of the more precise
    one, combined as for two independent estimates (never where one is undefined). (A track that pulls the rate
    also widens its standard error: combining the two errors would let it pass.)"""
    tol = 3.0 * math.sqrt(2.0) * min(a.std_hz, b.std_hz)
    return bool(math.isfinite(tol) and abs(a.frequency_hz - b.frequency_hz) > tol)


def estimate_heart_rate(times, positions, harmonics: int = HARMONICS, band=BAND_HZ, *,
                        prominent: bool = False) -> HeartRate:
    """The heart rate of tracked points (K, P, 3 with NaN where unseen) (:func:`_heart_rate`), which no single
    track decides: the rate is taken again without the track that carries the largest share of the tracks' motion
    (:func:`dominant_track`); where the tracks showed no heartbeat (:class:`NoHeartbeat`, :class:`NotProminent`)
    but the others do, or where the others' rate differs significantly (:func:`_disagree`), theirs is taken
    and the next such track is tried, at most :data:`MAX_LEFT_OUT` in all (``left_out`` names them). A track whose
    stereo match slipped for a while (its depth jumping by millimetres) can carry several times its share: it
    flattens the spectral peak or pulls the dominant motion, and so the rate. Where leaving a track out changes
    nothing significant, the result is that of all the tracks."""
    y = np.asarray(positions, float)
    try:
        hr, failure = _heart_rate(times, y, harmonics, band, prominent=prominent), None
    except NoHeartbeat as exc:
        hr, failure = None, exc
    left = []
    for _ in range(MAX_LEFT_OUT):
        p = dominant_track(y)
        if p is None:
            break
        without = y.copy()
        without[:, p] = np.nan
        try:
            other = _heart_rate(times, without, harmonics, band, prominent=prominent)
        except NoHeartbeat:
            break
        if hr is not None and not _disagree(hr, other):
            break
        y, hr = without, other
        left.append(p)
    if hr is None:
        raise failure
    return replace(hr, left_out=tuple(left))


def _heart_rate(times, positions, harmonics: int = HARMONICS, band=BAND_HZ, *,
                prominent: bool = False) -> HeartRate:
    """The heart rate of tracked points (K, P, 3 with NaN where unseen): spectral peak, then refined.

    The peak of the summed Hann-windowed power spectrum of every point's detrended coordinates in ``band``
    (points seen in >= 90 % of the frames), parabolic interpolation of its log power; then the frequency within one
    bin of it that minimises the residual of a least-squares fit of ``harmonics`` harmonics to the dominant motion
    (first principal component of the tracks), by bounded scalar minimisation.

    Raises
    ------
    NoHeartbeat
        Fewer than 8 frames or no track seen in 90 % of them; shorter than :data:`MIN_BEATS` beats at the found
        rate (or at the band's upper end); no peak :data:`PEAK_RATIO` times the band's median power, nor one
        :data:`PEAK_RATIO` times the power between its harmonics and :data:`PEAK_PROMINENCE` prominent.
    NotProminent
        With ``prominent``: a peak that passes those tests but is less than :data:`PEAK_PROMINENCE` prominent
        (drift's falling spectrum passes the band-median test in most draws; its peak at the band's low end is
        seldom prominent). A NaN prominence (``1.5 peak`` beyond the Nyquist frequency) is not refused.
    """
    from scipy.optimize import minimize_scalar

    t = np.asarray(times, float)
    K = t.size
    lo, hi = band
    if K < 8:
        raise NoHeartbeat(f"{K} frames: too short to show a heartbeat")
    dt = float(np.median(np.diff(t)))
    duration = K * dt
    if 0.5 / dt < lo:
        raise NoHeartbeat(_undersampled(dt, lo, "heart rates"))
    if duration < MIN_BEATS / hi:
        raise NoHeartbeat(f"{duration:.3g} s: shorter than {MIN_BEATS:g} heartbeats even at {hi * 60:g} bpm")
    Y, n_points = filled_tracks(t, positions)
    if n_points == 0:
        raise NoHeartbeat("no track is seen in 90 % of the frames that hold any: no motion signal to take a heart "
                          "rate from")
    peak, ratio, df = spectral_peak(Y, dt, band)
    if peak is None:
        raise NoHeartbeat(f"{duration:.3g} s: too short to resolve heart rates in {lo:g}-{hi:g} Hz")
    if duration * (peak + df) < MIN_BEATS:   # short even at the top of the peak's bin
        raise NoHeartbeat(f"{duration:.3g} s holds {duration * peak:.2g} heartbeats at the tracks' dominant "
                          f"frequency {peak:.3g} Hz: at least {MIN_BEATS:g} are needed")
    periodic, background, prominence = periodic_peak(Y, dt, peak, ratio)
    if not periodic:
        raise NoHeartbeat(f"no periodic motion: the tracks' largest spectral peak in {lo:g}-{hi:g} Hz is "
                          f"{ratio:.3g} times the band's median power and {background:.3g} times the power between "
                          f"its harmonics, with a prominence of {prominence:.3g} (a heartbeat gives more than "
                          f"{PEAK_RATIO:g} times the band's median, or {PEAK_RATIO:g} times the power between its "
                          f"harmonics with a prominence above {PEAK_PROMINENCE:g})")
    if prominent and prominence < PEAK_PROMINENCE:
        raise NotProminent(f"no periodic motion: the tracks' largest spectral peak in {lo:g}-{hi:g} Hz, at "
                           f"{peak:.3g} Hz, stands only {prominence:.3g} times above their spectrum at half and one "
                           f"and a half times its frequency (a heartbeat: {PEAK_PROMINENCE:g} times and more): the "
                           f"falling spectrum of drift, not a heartbeat")
    # the dominant motion signal: first principal component of the tracks
    U, S, _ = np.linalg.svd(Y - Y.mean(axis=0), full_matrices=False)
    s = U[:, 0] * S[0]
    tt = t - t[0]
    res = minimize_scalar(lambda ff: _harmonic_rss(tt, s, ff, harmonics), bounds=(max(lo, peak - df), peak + df),
                          method="bounded", options={"xatol": 1e-6 * peak})
    beats = float(duration * res.x)
    if beats < MIN_BEATS - 1e-9:
        raise NoHeartbeat(f"{duration:.3g} s holds {beats:.2g} heartbeats at the tracks' heart rate {res.x:.4g} Hz: "
                          f"at least {MIN_BEATS:g} are needed")
    return HeartRate(float(res.x), peak, ratio, beats, int(n_points), _frequency_std(tt, s, float(res.x), harmonics),
                     prominence, background)


def heart_rate_at(times, positions, frequency_hz: float, band=BAND_HZ) -> HeartRate:
    """A heart rate known from elsewhere (an ECG, the monitor), for tracked points (K, P, 3 with NaN where unseen):
    ``frequency_hz`` as it is (``std_hz`` 0, ``peak_hz`` the same), with what the tracks' spectrum shows at it for
    the record (``peak_ratio``: its power over the band's median; ``prominence``, ``background_ratio``), however
    small. No periodicity test; the recording must still hold :data:`MIN_BEATS` beats at the rate.

    Raises
    ------
    ValueError
        ``frequency_hz`` outside ``band``.
    NoHeartbeat
        Fewer than 8 frames, no track seen in 90 % of them, or fewer than :data:`MIN_BEATS` beats at the rate.
    """
    t = np.asarray(times, float)
    K = t.size
    lo, hi = band
    f = float(frequency_hz)
    if not (math.isfinite(f) and lo <= f <= hi):
        raise ValueError(f"heart rate: {lo:g}-{hi:g} Hz expected, got {frequency_hz}")
    if K < 8:
        raise NoHeartbeat(f"{K} frames: too short to show a heartbeat")
    dt = float(np.median(np.diff(t)))
    beats = K * dt * f
    if beats < MIN_BEATS - 1e-9:
        raise NoHeartbeat(f"{K * dt:.3g} s holds {beats:.2g} heartbeats at the heart rate {f:.4g} Hz: at least "
                          f"{MIN_BEATS:g} are needed")
    Y, n_points = filled_tracks(t, positions)
    if n_points == 0:
        raise NoHeartbeat("no track is seen in 90 % of the frames that hold any: no motion signal to fit a "
                          "heartbeat to")
    freqs, power = _power_spectrum(Y, dt)
    band_idx = (freqs >= lo) & (freqs <= hi)
    median = float(np.median(power[band_idx])) if band_idx.sum() >= 3 else float("nan")
    ratio = float(np.interp(f, freqs, power) / median) if median > 0 else float("nan")
    return HeartRate(f, f, ratio, float(beats), int(n_points), 0.0, peak_prominence(Y, dt, f),
                     harmonic_background_ratio(Y, dt, f))


def _frequency_std(t, s, f, harmonics) -> float:
    """Standard error of the frequency of a harmonic least-squares fit from the profile RSS's curvature."""
    dof = t.size - 2 * harmonics - 2
    rss = _harmonic_rss(t, s, f, harmonics)
    if dof < 1 or rss <= 0:
        return float("nan")
    h = 1e-2 / max(float(t[-1] - t[0]), 1e-9)   # a hundredth of the frequency resolution
    curv = (_harmonic_rss(t, s, f + h, harmonics) - 2 * rss + _harmonic_rss(t, s, f - h, harmonics)) / (h * h)
    return float(math.sqrt(2.0 * rss / dof / curv)) if curv > 0 else float("nan")


def fit_harmonics(t, series, frequency_hz: float, harmonics: int = HARMONICS):
    """Least-squares constant and harmonics of ``series`` (K, m) at times t (relative to the first):
    ``(constant (m,), coefficients (2 harmonics, m) [cos_1, sin_1, ...], residual (K, m))``."""
    t = np.asarray(t, float)
    s = np.asarray(series, float)
    X = np.hstack([np.ones((t.size, 1)), harmonic_basis(t - t[0], frequency_hz, harmonics)])
    coef, *_ = np.linalg.lstsq(X, s, rcond=None)
    return coef[0], coef[1:], s - X @ coef


@dataclass(frozen=True)
class Respiration:
    """Result of :func:`estimate_respiration`: ``frequency_hz`` None when no breathing rhythm is seen (``reason``
    says why).

    Attributes
    ----------
    frequency_hz : float or None  the refined respiration rate
    std_hz : float                its standard error (profile curvature, as :class:`HeartRate`)
    cycles : float                breaths in the frames used (at the rate, or at the band's top when none is seen)
    explained : float             fraction of the translation's variance (after the heartbeat and a linear trend)
                                  explained by the rate's harmonics
    reason : str                  why none is seen ('' when one is)
    """

    frequency_hz: float | None
    std_hz: float = float("nan")
    cycles: float = 0.0
    explained: float = 0.0
    reason: str = ""

    @property
    def seen(self) -> bool:
        return self.frequency_hz is not None

    def to_dict(self) -> dict:
        return {"frequency_hz": self.frequency_hz, "std_hz": None if not self.seen else float(self.std_hz),
                "per_min": None if not self.seen else 60 * self.frequency_hz, "cycles": float(self.cycles),
                "explained": float(self.explained), "reason": self.reason}


def estimate_respiration(times, translation, heart_rate_hz: float, harmonics: int = RESPIRATION_HARMONICS,
                         heart_harmonics: int = HARMONICS, band=RESPIRATION_BAND_HZ) -> Respiration:
    """The respiration rate of a rigid translation (K, 3) at ``times`` (the fit's per-frame translation), or the
    reason none is seen.

    The heartbeat's ``heart_harmonics`` harmonics and a linear trend are removed; the peak of the summed power
    spectrum of the three axes in ``band`` (capped at half the heart rate) is refined, as the heart rate's, by the
    frequency within one bin that minimises the residual of a fit of ``harmonics`` harmonics to the translation's
    first principal component. It counts as seen when the frames hold at least :data:`MIN_BREATHS` breaths at it
    and its harmonics explain at least :data:`RESPIRATION_MIN_EXPLAINED` of the remaining variance of all three
    axes. Never raises for a recording without one: a breathing rhythm is optional.
    """
    from scipy.optimize import minimize_scalar

    t = np.asarray(times, float)
    tr = np.asarray(translation, float)
    K = t.size
    if tr.shape != (K, 3) or not np.isfinite(tr).all():
        raise ValueError(f"translation: finite (K, 3) = ({K}, 3) expected, got {tr.shape}")
    lo, hi = band[0], min(band[1], 0.5 * float(heart_rate_hz))
    if K < 8 or hi <= lo:
        return Respiration(None, reason=f"{K} frames at a heart rate of {heart_rate_hz:.3g} Hz: no band left for a "
                                        f"respiration rate")
    dt = float(np.median(np.diff(t)))
    duration = K * dt
    if 0.5 / dt < lo:
        return Respiration(None, cycles=duration * hi, reason=_undersampled(dt, lo, "respiration rates"))
    if duration * hi < MIN_BREATHS:
        return Respiration(None, cycles=duration * hi,
                           reason=f"{duration:.3g} s hold fewer than {MIN_BREATHS:g} breaths even at "
                                  f"{hi * 60:.3g} per minute")
    _, _, resid = fit_harmonics(t, tr, heart_rate_hz, heart_harmonics)
    k = np.arange(K)
    Y = resid - np.polyval(np.polyfit(k, resid, 1), k[:, None]) if K > 2 else resid
    total = float(np.sum((Y - Y.mean(axis=0)) ** 2))
    peak, _, df = spectral_peak(Y, dt, (lo, hi))
    if peak is None or total <= 0:
        return Respiration(None, cycles=duration * hi,
                           reason=f"{duration:.3g} s: too short to resolve rates in {lo:g}-{hi:.3g} Hz")
    U, S, _ = np.linalg.svd(Y - Y.mean(axis=0), full_matrices=False)
    s = U[:, 0] * S[0]
    tt = t - t[0]
    res = minimize_scalar(lambda ff: _harmonic_rss(tt, s, ff, harmonics),
                          bounds=(max(lo, peak - df), min(hi, peak + df)), method="bounded",
                          options={"xatol": 1e-6 * peak})
    f = float(res.x)
    cycles = duration * f
    _, _, r = fit_harmonics(t, Y, f, harmonics)
    explained = 1.0 - float(np.sum(r * r)) / total
    if cycles < MIN_BREATHS:
        return Respiration(None, cycles=cycles, explained=explained,
                           reason=f"{duration:.3g} s hold {cycles:.3g} breaths at the translation's slow peak "
                                  f"{f:.3g} Hz: at least {MIN_BREATHS:g} are needed")
    if explained < RESPIRATION_MIN_EXPLAINED:
        return Respiration(None, cycles=cycles, explained=explained,
                           reason=f"no breathing rhythm: {harmonics} harmonics of the translation's slow peak "
                                  f"{f:.3g} Hz explain {100 * explained:.0f} % of its variance (at least "
                                  f"{100 * RESPIRATION_MIN_EXPLAINED:.0f} % expected)")
    return Respiration(f, _frequency_std(tt, s, f, harmonics), cycles, explained)


def _rotation(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, s], [-s, c]])


@dataclass(frozen=True)
class InputBlock:
    """The estimated input and rigid motion as states of the linear block, appended after the kinematic (and
    reference) states: ``e = [z_p (2H) | tau (D) | z_r (3 x 2H_r) | z_b (3 x 2R) | l (D p)]``.

    ``z_p``: the input's harmonics (oscillator h: ``[c_h, s_h]``, value ``c_h``), driving model input ``column``;
    ``tau``: the translation not periodic, a random walk, or with ``rigid_ar`` (p > 0) a vector autoregression of
    its increments ``d_k = tau_k - tau_(k-1)``: ``d_(k+1) = sum_i A_i d_(k+1-i) + w`` with ``l = [tau_(k-1), ...,
    tau_(k-p)]`` the previous translations; ``z_r``: the heartbeat's ``H_r`` harmonics of the rigid motion per axis
    (``rigid_harmonics``, default H); ``z_b``: the respiration's (``R = 0`` when no breathing rhythm was seen). The
    points move rigidly by ``G e = tau + sum_h c_h^axis + sum_r b_r^axis``.

    With ``field_degree`` d > 0, ``tau`` is a smooth displacement field instead of a translation: ``D = 3 n`` with
    ``n = (d + 1)(d + 2) / 2`` monomials ``u^i v^j`` (i + j <= d, the constant first) of a point's coordinates along
    the observed surface, ``(u, v) = field_axes (X - field_centre) / field_scale``; ``tau = [c_1 (3) | c_2 (3) |
    ...]`` moves point p by ``sum_j phi_j(u_p, v_p) c_j`` (:meth:`motion_maps`), its first 3 entries the
    translation of the patch centre. The field's increments follow the same vector autoregression (``rigid_ar``
    (p, D, D)). d = 0 is the rigid translation.

    Attributes
    ----------
    frequency_hz : float        heart rate
    harmonics : int             H
    dt : float                  frame interval (s)
    n_u : int                   the model's inputs
    column : int                the model input driven by z_p
    mean0 : ndarray (m,)        prior mean at the first frame
    std0 : ndarray (m,)         prior standard deviation
    noise_std : ndarray (m,)    random walk per frame
    input_scale : float         input units (Pa) per unit of ``z_p`` (the states stay of order 1, as the
                                kinematic ones in metres, for the estimators' runaway checks and conditioning)
    respiration_hz : float      respiration rate (0 with ``respiration_harmonics`` 0)
    respiration_harmonics : int R
    rigid_harmonics : int       H_r, the heartbeat's harmonics in the rigid motion (None: H)
    rigid_ar : ndarray (p, D, D) the autoregression of the translation's increments, ``d_(k+1) = sum_i A_i d_(k+1-i)``
                                (None or p = 0: a random walk)
    centred : bool              the model's displacements centred over the points (their mean displacement map
                                subtracted from each; :class:`tracker.fit.UnknownInputProblem` ``centred``): ``tau``
                                is then the tracks' mean motion, not that minus the model's mean bulge
    field_degree : int          d, the degree of the displacement field ``tau`` (0: a translation)
    field_centre : (3,)         the field's origin in the patch frame (m)
    field_axes : (2, 3)         the field's in-plane directions (orthonormal rows; None: the patch's x and y)
    field_scale : float         the field's length unit (m)
    """

    frequency_hz: float
    harmonics: int
    dt: float
    n_u: int
    column: int
    mean0: np.ndarray
    std0: np.ndarray
    noise_std: np.ndarray
    input_scale: float = 1.0
    respiration_hz: float = 0.0
    respiration_harmonics: int = 0
    rigid_harmonics: int | None = None
    rigid_ar: np.ndarray | None = None
    field_degree: int = 0
    field_centre: tuple = (0.0, 0.0, 0.0)
    field_scale: float = 1.0
    field_axes: tuple | None = None
    centred: bool = False

    def __post_init__(self):
        if self.rigid_harmonics is None:
            object.__setattr__(self, "rigid_harmonics", int(self.harmonics))
        if not 0 <= int(self.field_degree) <= MAX_FIELD_DEGREE:
            raise ValueError(f"input block: field_degree in 0..{MAX_FIELD_DEGREE} expected, got {self.field_degree}")
        centre = np.asarray(self.field_centre, float).reshape(-1)
        axes = np.eye(3)[:2] if self.field_axes is None else np.asarray(self.field_axes, float)
        if centre.size != 3 or not np.isfinite(centre).all() or not (np.isfinite(self.field_scale)
                                                                     and self.field_scale > 0):
            raise ValueError("input block: field_centre (3 finite values) and a positive field_scale expected")
        if axes.shape != (2, 3) or not np.isfinite(axes).all() or not np.allclose(axes @ axes.T, np.eye(2),
                                                                                 atol=1e-6):
            raise ValueError(f"input block: field_axes must be 2 orthonormal rows of 3, got {axes.tolist()}")
        object.__setattr__(self, "field_degree", int(self.field_degree))
        object.__setattr__(self, "field_centre", tuple(float(v) for v in centre))
        object.__setattr__(self, "field_axes", tuple(tuple(float(v) for v in row) for row in axes))
        object.__setattr__(self, "field_scale", float(self.field_scale))
        D = self.motion_dim
        ar = np.zeros((0, D, D)) if self.rigid_ar is None else np.asarray(self.rigid_ar, float)
        if ar.ndim != 3 or ar.shape[1:] != (D, D) or not np.isfinite(ar).all():
            raise ValueError(f"input block: rigid_ar must be finite (p, {D}, {D}), got shape {ar.shape}")
        if not 0 <= int(self.rigid_harmonics) <= int(self.harmonics):
            raise ValueError(f"input block: rigid_harmonics in 0..{self.harmonics} expected, got "
                             f"{self.rigid_harmonics}")
        object.__setattr__(self, "rigid_ar", ar)
        m = self.size
        for name in ("mean0", "std0", "noise_std"):
            v = np.asarray(getattr(self, name), float).reshape(-1)
            if v.size != m or not np.isfinite(v).all():
                raise ValueError(f"input block: {name} must hold {m} finite values, got {v.size}")
            object.__setattr__(self, name, v)
        if not (self.frequency_hz > 0 and self.dt > 0 and self.input_scale > 0 and self.harmonics >= 1
                and 0 <= self.column < self.n_u):
            raise ValueError("input block: positive frequency, dt and harmonics and a valid input column expected")
        if self.respiration_harmonics < 0 or (self.respiration_harmonics > 0) != (self.respiration_hz > 0):
            raise ValueError("input block: a positive respiration_hz with respiration_harmonics >= 1, or neither")

    @property
    def ar_order(self) -> int:
        return 0 if self.rigid_ar is None else int(np.shape(self.rigid_ar)[0])

    @property
    def motion_dim(self) -> int:
        """D: the states of ``tau`` (3 per monomial of the displacement field; 3 for a translation)."""
        return 3 * len(field_powers(self.field_degree))

    @property
    def size(self) -> int:
        D = self.motion_dim
        return 2 * self.harmonics + D + 6 * self.rigid_harmonics + 6 * self.respiration_harmonics + D * self.ar_order

    @property
    def slices(self):
        """``(z_p, tau, z_r, z_b)`` slices of the block (the lags :attr:`lags` after them)."""
        H, Hr, R, D = self.harmonics, self.rigid_harmonics, self.respiration_harmonics, self.motion_dim
        zb = 2 * H + D + 6 * Hr
        return slice(0, 2 * H), slice(2 * H, 2 * H + D), slice(2 * H + D, zb), slice(zb, zb + 6 * R)

    @property
    def translation_states(self) -> tuple:
        """Where ``tau``'s translation (its first 3 entries) and each previous one's in ``l_j`` start: a constant
        shift of the translation moves all of them alike (its increments unchanged)."""
        D = self.motion_dim
        return (self.slices[1].start,) + tuple(self.lags.start + D * j for j in range(self.ar_order))

    @property
    def lags(self) -> slice:
        """The previous translations (fields) ``l`` (D p)."""
        start = self.slices[3].stop
        return slice(start, start + self.motion_dim * self.ar_order)

    def without_input(self) -> InputBlock:
        """The same block with the input's oscillators ``z_p`` pinned at zero (prior mean 0, prior and random walk
        1e-12 in state units): the model's input stays zero, so the patch deforms by its own dynamics only while
        the rigid motion is unchanged. An ablation: what the estimated input adds to the predictions."""
        zp = self.slices[0]
        mean0, std0, q = self.mean0.copy(), self.std0.copy(), self.noise_std.copy()
        mean0[zp], std0[zp], q[zp] = 0.0, 1e-12, 1e-12
        return replace(self, mean0=mean0, std0=std0, noise_std=q)

    def with_frequency(self, frequency_hz: float, respiration_hz: float | None = None) -> InputBlock:
        """The same block at another heart rate (and respiration rate): the GE's samples of the sampled rates."""
        if respiration_hz is None or self.respiration_harmonics == 0:
            return replace(self, frequency_hz=float(frequency_hz))
        return replace(self, frequency_hz=float(frequency_hz), respiration_hz=float(respiration_hz))

    def _oscillators(self):
        """``(start, frequency, harmonic)`` of every 2-D oscillator."""
        H, Hr, R = self.harmonics, self.rigid_harmonics, self.respiration_harmonics
        zr, zb = self.slices[2].start, self.slices[3].start
        out = [(2 * (h - 1), self.frequency_hz, h) for h in range(1, H + 1)]
        for a in range(3):
            out += [(zr + 2 * Hr * a + 2 * (h - 1), self.frequency_hz, h) for h in range(1, Hr + 1)]
            out += [(zb + 2 * R * a + 2 * (r - 1), self.respiration_hz, r) for r in range(1, R + 1)]
        return out

    def transition(self) -> np.ndarray:
        """T (m, m): a rotation by ``2 pi h f dt`` per oscillator (f the heart or the respiration rate); for the
        translation the identity, or with ``rigid_ar`` ``tau' = tau + sum_i A_i (l_(i-1) - l_i)`` (``l_0 = tau``),
        ``l_1' = tau``, ``l_j' = l_(j-1)``."""
        T = np.eye(self.size)
        for i, f, h in self._oscillators():
            T[i:i + 2, i:i + 2] = _rotation(2 * np.pi * h * f * self.dt)
        p, D = self.ar_order, self.motion_dim
        if p:
            tau = self.slices[1].start
            col = [tau] + [self.lags.start + D * j for j in range(p)]     # tau, l_1 .. l_p
            for i in range(1, p + 1):
                A = self.rigid_ar[i - 1]
                T[tau:tau + D, col[i - 1]:col[i - 1] + D] += A
                T[tau:tau + D, col[i]:col[i] + D] -= A
            for j in range(p):
                r = self.lags.start + D * j
                T[r:r + D, :] = 0.0
                T[r:r + D, col[j]:col[j] + D] = np.eye(D)
        return T

    def input_maps(self):
        """``(P0, P1)`` (n_u, m): the model's inputs at the start and the end of a frame from the block's state at
        its start (``P1 = P0 T``)."""
        P0 = np.zeros((self.n_u, self.size))
        P0[self.column, 0:2 * self.harmonics:2] = self.input_scale
        return P0, P0 @ self.transition()

    def translation_map(self) -> np.ndarray:
        """G (3, m): the rigid translation of every point (with a displacement field, that of the field's
        centre)."""
        H, Hr, R = self.harmonics, self.rigid_harmonics, self.respiration_harmonics
        zr, zb = self.slices[2].start, self.slices[3].start
        G = np.zeros((3, self.size))
        G[:, 2 * H:2 * H + 3] = np.eye(3)
        for a in range(3):
            G[a, zr + 2 * Hr * a:zr + 2 * Hr * (a + 1):2] = 1.0
            G[a, zb + 2 * R * a:zb + 2 * R * (a + 1):2] = 1.0
        return G

    def motion_maps(self, points) -> np.ndarray:
        """G_p (P, 3, m): the motion of points at patch-frame positions ``points`` (P, 3): the translation map
        with ``tau`` replaced by the displacement field's monomials at each point (every point alike for d = 0)."""
        X = np.asarray(points, float).reshape(-1, 3)
        G = np.repeat(self.translation_map()[None], X.shape[0], axis=0)
        if self.field_degree:
            phi = field_basis(X, self.field_degree, self.field_centre, self.field_axes, self.field_scale)  # (P, n)
            tau = self.slices[1].start
            for j in range(1, phi.shape[1]):
                G[:, :, tau + 3 * j:tau + 3 * j + 3] = phi[:, j, None, None] * np.eye(3)
        return G

    def coupling(self, B0, B1) -> np.ndarray:
        """``B0 P0 + B1 P1`` (n_x, m): the kinematic state's dependence on the block over one frame."""
        P0, P1 = self.input_maps()
        return np.asarray(B0) @ P0 + np.asarray(B1) @ P1

    def noise(self) -> np.ndarray:
        return np.diag(self.noise_std ** 2)

    def _propagated(self, M, K: int) -> np.ndarray:
        T = self.transition()
        e = self.mean0.copy()
        out = np.empty((K, M.shape[0]))
        for k in range(K):
            out[k] = M @ e
            e = T @ e
        return out

    def mean_inputs(self, K: int) -> np.ndarray:
        """The model's inputs (K, n_u) of the block's prior mean propagated without noise (the fitted input)."""
        return self._propagated(self.input_maps()[0], K)

    def mean_translation(self, K: int) -> np.ndarray:
        """The rigid translation (K, 3) of the block's prior mean propagated without noise."""
        return self._propagated(self.translation_map(), K)

    def to_dict(self) -> dict:
        return {"kind": "harmonic", "frequency_hz": float(self.frequency_hz), "harmonics": int(self.harmonics),
                "dt": float(self.dt), "n_u": int(self.n_u), "column": int(self.column),
                "input_scale": float(self.input_scale), "respiration_hz": float(self.respiration_hz),
                "respiration_harmonics": int(self.respiration_harmonics),
                "rigid_harmonics": int(self.rigid_harmonics), "rigid_ar": self.rigid_ar.tolist(),
                "field_degree": int(self.field_degree), "field_centre_m": list(self.field_centre),
                "field_axes": [list(r) for r in self.field_axes], "field_scale_m": float(self.field_scale),
                "centred": bool(self.centred),
                "mean0": self.mean0.tolist(),
                "std0": self.std0.tolist(), "noise_std": self.noise_std.tolist()}

    @classmethod
    def from_dict(cls, d: dict, dt: float | None = None) -> "InputBlock":
        """The block of a parameters file's ``estimated_input``; ``dt`` another frame interval (the rotation and
        the random walk per frame follow it). ValueError naming the key."""
        if not isinstance(d, dict) or d.get("kind") != "harmonic":
            raise ValueError("kind: 'harmonic' expected")
        try:
            fd = int(d.get("field_degree", 0))
            if not 0 <= fd <= MAX_FIELD_DEGREE:
                raise ValueError(f"field_degree: 0..{MAX_FIELD_DEGREE} expected, got {fd}")
            D = 3 * len(field_powers(fd))
            blk = cls(float(d["frequency_hz"]), int(d["harmonics"]), float(d["dt"]), int(d["n_u"]), int(d["column"]),
                      np.asarray(d["mean0"], float), np.asarray(d["std0"], float),
                      np.asarray(d["noise_std"], float), float(d.get("input_scale", 1.0)),
                      float(d.get("respiration_hz", 0.0)), int(d.get("respiration_harmonics", 0)),
                      None if d.get("rigid_harmonics") is None else int(d["rigid_harmonics"]),
                      None if d.get("rigid_ar") is None else np.asarray(d["rigid_ar"], float).reshape(-1, D, D),
                      fd, tuple(np.asarray(d.get("field_centre_m", (0.0, 0.0, 0.0)), float).reshape(-1)),
                      float(d.get("field_scale_m", 1.0)),
                      None if d.get("field_axes") is None else np.asarray(d["field_axes"], float),
                      _flag(d.get("centred", False), "centred"))
        except KeyError as exc:
            raise ValueError(f"{exc.args[0]}: missing") from None
        except (TypeError, ValueError) as exc:
            raise ValueError(str(exc)) from None
        if dt is not None and abs(dt - blk.dt) > 1e-9 * blk.dt:
            if blk.ar_order:
                raise ValueError(f"rigid_ar: fitted at a frame interval of {blk.dt:g} s, the measurements have "
                                 f"{dt:g} s (an autoregression does not carry over; refit)")
            blk = replace(blk, dt=float(dt), noise_std=blk.noise_std * math.sqrt(dt / blk.dt))
        return blk


def _flag(value, name: str) -> bool:
    if not isinstance(value, bool):
        raise ValueError(f"{name}: true or false expected, got {value!r}")
    return value


def _oscillator_prior(coef, drift, dt):
    """Prior mean, standard deviation and walk per frame of oscillators fitted with amplitudes ``coef``
    ([a_1, b_1, ...]): the amplitudes; ``drift`` of each harmonic's amplitude; ``drift |(a, b)| sqrt(dt)``."""
    amp = np.repeat(np.hypot(coef[0::2], coef[1::2]), 2)
    return coef, drift * amp + 1e-9, drift * amp * math.sqrt(dt) + 1e-12


def input_block_from_fit(frequency_hz, harmonics, dt, n_u, column, alpha, alpha_std, translation, times,
                         drift: float = DRIFT_PER_SQRT_S, respiration_hz: float | None = None,
                         respiration_harmonics: int = RESPIRATION_HARMONICS, rigid_harmonics: int | None = None,
                         rigid_ar_order: int | None = None, field=None, field_degree: int = 0,
                         field_frame=None, centred: bool = False) -> InputBlock:
    """The estimators' block from a fit: input amplitudes ``alpha`` (2H,) [a_1, b_1, ...] with their standard
    deviations, the fit's per-frame translation (K_fit, 3) at ``times`` (the sequence's first frames), and the
    respiration rate when one was seen (:func:`estimate_respiration`; None: no respiration oscillators).

    The prior of each oscillator is its fitted amplitude at the first frame (``[a_h, b_h]``), with standard deviation
    the fit's plus ``drift`` of the amplitude; its random walk per frame ``drift |(a_h, b_h)| sqrt(dt)``. The rigid
    motion: the heartbeat's harmonics (and the respiration's) fitted jointly to the translation, likewise; the
    random-walk translation starts where the translation minus its harmonics starts, with standard deviation the
    residual's, and moves by the residual's increments (their standard deviation per frame). ``rigid_harmonics``
    (default ``harmonics``) of the heartbeat in the rigid motion; with ``rigid_ar_order`` p > 0 the increments
    follow the vector autoregression fitted to them by least squares (:func:`fit_increment_ar`; None, the
    default: the order in 0 .. :data:`MAX_AR_ORDER` by :func:`select_increment_ar`, 0 the plain random walk), the
    random walk its residual, and the previous translations start where the translation does.

    With ``field_degree`` d > 0, ``field`` (K_fit, D - 3) holds the fit's residual displacement field per frame
    beyond the translation (the non-constant monomials' coefficients, :meth:`tracker.fit.UnknownInputProblem.
    residual_field`, in ``field_frame`` = ``(centre (3,), axes (2, 3), scale)`` of :meth:`tracker.fit.
    UnknownInputProblem.field_frame`): ``tau`` is the whole field, its non-constant part
    starting at the first frame's field with the field's standard deviation, and the vector autoregression of its
    increments is fitted to all D coordinates, the order (None: 0 .. :data:`MAX_AR_ORDER`) and ridge by
    :func:`select_field_ar` (with D^2 p coefficients the information criterion of a translation does not carry
    over). ``centred``: the fit centred the model's displacements (``translation`` is then in that gauge), and the
    estimators do too."""
    H = int(harmonics)
    Hr = H if rigid_harmonics is None else int(rigid_harmonics)
    R = int(respiration_harmonics) if respiration_hz else 0
    alpha = np.asarray(alpha, float).reshape(2 * H)
    alpha_std = np.asarray(alpha_std, float).reshape(2 * H)
    tr = np.asarray(translation, float)
    t = np.asarray(times, float)
    X = [np.ones((t.size, 1))]
    if Hr:
        X.append(harmonic_basis(t - t[0], frequency_hz, Hr))
    if R:
        X.append(harmonic_basis(t - t[0], respiration_hz, R))
    X = np.hstack(X)
    coef, *_ = np.linalg.lstsq(X, tr, rcond=None)
    resid = tr - X @ coef
    d = int(field_degree)
    D = 3 * len(field_powers(d))
    if d:
        fld = np.asarray(field, float).reshape(tr.shape[0], D - 3)
        resid = np.hstack([resid, fld - fld.mean(axis=0)])
    inc = np.diff(resid, axis=0)
    p, ridge, ar, rw_sd = _increment_dynamics(inc, d, rigid_ar_order)
    m = 2 * H + D + 6 * Hr + 6 * R + D * p
    mean0, std0, q = np.zeros(m), np.zeros(m), np.zeros(m)
    scale = float(np.sqrt(np.sum(alpha ** 2)))
    scale = scale if scale > 0 and np.isfinite(scale) else 1.0
    amp_p = np.repeat(np.hypot(alpha[0::2], alpha[1::2]), 2) / scale
    mean0[:2 * H] = alpha / scale
    std0[:2 * H] = np.hypot(alpha_std / scale, drift * amp_p) + 1e-9
    q[:2 * H] = drift * amp_p * math.sqrt(dt) + 1e-12
    tau = slice(2 * H, 2 * H + D)
    mean0[tau] = (np.concatenate([coef[0], fld.mean(axis=0)]) if d else coef[0]) + resid[0]   # the first frame's
    std0[tau] = np.std(resid, axis=0) + 1e-9
    q[tau] = rw_sd + 1e-9
    zr = 2 * H + D
    zb = zr + 6 * Hr
    for a in range(3):
        s = slice(zr + 2 * Hr * a, zr + 2 * Hr * (a + 1))
        mean0[s], std0[s], q[s] = _oscillator_prior(coef[1:1 + 2 * Hr, a], drift, dt)
        if R:
            s = slice(zb + 2 * R * a, zb + 2 * R * (a + 1))
            mean0[s], std0[s], q[s] = _oscillator_prior(coef[1 + 2 * Hr:, a], drift, dt)
    lags = slice(zb + 6 * R, m)
    mean0[lags] = np.tile(mean0[tau], p)
    std0[lags] = np.tile(std0[tau], p)
    q[lags] = 1e-12
    return InputBlock(float(frequency_hz), H, float(dt), int(n_u), int(column), mean0, std0, q, scale,
                      float(respiration_hz) if R else 0.0, R, Hr, ar, d,
                      *((tuple(field_frame[0]), float(field_frame[2]), field_frame[1]) if d
                        else ((0.0, 0.0, 0.0), 1.0, None)), bool(centred))


def _increment_dynamics(inc, degree: int, order: int | None = None):
    """``(p, ridge, A (p, D, D) or None, std of the residual per coordinate (D,))`` of a rigid motion's increments
    (K, D): the order (None: chosen, by :func:`select_increment_ar` for a translation, by :func:`select_field_ar`
    with its ridge for a field) and the autoregression fitted to them (p = 0: the random walk, the increments'
    standard deviation)."""
    inc = np.asarray(inc, float)
    ridge = 1e-6
    if degree:
        p, ridge = select_field_ar(inc, None if order is None else int(order))
    else:
        p = select_increment_ar(inc) if order is None else int(order)
    rw_sd = np.std(inc, axis=0) if inc.shape[0] > 1 else np.full(inc.shape[1], 1e-4)
    ar = None
    if p:
        ar, rw_sd = fit_increment_ar(inc, p, ridge)
    return p, float(ridge), ar, rw_sd


MIN_RELEARN_FRAMES = 10
"""Fewest frames of a filtered rigid motion :func:`with_rigid_dynamics` relearns its dynamics from."""


def with_rigid_dynamics(block: InputBlock, motion, order: int | None = None) -> tuple:
    """The block with its rigid motion's increment dynamics learned again from ``motion`` (K, D), a per-frame
    series of ``tau`` (the field's coefficients beyond the harmonics; e.g. an estimator's filtered states over the
    fitted frames, :func:`tracker.tracking.relearn_rigid_dynamics`): the order and ridge chosen as
    :func:`input_block_from_fit` chooses them (``order`` forces one), the autoregression and the random walk of
    ``tau`` (its residual) refitted, the previous fields' prior the current one's. Everything else (oscillators,
    priors of ``tau`` and of the oscillators, the field's frame) is kept. Returns ``(block, ridge)``; ValueError
    for fewer than :data:`MIN_RELEARN_FRAMES` frames or a series of the wrong width."""
    x = np.asarray(motion, float)
    D = block.motion_dim
    if x.ndim != 2 or x.shape[1] != D:
        raise ValueError(f"motion: (K, {D}) expected, got {x.shape}")
    if x.shape[0] < MIN_RELEARN_FRAMES or not np.isfinite(x).all():
        raise ValueError(f"motion: at least {MIN_RELEARN_FRAMES} finite frames expected, got {x.shape[0]}")
    p, ridge, ar, rw_sd = _increment_dynamics(np.diff(x, axis=0), block.field_degree, order)
    base = block.lags.start
    tau = block.slices[1]
    mean0 = np.concatenate([block.mean0[:base], np.tile(block.mean0[tau], p)])
    std0 = np.concatenate([block.std0[:base], np.tile(block.std0[tau], p)])
    q = np.concatenate([block.noise_std[:base], np.full(D * p, 1e-12)])
    q[tau] = rw_sd + 1e-9
    return replace(block, mean0=mean0, std0=std0, noise_std=q, rigid_ar=ar), ridge


MAX_AR_ORDER = 4
"""Largest order of the translation's increment autoregression that :func:`select_increment_ar` considers."""

MAX_FIELD_DEGREE = 2
"""Largest degree of the displacement field in the rigid motion's place (:class:`InputBlock`)."""

FIELD_DEGREE = 1
"""The degree of the rigid motion's displacement field that ``heartcv fit`` gives an estimated input by default: an
affine field, the lowest degree that holds a small rotation of the observed surface (its antisymmetric linear part)
besides the translation, and the surface's in-plane stretch and shear and its tilt (docs/model.md 17)."""

FIELD_RIDGES = (1e-3, 1e-2, 1e-1, 1.0)
"""Relative ridge penalties :func:`select_field_ar` chooses among."""

VALIDATION_FRACTION = 0.3
"""Share of the fitted frames' increments (the last ones) that :func:`select_field_ar` predicts to choose."""


def field_powers(degree: int) -> list:
    """The monomials ``u^i v^j`` of total degree <= ``degree`` as ``(i, j)``, by degree, the constant first."""
    return [(i, t - i) for t in range(int(degree) + 1) for i in range(t, -1, -1)]


def field_basis(points, degree: int, centre=(0.0, 0.0, 0.0), axes=None, scale: float = 1.0) -> np.ndarray:
    """(P, n) the monomials of :func:`field_powers` at ``(u, v) = axes (X - centre) / scale`` of ``points`` (P, 3)
    (``axes`` (2, 3); None: x and y)."""
    X = np.asarray(points, float)
    A = np.eye(3)[:2] if axes is None else np.asarray(axes, float)
    uv = (X - np.asarray(centre, float)) @ A.T / float(scale)
    return np.stack([uv[:, 0] ** i * uv[:, 1] ** j for i, j in field_powers(degree)], axis=1)


def _lagged(d, p: int, start: int) -> np.ndarray:
    """Rows k = start .. K-1 of ``[d_(k-1), ..., d_(k-p)]`` (K - start, D p)."""
    return np.hstack([d[start - i:d.shape[0] - i] for i in range(1, p + 1)])


def select_field_ar(increments, order: int | None = None, max_order: int = MAX_AR_ORDER,
                    ridges=FIELD_RIDGES) -> tuple:
    """The order p (given, or in 0 .. ``max_order``) and the relative ridge of :func:`fit_increment_ar` for a
    displacement field's increments (K, D), by how well they predict: each candidate is fitted to the first
    ``1 - VALIDATION_FRACTION`` of the increments and predicts the rest one step ahead; the least sum of squared
    errors wins (p = 0, the random walk, predicts no increment). Returns ``(p, ridge)``."""
    d = np.asarray(increments, float)
    if d.ndim != 2:
        raise ValueError(f"increments: (K, D) expected, got {d.shape}")
    n_val = int(round(VALIDATION_FRACTION * d.shape[0]))
    orders = [int(order)] if order is not None else list(range(0, int(max_order) + 1))
    best, best_err = (0, float(ridges[0])), float(np.sum(d[d.shape[0] - n_val:] ** 2))
    if order is not None and int(order) == 0:
        return best
    train_end = d.shape[0] - n_val
    for p in orders:
        if p == 0 or train_end < p + 3 or n_val < 1:
            continue
        for ridge in ridges:
            W = _ar_solve(d[:train_end], p, float(ridge))
            Z = _lagged(d, p, train_end)
            err = float(np.sum((d[train_end:] - Z @ W) ** 2))
            if err < best_err or (order is not None and best[0] == 0):
                best, best_err = (p, float(ridge)), err
    return best


def _ar_solve(d, p: int, ridge: float) -> np.ndarray:
    """W (D p, D) of ``d_k ~ [d_(k-1) .. d_(k-p)] W`` by ridge regression (``ridge`` times the normal matrix's mean
    diagonal)."""
    Z = _lagged(d, p, p)
    Y = d[p:]
    G = Z.T @ Z
    G[np.diag_indices_from(G)] += ridge * float(np.mean(np.diag(G))) + 1e-300
    return np.linalg.solve(G, Z.T @ Y)


def select_increment_ar(increments, max_order: int = MAX_AR_ORDER) -> int:
    """The order p in 0 .. ``max_order`` of :func:`fit_increment_ar` with the least Bayesian information criterion
    ``n log det(Sigma_w) + D^2 p log n`` over the same rows (n = K - ``max_order``) for every order; p = 0 is the
    random walk (white increments, ``Sigma_w`` their second moment). Fewer frames than the largest order needs
    lower it."""
    d = np.asarray(increments, float)
    if d.ndim != 2:
        raise ValueError(f"increments: (K, D) expected, got {d.shape}")
    D = d.shape[1]
    top = min(int(max_order), max(0, (d.shape[0] - 5) // 4))
    n = d.shape[0] - top
    best, best_bic = 0, np.inf
    for p in range(0, top + 1):
        Y = d[top:]
        if p:
            Z = _lagged(d, p, top)
            E = Y - Z @ np.linalg.lstsq(Z, Y, rcond=None)[0]
        else:
            E = Y
        sign, logdet = np.linalg.slogdet(E.T @ E / n)
        bic = n * logdet + D * D * p * np.log(n) if sign > 0 else np.inf
        if bic < best_bic:
            best, best_bic = p, bic
    return best


def fit_increment_ar(increments, order: int, ridge: float = 1e-6):
    """Least-squares vector autoregression of a translation's (or a displacement field's) increments (K, D):
    ``d_k = sum_i A_i d_(k-i) + w_k``, i = 1 .. ``order``. Returns ``(A (order, D, D), std of w per coordinate
    (D,))``; ``ridge`` (relative to the normal matrix's mean diagonal) guards a singular system, or with a field's
    many coefficients (:func:`select_field_ar`) shrinks them. A translation (D = 3) needs ``3 p + 5`` increments,
    a field ``p + 5`` (the ridge determines the rest)."""
    d = np.asarray(increments, float)
    p = int(order)
    need = 3 * p + 5 if d.ndim == 2 and d.shape[1] == 3 else p + 5
    if d.ndim != 2 or d.shape[1] % 3 or d.shape[0] < need:
        raise ValueError(f"increments: at least {need} frames of (K, D) expected for an order-{p} "
                         f"autoregression, got {d.shape}")
    D = d.shape[1]
    W = _ar_solve(d, p, ridge)                                                # Y ~ Z W
    A = np.stack([W[D * (i - 1):D * i].T for i in range(1, p + 1)])
    return A, np.std(d[p:] - _lagged(d, p, p) @ W, axis=0)


# -- the block in the estimators' matrices ---------------------------------------------------------------------------

def extend_observation(H, n_points: int, block: InputBlock, points=None) -> np.ndarray:
    """``[H, G_1; H, G_2; ...]``: every point moves by the block's rigid translation ``G e``, or with a displacement
    field (``block.field_degree`` > 0) by the field at its patch-frame position ``points`` (n_points, 3). With
    ``block.centred`` the model's rows ``H`` are centred over the points (their mean subtracted), as the fit's."""
    H = np.asarray(H, float)
    if block.centred:
        Hp = H.reshape(int(n_points), 3, -1)
        H = (Hp - Hp.mean(axis=0)).reshape(H.shape)
    if block.field_degree:
        if points is None or np.shape(points) != (int(n_points), 3):
            raise ValueError(f"points: the ({n_points}, 3) patch-frame positions of the points expected for a "
                             "displacement field")
        G = block.motion_maps(points).reshape(3 * int(n_points), block.size)
    else:
        G = np.tile(block.translation_map(), (int(n_points), 1))
    return np.hstack([H, G])


def extend_prior(mean, cov, block: InputBlock):
    """The linear block's prior extended by ``e ~ N(mean0, diag(std0^2))`` (uncorrelated with the rest)."""
    n, m = mean.size, block.size
    out = np.zeros((n + m, n + m))
    out[:n, :n] = cov
    out[n:, n:] = np.diag(block.std0 ** 2)
    return np.concatenate([mean, block.mean0]), out


def extend_noise(Q, block: InputBlock) -> np.ndarray:
    n = Q.shape[0]
    out = np.zeros((n + block.size, n + block.size))
    out[:n, :n] = Q
    out[n:, n:] = block.noise()
    return out


def extend_transition(A, B0, B1, block: InputBlock) -> np.ndarray:
    """``[[A, C], [0, T]]`` with ``C = [B0 P0 + B1 P1; 0]`` (A (n, n) may already carry static states after the
    model's ``n_x = B0.shape[0]`` kinematic ones)."""
    n, m, n_x = A.shape[0], block.size, B0.shape[0]
    out = np.zeros((n + m, n + m))
    out[:n, :n] = A
    out[:n_x, n:] = block.coupling(B0, B1)
    out[n:, n:] = block.transition()
    return out


def prior_input(block: InputBlock, known_u0) -> np.ndarray:
    """The model's inputs at the first frame: the known ones plus the block's prior mean."""
    P0, _ = block.input_maps()
    return np.asarray(known_u0, float) + P0 @ block.mean0


def known_inputs(meas, model, block: InputBlock) -> np.ndarray:
    """The model's inputs (K, n_u) recorded in ``meas``, the block's column (and any other missing one) zero."""
    out = np.zeros((meas.n_frames, len(model.input_names)))
    for j, name in enumerate(model.input_names):
        if j != block.column and name in meas.input_names:
            out[:, j] = meas.input_columns([name])[:, 0]
    return out
