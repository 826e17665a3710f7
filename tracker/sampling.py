"""Deterministic Dirac-mixture sampling of the parameter block x^n = theta (docs/spec/estimator.md §1, normative).

A standard normal is replaced by the ``D`` equally weighted Cramer-von Mises optimal positions
``u_k = Phi^{-1}((2k-1)/(2D))`` (§1.1). The positions are rescaled by ``1/s_D`` so that their variance is one, laid
along the columns ``s_j`` of a square root ``S`` of ``C_nn`` around a shared centre (§1.2), and weighted by one of
three variants (§1.3):

- ``'A'`` (normative default): equal weights ``1/L``, spread ``c_A = sqrt(L / (D s_D^2))``;
- ``'B'``: centre weight ``1/D``, other weights ``1/(M D)``, spread ``c_B = sqrt(M) / s_D``;
- ``'U'``: axis-wise ("univariate dimension reduction"), nodes ``mu_n +- (u_k/s_D) s_j``, no spreading; not a
  probability mixture, moments by the axis-wise formulas of §1.3 (:func:`moments`, :func:`cross_moment`).

A and B reproduce the mean and covariance of N(mu_n, C_nn) exactly; U does so for linear maps, and for any function
additive in the standardised coordinates ``z = S^{-1} (theta - mu_n)`` it equals the D^M-point tensor-product rule.
Nodes may be clipped into a box (§1.4).

References: M. F. Huber and U. D. Hanebeck, "Gaussian filter based on deterministic sampling for high quality
nonlinear estimation", IFAC World Congress 2008 (not available to us; the rule is reconstructed in spec §1.1/§1.5).
"""

from __future__ import annotations

from dataclasses import dataclass
import numbers

import numpy as np
from scipy.special import ndtri

__all__ = ["SampleSet", "cvm_nodes", "cvm_variance", "sample", "moments", "cross_moment"]

VARIANTS = ("A", "B", "U")
SQRT_CHOICES = ("correlation", "eigen", "cholesky")
CLIP_REL_EPS = 1e-6  # eps_j = 1e-6 (b_j - a_j), spec §1.4
_SYM_RTOL = 1e-9


def _check_D(D, minimum=1):
    if isinstance(D, bool) or not isinstance(D, numbers.Integral):
        raise ValueError(f"D: expected an integer >= {minimum}, got {D!r}")
    D = int(D)
    if D < minimum:
        raise ValueError(f"D: expected an integer >= {minimum}, got {D}")
    return D


def cvm_nodes(D: int) -> np.ndarray:
    """Cramer-von Mises optimal equal-weight positions of a standard normal (spec §1.1).

    ``u_k = Phi^{-1}((2k-1)/(2D)) = sqrt(2) erfinv((2k-1-D)/D)``, k = 1..D: the minimiser of
    ``integral w(t) (Phi(t) - Ftilde(t))^2 dt`` over D equally weighted Diracs, for any positive weight ``w``.

    Parameters
    ----------
    D : int
        Number of positions, D >= 1.

    Returns
    -------
    u : ndarray of shape (D,)
        Sorted positions u_1 < ... < u_D, exactly antisymmetric (``u[::-1] == -u``); the middle one is exactly 0
        for odd D.
    """
    D = _check_D(D)
    k = np.arange(1, D + 1, dtype=np.float64)
    u = ndtri((2.0 * k - 1.0) / (2.0 * D))
    return 0.5 * (u - u[::-1])  # enforce the exact symmetry of the rule (and u = 0 in the middle)


def cvm_variance(D: int) -> float:
    """Variance ``s_D^2 = (1/D) sum_k u_k^2 < 1`` of the D-point rule :func:`cvm_nodes` (spec §1.1)."""
    u = cvm_nodes(D)
    return float(np.mean(u * u))


