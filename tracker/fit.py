"""Weighted least-squares fit of the material parameters to a measurement set (paper §IV; docs/cli.md §12).

The estimated subset of ``theta = [rho, alpha1, alpha2, E, nu]`` (the model file's ``estimation.estimate``) is
optimised in the estimators' coordinates ``phi`` (:mod:`tracker.params`) inside the box ``estimation.bounds``
mapped to ``phi``, with ``scipy.optimize.least_squares`` (``method='trf'``, ``x_scale='jac'``).

Prediction. The patch starts at the static equilibrium of the first frame's input and follows the same
discretisation as the estimators (exact, first-order-hold input, the measurement file's frame interval), with
no noise: ``x_0 = [K^-1 F u_0; 0]``, ``x_k = A x_{k-1} + B0 u_{k-1} + B1 u_k``.

Residuals. A measured point is ``y_kp = X_p + r(t_k) + H_p x_k + v_kp``, ``v_kp ~ N(0, R_kp)``, with ``r(t)`` the
known respiration translation. The undeformed position ``X_p`` is not known for points from ``heartcv
measure`` (their ``reference`` is the position in the frame they were born in, already deformed), so the fit
uses only displacements: ``X_p`` is a nuisance offset per point, eliminated exactly by generalised least
squares,

    m_p(theta) = (sum_k R_kp^-1)^-1 sum_k R_kp^-1 e_kp,     e_kp = y_kp - r(t_k) - H_p x_k(theta),
    residual_kp = L_kp^-1 (e_kp - m_p),                      L_kp L_kp^T = R_kp (Cholesky).

This is the displacement form ``y_kp - y_bp = H_p (x_k - x_b)`` relative to a point's birth frame b, weighted
with the full covariance of those differences (the birth frame's noise is common to all of them): any full set
of such contrasts gives the same cost (tested), and the form above whitens them exactly, so that at the true
parameters ``2 cost`` is chi-square with ``3 n_obs - 3 n_points - M`` degrees of freedom. Points seen in fewer
than two frames of the fitted window carry no displacement and are not used.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import logging

import numpy as np
import scipy.linalg as sla

from .files import InputError
from .measurements import MeasurementSet
from .model import PatchModel
from .params import NAMES, ParameterSpace
from .tracking import ObservedPoints, first_frames, frame_interval, locate_points

__all__ = ["FitProblem", "UnknownInputProblem", "FitResult", "fit", "tracking_prior", "undeformed_references",
           "UndeformedReferences", "causal_heldout_selection", "S_LIMIT", "SINGULAR_RTOL"]

log = logging.getLogger(__name__)

S_LIMIT = 15.0
"""|s| = |log(lambda/mu)| is kept below this (nu in [1.5e-7, 0.5 - 7.6e-8]) where the box leaves s unbounded."""

PHI_LIMIT = 50.0
"""Other phi coordinates (logarithms) are kept within +-50 where the box leaves them unbounded."""

ROBUST_MIN_POINTS = 30
"""From this many points on, the parameter covariance is the cluster-robust (sandwich) estimate by point."""

SINGULAR_RTOL = 1e-8
"""Smallest singular value of the column-normalised Jacobian, relative, below which a fit is singular."""


class FitProblem:
    """The weighted least-squares problem of one model and one measurement set (patch frame).

    Parameters
    ----------
    model : PatchModel
    meas : MeasurementSet
        In the patch frame (register rig-frame files first).
    frames : int, optional
        Use the first ``frames`` frames (default all); at least 2.
    points : ObservedPoints, optional
        Placement of the points on the model (default :func:`tracker.tracking.locate_points`).
    inputs, translation : optional
        The model's inputs (K, n_u) and the rigid translation (K, 3) (default: the measurement set's columns).
    centring : ndarray (3, r), optional
        Subtracted from every point's displacement map on the model's positions (:attr:`UnknownInputProblem.
        centring`: the model's displacements centred over another problem's points, so that a translation in that
        gauge applies here).

    Attributes
    ----------
    keep : ndarray (P_used,) int      indices into the measurement set's points used by the fit
    frames : int                      frames used (K)
    n_obs : int                       observations (point-frames) used
    dof : int                         ``3 n_obs - 3 P_used`` (before subtracting the estimated parameters)
    """

    def __init__(self, model: PatchModel, meas: MeasurementSet, frames: int | None = None,
                 points: ObservedPoints | None = None, inputs=None, translation=None, centring=None):
        if frames is not None and int(frames) < 2:
            raise ValueError(f"frames: at least 2 frames are needed for a fit, got {frames}")
        K = meas.n_frames if frames is None else min(int(frames), meas.n_frames)
        if K < 2:
            raise InputError(None, f"at least 2 frames are needed (heartcv fit, and heartcv track --params, whose "
                                   f"measured points' undeformed references are fitted), the file has "
                                   f"{meas.n_frames}", "times")
        pts = points or locate_points(model, meas)
        self.model = model
        self.dt = frame_interval(model, meas)
        self.inputs = (meas.input_columns(model.input_names) if inputs is None else np.asarray(inputs, float))[:K]
        trans = (meas.translation() if translation is None else np.asarray(translation, float))[:K]
        y = meas.positions[:K, pts.keep]
        seen = np.isfinite(y).all(axis=2)
        use = seen.sum(axis=0) >= 2
        if not use.any():
            raise InputError(None, f"no point on the patch is seen in two of the first {K} frames", "positions")
        self.keep = pts.keep[use]
        self.dropped = np.setdiff1d(np.arange(meas.n_points), self.keep)
        P = int(use.sum())
        r = model.r
        H = pts.observation.H.reshape(-1, 3, 2 * r)[use]  # (P, 3, 2r)
        Hq = H[:, :, :r] - (0.0 if centring is None else np.asarray(centring, float).reshape(3, r))
        self.H_q = Hq.reshape(3 * P, r)  # positions depend on q only
        self.seen = seen[:, use]
        self.y = (y[:, use] - trans[:, None, :])[self.seen]  # (n_obs, 3)
        self._frame_idx, self._point_idx = np.nonzero(self.seen)
        # the seen covariances (n_obs, 3, 3) gathered at once, in the order of the mask, with no copy of the
        # frames x points array between; symmetrised in place (the numbers of 0.5 * (cov + cov^T))
        cov = meas.covariances[self._frame_idx, self.keep[self._point_idx]]
        cov += np.swapaxes(cov, -1, -2)
        cov *= 0.5
        L = np.linalg.cholesky(cov)
        del cov
        eye = np.broadcast_to(np.eye(3), L.shape)
        self.L_inv = np.linalg.solve(L, eye)  # (n_obs, 3, 3)
        del L
        R_inv = np.swapaxes(self.L_inv, -1, -2) @ self.L_inv
        G = np.zeros((P, 3, 3))
        np.add.at(G, self._point_idx, R_inv)
        self._R_inv = R_inv
        self._G_inv = np.linalg.inv(G)
        self.frames = K
        self.n_points = P
        self.n_obs = int(self.seen.sum())
        self.dof = 3 * self.n_obs - 3 * P

    # -- model side ------------------------------------------------------------------------------
    def states(self, theta) -> np.ndarray:
        """Deterministic kinematic states (K, 2r) from equilibrium at ``u_0``."""
        return self.simulate(theta, self.inputs[:, :, None])[:, :, 0]

    def simulate(self, theta, U) -> np.ndarray:
        """Deterministic kinematic states (K, 2r, J) for J input sequences U (K, n_u, J), each from the
        equilibrium at its first value."""
        sysd = self.model.system(theta, self.dt)
        drive = np.einsum("ij,kjl->kil", sysd.B0, U[:-1]) + np.einsum("ij,kjl->kil", sysd.B1, U[1:])
        X = np.empty((self.frames, self.model.state_dim, U.shape[2]))
        x = np.stack([self.model.static_state(theta, U[0, :, j]) for j in range(U.shape[2])], axis=1)
        X[0] = x
        A = sysd.A
        for k in range(1, self.frames):
            x = A @ x + drive[k - 1]
            X[k] = x
        return X

    def displacements(self, theta) -> np.ndarray:
        """Model displacements ``H_p x_k`` (K, P_used, 3) of the used points."""
        X = self.states(theta)
        return (X[:, : self.model.r] @ self.H_q.T).reshape(self.frames, self.n_points, 3)

    # -- residuals --------------------------------------------------------------------------------
    def residuals(self, theta) -> np.ndarray:
        """Whitened residuals with the per-point offsets profiled out, shape (3 n_obs,)."""
        e = self.y - self.displacements(theta)[self.seen]  # (n_obs, 3)
        b = np.zeros((self.n_points, 3))
        np.add.at(b, self._point_idx, np.einsum("nij,nj->ni", self._R_inv, e))
        m = np.einsum("pij,pj->pi", self._G_inv, b)
        return np.einsum("nij,nj->ni", self.L_inv, e - m[self._point_idx]).ravel()

    def offsets(self, theta, relative_model_error: float = 0.0) -> np.ndarray:
        """The profiled offsets ``m_p`` (P_used, 3): the estimated undeformed positions (patch frame, m).

        ``relative_model_error`` gamma > 0 adds a model-error covariance ``gamma^2 |d_kp|^2 I`` to each
        observation's ``R_kp`` (``d_kp`` the model displacement of the point in that frame), so that the offsets
        rest on the frames where the model displaces the point least: a model whose displacements are off by a
        fraction (a constant E where the truth's stiffness follows the cycle, a coarse mesh) then biases the
        undeformed positions by that fraction of the *smallest* displacements instead of their weighted mean.
        0 gives the fit's own offsets (the measurement covariances alone).
        """
        d = self.displacements(theta)[self.seen]
        e = self.y - d
        if relative_model_error > 0:
            g2 = float(relative_model_error) ** 2 * np.einsum("ni,ni->n", d, d)
            R = np.linalg.inv(self._R_inv) + g2[:, None, None] * np.eye(3)
            W = np.linalg.inv(R)
        elif relative_model_error == 0:
            W = self._R_inv
        else:
            raise ValueError(f"relative_model_error must be >= 0, got {relative_model_error}")
        b = np.zeros((self.n_points, 3))
        np.add.at(b, self._point_idx, np.einsum("nij,nj->ni", W, e))
        G = np.zeros((self.n_points, 3, 3))
        np.add.at(G, self._point_idx, W)
        return np.linalg.solve(G, b[..., None])[..., 0]

    def chi2(self, theta) -> float:
        """``sum residuals^2`` (= 2 cost)."""
        r = self.residuals(theta)
        return float(r @ r)


class UnknownInputProblem(FitProblem):
    """The fit of a recording without the model's pressure (docs/model.md "Unknown input"): the input is
    ``u(t) = sum_h a_h cos(2 pi h f t) + b_h sin(2 pi h f t)`` on the model's input ``column`` (t from the first
    frame, the heart rate ``f`` given) and the observed surface moves rigidly by an unknown translation ``tau_k``
    per frame besides. For a given theta the states are linear in the amplitudes ``alpha = [a_1, b_1, ...]``, so
    ``alpha``, ``tau_k`` (``tau_0 = 0``: the offsets take the common part) and the offsets ``m_p`` are all profiled
    out by one generalised least-squares solve: the offsets eliminated per point (block diagonal), then the
    reduced normal equations of ``[tau_1 .. tau_{K-1}, alpha]`` (size ``3 (K - 1) + 2 H``) solved densely.

    ``dof = 3 n_obs - 3 P - 3 (K - 1) - 2 H`` (before the estimated parameters). ``rotation=True`` adds a small
    rotation per frame about the patch origin (6 rigid unknowns per frame; the estimators carry the translation
    only).

    ``centred=True`` centres the model's displacements over the fitted points (:attr:`centring`, the mean of their
    displacement maps, subtracted from each): with a free translation per frame the model's mean displacement and
    the translation are not separable, and centring fixes the split, so that the translation is the tracks' mean
    motion rather than that minus the model's mean bulge (docs/model.md 17). theta, the amplitudes, the residual,
    the cost and the offsets are unchanged (the translation starts at the model's mean displacement of the first
    frame instead of zero); the translation moves by the model's mean displacement.
    """

    def __init__(self, model: PatchModel, meas: MeasurementSet, frequency_hz: float, harmonics: int, column: int,
                 frames: int | None = None, points: ObservedPoints | None = None, rotation: bool = False,
                 centred: bool = False):
        from .unknown_input import harmonic_basis

        n_u = len(model.input_names)
        if not 0 <= column < n_u:
            raise ValueError(f"column: an input of the model expected (0..{n_u - 1}), got {column}")
        known = np.zeros((meas.n_frames, n_u))
        for j, name in enumerate(model.input_names):
            if j != column and name in meas.input_names:
                known[:, j] = meas.input_columns([name])[:, 0]
        super().__init__(model, meas, frames, points, inputs=known, translation=np.zeros((meas.n_frames, 3)))
        r = model.r
        self.centring = None
        if centred:
            Hq = self.H_q.reshape(self.n_points, 3, r)
            self.centring = Hq.mean(axis=0)                                      # (3, r)
            self.H_q = (Hq - self.centring).reshape(3 * self.n_points, r)
        K = self.frames
        self.frequency_hz = float(frequency_hz)
        self.harmonics = int(harmonics)
        self.column = int(column)
        self.basis = harmonic_basis(meas.times[:K] - meas.times[0], frequency_hz, harmonics)  # (K, 2H)
        U = np.repeat(self.inputs[:, :, None], 1 + self.basis.shape[1], axis=2)
        U[:, column, 1:] += self.basis
        self._U = U
        self.rotation = bool(rotation)
        self.dof = 3 * self.n_obs - 3 * self.n_points - (6 if rotation else 3) * (K - 1) - 2 * self.harmonics
        y = meas.positions[:K][:, self.keep]
        self._lever = np.nanmedian(y, axis=0)  # the points' positions (lever arms of the small rotations)
        self._rigid = self._rigid_design()

    def _design(self, theta):
        """Model displacements at the seen observations: known-input part (n_obs, 3) and per amplitude
        (n_obs, 3, 2H); and the first frame's positions, known-input part (r,) and per amplitude (r, 2H)."""
        X = self.simulate(theta, self._U)  # (K, 2r, 1 + 2H)
        r = self.model.r
        D = np.einsum("krj,pcr->kpcj", X[:, :r], self.H_q.reshape(self.n_points, 3, r))  # (K, P, 3, J)
        D = D[self.seen]  # (n_obs, 3, J)
        return D[:, :, 0], D[:, :, 1:], X[0, :r, 0], X[0, :r, 1:]

    def _rigid_design(self) -> np.ndarray:
        """Per observation (n_obs, 3, 3) or (n_obs, 3, 6) with ``rotation``: displacement per translation (and
        small rotation about the patch origin) of the frame, ``[I, -[X_p]x]`` with ``X_p`` the point's position."""
        X = self._lever[self._point_idx]
        G = np.zeros((X.shape[0], 3, 6 if self.rotation else 3))
        G[:, :, :3] = np.eye(3)
        if not self.rotation:
            return G
        G[:, 0, 4], G[:, 0, 5] = X[:, 2], -X[:, 1]
        G[:, 1, 3], G[:, 1, 5] = -X[:, 2], X[:, 0]
        G[:, 2, 3], G[:, 2, 4] = X[:, 1], -X[:, 0]
        return G

    def solve(self, theta):
        """The profiled ``(alpha (2H,), rigid (K, 3) translation (K, 6 with rotation vector), offsets (P, 3),
        e (n_obs, 3) residual before whitening, reduced normal matrix)`` at theta."""
        d0, J, q0, Q0 = self._design(np.asarray(theta, float))
        e = self.y - d0
        W = self._R_inv
        K, P, nA = self.frames, self.n_points, J.shape[2]
        fi, pi = self._frame_idx, self._point_idx
        nr = self._rigid.shape[2]
        nt = nr * (K - 1)
        nb = nt + nA
        Gr = self._rigid
        WJ = np.einsum("nij,nja->nia", W, J)  # (n_obs, 3, nA)
        We = np.einsum("nij,nj->ni", W, e)
        WG = np.einsum("nij,njb->nib", W, Gr)  # (n_obs, 3, 6)
        # per point: B_p = sum_n W_n X_n (3, nb), b_p = sum_n W_n e_n
        B = np.zeros((P, 3, nb))
        tau_obs = fi > 0
        cols = nr * (fi[tau_obs] - 1)
        for c in range(nr):
            np.add.at(B, (pi[tau_obs], slice(None), cols + c), WG[tau_obs][:, :, c])
        np.add.at(B[:, :, nt:], pi, WJ)
        b = np.zeros((P, 3))
        np.add.at(b, pi, We)
        # sum_n X_n^T W_n X_n
        S = np.zeros((nb, nb))
        GWG = np.zeros((K, nr, nr))
        np.add.at(GWG, fi, np.einsum("nia,nib->nab", Gr, WG))
        for k in range(1, K):
            S[nr * (k - 1):nr * k, nr * (k - 1):nr * k] = GWG[k]
        TA = np.zeros((K, nr, nA))
        np.add.at(TA, fi, np.einsum("nia,nib->nab", Gr, WJ))
        S[:nt, nt:] = TA[1:].reshape(nt, nA)
        S[nt:, :nt] = S[:nt, nt:].T
        S[nt:, nt:] = np.einsum("nia,nib->ab", J, WJ)
        rhs = np.zeros(nb)
        Te = np.zeros((K, nr))
        np.add.at(Te, fi, np.einsum("nia,ni->na", Gr, We))
        rhs[:nt] = Te[1:].reshape(-1)
        rhs[nt:] = np.einsum("nia,ni->a", J, We)
        GB = np.einsum("pij,pjb->pib", self._G_inv, B)
        S -= B.reshape(3 * P, nb).T @ GB.reshape(3 * P, nb)
        rhs -= np.einsum("pib,pi->b", GB, b)
        S = 0.5 * (S + S.T)
        d = 1.0 / np.sqrt(np.maximum(np.diag(S), 1e-300))  # Jacobi scaling: metres, radians and Pa differ by 1e9
        beta = d * sla.lstsq(S * np.outer(d, d), rhs * d, cond=1e-12)[0]
        rigid = np.zeros((K, nr))
        rigid[1:] = beta[:nt].reshape(K - 1, nr)
        seen = np.zeros(K, bool)
        seen[fi] = True
        seen[0] = True                       # the gauge: no rigid motion at the first frame
        if not seen.all():                   # frames where nothing was seen: their motion between their neighbours'
            k = np.arange(K)
            rigid = np.column_stack([np.interp(k, k[seen], rigid[seen, c]) for c in range(nr)])
        alpha = beta[nt:]
        m = np.einsum("pij,pj->pi", self._G_inv, b - np.einsum("pib,b->pi", B, beta))
        res = e - np.einsum("nia,na->ni", Gr, rigid[fi]) - np.einsum("nia,a->ni", J, alpha) - m[pi]
        if self.centring is not None:
            # the gauge of the uncentred problem's offsets: tau_0 = the model's mean displacement at the first frame
            shift = self.centring @ (q0 + Q0 @ alpha)
            rigid[:, :3] += shift
            m = m - shift
        return alpha, rigid, m, res, S

    def residuals(self, theta) -> np.ndarray:
        alpha, tau, m, res, _ = self.solve(theta)
        return np.einsum("nij,nj->ni", self.L_inv, res).ravel()

    def offsets(self, theta, relative_model_error: float = 0.0) -> np.ndarray:
        """The profiled offsets (P_used, 3) (the model-error weighting of :meth:`FitProblem.offsets` is not
        applied: the rigid motion and the input are profiled with the measurement weights)."""
        return self.solve(theta)[2]

    def field_frame(self) -> tuple:
        """``(centre (3,), axes (2, 3), scale)`` of a displacement field over the fitted points (their median
        positions): their mean, the two principal directions of their spread (along the observed surface) and the
        RMS distance from the mean within them (m)."""
        X = self._lever[np.isfinite(self._lever).all(axis=1)]
        centre = X.mean(axis=0)
        axes = np.linalg.svd(X - centre, full_matrices=False)[2][:2]
        scale = float(np.sqrt(np.mean(np.sum(((X - centre) @ axes.T) ** 2, axis=1))))
        return centre, axes, scale if scale > 0 else 1.0

    def residual_field(self, theta, degree: int, frame) -> np.ndarray:
        """(K, 3 (n - 1)): per fitted frame, the smooth displacement field that the profiled residual (after the
        model, the translation and the offsets at theta) holds beyond a translation: the coefficients
        ``[c_2 (3) | c_3 (3) | ...]`` of the non-constant monomials of :func:`tracker.unknown_input.field_basis`
        (degree ``degree``, in ``frame`` of :meth:`field_frame`), fitted with the constant by least squares to the
        frame's residuals at the points' positions. A frame with fewer points than twice the monomials repeats the
        previous frame's field (zero before the first)."""
        from .unknown_input import field_basis

        res = self.solve(np.asarray(theta, float))[3]
        centre, axes, scale = frame
        phi = field_basis(self._lever[self._point_idx], degree, centre, axes, scale)   # (n_obs, n)
        n = phi.shape[1]
        out = np.zeros((self.frames, 3 * (n - 1)))
        for k in range(self.frames):
            rows = self._frame_idx == k
            if rows.sum() < 2 * n:
                out[k] = out[k - 1] if k else 0.0
                continue
            c = np.linalg.lstsq(phi[rows], res[rows], rcond=None)[0]          # (n, 3)
            out[k] = c[1:].reshape(-1)
        return out

    def input_solution(self, theta, reduced_chi2: float = 1.0):
        """``(alpha, alpha_std, tau)`` at theta: the amplitudes' standard deviations from the reduced normal
        matrix, scaled by the reduced chi-square when above 1."""
        alpha, tau, _, _, S = self.solve(theta)
        nA = alpha.size
        keep = np.diag(S) > 0                # a frame where nothing was seen has no rigid unknowns to speak of
        keep[-nA:] = True
        S = S[np.ix_(keep, keep)]
        try:
            d = 1.0 / np.sqrt(np.maximum(np.diag(S), 1e-300))
            cov = (np.linalg.inv(S * np.outer(d, d)) * np.outer(d, d))[-nA:, -nA:]
            sd = np.sqrt(np.clip(np.diag(cov), 0, None) * max(reduced_chi2, 1.0))
        except np.linalg.LinAlgError:
            sd = np.full(nA, np.nan)
        return alpha, sd, tau


