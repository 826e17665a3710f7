"""Registration onto what an endoscope sees (issue 16): a patch fitted to the observed surface.

An endoscope sees a few centimetres of the heart from about 3 cm. Nothing in such a view shows where a model patch
of the configured size would lie, and a recording without a pressure signal cannot place it by its motion
(:mod:`tracker.registration`). Here the patch is made to fit the view instead: its pose, extent and curvature come
from the points' reference positions (docs/model.md "Patch fitted to the observed surface"):

1. **Frame.** The robust centre and principal axes of the reference positions of the points seen in the first
   frames; the normal (smallest axis) turned towards the cameras (the rig origin), the first in-plane axis along
   the largest spread.
2. **Curvature.** A quadric ``y = c0 + c1 x + c2 z - (k_xx x^2 + 2 k_xz x z + k_zz z^2) / 2`` fitted by robust least
   squares in that frame; its Hessian's eigenvectors turn the in-plane axes onto the principal directions (``s``
   the one of the larger radius), the apex moves to the quadric's point above the centre, the normal to its
   normal there. The radii are ``1 / k`` of the principal curvatures, each clipped to ``[MIN_RADIUS_FACTOR,
   MAX_RADIUS_FACTOR]`` times the patch's size (a concave or flat direction gets the largest: nearly flat), and
   above twice the wall thickness.
3. **Extent.** The observed region, the ``[QUANTILE, 1 - QUANTILE]`` range of the points' in-plane coordinates
   about the apex, times :data:`MARGIN`: the clamped rim of the model lies outside the view, as the heart around
   the view is not clamped either. The model keeps the model file's node counts, so its resolution follows the
   patch's size.
4. **Pose refinement** of the surface's distances (the trimmed soft-L1 fit of :mod:`tracker.registration`) over
   the patch's depth, tilt and spin about its normal (:data:`REFINED_DOF`). Its in-plane position stays where
   steps 2-3 centred it on the observed region: the distances do not determine a slide along a nearly flat
   direction, and a free fit drifted there until no point was left on the patch.

Points whose reference falls off the patch (beyond the extent, or farther than a quarter of the thickness from the
surface) are dropped and counted.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math

import numpy as np
from scipy.optimize import least_squares

from .files import InputError
from .geometry import PatchGeometry
from .measurements import MeasurementSet
from .registration import MIN_POINTS, Registration, _apply, _fit_surface, _inside, _pose

__all__ = ["ObservedPatch", "fit_observed_patch", "MARGIN", "QUANTILE", "geometry_to_dict", "geometry_from_dict",
           "view_extent", "view_within_patch", "check_view_scale", "MAX_VIEW_M"]

MARGIN = 2.0
"""Patch extent over the observed region's extent (per axis): the view covers the central half of the patch."""
QUANTILE = 0.02
"""The observed region: the 2-98 % range of the points' in-plane coordinates (a few stray points do not widen it)."""
MIN_RADIUS_FACTOR = 0.5
REFINED_DOF = np.array([0, 1, 2, 4])
"""Pose coordinates the surface fit refines (:data:`tracker.registration.ALL_DOF`'s order: rotation vector x, y, z,
translation x, y, z in the patch frame): the rotations about the apex and the translation along the normal. The
in-plane translation is left out: along a direction whose radius is many times the view (a cylinder's axis) the
surface's distances do not change with it, and the soft-L1 fit then slid the patch off the observed region (a
real sequence's later half, 0 of 255 points left on the patch; ``tests/tracker/test_unknown_input.py``)."""
MAX_RADIUS_FACTOR = 20.0


@dataclass(frozen=True)
class ObservedPatch:
    """Result of :func:`fit_observed_patch`.

    Attributes
    ----------
    geometry : PatchGeometry            the fitted patch (the model file's thickness and node counts)
    registration : Registration         rig -> patch pose, on-patch flags per point, surface RMS
    observed_extent_m : (2,)            the observed region along s and t
    curvature_1pm : (2,)                fitted principal curvatures along s and t (1/m; negative = concave)
    """

    geometry: PatchGeometry
    registration: Registration
    observed_extent_m: np.ndarray
    curvature_1pm: np.ndarray

    def info(self) -> dict:
        g = self.geometry
        reg = self.registration
        return {"method": "observed surface", "length_m": g.length, "width_m": g.width,
                "radius_long_m": g.radius_long, "radius_circ_m": g.radius_circ,
                "observed_extent_m": [float(v) for v in self.observed_extent_m],
                "curvature_1pm": [float(v) for v in self.curvature_1pm], "margin": MARGIN,
                "points_on_patch": int(reg.on_patch.sum()), "points_dropped": int((~reg.on_patch).sum()),
                "rms_m": float(reg.rms_m)}


