"""heartcv.rig_formats: importing rigs calibrated elsewhere (OpenCV FileStorage, Kalibr, COLMAP, caliscope, plain
text) against exact answers: heartcv's own COLMAP and Kalibr exports come back to 1e-9, COLMAP's camera models
project as pycolmap projects them, caliscope's poses come back bit for bit, the Hamlyn files give their printed
numbers, and the rotation, units and detection rules give their documented results."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from heartcv.camera import Camera, Rig, pose_matrix
from heartcv.io import write_colmap, write_kalibr
from heartcv.rig_formats import (
    COLMAP_MODELS,
    ORTHO_TOL,
    colmap_to_opencv,
    convert_units,
    detect_format,
    finish_import,
    orthonormalise,
    plan_import,
    read_foreign,
    rectified_rig,
    rig_span,
    side_warnings,
    units_message,
)
from heartcv.tracker.files import InputError
from tests.conftest import SHARED_DATA

CALISCOPE = SHARED_DATA / "caliscope_4cam_charuco"
HAMLYN = SHARED_DATA / "hamlyn_heart_phantom_f7"
OPENCV = SHARED_DATA / "opencv_stereo"


def _import(paths, fmt=None, image_sizes=()):
    fmt, files = plan_import([Path(p) for p in paths], fmt)
    return read_foreign(fmt, files, image_sizes)


def _padded(d, n=14):
    out = np.zeros(n)
    out[: len(d)] = d
    return out


def _same_cameras(a: Rig, b: Rig, tol=1e-9):
    assert len(a) == len(b)
    for ca, cb in zip(a.cameras, b.cameras):
        assert (ca.width, ca.height) == (cb.width, cb.height)
        np.testing.assert_allclose(ca.K, cb.K, rtol=0, atol=tol)
        np.testing.assert_allclose(_padded(ca.dist), _padded(cb.dist), rtol=0, atol=tol)
        np.testing.assert_allclose(ca.cam_from_rig, cb.cam_from_rig, rtol=0, atol=tol)


def _random_rig(rng, dists):
    cams = []
    for i, d in enumerate(dists):
        f = rng.uniform(400, 2000)
        K = [[f, 0, rng.uniform(300, 340)], [0, f * rng.uniform(0.98, 1.02), rng.uniform(220, 260)], [0, 0, 1]]
        T = np.eye(4) if i == 0 else pose_matrix(Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix(),
                                                 rng.normal(0, 0.2, 3))
        cams.append(Camera(f"c{i}", 640, 480, K, d, T))
    return Rig(tuple(cams))


# ---------------------------------------------------------------------------------------------------------------------
# COLMAP
# ---------------------------------------------------------------------------------------------------------------------
@pytest.fixture
def colmap_rig(rng):
    # PINHOLE (no coefficients), OPENCV (4, and 5 with k3 = 0), FULL_OPENCV (8; and 5 with k3 != 0)
    dists = [[], [0.1, -0.05, 1e-3, -2e-3], [0.1, -0.05, 1e-3, -2e-3, 0.0], [0.1, -0.2, 1e-3, 2e-3, 0.05],
             [0.1, -0.2, 1e-3, 2e-3, 0.05, 0.01, -0.02, 0.03]]
    return _random_rig(rng, dists)


def test_colmap_round_trip(tmp_path, colmap_rig):
    """heartcv's own COLMAP export (PINHOLE, OPENCV, FULL_OPENCV) comes back to 1e-9, cameras named by their ids,
    in rig order, camera 1 the rig frame."""
    write_colmap(tmp_path / "model", colmap_rig)
    for given in (tmp_path / "model", tmp_path / "model" / "cameras.txt", tmp_path / "model" / "rigs.txt"):
        imp = _import([given])
        assert imp.source_format == "colmap"
        assert [p.name for p in imp.files] == ["cameras.txt", "rigs.txt"]
        assert imp.rig.names == ["cam1", "cam2", "cam3", "cam4", "cam5"]
        _same_cameras(imp.rig, colmap_rig)
    assert imp.rig.cameras[0].dist.size == 0  # PINHOLE: no coefficients, as written
    # a renamed cameras file with --format colmap: rigs.txt given with it, or found beside it
    other = tmp_path / "other"
    other.mkdir()
    (other / "cams.txt").write_text((tmp_path / "model" / "cameras.txt").read_text())
    assert plan_import([other / "cams.txt", tmp_path / "model" / "rigs.txt"], "colmap")[1] == [
        other / "cams.txt", tmp_path / "model" / "rigs.txt"]
    _same_cameras(_import([other / "cams.txt", tmp_path / "model" / "rigs.txt"], "colmap").rig, colmap_rig)
    (other / "rigs.txt").write_text((tmp_path / "model" / "rigs.txt").read_text())
    assert plan_import([other / "cams.txt"], "colmap")[1] == [other / "cams.txt", other / "rigs.txt"]


def test_colmap_agrees_with_pycolmap(tmp_path, colmap_rig):
    """Our parser against pycolmap's reader of the same files: principal point - 0.5 and sensor_from_rig."""
    pycolmap = pytest.importorskip("pycolmap")
    folder = tmp_path / "model"
    write_colmap(folder, colmap_rig)
    for name in ("frames.txt", "images.txt", "points3D.txt"):
        (folder / name).write_text("")
    rec = pycolmap.Reconstruction()
    rec.read_text(str(folder))
    ours = _import([folder]).rig
    for cid, cam in zip(range(1, 6), ours.cameras):
        pc = rec.cameras[cid]
        assert (pc.width, pc.height) == (cam.width, cam.height)
        assert pc.focal_length_x == pytest.approx(cam.K[0, 0], abs=1e-9)
        assert pc.principal_point_x - 0.5 == pytest.approx(cam.K[0, 2], abs=1e-9)
        assert pc.principal_point_y - 0.5 == pytest.approx(cam.K[1, 2], abs=1e-9)
    prig = rec.rigs[1]
    assert prig.ref_sensor_id.id == 1
    for sensor, pose in prig.non_ref_sensors.items():
        np.testing.assert_allclose(pose.matrix(), ours[f"cam{sensor.id}"].cam_from_rig[:3], atol=1e-12)


