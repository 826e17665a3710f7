"""The model configuration (the content of a model YAML file) as typed, validated values.

:func:`model_config_from_dict` accepts the parsed YAML mapping, rejects unknown keys and out-of-range values
with a :class:`ConfigError` that names the field (``parameters.nu``), and fills documented defaults.
The file format is documented in ``docs/formats.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

from .files import InputError
from .files import show as _show
from .geometry import PatchGeometry
from .params import DEFAULT_BOUNDS, NAMES, ParameterSpace

__all__ = ["ConfigError", "ModelConfig", "model_config_from_dict", "FORMAT", "FORMAT_VERSION", "SIZE_LIMITS",
           "MAX_FULL_DOF"]

FORMAT = "heartcv.model"
FORMAT_VERSION = 1


# prior standard deviation in phi units when the model file gives none (docs/spec/model.md §4.2)
DEFAULT_PRIOR_STD = {"rho": 0.3, "alpha1": 1.0, "alpha2": 1.0, "E": 0.5, "nu": 0.5}
GE_DEFAULTS = {"nodes": 5, "variant": "A", "sqrt": "cholesky", "truncation": "sequential"}
UKF_DEFAULTS = {"alpha": 0.1, "beta": 2.0, "kappa": 0.0}

MAX_FULL_DOF = 3000
"""Largest free-DOF count for which the full (unreduced) model is allowed (dense matrices of 72 MB each)."""
SIZE_LIMITS = {
    "grid_axis": 1000,        # nodes along one axis of geometry.grid
    "mesh_nodes": 10_000,     # nodes of the mesh (n_s n_t n_d): builds in about 15 s and < 1 GB with a reduction
    "observed_points": 1000,  # observed points (observation): 3000 measurement rows
    "static_nu": 10,          # entries of reduction.static_nu
    "rr_intervals": 100_000,  # entries of inputs.pressure.rr_intervals
}
"""Size caps of the model file (docs/formats.md §2.1): nothing a model file asks for allocates gigabytes."""
MAX_PRIOR_STD_PHI = 10.0
"""Largest prior or random-walk standard deviation in phi units (a factor e^10 on rho, E, alpha + eps)."""


class ConfigError(InputError):
    """A model file field is missing, unknown or out of range; ``field`` names it (dotted path, None for the file as
    a whole). An :class:`~heartcv.tracker.files.InputError` without a file: ``tracker.io.read_model`` attaches the
    file with :meth:`~heartcv.tracker.files.InputError.in_file`."""

    def __init__(self, field_name: str | None, message: str):
        super().__init__(None, message, field_name)


@dataclass(frozen=True)
class InputsConfig:
    pressure: str = "lv"  # lv | la | fourier60 | none
    heart_rate_bpm: float = 60.0
    rr_intervals: tuple | None = None
    pressure_scale: float = 1.0
    la_mean_mmhg: float = 8.0
    active_tension: float | None = None  # peak active stress T_max in Pa, None = no active column
    respiration: dict | None = None  # amplitude, frequency_hz, direction, n, phase
    sample_rate_hz: float = 250.0


@dataclass(frozen=True)
class NoiseConfig:
    measurement_std: float = 1.0e-4
    process_kind: str = "diagonal"  # diagonal | acceleration
    position_std: float = 1.0e-6
    velocity_std: float = 1.0e-4
    accel_psd: float = 1.0e-4
    initial_position_std: float = 1.0e-4
    initial_velocity_std: float = 1.0e-3


@dataclass(frozen=True)
class EstimationConfig:
    estimate: tuple = ("E", "nu")
    prior_std: dict = field(default_factory=dict)  # phi units per estimated parameter
    random_walk_std: dict = field(default_factory=dict)  # phi units per step
    bounds: dict = field(default_factory=dict)
    epsilon: tuple = (None, None)
    prior_std_si: dict = field(default_factory=dict)  # SI units per estimated parameter (converted at theta)
    ge: dict = field(default_factory=lambda: dict(GE_DEFAULTS))
    ukf: dict = field(default_factory=lambda: dict(UKF_DEFAULTS))


@dataclass(frozen=True)
class ModelConfig:
    name: str
    geometry: PatchGeometry
    theta: np.ndarray  # (5,) SI
    estimation: EstimationConfig
    inputs: InputsConfig
    noise: NoiseConfig
    method: str = "modal"
    frame_rate: float = 30.0
    reduction: dict | None = None  # {'modes': int, 'static_nu': [..]}
    observation: dict = field(default_factory=lambda: {"points": "epicardial_nodes"})
    raw: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def dt(self) -> float:
        return 1.0 / self.frame_rate

    def parameter_space(self) -> ParameterSpace:
        est = self.estimation
        lo = np.array([est.bounds.get(n, DEFAULT_BOUNDS[n])[0] for n in NAMES], float)
        up = np.array([est.bounds.get(n, DEFAULT_BOUNDS[n])[1] for n in NAMES], float)
        e1, e2 = est.epsilon
        e1 = e1 if e1 is not None else (1e-3 * self.theta[1] if self.theta[1] > 0 else 1e-3)
        e2 = e2 if e2 is not None else (1e-3 * self.theta[2] if self.theta[2] > 0 else 1e-6)
        try:
            return ParameterSpace(self.theta, est.estimate, lo, up, np.array([e1, e2]))
        except ValueError as exc:
            head, _, msg = str(exc).partition(": ")
            if head in NAMES:  # a parameter value outside its box
                raise ConfigError(f"parameters.{head}", f"{msg} (see estimation.bounds.{head})") from None
            if head.startswith("bounds."):
                raise ConfigError(f"estimation.{head}", msg) from None
            raise ConfigError("estimation", str(exc)) from None

    def prior_std_phi(self) -> np.ndarray:
        """Prior standard deviation of the estimated parameters in phi units (dim,).

        ``prior_std`` is taken as given; ``prior_std_si`` (SI units) is converted at the model's theta with
        the delta method, ``sigma_phi = sigma_theta / (d theta / d phi)``; absent entries get
        ``DEFAULT_PRIOR_STD``.
        """
        space = self.parameter_space()
        est = self.estimation
        jac = space.dtheta_dphi(space.to_phi(self.theta))
        out = []
        for name in space.estimated:
            i = NAMES.index(name)
            if name in est.prior_std:
                out.append(est.prior_std[name])
            elif name in est.prior_std_si:
                out.append(est.prior_std_si[name] / jac[i])
            else:
                out.append(DEFAULT_PRIOR_STD[name])
        return np.array(out, float)

    def random_walk_std_phi(self, dt: float | None = None) -> np.ndarray:
        """Random-walk standard deviation of the estimated parameters in phi units (dim,), per frame of ``dt``
        seconds: the model file gives it per frame at its ``frame_rate``, i.e. a rate per second of
        ``std * sqrt(frame_rate)``, so that a sequence at another frame rate gets the same change per second
        (``std * sqrt(dt * frame_rate)``). ``dt`` None: per frame at the model file's rate."""
        space = self.parameter_space()
        sd = np.array([self.estimation.random_walk_std.get(n, 0.0) for n in space.estimated], float)
        return sd if dt is None else sd * np.sqrt(float(dt) * self.frame_rate)

    @property
    def input_names(self) -> tuple:
        names = []
        if self.inputs.pressure != "none":
            names.append("pressure")
        if self.inputs.active_tension is not None:
            names.append("active_tension")
        return tuple(names)


