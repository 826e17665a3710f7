"""Run an estimator over a measurement set with the patch model (the KF here; GE/UKF/EKF in their modules).

The cycle per frame k: predict ``x_k = A x_{k-1} + B0 u_{k-1} + B1 u_k`` (first-order hold), record the
one-step prediction of every point, update with the points seen in frame k (NaN rows dropped) and record the
filtered (posterior) position of every point.
Frame 0 updates the prior (static equilibrium under ``u_0`` with the configured initial covariance).
"""

from __future__ import annotations

from dataclasses import dataclass
import logging
from typing import Callable

import numpy as np

from .estimators import Estimator, register, run_filter
from .files import InputError
from .kalman import GaussianState, predict
from .measurements import EstimateSet, MeasurementSet
from .model import Observation, PatchModel

__all__ = ["ObservedPoints", "locate_points", "run_kalman", "EstimationDiverged", "check_references", "KalmanFilter",
           "relearn_rigid_dynamics", "RigidRelearning",
           "DriftSelection", "select_track_drift", "first_frames", "DRIFT_GRID"]

log = logging.getLogger(__name__)


class EstimationDiverged(FloatingPointError):
    """The estimate became non-finite; ``step`` is the frame index and ``partial`` the steps done."""

    def __init__(self, step: int, partial: EstimateSet | None = None):
        super().__init__(f"estimate became non-finite at step {step}")
        self.step = step
        self.partial = partial


@dataclass(frozen=True)
class ObservedPoints:
    """Measurement points of a set placed on the model.

    Attributes
    ----------
    keep : ndarray (P_used,) int      indices into the measurement set's points
    observation : Observation         H and reference positions for the kept points
    dropped : ndarray (P_drop,) int   indices of points off the patch
    """

    keep: np.ndarray
    observation: Observation
    dropped: np.ndarray


def locate_points(model: PatchModel, meas: MeasurementSet, *, max_depth=None) -> ObservedPoints:
    """Give each point of a patch-frame measurement set its material coordinates and measurement rows.

    Points whose reference position lies outside the patch (in ``s``/``t``) or farther than ``max_depth``
    (default: a quarter of the thickness) from the epicardium are dropped. Surface points are projected onto
    the epicardium (``d = 0``).

    Raises
    ------
    InputError
        A rig-frame set (field ``meta.frame``) or one of which no point lies on the patch (``reference``); no
        file is named: the caller attaches it (:meth:`InputError.in_file`).
    """
    if meas.frame != "patch":
        raise InputError(None, "frame 'rig' needs registration onto the model first (heartcv fit); this file is "
                               "not in the patch frame", "meta.frame")
    g = model.mesh.geometry
    param = g.from_patch(meas.reference)
    max_depth = 0.25 * g.thickness if max_depth is None else max_depth
    inside = (
        (np.abs(param[:, 0]) <= g.length / 2 * (1 + 1e-9))
        & (np.abs(param[:, 1]) <= g.width / 2 * (1 + 1e-9))
        & (np.abs(param[:, 2]) <= max_depth)
    )
    keep = np.flatnonzero(inside)
    if keep.size == 0:
        raise InputError(None, f"none of the {meas.n_points} points lies on the model's patch (reference positions "
                               f"span {np.ptp(meas.reference, axis=0)} m; wrong units or frame?)", "reference")
    p = param[keep].copy()
    p[:, 0] = np.clip(p[:, 0], -g.length / 2, g.length / 2)
    p[:, 1] = np.clip(p[:, 1], -g.width / 2, g.width / 2)
    p[:, 2] = 0.0
    obs = model.observation(p)
    # keep the measured reference (not the FE surface) as the offset
    obs = Observation(obs.H, meas.reference[keep].copy(), p)
    return ObservedPoints(keep, obs, np.flatnonzero(~inside))


