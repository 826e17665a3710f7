"""Multi-view triangulation of pixel observations through the full camera model, with covariances.

For every point seen by two or more cameras of a rig: a linear (DLT) estimate from the undistorted normalised
coordinates, Levenberg-Marquardt refinement of the pixel reprojection error through the full OpenCV distortion
model, the covariance of the result under isotropic pixel noise, quality flags, and optionally a leave-worst-out
rejection of inconsistent views. Everything is vectorised over points (loops run over cameras and iterations).
Also the fundamental matrix of two calibrated cameras and the epipolar distance used by cross-view matching.

References
----------
.. [HZ] R. Hartley and A. Zisserman, *Multiple View Geometry in Computer Vision*, 2nd ed., 2004:
   §12.2 (linear triangulation), §5.2 (covariance propagation), §9.2 and §11.4.3 (fundamental matrix,
   symmetric epipolar distance), §A6 (Levenberg-Marquardt).
.. [HS] R. Hartley and P. Sturm, "Triangulation", CVIU 68(2), 1997 (iterative linear method).
.. [COLMAP] J. L. Schönberger and J.-M. Frahm, "Structure-from-Motion Revisited", CVPR 2016, and
   ``colmap/estimators/triangulation.cc`` (robust multi-view triangulation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from heartcv.camera import Camera, Rig, invert_pose

__all__ = ["Triangulation", "triangulate", "fundamental_matrix", "epipolar_distance"]

_XTOL = 1e-9  # LM stops when |step| <= _XTOL * (|X| + _XTOL): below a nanometre within a metre of the rig


@dataclass(frozen=True)
class Triangulation:
    """Triangulated points of one frame (N points, C cameras).

    Attributes
    ----------
    points : ndarray of shape (N, 3)
        Rig-frame positions (m); NaN where fewer than two views were usable or the rays meet at infinity.
    covariances : ndarray of shape (N, 3, 3)
        ``(sum_c J_c^T J_c / sigma_px^2)^-1`` (m^2) over the used views at the solution, J_c the Jacobian of
        camera c's pixel projection ([HZ] §5.2); NaN where not triangulated.
    reprojection_px : ndarray of shape (N, C)
        Reprojection error norm (px) in every camera that observed the point, used or rejected; NaN where the
        camera did not observe it or the point is behind it.
    rms_px : ndarray of shape (N,)
        RMS of the reprojection error norms over the used views.
    angle_deg : ndarray of shape (N,)
        Largest angle between the observed viewing rays of two used views (triangulation angle).
    used : ndarray of shape (N, C), bool
        Views used in the final solution.
    ok : ndarray of shape (N,), bool
        At least 2 used views, a finite point in front of every used camera, ``rms_px <= max_rms_px`` and
        ``angle_deg >= min_angle_deg``.
    """

    points: np.ndarray
    covariances: np.ndarray
    reprojection_px: np.ndarray
    rms_px: np.ndarray
    angle_deg: np.ndarray
    used: np.ndarray
    ok: np.ndarray

    def __post_init__(self):
        n, c = self.used.shape
        for name, shape in (("points", (n, 3)), ("covariances", (n, 3, 3)), ("reprojection_px", (n, c)),
                            ("rms_px", (n,)), ("angle_deg", (n,)), ("ok", (n,))):
            if getattr(self, name).shape != shape:
                raise ValueError(f"Triangulation.{name}: shape {shape} expected, got {getattr(self, name).shape}")

    @property
    def n_views(self) -> np.ndarray:
        """Number of used views per point (N,)."""
        return self.used.sum(axis=1)


# -- input handling ----------------------------------------------------------------------------------------------
def _as_cameras(cameras) -> tuple:
    cams = tuple(cameras.cameras if isinstance(cameras, Rig) else cameras)
    if not all(isinstance(c, Camera) for c in cams):
        raise ValueError("cameras: a Rig or a sequence of Camera expected")
    if len(cams) < 2:
        raise ValueError(f"cameras: at least 2 cameras needed to triangulate, got {len(cams)}")
    return cams


def _check_uv(uv, n_cam) -> np.ndarray:
    uv = np.asarray(uv, dtype=float)
    if uv.ndim != 3 or uv.shape[1:] != (n_cam, 2):
        raise ValueError(f"uv: shape (N, {n_cam}, 2) expected (pixels, NaN where a camera did not see the "
                         f"point), got {uv.shape}")
    return uv


def _normalised(cams, uv, seen) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates (N, C, 2) of the seen observations (0 elsewhere), and the seen mask
    less observations that could not be undistorted."""
    xy = np.zeros(uv.shape)
    for c, cam in enumerate(cams):
        if seen[:, c].any():
            xy[seen[:, c], c] = cam.undistort_points(uv[seen[:, c], c])
    ok = np.isfinite(xy).all(axis=2)
    return np.where(ok[..., None], xy, 0.0), seen & ok