# ---------------------------------------------------------------------------------------------
def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _range_text(lo, hi, lo_open, hi_open) -> str:
    return f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"


def _number(v, name: str, lo=-math.inf, hi=math.inf, lo_open=False, hi_open=False, allow_inf=False) -> float:
    """A finite float (``.inf`` too with ``allow_inf``) in the given range, or ConfigError naming ``name``."""
    if isinstance(v, str):  # a number written as text; PyYAML (YAML 1.1) reads 1.0e8 as a string
        try:
            v = float(v.strip().replace(".inf", "inf").replace(".Inf", "inf").replace(".INF", "inf"))
        except ValueError:
            raise ConfigError(name, f"a number expected, got {_show(v)}") from None
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ConfigError(name, f"a number expected, got {_show(v)}")
    try:
        v = float(v)
    except OverflowError:  # an integer beyond the float range
        raise ConfigError(name, f"a finite number expected, got {_show(v)}") from None
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise ConfigError(name, f"a finite number expected, got {v!r}")
    if allow_inf and v == math.inf:  # .inf means "unbounded" or "flat": not range-checked
        return v
    if (v <= lo if lo_open else v < lo) or (v >= hi if hi_open else v > hi):
        raise ConfigError(name, f"must lie in {_range_text(lo, hi, lo_open, hi_open)}, got {v!r}")
    return v


