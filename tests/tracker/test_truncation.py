"""Tests of tracker.truncation against docs/spec/estimator.md §3 (items 5-7 of §8): 1-D moments table, rank-1 update,
truncate-then-lift identity, lift vector, uncorrelated/2-D/3-D examples, low mass, validation."""

import dataclasses
import logging
import math

import numpy as np
import pytest
from scipy import stats
from scipy.integrate import quad

from heartcv.tracker.truncation import TruncationResult, truncate_box, truncate_linear, truncnorm_moments

INF = np.inf

# spec §3.1 reference table: (alpha, beta), mean_std, var_std
TABLE = [
    ((0.0, INF), 0.797884560803, 0.363380227632),
    ((-1.0, 1.0), 0.0, 0.291125094773),
    ((1.0, INF), 1.525135276161, 0.199097665570),
    ((-INF, -1.0), -1.525135276161, 0.199097665570),
    ((2.0, 3.0), 2.315821326744, 0.061520779574),
    ((-0.5, 2.0), 0.445743778273, 0.376593836137),
    ((10.0, INF), 10.098093233963, 0.009445377825656),
    ((10.0, 10.5), 10.095268735313, 0.008042644536668),
    ((30.0, 31.0), 30.033259667434, 0.001103771511835),
    ((38.0, 40.0), 38.026279466576, 0.000689659753466),
]


def random_spd(rng, n, jitter=0.5):
    A = rng.standard_normal((n, n))
    return A @ A.T + jitter * np.eye(n)


def is_pd(C):
    try:
        np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        return False
    return True


# ---------------------------------------------------------------------------------------------------------------------
# §3.1 one-dimensional moments

@pytest.mark.parametrize("bounds, mean, var", TABLE, ids=[f"[{a:g},{b:g}]" for (a, b), _, _ in TABLE])
def test_reference_table(bounds, mean, var):
    m, v = truncnorm_moments(*bounds)
    far_tail = max(abs(x) for x in bounds if np.isfinite(x)) >= 8
    if far_tail:
        assert abs(float(m) - mean) <= 1e-8 * abs(mean)
        assert abs(float(v) - var) <= 1e-8 * var
    else:
        assert abs(float(m) - mean) <= 1e-12
        assert abs(float(v) - var) <= 1e-12


def test_closed_form_first_row():
    m, v = truncnorm_moments(0.0, INF)
    assert float(m) == pytest.approx(math.sqrt(2 / math.pi), abs=1e-15)
    assert float(v) == pytest.approx(1 - 2 / math.pi, abs=1e-15)


def test_reflection_symmetry():
    rng = np.random.default_rng(1)
    a = rng.uniform(-40, 40, 200)
    b = a + rng.exponential(2.0, 200)
    b[::7] = INF
    m, v = truncnorm_moments(a, b)
    m_ref, v_ref = truncnorm_moments(-b, -a)
    np.testing.assert_array_equal(m, -m_ref)
    np.testing.assert_array_equal(v, v_ref)


@pytest.mark.parametrize("bounds", [(0.0, INF), (-1.0, 1.0), (1.0, INF), (2.0, 3.0), (-0.5, 2.0), (-3.0, 0.25)])
def test_against_scipy_truncnorm(bounds):
    m_ref, v_ref = stats.truncnorm.stats(*bounds, moments="mv")
    m, v = truncnorm_moments(*bounds)
    assert float(m) == pytest.approx(float(m_ref), abs=1e-13)
    assert float(v) == pytest.approx(float(v_ref), rel=1e-12)


def _quadrature_moments(al, be):
    """Independent oracle: adaptive quadrature of exp(-s t - t^2/2) in t = x - s, central moments in two passes."""
    if al + be < 0:
        m, v = _quadrature_moments(-be, -al)
        return -m, v
    s = al if al > 0 else 0.0
    lo_t = max(al - s, -40.0)
    hi_t = min(be - s, 60.0 / max(s, 1.0))
    f = lambda t: math.exp(-s * t - 0.5 * t * t)                                       # noqa: E731
    kw = dict(epsabs=0.0, epsrel=1e-13, limit=200)
    z = quad(f, lo_t, hi_t, **kw)[0]
    m = quad(lambda t: t * f(t), lo_t, hi_t, **kw)[0] / z
    v = quad(lambda t: (t - m) ** 2 * f(t), lo_t, hi_t, **kw)[0] / z
    return s + m, v


