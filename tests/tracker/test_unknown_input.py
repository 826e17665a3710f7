"""The input of a recording without pressure (tracker/unknown_input.py, UnknownInputProblem in tracker/fit.py) and
the patch fitted to the observed surface (tracker/patch_fit.py): issue 16."""

import copy
import dataclasses
import functools

import numpy as np
import pytest

from heartcv.tracker.config import model_config_from_dict
from heartcv.tracker.fit import UnknownInputProblem, fit
from heartcv.tracker.geometry import PatchGeometry
from heartcv.tracker.measurements import MeasurementSet
from heartcv.tracker.model import build_model
from heartcv.tracker.patch_fit import fit_observed_patch, view_extent, view_within_patch
from heartcv.tracker.simulate import simulate, to_measurements
from heartcv.tracker.tracking import run_kalman
from heartcv.tracker.unknown_input import (
    HARMONICS,
    PEAK_PROMINENCE,
    PEAK_RATIO,
    InputBlock,
    NoHeartbeat,
    NotProminent,
    estimate_heart_rate,
    filled_tracks,
    harmonic_basis,
    heart_rate_at,
    input_block_from_fit,
    peak_prominence,
)
from tests.conftest import load_yaml


def _model(bpm=72.0, noise=None, **est):
    d = copy.deepcopy(load_yaml("paper_patch.yaml"))
    d["inputs"]["pressure"]["heart_rate_bpm"] = bpm
    if noise is not None:
        d["noise"]["measurement_std"] = noise
    d["estimation"].update(est)
    return build_model(model_config_from_dict(d))


def _tracks(f, K=250, fps=25.0, P=20, noise=1e-5, seed=0, harmonics=(1.0, 0.4, 0.2)):
    rng = np.random.default_rng(seed)
    t = np.arange(K) / fps
    y = np.zeros((K, P, 3))
    for h, a in enumerate(harmonics, 1):
        ph = rng.uniform(0, 2 * np.pi, (P, 3))
        y += 1e-3 * a * rng.uniform(0.5, 1, (P, 3)) * np.cos(2 * np.pi * h * f * t[:, None, None] + ph)
    return t, y + noise * rng.standard_normal(y.shape)


def _fit_blind(meas, positions, frames):
    """What ``heartcv fit`` does to a paper-patch recording at 72 bpm whose pressure is dropped (positions
    replaced): ``(blind set, heart rate, UnknownInputProblem, FitResult, alpha, alpha_std, rigid translation)`` over
    the first ``frames`` frames, nu fitted."""
    blind = MeasurementSet(meas.times, meas.point_ids, positions, meas.covariances, meas.reference,
                           np.zeros((meas.n_frames, 0)), (), (), "patch")
    hr = estimate_heart_rate(blind.times[:frames], blind.positions[:frames])
    fm = _model(72.0, estimate=["nu"])
    prob = UnknownInputProblem(fm, blind, hr.frequency_hz, HARMONICS, 0, frames=frames)
    res = fit(fm, blind, problem=prob)
    alpha, sd, rigid = prob.input_solution(res.theta, res.reduced_chi2)
    return blind, hr, prob, res, alpha, sd, rigid


# -- heart rate --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("f", [0.87, 1.13, 2.4])
def test_heart_rate_of_periodic_tracks_within_0p2_percent(f):
    """Harmonic tracks (3 harmonics, random phases, 10 s at 25 fps, 10 um noise): the refined rate is within 0.2 %
    (the spectral peak alone has a bin of 0.1 Hz, 4-11 %)."""
    t, y = _tracks(f)
    hr = estimate_heart_rate(t, y)
    assert abs(hr.frequency_hz - f) / f < 2e-3
    assert hr.peak_ratio > 10 and hr.points == 20


def test_frames_where_nothing_is_seen_count_against_no_track():
    """Every 6th frame empty (a frame the recording lacks: dropped, repeated, unreadable) leaves each track seen in
    83 % of all frames but in every frame that holds anything: the rate as with those frames interpolated; a track
    missing from 20 % of the frames that hold others is still left out. seen_share against a count by hand."""
    from heartcv.tracker.unknown_input import seen_share

    t, y = _tracks(1.13, P=6)
    holed = y.copy()
    holed[::6] = np.nan
    holed[:50, 5] = np.nan                                 # track 5: missing in 50 of the frames that hold others
    some = np.ones(250, bool)
    some[::6] = False
    np.testing.assert_allclose(seen_share(holed), [1, 1, 1, 1, 1, 1 - np.sum(some[:50]) / some.sum()])
    assert seen_share(np.full((5, 2, 3), np.nan)).tolist() == [0.0, 0.0]
    hr = estimate_heart_rate(t, holed)
    assert hr.points == 5 and abs(hr.frequency_hz - 1.13) / 1.13 < 2e-3
    with pytest.raises(NoHeartbeat, match="90 % of the frames that hold any"):
        estimate_heart_rate(t, np.where(np.arange(250)[:, None, None] % 3 == np.arange(6)[None, :, None] % 3,
                                        np.nan, y))


def test_no_single_track_decides_the_heart_rate():
    """20 tracks at 1.13 Hz over 4 s; tracks 7 (and 12) slip in depth for 29 frames (a stereo match on the wrong
    texture): 15 mm pulls the rate of all tracks 4.7 % off, 50 mm makes them show no heartbeat at all; the rate
    without the slipped tracks is the clean one, and they are named. Clean tracks: nothing left out, the same
    result as all the tracks'."""
    from heartcv.tracker.unknown_input import _heart_rate, dominant_track

    t, y = _tracks(1.13, K=100, P=20)
    clean = estimate_heart_rate(t, y, prominent=True)
    assert clean.left_out == () and clean == _heart_rate(t, y, prominent=True)
    slipped = y.copy()
    slipped[26:55, 7, 2] += 0.015
    assert dominant_track(slipped) == 7
    pulled = _heart_rate(t, slipped, prominent=True)
    assert abs(pulled.frequency_hz - 1.13) / 1.13 > 0.04
    hr = estimate_heart_rate(t, slipped, prominent=True)
    assert hr.left_out == (7,) and abs(hr.frequency_hz - clean.frequency_hz) < 1e-3
    slipped[26:55, 7, 2] += 0.035
    with pytest.raises(NoHeartbeat, match="no periodic motion"):
        _heart_rate(t, slipped, prominent=True)
    assert estimate_heart_rate(t, slipped, prominent=True).left_out == (7,)
    slipped[40:70, 12, 0] -= 0.02
    hr = estimate_heart_rate(t, slipped, prominent=True)
    assert hr.left_out == (7, 12) and abs(hr.frequency_hz - clean.frequency_hz) < 1e-3
    with pytest.raises(NoHeartbeat, match="no periodic motion"):       # noise stays refused, with its own reason
        estimate_heart_rate(t, np.random.default_rng(4).standard_normal(y.shape) * 1e-4, prominent=True)


def test_heart_rate_of_a_simulated_patch_within_1_percent():
    """The paper patch driven by the LV pressure at 72 bpm (model simulate, noise of 0.1 mm): within 1 %."""
    m = _model(72.0)
    sim = simulate(m, 6.0, np.random.default_rng(3), process_noise=False, initial_noise=False)
    meas = to_measurements(sim)
    hr = estimate_heart_rate(meas.times, meas.positions)
    assert abs(hr.frequency_hz - 1.2) / 1.2 < 0.01


def test_no_heartbeat_short_or_aperiodic():
    t, y = _tracks(1.0, K=30)                       # 1.2 s: 1.2 beats
    with pytest.raises(NoHeartbeat, match="heartbeats"):
        estimate_heart_rate(t, y)
    rng = np.random.default_rng(1)
    with pytest.raises(NoHeartbeat, match="no periodic motion"):
        estimate_heart_rate(np.arange(250) / 25.0, rng.standard_normal((250, 20, 3)) * 1e-4)
    # the same beating tracks with their times in milliseconds (a 40-s frame interval): no heart rate can show
    # below a Nyquist frequency of 0.0125 Hz; the reason says so (it had said "too short")
    t, y = _tracks(1.0, K=250)
    assert abs(estimate_heart_rate(t, y).frequency_hz - 1.0) < 0.01
    with pytest.raises(NoHeartbeat, match=r"a frame interval of 40 s .* below the 0.5-Hz low end .* milliseconds"):
        estimate_heart_rate(1e3 * t, y)


def _drift(K, seed, P=20, fps=25.0):
    """Aperiodic tracks: each a random walk plus a random walk common to all (1e-4 m steps), no heartbeat."""
    rng = np.random.default_rng(seed)
    y = np.cumsum(rng.standard_normal((K, P, 3)), axis=0) + 3 * np.cumsum(rng.standard_normal((K, 1, 3)), axis=0)
    return np.arange(K) / fps, 1e-4 * y


def test_peak_prominence_of_a_power_law_spectrum():
    """Series of random phase whose power falls as f^-a (a = 1, 2) on the FFT grid: at 1.2-2.4 Hz the prominence is
    the closed form (3/4)^(a/2) (0.87 and 0.75) within 10 % (the median over 40 draws; the Hann window's leakage
    is the difference), far below PEAK_PROMINENCE."""
    K, dt = 250, 0.04
    f = np.fft.rfftfreq(K, dt)
    rng = np.random.default_rng(5)
    for a in (1.0, 2.0):
        amp = np.zeros_like(f)
        amp[1:] = f[1:] ** (-a / 2)
        vals = []
        for _ in range(40):
            X = amp[:, None] * np.exp(2j * np.pi * rng.uniform(size=(f.size, 60)))
            Y = np.fft.irfft(X, n=K, axis=0)
            vals += [peak_prominence(Y, dt, fp) for fp in (1.2, 1.6, 2.0, 2.4)]
        assert np.median(vals) == pytest.approx(0.75 ** (a / 2), rel=0.1)
        assert np.median(vals) < PEAK_PROMINENCE / 2
    t, y = _tracks(1.0)
    Y, _ = filled_tracks(t, y)
    assert np.isnan(peak_prominence(Y, 0.04, 9.0))          # 3 f / 2 beyond the Nyquist frequency


