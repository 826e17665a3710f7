"""A surgical instrument: a round-ended cylinder (capsule) that moves in over the surface and occludes it.

The scene's ``instrument`` section gives, in the **patch frame**, the final tip position ``tip_m`` and the axis
``direction`` from the tip towards the handle. The instrument exists during ``window_s = [t_on, t_off]``; it
enters along its own axis, its tip travelling from ``tip_m + travel_m * axis`` to ``tip_m`` during the first
``enter_s`` seconds of the window (smootherstep in time), then stays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Instrument", "make_instrument"]


@dataclass(frozen=True)
class Instrument:
    """Capsule mesh in its own frame (tip at the origin, axis +z) and its motion (world frame)."""

    vertices: np.ndarray  # (n, 3) own frame
    faces: np.ndarray  # (m, 3) int32
    normals: np.ndarray  # (n, 3) own frame
    world_tip_final: np.ndarray  # (3,)
    world_axis: np.ndarray  # (3,) unit, tip -> handle
    travel_m: float
    window_s: tuple
    enter_s: float
    reflectance: float

    def present(self, t) -> bool:
        return self.window_s[0] <= t <= self.window_s[1]

    def tip(self, t) -> np.ndarray:
        """World tip position at time t (the final position outside the window)."""
        x = 1.0 if self.enter_s <= 0 else np.clip((t - self.window_s[0]) / self.enter_s, 0.0, 1.0)
        s = x * x * x * (x * (6 * x - 15) + 10)
        return self.world_tip_final + self.world_axis * self.travel_m * (1.0 - s)

    def world_from_own(self, t) -> np.ndarray:
        z = self.world_axis
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        T = np.eye(4)
        T[:3, :3] = np.stack([x, y, z], axis=1)
        T[:3, 3] = self.tip(t)
        return T

    def mesh(self, t):
        """``(vertices, normals)`` in the world frame at time t."""
        T = self.world_from_own(t)
        return self.vertices @ T[:3, :3].T + T[:3, 3], self.normals @ T[:3, :3].T


def make_instrument(spec, world_from_patch) -> Instrument | None:
    """The scene's instrument (None when disabled)."""
    if not spec.enabled:
        return None
    import trimesh

    r, L = spec.radius_m, spec.length_m
    cap = trimesh.creation.capsule(height=L, radius=r, count=[32, 16])
    v = np.asarray(cap.vertices, float) + [0.0, 0.0, L / 2 + r]  # tip (lowest point) at the origin
    R = world_from_patch[:3, :3]
    axis = R @ (np.asarray(spec.direction, float) / np.linalg.norm(spec.direction))
    tip = R @ np.asarray(spec.tip_m, float) + world_from_patch[:3, 3]
    return Instrument(v, np.asarray(cap.faces, np.int32), np.asarray(cap.vertex_normals, float), tip, axis,
                      float(spec.travel_m), tuple(spec.window_s), float(spec.enter_s), float(spec.reflectance))
