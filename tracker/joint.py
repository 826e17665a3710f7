"""Simultaneous state and parameter estimation over a measurement set: the GE and the joint UKF/EKF baselines.

The joint state is ``z = [x_n; x_l]``: ``x_n`` the estimated parameters in the estimator's coordinates
``phi`` (:mod:`tracker.params`; log for rho, alpha1, alpha2, E and ``s = log(lambda/mu)`` for nu), ``x_l`` the
kinematic state of the patch model (and the static reference states of :mod:`tracker.reference` when they are
estimated). The three are variants of one predict/update shape (:mod:`tracker.estimators`): they override the
prediction only, and share the frame loop :func:`tracker.estimators.run_filter` with the KF. Per frame k
(docs/spec/estimator.md):

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
from typing import Callable

import numpy as np

from .estimators import JOINT, Estimator, register, run_filter, variant
from .ge import conditional_split, ge_predict, ge_predict_family
from .kalman import GaussianState, cholesky_psd, symmetrise
from .measurements import EstimateSet, MeasurementSet
from .model import PatchModel
from .params import NAMES, ParameterSpace
from .sampling import sample
from .tracking import ObservedPoints, check_references, run_setup
from .transition import TransitionFamily
from .truncation import SKIP_SIGMA, truncate_box

__all__ = ["JointOptions", "JointPrior", "joint_prior", "run_joint", "ESTIMATORS", "JointFilter", "GEFilter",
           "UKFFilter", "EKFFilter"]

log = logging.getLogger(__name__)

ESTIMATORS = JOINT


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


def joint_prior(model: PatchModel, u0, theta0=None, prior_std=None, block=None, dt=None,
                input_block=None, rate=None) -> JointPrior:
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
    block : tracker.reference.ReferenceBlock, optional
        Static reference states appended to the kinematic state (uncorrelated with the rest in the prior).
    input_block : tracker.unknown_input.InputBlock, optional
        The estimated input and rigid motion, appended after the reference states (uncorrelated in the prior);
        E is then held at ``theta0`` when other parameters are estimated (the input's scale and E are not
        separable, as in the fit; docs/model.md §17), else estimated as a constant (no random walk).
    dt : float, optional
        Frame interval of the sequence: the random walk ``Q_n`` is the model file's per frame of ``dt``
        (:meth:`tracker.config.ModelConfig.random_walk_std_phi`); None: per frame at the model file's rate.
    rate : tracker.unknown_input.RatePrior or sequence of them, optional
        With an ``input_block``: the log heart rate (and the log respiration rate, second, when the block has
        respiration oscillators) as more sampled parameters, after the M of the space (uncorrelated in the prior;
        their walk per frame of ``dt``).
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
    Q_walk = cfg.random_walk_std_phi(dt)
    estimated = space.estimated
    if input_block is not None and "E" in estimated and M > 1:
        # the input's scale and E are not separable without a recorded pressure (quasi-statically u / E): the fit
        # holds E, and so do the estimators (docs/model.md §17)
        keep = [i for i, n in enumerate(estimated) if n != "E"]
        sd, Q_walk, M, estimated = sd[keep], Q_walk[keep], M - 1, tuple(estimated[i] for i in keep)
    space = ParameterSpace(theta0, estimated, space.lower, space.upper, space.eps)
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
    Q_n = np.diag(Q_walk ** 2)
    Q_l = model.process_noise(theta0)
    if block is not None:
        x_l, C_l = block.prior(x_l, C[M:, M:])
        C_full = np.zeros((M + x_l.size, M + x_l.size))
        C_full[:M + n_l, :M + n_l] = C
        C_full[M:, M:] = C_l
        C = C_full
        Q_l = block.noise(Q_l)
    if input_block is not None:
        from .unknown_input import extend_noise, extend_prior

        # E alone estimated: a constant (its walk and the input amplitudes' would scale the same response)
        if "E" in space.estimated:
            i = space.estimated.index("E")
            Q_n = Q_n.copy()
            Q_n[i, :] = Q_n[:, i] = 0.0
        x_l, C_l = extend_prior(x_l, C[M:, M:], input_block)
        C_full = np.zeros((M + x_l.size, M + x_l.size))
        C_full[:C.shape[0], :C.shape[0]] = C
        C_full[M:, M:] = C_l
        C = C_full
        Q_l = extend_noise(Q_l, input_block)
    rates = sampled_rates(rate, input_block)
    if rates:
        if dt is None:
            raise ValueError("heart rate: a sampled rate needs the frame interval dt")
        n, r = C.shape[0], len(rates)
        C2 = np.zeros((n + r, n + r))
        C2[:M, :M], C2[:M, M + r:], C2[M + r:, :M], C2[M + r:, M + r:] = C[:M, :M], C[:M, M:], C[M:, :M], C[M:, M:]
        C2[M:M + r, M:M + r] = np.diag([p.phi_std ** 2 for p in rates])
        C = C2
        x_n = np.append(x_n, [p.phi_mean for p in rates])
        Q2 = np.zeros((M + r, M + r))
        Q2[:M, :M] = Q_n
        Q2[M:, M:] = np.diag([p.walk_per_frame(dt) ** 2 for p in rates])
        Q_n = Q2
    return JointPrior(GaussianState(np.concatenate([x_n, x_l]), C), space, Q_n, Q_l)


def sampled_rates(rate, input_block) -> tuple:
    """The sampled rates as a tuple (heart rate, then respiration rate), checked against the input block: none
    without ``rate``; the respiration rate only with the block's respiration oscillators. ValueError otherwise."""
    if rate is None:
        return ()
    from .unknown_input import RatePrior

    rates = (rate,) if isinstance(rate, RatePrior) else tuple(rate)
    if input_block is None:
        raise ValueError("heart rate: a sampled rate needs an estimated input (input_block)")
    want = 1 + (input_block.respiration_harmonics > 0)
    if not 1 <= len(rates) <= want or rates[0].name != "heart rate" \
            or any(p.name != "respiration rate" for p in rates[1:]):
        raise ValueError(f"sampled rates: the heart rate{' (and the respiration rate)' if want > 1 else ''} "
                         f"expected, got {[p.name for p in rates]}")
    return rates