@pytest.mark.parametrize("al", [-2.0, 0.0, 0.4, 2.5, 3.5, 7.0, 60.0, 1e3, 1e4, 1e5])
def test_against_quadrature_all_regimes(al):
    """Every path (short interval, erfcx/continued-fraction tail, straddling) against quadrature, widths 1e-7..inf."""
    for width in [1e-7, 1e-5, 1e-3, 0.05, 0.7, 3.0, INF]:
        be = al + width
        m, v = (float(x) for x in truncnorm_moments(al, be))
        m_ref, v_ref = _quadrature_moments(al, be)
        assert abs(m - m_ref) <= 1e-10 * math.sqrt(v_ref) + 4e-16 * abs(m_ref), (al, width)
        assert abs(v - v_ref) <= 1e-10 * v_ref, (al, width)


def test_uniform_limit_for_short_intervals():
    for a in [-3.0, 0.5, 12.0]:
        w = 5e-7
        m, v = truncnorm_moments(a, a + w)
        assert float(m) == pytest.approx(a + w / 2, abs=1e-12)
        assert float(v) == pytest.approx(w * w / 12, rel=1e-6)
    m, v = truncnorm_moments(2.0, 2.0)
    assert float(m) == 2.0 and float(v) == 0.0


def test_asymptotic_far_tail():
    for al in [1e4, 1e5, 1e7]:
        m, v = truncnorm_moments(al, INF)
        assert float(v) == pytest.approx(1 / al**2, rel=7 / al**2)       # 1/al^2 - 6/al^4 + ...
        assert float(m) == pytest.approx(al + 1 / al, rel=1e-15)
    m, v = truncnorm_moments(1e300, INF)
    assert np.isfinite(m) and float(v) == 0.0


def test_vectorised_shapes_and_range():
    a = np.array([[-INF], [-1.0], [0.3], [25.0]])
    b = np.array([0.0, 1.0, 2.0, INF])
    b = np.maximum(b, a + 0.1)                               # (4, 4), alpha < beta
    m, v = truncnorm_moments(a, b)
    assert m.shape == v.shape == (4, 4)
    assert np.all((m >= a) & (m <= b)) and np.all((v >= 0) & (v <= 1))
    m0, v0 = truncnorm_moments(-INF, INF)
    assert m0.shape == () and float(m0) == 0.0 and float(v0) == 1.0


@pytest.mark.parametrize("a, b", [(1.0, 0.0), (np.nan, 1.0), (0.0, np.nan), (INF, INF), (-INF, -INF)])
def test_truncnorm_invalid(a, b):
    with pytest.raises(ValueError):
        truncnorm_moments(a, b)


# ---------------------------------------------------------------------------------------------------------------------
# §3.2 one linear constraint

def test_truncate_linear_exact_structure():
    """The constrained direction gets the 1-D truncated moments; directions decorrelated from it are untouched."""
    rng = np.random.default_rng(2)
    C = random_spd(rng, 4)
    mu = rng.standard_normal(4)
    phi = rng.standard_normal(4)
    sig = math.sqrt(phi @ C @ phi)
    a, b = phi @ mu - 0.3 * sig, phi @ mu + 1.1 * sig
    mu_p, C_p, info = truncate_linear(mu, C, phi, a, b)
    m, v = truncnorm_moments(-0.3, 1.1)
    assert info["alpha"] == pytest.approx(-0.3, abs=1e-14) and info["beta"] == pytest.approx(1.1, abs=1e-14)
    assert info["prob"] == pytest.approx(stats.norm.cdf(1.1) - stats.norm.cdf(-0.3), rel=1e-13)
    assert phi @ mu_p == pytest.approx(phi @ mu + sig * float(m), abs=1e-13)
    assert phi @ C_p @ phi == pytest.approx(sig**2 * float(v), rel=1e-12)
    W = np.linalg.svd((C @ phi)[None, :])[2][1:]              # rows w with w^T C phi = 0: independent of phi^T z
    np.testing.assert_allclose(W @ mu_p, W @ mu, atol=1e-13)
    np.testing.assert_allclose(W @ C_p @ W.T, W @ C @ W.T, atol=1e-13)
    np.testing.assert_allclose(W @ C_p @ phi, 0.0, atol=1e-13)
    np.testing.assert_array_equal(C_p, C_p.T)


