"""Heart-like phantom surface that contains the model's patch (tracker/geometry.py).

The phantom is a closed surface of revolution about the patch's long axis, the line ``y = -R2, z = 0`` of the
patch frame (the axis of the patch map, docs/spec/model.md §2.1). Its meridian profile (distance ``r`` from the axis
against ``x``) is

* inside the patch band ``|x| <= x_e = R1 sin(L / 2 R1)``: the patch's own meridian circle, so the band *is*
  the patch's epicardium (d = 0) and the patch ``|s| <= L/2, |t| <= W/2`` lies exactly on the phantom;
* beyond it, towards the apex (``x = -apex_m``) and the base (``x = +base_m``): ``r^2`` is the quartic in x
  that continues the circle with the same value, slope and curvature (C2) and reaches the axis with a round
  tip of curvature radius ``apex_radius_m`` / ``base_radius_m`` (``r^2 ~ 2 rho (x_end - x)`` there). A shape
  whose radius would not shrink monotonically to the tip is rejected.

Material coordinates of a surface point are ``(sigma, t)``: ``sigma`` the arc length along the meridian from
the patch centre, ``t = b R2`` with ``b`` the angle about the axis in [-pi, pi) (zero at the patch centre). On
the patch they equal the model's ``(s, t)`` at ``d = 0``. The mesh is a (sigma, b) grid whose lines run along
the patch rim, closed by one vertex at the apex and one at the base (watertight).
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
import scipy.sparse as sp

from ..tracker.files import InputError

__all__ = ["PhantomMesh", "build_phantom", "smootherstep", "displacement_operator", "vertex_normals", "locate",
           "surface_points"]


def smootherstep(x):
    """``6x^5 - 15x^4 + 10x^3`` on [0, 1], clamped outside: C2 with zero first and second derivative at the ends."""
    x = np.clip(np.asarray(x, float), 0.0, 1.0)
    return x * x * x * (x * (6 * x - 15) + 10)


@dataclass(frozen=True)
class PhantomMesh:
    """Reference (undeformed) phantom surface, patch frame, metres.

    Attributes
    ----------
    vertices : ndarray (V, 3)      reference positions (patch frame)
    faces : ndarray (F, 3) int32   counter-clockwise seen from outside (outward normals)
    material : ndarray (V, 2)      (sigma, t) of each vertex
    corner_uv : ndarray (F, 3, 2)  (sigma, t) of each face corner, t unwrapped across the seam at b = +-pi
    in_patch : ndarray (V,) bool   vertex lies on the model's patch (|sigma| <= L/2, |t| <= W/2)
    falloff : ndarray (V,)         weight w in [0, 1] of the outside motion: 0 on the patch and its rim, 1 at
                                   ``falloff_m`` (parameter distance) or more from it
    normals : ndarray (V, 3)       reference outward unit normals
    sigma_range : (float, float)   meridian arc length (signed) of the apex and the base
    period_m : float               circumferential period of t, 2 pi R2
    """

    vertices: np.ndarray
    faces: np.ndarray
    material: np.ndarray
    corner_uv: np.ndarray
    in_patch: np.ndarray
    falloff: np.ndarray
    normals: np.ndarray
    sigma_range: tuple
    period_m: float
    geometry: object

    @property
    def n_vertices(self) -> int:
        return self.vertices.shape[0]

    def trimesh(self, vertices=None):
        """A ``trimesh.Trimesh`` of the surface (reference vertices unless given)."""
        import trimesh

        v = self.vertices if vertices is None else vertices
        return trimesh.Trimesh(np.asarray(v, float), self.faces, process=False)


def _profile(geometry, spec):
    """Dense meridian polylines ``(sigma, x, r)`` beyond the patch band, towards the apex and towards the base."""
    R1, R2 = geometry.radius_long, geometry.radius_circ
    half = geometry.length / 2
    x_e = R1 * math.sin(half / R1)
    root = math.sqrt(R1 * R1 - x_e * x_e)
    r_e = (R2 - R1) + root  # circle at the band edge: value, slope and curvature (for |x| increasing)
    dr = -x_e / root
    d2r = -R1 * R1 / root**3
    out = []
    for sign, end, rho, names in ((-1, spec.apex_m, spec.apex_radius_m, ("apex_m", "apex_radius_m")),
                                  (1, spec.base_m, spec.base_radius_m, ("base_m", "base_radius_m"))):
        span = end - x_e
        if span <= 2e-3:
            raise InputError(None, f"the end must lie beyond the patch (> {1e3 * x_e + 2:.1f} mm from its centre), "
                                   f"got {1e3 * end:.1f} mm", f"phantom.{names[0]}")
        # F(u) = r^2 on u = (|x| - x_e) / span in [0, 1]: F(0), F'(0), F''(0) from the circle, F(1) = 0,
        # F'(1) = -2 rho span (round tip of curvature radius rho)
        a0, a1, a2 = r_e * r_e, 2 * r_e * dr * span, (dr * dr + r_e * d2r) * span * span
        c1 = -(a0 + a1 + a2)  # a3 + a4
        c2 = -2 * rho * span - a1 - 2 * a2  # 3 a3 + 4 a4
        a4 = c2 - 3 * c1
        a3 = c1 - a4
        u = 1 - np.cos(np.linspace(0, math.pi / 2, 40001))  # dense near the tip, where r changes fast
        F = a0 + u * (a1 + u * (a2 + u * (a3 + u * a4)))
        dF = a1 + u * (2 * a2 + u * (3 * a3 + u * 4 * a4))
        if (F[:-1] <= 0).any() or (dF[1:] >= 0).any():
            raise InputError(None, f"no round, monotonically narrowing end reaches {names[0]} = {1e3 * end:.1f} mm "
                                   f"with a tip radius of {1e3 * rho:.1f} mm; change either", f"phantom.{names[1]}")
        x = sign * (x_e + span * u)
        r = np.sqrt(np.maximum(F, 0.0))
        r[-1] = 0.0
        seg = np.hypot(np.diff(x), np.diff(r))
        sigma = sign * (half + np.concatenate([[0.0], np.cumsum(seg)]))
        out.append((sigma, x, r))
    return out


def _rows(half, sigma_end, step):
    """Row positions from +-half (exclusive) to the pole (inclusive), about ``step`` apart."""
    n = max(1, int(math.ceil(abs(sigma_end - half * np.sign(sigma_end)) / step)))
    return np.linspace(half * np.sign(sigma_end), sigma_end, n + 1)[1:]


def build_phantom(geometry, spec) -> PhantomMesh:
    """The reference phantom mesh for the patch ``geometry`` (``tracker.geometry.PatchGeometry``) and the scene's
    ``phantom`` section (:class:`heartcv.render.scene.PhantomSpec`)."""
    if geometry.flat:
        raise InputError(None, "the model's patch must be curved (finite radius_long and radius_circ)", "phantom")
    R1, R2 = geometry.radius_long, geometry.radius_circ
    half_s, half_t = geometry.length / 2, geometry.width / 2
    b_w = half_t / R2
    if b_w >= math.pi * 0.9:
        raise InputError(None, "the patch wraps (almost) around its axis; use a larger radius_circ", "phantom")
    h = spec.mesh_edge_m
    apex, base = _profile(geometry, spec)
    # meridian rows: exact patch rows on [-L/2, L/2], then outwards to the poles (the poles are single vertices)
    n_in = max(2, int(math.ceil(2 * half_s / h)))
    s_in = np.linspace(-half_s, half_s, n_in + 1)
    s_apex = _rows(half_s, apex[0][-1], h)[::-1]
    s_base = _rows(half_s, base[0][-1], h)
    rows = np.concatenate([s_apex[1:], s_in, s_base[:-1]])  # without the poles
    # circumferential columns: exact patch columns on [-b_w, b_w], seam at b = +-pi (the back)
    n_tin = max(2, int(math.ceil(2 * half_t / h)))
    n_out = max(2, int(math.ceil((math.pi - b_w) * R2 / h)))
    b = np.concatenate([np.linspace(-math.pi, -b_w, n_out + 1)[:-1], np.linspace(-b_w, b_w, n_tin + 1),
                        np.linspace(b_w, math.pi, n_out + 1)[1:-1]])
    nr, nb = rows.size, b.size
    S, B = np.meshgrid(rows, b, indexing="ij")  # (nr, nb)
    x = np.empty_like(S)
    r = np.empty_like(S)
    inner = np.abs(S) <= half_s + 1e-12
    a = S[inner] / R1
    x[inner] = R1 * np.sin(a)
    r[inner] = (R2 - R1) + R1 * np.cos(a)
    for sigma, xp, rp in (apex, base):
        sel = ~inner & (np.sign(S) == np.sign(sigma[-1]))
        order = np.argsort(sigma)
        x[sel] = np.interp(S[sel], sigma[order], xp[order])
        r[sel] = np.interp(S[sel], sigma[order], rp[order])
    ring = np.stack([x, r * np.cos(B) - R2, r * np.sin(B)], axis=-1).reshape(-1, 3)
    poles = np.array([[-spec.apex_m, -R2, 0.0], [spec.base_m, -R2, 0.0]])
    vertices = np.concatenate([ring, poles])
    # the exact patch map for the patch vertices (same formula; removes any round-off difference)
    t_all = (B * R2).ravel()
    s_all = S.ravel()
    on = inner.ravel()
    vertices[:-2][on] = geometry.to_patch(s_all[on], t_all[on], 0.0)
    material = np.concatenate([np.stack([s_all, t_all], axis=1),
                               [[apex[0][-1], 0.0], [base[0][-1], 0.0]]])
    faces, corner_uv = _triangulate(nr, nb, material, 2 * math.pi * R2)
    in_patch = np.zeros(vertices.shape[0], bool)
    in_patch[:-2] = on & (np.abs(t_all) <= half_t + 1e-12)
    ds = np.maximum(np.abs(material[:, 0]) - half_s, 0.0)
    dt = np.maximum(np.abs(material[:, 1]) - half_t, 0.0)
    falloff = smootherstep(np.hypot(ds, dt) / spec.falloff_m)
    mesh = PhantomMesh(vertices, faces, material, corner_uv, in_patch, falloff, np.zeros_like(vertices),
                       (float(apex[0][-1]), float(base[0][-1])), 2 * math.pi * R2, geometry)
    normals = vertex_normals(vertices, faces)
    object.__setattr__(mesh, "normals", normals)
    return mesh


def _triangulate(nr, nb, material, period):
    idx = np.arange(nr * nb).reshape(nr, nb)
    apex_v, base_v = nr * nb, nr * nb + 1
    i0, j0 = np.meshgrid(np.arange(nr - 1), np.arange(nb), indexing="ij")
    j1 = (j0 + 1) % nb
    a, b_, c, d = idx[i0, j0], idx[i0, j1], idx[i0 + 1, j1], idx[i0 + 1, j0]
    quads = np.concatenate([np.stack([a, b_, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    j = np.arange(nb)
    fan_apex = np.stack([np.full(nb, apex_v), idx[0, (j + 1) % nb], idx[0, j]], axis=1)
    fan_base = np.stack([np.full(nb, base_v), idx[-1, j], idx[-1, (j + 1) % nb]], axis=1)
    faces = np.concatenate([quads, fan_apex, fan_base]).astype(np.int32)
    uv = material[faces].copy()  # (F, 3, 2)
    # unwrap t across the seam (b = +-pi): corners more than half a period from the face's first ring corner
    ref = np.where(faces[:, :1] >= nr * nb, uv[:, 1:2, 1], uv[:, :1, 1])
    uv[..., 1] -= period * np.round((uv[..., 1] - ref) / period)
    for pole in (apex_v, base_v):  # pole corners take the mean t of the face's ring corners
        at = faces == pole
        rows = at.any(axis=1)
        ring_t = np.where(at[rows], np.nan, uv[rows, :, 1])
        uv[rows, :, 1] = np.where(at[rows], np.nanmean(ring_t, axis=1, keepdims=True), uv[rows, :, 1])
    return faces, uv.astype(np.float64)


def vertex_normals(vertices, faces) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3) of a triangle mesh (float64 or float32 in, same out)."""
    v = np.asarray(vertices)
    tri = v[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 area
    n = np.zeros_like(v)
    for k in range(3):
        for c in range(3):
            n[:, c] += np.bincount(faces[:, k], weights=fn[:, c], minlength=v.shape[0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    return n


def displacement_operator(mesh: PhantomMesh, model) -> sp.csr_matrix:
    """Sparse map ``D`` (V, n_nodes) from the model's node displacements to the vertices' displacements.

    Patch vertices get the trilinear interpolation ``N(s, t, 0)`` at their material coordinates (the simulator's
    interpolated epicardial displacement, ``model.shape_matrix``); every other vertex gets ``(1 - w)`` times the
    displacement of the nearest point of the patch rectangle in (s, t), so the field is continuous across the
    patch rim (with a clamped rim that extension is zero) and fades out over ``falloff_m``.
    """
    g = model.mesh.geometry
    s = np.clip(mesh.material[:, 0], -g.length / 2, g.length / 2)
    t = np.clip(mesh.material[:, 1], -g.width / 2, g.width / 2)
    N = model.shape_matrix(np.stack([s, t, np.zeros_like(s)], axis=1))
    weight = np.where(mesh.in_patch, 1.0, 1.0 - mesh.falloff)
    return sp.diags(weight) @ N


def locate(mesh: PhantomMesh, material) -> tuple[np.ndarray, np.ndarray]:
    """Face index (n,) and barycentric weights (n, 3) of material points ``(sigma, t)`` (n, 2) on the mesh
    (t taken modulo the period). The surface position of such a point in any configuration is
    ``(bary[:, :, None] * vertices[faces[face]]).sum(1)``: the texture is drawn there."""
    q = np.atleast_2d(np.asarray(material, float)).copy()
    P = mesh.period_m
    q[:, 1] = np.mod(q[:, 1] + P / 2, P) - P / 2
    uv = mesh.corner_uv
    lo, hi = uv.min(axis=1), uv.max(axis=1)
    # uniform bins over the (sigma, t) domain; a face is listed in every bin its bounding box touches
    size = np.maximum(np.median(hi - lo, axis=0), 1e-9)
    origin = lo.min(axis=0)
    c0 = np.floor((lo - origin) / size).astype(np.int64)
    c1 = np.floor((hi - origin) / size).astype(np.int64)
    ncol = int(c1[:, 1].max()) + 2
    keys, faces_of = [], []
    for di in range(int((c1 - c0)[:, 0].max()) + 1):
        for dj in range(int((c1 - c0)[:, 1].max()) + 1):
            ok = (c0[:, 0] + di <= c1[:, 0]) & (c0[:, 1] + dj <= c1[:, 1])
            keys.append((c0[ok, 0] + di) * ncol + c0[ok, 1] + dj)
            faces_of.append(np.flatnonzero(ok))
    keys, faces_of = np.concatenate(keys), np.concatenate(faces_of)
    order = np.argsort(keys, kind="stable")
    keys, faces_of = keys[order], faces_of[order]
    face = np.full(q.shape[0], -1)
    bary = np.zeros((q.shape[0], 3))
    for shift in (0.0, -P, P):  # faces across the seam have unwrapped t
        todo = np.flatnonzero(face < 0)
        if todo.size == 0:
            break
        pt = q[todo] + [0.0, shift]
        cell = np.floor((pt - origin) / size).astype(np.int64)
        key = cell[:, 0] * ncol + cell[:, 1]
        a, b = np.searchsorted(keys, key, "left"), np.searchsorted(keys, key, "right")
        for i, p, s0, s1 in zip(todo, pt, a, b):
            cand = faces_of[s0:s1]
            if cand.size == 0:
                continue
            A, B, C = uv[cand, 0], uv[cand, 1], uv[cand, 2]
            e1, e2, r = B - A, C - A, p - A
            det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
            det = np.where(np.abs(det) > 1e-30, det, np.nan)
            w1 = (r[:, 0] * e2[:, 1] - r[:, 1] * e2[:, 0]) / det
            w2 = (e1[:, 0] * r[:, 1] - e1[:, 1] * r[:, 0]) / det
            w = np.stack([1 - w1 - w2, w1, w2], axis=1)
            inside = np.flatnonzero((w >= -1e-9).all(axis=1))
            if inside.size:
                face[i], bary[i] = cand[inside[0]], w[inside[0]]
    if (face < 0).any():
        bad = int(np.flatnonzero(face < 0)[0])
        raise ValueError(f"material point {bad} {tuple(q[bad])} is not on the phantom")
    return face, bary


def surface_points(mesh: PhantomMesh, face, bary, vertices) -> np.ndarray:
    """Positions (n, 3) of located material points (:func:`locate`) on a configuration ``vertices`` (V, 3)."""
    v = np.asarray(vertices, float)[mesh.faces[np.asarray(face)]]  # (n, 3, 3)
    return np.einsum("nc,ncj->nj", np.asarray(bary, float), v)