def _frozen(a):
    a = np.array(a, dtype=np.float64, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class SampleSet:
    """Deterministic sample set of N(mu_n, C_nn) for the parameter block (spec §1.2-§1.4); an immutable value.

    Node order: the shared centre first, then axis j = 1..M, each with its D-1 non-zero nodes in increasing u order,
    so that ``L = M (D - 1) + 1`` and axis j occupies rows ``1 + (j-1)(D-1) .. j (D-1)``.

    Attributes
    ----------
    nodes : ndarray of shape (L, M)
        Parameter samples theta_i, after clipping into the box (the set actually used).
    weights : ndarray of shape (L,)
        Weights w_i, summing to 1. Variants A/B: a probability measure. Variant U: the effective weights of its
        mean rule (centre ``1 - M + M/D``, negative for M >= 2; others ``1/D``); its covariances are axis-wise,
        not weighted sums, so use :func:`moments` / :func:`cross_moment`.
    variant : str
        'A', 'B' or 'U' (spec §1.3).
    D : int
        Nodes per axis, odd and >= 3 (centre included).
    axes : ndarray of shape (M, M)
        Square root S of C_nn used, columns s_j, ``S S^T = C_nn``.
    coeff : ndarray of shape (L, M)
        Standardised offsets before clipping: ``theta_i = mu_n + S coeff[i]`` (row i of ``coeff`` is
        ``c u_k e_j`` for the node k of axis j, zero for the centre; c = c_A, c_B or 1/s_D).
    clipped : int
        Number of node coordinates moved by clipping (0 without a box).
    """

    nodes: np.ndarray
    weights: np.ndarray
    variant: str
    D: int
    axes: np.ndarray
    coeff: np.ndarray
    clipped: int = 0

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"SampleSet.variant: expected one of {VARIANTS}, got {self.variant!r}")
        D = _check_D(self.D, 3)
        if D % 2 == 0:
            raise ValueError(f"SampleSet.D: D must be odd and >= 3, got {D}")
        nodes = _frozen(self.nodes)
        if nodes.ndim != 2 or nodes.shape[1] < 1:
            raise ValueError(f"SampleSet.nodes: expected shape (L, M) with M >= 1, got {nodes.shape}")
        L, M = nodes.shape
        if L != M * (D - 1) + 1:
            raise ValueError(f"SampleSet.nodes: expected L = M (D - 1) + 1 = {M * (D - 1) + 1} rows, got {L}")
        weights, axes, coeff = _frozen(self.weights), _frozen(self.axes), _frozen(self.coeff)
        for name, a, shape in (("weights", weights, (L,)), ("axes", axes, (M, M)), ("coeff", coeff, (L, M))):
            if a.shape != shape:
                raise ValueError(f"SampleSet.{name}: expected shape {shape}, got {a.shape}")
        for name, a in (("nodes", nodes), ("weights", weights), ("axes", axes), ("coeff", coeff)):
            if not np.isfinite(a).all():
                raise ValueError(f"SampleSet.{name}: non-finite values")
        if isinstance(self.clipped, bool) or not isinstance(self.clipped, numbers.Integral) or self.clipped < 0:
            raise ValueError(f"SampleSet.clipped: expected an integer >= 0, got {self.clipped!r}")
        object.__setattr__(self, "D", D)
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "weights", weights)
        object.__setattr__(self, "axes", axes)
        object.__setattr__(self, "coeff", coeff)
        object.__setattr__(self, "clipped", int(self.clipped))

    @property
    def L(self) -> int:
        """Number of samples, M (D - 1) + 1."""
        return self.nodes.shape[0]

    @property
    def M(self) -> int:
        """Dimension of the parameter block."""
        return self.nodes.shape[1]


