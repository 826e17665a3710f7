"""Triangulation: exact recovery on the paper rig, cv2 / pycolmap / scipy as independent implementations,
Monte-Carlo check of the predicted covariance, robust leave-worst-out, degenerate geometry without warnings,
epipolar distances against closed-form values, input validation."""

import warnings

import cv2
import numpy as np
import pycolmap
import pytest
from scipy.optimize import least_squares

from heartcv.camera import Camera, Rig, invert_pose, pose_matrix
from heartcv.triangulation import Triangulation, epipolar_distance, fundamental_matrix, triangulate

DIST = np.array([-0.06, 0.12, 2e-4, -1e-4, 0.0])  # k1 k2 p1 p2 k3: realistic for a 35 mm lens


def _look_at(centre, target=(0.0, 0.0, 0.0)):
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return pose_matrix(R, -R @ centre)


def paper_rig(dist=DIST, f=5970.0):
    """docs/design.md §7: three cameras on an equilateral triangle of side 0.5 m, 0.53 m from the heart at the
    world origin, converging on it. Returns the cameras (rig frame = camera 0) and cam0_from_world."""
    r, wd = 0.5 / np.sqrt(3), 0.53
    h = np.sqrt(wd ** 2 - r ** 2)
    cam_from_world = [_look_at(np.array([r * np.cos(a), r * np.sin(a), -h]))
                      for a in np.pi / 2 + 2 * np.pi * np.arange(3) / 3]
    world_from_cam0 = invert_pose(cam_from_world[0])
    cams = []
    for i, T in enumerate(cam_from_world):
        K = np.array([[f * (1 + 0.01 * i), 0, 959.5 + 10 * i], [0, f * (1 + 0.01 * i) * 1.001, 539.5 - 8 * i],
                      [0, 0, 1]])
        cams.append(Camera(f"cam{i}", 1920, 1080, K, dist, T @ world_from_cam0))
    return cams, cam_from_world[0]


def heart_points(cam0_from_world, rng, n):
    """Rig-frame points on a 8 x 6 x 2 cm box around the heart."""
    Xw = rng.uniform(-1, 1, (n, 3)) * [0.04, 0.03, 0.01]
    return Xw @ cam0_from_world[:3, :3].T + cam0_from_world[:3, 3]


def observe(cams, X):
    return np.stack([c.project(X) for c in cams], axis=1)


@pytest.fixture
def rng():
    return np.random.default_rng(20240611)


@pytest.fixture
def no_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        yield


def _cost(cams, X, uv):
    return sum(((c.project(X) - uv[:, i]) ** 2).sum(axis=1) for i, c in enumerate(cams))


# -- exact recovery --------------------------------------------------------------------------------------------
def test_noise_free_recovery_with_2_and_3_views(rng, no_warnings):
    cams, c0 = paper_rig()
    X = heart_points(c0, rng, 300)
    uv = observe(cams, X)
    assert np.isfinite(uv).all() and all(c.in_image(uv[:, i]).all() for i, c in enumerate(cams))
    missing = rng.integers(-1, 3, len(X))  # -1: all views, else the camera that missed the point
    uv[missing >= 0, missing[missing >= 0]] = np.nan
    for cameras in (cams, Rig(tuple(cams))):
        tri = triangulate(cameras, uv)
        assert isinstance(tri, Triangulation)
        assert np.abs(tri.points - X).max() < 1e-9
        assert tri.ok.all() and np.array_equal(tri.used, np.isfinite(uv).all(axis=2))
        assert np.array_equal(tri.n_views, np.where(missing >= 0, 2, 3))
        assert np.array_equal(np.isnan(tri.reprojection_px), ~tri.used)
        assert tri.rms_px.max() < 1e-8 and 40 < tri.angle_deg.min() and tri.angle_deg.max() < 70
    lin = triangulate(cams, uv, refine=False)
    assert np.abs(lin.points - X).max() < 1e-9  # the linear stage is exact without noise, too