def test_heartbeat_prominent_drift_not():
    """A heartbeat's spectral peak is prominent (harmonic tracks at 0.87-2.4 Hz: above 50; the paper patch at
    72 bpm above 10); drift (random walks, 4 and 10 s) often passes the band-median test (measured in 18 and 35 of
    40 draws), but its peak, at the low end of the band, is seldom prominent: below PEAK_PROMINENCE in at least
    80 % of the draws that pass (measured 94 % and 86 %). The second way to pass, a peak far above the power between
    its harmonics and prominent (for a fast heart, whose own harmonics fill the band), lets at most 2 draws in 40
    more through (measured 1 and 0)."""
    for f in (0.87, 1.13, 2.4):
        assert estimate_heart_rate(*_tracks(f)).prominence > 50
    sim = simulate(_model(72.0), 6.0, np.random.default_rng(3), process_noise=False, initial_noise=False)
    meas = to_measurements(sim)
    assert estimate_heart_rate(meas.times, meas.positions).prominence > 10
    for K in (100, 250):
        passed, second_way = [], 0
        for seed in range(40):
            try:
                hr = estimate_heart_rate(*_drift(K, seed))
            except NoHeartbeat:
                continue
            if hr.peak_ratio < PEAK_RATIO:
                assert hr.background_ratio >= PEAK_RATIO and hr.prominence >= PEAK_PROMINENCE
                second_way += 1
                continue
            passed.append(hr.prominence)
        assert len(passed) >= 12 and second_way <= 2, (len(passed), second_way)
        assert np.mean(np.asarray(passed) < PEAK_PROMINENCE) >= 0.8, passed


def test_prominent_refuses_drift_and_keeps_heartbeats():
    """``estimate_heart_rate(..., prominent=True)`` (what ``heartcv fit`` uses) raises NotProminent exactly when the
    peak passes the other tests but is less than PEAK_PROMINENCE prominent: on the drift draws of the test above,
    every draw either raises NoHeartbeat with and without it, or passes without it and then raises NotProminent iff
    its prominence is below the line (at least 80 % of them, measured 94 % and 86 %); heartbeats pass unchanged."""
    for f in (0.87, 1.13, 2.4):
        t, y = _tracks(f)
        assert estimate_heart_rate(t, y, prominent=True) == estimate_heart_rate(t, y)
    for K in (100, 250):
        refused = passed = 0
        for seed in range(40):
            t, y = _drift(K, seed)
            try:
                hr = estimate_heart_rate(t, y)
            except NoHeartbeat:
                with pytest.raises(NoHeartbeat):
                    estimate_heart_rate(t, y, prominent=True)
                continue
            passed += 1
            if hr.prominence < PEAK_PROMINENCE:
                with pytest.raises(NotProminent, match="not a heartbeat"):
                    estimate_heart_rate(t, y, prominent=True)
                refused += 1
            else:
                assert estimate_heart_rate(t, y, prominent=True) == hr
        assert passed >= 12 and refused >= 0.8 * passed, (passed, refused)


def test_heart_rate_at_a_given_rate():
    """A rate given from elsewhere is used as it is (std 0), with what the spectrum shows there: for harmonic tracks
    at 1.13 Hz, given 1.13 Hz the prominence equals peak_prominence of the filled tracks at 1.13 Hz (far above the
    line) and the beats are K dt f; given 1.5 Hz (between the fundamental and its second harmonic) the prominence
    is far below it. Too few beats at the rate, or a rate outside the band, is refused; drift that the spectrum
    refuses is accepted at a given rate."""
    t, y = _tracks(1.13)
    hr = heart_rate_at(t, y, 1.13)
    Y, n = filled_tracks(t, y)
    assert hr.frequency_hz == hr.peak_hz == 1.13 and hr.std_hz == 0.0 and hr.points == n == 20
    assert hr.prominence == pytest.approx(peak_prominence(Y, 0.04, 1.13), rel=1e-9) and hr.prominence > 50
    assert hr.beats == pytest.approx(250 * 0.04 * 1.13)
    assert heart_rate_at(t, y, 1.5).prominence < 0.1
    with pytest.raises(NoHeartbeat, match="heartbeats"):
        heart_rate_at(t[:40], y[:40], 1.13)                 # 1.6 s: 1.8 beats
    with pytest.raises(ValueError, match="0.5-4 Hz"):
        heart_rate_at(t, y, 4.5)
    for seed in range(40):
        td, yd = _drift(250, seed)
        try:
            estimate_heart_rate(td, yd, prominent=True)
        except NotProminent:
            assert heart_rate_at(td, yd, 1.0).frequency_hz == 1.0
            break
    else:
        pytest.fail("no drift draw was refused as not prominent")


def test_harmonic_background_ratio_closed_form():
    """A periodic series of 8 harmonics of amplitude A each on the FFT grid (1-8 Hz, K = 200 frames at 25 fps) in
    white noise of variance s^2, 60 series: the fundamental's power over the median power at 0.5, 1.5, ... 11.5 Hz
    (between the harmonics) is 1 + A^2 (K - 1) / (6 s^2) (the symmetric Hann window: sum w = (K - 1) / 2,
    sum w^2 = 3 (K - 1) / 8), within 15 % (the median over 10 draws); white noise alone about 1; NaN when fewer
    than two such frequencies lie below the Nyquist frequency."""
    from heartcv.tracker.unknown_input import harmonic_background_ratio

    K, dt, n = 200, 0.04, 60
    t = np.arange(K) * dt
    rng = np.random.default_rng(21)
    for A in (0.5, 1.0):
        vals = []
        for _ in range(10):
            Y = rng.standard_normal((K, n))
            for h in range(1, 9):
                Y += A * np.cos(2 * np.pi * h * t[:, None] + rng.uniform(0, 2 * np.pi, n))
            vals.append(harmonic_background_ratio(Y, dt, 1.0))
        assert np.median(vals) == pytest.approx(1 + A ** 2 * (K - 1) / 6, rel=0.15)
    noise = [harmonic_background_ratio(rng.standard_normal((K, n)), dt, 1.0) for _ in range(10)]
    assert 0.7 < np.median(noise) < 1.4
    assert np.isnan(harmonic_background_ratio(rng.standard_normal((K, n)), dt, 9.0))   # 13.5 Hz > 12.5 Hz


def test_white_noise_passes_neither_test():
    """Tracks of white noise (1, 3 and 20 of them; 60, 100 and 250 frames; 30 draws each) never pass as a
    heartbeat: neither the band-median test nor the peak over the power between its harmonics (measured: 0 of
    270)."""
    for P in (1, 3, 20):
        for K in (60, 100, 250):
            for seed in range(30):
                rng = np.random.default_rng(1000 * P + K + seed)
                with pytest.raises(NoHeartbeat, match="no periodic motion"):
                    estimate_heart_rate(np.arange(K) / 25.0, rng.standard_normal((K, P, 3)) * 1e-4)


# -- the block ---------------------------------------------------------------------------------------------------
def test_oscillators_reproduce_the_harmonic_input_exactly():
    """P0 T^k e0 equals sum_h a_h cos(2 pi h f t_k) + b_h sin(..) for the block started at [a_h, b_h]; G T^k e0 the
    rigid motion's harmonics plus the translation."""
    H, f, dt = 3, 1.17, 0.04
    alpha = np.array([1.0, -0.5, 0.3, 0.2, -0.1, 0.05])
    K = 200
    t = np.arange(K) * dt
    tr = np.c_[np.cos(2 * np.pi * f * t), np.sin(4 * np.pi * f * t), 0.5 + 0 * t] * 1e-3
    blk = input_block_from_fit(f, H, dt, 2, 1, alpha, np.zeros(6), tr, t)
    u = blk.mean_inputs(K)
    np.testing.assert_allclose(u[:, 1], harmonic_basis(t, f, H) @ alpha, atol=1e-12)
    np.testing.assert_array_equal(u[:, 0], 0.0)
    np.testing.assert_allclose(blk.mean_translation(K), tr, atol=1e-12)
    P0, P1 = blk.input_maps()
    np.testing.assert_allclose(P1, P0 @ blk.transition())
    again = InputBlock.from_dict(blk.to_dict())
    np.testing.assert_array_equal(again.mean0, blk.mean0)
    half = InputBlock.from_dict(blk.to_dict(), dt / 2)        # another frame rate: the same signal at t/2 steps
    np.testing.assert_allclose(half.mean_inputs(2 * K)[::2, 1], u[:, 1], atol=1e-12)
    # the ablation pins the input at zero and leaves the rigid motion as it was
    off = blk.without_input()
    assert off.size == blk.size and np.abs(off.mean_inputs(K)).max() < 1e-9 * np.abs(u).max()
    np.testing.assert_array_equal(off.mean_translation(K), blk.mean_translation(K))
    zp = blk.slices[0]
    assert np.all(off.noise_std[zp] <= 1e-12) and np.all(off.std0[zp] <= 1e-12)
    keep = np.ones(blk.size, bool)
    keep[zp] = False
    np.testing.assert_array_equal(off.noise_std[keep], blk.noise_std[keep])
    np.testing.assert_array_equal(off.std0[keep], blk.std0[keep])


