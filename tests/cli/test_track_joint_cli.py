"""CLI: heartcv track --estimator ge|ukf|ekf (JSON keys, artifacts, bad input, divergence)."""

import json
import os

from click.testing import CliRunner
import numpy as np
import pytest
import yaml

from heartcv.cli.main import main
from heartcv.tracker.io import read_estimates, read_measurements, read_model, write_measurements
from heartcv.tracker.joint import run_joint
from heartcv.tracker.measurements import MeasurementSet
from heartcv.tracker.model import build_model
from heartcv.tracker.params import NAMES
from tests.conftest import SAMPLES

PAPER = str(SAMPLES / "paper_patch.yaml")


@pytest.fixture(scope="module")
def meas_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("track")
    path = str(d / "m.npz")
    res = CliRunner().invoke(main, ["model", "simulate", PAPER, "--duration", "1", "--seed", "2", "-o", path])
    assert res.exit_code == 0, res.output
    return path


def _run(args):
    return CliRunner().invoke(main, args)


@pytest.mark.parametrize("name", ["ge", "ukf", "ekf"])
def test_joint_track_json_and_file(tmp_path, meas_file, name):
    out = str(tmp_path / f"{name}.npz")
    res = _run(["track", meas_file, "--model", PAPER, "--estimator", name, "-o", out, "--json"])
    assert res.exit_code == 0, res.output
    s = json.loads(res.stdout)
    e = read_estimates(out)
    assert e.complete and e.estimator == name and s["steps"] == 31
    assert s["estimated"] == ["E", "nu"]
    # theta_final / theta_std_final are the file's last row, in physical units, keyed by name
    assert s["theta_final"] == pytest.approx(dict(zip(NAMES, e.theta[-1], strict=True)), rel=1e-12)
    assert s["theta_std_final"] == pytest.approx(dict(zip(NAMES, e.theta_std[-1], strict=True)), rel=1e-12)
    assert s["theta_std_final"]["rho"] == 0 and s["theta_std_final"]["E"] > 0
    assert s["truncation_events"] == int(e.truncation_events.sum())
    # the model file's prior is centred on the truth: E stays within a few per cent
    assert s["theta_final"]["E"] == pytest.approx(150e3, rel=0.05)
    assert e.phi_mean.shape == (31, 2) and e.phi_cov.shape == (31, 2, 2)
    # same as the library call (the CLI adapts the noise levels by default; exact references: fixed)
    from heartcv.tracker.adaptive import AdaptationOptions

    assert s["references"] == "fixed" and s["adaptation"]["window_s"] == 0.03
    lib = run_joint(build_model(read_model(PAPER)), read_measurements(meas_file), name,
                    adaptation=AdaptationOptions())
    np.testing.assert_allclose(e.theta, lib.theta, rtol=1e-12)
    assert s["adaptation"]["measurement_scale"] and not s["adaptation"]["random_walk"]
    walk = _run(["track", meas_file, "--model", PAPER, "--estimator", name, "-o", str(tmp_path / "w.npz"),
                 "--adapt-random-walk", "--json"])
    assert walk.exit_code == 0 and json.loads(walk.stdout)["adaptation"]["random_walk"]
    plain = _run(["track", meas_file, "--model", PAPER, "--estimator", name, "-o", str(tmp_path / "p.npz"),
                  "--no-adapt", "--json"])
    assert plain.exit_code == 0 and json.loads(plain.stdout)["adaptation"] is None
    np.testing.assert_allclose(read_estimates(str(tmp_path / "p.npz")).theta,
                               run_joint(build_model(read_model(PAPER)), read_measurements(meas_file), name).theta,
                               rtol=1e-12)


