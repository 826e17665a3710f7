"""``heartcv rig import`` and ``heartcv rig rectified``: exit codes, messages naming the file and field, the JSON
summary, the written rig file read back, and output safety."""

from __future__ import annotations

import json
from pathlib import Path

from click.testing import CliRunner
import numpy as np
import pytest

from heartcv.camera import Camera, Rig, pose_matrix
from heartcv.cli.main import main
from heartcv.io import read_rig, write_kalibr
from tests.conftest import SHARED_DATA

CALISCOPE = SHARED_DATA / "caliscope_4cam_charuco"
HAMLYN = SHARED_DATA / "hamlyn_heart_phantom_f7"
OPENCV = SHARED_DATA / "opencv_stereo"


def _run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _stereo(tmp_path) -> Path:
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec([0.02, 0.1, -0.01]).as_matrix()
    rig = Rig((Camera("a", 640, 480, [[500, 0, 320], [0, 500, 240], [0, 0, 1]], [0.1, -0.02, 0, 0]),
               Camera("b", 640, 480, [[510, 0, 322], [0, 511, 238], [0, 0, 1]], [0.05, 0, 1e-3, 0],
                      pose_matrix(R, [-0.08, 0.001, 0.002]))))
    path = tmp_path / "camchain.yaml"
    write_kalibr(path, rig)
    return path, rig


def test_rig_is_registered_and_choices_match():
    from heartcv.cli import rig as cli_rig
    from heartcv.rig_formats import FORMATS, UNITS

    assert cli_rig.FORMATS == FORMATS and set(cli_rig.UNITS) == set(UNITS)
    res = _run("rig", "--help")
    assert res.exit_code == 0 and "import" in res.output and "rectified" in res.output


def test_import_kalibr_names_and_json(tmp_path):
    src, rig = _stereo(tmp_path)
    out = tmp_path / "rig.yaml"
    res = _run("rig", "import", src, "--names", "left,right", "-o", out, "--json")
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["source_format"] == "kalibr" and summary["rig_frame"] == "left"
    assert [c["name"] for c in summary["cameras"]] == ["left", "right"]
    assert summary["baselines_m"] == {"left-right": pytest.approx(np.linalg.norm(rig[1].centre), abs=1e-12)}
    back = read_rig(out)
    assert back.names == ["left", "right"]
    np.testing.assert_allclose(back[1].cam_from_rig, rig[1].cam_from_rig, atol=1e-12)
    assert back.meta["producer"] == "heartcv rig import" and back.meta["source_format"] == "kalibr"
    assert back.meta["source_files"][0]["file"] == str(src)
    assert back.meta["source_files"][0]["sha256"].startswith("sha256:")
    assert back.meta["inputs_hash"] == {"source_0": back.meta["source_files"][0]["sha256"]}
    # running again replaces heartcv's own output
    assert _run("rig", "import", src, "-o", out).exit_code == 0
    assert read_rig(out).names == ["cam0", "cam1"]


def test_import_output_safety(tmp_path):
    src, _ = _stereo(tmp_path)
    res = _run("rig", "import", src, "-o", src)
    assert res.exit_code == 2
    assert f"{src}: -o/--output: is the input FILE ({src}); choose another output path" in res.output
    other = tmp_path / "notes.yaml"
    other.write_text("mine: 1\n")
    res = _run("rig", "import", src, "-o", other)
    assert res.exit_code == 2 and "not written by heartcv" in res.output
    assert other.read_text() == "mine: 1\n"
    res = _run("rig", "import", src, "-o", tmp_path / "rig.txt")
    assert res.exit_code == 2 and "a .yaml file expected" in res.output