@dataclass(frozen=True)
class FitResult:
    """Outcome of :func:`fit` (and the content of a parameters file, docs/formats.md §12).

    Attributes
    ----------
    theta : ndarray (5,)              fitted [rho, alpha1, alpha2, E, nu] (SI); fixed ones at the model's value
    theta_std : ndarray (5,)          standard deviation (delta method from phi; 0 for fixed parameters)
    estimated : tuple of str          fitted parameters, NAMES order (rows/columns of the covariances)
    phi : ndarray (M,)                fitted estimated subset in phi coordinates
    cov_phi, cov_theta : ndarray (M, M) or None   covariance in phi and in SI units (None when unavailable)
    epsilon : ndarray (2,)            the alpha offsets eps1, eps2 of phi
    cost : float                      0.5 * sum of squared whitened residuals at the solution
    dof : int                         residual degrees of freedom, ``3 n_obs - 3 points - M``
    reduced_chi2 : float              ``2 cost / dof``
    covariance_scaled : bool          whether the covariance was multiplied by ``reduced_chi2`` (> 1)
    covariance_kind : str             'model': ``(J^T J)^-1`` (scaled as above); 'cluster-robust': the sandwich
                                      ``A^-1 (sum_p g_p g_p^T) A^-1`` with ``A = J^T J`` and ``g_p`` the gradient of
                                      point p's residuals, times ``P / (P - M)`` (:func:`fit`)
    iterations, evaluations : int     Jacobian and residual evaluations of the winning start
    converged : bool                  least_squares status > 0 and a non-singular Jacobian
    status : int                      least_squares status of the winning start
    message : str                     reason of success or failure
    frames, points, observations : int   frames, points and point-frames used
    starts : tuple of dict            per start: theta0, theta, cost, status, evaluations, message
    at_bound : tuple of str           estimated parameters at a bound of the box at the solution
    registration : dict or None       rig-to-patch registration applied before the fit (CLI); with ``geometry``
                                      when the patch was fitted to the observed surface
    estimated_input : dict or None    the estimated input (:class:`tracker.unknown_input.InputBlock` entry plus the
                                      heart rate and amplitudes) when none was recorded
    meta : dict                       provenance (producer, inputs_hash, seed, ...)
    """

    theta: np.ndarray
    theta_std: np.ndarray
    estimated: tuple
    phi: np.ndarray
    cov_phi: np.ndarray | None
    cov_theta: np.ndarray | None
    epsilon: np.ndarray
    cost: float
    dof: int
    reduced_chi2: float
    covariance_scaled: bool
    iterations: int
    evaluations: int
    converged: bool
    status: int
    message: str
    frames: int
    points: int
    observations: int
    starts: tuple = ()
    at_bound: tuple = ()
    registration: dict | None = None
    meta: dict = field(default_factory=dict)
    covariance_kind: str = "model"
    estimated_input: dict | None = None

    def __post_init__(self):
        if self.covariance_kind not in ("model", "cluster-robust"):
            raise ValueError(f"covariance_kind: 'model' or 'cluster-robust' expected, got {self.covariance_kind!r}")
        th = np.array(self.theta, float).reshape(-1)
        sd = np.array(self.theta_std, float).reshape(-1)
        if th.shape != (5,) or sd.shape != (5,):
            raise ValueError(f"theta/theta_std: shape (5,) expected, got {th.shape} and {sd.shape}")
        est = tuple(self.estimated)
        if any(n not in NAMES for n in est) or len(set(est)) != len(est):
            raise ValueError(f"estimated: distinct names from {NAMES} expected, got {est}")
        est = tuple(n for n in NAMES if n in est)
        M = len(est)
        phi = np.array(self.phi, float).reshape(-1)
        if phi.shape != (M,):
            raise ValueError(f"phi: shape ({M},) expected, got {phi.shape}")
        for name in ("cov_phi", "cov_theta"):
            c = getattr(self, name)
            if c is not None:
                c = np.array(c, float)
                if c.shape != (M, M):
                    raise ValueError(f"{name}: shape ({M}, {M}) expected, got {c.shape}")
                c.setflags(write=False)
                object.__setattr__(self, name, c)
        eps = np.array(self.epsilon, float).reshape(-1)
        if eps.shape != (2,):
            raise ValueError(f"epsilon: shape (2,) expected, got {eps.shape}")
        for name, val in (("theta", th), ("theta_std", sd), ("phi", phi), ("epsilon", eps)):
            val.setflags(write=False)
            object.__setattr__(self, name, val)
        object.__setattr__(self, "estimated", est)
        object.__setattr__(self, "at_bound", tuple(self.at_bound))
        object.__setattr__(self, "starts", tuple(self.starts))

    @property
    def fixed(self) -> tuple:
        """Names of the parameters held at the model file's values."""
        return tuple(n for n in NAMES if n not in self.estimated)

    @property
    def poorly_determined(self) -> tuple:
        """Estimated parameters whose standard deviation in phi exceeds 1: the data do not pin them down to a
        factor e (docs/spec/model.md §4.3). Empty without a covariance."""
        if self.cov_phi is None:
            return ()
        return tuple(n for n, v in zip(self.estimated, np.diag(self.cov_phi), strict=True) if v > 1.0)

    @property
    def index(self) -> np.ndarray:
        return np.array([NAMES.index(n) for n in self.estimated], dtype=int)