def _integer(v, name: str, lo: int, hi: int, what: str = "an integer") -> int:
    if not _is_int(v):
        raise ConfigError(name, f"{what} expected, got {_show(v)}")
    if not lo <= v <= hi:
        raise ConfigError(name, f"must lie in [{lo}, {hi}], got {_show(v)}")
    return int(v)


def _number_list(v, name: str, lo, hi, *, lo_open=False, hi_open=False, n=None, max_len=None,
                 what="a list of numbers") -> tuple:
    """A list of numbers in a range: ConfigError naming the list (wrong type or length) or the entry."""
    if (not isinstance(v, (list, tuple)) or (n is not None and len(v) != n)
            or (max_len is not None and len(v) > max_len)):
        raise ConfigError(name, f"{what} expected, got {_show(v)}")
    return tuple(_number(x, f"{name}[{i}]", lo, hi, lo_open, hi_open) for i, x in enumerate(v))


class _Section:
    """Reads one mapping, tracking its path for error messages and rejecting unknown keys."""

    def __init__(self, data, path: str):
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(path or None, f"a mapping expected, got {type(data).__name__}"
                              + ("" if path else " (a model file is a YAML mapping, docs/formats.md §2)"))
        self.data = dict(data)
        self.path = path
        self.seen: set = set()

    def _name(self, key):
        return f"{self.path}.{key}" if self.path else str(key)

    def has(self, key):
        return key in self.data

    def raw(self, key, default=None):
        self.seen.add(key)
        return self.data.get(key, default)

    def number(self, key, default=None, *, lo=-math.inf, hi=math.inf, lo_open=False, hi_open=False,
               allow_none=False, allow_inf=False):
        self.seen.add(key)
        if key not in self.data:
            if default is None and not allow_none:
                raise ConfigError(self._name(key), "required field is missing")
            return default
        v = self.data[key]
        if v is None and allow_none:
            return None
        return _number(v, self._name(key), lo, hi, lo_open, hi_open, allow_inf)

    def choice(self, key, default, options):
        self.seen.add(key)
        v = self.data.get(key, default)
        if not isinstance(v, str) or v not in options:
            raise ConfigError(self._name(key), f"one of {list(options)} expected, got {_show(v)}")
        return v

    def section(self, key):
        self.seen.add(key)
        return _Section(self.data.get(key), self._name(key))

    def done(self):
        unknown = sorted(set(self.data) - self.seen, key=str)
        if unknown:
            raise ConfigError(self._name(unknown[0]), f"unknown key (known: {sorted(self.seen, key=str)})")


def _geometry(sec: _Section) -> PatchGeometry:
    g = PatchGeometry()
    length = sec.number("length", g.length, lo=1e-4, hi=1.0)
    width = sec.number("width", g.width, lo=1e-4, hi=1.0)
    thick = sec.number("thickness", g.thickness, lo=1e-4, hi=1.0)
    r1 = sec.number("radius_long", g.radius_long, lo=0, lo_open=True, hi=100.0, allow_none=True, allow_inf=True)
    r2 = sec.number("radius_circ", g.radius_circ, lo=0, lo_open=True, hi=100.0, allow_none=True, allow_inf=True)
    r1 = math.inf if r1 is None else r1
    r2 = math.inf if r2 is None else r2
    grid = sec.raw("grid", list(g.grid))
    if not isinstance(grid, (list, tuple)) or len(grid) != 3:
        raise ConfigError(sec._name("grid"), f"three integer node counts [n_s, n_t, n_d] expected, got {_show(grid)}")
    cap = SIZE_LIMITS["grid_axis"]
    # n_s, n_t >= 3: the rim (first and last node along s and t) is clamped, so the mesh needs inner nodes
    grid = tuple(_integer(v, f"{sec._name('grid')}[{i}]", lo, cap, "an integer node count")
                 for i, (v, lo) in enumerate(zip(grid, (3, 3, 2))))
    if math.prod(grid) > SIZE_LIMITS["mesh_nodes"]:
        raise ConfigError(sec._name("grid"), f"{grid[0]} x {grid[1]} x {grid[2]} = {math.prod(grid)} nodes; at most "
                                             f"{SIZE_LIMITS['mesh_nodes']} allowed")
    sec.done()
    try:
        return PatchGeometry(length, width, thick, r1, r2, grid)
    except ValueError as exc:  # PatchGeometry's messages already name the field
        field_name, _, msg = str(exc).partition(": ")
        raise ConfigError(field_name if msg else sec.path, msg or str(exc)) from None


