"""Joint state and parameter estimators (tracker/joint.py: GE, joint UKF, joint EKF; docs/spec/estimator.md §2, §4,
§5, §8 items 3, 9, 10).

Reference computations are independent of the code under test: the Kalman prediction of the joint state
(tracker.kalman.predict with F = blkdiag(I, A)), the dense per-node GE of tracker.ge.ge_predict fed with
``PatchModel.system``, finite differences of ``PatchModel.system`` and the batch least-squares oracle of
tests/tracker/lg_checker.py.
"""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pytest
import scipy.linalg as sla

from heartcv.tracker.config import model_config_from_dict
from heartcv.tracker.ge import ge_predict, ge_predict_family
from heartcv.tracker.io import read_estimates, write_estimates
from heartcv.tracker.joint import ESTIMATORS, JointFilter, JointOptions, joint_prior, run_joint
from heartcv.tracker.kalman import GaussianState, predict, update
from heartcv.tracker.measurements import MeasurementSet
from heartcv.tracker.model import build_model
from heartcv.tracker.sampling import sample
from heartcv.tracker.simulate import simulate, to_measurements
from heartcv.tracker.tracking import EstimationDiverged, locate_points, run_kalman
from heartcv.tracker.transition import TransitionFamily
from heartcv.tracker.truncation import truncate_box

from .lg_checker import LGProblem, check_estimator, make_problem

SEED = 11
THETA_FACTORS = np.array([1.0, 1.0, 1.0, 1.5, 1.0])  # E off by 1.5x ...
NU0 = 0.40                                           # ... and nu = 0.40 (truth 0.45), both inside the box


# ---------------------------------------------------------------------------------------------------------------
# fixtures and helpers

def theta_start(model):
    th = np.array(model.config.theta, float) * THETA_FACTORS
    th[4] = NU0
    return th


@pytest.fixture(scope="module")
def seq100(paper_model):
    """A simulated paper_patch sequence: 100 frames at 30 fps (3.3 s), process and measurement noise."""
    sim = simulate(paper_model, 99 / 30, np.random.default_rng(SEED))
    meas = to_measurements(sim, {"seed": SEED})
    assert meas.n_frames == 100
    return sim, meas


@pytest.fixture(scope="module")
def short_meas(paper_model):
    """16 frames (0.5 s) for the expensive comparisons."""
    return to_measurements(simulate(paper_model, 0.5, np.random.default_rng(SEED + 1)))


@pytest.fixture(scope="module")
def runs(paper_model, seq100):
    """run_joint of GE, UKF and EKF on seq100 from the shifted start (default options from the model file)."""
    th0 = theta_start(paper_model)
    return {name: run_joint(paper_model, seq100[1], name, theta0=th0) for name in ESTIMATORS}


def frame_data(model, meas):
    """Per-frame (y, H_l, R, offset) exactly as the joint estimators see them (independent re-assembly)."""
    pts = locate_points(model, meas)
    obs = pts.observation
    trans = meas.translation()
    frames = []
    for k in range(meas.n_frames):
        y = meas.positions[k, pts.keep].reshape(-1)
        R = sla.block_diag(*meas.covariances[k, pts.keep])
        frames.append((y, obs.H, R, (obs.reference + trans[k]).reshape(-1)))
    return frames


def make_filter(name, model, meas, options=None, theta0=None):
    dt = float(np.median(np.diff(meas.times)))
    u = meas.input_columns(model.input_names)
    prior = joint_prior(model, u[0], theta_start(model) if theta0 is None else theta0)
    options = options or JointOptions.from_config(model.config)
    return JointFilter(name, model, prior.space, dt, prior.Q_n, prior.Q_l, options), prior, u


def assert_spd_symmetric(C, what):
    assert np.array_equal(C, C.T), f"{what}: not exactly symmetric"
    try:
        np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        raise AssertionError(f"{what}: Cholesky failed") from None


def rel(x, ref):
    return float(np.max(np.abs(np.asarray(x) - ref)) / np.max(np.abs(ref)))


def joint_errors(a: GaussianState, b: GaussianState, M):
    """Relative errors of a joint prediction ``a`` against ``b``, block by block (the blocks differ by ~10 orders
    of magnitude: phi units vs metres). Mean blocks and C_nn, C_ll are relative to their own largest entry.

    C_ln is relative to ``max|mu_l| * max sd(x_n)``, the size of the products ``y_i dtheta_i^T`` it is summed
    from: the GE (and the UT) form the cross-covariance from *differences* of propagated means, so a rounding of
    the means y_i shows up at that scale; the block itself is ~50x smaller here (|y_i| / |y_i - mu'_l| ~ 50), so
    a block-relative bound would measure cancellation, not correctness. ``ln_block`` (block-relative) is reported
    too and checked loosely.
    """
    scale_ln = np.max(np.abs(b.mean[M:])) * np.sqrt(np.max(np.diag(b.cov)[:M]))
    return {
        "mean_n": rel(a.mean[:M], b.mean[:M]),
        "mean_l": rel(a.mean[M:], b.mean[M:]),
        "cov_nn": rel(a.cov[:M, :M], b.cov[:M, :M]),
        "cov_ln": float(np.max(np.abs(a.cov[M:, :M] - b.cov[M:, :M])) / scale_ln),
        "cov_ll": rel(a.cov[M:, M:], b.cov[M:, M:]),
        "ln_block": rel(a.cov[M:, :M], b.cov[M:, :M]),
    }


