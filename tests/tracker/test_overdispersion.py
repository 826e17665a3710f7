"""The parameters' update tempered by their over-dispersion (tracker/overdispersion.py, docs/estimators.md §3.11):
the normalised shift against Monte Carlo and its exact expectation, the joint state that keeps the plain conditional,
the sequential test's silence under the filter's own model, and the GE unchanged on data its model explains."""

import numpy as np
import pytest

from heartcv.tracker.kalman import GaussianState, update
from heartcv.tracker.overdispersion import ALPHA, Overdispersion, adjusted, parameter_nis, tempered_marginal

M, N_L, P = 2, 4, 5            # parameters, the rest of the state, points (3 rows each)


def _problem(seed=0, r_scale=1.0):
    """A joint prior, a measurement matrix and R; ``r_scale`` makes the measurements weak against the prior (their
    errors then dominate the parameters' shifts)."""
    rng = np.random.default_rng(seed)
    n = M + N_L
    A = rng.standard_normal((n, n))
    prior = GaussianState(rng.standard_normal(n), A @ A.T / n + 0.1 * np.eye(n))
    H = rng.standard_normal((3 * P, n))
    R = r_scale * np.diag(rng.uniform(0.5, 2.0, 3 * P))
    return rng, prior, H, R


def _conditional(state, at):
    """Mean and covariance of the rest of the state given the parameters = ``at``."""
    A, B, C = state.cov[:M, :M], state.cov[M:, :M], state.cov[M:, M:]
    G = B @ np.linalg.inv(A)
    return state.mean[M:] + G @ (at - state.mean[:M]), C - G @ B.T


