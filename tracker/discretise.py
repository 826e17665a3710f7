"""Time discretisation of ``M c'' + D c' + K c = F u`` with first-order-hold input (docs/spec/model.md §3).

With ``x = [c; c']`` the exact discrete system over one frame interval ``dt`` is

    x_{k+1} = A x_k + B0 u_k + B1 u_{k+1}

when ``u`` is linear between frames (first-order hold). Three methods:

* ``modal`` (default): generalised eigenproblem ``K phi = w^2 M phi`` and closed-form 2x2 blocks per mode
  (spec §3.4); exact for Rayleigh damping ``D = alpha1 M + alpha2 K``.
* ``expm``: Van Loan's augmented matrix exponential (the test oracle).
* ``implicit-euler``: backward Euler on the first-order system (an L-stable fallback, first-order accurate,
  exact steady-state gain).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

__all__ = ["DiscreteSystem", "discretise", "modal_blocks", "METHODS"]

METHODS = ("modal", "expm", "implicit-euler")


@dataclass(frozen=True)
class DiscreteSystem:
    """``x_{k+1} = A x_k + B0 u_k + B1 u_{k+1}``.

    Attributes
    ----------
    A : ndarray of shape (2r, 2r)
    B0, B1 : ndarray of shape (2r, n_u)
    dt : float
    """

    A: np.ndarray
    B0: np.ndarray
    B1: np.ndarray
    dt: float

    @property
    def B(self) -> np.ndarray:
        """``[B0, B1]`` of shape (2r, 2 n_u), acting on ``[u_k; u_{k+1}]``."""
        return np.hstack([self.B0, self.B1])


def _check(M, K, F, dt):
    M = np.asarray(M, float)
    K = np.asarray(K, float)
    F = np.asarray(F, float)
    r = M.shape[0]
    if M.shape != (r, r) or K.shape != (r, r):
        raise ValueError(f"M and K: square (r, r) matrices expected, got {M.shape} and {K.shape}")
    if F.ndim == 1:
        F = F[:, None]
    if F.shape[0] != r:
        raise ValueError(f"F: shape ({r}, n_u) expected, got {F.shape}")
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt: positive time step expected, got {dt}")
    return M, K, F


def modal_blocks(omega2, c, dt):
    """Closed-form transition blocks of ``q'' + c q' + omega2 q = g u`` per mode.

    Parameters
    ----------
    omega2, c : ndarray of shape (r,)
        Squared natural frequencies (rad^2/s^2, > 0) and modal damping ``alpha1 + alpha2 omega2`` (1/s).
    dt : float

    Returns
    -------
    a0, s : ndarray of shape (r,)
        The mode's transition matrix is ``[[a0, s], [-omega2 s, a0 - c s]]``.
    """
    omega2 = np.asarray(omega2, float)
    c = np.asarray(c, float)
    disc = np.sqrt((c * c / 4 - omega2).astype(complex))
    lam_m = -c / 2 - disc  # largest magnitude root, no cancellation
    lam_p = omega2 / lam_m  # product of the roots is omega2
    e_m = np.exp(lam_m * dt)
    e_p = np.exp(lam_p * dt)
    diff = lam_p - lam_m
    near = np.abs(diff) * dt < 1e-6
    safe = np.where(near, 1.0, diff)
    s = (e_p - e_m) / safe
    a0 = (lam_p * e_m - lam_m * e_p) / safe
    if near.any():
        lb = 0.5 * (lam_p + lam_m)
        eb = np.exp(lb * dt)
        s = np.where(near, dt * eb, s)
        a0 = np.where(near, eb * (1 - lb * dt), a0)
    return a0.real, s.real


def _modal(M, K, alpha1, alpha2, F, dt):
    w2, Phi = sla.eigh(K, M)
    if w2.min() <= 0:
        raise ValueError("K must be positive definite on the free DOFs (is the rim clamped?)")
    c = alpha1 + alpha2 * w2
    a0, s = modal_blocks(w2, c, dt)
    g = Phi.T @ F  # modal loads (r, n_u)
    gam_u = ((1 - a0) / w2)[:, None] * g
    gam_v = s[:, None] * g
    # FOH: B1 = F_mode^{-1} (Gamma/dt - G_mode), F_mode^{-1} = [[-c/w2, -1/w2], [1, 0]]
    b1_u = (-c / w2)[:, None] * (gam_u / dt) - (1 / w2)[:, None] * (gam_v / dt - g)
    b1_v = gam_u / dt
    b0_u, b0_v = gam_u - b1_u, gam_v - b1_v
    PtM = Phi.T @ M
    r = M.shape[0]
    A = np.empty((2 * r, 2 * r))
    A[:r, :r] = (Phi * a0) @ PtM
    A[:r, r:] = (Phi * s) @ PtM
    A[r:, :r] = (Phi * (-w2 * s)) @ PtM
    A[r:, r:] = (Phi * (a0 - c * s)) @ PtM
    B0 = np.vstack([Phi @ b0_u, Phi @ b0_v])
    B1 = np.vstack([Phi @ b1_u, Phi @ b1_v])
    return A, B0, B1


def continuous(M, K, alpha1, alpha2, F):
    """First-order form ``x' = Fc x + Gc u`` (dense), ``Fc = [[0, I], [-M^-1 K, -M^-1 D]]``."""
    r = M.shape[0]
    D = alpha1 * M + alpha2 * K
    cf = sla.cho_factor(M)
    Fc = np.zeros((2 * r, 2 * r))
    Fc[:r, r:] = np.eye(r)
    Fc[r:, :r] = -sla.cho_solve(cf, K)
    Fc[r:, r:] = -sla.cho_solve(cf, D)
    Gc = np.zeros((2 * r, F.shape[1]))
    Gc[r:] = sla.cho_solve(cf, F)
    return Fc, Gc


