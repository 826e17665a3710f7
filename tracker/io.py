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
def read_model(path) -> ModelConfig:
    """Read and validate a model YAML file (ConfigError names the field, FileFormatError the file)."""
    import yaml

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise FileFormatError(path, f"cannot read model file ({exc.strerror})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise FileFormatError(path, f"not valid YAML: {exc}") from None
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
_EST_OPTIONAL = ("phi_mean", "phi_cov")


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
