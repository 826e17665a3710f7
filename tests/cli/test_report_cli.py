"""CLI: heartcv report on estimate files made with the existing CLI (model simulate -> track kf/ge): the folder,
metrics.json against the estimate files, the figures, mixed sequences, partial runs, render truths, bad input."""

import json

from click.testing import CliRunner
import numpy as np
from PIL import Image
import pytest

from heartcv.cli.main import main
from tests.conftest import SAMPLES

PAPER = str(SAMPLES / "paper_patch.yaml")
PER_ESTIMATOR = {"prediction_error_mean_m", "prediction_error_std_m", "prediction_error_rms_m", "truth_error_mean_m",
                 "prediction_truth_error_mean_m", "measurement_truth_error_mean_m", "nis_mean", "nis_mean_dof",
                 "nis_in_band_fraction", "theta_final", "theta_std_final", "step_time_median_s", "step_time_p95_s",
                 "completed_steps"}


def _ok(cmd, args):
    res = CliRunner().invoke(cmd, [str(a) for a in args])
    assert res.exit_code == 0, res.output
    return res


def _report(args):
    return CliRunner().invoke(main, ["report"] + [str(a) for a in args])


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("report")
    _ok(main, ["-q", "model", "simulate", PAPER, "--duration", "1", "--seed", "1", "-o", d / "m.npz",
               "--truth", d / "t.npz"])
    for e in ("kf", "ge"):
        _ok(main, ["-q", "track", d / "m.npz", "--model", PAPER, "--estimator", e, "-o", d / f"{e}.npz"])
    _ok(main, ["-q", "model", "simulate", PAPER, "--duration", "0.5", "--seed", "1", "-o", d / "short.npz"])
    _ok(main, ["-q", "track", d / "short.npz", "--model", PAPER, "-o", d / "kf_short.npz"])
    return d


