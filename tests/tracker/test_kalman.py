"""Tests of tracker.kalman: spec §4 vector, the shared linear-Gaussian checker, NaN rows, NIS, validation."""

import math

import numpy as np
import pytest
from scipy import stats

from heartcv.tracker.kalman import GaussianState, UpdateResult, cholesky_psd, predict, symmetrise, update, update_blocks

from .lg_checker import batch_posterior, check_estimator, make_problem

# docs/spec/estimator.md §4 test vector
MU = np.array([4.0, 1.0, -0.188])
C = np.array([[0.25, 0.05, -0.02], [0.05, 0.10, 0.006], [-0.02, 0.006, 0.19]])
H = np.array([[0.0, 1.0, 0.0]])
MU_POST = np.array([4.0909090909, 1.1818181818, -0.1770909091])
C_POST = np.array([[0.2272727273, 0.0045454545, -0.0227272727],
                   [0.0045454545, 0.0090909091, 0.0005454545],
                   [-0.0227272727, 0.0005454545, 0.1896727273]])


def kalman_run(joseph=False, omit_Q=False, input_lag=1):
    def run(p):
        state = GaussianState(p.prior_mean, p.prior_cov)
        out = []
        for k in range(p.steps):
            if k > 0:
                Q = np.zeros_like(p.Q) if omit_Q else p.Q
                state = predict(state, p.A, Q, p.B @ p.u[k - input_lag])
            state = update(state, p.y[k], p.H, p.R, p.offset, joseph=joseph).state
            out.append((state.mean, state.cov))
        return out
    return run


@pytest.mark.parametrize("joseph", [False, True], ids=["standard", "joseph"])
def test_spec_vector(joseph):
    res = update(GaussianState(MU, C), [1.2], H, [[0.01]], joseph=joseph)
    np.testing.assert_allclose(res.state.mean, MU_POST, rtol=0, atol=1e-10)
    np.testing.assert_allclose(res.state.cov, C_POST, rtol=0, atol=1e-10)
    assert abs(res.nis - 0.3636363636) < 1e-10
    assert res.dof == 1 and res.used.tolist() == [True] and res.jitter_events == 0
    np.testing.assert_allclose(res.innovation, [0.2], atol=1e-15)
    np.testing.assert_allclose(res.innovation_cov, [[0.11]], atol=1e-15)


def test_standard_equals_joseph_on_spec_vector():
    std = update(GaussianState(MU, C), [1.2], H, [0.01])
    jos = update(GaussianState(MU, C), [1.2], H, [0.01], joseph=True)
    assert np.max(np.abs(std.state.cov - jos.state.cov)) <= 1e-15
    assert np.max(np.abs(std.state.mean - jos.state.mean)) <= 1e-15


def test_log_likelihood_matches_scipy():
    rng = np.random.default_rng(7)
    p = make_problem(rng, missing_fraction=0.0)
    res = update(GaussianState(p.prior_mean, p.prior_cov), p.y[0], p.H, p.R)
    ref = stats.multivariate_normal(p.H @ p.prior_mean, p.H @ p.prior_cov @ p.H.T + p.R).logpdf(p.y[0])
    assert abs(res.log_likelihood - ref) < 1e-12 * abs(ref)
    assert update(GaussianState(MU, C), [np.nan], H, [0.01]).log_likelihood == 0.0


def test_predict_matches_textbook():
    rng = np.random.default_rng(1)
    A, b = rng.standard_normal((3, 3)), rng.standard_normal(3)
    Q = np.diag([0.1, 0.2, 0.3])
    pred = predict(GaussianState(MU, C), A, Q, b)
    np.testing.assert_allclose(pred.mean, A @ MU + b, rtol=1e-15)
    np.testing.assert_allclose(pred.cov, A @ C @ A.T + Q, rtol=1e-14)
    assert np.array_equal(pred.cov, pred.cov.T)
    np.testing.assert_array_equal(predict(GaussianState(MU, C), A, Q).mean, A @ MU)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("joseph", [False, True], ids=["standard", "joseph"])
def test_lg_checker(seed, joseph):
    p = make_problem(np.random.default_rng(seed), with_offset=seed == 2)
    assert np.isnan(p.y).any() and np.isnan(p.y).all(axis=1).any()
    check_estimator(kalman_run(joseph=joseph), p)


@pytest.mark.parametrize("wrong", [dict(omit_Q=True), dict(input_lag=0)], ids=["Q-omitted", "u_k-not-u_k-1"])
def test_lg_checker_detects_wrong_filter(wrong):
    p = make_problem(np.random.default_rng(0))
    with pytest.raises(AssertionError):
        check_estimator(kalman_run(**wrong), p)


