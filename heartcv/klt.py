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

__all__ = ["LKParams", "template_patches", "track_from_template", "TileSet", "cut_tiles", "tile_mosaics", "track_tiles",
           "flow_step", "expected_ncc", "LOST", "FORWARD_BACKWARD", "PHOTOMETRIC"]

# why a view was not accepted (the ``reason`` codes of :func:`track_tiles`)
ACCEPTED, LOST, FORWARD_BACKWARD, PHOTOMETRIC = 0, 1, 2, 3


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
    ncc_allowance: float | None = None
    refine_levels: int = 1
    search_px: int = 8

    def __post_init__(self):
        if self.window < 5 or self.window % 2 == 0:
            raise ValueError(f"window: an odd number >= 5 expected, got {self.window}")
        if not 0 <= self.levels <= 6:
            raise ValueError(f"levels: 0..6 expected, got {self.levels}")
        if not 0 <= self.refine_levels <= 3:
            raise ValueError(f"refine_levels: 0..3 expected, got {self.refine_levels}")
        if self.ncc_allowance is not None and not 0 <= self.ncc_allowance <= 2:
            raise ValueError(f"ncc_allowance: 0..2 expected, got {self.ncc_allowance}")

    @property
    def tile_half(self) -> int:
        """Half side of the tiles of :func:`track_tiles`: the LK window's reach at the coarsest refinement level
        plus ``search_px`` of motion away from the starting guess."""
        return (self.window // 2 + 2) * 2 ** self.refine_levels + self.search_px


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


# =====================================================================================================================
# Template tracking of many points with per-point templates: tiles packed into one mosaic per image
# =====================================================================================================================
@dataclass
class TileSet:
    """Per-point template tiles: ``tiles`` (N, S, S) uint8 crops of the template images, ``origin`` (N, 2) int
    the image position of each tile's top-left pixel, ``uv`` (N, 2) the point in the template image, ``patch``
    (N, G) its NCC template (:func:`template_patches`) and ``expected`` (N,) the NCC that image noise alone
    leaves between the template and a perfect match (:func:`expected_ncc`)."""

    tiles: np.ndarray
    origin: np.ndarray
    uv: np.ndarray
    patch: np.ndarray
    expected: np.ndarray


def expected_ncc(patch, noise_var) -> np.ndarray:
    """NCC (N,) of a template patch (N, G) with a perfect match, when both carry independent pixel noise of
    variance ``noise_var`` (grey levels^2): ``s / (s + noise_var)`` with ``s = var(patch) - noise_var`` the
    variance of the patch's signal (at least 0)."""
    v = np.nanvar(np.asarray(patch, np.float64), axis=-1)
    s = np.maximum(v - noise_var, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(v > 0, s / (s + noise_var), 0.0)


def cut_tiles(gray, uv, half) -> tuple[np.ndarray, np.ndarray]:
    """Square crops (N, 2 half + 1, 2 half + 1) of ``gray`` centred on the pixels nearest ``uv`` (N, 2) (the
    border replicated outside the image) and their top-left positions (N, 2) int."""
    import cv2

    gray = np.ascontiguousarray(gray)
    uv = np.asarray(uv, float).reshape(-1, 2)
    S = 2 * half + 1
    origin = np.rint(np.nan_to_num(uv, nan=0.0)).astype(np.int64) - half
    H, W = gray.shape[:2]
    padded = cv2.copyMakeBorder(gray, S, S, S, S, cv2.BORDER_REPLICATE)
    o = np.clip(origin + S, 0, [W + S, H + S])           # far outside: the replicated border's edge
    windows = np.lib.stride_tricks.sliding_window_view(padded, (S, S))
    return windows[o[:, 1], o[:, 0]], origin


def _mosaic(tiles) -> tuple[np.ndarray, np.ndarray]:
    """Tiles (N, S, S) packed into one image (rows of ``ceil(sqrt(N))`` tiles) and each tile's top-left position
    (N, 2) in it (x, y)."""
    N, S = tiles.shape[0], tiles.shape[1]
    cols = int(np.ceil(np.sqrt(N)))
    rows = int(np.ceil(N / cols))
    pad = rows * cols - N
    t = np.concatenate([tiles, np.zeros((pad, S, S), tiles.dtype)]) if pad else tiles
    img = t.reshape(rows, cols, S, S).transpose(0, 2, 1, 3).reshape(rows * S, cols * S)
    k = np.arange(N)
    return np.ascontiguousarray(img), np.stack([(k % cols) * S, (k // cols) * S], axis=1).astype(np.float64)


def tile_mosaics(templates: TileSet, cur_gray, uv_init, half):
    """The two mosaics of :func:`track_tiles`: the template tiles (A) and the tiles of ``cur_gray`` around the
    starting guesses (B; the template position where a guess is NaN), each tile's top-left position in them (N, 2),
    the current tiles' image origins (N, 2), and the points' positions in A (template) and B (guess) as LK takes
    them (float32 (N, 1, 2))."""
    init = np.where(np.isfinite(uv_init), uv_init, templates.uv)
    cur_tiles, cur_origin = cut_tiles(cur_gray, init, half)
    A, pos = _mosaic(templates.tiles)
    B, _ = _mosaic(cur_tiles)
    p0 = (pos + templates.uv - templates.origin).astype(np.float32).reshape(-1, 1, 2)
    p1 = (pos + init - cur_origin).astype(np.float32).reshape(-1, 1, 2)
    return A, B, pos, cur_origin, p0, p1


def track_tiles(templates: TileSet, cur_gray, uv_init, params: LKParams, *, ncc_floor: float = 0.5):
    """Track points from their own template tiles into the current image, all in one Lucas–Kanade call.

    Each point's template tile and a tile of the current image around its starting guess are packed into two
    mosaics (:func:`_mosaic`); pyramidal LK (``params.refine_levels`` levels) aligns each template to its current
    tile, and LK back from the result to the template gives the forward–backward error (Kalal et al., ICPR
    2010). The gates, in this order (a point's ``reason`` is the first it fails): ``LOST`` unless LK converged
    inside its tile; ``PHOTOMETRIC`` unless the NCC of its template patch with the patch at the result is at least
    ``max(ncc_floor, expected - ncc_allowance)``, ``expected`` the NCC that image noise alone leaves
    (:func:`expected_ncc`; without ``ncc_allowance`` the fixed ``params.min_ncc``); ``FORWARD_BACKWARD`` unless the
    LK back converged within ``params.fb_max_px`` of the template position. The LK back runs only on the points
    that passed the first two gates (LK treats every point on its own, so this changes no decision).

    Returns
    -------
    uv : ndarray (N, 2)       tracked positions (NaN where not accepted)
    reason : ndarray (N,) int ``ACCEPTED`` (0), ``LOST``, ``PHOTOMETRIC`` or ``FORWARD_BACKWARD``
    fb_px : ndarray (N,)      forward-backward error (NaN where the LK back did not run)
    score : ndarray (N,)      NCC of template and tracked patch
    """
    import cv2

    N = len(templates.uv)
    if N == 0:
        return np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    half = params.tile_half
    S = 2 * half + 1
    if templates.tiles.shape[1] != S:
        raise ValueError(f"templates: tiles of side {S} expected, got {templates.tiles.shape[1]}")
    A, B, pos, cur_origin, p0, p1 = tile_mosaics(templates, cur_gray, uv_init, half)
    win = (params.window, params.window)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, params.iterations, params.epsilon_px)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(A, B, p0, p1.copy(), winSize=win, maxLevel=params.refine_levels,
                                         criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    local = p1.reshape(-1, 2).astype(float) - pos
    uv = local + cur_origin
    margin = params.window / 2
    inside = np.isfinite(local).all(axis=1) & (local >= margin).all(axis=1) & (local <= S - 1 - margin).all(axis=1)
    cur = sample_patches(np.asarray(cur_gray, np.float32), uv, patch_offsets(params.ncc_radius))
    score = np.nan_to_num(ncc(templates.patch, cur).astype(float), nan=-1.0)
    if params.ncc_allowance is None:
        gate = np.full(N, params.min_ncc)
    else:
        gate = np.maximum(ncc_floor, templates.expected - params.ncc_allowance)
    reason = np.full(N, ACCEPTED, np.int64)
    reason[(st.ravel() != 1) | ~inside | ~np.isfinite(score)] = LOST
    reason[(reason == ACCEPTED) & (score < gate)] = PHOTOMETRIC
    fb = np.full(N, np.nan)
    back_of = np.flatnonzero(reason == ACCEPTED)
    if back_of.size:
        q0, q1 = p0[back_of], p1[back_of]
        back, st2, _ = cv2.calcOpticalFlowPyrLK(B, A, q1, q0.copy(), winSize=win, maxLevel=params.refine_levels,
                                                criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        fb[back_of] = np.linalg.norm(back.reshape(-1, 2).astype(float) - q0.reshape(-1, 2), axis=1)
        fb[back_of[st2.ravel() != 1]] = np.nan
    reason[(reason == ACCEPTED) & ~(fb <= params.fb_max_px)] = FORWARD_BACKWARD
    uv[reason != ACCEPTED] = np.nan
    return uv, reason, fb, score


def flow_step(prev_gray, cur_gray, uv_prev, params: LKParams) -> np.ndarray:
    """Frame-to-frame pyramidal LK of points ``uv_prev`` (N, 2) from the previous image to the current one (the
    starting guesses of :func:`track_tiles`); NaN where LK lost a point."""
    import cv2

    n = len(uv_prev)
    if n == 0:
        return np.zeros((0, 2))
    x0, y0, x1, y1 = _crop_box(uv_prev, prev_gray.shape, params)
    off = np.array([x0, y0], np.float32)
    a = np.ascontiguousarray(prev_gray[y0:y1, x0:x1])
    b = np.ascontiguousarray(cur_gray[y0:y1, x0:x1])
    p0 = (np.asarray(uv_prev, np.float32) - off).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, params.iterations, params.epsilon_px)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None, winSize=(params.window, params.window),
                                         maxLevel=params.levels, criteria=crit)
    uv = p1.reshape(-1, 2).astype(float) + off
    uv[st.ravel() != 1] = np.nan
    return uv
