"""Held-out tracks (issue 16): left out of every update, predicted from the model alone, reported apart."""

import dataclasses

import numpy as np
import pytest

from heartcv.tracker import metrics as tm
from heartcv.tracker.estimators import holdout_points
from heartcv.tracker.joint import run_joint
from heartcv.tracker.simulate import simulate, to_measurements
from heartcv.tracker.tracking import run_kalman


@pytest.fixture(scope="module")
def meas(paper_model):
    return to_measurements(simulate(paper_model, 2.0, np.random.default_rng(8)))


def test_holdout_points_draw():
    a = holdout_points(np.arange(3, 23), 0.25, np.random.default_rng(1))
    b = holdout_points(np.arange(22, 2, -1), 0.25, np.random.default_rng(1))
    assert a.size == 5 and np.array_equal(a, b) and np.all(np.diff(a) > 0) and np.isin(a, np.arange(3, 23)).all()
    assert holdout_points(np.arange(10), 0.0, np.random.default_rng(0)).size == 0
    for bad in (-0.1, 1.0):
        with pytest.raises(ValueError, match="holdout"):
            holdout_points(np.arange(10), bad, np.random.default_rng(0))


def test_holdout_draw_is_stable_under_a_changed_candidate_set_and_uniform():
    """A track is held out by its id and the seed, not by the other candidates: dropping a candidate that was not
    held out changes nothing; dropping one that was swaps in at most one other. Over 4000 seeds every candidate is
    held out with the fraction's probability (within 4 standard errors) and each draw holds out exactly
    round(fraction n)."""
    ids = np.arange(1000, 1200) * 7                     # arbitrary, sparse point ids
    cand = np.arange(200)
    held = holdout_points(cand, 0.1, np.random.default_rng(3), ids=ids)
    assert held.size == 20
    out = np.setdiff1d(cand, held)[5]
    kept = np.delete(cand, out)
    np.testing.assert_array_equal(holdout_points(kept, 0.1, np.random.default_rng(3), ids=ids[kept]), held)
    gone = held[3]
    kept = np.delete(cand, gone)
    again = holdout_points(kept, 0.1, np.random.default_rng(3), ids=ids[kept])
    assert np.setdiff1d(held, again).tolist() == [gone] and np.setdiff1d(again, held).size <= 1
    # a plain random draw (the previous rule) would have reshuffled: compare with rng.choice on the same change
    a = np.sort(np.random.default_rng(3).choice(cand, 20, replace=False))
    b = np.sort(np.random.default_rng(3).choice(np.delete(cand, out), 20, replace=False))
    assert np.setdiff1d(a, b).size > 1
    counts = np.zeros(20)
    for seed in range(4000):
        h = holdout_points(np.arange(20), 0.25, np.random.default_rng(seed), ids=np.arange(20) + 10 ** 9)
        assert h.size == 5
        counts[h] += 1
    p = counts / 4000
    assert np.all(np.abs(p - 0.25) < 4 * np.sqrt(0.25 * 0.75 / 4000)), p
    with pytest.raises(ValueError, match="ids"):
        holdout_points(np.arange(5), 0.2, np.random.default_rng(0), ids=np.arange(4))


@pytest.mark.parametrize("which", ["kf", "ge"])
def test_heldout_points_do_not_touch_the_state(paper_model, meas, which):
    """The run with points held out equals the run on the same file with those points' measurements removed (the
    state, exactly), while their predictions and innovations against the real measurements are still recorded."""
    held = np.array([1, 6, 11])
    blank = meas.positions.copy()
    blank[:, held] = np.nan
    cov = meas.covariances.copy()
    cov[:, held] = np.nan
    removed = dataclasses.replace(meas, positions=blank, covariances=cov)

    def run(m, **kw):
        return run_kalman(paper_model, m, **kw) if which == "kf" else run_joint(paper_model, m, "ge", **kw)
    a, b = run(meas, heldout=held), run(removed)
    np.testing.assert_array_equal(a.state_mean, b.state_mean)
    np.testing.assert_array_equal(a.predictions, b.predictions)
    np.testing.assert_allclose(a.innovations[:, held], meas.positions[:, held] - a.predictions[:, held], rtol=1e-15)
    assert a.meta["heldout_points"] == [int(i) for i in meas.point_ids[held]]
    m = tm.estimator_metrics(a)
    assert m["heldout_points"] == 3
    e = np.linalg.norm(a.innovations[1:], axis=-1)
    in_upd = np.setdiff1d(np.arange(meas.n_points), held)
    assert m["heldout_prediction_error_mean_m"] == pytest.approx(np.nanmean(e[:, held]), rel=1e-12)
    assert m["prediction_error_mean_m"] == pytest.approx(np.nanmean(e[:, in_upd]), rel=1e-12)
    # the model predicts the held-out points about as well as the others (the paper model is exact here)
    assert m["heldout_prediction_error_mean_m"] < 1.3 * m["prediction_error_mean_m"]
