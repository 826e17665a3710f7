"""heartcv.io: images, target files, rig files (exact round trip, cv2.FileStorage), COLMAP export (read back
with pycolmap, projections compared) and Kalibr export (field by field)."""

import os
import re

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
import yaml

from heartcv import __version__
from heartcv.camera import Camera, Rig, pose_matrix
from heartcv.io import (
    HeartcvIOError,
    atomic_path,
    colmap_camera,
    dump_yaml,
    kalibr_camchain,
    list_image_folder,
    read_image,
    read_rig,
    read_target,
    rig_from_dict,
    rig_to_dict,
    write_board_image,
    write_colmap,
    write_image,
    write_kalibr,
    write_rig,
    write_target,
)
from heartcv.targets import INCH_M, TargetSpec, render_board

TARGET = TargetSpec("charuco", (11, 8), 0.012, 0.009, "DICT_5X5_250", name="default")


def _rig(rng, n_dist=(5, 8, 5)):
    """Three cameras with irrational-looking numbers (every float digit matters for the round trip)."""
    cams = []
    for i, n in enumerate(n_dist):
        K = np.array([[5972.696245733788 + rng.normal(), 0, 959.5 + rng.normal()],
                      [0, 5970.1 + rng.normal(), 539.5 + rng.normal()], [0, 0, 1]])
        dist = rng.normal(scale=[0.1, 0.05, 1e-3, 1e-3, 0.01, 0.01, 1e-3, 1e-4][:n])
        T = np.eye(4) if i == 0 else pose_matrix(Rotation.from_rotvec(rng.normal(scale=0.5, size=3)).as_matrix(),
                                                 rng.normal(scale=0.3, size=3))
        cams.append(Camera(f"cam{i}", 1920, 1080, K, dist, T))
    per_cam = {c.name: {"rms_px": float(rng.uniform(0.05, 0.2)), "views_used": 17,
                        "per_view_errors": rng.uniform(0.05, 0.3, 5).tolist(),
                        "std": {"fx": 0.31, "fy": 0.29, "cx": 0.5, "cy": 0.45, "k1": 1e-3, "k2": 0.01,
                                "p1": 1e-5, "p2": 1e-5, "k3": 0.1, "rotation_deg": [1e-3, 2e-3, 1.5e-3],
                                "translation_m": [1e-5, 2e-5, 3e-5]}} for c in cams}
    meta = {"producer": "heartcv calibrate", "inputs_hash": {"target": "sha256:0123abcd", "images": "sha256:99"},
            "rms_px": 0.1234567890123, "target": TARGET.to_dict(), "cameras": per_cam}
    return Rig(tuple(cams), meta)


# -- rig file ---------------------------------------------------------------------------------------------------------
def test_rig_round_trip_is_exact(tmp_path, rng):
    rig = _rig(rng)
    path = tmp_path / "rig.yaml"
    write_rig(path, rig)
    back = read_rig(path)
    assert back.names == rig.names
    for a, b in zip(rig.cameras, back.cameras):
        assert (a.width, a.height) == (b.width, b.height)
        for k in ("K", "dist", "cam_from_rig"):
            assert np.array_equal(getattr(a, k), getattr(b, k)), k  # bit for bit (float repr)
    assert back.meta == dict(rig.meta, heartcv_version=__version__)
    d = yaml.safe_load(path.read_text())
    assert (d["format"], d["format_version"], d["rig_frame"]) == ("heartcv.rig", 1, "cam0")
    assert d["baselines_m"] == pytest.approx(rig.baselines(), rel=1e-15)
    assert d["cameras"][1]["dist_names"] == ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"]
    assert d["cameras"][0]["distortion_model"] == "opencv" and d["cameras"][0]["image_size"] == [1920, 1080]
    # writing what was read gives the same bytes (apart from nothing: same version)
    write_rig(tmp_path / "again.yaml", back)
    assert (tmp_path / "again.yaml").read_text() == path.read_text()