def _fit_bounds(space: ParameterSpace):
    lo, up = space.bounds_phi
    limit = np.array([S_LIMIT if n == "nu" else PHI_LIMIT for n in space.estimated])
    lo = np.where(np.isfinite(lo), lo, -limit)
    up = np.where(np.isfinite(up), up, limit)
    lo, up = np.maximum(lo, -limit), np.minimum(up, limit)
    margin = 1e-9 * np.maximum(1.0, np.abs(np.r_[lo, up]).reshape(2, -1).max(axis=0))
    return lo, up, lo + margin, up - margin


def _theta_of(space: ParameterSpace, theta_fixed, x):
    """Full theta with the estimated entries from phi ``x`` and the others exactly at ``theta_fixed``."""
    phi = space.to_phi(theta_fixed)
    phi[space.index] = x
    theta = np.array(theta_fixed, float)
    theta[space.index] = space.from_phi(phi)[space.index]
    return theta


def _starts(x_model, prior_std, count, rng, inner_lo, inner_up):
    starts = [np.clip(x_model, inner_lo, inner_up)]
    if count > 1:
        if rng is None:
            raise ValueError("rng: a numpy Generator is needed for more than one start")
        draws = x_model + prior_std * rng.standard_normal((count - 1, x_model.size))
        starts.extend(np.clip(draws, inner_lo, inner_up))
    return starts


