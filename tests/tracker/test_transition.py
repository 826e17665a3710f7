"""TransitionFamily (tracker/transition.py) against the dense reference ``PatchModel.system``
(docs/spec/estimator.md §7,
§8 item 9): the modal batch path must reproduce ``A(theta)``, ``B0(theta)``, ``B1(theta)``, the propagation
``A x + B0 u0 + B1 u1`` and the weighted sandwich ``sum_i w_i A_i C A_i^T`` to rounding.

Error measure throughout: ``max |x - x_ref| / max |x_ref|`` per matrix (or per propagated state). The family
factors ``M0`` by Cholesky and calls ``eigh`` on the standard problem; the reference solves the generalised
``eigh(K, M)``; the two differ by the rounding of two different eigensolvers. Observed: 1e-15 .. 1e-13 for every
case except ``light_soft`` on the paper patch, so RTOL = 1e-12 (spec §8 item 9) has a margin of >= 10x, while any
algebraic slip (a wrong FOH coefficient, a transposed block, a lost 1/rho) gives O(1) errors.

``light_soft`` (nu = 0.49, zeta_0 = 0.02, omega_max dt = 340 rad) is ill-conditioned: an offline 40-digit mpmath
evaluation of the exact modal A/B0/B1 (eigsy + per-mode augmented expm) put *both* the family and the reference
(and scipy's expm) at 2e-13 .. 8e-13 from the exact answer, so their mutual difference reaches 1.5e-12 (observed).
That case gets RTOL_ILL = 5e-12 (3x margin); it is the eigenproblem's conditioning, not the family's algebra.
"""

import copy

import numpy as np
import pytest

from heartcv.tracker.config import model_config_from_dict
from heartcv.tracker.model import build_model
from heartcv.tracker.transition import TransitionFamily
from tests.conftest import load_yaml

RTOL = 1e-12  # spec §8 item 9; see the module docstring for the observed margin
RTOL_ILL = 5e-12  # the ill-conditioned 'light_soft' case only (module docstring)


def rel_err(x, ref):
    return float(np.max(np.abs(np.asarray(x) - ref)) / np.max(np.abs(ref)))


@pytest.fixture(scope="module")
def myo_model():
    """The reduced (Ritz basis, r = 13) myocardium model of sample_sequences/myocardium.yaml (~2 s to build)."""
    return build_model(model_config_from_dict(copy.deepcopy(load_yaml("myocardium.yaml"))))


@pytest.fixture(scope="module", params=["paper_patch", "myocardium"])
def model(request, paper_model, myo_model):
    return paper_model if request.param == "paper_patch" else myo_model


def theta_cases(model):
    """Named thetas: nominal, heavily overdamped (large alpha2), a critically damped lowest mode (the
    ``near`` branch of ``modal_blocks``), a mode just above/below critical, undamped, and a different rho/E/nu."""
    th0 = np.array(model.config.theta, float)
    fam = TransitionFamily(model, model.config.dt)
    omega0 = np.sqrt(th0[3] / th0[0] * fam.basis(th0[4]).lam[0])
    crit = 2.0 / omega0  # alpha1 = 0, alpha2 = 2/omega_0  ->  zeta_0 = alpha2 omega_0 / 2 = 1
    return {
        "nominal": th0,
        "overdamped": np.array([th0[0], 50.0, 0.5, th0[3], th0[4]]),  # zeta >= ~200 for every mode
        "critical": np.array([th0[0], 0.0, crit, th0[3], th0[4]]),
        "above_critical": np.array([th0[0], 0.0, crit * (1 + 1e-6), th0[3], th0[4]]),
        "below_critical": np.array([th0[0], 0.0, crit * (1 - 1e-6), th0[3], th0[4]]),
        "undamped": np.array([th0[0], 0.0, 0.0, th0[3], 0.3]),
        "light_soft": np.array([700.0, 1.0, 1e-4, 2.0e4, 0.49]),
    }


CASES = ["nominal", "overdamped", "critical", "above_critical", "below_critical", "undamped", "light_soft"]