def test_against_cv2_triangulate_points(rng, no_warnings):
    """Two undistorted views: cv2's DLT in pixels is exact on perfect data; with noise ours (the maximum
    likelihood point) has the lower reprojection cost and lies within a fraction of a standard deviation."""
    cams, c0 = paper_rig(dist=np.zeros(5))
    X = heart_points(c0, rng, 200)
    uv = observe(cams, X)[:, :2]
    P = [c.K @ c.cam_from_rig[:3] for c in cams[:2]]

    def cv2_tri(uv):
        Xh = cv2.triangulatePoints(P[0], P[1], uv[:, 0].T.copy(), uv[:, 1].T.copy())
        return (Xh[:3] / Xh[3]).T

    assert np.abs(triangulate(cams[:2], uv).points - X).max() < 1e-9
    assert np.abs(cv2_tri(uv) - X).max() < 1e-9
    noisy = uv + 0.1 * rng.standard_normal(uv.shape)
    tri, ref = triangulate(cams[:2], noisy), cv2_tri(noisy)
    assert (_cost(cams[:2], tri.points, noisy) <= _cost(cams[:2], ref, noisy) + 1e-12).all()
    sigma_max = np.sqrt(np.linalg.eigvalsh(tri.covariances)[:, -1])
    assert (np.linalg.norm(tri.points - ref, axis=1) < 0.2 * sigma_max).all()


def _pycolmap_setup(cams):
    cameras = [pycolmap.Camera(model="OPENCV", width=c.width, height=c.height,
                               params=[c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2], *c.dist[:4]]) for c in cams]
    return cameras, [pycolmap.Rigid3d(c.cam_from_rig[:3]) for c in cams]


def test_against_pycolmap(rng, no_warnings):
    """pycolmap.estimate_triangulation (COLMAP's LO-RANSAC on its own distortion model, no refinement):
    equal on perfect data; with noise ours has the lower pixel cost and agrees within 0.2 sigma; with a
    30 px outlier both reject the same view."""
    cams, c0 = paper_rig()
    assert not cams[0].dist[4:].any()  # the OPENCV model of COLMAP has k1 k2 p1 p2
    pc_cams, pc_poses = _pycolmap_setup(cams)
    opt = pycolmap.EstimateTriangulationOptions()
    opt.residual_type = pycolmap.TriangulationResidualType.REPROJECTION_ERROR
    opt.ransac.max_error = 2.0
    opt.ransac.random_seed = 1
    X = heart_points(c0, rng, 30)
    uv = observe(cams, X)
    noisy = uv + 0.1 * rng.standard_normal(uv.shape)
    bad = noisy.copy()
    bad[:, 2] += [30.0, 0.0]
    tri = triangulate(cams, noisy)
    tri_bad = triangulate(cams, bad, robust=True)
    sigma_max = np.sqrt(np.linalg.eigvalsh(tri.covariances)[:, -1])
    for i in range(len(X)):
        exact = pycolmap.estimate_triangulation(uv[i], pc_poses, pc_cams, opt)
        assert np.abs(exact["xyz"] - X[i]).max() < 1e-9
        ref = pycolmap.estimate_triangulation(noisy[i], pc_poses, pc_cams, opt)
        assert np.all(ref["inliers"])
        assert _cost(cams, tri.points[i:i + 1], noisy[i:i + 1])[0] <= _cost(cams, ref["xyz"][None], noisy[i:i + 1])[0]
        assert np.linalg.norm(tri.points[i] - ref["xyz"]) < 0.2 * sigma_max[i]
        ref_bad = pycolmap.estimate_triangulation(bad[i], pc_poses, pc_cams, opt)
        assert np.array_equal(np.asarray(ref_bad["inliers"], bool), tri_bad.used[i]) and tri_bad.ok[i]