def test_import_bad_input_exit_2(tmp_path):
    """Every user mistake exits 2 with one line naming the file and the field, never a traceback."""
    notes = tmp_path / "notes.yaml"
    notes.write_text("hello: world\n")
    res = _run("rig", "import", notes, "-o", tmp_path / "rig.yaml")
    assert res.exit_code == 2 and f"{notes}: format: not recognised" in res.output
    assert "opencv, kalibr, colmap, caliscope, text" in res.output
    png = tmp_path / "frame.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR")
    res = _run("rig", "import", png, "-o", tmp_path / "rig.yaml")
    assert res.exit_code == 2 and f"{png}: format: not recognised as any of the formats heartcv imports (a binary" \
        in res.output
    res = _run("rig", "import", tmp_path / "missing.yml", "-o", tmp_path / "rig.yaml")
    assert res.exit_code == 2 and "missing.yml: no such" in res.output
    toml = tmp_path / "camera_array.toml"
    toml.write_text("[cameras.0]\nsize = [640, 480\n")
    res = _run("rig", "import", toml, "-o", tmp_path / "rig.yaml")
    assert res.exit_code == 2 and f"{toml}: not valid TOML" in res.output
    cams = tmp_path / "cameras.txt"
    cams.write_text("1 PINHOLE 640 480 500 500 320\n")
    res = _run("rig", "import", cams, "-o", tmp_path / "rig.yaml")
    assert res.exit_code == 2 and f"{cams}: line 1 PARAMS: camera 1: PINHOLE has 4 parameters, got 3" in res.output
    k = tmp_path / "k.txt"
    k.write_text("500 0 320\n0 500 240\n0 0 1\n")
    res = _run("rig", "import", k, "-o", tmp_path / "rig.yaml")
    assert res.exit_code == 2 and f"{k}: image size: the image size is not in the file: pass --image-size" in res.output
    res = _run("rig", "import", k, "--image-size", "640x0", "-o", tmp_path / "rig.yaml")
    assert res.exit_code == 2 and "Invalid value for '--image-size'" in res.output
    res = _run("rig", "import", k, "--image-size", "640x480", "--names", "a,a", "-o", tmp_path / "rig.yaml")
    assert res.exit_code == 2 and "Invalid value for '--names'" in res.output
    assert "Traceback" not in res.output
    assert not (tmp_path / "rig.yaml").exists()


def test_import_text_orthonormalised_json(tmp_path):
    """A pose printed to 6 decimals: re-orthonormalised, reported in the JSON and in the rig file."""
    K = tmp_path / "k.txt"
    K.write_text("500 0 320\n0 500 240\n0 0 1\n")
    pose = tmp_path / "p.4x4"
    pose.write_text("0.999999 -0.001045 0.000000 -5.520739\n0.001045 0.999999 0.000000 -0.031516\n"
                    "0.000000 0.000000 1.000000 -0.051285\n0 0 0 1\n")
    out = tmp_path / "rig.yaml"
    res = _run("rig", "import", K, K, pose, "--format", "text", "--image-size", "360x288", "--units", "mm",
               "-o", out, "--json")
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    (corr,) = summary["orthonormalised"]
    assert corr["file"] == str(pose) and corr["field"] == "pose (rotation)"
    assert corr["deviation"] == pytest.approx(9.08e-7, rel=1e-3)
    assert summary["units_conversion"]["scale_to_m"] == 1e-3
    back = read_rig(out)
    assert back.meta["orthonormalised"] == [corr]
    assert np.abs(back[1].R.T @ back[1].R - np.eye(3)).max() < 1e-15


