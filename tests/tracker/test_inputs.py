"""Tests for tracker.inputs against the numbers of spec model.md §5 and independent closed forms."""

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import brentq
from scipy.special import ndtr

from heartcv.tracker import inputs
from heartcv.tracker.inputs import (
    MMHG_TO_PA,
    LVParams,
    active_tension,
    cardiac_phase,
    double_hill,
    la_pressure,
    lv_beat,
    lv_pressure,
    lv_pressure_fourier_60bpm,
    respiration,
)

ML = 1e-6


# --------------------------------------------------------------------------------------------- double Hill
def test_double_hill_peak_is_one_and_starts_at_zero():
    # Independent peak location: root of d log h / dt_n = (1.9/(1+r) - 21.9 q/(1+q)) / t_n,
    # r = (t_n/0.7)^1.9, q = (t_n/1.17)^21.9.
    def dlog(x):
        r, q = (x / 0.7) ** 1.9, (x / 1.17) ** 21.9
        return 1.9 / (1 + r) - 21.9 * q / (1 + q)

    t_peak = brentq(dlog, 0.5, 1.5, xtol=1e-14)
    assert float(double_hill(t_peak)) == pytest.approx(1.0, abs=1e-9)
    dense = double_hill(np.linspace(0.0, 4.0, 400_001))
    assert dense.max() <= 1.0 + 1e-12
    assert float(double_hill(0.0)) == 0.0
    assert np.all(dense >= 0.0)


def test_double_hill_rejects_negative_and_nan():
    with pytest.raises(ValueError, match="t_n"):
        double_hill([-0.1, 0.5])
    with pytest.raises(ValueError, match="t_n"):
        double_hill(np.nan)


# ------------------------------------------------------------------------------------------- 0-D LV model
# Spec §5.1 table (mmHg, ml, mmHg/s). Tolerances: those of the brief at 60 bpm; at 90 and 120 bpm
# pressures ±4, volumes ±4, dP/dt ±200 (the spec gives those rows to fewer digits and no EDP).
TABLE = {
    60: dict(p=(124, 5), ao=(119, 72), v=(159, 67), sv=92, dpdt=1200,
             tol=dict(pmax=2, pmin=1, ao=3, v=3, sv=3, dpdt=150)),
    90: dict(p=(139, 5), ao=(133, 97), v=(147, 73), sv=74, dpdt=1380,
             tol=dict(pmax=4, pmin=1, ao=4, v=4, sv=4, dpdt=200)),
    120: dict(p=(136, 5), ao=(129, 103), v=(128, 72), sv=56, dpdt=1300,
              tol=dict(pmax=4, pmin=1, ao=4, v=4, sv=4, dpdt=200)),
}


@pytest.mark.parametrize("hr", sorted(TABLE))
def test_lv_beat_reproduces_spec_table(hr):
    row, tol = TABLE[hr], TABLE[hr]["tol"]
    beat = lv_beat(hr)
    assert beat.p_max / MMHG_TO_PA == pytest.approx(row["p"][0], abs=tol["pmax"])
    assert beat.p_min / MMHG_TO_PA == pytest.approx(row["p"][1], abs=tol["pmin"])
    assert beat.p_ao.max() / MMHG_TO_PA == pytest.approx(row["ao"][0], abs=tol["ao"])
    assert beat.p_ao.min() / MMHG_TO_PA == pytest.approx(row["ao"][1], abs=tol["ao"])
    assert beat.edv / ML == pytest.approx(row["v"][0], abs=tol["v"])
    assert beat.esv / ML == pytest.approx(row["v"][1], abs=tol["v"])
    assert (beat.edv - beat.esv) / ML == pytest.approx(row["sv"], abs=tol["sv"])
    assert beat.dpdt_max / MMHG_TO_PA == pytest.approx(row["dpdt"], abs=tol["dpdt"])
    if hr == 60:
        assert beat.edp / MMHG_TO_PA == pytest.approx(9.0, abs=1.0)


def test_lv_beat_layout_and_cache():
    beat = lv_beat(75.0)
    assert beat.t.shape == beat.p_lv.shape == beat.p_ao.shape == beat.volume.shape == (8000,)
    assert beat.t[0] == 0.0 and beat.t[-1] == pytest.approx(0.8 - 1e-4)
    assert lv_beat(75) is beat  # cached
    with pytest.raises(ValueError):
        beat.p_lv[0] = 0.0  # cached arrays are read-only