# -- the fit's profile -------------------------------------------------------------------------------------------
def test_profile_recovers_amplitudes_translation_and_offsets_exactly():
    """Noise-free positions built from the problem's own model (offsets + translation + the response to a harmonic
    input): the profile returns them to 1e-6 relative with zero residual (the linear algebra of the solve)."""
    m = _model(72.0)
    sim = simulate(m, 3.0, np.random.default_rng(0), process_noise=False, initial_noise=False)
    meas = to_measurements(sim)
    K, P = meas.n_frames, meas.n_points
    prob0 = UnknownInputProblem(m, meas, 1.2, 2, 0)
    rng = np.random.default_rng(5)
    alpha = np.array([4000.0, -2500.0, 800.0, 300.0])
    tau = np.zeros((K, 3))
    tau[1:] = 1e-3 * rng.standard_normal((K - 1, 3))
    offsets = meas.reference + 1e-4 * rng.standard_normal((P, 3))
    d0, J = prob0._design(m.config.theta)[:2]
    disp = np.zeros((K, P, 3))
    disp[prob0.seen] = d0 + np.einsum("nia,a->ni", J, alpha)
    pos = offsets[None] + tau[:, None] + disp
    clean = MeasurementSet(meas.times, meas.point_ids, pos, meas.covariances, meas.reference, np.zeros((K, 0)),
                           (), (), "patch")
    prob = UnknownInputProblem(m, clean, 1.2, 2, 0)
    a, rigid, off, res, _ = prob.solve(m.config.theta)
    np.testing.assert_allclose(a, alpha, rtol=1e-6)
    np.testing.assert_allclose(rigid, tau, atol=1e-10)
    np.testing.assert_allclose(off, offsets[prob.keep], atol=1e-10)
    assert np.abs(res).max() < 1e-10


def test_estimated_input_predicts_within_1p3_of_the_known_pressure():
    """Deliverable 1's check: the paper patch at 72 bpm (10 s at 30 fps, noise 0.1 mm), simulated with the known LV
    pressure; the pressure dropped, the fit (first 3 s) estimates the heart rate (within 1 %) and the input's
    harmonics (the default 6); the KF with the estimated input (and the fit's offsets as references: the input's
    mean is in them) predicts within 1.3x of the KF with the known pressure (measured 1.10x)."""
    m = _model(72.0)
    sim = simulate(m, 10.0, np.random.default_rng(7), process_noise=False, initial_noise=False)
    meas = to_measurements(sim)
    known = run_kalman(m, meas, m.config.theta)
    blind = MeasurementSet(meas.times, meas.point_ids, meas.positions, meas.covariances, meas.reference,
                           np.zeros((meas.n_frames, 0)), (), (), "patch")
    K = 90
    hr = estimate_heart_rate(blind.times[:K], blind.positions[:K])
    assert abs(hr.frequency_hz - 1.2) / 1.2 < 0.01
    fm = _model(72.0, estimate=["nu"])
    prob = UnknownInputProblem(fm, blind, hr.frequency_hz, HARMONICS, 0, frames=K)
    res = fit(fm, blind, problem=prob)
    assert res.converged
    alpha, sd, rigid = prob.input_solution(res.theta, res.reduced_chi2)
    blk = input_block_from_fit(hr.frequency_hz, HARMONICS, prob.dt, 1, 0, alpha, sd, rigid, blind.times[:K])
    assert prob.keep.size == blind.n_points
    ref = dataclasses.replace(blind, reference=prob.offsets(res.theta))
    est = run_kalman(m, ref, res.theta, input_block=blk)

    def err(e):
        return float(np.nanmean(np.linalg.norm(e.predictions[1:] - meas.positions[1:], axis=-1)))

    ratio = err(est) / err(known)
    assert ratio < 1.3, f"estimated / known input prediction error {ratio:.3f}"
    # the ablation (track --without-input): with the input pinned at zero only the rigid motion is left to follow
    # a deformation driven by the pressure alone (measured 3.95x)
    ablated = err(run_kalman(m, ref, res.theta, input_block=blk.without_input())) / err(est)
    assert ablated > 2.0, f"without / with the estimated input {ablated:.3f}"


def test_the_ge_samples_the_heart_rate_and_finds_the_true_one(tmp_path):
    """Deliverable 1: the heart rate among the GE's sampled parameters. The paper patch at 72 bpm (6 s), pressure
    dropped, the input fitted at the right rate; the GE starts from a rate 3 % too high (prior σ 3 %). Sampled, the
    rate comes back to within 1 % of the truth inside its 3σ band, and the GE predicts better than with the wrong
    rate held (measured 0.176 against 0.196 mm over 10 s); the file round-trips its (K, 2) rate trace."""
    from heartcv.tracker.io import read_estimates, write_estimates
    from heartcv.tracker.joint import run_joint
    from heartcv.tracker.unknown_input import RatePrior

    m = _model(72.0)
    sim = simulate(m, 6.0, np.random.default_rng(7), process_noise=False, initial_noise=False)
    meas = to_measurements(sim)
    blind = MeasurementSet(meas.times, meas.point_ids, meas.positions, meas.covariances, meas.reference,
                           np.zeros((meas.n_frames, 0)), (), (), "patch")
    K = 90
    fm = _model(72.0, estimate=["nu"])
    prob = UnknownInputProblem(fm, blind, 1.2, HARMONICS, 0, frames=K)
    res = fit(fm, blind, problem=prob)
    alpha, sd, rigid = prob.input_solution(res.theta, res.reduced_chi2)
    ref = dataclasses.replace(blind, reference=prob.offsets(res.theta))
    wrong = 1.2 * 1.03
    blk = input_block_from_fit(wrong, HARMONICS, prob.dt, 1, 0, alpha, sd, rigid, blind.times[:K])

    def err(e):
        return float(np.nanmean(np.linalg.norm(e.predictions[1:] - meas.positions[1:], axis=-1)))

    held = run_joint(m, ref, "ge", theta0=res.theta, input_block=blk)
    sampled = run_joint(m, ref, "ge", theta0=res.theta, input_block=blk, rate=RatePrior(wrong, 0.03 * wrong))
    assert held.heart_rate is None and sampled.heart_rate.shape == (meas.n_frames, 2)
    f, s = sampled.heart_rate[-1]
    assert abs(f - 1.2) < min(0.012, 3 * s), (f, s)
    assert sampled.heart_rate[0, 0] == pytest.approx(wrong, rel=0.01)
    assert err(sampled) < err(held)
    assert sampled.phi_mean.shape[1] == 1 and sampled.meta["estimated"] == ["nu"]   # E held (no pressure)
    assert sampled.meta["held_parameters"] == ["E"]
    with pytest.raises(ValueError, match="heart rate"):
        run_joint(m, ref, "ukf", theta0=res.theta, input_block=blk, rate=RatePrior(wrong, 0.01))
    with pytest.raises(ValueError, match="heart rate"):
        RatePrior(7.0)
    write_estimates(tmp_path / "ge.npz", sampled)
    np.testing.assert_array_equal(read_estimates(tmp_path / "ge.npz").heart_rate, sampled.heart_rate)


def test_with_an_estimated_input_e_is_held_or_constant():
    """The input's scale and E are not separable without a recorded pressure: with an input block the joint prior
    holds E at theta0 when other parameters are estimated (nu keeps its walk, a sampled rate follows), and estimates
    it as a constant when it is the only one; without a block E walks as the model file says."""
    from heartcv.tracker.joint import joint_prior
    from heartcv.tracker.unknown_input import RatePrior

    m = _model(72.0, random_walk_std={"E": 0.1, "nu": 0.02})
    blk = InputBlock(1.2, 1, 1 / 30, 1, 0, np.zeros(11), np.ones(11), np.full(11, 0.01))
    u0 = np.zeros(1)
    plain = joint_prior(m, u0, dt=1 / 30)
    est = joint_prior(m, u0, dt=1 / 30, input_block=blk, rate=RatePrior(1.2, 0.01))
    iE, inu = plain.space.estimated.index("E"), plain.space.estimated.index("nu")
    assert plain.Q_n[iE, iE] > 0 and est.space.estimated == ("nu",)
    assert est.Q_n.shape == (2, 2) and est.Q_n[0, 0] == plain.Q_n[inu, inu] > 0 and est.Q_n[1, 1] > 0
    np.testing.assert_allclose(est.state.cov[0, 0], plain.state.cov[inu, inu])
    only_e = _model(72.0, estimate=["E"], random_walk_std={"E": 0.1, "nu": 0.0})
    e = joint_prior(only_e, u0, dt=1 / 30, input_block=blk)
    assert e.space.estimated == ("E",) and e.Q_n[0, 0] == 0.0


def test_heart_rate_standard_error_matches_monte_carlo():
    """The profile-curvature standard error of the rate against its spread over 40 noise draws (6 s at 25 fps,
    1 mm noise on 1 mm tracks): within 0.7-1.4x (measured 1.05x), the mean within 3 sigma of the truth."""
    fs, ss = [], []
    for seed in range(40):
        t, y = _tracks(1.13, K=150, noise=1e-3, seed=seed)
        hr = estimate_heart_rate(t, y)
        fs.append(hr.frequency_hz)
        ss.append(hr.std_hz)
    ratio = np.mean(ss) / np.std(fs, ddof=1)
    assert 0.7 < ratio < 1.4, ratio
    assert abs(np.mean(fs) - 1.13) < 3 * np.std(fs, ddof=1) / np.sqrt(40)   # unbiased: 3 sigma of the mean


