"""Geometry of the curved left-ventricular wall patch (docs/spec/model.md §2.1).

The patch is parameterised by ``(s, t, d)``: arc length along the long axis, circumferential arc length
and depth below the epicardium. The map to the patch frame is a surface of revolution about the x-axis,
offset inward along the normal, shifted so that the epicardial centre is the origin with outward normal +y:

    a = s/R1,  b = t/R2,  r = (R2 - R1) + (R1 - d) cos a
    x = (R1 - d) sin a,   y = r cos b - R2,   z = r sin b

``R1 = R2 = inf`` gives a flat slab (x = s, y = -d, z = t). Distances are in metres.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

__all__ = ["PatchGeometry", "PatchMesh", "build_mesh"]


@dataclass(frozen=True)
class PatchGeometry:
    """Size, curvature and resolution of the patch.

    Parameters
    ----------
    length, width, thickness : float
        L (along s), W (along t) and H (along d), in m.
    radius_long, radius_circ : float
        Meridional radius R1 and circumferential epicardial radius R2 in m; ``math.inf`` for flat.
        Either both finite or both infinite.
    grid : tuple of int
        Node counts (n_s, n_t, n_d) of the tensor hexahedral mesh, each >= 2.
    """

    length: float = 0.060
    width: float = 0.040
    thickness: float = 0.010
    radius_long: float = 0.080
    radius_circ: float = 0.035
    grid: tuple[int, int, int] = (9, 4, 2)

    def __post_init__(self):
        for name in ("length", "width", "thickness"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"geometry.{name}: must be a positive length in m, got {v!r}")
        r1, r2 = self.radius_long, self.radius_circ
        for name, v in (("radius_long", r1), ("radius_circ", r2)):
            if not (v > 0) or math.isnan(v):
                raise ValueError(f"geometry.{name}: must be positive (or inf for flat), got {v!r}")
        if math.isinf(r1) != math.isinf(r2):
            raise ValueError("geometry.radius_long/radius_circ: both finite or both inf (flat)")
        if not math.isinf(r1):
            if self.thickness >= min(r1, r2):
                raise ValueError(f"geometry.thickness: must be smaller than both radii, got {self.thickness}")
            if self.length / r1 >= math.pi or self.width / r2 >= 2 * math.pi:
                raise ValueError("geometry.length/width: patch wraps around its axis; use larger radii")
        g = tuple(int(v) for v in self.grid)
        if len(g) != 3 or min(g) < 2:
            raise ValueError(f"geometry.grid: three node counts >= 2 expected, got {self.grid!r}")
        object.__setattr__(self, "grid", g)

    @property
    def flat(self) -> bool:
        return math.isinf(self.radius_long)

    def to_patch(self, s, t, d):
        """Map parameter coordinates to the patch frame.

        Parameters
        ----------
        s, t, d : array_like, broadcastable
            Parameter coordinates in m.

        Returns
        -------
        ndarray of shape (..., 3)
        """
        s, t, d = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (s, t, d)))
        if self.flat:
            return np.stack([s, -d, t], axis=-1)
        R1, R2 = self.radius_long, self.radius_circ
        a = s / R1
        b = t / R2
        r = (R2 - R1) + (R1 - d) * np.cos(a)
        return np.stack([(R1 - d) * np.sin(a), r * np.cos(b) - R2, r * np.sin(b)], axis=-1)

    def from_patch(self, points):
        """Inverse of :meth:`to_patch` (closed form).

        Parameters
        ----------
        points : ndarray of shape (..., 3)

        Returns
        -------
        ndarray of shape (..., 3)
            ``(s, t, d)`` per point.
        """
        p = np.asarray(points, dtype=float)
        if p.shape[-1] != 3:
            raise ValueError(f"points: shape (..., 3) expected, got {p.shape}")
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        if self.flat:
            return np.stack([x, z, -y], axis=-1)
        R1, R2 = self.radius_long, self.radius_circ
        yy = y + R2
        b = np.arctan2(z, yy)
        r = np.hypot(yy, z)
        u = r - (R2 - R1)
        a = np.arctan2(x, u)
        rho = np.hypot(x, u)
        return np.stack([a * R1, b * R2, R1 - rho], axis=-1)

    def epicardial_normal(self, s, t):
        """Outward unit normal of the epicardium at ``(s, t)``, shape (..., 3)."""
        s, t = np.broadcast_arrays(np.asarray(s, float), np.asarray(t, float))
        if self.flat:
            n = np.zeros(s.shape + (3,))
            n[..., 1] = 1.0
            return n
        a, b = s / self.radius_long, t / self.radius_circ
        return np.stack([np.sin(a), np.cos(a) * np.cos(b), np.cos(a) * np.sin(b)], axis=-1)


@dataclass(frozen=True)
class PatchMesh:
    """Tensor hexahedral mesh of the patch.

    Attributes
    ----------
    geometry : PatchGeometry
    param : ndarray of shape (n_nodes, 3)
        ``(s, t, d)`` of every node.
    points : ndarray of shape (n_nodes, 3)
        Node positions in the patch frame (m).
    elements : ndarray of shape (n_elements, 8)
        Node indices per hexahedron, in scikit-fem's ``MeshHex`` order.
    node_index : ndarray of shape (n_s, n_t, n_d)
        Node index of grid position (i, j, k).
    axes : tuple of three ndarrays
        Grid coordinates along s, t and d.
    """

    geometry: PatchGeometry
    param: np.ndarray
    points: np.ndarray
    elements: np.ndarray
    node_index: np.ndarray
    axes: tuple

    @property
    def n_nodes(self) -> int:
        return self.points.shape[0]

    @property
    def rim_nodes(self) -> np.ndarray:
        """Boolean mask (n_nodes,) of nodes on the rim (s = +-L/2 or t = +-W/2, any depth)."""
        ni = self.node_index
        mask = np.zeros(self.n_nodes, bool)
        mask[ni[0].ravel()] = mask[ni[-1].ravel()] = True
        mask[ni[:, 0].ravel()] = mask[ni[:, -1].ravel()] = True
        return mask

    @property
    def epicardial_nodes(self) -> np.ndarray:
        """Boolean mask (n_nodes,) of nodes on the epicardium (d = 0)."""
        mask = np.zeros(self.n_nodes, bool)
        mask[self.node_index[:, :, 0].ravel()] = True
        return mask

    @property
    def endocardial_nodes(self) -> np.ndarray:
        """Boolean mask (n_nodes,) of nodes on the endocardium (d = H)."""
        mask = np.zeros(self.n_nodes, bool)
        mask[self.node_index[:, :, -1].ravel()] = True
        return mask

    def skfem_mesh(self):
        """The mesh as ``skfem.MeshHex`` in the patch frame (same node and element order)."""
        from skfem import MeshHex

        return MeshHex(self.points.T.copy(), self.elements.T.copy())


def build_mesh(geometry: PatchGeometry) -> PatchMesh:
    """Build the tensor hex mesh in ``(s, t, d)`` and map its vertices to the patch frame."""
    from skfem import MeshHex

    g = geometry
    ns, nt, nd = g.grid
    s = np.linspace(-g.length / 2, g.length / 2, ns)
    t = np.linspace(-g.width / 2, g.width / 2, nt)
    d = np.linspace(0.0, g.thickness, nd)
    m = MeshHex.init_tensor(s, t, d)
    param = m.p.T.copy()
    # node index of each grid position, recovered from coordinates (robust to skfem's ordering)
    i = np.rint((param[:, 0] + g.length / 2) / (g.length / (ns - 1))).astype(int)
    j = np.rint((param[:, 1] + g.width / 2) / (g.width / (nt - 1))).astype(int)
    k = np.rint(param[:, 2] / (g.thickness / (nd - 1))).astype(int)
    node_index = np.full((ns, nt, nd), -1, dtype=np.int64)
    node_index[i, j, k] = np.arange(param.shape[0])
    if (node_index < 0).any():
        raise RuntimeError("mesh generation: grid positions not all covered")
    param[:, 0], param[:, 1], param[:, 2] = s[i], t[j], d[k]
    points = g.to_patch(param[:, 0], param[:, 1], param[:, 2])
    return PatchMesh(g, param, points, m.t.T.copy(), node_index, (s, t, d))
