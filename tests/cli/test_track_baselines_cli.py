"""CLI: heartcv track --estimator hold|constvel|harmonic (issue 16 baselines): same outputs as the estimators,
same points, bad usage."""

import dataclasses
import json

from click.testing import CliRunner
import numpy as np
import pytest

from heartcv.cli.main import main
from heartcv.tracker.baselines import run_baseline
from heartcv.tracker.io import read_estimates, read_measurements, write_measurements
from tests.conftest import SAMPLES

PAPER = str(SAMPLES / "paper_patch.yaml")


@pytest.fixture(scope="module")
def meas_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("baselines")
    path = str(d / "m.npz")
    res = CliRunner().invoke(main, ["model", "simulate", PAPER, "--duration", "4", "--seed", "5", "-o", path])
    assert res.exit_code == 0, res.output
    return path


@pytest.mark.parametrize("name", ["hold", "constvel", "harmonic"])
def test_baseline_track_file_and_json(tmp_path, meas_file, name):
    out = str(tmp_path / f"{name}.npz")
    res = CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, "--estimator", name, "-o", out, "--json"])
    assert res.exit_code == 0, res.output
    s = json.loads(res.stdout)
    e = read_estimates(out)
    assert e.estimator == name and e.complete and s["steps"] == e.times.size
    assert s["theta_final"]["E"] is None and s["nis_mean"] is None and s["estimated"] == []
    assert s["log_likelihood_per_point"] is None and e.log_likelihood is None
    assert s["references"] is None      # (--references is refused for a baseline; it said "fixed")
    lib = run_baseline(name, read_measurements(meas_file))
    np.testing.assert_allclose(e.predictions, lib.predictions, rtol=1e-12, equal_nan=True)
    assert s["prediction_rmse_m"] == pytest.approx(lib.prediction_rmse(), rel=1e-12)
    if name == "harmonic":
        assert s["heart_rate_hz"] == pytest.approx(1.0, rel=0.01)             # paper_patch: 60 bpm
    # the report takes them beside the model-based estimators
    kf = str(tmp_path / "kf.npz")
    assert CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, "-o", kf]).exit_code == 0
    rep = CliRunner().invoke(main, ["report", kf, out, "-o", str(tmp_path / "rep"), "--json"])
    assert rep.exit_code == 0, rep.output
    assert json.loads(rep.stdout)["estimators"][name]["prediction_error_mean_m"] > 0


def test_given_heart_rate_and_bad_usage(tmp_path, meas_file):
    out = str(tmp_path / "h.npz")
    res = CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, "--estimator", "harmonic",
                                    "--heart-rate-hz", "1.0", "-o", out, "--json"])
    assert res.exit_code == 0 and json.loads(res.stdout)["heart_rate_hz"] == 1.0
    for args, msg in ((["--estimator", "kf", "--heart-rate-hz", "1.2"], "--heart-rate-hz applies"),
                      (["--estimator", "hold", "--joseph"], "--joseph applies"),
                      (["--estimator", "constvel", "--truncation", "none"], "--truncation applies"),
                      (["--estimator", "hold", "--nodes", "5"], "--nodes applies")):
        r = CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, *args, "-o", str(tmp_path / "x.npz")])
        assert r.exit_code == 2 and msg in r.output, r.output


def test_harmonic_without_periodic_motion_exits_1(tmp_path, meas_file):
    m = read_measurements(meas_file)
    rng = np.random.default_rng(0)
    flat = dataclasses.replace(m, positions=m.reference[None] + 1e-4 * rng.normal(size=m.positions.shape))
    path = tmp_path / "flat.npz"
    write_measurements(path, flat, m.meta)
    r = CliRunner().invoke(main, ["track", str(path), "--model", PAPER, "--estimator", "harmonic",
                                  "-o", str(tmp_path / "h.npz")])
    assert r.exit_code == 1 and "no heart rate" in r.output, r.output
    assert not (tmp_path / "h.npz").exists()


def test_holdout_selects_the_same_tracks_for_every_estimator(tmp_path, meas_file):
    ids = {}
    for name in ("kf", "ge", "hold"):
        out = str(tmp_path / f"{name}.npz")
        r = CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, "--estimator", name, "--holdout", "0.3",
                                      "--seed", "7", "-o", out, "--json"])
        assert r.exit_code == 0, r.output
        assert json.loads(r.stdout)["heldout_points"] == 4                     # round(0.3 * 14)
        e = read_estimates(out)
        ids[name] = e.meta["heldout_points"]
        assert e.meta["holdout"] == 0.3 and e.meta["seed"] == 7
    assert ids["kf"] == ids["ge"] == ids["hold"]
    rep = CliRunner().invoke(main, ["report", *(str(tmp_path / f"{n}.npz") for n in ("ge", "kf", "hold")),
                                    "-o", str(tmp_path / "rep"), "--json"])
    est = json.loads(rep.stdout)["estimators"]
    assert all(est[n]["heldout_points"] == 4 and est[n]["heldout_prediction_error_mean_m"] > 0 for n in est)
    for bad in ("1.0", "-0.1"):
        r = CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, "--holdout", bad, "-o",
                                      str(tmp_path / "x.npz")])
        assert r.exit_code == 2 and "--holdout" in r.output
    r = CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, "--holdout", "0.01", "-o",
                                  str(tmp_path / "x.npz")])
    assert r.exit_code == 2 and "leave some in and some out" in r.output


