"""Feature detection on the heart surface: region of interest, evenly spread corners, patch sampling and NCC.

Corners are Shi–Tomasi corners (the smaller eigenvalue of the structure tensor, Shi & Tomasi, "Good features to
track", CVPR 1994) picked per grid cell so that they cover the whole region, not only its most textured part
(the bucketing of ORB-SLAM and of most visual-odometry front ends). Images are 8-bit gray (H, W) arrays; pixel
coordinates follow OpenCV (the centre of the top-left pixel is (0, 0)).
"""

from __future__ import annotations

import numpy as np

__all__ = ["region_of_interest", "moving_mask", "detect_corners", "sample_patches", "ncc", "saturation_mask",
           "texture_strength"]


def texture_strength(gray, window=15) -> np.ndarray:
    """Local standard deviation (float32, grey levels) of the high-pass image ``gray - blur(gray)`` over a
    ``window``-pixel box: large on speckled tissue, small on flat background and on blur."""
    import cv2

    g = np.asarray(gray, np.float32)
    hp = g - cv2.GaussianBlur(g, (0, 0), 2.0)
    m2 = cv2.boxFilter(hp * hp, -1, (window, window))
    m1 = cv2.boxFilter(hp, -1, (window, window))
    return np.sqrt(np.maximum(m2 - m1 * m1, 0.0))


def saturation_mask(gray, level=250, grow=0) -> np.ndarray:
    """Pixels at or above ``level`` (specular highlights, clipped), dilated by ``grow`` pixels (bool (H, W))."""
    import cv2

    m = (np.asarray(gray) >= level).astype(np.uint8)
    if grow > 0 and m.any():
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1, 2 * grow + 1)))
    return m.astype(bool)


class RegionNotFound(ValueError):
    """:func:`region_of_interest` found no (or too little) textured surface: a failed result, not a bug."""


def region_of_interest(frames, *, margin=12, texture_factor=3.0, motion_px=0.5, min_area=2000):
    """The moving, textured surface seen in the first frames of one camera.

    Parameters
    ----------
    frames : sequence of ndarray (H, W) uint8
        The first frames of one camera (at least one; motion is used when there are two or more).
    margin : int
        Erode the region by this many pixels, so that patches around its points stay on the surface.
    texture_factor : float
        A pixel is textured where :func:`texture_strength` exceeds this multiple of its median over the
        background (the darker Otsu class of the first frame), which measures the image noise.
    motion_px : float
        Keep only the part of the textured region that moves, if a moving part is found: pixels whose
        brightness changes over the frames by more than the noise would explain (in grey levels, scaled by
        the local gradient so that ``motion_px`` is roughly a displacement in pixels).
    min_area : int
        Fewer pixels than this: ValueError.

    Returns
    -------
    mask : ndarray (H, W) bool
        The largest connected component of the textured (and, if seen, moving) bright region.
    info : dict
        ``moving`` (whether motion was used), ``area_px``.
    """
    import cv2

    frames = [np.asarray(f) for f in frames]
    if not frames or frames[0].ndim != 2:
        raise ValueError("frames: at least one gray image (H, W) expected")
    g0 = frames[0]
    blur = cv2.GaussianBlur(g0, (0, 0), 3.0)
    thr, bright = cv2.threshold(blur, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    bright = bright.astype(bool)
    tex = texture_strength(g0)
    noise = float(np.median(tex[~bright])) if (~bright).sum() > 100 else float(np.percentile(tex, 5))
    textured = bright & (tex > texture_factor * max(noise, 0.5))
    region = textured
    moving_used = False
    if len(frames) >= 2:
        moving = moving_mask(frames, noise, motion_px=motion_px)
        if (textured & moving).sum() >= max(min_area, 0.05 * textured.sum()):
            region = textured & moving
            moving_used = True
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (15, 15))
    region = cv2.morphologyEx(region.astype(np.uint8), cv2.MORPH_CLOSE, k)
    region = cv2.morphologyEx(region, cv2.MORPH_OPEN, k)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(region, connectivity=8)
    if n <= 1:
        raise RegionNotFound("region of interest: no textured surface found in the first frames")
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    mask = (labels == best).astype(np.uint8)
    # fill holes (highlights, fiducial dots) so that the region is one piece of surface
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    mask = cv2.drawContours(np.zeros_like(mask), contours, -1, 1, thickness=cv2.FILLED)
    if margin > 0:
        mask = cv2.erode(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1)))
    mask = mask.astype(bool)
    if mask.sum() < min_area:
        raise RegionNotFound(f"region of interest: only {int(mask.sum())} px of textured surface found "
                             f"(at least {min_area} expected)")
    return mask, {"moving": moving_used, "area_px": int(mask.sum())}


