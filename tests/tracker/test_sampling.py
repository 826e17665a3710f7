"""Tests of tracker.sampling: docs/spec/estimator.md §1 tables, exact moments of A/B (§1.5, §8 items 1-2), variant U,
clipping (§1.4) and validation."""

import dataclasses
import itertools

import numpy as np
import pytest
from scipy import integrate, stats

from heartcv.tracker.sampling import SampleSet, cross_moment, cvm_nodes, cvm_variance, moments, sample

SQRTS = ("correlation", "eigen", "cholesky")

# spec §1.1 table: D -> (u_k >= 0, s_D^2, s_D, E[u^4], u_k/s_D, E[(u/s_D)^4])
TABLE_1_1 = {
    3: ([0, 0.967422], 0.623936, 0.789896, 0.583945, [0, 1.224745], 1.5000),
    5: ([0, 0.524401, 1.281552], 0.766948, 0.875756, 1.109207, [0, 0.598798, 1.463366], 1.8857),
    7: ([0, 0.366106, 0.791639, 1.465234], 0.830753, 0.911457, 1.434266,
        [0, 0.401672, 0.868542, 1.607574], 2.0782),
    9: ([0, 0.282216, 0.589456, 0.967422, 1.593219], 0.866968, 0.931111, 1.654709,
        [0, 0.303096, 0.633067, 1.038997, 1.711094], 2.2015),
}

# spec §1.3 node-spread table for M = 5: D -> (L, c_A, outer A, E[t^4] A, c_B, outer B, E[t^4] B, outer U)
TABLE_1_3 = {
    3: (11, "2.4242", "2.345", "5.50", "2.8308", "2.739", "7.50", "1.225"),
    5: (21, "2.3401", "2.999", "7.92", "2.5533", "3.272", "9.43", "1.463"),
    7: (31, "2.3089", "3.383", "9.20", "2.4533", "3.595", "10.39", "1.608"),
    9: (41, "2.2923", "3.652", "10.03", "2.4015", "3.826", "11.01", "1.711"),
}


def assert_printed(value, printed):
    """value agrees with the printed decimal string to its last digit (half a unit of it, plus rounding slack)."""
    decimals = len(printed.split(".")[1])
    assert abs(value - float(printed)) <= 0.5 * 10.0**-decimals + 1e-12, (value, printed)


def badly_scaled_problem(seed, M=5):
    """Random SPD C_nn with standard deviations from 1e-2 to 3e1 and a random correlation; mean on the same scales."""
    rng = np.random.default_rng(seed)
    d = rng.permutation(np.geomspace(1e-2, 3e1, M))
    G = rng.normal(size=(M, M + 2))
    P = G @ G.T
    R = P / np.sqrt(np.outer(np.diag(P), np.diag(P)))
    C = d[:, None] * R * d[None, :]
    C = 0.5 * (C + C.T)
    mu = d * rng.uniform(1.0, 3.0, M) * rng.choice([-1.0, 1.0], M)
    return mu, C


# ---------------------------------------------------------------- §1.1 one-dimensional positions


def test_cvm_nodes_D5():
    np.testing.assert_allclose(cvm_nodes(5), [-1.281552, -0.524401, 0.0, 0.524401, 1.281552], rtol=0, atol=1e-6)
    assert abs(cvm_variance(5) - 0.766948) <= 5e-7