def _check_mean_cov(mean, cov):
    mu = np.array(mean, dtype=np.float64, copy=True)
    if mu.ndim != 1 or mu.shape[0] < 1:
        raise ValueError(f"mean: expected shape (M,) with M >= 1, got {mu.shape}")
    if not np.isfinite(mu).all():
        raise ValueError("mean: non-finite values")
    M = mu.shape[0]
    C = np.array(cov, dtype=np.float64, copy=True)
    if C.shape != (M, M):
        raise ValueError(f"cov: expected shape ({M}, {M}) to match mean, got {C.shape}")
    if not np.isfinite(C).all():
        raise ValueError("cov: non-finite values")
    scale = float(np.max(np.abs(C)))
    asym = float(np.max(np.abs(C - C.T)))
    if asym > _SYM_RTOL * scale:
        raise ValueError(f"cov: not symmetric (max |C - C^T| = {asym:.3g} > {_SYM_RTOL:g} * max |C| = {scale:.3g})")
    C = 0.5 * (C + C.T)
    if np.any(np.diag(C) <= 0.0):
        raise ValueError("cov: not positive definite (expected a diagonal > 0)")
    try:
        np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        raise ValueError("cov: not positive definite (Cholesky factorisation failed)") from None
    return mu, C


def _orient(V, lam):
    """Sort eigenpairs by decreasing eigenvalue and make each column's largest-magnitude entry positive."""
    order = np.argsort(lam)[::-1]
    lam, V = lam[order], V[:, order]
    signs = np.sign(V[np.argmax(np.abs(V), axis=0), np.arange(V.shape[1])])
    return V * signs, lam


def _square_root(C, sqrt):
    """Square root S with S S^T = C (spec §1.2); columns ordered by decreasing eigenvalue for the eigen choices."""
    if sqrt == "cholesky":
        return np.linalg.cholesky(C)
    if sqrt == "eigen":
        lam, V = np.linalg.eigh(C)
        V, lam = _orient(V, lam)
        if lam[-1] <= 0.0:
            raise ValueError(f"cov: not positive definite (smallest eigenvalue {lam[-1]:.3g})")
        return V * np.sqrt(lam)
    if sqrt == "correlation":
        d = np.sqrt(np.diag(C))
        R = C / np.outer(d, d)
        lam, V = np.linalg.eigh(0.5 * (R + R.T))
        V, lam = _orient(V, lam)
        if lam[-1] <= 0.0:
            raise ValueError(f"cov: not positive definite (smallest correlation eigenvalue {lam[-1]:.3g})")
        return d[:, None] * (V * np.sqrt(lam))
    raise ValueError(f"sqrt: expected one of {SQRT_CHOICES}, got {sqrt!r}")


def _bound(name, value, M, fill):
    if value is None:
        return np.full(M, fill)
    b = np.array(value, dtype=np.float64, copy=True)
    if b.ndim == 0:
        b = np.full(M, float(b))
    if b.shape != (M,):
        raise ValueError(f"{name}: expected shape ({M},) (may contain +-inf), got {b.shape}")
    if np.isnan(b).any():
        raise ValueError(f"{name}: NaN values (use +-inf for an open side)")
    return b


def _clip(nodes, lower, upper):
    """Clip nodes into [a + eps, b - eps], eps_j = 1e-6 (b_j - a_j) (0 for an infinite width); spec §1.4."""
    M = nodes.shape[1]
    a = _bound("lower", lower, M, -np.inf)
    b = _bound("upper", upper, M, np.inf)
    if np.any(a >= b) or np.any(a == np.inf) or np.any(b == -np.inf):
        raise ValueError(f"lower/upper: expected lower < upper elementwise, got lower={a}, upper={b}")
    width = b - a
    eps = np.where(np.isfinite(width), CLIP_REL_EPS * width, 0.0)
    lo, hi = a + eps, b - eps
    clipped_nodes = np.clip(nodes, lo, hi)
    return clipped_nodes, int(np.count_nonzero(clipped_nodes != nodes))