@pytest.mark.skipif(not HAMLYN.is_dir(), reason="shared data not available (hamlyn_heart_phantom_f7)")
def test_import_hamlyn(tmp_path):
    out = tmp_path / "hamlyn.yaml"
    res = _run("rig", "import", HAMLYN, "--image-size", "360x288", "-o", out)
    assert res.exit_code == 2
    assert (f"Error: {HAMLYN / 'calib.l2r.4x4'}: pose (translation): baseline 5.52 m (left-right): translations look "
            "like millimetres; pass --units mm (or --units m if the rig really spans 5.52 m)") in res.output
    assert not out.exists()
    res = _run("rig", "import", HAMLYN, "--image-size", "360x288", "--units", "mm", "-o", out, "--json")
    assert res.exit_code == 0, res.output
    back = read_rig(out)
    assert back.names == ["left", "right"]
    assert back[0].K[0, 0] == 391.656525 and back[0].K[1, 1] == 426.835144
    assert back[1].K[0, 0] == 390.376862 and back[1].K[1, 2] == 145.071411
    assert back.baselines()["left-right"] == pytest.approx(5.52e-3, abs=5e-6)
    np.testing.assert_array_equal(back[1].t, np.array([-5.520739, -0.031516, -0.051285]) * 1e-3)
    # the same files given one by one, in camera order
    files = [HAMLYN / n for n in ("calib.left.intrinsic.txt", "calib.left.distortion.txt", "calib.right.intrinsic.txt",
                                  "calib.right.distortion.txt", "calib.l2r.4x4")]
    res = _run("rig", "import", *files, "--image-size", "360x288", "--units", "mm", "-o", tmp_path / "r2.yaml")
    assert res.exit_code == 0, res.output
    again = read_rig(tmp_path / "r2.yaml")
    assert again.names == back.names
    for a, b in zip(again.cameras, back.cameras):
        assert np.array_equal(a.K, b.K) and np.array_equal(a.cam_from_rig, b.cam_from_rig)


@pytest.mark.skipif(not HAMLYN.is_dir(), reason="shared data not available (hamlyn_heart_phantom_f7)")
def test_measure_pairs_files_named_per_camera_by_their_number(tmp_path):
    """The Hamlyn phantom's views as its owners name them (left/f7_dynamic_deint_L_0100.png, right/..._R_0100.png:
    no stem in common; measure found no corner, 'camera images missing'): paired by the frame number, the
    measurement file equals that of a copy renamed to one stem per instant, array for array; its frame name is the
    left file's stem."""
    import shutil

    from heartcv.tracker.io import read_measurements

    rig = tmp_path / "rig.yaml"
    assert _run("rig", "import", HAMLYN, "--image-size", "360x288", "--units", "mm", "-o", rig).exit_code == 0
    native, renamed = tmp_path / "native", tmp_path / "renamed"
    for cam, side in (("left", "L"), ("right", "R")):
        (native / cam).mkdir(parents=True)
        (renamed / cam).mkdir(parents=True)
        shutil.copy(HAMLYN / f"f7_dynamic_deint_{side}_0100.png", native / cam)
        shutil.copy(HAMLYN / f"f7_dynamic_deint_{side}_0100.png", renamed / cam / "0100.png")
    out = {}
    for name, seq in (("native", native), ("renamed", renamed)):
        out[name] = tmp_path / f"{name}.npz"
        res = _run("measure", seq, "--rig", rig, "--fps", "25", "-o", out[name])
        assert res.exit_code == 0, res.output
    assert "paired by the last number in the names" in _run("-v", "measure", native, "--rig", rig, "--fps", "25",
                                                            "-o", tmp_path / "again.npz").stderr
    a, b = read_measurements(out["native"]), read_measurements(out["renamed"])
    assert a.n_points >= 40
    for field in ("positions", "covariances", "reference", "point_ids"):
        assert np.array_equal(getattr(a, field), getattr(b, field), equal_nan=True), field
    assert a.meta["frame_names"] == ["f7_dynamic_deint_L_0100"] and b.meta["frame_names"] == ["0100"]
    (native / "right" / "f7_dynamic_deint_R_0100.png").rename(native / "right" / "f7_dynamic_deint_R.png")
    res = _run("measure", native, "--rig", rig, "--fps", "25", "-o", tmp_path / "none.npz")
    assert res.exit_code == 2 and "right ('f7_dynamic_deint_R') share no file name (stem) with left" in res.output
    assert not (tmp_path / "none.npz").exists()


