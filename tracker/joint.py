"""Simultaneous state and parameter estimation over a measurement set: the GE and the joint UKF/EKF baselines.

The joint state is ``z = [x_n; x_l]``: ``x_n`` the estimated parameters in the estimator's coordinates
``phi`` (:mod:`tracker.params`; log for rho, alpha1, alpha2, E and ``s = log(lambda/mu)`` for nu), ``x_l`` the
kinematic state of the patch model. Per frame k (docs/spec/estimator.md; the same cycle as the KF of
:mod:`tracker.tracking`):

1. ``k > 0``: predict with the estimator's rule (GE §2, UKF or EKF §5), first-order-hold input ``u_{k-1}, u_k``;
   then truncate the parameter block to the box (§3; GE by default, optional for the baselines);
2. record the one-step prediction of every point;
3. update with the points seen in frame k (§4, shared with the KF), NaN rows dropped; truncate again; record
   the filtered (posterior) position of every point from the kinematic block of the truncated posterior.

A non-finite state stops the run with :class:`tracker.tracking.EstimationDiverged`, whose ``partial`` holds the
steps completed (``completed_steps < K``), so nothing downstream can mistake it for a complete run.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import logging
import time
from typing import Callable

import numpy as np
import scipy.linalg as sla

from .ge import conditional_split, ge_predict, ge_predict_family
from .kalman import GaussianState, cholesky_psd, symmetrise, update
from .measurements import EstimateSet, MeasurementSet
from .model import PatchModel
from .params import NAMES, ParameterSpace
from .sampling import sample
from .tracking import EstimationDiverged, ObservedPoints, _block_diag_R, run_setup
from .transition import TransitionFamily
from .truncation import SKIP_SIGMA, truncate_box

__all__ = ["JointOptions", "JointPrior", "joint_prior", "run_joint", "ESTIMATORS", "JointFilter"]

log = logging.getLogger(__name__)

ESTIMATORS = ("ge", "ukf", "ekf")


@dataclass(frozen=True)
class JointOptions:
    """Estimator settings (defaults from the model file's ``estimation`` section).

    nodes, variant, sqrt : the GE sampler (spec §1): D per axis (odd >= 3), 'A' or 'B', square root of C_nn.
        ``sqrt='cholesky'`` orders nu first, so only the D-1 nodes of the first axis move nu and the others share
        one eigen-decomposition (spec §7.4, a documented variant); 'correlation' and 'eigen' are rotation-invariant
        choices that move nu at every node (one eigen-decomposition each).
    truncation : 'sequential' | 'tallis' | 'none' for the GE; baselines use ``baseline_truncation``.
    alpha, beta, kappa : scaled unscented transform of the UKF.
    fd_step : central-difference step in phi of the EKF Jacobian.
    joseph : Joseph-form update.
    """

    nodes: int = 5
    variant: str = "A"
    sqrt: str = "cholesky"
    truncation: str = "sequential"
    baseline_truncation: str = "none"
    alpha: float = 0.1
    beta: float = 2.0
    kappa: float = 0.0
    fd_step: float = 1e-4
    joseph: bool = False
    dense: bool = False  # build dense A(theta) with model.system per sample / sigma point (reference path; slow)

    @classmethod
    def from_config(cls, cfg, **overrides) -> "JointOptions":
        ge, ukf = cfg.estimation.ge, cfg.estimation.ukf
        base = cls(nodes=ge["nodes"], variant=ge["variant"], sqrt=ge["sqrt"], truncation=ge["truncation"],
                   alpha=ukf["alpha"], beta=ukf["beta"], kappa=ukf["kappa"])
        return replace(base, **{k: v for k, v in overrides.items() if v is not None})

    def __post_init__(self):
        if int(self.nodes) != self.nodes or self.nodes < 3 or self.nodes % 2 == 0:
            raise ValueError(f"nodes: D must be an odd integer >= 3 (shared centre node), got {self.nodes}")
        if self.variant not in ("A", "B"):
            raise ValueError(f"variant: 'A' or 'B' expected, got {self.variant!r}")
        if self.sqrt not in ("cholesky", "correlation", "eigen"):
            raise ValueError(f"sqrt: 'cholesky', 'correlation' or 'eigen' expected, got {self.sqrt!r}")
        for name in ("truncation", "baseline_truncation"):
            if getattr(self, name) not in ("sequential", "tallis", "none"):
                raise ValueError(f"{name}: 'sequential', 'tallis' or 'none' expected, got {getattr(self, name)!r}")
        if not 0 < self.alpha <= 1:
            raise ValueError(f"alpha: in (0, 1] expected, got {self.alpha}")
        if not self.fd_step > 0:
            raise ValueError(f"fd_step: positive expected, got {self.fd_step}")


@dataclass(frozen=True)
class JointPrior:
    """Initial joint density and the parameter space it lives in."""

    state: GaussianState
    space: ParameterSpace
    Q_n: np.ndarray  # (M, M) random walk per frame, phi units
    Q_l: np.ndarray  # (n_l, n_l)


def joint_prior(model: PatchModel, u0, theta0=None, prior_std=None) -> JointPrior:
    """Prior of the joint state: ``x_n ~ N(phi(theta0), diag(prior_std^2))`` and the kinematic state at the
    equilibrium of the (uncertain) parameters, ``x_l = x_static(phi) + e``, ``e ~ N(0, C_l0)``, linearised at
    ``phi0``: mean ``x_static(phi0)``, ``C_ln = J C_nn``, ``C_ll = C_l0 + J C_nn J^T`` with
    ``J = d x_static / d phi`` (central differences).

    Parameters
    ----------
    theta0 : (5,), optional
        Initial parameter estimate in SI (default: the model file's theta). Must lie inside the box.
    prior_std : (M,), optional
        Prior standard deviation of the estimated parameters in phi units (default: the model file's).
    """
    cfg = model.config
    space = cfg.parameter_space()
    theta0 = cfg.theta if theta0 is None else np.asarray(theta0, float).reshape(5)
    if not np.isfinite(theta0).all():
        raise ValueError(f"prior: theta0 must be finite, got {theta0}")
    for i, n in enumerate(NAMES):
        if not space.lower[i] <= theta0[i] <= space.upper[i]:
            raise ValueError(f"prior: {n} = {theta0[i]:.6g} lies outside its bounds "
                             f"[{space.lower[i]:.6g}, {space.upper[i]:.6g}] (estimation.bounds.{n})")
    M = space.dim
    if M == 0:
        raise ValueError("estimation.estimate: the joint estimators need at least one estimated parameter")
    sd = cfg.prior_std_phi() if prior_std is None else np.asarray(prior_std, float).reshape(M)
    if not (np.isfinite(sd).all() and (sd > 0).all()):
        raise ValueError(f"prior: positive finite standard deviations expected, got {sd}")
    space = ParameterSpace(theta0, space.estimated, space.lower, space.upper, space.eps)
    x_n = space.x_from_theta(theta0)
    x_l = model.static_state(theta0, u0)
    # The initial kinematic state is the equilibrium of the *true* parameters: linearise x_static(phi) around
    # phi0 (central differences) so that the prior carries the cross-covariance C_ln = J C_nn.
    h = 1e-4
    J = np.stack([(model.static_state(space.theta_from_x(x_n + h * e), u0)
                   - model.static_state(space.theta_from_x(x_n - h * e), u0)) / (2 * h) for e in np.eye(M)],
                 axis=1)
    C_nn = np.diag(sd**2)
    n_l = x_l.size
    C = np.zeros((M + n_l, M + n_l))
    C[:M, :M] = C_nn
    C[M:, :M] = J @ C_nn
    C[:M, M:] = C[M:, :M].T
    C[M:, M:] = model.initial_covariance() + J @ C_nn @ J.T
    Q_n = np.diag(cfg.random_walk_std_phi() ** 2)
    Q_l = model.process_noise(theta0)
    return JointPrior(GaussianState(np.concatenate([x_n, x_l]), C), space, Q_n, Q_l)


class JointFilter:
    """One joint estimator bound to a model, a parameter space and a frame interval.

    ``predict(state, u0, u1)`` returns ``(state, info)``; the update is :func:`tracker.kalman.update` on
    ``H_z = [0, H]``. ``info`` counts clipped sample coordinates and eigen-decompositions.
    """

    def __init__(self, name: str, model: PatchModel, space: ParameterSpace, dt: float, Q_n, Q_l,
                 options: JointOptions = JointOptions()):
        if name not in ESTIMATORS:
            raise ValueError(f"estimator: one of {ESTIMATORS} expected, got {name!r}")
        self.name = name
        self.model = model
        self.space = space
        self.M = space.dim
        self.dt = float(dt)
        self.Q_n = np.asarray(Q_n, float)
        self.Q_l = np.asarray(Q_l, float)
        self.options = options
        self.modal = model.config.method == "modal" and not options.dense
        self.family = TransitionFamily(model, dt) if self.modal else None
        lo, up = space.bounds_phi
        self.lower, self.upper = lo, up
        # nu first for the Cholesky square root (spec §7.4): only the first axis then moves nu
        est = list(space.estimated)
        self.perm = np.array([est.index("nu")] + [i for i, n in enumerate(est) if n != "nu"]) if "nu" in est \
            else np.arange(self.M)
        self.inv_perm = np.argsort(self.perm)

    # -- transitions -------------------------------------------------------------------------------
    def propagate(self, thetas, X, u0, u1) -> np.ndarray:
        """``A(theta_i) x_i + B0 u0 + B1 u1`` for rows of thetas (L, 5) and X (L, n_l)."""
        if self.modal:
            return self.family.propagate(thetas, X, u0, u1)
        out = np.empty_like(X)
        for i, (th, x) in enumerate(zip(thetas, X)):
            s = self.model.system(th, self.dt)
            out[i] = s.A @ x + s.B0 @ u0 + s.B1 @ u1
        return out

    def sandwich(self, theta, C) -> np.ndarray:
        """``A(theta) C A(theta)^T``."""
        if self.modal:
            return self.family.weighted_sandwich(np.asarray(theta)[None], np.ones(1), C)
        A = self.model.system(theta, self.dt).A
        return A @ C @ A.T

    def predict(self, state: GaussianState, u0, u1):
        if self.name == "ge":
            return self._predict_ge(state, u0, u1)
        if self.name == "ukf":
            return self._predict_ukf(state, u0, u1)
        return self._predict_ekf(state, u0, u1)

    # -- GE (spec §2) --------------------------------------------------------------------------------
    def _predict_ge(self, state, u0, u1):
        o = self.options
        M, p = self.M, self.perm
        mu_n, C_nn = state.mean[:M], symmetrise(state.cov[:M, :M])
        ss = sample(mu_n[p], C_nn[np.ix_(p, p)], D=o.nodes, variant=o.variant, sqrt=o.sqrt,
                    lower=self.lower[p], upper=self.upper[p])
        nodes = ss.nodes[:, self.inv_perm]
        thetas = self.space.theta_from_x(nodes)
        split = conditional_split(state, M, factor=not self.modal)
        if self.modal:
            pred = ge_predict_family(state, M, nodes, ss.weights, thetas, self.family, u0, u1, self.Q_n, self.Q_l,
                                     split=split)
        else:
            def transition(_nodes):
                A = np.empty((len(thetas), self.Q_l.shape[0], self.Q_l.shape[0]))
                b = np.empty((len(thetas), self.Q_l.shape[0]))
                for i, th in enumerate(thetas):
                    s = self.model.system(th, self.dt)
                    A[i] = s.A
                    b[i] = s.B0 @ u0 + s.B1 @ u1
                return A, b
            pred = ge_predict(state, M, nodes, ss.weights, transition, self.Q_n, self.Q_l, split=split)
        return pred, {"clipped": ss.clipped, "samples": ss.L, "jitter": split.jitter_events}

    # -- joint UKF (spec §5 b) -------------------------------------------------------------------------
    def _predict_ukf(self, state, u0, u1):
        o = self.options
        M = self.M
        n = state.mean.size
        lam = o.alpha**2 * (n + o.kappa) - n
        c = n + lam
        S, jitter = cholesky_psd(symmetrise(state.cov))
        offs = np.sqrt(c) * S.T  # rows: columns of the lower factor
        Z = np.concatenate([state.mean[None], state.mean + offs, state.mean - offs])
        wm = np.full(2 * n + 1, 1.0 / (2 * c))
        wc = wm.copy()
        wm[0] = lam / c
        wc[0] = lam / c + (1 - o.alpha**2 + o.beta)
        # clip the parameter part into the box before evaluating A (as for the GE nodes, spec §1.4)
        Zn = Z[:, :M]
        lo, up = self.lower, self.upper
        width = up - lo
        eps = np.where(np.isfinite(width), 1e-6 * width, 0.0)
        Zc = np.clip(Zn, lo + eps, up - eps)
        clipped = int(np.count_nonzero(Zc != Zn))
        thetas = self.space.theta_from_x(Zc)
        Y = np.empty_like(Z)
        Y[:, :M] = Zc
        Y[:, M:] = self.propagate(thetas, Z[:, M:], u0, u1)
        mean = wm @ Y
        d = Y - mean
        cov = (d * wc[:, None]).T @ d
        cov[:M, :M] += self.Q_n
        cov[M:, M:] += self.Q_l
        return GaussianState(mean, symmetrise(cov)), {"clipped": clipped, "samples": 2 * n + 1, "jitter": jitter}

    # -- joint EKF (spec §5 c) -------------------------------------------------------------------------
    def _predict_ekf(self, state, u0, u1):
        M = self.M
        mu, C = state.mean, symmetrise(state.cov)
        mu_n, mu_l = mu[:M], mu[M:]
        h = self.options.fd_step
        pts = np.concatenate([mu_n[None], mu_n + h * np.eye(M), mu_n - h * np.eye(M)])
        thetas = self.space.theta_from_x(pts)
        F = self.propagate(thetas, np.broadcast_to(mu_l, (2 * M + 1, mu_l.size)).copy(), u0, u1)
        J = ((F[1:M + 1] - F[M + 1:]) / (2 * h)).T  # (n_l, M)
        th0 = thetas[0]
        C_nn, C_nl, C_ll = C[:M, :M], C[:M, M:], C[M:, M:]
        zero = np.zeros_like(u0)
        AC_ln = self.propagate(np.broadcast_to(th0, (M, 5)), C_nl, zero, zero).T  # A C_ln (n_l, M)
        cross = AC_ln @ J.T
        out = np.empty_like(C)
        out[:M, :M] = C_nn + self.Q_n
        out[M:, :M] = J @ C_nn + AC_ln
        out[:M, M:] = out[M:, :M].T
        out[M:, M:] = self.sandwich(th0, C_ll) + cross + cross.T + J @ C_nn @ J.T + self.Q_l
        return GaussianState(np.concatenate([mu_n, F[0]]), symmetrise(out)), {"clipped": 0, "samples": 2 * M + 1,
                                                                              "jitter": 0}

    # -- truncation (spec §3) ---------------------------------------------------------------------------
    def truncate(self, state: GaussianState):
        method = self.options.truncation if self.name == "ge" else self.options.baseline_truncation
        if method == "none":
            return state, 0, 0
        # every constraint inactive (the skip test of truncate_box, which then returns its input): skip the call
        sd = np.sqrt(np.diag(state.cov)[:self.M])
        mu = state.mean[:self.M]
        if ((self.lower - mu < -SKIP_SIGMA * sd) & (self.upper - mu > SKIP_SIGMA * sd)).all():
            return state, 0, 0
        res = truncate_box(state.mean, symmetrise(state.cov), self.lower, self.upper, self.M, method=method)
        if res.events == 0:
            return state, 0, 0
        return GaussianState(res.mean, res.cov), res.events, res.low_mass


class _Runaway(FloatingPointError):
    pass


# A state beyond these is a diverged filter, not an estimate: stop before it reaches the model (e.g. a Poisson
# ratio that rounds to exactly 0 or 0.5, or displacements of kilometres).
RUNAWAY_PHI = 1e3   # |phi| (log-parameters: a factor e^1000)
RUNAWAY_STATE = 1e3  # |x_l| (m, m/s)


def _check_runaway(state: GaussianState, M: int, where: str):
    mu, C = state.mean, state.cov
    if not (np.isfinite(mu).all() and np.isfinite(C).all()):
        raise _Runaway(f"non-finite {where}")
    if np.abs(mu[:M]).max(initial=0) > RUNAWAY_PHI or np.abs(mu[M:]).max(initial=0) > RUNAWAY_STATE:
        raise _Runaway(f"runaway {where}: |phi| up to {np.abs(mu[:M]).max(initial=0):.3g}, "
                       f"|x_l| up to {np.abs(mu[M:]).max(initial=0):.3g}")


def _theta_and_std(space: ParameterSpace, mean_n, cov_nn):
    """Physical theta (5,) at the phi mean and its delta-method std (0 for fixed parameters)."""
    theta = space.theta_from_x(mean_n)
    jac = space.dtheta_dphi(space.to_phi(theta))
    std = np.zeros(5)
    std[space.index] = jac[space.index] * np.sqrt(np.clip(np.diag(cov_nn), 0, None))
    return theta, std


def run_joint(model: PatchModel, meas: MeasurementSet, estimator: str = "ge", *, theta0=None, prior_std=None,
              options: JointOptions | None = None, points: ObservedPoints | None = None,
              progress: Callable[[int, int], None] | None = None) -> EstimateSet:
    """Run the GE, the joint UKF or the joint EKF over a measurement set.

    Parameters
    ----------
    estimator : {'ge', 'ukf', 'ekf'}
    theta0 : (5,), optional
        Initial parameter estimate (SI); default the model file's theta.
    prior_std : (M,), optional
        Prior std of the estimated parameters in phi units; default the model file's.
    options : JointOptions, optional
        Default: :meth:`JointOptions.from_config` of the model file.
    progress : callable(done, total), optional

    Returns
    -------
    EstimateSet
        With ``theta``/``theta_std`` per step (physical units, delta method from phi), ``phi_mean``/``phi_cov``
        of the parameter block, NIS, one-step predictions, filtered positions and truncation events.

    Raises
    ------
    EstimationDiverged
        When the state becomes non-finite; ``partial`` holds the steps done.
    ValueError
        For a prior outside the box, bad options or a measurement set that does not fit the model.
    """
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator: one of {ESTIMATORS} expected, got {estimator!r}")
    options = options or JointOptions.from_config(model.config)
    pts, obs, u, trans, K, dt = run_setup(model, meas, points)
    prior = joint_prior(model, u[0], theta0, prior_std)
    space = prior.space
    M = space.dim
    filt = JointFilter(estimator, model, space, dt, prior.Q_n, prior.Q_l, options)
    n_l = model.state_dim
    Hz = np.hstack([np.zeros((obs.H.shape[0], M)), obs.H])
    y_all = meas.positions[:, pts.keep, :].reshape(K, -1)
    cov_all = meas.covariances[:, pts.keep]
    P_all = meas.n_points

    state_mean = np.full((K, n_l), np.nan)
    state_var = np.full((K, n_l), np.nan)
    theta = np.full((K, 5), np.nan)
    theta_std = np.full((K, 5), np.nan)
    phi_mean = np.full((K, M), np.nan)
    phi_cov = np.full((K, M, M), np.nan)
    predictions = np.full((K, P_all, 3), np.nan)
    filtered = np.full((K, P_all, 3), np.nan)
    innovations = np.full((K, P_all, 3), np.nan)
    nis = np.full(K, np.nan)
    dof = np.zeros(K, np.int64)
    trunc = np.zeros(K, np.int64)
    step_time = np.zeros(K)
    counters = {"clipped": 0, "low_mass": 0, "jitter": 0, "eig": 0}

    def result(done):
        return EstimateSet(
            estimator, meas.times, meas.point_ids, state_mean, state_var, theta, theta_std, predictions,
            innovations, nis, dof, trunc, step_time, done,
            meta={"dropped_points": pts.dropped.tolist(), "joseph": options.joseph, "dt": dt,
                  "estimated": list(space.estimated), "theta0": space.theta.tolist(),
                  "prior_std_phi": np.sqrt(np.diag(prior.state.cov[:M, :M])).tolist(),
                  "options": {k: getattr(options, k) for k in options.__dataclass_fields__},
                  "counters": dict(counters, eig=filt.family.eig_count if filt.family else 0),
                  "modal_path": filt.modal},
            phi_mean=phi_mean, phi_cov=phi_cov, filtered=filtered,
        )

    state = prior.state
    for k in range(K):
        t0 = time.perf_counter()
        events = 0
        try:
            if k > 0:
                state, info = filt.predict(state, u[k - 1], u[k])
                counters["clipped"] += info["clipped"]
                counters["jitter"] += info["jitter"]
                _check_runaway(state, M, "prediction")
                state, ev, low = filt.truncate(state)
                events += ev
                counters["low_mass"] += low
            offset = (obs.reference + trans[k]).reshape(-1)
            pred_y = offset + obs.H @ state.mean[M:]
            res = update(state, y_all[k], Hz, _block_diag_R(cov_all[k]), offset, joseph=options.joseph)
            state = res.state
            counters["jitter"] += res.jitter_events
            _check_runaway(state, M, "update")
            state, ev, low = filt.truncate(state)
            events += ev
            counters["low_mass"] += low
        except (_Runaway, FloatingPointError, np.linalg.LinAlgError, sla.LinAlgError) as exc:
            log.error("%s: the estimate diverged at step %d (%s)", estimator, k, exc)
            raise EstimationDiverged(k, result(k)) from None
        step_time[k] = time.perf_counter() - t0
        predictions[k, pts.keep] = pred_y.reshape(-1, 3)
        filtered[k, pts.keep] = (offset + obs.H @ state.mean[M:]).reshape(-1, 3)
        innovations[k, pts.keep] = (y_all[k] - pred_y).reshape(-1, 3)
        state_mean[k] = state.mean[M:]
        state_var[k] = np.diag(state.cov)[M:]
        phi_mean[k] = state.mean[:M]
        phi_cov[k] = state.cov[:M, :M]
        theta[k], theta_std[k] = _theta_and_std(space, state.mean[:M], state.cov[:M, :M])
        nis[k] = res.nis
        dof[k] = res.dof
        trunc[k] = events
        if progress is not None:
            progress(k + 1, K)
    return result(K)
