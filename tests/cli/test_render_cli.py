"""CLI: heartcv render calibration / render sequence (CliRunner, exit codes, artifacts read back)."""

from dataclasses import replace
import json

from click.testing import CliRunner
import numpy as np
import pytest
import yaml

from heartcv.cli.main import main
from heartcv.io import list_image_folder, read_image, read_inputs_csv, read_render_truth, read_rig
from heartcv.tracker.io import read_model
from tests.conftest import SAMPLES
from tests.heartcv.render_scenes import scene_dict, write_truth_model


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    return write_truth_model(tmp_path_factory.mktemp("render_cli") / "truth.yaml")


@pytest.fixture
def runner():
    return CliRunner()


def _scene(tmp_path, model_file, **sections):
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(scene_dict(model_file, **sections)))
    return str(path)


def _json(result):
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def test_render_calibration(runner, tmp_path, model_file):
    scene = _scene(tmp_path, model_file, calibration={"views": 2, "partial_fraction": 0.5,
                                                      "target": str(SAMPLES.parent / "calibration_targets" /
                                                                    "charuco_11x8_12mm.yaml")})
    out = tmp_path / "calib"
    summary = _json(runner.invoke(main, ["render", "calibration", scene, "-o", str(out), "--workers", "1",
                                         "--json"]))
    assert summary["views"] == 2 and summary["partial_views"] == 1 and summary["cameras"] == ["cam0", "cam1", "cam2"]
    names = [[p.name for p in list_image_folder(out / c)] for c in summary["cameras"]]
    assert names[0] == names[1] == names[2] == ["000000.png", "000001.png"]
    img = read_image(out / "cam1" / "000001.png", expected_size=(480, 270))
    assert img.std() > 10
    arrays, meta = read_render_truth(out / "truth.npz")
    assert meta["kind"] == "calibration" and meta["file_names"] == names[0] and meta["target"]["name"]
    assert arrays["cam_from_board"].shape == (2, 3, 4, 4) and arrays["corners_uv"].shape[:2] == (2, 3)
    rig = read_rig(out / "rig_truth.yaml")
    assert np.allclose(np.stack([c.K for c in rig.cameras]), arrays["K"])
    assert np.allclose(rig.cameras[2].cam_from_rig, arrays["cam_from_world"][2])
    assert (out / "scene.yaml").read_text() == open(scene).read()


def test_render_sequence(runner, tmp_path, model_file):
    scene = _scene(tmp_path, model_file, seed=3, phantom={"fiducials": {"enabled": True}},
                   instrument={"enabled": True, "window_s": [0.09, 1.0], "enter_s": 0.05},
                   motion={"respiration": True}, motion_blur={"subsamples": 2, "exposure_fraction": 0.5})
    out = tmp_path / "seq"
    summary = _json(runner.invoke(main, ["render", "sequence", scene, "-o", str(out), "--frames", "4", "--json"]))
    assert summary["frames"] == 4 and summary["instrument"] and summary["seed"] == 3
    for cam in summary["cameras"]:
        files = list_image_folder(out / cam)
        assert [p.name for p in files] == [f"{k:06d}.png" for k in range(4)]
        assert read_image(files[0], "color").shape == (270, 480, 3)
    cols, vals = read_inputs_csv(out / "inputs.csv")
    assert cols == ["time_s", "pressure_pa", "respiration_x_m", "respiration_y_m", "respiration_z_m"]
    assert vals.shape == (4, 5) and np.allclose(vals[:, 0], np.arange(4) / 30)
    assert (out / "inputs.csv").read_text().startswith("# heartcv render sequence")
    arrays, meta = read_render_truth(out / "truth.npz")
    assert meta["kind"] == "sequence" and meta["seed"] == 3 and meta["camera_names"] == summary["cameras"]
    V = arrays["reference_vertices"].shape[0]
    assert arrays["vertex_positions"].shape == (4, V, 3) and arrays["theta"].shape == (4, 5)
    assert np.allclose(arrays["inputs"][:, 0], vals[:, 1]) and np.allclose(arrays["translation"], vals[:, 2:])
    mask = np.unpackbits(arrays["instrument_mask"], axis=-1)[..., :480].astype(bool)
    assert mask.shape == (4, 3, 270, 480) and not mask[:3].any() and mask[3].any()
    assert list(arrays["instrument_present"]) == [False, False, False, True]
    per_frame = [k for k in arrays if k in ("times", "theta", "inputs", "translation", "vertex_positions",
                                            "point_positions", "fiducial_positions", "instrument_tip",
                                            "instrument_present", "instrument_mask")]
    assert len(per_frame) == 10 and {arrays[k].shape[0] for k in per_frame} == {4}  # the rendered frames only
    assert "timestamps.csv" in json.loads((out / "heartcv-manifest.json").read_text())["files"]


def test_render_sequence_of_more_frames_than_the_scene_holds_warns(runner, tmp_path, model_file):
    scene = _scene(tmp_path, model_file, motion={"duration_s": 0.1})
    res = runner.invoke(main, ["render", "sequence", scene, "-o", str(tmp_path / "s"), "--frames", "50", "--json"])
    assert res.exit_code == 0 and json.loads(res.stdout)["frames"] == 4, res.output
    assert "--frames 50: the scene holds 4 frames" in res.stderr


