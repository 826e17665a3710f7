"""Typed measurement and estimate sets (the in-memory side of the files in docs/formats.md)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from .files import InputError

__all__ = ["MeasurementSet", "EstimateSet", "frames_within", "SI_UNITS"]


def _frozen(a) -> bool:
    """True when neither ``a`` nor any array it views can be written: sharing it keeps a set immutable."""
    while isinstance(a, np.ndarray):
        if a.flags.writeable:
            return False
        a = a.base
    return a is None or isinstance(a, bytes)


def _ro(a, dtype=float):
    """A read-only array of ``dtype``: ``a`` itself when it already is one that nothing can write (another set's
    array, e.g. through ``dataclasses.replace``: no copy of the frames x points arrays), else a read-only copy."""
    if isinstance(a, np.ndarray) and a.dtype == np.dtype(dtype) and _frozen(a):
        return a
    a = np.array(a, dtype=dtype)
    a.setflags(write=False)
    return a


def _adopt(a, dtype=float):
    """``a`` read-only without a copy (:func:`_ro` for arrays this package just made from a validated set's: a fresh
    array, or a view of one that nothing can write, is frozen in place, with every array it views; another dtype is
    converted, a copy). Never for an array that anything else may still write."""
    if not isinstance(a, np.ndarray) or a.dtype != np.dtype(dtype):
        return _ro(a, dtype)
    b = a
    while isinstance(b, np.ndarray):
        b.flags.writeable = False
        b = b.base
    return a


_CHUNK = 65536
"""Covariances checked at a time (their temporaries stay a few MB however many frames and points)."""


def _first_bad_covariance(cov, seen):
    """``(index into the seen observations, reason)`` of the first seen covariance that is not finite, symmetric and
    positive definite, or None; checked in chunks of :data:`_CHUNK`."""
    idx = np.flatnonzero(seen.reshape(-1))
    flat = cov.reshape(-1, 3, 3)
    for start in range(0, idx.size, _CHUNK):
        cs = flat[idx[start:start + _CHUNK]]
        fin = np.isfinite(cs).all(axis=(1, 2))
        if not fin.all():
            return start + int(np.flatnonzero(~fin)[0]), "non-finite covariance for an observed point"
        scale = np.abs(cs).max(axis=(1, 2))
        asym = np.abs(cs - np.swapaxes(cs, -1, -2)).max(axis=(1, 2))
        if (asym > 1e-9 * scale).any():
            return start + int(np.flatnonzero(asym > 1e-9 * scale)[0]), "not symmetric"
        ev = np.linalg.eigvalsh(0.5 * (cs + np.swapaxes(cs, -1, -2)))
        bad = ev[:, 0] <= 1e-12 * np.maximum(ev[:, -1], np.finfo(float).tiny)
        if bad.any():
            return start + int(np.flatnonzero(bad)[0]), "singular or not positive definite"
    return None


SI_UNITS = {"pressure": "Pa", "active_tension": "Pa", "respiration_x": "m", "respiration_y": "m", "respiration_z": "m"}
"""The unit of each input the model reads (``meta.input_units`` may leave it empty; any other unit is refused:
units were recorded but not checked before 2026-11-29, and a pressure in kPa was read as pascals)."""

@dataclass(frozen=True)
class MeasurementSet:
    """Tracked 3-D surface points per frame.

    Attributes
    ----------
    times : ndarray (K,)                 seconds from the first frame, strictly increasing
    point_ids : ndarray (P,) int          identifiers that survive filtering
    positions : ndarray (K, P, 3)         m, NaN where a point is not seen
    covariances : ndarray (K, P, 3, 3)    m^2 (NaN where not seen)
    reference : ndarray (P, 3)            reference (undeformed) position of each point, m
    inputs : ndarray (K, n_u)             known inputs at the frame times
    input_names, input_units : tuple of str
    frame : str                           'patch' (model frame) or 'rig'
    views : ndarray (K, P) int            cameras that saw each observation (0 if simulated)
    reprojection_rms : ndarray (K, P)     px (NaN if simulated)
    meta : dict                           free-form provenance (producer, seed, model hash, ...)
    """

    times: np.ndarray
    point_ids: np.ndarray
    positions: np.ndarray
    covariances: np.ndarray
    reference: np.ndarray
    inputs: np.ndarray
    input_names: tuple = ()
    input_units: tuple = ()
    frame: str = "patch"
    views: np.ndarray | None = None
    reprojection_rms: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        t = _ro(self.times).reshape(-1)
        K = t.size
        if K < 1:
            raise InputError(None, "at least one frame expected", "times")
        if not np.isfinite(t).all() or (np.diff(t) <= 0).any():
            raise InputError(None, "finite and strictly increasing values expected", "times")
        pos = _ro(self.positions)
        if pos.ndim != 3 or pos.shape[0] != K or pos.shape[2] != 3:
            raise InputError(None, f"shape ({K}, P, 3) expected, got {pos.shape}", "positions")
        P = pos.shape[1]
        if np.isinf(pos).any():
            raise InputError(None, "infinite values (use NaN for points not seen)", "positions")
        cov = _ro(self.covariances)
        if cov.shape != (K, P, 3, 3):
            raise InputError(None, f"shape ({K}, {P}, 3, 3) expected, got {cov.shape}", "covariances")
        seen = np.isfinite(pos).all(axis=2)
        partial = np.isfinite(pos).any(axis=2) & ~seen
        if partial.any():
            k, p = np.argwhere(partial)[0]
            raise InputError(None, f"frame {k}, point {p} has some but not all coordinates NaN", "positions")
        found = _first_bad_covariance(cov, seen)
        if found is not None:
            k, p = np.argwhere(seen)[found[0]]
            raise InputError(None, f"frame {k}, point {p}: {found[1]}", "covariances")
        ref = _ro(self.reference)
        if ref.shape != (P, 3) or not np.isfinite(ref).all():
            raise InputError(None, f"finite array of shape ({P}, 3) expected, got {ref.shape}", "reference")
        ids = _ro(self.point_ids, np.int64).reshape(-1)
        if ids.size != P or np.unique(ids).size != P:
            raise InputError(None, f"{P} unique identifiers expected", "point_ids")
        u = _ro(self.inputs)
        if u.ndim == 1:
            u = _ro(u.reshape(K, -1))
        if u.shape[0] != K or not np.isfinite(u).all():
            raise InputError(None, f"finite array of shape ({K}, n_u) expected, got {u.shape}", "inputs")
        names = tuple(self.input_names)
        units = tuple(self.input_units) or tuple("" for _ in names)
        if len(names) != u.shape[1] or len(units) != len(names):
            raise InputError(None, f"{u.shape[1]} names and units expected", "input_names/input_units")
        for name, unit in zip(names, units):
            si = SI_UNITS.get(str(name))
            if si is not None and str(unit).strip() and str(unit).strip().lower() != si.lower():
                raise InputError(None, f"{name!r} in {unit!r}: the inputs the model reads are in SI units ({name} in "
                                       f"{si}); convert the column (heartcv measure converts inputs.csv's "
                                       "pressure_kpa, pressure_mmhg, respiration_x_mm)", "meta.input_units")
        if self.frame not in ("patch", "rig"):
            raise InputError(None, f"'patch' or 'rig' expected, got {self.frame!r}", "frame")
        views = _ro(np.zeros((K, P), np.int64) if self.views is None else self.views, np.int64)
        rms = _ro(np.full((K, P), np.nan) if self.reprojection_rms is None else self.reprojection_rms)
        if views.shape != (K, P) or rms.shape != (K, P):
            raise InputError(None, f"shape ({K}, {P}) expected", "views/reprojection_rms")
        for name, val in (("times", t), ("positions", pos), ("covariances", cov), ("reference", ref),
                          ("point_ids", ids), ("inputs", u), ("views", views), ("reprojection_rms", rms)):
            object.__setattr__(self, name, val)
        object.__setattr__(self, "input_names", names)
        object.__setattr__(self, "input_units", units)

    @classmethod
    def _derived(cls, base: MeasurementSet, *, check: bool = True, **changes) -> MeasurementSet:
        """``dataclasses.replace(base, **changes)`` for a set this package derives from a validated ``base`` (a
        subset of its points or frames, the same points in another frame, other references): neither validated
        again (``base`` was, on construction; a set read from a file or built through the constructor always is)
        nor copied (the changed arrays are frozen in place, :func:`_adopt`: fresh arrays, or views of ``base``'s).
        Only the shapes are checked, against each other (a mistake in the caller, ValueError; ``check`` false: not
        even they, for a set whose other arrays the caller replaces at once, through this method)."""
        unknown = set(changes) - {f.name for f in fields(cls)}
        if unknown:
            raise TypeError(f"unknown fields {sorted(unknown)}")
        out = object.__new__(cls)
        for f in fields(cls):
            object.__setattr__(out, f.name, changes.get(f.name, getattr(base, f.name)))
        for name in ("times", "positions", "covariances", "reference", "inputs", "reprojection_rms"):
            if name in changes:
                object.__setattr__(out, name, _adopt(changes[name]))
        for name in ("point_ids", "views"):
            if name in changes:
                object.__setattr__(out, name, _adopt(changes[name], np.int64))
        object.__setattr__(out, "input_names", tuple(out.input_names))
        object.__setattr__(out, "input_units", tuple(out.input_units))
        if not check:
            return out
        K, P = out.times.size, out.point_ids.size
        expect = {"times": (K,), "positions": (K, P, 3), "covariances": (K, P, 3, 3), "reference": (P, 3),
                  "point_ids": (P,), "inputs": (K, len(out.input_names)), "views": (K, P),
                  "reprojection_rms": (K, P)}
        for name, shape in expect.items():
            if getattr(out, name).shape != shape:
                raise ValueError(f"{name}: shape {shape} expected, got {getattr(out, name).shape}")
        return out

    @property
    def n_frames(self) -> int:
        return self.times.size

    @property
    def n_points(self) -> int:
        return self.point_ids.size

    @property
    def seen(self) -> np.ndarray:
        """(K, P) bool: point observed in frame."""
        return np.isfinite(self.positions).all(axis=2)

    def input_columns(self, names) -> np.ndarray:
        """Inputs (K, len(names)) in the order of ``names``; ValueError naming a missing one."""
        idx = []
        for n in names:
            if n not in self.input_names:
                raise InputError(None, f"the model needs input {n!r}, the file has {list(self.input_names)}", "inputs")
            idx.append(self.input_names.index(n))
        return self.inputs[:, idx]

    def translation(self) -> np.ndarray:
        """Known rigid translation (K, 3) from inputs ``respiration_x/y/z`` (zeros if absent)."""
        names = ("respiration_x", "respiration_y", "respiration_z")
        if all(n in self.input_names for n in names):
            return self.input_columns(names)
        return np.zeros((self.n_frames, 3))


@dataclass(frozen=True)
class EstimateSet:
    """Per-step output of an estimator (one file per estimator run).

    Attributes
    ----------
    estimator : str
    times : (K,)
    point_ids : (P,)
    state_mean : (K, n_x)                 kinematic state posterior mean
    state_var : (K, n_x)                  its covariance diagonal
    theta : (K, 5)                        parameter posterior mean (physical units)
    theta_std : (K, 5)                    parameter posterior std (0 for fixed parameters)
    predictions : (K, P, 3)               one-step predicted position of every point (prior at step 0)
    innovations : (K, P, 3)               measurement minus prediction (NaN where not seen)
    nis : (K,)                            normalised innovation squared (NaN if nothing seen)
    nis_dof : (K,) int                    its degrees of freedom
    truncation_events : (K,) int
    step_time : (K,)                      wall time per step, s
    completed_steps : int                 steps completed (== K unless the run stopped)
    meta : dict
    phi_mean : (K, M), optional           joint estimators: parameter block mean in phi coordinates
    phi_cov : (K, M, M), optional         its covariance (``meta['estimated']`` names the M parameters)
    filtered : (K, P, 3), optional        filtered (posterior) position of every point after the update of
                                          step k, ``offset + H @ state_mean[k]`` in the frame of ``predictions``
                                          (NaN for dropped points and rows after ``completed_steps``; absent
                                          from files written before it was recorded)
    heart_rate : (K, 2), optional         the GE with a sampled heart rate: its posterior mean and standard
                                          deviation per step (Hz)
    respiration_rate : (K, 2), optional   the GE with a sampled respiration rate: likewise (Hz)
    log_likelihood : (K,), optional       the model-based estimators: log p(y_k | y_0 .. y_(k-1)) of each step's
                                          update, the Gaussian predictive density of the measurements used (nats,
                                          positions in metres; NaN where nothing was seen or the step did not run)
    """

    estimator: str
    times: np.ndarray
    point_ids: np.ndarray
    state_mean: np.ndarray
    state_var: np.ndarray
    theta: np.ndarray
    theta_std: np.ndarray
    predictions: np.ndarray
    innovations: np.ndarray
    nis: np.ndarray
    nis_dof: np.ndarray
    truncation_events: np.ndarray
    step_time: np.ndarray
    completed_steps: int
    meta: dict = field(default_factory=dict)
    phi_mean: np.ndarray | None = None
    phi_cov: np.ndarray | None = None
    filtered: np.ndarray | None = None
    heart_rate: np.ndarray | None = None
    respiration_rate: np.ndarray | None = None
    log_likelihood: np.ndarray | None = None

    def __post_init__(self):
        K = np.asarray(self.times).size
        if (self.phi_mean is None) != (self.phi_cov is None):
            raise InputError(None, "both or neither expected", "phi_mean and phi_cov")
        if self.phi_mean is not None:
            pm, pc = np.asarray(self.phi_mean), np.asarray(self.phi_cov)
            if pm.ndim != 2 or pm.shape[0] != K or pc.shape != (K, pm.shape[1], pm.shape[1]):
                raise InputError(None, f"shapes (K, M) and (K, M, M) expected, got {pm.shape}, {pc.shape}",
                                 "phi_mean/phi_cov")
        P = np.asarray(self.point_ids).size
        expect = {
            "state_mean": (K, None), "state_var": (K, None), "theta": (K, 5), "theta_std": (K, 5),
            "predictions": (K, P, 3), "innovations": (K, P, 3), "nis": (K,), "nis_dof": (K,),
            "truncation_events": (K,), "step_time": (K,),
        }
        if self.filtered is not None:
            expect["filtered"] = (K, P, 3)
        for name in ("heart_rate", "respiration_rate"):
            if getattr(self, name) is not None:
                expect[name] = (K, 2)
        if self.log_likelihood is not None:
            expect["log_likelihood"] = (K,)
        for name, shape in expect.items():
            a = np.asarray(getattr(self, name))
            if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
                raise InputError(None, f"shape {shape} expected, got {a.shape}", f"{name}")
        if not 0 <= self.completed_steps <= K:
            raise InputError(None, f"0..{K} expected, got {self.completed_steps}", "completed_steps")

    @property
    def complete(self) -> bool:
        return self.completed_steps == np.asarray(self.times).size

    def prediction_rmse(self) -> float:
        """RMS over points, coordinates-per-point norm and steps k >= 1 of the one-step prediction error (m)."""
        e = np.asarray(self.innovations)[1 : self.completed_steps]
        d2 = np.sum(e**2, axis=-1)
        d2 = d2[np.isfinite(d2)]
        return float(np.sqrt(d2.mean())) if d2.size else float("nan")


def frames_within(times, duration_s: float) -> int:
    """How many frames lie within the first ``duration_s`` seconds of ``times`` (s, increasing): those with
    ``t - t_0 < duration_s`` (a frame a rounding error short of ``duration_s`` counts as at it, so 4 s at exactly
    25 fps is 100 frames)."""
    t = np.asarray(times, float)
    if t.size == 0:
        return 0
    return int(np.count_nonzero(t - t[0] < duration_s - 1e-9 * max(abs(duration_s), 1.0)))
