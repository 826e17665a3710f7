"""heartcv.tracker.metrics: exact values on tiny hand-made estimate sets, chi-square bands against scipy.stats, truth
errors, partial runs and the sequence comparison."""

import numpy as np
import pytest
from scipy import stats

from heartcv.tracker import metrics as tm
from heartcv.tracker.measurements import EstimateSet
from heartcv.tracker.params import NAMES

NAN = np.nan


def _est(innovations, *, predictions=None, filtered=None, nis=None, dof=None, step_time=None, theta=None,
         theta_std=None, completed=None, times=None, point_ids=None, meta=None, estimator="kf"):
    e = np.asarray(innovations, float)
    K, P = e.shape[:2]
    return EstimateSet(
        estimator, np.arange(K) * 0.1 if times is None else times, np.arange(P) if point_ids is None else point_ids,
        np.zeros((K, 2)), np.zeros((K, 2)),
        np.tile([1050.0, 2.39, 0.003, 1.5e5, 0.45], (K, 1)) if theta is None else theta,
        np.zeros((K, 5)) if theta_std is None else theta_std,
        np.zeros((K, P, 3)) if predictions is None else predictions, e,
        np.full(K, 42.0) if nis is None else np.asarray(nis, float),
        np.full(K, 42) if dof is None else np.asarray(dof), np.zeros(K, np.int64),
        np.full(K, 1e-3) if step_time is None else np.asarray(step_time, float),
        K if completed is None else completed, meta or {}, filtered=filtered)


# three steps, two points; norms 5/NaN, 3/4 (hand: 3-4-0 and 0-0-3, 0-4-0 ...), 1/1
E1 = np.array([
    [[3.0, 4.0, 0.0], [NAN, NAN, NAN]],   # k = 0: norms 5, unseen
    [[0.0, 0.0, 3.0], [0.0, 4.0, 0.0]],   # k = 1: norms 3, 4
    [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]],  # k = 2: norms 1, 1
]) * 1e-4


def test_error_norms_and_per_step_stats_exact():
    n = tm.error_norms(E1)
    np.testing.assert_allclose(n, np.array([[5, NAN], [3, 4], [1, 1]]) * 1e-4, rtol=1e-15)
    mean, var, count = tm.per_step_stats(n)
    np.testing.assert_allclose(mean, np.array([5, 3.5, 1]) * 1e-4, rtol=1e-15)
    np.testing.assert_allclose(var, np.array([0, 0.25, 0]) * 1e-8, rtol=1e-12, atol=1e-24)
    np.testing.assert_array_equal(count, [1, 2, 2])
    mean, var, count = tm.per_step_stats(np.full((2, 3), NAN))
    assert np.isnan(mean).all() and np.isnan(var).all() and (count == 0).all()
    with pytest.raises(ValueError, match=r"\(K, P\)"):
        tm.per_step_stats(np.zeros(3))


def test_estimator_metrics_prediction_error_exact():
    est = _est(E1)
    m = tm.estimator_metrics(est)
    # steps k >= 1: norms 3, 4, 1, 1 (x 1e-4 m)
    assert m["prediction_error_mean_m"] == pytest.approx(2.25e-4, rel=1e-14)
    assert m["prediction_error_std_m"] == pytest.approx(np.sqrt((0.75**2 + 1.75**2 + 2 * 1.25**2) / 4) * 1e-4,
                                                        rel=1e-14)
    assert m["prediction_error_rms_m"] == pytest.approx(np.sqrt(27 / 4) * 1e-4, rel=1e-14)
    assert m["prediction_error_rms_m"] == pytest.approx(est.prediction_rmse(), rel=1e-14)
    assert m["prediction_error_count"] == 4 and m["completed_steps"] == 3
    assert np.isnan(m["truth_error_mean_m"]) and np.isnan(m["per_step"]["truth_error_mean"]).all()
    assert np.isnan(m["prediction_truth_error_mean_m"]) and np.isnan(m["per_step"]["prediction_truth_error_mean"]).all()
    np.testing.assert_allclose(m["per_step"]["error_mean"], np.array([5, 3.5, 1]) * 1e-4, rtol=1e-15)
    assert m["theta_final"] == dict(zip(NAMES, [1050.0, 2.39, 0.003, 1.5e5, 0.45]))
    assert m["theta_std_final"] == dict.fromkeys(NAMES, 0.0)