def test_end_to_end(run):
    out = run / "rep"
    res = _report([run / "ge.npz", run / "kf.npz", "--truth", run / "t.npz", "--measurements", run / "m.npz",
                   "-o", out, "--json"])
    assert res.exit_code == 0, res.output
    js = json.loads(res.stdout)
    doc = json.loads((out / "metrics.json").read_text())
    assert js == dict(doc, output=str(out))
    assert set(doc["files"]) | {"heartcv-manifest.json"} == {p.name for p in out.iterdir()}
    assert json.loads((out / "heartcv-manifest.json").read_text())["producer"] == "heartcv report"
    assert not [p for p in run.iterdir() if p.name.startswith(".rep.")]  # no temporary folder left
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert set(pngs) == set(doc["figures"]) == {"prediction_error.png", "parameter_E.png", "parameter_nu.png",
                                                  "nis.png", "truth_error.png", "step_time.png"}
    html = (out / "index.html").read_text()
    md = (out / "summary.md").read_text()
    for name in pngs:
        assert f'href="{name}"' in html and f"]({name})" in md
        with Image.open(out / name) as im:
            assert im.width >= 960 and im.info["dpi"][0] == pytest.approx(150, abs=1)
    assert html.count("data:image/png;base64,") == len(pngs)

    from heartcv.tracker.io import read_estimates, read_measurements, read_truth

    truth, _ = read_truth(run / "t.npz")
    meas = read_measurements(run / "m.npz")
    assert doc["sequence"] == {"frames": 31, "duration_s": pytest.approx(1.0), "points": 14,
                               "dt_s": pytest.approx(1 / 30), "mixed": False, "points_left_out": 0}
    assert doc["measurement_noise_m"] == pytest.approx(1e-4, rel=1e-12)  # paper_patch: 0.1 mm per coordinate
    assert doc["truth"]["kind"] == "simulation" and doc["truth"]["positions"]
    for name in ("ge", "kf"):
        e = doc["estimators"][name]
        est = read_estimates(run / f"{name}.npz")
        assert PER_ESTIMATOR <= set(e) and e["completed_steps"] == 31 and not e["partial"]
        # against the estimate files directly
        assert e["prediction_error_rms_m"] == pytest.approx(est.prediction_rmse(), rel=1e-12)
        d = np.linalg.norm(est.innovations[1:], axis=-1)
        assert e["prediction_error_mean_m"] == pytest.approx(d.mean(), rel=1e-12)
        # truth errors over k >= 1 (every point is seen in this file): the filtered estimates, the one-step
        # predictions and the measurements themselves (from the measurement file, not the estimates)
        t = np.linalg.norm(est.filtered[1:] - truth["positions"][1:], axis=-1)
        assert e["truth_error_mean_m"] == pytest.approx(t.mean(), rel=1e-12)
        assert e["truth_error_rms_m"] == pytest.approx(np.sqrt(np.mean(t**2)), rel=1e-12)
        tp = np.linalg.norm(est.predictions[1:] - truth["positions"][1:], axis=-1)
        assert e["prediction_truth_error_mean_m"] == pytest.approx(tp.mean(), rel=1e-12)
        assert e["prediction_truth_error_std_m"] == pytest.approx(tp.std(), rel=1e-12)
        ty = np.linalg.norm(meas.positions[1:] - truth["positions"][1:], axis=-1)
        assert e["measurement_truth_error_mean_m"] == pytest.approx(ty.mean(), rel=1e-12)
        assert e["nis_mean"] == pytest.approx(np.mean(est.nis), rel=1e-12) and e["nis_mean_dof"] == 42
        assert e["theta_final"]["E"] == pytest.approx(est.theta[-1, 3], rel=1e-12)
        assert e["step_time_median_s"] == pytest.approx(np.median(est.step_time[1:]), rel=1e-12)
        assert e["step_time_p95_s"] >= e["step_time_median_s"] > 0
        # plausible: the measurement noise (0.1 mm) dominates the prediction error, the truth error lies below
        # it, and the paper's model is consistent (both estimators run with the true parameters)
        assert 1e-4 < e["prediction_error_mean_m"] < 3e-4
        assert e["truth_error_mean_m"] < e["prediction_truth_error_mean_m"] < e["prediction_error_mean_m"]
        assert e["prediction_truth_error_mean_m"] < 0.3 * e["measurement_truth_error_mean_m"]
        assert e["truth_error_mean_m"] < doc["measurement_noise_m"]
        assert 0.7 < e["nis_mean"] / e["nis_mean_dof"] < 1.3
        # the predictive log-likelihood per measured point (14 points in each frame k >= 1)
        assert e["log_likelihood_points"] == 30 * 14
        assert e["log_likelihood_per_point"] == pytest.approx(est.log_likelihood[1:].sum() / (30 * 14), rel=1e-12)
        assert est.meta["log_likelihood"] == pytest.approx(est.log_likelihood[1:].sum(), rel=1e-12)
    assert doc["measurement_truth_error_mean_m"] == doc["estimators"]["ge"]["measurement_truth_error_mean_m"]
    # the covariances' own E|v| (quadrature), isotropic here: the chi(3) mean
    assert doc["measurement_noise_norm_mean_m"] == pytest.approx(1e-4 * np.sqrt(8 / np.pi), rel=1e-5)
    # the measurements' own truth error is the noise: 434 norms of N(0, sigma^2 I3), mean sigma sqrt(8/pi)
    assert doc["measurement_truth_error_mean_m"] == pytest.approx(doc["measurement_noise_norm_mean_m"], rel=0.05)
    assert doc["ratio_ge_to_kf_truth_error"] == pytest.approx(
        doc["estimators"]["ge"]["truth_error_mean_m"] / doc["estimators"]["kf"]["truth_error_mean_m"])
    assert "pred. truth error mean" in md and "measurements themselves against the truth" in md
    assert "E|v|" in html
    assert doc["estimators"]["ge"]["estimated"] == ["E", "nu"]
    assert doc["estimators"]["ge"]["theta_std_final"]["E"] > 0 == doc["estimators"]["kf"]["theta_std_final"]["E"]
    assert doc["ratio_ge_to_kf_prediction_error"] == pytest.approx(
        doc["estimators"]["ge"]["prediction_error_mean_m"] / doc["estimators"]["kf"]["prediction_error_mean_m"])
    ll = {n: doc["estimators"][n]["log_likelihood_per_point"] for n in ("ge", "kf")}
    assert doc["difference_ge_minus_kf_log_likelihood_per_point"] == pytest.approx(ll["ge"] - ll["kf"], rel=1e-12)
    assert "log lik. / point" in md and "GE − KF one-step predictive log-likelihood" in md
    assert doc["inputs_hash"]["measurements"] == read_estimates(run / "kf.npz").meta["inputs_hash"]["measurements"]
    assert meas.n_frames == 31

    # a second report replaces the folder as a whole, but not a file a person put there
    (out / "stale.txt").write_text("x")
    res = _report([run / "kf.npz", "-o", out])
    assert res.exit_code == 2 and "holds files heartcv report did not write (stale.txt)" in res.output
    assert (out / "stale.txt").read_text() == "x" and (out / "truth_error.png").exists()
    (out / "stale.txt").unlink()
    res = _report([run / "kf.npz", "-o", out])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "metrics.json").read_text())
    assert not (out / "truth_error.png").exists()
    assert doc["measurement_noise_m"] is None and doc["estimators"]["kf"]["truth_error_mean_m"] is None
    assert doc["estimators"]["kf"]["prediction_truth_error_mean_m"] is None
    assert doc["estimators"]["kf"]["measurement_truth_error_mean_m"] is None
    assert doc["measurement_truth_error_mean_m"] is None and doc["measurement_noise_norm_mean_m"] is None
    assert doc["ratio_ge_to_kf_prediction_error"] is None and "parameter_E.png" not in doc["figures"]


