"""Material parameters and the estimator's coordinates (docs/spec/model.md §4.2).

``theta = [rho, alpha1, alpha2, E, nu]`` in SI units (kg/m^3, 1/s, s, Pa, 1) and

    phi = [log rho, log(alpha1 + eps1), log(alpha2 + eps2), log E, s],   s = log(lambda/mu) = log(2 nu / (1 - 2 nu))

so ``nu = e^s / (2 (1 + e^s))``. Every map is monotone, so a box in theta is a box in phi (bounds may
become infinite, e.g. ``nu in [0, 0.5]`` maps to ``s in [-inf, inf]``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "NAMES",
    "UNITS",
    "DEFAULT_BOUNDS",
    "lame",
    "nu_from_s",
    "s_from_nu",
    "ParameterSpace",
]

NAMES = ("rho", "alpha1", "alpha2", "E", "nu")
UNITS = ("kg/m^3", "1/s", "s", "Pa", "1")
DEFAULT_BOUNDS = {
    "rho": (1.0, 1.0e5),
    "alpha1": (0.0, 1.0e3),
    "alpha2": (0.0, 1.0),
    "E": (1.0, 1.0e10),
    "nu": (0.0, 0.5),
}


def lame(E, nu):
    """Lamé constants ``(lambda, mu)`` of Young's modulus ``E`` (Pa) and Poisson's ratio ``nu``."""
    E = np.asarray(E, float)
    nu = np.asarray(nu, float)
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


def s_from_nu(nu):
    """``s = log(2 nu / (1 - 2 nu))``; -inf at nu = 0, +inf at nu = 0.5."""
    nu = np.asarray(nu, float)
    with np.errstate(divide="ignore"):
        return np.log(2 * nu) - np.log1p(-2 * nu)


def nu_from_s(s):
    """Inverse of :func:`s_from_nu`: ``nu = e^s / (2 (1 + e^s))`` (stable for large |s|)."""
    s = np.asarray(s, float)
    return 0.5 / (1.0 + np.exp(-s))


@dataclass(frozen=True)
class ParameterSpace:
    """The five parameters, which of them are estimated, their box and the phi transform.

    Parameters
    ----------
    theta : ndarray of shape (5,)
        Nominal values in SI (the fixed values of parameters that are not estimated).
    estimated : tuple of str
        Names of estimated parameters, in ``NAMES`` order.
    lower, upper : ndarray of shape (5,)
        Box in theta (physical units).
    eps : ndarray of shape (2,)
        Offsets ``eps1, eps2`` of the damping logarithms (1/s and s).
    """

    theta: np.ndarray
    estimated: tuple = ("E", "nu")
    lower: np.ndarray = field(default_factory=lambda: np.array([DEFAULT_BOUNDS[n][0] for n in NAMES]))
    upper: np.ndarray = field(default_factory=lambda: np.array([DEFAULT_BOUNDS[n][1] for n in NAMES]))
    eps: np.ndarray = field(default_factory=lambda: np.array([1e-3, 1e-6]))

    def __post_init__(self):
        th = np.array(self.theta, float).reshape(-1)
        if th.shape != (5,):
            raise ValueError(f"theta: shape (5,) expected [rho, alpha1, alpha2, E, nu], got {th.shape}")
        lo = np.array(self.lower, float).reshape(5)
        up = np.array(self.upper, float).reshape(5)
        eps = np.array(self.eps, float).reshape(2)
        est = tuple(self.estimated)
        for n in est:
            if n not in NAMES:
                raise ValueError(f"estimate: unknown parameter {n!r}; choose from {NAMES}")
        if len(set(est)) != len(est):
            raise ValueError(f"estimate: repeated parameter in {est}")
        est = tuple(n for n in NAMES if n in est)
        if (eps <= 0).any() or not np.isfinite(eps).all():
            raise ValueError(f"epsilon: alpha offsets must be positive, got {eps}")
        physical_lo = np.array([0.0, -eps[0], -eps[1], 0.0, 0.0])
        for i, n in enumerate(NAMES):
            if not lo[i] < up[i]:
                raise ValueError(f"bounds.{n}: lower < upper required, got [{lo[i]}, {up[i]}]")
            if lo[i] < physical_lo[i] or (n == "nu" and up[i] > 0.5):
                raise ValueError(f"bounds.{n}: outside the physical range, got [{lo[i]}, {up[i]}]")
            if not (lo[i] <= th[i] <= up[i]):
                raise ValueError(f"{n}: value {th[i]} outside its bounds [{lo[i]}, {up[i]}]")
        if th[0] <= 0 or th[3] <= 0:
            raise ValueError("rho and E must be positive")
        if not (0.0 < th[4] < 0.5):
            raise ValueError(f"nu: must lie in (0, 0.5), got {th[4]}")
        for name, val in (("theta", th), ("lower", lo), ("upper", up), ("eps", eps)):
            val.setflags(write=False)
            object.__setattr__(self, name, val)
        object.__setattr__(self, "estimated", est)

    # -- index helpers -------------------------------------------------------------------------
    @property
    def index(self) -> np.ndarray:
        """Indices (into ``NAMES``) of the estimated parameters."""
        return np.array([NAMES.index(n) for n in self.estimated], dtype=int)

    @property
    def dim(self) -> int:
        return len(self.estimated)

    # -- transforms ----------------------------------------------------------------------------
    def to_phi(self, theta):
        """Full theta (..., 5) -> full phi (..., 5)."""
        th = np.asarray(theta, float)
        if th.shape[-1] != 5:
            raise ValueError(f"theta: shape (..., 5) expected, got {th.shape}")
        with np.errstate(divide="ignore"):
            return np.stack(
                [
                    np.log(th[..., 0]),
                    np.log(th[..., 1] + self.eps[0]),
                    np.log(th[..., 2] + self.eps[1]),
                    np.log(th[..., 3]),
                    s_from_nu(th[..., 4]),
                ],
                axis=-1,
            )

    def from_phi(self, phi):
        """Full phi (..., 5) -> full theta (..., 5)."""
        ph = np.asarray(phi, float)
        if ph.shape[-1] != 5:
            raise ValueError(f"phi: shape (..., 5) expected, got {ph.shape}")
        return np.stack(
            [
                np.exp(ph[..., 0]),
                np.exp(ph[..., 1]) - self.eps[0],
                np.exp(ph[..., 2]) - self.eps[1],
                np.exp(ph[..., 3]),
                nu_from_s(ph[..., 4]),
            ],
            axis=-1,
        )

    def dtheta_dphi(self, phi):
        """Diagonal Jacobian d theta / d phi, shape (..., 5)."""
        ph = np.asarray(phi, float)
        e = np.exp(-ph[..., 4])
        return np.stack(
            [np.exp(ph[..., 0]), np.exp(ph[..., 1]), np.exp(ph[..., 2]), np.exp(ph[..., 3]),
             0.5 * e / (1 + e) ** 2],
            axis=-1,
        )

    def theta_from_x(self, x_n):
        """Estimated-subset phi (..., dim) -> full theta (..., 5), fixed parameters at their nominal value."""
        x_n = np.asarray(x_n, float)
        if x_n.shape[-1] != self.dim:
            raise ValueError(f"x_n: shape (..., {self.dim}) expected, got {x_n.shape}")
        phi = np.broadcast_to(self.to_phi(self.theta), x_n.shape[:-1] + (5,)).copy()
        phi[..., self.index] = x_n
        return self.from_phi(phi)

    def x_from_theta(self, theta):
        """Full theta (..., 5) -> estimated-subset phi (..., dim)."""
        return self.to_phi(theta)[..., self.index]

    @property
    def bounds_phi(self) -> tuple[np.ndarray, np.ndarray]:
        """Box of the estimated subset in phi, ``(lower, upper)`` each of shape (dim,)."""
        lo, up = self.to_phi(self.lower), self.to_phi(self.upper)
        return lo[self.index], up[self.index]
