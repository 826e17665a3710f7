"""Structure-aware fuzzing of the hand-written input files: model (docs/formats.md §2), scene (§10) and target (§7).

Every case starts from a valid document (the committed samples and a model with every section switched on), mutates
one to three random nodes (a value replaced by NaN, infinities, negative, zero, huge or tiny numbers, a huge integer,
a huge list, a string, a bool, null, a mapping or a list of mappings; a numeric leaf scaled by a power of ten; a key
deleted or added; a list made shorter or longer) and validates the result. A case passes when the document is
accepted -- and then, for a model, the model builds and the matrices every stage uses are finite -- or when
:class:`~heartcv.tracker.files.InputError` (or a subclass) is raised. Anything else (TypeError, OverflowError,
LinAlgError, ...) is a bug: the failure lists the mutations that led to it.

The committed test runs a fixed seed for a bounded time per format (a few seconds in all). For a long local run::

    HEARTCV_FUZZ_SECONDS=120 HEARTCV_FUZZ_SEED=7 .venv/bin/python -m pytest -q tests/tracker/test_config_fuzz.py
"""

from __future__ import annotations

import copy
import math
import os
from pathlib import Path
import time

import numpy as np
import pytest

from heartcv.render.rig import build_rig
from heartcv.render.scene import scene_from_dict
from heartcv.targets import TargetSpec
from heartcv.tracker.config import ConfigError, model_config_from_dict
from heartcv.tracker.files import InputError, read_yaml
from heartcv.tracker.io import read_model
from heartcv.tracker.model import build_model

ROOT = Path(__file__).resolve().parents[2]
SECONDS = float(os.environ.get("HEARTCV_FUZZ_SECONDS", "1.0"))
SEED = int(os.environ.get("HEARTCV_FUZZ_SEED", "20240611"))
MAX_CASES = int(os.environ.get("HEARTCV_FUZZ_CASES", "100000"))
BUILD_NODES = 1500  # accepted models with more mesh nodes are validated but not built (time)
CHECK_STATES = 400  # built models with more states are not discretised (time)

# a model with every section switched on (docs/formats.md §2.11)
FULL_MODEL = {
    "format": "heartcv.model", "format_version": 1, "name": "full", "description": "every key",
    "geometry": {"length": 0.06, "width": 0.04, "thickness": 0.01, "radius_long": 0.08, "radius_circ": 0.035,
                 "grid": [7, 4, 2]},
    "parameters": {"rho": 1050.0, "alpha1": 2.39, "alpha2": 0.003, "E": 150000.0, "nu": 0.45},
    "estimation": {"estimate": ["E", "nu"], "prior_std": {"E": 0.5}, "prior_std_si": {"nu": 0.02},
                   "random_walk_std": {"E": 0.01}, "bounds": {"rho": [1.0, 1.0e5], "E": [1.0, 1.0e10],
                                                              "nu": [0.0, 0.5]},
                   "epsilon": {"alpha1": 0.001, "alpha2": 1.0e-6},
                   "ge": {"nodes": 5, "variant": "A", "sqrt": "cholesky", "truncation": "sequential"},
                   "ukf": {"alpha": 0.1, "beta": 2.0, "kappa": 0.0}},
    "inputs": {"pressure": {"source": "lv", "heart_rate_bpm": 60.0, "rr_intervals": [1.0, 0.9], "scale": 1.0,
                            "la_mean_mmhg": 8.0},
               "active_tension": {"t_max": 5000.0},
               "respiration": {"amplitude": 0.004, "frequency_hz": 0.25, "direction": [1.0, 0.3, 0.0], "n": 2,
                               "phase": 0.0},
               "sample_rate_hz": 250.0},
    "noise": {"measurement_std": 1.0e-4,
              "process": {"kind": "acceleration", "position_std": 1.0e-6, "velocity_std": 1.0e-4, "accel_psd": 1e-4},
              "initial": {"position_std": 1.0e-4, "velocity_std": 1.0e-3}},
    "discretisation": {"method": "modal", "frame_rate": 30.0},
    "reduction": {"modes": 10, "static_nu": [0.3, 0.45, 0.49]},
    "observation": {"points": {"grid": [3, 2]}, "margin": 0.1},
}

CHESSBOARD = {"format": "heartcv.target", "format_version": 1, "name": "chess", "type": "chessboard",
              "inner_corners": [9, 6], "square_m": 0.025, "description": "a chessboard"}


def _load(*names):
    return [read_yaml(ROOT / n) for n in names]


