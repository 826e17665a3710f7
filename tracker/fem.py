"""Finite-element matrices of the patch (docs/spec/model.md §2.2–§2.3).

Trilinear hexahedra (Hex1). The three parameter-free matrices are assembled once:

* ``K_lambda = int (div u)(div v)``  with a 1-point rule (selective reduced integration, no locking),
* ``K_mu     = int 2 eps(u):eps(v)`` with the 2x2x2 Gauss rule,
* ``M0       = int u . v``           with the 2x2x2 Gauss rule,

so that ``K(theta) = lambda K_lambda + mu K_mu`` and ``M(theta) = rho M0``. They are built from the six
scalar matrices ``G_ab = int d_a phi_j d_b phi_i`` (fast, exact path of spec §2.3):
block (b, a) of ``K_lambda`` is ``G_ab`` and block (b, a) of ``K_mu`` is ``delta_ab (G_xx + G_yy + G_zz) + G_ba``.
Degrees of freedom are interleaved: ``dof = 3 * node + component``.

Loads: ``f_p = -int_endo n . v dS`` per unit cavity pressure (N/Pa), and the optional active-tension column
``f_act = -int (f x f) : grad v dOmega`` per unit active stress, with the fibre helix angle varying linearly
from ``-60 deg`` (epicardium) to ``+60 deg`` (endocardium).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .geometry import PatchMesh

__all__ = ["FEMatrices", "assemble", "ONE_POINT_HEX"]

ONE_POINT_HEX = (np.full((3, 1), 0.5), np.array([1.0]))
"""One-point rule on scikit-fem's reference hexahedron [0, 1]^3."""


@dataclass(frozen=True)
class FEMatrices:
    """Assembled matrices on all ``3 * n_nodes`` DOFs (rim not yet eliminated).

    Attributes
    ----------
    K_lambda, K_mu, M0 : scipy.sparse.csr_matrix of shape (3 n_nodes, 3 n_nodes)
        In m (stiffness per unit Lamé constant) and m^3 (mass per unit density).
    f_pressure : ndarray of shape (3 n_nodes,)
        Load per unit endocardial pressure, N/Pa.
    f_active : ndarray of shape (3 n_nodes,)
        Load per unit active fibre stress, N/Pa.
    volume : float
        Volume of the mesh, m^3.
    """

    K_lambda: sp.csr_matrix
    K_mu: sp.csr_matrix
    M0: sp.csr_matrix
    f_pressure: np.ndarray
    f_active: np.ndarray
    volume: float


def _interleave(n: int, blocks) -> sp.csr_matrix:
    """Sum of scalar matrices placed at interleaved DOFs: entry (i, j) of block (b, a) goes to (3i+b, 3j+a)."""
    rows, cols, vals = [], [], []
    for b, a, S in blocks:
        S = S.tocoo()
        rows.append(3 * S.row + b)
        cols.append(3 * S.col + a)
        vals.append(S.data)
    return sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(n, n)).tocsr()


def scalar_gradient_blocks(basis) -> list[list[sp.csr_matrix]]:
    """``G[a][b] = int d_a phi_j d_b phi_i`` (row i, column j) for a, b in {x, y, z}."""
    from skfem import BilinearForm, asm

    G = [[None] * 3 for _ in range(3)]
    for a in range(3):
        for b in range(3):
            form = BilinearForm(lambda u, v, w, a=a, b=b: u.grad[a] * v.grad[b])
            G[a][b] = asm(form, basis).tocsr()
    return G


def assemble(mesh: PatchMesh) -> FEMatrices:
    """Assemble ``K_lambda``, ``K_mu``, ``M0`` and the load vectors for a patch mesh."""
    from skfem import Basis, BilinearForm, ElementHex1, asm

    m = mesh.skfem_mesh()
    elem = ElementHex1()
    basis = Basis(m, elem, intorder=2)
    basis1 = Basis(m, elem, quadrature=ONE_POINT_HEX)

    G = scalar_gradient_blocks(basis)
    G1 = scalar_gradient_blocks(basis1)
    n = 3 * mesh.n_nodes
    lap = G[0][0] + G[1][1] + G[2][2]
    # block (b, a) of K_lambda is G1_ab; block (b, a) of K_mu is delta_ab lap + G_ba (one COO pass each)
    K_lambda = _interleave(n, [(b, a, G1[a][b]) for a in range(3) for b in range(3)])
    K_mu = _interleave(n, [(b, a, G[b][a]) for a in range(3) for b in range(3)]
                       + [(c, c, lap) for c in range(3)])
    Ms = asm(BilinearForm(lambda u, v, w: u * v), basis)
    M0 = _interleave(n, [(c, c, Ms) for c in range(3)])

    f_p = _pressure_load(m, mesh, elem)
    f_act = _active_load(basis, mesh)
    volume = float(basis.dx.sum())
    return FEMatrices(
        K_lambda.tocsr(), K_mu.tocsr(), M0.tocsr(), f_p, f_act, volume
    )


def _pressure_load(m, mesh: PatchMesh, elem) -> np.ndarray:
    from skfem import FacetBasis, LinearForm, asm

    endo = mesh.endocardial_nodes
    facets = np.flatnonzero(endo[m.facets].all(axis=0))
    fb = FacetBasis(m, elem, facets=facets, intorder=2)
    # outward normal of the solid on the endocardium: orient it away from the element (towards the cavity)
    f = np.zeros(3 * mesh.n_nodes)
    for b in range(3):
        col = asm(LinearForm(lambda v, w, b=b: -w.n[b] * v), fb)
        f[b::3] = col
    # scikit-fem orients boundary-facet normals outward, so the traction -p n pushes the wall towards +y
    if not f[1::3].sum() > 0:
        raise RuntimeError("pressure load points inward: boundary-facet normals are not outward")
    return f


def _active_load(basis, mesh: PatchMesh) -> np.ndarray:
    from skfem import LinearForm, asm

    geom = mesh.geometry
    x = np.moveaxis(np.asarray(basis.global_coordinates()), 0, -1)  # (nel, nqp, 3)
    s, t, d = np.moveaxis(geom.from_patch(x), -1, 0)
    h = np.deg2rad(-60.0 + 120.0 * np.clip(d / geom.thickness, 0.0, 1.0))
    eps = 1e-6
    e_s = geom.to_patch(s + eps, t, d) - geom.to_patch(s - eps, t, d)
    e_t = geom.to_patch(s, t + eps, d) - geom.to_patch(s, t - eps, d)
    e_s /= np.linalg.norm(e_s, axis=-1, keepdims=True)
    e_t /= np.linalg.norm(e_t, axis=-1, keepdims=True)
    fib = np.cos(h)[..., None] * e_t + np.sin(h)[..., None] * e_s  # (nel, nqp, 3)
    fields = {f"f{c}": fib[..., c] for c in range(3)}

    f = np.zeros(3 * mesh.n_nodes)
    for b in range(3):
        form = LinearForm(
            lambda v, w, b=b: -sum(w[f"f{b}"] * w[f"f{c}"] * v.grad[c] for c in range(3))
        )
        f[b::3] = asm(form, basis, **fields)
    return f