@pytest.mark.parametrize("model", sorted(COLMAP_MODELS))
def test_colmap_models_project_as_pycolmap(model, rng):
    """Each supported COLMAP model, converted to K and OpenCV coefficients, projects camera-frame points to COLMAP's
    pixels minus 0.5 (pycolmap's own projection; an independent implementation)."""
    pycolmap = pytest.importorskip("pycolmap")
    n = COLMAP_MODELS[model]
    base = [600.0, 310.2, 250.7] if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL") else [600.0, 590.0,
                                                                                                    310.2, 250.7]
    extra = list(rng.normal(0, 0.05, n - len(base)))
    params = base + extra
    pc = pycolmap.Camera.create_from_model_name(1, model, 600.0, 640, 480)
    pc.params = params
    X = np.column_stack([rng.uniform(-0.4, 0.4, (50, 2)), np.ones(50)]) * rng.uniform(0.5, 2.0, (50, 1))
    uv_colmap = np.asarray(pc.img_from_cam(X))
    K, dist = colmap_to_opencv(model, params)
    uv = Camera("c", 640, 480, K, dist).project_cam(X)
    np.testing.assert_allclose(uv, uv_colmap - 0.5, atol=1e-8)


def test_colmap_refusals(tmp_path, colmap_rig):
    folder = tmp_path / "m"
    write_colmap(folder, colmap_rig)
    text = (folder / "cameras.txt").read_text().replace(" FULL_OPENCV ", " OPENCV_FISHEYE ", 1)
    (folder / "cameras.txt").write_text(text)
    with pytest.raises(InputError) as err:
        _import([folder])
    assert err.value.path == str(folder / "cameras.txt") and err.value.field.startswith("line ")
    assert "OPENCV_FISHEYE: not supported" in err.value.reason
    # two cameras and no rigs.txt: poses unknown
    one = tmp_path / "two"
    one.mkdir()
    (one / "cameras.txt").write_text("1 PINHOLE 640 480 500 500 320 240\n2 PINHOLE 640 480 500 500 320 240\n")
    with pytest.raises(InputError, match="no rigs.txt") as err:
        _import([one])
    assert err.value.field == "rigs.txt"
    # one camera alone is a rig of one
    (one / "cameras.txt").write_text("# c\n7 SIMPLE_RADIAL 640 480 500 320.5 240.5 -0.1\n")
    imp = _import([one])
    assert imp.rig.names == ["cam7"]
    np.testing.assert_array_equal(imp.rig[0].K, [[500, 0, 320], [0, 500, 240], [0, 0, 1]])
    np.testing.assert_array_equal(imp.rig[0].dist, [-0.1, 0, 0, 0])
    # a sensor without a pose
    (one / "cameras.txt").write_text("1 PINHOLE 640 480 500 500 320 240\n2 PINHOLE 640 480 500 500 320 240\n")
    (one / "rigs.txt").write_text("1 2 CAMERA 1 CAMERA 2 0\n")
    with pytest.raises(InputError, match="HAS_POSE 0"):
        _import([one])
    (one / "rigs.txt").write_text("1 2 CAMERA 1 CAMERA 2 1 0.5 0 0 0 0 0\n")  # 6 pose numbers
    with pytest.raises(InputError, match="RIG_ID NUM_SENSORS") as err:
        _import([one])
    assert err.value.field == "line 1"
    # a quaternion of norm 2: its own reason (the layout message had hidden it)
    (one / "rigs.txt").write_text("1 2 CAMERA 1 CAMERA 2 1 2 0 0 0 0.1 0 0\n")
    with pytest.raises(InputError, match="a unit quaternion QW QX QY QZ expected, got norm 2") as err:
        _import([one])
    assert err.value.field == "line 1 sensor CAMERA 2"


