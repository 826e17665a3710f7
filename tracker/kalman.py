"""Linear Kalman prediction and measurement update on frozen Gaussian states (docs/spec/estimator.md §4, normative).

``predict(prior, A, Q, b)`` and ``update(prediction, y, H, R, offset)`` are pure functions on :class:`GaussianState`
values (Stone Soup split). The update is the Cholesky form of §4: ``S = H C H^T + R``, ``L_S = chol(S)``,
``W = C H^T L_S^{-T}``, ``ebar = L_S^{-1} e``, ``mu+ = mu + W ebar``, ``C+ = C - W W^T`` (or Joseph),
``NIS = ebar^T ebar``. No matrix is ever inverted.

``update_blocks(prediction, y, H, R_blocks, offset)`` is the same update for a measurement noise that is block
diagonal (one small block per tracked point) and many more rows than states, in the low-rank (Woodbury) form: it
never forms the m x m ``S``, so it costs O(m n^2) instead of O(m^3) (thousands of points per frame; docs/estimators.md
§3.10).

References: D. Simon, *Optimal State Estimation*, Wiley 2006, ch. 5 (Kalman filter, Joseph form).
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
from scipy.linalg import solve_triangular

__all__ = ["GaussianState", "UpdateResult", "BlockInnovation", "symmetrise", "cholesky_psd", "predict", "update",
           "update_blocks"]

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


def _whiten(L_R, v) -> np.ndarray:
    """L_R^{-1} v block by block (L_R of shape (p, b, b)) for v of shape (p b,) or (p b, k)."""
    p, b = L_R.shape[:2]
    v = np.asarray(v, float)
    return np.linalg.solve(L_R, v.reshape(p, b, -1)).reshape(v.shape)


class BlockInnovation:
    """The innovation covariance ``S = R + H C H^T`` of :func:`update_blocks`, held factored: ``R = L_R L_R^T`` block
    by block (p blocks of b x b), ``F = L_R^{-1} H L_C`` (m x r, ``C = L_C L_C^T``) and ``I + F^T F = L_A L_A^T``.
    Then ``S = L_R (I + F F^T) L_R^T`` and, by the Woodbury identity,
    ``S^{-1} = L_R^{-T} (I - F (I + F^T F)^{-1} F^T) L_R^{-1}``: every quantity below costs O(m r^2), never O(m^3).
    """

    def __init__(self, L_R, F, L_A):
        self.L_R = _frozen(L_R)
        self.F = _frozen(F)
        self.L_A = _frozen(L_A)

    @property
    def blocks(self) -> tuple[int, int]:
        """(p, b): the number of blocks and their size."""
        return self.L_R.shape[0], self.L_R.shape[1]

    @property
    def log_det(self) -> float:
        """log det S = log det R + log det (I + F^T F)."""
        return 2.0 * float(np.sum(np.log(np.diagonal(self.L_R, axis1=1, axis2=2)))
                           + np.sum(np.log(np.diag(self.L_A))))

    def whiten(self, v) -> np.ndarray:
        """L_R^{-1} v for v of shape (m,) or (m, k)."""
        return _whiten(self.L_R, v)

    def solve(self, v) -> np.ndarray:
        """S^{-1} v for v of shape (m,)."""
        p, b = self.blocks
        w = self.whiten(v)
        g = solve_triangular(self.L_A, self.F.T @ w, lower=True, check_finite=False)
        w = w - self.F @ solve_triangular(self.L_A, g, lower=True, trans="T", check_finite=False)
        return np.linalg.solve(np.swapaxes(self.L_R, 1, 2), w.reshape(p, b, 1)).reshape(-1)

    def inverse_blocks(self) -> np.ndarray:
        """The diagonal b x b blocks of S^{-1}, shape (p, b, b)."""
        p, b = self.blocks
        Z = solve_triangular(self.L_A, self.F.T, lower=True, check_finite=False).T.reshape(p, b, -1)
        inner = np.eye(b) - Z @ np.swapaxes(Z, 1, 2)              # I - F_p (I + F^T F)^{-1} F_p^T
        L_inv = np.linalg.inv(self.L_R)
        out = np.swapaxes(L_inv, 1, 2) @ inner @ L_inv
        return 0.5 * (out + np.swapaxes(out, 1, 2))


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
    innovation_factor : BlockInnovation or None
        :func:`update_blocks` only: S in factored low-rank form (``innovation_cov`` and ``innovation_chol`` are then
        None: S is never formed).
    """

    state: GaussianState
    innovation: np.ndarray
    innovation_cov: np.ndarray
    nis: float
    dof: int
    used: np.ndarray
    jitter_events: int
    innovation_chol: np.ndarray | None = None
    innovation_factor: BlockInnovation | None = None

    @property
    def log_likelihood(self) -> float:
        """log N(e; 0, S) = -(NIS + log det S + m_used log 2 pi) / 2, from L_S; 0.0 when no row was used."""
        if self.dof == 0:
            return 0.0
        if self.innovation_factor is not None:
            log_det = self.innovation_factor.log_det
        else:
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