def test_rig_file_is_readable_by_cv2_filestorage(tmp_path, rng):
    rig = _rig(rng)
    path = tmp_path / "rig.yaml"
    write_rig(path, rig)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    for i, cam in enumerate(rig.cameras):
        node = fs.getNode("cameras").at(i)
        assert node.getNode("name").string() == cam.name
        Kn = node.getNode("K")
        K = np.array([[Kn.at(r).at(c).real() for c in range(3)] for r in range(3)])
        assert np.array_equal(K, cam.K)
        dn = node.getNode("dist")
        assert np.array_equal([dn.at(j).real() for j in range(dn.size())], cam.dist)
        Tn = node.getNode("cam_from_rig")
        assert np.array_equal([[Tn.at(r).at(c).real() for c in range(4)] for r in range(4)], cam.cam_from_rig)
    assert fs.getNode("rms_px").real() == rig.meta["rms_px"]
    assert fs.getNode("heartcv_version").string() == __version__
    assert fs.getNode("target").getNode("dictionary").string() == "DICT_5X5_250"
    fs.release()


def test_rig_file_with_long_strings_and_hashes_is_readable_by_cv2_filestorage(tmp_path, rng):
    """What real calibrations write: warnings longer than a line (PyYAML folded them onto a second line, which
    cv2.FileStorage cannot read) and hashes 'sha256:<hex>' whose hex starts with a digit (a plain scalar with a
    colon OpenCV misreads). Both come back from OpenCV exactly, and from heartcv's reader."""
    rig = _rig(rng)
    warning = ("cam1: the corners cover 12 % of the image; k2 and k3 held at 0 for want of coverage, "
               "and the principal point's uncertainty is 41 px: more views near the corners of the image would "
               "determine it (docs/cli.md 8.4) # not a comment")
    digest = "sha256:0" + "1a2b3c4d" * 7 + "9e8f7a6"
    rig = Rig(rig.cameras, dict(rig.meta, warnings=[warning, "short: one"], inputs_hash={"target": digest},
                                method="x" * 300))
    path = tmp_path / "rig.yaml"
    write_rig(path, rig)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    assert fs.getNode("warnings").at(0).string() == warning
    assert fs.getNode("warnings").at(1).string() == "short: one"
    assert fs.getNode("inputs_hash").getNode("target").string() == digest
    assert fs.getNode("method").string() == "x" * 300
    assert fs.getNode("cameras").at(1).getNode("K").at(0).at(0).real() == rig.cameras[1].K[0, 0]
    fs.release()
    back = read_rig(path)
    assert back.meta["warnings"] == [warning, "short: one"] and back.meta["inputs_hash"] == {"target": digest}


def test_rig_without_meta_and_custom_frame(tmp_path):
    c0 = Camera("left", 640, 480, np.diag([500.0, 500, 1]), np.zeros(0), pose_matrix(np.eye(3), [0.1, 0, 0]))
    c1 = Camera("right", 640, 480, np.diag([500.0, 500, 1]), np.zeros(14))
    path = tmp_path / "r.yaml"
    write_rig(path, Rig((c0, c1)))
    assert yaml.safe_load(path.read_text())["rig_frame"] == "custom"
    back = read_rig(path)
    assert back.meta == {"heartcv_version": __version__} and back[0].dist.size == 0 and back[1].dist.size == 14


