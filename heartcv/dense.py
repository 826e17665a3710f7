"""Dense surface measurement from a stereo pair: semi-global matching for depth, dense optical flow for tracks.

The mode of ``heartcv measure --dense``: instead of a few hundred corners matched and tracked by Lucas–Kanade
(:mod:`heartcv.measure`), thousands of points on a regular grid of the reference image, carried from frame to frame
by dense optical flow, each triangulated in every frame from a dense disparity map. The result is the same
:class:`heartcv.measure.MeasureResult` (tracks with persistent ids, positions, covariances), so it is written to
the same measurement file.

Method, per instant (two cameras: the reference camera and its partner; with more cameras the partner is the
camera whose projection centre lies farthest from the reference camera's, i.e. the widest baseline, and the
others are not used):

1. *Rectification* of the pair from the calibration (``cv2.stereoRectify`` with zero disparity at infinity,
   ``cv2.initUndistortRectifyMap``). For a rig that is already rectified (no distortion, equal intrinsics, the
   partner displaced along the reference camera's x axis) this is the identity to 1e-3 px, which is checked, and
   the remapping is skipped. Vertical baselines are not supported. ``stereoRectify``'s focal length is the
   cameras' mean fy; for pixels taller than wide (fy < fx: one field of interlaced video) the rectified images get
   ``round(H mean fx / mean fy)`` rows instead, so that it is the mean fx and the columns keep their resolution.
2. *Disparity*: semi-global matching ([SGM]; ``cv2.StereoSGBM``, 3-way mode by default, ``P1 = 8 b^2``,
   ``P2 = 32 b^2`` for blocks of b x b pixels, OpenCV's speckle filter) from the left image to the right one and,
   with the mirrored matcher (``cv2.ximgproc.createRightMatcher``), from the right image to the left one. Each
   matcher sees its images padded by the largest disparity on the side where OpenCV leaves the first columns
   unmatched, so the whole image is searched. A reference pixel's disparity is valid where the two maps agree
   (left-right consistency within ``lr_tolerance_px``), its match lies inside the partner image, neither it nor
   its match lies on a specular highlight (gray >= ``saturation_level``, grown by ``saturation_grow_px``, in each
   image, per frame).
3. *Tracks*: points are seeded at the centres of the cells of a regular grid (``grid_step_px``) of the
   rectified reference image where the disparity is valid, and carried from frame to frame by dense inverse
   search optical flow ([DIS]; ``cv2.DISOpticalFlow``) of the reference camera, with a forward–backward check
   ([FB]): the backward flow at the carried position must return within ``fb_tolerance_px``. A point is missing in
   a frame where the check fails or where its disparity is invalid; it is still carried by the flow and resumes
   when it is valid again; it ends after ``max_gap_frames`` frames missing in a row, or at once when it leaves the
   image. *Reseeding*: when fewer than
   ``reseed_fraction`` of the cell centres with a valid disparity have a point seen in this frame within one grid
   step, a new point (a new id, born in this frame) is put on every such centre inside the region of interest
   with no alive point (seen or missing) within one grid step. The region of interest restricts where points are
   born, as in the sparse mode, not where they are seen: a point of the surface carried out of it by the motion
   is still measured. (Filling every cell without a point instead creates new points wherever the
   flow has moved the old ones a little -- 12 000 points in 60 frames of the in-vivo heart instead of 3 700 --
   and the distance criterion keeps the density near one point per cell.) At most ``max_tracks`` points are
   created over the sequence: the result holds dense (K, P, ...) arrays, about 130 bytes per frame and point
   (0.8 GB for 300 frames and 20 000 points); once the cap is reached no more points are seeded (logged). On the
   300 in-vivo frames (360x288) about 5 700 points are created (automatic region of interest).
4. *Triangulation*, closed form on the rectified pair: with rectified focal length f, principal point
   (cx, cy) and the partner's centre at (b, 0, 0) in the rectified reference frame, a point at (u, v) with
   disparity d = u - u' (u' its match in the partner) lies at ``X = b / d (u - cx, v - cy, f)``, mapped to the rig
   frame by the rectifying rotation and the reference camera's pose. Its unit covariance is
   ``(J_r^T J_r + J_p^T J_p)^-1``, J the Jacobians of the two rectified pinhole projections at X -- the
   covariance of :func:`heartcv.triangulation.triangulate` for isotropic pixel noise in both (rectified) images
   ([HZ] §5.2). The point reprojects exactly onto (u, v) and (u - d, v), so on a rectified rig without
   distortion positions and covariances are those of ``triangulate`` (tested to 1e-6 relative) at a fraction
   of the cost, and the reprojection RMS is 0.
5. *Pixel noise*: unless ``pixel_sigma`` is given, ``sigma_px`` is estimated from the sub-pixel disparity
   residuals ``r = d_SGBM - d_LK`` of up to 500 points a frame (pooled over the sequence), ``d_LK`` an independent
   sub-pixel disparity: 1-D Lucas–Kanade along the rectified row (:func:`refine_disparity`, zero-mean SSD over
   (b/2 + 1)-radius patches) started at the SGBM disparity; residuals beyond ``lr_tolerance_px`` (LK diverged, or
   a gross SGBM error) are left out. The refinement is 2-3 times more accurate than SGBM's parabolic sub-pixel
   interpolation (0.044 against 0.11 px RMS on a textured plane), so ``rms(r)`` estimates the disparity error
   ``sigma_d`` of SGBM (slightly high), and a disparity triangulated from two pixel observations of noise
   ``sigma_px`` each has ``sigma_d^2 = 2 sigma_px^2``: ``sigma_px = rms(r) / sqrt(2)``, floored at
   ``min_pixel_sigma``. Covariances are the unit covariances times ``sigma_px^2``, as in the sparse path. (The
   left-right consistency residuals were tried first: the two SGBM maps share their matching costs and their
   pixel-locking errors, and ``rms / 2`` came out at half the true error on the synthetic plane, normalised
   errors of 2.1 against 0.92 with this estimate.) On the in-vivo heart ``sigma_px`` is about 0.29 px.

Limitations: tracks are carried from frame to frame (not from their birth image, unlike :mod:`heartcv.klt`), so
their image positions drift slowly (a random walk of the flow error); a point's id follows the surface only as
well as the flow does. Positions are in the rig frame, metres.

References
----------
.. [SGM] H. Hirschmüller, "Stereo processing by semiglobal matching and mutual information", IEEE TPAMI 30(2),
   328-341, 2008.
.. [DIS] T. Kroeger, R. Timofte, D. Dai and L. Van Gool, "Fast optical flow using dense inverse search",
   ECCV 2016.
.. [FB] Z. Kalal, K. Mikolajczyk and J. Matas, "Forward-backward error: automatic detection of tracking
   failures", ICPR 2010.
.. [HZ] R. Hartley and A. Zisserman, *Multiple View Geometry in Computer Vision*, 2nd ed., 2004.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import logging
import math
import time

import numpy as np

from .camera import Camera, Rig, invert_pose
from .features import saturation_mask
from .measure import MeasureFailed, MeasureResult, SequenceRun, WorkingView, assemble_result, run_frames

__all__ = ["DenseOptions", "StereoPair", "DenseTracker", "dense_sequence", "refine_disparity", "default_grid_step",
           "default_block_size"]

logger = logging.getLogger(__name__)

_SGBM_MODES = ("3way", "hh", "sgbm", "hh4")
_FLOW_PRESETS = ("ultrafast", "fast", "medium")
# largest pixel displacement of a rectification that counts as the identity (the remapping is skipped)
_IDENTITY_PX = 1e-3
# points per frame of the noise probe (step 5): enough for a pooled estimate, cheap (a few ms a frame)
_PROBE_POINTS = 500


def default_grid_step(width: int, height: int) -> int:
    """Seed grid step (px): ``max(4, round(min(W, H) / 60))`` -- 5 px at 360x288 (about 4 000 cells), 18 px at
    1920x1080 (about 6 000 cells)."""
    return max(4, round(min(width, height) / 60))


def default_block_size(width: int, height: int) -> int:
    """SGBM block side (px, odd): ``round(min(W, H) / 60)`` made odd, within 3..11 -- 5 at 360x288, 11 at
    1920x1080."""
    b = round(min(width, height) / 60)
    b += 1 - b % 2
    return int(min(max(b, 3), 11))


def _ceil16(n) -> int:
    return int(16 * math.ceil(n / 16))


@dataclass(frozen=True)
class DenseOptions:
    """Settings of the dense measurement (module docstring); ``None`` means derived from the image size or rig.

    Attributes
    ----------
    ref_camera : int
        Reference camera (seeds, flow, region of interest).
    grid_step_px : int or None
        Seed grid step; default :func:`default_grid_step` (5 px at 360x288: a few thousand seeds).
    disparity_range_px : (int, int) or None
        Smallest and largest disparity searched (px, rectified). Default: from ``depth_range_m``, else measured
        on the first pair (below).
    depth_range_m : (float, float) or None
        Nearest and farthest depth (m): disparities ``f |b| / z`` of the rectified pair. Without either range, the
        first pair is matched at half resolution over disparities 0 .. W/2 and the 1st..99th percentiles of its
        consistent disparities, widened by ``range_margin`` (relative, at least 8 px), are used for the whole
        sequence (a documented default for an unknown scene).
    range_margin : float
        Relative widening of the disparity range measured on the first pair (not of a given range).
    block_size : int or None
        SGBM block side (odd, 3..11); default :func:`default_block_size`. ``P1 = 8 b^2``, ``P2 = 32 b^2``.
    sgbm_mode : {'3way', 'hh', 'sgbm', 'hh4'}
        ``cv2.StereoSGBM`` mode (3-way: 8 directions' worth of smoothing at the cost of 3 passes, fastest).
    uniqueness_ratio : int
        SGBM uniqueness margin (per cent).
    speckle_window : int or None
        Largest connected disparity blob (px) removed as a speckle; default ``max(20, W H / 2000)``.
    speckle_range_px : int
        Disparity variation within a connected blob (px).
    lr_tolerance_px : float
        Left-right consistency tolerance (px).
    fb_tolerance_px : float
        Forward-backward optical flow tolerance (px).
    flow_preset : {'ultrafast', 'fast', 'medium'}
        ``cv2.DISOpticalFlow`` preset (medium: 9 ms a flow at 360x288 on 2 cores, 0.05 px RMS on a textured
        plane).
    flow_finest_scale : int or None
        Finest pyramid level of the flow (0: full resolution, 3x more accurate and 3.5x slower than the medium
        preset's level 1); default the preset's.
    reseed_fraction : float
        Reseed when fewer than this fraction of the grid cell centres with a valid disparity have a point seen in
        this frame within one grid step.
    max_gap_frames : int
        A point missing for more frames in a row ends (10: 0.4 s at 25 fps; on the in-vivo heart 5 gives 9 600
        points over 300 frames with a median track of 25 frames, 10 gives 7 900 points, median 62 frames;
        measured on the whole image, before the automatic region of interest).
    max_tracks : int
        Most points created over the sequence (bounds the memory of the result).
    saturation_level : int
        Gray level of specular highlights (per frame, both images).
    saturation_grow_px : int
        Highlights are grown by this many pixels.
    pixel_sigma : float or None
        Pixel noise for the covariances; default estimated (module docstring, step 5).
    min_pixel_sigma : float
        Floor of the estimated pixel noise (px).
    """

    ref_camera: int = 0
    grid_step_px: int | None = None
    disparity_range_px: tuple | None = None
    depth_range_m: tuple | None = None
    range_margin: float = 0.15
    block_size: int | None = None
    sgbm_mode: str = "3way"
    uniqueness_ratio: int = 10
    speckle_window: int | None = None
    speckle_range_px: int = 2
    lr_tolerance_px: float = 1.0
    fb_tolerance_px: float = 1.0
    flow_preset: str = "medium"
    flow_finest_scale: int | None = None
    reseed_fraction: float = 0.8
    max_gap_frames: int = 10
    max_tracks: int = 20_000
    saturation_level: int = 250
    saturation_grow_px: int = 3
    pixel_sigma: float | None = None
    min_pixel_sigma: float = 0.02

    def __post_init__(self):
        def integer(name, lo):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ValueError(f"{name}: an integer >= {lo} expected, got {v!r}")

        integer("ref_camera", 0)
        if self.grid_step_px is not None:
            integer("grid_step_px", 1)
        if self.disparity_range_px is not None:
            r = tuple(self.disparity_range_px)
            if len(r) != 2 or not all(isinstance(x, (int, np.integer)) and not isinstance(x, bool) for x in r) \
                    or not 0 <= r[0] < r[1]:
                raise ValueError(f"disparity_range_px: two integers 0 <= min < max expected, got {r!r}")
        if self.depth_range_m is not None:
            r = tuple(self.depth_range_m)
            if len(r) != 2 or not all(np.isfinite(x) for x in r) or not 0 < r[0] < r[1]:
                raise ValueError(f"depth_range_m: two depths 0 < near < far expected, got {r!r}")
        if not 0 <= self.range_margin <= 1:
            raise ValueError(f"range_margin: in [0, 1] expected, got {self.range_margin}")
        if self.block_size is not None:
            integer("block_size", 3)
            if self.block_size % 2 == 0 or self.block_size > 11:
                raise ValueError(f"block_size: an odd integer in 3..11 expected, got {self.block_size}")
        if self.sgbm_mode not in _SGBM_MODES:
            raise ValueError(f"sgbm_mode: one of {_SGBM_MODES} expected, got {self.sgbm_mode!r}")
        integer("uniqueness_ratio", 0)
        if self.speckle_window is not None:
            integer("speckle_window", 0)
        integer("speckle_range_px", 1)
        for name in ("lr_tolerance_px", "fb_tolerance_px"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: positive expected, got {getattr(self, name)}")
        if self.flow_preset not in _FLOW_PRESETS:
            raise ValueError(f"flow_preset: one of {_FLOW_PRESETS} expected, got {self.flow_preset!r}")
        if self.flow_finest_scale is not None:
            integer("flow_finest_scale", 0)
        if not 0 < self.reseed_fraction <= 1:
            raise ValueError(f"reseed_fraction: in (0, 1] expected, got {self.reseed_fraction}")
        integer("max_gap_frames", 0)
        integer("max_tracks", 1)
        integer("saturation_level", 1)
        if self.saturation_level > 256:
            raise ValueError(f"saturation_level: 1..256 expected (256: no masking), got {self.saturation_level}")
        integer("saturation_grow_px", 0)
        if self.pixel_sigma is not None and not self.pixel_sigma > 0:
            raise ValueError(f"pixel_sigma: positive expected, got {self.pixel_sigma}")
        if not self.min_pixel_sigma > 0:
            raise ValueError(f"min_pixel_sigma: positive expected, got {self.min_pixel_sigma}")


# =====================================================================================================================
# The rectified pair and its closed-form triangulation
# =====================================================================================================================
@dataclass(frozen=True)
class StereoPair:
    """The reference camera and its partner, rectified (module docstring, steps 1 and 4).

    Attributes
    ----------
    cameras : tuple of Camera        the whole rig
    ref, other : int                 indices of the reference camera and its partner
    width, height : int              the original images' size (px)
    rect_width, rect_height : int    the rectified images' size (px): the original size, except for cameras whose
                                     pixels are taller than wide (fy < fx: one field of interlaced video), whose
                                     rows are resampled so that ``f`` is fx, the horizontal resolution
    f, cx, cy : float                rectified focal length and principal point (px), the same in both rectified
                                     cameras (zero disparity at infinity)
    baseline : float                 x of the partner's centre in the rectified reference frame (m): > 0 when the
                                     partner is to the right (the reference image is the left one)
    rig_from_rect : ndarray (4, 4)   rig frame from the rectified reference camera frame
    identity : bool                  the rectification is the identity: images are used as they are
    maps : tuple or None             ``(ref maps, other maps)`` of ``cv2.remap`` (None with ``identity``)
    """

    cameras: tuple
    ref: int
    other: int
    width: int
    height: int
    f: float
    cx: float
    cy: float
    baseline: float
    rig_from_rect: np.ndarray
    identity: bool
    maps: tuple | None
    rect_width: int = 0
    rect_height: int = 0

    def __post_init__(self):
        if not self.rect_width:
            object.__setattr__(self, "rect_width", self.width)
        if not self.rect_height:
            object.__setattr__(self, "rect_height", self.height)

    @classmethod
    def from_cameras(cls, cameras, ref: int = 0) -> "StereoPair":
        """Pick the partner of camera ``ref`` (the widest baseline) and rectify the pair.

        Raises
        ------
        ValueError
            Fewer than two cameras, ``ref`` out of range, image sizes that differ, coincident centres or a
            vertical baseline.
        """
        import cv2

        cams = tuple(cameras.cameras if isinstance(cameras, Rig) else cameras)
        if len(cams) < 2 or not all(isinstance(c, Camera) for c in cams):
            raise ValueError(f"cameras: at least 2 Camera expected, got {len(cams)}")
        if isinstance(ref, bool) or not 0 <= ref < len(cams):
            raise ValueError(f"ref_camera: 0..{len(cams) - 1} expected, got {ref}")
        a = cams[ref]
        dist = [np.linalg.norm(c.centre - a.centre) if i != ref else -1.0 for i, c in enumerate(cams)]
        other = int(np.argmax(dist))
        b = cams[other]
        if dist[other] <= 0:
            raise ValueError(f"cameras {a.name} and {b.name}: coincident projection centres (no baseline)")
        if (a.width, a.height) != (b.width, b.height):
            raise ValueError(f"cameras {a.name} and {b.name}: the image sizes differ ({a.width}x{a.height}, "
                             f"{b.width}x{b.height}); dense matching needs equal sizes")
        W, H = a.width, a.height
        # stereoRectify's focal length is the cameras' mean fy times (rectified rows / rows): for pixels taller
        # than wide (fy < fx: one field of interlaced video) the rows are resampled so that it is their mean fx,
        # the resolution along the disparity (else the columns would be squeezed, half the image black for a field)
        Hr = max(H, int(round(H * (a.K[0, 0] + b.K[0, 0]) / (a.K[1, 1] + b.K[1, 1]))))
        T = b.cam_from_rig @ invert_pose(a.cam_from_rig)                      # other_from_ref
        R1, R2, P1, P2, *_ = cv2.stereoRectify(a.K, a.dist.copy(), b.K, b.dist.copy(), (W, H),
                                               T[:3, :3].copy(), T[:3, 3].reshape(3, 1).copy(),
                                               flags=cv2.CALIB_ZERO_DISPARITY, alpha=-1, newImageSize=(W, Hr))
        if abs(P2[1, 3]) > abs(P2[0, 3]):
            raise ValueError(f"cameras {a.name} and {b.name}: vertical baseline; dense matching needs the partner "
                             "displaced mostly along the reference camera's x axis")
        f = float(P1[0, 0])
        # identity: the rectifying rotations move no pixel (at most 2 f |R - I| px) and the new intrinsics are the
        # old ones, each to _IDENTITY_PX
        rot_px = 2 * f * max(np.abs(R1 - np.eye(3)).max(), np.abs(R2 - np.eye(3)).max())
        identity = (Hr == H and not a.dist.any() and not b.dist.any() and rot_px <= _IDENTITY_PX
                    and max(np.abs(P1[:3, :3] - a.K).max(), np.abs(P2[:3, :3] - b.K).max()) <= _IDENTITY_PX)
        if identity:
            # the original cameras are the rectified ones: use their exact intrinsics (not OpenCV's float32 echo)
            K = a.K
            R1 = np.eye(3)
            f, cx, cy = float(K[0, 0]), float(K[0, 2]), float(K[1, 2])
            baseline = float(-(T[:3, :3].T @ T[:3, 3])[0])                     # the partner's centre, x
            maps = None
        else:
            cx, cy = float(P1[0, 2]), float(P1[1, 2])
            baseline = float(-P2[0, 3] / P2[0, 0])
            maps = tuple(cv2.initUndistortRectifyMap(c.K, c.dist.copy(), Rr, P[:3, :3], (W, Hr), cv2.CV_16SC2)
                         for c, Rr, P in ((a, R1, P1), (b, R2, P2)))
        rect_from_refcam = np.eye(4)
        rect_from_refcam[:3, :3] = R1
        rig_from_rect = invert_pose(a.cam_from_rig) @ invert_pose(rect_from_refcam)
        logger.debug("dense pair %s-%s: f %.3f px, baseline %.6g m, identity rectification %s", a.name, b.name, f,
                     baseline, identity)
        return cls(cams, int(ref), other, W, H, f, cx, cy, baseline, rig_from_rect, bool(identity), maps, W, Hr)

    def rectify(self, ref_image, other_image):
        """The rectified (reference, partner) images (the same arrays with the identity rectification)."""
        if self.identity:
            return ref_image, other_image
        import cv2

        return tuple(cv2.remap(im, m[0], m[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
                     for im, m in zip((ref_image, other_image), self.maps))

    def rectify_mask(self, mask) -> np.ndarray:
        """A bool mask of the reference camera in the rectified reference image (nearest pixel; False outside)."""
        if self.identity:
            return np.asarray(mask, bool)
        import cv2

        m = self.maps[0]
        return cv2.remap(np.asarray(mask, np.uint8), m[0], m[1], cv2.INTER_NEAREST,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0

    def triangulate(self, uv, disparity) -> tuple[np.ndarray, np.ndarray]:
        """Closed-form triangulation of rectified reference pixels and their disparities.

        Parameters
        ----------
        uv : ndarray (N, 2)
            Rectified reference pixels.
        disparity : ndarray (N,)
            ``u - u_partner`` in the rectified images (px; same sign as :attr:`baseline`).

        Returns
        -------
        X : ndarray (N, 3)
            Rig-frame positions (m); NaN where the disparity is 0 or of the wrong sign (behind the cameras).
        cov : ndarray (N, 3, 3)
            Unit covariances (1 px noise per coordinate in both rectified images), rig frame (m^2).
        """
        uv = np.asarray(uv, float).reshape(-1, 2)
        d = np.asarray(disparity, float).reshape(-1)
        f, b = self.f, self.baseline
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(d * b > 0, b / d, np.nan)                            # Z / f
        Xr = np.stack([(uv[:, 0] - self.cx) * s, (uv[:, 1] - self.cy) * s, f * s], axis=1)
        Z = Xr[:, 2]
        a2 = (f / Z) ** 2
        ex, ey, ex2 = Xr[:, 0] / Z, Xr[:, 1] / Z, (Xr[:, 0] - b) / Z
        M = np.zeros((len(d), 3, 3))                                          # J_r^T J_r + J_p^T J_p
        M[:, 0, 0] = 2
        M[:, 1, 1] = 2
        M[:, 0, 2] = M[:, 2, 0] = -(ex + ex2)
        M[:, 1, 2] = M[:, 2, 1] = -2 * ey
        M[:, 2, 2] = ex * ex + ex2 * ex2 + 2 * ey * ey
        M *= a2[:, None, None]
        ok = np.isfinite(M).all(axis=(1, 2))
        cov = np.full_like(M, np.nan)
        if ok.any():
            cov[ok] = np.linalg.inv(M[ok])
        A = self.rig_from_rect[:3, :3]
        X = Xr @ A.T + self.rig_from_rect[:3, 3]
        cov = A @ cov @ A.T
        return X, cov

    def original_pixels(self, uv, disparity, X) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) of the points in the original reference and partner images: ``(u, v)`` and
        ``(u - d, v)`` with the identity rectification, else the projections of ``X`` (rig frame)."""
        uv = np.asarray(uv, float).reshape(-1, 2)
        if self.identity:
            other = np.stack([uv[:, 0] - disparity, uv[:, 1]], axis=1)
            return uv.copy(), other
        return self.cameras[self.ref].project(X), self.cameras[self.other].project(X)


# =====================================================================================================================
# Disparity: SGBM both ways, left-right check, highlights
# =====================================================================================================================
class _Matcher:
    """SGBM from left to right and back on padded images; disparities in the reference camera's sign convention
    (``u_ref - u_partner``, the sign of the baseline)."""

    def __init__(self, opt: DenseOptions, width: int, height: int, d_min: int, d_max: int, ref_is_left: bool):
        import cv2

        self.d_min = int(d_min)
        self.num = _ceil16(max(d_max - d_min + 1, 16))
        self.d_max = self.d_min + self.num - 1
        self.pad = self.d_max + 1
        self.ref_is_left = ref_is_left
        self.width = width
        b = opt.block_size or default_block_size(width, height)
        window = opt.speckle_window if opt.speckle_window is not None else max(20, width * height // 2000)
        mode = {"3way": cv2.StereoSGBM_MODE_SGBM_3WAY, "hh": cv2.StereoSGBM_MODE_HH,
                "sgbm": cv2.StereoSGBM_MODE_SGBM, "hh4": cv2.StereoSGBM_MODE_HH4}[opt.sgbm_mode]
        self.left = cv2.StereoSGBM_create(minDisparity=self.d_min, numDisparities=self.num, blockSize=b,
                                          P1=8 * b * b, P2=32 * b * b, disp12MaxDiff=-1, preFilterCap=63,
                                          uniquenessRatio=opt.uniqueness_ratio, speckleWindowSize=window,
                                          speckleRange=opt.speckle_range_px, mode=mode)
        self.right = cv2.ximgproc.createRightMatcher(self.left)
        self.tol16 = opt.lr_tolerance_px * 16
        self.block = b
        self.n_good = 0             # consistent disparities returned, over the sequence
        self.n_clamped = 0          # consistent matches at an end of the range (left out: beyond the range)

    def compute(self, ref, other):
        """``(disparity, match column)`` (H, W) on the reference image: the disparity (px, float32) where left-right
        consistent and the match lies inside the partner image, NaN elsewhere; the partner's column of each pixel's
        match (int, clipped to the image)."""
        import cv2

        left, right = (ref, other) if self.ref_is_left else (other, ref)
        p = self.pad
        W = self.width
        dl = self.left.compute(cv2.copyMakeBorder(left, 0, 0, p, 0, cv2.BORDER_REPLICATE),
                               cv2.copyMakeBorder(right, 0, 0, p, 0, cv2.BORDER_REPLICATE))[:, p:]
        dr = self.right.compute(cv2.copyMakeBorder(right, 0, 0, 0, p, cv2.BORDER_REPLICATE),
                                cv2.copyMakeBorder(left, 0, 0, 0, p, cv2.BORDER_REPLICATE))[:, :W]
        # |disparity| * 16 of the reference image (prim) and of the partner image (sec): the left map holds
        # x_l - x_r >= 0, the right one x_r - x_l <= 0; sgn: the sign of u_ref - u_partner
        if self.ref_is_left:
            prim, sec, sgn = dl.astype(np.int32), -dr.astype(np.int32), 1
        else:
            prim, sec, sgn = -dr.astype(np.int32), dl.astype(np.int32), -1
        lo, hi = self.d_min * 16, self.d_max * 16
        # a disparity at an end of the searched range is SGBM's clamp of a match beyond it (a surface nearer, or
        # farther, than the range measured on the first pair), not a measurement: invalid (d_min 0 is infinity)
        valid = ((prim > lo) | (self.d_min == 0)) & (prim >= lo) & (prim < hi)
        xs = np.arange(W, dtype=np.int32)[None, :]
        # the match's column in the partner image (nearest pixel)
        xm = xs - sgn * ((prim + 8) >> 4)
        inside = valid & (xm >= 0) & (xm < W)
        xm = np.clip(xm, 0, W - 1)
        back = np.take_along_axis(sec, xm, axis=1)                            # |d| of the partner's map at the match
        back_ok = (back >= lo) & (back <= hi)
        good = inside & back_ok & (np.abs(prim - back) <= self.tol16)
        edge = ((prim == hi) | ((prim == lo) & (self.d_min > 0))) & (np.abs(prim - back) <= self.tol16)
        self.n_good += int(good.sum())
        self.n_clamped += int(edge.sum())
        disp = np.where(good, sgn * prim.astype(np.float32) / 16.0, np.nan).astype(np.float32)
        return disp, xm


def _probe_range(opt, ref, other, ref_is_left) -> tuple[int, int] | None:
    """Disparity range (px) of the 1st..99th percentiles of the consistent disparities of a half-resolution
    match over 0 .. W/2, widened by ``range_margin`` (at least 8 px); None with fewer than 100 such pixels."""
    import cv2

    small = [cv2.pyrDown(im) for im in (ref, other)]
    h, w = small[0].shape
    m = _Matcher(opt, w, h, 0, max(16, w // 2), ref_is_left)
    disp, _ = m.compute(*small)
    d = np.abs(disp[np.isfinite(disp)]) * 2
    if d.size < 100:
        return None
    lo, hi = np.percentile(d, [1, 99])
    return _widen(lo, hi, opt.range_margin)


def _widen(lo, hi, margin) -> tuple[int, int]:
    m = max(8.0, margin * hi)
    return max(0, int(math.floor(lo - m))), int(math.ceil(hi + m))


def refine_disparity(ref, other, uv, disparity, *, radius=3, iterations=8) -> np.ndarray:
    """Sub-pixel disparities by 1-D Lucas–Kanade along the rectified rows (the noise probe of step 5).

    Gauss–Newton on the zero-mean sum of squared differences between the ``(2 radius + 1)^2`` patch of ``ref``
    around each point and the patch of ``other`` around ``(u - d, v)``, over the horizontal shift ``d`` only
    (bilinear sampling, image gradient of ``other`` by central differences), from the given disparities.

    Parameters
    ----------
    ref, other : ndarray (H, W) uint8     rectified reference and partner images
    uv : ndarray (N, 2)                   points in ``ref``
    disparity : ndarray (N,)              starting disparities (``u - u_other``)

    Returns
    -------
    ndarray (N,)
        Refined disparities; NaN where the patch of ``other`` has no horizontal gradient.
    """
    import cv2

    uv = np.asarray(uv, np.float32).reshape(-1, 2)
    N = len(uv)
    o = np.arange(-radius, radius + 1, dtype=np.float32)
    oy, ox = np.meshgrid(o, o, indexing="ij")
    mx = (uv[:, 0, None] + ox.ravel()).astype(np.float32)
    my = (uv[:, 1, None] + oy.ravel()).astype(np.float32)
    R = np.asarray(other, np.float32)
    Rx = cv2.Sobel(R, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
    T = cv2.remap(np.asarray(ref, np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    T -= T.mean(axis=1, keepdims=True)
    t = np.asarray(disparity, np.float32).reshape(-1).copy()
    ok = np.ones(N, bool)
    for _ in range(iterations):
        xs = mx - t[:, None]
        I = cv2.remap(R, xs, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        G = cv2.remap(Rx, xs, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        I -= I.mean(axis=1, keepdims=True)
        G -= G.mean(axis=1, keepdims=True)
        gg = (G * G).sum(axis=1)
        ok = gg > 1e-6
        # residual T - I(x - t): d I(x - t) / dt = -G, so the Gauss-Newton step is -sum((T - I) G) / sum(G^2)
        t -= np.where(ok, ((T - I) * G).sum(axis=1) / np.where(ok, gg, 1.0), 0.0)
    return np.where(ok, t, np.nan).astype(float)


# =====================================================================================================================
# The tracker
# =====================================================================================================================
def _sample(field, uv):
    """Bilinear samples of a (H, W, k) float32 field at (N, 2) points (edge values outside)."""
    import cv2

    m = np.ascontiguousarray(uv, np.float32).reshape(1, -1, 2)
    out = cv2.remap(field, m, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(len(uv), -1)


def _sample_disparity(disp, uv, tol):
    """Disparity at sub-pixel points: bilinear over the 2x2 neighbours with a nonzero weight, NaN where one of them
    is invalid or they differ by more than ``tol`` (a depth edge)."""
    H, W = disp.shape
    x0 = np.floor(uv[:, 0]).astype(np.int64)
    y0 = np.floor(uv[:, 1]).astype(np.int64)
    fx = uv[:, 0] - x0
    fy = uv[:, 1] - y0
    acc = np.zeros(len(uv))
    lo = np.full(len(uv), np.inf)
    hi = np.full(len(uv), -np.inf)
    ok = np.ones(len(uv), bool)
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        w = (fx if dx else 1 - fx) * (fy if dy else 1 - fy)
        x = x0 + dx
        y = y0 + dy
        used = w > 0
        inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
        v = np.full(len(uv), np.nan)
        v[inside] = disp[y[inside], x[inside]]
        bad = used & ~np.isfinite(v)
        ok &= ~bad
        vv = np.where(used & ~bad, v, 0.0)
        acc += w * vv
        lo = np.where(used & ~bad, np.minimum(lo, v), lo)
        hi = np.where(used & ~bad, np.maximum(hi, v), hi)
    ok &= (hi - lo) <= tol
    return np.where(ok, acc, np.nan)


class DenseTracker:
    """Frame-by-frame dense measurement (module docstring). Feed instants in order with :meth:`step` (or
    :meth:`skip`), then call :meth:`result`.

    Parameters
    ----------
    cameras : Rig or sequence of Camera
    options : DenseOptions
    roi : ndarray (H, W) bool, optional
        Region of interest in the (original) reference image, where points are born; default the whole image.
    """

    def __init__(self, cameras, options: DenseOptions = DenseOptions(), *, roi=None):
        import cv2

        self.opt = options
        self.pair = StereoPair.from_cameras(cameras, options.ref_camera)
        self.cameras = self.pair.cameras
        W, H = self.pair.width, self.pair.height
        if roi is None:
            roi = np.ones((H, W), bool)
        roi = np.asarray(roi)
        if roi.shape != (H, W):
            raise ValueError(f"roi: shape {(H, W)} expected, got {roi.shape}")
        self.roi = roi.astype(bool)
        self.roi_rect = self.pair.rectify_mask(self.roi)
        W, H = self.pair.rect_width, self.pair.rect_height          # the seed grid lies in the rectified image
        self.step_px = options.grid_step_px or default_grid_step(W, H)
        s = self.step_px
        self.grid_shape = (H // s, W // s)
        gy, gx = np.mgrid[0:self.grid_shape[0], 0:self.grid_shape[1]]
        self.cell_uv = np.stack([gx.ravel() * s + s // 2, gy.ravel() * s + s // 2], axis=1).astype(float)
        self._flow = cv2.DISOpticalFlow_create({"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
                                                "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
                                                "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}[options.flow_preset])
        if options.flow_finest_scale is not None:
            self._flow.setFinestScale(options.flow_finest_scale)
        self.matcher = None
        self.disparity_range = None
        # tracks (grown by concatenation): id = index
        self.birth = np.zeros(0, np.int64)
        self.uv = np.zeros((0, 2))              # rectified reference position (carried)
        self.alive = np.zeros(0, bool)
        self.last_seen = np.zeros(0, np.int64)
        self._prev = None                       # last rectified reference image
        self._records = []                      # per instant: (track indices, X, unit cov, rms 0, uv (n, C, 2))
        self._frames = []
        self._reseeded = []
        self.timings = {"tracking": 0.0, "triangulation": 0.0, "detection": 0.0}
        self.problems = []
        self._sq_resid = 0.0
        self._n_resid = 0
        self._capped = False

    # -- set-up ---------------------------------------------------------------------------------------------------
    def _make_matcher(self, ref, other):
        o, p = self.opt, self.pair
        ref_is_left = p.baseline > 0
        if o.disparity_range_px is not None:
            lo, hi = o.disparity_range_px
            how = "given"
        elif o.depth_range_m is not None:
            near, far = o.depth_range_m
            fb = p.f * abs(p.baseline)
            lo, hi = max(0, int(math.floor(fb / far))), int(math.ceil(fb / near))
            how = f"depths {near:g}..{far:g} m"
        else:
            r = _probe_range(o, ref, other, ref_is_left)
            if r is None:
                lo, hi = 0, _ceil16(p.rect_width / 3)
                how = "default 0..W/3 (too few consistent matches in the first pair to measure it)"
                logger.warning("dense: disparity range not measurable on the first pair; using 0..%d px", hi)
            else:
                lo, hi = r
                how = "measured on the first pair"
        self.matcher = _Matcher(o, p.rect_width, p.rect_height, lo, hi, ref_is_left)
        self.disparity_range = (self.matcher.d_min, self.matcher.d_max)
        logger.info("dense: disparities %d..%d px (%s), %dx%d blocks, seed grid %d px (%d cells)",
                    *self.disparity_range, how, self.matcher.block, self.matcher.block, self.step_px,
                    len(self.cell_uv))

    # -- one instant ----------------------------------------------------------------------------------------------
    def step(self, frame_index, images) -> int:
        """Process the images of one instant (one 8-bit gray array per camera, None where missing); the reference
        camera's and its partner's are needed (else use :meth:`skip`). Returns the number of points seen."""
        C = len(self.cameras)
        if len(images) != C:
            raise ValueError(f"images: {C} expected, got {len(images)}")
        p, o = self.pair, self.opt
        ref_img, oth_img = images[p.ref], images[p.other]
        if ref_img is None or oth_img is None:
            raise ValueError("the reference camera's and its partner's images are needed (use skip())")
        for c in (p.ref, p.other):
            im = images[c]
            if im.shape[:2] != (p.height, p.width) or im.ndim != 2:
                raise ValueError(f"images[{c}]: an 8-bit gray {p.width}x{p.height} image expected for camera "
                                 f"{self.cameras[c].name}, got shape {im.shape}")
        s = len(self._frames)
        self._frames.append(int(frame_index))
        t0 = time.perf_counter()
        ref, oth = p.rectify(np.ascontiguousarray(ref_img, np.uint8), np.ascontiguousarray(oth_img, np.uint8))
        if self.matcher is None:
            self._make_matcher(ref, oth)
        disp, xm = self.matcher.compute(ref, oth)
        invalid = np.zeros(disp.shape, bool)
        if o.saturation_level <= 255:
            invalid |= saturation_mask(ref, o.saturation_level, o.saturation_grow_px)
            sat_o = saturation_mask(oth, o.saturation_level, o.saturation_grow_px)
            invalid |= np.take_along_axis(sat_o, xm, axis=1)
        disp[invalid] = np.nan
        t1 = time.perf_counter()
        seen_idx, d_seen = self._track(s, ref, disp)
        t2 = time.perf_counter()
        new_idx, d_new = self._reseed(s, disp, seen_idx)
        self._reseeded.append(new_idx.size > 0)
        idx = np.r_[seen_idx, new_idx]
        d = np.r_[d_seen, d_new]
        if o.pixel_sigma is None and idx.size:
            self._noise_probe(ref, oth, idx, d)
        t3 = time.perf_counter()
        idx = self._triangulate(idx, d)
        self.last_seen[idx] = s
        t4 = time.perf_counter()
        self._prev = ref.copy() if p.identity else ref                       # the caller may reuse its buffer
        self._expire(s)
        self.timings["detection"] += (t1 - t0) + (t3 - t2)
        self.timings["tracking"] += t2 - t1
        self.timings["triangulation"] += t4 - t3
        return int(idx.size)

    def _track(self, s, ref, disp):
        """Carry the alive points into this frame; returns (indices seen, their disparities)."""
        o = self.opt
        live = np.flatnonzero(self.alive)
        if live.size == 0 or self._prev is None:
            return np.zeros(0, np.int64), np.zeros(0)
        fwd = self._flow.calc(self._prev, ref, None)
        bwd = self._flow.calc(ref, self._prev, None)
        p0 = self.uv[live]
        p1 = p0 + _sample(fwd, p0)
        back = p1 + _sample(bwd, p1)
        fb_ok = np.linalg.norm(back - p0, axis=1) <= o.fb_tolerance_px
        W, H = self.pair.rect_width, self.pair.rect_height
        inside = (p1[:, 0] >= 0) & (p1[:, 0] <= W - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= H - 1)
        self.alive[live[~inside]] = False                                      # left the image: ends
        live, p1, fb_ok = live[inside], p1[inside], fb_ok[inside]
        self.uv[live] = p1
        d = np.full(live.size, np.nan)
        if fb_ok.any():
            d[fb_ok] = _sample_disparity(disp, p1[fb_ok], o.lr_tolerance_px)
        ok = np.isfinite(d)
        logger.debug("dense frame %d: %d carried, %d left the image, %d failed forward-backward, %d without a valid "
                     "disparity", s, inside.size, int((~inside).sum()), int((~fb_ok).sum()), int((fb_ok & ~ok).sum()))
        return live[ok], d[ok]

    def _reseed(self, s, disp, seen_idx):
        """New points at the grid cell centres with a valid disparity and no alive point within one grid step,
        when fewer than ``reseed_fraction`` of those centres have a point seen in this frame within one step;
        returns (new indices, their disparities)."""
        o = self.opt
        cu = self.cell_uv.astype(np.int64)
        dc = disp[cu[:, 1], cu[:, 0]]
        valid = np.isfinite(dc) & (dc != 0) & self.roi_rect[cu[:, 1], cu[:, 0]]
        n_valid = int(valid.sum())
        none = np.zeros(0, np.int64), np.zeros(0)
        if n_valid == 0:
            return none
        covered = self._near(self.uv[seen_idx], cu)
        n_cov = int((covered & valid).sum())
        if n_cov >= o.reseed_fraction * n_valid:
            return none
        cells = np.flatnonzero(valid & ~self._near(self.uv[self.alive], cu))
        room = o.max_tracks - len(self.birth)
        if room <= 0:
            if cells.size and not self._capped:
                logger.warning("dense: %d points created, the cap (max_tracks); no more points are seeded",
                               len(self.birth))
                self._capped = True
            return none
        if cells.size > room:
            cells = cells[np.unique(np.linspace(0, cells.size - 1, room).round().astype(np.int64))]
        n = cells.size
        logger.debug("dense frame %d: %d of %d cells with a valid disparity have a seen point; %d new points", s,
                     n_cov, n_valid, n)
        start = len(self.birth)
        self.birth = np.r_[self.birth, np.full(n, s)]
        self.uv = np.concatenate([self.uv, self.cell_uv[cells]])
        self.alive = np.r_[self.alive, np.ones(n, bool)]
        self.last_seen = np.r_[self.last_seen, np.full(n, s)]
        return start + np.arange(n), dc[cells].astype(float)

    def _near(self, uv, at):
        """Whether a point of ``uv`` (N, 2) lies within one grid step of each pixel of ``at`` (M, 2) int."""
        import cv2

        H, W = self.pair.rect_height, self.pair.rect_width
        free = np.full((H, W), 255, np.uint8)
        if len(uv):
            q = np.rint(uv).astype(np.int64)
            free[np.clip(q[:, 1], 0, H - 1), np.clip(q[:, 0], 0, W - 1)] = 0
        dist = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        return dist[at[:, 1], at[:, 0]] <= self.step_px

    def _noise_probe(self, ref, oth, idx, d):
        """Pool the sub-pixel disparity residuals (SGBM minus 1-D Lucas–Kanade) of up to ``_PROBE_POINTS`` of this
        frame's points (evenly spread), those within ``lr_tolerance_px`` (module docstring, step 5)."""
        pick = np.unique(np.linspace(0, idx.size - 1, min(idx.size, _PROBE_POINTS)).round().astype(np.int64))
        uv = self.uv[idx[pick]]
        r = d[pick] - refine_disparity(ref, oth, uv, d[pick], radius=self.matcher.block // 2 + 1)
        r = r[np.abs(r) <= self.opt.lr_tolerance_px]
        self._sq_resid += float((r ** 2).sum())
        self._n_resid += r.size

    def _triangulate(self, idx, d):
        p = self.pair
        C = len(self.cameras)
        uvr = self.uv[idx]
        X, cov = p.triangulate(uvr, d)
        ok = np.isfinite(X).all(axis=1)
        idx, uvr, d, X, cov = idx[ok], uvr[ok], d[ok], X[ok], cov[ok]
        uv = np.full((idx.size, C, 2), np.nan, np.float32)
        a, b = p.original_pixels(uvr, d, X)
        uv[:, p.ref] = a
        uv[:, p.other] = b
        self._records.append((idx, X, cov, np.zeros(len(idx)), uv))
        return idx

    def _expire(self, s):
        self.alive &= ~(s - self.last_seen > self.opt.max_gap_frames)

    def skip(self, frame_index, reason):
        """Record an instant that could not be processed (all points missing in it)."""
        self._frames.append(int(frame_index))
        self._reseeded.append(False)
        self._records.append((np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0),
                              np.zeros((0, len(self.cameras), 2), np.float32)))
        self.problems.append(reason)

    # -- result ---------------------------------------------------------------------------------------------------
    def estimated_sigma(self) -> float:
        """Pixel noise (px) from the pooled sub-pixel disparity residuals: ``rms(r) / sqrt(2)``, floored at
        ``min_pixel_sigma`` (module docstring, step 5); NaN before any point was seen."""
        if self._n_resid == 0:
            return float("nan")
        return max(float(np.sqrt(self._sq_resid / self._n_resid / 2)), self.opt.min_pixel_sigma)

    @property
    def detected(self) -> bool:
        """Whether the last instant seeded new points."""
        return bool(self._reseeded and self._reseeded[-1])

    def unusable(self, images) -> str | None:
        """Why an instant cannot be processed, or None: fewer than two images, or no image of the reference camera
        or of its partner."""
        p = self.pair
        if sum(im is not None for im in images) < 2:
            return "fewer than two readable images"
        if images[p.ref] is None or images[p.other] is None:
            return (f"no image of camera {self.cameras[p.ref if images[p.ref] is None else p.other].name} "
                    "(dense matching needs the reference camera and its partner)")
        return None

    def result(self) -> MeasureResult:
        return assemble_result(self, np.arange(len(self.birth)))


# =====================================================================================================================
# A whole sequence
# =====================================================================================================================
def dense_sequence(frames, cameras, options: DenseOptions = DenseOptions(), *, roi=None,
                   clock=time.perf_counter, field: int | None = None, drop_repeats: bool = True) -> SequenceRun:
    """Dense measurement of a whole sequence: set up a :class:`DenseTracker` and feed it every instant of
    ``frames`` (the contract of :func:`heartcv.measure.measure_sequence`).

    Two cameras: the reference camera (``options.ref_camera``) and the other. More than two: the reference camera
    and the camera with the widest baseline to it (:meth:`StereoPair.from_cameras`); the other cameras' images are
    not used and their ``uv`` are NaN.

    Parameters
    ----------
    frames : iterable of (int, list, list)
        ``(k, images, problems)`` per instant, in order (e.g. a :class:`heartcv.io.FrameReader`): one 8-bit gray
        image per camera, None where missing, and the messages naming the images left out. An instant with fewer
        than two images, or without the reference camera's or its partner's image, is recorded with all points
        missing.
    cameras : Rig or sequence of Camera
    options : DenseOptions
    roi : ndarray (H, W) bool, optional
        Region of interest in the reference camera (no point is seeded outside it, and a point outside it is
        missing); default the whole image.
    clock : callable
        Time source of the per-instant timings.
    field : {None, 0, 1}
        Interlaced video: measure one field of every image, rows ``field``, ``field + 2``, ...
        (:class:`heartcv.measure.WorkingView`; a given ``options.pixel_sigma`` is in the full images' pixels), the
        result in the full images' pixels (``uv``; ``sigma_px`` and ``reprojection_rms`` times sqrt 2). None: the
        whole images.
    drop_repeats : bool
        Leave out every view whose image repeats its previous one (:func:`heartcv.measure.run_frames`).

    Returns
    -------
    SequenceRun
        ``frames[i].detected``: new points were seeded in that instant.

    Raises
    ------
    ValueError
        Unusable rig or options (:meth:`StereoPair.from_cameras`), roi or image of the wrong size.
    MeasureFailed
        No point could be measured in any instant.
    """
    t0 = clock()
    view = None
    if field is not None:
        cameras = list(cameras)
        ref = cameras[options.ref_camera]
        full_roi = np.ones((ref.height, ref.width), bool) if roi is None else np.asarray(roi, bool)
        view = WorkingView.of(cameras, full_roi, field=field)
        cameras, roi, frames = view.cameras, view.roi, view.frames(frames)
        if options.pixel_sigma is not None:            # given in the full frames' pixels
            options = replace(options, pixel_sigma=options.pixel_sigma / view.pixel_scale(options.ref_camera))
    tracker = DenseTracker(cameras, options, roi=roi)
    run = run_frames(tracker, frames, clock, clock() - t0, drop_repeats)
    if view is not None:
        run = replace(run, result=view.to_full(run.result, options.ref_camera, full_roi))
    m = tracker.matcher
    if m is not None and m.n_clamped > 0.001 * max(m.n_good, 1):
        logger.warning("dense: %.1f %% of the consistent matches lay at an end of the disparity range %d..%d px "
                       "measured on the first pair (the surface came nearer or went farther than there) and were "
                       "left out", 100 * m.n_clamped / max(m.n_good + m.n_clamped, 1), *tracker.disparity_range)
    res = run.result
    if res.point_ids.size == 0 or not res.seen.any():
        raise MeasureFailed(f"no surface point could be measured densely (region of interest {int(res.roi.sum())} "
                            f"px in camera {tracker.cameras[tracker.pair.ref].name})")
    return run