def sample(mean, cov, D=5, variant="A", sqrt="correlation", lower=None, upper=None) -> SampleSet:
    """Deterministic Dirac-mixture samples of N(mu_n, C_nn) along the axes of a square root (spec §1.2-§1.4).

    ``theta_0 = mu_n`` (shared centre) and ``theta_{j,k} = mu_n + c u_k s_j`` for j = 1..M and the D-1 non-zero
    positions u_k of :func:`cvm_nodes`, so ``L = M (D - 1) + 1``. Spread and weights by variant (§1.3):

    ======= ========================== ================================================
    variant c                          weights
    ======= ========================== ================================================
    'A'     sqrt(L / (D s_D^2))        1/L everywhere
    'B'     sqrt(M) / s_D              centre 1/D, others 1/(M D)
    'U'     1 / s_D                    axis-wise rule; stored weights: centre 1 - M + M/D, others 1/D
    ======= ========================== ================================================

    Parameters
    ----------
    mean : array_like of shape (M,)
        Mean mu_n of the parameter block.
    cov : array_like of shape (M, M)
        Covariance C_nn, symmetric (to 1e-9 relative) positive definite.
    D : int
        Nodes per axis including the centre; odd and >= 3.
    variant : {'A', 'B', 'U'}
        Weighting variant of §1.3.
    sqrt : {'correlation', 'eigen', 'cholesky'}
        Square root S of C_nn: 'correlation' (default, §1.2) ``S = diag(d) V diag(sqrt(lambda))`` with
        ``R = C_nn ./ (d d^T) = V diag(lambda) V^T``, ``d = sqrt(diag C_nn)``; 'eigen' the principal axes
        ``S = V diag(sqrt(lambda))`` of C_nn; 'cholesky' the lower Cholesky factor. Eigen columns are ordered by
        decreasing eigenvalue with the largest-magnitude entry of each eigenvector positive.
    lower, upper : array_like of shape (M,), optional
        Box [a, b] (entries may be -inf / +inf). Every node is clipped into ``[a + eps_j, b - eps_j]``,
        ``eps_j = 1e-6 (b_j - a_j)`` (0 for an infinite width), and the clipped nodes are returned (§1.4).

    Returns
    -------
    SampleSet
        Nodes (L, M), weights (L,), the square root and standardised offsets used, and the clip count.

    Raises
    ------
    ValueError
        For D not odd and >= 3, an unknown variant or sqrt, wrong shapes, non-finite values, a covariance that is
        not symmetric positive definite, or a box with lower >= upper.
    """
    D = _check_D(D)
    if D < 3 or D % 2 == 0:
        raise ValueError(f"D must be odd and >= 3 (the variants share a centre node), got D = {D}")
    if variant not in VARIANTS:
        raise ValueError(f"variant: expected one of {VARIANTS}, got {variant!r}")
    if sqrt not in SQRT_CHOICES:
        raise ValueError(f"sqrt: expected one of {SQRT_CHOICES}, got {sqrt!r}")
    mu, C = _check_mean_cov(mean, cov)
    M = mu.shape[0]
    L = M * (D - 1) + 1
    S = _square_root(C, sqrt)

    u = cvm_nodes(D)
    u_nonzero = np.delete(u, D // 2)  # increasing, the centre removed
    s2 = cvm_variance(D)
    if variant == "A":
        c = np.sqrt(L / (D * s2))
        weights = np.full(L, 1.0 / L)
    elif variant == "B":
        c = np.sqrt(M / s2)
        weights = np.full(L, 1.0 / (M * D))
        weights[0] = 1.0 / D
    else:
        c = 1.0 / np.sqrt(s2)
        weights = np.full(L, 1.0 / D)
        weights[0] = 1.0 - M + M / D

    coeff = np.zeros((L, M))
    for j in range(M):
        coeff[1 + j * (D - 1): 1 + (j + 1) * (D - 1), j] = c * u_nonzero
    nodes = mu + coeff @ S.T
    nodes[0] = mu  # the centre exactly
    clipped = 0
    if lower is not None or upper is not None:
        nodes, clipped = _clip(nodes, lower, upper)
    return SampleSet(nodes=nodes, weights=weights, variant=variant, D=D, axes=S, coeff=coeff, clipped=clipped)


def _check_values(samples, values):
    if not isinstance(samples, SampleSet):
        raise ValueError(f"samples: expected a SampleSet, got {type(samples).__name__}")
    F = np.asarray(values, dtype=np.float64)
    if F.ndim == 1:
        F = F[:, None]
    if F.ndim != 2 or F.shape[0] != samples.L:
        raise ValueError(f"values: expected shape ({samples.L}, p) or ({samples.L},), got {np.shape(values)}")
    if not np.isfinite(F).all():
        raise ValueError("values: non-finite values")
    return F


def _axis_blocks(samples, A):
    """Per-axis node blocks (M, D, q) of rows of A (L, q): the centre row then that axis' D-1 rows."""
    M, D = samples.M, samples.D
    blocks = A[1:].reshape(M, D - 1, A.shape[1])
    centre = np.broadcast_to(A[0], (M, 1, A.shape[1]))
    return np.concatenate([centre, blocks], axis=1)


def moments(samples: SampleSet, values) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of f(theta) from its values at the sample nodes (spec §1.3).

    Variants A/B: ``E[f] = sum_i w_i f_i``, ``Cov[f] = sum_i w_i (f_i - E[f])(f_i - E[f])^T``.
    Variant U (axis-wise, over the D nodes of axis j including the centre):
    ``fbar_j = (1/D) sum_k f_{j,k}``, ``E[f] = f(mu_n) + sum_j (fbar_j - f(mu_n))``,
    ``Cov[f] = sum_j (1/D) sum_k (f_{j,k} - fbar_j)(f_{j,k} - fbar_j)^T``.

    Parameters
    ----------
    samples : SampleSet
        The sample set the values were computed at (L nodes, dimension M).
    values : array_like of shape (L, p) or (L,)
        f_i = f(theta_i) in node order (a 1-D array is one output, p = 1).

    Returns
    -------
    mean : ndarray of shape (p,)
        Estimate of E[f].
    cov : ndarray of shape (p, p)
        Estimate of Cov[f], exactly symmetric.
    """
    F = _check_values(samples, values)
    if samples.variant == "U":
        blocks = _axis_blocks(samples, F)  # (M, D, p)
        fbar = blocks.mean(axis=1)  # (M, p)
        mean = F[0] + np.sum(fbar - F[0], axis=0)
        dev = blocks - fbar[:, None, :]
        cov = np.einsum("jkp,jkq->pq", dev, dev) / samples.D
    else:
        w = samples.weights
        mean = w @ F
        dev = F - mean
        cov = (dev * w[:, None]).T @ dev
    return mean, 0.5 * (cov + cov.T)


def cross_moment(samples: SampleSet, values) -> np.ndarray:
    """Cross-covariance Cov[f(theta), theta] from values at the sample nodes (spec §1.3).

    Variants A/B: ``sum_i w_i (f_i - fbar)(theta_i - thetabar)^T`` with the weighted means fbar and thetabar.
    Variant U: ``sum_j (1/D) sum_k (f_{j,k} - fbar_j)(theta_{j,k} - thetabar_j)^T``, which without clipping equals
    the spec's ``sum_j (1/D) sum_k f_{j,k} (u_k/s_D) s_j^T``. The (clipped) nodes of ``samples`` are used.

    Parameters
    ----------
    samples : SampleSet
        The sample set the values were computed at (L nodes, dimension M).
    values : array_like of shape (L, p) or (L,)
        f_i = f(theta_i) in node order.

    Returns
    -------
    ndarray of shape (p, M)
        Estimate of Cov[f, theta].
    """
    F = _check_values(samples, values)
    X = samples.nodes
    if samples.variant == "U":
        Fb, Xb = _axis_blocks(samples, F), _axis_blocks(samples, X)
        dF = Fb - Fb.mean(axis=1, keepdims=True)
        dX = Xb - Xb.mean(axis=1, keepdims=True)
        return np.einsum("jkp,jkm->pm", dF, dX) / samples.D
    w = samples.weights
    dF = F - w @ F
    dX = X - w @ X
    return (dF * w[:, None]).T @ dX
