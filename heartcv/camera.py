"""Pinhole camera with OpenCV's distortion model, and a rig of such cameras.

Conventions (docs/design.md §3): camera axes as OpenCV (x right, y down, z forward); transforms are named
``<target>_from_<source>`` with ``x_target = R x_source + t``; the rig frame is camera 0's frame unless a rig
file says otherwise. Pixel coordinates: the centre of the top-left pixel is (0, 0) (OpenCV).

Distortion coefficients follow ``cv2.projectPoints``: ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[,
tau_x, tau_y]]]])`` -- 4, 5, 8, 12 or 14 values (0 = none). The projection is implemented here in numpy
(vectorised, with exact analytic Jacobians; complex-step differentiation of the distortion for a tilted
sensor) and is tested against ``cv2.projectPoints``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

__all__ = ["Camera", "Rig", "DIST_SIZES", "pose_matrix", "invert_pose", "distort_normalised", "distortion_jacobian"]

DIST_SIZES = (0, 4, 5, 8, 12, 14)


def pose_matrix(R, t) -> np.ndarray:
    """4x4 homogeneous matrix of ``x' = R x + t``."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, float)
    T[:3, 3] = np.asarray(t, float).reshape(3)
    return T


def invert_pose(T) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (``source_from_target`` of ``target_from_source``)."""
    T = np.asarray(T, float)
    R, t = T[:3, :3], T[:3, 3]
    return pose_matrix(R.T, -R.T @ t)


def _check_pose(name, T) -> np.ndarray:
    T = np.array(T, float)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"{name}: finite 4x4 matrix expected, got shape {T.shape}")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0 or np.abs(T[3] - [0, 0, 0, 1]).max() > 0:
        raise ValueError(f"{name}: not a rigid transform (R^T R = I, det R = +1, last row [0 0 0 1] expected)")
    return T


def _full_dist(dist) -> np.ndarray:
    d = np.zeros(14, dtype=np.result_type(dist, float))
    d[: len(dist)] = dist
    return d


def _tilt_matrix(tau_x, tau_y):
    """OpenCV's ``computeTiltProjectionMatrix``: Z-projection of the rotated sensor plane (3x3)."""
    cx, sx = np.cos(tau_x), np.sin(tau_x)
    cy, sy = np.cos(tau_y), np.sin(tau_y)
    rot_x = np.array([[1, 0, 0], [0, cx, sx], [0, -sx, cx]], dtype=np.result_type(tau_x, float))
    rot_y = np.array([[cy, 0, -sy], [0, 1, 0], [sy, 0, cy]], dtype=np.result_type(tau_y, float))
    rot = rot_y @ rot_x
    proj_z = np.array([[rot[2, 2], 0, -rot[0, 2]], [0, rot[2, 2], -rot[1, 2]], [0, 0, 1]], dtype=rot.dtype)
    return proj_z @ rot


def distort_normalised(xy, dist) -> np.ndarray:
    """OpenCV distortion of normalised image coordinates ``(x/z, y/z)`` (..., 2) -> (..., 2)."""
    d = _full_dist(np.asarray(dist))
    if not d.any():                     # no distortion (e.g. a rectified rig): the identity
        return np.array(xy)
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tx, ty = d
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
    if tx != 0 or ty != 0:
        Tm = _tilt_matrix(tx, ty)
        u = Tm[0, 0] * xd + Tm[0, 1] * yd + Tm[0, 2]
        v = Tm[1, 0] * xd + Tm[1, 1] * yd + Tm[1, 2]
        w = Tm[2, 0] * xd + Tm[2, 1] * yd + Tm[2, 2]
        xd, yd = u / w, v / w
    return np.stack([xd, yd], axis=-1)


def distortion_jacobian(xy, dist) -> np.ndarray:
    """d distort_normalised / d xy (..., 2, 2) at normalised coordinates ``xy`` (..., 2): analytic for the
    radial (rational), tangential and thin-prism terms; the tilted-sensor terms (``tau_x``, ``tau_y``) are
    differentiated by complex step (exact to rounding, two evaluations)."""
    xy = np.asarray(xy)
    d = _full_dist(np.asarray(dist))
    J = np.zeros(xy.shape[:-1] + (2, 2), dtype=np.result_type(xy, float))
    if not d.any():
        J[..., 0, 0] = 1.0
        J[..., 1, 1] = 1.0
        return J
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tx, ty = d
    if tx != 0 or ty != 0:
        h = 1e-30
        for j in range(2):
            Z = xy.astype(complex)
            Z[..., j] += 1j * h
            J[..., :, j] = distort_normalised(Z, d).imag / h
        return J
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    r4 = r2 * r2
    a = 1 + k1 * r2 + k2 * r4 + k3 * r4 * r2
    b = 1 + k4 * r2 + k5 * r4 + k6 * r4 * r2
    radial = a / b
    dradial = ((k1 + 2 * k2 * r2 + 3 * k3 * r4) * b - a * (k4 + 2 * k5 * r2 + 3 * k6 * r4)) / (b * b)   # d/d r2
    px = s1 + 2 * s2 * r2           # d (s1 r2 + s2 r4) / d r2
    py = s3 + 2 * s4 * r2
    J[..., 0, 0] = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x + 2 * x * px
    J[..., 0, 1] = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y + 2 * y * px
    J[..., 1, 0] = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y + 2 * x * py
    J[..., 1, 1] = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x + 2 * y * py
    return J