def test_truncate_linear_tail_probability_is_finite_and_positive():
    mu_p, C_p, info = truncate_linear([0.0, 0.0], [[1.0, 0.5], [0.5, 2.0]], [1.0, 1.0], 100.0, 101.0)
    assert info["prob"] == 0.0 and np.isfinite(info["log_prob"]) and info["log_prob"] < -1000
    sig = math.sqrt(4.0)
    assert 100.0 <= mu_p.sum() <= 101.0 and np.all(np.isfinite(C_p))
    assert info["alpha"] == pytest.approx(100.0 / sig)


@pytest.mark.parametrize("args", [
    ([0.0, 0.0], np.eye(2), [1.0, 0.0], 1.0, 1.0),          # a == b
    ([0.0, 0.0], np.eye(2), [1.0, 0.0], 2.0, 1.0),          # a > b
    ([0.0, 0.0], np.eye(2), [0.0, 0.0], 0.0, 1.0),          # phi^T C phi = 0
    ([0.0, 0.0], np.eye(2), [1.0, 0.0, 0.0], 0.0, 1.0),     # phi shape
    ([0.0, np.nan], np.eye(2), [1.0, 0.0], 0.0, 1.0),       # non-finite mean
    ([0.0, 0.0], np.eye(3), [1.0, 0.0], 0.0, 1.0),          # cov shape
])
def test_truncate_linear_invalid(args):
    with pytest.raises(ValueError):
        truncate_linear(*args)


# ---------------------------------------------------------------------------------------------------------------------
# §3.3 truncate the parameter block, then lift

@pytest.mark.parametrize("order", [None, [1, 0]])
def test_block_then_lift_equals_joint_sequential(order):
    rng = np.random.default_rng(7)
    n_param, n = 2, 6
    C = random_spd(rng, n)
    mu = rng.standard_normal(n)
    sd = np.sqrt(np.diag(C))
    lower = np.array([mu[0] - 0.2 * sd[0], -INF])
    upper = np.array([mu[0] + 0.9 * sd[0], mu[1] - 0.4 * sd[1]])
    res = truncate_box(mu, C, lower, upper, n_param, order=order)
    mu_ref, C_ref, log_p = mu, C, 0.0
    for j in (order or range(n_param)):
        e = np.zeros(n)
        e[j] = 1.0
        mu_ref, C_ref, info = truncate_linear(mu_ref, C_ref, e, lower[j], upper[j])
        log_p += info["log_prob"]
    assert res.events == 2 and res.low_mass == 0 and res.method == "sequential"
    np.testing.assert_allclose(res.mean, mu_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.cov, C_ref, rtol=0, atol=1e-12)
    assert res.log_prob == pytest.approx(log_p, abs=1e-12)
    np.testing.assert_array_equal(res.cov, res.cov.T)


def test_lift_vector():
    mu = [0.2, 1.0, -1.0]
    C = [[1.34, 0.62, 0.30], [0.62, 1.16, 0.40], [0.30, 0.40, 1.00]]
    res = truncate_box(mu, C, [0.0], [1.0], 1)
    np.testing.assert_allclose(res.mean, [0.4818176998, 1.1303932641, -0.9369064851], rtol=0, atol=1e-10)
    C_plus = np.array([[0.0810849621, 0.0375169228, 0.0181533497],
                       [0.0375169228, 0.8904929046, 0.2695933409],
                       [0.0181533497, 0.2695933409, 0.9369000037]])
    np.testing.assert_allclose(res.cov, C_plus, rtol=0, atol=1e-10)
    assert res.events == 1
    assert math.exp(res.log_prob) == pytest.approx(stats.norm.cdf(0.8 / math.sqrt(1.34))
                                                   - stats.norm.cdf(-0.2 / math.sqrt(1.34)), rel=1e-13)


