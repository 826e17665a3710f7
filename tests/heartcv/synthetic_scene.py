"""A small synthetic trinocular scene with exact ground truth, for the unit tests of ``heartcv measure``.

Three cameras like the paper's rig (docs/design.md §7: an equilateral triangle of side 0.5 m, 0.53 m from the surface,
converging on it, the paper's distortion), with the intrinsics scaled by ``scale`` (default 1/4: 480x270 images,
f ~ 1492 px, about 0.36 mm per pixel at the working distance). The surface is a spherical cap (sphere radius
``radius_m``, cap radius ``cap_m`` measured in the tangent plane of its apex), apex at the world origin, facing the
rig. Its albedo is a fixed band-limited random pattern in material coordinates: Gaussian-smoothed white noise on a
0.1 mm texel grid, looked up (bilinear) at the material point's tangent-plane coordinates ``(m_x, m_y)``. Lambert
shading under a directional light from the rig. Every image pixel is ray cast (analytic ray-sphere intersection
through the full distortion model) with ``supersample**2`` rays per pixel, averaged (the pixel integrates).

The surface moves rigidly by a known translation per frame (``motion_m``, world frame), and a directional light
makes the brightness of a material point constant under translation, so the exact 3-D position of every material
point in every frame is known: ``scene.position(m, k)``. An occluder is a dark, flat disk painted over one
camera's image.

Frames: world = the rig's world (surface at the origin); the cameras and every position returned are in the rig
frame (camera 0's frame), as the heartcv code expects. Deterministic: the texture comes from ``seed``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from heartcv.camera import Camera, distort_normalised, invert_pose, pose_matrix

F_FULL = 5970.0
DIST = np.array([-0.08, 0.4, 3e-4, -2e-4, 0.0])
_RAY_CACHE = {}


def look_at(centre, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """cam_from_world of a camera at ``centre`` looking at ``target`` (world y roughly up in the image)."""
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return pose_matrix(R, -R @ centre)


def small_rig(scale=0.25, distortion=True):
    """The paper rig (tests/heartcv/test_calibration.py ``paper_rig``) with K scaled by ``scale`` (pixel centres
    kept: ``c' = (c + 0.5) scale - 0.5``). Returns the cameras (rig frame = camera 0) and cam0_from_world."""
    r, wd = 0.5 / np.sqrt(3), 0.53
    h = np.sqrt(wd ** 2 - r ** 2)
    cam_from_world = [look_at(np.array([r * np.cos(a), r * np.sin(a), -h]))
                      for a in np.pi / 2 + 2 * np.pi * np.arange(3) / 3]
    world_from_cam0 = invert_pose(cam_from_world[0])
    W, H = int(round(1920 * scale)), int(round(1080 * scale))
    cams = []
    for i, T in enumerate(cam_from_world):
        f = F_FULL * (1 + 0.01 * i) * scale
        cx, cy = (959.5 + 10 * i + 0.5) * scale - 0.5, (539.5 - 8 * i + 0.5) * scale - 0.5
        K = np.array([[f, 0, cx], [0, f * 1.001, cy], [0, 0, 1]])
        dist = DIST * (1 + 0.2 * i) if distortion else np.zeros(5)
        cams.append(Camera(f"cam{i}", W, H, K, dist, T @ world_from_cam0))
    return cams, cam_from_world[0]


def undistort_exact(cam: Camera, uv) -> np.ndarray:
    """Normalised ideal coordinates (N, 2) of pixels (N, 2): cv2's iteration, then Newton steps on the exact model
    (the same model as ``Camera.project``) until the reprojection error is below 1e-9 px."""
    import cv2

    uv = np.asarray(uv, float)
    xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist,
                             criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)).reshape(-1, 2)
    K = cam.K

    def pix(p):
        d = distort_normalised(p, cam.dist)
        return np.stack([K[0, 0] * d[:, 0] + K[0, 1] * d[:, 1] + K[0, 2], K[1, 1] * d[:, 1] + K[1, 2]], axis=1)

    h = 1e-7
    for _ in range(5):
        r = uv - pix(xy)
        if np.abs(r).max(initial=0) < 1e-9:
            break
        Jx = (pix(xy + [h, 0]) - pix(xy - [h, 0])) / (2 * h)
        Jy = (pix(xy + [0, h]) - pix(xy - [0, h])) / (2 * h)
        J = np.stack([Jx, Jy], axis=2)
        xy = xy + np.linalg.solve(J, r[..., None])[..., 0]
    return xy