def test_lv_beat_is_periodic_and_matches_an_accurate_ode_solver():
    """One beat from the Euler end state with RK45 (written here from the spec formulas) returns to the start."""
    p = LVParams()
    beat = lv_beat(60)
    t_peak = 0.2 + 0.15 * 1.0

    def la(phi):
        g = lambda c, w: math.exp(-0.5 * ((phi - c) / w) ** 2)  # noqa: E731
        return 6.5 + 4 * g(0.92, 0.035) + 4 * g(-0.08, 0.035) + 5 * g(0.42, 0.06)

    def rhs(t, y):
        v, p_ao = y
        e = p.E_min + (p.E_max - p.E_min) * float(double_hill(t / t_peak))
        p_lv = e * (v - p.V0)
        q_mv = max(la(t) - p_lv, 0.0) / p.R_mv
        q_av = max(p_lv - p_ao, 0.0) / p.Z_c
        return [q_mv - q_av, (q_av - p_ao / p.R_p) / p.C]

    y0 = [beat.volume[0] / ML, beat.p_ao[0] / MMHG_TO_PA]
    sol = solve_ivp(rhs, (0.0, 1.0), y0, t_eval=beat.t[::50], max_step=2e-3, rtol=1e-7, atol=1e-7)
    p_lv = (p.E_min + (p.E_max - p.E_min) * double_hill(sol.t / t_peak)) * (sol.y[0] - p.V0)
    rms = np.sqrt(np.mean((p_lv - beat.p_lv[::50] / MMHG_TO_PA) ** 2))
    assert rms < 1.0  # first-order Euler error at dt = 0.1 ms
    end = solve_ivp(rhs, (0.0, 1.0), y0, max_step=2e-3, rtol=1e-7, atol=1e-7).y[:, -1]
    np.testing.assert_allclose(end, y0, atol=0.5)  # periodic steady state (ml, mmHg)


def test_lv_params_validation_names_field():
    with pytest.raises(ValueError, match="R_p"):
        LVParams(R_p=-1.0)
    with pytest.raises(ValueError, match="C"):
        LVParams(C=0.0)
    with pytest.raises(ValueError, match="E_max"):
        LVParams(E_max=0.05)
    with pytest.raises(ValueError, match="dt"):
        lv_beat(60, dt=0.01)


# ---------------------------------------------------------------------------------- LV pressure signals
def test_fourier_series_matches_0d_model_at_60bpm():
    t = np.arange(10_000) * 1e-4
    p0d = lv_pressure(t, 60.0)
    rms = np.sqrt(np.mean((lv_pressure_fourier_60bpm(t) - p0d) ** 2)) / MMHG_TO_PA
    assert rms <= 0.5  # spec: 0.3 mmHg
    # the time origin matters: a 5 ms shift already doubles the error
    shifted = np.sqrt(np.mean((lv_pressure_fourier_60bpm(t + 0.005) - p0d) ** 2)) / MMHG_TO_PA
    assert shifted > 2 * rms
    np.testing.assert_allclose(lv_pressure_fourier_60bpm(t + 1.0), lv_pressure_fourier_60bpm(t), atol=1e-6)


@pytest.mark.parametrize("hr", [60.0, 75.0, 133.0])
def test_lv_pressure_is_periodic_for_constant_hr(hr):
    rng = np.random.default_rng(1)
    t = rng.uniform(-2.0, 5.0, size=(40, 3))
    period = 60.0 / hr
    np.testing.assert_allclose(lv_pressure(t + period, hr), lv_pressure(t, hr), rtol=0, atol=1e-3)
    np.testing.assert_allclose(lv_pressure(t + 3 * period, hr, t0=0.3), lv_pressure(t, hr, t0=0.3), atol=1e-3)
    assert lv_pressure(t, hr).shape == (40, 3)


def test_lv_pressure_interpolates_the_stored_beat_linearly():
    beat = lv_beat(60)
    np.testing.assert_allclose(lv_pressure(beat.t[:500]), beat.p_lv[:500], rtol=1e-12)
    mid = 0.5 * (beat.t[100] + beat.t[101])
    assert float(lv_pressure(mid)) == pytest.approx(0.5 * (beat.p_lv[100] + beat.p_lv[101]), rel=1e-9)