# ---------------------------------------------------------------------------------------------------------------------
# Kalibr
# ---------------------------------------------------------------------------------------------------------------------
def test_kalibr_round_trip(tmp_path, rng):
    rig = _random_rig(rng, [[0.1, -0.05, 1e-3, -2e-3], [0.0, 0.0, 0.0, 0.0, 0.0], [-0.2, 0.1, 0, 1e-3]])
    path = tmp_path / "camchain.yaml"
    write_kalibr(path, rig)
    assert detect_format(path) == "kalibr"
    imp = _import([path])
    assert imp.rig.names == ["cam0", "cam1", "cam2"]
    _same_cameras(imp.rig, rig)
    assert imp.corrections == ()


def test_kalibr_refuses_equidistant(tmp_path, rng):
    path = tmp_path / "camchain.yaml"
    write_kalibr(path, _random_rig(rng, [[0.1, 0, 0, 0], [0.1, 0, 0, 0]]))
    text = path.read_text()
    path.write_text(text.replace("distortion_model: radtan", "distortion_model: equidistant"))
    with pytest.raises(InputError, match="equidistant") as err:
        _import([path])
    assert err.value.path == str(path) and err.value.field == "cam0.distortion_model"
    path.write_text(text.replace("camera_model: pinhole", "camera_model: omni", 1))
    with pytest.raises(InputError) as err:
        _import([path])
    assert err.value.field == "cam0.camera_model"


# ---------------------------------------------------------------------------------------------------------------------
# caliscope
# ---------------------------------------------------------------------------------------------------------------------
needs_caliscope = pytest.mark.skipif(not CALISCOPE.is_dir(), reason="shared data not available (caliscope)")


@needs_caliscope
@pytest.mark.parametrize("name", ["camera_array.toml", "config.toml"])
def test_caliscope_poses_exact(name):
    """cam_from_rig = [rotation | translation] of the TOML, bit for bit, K and distortions likewise, in caliscope's
    world frame; the reference centre distances of README.txt."""
    path = CALISCOPE / name
    imp = _import([path])
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    truth = tomllib.loads((CALISCOPE / "camera_array.toml").read_text())["cameras"]
    assert imp.source_format == "caliscope" and imp.rig.names == ["cam_0", "cam_1", "cam_2", "cam_3"]
    for cam, key in zip(imp.rig.cameras, sorted(truth)):
        t = truth[key]
        assert (cam.width, cam.height) == tuple(t["size"])
        assert cam.K.tolist() == t["matrix"]
        assert cam.dist.tolist() == t["distortions"]
        assert cam.R.tolist() == t["rotation"]
        assert cam.t.tolist() == t["translation"]
    assert imp.corrections == ()
    rig = finish_import(imp)
    assert rig.meta["cameras"]["cam_0"]["rms_px"] == 0.541
    ref = {"cam_0-cam_1": 1.149, "cam_0-cam_2": 0.533, "cam_0-cam_3": 0.417, "cam_1-cam_2": 0.953,
           "cam_1-cam_3": 1.438, "cam_2-cam_3": 0.616}
    assert rig.baselines() == pytest.approx(ref, abs=5e-4)


