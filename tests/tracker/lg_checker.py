"""Shared linear-Gaussian checker for every estimator in ``tracker/`` (ISAS style).

A random stable linear-Gaussian problem (:func:`make_problem`) is filtered by the estimator under test; each
posterior must equal the closed-form batch posterior (:func:`batch_posterior`) and stay symmetric positive
definite (:func:`check_estimator`).

Model (the convention every ``run`` must follow)::

    x_0 ~ N(prior_mean, prior_cov)
    x_k = A x_{k-1} + B u_{k-1} + w_{k-1},   w ~ N(0, Q)          k = 1 .. steps-1
    y_k = offset + H x_k + v_k,              v ~ N(0, R)          k = 0 .. steps-1

Step 0 updates the prior with y_0; step k > 0 predicts x_k from x_{k-1}, then updates with y_k. NaN entries of
y_k are missing measurements (their rows are dropped, including the rows/columns of R).

The oracle does not run a recursion: it stacks the trajectory [x_0 .. x_k], writes the prior, the dynamics and
every finite measurement as one weighted linear least-squares problem (information form), solves the full dense
normal equations, and reads off the marginal of x_k.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

__all__ = ["LGProblem", "make_problem", "batch_posterior", "check_estimator"]


@dataclass(frozen=True)
class LGProblem:
    """A linear-Gaussian filtering problem with simulated data (arrays are read-only).

    Attributes
    ----------
    A : ndarray of shape (n, n)      transition, spectral radius < 1
    B : ndarray of shape (n, p)      input matrix
    u : ndarray of shape (steps, p)  known inputs; u[k-1] drives the step k-1 -> k
    Q : ndarray of shape (n, n)      process noise covariance (SPD)
    H : ndarray of shape (m, n)      measurement matrix
    R : ndarray of shape (m, m)      measurement noise covariance (SPD, full)
    offset : ndarray of shape (m,)   known measurement offset (zeros unless requested)
    prior_mean : ndarray of shape (n,)
    prior_cov : ndarray of shape (n, n)
    y : ndarray of shape (steps, m)  measurements, NaN where missing
    x : ndarray of shape (steps, n)  simulated true states (for Monte Carlo checks)
    """

    A: np.ndarray
    B: np.ndarray
    u: np.ndarray
    Q: np.ndarray
    H: np.ndarray
    R: np.ndarray
    offset: np.ndarray
    prior_mean: np.ndarray
    prior_cov: np.ndarray
    y: np.ndarray
    x: np.ndarray

    @property
    def steps(self) -> int:
        return self.y.shape[0]


def _random_spd(rng, d, scale):
    G = rng.standard_normal((d, d))
    return scale * (G @ G.T / d + 0.2 * np.eye(d))


def make_problem(rng, n=6, m=3, steps=30, missing_fraction=0.1, *, p=2, with_offset=False) -> LGProblem:
    """Draw a random stable linear-Gaussian problem and simulate its data.

    Each measurement entry is missing (NaN) with probability ``missing_fraction``; in addition, when
    ``missing_fraction > 0`` and ``steps >= 3``, the whole measurement at step ``steps // 2`` is missing so
    that every estimator meets a step without any measurement.

    Parameters
    ----------
    rng : numpy.random.Generator
    n, m, p, steps : int
        State, measurement and input dimensions, and the number of steps.
    missing_fraction : float
        Probability that an entry of y is NaN.
    with_offset : bool
        Draw a non-zero measurement offset (estimators without an offset argument leave it False).
    """
    G = rng.standard_normal((n, n))
    A = G * (rng.uniform(0.6, 0.95) / np.max(np.abs(np.linalg.eigvals(G))))
    B = rng.standard_normal((n, p))
    u = rng.standard_normal((steps, p))
    Q = _random_spd(rng, n, 0.05)
    H = rng.standard_normal((m, n))
    R = _random_spd(rng, m, 0.1)
    offset = rng.standard_normal(m) if with_offset else np.zeros(m)
    prior_mean = rng.standard_normal(n)
    prior_cov = _random_spd(rng, n, 1.0)

    x = np.empty((steps, n))
    x[0] = rng.multivariate_normal(prior_mean, prior_cov)
    w = rng.multivariate_normal(np.zeros(n), Q, size=steps)
    for k in range(1, steps):
        x[k] = A @ x[k - 1] + B @ u[k - 1] + w[k - 1]
    y = offset + x @ H.T + rng.multivariate_normal(np.zeros(m), R, size=steps)
    y[rng.random((steps, m)) < missing_fraction] = np.nan
    if missing_fraction > 0 and steps >= 3:
        y[steps // 2] = np.nan

    arrays = dict(A=A, B=B, u=u, Q=Q, H=H, R=R, offset=offset, prior_mean=prior_mean, prior_cov=prior_cov, y=y, x=x)
    for a in arrays.values():
        a.setflags(write=False)
    return LGProblem(**arrays)


def batch_posterior(problem: LGProblem, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form p(x_k | y_0..y_k) from the stacked trajectory, without any recursion.

    The negative log posterior of X = [x_0; ..; x_k] is (1/2) ||J X - r||^2 in the metric Sigma^{-1}, where the
    rows of J, r and the blocks of Sigma = blkdiag(P_0, Q, .., Q, R_0, .., R_k) are the prior, the k dynamics
    residuals x_j - A x_{j-1} - B u_{j-1} and the finite measurement rows y_j - offset - H x_j. The information
    matrix Lambda = J^T Sigma^{-1} J and vector eta = J^T Sigma^{-1} r give mean Lambda^{-1} eta and covariance
    Lambda^{-1}; both are obtained with one dense solve, and the last n x n block is returned.

    Returns
    -------
    mean : ndarray of shape (n,)
    cov : ndarray of shape (n, n)
    """
    P = problem
    n = P.A.shape[0]
    N = (k + 1) * n
    rows_J, rows_r, blocks = [], [], []

    def block(j, M):                       # M placed in the columns of x_j
        out = np.zeros((M.shape[0], N))
        out[:, j * n:(j + 1) * n] = M
        return out

    rows_J.append(block(0, np.eye(n)))
    rows_r.append(P.prior_mean)
    blocks.append(P.prior_cov)
    for j in range(1, k + 1):
        rows_J.append(block(j, np.eye(n)) - block(j - 1, P.A))
        rows_r.append(P.B @ P.u[j - 1])
        blocks.append(P.Q)
    for j in range(k + 1):
        ok = np.isfinite(P.y[j])
        if ok.any():
            rows_J.append(block(j, P.H[ok]))
            rows_r.append(P.y[j, ok] - P.offset[ok])
            blocks.append(P.R[np.ix_(ok, ok)])

    J = np.vstack(rows_J)
    r = np.concatenate(rows_r)
    Sigma = scipy.linalg.block_diag(*blocks)
    Sigma_inv_J = np.linalg.solve(Sigma, J)
    Lam = J.T @ Sigma_inv_J
    eta = Sigma_inv_J.T @ r
    rhs = np.column_stack([eta, np.eye(N)[:, -n:]])
    sol = scipy.linalg.solve(Lam, rhs, assume_a="pos")
    mean = sol[-n:, 0]
    cov = sol[-n:, 1:]
    return mean, 0.5 * (cov + cov.T)