@dataclass(frozen=True)
class Camera:
    """One calibrated camera.

    Parameters
    ----------
    name : str
    width, height : int
        Image size in pixels.
    K : ndarray of shape (3, 3)
        Intrinsic matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` (pixels).
    dist : ndarray of shape (n,), n in DIST_SIZES
        OpenCV distortion coefficients.
    cam_from_rig : ndarray of shape (4, 4)
        Pose of the rig frame in this camera's frame.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    cam_from_rig: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name or any(c.isspace() for c in self.name):
            raise ValueError(f"camera name: a non-empty string without spaces expected, got {self.name!r}")
        for n in ("width", "height"):
            v = getattr(self, n)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer, float)) or int(v) != v or v < 1:
                raise ValueError(f"{self.name}: {n} must be a positive integer, got {v!r}")
            object.__setattr__(self, n, int(v))
        K = np.array(self.K, float)
        if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0 \
                or np.abs(K[2] - [0, 0, 1]).max() > 0 or K[1, 0] != 0:
            raise ValueError(f"{self.name}: K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
        dist = np.array(self.dist, float).reshape(-1)
        if dist.size not in DIST_SIZES or not np.isfinite(dist).all():
            raise ValueError(f"{self.name}: {dist.size} distortion coefficients; one of {DIST_SIZES} expected")
        T = _check_pose(f"{self.name}: cam_from_rig", self.cam_from_rig)
        for n, v in (("K", K), ("dist", dist), ("cam_from_rig", T)):
            v.setflags(write=False)
            object.__setattr__(self, n, v)

    # -- construction ------------------------------------------------------------------------------
    @classmethod
    def from_focal_mm(cls, name, width, height, focal_mm, pixel_pitch_m, *, cx=None, cy=None, dist=None,
                      cam_from_rig=None) -> "Camera":
        """A camera from its lens focal length (mm) and sensor pixel pitch (m); principal point at the image
        centre ``((w - 1) / 2, (h - 1) / 2)`` unless given."""
        if not (focal_mm > 0 and pixel_pitch_m > 0):
            raise ValueError(f"focal_mm and pixel_pitch_m must be positive, got {focal_mm}, {pixel_pitch_m}")
        f = focal_mm * 1e-3 / pixel_pitch_m
        cx = (width - 1) / 2 if cx is None else cx
        cy = (height - 1) / 2 if cy is None else cy
        K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
        return cls(name, width, height, K, np.zeros(5) if dist is None else dist,
                   np.eye(4) if cam_from_rig is None else cam_from_rig)

    def with_pose(self, cam_from_rig) -> "Camera":
        return replace(self, cam_from_rig=cam_from_rig)

    # -- geometry ------------------------------------------------------------------------------------
    @property
    def R(self) -> np.ndarray:
        return self.cam_from_rig[:3, :3]

    @property
    def t(self) -> np.ndarray:
        return self.cam_from_rig[:3, 3]

    @property
    def centre(self) -> np.ndarray:
        """Projection centre in the rig frame (3,)."""
        return -self.R.T @ self.t

    @property
    def size(self) -> tuple[int, int]:
        return self.width, self.height

    def to_cam(self, X_rig) -> np.ndarray:
        """Rig-frame points (..., 3) -> camera frame."""
        X = np.asarray(X_rig)
        return X @ self.R.T + self.t

    def _pixels(self, Xc):
        z = Xc[..., 2]
        z = np.where(z == 0, np.nan, z)  # on the camera plane: NaN, no division warning
        xy = Xc[..., :2] / z[..., None]
        xd = distort_normalised(xy, self.dist)
        K = self.K
        u = K[0, 0] * xd[..., 0] + K[0, 1] * xd[..., 1] + K[0, 2]
        v = K[1, 1] * xd[..., 1] + K[1, 2]
        return np.stack([u, v], axis=-1)

    def project_cam(self, X_cam, *, jacobian=False):
        """Pixels (N, 2) of camera-frame points (N, 3); with ``jacobian`` also d uv / d X_cam (N, 2, 3).

        Points with ``z <= 0`` (behind the camera) give NaN. The Jacobian is exact: the chain rule through the
        pinhole division, :func:`distortion_jacobian` and K.
        """
        Xc = np.atleast_2d(np.asarray(X_cam, float))
        if Xc.shape[-1] != 3:
            raise ValueError(f"points: shape (N, 3) expected, got {Xc.shape}")
        behind = Xc[:, 2] <= 0
        uv = self._pixels(Xc)
        uv[behind] = np.nan
        if not jacobian:
            return uv
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = 1.0 / np.where(Xc[:, 2] == 0, np.nan, Xc[:, 2])
        x, y = Xc[:, 0] * iz, Xc[:, 1] * iz
        D = distortion_jacobian(np.stack([x, y], axis=1), self.dist)          # (N, 2, 2)
        K = self.K
        A = np.empty_like(D)                                                   # K[:2, :2] @ D
        A[:, 0] = K[0, 0] * D[:, 0] + K[0, 1] * D[:, 1]
        A[:, 1] = K[1, 1] * D[:, 1]
        # d (x, y) / d Xc = [[1/z, 0, -x/z], [0, 1/z, -y/z]]
        J = np.empty(Xc.shape[:1] + (2, 3))
        J[:, :, 0] = A[:, :, 0] * iz[:, None]
        J[:, :, 1] = A[:, :, 1] * iz[:, None]
        J[:, :, 2] = -(A[:, :, 0] * x[:, None] + A[:, :, 1] * y[:, None]) * iz[:, None]
        J[behind] = np.nan
        return uv, J

    def project(self, X_rig, *, jacobian=False):
        """Pixels (N, 2) of rig-frame points (N, 3); with ``jacobian`` also d uv / d X_rig (N, 2, 3)."""
        Xc = self.to_cam(np.atleast_2d(np.asarray(X_rig, float)))
        if not jacobian:
            return self.project_cam(Xc)
        uv, J = self.project_cam(Xc, jacobian=True)
        return uv, J @ self.R

    def undistort_points(self, uv, iterations=20) -> np.ndarray:
        """Normalised ideal coordinates ``(x/z, y/z)`` (N, 2) of pixels (N, 2): Gauss-Newton on the exact model,
        started at the undistorted pinhole inverse."""
        uv = np.atleast_2d(np.asarray(uv, float))
        K = self.K
        y = (uv[:, 1] - K[1, 2]) / K[1, 1]
        x = (uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        xy = np.stack([x, y], axis=1)
        if not self.dist.any():
            return xy
        for _ in range(iterations):
            X = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
            pred, J = self.project_cam(X, jacobian=True)
            r = uv - pred
            step = np.linalg.solve(J[:, :, :2], r[..., None])[..., 0]
            xy = xy + step
            if np.abs(r).max(initial=0) < 1e-10:
                break
        return xy

    def rays(self, uv) -> tuple[np.ndarray, np.ndarray]:
        """Origins (N, 3) and unit directions (N, 3), in the rig frame, of the rays through pixels (N, 2)."""
        xy = self.undistort_points(uv)
        d_cam = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        d = d_cam @ self.R  # R^T d for each row
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.broadcast_to(self.centre, d.shape).copy(), d

    def in_image(self, uv, margin=0.0) -> np.ndarray:
        uv = np.asarray(uv)
        return ((uv[..., 0] >= -0.5 + margin) & (uv[..., 0] <= self.width - 0.5 - margin)
                & (uv[..., 1] >= -0.5 + margin) & (uv[..., 1] <= self.height - 0.5 - margin))


@dataclass(frozen=True)
class Rig:
    """N >= 1 cameras with their poses in a common rig frame (camera 0's frame by default).

    Attributes
    ----------
    cameras : tuple of Camera
    meta : dict   residuals, target, standard deviations, provenance (see docs/formats.md, rig file)
    """

    cameras: tuple
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        cams = tuple(self.cameras)
        if not cams or not all(isinstance(c, Camera) for c in cams):
            raise ValueError("rig: at least one Camera expected")
        names = [c.name for c in cams]
        if len(set(names)) != len(names):
            raise ValueError(f"rig: camera names must be unique, got {names}")
        object.__setattr__(self, "cameras", cams)

    def __len__(self):
        return len(self.cameras)

    def __getitem__(self, key) -> Camera:
        if isinstance(key, str):
            for c in self.cameras:
                if c.name == key:
                    return c
            raise KeyError(f"no camera named {key!r} in the rig ({[c.name for c in self.cameras]})")
        return self.cameras[key]

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def cam_from_cam(self, a, b) -> np.ndarray:
        """``a_from_b`` (4x4) between two cameras (names or indices)."""
        return self[a].cam_from_rig @ invert_pose(self[b].cam_from_rig)

    def baselines(self) -> dict:
        """Distance in metres between every pair of projection centres, keyed ``'A-B'``."""
        out = {}
        for i, a in enumerate(self.cameras):
            for b in self.cameras[i + 1:]:
                out[f"{a.name}-{b.name}"] = float(np.linalg.norm(a.centre - b.centre))
        return out

    def project(self, X_rig) -> np.ndarray:
        """Pixels (n_cam, N, 2) of rig-frame points in every camera."""
        return np.stack([c.project(X_rig) for c in self.cameras])