# -- the observed patch ------------------------------------------------------------------------------------------
def test_observed_patch_recovers_pose_and_curvature():
    """Points on the central 20 x 16 mm of a curved surface (radii 40 and 25 mm) placed 30 mm in front of the
    camera: the fitted patch's normal within 2 deg of the truth, its radii within 15 %, extent 2x the observed
    region, surface RMS < 50 um (a quadric approximates the surface; measured 18 um), no point dropped."""
    g = PatchGeometry(0.06, 0.05, 0.008, 0.040, 0.025, (9, 9, 2))
    rng = np.random.default_rng(2)
    s = rng.uniform(-0.010, 0.010, 400)
    t = rng.uniform(-0.008, 0.008, 400)
    P = g.to_patch(s, t, np.zeros_like(s))
    from scipy.spatial.transform import Rotation

    Rrp = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()     # patch -> rig rotation
    normal_true = Rrp @ np.array([0, 1.0, 0])
    c = -0.030 * normal_true                                     # the camera 30 mm along the outward normal
    X = P @ Rrp.T + c
    K = 5
    pos = np.broadcast_to(X, (K, 400, 3)).copy()
    cov = np.broadcast_to(np.eye(3) * 1e-10, (K, 400, 3, 3)).copy()
    meas = MeasurementSet(np.arange(K) / 25.0, np.arange(400), pos, cov, X, np.zeros((K, 0)), (), (), "rig")
    op = fit_observed_patch(meas, PatchGeometry(thickness=0.008, grid=(9, 9, 2)))
    n_fit = op.registration.rotation.T @ np.array([0, 1.0, 0])
    assert np.degrees(np.arccos(np.clip(n_fit @ normal_true, -1, 1))) < 2.0
    radii = sorted([op.geometry.radius_long, op.geometry.radius_circ])
    np.testing.assert_allclose(radii, [0.025, 0.040], rtol=0.15)
    assert op.registration.rms_m < 5e-5   # measured 18 um: the radii come from a quadric, not refined
    assert op.registration.on_patch.all()
    ext = sorted([op.geometry.length, op.geometry.width])
    np.testing.assert_allclose(ext, [2 * 0.016 * 0.96, 2 * 0.020 * 0.96], rtol=0.1)
    # the view's extent (2-98 % along the principal axes) decides between fitting a patch and placing the model's
    np.testing.assert_allclose(view_extent(meas), [0.020 * 0.96, 0.016 * 0.96], rtol=0.08)  # chords, not arcs
    assert view_within_patch(meas, PatchGeometry(length=0.040, width=0.045))
    assert not view_within_patch(meas, PatchGeometry(length=0.018, width=0.012))


@pytest.mark.parametrize("seed", range(4))
def test_observed_patch_does_not_slide_along_a_flat_direction(seed):
    """A view of 16 x 16 mm on a cylinder-like surface (radius 25 mm across, 1 m along), depth noise 0.3 mm, 26 mm
    from the camera: the distances to the surface barely change with a slide along the axis, so the pose refinement
    must not move the patch in-plane. Every point stays on the patch and the view stays centred on it (median
    in-plane position within 1.5 mm; measured <= 1.1 mm). A refinement free in-plane slid 5-13 mm on these draws,
    once until no point was left (a real sequence's later half: 0 of 255)."""
    from scipy.spatial.transform import Rotation

    n = 300
    g = PatchGeometry(0.06, 0.05, 0.008, 1.0, 0.025, (9, 9, 2))
    rng = np.random.default_rng(seed)
    s = rng.uniform(-0.008, 0.008, n)
    t = rng.uniform(-0.008, 0.008, n)
    P = g.to_patch(s, t, 3e-4 * rng.standard_normal(n))
    Rrp = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix()
    X = P @ Rrp.T - 0.026 * (Rrp @ np.array([0, 1.0, 0]))
    K = 5
    meas = MeasurementSet(np.arange(K) / 25.0, np.arange(n), np.broadcast_to(X, (K, n, 3)).copy(),
                          np.broadcast_to(np.eye(3) * 1e-10, (K, n, 3, 3)).copy(), X, np.zeros((K, 0)), (), (),
                          "rig")
    op = fit_observed_patch(meas, PatchGeometry(thickness=0.010, grid=(9, 9, 2)))
    reg = op.registration
    assert reg.converged and reg.on_patch.all()
    st = op.geometry.from_patch(X @ reg.rotation.T + reg.translation)
    assert np.all(np.abs(np.median(st[:, :2], axis=0)) < 1.5e-3), np.median(st[:, :2], axis=0)


