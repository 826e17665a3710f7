"""CLI: heartcv fit and heartcv track --params (CliRunner, exit codes, artifacts read back)."""

from dataclasses import replace
import json
from pathlib import Path

from click.testing import CliRunner
import numpy as np
import pytest
import yaml

from heartcv.cli.main import main
from heartcv.tracker.io import read_estimates, read_measurements, read_parameters, write_measurements
from heartcv.tracker.measurements import MeasurementSet
from heartcv.tracker.params import NAMES
from tests.conftest import SAMPLES

PAPER = str(SAMPLES / "paper_patch.yaml")
SIMULATION = str(SAMPLES / "paper_simulation.yaml")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """`heartcv model simulate` files: paper_patch 1 s (E, nu) and paper_simulation 3 s (all five)."""
    d = tmp_path_factory.mktemp("fit")
    runner = CliRunner()
    out = {}
    for key, model, duration in (("patch", PAPER, "1"), ("sim", SIMULATION, "3")):
        path = str(d / f"{key}.npz")
        r = runner.invoke(main, ["model", "simulate", model, "--duration", duration, "--seed", "3", "-o", path])
        assert r.exit_code == 0, r.output
        out[key] = path
    out["dir"] = d
    return out


def _ok(result):
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def test_fit_json_file_and_recovery(files, tmp_path):
    """All five parameters of paper_simulation from a `model simulate` file: |z| < 3.5 each (measured: all
    within 0.82 sigma for seed 3); the JSON summary and the file agree."""
    out = tmp_path / "p.yaml"
    s = _ok(CliRunner().invoke(main, ["fit", files["sim"], "--model", SIMULATION, "-o", str(out), "--json"]))
    for key in ("theta", "theta_std", "cost", "converged", "frames", "points", "starts", "iterations",
                "reduced_chi2", "estimated", "fixed", "covariance_scaled", "dof", "message", "at_bound"):
        assert key in s, key
    assert s["converged"] and s["frames"] == 91 and s["points"] == 14 and s["starts"] == 3
    assert s["estimated"] == list(NAMES) and s["fixed"] == []
    p = read_parameters(out)
    assert p.theta.tolist() == [s["theta"][n] for n in NAMES] and p.cost == s["cost"]
    truth = np.array([1050.0, 2.0, 0.003, 150.0, 0.45])
    z = (p.theta - truth) / p.theta_std
    assert np.abs(z).max() < 3.5, z
    assert abs(s["reduced_chi2"] - 1) < 5 * np.sqrt(2 / s["dof"])
    assert p.meta["producer"] == "heartcv fit" and set(p.meta["inputs_hash"]) == {"measurements", "model"}
    assert p.meta["seed"] == 0 and p.registration is None


def test_fit_frames_and_seed(files, tmp_path):
    out = tmp_path / "p.yaml"
    s = _ok(CliRunner().invoke(main, ["fit", files["patch"], "--model", PAPER, "-o", str(out), "--frames", "20",
                                         "--starts", "2", "--seed", "5", "--json"]))
    assert s["frames"] == 20 and s["starts"] == 2 and s["estimated"] == ["E", "nu"]
    assert s["fixed"] == ["rho", "alpha1", "alpha2"] and s["theta_std"]["rho"] == 0.0
    assert read_parameters(out).meta["seed"] == 5


def test_fit_not_converged_exits_1_and_writes_nothing(files, tmp_path):
    out = tmp_path / "p.yaml"
    r = CliRunner().invoke(main, ["fit", files["patch"], "--model", PAPER, "-o", str(out), "--max-evaluations", "1"])
    assert r.exit_code == 1 and "did not converge" in r.output and "nothing written" in r.output
    assert not out.exists() and not list(tmp_path.iterdir())


