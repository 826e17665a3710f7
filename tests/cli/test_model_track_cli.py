"""CLI: heartcv model info / model simulate / track (CliRunner, exit codes, artifacts read back)."""

import json
import os
from pathlib import Path

from click.testing import CliRunner
import numpy as np
import pytest
import yaml

from heartcv.cli.main import main
from heartcv.tracker.io import read_estimates, read_measurements, read_truth
from tests.conftest import SAMPLES

PAPER = str(SAMPLES / "paper_patch.yaml")


@pytest.fixture
def runner():
    return CliRunner()


def _json(result):
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def test_model_info_paper(runner):
    out = _json(runner.invoke(main, ["model", "info", PAPER, "--json"]))
    assert (out["free_nodes"], out["state_dim"], out["observed_rows"]) == (28, 168, 42)
    assert out["nodes"] == 72 and len(out["frequencies_hz"]) == 5
    assert out["frequencies_hz"] == sorted(out["frequencies_hz"])


def test_model_info_myocardium_is_reduced(runner):
    out = _json(runner.invoke(main, ["model", "info", str(SAMPLES / "myocardium.yaml"), "--json"]))
    assert out["reduced"] and out["free_nodes"] == 2204 and out["state_dim"] == 2 * out["basis_size"]
    assert out["state_dim"] <= 30


def test_simulate_then_track(runner, tmp_path):
    meas, truth, est = (str(tmp_path / n) for n in ("m.npz", "t.npz", "e.npz"))
    sim = _json(runner.invoke(main, ["model", "simulate", PAPER, "--duration", "2", "--seed", "4", "-o", meas,
                                     "--truth", truth, "--json"]))
    assert sim["frames"] == 61 and sim["points"] == 14
    m = read_measurements(meas)
    t, meta = read_truth(truth)
    assert m.positions.shape == (61, 14, 3) and t["positions"].shape == (61, 14, 3)
    assert meta["seed"] == 4 and meta["format"] == "heartcv.truth"
    # noise level: measurements minus truth have the configured std
    assert np.std(m.positions - t["positions"]) == pytest.approx(1e-4, rel=0.1)
    out = _json(runner.invoke(main, ["track", meas, "--model", PAPER, "--estimator", "kf", "-o", est, "--json"]))
    assert out["steps"] == 61
    for key in ("nis_mean", "prediction_rmse_m", "step_ms_median"):
        assert np.isfinite(out[key])
    e = read_estimates(est)
    assert e.complete and e.estimator == "kf"
    assert e.prediction_rmse() == pytest.approx(out["prediction_rmse_m"])
    # the predictive log-likelihood per measured point: 14 points in each of frames 1..60
    assert out["log_likelihood_per_point"] == pytest.approx(e.log_likelihood[1:].sum() / (60 * 14), rel=1e-12)
    # same seed -> identical file contents
    meas2 = str(tmp_path / "m2.npz")
    _json(runner.invoke(main, ["model", "simulate", PAPER, "--duration", "2", "--seed", "4", "-o", meas2, "--json"]))
    np.testing.assert_array_equal(read_measurements(meas2).positions, m.positions)


def test_simulate_with_stiffness_cycle_and_missing(runner, tmp_path):
    meas, truth = str(tmp_path / "m.npz"), str(tmp_path / "t.npz")
    _json(runner.invoke(main, ["model", "simulate", PAPER, "--duration", "1", "--stiffness-cycle", "1.0",
                               "--missing", "0.2", "-o", meas, "--truth", truth, "--json"]))
    t, _ = read_truth(truth)
    E = t["theta"][:, 3]
    assert E.min() == pytest.approx(150e3) and E.max() > 1.8 * 150e3
    # E(t) = E (1 + a h(t)), h the normalised active-tension shape at the model's 60 bpm (tracker.inputs)
    from heartcv.tracker.inputs import active_tension

    h = active_tension(t["times"], heart_rate_bpm=60.0, t_max=1.0)
    np.testing.assert_allclose(E, 150e3 * (1.0 + 1.0 * h), rtol=1e-15, atol=0)
    assert (t["theta"][:, [0, 1, 2, 4]] == [1050.0, 2.39, 0.003, 0.45]).all()
    assert np.isnan(read_measurements(meas).positions).any()
    est = str(tmp_path / "e.npz")
    out = _json(runner.invoke(main, ["track", meas, "--model", PAPER, "-o", est, "--json"]))
    assert out["steps"] == 31