def assert_joint_close(a, b, M, tol, ln_block_tol=1e-10):
    err = joint_errors(a, b, M)
    assert max(v for k, v in err.items() if k != "ln_block") <= tol, err
    assert err["ln_block"] <= ln_block_tol, err
    return err


@pytest.fixture(scope="module")
def ge_steps(paper_model, seq100):
    """The GE run step by step for all 100 frames (JointFilter.predict, truncate, kalman.update, truncate), with
    the covariance after every stage; the states after step 5 serve as realistic correlated joint states."""
    _, meas = seq100
    filt, prior, u = make_filter("ge", paper_model, meas)
    M = filt.M
    frames = frame_data(paper_model, meas)
    state = prior.state
    stages, posts = [], []
    for k, (y, H, R, off) in enumerate(frames):
        if k > 0:
            state, _ = filt.predict(state, u[k - 1], u[k])
            stages.append((k, "predict", state.cov))
            state, _, _ = filt.truncate(state)
            stages.append((k, "truncate(pred)", state.cov))
        Hz = np.hstack([np.zeros((H.shape[0], M)), H])
        state = update(state, y, Hz, R, off).state
        stages.append((k, "update", state.cov))
        state, _, _ = filt.truncate(state)
        stages.append((k, "truncate(post)", state.cov))
        posts.append(state)
    return filt, u, stages, posts


# ---------------------------------------------------------------------------------------------------------------
# theta-independent transition: the joint problem is linear-Gaussian

class FrozenFamily:
    """A transition family whose ``A`` and ``B`` do not depend on theta (the interface of
    tracker.transition.TransitionFamily used by the joint estimators)."""

    def __init__(self, A, B0, B1=None):
        self.A, self.B0 = np.asarray(A, float), np.asarray(B0, float)
        self.B1 = np.zeros_like(self.B0) if B1 is None else np.asarray(B1, float)
        self.calls = 0

    def propagate(self, thetas, X, u0=None, u1=None):
        th, X = np.atleast_2d(thetas), np.atleast_2d(X)
        assert th.shape == (X.shape[0], 5) and np.isfinite(th).all()
        self.calls += 1
        b = 0.0 if u0 is None else self.B0 @ u0 + self.B1 @ u1
        return X @ self.A.T + b

    def weighted_sandwich(self, thetas, weights, C):
        assert np.atleast_2d(thetas).shape == (np.size(weights), 5)
        return float(np.sum(weights)) * (self.A @ C @ self.A.T)

    def propagate_and_sandwich(self, thetas, X, weights, C, u0=None, u1=None):
        Y = None if X is None else self.propagate(thetas, X, u0, u1)
        return Y, self.weighted_sandwich(thetas, weights, C)


def FrozenJointFilter(name, model, space, family, Q_n, Q_l, options=JointOptions()):  # noqa: N802
    """The library's registered joint variant ``name`` (sampling, GE moments, UT, EKF Jacobian, truncation all
    unchanged) on a model whose transition does not depend on the parameters: a linear-Gaussian joint problem.
    ``family`` supplies the transition (a FrozenFamily); the patch model only provides the configuration."""
    filt = JointFilter(name, model, space, model.config.dt, Q_n, Q_l, options)
    assert filt.modal  # the modal path reaches the transition only through filt.family
    filt.family = family
    return filt


def joint_lg_problem(seed, space, n_l=4, m=3, steps=30, q_n=1e-4, param_sd=0.2):
    """A linear-Gaussian joint problem z = [x_n; x_l] in lg_checker form: x_n is a random walk (Q_n = q_n I)
    correlated with x_l through the prior only, x_l follows a random stable LG model, y sees x_l only (with the
    checker's missing entries and one empty frame). x_n starts at phi(theta) of ``space`` with standard
    deviations ~param_sd, far (> 8.3 sigma) from the box, so clipping and truncation stay inactive."""
    rng = np.random.default_rng(seed)
    base = make_problem(rng, n=n_l, m=m, steps=steps)
    M = space.dim
    n = M + n_l
    A = sla.block_diag(np.eye(M), base.A)
    B = np.vstack([np.zeros((M, base.B.shape[1])), base.B])
    Q = sla.block_diag(q_n * np.eye(M), base.Q)
    H = np.hstack([np.zeros((m, M)), base.H])
    G = rng.standard_normal((n, n))
    D = np.r_[np.full(M, param_sd), np.ones(n_l)]
    P0 = D[:, None] * (G @ G.T / n + 0.2 * np.eye(n)) * D[None, :]
    mu0 = np.r_[space.x_from_theta(space.theta), base.prior_mean]
    x = np.empty((steps, n))
    x[0] = rng.multivariate_normal(mu0, P0)
    for k in range(1, steps):
        x[k] = A @ x[k - 1] + B @ base.u[k - 1] + rng.multivariate_normal(np.zeros(n), Q)
    y = x @ H.T + rng.multivariate_normal(np.zeros(m), base.R, size=steps)
    y[np.isnan(base.y)] = np.nan
    arrays = dict(A=A, B=B, u=np.array(base.u), Q=Q, H=H, R=np.array(base.R), offset=np.zeros(m), prior_mean=mu0,
                  prior_cov=0.5 * (P0 + P0.T), y=y, x=x)
    for a in arrays.values():
        a.setflags(write=False)
    return LGProblem(**arrays)