def _rig_dict(rng):
    return rig_to_dict(_rig(rng))


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.update(format="heartcv.target"), "format: 'heartcv.rig' expected"),
    (lambda d: d.update(format_version=2), "format_version: 1 supported"),
    (lambda d: d.update(cameras=[]), "cameras: a non-empty list"),
    (lambda d: d["cameras"][1].pop("K"), r"cameras\[1\]: missing \['K'\]"),
    (lambda d: d["cameras"][1].update(K=[[1, 0], [0, 1]]), r"cameras\[1\] \(cam1\).K: shape"),
    (lambda d: d["cameras"][1].update(dist=[0.1, 0.2, 0.3]), "3 distortion coefficients"),
    (lambda d: d["cameras"][0].update(dist_names=["k1", "k2", "p2", "p1", "k3"]), "dist_names"),
    (lambda d: d["cameras"][0].update(distortion_model="fisheye"), "distortion_model"),
    (lambda d: d["cameras"][2].update(cam_from_rig=np.diag([1.0, 1, 1.01, 1]).tolist()), "not a rigid"),
    (lambda d: d["cameras"][2].update(name="cam0"), "unique"),
    (lambda d: d["cameras"][2].update(image_size=[1920]), "image_size"),
    (lambda d: d["cameras"][2].update(K=[[1, 0, "x"], [0, 1, 0], [0, 0, 1]]), "numbers expected"),
    (lambda d: d["cameras"][2].update(rms_px=-1), "rms_px"),
    (lambda d: d["cameras"][2].update(per_view_errors="big"), "per_view_errors"),
    (lambda d: d["cameras"][2].update(std={"fx": "x"}), "std"),
    (lambda d: d.update(rig_frame="cam1"), "not the identity"),
    (lambda d: d.update(rig_frame="camX"), "rig_frame"),
    (lambda d: d["target"].update(square_m=-1), "target.square_m: square size"),
])
def test_read_rig_errors_name_file_and_field(tmp_path, rng, edit, match):
    d = _rig_dict(rng)
    edit(d)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(HeartcvIOError, match=match) as exc:
        read_rig(path)
    assert str(exc.value).startswith(str(path))


def test_read_rig_file_errors(tmp_path):
    with pytest.raises(HeartcvIOError, match="no such rig file"):
        read_rig(tmp_path / "none.yaml")
    (tmp_path / "bad.yaml").write_text("cameras: [\n")
    with pytest.raises(HeartcvIOError, match="not valid YAML"):
        read_rig(tmp_path / "bad.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n")
    with pytest.raises(HeartcvIOError, match="mapping expected"):
        read_rig(tmp_path / "list.yaml")


def test_rig_to_dict_rejects_bad_meta(rng):
    rig = _rig(rng)
    with pytest.raises(ValueError, match="no camera named"):
        rig_to_dict(Rig(rig.cameras, {"cameras": {"camX": {}}}))
    with pytest.raises(ValueError, match="reserved"):
        rig_to_dict(Rig(rig.cameras, {"cameras": {"cam0": {"K": 1}}}))
    assert rig_from_dict(rig_to_dict(Rig(rig.cameras))).meta == {"heartcv_version": __version__}
    partial = Rig(rig.cameras, {"cameras": {"cam1": {"rms_px": 0.2}}})
    assert rig_from_dict(rig_to_dict(partial)).meta == dict(partial.meta, heartcv_version=__version__)


def test_dump_yaml_quotes_number_like_strings_and_keeps_floats():
    text = dump_yaml({"v": "0.1.0", "h": "sha256:ab", "x": 1e-05, "l": [[1.0, 2.5e-300]]}, header="a\nb")
    assert text.startswith("# a\n# b\n") and "v: '0.1.0'" in text
    assert yaml.safe_load(text) == {"v": "0.1.0", "h": "sha256:ab", "x": 1e-05, "l": [[1.0, 2.5e-300]]}