def _expm(M, K, alpha1, alpha2, F, dt):
    Fc, Gc = continuous(M, K, alpha1, alpha2, F)
    n, nu = Gc.shape
    Z = np.zeros((n + 2 * nu, n + 2 * nu))
    Z[:n, :n] = Fc
    Z[:n, n : n + nu] = Gc
    Z[n : n + nu, n + nu :] = np.eye(nu) / dt
    E = sla.expm(Z * dt)
    A = E[:n, :n]
    G1 = E[:n, n : n + nu]
    G2 = E[:n, n + nu :]
    return A, G1 - G2, G2


def _implicit_euler(M, K, alpha1, alpha2, F, dt):
    Fc, Gc = continuous(M, K, alpha1, alpha2, F)
    n = Fc.shape[0]
    lu = sla.lu_factor(np.eye(n) - dt * Fc)
    A = sla.lu_solve(lu, np.eye(n))
    B1 = sla.lu_solve(lu, dt * Gc)
    return A, np.zeros_like(B1), B1


def discretise(M, K, alpha1, alpha2, F, dt, method="modal") -> DiscreteSystem:
    """Discretise ``M c'' + (alpha1 M + alpha2 K) c' + K c = F u`` over ``dt`` with first-order hold.

    Parameters
    ----------
    M, K : ndarray of shape (r, r)
        Symmetric positive definite mass and stiffness (physical units, after ``rho``, ``lambda``, ``mu``).
    alpha1, alpha2 : float
        Rayleigh coefficients (1/s, s).
    F : ndarray of shape (r, n_u) or (r,)
        Load columns per unit input.
    dt : float
        Frame interval in s.
    method : {'modal', 'expm', 'implicit-euler'}
    """
    M, K, F = _check(M, K, F, dt)
    if method == "modal":
        A, B0, B1 = _modal(M, K, alpha1, alpha2, F, dt)
    elif method == "expm":
        A, B0, B1 = _expm(M, K, alpha1, alpha2, F, dt)
    elif method == "implicit-euler":
        A, B0, B1 = _implicit_euler(M, K, alpha1, alpha2, F, dt)
    else:
        raise ValueError(f"discretisation.method: one of {METHODS} expected, got {method!r}")
    return DiscreteSystem(A, B0, B1, float(dt))