def test_lift_vector_monte_carlo():
    """Seeded Monte Carlo of the lift vector; tolerances are 5 standard errors of the accepted sample."""
    mu = np.array([0.2, 1.0, -1.0])
    C = np.array([[1.34, 0.62, 0.30], [0.62, 1.16, 0.40], [0.30, 0.40, 1.00]])
    res = truncate_box(mu, C, [0.0], [1.0], 1)
    z = np.random.default_rng(11).multivariate_normal(mu, C, size=1_000_000)
    z = z[(z[:, 0] >= 0.0) & (z[:, 0] <= 1.0)]
    N = z.shape[0]
    sd = np.sqrt(np.diag(res.cov))
    assert np.all(np.abs(z.mean(axis=0) - res.mean) <= 5 * sd / math.sqrt(N))
    # var of a sample covariance entry: C_ii C_jj + C_ij^2 (Gaussian bound; the truncated block is lighter-tailed)
    se_cov = np.sqrt((np.outer(sd**2, sd**2) + res.cov**2) / N)
    assert np.all(np.abs(np.cov(z.T) - res.cov) <= 5 * se_cov)


def test_inactive_box_returns_input_unchanged():
    rng = np.random.default_rng(3)
    C = random_spd(rng, 5)
    mu = rng.standard_normal(5)
    sd = np.sqrt(np.diag(C))[:3]
    lower, upper = mu[:3] - 9 * sd, mu[:3] + 9 * sd
    lower[1] = -INF
    for method in ("sequential", "tallis"):
        res = truncate_box(mu, C, lower, upper, 3, method=method)
        assert res.events == 0 and res.low_mass == 0 and res.log_prob == 0.0
        np.testing.assert_array_equal(res.mean, mu)
        np.testing.assert_array_equal(res.cov, C)


def test_posterior_covariance_symmetric_and_pd():
    rng = np.random.default_rng(4)
    for _ in range(20):
        n_param, n = int(rng.integers(1, 6)), 9
        C = random_spd(rng, n, jitter=1e-2)
        mu = rng.standard_normal(n)
        sd = np.sqrt(np.diag(C))[:n_param]
        lower = mu[:n_param] + rng.uniform(-2, 0.5, n_param) * sd
        upper = lower + rng.uniform(0.05, 3, n_param) * sd
        upper[rng.random(n_param) < 0.3] = INF
        res = truncate_box(mu, C, lower, upper, n_param, order=rng.permutation(n_param))
        np.testing.assert_array_equal(res.cov, res.cov.T)
        assert is_pd(res.cov)
        assert np.all(res.mean[:n_param] >= lower) and np.all(res.mean[:n_param] <= upper)


def test_low_mass_box_far_in_the_tail(caplog):
    mu = np.array([0.0, 0.0, 1.0])
    C = np.array([[1.0, 0.3, 0.2], [0.3, 2.0, 0.1], [0.2, 0.1, 1.5]])
    with caplog.at_level(logging.WARNING, logger="heartcv.tracker.truncation"):
        res = truncate_box(mu, C, [40.0, -INF], [41.0, INF], 2)
    assert res.low_mass == 1 and res.events == 1
    assert "box mass" in caplog.text
    assert np.all(np.isfinite(res.mean)) and np.all(np.isfinite(res.cov)) and np.isfinite(res.log_prob)
    assert 40.0 <= res.mean[0] <= 40.0 + 2.0 / 40.0                   # within ~2/al of the lower bound
    assert res.log_prob == pytest.approx(stats.norm.logsf(40.0), rel=1e-10)
    assert 0.0 < res.cov[0, 0] < 1.0 / 40.0**2
    np.testing.assert_array_equal(res.cov, res.cov.T)
    assert is_pd(res.cov)


# ---------------------------------------------------------------------------------------------------------------------
# §3.4 several constraints: sequential vs exact

@pytest.mark.parametrize("method", ["sequential", "tallis"])
@pytest.mark.parametrize("order", [[0, 1], [1, 0]])
def test_uncorrelated_case_exact_both_ways(method, order):
    res = truncate_box([0.3, -1.0], np.diag([1.0, 4.0]), [0.0, -2.0], [1.0, 0.0], 2, method=method, order=order)
    np.testing.assert_allclose(res.mean, [0.4838922521, -1.0], rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.diag(res.cov), [0.0804379999, 0.3223566184], rtol=0, atol=1e-10)
    assert abs(res.cov[0, 1]) <= 1e-12 and res.events == 2 and res.method == method