# -- COLMAP ---------------------------------------------------------------------------------------------------------
def test_colmap_export_read_back_with_pycolmap(tmp_path, rng):
    pycolmap = pytest.importorskip("pycolmap")
    rig = _rig(rng, n_dist=(5, 8, 4))
    rig = Rig(rig.cameras[:2] + (Camera("cam2", 1920, 1080, rig[2].K, np.r_[rig[2].dist, 0.0],  # k3 = 0
                                        rig[2].cam_from_rig),))
    ids = write_colmap(tmp_path, rig)
    assert ids == {"cam0": 1, "cam1": 2, "cam2": 3}
    for name in ("frames.txt", "images.txt", "points3D.txt"):  # an otherwise empty model
        (tmp_path / name).write_text("")
    rec = pycolmap.Reconstruction()
    rec.read_text(str(tmp_path))
    # 5 coefficients with k3 != 0 and 8 coefficients need FULL_OPENCV; k3 = 0 fits OPENCV
    assert [rec.cameras[i].model.name for i in (1, 2, 3)] == ["FULL_OPENCV", "FULL_OPENCV", "OPENCV"]
    X = np.c_[rng.uniform(-0.1, 0.1, (50, 2)), rng.uniform(0.4, 0.7, 50)]
    for cam in rig.cameras:
        pc = rec.cameras[ids[cam.name]]
        assert (pc.width, pc.height) == (cam.width, cam.height)
        # independent implementation: COLMAP's projection = ours + 0.5 px (pixel-corner vs pixel-centre origin)
        assert np.abs(pc.img_from_cam(X) - (cam.project_cam(X) + 0.5)).max() < 1e-9
    crig = rec.rigs[1]
    assert crig.ref_sensor_id.id == 1
    for sensor, pose in crig.non_ref_sensors.items():
        idx = sensor.id - 1
        assert np.allclose(pose.matrix(), rig.cam_from_cam(idx, 0)[:3], atol=1e-14)


def test_colmap_models_and_refusals(rng):
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    assert colmap_camera(Camera("a", 640, 480, K, np.zeros(0)))[0] == "PINHOLE"
    assert colmap_camera(Camera("a", 640, 480, K, [0.1, 0, 0, 0, 0.2]))[0] == "FULL_OPENCV"
    model, params = colmap_camera(Camera("a", 640, 480, K, np.r_[0.1, 0.2, 0, 0, 0.3, 0.01, 0, 0, np.zeros(6)]))
    assert model == "FULL_OPENCV" and params == [500, 500, 320.5, 240.5, 0.1, 0.2, 0, 0, 0.3, 0.01, 0, 0]
    with pytest.raises(ValueError, match=r"thin-prism or tilt.*'s2': 0.001"):
        colmap_camera(Camera("a", 640, 480, K, np.r_[np.zeros(9), 1e-3, 0, 0]))
    with pytest.raises(ValueError, match=r"'tau_y': 0.01"):
        colmap_camera(Camera("a", 640, 480, K, np.r_[np.zeros(13), 0.01]))
    Ks = K.copy()
    Ks[0, 1] = 0.5
    with pytest.raises(ValueError, match="skew"):
        colmap_camera(Camera("a", 640, 480, Ks))


# -- Kalibr ---------------------------------------------------------------------------------------------------------
def test_kalibr_camchain_field_by_field(tmp_path, rng):
    rig = _rig(rng, n_dist=(4, 5, 8))
    cams = [rig[0], Camera("cam1", 1920, 1080, rig[1].K, np.r_[rig[1].dist[:4], 0.0], rig[1].cam_from_rig),
            Camera("cam2", 1920, 1080, rig[2].K, np.r_[rig[2].dist[:4], np.zeros(4)], rig[2].cam_from_rig)]
    rig = Rig(tuple(cams))
    path = tmp_path / "camchain.yaml"
    write_kalibr(path, rig, rostopics={"cam2": "/right/image"})
    d = yaml.safe_load(path.read_text())
    assert list(d) == ["cam0", "cam1", "cam2"]
    for i, cam in enumerate(rig.cameras):
        e = d[f"cam{i}"]
        assert e["camera_model"] == "pinhole" and e["distortion_model"] == "radtan"
        assert e["intrinsics"] == [cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]]
        assert e["distortion_coeffs"] == cam.dist[:4].tolist()
        assert e["resolution"] == [1920, 1080]
        if i == 0:
            assert "T_cn_cnm1" not in e
        else:  # takes camera i-1 coordinates to camera i
            T = np.array(e["T_cn_cnm1"])
            X = rng.normal(size=(5, 3))
            assert np.allclose(rig[i].to_cam(X), rig[i - 1].to_cam(X) @ T[:3, :3].T + T[:3, 3], atol=1e-13)
    assert d["cam0"]["rostopic"] == "/cam0/image_raw" and d["cam2"]["rostopic"] == "/right/image"
    assert kalibr_camchain(rig)["cam1"]["T_cn_cnm1"][3] == [0.0, 0.0, 0.0, 1.0]