def _psd_factor(C) -> np.ndarray:
    """A square factor L with L L^T = C for a symmetric PSD C: its Cholesky factor, or ``V sqrt(max(d, 0))`` from
    its eigen-decomposition when C is singular (no jitter: a zero-variance direction stays exactly zero)."""
    try:
        return np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        d, V = np.linalg.eigh(C)
        return V * np.sqrt(np.clip(d, 0.0, None))


def update_blocks(prediction: GaussianState, y, H, R_blocks, offset=None) -> UpdateResult:
    """Kalman measurement update for y = offset + H x + v with a block-diagonal noise, v_i ~ N(0, R_i) for the
    p blocks of b rows each (a tracked point's 3 coordinates), in the low-rank form.

    The posterior is the one of :func:`update` (to rounding): with ``C = L_C L_C^T``, ``F = L_R^{-1} H L_C`` and
    ``I + F^T F = L_A L_A^T``, ``C+ = X^T X`` with ``X = L_A^{-1} L_C^T``, ``mu+ = mu + X^T L_A^{-1} F^T L_R^{-1} e``,
    ``NIS = |L_R^{-1} e|^2 - |L_A^{-1} F^T L_R^{-1} e|^2`` and ``log det S = log det R + log det (I + F^T F)``
    (Woodbury; the matrix determinant lemma). It costs O(m n^2 + n^3) against :func:`update`'s O(m^3 + m^2 n): use it
    when there are more rows than states. ``C+`` is positive semi-definite by construction (as the Joseph form's).

    Parameters
    ----------
    prediction : GaussianState
        N(mu, C) of dimension n.
    y : array_like of shape (m,), m = p b
        Measurement, every row finite (drop unseen blocks before calling).
    H : array_like of shape (m, n)
    R_blocks : array_like of shape (p, b, b)
        Symmetric positive-definite noise covariance of each block.
    offset : array_like of shape (m,), optional

    Returns
    -------
    UpdateResult
        With ``innovation_factor`` (S factored) and ``innovation_cov``/``innovation_chol`` None.

    Raises
    ------
    numpy.linalg.LinAlgError
        A block of R is not positive definite (use :func:`update`, which needs only S positive definite).
    """
    if not isinstance(prediction, GaussianState):
        raise TypeError(f"update_blocks: prediction must be a GaussianState, got {type(prediction).__name__}")
    n = prediction.mean.shape[0]
    R_blocks = np.asarray(R_blocks, float)
    if R_blocks.ndim != 3 or R_blocks.shape[1] != R_blocks.shape[2]:
        raise ValueError(f"update_blocks: R_blocks: expected shape (p, b, b), got {R_blocks.shape}")
    p, b = R_blocks.shape[:2]
    m = p * b
    y = _as_array("update_blocks: y", y, (m,))
    H = _as_array("update_blocks: H", H, (m, n))
    R_blocks = _as_array("update_blocks: R_blocks", R_blocks, (p, b, b))
    offset = np.zeros(m) if offset is None else _as_array("update_blocks: offset", offset, (m,))
    used = np.ones(m, bool)
    used.setflags(write=False)
    if m == 0:
        return UpdateResult(prediction, _frozen(np.empty(0)), None, math.nan, 0, used, 0)
    R_blocks = 0.5 * (R_blocks + np.swapaxes(R_blocks, 1, 2))
    L_R = np.linalg.cholesky(R_blocks)                       # batched; LinAlgError if a block is not PD
    mu, C = prediction.mean, prediction.cov
    L_C = _psd_factor(C)
    F = _whiten(L_R, H) @ L_C
    L_A = np.linalg.cholesky(np.eye(n) + F.T @ F)
    factor = BlockInnovation(L_R, F, L_A)
    e = y - offset - H @ mu
    ew = factor.whiten(e)
    v = solve_triangular(L_A, F.T @ ew, lower=True, check_finite=False)
    X = solve_triangular(L_A, L_C.T, lower=True, check_finite=False)
    mean = mu + X.T @ v
    cov = symmetrise(X.T @ X)
    _, post_events, post_delta = _cholesky_jitter(cov, 6, "update_blocks: C+")   # PD check of C+, as update's
    if post_events:
        cov = cov + post_delta * np.eye(n)
    nis = max(float(ew @ ew - v @ v), 0.0)
    return UpdateResult(GaussianState(mean, cov), _frozen(e), None, nis, m, used, post_events, None, factor)