@pytest.fixture(scope="module")
def space(paper_model):
    return paper_model.config.parameter_space()


def joint_run(filt):
    """run(problem) for check_estimator: JointFilter.predict + truncate + kalman.update + truncate (run_joint's
    cycle), asserting that nothing was clipped or truncated (the problem is then exactly linear-Gaussian)."""
    def run(p):
        state = GaussianState(p.prior_mean, p.prior_cov)
        out = []
        for k in range(p.steps):
            if k > 0:
                state, info = filt.predict(state, p.u[k - 1], np.zeros_like(p.u[k]))
                assert info["clipped"] == 0
                state, ev, _ = filt.truncate(state)
                assert ev == 0
            state = update(state, p.y[k], p.H, p.R, p.offset).state
            state, ev, _ = filt.truncate(state)
            assert ev == 0
            out.append((state.mean, state.cov))
        assert filt.family.calls > 0
        return out
    return run


def lg_filter(name, model, space, p, options=JointOptions(), family=None):
    M = space.dim
    family = family or FrozenFamily(p.A[M:, M:], p.B[M:])
    return FrozenJointFilter(name, model, space, family, p.Q[:M, :M], p.Q[M:, M:], options)


LG_CASES = [
    ("ge", JointOptions()),
    ("ge", JointOptions(sqrt="correlation", variant="B", nodes=3)),
    ("ge", JointOptions(sqrt="eigen", nodes=7)),
    ("ukf", JointOptions(alpha=1.0)),
    ("ukf", JointOptions(alpha=0.5, kappa=-3.0)),   # kappa = 3 - n (Julier): negative centre weight
    ("ukf", JointOptions(alpha=0.1)),
    ("ekf", JointOptions()),
]


@pytest.mark.parametrize("name,options", LG_CASES, ids=[f"{n}-{i}" for i, (n, _) in enumerate(LG_CASES)])
def test_lg_checker(paper_model, space, name, options):
    """The shared linear-Gaussian checker (batch least-squares oracle over the stacked trajectory) for every joint
    estimator on a joint problem where no parameter influences the dynamics. The parameter block is corrected only
    through its prior correlation with x_l; GE, UKF and EKF must then all be the exact Kalman filter (checker
    tolerance 1e-9 relative; observed <= 6.7e-13, the oracle's own dense-solve rounding)."""
    for seed in (0, 1):
        p = joint_lg_problem(seed, space)
        check_estimator(joint_run(lg_filter(name, paper_model, space, p, options)), p)


class Drifting(FrozenFamily):
    """A mildly theta-dependent transition: A(theta) = g(theta) A, g = 1 + 0.05 (log E - log E_ref)."""

    def __init__(self, A, B0, E_ref):
        super().__init__(A, B0)
        self.log_E_ref = float(np.log(E_ref))

    def gain(self, thetas):
        return 1.0 + 0.05 * (np.log(np.atleast_2d(thetas)[:, 3]) - self.log_E_ref)

    def propagate(self, thetas, X, u0=None, u1=None):
        X = np.atleast_2d(X)
        b = 0.0 if u0 is None else self.B0 @ u0 + self.B1 @ u1
        return self.gain(thetas)[:, None] * super().propagate(thetas, X) + b

    def weighted_sandwich(self, thetas, weights, C):
        return float(np.sum(np.asarray(weights) * self.gain(thetas) ** 2)) * (self.A @ C @ self.A.T)


@pytest.mark.parametrize("name", ESTIMATORS)
def test_lg_checker_detects_a_theta_dependent_transition(paper_model, space, name):
    """The check has power: with A depending mildly on E the same problem is no longer linear-Gaussian and every
    estimator departs from the batch oracle."""
    p = joint_lg_problem(0, space)
    family = Drifting(p.A[2:, 2:], p.B[2:], space.theta[3])
    with pytest.raises(AssertionError, match="error"):
        check_estimator(joint_run(lg_filter(name, paper_model, space, p, family=family)), p)


# ---------------------------------------------------------------------------------------------------------------
# spec §8 item 3: GE == KF when A and B do not depend on theta (on the paper model's dimensions)

