"""Output safety and error semantics of the vision stages (target, calibrate, render, measure): no stage replaces,
deletes or modifies an input or a file or folder heartcv did not write (exit 2 naming both paths, the input's bytes
unchanged), an unwritable output is a clean exit 2 naming it, and an exception inside the computation is reported
as a bug (exit 1, "internal error"), never as bad input. Each overwrite case failed on the code before the
output guards (it replaced, deleted or wrote into the input)."""

from __future__ import annotations

import hashlib
from pathlib import Path
import shutil

from click.testing import CliRunner
import pytest
import yaml

from heartcv.cli.main import main
from tests.cli.test_calibrate_cli import syn_set, syn_target  # noqa: F401 - fixtures
from tests.cli.test_measure_cli import rendered  # noqa: F401 - fixture
from tests.heartcv.render_scenes import scene_dict, write_truth_model

CHARUCO = ["target", "--type", "charuco", "--squares", "5x4", "--square-mm", "20", "--marker-mm", "15",
           "--dict", "DICT_4X4_50", "--dpi", "100"]


def _run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _snapshot(*paths) -> dict:
    """sha256 of every file under the given files and folders (names relative to nothing: absolute)."""
    files = {}
    for p in map(Path, paths):
        for f in ([p] if p.is_file() else sorted(q for q in p.rglob("*") if q.is_file())):
            files[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest()
    return files


def _break(monkeypatch, module, name):
    """Make ``module.name`` raise a ValueError, as a bug inside the computation would."""
    def broken(*a, **k):
        raise ValueError("broken on purpose")

    monkeypatch.setattr(module, name, broken)


def _internal_error(res):
    """Exit 1 with the one-line internal error naming the exception: a bug, never blamed on the input."""
    assert res.exit_code == 1, res.output
    assert "internal error: ValueError" in res.stderr and "broken on purpose" in res.stderr
    assert "this is a bug in heartcv" in res.stderr and "Traceback" not in res.output


def _refused(res, *names):
    """Exit 2, one line naming every path in ``names``, no traceback, no internal error."""
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output and "internal error" not in res.stderr
    for n in names:
        assert str(n) in res.stderr, (n, res.stderr)


# =====================================================================================================================
# heartcv target: NAME.yaml, NAME.png, NAME.pdf
# =====================================================================================================================
@pytest.mark.parametrize("suffix", [".yaml", ".png", ".pdf"])
def test_target_never_replaces_a_file_heartcv_did_not_write(tmp_path, suffix):
    mine = tmp_path / f"board{suffix}"
    mine.write_bytes({".yaml": b"name: mine\n", ".png": b"\x89PNG\r\n\x1a\nmine", ".pdf": b"%PDF-1.4 mine"}[suffix])
    before = _snapshot(tmp_path)
    res = _run(*CHARUCO, "-o", tmp_path / "board.yaml")
    _refused(res, mine, "exists and was not written by heartcv; not replaced")
    assert _snapshot(tmp_path) == before


def test_target_rerun_replaces_its_own_files(tmp_path):
    out = tmp_path / "board.yaml"
    assert _run(*CHARUCO, "-o", out).exit_code == 0
    first = _snapshot(tmp_path)
    assert sorted(Path(p).name for p in first) == ["board.pdf", "board.png", "board.yaml"]
    res = _run(*CHARUCO, "--name", "again", "-o", out)
    assert res.exit_code == 0, res.output
    assert yaml.safe_load(out.read_text())["name"] == "again"
    assert sorted(Path(p).name for p in _snapshot(tmp_path)) == ["board.pdf", "board.png", "board.yaml"]


def test_target_unwritable_output_exit_2(tmp_path):
    (tmp_path / "afile.txt").write_text("a file, not a folder")
    res = _run(*CHARUCO, "-o", tmp_path / "afile.txt" / "board.yaml")
    _refused(res, tmp_path / "afile.txt" / "board.yaml", "is not a folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile.txt"]


def test_target_bug_in_the_computation_is_an_internal_error(tmp_path, monkeypatch):
    import heartcv.targets

    _break(monkeypatch, heartcv.targets, "render_board")
    res = _run(*CHARUCO, "-o", tmp_path / "board.yaml")
    _internal_error(res)
    assert list(tmp_path.iterdir()) == []


# =====================================================================================================================
# heartcv calibrate: RIG.yaml, RIG_colmap/, RIG_camchain.yaml
# =====================================================================================================================
def _syn_folder(tmp_path, syn_set):  # noqa: F811
    from tests.cli.test_calibrate_cli import _syn_folder as link

    return link(tmp_path / "calib", syn_set)


def test_calibrate_output_is_the_target(tmp_path, syn_set, syn_target):  # noqa: F811
    target = tmp_path / "target.yaml"
    shutil.copy(syn_target, target)
    folder = _syn_folder(tmp_path, syn_set)
    before = _snapshot(target, folder)
    res = _run("calibrate", folder, "--target", target, "-o", target)
    _refused(res, f"{target}: -o/--output: is the input --target ({target})")
    assert _snapshot(target, folder) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calib", "target.yaml"]


def test_calibrate_kalibr_export_is_the_target(tmp_path, syn_set, syn_target):  # noqa: F811
    """--dist 5 (k3 estimated): the old code removed a 'stale' RIG_camchain.yaml -- here the user's target."""
    target = tmp_path / "rig_camchain.yaml"
    shutil.copy(syn_target, target)
    folder = _syn_folder(tmp_path, syn_set)
    before = _snapshot(target)
    res = _run("calibrate", folder, "--target", target, "-o", tmp_path / "rig.yaml", "--dist", "5")
    _refused(res, f"{target}: Kalibr export: is the input --target ({target})")
    assert _snapshot(target) == before and not (tmp_path / "rig.yaml").exists()


def test_calibrate_colmap_export_contains_the_images(tmp_path, syn_set, syn_target):  # noqa: F811
    folder = _syn_folder(tmp_path, syn_set)
    colmap = tmp_path / "rig_colmap"
    folder.rename(colmap)
    before = _snapshot(colmap)
    res = _run("calibrate", colmap, "--target", syn_target, "-o", tmp_path / "rig.yaml")
    _refused(res, f"{colmap}: COLMAP export: is the input FOLDER ({colmap})")
    assert _snapshot(colmap) == before and sorted(p.name for p in colmap.iterdir()) == ["cam0", "cam1", "cam2"]


def test_calibrate_never_replaces_a_colmap_model_it_did_not_write(tmp_path, syn_set, syn_target):  # noqa: F811
    folder = _syn_folder(tmp_path, syn_set)
    colmap = tmp_path / "rig_colmap"
    colmap.mkdir()
    (colmap / "cameras.txt").write_text("# the user's own COLMAP model\n1 PINHOLE 640 480 1 1 1 1\n")
    (colmap / "images.txt").write_text("# more of it\n")
    before = _snapshot(colmap)
    res = _run("calibrate", folder, "--target", syn_target, "-o", tmp_path / "rig.yaml")
    _refused(res, colmap, "holds no heartcv manifest")
    assert _snapshot(colmap) == before and not (tmp_path / "rig.yaml").exists()


def test_calibrate_rerun_replaces_its_own_outputs_and_logs_at_info(tmp_path, syn_set, syn_target):  # noqa: F811
    folder = _syn_folder(tmp_path, syn_set)
    out = tmp_path / "out" / "rig.yaml"
    from heartcv.camera import Camera, Rig
    from heartcv.io import read_rig, write_rig

    given = tmp_path / "given.yaml"
    for run in (1, 2):
        extra = [] if run == 1 else ["--intrinsics", given, "--hold", "all"]
        res = _run("calibrate", folder, "--target", syn_target, "-o", out, "--dist", "5", *extra)
        assert res.exit_code == 0, res.output
        assert f"INFO heartcv.cli.calibrate: wrote {out}: 3 cameras" in res.stderr
        assert "WARNING heartcv.cli.calibrate: wrote" not in res.stderr
        if run == 1:  # the views cover under half of each image: k3 held at 0, a camchain is written
            assert (out.parent / "rig_camchain.yaml").is_file()
            rig = read_rig(out)
            write_rig(given, Rig(tuple(Camera(c.name, c.width, c.height, c.K, [*c.dist[:4], 1e-3], c.cam_from_rig)
                                       for c in rig.cameras)))
    # the second run (intrinsics held with k3 = 1e-3: no camchain) removed the camchain of the first, its own file
    assert sorted(p.name for p in out.parent.iterdir()) == ["rig.yaml", "rig_colmap"]
    assert sorted(p.name for p in (out.parent / "rig_colmap").iterdir()) == ["cameras.txt", "heartcv-manifest.json",
                                                                            "rigs.txt"]
    # intrinsics of other images (half the resolution): exit 2 naming the file, the camera and both sizes
    rig = read_rig(given)
    halved = tmp_path / "halved.yaml"
    write_rig(halved, Rig(tuple(Camera(c.name, c.width // 2, c.height // 2, c.K * [[0.5], [0.5], [1]], c.dist,
                                       c.cam_from_rig) for c in rig.cameras)))
    c0 = rig.cameras[0]
    res = _run("calibrate", folder, "--target", syn_target, "-o", tmp_path / "other.yaml", "--dist", "5",
               "--intrinsics", halved, "--hold", "all")
    _refused(res, halved)
    assert (f"camera {c0.name} is {c0.width // 2}x{c0.height // 2} px, but its views in FOLDER are "
            f"{c0.width}x{c0.height}") in res.stderr
    assert not (tmp_path / "other.yaml").exists()


def test_calibrate_unwritable_output_exit_2(tmp_path, syn_target):  # noqa: F811
    (tmp_path / "afile.txt").write_text("a file")
    (tmp_path / "calib").mkdir()
    res = _run("calibrate", tmp_path / "calib", "--target", syn_target, "-o", tmp_path / "afile.txt" / "rig.yaml")
    _refused(res, tmp_path / "afile.txt" / "rig.yaml", "is not a folder")


def test_calibrate_bug_in_the_kalibr_export_is_an_internal_error(tmp_path, syn_set, syn_target, monkeypatch):  # noqa: F811
    """The old code took any ValueError of the Kalibr export for 'Kalibr cannot hold this model' (exit 0)."""
    import heartcv.io

    _break(monkeypatch, heartcv.io, "kalibr_camchain")
    folder = _syn_folder(tmp_path, syn_set)
    res = _run("calibrate", folder, "--target", syn_target, "-o", tmp_path / "rig.yaml", "--dist", "4")
    _internal_error(res)
    assert not (tmp_path / "rig.yaml").exists()


# =====================================================================================================================
# heartcv render: an output folder
# =====================================================================================================================
@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    return write_truth_model(tmp_path_factory.mktemp("safety_model") / "truth.yaml")


def _scene(folder: Path, model, **sections) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "scene.yaml"
    path.write_text(yaml.safe_dump(scene_dict(model, **sections)))
    return path


@pytest.mark.parametrize("cmd", ["sequence", "calibration"])
def test_render_into_the_scene_folder_is_refused(tmp_path, model_file, cmd):
    """The old code deleted the whole folder holding the scene and model files."""
    work = tmp_path / "work"
    model = work / "model.yaml"
    work.mkdir()
    shutil.copy(model_file, model)
    scene = _scene(work, model)
    (work / "notes.txt").write_text("the user's notes")
    before = _snapshot(work)
    res = _run("render", cmd, scene, "-o", work)
    _refused(res, f"{work}: -o/--output: contains the input SCENE_FILE ({scene})")
    assert _snapshot(work) == before


@pytest.mark.parametrize("field", ["motion.model", "calibration.target"])
def test_render_into_a_folder_holding_a_file_the_scene_names_is_refused(tmp_path, model_file, field):
    from tests.cli.test_target_cli import DEFAULT

    data = tmp_path / "data"
    data.mkdir()
    model = (data if field == "motion.model" else tmp_path) / "model.yaml"
    target = (data if field == "calibration.target" else tmp_path) / "target.yaml"
    shutil.copy(model_file, model)
    shutil.copy(DEFAULT, target)
    named = model if field == "motion.model" else target
    scene = _scene(tmp_path / "scenes", model, calibration={"target": str(target)})
    before = _snapshot(data)
    res = _run("render", "calibration" if field == "calibration.target" else "sequence", scene, "-o", data)
    _refused(res, f"{data}: -o/--output: contains the input {field} ({named})")
    assert _snapshot(data) == before


def test_render_never_replaces_a_folder_it_did_not_write(tmp_path, model_file):
    scene = _scene(tmp_path / "scenes", model_file)
    out = tmp_path / "photos"
    out.mkdir()
    (out / "holiday.png").write_bytes(b"\x89PNG not heartcv's")
    before = _snapshot(out)
    res = _run("render", "sequence", scene, "-o", out, "--frames", "1")
    _refused(res, out, "holds no heartcv manifest: heartcv render replaces only a folder it wrote itself")
    assert _snapshot(out) == before


def test_render_unwritable_output_exit_2(tmp_path, model_file):
    scene = _scene(tmp_path / "scenes", model_file)
    (tmp_path / "afile.txt").write_text("a file")
    res = _run("render", "sequence", scene, "-o", tmp_path / "afile.txt" / "out", "--frames", "1")
    _refused(res, tmp_path / "afile.txt" / "out", "is not a folder")


def test_render_bug_in_the_computation_is_an_internal_error(tmp_path, model_file, monkeypatch):
    """The old code reported any ValueError of the set-up as a bad scene (exit 2)."""
    import heartcv.render.sequence

    _break(monkeypatch, heartcv.render.sequence, "prepare_sequence")
    scene = _scene(tmp_path / "scenes", model_file)
    res = _run("render", "sequence", scene, "-o", tmp_path / "out", "--frames", "1")
    _internal_error(res)
    assert not (tmp_path / "out").exists()


# =====================================================================================================================
# heartcv measure: -o MEAS.npz, --csv
# =====================================================================================================================
@pytest.fixture
def case(tmp_path, rendered):  # noqa: F811
    """A private copy of the rendered sequence (with its truth), its rig and a mask."""
    import cv2
    import numpy as np

    seq = tmp_path / "seq"
    shutil.copytree(rendered, seq)
    rig = tmp_path / "rig.yaml"
    shutil.copy(rendered / "rig_truth.yaml", rig)
    mask = tmp_path / "mask.png"
    cv2.imwrite(str(mask), np.full((270, 480), 255, np.uint8))
    return {"seq": seq, "rig": rig, "mask": mask, "root": tmp_path}


def _measure(case, *args):
    return _run("measure", case["seq"], "--rig", case["rig"], "--points", "50", *args)


@pytest.mark.parametrize("option, target, label", [
    ("--csv", "rig", "--rig"),
    ("--csv", "mask", "--mask"),
    ("--csv", "seq/inputs.csv", "--inputs"),
    ("--csv", "seq/timestamps.csv", "SEQUENCE/timestamps.csv"),
    ("--csv", "seq/cam0/000000.png", "SEQUENCE/cam0/000000.png"),
    ("-o", "seq/truth.npz", "--truth"),
    ("-o", "seq/truth.npz", "SEQUENCE/truth.npz"),
])
def test_measure_output_is_an_input(case, option, target, label):
    """Each of these replaced an input on the old code (the rig and the truth only after the whole run)."""
    path = case[target] if target in case else case["root"] / target
    outputs = {"-o": case["root"] / "meas.npz", "--csv": None, option: path}
    args = ["-o", outputs["-o"], "--mask", case["mask"]]
    args += ["--csv", outputs["--csv"]] if outputs["--csv"] else []
    args += ["--truth", path] if label == "--truth" else []
    before = _snapshot(case["seq"], case["rig"], case["mask"])
    res = _measure(case, *args)
    _refused(res, f"{path}: {'--csv' if option == '--csv' else '-o/--output'}: is the input {label} ({path})")
    assert _snapshot(case["seq"], case["rig"], case["mask"]) == before
    assert not (case["root"] / "meas.npz").exists()


def test_measure_never_replaces_a_file_heartcv_did_not_write(case):
    notes = case["root"] / "notes.csv"
    notes.write_text("my,own\n1,2\n")
    res = _measure(case, "-o", case["root"] / "meas.npz", "--csv", notes)
    _refused(res, notes, "exists and was not written by heartcv")
    assert notes.read_text() == "my,own\n1,2\n" and not (case["root"] / "meas.npz").exists()


def test_measure_csv_and_output_the_same_file(case):
    out = case["root"] / "meas.npz"
    res = _measure(case, "-o", out, "--csv", out)
    _refused(res, f"--csv: {out} is the -o/--output file")


def test_measure_unwritable_output_exit_2(case):
    (case["root"] / "afile.txt").write_text("a file")
    res = _measure(case, "-o", case["root"] / "afile.txt" / "meas.npz")
    _refused(res, case["root"] / "afile.txt" / "meas.npz", "is not a folder")


def test_measure_rerun_replaces_its_own_outputs_and_logs_at_info(case):
    out, csv = case["root"] / "out" / "meas.npz", case["root"] / "out" / "meas.csv"
    for _ in range(2):
        res = _measure(case, "-o", out, "--csv", csv, "--frames", "3")
        assert res.exit_code == 0, res.output
        assert f"INFO heartcv.cli.measure: wrote {out}: 3 frames" in res.stderr
        assert "WARNING heartcv.cli.measure: wrote" not in res.stderr
    assert sorted(p.name for p in out.parent.iterdir()) == ["meas.csv", "meas.npz"]


def test_measure_bug_in_the_set_up_is_an_internal_error(case, monkeypatch):
    """The old code reported any ValueError of the backend's set-up as a bad --backend/--device (exit 2)."""
    import heartcv.backend

    _break(monkeypatch, heartcv.backend, "get_backend")
    res = _measure(case, "-o", case["root"] / "meas.npz")
    _internal_error(res)
    assert not (case["root"] / "meas.npz").exists()


@pytest.mark.parametrize("cmd, args, message", [
    ("calibrate", ["--max-view-rms", "nan"], "'nan': a finite number expected"),
    ("calibrate", ["--max-view-rms", "inf"], "'inf': a finite number expected"),
    ("calibrate", ["--max-view-rms", "0"], "0 is not in the range (0, 1000]"),
    ("calibrate", ["--every", "0"], "0 is not in the range 1<=x<=1000000"),
    ("calibrate", ["--min-views", "1000001"], "1000001 is not in the range 3<=x<=1000000"),
    ("calibrate", ["--jobs", "1025"], "1025 is not in the range 1<=x<=1024"),
    ("measure", ["--fps", "nan"], "'nan': a finite number expected"),
    ("measure", ["--fps", "inf"], "'inf': a finite number expected"),
    ("measure", ["--fps", "0"], "0 is not in the range (0, 10000]"),
    ("measure", ["--fps", "10001"], "10001 is not in the range (0, 10000]"),
    ("measure", ["--corner-quality", "nan"], "'nan': a finite number expected"),
    ("measure", ["--corner-quality", "0"], "0 is not in the range (0, 1]"),
    ("measure", ["--highpass", "inf"], "'inf': a finite number expected"),
    ("measure", ["--highpass", "-1"], "-1 is not in the range [0, 1000]"),
    ("measure", ["--pixel-sigma", "nan"], "'nan': a finite number expected"),
    ("measure", ["--min-distance", "-inf"], "'-inf': a finite number expected"),
    ("measure", ["--points", "1000001"], "1000001 is not in the range 1<=x<=1000000"),
    ("measure", ["--frames", "0"], "0 is not in the range 1<=x<=1000000"),
    ("measure", ["--corner-block", "256"], "256 is not in the range 2<=x<=255"),
    ("measure", ["--workers", "0"], "0 is not in the range 1<=x<=1024"),
])
def test_out_of_range_options_exit_2(tmp_path, cmd, args, message):
    """Refused by click before any work (nothing read, nothing written)."""
    inputs = {"calibrate": ["--target", tmp_path / "t.yaml", "-o", tmp_path / "rig.yaml"],
              "measure": ["--rig", tmp_path / "rig.yaml", "-o", tmp_path / "m.npz"]}[cmd]
    res = _run(cmd, tmp_path, *inputs, *args)
    assert res.exit_code == 2 and message in res.stderr, res.output
    assert list(tmp_path.iterdir()) == []


def test_measure_unknown_device_exit_2(case):
    pytest.importorskip("kornia")
    res = _measure(case, "-o", case["root"] / "meas.npz", "--backend", "kornia", "--device", "nonsense")
    _refused(res, "--device: 'nonsense' is not a torch device")
    assert not (case["root"] / "meas.npz").exists()
