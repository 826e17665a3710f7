"""Single-camera calibration from target detections, and the pieces the rig calibration shares.

:func:`calibrate_intrinsics` runs ``cv2.calibrateCameraExtended`` [1]_ on the usable views of one camera, rejects
outlier views (:func:`outlier_views`) and calibrates again until none is left. The rig calibration
(:mod:`heartcv.calibration_rig`) starts from its results.

Conventions. Reprojection RMS is OpenCV's: ``sqrt(mean over corners of |uv_measured - uv_projected|^2)`` in
pixels (one number per corner, not per coordinate). Distortion models: 5 coefficients ``(k1, k2, p1, p2, k3)``
(the default), 8 (rational: ``+ k4, k5, k6``) or 4 (``k3 = 0``: the models of COLMAP's ``OPENCV`` camera and
Kalibr's ``radtan``); skew is fixed at 0. Poses follow docs/design.md §3 (``cam_from_board``:
``x_cam = R x_board + t``, metres).

References
----------
.. [1] Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000; OpenCV
   ``calibrateCameraExtended``.
"""

from __future__ import annotations

from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from .detect import Detection

__all__ = ["CalibrationError", "IntrinsicsResult", "calibrate_intrinsics", "outlier_views", "usable_view",
           "describe_target", "target_mismatch", "polarity_mismatch", "ViewSelection", "select_views",
           "DIST_MODELS", "MIN_VIEWS", "OUTLIER_FACTOR", "OUTLIER_FLOOR_PX", "opencv_threads"]

DIST_MODELS = (4, 5, 8)  # (k1, k2, p1, p2) [COLMAP OPENCV, Kalibr radtan], + k3, + rational k4..k6
MIN_VIEWS = 4            # usable views needed per camera
OUTLIER_FACTOR = 3.0     # a view is an outlier above OUTLIER_FACTOR x the median view RMS of its camera ...
OUTLIER_FLOOR_PX = 0.25  # ... but never below this RMS (clean data keep their slightly worse views)
MIN_CHARUCO_CORNERS = 6


class CalibrationError(ValueError):
    """An expected failure of a calibration (too few views, target not found, cameras not linked).

    Attributes
    ----------
    views_per_camera : dict or None
        Camera name -> number of usable views, when the failure is about counts.
    """

    def __init__(self, message, views_per_camera=None):
        super().__init__(message)
        self.views_per_camera = views_per_camera


@dataclass(frozen=True)
class IntrinsicsResult:
    """One camera's intrinsic calibration.

    Attributes
    ----------
    K : ndarray of shape (3, 3)
    dist : ndarray of shape (5,) or (8,)
    rms_px : float
        RMS over the corners of the views used.
    per_view_rms : ndarray of shape (n_views,)
        RMS of every view in the last calibration it took part in (rejected views: the calibration that
        rejected them); NaN for views that were never usable.
    used : ndarray of shape (n_views,), bool
    rejected : ndarray of shape (n_views,), bool
        Usable views dropped as outliers.
    cam_from_board : ndarray of shape (n_views, 4, 4)
        Board pose of the views used; NaN elsewhere.
    std : ndarray of shape (4 + n_dist,)
        Standard deviations of ``(fx, fy, cx, cy, dist...)`` (OpenCV's stdDeviationsIntrinsics).
    """

    K: np.ndarray
    dist: np.ndarray
    rms_px: float
    per_view_rms: np.ndarray
    used: np.ndarray
    rejected: np.ndarray
    cam_from_board: np.ndarray
    std: np.ndarray


@dataclass(frozen=True)
class ViewSelection:
    """The views a calibration uses (:func:`select_views`).

    Attributes
    ----------
    detections : list
        Per camera, per view: the Detection, or None where the image was missing, unreadable or of an odd size.
    sizes : list
        Per camera its image size (width, height): the most common one of its readable images; None if none.
    used : list of (int, int)
        (camera, view) of the images used, sorted.
    warnings : list of str
        Images left out (unreadable, odd size: named) and cameras none of whose images could be read.
    counts : list of (int, int)
        Per camera: images read, and views whose image shows the target.
    """

    detections: list
    sizes: list
    used: list
    warnings: list
    counts: list