def tol(case):
    return RTOL_ILL if case == "light_soft" else RTOL


def test_critical_case_is_critical(model):
    """Guard for the case list: the 'critical' theta really puts the lowest mode at zeta = 1 (so the modal
    ``near`` branch is exercised) and 'overdamped' really is overdamped in every mode."""
    fam = TransitionFamily(model, model.config.dt)
    cases = theta_cases(model)
    for name, zeta_check in (("critical", lambda z: abs(z[0] - 1) < 1e-12),
                             ("overdamped", lambda z: z.min() > 100)):
        th = cases[name]
        w2 = th[3] / th[0] * fam.basis(th[4]).lam
        zeta = (th[1] + th[2] * w2) / (2 * np.sqrt(w2))
        assert zeta_check(zeta), (name, zeta[:3])


@pytest.mark.parametrize("case", CASES)
def test_system_equals_reference_modal(model, case):
    th = theta_cases(model)[case]
    fam = TransitionFamily(model, model.config.dt)
    A, B0, B1 = fam.system(th)
    ref = model.system(th)  # the model file's method: modal (generalised eigh), the reference of spec §3.4
    assert model.config.method == "modal"
    assert rel_err(A, ref.A) <= tol(case)
    assert rel_err(B0, ref.B0) <= tol(case)
    assert rel_err(B1, ref.B1) <= tol(case)


@pytest.mark.parametrize("case", ["nominal", "critical", "undamped", "light_soft"])
def test_system_equals_expm(model, case):
    """Independent oracle: Van Loan's augmented exponential. expm is itself accurate only to ~1e-11 here
    (observed 2e-13 .. 6e-12 against either modal path), hence 1e-10; stiff overdamped cases are left out because
    scaling-and-squaring of ``|c dt| ~ 1e4`` loses ~1e-10 on its own."""
    th = theta_cases(model)[case]
    fam = TransitionFamily(model, model.config.dt)
    A, B0, B1 = fam.system(th)
    ref = model.system(th, method="expm")
    assert rel_err(A, ref.A) <= 1e-10
    assert rel_err(B0, ref.B0) <= 1e-10
    assert rel_err(B1, ref.B1) <= 1e-10


def test_system_other_dt(paper_model):
    """The family's own dt is used (not the model file's)."""
    th = theta_cases(paper_model)["nominal"]
    dt = 0.004
    A, B0, B1 = TransitionFamily(paper_model, dt).system(th)
    ref = paper_model.system(th, dt)
    assert rel_err(A, ref.A) <= RTOL and rel_err(B0, ref.B0) <= RTOL and rel_err(B1, ref.B1) <= RTOL
    assert rel_err(A, paper_model.system(th).A) > 1e-2  # and dt matters


def mixed_thetas(model):
    """8 samples in 3 nu groups (0.45/0.47 shared by 4, 0.3 by 2, 0.49 by 2), varied rho, alpha, E; and the
    tolerance of each row (row 6 is the ill-conditioned 'light_soft' case)."""
    th0 = np.array(model.config.theta, float)
    c = theta_cases(model)
    rows = [th0, c["overdamped"], c["critical"], c["above_critical"],  # share th0[4]
            c["undamped"], [1200.0, 5.0, 0.002, 3.0e5, 0.3],          # share 0.3
            c["light_soft"], [900.0, 0.5, 0.01, 8.0e4, 0.49]]         # share 0.49
    tols = np.full(len(rows), RTOL)
    tols[6] = RTOL_ILL
    return np.array(rows, float), tols


def realistic_states(model, rng, L):
    """States with mm-scale displacements and cm/s-scale velocities."""
    r = model.r
    return np.hstack([1e-3 * rng.standard_normal((L, r)), 1e-2 * rng.standard_normal((L, r))])


