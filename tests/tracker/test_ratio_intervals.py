"""Bootstrap intervals of error ratios (tracker.metrics.optimal_block_length, paired_ratio_interval, and their
use in compare_runs).

Oracles: the closed-form optimal block length of an AR(1) series (Politis & White 2004); the coverage of the
interval in a Monte Carlo study with a known ratio (fixed seed), against the i.i.d. bootstrap (blocks of one
frame), which must under-cover on correlated frames; a block of the whole sequence, whose resamples are
rotations and so give the ratio exactly; brute-force sums over the common observations.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from heartcv.tracker.metrics import compare_runs, error_norms, optimal_block_length, paired_ratio_interval


def _ar1(n, phi, rng):
    e = rng.standard_normal(n + 200) * np.sqrt(1.0 - phi * phi)
    x = np.zeros_like(e)
    for i in range(1, e.size):
        x[i] = phi * x[i - 1] + e[i]
    return x[200:]


@pytest.mark.parametrize("phi", [0.5, 0.8])
def test_block_length_of_an_ar1_series_matches_the_closed_form(phi):
    """b = (6 phi^2 / (1 - phi^2)^2)^(1/3) n^(1/3) for the circular block bootstrap of an AR(1) mean."""
    n = 20000
    theory = (6.0 * phi ** 2 / (1.0 - phi ** 2) ** 2) ** (1.0 / 3.0) * n ** (1.0 / 3.0)
    est = [optimal_block_length(_ar1(n, phi, np.random.default_rng(s))) for s in range(4)]
    assert np.mean(est) == pytest.approx(theory, rel=0.12)


def test_block_length_of_white_noise_is_short_and_bounded():
    rng = np.random.default_rng(1)
    assert np.mean([optimal_block_length(rng.standard_normal(5000)) for _ in range(5)]) < 3.0
    assert optimal_block_length(np.ones(50)) == 1.0                          # no variance: no dependence to keep
    assert optimal_block_length(np.cumsum(rng.standard_normal(300))) <= 300 / 3  # capped at n / 3


def _pair(rng, K=300, P=20, phi=0.9):
    """Errors of two runs sharing a slowly varying frame effect; E a / E b = 1 / 1.2; 20 % of a missing."""
    u, v = _ar1(K, phi, rng), _ar1(K, phi, rng)
    a = 1.0 + 0.3 * u[:, None] + 0.1 * rng.standard_normal((K, P))
    b = 1.2 + 0.3 * (0.6 * u + 0.8 * v)[:, None] + 0.1 * rng.standard_normal((K, P))
    a[rng.random((K, P)) < 0.2] = np.nan
    return a, b


def test_ratio_is_the_brute_force_ratio_over_common_observations():
    rng = np.random.default_rng(3)
    a, b = _pair(rng, K=40, P=5)
    b[3, :] = np.nan
    ci = paired_ratio_interval(a, b, np.random.default_rng(0), resamples=200)
    total_a = total_b = 0.0
    n = 0
    for k in range(40):
        for p in range(5):
            if np.isfinite(a[k, p]) and np.isfinite(b[k, p]):
                total_a, total_b, n = total_a + a[k, p], total_b + b[k, p], n + 1
    assert ci["ratio"] == pytest.approx(total_a / total_b, rel=1e-13)
    assert ci["observations"] == n and ci["frames"] == 40 and ci["resamples"] == 200
    assert ci["low"] <= ci["ratio"] <= ci["high"]


def test_a_block_of_the_whole_sequence_resamples_rotations_only():
    a, b = _pair(np.random.default_rng(4), K=50, P=4)
    ci = paired_ratio_interval(a, b, np.random.default_rng(0), block=50, resamples=300)
    assert ci["block_frames"] == 50
    assert ci["low"] == pytest.approx(ci["ratio"], rel=1e-12) and ci["high"] == pytest.approx(ci["ratio"], rel=1e-12)


def test_same_seed_same_interval_and_another_seed_another():
    a, b = _pair(np.random.default_rng(5))
    one = paired_ratio_interval(a, b, np.random.default_rng(7))
    assert one == paired_ratio_interval(a, b, np.random.default_rng(7))
    other = paired_ratio_interval(a, b, np.random.default_rng(8))
    assert other["ratio"] == one["ratio"] and (other["low"], other["high"]) != (one["low"], one["high"])


def test_coverage_of_a_known_ratio_and_the_iid_bootstrap_under_covers():
    """150 replications (fixed seed) of 300 frames whose errors share an AR(1) frame effect (phi 0.9): the 95 %
    interval with the automatic block (median 23 frames) covers the true 1/1.2 in 0.85 of them (measured; block
    bootstraps under-cover somewhat when the dependence is this long against the series), the i.i.d. bootstrap
    of frames in 0.35."""
    rng = np.random.default_rng(42)
    hits = {"auto": 0, "iid": 0}
    for _ in range(150):
        a, b = _pair(rng)
        for key, block in (("auto", None), ("iid", 1)):
            ci = paired_ratio_interval(a, b, rng, block=block, resamples=500)
            hits[key] += ci["low"] <= 1.0 / 1.2 <= ci["high"]
    assert 0.80 <= hits["auto"] / 150 <= 0.99
    assert hits["iid"] / 150 <= 0.6


def test_bad_arguments_and_nothing_in_common():
    rng = np.random.default_rng(0)
    a = np.ones((10, 3))
    with pytest.raises(ValueError, match="one shape"):
        paired_ratio_interval(a, np.ones((10, 4)), rng)
    with pytest.raises(ValueError, match="at least 100"):
        paired_ratio_interval(a, a, rng, resamples=50)
    with pytest.raises(ValueError, match="block"):
        paired_ratio_interval(a, a, rng, block=0.5)
    assert paired_ratio_interval(a, np.full((10, 3), np.nan), rng) is None
    assert paired_ratio_interval(a, np.zeros((10, 3)), rng) is None


# -- in compare_runs ----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def runs(paper_model):
    """A KF, a GE-labelled copy with other innovations and a hold baseline over one simulated measurement file,
    two points held out."""
    from heartcv.tracker.baselines import run_baseline
    from heartcv.tracker.simulate import simulate, to_measurements
    from heartcv.tracker.tracking import run_kalman

    meas = to_measurements(simulate(paper_model, 3.0, np.random.default_rng(2)))
    kf = run_kalman(paper_model, meas)
    hold = run_baseline("hold", meas)
    held = [int(kf.point_ids[0]), int(kf.point_ids[3])]
    scale = 1.0 + 0.2 * np.random.default_rng(9).random(kf.innovations.shape[:2])
    ge = dataclasses.replace(kf, innovations=kf.innovations * scale[..., None])
    return {label: dataclasses.replace(est, meta=dict(est.meta, heldout_points=held))
            for label, est in (("ge", ge), ("kf", kf), ("hold", hold))}


def test_compare_runs_intervals_against_brute_force(runs):
    res = compare_runs(runs, rng=np.random.default_rng(0), resamples=300)
    held = np.isin(runs["kf"].point_ids, runs["kf"].meta["heldout_points"])
    norms = {k: error_norms(np.asarray(e.innovations))[1:] for k, e in runs.items()}
    for label in ("ge", "kf"):
        for key, mask in (("ratio_to_hold_interval", ~held), ("heldout_ratio_to_hold_interval", held)):
            a, b = norms[label][:, mask], norms["hold"][:, mask]
            ok = np.isfinite(a) & np.isfinite(b)
            ci = res["per_run"][label][key]
            assert ci["ratio"] == pytest.approx(a[ok].sum() / b[ok].sum(), rel=1e-12)
            assert ci["low"] < ci["ratio"] < ci["high"] and ci["resamples"] == 300
    a, b = norms["ge"][:, ~held], norms["kf"][:, ~held]
    ok = np.isfinite(a) & np.isfinite(b)
    assert res["ratio_ge_to_kf_prediction_error_interval"]["ratio"] == pytest.approx(a[ok].sum() / b[ok].sum(),
                                                                                       rel=1e-12)
    assert res["per_run"]["hold"]["ratio_to_hold_interval"] is None
    plain = compare_runs(runs)
    assert plain["ratio_ge_to_kf_prediction_error_interval"] is None
    assert plain["per_run"]["ge"]["ratio_to_hold_interval"] is None
    assert plain["per_run"]["ge"]["prediction_error_mean_m"] == res["per_run"]["ge"]["prediction_error_mean_m"]


def test_runs_on_other_points_are_not_paired(runs):
    other = dataclasses.replace(runs["hold"], point_ids=runs["hold"].point_ids + 1000)
    res = compare_runs({"kf": runs["kf"], "hold": other}, rng=np.random.default_rng(0), resamples=200)
    assert res["per_run"]["kf"]["ratio_to_hold_interval"] is None


def test_runs_holding_out_other_tracks_are_not_paired(runs):
    """Another --holdout/--seed holds out other tracks: the two runs' errors are over other tracks (the audit's
    1.506 'held-out ratio' rested on the 10 % of held-out observations both draws shared)."""
    moved = [int(runs["kf"].point_ids[1])]
    other = dataclasses.replace(runs["hold"], meta=dict(runs["hold"].meta, heldout_points=moved))
    res = compare_runs({"kf": runs["kf"], "hold": other}, rng=np.random.default_rng(0), resamples=200,
                       fit_frames=10)
    kf = res["per_run"]["kf"]
    assert kf["ratio_to_hold_interval"] is None and kf["heldout_ratio_to_hold_interval"] is None
    assert kf["prediction_error_after_fit_ratio_to_hold"] is None


def test_an_interval_does_not_move_with_the_other_runs_given(runs):
    """Each pair resamples from its own stream: ge / hold's interval is the same with or without the kf run (it
    moved with the files given when one stream served every pair in turn); another seed moves it."""
    both = compare_runs(runs, rng=np.random.default_rng(5), resamples=200)
    alone = compare_runs({"ge": runs["ge"], "hold": runs["hold"]}, rng=np.random.default_rng(5), resamples=200)
    assert both["per_run"]["ge"]["ratio_to_hold_interval"] == alone["per_run"]["ge"]["ratio_to_hold_interval"]
    other = compare_runs({"ge": runs["ge"], "hold": runs["hold"]}, rng=np.random.default_rng(6), resamples=200)
    assert other["per_run"]["ge"]["ratio_to_hold_interval"]["low"] != alone["per_run"]["ge"][
        "ratio_to_hold_interval"]["low"]


def test_after_fit_ratio_to_hold_is_over_the_observations_both_predicted(runs):
    """prediction_error_after_fit_ratio_to_hold: brute force over k >= N of the used observations both runs
    predicted; a track's first sighting (hold has no prediction there) is left out of the run's side too."""
    n = 12
    est = runs["ge"]
    hold = runs["hold"]
    first_seen = np.array(hold.innovations, float)
    first_seen[n + 2, 4] = np.nan               # hold without a prediction where ge has one
    hold = dataclasses.replace(hold, innovations=first_seen)
    res = compare_runs({"ge": est, "hold": hold}, fit_frames=n)
    held = np.isin(est.point_ids, est.meta["heldout_points"])
    a = error_norms(np.asarray(est.innovations))[n:, ~held]
    b = error_norms(first_seen)[n:, ~held]
    ok = np.isfinite(a) & np.isfinite(b)
    assert np.isfinite(a).sum() == ok.sum() + 1
    ratio = res["per_run"]["ge"]["prediction_error_after_fit_ratio_to_hold"]
    assert ratio == pytest.approx(a[ok].mean() / b[ok].mean(), rel=1e-12)
    assert ratio != pytest.approx(np.nanmean(a) / np.nanmean(b), rel=1e-9)
    assert compare_runs({"ge": est, "hold": hold})["per_run"]["ge"]["prediction_error_after_fit_ratio_to_hold"] is None


def test_missing_predictions_are_counted_on_either_side():
    a = np.ones((20, 4))
    b = np.ones((20, 4)) * 2
    a[3, 1] = a[4, 2] = np.nan
    b[7, 0] = np.nan
    ci = paired_ratio_interval(a, b, np.random.default_rng(0), resamples=100)
    assert ci["numerator_missing"] == 2 and ci["denominator_missing"] == 1 and ci["observations"] == 77


def test_runs_of_other_measurement_files_are_not_paired(runs):
    """report --allow-mixed lets runs of other recordings into one report; their observations are not the same
    (the audit's 'paired' 0.526 between two recordings): no ratio."""
    other = dataclasses.replace(runs["hold"], meta=dict(runs["hold"].meta,
                                                        inputs_hash={"measurements": "sha256:other"}))
    ge = dataclasses.replace(runs["ge"], meta=dict(runs["ge"].meta, inputs_hash={"measurements": "sha256:this"}))
    res = compare_runs({"ge": ge, "hold": other}, rng=np.random.default_rng(0), resamples=200, fit_frames=10)
    assert res["per_run"]["ge"]["ratio_to_hold_interval"] is None
    assert res["per_run"]["ge"]["prediction_error_after_fit_ratio_to_hold"] is None
    same = dataclasses.replace(other, meta=dict(other.meta, inputs_hash={"measurements": "sha256:this"}))
    assert compare_runs({"ge": ge, "hold": same}, rng=np.random.default_rng(0),
                        resamples=200)["per_run"]["ge"]["ratio_to_hold_interval"] is not None