def select_views(results: dict, camera_names, view_names) -> ViewSelection:
    """Drop unreadable images and images whose size differs from the rest of their camera.

    Parameters
    ----------
    results : dict of {(camera, view): (size, detection)}
        Per image read: ``size`` (width, height) and its Detection, or ``(None, message)`` for an image that could
        not be read (the message names it).
    camera_names, view_names : sequence of str
    """
    detections, sizes, used, warnings, counts = [], [], [], [], []
    for c, cam in enumerate(camera_names):
        mine = {v: r for (cc, v), r in results.items() if cc == c}
        warnings += [f"skipped: {r[1]}" for _, r in sorted(mine.items()) if r[0] is None]
        ok_sizes = Counter(r[0] for r in mine.values() if r[0] is not None)
        if not ok_sizes:
            warnings.append(f"{cam}: none of its {len(mine)} images could be read")
        size = ok_sizes.most_common(1)[0][0] if ok_sizes else None
        warnings += [f"skipped: {cam}/{view_names[v]}: image is {r[0][0]}x{r[0][1]} px, the camera's other images "
                     f"are {size[0]}x{size[1]} px" for v, r in sorted(mine.items()) if r[0] not in (None, size)]
        dets = [None] * len(view_names)
        for v, r in sorted(mine.items()):
            if size is not None and r[0] == size:
                dets[v] = r[1]
                used.append((c, v))
        detections.append(dets)
        sizes.append(size)
        counts.append((len(mine), sum(d is not None and len(d) > 0 for d in dets)))
    return ViewSelection(detections, sizes, used, warnings, counts)


def usable_view(det: Detection | None, spec) -> bool:
    """Whether a detection can take part in a calibration: a complete chessboard, or at least
    ``MIN_CHARUCO_CORNERS`` ChArUco corners that do not lie on one line."""
    if det is None or len(det) == 0:
        return False
    if spec.type == "chessboard":
        return len(det) == spec.n_corners
    if len(det) < MIN_CHARUCO_CORNERS:
        return False
    xy = spec.object_points()[det.ids, :2]
    s = np.linalg.svd(xy - xy.mean(axis=0), compute_uv=False)
    return bool(s[1] > 0.5 * spec.square_m)


def describe_target(spec) -> str:
    """``'charuco with squares 11x8, DICT_5X5_250'`` or ``'chessboard with inner corners 9x6'``."""
    if spec.type == "chessboard":
        return f"chessboard with inner corners {spec.squares[0]}x{spec.squares[1]}"
    return (f"charuco with squares {spec.squares[0]}x{spec.squares[1]}, {spec.dictionary}"
            + (", legacy pattern" if spec.legacy else "") + (", inverted" if spec.inverted else ""))


def polarity_mismatch(detections, spec) -> str | None:
    """Why the target's colours do not match the printed board, or None.

    The board's markers are looked for in the negative of every image where none was found
    (``Detection.other_polarity_markers``); when more images show at least 4 of them that way than show the
    target as described, the board is printed with the other polarity.
    """
    if spec.type != "charuco":
        return None
    dets = [d for d in _flatten(detections) if d is not None]
    other = sum(d.other_polarity_markers >= 4 for d in dets)
    seen = sum(d.markers >= 4 for d in dets)
    if other == 0 or other <= seen:
        return None
    if spec.inverted:
        return (f"the board's markers were found in {other} images with black markers on white squares (and in "
                f"{seen} as the target describes them, white on black): the board is not inverted; make the target "
                f"without --inverted")
    return (f"the board's markers were found in {other} images only with black and white swapped (and in {seen} as "
            f"the target describes them): the board is printed inverted, white markers on black squares; make the "
            f"target with `heartcv target ... --inverted`")


