"""Assembled model: counts, invariances, lifting, measurement matrix, reduced basis (docs/spec/model.md §7)."""

import copy

import numpy as np
import pytest

from heartcv.tracker.config import model_config_from_dict
from heartcv.tracker.model import build_model


def test_paper_counts(paper_model):
    info = paper_model.info()
    assert info["free_nodes"] == 28
    assert info["state_dim"] == 168
    assert info["observed_rows"] == 42
    assert paper_model.observation(paper_model.default_points()).H.shape == (42, 168)


def test_scaling_invariance(paper_model):
    """(2 rho, 2 E, 2 f) leaves every trajectory unchanged (spec §4.3)."""
    th = np.array([1050.0, 2.39, 0.003, 150e3, 0.45])
    th2 = th * np.array([2, 1, 1, 2, 1])
    u = 5000.0 * np.sin(np.linspace(0, 6, 61))[:, None]
    s1 = paper_model.system(th)
    s2 = paper_model.system(th2)
    x1 = np.zeros(168)
    x2 = np.zeros(168)
    worst = 0.0
    for k in range(60):
        x1 = s1.A @ x1 + s1.B0 @ u[k] + s1.B1 @ u[k + 1]
        x2 = s2.A @ x2 + 2 * (s2.B0 @ u[k] + s2.B1 @ u[k + 1])
        worst = max(worst, np.abs(x1[:84] - x2[:84]).max())
    assert np.abs(x1[:84]).max() > 1e-4  # a real motion of ~mm
    assert worst < 1e-15


def test_lifting_of_rigid_translation(paper_model):
    """R T_b = T_f for a rigid translation, for any theta (spec §2.4)."""
    rim = np.setdiff1d(np.arange(3 * paper_model.mesh.n_nodes), paper_model.free_dofs)
    for th in ([1050, 2.39, 0.003, 150e3, 0.45], [1291, 0.5, 0.02, 24e6, 0.33]):
        R = paper_model.lifting(th)
        for axis in range(3):
            Tb = (rim % 3 == axis).astype(float)
            Tf = (paper_model.free_dofs % 3 == axis).astype(float)
            np.testing.assert_allclose(R @ Tb, Tf, atol=1e-10)


def test_measurement_matrix_selects_nodes(paper_model):
    pts = paper_model.default_points()
    obs = paper_model.observation(pts)
    Hq = obs.H[:, :84]
    assert set(np.unique(Hq)) <= {0.0, 1.0}
    assert (Hq.sum(axis=1) == 1).all()
    np.testing.assert_allclose(obs.reference, paper_model.mesh.geometry.to_patch(*pts.T), atol=1e-16)
    assert (obs.H[:, 84:] == 0).all()


def test_measurement_matrix_interpolates_trilinear_fields(paper_model, rng):
    """A field that is trilinear in (s, t, d) per element is reproduced exactly at arbitrary points."""
    mesh = paper_model.mesh
    coef = rng.standard_normal((3, 3))
    field = mesh.param @ coef  # linear in (s,t,d): exact for trilinear shape functions
    g = mesh.geometry
    pts = np.column_stack([rng.uniform(-g.length / 2, g.length / 2, 50), rng.uniform(-g.width / 2, g.width / 2, 50),
                           rng.uniform(0, g.thickness, 50)])
    N = paper_model.shape_matrix(pts)
    np.testing.assert_allclose(N @ field, pts @ coef, atol=1e-12)
    np.testing.assert_allclose(np.asarray(N.sum(axis=1)).ravel(), 1.0, atol=1e-14)


def test_measurement_matrix_rejects_points_off_the_patch(paper_model):
    with pytest.raises(ValueError, match="outside the patch"):
        paper_model.shape_matrix([[0.5, 0.0, 0.0]])


def _small_model(paper_dict, reduction=None, grid=(13, 9, 3)):
    d = copy.deepcopy(paper_dict)
    d["geometry"]["grid"] = list(grid)
    d["observation"] = {"points": {"grid": [5, 4]}, "margin": 0.1}
    if reduction:
        d["reduction"] = reduction
    return build_model(model_config_from_dict(d))


@pytest.mark.parametrize("nu,tol", [(0.45, 1e-7), (0.47, 5e-7)])
def test_reduced_basis_matches_full_model(paper_dict, nu, tol):
    """Ritz basis (modes + static responses): the camera points follow the full model to < 0.1 um when
    nu is one of the static-response ratios, < 0.5 um between them (0.5 % of the 0.1 mm noise)."""
    full = _small_model(paper_dict)
    red = _small_model(paper_dict, {"modes": 10, "static_nu": [0.3, 0.45, 0.49]})
    assert red.r < 15 and full.r == 3 * 11 * 7 * 3
    Mr = red.M0
    assert np.abs(Mr / red.fe.volume - np.eye(red.r)).max() < 1e-9  # V^T M0 V = vol I
    from heartcv.tracker import inputs as inp

    t = np.arange(61) / 30.0
    u = inp.lv_pressure(t)[:, None]
    theta = np.array([1050.0, 2.39, 0.003, 150e3, nu])
    pts = full.default_points()
    traj = []
    for m in (full, red):
        s = m.system(theta)
        H = m.observation(pts).H
        x = m.static_state(theta, u[0])
        ys = [H @ x]
        for k in range(60):
            x = s.A @ x + s.B0 @ u[k] + s.B1 @ u[k + 1]
            ys.append(H @ x)
        traj.append(np.array(ys))
    assert np.abs(traj[0]).max() > 1e-3  # ~mm motion
    assert np.abs(traj[0] - traj[1]).max() < tol