def test_lv_pressure_with_rr_intervals_uses_one_0d_beat_per_hr():
    rr = [1.0, 0.5, 0.5]
    k, t_c, period = cardiac_phase([0.0, 1.0, 1.5, 2.0, 2.5], rr_intervals=rr)
    np.testing.assert_array_equal(k, [0, 1, 2, 3, 4])
    np.testing.assert_allclose(t_c, 0.0, atol=1e-12)
    np.testing.assert_allclose(period, [1.0, 0.5, 0.5, 0.5, 0.5])

    b60, b120 = lv_beat(60), lv_beat(120)
    np.testing.assert_allclose(lv_pressure(b60.t[::7], rr_intervals=rr), b60.p_lv[::7], rtol=1e-9)
    np.testing.assert_allclose(lv_pressure(1.0 + b120.t[::7], rr_intervals=rr), b120.p_lv[::7], rtol=1e-6)
    tail = np.linspace(0.0, 0.499, 101)
    np.testing.assert_allclose(lv_pressure(2.0 + tail, rr_intervals=rr), lv_pressure(1.5 + tail, rr_intervals=rr),
                               atol=1e-3)
    # not a time-scaled 60 bpm beat: systole shortens less than diastole
    scaled = np.interp(2 * b120.t, b60.t, b60.p_lv)
    assert np.sqrt(np.mean((scaled - b120.p_lv) ** 2)) / MMHG_TO_PA > 10


def test_cardiac_phase_before_and_after_listed_beats():
    rr = [1.0, 0.5, 0.8]
    k, t_c, period = cardiac_phase([-0.25, 0.99, 1.2, 1.6, 2.3, 3.2], rr_intervals=rr, t0=0.0)
    np.testing.assert_array_equal(k, [-1, 0, 1, 2, 3, 4])
    np.testing.assert_allclose(t_c, [0.75, 0.99, 0.2, 0.1, 0.0, 0.1], atol=1e-12)
    np.testing.assert_allclose(period, [1.0, 1.0, 0.5, 0.8, 0.8, 0.8])
    t = np.linspace(-3, 3, 61)
    for got, want in zip(cardiac_phase(t, rr_intervals=[0.8], t0=0.1), cardiac_phase(t, 75.0, t0=0.1)):
        np.testing.assert_allclose(got, want, atol=1e-12)


# ------------------------------------------------------------------------------------------ LA, tension
def test_la_surrogate_mean_and_waves():
    hr, mean = 75.0, 8.0
    period = 60.0 / hr
    t = (np.arange(200_000) + 0.5) / 200_000 * period  # midpoint rule over one beat
    p = la_pressure(t, hr, mean_mmhg=mean) / MMHG_TO_PA
    # exact mean of the spec formula: baseline plus Gaussian areas restricted to phase [0, 1)
    area = lambda a, c, w: a * w * math.sqrt(2 * math.pi) * (ndtr((1 - c) / w) - ndtr(-c / w))  # noqa: E731
    exact = (mean - 1.5) + area(4, 0.92, 0.035) + area(4, -0.08, 0.035) + area(5, 0.42, 0.06)
    assert p.mean() == pytest.approx(exact, abs=1e-6)
    assert abs(p.mean() - mean) < 0.5  # "P̄ ≈ 8"
    # a-wave in late diastole (phase 0.92) and v-wave at end systole (0.42). The spec's formula gives
    # P̄ + 2.5 and P̄ + 3.5 (10.5 and 11.5 mmHg); its prose says about 12 and 13, i.e. without the -1.5.
    phi = t / period
    late, mid = phi > 0.7, (phi > 0.2) & (phi < 0.7)
    assert phi[late][np.argmax(p[late])] == pytest.approx(0.92, abs=1e-3)
    assert p[late].max() == pytest.approx(mean + 2.5, abs=1e-3)
    assert phi[mid][np.argmax(p[mid])] == pytest.approx(0.42, abs=1e-3)
    assert p[mid].max() == pytest.approx(mean + 3.5, abs=1e-3)
    # with R-R intervals the phase follows each beat's own length
    np.testing.assert_allclose(la_pressure(1.0 + 0.42 * 0.5, rr_intervals=[1.0, 0.5]) / MMHG_TO_PA, mean + 3.5,
                               atol=1e-3)