def _covariance(J, names):
    """``(J^T J)^-1`` by SVD of the column-normalised Jacobian; (None, reason) when singular."""
    norms = np.linalg.norm(J, axis=0)
    if not np.isfinite(J).all():
        return None, "the Jacobian at the solution is not finite"
    if (norms == 0).any():
        bad = [names[i] for i in np.flatnonzero(norms == 0)]
        return None, f"singular Jacobian: the residuals do not depend on {', '.join(bad)}"
    Jn = J / norms
    _, s, Vt = np.linalg.svd(Jn, full_matrices=False)
    if s[-1] < SINGULAR_RTOL * s[0]:
        weak = np.abs(Vt[s < SINGULAR_RTOL * s[0]]).max(axis=0)
        bad = [names[i] for i in np.flatnonzero(weak > 0.3)] or list(names)
        return None, (f"singular Jacobian (condition {s[0] / s[-1]:.3g}): {', '.join(bad)} cannot be told apart "
                      "from these data; fix them (estimation.estimate) or use data that excite them")
    cov_n = (Vt.T / s**2) @ Vt
    return cov_n / np.outer(norms, norms), None


def fit(model: PatchModel, meas: MeasurementSet, rng: np.random.Generator | None = None, *,
        frames: int | None = None, starts: int = 1, max_evaluations: int | None = None,
        points: ObservedPoints | None = None, problem: FitProblem | None = None) -> FitResult:
    """Bounded weighted least-squares fit of the model file's estimated parameters (paper §IV).

    Parameters
    ----------
    model : PatchModel
        Its ``config.theta`` is the first start and the value of the fixed parameters; ``estimation.estimate``
        the fitted subset; ``estimation.bounds`` the box; the prior (``prior_std``/``prior_std_si``) the spread
        of the other starts.
    meas : MeasurementSet
        Patch frame.
    rng : numpy.random.Generator, optional
        Draws the starts after the first (needed when ``starts > 1``).
    frames : int, optional
        Fit the first ``frames`` frames (default all).
    starts : int
        The model file's value plus ``starts - 1`` draws from the prior ``N(phi(theta), diag(prior_std^2))``,
        clipped into the box. The converged start with the lowest cost wins.
    max_evaluations : int, optional
        ``max_nfev`` of each least_squares run (default scipy's, 100 per parameter).
    problem : FitProblem, optional
        A prepared problem (then ``frames`` and ``points`` are ignored).

    Returns
    -------
    FitResult
        ``converged`` is False, with the reason in ``message``, when no start converged (least_squares status
        <= 0 or a failed evaluation) or the Jacobian at the best solution is singular (then no covariance).
        Covariance in phi, converted to SI by the delta method: with at least ``ROBUST_MIN_POINTS`` points the
        cluster-robust sandwich by point (``covariance_kind``; a tracked point's errors are correlated from frame
        to frame, a matching bias that moves with the track, and the model's own error is smooth in time, so the
        residuals of one point are not independent and ``(J^T J)^-1`` is too small: on the rendered phantom
        by a factor of 12 in standard deviation); with fewer points, where a sandwich over so few clusters is
        itself too noisy, ``(J^T J)^-1`` multiplied by the reduced chi-square when that exceeds 1
        (``covariance_scaled``).

    Raises
    ------
    InputError
        Nothing to estimate (field ``estimation.estimate``), too few frames, points or observations, points off
        the patch, missing inputs, unequal frame intervals (no file named: the caller attaches it).
    ValueError
        ``starts`` or ``max_evaluations`` below 1, ``starts > 1`` without ``rng``.
    """
    if starts < 1:
        raise ValueError(f"starts: at least 1 expected, got {starts}")
    if max_evaluations is not None and max_evaluations < 1:
        raise ValueError(f"max_evaluations: at least 1 expected, got {max_evaluations}")
    cfg = model.config
    space = cfg.parameter_space()
    if space.dim == 0:
        raise InputError(None, "empty; the fit needs at least one parameter to estimate", "estimation.estimate")
    prob = problem or FitProblem(model, meas, frames, points)
    M = space.dim
    dof = prob.dof - M
    if dof <= 0:
        raise InputError(None, f"{3 * prob.n_obs} residuals leave no degrees of freedom for {prob.n_points} point "
                               f"offsets and {M} parameters", "positions")
    lo, up, inner_lo, inner_up = _fit_bounds(space)
    theta_model = np.array(cfg.theta, float)
    x_model = space.x_from_theta(theta_model)
    x0s = _starts(x_model, cfg.prior_std_phi(), starts, rng, inner_lo, inner_up)

    def fun(x):
        r = prob.residuals(_theta_of(space, theta_model, x))
        if not np.isfinite(r).all():
            raise FloatingPointError(f"non-finite residuals at phi = {x}")
        return r

    results, records = [], []
    for i, x0 in enumerate(x0s):
        res, rec = _run_start(fun, x0, lo, up, max_evaluations)
        rec["theta0"] = (theta_model if i == 0 else _theta_of(space, theta_model, x0)).tolist()
        rec["theta"] = None if res is None else _theta_of(space, theta_model, res.x).tolist()
        log.debug("fit start %d: %s", i, rec)
        results.append(res)
        records.append({k: rec[k] for k in ("theta0", "theta", "cost", "status", "evaluations", "message")})
    sizes = dict(frames=prob.frames, points=prob.n_points, observations=prob.n_obs, starts=tuple(records))
    ok = [i for i, r in enumerate(results) if r is not None and r.status > 0]
    if not ok:
        reasons = "; ".join(f"start {i}: {r['message']}" for i, r in enumerate(records))
        tried = [r for r in results if r is not None]
        res = min(tried, key=lambda r: r.cost) if tried else None
        x = x0s[0] if res is None else res.x
        cost = float("nan") if res is None else float(res.cost)
        return FitResult(_theta_of(space, theta_model, x), np.zeros(5), space.estimated, x, None, None, space.eps,
                         cost, dof, 2 * cost / dof, False, 0 if res is None else int(res.njev or 0),
                         0 if res is None else int(res.nfev), False, -99 if res is None else int(res.status),
                         f"no start converged ({reasons})", **sizes)
    res = min((results[i] for i in ok), key=lambda r: r.cost)
    clusters = np.repeat(prob._point_idx, 3) if prob.n_points >= ROBUST_MIN_POINTS else None
    return _solution(space, theta_model, res, lo, up, dof, sizes, clusters)