def _model_docs():
    docs = _load("sample_sequences/paper_patch.yaml", "sample_sequences/phantom/model.yaml",
                 "sample_sequences/paper_simulation.yaml")
    flat = copy.deepcopy(FULL_MODEL)
    flat["geometry"].update(radius_long=None, radius_circ=".inf")
    flat["noise"]["process"]["kind"] = "diagonal"
    flat["observation"] = {"points": "epicardial_nodes"}
    flat.pop("reduction")
    return docs + [copy.deepcopy(FULL_MODEL), flat]


def _scene_docs():
    return _load("sample_sequences/phantom/scene.yaml", "sample_sequences/phantom/instrument.yaml",
                 "sample_sequences/myocardium/scene.yaml")


def _target_docs():
    return _load("calibration_targets/charuco_11x8_12mm.yaml") + [copy.deepcopy(CHESSBOARD)]


# -- mutations ----------------------------------------------------------------------------------------------------
REPLACEMENTS = [
    math.nan, math.inf, -math.inf, -1, 0, 1, 2, 0.5, -0.5, 1e308, -1e308, 1e-300, 10**30, -(10**30), 10**400, 2**63,
    "x", "", "nan", "1e999", "-inf", "0.1", True, False, None, {}, {"x": 1}, [], [{"x": 1}], [1.0, 2.0, 3.0],
    [math.nan, 1.0, 1.0], ["a", "b"], [[1, 2], [3, 4]], {1: "a", "b": 2},
]
HUGE_LIST = [1] * 100_000


def _nodes(node, path=()):
    """(path, value) of every node below the root (of a long list, the first 20 entries only)."""
    if isinstance(node, dict):
        items = list(node.items())
    elif isinstance(node, list):
        items = list(enumerate(node[:20]))
    else:
        return
    for k, v in items:
        yield path + (k,), v
        yield from _nodes(v, path + (k,))


def _get(doc, path):
    for k in path:
        doc = doc[k]
    return doc


def _mutate(doc, rng: np.random.Generator):
    """Mutate ``doc`` in place (the root may be replaced: the new root is returned) and describe the mutation."""
    nodes = list(_nodes(doc))
    op = rng.integers(0, 8) if nodes else 7
    if op == 7 and rng.random() < 0.3 or not nodes:
        new = [None, [], [doc], "model", 3, {}][rng.integers(0, 6)]
        return new, f"root := {new!r:.60}"
    path, value = nodes[rng.integers(0, len(nodes))]
    parent = _get(doc, path[:-1])
    key = path[-1]
    if op <= 2 or op == 7:
        new = REPLACEMENTS[rng.integers(0, len(REPLACEMENTS))]
        if rng.random() < 0.03:
            new = HUGE_LIST
        parent[key] = list(new) if new is HUGE_LIST else copy.deepcopy(new)
        return doc, f"{path} := {'[1] * 100000' if new is HUGE_LIST else repr(new)[:60]}"
    if op == 3:  # scale a number by a power of ten, negate it, or shift an integer
        if isinstance(value, bool) or not isinstance(value, (int, float)) or abs(value) > 1e300:
            return _mutate(doc, rng)
        if isinstance(value, int) and rng.random() < 0.5:
            new = value + int(rng.choice([-3, -2, -1, 1, 2, 3, 100, 10**4, 10**7]))
        else:
            new = value * 10.0 ** int(rng.integers(-15, 16)) * (-1 if rng.random() < 0.2 else 1)
        parent[key] = new
        return doc, f"{path} := {new!r}"
    if op == 4:  # delete a key or a list entry
        del parent[key]
        return doc, f"del {path}"
    if op == 5:  # add a key (unknown, or one that exists elsewhere) to a mapping
        target = value if isinstance(value, dict) else parent if isinstance(parent, dict) else None
        if target is None:
            return _mutate(doc, rng)
        names = ["unknown", 7, None] + [p[-1] for p, _ in nodes if isinstance(p[-1], str)]
        name = names[rng.integers(0, len(names))]
        new = REPLACEMENTS[rng.integers(0, len(REPLACEMENTS))]
        target[name] = copy.deepcopy(new)
        return doc, f"{path}[{name!r}] := {new!r:.60}"
    # op == 6: change a list's length
    lst = value if isinstance(value, list) else parent if isinstance(parent, list) else None
    if lst is None or len(lst) > 1000:
        return _mutate(doc, rng)
    how = rng.integers(0, 3)
    if how == 0 and lst:
        lst.pop()
    elif how == 1:
        lst.append(copy.deepcopy(lst[-1]) if lst else 1)
    else:
        lst.extend([copy.deepcopy(lst[-1]) if lst else 1] * int(rng.choice([10, 1000, 20000])))
    return doc, f"{path}: length {len(lst)}"


