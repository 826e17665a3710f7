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
    polarity_mismatch,
    target_mismatch,
    usable_view,
)
from .calibration_ba import RigProblem, bundle_adjust
from .calibration_checks import (
    CONSISTENCY_RATIO,
    HELD_DIST_SIGMA,
    PP_PRIOR_FRACTION,
    SYNC_DROP_PX,
    distortion_fold,
    distortion_terms,
    image_coverage,
    jackknife_std,
    sync_displacement,
    sync_weights,
)
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
                           max_rounds=5, given=None, hold=None, times=None, folds=5,
                           progress=None, weak_data_rules=True) -> RigCalibration:
    """Calibrate a rig of N >= 2 cameras (module docstring for the method).

    Parameters
    ----------
    detections : sequence (n_cameras) of sequences (n_views) of Detection or None
        ``detections[c][v]``: camera ``c`` at instant ``v`` (None or empty: not seen or no image). Views that one
        camera saw alone (its own intrinsic recordings) take part too: they determine that camera's intrinsics.
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
    given : sequence (n_cameras) of (K, dist) or None, optional
        Intrinsics of an earlier or imported calibration: the start for that camera.
    hold : sequence (n_cameras) of bool, optional
        Keep the ``given`` intrinsics of these cameras (only poses are refined).
    times : ndarray (n_cameras, n_views), optional
        Frame times (s) of cameras that are not synchronised (NaN where unknown); corners of a camera view are
        down-weighted by how far the board moved between its exposure and the instant's median time, and views
        where it moved more than ``SYNC_DROP_PX`` are dropped (:mod:`heartcv.calibration_checks`).
    folds : int
        k of the k-fold check of the uncertainties (views left out, refitted, reprojected); below 3 or with fewer
        than 2 k instants seen by two cameras: leave-one-group-out over what there is, none under 3 instants.
    progress : callable(str), optional
        Called with a line per stage and refinement round.
    weak_data_rules : bool
        Apply the rules for weak data: distortion terms by coverage and the principal point's prior. False
        estimates every requested parameter freely, as ``cv2.stereoCalibrate`` does (comparisons with OpenCV).

    Returns
    -------
    RigCalibration
        ``rig.meta`` (docs/formats.md, rig file): ``rms_px``, ``residual_sigma_px`` (sqrt of sigma^2 above,
        per coordinate), ``target`` (the target's dict), ``baselines_m``, ``dist_model``, ``solver``,
        ``solver_iterations``, ``solver_converged``, ``observations`` (corners), ``views_used`` (instants),
        ``view_names``, ``warnings``, ``heldout_rms_px``, ``uncertainty``, ``sync`` and ``cameras: {name:
        {rms_px, views_used, per_view_errors (list aligned with view_names, None where not used), rejected_views
        {view: px}, std {fx, fy, cx, cy, k1, ..., rotation_deg [3], translation_m [3]}, std_formal,
        intrinsics_only_rms_px, coverage, intrinsics {parameter: how it was obtained}, heldout_rms_px}}``.

    Raises
    ------
    CalibrationError
        The target is found in no image, or the ChArUco board in the images is not the target
        (:func:`heartcv.calibration.target_mismatch`, :func:`heartcv.calibration.polarity_mismatch`); a camera has
        fewer than ``min_views`` usable views (the message and ``views_per_camera`` give the count of every
        camera); cameras cannot be linked to camera 0.
    """
    say = progress or (lambda msg: None)
    names, view_names = _check_inputs(detections, spec, image_sizes, names, view_names, min_views)
    n_cam, n_views = len(detections), len(view_names)
    given = [None] * n_cam if given is None else list(given)
    hold = np.zeros(n_cam, bool) if hold is None else np.asarray(hold, bool)
    if len(given) != n_cam or hold.shape != (n_cam,) or any(h and g is None for h, g in zip(hold, given)):
        raise ValueError("given, hold: one entry per camera expected; a held camera needs given intrinsics")
    warnings = []
    # 1. coverage decides the distortion terms; single-camera calibrations give the start and the board poses
    coverage = np.array([image_coverage([d.uv for d in dets if usable_view(d, spec)], size)
                         for dets, size in zip(detections, image_sizes)])
    free_dist = np.stack([distortion_terms(cv if weak_data_rules else 1.0, dist_size) for cv in coverage])
    intr, full = [], []
    for c, (dets, size, n) in enumerate(zip(detections, image_sizes, names)):
        say(f"{n}: {'board poses with its given intrinsics held' if hold[c] else 'single-camera calibration'} "
            f"({int(sum(usable_view(d, spec) for d in dets))} views, coverage {100 * coverage[c]:.0f} %)")
        kw = dict(dist_size=dist_size, max_view_rms=max_view_rms, outlier_factor=outlier_factor,
                  min_views=min_views, name=n)
        if hold[c]:
            r = calibrate_intrinsics(dets, spec, size, held=given[c], **kw)
            intr.append(r)
            full.append(r)
            continue
        r_full = calibrate_intrinsics(dets, spec, size, start=given[c], **kw)
        full.append(r_full)
        if given[c] is not None:  # start from the given intrinsics: board poses with them
            r = calibrate_intrinsics(dets, spec, size, held=given[c], **kw)
        elif not free_dist[c].all():
            # the start of the joint refinement: what the coverage supports, principal point at the centre
            r = calibrate_intrinsics(dets, spec, size, free_dist=free_dist[c], fix_principal_point=True, **kw)
        else:
            r = r_full
        intr.append(r)
    used = np.stack([r.used for r in intr])
    view_rms = np.stack([r.per_view_rms for r in intr])
    cam_from_board = np.stack([r.cam_from_board for r in intr])
    cam_from_rig = _initial_cam_from_rig(cam_from_board, used, names)
    rig_from_board = np.full((n_views, 4, 4), np.nan)
    for v in range(n_views):  # board poses in the rig frame, from the camera that sees most corners of the view
        cams = [c for c in range(n_cam) if used[c, v]]
        if cams:
            c = max(cams, key=lambda c: len(detections[c][v]))
            rig_from_board[v] = invert_pose(cam_from_rig[c]) @ cam_from_board[c, v]
    x_intr = np.stack([np.r_[r.K[0, 0], r.K[1, 1], r.K[0, 2], r.K[1, 2], _dist_vector(r.dist, dist_size)]
                       for r in intr])

    # 2. what is estimated: held cameras nothing, the others focal lengths, principal point (weak prior at the
    #    image centre) and the distortion terms their coverage supports
    ni = 4 + dist_size
    free_intr = np.zeros((n_cam, ni), bool)
    for c in range(n_cam):
        if not hold[c]:
            free_intr[c, :4] = True
            free_intr[c, 4:] = free_dist[c]
            x_intr[c, 4:] = np.where(free_dist[c], x_intr[c, 4:], 0.0 if given[c] is None else x_intr[c, 4:])
    prior_mean = x_intr.copy()
    prior_sigma = np.full((n_cam, ni), np.inf)
    for c, (w, h) in enumerate(image_sizes):
        if not hold[c] and weak_data_rules:
            prior_mean[c, 2:4] = (w - 1) / 2, (h - 1) / 2
            prior_sigma[c, 2:4] = PP_PRIOR_FRACTION * w, PP_PRIOR_FRACTION * h
    decisions = _decisions(names, hold, given, free_intr, coverage, dist_size, np.isfinite(prior_sigma[:, 2]))
    consider = np.full((n_cam, ni), np.nan)  # distortion terms held for want of coverage: roughly known
    for c in range(n_cam):
        if not hold[c]:
            consider[c, 4:] = np.where(free_dist[c], np.nan, np.asarray(HELD_DIST_SIGMA[:dist_size]))
    for c, n in enumerate(names):
        fixed = [_DIST_NAMES[k] for k in range(dist_size) if not hold[c] and not free_dist[c, k]]
        if fixed:
            warnings.append(f"{n}: the corners cover {100 * coverage[c]:.0f} % of the image; distortion "
                            f"{', '.join(fixed)} not determined by the views: held at "
                            f"{'0' if given[c] is None else 'the given values'}")

    # 3. unsynchronised cameras: down-weight corners by the board's motion between the exposures, drop views
    weights_cv, sync = _sync(detections, used, times, names)
    if sync["dropped"]:
        warnings.append(f"{sync['dropped']} camera views dropped: the board moved more than {SYNC_DROP_PX:g} px "
                        f"between the cameras' exposures")
    used &= ~sync["drop_mask"]

    # 4. joint refinement, outlier views rejected, distortion checked monotonic inside the image
    for _ in range(4):  # a fold removes one radial term per camera and round
        ba, prob, vidx, used, view_rms = _refine(detections, used, spec, dist_size, x_intr, cam_from_rig,
                                                 rig_from_board, free_intr, prior_mean, prior_sigma, weights_cv,
                                                 view_rms, names, max_view_rms, outlier_factor, min_views,
                                                 max_rounds, say, consider)
        folded = []
        for c in range(n_cam):
            K = _K(ba.intrinsics[c])
            r_fold = distortion_fold(K, ba.intrinsics[c, 4:], image_sizes[c])
            if r_fold is not None and not hold[c]:
                # k1 alone is kept: a barrel lens fitted near the middle of its image is better described by k1
                # than by none (holding it at 0 moves the principal point instead); the fold is reported
                radial = [k for k in (7, 6, 5, 4, 1) if k < dist_size and free_intr[c, 4 + k]]
                if not radial:
                    warnings.append(f"{names[c]}: with k1 alone the distortion folds back inside the image (at "
                                    f"normalised radius {r_fold:.2f}): the model holds near the corners seen, not "
                                    f"in the image corners; add views with the board near the image corners")
                if radial:
                    k = radial[0]
                    free_intr[c, 4 + k] = False
                    consider[c, 4 + k] = HELD_DIST_SIGMA[k]
                    folded.append(c)
                    decisions[names[c]][_DIST_NAMES[k]] = "held at 0: the fitted distortion folded back inside " \
                                                          "the image"
                    warnings.append(f"{names[c]}: the fitted distortion folds back inside the image (at normalised "
                                    f"radius {r_fold:.2f}); {_DIST_NAMES[k]} held at 0")
            elif r_fold is not None:
                warnings.append(f"{names[c]}: the given distortion folds back inside the image (at normalised "
                                f"radius {r_fold:.2f})")
        if not folded:
            break
        x_intr = ba.intrinsics.copy()
        for c in folded:
            x_intr[c, 4:] = np.where(free_intr[c, 4:], x_intr[c, 4:], 0.0)
        cam_from_rig = ba.cam_from_rig
        rig_from_board = np.full((n_views, 4, 4), np.nan)
        rig_from_board[vidx >= 0] = ba.rig_from_board
    rig_from_board = np.full((n_views, 4, 4), np.nan)
    rig_from_board[vidx >= 0] = ba.rig_from_board
    free = np.r_[free_intr.ravel(), np.ones(6 * (n_cam - 1), bool)]

    # 5. uncertainty checked on views left out; weakly determined parameters named
    if folds >= 3:
        say("k-fold check of the uncertainties")
    check = _kfold(detections, used, spec, dist_size, ba, vidx, free, prior_mean, prior_sigma, weights_cv, folds)
    warnings += _weak_parameters(ba, names, image_sizes, free_intr, prior_sigma, dist_size)
    return _result(prob, ba, names, view_names, image_sizes, used, view_rms, full, spec, dist_size,
                   rig_from_board, warnings=warnings, coverage=coverage, decisions=decisions, check=check,
                   sync=sync)