def _run_start(fun, x0, lo, up, max_evaluations):
    """One bounded least_squares run from ``x0``: ``(OptimizeResult or None, record)``; a start whose model
    evaluation fails numerically (non-finite residuals, a matrix that does not factor) is recorded as failed."""
    from scipy.optimize import least_squares

    try:
        res = least_squares(fun, x0, jac="3-point", bounds=(lo, up), method="trf", x_scale="jac",
                            max_nfev=max_evaluations)
    except (FloatingPointError, np.linalg.LinAlgError, sla.LinAlgError) as exc:
        return None, {"cost": None, "status": -99, "evaluations": 0, "message": f"evaluation failed: {exc}"}
    return res, {"cost": float(res.cost), "status": int(res.status), "evaluations": int(res.nfev),
                 "message": str(res.message)}


def _cluster_robust(cov_model, J, r, clusters) -> np.ndarray:
    """The cluster-robust (sandwich) covariance ``C (sum_p g_p g_p^T) C * P / (P - M)``, with ``C = (J^T J)^-1``
    and ``g_p = J_p^T r_p`` summed over the residual rows of cluster p (Liang & Zeger 1986; P clusters, M
    parameters)."""
    ids, inv = np.unique(clusters, return_inverse=True)
    P, M = ids.size, J.shape[1]
    g = np.zeros((P, M))
    np.add.at(g, inv, J * r[:, None])
    meat = g.T @ g * (P / max(P - M, 1))
    return cov_model @ meat @ cov_model