def test_caliscope_ignore_rodrigues_and_refusals(tmp_path):
    rv = [0.1, -0.2, 0.3]
    text = """
[cameras.0]
cam_id = 0
size = [640, 480]
matrix = [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]
distortions = [0.1, 0.0, 0.0, 0.0, 0.0]
rotation = [0.1, -0.2, 0.3]
translation = [0.1, 0.2, 0.3]
ignore = false

[cameras.1]
cam_id = 1
ignore = true
size = [640, 480]

[cameras.2]
cam_id = 2
size = [640, 480]
matrix = [[510.0, 0.0, 320.0], [0.0, 510.0, 240.0], [0.0, 0.0, 1.0]]
distortions = [0.0, 0.0, 0.0, 0.0, 0.0]
rotation = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
translation = [0.0, 0.0, 1.0]
"""
    path = tmp_path / "camera_array.toml"
    path.write_text(text)
    assert detect_format(path) == "caliscope"
    imp = _import([path])
    assert imp.rig.names == ["cam_0", "cam_2"]
    assert len(imp.warnings) == 1 and "ignore = true" in imp.warnings[0]
    np.testing.assert_allclose(imp.rig[0].R, Rotation.from_rotvec(rv).as_matrix(), atol=1e-15)
    path.write_text(text.replace("rotation_count", "x").replace("cam_id = 2\n", "cam_id = 2\nrotation_count = 1\n"))
    with pytest.raises(InputError) as err:
        _import([path])
    assert err.value.field == "cameras.2.rotation_count"
    path.write_text(text.replace("translation = [0.0, 0.0, 1.0]\n", ""))
    with pytest.raises(InputError, match="pose is unknown") as err:
        _import([path])
    assert err.value.field == "cameras.2.translation"
    path.write_text("[cameras.0\n")
    with pytest.raises(InputError, match="not valid TOML"):
        _import([path])


# ---------------------------------------------------------------------------------------------------------------------
# Plain text (Hamlyn)
# ---------------------------------------------------------------------------------------------------------------------
needs_hamlyn = pytest.mark.skipif(not HAMLYN.is_dir(), reason="shared data not available (hamlyn_heart_phantom_f7)")


