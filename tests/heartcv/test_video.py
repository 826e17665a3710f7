"""Video input (heartcv.video; docs/cli.md §8.2): every video is decoded once before any processing and refused,
naming the file, when it cannot be opened, is truncated or corrupt; FFmpeg's decoder messages are silenced; frame
``k`` is the ``k``-th decoded frame everywhere; per-camera frame times come from a multi-camera timestamps.csv.

Videos are written here with cv2.VideoWriter (MJPG in .avi, mp4v in .mp4: the two fourccs this OpenCV build
writes without an external encoder). Frame ``k`` is a uniform gray level ``10 k`` with a seeded noise band (the
noise makes the frames large enough that a corrupted block of bytes hits several of them); reading back a frame's
gray level identifies its index exactly.
"""

from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest

from heartcv.tracker.files import InputError
from heartcv.video import (
    VideoReader,
    camera_number,
    check_videos,
    iter_frames,
    probe_video,
    read_camera_times,
    silence_ffmpeg,
)
from tests.conftest import ROOT, SHARED_DATA

CALISCOPE = SHARED_DATA / "caliscope_4cam_charuco" / "calibration" / "extrinsic"
needs_caliscope = pytest.mark.skipif(not (CALISCOPE / "timestamps.csv").is_file(),
                                     reason="shared data not available (caliscope_4cam_charuco)")

N_FRAMES = 23
SIZE = (160, 120)
FPS = 10.0
FORMATS = [("MJPG", ".avi"), ("mp4v", ".mp4")]


