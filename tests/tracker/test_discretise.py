"""Time discretisation (docs/spec/model.md §3, §7 items 3-5)."""

import itertools

import numpy as np
import pytest
import scipy.linalg as sla

from heartcv.tracker.discretise import discretise, modal_blocks

THETAS = [
    (1050.0, 2.39, 0.003, 150e3, 0.45),   # paper_patch default
    (1050.0, 0.5, 0.01, 30e3, 0.45),      # spec §3.2 example
    (1291.0, 0.55, 0.02, 24e6, 0.33),     # paper phantom prior (strongly over-damped high modes)
    (1050.0, 0.2, 1e-4, 300.0, 0.49),     # dynamic regime, f1 of a few Hz
]


@pytest.mark.parametrize("theta", THETAS)
def test_modal_equals_expm(paper_model, theta):
    a = paper_model.system(theta, method="modal")
    b = paper_model.system(theta, method="expm")
    for X, Y in ((a.A, b.A), (a.B0, b.B0), (a.B1, b.B1)):
        assert np.linalg.norm(X - Y) <= 1e-9 * np.linalg.norm(Y)


@pytest.mark.parametrize("method", ["modal", "expm", "implicit-euler"])
@pytest.mark.parametrize("theta", THETAS)
def test_steady_state_gain(paper_model, theta, method):
    s = paper_model.system(theta, method=method)
    n = paper_model.state_dim
    G = np.linalg.solve(np.eye(n) - s.A, s.B0 + s.B1)
    M, K = paper_model.matrices(theta)
    ref = np.linalg.solve(K, paper_model.loads)
    tol = 1e-9 if method == "expm" else 1e-10  # Van Loan loses a digit on the stiff phantom values
    assert np.abs(G[: n // 2] - ref).max() <= tol * np.abs(ref).max()
    assert np.abs(G[n // 2 :]).max() <= tol * np.abs(ref).max() / s.dt


def test_spectral_radius_below_one_over_the_box(paper_model):
    """Any positive Rayleigh damping gives |eig A| < 1 at every corner of the box (no step limit)."""
    grid = itertools.product([500.0, 2000.0], [1e-3, 100.0], [0.0, 1.0], [1e3, 1e8], [0.01, 0.499])
    worst = 0.0
    for th in grid:
        A = paper_model.system(th).A
        worst = max(worst, np.abs(np.linalg.eigvals(A)).max())
    assert worst < 1.0


def test_undamped_corner_is_marginal(paper_model):
    """alpha1 = alpha2 = 0 (the box's lower corner) is undamped: |eig A| = 1 to rounding, never above."""
    A = paper_model.system((1050.0, 0.0, 0.0, 150e3, 0.45)).A
    rad = np.abs(np.linalg.eigvals(A))
    assert np.abs(rad - 1).max() < 1e-10


def test_spectral_radius_spec_example(paper_model):
    A = paper_model.system(THETAS[1]).A
    assert np.abs(np.linalg.eigvals(A)).max() == pytest.approx(0.036, abs=0.001)


def test_foh_is_exact_for_a_ramp():
    """One mode driven by a linear ramp: FOH reproduces the analytic solution of q'' + c q' + w2 q = g (a + b t)."""
    w2, c, g, dt = 40.0, 3.0, 2.0, 0.05
    a, b = 0.7, -1.3
    M, K, F = np.eye(1), np.eye(1) * w2, np.array([[g]])
    # Rayleigh: c = alpha1 + alpha2 w2 -> take alpha2 = 0
    s = discretise(M, K, c, 0.0, F, dt)
    # particular solution of the ramp: q_p = (g/w2)(a + b t) - g b c / w2^2
    qp = lambda t: (g / w2) * (a + b * t) - g * b * c / w2**2  # noqa: E731
    x0 = np.array([qp(0.0) + 0.1, g * b / w2 - 0.2])
    # homogeneous part by the exact exponential
    Fc = np.array([[0, 1], [-w2, -c]])
    hom0 = x0 - np.array([qp(0.0), g * b / w2])
    exact = sla.expm(Fc * dt) @ hom0 + np.array([qp(dt), g * b / w2])
    got = s.A @ x0 + s.B0[:, 0] * (a) + s.B1[:, 0] * (a + b * dt)
    np.testing.assert_allclose(got, exact, rtol=1e-12, atol=1e-14)


def test_modal_blocks_critical_and_overdamped_limits():
    """Near-critical damping uses the limit formula; heavy over-damping must not overflow."""
    dt = 0.01
    w2 = np.array([100.0, 100.0, 1e8])
    c = np.array([20.0, 20.0 + 1e-9, 1e7])
    a0, s = modal_blocks(w2, c, dt)
    assert np.isfinite(a0).all() and np.isfinite(s).all()
    ref = sla.expm(np.array([[0, 1], [-100.0, -20.0]]) * dt)
    np.testing.assert_allclose([a0[0], s[0]], [ref[0, 0], ref[0, 1]], rtol=1e-10)
    np.testing.assert_allclose([a0[1], s[1]], [ref[0, 0], ref[0, 1]], rtol=1e-7)
    ref3 = sla.expm(np.array([[0, 1], [-1e8, -1e7]]) * dt)
    np.testing.assert_allclose([a0[2], s[2]], [ref3[0, 0], ref3[0, 1]], rtol=1e-8, atol=1e-300)


def test_discretise_rejects_bad_input():
    with pytest.raises(ValueError, match="dt"):
        discretise(np.eye(2), np.eye(2), 0, 0, np.ones(2), -1.0)
    with pytest.raises(ValueError, match="method"):
        discretise(np.eye(2), np.eye(2), 0, 0, np.ones(2), 0.1, method="euler")
    with pytest.raises(ValueError, match="F"):
        discretise(np.eye(2), np.eye(2), 0, 0, np.ones(3), 0.1)