def test_against_scipy_least_squares(rng, no_warnings):
    """The refined point is the minimiser of the pixel reprojection error through the distortion model:
    scipy's independent LM solve lands on it to sub-nanometre."""
    cams, c0 = paper_rig()
    X = heart_points(c0, rng, 20)
    uv = observe(cams, X) + 0.5 * rng.standard_normal((20, 3, 2))
    uv[::3, 1] = np.nan
    tri = triangulate(cams, uv)
    for i in range(len(X)):
        views = [c for c in range(3) if np.isfinite(uv[i, c]).all()]
        fun = lambda p: np.concatenate([cams[c].project(p[None])[0] - uv[i, c] for c in views])  # noqa: E731
        ref = least_squares(fun, X[i], method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15).x
        assert np.abs(tri.points[i] - ref).max() < 1e-9
        assert tri.rms_px[i] == pytest.approx(np.sqrt((fun(ref) ** 2).sum() / len(views)), rel=1e-6)


def test_rectified_pair_closed_form_is_the_least_squares_optimum(rng, no_warnings):
    """A rectified stereo pair (as `heartcv rig rectified` writes: same K, no distortion, partner along x), posed
    anywhere in the rig frame: the closed-form optimum equals scipy's LM minimiser of the reprojection error to
    1e-12 m and the general path (linear + LM, the closed form switched off) to 1e-12 m; rows differing by the
    noise; points seen in one view or at negative disparity go the general way (NaN / not ok, as before)."""
    import heartcv.triangulation as T

    K = np.array([[390.0, 0.0, 179.5], [0.0, 390.0, 143.5], [0.0, 0.0, 1.0]])
    R = cv2.Rodrigues(np.array([0.2, -0.1, 0.3]))[0]
    t = np.array([0.01, -0.02, 0.005])
    left = Camera("cam0", 360, 288, K, np.zeros(5), pose_matrix(R, t))
    right = Camera("cam1", 360, 288, K, np.zeros(5), pose_matrix(R, t - [0.0055, 0.0, 0.0]))
    assert T._rectified_pair([left, right]) == (0, 1, pytest.approx(0.0055))
    assert T._rectified_pair([left, left.with_pose(pose_matrix(R, t - [0.0, 0.0055, 0.0]))]) is None
    Xc = np.c_[rng.uniform(-0.01, 0.01, (40, 2)), rng.uniform(0.02, 0.05, 40)]
    X = (Xc - t) @ R
    uv = np.stack([left.project(X), right.project(X)], axis=1) + 0.4 * rng.standard_normal((40, 2, 2))
    uv[0, 1] = np.nan                                               # one view only
    uv[1, 1, 0] = uv[1, 0, 0] + 2.0                                 # negative disparity
    tri = triangulate([left, right], uv)
    real = T._rectified_pair
    T._rectified_pair = lambda cams: None
    try:
        general = triangulate([left, right], uv)
    finally:
        T._rectified_pair = real
    assert np.array_equal(tri.ok, general.ok) and not tri.ok[:2].any() and tri.ok[2:].all()
    np.testing.assert_allclose(tri.points[2:], general.points[2:], rtol=0, atol=1e-12)
    np.testing.assert_allclose(tri.covariances[2:], general.covariances[2:], rtol=1e-9, atol=0)
    for i in range(2, 12):
        fun = lambda p: np.concatenate([left.project(p[None])[0] - uv[i, 0], right.project(p[None])[0] - uv[i, 1]])  # noqa: E731,B023
        ref = least_squares(fun, X[i], method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15).x
        assert np.abs(tri.points[i] - ref).max() < 1e-12
        # the residuals: columns kept, rows split equally
        r = fun(tri.points[i]).reshape(2, 2)
        assert np.abs(r[:, 0]).max() < 1e-9 and abs(r[0, 1] + r[1, 1]) < 1e-9


