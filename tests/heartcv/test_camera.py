"""Camera and rig: projection against cv2.projectPoints, Jacobians against finite differences, undistortion
against the forward model and cv2.undistortPointsIter, rays, construction and validation."""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from heartcv.camera import Camera, Rig, invert_pose, pose_matrix

# realistic coefficients in OpenCV order (k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4 tau_x tau_y)
FULL = np.array([-0.21, 0.12, 1.1e-3, -6e-4, -0.03, 0.04, 0.011, 0.0025, 1.5e-3, -4e-4, -1.1e-3, 3e-4, 0.012, -0.021])
K = np.array([[5972.7, 0.0, 961.3], [0.0, 5968.1, 537.9], [0.0, 0.0, 1.0]])


def _pose(rng):
    R = Rotation.from_rotvec(rng.normal(scale=0.3, size=3)).as_matrix()
    return pose_matrix(R, rng.normal(scale=0.1, size=3))


def _points_in_view(cam, rng, n=200):
    """Rig-frame points in front of the camera, within about +-0.2 in normalised coordinates."""
    xy = rng.uniform(-0.2, 0.2, size=(n, 2))
    z = rng.uniform(0.4, 0.7, size=n)
    X_cam = np.c_[xy * z[:, None], z]
    T = invert_pose(cam.cam_from_rig)
    return X_cam @ T[:3, :3].T + T[:3, 3]


@pytest.mark.parametrize("n_dist", [0, 4, 5, 8, 12, 14])
def test_project_matches_opencv(n_dist, rng):
    cam = Camera("c", 1920, 1080, K, FULL[:n_dist], _pose(rng))
    X = _points_in_view(cam, rng)
    rvec, _ = cv2.Rodrigues(cam.R)
    ref, _ = cv2.projectPoints(X, rvec, cam.t, K, FULL[:n_dist] if n_dist else None)
    assert np.abs(cam.project(X) - ref.reshape(-1, 2)).max() < 1e-9


def test_project_skew_and_behind_camera(rng):
    Ks = K.copy()
    Ks[0, 1] = 2.5
    cam = Camera("c", 1920, 1080, Ks, np.zeros(0))
    X = np.array([[0.01, -0.02, 0.5], [0.0, 0.0, -0.5], [0.1, 0.0, -1e-9]])
    uv = cam.project(X)
    x, y = 0.01 / 0.5, -0.02 / 0.5
    assert uv[0] == pytest.approx([Ks[0, 0] * x + 2.5 * y + Ks[0, 2], Ks[1, 1] * y + Ks[1, 2]], abs=1e-9)
    assert np.isnan(uv[1:]).all()


@pytest.mark.parametrize("n_dist", [0, 5, 8, 14])
def test_jacobian_matches_central_differences(n_dist, rng):
    cam = Camera("c", 1920, 1080, K, FULL[:n_dist], _pose(rng))
    X = _points_in_view(cam, rng, 50)
    uv, J = cam.project(X, jacobian=True)
    assert J.shape == (50, 2, 3) and np.array_equal(uv, cam.project(X))
    h = 1e-6
    for j in range(3):
        d = np.zeros(3)
        d[j] = h
        fd = (cam.project(X + d) - cam.project(X - d)) / (2 * h)
        assert np.allclose(J[:, :, j], fd, rtol=1e-6, atol=1e-3)  # |J| ~ 1e4 px/m: 1e-7 relative


@pytest.mark.parametrize("n_dist", [0, 4, 5, 8, 12, 14])
@pytest.mark.parametrize("skew", [0.0, 2.5])
def test_analytic_jacobian_equals_complex_step(n_dist, skew, rng):
    """The analytic projection Jacobian against complex-step differentiation of the whole projection (an
    independent derivative, exact to rounding), for every distortion model, with and without skew; wide field
    (+-0.6 normalised) so that every distortion term matters."""
    Ks = K.copy()
    Ks[0, 1] = skew
    cam = Camera("c", 1920, 1080, Ks, FULL[:n_dist], _pose(rng))
    xy = rng.uniform(-0.6, 0.6, size=(100, 2))
    Xc = np.c_[xy, np.ones(100)] * rng.uniform(0.3, 2.0, size=(100, 1))
    _, J = cam.project_cam(Xc, jacobian=True)
    h = 1e-30 * np.abs(Xc).max(axis=1)
    ref = np.empty_like(J)
    for j in range(3):
        Z = Xc.astype(complex)
        Z[:, j] += 1j * h
        ref[:, :, j] = cam._pixels(Z).imag / h[:, None]
    assert np.abs(J - ref).max() <= 1e-10 * np.abs(ref).max()


def test_undistorted_camera_projects_as_pinhole(rng):
    """No distortion: the projection is exactly K [x/z, y/z, 1] (the fast path skips the distortion model)."""
    cam = Camera("c", 640, 480, K, np.zeros(5))
    Xc = np.c_[rng.uniform(-0.2, 0.2, size=(20, 2)), np.ones(20)] * 0.5
    uv = cam.project_cam(Xc)
    ref = (Xc / Xc[:, 2:]) @ K.T
    assert np.array_equal(uv, ref[:, :2]) or np.abs(uv - ref[:, :2]).max() < 1e-9


@pytest.mark.parametrize("n_dist", [4, 5, 8, 12, 14])
def test_undistort_inverts_projection(n_dist, rng):
    cam = Camera("c", 1920, 1080, K, FULL[:n_dist])
    xy = rng.uniform(-0.15, 0.15, size=(300, 2))
    uv = cam.project_cam(np.c_[xy, np.ones(len(xy))])
    assert np.abs(cam.undistort_points(uv) - xy).max() < 1e-12
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, FULL[:n_dist], None, None, None,
                              (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)).reshape(-1, 2)
    assert np.abs(ref - xy).max() < 1e-8  # OpenCV's fixed-point iteration, an independent inverse