@pytest.mark.parametrize("D", [3, 5, 7])
@pytest.mark.parametrize("variant", ["A", "B"])
@pytest.mark.parametrize("sqrt", ["cholesky", "correlation"])
def test_ge_reduces_to_kf_when_transition_is_parameter_free(paper_model, ge_steps, D, variant, sqrt):
    """A realistic correlated joint state (GE after 5 steps); A, B0, B1 frozen at one theta. Both GE paths (the
    dense ge_predict and the family path ge_predict_family) must equal the Kalman prediction with
    F = blkdiag(I, A), Q = blkdiag(Q_n, Q_l), b = [0; B0 u0 + B1 u1] to 1e-12 (joint_errors; observed <= 1.5e-15
    for the means, C_nn, C_ll and C_ln at its term scale; C_ln block-relative <= 7.4e-13 from cancellation)."""
    filt, u, _, posts = ge_steps
    state, M = posts[5], filt.M
    n_l = state.mean.size - M
    th_ref = theta_start(paper_model)
    s = paper_model.system(th_ref, filt.dt)
    u0, u1 = u[5], u[6]
    b = s.B0 @ u0 + s.B1 @ u1
    Q_n = np.diag([1e-4, 4e-4])
    Q_l = filt.Q_l
    F = sla.block_diag(np.eye(M), s.A)
    ref = predict(state, F, sla.block_diag(Q_n, Q_l), np.r_[np.zeros(M), b])

    ss = sample(state.mean[:M], state.cov[:M, :M], D=D, variant=variant, sqrt=sqrt,
                lower=filt.lower, upper=filt.upper)
    assert ss.clipped == 0  # clipping would (correctly) break the identity
    thetas = filt.space.theta_from_x(ss.nodes)
    fam = FrozenFamily(s.A, s.B0, s.B1)
    out_f = ge_predict_family(state, M, ss.nodes, ss.weights, thetas, fam, u0, u1, Q_n, Q_l)

    def frozen(nodes):
        L = nodes.shape[0]
        return np.broadcast_to(s.A, (L, n_l, n_l)), np.broadcast_to(b, (L, n_l))

    out_d = ge_predict(state, M, ss.nodes, ss.weights, frozen, Q_n, Q_l)
    for out in (out_f, out_d):
        assert_joint_close(out, ref, M, 1e-12)
        assert np.array_equal(out.cov, out.cov.T)


def test_joint_filter_ge_reduces_to_kf(paper_model, space, ge_steps):
    """The same through JointFilter.predict (sampling with the nu-first permutation and clipping, then the family
    path), with the frozen family: equals the joint Kalman prediction (1e-12, joint_errors)."""
    _, u, _, posts = ge_steps
    state = posts[5]
    s = paper_model.system(theta_start(paper_model))
    Q_n, Q_l = np.diag([1e-4, 4e-4]), paper_model.process_noise()
    for options in (JointOptions(), JointOptions(sqrt="correlation", variant="B")):
        filt = FrozenJointFilter("ge", paper_model, space, FrozenFamily(s.A, s.B0, s.B1), Q_n, Q_l, options)
        out, info = filt.predict(state, u[5], u[6])
        assert info["clipped"] == 0 and info["samples"] == 2 * (options.nodes - 1) + 1
        ref = predict(state, sla.block_diag(np.eye(2), s.A), sla.block_diag(Q_n, Q_l),
                      np.r_[0, 0, s.B0 @ u[5] + s.B1 @ u[6]])
        assert_joint_close(out, ref, 2, 1e-12)


@pytest.mark.parametrize("alpha", [1.0, 0.5, 0.1, 1e-2, 1e-3])
def test_ukf_with_linear_model_is_the_kf_for_any_alpha(paper_model, space, ge_steps, alpha):
    """UT of a linear map is exact for any alpha, beta, kappa (the centre weight only multiplies a zero deviation
    in the covariance). Rounding grows with the centre weight |1 - 1/alpha^2| through the weighted mean
    (the sigma points' common part cancels): tolerance 1e-13 * max(1, 1/alpha^2) (joint_errors); observed
    2e-15, 1.2e-14, 1e-13, 9.4e-12, 5.5e-9 for alpha = 1, 0.5, 0.1, 1e-2, 1e-3 (margins 18x .. 100x)."""
    _, u, _, posts = ge_steps
    state = posts[5]
    s = paper_model.system(theta_start(paper_model))
    Q_n, Q_l = np.diag([1e-4, 4e-4]), paper_model.process_noise()
    filt = FrozenJointFilter("ukf", paper_model, space, FrozenFamily(s.A, s.B0, s.B1), Q_n, Q_l,
                             JointOptions(alpha=alpha))
    out, info = filt.predict(state, u[5], u[6])
    ref = predict(state, sla.block_diag(np.eye(2), s.A), sla.block_diag(Q_n, Q_l),
                  np.r_[0, 0, s.B0 @ u[5] + s.B1 @ u[6]])
    assert_joint_close(out, ref, 2, 1e-13 * max(1.0, alpha**-2), ln_block_tol=1e-8 * max(1.0, alpha**-2))


# ---------------------------------------------------------------------------------------------------------------
# spec §8 item 9: the modal family path equals the dense per-node reference on the real model

