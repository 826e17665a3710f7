"""File I/O of the tracker package: model YAML, measurement / estimate / truth ``.npz`` files.

Every ``.npz`` holds its arrays plus one ``meta_json`` entry (UTF-8 JSON with ``format``, ``format_version``,
the producing ``heartcv`` version and the inputs' hashes). Writes are atomic: a temporary file in the
target directory is renamed over the destination only when complete. Formats: ``docs/formats.md``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from pathlib import Path
import tempfile
import zipfile

import numpy as np

from . import __version__
from .config import ConfigError, ModelConfig, model_config_from_dict
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
    "MEASUREMENT_FORMAT",
    "ESTIMATE_FORMAT",
    "TRUTH_FORMAT",
]

MEASUREMENT_FORMAT = ("heartcv.measurements", 1)
ESTIMATE_FORMAT = ("heartcv.estimates", 1)
TRUTH_FORMAT = ("heartcv.truth", 1)
STUDY_FORMAT = ("heartcv.study", 1)


class FileFormatError(ValueError):
    """A file is missing, unreadable, truncated or not of the expected format; ``path`` names it."""

    def __init__(self, path, message):
        super().__init__(f"{path}: {message}")
        self.path = str(path)


def file_hash(path) -> str:
    """``sha256:<hex>`` of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return "sha256:" + h.hexdigest()


