"""File I/O of the tracker package: model YAML, measurement / estimate / truth / study ``.npz`` files and the
parameters file of ``heartcv fit``.

Built on :mod:`heartcv.tracker.files` (the one file-handling foundation of heartcv): every reader validates the
whole file against its documented layout (docs/formats.md §2–§6, §12) — dtypes, shapes with named dimensions that
must agree, finiteness, metadata types — and raises :class:`~heartcv.tracker.files.InputError` naming the file and
the field; writes are atomic.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from . import __version__
from .config import ConfigError, ModelConfig, model_config_from_dict
from .files import (
    ArraySpec,
    InputError,
    atomic_path,
    check_provenance,
    dump_yaml,
    file_hash,
    get_field,
    get_matrix,
    plain,
    read_npz,
    read_yaml,
    write_npz,
)
from .measurements import EstimateSet, MeasurementSet

__all__ = [
    "FileFormatError",
    "atomic_path",
    "file_hash",
    "read_model",
    "read_measurements",
    "write_measurements",
    "read_estimates",
    "write_estimates",
    "write_truth",
    "read_truth",
    "read_study",
    "write_study",
    "read_parameters",
    "write_parameters",
    "MEASUREMENT_FORMAT",
    "ESTIMATE_FORMAT",
    "TRUTH_FORMAT",
    "PARAMETERS_FORMAT",
]

MEASUREMENT_FORMAT = ("heartcv.measurements", 1)
ESTIMATE_FORMAT = ("heartcv.estimates", 1)
TRUTH_FORMAT = ("heartcv.truth", 1)
STUDY_FORMAT = ("heartcv.study", 1)

#: The error of every reader (the one error type of heartcv; kept under its old name)
FileFormatError = InputError


# -- model ---------------------------------------------------------------------------------------
def read_model(path) -> ModelConfig:
    """Read and validate a model YAML file (InputError naming the file and the field)."""
    path = Path(path)
    data = read_yaml(path, "model file")
    try:
        return model_config_from_dict(data)
    except ConfigError as exc:
        raise exc.in_file(path) from None


# -- shared metadata checks --------------------------------------------------------------------------
def _meta_str_list(meta, key, path, n=None):
    v = get_field(meta, key, "str-list", path, default=[], prefix="meta.")
    if n is not None and len(v) != n:
        raise InputError(path, f"{n} entries expected, got {len(v)}", f"meta.{key}")
    return tuple(v)


def _meta_int_list(meta, key, path, hi):
    v = get_field(meta, key, "list", path, default=[], prefix="meta.")
    if any(isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < hi for i in v):
        raise InputError(path, f"a list of indices 0..{hi - 1} expected", f"meta.{key}")
    return v


# -- measurements --------------------------------------------------------------------------------
# Plausibility bounds (SI): no recording is longer than 1e7 s (4 months), no point 1 km from the rig, no input
# (pressure in Pa, respiration in m) beyond 1e9; values past them overflow the estimators' squares (1e308).
T_MAX, L_MAX, L2_MAX, U_MAX = 1e7, 1e3, 1e6, 1e9
_MEAS_SCHEMA = {
    "times": ArraySpec("f", ("K",), max_abs=T_MAX),
    "point_ids": ArraySpec("iu", ("P",)),
    "positions": ArraySpec("f", ("K", "P", 3), finite="nan", max_abs=L_MAX),
    "covariances": ArraySpec("f", ("K", "P", 3, 3), finite="nan", max_abs=L2_MAX),
    "reference": ArraySpec("f", ("P", 3), max_abs=L_MAX),
    "inputs": ArraySpec("f", None, max_abs=U_MAX),
    "views": ArraySpec("iu", ("K", "P"), required=False, max_abs=1e6),
    "reprojection_rms": ArraySpec("f", ("K", "P"), finite="nan", required=False, max_abs=1e7),
}


def write_measurements(path, m: MeasurementSet, meta: dict | None = None):
    md = dict(m.meta)
    md.update(meta or {})
    md.update({"input_names": list(m.input_names), "input_units": list(m.input_units), "frame": m.frame})
    write_npz(path, MEASUREMENT_FORMAT, {
        "times": m.times, "point_ids": m.point_ids, "positions": m.positions, "covariances": m.covariances,
        "reference": m.reference, "inputs": m.inputs, "views": m.views, "reprojection_rms": m.reprojection_rms,
    }, md)


def read_measurements(path) -> MeasurementSet:
    """Read and validate a measurement file (docs/formats.md §3)."""
    data, meta = read_npz(path, MEASUREMENT_FORMAT, _MEAS_SCHEMA)
    for a in data.values():     # read for this set alone: frozen in place, the set takes them without a copy
        if isinstance(a, np.ndarray) and a.base is None:
            a.flags.writeable = False
    K, P = data["positions"].shape[:2]
    u = data["inputs"]
    if u.ndim == 1:
        u = u.reshape(-1, 1)
    if u.ndim != 2 or u.shape[0] != K:
        raise InputError(path, f"shape ({K}, n_u) or ({K},) expected, got {data['inputs'].shape}", "inputs")
    names = _meta_str_list(meta, "input_names", path, u.shape[1])
    units = _meta_str_list(meta, "input_units", path) or ("",) * len(names)
    if len(units) != len(names):
        raise InputError(path, f"{len(names)} entries expected, got {len(units)}", "meta.input_units")
    frame = get_field(meta, "frame", "str", path, default="patch", prefix="meta.")
    _check_measure_meta(meta, path, K, P)
    try:
        return MeasurementSet(data["times"], data["point_ids"], data["positions"], data["covariances"],
                              data["reference"], u, names, units, frame, data.get("views"),
                              data.get("reprojection_rms"), meta)
    except InputError as exc:
        raise exc.in_file(path) from None


def _check_measure_meta(meta, path, K, P):
    """Types of the optional metadata that later stages use (docs/formats.md §3.2)."""
    if "reference_uv" in meta:
        get_matrix(meta["reference_uv"], (P, 2), path, "meta.reference_uv")
    if "reference_frame_index" in meta:
        v = _meta_int_list(meta, "reference_frame_index", path, K)
        if len(v) != P:
            raise InputError(path, f"{P} entries expected, got {len(v)}", "meta.reference_frame_index")
    for key in ("sigma_px", "stiffness_cycle"):
        if key in meta and meta[key] is not None:
            get_field(meta, key, "float", path, lo=0, prefix="meta.")
    for key in ("camera_names", "frame_names"):
        if key in meta:
            _meta_str_list(meta, key, path)
    if meta.get("registration") is not None:
        _check_registration(meta["registration"], path, "meta.registration")
    if meta.get("dropped_points") is not None:
        _meta_int_list(meta, "dropped_points", path, P)


def _check_registration(reg, path, field):
    """A registration mapping (parameters file, measurement metadata): ``patch_from_rig`` a finite rigid 4x4."""
    if not isinstance(reg, dict):
        raise InputError(path, "a mapping expected", field)
    if "patch_from_rig" in reg or field == "registration":
        T = get_matrix(reg.get("patch_from_rig"), (4, 4), path, f"{field}.patch_from_rig")
        R = T[:3, :3]
        if (np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or abs(np.linalg.det(R) - 1) > 1e-6
                or np.abs(T[3] - [0, 0, 0, 1]).max() > 0):
            raise InputError(path, "a rigid transform (rotation, translation, last row 0 0 0 1) expected",
                             f"{field}.patch_from_rig")
    if "rms_m" in reg:
        get_field(reg, "rms_m", "float", path, lo=0, prefix=f"{field}.")
    if "points_on_patch" in reg:
        v = get_field(reg, "points_on_patch", "list", path, prefix=f"{field}.")
        if any(isinstance(i, bool) or not isinstance(i, int) for i in v):
            raise InputError(path, "a list of point ids expected", f"{field}.points_on_patch")


# -- estimates ------------------------------------------------------------------------------------
_EST_ARRAYS = ("times", "point_ids", "state_mean", "state_var", "theta", "theta_std", "predictions",
               "innovations", "nis", "nis_dof", "truncation_events", "step_time")
_EST_OPTIONAL = ("phi_mean", "phi_cov", "filtered", "heart_rate", "respiration_rate", "log_likelihood")
_EST_SCHEMA = {
    "times": ArraySpec("f", ("K",), max_abs=T_MAX),
    "point_ids": ArraySpec("iu", ("P",)),
    "state_mean": ArraySpec("f", ("K", "NX"), finite="nan", max_abs=L2_MAX),
    "state_var": ArraySpec("f", ("K", "NX"), finite="nan", max_abs=1e12),
    "theta": ArraySpec("f", ("K", 5), finite="nan", max_abs=1e12),
    "theta_std": ArraySpec("f", ("K", 5), finite="nan", max_abs=1e12),
    "predictions": ArraySpec("f", ("K", "P", 3), finite="nan", max_abs=L_MAX),
    "innovations": ArraySpec("f", ("K", "P", 3), finite="nan", max_abs=2 * L_MAX),
    "nis": ArraySpec("f", ("K",), finite="nan", max_abs=1e100),
    "nis_dof": ArraySpec("iu", ("K",), max_abs=1e9),
    "truncation_events": ArraySpec("iu", ("K",), max_abs=1e9),
    "step_time": ArraySpec("f", ("K",), finite="nan", max_abs=T_MAX),
    "phi_mean": ArraySpec("f", ("K", "M"), finite="nan", required=False, max_abs=1e3),
    "phi_cov": ArraySpec("f", ("K", "M", "M"), finite="nan", required=False, max_abs=1e6),
    "filtered": ArraySpec("f", ("K", "P", 3), finite="nan", required=False, max_abs=L_MAX),
    "heart_rate": ArraySpec("f", ("K", 2), finite="nan", required=False, max_abs=1e3),
    "respiration_rate": ArraySpec("f", ("K", 2), finite="nan", required=False, max_abs=1e3),
    "log_likelihood": ArraySpec("f", ("K",), finite="nan", required=False, max_abs=1e100),
}
from .estimators import NAMES as ESTIMATORS  # noqa: E402  (the registry of estimator names)


def write_estimates(path, e: EstimateSet, meta: dict | None = None):
    md = dict(e.meta)
    md.update(meta or {})
    md.update({"estimator": e.estimator, "completed_steps": int(e.completed_steps)})
    arrays = {k: getattr(e, k) for k in _EST_ARRAYS + _EST_OPTIONAL}
    write_npz(path, ESTIMATE_FORMAT, arrays, md)


def _check_report_meta(meta, path, K):
    """The meta entries ``heartcv report`` reads (docs/formats.md §4): numbers made numbers (a numeric string
    becomes its float), the rest checked; an InputError names the field."""
    for key in ("heart_rate_hz", "heart_rate_std_hz", "respiration_rate_hz", "respiration_rate_std_hz"):
        if meta.get(key) is not None:
            meta[key] = get_field(meta, key, "float", path, lo=0, prefix="meta.")
    band = meta.get("heart_rate_band_hz")
    if band is not None:
        if not (isinstance(band, (list, tuple)) and len(band) == 2
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in band)
                and 0 < band[0] < band[1]):
            raise InputError(path, f"[lo, hi] with 0 < lo < hi expected, got {band!r}", "meta.heart_rate_band_hz")
        meta["heart_rate_band_hz"] = [float(band[0]), float(band[1])]
    for key in ("heart_rate_source", "respiration_rate_source"):
        if meta.get(key) is not None:
            get_field(meta, key, "str", path, prefix="meta.")
    if meta.get("rigid_ar_order") is not None:
        meta["rigid_ar_order"] = get_field(meta, "rigid_ar_order", "int", path, lo=0, hi=1000, prefix="meta.")
    if meta.get("field_degree") is not None:
        meta["field_degree"] = get_field(meta, "field_degree", "int", path, lo=0, hi=10, prefix="meta.")
    if meta.get("rigid_harmonics") is not None:
        meta["rigid_harmonics"] = get_field(meta, "rigid_harmonics", "int", path, lo=0, hi=1000, prefix="meta.")
    rd = meta.get("rigid_dynamics")
    if rd is not None and (not isinstance(rd, dict) or rd.get("source") not in ("refit", "fit")):
        raise InputError(path, "a mapping with source 'refit' or 'fit' expected", "meta.rigid_dynamics")
    od = meta.get("parameter_overdispersion")
    if od is not None:                                 # written by track (tracker.overdispersion summary)
        pre = "meta.parameter_overdispersion."
        if not isinstance(od, dict):
            raise InputError(path, f"a mapping expected, got {type(od).__name__}", pre.rstrip("."))
        od = dict(od)
        for key, kind, lo in (("kappa_final", "float", 0.0), ("nis_per_dof", "float", 0.0), ("alpha", "float", 0.0),
                              ("dof", "int", 0), ("frames_adjusted", "int", 0)):
            od[key] = get_field(od, key, kind, path, default=None, lo=lo, prefix=pre)
        if od.get("mode") is not None:
            get_field(od, "mode", "str", path, prefix=pre)
        if od["frames_adjusted"] and od["kappa_final"] is None:
            raise InputError(path, "required with frames_adjusted > 0, missing", pre + "kappa_final")
        meta["parameter_overdispersion"] = od
    if meta.get("fit_frames") is not None:
        meta["fit_frames"] = get_field(meta, "fit_frames", "int", path, lo=1, hi=max(K, 1), prefix="meta.")
    if meta.get("measurement_noise_m") is not None:
        meta["measurement_noise_m"] = get_field(meta, "measurement_noise_m", "float", path, lo=0, hi=1.0,
                                                prefix="meta.")
    for key in ("heldout_points", "left_out_points"):
        ids = meta.get(key)
        if ids is not None and (not isinstance(ids, list) or any(
                isinstance(i, bool) or not isinstance(i, int) or abs(i) >= 2**63 for i in ids)):
            raise InputError(path, "a list of point ids (integers) expected", f"meta.{key}")


def read_estimates(path) -> EstimateSet:
    """Read and validate an estimate file (docs/formats.md §4)."""
    data, meta = read_npz(path, ESTIMATE_FORMAT, _EST_SCHEMA)
    K, P = data["predictions"].shape[:2]
    estimator = get_field(meta, "estimator", "str", path, prefix="meta.")
    if estimator not in ESTIMATORS:
        raise InputError(path, f"one of {list(ESTIMATORS)} expected, got {estimator!r}", "meta.estimator")
    steps = get_field(meta, "completed_steps", "int", path, lo=0, hi=K, prefix="meta.")
    if (np.diff(data["times"]) <= 0).any():
        raise InputError(path, "strictly increasing frame times expected", "times")
    for key in ("nis_dof", "truncation_events"):
        if (data[key] < 0).any():
            raise InputError(path, "counts (integers >= 0) expected, got a negative value", key)
    for key in ("theta_std", "state_var", "nis", "step_time"):     # (NaN where not defined: allowed)
        if (data[key] < 0).any():
            raise InputError(path, f"values >= 0 expected (or NaN), got {float(np.nanmin(data[key])):.3g}", key)
    orphan = np.isfinite(data["innovations"]).any(axis=-1) & ~np.isfinite(data["predictions"]).all(axis=-1)
    if orphan.any():        # an innovation is the measurement minus a prediction: none without the prediction
        k, p = np.argwhere(orphan)[0]
        raise InputError(path, f"frame {k}, point {p}: an innovation where the prediction is NaN (innovations are "
                               "measurement minus prediction)", "innovations")
    M = data["phi_mean"].shape[1] if "phi_mean" in data else 0
    est = _meta_str_list(meta, "estimated", path, M if "phi_mean" in data else None)
    from .params import NAMES

    if any(n not in NAMES for n in est) or len(set(est)) != len(est):
        raise InputError(path, f"distinct names from {list(NAMES)} expected, got {list(est)}", "meta.estimated")
    held = _meta_str_list(meta, "held_parameters", path)
    if any(n not in NAMES for n in held):
        raise InputError(path, f"names from {list(NAMES)} expected, got {list(held)}", "meta.held_parameters")
    if meta.get("dropped_points") is not None:
        _meta_int_list(meta, "dropped_points", path, P)
    for key in ("theta0", "prior_std_phi"):
        if meta.get(key) is not None:
            get_matrix(meta[key], (5,) if key == "theta0" else (M,), path, f"meta.{key}")
    if meta.get("dt") is not None:
        get_field(meta, "dt", "float", path, lo=0, prefix="meta.")
    if meta.get("patch_from_rig") is not None:
        _check_registration({"patch_from_rig": meta["patch_from_rig"]}, path, "meta")
    for key in ("partial", "joseph", "modal_path", "without_input"):
        if key in meta:
            get_field(meta, key, "bool", path, prefix="meta.")
    _check_report_meta(meta, path, K)
    held_ids = meta.get("heldout_points")
    if isinstance(held_ids, list) and not set(held_ids) <= set(data["point_ids"].tolist()):
        raise InputError(path, "ids of the file's points (point_ids) expected; "
                               f"{sorted(set(held_ids) - set(data['point_ids'].tolist()))[:5]} are not",
                         "meta.heldout_points")
    try:
        return EstimateSet(estimator, *(data[k] for k in _EST_ARRAYS), steps, meta,
                           *(data.get(k) for k in _EST_OPTIONAL))
    except InputError as exc:
        raise exc.in_file(path) from None


# -- truth ----------------------------------------------------------------------------------------
_TRUTH_SCHEMA = {
    "times": ArraySpec("f", ("K",), max_abs=T_MAX),
    "theta": ArraySpec("f", ("K", 5), max_abs=1e12),
    "inputs": ArraySpec("f", ("K", "NU"), required=False, max_abs=U_MAX),
    "translation": ArraySpec("f", ("K", 3), required=False, max_abs=L_MAX),
    "states": ArraySpec("f", ("K", "NX"), required=False, max_abs=L2_MAX),
    "node_displacements": ArraySpec("f", ("K", "N", 3), required=False, max_abs=L_MAX),
    "point_param": ArraySpec("f", ("P", 3), required=False, max_abs=L_MAX),
    "reference": ArraySpec("f", ("P", 3), max_abs=L_MAX),
    "positions": ArraySpec("f", ("K", "P", 3), max_abs=L_MAX),
}


def write_truth(path, sim, meta: dict | None = None):
    """Ground truth of a simulation (``tracker.simulate.Simulation``)."""
    write_npz(path, TRUTH_FORMAT, {
        "times": sim.times, "theta": sim.theta, "inputs": sim.inputs, "translation": sim.translation,
        "states": sim.states, "node_displacements": sim.node_displacements, "point_param": sim.point_param,
        "reference": sim.reference, "positions": sim.positions,
    }, dict(meta or {}, input_names=list(sim.input_names)))


def read_truth(path) -> tuple[dict, dict]:
    """``(arrays, meta)`` of a truth file, validated (docs/formats.md §5)."""
    data, meta = read_npz(path, TRUTH_FORMAT, _TRUTH_SCHEMA)
    t = data["times"]
    if t.size < 1 or (np.diff(t) <= 0).any():
        raise InputError(path, "at least one frame, strictly increasing times expected", "times")
    if "inputs" in data:
        _meta_str_list(meta, "input_names", path, data["inputs"].shape[1])
    return data, meta


# -- Monte-Carlo study ----------------------------------------------------------------------------
def write_study(path, arrays: dict, meta: dict | None = None):
    """The arrays of a Monte-Carlo study (``heartcv simulate``), written atomically (docs/formats.md §6)."""
    write_npz(path, STUDY_FORMAT, arrays, dict(meta or {}))


def read_study(path) -> tuple[dict, dict]:
    """``(arrays, meta)`` of a study file (safe loading; the arrays are checked by their consumer)."""
    return read_npz(path, STUDY_FORMAT, {})


# -- parameters (heartcv fit) ------------------------------------------------------------------------
PARAMETERS_FORMAT = ("heartcv.parameters", 1)
_PARAM_KEYS = ("format", "format_version", "theta", "theta_std", "units", "estimated", "fixed", "phi", "epsilon",
               "covariance", "cost", "dof", "reduced_chi2", "iterations", "evaluations", "converged", "status",
               "message", "frames", "points", "observations", "at_bound", "starts", "registration",
               "estimated_input")


def parameters_to_dict(result, meta: dict | None = None) -> dict:
    """The YAML mapping of a parameters file (``heartcv.parameters`` v1) for a ``tracker.fit.FitResult``."""
    from .params import NAMES, UNITS

    est = list(result.estimated)
    d = {"format": PARAMETERS_FORMAT[0], "format_version": PARAMETERS_FORMAT[1], "heartcv_version": __version__}
    md = dict(result.meta)
    md.update(meta or {})
    md.pop("heartcv_version", None)
    d.update({
        "theta": dict(zip(NAMES, map(float, result.theta))),
        "theta_std": dict(zip(NAMES, map(float, result.theta_std))),
        "units": dict(zip(NAMES, UNITS)),
        "estimated": est,
        "fixed": list(result.fixed),
        "phi": dict(zip(est, map(float, result.phi))),
        "epsilon": {"alpha1": float(result.epsilon[0]), "alpha2": float(result.epsilon[1])},
        "covariance": {
            "theta": None if result.cov_theta is None else result.cov_theta,
            "phi": None if result.cov_phi is None else result.cov_phi,
            "scaled": bool(result.covariance_scaled),
            "kind": str(result.covariance_kind),
        },
        "cost": float(result.cost),
        "dof": int(result.dof),
        "reduced_chi2": float(result.reduced_chi2),
        "iterations": int(result.iterations),
        "evaluations": int(result.evaluations),
        "converged": bool(result.converged),
        "status": int(result.status),
        "message": str(result.message),
        "frames": int(result.frames),
        "points": int(result.points),
        "observations": int(result.observations),
        "at_bound": list(result.at_bound),
        "starts": list(result.starts),
        "registration": result.registration,
    })
    if result.estimated_input is not None:
        d["estimated_input"] = result.estimated_input
    for k, v in md.items():
        if k in _PARAM_KEYS:
            raise ValueError(f"meta: key {k!r} is reserved in a parameters file")
        d[k] = v
    return plain(d)


def parameters_from_dict(d, path="<parameters>"):
    """A ``tracker.fit.FitResult`` from the mapping of a parameters file; FileFormatError naming the field."""
    from .fit import FitResult
    from .params import NAMES

    def bad(field_name, msg):
        return InputError(path, msg, field_name)

    if not isinstance(d, dict):
        raise InputError(path, "a YAML mapping expected: not a heartcv parameters file")
    if d.get("format") != PARAMETERS_FORMAT[0]:
        raise bad("format", f"{PARAMETERS_FORMAT[0]!r} expected, got {str(d.get('format'))[:80]!r}")
    if d.get("format_version") != PARAMETERS_FORMAT[1]:
        raise bad("format_version", f"{PARAMETERS_FORMAT[1]} supported, got {str(d.get('format_version'))[:80]}")

    def number(v, field_name):
        return get_field({field_name: v}, field_name, "float", path)

    def per_name(key, names, required=True, default=0.0):
        v = d.get(key)
        if v is None:
            if required:
                raise bad(key, "required mapping {name: value} is missing")
            return np.full(len(names), default)
        if not isinstance(v, dict) or set(map(str, v)) - set(names) or (required and set(names) - set(v)):
            raise bad(key, f"a mapping with the keys {list(names)} expected")
        return np.array([number(v.get(n, default), f"{key}.{n}") for n in names])

    def matrix(v, field_name, M):
        a = get_matrix(v, (M, M), path, field_name, allow_none=True)
        if a is not None and np.abs(a - a.T).max(initial=0) > 1e-9 * np.abs(a).max(initial=0):
            raise bad(field_name, "not symmetric")
        if a is not None and M and np.isfinite(a).all() and np.linalg.eigvalsh(a).min() < -1e-9 * max(
                np.abs(a).max(), np.finfo(float).tiny):
            raise bad(field_name, "not positive semi-definite (a negative variance)")
        return a

    theta = per_name("theta", NAMES)
    if not (theta[0] > 0 and theta[3] > 0 and theta[1] >= 0 and theta[2] >= 0 and 0 < theta[4] < 0.5
            and np.isfinite(theta).all()):
        raise bad("theta", f"outside the physical range (rho, E > 0; alpha >= 0; 0 < nu < 0.5): {theta.tolist()}")
    theta_std = per_name("theta_std", NAMES, required=False)
    for n, v in zip(NAMES, theta_std, strict=True):     # NaN (not determined, as the fit writes it) passes
        if v < 0:
            raise bad(f"theta_std.{n}", f"a standard deviation of at least 0 expected, got {v}")
    est = d.get("estimated", [])
    if not isinstance(est, list) or any(n not in NAMES for n in est) or len(set(est)) != len(est):
        raise bad("estimated", f"a list of distinct names from {list(NAMES)} expected, got {est!r}")
    est = [n for n in NAMES if n in est]
    M = len(est)
    eps = d.get("epsilon") or {}
    if not isinstance(eps, dict) or set(eps) - {"alpha1", "alpha2"}:
        raise bad("epsilon", f"a mapping {{alpha1, alpha2}} expected, got {eps!r}")
    epsilon = np.array([
        number(eps["alpha1"], "epsilon.alpha1") if "alpha1" in eps else (1e-3 * theta[1] if theta[1] > 0 else 1e-3),
        number(eps["alpha2"], "epsilon.alpha2") if "alpha2" in eps else (1e-3 * theta[2] if theta[2] > 0 else 1e-6),
    ])
    if not (epsilon > 0).all():
        raise bad("epsilon", f"positive offsets expected, got {epsilon.tolist()}")
    if d.get("phi") is not None:
        phi = per_name("phi", est)
    else:  # a hand-written file: phi of theta
        from .params import s_from_nu

        full = np.array([np.log(theta[0]), np.log(theta[1] + epsilon[0]), np.log(theta[2] + epsilon[1]),
                         np.log(theta[3]), s_from_nu(theta[4])])
        phi = full[[NAMES.index(n) for n in est]]
    cov = d.get("covariance") or {}
    if not isinstance(cov, dict) or set(cov) - {"theta", "phi", "scaled", "kind"}:
        raise bad("covariance", f"a mapping {{theta, phi, scaled, kind}} expected, got {cov!r}")
    kind = cov.get("kind", "model")
    if kind not in ("model", "cluster-robust"):
        raise bad("covariance.kind", f"'model' or 'cluster-robust' expected, got {kind!r}")
    cov_theta = matrix(cov.get("theta"), "covariance.theta", M)
    cov_phi = matrix(cov.get("phi"), "covariance.phi", M)
    scaled = cov.get("scaled", False)
    if not isinstance(scaled, bool):
        raise bad("covariance.scaled", f"true or false expected, got {scaled!r}")
    reg = d.get("registration")
    if reg is not None:
        _check_registration(reg, path, "registration")

    def opt(key, kind, default):
        v = d.get(key, default)
        if kind is float:
            return v if key not in d else number(v, key)  # absent: NaN (cost, chi-square not recorded)
        if kind is int:
            if isinstance(v, bool) or not isinstance(v, int):
                raise bad(key, f"an integer expected, got {v!r}")
            return v
        if kind is bool:
            if not isinstance(v, bool):
                raise bad(key, f"true or false expected, got {v!r}")
            return v
        return str(v)

    starts = d.get("starts") or []
    at_bound = d.get("at_bound") or []
    if not isinstance(starts, list) or not all(isinstance(s, dict) for s in starts):
        raise bad("starts", "a list of mappings expected")
    if not isinstance(at_bound, list) or any(not isinstance(n, str) or n not in est for n in at_bound):
        raise bad("at_bound", f"a list of estimated names expected, got {at_bound!r}")
    meta = {k: v for k, v in d.items() if k not in _PARAM_KEYS}
    check_provenance(meta, path)
    try:
        return FitResult(
            theta, theta_std, tuple(est), phi, cov_phi, cov_theta, epsilon,
            opt("cost", float, float("nan")), opt("dof", int, 0), opt("reduced_chi2", float, float("nan")),
            scaled,
            opt("iterations", int, 0), opt("evaluations", int, 0), opt("converged", bool, True),
            opt("status", int, 0), opt("message", str, ""), opt("frames", int, 0), opt("points", int, 0),
            opt("observations", int, 0), tuple(starts), tuple(at_bound), reg, meta, covariance_kind=kind,
            estimated_input=_estimated_input(d.get("estimated_input"), path),
        )
    except InputError:         # a field's own check, already naming the file and the field
        raise
    except ValueError as exc:  # FitResult's own checks of the values it is given (validation, not computation)
        raise InputError(path, str(exc)) from None


def _estimated_input(entry, path):
    """The ``estimated_input`` entry of a parameters file, checked by building its block (FileFormatError naming
    the field)."""
    if entry is None:
        return None
    from .unknown_input import InputBlock

    try:
        InputBlock.from_dict(entry)
    except (ValueError, TypeError) as exc:
        text = str(exc)
        if "inhomogeneous" in text or "setting an array element" in text:   # numpy's words for ragged lists
            text = "a list of numbers has the wrong length or holds a list where a number belongs"
        raise InputError(path, text, "estimated_input") from None
    return entry


def write_parameters(path, result, meta: dict | None = None):
    """Write a ``tracker.fit.FitResult`` as a parameters file (YAML, ``heartcv.parameters`` v1), atomically."""
    d = parameters_to_dict(result, meta)
    text = dump_yaml(d, "heartcv parameters: fitted theta [rho, alpha1, alpha2, E, nu] (SI) and its covariance, in "
                        "SI and in\nthe estimators' coordinates phi (estimated subset). docs/formats.md, parameters "
                        "file.")
    with atomic_path(path, suffix=Path(path).suffix or ".yaml") as tmp:
        Path(tmp).write_text(text, encoding="utf-8")


def read_parameters(path):
    """Read a parameters file into a ``tracker.fit.FitResult`` (FileFormatError names the file and field)."""
    path = Path(path)
    return parameters_from_dict(read_yaml(path, "parameters file"), path)
