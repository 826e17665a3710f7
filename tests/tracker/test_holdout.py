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
