"""The overlay folder of ``heartcv measure --overlay DIR`` (cli/measure_overlay.py) on a tiny synthetic sequence.

Two cameras, five instants of 64x48 px noise images (cam0/000000.png ...) read with heartcv.io, and the hand-made
result of tests/heartcv/test_overlay.py. Each frame PNG must equal :func:`heartcv.overlay.overlay_frame` of the
images exactly (PNG is lossless); the video must hold one frame per instant of the same picture (MPEG-4 is lossy:
compared on average); tracks.png must be a PNG of the figure's size. A folder heartcv did not write is refused
before any work and left as it was; an earlier overlay is replaced; a failure leaves no folder behind.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from heartcv.cli.measure_overlay import PRODUCER, check_overlay_dir, tracks_figure, write_overlay
from heartcv.io import FrameReader, open_frame_source
from heartcv.overlay import overlay_frame
from heartcv.tracker.files import MANIFEST_NAME, InputError
from tests.heartcv.test_overlay import IMAGE_H, IMAGE_W, synthetic_result

NAMES = ["cam0", "cam1"]
FRAME_NAMES = [f"{k:06d}" for k in range(15)]      # the result's frames are 10..14


def _mp4v_works(tmp: Path) -> bool:
    writer = cv2.VideoWriter(str(tmp / "probe.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (64, 48))
    ok = writer.isOpened()
    writer.release()
    return ok


@pytest.fixture
def sequence(tmp_path):
    """``tmp/seq/cam0/000000.png`` ... 15 instants of seeded noise per camera (the result uses 10..14)."""
    rng = np.random.default_rng(7)
    seq = tmp_path / "seq"
    for name in NAMES:
        (seq / name).mkdir(parents=True)
        for frame in FRAME_NAMES:
            assert cv2.imwrite(str(seq / name / f"{frame}.png"), rng.integers(0, 80, (IMAGE_H, IMAGE_W, 3),
                                                                                 dtype=np.uint8))
    return open_frame_source(seq, cameras=NAMES)


def _write(folder, source, result=None, **kw):
    result = synthetic_result() if result is None else result
    with FrameReader(source, mode="color", frames=result.frames) as reader:
        return write_overlay(folder, reader, result, NAMES, source.frame_names, **kw)


def _expected(source, k):
    res = synthetic_result()
    with FrameReader(source, mode="color", frames=[int(res.frames[k])]) as reader:
        images = reader.read(int(res.frames[k]))[0]
    return overlay_frame(images, res, k, 0, 15, names=NAMES, max_tracks=IMAGE_W * IMAGE_H // 400)


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_frames_and_figure(tmp_path, sequence):
    out = tmp_path / "overlay"
    ticks = []
    summary = _write(out, sequence, progress=lambda done, total: ticks.append((done, total)))
    names = [f"frames/{k:06d}.png" for k in range(10, 15)]
    assert summary["files"] == sorted([*names, "tracks.png"])
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()) == sorted(
        [*names, "tracks.png", MANIFEST_NAME])
    assert ticks == [(i, 5) for i in range(1, 6)]
    for k, name in enumerate(names):
        picture = cv2.imread(str(out / name), cv2.IMREAD_UNCHANGED)
        assert picture.shape[1:] == (2 * IMAGE_W, 3) and picture.shape[0] > IMAGE_H
        assert np.array_equal(picture, _expected(sequence, k))
    # the statistics of the hand-made result: spans 5, 4, 3; points per frame 2, 2, 2, 3, 2
    assert summary["frames"] == 5 and summary["tracks"] == 3 and summary["video"] is None
    assert summary["track_span_median_frames"] == 4.0
    assert summary["points_min"] == 2 and summary["points_mean"] == pytest.approx(2.2, abs=1e-12)
    png = (out / "tracks.png").read_bytes()
    assert png.startswith(b"\x89PNG\r\n\x1a\n")
    fig = cv2.imread(str(out / "tracks.png"), cv2.IMREAD_UNCHANGED)
    assert fig.shape[:2] == (418, 1100)                      # 10 x 3.8 in at 110 dpi
    assert summary["tracks_png"] == out / "tracks.png"
    manifest = json.loads((out / MANIFEST_NAME).read_text())
    assert manifest["producer"] == PRODUCER and manifest["frames"] == 5 and not manifest["video"]


def test_figure_panels():
    fig = tracks_figure(synthetic_result())
    per_frame, spans = fig.axes
    assert per_frame.get_lines()[0].get_ydata().tolist() == [2, 2, 2, 3, 2]
    labels = [t.get_text() for t in per_frame.get_legend().get_texts()]
    assert labels == ["points seen", "mean 2.2", "min 2 (frame 10)"]
    assert [t.get_text() for t in spans.get_legend().get_texts()] == ["tracks", "median 4 frames"]
    assert sorted(int(p.get_height()) for p in spans.patches if p.get_height() > 0) == [1, 1, 1]
    assert "[frames]" in spans.get_xlabel() and "[count]" in per_frame.get_ylabel()


def test_refuses_a_foreign_folder_before_any_work(tmp_path, sequence):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("do not lose me")
    before = _snapshot(out)
    with pytest.raises(InputError, match="--overlay"):
        check_overlay_dir(out)
    with pytest.raises(InputError, match="no heartcv manifest"):
        _write(out, sequence)
    assert _snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine", "seq"]    # no temporary folder left
    # another stage's folder is not ours either
    other = tmp_path / "report"
    other.mkdir()
    (other / MANIFEST_NAME).write_text(json.dumps({"producer": "heartcv calibrate --report"}))
    with pytest.raises(InputError, match="calibrate --report"):
        _write(other, sequence)
    # a file where the folder should be
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        check_overlay_dir(tmp_path / "file")


def test_missing_or_empty_folder_is_fine(tmp_path, sequence):
    check_overlay_dir(tmp_path / "new")
    empty = tmp_path / "empty"
    empty.mkdir()
    check_overlay_dir(empty)
    assert "tracks.png" in _write(empty, sequence)["files"]


def test_rerun_replaces_its_own_folder(tmp_path, sequence):
    out = tmp_path / "overlay"
    _write(out, sequence)
    first = _snapshot(out)
    check_overlay_dir(out)
    _write(out, sequence)
    again = _snapshot(out)
    assert again.keys() == first.keys()
    assert all(again[n] == first[n] for n in first if n.endswith(".png") and n.startswith("frames/"))
    if _mp4v_works(tmp_path):            # a run of another kind replaces the whole folder: no stale frames
        _write(out, sequence, video=True)
        assert sorted(p.name for p in out.iterdir()) == sorted([MANIFEST_NAME, "overlay.mp4", "tracks.png"])


def test_failure_leaves_nothing(tmp_path, sequence):
    res = synthetic_result()
    out = tmp_path / "overlay"
    with FrameReader(sequence, mode="color", frames=res.frames[:3]) as reader:      # two instants short
        with pytest.raises(ValueError, match="5 frames of the result"):
            write_overlay(out, reader, res, NAMES, sequence.frame_names)
    with FrameReader(sequence, mode="color", frames=[9, 10]) as reader:              # not a frame of the result
        with pytest.raises(ValueError, match="frame 9"):
            write_overlay(out, reader, res, NAMES, sequence.frame_names)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]
    with pytest.raises(ValueError, match="camera_names"):
        write_overlay(out, [], res, NAMES[:1], sequence.frame_names)
    with pytest.raises(ValueError, match="frame_names"):
        write_overlay(out, [], res, NAMES, sequence.frame_names[:12])


def test_missing_image_is_drawn_gray(tmp_path, sequence):
    (sequence.folder / "cam1" / "000012.png").unlink()
    source = open_frame_source(sequence.folder, cameras=NAMES)
    out = tmp_path / "overlay"
    _write(out, source)
    picture = cv2.imread(str(out / "frames" / "000012.png"))
    band = picture.shape[0] - IMAGE_H
    assert picture.shape == (band + IMAGE_H, 2 * IMAGE_W, 3)
    assert picture[band + 45, IMAGE_W + 2].tolist() == [96, 96, 96]


def test_video(tmp_path, sequence):
    if not _mp4v_works(tmp_path):
        pytest.skip("this OpenCV build cannot write mp4v video")
    out = tmp_path / "overlay"
    summary = _write(out, sequence, video=True, fps=10.0)
    assert summary["files"] == ["overlay.mp4", "tracks.png"] and summary["video"] == out / "overlay.mp4"
    assert sorted(p.name for p in out.iterdir()) == sorted([MANIFEST_NAME, "overlay.mp4", "tracks.png"])
    cap = cv2.VideoCapture(str(out / "overlay.mp4"))
    assert cap.isOpened()
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(10.0)
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f)
    cap.release()
    assert len(frames) == 5
    for k, f in enumerate(frames):
        want = _expected(sequence, k)
        h, w = want.shape[:2]
        assert f.shape == (h + h % 2, w + w % 2, 3)          # even sides
        err = np.abs(f[:h, :w].astype(float) - want).mean()
        assert err < 12, f"instant {k}: mean abs difference {err:.1f} grey levels"
        # and the pictures differ between instants more than the compression does
        other = _expected(sequence, (k + 1) % 5)
        assert np.abs(f[:h, :w].astype(float) - other).mean() > err
