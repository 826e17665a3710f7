"""The undeformed reference configuration as static states of the linear block (issue 15, docs/estimators.md §3.7).

A measured point is ``y_kp = X_p + r(t_k) + H_p x_k + v_kp`` (docs/model.md §7). For points measured by
``heartcv measure`` the undeformed positions ``X_p`` are not observed: ``heartcv fit`` profiles them out and
``heartcv track`` takes the fit's offsets at the fitted constant theta (:func:`tracker.fit.undeformed_references`).
Those offsets are the weighted mean over the fitted frames of ``y_kp - r(t_k) - H_p x_k(theta_fit)``, so when the
true parameters differ from the constant ``theta_fit`` (a stiffness that changes over the heartbeat) every offset
is wrong by ``-H_p (x_bar(theta_fit) - x_bar(theta))``, the position part of the mean model response: an error that
lies in the span of the model's own displacement field at the points. Treated as exact, it is a constant that
the estimated parameters have to explain (in diastole, where the load is small, by a stiffness far from the
truth).

So the estimators carry the reference correction as ``s = r`` static states ``q_ref`` (the model's position
coordinates) after the kinematic state: ``x_l = [q; q_dot; q_ref]``,

    y_kp = X_p + r(t_k) + H_q,p (q_k + q_ref) + v_kp,     q_ref' = q_ref (no process noise),

i.e. ``A' = blkdiag(A(theta), I_r)``, ``B' = [B; 0]``, ``Q' = blkdiag(Q_l, 0)``, ``H' = [H_q, 0, H_q]``. The
transition of ``q_ref`` does not depend on theta, so the model stays conditionally linear and the GE's
Rao-Blackwellised propagation is still exact; the block costs r states (13 on the demo model), not 3 per point.
``q_ref`` is observable because ``q`` follows the input through ``A(theta)`` and its process noise cannot hold a
constant offset, while ``q_ref`` is exactly constant.

The prior of ``q_ref`` is zero-mean (the offsets are right on average) with the standard deviation of each
coordinate the size of the model's static response to the largest input of the sequence at the prior theta,
``|K(theta_0)^-1 F u_max|``, plus the initial position std (noise.initial.position_std): an offset error as large
as the whole static displacement is covered at 1 sigma.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .model import Observation, PatchModel

__all__ = ["ReferenceBlock", "reference_block", "augment_observation", "augment_transition", "MODES"]

MODES = ("fixed", "estimate")
"""``fixed``: the references are exact (model simulate) or taken as exact; ``estimate``: the static block."""


@dataclass(frozen=True)
class ReferenceBlock:
    """The static reference states appended to the kinematic state: ``q_ref = V c``.

    Attributes
    ----------
    basis : ndarray (r, s)  V, the displacement shapes (model position coordinates) the references may be off by
    std : ndarray (s,)      prior standard deviation of each coordinate of c
    """

    basis: np.ndarray
    std: np.ndarray

    @property
    def size(self) -> int:
        """s, the number of static states."""
        return self.basis.shape[1]

    def prior(self, mean_l, cov_l):
        """The kinematic prior ``N(mean_l, cov_l)`` extended by ``c ~ N(0, diag(std^2))`` (uncorrelated)."""
        n = mean_l.size
        mean = np.concatenate([mean_l, np.zeros(self.size)])
        cov = np.zeros((n + self.size, n + self.size))
        cov[:n, :n] = cov_l
        cov[n:, n:] = np.diag(self.std ** 2)
        return mean, cov

    def noise(self, Q_l) -> np.ndarray:
        """``blkdiag(Q_l, 0)``."""
        n = Q_l.shape[0]
        Q = np.zeros((n + self.size, n + self.size))
        Q[:n, :n] = Q_l
        return Q


def reference_block(model: PatchModel, theta, inputs, nus=None) -> ReferenceBlock:
    """The reference block of ``model`` for a sequence with inputs (K, n_u): the static responses
    ``K(theta_j)^-1 F_i u_max,i`` of every input i at the Poisson's ratios ``nus`` (``theta_j`` = theta with
    ``nu = nus[j]``; default: the model's ``reduction.static_nu``, else 0.3, 0.45, 0.49, each kept inside the
    parameter box), ``u_max`` the largest value of each input over the sequence; c of prior std 1 (an error of the
    whole peak static displacement at 1 sigma). Inputs that are never positive add no shape. A model without
    inputs gets an empty block (nothing to be off by)."""
    cfg = model.config
    n_u = model.loads.shape[1]
    u = np.asarray(inputs, float).reshape(-1, n_u) if n_u else np.zeros((1, 0))
    u_max = np.maximum(np.nanmax(u, axis=0), 0.0) if u.size else np.zeros(n_u)
    if nus is None:
        red = cfg.reduction or {}
        nus = red.get("static_nu") or DEFAULT_NUS
    space = cfg.parameter_space()
    lo, up = space.lower[4], space.upper[4]
    cols = []
    for nu in sorted({float(np.clip(v, max(lo, 1e-3), min(up, 0.4999))) for v in nus}):
        th = np.array(theta, float)
        th[4] = nu
        for i in range(n_u):
            if u_max[i] > 0:
                e = np.zeros(n_u)
                e[i] = u_max[i]
                cols.append(model.static_state(th, e)[:model.r])
    V = np.stack(cols, axis=1) if cols else np.zeros((model.r, 0))
    return ReferenceBlock(V, np.ones(V.shape[1]))


DEFAULT_NUS = (0.3, 0.45, 0.49)
"""Poisson's ratios of the reference shapes when the model file has no ``reduction.static_nu``."""


def augment_observation(obs: Observation, block: ReferenceBlock) -> Observation:
    """``H' = [H, H_q V]``: the reference states displace the points by ``H_q V c``."""
    H = np.asarray(obs.H)
    r = block.basis.shape[0]
    return Observation(np.hstack([H, H[:, :r] @ block.basis]), obs.reference, obs.param)
def augment_transition(A, b, size: int):
    """``(blkdiag(A, I_size), [b; 0])`` for one dense transition; A (n, n), b (n,)."""
    n = A.shape[0]
    Ab = np.eye(n + size)
    Ab[:n, :n] = A
    return Ab, np.concatenate([b, np.zeros(size)])