@pytest.mark.parametrize("variant", ["A", "B"])
@pytest.mark.parametrize("sqrt", ["cholesky", "correlation"])
def test_ge_family_equals_dense_reference(paper_model, ge_steps, sqrt, variant):
    """ge_predict_family (modal TransitionFamily, one eigendecomposition per distinct nu) vs ge_predict with dense
    A(theta_i), B0(theta_i), B1(theta_i) from PatchModel.system for every node; a real sample set of a correlated
    GE state. Mean, C'_nn and C'_ll (which holds the sandwich of spec §8 item 9) to 1e-12 per block (observed
    <= 7.2e-14), C'_ln to 1e-12 at its term scale (joint_errors; observed <= 1.6e-14)."""
    filt, u, _, posts = ge_steps
    state, M = posts[5], filt.M
    p = filt.perm  # nu first, as the GE does for the Cholesky square root
    ss = sample(state.mean[:M][p], state.cov[:M, :M][np.ix_(p, p)], D=5, variant=variant, sqrt=sqrt,
                lower=filt.lower[p], upper=filt.upper[p])
    nodes = ss.nodes[:, filt.inv_perm]
    thetas = filt.space.theta_from_x(nodes)
    assert np.unique(thetas[:, 4]).size == (5 if sqrt == "cholesky" else ss.L)  # spec §7.4 node geometry
    u0, u1 = u[5], u[6]

    def dense(_nodes):
        systems = [paper_model.system(th, filt.dt) for th in thetas]
        return (np.array([s.A for s in systems]), np.array([s.B0 @ u0 + s.B1 @ u1 for s in systems]))

    ref = ge_predict(state, M, nodes, ss.weights, dense, filt.Q_n, filt.Q_l)
    fam = TransitionFamily(paper_model, filt.dt)
    out = ge_predict_family(state, M, nodes, ss.weights, thetas, fam, u0, u1, filt.Q_n, filt.Q_l)
    # C'_ln at its term scale (see joint_errors): a relative rounding delta of A(theta_i), b(theta_i) moves it by
    # ~delta max|y_i| max|dtheta_i|; block-relative it is 1e-12 .. 2.5e-12 here (cancellation)
    assert_joint_close(out, ref, M, 1e-12)
    assert fam.eig_count == np.unique(thetas[:, 4]).size


def test_ge_eigendecompositions_per_step(paper_model, ge_steps):
    """Cholesky square root with nu first: D distinct nu per GE prediction (D eigendecompositions), the
    rotation-invariant square roots L = M (D - 1) + 1 (spec §7.4)."""
    ref, u, _, posts = ge_steps
    for sqrt, expected in (("cholesky", 5), ("correlation", 9), ("eigen", 9)):
        filt = JointFilter("ge", paper_model, ref.space, ref.dt, ref.Q_n, ref.Q_l, JointOptions(sqrt=sqrt))
        filt.predict(posts[5], u[5], u[6])
        assert filt.family.eig_count == expected  # one per distinct nu, none repeated within the step
        if sqrt == "cholesky":  # 5 bases fit the default cache (8); 9 would cycle through an LRU of 8
            filt.predict(posts[5], u[5], u[6])  # the same nodes again: all cache hits
            assert filt.family.eig_count == expected


def test_dense_option_equals_modal_path(paper_model, short_meas):
    """JointOptions(dense=True) (PatchModel.system per node) and the default modal path give the same run over 16
    frames: theta trajectory, phi moments, state means and NIS to ~1e-9 relative. Observed: GE <= 5.5e-14 (the
    1e-14 differences of the two transitions are filtered, not amplified); EKF <= 2.4e-10 in phi_cov, because its
    central-difference Jacobian (step 1e-4) amplifies those differences by 1/h, hence 3e-9 for the EKF."""
    for name, tol in (("ge", 1e-9), ("ekf", 3e-9)):
        opts = JointOptions.from_config(paper_model.config)
        modal = run_joint(paper_model, short_meas, name, theta0=theta_start(paper_model), options=opts)
        dense = run_joint(paper_model, short_meas, name, theta0=theta_start(paper_model),
                          options=replace(opts, dense=True))
        assert modal.meta["modal_path"] and not dense.meta["modal_path"]
        assert modal.complete and dense.complete
        for key in ("theta", "phi_mean", "phi_cov", "state_mean", "nis"):
            assert rel(getattr(dense, key), getattr(modal, key)) <= tol, (name, key)


# ---------------------------------------------------------------------------------------------------------------
# EKF Jacobian

def test_ekf_jacobian_matches_independent_finite_difference(paper_model, seq100):
    """With C_ln = 0 the EKF's predicted cross-covariance is J C_nn, so J = C'_ln C_nn^{-1} is observable. It must
    match a central difference of PatchModel.system (dense, step 1e-3 in phi vs the EKF's 1e-4 in the modal
    family) to 1e-5 relative, per column. Observed 1.7e-7: the reference's own O(h^2) truncation error (1.7e-5 with
    h = 1e-2, 1e-10 with h = 1e-4, so the EKF's J itself is accurate to ~1e-10). The predicted mean is f(mu)
    (1e-12; observed 2e-14), C'_nn = C_nn + Q_n, and C'_ll uses the same J (1e-12; observed 1e-18)."""
    sim, meas = seq100
    filt, prior, u = make_filter("ekf", paper_model, meas)
    M, n_l = filt.M, paper_model.state_dim
    k = 20
    mu_n = prior.state.mean[:M] + np.array([0.1, -0.2])
    x_l = sim.states[k]                      # a moving, non-equilibrium state
    C_nn = np.array([[0.04, 0.01], [0.01, 0.09]])
    C_ll = paper_model.initial_covariance()
    state = GaussianState(np.r_[mu_n, x_l], sla.block_diag(C_nn, C_ll))
    pred, _ = filt.predict(state, u[k], u[k + 1])
    J_ekf = np.linalg.solve(C_nn, pred.cov[M:, :M].T).T

    def f(phi):
        s = paper_model.system(filt.space.theta_from_x(phi), filt.dt)
        return s.A @ x_l + s.B0 @ u[k] + s.B1 @ u[k + 1]

    h = 1e-3
    J_ref = np.stack([(f(mu_n + h * e) - f(mu_n - h * e)) / (2 * h) for e in np.eye(M)], axis=1)
    assert np.abs(J_ref).max() > 1e-3 * np.abs(f(mu_n)).max()  # a non-trivial sensitivity
    assert rel(J_ekf, J_ref) <= 1e-5
    for j in range(M):
        assert rel(J_ekf[:, j], J_ref[:, j]) <= 1e-5, j
    assert rel(pred.mean[M:], f(mu_n)) <= 1e-12
    np.testing.assert_array_equal(pred.mean[:M], mu_n)
    np.testing.assert_allclose(pred.cov[:M, :M], C_nn + filt.Q_n, rtol=1e-15, atol=0)
    # C'_ll = A C_ll A^T + J C_nn J^T + Q_l with the EKF's own J (internal consistency, 1e-12)
    A = paper_model.system(filt.space.theta_from_x(mu_n), filt.dt).A
    ref_ll = A @ C_ll @ A.T + J_ekf @ C_nn @ J_ekf.T + filt.Q_l
    assert rel(pred.cov[M:, M:], ref_ll) <= 1e-12
    assert pred.cov.shape == (M + n_l, M + n_l)


