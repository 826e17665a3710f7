"""From calibrated multi-camera image sequences to tracked 3-D surface points with covariances.

The pipeline of ``heartcv measure`` (docs/cli.md), frame by frame:

1. *Region of interest*: given, or :func:`auto_region` of the reference camera's first frames (the tissue, without
   dark borders, highlights, instruments and untextured parts, and its moving part when one is seen).
2. *Reference detection*: Shi–Tomasi corners spread over the region (grid buckets), away from this frame's
   highlights and (colour frames) near-neutral instrument pixels, matched in every other camera by the trinocular
   plane sweep (:mod:`heartcv.matching`) with a noise-adaptive NCC gate.
3. *Temporal tracking* (:mod:`heartcv.klt`): frame-to-frame pyramidal LK gives each view's starting guess; the
   view is then aligned to its birth template and, where that fails, to its key template (the last frame where it
   was aligned to its birth template), all points of a camera in one LK call on a mosaic of per-point tiles;
   forward–backward, noise-adaptive NCC and per-frame highlight gates. A key is never more than one alignment
   from the birth template, so tracks do not drift.
4. *Triangulation* of the accepted views of each point (:func:`heartcv.triangulation.triangulate`: linear, then
   Gauss–Newton on the reprojection error, worst view dropped while it exceeds ``outlier_px``); points with a
   poor reprojection RMS, or whose predicted depth standard deviation exceeds ``max_depth_std_ratio`` of the
   depth, are missing in that frame. Every gate counts what it removed (:data:`GATES`, ``Measurer.rejected``).
5. *Re-detection*: when fewer than ``refill_fraction * max_points`` points are seen (checked at most every
   ``respawn_interval`` frames), new corners are detected in the free parts of the region and matched; they
   start new tracks (new ids). A track unseen for more than ``max_gap_frames`` frames ends; until then it is
   predicted from its neighbours' motion and searched for in every frame (it resumes after an occlusion).
6. *Covariances*: the pixel noise sigma is estimated from the reprojection residuals of all accepted
   observations (pooled, ``sum r^2 / sum (2 n_views - 3)``) unless given, and propagated through the
   triangulation Jacobian: ``C = sigma^2 (sum_c J_c^T J_c)^-1`` (Hartley & Zisserman §5.2).

Positions are in the rig frame (camera 0's frame unless the rig file says otherwise), metres. A point's
reference position is its position in the frame it was born in.

:func:`measure_sequence` is the one frame loop over a whole sequence (``heartcv measure`` and
``benchmarks/measure.py`` call it): it takes the images from an iterator, so it opens no file. Failures on valid
input raise :class:`MeasureFailed`; input that cannot be used raises :class:`heartcv.tracker.files.InputError`.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace
import math
import time

import numpy as np

from .backend import OpenCVBackend
from .camera import Camera
from .features import detect_corners, moving_mask, saturation_mask
from .klt import (
    ACCEPTED,
    FORWARD_BACKWARD,
    LOST,
    PHOTOMETRIC,
    LKParams,
    TileSet,
    cut_tiles,
    expected_ncc,
    flow_step,
    template_patches,
    track_tiles,
)
from .matching import match_points
from .tissue import TissueNotFound, neutral_mask, noise_sigma, specular_mask, tissue_region
from .tracker.files import InputError
from .triangulation import triangulate

__all__ = ["MeasureOptions", "SHARP_BLUR_PX", "texture_blur_px", "auto_size_factor",
           "MIN_REDUCED_SIDE_PX", "REDUCTION_STEP", "auto_reduction", "reduced_size", "reduce_image", "reduce_mask",
           "reduced_camera", "field_image", "field_camera", "WorkingView", "COMBING_RATIO", "combing_ratio",
           "frames_combing_ratio", "auto_field", "bob_field", "FieldInstants", "field_order", "field_order_clear",
           "MeasureResult", "Highlights",
           "Measurer", "MeasureFailed", "FrameStats", "SequenceRun",
           "ROI_FRAMES", "GATES", "emptied_by", "reference_frames", "auto_region", "measure_sequence", "run_frames",
           "assemble_result", "REPEAT_LEVEL", "REPEAT_SHARE", "REPEAT_RELATIVE", "REPEAT_HISTORY", "REPEAT_UNCHANGED",
           "changed_share", "unchanged_share", "RepeatedViews"]

# Frames of the reference camera from which the automatic region of interest is computed (every third of the
# first 30: the surface moves enough between them to tell it from the static background)
ROI_FRAMES = range(0, 30, 3)


class MeasureFailed(RuntimeError):
    """The measurement failed on valid input: no textured surface for the region of interest, or no point could
    be tracked. The command line reports it as a failed stage (exit 1), not as bad input."""


@dataclass(frozen=True)
class MeasureOptions:
    """Settings of :class:`Measurer` (docs/cli.md, measure). Fields left at None follow the reference camera's
    image size (:meth:`for_image`): the values below are those of a 1080-row image and shrink with the image's
    smaller side down to a floor (a feature needs a few pixels whatever the image)."""

    ref_camera: int = 0
    max_points: int = 300
    min_distance_px: float | None = None        # 15 px at 1080 rows, at least 5
    corner_block_size: int | None = None        # 7 px at 1080 rows, at least 3
    corner_quality: float = 0.01
    refill_fraction: float = 0.8
    saturation_level: int = 250
    match_min_ncc: float | None = None          # fixed NCC gate of the matching (None: adaptive)
    match_ncc_allowance: float = 0.15
    track_ncc_allowance: float = 0.25
    ncc_floor: float = 0.5
    respawn_interval: int = 1
    match_radius: int | None = None             # 7 px at 1080 rows, at least 4
    lk: LKParams | None = None                  # None: from the fields below and the image size
    window_px: int | None = None                # LK window: 21 px at 1080 rows, at least 11 (odd)
    fb_max_px: float = 1.0
    track_min_ncc: float | None = None          # fixed NCC gate of the tracking (None: adaptive)
    key_interval: int = 1
    highpass_sigma: float | None = 3.0
    max_reprojection_px: float = 1.0
    outlier_px: float = 1.0
    min_angle_deg: float = 0.0
    max_depth_std_ratio: float = 0.05
    max_gap_frames: int = 60
    specular: bool = True
    pixel_sigma: float | None = None
    min_pixel_sigma: float = 0.01
    size_factor: float = 1.0                    # every pixel size and threshold above times this (blurry video)

    def __post_init__(self):
        if self.max_points < 1:
            raise ValueError(f"max_points: at least 1 expected, got {self.max_points}")
        if not (math.isfinite(self.size_factor) and self.size_factor > 0):
            raise ValueError(f"size_factor: a positive number expected, got {self.size_factor}")
        if not 0 < self.refill_fraction <= 1:
            raise ValueError(f"refill_fraction: in (0, 1] expected, got {self.refill_fraction}")
        if self.pixel_sigma is not None and not self.pixel_sigma > 0:
            raise ValueError(f"pixel_sigma: positive expected, got {self.pixel_sigma}")
        for name in ("respawn_interval", "key_interval", "max_gap_frames"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: at least 1 expected, got {getattr(self, name)}")
        if not self.max_depth_std_ratio > 0:
            raise ValueError(f"max_depth_std_ratio: positive expected, got {self.max_depth_std_ratio}")

    def for_image(self, width: int, height: int) -> "MeasureOptions":
        """These options with every size left at None set from the image size: with ``s = min(1, min(width,
        height) / 1080)``, the least corner distance ``max(5, 15 s)`` px, the corner block ``max(3, 7 s)``, the NCC
        patch radius ``max(4, 7 s)`` and the LK window ``max(11, 21 s)`` (odd); 1080-row images get the sizes the
        paper's rig was tuned with (issue 5). Without ``lk``, the LK settings are built from ``window_px``,
        ``fb_max_px`` and the tracking NCC gate (``track_min_ncc``, else adaptive with ``track_ncc_allowance``).

        ``size_factor`` k (blurry or oversampled video, :func:`auto_size_factor`) multiplies every pixel size and
        threshold, given or from the rules above: corner distance, corner block and window (odd, rounded up),
        NCC radius (rounded), high-pass sigma, forward-backward, reprojection and outlier limits. An ``lk`` given
        whole is used as given. The result has ``size_factor`` 1 (applying it twice changes nothing more)."""
        s = min(1.0, min(width, height) / 1080.0)
        k = self.size_factor

        def odd(v):
            v = int(round(v))
            return v if v % 2 else v + 1

        def scaled_odd(v):                       # k v rounded up to an odd integer (v itself when k = 1)
            if k == 1.0:
                return v
            v = int(math.ceil(k * v - 1e-9))
            return v if v % 2 else v + 1

        radius = self.match_radius if self.match_radius is not None else max(4, int(round(7 * s)))
        radius = radius if k == 1.0 else int(round(k * radius))
        lk = self.lk
        if lk is None:
            window = scaled_odd(self.window_px if self.window_px is not None else max(11, odd(21 * s)))
            fixed = self.track_min_ncc is not None
            lk = LKParams(window=window, ncc_radius=radius, fb_max_px=k * self.fb_max_px,
                          min_ncc=self.track_min_ncc if fixed else LKParams.min_ncc,
                          ncc_allowance=None if fixed else self.track_ncc_allowance)
        return replace(
            self,
            min_distance_px=k * (self.min_distance_px if self.min_distance_px is not None else max(5.0, 15.0 * s)),
            corner_block_size=scaled_odd(self.corner_block_size if self.corner_block_size is not None
                                         else max(3, odd(7 * s))),
            match_radius=radius, lk=lk, fb_max_px=k * self.fb_max_px,
            highpass_sigma=None if self.highpass_sigma is None else k * self.highpass_sigma,
            max_reprojection_px=k * self.max_reprojection_px, outlier_px=k * self.outlier_px, size_factor=1.0)


SHARP_BLUR_PX = 1.0
"""The blurriest texture the sparse tracker's pixel sizes are meant for, as :func:`texture_blur_px` reads it (a
Gaussian blur of about 1.1 px). Measured in the automatic region of the first frames: the in-vivo heart (360 x
288) 0.80, the rendered phantoms (1920 x 1080) 0.89 and 0.91; the Hamlyn silicone phantom 0.55 over its image.
All are sharper and are tracked as they are (every default was chosen on them); blurrier video is tracked on
frames reduced until they read this sharp (:func:`auto_reduction`): the in-vivo frames upsampled 2x read 1.45 in
their automatic region, and 0.95 reduced 2.12x."""


def texture_blur_px(gray, mask=None) -> float:
    """The effective blur sigma (px) of an image's finest texture: ``sqrt(2 E|grad I|^2 / E(lap I)^2)`` over
    ``mask`` (default: the image without an eighth of each side). For a texture of white noise blurred by a
    Gaussian of sigma >= 2 px this is sigma (5 %; finer blur reads low, 0.85 at 1 px); upsampling an image by f
    multiplies it by f; pixel noise and sharper texture make it smaller. ``gray``: (H, W) or (H, W, 3) BGR."""
    import cv2

    g = np.asarray(_gray(gray), np.float64)
    gx = cv2.Sobel(g, cv2.CV_64F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(g, cv2.CV_64F, 0, 1, ksize=3) / 8.0
    lap = cv2.Laplacian(g, cv2.CV_64F, ksize=1)
    if mask is None:
        H, W = g.shape
        mask = np.zeros(g.shape, bool)
        mask[H // 8:H - H // 8, W // 8:W - W // 8] = True
    mask = np.asarray(mask, bool)
    grad, curv = float(np.mean(gx[mask] ** 2 + gy[mask] ** 2)), float(np.mean(lap[mask] ** 2))
    if not curv > 0:
        return math.inf if grad > 0 else math.nan
    return math.sqrt(2.0 * grad / curv)


def auto_size_factor(frames, mask=None) -> tuple[float, float]:
    """``(size_factor, blur)``: the median :func:`texture_blur_px` of ``frames`` (the reference camera's first
    frames) over ``mask``, and ``max(1, blur / SHARP_BLUR_PX)`` (1 where the blur is not finite: a flat image).
    ``measure --size-factor auto`` reduces the frames instead (:func:`auto_reduction`); this is the factor by which
    sizes would have to grow, kept for comparison."""
    blur = _median_blur(frames, mask)
    return (max(1.0, blur / SHARP_BLUR_PX) if math.isfinite(blur) else 1.0), blur


#: The smallest side (px) that :func:`auto_reduction` leaves an image (the in-vivo heart at half resolution, 180 x
#: 144 px, still gives 530 tracks; docs/cli.md §10.3).
MIN_REDUCED_SIDE_PX = 144
#: The step between the reductions :func:`auto_reduction` tries (each 10 % more than the last).
REDUCTION_STEP = 1.1
#: Frames that read at most this many times :data:`SHARP_BLUR_PX` are measured as they are: area averaging by a
#: factor near 1 adds about 0.15 px of its own blur, so a frame just over the line (the in-vivo right camera reads
#: 1.006) only reads sharp again at a factor of about 1.6, a cliff that threw away 38 % of the resolution (GE
#: 0.79x -> 0.87x hold on the mirrored in-vivo pair).
NEAR_SHARP = 1.25


def _median_blur(frames, mask=None) -> float:
    return float(np.median([texture_blur_px(f, mask) for f in frames])) if len(frames) else math.nan


def reduced_size(width: int, height: int, factor: float) -> tuple[int, int]:
    """The size ``(width, height)`` of an image reduced by ``factor`` (>= 1), each side rounded, at least 1."""
    return max(1, int(round(width / factor))), max(1, int(round(height / factor)))


def reduce_image(image, factor: float):
    """``image`` (H, W) or (H, W, 3) reduced by ``factor`` by area averaging (``cv2.INTER_AREA``; the image itself
    when the factor is 1)."""
    import cv2

    if factor == 1.0:
        return image
    h, w = image.shape[:2]
    return cv2.resize(image, reduced_size(w, h, factor), interpolation=cv2.INTER_AREA)


def reduce_mask(mask, factor: float) -> np.ndarray:
    """A boolean mask (H, W) reduced by ``factor``: a reduced pixel is in it when at least half its area is."""
    if factor == 1.0:
        return np.asarray(mask, bool)
    return reduce_image(np.asarray(mask, np.float32), factor) >= 0.5


def reduced_camera(camera: Camera, factor: float) -> Camera:
    """``camera`` as it sees images reduced by ``factor`` (:func:`reduce_image`): a pixel ``u`` of the full image
    is ``(u + 0.5) s - 0.5`` of the reduced one, with ``s`` the ratio of the reduced side to the full side per
    axis (pixel centres at integers); the distortion (of normalised coordinates) and the pose are unchanged."""
    w, h = reduced_size(camera.width, camera.height, factor)
    sx, sy = w / camera.width, h / camera.height
    K = np.array(camera.K, float)
    S = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    return replace(camera, width=w, height=h, K=S @ K)


def field_image(image, field: int) -> np.ndarray:
    """One field of an interlaced image (H, W) or (H, W, 3): its rows ``field``, ``field + 2``, ... (0: the first
    field, 1: the second)."""
    return np.ascontiguousarray(np.asarray(image)[field::2])


def field_camera(camera: Camera, field: int) -> Camera:
    """``camera`` as it sees one field of its images (:func:`field_image`): a pixel ``(u, v)`` of the full image
    is ``(u, (v - field) / 2)`` of the field (half the rows; the distortion and the pose unchanged)."""
    h = (camera.height - field + 1) // 2
    S = np.array([[1.0, 0.0, 0.0], [0.0, 0.5, -0.5 * field], [0.0, 0.0, 1.0]])
    return replace(camera, height=h, K=S @ np.array(camera.K, float))


COMBING_RATIO = 1.0
"""Frames whose :func:`combing_ratio` exceeds this look interlaced. White noise reads 1; progressive video less
(its texture is smooth over two rows): the in-vivo heart 0.27-0.28, with added noise of 6 grey levels 0.37-0.41,
the Hamlyn silicone phantom 0.45, the OpenCV stereo views 0.16-0.19, upsampled frames 0.09-0.12. Interlaced video
of a moving scene reads more where its two fields differ: the in-vivo heart woven from consecutive frames 0.6-3.0,
the scikit-surgery laparoscope's chessboard views (1920 x 1080, visibly combed) 0.6-6.3."""


