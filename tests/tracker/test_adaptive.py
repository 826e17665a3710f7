"""tracker/adaptive.py: covariance matching of the measurement scale and the parameters' random walk (issue 15).

Oracles: simulations of the model itself with a known noise level (the scale the filter must find is the ratio of
the true to the stated measurement variance; its NIS per dof must then be 1 within the chi-square band), and the
moment identity of the random-walk estimate on synthetic corrections drawn with a known variance."""

import dataclasses

import numpy as np
import pytest
from scipy import stats

from heartcv.tracker.adaptive import AdaptationOptions, NoiseAdaptation
from heartcv.tracker.kalman import GaussianState, UpdateResult
from heartcv.tracker.simulate import simulate, to_measurements
from heartcv.tracker.tracking import run_kalman


@pytest.fixture(scope="module")
def sim_meas(paper_model):
    sim = simulate(paper_model, 8.0, np.random.default_rng(21))
    return to_measurements(sim, {"seed": 21})


@pytest.mark.parametrize("stated", [1.0, 10.0, 0.2])
def test_measurement_scale_finds_the_true_noise(paper_model, sim_meas, stated):
    """The file states ``stated`` x the true measurement variance: the scale settles at 1 / stated (median over
    the frames after the first second within 15 %) and the NIS per dof of the run is 1 within its 95 % band."""
    meas = dataclasses.replace(sim_meas, covariances=sim_meas.covariances * stated)
    est = run_kalman(paper_model, meas, adaptation=AdaptationOptions(window_s=0.5))
    lam = est.meta["adaptation"]["measurement_scale_median"]      # (the median is insensitive to the start)
    assert lam == pytest.approx(1.0 / stated, rel=0.15)
    settled = int(round(1.0 / est.meta["dt"]))              # after the first second
    nis, dof = est.nis[settled:], est.nis_dof[settled:]
    lo, hi = stats.chi2.ppf([0.001, 0.999], dof.sum()) / dof.sum()
    # the scale follows the NIS with a lag: allow 10 % beyond the white-noise band
    assert 0.9 * lo < nis.sum() / dof.sum() < 1.1 * hi
    # without adaptation a wrong statement shows in the NIS
    plain = run_kalman(paper_model, meas)
    ratio = plain.nis[1:].sum() / plain.nis_dof[1:].sum()
    if stated != 1.0:
        assert abs(np.log(ratio)) > 0.5 * abs(np.log(stated))


def _result(nis, dof):
    return UpdateResult(GaussianState(np.zeros(1), np.eye(1)), np.zeros(dof), np.eye(dof), float(nis), dof,
                        np.ones(dof, bool), 0)


def test_random_walk_estimate_is_the_moment_identity():
    """Synthetic corrections with E[delta^2] = removed + (q* - q): the weighted mean of q_hat converges to q*
    (within 5 % over 20 000 frames), never below the floor (the configured walk), and stays at the floor when
    the data move less than expected."""
    rng = np.random.default_rng(4)
    dt = 1 / 60
    q_floor = 1e-4
    q_true = 9e-4
    ad = NoiseAdaptation(1, dt, np.array([[q_floor]]),
                         AdaptationOptions(window_s=2.0, measurement_scale=False, random_walk=True))
    removed = 3e-4
    qs = []
    for k in range(1, 20001):
        sd = np.sqrt(removed + q_true - ad.q[0])
        pred = GaussianState(np.zeros(1), np.array([[removed + 1e-4]]))
        post = GaussianState(np.array([rng.normal(0, sd)]), np.array([[1e-4]]))
        ad.observe(k, pred, post, _result(1.0, 3))
        qs.append(ad.q[0])
    assert np.mean(qs[2000:]) == pytest.approx(q_true, rel=0.05)
    assert min(qs) >= q_floor
    ad2 = NoiseAdaptation(1, dt, np.array([[q_floor]]),
                          AdaptationOptions(measurement_scale=False, random_walk=True))
    for k in range(1, 2000):
        pred = GaussianState(np.zeros(1), np.array([[removed + 1e-4]]))
        post = GaussianState(np.array([rng.normal(0, np.sqrt(removed) * 0.5)]), np.array([[1e-4]]))
        ad2.observe(k, pred, post, _result(1.0, 3))
    assert ad2.q[0] == q_floor
    assert ad2.random_walk(5, np.array([[q_floor]]))[0, 0] == q_floor


def test_scale_is_bounded_and_options_checked():
    ad = NoiseAdaptation(0, 1 / 30, np.zeros((0, 0)), AdaptationOptions(scale_max=5.0))
    for k in range(200):
        ad.observe(k, None, None, _result(1e6, 3))
    assert ad.measurement_scale(0) == 5.0
    assert ad.random_walk(1, np.zeros((0, 0))).shape == (0, 0)
    for bad in (dict(window_s=0), dict(q_max_std=-1), dict(scale_min=2.0), dict(scale_max=0.5)):
        with pytest.raises(ValueError):
            AdaptationOptions(**bad)


def test_random_walk_is_rescaled_to_the_frame_interval():
    """random_walk_std is per frame at the model file's frame_rate: a sequence at half that rate gets sqrt(2) x the
    std per frame (the same variance per second), and run_joint uses it."""
    import copy

    from heartcv.tracker.config import model_config_from_dict
    from heartcv.tracker.joint import joint_prior
    from heartcv.tracker.model import build_model
    from tests.conftest import load_yaml

    d = copy.deepcopy(load_yaml("stiffness_cycle.yaml"))
    cfg = model_config_from_dict(d)
    sd = cfg.random_walk_std_phi()
    assert sd[0] > 0
    np.testing.assert_allclose(cfg.random_walk_std_phi(1 / cfg.frame_rate), sd, rtol=1e-15)
    np.testing.assert_allclose(cfg.random_walk_std_phi(2 / cfg.frame_rate), sd * np.sqrt(2), rtol=1e-15)
    model = build_model(cfg)
    u0 = np.zeros(model.loads.shape[1])
    Q = joint_prior(model, u0, dt=2 / cfg.frame_rate).Q_n
    np.testing.assert_allclose(np.diag(Q), 2 * sd ** 2, rtol=1e-15)