def frame_interval(model: PatchModel, meas: MeasurementSet) -> float:
    """The constant frame interval of a measurement set (the model's for a single frame); InputError (field
    ``times``) if the frame times are not equally spaced to 1e-6 relative."""
    dts = np.diff(meas.times)
    if dts.size == 0:
        return model.config.dt
    dt = float(np.median(dts))
    worst = float(np.abs(dts - dt).max())
    if worst > 1e-6 * dt:
        raise InputError(None, f"the estimators need a constant frame interval (equally spaced frame times): an "
                               f"interval differs from the median {dt:.6g} s by {worst:.3g} s (more than 1e-6 of "
                               "it; times in single precision round by that much: float64 expected)", "times")
    return dt


def run_setup(model: PatchModel, meas: MeasurementSet, points: ObservedPoints | None = None, input_block=None):
    """What every estimator run over ``meas`` starts from: ``(points, observation, inputs (K, n_u), translation
    (K, 3), K, dt)`` (:func:`locate_points`, :func:`frame_interval`). With an ``input_block``
    (:class:`tracker.unknown_input.InputBlock`) the block's input column is zero (the block drives it) and there
    is no known translation (the block carries the rigid motion)."""
    pts = points or locate_points(model, meas)
    if input_block is not None:
        from .unknown_input import known_inputs

        return (pts, pts.observation, known_inputs(meas, model, input_block), np.zeros((meas.n_frames, 3)),
                meas.n_frames, frame_interval(model, meas))
    return (pts, pts.observation, meas.input_columns(model.input_names), meas.translation(), meas.n_frames,
            frame_interval(model, meas))


def _prior_input(input_block, u0):
    from .unknown_input import prior_input

    return prior_input(input_block, u0)


def check_references(references: str) -> None:
    from .reference import MODES

    if references not in MODES:
        raise ValueError(f"references: one of {MODES} expected, got {references!r}")


@register("kf")
class KalmanFilter(Estimator):
    """The KF variant (:mod:`tracker.estimators`): the linear prediction ``x' = A x + B0 u0 + B1 u1``,
    ``C' = A C A^T + Q`` at a fixed theta (no parameter block, M = 0); with static states,
    ``A = blkdiag(A(theta), I)``."""

    def __init__(self, theta, A, B0, B1, Q):
        self.theta = np.asarray(theta, float)
        self.A, self.B0, self.B1, self.Q = A, B0, B1, Q

    def predict(self, state, u0, u1, Q_n=None):
        return predict(state, self.A, self.Q, self.B0 @ u0 + self.B1 @ u1), {}

    def parameters(self, state):
        return self.theta, np.zeros(5)