def _fuzz(docs, check, seed: int, seconds: float, max_cases: int = MAX_CASES):
    """Run mutated copies of ``docs`` through ``check``; the failures (mutations, error) and the case count."""
    rng = np.random.default_rng(seed)
    failures, n = [], 0
    end = time.monotonic() + seconds
    while n < max_cases and time.monotonic() < end:
        n += 1
        doc = copy.deepcopy(docs[rng.integers(0, len(docs))])
        ops = []
        for _ in range(rng.integers(1, 4)):
            doc, what = _mutate(doc, rng)
            ops.append(what)
        try:
            with np.errstate(over="raise", invalid="raise", divide="raise", under="ignore"):
                check(doc)
        except InputError:
            pass
        except Exception as exc:  # noqa: BLE001 -- every other exception is the bug this test looks for
            failures.append(f"{'; '.join(ops)} -> {type(exc).__name__}: {str(exc)[:200]}")
    return failures, n


def _finite(name, a):
    a = np.asarray(a)
    assert a.size == 0 or np.isfinite(a).all(), f"{name}: non-finite values"


def check_model(doc):
    cfg = model_config_from_dict(doc)
    cfg.prior_std_phi()
    cfg.random_walk_std_phi()
    if math.prod(cfg.geometry.grid) > BUILD_NODES:
        return
    model = build_model(cfg)
    if model.state_dim > CHECK_STATES:
        return
    sys = model.system(cfg.theta)
    _finite("A", sys.A)
    _finite("B0", sys.B0)
    _finite("Q", model.process_noise())
    _finite("P0", model.initial_covariance())
    obs = model.observation(model.default_points())
    _finite("H", obs.H)
    _finite("frequencies", model.frequencies_hz(cfg.theta, 2))


def check_scene(doc):
    scene = scene_from_dict(doc)
    build_rig(scene.rig)
    _finite("convergence point", scene.convergence_point)


def check_target(doc):
    spec = TargetSpec.from_dict(doc)
    assert TargetSpec.from_dict(spec.to_dict()) == spec
    _finite("corners", spec.object_points())


@pytest.mark.parametrize("docs, check", [(_model_docs, check_model), (_scene_docs, check_scene),
                                         (_target_docs, check_target)], ids=["model", "scene", "target"])
def test_mutated_files_raise_only_input_errors(docs, check):
    failures, n = _fuzz(docs(), check, SEED, SECONDS)
    assert n > 10
    assert not failures, f"{len(failures)} of {n} mutated documents crashed:\n" + "\n".join(failures[:30])


def test_seed_documents_are_valid():
    for d in _model_docs():
        check_model(d)
    for d in _scene_docs():
        check_scene(d)
    for d in _target_docs():
        check_target(d)


# -- empty and non-mapping model files -------------------------------------------------------------------------------
@pytest.mark.parametrize("text", ["", "{}\n", "# only a comment\n", "---\n"])
def test_empty_model_file_is_the_default_model(tmp_path, text):
    """docs/formats.md §2: an empty file (or ``{}``) is a valid model, the default paper-sized patch."""
    path = tmp_path / "empty.yaml"
    path.write_text(text)
    cfg = read_model(path)
    assert cfg.geometry.grid == (9, 4, 2) and cfg.name == "model"
    model = build_model(cfg)
    assert model.state_dim == 168
    _finite("A", model.system(cfg.theta).A)


@pytest.mark.parametrize("text, kind", [("- 1\n- 2\n", "list"), ("just a string\n", "str"), ("42\n", "int"),
                                        ("[geometry]\n", "list")])
def test_model_file_that_is_not_a_mapping(tmp_path, text, kind):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as err:
        read_model(path)
    assert err.value.path == str(path) and kind in str(err.value)
    assert str(err.value).startswith(str(path))


def test_config_error_is_an_input_error():
    err = ConfigError("parameters.nu", "must lie in (0, 0.5), got 0.7")
    assert isinstance(err, InputError) and isinstance(err, ValueError)
    assert err.field == "parameters.nu" and err.path is None
    assert str(err) == "parameters.nu: must lie in (0, 0.5), got 0.7"
    moved = err.in_file("m.yaml")
    assert isinstance(moved, InputError) and moved.field == "parameters.nu"
    assert str(moved) == "m.yaml: parameters.nu: must lie in (0, 0.5), got 0.7"
