"""Joint refinement (bundle adjustment) of a camera rig and the board poses it observed.

Unknowns: every camera's ``fx, fy, cx, cy`` and distortion coefficients, ``cam_from_rig`` of cameras 1..N-1
(camera 0 is the rig frame: its pose is fixed at the identity, which removes the gauge freedom), and every
view's ``rig_from_board``. The residuals are the reprojection errors of the board corners (px):
``project_c(cam_from_rig_c rig_from_board_v X_k) - uv``.

Solver: Levenberg-Marquardt on the normal equations with the board poses eliminated by the Schur complement
(Triggs et al. [1]_ §6; Marquardt's diagonal damping ``H + lambda diag(H)``). Each step solves the reduced
camera system (a few dozen unknowns) exactly, which converges in a handful of iterations even where the
distortion coefficients are nearly unobservable (narrow fields of view); ``scipy.optimize.least_squares``
with a sparse Jacobian structure solves its trust-region steps with LSMR, which needed over 10 000 LSMR
iterations per step on the paper's rig (20 s), or, with default tolerances, did not converge. The Jacobian is
exact: complex-step derivatives ([2]_), one complex evaluation per parameter *kind* (all cameras' ``fx`` at
once, all views' first rotation component at once, ...), as the blocks never share a residual row.

Some camera parameters can be held (``free``: a mask over the camera block) and intrinsics can carry Gaussian
priors (``prior_mean``, ``prior_sigma``: a term ``((x - mean) / sigma)^2`` added to the cost per parameter), and
observations can be weighted (``RigProblem(weights=...)``: the cost is ``sum_m w_m |r_m|^2``); the calibration uses
these to keep what the views do not determine out of the fit (heartcv.calibration_rig).

Rotations are refined as left increments ``R = exp([w]x) R0`` with ``R0`` re-centred after each accepted step,
so the Jacobian is always taken at ``w = 0``. Covariance of the camera parameters: ``sigma^2 S^-1`` at the
solution, ``S`` the undamped Schur complement (the marginal of ``sigma^2 (J^T J)^-1``) and
``sigma^2 = |r|^2 / (2 M - n_params)``.

References
----------
.. [1] Triggs, McLauchlan, Hartley, Fitzgibbon, "Bundle adjustment -- a modern synthesis", Vision Algorithms:
   Theory and Practice, LNCS 1883, 2000.
.. [2] Martins, Sturdza, Alonso, "The complex-step derivative approximation", ACM TOMS 29(3), 2003.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import distort_normalised

__all__ = ["RigProblem", "BundleResult", "bundle_adjust", "rotvec_to_matrix"]

_H = 1e-20  # complex step


def rotvec_to_matrix(w) -> np.ndarray:
    """Rodrigues' formula for rotation vectors (..., 3) -> (..., 3, 3); exact for complex input (complex
    step), with a series near 0."""
    w = np.asarray(w)
    th2 = np.sum(w * w, axis=-1)
    small = np.abs(th2) < 1e-8
    th2s = np.where(small, 1.0, th2)
    th = np.sqrt(th2s)
    a = np.where(small, 1 - th2 / 6 + th2 * th2 / 120, np.sin(th) / th)
    b = np.where(small, 0.5 - th2 / 24 + th2 * th2 / 720, (1 - np.cos(th)) / th2s)
    z = np.zeros_like(w[..., 0])
    Kx = np.stack([np.stack([z, -w[..., 2], w[..., 1]], -1),
                   np.stack([w[..., 2], z, -w[..., 0]], -1),
                   np.stack([-w[..., 1], w[..., 0], z], -1)], -2)
    return np.eye(3) + a[..., None, None] * Kx + b[..., None, None] * (Kx @ Kx)


@dataclass
class _State:
    intr: np.ndarray   # (C, ni): fx, fy, cx, cy, dist...
    Rc: np.ndarray     # (C, 3, 3) cam_from_rig rotations (Rc[0] = I)
    tc: np.ndarray     # (C, 3)
    Rv: np.ndarray     # (V, 3, 3) rig_from_board rotations
    tv: np.ndarray     # (V, 3)

    def moved(self, d_intr, d_cam, d_view) -> "_State":
        Rc, tc = self.Rc.copy(), self.tc.copy()
        Rc[1:] = rotvec_to_matrix(d_cam[:, :3]) @ Rc[1:]
        tc[1:] += d_cam[:, 3:]
        return _State(self.intr + d_intr, Rc, tc, rotvec_to_matrix(d_view[:, :3]) @ self.Rv, self.tv + d_view[:, 3:])


@dataclass(frozen=True)
class BundleResult:
    """Refined rig and board poses.

    Attributes
    ----------
    intrinsics : ndarray of shape (n_cam, 4 + n_dist)
        ``fx, fy, cx, cy, dist...`` per camera.
    cam_from_rig : ndarray of shape (n_cam, 4, 4)
    rig_from_board : ndarray of shape (n_view, 4, 4)
    residuals : ndarray of shape (M, 2)
        Reprojection errors (px) of the observations, in the problem's order.
    cov_cameras : ndarray of shape (n_cam_params, n_cam_params)
        Covariance of ``[intrinsics of every camera | (w, t) of cameras 1..]`` (w: rotation vector, rad).
    sigma2 : float
        Residual variance per coordinate (px^2).
    iterations : int
    converged : bool
    """

    intrinsics: np.ndarray
    cam_from_rig: np.ndarray
    rig_from_board: np.ndarray
    residuals: np.ndarray
    cov_cameras: np.ndarray
    sigma2: float
    iterations: int
    converged: bool


class RigProblem:
    """Observations of a bundle adjustment: observation ``m`` is corner ``X[m]`` (board frame, m) of view
    ``obs_view[m]`` seen by camera ``obs_cam[m]`` at pixel ``uv[m]``."""

    def __init__(self, obs_cam, obs_view, X, uv, n_cam, n_view, n_dist, weights=None):
        self.obs_cam = np.asarray(obs_cam, np.int64)
        self.obs_view = np.asarray(obs_view, np.int64)
        self.X, self.uv = np.asarray(X, float), np.asarray(uv, float)
        M = self.obs_cam.size
        if self.obs_view.shape != (M,) or self.X.shape != (M, 3) or self.uv.shape != (M, 2):
            raise ValueError(f"observations: obs_cam, obs_view (M,), X (M, 3), uv (M, 2) expected with M = {M}")
        self.weights = np.ones(M) if weights is None else np.asarray(weights, float)
        if self.weights.shape != (M,) or not (np.isfinite(self.weights).all() and (self.weights > 0).all()):
            raise ValueError(f"weights: positive finite (M,) = ({M},) expected")
        self.n_cam, self.n_view, self.n_dist = int(n_cam), int(n_view), int(n_dist)
        self.ni = 4 + self.n_dist
        self.n_cam_params = self.n_cam * self.ni + 6 * (self.n_cam - 1)
        self.n_params = self.n_cam_params + 6 * self.n_view
        self._cam_masks = [self.obs_cam == c for c in range(self.n_cam)]

    def residuals(self, s: _State, d_intr=None, d_cam=None, d_view=None) -> np.ndarray:
        """Reprojection errors (M, 2) at ``s`` moved by optional (complex) increments."""
        intr, Rc, tc, Rv, tv = s.intr, s.Rc, s.tc, s.Rv, s.tv
        if d_intr is not None:
            intr = intr + d_intr
        if d_cam is not None:
            Rc = np.concatenate([Rc[:1], rotvec_to_matrix(d_cam[:, :3]) @ Rc[1:]])
            tc = np.concatenate([tc[:1], tc[1:] + d_cam[:, 3:]])
        if d_view is not None:
            Rv = rotvec_to_matrix(d_view[:, :3]) @ Rv
            tv = tv + d_view[:, 3:]
        v, c = self.obs_view, self.obs_cam
        Xr = np.einsum("mij,mj->mi", Rv[v], self.X) + tv[v]
        Xc = np.einsum("mij,mj->mi", Rc[c], Xr) + tc[c]
        xy = Xc[:, :2] / Xc[:, 2:]
        out = np.empty(xy.shape, np.result_type(xy, intr))
        for k, m in enumerate(self._cam_masks):
            xd = distort_normalised(xy[m], intr[k, 4:])
            out[m, 0] = intr[k, 0] * xd[:, 0] + intr[k, 2]
            out[m, 1] = intr[k, 1] * xd[:, 1] + intr[k, 3]
        return out - self.uv

    def jacobian(self, s: _State):
        """Exact Jacobian blocks of the residuals (M, 2) by complex step: ``J_intr`` (M, 2, ni) w.r.t. the
        observing camera's intrinsics, ``J_cam`` (M, 2, 6) w.r.t. its pose increment (zero for camera 0) and
        ``J_view`` (M, 2, 6) w.r.t. the view's pose increment."""
        C, V, ni = self.n_cam, self.n_view, self.ni
        J_intr = np.empty((self.obs_cam.size, 2, ni))
        for k in range(ni):
            d = np.zeros((C, ni), complex)
            d[:, k] = 1j * _H
            J_intr[:, :, k] = self.residuals(s, d_intr=d).imag / _H
        J_cam = np.zeros((self.obs_cam.size, 2, 6))
        if C > 1:
            for k in range(6):
                d = np.zeros((C - 1, 6), complex)
                d[:, k] = 1j * _H
                J_cam[:, :, k] = self.residuals(s, d_cam=d).imag / _H
        J_view = np.empty((self.obs_cam.size, 2, 6))
        for k in range(6):
            d = np.zeros((V, 6), complex)
            d[:, k] = 1j * _H
            J_view[:, :, k] = self.residuals(s, d_view=d).imag / _H
        return J_intr, J_cam, J_view

    # -- normal equations ------------------------------------------------------------------------------------
    def _cam_index(self, c) -> np.ndarray:
        """Columns of camera c's parameters in the camera block."""
        idx = np.arange(c * self.ni, (c + 1) * self.ni)
        if c > 0:
            idx = np.concatenate([idx, self.n_cam * self.ni + 6 * (c - 1) + np.arange(6)])
        return idx

    def normal_equations(self, s: _State, r=None):
        """``U`` (nc, nc), ``W`` (nc, V, 6), ``Vb`` (V, 6, 6), ``gc`` (nc,), ``gv`` (V, 6) of ``J^T J`` and
        ``J^T r`` with the camera block first."""
        r = self.residuals(s) if r is None else r
        J_intr, J_cam, J_view = self.jacobian(s)
        sw = np.sqrt(self.weights)[:, None]
        r = r * sw
        J_intr, J_cam, J_view = J_intr * sw[..., None], J_cam * sw[..., None], J_view * sw[..., None]
        V, nc = self.n_view, self.n_cam_params
        U = np.zeros((nc, nc))
        W = np.zeros((nc, V, 6))
        gc = np.zeros(nc)
        for c, m in enumerate(self._cam_masks):
            A = J_intr[m] if c == 0 else np.concatenate([J_intr[m], J_cam[m]], axis=2)  # (Mc, 2, p)
            idx = self._cam_index(c)
            U[np.ix_(idx, idx)] += np.einsum("mip,miq->pq", A, A)
            gc[idx] += np.einsum("mip,mi->p", A, r[m])
            outer = np.einsum("mip,miq->mpq", A, J_view[m]).reshape(A.shape[0], -1)
            views = self.obs_view[m]
            blk = np.stack([np.bincount(views, outer[:, j], V) for j in range(outer.shape[1])], axis=1)
            W[idx] += blk.reshape(V, len(idx), 6).transpose(1, 0, 2)
        outer = np.einsum("mip,miq->mpq", J_view, J_view).reshape(-1, 36)
        Vb = np.stack([np.bincount(self.obs_view, outer[:, j], V) for j in range(36)], axis=1).reshape(V, 6, 6)
        gv_flat = np.einsum("mip,mi->mp", J_view, r)
        gv = np.stack([np.bincount(self.obs_view, gv_flat[:, j], V) for j in range(6)], axis=1)
        return U, W, Vb, gc, gv

    def n_residuals(self) -> int:
        return 2 * self.obs_cam.size

    def cost(self, r) -> float:
        """Weighted sum of squared residuals (M, 2)."""
        return float((self.weights[:, None] * np.asarray(r) ** 2).sum())


