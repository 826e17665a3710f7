"""Filtered (posterior) point positions of the estimators (``EstimateSet.filtered``): the identity with the
posterior state mean, the gain over the raw measurements and the one-step predictions against the truth, partial
runs, the estimate file, and the truth errors of tracker.metrics on a real run."""

from dataclasses import replace

import numpy as np
import pytest

from heartcv.tracker import metrics as tm
from heartcv.tracker.io import read_estimates, write_estimates
from heartcv.tracker.joint import ESTIMATORS, run_joint
from heartcv.tracker.measurements import MeasurementSet
from heartcv.tracker.simulate import simulate, to_measurements
from heartcv.tracker.tracking import EstimationDiverged, locate_points, run_kalman


def _reconstructed(model, meas, state_mean):
    """reference + translation + H x_k|k of the kept points, (K, P, 3), NaN for dropped points and NaN rows."""
    pts = locate_points(model, meas)
    obs = pts.observation
    K = meas.n_frames
    out = np.full((K, meas.n_points, 3), np.nan)
    out[:, pts.keep] = (obs.reference[None] + meas.translation()[:, None, :]
                        + (np.asarray(state_mean) @ obs.H.T).reshape(K, -1, 3))
    return out


@pytest.fixture(scope="module")
def kf_run(paper_model):
    """2 s of `heartcv model simulate` data (process, initial and measurement noise; 20 % of the points unseen
    per frame) tracked by the KF with the true parameters. Process noise matters: without it the prediction
    from the exact prior is the truth itself (to 1e-10 m) and no update can improve on it."""
    sim = simulate(paper_model, 2.0, np.random.default_rng(4), missing_fraction=0.2)
    meas = to_measurements(sim)
    return sim, meas, run_kalman(paper_model, meas)


def test_kf_filtered_is_the_posterior_mean_on_the_points(paper_model, kf_run):
    sim, meas, est = kf_run
    assert est.filtered.shape == (meas.n_frames, meas.n_points, 3)
    np.testing.assert_allclose(est.filtered, _reconstructed(paper_model, meas, est.state_mean), rtol=0,
                               atol=1e-12)
    assert np.isfinite(est.filtered).all()  # every point of the paper patch lies on it, seen or not


def test_kf_filtered_beats_the_measurements_and_the_predictions(kf_run):
    sim, meas, est = kf_run
    seen = np.isfinite(meas.positions).all(axis=-1)
    seen[0] = False  # k >= 1: frame 0 is the prior, predicted or corrected by one frame
    assert 0.6 * seen.size < seen.sum() < 0.9 * seen.size

    def err(pos):
        return np.linalg.norm(pos - sim.positions, axis=-1)[seen]

    e_f, e_p, e_y = err(est.filtered), err(est.predictions), err(meas.positions)
    # measured: the measurements 0.161 mm (sigma * sqrt(8 / pi) = 0.160 mm), filtered 0.0313, predicted 0.0320 mm
    assert e_f.mean() < 0.25 * e_y.mean()
    assert e_f.mean() < e_p.mean()
    assert np.sqrt(np.mean(e_f**2)) < np.sqrt(np.mean(e_p**2))
    # the measured position is prediction + innovation
    np.testing.assert_allclose((est.predictions + est.innovations)[seen], meas.positions[seen], rtol=0, atol=1e-15)