def test_ekf_prediction_is_the_linearised_kalman_prediction(paper_model, seq100):
    """On a strongly correlated joint state (C_ln = G C_nn, G along the state's own parameter sensitivity J scaled
    so that |A G| ~ |J|: the cross terms A C_ln J^T are as large as J C_nn J^T and A C_ll A^T) the EKF prediction
    equals the Kalman prediction with F = [[I, 0], [J, A]] built from PatchModel.system and a finite-difference J
    (step 1e-3 in phi, whose O(h^2) error bounds the agreement): 1e-5 (joint_errors; observed 3.3e-7)."""
    sim, meas = seq100
    ref_filt, prior, u = make_filter("ekf", paper_model, meas)
    # small kinematic noise so that the parameter-driven terms dominate C'_ll
    filt = JointFilter("ekf", paper_model, ref_filt.space, ref_filt.dt, ref_filt.Q_n, 1e-6 * ref_filt.Q_l)
    M, k = filt.M, 20
    mu_n, x_l = prior.state.mean[:M], sim.states[k]

    def f(phi):
        s = paper_model.system(filt.space.theta_from_x(phi), filt.dt)
        return s.A @ x_l + s.B0 @ u[k] + s.B1 @ u[k + 1]

    h = 1e-3
    J = np.stack([(f(mu_n + h * e) - f(mu_n - h * e)) / (2 * h) for e in np.eye(M)], axis=1)
    A = paper_model.system(filt.space.theta_from_x(mu_n), filt.dt).A
    G = J * (np.abs(J).max() / np.abs(A @ J).max())  # C_ln = G C_nn with |A G| ~ |J|: all three terms comparable
    C_nn = np.array([[0.04, 0.01], [0.01, 0.09]])
    C = np.block([[C_nn, C_nn @ G.T], [G @ C_nn, 1e-6 * paper_model.initial_covariance() + G @ C_nn @ G.T]])
    state = GaussianState(np.r_[mu_n, x_l], 0.5 * (C + C.T))
    pred, _ = filt.predict(state, u[k], u[k + 1])
    F = np.block([[np.eye(M), np.zeros((M, A.shape[0]))], [J, A]])
    ref = GaussianState(np.r_[mu_n, f(mu_n)], F @ state.cov @ F.T + sla.block_diag(filt.Q_n, filt.Q_l))
    cross = A @ state.cov[M:, :M] @ J.T
    assert np.abs(cross).max() > 0.1 * np.abs(ref.cov[M:, M:]).max()  # the cross terms matter
    assert_joint_close(pred, ref, M, 1e-5, ln_block_tol=1e-5)


# ---------------------------------------------------------------------------------------------------------------
# spec §8 item 10 and the run_joint loop

def test_covariances_symmetric_and_pd_after_every_step(ge_steps):
    """100 steps of the GE on a simulated paper_patch sequence: after every predict, truncate, update and truncate
    the joint covariance is exactly symmetric and Cholesky-factorable (spec §8 item 10)."""
    _, _, stages, posts = ge_steps
    assert len(posts) == 100 and len(stages) == 4 * 100 - 2
    for k, what, C in stages:
        assert_spd_symmetric(C, f"step {k} {what}")


def test_run_joint_equals_the_step_by_step_ge(runs, ge_steps):
    """run_joint('ge') is the cycle predict, truncate, update, truncate of spec §2-§4 with the model file's options:
    its per-step phi moments and state means equal the step-by-step run (1e-12; the same arithmetic)."""
    est = runs["ge"]
    _, _, _, posts = ge_steps
    M = est.phi_mean.shape[1]
    assert est.complete and est.meta["estimated"] == ["E", "nu"]
    for k in (0, 1, 2, 50, 99):
        assert rel(est.phi_mean[k], posts[k].mean[:M]) <= 1e-12, k
        assert rel(est.phi_cov[k], posts[k].cov[:M, :M]) <= 1e-12, k
        assert rel(est.state_mean[k], posts[k].mean[M:]) <= 1e-12, k


