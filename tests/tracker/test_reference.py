"""The reference block (tracker/reference.py, issue 15): the points' undeformed positions corrected by static states
of the linear block.

Oracles: a simulation of the model itself whose references are shifted by a known displacement of the model (the
error a fit at the wrong stiffness leaves, docs/estimators.md 3.7): the estimated correction must find it within its
own uncertainty and bring the one-step prediction error back to that of the exact references; the GE with an
almost deterministic parameter block must equal the KF with the same block (two implementations of the
augmentation: the modal family and the dense block-diagonal transition)."""

import dataclasses

import numpy as np
import pytest

from heartcv.tracker.joint import JointOptions, run_joint
from heartcv.tracker.reference import augment_observation, reference_block
from heartcv.tracker.simulate import simulate, to_measurements
from heartcv.tracker.tracking import locate_points, run_kalman


@pytest.fixture(scope="module")
def shifted(paper_model):
    """A 6 s simulation of the paper model and the same set with every reference shifted by H_q delta, delta = 40 %
    of the static response to the peak pressure (what a fit at 1.7 x the true E leaves)."""
    sim = simulate(paper_model, 6.0, np.random.default_rng(11))
    meas = to_measurements(sim, {"seed": 11})
    pts = locate_points(paper_model, meas)
    r = paper_model.r
    q_peak = paper_model.static_state(paper_model.config.theta, sim.inputs.max(axis=0))[:r]
    delta = 0.4 * q_peak
    shift = (pts.observation.H[:, :r] @ delta).reshape(-1, 3)
    ref = meas.reference.copy()
    ref[pts.keep] += shift
    return meas, dataclasses.replace(meas, reference=ref), delta, shift


def _rmse(est):
    return float(est.prediction_rmse())


def test_estimated_references_recover_a_model_shaped_shift(paper_model, shifted):
    exact, wrong, delta, shift = shifted
    r = paper_model.r
    n = paper_model.state_dim
    block = reference_block(paper_model, paper_model.config.theta, wrong.inputs[:, :1])
    base = _rmse(run_kalman(paper_model, exact))
    fixed = _rmse(run_kalman(paper_model, wrong))
    est = run_kalman(paper_model, wrong, references="estimate")
    s = block.size
    assert s == 3 and est.meta["reference_states"] == s and est.state_mean.shape[1] == n + s
    # the shift costs the fixed references dearly; the estimated block wins it back (after its own learning)
    assert fixed > 2.0 * base, (fixed, base)
    assert _rmse(est) < 1.15 * base, (_rmse(est), base)
    # the correction: the points' reference error H_q V c = -shift, to 10 % of the shift
    c = est.state_mean[-1, n:]
    H_q = locate_points(paper_model, wrong).observation.H[:, :r]
    err = (H_q @ block.basis @ c).reshape(-1, 3) + shift
    assert np.sqrt(np.mean(err ** 2)) < 0.1 * np.sqrt(np.mean(shift ** 2))
    # (c itself is not unique: the three shapes at nu 0.3, 0.45, 0.49 are nearly collinear; V c is what counts)


def test_block_shapes_are_the_static_responses(paper_model):
    """V's columns: K(theta_j)^-1 F u_max at the model's static nus (or 0.3, 0.45, 0.49); each the model's own
    static_state; an input that never rises above 0 adds none."""
    th = paper_model.config.theta
    u = np.array([[1000.0], [12000.0], [3000.0]])
    block = reference_block(paper_model, th, u)
    nus = (paper_model.config.reduction or {}).get("static_nu") or (0.3, 0.45, 0.49)
    assert block.size == len(nus)
    for j, nu in enumerate(sorted(nus)):
        t = th.copy()
        t[4] = nu
        np.testing.assert_allclose(block.basis[:, j], paper_model.static_state(t, [12000.0])[:paper_model.r],
                                   rtol=1e-12)
    np.testing.assert_array_equal(block.std, np.ones(block.size))
    assert reference_block(paper_model, th, -u).size == 0


def test_exact_references_are_left_alone(paper_model, shifted):
    """With exact references the block's estimate stays near zero and costs little prediction accuracy."""
    exact = shifted[0]
    n = paper_model.state_dim
    base = run_kalman(paper_model, exact)
    est = run_kalman(paper_model, exact, references="estimate")
    assert _rmse(est) < 1.05 * _rmse(base)
    c = est.state_mean[-1, n:]
    sd = np.sqrt(est.state_var[-1, n:])
    assert np.abs(c / sd).max() < 4.0, c / sd
    assert (sd < 1.0).all()                        # the data pin the block down from its prior std 1


@pytest.mark.parametrize("dense", [False, True])
def test_ge_with_a_fixed_parameter_block_equals_the_kf(paper_model, shifted, dense):
    """Prior std 1e-9 on the parameters and no random walk: the GE is the KF at those parameters, reference block
    included (modal family and dense block-diagonal path)."""
    wrong = shifted[1]
    short = dataclasses.replace(wrong, times=wrong.times[:25], positions=wrong.positions[:25],
                                covariances=wrong.covariances[:25], inputs=wrong.inputs[:25],
                                views=wrong.views[:25], reprojection_rms=wrong.reprojection_rms[:25])
    kf = run_kalman(paper_model, short, references="estimate")
    M = paper_model.config.parameter_space().dim
    assert not paper_model.config.random_walk_std_phi().any()       # paper_patch.yaml: no random walk
    opts = dataclasses.replace(JointOptions.from_config(paper_model.config), dense=dense, truncation="none")
    ge = run_joint(paper_model, short, "ge", prior_std=np.full(M, 1e-9), options=opts, references="estimate")
    np.testing.assert_allclose(ge.state_mean, kf.state_mean, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(ge.predictions, kf.predictions, rtol=0, atol=1e-11)


def test_augment_observation_adds_the_position_columns(paper_model, shifted):
    obs = locate_points(paper_model, shifted[0]).observation
    r = paper_model.r
    block = reference_block(paper_model, paper_model.config.theta, shifted[0].inputs[:, :1])
    aug = augment_observation(obs, block)
    assert aug.H.shape == (obs.H.shape[0], obs.H.shape[1] + block.size)
    np.testing.assert_allclose(aug.H[:, -block.size:], obs.H[:, :r] @ block.basis, rtol=1e-15)
    np.testing.assert_array_equal(aug.H[:, :obs.H.shape[1]], obs.H)


def test_unknown_mode_is_rejected(paper_model, shifted):
    with pytest.raises(ValueError, match="references"):
        run_kalman(paper_model, shifted[0], references="guess")
    with pytest.raises(ValueError, match="references"):
        run_joint(paper_model, shifted[0], "ge", references="guess")