def target_mismatch(detections, spec) -> str | None:
    """Why the ChArUco board in the images is not the target ``spec``, or None (chessboards: None).

    A ChArUco board whose layout differs from the target's is often still detected, in part, with corners that
    fit it (a board with more or fewer rows than the target shares its first rows). Three signs give it away
    over the images where at least 4 of the target's markers were found:

    * in at least half of them, markers of the dictionary that the target does not have (the board in the
      images is larger, or another board is in view);
    * fewer than half of the corners that the markers found promise (``Detection.corners_expected``) were
      found (the layout differs: number of squares, legacy pattern);
    * over all images, no corner of the target's first or last row or column (the board is smaller).

    Parameters
    ----------
    detections : iterable of Detection or None (any nesting of lists)
    spec : heartcv.targets.TargetSpec
    """
    if spec.type != "charuco":
        return None
    dets = [d for d in _flatten(detections) if d is not None]
    seen = [d for d in dets if d.markers >= 4]
    foreign = sum(d.foreign_markers > 0 for d in seen)
    if foreign and 2 * foreign >= len(seen):
        return (f"markers that the target does not have were found in {foreign} of the {len(seen)} images that "
                f"show the target: the board in the images is larger than the target, or another board is in view")
    found, expected = sum(len(d) for d in seen), sum(d.corners_expected for d in seen)
    if expected and 2 * found < expected:
        return (f"the markers found promise {expected} corners but {found} were found: the board's layout is not "
                f"the target's (number of squares, legacy pattern)")
    ids = np.unique(np.concatenate([d.ids for d in dets] + [np.zeros(0, np.int64)]))
    if ids.size:
        nx, ny = spec.inner_size
        rows, cols = set((ids // nx).tolist()), set((ids % nx).tolist())
        missing = [name for name, ok in (("first row", 0 in rows), ("last row", ny - 1 in rows),
                                         ("first column", 0 in cols), ("last column", nx - 1 in cols)) if not ok]
        if missing:
            return (f"no image shows a corner of the target's {' or '.join(missing)} of corners: the board in the "
                    f"images is smaller than the target, or that part of the board is out of view in every image")
    return None


def _flatten(x):
    for item in x:
        if item is None or isinstance(item, Detection):
            yield item
        else:
            yield from _flatten(item)


def outlier_views(rms, *, factor=OUTLIER_FACTOR, floor_px=OUTLIER_FLOOR_PX, max_view_rms=None) -> np.ndarray:
    """Mask of outlier views among view RMS values (n,): above ``max(factor * median, floor_px)``, or above
    ``max_view_rms`` when given. NaN entries are never outliers."""
    rms = np.asarray(rms, float)
    ok = np.isfinite(rms)
    if not ok.any():
        return np.zeros(rms.shape, bool)
    thr = max(factor * float(np.median(rms[ok])), floor_px)
    if max_view_rms is not None:
        thr = min(thr, float(max_view_rms))
    return ok & (np.where(ok, rms, 0) > thr)


def _flags(dist_size):
    import cv2

    if dist_size not in DIST_MODELS:
        raise ValueError(f"dist_size: one of {DIST_MODELS} expected, got {dist_size!r}")
    return {4: cv2.CALIB_FIX_K3, 5: 0, 8: cv2.CALIB_RATIONAL_MODEL}[dist_size]


_FIX_FLAGS = ("CALIB_FIX_K1", "CALIB_FIX_K2", None, None, "CALIB_FIX_K3", "CALIB_FIX_K4", "CALIB_FIX_K5",
              "CALIB_FIX_K6")


@contextmanager
def opencv_threads(n: int):
    """Run the block with OpenCV's thread count at ``n`` (process-wide; restored after). ``cv2.calibrateCameraExtended``
    with several threads is not reproducible: on the rendered phantom's calibration views two runs' k3 differed in
    the 8th digit, and the later stages carried that on (two ``make demo`` runs: GE prediction error 0.01513 and
    0.01496 mm). With one thread the rig file is identical run to run."""
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(int(n))
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def _cv_calibrate(obj, img, image_size, dist_size, free_dist=None, fix_principal_point=False, start=None):
    import cv2

    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    flags = _flags(dist_size)
    K0, d0 = None, None
    if free_dist is not None:
        for k, name in enumerate(_FIX_FLAGS[:dist_size]):
            if not free_dist[k] and name is not None:
                flags |= getattr(cv2, name)
        if not (free_dist[2] and free_dist[3]):
            flags |= cv2.CALIB_ZERO_TANGENT_DIST
    if fix_principal_point:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    if start is not None or fix_principal_point:
        w, h = image_size
        K0 = np.array([[max(w, h), 0, (w - 1) / 2], [0, max(w, h), (h - 1) / 2], [0, 0, 1.0]])
        d0 = np.zeros(max(dist_size, 5))
        if start is not None:
            K0, d = np.array(start[0], float), np.asarray(start[1], float)
            d0[:min(d.size, d0.size)] = d[:d0.size]
        if free_dist is not None:  # fixed terms are fixed at 0 unless a start gives them
            d0[:dist_size] = np.where(free_dist | (start is not None), d0[:dist_size], 0.0)
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    with opencv_threads(1):   # OpenCV's threads sum the views in a varying order: results then differ run to run
        out = cv2.calibrateCameraExtended(obj, img, tuple(int(v) for v in image_size), K0, d0,
                                          flags=flags, criteria=crit)
    rms, K, dist, rvecs, tvecs, std_in, _, per_view = out
    return (float(rms), np.asarray(K, float), np.asarray(dist, float).reshape(-1)[:dist_size], rvecs, tvecs,
            np.asarray(std_in, float).reshape(-1), np.asarray(per_view, float).reshape(-1))


def calibrate_intrinsics(detections, spec, image_size, *, dist_size=5, max_view_rms=None,
                         outlier_factor=OUTLIER_FACTOR, min_views=MIN_VIEWS, name="camera", free_dist=None,
                         fix_principal_point=False, start=None, held=None) -> IntrinsicsResult:
    """Intrinsics of one camera from its detections, with outlier views rejected.

    Parameters
    ----------
    detections : sequence of Detection or None, length n_views
    spec : heartcv.targets.TargetSpec
    image_size : (int, int)
        ``(width, height)`` in pixels.
    dist_size : {4, 5, 8}
        Distortion model (module docstring).
    max_view_rms : float, optional
        Views with a larger RMS (px) are rejected whatever the median.
    outlier_factor : float
        Views above ``max(outlier_factor * median, OUTLIER_FLOOR_PX)`` are rejected, and the camera is
        calibrated again, until no view is rejected.
    min_views : int
        Fewer usable views (before or after rejection) raise :class:`CalibrationError`.
    free_dist : ndarray of shape (dist_size,), bool, optional
        Distortion coefficients estimated; the others stay at 0 (or at ``start``). Default: all.
    fix_principal_point : bool
        Keep the principal point at the image centre (or at ``start``).
    start : (K, dist), optional
        Start values (OpenCV's ``CALIB_USE_INTRINSIC_GUESS``).
    held : (K, dist), optional
        Intrinsics known and kept: only the board poses are estimated (``cv2.solvePnP`` per view, then
        outlier views rejected); ``std`` is zero.

    Returns
    -------
    IntrinsicsResult
    """
    import cv2

    n_views = len(detections)
    usable = np.array([usable_view(d, spec) for d in detections], bool)
    if usable.sum() < min_views:
        raise CalibrationError(f"{name}: {int(usable.sum())} usable views, at least {min_views} needed",
                               {name: int(usable.sum())})
    obj_all = spec.object_points().astype(np.float32)
    used = usable.copy()
    rejected = np.zeros(n_views, bool)
    per_view = np.full(n_views, np.nan)
    for _ in range(10):
        idx = np.flatnonzero(used)
        obj = [obj_all[detections[i].ids] for i in idx]
        img = [detections[i].uv.astype(np.float32) for i in idx]
        if held is not None:
            rms, K, dist, rvecs, tvecs, std_in, pv = _pnp_views(obj, img, held, dist_size)
        else:
            rms, K, dist, rvecs, tvecs, std_in, pv = _cv_calibrate(obj, img, image_size, dist_size, free_dist,
                                                                   fix_principal_point, start)
        per_view[idx] = pv
        bad = outlier_views(pv, factor=outlier_factor, max_view_rms=max_view_rms)
        if not bad.any():
            break
        rejected[idx[bad]] = True
        used[idx[bad]] = False
        if used.sum() < min_views:
            raise CalibrationError(
                f"{name}: {int(used.sum())} usable views left after rejecting {int(rejected.sum())} outlier "
                f"views (RMS above the threshold), at least {min_views} needed", {name: int(used.sum())})
    poses = np.full((n_views, 4, 4), np.nan)
    for k, i in enumerate(idx):
        poses[i] = np.eye(4)
        poses[i, :3, :3] = cv2.Rodrigues(np.asarray(rvecs[k], float))[0]
        poses[i, :3, 3] = np.asarray(tvecs[k], float).reshape(3)
    std = np.concatenate([std_in[:4], std_in[4:4 + dist_size]])
    return IntrinsicsResult(K, dist, rms, per_view, used, rejected, poses, std)


def _pnp_views(obj, img, held, dist_size):
    """``_cv_calibrate``'s outputs with the intrinsics ``held`` = (K, dist): board poses by ``cv2.solvePnP``
    (iterative, from the IPPE solution for planar targets)."""
    import cv2

    K = np.array(held[0], float)
    d = np.zeros(dist_size)
    given = np.asarray(held[1], float).reshape(-1)
    d[:min(given.size, dist_size)] = given[:dist_size]
    rvecs, tvecs, per_view, sq, n = [], [], [], 0.0, 0
    for o, uv in zip(obj, img):
        o = np.asarray(o, np.float64)
        uv = np.asarray(uv, np.float64)
        _, rv, tv = cv2.solvePnP(o, uv, K, d, flags=cv2.SOLVEPNP_IPPE)
        _, rv, tv = cv2.solvePnP(o, uv, K, d, rv, tv, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        e = cv2.projectPoints(o, rv, tv, K, d)[0].reshape(-1, 2) - uv
        e2 = (e ** 2).sum(axis=1)
        per_view.append(float(np.sqrt(e2.mean())))
        sq, n = sq + float(e2.sum()), n + len(e2)
        rvecs.append(rv)
        tvecs.append(tv)
    return (float(np.sqrt(sq / max(n, 1))), K, d, rvecs, tvecs, np.zeros(4 + dist_size), np.array(per_view))