def check_estimator(run, problem: LGProblem, atol=1e-9) -> None:
    """Assert that an estimator reproduces the closed-form posterior at every step.

    Parameters
    ----------
    run : callable
        ``run(problem)`` returns a sequence of ``steps`` pairs ``(mean (n,), cov (n, n))``, the posterior after
        the update with y_k (see the module docstring for the convention).
    problem : LGProblem
    atol : float
        Tolerance relative to the scale of the reference: ``max |mean - mean_ref| <= atol * s_mu`` with
        ``s_mu = max(max |mean_ref|, sqrt(max diag cov_ref))`` and ``max |cov - cov_ref| <= atol * max |cov_ref|``.

    Raises
    ------
    AssertionError
        On any mismatch, a covariance that is not exactly symmetric, or one that Cholesky rejects.
    """
    posteriors = list(run(problem))
    n = problem.A.shape[0]
    assert len(posteriors) == problem.steps, f"run returned {len(posteriors)} posteriors, expected {problem.steps}"
    for k, (mean, cov) in enumerate(posteriors):
        mean, cov = np.asarray(mean, dtype=float), np.asarray(cov, dtype=float)
        assert mean.shape == (n,) and cov.shape == (n, n), (
            f"step {k}: shapes {mean.shape}, {cov.shape}, expected ({n},), ({n}, {n})")
        assert np.array_equal(cov, cov.T), f"step {k}: covariance not exactly symmetric"
        try:
            np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:
            raise AssertionError(f"step {k}: covariance is not positive definite (Cholesky failed)") from None
        mean_ref, cov_ref = batch_posterior(problem, k)
        s_mu = max(np.max(np.abs(mean_ref)), np.sqrt(np.max(np.diag(cov_ref))))
        s_C = np.max(np.abs(cov_ref))
        err_mu = np.max(np.abs(mean - mean_ref))
        err_C = np.max(np.abs(cov - cov_ref))
        assert err_mu <= atol * s_mu, f"step {k}: mean error {err_mu:.3g} > {atol:g} * {s_mu:.3g}"
        assert err_C <= atol * s_C, f"step {k}: covariance error {err_C:.3g} > {atol:g} * {s_C:.3g}"
