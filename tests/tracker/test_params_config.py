"""Parameter coordinates (docs/spec/model.md §4.2) and model-file validation."""

import copy

import numpy as np
import pytest

from heartcv.tracker.config import ConfigError, model_config_from_dict
from heartcv.tracker.files import InputError
from heartcv.tracker.params import NAMES, ParameterSpace, lame, nu_from_s, s_from_nu


def test_s_reference_points():
    np.testing.assert_allclose(s_from_nu([0.33, 0.45, 0.49, 0.499]), [0.66, 2.20, 3.89, 6.21], atol=0.005)
    nu = np.linspace(0.001, 0.4999, 50)
    np.testing.assert_allclose(nu_from_s(s_from_nu(nu)), nu, rtol=1e-12)
    lam, mu = lame(1.0, nu)
    np.testing.assert_allclose(np.exp(s_from_nu(nu)), lam / mu, rtol=1e-12)


def test_phi_round_trip_and_jacobian(rng):
    ps = ParameterSpace(np.array([1050, 2.39, 0.003, 150e3, 0.45]), ("rho", "alpha1", "alpha2", "E", "nu"))
    th = np.column_stack([rng.uniform(500, 2000, 20), rng.uniform(0, 10, 20), rng.uniform(0, 0.1, 20),
                          rng.uniform(1e3, 1e6, 20), rng.uniform(0.01, 0.49, 20)])
    phi = ps.to_phi(th)
    np.testing.assert_allclose(ps.from_phi(phi), th, rtol=1e-12, atol=1e-15)
    h = 1e-6
    fd = (ps.from_phi(phi + h) - ps.from_phi(phi - h)) / (2 * h)
    np.testing.assert_allclose(ps.dtheta_dphi(phi), fd, rtol=1e-6)


def test_subset_and_bounds_map_to_a_box():
    ps = ParameterSpace(np.array([1050, 2.39, 0.003, 150e3, 0.45]), ("nu", "E"),
                        lower=np.array([500, 0, 0, 1e3, 0.0]), upper=np.array([2000, 100, 1, 1e8, 0.5]))
    assert ps.estimated == ("E", "nu") and ps.dim == 2
    lo, up = ps.bounds_phi
    np.testing.assert_allclose(lo, [np.log(1e3), -np.inf])
    np.testing.assert_allclose(up, [np.log(1e8), np.inf])
    th = ps.theta_from_x(np.array([[np.log(2e5), s_from_nu(0.3)]]))
    np.testing.assert_allclose(th[0], [1050, 2.39, 0.003, 2e5, 0.3], rtol=1e-12)
    np.testing.assert_allclose(ps.x_from_theta(th)[0], [np.log(2e5), s_from_nu(0.3)], rtol=1e-12)