def test_kalibr_refuses_what_radtan_cannot_hold():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    with pytest.raises(ValueError, match=r"k1, k2, p1, p2 only; non-zero \{'k3': 0.01\}"):
        kalibr_camchain(Rig((Camera("a", 640, 480, K, [0.1, 0, 0, 0, 0.01]),)))
    Ks = K.copy()
    Ks[0, 1] = 1.0
    with pytest.raises(ValueError, match="skew"):
        kalibr_camchain(Rig((Camera("a", 640, 480, Ks),)))
    assert kalibr_camchain(Rig((Camera("a", 640, 480, K, np.zeros(0)),)))["cam0"]["distortion_coeffs"] == [0] * 4


# -- targets --------------------------------------------------------------------------------------------------------
def test_target_file_and_images(tmp_path):
    img, ppm = render_board(TARGET, 300, 0.012)
    png, pdf, yml = tmp_path / "t.png", tmp_path / "t.pdf", tmp_path / "t.yaml"
    size_m = (img.shape[1] / ppm, img.shape[0] / ppm)
    write_board_image(png, pdf, img, ppm * INCH_M, size_m)
    write_target(yml, TARGET, png=png, pdf=pdf, px_per_m=ppm, image_size=img.shape[::-1])
    assert read_target(yml) == TARGET
    d = yaml.safe_load(yml.read_text())
    assert d["image"]["png"] == "t.png" and d["image"]["pdf"] == "t.pdf"
    assert d["image"]["dpi"] == pytest.approx(298.45) and d["image"]["square_px"] == 141
    assert d["image"]["margin_m"] == pytest.approx(0.012) and d["heartcv_version"] == __version__
    assert d["board_size_m"] == pytest.approx([0.132, 0.096])
    from PIL import Image

    with Image.open(png) as im:
        assert im.size == (img.shape[1], img.shape[0]) and im.info["dpi"] == pytest.approx((298.45, 298.45))
        assert np.array_equal(np.asarray(im), img)
    raw = png.read_bytes()
    i = raw.index(b"pHYs")
    assert int.from_bytes(raw[i + 4:i + 8], "big") == 11750 and raw[i + 12] == 1  # px per metre, unit metre
    box = re.search(rb"/MediaBox \[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", pdf.read_bytes())
    assert float(box[1]) == pytest.approx(size_m[0] / INCH_M * 72, abs=1e-6)  # points: 1/72 inch
    assert float(box[2]) == pytest.approx(size_m[1] / INCH_M * 72, abs=1e-6)
    with pytest.raises(ValueError, match="is not"):
        write_board_image(png, None, img, 300, size_m)