THETA_RANGES = {  # name: (default, lo, hi, lo_open, hi_open); SI units
    "rho": (1050.0, 1e-3, 1e6, False, False),
    "alpha1": (2.39, 0.0, 1e4, False, False),
    "alpha2": (0.003, 0.0, 100.0, False, False),
    "E": (150e3, 1e-3, 1e12, False, False),
    "nu": (0.45, 1e-3, 0.4999, False, False),
}
"""Valid values of each parameter in the model file (docs/formats.md §2.4)."""


def _theta(sec: _Section) -> np.ndarray:
    th = np.array([sec.number(n, d, lo=lo, hi=hi, lo_open=lo_o, hi_open=hi_o)
                   for n, (d, lo, hi, lo_o, hi_o) in THETA_RANGES.items()])
    sec.done()
    return th


def _per_parameter(sec: _Section, allowed, *, pair=False, hi=math.inf):
    out = {}
    for key in list(sec.data):
        if not isinstance(key, str) or key not in allowed:
            raise ConfigError(sec._name(key), f"unknown parameter (known: {list(allowed)})")
        if pair:
            v = sec.raw(key)
            if not isinstance(v, (list, tuple)) or len(v) != 2:
                raise ConfigError(sec._name(key), f"[lower, upper] expected, got {_show(v)}")
            out[key] = tuple(_number(x, f"{sec._name(key)}[{i}]", allow_inf=True) for i, x in enumerate(v))
        else:
            out[key] = sec.number(key, lo=0, hi=hi[key] if isinstance(hi, dict) else hi)
    sec.done()
    return out


def _estimation(sec: _Section) -> EstimationConfig:
    est = sec.raw("estimate", ["E", "nu"])
    if isinstance(est, str):
        est = [est]
    if not isinstance(est, (list, tuple)) or any(not isinstance(e, str) or e not in NAMES for e in est):
        raise ConfigError(sec._name("estimate"),
                          f"a list of parameter names from {list(NAMES)} expected, got {_show(est)}")
    prior = _per_parameter(sec.section("prior_std"), NAMES, hi=MAX_PRIOR_STD_PHI)
    prior_si = _per_parameter(sec.section("prior_std_si"), NAMES, hi={n: r[2] for n, r in THETA_RANGES.items()})
    both = sorted(set(prior) & set(prior_si))
    if both:
        raise ConfigError(sec._name("prior_std_si"), f"{both[0]} is also given in prior_std; give one of the two")
    for name, d in (("prior_std", prior), ("prior_std_si", prior_si)):
        for k, v in d.items():
            if v <= 0 and k in est:
                raise ConfigError(sec._name(f"{name}.{k}"), f"an estimated parameter needs a prior std > 0, got {v}")
    walk = _per_parameter(sec.section("random_walk_std"), NAMES, hi=MAX_PRIOR_STD_PHI)
    bounds = _per_parameter(sec.section("bounds"), NAMES, pair=True)
    eps = sec.section("epsilon")
    e1 = eps.number("alpha1", None, lo=0, lo_open=True, hi=THETA_RANGES["alpha1"][2], allow_none=True)
    e2 = eps.number("alpha2", None, lo=0, lo_open=True, hi=THETA_RANGES["alpha2"][2], allow_none=True)
    eps.done()
    g = sec.section("ge")
    nodes = g.number("nodes", GE_DEFAULTS["nodes"], lo=3, hi=51)
    if nodes != int(nodes) or int(nodes) % 2 == 0:
        raise ConfigError(g._name("nodes"), f"an odd integer >= 3 expected (shared centre node), got {nodes!r}")
    ge = {
        "nodes": int(nodes),
        "variant": g.choice("variant", GE_DEFAULTS["variant"], ("A", "B")),
        "sqrt": g.choice("sqrt", GE_DEFAULTS["sqrt"], ("cholesky", "correlation", "eigen")),
        "truncation": g.choice("truncation", GE_DEFAULTS["truncation"], ("sequential", "tallis", "none")),
    }
    g.done()
    u = sec.section("ukf")
    ukf = {
        "alpha": u.number("alpha", UKF_DEFAULTS["alpha"], lo=1e-4, hi=1),
        "beta": u.number("beta", UKF_DEFAULTS["beta"], lo=0, hi=1e3),
        "kappa": u.number("kappa", UKF_DEFAULTS["kappa"], lo=-1e3, hi=1e3),
    }
    u.done()
    sec.done()
    return EstimationConfig(tuple(est), prior, walk, bounds, (e1, e2), prior_si, ge, ukf)