class JointFilter(Estimator):
    """The joint estimators' shared part (:class:`tracker.estimators.Estimator` hooks): a model, a parameter space
    and a frame interval; the transition of the linear block for many theta; the box truncation. The variants
    (:class:`GEFilter`, :class:`UKFFilter`, :class:`EKFFilter`) override :meth:`_predict` only.

    ``predict(state, u0, u1, Q_n=None)`` returns ``(state, info)``; ``info`` counts clipped sample coordinates,
    samples and jitter events. ``Q_l`` may be larger than the model's kinematic state: the extra states are static
    (the reference block of :mod:`tracker.reference`, transition identity).
    """

    def __new__(cls, name=None, *args, **kwargs):
        # JointFilter('ge', ...) builds the registered variant (the name selects the class, nothing else does)
        if cls is JointFilter:
            if name not in JOINT:
                raise ValueError(f"estimator: one of {JOINT} expected, got {name!r}")
            cls = variant(name)
        return super().__new__(cls)

    def __init__(self, name: str, model: PatchModel, space: ParameterSpace, dt: float, Q_n, Q_l,
                 options: JointOptions = JointOptions(), input_block=None, rate=None):
        if name != self.name:
            raise ValueError(f"estimator: {self.name!r} expected by {type(self).__name__}, got {name!r}")
        self.model = model
        self.space = space
        self._M_theta = space.dim                              # the physical parameters' phi ...
        if rate is not None and (input_block is None or self.name != "ge"):
            raise ValueError("heart rate: sampled by the GE with an estimated input only")
        self.rates = sampled_rates(rate, input_block)          # ... then log f (and log f_r) when sampled
        self.M = space.dim + len(self.rates)
        self.dt = float(dt)
        self.Q_n = np.asarray(Q_n, float)
        self.Q_l = np.asarray(Q_l, float)
        self.n_x = model.state_dim
        self.static = max(self.Q_l.shape[0] - self.n_x, 0)    # static states after the kinematic ones
        self.input_block = input_block                         # the last of them: tracker.unknown_input
        self.options = options
        # the input block couples into the kinematic state per sample: the dense path
        self.modal = model.config.method == "modal" and not options.dense and input_block is None
        self.family = TransitionFamily(model, dt) if self.modal else None
        lo, up = space.bounds_phi
        for p in self.rates:
            lo, up = np.append(lo, p.bounds_phi[0]), np.append(up, p.bounds_phi[1])
        self.lower, self.upper = lo, up
        # nu first for the Cholesky square root (spec §7.4): only the first axis then moves nu
        est = list(space.estimated) + ["heart_rate", "respiration_rate"][:len(self.rates)]
        self.perm = np.array([est.index("nu")] + [i for i, n in enumerate(est) if n != "nu"]) if "nu" in est \
            else np.arange(self.M)
        self.inv_perm = np.argsort(self.perm)

    @property
    def truncation_method(self) -> str:
        """The box truncation after predictions and updates: the baselines' (``baseline_truncation``)."""
        return self.options.baseline_truncation

    # -- truncation (spec §3) ---------------------------------------------------------------------------
    def truncate(self, state: GaussianState):
        method = self.truncation_method
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

    # -- transitions -------------------------------------------------------------------------------
    def propagate(self, thetas, X, u0, u1) -> np.ndarray:
        """``A(theta_i) x_i + B0 u0 + B1 u1`` for rows of thetas (L, 5) and X (L, n_l)."""
        if self.modal:
            return self.family.propagate(thetas, X, u0, u1)
        n = self.n_x
        out = np.array(X, float, copy=True)
        blk = self.input_block
        if blk is not None:
            P0, P1 = blk.input_maps()
            T = blk.transition()
            m = blk.size
        for i, (th, x) in enumerate(zip(thetas, X)):
            s = self.model.system(th, self.dt)
            if blk is None:
                out[i, :n] = s.A @ x[:n] + s.B0 @ u0 + s.B1 @ u1
            else:
                e = x[-m:]
                out[i, :n] = s.A @ x[:n] + s.B0 @ (u0 + P0 @ e) + s.B1 @ (u1 + P1 @ e)
                out[i, -m:] = T @ e
        return out

    def dense_transition(self, theta, u0, u1, rates=None):
        """``(A, b)`` of one theta as dense arrays, static states included (``blkdiag(A(theta), I)``); the input
        block at the rates given (a sample of the sampled heart rate and respiration rate, Hz)."""
        from .reference import augment_transition

        s = self.model.system(theta, self.dt)
        blk = self.input_block
        if blk is not None and rates is not None:
            blk = blk.with_frequency(*rates)
        if blk is None:
            return augment_transition(s.A, s.B0 @ u0 + s.B1 @ u1, self.static)
        from .unknown_input import extend_transition

        A, b = augment_transition(s.A, s.B0 @ u0 + s.B1 @ u1, self.static - blk.size)
        return extend_transition(A, s.B0, s.B1, blk), np.concatenate([b, np.zeros(blk.size)])

    def sandwich(self, theta, C) -> np.ndarray:
        """``A(theta) C A(theta)^T`` (static states included)."""
        if self.modal:
            return self.family.weighted_sandwich(np.asarray(theta)[None], np.ones(1), C)
        z = np.zeros(self.model.loads.shape[1])
        A, _ = self.dense_transition(theta, z, z)
        return A @ C @ A.T

    def predict(self, state: GaussianState, u0, u1, Q_n=None):
        """One-frame prediction of the joint state with the random walk ``Q_n`` (default: the filter's)."""
        return self._predict(state, u0, u1, self.Q_n if Q_n is None else np.asarray(Q_n, float))

    def _predict(self, state, u0, u1, Q_n):
        raise NotImplementedError

    def constrain(self, state):
        return self.truncate(state)

    def parameters(self, state):
        Mt = self.M_theta
        return _theta_and_std(self.space, state.mean[:Mt], state.cov[:Mt, :Mt])

    @property
    def M_theta(self) -> int:
        return self._M_theta

    @property
    def sampled_rate_names(self) -> tuple:
        return ("heart_rate", "respiration_rate")[:len(self.rates)]

    def rate(self, state, name: str):
        """``(mean, std)`` of a sampled rate (Hz; delta method from log f), None when not sampled."""
        names = self.sampled_rate_names
        if name not in names:
            return None
        i = self.M_theta + names.index(name)
        f = float(np.exp(state.mean[i]))
        return f, f * float(np.sqrt(max(state.cov[i, i], 0.0)))

    def meta(self):
        return {"counters": {"eig": self.family.eig_count if self.family else 0}, "modal_path": self.modal}


