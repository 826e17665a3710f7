"""The parameters' update when the points' errors are not independent (docs/estimators.md §3.11).

Every update treats the P seen points' measurement errors as independent. Errors that the model does not explain
and that neighbouring points share (on the real heart, neighbouring residuals correlate about 0.7) then count many
times in the directions where all points move together, and that is where a global parameter (a heart rate, a
stiffness) acts: the parameters' update is too confident, their band too narrow, and they chase what they cannot
explain.

The test. Under the filter's own model, the parameter block's shift in an update, ``d = m+_p - m-_p``, has the
covariance ``V = P-_pp - P+_pp`` (the variance the update removed), so ``q = d' V^+ d`` is chi-square with
``rank(V)`` degrees of freedom: ``E q / dof = 1``. Summed over the frames so far, ``sum q`` is chi-square with
``sum dof`` degrees of freedom. Where it exceeds that beyond doubt (its upper tail probability below :data:`ALPHA`),
the over-dispersion of the parameters' score is ``kappa = sum q / sum dof``; otherwise ``kappa = 1`` and nothing
changes (on the rendered phantom ``sum q / sum dof`` is 0.11).

The adjustment ("magnitude adjustment" of a composite likelihood: Pauli, Racugno and Ventura, Statistica Sinica
2011; Ribatet, Cooley and Davison, Statistica Sinica 2012) raises the parameters' likelihood to the power
``1 / kappa``. In the joint Gaussian update the parameters' posterior marginal is their prior times the likelihood
``p(y | parameters)``, so the tempered marginal is the geometric mixture of prior and plain posterior with weights
``1 - 1/kappa`` and ``1/kappa`` (:func:`tempered_marginal`); the rest of the state keeps its conditional on the
parameters from the plain update (:func:`adjusted`). Frame k uses the ``kappa`` of the frames before it (causal).
The points' own estimates, the innovations, the NIS and the log-likelihood are the plain update's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from scipy.stats import chi2

from .kalman import GaussianState

__all__ = ["ALPHA", "Overdispersion", "parameter_nis", "tempered_marginal", "adjusted"]

# The level of the test that the parameters' shifts exceed their predicted spread: strict, so that a filter whose
# model holds is left unchanged (the test repeats every frame: over 10 000 frames at most a 1 % chance of a false
# alarm), while an over-dispersion of 2 or more is found within tens of frames.
ALPHA = 1e-6
# Directions of V below this fraction of its largest eigenvalue carry no information and are left out of q.
_RANK_TOL = 1e-9


def parameter_nis(prior: GaussianState, posterior: GaussianState, M: int) -> tuple[float, int]:
    """``(q, dof)``: the parameter block's shift in one update normalised by the variance the update removed."""
    d = posterior.mean[:M] - prior.mean[:M]
    V = prior.cov[:M, :M] - posterior.cov[:M, :M]
    V = 0.5 * (V + V.T)
    w, U = np.linalg.eigh(V)
    top = float(w.max(initial=0.0))
    if not np.isfinite(top) or top <= 0:
        return 0.0, 0
    ok = w > _RANK_TOL * top
    z = U[:, ok].T @ d
    return float(np.sum(z * z / w[ok])), int(ok.sum())


def tempered_marginal(prior: GaussianState, plain: GaussianState, M: int, kappa: float):
    """Mean and covariance of the parameters' posterior with their likelihood raised to ``1 / kappa``.

    With the prior marginal ``N(m, C)`` and the plain posterior marginal ``N(a, A)`` (= prior x likelihood), the
    likelihood is their ratio, and the tempered posterior has the precision ``(1 - 1/kappa) C^-1 + A^-1 / kappa``
    and the precision-weighted mean ``(1 - 1/kappa) C^-1 m + A^-1 a / kappa``.

    Raises
    ------
    numpy.linalg.LinAlgError
        A marginal covariance that is not positive definite (no adjustment is then possible).
    """
    w = 1.0 / kappa
    m, C = prior.mean[:M], prior.cov[:M, :M]
    a, A = plain.mean[:M], plain.cov[:M, :M]
    Ci = sla.cho_solve(sla.cho_factor(C), np.eye(M))
    Ai = sla.cho_solve(sla.cho_factor(A), np.eye(M))
    precision = (1.0 - w) * Ci + w * Ai
    cov = sla.cho_solve(sla.cho_factor(0.5 * (precision + precision.T)), np.eye(M))
    cov = 0.5 * (cov + cov.T)
    return cov @ ((1.0 - w) * Ci @ m + w * Ai @ a), cov


def adjusted(plain: GaussianState, mean_p, cov_p, M: int) -> GaussianState:
    """The joint state whose parameter marginal is ``N(mean_p, cov_p)`` and whose conditional of the rest given the
    parameters is ``plain``'s.

    With the plain posterior ``[[A, B'], [B, C]]`` (parameters first) and mean ``[a; c]``, the gain of the rest on
    the parameters is ``G = B A^-1``; the marginal ``N(a~, A~)`` then gives the mean ``[a~; c + G (a~ - a)]``
    and the covariance ``[[A~, A~ G'], [G A~, C - G A G' + G A~ G']]``.
    """
    a, c = plain.mean[:M], plain.mean[M:]
    A, B, C = plain.cov[:M, :M], plain.cov[M:, :M], plain.cov[M:, M:]
    At, at = np.asarray(cov_p, float), np.asarray(mean_p, float)
    try:
        G = sla.solve(A, B.T, assume_a="pos").T
    except (np.linalg.LinAlgError, sla.LinAlgError):
        G = np.linalg.lstsq(A, B.T, rcond=None)[0].T
    mean = np.concatenate([at, c + G @ (at - a)])
    GAt = G @ At
    cov = np.empty_like(plain.cov)
    cov[:M, :M] = At
    cov[M:, :M] = GAt
    cov[:M, M:] = GAt.T
    rest = C - G @ B.T + GAt @ G.T
    cov[M:, M:] = 0.5 * (rest + rest.T)
    return GaussianState(mean, cov)


@dataclass
class Overdispersion:
    """The parameters' over-dispersion over the frames so far (module docstring).

    ``fixed``: a given factor (>= 1; 1 is the plain update) instead of the estimate.
    """

    fixed: float | None = None
    q_sum: float = 0.0
    dof_sum: int = 0
    frames_adjusted: int = 0
    _kappa: float = 1.0

    def __post_init__(self):
        if self.fixed is not None and not (np.isfinite(self.fixed) and self.fixed >= 1.0):
            raise ValueError(f"parameter over-dispersion: a factor >= 1 expected, got {self.fixed!r}")

    @property
    def kappa(self) -> float:
        """The factor for the next update."""
        return float(self.fixed) if self.fixed is not None else self._kappa

    def observe(self, prior: GaussianState, plain: GaussianState, M: int) -> None:
        """Add one frame's plain update of the parameter block."""
        q, dof = parameter_nis(prior, plain, M)
        if dof == 0:
            return
        self.q_sum += q
        self.dof_sum += dof
        significant = self.q_sum > self.dof_sum and chi2.sf(self.q_sum, self.dof_sum) < ALPHA
        self._kappa = self.q_sum / self.dof_sum if significant else 1.0

    def summary(self) -> dict:
        return {"mode": "estimated" if self.fixed is None else "fixed", "kappa_final": self.kappa,
                "nis_per_dof": self.q_sum / self.dof_sum if self.dof_sum else None, "dof": self.dof_sum,
                "frames_adjusted": self.frames_adjusted, "alpha": ALPHA if self.fixed is None else None}