def run_kalman(model: PatchModel, meas: MeasurementSet, theta=None, *, joseph=False,
               points: ObservedPoints | None = None, references: str = "fixed", adaptation=None,
               heldout=None, input_block=None, drift: float | None = None,
               progress: Callable[[int, int], None] | None = None) -> EstimateSet:
    """Kalman filter with fixed ``theta`` (default: the model file's) over a measurement set (the ``kf`` variant
    of :mod:`tracker.estimators`, its frame loop :func:`tracker.estimators.run_filter`).

    ``references='estimate'`` appends the static reference states (:mod:`tracker.reference`) to the state;
    ``adaptation`` (:class:`tracker.adaptive.AdaptationOptions`) adds the model error estimated from the
    innovations to R (the KF has no random walk to adapt); ``heldout`` (indices into ``meas``) are left out of
    every update (:func:`tracker.estimators.run_filter`); ``input_block``
    (:class:`tracker.unknown_input.InputBlock`) estimates the input and the rigid motion as states; ``drift``
    (m per frame) adds per-track offsets (:class:`tracker.estimators.TrackOffsets`)."""
    from .reference import augment_observation, augment_transition, reference_block

    check_references(references)
    theta = model.config.theta if theta is None else np.asarray(theta, float)
    pts, obs, u, trans, K, dt = run_setup(model, meas, points, input_block)
    sysd = model.system(theta, dt)
    Q = model.process_noise(theta, dt)
    A, B0, B1 = sysd.A, sysd.B0, sysd.B1
    u_start = u[0] if input_block is None else _prior_input(input_block, u[0])
    mean0, cov0 = model.static_state(theta, u_start), model.initial_covariance()
    block = None
    if references == "estimate":
        u_ref = u if input_block is None else u + input_block.mean_inputs(K)
        block = reference_block(model, theta, u_ref)
        obs = augment_observation(obs, block)
        A, _ = augment_transition(A, np.zeros(A.shape[0]), block.size)
        B0 = np.vstack([B0, np.zeros((block.size, B0.shape[1]))])
        B1 = np.vstack([B1, np.zeros((block.size, B1.shape[1]))])
        Q = block.noise(Q)
        mean0, cov0 = block.prior(mean0, cov0)
    H = obs.H
    if input_block is not None:
        from .unknown_input import extend_noise, extend_observation, extend_prior, extend_transition

        A = extend_transition(A, sysd.B0, sysd.B1, input_block)
        B0 = np.vstack([B0, np.zeros((input_block.size, B0.shape[1]))])
        B1 = np.vstack([B1, np.zeros((input_block.size, B1.shape[1]))])
        Q = extend_noise(Q, input_block)
        mean0, cov0 = extend_prior(mean0, cov0, input_block)
        H = extend_observation(H, pts.keep.size, input_block, obs.reference)
    kf = KalmanFilter(theta, A, B0, B1, Q)
    meta = {"dropped_points": pts.dropped.tolist(), "joseph": joseph, "dt": dt, "references": references,
            "reference_states": 0 if block is None else block.size,
            "input_states": 0 if input_block is None else input_block.size,
            "rigid_ar_order": None if input_block is None else input_block.ar_order,
            "field_degree": None if input_block is None else input_block.field_degree,
            "rigid_harmonics": None if input_block is None else input_block.rigid_harmonics}
    adapt = None
    if adaptation is not None:
        from .adaptive import NoiseAdaptation

        adapt = NoiseAdaptation(0, dt, np.zeros((0, 0)), adaptation)
    return run_filter(kf, meas, GaussianState(mean0, cov0), H, obs.reference, pts.keep, u, trans,
                      np.zeros((0, 0)), joseph=joseph, meta=meta, adapt=adapt, heldout=heldout, drift=drift,
                      progress=progress, translation=None if input_block is None else
                      [H.shape[1] - input_block.size + i for i in input_block.translation_states])



@dataclass(frozen=True)
class RigidRelearning:
    """Result of :func:`relearn_rigid_dynamics`: the block with the relearned dynamics, the frames they were learned
    from, the autoregression's order before and after, and the ridge chosen."""

    block: object
    frames: int
    order_before: int
    order: int
    ridge: float

    def info(self) -> dict:
        return {"source": "refit", "frames": self.frames, "order_fit": self.order_before, "order": self.order,
                "ridge": self.ridge}


def relearn_rigid_dynamics(model: PatchModel, meas: MeasurementSet, theta, input_block, *, frames: int,
                           order: int | None = None, **kalman) -> RigidRelearning:
    """The estimated input's rigid motion with its dynamics learned from the estimator's own view of it
    (docs/model.md §17 "Relearning the rigid motion's dynamics"): the KF at ``theta`` with ``input_block`` over the
    first ``frames`` frames (the fitted ones), its filtered ``tau`` per frame, and the block's increment
    autoregression and random walk refitted to that series (:func:`tracker.unknown_input.with_rigid_dynamics`;
    ``order`` forces the order). The fit learns them from its profiled per-frame residual, which holds what the
    per-track offsets and the filter's references take up in the estimators; the filtered series is what the
    estimators propagate. One pass of the expectation-maximisation idea, on filtered (causal) states. ``kalman``:
    the other arguments of :func:`run_kalman` (references, adaptation, heldout, drift)."""
    from .unknown_input import with_rigid_dynamics

    sub = first_frames(meas, frames)
    est = run_kalman(model, sub, theta, input_block=input_block, **kalman)
    done = est.completed_steps
    tau = est.state_mean[:done, est.state_mean.shape[1] - input_block.size:][:, input_block.slices[1]]
    block, ridge = with_rigid_dynamics(input_block, tau, order)
    return RigidRelearning(block, int(done), input_block.ar_order, block.ar_order, ridge)


