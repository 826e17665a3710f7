"""From calibrated multi-camera image sequences to tracked 3-D surface points with covariances.

The pipeline of ``heartcv measure`` (docs/cli.md), frame by frame:

1. *Region of interest*: given, or the moving, textured surface of the reference camera's first frames
   (:func:`heartcv.features.region_of_interest`).
2. *Reference detection*: Shi–Tomasi corners spread over the region (grid buckets), away from specular
   highlights, matched in every other camera by the trinocular plane sweep (:mod:`heartcv.matching`).
3. *Temporal tracking*: every view of every point is tracked by Lucas–Kanade from the image the point was born
   in (:mod:`heartcv.klt`; forward–backward and NCC checks), so tracks do not drift.
4. *Triangulation* of the accepted views of each point (:func:`heartcv.triangulation.triangulate`: linear, then
   Gauss–Newton on the reprojection error, worst view dropped while it exceeds ``outlier_px``); points with a
   poor reprojection RMS or triangulation angle are missing in that frame.
5. *Re-detection*: when fewer than ``refill_fraction * max_points`` points are seen (checked at most every
   ``respawn_interval`` frames), new corners are detected in the free parts of the region and matched; they
   start new tracks (new ids). A track unseen for more than
   ``max_gap_frames`` frames ends; until then it is searched for in every frame (it resumes after an
   occlusion).
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

from dataclasses import dataclass, field
import time

import numpy as np

from .backend import OpenCVBackend
from .features import RegionNotFound, detect_corners, region_of_interest, saturation_mask
from .klt import LKParams, template_patches, track_from_template
from .matching import match_points
from .tracker.files import InputError
from .triangulation import triangulate

__all__ = ["MeasureOptions", "MeasureResult", "Measurer", "MeasureFailed", "FrameStats", "SequenceRun",
           "ROI_FRAMES", "reference_frames", "auto_region", "measure_sequence", "run_frames", "assemble_result"]

# Frames of the reference camera from which the automatic region of interest is computed (every third of the
# first 30: the surface moves enough between them to tell it from the static background)
ROI_FRAMES = range(0, 30, 3)


class MeasureFailed(RuntimeError):
    """The measurement failed on valid input: no textured surface for the region of interest, or no point could
    be tracked. The command line reports it as a failed stage (exit 1), not as bad input."""


@dataclass(frozen=True)
class MeasureOptions:
    """Settings of :class:`Measurer` (defaults suit the paper's rig at 1920x1080; docs/cli.md, measure)."""

    ref_camera: int = 0
    max_points: int = 300
    min_distance_px: float = 15.0
    corner_block_size: int = 7
    corner_quality: float = 0.02
    refill_fraction: float = 0.8
    roi_margin_px: int = 15
    saturation_level: int = 250
    match_min_ncc: float = 0.85
    respawn_interval: int = 30
    match_radius: int = 7
    lk: LKParams = field(default_factory=LKParams)
    highpass_sigma: float | None = None
    max_reprojection_px: float = 1.0
    outlier_px: float = 1.0
    min_angle_deg: float = 5.0
    max_gap_frames: int = 60
    pixel_sigma: float | None = None
    min_pixel_sigma: float = 0.01

    def __post_init__(self):
        if self.max_points < 1:
            raise ValueError(f"max_points: at least 1 expected, got {self.max_points}")
        if not 0 < self.refill_fraction <= 1:
            raise ValueError(f"refill_fraction: in (0, 1] expected, got {self.refill_fraction}")
        if self.pixel_sigma is not None and not self.pixel_sigma > 0:
            raise ValueError(f"pixel_sigma: positive expected, got {self.pixel_sigma}")


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
    roi_frames : sequence of ndarray (H, W) uint8
        The first frames of the reference camera (for the automatic region of interest); ignored with ``roi``.
    roi : ndarray (H, W) bool, optional
        Region of interest in the reference camera.
    backend : image-ops backend for detection and matching (heartcv.backend), default OpenCV.
    """

    def __init__(self, cameras, options: MeasureOptions = MeasureOptions(), *, roi_frames=None, roi=None,
                 backend=None):
        self.cameras = list(cameras)
        self.opt = options
        self.backend = backend or OpenCVBackend()
        C = len(self.cameras)
        if C < 2:
            raise ValueError(f"cameras: at least 2 expected, got {C}")
        if not 0 <= options.ref_camera < C:
            raise ValueError(f"ref_camera: 0..{C - 1} expected, got {options.ref_camera}")
        ref = self.cameras[options.ref_camera]
        if roi is not None:
            roi = np.asarray(roi, bool)
            if roi.shape != (ref.height, ref.width):
                raise ValueError(f"roi: shape {(ref.height, ref.width)} expected, got {roi.shape}")
            m = roi
        else:
            if not roi_frames:
                raise ValueError("roi_frames: the first frames of the reference camera are needed without roi")
            m, _ = region_of_interest(roi_frames, margin=options.roi_margin_px)
        self.roi = m
        self._G = (2 * options.lk.ncc_radius + 1) ** 2
        # track state (grown by concatenation)
        self.ids = np.zeros(0, np.int64)
        self.birth = np.zeros(0, np.int64)
        self.tmpl_uv = np.zeros((0, C, 2))
        self.tmpl_patch = np.zeros((0, C, self._G), np.float32)
        self.last_uv = np.zeros((0, C, 2))
        self.last_X = np.zeros((0, 3))
        self.last_seen = np.zeros(0, np.int64)
        self.alive = np.zeros(0, bool)
        self._templates = {}          # birth step -> per camera template image (None where it was missing)
        self._records = []            # per step: (track indices, X, unit cov, rms, uv (n, C, 2))
        self._frames = []
        self.timings = {"tracking": 0.0, "triangulation": 0.0, "detection": 0.0}
        self.problems = []
        self._sq_resid = 0.0
        self._dof = 0
        self._last_spawn = None
        self.detected = False         # whether the last step detected and matched new points

    # -- one frame ------------------------------------------------------------------------------------------------
    def step(self, frame_index, images):
        """Process the images of one instant (one 8-bit gray array per camera, None where missing).

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
        track_images = [None if im is None else self._prefilter(im) for im in images]
        obs = self._track(s, track_images)
        t1 = time.perf_counter()
        idx, tri = self._triangulate(obs)
        t2 = time.perf_counter()
        seen = len(idx)
        ref = self.opt.ref_camera
        need = self.opt.refill_fraction * self.opt.max_points
        due = self._last_spawn is None or s - self._last_spawn >= self.opt.respawn_interval
        self.detected = seen < need and due and images[ref] is not None and sum(im is not None for im in images) >= 2
        if self.detected:
            self._last_spawn = s
            seen += self._spawn(s, images, track_images)
        t3 = time.perf_counter()
        self.timings["tracking"] += t1 - t0
        self.timings["triangulation"] += t2 - t1
        self.timings["detection"] += t3 - t2
        self._expire(s)
        return seen

    def _prefilter(self, gray):
        """The image the tracker sees: the gray image, or its high-pass ``128 + 2 (g - blur(g))`` (removes the slow
        shading changes of a moving, curved surface) with ``highpass_sigma``."""
        sig = self.opt.highpass_sigma
        if not sig:
            return gray
        import cv2

        blur = cv2.GaussianBlur(gray, (0, 0), sig)                    # uint8 in, uint8 out (SIMD)
        return cv2.addWeighted(gray, 2.0, blur, -2.0, 128.0)          # saturated to [0, 255]

    def _track(self, s, images):
        """Observations (P, C, 2) of the alive tracks in this frame (NaN where not accepted)."""
        C = len(self.cameras)
        P = len(self.ids)
        obs = np.full((P, C, 2), np.nan)
        if P == 0:
            return obs
        for b, tmpl in self._templates.items():
            for c in range(C):
                if images[c] is None or tmpl[c] is None:
                    continue
                sel = np.flatnonzero(self.alive & (self.birth == b) & np.isfinite(self.tmpl_uv[:, c, 0]))
                if sel.size == 0:
                    continue
                init = self.last_uv[sel, c]
                missing = ~np.isfinite(init).all(axis=1)
                if missing.any():
                    proj = self.cameras[c].project(self.last_X[sel[missing]])
                    init[missing] = proj
                uv, ok, _, _ = track_from_template(tmpl[c], images[c], self.tmpl_uv[sel, c],
                                                   self.tmpl_patch[sel, c], init, self.opt.lk)
                inside = self.cameras[c].in_image(uv, self.opt.lk.window / 2)
                ok &= inside
                obs[sel[ok], c] = uv[ok]
        return obs

    def _triangulate(self, obs):
        """Triangulate the observed tracks, record them; returns (track indices, Triangulation)."""
        idx = np.flatnonzero(np.isfinite(obs[..., 0]).sum(axis=1) >= 2)
        s = len(self._frames) - 1
        if idx.size == 0:
            self._records.append((idx, np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0),
                                  np.zeros((0, len(self.cameras), 2), np.float32)))
            return idx, None
        tri = triangulate(self.cameras, obs[idx], sigma_px=1.0, robust=True, outlier_px=self.opt.outlier_px,
                          max_rms_px=self.opt.max_reprojection_px, min_angle_deg=self.opt.min_angle_deg)
        good = tri.ok
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
        # next frame's starting guesses: the accepted views, and the projection of X for the others
        for c, cam in enumerate(self.cameras):
            p = cam.project(X)
            self.last_uv[i, c] = np.where(used[:, c, None], obs[i, c], p)
        lost = np.setdiff1d(np.flatnonzero(self.alive), i)
        self.last_uv[lost] = np.nan
        return i, tri

    def _spawn(self, s, images, track_images):
        """Detect and match new points in free parts of the region; returns how many were added."""
        o = self.opt
        ref = o.ref_camera
        C = len(self.cameras)
        current = self.last_uv[self.alive & (self.last_seen == s), ref]
        exclude = current[np.isfinite(current).all(axis=1)]
        gray = images[ref]
        mask = self.roi & ~saturation_mask(gray, o.saturation_level, grow=o.lk.window // 2)
        room = o.max_points - len(exclude)
        if room <= 0:
            return 0
        uv, _ = detect_corners(gray, mask, max_points=room, min_distance=o.min_distance_px, exclude=exclude,
                               block_size=o.corner_block_size, quality=o.corner_quality, backend=self.backend)
        if len(uv) == 0:
            return 0
        imgs = [None if im is None else np.asarray(im, np.float32) for im in images]
        m = match_points(self.cameras, imgs, ref, uv, radius=o.match_radius, min_ncc=o.match_min_ncc,
                         backend=self.backend)
        keep = m.ok
        for c, cam in enumerate(self.cameras):
            inside = cam.in_image(np.nan_to_num(m.uv[:, c], nan=-1e9), o.lk.window)
            m.uv[~inside, c] = np.nan
        keep &= np.isfinite(m.uv[..., 0]).sum(axis=1) >= 2
        if not keep.any():
            return 0
        uvk = m.uv[keep]
        tri = triangulate(self.cameras, uvk, sigma_px=1.0, robust=True, outlier_px=o.outlier_px,
                          max_rms_px=o.max_reprojection_px, min_angle_deg=o.min_angle_deg)
        good = tri.ok
        if not good.any():
            return 0
        uvk = np.where(tri.used[good][..., None], uvk[good], np.nan)
        n = len(uvk)
        patches = np.full((n, C, self._G), np.nan, np.float32)
        for c in range(C):
            has = np.isfinite(uvk[:, c, 0])
            if has.any():
                patches[has, c] = template_patches(track_images[c], uvk[has, c], o.lk)
        start = int(self.ids[-1]) + 1 if len(self.ids) else 0
        self.ids = np.r_[self.ids, start + np.arange(n)]
        self.birth = np.r_[self.birth, np.full(n, s)]
        self.tmpl_uv = np.concatenate([self.tmpl_uv, uvk])
        self.tmpl_patch = np.concatenate([self.tmpl_patch, patches])
        self.last_uv = np.concatenate([self.last_uv, uvk])
        self.last_X = np.concatenate([self.last_X, tri.points[good]])
        self.last_seen = np.r_[self.last_seen, np.full(n, s)]
        self.alive = np.r_[self.alive, np.ones(n, bool)]
        self._templates[s] = list(track_images)
        new = np.arange(len(self.ids) - n, len(self.ids))
        i, X, cov, rms, uv = self._records[-1]
        self._records[-1] = (np.r_[i, new], np.concatenate([X, tri.points[good]]),
                             np.concatenate([cov, tri.covariances[good]]), np.r_[rms, tri.rms_px[good]],
                             np.concatenate([uv, uvk.astype(np.float32)]))
        used = tri.used[good]
        self._sq_resid += float((np.where(used, tri.reprojection_px[good], 0.0) ** 2).sum())
        self._dof += int((2 * used.sum(axis=1) - 3).sum())
        return n

    def _expire(self, s):
        """End tracks unseen for too long; drop template images nobody uses."""
        gone = self.alive & (s - self.last_seen > self.opt.max_gap_frames)
        self.alive &= ~gone
        live_births = set(np.unique(self.birth[self.alive]).tolist())
        for b in list(self._templates):
            if b not in live_births and b != s:
                del self._templates[b]

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
                         np.asarray(tracker.roi, bool).copy(), dict(tracker.timings), list(tracker.problems))


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
    """

    result: MeasureResult
    frames: tuple
    problems: tuple
    setup_s: float

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


def auto_region(roi_frames, options: MeasureOptions) -> np.ndarray:
    """The automatic region of interest (:func:`heartcv.features.region_of_interest`) of the reference camera's
    first frames.

    Raises
    ------
    InputError
        No frame (none of the first frames of the reference camera could be read); field ``images``.
    MeasureFailed
        No textured surface found in them.
    """
    if not roi_frames:
        raise InputError(None, f"none of the reference camera's frames {ROI_FRAMES.start}, "
                               f"{ROI_FRAMES.start + ROI_FRAMES.step}, ... can be read", "images")
    try:
        mask, _ = region_of_interest(roi_frames, margin=options.roi_margin_px)
    except RegionNotFound as exc:  # its documented failure: no (or too little) textured surface in the frames
        raise MeasureFailed(str(exc)) from None
    return mask


def measure_sequence(frames, cameras, options: MeasureOptions = MeasureOptions(), *, roi=None, roi_frames=(),
                     backend=None, clock=time.perf_counter) -> SequenceRun:
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
    measurer = Measurer(cameras, options, roi=roi, backend=backend)
    run = run_frames(measurer, frames, clock, clock() - t0)
    if run.result.point_ids.size == 0 or not run.result.seen.any():
        raise MeasureFailed(f"no surface point could be tracked (region of interest {int(run.result.roi.sum())} px "
                            f"in camera {measurer.cameras[options.ref_camera].name})")
    return run


def run_frames(tracker, frames, clock, setup_s) -> SequenceRun:
    """Feed every instant of ``frames`` (``(k, images, problems)``) to a frame-by-frame tracker (:class:`Measurer`,
    ``heartcv.dense.DenseTracker``: ``step``, ``skip``, ``unusable``, ``timings``, ``detected``, ``result``) and
    time each instant; instants the tracker cannot use are recorded with all points missing."""
    stats, problems = [], []
    it = iter(frames)
    prev = clock()
    while True:
        t_wait = clock()
        item = next(it, None)
        if item is None:
            break
        k, images, probs = item
        t_got = clock()
        problems.extend((int(k), str(m)) for m in probs)
        before = dict(tracker.timings)
        why = tracker.unusable(images)
        if why is not None:
            tracker.skip(k, f"frame {k}: {why}")
            seen = 0
        else:
            seen = tracker.step(k, images)
        now = clock()
        d = {key: tracker.timings[key] - before[key] for key in before}
        stats.append(FrameStats(int(k), t_got - t_wait, now - prev, d["tracking"], d["triangulation"],
                                d["detection"], int(seen), why is None and tracker.detected, why is not None))
        prev = now
    return SequenceRun(tracker.result(), tuple(stats), tuple(problems), setup_s)