def combing_ratio(image, mask=None) -> float:
    """How interlaced an image looks: the mean square of its rows' second difference to their neighbours
    ``I(y) - (I(y - 1) + I(y + 1)) / 2`` over the same two rows apart ``I(y) - (I(y - 2) + I(y + 2)) / 2``, over
    ``mask`` (default: the image without an eighth of each side). Two fields taken at different instants comb
    every edge that moved, which puts energy at the vertical Nyquist frequency (the ratio above 1); white noise
    reads 1 and smooth progressive texture less. NaN for a flat image."""
    g = np.asarray(_gray(image), np.float64)
    H, W = g.shape
    if H < 5:
        return math.nan
    d1 = g[2:-2] - 0.5 * (g[1:-3] + g[3:-1])
    d2 = g[2:-2] - 0.5 * (g[:-4] + g[4:])
    if mask is None:
        m = np.zeros(g.shape, bool)
        m[H // 8:H - H // 8, W // 8:W - W // 8] = True
    else:
        m = np.asarray(mask, bool)
    m = m[2:-2]
    den = float(np.mean(d2[m] ** 2)) if m.any() else 0.0
    return float(np.mean(d1[m] ** 2)) / den if den > 0 else math.nan


def frames_combing_ratio(frames, mask=None) -> float:
    """The median :func:`combing_ratio` of ``frames`` (the reference camera's first frames) over ``mask``, NaN
    where none is finite (no frame, flat frames)."""
    values = [v for v in (combing_ratio(f, mask) for f in frames) if math.isfinite(v)]
    return float(np.median(values)) if values else math.nan


def auto_field(frames, mask=None) -> tuple[int | None, float]:
    """``(field, ratio)`` for frames that may be interlaced: ``ratio`` the median :func:`combing_ratio` of ``frames``
    (the reference camera's first frames) over ``mask`` (NaN: none readable), ``field`` 0 (measure the first field)
    when it exceeds :data:`COMBING_RATIO`, else None (the whole frames)."""
    ratio = frames_combing_ratio(frames, mask)
    return (0 if math.isfinite(ratio) and ratio > COMBING_RATIO else None), ratio


def bob_field(image, field: int) -> np.ndarray:
    """One field of an interlaced image (H, W) or (H, W, 3) back on the image's own rows, at the field's phase:
    its rows ``field``, ``field + 2``, ... as they are, the rows between them the mean of their two neighbours
    (the nearest one at the top or bottom edge); the input's dtype (8-bit rounded). Both fields so treated are
    images of one geometry, the camera's, taken at two instants ("bob" deinterlacing without a half-row shift)."""
    img = np.asarray(image)
    H = img.shape[0]
    if field not in (0, 1):
        raise ValueError(f"field: 0 or 1 expected, got {field!r}")
    if H < 2:
        raise ValueError(f"image: at least 2 rows expected, got {H}")
    src = img.astype(np.float32)
    out = src.copy()
    other = np.arange(1 - field, H, 2)                      # the rows of the other field, filled
    above, below = other - 1, other + 1
    above = np.where(above < 0, below, above)
    below = np.where(below >= H, above, below)
    out[other] = 0.5 * (src[above] + src[below])
    if np.issubdtype(img.dtype, np.integer):
        info = np.iinfo(img.dtype)
        return np.clip(np.rint(out), info.min, info.max).astype(img.dtype)
    return out.astype(img.dtype)


class FieldInstants:
    """Both fields of interlaced frames as instants of their own (:func:`bob_field`): instant ``2 k`` is the field
    taken first of frame ``k`` (``first``: 0 the top field, rows 0, 2, ...; 1 the bottom one), instant ``2 k + 1``
    the other. Wraps a reader of frames (``read(k) -> (images, problems)`` and iteration over ``(k, images,
    problems)``, e.g. :class:`heartcv.io.FrameReader`) and offers the same for the instants; a frame's problems
    are those of both its instants."""

    def __init__(self, reader, first: int = 0):
        if first not in (0, 1):
            raise ValueError(f"first: 0 or 1 expected, got {first!r}")
        self.reader = reader
        self.order = (first, 1 - first)

    def _fields(self, images, j):
        f = self.order[j]
        return [None if im is None else bob_field(im, f) for im in images]

    def read(self, i: int):
        images, problems = self.reader.read(i // 2)
        return self._fields(images, i % 2), problems

    def __iter__(self):
        for k, images, problems in self.reader:
            for j in (0, 1):
                yield 2 * k + j, self._fields(images, j), problems


def field_order(frames, mask=None) -> tuple[int, float, int, int]:
    """``(first, ratio, votes, pairs)``: which field of interlaced frames was taken first, from consecutive frames
    (the reference camera's first frames, in order, gray or BGR) of a moving scene. With ``A_k``, ``B_k`` the top
    and bottom fields of frame ``k`` (:func:`bob_field`), the top field first puts ``B_k`` half a frame before
    ``A_{k+1}`` and one and a half after ``A_{k-1}``; the bottom field first the other way round. So each frame ``k``
    with both neighbours votes for the top field first when ``B_k`` differs less from ``A_{k+1}`` than from
    ``A_{k-1}`` (mean absolute difference over ``mask``, default the image without an eighth of each side).
    ``first`` is 0 (top) when more than half of the ``pairs`` votes say so, else 1; ``ratio`` the summed difference
    to ``A_{k-1}`` over that to ``A_{k+1}`` (above 1: top first). ``votes`` counts the votes for ``first``; a frame
    whose two differences are equal (a still scene) does not vote. No vote: ``first`` 0 (``ratio`` NaN with fewer
    than 3 readable consecutive frames)."""
    g = [None if f is None else np.asarray(_gray(f), np.float32) for f in frames]
    if mask is None and g and g[0] is not None:
        H, W = g[0].shape
        mask = np.zeros((H, W), bool)
        mask[H // 8:H - H // 8, W // 8:W - W // 8] = True
    top = [None if im is None else bob_field(im, 0) for im in g]
    bottom = [None if im is None else bob_field(im, 1) for im in g]
    m = None if mask is None else np.asarray(mask, bool)
    prev_sum = next_sum = 0.0
    top_votes = pairs = 0
    for k in range(1, len(g) - 1):
        if bottom[k] is None or top[k - 1] is None or top[k + 1] is None:
            continue
        d_prev = float(np.mean(np.abs(bottom[k] - top[k - 1])[m]))
        d_next = float(np.mean(np.abs(bottom[k] - top[k + 1])[m]))
        prev_sum += d_prev
        next_sum += d_next
        if d_next != d_prev:           # a tie (a still scene) does not vote
            pairs += 1
            top_votes += d_next < d_prev
    ratio = prev_sum / next_sum if next_sum > 0 else math.nan
    if pairs == 0:
        return 0, ratio, 0, 0
    first = 0 if 2 * top_votes > pairs else 1
    return first, ratio, top_votes if first == 0 else pairs - top_votes, pairs


def field_order_clear(votes: int, pairs: int, level: float = 0.05) -> bool:
    """Whether :func:`field_order`'s ``votes`` of ``pairs`` tell the order: a one-sided binomial sign test (each
    frame's vote a fair coin if they cannot tell) below ``level``."""
    from scipy.stats import binom

    return pairs > 0 and float(binom.sf(votes - 1, pairs, 0.5)) < level


def auto_reduction(frames, mask=None) -> tuple[float, float, float]:
    """``(factor, blur, reduced_blur)``: how much to reduce blurry or oversampled frames so that their texture is as
    sharp as the sparse tracker's sizes expect (docs/cli.md §10.3). ``blur`` is the median :func:`texture_blur_px` of
    ``frames`` (the reference camera's first frames) over ``mask``; at most :data:`NEAR_SHARP` times
    :data:`SHARP_BLUR_PX` (or not finite: a flat image) the factor is 1. Otherwise the factors ``blur / SHARP_BLUR_PX``,
    then each :data:`REDUCTION_STEP` times the last, are tried on the frames reduced by area averaging, and the first
    whose reduced frames read at most :data:`SHARP_BLUR_PX` is taken, but none that leaves a side under
    :data:`MIN_REDUCED_SIDE_PX` (or the image's own smaller side, if smaller); ``reduced_blur`` is what the frames read
    at the factor taken."""
    blur = _median_blur(frames, mask)
    if not (math.isfinite(blur) and blur > SHARP_BLUR_PX * NEAR_SHARP):
        return 1.0, blur, blur
    h, w = np.asarray(frames[0]).shape[:2]
    cap = max(1.0, min(h, w) / MIN_REDUCED_SIDE_PX)
    factor = min(blur / SHARP_BLUR_PX, cap)
    while True:
        small = [reduce_image(np.asarray(f), factor) for f in frames]
        reduced = _median_blur(small, None if mask is None else reduce_mask(mask, factor))
        if not reduced > SHARP_BLUR_PX or factor >= cap:
            return factor, blur, reduced
        factor = min(factor * REDUCTION_STEP, cap)


#: The gates that remove candidates (``Measurer.rejected``; docs/cli.md, measure): per view and frame for the
#: tracking gates, per point and frame for the triangulation gates, per new corner for the matching gate.
GATES = ("lost", "photometric", "forward_backward", "specular", "reprojection", "depth_uncertainty", "match")


class Highlights:
    """One frame's specular highlights (bool (H, W), before growing) and the radius ``grow`` (px) they are grown by
    (dilation by the ellipse of :func:`heartcv.tissue.specular_mask`). :meth:`at` reads the grown mask at a few
    points without growing the whole frame (tracking needs only that); :meth:`grown` grows it (re-detection)."""

    def __init__(self, raw, grow: int):
        self.raw = np.ascontiguousarray(np.asarray(raw, bool))
        self.grow = int(grow)
        self._grown = None
        self._any = bool(self.raw.any())

    def grown(self) -> np.ndarray:
        """The grown mask, bool (H, W) (``cv2.dilate`` by the ellipse of side ``2 grow + 1``)."""
        if self._grown is None:
            if self.grow > 0 and self._any:
                import cv2

                k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * self.grow + 1, 2 * self.grow + 1))
                self._grown = cv2.dilate(self.raw.view(np.uint8), k).view(bool)
            else:
                self._grown = self.raw
        return self._grown

    def at(self, uv) -> np.ndarray:
        """Whether each position (N, 2) falls on the grown mask (nearest pixel; False outside the image or NaN):
        any highlight pixel under the ellipse centred on that pixel, which is what the dilation computes there."""
        uv = np.asarray(uv, float).reshape(-1, 2)
        if not self._any:
            return np.zeros(len(uv), bool)
        if self._grown is not None or self.grow <= 0:
            return _mask_at(self.grown(), uv)
        import cv2

        g = self.grow
        r, inside = _nearest_pixels(uv, self.raw.shape)
        out = np.zeros(len(uv), bool)
        if inside.any():
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * g + 1, 2 * g + 1)).astype(bool)
            padded = cv2.copyMakeBorder(self.raw.view(np.uint8), g, g, g, g, cv2.BORDER_CONSTANT, value=0)
            windows = np.lib.stride_tricks.sliding_window_view(padded, (2 * g + 1, 2 * g + 1))
            ri = r[inside]
            out[inside] = (windows[ri[:, 1], ri[:, 0]].view(bool) & k).any(axis=(1, 2))
        return out