@contextlib.contextmanager
def atomic_path(path, suffix=None):
    """Yield a temporary path beside ``path``; rename it over ``path`` only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix or ".tmp",
                               dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file ordinary permissions
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


# -- model ---------------------------------------------------------------------------------------
def _load_yaml(path: Path, what: str):
    """The parsed YAML of ``path``; FileFormatError naming the file when it cannot be read or parsed."""
    import yaml

    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise FileFormatError(path, f"cannot read {what} ({exc.strerror})") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise FileFormatError(path, f"not valid YAML: {exc}") from None


def read_model(path) -> ModelConfig:
    """Read and validate a model YAML file (ConfigError names the field, FileFormatError the file)."""
    path = Path(path)
    data = _load_yaml(path, "model file")
    try:
        return model_config_from_dict(data)
    except ConfigError as exc:
        raise ConfigError(exc.field, f"{str(exc).split(': ', 1)[1]} (in {path})") from None


# -- npz helpers -----------------------------------------------------------------------------------
def _write_npz(path, fmt, arrays: dict, meta: dict):
    meta = dict(meta)
    meta.update({"format": fmt[0], "format_version": fmt[1], "heartcv_version": __version__})
    payload = {k: np.asarray(v) for k, v in arrays.items() if v is not None}
    payload["meta_json"] = np.frombuffer(json.dumps(meta, sort_keys=True, default=_json_default).encode(),
                                         dtype=np.uint8)
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **payload)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _read_npz(path, fmt, required):
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(path, "no such file")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        raise FileFormatError(path, f"not a readable .npz file (truncated or corrupt: {exc})") from None
    if "meta_json" not in data:
        raise FileFormatError(path, "no meta_json entry: not a heartcv file")
    try:
        meta = json.loads(bytes(data.pop("meta_json")).decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FileFormatError(path, f"corrupt metadata ({exc})") from None
    if meta.get("format") != fmt[0]:
        raise FileFormatError(path, f"format {fmt[0]!r} expected, got {meta.get('format')!r}")
    if meta.get("format_version") != fmt[1]:
        raise FileFormatError(path, f"{fmt[0]} version {fmt[1]} supported, got {meta.get('format_version')!r}")
    missing = [k for k in required if k not in data]
    if missing:
        raise FileFormatError(path, f"missing arrays {missing}")
    return data, meta


# -- measurements --------------------------------------------------------------------------------
def write_measurements(path, m: MeasurementSet, meta: dict | None = None):
    md = dict(m.meta)
    md.update(meta or {})
    md.update({"input_names": list(m.input_names), "input_units": list(m.input_units), "frame": m.frame})
    _write_npz(path, MEASUREMENT_FORMAT, {
        "times": m.times, "point_ids": m.point_ids, "positions": m.positions, "covariances": m.covariances,
        "reference": m.reference, "inputs": m.inputs, "views": m.views, "reprojection_rms": m.reprojection_rms,
    }, md)


def read_measurements(path) -> MeasurementSet:
    data, meta = _read_npz(path, MEASUREMENT_FORMAT,
                           ("times", "point_ids", "positions", "covariances", "reference", "inputs"))
    try:
        return MeasurementSet(
            data["times"], data["point_ids"], data["positions"], data["covariances"], data["reference"],
            data["inputs"], tuple(meta.get("input_names", ())), tuple(meta.get("input_units", ())),
            meta.get("frame", "patch"), data.get("views"), data.get("reprojection_rms"), meta,
        )
    except ValueError as exc:
        raise FileFormatError(path, str(exc)) from None


# -- estimates ------------------------------------------------------------------------------------
_EST_ARRAYS = ("times", "point_ids", "state_mean", "state_var", "theta", "theta_std", "predictions",
               "innovations", "nis", "nis_dof", "truncation_events", "step_time")
_EST_OPTIONAL = ("phi_mean", "phi_cov", "filtered")


def write_estimates(path, e: EstimateSet, meta: dict | None = None):
    md = dict(e.meta)
    md.update(meta or {})
    md.update({"estimator": e.estimator, "completed_steps": int(e.completed_steps)})
    arrays = {k: getattr(e, k) for k in _EST_ARRAYS + _EST_OPTIONAL}
    _write_npz(path, ESTIMATE_FORMAT, arrays, md)


def read_estimates(path) -> EstimateSet:
    data, meta = _read_npz(path, ESTIMATE_FORMAT, _EST_ARRAYS)
    try:
        return EstimateSet(meta["estimator"], *(data[k] for k in _EST_ARRAYS), int(meta["completed_steps"]),
                           meta, *(data.get(k) for k in _EST_OPTIONAL))
    except (KeyError, ValueError) as exc:
        raise FileFormatError(path, f"inconsistent estimate file: {exc}") from None


# -- truth ----------------------------------------------------------------------------------------
def write_truth(path, sim, meta: dict | None = None):
    """Ground truth of a simulation (``tracker.simulate.Simulation``)."""
    _write_npz(path, TRUTH_FORMAT, {
        "times": sim.times, "theta": sim.theta, "inputs": sim.inputs, "translation": sim.translation,
        "states": sim.states, "node_displacements": sim.node_displacements, "point_param": sim.point_param,
        "reference": sim.reference, "positions": sim.positions,
    }, dict(meta or {}, input_names=list(sim.input_names)))


def read_truth(path) -> tuple[dict, dict]:
    return _read_npz(path, TRUTH_FORMAT, ("times", "theta", "positions", "reference"))


# -- Monte-Carlo study ----------------------------------------------------------------------------
def write_study(path, arrays: dict, meta: dict | None = None):
    """The arrays of a Monte-Carlo study (``heartcv simulate``), written atomically (docs/formats.md)."""
    _write_npz(path, STUDY_FORMAT, arrays, dict(meta or {}))


def read_study(path) -> tuple[dict, dict]:
    return _read_npz(path, STUDY_FORMAT, ())


# -- parameters (heartcv fit) ------------------------------------------------------------------------
PARAMETERS_FORMAT = ("heartcv.parameters", 1)
_PARAM_KEYS = ("format", "format_version", "theta", "theta_std", "units", "estimated", "fixed", "phi", "epsilon",
               "covariance", "cost", "dof", "reduced_chi2", "iterations", "evaluations", "converged", "status",
               "message", "frames", "points", "observations", "at_bound", "starts", "registration")


def _plain(o):
    """numpy scalars and arrays -> Python floats, ints, bools and lists (for yaml.safe_dump)."""
    if isinstance(o, dict):
        return {str(k): _plain(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_plain(v) for v in o]
    if isinstance(o, np.ndarray):
        return _plain(o.tolist())
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, Path):
        return str(o)
    return o


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
    for k, v in md.items():
        if k in _PARAM_KEYS:
            raise ValueError(f"meta: key {k!r} is reserved in a parameters file")
        d[k] = v
    return _plain(d)


def parameters_from_dict(d, path="<parameters>"):
    """A ``tracker.fit.FitResult`` from the mapping of a parameters file; FileFormatError naming the field."""
    from .fit import FitResult
    from .params import NAMES

    def bad(field_name, msg):
        return FileFormatError(path, f"{field_name}: {msg}")

    if not isinstance(d, dict):
        raise FileFormatError(path, "a YAML mapping expected: not a heartcv parameters file")
    if d.get("format") != PARAMETERS_FORMAT[0]:
        raise FileFormatError(path, f"format {PARAMETERS_FORMAT[0]!r} expected, got {d.get('format')!r}")
    if d.get("format_version") != PARAMETERS_FORMAT[1]:
        raise FileFormatError(path, f"{PARAMETERS_FORMAT[0]} version {PARAMETERS_FORMAT[1]} supported, "
                                    f"got {d.get('format_version')!r}")

    def number(v, field_name):
        if isinstance(v, str):  # PyYAML reads 1e-3 (no dot) as a string
            try:
                v = float(v)
            except ValueError:
                raise bad(field_name, f"a number expected, got {v!r}") from None
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise bad(field_name, f"a number expected, got {v!r}")
        return float(v)

    def per_name(key, names, required=True, default=0.0):
        v = d.get(key)
        if v is None:
            if required:
                raise bad(key, "required mapping {name: value} is missing")
            return np.full(len(names), default)
        if not isinstance(v, dict) or set(v) - set(names) or (required and set(names) - set(v)):
            raise bad(key, f"a mapping with the keys {list(names)} expected, got {v!r}")
        return np.array([number(v.get(n, default), f"{key}.{n}") for n in names])

    def matrix(v, field_name, M):
        if v is None:
            return None
        try:
            a = np.array([[number(x, field_name) for x in row] for row in v], float)
        except TypeError:
            raise bad(field_name, f"a {M}x{M} list of lists expected") from None
        if a.shape != (M, M) or not np.isfinite(a).all():
            raise bad(field_name, f"a finite {M}x{M} matrix expected, got shape {a.shape}")
        if np.abs(a - a.T).max(initial=0) > 1e-9 * np.abs(a).max(initial=0):
            raise bad(field_name, "not symmetric")
        return a

    theta = per_name("theta", NAMES)
    if not (theta[0] > 0 and theta[3] > 0 and theta[1] >= 0 and theta[2] >= 0 and 0 < theta[4] < 0.5
            and np.isfinite(theta).all()):
        raise bad("theta", f"outside the physical range (rho, E > 0; alpha >= 0; 0 < nu < 0.5): {theta.tolist()}")
    theta_std = per_name("theta_std", NAMES, required=False)
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
        if not isinstance(reg, dict) or "patch_from_rig" not in reg:
            raise bad("registration", "a mapping with patch_from_rig (4x4) expected")
        T = np.array(reg["patch_from_rig"], float) if isinstance(reg["patch_from_rig"], list) else None
        if T is None or T.shape != (4, 4) or not np.isfinite(T).all():
            raise bad("registration.patch_from_rig", "a finite 4x4 matrix expected")

    def opt(key, kind, default):
        v = d.get(key, default)
        if kind is float:
            return number(v, key)
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
    if not isinstance(at_bound, list) or any(n not in est for n in at_bound):
        raise bad("at_bound", f"a list of estimated names expected, got {at_bound!r}")
    meta = {k: v for k, v in d.items() if k not in _PARAM_KEYS}
    try:
        return FitResult(
            theta, theta_std, tuple(est), phi, cov_phi, cov_theta, epsilon,
            opt("cost", float, float("nan")), opt("dof", int, 0), opt("reduced_chi2", float, float("nan")),
            scaled,
            opt("iterations", int, 0), opt("evaluations", int, 0), opt("converged", bool, True),
            opt("status", int, 0), opt("message", str, ""), opt("frames", int, 0), opt("points", int, 0),
            opt("observations", int, 0), tuple(starts), tuple(at_bound), reg, meta, covariance_kind=kind,
        )
    except ValueError as exc:
        raise FileFormatError(path, str(exc)) from None


def write_parameters(path, result, meta: dict | None = None):
    """Write a ``tracker.fit.FitResult`` as a parameters file (YAML, ``heartcv.parameters`` v1), atomically."""
    import yaml

    d = parameters_to_dict(result, meta)
    text = ("# heartcv parameters: fitted theta [rho, alpha1, alpha2, E, nu] (SI) and its covariance, in SI and in\n"
            "# the estimators' coordinates phi (estimated subset). docs/formats.md, parameters file.\n")
    text += yaml.safe_dump(d, sort_keys=False, default_flow_style=None, width=120, allow_unicode=True)
    with atomic_path(path, suffix=Path(path).suffix or ".yaml") as tmp:
        Path(tmp).write_text(text, encoding="utf-8")


def read_parameters(path):
    """Read a parameters file into a ``tracker.fit.FitResult`` (FileFormatError names the file and field)."""
    path = Path(path)
    return parameters_from_dict(_load_yaml(path, "parameters file"), path)