@pytest.mark.skipif(not CALISCOPE.is_dir(), reason="shared data not available (caliscope)")
def test_import_caliscope(tmp_path):
    out = tmp_path / "caliscope.yaml"
    res = _run("rig", "import", CALISCOPE / "camera_array.toml", "-o", out, "--json")
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["rig_frame"] == "custom"
    back = read_rig(out)
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    truth = tomllib.loads((CALISCOPE / "camera_array.toml").read_text())["cameras"]
    assert "\nrig_frame: custom\n" in out.read_text()
    for cam, key in zip(back.cameras, sorted(truth)):
        assert cam.name == f"cam_{truth[key]['cam_id']}"
        assert cam.R.tolist() == truth[key]["rotation"] and cam.t.tolist() == truth[key]["translation"]
        assert cam.K.tolist() == truth[key]["matrix"]


@pytest.mark.skipif(not OPENCV.is_dir(), reason="shared data not available (opencv_stereo)")
def test_import_opencv_left(tmp_path):
    out = tmp_path / "left.yaml"
    res = _run("rig", "import", OPENCV / "left_intrinsics.yml", "-o", out)
    assert res.exit_code == 0, res.output
    (cam,) = read_rig(out).cameras
    assert round(cam.K[0, 0], 3) == round(cam.K[1, 1], 3) == 535.916
    assert (round(cam.K[0, 2], 3), round(cam.K[1, 2], 3)) == (342.283, 235.571)
    res = _run("rig", "import", OPENCV / "intrinsics_samples_data.yml", "--image-size", "640x480", "-o", out)
    assert res.exit_code == 2
    assert "intrinsics_samples_data.yml: R: the second camera's pose is missing" in res.output


def test_rectified(tmp_path):
    out = tmp_path / "rect.yaml"
    res = _run("rig", "rectified", "--image-size", "360x288", "--focal-px", "390", "--baseline-m", "0.0055", "-o",
               out, "--json")
    assert res.exit_code == 0, res.output
    back = read_rig(out)
    assert back.names == ["cam0", "cam1"] and back.meta["producer"] == "heartcv rig rectified"
    assert back[0].K.tolist() == back[1].K.tolist() == [[390.0, 0, 179.5], [0, 390.0, 143.5], [0, 0, 1]]
    np.testing.assert_array_equal(back[1].cam_from_rig, pose_matrix(np.eye(3), [-0.0055, 0, 0]))
    assert not back[0].dist.any() and not back[1].dist.any()
    assert json.loads(res.stdout)["baselines_m"] == {"cam0-cam1": 0.0055}
    res = _run("rig", "rectified", "--image-size", "360x288", "--focal-px", "390", "--baseline-m", "0.0055",
               "--principal-point", "170,150", "--names", "l,r", "-o", out)
    assert res.exit_code == 0, res.output
    assert read_rig(out)["r"].K[:2, 2].tolist() == [170.0, 150.0]


@pytest.mark.parametrize("args, message", [
    (["--baseline-m", "5.5"], "--baseline-m: baseline 5.5 m: looks like millimetres; give it in metres"),
    (["--baseline-m", "0"], "Invalid value for '--baseline-m'"),
    (["--baseline-m", "nan"], "Invalid value for '--baseline-m'"),
    (["--baseline-m", "0.005", "--focal-px", "-1"], "Invalid value for '--focal-px'"),
    (["--baseline-m", "0.005", "--principal-point", "400,10"], "--principal-point: 400,10 lies outside"),
    (["--baseline-m", "0.005", "--names", "a,b,c"], "--names: two names expected"),
])
def test_rectified_refusals(tmp_path, args, message):
    base = ["rig", "rectified", "--image-size", "360x288", "--focal-px", "390", "-o", tmp_path / "r.yaml"]
    res = _run(*base, *args)
    assert res.exit_code == 2 and message in res.output, res.output
    assert not (tmp_path / "r.yaml").exists()


def _pair_folder(root, sizes, packed=None):
    """cam0/ cam1/ folders of two noise images each of ``sizes`` [(W, H), (W, H)]; with ``packed`` one folder
    ``frames/`` of side-by-side frames of the two views instead."""
    import cv2

    rng = np.random.default_rng(0)
    for k in range(2):
        views = [rng.integers(0, 255, (h, w, 3), dtype=np.uint8) for w, h in sizes]
        if packed:
            (root / "frames").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / "frames" / f"{k:04d}.png"), np.hstack(views))
            continue
        for cam, v in zip(("cam0", "cam1"), views):
            (root / cam).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / cam / f"{k:04d}.png"), v)
    return root