def geometry_to_dict(g: PatchGeometry) -> dict:
    return {"length": float(g.length), "width": float(g.width), "thickness": float(g.thickness),
            "radius_long": float(g.radius_long), "radius_circ": float(g.radius_circ), "grid": list(g.grid)}


def geometry_from_dict(d) -> PatchGeometry:
    """ValueError naming the key for a bad mapping."""
    if not isinstance(d, dict):
        raise ValueError("a mapping expected")
    try:
        return PatchGeometry(float(d["length"]), float(d["width"]), float(d["thickness"]), float(d["radius_long"]),
                             float(d["radius_circ"]), tuple(int(v) for v in d["grid"]))
    except KeyError as exc:
        raise ValueError(f"{exc.args[0]}: missing") from None
    except (TypeError, ValueError) as exc:
        raise ValueError(str(exc)) from None


def _reference_points(meas: MeasurementSet, frames: int):
    """Indices and reference positions of the points seen in two of the first ``frames`` frames."""
    K = min(int(frames), meas.n_frames)
    seen = np.isfinite(meas.positions[:K, :, 0]).sum(axis=0) >= min(2, K)
    idx = np.flatnonzero(seen & np.isfinite(meas.reference).all(axis=1))
    return idx, meas.reference[idx]


def view_extent(meas: MeasurementSet, frames: int = 10) -> np.ndarray:
    """In-plane extent (m, larger first) of the surface seen in the first ``frames`` frames: the
    ``[QUANTILE, 1 - QUANTILE]`` range of the reference positions along their two principal axes (zeros with fewer
    than three points)."""
    _, X = _reference_points(meas, frames)
    if X.shape[0] < 3:
        return np.zeros(2)
    _, _, Vt = np.linalg.svd(X - np.median(X, axis=0), full_matrices=False)
    P = (X - np.median(X, axis=0)) @ Vt[:2].T
    ext = np.quantile(P, 1 - QUANTILE, axis=0) - np.quantile(P, QUANTILE, axis=0)
    return np.sort(ext)[::-1]


MAX_VIEW_M = 0.5
"""Largest extent of an observed heart surface (m): an adult human heart is about 12 cm long, a horse's about 25;
a wider view is positions in other units than metres (millimetres: a 3-cm view reads 30 m)."""


def check_view_scale(meas: MeasurementSet, frames: int = 10) -> None:
    """InputError (field ``reference``) when the surface seen in the first ``frames`` frames spans more than
    :data:`MAX_VIEW_M`: no heart's surface does; positions in millimetres do (a fit would place a patch tens of
    metres wide and report it as converged)."""
    ext = view_extent(meas, frames)
    if ext[0] > MAX_VIEW_M:
        raise InputError(None, f"the observed surface spans {ext[0]:.3g} x {ext[1]:.3g} m; a heart's surface spans "
                               f"centimetres (at most {MAX_VIEW_M:g} m): are the positions in millimetres? "
                               "Measurement files hold metres", "reference")


def view_within_patch(meas: MeasurementSet, geometry: PatchGeometry, frames: int = 10) -> bool:
    """Whether the observed surface fits inside the model's patch (each sorted extent at most the patch's): an
    endoscope's view of a few centimetres, onto which the patch is fitted (:func:`fit_observed_patch`), rather than
    a view of more than the patch, in which the model's patch is placed (:mod:`tracker.registration`)."""
    ext = view_extent(meas, frames)
    patch = np.sort([geometry.length, geometry.width])[::-1]
    return bool(np.all(ext <= patch))


def _quadric(xz, y, f_scale):
    """Robust quadric fit ``y = c0 + c1 x + c2 z - (kxx x^2 + 2 kxz x z + kzz z^2) / 2``: (c, Hessian)."""
    x, z = xz[:, 0], xz[:, 1]
    X = np.stack([np.ones_like(x), x, z, -0.5 * x * x, -x * z, -0.5 * z * z], axis=1)
    c0, *_ = np.linalg.lstsq(X, y, rcond=None)
    sol = least_squares(lambda c: X @ c - y, c0, loss="soft_l1", f_scale=f_scale)
    c = sol.x
    return c, np.array([[c[3], c[4]], [c[4], c[5]]])