def _solution(space, theta_model, res, lo, up, dof, sizes, clusters=None) -> FitResult:
    """Covariance, bounds and convergence flag of the winning least_squares run (``clusters``: the point of
    each residual row, for the cluster-robust covariance; None for the model covariance)."""
    theta = _theta_of(space, theta_model, res.x)
    chi2_red = float(2 * res.cost / dof)
    # the Jacobian at the solution: least_squares' own central differences in phi at the final x
    J = np.asarray(res.jac, float)
    cov_phi, reason = _covariance(J, space.estimated)
    kind = "model"
    if cov_phi is not None and clusters is not None:
        cov_phi = _cluster_robust(cov_phi, J, np.asarray(res.fun, float), clusters)
        kind = "cluster-robust"
    # trf keeps its iterates strictly feasible: a parameter within 1e-4 of the box width of a bound is at it
    tol = 1e-4 * (up - lo)
    near = (res.active_mask != 0) | (res.x - lo < tol) | (up - res.x < tol)
    at_bound = tuple(space.estimated[i] for i in np.flatnonzero(near))
    scaled = chi2_red > 1.0 and cov_phi is not None and kind == "model"
    theta_std = np.zeros(5)
    cov_theta = None
    if cov_phi is not None:
        if scaled:
            cov_phi = cov_phi * chi2_red
        cov_phi = 0.5 * (cov_phi + cov_phi.T)
        jac = space.dtheta_dphi(space.to_phi(theta))[space.index]
        cov_theta = cov_phi * np.outer(jac, jac)
        theta_std[space.index] = np.sqrt(np.diag(cov_theta))
    return FitResult(theta, theta_std, space.estimated, res.x, cov_phi, cov_theta, space.eps, float(res.cost), dof,
                     chi2_red, scaled, int(res.njev or 0), int(res.nfev), reason is None, int(res.status),
                     str(res.message) if reason is None else reason, at_bound=at_bound, covariance_kind=kind,
                     **sizes)


def tracking_prior(cfg, fitted: FitResult):
    """Prior of the joint estimators started from a fit (``heartcv track --params``).

    The fitted theta (all five) replaces the model file's values as the prior mean. The prior standard deviation
    of each parameter the tracker estimates:

    * a **static** parameter (no random walk in the model file): the fit's, ``theta_std / (d theta / d phi)`` at
      the fitted theta in the tracker's phi, when the fit estimated that parameter and has a covariance, unless the
      model file's prior (``prior_std`` / ``prior_std_si``) is tighter; otherwise the model file's. The fitted
      constant is then the parameter itself.
    * a **time-varying** parameter (``random_walk_std > 0``): the model file's. The fit's standard deviation is
      the uncertainty of the constant that best explains the fitted window, not of the parameter in the first
      frame, which for a stiffness that follows the heartbeat may lie anywhere in the cycle's range; taken as
      the prior it would make the reference states (:mod:`tracker.reference`) lock onto the constant's
      references in the first beat (docs/estimators.md 3.7).

    Correlations of the fit are not carried over (the joint prior is diagonal in phi).

    Returns
    -------
    theta0 : ndarray (5,)
    prior_std : ndarray (M,)          phi units, the tracker's ``estimation.estimate`` order
    source : dict                     name -> 'fit' or 'model'

    Raises
    ------
    InputError
        A fitted value outside the model file's box ``estimation.bounds`` (field ``theta.<name>``; no file named:
        the caller attaches the parameters file).
    """
    space = cfg.parameter_space()
    model_sd = cfg.prior_std_phi()
    walk = cfg.random_walk_std_phi()
    theta0 = np.array(fitted.theta, float)
    for i in range(len(NAMES)):
        if not space.lower[i] <= theta0[i] <= space.upper[i]:
            raise InputError(None, f"{NAMES[i]} = {theta0[i]:.6g} lies outside its bounds [{space.lower[i]:.6g}, "
                                   f"{space.upper[i]:.6g}] of the model file (estimation.bounds.{NAMES[i]})",
                             f"theta.{NAMES[i]}")
    jac = space.dtheta_dphi(space.to_phi(theta0))
    has_cov = fitted.cov_phi is not None or fitted.cov_theta is not None
    sd = model_sd.copy()
    source = {}
    for j, name in enumerate(space.estimated):
        i = NAMES.index(name)
        fit_sd = fitted.theta_std[i] / jac[i] if (has_cov and name in fitted.estimated) else np.inf
        if walk[j] == 0 and 0 < fit_sd < model_sd[j]:
            sd[j] = fit_sd
            source[name] = "fit"
        else:
            source[name] = "model"
    return theta0, sd, source


REFERENCE_MODEL_ERROR = 0.1
"""Default relative model error of :func:`undeformed_references` (10 % of a point's model displacement)."""

LATE_REFERENCE_FRAMES = 2
"""Frames a held-out point born after the fitted window takes its reference from (:func:`undeformed_references`
``causal_ids``): its first two seen, the fewest a reference takes, so its later measurements never enter."""


