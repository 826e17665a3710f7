"""Temporal tracking of surface points in one view: pyramidal Lucas–Kanade against the point's reference
template, with a forward–backward check and photometric verification.

Every point is tracked from the image it was born in (its *template*), not from the previous frame, so errors
do not accumulate (no drift); the previous frame only supplies the starting guess. A track is accepted in a
frame when (1) LK converged, (2) tracking the result back to the template returns to the template position
within ``fb_max_px`` (Kalal et al., "Forward-backward error", ICPR 2010), and (3) the zero-mean NCC of the
template patch and the patch at the tracked position reaches ``min_ncc`` — a point hidden by an instrument
fails (2) or (3) and is reported missing, not wrong. Bouguet, "Pyramidal implementation of the Lucas Kanade
feature tracker", Intel 2000 (cv2.calcOpticalFlowPyrLK).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .features import ncc, sample_patches
from .matching import patch_offsets

__all__ = ["LKParams", "template_patches", "track_from_template"]


@dataclass(frozen=True)
class LKParams:
    """Lucas–Kanade settings: window side (px), pyramid levels above the image, iteration limits, checks."""

    window: int = 21
    levels: int = 3
    iterations: int = 30
    epsilon_px: float = 0.005
    fb_max_px: float = 0.3
    min_ncc: float = 0.85
    ncc_radius: int = 7

    def __post_init__(self):
        if self.window < 5 or self.window % 2 == 0:
            raise ValueError(f"window: an odd number >= 5 expected, got {self.window}")
        if not 0 <= self.levels <= 6:
            raise ValueError(f"levels: 0..6 expected, got {self.levels}")


def template_patches(gray, uv, params: LKParams) -> np.ndarray:
    """The NCC template of each point: samples (N, G) of ``gray`` around ``uv`` (N, 2)."""
    return sample_patches(np.asarray(gray, np.float32), uv, patch_offsets(params.ncc_radius))


def track_from_template(tmpl_gray, cur_gray, uv_tmpl, tmpl_patches, uv_init, params: LKParams):
    """Track points from their template image into the current image.

    Parameters
    ----------
    tmpl_gray, cur_gray : ndarray (H, W) uint8   the template image and the current image (OpenCV 5's Python
                                                 binding takes images, not prebuilt pyramids)
    uv_tmpl : ndarray (N, 2)               positions in the template image
    tmpl_patches : ndarray (N, G)          :func:`template_patches` of the points
    uv_init : ndarray (N, 2)               starting guesses in the current image (e.g. the last positions)

    Returns
    -------
    uv : ndarray (N, 2)      tracked positions (NaN where rejected)
    ok : ndarray (N,) bool
    fb_px : ndarray (N,)     forward-backward error (px)
    score : ndarray (N,)     NCC of template and tracked patch
    """
    import cv2

    n = len(uv_tmpl)
    if n == 0:
        z = np.zeros((0, 2))
        return z, np.zeros(0, bool), np.zeros(0), np.zeros(0)
    win = (params.window, params.window)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, params.iterations, params.epsilon_px)
    guess = np.where(np.isfinite(uv_init), uv_init, uv_tmpl)
    # both images cropped to the points' bounding box plus the reach of the coarsest pyramid level (the
    # pyramids are rebuilt on every call: cropping is what keeps this cheap)
    x0, y0, x1, y1 = _crop_box(np.concatenate([uv_tmpl, guess]), tmpl_gray.shape, params)
    off = np.array([x0, y0], np.float32)
    a = np.ascontiguousarray(tmpl_gray[y0:y1, x0:x1])
    b = np.ascontiguousarray(cur_gray[y0:y1, x0:x1])
    p0 = (np.asarray(uv_tmpl, np.float32) - off).reshape(-1, 1, 2)
    p1 = (np.asarray(guess, np.float32) - off).reshape(-1, 1, 2)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, p1, winSize=win, maxLevel=params.levels,
                                         criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    back = p0.copy()
    back, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, back, winSize=win, maxLevel=params.levels,
                                            criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    p0 = p0 + off
    p1 = p1 + off
    back = back + off
    uv = p1.reshape(-1, 2).astype(float)
    fb = np.linalg.norm(back.reshape(-1, 2) - p0.reshape(-1, 2), axis=1).astype(float)
    cur = sample_patches(np.asarray(cur_gray, np.float32), uv, patch_offsets(params.ncc_radius))
    score = ncc(tmpl_patches, cur).astype(float)
    ok = (st.ravel() == 1) & (st2.ravel() == 1) & np.isfinite(uv).all(axis=1) & (fb <= params.fb_max_px) \
        & (np.nan_to_num(score, nan=-1.0) >= params.min_ncc)
    uv[~ok] = np.nan
    return uv, ok, fb, score


def _crop_box(uv, shape, params: LKParams, motion_px=48):
    """Integer crop ``(x0, y0, x1, y1)`` holding every point with room for the LK window at the coarsest level
    and ``motion_px`` of motion."""
    H, W = shape[:2]
    pad = (params.window // 2 + 2) * 2 ** params.levels + motion_px
    finite = np.isfinite(uv).all(axis=1)
    if not finite.any():
        return 0, 0, W, H
    lo = np.floor(uv[finite].min(axis=0) - pad).astype(int)
    hi = np.ceil(uv[finite].max(axis=0) + pad).astype(int)
    return max(lo[0], 0), max(lo[1], 0), min(hi[0], W), min(hi[1], H)