@pytest.mark.parametrize("kwargs,match", [
    (dict(estimated=("G",)), "unknown parameter"),
    (dict(lower=np.array([500, 0, 0, 1e3, 0.0]), upper=np.array([1000, 1, 1, 1e8, 0.5])), "rho"),
    (dict(upper=np.array([2000, 100, 1, 1e8, 0.6])), "nu"),
])
def test_parameter_space_rejects(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ParameterSpace(np.array([1050, 2.39, 0.003, 150e3, 0.45]), **kwargs)


def _set(d, path, value):
    d = copy.deepcopy(d)
    cur = d
    keys = path.split(".")
    for k in keys[:-1]:
        cur = cur.setdefault(k, {})
    cur[keys[-1]] = value
    return d


@pytest.mark.parametrize("path,value,field", [
    ("parameters.nu", 0.5, "parameters.nu"),
    ("parameters.nu", 0.7, "parameters.nu"),
    ("geometry.thickness", -0.01, "geometry.thickness"),
    ("geometry.colour", "red", "geometry.colour"),
    ("noise.measurement_std", float("nan"), "noise.measurement_std"),
    ("discretisation.method", "euler", "discretisation.method"),
    ("estimation.bounds.E", [1e6, 1e8], "parameters.E"),
    ("estimation.bounds.rho", [10.0, 5.0], "estimation.bounds.rho"),
    ("inputs.pressure.heart_rate_bpm", 400, "inputs.pressure.heart_rate_bpm"),
    ("parameters.E", "soft", "parameters.E"),
    ("unknown_section", {}, "unknown_section"),
    # hardened (docs/formats.md §2.1): finite numbers in documented ranges, typed list entries, size caps
    ("parameters.E", 10**400, "parameters.E"),
    ("parameters.rho", float("inf"), "parameters.rho"),
    ("parameters.nu", 1e-300, "parameters.nu"),
    ("parameters.E", True, "parameters.E"),
    ("geometry.length", 1e308, "geometry.length"),
    ("geometry.radius_long", -float("inf"), "geometry.radius_long"),
    ("geometry.grid", [9, 2, 2], "geometry.grid[1]"),
    ("geometry.grid", [9, 4.5, 2], "geometry.grid[1]"),
    ("geometry.grid", [9, 10**30, 2], "geometry.grid[1]"),
    ("geometry.grid", [9, 4], "geometry.grid"),
    ("geometry.grid", [200, 200, 2], "geometry.grid"),
    ("geometry.grid", [40, 30, 2], "geometry.grid"),  # 6048 free DOFs without a reduction
    ("geometry", {1: "a", "b": 2}, "geometry.1"),
    ("estimation.estimate", [["E"]], "estimation.estimate"),
    ("estimation.bounds.E", [1.0, "x"], "estimation.bounds.E[1]"),
    ("estimation.prior_std.E", 1e6, "estimation.prior_std.E"),
    ("estimation.prior_std", {"E": 1e-12}, "estimation.prior_std.E"),
    ("estimation.ukf.alpha", 1e-300, "estimation.ukf.alpha"),
    ("inputs.pressure.rr_intervals", [1.0, "nan"], "inputs.pressure.rr_intervals[1]"),
    ("inputs.pressure.rr_intervals", [], "inputs.pressure.rr_intervals"),
    ("inputs.respiration", {"direction": ["x", 0, 0]}, "inputs.respiration.direction[0]"),
    ("inputs.respiration", {"direction": [1e308, 1e308, 0]}, "inputs.respiration.direction[0]"),
    ("inputs.respiration", {"direction": [0, 0, 0]}, "inputs.respiration.direction"),
    ("noise.process.kind", ["diagonal"], "noise.process.kind"),
    ("noise.initial.position_std", 1e-300, "noise.initial.position_std"),
    ("reduction", {"static_nu": [0.3] * 11}, "reduction.static_nu"),
    ("reduction", {"static_nu": [0.3, 0.5]}, "reduction.static_nu[1]"),
    ("observation", {"points": {"grid": [100, 100]}}, "observation.points"),
    ("observation", {"points": {"grid": [3, True]}}, "observation.points.grid[1]"),
    ("observation", {"points": ["epicardial_nodes"]}, "observation.points"),
    ("name", {"a": 1}, "name"),
    ("format_version", True, "format_version"),
])
def test_config_errors_name_the_field(paper_dict, path, value, field):
    with pytest.raises(ConfigError) as info:
        model_config_from_dict(_set(paper_dict, path, value))
    assert isinstance(info.value, InputError) and info.value.path is None
    assert info.value.field == field
    assert str(info.value).startswith(field + ": ")


def test_prior_std_si_is_checked_in_phi_units(paper_dict):
    d = _set(paper_dict, "estimation.prior_std", {"nu": 0.5})
    model_config_from_dict(_set(d, "estimation.prior_std_si", {"E": 3e4}))  # 0.2 in phi units
    with pytest.raises(ConfigError, match="prior std of 6.67e\\+06 in phi units") as info:
        model_config_from_dict(_set(d, "estimation.prior_std_si", {"E": 1e12}))
    assert info.value.field == "estimation.prior_std_si.E"


@pytest.mark.parametrize("data, kind", [([1, 2], "list"), ("model", "str"), (3, "int")])
def test_model_document_must_be_a_mapping(data, kind):
    with pytest.raises(ConfigError, match=f"a mapping expected, got {kind}") as info:
        model_config_from_dict(data)
    assert info.value.field is None
    assert str(info.value.in_file("m.yaml")).startswith("m.yaml: a mapping expected")


def test_config_defaults_and_numeric_strings(paper_dict):
    cfg = model_config_from_dict(_set(paper_dict, "parameters.E", "2.0e5"))
    assert cfg.theta[3] == 2e5
    cfg = model_config_from_dict({})
    np.testing.assert_allclose(cfg.theta, [1050, 2.39, 0.003, 150e3, 0.45])
    assert model_config_from_dict(None).geometry == cfg.geometry  # an empty file: the default model
    assert cfg.geometry.grid == (9, 4, 2) and cfg.input_names == ("pressure",)
    assert list(NAMES) == ["rho", "alpha1", "alpha2", "E", "nu"]
