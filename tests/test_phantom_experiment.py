"""Acceptance of issue 6 on the rendered phantom (slow, about 12 minutes on 2 cores; `make test-slow`).

1. The reference pipeline (`make -C sample_sequences phantom`: target, render, calibrate, measure, fit, track ge
   and kf, report) on the phantom scene, whose stiffness doubles in systole: the GE's mean one-step prediction
   error is at most 0.6 x the KF's with the fitted constant parameters, and the GE's filtered surface is closer to
   the truth than the measurements themselves and than the noise level (mean 3-D norms).
2. The same scene rendered with a constant stiffness (`render sequence --stiffness-cycle 0`) and measured with the
   calibrated rig: `heartcv fit` recovers the truth's E and nu within 2 reported sigmas once the estimator
   model's own bias is accounted for. That bias (spec/model.md 2.3: a coarser mesh is stiffer) is measured here,
   not assumed: the fit of the estimator model to the truth model's noise-free surface motion.
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
    r = subprocess.run([sys.executable, "-m", "cli.main", *map(str, args)], env=env, capture_output=True, text=True)
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


def _model_bias(theta_true):
    """theta of the estimator model (phantom/model.yaml) fitted to the truth model's noise-free motion."""
    from threadpoolctl import threadpool_limits

    from tracker.fit import fit
    from tracker.io import read_model
    from tracker.model import build_model
    from tracker.simulate import simulate, to_measurements

    truth = build_model(dataclasses.replace(read_model(SAMPLES / "phantom" / "truth_model.yaml"), frame_rate=60))
    est = build_model(read_model(SAMPLES / "phantom" / "model.yaml"))
    assert np.allclose(truth.config.theta, theta_true)
    with threadpool_limits(1):
        sim = simulate(truth, 2.0, np.random.default_rng(0), process_noise=False, initial_noise=False, substeps=4)
        meas = to_measurements(sim)
        cov = np.broadcast_to(1e-10 * np.eye(3), meas.covariances.shape).copy()   # 10 um, exact positions
        meas = dataclasses.replace(meas, positions=sim.positions.copy(), covariances=cov)
        return fit(est, meas, np.random.default_rng(1))


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
    bias = _model_bias(theta_true)
    assert bias.converged
    # the estimator model's bias, measured: E within 3 %, nu lower (two elements through the wall)
    assert abs(bias.theta[3] / theta_true[3] - 1) < 0.03 and bias.theta[4] < theta_true[4]
    assert res["converged"]
    for name, i in (("E", 3), ("nu", 4)):
        z = (res["theta"][name] - bias.theta[i]) / res["theta_std"][name]
        assert abs(z) < 2, (name, res["theta"][name], bias.theta[i], res["theta_std"][name])