def write_video(path: Path, fourcc: str, n: int = N_FRAMES, size=SIZE, seed: int = 0, level0: int = 0) -> Path:
    """Frame k: gray level ``level0 + 10 k`` (mod 250) over the top half, seeded noise in the bottom half."""
    import cv2

    rng = np.random.default_rng(seed)
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), FPS, size)
    if not w.isOpened():
        pytest.skip(f"this OpenCV build cannot write {fourcc} to {path.suffix}")
    for k in range(n):
        img = np.full((size[1], size[0], 3), (level0 + 10 * k) % 250, np.uint8)
        img[size[1] // 2:] = rng.integers(0, 256, (size[1] - size[1] // 2, size[0], 3), dtype=np.uint8)
        w.write(img)
    w.release()
    return path


def frame_level(img) -> int:
    """The index-coding gray level of a frame read back (top half, lossy codecs: rounded to the nearest 10)."""
    top = img[: img.shape[0] // 2 - 4]
    return int(round(float(top.mean()) / 10.0)) * 10


def truncated_copy(src: Path, dst: Path, fraction: float = 0.6) -> Path:
    data = src.read_bytes()
    dst.write_bytes(data[: int(fraction * len(data))])
    return dst


def corrupted_copy(src: Path, dst: Path, seed: int = 7) -> Path:
    """Bytes 40-55 % of the file overwritten with seeded random bytes (the container's header and index intact)."""
    data = bytearray(src.read_bytes())
    a, b = int(0.40 * len(data)), int(0.55 * len(data))
    data[a:b] = np.random.default_rng(seed).integers(0, 256, b - a, dtype=np.uint8).tobytes()
    dst.write_bytes(bytes(data))
    return dst


@pytest.fixture(params=FORMATS, ids=[f"{c}{s}" for c, s in FORMATS])
def video(request, tmp_path):
    fourcc, suffix = request.param
    return write_video(tmp_path / f"cam0{suffix}", fourcc)


# -- probing ----------------------------------------------------------------------------------------------------
def test_probe_exact_count_size_rate_and_times(video):
    info = probe_video(video)
    assert info.path == video
    assert (info.n_frames, info.container_frames) == (N_FRAMES, N_FRAMES)
    assert (info.width, info.height) == SIZE and info.size == SIZE
    assert info.fps == FPS
    np.testing.assert_allclose(info.times_s, np.arange(N_FRAMES) / FPS, rtol=0, atol=1e-9)


def test_truncated_video_is_refused_naming_the_file(video, tmp_path):
    bad = truncated_copy(video, tmp_path / f"short{video.suffix}")
    with pytest.raises(InputError) as err:
        probe_video(bad)
    assert err.value.path == str(bad)
    if video.suffix == ".avi":  # the AVI header is at the front: it opens, and frames are missing
        assert "truncated or corrupt: " in err.value.reason and f" of {N_FRAMES} frames decode" in err.value.reason
        decoded = int(err.value.reason.split("truncated or corrupt: ")[1].split(" of ")[0])
        assert 0 < decoded < N_FRAMES - 1
    else:  # mp4v: OpenCV's writer puts the index (moov) at the end, which truncation cuts off
        assert "cannot open the video" in err.value.reason


def test_corrupted_video_is_refused_naming_the_file(video, tmp_path):
    bad = corrupted_copy(video, tmp_path / f"damaged{video.suffix}")
    with pytest.raises(InputError) as err:
        probe_video(bad)
    assert err.value.path == str(bad)
    assert err.value.reason.startswith("truncated or corrupt: ") and f"of {N_FRAMES} frames decode" in str(err.value)


@pytest.mark.parametrize("content", [b"this is not a video\n", b""], ids=["text", "empty"])
def test_not_a_video_is_refused(tmp_path, content):
    bad = tmp_path / "notes.mp4"
    bad.write_bytes(content)
    with pytest.raises(InputError, match="notes.mp4: cannot open the video") as err:
        probe_video(bad)
    assert err.value.path == str(bad)


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(InputError, match="nope.mp4: no such file"):
        probe_video(tmp_path / "nope.mp4")
    (tmp_path / "dir.mp4").mkdir()
    with pytest.raises(InputError, match="dir.mp4: not a file"):
        probe_video(tmp_path / "dir.mp4")


def test_check_videos_probes_all_and_names_the_bad_one(tmp_path):
    good = [write_video(tmp_path / f"cam{i}.avi", "MJPG", seed=i) for i in range(3)]
    seen = []
    infos = check_videos(good, progress=seen.append)
    assert [i.path for i in infos] == good and [i.n_frames for i in infos] == [N_FRAMES] * 3
    assert sorted(i.path.name for i in seen) == ["cam0.avi", "cam1.avi", "cam2.avi"]
    bad = truncated_copy(good[1], tmp_path / "cam9.avi")
    with pytest.raises(InputError) as err:
        check_videos([good[0], bad, good[2]])
    assert err.value.path == str(bad) and "truncated or corrupt" in err.value.reason
    assert check_videos([]) == []


# -- reading -----------------------------------------------------------------------------------------------------
def test_iter_frames_every_and_gray(video):
    got = [(k, frame_level(img), img.shape) for k, img in iter_frames(video, every=4)]
    assert [g[0] for g in got] == list(range(0, N_FRAMES, 4))
    assert [g[1] for g in got] == [10 * k for k in range(0, N_FRAMES, 4)]
    assert {g[2] for g in got} == {(SIZE[1], SIZE[0], 3)}
    gray = [img for _, img in iter_frames(video, gray=True)]
    assert len(gray) == N_FRAMES and gray[5].shape == (SIZE[1], SIZE[0]) and gray[5].dtype == np.uint8
    with pytest.raises(ValueError):
        next(iter_frames(video, every=0))


def test_video_reader_forward_backward_and_past_the_end(video):
    with VideoReader(video, size=SIZE) as reader:
        assert frame_level(reader.read(7)) == 70
        assert frame_level(reader.read(8)) == 80
        assert frame_level(reader.read(2)) == 20  # back: reopened
        assert frame_level(reader.read(N_FRAMES - 1)) == 10 * (N_FRAMES - 1)
        assert reader.read(N_FRAMES) is None
    with VideoReader(video, size=(SIZE[0] + 2, SIZE[1])) as reader, pytest.raises(InputError, match="frame 0 is"):
        reader.read(0)


# -- heartcv.io: open_frame_source / FrameReader (heartcv measure) ----------------------------------------------------
def test_frame_source_checks_and_reads_videos(tmp_path):
    from heartcv.io import FrameReader, open_frame_source

    seq = tmp_path / "seq"
    seq.mkdir()
    for i in range(3):
        write_video(seq / f"cam{i}.avi", "MJPG", seed=i, level0=30 * i)
    src = open_frame_source(seq)
    assert (src.kind, src.camera_names, src.n_frames, src.fps) == ("video", ("cam0", "cam1", "cam2"), N_FRAMES, FPS)
    assert [v.n_frames for v in src.videos] == [N_FRAMES] * 3 and src.videos[2].size == SIZE
    with FrameReader(src, sizes=[SIZE] * 3, frames=[0, 5, 6, 22]) as reader:
        got = [(k, [frame_level(im) for im in images], problems) for k, images, problems in reader]
    assert got == [(k, [(30 * i + 10 * k) % 250 for i in range(3)], []) for k in (0, 5, 6, 22)]
    with FrameReader(src, sizes=[SIZE, (SIZE[0], 99), SIZE]) as reader:
        images, problems = reader.read(3)
    assert images[1] is None and problems == [f"{seq / 'cam1.avi'}: frame 3 is 160x120 px, 160x99 expected"]


def test_a_segment_of_videos_reads_the_recordings_frames(tmp_path):
    """FrameSource.segment(7): instant k of the segment is decoded frame 7 + k of every video (the frame index
    coded in the gray level), named as in the recording; a segment of a segment adds the starts; a start outside
    the recording or an empty segment is a ValueError."""
    from heartcv.io import FrameReader, open_frame_source

    seq = tmp_path / "seq"
    seq.mkdir()
    for i in range(2):
        write_video(seq / f"cam{i}.avi", "MJPG", seed=i, level0=30 * i)
    src = open_frame_source(seq)
    seg = src.segment(7)
    assert (seg.n_frames, seg.start, seg.frame_names) == (N_FRAMES - 7, 7, src.frame_names[7:])
    with FrameReader(seg, sizes=[SIZE] * 2, frames=[0, 1, 9]) as reader:
        got = [(k, [frame_level(im) for im in images]) for k, images, _ in reader]
    assert got == [(k, [(30 * i + 10 * (7 + k)) % 250 for i in range(2)]) for k in (0, 1, 9)]
    sub = seg.segment(3, 4)
    assert (sub.start, sub.n_frames, sub.frame_names) == (10, 4, src.frame_names[10:14])
    with FrameReader(sub, sizes=[SIZE] * 2) as reader:
        assert [frame_level(im[0]) for _, im, _ in reader] == [10 * k for k in range(10, 14)]
    for bad in (-1, N_FRAMES):
        with pytest.raises(ValueError, match="start"):
            src.segment(bad)
    with pytest.raises(ValueError, match="count"):
        src.segment(2, 0)


def test_frame_source_refuses_a_bad_video_before_reading(tmp_path):
    from heartcv.io import open_frame_source

    seq = tmp_path / "seq"
    seq.mkdir()
    full = write_video(tmp_path / "full.avi", "MJPG", seed=1)
    write_video(seq / "cam0.avi", "MJPG")
    truncated_copy(full, seq / "cam1.avi")
    with pytest.raises(InputError) as err:
        open_frame_source(seq)
    assert err.value.path == str(seq / "cam1.avi") and "truncated or corrupt" in err.value.reason
    write_video(seq / "cam1.avi", "MJPG", n=N_FRAMES - 3)
    with pytest.raises(InputError, match=f"cameras with different frame counts: cam0 {N_FRAMES}, cam1 {N_FRAMES - 3}"):
        open_frame_source(seq)
    # as many frames at twice the rate: frame k is not one instant in both
    import cv2

    w = cv2.VideoWriter(str(seq / "cam1.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 2 * FPS, SIZE)
    for k in range(N_FRAMES):
        w.write(np.full((SIZE[1], SIZE[0], 3), 10 * k, np.uint8))
    w.release()
    with pytest.raises(InputError, match=f"cameras' videos at different frame rates \\(cam0 {FPS:g} fps, cam1 "
                                         f"{2 * FPS:g} fps\\) with {N_FRAMES} frames each"):
        open_frame_source(seq)


def test_frame_reader_checks_an_unchecked_source(tmp_path):
    from heartcv.io import FrameReader, FrameSource

    good = write_video(tmp_path / "a.avi", "MJPG")
    bad = corrupted_copy(write_video(tmp_path / "b0.avi", "MJPG", seed=3), tmp_path / "b.avi")
    src = FrameSource(tmp_path, "video", ("a", "b"), tuple(f"frame{k:06d}" for k in range(N_FRAMES)),
                      ((good,), (bad,)))
    with pytest.raises(InputError) as err, FrameReader(src):
        pass
    assert err.value.path == str(bad)


# -- FFmpeg's messages ---------------------------------------------------------------------------------------------
SNIPPET = """
import sys
from heartcv.tracker.files import InputError
from heartcv.video import probe_video, silence_ffmpeg
if sys.argv[1] == "silent":
    silence_ffmpeg(False)
for path in sys.argv[2:]:
    try:
        probe_video(path)
    except InputError as exc:
        print(exc)
"""


def _stderr_lines(mode, paths):
    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENCV_FFMPEG_LOGLEVEL", "OPENCV_LOG_LEVEL", "OPENCV_FFMPEG_DEBUG", "OPENCV_VIDEOIO_DEBUG")}
    res = subprocess.run([sys.executable, "-c", SNIPPET, mode, *map(str, paths)], capture_output=True, text=True,
                         env=env, cwd=ROOT, timeout=120)
    assert res.returncode == 0, res.stderr
    assert [line.split(": ")[0] for line in res.stdout.splitlines()] == [str(p) for p in paths]  # all refused
    return res.stderr.splitlines()


def test_silence_ffmpeg_removes_decoder_messages(tmp_path):
    """A corrupt and a truncated video of each format, probed in a fresh process (FFmpeg writes to fd 2)."""
    paths = []
    for fourcc, suffix in FORMATS:
        src = write_video(tmp_path / f"src{suffix}", fourcc, n=40)
        paths += [corrupted_copy(src, tmp_path / f"corrupt{suffix}"), truncated_copy(src, tmp_path / f"short{suffix}")]
    assert _stderr_lines("silent", paths) == []
    loud = _stderr_lines("loud", paths)
    if not loud:
        pytest.skip("this OpenCV/FFmpeg build prints nothing for these files even when not silenced")
    assert any(" @ 0x" in line for line in loud), loud  # FFmpeg's "[codec @ 0x...] message" lines


def test_silence_ffmpeg_leaves_user_settings_and_verbose(monkeypatch):
    for name in ("OPENCV_FFMPEG_LOGLEVEL", "OPENCV_LOG_LEVEL"):
        monkeypatch.delenv(name, raising=False)
    silence_ffmpeg(True)
    assert "OPENCV_FFMPEG_LOGLEVEL" not in os.environ and "OPENCV_LOG_LEVEL" not in os.environ
    monkeypatch.setenv("OPENCV_FFMPEG_LOGLEVEL", "24")
    silence_ffmpeg(False)
    assert os.environ["OPENCV_FFMPEG_LOGLEVEL"] == "24" and os.environ["OPENCV_LOG_LEVEL"] == "ERROR"
    monkeypatch.delenv("OPENCV_FFMPEG_LOGLEVEL")
    silence_ffmpeg(False)
    assert os.environ["OPENCV_FFMPEG_LOGLEVEL"] == "-8"


def test_cli_refuses_a_corrupt_video_in_one_line(tmp_path):
    """``heartcv measure`` on one video per camera with one corrupted: exit 2 before any processing, and stderr
    holds the one error line naming the file (no FFmpeg output, fresh process)."""
    from heartcv.camera import Camera, Rig
    from heartcv.io import write_rig

    seq = tmp_path / "seq"
    seq.mkdir()
    write_video(seq / "cam0.avi", "MJPG", n=30)
    corrupted_copy(write_video(tmp_path / "cam1.avi", "MJPG", n=30, seed=5), seq / "cam1.avi")
    K = np.array([[200.0, 0, 80], [0, 200, 60], [0, 0, 1]])
    T = np.eye(4)
    T[0, 3] = -0.05
    write_rig(tmp_path / "rig.yaml", Rig((Camera("cam0", *SIZE, K), Camera("cam1", *SIZE, K, np.zeros(5), T))))
    env = {k: v for k, v in os.environ.items() if not k.startswith("OPENCV_")}
    res = subprocess.run([sys.executable, "-m", "heartcv.cli.main", "measure", str(seq), "--rig",
                          str(tmp_path / "rig.yaml"), "-o", str(tmp_path / "meas.npz")],
                         capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"Error: {seq / 'cam1.avi'}: truncated or corrupt: ") and " of 30 frames" in lines[0]
    assert not (tmp_path / "meas.npz").exists()


# -- per-camera frame times --------------------------------------------------------------------------------------------
@needs_caliscope
def test_caliscope_timestamps():
    names = ["cam_0", "cam_1", "cam_2", "cam_3"]
    times = read_camera_times(CALISCOPE / "timestamps.csv", names, [57] * 4)
    assert list(times) == names and all(t.shape == (57,) for t in times.values())
    assert times["cam_2"][0] == 25.0009787 and times["cam_0"][0] == 25.00119655
    assert all((np.diff(t) > 0).all() for t in times.values())
    with pytest.raises(InputError, match="57 rows for camera 'cam_1', whose video has 56 frames"):
        read_camera_times(CALISCOPE / "timestamps.csv", names, {"cam_0": 57, "cam_1": 56, "cam_2": 57, "cam_3": 57})


@needs_caliscope
def test_caliscope_videos_probe():
    infos = check_videos([CALISCOPE / f"cam_{i}.mp4" for i in range(4)])
    assert [(i.n_frames, i.size, i.fps, i.container_frames) for i in infos] == [(57, (1280, 720), 6.0, 57)] * 4
    np.testing.assert_allclose(infos[3].times_s, np.arange(57) / 6.0, rtol=0, atol=1e-9)


def _csv(tmp_path, text, name="timestamps.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_camera_matching_and_order(tmp_path):
    assert [camera_number(n) for n in ("cam_0", "cam3", "7", "left", "cam12")] == [0, 3, 7, None, 12]
    # rows out of order, an extra camera (5) ignored, frame_index instead of sync_index, names with trailing numbers
    p = _csv(tmp_path, "# recorder output\nframe_index,cam_id,frame_time\n"
                       "11,1,2.5\n10,0,1.0\n10,1,2.0\n11,0,1.5\n10,5,9.0\n12,0,1.75\n12,1,3.0\n")
    times = read_camera_times(p, ["cam0", "right_1"], [3, 3])
    assert {k: v.tolist() for k, v in times.items()} == {"cam0": [1.0, 1.5, 1.75], "right_1": [2.0, 2.5, 3.0]}
    # a camera column with names; a name equal to the camera's name matches, so does its number
    p = _csv(tmp_path, "sync_index,camera,time_s\n0,left,0.0\n0,2,0.01\n1,left,0.1\n1,2,0.11\n", "named.csv")
    times = read_camera_times(p, ["left", "cam2"], {"left": 2, "cam2": 2})
    assert times["left"].tolist() == [0.0, 0.1] and times["cam2"].tolist() == [0.01, 0.11]


@pytest.mark.parametrize("text, field, reason", [
    ("cam_id,frame_time\n0,1.0\n", "column 'sync_index' or 'frame_index'", "missing"),
    ("sync_index,frame_time\n0,1.0\n", "column 'cam_id' or 'camera'", "missing"),
    ("sync_index,cam_id\n0,0\n", "column 'frame_time' or 'time_s'", "missing"),
    ("sync_index,frame_index,cam_id,frame_time\n0,0,0,1.0\n", "column 'sync_index' or 'frame_index'", "both"),
    ("sync_index,cam_id,frame_time\n0,0,1.0\n1,0,nan\n", "column 'frame_time'", "non-finite"),
    ("sync_index,cam_id,frame_time\n0,0,1.0\n1,0,x\n", "column 'frame_time'", "not numeric"),
    ("sync_index,cam_id,frame_time\n0,0,1.0\n1,0\n", "row 2", "2 values for 3 columns"),
    ("sync_index,cam_id,frame_time\n0,0,1.0\n1,0,1.0\n", "column 'frame_time'", "strictly increase"),
    ("sync_index,cam_id,frame_time\n1,0,1.0\n0,0,2.0\n", "column 'frame_time'", "row 1 has 1.0 after row 2"),
    ("sync_index,cam_id,frame_time\n0,0,1.0\n0,0,2.0\n", "column 'sync_index'", "repeated"),
    ("sync_index,cam_id,frame_time\n0,0,1.0\n1,0,2.0\n2,0,3.0\n", "column 'cam_id'", "3 rows for camera 'cam_0'"),
    ("sync_index,cam_id,frame_time\n0,1,1.0\n1,1,2.0\n", "column 'cam_id'", "no rows for camera 'cam_0'"),
    ("sync_index,cam_id,frame_time\n0,0.5,1.0\n1,0,2.0\n", "column 'cam_id'", "integer camera ids"),
    ("", None, "empty timestamps table"),
])
def test_malformed_timestamps_name_file_and_column(tmp_path, text, field, reason):
    p = _csv(tmp_path, text)
    with pytest.raises(InputError) as err:
        read_camera_times(p, ["cam_0"], [2])
    assert err.value.path == str(p)
    assert err.value.field == field and reason in err.value.reason, str(err.value)


def test_ambiguous_camera_names(tmp_path):
    p = _csv(tmp_path, "sync_index,cam_id,frame_time\n0,1,1.0\n")
    with pytest.raises(InputError, match="cameras 'cam1' and 'left1' both match cam_id 1"):
        read_camera_times(p, ["cam1", "left1"], [1, 1])