def _inputs(sec: _Section) -> InputsConfig:
    d = InputsConfig()
    p = sec.section("pressure")
    source = p.choice("source", "lv", ("lv", "la", "fourier60", "none"))
    hr = p.number("heart_rate_bpm", d.heart_rate_bpm, lo=20, hi=250)
    rr = p.raw("rr_intervals", None)
    if rr is not None:
        cap = SIZE_LIMITS["rr_intervals"]
        rr = _number_list(rr, p._name("rr_intervals"), 0.24, 3.0, max_len=cap,
                          what=f"a list of 1 to {cap} beat lengths in [0.24, 3] s")
        if not rr:
            raise ConfigError(p._name("rr_intervals"), "a list of 1 or more beat lengths expected, got []")
    scale = p.number("scale", 1.0, lo=0, hi=1e3)
    la_mean = p.number("la_mean_mmhg", 8.0, lo=0, hi=60)
    p.done()
    act = sec.section("active_tension")
    t_max = act.number("t_max", None, lo=0, hi=1e7, allow_none=True) if act.data else None
    act.done()
    resp = None
    if sec.raw("respiration") is not None:
        r = sec.section("respiration")
        resp = {
            "amplitude": r.number("amplitude", 0.004, lo=0, hi=0.05),
            "frequency_hz": r.number("frequency_hz", 0.25, lo=0.01, hi=2.0),
            "n": int(r.number("n", 2, lo=1, hi=10)),
            "phase": r.number("phase", 0.0, lo=-1e6, hi=1e6),
        }
        direction = _number_list(r.raw("direction", [1.0, 0.3, 0.0]), r._name("direction"), -1e3, 1e3, n=3,
                                 what="a non-zero 3-vector (numbers in [-1000, 1000])")
        if not any(direction):
            raise ConfigError(r._name("direction"), f"a non-zero 3-vector expected, got {list(direction)}")
        resp["direction"] = direction
        r.done()
    rate = sec.number("sample_rate_hz", 250.0, lo=1, hi=1e5)
    sec.done()
    return InputsConfig(source, hr, rr, scale, la_mean, t_max, resp, rate)


def _noise(sec: _Section) -> NoiseConfig:
    d = NoiseConfig()
    meas = sec.number("measurement_std", d.measurement_std, lo=1e-9, hi=1.0)
    pr = sec.section("process")
    kind = pr.choice("kind", "diagonal", ("diagonal", "acceleration"))
    pos = pr.number("position_std", d.position_std, lo=0, hi=1.0)
    vel = pr.number("velocity_std", d.velocity_std, lo=0, hi=100.0)
    acc = pr.number("accel_psd", d.accel_psd, lo=0, hi=1e6)
    pr.done()
    ini = sec.section("initial")
    ipos = ini.number("position_std", d.initial_position_std, lo=1e-12, hi=1.0)
    ivel = ini.number("velocity_std", d.initial_velocity_std, lo=1e-12, hi=100.0)
    ini.done()
    sec.done()
    return NoiseConfig(meas, kind, pos, vel, acc, ipos, ivel)


def _name_value(v) -> str:
    if isinstance(v, str):
        return v
    if isinstance(v, (int, float)) and not isinstance(v, bool) and abs(v) < 1e15:  # NaN fails too
        return str(v)  # YAML reads `name: 2024` as a number
    raise ConfigError("name", f"a string expected, got {_show(v)}")


