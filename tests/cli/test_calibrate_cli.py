"""``heartcv calibrate`` on OpenCV's stereo photographs (../shared/data/opencv_stereo), linked into a temporary
camera folder: outputs, JSON summary, exports, bad images, failures and exit codes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import main
from heartcv.targets import TargetSpec

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "opencv_stereo"
PAIRS = ["01", "02", "03", "04", "05", "06", "07", "08", "09", "11", "12", "13", "14"]

pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="shared data not available")


def _camera_folder(root: Path, pairs, cam_pairs=None) -> Path:
    """root/cam0, root/cam1 with symlinks to left/right images named NN.jpg (cam_pairs: pairs per camera)."""
    cam_pairs = cam_pairs or [pairs, pairs]
    for cam, side, names in (("cam0", "left", cam_pairs[0]), ("cam1", "right", cam_pairs[1])):
        (root / cam).mkdir(parents=True)
        for n in names:
            (root / cam / f"{n}.jpg").symlink_to(DATA / f"{side}{n}.jpg")
    return root


@pytest.fixture(scope="module")
def target(tmp_path_factory):
    from heartcv.io import write_target

    path = tmp_path_factory.mktemp("target") / "chess9x6.yaml"
    write_target(path, TargetSpec("chessboard", (9, 6), 0.025, name="chess9x6"))
    return path


def _run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_calibrate_stereo_pairs(tmp_path, target):
    """All 13 pairs: exit 0, the JSON keys of the issue, the rig file read back, COLMAP export; the default
    5-coefficient model has a k3 that Kalibr's radtan cannot hold, so no camchain is written (a warning)."""
    from heartcv.io import read_rig

    folder = _camera_folder(tmp_path / "calib", PAIRS)
    out = tmp_path / "out" / "rig.yaml"
    res = _run("calibrate", folder, "--target", target, "-o", out, "--json")
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["rms_px"] < 0.45 * 1.1
    assert summary["baselines_m"] == {"cam0-cam1": pytest.approx(0.0835, abs=0.0005)}
    assert [c["name"] for c in summary["cameras"]] == ["cam0", "cam1"]
    for c in summary["cameras"]:
        assert {"name", "rms_px", "fx", "fy", "cx", "cy", "views_used"} <= set(c)
        assert c["views_used"] == 13 and 520 < c["fx"] < 550
    rig = read_rig(out)
    assert rig.names == ["cam0", "cam1"]
    assert rig.meta["producer"] == "heartcv calibrate" and rig.meta["target"]["name"] == "chess9x6"
    assert rig.meta["rms_px"] == pytest.approx(summary["rms_px"])
    assert rig.meta["cameras"]["cam1"]["views_used"] == 13
    assert len(rig.meta["cameras"]["cam1"]["per_view_errors"]) == 13
    assert rig.meta["view_names"] == PAIRS
    assert np.allclose(rig[0].cam_from_rig, np.eye(4))
    assert (out.parent / "rig_colmap" / "cameras.txt").is_file() and (out.parent / "rig_colmap" / "rigs.txt").is_file()
    assert summary["exports"]["kalibr"] is None and "k3" in summary["exports"]["kalibr_skipped"]
    assert not (out.parent / "rig_camchain.yaml").exists()
    assert "no Kalibr camchain written" in res.stderr


def test_bad_images_named_and_skipped(tmp_path, target):
    """An unreadable image and a wrong-sized one are named in warnings and skipped; --dist 4 writes Kalibr."""
    import cv2

    folder = _camera_folder(tmp_path / "calib", PAIRS[:6])
    (folder / "cam0" / "07.jpg").write_bytes(b"not a jpeg at all")
    small = cv2.resize(cv2.imread(str(DATA / "right07.jpg")), (320, 240))
    cv2.imwrite(str(folder / "cam1" / "07.png"), small)
    out = tmp_path / "rig.yaml"
    res = _run("calibrate", folder, "--target", target, "-o", out, "--dist", "4", "--json")
    assert res.exit_code == 0, res.output
    assert "07.jpg" in res.stderr and "not a readable image" in res.stderr
    assert "cam1/07: image is 320x240 px, the camera's other images are 640x480 px" in res.stderr
    summary = json.loads(res.stdout)
    assert [c["views_used"] for c in summary["cameras"]] == [6, 6]
    assert summary["views"] == 7 and summary["dist_model"] == 4
    assert all(len(c["dist"]) == 4 for c in summary["cameras"])
    assert Path(summary["exports"]["kalibr"]).is_file()