def test_batch_posterior_step0_is_single_update():
    p = make_problem(np.random.default_rng(3), missing_fraction=0.0)
    C0, m0 = p.prior_cov, p.prior_mean
    S = p.H @ C0 @ p.H.T + p.R
    K = np.linalg.solve(S, p.H @ C0).T
    mean, cov = batch_posterior(p, 0)
    np.testing.assert_allclose(mean, m0 + K @ (p.y[0] - p.H @ m0), rtol=1e-10)
    np.testing.assert_allclose(cov, C0 - K @ S @ K.T, rtol=1e-10, atol=1e-12)


def test_all_nan_leaves_state_unchanged():
    prior = GaussianState(MU, C)
    res = update(prior, [np.nan, np.nan], np.vstack([H, H]), [0.01, 0.02])
    assert res.state is prior
    assert math.isnan(res.nis) and res.dof == 0 and not res.used.any() and res.jitter_events == 0
    assert res.innovation.shape == (0,) and res.innovation_cov.shape == (0, 0)


@pytest.mark.parametrize("joseph", [False, True])
def test_nan_rows_equal_reduced_update(joseph):
    rng = np.random.default_rng(4)
    n, m = 5, 4
    G = rng.standard_normal((n, n))
    prior = GaussianState(rng.standard_normal(n), G @ G.T + np.eye(n))
    Hm, off = rng.standard_normal((m, n)), rng.standard_normal(m)
    F = rng.standard_normal((m, m))
    R = F @ F.T + 0.5 * np.eye(m)
    y = rng.standard_normal(m)
    y[[1, 3]] = np.nan
    keep = [0, 2]
    res = update(prior, y, Hm, R, off, joseph=joseph)
    red = update(prior, y[keep], Hm[keep], R[np.ix_(keep, keep)], off[keep], joseph=joseph)
    assert res.used.tolist() == [True, False, True, False] and res.dof == 2
    np.testing.assert_array_equal(res.state.mean, red.state.mean)
    np.testing.assert_array_equal(res.state.cov, red.state.cov)
    assert res.nis == red.nis
    # by hand: textbook gain K = C H^T S^-1 with a general solve
    Hr, Rr, mu, Cp = Hm[keep], R[np.ix_(keep, keep)], prior.mean, prior.cov
    S = Hr @ Cp @ Hr.T + Rr
    e = y[keep] - off[keep] - Hr @ mu
    K = np.linalg.solve(S, Hr @ Cp).T
    np.testing.assert_allclose(res.state.mean, mu + K @ e, rtol=1e-12)
    np.testing.assert_allclose(res.state.cov, Cp - K @ S @ K.T, rtol=1e-11, atol=1e-13)
    assert abs(res.nis - e @ np.linalg.solve(S, e)) < 1e-12 * res.nis


def test_diagonal_R_equals_full_R():
    rng = np.random.default_rng(5)
    Hm, y, r = rng.standard_normal((2, 3)), rng.standard_normal(2), np.array([0.3, 0.05])
    a = update(GaussianState(MU, C), y, Hm, r)
    b = update(GaussianState(MU, C), y, Hm, np.diag(r))
    np.testing.assert_array_equal(a.state.cov, b.state.cov)
    np.testing.assert_array_equal(a.state.mean, b.state.mean)


def _nis_run(R_filter_scale, seed=11, steps=2000):
    rng = np.random.default_rng(seed)
    p = make_problem(rng, n=4, m=3, steps=steps, missing_fraction=0.05)
    state = GaussianState(p.prior_mean, p.prior_cov)
    nis, dof = [], []
    for k in range(steps):
        if k > 0:
            state = predict(state, p.A, p.Q, p.B @ p.u[k - 1])
        res = update(state, p.y[k], p.H, R_filter_scale * p.R)
        state = res.state
        if res.dof:
            nis.append(res.nis)
            dof.append(res.dof)
    total = int(np.sum(dof))
    # sum of NIS over steps ~ chi2(total dof) (innovations are white); per-dof mean NIS band at 99 %
    lo, hi = stats.chi2.ppf([0.005, 0.995], total) / total
    return np.sum(nis) / total, lo, hi


def test_nis_consistency_monte_carlo():
    mean_nis, lo, hi = _nis_run(1.0)
    assert lo <= mean_nis <= hi, (mean_nis, lo, hi)


def test_nis_detects_misspecified_R():
    mean_nis, lo, hi = _nis_run(0.5)
    assert mean_nis > hi


