"""Fast evaluation of the transition ``x' = A(theta) x + B0(theta) u_k + B1(theta) u_{k+1}`` for many theta.

The joint estimators (GE, UKF, EKF) need the transition at many parameter values per frame. Building the
dense ``A(theta)`` (168 x 168) for every sample costs one generalised eigenproblem and four GEMMs. This module
works in the modal coordinates instead (docs/spec/estimator.md §7.2-7.4, adapted to the exact modal discretisation):

* ``K(theta) = E (a(nu) K_lambda + b(nu) K_mu) = E b(nu) (e^s K_lambda + K_mu)`` and ``M = rho M0``. For a
  fixed ``nu`` the eigenvectors ``Phi`` of ``(K_nu, M0)`` (``Phi^T M0 Phi = I``) do not depend on rho, E,
  alpha1 or alpha2: those only scale the modal frequencies ``omega^2 = (E / rho) lam`` and damping
  ``c = alpha1 + alpha2 omega^2``. One eigenproblem per distinct ``nu`` serves every sample that shares it.
* In modal coordinates ``xt = T^-1 x`` with ``T = blkdiag(Phi, Phi)``, ``T^-1 = blkdiag(Phi^T M0, Phi^T M0)``,
  the transition is 2 x 2 block diagonal per mode: ``G = [[a0, s], [-omega^2 s, a0 - c s]]``
  (:func:`tracker.discretise.modal_blocks`), so ``A(theta) = T G(theta) T^-1`` and
  ``sum_i w_i A_i C A_i^T = T (sum_i w_i G_i Ct G_i^T) T^T`` with ``Ct = T^-1 C T^-T``: the weighted sum
  over the samples of a group is an O(r^2) Hadamard sum, and the group pays four r x r GEMM pairs once.

Everything here equals :meth:`tracker.model.PatchModel.system` (method ``modal``) to rounding; the tests check it.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from .discretise import modal_blocks
from .model import PatchModel

__all__ = ["ModalBasis", "TransitionFamily"]


@dataclass(frozen=True)
class ModalBasis:
    """Eigen-decomposition of ``(K_nu, M0)`` for one Poisson's ratio.

    Attributes
    ----------
    nu : float
    lam : ndarray (r,)       eigenvalues of ``a(nu) K_lambda + b(nu) K_mu`` w.r.t. ``M0`` (stiffness per unit E)
    Phi : ndarray (r, r)     ``M0``-orthonormal eigenvectors (columns)
    PtM : ndarray (r, r)     ``Phi^T M0`` (the inverse of ``Phi``)
    PtF : ndarray (r, n_u)   ``Phi^T F`` (modal loads per unit input, before dividing by rho)
    """

    nu: float
    lam: np.ndarray
    Phi: np.ndarray
    PtM: np.ndarray
    PtF: np.ndarray

    def to_modal(self, X) -> np.ndarray:
        """Physical states (..., 2r) -> modal (..., 2, r)."""
        X = np.asarray(X, float)
        r = self.lam.size
        return np.stack([X[..., :r] @ self.PtM.T, X[..., r:] @ self.PtM.T], axis=-2)

    def from_modal(self, Xt) -> np.ndarray:
        """Modal states (..., 2, r) -> physical (..., 2r)."""
        return np.concatenate([Xt[..., 0, :] @ self.Phi.T, Xt[..., 1, :] @ self.Phi.T], axis=-1)

    def cov_to_modal(self, C) -> np.ndarray:
        """``T^-1 C T^-T`` as blocks (2, 2, r, r)."""
        r = self.lam.size
        out = np.empty((2, 2, r, r))
        for a in range(2):
            for b in range(a, 2):
                out[a, b] = self.PtM @ C[a * r:(a + 1) * r, b * r:(b + 1) * r] @ self.PtM.T
                if b != a:
                    out[b, a] = out[a, b].T
        return out

    def cov_from_modal(self, S) -> np.ndarray:
        """``T S T^T`` for blocks S (2, 2, r, r) -> (2r, 2r)."""
        r = self.lam.size
        out = np.empty((2 * r, 2 * r))
        for a in range(2):
            for b in range(a, 2):
                blk = self.Phi @ S[a, b] @ self.Phi.T
                out[a * r:(a + 1) * r, b * r:(b + 1) * r] = blk
                if b != a:
                    out[b * r:(b + 1) * r, a * r:(a + 1) * r] = blk.T
        return out


class TransitionFamily:
    """``A(theta)``, ``B0(theta)``, ``B1(theta)`` of a :class:`PatchModel` for batches of theta (modal method).

    Parameters
    ----------
    model : PatchModel
    dt : float
        Frame interval in s.
    cache_size : int
        Number of eigen-decompositions kept (keyed by the exact value of nu).
    """

    def __init__(self, model: PatchModel, dt: float, cache_size: int = 8):
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt: positive time step expected, got {dt}")
        self.model = model
        self.dt = float(dt)
        self.r = model.r
        self.n_u = model.loads.shape[1]
        L = np.linalg.cholesky(model.M0)
        self._L = L
        Li = sla.solve_triangular(L, np.eye(self.r), lower=True)
        self._Kl = Li @ model.K_lambda @ Li.T
        self._Km = Li @ model.K_mu @ Li.T
        self._Kl = 0.5 * (self._Kl + self._Kl.T)
        self._Km = 0.5 * (self._Km + self._Km.T)
        self._cache: OrderedDict[float, ModalBasis] = OrderedDict()
        self._cache_size = int(cache_size)
        self.eig_count = 0  # eigen-decompositions computed (a cost counter for benchmarks and tests)

    # -- eigen-decompositions -----------------------------------------------------------------------
    def basis(self, nu: float) -> ModalBasis:
        nu = float(nu)
        hit = self._cache.get(nu)
        if hit is not None:
            self._cache.move_to_end(nu)
            return hit
        if not 0.0 < nu < 0.5:
            raise ValueError(f"nu: must lie in (0, 0.5), got {nu}")
        a = nu / ((1 + nu) * (1 - 2 * nu))
        b = 1.0 / (2 * (1 + nu))
        lam, V = sla.eigh(a * self._Kl + b * self._Km, driver="evd", check_finite=False)
        self.eig_count += 1
        if lam[0] <= 0:
            raise ValueError("K must be positive definite on the free DOFs (is the rim clamped?)")
        Phi = sla.solve_triangular(self._L, V, lower=True, trans="T")  # M0-orthonormal
        PtM = V.T @ self._L.T  # Phi^T M0 = V^T L^T
        basis = ModalBasis(nu, lam, Phi, PtM, Phi.T @ self.model.loads)
        self._cache[nu] = basis
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return basis

    # -- modal transition per sample -----------------------------------------------------------------
    def modal_terms(self, thetas, basis: ModalBasis, u0=None, u1=None):
        """Modal transition blocks and input terms for samples sharing ``basis.nu``.

        Parameters
        ----------
        thetas : ndarray (L, 5)
        u0, u1 : ndarray (n_u,), optional
            Inputs at the start and the end of the interval (first-order hold). Omitted: no input term.

        Returns
        -------
        G : ndarray (L, 2, 2, r)   per-mode transition ``[[a0, s], [-w2 s, a0 - c s]]``
        bt : ndarray (L, 2, r)     modal input term ``T^-1 (B0 u0 + B1 u1)`` (zeros without inputs)
        """
        th = np.atleast_2d(np.asarray(thetas, float))
        rho, a1, a2, E = th[:, 0:1], th[:, 1:2], th[:, 2:3], th[:, 3:4]
        w2 = (E / rho) * basis.lam[None, :]
        c = a1 + a2 * w2
        a0, s = modal_blocks(w2, c, self.dt)
        G = np.empty((th.shape[0], 2, 2, self.r))
        G[:, 0, 0] = a0
        G[:, 0, 1] = s
        G[:, 1, 0] = -w2 * s
        G[:, 1, 1] = a0 - c * s
        bt = np.zeros((th.shape[0], 2, self.r))
        if u0 is not None and self.n_u:
            u0 = np.asarray(u0, float).reshape(self.n_u)
            u1 = np.asarray(u1, float).reshape(self.n_u)
            dt = self.dt
            # FOH of q'' + c q' + w2 q = g(t), g linear from g0 to g1 (exact; see discretise._modal)
            g0 = (basis.PtF @ u0)[None, :] / rho
            g1 = (basis.PtF @ u1)[None, :] / rho
            gam_u = (1 - a0) / w2
            gam_v = s
            # B1 acting on g: u-part (-c/w2) gam_u/dt - (1/w2)(gam_v/dt - 1), v-part gam_u/dt
            b1_u = (-c / w2) * (gam_u / dt) - (gam_v / dt - 1.0) / w2
            b1_v = gam_u / dt
            bt[:, 0] = (gam_u - b1_u) * g0 + b1_u * g1
            bt[:, 1] = (gam_v - b1_v) * g0 + b1_v * g1
        return G, bt

    def groups(self, thetas):
        """Indices of the samples grouped by their exact nu: list of (basis, idx)."""
        th = np.atleast_2d(np.asarray(thetas, float))
        nus, inv = np.unique(th[:, 4], return_inverse=True)
        return [(self.basis(nu), np.flatnonzero(inv == g)) for g, nu in enumerate(nus)]

    def _check_states(self, th, X):
        """X (L, 2r + s): kinematic states, optionally followed by s static states (the reference block,
        docs/estimators.md §3.7) that the transition leaves unchanged."""
        X = np.atleast_2d(np.asarray(X, float))
        if X.shape[0] != th.shape[0] or X.shape[1] < 2 * self.r:
            raise ValueError(f"X: shape ({th.shape[0]}, {2 * self.r} + static) expected, got {X.shape}")
        return X

    def propagate(self, thetas, X, u0=None, u1=None) -> np.ndarray:
        """``A(theta_i) x_i + B0(theta_i) u0 + B1(theta_i) u1`` for every sample: thetas (L, 5), X (L, 2r + s);
        the last s columns (static states) are copied unchanged."""
        th = np.atleast_2d(np.asarray(thetas, float))
        X = self._check_states(th, X)
        n = 2 * self.r
        out = X.copy()
        for basis, idx in self.groups(th):
            G, bt = self.modal_terms(th[idx], basis, u0, u1)
            xt = basis.to_modal(X[idx, :n])
            yt = np.einsum("iabp,ibp->iap", G, xt) + bt
            out[idx, :n] = basis.from_modal(yt)
        return out

    def weighted_sandwich(self, thetas, weights, C) -> np.ndarray:
        """``sum_i w_i A(theta_i) C A(theta_i)^T`` (one modal transform per nu group) for any weights; C may carry
        s static states after the kinematic ones (``A = blkdiag(A(theta), I_s)``)."""
        return self.propagate_and_sandwich(thetas, None, weights, C)[1]

    def propagate_and_sandwich(self, thetas, X, weights, C, u0=None, u1=None):
        """:meth:`propagate` of X (or None) and :meth:`weighted_sandwich` of C in one pass over the nu groups.

        With s static states (C of size 2r + s): the kinematic block as below, the cross block
        ``sum_i w_i A_i C_xs = T (sum_i w_i G_i) T^-1 C_xs`` per group (two r x r x s products each way) and the
        static block ``(sum_i w_i) C_ss``."""
        th = np.atleast_2d(np.asarray(thetas, float))
        w = np.asarray(weights, float).reshape(-1)
        if w.size != th.shape[0]:
            raise ValueError(f"weights: {th.shape[0]} values expected, got {w.size}")
        n = 2 * self.r
        r = self.r
        C = np.asarray(C, float)
        ns = C.shape[0] - n
        if ns < 0 or C.shape != (n + ns, n + ns):
            raise ValueError(f"C: square of size {n} + static expected, got {C.shape}")
        if X is not None:
            X = self._check_states(th, X)
            if X.shape[1] != n + ns:
                raise ValueError(f"X: {n + ns} columns expected (as C), got {X.shape[1]}")
        Y = None if X is None else X.copy()
        out = np.zeros((n + ns, n + ns))
        C_xx = C[:n, :n]
        C_xs = C[:n, n:]
        for basis, idx in self.groups(th):
            G, bt = self.modal_terms(th[idx], basis, u0, u1)
            if X is not None:
                yt = np.einsum("iabp,ibp->iap", G, basis.to_modal(X[idx, :n])) + bt
                Y[idx, :n] = basis.from_modal(yt)
            Ct = basis.cov_to_modal(C_xx)
            # S[a, b] = sum_{c, d} (sum_i w_i g_ac^i (g_bd^i)^T) o Ct[c, d]: all 16 weighted outer products in
            # one GEMM of (4r x Lg)(Lg x 4r), then one Hadamard contraction
            Lg = idx.size
            Gf = G.reshape(Lg, 4 * r)
            W = ((Gf * w[idx][:, None]).T @ Gf).reshape(2, 2, r, 2, 2, r)  # [a, c, p, b, d, q]
            S = np.zeros((2, r, 2, r))  # [a, p, b, q]
            for c_ in range(2):
                for d in range(2):
                    S += W[:, c_, :, :, d, :] * Ct[c_, d][None, :, None, :]
            S = S.transpose(0, 2, 1, 3)
            out[:n, :n] += basis.cov_from_modal(S)
            if ns:
                Gw = np.einsum("i,iabp->abp", w[idx], G)                              # sum_i w_i G_i
                Xt = np.stack([basis.PtM @ C_xs[:r], basis.PtM @ C_xs[r:]])            # T^-1 C_xs (2, r, s)
                Yt = np.einsum("abp,bps->aps", Gw, Xt)
                out[:n, n:] += np.concatenate([basis.Phi @ Yt[0], basis.Phi @ Yt[1]])
        if ns:
            out[n:, :n] = out[:n, n:].T
            out[n:, n:] = w.sum() * C[n:, n:]
        return Y, out

    def system(self, theta):
        """Dense ``(A, B0, B1)`` for one theta (for tests and for the KF-style sandwich)."""
        th = np.asarray(theta, float).reshape(5)
        basis = self.basis(th[4])
        G, _ = self.modal_terms(th[None], basis)
        r, n_u = self.r, self.n_u
        A = np.empty((2 * r, 2 * r))
        for a in range(2):
            for b in range(2):
                A[a * r:(a + 1) * r, b * r:(b + 1) * r] = (basis.Phi * G[0, a, b]) @ basis.PtM
        B = []
        for k in range(2):
            cols = np.empty((2 * r, n_u))
            for j in range(n_u):
                u0 = np.eye(n_u)[j] if k == 0 else np.zeros(n_u)
                u1 = np.zeros(n_u) if k == 0 else np.eye(n_u)[j]
                _, bt = self.modal_terms(th[None], basis, u0, u1)
                cols[:, j] = basis.from_modal(bt[0])
            B.append(cols)
        return A, B[0], B[1]