@pytest.mark.parametrize("D", sorted(TABLE_1_1))
def test_table_1_1(D):
    u_half, s2, s, m4, u_std, m4_std = TABLE_1_1[D]
    u = cvm_nodes(D)
    np.testing.assert_allclose(u[D // 2:], u_half, rtol=0, atol=5e-7)
    np.testing.assert_allclose(u[: D // 2 + 1], -np.array(u_half[::-1]), rtol=0, atol=5e-7)
    assert abs(cvm_variance(D) - s2) <= 5e-7
    assert abs(np.sqrt(cvm_variance(D)) - s) <= 5e-7
    assert abs(np.mean(u**4) - m4) <= 5e-7
    np.testing.assert_allclose(u[D // 2:] / np.sqrt(cvm_variance(D)), u_std, rtol=0, atol=5e-7)
    assert abs(np.mean(u**4) / cvm_variance(D) ** 2 - m4_std) <= 5e-5


@pytest.mark.parametrize("D", [1, 2, 3, 4, 5, 8, 11])
def test_cvm_nodes_structure(D):
    u = cvm_nodes(D)
    assert u.shape == (D,)
    assert np.all(np.diff(u) > 0)
    np.testing.assert_array_equal(u, -u[::-1])  # exactly symmetric
    if D % 2:
        assert u[D // 2] == 0.0
    # midpoint-quantile rule: the stationarity condition 2 Phi(u_k) = (2k-1)/D of spec §1.1
    k = np.arange(1, D + 1)
    np.testing.assert_allclose(stats.norm.cdf(u), (2 * k - 1) / (2 * D), rtol=0, atol=1e-15)
    assert cvm_variance(D) < 1.0


def _cvm_distance(u):
    """Plain Cramer-von Mises distance integral (Phi - Ftilde)^2 dt, integrated piecewise between the jumps."""
    u = np.sort(u)
    D = len(u)
    edges = np.concatenate([[-np.inf], u, [np.inf]])
    total = 0.0
    for i in range(D + 1):
        F = i / D
        total += integrate.quad(lambda t: (stats.norm.cdf(t) - F) ** 2, edges[i], edges[i + 1], epsabs=1e-13)[0]
    return total


def test_cvm_nodes_minimise_distance_D3():
    u = cvm_nodes(3)
    d0 = _cvm_distance(u)
    for k in range(3):
        for step in (-1e-2, 1e-2):
            v = u.copy()
            v[k] += step
            assert _cvm_distance(v) > d0


# ---------------------------------------------------------------- §1.3 spread table and sample structure


@pytest.mark.parametrize("D", sorted(TABLE_1_3))
def test_table_1_3_spread(D):
    L, cA, outA, m4A, cB, outB, m4B, outU = TABLE_1_3[D]
    M = 5
    u_max = cvm_nodes(D)[-1]
    res = {}
    for v in "ABU":
        s = sample(np.zeros(M), np.eye(M), D=D, variant=v, sqrt="cholesky")
        assert s.L == L and s.nodes.shape == (L, M)
        t = s.nodes[:, 0]  # axes = I, so the nodes are standardised coordinates
        res[v] = (np.max(np.abs(s.nodes)) / u_max, np.max(np.abs(s.nodes)), float(s.weights @ t**4))
    assert_printed(res["A"][0], cA)
    assert_printed(res["A"][1], outA)
    assert_printed(res["A"][2], m4A)
    assert_printed(res["B"][0], cB)
    assert_printed(res["B"][1], outB)
    assert_printed(res["B"][2], m4B)
    assert_printed(res["U"][1], outU)


@pytest.mark.parametrize("variant", "ABU")
def test_node_order_and_weights(variant):
    M, D = 3, 5
    mu, C = badly_scaled_problem(1, M)
    s = sample(mu, C, D=D, variant=variant)
    L = M * (D - 1) + 1
    u = cvm_nodes(D)
    u_nz = np.delete(u, D // 2)
    np.testing.assert_array_equal(s.nodes[0], mu)
    np.testing.assert_array_equal(s.coeff[0], 0.0)
    c = {"A": np.sqrt(L / (D * cvm_variance(D))), "B": np.sqrt(M / cvm_variance(D)),
         "U": 1 / np.sqrt(cvm_variance(D))}[variant]
    for j in range(M):
        block = s.coeff[1 + j * (D - 1): 1 + (j + 1) * (D - 1)]
        np.testing.assert_allclose(block[:, j], c * u_nz, rtol=1e-15)
        np.testing.assert_array_equal(np.delete(block, j, axis=1), 0.0)
    np.testing.assert_allclose(s.nodes, mu + s.coeff @ s.axes.T, rtol=0, atol=1e-14 * np.max(np.abs(s.nodes)))
    assert abs(s.weights.sum() - 1.0) <= 1e-14
    expected_w = {"A": np.full(L, 1 / L),
                  "B": np.r_[1 / D, np.full(L - 1, 1 / (M * D))],
                  "U": np.r_[1 - M + M / D, np.full(L - 1, 1 / D)]}[variant]
    np.testing.assert_allclose(s.weights, expected_w, rtol=1e-15)
    assert s.variant == variant and s.D == D and s.clipped == 0


def test_variant_U_centre_weight_is_negative():
    s = sample(np.zeros(5), np.eye(5), D=5, variant="U")
    assert s.weights[0] == pytest.approx(-3.0)


# ---------------------------------------------------------------- §1.5 exact moments of A and B


@pytest.mark.parametrize("sqrt", SQRTS)
@pytest.mark.parametrize("variant", "AB")
@pytest.mark.parametrize("D", [3, 5, 9])
def test_exact_moments_A_B(variant, sqrt, D):
    for seed in range(3):
        mu, C = badly_scaled_problem(seed)
        s = sample(mu, C, D=D, variant=variant, sqrt=sqrt)
        norm_C = np.linalg.norm(C, 2)
        np.testing.assert_allclose(s.axes @ s.axes.T, C, rtol=0, atol=1e-13 * norm_C)
        assert np.all(s.weights > 0)
        assert abs(s.weights.sum() - 1.0) <= 1e-14
        # the spec's sums over the sample set
        assert np.linalg.norm(s.weights @ s.nodes - mu) <= 1e-12 * np.linalg.norm(mu)
        dev = s.nodes - mu
        assert np.linalg.norm((dev * s.weights[:, None]).T @ dev - C, 2) <= 1e-12 * norm_C
        # through the moment functions, f = identity
        m, P = moments(s, s.nodes)
        assert np.linalg.norm(m - mu) <= 1e-12 * np.linalg.norm(mu)
        assert np.linalg.norm(P - C, 2) <= 1e-12 * norm_C
        np.testing.assert_array_equal(P, P.T)
        assert np.linalg.norm(cross_moment(s, s.nodes) - C, 2) <= 1e-12 * norm_C


@pytest.mark.parametrize("variant", "ABU")
def test_linear_map_exact(variant):
    """f(theta) = G theta + g: mean G mu + g, covariance G C G^T, cross-covariance G C for every variant and root."""
    rng = np.random.default_rng(7)
    mu, C = badly_scaled_problem(3)
    G = rng.normal(size=(3, 5)) / np.sqrt(np.diag(C))
    g = rng.normal(size=3)
    for sqrt in SQRTS:
        s = sample(mu, C, D=5, variant=variant, sqrt=sqrt)
        F = s.nodes @ G.T + g
        m, P = moments(s, F)
        P_true = G @ C @ G.T
        np.testing.assert_allclose(m, G @ mu + g, rtol=0, atol=1e-12 * np.linalg.norm(G @ mu + g))
        np.testing.assert_allclose(P, P_true, rtol=0, atol=1e-12 * np.linalg.norm(P_true, 2))
        np.testing.assert_allclose(cross_moment(s, F), G @ C, rtol=0, atol=1e-12 * np.linalg.norm(G @ C, 2))


@pytest.mark.parametrize("D", [3, 5, 7])
@pytest.mark.parametrize("variant", "ABU")
def test_M1_all_variants_agree(variant, D):
    mu, sigma = 2.5, 0.3
    s = sample([mu], [[sigma**2]], D=D, variant=variant)
    u = cvm_nodes(D)
    expected = mu + np.r_[0.0, np.delete(u, D // 2)] / np.sqrt(cvm_variance(D)) * sigma
    np.testing.assert_allclose(s.nodes[:, 0], expected, rtol=1e-15, atol=0)
    np.testing.assert_allclose(s.weights, 1.0 / D, rtol=1e-14)
    m, P = moments(s, s.nodes)
    assert m[0] == pytest.approx(mu, rel=1e-15)
    assert P[0, 0] == pytest.approx(sigma**2, rel=1e-13)


# ---------------------------------------------------------------- variant U


def _tensor_rule(mu, S, D, F_of_theta):
    """Brute force: D^M-point product rule of the standardised 1-D positions u/s_D along the columns of S."""
    t = cvm_nodes(D) / np.sqrt(cvm_variance(D))
    Z = np.array(list(itertools.product(t, repeat=len(mu))))
    X = mu + Z @ S.T
    F = F_of_theta(X)
    m = F.mean(axis=0)
    dF = F - m
    return m, dF.T @ dF / len(F), dF.T @ (X - X.mean(axis=0)) / len(F)


def _additive(mu, S):
    """f = [sum_j h_j(z_j), sum_j g_j(z_j)] with z = S^{-1}(theta - mu); h_j cubic, g_j non-polynomial."""
    a = np.array([0.3, -1.2, 0.7, 2.0, -0.4])
    b = np.array([1.5, 0.2, -0.8, 0.1, 1.1])

    def f(X):
        Z = np.linalg.solve(S, (X - mu).T).T
        h = np.sum(a * Z**3 + b * Z**2 + Z, axis=1)
        g = np.sum(np.sin(a * Z) + np.exp(0.3 * b * Z), axis=1)
        return np.column_stack([h, g])

    return f, b


@pytest.mark.parametrize("sqrt", SQRTS)
def test_variant_U_additive_in_standardised_coordinates(sqrt):
    mu, C = badly_scaled_problem(4)
    s = sample(mu, C, D=5, variant="U", sqrt=sqrt)
    f, b = _additive(mu, s.axes)
    F = f(s.nodes)
    m, P = moments(s, F)
    Cx = cross_moment(s, F)
    m_ref, P_ref, Cx_ref = _tensor_rule(mu, s.axes, 5, f)
    np.testing.assert_allclose(m, m_ref, rtol=1e-12)
    np.testing.assert_allclose(P, P_ref, rtol=1e-11, atol=1e-12 * np.abs(P_ref).max())
    np.testing.assert_allclose(Cx, Cx_ref, rtol=0, atol=1e-11 * np.abs(Cx_ref).max())
    # the cubic part is exact against the Gaussian itself: E[a z^3 + b z^2 + z] = b
    assert m[0] == pytest.approx(b.sum(), rel=1e-12)


def test_variant_U_spec_cross_formula():
    """Without clipping, cross_moment equals the spec's sum_j (1/D) sum_k f_{j,k} (u_k/s_D) s_j^T."""
    mu, C = badly_scaled_problem(5)
    D, M = 5, 5
    s = sample(mu, C, D=D, variant="U")
    F = np.column_stack([np.sin(s.nodes[:, 0] / 30) * s.nodes[:, 1], s.nodes[:, 2] ** 2])
    t = np.delete(cvm_nodes(D), D // 2) / np.sqrt(cvm_variance(D))
    ref = np.zeros((2, M))
    for j in range(M):
        Fj = F[1 + j * (D - 1): 1 + (j + 1) * (D - 1)]
        ref += np.outer(Fj.T @ t, s.axes[:, j]) / D
    np.testing.assert_allclose(cross_moment(s, F), ref, rtol=0, atol=1e-12 * np.abs(ref).max())


def test_variant_U_misses_interactions():
    """Products of standardised coordinates are invisible along single axes: E[z1^2 z2^2] = 1, Var[z1 z2] = 1."""
    mu, C = badly_scaled_problem(6)
    s = sample(mu, C, D=5, variant="U", sqrt="eigen")
    Z = np.linalg.solve(s.axes, (s.nodes - mu).T).T
    m, _ = moments(s, Z[:, 0] ** 2 * Z[:, 1] ** 2)
    assert abs(m[0] - 1.0) > 0.5
    _, P = moments(s, Z[:, 0] * Z[:, 1])
    assert abs(P[0, 0] - 1.0) > 0.5
    # the D^M product rule over the same positions does see them: E[z1^2 z2^2] = E[t^2]^2 = 1 there
    def z1z2_squared(X):
        Zx = np.linalg.solve(s.axes, (X - mu).T).T
        return (Zx[:, 0] * Zx[:, 1])[:, None] ** 2

    m_ref, _, _ = _tensor_rule(mu, s.axes, 5, z1z2_squared)
    assert m_ref[0] == pytest.approx(1.0, rel=1e-12)


# ---------------------------------------------------------------- §1.4 clipping


def test_clipping_counts_and_values():
    mu = np.array([0.15, 0.45])  # rho-like and nu-like parameters near their bounds
    C = np.diag([0.1**2, 0.05**2])
    lower = np.array([0.0, -1.0])
    upper = np.array([np.inf, 0.5])
    free = sample(mu, C, D=5, variant="A", sqrt="cholesky")
    s = sample(mu, C, D=5, variant="A", sqrt="cholesky", lower=lower, upper=upper)
    eps = np.array([0.0, 1e-6 * 1.5])
    expected = np.clip(free.nodes, lower + eps, upper - eps)
    assert s.clipped == int(np.count_nonzero(expected != free.nodes)) == 2
    np.testing.assert_array_equal(s.nodes, expected)
    assert s.nodes[:, 0].min() == 0.0  # infinite width: eps = 0
    assert s.nodes[:, 1].max() == 0.5 - 1.5e-6
    # coeff keeps the unclipped construction; the moments use the clipped nodes
    np.testing.assert_array_equal(s.coeff, free.coeff)
    m, _ = moments(s, s.nodes)
    np.testing.assert_allclose(m, s.weights @ expected, rtol=1e-15)
    assert m[0] > mu[0] and m[1] < mu[1]


def test_clipping_wide_box_and_one_side():
    mu, C = badly_scaled_problem(2)
    free = sample(mu, C)
    s = sample(mu, C, lower=np.full(5, -1e6), upper=np.full(5, 1e6))
    assert s.clipped == 0
    np.testing.assert_array_equal(s.nodes, free.nodes)
    lo = mu - 0.5 * np.sqrt(np.diag(C))
    s = sample(mu, C, lower=lo)
    assert s.clipped == int(np.count_nonzero(free.nodes < lo)) > 0
    assert np.all(s.nodes >= lo)


def test_clipping_validation():
    mu, C = np.zeros(2), np.eye(2)
    with pytest.raises(ValueError, match="lower < upper"):
        sample(mu, C, lower=[0.0, 1.0], upper=[1.0, 1.0])
    with pytest.raises(ValueError, match=r"lower: expected shape \(2,\)"):
        sample(mu, C, lower=[0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="NaN"):
        sample(mu, C, upper=[np.nan, 1.0])


# ---------------------------------------------------------------- validation and value semantics


@pytest.mark.parametrize("D", [1, 2, 4, 6])
def test_D_must_be_odd_at_least_3(D):
    with pytest.raises(ValueError, match="D must be odd and >= 3"):
        sample(np.zeros(2), np.eye(2), D=D)


@pytest.mark.parametrize("D", [0, -3, 2.0, True])
def test_bad_D_type_or_range(D):
    with pytest.raises(ValueError, match="D"):
        sample(np.zeros(2), np.eye(2), D=D)
    with pytest.raises(ValueError, match="D"):
        cvm_nodes(D)


@pytest.mark.parametrize("cov, match", [
    ([[1.0, 2.0], [2.0, 1.0]], "cov: not positive definite"),
    ([[1.0, 0.0], [0.0, 0.0]], "cov: not positive definite"),
    ([[-1.0, 0.0], [0.0, 1.0]], "cov: not positive definite"),
    ([[1.0, 0.5], [0.1, 1.0]], "cov: not symmetric"),
    ([[1.0, 0.0], [0.0, np.inf]], "cov: non-finite"),
    (np.eye(3), r"cov: expected shape \(2, 2\)"),
])
@pytest.mark.parametrize("sqrt", SQRTS)
def test_bad_cov(cov, match, sqrt):
    with pytest.raises(ValueError, match=match):
        sample(np.zeros(2), cov, sqrt=sqrt)


def test_bad_arguments():
    with pytest.raises(ValueError, match=r"mean: expected shape \(M,\)"):
        sample(np.zeros((2, 1)), np.eye(2))
    with pytest.raises(ValueError, match="mean: non-finite"):
        sample([0.0, np.nan], np.eye(2))
    with pytest.raises(ValueError, match="variant"):
        sample(np.zeros(2), np.eye(2), variant="C")
    with pytest.raises(ValueError, match="sqrt"):
        sample(np.zeros(2), np.eye(2), sqrt="svd")
    s = sample(np.zeros(2), np.eye(2))
    with pytest.raises(ValueError, match=r"values: expected shape \(9, p\)"):
        moments(s, np.zeros((8, 2)))
    with pytest.raises(ValueError, match=r"values: expected shape \(9, p\)"):
        cross_moment(s, np.zeros((9, 2, 1)))
    with pytest.raises(ValueError, match="values: non-finite"):
        moments(s, np.full(9, np.inf))


def test_sample_set_is_a_checked_value():
    s = sample(np.zeros(2), np.eye(2))
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.D = 7
    with pytest.raises(ValueError):
        s.nodes[0, 0] = 1.0  # read-only arrays
    with pytest.raises(ValueError, match="weights: expected shape"):
        dataclasses.replace(s, weights=np.ones(3))
    with pytest.raises(ValueError, match="L = M"):
        SampleSet(nodes=np.zeros((4, 2)), weights=np.ones(4) / 4, variant="A", D=3, axes=np.eye(2),
                  coeff=np.zeros((4, 2)))
    # pure and deterministic
    again = sample(np.zeros(2), np.eye(2))
    np.testing.assert_array_equal(again.nodes, s.nodes)
    np.testing.assert_array_equal(again.axes, s.axes)


def test_correlation_root_of_diagonal_cov():
    """For a diagonal C_nn every root is diag(sigma) up to column order and sign; nodes sit on the coordinate axes."""
    sigma = np.array([1e-2, 3e1, 0.5])
    for sqrt in SQRTS:
        s = sample(np.ones(3), np.diag(sigma**2), sqrt=sqrt)
        np.testing.assert_allclose(np.sort(np.abs(s.axes), axis=None)[-3:], np.sort(sigma), rtol=1e-14)
        assert np.count_nonzero(np.abs(s.axes) > 1e-300) == 3