def _write_model(tmp_path, edit):
    d = yaml.safe_load(Path(PAPER).read_text())
    edit(d)
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(d))
    return str(p)


@pytest.mark.parametrize("edit,field", [
    (lambda d: d["parameters"].update(nu=0.5), "parameters.nu"),
    (lambda d: d["geometry"].update(thickness=-0.01), "geometry.thickness"),
    (lambda d: d.update(colour="red"), "colour"),
    (lambda d: d["parameters"].pop("E") and d["parameters"].update(Young=1.0), "parameters.Young"),
])
def test_bad_model_file_exits_2_naming_the_field(runner, tmp_path, edit, field):
    bad = _write_model(tmp_path, edit)
    out = tmp_path / "m.npz"
    for args in (["model", "info", bad], ["model", "simulate", bad, "--duration", "1", "-o", str(out)]):
        res = runner.invoke(main, args)
        assert res.exit_code == 2
        assert field in res.stderr
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["bad.yaml"]


def test_truncated_measurement_file_exits_2_and_writes_nothing(runner, tmp_path):
    meas = tmp_path / "m.npz"
    _json(runner.invoke(main, ["model", "simulate", PAPER, "--duration", "1", "-o", str(meas), "--json"]))
    data = meas.read_bytes()
    meas.write_bytes(data[: len(data) // 2])
    before = meas.read_bytes()
    est = tmp_path / "e.npz"
    res = runner.invoke(main, ["track", str(meas), "--model", PAPER, "-o", str(est)])
    assert res.exit_code == 2
    assert "m.npz" in res.stderr and "truncated or corrupt" in res.stderr
    assert not est.exists() and meas.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["m.npz"]


def test_measurements_off_the_patch_exit_2(runner, tmp_path):
    from heartcv.tracker.io import write_measurements
    from heartcv.tracker.measurements import MeasurementSet

    meas = tmp_path / "m.npz"
    _json(runner.invoke(main, ["model", "simulate", PAPER, "--duration", "1", "-o", str(meas), "--json"]))
    m = read_measurements(meas)
    mm = MeasurementSet(m.times, m.point_ids, m.positions * 1000, m.covariances * 1e6, m.reference * 1000,
                        m.inputs, m.input_names, m.input_units)  # millimetres by mistake
    write_measurements(meas, mm)
    res = runner.invoke(main, ["track", str(meas), "--model", PAPER, "-o", str(tmp_path / "e.npz")])
    assert res.exit_code == 2 and "none of the" in res.stderr
    assert not (tmp_path / "e.npz").exists()


def test_missing_input_column_exits_2(runner, tmp_path):
    from heartcv.tracker.io import write_measurements
    from heartcv.tracker.measurements import MeasurementSet

    meas = tmp_path / "m.npz"
    _json(runner.invoke(main, ["model", "simulate", PAPER, "--duration", "1", "-o", str(meas), "--json"]))
    m = read_measurements(meas)
    write_measurements(meas, MeasurementSet(m.times, m.point_ids, m.positions, m.covariances, m.reference,
                                            m.inputs[:, 1:], m.input_names[1:], m.input_units[1:]))
    res = runner.invoke(main, ["track", str(meas), "--model", PAPER, "-o", str(tmp_path / "e.npz")])
    assert res.exit_code == 2 and "pressure" in res.stderr


def test_times_and_units_a_hand_built_file_gets_wrong_are_named(runner, tmp_path):
    """A hand-built measurement file: times in single precision (evenly spaced, but rounded past the estimators'
    1e-6 tolerance) exit 2 naming `times` and float64 before any work; a pressure recorded in kPa exits 2 naming
    `meta.input_units` (it was read as pascals); times in milliseconds run, with a warning."""
    from dataclasses import replace

    from heartcv.tracker.io import write_measurements

    meas = tmp_path / "m.npz"
    _json(runner.invoke(main, ["model", "simulate", PAPER, "--duration", "2", "-o", str(meas), "--json"]))
    m = read_measurements(meas)
    t32 = (100.0 + m.times).astype(np.float32).astype(np.float64)       # a clock that does not start at 0
    assert np.abs(np.diff(t32) - np.median(np.diff(t32))).max() > 1e-6 * np.median(np.diff(t32))
    cases = {"t32": (replace(m, times=t32), "times: the estimators need a constant frame interval"),
             "kpa": (replace(m, inputs=m.inputs / 1e3), "meta.input_units: 'pressure' in 'kPa'")}
    for name, (bad, message) in cases.items():
        path = tmp_path / f"{name}.npz"
        write_measurements(path, bad)
        if name == "kpa":   # (a MeasurementSet refuses it: the file is edited as a person's script would write it)
            data = dict(np.load(path))
            meta = json.loads(data["meta_json"].tobytes())
            meta["input_units"][0] = "kPa"
            data["meta_json"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
            np.savez(path, **data)
        res = runner.invoke(main, ["-v", "track", str(path), "--model", PAPER, "-o", str(tmp_path / "e.npz")])
        assert res.exit_code == 2 and f"{path}: {message}" in res.stderr, res.output
        assert "KF runs" not in res.stderr and not (tmp_path / "e.npz").exists()
    res = runner.invoke(main, ["track", str(tmp_path / "t32.npz"), "--model", PAPER, "-o", str(tmp_path / "e.npz")])
    assert "float64 expected" in res.stderr.replace("\n", " ")
    write_measurements(tmp_path / "ms.npz", replace(m, times=1e3 * m.times))
    res = runner.invoke(main, ["track", str(tmp_path / "ms.npz"), "--model", PAPER, "--estimator", "kf",
                               "--track-offsets", "none", "-o", str(tmp_path / "e.npz")])
    assert "a frame interval of 33.3 s" in res.stderr and "milliseconds?" in res.stderr, res.output


def test_help_is_fast_and_lists_commands(runner):
    res = runner.invoke(main, ["--help"])
    assert res.exit_code == 0 and "model" in res.output and "track" in res.output


def test_stiffness_schedule_shapes(paper_model):
    """tracker.simulate.stiffness_schedule, the one E(t) of model simulate, the render scenes and the tests."""
    from heartcv.tracker.files import InputError
    from heartcv.tracker.inputs import active_tension
    from heartcv.tracker.simulate import input_signals, stiffness_schedule

    assert stiffness_schedule(paper_model, 0.0) is None
    base = paper_model.config.theta
    active = stiffness_schedule(paper_model, 0.5, "active", t_offset=0.2)
    th = active(0.5)
    assert th[3] == base[3] * (1.0 + 0.5 * float(active_tension(np.array([0.3]), 60.0, 1.0)[0]))
    assert (th[[0, 1, 2, 4]] == base[[0, 1, 2, 4]]).all()
    load = input_signals(paper_model).load
    p_max = load(np.linspace(0.0, 3.0, 3001))[:, 0].max()
    pressure = stiffness_schedule(paper_model, 2.0, "pressure")
    for t in (0.0, 0.31, 0.77):
        assert pressure(t)[3] == base[3] * (1.0 + 2.0 * max(float(load(np.array([t]))[0, 0]), 0.0) / p_max)
    with pytest.raises(InputError) as exc:
        stiffness_schedule(paper_model, 1.0, "pressure", load=lambda t: -np.ones((np.size(t), 1)))
    assert exc.value.field == "stiffness_cycle.shape" and "never positive" in exc.value.reason


def test_track_logs_progress_when_stderr_is_not_a_terminal(runner, tmp_path, monkeypatch):
    """A long stage in a Makefile's log (stderr not a terminal) reports its progress as INFO lines, at most every
    PROGRESS_LOG_S seconds (here 0: every frame), for the KF and the GE alike; -q silences them."""
    from heartcv.cli import options

    meas = str(tmp_path / "m.npz")
    _json(runner.invoke(main, ["model", "simulate", PAPER, "--duration", "1", "--seed", "4", "-o", meas, "--json"]))
    monkeypatch.setattr(options, "PROGRESS_LOG_S", 0.0)
    for estimator in ("kf", "ge"):
        res = runner.invoke(main, ["track", meas, "--model", PAPER, "--estimator", estimator,
                                   "-o", str(tmp_path / f"{estimator}.npz")])
        assert res.exit_code == 0, res.output
        lines = [ln for ln in res.stderr.splitlines() if ln.startswith(f"INFO heartcv.cli: {estimator}: ")]
        assert len(lines) == 31, res.stderr                       # 1 s at 30 Hz: 31 frames, one line each
        assert lines[0].startswith(f"INFO heartcv.cli: {estimator}: 1/31 (3 %), ")
        assert lines[-1].startswith(f"INFO heartcv.cli: {estimator}: 31/31 (100 %), ")
    res = runner.invoke(main, ["-q", "track", meas, "--model", PAPER, "--estimator", "kf",
                               "-o", str(tmp_path / "quiet.npz")])
    assert res.exit_code == 0 and "heartcv.cli: kf:" not in res.stderr
