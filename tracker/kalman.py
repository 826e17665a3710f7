"""Linear Kalman prediction and measurement update on frozen Gaussian states (docs/spec/estimator.md §4, normative).

``predict(prior, A, Q, b)`` and ``update(prediction, y, H, R, offset)`` are pure functions on :class:`GaussianState`
values (Stone Soup split). The update is the Cholesky form of §4: ``S = H C H^T + R``, ``L_S = chol(S)``,
``W = C H^T L_S^{-T}``, ``ebar = L_S^{-1} e``, ``mu+ = mu + W ebar``, ``C+ = C - W W^T`` (or Joseph),
``NIS = ebar^T ebar``. No matrix is ever inverted.

References: D. Simon, *Optimal State Estimation*, Wiley 2006, ch. 5 (Kalman filter, Joseph form).
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
from scipy.linalg import solve_triangular

__all__ = ["GaussianState", "UpdateResult", "symmetrise", "cholesky_psd", "predict", "update"]

_SYM_RTOL = 1e-9


def _as_array(name, value, shape, *, allow_nan=False):
    """Copy ``value`` to a read-only float64 array; check its shape (str entries are free symbols) and finiteness."""
    a = np.array(value, dtype=np.float64, copy=True)
    if a.ndim != len(shape) or any(isinstance(s, int) and s != d for s, d in zip(shape, a.shape)):
        want = "(" + ", ".join(str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ValueError(f"{name}: expected shape {want}, got {a.shape}")
    bad = ~np.isfinite(a)
    if allow_nan:
        bad &= ~np.isnan(a)
    if bad.any():
        raise ValueError(f"{name}: non-finite values ({int(bad.sum())} entries{', NaN allowed' if allow_nan else ''})")
    a.setflags(write=False)
    return a


def _check_symmetric(name, a):
    scale = float(np.max(np.abs(a))) if a.size else 0.0
    asym = float(np.max(np.abs(a - a.T))) if a.size else 0.0
    if asym > _SYM_RTOL * scale:
        raise ValueError(f"{name}: not symmetric (max |C - C^T| = {asym:.3g} > {_SYM_RTOL:g} * max |C| = {scale:.3g})")


def _frozen(a):
    a = np.asarray(a)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class GaussianState:
    """Gaussian density N(mu, C) of an n-dimensional state; an immutable value.

    Parameters
    ----------
    mean : array_like of shape (n,)
        Mean mu. Copied to a read-only float64 array.
    cov : array_like of shape (n, n)
        Covariance C, symmetric to 1e-9 relative (stored as given, not symmetrised). A wrong shape,
        non-finite values or an asymmetric covariance raise ValueError.
    """

    mean: np.ndarray
    cov: np.ndarray

    def __post_init__(self):
        mean = _as_array("GaussianState.mean", self.mean, ("n",))
        if mean.shape[0] < 1:
            raise ValueError("GaussianState.mean: expected shape (n,) with n >= 1, got (0,)")
        n = mean.shape[0]
        cov = _as_array("GaussianState.cov", self.cov, (n, n))
        _check_symmetric("GaussianState.cov", cov)
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "cov", cov)


@dataclass(frozen=True)
class UpdateResult:
    """Outcome of one measurement update (:func:`update`).

    Attributes
    ----------
    state : GaussianState
        Posterior N(mu+, C+); the prediction itself when no measurement row was finite.
    innovation : ndarray of shape (m_used,)
        e = y - offset - H mu over the rows used.
    innovation_cov : ndarray of shape (m_used, m_used)
        S = H C H^T + R (symmetrised; including any jitter added to factor it, so S = L_S L_S^T).
    nis : float
        Normalised innovation squared e^T S^{-1} e (chi-square with ``dof`` degrees of freedom); NaN if no row used.
    dof : int
        m_used, the number of measurement rows used.
    used : ndarray of shape (m,), bool
        Rows of y that were finite and used.
    jitter_events : int
        Jitter additions in this update (factoring S, then the PD check of C+).
    innovation_chol : ndarray of shape (m_used, m_used) or None
        Lower Cholesky factor L_S of S, kept for :attr:`log_likelihood` and gating.
    """

    state: GaussianState
    innovation: np.ndarray
    innovation_cov: np.ndarray
    nis: float
    dof: int
    used: np.ndarray
    jitter_events: int
    innovation_chol: np.ndarray | None = None

    @property
    def log_likelihood(self) -> float:
        """log N(e; 0, S) = -(NIS + log det S + m_used log 2 pi) / 2, from L_S; 0.0 when no row was used."""
        if self.dof == 0:
            return 0.0
        L = self.innovation_chol if self.innovation_chol is not None else np.linalg.cholesky(self.innovation_cov)
        log_det = 2.0 * float(np.sum(np.log(np.diag(L))))
        return -0.5 * (self.nis + log_det + self.dof * math.log(2.0 * math.pi))


def symmetrise(C) -> np.ndarray:
    """Return (C + C^T) / 2 for C of shape (n, n): exactly symmetric, a new float64 array."""
    C = np.asarray(C, dtype=np.float64)
    if C.ndim != 2 or C.shape[0] != C.shape[1]:
        raise ValueError(f"symmetrise: expected shape (n, n), got {C.shape}")
    return 0.5 * (C + C.T)


def _cholesky_jitter(C, max_tries, what="cholesky_psd"):
    """Lower factor of C or of C + delta I, delta = 1e-12 * 10^k * trace(C)/n; returns (L, events, delta)."""
    try:
        return np.linalg.cholesky(C), 0, 0.0
    except np.linalg.LinAlgError:
        pass
    n = C.shape[0]
    trace = float(np.trace(C))
    scale = trace / n if trace > 0 else 1.0  # a zero matrix is PSD; give it an absolute jitter
    delta = 0.0
    for k in range(max_tries):
        delta = 1e-12 * 10.0**k * scale
        try:
            return np.linalg.cholesky(C + delta * np.eye(n)), k + 1, delta
        except np.linalg.LinAlgError:
            continue
    raise np.linalg.LinAlgError(
        f"{what}: matrix of shape {C.shape} is not positive semi-definite: Cholesky failed even with "
        f"{max_tries} jitter additions (largest delta = {delta:.3g} * I, trace/n = {trace / n:.3g})"
    )


def cholesky_psd(C, *, max_tries=6) -> tuple[np.ndarray, int]:
    """Lower Cholesky factor of a symmetric PSD matrix, adding diagonal jitter when it is (numerically) singular.

    After a plain attempt, try k = 0..max_tries-1 factors C + delta_k I, delta_k = 1e-12 * 10^k * trace(C)/n (spec §4).

    Parameters
    ----------
    C : array_like of shape (n, n)
        Symmetric matrix (only its lower triangle is read).
    max_tries : int
        Jitter attempts after the plain factorisation.

    Returns
    -------
    L : ndarray of shape (n, n)
        Lower triangular with L L^T = C + delta I.
    jitter_events : int
        Number of jitter additions made (0 when C factored as is).

    Raises
    ------
    numpy.linalg.LinAlgError
        When every attempt fails (C is not PSD).
    """
    C = np.asarray(C, dtype=np.float64)
    if C.ndim != 2 or C.shape[0] != C.shape[1] or C.shape[0] == 0:
        raise ValueError(f"cholesky_psd: expected shape (n, n) with n >= 1, got {C.shape}")
    if not np.isfinite(C).all():
        raise ValueError("cholesky_psd: non-finite values in C")
    L, events, _ = _cholesky_jitter(C, int(max_tries))
    return L, events


def predict(prior: GaussianState, A, Q, b=None) -> GaussianState:
    """Kalman prediction x' = A x + b + w, w ~ N(0, Q).

    Parameters
    ----------
    prior : GaussianState
        N(mu, C) of dimension n.
    A : array_like of shape (n, n)
        Transition matrix.
    Q : array_like of shape (n, n)
        Process noise covariance (symmetric).
    b : array_like of shape (n,), optional
        Known additive term (e.g. B u).

    Returns
    -------
    GaussianState
        N(A mu + b, sym(A C A^T + Q)).
    """
    if not isinstance(prior, GaussianState):
        raise TypeError(f"predict: prior must be a GaussianState, got {type(prior).__name__}")
    n = prior.mean.shape[0]
    A = _as_array("predict: A", A, (n, n))
    Q = _as_array("predict: Q", Q, (n, n))
    _check_symmetric("predict: Q", Q)
    mean = A @ prior.mean
    if b is not None:
        mean = mean + _as_array("predict: b", b, (n,))
    return GaussianState(mean, symmetrise(A @ prior.cov @ A.T + Q))


def update(prediction: GaussianState, y, H, R, offset=None, *, joseph=False) -> UpdateResult:
    """Kalman measurement update for y = offset + H x + v, v ~ N(0, R), in the Cholesky form of spec §4.

    NaN entries of y are missing: those rows of y, H, offset and rows/columns of R are dropped for this step.

    Parameters
    ----------
    prediction : GaussianState
        N(mu, C) of dimension n.
    y : array_like of shape (m,)
        Measurement; NaN marks a missing entry (inf is an error).
    H : array_like of shape (m, n)
        Measurement matrix.
    R : array_like of shape (m, m) or (m,)
        Measurement noise covariance, or its diagonal (variances >= 0).
    offset : array_like of shape (m,), optional
        Known additive term of the measurement.
    joseph : bool
        Use C+ = (I - K H) C (I - K H)^T + K R K^T (product form, K = W L_S^{-1}) instead of C - W W^T.

    Returns
    -------
    UpdateResult
        Posterior, innovation e, S, NIS, dof, used rows, jitter events. After the update C+ is symmetrised and
        factored as a PD check; on failure the jitter of :func:`cholesky_psd` is added to C+ and counted.
    """
    if not isinstance(prediction, GaussianState):
        raise TypeError(f"update: prediction must be a GaussianState, got {type(prediction).__name__}")
    n = prediction.mean.shape[0]
    y = _as_array("update: y", y, ("m",), allow_nan=True)
    m = y.shape[0]
    H = _as_array("update: H", H, (m, n))
    R = np.asarray(R, dtype=np.float64)
    if R.shape == (m,):
        R = _as_array("update: R (diagonal)", R, (m,))
        if (R < 0).any():
            raise ValueError("update: R (diagonal) must hold variances >= 0")
        R = np.diag(R)
    elif R.shape == (m, m):
        R = _as_array("update: R", R, (m, m))
        _check_symmetric("update: R", R)
    else:
        raise ValueError(f"update: R: expected shape ({m}, {m}) or ({m},), got {R.shape}")
    offset = np.zeros(m) if offset is None else _as_array("update: offset", offset, (m,))

    used = np.isfinite(y)
    used.setflags(write=False)
    if not used.any():
        return UpdateResult(prediction, _frozen(np.empty(0)), _frozen(np.empty((0, 0))), math.nan, 0, used, 0,
                            _frozen(np.empty((0, 0))))
    H_u, R_u = H[used], R[np.ix_(used, used)]
    mu, C = prediction.mean, prediction.cov

    e = y[used] - offset[used] - H_u @ mu
    P_zy = C @ H_u.T                                       # (n, m_used)
    S = symmetrise(H_u @ P_zy + R_u)
    L_S, events, delta = _cholesky_jitter(S, 6, "update: S")
    if events:
        S = S + delta * np.eye(S.shape[0])
    W = solve_triangular(L_S, P_zy.T, lower=True, check_finite=False).T    # P_zy L_S^{-T}
    ebar = solve_triangular(L_S, e, lower=True, check_finite=False)
    mean = mu + W @ ebar
    if joseph:
        # Product form: a sum of two PSD terms, robust to a rounded gain (Simon 2006, ch. 5).
        K = solve_triangular(L_S, W.T, lower=True, trans="T", check_finite=False).T   # W L_S^{-1}
        I_KH = np.eye(n) - K @ H_u
        cov = symmetrise(I_KH @ C @ I_KH.T + K @ R_u @ K.T)
    else:
        cov = symmetrise(C - W @ W.T)
    _, post_events, post_delta = _cholesky_jitter(cov, 6, "update: C+")  # PD check of C+ (spec §4, after every step)
    if post_events:
        cov = cov + post_delta * np.eye(n)
    return UpdateResult(GaussianState(mean, cov), _frozen(e), _frozen(S), float(ebar @ ebar), int(used.sum()), used,
                        events + post_events, _frozen(L_S))