@dataclass(frozen=True)
class MeasureResult:
    """Tracked points of a sequence (K frames, P tracks, C cameras); rig frame, metres.

    Attributes
    ----------
    frames : ndarray (K,) int             frame indices processed
    point_ids : ndarray (P,) int          track ids (0, 1, ... in order of birth)
    birth_frame : ndarray (P,) int        index into ``frames`` of each track's first frame
    positions : ndarray (K, P, 3)         NaN where not seen
    covariances : ndarray (K, P, 3, 3)    sigma_px^2 times the unit covariance; NaN where not seen
    reference : ndarray (P, 3)            position in the birth frame
    uv : ndarray (K, P, C, 2) float32     pixel position of each view used (NaN: view not used)
    views : ndarray (K, P) int            views used
    reprojection_rms : ndarray (K, P)     px
    sigma_px : float                      pixel noise used for the covariances
    sigma_estimated : bool                whether ``sigma_px`` was estimated from the residuals
    roi : ndarray (H, W) bool             region of interest in the reference camera
    timings : dict                        seconds spent per part (``tracking``, ``triangulation``, ``detection``)
    problems : list of str                frames or images skipped, with the reason
    rejected : dict                       candidates each gate removed (:data:`GATES`)
    """

    frames: np.ndarray
    point_ids: np.ndarray
    birth_frame: np.ndarray
    positions: np.ndarray
    covariances: np.ndarray
    reference: np.ndarray
    uv: np.ndarray
    views: np.ndarray
    reprojection_rms: np.ndarray
    sigma_px: float
    sigma_estimated: bool
    roi: np.ndarray
    timings: dict
    problems: list
    rejected: dict = field(default_factory=dict)

    @property
    def seen(self) -> np.ndarray:
        return np.isfinite(self.positions).all(axis=2)


