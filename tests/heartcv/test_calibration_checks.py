"""Pure checks of heartcv.calibration_checks against closed forms and brute force."""

from __future__ import annotations

import numpy as np
import pytest

from heartcv.calibration_checks import (
    COVERAGE_FULL,
    COVERAGE_K2,
    distortion_fold,
    distortion_terms,
    image_coverage,
    jackknife_std,
    sync_displacement,
    sync_weights,
)


def test_coverage_of_a_rectangle_is_its_area_fraction():
    # a 320 x 180 rectangle of corners in a 1280 x 720 image: 1/16 of the area (+- one grid cell along the edges)
    xs, ys = np.meshgrid(np.linspace(100, 419, 5), np.linspace(200, 379, 4))
    uv = np.stack([xs.ravel(), ys.ravel()], 1)
    assert image_coverage([uv], (1280, 720)) == pytest.approx(1 / 16, abs=0.004)
    # two views over the same area count once; fewer than 3 corners count nothing
    assert image_coverage([uv, uv + 0.1, uv[:2] + 500], (1280, 720)) == pytest.approx(1 / 16, abs=0.004)


def test_distortion_terms_follow_coverage():
    assert distortion_terms(0.1, 5).tolist() == [True, False, False, False, False]
    assert distortion_terms(COVERAGE_K2, 5).tolist() == [True, True, True, True, False]
    assert distortion_terms(COVERAGE_FULL, 8).all()


def test_fold_closed_form_for_k1():
    """r_d = r (1 + k1 r^2) has its maximum 2 / (3 sqrt(3 |k1|)) at r = 1 / sqrt(3 |k1|): with k1 = -0.34 and f =
    890 px on a 1280 x 720 image (corner at r_d = 0.825 from the centre) it never reaches the image corner."""
    K = np.array([[890.0, 0, 639.5], [0, 890.0, 359.5], [0, 0, 1]])
    r = distortion_fold(K, [-0.34, 0, 0, 0, 0], (1280, 720))
    assert r == pytest.approx(1 / np.sqrt(3 * 0.34), abs=0.01)
    assert distortion_fold(K, [-0.2, 0, 0, 0, 0], (1280, 720)) is None  # max r_d 0.86 > 0.825
    assert distortion_fold(K, [0.1, -0.05, 0, 0, 0.01], (1280, 720)) is None


def test_sync_displacement_of_a_board_moving_at_constant_speed():
    """Corners moving 100 px/s; a camera 10 ms late at every instant: 1 px (exact for constant speed)."""
    ids = np.arange(6)
    t = np.arange(5) * 0.2 + 0.01
    uv = [np.stack([np.arange(6) * 10 + 100 * ti, np.full(6, 50.0)], 1) for ti in t]
    d = sync_displacement(uv, [ids] * 5, t, t - 0.01)
    np.testing.assert_allclose(d, 1.0, rtol=1e-9)
    assert sync_weights(d) == pytest.approx(1 / (1 + 4))
    d2 = sync_displacement([uv[0], None, uv[2], None, None], [ids, None, ids, None, None], t, t)
    assert d2.tolist() == [0, 0, 0, 0, 0]


def test_jackknife_of_a_mean_is_the_standard_error():
    """For the mean, the delete-a-group jackknife with k equal groups reproduces s / sqrt(n) exactly."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=40)
    k = 5
    est = np.array([[np.mean(np.delete(x, np.arange(g, 40, k)))] for g in range(k)])
    # groups of 8: leave-group-out means; the jackknife gives sqrt((k-1)/k sum (m_i - m)^2)
    sj = jackknife_std(est)[0]
    groups = np.array([x[g::k].mean() for g in range(k)])
    assert sj == pytest.approx(np.std(groups, ddof=1) / np.sqrt(k), rel=1e-9)