@needs_hamlyn
def test_hamlyn_text_folder():
    """The folder layout gives left, right with the printed K; calib.l2r.4x4 is right_from_left in millimetres:
    refused without --units (the units message names the pose file), baseline 5.52 mm with --units mm."""
    fmt, files = plan_import([HAMLYN])
    assert fmt == "text"
    assert [f.name for f in files] == ["calib.left.intrinsic.txt", "calib.left.distortion.txt",
                                       "calib.right.intrinsic.txt", "calib.right.distortion.txt", "calib.l2r.4x4"]
    with pytest.raises(InputError, match="image size"):
        read_foreign(fmt, files)
    imp = read_foreign(fmt, files, [(360, 288)])
    left, right = imp.rig.cameras
    assert (left.name, right.name) == ("left", "right")
    assert left.K.tolist() == [[391.656525, 0, 165.964371], [0, 426.835144, 154.498138], [0, 0, 1]]
    assert right.K.tolist() == [[390.376862, 0, 190.896454], [0, 426.228882, 145.071411], [0, 0, 1]]
    assert (left.width, left.height) == (360, 288) and not left.dist.any() and not right.dist.any()
    (corr,) = imp.corrections  # printed to 6 decimals: |R^T R - I| ~ 1e-6, projected
    assert corr["file"] == str(HAMLYN / "calib.l2r.4x4") and 1e-7 < corr["deviation"] < 1e-5
    assert np.abs(right.R.T @ right.R - np.eye(3)).max() < 1e-15
    np.testing.assert_array_equal(right.t, [-5.520739, -0.031516, -0.051285])
    with pytest.raises(InputError) as err:
        finish_import(imp)
    assert err.value.path == str(HAMLYN / "calib.l2r.4x4")
    assert "baseline 5.52 m (left-right): translations look like millimetres; pass --units mm" in err.value.reason
    rig = finish_import(imp, "mm")
    assert rig.baselines()["left-right"] == pytest.approx(np.linalg.norm([5.520739, 0.031516, 0.051285]) * 1e-3,
                                                          rel=1e-12)
    assert rig.baselines()["left-right"] == pytest.approx(5.52e-3, abs=5e-6)
    assert rig.meta["units_conversion"]["scale_to_m"] == 1e-3
    assert rig.meta["orthonormalised"] == [corr]
    assert side_warnings(rig) == []
    # the right camera's files first: the l2r pose is then read as left_from_right, and 'right' lies 5.52 mm to
    # the left of 'left' (imported without a word before 2026-11-29)
    swapped = finish_import(read_foreign(fmt, files[2:4] + files[:2] + files[4:], [(360, 288)]), "mm")
    assert swapped.names == ["right", "left"]
    (msg,) = side_warnings(swapped)
    assert msg.startswith("camera 'right' lies 5.52 mm to the left of camera 'left'")
    # a principal point outside the image (the image size given wrong): exit-2 error naming the camera
    with pytest.raises(InputError, match=r"camera left: principal point \(165.964, 154.498\) lies outside its "
                                         r"160x120 image"):
        finish_import(read_foreign(fmt, files, [(160, 120)]), "mm")


def _write(path, text):
    path.write_text(text)
    return path


def test_text_files_in_camera_order(tmp_path):
    """K starts a camera, a row after it is its distortion, a 3x4 or 4x4 after it its cam_from_cam0."""
    K0 = _write(tmp_path / "k0.txt", "500 0 320\n0 510 240\n0 0 1\n")
    d0 = _write(tmp_path / "d0.txt", "0.1, -0.05, 0.001, 0.002\n")
    K1 = _write(tmp_path / "k1.txt", "# right\n501 0 321\n0 511 241\n0 0 1\n")
    p1 = _write(tmp_path / "p1.txt", "1 0 0 -0.06\n0 1 0 0\n0 0 1 0\n")
    imp = _import([K0, d0, K1, p1], "text", [(640, 480), (800, 600)])
    assert imp.rig.names == ["cam0", "cam1"]
    assert imp.rig[1].size == (800, 600)
    np.testing.assert_array_equal(imp.rig[0].dist, [0.1, -0.05, 0.001, 0.002])
    np.testing.assert_array_equal(imp.rig[1].dist, np.zeros(5))
    np.testing.assert_array_equal(imp.rig[1].t, [-0.06, 0, 0])
    assert detect_format(K0) == "text"
    with pytest.raises(InputError, match="before any K") as err:
        _import([p1, K0], "text", [(640, 480)])
    assert err.value.path == str(p1)
    with pytest.raises(InputError, match="no pose for this camera") as err:
        _import([K0, K1], "text", [(640, 480)])
    assert err.value.path == str(K1) and err.value.field == "pose"
    bad = _write(tmp_path / "bad.txt", "1 0 0 0\n0 1 0 0\n0 0 -1 0\n0 0 0 1\n")
    with pytest.raises(InputError, match="det R") as err:
        _import([K0, K1, bad], "text", [(640, 480)])
    assert err.value.path == str(bad) and err.value.field == "pose (rotation)"
    nan = _write(tmp_path / "nan.txt", "500 0 320\n0 x 240\n0 0 1\n")
    with pytest.raises(InputError) as err:
        _import([nan], "text", [(640, 480)])
    assert err.value.field == "line 2"
    with pytest.raises(InputError, match="3 image sizes for 2 cameras"):
        _import([K0, K1, p1], "text", [(640, 480)] * 3)