def test_truth_errors_exact():
    """Filtered and predicted positions against the truth over the seen (k, p) of E1 (step 0: point 1 unseen),
    overall over k >= 1; the measurements (prediction + innovation) over the same observations."""
    truth = np.zeros((3, 2, 3))
    pred = np.zeros((3, 2, 3))
    pred[0] = [[9.0, 0, 0], [0, 0, 0]]          # step 0 is left out of the overall numbers
    pred[1] = [[0, 3.0, 4.0], [0, 0, 2.0]]      # norms 5, 2
    pred[2] = [[0, 0, 0], [6.0, 8.0, 0]]        # norms 0, 10
    filt = np.zeros((3, 2, 3))
    filt[0] = [[0, 0, 1.0], [0, 7.0, 0]]        # norms 1, (7: point 1 unseen at step 0)
    filt[1] = [[2.0, 0, 0], [0, 0, 0]]          # norms 2, 0
    filt[2] = [[0, 0, 3.0], [0, 4.0, 0]]        # norms 3, 4
    truth[:] = [1.0, 2.0, 3.0]                  # a common offset: errors are differences
    pred = (pred + truth) * 1e-3
    filt = (filt + truth) * 1e-3
    truth = truth * 1e-3
    np.testing.assert_allclose(tm.truth_error_norms(pred, truth), np.array([[9, 0], [5, 2], [0, 10]]) * 1e-3,
                               rtol=1e-12, atol=1e-18)
    est = _est(E1, predictions=pred, filtered=filt)
    m = tm.estimator_metrics(est, truth)
    # filtered, k >= 1: norms 2, 0, 3, 4
    assert m["truth_error_mean_m"] == pytest.approx(9 / 4 * 1e-3, rel=1e-12)
    assert m["truth_error_rms_m"] == pytest.approx(np.sqrt(29 / 4) * 1e-3, rel=1e-12)
    assert m["truth_error_std_m"] == pytest.approx(np.sqrt((0.25**2 + 2.25**2 + 0.75**2 + 1.75**2) / 4) * 1e-3,
                                                   rel=1e-12)
    np.testing.assert_allclose(m["per_step"]["truth_error_mean"], np.array([1, 1, 3.5]) * 1e-3, rtol=1e-12)
    np.testing.assert_allclose(m["per_step"]["truth_error_var"], np.array([0, 1, 0.25]) * 1e-6, rtol=1e-10,
                               atol=1e-20)
    # predicted, k >= 1: norms 5, 2, 0, 10; step 0 only point 0 (seen)
    assert m["prediction_truth_error_mean_m"] == pytest.approx(17 / 4 * 1e-3, rel=1e-12)
    assert m["prediction_truth_error_rms_m"] == pytest.approx(np.sqrt(129 / 4) * 1e-3, rel=1e-12)
    np.testing.assert_allclose(m["per_step"]["prediction_truth_error_mean"], np.array([9, 3.5, 5]) * 1e-3,
                               rtol=1e-12)
    np.testing.assert_allclose(m["per_step"]["prediction_truth_error_var"], np.array([0, 2.25, 25]) * 1e-6,
                               rtol=1e-10, atol=1e-20)
    # the measurements: prediction + innovation against the truth, NaN where not seen
    meas = pred + E1
    np.testing.assert_allclose(tm.measurement_truth_error_norms(est, truth),
                               np.linalg.norm(meas - truth, axis=-1), rtol=1e-12)
    assert np.isnan(tm.measurement_truth_error_norms(est, truth)[0, 1])
    # an unseen point is left out, however good its estimate
    e = E1.copy()
    e[1, 1] = NAN
    m = tm.estimator_metrics(_est(e, predictions=pred, filtered=filt), truth)
    assert m["truth_error_mean_m"] == pytest.approx(9 / 3 * 1e-3, rel=1e-12)
    assert m["prediction_truth_error_mean_m"] == pytest.approx(15 / 3 * 1e-3, rel=1e-12)
    # no filtered positions in the file (written before they were recorded): no truth error of the estimate
    m = tm.estimator_metrics(_est(E1, predictions=pred), truth)
    assert np.isnan(m["truth_error_mean_m"]) and np.isnan(m["per_step"]["truth_error_mean"]).all()
    assert m["prediction_truth_error_mean_m"] == pytest.approx(17 / 4 * 1e-3, rel=1e-12)
    with pytest.raises(ValueError, match="one shape"):
        tm.truth_error_norms(pred[:2], truth)
    with pytest.raises(ValueError, match="filtered"):
        _est(E1, filtered=filt[:2])