def moving_mask(frames, noise, *, motion_px=0.5, close_px=31) -> np.ndarray:
    """Pixels (H, W) bool whose brightness changes over ``frames`` (gray, 2 or more) by more than the noise
    (``noise``, grey levels) and a motion of ``motion_px`` pixels at the local gradient would explain, closed over
    ``close_px`` (the moving surface as one piece)."""
    import cv2

    stack = np.stack([cv2.GaussianBlur(f, (0, 0), 2.0).astype(np.float32) for f in frames])
    change = stack.max(axis=0) - stack.min(axis=0)
    gx = cv2.Sobel(stack[0], cv2.CV_32F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(stack[0], cv2.CV_32F, 0, 1, ksize=3) / 8
    grad = cv2.GaussianBlur(np.sqrt(gx * gx + gy * gy), (0, 0), 6.0)
    moving = change > motion_px * grad + 4.0 * max(noise, 0.5)
    return cv2.morphologyEx(moving.astype(np.uint8), cv2.MORPH_CLOSE,
                            cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (close_px, close_px))).astype(bool)


def detect_corners(gray, mask=None, *, max_points=400, min_distance=15, block_size=7, quality=0.02,
                   exclude=None, backend=None) -> tuple[np.ndarray, np.ndarray]:
    """Shi–Tomasi corners spread evenly over ``mask``.

    The region is cut into square cells whose number is about ``max_points``; each cell contributes its
    strongest local maximum of the minimum-eigenvalue response (above ``quality`` times the strongest response
    in the region); candidates closer than ``min_distance`` to a stronger one are dropped.

    Parameters
    ----------
    gray : ndarray (H, W) uint8
    mask : ndarray (H, W) bool, optional
        Where corners may lie (default: everywhere).
    exclude : ndarray (M, 2), optional
        Existing points: no new corner within ``min_distance`` of them.
    backend : heartcv.backend backend, optional
        Computes the corner response (default: ``cv2.cornerMinEigenVal``).

    Returns
    -------
    uv : ndarray (N, 2) float64
        Corner positions (integer pixel centres), strongest first.
    response : ndarray (N,)
    """
    import cv2

    g = np.asarray(gray)
    if g.ndim != 2:
        raise ValueError(f"gray: (H, W) image expected, got shape {g.shape}")
    H, W = g.shape
    m = np.ones((H, W), bool) if mask is None else np.asarray(mask, bool)
    if m.shape != (H, W):
        raise ValueError(f"mask: shape {(H, W)} expected, got {m.shape}")
    resp = cv2.cornerMinEigenVal(g, block_size, ksize=3) if backend is None else \
        np.asarray(backend.corner_response(g, block_size), np.float32)
    local_max = resp >= cv2.dilate(resp, np.ones((5, 5), np.uint8))
    valid = m & local_max & (resp > 0)
    if not valid.any():
        return np.zeros((0, 2)), np.zeros(0)
    vmax = float(resp[m].max())
    valid &= resp >= quality * vmax
    ys, xs = np.nonzero(valid)
    r = resp[ys, xs]
    area = float(m.sum())
    cell = max(min_distance, int(np.sqrt(area / max(max_points, 1))))
    cell_id = (ys // cell) * (W // cell + 1) + xs // cell
    order = np.lexsort((-r, cell_id))
    first = np.r_[True, cell_id[order][1:] != cell_id[order][:-1]]
    pick = order[first]
    pick = pick[np.argsort(-r[pick])]
    cand = np.stack([xs[pick], ys[pick]], axis=1).astype(float)
    kept = _suppress(cand, min_distance, exclude)
    cand, rr = cand[kept][:max_points], r[pick][kept][:max_points]
    return cand, rr


def _suppress(points, radius, exclude=None) -> np.ndarray:
    """Greedy non-maximum suppression of ``points`` (sorted strongest first): indices kept."""
    from scipy.spatial import cKDTree

    occupied = [] if exclude is None or len(exclude) == 0 else [np.asarray(exclude, float)]
    kept = []
    tree_ex = cKDTree(occupied[0]) if occupied else None
    taken = np.zeros(len(points), bool)
    if len(points) == 0:
        return np.zeros(0, int)
    tree = cKDTree(points)
    for i in range(len(points)):
        if taken[i]:
            continue
        if tree_ex is not None and tree_ex.query_ball_point(points[i], radius, return_length=True) > 0:
            taken[i] = True
            continue
        kept.append(i)
        for j in tree.query_ball_point(points[i], radius):
            taken[j] = True
    return np.array(kept, int)


def sample_patches(image, uv, offsets) -> np.ndarray:
    """Bilinear samples of ``image`` at ``uv[..., None, :] + offsets`` (float32 (..., G)); outside: NaN.

    Parameters
    ----------
    image : ndarray (H, W)
    uv : ndarray (..., 2)           patch centres (pixels)
    offsets : ndarray (G, 2)        sample offsets (pixels)
    """
    pts = np.asarray(uv, np.float64)[..., None, :] + np.asarray(offsets, np.float64)
    return sample_at(image, pts)


def sample_at(image, pts) -> np.ndarray:
    """Bilinear samples (float32 (...)) of ``image`` at pixel positions ``pts`` (..., 2); NaN where a sample
    needs a pixel outside the image (``cv2.remap`` with a NaN constant border: the valid domain is
    [0, W - 1) x [0, H - 1), since a sample exactly on the last column or row weighs the border by zero)."""
    import cv2

    pts = np.asarray(pts, np.float32)
    shape = pts.shape[:-1]
    n = int(np.prod(shape))
    if n == 0:
        return np.empty(shape, np.float32)
    cols = shape[-1] if len(shape) >= 2 and shape[-1] <= 4096 else 1
    flat = pts.reshape(-1, cols, 2)
    img = np.asarray(image, np.float32)
    rows = 30000                                   # cv2.remap: output sides below 32767
    out = np.empty(flat.shape[:2], np.float32)
    for a in range(0, flat.shape[0], rows):
        blk = flat[a:a + rows]
        out[a:a + rows] = cv2.remap(img, np.ascontiguousarray(blk[..., 0]), np.ascontiguousarray(blk[..., 1]),
                                    cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return out.reshape(shape)


def ncc(a, b, axis=-1, min_std=1e-3) -> np.ndarray:
    """Zero-mean normalised cross-correlation of ``a`` and ``b`` along ``axis`` (in [-1, 1]); NaN where a patch
    has a NaN sample, 0 where either patch is flat (standard deviation below ``min_std``)."""
    a = np.asarray(a, np.float32)
    b = np.asarray(b, np.float32)
    a = a - a.mean(axis=axis, keepdims=True)
    b = b - b.mean(axis=axis, keepdims=True)
    sa = np.sqrt((a * a).sum(axis=axis))
    sb = np.sqrt((b * b).sum(axis=axis))
    num = (a * b).sum(axis=axis)
    n = a.shape[axis]
    den = sa * sb
    flat = (sa < min_std * np.sqrt(n)) | (sb < min_std * np.sqrt(n))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(flat, 0.0, num / np.where(den > 0, den, 1.0))
    return out.astype(np.float32)
