"""Calibration renders: the target as a textured plane at seeded poses, seen through the true camera models.

Poses (``sample_board_poses``, drawn from ``default_rng([seed, 4])``): the board's centre sits near the
convergence point (uniform jitter ``offset_m`` across and ``depth_m`` along the central axis), tilted by up to
``max_tilt_deg`` about a random in-plane axis and rolled by up to ``max_roll_deg``. A view is kept when at least
two cameras see its printed side within ``max_incidence_deg`` of face-on with ``min_corners`` corners inside the
image. ``partial_fraction`` of the views are *partial*: shifted sideways until the board leaves the image of at
least one camera (some corners in, some out); every other view is complete in every camera that sees it.

Rendering (``render_view``): each pixel's exact ray (``raycast.PixelGrid``) meets the board plane; the point's
board-frame position gives the reflectance (``heartcv.targets.board_reflectance``: black ``black``, white
``white``, a white margin ``board_margin_m`` around the squares; the back of the board is a uniform 0.5);
shading is Lambert under the scene's lights (matte print). Pixels whose 3x3 neighbourhood is not uniform are
re-rendered with ``supersampling`` x ``supersampling`` rays (box filter over the pixel), which keeps the corners'
sub-pixel positions exact. Sensor noise of view i, camera c comes from ``default_rng([seed, 5, i, c])``.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from ..camera import invert_pose, pose_matrix
from ..tracker.files import InputError
from .parallel import imap_ordered
from .scene import Scene, build_rig
from .sensor import expose
from .shading import Lights, make_lights

__all__ = ["CalibrationSetup", "ViewResult", "sample_board_poses", "prepare_calibration", "render_view",
           "render_calibration", "calibration_truth", "corner_visibility"]

BACK_REFLECTANCE = 0.5


@dataclass(frozen=True)
class CalibrationSetup:
    scene: Scene
    rig: object  # heartcv.camera.Rig
    target: object  # heartcv.targets.TargetSpec
    grids: tuple  # PixelGrid per camera
    directions: tuple  # (H*W, 3) float32 per camera
    lights: Lights
    world_from_board: np.ndarray  # (n_views, 4, 4)
    partial: np.ndarray  # (n_views,) bool

    @property
    def n_views(self) -> int:
        return self.world_from_board.shape[0]


@dataclass(frozen=True)
class ViewResult:
    index: int
    images: list
    rays: int


def _rotation(axis, angle) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(axis, float).reshape(3, 1) * angle)[0]


def corner_visibility(rig, target, world_from_board):
    """Per camera: corner pixels (n_cam, n, 2), in-image and front-facing flags (n_cam, n) and the incidence
    angle of the board (deg, angle between its printed side's normal and the direction to the camera)."""
    obj = target.object_points()
    X = obj @ world_from_board[:3, :3].T + world_from_board[:3, 3]
    centre = world_from_board[:3, :3] @ np.r_[np.asarray(target.squares_origin_m) + np.asarray(target.board_size_m) / 2,
                                              0.0] + world_from_board[:3, 3]
    front_normal = -world_from_board[:3, 2]
    uv, seen, inc = [], [], []
    for cam in rig.cameras:
        p = cam.project(X)
        to_cam = cam.centre - centre
        cos_inc = front_normal @ to_cam / np.linalg.norm(to_cam)
        front = ((cam.centre - X) @ front_normal) > 0
        uv.append(p)
        seen.append(cam.in_image(p, margin=1.0) & front & np.isfinite(p).all(axis=1))
        inc.append(math.degrees(math.acos(np.clip(cos_inc, -1, 1))))
    return np.stack(uv), np.stack(seen), np.array(inc)


def sample_board_poses(scene: Scene, rig, target, rng: np.random.Generator):
    """``(world_from_board (n, 4, 4), partial (n,) bool)`` for the scene's calibration section.

    Raises
    ------
    InputError
        Field ``calibration``: no pose of some view that two cameras see (the board does not fit the field of view).
    """
    cal = scene.calibration
    n = cal.views
    n_partial = int(round(cal.partial_fraction * n))
    partial = np.zeros(n, bool)
    partial[rng.permutation(n)[:n_partial]] = True
    world_from_ring = scene.world_from_ring
    centre_b = np.r_[np.asarray(target.squares_origin_m) + np.asarray(target.board_size_m) / 2, 0.0]
    diag = float(np.hypot(*target.board_size_m))
    poses = np.empty((n, 4, 4))
    if cal.min_corners > int(target.n_corners):
        raise InputError(None, f"{cal.min_corners}: the target has {target.n_corners} corners; no view can show that "
                               "many", "calibration.min_corners")
    for i in range(n):
        for _attempt in range(2000):
            psi = rng.uniform(0, 2 * math.pi)
            tilt = math.radians(cal.max_tilt_deg) * rng.uniform(0, 1)
            roll = math.radians(cal.max_roll_deg) * rng.uniform(-1, 1)
            R = _rotation([math.cos(psi), math.sin(psi), 0.0], tilt) @ _rotation([0, 0, 1], roll)
            o = np.array([rng.uniform(-1, 1) * cal.offset_m, rng.uniform(-1, 1) * cal.offset_m,
                          scene.rig.working_distance_m + rng.uniform(-1, 1) * cal.depth_m])
            if partial[i]:
                phi = rng.uniform(0, 2 * math.pi)
                o[:2] += rng.uniform(0.3, 0.65) * diag * np.array([math.cos(phi), math.sin(phi)])
            ring_from_board = pose_matrix(R, o - R @ centre_b)
            T = world_from_ring @ ring_from_board
            _, seen, inc = corner_visibility(rig, target, T)
            good = inc <= cal.max_incidence_deg
            count = seen.sum(axis=1)
            if (good & (count >= cal.min_corners)).sum() < 2:
                continue
            frac = count[good] / seen.shape[1]
            if partial[i] and not ((frac < 0.9) & (count[good] >= cal.min_corners)).any():
                continue
            if not partial[i] and (frac < 1.0).any():
                continue
            poses[i] = T
            break
        else:
            raise InputError(None, f"no pose found for view {i} ({'partial' if partial[i] else 'complete'}) that at "
                                   f"least two cameras see with {cal.min_corners} corners (min_corners) at incidence "
                                   f"up to {cal.max_incidence_deg:g} deg (max_incidence_deg); the board may not fit "
                                   f"the field of view at rig.working_distance_m {scene.rig.working_distance_m:g} m: "
                                   "check those, or reduce max_tilt_deg, max_roll_deg or offset_m", "calibration")
    return poses, partial


def prepare_calibration(scene: Scene, target, *, workers=1, grids=None) -> CalibrationSetup:
    """Cameras, exact pixel rays, lights and board poses of the scene's calibration set."""
    from .sequence import camera_directions

    rig = build_rig(scene.rig)
    poses, partial = sample_board_poses(scene, rig, target, np.random.default_rng([scene.seed, 4]))
    if grids is None:
        grids, dirs = camera_directions(rig, workers)
    else:
        dirs = tuple(g.directions() for g in grids)
    lights = make_lights(scene.lighting, rig, scene.world_from_ring, scene.rig.working_distance_m)
    return CalibrationSetup(scene, rig, target, tuple(grids), dirs, lights, poses, partial)


def _radiance(setup, cam, T, d):
    """Radiance and reflectance (background value for misses) of rays from ``cam.centre`` along ``d`` (N, 3)
    against board pose T (world_from_board)."""
    from ..targets import board_extent_m, board_reflectance

    cal = setup.scene.calibration
    d = np.asarray(d, np.float64)
    o = cam.centre
    z = T[:3, 2]
    p0 = T[:3, 3]
    denom = d @ z
    with np.errstate(divide="ignore", invalid="ignore"):
        s = ((p0 - o) @ z) / denom
    X = o + s[:, None] * d
    xy = (X - p0) @ T[:3, :2]
    ex = board_extent_m(setup.target, cal.board_margin_m)
    hit = (s > 0) & (xy[:, 0] >= ex[0]) & (xy[:, 0] <= ex[2]) & (xy[:, 1] >= ex[1]) & (xy[:, 1] <= ex[3])
    out = np.full(d.shape[0], cal.background, np.float64)
    if not hit.any():
        return out, out.copy()
    front = hit & (denom > 0)
    refl = np.full(d.shape[0], BACK_REFLECTANCE)
    if front.any():
        val = board_reflectance(setup.target, xy[front], margin_m=cal.board_margin_m)
        refl[front] = cal.black + (cal.white - cal.black) * val
    n = np.where(front[:, None], -z, z)
    L = setup.lights
    irr = np.full(d.shape[0], L.ambient)
    Xh = X[hit]
    for p, inten in zip(L.positions, L.intensity):
        lv = p - Xh
        dist2 = np.einsum("ij,ij->i", lv, lv)
        ndl = np.einsum("ij,ij->i", n[hit], lv) / np.sqrt(dist2)
        irr[hit] += inten * L.reference_m ** 2 / dist2 * np.maximum(ndl, 0)
    out[hit] = refl[hit] * irr[hit]
    refl[~hit] = cal.background
    return out, refl


def render_view(setup: CalibrationSetup, i: int, *, noise=True, encode=None) -> ViewResult:
    """Gray images (H, W) of view i in every camera (module docstring)."""
    import cv2

    scene = setup.scene
    T = setup.world_from_board[i]
    ss = scene.calibration.supersampling
    offsets = np.array([((a + 0.5) / ss - 0.5, (b + 0.5) / ss - 0.5) for b in range(ss) for a in range(ss)])
    images, rays = [], 0
    for c, cam in enumerate(setup.rig.cameras):
        H, W = cam.height, cam.width
        rad, refl = _radiance(setup, cam, T, setup.directions[c])
        img = rad.astype(np.float32).reshape(H, W)
        refl = refl.astype(np.float32).reshape(H, W)
        rays += H * W
        if ss > 1:
            # the pattern changes within a pixel if its 3x3 neighbourhood (the ring beyond the image included)
            # is not uniform
            ext = np.empty((H + 2, W + 2), np.float32)
            ext[1:-1, 1:-1] = refl
            ring = np.ones((H + 2, W + 2), bool)
            ring[1:-1, 1:-1] = False
            rv, ru = np.nonzero(ring)
            ext[rv, ru] = _radiance(setup, cam, T, setup.grids[c].directions(ru - 1.0, rv - 1.0, np.float64))[1]
            k = np.ones((3, 3), np.uint8)
            edge = ((cv2.dilate(ext, k) - cv2.erode(ext, k)) > 1e-3)[1:-1, 1:-1]
            idx = np.flatnonzero(edge.ravel())
            acc = np.zeros(idx.size)
            for chunk in np.array_split(np.arange(len(offsets)), max(1, len(offsets) * idx.size // 4_000_000)):
                u = (idx % W)[None, :] + offsets[chunk, 0][:, None]
                v = (idx // W)[None, :] + offsets[chunk, 1][:, None]
                d = setup.grids[c].directions(u.ravel(), v.ravel(), dtype=np.float64)
                acc += _radiance(setup, cam, T, d)[0].reshape(len(chunk), -1).sum(axis=0)
                rays += d.shape[0]
            img.reshape(-1)[idx] = acc / len(offsets)
        rng = np.random.default_rng([scene.seed, 5, i, c]) if noise else None
        out = expose(img, scene.noise, rng, scene.optics.psf_sigma_px)
        images.append(encode(out) if encode is not None else out)
    return ViewResult(i, images, rays)


def _job(setup, args):
    i, noise, encode = args
    return render_view(setup, i, noise=noise, encode=encode)


def render_calibration(setup: CalibrationSetup, *, views=None, workers=1, noise=True, encode=None):
    """Yield :class:`ViewResult` per view, in order, rendered by ``workers`` processes."""
    views = range(setup.n_views) if views is None else views
    yield from imap_ordered(_job, setup, [(i, noise, encode) for i in views], workers)


def calibration_truth(setup: CalibrationSetup) -> tuple[dict, dict]:
    """Arrays and metadata of the calibration ``truth.npz`` (``heartcv.render_truth`` v1, kind ``calibration``)."""
    cams = setup.rig.cameras
    uv, seen, inc = zip(*(corner_visibility(setup.rig, setup.target, T) for T in setup.world_from_board))
    cam_from_world = np.stack([c.cam_from_rig for c in cams])
    nd = max(c.dist.size for c in cams)
    arrays = {
        "K": np.stack([c.K for c in cams]), "dist": np.stack([np.pad(c.dist, (0, nd - c.dist.size)) for c in cams]),
        "cam_from_world": cam_from_world, "cam_from_rig": cam_from_world,
        "image_size": np.array([cams[0].width, cams[0].height]),
        "world_from_board": setup.world_from_board,
        "cam_from_board": np.einsum("cij,vjk->vcik", cam_from_world, setup.world_from_board),
        "object_points": setup.target.object_points(), "corners_uv": np.stack(uv), "corners_visible": np.stack(seen),
        "incidence_deg": np.stack(inc), "partial": setup.partial,
        "board_from_world": np.stack([invert_pose(T) for T in setup.world_from_board]),
    }
    meta = {"kind": "calibration", "scene": setup.scene.name, "seed": setup.scene.seed,
            "seeds": {"poses": [setup.scene.seed, 4], "sensor_noise": [setup.scene.seed, 5, "view", "camera"]},
            "camera_names": [c.name for c in cams], "target": setup.target.to_dict(), "world_frame": "cam0",
            "image_width": int(cams[0].width), "image_height": int(cams[0].height)}
    return arrays, meta
