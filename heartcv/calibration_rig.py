"""Rig calibration: intrinsics and ``cam_from_rig`` of N >= 2 cameras from target detections.

Steps (:func:`calibrate_rig_detailed`):

1. per camera, intrinsics and board poses from :func:`heartcv.calibration.calibrate_intrinsics` (outlier
   views rejected there);
2. for every camera pair, the relative poses ``a_from_b = a_from_board @ inv(b_from_board)`` of the views both
   see, robustly averaged (:func:`robust_mean_pose`); the pairs are chained along a maximum spanning tree
   (weight = views agreeing with the average) rooted at camera 0, so cameras that never see the board
   together with camera 0 are placed through the others;
3. each view's board pose in the rig frame from the camera that sees most of its corners;
4. **one joint refinement** of every camera's ``fx, fy, cx, cy``, distortion and ``cam_from_rig`` (camera 0
   fixed at the identity: it defines the rig frame) and every view's ``rig_from_board``, minimising the
   reprojection error (:func:`heartcv.calibration_ba.bundle_adjust`: Levenberg-Marquardt with the board poses
   eliminated by the Schur complement, exact complex-step Jacobian); camera views whose RMS is an outlier
   (:func:`heartcv.calibration.outlier_views`, per camera) are dropped and the refinement is run again;
5. standard deviations of the camera parameters from ``sigma^2 (J^T J)^-1`` at the solution, with the board
   poses marginalised by the Schur complement and ``sigma^2 = sum r^2 / (2 M - n_params)``; the rotation's
   are those of the rotation vector of a left increment ``exp([w]x) R`` at the solution, in degrees.

References: Triggs et al., "Bundle adjustment -- a modern synthesis", 2000 (Schur complement, gauge);
Hartley et al., "Rotation averaging", IJCV 103, 2013 (chordal L2 mean).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .calibration import (
    MIN_VIEWS,
    OUTLIER_FACTOR,
    CalibrationError,
    calibrate_intrinsics,
    describe_target,
    outlier_views,
    target_mismatch,
    usable_view,
)
from .calibration_ba import RigProblem, bundle_adjust
from .camera import Camera, Rig, invert_pose

__all__ = ["RigCalibration", "calibrate_rig", "calibrate_rig_detailed", "robust_mean_pose", "kalibr_limitation"]

_DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")  # OpenCV order (docs/formats.md, rig file)
_SOLVER = "Levenberg-Marquardt, Schur complement, complex-step Jacobian (heartcv.calibration_ba)"


@dataclass(frozen=True)
class RigCalibration:
    """A rig calibration with what the rig file does not keep.

    Attributes
    ----------
    rig : heartcv.camera.Rig
    rig_from_board : ndarray of shape (n_views, 4, 4)
        Board pose per view in the rig frame; NaN for views not used.
    used : ndarray of shape (n_cameras, n_views), bool
        Camera views in the final refinement.
    view_rms : ndarray of shape (n_cameras, n_views)
        RMS per camera view (px); NaN for views without a usable detection.
    """

    rig: Rig
    rig_from_board: np.ndarray
    used: np.ndarray
    view_rms: np.ndarray


# -- rotations ---------------------------------------------------------------------------------------------
def _angle(Ra, Rb) -> np.ndarray:
    """Geodesic angle (rad) between rotations (..., 3, 3)."""
    c = (np.trace(np.swapaxes(Ra, -1, -2) @ Rb, axis1=-2, axis2=-1) - 1) / 2
    return np.arccos(np.clip(c, -1, 1))


def _project_so3(M) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def robust_mean_pose(T, *, min_angle=np.radians(0.5), min_dist_rel=0.01):
    """Robust average of rigid transforms (n, 4, 4) -> (4x4, inlier mask (n,)).

    The medoid (smallest summed rotation angle to the others) and the component-wise median translation
    give a first estimate; samples within ``max(3 * median deviation, min_angle)`` in rotation and
    ``max(3 * median deviation, min_dist_rel * |t|)`` in translation are inliers, and the result is their
    chordal L2 mean rotation and mean translation.
    """
    T = np.asarray(T, float)
    R, t = T[:, :3, :3], T[:, :3, 3]
    ang = _angle(R[:, None], R[None])
    R_med = R[np.argmin(ang.sum(axis=1))]
    t_med = np.median(t, axis=0)
    da = _angle(R, R_med[None])
    dt = np.linalg.norm(t - t_med, axis=1)
    inl = (da <= max(3 * np.median(da), min_angle)) & (dt <= max(3 * np.median(dt),
                                                                 min_dist_rel * np.linalg.norm(t_med)))
    out = np.eye(4)
    out[:3, :3] = _project_so3(R[inl].sum(axis=0))
    out[:3, 3] = t[inl].mean(axis=0)
    return out, inl


# -- initialisation ----------------------------------------------------------------------------------------
def _initial_cam_from_rig(cam_from_board, used, names):
    """Chain robust pairwise relative poses along a maximum spanning tree rooted at camera 0."""
    n_cam = len(names)
    rel, weight = {}, np.zeros((n_cam, n_cam), int)
    for a in range(n_cam):
        for b in range(a + 1, n_cam):
            common = np.flatnonzero(used[a] & used[b])
            if common.size == 0:
                continue
            a_from_b = cam_from_board[a, common] @ np.stack([invert_pose(T) for T in cam_from_board[b, common]])
            T, inl = robust_mean_pose(a_from_b)
            rel[a, b], rel[b, a] = T, invert_pose(T)
            weight[a, b] = weight[b, a] = int(inl.sum())
    cam_from_rig = [None] * n_cam
    cam_from_rig[0] = np.eye(4)
    while True:  # Prim: add the heaviest edge from the tree to a camera outside it
        best = None
        for a in range(n_cam):
            for b in range(n_cam):
                if cam_from_rig[a] is not None and cam_from_rig[b] is None and weight[a, b] > 0 \
                        and (best is None or weight[a, b] > weight[best]):
                    best = (a, b)
        if best is None:
            break
        a, b = best
        cam_from_rig[b] = rel[b, a] @ cam_from_rig[a]  # b_from_rig = b_from_a a_from_rig
    if any(T is None for T in cam_from_rig):
        _check_linked(used, names)
    return np.stack(cam_from_rig)


# -- the calibration ---------------------------------------------------------------------------------------
def calibrate_rig(detections, spec, image_sizes, **kwargs) -> Rig:
    """:func:`calibrate_rig_detailed` returning the :class:`~heartcv.camera.Rig` only."""
    return calibrate_rig_detailed(detections, spec, image_sizes, **kwargs).rig


def calibrate_rig_detailed(detections, spec, image_sizes, *, names=None, view_names=None, dist_size=5,
                           max_view_rms=None, outlier_factor=OUTLIER_FACTOR, min_views=MIN_VIEWS,
                           max_rounds=5) -> RigCalibration:
    """Calibrate a rig of N >= 2 cameras (module docstring for the method).

    Parameters
    ----------
    detections : sequence (n_cameras) of sequences (n_views) of Detection or None
        ``detections[c][v]``: camera ``c`` at instant ``v`` (None or empty: not seen or no image).
    spec : heartcv.targets.TargetSpec
    image_sizes : sequence of (int, int)
        ``(width, height)`` per camera.
    names : sequence of str, optional
        Camera names (default ``cam0, cam1, ...``).
    view_names : sequence of str, optional
        Names of the instants, used in the per-view errors (default ``"0", "1", ...``).
    dist_size : {4, 5, 8}
    max_view_rms : float, optional
        Camera views above this RMS (px) are rejected.
    outlier_factor : float
        Camera views above ``max(outlier_factor * median, OUTLIER_FLOOR_PX)`` of their camera are rejected.
    min_views : int
        Usable views needed per camera, before and after rejection.
    max_rounds : int
        Refinements at most (each after a rejection).

    Returns
    -------
    RigCalibration
        ``rig.meta`` (docs/formats.md, rig file): ``rms_px``, ``residual_sigma_px`` (sqrt of sigma^2 above,
        per coordinate), ``target`` (the target's dict), ``baselines_m``, ``dist_model``, ``solver``,
        ``solver_iterations``, ``solver_converged``, ``observations`` (corners), ``views_used`` (instants),
        ``view_names`` and ``cameras: {name: {rms_px, views_used, per_view_errors (list aligned with
        view_names, None where not used), rejected_views {view: px}, std {fx, fy, cx, cy, k1, ...,
        rotation_deg [3], translation_m [3]}, intrinsics_only_rms_px}}``.

    Raises
    ------
    CalibrationError
        The target is found in no image, or the ChArUco board in the images is not the target
        (:func:`heartcv.calibration.target_mismatch`); a camera has fewer than ``min_views`` usable views (the
        message and ``views_per_camera`` give the count of every camera); cameras cannot be linked to camera 0.
    """
    names, view_names = _check_inputs(detections, spec, image_sizes, names, view_names, min_views)
    n_cam, n_views = len(detections), len(view_names)
    intr = [calibrate_intrinsics(dets, spec, size, dist_size=dist_size, max_view_rms=max_view_rms,
                                 outlier_factor=outlier_factor, min_views=min_views, name=n)
            for dets, size, n in zip(detections, image_sizes, names)]
    used = np.stack([r.used for r in intr])
    view_rms = np.stack([r.per_view_rms for r in intr])
    cam_from_board = np.stack([r.cam_from_board for r in intr])
    cam_from_rig = _initial_cam_from_rig(cam_from_board, used, names)
    # board poses in the rig frame, from the camera that sees most corners of each view
    rig_from_board = np.full((n_views, 4, 4), np.nan)
    for v in range(n_views):
        cams = [c for c in range(n_cam) if used[c, v]]
        if cams:
            c = max(cams, key=lambda c: len(detections[c][v]))
            rig_from_board[v] = invert_pose(cam_from_rig[c]) @ cam_from_board[c, v]
    x_intr = np.stack([np.r_[r.K[0, 0], r.K[1, 1], r.K[0, 2], r.K[1, 2], r.dist] for r in intr])

    for _ in range(max_rounds):
        prob, vidx = _build_problem(detections, used, spec, dist_size)
        try:
            ba = bundle_adjust(prob, x_intr, cam_from_rig, rig_from_board[vidx >= 0])
        except np.linalg.LinAlgError:
            raise CalibrationError("the joint refinement is degenerate (singular normal equations): the views do "
                                   "not constrain every camera; add views with the board tilted") from None
        x_intr, cam_from_rig = ba.intrinsics, ba.cam_from_rig
        rig_from_board = np.full((n_views, 4, 4), np.nan)
        rig_from_board[vidx >= 0] = ba.rig_from_board
        new_rms = _view_rms(prob, ba.residuals, used, vidx)
        view_rms = np.where(used, new_rms, view_rms)
        bad = np.stack([outlier_views(r, factor=outlier_factor, max_view_rms=max_view_rms) for r in new_rms])
        if not bad.any():
            break
        used &= ~bad
        left = dict(zip(names, used.sum(axis=1).tolist()))
        if min(left.values()) < min_views:
            raise CalibrationError("too few usable views after rejecting outlier views in the joint refinement: "
                                   + ", ".join(f"{n} {k}" for n, k in left.items())
                                   + f" (at least {min_views} per camera needed)", left)
        _check_linked(used, names)
    return _result(prob, ba, names, view_names, image_sizes, used, view_rms, intr, spec, dist_size,
                   rig_from_board)


def _check_inputs(detections, spec, image_sizes, names, view_names, min_views):
    n_cam = len(detections)
    if n_cam < 2:
        raise ValueError(f"detections: at least 2 cameras expected, got {n_cam}")
    n_views = len(detections[0])
    if any(len(d) != n_views for d in detections):
        raise ValueError(f"detections: the same number of views per camera expected, got "
                         f"{[len(d) for d in detections]}")
    names = [f"cam{i}" for i in range(n_cam)] if names is None else list(names)
    view_names = [str(v) for v in range(n_views)] if view_names is None else [str(v) for v in view_names]
    if len(names) != n_cam or len(view_names) != n_views or len(image_sizes) != n_cam:
        raise ValueError(f"names, image_sizes: {n_cam} expected; view_names: {n_views} expected")
    if not any(d is not None and len(d) for dets in detections for d in dets):
        raise CalibrationError(f"the target ({describe_target(spec)}) was found in none of the {n_cam * n_views} "
                               f"images: check that the target file matches the board in the images",
                               dict.fromkeys(names, 0))
    mismatch = target_mismatch(detections, spec)
    if mismatch:
        raise CalibrationError(f"the target ({describe_target(spec)}) does not match the board in the images: "
                               f"{mismatch}; check the target file")
    counts = {n: int(sum(usable_view(d, spec) for d in dets)) for n, dets in zip(names, detections)}
    if min(counts.values()) < min_views:
        raise CalibrationError("too few usable views: " + ", ".join(f"{n} {k}" for n, k in counts.items())
                               + f" (at least {min_views} per camera needed)", counts)
    return names, view_names


def _check_linked(used, names):
    """CalibrationError naming the cameras that no chain of shared views links to camera 0."""
    n_cam = len(names)
    linked, frontier = {0}, [0]
    while frontier:
        a = frontier.pop()
        for b in range(n_cam):
            if b not in linked and (used[a] & used[b]).any():
                linked.add(b)
                frontier.append(b)
    missing = [names[i] for i in range(n_cam) if i not in linked]
    if missing:
        raise CalibrationError(
            f"cameras {', '.join(missing)} share no usable view with {names[0]} or with a camera linked to it: "
            f"they cannot be placed in the rig (show the target to them together with another camera)")


def _build_problem(detections, used, spec, dist_size):
    """The observations of the used camera views; views renumbered densely (``vidx``: -1 if unused)."""
    n_cam, n_views = used.shape
    views = np.flatnonzero(used.any(axis=0))
    vidx = np.full(n_views, -1)
    vidx[views] = np.arange(views.size)
    obj = spec.object_points()
    oc, ov, X, uv = [], [], [], []
    for c in range(n_cam):
        for v in np.flatnonzero(used[c]):
            d = detections[c][v]
            oc.append(np.full(len(d), c))
            ov.append(np.full(len(d), vidx[v]))
            X.append(obj[d.ids])
            uv.append(d.uv)
    prob = RigProblem(np.concatenate(oc), np.concatenate(ov), np.concatenate(X), np.concatenate(uv), n_cam,
                      views.size, dist_size)
    return prob, vidx


def _view_rms(prob, r, used, vidx):
    """RMS (px) per camera view (n_cam, n_views) of the residuals r; NaN where not used."""
    n_cam, n_views = used.shape
    e2 = (np.asarray(r) ** 2).sum(axis=1)
    key = prob.obs_cam * prob.n_view + prob.obs_view
    size = n_cam * prob.n_view
    mean = np.bincount(key, e2, size) / np.maximum(np.bincount(key, minlength=size), 1)
    out = np.full((n_cam, n_views), np.nan)
    views = vidx >= 0
    out[:, views] = np.sqrt(mean.reshape(n_cam, prob.n_view))
    return np.where(used, out, np.nan)


def _result(prob, ba, names, view_names, image_sizes, used, view_rms, intr, spec, dist_size, rig_from_board):
    n_cam, ni = len(names), prob.ni
    std_all = np.sqrt(np.clip(np.diag(ba.cov_cameras), 0, None))
    e2 = (ba.residuals ** 2).sum(axis=1)
    cameras, cam_meta = [], {}
    for c, n in enumerate(names):
        p = ba.intrinsics[c]
        K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
        cameras.append(Camera(n, *image_sizes[c], K, p[4:], ba.cam_from_rig[c]))
        s = std_all[c * ni:(c + 1) * ni]
        sp = std_all[n_cam * ni + 6 * (c - 1):n_cam * ni + 6 * c] if c else np.zeros(6)
        rejected = np.isfinite(view_rms[c]) & ~used[c]
        std = {"fx": float(s[0]), "fy": float(s[1]), "cx": float(s[2]), "cy": float(s[3])}
        std.update(zip(_DIST_NAMES, map(float, s[4:])))
        std["rotation_deg"] = np.degrees(sp[:3]).tolist()
        std["translation_m"] = sp[3:].tolist()
        cam_meta[n] = {
            "rms_px": float(np.sqrt(e2[prob.obs_cam == c].mean())),
            "views_used": int(used[c].sum()),
            "per_view_errors": [float(view_rms[c, v]) if used[c, v] else None for v in range(len(view_names))],
            "rejected_views": {view_names[v]: float(view_rms[c, v]) for v in np.flatnonzero(rejected)},
            "std": std,
            "intrinsics_only_rms_px": float(intr[c].rms_px),
        }
    rig = Rig(tuple(cameras))
    meta = {
        "rms_px": float(np.sqrt(e2.mean())),
        "residual_sigma_px": float(np.sqrt(ba.sigma2)),
        "cameras": cam_meta,
        "baselines_m": rig.baselines(),
        "target": spec.to_dict(),
        "dist_model": int(dist_size),
        "solver": _SOLVER,
        "solver_iterations": int(ba.iterations),
        "solver_converged": bool(ba.converged),
        "observations": int(e2.size),
        "views_used": int(used.any(axis=0).sum()),
        "view_names": list(view_names),
    }
    return RigCalibration(Rig(tuple(cameras), meta), rig_from_board, used.copy(), view_rms)


def kalibr_limitation(rig: Rig) -> str | None:
    """Why a Kalibr camchain (``pinhole`` cameras without skew, ``radtan`` distortion k1 k2 p1 p2) cannot hold
    the rig, or None when it can (``heartcv calibrate`` then writes one; docs/cli.md §8, Kalibr export)."""
    for cam in rig.cameras:
        if cam.K[0, 1] != 0:
            return f"{cam.name}: K has skew {cam.K[0, 1]}; Kalibr's pinhole model has none"
        d = np.asarray(cam.dist, float)
        if d.size > 4 and np.any(d[4:] != 0):
            names = _DIST_NAMES + tuple(f"d{i}" for i in range(len(_DIST_NAMES), d.size))
            bad = {n: float(v) for n, v in zip(names[4:], d[4:]) if v != 0}
            return (f"{cam.name}: Kalibr's radtan model has k1, k2, p1, p2 only; non-zero {bad} (calibrate with 4 "
                    "or 5 coefficients and k3 fixed at 0 for a Kalibr export)")
    return None