DRIFT_GRID = (0.01, 0.03, 0.1, 0.3, 1.0, 3.0)
"""Candidate random walks of the per-track offsets, per frame, in units of the median measurement σ (plus none)."""


def first_frames(meas: MeasurementSet, frames: int) -> MeasurementSet:
    """The set's first ``frames`` frames (every per-frame array cut, views of the set's; points, references and meta
    kept; not validated again: :meth:`MeasurementSet._derived`)."""
    K = max(1, min(int(frames), meas.n_frames))
    return MeasurementSet._derived(meas, times=meas.times[:K], positions=meas.positions[:K],
                                   covariances=meas.covariances[:K], inputs=meas.inputs[:K], views=meas.views[:K],
                                   reprojection_rms=meas.reprojection_rms[:K])


@dataclass(frozen=True)
class DriftSelection:
    """Result of :func:`select_track_drift`: the chosen random walk per frame (m; 0: no offsets), the candidates
    and their innovation log-likelihoods, the frames used and the σ the grid was scaled by."""

    std_per_frame_m: float
    candidates_m: tuple
    log_likelihoods: tuple
    frames: int
    sigma_m: float

    def info(self) -> dict:
        return {"std_per_frame_m": self.std_per_frame_m, "frames": self.frames, "sigma_m": self.sigma_m,
                "candidates_m": list(self.candidates_m), "log_likelihoods": list(self.log_likelihoods)}


def select_track_drift(model: PatchModel, meas: MeasurementSet, theta=None, *, frames: int = 100,
                       references: str = "fixed", adaptation=None, heldout=None, input_block=None,
                       grid=DRIFT_GRID) -> DriftSelection:
    """The per-track offsets' random walk by maximum likelihood (docs/estimators.md §3.9): the KF at ``theta``
    over the first ``frames`` frames for no offsets and for each ``grid`` value times the median measurement σ
    (per coordinate); the candidate with the largest innovation log-likelihood (frames 1 .. frames - 1) wins, then
    a parabola through it and its neighbours in log σ_b refines it (kept only when it beats the grid's best). The
    other arguments as :func:`run_kalman`."""
    from .metrics import measurement_noise_level

    sub = first_frames(meas, frames)
    sigma = float(measurement_noise_level(sub.covariances, sub.seen))
    if not (np.isfinite(sigma) and sigma > 0):
        raise InputError(None, "no finite measurement covariance in the first frames: no scale for the track "
                               "offsets", "covariances")

    def loglik(q):
        est = run_kalman(model, sub, theta, references=references, adaptation=adaptation, heldout=heldout,
                         input_block=input_block, drift=q or None)
        return float(est.meta["log_likelihood"])

    qs = [0.0] + [g * sigma for g in grid]
    ll = [loglik(q) for q in qs]
    best = int(np.argmax(ll))
    q_best, l_best = qs[best], ll[best]
    if 1 < best < len(qs) - 1:   # interior of the (logarithmic) grid: refine by a parabola in log q
        x = np.log(qs[best - 1:best + 2])
        a, b, _ = np.polyfit(x, ll[best - 1:best + 2], 2)
        if a < 0:
            q_ref = float(np.exp(np.clip(-b / (2 * a), x[0], x[2])))
            l_ref = loglik(q_ref)
            qs.append(q_ref)
            ll.append(l_ref)
            if l_ref > l_best:
                q_best, l_best = q_ref, l_ref
    return DriftSelection(float(q_best), tuple(float(q) for q in qs), tuple(ll), sub.n_frames, sigma)