def test_nis_bands_against_scipy():
    lo, hi = tm.nis_step_band([42, 3, 0, 1], 0.95)
    assert lo[0] == pytest.approx(stats.chi2.ppf(0.025, 42), rel=1e-12)
    assert hi[1] == pytest.approx(stats.chi2.ppf(0.975, 3), rel=1e-12)
    assert np.isnan(lo[2]) and np.isnan(hi[2])
    assert hi[3] == pytest.approx(stats.chi2.ppf(0.975, 1), rel=1e-12)
    lo, hi = tm.nis_step_band([10], 0.9)
    assert (lo[0], hi[0]) == pytest.approx((stats.chi2.ppf(0.05, 10), stats.chi2.ppf(0.95, 10)), rel=1e-12)
    # the time average of n chi2(d_k): chi2(sum d) / n
    band = tm.nis_mean_band([42, 39, 42])
    assert band == pytest.approx((stats.chi2.ppf(0.025, 123) / 3, stats.chi2.ppf(0.975, 123) / 3), rel=1e-12)
    # equals the study's chi2_band for a constant dof
    from heartcv.tracker.study import chi2_band

    assert tm.nis_mean_band([6] * 5) == pytest.approx(chi2_band(5, 6), rel=1e-12)
    with pytest.raises(ValueError, match="dof >= 1"):
        tm.nis_mean_band([3, 0])
    with pytest.raises(ValueError, match="level"):
        tm.nis_step_band([3], 1.0)


def test_nis_statistics_exact():
    lo, hi = stats.chi2.ppf(0.025, 6), stats.chi2.ppf(0.975, 6)
    nis = [NAN, lo - 0.01, hi, 3.0, 50.0]   # step 0 nothing seen; bounds count as inside
    dof = [0, 6, 6, 6, 6]
    s = tm.nis_statistics(nis, dof)
    assert s["steps"] == 4
    assert s["mean"] == pytest.approx((lo - 0.01 + hi + 3 + 50) / 4, rel=1e-14)
    assert s["mean_dof"] == 6.0
    assert s["in_band_fraction"] == pytest.approx(0.5)
    assert s["mean_band"] == pytest.approx((stats.chi2.ppf(0.025, 24) / 4, stats.chi2.ppf(0.975, 24) / 4))
    none = tm.nis_statistics([NAN, NAN], [0, 0])
    assert none["steps"] == 0 and none["mean_band"] is None and np.isnan(none["mean"])


def test_step_time_statistics_exact():
    st = [0.5, 1.0, 2.0, 3.0, 4.0, 100.0]  # step 0 excluded
    s = tm.step_time_statistics(st)
    assert s["median"] == 3.0 and s["steps"] == 5
    # numpy's linear interpolation: position 0.95 * 4 = 3.8 between 4 and 100
    assert s["p95"] == pytest.approx(4.0 + 0.8 * 96.0, rel=1e-14)
    assert tm.step_time_statistics([0.25]) == {"median": 0.25, "p95": 0.25, "steps": 1}


def test_partial_run_uses_completed_steps_only():
    e = np.concatenate([E1, np.full((2, 2, 3), NAN)])
    nis = [40.0, 44.0, 42.0, NAN, NAN]
    theta = np.tile([1050.0, 2.39, 0.003, 1.5e5, 0.45], (5, 1))
    theta[2, 3] = 1.6e5
    theta[3:] = NAN
    st = [0.1, 0.2, 0.4, 0.0, 0.0]
    est = _est(e, nis=nis, dof=[42, 42, 42, 0, 0], step_time=st, theta=theta, completed=3)
    m = tm.estimator_metrics(est)
    assert m["completed_steps"] == 3 and m["prediction_error_mean_m"] == pytest.approx(2.25e-4, rel=1e-14)
    assert m["theta_final"]["E"] == 1.6e5
    assert m["nis_mean"] == pytest.approx(42.0) and m["nis_steps"] == 3
    assert m["step_time_median_s"] == pytest.approx(0.3) and len(m["per_step"]["times"]) == 3


def test_measurement_noise_level_exact():
    cov = np.full((2, 2, 3, 3), NAN)
    cov[0, 0] = np.diag([1.0, 2.0, 3.0]) * 1e-8     # trace/3 = 2e-8
    cov[1, 0] = np.eye(3) * 1e-8                    # 1e-8
    cov[1, 1] = np.diag([3.0, 6.0, 3.0]) * 1e-8     # 4e-8
    assert tm.measurement_noise_level(cov) == pytest.approx(np.sqrt(7e-8 / 3), rel=1e-14)
    seen = np.array([[True, False], [False, True]])
    assert tm.measurement_noise_level(cov, seen) == pytest.approx(np.sqrt(3e-8), rel=1e-14)
    assert np.isnan(tm.measurement_noise_level(np.full((1, 1, 3, 3), NAN)))
    # mean norm of N(0, s^2 I3): the chi(3) distribution's mean times s
    assert tm.mean_noise_norm(1e-4) == pytest.approx(stats.chi(3).mean() * 1e-4, rel=1e-12)