def _subset_points(meas: MeasurementSet, idx, frames_x_points: bool = True) -> MeasurementSet:
    """The set restricted to the points ``idx`` (indices into its points), every frame (one copy of its arrays, not
    validated again: :meth:`MeasurementSet._derived`). ``frames_x_points`` false: its positions and covariances
    left as ``meas``'s, for the caller to replace (nothing else may use the set before)."""
    meta = dict(meas.meta)
    for key in ("reference_frame_index", "reference_uv"):
        if key in meta:
            meta[key] = [meta[key][i] for i in idx]
    if not frames_x_points:
        return MeasurementSet._derived(meas, point_ids=meas.point_ids[idx], reference=meas.reference[idx],
                                       views=meas.views[:, idx], reprojection_rms=meas.reprojection_rms[:, idx],
                                       meta=meta, check=False)
    return MeasurementSet._derived(
        meas, point_ids=meas.point_ids[idx], positions=meas.positions[:, idx], covariances=meas.covariances[:, idx],
        reference=meas.reference[idx], views=meas.views[:, idx], reprojection_rms=meas.reprojection_rms[:, idx],
        meta=meta)


def _observed_motion(model, meas, keep, offsets, theta, kw, field=None) -> tuple:
    """The rigid motion per frame that the points ``keep`` with known offsets show under the model (its inputs and
    centring in ``kw``), from their measured position minus offset minus model displacement by generalised least
    squares: ``(translation (K, 3), field (K, n - 1, 3))``.

    Without ``field`` (``None``, or a block of degree 0) the translation is the residuals' weighted mean and the
    field is empty (n = 1). With ``field`` (an :class:`tracker.unknown_input.InputBlock` of degree d > 0) the
    frame's residuals are fitted by the block's displacement field (:func:`tracker.unknown_input.field_basis` at
    each point's offset, as the estimators evaluate it, with the block's centre, axes and scale), the constant
    monomial's coefficients being the translation. A frame with fewer points than twice the monomials, or whose
    points do not determine the field, keeps the previous frame's non-constant coefficients (zero before the
    first) and fits the translation alone. Frames where none is seen take ``kw['translation']`` (the block's
    expectation) and the previous frame's field."""
    from .unknown_input import field_basis

    # the points ``keep`` placed as a set of them alone places them (locate_points reads the references: one frame of
    # them suffices), their frames x points arrays then taken from ``meas`` itself (no copy of them for a subset)
    keep = np.asarray(keep)
    placed = locate_points(model, _subset_points(first_frames(meas, 1), keep))
    pts = ObservedPoints(keep[placed.keep], placed.observation, keep[placed.dropped])
    win = FitProblem(model, meas, None, points=pts, inputs=kw["inputs"], translation=np.zeros((meas.n_frames, 3)),
                     centring=kw.get("centring"))
    in_keep = np.zeros(meas.n_points, np.int64)
    in_keep[keep] = np.arange(keep.size)
    used = in_keep[win.keep]    # win.keep indexes meas; offsets follow keep
    r = win.y - np.asarray(offsets)[used][win._point_idx] - win.displacements(np.asarray(theta, float))[win.seen]
    K = meas.n_frames
    degree = 0 if field is None else int(field.field_degree)
    if degree:
        # at the points' offsets, where the estimators evaluate the field (InputBlock.motion_maps of the references)
        phi = field_basis(np.asarray(offsets)[used], degree, field.field_centre, field.field_axes,
                          field.field_scale)[win._point_idx]
    else:
        phi = np.ones((r.shape[0], 1))
    n = phi.shape[1]
    trans = np.array(kw["translation"], float)
    coef = np.zeros((K, n - 1, 3))
    RinvR = np.einsum("nij,nj->ni", win._R_inv, r)
    counts = np.bincount(win._frame_idx, minlength=K)
    order = np.argsort(win._frame_idx, kind="stable")
    bounds = np.r_[0, np.cumsum(counts)]
    for k in range(K):
        rows = order[bounds[k]:bounds[k + 1]]
        if k and n > 1:
            coef[k] = coef[k - 1]
        if rows.size == 0:
            continue
        if n > 1 and rows.size >= 2 * n:
            # (Φ ⊗ I3)ᵀ R⁻¹ (Φ ⊗ I3) and (Φ ⊗ I3)ᵀ R⁻¹ r, the unknowns ordered [c_1 (3) | c_2 (3) | ...]
            N = np.einsum("na,nij,nb->aibj", phi[rows], win._R_inv[rows], phi[rows]).reshape(3 * n, 3 * n)
            b = np.einsum("na,ni->ai", phi[rows], RinvR[rows]).reshape(3 * n)
            if np.linalg.cond(N) < 1e12:
                c = np.linalg.solve(N, b).reshape(n, 3)
                trans[k] = c[0]
                coef[k] = c[1:]
                continue
        # the translation alone, under the frame's field beyond it
        rk = RinvR[rows] - np.einsum("nij,nj->ni", win._R_inv[rows], np.einsum("na,ai->ni", phi[rows, 1:], coef[k]))
        trans[k] = np.linalg.solve(win._R_inv[rows].sum(axis=0), rk.sum(axis=0))
    return trans, coef


def undeformed_references(model: PatchModel, meas: MeasurementSet, theta, frames: int | None = None,
                          relative_model_error: float = REFERENCE_MODEL_ERROR, input_block=None,
                          causal_ids=None) -> MeasurementSet:
    """The measurement set with each point's ``reference`` replaced by its undeformed position at ``theta``.

    A measured point's reference (``heartcv measure``) is its position in the frame it was born in, which is
    already deformed by the load of that frame; the estimators take the reference as the undeformed offset of
    the point, so a birth-frame reference is a constant error the state or the parameters would have to
    explain (the GE then drives E to its bound). The undeformed positions are the per-point offsets that the
    fit profiles out (:meth:`FitProblem.offsets`: generalised least squares of each point's measured minus
    model displacement over the first ``frames`` frames), here with a model-error term in the weights
    (``relative_model_error``, :meth:`FitProblem.offsets`): the fitted theta is a constant that cannot follow a
    stiffness that changes over the cycle, and with the plain weights its error at the large displacements of
    systole would shift every undeformed position, which the GE then explains at rest by a drifting E.

    Points born after that window (seen in fewer than two of its frames; for instance after a respiration shift or
    an instrument that uncovered them) get their offsets the same way from every frame they are seen in, with the
    same deterministic model states continued over the whole sequence, so that their reference error has the same
    structure as the others' (the span the reference states of :mod:`tracker.reference` correct). Points off the
    patch or seen in fewer than two frames of the whole sequence are dropped; ``meta['dropped_points']`` lists
    their ids and ``meta['late_points']`` those whose offsets came from after the window.

    With an ``input_block`` (a recording without pressure, :mod:`tracker.unknown_input`) the window's offsets are
    those of :class:`UnknownInputProblem` (input and rigid motion profiled, no model-error weighting) and the late
    points' those under the block's mean input continued over the sequence and the rigid translation that the
    window's points show in each frame (:func:`_observed_motion`; with a displacement field, the field they show, taken
    off the late points' positions), not one extrapolated from the window.

    ``causal_ids``: point ids whose late references come from their first :data:`LATE_REFERENCE_FRAMES` seen frames
    only (``heartcv track --holdout``'s held-out tracks, whose measurements must not enter after those; every other
    late point keeps all its frames, which predict the rendered scenes' few late points better).
    """
    return UndeformedReferences(model, meas, theta, frames, relative_model_error, input_block).apply(causal_ids)