@pytest.mark.parametrize("kappa", [1.0, 3.7])
def test_tempered_marginal_against_the_likelihood_written_out(kappa):
    """The parameters' posterior with p(y | parameters)^(1/kappa), p(y | p) = N(H mu + L (p - m), S_c) written out
    from the joint prior (L = H_p + H_x C_xp C_pp^-1, S_c = H_x C_x|p H_x' + R), against tempered_marginal of the
    plain update."""
    rng, prior, H, R = _problem(5)
    y = H @ prior.mean + 2.0 * rng.standard_normal(3 * P)
    C = prior.cov
    Cpp, Cxp, Cxx = C[:M, :M], C[M:, :M], C[M:, M:]
    gain = Cxp @ np.linalg.inv(Cpp)
    L = H[:, :M] + H[:, M:] @ gain
    S_c = H[:, M:] @ (Cxx - gain @ Cxp.T) @ H[:, M:].T + R
    precision = np.linalg.inv(Cpp) + L.T @ np.linalg.solve(S_c, L) / kappa
    cov = np.linalg.inv(precision)
    mean = prior.mean[:M] + cov @ L.T @ np.linalg.solve(S_c, y - H @ prior.mean) / kappa
    got_mean, got_cov = tempered_marginal(prior, update(prior, y, H, R).state, M, kappa)
    np.testing.assert_allclose(got_mean, mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(got_cov, cov, rtol=1e-9, atol=1e-14)
    # tempering removes less of the prior's variance than the plain update, never more than the prior has
    plain = update(prior, y, H, R).state.cov[:M, :M]
    assert np.all(np.linalg.eigvalsh(Cpp - got_cov) >= -1e-12)
    assert np.all(np.linalg.eigvalsh(got_cov - plain) >= -1e-12)


def test_adjusted_takes_the_tempered_marginal_and_keeps_the_plain_conditional():
    rng, prior, H, R = _problem(1)
    y = H @ prior.mean + rng.standard_normal(3 * P)
    plain = update(prior, y, H, R).state
    t_mean, t_cov = tempered_marginal(prior, plain, M, 4.0)
    joint = adjusted(plain, t_mean, t_cov, M)
    np.testing.assert_allclose(joint.mean[:M], t_mean, rtol=1e-12)
    np.testing.assert_allclose(joint.cov[:M, :M], t_cov, rtol=1e-12)
    for at in (plain.mean[:M], t_mean + 0.3):
        mean_a, cov_a = _conditional(joint, at)
        mean_b, cov_b = _conditional(plain, at)
        np.testing.assert_allclose(mean_a, mean_b, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(cov_a, cov_b, rtol=1e-9, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(joint.cov) > 0)
    # tempering by 1 is the plain update
    same = adjusted(plain, plain.mean[:M], plain.cov[:M, :M], M)
    np.testing.assert_allclose(same.mean, plain.mean, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(same.cov, plain.cov, rtol=1e-10, atol=1e-14)


def _draws(prior, H, R_true, R_filter, rng, n):
    """q / dof of the plain update (with R_filter) of n measurements drawn from the prior and R_true."""
    Lp, Lr = np.linalg.cholesky(prior.cov), np.linalg.cholesky(R_true)
    out = []
    for _ in range(n):
        z = prior.mean + Lp @ rng.standard_normal(prior.mean.size)
        y = H @ z + Lr @ rng.standard_normal(H.shape[0])
        q, dof = parameter_nis(prior, update(prior, y, H, R_filter).state, M)
        out.append((q, dof))
    return np.array(out)


def test_the_normalised_shift_is_chi_square_under_the_filters_model():
    rng, prior, H, R = _problem(2)
    qd = _draws(prior, H, R, R, rng, 4000)
    assert np.all(qd[:, 1] == M)
    q = qd[:, 0]
    assert abs(q.mean() - M) < 3 * np.sqrt(2 * M / q.size), q.mean()         # chi-square: mean M, variance 2M
    assert abs(q.var() - 2 * M) < 0.25 * 2 * M, q.var()


def test_correlated_errors_give_the_exact_expected_overdispersion():
    """Errors shared by the points in the pattern of a parameter change (what a model misfit that looks like a rate
    change does), taken by the filter as independent: the Monte Carlo mean of q equals its exact expectation
    tr(V^-1 K_p S_true K_p')."""
    rng, prior, H, R = _problem(3, r_scale=5.0)
    R_true = R + 3.0 * H[:, :M] @ H[:, :M].T
    S = H @ prior.cov @ H.T + R
    K = prior.cov @ H.T @ np.linalg.inv(S)
    V = (K @ S @ K.T)[:M, :M]
    S_true = H @ prior.cov @ H.T + R_true
    expected = np.trace(np.linalg.solve(V, K[:M] @ S_true @ K[:M].T))
    q = _draws(prior, H, R_true, R, rng, 4000)[:, 0]
    assert expected > 2 * M, expected                                        # the case is one of over-dispersion
    assert q.mean() == pytest.approx(expected, rel=0.06)


def test_the_sequential_estimate_is_silent_under_the_model_and_finds_an_overdispersion():
    rng, prior, H, R = _problem(4, r_scale=20.0)
    od = Overdispersion()
    for _ in range(1500):
        z = prior.mean + np.linalg.cholesky(prior.cov) @ rng.standard_normal(prior.mean.size)
        y = H @ z + np.sqrt(np.diag(R)) * rng.standard_normal(3 * P)
        od.observe(prior, update(prior, y, H, R).state, M)
        assert od.kappa == 1.0
    assert od.summary()["nis_per_dof"] == pytest.approx(1.0, abs=0.1)
    od4 = Overdispersion()
    kappas = []
    for _ in range(400):
        z = prior.mean + np.linalg.cholesky(prior.cov) @ rng.standard_normal(prior.mean.size)
        y = H @ z + 3.0 * np.sqrt(np.diag(R)) * rng.standard_normal(3 * P)     # errors 3x the filter's sigma
        od4.observe(prior, update(prior, y, H, R).state, M)
        kappas.append(od4.kappa)
    exact = od4.q_sum / od4.dof_sum
    assert kappas[-1] == exact > 2.0
    assert kappas.index(next(k for k in kappas if k > 1.0)) < 40              # found within tens of frames
    assert Overdispersion(fixed=2.5).kappa == 2.5
    with pytest.raises(ValueError, match=">= 1"):
        Overdispersion(fixed=0.5)
    assert 0 < ALPHA < 1e-3


def test_the_ge_is_unchanged_where_its_model_holds():
    """On data its model explains (the paper patch simulated), the default ('auto') never tempers: the GE's
    predictions and parameters equal the plain update's to the last bit; a fixed factor does change them."""
    from heartcv.tracker.joint import run_joint
    from heartcv.tracker.simulate import simulate, to_measurements
    from tests.tracker.test_unknown_input import _model

    m = _model(72.0)
    meas = to_measurements(simulate(m, 2.0, np.random.default_rng(3)))
    auto = run_joint(m, meas, "ge")
    plain = run_joint(m, meas, "ge", parameter_overdispersion=1.0)
    summary = auto.meta["parameter_overdispersion"]
    assert summary["mode"] == "estimated" and summary["frames_adjusted"] == 0 and summary["kappa_final"] == 1.0
    assert summary["dof"] > 0
    np.testing.assert_array_equal(auto.predictions, plain.predictions)
    np.testing.assert_array_equal(auto.phi_mean, plain.phi_mean)
    tempered = run_joint(m, meas, "ge", parameter_overdispersion=4.0)
    assert tempered.meta["parameter_overdispersion"]["frames_adjusted"] == meas.n_frames   # every frame updates
    assert np.all(tempered.phi_cov[-1].diagonal() > plain.phi_cov[-1].diagonal())
