"""What the views of a calibration can determine, and how far to trust the result.

Pure functions on arrays, used by :mod:`heartcv.calibration_rig`:

* :func:`image_coverage` -- the fraction of the image that the board's corners cover (union of the convex hulls of
  the corners of every view) and how far from the principal point they reach;
* :func:`distortion_terms` -- the distortion coefficients that coverage supports (module constants below);
* :func:`distortion_fold` -- where the radial distortion stops being monotonic inside the image (a camera that
  maps two directions onto one pixel is not physical);
* :func:`sync_displacement` -- for cameras that are not synchronised, how far (px) the board moved between a
  camera's exposure and the instant's reference time, from the corners' image speed in the neighbouring frames of
  the same camera;
* :func:`jackknife_std` -- the delete-a-group jackknife spread of estimates from k-fold refits.

The rules are general (no constant depends on one recording); docs/cli.md §8 (weakly determined parameters) gives
their reasons.
"""

from __future__ import annotations

import numpy as np

__all__ = ["image_coverage", "coverage_mask", "distortion_terms", "distortion_fold", "sync_displacement",
           "sync_weights", "jackknife_std", "CONSISTENCY_RATIO", "HELD_DIST_SIGMA", "COVERAGE_FULL", "COVERAGE_K2",
           "SYNC_DROP_PX", "SYNC_SIGMA_PX", "PP_PRIOR_FRACTION"]

# coverage (fraction of the image area under the corners) needed for ...
COVERAGE_K2 = 0.20    # ... k2 and the tangential terms (below it: k1 only)
COVERAGE_FULL = 0.50  # ... k3 and the rational terms (the model asked for)
PP_PRIOR_FRACTION = 0.10  # principal point prior: image centre, sigma = 10 % of the image side
SYNC_SIGMA_PX = 0.5   # a corner that moved d px between exposures gets weight 1 / (1 + (d / SYNC_SIGMA_PX)^2)
SYNC_DROP_PX = 5.0    # camera views whose board moved more than this (median over corners) are dropped
# spread of the distortion terms that coverage holds at 0 (k1 k2 p1 p2 k3 k4 k5 k6), used for the "consider"
# covariance of the others: the terms of real lenses (webcams, endoscopes, machine-vision lenses) seldom pass
# |k2|, |k3| ~ 0.3 or |p| ~ 0.005 when k1 is fitted (OpenCV's sample cameras, caliscope's, Kalibr's examples)
HELD_DIST_SIGMA = (0.0, 0.15, 0.003, 0.003, 0.15, 0.15, 0.15, 0.15)
# a camera whose RMS in the joint refinement passes this multiple of its RMS calibrated alone (its own board poses)
# is told that the cameras disagree about the board's pose at each instant (consistent cameras: ratio 1.0-1.3)
CONSISTENCY_RATIO = 2.0
COVERAGE_GRID = 256   # coverage is counted on a grid of at most this many cells along the longer side


def image_coverage(uv_views, image_size) -> float:
    """Fraction of the image area inside the union of the convex hulls of the corners of each view, counted on a
    grid of at most ``COVERAGE_GRID`` cells along the longer side (:func:`coverage_mask`)."""
    return coverage_mask(uv_views, image_size, COVERAGE_GRID)[0]


def coverage_mask(uv_views, image_size, max_side) -> tuple[float, np.ndarray]:
    """Union of the convex hulls of point sets (one per view; fewer than 3 points cover nothing), rasterised.

    Parameters
    ----------
    uv_views : iterable of ndarray (n_i, 2)
        Pixels (OpenCV convention: pixel ``(0, 0)`` is the centre of the top-left pixel).
    image_size : (int, int)
        ``(width, height)``.
    max_side : int
        The mask's longer side at most (the image is scaled down to it, never up).

    Returns
    -------
    fraction : float in [0, 1]
    mask : ndarray (h, w), bool
    """
    import cv2

    w, h = image_size
    s = min(1.0, max_side / max(w, h))
    mask = np.zeros((max(1, round(h * s)), max(1, round(w * s))), np.uint8)
    for uv in uv_views:
        uv = np.asarray(uv, float).reshape(-1, 2)
        uv = uv[np.isfinite(uv).all(axis=1)]
        if len(uv) < 3:
            continue
        hull = cv2.convexHull(np.round(((uv + 0.5) * s - 0.5) * 16).astype(np.int32))  # 1/16 px: shift=4
        cv2.fillConvexPoly(mask, hull, 1, lineType=cv2.LINE_8, shift=4)
    return float(mask.mean()), mask.astype(bool)