def test_states_are_immutable_values():
    mean, cov = MU.copy(), C.copy()
    s = GaussianState(mean, cov)
    mean[0] = 99.0
    assert s.mean[0] == 4.0 and s.mean.dtype == np.float64
    with pytest.raises(ValueError):
        s.cov[0, 0] = 1.0
    with pytest.raises(AttributeError):
        s.mean = MU
    res = update(s, [1.2], H, [0.01])
    assert isinstance(res, UpdateResult) and not res.innovation.flags.writeable and not res.state.cov.flags.writeable


@pytest.mark.parametrize("mean, cov, match", [
    (np.zeros((3, 1)), np.eye(3), r"mean: expected shape \(n,\)"),
    (np.zeros(3), np.eye(2), r"cov: expected shape \(3, 3\)"),
    ([1.0, np.nan, 0.0], np.eye(3), "non-finite"),
    (np.zeros(3), np.diag([1.0, np.inf, 1.0]), "non-finite"),
    (np.zeros(3), np.array([[1.0, 0.1, 0], [0.2, 1.0, 0], [0, 0, 1.0]]), "not symmetric"),
    (np.zeros(0), np.zeros((0, 0)), "n >= 1"),
])
def test_gaussian_state_rejects(mean, cov, match):
    with pytest.raises(ValueError, match=match):
        GaussianState(mean, cov)


def test_symmetry_tolerance_is_relative():
    cov = 1e6 * C
    cov[0, 1] += 1e-5                # 1e-5 / 2.5e5 = 4e-11 relative
    GaussianState(MU, cov)


@pytest.mark.parametrize("kwargs, match", [
    (dict(A=np.eye(2)), r"A: expected shape \(3, 3\)"),
    (dict(Q=np.eye(4)), r"Q: expected shape \(3, 3\)"),
    (dict(b=np.zeros(2)), r"b: expected shape \(3,\)"),
    (dict(Q=np.triu(np.ones((3, 3)))), "not symmetric"),
    (dict(A=np.full((3, 3), np.nan)), "non-finite"),
])
def test_predict_rejects(kwargs, match):
    args = dict(A=np.eye(3), Q=np.eye(3), b=None) | kwargs
    with pytest.raises(ValueError, match=match):
        predict(GaussianState(MU, C), **args)


@pytest.mark.parametrize("kwargs, match", [
    (dict(y=[[1.2]]), r"y: expected shape \(m,\)"),
    (dict(H=np.ones((1, 2))), r"H: expected shape \(1, 3\)"),
    (dict(H=np.ones((2, 3))), r"H: expected shape \(1, 3\)"),
    (dict(R=np.eye(2)), r"R: expected shape \(1, 1\) or \(1,\)"),
    (dict(R=[-0.1]), "variances >= 0"),
    (dict(offset=[0.0, 1.0]), r"offset: expected shape \(1,\)"),
    (dict(y=[np.inf]), "non-finite"),
    (dict(H=[[0.0, np.nan, 0.0]]), "non-finite"),
])
def test_update_rejects(kwargs, match):
    args = dict(y=[1.2], H=H, R=[0.01]) | kwargs
    with pytest.raises(ValueError, match=match):
        update(GaussianState(MU, C), **args)


def test_wrong_state_type():
    with pytest.raises(TypeError):
        predict((MU, C), np.eye(3), np.eye(3))
    with pytest.raises(TypeError):
        update((MU, C), [1.0], H, [0.01])


def test_symmetrise_exact():
    rng = np.random.default_rng(6)
    M = rng.standard_normal((7, 7))
    S = symmetrise(M)
    assert np.array_equal(S, S.T)
    np.testing.assert_allclose(S, (M + M.T) / 2)
    with pytest.raises(ValueError, match=r"\(n, n\)"):
        symmetrise(np.ones((2, 3)))


def test_cholesky_psd_singular_needs_jitter():
    v = np.array([1.0, 2.0, -1.0])
    for M in (np.ones((3, 3)), np.outer(v, v), np.zeros((2, 2))):
        L, events = cholesky_psd(M)
        assert events > 0
        assert np.allclose(L @ L.T, M, atol=1e-9 * max(1.0, np.trace(M)))
        assert np.array_equal(L, np.tril(L))


def test_cholesky_psd_pd_needs_no_jitter():
    L, events = cholesky_psd(C)
    assert events == 0
    np.testing.assert_allclose(L @ L.T, C, rtol=1e-15, atol=1e-16)