def test_track_offsets_option(tmp_path, meas_file):
    """--track-offsets: a given walk equals the library run with it; 'auto' records the maximum-likelihood choice
    in the file's meta and runs with it; bad values and baselines exit 2."""
    from heartcv.cli.options import load_model
    from heartcv.tracker.tracking import run_kalman

    out = str(tmp_path / "kf.npz")
    res = CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, "--estimator", "kf", "--no-adapt",
                                    "--track-offsets", "2e-5", "-o", out])
    assert res.exit_code == 0, res.output
    e = read_estimates(out)
    lib = run_kalman(load_model(PAPER), read_measurements(meas_file), drift=2e-5)
    np.testing.assert_allclose(e.predictions, lib.predictions, rtol=1e-10, equal_nan=True)
    assert e.meta["track_offsets"]["std_per_frame_m"] == 2e-5 and e.meta["track_offsets"]["final_norm_max_m"] > 0
    auto = str(tmp_path / "auto.npz")
    res = CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, "--estimator", "kf", "--track-offsets",
                                    "auto", "-o", auto, "--json"])
    assert res.exit_code == 0, res.output
    sel = read_estimates(auto).meta["track_offsets"]
    assert json.loads(res.stdout)["track_offsets_std_per_frame_m"] == sel["std_per_frame_m"]
    assert sel["source"].startswith("maximum likelihood") and sel["frames"] == 100
    assert sel["log_likelihoods"][sel["candidates_m"].index(sel["std_per_frame_m"])] == max(sel["log_likelihoods"])
    for bad in ("-1e-5", "abc", "inf"):
        res = CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, "--track-offsets", bad,
                                        "-o", str(tmp_path / "x.npz")])
        assert res.exit_code == 2 and "--track-offsets" in res.output, res.output
    res = CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, "--estimator", "hold", "--track-offsets",
                                    "auto", "-o", str(tmp_path / "y.npz")])
    assert res.exit_code == 2 and "model-based estimators" in res.output


def test_track_offsets_default_is_auto_for_the_model_and_absent_for_the_baselines(tmp_path, meas_file):
    """Without --track-offsets a model-based run selects the offsets by maximum likelihood (the same run as
    'auto', to the bit), 'none' runs without them (no meta.track_offsets, the library run without drift), and a
    baseline runs without them (the option is refused only when given)."""
    from heartcv.cli.options import load_model
    from heartcv.tracker.tracking import run_kalman

    runs = {}
    for name, extra in (("default", []), ("auto", ["--track-offsets", "auto"]), ("none", ["--track-offsets", "none"])):
        runs[name] = str(tmp_path / f"{name}.npz")
        res = CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, "--estimator", "kf", "--no-adapt",
                                        "-o", runs[name]] + extra)
        assert res.exit_code == 0, res.output
    d, a, n = (read_estimates(runs[k]) for k in ("default", "auto", "none"))
    assert d.meta["track_offsets"]["source"] == "maximum likelihood (--track-offsets auto)"
    assert d.meta["track_offsets"]["std_per_frame_m"] == a.meta["track_offsets"]["std_per_frame_m"]
    np.testing.assert_array_equal(d.predictions, a.predictions)
    assert "track_offsets" not in n.meta
    lib = run_kalman(load_model(PAPER), read_measurements(meas_file))
    np.testing.assert_allclose(n.predictions, lib.predictions, rtol=1e-10, equal_nan=True)
    res = CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, "--estimator", "hold",
                                    "-o", str(tmp_path / "hold.npz")])
    assert res.exit_code == 0, res.output
    assert "track_offsets" not in read_estimates(str(tmp_path / "hold.npz")).meta


@pytest.mark.parametrize("estimator, args, option", [
    ("kf", ["--adapt-random-walk"], "--adapt-random-walk applies to the estimators of parameters"),
    ("kf", ["--hold-heart-rate"], "--sample-heart-rate/--hold-heart-rate applies to the GE only"),
    ("ukf", ["--sample-heart-rate"], "--sample-heart-rate/--hold-heart-rate applies to the GE only"),
    ("hold", ["--references", "estimate"], "--references applies to the model-based estimators"),
    ("constvel", ["--rigid-dynamics", "fit"], "--rigid-dynamics applies to the model-based estimators"),
    ("harmonic", ["--no-adapt"], "--adapt/--no-adapt applies to the model-based estimators"),
    ("hold", ["--adapt-window", "2"], "--adapt-window applies to the model-based estimators"),
    ("ge", ["--hold-heart-rate"], "holds no estimated input"),         # a recorded pressure: no rate to sample
    ("kf", ["--rigid-dynamics", "refit"], "holds no estimated input"),
])
def test_options_that_do_not_apply_exit_2(tmp_path, meas_file, estimator, args, option):
    """Options accepted and ignored before (a KF's --adapt-random-walk even reported as used): exit 2 naming the
    option, nothing written; the same options where they apply run."""
    params = tmp_path / "p.yaml"
    if "holds no estimated input" in option:
        r = CliRunner().invoke(main, ["fit", meas_file, "--model", PAPER, "-o", str(params), "--frames", "20"])
        assert r.exit_code == 0, r.output
        args = args + ["--params", str(params)]
    out = tmp_path / "e.npz"
    r = CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, "--estimator", estimator, *args,
                                  "-o", str(out)])
    assert r.exit_code == 2 and option in r.output.replace("\n", " "), r.output
    assert not out.exists()
    if option.startswith("--adapt-random-walk"):
        r = CliRunner().invoke(main, ["track", meas_file, "--model", PAPER, "--estimator", "ekf", *args,
                                      "--track-offsets", "none", "-o", str(out), "--json"])
        assert r.exit_code == 0 and json.loads(r.stdout)["adaptation"]["random_walk"] is True, r.output