def test_active_tension_shape_and_timing():
    hr = 90.0
    t_peak = 0.2 + 0.15 * 60.0 / hr
    assert float(active_tension(0.0, hr, t_max=3.0)) == 0.0
    assert float(active_tension(0.9972050 * t_peak, hr, t_max=3.0)) == pytest.approx(3.0, abs=1e-9)
    t = np.linspace(0, 2.0, 2001)
    assert active_tension(t, hr, t_max=3.0).max() <= 3.0 + 1e-12
    np.testing.assert_allclose(active_tension(t, hr, 2.0), 2.0 * double_hill(cardiac_phase(t, hr)[1] / t_peak))
    rr_value = active_tension(1.0 + 0.9972050 * (0.2 + 0.15 * 0.5), t_max=1.0, rr_intervals=[1.0, 0.5])
    assert float(rr_value) == pytest.approx(1.0, abs=1e-9)


# ------------------------------------------------------------------------------------------ respiration
def test_respiration_closed_forms():
    amp, f = 0.005, 0.2
    e = np.array([1.0, 0.3, 0.0]) / np.hypot(1.0, 0.3)
    assert np.all(respiration(0.0, amp, f) == 0.0)
    np.testing.assert_allclose(respiration(1 / (2 * f), amp, f), amp * e, rtol=1e-12)
    t = np.linspace(0, 10, 101)
    r = respiration(t, amp, f, direction=(2.0, 0.6, 0.0))
    assert r.shape == (101, 3)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1).max(), amp, rtol=1e-12)
    np.testing.assert_allclose(np.cross(r, e), 0.0, atol=1e-15)  # along e
    # n = 1: 1 - cos^2 = sin^2
    r1 = respiration(t, amp, f, direction=(0, 0, 3.0), n=1, phase=0.4)
    np.testing.assert_allclose(r1[:, 2], amp * np.sin(np.pi * f * t - 0.4) ** 2, atol=1e-15)
    assert respiration(np.zeros((4, 2)), amp, f).shape == (4, 2, 3)


# ------------------------------------------------------------------------------------------- bad inputs
@pytest.mark.parametrize("fn", [lv_pressure, la_pressure, active_tension, cardiac_phase, lv_pressure_fourier_60bpm,
                                respiration])
def test_non_finite_time_is_rejected(fn):
    with pytest.raises(ValueError, match="t"):
        fn(np.array([0.0, np.nan]))
    with pytest.raises(ValueError, match="t"):
        fn(np.inf)


@pytest.mark.parametrize("hr", [0.0, 19.9, 251.0, np.nan, -60.0])
@pytest.mark.parametrize("fn", [lv_pressure, la_pressure, active_tension, cardiac_phase])
def test_invalid_heart_rate_is_rejected(fn, hr):
    with pytest.raises(ValueError, match="heart_rate_bpm"):
        fn(0.5, heart_rate_bpm=hr)


def test_other_bad_inputs():
    with pytest.raises(ValueError, match="heart_rate_bpm"):
        lv_beat(0.0)
    with pytest.raises(ValueError, match="rr_intervals"):
        lv_pressure(0.5, rr_intervals=[1.0, 0.1])
    with pytest.raises(ValueError, match="rr_intervals"):
        cardiac_phase(0.5, rr_intervals=[])
    with pytest.raises(ValueError, match="amplitude"):
        respiration(0.0, amplitude=-0.001)
    with pytest.raises(ValueError, match="frequency_hz"):
        respiration(0.0, frequency_hz=0.0)
    with pytest.raises(ValueError, match="n must"):
        respiration(0.0, n=1.5)
    with pytest.raises(ValueError, match="n must"):
        respiration(0.0, n=0)
    with pytest.raises(ValueError, match="direction"):
        respiration(0.0, direction=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="t_max"):
        active_tension(0.0, t_max=-1.0)
    with pytest.raises(ValueError, match="t0"):
        lv_pressure(0.0, t0=np.nan)


def test_unit_constant():
    assert inputs.MMHG_TO_PA == 133.322387415
    assert float(la_pressure(0.42, mean_mmhg=8.0)) == pytest.approx(11.5 * 133.322387415, rel=1e-6)