def test_render_sequence_stiffness_cycle_override(runner, tmp_path, model_file):
    """--stiffness-cycle replaces the scene's amplitude: 0 gives the model file's constant E in every frame, a
    positive value E (1 + a p / p_max) (the test scene's 'pressure' shape) with the inputs.csv pressure."""
    scene = _scene(tmp_path, model_file)
    E0 = read_model(model_file).theta[3]
    for amp in (0.0, 2.0):
        out = tmp_path / f"seq{amp}"
        _json(runner.invoke(main, ["render", "sequence", scene, "-o", str(out), "--frames", "6",
                                   "--stiffness-cycle", str(amp), "--json"]))
        arrays, meta = read_render_truth(out / "truth.npz")
        assert meta["stiffness_cycle"]["amplitude"] == amp
        p = arrays["inputs"][:, 0]
        assert p.max() > 0
        E = arrays["theta"][:, 3]
        if amp == 0:
            assert np.array_equal(E, np.full(6, E0))
        else:
            s = (E / E0 - 1) / amp                       # p / p_max, p_max over the whole cycle >= these frames'
            assert np.allclose(s * p.max() / s.max(), p, rtol=1e-9) and 0 < s.max() <= 1 + 1e-12
    result = runner.invoke(main, ["render", "sequence", scene, "-o", str(tmp_path / "bad"), "--stiffness-cycle",
                                  "-1"])
    assert result.exit_code == 2 and not (tmp_path / "bad").exists()


def test_render_sequence_same_seed_same_images(runner, tmp_path, model_file):
    scene = _scene(tmp_path, model_file)
    a, b = tmp_path / "a", tmp_path / "b"
    for out, workers in ((a, "1"), (b, "2")):
        _json(runner.invoke(main, ["render", "sequence", scene, "-o", str(out), "--frames", "2", "--workers",
                                   workers, "--json"]))
    for name in ("cam0/000001.png", "cam2/000000.png", "inputs.csv"):
        assert (a / name).read_bytes() == (b / name).read_bytes()


@pytest.mark.parametrize("patch, field", [
    ({"phantom": {"textur": {}}}, "phantom.textur"),
    ({"noise": {"read_noise_e": -1}}, "noise.read_noise_e"),
    ({"motion": {"frame_rate_hz": 0}}, "motion.frame_rate_hz"),
])
def test_bad_scene_field_exits_2_naming_it(runner, tmp_path, model_file, patch, field):
    scene = _scene(tmp_path, model_file, **patch)
    for cmd in ("sequence", "calibration"):
        result = runner.invoke(main, ["render", cmd, scene, "-o", str(tmp_path / "out")])
        assert result.exit_code == 2, result.output
        assert field in result.stderr and "Traceback" not in result.output
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("cmd, patch, message", [
    ("sequence", {"phantom": {"apex_m": 0.001}}, "phantom.apex_m: the end must lie beyond the patch"),
    ("calibration", {"calibration": {"views": 1, "offset_m": 1.0}}, "calibration: no pose found for view 0"),
    ("calibration", {"calibration": {"views": 1, "min_corners": 5000}},
     "calibration.min_corners: 5000: the target has"),
])
def test_scene_the_core_refuses_exits_2_naming_file_and_field(runner, tmp_path, model_file, cmd, patch, message):
    """A phantom that cannot be built, board poses no two cameras see: the core's InputError, with the scene file."""
    scene = _scene(tmp_path, model_file, **patch)
    result = runner.invoke(main, ["render", cmd, scene, "-o", str(tmp_path / "out"), "--workers", "1"])
    assert result.exit_code == 2, result.output
    assert f"Error: {scene}: {message}" in result.stderr and "internal error" not in result.stderr
    assert not (tmp_path / "out").exists()


def test_missing_model_or_target_exits_2(runner, tmp_path, model_file):
    scene = _scene(tmp_path, tmp_path / "nope.yaml")
    result = runner.invoke(main, ["render", "sequence", scene, "-o", str(tmp_path / "out")])
    assert result.exit_code == 2 and "motion.model" in result.stderr
    scene = _scene(tmp_path, model_file, calibration={"target": "missing_target.yaml"})
    result = runner.invoke(main, ["render", "calibration", scene, "-o", str(tmp_path / "out")])
    assert result.exit_code == 2 and "calibration.target" in result.stderr
    # the file only the other kind of render uses is checked too (each kind ignored it: exit 0)
    result = runner.invoke(main, ["render", "sequence", scene, "-o", str(tmp_path / "out"), "--frames", "1"])
    assert result.exit_code == 2 and f"{scene}: calibration.target:" in result.stderr, result.output
    scene = _scene(tmp_path, tmp_path / "nope.yaml")
    result = runner.invoke(main, ["render", "calibration", scene, "-o", str(tmp_path / "out"), "--views", "1"])
    assert result.exit_code == 2 and f"{scene}: motion.model:" in result.stderr, result.output
    assert not (tmp_path / "out").exists()