def test_kf_truth_metrics_against_independent_numbers(kf_run):
    """estimator_metrics on a real run: filtered and predicted truth errors over the seen (k, p), k >= 1, and
    the measurements' own error (prediction + innovation) against the simulation's exact positions."""
    sim, meas, est = kf_run
    seen = np.isfinite(meas.positions).all(axis=-1)
    m = tm.estimator_metrics(est, sim.positions)
    e_f = np.linalg.norm(est.filtered - sim.positions, axis=-1)
    e_p = np.linalg.norm(est.predictions - sim.positions, axis=-1)
    assert m["truth_error_mean_m"] == pytest.approx(e_f[1:][seen[1:]].mean(), rel=1e-12)
    assert m["truth_error_std_m"] == pytest.approx(e_f[1:][seen[1:]].std(), rel=1e-12)
    assert m["truth_error_rms_m"] == pytest.approx(np.sqrt(np.mean(e_f[1:][seen[1:]] ** 2)), rel=1e-12)
    assert m["prediction_truth_error_mean_m"] == pytest.approx(e_p[1:][seen[1:]].mean(), rel=1e-12)
    assert m["prediction_truth_error_rms_m"] == pytest.approx(np.sqrt(np.mean(e_p[1:][seen[1:]] ** 2)), rel=1e-12)
    k = 5
    assert m["per_step"]["truth_error_mean"][k] == pytest.approx(e_f[k][seen[k]].mean(), rel=1e-12)
    assert m["per_step"]["prediction_truth_error_mean"][k] == pytest.approx(e_p[k][seen[k]].mean(), rel=1e-12)
    assert m["per_step"]["truth_error_var"][k] == pytest.approx(e_f[k][seen[k]].var(), rel=1e-10)
    e_y = np.linalg.norm(meas.positions - sim.positions, axis=-1)  # NaN where not seen
    np.testing.assert_allclose(tm.measurement_truth_error_norms(est, sim.positions), e_y, rtol=1e-9)
    assert m["truth_error_mean_m"] < m["prediction_truth_error_mean_m"] < np.nanmean(e_y[1:])


@pytest.fixture(scope="module")
def short_meas(paper_model):
    """6 frames (0.17 s) with noise, for the joint estimators."""
    return to_measurements(simulate(paper_model, 5 / 30, np.random.default_rng(21), missing_fraction=0.2))


@pytest.mark.parametrize("name", ESTIMATORS)
def test_joint_filtered_is_the_posterior_kinematic_block(paper_model, short_meas, name):
    est = run_joint(paper_model, short_meas, name)
    assert est.complete and est.filtered.shape == (6, short_meas.n_points, 3)
    np.testing.assert_allclose(est.filtered, _reconstructed(paper_model, short_meas, est.state_mean), rtol=0,
                               atol=1e-12)
    # the update moves the estimate off the prediction towards the seen measurements
    assert not np.allclose(est.filtered[1:], est.predictions[1:], rtol=0, atol=1e-9)


def test_partial_joint_run_carries_the_filtered_steps_done(paper_model, short_meas):
    pos = short_meas.positions.copy()
    pos[2:] += 1e10  # absurd from frame 2: the runaway check stops the update of frame 2
    bad = MeasurementSet(short_meas.times, short_meas.point_ids, pos, short_meas.covariances,
                         short_meas.reference, short_meas.inputs, short_meas.input_names, short_meas.input_units)
    with pytest.raises(EstimationDiverged) as info:
        run_joint(paper_model, bad, "ge")
    part = info.value.partial
    assert part.completed_steps == 2 and part.filtered is not None
    np.testing.assert_allclose(part.filtered[:2], _reconstructed(paper_model, bad, part.state_mean)[:2], rtol=0,
                               atol=1e-12)
    assert np.isfinite(part.filtered[:2]).all() and np.isnan(part.filtered[2:]).all()


def test_dropped_points_have_no_filtered_position(paper_model, kf_run):
    """A point off the patch is dropped: NaN in filtered, like its prediction."""
    _, meas, _ = kf_run
    ref = meas.reference.copy()
    ref[3, 0] += 1.0  # 1 m off along s
    moved = MeasurementSet(meas.times[:4], meas.point_ids, meas.positions[:4], meas.covariances[:4], ref,
                           meas.inputs[:4], meas.input_names, meas.input_units)
    est = run_kalman(paper_model, moved)
    assert est.meta["dropped_points"] == [3]
    assert np.isnan(est.filtered[:, 3]).all() and np.isnan(est.predictions[:, 3]).all()
    keep = np.arange(meas.n_points) != 3
    np.testing.assert_allclose(est.filtered[:, keep], _reconstructed(paper_model, moved, est.state_mean)[:, keep],
                               rtol=0, atol=1e-12)