# ---------------------------------------------------------------------------------------------------------------------
# OpenCV FileStorage
# ---------------------------------------------------------------------------------------------------------------------
M1 = np.array([[534.8, 0, 335.7], [0, 534.9, 240.7], [0, 0, 1]])
D1 = np.array([[0.29, -1.03, 0.001, -0.002, 0.1]])
M2 = np.array([[535.8, 0, 334.6], [0, 535.9, 242.1], [0, 0, 1]])
D2 = np.array([[-0.17, -0.11, 0, 0, 0, 0.01, 0.02, 0.03]])
R12 = Rotation.from_rotvec([0.01, -0.02, 0.005]).as_matrix()
T12 = np.array([[-83.6], [1.0], [1.3]])


def _filestorage(path, **mats):
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in mats.items():
        fs.write(k, v)
    fs.release()
    return path


@pytest.mark.parametrize("ext", ["yml", "xml"])
def test_opencv_stereo_calib_files(tmp_path, ext):
    """intrinsics (M1 D1 M2 D2) + extrinsics (R T R1 R2 P1 P2 Q) as stereo_calib.cpp writes them, given together or
    as one file: the cameras and cam1_from_cam0 = [R | T]; T in the board's units (mm here)."""
    intr = _filestorage(tmp_path / f"intrinsics.{ext}", M1=M1, D1=D1, M2=M2, D2=D2)
    extr = _filestorage(tmp_path / f"extrinsics.{ext}", R=R12, T=T12, R1=np.eye(3), R2=np.eye(3),
                        P1=np.eye(3, 4), P2=np.eye(3, 4), Q=np.eye(4))
    both = _filestorage(tmp_path / f"all.{ext}", M1=M1, D1=D1, M2=M2, D2=D2, R=R12, T=T12)
    assert detect_format(intr) == "opencv"
    for files in ([intr, extr], [extr, intr], [both]):
        imp = _import(files, image_sizes=[(640, 480)])
        c0, c1 = imp.rig.cameras
        assert (c0.name, c1.name) == ("cam0", "cam1")
        np.testing.assert_array_equal(c0.K, M1)
        np.testing.assert_array_equal(c1.K, M2)
        np.testing.assert_array_equal(c0.dist, D1[0])
        np.testing.assert_array_equal(c1.dist, D2[0])
        np.testing.assert_array_equal(c0.cam_from_rig, np.eye(4))
        np.testing.assert_allclose(c1.cam_from_rig, pose_matrix(R12, T12), atol=1e-15)
    rig = finish_import(imp, "mm")
    np.testing.assert_allclose(rig[1].t, T12[:, 0] * 1e-3, rtol=1e-15)
    with pytest.raises(InputError, match="image size is not in the file"):
        _import([intr, extr])
    with pytest.raises(InputError, match="second camera's pose is missing") as err:
        _import([intr], image_sizes=[(640, 480)])
    assert err.value.field == "R"
    with pytest.raises(InputError, match="look like millimetres"):
        finish_import(_import([both], image_sizes=[(640, 480)]))


needs_opencv_data = pytest.mark.skipif(not OPENCV.is_dir(), reason="shared data not available (opencv_stereo)")


@needs_opencv_data
def test_opencv_left_intrinsics_real():
    """OpenCV's published left_intrinsics.yml: fx = fy = 535.916, cx 342.283, cy 235.571, 640x480, RMS 0.3926."""
    imp = _import([OPENCV / "left_intrinsics.yml"])
    (cam,) = imp.rig.cameras
    assert cam.size == (640, 480)
    assert cam.K[0, 0] == cam.K[1, 1] == 5.3591573396163199e+02
    assert (cam.K[0, 2], cam.K[1, 2]) == (3.4228315473308373e+02, 2.3557082909788173e+02)
    np.testing.assert_array_equal(cam.dist, [-2.6637260909660682e-01, -3.8588898922304653e-02,
                                             1.7831947042852964e-03, -2.8122100441115472e-04, 2.3839153080878486e-01])
    assert imp.rig.meta["cameras"]["cam0"]["rms_px"] == pytest.approx(0.3926, abs=1e-4)
    with pytest.raises(InputError, match="the file says 640x480"):
        _import([OPENCV / "left_intrinsics.yml"], image_sizes=[(320, 240)])
    # the real stereo sample has no extrinsics: refused, not guessed
    with pytest.raises(InputError, match="second camera's pose is missing"):
        _import([OPENCV / "intrinsics_samples_data.yml"], image_sizes=[(640, 480)])