# -- respiration ---------------------------------------------------------------------------------------------------
def _breathing(fr, K=300, fps=25.0, fh=1.1, amp=2e-3, noise=1e-4, seed=0):
    """A rigid translation (K, 3): a breath at ``fr`` (a sinusoid plus a 30 % second harmonic, different per axis),
    a heartbeat at ``fh`` (3 harmonics), a linear drift and white noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(K) / fps
    w = np.array([1.0, 0.5, 0.25])
    tr = amp * w * (np.cos(2 * np.pi * fr * t)[:, None] + 0.3 * np.sin(4 * np.pi * fr * t + 0.4)[:, None])
    tr += 0.5e-3 * harmonic_basis(t, fh, 3) @ rng.uniform(-1, 1, (6, 3))
    tr += 1e-4 * t[:, None] * rng.uniform(-1, 1, 3)
    return t, tr + noise * rng.standard_normal((K, 3))


@pytest.mark.parametrize("fr", [0.17, 0.25, 0.4])
def test_respiration_rate_of_a_breathing_translation_within_2_percent(fr):
    """A breath at 0.17-0.4 Hz in 12 s (2-5 breaths) under a heartbeat at 1.1 Hz and a drift: seen, within 2 %
    (the spectrum's bin is 0.083 Hz, 20-50 %), the truth within 3 of its standard errors."""
    from heartcv.tracker.unknown_input import estimate_respiration

    t, tr = _breathing(fr)
    r = estimate_respiration(t, tr, 1.1)
    assert r.seen, r.reason
    assert abs(r.frequency_hz - fr) / fr < 0.02
    assert abs(r.frequency_hz - fr) < 3 * r.std_hz and r.explained > 0.9


def test_a_rat_s_breath_is_seen_in_its_band_and_sampled_in_its_box():
    """A rat: breath at 1.8 Hz under a heartbeat at 6 Hz, 4 s at 150 fps. The default band (0.1-0.7 Hz) does not
    see it; the band 1-2.5 Hz (fit --respiration-band) finds it within 2 %; its GE prior boxes the rate there
    (respiration_prior's band; the default box refuses 1.8 Hz)."""
    from heartcv.tracker.unknown_input import estimate_respiration, respiration_prior

    t, tr = _breathing(1.8, fh=6.0, K=600, fps=150.0)
    assert not estimate_respiration(t, tr, 6.0).seen
    r = estimate_respiration(t, tr, 6.0, band=(1.0, 2.5))
    assert r.seen, r.reason
    assert abs(r.frequency_hz - 1.8) / 1.8 < 0.02
    prior = respiration_prior(r.frequency_hz, r.std_hz, (1.0, 2.5))
    assert prior.bounds_phi == pytest.approx((np.log(1.0), np.log(2.5)))
    with pytest.raises(ValueError, match="respiration rate: a frequency in 0.1-0.7 Hz expected"):
        respiration_prior(r.frequency_hz, r.std_hz)


def test_no_respiration_short_or_absent():
    """Under two breaths in the window, or no breath at all (heartbeat, drift and noise only): not seen, with the
    reason; the block built then has no respiration oscillators."""
    from heartcv.tracker.unknown_input import estimate_respiration

    t, tr = _breathing(0.2, K=200)                     # 8 s: 1.6 breaths
    r = estimate_respiration(t, tr, 1.1)
    assert not r.seen and "breaths" in r.reason
    t, tr = _breathing(0.2, amp=0.0)
    r = estimate_respiration(t, tr, 1.1)
    assert not r.seen and "no breathing rhythm" in r.reason and r.explained < 0.5
    blk = input_block_from_fit(1.1, 2, 0.04, 1, 0, np.ones(4), np.zeros(4), tr, t, respiration_hz=r.frequency_hz,
                               rigid_ar_order=0)
    assert blk.respiration_harmonics == 0 and blk.size == 8 * 2 + 3


def test_respiration_oscillators_reproduce_the_breath_exactly():
    """A translation of a heartbeat's and a breath's harmonics plus a constant: the block's mean translation
    (G T^k e0) equals it to 1e-12; the dictionary round trip and another frame rate keep it; a block written before
    respiration existed reads with none."""
    H, f, fr, dt, K = 2, 1.17, 0.23, 0.04, 250
    t = np.arange(K) * dt
    tr = (0.5e-3 + harmonic_basis(t, f, H) @ np.arange(12).reshape(4, 3) * 1e-4
          + harmonic_basis(t, fr, 2) @ np.linspace(-1, 1, 12).reshape(4, 3) * 1e-3)
    # the residual the rigid motion's autoregression would model is rounding noise here: its order is
    # pinned at 0, since 'auto' would choose among orders on noise (NumPy 2.4.6 / SciPy 1.17.1 pick 4)
    blk = input_block_from_fit(f, H, dt, 1, 0, np.ones(2 * H), np.zeros(2 * H), tr, t, respiration_hz=fr,
                               rigid_ar_order=0)
    assert blk.respiration_harmonics == 2 and blk.size == 8 * H + 3 + 12
    np.testing.assert_allclose(blk.mean_translation(K), tr, atol=1e-12)
    np.testing.assert_allclose(blk.noise_std[blk.slices[1]], 1e-9, atol=1e-12)   # nothing left for the walk
    again = InputBlock.from_dict(blk.to_dict())
    assert (again.respiration_hz, again.respiration_harmonics) == (fr, 2)
    np.testing.assert_array_equal(again.noise_std, blk.noise_std)
    np.testing.assert_allclose(again.mean_translation(K), tr, atol=1e-12)
    half = InputBlock.from_dict(blk.to_dict(), dt / 2)
    np.testing.assert_allclose(half.mean_translation(2 * K)[::2], tr, atol=1e-12)
    moved = blk.with_frequency(f, 0.3)
    np.testing.assert_allclose(moved.mean_translation(K) - moved.mean_translation(K)[0],
                               (harmonic_basis(t, f, H) @ np.arange(12).reshape(4, 3) * 1e-4
                                + harmonic_basis(t, 0.3, 2) @ np.linspace(-1, 1, 12).reshape(4, 3) * 1e-3)
                               - (harmonic_basis(t[:1], f, H) @ np.arange(12).reshape(4, 3) * 1e-4
                                  + harmonic_basis(t[:1], 0.3, 2) @ np.linspace(-1, 1, 12).reshape(4, 3) * 1e-3),
                               atol=1e-12)
    old = {k: v for k, v in input_block_from_fit(f, H, dt, 1, 0, np.ones(2 * H), np.zeros(2 * H), tr, t,
                                                 rigid_ar_order=0).to_dict().items()
           if not k.startswith("respiration")}
    assert InputBlock.from_dict(old).respiration_harmonics == 0
    with pytest.raises(ValueError, match="respiration"):
        dataclasses.replace(blk, respiration_hz=0.0)


def test_a_breathing_patch_fit_sees_the_respiration_and_the_ge_samples_it():
    """The paper patch at 72 bpm (10 s at 30 fps, noise 0.1 mm) moved rigidly by a breath at 0.3 Hz (2 mm), the
    pressure dropped. The fit (first 7.5 s: 2.25 breaths) sees the respiration within 3 %; the KF with its
    oscillators predicts better than with the random-walk translation alone; the GE samples both rates from a
    respiration rate started 5 % off (prior σ 5 %), ends within 3 % of 0.3 Hz inside 3σ, and predicts no worse than
    the KF at the fit's constants."""
    from heartcv.tracker.joint import run_joint
    from heartcv.tracker.unknown_input import RatePrior, estimate_respiration, respiration_prior

    m = _model(72.0)
    sim = simulate(m, 10.0, np.random.default_rng(7), process_noise=False, initial_noise=False)
    meas = to_measurements(sim)
    t = meas.times - meas.times[0]
    breath = 2e-3 * np.array([0.3, 1.0, 0.5]) * (np.cos(2 * np.pi * 0.3 * t) - 1)[:, None]
    K = 225
    pos = meas.positions + breath[:, None, :]
    blind, hr, prob, res, alpha, sd, rigid = _fit_blind(meas, pos, K)
    r = estimate_respiration(blind.times[:K], rigid, hr.frequency_hz)
    assert r.seen, r.reason
    assert abs(r.frequency_hz - 0.3) / 0.3 < 0.03
    ref = dataclasses.replace(blind, reference=prob.offsets(res.theta))
    with_r = input_block_from_fit(hr.frequency_hz, HARMONICS, prob.dt, 1, 0, alpha, sd, rigid, blind.times[:K],
                                  respiration_hz=r.frequency_hz)
    without = input_block_from_fit(hr.frequency_hz, HARMONICS, prob.dt, 1, 0, alpha, sd, rigid, blind.times[:K])

    def err(e):
        return float(np.nanmean(np.linalg.norm(e.predictions[1:] - pos[1:], axis=-1)))

    kf_r = run_kalman(m, ref, res.theta, input_block=with_r)
    kf_0 = run_kalman(m, ref, res.theta, input_block=without)
    assert err(kf_r) < err(kf_0), (err(kf_r), err(kf_0))
    off = dataclasses.replace(with_r, respiration_hz=0.3 * 1.05)
    ge = run_joint(m, ref, "ge", theta0=res.theta, input_block=off,
                   rate=[RatePrior(hr.frequency_hz, hr.std_hz), respiration_prior(0.3 * 1.05, 0.05 * 0.3)])
    f, s = ge.respiration_rate[-1]
    assert abs(f - 0.3) / 0.3 < 0.03 and abs(f - 0.3) < 3 * s, (f, s)
    assert ge.heart_rate.shape == ge.respiration_rate.shape == (meas.n_frames, 2)
    assert err(ge) <= 1.05 * err(kf_r), (err(ge), err(kf_r))
    with pytest.raises(ValueError, match="sampled rates"):
        run_joint(m, ref, "ge", theta0=res.theta, input_block=without,
                  rate=[RatePrior(1.2), respiration_prior(0.3)])


def test_a_drifting_view_is_rarely_taken_for_breathing():
    """False positives: of 100 random-walk translations over 12 s (a view that drifts, no breath) at most 5 are
    taken for a breathing rhythm (measured 3 of 200); white noise never."""
    from heartcv.tracker.unknown_input import estimate_respiration

    t = np.arange(300) / 25.0
    walks = sum(estimate_respiration(t, np.cumsum(np.random.default_rng(s).standard_normal((300, 3)), axis=0) * 1e-5,
                                     1.1).seen for s in range(100))
    white = sum(estimate_respiration(t, np.random.default_rng(s).standard_normal((300, 3)) * 1e-5, 1.1).seen
                for s in range(100))
    assert walks <= 5 and white == 0, (walks, white)


# -- the rigid translation's autoregression -----------------------------------------------------------------------
def _var_increments(A, K, sd, seed):
    """Increments (K, 3) of a vector autoregression ``d_k = sum_i A_i d_(k-i) + w_k``, w ~ N(0, sd^2 I)."""
    rng = np.random.default_rng(seed)
    p = len(A)
    d = np.zeros((K + 50, 3))
    for k in range(p, K + 50):
        d[k] = sum(A[i] @ d[k - 1 - i] for i in range(p)) + sd * rng.standard_normal(3)
    return d[50:]


def test_the_block_propagates_the_translation_as_its_autoregression():
    """The block's transition on ``[tau, l_1 .. l_p]`` reproduces the recursion ``tau_(k+1) = tau_k + sum_i A_i
    (tau_(k+1-i) - tau_(k-i))`` exactly (to 1e-15 of the values) from any history, with the heartbeat's
    oscillators beside it untouched; the dictionary round trip keeps it; another frame interval is refused."""
    rng = np.random.default_rng(0)
    A = 0.3 * rng.standard_normal((3, 3, 3))
    H = 2
    m = 8 * H + 3 + 9
    blk = InputBlock(1.1, H, 0.04, 1, 0, np.zeros(m), np.ones(m), np.full(m, 1e-3), rigid_ar=A)
    assert blk.size == m and blk.ar_order == 3 and blk.lags == slice(8 * H + 3, m)
    assert blk.translation_states == (2 * H, 8 * H + 3, 8 * H + 6, 8 * H + 9)
    hist = rng.standard_normal((4, 3))                      # tau_k, tau_(k-1), tau_(k-2), tau_(k-3)
    e = rng.standard_normal(m)
    e[2 * H:2 * H + 3] = hist[0]
    e[blk.lags] = hist[1:].reshape(-1)
    T = blk.transition()
    taus = list(hist[::-1])                                 # oldest first
    for _ in range(20):
        d = [taus[-j] - taus[-j - 1] for j in range(1, 4)]  # d_k, d_(k-1), d_(k-2)
        taus.append(taus[-1] + sum(A[i] @ d[i] for i in range(3)))
        e_next = T @ e
        np.testing.assert_allclose(blk.translation_map() @ e_next - blk.translation_map() @ (
            e_next - np.r_[np.zeros(2 * H), e_next[2 * H:2 * H + 3], np.zeros(m - 2 * H - 3)]), taus[-1],
            rtol=0, atol=1e-15 * max(1.0, np.abs(taus[-1]).max()))
        np.testing.assert_allclose(e_next[blk.lags], np.concatenate(taus[-2:-5:-1]), rtol=0, atol=1e-15 * 10)
        np.testing.assert_allclose(e_next[:2 * H], T[:2 * H, :2 * H] @ e[:2 * H], rtol=0, atol=1e-15)
        e = e_next
    again = InputBlock.from_dict(blk.to_dict())
    np.testing.assert_array_equal(again.rigid_ar, A)
    np.testing.assert_array_equal(again.transition(), T)
    with pytest.raises(ValueError, match="rigid_ar"):
        InputBlock.from_dict(blk.to_dict(), 0.02)
    with pytest.raises(ValueError, match="rigid_ar"):
        InputBlock(1.1, H, 0.04, 1, 0, np.zeros(m), np.ones(m), np.ones(m), rigid_ar=np.zeros((3, 2, 3)))


def test_increment_autoregression_recovers_its_coefficients_and_bic_its_order():
    """Monte Carlo with fixed seeds: a VAR(2) of the increments (3000 frames) is recovered to 0.05 per coefficient
    and its noise to 3 %; BIC picks order 2 for it, 0 for white increments (a random walk) in 10 of 10 draws, and
    at least 1 for a translation with white jitter (its increments are negatively correlated)."""
    from heartcv.tracker.unknown_input import fit_increment_ar, select_increment_ar

    A = np.array([[[0.5, 0.1, 0.0], [0.0, -0.3, 0.2], [0.1, 0.0, 0.4]],
                  [[-0.2, 0.0, 0.0], [0.1, 0.2, 0.0], [0.0, 0.0, -0.3]]])
    d = _var_increments(A, 3000, 1e-4, 1)
    est, sd = fit_increment_ar(d, 2)
    np.testing.assert_allclose(est, A, atol=0.05)
    np.testing.assert_allclose(sd, 1e-4, rtol=0.03)
    assert select_increment_ar(d) == 2
    assert select_increment_ar(_var_increments(A, 300, 1e-4, 2)) == 2
    white = [select_increment_ar(np.random.default_rng(s).standard_normal((300, 3))) for s in range(10)]
    assert white == [0] * 10, white
    jitter = np.diff(np.random.default_rng(3).standard_normal((301, 3)), axis=0)
    assert select_increment_ar(jitter) >= 1
    with pytest.raises(ValueError, match="increments"):
        fit_increment_ar(d[:8], 2)


@functools.lru_cache(maxsize=1)
def _drifting_patch():
    """The paper patch at 72 bpm, its pressure dropped, moved rigidly by a translation whose increments follow a
    VAR(1) (a smooth drift: 0.9 per axis, 0.03 mm per frame), fitted over its first 90 frames: ``(model, fitted
    frames, the set with the fit's references, the fit, block(order), err(block))``, ``block`` the fit's input
    block with that rigid order (None: BIC's), ``err`` the KF's mean one-step error against the true surface."""
    m = _model(72.0)
    sim = simulate(m, 10.0, np.random.default_rng(7), process_noise=False, initial_noise=False)
    meas = to_measurements(sim)
    drift = np.cumsum(_var_increments(np.array([0.9 * np.eye(3)]), meas.n_frames, 3e-5, 4), axis=0)[:, None, :]
    K = 90
    blind, hr, prob, res, alpha, sd, rigid = _fit_blind(meas, meas.positions + drift, K)
    ref = dataclasses.replace(blind, reference=prob.offsets(res.theta))
    truth = sim.positions + drift

    def block(order):
        return input_block_from_fit(hr.frequency_hz, HARMONICS, prob.dt, 1, 0, alpha, sd, rigid, blind.times[:K],
                                    rigid_ar_order=order)

    def err(blk):
        e = run_kalman(m, ref, res.theta, input_block=blk)
        return float(np.nanmean(np.linalg.norm(e.predictions[1:] - truth[1:], axis=-1)))

    return m, K, ref, res, block, err


def test_an_autoregressive_translation_predicts_better_than_a_random_walk():
    """The drifting paper patch (:func:`_drifting_patch`): the fit's block (first 3 s) gets order >= 1 by BIC, and
    the KF with it predicts the true surface better than with the random walk (``rigid_ar_order=0``; measured
    0.164 against 0.191 mm, 0.86x; bound 0.92x)."""
    _, _, _, _, block, err = _drifting_patch()
    fitted = block(None)
    e_ar, e_rw = err(fitted), err(block(0))
    assert fitted.ar_order >= 1
    assert e_ar < 0.92 * e_rw, (e_ar, e_rw)


# -- a smooth displacement field in the rigid motion's place ---------------------------------------------------------
def test_field_basis_and_the_block_move_each_point_by_the_field_at_its_position():
    """The block with a degree-d field moves a point at X by ``sum_j phi_j(u, v) c_j`` with the monomials by hand
    (1, u, v, u^2, u v, v^2 at ``(u, v) = axes (X - centre) / scale``), the heartbeat's rigid harmonics alike for
    every point; degree 0 is the translation map for every point. The observation needs the points' positions."""
    from heartcv.tracker.unknown_input import extend_observation, field_basis, field_powers

    assert field_powers(2) == [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2)]
    rng = np.random.default_rng(1)
    X = rng.uniform(-0.01, 0.01, (7, 3))
    centre, scale = (0.001, -0.002, 0.0005), 0.005
    axes = np.linalg.qr(rng.standard_normal((3, 2)))[0].T                       # 2 orthonormal rows
    u, v = ((X - centre) @ axes.T / scale).T
    np.testing.assert_allclose(field_basis(X, 2, centre, axes, scale),
                               np.stack([np.ones(7), u, v, u * u, u * v, v * v], axis=1), rtol=1e-14)
    H = 2
    for d, n in ((0, 1), (1, 3), (2, 6)):
        D = 3 * n
        m = 2 * H + D + 6 * H
        blk = InputBlock(1.1, H, 0.04, 1, 0, np.zeros(m), np.ones(m), np.ones(m), field_degree=d,
                         field_centre=centre, field_scale=scale, field_axes=axes)
        assert blk.size == m and blk.motion_dim == D
        e = rng.standard_normal(m)
        c = e[2 * H:2 * H + D].reshape(n, 3)
        rigid_harm = blk.translation_map() @ e - c[0]        # the heartbeat's harmonics of the rigid motion
        want = field_basis(X, d, centre, axes, scale) @ c + rigid_harm
        np.testing.assert_allclose(np.einsum("pam,m->pa", blk.motion_maps(X), e), want, rtol=1e-12, atol=1e-15)
        G = extend_observation(np.zeros((21, 4)), 7, blk, X)
        np.testing.assert_allclose((G[:, 4:] @ e).reshape(7, 3), want, rtol=1e-12, atol=1e-15)
        again = InputBlock.from_dict(blk.to_dict())
        assert (again.field_degree, again.field_centre, again.field_scale) == (d, centre, scale)
        np.testing.assert_array_equal(again.field_axes, axes)
        np.testing.assert_array_equal(again.motion_maps(X), blk.motion_maps(X))
    with pytest.raises(ValueError, match="points"):
        extend_observation(np.zeros((21, 4)), 7, blk)
    with pytest.raises(ValueError, match="field_degree"):
        InputBlock(1.1, H, 0.04, 1, 0, np.zeros(m), np.ones(m), np.ones(m), field_degree=3)
    with pytest.raises(ValueError, match="rigid_ar"):
        InputBlock(1.1, H, 0.04, 1, 0, np.zeros(m + 9), np.ones(m + 9), np.ones(m + 9), field_degree=1,
                   rigid_ar=np.zeros((1, 3, 3)))
    with pytest.raises(ValueError, match="field_axes"):
        InputBlock(1.1, H, 0.04, 1, 0, np.zeros(m), np.ones(m), np.ones(m), field_degree=2,
                   field_axes=2 * axes)