def _schur_solve(U, W, Vb, gc, gv, lam):
    """Solve ``(H + lam diag(H)) d = -g`` by eliminating the view blocks; also returns the (damped) Schur
    complement."""
    Ud = U + lam * np.diag(np.diag(U))
    Vd = Vb + lam * np.einsum("vii->vi", Vb)[:, :, None] * np.eye(6)
    Vinv = np.linalg.inv(Vd)
    WV = np.einsum("cvk,vkl->cvl", W, Vinv)
    S = Ud - np.einsum("cvl,dvl->cd", WV, W)
    rhs = -gc + np.einsum("cvl,vl->c", WV, gv)
    dc = np.linalg.solve(S, rhs)
    dv = np.einsum("vkl,vl->vk", Vinv, -gv - np.einsum("cvk,c->vk", W, dc))
    return dc, dv, S


def bundle_adjust(problem: RigProblem, intrinsics, cam_from_rig, rig_from_board, *, free=None, prior_mean=None,
                  prior_sigma=None, consider_sigma=None, max_iterations=100, rtol=1e-12) -> BundleResult:
    """Levenberg-Marquardt with Schur complement (module docstring).

    Parameters
    ----------
    problem : RigProblem
    intrinsics : ndarray of shape (n_cam, 4 + n_dist)
    cam_from_rig : ndarray of shape (n_cam, 4, 4)
        Start; ``cam_from_rig[0]`` is kept as it is (the identity for a rig in camera 0's frame).
    rig_from_board : ndarray of shape (n_view, 4, 4)
    free : ndarray of shape (n_cam_params,), bool, optional
        Camera-block parameters refined (``[intrinsics of every camera | (w, t) of cameras 1..]``); the others keep
        their start values. Default: all.
    prior_mean, prior_sigma : ndarray of shape (n_cam, 4 + n_dist), optional
        Gaussian priors on the intrinsics; ``prior_sigma = inf`` where there is none.
    consider_sigma : ndarray of shape (n_cam, 4 + n_dist), optional
        Uncertainty of held intrinsics (finite entries of held parameters): their effect on the estimated
        parameters is added to the covariance ("consider" covariance: ``G diag(sigma^2) G^T`` with
        ``G = S_ee^-1 S_eh`` from the Schur complement over estimated and considered parameters), so holding a
        parameter at a value that is only roughly known does not make the others look more certain.
    max_iterations : int
    rtol : float
        Converged when an accepted step lowers the cost by less than ``rtol`` times the cost.

    Returns
    -------
    BundleResult
        ``cov_cameras`` is zero in the rows and columns of held parameters; ``sigma2`` is the weighted data cost
        over ``2 M - n_free`` (priors not counted).

    Raises
    ------
    numpy.linalg.LinAlgError
        The reduced camera system is singular (a camera or view without constraints).
    """
    C, V, ni = problem.n_cam, problem.n_view, problem.ni
    nc = problem.n_cam_params
    free = np.ones(nc, bool) if free is None else np.asarray(free, bool).reshape(nc)
    fidx = np.flatnonzero(free)
    if prior_sigma is None:
        p_mean, p_info = np.zeros(nc), np.zeros(nc)
    else:
        sig = np.asarray(prior_sigma, float).reshape(C * ni)
        p_mean = np.r_[np.asarray(prior_mean, float).reshape(C * ni), np.zeros(nc - C * ni)]
        p_info = np.r_[np.where(np.isfinite(sig), 1.0 / np.where(np.isfinite(sig), sig, 1.0) ** 2, 0.0),
                       np.zeros(nc - C * ni)]

    def x_cam(st):
        return np.r_[st.intr.reshape(-1), np.zeros(nc - C * ni)]

    def total_cost(st, r):
        d = x_cam(st) - p_mean
        return problem.cost(r) + float((p_info * d * d).sum())

    s = _State(np.array(intrinsics, float).reshape(C, ni), np.array(cam_from_rig)[:, :3, :3].copy(),
               np.array(cam_from_rig)[:, :3, 3].copy(), np.array(rig_from_board)[:, :3, :3].copy(),
               np.array(rig_from_board)[:, :3, 3].copy())

    def system(st, r):
        U, W, Vb, gc, gv = problem.normal_equations(st, r)
        U = U + np.diag(p_info)
        gc = gc + p_info * (x_cam(st) - p_mean)
        return U[np.ix_(fidx, fidx)], W[fidx], Vb, gc[fidx], gv

    r = problem.residuals(s)
    cost = total_cost(s, r)
    lam, converged, it = 1e-4, False, 0
    while it < max_iterations and not converged:
        it += 1
        U, W, Vb, gc, gv = system(s, r)
        while True:
            dcf, dv, _ = _schur_solve(U, W, Vb, gc, gv, lam)
            dc = np.zeros(nc)
            dc[fidx] = dcf
            d_intr = dc[:C * ni].reshape(C, ni)
            d_cam = dc[C * ni:].reshape(C - 1, 6)
            trial = s.moved(d_intr, d_cam, dv)
            r_new = problem.residuals(trial)
            cost_new = total_cost(trial, r_new)
            if np.isfinite(cost_new) and cost_new <= cost:
                converged = cost - cost_new <= rtol * cost
                s, r, cost = trial, r_new, cost_new
                lam = max(lam / 5, 1e-12)
                break
            lam *= 8
            if lam > 1e12:  # no step lowers the cost: at the minimum to machine precision
                converged = True
                break
    sigma2 = problem.cost(r) / max(problem.n_residuals() - fidx.size - 6 * V, 1)
    cons = np.zeros(nc, bool)
    if consider_sigma is not None:
        cs = np.r_[np.asarray(consider_sigma, float).reshape(C * ni), np.full(nc - C * ni, np.nan)]
        cons = ~free & np.isfinite(cs) & (np.nan_to_num(cs) > 0)
    fidx_saved = fidx
    fidx = np.flatnonzero(free | cons)
    U, W, Vb, gc, gv = system(s, r)
    _, _, S_all = _schur_solve(U, W, Vb, gc, gv, 0.0)
    fidx = fidx_saved
    e = np.flatnonzero(free[free | cons])
    h = np.flatnonzero(cons[free | cons])
    S = S_all[np.ix_(e, e)]
    cov = np.zeros((nc, nc))
    cov_e = sigma2 * np.linalg.inv(S)
    if h.size:
        G = np.linalg.solve(S, S_all[np.ix_(e, h)])
        cov_e = cov_e + G @ np.diag(cs[cons] ** 2) @ G.T
    cov[np.ix_(fidx, fidx)] = cov_e
    T_c = np.tile(np.eye(4), (C, 1, 1))
    T_c[:, :3, :3], T_c[:, :3, 3] = s.Rc, s.tc
    T_v = np.tile(np.eye(4), (V, 1, 1))
    T_v[:, :3, :3], T_v[:, :3, 3] = s.Rv, s.tv
    return BundleResult(s.intr.copy(), T_c, T_v, r, cov, sigma2, it, converged)