def test_opencv_ros_camera_info(tmp_path):
    """Plain-YAML {rows, cols, data} matrices (ROS camera_info files) are read too."""
    path = _write(tmp_path / "cam.yaml", "image_width: 800\nimage_height: 600\ncamera_name: x\n"
                  "camera_matrix: {rows: 3, cols: 3, data: [538.6, 0, 457.7, 0, 539.7, 297.0, 0, 0, 1]}\n"
                  "distortion_model: plumb_bob\n"
                  "distortion_coefficients: {rows: 1, cols: 5, data: [-0.3, 0.08, 0.003, -0.0002, 0]}\n")
    assert detect_format(path) == "opencv"
    (cam,) = _import([path]).rig.cameras
    assert cam.size == (800, 600) and cam.K[1, 2] == 297.0 and cam.dist[0] == -0.3
    path.write_text(path.read_text().replace("plumb_bob", "equidistant"))
    with pytest.raises(InputError) as err:
        _import([path])
    assert err.value.field == "distortion_model"
    path.write_text(path.read_text().replace("equidistant", "plumb_bob").replace("539.7", ".nan"))
    with pytest.raises(InputError, match="finite numbers expected") as err:
        _import([path])
    assert err.value.field == "camera_matrix.data"


@needs_opencv_data
def test_opencv_filestorage_nan_entries_are_named(tmp_path):
    """NaN or infinite entries of an OpenCV FileStorage matrix are named as such (the message said 'got shape
    (3, 3)' for a NaN focal length, and '5 distortion coefficients; one of ...' for an infinite k2)."""
    text = (OPENCV / "left_intrinsics.yml").read_text()
    bad = _write(tmp_path / "k.yml", text.replace("5.3591573396163199e+02, 0.,", ".nan, 0.,", 1))
    with pytest.raises(InputError, match="a finite 3x3 matrix expected, got 1 NaN or infinite entries") as err:
        _import([bad], image_sizes=[(640, 480)])
    assert err.value.field == "camera_matrix"
    bad = _write(tmp_path / "d.yml", text.replace("-3.8588898922304653e-02", ".Inf", 1))
    with pytest.raises(InputError, match="finite distortion coefficients expected, got 1 NaN or infinite") as err:
        _import([bad], image_sizes=[(640, 480)])
    assert err.value.field == "distortion_coefficients"


# ---------------------------------------------------------------------------------------------------------------------
# Rules: rotations, units, detection, rectified rigs
# ---------------------------------------------------------------------------------------------------------------------
def test_orthonormalise():
    Q = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    R, corr = orthonormalise(Q, "f", "R")
    assert R is not None and corr is None and np.array_equal(R, Q)  # a rotation is kept bit for bit
    # turn column 0 by alpha towards column 1: the nearest rotation splits the error, each column turns alpha / 2
    alpha = 5e-5
    B = Q.copy()
    B[:, 0] = np.cos(alpha) * Q[:, 0] + np.sin(alpha) * Q[:, 1]
    R, corr = orthonormalise(B, "f", "R")
    assert np.abs(R.T @ R - np.eye(3)).max() < 1e-15 and np.linalg.det(R) == pytest.approx(1, abs=1e-15)
    assert corr["deviation"] == pytest.approx(np.sin(alpha), rel=1e-9)
    assert corr["angle_deg"] == pytest.approx(np.degrees(alpha / 2), rel=1e-6)
    np.testing.assert_allclose(R, Q @ Rotation.from_rotvec([0, 0, alpha / 2]).as_matrix(), atol=1e-12)
    # a uniform scale error (6 printed decimals) moves no axis
    R, corr = orthonormalise(Q * (1 - 5e-7), "f", "R")
    np.testing.assert_allclose(R, Q, atol=1e-15)
    assert corr["angle_deg"] < 1e-12 and corr["deviation"] == pytest.approx(1e-6, rel=1e-6)
    B[:, 0] = np.cos(3e-4) * Q[:, 0] + np.sin(3e-4) * Q[:, 1]
    with pytest.raises(InputError, match="not a rotation") as err:
        orthonormalise(B, "f.txt", "R")
    assert (err.value.path, err.value.field) == ("f.txt", "R") and f"> {ORTHO_TOL:g}" in err.value.reason
    with pytest.raises(InputError, match="det R"):
        orthonormalise(-Q, "f.txt", "R")


