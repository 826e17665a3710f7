"""The one-step predictive log-likelihood per frame in the estimate file (``EstimateSet.log_likelihood``) and its
per-point summary in the report (``tracker.metrics.log_likelihood_statistics``)."""

import dataclasses

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from heartcv.tracker.measurements import EstimateSet
from heartcv.tracker.metrics import compare_runs, log_likelihood_statistics
from heartcv.tracker.simulate import simulate, to_measurements
from heartcv.tracker.tracking import first_frames, run_kalman, run_setup


@pytest.fixture(scope="module")
def short(paper_model):
    """The paper patch, 5 frames, one point unseen in frame 2 and nothing seen in frame 3."""
    meas = first_frames(to_measurements(simulate(paper_model, 1.0, np.random.default_rng(11))), 5)
    pos = meas.positions.copy()
    pos[2, 4] = np.nan
    pos[3] = np.nan
    return dataclasses.replace(meas, positions=pos)


def _joint_log_density(model, meas):
    """log p(y_0, ..., y_(K-1)) of the linear-Gaussian model the KF runs (fixed references, the model file's theta),
    by brute force: the stacked measurements' mean and covariance from the state's moments,
    Cov(x_j, x_k) = A^(k-j) P_j, and one multivariate normal density over every seen coordinate."""
    pts, obs, u, trans, K, dt = run_setup(model, meas)
    theta = model.config.theta
    sysd = model.system(theta, dt)
    A, Q = sysd.A, model.process_noise(theta, dt)
    mu = [model.static_state(theta, u[0])]
    P = [model.initial_covariance()]
    for k in range(1, K):
        mu.append(A @ mu[-1] + sysd.B0 @ u[k - 1] + sysd.B1 @ u[k])
        P.append(A @ P[-1] @ A.T + Q)
    n = mu[0].size
    Cx = np.zeros((K * n, K * n))
    for j in range(K):
        Akj = np.eye(n)
        for k in range(j, K):
            Cx[k * n:(k + 1) * n, j * n:(j + 1) * n] = Akj @ P[j]
            Cx[j * n:(j + 1) * n, k * n:(k + 1) * n] = (Akj @ P[j]).T
            Akj = A @ Akj
    H = obs.H
    Hs = np.kron(np.eye(K), H)
    y = meas.positions[:, pts.keep, :].reshape(K, -1)
    m = np.concatenate([(obs.reference + trans[k]).reshape(-1) + H @ mu[k] for k in range(K)])
    R = np.zeros((y.size, y.size))
    for k in range(K):
        for i, p in enumerate(pts.keep):
            r = k * y.shape[1] + 3 * i
            R[r:r + 3, r:r + 3] = meas.covariances[k, p]
    S = Hs @ Cx @ Hs.T + R
    seen = np.isfinite(y.reshape(-1))
    return multivariate_normal(m[seen], S[np.ix_(seen, seen)]).logpdf(y.reshape(-1)[seen])


def test_per_frame_log_likelihood_sums_to_the_joint_density(paper_model, short):
    """The KF's per-frame predictive log-likelihoods (prediction-error decomposition) add up to the joint density of
    all the measurements computed by brute force (to 1e-6 relative); the frame with nothing seen is NaN; the meta's
    total is the sum over frames 1 .. K-1."""
    est = run_kalman(paper_model, short)
    ll = est.log_likelihood
    assert ll.shape == (5,)
    assert np.isnan(ll[3]) and np.isfinite(np.delete(ll, 3)).all()
    assert np.nansum(ll) == pytest.approx(_joint_log_density(paper_model, short), rel=1e-6)
    assert est.meta["log_likelihood"] == pytest.approx(np.nansum(ll[1:]), rel=1e-12)
    assert est.nis_dof[3] == 0


def _est(name, ll, dof, K=6):
    P = 2
    z = np.zeros((K, 1))
    return EstimateSet(name, np.arange(K) * 0.04, np.arange(P), z, z, np.zeros((K, 5)), np.zeros((K, 5)),
                       np.zeros((K, P, 3)), np.zeros((K, P, 3)), np.ones(K), np.asarray(dof), np.zeros(K, int),
                       np.zeros(K), K, log_likelihood=None if ll is None else np.asarray(ll, float))


def test_statistics_per_point_and_split():
    """Per measured point (nis_dof / 3), frame 0 left out, NaN frames skipped; split at the fitted frames; None for a
    run without the array; the GE - KF difference only over the same number of points."""
    ll = [100.0, 30.0, np.nan, 12.0, 6.0, 9.0]
    dof = [6, 6, 0, 3, 6, 3]
    s = log_likelihood_statistics(_est("kf", ll, dof), fit_frames=4)
    assert s["log_likelihood_per_point"] == pytest.approx((30 + 12 + 6 + 9) / (2 + 1 + 2 + 1))
    assert s["log_likelihood_points"] == 6
    assert s["log_likelihood_within_fit_per_point"] == pytest.approx((30 + 12) / 3)
    assert s["log_likelihood_after_fit_per_point"] == pytest.approx((6 + 9) / 3)
    assert log_likelihood_statistics(_est("kf", ll, dof))["log_likelihood_within_fit_per_point"] is None
    assert set(log_likelihood_statistics(_est("hold", None, dof)).values()) == {None}
    ge = _est("ge", [0.0, 33.0, np.nan, 12.0, 6.0, 9.0], dof)
    out = compare_runs({"ge": ge, "kf": _est("kf", ll, dof)})
    assert out["difference_ge_minus_kf_log_likelihood_per_point"] == pytest.approx(3.0 / 6)
    other = _est("kf", ll, [6, 6, 0, 3, 6, 6])
    assert compare_runs({"ge": ge, "kf": other})["difference_ge_minus_kf_log_likelihood_per_point"] is None