def test_fit_bad_input_exits_2(files, tmp_path):
    runner = CliRunner()
    m = read_measurements(files["patch"])
    mm = tmp_path / "mm.npz"  # millimetres instead of metres
    write_measurements(mm, MeasurementSet(m.times, m.point_ids, m.positions * 1e3, m.covariances * 1e6,
                                          m.reference * 1e3, m.inputs, m.input_names, m.input_units))
    out = tmp_path / "p.yaml"
    r = runner.invoke(main, ["fit", str(mm), "--model", PAPER, "-o", str(out)])
    assert r.exit_code == 2 and "none of the 14 points lies on the model's patch" in r.output
    r = runner.invoke(main, ["fit", files["patch"], "--model", PAPER, "-o", str(tmp_path / "p.txt")])
    assert r.exit_code == 2 and ".yaml" in r.output
    r = runner.invoke(main, ["fit", str(tmp_path / "missing.npz"), "--model", PAPER, "-o", str(out)])
    assert r.exit_code == 2
    empty = tmp_path / "empty.yaml"
    empty.write_text((SAMPLES / "paper_patch.yaml").read_text().replace("estimate: [E, nu]", "estimate: []"))
    r = runner.invoke(main, ["fit", files["patch"], "--model", str(empty), "-o", str(out)])
    assert r.exit_code == 2 and "nothing to fit" in r.output
    assert not out.exists()


# -- track --params ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def params(files):
    out = files["dir"] / "patch_params.yaml"
    r = CliRunner().invoke(main, ["fit", files["patch"], "--model", PAPER, "-o", str(out)])
    assert r.exit_code == 0, r.output
    return out


def test_track_kf_with_params_uses_the_fitted_theta(files, params, tmp_path):
    est = tmp_path / "e.npz"
    s = _ok(CliRunner().invoke(main, ["track", files["patch"], "--model", PAPER, "--params", str(params),
                                      "--estimator", "kf", "-o", str(est), "--json"]))
    p = read_parameters(params)
    e = read_estimates(est)
    assert np.array_equal(e.theta, np.broadcast_to(p.theta, e.theta.shape))
    assert [s["theta_final"][n] for n in NAMES] == p.theta.tolist()
    assert e.meta["params"] == str(params) and "params" in e.meta["inputs_hash"]
    # without --params: the model file's theta, as before
    est2 = tmp_path / "e2.npz"
    _ok(CliRunner().invoke(main, ["track", files["patch"], "--model", PAPER, "-o", str(est2), "--json"]))
    assert read_estimates(est2).theta[0].tolist() == [1050.0, 2.39, 0.003, 150000.0, 0.45]


def test_track_ge_with_params_starts_at_the_fit(files, params, tmp_path):
    est = tmp_path / "e.npz"
    _ok(CliRunner().invoke(main, ["track", files["patch"], "--model", PAPER, "--params", str(params),
                                  "--estimator", "ge", "--nodes", "3", "-o", str(est), "--json"]))
    p = read_parameters(params)
    e = read_estimates(est)
    assert e.meta["theta0"] == p.theta.tolist()
    fit_sd = np.sqrt(np.diag(p.cov_phi))
    np.testing.assert_allclose(e.meta["prior_std_phi"], np.minimum(fit_sd, [0.5, 0.5]), rtol=1e-9)
    assert e.meta["prior_source"] == {"E": "fit", "nu": "fit"}


def test_track_params_errors(files, params, tmp_path):
    runner = CliRunner()
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: heartcv.model\n")
    r = runner.invoke(main, ["track", files["patch"], "--model", PAPER, "--params", str(bad), "-o",
                             str(tmp_path / "e.npz")])
    assert r.exit_code == 2 and "heartcv.parameters" in r.output
    # a fitted theta outside the tracking model's box
    out = tmp_path / "far.yaml"
    out.write_text("format: heartcv.parameters\nformat_version: 1\nestimated: [E]\n"
                   "theta: {rho: 1050, alpha1: 2.39, alpha2: 0.003, E: 5.0e+8, nu: 0.45}\n")
    r = runner.invoke(main, ["track", files["patch"], "--model", PAPER, "--params", str(out), "--estimator", "ge",
                             "-o", str(tmp_path / "e.npz")])
    assert r.exit_code == 2
    assert f"Error: {out}: theta.E: E = 5e+08 lies outside its bounds [" in r.stderr
    assert "of the model file (estimation.bounds.E)" in r.stderr
    assert not (tmp_path / "e.npz").exists()
    # a negative standard deviation or variance (before 2026-11-29 tracked as given)
    text = Path(params).read_text()
    for field, edit, message in [
            ("theta_std.nu", lambda d: d["theta_std"].update(nu=-0.03),
             "a standard deviation of at least 0 expected, got -0.03"),
            ("covariance.theta", lambda d: d["covariance"]["theta"][0].__setitem__(
                0, -abs(d["covariance"]["theta"][0][0])),
             "not positive semi-definite (a negative variance)"),
            ("frames", lambda d: d.update(frames="many"), "an integer expected, got 'many'")]:
        d = yaml.safe_load(text)
        edit(d)
        out.write_text(yaml.safe_dump(d))
        r = runner.invoke(main, ["track", files["patch"], "--model", PAPER, "--params", str(out), "-o",
                                 str(tmp_path / "e.npz")])
        assert r.exit_code == 2 and f"Error: {out}: {field}: {message}" in r.stderr, r.output
        assert r.stderr.count(str(out)) == 1          # the file named once (it was twice for some fields)