def test_rectified_size_of_a_sequence_and_field_of_view(tmp_path):
    """--size-of SEQUENCE takes the views' size as measure reads them: the same file as --image-size, byte for byte;
    --packed side-by-side: one view's size; --hfov-deg: f = (W / 2) / tan(hfov / 2) (90 degrees: f = W / 2)."""
    seq = _pair_folder(tmp_path / "seq", [(320, 240), (320, 240)])
    base = ["rig", "rectified", "--focal-px", "300", "--baseline-m", "0.005"]
    assert _run(*base, "--image-size", "320x240", "-o", tmp_path / "a.yaml").exit_code == 0
    res = _run(*base, "--size-of", seq, "-o", tmp_path / "b.yaml")
    assert res.exit_code == 0, res.output
    assert (tmp_path / "a.yaml").read_bytes() == (tmp_path / "b.yaml").read_bytes()
    packed = _pair_folder(tmp_path / "packed", [(200, 150), (200, 150)], packed=True)
    res = _run(*base, "--size-of", packed, "--packed", "side-by-side", "-o", tmp_path / "c.yaml")
    assert res.exit_code == 0, res.output
    assert (read_rig(tmp_path / "c.yaml")[0].width, read_rig(tmp_path / "c.yaml")[0].height) == (200, 150)
    res = _run("rig", "rectified", "--image-size", "320x240", "--hfov-deg", "90", "--baseline-m", "0.005", "-o",
               tmp_path / "d.yaml", "--json")
    assert res.exit_code == 0, res.output
    assert abs(json.loads(res.stdout)["cameras"][0]["fx"] - 160.0) < 1e-9
    res = _run("rig", "rectified", "--image-size", "320x240", "--hfov-deg", "60", "--baseline-m", "0.005", "-o",
               tmp_path / "e.yaml")
    assert abs(read_rig(tmp_path / "e.yaml")[1].K[0, 0] - 160.0 / np.tan(np.radians(30.0))) < 1e-9


@pytest.mark.parametrize("args, message", [
    (["--focal-px", "390"], "--image-size or --size-of: one of them expected"),
    (["--image-size", "360x288"], "--focal-px or --hfov-deg: one of them expected"),
    (["--image-size", "360x288", "--focal-px", "390", "--hfov-deg", "50"], "--focal-px and --hfov-deg: one of them"),
    (["--image-size", "360x288", "--focal-px", "390", "--packed", "rows"], "--packed: only with --size-of"),
    (["--image-size", "360x288", "--hfov-deg", "180"], "Invalid value for '--hfov-deg'"),
    (["--size-of", "SEQ", "--image-size", "360x288", "--focal-px", "390"], "--image-size and --size-of: one of"),
    (["--size-of", "ODD", "--focal-px", "390"], "ODD: image size: instant 0000: the views are 320x240 and 300x240"),
])
def test_rectified_size_and_focal_refusals(tmp_path, args, message):
    _pair_folder(tmp_path / "SEQ", [(320, 240), (320, 240)])
    _pair_folder(tmp_path / "ODD", [(320, 240), (300, 240)])
    args = [str(tmp_path / a) if a in ("SEQ", "ODD") else a for a in args]
    res = CliRunner().invoke(main, ["rig", "rectified", "--baseline-m", "0.005", "-o", str(tmp_path / "r.yaml"),
                                    *args])
    assert res.exit_code == 2 and message.replace("ODD", str(tmp_path / "ODD")) in res.output, res.output
    assert not (tmp_path / "r.yaml").exists()