# -- small batched linear algebra --------------------------------------------------------------------------------
def _inv3(A) -> np.ndarray:
    """Inverses of (n, 3, 3) matrices by the adjugate; NaN (no warning, no exception) where singular."""
    cof = np.empty_like(A)
    for i in range(3):
        for j in range(3):
            r = [k for k in range(3) if k != i]
            s = [k for k in range(3) if k != j]
            cof[:, j, i] = (-1) ** (i + j) * (A[:, r[0], s[0]] * A[:, r[1], s[1]] - A[:, r[0], s[1]] * A[:, r[1], s[0]])
    det = np.einsum("ni,ni->n", A[:, 0, :], cof[:, :, 0])
    good = np.isfinite(det) & (np.abs(det) > 0)
    return np.divide(cof, det[:, None, None], out=np.full_like(A, np.nan), where=good[:, None, None])


# -- the three stages ----------------------------------------------------------------------------------------------
def _linear(cams, xy, used, reweight=1) -> np.ndarray:
    """Homogeneous DLT ([HZ] §12.2) on normalised coordinates, batched over points, then ``reweight`` passes
    of the iterative linear method of [HS]: each view's two rows are scaled by ``f_c / depth_c`` at the
    previous estimate, so that the algebraic error becomes the image-plane error in (undistorted) pixels.
    The first pass normalises every row to unit norm. Returns (N, 3), NaN where the rays meet at infinity."""
    P = np.stack([c.cam_from_rig[:3] for c in cams])                             # (C, 3, 4)
    A = xy[..., None] * P[None, :, 2:3, :] - P[None, :, :2, :]                    # (N, C, 2, 4)
    A = np.where(used[:, :, None, None], A, 0.0)
    norm = np.linalg.norm(A, axis=3, keepdims=True)
    A = np.divide(A, norm, out=np.zeros_like(A), where=norm > 0)
    focal = np.array([np.sqrt(c.K[0, 0] * c.K[1, 1]) for c in cams])
    Xh = None
    for k in range(reweight + 1):
        if k:
            depth = np.abs(np.einsum("cj,nj->nc", P[:, 2], Xh))                   # p3 . X up to the scale of Xh
            w = np.divide(focal, depth, out=np.zeros_like(depth), where=used & (depth > 0))
            w /= np.maximum(w.max(axis=1, keepdims=True), 1e-300)
            Ak = A * w[:, :, None, None]
        else:
            Ak = A
        M = np.einsum("ncki,nckj->nij", Ak, Ak)
        Xh = np.linalg.eigh(M)[1][:, :, 0]                                        # smallest eigenvector
    w = Xh[:, 3]
    finite = np.abs(w) > 1e-12 * np.linalg.norm(Xh[:, :3], axis=1)
    return np.divide(Xh[:, :3], w[:, None], out=np.full((len(Xh), 3), np.nan), where=finite[:, None])


