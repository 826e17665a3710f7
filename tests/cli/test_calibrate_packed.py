"""``heartcv calibrate --packed``: a stereo camera that records both views into one frame, calibrated from that
recording as it is.

On OpenCV's 13 real stereo pairs (../shared/data/opencv_stereo, 9x6 chessboard, 25 mm), packed by this test:
the rig from the packed frames must equal, value for value, the rig from the same views stored one folder per
camera (only the input hash differs: the files differ). For an MJPG video, the views cut from the decoded
frames by plain OpenCV are the oracle. Bad usage exits 2 naming the cause, with nothing written.
"""

from __future__ import annotations

from click.testing import CliRunner
import numpy as np
import pytest

from heartcv.cli.main import main
from tests.conftest import SHARED_DATA, assert_exit_2

DATA = SHARED_DATA / "opencv_stereo"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="shared data not available (opencv_stereo)")


def _run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _pairs():
    import cv2

    for left in sorted(DATA.glob("left*.jpg")):
        right = left.with_name(left.name.replace("left", "right"))
        yield left.stem.replace("left", ""), [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in (left, right)]


@pytest.fixture(scope="module")
def target(tmp_path_factory):
    path = tmp_path_factory.mktemp("target") / "t.yaml"
    res = _run("target", "--type", "chessboard", "--inner-corners", "9x6", "--square-mm", "25", "-o", path)
    assert res.exit_code == 0, res.output
    return path


def _calibrate(folder, target, out, *extra):
    res = _run("-q", "calibrate", folder, "--target", target, "-o", out, "--folds", "0", *extra)
    return res


def _rig_without_hash(path):
    import yaml

    d = yaml.safe_load(path.read_text())
    d.pop("inputs_hash")
    return d


def _write_folders(root, frames):
    """``root/cam0``, ``root/cam1``: the views as lossless PNG, one folder per camera."""
    import cv2

    for stem, views in frames:
        for c, v in enumerate(views):
            (root / f"cam{c}").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / f"cam{c}" / f"{stem}.png"), v)


@needs_data
def test_packed_side_by_side_images_give_the_rig_of_the_separate_views(target, tmp_path):
    import cv2

    frames = list(_pairs())
    assert len(frames) == 13
    _write_folders(tmp_path / "separate", frames)
    (tmp_path / "packed" / "stereo").mkdir(parents=True)
    for stem, (left, right) in frames:
        cv2.imwrite(str(tmp_path / "packed" / "stereo" / f"{stem}.png"), np.concatenate([left, right], axis=1))
    res = _calibrate(tmp_path / "separate", target, tmp_path / "a.yaml")
    assert res.exit_code == 0, res.output
    res = _calibrate(tmp_path / "packed", target, tmp_path / "b.yaml", "--packed", "side-by-side")
    assert res.exit_code == 0, res.output
    a, b = _rig_without_hash(tmp_path / "a.yaml"), _rig_without_hash(tmp_path / "b.yaml")
    assert a == b
    assert a["baselines_m"]["cam0-cam1"] == pytest.approx(0.0835, abs=0.001)      # the data set's own number


@needs_data
def test_packed_top_bottom_video_with_named_cameras(target, tmp_path):
    """An MJPG top-bottom video; the oracle cuts the decoded frames with OpenCV. --packed-cameras names the rig's
    cameras."""
    import cv2

    frames = list(_pairs())
    h, w = frames[0][1][0].shape[:2]
    (tmp_path / "video").mkdir()
    writer = cv2.VideoWriter(str(tmp_path / "video" / "stereo.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 5.0, (w, 2 * h))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG to .avi")
    for _, views in frames:
        writer.write(cv2.cvtColor(np.concatenate(views, axis=0), cv2.COLOR_GRAY2BGR))
    writer.release()
    cap, cut = cv2.VideoCapture(str(tmp_path / "video" / "stereo.avi")), []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        cut.append((f"frame{len(cut):06d}", [frame[:h], frame[h:]]))
    cap.release()
    assert len(cut) == 13
    _write_folders(tmp_path / "cut", cut)
    for c, name in enumerate(("left", "right")):
        (tmp_path / "cut" / f"cam{c}").rename(tmp_path / "cut" / name)
    res = _calibrate(tmp_path / "cut", target, tmp_path / "a.yaml")
    assert res.exit_code == 0, res.output
    res = _calibrate(tmp_path / "video", target, tmp_path / "b.yaml", "--packed", "top-bottom", "--packed-cameras",
                     "left,right")
    assert res.exit_code == 0, res.output
    a, b = _rig_without_hash(tmp_path / "a.yaml"), _rig_without_hash(tmp_path / "b.yaml")
    assert [c["name"] for c in b["cameras"]] == ["left", "right"]
    assert a == b


@pytest.mark.parametrize("names", ["cam0", "a,a", "a, ,b"])
def test_bad_packed_camera_names_exit_2(target, tmp_path, names):
    (tmp_path / "seq" / "stereo").mkdir(parents=True)
    out = tmp_path / "rig.yaml"
    res = _calibrate(tmp_path / "seq", target, out, "--packed", "rows", "--packed-cameras", names)
    assert_exit_2(res, out, "--packed-cameras")


def test_timestamps_with_packed_exit_2(target, tmp_path):
    (tmp_path / "seq" / "stereo").mkdir(parents=True)
    (tmp_path / "t.csv").write_text("camera,time_s\n")
    out = tmp_path / "rig.yaml"
    res = _calibrate(tmp_path / "seq", target, out, "--packed", "rows", "--timestamps", tmp_path / "t.csv")
    assert_exit_2(res, out, "--timestamps", "simultaneous")


def test_a_packed_image_that_does_not_split_exit_2(target, tmp_path):
    import cv2

    (tmp_path / "seq" / "stereo").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "seq" / "stereo" / "0001.png"), np.zeros((48, 65), np.uint8))
    out = tmp_path / "rig.yaml"
    res = _calibrate(tmp_path / "seq", target, out, "--packed", "side-by-side")
    assert_exit_2(res, out, "0001.png", "--packed", "65x48", "do not split into 2")


def test_two_camera_folders_with_packed_exit_2(target, tmp_path):
    import cv2

    for c in ("cam0", "cam1"):
        (tmp_path / "seq" / c).mkdir(parents=True)
        cv2.imwrite(str(tmp_path / "seq" / c / "0001.png"), np.zeros((48, 64), np.uint8))
    out = tmp_path / "rig.yaml"
    res = _calibrate(tmp_path / "seq", target, out, "--packed", "side-by-side")
    assert_exit_2(res, out, "2 image sources", "cam0/", "cam1/")