def _sources(tmp_path) -> dict:
    """One valid file of every format (name -> bytes)."""
    import cv2

    from heartcv.io import write_colmap

    src, rig = _stereo(tmp_path)
    write_colmap(tmp_path / "colmap", rig)
    fs = cv2.FileStorage(str(tmp_path / "all.yml"), cv2.FILE_STORAGE_WRITE)
    for k, v in (("M1", rig[0].K), ("D1", rig[0].dist), ("M2", rig[1].K), ("D2", rig[1].dist), ("R", rig[1].R),
                 ("T", rig[1].t)):
        fs.write(k, v)
    fs.release()
    toml = ("[cameras.0]\ncam_id = 0\nsize = [640, 480]\nmatrix = [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], "
            "[0.0, 0.0, 1.0]]\ndistortions = [0.1, 0.0, 0.0, 0.0, 0.0]\nrotation = [0.1, -0.2, 0.3]\n"
            "translation = [0.1, 0.2, 0.3]\nignore = false\n")
    return {"camchain.yaml": src.read_bytes(), "cameras.txt": (tmp_path / "colmap" / "cameras.txt").read_bytes(),
            "rigs.txt": (tmp_path / "colmap" / "rigs.txt").read_bytes(), "camera_array.toml": toml.encode(),
            "all.yml": (tmp_path / "all.yml").read_bytes(),
            "p.4x4": b"0.999999 -0.001045 0.0 -5.52\n0.001045 0.999999 0.0 -0.03\n0.0 0.0 1.0 -0.05\n0 0 0 1\n"}


def test_import_mutated_files_never_internal_error(tmp_path):
    """Seeded mutations of a valid file of every format: exit 0 or 2, never an internal error or a traceback."""
    rng = np.random.default_rng(7)
    sources = _sources(tmp_path)
    tokens = [b"nan", b"inf", b"-", b"0", b"1e400", b"[", b"]", b"{", b'"', b"\n", b" ", b"ignore = true", b"-1",
              b"99999999999999999999", b"x", b"\xff", b",", b":", b"!!opencv-matrix", b"..."]
    k = tmp_path / "k.txt"
    k.write_text("500 0 320\n0 500 240\n0 0 1\n")
    for case in range(120):
        name = list(sources)[case % len(sources)]
        data = bytearray(sources[name])
        for _ in range(rng.integers(1, 4)):
            i = rng.integers(len(data))
            op = rng.integers(3)
            if op == 0:
                del data[i:i + rng.integers(1, 20)]
            elif op == 1:
                data[i:i] = tokens[rng.integers(len(tokens))]
            else:
                data[i:i + rng.integers(1, 8)] = tokens[rng.integers(len(tokens))]
        folder = tmp_path / f"case{case}"
        folder.mkdir()
        (folder / name).write_bytes(bytes(data))
        if name == "rigs.txt":
            (folder / "cameras.txt").write_bytes(sources["cameras.txt"])
        args = [k, k, folder / name, "--units", "mm"] if name == "p.4x4" else [folder / name]
        res = _run("rig", "import", *args, "--image-size", "640x480", "-o", folder / "out.yaml")
        assert res.exit_code in (0, 2), (case, name, res.output)
        assert "internal error" not in res.output and "Traceback" not in res.output, (case, name, res.output)
        assert res.exit_code == 2 or read_rig(folder / "out.yaml").names


def test_import_rig_file_reads_with_opencv(tmp_path, monkeypatch):
    """The rig file stays readable by cv2.FileStorage (docs/formats.md §8.2), also with source paths such as
    ``../x.yaml`` that YAML must quote (OpenCV cannot read quoted keys: they appear only as values)."""
    import cv2

    src, rig = _stereo(tmp_path)
    (tmp_path / "sub").mkdir()
    monkeypatch.chdir(tmp_path / "sub")
    res = _run("rig", "import", "../camchain.yaml", "-o", "rig.yaml")
    assert res.exit_code == 0, res.output
    fs = cv2.FileStorage()
    assert fs.open("rig.yaml", cv2.FILE_STORAGE_READ)
    cam = fs.getNode("cameras").at(1)
    assert cam.getNode("K").at(0).at(0).real() == rig[1].K[0, 0]
    assert fs.getNode("source_files").at(0).getNode("file").string() == "../camchain.yaml"
    fs.release()