def test_refinement_lowers_reprojection_error(rng, no_warnings):
    cams, c0 = paper_rig(dist=np.array([-0.3, 0.5, 1e-3, -1e-3, 0.0]))  # strong distortion
    X = heart_points(c0, rng, 200) * [4, 4, 1]  # spread to the image corners
    uv = observe(cams, X) + 0.5 * rng.standard_normal((200, 3, 2))
    lin, ref = triangulate(cams, uv, refine=False), triangulate(cams, uv)
    assert (ref.rms_px <= lin.rms_px + 1e-12).all() and (ref.rms_px < lin.rms_px).mean() > 0.9
    # first-order optimality: the Gauss-Newton step left at the refined point, H^-1 J^T r, is sub-nanometre
    H, g = np.zeros((200, 3, 3)), np.zeros((200, 3))
    for c, cam in enumerate(cams):
        uv_hat, J = cam.project(ref.points, jacobian=True)
        H += np.einsum("nki,nkj->nij", J, J)
        g += np.einsum("nki,nk->ni", J, uv[:, c] - uv_hat)
    assert np.linalg.norm(np.linalg.solve(H, g[..., None])[..., 0], axis=1).max() < 1e-9
    lin_step = np.linalg.norm(ref.points - lin.points, axis=1)
    assert np.median(lin_step) > 1e-7  # the linear estimate was measurably off


# -- uncertainty -----------------------------------------------------------------------------------------------
def test_covariance_matches_monte_carlo(rng, no_warnings):
    """2000 draws of 0.1 px noise for 5 points: the sample covariance matches the predicted one within
    4 times its RMS Frobenius error sqrt((|S|_F^2 + tr(S)^2) / (n - 1)) (Wishart), and the mean error is
    consistent with zero (chi^2_3 at 0.999: 16.27)."""
    cams, c0 = paper_rig()
    n_draw, sigma = 2000, 0.1
    X = heart_points(c0, rng, 5)
    uv = observe(cams, X)
    pred = triangulate(cams, uv, sigma_px=sigma).covariances
    noisy = np.repeat(uv, n_draw, axis=0) + sigma * rng.standard_normal((5 * n_draw, 3, 2))
    tri = triangulate(cams, noisy, sigma_px=sigma)
    assert tri.ok.all()
    err = (tri.points - np.repeat(X, n_draw, axis=0)).reshape(5, n_draw, 3)
    for e, S in zip(err, pred):
        sample = np.cov(e.T)
        bound = 4 * np.sqrt((np.sum(S ** 2) + np.trace(S) ** 2) / (n_draw - 1)) / np.linalg.norm(S)
        assert np.linalg.norm(sample - S) / np.linalg.norm(S) < bound
        m = e.mean(axis=0)
        assert n_draw * m @ np.linalg.solve(S, m) < 16.27
    # a wrong scale (sigma instead of sigma^2) would be off by 10x: the check can fail
    assert bound < 0.25


def test_predicted_std_at_the_paper_rig(rng, no_warnings):
    """docs/design.md §7: triangulation noise alone is about 10-20 um at 0.1 px."""
    cams, c0 = paper_rig()
    tri = triangulate(cams, observe(cams, heart_points(c0, rng, 100)), sigma_px=0.1)
    total = np.sqrt(np.trace(tri.covariances, axis1=1, axis2=2))  # sqrt(E|e|^2)
    axes = np.sqrt(np.linalg.eigvalsh(tri.covariances))
    assert 10e-6 < total.min() and total.max() < 15e-6
    assert 4e-6 < axes[:, 0].min() and axes[:, 2].max() < 11e-6  # depth (worst axis) ~9 um, lateral ~5.5 um
    two = triangulate(cams[:2], observe(cams[:2], heart_points(c0, rng, 100)), sigma_px=0.1)
    assert (np.trace(two.covariances, axis1=1, axis2=2) > 1.2 * np.trace(tri.covariances, axis1=1, axis2=2)).all()


# -- robust mode ----------------------------------------------------------------------------------------------
def test_robust_drops_a_grossly_wrong_view(rng, no_warnings):
    cams, c0 = paper_rig()
    X = heart_points(c0, rng, 50)
    uv = observe(cams, X)
    wrong = rng.integers(0, 3, 50)
    uv[np.arange(50), wrong] += rng.choice([-1, 1], (50, 2)) * [30.0, 20.0]
    plain = triangulate(cams, uv)
    assert not plain.ok.any() and plain.used.all() and (plain.rms_px > 1).all()
    tri = triangulate(cams, uv, robust=True)
    assert tri.ok.all() and np.abs(tri.points - X).max() < 1e-9
    assert np.array_equal(tri.used, np.arange(3)[None] != wrong[:, None])
    off = tri.reprojection_px[np.arange(50), wrong]  # still reported for the dropped view
    assert (off > 30).all() and (off < np.hypot(30, 20) + 1e-6).all()
    # nothing to drop: robust mode changes nothing
    clean = observe(cams, X)
    assert np.array_equal(triangulate(cams, clean, robust=True).points, triangulate(cams, clean).points)