@dataclass(frozen=True)
class Occluder:
    """A flat dark disk (``value`` grey level) of ``radius_px`` at ``centre_uv`` in camera ``camera``'s image, over
    the frames ``frames``."""

    camera: int
    centre_uv: tuple
    radius_px: float
    frames: tuple
    value: int = 20

    def paint(self, image, camera, frame) -> np.ndarray:
        """A copy of ``image`` (camera ``camera``, ``frame``) with the disk painted over the pixels it covers."""
        image = np.array(image)
        if camera == self.camera and frame in self.frames:
            vv, uu = np.mgrid[0:image.shape[0], 0:image.shape[1]]
            image[self.hides(camera, frame, np.stack([uu.ravel(), vv.ravel()], axis=1)).reshape(image.shape)] = \
                self.value
        return image

    def hides(self, camera, frame, uv) -> np.ndarray:
        """Whether pixels (N, 2) of ``camera`` in ``frame`` are under the disk (bool (N,))."""
        uv = np.asarray(uv, float)
        if camera != self.camera or frame not in self.frames:
            return np.zeros(len(uv), bool)
        return np.linalg.norm(uv - np.asarray(self.centre_uv, float), axis=1) <= self.radius_px


@dataclass(frozen=True)
class Scene:
    """The synthetic scene (module docstring). ``motion_m`` (K, 3): world translation of the surface per frame."""

    motion_m: np.ndarray
    seed: int = 7
    scale: float = 0.25
    radius_m: float = 0.05
    cap_m: float = 0.03
    texel_m: float = 1e-4
    texture_sigma_m: float = 6e-4
    supersample: int = 2
    distortion: bool = True
    light: np.ndarray = field(default_factory=lambda: np.array([0.15, -0.1, -1.0]))

    # -- geometry ---------------------------------------------------------------------------------------------
    @cached_property
    def _rig(self):
        return small_rig(self.scale, self.distortion)

    @property
    def cameras(self) -> list:
        return self._rig[0]

    @property
    def rig_from_world(self) -> np.ndarray:
        return self._rig[1]

    @property
    def n_frames(self) -> int:
        return len(self.motion_m)

    def _world_rays(self, c, uv):
        """World-frame origins (3,) and unit directions (N, 3) of camera c's rays through pixels (N, 2)."""
        cam = self.cameras[c]
        T = cam.cam_from_rig @ self.rig_from_world                      # cam_from_world
        xy = undistort_exact(cam, uv)
        d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ T[:3, :3]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return -T[:3, :3].T @ T[:3, 3], d

    def _hit(self, origin, dirs, frame):
        """Material points (N, 3) where world rays first meet the cap in ``frame`` (NaN rows: no hit)."""
        shift = np.asarray(self.motion_m[frame], float)
        c = np.array([0.0, 0.0, self.radius_m]) + shift
        oc = origin - c
        b = dirs @ oc
        disc = b * b - (oc @ oc - self.radius_m ** 2)
        with np.errstate(invalid="ignore"):
            t = -b - np.sqrt(disc)
        m = origin + t[:, None] * dirs - shift
        inside = (disc > 0) & (m[:, 0] ** 2 + m[:, 1] ** 2 < self.cap_m ** 2) & (m[:, 2] < self.radius_m)
        m[~inside] = np.nan
        return m

    def material_point(self, c, uv, frame) -> np.ndarray:
        """Material points (N, 3) (surface coordinates at rest, world frame) seen by camera ``c`` at pixels
        (N, 2) in ``frame``; NaN where the ray misses the cap."""
        o, d = self._world_rays(c, np.atleast_2d(uv))
        return self._hit(o, d, frame)

    def position(self, m, frame) -> np.ndarray:
        """Rig-frame positions (N, 3) of material points ``m`` (N, 3) in ``frame``."""
        X = np.asarray(m, float) + np.asarray(self.motion_m[frame], float)
        return X @ self.rig_from_world[:3, :3].T + self.rig_from_world[:3, 3]

    def surface_point(self, c, uv, frame) -> np.ndarray:
        """Rig-frame points (N, 3) seen by camera ``c`` at pixels (N, 2) in ``frame`` (the exact ray-surface
        intersection)."""
        return self.position(self.material_point(c, uv, frame), frame)

    def normal(self, m) -> np.ndarray:
        """Outward unit normals (N, 3) of the surface at material points, rig frame."""
        n = (np.asarray(m, float) - [0.0, 0.0, self.radius_m]) / self.radius_m
        return n @ self.rig_from_world[:3, :3].T

    # -- images -----------------------------------------------------------------------------------------------
    @cached_property
    def texture(self) -> np.ndarray:
        """Albedo on the texel grid covering [-L, L]^2 of material (x, y), L = cap + 2 mm (float32, in [0.05, 1])."""
        import cv2

        n = int(np.ceil(2 * (self.cap_m + 2e-3) / self.texel_m)) + 1
        rng = np.random.default_rng(self.seed)
        z = cv2.GaussianBlur(rng.normal(size=(n, n)).astype(np.float32), (0, 0), self.texture_sigma_m / self.texel_m)
        z /= z.std()
        return np.clip(0.55 + 0.22 * z, 0.05, 1.0).astype(np.float32)

    @property
    def _pixel_rays(self):
        """Per camera: world origin (3,) and directions (H * W * s^2, 3) of the supersampled pixel grid (cached
        per rig and sampling: they do not depend on the surface)."""
        key = (self.scale, self.distortion, self.supersample)
        if key not in _RAY_CACHE:
            s = self.supersample
            out = []
            for c, cam in enumerate(self.cameras):
                sub = (np.arange(s) + 0.5) / s - 0.5
                u = (np.arange(cam.width)[:, None] + sub[None]).ravel()
                v = (np.arange(cam.height)[:, None] + sub[None]).ravel()
                uu, vv = np.meshgrid(u, v)
                out.append(self._world_rays(c, np.stack([uu.ravel(), vv.ravel()], axis=1)))
            _RAY_CACHE[key] = out
        return _RAY_CACHE[key]

    def radiance(self, m) -> np.ndarray:
        """Grey level (float, before noise) of material points (N, 3); the background (12) where NaN."""
        out = np.full(len(m), 12.0)
        ok = np.flatnonzero(np.isfinite(m[:, 0]))
        q = m[ok]
        tex = self.texture
        L = (tex.shape[0] - 1) * self.texel_m / 2
        gx = np.clip((q[:, 0] + L) / self.texel_m, 0, tex.shape[1] - 1.000001)
        gy = np.clip((q[:, 1] + L) / self.texel_m, 0, tex.shape[0] - 1.000001)
        ix, iy = gx.astype(np.int64), gy.astype(np.int64)
        fx, fy = gx - ix, gy - iy
        albedo = ((1 - fy) * ((1 - fx) * tex[iy, ix] + fx * tex[iy, ix + 1])
                  + fy * ((1 - fx) * tex[iy + 1, ix] + fx * tex[iy + 1, ix + 1]))
        light = self.light / np.linalg.norm(self.light)
        n = (q - [0.0, 0.0, self.radius_m]) / self.radius_m
        out[ok] = 12.0 + 225.0 * albedo * (0.3 + 0.7 * np.clip(n @ light, 0.0, None))
        return out

    def render(self, c, frame, *, noise=0.0, rng=None, occluders=()) -> np.ndarray:
        """8-bit gray image (H, W) of camera ``c`` in ``frame``: Gaussian noise of ``noise`` grey levels (from
        ``rng``), rounded; occluder disks painted last."""
        cam = self.cameras[c]
        s = self.supersample
        o, d = self._pixel_rays[c]
        val = self.radiance(self._hit(o, d, frame))
        img = val.reshape(cam.height, s, cam.width, s).mean(axis=(1, 3))
        if noise > 0:
            img = img + rng.normal(0.0, noise, img.shape)
        img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        for occ in occluders:
            img = occ.paint(img, c, frame)
        return img

    def render_frame(self, frame, *, noise=0.0, rng=None, occluders=()) -> list:
        """The images of every camera in ``frame``."""
        return [self.render(c, frame, noise=noise, rng=rng, occluders=occluders) for c in range(len(self.cameras))]

    def cap_mask(self, c, frame, inner_m=None) -> np.ndarray:
        """Pixels (H, W) bool of camera ``c`` whose centre ray meets the cap within ``inner_m`` (default: the
        cap radius) of its apex in ``frame``."""
        cam = self.cameras[c]
        vv, uu = np.mgrid[0:cam.height, 0:cam.width]
        m = self.material_point(c, np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float), frame)
        r = np.hypot(m[:, 0], m[:, 1])
        lim = self.cap_m if inner_m is None else inner_m
        return (np.nan_to_num(r, nan=np.inf) < lim).reshape(cam.height, cam.width)


def translating_scene(n_frames=8, step_m=(8e-4, -5e-4, 3e-4), **kw) -> Scene:
    """A scene whose surface translates by ``step_m`` (world, m) per frame (about 1 mm)."""
    return Scene(np.arange(n_frames)[:, None] * np.asarray(step_m, float)[None], **kw)