def _K(p) -> np.ndarray:
    return np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])


def _dist_vector(d, dist_size) -> np.ndarray:
    out = np.zeros(dist_size)
    d = np.asarray(d, float).reshape(-1)
    out[:min(d.size, dist_size)] = d[:dist_size]
    return out


def _decisions(names, hold, given, free_intr, coverage, dist_size, pp_prior) -> dict:
    """Per camera and intrinsic parameter: how it was obtained (recorded in the rig file)."""
    out = {}
    for c, n in enumerate(names):
        d = {}
        for k, p in enumerate(("fx", "fy", "cx", "cy") + _DIST_NAMES[:dist_size]):
            if hold[c]:
                d[p] = "held at the given value"
            elif p in ("cx", "cy") and pp_prior[c]:
                d[p] = f"estimated, prior: image centre +- {100 * PP_PRIOR_FRACTION:g} % of the image side"
            elif free_intr[c, k]:
                d[p] = "estimated"
            else:
                d[p] = (f"held at {'0' if given[c] is None else 'the given value'}: coverage "
                        f"{100 * coverage[c]:.0f} % of the image")
        out[n] = d
    return out


def _sync(detections, used, times, names):
    """Observation weights per camera view (n_cam, n_views) and the sync summary (``drop_mask`` included)."""
    n_cam, n_views = used.shape
    weights = np.ones((n_cam, n_views))
    summary = {"times_given": times is not None, "dropped": 0, "downweighted": 0, "max_offset_s": 0.0,
               "max_displacement_px": 0.0, "drop_mask": np.zeros((n_cam, n_views), bool)}
    if times is None:
        return weights, summary
    times = np.asarray(times, float)
    if times.shape != (n_cam, n_views):
        raise ValueError(f"times: shape ({n_cam}, {n_views}) expected, got {times.shape}")
    ref = np.full(n_views, np.nan)
    seen = used & np.isfinite(times)
    for v in range(n_views):
        if seen[:, v].any():
            ref[v] = np.median(times[seen[:, v], v])
    for c in range(n_cam):
        uv = [d.uv if d is not None and len(d) else None for d in detections[c]]
        ids = [d.ids if d is not None and len(d) else None for d in detections[c]]
        disp = sync_displacement(uv, ids, times[c], ref)
        ok = used[c] & np.isfinite(disp)
        if ok.any():
            summary["max_displacement_px"] = max(summary["max_displacement_px"], float(disp[ok].max()))
        off = np.abs(times[c] - ref)[used[c] & np.isfinite(times[c]) & np.isfinite(ref)]
        if off.size:
            summary["max_offset_s"] = max(summary["max_offset_s"], float(off.max()))
        drop = ok & (disp > SYNC_DROP_PX)
        summary["drop_mask"][c] = drop
        w = np.where(ok, sync_weights(disp), 1.0)
        weights[c] = w
        summary["dropped"] += int(drop.sum())
        summary["downweighted"] += int((ok & ~drop & (w < 0.5)).sum())
    return weights, summary


