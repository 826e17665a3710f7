"""``heartcv measure --packed``: stereo frames that hold both views in one image (a side-by-side or top-bottom
stereo video, an interlaced frame whose fields are the views).

The oracle is the same views stored the usual way, one folder per camera: ``measure`` must write the same
measurement arrays from either. For a video the views are cut from the decoded frames by plain OpenCV, outside
heartcv, and written losslessly, so the comparison is exact there too. Bad packings exit 2 naming the file,
with nothing written.
"""

from __future__ import annotations

from click.testing import CliRunner
import numpy as np
import pytest

from heartcv.cli.main import main
from heartcv.io import FrameReader, open_frame_source, unpack_views
from tests.conftest import assert_exit_2

W, H = 160, 120
LAYOUTS = ("side-by-side", "top-bottom", "rows")


def _run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _pack(views, layout):
    """The packing of ``views`` written independently of heartcv."""
    if layout == "side-by-side":
        return np.concatenate(views, axis=1)
    if layout == "top-bottom":
        return np.concatenate(views, axis=0)
    out = np.empty((len(views) * views[0].shape[0],) + views[0].shape[1:], views[0].dtype)
    for c, v in enumerate(views):
        out[c::len(views)] = v
    return out


# -- the pure split ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("n", [2, 3])
@pytest.mark.parametrize("channels", [None, 3])
def test_unpack_inverts_an_independent_packing(layout, n, channels):
    rng = np.random.default_rng(n)
    shape = (6, 10) if channels is None else (6, 10, channels)
    views = [rng.integers(0, 256, shape, dtype=np.uint8) for _ in range(n)]
    got = unpack_views(_pack(views, layout), layout, n)
    assert len(got) == n
    for g, v in zip(got, views):
        assert g.flags.c_contiguous
        np.testing.assert_array_equal(g, v)


@pytest.mark.parametrize("layout, shape", [("side-by-side", (4, 7)), ("top-bottom", (5, 8)), ("rows", (7, 8))])
def test_a_frame_that_does_not_split_evenly_is_refused(layout, shape):
    with pytest.raises(ValueError, match=f"{shape[1]}x{shape[0]} px"):
        unpack_views(np.zeros(shape, np.uint8), layout, 2)


def test_unknown_packing_and_one_view_are_refused():
    with pytest.raises(ValueError, match="packing"):
        unpack_views(np.zeros((4, 4), np.uint8), "diagonal", 2)
    with pytest.raises(ValueError, match="at least 2"):
        unpack_views(np.zeros((4, 4), np.uint8), "rows", 1)


# -- a scene to measure --------------------------------------------------------------------------------------------
def _views(k):
    """Left and right views of a textured plane 30 mm from a rectified 5.5 mm rig (focal 390 px), shifted 1.5 px
    per instant."""
    import cv2

    rng = np.random.default_rng(3)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (H, W + 200, 3)).astype(np.float32), (0, 0), 1.5)
    tex = cv2.normalize(tex, None, 30, 220, cv2.NORM_MINMAX).astype(np.uint8)
    tex[..., 2] = np.clip(tex[..., 2].astype(int) + 40, 0, 255)          # reddish: tissue, not an instrument
    d = 390 * 0.0055 / 0.03
    shift = 1.5 * k
    left = cv2.warpAffine(tex, np.float32([[1, 0, -100 + shift], [0, 1, 0]]), (W, H), flags=cv2.INTER_CUBIC)
    right = cv2.warpAffine(tex, np.float32([[1, 0, -100 - d + shift], [0, 1, 0]]), (W, H), flags=cv2.INTER_CUBIC)
    return [left, right]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Three instants stored one folder per camera and packed in every layout; the rig of the views."""
    import cv2

    root = tmp_path_factory.mktemp("packed")
    for k in range(3):
        views = _views(k)
        for c, v in enumerate(views):
            (root / "separate" / f"cam{c}").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / "separate" / f"cam{c}" / f"{k:06d}.png"), v)
        for layout in LAYOUTS:
            (root / layout / "stereo").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / layout / "stereo" / f"{k:06d}.png"), _pack(views, layout))
    res = _run("rig", "rectified", "--image-size", f"{W}x{H}", "--focal-px", "390", "--baseline-m", "0.0055",
               "-o", root / "rig.yaml")
    assert res.exit_code == 0, res.output
    return root


def _measure(seq, rig, out, *extra):
    res = _run("measure", seq, "--rig", rig, "-o", out, "--fps", "25", "--json", *extra)
    return res


def _arrays(path):
    """Every array of a measurement file, and its metadata (read by heartcv's validating reader)."""
    from heartcv.tracker.io import read_measurements

    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files if k != "meta_json"}
    return arrays, read_measurements(path).meta