def model_config_from_dict(data) -> ModelConfig:
    """Validate a parsed model file and return a :class:`ModelConfig`.

    ``data`` is the parsed YAML document: a mapping, or None for an empty file (the default model).

    Raises
    ------
    ConfigError
        Naming the first offending field (an :class:`~heartcv.tracker.files.InputError` without a file).
    """
    root = _Section(data, "")
    fmt = root.raw("format", FORMAT)
    if fmt != FORMAT:
        raise ConfigError("format", f"{FORMAT!r} expected, got {_show(fmt)}")
    ver = root.raw("format_version", FORMAT_VERSION)
    if isinstance(ver, bool) or ver != FORMAT_VERSION:
        raise ConfigError("format_version", f"{FORMAT_VERSION} supported, got {_show(ver)}")
    name = _name_value(root.raw("name", "model"))
    root.raw("description")
    geometry = _geometry(root.section("geometry"))
    theta = _theta(root.section("parameters"))
    estimation = _estimation(root.section("estimation"))
    inputs = _inputs(root.section("inputs"))
    noise = _noise(root.section("noise"))
    disc = root.section("discretisation")
    method = disc.choice("method", "modal", ("modal", "expm", "implicit-euler"))
    rate = disc.number("frame_rate", 30.0, lo=1, hi=10000)
    disc.done()
    reduction = None
    if root.raw("reduction") is not None:
        red = root.section("reduction")
        modes = red.number("modes", 10, lo=1, hi=500)
        cap = SIZE_LIMITS["static_nu"]
        static = _number_list(red.raw("static_nu", [0.3, 0.45, 0.49]), "reduction.static_nu", 1e-3, 0.4999,
                              max_len=cap, what=f"a list of at most {cap} Poisson ratios in [0.001, 0.4999]")
        red.done()
        reduction = {"modes": int(modes), "static_nu": static}
    obs = root.section("observation")
    points = obs.raw("points", "epicardial_nodes")
    ns, nt, nd = geometry.grid
    if isinstance(points, str) and points == "epicardial_nodes":
        observation = {"points": "epicardial_nodes"}
        n_points = (ns - 2) * (nt - 2)
    elif isinstance(points, dict) and set(points) == {"grid"}:
        grid = points["grid"]
        if not isinstance(grid, (list, tuple)) or len(grid) != 2:
            raise ConfigError("observation.points.grid", f"[n_s, n_t] positive integers expected, got {_show(grid)}")
        cap = SIZE_LIMITS["observed_points"]
        grid = tuple(_integer(v, f"observation.points.grid[{i}]", 1, cap, "a positive integer")
                     for i, v in enumerate(grid))
        margin = obs.number("margin", 0.1, lo=0, hi=0.49)
        observation = {"points": "grid", "grid": grid, "margin": margin}
        n_points = grid[0] * grid[1]
    else:
        raise ConfigError("observation.points",
                          f"'epicardial_nodes' or {{grid: [n_s, n_t]}} expected, got {_show(points)}")
    obs.done()
    root.done()
    free_dofs = 3 * (ns - 2) * (nt - 2) * nd
    if reduction is None and free_dofs > MAX_FULL_DOF:
        raise ConfigError("geometry.grid", f"the model has {free_dofs} free DOFs; the full model allows at most "
                                           f"{MAX_FULL_DOF}. Add a 'reduction' section (a fixed Ritz basis, "
                                           "docs/model.md §5) or use a coarser grid")
    if n_points > SIZE_LIMITS["observed_points"]:
        raise ConfigError("observation.points", f"{n_points} observed points; at most "
                                                f"{SIZE_LIMITS['observed_points']} allowed (use {{grid: [n_s, n_t]}})")
    cfg = ModelConfig(name, geometry, theta, estimation, inputs, noise, method, rate, reduction, observation,
                      raw=dict(data or {}))
    space = cfg.parameter_space()  # validate bounds and estimated set now
    for n, sd in zip(space.estimated, cfg.prior_std_phi()):
        if not 1e-8 <= sd <= MAX_PRIOR_STD_PHI:
            key = "prior_std" if n in estimation.prior_std else "prior_std_si"
            raise ConfigError(f"estimation.{key}.{n}", f"gives a prior std of {sd:.3g} in phi units at the model's "
                                                       f"parameters; [1e-08, {MAX_PRIOR_STD_PHI:g}] allowed")
    return cfg