@register("ge")
class GEFilter(JointFilter):
    """The GE (spec §2): deterministic Dirac-mixture samples of the parameter block, exact conditional
    propagation of the linear block per sample."""

    @property
    def truncation_method(self) -> str:
        return self.options.truncation

    def _predict(self, state, u0, u1, Q_n):
        o = self.options
        M, p = self.M, self.perm
        mu_n, C_nn = state.mean[:M], symmetrise(state.cov[:M, :M])
        ss = sample(mu_n[p], C_nn[np.ix_(p, p)], D=o.nodes, variant=o.variant, sqrt=o.sqrt,
                    lower=self.lower[p], upper=self.upper[p])
        nodes = ss.nodes[:, self.inv_perm]
        thetas = self.space.theta_from_x(nodes[:, :self.M_theta])
        freqs = np.exp(nodes[:, self.M_theta:self.M]) if self.rates else [None] * len(thetas)
        split = conditional_split(state, M, factor=not self.modal)
        if self.modal:
            pred = ge_predict_family(state, M, nodes, ss.weights, thetas, self.family, u0, u1, Q_n, self.Q_l,
                                     split=split)
        else:
            def transition(_nodes):
                A = np.empty((len(thetas), self.Q_l.shape[0], self.Q_l.shape[0]))
                b = np.empty((len(thetas), self.Q_l.shape[0]))
                for i, th in enumerate(thetas):
                    A[i], b[i] = self.dense_transition(th, u0, u1, freqs[i])
                return A, b
            pred = ge_predict(state, M, nodes, ss.weights, transition, Q_n, self.Q_l, split=split)
        return pred, {"clipped": ss.clipped, "samples": ss.L, "jitter": split.jitter_events}



