"""GE prediction (docs/spec/estimator.md §2.5 worked check, §8 items 3-4, 9)."""

import numpy as np
import pytest

from heartcv.tracker.ge import ge_predict
from heartcv.tracker.kalman import GaussianState, predict
from heartcv.tracker.sampling import sample

DT = 0.05
MU = np.array([4.0, 0.5, 1.0, 0.0])
C = np.array([[0.25, 0.01, 0.05, 0.00],
              [0.01, 0.04, 0.00, 0.01],
              [0.05, 0.00, 0.10, 0.02],
              [0.00, 0.01, 0.02, 0.20]])
QN = np.diag([1e-3, 1e-4])
QL = np.diag([1e-4, 1e-3])
EXPECTED = np.array([[0.251, 0.01, 0.05, -0.0225],
                     [0.01, 0.0401, 0.0005, 0.00925],
                     [0.05, 0.0005, 0.1026, 0.00655],
                     [-0.0225, 0.00925, 0.00655, 0.18904]])


def oscillator(nodes):
    k, c = nodes[:, 0], nodes[:, 1]
    L = nodes.shape[0]
    A = np.zeros((L, 2, 2))
    A[:, 0, 0] = 1
    A[:, 0, 1] = DT
    A[:, 1, 0] = -k * DT
    A[:, 1, 1] = 1 - c * DT
    b = np.tile([0.0, 0.3 * DT], (L, 1))
    return A, b


def _predict(D, variant="A"):
    s = sample(MU[:2], C[:2, :2], D=D, variant=variant)
    return ge_predict(GaussianState(MU, C), 2, s.nodes, s.weights, oscillator, QN, QL)


@pytest.mark.parametrize("D,c33", [(3, 0.189029209596), (5, 0.189033234042), (7, 0.189035327348)])
def test_oscillator_reference_moments(D, c33):
    out = _predict(D)
    np.testing.assert_allclose(out.mean, [4, 0.5, 1, -0.188], atol=1e-15)
    mask = np.ones((4, 4), bool)
    mask[3, 3] = False
    np.testing.assert_allclose(out.cov[mask], EXPECTED[mask], atol=1e-15)
    assert out.cov[3, 3] == pytest.approx(c33, abs=1e-12)


def test_oscillator_variant_b_exact_except_quartic_term():
    out = _predict(5, "B")
    mask = np.ones((4, 4), bool)
    mask[3, 3] = False
    np.testing.assert_allclose(out.cov[mask], EXPECTED[mask], atol=1e-14)
    assert out.cov[3, 3] == pytest.approx(0.18904, abs=5e-5)


def test_ge_equals_kf_when_A_is_parameter_free(rng):
    """Replace A(theta) by A(mu_n): the GE prediction equals F C F^T + Q with F = blkdiag(I, A)."""
    A0, b0 = oscillator(MU[None, :2])

    def fixed(nodes):
        L = nodes.shape[0]
        return np.repeat(A0, L, axis=0), np.repeat(b0, L, axis=0)

    for D in (3, 5, 9):
        s = sample(MU[:2], C[:2, :2], D=D)
        out = ge_predict(GaussianState(MU, C), 2, s.nodes, s.weights, fixed, QN, QL)
        F = np.eye(4)
        F[2:, 2:] = A0[0]
        Q = np.zeros((4, 4))
        Q[:2, :2], Q[2:, 2:] = QN, QL
        ref = predict(GaussianState(MU, C), F, Q, np.r_[0, 0, b0[0]])
        np.testing.assert_allclose(out.mean, ref.mean, atol=1e-14)
        np.testing.assert_allclose(out.cov, ref.cov, atol=1e-14)


def test_monte_carlo_agreement():
    """Loose Monte Carlo check of the whole predicted covariance (spec: agreement to ~2e-4)."""
    rng = np.random.default_rng(2)
    z = rng.multivariate_normal(MU, C, size=400_000)
    A, b = oscillator(z[:, :2])
    xl = np.einsum("lij,lj->li", A, z[:, 2:]) + b
    xl += rng.multivariate_normal(np.zeros(2), QL, size=z.shape[0])
    xn = z[:, :2] + rng.multivariate_normal(np.zeros(2), QN, size=z.shape[0])
    mc = np.cov(np.hstack([xn, xl]).T)
    out = _predict(5)
    np.testing.assert_allclose(out.cov, mc, atol=2.5e-3)  # 4e5 samples: standard error ~ 5e-4 on 0.2
