"""Prediction step of the Rao-Blackwellised Gaussian estimator (GE), docs/spec/estimator.md §2 and §7.2.

The joint state is ``z = [x_n; x_l]``: ``x_n`` the M estimated parameters (in phi coordinates), ``x_l`` the
kinematic state. The model is conditionally linear, ``x_l' = A(x_n) x_l + b(x_n) + w_l``, ``x_n' = x_n + w_n``.
Given deterministic samples ``(theta_i, w_i)`` of the parameter block, the prediction uses the exact Gaussian
conditional of ``x_l`` given ``x_n`` (one shared ``C_l|n``) and the law of total mean and covariance
(spec §2.3; this replaces the seed paper's garbled ``C^p``):

    m_i   = mu_l + K (theta_i - mu_n),   K = C_ln C_nn^{-1},   C_l|n = C_ll - K C_nl
    y_i   = A_i m_i + b_i
    mu'_n = sum w_i theta_i,   mu'_l = sum w_i y_i
    C'_nn = sum w_i (theta_i - mu'_n)(.)^T + Q_n
    C'_ln = sum w_i (y_i - mu'_l)(theta_i - mu'_n)^T
    C'_ll = sum w_i A_i C_l|n A_i^T + sum w_i (y_i - mu'_l)(.)^T + Q_l

The expectation term is evaluated as one SYRK ``W W^T`` with ``W = [sqrt(w_i) A_i R]`` and ``R R^T = C_l|n``
(spec §7.2): PSD by construction and two large BLAS calls instead of 2L small ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.linalg as sla

from .kalman import GaussianState, cholesky_psd, symmetrise

__all__ = ["ConditionalSplit", "conditional_split", "ge_predict", "ge_predict_family"]


@dataclass(frozen=True)
class ConditionalSplit:
    """``x_l | x_n ~ N(mu_l + K (x_n - mu_n), C_l|n)``.

    Attributes
    ----------
    gain_T : ndarray (M, n_l)      K^T = C_nn^{-1} C_nl
    C_cond : ndarray (n_l, n_l)    C_l|n
    R_cond : ndarray (n_l, n_l) or None   lower Cholesky factor of C_l|n (with jitter if needed); None if not asked
    jitter_events : int
    """

    gain_T: np.ndarray
    C_cond: np.ndarray
    R_cond: np.ndarray
    jitter_events: int


def conditional_split(state: GaussianState, n_param: int, factor: bool = True) -> ConditionalSplit:
    """Gaussian conditional of the kinematic block given the parameter block (spec §2.2, two triangular
    solves, never an inverse). ``factor=False`` skips the Cholesky factor of ``C_l|n`` (``R_cond`` is then
    None), which only the dense SYRK path of :func:`ge_predict` needs."""
    C = symmetrise(state.cov)
    M = n_param
    C_nn, C_nl, C_ll = C[:M, :M], C[:M, M:], C[M:, M:]
    L_nn, j1 = cholesky_psd(C_nn)
    gain_T = sla.solve_triangular(L_nn, sla.solve_triangular(L_nn, C_nl, lower=True), lower=True, trans="T")
    C_cond = symmetrise(C_ll - C_nl.T @ gain_T)
    if not factor:
        return ConditionalSplit(gain_T, C_cond, None, j1)
    R, j2 = cholesky_psd(C_cond)
    return ConditionalSplit(gain_T, C_cond, R, j1 + j2)


def ge_predict(prior: GaussianState, n_param: int, nodes, weights,
               transition: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], Q_n, Q_l,
               split: ConditionalSplit | None = None) -> GaussianState:
    """One GE prediction.

    Parameters
    ----------
    prior : GaussianState
        Joint ``z = [x_n; x_l]`` of size ``M + n_l``.
    n_param : int
        M, the size of the parameter block.
    nodes : ndarray (L, M)
        Parameter samples ``theta_i`` (already clipped into the box).
    weights : ndarray (L,)
        Positive weights summing to 1 (variants A and B of spec §1.3).
    transition : callable
        ``transition(nodes) -> (A, b)`` with ``A`` (L, n_l, n_l) and ``b`` (L, n_l): the conditional
        transition and input term ``B(theta_i) u`` of every sample.
    Q_n : ndarray (M, M)
        Random-walk covariance of the parameters.
    Q_l : ndarray (n_l, n_l)
        Additive process noise of the kinematic state.
    split : ConditionalSplit, optional
        Precomputed :func:`conditional_split` of ``prior``.

    Returns
    -------
    GaussianState
        The predicted joint (symmetrised). Equals the Kalman prediction of the joint state when A and b do
        not depend on the parameters.
    """
    M = n_param
    mu = prior.mean
    n = mu.size
    n_l = n - M
    nodes, w = _check_nodes(nodes, weights, M)
    L = w.size
    Q_n = np.asarray(Q_n, float)
    Q_l = np.asarray(Q_l, float)
    if Q_n.shape != (M, M) or Q_l.shape != (n_l, n_l):
        raise ValueError(f"Q_n, Q_l: shapes ({M}, {M}) and ({n_l}, {n_l}) expected, got {Q_n.shape}, {Q_l.shape}")
    split = split if split is not None and split.R_cond is not None else conditional_split(prior, M)
    mu_n, mu_l = mu[:M], mu[M:]
    A, b = transition(nodes)
    A = np.asarray(A, float)
    b = np.asarray(b, float)
    if A.shape != (L, n_l, n_l) or b.shape != (L, n_l):
        raise ValueError(f"transition: A ({L}, {n_l}, {n_l}) and b ({L}, {n_l}) expected, got {A.shape}, {b.shape}")
    m_i = mu_l + (nodes - mu_n) @ split.gain_T  # (L, n_l)
    y = np.einsum("lij,lj->li", A, m_i) + b
    sw = np.sqrt(w)
    U = (A @ split.R_cond) * sw[:, None, None]  # (L, n_l, n_l): sqrt(w_i) A_i R
    Wm = np.concatenate(list(U), axis=1)  # (n_l, L n_l)
    return _assemble(nodes, w, y, Wm @ Wm.T, Q_n, Q_l)


def _check_nodes(nodes, weights, M):
    nodes = np.asarray(nodes, float)
    w = np.asarray(weights, float).reshape(-1)
    if nodes.shape != (w.size, M):
        raise ValueError(f"nodes: shape ({w.size}, {M}) expected, got {nodes.shape}")
    if (w <= 0).any() or abs(w.sum() - 1) > 1e-12:
        raise ValueError("weights: positive and summing to 1 expected (variants A or B)")
    return nodes, w


def _assemble(nodes, w, y, expected_sandwich, Q_n, Q_l) -> GaussianState:
    """Mixture moments of spec §2.3 from the nodes, weights, conditional means ``y_i`` and
    ``sum w_i A_i C_l|n A_i^T``."""
    M = nodes.shape[1]
    n_l = y.shape[1]
    n = M + n_l
    mu_n_p = w @ nodes
    mu_l_p = w @ y
    dth = nodes - mu_n_p
    dy = y - mu_l_p
    Dy = dy * np.sqrt(w)[:, None]
    C_ll = expected_sandwich + Dy.T @ Dy + Q_l
    C_ln = (dy * w[:, None]).T @ dth
    C_nn = (dth * w[:, None]).T @ dth + Q_n
    C = np.empty((n, n))
    C[:M, :M] = C_nn
    C[M:, :M] = C_ln
    C[:M, M:] = C_ln.T
    C[M:, M:] = C_ll
    return GaussianState(np.concatenate([mu_n_p, mu_l_p]), symmetrise(C))


def ge_predict_family(prior: GaussianState, n_param: int, nodes, weights, thetas, family, u0, u1, Q_n, Q_l,
                      split: ConditionalSplit | None = None) -> GaussianState:
    """GE prediction through a :class:`tracker.transition.TransitionFamily` (modal path, spec §7.2 adapted).

    Same result as :func:`ge_predict` with ``transition(nodes) = (A(theta_i), B0(theta_i) u0 + B1(theta_i) u1)``,
    but the conditional means are propagated in modal coordinates and ``sum_i w_i A_i C_l|n A_i^T`` costs one
    modal transform per distinct ``nu`` among the samples instead of two GEMMs per sample.

    Parameters
    ----------
    nodes : ndarray (L, M)     samples of the parameter block (estimator coordinates)
    thetas : ndarray (L, 5)    the same samples as full physical theta
    family : TransitionFamily
    u0, u1 : ndarray (n_u,)    inputs at the start and end of the interval
    """
    M = n_param
    mu = prior.mean
    n_l = mu.size - M
    nodes, w = _check_nodes(nodes, weights, M)
    L = w.size
    split = split or conditional_split(prior, M, factor=False)
    m_i = mu[M:] + (nodes - mu[:M]) @ split.gain_T
    y, sandwich = family.propagate_and_sandwich(thetas, m_i, w, split.C_cond, u0, u1)
    if y.shape != (L, n_l):
        raise ValueError(f"family: states of size {n_l} expected, got {y.shape}")
    return _assemble(nodes, w, y, sandwich, np.asarray(Q_n, float), np.asarray(Q_l, float))