def test_two_inconsistent_views_are_not_ok(rng, no_warnings):
    cams, c0 = paper_rig()
    X = heart_points(c0, rng, 10)
    uv = observe(cams, X)
    uv[:, 2] = np.nan
    uv[:, 1] += [30.0, 0.0]
    tri = triangulate(cams, uv, robust=True)
    assert not tri.ok.any() and (tri.rms_px > 1.0).all() and (tri.n_views == 2).all()
    assert np.isfinite(tri.points).all() and np.isfinite(tri.covariances).all()


# -- degenerate geometry ---------------------------------------------------------------------------------------
def test_degenerate_points_are_flagged_without_warnings(rng, no_warnings):
    cams, c0 = paper_rig()
    X = heart_points(c0, rng, 2)
    uv = np.full((7, 3, 2), np.nan)
    uv[0] = observe(cams, X[:1])  # good
    uv[1, 0] = cams[0].project(X[1:])[0]  # one view only
    # behind every camera: pixels of the mirrored point (x/z, y/z unchanged)
    behind = -X[1] * 3
    uv[2] = np.stack([c.project_cam(-c.to_cam(behind[None]))[0] for c in cams])
    assert all(c.to_cam(behind)[2] < 0 for c in cams)
    # exactly parallel rays (a point at infinity) and nearly parallel ones (1 km away)
    d = np.array([0.01, -0.02, 1.0])
    uv[3] = np.stack([c.project_cam((c.R @ d)[None])[0] for c in cams])
    uv[4] = observe(cams, np.array([[0.0, 0.0, 1e3]]))[0]
    uv[6, :2] = uv[0, :2]  # row 5 stays all-NaN
    tri = triangulate(cams, uv, robust=True)
    assert tri.ok.tolist() == [True, False, False, False, False, False, True]
    assert np.isnan(tri.points[[1, 3, 5]]).all() and np.isnan(tri.covariances[[1, 3, 5]]).all()
    assert np.isnan(tri.rms_px[[1, 2, 3, 5]]).all() and np.isnan(tri.reprojection_px[2]).all()
    assert np.all(tri.points[2] @ np.stack([c.R[2] for c in cams]).T + [c.t[2] for c in cams] < 0)
    assert tri.angle_deg[3] < 1e-6 and tri.angle_deg[4] < 0.05 and np.isfinite(tri.points[4]).all()
    assert np.abs(tri.points[4] - [0, 0, 1e3]).max() < 1e-3
    assert np.isnan(tri.angle_deg[[1, 5]]).all() and tri.used[5].sum() == 0
    empty = triangulate(cams, np.zeros((0, 3, 2)))
    assert empty.points.shape == (0, 3) and empty.ok.shape == (0,)


# -- epipolar geometry -----------------------------------------------------------------------------------------
def _undistorted_pixels(cam, uv):
    return np.c_[cam.undistort_points(uv), np.ones(len(uv))] @ cam.K.T


def test_fundamental_matrix_matches_eight_point(rng, no_warnings):
    cams, c0 = paper_rig()
    X = heart_points(c0, rng, 100)
    for a, b in ((0, 1), (2, 0)):
        pa = _undistorted_pixels(cams[a], cams[a].project(X))
        pb = _undistorted_pixels(cams[b], cams[b].project(X))
        F = fundamental_matrix(cams[a], cams[b])
        assert np.abs(np.einsum("ni,ij,nj->n", pb, F, pa)).max() < 1e-9 * np.linalg.norm(F)
        ref, _ = cv2.findFundamentalMat(pa[:, :2], pb[:, :2], cv2.FM_8POINT)
        F, ref = F / np.linalg.norm(F), ref / np.linalg.norm(ref)
        assert min(np.abs(F - ref).max(), np.abs(F + ref).max()) < 1e-6


