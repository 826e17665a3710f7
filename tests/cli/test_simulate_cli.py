"""CLI: heartcv simulate (Monte-Carlo study): JSON against an independent recomputation from study.npz and
from the estimators themselves, workers 1 vs 2, figures, bad input, divergence, overwriting a study folder."""

import json
from pathlib import Path

from click.testing import CliRunner
import numpy as np
from PIL import Image
import pytest
from scipy import stats

from heartcv.cli.main import main
from tests.cli.test_model_track_cli import _write_model as _model
from tests.conftest import SAMPLES

PAPER = str(SAMPLES / "paper_patch.yaml")
ARGS = ["--runs", "3", "--steps", "12", "--seed", "4"]
KEYS = {"rmse_initial", "rmse_final", "anees", "anees_band", "anees_in_band_fraction", "nees_per_parameter_final",
        "nis_per_dof_mean", "step_ms_median", "diverged"}


def _invoke(args):
    return CliRunner().invoke(main, args)


def _load(folder):
    with np.load(Path(folder) / "study.npz", allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    return data, json.loads(bytes(data.pop("meta_json")).decode())


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("study") / "s"
    res = _invoke(["simulate", PAPER, *ARGS, "--workers", "1", "-o", str(out), "--json"])
    assert res.exit_code == 0, res.output
    return out, json.loads(res.stdout)


def test_json_matches_recomputation_from_npz(study):
    out, js = study
    data, meta = _load(out)
    assert meta["format"] == "heartcv.study" and meta["format_version"] == 1 and meta["producer"] == "heartcv simulate"
    assert (js["runs"], js["steps"], js["seed"], js["estimated"]) == (3, 12, 4, ["E", "nu"])
    assert js["output"] == str(out) and js["wall_s"] > 0
    assert js["theta_true"] == {"rho": 1050.0, "alpha1": 2.39, "alpha2": 0.003, "E": 150000.0, "nu": 0.45}
    assert list(data["estimators"]) == ["ge", "ukf", "ekf", "kf"] and set(js["estimators"]) == set(data["estimators"])
    truth, theta0, idx = data["theta_true"], data["theta0"], [3, 4]
    # the prior draws are N(phi_true, diag(0.5^2)) in (log E, s): theta0 differs from the truth in every run
    assert theta0.shape == (3, 5) and (theta0[:, idx] != truth[idx]).all() and (theta0[:, :3] == truth[:3]).all()
    band = [stats.chi2.ppf(0.025, 3 * 2) / 3, stats.chi2.ppf(0.975, 3 * 2) / 3]
    for name, s in js["estimators"].items():
        assert KEYS <= set(s) and s["diverged"] == 0
        theta = data[f"{name}_theta"]
        assert theta.shape == (3, 12, 5)
        for j, p in zip(idx, ["E", "nu"], strict=True):
            assert s["rmse_initial"][p] == pytest.approx(np.sqrt(np.mean((theta0[:, j] - truth[j]) ** 2)), rel=1e-12)
            assert s["rmse_final"][p] == pytest.approx(np.sqrt(np.mean((theta[:, -1, j] - truth[j]) ** 2)), rel=1e-12)
            err = np.abs(theta[:, :, j] - truth[j])
            np.testing.assert_allclose(data[f"{name}_abs_error_mean"][:, idx.index(j)], err.mean(axis=0), rtol=1e-12)
            np.testing.assert_allclose(data[f"{name}_abs_error_var"][:, idx.index(j)], err.var(axis=0, ddof=1),
                                       rtol=1e-10)
        ratio = data[f"{name}_nis"] / data[f"{name}_nis_dof"]
        assert (data[f"{name}_nis_dof"] == 42).all()
        assert s["nis_per_dof_mean"] == pytest.approx(ratio.mean(), rel=1e-12)
        assert s["step_ms_median"] == pytest.approx(1e3 * np.median(data[f"{name}_step_time"]), rel=1e-12)
        if name == "kf":  # parameters held at the prior draw: no NEES, the error never changes
            assert s["anees"] is None and s["anees_band"] is None and "kf_phi_cov" not in data
            assert s["rmse_final"] == s["rmse_initial"]
            continue
        e = data[f"{name}_phi_mean"] - data["phi_true"]
        cov = data[f"{name}_phi_cov"]
        nees = np.array([[e[r, k] @ np.linalg.inv(cov[r, k]) @ e[r, k] for k in range(12)] for r in range(3)])
        anees = nees.mean(axis=0)
        np.testing.assert_allclose(data[f"{name}_anees"], anees, rtol=1e-9)
        assert s["anees"] == pytest.approx(anees[1:].mean(), rel=1e-9)
        assert s["anees_band"] == pytest.approx(band, rel=1e-12)
        inside = (anees[1:] >= band[0]) & (anees[1:] <= band[1])
        assert s["anees_in_band_fraction"] == pytest.approx(inside.mean())
        per = (e[:, -1] ** 2 / np.diagonal(cov[:, -1], axis1=1, axis2=2)).mean(axis=0)
        assert [s["nees_per_parameter_final"][p] for p in ("E", "nu")] == pytest.approx(per, rel=1e-9)
        # the joint estimators learn E: 12 frames shrink the error by an order of magnitude
        assert s["rmse_final"]["E"] < 0.1 * s["rmse_initial"]["E"]


def test_summary_file_holds_the_json_and_the_file_list(study):
    out, js = study
    doc = json.loads((out / "summary.json").read_text())
    assert {k: doc[k] for k in js} == js
    assert doc["format"] == "heartcv.study" and doc["inputs_hash"]["model"].startswith("sha256:")
    assert sorted(doc["files"]) == sorted(["study.npz", "fig2_E.png", "fig2_nu.png", "anees.png", "nis.png",
                                           "summary.json"])
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary file left


def test_npz_matches_a_direct_run_of_the_estimator(study, paper_model):
    """Run 2 of the study recomputed with run_joint from the documented seeds (independent of tracker.study)."""
    from heartcv.tracker.joint import run_joint
    from heartcv.tracker.simulate import simulate, to_measurements

    out, _ = study
    data, _ = _load(out)
    g = np.random.default_rng(np.random.SeedSequence(4).spawn(3)[2])
    space = paper_model.config.parameter_space()
    lo, up = space.bounds_phi
    while True:
        phi0 = space.x_from_theta(paper_model.config.theta) + 0.5 * g.standard_normal(2)
        if ((phi0 > lo) & (phi0 < up)).all():
            break
    np.testing.assert_array_equal(data["phi0"][2], phi0)
    meas = to_measurements(simulate(paper_model, 11 / 30, g.spawn(1)[0]))
    est = run_joint(paper_model, meas, "ekf", theta0=space.theta_from_x(phi0))
    np.testing.assert_allclose(data["ekf_theta"][2], est.theta, rtol=1e-12)
    np.testing.assert_allclose(data["ekf_nis"][2], est.nis, rtol=1e-12)


def test_figures_are_valid_pngs(study):
    out, _ = study
    for name in ("fig2_E.png", "fig2_nu.png", "anees.png", "nis.png"):
        path = out / name
        assert path.stat().st_size > 10_000
        with Image.open(path) as im:
            im.verify()
        with Image.open(path) as im:
            assert im.format == "PNG" and im.size[0] >= 800 and im.size[1] >= 500
            assert im.info["dpi"][0] == pytest.approx(150, abs=1)
            assert np.asarray(im.convert("L")).std() > 10  # not a blank image


def test_two_workers_give_the_same_study_and_a_table(study, tmp_path):
    out1, js1 = study
    out2 = tmp_path / "w2"
    res = _invoke(["simulate", PAPER, *ARGS, "--workers", "2", "-o", str(out2)])
    assert res.exit_code == 0, res.output
    assert res.stdout == ""
    assert "heartcv.cli.simulate" in res.stderr and "ANEES" in res.stderr and "ukf" in res.stderr
    a, _ = _load(out1)
    b, _ = _load(out2)
    assert set(a) == set(b)
    for key in a:
        if not key.endswith("step_time"):
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    js2 = json.loads((out2 / "summary.json").read_text())
    for name, s in js1["estimators"].items():
        for key in KEYS - {"step_ms_median"}:
            assert js2["estimators"][name][key] == s[key]


def _no_estimates(d):
    d["estimation"]["estimate"] = []


@pytest.mark.parametrize("args, message", [
    (["missing.yaml"], "does not exist"),
    (["BAD", "--runs", "1"], "--runs"),
    (["BAD", "--steps", "1"], "--steps"),
    (["BAD", "--estimators", "ge,foo"], "'foo'"),
    (["BAD", "--estimators", ","], "--estimators"),
    (["BAD", "--workers", "0"], "--workers"),
    (["INVALID"], "parameters.nu"),
    (["NOEST", "--estimators", "ge,ekf"], "ge, ekf need at least one estimated parameter"),
])
def test_bad_input_exits_2_and_writes_nothing(tmp_path, args, message):
    edits = {"INVALID": lambda d: d["parameters"].update(nu=0.5), "NOEST": _no_estimates}
    subs = {a: _model(tmp_path, edits[a]) for a in args if a in edits}
    subs["BAD"] = PAPER
    out = tmp_path / "study"
    res = _invoke(["simulate", *[subs.get(a, a) for a in args], "-o", str(out), "--json"])
    assert res.exit_code == 2, res.output
    assert message in res.stderr and res.stdout == ""
    assert not (out / "summary.json").exists() and not out.exists()


@pytest.mark.parametrize("workers", ["1", "2"])
def test_a_prior_that_never_lands_in_the_box_exits_2_naming_the_model(tmp_path, workers):
    """A box far narrower than the prior: no initial draw lands inside; with workers the main process finds it
    before any worker starts."""
    def narrow(d):
        d["estimation"]["bounds"].update(E=[149.9e3, 150.1e3], nu=[0.4499, 0.4501])

    model = _model(tmp_path, narrow)
    out = tmp_path / "study"
    res = _invoke(["simulate", model, "--runs", "2", "--steps", "3", "--workers", workers, "-o", str(out)])
    assert res.exit_code == 2, res.output
    assert f"Error: {model}: estimation.prior_std: none of 1000 draws of the initial parameters" in res.stderr
    assert "lies inside the box estimation.bounds" in res.stderr
    assert not out.exists()


def test_output_that_is_a_file_exits_2(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    res = _invoke(["simulate", PAPER, "--runs", "2", "--steps", "2", "-o", str(f)])
    assert res.exit_code == 2 and f.read_text() == "x"


def test_all_runs_diverged_exits_1_and_writes_nothing(tmp_path, monkeypatch):
    from heartcv.tracker import study as st
    from heartcv.tracker.tracking import EstimationDiverged

    def diverge(*a, **k):
        raise EstimationDiverged(3)

    monkeypatch.setattr(st, "run_joint", diverge)
    monkeypatch.setattr(st, "run_kalman", diverge)
    out = tmp_path / "study"
    res = _invoke(["simulate", PAPER, "--runs", "2", "--steps", "5", "--workers", "1", "-o", str(out), "--json"])
    assert res.exit_code == 1, res.output
    assert "every run diverged" in res.stderr and res.stdout == ""
    assert not out.exists()


def test_kf_only_study_without_estimated_parameters_replaces_an_old_study(study, tmp_path):
    """A model estimating nothing runs the KF alone (NIS only); a folder that heartcv simulate wrote is replaced
    as a whole (its figures of parameters no longer estimated are gone); not while it holds a file a person added
    (the replacement would delete it)."""
    import shutil

    out = tmp_path / "study"
    shutil.copytree(study[0], out)
    (out / "notes.txt").write_text("added to the old study")
    args = ["simulate", _model(tmp_path, _no_estimates), "--runs", "2", "--steps", "4", "--estimators", "kf",
            "--workers", "1", "-o", str(out), "--json"]
    res = _invoke(args)
    assert res.exit_code == 2 and "holds files heartcv simulate did not write (notes.txt)" in res.stderr
    assert (out / "notes.txt").read_text() == "added to the old study"
    (out / "notes.txt").unlink()
    res = _invoke(args)
    assert res.exit_code == 0, res.output
    js = json.loads(res.stdout)
    assert js["estimated"] == [] and list(js["estimators"]) == ["kf"]
    kf = js["estimators"]["kf"]
    assert kf["rmse_initial"] == {} and kf["anees"] is None and kf["nis_per_dof_mean"] > 0
    assert sorted(p.name for p in out.iterdir()) == ["heartcv-manifest.json", "nis.png", "study.npz",
                                                     "summary.json"]
    assert json.loads((out / "summary.json").read_text())["runs"] == 2
    assert json.loads((out / "heartcv-manifest.json").read_text())["producer"] == "heartcv simulate"
    data, _ = _load(out)
    assert data["phi0"].shape == (2, 0) and (data["theta0"] == data["theta_true"]).all()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folder left


def test_si_scale_of_the_plot_axes():
    from heartcv.cli.plots import si_scale

    assert si_scale([1.5e5, 2e3], "Pa") == (1e-3, "kPa")
    assert si_scale([np.nan, 2.5e-4, 0.0], "m") == (1e6, "µm")
    assert si_scale([0.003], "s") == (1e3, "ms")
    assert si_scale([1e7], "1") == (1.0, "1") and si_scale([1050.0], "kg/m^3") == (1.0, "kg/m^3")
    assert si_scale([np.nan], "Pa") == (1.0, "Pa")


def test_figures_band_and_title_with_divergences():
    """With divergences the estimators' n differ: the figures still shade a band (the fewest runs', named)."""
    from types import SimpleNamespace

    from heartcv.cli.simulate import _band

    a = SimpleNamespace(runs_used=6, anees_band=(1.0, 3.0))
    b = SimpleNamespace(runs_used=2, anees_band=(0.2, 5.0))
    assert _band({"ge": a}, "anees_band") == ((1.0, 3.0), "95 % χ² band")
    assert _band({"ge": a, "ukf": b}, "anees_band") == ((0.2, 5.0), "95 % χ² band (UKF, 2 runs)")
    assert _band({}, "anees_band") == (None, "95 % χ² band")