def test_propagate_mixed_groups_equals_dense(model, rng):
    th, tols = mixed_thetas(model)
    perm = rng.permutation(th.shape[0])  # groups interleaved in the input order
    th, tols = th[perm], tols[perm]
    X = realistic_states(model, rng, th.shape[0])
    n_u = model.loads.shape[1]
    u0, u1 = rng.uniform(500, 15000, n_u), rng.uniform(500, 15000, n_u)  # Pa
    fam = TransitionFamily(model, model.config.dt)
    out = fam.propagate(th, X, u0, u1)
    assert fam.eig_count == 3
    for i in range(th.shape[0]):
        s = model.system(th[i])
        ref = s.A @ X[i] + s.B0 @ u0 + s.B1 @ u1
        assert rel_err(out[i], ref) <= tols[i], i
    # without inputs: the homogeneous part only
    out0 = fam.propagate(th, X)
    for i in range(th.shape[0]):
        ref = model.system(th[i]).A @ X[i]
        assert rel_err(out0[i], ref) <= tols[i], i
    assert fam.eig_count == 3  # the second call hit the cache


def random_cov(model, rng):
    """SPD covariance with position/velocity scales (1e-4 m, 1e-3 m/s) and strong correlations."""
    n = 2 * model.r
    G = rng.standard_normal((n, n + 3))
    d = np.r_[np.full(model.r, 1e-4), np.full(model.r, 1e-3)]
    C = (d[:, None] * G) @ (d[:, None] * G).T / n
    return 0.5 * (C + C.T)


def test_weighted_sandwich_equals_dense(model, rng):
    """spec §8 item 9: sum_i w_i A_i C A_i^T, arbitrary positive weights (not normalised), mixed nu groups."""
    th, _ = mixed_thetas(model)
    w = rng.uniform(0.05, 3.0, th.shape[0])
    C = random_cov(model, rng)
    fam = TransitionFamily(model, model.config.dt)
    S = fam.weighted_sandwich(th, w, C)
    ref = np.zeros_like(C)
    for wi, t in zip(w, th):
        A = model.system(t).A
        ref += wi * (A @ C @ A.T)
    assert rel_err(S, ref) <= RTOL  # observed 3e-14 / 8e-14 (the sums average the ill-conditioned row away)
    # symmetric to rounding only (blocks T S T^T are not symmetrised; the GE symmetrises its result): obs. 3e-16
    assert np.max(np.abs(S - S.T)) <= 1e-14 * np.max(np.abs(S))
    # every group on its own, and a single sample: the sandwich is linear in the weights
    for nu in np.unique(th[:, 4]):
        idx = np.flatnonzero(th[:, 4] == nu)
        part = TransitionFamily(model, model.config.dt).weighted_sandwich(th[idx], w[idx], C)
        ref_g = sum(wi * (model.system(t).A @ C @ model.system(t).A.T) for wi, t in zip(w[idx], th[idx]))
        assert rel_err(part, ref_g) <= RTOL
    A0 = model.system(th[0]).A
    assert rel_err(fam.weighted_sandwich(th[:1], [1.0], C), A0 @ C @ A0.T) <= RTOL


def test_static_states_equal_dense_block_diagonal(model, rng):
    """Static states after the kinematic ones (the reference block): the transition is blkdiag(A(theta), I_s);
    propagate and the weighted sandwich equal the dense products (mixed nu groups, arbitrary weights)."""
    th, tols = mixed_thetas(model)
    s_dim = model.r
    n = 2 * model.r
    w = rng.uniform(0.05, 3.0, th.shape[0])
    G = rng.standard_normal((n + s_dim, n + s_dim + 3))
    d = np.r_[np.full(model.r, 1e-4), np.full(model.r, 1e-3), np.full(s_dim, 3e-4)]
    C = (d[:, None] * G) @ (d[:, None] * G).T / n
    C = 0.5 * (C + C.T)
    X = np.hstack([realistic_states(model, rng, th.shape[0]), 1e-3 * rng.standard_normal((th.shape[0], s_dim))])
    n_u = model.loads.shape[1]
    u0, u1 = rng.uniform(500, 15000, n_u), rng.uniform(500, 15000, n_u)
    fam = TransitionFamily(model, model.config.dt)
    Y, S = fam.propagate_and_sandwich(th, X, w, C, u0, u1)
    ref = np.zeros_like(C)
    for i, (wi, t) in enumerate(zip(w, th)):
        sysd = model.system(t)
        Ab = np.eye(n + s_dim)
        Ab[:n, :n] = sysd.A
        ref += wi * (Ab @ C @ Ab.T)
        y_ref = np.r_[sysd.A @ X[i, :n] + sysd.B0 @ u0 + sysd.B1 @ u1, X[i, n:]]
        assert rel_err(Y[i], y_ref) <= tols[i], i
        assert np.array_equal(fam.propagate(t[None], X[i:i + 1], u0, u1)[0, n:], X[i, n:])
    assert rel_err(S, ref) <= RTOL
    assert np.array_equal(S[n:, :n], S[:n, n:].T)
    with pytest.raises(ValueError, match="columns"):
        fam.propagate_and_sandwich(th, X[:, :-1], w, C)