def test_epipolar_distance_exact_values(rng, no_warnings):
    """True correspondences: 0. A point moved by delta perpendicular to its epipolar line (in undistorted
    pixels of image b) and re-distorted: the one-sided distance is delta, and the symmetric one is the RMS
    with the distance in image a computed independently, by projecting two points of b's ray into a."""
    cams, c0 = paper_rig()
    a, b = cams[0], cams[2]
    X = heart_points(c0, rng, 50)
    uv_a, uv_b = a.project(X), b.project(X)
    assert epipolar_distance(a, b, uv_a, uv_b).max() < 1e-9
    assert epipolar_distance(a, b, uv_a, uv_b, symmetric=False).max() < 1e-9
    F = fundamental_matrix(a, b)
    pa, pb = _undistorted_pixels(a, uv_a), _undistorted_pixels(b, uv_b)
    line = pa @ F.T
    normal = line[:, :2] / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    delta = rng.uniform(-5, 5, 50)
    pb_moved = pb[:, :2] + delta[:, None] * normal
    xy = np.c_[pb_moved, np.ones(50)] @ np.linalg.inv(b.K).T  # normalised coordinates in b
    uv_b_moved = b.project_cam(xy)
    d_b = epipolar_distance(a, b, uv_a, uv_b_moved, symmetric=False)
    assert np.abs(d_b - np.abs(delta)).max() < 1e-8
    # independent d_a: the ray of b through the moved point, two of its points projected with a's pinhole
    a_from_b = a.cam_from_rig @ invert_pose(b.cam_from_rig)
    ends = [(xy * s) @ a_from_b[:3, :3].T + a_from_b[:3, 3] for s in (0.3, 0.8)]
    ends = [(e / e[:, 2:]) @ a.K.T for e in ends]
    u = ends[1][:, :2] - ends[0][:, :2]
    w = pa[:, :2] - ends[0][:, :2]
    d_a = np.abs(u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]) / np.linalg.norm(u, axis=1)
    sym = epipolar_distance(a, b, uv_a, uv_b_moved)
    assert np.abs(sym - np.sqrt((d_a ** 2 + delta ** 2) / 2)).max() < 1e-8
    assert np.abs(sym - epipolar_distance(b, a, uv_b_moved, uv_a)).max() < 1e-9
    # one point against many candidates broadcasts; NaN in, NaN out
    many = epipolar_distance(a, b, uv_a[0], np.vstack([uv_b_moved[:5], [np.nan, np.nan]]))
    assert many.shape == (6,) and np.isnan(many[5])
    assert np.abs(many[:5] - epipolar_distance(a, b, np.repeat(uv_a[:1], 5, 0), uv_b_moved[:5])).max() < 1e-12


# -- validation ------------------------------------------------------------------------------------------------
def test_bad_input_raises():
    cams, _ = paper_rig()
    with pytest.raises(ValueError, match=r"shape \(N, 3, 2\) expected"):
        triangulate(cams, np.zeros((5, 2, 2)))
    with pytest.raises(ValueError, match=r"shape \(N, 3, 2\) expected"):
        triangulate(cams, np.zeros((5, 3)))
    with pytest.raises(ValueError, match="at least 2 cameras"):
        triangulate(cams[:1], np.zeros((5, 1, 2)))
    with pytest.raises(ValueError, match="Rig or a sequence of Camera"):
        triangulate([cams[0], "cam1"], np.zeros((5, 2, 2)))
    with pytest.raises(ValueError, match="sigma_px"):
        triangulate(cams, np.zeros((5, 3, 2)), sigma_px=0)
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 2\)"):
        epipolar_distance(cams[0], cams[1], np.zeros((4, 3)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="points: shape"):
        Triangulation(np.zeros((2, 2)), np.zeros((2, 3, 3)), np.zeros((2, 3)), np.zeros(2), np.zeros(2),
                      np.zeros((2, 3), bool), np.zeros(2, bool))