@pytest.fixture(scope="module")
def separate(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("separate") / "m.npz"
    res = _measure(scene / "separate", scene / "rig.yaml", out)
    assert res.exit_code == 0, res.output
    arrays, meta = _arrays(out)
    assert arrays["positions"].shape[1] > 20                    # the scene is trackable: the comparison means something
    assert "packed" not in meta
    return arrays


@pytest.mark.parametrize("layout", LAYOUTS)
def test_reader_gives_the_views_of_the_separate_folders(scene, layout):
    sep = open_frame_source(scene / "separate", cameras=["cam0", "cam1"])
    pk = open_frame_source(scene / layout, cameras=["cam0", "cam1"], packing=layout)
    assert pk.n_frames == sep.n_frames == 3 and pk.frame_names == sep.frame_names
    assert pk.missing() == []
    with FrameReader(sep, mode="color") as a, FrameReader(pk, mode="color", sizes=[(W, H)] * 2) as b:
        for (_, ia, pa), (_, ib, pb) in zip(a, b):
            assert pa == pb == []
            for x, y in zip(ia, ib):
                np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_measure_packed_frames_equals_measure_of_separate_folders(scene, separate, layout, tmp_path):
    out = tmp_path / "m.npz"
    res = _measure(scene / layout, scene / "rig.yaml", out, "--packed", layout)
    assert res.exit_code == 0, res.output
    arrays, meta = _arrays(out)
    assert meta["packed"] == layout and meta["camera_names"] == ["cam0", "cam1"]
    import cv2

    assert meta["software"]["opencv"] == cv2.__version__ and meta["software"]["numpy"] == np.__version__
    assert set(arrays) == set(separate)
    for k, v in separate.items():
        np.testing.assert_array_equal(arrays[k], v, err_msg=k)


def test_a_packed_video_equals_its_views_cut_by_opencv(scene, tmp_path):
    """MJPG side-by-side video: heartcv's split of the decoded frames against OpenCV's own decode and slicing."""
    import cv2

    seq = tmp_path / "video"
    seq.mkdir()
    writer = cv2.VideoWriter(str(seq / "stereo.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (2 * W, H))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG to .avi")
    for k in range(3):
        writer.write(_pack(_views(k), "side-by-side"))
    writer.release()
    cap, k = cv2.VideoCapture(str(seq / "stereo.avi")), 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        for c in range(2):
            (tmp_path / "cut" / f"cam{c}").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(tmp_path / "cut" / f"cam{c}" / f"{k:06d}.png"), frame[:, c * W:(c + 1) * W])
        k += 1
    cap.release()
    assert k == 3
    res = _measure(seq, scene / "rig.yaml", tmp_path / "v.npz", "--packed", "side-by-side")
    assert res.exit_code == 0, res.output
    res = _measure(tmp_path / "cut", scene / "rig.yaml", tmp_path / "c.npz")
    assert res.exit_code == 0, res.output
    (a, meta), (b, _) = _arrays(tmp_path / "v.npz"), _arrays(tmp_path / "c.npz")
    assert meta["packed"] == "side-by-side" and a["positions"].shape[1] > 20
    for key, v in b.items():
        np.testing.assert_array_equal(a[key], v, err_msg=key)


# -- bad packings ---------------------------------------------------------------------------------------------------
def test_packed_on_a_folder_of_two_cameras_exit_2(scene, tmp_path):
    out = tmp_path / "m.npz"
    res = _measure(scene / "separate", scene / "rig.yaml", out, "--packed", "side-by-side")
    assert_exit_2(res, out, "2 image sources", "cam0/", "cam1/", "one sub-folder of images or one video")


def test_a_frame_that_does_not_split_exit_2_naming_it(scene, tmp_path):
    import cv2

    (tmp_path / "odd").mkdir()
    frame = np.concatenate([_views(0)[0], _views(0)[1][:, :-1]], axis=1)        # 319 columns
    cv2.imwrite(str(tmp_path / "odd" / "000000.png"), frame)
    out = tmp_path / "m.npz"
    res = _measure(tmp_path / "odd", scene / "rig.yaml", out, "--packed", "side-by-side")
    assert_exit_2(res, out, "000000.png", "--packed", f"{2 * W - 1}x{H}", "do not split into 2")


def test_views_of_another_size_than_the_rig_exit_2(scene, tmp_path):
    out = tmp_path / "m.npz"
    res = _measure(scene / "top-bottom", scene / "rig.yaml", out, "--packed", "side-by-side")  # 80x240 views
    assert_exit_2(res, out, "000000.png", f"{W // 2}x{2 * H}", f"{W}x{H}", "does not belong")
