"""Input signals for the heart-wall patch: LV and LA pressure, active tension, respiration.

Everything here is a pure function of time arrays (spec ``model.md`` §5). Inputs and outputs are SI: time in s,
pressure in Pa, volume in m^3, displacement in m. The 0-D LV model of §5.1 is parameterised in its native units
(mmHg, ml, s) and converted at the boundary with :data:`MMHG_TO_PA` and :data:`ML_TO_M3`.
All cardiac signals share the beat timing of :func:`cardiac_phase` (t_c = 0 at contraction onset).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
import functools
import math

import numpy as np
from scipy.optimize import minimize_scalar

MMHG_TO_PA = 133.322387415  # Pa per mmHg
ML_TO_M3 = 1e-6  # m^3 per ml
HR_RANGE_BPM = (20.0, 250.0)  # accepted heart rates (bpm), inclusive
_ONSET_TOL = 1e-9  # s; a time this close before a beat onset belongs to the new beat (floating-point sums)

_FOURIER_A0 = 45.06
_FOURIER_A = (1.65, -29.43, 1.84, -10.39, -0.06, 0.05, -1.33, 1.96, -0.88, 0.62, -0.04, -0.30)
_FOURIER_B = (62.47, -0.25, -0.88, 1.43, -7.13, 1.28, -2.96, -0.06, 0.22, -0.64, 0.63, -0.33)


def _as_time(t, name="t"):
    t = np.asarray(t, dtype=float)
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{name} must be finite (no NaN or inf)")
    return t


def _scalar(x, name, lower=-math.inf, strict=False):
    """``float(x)``, checked finite and ``>= lower`` (``> lower`` if ``strict``)."""
    x = float(x)
    if not math.isfinite(x) or x < lower or (strict and x == lower):
        raise ValueError(f"{name} must be finite and {'>' if strict else '>='} {lower}, got {x}")
    return x


def _check_hr(heart_rate_bpm):
    hr = float(heart_rate_bpm)
    lo, hi = HR_RANGE_BPM
    if not (lo <= hr <= hi):  # also rejects NaN
        raise ValueError(f"heart_rate_bpm must be within [{lo:g}, {hi:g}] bpm, got {heart_rate_bpm}")
    return hr


def _check_rr(rr_intervals):
    rr = np.asarray(rr_intervals, dtype=float)
    lo, hi = 60.0 / HR_RANGE_BPM[1], 60.0 / HR_RANGE_BPM[0]
    if rr.ndim != 1 or rr.size == 0 or not np.all((rr >= lo) & (rr <= hi)):  # also rejects NaN
        raise ValueError(f"rr_intervals must be a non-empty 1-D sequence of beat lengths within [{lo:g}, {hi:g}] s")
    return rr


def _wrap(s, period):
    """Split ``s`` into whole periods ``m`` and a remainder in ``[0, period)``, onsets snapped by ``_ONSET_TOL``."""
    m = np.floor((s + _ONSET_TOL) / period)
    return m, np.maximum(s - m * period, 0.0)


def cardiac_phase(t, heart_rate_bpm=60.0, rr_intervals=None, t0=0.0):
    """Beat index, time since beat onset and beat length at times ``t``.

    Parameters
    ----------
    t : array_like of any shape
        Times (s).
    heart_rate_bpm : float
        Constant heart rate HR (bpm, 20-250) used when ``rr_intervals`` is None; T = 60/HR.
    rr_intervals : sequence of float, optional
        Lengths (s) of beats 0, 1, ...; the last repeats afterwards, the first repeats backwards before ``t0``.
    t0 : float
        Onset of beat 0 (s).

    Returns
    -------
    beat_index, t_c, T : ndarrays of shape of ``t``
        Beat k (int64; starts at ``t0 + sum(rr[:k])``, negative before ``t0``), the time since its onset
        ``0 <= t_c < T`` (s) and its length T (s).
    """
    t = _as_time(t)
    hr = _check_hr(heart_rate_bpm)
    s = t - _scalar(t0, "t0")
    if rr_intervals is None:
        period = 60.0 / hr
        k, t_c = _wrap(s, period)
        return np.asarray(k, dtype=np.int64), np.asarray(t_c), np.full_like(s, period)
    rr = _check_rr(rr_intervals)
    starts = np.concatenate(([0.0], np.cumsum(rr[:-1])))  # onsets of the listed beats relative to t0
    k = np.clip(np.searchsorted(starts, s + _ONSET_TOL, side="right") - 1, 0, rr.size - 1)
    t_c, period = np.maximum(s - starts[k], 0.0), rr[k]
    m_before, tc_before = _wrap(s, rr[0])  # before t0: beat 0 repeated backwards
    m_after, tc_after = _wrap(s - starts[-1], rr[-1])  # from the last listed onset: last beat repeated
    before, after = s + _ONSET_TOL < 0.0, s + _ONSET_TOL >= starts[-1]
    k = np.where(before, m_before, np.where(after, rr.size - 1 + m_after, k))
    t_c = np.where(before, tc_before, np.where(after, tc_after, t_c))
    period = np.where(before, rr[0], np.where(after, rr[-1], period))
    return np.asarray(k, dtype=np.int64), np.asarray(t_c), np.asarray(period)


def _double_hill_raw(t_n):
    with np.errstate(over="ignore", divide="ignore"):  # t_n = 0 and huge t_n give exact 0 via 1/inf
        return 1.55 / (1.0 + (0.7 / t_n) ** 1.9) / (1.0 + (t_n / 1.17) ** 21.9)


@functools.cache
def _double_hill_peak():
    res = minimize_scalar(lambda x: -_double_hill_raw(x), bounds=(0.5, 1.5), method="bounded",
                          options={"xatol": 1e-12})
    return float(-res.fun)


def double_hill(t_n):
    """Normalised double-Hill elastance shape h(t_n) with peak 1 (spec §5.1, Stergiopulos-type).

    ``h = 1.55 (t_n/0.7)^1.9 / (1 + (t_n/0.7)^1.9) / (1 + (t_n/1.17)^21.9)``, divided by its maximum
    (found once by bounded scalar optimisation; the peak lies at t_n ≈ 0.997).

    Parameters
    ----------
    t_n : array_like of any shape
        Normalised time since contraction onset, t_c / (0.2 + 0.15 T) (dimensionless, >= 0).

    Returns
    -------
    ndarray of shape of ``t_n``
        h(t_n) in [0, 1]; h(0) = 0.
    """
    t_n = _as_time(t_n, "t_n")
    if np.any(t_n < 0):
        raise ValueError("t_n must be >= 0")
    return _double_hill_raw(t_n) / _double_hill_peak()


def active_tension(t, heart_rate_bpm=60.0, t_max=1.0, rr_intervals=None, t0=0.0):
    """Active fibre-tension input T_a(t) = T_max h(t_n) (spec §5.1, physics caveat).

    Parameters
    ----------
    t : array_like of any shape
        Times (s).
    heart_rate_bpm, rr_intervals, t0
        Beat timing, see :func:`cardiac_phase`.
    t_max : float
        Peak tension T_max (>= 0, in the caller's units, e.g. Pa). Not to be confused with the time to peak
        elastance 0.2 + 0.15 T (s) that sets t_n = t_c / (0.2 + 0.15 T).

    Returns
    -------
    ndarray, shape of ``t``
        T_a(t), same units as ``t_max``.
    """
    t_max = _scalar(t_max, "t_max", 0.0)
    _, t_c, period = cardiac_phase(t, heart_rate_bpm, rr_intervals, t0)
    return t_max * double_hill(t_c / (0.2 + 0.15 * period))


def _la_mmhg(phase, mean_mmhg):
    g = lambda centre, width: np.exp(-0.5 * ((phase - centre) / width) ** 2)  # noqa: E731
    return (mean_mmhg - 1.5) + 4.0 * g(0.92, 0.035) + 4.0 * g(-0.08, 0.035) + 5.0 * g(0.42, 0.06)


def la_pressure(t, heart_rate_bpm=60.0, mean_mmhg=8.0, rr_intervals=None, t0=0.0):
    """Left-atrial pressure surrogate of spec §5.2.

    With phase φ = t_c/T: ``P_la = (P̄ - 1.5) + 4 G(φ; 0.92, 0.035) + 4 G(φ; -0.08, 0.035) + 5 G(φ; 0.42, 0.06)``
    (mmHg), G a unit-height Gaussian; the second term is the wrap-around copy of the a-wave. Taken literally,
    the time mean is P̄ - 0.40 mmHg, the a-wave peaks at P̄ + 2.5 (φ = 0.92) and the v-wave at P̄ + 3.5 (φ = 0.42).

    Parameters
    ----------
    t : array_like of any shape
        Times (s).
    heart_rate_bpm, rr_intervals, t0
        Beat timing, see :func:`cardiac_phase`.
    mean_mmhg : float
        P̄ of the surrogate (mmHg).

    Returns
    -------
    ndarray, shape of ``t``
        P_la (Pa).
    """
    mean_mmhg = _scalar(mean_mmhg, "mean_mmhg")
    _, t_c, period = cardiac_phase(t, heart_rate_bpm, rr_intervals, t0)
    return _la_mmhg(t_c / period, mean_mmhg) * MMHG_TO_PA


@dataclass(frozen=True)
class LVParams:
    """Parameters of the 0-D LV model of spec §5.1, in its native units (mmHg, ml, s).

    Attributes
    ----------
    E_max, E_min : float
        Maximal and minimal elastance (mmHg/ml).
    V0 : float
        Unstressed volume (ml).
    R_mv, Z_c, R_p : float
        Mitral-valve resistance, aortic characteristic impedance, peripheral resistance (mmHg s/ml).
    C : float
        Arterial compliance (ml/mmHg).
    P_la_mean : float
        Left-atrial filling pressure P̄ (mmHg). The spec does not give P_la for Q_mv; P_la(t) is the §5.2
        surrogate with P̄ = ``P_la_mean`` (baseline 6.5 mmHg, a-wave 10.5, v-wave 11.5). With 8 mmHg the model
        reproduces the spec table at 60, 90 and 120 bpm and the Fourier series to 0.31 mmHg rms; no constant P_la
        fits all three rates (8.66 mmHg fits 60 bpm, 8.1-8.2 mmHg fit 90 and 120 bpm).
    """

    E_max: float = 2.3
    E_min: float = 0.06
    V0: float = 15.0
    R_mv: float = 0.005
    Z_c: float = 0.033
    R_p: float = 1.05
    C: float = 1.4
    P_la_mean: float = 8.0

    def __post_init__(self):
        for f in fields(self):
            value = float(getattr(self, f.name))
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{f.name} must be positive and finite, got {getattr(self, f.name)}")
            object.__setattr__(self, f.name, value)
        if self.E_max <= self.E_min:
            raise ValueError(f"E_max must exceed E_min ({self.E_min}), got {self.E_max}")


@dataclass(frozen=True, eq=False)
class LVBeat:
    """One periodic beat of the 0-D LV model (the last of the run), SI units.

    Attributes
    ----------
    t : ndarray of shape (N,)
        Time since contraction onset (s), ``t[i] = i T / N``; the beat covers ``[0, T)``.
    p_lv, p_ao : ndarray of shape (N,)
        LV and aortic pressure (Pa).
    volume : ndarray of shape (N,)
        LV volume (m^3).
    heart_rate_bpm : float
        Heart rate (bpm); T = 60 / heart_rate_bpm.
    """

    t: np.ndarray
    p_lv: np.ndarray
    p_ao: np.ndarray
    volume: np.ndarray
    heart_rate_bpm: float

    def __post_init__(self):
        n = np.shape(self.t)
        for name in ("t", "p_lv", "p_ao", "volume"):
            if np.ndim(getattr(self, name)) != 1 or np.shape(getattr(self, name)) != n or n[0] < 2:
                raise ValueError(f"{name} must have shape {n} with N >= 2, got {np.shape(getattr(self, name))}")

    p_max = property(lambda self: float(self.p_lv.max()), doc="Peak LV pressure (Pa).")
    p_min = property(lambda self: float(self.p_lv.min()), doc="Minimal LV pressure (Pa).")
    edp = property(lambda self: float(self.p_lv[0]), doc="End-diastolic LV pressure, at t = 0 (Pa).")
    edv = property(lambda self: float(self.volume.max()), doc="End-diastolic (maximal) volume (m^3).")
    esv = property(lambda self: float(self.volume.min()), doc="End-systolic (minimal) volume (m^3).")

    @property
    def dpdt_max(self):
        """Maximal dP_lv/dt (Pa/s), forward differences over the periodic beat."""
        return float(np.max(np.diff(self.p_lv, append=self.p_lv[0])) / (self.t[1] - self.t[0]))


@functools.lru_cache(maxsize=256)
def _lv_beat_cached(hr, params, dt, beats):
    period = 60.0 / hr
    n = max(int(round(period / dt)), 2)
    t = np.arange(n) * (period / n)  # step adjusted so that a beat is exactly n steps
    h = period / n
    elastance = (params.E_min + (params.E_max - params.E_min) * double_hill(t / (0.2 + 0.15 * period))).tolist()
    p_la = _la_mmhg(t / period, params.P_la_mean).tolist()
    E_min, V0, R_mv, Z_c, RpC, C = params.E_min, params.V0, params.R_mv, params.Z_c, params.R_p * params.C, params.C
    volume, p_ao = V0 + p_la[0] / E_min, 80.0  # filled ventricle at P_la, typical diastolic aortic pressure
    out = np.empty((3, n))
    for beat in range(beats):
        record = beat == beats - 1
        for i in range(n):  # explicit Euler (spec §5.1)
            p_lv = elastance[i] * (volume - V0)
            q_mv = (p_la[i] - p_lv) / R_mv if p_la[i] > p_lv else 0.0
            q_av = (p_lv - p_ao) / Z_c if p_lv > p_ao else 0.0
            if record:
                out[0, i], out[1, i], out[2, i] = p_lv, p_ao, volume
            volume += h * (q_mv - q_av)
            p_ao += h * (q_av / C - p_ao / RpC)
    out[:2] *= MMHG_TO_PA
    out[2] *= ML_TO_M3
    t.setflags(write=False)
    out.setflags(write=False)
    return LVBeat(t=t, p_lv=out[0], p_ao=out[1], volume=out[2], heart_rate_bpm=hr)


def lv_beat(heart_rate_bpm, params=LVParams(), dt=1e-4, beats=10):
    """Periodic beat of the 0-D LV model (spec §5.1): double-Hill elastance, valves, 3-element Windkessel.

    ``P_lv = E(t)(V - V0)``, ``E = E_min + (E_max - E_min) h(t_c / (0.2 + 0.15 T))``,
    ``dV/dt = Q_mv - Q_av``, ``C dP_ao/dt = Q_av - P_ao / R_p``, ``Q_mv = max(P_la - P_lv, 0) / R_mv``,
    ``Q_av = max(P_lv - P_ao, 0) / Z_c`` with P_la the §5.2 surrogate (see :class:`LVParams`). Explicit Euler
    from V = V0 + P_la(0)/E_min, P_ao = 80 mmHg for ``beats`` beats; the last is returned. Results are
    cached per (heart rate rounded to 1e-6 bpm, params, dt, beats) and their arrays are read-only.

    Parameters
    ----------
    heart_rate_bpm : float
        Heart rate HR (bpm, 20-250).
    params : LVParams
        Model parameters (mmHg, ml, s).
    dt : float
        Euler step (s); rounded so that T is a whole number of steps. Must satisfy dt E_max / min(R_mv, Z_c) < 1.
    beats : int
        Number of simulated beats (>= 1).

    Returns
    -------
    LVBeat
        The last beat, SI units.
    """
    hr = round(_check_hr(heart_rate_bpm), 6)
    if not isinstance(params, LVParams):
        raise ValueError(f"params must be an LVParams, got {type(params).__name__}")
    dt_stable = min(params.R_mv, params.Z_c) / params.E_max  # explicit-Euler stability of the valve branches
    if not (0 < _scalar(dt, "dt") < dt_stable):
        raise ValueError(f"dt must be in (0, {dt_stable:.3g}) s, got {dt}")
    if int(beats) != beats or beats < 1:
        raise ValueError(f"beats must be an integer >= 1, got {beats}")
    return _lv_beat_cached(hr, params, dt, int(beats))


def lv_pressure(t, heart_rate_bpm=60.0, rr_intervals=None, params=LVParams(), t0=0.0):
    """LV pressure at arbitrary times from the 0-D model, one periodic 0-D beat per beat length.

    Each beat uses :func:`lv_beat` at its own heart rate 60/T (not a time-scaled 60 bpm beat, since systole
    shortens less than diastole), linearly interpolated at t_c.

    Parameters
    ----------
    t : array_like of any shape
        Times (s).
    heart_rate_bpm, rr_intervals, t0
        Beat timing, see :func:`cardiac_phase`.
    params : LVParams
        0-D model parameters.

    Returns
    -------
    ndarray, shape of ``t``
        P_lv (Pa).
    """
    _, t_c, period = cardiac_phase(t, heart_rate_bpm, rr_intervals, t0)
    out = np.empty_like(t_c)
    for length in np.unique(period):
        mask = period == length
        beat = lv_beat(60.0 / length, params)
        out[mask] = np.interp(t_c[mask], beat.t, beat.p_lv, period=60.0 / beat.heart_rate_bpm)
    return out


def lv_pressure_fourier_60bpm(t):
    """Ready-made 12-harmonic LV pressure at 60 bpm (spec §5.1), t = 0 at contraction onset.

    ``P = a0 + sum_k a_k cos(2 pi k t) + b_k sin(2 pi k t)`` (mmHg, T = 1 s); matches :func:`lv_pressure` at 60 bpm
    to about 0.3 mmHg rms.

    Parameters
    ----------
    t : array_like of any shape
        Times (s).

    Returns
    -------
    ndarray, shape of ``t``
        P_lv (Pa).
    """
    t = _as_time(t)
    k = np.arange(1, 13)
    arg = 2.0 * np.pi * t[..., None] * k
    p = _FOURIER_A0 + np.cos(arg) @ np.array(_FOURIER_A) + np.sin(arg) @ np.array(_FOURIER_B)
    return p * MMHG_TO_PA


def respiration(t, amplitude=0.004, frequency_hz=0.25, direction=(1.0, 0.3, 0.0), n=2, phase=0.0):
    """Rigid breathing translation r(t) = A [1 - cos^{2n}(pi f t - phase)] e (spec §5.3, Lujan-type).

    Parameters
    ----------
    t : array_like of shape (...)
        Times (s).
    amplitude : float
        A (m, >= 0); spec range 2-8 mm.
    frequency_hz : float
        Breathing rate f = 1/tau (Hz, > 0); spec range 0.2-0.3 Hz.
    direction : array_like of shape (3,)
        Direction of motion, normalised internally to e (non-zero).
    n : int
        Dwell exponent (>= 1); n = 2 lengthens the end-expiration dwell.
    phase : float
        phi0 (rad).

    Returns
    -------
    ndarray of shape (..., 3)
        Displacement (m); zero at end-expiration (t = phase/(pi f)), ``A e`` at peak inspiration half a period later.
    """
    t = _as_time(t)
    amplitude = _scalar(amplitude, "amplitude", 0.0)
    frequency_hz = _scalar(frequency_hz, "frequency_hz", 0.0, strict=True)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be an integer >= 1, got {n!r}")
    phase = _scalar(phase, "phase")
    e = np.asarray(direction, dtype=float)
    norm = np.linalg.norm(e) if e.shape == (3,) else 0.0
    if not (np.isfinite(norm) and norm > 0):
        raise ValueError(f"direction must be a finite non-zero vector of shape (3,), got {direction!r}")
    shape = amplitude * (1.0 - np.cos(np.pi * frequency_hz * t - phase) ** (2 * int(n)))
    return shape[..., None] * (e / norm)