@register("ukf")
class UKFFilter(JointFilter):
    """Joint UKF (spec §5 b): the scaled unscented transform of the whole joint state."""

    def _predict(self, state, u0, u1, Q_n):
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
        cov[:M, :M] += Q_n
        cov[M:, M:] += self.Q_l
        return GaussianState(mean, symmetrise(cov)), {"clipped": clipped, "samples": 2 * n + 1, "jitter": jitter}



@register("ekf")
class EKFFilter(JointFilter):
    """Joint EKF (spec §5 c): linearised in phi by central differences."""

    def _predict(self, state, u0, u1, Q_n):
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
        out[:M, :M] = C_nn + Q_n
        out[M:, :M] = J @ C_nn + AC_ln
        out[:M, M:] = out[M:, :M].T
        out[M:, M:] = self.sandwich(th0, C_ll) + cross + cross.T + J @ C_nn @ J.T + self.Q_l
        return GaussianState(np.concatenate([mu_n, F[0]]), symmetrise(out)), {"clipped": 0, "samples": 2 * M + 1,
                                                                              "jitter": 0}


def _theta_and_std(space: ParameterSpace, mean_n, cov_nn):
    """Physical theta (5,) at the phi mean and its delta-method std (0 for fixed parameters)."""
    theta = space.theta_from_x(mean_n)
    jac = space.dtheta_dphi(space.to_phi(theta))
    std = np.zeros(5)
    std[space.index] = jac[space.index] * np.sqrt(np.clip(np.diag(cov_nn), 0, None))
    return theta, std