def test_shared_nu_shares_one_eigendecomposition(paper_model):
    th0 = np.array(paper_model.config.theta, float)
    fam = TransitionFamily(paper_model, paper_model.config.dt)
    assert fam.eig_count == 0
    same_nu = np.array([th0 * [1, 1, 1, f, 1] for f in (0.5, 1.0, 2.0, 4.0)])
    same_nu[:, 0] = [800, 1000, 1200, 1500]
    X = np.zeros((4, paper_model.state_dim))
    fam.propagate(same_nu, X)
    assert fam.eig_count == 1
    b = fam.basis(th0[4])
    assert fam.basis(th0[4]) is b and fam.eig_count == 1  # cache hit returns the same object, no recompute
    fam.weighted_sandwich(same_nu, np.ones(4), np.eye(paper_model.state_dim))
    fam.system(same_nu[2])
    assert fam.eig_count == 1
    two = same_nu.copy()
    two[2:, 4] = 0.3
    fam.propagate(two, X)
    assert fam.eig_count == 2  # only nu = 0.3 is new
    assert [len(idx) for _, idx in fam.groups(two)] == [2, 2]


def test_cache_evicts_least_recently_used(paper_model):
    fam = TransitionFamily(paper_model, paper_model.config.dt, cache_size=2)
    fam.basis(0.3)
    fam.basis(0.4)
    fam.basis(0.3)          # hit; 0.4 becomes the least recently used
    assert fam.eig_count == 2
    fam.basis(0.45)         # evicts 0.4
    assert fam.eig_count == 3
    fam.basis(0.3)
    assert fam.eig_count == 3
    fam.basis(0.4)          # was evicted: recomputed
    assert fam.eig_count == 4


@pytest.mark.parametrize("nu", [0.0, 0.5, 0.6, -0.1, float("nan")])
def test_nu_outside_open_interval_is_rejected(paper_model, nu):
    fam = TransitionFamily(paper_model, paper_model.config.dt)
    th = np.array(paper_model.config.theta, float)
    th[4] = nu
    with pytest.raises(ValueError, match="nu"):
        fam.propagate(th[None], np.zeros((1, paper_model.state_dim)))
    with pytest.raises(ValueError, match="nu"):
        fam.system(th)
    assert fam.eig_count == 0


def test_bad_shapes_are_rejected(paper_model):
    fam = TransitionFamily(paper_model, paper_model.config.dt)
    th = np.tile(paper_model.config.theta, (3, 1))
    n = paper_model.state_dim
    for shape in ((2, n), (4, n), (3, n // 2), (3, n - 1)):
        with pytest.raises(ValueError, match="X"):
            fam.propagate(th, np.zeros(shape))
    with pytest.raises(ValueError, match="weights"):
        fam.weighted_sandwich(th, np.ones(2), np.eye(n))


@pytest.mark.parametrize("dt", [0.0, -1 / 30, float("nan"), float("inf")])
def test_bad_dt_is_rejected(paper_model, dt):
    with pytest.raises(ValueError, match="dt"):
        TransitionFamily(paper_model, dt)
