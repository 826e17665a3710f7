"""Run an estimator over a measurement set with the patch model (the KF here; GE/UKF/EKF in their modules).

The cycle per frame k: predict ``x_k = A x_{k-1} + B0 u_{k-1} + B1 u_k`` (first-order hold), record the
one-step prediction of every point, update with the points seen in frame k (NaN rows dropped) and record the
filtered (posterior) position of every point.
Frame 0 updates the prior (static equilibrium under ``u_0`` with the configured initial covariance).
"""

from __future__ import annotations

from dataclasses import dataclass
import logging
import time

import numpy as np

from .files import InputError
from .kalman import GaussianState, predict, update
from .measurements import EstimateSet, MeasurementSet
from .model import Observation, PatchModel

__all__ = ["ObservedPoints", "locate_points", "run_kalman", "EstimationDiverged"]

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
    if np.abs(dts - dt).max() > 1e-6 * dt:
        raise InputError(None, "the estimators need a constant frame interval (equally spaced frame times)",
                         "times")
    return dt


def _block_diag_R(cov_k: np.ndarray) -> np.ndarray:
    """Block-diagonal R (3P, 3P) of per-point covariances (P, 3, 3); unseen points get an identity block
    (their rows are dropped by the update anyway)."""
    P = cov_k.shape[0]
    blocks = np.where(np.isfinite(cov_k).all(axis=(1, 2))[:, None, None], cov_k, np.eye(3))
    R = np.zeros((P, 3, P, 3))
    R[np.arange(P), :, np.arange(P), :] = blocks
    return R.reshape(3 * P, 3 * P)


def run_setup(model: PatchModel, meas: MeasurementSet, points: ObservedPoints | None = None):
    """What every estimator run over ``meas`` starts from: ``(points, observation, inputs (K, n_u), translation
    (K, 3), K, dt)`` (:func:`locate_points`, :func:`frame_interval`)."""
    pts = points or locate_points(model, meas)
    return (pts, pts.observation, meas.input_columns(model.input_names), meas.translation(), meas.n_frames,
            frame_interval(model, meas))


def run_kalman(model: PatchModel, meas: MeasurementSet, theta=None, *, joseph=False,
               points: ObservedPoints | None = None) -> EstimateSet:
    """Kalman filter with fixed ``theta`` (default: the model file's) over a measurement set."""
    theta = model.config.theta if theta is None else np.asarray(theta, float)
    pts, obs, u, trans, K, dt = run_setup(model, meas, points)
    sysd = model.system(theta, dt)
    Q = model.process_noise(theta, dt)
    n = model.state_dim
    P_all = meas.n_points
    y_all = meas.positions[:, pts.keep, :].reshape(K, -1)
    cov_all = meas.covariances[:, pts.keep]
    H = obs.H

    prior = GaussianState(model.static_state(theta, u[0]), model.initial_covariance())
    state_mean = np.full((K, n), np.nan)
    state_var = np.full((K, n), np.nan)
    predictions = np.full((K, P_all, 3), np.nan)
    filtered = np.full((K, P_all, 3), np.nan)
    innovations = np.full((K, P_all, 3), np.nan)
    nis = np.full(K, np.nan)
    dof = np.zeros(K, np.int64)
    step_time = np.zeros(K)
    completed = 0
    state = prior
    for k in range(K):
        t0 = time.perf_counter()
        if k > 0:
            state = predict(state, sysd.A, Q, sysd.B0 @ u[k - 1] + sysd.B1 @ u[k])
        offset = (obs.reference + trans[k]).reshape(-1)
        pred_y = offset + H @ state.mean
        res = update(state, y_all[k], H, _block_diag_R(cov_all[k]), offset, joseph=joseph)
        state = res.state
        step_time[k] = time.perf_counter() - t0
        if not np.isfinite(state.mean).all():
            raise EstimationDiverged(k)
        predictions[k, pts.keep] = pred_y.reshape(-1, 3)
        filtered[k, pts.keep] = (offset + H @ state.mean).reshape(-1, 3)
        innovations[k, pts.keep] = (y_all[k] - pred_y).reshape(-1, 3)
        state_mean[k] = state.mean
        state_var[k] = np.diag(state.cov)
        nis[k] = res.nis
        dof[k] = res.dof
        completed = k + 1
    theta_k = np.broadcast_to(theta, (K, 5)).copy()
    return EstimateSet(
        "kf", meas.times, meas.point_ids, state_mean, state_var, theta_k, np.zeros((K, 5)), predictions,
        innovations, nis, dof, np.zeros(K, np.int64), step_time, completed,
        meta={"dropped_points": pts.dropped.tolist(), "joseph": joseph, "dt": dt}, filtered=filtered,
    )