def test_estimate_file_round_trips_filtered(tmp_path, kf_run):
    _, _, est = kf_run
    write_estimates(tmp_path / "kf.npz", est)
    back = read_estimates(tmp_path / "kf.npz")
    np.testing.assert_array_equal(back.filtered, est.filtered)
    np.testing.assert_array_equal(back.predictions, est.predictions)
    # a file written before filtered was recorded reads with filtered None; its truth error is undefined
    old = replace(est, filtered=None)
    write_estimates(tmp_path / "old.npz", old)
    with np.load(tmp_path / "old.npz") as z:
        assert "filtered" not in z.files and "predictions" in z.files
    back = read_estimates(tmp_path / "old.npz")
    assert back.filtered is None
    truth = back.predictions  # any finite truth
    m = tm.estimator_metrics(back, truth)
    assert np.isnan(m["truth_error_mean_m"]) and m["prediction_truth_error_mean_m"] == 0.0
    with pytest.raises(ValueError, match="filtered"):
        replace(est, filtered=est.filtered[:, :3])


def test_estimate_file_with_bad_times_or_negative_counts_is_refused(tmp_path, kf_run):
    """Frame times that do not increase, and a negative NIS degree of freedom or truncation count: exit-2 errors
    naming the file and the array (both were read and reported)."""
    from heartcv.tracker.files import InputError

    _, _, est = kf_run
    write_estimates(tmp_path / "kf.npz", est)
    with np.load(tmp_path / "kf.npz") as z:
        arrays = {k: z[k] for k in z.files}
    import json

    meta = json.loads(bytes(arrays["meta_json"]).decode())
    np.savez(tmp_path / "bad_software.npz", **dict(arrays, meta_json=np.frombuffer(
        json.dumps(dict(meta, software=5)).encode(), np.uint8)))
    with pytest.raises(InputError) as exc:     # (the fuzz: report's software line failed on it)
        read_estimates(tmp_path / "bad_software.npz")
    assert exc.value.field == "meta.software"
    for key, edit in (("times", lambda a: a[::-1].copy()), ("nis_dof", lambda a: a - 10 ** 6),
                      ("truncation_events", lambda a: a - 1), ("theta_std", lambda a: -a - 1),
                      ("step_time", lambda a: a - 10.0), ("nis", lambda a: np.where(np.isnan(a), a, -1.0)),
                      ("state_var", lambda a: -a - 1),
                      # a prediction removed where its innovation stays (the audit's edited file: accepted, its
                      # ratio to hold then over the easier observations)
                      ("innovations", None)):
        if edit is None:
            pred = arrays["predictions"].copy()
            pred[3, 1] = np.nan
            bad = dict(arrays, predictions=pred)
            np.savez(tmp_path / f"bad_{key}.npz", **bad)
            with pytest.raises(InputError, match="frame 3, point 1: an innovation where the prediction is NaN"):
                read_estimates(tmp_path / f"bad_{key}.npz")
            continue
        bad = dict(arrays, **{key: edit(arrays[key])})
        np.savez(tmp_path / f"bad_{key}.npz", **bad)
        with pytest.raises(InputError) as exc:
            read_estimates(tmp_path / f"bad_{key}.npz")
        assert exc.value.field == key and str(tmp_path / f"bad_{key}.npz") in str(exc.value)
    # meta a person edited: a noise level that is not a length, held-out ids the file does not hold
    ids = arrays["point_ids"].tolist()
    for field, value in (("measurement_noise_m", "x"), ("measurement_noise_m", -1.0), ("measurement_noise_m", 1e300),
                         ("heldout_points", [max(ids) + 1])):
        np.savez(tmp_path / "bad_meta.npz", **dict(arrays, meta_json=np.frombuffer(
            json.dumps(dict(meta, **{field: value})).encode(), np.uint8)))
        with pytest.raises(InputError) as exc:
            read_estimates(tmp_path / "bad_meta.npz")
        assert exc.value.field == f"meta.{field}", (field, value)
    np.savez(tmp_path / "ok_meta.npz", **dict(arrays, meta_json=np.frombuffer(json.dumps(dict(
        meta, measurement_noise_m=2e-4, heldout_points=ids[:2])).encode(), np.uint8)))
    assert read_estimates(tmp_path / "ok_meta.npz").meta["measurement_noise_m"] == 2e-4