def test_uncorrelated_case_tallis_equals_sequential():
    args = ([0.3, -1.0], np.diag([1.0, 4.0]), [0.0, -2.0], [1.0, 0.0], 2)
    seq, exact = truncate_box(*args), truncate_box(*args, method="tallis")
    np.testing.assert_allclose(exact.mean, seq.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(exact.cov, seq.cov, rtol=0, atol=1e-10)
    assert exact.log_prob == pytest.approx(seq.log_prob, abs=1e-9)


CORR_2D = dict(mean=[0.0, 0.0], cov=[[1.0, 0.8], [0.8, 1.0]], lower=[0.0, 0.0], upper=[INF, INF], n_param=2)


def _summary(res):
    return [*res.mean, res.cov[0, 0], res.cov[1, 1], res.cov[0, 1]]


def test_correlated_2d_exact_via_tallis():
    res = truncate_box(**CORR_2D, method="tallis")
    expected = [0.9030755706, 0.9030755706, 0.3766011952, 0.3766011952, 0.2246378655]
    np.testing.assert_allclose(_summary(res), expected, rtol=0, atol=1e-9)
    assert math.exp(res.log_prob) == pytest.approx(0.25 + math.asin(0.8) / (2 * math.pi), abs=1e-10)
    assert res.method == "tallis" and res.low_mass == 0


@pytest.mark.parametrize("order, expected", [
    ([0, 1], [0.9320059311, 0.9116969317, 0.3033921464, 0.3433151752, 0.1684261403]),
    ([1, 0], [0.9116969317, 0.9320059311, 0.3433151752, 0.3033921464, 0.1684261403]),
], ids=["x1-then-x2", "x2-then-x1"])
def test_correlated_2d_sequential(order, expected):
    res = truncate_box(**CORR_2D, order=order)
    np.testing.assert_allclose(_summary(res), expected, rtol=0, atol=1e-9)


def test_tallis_with_one_binding_constraint_equals_rank1():
    """One finite bound: the single rank-1 update is exact, so both methods agree (and the lift is shared)."""
    rng = np.random.default_rng(8)
    C = random_spd(rng, 5)
    mu = rng.standard_normal(5)
    lower, upper = np.array([-INF, mu[1] + 0.2]), np.array([INF, INF])
    seq, exact = truncate_box(mu, C, lower, upper, 2), truncate_box(mu, C, lower, upper, 2, method="tallis")
    assert exact.method == "tallis" and exact.events == 1
    np.testing.assert_allclose(exact.mean, seq.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(exact.cov, seq.cov, rtol=0, atol=1e-10)


def test_order_dependence_3d_example():
    A = np.random.default_rng(5).standard_normal((3, 3))
    S = A @ A.T + 0.5 * np.eye(3)
    mu = [0.2, -0.1, 0.4]
    lower, upper = [0.0, -1.0, -INF], [1.5, INF, 0.8]
    exact = truncate_box(mu, S, lower, upper, 3, method="tallis")
    np.testing.assert_allclose(exact.mean, [0.62567, 0.07121, -0.26715], rtol=0, atol=5e-5)
    assert exact.events == 3
    np.testing.assert_array_equal(exact.cov, exact.cov.T)
    assert is_pd(exact.cov)
    forward = truncate_box(mu, S, lower, upper, 3, order=[0, 1, 2])
    backward = truncate_box(mu, S, lower, upper, 3, order=[2, 1, 0])
    np.testing.assert_allclose(forward.mean, [0.62663, 0.07238, -0.26680], rtol=0, atol=5e-5)
    np.testing.assert_allclose(backward.mean, [0.62346, 0.08670, -0.30346], rtol=0, atol=5e-5)
    # default order is 0..n_param-1
    np.testing.assert_array_equal(truncate_box(mu, S, lower, upper, 3).mean, forward.mean)


def test_tallis_lifts_the_kinematic_block():
    """Tallis on a 2+2 joint: the x^l part follows the prior regression of the exact x^n moments."""
    rng = np.random.default_rng(9)
    C = random_spd(rng, 4)
    mu = rng.standard_normal(4)
    sd = np.sqrt(np.diag(C))
    lower, upper = mu[:2] - 0.1 * sd[:2], mu[:2] + 1.0 * sd[:2]
    res = truncate_box(mu, C, lower, upper, 2, method="tallis")
    block = truncate_box(mu[:2], C[:2, :2], lower, upper, 2, method="tallis")
    np.testing.assert_allclose(res.mean[:2], block.mean, rtol=0, atol=1e-14)
    K = np.linalg.solve(C[:2, :2], C[:2, 2:]).T
    np.testing.assert_allclose(res.mean[2:], mu[2:] + K @ (block.mean - mu[:2]), rtol=0, atol=1e-12)
    C_cond = C[2:, 2:] - K @ C[:2, 2:]
    np.testing.assert_allclose(res.cov[2:, 2:], C_cond + K @ block.cov @ K.T, rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.cov[2:, :2], K @ block.cov, rtol=0, atol=1e-12)


def test_tallis_falls_back_to_sequential_at_tiny_mass(caplog):
    args = ([0.0, 0.0], [[1.0, 0.5], [0.5, 1.0]], [30.0, 30.0], [31.0, 31.0], 2)
    with caplog.at_level(logging.WARNING, logger="heartcv.tracker.truncation"):
        res = truncate_box(*args, method="tallis")
    assert res.method == "sequential" and res.low_mass > 0 and "Tallis" in caplog.text
    seq = truncate_box(*args)
    np.testing.assert_array_equal(res.mean, seq.mean)
    assert np.all(np.isfinite(res.cov)) and is_pd(res.cov)


# ---------------------------------------------------------------------------------------------------------------------
# Validation

GOOD = dict(mean=[0.0, 0.0, 0.0], cov=np.eye(3), lower=[0.0, -1.0], upper=[1.0, INF], n_param=2)


@pytest.mark.parametrize("change", [
    dict(mean=[0.0, 0.0]),
    dict(mean=[0.0, INF, 0.0]),
    dict(cov=np.eye(2)),
    dict(cov=np.array([[1.0, np.nan, 0], [np.nan, 1, 0], [0, 0, 1]])),
    dict(cov=np.array([[1.0, 0.5, 0], [0.0, 1, 0], [0, 0, 1]])),           # asymmetric
    dict(cov=np.array([[1.0, 1.0, 0], [1.0, 1.0, 0], [0, 0, 1]])),         # C_nn singular
    dict(cov=np.diag([1.0, -1.0, 1.0])),                                   # C_nn indefinite
    dict(lower=[0.0]),
    dict(lower=[0.0, np.nan]),
    dict(lower=[1.0, -1.0]),                                               # lower == upper
    dict(lower=[2.0, -1.0]),                                               # lower > upper
    dict(upper=[1.0, -INF], lower=[0.0, -INF]),
    dict(n_param=0),
    dict(n_param=4),
    dict(n_param=2.0),
    dict(n_param=True),
    dict(method="exact"),
    dict(order=[0, 0]),
    dict(order=[0, 1, 2]),
    dict(order=[1]),
], ids=lambda d: ",".join(d))
def test_truncate_box_invalid(change):
    kwargs = {**GOOD, **change}
    method, order = kwargs.pop("method", "sequential"), kwargs.pop("order", None)
    with pytest.raises(ValueError):
        truncate_box(**kwargs, method=method, order=order)


def test_result_is_frozen_and_checks_shapes():
    res = truncate_box(**GOOD)
    assert isinstance(res, TruncationResult) and res.events == 2
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.events = 0
    with pytest.raises(ValueError):
        TruncationResult(np.zeros(3), np.eye(2), 0, 0, 0.0)


def test_scalar_fast_path_equals_the_array_path():
    """One pair of floats straddling 0 takes a math-module path (the GE's common case); it equals the vectorised
    formulas to rounding over a grid of bounds, reflected or not, with infinite ends."""
    from heartcv.tracker.truncation import _truncnorm_stats

    grid = [-np.inf, -40.0, -8.3, -3.0, -1.2, -0.4, 0.0, 0.3, 1.1, 2.5, 7.0, 50.0, np.inf]
    for a in grid:
        for b in grid:
            if not a < b or a > 0 or b < 0:
                continue
            fast = np.array(_truncnorm_stats(float(a), float(b)), float)
            slow = np.array([x[0] for x in _truncnorm_stats(np.array([a]), np.array([b]))], float)
            np.testing.assert_allclose(fast, slow, rtol=1e-13, atol=1e-15, err_msg=f"{a}, {b}")