def test_sequence_mismatch():
    a = _est(E1, meta={"inputs_hash": {"measurements": "sha256:aa"}})
    assert tm.sequence_mismatch(a, _est(E1)) is None
    assert tm.sequence_mismatch(a, _est(E1, meta={"inputs_hash": {"measurements": "sha256:aa"}})) is None
    assert "frames" in tm.sequence_mismatch(a, _est(E1[:2]))
    assert "times" in tm.sequence_mismatch(a, _est(E1, times=np.arange(3) * 0.2))
    assert "point ids" in tm.sequence_mismatch(a, _est(E1, point_ids=[5, 6]))
    assert "point ids" in tm.sequence_mismatch(a, _est(E1[:, :1]))
    assert "inputs_hash" in tm.sequence_mismatch(a, _est(E1, meta={"inputs_hash": {"measurements": "sha256:bb"}}))


# -- theta_truth_agreement (issue 15) ------------------------------------------------------------------------------
def test_theta_truth_agreement_matches_scipy_and_a_count():
    from scipy.stats import pearsonr

    from heartcv.tracker.metrics import theta_truth_agreement

    rng = np.random.default_rng(3)
    K = 200
    t = np.arange(K) / 60.0
    truth = np.tile([1070.0, 2.39, 0.003, 2e5, 0.47], (K, 1))
    truth[:, 3] = 2e5 * (1 + 0.8 * np.clip(np.sin(2 * np.pi * t), 0, None))
    sd = np.zeros((K, 5))
    sd[:, 3] = 2e4
    est = truth.copy()
    est[:, 3] += rng.normal(0, 2e4, K)
    est[0, 3] = np.nan                                        # step 0 is left out anyway
    out = theta_truth_agreement(est, sd, truth, ["E", "nu"])
    r_ref = pearsonr(est[1:, 3], truth[1:, 3]).statistic
    assert out["correlation"]["E"] == pytest.approx(r_ref, rel=1e-12)
    inside = sum(abs(est[k, 3] - truth[k, 3]) <= 2 * sd[k, 3] for k in range(1, K))
    assert out["coverage_2sigma"]["E"] == pytest.approx(inside / (K - 1), abs=0)
    # nu: both constant -> correlation undefined; std 0 and exact -> always covered
    assert out["correlation"]["nu"] is None
    assert out["coverage_2sigma"]["nu"] == 1.0


def test_theta_truth_agreement_sign_and_shorter_truth():
    from heartcv.tracker.metrics import theta_truth_agreement

    K = 50
    truth = np.tile([1.0, 1.0, 1.0, 1.0, 0.4], (K, 1))
    truth[:, 3] = np.linspace(1, 2, K)
    est = truth.copy()
    est[:, 3] = 3 - truth[:, 3]                               # anti-correlated
    sd = np.full((K, 5), 0.01)
    out = theta_truth_agreement(est, sd, truth[:30], ["E"])
    assert out["correlation"]["E"] == pytest.approx(-1.0, abs=1e-12)
    # truth inside +-2 sd only where |3 - 2 T| <= 0.02, i.e. T within 0.01 of 1.5: none of the first 30 steps
    assert out["coverage_2sigma"]["E"] == 0.0


def test_systole_mask_is_the_high_pressure_half():
    p = np.array([5.0, 10.0, 60.0, 100.0, 98.0, 52.6, 52.4, 6.0, np.nan, 5.0])   # range 5 .. 100: midpoint 52.5
    np.testing.assert_array_equal(tm.systole_mask(p), [0, 0, 1, 1, 1, 1, 0, 0, 0, 0])
    assert not tm.systole_mask(np.full(5, 7.0)).any()
    assert not tm.systole_mask(np.full(3, np.nan)).any()