def test_full_model_too_large_is_refused(paper_dict):
    """Refused by validation (the model file's field named) and, for a config made otherwise, by build_model
    before the mesh is built."""
    from dataclasses import replace

    from heartcv.tracker.config import ConfigError

    d = copy.deepcopy(paper_dict)
    d["geometry"]["grid"] = [31, 21, 4]
    with pytest.raises(ConfigError, match="reduction") as info:
        model_config_from_dict(d)
    assert info.value.field == "geometry.grid"
    d["reduction"] = {"modes": 10}
    cfg = replace(model_config_from_dict(d), reduction=None)
    with pytest.raises(ConfigError, match="6612 free DOFs") as info:
        build_model(cfg)
    assert info.value.field == "geometry.grid"


def test_ukf_kappa_must_leave_a_positive_spread(paper_dict):
    from heartcv.tracker.config import ConfigError

    d = copy.deepcopy(paper_dict)
    d["estimation"]["ukf"] = {"kappa": -170.0}  # n = 168 states + 2 parameters
    with pytest.raises(ConfigError, match="must exceed -n = -170") as info:
        build_model(model_config_from_dict(d))
    assert info.value.field == "estimation.ukf.kappa"
    d["estimation"]["ukf"] = {"kappa": -169.0}
    assert build_model(model_config_from_dict(d)).state_dim == 168


@pytest.mark.parametrize("reduction", [None, {"modes": 500, "static_nu": [0.3, 0.3]}])
@pytest.mark.parametrize("radius, width", [(0.08, 0.04), (None, 0.00026762107709657967)])
def test_smallest_mesh_builds(reduction, radius, width):
    """One free node column (grid [3, 3, 2]: 6 free DOFs); reduction.modes is capped at free DOFs - 2; on the flat
    patch the active tension load is zero (exactly, at this width: a fuzz finding), and its static response is
    dropped from the basis instead of being divided by its zero norm."""
    d = {"geometry": {"grid": [3, 3, 2], "width": width, "radius_long": radius, "radius_circ": radius},
         "inputs": {"active_tension": {"t_max": 1000.0}}, "reduction": reduction}
    cfg = model_config_from_dict(d)
    with np.errstate(invalid="raise", divide="raise"):
        m = build_model(cfg)
    assert m.free_dofs.size == 6 and m.r <= 6
    sys = m.system(cfg.theta)
    assert np.isfinite(sys.A).all() and m.default_points().shape == (1, 3)


def test_acceleration_process_noise_is_van_loan(paper_dict):
    """Q for white acceleration noise: a single mode check against the closed form of the integrated
    Wiener-velocity block for an undamped free mass limit (stiffness -> 0 is not allowed, so compare the
    trace of the velocity block with q*dt to first order at a tiny dt)."""
    d = copy.deepcopy(paper_dict)
    d["noise"]["process"] = {"kind": "acceleration", "accel_psd": 2.0}
    m = build_model(model_config_from_dict(d))
    dt = 1e-6
    Q = m.process_noise(theta=[1050.0, 0.0, 0.0, 150e3, 0.45], dt=dt)
    r = m.r
    np.testing.assert_allclose(np.diag(Q)[r:], 2.0 * dt, rtol=1e-3)
    np.testing.assert_allclose(np.diag(Q)[:r], 2.0 * dt**3 / 3, rtol=1e-3)
    assert np.linalg.eigvalsh(m.process_noise()).min() > -1e-18


def test_integrated_noise_stiff_and_plain_van_loan():
    """Stiff pair: Q(dt) equals the stationary covariance (Lyapunov) when dt >> every time constant;
    mild system: equals the plain one-shot Van Loan formula."""
    import scipy.linalg as sla

    from heartcv.tracker.model import integrated_noise

    Fc = np.array([[0.0, 1.0], [-4e8, -1e5]])  # eigenvalues about -4.2e3 and -9.6e4 1/s
    Qc = np.diag([0.0, 3.0])
    Q = integrated_noise(Fc, Qc, 1 / 30)
    P = sla.solve_continuous_lyapunov(Fc, -Qc)
    np.testing.assert_allclose(Q, P, rtol=1e-9, atol=1e-9 * np.abs(P).max())
    F2 = np.array([[0.0, 1.0], [-30.0, -2.0]])
    dt = 0.05
    Z = np.block([[-F2, Qc], [np.zeros((2, 2)), F2.T]])
    E = sla.expm(Z * dt)
    ref = E[2:, 2:].T @ E[:2, 2:]
    np.testing.assert_allclose(integrated_noise(F2, Qc, dt), 0.5 * (ref + ref.T), rtol=1e-12, atol=1e-18)


def test_ritz_basis_drops_zero_static_responses(paper_model):
    from heartcv.tracker.model import _ritz_basis

    fe, free = paper_model.fe, paper_model.free_dofs
    loads = np.column_stack([fe.f_pressure[free], np.zeros(free.size)])
    with np.errstate(invalid="raise", divide="raise"):
        V = _ritz_basis(fe, free, loads, paper_model.config.theta, 10, (0.3, 0.45), fe.volume)
    assert V.shape == (free.size, 12) and np.isfinite(V).all()  # 10 modes + 2 responses to the pressure