def test_rays_pass_through_the_points(rng):
    cam = Camera("c", 1920, 1080, K, FULL[:8], _pose(rng))
    X = _points_in_view(cam, rng)
    o, d = cam.rays(cam.project(X))
    assert np.allclose(np.linalg.norm(d, axis=1), 1, atol=1e-15)
    assert np.allclose(o, cam.centre)
    v = X - o
    dist = np.linalg.norm(v - (v * d).sum(1, keepdims=True) * d, axis=1)
    assert dist.max() < 1e-12 and ((v * d).sum(1) > 0).all()  # on the ray, in front of the camera


def test_from_focal_mm():
    cam = Camera.from_focal_mm("cam0", 1920, 1080, 35.0, 5.86e-6)
    assert cam.K[0, 0] == cam.K[1, 1] == pytest.approx(5972.696245733788, rel=1e-15)
    assert round(cam.K[0, 0], 1) == 5972.7
    assert (cam.K[0, 2], cam.K[1, 2]) == (959.5, 539.5)  # image centre, OpenCV pixel-centre convention
    assert np.array_equal(cam.dist, np.zeros(5)) and np.array_equal(cam.cam_from_rig, np.eye(4))
    # 17.0 cm across 1920 px at the working distance of docs/design.md 7: about 0.53 m
    assert 0.170 / 1920 * cam.K[0, 0] == pytest.approx(0.529, abs=0.002)
    with pytest.raises(ValueError, match="positive"):
        Camera.from_focal_mm("c", 10, 10, 0, 5e-6)


def _triangle_rig():
    """Three cameras on an equilateral triangle of side 0.5 m, all looking at a point 0.53 m ahead."""
    r = 0.5 / np.sqrt(3)
    target = np.array([0.0, 0.0, 0.53])
    cams = []
    for i, a in enumerate(np.deg2rad([90, 210, 330])):
        c = np.array([r * np.cos(a), r * np.sin(a), 0.0])
        z = (target - c) / np.linalg.norm(target - c)
        x = np.cross([0, 1.0, 0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])  # rows: camera axes in the rig frame
        cams.append(Camera.from_focal_mm(f"cam{i}", 1920, 1080, 35, 5.86e-6, cam_from_rig=pose_matrix(R, -R @ c)))
    return Rig(tuple(cams))


def test_rig_baselines_and_relative_poses(rng):
    rig = _triangle_rig()
    b = rig.baselines()
    assert list(b) == ["cam0-cam1", "cam0-cam2", "cam1-cam2"]
    assert np.allclose(list(b.values()), 0.5, atol=1e-15)
    X = rng.normal(size=(10, 3))
    T01 = rig.cam_from_cam("cam0", "cam1")
    assert np.allclose(rig[0].to_cam(X), rig[1].to_cam(X) @ T01[:3, :3].T + T01[:3, 3], atol=1e-14)
    assert np.allclose(rig.cam_from_cam(0, 1) @ rig.cam_from_cam(1, 0), np.eye(4), atol=1e-15)
    assert np.allclose(rig.cam_from_cam(2, 2), np.eye(4), atol=1e-15)
    assert rig.names == ["cam0", "cam1", "cam2"] and len(rig) == 3 and rig["cam2"] is rig[2]
    uv = rig.project(np.array([[0.0, 0.0, 0.53]]))
    assert uv.shape == (3, 1, 2) and np.allclose(uv[:, 0], [959.5, 539.5], atol=1e-9)  # all converge there


def test_pose_helpers(rng):
    T = _pose(rng)
    assert np.allclose(invert_pose(T) @ T, np.eye(4), atol=1e-15)


@pytest.mark.parametrize("kwargs, match", [
    (dict(name="cam 0"), "name"),
    (dict(name=""), "name"),
    (dict(width=0), "width"),
    (dict(height=10.5), "height"),
    (dict(K=[[100, 0, 5], [0, -100, 5], [0, 0, 1]]), "K must be"),
    (dict(K=[[100, 0, 5], [0, 100, 5], [0, 0, 2]]), "K must be"),
    (dict(K=np.eye(2)), "K must be"),
    (dict(dist=np.zeros(6)), "6 distortion coefficients"),
    (dict(dist=[np.nan, 0, 0, 0, 0]), "distortion"),
    (dict(cam_from_rig=np.diag([2.0, 2, 2, 1])), "not a rigid transform"),
    (dict(cam_from_rig=np.diag([1.0, 1, -1, 1])), "not a rigid transform"),
    (dict(cam_from_rig=np.eye(3)), "4x4"),
])
def test_camera_validation(kwargs, match):
    args = dict(name="c", width=640, height=480, K=[[500, 0, 320], [0, 500, 240], [0, 0, 1]])
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        Camera(**args)


def test_rig_validation():
    c = Camera("a", 10, 10, np.diag([5.0, 5, 1]))
    with pytest.raises(ValueError, match="unique"):
        Rig((c, c))
    with pytest.raises(ValueError, match="at least one"):
        Rig(())
    with pytest.raises(KeyError, match="no camera named"):
        Rig((c,))["b"]
    with pytest.raises(ValueError, match="shape"):
        c.project_cam(np.zeros((3, 2)))
    assert not c.K.flags.writeable and not c.dist.flags.writeable