def test_convert_units():
    rig = Rig((Camera("a", 10, 10, np.diag([5.0, 5, 1])),
               Camera("b", 10, 10, np.diag([5.0, 5, 1]), cam_from_rig=pose_matrix(np.eye(3), [-3.0, 4.0, 0.0]))))
    assert rig_span(rig) == (5.0, "a-b")
    with pytest.raises(InputError) as err:
        convert_units(rig, None, "p.txt", "T")
    squares = ". A file of OpenCV's stereo_calib.cpp holds T in board squares: multiply it by the square size first"
    assert str(err.value) == ("p.txt: T: baseline 5 m (a-b): translations look like millimetres; pass --units mm "
                              "(or --units m if the rig really spans 5 m)" + squares)
    assert units_message(5.520739) == ("baseline 5.52 m: translations look like millimetres; pass --units mm (or "
                                       "--units m if the rig really spans 5.52 m)" + squares)
    # beyond what a rig file holds (1000 m), --units m is not offered (it would be refused)
    assert units_message(1220.0) == "baseline 1.22e+03 m: translations look like millimetres; pass --units mm" + squares
    for units, scale in (("mm", 1e-3), ("cm", 1e-2), ("m", 1.0)):
        out, record = convert_units(rig, units)
        np.testing.assert_array_equal(out[1].t, np.array([-3.0, 4.0, 0.0]) * scale)
        assert record["scale_to_m"] == scale and record["units"] == units
        np.testing.assert_array_equal(out[1].R, rig[1].R)


def test_detect_format(tmp_path, colmap_rig):
    write_colmap(tmp_path / "colmap", colmap_rig)
    assert detect_format(tmp_path / "colmap") == "colmap"
    assert detect_format(tmp_path / "colmap" / "rigs.txt") == "colmap"
    other = _write(tmp_path / "notes.yaml", "hello: world\n")
    with pytest.raises(InputError) as err:
        detect_format(other)
    assert err.value.path == str(other) and err.value.field == "format"
    assert "opencv, kalibr, colmap, caliscope, text" in err.value.reason
    with pytest.raises(InputError, match="no such"):
        detect_format(tmp_path / "missing.yml")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="neither cameras.txt"):
        detect_format(tmp_path / "empty")
    k = _write(tmp_path / "k.txt", "500 0 320\n0 510 240\n0 0 1\n")
    with pytest.raises(InputError, match="different formats"):
        plan_import([k, tmp_path / "colmap"])


def test_rectified_rig():
    """A point at depth Z projects with disparity f B / Z on the same row; principal point at ((W-1)/2, (H-1)/2)."""
    rig = rectified_rig(360, 288, 400.0, 0.005)
    left, right = rig.cameras
    assert left.K.tolist() == right.K.tolist() == [[400.0, 0, 179.5], [0, 400.0, 143.5], [0, 0, 1]]
    np.testing.assert_array_equal(right.cam_from_rig, pose_matrix(np.eye(3), [-0.005, 0, 0]))
    np.testing.assert_array_equal(right.centre, [0.005, 0, 0])
    X = np.array([[0.003, -0.002, 0.08]])
    uv = rig.project(X)[:, 0]
    assert uv[0, 0] - uv[1, 0] == pytest.approx(400.0 * 0.005 / 0.08, rel=1e-12)
    assert uv[0, 1] == uv[1, 1]
    assert rectified_rig(360, 288, 400.0, 0.005, (170.0, 150.0))[1].K[:2, 2].tolist() == [170.0, 150.0]