@pytest.mark.parametrize("nodes, message", [
    ("4", "Invalid value for '--nodes': D must be an odd integer >= 3 (shared centre node), got 4"),
    ("1", "Invalid value for '--nodes': 1 is not in the range 3<=x<=51."),
    ("2", "Invalid value for '--nodes': 2 is not in the range 3<=x<=51."),
    ("53", "Invalid value for '--nodes': 53 is not in the range 3<=x<=51."),
])
def test_even_small_or_large_node_count_exits_2(tmp_path, meas_file, nodes, message):
    out = tmp_path / "x.npz"
    res = _run(["track", meas_file, "--model", PAPER, "--estimator", "ge", "--nodes", nodes, "-o", str(out)])
    assert res.exit_code == 2 and message in res.output
    assert not out.exists()


def test_nodes_in_the_model_file_must_be_odd(tmp_path, meas_file):
    d = yaml.safe_load(open(PAPER))
    d["estimation"]["ge"] = {"nodes": 6}
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(d))
    res = _run(["track", meas_file, "--model", str(bad), "--estimator", "ge", "-o", str(tmp_path / "x.npz")])
    assert res.exit_code == 2 and "estimation.ge.nodes" in res.output


def test_prior_outside_its_bounds_exits_2(tmp_path, meas_file):
    d = yaml.safe_load(open(PAPER))
    d["estimation"]["bounds"]["E"] = [1000.0, 100000.0]  # the model's E = 150 kPa is the prior mean
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(d))
    res = _run(["track", meas_file, "--model", str(bad), "--estimator", "ge", "-o", str(tmp_path / "x.npz")])
    assert res.exit_code == 2 and "parameters.E" in res.output and "bounds" in res.output


def _with_cov(meas, cov):
    return MeasurementSet(meas.times, meas.point_ids, meas.positions, cov, meas.reference, meas.inputs,
                          meas.input_names, meas.input_units)


@pytest.mark.parametrize("kind, message", [("asym", "not symmetric"), ("singular", "singular")])
def test_bad_covariance_in_the_file_exits_2_naming_frame_and_point(tmp_path, meas_file, kind, message):
    meas = read_measurements(meas_file)
    cov = meas.covariances.copy()
    if kind == "asym":
        cov[3, 5, 0, 1] += 1e-9
    else:
        cov[3, 5] = np.diag([1e-8, 1e-8, 0.0])
    # bypass the writer's validation: write the arrays as a foreign tool would
    path = tmp_path / "bad.npz"
    with np.load(meas_file) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["covariances"] = cov
    np.savez(path, **arrays)
    out = tmp_path / "x.npz"
    res = _run(["track", str(path), "--model", PAPER, "--estimator", "ge", "-o", str(out)])
    assert res.exit_code == 2, res.output
    assert message in res.output and "frame 3, point 5" in res.output
    assert not out.exists()


def test_diverging_run_exits_1_and_writes_only_a_partial_file(tmp_path, meas_file):
    meas = read_measurements(meas_file)
    pos = meas.positions.copy()
    pos[5:] += 900.0  # finite, within the readers' plausibility bound (1 km), absurd from frame 5 on
    bad = tmp_path / "absurd.npz"
    write_measurements(bad, MeasurementSet(meas.times, meas.point_ids, pos, meas.covariances, meas.reference,
                                           meas.inputs, meas.input_names, meas.input_units))
    out = tmp_path / "ge.npz"
    res = _run(["track", str(bad), "--model", PAPER, "--estimator", "ge", "-o", str(out)])
    assert res.exit_code == 1
    assert f"diverged on {bad} at step 5" in res.output and "no estimate file written" in res.output
    assert not out.exists()
    part = read_estimates(tmp_path / "ge.partial.npz")
    assert part.completed_steps == 5 and not part.complete and part.meta["partial"] is True
    assert sorted(os.listdir(tmp_path)) == ["absurd.npz", "ge.partial.npz"]