@pytest.mark.parametrize("text, match", [
    ("format: heartcv.rig\n", "format: 'heartcv.target' expected"),
    ("type: charuco\nsquares: [3, 3]\nsquare_m: 0.01\nmarker_m: 0.02\ndictionary: DICT_4X4_50\n", "marker size"),
    ("type: chessboard\ninner_corners: [3, 3]\nsquare_m: 0.01\nimage: t.png\n", "image: a mapping"),
    # the informative image block and board size, hand-edited: refused, not carried on (NaN is refused everywhere)
    ("type: chessboard\ninner_corners: [3, 3]\nsquare_m: 0.01\nimage: {px_per_m: .nan}\n",
     "image.px_per_m: a finite positive number expected"),
    ("type: chessboard\ninner_corners: [3, 3]\nsquare_m: 0.01\nimage: {colour: blue}\n", "image.colour: unknown key"),
    ("type: chessboard\ninner_corners: [3, 3]\nsquare_m: 0.01\nimage: {dpi: 1" + "0" * 400 + "}\n",
     "image.dpi: a finite positive number expected, got an integer of about 10"),     # beyond float (fuzz)
    ("type: chessboard\ninner_corners: [3, 3]\nsquare_m: 0.01\nimage: {size_px: [10]}\n",
     "image.size_px: two finite positive numbers"),
    ("type: chessboard\ninner_corners: [3, 3]\nsquare_m: 0.01\nimage: {png: 3}\n", "image.png: a file name"),
    ("type: chessboard\ninner_corners: [3, 3]\nsquare_m: 0.01\nboard_size_m: [9, 9]\n",
     r"board_size_m: \[0.04, 0.04\] \(the board the other keys describe\) expected"),
    ("[1, 2]\n", "mapping expected"),
])
def test_read_target_errors(tmp_path, text, match):
    path = tmp_path / "t.yaml"
    path.write_text(text)
    with pytest.raises(HeartcvIOError, match=match) as exc:
        read_target(path)
    assert exc.value.path == str(path)


