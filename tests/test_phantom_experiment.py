"""Acceptance of issue 6 on the rendered phantom (slow, about 12 minutes on 2 cores; `make test-slow`).

1. The reference pipeline (`make -C sample_sequences phantom`: target, render, calibrate, measure, fit, track ge
   and kf, report) on the phantom scene, whose stiffness doubles in systole: the GE's mean one-step prediction
   error is at most 0.6 x the KF's with the fitted constant parameters, and the GE's filtered surface is closer to
   the truth than the measurements themselves and than the noise level (mean 3-D norms).
2. The same scene rendered with a constant stiffness (`render sequence --stiffness-cycle 0`) and measured with the
   calibrated rig: `heartcv fit` recovers the truth's E and nu within 2 reported sigmas once the estimator
   model's own bias is accounted for. That bias (docs/spec/model.md 2.3: a coarser mesh is stiffer) is measured here,
   not assumed: the same fit of the same points' true (noise-free) positions. The GE started from that fit ends
   within 2 of its sigmas of the same value.
3. Issue 15 (parameters right through the heartbeat), on the phantom and on the second scene
   (`make -C sample_sequences phantom95`: 95 bpm, another patch, E 2.5x in systole, respiration, an instrument,
   50 fps; the phantom's calibration, the same options): the GE's E(t) correlates with the true E(t) at >= 0.9, the
   truth lies inside its +-2 sigma band in >= 80 % of the frames, GE/KF mean prediction error <= 0.6 and the GE's
   truth error below the noise level; on the phantom the NIS per dof of GE and KF lies in [0.7, 1.5].
4. The automatic registration of the pipeline's rig-frame measurement onto the patch, against the render's pose.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import SAMPLES

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    w = tmp_path_factory.mktemp("phantom")
    env = dict(os.environ, PYTHONPATH=str(SAMPLES.parent))
    subprocess.run(["make", "-C", str(SAMPLES), "phantom", f"WORK={w}", f"PY={sys.executable}"], check=True,
                   env=env, stdout=subprocess.DEVNULL)
    return w / "phantom_scene"


def _heartcv(*args):
    env = dict(os.environ, PYTHONPATH=str(SAMPLES.parent))
    r = subprocess.run([sys.executable, "-m", "heartcv.cli.main", *map(str, args)], env=env, capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout) if "--json" in args else None


def test_ge_beats_the_fitted_kf_on_the_rendered_phantom(work):
    m = json.loads((work / "report" / "metrics.json").read_text())
    ge, kf = m["estimators"]["ge"], m["estimators"]["kf"]
    assert ge["prediction_error_mean_m"] <= 0.6 * kf["prediction_error_mean_m"], (ge, kf)
    # the filtered surface against the truth: better than the measurements and the noise level (3-D mean norms)
    assert ge["truth_error_mean_m"] < m["measurement_truth_error_mean_m"]
    assert ge["truth_error_mean_m"] < m["measurement_noise_norm_mean_m"]
    assert ge["truth_error_mean_m"] < kf["truth_error_mean_m"]
    fit = json.loads((work / "fit.json").read_text())
    assert fit["converged"] and fit["frames"] == 120
    for f in ("index.html", "summary.md", "prediction_error.png", "parameter_E.png", "nis.png"):
        assert (work / "report" / f).stat().st_size > 0


def _true_positions_file(meas_path, truth_path, out):
    """The measurement file with every observed position replaced by its material point's true position (the
    point its reference-camera pixel saw at birth, heartcv.evaluate; gauge of the calibrated rig removed)."""
    from heartcv.evaluate import truth_errors
    from heartcv.io import read_render_truth
    from heartcv.tracker.io import read_measurements, write_measurements

    raw = read_measurements(meas_path)
    arrays, _ = read_render_truth(truth_path)
    te = truth_errors(raw.positions, np.asarray(raw.meta["reference_uv"], float),
                      np.asarray(raw.meta["reference_frame_index"], int), arrays)
    R = np.linalg.inv(te.truth_from_rig)
    true_rig = te.true_positions @ R[:3, :3].T + R[:3, 3]
    pos = np.where(np.isfinite(raw.positions), true_rig, np.nan)
    write_measurements(out, dataclasses.replace(raw, positions=pos), raw.meta)


def test_fit_recovers_a_constant_stiffness_within_two_sigma(work, tmp_path):
    seq = tmp_path / "seq"
    _heartcv("render", "sequence", SAMPLES / "phantom" / "scene.yaml", "-o", seq, "--frames", "120",
             "--stiffness-cycle", "0", "--json")
    _heartcv("measure", seq, "--rig", work / "rig.yaml", "-o", tmp_path / "meas.npz", "--json")
    res = _heartcv("fit", tmp_path / "meas.npz", "--model", SAMPLES / "phantom" / "model.yaml", "-o",
                   tmp_path / "params.yaml", "--frames", "120", "--seed", "1", "--json")
    truth = np.load(seq / "truth.npz")
    theta_true = truth["theta"][0]
    assert np.all(truth["theta"] == theta_true)                         # constant stiffness
    # the estimator model's own bias on these points: the same fit of the noise-free true positions
    _true_positions_file(tmp_path / "meas.npz", seq / "truth.npz", tmp_path / "meas_true.npz")
    eff = _heartcv("fit", tmp_path / "meas_true.npz", "--model", SAMPLES / "phantom" / "model.yaml", "-o",
                   tmp_path / "params_true.yaml", "--frames", "120", "--seed", "1", "--json")
    assert res["converged"] and eff["converged"] and res["covariance_kind"] == "cluster-robust"
    # measured (seed 1): E 150.06 +- 1.40 kPa (truth 150.00, effective 149.96); nu 0.438 +- 0.011 (effective 0.435,
    # truth 0.48: the 17x11x3 mesh is stiffer in bending, and the fit lowers nu to match)
    assert abs(eff["theta"]["E"] / theta_true[3] - 1) < 0.02 and eff["theta"]["nu"] < theta_true[4]
    for name in ("E", "nu"):
        z = (res["theta"][name] - eff["theta"][name]) / res["theta_std"][name]
        assert abs(z) < 2, (name, res["theta"][name], eff["theta"][name], res["theta_std"][name])
    # without the bias, nu would be several sigmas off: the accounting matters
    assert abs(res["theta"]["nu"] - theta_true[4]) > 2 * res["theta_std"]["nu"]
    # the GE from that fit (defaults: reference states, adaptation; the paper's estimator, without per-track offsets
    # as make demo runs it) ends at the effective E within 2 of its sigmas
    ge = _heartcv("track", tmp_path / "meas.npz", "--model", SAMPLES / "phantom" / "model.yaml", "--params",
                  tmp_path / "params.yaml", "--estimator", "ge", "--track-offsets", "none", "-o", tmp_path / "ge.npz",
                  "--json")
    assert ge["references"] == "estimate"
    z = (ge["theta_final"]["E"] - eff["theta"]["E"]) / ge["theta_std_final"]["E"]
    assert abs(z) < 2, (ge["theta_final"]["E"], eff["theta"]["E"], ge["theta_std_final"]["E"])


def _issue15_checks(m, nis=True):
    ge, kf = m["estimators"]["ge"], m["estimators"]["kf"]
    assert ge["theta_truth_correlation"]["E"] >= 0.9, ge["theta_truth_correlation"]
    assert ge["theta_truth_coverage_2sigma"]["E"] >= 0.8, ge["theta_truth_coverage_2sigma"]
    assert ge["prediction_error_mean_m"] <= 0.6 * kf["prediction_error_mean_m"], (ge, kf)
    assert ge["truth_error_mean_m"] < m["measurement_noise_norm_mean_m"]
    if nis:
        for e in (ge, kf):
            assert 0.7 <= e["nis_mean"] / e["nis_mean_dof"] <= 1.5, e


def test_parameters_follow_the_truth_through_the_heartbeat(work):
    _issue15_checks(json.loads((work / "report" / "metrics.json").read_text()))


def test_second_scene_with_the_same_options(work):
    """The same code and options on another heart rate, geometry and stiffness cycle (sample_sequences/phantom95)."""
    env = dict(os.environ, PYTHONPATH=str(SAMPLES.parent))
    subprocess.run(["make", "-C", str(SAMPLES), "phantom95", f"WORK={work.parent}", f"PY={sys.executable}"],
                   check=True, env=env, stdout=subprocess.DEVNULL)
    m = json.loads((work.parent / "phantom95_scene" / "report" / "metrics.json").read_text())
    _issue15_checks(m, nis=False)



def test_phantom_without_its_pressure(work):
    """Issue 16 on the rendered phantom (`make phantom-blind`): the recorded pressure ignored (`fit --input
    estimate` over the 4 beats), the GE with the estimated input (heart rate sampled, E held) predicts within 1.5x
    of the GE with the pressure (measured 0.98x with the affine rigid motion, 1.01x with a translation); the heart
    rate within 1 % of the truth (1 Hz)."""
    env = dict(os.environ, PYTHONPATH=str(SAMPLES.parent))
    subprocess.run(["make", "-C", str(SAMPLES), "phantom-blind", f"WORK={work.parent}", f"PY={sys.executable}"],
                   check=True, env=env, stdout=subprocess.DEVNULL)
    e = json.loads((work.parent / "phantom_blind" / "report.json").read_text())["estimators"]
    blind, known = e["ge:est_ge"], e["ge:est_ge-2"]
    assert blind["prediction_error_mean_m"] <= 1.5 * known["prediction_error_mean_m"], (blind, known)
    fit = json.loads((work.parent / "phantom_blind" / "fit.json").read_text())
    assert abs(fit["heart_rate_hz"] - 1.0) < 0.01
    assert blind["heart_rate_source"].startswith("sampled by the GE") and abs(blind["heart_rate_hz"] - 1.0) < 0.01


def test_registration_of_the_phantom_measurement_against_the_render_truth(work):
    """The reference pipeline's measurement file of the rendered phantom (rig frame; the calibrated rig's camera 0
    differs from the truth's by about 0.015 deg / 0.1 mm): the automatic registration onto the estimator model's
    patch lands within 0.5 deg and 0.5 mm of the render's world_from_patch, its surface RMS below 0.1 mm, at most 5
    points placed on or off the patch otherwise than the truth places them, and the KF on the registered points
    predicts within 5 % of the KF on the same points placed by the true pose. (It used to read a measurement left in
    /tmp/hw, and was skipped wherever that was missing.)"""
    from heartcv.io import read_render_truth
    from heartcv.tracker.io import read_measurements, read_model
    from heartcv.tracker.model import build_model
    from heartcv.tracker.registration import Registration, register, to_patch_frame
    from heartcv.tracker.tracking import run_kalman
    from tests.tracker.test_registration import apply, errors

    meas = read_measurements(work / "meas.npz")
    truth, _ = read_render_truth(work / "seq" / "truth.npz")
    model = build_model(read_model(SAMPLES / "phantom" / "model.yaml"))
    reg = register(meas, model)
    T_true = np.linalg.inv(truth["world_from_patch"])
    rot, origin = errors(reg.patch_from_rig, T_true)
    assert reg.converged, reg.message
    assert np.degrees(rot) < 0.5 and np.linalg.norm(origin) < 0.5e-3, (np.degrees(rot), origin)
    assert reg.rms_m < 0.1e-3
    g = model.mesh.geometry
    std = g.from_patch(apply(T_true, meas.reference))
    on_true = (np.abs(std[:, 0]) <= g.length / 2) & (np.abs(std[:, 1]) <= g.width / 2) \
        & (np.abs(std[:, 2]) <= g.thickness / 4)
    assert (reg.on_patch != on_true).sum() <= 5
    # the KF on the registered points predicts as well as on the same points placed by the true pose (measured
    # 0.15705 against 0.15678 mm RMS: the model file's nominal parameters, not fitted ones, so worse than hold)
    est = run_kalman(model, to_patch_frame(meas, reg))
    ideal = run_kalman(model, to_patch_frame(meas, Registration(T_true, reg.rms_m, reg.on_patch, reg.n_points,
                                                                 True, "")))
    assert est.complete and est.prediction_rmse() <= 1.05 * ideal.prediction_rmse(), (est.prediction_rmse(),
                                                                                       ideal.prediction_rmse())