def distortion_terms(coverage: float, dist_size: int) -> np.ndarray:
    """Mask (dist_size,) of the distortion coefficients (OpenCV order k1 k2 p1 p2 k3 k4 k5 k6) that corners
    covering ``coverage`` of the image can determine: k1 always; k2, p1, p2 from ``COVERAGE_K2``; k3 and the
    rational terms from ``COVERAGE_FULL``. Higher-order terms extrapolate wildly beyond the corners (a k3 fitted
    to the middle tenth of an image folds the distortion back inside it), and the tangential terms trade off
    against the principal point when the corners cover a small patch."""
    free = np.zeros(dist_size, bool)
    free[0] = True
    if coverage >= COVERAGE_K2:
        free[1:4] = True
    if coverage >= COVERAGE_FULL:
        free[:] = True
    return free


def _radial(dist, r):
    d = np.zeros(8)
    d[:min(8, len(dist))] = np.asarray(dist, float)[:8]
    k1, k2, _, _, k3, k4, k5, k6 = d
    r2 = r * r
    return r * (1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3) / (1 + k4 * r2 + k5 * r2 ** 2 + k6 * r2 ** 3)


def distortion_fold(K, dist, image_size, n=2000) -> float | None:
    """The smallest undistorted radius (normalised) inside the image at which the radial distortion
    ``r_d(r)`` stops increasing (or its denominator vanishes), or None if it is monotonic up to the image
    corner farthest from the principal point."""
    K = np.asarray(K, float)
    w, h = image_size
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    xy = (corners - K[:2, 2]) / np.diag(K)[:2]
    r_img = float(np.linalg.norm(xy, axis=1).max())
    # the distorted radius must reach the image corner: follow r until r_d passes r_img or stops increasing
    r = np.linspace(0, 3 * r_img, n)
    rd = _radial(dist, r)
    ok = np.isfinite(rd)
    drd = np.diff(rd)
    for i in range(1, n):
        if not ok[i] or drd[i - 1] <= 0:
            return float(r[i - 1]) if rd[i - 1] < r_img else None
        if rd[i] >= r_img:
            return None
    return float(r[-1])


def sync_displacement(uv_by_view, ids_by_view, times, ref_times) -> np.ndarray:
    """Median displacement (px) of a camera's corners between its exposure and the instant's reference time.

    Parameters
    ----------
    uv_by_view, ids_by_view : sequences (n_views) of ndarray or None
        The camera's corners per view (pixels, ids); None where it did not see the board.
    times : ndarray (n_views,)
        The camera's frame times (s); NaN where unknown.
    ref_times : ndarray (n_views,)
        Reference time per instant (the median of the cameras' frame times).

    Returns
    -------
    ndarray (n_views,)
        ``|v| |t - t_ref|`` with ``v`` the median image speed (px/s) of the corners shared with the previous and
        next frames of the same camera (the mean of the two where both exist); 0 where ``t == t_ref``; NaN where
        the speed is unknown (no neighbouring frame shows a shared corner) and the offset is not zero.
    """
    n = len(uv_by_view)
    times = np.asarray(times, float)
    out = np.full(n, np.nan)
    for v in range(n):
        dt = abs(times[v] - ref_times[v])
        if not np.isfinite(dt):
            continue
        if dt == 0:
            out[v] = 0.0
            continue
        if uv_by_view[v] is None or len(uv_by_view[v]) == 0:
            continue
        speeds = []
        for w in (v - 1, v + 1):
            if not (0 <= w < n) or uv_by_view[w] is None or len(uv_by_view[w]) == 0:
                continue
            gap = abs(times[w] - times[v])
            if not np.isfinite(gap) or gap <= 0:
                continue
            _, ia, ib = np.intersect1d(ids_by_view[v], ids_by_view[w], return_indices=True)
            if ia.size:
                speeds.append(float(np.median(np.linalg.norm(uv_by_view[w][ib] - uv_by_view[v][ia], axis=1))) / gap)
        if speeds:
            out[v] = float(np.mean(speeds)) * dt
    return out


def sync_weights(displacement) -> np.ndarray:
    """Observation weights from :func:`sync_displacement` (unknown displacement: weight 1)."""
    d = np.nan_to_num(np.asarray(displacement, float), nan=0.0)
    return 1.0 / (1.0 + (d / SYNC_SIGMA_PX) ** 2)


def jackknife_std(estimates) -> np.ndarray:
    """Delete-a-group jackknife standard deviation from k refits (k, p), each leaving out one group of views:
    ``sqrt((k - 1) / k * sum_i (x_i - mean)^2)`` (Efron & Stein; for k equal groups it estimates the standard
    deviation of the estimate from all the data)."""
    x = np.asarray(estimates, float)
    k = x.shape[0]
    if k < 2:
        return np.full(x.shape[1:], np.nan)
    return np.sqrt((k - 1) / k * ((x - x.mean(axis=0)) ** 2).sum(axis=0))