def run_joint(model: PatchModel, meas: MeasurementSet, estimator: str = "ge", *, theta0=None, prior_std=None,
              options: JointOptions | None = None, points: ObservedPoints | None = None,
              progress: Callable[[int, int], None] | None = None, references: str = "fixed",
              adaptation=None, heldout=None, input_block=None, drift: float | None = None,
              rate=None, parameter_overdispersion: float | str = "auto") -> EstimateSet:
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
    references : {'fixed', 'estimate'}
        ``estimate``: the static reference states of :mod:`tracker.reference` join the kinematic state (their
        means and variances are in ``state_mean`` / ``state_var`` after the model's ``2 r`` columns).
    heldout : (H,) int, optional
        Points (indices into ``meas``) left out of every update (:func:`tracker.estimators.holdout_points`).
    input_block : tracker.unknown_input.InputBlock, optional
        A recording without the model's pressure: the input's harmonics and the rigid motion as states of the
        linear block (after the reference states; the dense transition path).
    adaptation : tracker.adaptive.AdaptationOptions, optional
        Estimate the parameters' random walk and the model error added to R from the innovations
        (:mod:`tracker.adaptive`); None keeps the model file's random walk and the measurement covariances.
    parameter_overdispersion : 'auto' or float >= 1
        The parameters' update tempered by the over-dispersion of their shifts (:mod:`tracker.overdispersion`,
        docs/estimators.md §3.11): 'auto' estimates it over the frames so far (1 until it is beyond doubt); a
        number fixes it (1: the plain update).

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
    from .reference import augment_observation, reference_block

    check_references(references)
    options = options or JointOptions.from_config(model.config)
    pts, obs, u, trans, K, dt = run_setup(model, meas, points, input_block)
    u_start, u_ref = u[0], u
    if input_block is not None:
        from .unknown_input import extend_observation, prior_input

        u_start, u_ref = prior_input(input_block, u[0]), u + input_block.mean_inputs(K)
    block = None
    if references == "estimate":
        block = reference_block(model, model.config.theta if theta0 is None else theta0, u_ref)
        obs = augment_observation(obs, block)
    H = obs.H if input_block is None else extend_observation(obs.H, pts.keep.size, input_block, obs.reference)
    prior = joint_prior(model, u_start, theta0, prior_std, block, dt, input_block, rate)
    space = prior.space
    M = space.dim
    filt = JointFilter(estimator, model, space, dt, prior.Q_n, prior.Q_l, options, input_block, rate)
    meta = {"dropped_points": pts.dropped.tolist(), "joseph": options.joseph, "dt": dt,
            "estimated": list(space.estimated), "theta0": space.theta.tolist(),
            "prior_std_phi": np.sqrt(np.diag(prior.state.cov[:M, :M])).tolist(),
            "options": {k: getattr(options, k) for k in options.__dataclass_fields__},
            "references": references, "reference_states": 0 if block is None else block.size,
            "input_states": 0 if input_block is None else input_block.size,
            "rigid_ar_order": None if input_block is None else input_block.ar_order,
            "field_degree": None if input_block is None else input_block.field_degree,
            "rigid_harmonics": None if input_block is None else input_block.rigid_harmonics,
            "random_walk_std_phi": np.sqrt(np.diag(prior.Q_n)).tolist(),
            "held_parameters": [n for n in model.config.parameter_space().estimated if n not in space.estimated]}
    for name, p in zip(filt.sampled_rate_names, filt.rates):
        meta[f"{name}_prior"] = {"frequency_hz": p.frequency_hz, "std_log": p.phi_std,
                                 "walk_per_frame_log": p.walk_per_frame(dt)}
    adapt = None
    if adaptation is not None:
        from .adaptive import NoiseAdaptation

        adapt = NoiseAdaptation(filt.M, dt, prior.Q_n, adaptation)
    from .overdispersion import Overdispersion

    od = Overdispersion(None if parameter_overdispersion == "auto" else float(parameter_overdispersion))
    return run_filter(filt, meas, prior.state, H, obs.reference, pts.keep, u, trans, prior.Q_n,
                      joseph=options.joseph, progress=progress, meta=meta, adapt=adapt, heldout=heldout,
                      drift=drift, translation=None if input_block is None else
                      [H.shape[1] - input_block.size + i for i in input_block.translation_states],
                      overdispersion=od)