# -- smooth_field_residual (issue 16: how much of the tracks' motion no smooth field explains) ---------------------
def _field_scene(seed=0, K=40, P=400, deform=True):
    """Points on a tilted plane moved by an affine map that changes every frame (a stretch, a shear, a tilt out of
    the plane and a translation, periodic): the displacement over any interval is an affine function of the
    earlier positions, which the polynomial fields hold exactly."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    uv = rng.uniform(-0.01, 0.01, (P, 2))
    Rm = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    X = np.column_stack([uv, np.zeros(P)]) @ Rm.T
    y = np.empty((K, P, 3))
    for k in range(K):
        a = np.sin(0.3 * k)
        M = np.eye(3) + deform * a * np.array([[0.05, 0.02, 0.0], [0.01, -0.03, 0.0], [0.04, 0.06, 0.0]])
        y[k] = (np.column_stack([uv, np.zeros(P)]) @ M.T) @ Rm.T + 1e-3 * np.array([a, 0.5 * a, -a])
    return rng, X, y


def test_smooth_field_residual_of_a_smooth_field_is_zero_and_of_noise_its_norm():
    from heartcv.tracker.metrics import mean_noise_norm, smooth_field_residual

    rng, X, y = _field_scene()
    for degree, lag in ((1, 1), (2, 1), (2, 7)):
        r = smooth_field_residual(y, degree=degree, lag=lag)
        assert np.isnan(r[:lag]).all() and np.nanmax(r[lag:]) < 1e-9 * np.abs(y - X).max()
    # points born at different frames (half of them at frame 10, at another phase of the motion): still zero, the
    # displacements are over the same interval
    late = y.copy()
    late[:10, 200:] = np.nan
    assert np.nanmax(smooth_field_residual(late, degree=1)[1:]) < 1e-9 * np.abs(y - X).max()
    sigma = 2e-5
    r = smooth_field_residual(y + sigma * rng.standard_normal(y.shape))
    # noise in both frames: sqrt(2) sigma sqrt(8/pi), less the 6 of 400 degrees of freedom the field takes per axis
    np.testing.assert_allclose(np.nanmean(r[1:]), np.sqrt(2) * mean_noise_norm(sigma), rtol=0.03)


def test_smooth_field_residual_sees_per_point_drift():
    """Each point drifts at its own constant velocity (random direction, 5 um per frame) on a translating plane: the
    residual over a lag of L frames is L times the mean norm of the velocities' spread about their mean (the field
    takes the mean), the same at every frame."""
    from heartcv.tracker.metrics import smooth_field_residual

    rng, X, y = _field_scene(seed=1, deform=False)
    v = 5e-6 * rng.standard_normal((X.shape[0], 3)) / np.sqrt(3)
    k = np.arange(y.shape[0])[:, None, None]
    expected = np.linalg.norm(v - v.mean(axis=0), axis=1).mean()
    for lag in (1, 5):
        r = smooth_field_residual(y + k * v[None], degree=1, lag=lag)
        np.testing.assert_allclose(r[lag:], lag * expected, rtol=0.03)
    with pytest.raises(ValueError, match="degree"):
        smooth_field_residual(y, degree=4)
    with pytest.raises(ValueError, match="lag"):
        smooth_field_residual(y, lag=0)
    with pytest.raises(ValueError, match="positions"):
        smooth_field_residual(y[0])
    # unseen points are allowed; too few points give NaN
    y2 = y.copy()
    y2[:, 50:] = np.nan
    assert np.isnan(smooth_field_residual(y2, min_points=60)).all()


def test_field_ar_prediction_is_exact_on_an_autoregressive_field_and_causal():
    """Points on a plane moving along its normal by a quadratic field whose coefficients are sums of two sinusoids
    (an exact AR(4) sequence): after the warm-up the AR(4) field predictor's error is ~0 and equals the oracle's,
    hold's is the displacement; frames after k do not change the prediction at k (causal); with noise of sigma the
    oracle leaves about sqrt(2) sigma sqrt(8/pi)."""
    from heartcv.tracker.metrics import field_ar_prediction, mean_noise_norm

    rng = np.random.default_rng(4)
    K, P = 120, 300
    uv = rng.uniform(-0.01, 0.01, (P, 2))
    basis = np.stack([np.ones(P), uv[:, 0] / 0.01, uv[:, 1] / 0.01, (uv[:, 0] / 0.01) ** 2,
                      uv[:, 0] * uv[:, 1] / 1e-4, (uv[:, 1] / 0.01) ** 2], axis=1)
    k = np.arange(K)
    a = (np.sin(2 * np.pi * 0.037 * k[:, None] + rng.uniform(0, 6, 6))
         + 0.5 * np.cos(2 * np.pi * 0.11 * k[:, None] + rng.uniform(0, 6, 6))) * rng.uniform(0.5, 1, 6) * 1e-4
    z = a @ basis.T                                              # (K, P)
    y = np.stack([np.broadcast_to(uv[:, 0], (K, P)), np.broadcast_to(uv[:, 1], (K, P)), z], axis=2)
    r = field_ar_prediction(y, order=4, ridge=0.0, start=40)
    assert np.isnan(r.predicted[:40]).all() and np.isfinite(r.predicted[40:]).all()
    assert np.nanmax(r.predicted) < 1e-5 * np.nanmean(r.hold) and np.nanmax(r.oracle) < 1e-9
    np.testing.assert_allclose(r.hold[40:], np.abs(z[40:] - z[39:-1]).mean(axis=1))
    assert r.ratio() < 1e-5
    cut = y.copy()
    cut[80:] += 1e-3 * rng.standard_normal(cut[80:].shape)      # the future changes: the past predictions do not
    r2 = field_ar_prediction(cut, order=4, ridge=0.0, start=40)
    np.testing.assert_array_equal(r2.predicted[:80], r.predicted[:80])
    # a penalty (the Cholesky solve of the normal equations accumulated frame by frame): as exact, as causal
    rr = field_ar_prediction(y, order=4, ridge=1e-10, start=40)
    assert np.nanmax(rr.predicted) < 1e-4 * np.nanmean(rr.hold)
    np.testing.assert_array_equal(field_ar_prediction(cut, order=4, ridge=1e-10, start=40).predicted[:80],
                                  rr.predicted[:80])
    sigma = 1e-5
    rn = field_ar_prediction(y + sigma * rng.standard_normal(y.shape), order=4, ridge=0.1, start=40)
    np.testing.assert_allclose(np.nanmean(rn.oracle), np.sqrt(2) * mean_noise_norm(sigma), rtol=0.05)
    with pytest.raises(ValueError, match="order"):
        field_ar_prediction(y, order=4, start=5)


def test_heldout_neighbour_oracle_exact_on_a_rigid_motion_and_noise_by_formula():
    """A rigidly translating cloud (points born at different frames): the neighbours' mean displacement is the held-
    out point's, error 0, while hold's is the per-frame step. A static cloud with white noise sigma: the oracle's
    error is sqrt(1 + 1/n) times hold's (the point's noise at birth and now, the n neighbours' mean), by Monte
    Carlo within 3 %."""
    from heartcv.tracker.metrics import heldout_neighbour_oracle

    rng = np.random.default_rng(6)
    K, P = 60, 300
    X = rng.uniform(-0.01, 0.01, (P, 3))
    step = 1e-4 * np.stack([np.sin(0.2 * np.arange(K)), np.cos(0.3 * np.arange(K)), np.zeros(K)], axis=1)
    y = X[None] + np.cumsum(step, axis=0)[:, None, :]
    y[:10, 150:] = np.nan                                   # half the points born at frame 10
    held = rng.random(P) < 0.1
    o, h = heldout_neighbour_oracle(y, held)
    assert o < 1e-12 * h and h > 1e-5
    np.testing.assert_array_equal(heldout_neighbour_oracle(y, np.flatnonzero(held)), (o, h))
    sigma, n = 1e-5, 4
    noisy = np.broadcast_to(X, (K, P, 3)) + sigma * rng.standard_normal((K, P, 3))
    o, h = heldout_neighbour_oracle(noisy, held, neighbours=n)
    np.testing.assert_allclose(o / h, np.sqrt(1 + 1 / n), rtol=0.03)
    with pytest.raises(ValueError, match="heldout"):
        heldout_neighbour_oracle(y, held[:10])


def test_fit_split_within_and_after_exact():
    # four steps, two points (x 1e-4 m): k = 0: 5, -; k = 1: 3, 4; k = 2: 1, 1; k = 3: 2, unseen
    e = np.concatenate([E1, [[[0.0, 2.0, 0.0], [NAN, NAN, NAN]]] * np.array(1e-4)])
    m = tm.estimator_metrics(_est(e), fit_frames=2)
    assert m["prediction_error_within_fit_mean_m"] == pytest.approx(3.5e-4, rel=1e-14)     # k = 1 only
    assert m["prediction_error_within_fit_count"] == 2
    assert m["prediction_error_after_fit_mean_m"] == pytest.approx(4e-4 / 3, rel=1e-14)    # k = 2, 3: 1, 1, 2
    assert m["prediction_error_after_fit_count"] == 3
    # continuing: seen at k - 1 too (k = 2: both points; k = 3: point 0)
    assert m["prediction_error_after_fit_continuing_mean_m"] == pytest.approx(4e-4 / 3, rel=1e-14)
    assert m["prediction_error_after_fit_continuing_count"] == 3
    gap = e.copy()
    gap[2, 0] = NAN                                   # point 0 unseen at k = 2: at k = 3 it re-appears
    g = tm.estimator_metrics(_est(gap), fit_frames=2)
    assert g["prediction_error_after_fit_count"] == 2 and g["prediction_error_after_fit_continuing_count"] == 1
    assert g["prediction_error_after_fit_continuing_mean_m"] == pytest.approx(1e-4, rel=1e-14)   # point 1, k = 2
    # a baseline has no prediction at a point's first measurement: its filtered (the measurement) says it was seen
    first = e.copy()
    first[1, 1] = NAN                                 # no innovation at k = 1 for point 1 ...
    filt = np.zeros_like(e)
    filt[0, 1] = NAN                                  # ... but measured there (filtered finite) for the baseline
    b = tm.estimator_metrics(_est(first, filtered=filt, meta={"baseline": True}), fit_frames=2)
    assert b["prediction_error_after_fit_continuing_count"] == 3
    k = tm.estimator_metrics(_est(first, filtered=filt), fit_frames=2)   # a model-based run: an innovation or none
    assert k["prediction_error_after_fit_continuing_count"] == 2
    assert m["heldout_prediction_error_after_fit_mean_m"] is None
    # point 1 held out: the split leaves it out of both parts and takes its own mean after the fit
    h = tm.estimator_metrics(_est(e, meta={"heldout_points": [1]}), fit_frames=2)
    assert h["prediction_error_within_fit_mean_m"] == pytest.approx(3e-4, rel=1e-14)
    assert h["prediction_error_after_fit_mean_m"] == pytest.approx(1.5e-4, rel=1e-14)
    assert h["heldout_prediction_error_after_fit_mean_m"] == pytest.approx(1e-4, rel=1e-14)
    # the parts pool back to the whole (counts weight the means)
    whole = tm.estimator_metrics(_est(e))
    pooled = (m["prediction_error_within_fit_mean_m"] * 2 + m["prediction_error_after_fit_mean_m"] * 3) / 5
    assert pooled == pytest.approx(whole["prediction_error_mean_m"], rel=1e-14)
    # no split: without fit_frames, or when the fit covers every completed step
    for n in (None, 4, 7, 0):
        s = tm.estimator_metrics(_est(e), fit_frames=n)
        assert s["prediction_error_after_fit_mean_m"] is None and s["prediction_error_within_fit_mean_m"] is None
    assert tm.compare_runs({"kf": _est(e)}, fit_frames=3)["per_run"]["kf"]["prediction_error_after_fit_count"] == 1


# -- the tracks' own heart rate in windows ---------------------------------------------------------------------------
def _beating(segments, fps=25.0, P=12, noise=2e-5, seed=0):
    """Tracks (K, P, 3) beating at a rate that steps between ``segments`` [(seconds, Hz), ...], phase continuous,
    with two harmonics per point and white noise."""
    rng = np.random.default_rng(seed)
    f = np.concatenate([np.full(int(round(d * fps)), hz) for d, hz in segments])
    t = np.arange(f.size) / fps
    phase = 2 * np.pi * np.cumsum(f) / fps
    y = np.zeros((t.size, P, 3))
    for h, a in ((1, 1.0), (2, 0.4)):
        ph = rng.uniform(0, 2 * np.pi, (P, 3))
        y += 1e-3 * a * rng.uniform(0.5, 1, (P, 3)) * np.cos(h * phase[:, None, None] + ph)
    return t, y + noise * rng.standard_normal(y.shape)


def test_windowed_heart_rate_follows_a_rate_that_changes():
    """Rate 1.0 Hz for 12 s, then 1.3 Hz for 12 s: the 6-s windows every 3 s lie inside one segment or straddle the
    step; those inside find their segment's rate within 0.5 % (measured within 0.05 %), with a standard error
    below 1 %; a window of noise alone shows no heartbeat and says why; a recording shorter than a window has
    none; frames with a point unseen still count."""
    t, y = _beating([(12.0, 1.0), (12.0, 1.3)])
    y[40:45, 3] = np.nan
    w = tm.windowed_heart_rate(t, y)
    assert [x["t_start_s"] for x in w] == pytest.approx([0, 3, 6, 9, 12, 15, 18])
    for x in w:
        if x["t_end_s"] <= 12.0 + 1e-9 or x["t_start_s"] >= 12.0 - 1e-9:
            true = 1.0 if x["t_end_s"] <= 12.0 + 1e-9 else 1.3
            assert x["frequency_hz"] == pytest.approx(true, rel=5e-3), x
            assert 0 < x["std_hz"] < 0.01 * true and x["reason"] is None
    rng = np.random.default_rng(1)
    quiet = tm.windowed_heart_rate(t[:150], 1e-4 * rng.standard_normal((150, 12, 3)))
    assert len(quiet) == 1 and quiet[0]["frequency_hz"] is None and "no periodic motion" in quiet[0]["reason"]
    assert tm.windowed_heart_rate(t[:100], y[:100]) == []
    with pytest.raises(ValueError):
        tm.windowed_heart_rate(t, y[:10])


def test_rate_agreement_against_hand_computation():
    """Two windows with rates and one without: the run's mean rate and mean standard deviation over each window's
    frames against the window's, |difference| <= 2 sqrt(s_run^2 + s_w^2)."""
    t = np.arange(0, 12, 0.5)
    mean = np.where(t < 6, 1.00, 1.10)
    std = np.full(t.size, 0.02)
    windows = [{"t_start_s": 0.0, "t_end_s": 6.0, "frequency_hz": 1.03, "std_hz": 0.01},        # 0.03 <= 0.0447
               {"t_start_s": 3.0, "t_end_s": 9.0, "frequency_hz": None, "std_hz": None},
               {"t_start_s": 6.0, "t_end_s": 12.0, "frequency_hz": 1.16, "std_hz": 0.01}]       # 0.06 > 0.0447
    a = tm.rate_agreement(windows, t, mean, std)
    assert a["windows"] == 2 and a["agree"] == 1 and a["z"] == 2.0
    assert a["mean_abs_difference_hz"] == pytest.approx(0.045) and a["max_abs_difference_hz"] == pytest.approx(0.06)
    assert tm.rate_agreement(windows, t, mean, std, z=3.0)["agree"] == 2
    assert tm.rate_agreement(windows[1:2], t, mean, std) is None
    assert tm.rate_agreement(windows, t + 100.0, mean, std) is None     # no window overlaps the run