def _refine(detections, used, spec, dist_size, x_intr, cam_from_rig, rig_from_board, free_intr, prior_mean,
            prior_sigma, weights_cv, view_rms, names, max_view_rms, outlier_factor, min_views, max_rounds, say,
            consider=None):
    """Joint refinement rounds with outlier camera views rejected (module docstring, step 4)."""
    n_cam, n_views = used.shape
    free = np.r_[free_intr.ravel(), np.ones(6 * (n_cam - 1), bool)]
    view_rms = view_rms.copy()
    for rnd in range(max_rounds):
        prob, vidx = _build_problem(detections, used, spec, dist_size, weights_cv)
        try:
            ba = bundle_adjust(prob, x_intr, cam_from_rig, rig_from_board[vidx >= 0], free=free,
                               prior_mean=prior_mean, prior_sigma=prior_sigma, consider_sigma=consider)
        except np.linalg.LinAlgError:
            raise CalibrationError("the joint refinement is degenerate (singular normal equations): the views do "
                                   "not constrain every camera; add views with the board tilted") from None
        x_intr, cam_from_rig = ba.intrinsics, ba.cam_from_rig
        rig_from_board = np.full((n_views, 4, 4), np.nan)
        rig_from_board[vidx >= 0] = ba.rig_from_board
        new_rms = _view_rms(prob, ba.residuals, used, vidx)
        view_rms = np.where(used, new_rms, view_rms)
        bad = np.stack([outlier_views(r, factor=outlier_factor, max_view_rms=max_view_rms) for r in new_rms])
        say(f"joint refinement round {rnd + 1}: RMS {np.sqrt((ba.residuals ** 2).sum(axis=1).mean()):.3f} px, "
            f"{ba.iterations} iterations, {int(bad.sum())} outlier camera views")
        if not bad.any():
            break
        used = used & ~bad
        left = dict(zip(names, used.sum(axis=1).tolist()))
        if min(left.values()) < min_views:
            raise CalibrationError("too few usable views after rejecting outlier views in the joint refinement: "
                                   + ", ".join(f"{n} {k}" for n, k in left.items())
                                   + f" (at least {min_views} per camera needed)", left)
        _check_linked(used, names)
    return ba, prob, vidx, used, view_rms


