"""tracker/baselines.py: the per-point predictors without physics (issue 16), against brute-force loops and exact
signals."""

import numpy as np
import pytest
from scipy import signal

from heartcv.tracker.baselines import dominant_frequency, predict_constvel, predict_harmonic, predict_hold, run_baseline
from heartcv.tracker.simulate import simulate, to_measurements


def _tracks(rng, K=120, P=6, gaps=0.2):
    t = np.arange(K) / 30.0
    y = rng.normal(size=(K, P, 3)).cumsum(axis=0)
    y[rng.random((K, P)) < gaps] = np.nan
    return t, y


def test_hold_and_constvel_equal_brute_force_loops(rng):
    t, y = _tracks(rng)
    hold, cv = predict_hold(t, y), predict_constvel(t, y)
    K, P = y.shape[:2]
    for p in range(P):
        seen = []
        for k in range(K):
            if not seen:
                assert np.isnan(hold[k, p]).all() and np.isnan(cv[k, p]).all()
            elif len(seen) == 1:
                np.testing.assert_array_equal(hold[k, p], y[seen[-1], p])
                np.testing.assert_array_equal(cv[k, p], y[seen[-1], p])
            else:
                j1, j0 = seen[-1], seen[-2]
                np.testing.assert_array_equal(hold[k, p], y[j1, p])
                v = (y[j1, p] - y[j0, p]) / (t[j1] - t[j0])
                np.testing.assert_allclose(cv[k, p], y[j1, p] + (t[k] - t[j1]) * v, rtol=1e-12, atol=1e-12)
            if np.isfinite(y[k, p, 0]):
                seen.append(k)


def test_harmonic_is_exact_on_a_periodic_signal_with_drift(rng):
    """A periodic motion whose period is a whole number of frames, plus a linear drift: predicted exactly (to
    rounding) once two periods of history exist, gaps included; before that, constant velocity."""
    fs, f = 40.0, 1.25                                   # T = 32 frames
    t = np.arange(200) / fs
    K, P = t.size, 4
    y = np.zeros((K, P, 3))
    for p in range(P):
        for c in range(3):
            y[:, p, c] = rng.normal() + 0.02 * t
            for n in range(1, 6):
                w = 2 * np.pi * n * f * t
                y[:, p, c] += rng.normal() * np.cos(w) + rng.normal() * np.sin(w)
    gaps = y.copy()
    gaps[rng.random((K, P)) < 0.1] = np.nan
    pred = predict_harmonic(t, gaps, f, periods=2)
    ok = np.isfinite(gaps[..., 0])
    start = 2 * 32 + 1
    # where the point's previous frame and the two periods' frames are all seen, the prediction is exact
    last = np.array([[max([j for j in range(k) if ok[j, p]], default=-1) for p in range(P)] for k in range(K)])
    for k in range(start, K):
        for p in range(P):
            j = last[k, p]
            if all(ok[i, p] for i in (j, k - 32, k - 64, j - 32, j - 64)):
                np.testing.assert_allclose(pred[k, p], y[k, p], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(pred[3], predict_constvel(t, gaps)[3])
    with pytest.raises(ValueError, match="frequency"):
        predict_harmonic(t, y, 0.0)


def test_harmonic_interpolates_between_frames(rng):
    """A period that is not a whole number of frames: the earlier instants are interpolated linearly; equal to a
    brute-force loop."""
    t = np.arange(90) / 30.0
    y = rng.normal(size=(90, 2, 3)).cumsum(axis=0)
    f = 1.13
    pred = predict_harmonic(t, y, f, periods=1)
    T = 1 / f
    for k in (50, 70, 89):
        for p in range(2):
            j = k - 1

            def at(tq):
                s = tq * 30.0
                i = int(np.floor(s))
                return (1 - (s - i)) * y[i, p] + (s - i) * y[i + 1, p]
            np.testing.assert_allclose(pred[k, p], y[j, p] + at(t[k] - T) - at(t[j] - T), rtol=1e-12)


def test_dominant_frequency_against_scipy_periodogram(rng):
    """1.23 Hz motion (with harmonics, drift, noise and gaps) at 25 fps over 12 s: within 1 % of the truth, and the
    same peak bin as scipy.signal.periodogram of one coordinate; white noise alone has none."""
    fs, f = 25.0, 1.23
    t = np.arange(300) / fs
    K, P = t.size, 10
    y = np.zeros((K, P, 3))
    for p in range(P):
        a = rng.uniform(0.5, 1.5, 3)
        y[:, p] = (a * np.sin(2 * np.pi * f * t[:, None] + p) + 0.3 * a * np.sin(4 * np.pi * f * t[:, None])
                   + 0.05 * t[:, None] + 0.05 * rng.normal(size=(K, 3)))
    y[rng.random((K, P)) < 0.05] = np.nan
    est = dominant_frequency(t, y)
    assert est == pytest.approx(f, rel=0.01)
    ff, pw = signal.periodogram(np.nan_to_num(y[:, 0, 0]), fs, detrend="linear")
    assert abs(ff[np.argmax(pw)] - est) <= ff[1]
    assert np.isnan(dominant_frequency(t, rng.normal(size=(K, P, 3))))


def test_run_baseline_on_a_simulation(paper_model):
    """Shapes and conventions of the EstimateSet; on the model's own motion (60 bpm) the harmonic predictor's heart
    rate is within 1 % of the truth and it beats hold on the noise-free positions."""
    sim = simulate(paper_model, 6.0, np.random.default_rng(2), process_noise=False, initial_noise=False)
    meas = to_measurements(sim)
    import dataclasses

    clean = dataclasses.replace(meas, positions=sim.positions)
    keep = np.arange(0, meas.n_points, 2)
    out = {n: run_baseline(n, clean, keep=keep) for n in ("hold", "constvel", "harmonic")}
    h = out["harmonic"]
    assert h.meta["heart_rate_hz"] == pytest.approx(1.0, rel=0.01)
    assert h.state_mean.shape == (meas.n_frames, 0) and np.isnan(h.theta).all() and (h.nis_dof == 0).all()
    drop = np.setdiff1d(np.arange(meas.n_points), keep)
    assert np.isnan(h.predictions[:, drop]).all() and np.isfinite(h.predictions[5:, keep]).all()
    np.testing.assert_array_equal(h.filtered[:, keep], clean.positions[:, keep])
    rmse = {n: e.prediction_rmse() for n, e in out.items()}
    assert rmse["harmonic"] < 0.5 * rmse["hold"], rmse
    with pytest.raises(ValueError, match="baseline"):
        run_baseline("kf", meas)
