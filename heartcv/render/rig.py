"""The scene's true rig: cameras on a regular polygon converging on the heart (docs/design.md §7).

The rig is built in a *ring frame*: the cameras sit on a regular polygon of side ``side_m`` in the plane z = 0
around the central axis +z (y down, x right), each looking at the convergence point ``(0, 0,
working_distance_m)`` with its y axis in the plane of its optical axis and the ring's y axis; camera 0 is at the
top (-y). The world (= rig) frame is camera 0's frame.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from ..camera import Camera, Rig, invert_pose, pose_matrix

if TYPE_CHECKING:  # scene.py imports this module
    from .scene import RigSpec

__all__ = ["ring_poses", "build_rig", "default_world_from_patch"]


def _look_at(centre, target) -> np.ndarray:
    """``cam_from_ring`` of a camera at ``centre`` looking at ``target`` with its y axis along ring +y."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in the ring frame
    return pose_matrix(R, -R @ centre)


def ring_poses(rig: RigSpec):
    """``(world_from_ring, [cam_from_world per camera])`` of the ring layout (module docstring)."""
    n = rig.cameras
    radius = rig.side_m / (2 * math.sin(math.pi / n)) if n > 1 else 0.0
    target = np.array([0.0, 0.0, rig.working_distance_m])
    cam_from_ring = []
    for i in range(n):
        phi = -math.pi / 2 + 2 * math.pi * i / n
        c = np.array([radius * math.cos(phi), radius * math.sin(phi), 0.0])
        cam_from_ring.append(_look_at(c, target))
    world_from_ring = cam_from_ring[0]
    ring_from_world = invert_pose(world_from_ring)
    return world_from_ring, [T @ ring_from_world for T in cam_from_ring]


def build_rig(rig: RigSpec) -> Rig:
    """The true cameras of the scene (names ``cam0``, ``cam1``...; ``cam_from_rig`` with rig = world)."""
    _, poses = ring_poses(rig)
    w, h = rig.image_size
    cams = []
    for i, T in enumerate(poses):
        over = rig.per_camera[i] if i < len(rig.per_camera) else {}
        f_mm = over.get("focal_mm", rig.focal_mm)
        pp = over.get("principal_point_px")
        dist = over.get("distortion", rig.distortion)
        cams.append(Camera.from_focal_mm(f"cam{i}", w, h, f_mm, rig.pixel_pitch_m,
                                         cx=None if pp is None else pp[0], cy=None if pp is None else pp[1],
                                         dist=np.asarray(dist, float) if len(dist) else np.zeros(5),
                                         cam_from_rig=T))
    return Rig(tuple(cams), {"source": "heartcv render (scene truth)"})


def default_world_from_patch(scene_rig: RigSpec) -> np.ndarray:
    """Patch centre at the convergence point, outward normal (+y) towards the rig, long axis (+x) along the
    ring's x axis (image rows)."""
    world_from_ring, _ = ring_poses(scene_rig)
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # columns: patch x, y, z in the ring frame
    ring_from_patch = pose_matrix(R, [0.0, 0.0, scene_rig.working_distance_m])
    return world_from_ring @ ring_from_patch