def test_the_field_block_propagates_the_field_as_its_autoregression():
    """With a degree-1 field (D = 9) and a VAR(2) of its increments, the transition reproduces ``c_(k+1) = c_k +
    sum_i A_i (c_(k+1-i) - c_(k-i))`` to 1e-15 of the values; the translation states are the first 3 of ``tau``
    and of each lag."""
    rng = np.random.default_rng(2)
    H, D, p = 1, 9, 2
    A = 0.2 * rng.standard_normal((p, D, D))
    m = 2 * H + D + 6 * H + D * p
    blk = InputBlock(1.1, H, 0.04, 1, 0, np.zeros(m), np.ones(m), np.ones(m), rigid_ar=A, field_degree=1)
    tau = slice(2 * H, 2 * H + D)
    assert blk.translation_states == (2 * H, 2 * H + D + 6 * H, 2 * H + 2 * D + 6 * H)
    hist = rng.standard_normal((p + 1, D))
    e = rng.standard_normal(m)
    e[tau] = hist[0]
    e[blk.lags] = hist[1:].reshape(-1)
    T = blk.transition()
    cs = list(hist[::-1])
    for _ in range(15):
        inc = [cs[-j] - cs[-j - 1] for j in range(1, p + 1)]
        cs.append(cs[-1] + sum(A[i] @ inc[i] for i in range(p)))
        e = T @ e
        np.testing.assert_allclose(e[tau], cs[-1], rtol=0, atol=1e-15 * max(1.0, np.abs(cs[-1]).max()) * 10)
        np.testing.assert_allclose(e[blk.lags], np.concatenate(cs[-2:-2 - p:-1]), rtol=0, atol=1e-13)


def test_field_autoregression_is_chosen_by_prediction():
    """Monte Carlo with fixed seeds: for a degree-1 field's increments (D = 9, 100 frames) following a VAR(1)
    (0.7 on the diagonal, coupled), :func:`select_field_ar` picks an order >= 1; for white increments (a random
    walk) order 0 in at least 8 of 10 draws (measured 9 of 10); the fitted coefficients of the VAR(1) at 3000
    frames are within 0.05 of the truth."""
    from heartcv.tracker.unknown_input import fit_increment_ar, select_field_ar

    rng = np.random.default_rng(4)
    D = 9
    A = 0.7 * np.eye(D) + 0.1 * rng.standard_normal((D, D))
    A *= 0.85 / max(abs(np.linalg.eigvals(A)))

    def var(K, seed):
        r = np.random.default_rng(seed)
        d = np.zeros((K + 50, D))
        for k in range(1, K + 50):
            d[k] = A @ d[k - 1] + 1e-4 * r.standard_normal(D)
        return d[50:]

    p, ridge = select_field_ar(var(100, 5))
    assert p >= 1
    white = [select_field_ar(np.random.default_rng(s).standard_normal((100, D)))[0] for s in range(10)]
    assert sum(o == 0 for o in white) >= 8, white
    est, sd = fit_increment_ar(var(3000, 6), 1, 1e-6)
    np.testing.assert_allclose(est[0], A, atol=0.05)
    assert select_field_ar(var(100, 5), order=2)[0] == 2
    assert select_field_ar(var(100, 5), order=0) == (0, select_field_ar(var(100, 5), order=0)[1])