def test_mixed_sequences_refused(run):
    out = run / "mixed"
    res = _report([run / "kf.npz", run / "kf_short.npz", "-o", out])
    assert res.exit_code == 2
    assert "different sequences" in res.output and "kf_short.npz" in res.output and "kf.npz" in res.output
    assert not out.exists()
    res = _report([run / "kf_short.npz", "--truth", run / "t.npz", "-o", out])
    assert res.exit_code == 2 and "frame times" in res.output and not out.exists()
    res = _report([run / "kf.npz", "--measurements", run / "short.npz", "-o", out])
    assert res.exit_code == 2 and "short.npz" in res.output and not out.exists()
    res = _report([run / "kf.npz", run / "kf_short.npz", "-o", out, "--allow-mixed", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["sequence"]["mixed"] and set(doc["estimators"]) == {"kf:kf", "kf:kf_short"}
    assert doc["estimators"]["kf:kf_short"]["completed_steps"] == 16


def test_a_truth_of_another_simulation_is_refused(run, tmp_path):
    """The truth of another seed has the same frame times (it was accepted and its errors reported): the truth file
    records the measurement file simulated with it (meta.measurements_hash) and the report refuses it beside
    estimates of another file, or another --measurements (exit 2). With --allow-mixed it is left out: no truth
    error, no true parameters for that run, a note says why; a truth of other frame times likewise."""
    from heartcv.tracker.io import file_hash, read_truth

    _ok(main, ["-q", "model", "simulate", PAPER, "--duration", "1", "--seed", "3", "-o", tmp_path / "m3.npz",
               "--truth", tmp_path / "t3.npz"])
    assert read_truth(tmp_path / "t3.npz")[1]["measurements_hash"] == file_hash(tmp_path / "m3.npz")
    assert read_truth(run / "t.npz")[1]["measurements_hash"] == file_hash(run / "m.npz")
    out = tmp_path / "rep"
    res = _report([run / "kf.npz", "--truth", tmp_path / "t3.npz", "-o", out])
    assert res.exit_code == 2 and "meta.measurements_hash: the truth was simulated with another measurement file" \
        in res.output and not out.exists(), res.output
    res = _report([run / "kf.npz", "--truth", tmp_path / "t3.npz", "--measurements", run / "m.npz", "-o", out])
    assert res.exit_code == 2 and "m.npz" in res.output and not out.exists()
    res = _report([run / "kf.npz", "--truth", tmp_path / "t3.npz", "-o", out, "--allow-mixed", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    (e,) = doc["estimators"].values()
    assert e["truth_error_mean_m"] is None and e["theta_truth_final"] is None
    assert any("another measurement file" in n for n in doc["truth"]["notes"])
    # the truth of the run's own file: its errors
    res = _report([run / "kf.npz", "--truth", run / "t.npz", "-o", tmp_path / "own", "--json"])
    assert res.exit_code == 0, res.output
    (own,) = json.loads(res.stdout)["estimators"].values()
    assert own["truth_error_mean_m"] > 0 and own["theta_truth_final"] is not None
    # other frame times, let in: no true parameters either
    res = _report([run / "kf_short.npz", "--truth", run / "t.npz", "-o", tmp_path / "short", "--allow-mixed",
                   "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    (e,) = doc["estimators"].values()
    assert e["theta_truth_final"] is None and e["theta_truth_coverage_2sigma"] is None
    assert any("other frame times" in n for n in doc["truth"]["notes"])


def test_partial_run_and_render_truth(run):
    from dataclasses import replace

    from heartcv.tracker.io import read_estimates, read_truth, write_estimates

    ge = read_estimates(run / "ge.npz")
    nan_rows = lambda a: np.concatenate([a[:20], np.full_like(a[20:], np.nan)])  # noqa: E731
    part = replace(ge, completed_steps=20, theta=nan_rows(ge.theta), theta_std=nan_rows(ge.theta_std),
                   predictions=nan_rows(ge.predictions), filtered=nan_rows(ge.filtered),
                   innovations=nan_rows(ge.innovations), nis=nan_rows(ge.nis),
                   nis_dof=np.where(np.arange(31) < 20, ge.nis_dof, 0),
                   step_time=np.where(np.arange(31) < 20, ge.step_time, 0.0))
    write_estimates(run / "ge.partial.npz", part, {"partial": True})
    truth, _ = read_truth(run / "t.npz")
    meta = json.dumps({"format": "heartcv.render_truth", "format_version": 1, "kind": "sequence"}).encode()
    np.savez(run / "render_truth.npz", times=truth["times"], theta=truth["theta"],
             point_positions=truth["positions"], meta_json=np.frombuffer(meta, np.uint8))
    res = _report([run / "ge.partial.npz", run / "kf.npz", "--truth", run / "render_truth.npz", "-o",
                   run / "rep_part", "--json"])
    assert res.exit_code == 0, res.output
    assert (f"WARNING heartcv.cli.report: {run / 'ge.partial.npz'}: partial run (20 of 31 steps completed); only "
            "the completed steps are used") in res.stderr
    doc = json.loads(res.stdout)
    g = doc["estimators"]["ge"]
    assert g["partial"] and g["completed_steps"] == 20 and g["steps"] == 31
    assert g["prediction_error_rms_m"] == pytest.approx(part.prediction_rmse(), rel=1e-12)
    assert g["theta_final"]["E"] == pytest.approx(ge.theta[19, 3], rel=1e-12)
    assert doc["truth"]["kind"] == "render" and not doc["truth"]["positions"]
    assert g["truth_error_mean_m"] is None and "--measurements" in doc["truth"]["notes"][0]
    assert "truth_error.png" not in doc["figures"] and "parameter_E.png" in doc["figures"]
    assert "GE / KF mean prediction error: " in (run / "rep_part" / "summary.md").read_text()
    assert "(over different frames: ge 20, kf 31 completed steps; no paired interval)" in \
        (run / "rep_part" / "summary.md").read_text()


def test_estimate_file_without_filtered_positions(run):
    """A file written before heartcv track recorded the filtered positions: its truth error is null (with a note),
    the one-step predictions' truth error is still reported."""
    from dataclasses import replace

    from heartcv.tracker.io import read_estimates, read_truth, write_estimates

    kf = read_estimates(run / "kf.npz")
    write_estimates(run / "kf_old.npz", replace(kf, filtered=None))
    res = _report([run / "kf_old.npz", "--truth", run / "t.npz", "-o", run / "rep_old", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    e = doc["estimators"]["kf"]
    truth, _ = read_truth(run / "t.npz")
    assert e["truth_error_mean_m"] is None and e["truth_error_rms_m"] is None
    tp = np.linalg.norm(kf.predictions[1:] - truth["positions"][1:], axis=-1)
    assert e["prediction_truth_error_mean_m"] == pytest.approx(tp.mean(), rel=1e-12)
    ty = np.linalg.norm(kf.predictions[1:] + kf.innovations[1:] - truth["positions"][1:], axis=-1)
    assert e["measurement_truth_error_mean_m"] == pytest.approx(ty.mean(), rel=1e-12)
    assert any("no filtered positions" in n for n in doc["truth"]["notes"])
    assert "truth_error.png" in doc["figures"]


def test_bad_input(run):
    res = _report([run / "missing.npz", "-o", run / "bad"])
    assert res.exit_code == 2 and "missing.npz" in res.output
    res = _report([run / "kf.npz", "--truth", run / "m.npz", "-o", run / "bad"])
    assert res.exit_code == 2 and "truth file" in res.output
    res = _report([run / "m.npz", "-o", run / "bad"])
    assert res.exit_code == 2 and "heartcv.estimates" in res.output
    other = run / "other"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    res = _report([run / "kf.npz", "-o", other])
    assert res.exit_code == 2 and "holds no heartcv manifest: heartcv report replaces only a folder it wrote" \
        in res.output
    assert [p.name for p in other.iterdir()] == ["keep.txt"] and (other / "keep.txt").read_text() == "mine"
    res = _report([run / "kf.npz", "-o", run / "m.npz"])
    assert res.exit_code == 2 and "not a folder" in res.output
    assert not (run / "bad").exists()


def test_render_truth_positions_into_the_patch_frame():
    """tracker.metrics.truth_in_patch_frame: the truth's world positions through the inverse gauge into the rig
    frame, then by the estimate's patch_from_rig, in the estimate's point order (NaN for a point the
    measurement file lacks); pose_magnitude names the gauge's size."""
    from scipy.spatial.transform import Rotation

    from heartcv.tracker.metrics import pose_magnitude, truth_in_patch_frame

    def pose(rotvec, t):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Rotation.from_rotvec(rotvec).as_matrix(), t
        return T

    rng = np.random.default_rng(0)
    rig = rng.normal(size=(4, 3, 3))                      # (K, P_meas, 3) in the rig frame
    truth_from_rig = pose([0.0, 0.0, np.radians(2.0)], [1e-3, 0.0, 0.0])
    patch_from_rig = pose([0.3, -0.2, 0.1], [0.01, 0.02, -0.3])
    world = rig @ truth_from_rig[:3, :3].T + truth_from_rig[:3, 3]
    got = truth_in_patch_frame(world, truth_from_rig, np.array([7, 8, 9]), np.array([9, 5, 7]), patch_from_rig)
    expect = rig[:, [2, 0]] @ patch_from_rig[:3, :3].T + patch_from_rig[:3, 3]
    np.testing.assert_allclose(got[:, [0, 2]], expect, rtol=0, atol=1e-14)
    assert np.isnan(got[:, 1]).all()
    angle, shift = pose_magnitude(truth_from_rig)
    assert angle == pytest.approx(2.0, rel=1e-12) and shift == pytest.approx(1e-3, rel=1e-12)


def test_report_meta_entries_are_checked(run, tmp_path):
    """The estimate meta that the report reads is validated: a wrong type exits 2 naming the file and the field; a
    numeric string is read as its number (the fuzzer found meta.rigid_ar_order = [] and meta.held_parameters = 12345
    crashing the summary and the figures, and meta.parameter_overdispersion = -1e308 crashing the summary)."""
    from heartcv.tracker.io import read_estimates, write_estimates

    est = read_estimates(run / "kf.npz")
    K = est.times.size
    cases = {"rigid_ar_order": [], "heart_rate_hz": [1.0], "fit_frames": K + 1, "without_input": "yes",
             "heldout_points": ["a"], "heart_rate_source": 3, "held_parameters": 12345, "field_degree": "one",
             "rigid_harmonics": "six", "rigid_dynamics": 5, "parameter_overdispersion": -1e308,
             "parameter_overdispersion.kappa_final": {"frames_adjusted": 3},
             "parameter_overdispersion.frames_adjusted": {"kappa_final": 2.0, "frames_adjusted": "many"}}
    for field, bad in cases.items():
        key = field.split(".")[0]
        path = tmp_path / f"bad_{field}.npz"
        write_estimates(path, est, dict(est.meta, **{key: bad}))
        res = _report([path, "-o", tmp_path / f"rep_{field}"])
        assert res.exit_code == 2 and str(path) in res.output and f"meta.{field}" in res.output, res.output
        assert "Traceback" not in res.output and not (tmp_path / f"rep_{field}").exists()
    good = tmp_path / "good.npz"
    write_estimates(good, est, dict(est.meta, heart_rate_hz="1.25", heart_rate_source="given", rigid_ar_order=2,
                                    fit_frames=K // 2))
    res = _report([good, "-o", tmp_path / "rep_good", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["estimators"]["kf"]["heart_rate_hz"] == 1.25 and doc["fit_frames"] == K // 2
    assert "Heart rate: 75 bpm" in (tmp_path / "rep_good" / "summary.md").read_text()


def test_heart_rate_against_the_tracks_own_spectrum(tmp_path):
    """With --measurements and runs that used a heart rate, the report takes the tracks' own rate in 6-s windows
    (the paper patch beats at 60 bpm: every window within 0.5 % of 1 Hz, measured 0.02 %) and says how each run's
    rate agrees with it: the right rate in every window (two runs with it in one entry of the summary), a rate 15 %
    low in none (its mean |difference| 0.15 Hz); the heart-rate figure draws them. Without a run that used a heart
    rate there is nothing to compare."""
    from heartcv.tracker.io import read_estimates, write_estimates

    _ok(main, ["-q", "model", "simulate", PAPER, "--duration", "12.5", "--seed", "1", "-o", tmp_path / "m.npz"])
    _ok(main, ["-q", "track", tmp_path / "m.npz", "--model", PAPER, "--estimator", "kf", "-o", tmp_path / "kf.npz"])
    est = read_estimates(tmp_path / "kf.npz")
    for name, hz in (("right", 1.0), ("same", 1.0), ("low", 0.85)):
        write_estimates(tmp_path / f"{name}.npz", est, dict(est.meta, heart_rate_hz=hz, heart_rate_std_hz=0.005))
    res = _report([tmp_path / "right.npz", tmp_path / "same.npz", tmp_path / "low.npz", "--measurements",
                   tmp_path / "m.npz", "-o", tmp_path / "rep", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    hw = doc["tracks"]["heart_rate_windows"]
    assert (hw["window_s"], hw["step_s"]) == (6.0, 3.0) and len(hw["windows"]) == 3
    assert all(w["frequency_hz"] == pytest.approx(1.0, rel=5e-3) for w in hw["windows"])
    assert all(w["peak_prominence"] > 10 for w in hw["windows"])      # a heartbeat's peak: prominent
    agree = doc["tracks"]["heart_rate_agreement"]
    assert (agree["kf:right"]["agree"], agree["kf:low"]["agree"]) == (3, 0), agree
    assert agree["kf:low"]["mean_abs_difference_hz"] == pytest.approx(0.15, abs=0.005)
    assert "heart_rate.png" in doc["figures"]
    md = (tmp_path / "rep" / "summary.md").read_text()
    assert "The tracks' own heart rate in 6-s windows every 3 s" in md and "kf:low within 2σ of it in 0 of 3" in md
    assert "kf:right, kf:same within 2σ of it in 3 of 3" in md      # runs that agree alike: one entry
    assert "may be drift" not in md
    res = _report([tmp_path / "kf.npz", "--measurements", tmp_path / "m.npz", "-o", tmp_path / "rep2", "--json"])
    assert res.exit_code == 0, res.output
    tracks = json.loads(res.stdout)["tracks"]
    assert tracks["heart_rate_windows"] is None and tracks["heart_rate_agreement"] is None


def test_summary_says_which_window_rates_may_be_drift():
    """A window whose rate comes from a peak that is not prominent (tracker.unknown_input.peak_prominence below
    PEAK_PROMINENCE) is counted in the summary's line on the windowed rates; a window without a rate is not."""
    from heartcv.cli.report_doc import _rate_windows

    windows = [{"t_start_s": 0.0, "t_end_s": 6.0, "frequency_hz": 1.0, "std_hz": 0.01, "peak_prominence": 1.3},
               {"t_start_s": 3.0, "t_end_s": 9.0, "frequency_hz": 1.1, "std_hz": 0.01, "peak_prominence": 8.0},
               {"t_start_s": 6.0, "t_end_s": 12.0, "frequency_hz": None, "std_hz": None, "peak_prominence": None,
                "reason": "no periodic motion"}]
    line = " ".join(_rate_windows({"tracks": {"heart_rate_windows": {"window_s": 6.0, "step_s": 3.0,
                                                                      "windows": windows}}}))
    assert "60–66 bpm in 2 of 3 windows (the others show no clear heartbeat)" in line, line
    assert "in 1 of them the spectral peak stands less than 2x above" in line and "may be drift" in line, line
    windows[0]["peak_prominence"] = 2.5
    line = " ".join(_rate_windows({"tracks": {"heart_rate_windows": {"window_s": 6.0, "step_s": 3.0,
                                                                      "windows": windows}}}))
    assert "may be drift" not in line, line


def test_the_rig_check_of_measure_is_reported(run, tmp_path):
    """A measurement file recording what `heartcv measure` found of its rig (`rig_epipolar_px`,
    `rig_vertical_offsets_px`): metrics.json `rig_check` holds both, summary.md says them; the simulated file,
    which records neither, gives null and no such line."""
    from dataclasses import replace

    from heartcv.tracker.io import read_measurements, write_measurements

    m = read_measurements(run / "m.npz")
    write_measurements(tmp_path / "m.npz", replace(m, meta=dict(m.meta, rig_epipolar_px={"cam1": 0.29, "cam2": None},
                                                                  rig_vertical_offsets_px={"cam1": 0.46})))
    _ok(main, ["-q", "track", tmp_path / "m.npz", "--model", PAPER, "-o", tmp_path / "kf.npz"])
    res = _report([tmp_path / "kf.npz", "--measurements", tmp_path / "m.npz", "-o", tmp_path / "rep", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["rig_check"] == {"epipolar_px": {"cam1": 0.29, "cam2": None}, "vertical_offsets_px": {"cam1": 0.46}}
    md = (tmp_path / "rep" / "summary.md").read_text()
    assert ("Rig checked against its views (heartcv measure): SIFT features matched between the views lie a median "
            "0.29 px (cam1), – px (cam2)") in md and "cam1 +0.460 px" in md, md
    res = _report([run / "kf.npz", "--measurements", run / "m.npz", "-o", tmp_path / "rep0", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["rig_check"] is None
    assert "Rig checked" not in (tmp_path / "rep0" / "summary.md").read_text()


def test_a_recording_shorter_than_the_rate_windows_says_its_rate_goes_unchecked():
    """The tracks' own heart rate is measured in 6-s windows: a 3-s recording has none, and the report said nothing
    (the audit's first 75 in-vivo frames); now one line says the runs' rate is not checked. No windows key (no run
    used a heart rate): nothing."""
    from heartcv.cli.report_doc import _rate_windows

    doc = {"sequence": {"duration_s": 2.96},
           "tracks": {"heart_rate_windows": {"window_s": 6.0, "step_s": 3.0, "windows": []}}}
    (line,) = _rate_windows(doc)
    assert "(2.96 s) is shorter than the 6-s windows" in line and "not checked" in line
    assert _rate_windows({"sequence": {"duration_s": 2.96}, "tracks": {"heart_rate_windows": None}}) == []