class Measurer:
    """Frame-by-frame measurement of a sequence (module docstring). Feed frames in order with :meth:`step`,
    then call :meth:`result`.

    Parameters
    ----------
    cameras : sequence of Camera
        The calibrated rig (same order as the images).
    options : MeasureOptions
        Sizes left at None follow the reference camera's image size (:meth:`MeasureOptions.for_image`).
    roi_frames : sequence of ndarray (H, W) uint8
        The first frames of the reference camera (for the automatic region of interest); ignored with ``roi``.
    roi : ndarray (H, W) bool, optional
        Region of interest in the reference camera.
    backend : image-ops backend for detection and matching (heartcv.backend), default OpenCV.
    """

    def __init__(self, cameras, options: MeasureOptions = MeasureOptions(), *, roi_frames=None, roi=None,
                 backend=None):
        self.cameras = list(cameras)
        C = len(self.cameras)
        if C < 2:
            raise ValueError(f"cameras: at least 2 expected, got {C}")
        if not 0 <= options.ref_camera < C:
            raise ValueError(f"ref_camera: 0..{C - 1} expected, got {options.ref_camera}")
        ref = self.cameras[options.ref_camera]
        self.opt = options = options.for_image(ref.width, ref.height)
        self.backend = backend or OpenCVBackend()
        if roi is not None:
            roi = np.asarray(roi, bool)
            if roi.shape != (ref.height, ref.width):
                raise ValueError(f"roi: shape {(ref.height, ref.width)} expected, got {roi.shape}")
            m = roi
        else:
            if not roi_frames:
                raise ValueError("roi_frames: the first frames of the reference camera are needed without roi")
            m = auto_region(roi_frames, options)
        self.roi = m
        lk = options.lk
        self._G = (2 * lk.ncc_radius + 1) ** 2
        self._S = 2 * lk.tile_half + 1
        # track state (grown by concatenation): per track, per camera
        self.ids = np.zeros(0, np.int64)
        self.birth = np.zeros(0, np.int64)
        self.birth_tmpl = self._empty_tiles(0)    # templates of the birth frame (drift-free)
        self.key_tmpl = self._empty_tiles(0)      # templates of a recent frame (follow the appearance)
        self.key_step = np.zeros((0, C), np.int64)
        self.prev_uv = np.zeros((0, C, 2))        # accepted position in the previous step (NaN: not seen there)
        self.carry_uv = np.zeros((0, C, 2))       # predicted position of a track while unseen
        self.last_X = np.zeros((0, 3))
        self.last_seen = np.zeros(0, np.int64)
        self.alive = np.zeros(0, bool)
        self._prev_images = [None] * C
        self._noise_var = [None] * C
        self._records = []            # per step: (track indices, X, unit cov, rms, uv (n, C, 2))
        self._frames = []
        self.timings = {"tracking": 0.0, "triangulation": 0.0, "detection": 0.0}
        self.rejected = dict.fromkeys(GATES, 0)
        self.problems = []
        self._sq_resid = 0.0
        self._dof = 0
        self._last_spawn = None
        self.detected = False         # whether the last step detected and matched new points

    def _empty_tiles(self, n):
        C, S, G = len(self.cameras), self._S, self._G
        return {"tiles": np.zeros((n, C, S, S), np.uint8), "origin": np.zeros((n, C, 2), np.int64),
                "uv": np.full((n, C, 2), np.nan), "patch": np.full((n, C, G), np.nan, np.float32),
                "expected": np.zeros((n, C))}

    # -- one frame ------------------------------------------------------------------------------------------------
    def step(self, frame_index, images):
        """Process the images of one instant (one 8-bit gray (H, W) or BGR (H, W, 3) array per camera, None where
        missing; colour is used for the specular highlights).

        Returns the number of points seen in this frame."""
        C = len(self.cameras)
        if len(images) != C:
            raise ValueError(f"images: {C} expected, got {len(images)}")
        for c, (im, cam) in enumerate(zip(images, self.cameras, strict=True)):
            if im is not None and im.shape[:2] != (cam.height, cam.width):
                raise ValueError(f"images[{c}]: {cam.width}x{cam.height} expected for camera {cam.name}, "
                                 f"got {im.shape[1]}x{im.shape[0]}")
        s = len(self._frames)
        self._frames.append(int(frame_index))
        t0 = time.perf_counter()
        gray = [None if im is None else _gray(im) for im in images]
        track_images = [None if g is None else self._prefilter(g) for g in gray]
        for c, im in enumerate(track_images):
            if im is not None and self._noise_var[c] is None:
                self._noise_var[c] = noise_sigma(im) ** 2
        spec = [self._highlights(im) for im in images]
        obs = self._track(track_images, spec)
        t1 = time.perf_counter()
        idx, tri = self._triangulate(obs)
        self._update_keys(s, idx, obs, track_images)
        t2 = time.perf_counter()
        seen = len(idx)
        ref = self.opt.ref_camera
        need = self.opt.refill_fraction * self.opt.max_points
        due = self._last_spawn is None or s - self._last_spawn >= self.opt.respawn_interval
        self.detected = seen < need and due and gray[ref] is not None and sum(g is not None for g in gray) >= 2
        if self.detected:
            self._last_spawn = s
            seen += self._spawn(s, gray, track_images, spec, colour=images[ref])
        t3 = time.perf_counter()
        self.timings["tracking"] += t1 - t0
        self.timings["triangulation"] += t2 - t1
        self.timings["detection"] += t3 - t2
        self._prev_images = track_images
        self._expire(s)
        return seen

    def _highlights(self, image) -> "Highlights | None":
        """This frame's specular highlights (grown by the NCC patch radius), or None: near-white blobs of a colour
        frame (:func:`heartcv.tissue.specular_mask`); in a gray frame bright tissue cannot be told from a highlight,
        so only clipped pixels (``saturation_level``) count."""
        if image is None or not self.opt.specular:
            return None
        grow = self.opt.lk.ncc_radius
        if image.ndim == 3:
            raw = specular_mask(image, grow_px=0)
        else:
            raw = saturation_mask(image, self.opt.saturation_level, grow=0)
        return Highlights(raw, grow)

    def _prefilter(self, gray):
        """The image the tracker sees: the gray image, or its high-pass ``128 + 2 (g - blur(g))`` with
        ``highpass_sigma``."""
        sig = self.opt.highpass_sigma
        if not sig:
            return gray
        import cv2

        blur = cv2.GaussianBlur(gray, (0, 0), sig)                    # uint8 in, uint8 out (SIMD)
        return cv2.addWeighted(gray, 2.0, blur, -2.0, 128.0)          # saturated to [0, 255]

    def _tiles(self, which, sel, c) -> TileSet:
        t = which
        return TileSet(t["tiles"][sel, c], t["origin"][sel, c], t["uv"][sel, c], t["patch"][sel, c],
                       t["expected"][sel, c])

    def _track(self, images, spec):
        """Observations (P, C, 2) of the alive tracks in this frame (NaN where not accepted): frame-to-frame LK
        for the starting guess, then alignment to the birth template (drift-free) or, where that fails, to the
        key template (a recent frame's appearance), camera by camera (:meth:`_track_camera`)."""
        C = len(self.cameras)
        P = len(self.ids)
        obs = np.full((P, C, 2), np.nan)
        self._anchored = np.zeros((P, C), bool)       # accepted against the birth template
        if P == 0:
            return obs
        for c in range(C):
            out = None if images[c] is None else self._track_camera(c, images[c], spec[c])
            if out is None:
                continue
            sel, uv, anchored, counts = out
            obs[sel, c] = uv
            self._anchored[sel, c] = anchored
            for name, n in counts.items():
                self.rejected[name] += n
        return obs

    def _track_camera(self, c, cur, spec):
        """:meth:`_track` in camera ``c`` (reads the tracker's state, changes nothing): (track indices (n,), their
        positions (n, 2) (NaN where not accepted), accepted against the birth template (n,), {gate: views
        removed}), or None without candidates."""
        lk = self.opt.lk
        P = len(self.ids)
        cand = self.alive & np.isfinite(self.birth_tmpl["uv"][:, c, 0])
        if not cand.any():
            return None
        init = np.full((P, 2), np.nan)
        prev = cand & np.isfinite(self.prev_uv[:, c, 0])
        if prev.any() and self._prev_images[c] is not None:
            init[prev] = flow_step(self._prev_images[c], cur, self.prev_uv[prev, c], lk)
        gap = cand & ~np.isfinite(init[:, 0])
        init[gap] = np.where(np.isfinite(self.carry_uv[gap, c]), self.carry_uv[gap, c],
                             self.cameras[c].project(self.last_X[gap]))
        sel = np.flatnonzero(cand)
        uv, why, _, _ = track_tiles(self._tiles(self.birth_tmpl, sel, c), cur, init[sel], lk,
                                    ncc_floor=self.opt.ncc_floor)
        anchored = why == ACCEPTED
        retry = ~anchored & (self.key_step[sel, c] != self.birth[sel])
        if retry.any():
            sk = sel[retry]
            uv2, why2, _, _ = track_tiles(self._tiles(self.key_tmpl, sk, c), cur, init[sk], lk,
                                          ncc_floor=self.opt.ncc_floor)
            r = np.flatnonzero(retry)
            uv[r], why[r] = uv2, why2
        inside = self.cameras[c].in_image(np.nan_to_num(uv, nan=-1e9), lk.window / 2)
        why[(why == ACCEPTED) & ~inside] = LOST
        uv[~inside] = np.nan
        counts = {}
        if spec is not None:
            hit = (why == ACCEPTED) & spec.at(uv)
            why[hit] = -1
            uv[hit] = np.nan
            counts["specular"] = int(hit.sum())
        for code, name in ((LOST, "lost"), (PHOTOMETRIC, "photometric"), (FORWARD_BACKWARD, "forward_backward")):
            counts[name] = int((why == code).sum())
        return sel, uv, anchored & np.isfinite(uv[:, 0]), counts

    def _depth_ok(self, X, cov) -> np.ndarray:
        """The depth-uncertainty gate: the standard deviation of each point's depth along the reference camera's
        ray, at the pixel noise (``pixel_sigma`` or the estimate so far, else 0.5 px), at most
        ``max_depth_std_ratio`` of the depth."""
        d = X - self.cameras[self.opt.ref_camera].centre
        depth = np.linalg.norm(d, axis=1)
        u = d / depth[:, None]
        var = np.einsum("ni,nij,nj->n", u, cov, u)
        if self.opt.pixel_sigma is not None:
            sigma = self.opt.pixel_sigma
        else:
            est = self.estimated_sigma()
            sigma = est if np.isfinite(est) else 0.5
        with np.errstate(invalid="ignore"):
            return sigma * np.sqrt(np.maximum(var, 0.0)) <= self.opt.max_depth_std_ratio * depth

    def _gated_triangulation(self, uv):
        """Triangulate observations (n, C, 2) (unit pixel sigma) and apply the reprojection and depth-uncertainty
        gates, counting what each removes; returns (Triangulation, kept (n,) bool)."""
        o = self.opt
        tri = triangulate(self.cameras, uv, sigma_px=1.0, robust=True, outlier_px=o.outlier_px,
                          max_rms_px=o.max_reprojection_px, min_angle_deg=o.min_angle_deg)
        good = tri.ok.copy()
        self.rejected["reprojection"] += int((~good).sum())
        deep = good.copy()
        deep[good] = self._depth_ok(tri.points[good], tri.covariances[good])
        self.rejected["depth_uncertainty"] += int((good & ~deep).sum())
        return tri, deep

    def _triangulate(self, obs):
        """Triangulate the observed tracks, record them; returns (track indices, Triangulation)."""
        idx = np.flatnonzero(np.isfinite(obs[..., 0]).sum(axis=1) >= 2)
        s = len(self._frames) - 1
        C = len(self.cameras)
        if idx.size == 0:
            self._records.append((idx, np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0),
                                  np.zeros((0, C, 2), np.float32)))
            self.prev_uv[:] = np.nan
            return idx, None
        tri, good = self._gated_triangulation(obs[idx])
        i = idx[good]
        used = tri.used[good]
        uv = np.where(used[..., None], obs[i], np.nan).astype(np.float32)
        X = tri.points[good]
        self._records.append((i, X, tri.covariances[good], tri.rms_px[good], uv))
        r = np.where(used, tri.reprojection_px[good], 0.0)
        self._sq_resid += float((r ** 2).sum())
        self._dof += int((2 * used.sum(axis=1) - 3).sum())
        self.last_X[i] = X
        self.last_seen[i] = s
        self._carry(i, used, obs)
        self.prev_uv[:] = np.nan
        self.prev_uv[i] = np.where(used[..., None], obs[i], np.nan)
        return i, tri

    def _carry(self, i, used, obs):
        """Predicted positions of the tracks not seen in this frame: their last prediction (or position) moved
        by the mean frame-to-frame motion of their 4 nearest tracks seen in both frames."""
        from scipy.spatial import cKDTree

        C = len(self.cameras)
        for c in range(C):
            vis = np.zeros(len(self.ids), bool)
            vis[i[used[:, c]]] = True
            both = vis & np.isfinite(self.prev_uv[:, c, 0])
            start = np.where(np.isfinite(self.prev_uv[:, c]), self.prev_uv[:, c], self.carry_uv[:, c])
            unseen = self.alive & ~vis & np.isfinite(start[:, 0])
            if unseen.any() and both.sum() >= 1:
                k = min(4, int(both.sum()))
                tree = cKDTree(self.prev_uv[both, c])
                _, nb = tree.query(start[unseen], k=k)
                motion = obs[both, c] - self.prev_uv[both, c]
                nb = np.asarray(nb).reshape(int(unseen.sum()), k)
                self.carry_uv[unseen, c] = start[unseen] + motion[nb].mean(axis=1)
            elif unseen.any():
                self.carry_uv[unseen, c] = start[unseen]
            self.carry_uv[vis, c] = np.nan

    def _update_keys(self, s, i, obs, images):
        """Key templates of the views seen in this frame, accepted against their birth template, whose key is
        ``key_interval`` or more steps old: cut from this frame at the accepted position. Only positions aligned
        to the birth template become keys, so a key is never more than one alignment away from the birth
        template: tracking through keys does not drift."""
        if i.size == 0:
            return
        for c, im in enumerate(images):
            if im is None:
                continue
            u = i[np.isfinite(obs[i, c, 0]) & self._anchored[i, c] & (s - self.key_step[i, c] >= self.opt.key_interval)]
            if u.size == 0:
                continue
            self._set_templates(self.key_tmpl, u, c, im, obs[u, c])
            self.key_step[u, c] = s

    def _set_templates(self, which, rows, c, image, uv):
        tiles, origin = cut_tiles(image, uv, self.opt.lk.tile_half)
        patch = template_patches(image, uv, self.opt.lk)
        which["tiles"][rows, c] = tiles
        which["origin"][rows, c] = origin
        which["uv"][rows, c] = uv
        which["patch"][rows, c] = patch
        which["expected"][rows, c] = expected_ncc(patch, self._noise_var[c])

    def _spawn(self, s, images, track_images, spec, colour=None):
        """Detect and match new points in free parts of the region (not on this frame's highlights, nor, in colour
        frames of colourful tissue, on near-neutral pixels: instruments that moved into the view); returns how many
        were added."""
        o = self.opt
        ref = o.ref_camera
        C = len(self.cameras)
        current = self.prev_uv[self.alive & (self.last_seen == s), ref]
        exclude = current[np.isfinite(current).all(axis=1)]
        gray = images[ref]
        mask = self.roi & ~saturation_mask(gray, o.saturation_level, grow=o.lk.window // 2)
        if spec[ref] is not None:
            mask &= ~spec[ref].grown()
        if colour is not None and colour.ndim == 3:
            neutral = neutral_mask(colour, self.roi, grow_px=o.lk.window // 2)
            if neutral is not None:
                mask &= ~neutral
        room = o.max_points - len(exclude)
        if room <= 0:
            return 0
        uv, _ = detect_corners(gray, mask, max_points=room, min_distance=o.min_distance_px, exclude=exclude,
                               block_size=o.corner_block_size, quality=o.corner_quality, backend=self.backend)
        if len(uv) == 0:
            return 0
        imgs = [None if im is None else np.asarray(im, np.float32) for im in images]
        min_ncc = o.match_min_ncc
        if min_ncc is None:
            patch = template_patches(gray, uv, LKParams(ncc_radius=o.match_radius))
            noise = [v for v in self._noise_var if v is not None]
            expected = expected_ncc(patch, max(noise) if noise else 0.0)
            min_ncc = np.maximum(o.ncc_floor, expected - o.match_ncc_allowance)
        # the points measured in this instant predict the surface around the new corners (no full-range sweep)
        X_now = self._records[-1][1] if self._records else np.zeros((0, 3))
        known = (self.cameras[ref].project(X_now), X_now)
        m = match_points(self.cameras, imgs, ref, uv, radius=o.match_radius, min_ncc=min_ncc, known=known,
                         backend=self.backend)
        keep = m.ok
        for c, cam in enumerate(self.cameras):
            inside = cam.in_image(np.nan_to_num(m.uv[:, c], nan=-1e9), o.lk.window)
            if spec[c] is not None:
                inside &= ~spec[c].at(m.uv[:, c])
            m.uv[~inside, c] = np.nan
        keep &= np.isfinite(m.uv[..., 0]).sum(axis=1) >= 2
        self.rejected["match"] += int((~keep).sum())
        if not keep.any():
            return 0
        uvk = m.uv[keep]
        tri, good = self._gated_triangulation(uvk)
        if not good.any():
            return 0
        uvk = np.where(tri.used[good][..., None], uvk[good], np.nan)
        n = len(uvk)
        old = len(self.ids)
        rows = np.arange(old, old + n)
        start = int(self.ids[-1]) + 1 if len(self.ids) else 0
        self.ids = np.r_[self.ids, start + np.arange(n)]
        self.birth = np.r_[self.birth, np.full(n, s)]
        for which in (self.birth_tmpl, self.key_tmpl):
            grown = self._empty_tiles(n)
            for key in which:
                which[key] = np.concatenate([which[key], grown[key]])
        for c in range(C):
            has = np.isfinite(uvk[:, c, 0])
            if has.any():
                self._set_templates(self.birth_tmpl, rows[has], c, track_images[c], uvk[has, c])
                self._set_templates(self.key_tmpl, rows[has], c, track_images[c], uvk[has, c])
        self.key_step = np.concatenate([self.key_step, np.full((n, C), s)])
        self.prev_uv = np.concatenate([self.prev_uv, uvk])
        self.carry_uv = np.concatenate([self.carry_uv, np.full((n, C, 2), np.nan)])
        self.last_X = np.concatenate([self.last_X, tri.points[good]])
        self.last_seen = np.r_[self.last_seen, np.full(n, s)]
        self.alive = np.r_[self.alive, np.ones(n, bool)]
        i, X, cov, rms, uv = self._records[-1]
        self._records[-1] = (np.r_[i, rows], np.concatenate([X, tri.points[good]]),
                             np.concatenate([cov, tri.covariances[good]]), np.r_[rms, tri.rms_px[good]],
                             np.concatenate([uv, uvk.astype(np.float32)]))
        used = tri.used[good]
        self._sq_resid += float((np.where(used, tri.reprojection_px[good], 0.0) ** 2).sum())
        self._dof += int((2 * used.sum(axis=1) - 3).sum())
        return n

    def _expire(self, s):
        """End tracks unseen for more than ``max_gap_frames`` steps; free their templates."""
        gone = self.alive & (s - self.last_seen > self.opt.max_gap_frames)
        if gone.any():
            self.alive &= ~gone
            for which in (self.birth_tmpl, self.key_tmpl):
                which["tiles"][gone] = 0

    def skip(self, frame_index, reason):
        """Record an instant that could not be processed at all (all points missing in it)."""
        self._frames.append(int(frame_index))
        self._records.append((np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0),
                              np.zeros((0, len(self.cameras), 2), np.float32)))
        self.problems.append(reason)

    # -- result ---------------------------------------------------------------------------------------------------
    def estimated_sigma(self) -> float:
        """Pooled pixel noise sigma of the accepted observations (px), floored at ``min_pixel_sigma``."""
        if self._dof <= 0:
            return float("nan")
        return max(float(np.sqrt(self._sq_resid / self._dof)), self.opt.min_pixel_sigma)

    def unusable(self, images) -> str | None:
        """Why an instant cannot be processed (fewer than two readable images), or None."""
        return "fewer than two readable images" if sum(im is not None for im in images) < 2 else None

    def result(self) -> MeasureResult:
        return assemble_result(self, self.ids)


def assemble_result(tracker, ids) -> MeasureResult:
    """The :class:`MeasureResult` of a frame-by-frame tracker (:class:`Measurer`, ``heartcv.dense.DenseTracker``)
    from its per-instant records ``(track indices, X, unit covariance, reprojection RMS, uv (n, C, 2))``: the
    covariances scaled by ``sigma^2``, sigma the option ``pixel_sigma`` or else ``tracker.estimated_sigma()``
    (floored at ``min_pixel_sigma``)."""
    K, P, C = len(tracker._frames), len(ids), len(tracker.cameras)
    pos = np.full((K, P, 3), np.nan)
    cov = np.full((K, P, 3, 3), np.nan)
    uv = np.full((K, P, C, 2), np.nan, np.float32)
    rms = np.full((K, P), np.nan)
    views = np.zeros((K, P), np.int64)
    for k, (i, X, Cu, r, u) in enumerate(tracker._records):
        pos[k, i] = X
        cov[k, i] = Cu
        rms[k, i] = r
        uv[k, i] = u
        views[k, i] = np.isfinite(u[..., 0]).sum(axis=1)
    opt = tracker.opt
    if opt.pixel_sigma is not None:
        sigma, estimated = float(opt.pixel_sigma), False
    else:
        sigma, estimated = tracker.estimated_sigma(), True
        if not np.isfinite(sigma):
            sigma = opt.min_pixel_sigma
    cov *= sigma ** 2
    ref = pos[tracker.birth, np.arange(P)] if P else np.zeros((0, 3))
    return MeasureResult(np.array(tracker._frames, np.int64), np.asarray(ids, np.int64).copy(),
                         tracker.birth.copy(), pos, cov, ref, uv, views, rms, sigma, estimated,
                         np.asarray(tracker.roi, bool).copy(), dict(tracker.timings), list(tracker.problems),
                         dict(getattr(tracker, "rejected", {})))


# =====================================================================================================================
# A whole sequence: the frame loop of ``heartcv measure`` (and of benchmarks/measure.py)
# =====================================================================================================================
@dataclass(frozen=True)
class FrameStats:
    """Timing and outcome of one instant of :func:`measure_sequence`.

    Attributes
    ----------
    frame : int              frame index
    wait_s : float           time spent waiting for the images (decoding, unless read ahead)
    total_s : float          time since the end of the previous instant (the first: since the setup ended)
    tracking_s, triangulation_s, detection_s : float   :attr:`Measurer.timings` spent on this instant
    seen : int               points seen in this instant
    detected : bool          whether new points were detected and matched in this instant
    skipped : bool           fewer than two readable images: all points missing
    """

    frame: int
    wait_s: float
    total_s: float
    tracking_s: float
    triangulation_s: float
    detection_s: float
    seen: int
    detected: bool
    skipped: bool


@dataclass(frozen=True)
class SequenceRun:
    """The outcome of :func:`measure_sequence`.

    Attributes
    ----------
    result : MeasureResult
    frames : tuple of FrameStats     one per instant, in order
    problems : tuple of (int, str)   (frame index, message) of every image left out (missing, unreadable, ...)
    setup_s : float                  region of interest and tracker set-up
    repeated : tuple of (int, int)   (frame index, camera index) of every image left out because it repeats the
                                     camera's previous one (:class:`RepeatedViews`)
    """

    result: MeasureResult
    frames: tuple
    problems: tuple
    setup_s: float
    repeated: tuple = ()

    @property
    def skipped(self) -> list:
        """Frame indices with fewer than two readable images."""
        return [f.frame for f in self.frames if f.skipped]

    @property
    def wait_s(self) -> float:
        """Total time spent waiting for images."""
        return float(sum(f.wait_s for f in self.frames))


def reference_frames(read, count: int, ref: int) -> list:
    """The readable images of the reference camera at :data:`ROI_FRAMES` (below ``count``).

    Parameters
    ----------
    read : callable
        ``read(k) -> (images, problems)`` of instant ``k`` (e.g. :meth:`heartcv.io.FrameReader.read`).
    count : int
        Instants in the sequence.
    ref : int
        Reference camera.
    """
    images = (read(k)[0][ref] for k in ROI_FRAMES if k < count)
    return [im for im in images if im is not None]


def auto_region(roi_frames, options: MeasureOptions = MeasureOptions()) -> np.ndarray:
    """The automatic region of interest of the reference camera's first frames: the tissue
    (:func:`heartcv.tissue.tissue_region`: without dark borders, specular highlights, instruments and untextured
    parts; frames in colour (BGR) for the instrument test), and of it only the part that moves
    (:func:`heartcv.features.moving_mask`) when two or more frames show a moving part of at least 5 % of the
    tissue (a static textured background is left out).

    Raises
    ------
    InputError
        No frame (none of the first frames of the reference camera could be read); field ``images``.
    MeasureFailed
        Too little tissue in them; the message says what was removed and to pass ``--mask``.
    """
    if not roi_frames:
        raise InputError(None, f"none of the reference camera's frames {ROI_FRAMES.start}, "
                               f"{ROI_FRAMES.start + ROI_FRAMES.step}, ... can be read", "images")
    try:
        region = tissue_region(roi_frames)
    except TissueNotFound as exc:
        raise MeasureFailed(f"automatic region of interest: {exc}") from None
    mask = region.mask
    if len(roi_frames) >= 2:
        gray = [_gray(f) for f in roi_frames]
        moving = moving_mask(gray, noise_sigma(gray[0]))
        if (mask & moving).sum() >= 0.05 * mask.sum():
            mask = mask & moving
    return mask


@dataclass(frozen=True)
class WorkingView:
    """The images as a tracker sees them: one field of interlaced video (:func:`field_image`), then reduced
    (:func:`reduce_image`), or the images themselves. ``cameras`` and ``roi`` are in those working pixels, and
    ``maps`` gives per camera ``(a (2,), b (2,))`` with ``full pixel = a * working pixel + b``."""

    cameras: list
    roi: np.ndarray
    maps: list
    field: int | None = None
    reduction: float = 1.0

    @classmethod
    def of(cls, cameras, roi, *, field: int | None = None, reduction: float = 1.0) -> "WorkingView":
        """The working view of ``cameras`` and the reference camera's ``roi`` (full images) for ``field`` (None, 0
        or 1) and ``reduction`` (>= 1)."""
        if not (math.isfinite(reduction) and reduction >= 1.0):
            raise ValueError(f"reduction: a factor >= 1 expected, got {reduction}")
        if field not in (None, 0, 1):
            raise ValueError(f"field: None, 0 or 1 expected, got {field!r}")
        cameras = list(cameras)
        maps = [(np.ones(2), np.zeros(2)) for _ in cameras]
        if field is not None:
            cameras = [field_camera(c, field) for c in cameras]
            roi = field_image(roi, field)
            maps = [(np.array([1.0, 2.0]), np.array([0.0, float(field)])) for _ in cameras]
        if reduction > 1.0:
            small = [reduced_camera(c, reduction) for c in cameras]
            ratio = [np.array([r.width / c.width, r.height / c.height]) for c, r in zip(cameras, small)]
            maps = [(a / q, a * (0.5 / q - 0.5) + b) for (a, b), q in zip(maps, ratio)]
            cameras, roi = small, reduce_mask(roi, reduction)
        return cls(cameras, np.asarray(roi, bool), maps, field, float(reduction))

    @property
    def transformed(self) -> bool:
        return self.field is not None or self.reduction > 1.0

    def pixel_scale(self, camera: int) -> float:
        """The geometric mean of camera ``camera``'s full-to-working scale factors (a full pixel length is this
        many working pixels' length, on average): sqrt 2 for a field alone."""
        return math.sqrt(float(np.prod(self.maps[camera][0])))

    def frames(self, frames):
        """``(k, images, problems)`` instants with every image in working pixels."""
        f, r = self.field, self.reduction
        return ((k, [None if im is None else reduce_image(im if f is None else field_image(im, f), r)
                     for im in images], problems) for k, images, problems in frames)

    def to_full(self, res: MeasureResult, ref: int, roi) -> MeasureResult:
        """A result measured in working pixels in the full images' pixels: ``uv`` mapped per camera, the
        reprojection RMS and sigma times the reference camera's :meth:`pixel_scale`, ``roi`` the full-size
        region. Positions and covariances (metres) are unchanged."""
        uv = np.array(res.uv, np.float64)
        for c, (a, b) in enumerate(self.maps):
            uv[:, :, c] = uv[:, :, c] * a + b
        scale = self.pixel_scale(ref)
        return replace(res, uv=uv.astype(res.uv.dtype), reprojection_rms=res.reprojection_rms * scale,
                       sigma_px=res.sigma_px * scale, roi=np.asarray(roi, bool).copy())


def measure_sequence(frames, cameras, options: MeasureOptions = MeasureOptions(), *, roi=None, roi_frames=(),
                     backend=None, clock=time.perf_counter, reduction: float = 1.0,
                     field: int | None = None, drop_repeats: bool = True) -> SequenceRun:
    """Measure a whole sequence: set up a :class:`Measurer` and feed it every instant of ``frames``.

    Parameters
    ----------
    frames : iterable of (int, list, list)
        ``(k, images, problems)`` per instant, in order (e.g. a :class:`heartcv.io.FrameReader`): one 8-bit gray
        image per camera, None where missing, and the messages naming the images left out. An instant with fewer
        than two images is recorded with all points missing (:meth:`Measurer.skip`).
    cameras : sequence of Camera
    options : MeasureOptions
    roi : ndarray (H, W) bool, optional
        Region of interest in the reference camera; default :func:`auto_region` of ``roi_frames``.
    roi_frames : sequence of ndarray
        The reference camera's first frames (:func:`reference_frames`), used without ``roi``.
    backend : image-ops backend (heartcv.backend), default OpenCV.
    clock : callable
        Time source of the per-instant timings.
    reduction : float
        At least 1 (:func:`auto_reduction`): the points are tracked and triangulated in every camera's images
        reduced by this factor (:func:`reduce_image`, :func:`reduced_camera`; the sizes of ``options`` follow the
        reduced images; a given ``options.pixel_sigma`` is in the full images' pixels), and the result is given
        in the full images' pixels: ``uv``, ``reprojection_rms`` and ``sigma_px`` mapped back (the latter two times
        the reference camera's factor), ``roi`` the full-size region. Positions and covariances are in metres
        either way.
    field : {None, 0, 1}
        Interlaced video (:func:`combing_ratio`): measure one field of every image, rows ``field``, ``field + 2``,
        ... (:func:`field_image`, :func:`field_camera`; before any ``reduction``); the result in the full
        images' pixels as above (``sigma_px`` and ``reprojection_rms`` times the geometric mean of the
        factors, sqrt 2 for a field alone). None: the whole images.
    drop_repeats : bool
        Leave out every view whose image repeats its previous one (:func:`run_frames`, :class:`RepeatedViews`).

    Raises
    ------
    InputError
        Without ``roi``: none of ``roi_frames`` (field ``images``).
    MeasureFailed
        No textured surface for the region of interest, or no point tracked in any instant.
    """
    t0 = clock()
    if roi is None:
        roi = auto_region(roi_frames, options)
    full_roi = np.asarray(roi, bool)
    view = WorkingView.of(cameras, full_roi, field=field, reduction=reduction)
    cameras, roi = view.cameras, view.roi
    if view.transformed:
        if options.pixel_sigma is not None:            # given in the full frames' pixels
            options = replace(options, pixel_sigma=options.pixel_sigma / view.pixel_scale(options.ref_camera))
        frames = view.frames(frames)
    measurer = Measurer(cameras, options, roi=roi, backend=backend)
    run = run_frames(measurer, frames, clock, clock() - t0, drop_repeats)
    if view.transformed:
        run = replace(run, result=view.to_full(run.result, options.ref_camera, full_roi))
    if run.result.point_ids.size == 0 or not run.result.seen.any():
        raise MeasureFailed(f"no surface point could be tracked (region of interest {int(run.result.roi.sum())} px "
                            f"in camera {measurer.cameras[options.ref_camera].name}): "
                            f"{emptied_by(run.result.rejected)}")
    return run


#: The option of ``heartcv measure`` that loosens each gate (for the failure messages).
GATE_OPTIONS = {"match": "--match-ncc-allowance or --min-ncc; a --window near the image's size leaves no room",
                "reprojection": "--max-reprojection or --min-angle",
                "depth_uncertainty": "--max-depth-std", "photometric": "--ncc-allowance or --min-ncc",
                "forward_backward": "--fb-max", "lost": "--window", "specular": "--no-specular"}


def emptied_by(rejected) -> str:
    """Which gates removed the candidates (largest first), with the option that loosens each."""
    hits = sorted(((n, g) for g, n in rejected.items() if n), reverse=True)
    if not hits:
        return ("no corner was detected in the region of interest (check the region, --corner-quality, and "
                "--min-distance and --corner-block, which --size-factor multiplies)")
    parts = [f"{g} gate {n}" + (f" ({GATE_OPTIONS[g]})" if g in GATE_OPTIONS else "") for n, g in hits]
    return "candidates removed by the " + ", ".join(parts)


# A view's image repeats its previous one (a frame-rate conversion, a capture that froze or dropped frames: no new
# exposure) when
# - at most REPEAT_SHARE of its pixels change by more than REPEAT_LEVEL of the full scale (8 of 255: what
#   re-encoding leaves of a copied frame; MPEG-4 part 2 left at most 0.09 % of the pixels of copied in-vivo frames
#   beyond it, while consecutive frames of the in-vivo heart change at least 9.5 %, median 36 %), and at most
#   REPEAT_RELATIVE times the median share of the view's last REPEAT_HISTORY frames that were not repeats, which
#   must itself exceed REPEAT_SHARE (a view seen moving: a still scene, or one whose moving part is small, is never
#   taken for repeats);
# - and at least REPEAT_UNCHANGED of its live pixels (in both frames inside 2-98 % of the full scale) keep exactly
#   their value: a new exposure brings fresh sensor noise (consecutive in-vivo frames keep at most 1.6 %, the
#   rendered phantom's 5.6 % even where it barely moves), a copy none (re-encoded copies kept 73-84 %).
REPEAT_LEVEL = 8 / 255
REPEAT_SHARE = 0.01
REPEAT_RELATIVE = 0.1
REPEAT_HISTORY = 25
REPEAT_UNCHANGED = 0.5


def _full_scale(image) -> float:
    """255 for 8-bit images, else the image's largest value (a 10- or 12-bit camera's frames in 16-bit files)."""
    return 255.0 if image.dtype == np.uint8 else max(float(np.max(image)), np.finfo(float).tiny) if image.size \
        else 1.0


def changed_share(image, previous, level: float = REPEAT_LEVEL) -> float:
    """The share of the pixels of ``image`` (H, W) or (H, W, C) whose value (in any channel) differs from
    ``previous``'s by more than ``level`` of the full scale (:func:`_full_scale` of ``previous``). Every second row
    and column (the share, not its detail). Images of different shapes: 1 (a change)."""
    a, b = np.asarray(image), np.asarray(previous)
    if a.shape != b.shape:
        return 1.0
    a, b = a[::2, ::2], b[::2, ::2]
    diff = np.abs(a.astype(np.float32) - b.astype(np.float32))
    if diff.ndim == 3:
        diff = diff.max(axis=2)
    return float(np.mean(diff > level * _full_scale(b))) if diff.size else 0.0


def unchanged_share(image, previous) -> float:
    """The share of the live pixels (every channel inside 2-98 % of the full scale in both images: sensor noise is
    not clipped there) whose value is exactly ``previous``'s in every channel; every second row and column. NaN
    where no pixel is live or the shapes differ."""
    a, b = np.asarray(image), np.asarray(previous)
    if a.shape != b.shape or not a.size:
        return math.nan
    a, b = a[::2, ::2], b[::2, ::2]
    top = _full_scale(b)
    live = (a > 0.02 * top) & (a < 0.98 * top) & (b > 0.02 * top) & (b < 0.98 * top)
    same = a == b
    if a.ndim == 3:
        live, same = live.all(axis=2), same.all(axis=2)
    return float(same[live].mean()) if live.any() else math.nan


class RepeatedViews:
    """Which views of each instant repeat their previous image (module constants ``REPEAT_*``): called with one
    instant's images after another (None where missing; a missing image leaves the view's previous one in place),
    returns the indices of the views whose image is a repeat. ``shares[c]``: the changed share of every comparison
    of view ``c``, in order."""

    def __init__(self, views: int):
        self._prev = [None] * views
        self._moving = [deque(maxlen=REPEAT_HISTORY) for _ in range(views)]
        self.shares = [[] for _ in range(views)]

    def __call__(self, images) -> list:
        out = []
        for c, image in enumerate(images):
            if image is None:
                continue
            prev, self._prev[c] = self._prev[c], image
            if prev is None:
                continue
            share = changed_share(image, prev)
            self.shares[c].append(share)
            seen = self._moving[c]
            typical = float(np.median(seen)) if seen else 0.0
            if typical > REPEAT_SHARE and share <= REPEAT_SHARE and share <= REPEAT_RELATIVE * typical \
                    and unchanged_share(image, prev) >= REPEAT_UNCHANGED:
                out.append(c)
            else:
                seen.append(share)
        return out


def run_frames(tracker, frames, clock, setup_s, drop_repeats: bool = True) -> SequenceRun:
    """Feed every instant of ``frames`` (``(k, images, problems)``) to a frame-by-frame tracker (:class:`Measurer`,
    ``heartcv.dense.DenseTracker``: ``step``, ``skip``, ``unusable``, ``timings``, ``detected``, ``result``) and
    time each instant; instants the tracker cannot use are recorded with all points missing. With
    ``drop_repeats`` a view whose image repeats its previous one (:class:`RepeatedViews`) is left out of its
    instant, as a missing image (``SequenceRun.repeated``)."""
    stats, problems, repeated = [], [], []
    it = iter(frames)
    repeats = None
    prev = clock()
    while True:
        t_wait = clock()
        item = next(it, None)
        if item is None:
            break
        k, images, probs = item
        t_got = clock()
        problems.extend((int(k), str(m)) for m in probs)
        same = []
        if drop_repeats:
            repeats = repeats or RepeatedViews(len(images))
            same = repeats(images)
            if same:
                images = [None if c in same else im for c, im in enumerate(images)]
                repeated.extend((int(k), c) for c in same)
        before = dict(tracker.timings)
        why = tracker.unusable(images)
        if why is not None:
            tracker.skip(k, f"frame {k}: {why}" + (" (views repeating their previous image left out: "
                                                   f"{', '.join(tracker.cameras[c].name for c in same)})"
                                                   if same else ""))
            seen = 0
        else:
            seen = tracker.step(k, images)
        now = clock()
        d = {key: tracker.timings[key] - before[key] for key in before}
        stats.append(FrameStats(int(k), t_got - t_wait, now - prev, d["tracking"], d["triangulation"],
                                d["detection"], int(seen), why is None and tracker.detected, why is not None))
        prev = now
    return SequenceRun(tracker.result(), tuple(stats), tuple(problems), setup_s, tuple(repeated))


def _gray(image) -> np.ndarray:
    """An 8-bit gray image of a gray (H, W) or BGR (H, W, 3) frame."""
    if image.ndim == 2:
        return image
    import cv2

    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def _nearest_pixels(uv, shape):
    """The nearest pixel (N, 2) int of each position (N, 2) and whether it lies in an image of ``shape`` (N,)
    (False for NaN or infinite positions)."""
    H, W = shape[:2]
    finite = np.isfinite(uv).all(axis=1)
    r = np.rint(np.nan_to_num(uv, nan=-1.0, posinf=-1.0, neginf=-1.0)).astype(np.int64)
    return r, finite & (r[:, 0] >= 0) & (r[:, 0] < W) & (r[:, 1] >= 0) & (r[:, 1] < H)


def _mask_at(mask, uv) -> np.ndarray:
    """Whether each position (N, 2) falls on a True pixel of ``mask`` (nearest pixel; False outside or NaN)."""
    r, inside = _nearest_pixels(uv, mask.shape)
    out = np.zeros(len(uv), bool)
    out[inside] = mask[r[inside, 1], r[inside, 0]]
    return out