@pytest.mark.parametrize("name", ESTIMATORS)
def test_convergence_from_a_shifted_start(paper_model, runs, name):
    """3.3 s of the paper patch, E started 1.5x too high and nu at 0.40 (truth 0.45): every estimator ends with E
    within 2 % and nu within 0.01 of the truth, and |E - truth| <= 3 theta_std (its own uncertainty).
    Observed (seed 11): E within 0.04 %, nu within 0.0043 (about 1 theta_std), |E error| <= 0.13 theta_std."""
    est = runs[name]
    truth = paper_model.config.theta
    assert est.complete
    th, sd = est.theta[-1], est.theta_std[-1]
    assert abs(th[3] / truth[3] - 1) < 0.02, th
    assert abs(th[4] - truth[4]) < 0.01, th
    assert abs(th[3] - truth[3]) <= 3 * sd[3], (th, sd)
    # the fixed parameters stay fixed, with zero reported std
    np.testing.assert_allclose(th[:3], truth[:3], rtol=1e-14, atol=0)  # via phi and back: 1 ulp
    np.testing.assert_array_equal(sd[:3], 0.0)
    # it did move: the start was 50 % off
    assert abs(est.theta[0, 3] / truth[3] - 1) > abs(th[3] / truth[3] - 1)
    for C in est.phi_cov:
        assert_spd_symmetric(C, name)


# ---------------------------------------------------------------------------------------------------------------
# truncation

def test_truncation_is_active_near_a_bound(paper_model, short_meas):
    """nu0 = 0.497 (upper bound 0.499: 2.2 prior sigma in s): the GE truncates (events > 0) and every phi_mean lies
    inside the phi box."""
    th0 = theta_start(paper_model)
    th0[4] = 0.497
    est = run_joint(paper_model, short_meas, "ge", theta0=th0)
    lo, up = paper_model.config.parameter_space().bounds_phi
    assert est.truncation_events.sum() > 0 and est.truncation_events[0] > 0
    assert ((est.phi_mean >= lo) & (est.phi_mean <= up)).all()


@pytest.fixture(scope="module")
def narrow_model(paper_dict):
    """The paper patch with a nu box [0.30, 0.42] that excludes the truth of the data (0.45)."""
    d = copy.deepcopy(paper_dict)
    d["estimation"]["bounds"]["nu"] = [0.30, 0.42]
    d["parameters"]["nu"] = 0.41  # the model file's value must lie in its box; short_meas comes from nu = 0.45
    return build_model(model_config_from_dict(d))


def test_truncation_keeps_the_estimate_in_the_box(narrow_model, paper_model, short_meas):
    """Start at nu = 0.40 in a box [0.30, 0.42] while the data come from nu = 0.45, so the data push nu across the
    upper bound. The EKF (no node clipping) without truncation leaves the box (12 of 16 steps observed): the box
    check below can fail. With sequential truncation the GE and the EKF count events and every phi_mean stays
    inside; for the GE truncation changes the estimate (nodes alone are clipped, spec §1.4, which keeps it inside
    but elsewhere)."""
    th0 = theta_start(narrow_model)
    assert th0[4] == NU0 and paper_model.config.theta[4] == 0.45
    lo, up = narrow_model.config.parameter_space().bounds_phi
    base = JointOptions.from_config(narrow_model.config)
    assert base.truncation == "sequential" and base.baseline_truncation == "none"

    def inside(est):
        return bool(((est.phi_mean >= lo) & (est.phi_mean <= up)).all())

    ekf_free = run_joint(narrow_model, short_meas, "ekf", theta0=th0, options=base)
    assert ekf_free.truncation_events.sum() == 0 and not inside(ekf_free)
    ekf_cut = run_joint(narrow_model, short_meas, "ekf", theta0=th0,
                        options=replace(base, baseline_truncation="sequential"))
    assert ekf_cut.truncation_events.sum() > 0 and inside(ekf_cut)

    ge_cut = run_joint(narrow_model, short_meas, "ge", theta0=th0, options=base)
    assert (ge_cut.truncation_events[1:] > 0).all() and inside(ge_cut)
    assert (ge_cut.theta[:, 4] <= 0.42).all()
    ge_free = run_joint(narrow_model, short_meas, "ge", theta0=th0, options=replace(base, truncation="none"))
    assert ge_free.truncation_events.sum() == 0
    assert abs(ge_free.phi_mean[-1, 1] - ge_cut.phi_mean[-1, 1]) > 0.01  # observed 0.07 in s


# ---------------------------------------------------------------------------------------------------------------
# bad input and divergence

def test_theta0_outside_the_bounds_names_the_parameter(paper_model, short_meas):
    for i, name, value in ((4, "nu", 0.4995), (3, "E", 500.0), (0, "rho", 3000.0)):
        th0 = np.array(paper_model.config.theta, float)
        th0[i] = value
        for est in ESTIMATORS:
            with pytest.raises(ValueError, match=rf"\b{name}\b.*outside its bounds"):
                run_joint(paper_model, short_meas, est, theta0=th0)