def test_option_scope_and_single_frame_log(tmp_path, meas_file):
    out = str(tmp_path / "x.npz")
    res = _run(["track", meas_file, "--model", PAPER, "--estimator", "ukf", "--nodes", "5", "-o", out])
    assert res.exit_code == 2 and "--nodes applies to the GE only" in res.output
    res = _run(["track", meas_file, "--model", PAPER, "--estimator", "kf", "--truncation", "sequential", "-o", out])
    assert res.exit_code == 2 and "joint estimators" in res.output
    res = _run(["track", meas_file, "--model", PAPER, "--estimator", "ekf", "--truncation", "sequential", "-o", out,
                "--json"])
    assert res.exit_code == 0, res.output
    assert read_estimates(out).meta["options"]["baseline_truncation"] == "sequential"
    # one frame: no prediction after frame 0, the log line says so instead of failing
    meas = read_measurements(meas_file)
    one = tmp_path / "one.npz"
    write_measurements(one, MeasurementSet(meas.times[:1], meas.point_ids, meas.positions[:1], meas.covariances[:1],
                                           meas.reference, meas.inputs[:1], meas.input_names, meas.input_units))
    res = _run(["track", str(one), "--model", PAPER, "--estimator", "ge", "-o", str(tmp_path / "one_est.npz")])
    assert res.exit_code == 0, res.output
    assert "n/a" in res.output


def test_parameter_overdispersion_option(tmp_path, meas_file):
    """--parameter-overdispersion: 'auto' by default (never adjusting on the simulated paper patch, whose model
    holds), a fixed factor widens the parameters' band, and bad values or the KF exit 2."""
    auto = _run(["track", meas_file, "--model", PAPER, "--estimator", "ge", "-o", str(tmp_path / "a.npz"), "--json"])
    assert auto.exit_code == 0, auto.output
    od = json.loads(auto.stdout)["parameter_overdispersion"]
    assert od["mode"] == "estimated" and od["frames_adjusted"] == 0 and od["kappa_final"] == 1.0
    assert read_estimates(str(tmp_path / "a.npz")).meta["parameter_overdispersion"] == od
    fixed = _run(["track", meas_file, "--model", PAPER, "--estimator", "ge", "-o", str(tmp_path / "f.npz"),
                  "--parameter-overdispersion", "9", "--json"])
    assert fixed.exit_code == 0, fixed.output
    s = json.loads(fixed.stdout)
    assert s["parameter_overdispersion"]["mode"] == "fixed" and s["parameter_overdispersion"]["kappa_final"] == 9
    assert s["theta_std_final"]["E"] > json.loads(auto.stdout)["theta_std_final"]["E"]
    kf = _run(["track", meas_file, "--model", PAPER, "--estimator", "kf", "-o", str(tmp_path / "k.npz"), "--json"])
    assert kf.exit_code == 0 and json.loads(kf.stdout)["parameter_overdispersion"] is None
    # the report carries it per run and says where it tempered
    rep = _run(["report", str(tmp_path / "a.npz"), str(tmp_path / "f.npz"), str(tmp_path / "k.npz"),
                "-o", str(tmp_path / "rep")])
    assert rep.exit_code == 0, rep.output
    runs = json.loads((tmp_path / "rep" / "metrics.json").read_text())["estimators"]
    assert [runs[k]["parameter_overdispersion"] for k in ("ge:a", "ge:f", "kf")] == \
        [od, s["parameter_overdispersion"], None]
    summary = (tmp_path / "rep" / "summary.md").read_text()
    assert "Parameters' update of ge:f tempered by their over-dispersion 9 " in summary
    assert "update of ge:a" not in summary
    for args, message in ((["--estimator", "kf", "--parameter-overdispersion", "2"], "ge, ukf, ekf"),
                          (["--estimator", "ge", "--parameter-overdispersion", "0.5"], "factor in [1, 1e6]"),
                          (["--estimator", "ge", "--parameter-overdispersion", "nan"], "factor in [1, 1e6]"),
                          (["--estimator", "ukf", "--parameter-overdispersion", "some"], "'auto' or a factor")):
        res = _run(["track", meas_file, "--model", PAPER, "-o", str(tmp_path / "x.npz"), *args])
        assert res.exit_code == 2 and message in res.output, res.output
        assert not os.path.exists(tmp_path / "x.npz")