def test_mean_noise_norm_of_covariances_against_closed_forms_and_monte_carlo():
    """E|v| of v ~ N(0, C): chi(3) sigma for C = sigma^2 I3, the Rayleigh mean sigma sqrt(pi/2) in a plane, the
    half-normal sigma sqrt(2/pi) on a line; an anisotropic stereo-like C (depth 10x lateral) against 2e6 draws
    (fixed seed), below sigma sqrt(8/pi) of its RMS per-coordinate sigma; NaN and unseen entries left out."""
    s = 1e-4
    f = tm.mean_noise_norm_of_covariances
    assert f(np.eye(3) * s * s) == pytest.approx(stats.chi(3).mean() * s, rel=2e-5)
    assert f(np.diag([s * s, s * s, 0.0])) == pytest.approx(s * np.sqrt(np.pi / 2), rel=2e-5)
    assert f(np.diag([s * s, 0.0, 0.0])) == pytest.approx(s * np.sqrt(2 / np.pi), rel=2e-5)
    rng = np.random.default_rng(11)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    c = q @ np.diag([1.0, 1.0, 100.0]) @ q.T * (0.016e-3) ** 2
    draws = rng.multivariate_normal(np.zeros(3), c, size=2_000_000)
    mc = np.linalg.norm(draws, axis=1)
    assert f(c) == pytest.approx(mc.mean(), abs=4 * mc.std() / np.sqrt(mc.size))
    sigma = tm.measurement_noise_level(c[None, None])
    assert f(c) < 0.9 * tm.mean_noise_norm(sigma)
    cov = np.full((2, 3, 3, 3), np.nan)
    cov[0, 0], cov[1, 2], cov[0, 1] = np.eye(3) * s * s, np.eye(3) * 4 * s * s, np.eye(3) * 9 * s * s
    seen = np.isfinite(cov).all(axis=(-2, -1))
    assert f(cov) == pytest.approx(stats.chi(3).mean() * s * (1 + 2 + 3) / 3, rel=2e-5)
    seen[0, 1] = False
    assert f(cov, seen) == pytest.approx(stats.chi(3).mean() * s * 1.5, rel=2e-5)
    assert np.isnan(f(np.full((1, 1, 3, 3), np.nan)))