class UndeformedReferences:
    """:func:`undeformed_references` in two steps: what does not depend on ``causal_ids`` once (the fitted window's
    offsets, the late points' candidates and, with an ``input_block``, the rigid motion the window's points show),
    then the set for any ``causal_ids`` (:meth:`apply`, as often as needed: ``heartcv track --holdout`` takes the
    references of all frames, then its held-out late tracks' causal ones). The parameters are those of
    :func:`undeformed_references`."""

    def __init__(self, model: PatchModel, meas: MeasurementSet, theta, frames: int | None = None,
                 relative_model_error: float = REFERENCE_MODEL_ERROR, input_block=None):
        late_kw = {}
        if input_block is None:
            prob = FitProblem(model, meas, frames)
        else:
            from .unknown_input import known_inputs

            prob = UnknownInputProblem(model, meas, input_block.frequency_hz, input_block.harmonics,
                                       input_block.column, frames, centred=input_block.centred)
            late_kw = {"inputs": known_inputs(meas, model, input_block) + input_block.mean_inputs(meas.n_frames),
                       "translation": input_block.mean_translation(meas.n_frames), "centring": prob.centring}
        self.model, self.meas, self.theta, self.input_block = model, meas, theta, input_block
        self.relative_model_error = relative_model_error
        self.frames = prob.frames
        self.keep = prob.keep
        self.offsets = prob.offsets(np.asarray(theta, float), relative_model_error)
        self.candidates = np.zeros(0, np.int64)
        self.coef = None
        if prob.frames < meas.n_frames:
            candidates = np.setdiff1d(locate_points(model, meas).keep, self.keep)
            seen = np.isfinite(meas.positions[:, candidates, 0]).sum(axis=0) >= 2
            self.candidates = candidates[seen]
            if self.candidates.size and late_kw:
                # the rigid motion that the window's points show in each frame: its translation, and for a field
                # its part beyond the translation at each late point (taken off the late points' positions)
                late_kw["translation"], self.coef = _observed_motion(model, meas, self.keep, self.offsets, theta,
                                                                     late_kw, input_block)
        self.late_kw = late_kw
        self._last = None   # (keep, the arrays of meas taken at keep) of the last apply

    def apply(self, causal_ids=None) -> MeasurementSet:
        """The measurement set with the undeformed references (``causal_ids``: :func:`undeformed_references`). The
        frames x points arrays of an earlier result with the same points are shared, not taken again."""
        model, meas, theta, input_block = self.model, self.meas, self.theta, self.input_block
        relative_model_error, late_kw, candidates = self.relative_model_error, self.late_kw, self.candidates
        keep, offsets = self.keep, self.offsets
        late = np.zeros(0, np.int64)
        if candidates.size:
            sub = _subset_points(meas, candidates, frames_x_points=False)
            causal = np.isin(sub.point_ids, np.asarray([] if causal_ids is None else causal_ids, np.int64))
            if causal.any():
                # their frames x points arrays gathered once, C-ordered, and written: the causal points' after
                # their first frames are unseen
                pos, cov = np.take(meas.positions, candidates, axis=1), np.take(meas.covariances, candidates, axis=1)
                seen_so_far = np.cumsum(np.isfinite(pos[..., 0]), axis=0)
                after = (seen_so_far > LATE_REFERENCE_FRAMES) & causal[None, :]
                pos[after], cov[after] = np.nan, np.nan
            else:
                pos, cov = meas.positions[:, candidates], meas.covariances[:, candidates]
            sub = MeasurementSet._derived(sub, positions=pos, covariances=cov)
            if late_kw and self.coef.shape[1]:
                from .unknown_input import field_basis

                coef = self.coef
                # near the offsets being computed: the positions less the translation, over the frames used
                lever = np.nanmedian(sub.positions - late_kw["translation"][:, None, :], axis=0)  # (P_late, 3)
                phi = field_basis(np.nan_to_num(lever), input_block.field_degree, input_block.field_centre,
                                  input_block.field_axes, input_block.field_scale)[:, 1:]  # (P_late, n - 1)
                sub = MeasurementSet._derived(sub, positions=sub.positions - np.einsum("pa,kai->kpi", phi, coef))
            late_prob = FitProblem(model, sub, None, **late_kw)
            late = candidates[late_prob.keep]
            late_off = late_prob.offsets(np.asarray(theta, float), relative_model_error)
            order = np.argsort(np.r_[keep, late], kind="stable")
            keep = np.r_[keep, late][order]
            offsets = np.concatenate([offsets, late_off])[order]
        meta = dict(meas.meta)
        if "reference_frame_index" in meta:
            meta["reference_frame_index"] = [meta["reference_frame_index"][i] for i in keep]
        meta["reference"] = (f"undeformed: heartcv fit offsets over the first {self.frames} frames, relative model "
                             f"error {relative_model_error:g}"
                             + (f"; {late.size} points born later over all their frames" if late.size else ""))
        dropped = np.setdiff1d(np.arange(meas.n_points), keep)
        meta["dropped_points"] = [int(i) for i in np.asarray(meas.point_ids)[dropped]]
        meta["late_points"] = [int(i) for i in np.asarray(meas.point_ids)[late]]
        if self._last is not None and np.array_equal(self._last[0], keep):
            taken = self._last[1]
        else:
            taken = {"point_ids": meas.point_ids[keep], "positions": meas.positions[:, keep],
                     "covariances": meas.covariances[:, keep], "views": meas.views[:, keep],
                     "reprojection_rms": meas.reprojection_rms[:, keep]}
        out = MeasurementSet._derived(meas, reference=offsets, meta=meta, **taken)
        self._last = (keep, {name: getattr(out, name) for name in taken})
        return out


def causal_heldout_selection(model: PatchModel, meas: MeasurementSet, causal: MeasurementSet, heldout, late):
    """Combine a run's points (``meas``, references from all frames) with the same points whose held-out late tracks
    ``late`` (ids) took causal references (``causal``, :func:`undeformed_references` with ``causal_ids=late``).

    A late track whose causal reference puts it off the patch where all its frames put it on (or the reverse) has no
    causal reference to be predicted from: it is left out. Returns ``(meas, heldout, kept, left_out)`` (the causal
    set without those tracks, the held-out indices into it, the late ids kept and those left out), or None when
    tracks other than ``late`` would move on or off the patch (the references do not depend on them, so it is not
    expected; the caller then keeps ``meas``)."""
    late = np.asarray(late, np.int64)
    before = np.asarray(meas.point_ids)[locate_points(model, meas).keep]
    after = np.asarray(causal.point_ids)[locate_points(model, causal).keep]
    moved = np.setxor1d(before, after)
    if np.setdiff1d(moved, late).size:
        return None
    if moved.size:
        causal = _subset_points(causal, np.flatnonzero(~np.isin(causal.point_ids, moved)))
    held_ids = np.setdiff1d(np.asarray(meas.point_ids)[heldout], moved)
    return causal, np.flatnonzero(np.isin(causal.point_ids, held_ids)), np.setdiff1d(late, moved), moved