def _kfold(detections, used, spec, dist_size, ba, vidx, free, prior_mean, prior_sigma, weights_cv, folds):
    """k-fold check: refit without each group of instants, re-estimate the left-out board poses with the refit
    cameras held, and reproject. Returns ``heldout_rms_px`` (overall and per camera), the jackknife standard
    deviation of the camera parameters and the number of folds used (or why none)."""
    n_cam, n_views = used.shape
    shared = np.flatnonzero(used.sum(axis=0) >= 1)
    k = min(int(folds), shared.size // 2)
    if k < 3 <= min(int(folds), shared.size):
        k = min(int(folds), shared.size)  # 3 to 5 instants: leave one out rather than no check at all
    out = {"folds": 0, "heldout_rms_px": None, "heldout_rms_px_per_camera": [None] * n_cam, "jackknife": None}
    if int(folds) < 3:
        out["skipped"] = f"folds = {int(folds)}: no k-fold check asked for (at least 3 folds make one)"
        return out
    if k < 3:
        out["skipped"] = f"{shared.size} views: too few for a k-fold check (at least 3 needed)"
        return out
    group = np.empty(n_views, int)
    group[shared] = np.arange(shared.size) % k
    est, sq, cnt = [], np.zeros(n_cam), np.zeros(n_cam)
    full = ba.intrinsics, ba.cam_from_rig
    rfb_full = np.full((n_views, 4, 4), np.nan)
    rfb_full[vidx >= 0] = ba.rig_from_board
    nc = free.size
    for g in range(k):
        out_views = np.zeros(n_views, bool)
        out_views[shared[group[shared] == g]] = True
        train = used & ~out_views[None]
        test = used & out_views[None]
        if (train.sum(axis=1) < 3).any() or not _linked(train):
            continue
        prob, vi = _build_problem(detections, train, spec, dist_size, weights_cv)
        try:
            fit = bundle_adjust(prob, full[0], full[1], rfb_full[vi >= 0], free=free, prior_mean=prior_mean,
                                prior_sigma=prior_sigma, max_iterations=30)
            tprob, tvi = _build_problem(detections, test, spec, dist_size, weights_cv)
            pose = bundle_adjust(tprob, fit.intrinsics, fit.cam_from_rig, rfb_full[tvi >= 0],
                                 free=np.zeros(nc, bool), max_iterations=30)
        except np.linalg.LinAlgError:
            continue
        e2 = (pose.residuals ** 2).sum(axis=1)
        sq += np.bincount(tprob.obs_cam, e2, n_cam)
        cnt += np.bincount(tprob.obs_cam, minlength=n_cam)
        est.append(_camera_vector(fit))
    if len(est) < 3:
        out["skipped"] = "fewer than 3 folds kept every camera linked"
        return out
    out["folds"] = len(est)
    out["heldout_rms_px"] = float(np.sqrt(sq.sum() / max(cnt.sum(), 1)))
    out["heldout_rms_px_per_camera"] = [float(np.sqrt(a / b)) if b else None for a, b in zip(sq, cnt)]
    out["jackknife"] = _jackknife(np.stack(est), _camera_vector(ba), ba.intrinsics.size)
    return out


def _camera_vector(ba) -> np.ndarray:
    """Camera parameters as one vector: intrinsics, then per camera 1.. the rotation vector of
    ``R R_ref^T`` about the reference (filled in by :func:`_jackknife`) and the translation."""
    return np.concatenate([ba.intrinsics.ravel()] + [np.r_[T[:3, :3].ravel(), T[:3, 3]] for T in ba.cam_from_rig[1:]])


def _jackknife(est, ref, n_intr) -> np.ndarray:
    """Jackknife standard deviations of :func:`_camera_vector` rows (k, n) in the layout of
    ``BundleResult.cov_cameras``: the first ``n_intr`` entries as they are, then per camera its rotation as the
    rotation vector of ``R R_ref^T`` (rad, a left increment about the full fit's, as the covariance has it) and
    its translation."""
    import cv2

    n_pose = (ref.size - n_intr) // 12
    rows = []
    for e in est:
        parts = [e[:n_intr]]
        for c in range(n_pose):
            o = n_intr + 12 * c
            R, Rr = e[o:o + 9].reshape(3, 3), ref[o:o + 9].reshape(3, 3)
            parts += [cv2.Rodrigues(R @ Rr.T)[0].ravel(), e[o + 9:o + 12]]
        rows.append(np.concatenate(parts))
    return jackknife_std(np.stack(rows))


def _weak_parameters(ba, names, image_sizes, free_intr, prior_sigma, dist_size) -> list:
    """Warnings for estimated intrinsics the views determine poorly: a principal point whose uncertainty is
    over half its prior's (the prior, not the views, placed it), a focal length uncertain by more than 2 %, and
    pairs of parameters correlated beyond 0.99."""
    out = []
    ni = 4 + dist_size
    cov = ba.cov_cameras
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    labels = [f"{n}.{p}" for n in names for p in ("fx", "fy", "cx", "cy") + _DIST_NAMES[:dist_size]]
    labels += [f"{n}.{p}" for n in names[1:] for p in ("rx", "ry", "rz", "tx", "ty", "tz")]
    for c, n in enumerate(names):
        o = c * ni
        for k, p in ((2, "cx"), (3, "cy")):
            if free_intr[c, k] and sd[o + k] > 0.5 * prior_sigma[c, k]:
                out.append(f"{n}: {p} weakly determined by the views (+-{sd[o + k]:.1f} px; the prior at the image "
                           f"centre, +-{prior_sigma[c, k]:.0f} px, holds it)")
        for k, p in ((0, "fx"), (1, "fy")):
            if free_intr[c, k] and sd[o + k] > 0.02 * ba.intrinsics[c, k]:
                out.append(f"{n}: {p} weakly determined by the views (+-{sd[o + k]:.1f} px, "
                           f"{100 * sd[o + k] / ba.intrinsics[c, k]:.1f} %)")
    ok = sd > 0
    corr = np.zeros_like(cov)
    corr[np.ix_(ok, ok)] = cov[np.ix_(ok, ok)] / np.outer(sd[ok], sd[ok])
    named = set()
    for c, n in enumerate(names):
        for k in range(ni):
            i = c * ni + k
            if not ok[i]:
                continue
            row = np.abs(corr[i])
            row[i] = 0
            j = int(np.argmax(row))
            if row[j] > 0.99 and frozenset((i, j)) not in named \
                    and (j > i or not (j < len(labels) and labels[j].startswith(n + "."))):
                named.add(frozenset((i, j)))
                out.append(f"{labels[i]} and {labels[j]} are not told apart by the views (correlation "
                           f"{corr[i, j]:+.3f}): their values trade off")
    return out


def _linked(used) -> bool:
    try:
        _check_linked(used, [str(i) for i in range(used.shape[0])])
    except CalibrationError:
        return False
    return True


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
    polarity = polarity_mismatch(detections, spec)
    if polarity:
        raise CalibrationError(f"the target ({describe_target(spec)}) does not match the board in the images: "
                               f"{polarity}", dict.fromkeys(names, 0))
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


def _build_problem(detections, used, spec, dist_size, weights_cv=None):
    """The observations of the used camera views; views renumbered densely (``vidx``: -1 if unused);
    ``weights_cv`` (n_cam, n_views): the weight of every corner of a camera view (default 1)."""
    n_cam, n_views = used.shape
    views = np.flatnonzero(used.any(axis=0))
    vidx = np.full(n_views, -1)
    vidx[views] = np.arange(views.size)
    obj = spec.object_points()
    oc, ov, X, uv, w = [], [], [], [], []
    for c in range(n_cam):
        for v in np.flatnonzero(used[c]):
            d = detections[c][v]
            w.append(np.full(len(d), 1.0 if weights_cv is None else float(weights_cv[c, v])))
            oc.append(np.full(len(d), c))
            ov.append(np.full(len(d), vidx[v]))
            X.append(obj[d.ids])
            uv.append(d.uv)
    prob = RigProblem(np.concatenate(oc), np.concatenate(ov), np.concatenate(X), np.concatenate(uv), n_cam,
                      views.size, dist_size, np.concatenate(w))
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


def _result(prob, ba, names, view_names, image_sizes, used, view_rms, intr, spec, dist_size, rig_from_board, *,
            warnings, coverage, decisions, check, sync):
    n_cam, ni = len(names), prob.ni
    formal = np.sqrt(np.clip(np.diag(ba.cov_cameras), 0, None))
    e2 = (ba.residuals ** 2).sum(axis=1)
    rms = float(np.sqrt(e2.mean()))
    # uncertainty that holds: the formal std scaled by one factor, never below 1, from the k-fold check: the
    # held-out / fitted RMS and the median ratio of the jackknife spread to the formal std (a median over all
    # camera parameters: one noisy fold does not move it)
    scale, jk_ratio = 1.0, None
    if check["heldout_rms_px"] is not None and rms > 0:
        scale = max(scale, check["heldout_rms_px"] / rms)
    if check["jackknife"] is not None and (formal > 0).any():
        jk_ratio = float(np.median(check["jackknife"][formal > 0] / formal[formal > 0]))
        scale = max(scale, jk_ratio)
    std_all = scale * formal
    if check.get("skipped") and not check["skipped"].startswith("folds ="):
        warnings.append(f"no k-fold check ({check['skipped']}): the standard deviations are the formal ones, "
                        f"unchecked; on real views they are often 1.5 to 3 times too small")
    if scale > 1.5:
        warnings.append(f"the k-fold check (views left out: {check['heldout_rms_px']:.3f} px RMS against {rms:.3f} px "
                        f"fitted; jackknife / formal std {jk_ratio:.2f}) finds the formal standard deviations "
                        f"over-confident: they are scaled by {scale:.2f}")
    cameras, cam_meta = [], {}
    for c, n in enumerate(names):
        p = ba.intrinsics[c]
        cameras.append(Camera(n, *image_sizes[c], _K(p), p[4:], ba.cam_from_rig[c]))
        rejected = np.isfinite(view_rms[c]) & ~used[c]
        heldout = check["heldout_rms_px_per_camera"][c]
        cam_meta[n] = {
            "rms_px": float(np.sqrt(e2[prob.obs_cam == c].mean())),
            "views_used": int(used[c].sum()),
            "per_view_errors": [float(view_rms[c, v]) if used[c, v] else None for v in range(len(view_names))],
            "rejected_views": {view_names[v]: float(view_rms[c, v]) for v in np.flatnonzero(rejected)},
            "std": _std_dict(std_all, c, n_cam, ni),
            "std_formal": _std_dict(formal, c, n_cam, ni),
            "intrinsics_only_rms_px": float(intr[c].rms_px),
            "coverage": float(coverage[c]),
            "intrinsics": decisions[n],
        }
        if heldout is not None:
            cam_meta[n]["heldout_rms_px"] = heldout
    inconsistent = [f"{n} {cam_meta[n]['rms_px']:.2f} px against {cam_meta[n]['intrinsics_only_rms_px']:.2f} px"
                    for n in names if cam_meta[n]["rms_px"] > CONSISTENCY_RATIO * cam_meta[n]["intrinsics_only_rms_px"]]
    if inconsistent:
        warnings.append(f"the cameras disagree about the board's pose at the same instant: the joint RMS is more than "
                        f"{CONSISTENCY_RATIO:g} x the RMS of each camera calibrated alone ({', '.join(inconsistent)}); "
                        f"exposures not simultaneous (unsynchronised cameras, rolling shutter) or a board that flexes "
                        f"while it moves. The standard deviations describe the spread of these views, not this "
                        f"systematic error: the intrinsics of a weakly covered camera may be off by several of them")
    rig = Rig(tuple(cameras))
    meta = {
        "rms_px": rms,
        "residual_sigma_px": float(np.sqrt(ba.sigma2)),
        "heldout_rms_px": check["heldout_rms_px"],
        "uncertainty": {"folds": check["folds"], "std_scale": scale, "jackknife_ratio": jk_ratio,
                        "method": "formal sigma^2 (J^T J)^-1 times max(1, held-out RMS / fitted RMS, median of "
                                  "k-fold jackknife std / formal std)"}
        | ({"skipped": check["skipped"]} if "skipped" in check else {}),
        "warnings": list(warnings),
        "sync": {k: v for k, v in sync.items() if k != "drop_mask"},
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


def _std_dict(std_all, c, n_cam, ni) -> dict:
    s = std_all[c * ni:(c + 1) * ni]
    sp = std_all[n_cam * ni + 6 * (c - 1):n_cam * ni + 6 * c] if c else np.zeros(6)
    std = {"fx": float(s[0]), "fy": float(s[1]), "cx": float(s[2]), "cy": float(s[3])}
    std.update(zip(_DIST_NAMES, map(float, s[4:])))
    std["rotation_deg"] = np.degrees(sp[:3]).tolist()
    std["translation_m"] = sp[3:].tolist()
    return std


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