@pytest.mark.parametrize("nodes", [4, 1, 0, 2, 5.5])
def test_joint_options_reject_bad_node_counts(nodes):
    with pytest.raises(ValueError, match="nodes"):
        JointOptions(nodes=nodes)


def test_unknown_estimator_is_rejected(paper_model, short_meas, space):
    with pytest.raises(ValueError, match="estimator"):
        run_joint(paper_model, short_meas, "pf")
    with pytest.raises(ValueError, match="estimator"):
        JointFilter("kf", paper_model, space, 1 / 30, np.zeros((2, 2)), paper_model.process_noise())


def absurd(meas, shift=1e10, start=2):
    """Every observed position from frame ``start`` on moved by ``shift`` metres (finite, so the measurement set
    is valid)."""
    pos = meas.positions.copy()
    pos[start:] += shift
    return MeasurementSet(meas.times, meas.point_ids, pos, meas.covariances, meas.reference,
                          meas.inputs, meas.input_names, meas.input_units)


@pytest.fixture(scope="module")
def diverged_ge(paper_model, short_meas):
    with pytest.raises(EstimationDiverged) as info:
        run_joint(paper_model, absurd(short_meas), "ge")
    return info.value


def test_ge_diverging_run_raises_with_partial_result(diverged_ge, short_meas):
    """Positions 1e10 m away from the model: the first update drives the parameter block into a box mass of
    ~0 and the next GE prediction finds C_nn indefinite. The run stops with EstimationDiverged whose partial
    result holds exactly the completed steps (finite) and NaN after."""
    exc = diverged_ge
    part = exc.partial
    K = short_meas.n_frames
    assert part is not None and not part.complete
    assert part.completed_steps == exc.step < K
    done = part.completed_steps
    assert done >= 1
    assert np.isfinite(part.theta[:done]).all() and np.isfinite(part.phi_mean[:done]).all()
    assert np.isnan(part.theta[done:]).all() and np.isnan(part.state_mean[done:]).all()
    assert np.isnan(part.phi_cov[done:]).all()


def test_ge_stops_at_the_first_absurd_frame(diverged_ge):
    """The runaway check stops the run at the update of frame 2 (the first shifted frame), before the absurd
    state reaches the next prediction: the partial result holds frames 0 and 1."""
    assert diverged_ge.step == 2 and diverged_ge.partial.completed_steps == 2


def test_truncated_mean_far_outside_the_box_lands_on_the_bound():
    """Regression (found with a diverging run): a mean 4.5e13 below the box used to come back as mu + s m*,
    which cancels to 6.8984 < log(1000) = 6.9078. The constrained coordinate is now computed from its bound."""
    res = truncate_box(np.array([-4.4785217556578484e13]), np.array([[0.05822121785524814]]),
                       [6.907755278982137], [18.420680743952367], 1)
    assert 6.907755278982137 <= res.mean[0] <= 6.907755278982137 + 1e-9


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # production behaviour: overflow warnings are not errors
@pytest.mark.parametrize("name", ["ukf", "ekf"])
def test_baseline_diverging_run_raises_estimation_diverged(paper_model, short_meas, name):
    """The same absurd input stops the UKF and EKF with EstimationDiverged too (it used to escape as a
    LinAlgError from the UKF and as ValueError('nu: must lie in (0, 0.5)') from the EKF)."""
    with pytest.raises(EstimationDiverged) as info:
        run_joint(paper_model, absurd(short_meas), name)
    assert info.value.step == 2 and info.value.partial.completed_steps == 2


# ---------------------------------------------------------------------------------------------------------------
# estimate files

def _assert_same_estimates(a, b):
    assert a.estimator == b.estimator and a.completed_steps == b.completed_steps
    for key in ("times", "point_ids", "state_mean", "state_var", "theta", "theta_std", "predictions",
                "innovations", "nis", "nis_dof", "truncation_events", "step_time"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)


def test_estimate_file_round_trips_phi_moments(tmp_path, runs, diverged_ge, paper_model, short_meas):
    est = runs["ge"]
    write_estimates(tmp_path / "ge.npz", est)
    back = read_estimates(tmp_path / "ge.npz")
    _assert_same_estimates(back, est)
    np.testing.assert_array_equal(back.phi_mean, est.phi_mean)
    np.testing.assert_array_equal(back.phi_cov, est.phi_cov)
    assert back.phi_mean.shape == (100, 2) and back.phi_cov.shape == (100, 2, 2)
    assert back.meta["estimated"] == ["E", "nu"]
    # a partial (diverged) run keeps its NaN tail
    part = diverged_ge.partial
    write_estimates(tmp_path / "partial.npz", part)
    back = read_estimates(tmp_path / "partial.npz")
    _assert_same_estimates(back, part)
    np.testing.assert_array_equal(back.phi_mean, part.phi_mean)
    np.testing.assert_array_equal(back.phi_cov, part.phi_cov)
    assert not back.complete
    # the KF has no parameter block: the optional arrays stay absent
    kf = run_kalman(paper_model, short_meas)
    write_estimates(tmp_path / "kf.npz", kf)
    back = read_estimates(tmp_path / "kf.npz")
    _assert_same_estimates(back, kf)
    assert back.phi_mean is None and back.phi_cov is None
