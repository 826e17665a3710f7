"""Ray casting with Intel Embree (through ``embreex``, the backend of ``trimesh.ray.ray_pyembree``).

* :func:`pixel_grid` -- the exact normalised ideal coordinates of every pixel centre of a camera (its distorted
  model inverted by :meth:`heartcv.camera.Camera.undistort_points`), computed once per camera, with a one-pixel
  ring around the image so that sub-pixel samples can be interpolated (:meth:`PixelGrid.directions`).
* :class:`EmbreeScene` -- triangle meshes (one Embree geometry each, the geometry id is the list index), built
  once per rendered instant: ``cast`` returns the first hit (geometry, triangle, barycentrics, distance).
* :func:`hull_mask` -- pixels that can see a mesh at all: the convex hull of its projected vertices, grown by a
  margin, so that background pixels never cast a ray.

Embree works in float32. Coordinates are shifted to a local origin near the geometry first, so that the
float32 rounding of a hit is far below 0.1 um at the default rig's scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["embree_available", "PixelGrid", "pixel_grid", "EmbreeScene", "Hits", "hull_mask"]


def embree_available() -> bool:
    """Whether ``embreex`` (Embree 4 bindings, used by trimesh) imports."""
    try:
        from embreex.mesh_construction import TriangleMesh  # noqa: F401
        import embreex.rtcore_scene  # noqa: F401
    except ImportError:
        return False
    return True


@dataclass(frozen=True)
class PixelGrid:
    """Normalised ideal coordinates ``(x/z, y/z)`` of pixel centres ``(u, v)`` for ``u = -1 .. W``,
    ``v = -1 .. H`` (a one-pixel ring beyond the image), camera frame.

    Attributes
    ----------
    xy : ndarray (H + 2, W + 2, 2) float64
    R_world_from_cam : ndarray (3, 3)
    centre : ndarray (3,)       projection centre, world frame
    """

    xy: np.ndarray
    R_world_from_cam: np.ndarray
    centre: np.ndarray

    @property
    def size(self):
        return self.xy.shape[1] - 2, self.xy.shape[0] - 2

    def directions(self, u=None, v=None, dtype=np.float32) -> np.ndarray:
        """Unit ray directions (N, 3), world frame, through pixel positions ``(u, v)`` (N,) (sub-pixel positions
        are interpolated bilinearly between the exact pixel centres); all pixel centres (row-major) if None."""
        if u is None:
            xy = self.xy[1:-1, 1:-1].reshape(-1, 2)
        else:
            u = np.asarray(u, float) + 1.0
            v = np.asarray(v, float) + 1.0
            W2, H2 = self.xy.shape[1], self.xy.shape[0]
            u0 = np.clip(np.floor(u).astype(np.int64), 0, W2 - 2)
            v0 = np.clip(np.floor(v).astype(np.int64), 0, H2 - 2)
            fu, fv = (u - u0)[:, None], (v - v0)[:, None]
            g = self.xy
            xy = ((1 - fv) * ((1 - fu) * g[v0, u0] + fu * g[v0, u0 + 1])
                  + fv * ((1 - fu) * g[v0 + 1, u0] + fu * g[v0 + 1, u0 + 1]))
        d = np.empty((xy.shape[0], 3), np.float64)
        d[:, :2] = xy
        d[:, 2] = 1.0
        d = d @ self.R_world_from_cam.T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return d.astype(dtype, copy=False)


def pixel_grid(camera) -> PixelGrid:
    """The :class:`PixelGrid` of a :class:`heartcv.camera.Camera` (one ``undistort_points`` call)."""
    W, H = camera.width, camera.height
    u, v = np.meshgrid(np.arange(-1.0, W + 1.0), np.arange(-1.0, H + 1.0))
    xy = camera.undistort_points(np.stack([u.ravel(), v.ravel()], axis=1)).reshape(H + 2, W + 2, 2)
    return PixelGrid(xy, camera.R.T.copy(), camera.centre.copy())


@dataclass(frozen=True)
class Hits:
    """First hits of N rays: ``geom`` (N,) int32 (-1 = miss), ``prim`` (N,) int32 triangle index, ``u``, ``v``
    (N,) float32 barycentrics (point = (1-u-v) v0 + u v1 + v v2), ``distance`` (N,) float32 (m)."""

    geom: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray
    distance: np.ndarray


class EmbreeScene:
    """Static Embree scene of triangle meshes in a shared local frame (see the module docstring)."""

    def __init__(self, meshes, origin=None):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        meshes = list(meshes)
        if not meshes:
            raise ValueError("EmbreeScene: at least one mesh expected")
        self.origin = (np.asarray(meshes[0][0], float).mean(axis=0) if origin is None
                       else np.asarray(origin, float))
        self._scene = rtcore_scene.EmbreeScene()
        self.n_triangles = 0
        for vertices, faces in meshes:
            v = np.ascontiguousarray(np.asarray(vertices, float) - self.origin, dtype=np.float32)
            f = np.ascontiguousarray(faces, dtype=np.int32)
            TriangleMesh(self._scene, v, f)
            self.n_triangles += f.shape[0]

    def cast(self, origin, directions) -> Hits:
        """First hits of rays from one ``origin`` (3,) (world frame) along unit ``directions`` (N, 3)."""
        d = np.ascontiguousarray(directions, dtype=np.float32)
        o = np.empty_like(d)
        o[:] = (np.asarray(origin, float) - self.origin).astype(np.float32)
        if d.shape[0] == 0:
            z = np.zeros(0, np.float32)
            return Hits(np.zeros(0, np.int32), np.zeros(0, np.int32), z, z, z)
        r = self._scene.run(o, d, output=1)
        geom = np.asarray(r["geomID"]).astype(np.int32)
        prim = np.asarray(r["primID"]).astype(np.int32)
        miss = (geom < 0) | (prim < 0) | (geom > 1000)  # embree's invalid id is 2^32 - 1
        geom[miss] = -1
        prim[miss] = -1
        return Hits(geom, prim, np.asarray(r["u"], np.float32), np.asarray(r["v"], np.float32),
                    np.asarray(r["tfar"], np.float32))


def hull_mask(camera, points_world, margin_px=3.0) -> np.ndarray:
    """Boolean (H, W) mask of the pixels inside the convex hull of the projections of ``points_world``
    (N, 3), grown by ``margin_px``. Points behind the camera make the whole image count."""
    import cv2

    uv = camera.project(np.asarray(points_world, float))
    mask = np.zeros((camera.height, camera.width), np.uint8)
    if not np.isfinite(uv).all():
        mask[:] = 1
        return mask.astype(bool)
    big = 1e6  # keep far-off projections representable as fixed-point coordinates
    hull = cv2.convexHull(np.clip(uv, -big, big).astype(np.float32)).reshape(-1, 2)
    shift = 4
    cv2.fillConvexPoly(mask, np.round(hull * (1 << shift)).astype(np.int32), 1, cv2.LINE_8, shift)
    r = int(np.ceil(margin_px))
    if r > 0:
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    return mask.astype(bool)