def test_cholesky_psd_rejects_indefinite():
    with pytest.raises(np.linalg.LinAlgError, match="not positive semi-definite"):
        cholesky_psd(np.diag([1.0, -1.0]))
    with pytest.raises(ValueError, match=r"\(n, n\)"):
        cholesky_psd(np.ones(3))


def test_perfect_measurement_counts_posterior_jitter():
    # R = 0 on a measured coordinate makes C+ singular: the PD check adds jitter and counts it
    res = update(GaussianState(MU, C), [1.2], H, [0.0])
    assert res.jitter_events > 0
    np.linalg.cholesky(res.state.cov)
    assert abs(res.state.mean[1] - 1.2) < 1e-12


def _block_problem(rng, n, p, singular=False):
    A = rng.standard_normal((n, n))
    C = A @ A.T / n + 1e-3 * np.eye(n)
    if singular:                                   # a state the prediction knows exactly (zero variance)
        C[0, :] = C[:, 0] = 0.0
    B = rng.standard_normal((p, 3, 3))
    blocks = B @ np.swapaxes(B, 1, 2) + 0.1 * np.eye(3)
    R = np.zeros((3 * p, 3 * p))
    for i in range(p):
        R[3 * i:3 * i + 3, 3 * i:3 * i + 3] = blocks[i]
    return (GaussianState(rng.standard_normal(n), C), rng.standard_normal(3 * p), rng.standard_normal((3 * p, n)),
            blocks, R, rng.standard_normal(3 * p))


@pytest.mark.parametrize("n, p, singular", [(6, 1, False), (5, 40, False), (30, 4, False), (12, 30, True)])
def test_block_update_equals_the_dense_update(n, p, singular):
    """The low-rank (Woodbury) update with a block-diagonal R is the Cholesky-form update with the same R written
    out: mean, covariance, innovation, NIS and log-likelihood to 1e-9 relative, with more rows than states or
    fewer, and with a singular predicted covariance (whose zero-variance state keeps its mean exactly)."""
    state, y, H, blocks, R, off = _block_problem(np.random.default_rng(n * 100 + p), n, p, singular)
    a = update(state, y, H, R, off)
    b = update_blocks(state, y, H, blocks, off)
    scale = np.abs(a.state.cov).max()
    np.testing.assert_allclose(b.state.mean, a.state.mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(b.state.cov, a.state.cov, rtol=0, atol=1e-10 * scale)
    np.testing.assert_array_equal(b.innovation, a.innovation)
    assert b.nis == pytest.approx(a.nis, rel=1e-9) and b.dof == a.dof == 3 * p
    assert b.log_likelihood == pytest.approx(a.log_likelihood, rel=1e-9)
    assert b.innovation_cov is None and b.innovation_chol is None
    if singular:
        assert b.state.mean[0] == state.mean[0] and abs(b.state.cov[0, 0]) <= 1e-12 * scale   # (the PD check's jitter)


def test_block_innovation_solves_and_inverts_like_the_explicit_inverse():
    """``BlockInnovation.solve`` and ``inverse_blocks`` against numpy's inverse of S = H C H^T + R formed in full;
    ``log_det`` against slogdet."""
    state, y, H, blocks, R, off = _block_problem(np.random.default_rng(8), 7, 9)
    res = update_blocks(state, y, H, blocks, off)
    S = H @ state.cov @ H.T + R
    S_inv = np.linalg.inv(S)
    np.testing.assert_allclose(res.innovation_factor.solve(res.innovation), S_inv @ res.innovation, rtol=1e-9)
    inv_blocks = res.innovation_factor.inverse_blocks()
    for i in range(9):
        np.testing.assert_allclose(inv_blocks[i], S_inv[3 * i:3 * i + 3, 3 * i:3 * i + 3], rtol=1e-9, atol=1e-12)
    assert res.innovation_factor.log_det == pytest.approx(np.linalg.slogdet(S)[1], rel=1e-12)


def test_block_update_refuses_a_block_that_is_not_positive_definite():
    """A singular block of R raises LinAlgError (the dense update, which needs only S positive definite, is the
    fallback the filter takes); wrong shapes and non-finite entries raise ValueError."""
    state, y, H, blocks, R, off = _block_problem(np.random.default_rng(9), 4, 3)
    bad = blocks.copy()
    bad[1] = 0.0
    with pytest.raises(np.linalg.LinAlgError):
        update_blocks(state, y, H, bad, off)
    with pytest.raises(ValueError, match="R_blocks"):
        update_blocks(state, y, H, blocks[:, :2], off)
    with pytest.raises(ValueError, match="y"):
        update_blocks(state, np.where(np.arange(9) == 2, np.nan, y), H, blocks, off)