def _evaluate(cams, X, uv, mask):
    """Residuals ``uv - project(X)`` (n, C, 2) and Jacobians of the projection d uv / d X (n, C, 2, 3) in the
    views of ``mask`` (n, C), 0 elsewhere and where the point is behind; depths (n, C), NaN outside ``mask``."""
    n, C = mask.shape
    r = np.zeros((n, C, 2))
    J = np.zeros((n, C, 2, 3))
    depth = np.full((n, C), np.nan)
    for c, cam in enumerate(cams):
        rows = np.flatnonzero(mask[:, c])
        if rows.size == 0:
            continue
        Xc = cam.to_cam(X[rows])
        uv_hat, Jc = cam.project_cam(Xc, jacobian=True)
        depth[rows, c] = Xc[:, 2]
        r[rows, c] = np.nan_to_num(uv[rows, c] - uv_hat)
        J[rows, c] = np.nan_to_num(Jc @ cam.R)
    return r, J, depth


def _cost(r, depth, used):
    """Sum of squared residuals over the used views (n,); inf where a used view is behind its camera."""
    cost = np.einsum("nck,nck->n", r * used[..., None], r)
    return np.where(np.all(~used | (depth > 0), axis=1), cost, np.inf)


def _refine(cams, X, uv, seen, used, iterations, fixed=None):
    """Levenberg-Marquardt ([HZ] §A6) on the pixel reprojection error, one 3x3 system per point, all points
    at once; a point leaves the loop when its step is below ``_XTOL`` relative. Points whose start is behind
    a used camera, and the rows ``fixed`` (already optimal), are left unrefined. Returns X and ``_evaluate`` over
    the seen views at X."""
    X = X.copy()
    finite = np.isfinite(X).all(axis=1)
    mask = seen & finite[:, None]
    r, J, depth = _evaluate(cams, np.where(finite[:, None], X, 0.0), uv, mask)
    if not iterations:
        return X, r, J, depth
    cost = _cost(r, depth, used)
    idx = np.flatnonzero(finite & np.isfinite(cost) & (True if fixed is None else ~fixed))
    lam = np.full(idx.size, 1e-6)
    for _ in range(iterations):
        if idx.size == 0:
            break
        Ju = J[idx] * used[idx][..., None, None]
        H = np.einsum("ncki,nckj->nij", Ju, Ju)
        g = np.einsum("ncki,nck->ni", Ju, r[idx])
        step = np.nan_to_num(np.einsum("nij,nj->ni", _inv3(H + lam[:, None, None] * (np.eye(3) * H)), g))
        X_new = X[idx] + step
        r_new, J_new, d_new = _evaluate(cams, X_new, uv[idx], mask[idx])
        cost_new = _cost(r_new, d_new, used[idx])
        acc = cost_new <= cost[idx]
        rows = idx[acc]
        X[rows], r[rows], J[rows], depth[rows], cost[rows] = X_new[acc], r_new[acc], J_new[acc], d_new[acc], \
            cost_new[acc]
        lam = np.where(acc, lam / 10, lam * 10)
        done = np.linalg.norm(step, axis=1) <= _XTOL * (np.linalg.norm(X[idx], axis=1) + _XTOL)
        keep = ~done & (lam < 1e12)
        idx, lam = idx[keep], lam[keep]
    return X, r, J, depth


def _solve(cams, uv, xy, seen, used, refine, iterations):
    exact = _rectified_optimum(cams, uv, used) if refine else None
    X = np.full((len(uv), 3), np.nan)
    rest = np.ones(len(uv), bool)
    if exact is not None:
        rows, X_exact = exact
        X[rows] = X_exact
        rest[rows] = False
    if rest.any():
        X[rest] = _linear(cams, xy[rest], used[rest])
    X[used.sum(axis=1) < 2] = np.nan
    return _refine(cams, X, uv, seen, used, iterations if refine else 0, fixed=~rest)


