"""Lights and surface shading: Lambert diffuse plus Blinn-Phong specular (wet tissue highlights).

Radiance (linear, 1 = a white Lambertian surface facing a light of intensity 1 at the working distance) is

    L = albedo * (ambient + sum_j I_j a_j max(n.l_j, 0)) + k_s sum_j I_j a_j max(n.h_j, 0)^shininess [n.l_j > 0]

with ``a_j = (d0 / |x - p_j|)^2`` the inverse-square fall-off of point light j at ``p_j`` normalised at the
working distance ``d0``, ``l_j`` the unit vector to the light, ``h_j`` the half vector of ``l_j`` and the view
direction. No shadows and no inter-reflections (the lights sit beside the cameras).
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

__all__ = ["Lights", "make_lights", "shade"]


@dataclass(frozen=True)
class Lights:
    """Point lights: ``positions`` (n, 3) world frame, ``intensity`` (n,), ``ambient``, ``reference_m`` (the
    fall-off normalisation distance d0), ``specular`` k_s and ``shininess`` of the tissue."""

    positions: np.ndarray
    intensity: np.ndarray
    ambient: float
    reference_m: float
    specular: float
    shininess: float


def make_lights(spec, rig, world_from_ring, working_distance_m) -> Lights:
    """Lights of the scene's ``lighting`` section: one beside each camera (``light_offset_m`` in that camera's
    frame) or a ring of ``ring_count`` lights of radius ``ring_radius_m`` around the central axis in the
    cameras' plane. ``intensity`` is the total over the lights, shared equally."""
    if spec.kind == "camera":
        pos = np.array([c.centre + c.R.T @ np.asarray(spec.light_offset_m, float) for c in rig.cameras])
        inten = np.full(len(pos), spec.intensity / len(pos))
    else:
        phi = 2 * math.pi * (np.arange(spec.ring_count) + 0.5) / spec.ring_count
        ring = np.stack([spec.ring_radius_m * np.cos(phi), spec.ring_radius_m * np.sin(phi),
                         np.zeros_like(phi)], axis=1)
        pos = ring @ world_from_ring[:3, :3].T + world_from_ring[:3, 3]
        inten = np.full(len(pos), spec.intensity / len(pos))
    d0 = math.hypot(working_distance_m, np.linalg.norm(pos - pos.mean(axis=0), axis=1).mean())
    return Lights(pos, inten, float(spec.ambient), float(d0), float(spec.specular), float(spec.shininess))


def light_terms(points, normals, view, lights: Lights, specular=None, shininess=None):
    """Irradiance factor ``ambient + sum_j I_j a_j max(n.l_j, 0)`` (N,) and specular term
    ``k_s sum_j I_j a_j (n.h_j)^shininess`` (N,) (float32) of surface points.

    Parameters
    ----------
    points : ndarray (N, 3)        world frame (float32 is enough)
    normals : ndarray (N, 3)       unit normals; flipped where they face away from the viewer
    view : ndarray (3,) or (N, 3)  the camera centre, or the unit directions from the points to the camera
    specular, shininess : optional overrides of the lights' tissue values (e.g. for the instrument)

    Notes
    -----
    The half vector is never formed: with unit l and v, ``n.h = (n.l + n.v) / sqrt(2 (1 + l.v))``. The
    specular power is evaluated only where it exceeds 1e-4 of its peak.
    """
    P = np.asarray(points, np.float32)
    n = np.asarray(normals, np.float32)
    ks = float(lights.specular if specular is None else specular)
    shin = np.float32(lights.shininess if shininess is None else shininess)
    view = np.asarray(view, np.float32)
    if view.ndim == 1:
        v = view[None, :] - P
        v /= np.linalg.norm(v, axis=1, keepdims=True)
    else:
        v = view
    ndv = np.einsum("ij,ij->i", n, v)
    flip = ndv < 0
    if flip.any():
        n = np.where(flip[:, None], -n, n)
        ndv = np.abs(ndv)
    diffuse = np.full(P.shape[0], lights.ambient, np.float32)
    spec = np.zeros(P.shape[0], np.float32)
    d02 = np.float32(lights.reference_m ** 2)
    cut = np.float32(1e-4 ** (1.0 / float(shin)))  # n.h below this: (n.h)^shininess < 1e-4
    for p, inten in zip(lights.positions, lights.intensity):
        lv = p.astype(np.float32)[None, :] - P
        inv = 1.0 / np.sqrt(np.einsum("ij,ij->i", lv, lv))
        att = (np.float32(inten) * d02) * inv * inv
        ndl = np.einsum("ij,ij->i", n, lv) * inv
        np.maximum(ndl, 0, out=ndl)
        diffuse += att * ndl
        if ks > 0:
            ldv = np.einsum("ij,ij->i", lv, v) * inv
            ndh = (ndl + ndv) / np.sqrt(np.maximum(2 * (1 + ldv), 1e-12))
            hot = np.flatnonzero((ndh > cut) & (ndl > 0))
            spec[hot] += att[hot] * ndh[hot] ** shin
    spec *= np.float32(ks)
    return diffuse, spec


def shade(points, normals, view, albedo, lights: Lights, specular=None, shininess=None) -> np.ndarray:
    """Radiance (N, C) float32 ``albedo * irradiance + specular`` (module docstring; arguments as
    :func:`light_terms`, ``albedo`` (N, C) the diffuse reflectance per channel in [0, 1])."""
    diffuse, spec = light_terms(points, normals, view, lights, specular, shininess)
    out = np.asarray(albedo, np.float32) * diffuse[:, None]
    out += spec[:, None]
    return out