def _listing(folder):
    """{relative path: bytes} of every file under ``folder``."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_output_folder_is_replaced_only_when_complete(runner, tmp_path, model_file, monkeypatch):
    """A render that fails half-way leaves the previous render's folder as it was and no temporary folder; a
    complete one replaces it as a whole."""
    scene = _scene(tmp_path, model_file)
    out = tmp_path / "seq"
    _json(runner.invoke(main, ["render", "sequence", scene, "-o", str(out), "--frames", "2", "--json"]))
    (out / "note.txt").write_text("added after the first render")
    res = runner.invoke(main, ["render", "sequence", scene, "-o", str(out), "--frames", "3", "--workers", "1"])
    assert res.exit_code == 2 and "holds files heartcv render did not write (note.txt)" in res.stderr
    (out / "note.txt").unlink()      # a file added to the folder is refused before any work, then taken out
    before = _listing(out)

    import heartcv.render.sequence as seq

    real = seq.render_frame

    def failing(setup, k, **kw):
        if k == 1:
            raise RuntimeError("disk full")
        return real(setup, k, **kw)

    monkeypatch.setattr(seq, "render_frame", failing)
    result = runner.invoke(main, ["render", "sequence", scene, "-o", str(out), "--frames", "3", "--workers", "1"])
    assert result.exit_code == 1 and "internal error: RuntimeError" in result.stderr and "disk full" in result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml", "seq"]  # no temporary folder left
    assert _listing(out) == before  # the previous folder is untouched
    monkeypatch.setattr(seq, "render_frame", real)
    _json(runner.invoke(main, ["render", "sequence", scene, "-o", str(out), "--frames", "1", "--json"]))
    assert sorted(p.name for p in (out / "cam0").iterdir()) == ["000000.png"]


@pytest.mark.parametrize("cmd", ["sequence", "calibration"])
def test_summary_logged_at_info(runner, tmp_path, model_file, cmd):
    scene = _scene(tmp_path, model_file, calibration={"views": 1})
    args = ["--frames", "1"] if cmd == "sequence" else ["--views", "1"]
    result = runner.invoke(main, ["render", cmd, scene, "-o", str(tmp_path / "out"), "--workers", "1", *args])
    assert result.exit_code == 0, result.output
    assert result.stdout == ""
    assert "INFO heartcv.cli.render: wrote " in result.stderr and "WARNING" not in result.stderr
    quiet = runner.invoke(main, ["-q", "render", cmd, scene, "-o", str(tmp_path / "out"), "--workers", "1", *args])
    assert quiet.exit_code == 0 and "wrote" not in quiet.stderr


@pytest.mark.parametrize("args, message", [
    (["sequence", "--frames", "0"], "0 is not in the range 1<=x<=1000000"),
    (["sequence", "--frames", "1000001"], "1000001 is not in the range 1<=x<=1000000"),
    (["sequence", "--stiffness-cycle", "nan"], "'nan': a finite number expected"),
    (["sequence", "--stiffness-cycle", "inf"], "'inf': a finite number expected"),
    (["sequence", "--stiffness-cycle", "21"], "21 is not in the range [0, 20]"),
    (["sequence", "--workers", "0"], "0 is not in the range 1<=x<=1024"),
    (["calibration", "--workers", "1025"], "1025 is not in the range 1<=x<=1024"),
    (["calibration", "--views", "1000001"], "1000001 is not in the range 1<=x<=1000000"),
    (["calibration", "--seed", "-1"], "-1 is not in the range 0<=x<=9223372036854775807"),
])
def test_out_of_range_options_exit_2(runner, tmp_path, model_file, args, message):
    scene = _scene(tmp_path, model_file)
    result = runner.invoke(main, ["render", args[0], scene, "-o", str(tmp_path / "out"), *args[1:]])
    assert result.exit_code == 2, result.output
    assert message in result.stderr and not (tmp_path / "out").exists()


@pytest.mark.parametrize("name", ["phantom", "myocardium"])
def test_sample_scenes_are_valid(name):
    """The shipped scenes validate, their model and target files load and their phantom builds."""
    from heartcv.io import read_scene, read_target, scene_file_path
    from heartcv.render.phantom import build_phantom
    from heartcv.tracker.io import read_model

    path = SAMPLES / name / "scene.yaml"
    scene = read_scene(path)
    cfg = read_model(scene_file_path(path, scene.motion.model))
    assert cfg.geometry.grid == (31, 21, 4) and cfg.reduction is not None  # a fine truth mesh
    target = read_target(scene_file_path(path, scene.calibration.target))
    assert target.type == "charuco"
    ph = build_phantom(cfg.geometry, scene.phantom)
    assert ph.trimesh().is_watertight
    assert scene.motion.stiffness_amplitude > 0
    if name == "phantom":  # the coarser estimator models beside the scene have the same patch, fewer nodes
        for f in ("model.yaml", "model_paper.yaml"):
            coarse = read_model(path.parent / f)
            assert replace(coarse.geometry, grid=cfg.geometry.grid) == cfg.geometry
            assert all(a < b for a, b in zip(coarse.geometry.grid, cfg.geometry.grid))