def _rectified_pair(cams):
    """(i, j, baseline) when cameras i and j form a rectified pair -- no distortion, the same K with zero skew,
    the same orientation and camera j displaced along camera i's x axis by ``baseline`` > 0 (m), to 1e-12 --
    else None."""
    for i in range(len(cams)):
        for j in range(len(cams)):
            a, b = cams[i], cams[j]
            if i == j or a.dist.any() or b.dist.any() or a.K[0, 1] != 0 or not np.array_equal(a.K, b.K):
                continue
            if np.abs(b.R @ a.R.T - np.eye(3)).max() > 1e-12:
                continue
            d = a.to_cam(b.centre)                       # camera j's centre in camera i's frame
            scale = max(np.linalg.norm(d), 1e-300)
            if d[0] > 0 and abs(d[1]) <= 1e-12 * scale and abs(d[2]) <= 1e-12 * scale:
                return i, j, float(d[0])
    return None


def _rectified_optimum(cams, uv, used):
    """(rows, X (n, 3)) for the points seen in exactly the two views of a rectified pair (:func:`_rectified_pair`):
    the exact minimiser of their pixel reprojection error, in closed form. The three free values of a point are
    its two columns and its common row, so both observations keep their columns and move to the mean of their rows
    (any other split costs more): ``X = b / d (u_i - cx, (v_i + v_j) / 2 - cy, f)`` in camera i's frame, d = u_i -
    u_j the disparity. Points with d <= 0 (at or beyond infinity) are left to the general path. None without a
    rectified pair."""
    pair = _rectified_pair(cams)
    if pair is None:
        return None
    i, j, b = pair
    only = used[:, i] & used[:, j] & (used.sum(axis=1) == 2)
    d = uv[:, i, 0] - uv[:, j, 0]
    rows = np.flatnonzero(only & (d > 0))
    K = cams[i].K
    z = K[0, 0] * b / d[rows]
    v = 0.5 * (uv[rows, i, 1] + uv[rows, j, 1])
    Xc = np.stack([(uv[rows, i, 0] - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    return rows, (Xc - cams[i].t) @ cams[i].R                  # rig frame: R^T (Xc - t)


def _ray_angles(cams, xy, used) -> np.ndarray:
    """Largest angle (deg) between the observed rays of two used views (N,), NaN with fewer than 2."""
    d = np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], axis=2)
    d = np.stack([d[:, c] @ cam.R for c, cam in enumerate(cams)], axis=1)         # R^T d per view, rig frame
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    best = np.full(len(xy), np.nan)
    for a in range(len(cams)):
        for b in range(a + 1, len(cams)):
            ang = np.degrees(np.arccos(np.clip(np.einsum("ni,ni->n", d[:, a], d[:, b]), -1.0, 1.0)))
            best = np.fmax(best, np.where(used[:, a] & used[:, b], ang, np.nan))
    return best


def _leave_one_out(cams, uv, xy, seen, used, refine, iterations):
    """Drop from every point the used view whose removal leaves the smallest reprojection cost (a finite
    cost before an infinite one, i.e. a remaining view the point is behind); returns ``_solve``'s outputs at
    the chosen subset and the new ``used``."""
    trials, outs, costs = [], [], []
    for c in range(len(cams)):
        trial = used.copy()
        trial[:, c] = False
        out = _solve(cams, uv, xy, seen, trial, refine, iterations)
        cost = np.minimum(np.nan_to_num(_cost(out[1], out[3], trial), nan=np.inf), np.finfo(float).max)
        trials.append(trial)
        outs.append(out)
        costs.append(np.where(used[:, c], cost, np.inf))  # an unused view can never be chosen
    pick = np.argmin(np.stack(costs), axis=0)
    rows = np.arange(len(pick))
    return [np.stack(parts)[pick, rows] for parts in zip(*outs)] + [np.stack(trials)[pick, rows]]


def triangulate(cameras, uv, *, sigma_px=0.1, refine=True, iterations=10, max_rms_px=1.0, min_angle_deg=2.0,
                robust=False, outlier_px=2.0) -> Triangulation:
    """Triangulate N points from their pixel observations in C >= 2 calibrated cameras.

    1. Linear estimate: homogeneous DLT ([HZ] §12.2) on undistorted normalised coordinates, rows normalised,
       followed by one pass of the iterative linear method of [HS] (rows weighted by focal length / depth),
       which makes the algebraic error the image-plane error in undistorted pixels. On the paper rig at
       0.1 px noise its RMS 3-D error is 12.143 um against 12.140 um after refinement and 12.147 um for the
       ray midpoint method, which has no such pixel weighting; a second reweighting pass changes nothing.
    2. Levenberg-Marquardt refinement (``refine=True``) of the sum of squared pixel reprojection errors
       through the full distortion model, every point's 3x3 normal equations solved together; a point stops
       when its step falls below 1e-9 of its distance from the rig origin, or after ``iterations``.
    3. Covariance ``(sum_c J_c^T J_c / sigma_px^2)^-1`` at the solution ([HZ] §5.2, result 5.10), J_c the
       exact Jacobian of camera c's projection.
    4. ``robust=True``, leave-worst-out: while a point has >= 3 used views and its worst used view
       reprojects worse than ``outlier_px`` (a view it is behind counts as worst), the point is re-solved
       without each used view in turn and the view whose removal leaves the smallest reprojection cost is
       dropped. (Dropping the view with the largest residual is not enough: the least-squares fit spreads a
       gross error, and with 3 views a good view often carries the largest residual.) This is the exhaustive,
       deterministic counterpart of COLMAP's RANSAC triangulation ([COLMAP],
       ``pycolmap.estimate_triangulation``), affordable for the 3 views of a trinocular rig; like it, it
       cannot tell which view is wrong when the error lies along the epipolar line of the other two.

    Parameters
    ----------
    cameras : Rig or sequence of Camera, length C >= 2
    uv : array_like of shape (N, C, 2)
        Pixel observations (OpenCV convention), NaN where camera c did not see point n.
    sigma_px : float
        Standard deviation of the pixel noise per coordinate, for the covariances.
    refine : bool
        Run step 2 (otherwise the linear estimate is returned, with its covariance and errors).
    iterations : int
        Maximum LM iterations.
    max_rms_px, min_angle_deg : float
        Quality thresholds for ``ok``.
    robust : bool
        Run step 4 with threshold ``outlier_px`` (pixels).

    Returns
    -------
    Triangulation
    """
    cams = _as_cameras(cameras)
    uv = _check_uv(uv, len(cams))
    if not sigma_px > 0 or not outlier_px > 0 or int(iterations) != iterations or iterations < 0:
        raise ValueError(f"sigma_px and outlier_px must be > 0 and iterations a non-negative integer, got "
                         f"{sigma_px}, {outlier_px}, {iterations}")
    seen = np.isfinite(uv).all(axis=2)
    xy, used = _normalised(cams, uv, seen)
    X, r, J, depth = _solve(cams, uv, xy, seen, used, refine, iterations)
    while robust:
        err = np.where(used, np.linalg.norm(r, axis=2), -1.0)
        err[used & ~(depth > 0)] = np.inf
        redo = np.isfinite(X).all(axis=1) & (used.sum(axis=1) >= 3) & (err.max(axis=1) > outlier_px)
        if not redo.any():
            break
        rows = np.flatnonzero(redo)
        X[rows], r[rows], J[rows], depth[rows], used[rows] = _leave_one_out(cams, uv[rows], xy[rows], seen[rows],
                                                                            used[rows], refine, iterations)
    return _summarise(X, r, J, depth, xy, cams, seen, used, sigma_px, max_rms_px, min_angle_deg)


def _summarise(X, r, J, depth, xy, cams, seen, used, sigma_px, max_rms_px, min_angle_deg) -> Triangulation:
    n = len(X)
    finite = np.isfinite(X).all(axis=1)
    front = depth > 0
    reproj = np.where(seen & finite[:, None] & front, np.linalg.norm(r, axis=2), np.nan)
    n_used = used.sum(axis=1)
    valid = finite & (n_used >= 2)
    all_front = np.all(~used | front, axis=1)
    ss = np.einsum("nck,nck->n", r * used[..., None], r)
    rms = np.sqrt(np.divide(ss, n_used, out=np.full(n, np.nan), where=valid & all_front))
    Ju = J * used[..., None, None]
    cov = _inv3(np.einsum("ncki,nckj->nij", Ju, Ju) / sigma_px ** 2)
    cov[~valid] = np.nan
    angle = _ray_angles(cams, xy, used)
    with np.errstate(invalid="ignore"):
        ok = valid & all_front & (rms <= max_rms_px) & (angle >= min_angle_deg)
    return Triangulation(X, cov, reproj, rms, angle, used, ok)


# -- epipolar geometry ------------------------------------------------------------------------------------------
def fundamental_matrix(cam_a: Camera, cam_b: Camera) -> np.ndarray:
    """Fundamental matrix (3, 3) ``F = K_b^-T [t]_x R K_a^-1`` with ``(R, t)`` = cam_b_from_cam_a, so that
    ``p_b^T F p_a = 0`` for *undistorted* homogeneous pixels ``p = K [x, y, 1]`` of one point ([HZ] §9.6)."""
    T = cam_b.cam_from_rig @ invert_pose(cam_a.cam_from_rig)
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return np.linalg.inv(cam_b.K).T @ tx @ R @ np.linalg.inv(cam_a.K)


def _undistorted_pixels(cam, uv) -> np.ndarray:
    uv = np.asarray(uv, dtype=float)
    if uv.shape[-1:] != (2,):
        raise ValueError(f"{cam.name}: pixel coordinates of shape (..., 2) expected, got {uv.shape}")
    flat = uv.reshape(-1, 2)
    good = np.isfinite(flat).all(axis=1)
    xy = np.full(flat.shape, np.nan)
    if good.any():
        xy[good] = cam.undistort_points(flat[good])
    p = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ cam.K.T
    return p.reshape(uv.shape[:-1] + (3,))


def epipolar_distance(cam_a: Camera, cam_b: Camera, uv_a, uv_b, *, symmetric=True) -> np.ndarray:
    """Distance (px) between observations and the epipolar lines of their partners ([HZ] §11.4.3).

    Works in undistorted pixel coordinates ``K [x, y, 1]`` (normalised coordinates scaled by the focal
    length), where epipolar lines are straight, so it is exact with lens distortion up to the local scale of
    the distortion (a fraction of a per cent over the paper's field of view).

    Parameters
    ----------
    cam_a, cam_b : Camera
    uv_a, uv_b : array_like of shape (..., 2)
        Distorted pixels in camera a and b; the leading shapes broadcast (one point against many candidates).
    symmetric : bool
        True: ``sqrt((d_a^2 + d_b^2) / 2)``, the RMS of the distance of ``uv_b`` to the epipolar line of
        ``uv_a`` in image b (d_b) and of ``uv_a`` to that of ``uv_b`` in image a (d_a). False: d_b only.

    Returns
    -------
    ndarray of shape broadcast(uv_a, uv_b)[:-1]
        NaN where an input is NaN or a line is undefined (coincident projection centres).
    """
    F = fundamental_matrix(cam_a, cam_b)
    p_a = _undistorted_pixels(cam_a, uv_a)
    p_b = _undistorted_pixels(cam_b, uv_b)
    p_a, p_b = np.broadcast_arrays(p_a, p_b)

    def dist(p, line):
        norm = np.hypot(line[..., 0], line[..., 1])
        return np.divide(np.abs(np.einsum("...i,...i->...", p, line)), norm, out=np.full(norm.shape, np.nan),
                         where=norm > 0)

    d_b = dist(p_b, p_a @ F.T)
    if not symmetric:
        return d_b
    d_a = dist(p_a, p_b @ F)
    return np.sqrt((d_a ** 2 + d_b ** 2) / 2)