def fit_observed_patch(meas: MeasurementSet, template: PatchGeometry, *, frames: int = 10,
                       margin: float = MARGIN) -> ObservedPatch:
    """Fit a patch to the surface seen in the first ``frames`` frames of a rig-frame set (steps of the module doc).

    ``template`` gives the wall thickness and the node counts. Raises InputError (field ``positions``) with fewer
    than :data:`tracker.registration.MIN_POINTS` points or a degenerate (collinear) point set.
    """
    if meas.frame != "rig":
        raise ValueError(f"measurements: frame 'rig' expected, got {meas.frame!r}")
    check_view_scale(meas, frames)
    idx, X = _reference_points(meas, frames)
    if idx.size < MIN_POINTS:
        raise InputError(None, f"{idx.size} points seen in two of the first {frames} frames: at least {MIN_POINTS} "
                               "are needed to fit a patch to the observed surface", "positions")
    c = np.median(X, axis=0)
    U, S, Vt = np.linalg.svd(X - c, full_matrices=False)
    if S[1] < 1e-6 * max(S[0], 1e-300):
        raise InputError(None, "the points lie on a line: no surface to fit a patch to", "positions")
    e_s, n = Vt[0], Vt[2]
    if n @ (-c) < 0:  # the outward normal faces the cameras
        n = -n
    e_t = np.cross(e_s, n)
    R = np.stack([e_s, n, e_t])  # patch x = s, y = normal, z = t
    P = (X - c) @ R.T
    spread = np.quantile(P[:, [0, 2]], 1 - QUANTILE, axis=0) - np.quantile(P[:, [0, 2]], QUANTILE, axis=0)
    size = float(max(spread.max(), 1e-6))
    coef, Hs = _quadric(P[:, [0, 2]], P[:, 1], f_scale=max(1e-2 * size, 1e-5))
    kappa, V = np.linalg.eigh(Hs)          # ascending: V[:, 0] the flatter direction -> s (larger radius)
    if np.linalg.det(V) < 0:
        V[:, 1] = -V[:, 1]
    # rotate the in-plane axes onto the principal directions, tilt the normal onto the quadric's at the centre
    ex = V[0, 0] * R[0] + V[1, 0] * R[2]
    ez = V[0, 1] * R[0] + V[1, 1] * R[2]
    grad = coef[1] * R[0] + coef[2] * R[2]
    n2 = R[1] - grad
    n2 /= np.linalg.norm(n2)
    ex = ex - (ex @ n2) * n2
    ex /= np.linalg.norm(ex)
    ez = np.cross(ex, n2)
    R2 = np.stack([ex, n2, ez])
    apex = c + coef[0] * R[1]
    P2 = (X - apex) @ R2.T
    lo = np.quantile(P2[:, [0, 2]], QUANTILE, axis=0)
    hi = np.quantile(P2[:, [0, 2]], 1 - QUANTILE, axis=0)
    mid = 0.5 * (lo + hi)
    extent = np.maximum(hi - lo, 1e-4)
    apex = apex + mid[0] * R2[0] + mid[1] * R2[2]
    length, width = margin * extent
    big = max(length, width)
    radii = []
    for k in kappa:
        r = 1.0 / k if k > 0 else math.inf
        radii.append(float(np.clip(r, max(MIN_RADIUS_FACTOR * big, 2.0 * template.thickness),
                                   MAX_RADIUS_FACTOR * big)))
    # keep the patch from wrapping around its axes (PatchGeometry's limits) with room to spare
    r1 = max(radii[0], length / 2.5)
    r2 = max(radii[1], width / 5.0)
    g = replace(template, length=float(length), width=float(width), radius_long=r1, radius_circ=r2)
    T = _pose(R2, -R2 @ apex)
    size_thick = min(g.thickness, 0.25 * min(length, width))
    T = _fit_surface(T, X, g, taus=(size_thick, 0.5 * size_thick), free=REFINED_DOF)
    # on-patch flags for every point of the set
    std = g.from_patch(_apply(T, meas.reference))
    max_depth = 0.25 * g.thickness
    ok = np.isfinite(std).all(axis=1)
    on = np.zeros(meas.n_points, bool)
    on[ok] = _inside(std[ok], g) & (np.abs(std[ok, 2]) <= max_depth)
    sel = np.zeros(meas.n_points, bool)
    sel[idx] = True
    used = on & sel
    if used.sum() < MIN_POINTS:
        reg = Registration(T, math.nan, on, int(used.sum()), False,
                           f"{int(used.sum())} of {idx.size} points lie on the patch fitted to the observed surface: "
                           f"at least {MIN_POINTS} are needed")
        return ObservedPatch(g, reg, extent, kappa)
    rms = float(np.sqrt(np.mean(std[used, 2] ** 2)))
    reg = Registration(T, rms, on, int(used.sum()), True,
                       f"patch fitted to the observed surface ({int(on.sum())} points on it, "
                       f"{int((~on).sum())} dropped)")
    return ObservedPatch(g, reg, extent, kappa)