def test_a_field_block_predicts_an_affine_motion_better_than_a_translation():
    """The paper patch at 72 bpm, its pressure dropped, with an affine displacement field added whose 9
    coefficients' increments follow a VAR(1) (0.9; 0.02 mm noise per frame, measurements 0.02 mm): the fit's
    residual field recovers the field's non-translation part (its increments at the points correlate with the
    truth's: measured 0.75, bound 0.6; over 14 points the fit's input-driven bulge and offsets take a share), and
    the KF with the degree-1 block predicts the true surface far better than with the translation alone, which
    cannot follow the points' differing motion (measured 0.196 against 5.33 mm; bound 0.5x)."""
    from heartcv.tracker.unknown_input import field_basis

    m = _model(72.0, noise=2e-5)
    sim = simulate(m, 10.0, np.random.default_rng(7), process_noise=False, initial_noise=False)
    meas = to_measurements(sim)
    K = 90
    rng = np.random.default_rng(8)
    inc = np.zeros((meas.n_frames + 50, 9))
    for k in range(1, inc.shape[0]):
        inc[k] = 0.9 * inc[k - 1] + SIGMA_FIELD * rng.standard_normal(9)
    coef = np.cumsum(inc[50:], axis=0).reshape(-1, 3, 3)                       # (K, monomial, axis)
    X = meas.reference
    centre = X.mean(axis=0)
    axes = np.linalg.svd(X - centre, full_matrices=False)[2][:2]
    phi = field_basis(X, 1, centre, axes, 0.01)                                 # (P, 3)
    motion = np.einsum("pj,kja->kpa", phi, coef)
    blind, hr, prob, res, alpha, sd, rigid = _fit_blind(meas, meas.positions + motion, K)
    frame = prob.field_frame()
    field = prob.residual_field(res.theta, 1, frame).reshape(K, 2, 3)          # the u and v monomials
    fitted = np.einsum("pj,kja->kpa", field_basis(X, 1, *frame)[:, 1:], field)
    true = np.einsum("pj,kja->kpa", phi[:, 1:], coef[:K, 1:])
    d_fit, d_true = np.diff(fitted, axis=0), np.diff(true, axis=0)
    d_fit, d_true = d_fit - d_fit.mean(axis=1, keepdims=True), d_true - d_true.mean(axis=1, keepdims=True)
    r = np.corrcoef(d_fit.ravel(), d_true.ravel())[0, 1]
    assert r > 0.6, r
    ref = dataclasses.replace(blind, reference=prob.offsets(res.theta))
    truth = sim.positions + motion

    def err(d):
        blk = input_block_from_fit(hr.frequency_hz, HARMONICS, prob.dt, 1, 0, alpha, sd, rigid, blind.times[:K],
                                   field=field.reshape(K, 6) if d else None, field_degree=d,
                                   field_frame=frame if d else None)
        e = run_kalman(m, ref, res.theta, input_block=blk)
        return float(np.nanmean(np.linalg.norm(e.predictions[1:] - truth[1:], axis=-1)))

    e1, e0 = err(1), err(0)
    assert e1 < 0.5 * e0, (e1, e0)


SIGMA_FIELD = 2e-5


def test_centring_moves_the_models_mean_displacement_into_the_translation_and_nothing_else():
    """UnknownInputProblem with ``centred=True`` on the paper patch, pressure dropped: the amplitudes, the residual,
    the cost and the offsets (the points' undeformed positions) equal the uncentred problem's (the column space is
    the same) to 1e-9 relative; the translation differs by exactly the model's mean displacement ``C q_k`` (C the
    mean displacement map over the points, q_k the model's positions); the estimators' observation with a centred
    block has rows whose mean over the points is zero in the model's columns, the block's columns unchanged."""
    from heartcv.tracker.unknown_input import extend_observation

    m = _model(72.0, estimate=["nu"])
    sim = simulate(m, 4.0, np.random.default_rng(3), process_noise=False, initial_noise=False)
    meas = to_measurements(sim)
    blind = MeasurementSet(meas.times, meas.point_ids, meas.positions, meas.covariances, meas.reference,
                           np.zeros((meas.n_frames, 0)), (), (), "patch")
    theta = m.config.theta.copy()
    u = UnknownInputProblem(m, blind, 1.2, 3, 0, frames=60)
    c = UnknownInputProblem(m, blind, 1.2, 3, 0, frames=60, centred=True)
    a_u, tau_u, off_u, res_u, _ = u.solve(theta)
    a_c, tau_c, off_c, res_c, _ = c.solve(theta)
    np.testing.assert_allclose(a_c, a_u, rtol=1e-9)
    np.testing.assert_allclose(res_c, res_u, rtol=1e-9, atol=1e-12 * np.abs(res_u).max())
    assert c.chi2(theta) == pytest.approx(u.chi2(theta), rel=1e-9)
    X = u.simulate(theta, u._U)                                    # (K, 2r, 1 + 2H)
    q = X[:, :m.r, 0] + X[:, :m.r, 1:] @ a_u                        # the model's positions with the fitted input
    mean_disp = q @ c.centring.T                                    # (K, 3)
    np.testing.assert_allclose(tau_c, tau_u + mean_disp, rtol=0, atol=1e-9 * np.abs(tau_u).max())
    np.testing.assert_allclose(off_c, off_u, rtol=0, atol=1e-9 * np.abs(off_u).max())
    H = np.random.default_rng(4).standard_normal((3 * 5, 7))
    blk = InputBlock(1.1, 1, 0.04, 1, 0, np.zeros(11), np.ones(11), np.ones(11), centred=True)
    E = extend_observation(H, 5, blk)
    np.testing.assert_allclose(E[:, :7].reshape(5, 3, 7).mean(axis=0), 0.0, atol=1e-15)
    np.testing.assert_allclose(E[:, :7], (H.reshape(5, 3, 7) - H.reshape(5, 3, 7).mean(axis=0)).reshape(15, 7))
    np.testing.assert_array_equal(E[:, 7:], np.tile(blk.translation_map(), (5, 1)))
    assert InputBlock.from_dict(blk.to_dict()).centred is True
    d = blk.to_dict()
    d["centred"] = "yes"
    with pytest.raises(ValueError, match="centred"):
        InputBlock.from_dict(d)


def _late_born(meas, motion, K=90, late=(0, 5, 9), born=120):
    """The paper-patch recording ``meas`` moved by ``motion`` (K_all, P or 1, 3), its points ``late`` first seen at
    frame ``born``, blind-fitted over its first K frames (centred, nu fitted): ``(blind set, model, problem, fit,
    alpha, alpha_std, rigid translation, heart rate)``."""
    pos = meas.positions + motion
    late = list(late)
    pos[:born, late] = np.nan
    cov = meas.covariances.copy()
    cov[:born, late] = np.nan
    blind = MeasurementSet(meas.times, meas.point_ids, pos, cov, meas.reference, np.zeros((meas.n_frames, 0)), (),
                           (), "patch")
    hr = estimate_heart_rate(blind.times[:K], blind.positions[:K])
    fm = _model(72.0, estimate=["nu"])
    prob = UnknownInputProblem(fm, blind, hr.frequency_hz, HARMONICS, 0, frames=K, centred=True)
    res = fit(fm, blind, problem=prob)
    alpha, sd, rigid = prob.input_solution(res.theta, res.reduced_chi2)
    return blind, fm, prob, res, alpha, sd, rigid, hr


def test_points_born_after_the_fit_get_references_under_the_observed_translation(monkeypatch):
    """The paper patch at 72 bpm, pressure dropped, moved by a 2 mm ramp that starts after the fitted frames (0-89);
    3 points first seen at frame 120: their undeformed references (after the common gauge shift) are as good as the
    window points' own offsets from the blind fit (measured: at most 0.42 mm off the truth, the window's up to
    0.45 mm; bound 0.6 mm), because the translation of each later frame is what the window's points show there.
    With the block's extrapolation instead, which knows nothing of the ramp, they are up to 1.41 mm off (bound: at
    least twice as far). The window's points keep their offsets exactly."""
    import heartcv.tracker.fit as fit_module
    from heartcv.tracker.fit import undeformed_references

    m = _model(72.0)
    sim = simulate(m, 10.0, np.random.default_rng(7), process_noise=False, initial_noise=False)
    meas = to_measurements(sim)
    K = 90
    ramp = np.zeros((meas.n_frames, 1, 3))
    ramp[K:, 0] = np.linspace(0.0, 1.0, meas.n_frames - K)[:, None] * np.array([2e-3, 0.0, -1e-3])
    late = [0, 5, 9]
    blind, fm, prob, res, alpha, sd, rigid, hr = _late_born(meas, ramp, K, late)
    blk = input_block_from_fit(hr.frequency_hz, HARMONICS, prob.dt, 1, 0, alpha, sd, rigid, blind.times[:K],
                               centred=True)
    out = undeformed_references(fm, blind, res.theta, K, input_block=blk)
    ids = list(out.point_ids)
    assert sorted(out.meta["late_points"]) == sorted(int(blind.point_ids[i]) for i in late)
    win = [i for i in range(blind.n_points) if i not in late]
    # the window's offsets are the fit's (the same problem, the same theta)
    np.testing.assert_allclose(out.reference[[ids.index(blind.point_ids[i]) for i in win]],
                               prob.offsets(res.theta), rtol=0, atol=1e-12)
    # the late points against the window points' own offsets: the reference differences to the true undeformed
    # positions are a common shift (the gauge, the same for all), so compare after removing the window's mean shift
    shift = np.mean(prob.offsets(res.theta) - meas.reference[prob.keep], axis=0)

    def late_error(refs):
        r = refs.reference[[list(refs.point_ids).index(blind.point_ids[i]) for i in late]]
        return np.abs(r - meas.reference[late] - shift).max()

    err = late_error(out)
    assert err < 6e-4, err
    monkeypatch.setattr(fit_module, "_observed_motion", lambda model, ms, keep, off, th, kw, field=None:
                        (kw["translation"], np.zeros((ms.n_frames, 0, 3))))
    extrapolated = late_error(undeformed_references(fm, blind, res.theta, K, input_block=blk))
    assert extrapolated > 2 * err, (extrapolated, err)