# -- rig-frame files: registration ---------------------------------------------------------------------------
RIG_FROM_PATCH = np.array([[0.0, -1.0, 0.0, 0.01], [1.0, 0.0, 0.0, -0.02], [0.0, 0.0, 1.0, 0.3], [0, 0, 0, 1]])


def _transform(T, m: MeasurementSet, keep, frame):
    R, t = T[:3, :3], T[:3, 3]
    return MeasurementSet(m.times, m.point_ids[keep], m.positions[:, keep] @ R.T + t,
                          R @ m.covariances[:, keep] @ R.T, m.reference[keep] @ R.T + t, m.inputs, m.input_names,
                          m.input_units, frame)


@pytest.fixture
def fake_registration(monkeypatch):
    """tracker.registration.register and to_patch_frame replaced by stand-ins that know the true transform (the
    stages call them through tracker.registration's register_rig_measurements and apply_stored_registration)."""
    from heartcv.tracker import registration
    from heartcv.tracker.registration import Registration

    calls = []
    state = {"converged": True}

    def register(meas, model, *, frames=10, initial=None, inputs=None):
        on = np.ones(meas.n_points, bool)
        on[0] = False  # pretend the first point lies off the patch
        calls.append(frames)
        return Registration(np.linalg.inv(RIG_FROM_PATCH), 2e-5, on, int(on.sum()), state["converged"], "ok")

    def to_patch_frame(meas, reg):
        calls.append("apply")
        return _transform(np.asarray(reg.patch_from_rig), meas, np.flatnonzero(reg.on_patch), "patch")

    monkeypatch.setattr(registration, "register", register)
    monkeypatch.setattr(registration, "to_patch_frame", to_patch_frame)
    return calls, state


def test_rig_frame_fit_registers_and_track_reuses_it(files, tmp_path, fake_registration):
    m = read_measurements(files["patch"])
    rig = tmp_path / "rig.npz"
    write_measurements(rig, _transform(RIG_FROM_PATCH, m, np.arange(m.n_points), "rig"))
    out = tmp_path / "p.yaml"
    s = _ok(CliRunner().invoke(main, ["fit", str(rig), "--model", PAPER, "-o", str(out), "--json"]))
    assert s["points"] == 13 and s["registration_rms_m"] == 2e-5
    p = read_parameters(out)
    np.testing.assert_array_equal(p.registration["patch_from_rig"], np.linalg.inv(RIG_FROM_PATCH))
    assert p.registration["points_on_patch"] == m.point_ids[1:].tolist()
    est = tmp_path / "e.npz"
    _ok(CliRunner().invoke(main, ["track", str(rig), "--model", PAPER, "--params", str(out), "-o", str(est),
                                  "--json"]))
    e = read_estimates(est)
    assert fake_registration[0] == [10, "apply", "apply"]
    assert e.point_ids.tolist() == m.point_ids[1:].tolist() and np.array_equal(e.theta[0], p.theta)
    assert e.meta["left_out_points"] == [int(m.point_ids[0])]      # the point the registration put off the patch
    # the same parameters on the patch-frame file: registration not applied, with a warning
    r = CliRunner().invoke(main, ["track", files["patch"], "--model", PAPER, "--params", str(out), "-o",
                                  str(tmp_path / "e2.npz")])
    assert r.exit_code == 0 and "not applied" in r.output