def test_failures_exit_1(tmp_path, target):
    from heartcv.io import write_target

    few = _camera_folder(tmp_path / "few", PAIRS[:3])
    res = _run("calibrate", few, "--target", target, "-o", tmp_path / "few.yaml")
    assert res.exit_code == 1
    assert "too few usable views: cam0 3, cam1 3 (at least 4 per camera needed)" in res.stderr
    assert not (tmp_path / "few.yaml").exists()

    wrong = tmp_path / "wrong.yaml"
    write_target(wrong, TargetSpec("chessboard", (7, 5), 0.025))
    res = _run("calibrate", few, "--target", wrong, "-o", tmp_path / "w.yaml")
    assert res.exit_code == 1 and "was found in none of the 6 images" in res.stderr
    assert not (tmp_path / "w.yaml").exists()

    split = _camera_folder(tmp_path / "split", None, [PAIRS[:5], PAIRS[5:10]])
    res = _run("calibrate", split, "--target", target, "-o", tmp_path / "s.yaml")
    assert res.exit_code == 1 and "cameras cam1 share no usable view with cam0" in res.stderr


def test_bad_usage_exit_2(tmp_path, target):
    folder = _camera_folder(tmp_path / "calib", PAIRS[:1])
    assert _run("calibrate", folder, "--target", target, "-o", tmp_path / "rig.txt").exit_code == 2
    assert _run("calibrate", tmp_path / "nope", "--target", target, "-o", tmp_path / "r.yaml").exit_code == 2
    res = _run("calibrate", folder / "cam0", "--target", target, "-o", tmp_path / "r.yaml")
    assert res.exit_code == 2 and "0 camera(s) found" in res.stderr
    bad_target = tmp_path / "t.yaml"
    bad_target.write_text("format: heartcv.target\ntype: chessboard\n")
    res = _run("calibrate", folder, "--target", bad_target, "-o", tmp_path / "r.yaml")
    assert res.exit_code == 2 and "t.yaml" in res.stderr


def test_videos(tmp_path, target):
    """One video per camera (MJPEG AVI of 8 pairs), every 2nd frame: 4 instants per camera, too few at
    --min-views 5 (exit 1, counts named), calibrated at the default of 4."""
    import cv2

    folder = tmp_path / "videos"
    folder.mkdir()
    for cam, side in (("left", "left"), ("right", "right")):
        w = cv2.VideoWriter(str(folder / f"{cam}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (640, 480))
        if not w.isOpened():
            pytest.skip("no MJPEG video writer in this OpenCV build")
        for n in PAIRS[:8]:
            w.write(cv2.imread(str(DATA / f"{side}{n}.jpg")))
        w.release()
    res = _run("calibrate", folder, "--target", target, "-o", tmp_path / "v.yaml", "--every", "2", "--min-views", "5")
    assert res.exit_code == 1 and "too few usable views: left 4, right 4" in res.stderr
    res = _run("calibrate", folder, "--target", target, "-o", tmp_path / "v.yaml", "--every", "2", "--json")
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert [c["name"] for c in summary["cameras"]] == ["left", "right"] and summary["views"] == 4
    from heartcv.io import read_rig

    assert read_rig(tmp_path / "v.yaml").meta["view_names"] == ["frame000000", "frame000002", "frame000004",
                                                                "frame000006"]


def test_camera_without_readable_images(tmp_path, target):
    folder = _camera_folder(tmp_path / "calib", PAIRS[:5])
    for p in (folder / "cam1").iterdir():
        p.unlink()
        p.write_bytes(b"\x89PNG\r\n\x1a\n broken")
    res = _run("calibrate", folder, "--target", target, "-o", tmp_path / "r.yaml")
    assert res.exit_code == 1, res.output
    assert "cam1: none of its 5 images could be read" in res.stderr
    assert "too few usable views: cam0 5, cam1 0 (no readable image)" in res.stderr