def test_points_born_after_the_fit_get_references_under_the_observed_field():
    """The paper patch at 72 bpm, pressure dropped, its view turned and stretched after the fitted frames (0-89):
    an affine displacement field along the surface that ramps from zero to a 0.1 rad turn and a 3 % stretch by the
    end (0.3-1 mm at the points), 3 points first seen at frame 120. With the block's degree-1 field, the late
    points' references take off the field the window's points show in each frame, as the estimators see it, and
    land as close to the truth as the window's own offsets from the blind fit (measured 0.45 mm, the window's up
    to 0.46 mm; bound twice the window's); with the translation alone (a degree-0 block) they keep the turn and
    stretch of their frames (measured 1.63 mm; bound: at least 2.5 times as far)."""
    from heartcv.tracker.fit import undeformed_references

    m = _model(72.0, noise=2e-5)
    sim = simulate(m, 10.0, np.random.default_rng(7), process_noise=False, initial_noise=False)
    meas = to_measurements(sim)
    K = 90
    X = meas.reference
    centre = X.mean(axis=0)
    axes = np.linalg.svd(X - centre, full_matrices=False)[2][:2]
    uv = (X - centre) @ axes.T                                                  # (P, 2) along the surface (m)
    ramp = np.clip((np.arange(meas.n_frames) - K) / (meas.n_frames - K), 0, None)[:, None, None]
    turn = np.stack([-uv[:, 1], uv[:, 0]], axis=1) * 0.1 + uv * 0.03            # (P, 2): turn + stretch
    late = [0, 5, 9]
    blind, fm, prob, res, alpha, sd, rigid, hr = _late_born(meas, ramp * (turn @ axes)[None], K, late)
    frame = prob.field_frame()
    field = prob.residual_field(res.theta, 1, frame)
    shift = np.mean(prob.offsets(res.theta) - meas.reference[prob.keep], axis=0)
    win_err = np.abs(prob.offsets(res.theta) - meas.reference[prob.keep] - shift).max()

    def late_error(d):
        blk = input_block_from_fit(hr.frequency_hz, HARMONICS, prob.dt, 1, 0, alpha, sd, rigid, blind.times[:K],
                                   field=field if d else None, field_degree=d, field_frame=frame if d else None,
                                   centred=True)
        out = undeformed_references(fm, blind, res.theta, K, input_block=blk)
        assert sorted(out.meta["late_points"]) == sorted(int(blind.point_ids[i]) for i in late)
        r = out.reference[[list(out.point_ids).index(blind.point_ids[i]) for i in late]]
        return np.abs(r - meas.reference[late] - shift).max()

    with_field, translation_only = late_error(1), late_error(0)
    assert with_field < max(2.5e-4, 2 * win_err), (with_field, win_err)
    assert translation_only > 2.5 * with_field, (translation_only, with_field)


# -- the rigid motion's dynamics relearned from the estimator's filtered motion ----------------------------------------
def test_with_rigid_dynamics_refits_the_autoregression_and_keeps_the_rest():
    """A block with a random-walk translation given 3000 frames of a VAR(2) translation: the relearned block has
    BIC's order 2, the coefficients to 0.05 and the residual's noise to 3 % (as fit_increment_ar on the same
    increments, exactly), the previous translations' prior the current one's; every other state's prior and walk
    unchanged. Too few frames or the wrong width are refused."""
    from heartcv.tracker.unknown_input import MIN_RELEARN_FRAMES, fit_increment_ar, with_rigid_dynamics

    A = np.array([[[0.5, 0.1, 0.0], [0.0, -0.3, 0.2], [0.1, 0.0, 0.4]],
                  [[-0.2, 0.0, 0.0], [0.1, 0.2, 0.0], [0.0, 0.0, -0.3]]])
    tau = np.cumsum(_var_increments(A, 3000, 1e-4, 1), axis=0)
    H = 2
    m = 8 * H + 3
    rng = np.random.default_rng(0)
    blk = InputBlock(1.1, H, 0.04, 1, 0, rng.standard_normal(m), rng.uniform(1, 2, m), rng.uniform(1, 2, m))
    new, ridge = with_rigid_dynamics(blk, tau)
    assert new.ar_order == 2 and new.size == m + 6 and new.lags == slice(m, m + 6)
    np.testing.assert_allclose(new.rigid_ar, A, atol=0.05)
    ar, sd = fit_increment_ar(np.diff(tau, axis=0), 2, ridge)
    np.testing.assert_array_equal(new.rigid_ar, ar)
    np.testing.assert_allclose(new.noise_std[2 * H:2 * H + 3], sd + 1e-9, rtol=1e-12)
    np.testing.assert_allclose(sd, 1e-4, rtol=0.03)
    tau_s = slice(2 * H, 2 * H + 3)
    keep = np.r_[0:2 * H, 2 * H + 3:m]
    np.testing.assert_array_equal(new.mean0[:m], blk.mean0)
    np.testing.assert_array_equal(new.std0[:m], blk.std0)
    np.testing.assert_array_equal(new.noise_std[keep], blk.noise_std[keep])
    np.testing.assert_array_equal(new.mean0[m:], np.tile(blk.mean0[tau_s], 2))
    np.testing.assert_array_equal(new.std0[m:], np.tile(blk.std0[tau_s], 2))
    again, _ = with_rigid_dynamics(new, tau[:500], order=0)        # back to a random walk: the lags go
    assert again.ar_order == 0 and again.size == m
    np.testing.assert_allclose(again.noise_std[tau_s], np.std(np.diff(tau[:500], axis=0), axis=0) + 1e-9)
    with pytest.raises(ValueError, match="at least"):
        with_rigid_dynamics(blk, tau[:MIN_RELEARN_FRAMES - 1])
    with pytest.raises(ValueError, match=r"\(K, 3\)"):
        with_rigid_dynamics(blk, np.zeros((50, 9)))


def test_relearning_from_the_filtered_motion_finds_the_dynamics_the_fit_missed():
    """The drifting paper patch (:func:`_drifting_patch`: a VAR(1) translation, 0.9 per axis, 0.03 mm per frame):
    a block fitted with a random-walk translation (``rigid_ar_order=0``) has its dynamics relearned
    from the KF's filtered translation over the fitted frames (relearn_rigid_dynamics): order >= 1 with positive
    diagonal coefficients (measured 0.48-0.50, the truth 0.9: 90 frames of a filtered, hence smoothed, series under
    the ridge; the fit's own order-1 block has 0.40-0.50; bound 0.3-1.0), and the KF with it predicts the true
    surface better than with the random walk (measured 0.160 against 0.191 mm; bound 0.92x) and no worse than with
    the fit's order-1 block (0.164 mm; bound 1.05x)."""
    from heartcv.tracker.tracking import relearn_rigid_dynamics

    m, K, ref, res, block, err = _drifting_patch()
    rw = block(0)
    out = relearn_rigid_dynamics(m, ref, res.theta, rw, frames=K)
    assert out.frames == K and out.order_before == 0 and out.order >= 1 and out.block.ar_order == out.order
    assert out.info() == {"source": "refit", "frames": K, "order_fit": 0, "order": out.order, "ridge": out.ridge}
    diag = np.diagonal(out.block.rigid_ar[0])
    assert np.all((diag > 0.3) & (diag < 1.0)), diag
    e_new, e_rw, e_fit = err(out.block), err(rw), err(block(None))
    assert e_new < 0.92 * e_rw, (e_new, e_rw)
    assert e_new < 1.05 * e_fit, (e_new, e_fit)


def test_a_frame_where_nothing_was_seen_inside_the_fitted_frames():
    """A frame where no point was seen (a dropped frame on the measurement grid, or one whose images could not be
    read) inside the fitted frames: the profiled rigid motion there lies on the line between its neighbours' (it
    has no data of its own; before, the normal matrix's empty rows made the amplitudes' standard deviations NaN
    and the estimators' block could not be built), the amplitudes and their standard deviations are finite and
    within 2 standard deviations of the fit with that frame seen, and the block is built."""
    m = _model(72.0)
    sim = simulate(m, 4.0, np.random.default_rng(5), process_noise=False, initial_noise=False)
    meas = to_measurements(sim)
    K, j = 90, 37
    pos = meas.positions.copy()
    _, _, _, _, alpha0, sd0, _ = _fit_blind(meas, pos, K)
    pos[j] = np.nan
    cov = meas.covariances.copy()
    cov[j] = np.nan
    meas_gap = dataclasses.replace(meas, positions=pos, covariances=cov)
    blind, hr, prob, res, alpha, sd, rigid = _fit_blind(meas_gap, pos, K)
    assert np.isfinite(rigid).all() and np.isfinite(alpha).all() and np.isfinite(sd).all()
    np.testing.assert_allclose(rigid[j], 0.5 * (rigid[j - 1] + rigid[j + 1]), rtol=1e-12, atol=1e-15)
    assert np.all(np.abs(alpha - alpha0) < 2 * np.hypot(sd, sd0)), (alpha, alpha0, sd)
    block = input_block_from_fit(hr.frequency_hz, HARMONICS, prob.dt, 1, 0, alpha, sd, rigid, blind.times[:K])
    assert np.isfinite(block.std0).all()