def test_rig_frame_registration_that_does_not_converge_exits_1(files, tmp_path, fake_registration):
    fake_registration[1]["converged"] = False
    m = read_measurements(files["patch"])
    rig = tmp_path / "rig.npz"
    write_measurements(rig, _transform(RIG_FROM_PATCH, m, np.arange(m.n_points), "rig"))
    out = tmp_path / "p.yaml"
    r = CliRunner().invoke(main, ["fit", str(rig), "--model", PAPER, "-o", str(out)])
    assert r.exit_code == 1
    assert f"registration onto the patch did not converge (ok); nothing written to {out}" in r.output
    assert "--patch observed fits the patch to the surface they see" in r.output.replace("\n", " ")
    assert fake_registration[0] == [10] and not out.exists()


def test_rig_frame_positions_in_millimetres_exit_2_before_any_placement(files, tmp_path, fake_registration):
    """The same rig-frame file scaled by 1000 (millimetres written as metres): its view spans tens of metres, no
    heart's surface does; exit 2 naming the file and `reference`, for a recorded and an estimated input alike
    (the latter had fitted a 31-m patch and written it), and the registration never ran."""
    m = read_measurements(files["patch"])
    rig = _transform(RIG_FROM_PATCH, m, np.arange(m.n_points), "rig")
    mm = tmp_path / "mm.npz"
    write_measurements(mm, replace(rig, positions=1e3 * rig.positions, reference=1e3 * rig.reference,
                                   covariances=1e6 * rig.covariances))
    for extra in ([], ["--input", "estimate"], ["--patch", "observed"]):
        out = tmp_path / "p.yaml"
        r = CliRunner().invoke(main, ["fit", str(mm), "--model", PAPER, "-o", str(out), *extra])
        assert r.exit_code == 2, (extra, r.output)
        assert f"{mm}: reference: the observed surface spans" in r.output and "millimetres" in r.output
        assert not out.exists() and fake_registration[0] == []
    # the file in metres passes the check (the same view, 1000 times smaller)
    from heartcv.tracker.patch_fit import check_view_scale, view_extent

    check_view_scale(rig)
    assert 1e-3 < view_extent(rig)[0] < 0.5 and np.isclose(view_extent(read_measurements(mm))[0],
                                                             1e3 * view_extent(rig)[0])


def test_rig_frame_track_needs_a_registration_in_params(files, params, tmp_path, fake_registration):
    m = read_measurements(files["patch"])
    rig = tmp_path / "rig.npz"
    write_measurements(rig, _transform(RIG_FROM_PATCH, m, np.arange(m.n_points), "rig"))
    r = CliRunner().invoke(main, ["track", str(rig), "--model", PAPER, "--params", str(params), "-o",
                                  str(tmp_path / "e.npz")])
    assert r.exit_code == 2 and "holds no registration" in r.output


@pytest.mark.slow
def test_fit_recovery_over_seeds_cli(tmp_path):
    """End to end over 5 seeds (paper_simulation, 3 s, three starts each): every |z| < 3.5."""
    runner = CliRunner()
    truth = np.array([1050.0, 2.0, 0.003, 150.0, 0.45])
    for seed in range(5):
        meas = tmp_path / f"m{seed}.npz"
        assert runner.invoke(main, ["model", "simulate", SIMULATION, "--duration", "3", "--seed", str(seed), "-o",
                                    str(meas)]).exit_code == 0
        out = tmp_path / f"p{seed}.yaml"
        s = _ok(runner.invoke(main, ["fit", str(meas), "--model", SIMULATION, "-o", str(out), "--json"]))
        z = (np.array([s["theta"][n] for n in NAMES]) - truth) / np.array([s["theta_std"][n] for n in NAMES])
        assert np.abs(z).max() < 3.5 and s["reduced_chi2"] < 1 + 5 * np.sqrt(2 / s["dof"])