# -- images ---------------------------------------------------------------------------------------------------------
def test_read_image_modes_and_errors(tmp_path):
    img = (np.arange(48 * 64) % 251).astype(np.uint8).reshape(48, 64)
    write_image(tmp_path / "a.png", img)
    assert np.array_equal(read_image(tmp_path / "a.png"), img)
    assert read_image(tmp_path / "a.png", mode="color").shape == (48, 64, 3)
    assert read_image(tmp_path / "a.png", expected_size=(64, 48)).shape == (48, 64)
    with pytest.raises(HeartcvIOError, match="64x48 px, 640x480 expected"):
        read_image(tmp_path / "a.png", expected_size=(640, 480))
    with pytest.raises(HeartcvIOError, match="no such image file"):
        read_image(tmp_path / "missing.png")
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(HeartcvIOError, match="empty file"):
        read_image(tmp_path / "empty.png")
    (tmp_path / "junk.png").write_bytes(b"this is not an image at all")
    with pytest.raises(HeartcvIOError, match="not a readable image"):
        read_image(tmp_path / "junk.png")
    raw = (tmp_path / "a.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(HeartcvIOError, match="truncated PNG"):
        read_image(tmp_path / "cut.png")
    write_image(tmp_path / "b.jpg", img)
    raw = (tmp_path / "b.jpg").read_bytes()
    (tmp_path / "cut.jpg").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(HeartcvIOError, match="truncated JPEG") as exc:
        read_image(tmp_path / "cut.jpg")
    assert exc.value.path == str(tmp_path / "cut.jpg")
    with pytest.raises(HeartcvIOError, match="not a file"):
        read_image(tmp_path)


def test_list_image_folder_natural_order(tmp_path):
    names = ["img10.png", "img2.png", "img1.PNG", "Img3.jpg", "x.tiff", "y.bmp", "z.jpeg", "notes.txt",
             ".img0.png.tmp123.png"]
    for n in names:
        (tmp_path / n).write_bytes(b"")
    (tmp_path / "sub.png").mkdir()
    assert [p.name for p in list_image_folder(tmp_path)] == ["img1.PNG", "img2.png", "Img3.jpg", "img10.png",
                                                             "x.tiff", "y.bmp", "z.jpeg"]
    with pytest.raises(HeartcvIOError, match="no such folder"):
        list_image_folder(tmp_path / "nope")
    with pytest.raises(HeartcvIOError, match="not a folder"):
        list_image_folder(tmp_path / "img2.png")


def test_pair_instants_by_stem_then_by_frame_number():
    """Image files pair by stem; cameras that share none pair by the last number in their names when it is unique
    in each camera (left-0007 / right-0007), the instant named after the first camera's file; no pairing at all
    is a ValueError naming the cameras and an example file of each."""
    from pathlib import Path

    from heartcv.io import pair_instants

    def files(*stems):
        return [Path(f"/x/{s}.png") for s in stems]

    inst, per, by = pair_instants(["a", "b"], [files("1", "2", "10"), files("2", "10", "11")])
    assert by == "stem" and inst == ["1", "2", "10", "11"]
    assert per[1]["10"] == Path("/x/10.png") and "1" not in per[1]
    inst, per, by = pair_instants(["left", "right"], [files("left-9", "left-10", "left-11"),
                                                      files("right-10", "right-11", "right-12")])
    assert by == "number" and inst == ["left-9", "left-10", "left-11", "right-12"]
    assert per[1]["left-10"] == Path("/x/right-10.png") and per[0]["left-10"] == Path("/x/left-10.png")
    assert "left-9" not in per[1] and per[1]["right-12"] == Path("/x/right-12.png")
    # camera indices in the names do not count: the last number does (cam0_0001 / cam1_0001)
    inst, per, by = pair_instants(["cam0", "cam1"], [files("cam0_0001", "cam0_0002"), files("cam1_0001", "cam1_0002")])
    assert by == "number" and inst == ["cam0_0001", "cam0_0002"] and per[1]["cam0_0002"].name == "cam1_0002.png"
    inst, per, by = pair_instants(["L"], [files("a", "b")])          # one camera: its stems
    assert by == "stem" and inst == ["a", "b"]
    with pytest.raises(ValueError, match=r"camera\(s\) right \('right-b'\) share no file name \(stem\) with left "
                                         r"\('left-a'\)"):
        pair_instants(["left", "right"], [files("left-a"), files("right-b")])       # no number
    with pytest.raises(ValueError, match="share no file name"):
        pair_instants(["left", "right"], [files("l-1", "l-2"), files("r-3", "r-4")])    # numbers never meet
    with pytest.raises(ValueError, match="share no file name"):
        pair_instants(["left", "right"], [files("l1-1", "l2-1"), files("r-1")])    # a number twice in a camera


def test_frames_named_by_decimal_seconds_are_in_time_order(tmp_path):
    """Stems that are all decimal numbers (a recorder naming frames by their time in seconds) sort by value, as a
    brute-force sort of the floats does; a folder of them lists in the same order; any other stem among them
    brings back natural order (img2 before img10)."""
    from pathlib import Path

    from heartcv.io import list_image_folder, pair_instants, sort_names

    rng = np.random.default_rng(3)
    times = np.round(np.cumsum(rng.uniform(0.01, 0.3, 40)), 3)
    stems = [f"{t:.3f}".rstrip("0").rstrip(".") if t % 1 else f"{t:.1f}" for t in times]
    shuffled = list(rng.permutation(stems))
    assert [float(x) for x in sort_names(shuffled)] == sorted(float(x) for x in stems)
    inst, _, by = pair_instants(["l", "r"], [[Path(f"/x/{s}.png") for s in shuffled]] * 2)
    assert by == "stem" and inst == sort_names(stems) and inst[:3] == [stems[0], stems[1], stems[2]]
    for s in shuffled[:12]:
        (tmp_path / f"{s}.png").write_bytes(b"")
    assert [p.stem for p in list_image_folder(tmp_path)] == sorted(shuffled[:12], key=float)
    # a ROS-style stamp with nanoseconds keeps its precision
    assert sort_names(["1613501234.000000002", "1613501234.000000001"]) == ["1613501234.000000001",
                                                                            "1613501234.000000002"]
    assert sort_names(["0.2", "0.04", "img10", "img2"]) == ["0.2", "0.04", "img2", "img10"]   # natural: not all numbers
    assert sort_names(["10", "9", "100"]) == ["9", "10", "100"]


def test_atomic_path_keeps_old_file_on_failure(tmp_path):
    path = tmp_path / "sub" / "f.txt"
    with atomic_path(path) as tmp:
        tmp.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(path) as tmp:
            tmp.write_text("new, half written")
            raise RuntimeError("interrupted")
    assert path.read_text() == "old" and os.listdir(path.parent) == ["f.txt"]
