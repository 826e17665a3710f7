"""The model configuration (the content of a model YAML file) as typed, validated values.

:func:`model_config_from_dict` accepts the parsed YAML mapping, rejects unknown keys and out-of-range values
with a :class:`ConfigError` that names the field (``parameters.nu``), and fills documented defaults.
The file format is documented in ``docs/formats.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

from .geometry import PatchGeometry
from .params import DEFAULT_BOUNDS, NAMES, ParameterSpace

__all__ = ["ConfigError", "ModelConfig", "model_config_from_dict", "FORMAT", "FORMAT_VERSION"]

FORMAT = "heartcv.model"
FORMAT_VERSION = 1


# prior standard deviation in phi units when the model file gives none (docs/spec/model.md §4.2)
DEFAULT_PRIOR_STD = {"rho": 0.3, "alpha1": 1.0, "alpha2": 1.0, "E": 0.5, "nu": 0.5}
GE_DEFAULTS = {"nodes": 5, "variant": "A", "sqrt": "cholesky", "truncation": "sequential"}
UKF_DEFAULTS = {"alpha": 0.1, "beta": 2.0, "kappa": 0.0}


class ConfigError(ValueError):
    """A model file field is missing, unknown or out of range; ``field`` names it."""

    def __init__(self, field_name: str, message: str):
        super().__init__(f"{field_name}: {message}")
        self.field = field_name


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

    def random_walk_std_phi(self) -> np.ndarray:
        """Random-walk standard deviation per frame of the estimated parameters in phi units (dim,)."""
        space = self.parameter_space()
        return np.array([self.estimation.random_walk_std.get(n, 0.0) for n in space.estimated], float)

    @property
    def input_names(self) -> tuple:
        names = []
        if self.inputs.pressure != "none":
            names.append("pressure")
        if self.inputs.active_tension is not None:
            names.append("active_tension")
        return tuple(names)


# ---------------------------------------------------------------------------------------------
class _Section:
    """Reads one mapping, tracking its path for error messages and rejecting unknown keys."""

    def __init__(self, data, path: str):
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(path or "<root>", f"a mapping expected, got {type(data).__name__}")
        self.data = dict(data)
        self.path = path
        self.seen: set = set()

    def _name(self, key):
        return f"{self.path}.{key}" if self.path else key

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
        if isinstance(v, str):  # PyYAML (YAML 1.1) reads 1.0e8 as a string
            try:
                v = float(v.strip().replace(".inf", "inf"))
            except ValueError:
                raise ConfigError(self._name(key), f"a number expected, got {v!r}") from None
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ConfigError(self._name(key), f"a number expected, got {v!r}")
        v = float(v)
        if math.isnan(v) or (math.isinf(v) and not allow_inf):
            raise ConfigError(self._name(key), f"a finite number expected, got {v!r}")
        bad = (v <= lo if lo_open else v < lo) or (v >= hi if hi_open else v > hi)
        if bad:
            lb = "(" if lo_open else "["
            rb = ")" if hi_open else "]"
            raise ConfigError(self._name(key), f"must lie in {lb}{lo}, {hi}{rb}, got {v}")
        return v

    def choice(self, key, default, options):
        self.seen.add(key)
        v = self.data.get(key, default)
        if v not in options:
            raise ConfigError(self._name(key), f"one of {list(options)} expected, got {v!r}")
        return v

    def section(self, key):
        self.seen.add(key)
        return _Section(self.data.get(key), self._name(key))

    def done(self):
        unknown = sorted(set(self.data) - self.seen)
        if unknown:
            raise ConfigError(self._name(unknown[0]), f"unknown key (known: {sorted(self.seen)})")


def _geometry(sec: _Section) -> PatchGeometry:
    g = PatchGeometry()
    length = sec.number("length", g.length, lo=0, lo_open=True)
    width = sec.number("width", g.width, lo=0, lo_open=True)
    thick = sec.number("thickness", g.thickness, lo=0, lo_open=True)
    r1 = sec.number("radius_long", g.radius_long, lo=0, lo_open=True, allow_none=True, allow_inf=True)
    r2 = sec.number("radius_circ", g.radius_circ, lo=0, lo_open=True, allow_none=True, allow_inf=True)
    r1 = math.inf if r1 is None else r1
    r2 = math.inf if r2 is None else r2
    grid = sec.raw("grid", list(g.grid))
    if (not isinstance(grid, (list, tuple)) or len(grid) != 3
            or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 2 for v in grid)):
        raise ConfigError(sec._name("grid"), f"three integer node counts >= 2 expected, got {grid!r}")
    sec.done()
    try:
        return PatchGeometry(length, width, thick, r1, r2, tuple(grid))
    except ValueError as exc:  # PatchGeometry's messages already name the field
        field_name, _, msg = str(exc).partition(": ")
        raise ConfigError(field_name if msg else sec.path, msg or str(exc)) from None


def _theta(sec: _Section) -> np.ndarray:
    th = np.array([
        sec.number("rho", 1050.0, lo=0, lo_open=True),
        sec.number("alpha1", 2.39, lo=0),
        sec.number("alpha2", 0.003, lo=0),
        sec.number("E", 150e3, lo=0, lo_open=True),
        sec.number("nu", 0.45, lo=0, hi=0.5, lo_open=True, hi_open=True),
    ])
    sec.done()
    return th


def _per_parameter(sec: _Section, allowed, *, pair=False):
    out = {}
    for key in list(sec.data):
        if key not in allowed:
            raise ConfigError(sec._name(key), f"unknown parameter (known: {list(allowed)})")
        if pair:
            v = sec.raw(key)
            if not isinstance(v, (list, tuple)) or len(v) != 2:
                raise ConfigError(sec._name(key), f"[lower, upper] expected, got {v!r}")
            sub = _Section({"lower": v[0], "upper": v[1]}, sec._name(key))
            out[key] = (sub.number("lower", allow_inf=True), sub.number("upper", allow_inf=True))
        else:
            out[key] = sec.number(key, lo=0)
    sec.done()
    return out


def _estimation(sec: _Section) -> EstimationConfig:
    est = sec.raw("estimate", ["E", "nu"])
    if isinstance(est, str):
        est = [est]
    if not isinstance(est, (list, tuple)) or any(e not in NAMES for e in est):
        raise ConfigError(sec._name("estimate"), f"a list of parameter names from {list(NAMES)} expected, got {est!r}")
    prior = _per_parameter(sec.section("prior_std"), NAMES)
    prior_si = _per_parameter(sec.section("prior_std_si"), NAMES)
    both = sorted(set(prior) & set(prior_si))
    if both:
        raise ConfigError(sec._name("prior_std_si"), f"{both[0]} is also given in prior_std; give one of the two")
    for name, d in (("prior_std", prior), ("prior_std_si", prior_si)):
        for k, v in d.items():
            if v <= 0 and k in est:
                raise ConfigError(sec._name(f"{name}.{k}"), f"an estimated parameter needs a prior std > 0, got {v}")
    walk = _per_parameter(sec.section("random_walk_std"), NAMES)
    bounds = _per_parameter(sec.section("bounds"), NAMES, pair=True)
    eps = sec.section("epsilon")
    e1 = eps.number("alpha1", None, lo=0, lo_open=True, allow_none=True)
    e2 = eps.number("alpha2", None, lo=0, lo_open=True, allow_none=True)
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
        "alpha": u.number("alpha", UKF_DEFAULTS["alpha"], lo=0, lo_open=True, hi=1),
        "beta": u.number("beta", UKF_DEFAULTS["beta"], lo=0),
        "kappa": u.number("kappa", UKF_DEFAULTS["kappa"]),
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
        if not isinstance(rr, (list, tuple)) or not rr or any(
            isinstance(v, bool) or not isinstance(v, (int, float)) or not (0.24 <= v <= 3.0) for v in rr
        ):
            raise ConfigError(p._name("rr_intervals"), f"a list of beat lengths in [0.24, 3] s expected, got {rr!r}")
        rr = tuple(float(v) for v in rr)
    scale = p.number("scale", 1.0, lo=0)
    la_mean = p.number("la_mean_mmhg", 8.0, lo=0, hi=60)
    p.done()
    act = sec.section("active_tension")
    t_max = act.number("t_max", None, lo=0, allow_none=True) if act.data else None
    act.done()
    resp = None
    if sec.raw("respiration") is not None:
        r = sec.section("respiration")
        resp = {
            "amplitude": r.number("amplitude", 0.004, lo=0, hi=0.05),
            "frequency_hz": r.number("frequency_hz", 0.25, lo=0.01, hi=2.0),
            "n": int(r.number("n", 2, lo=1, hi=10)),
            "phase": r.number("phase", 0.0),
        }
        direction = r.raw("direction", [1.0, 0.3, 0.0])
        if (not isinstance(direction, (list, tuple)) or len(direction) != 3
                or not np.isfinite(np.asarray(direction, float)).all()
                or np.linalg.norm(np.asarray(direction, float)) == 0):
            raise ConfigError(r._name("direction"), f"a non-zero 3-vector expected, got {direction!r}")
        resp["direction"] = tuple(float(v) for v in direction)
        r.done()
    rate = sec.number("sample_rate_hz", 250.0, lo=1, hi=1e5)
    sec.done()
    return InputsConfig(source, hr, rr, scale, la_mean, t_max, resp, rate)


def _noise(sec: _Section) -> NoiseConfig:
    d = NoiseConfig()
    meas = sec.number("measurement_std", d.measurement_std, lo=0, lo_open=True)
    pr = sec.section("process")
    kind = pr.choice("kind", "diagonal", ("diagonal", "acceleration"))
    pos = pr.number("position_std", d.position_std, lo=0)
    vel = pr.number("velocity_std", d.velocity_std, lo=0)
    acc = pr.number("accel_psd", d.accel_psd, lo=0)
    pr.done()
    ini = sec.section("initial")
    ipos = ini.number("position_std", d.initial_position_std, lo=0, lo_open=True)
    ivel = ini.number("velocity_std", d.initial_velocity_std, lo=0, lo_open=True)
    ini.done()
    sec.done()
    return NoiseConfig(meas, kind, pos, vel, acc, ipos, ivel)


def model_config_from_dict(data) -> ModelConfig:
    """Validate a parsed model file and return a :class:`ModelConfig`.

    Raises
    ------
    ConfigError
        Naming the first offending field.
    """
    root = _Section(data, "")
    fmt = root.raw("format", FORMAT)
    if fmt != FORMAT:
        raise ConfigError("format", f"{FORMAT!r} expected, got {fmt!r}")
    ver = root.raw("format_version", FORMAT_VERSION)
    if ver != FORMAT_VERSION:
        raise ConfigError("format_version", f"{FORMAT_VERSION} supported, got {ver!r}")
    name = str(root.raw("name", "model"))
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
        static = red.raw("static_nu", [0.3, 0.45, 0.49])
        if not isinstance(static, (list, tuple)) or any(
            isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < 0.5 for v in static
        ):
            raise ConfigError("reduction.static_nu", f"a list of Poisson ratios in (0, 0.5) expected, got {static!r}")
        red.done()
        reduction = {"modes": int(modes), "static_nu": tuple(float(v) for v in static)}
    obs = root.section("observation")
    points = obs.raw("points", "epicardial_nodes")
    if points == "epicardial_nodes":
        observation = {"points": "epicardial_nodes"}
    elif isinstance(points, dict) and set(points) == {"grid"}:
        grid = points["grid"]
        if not isinstance(grid, (list, tuple)) or len(grid) != 2 or not all(
            isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in grid
        ):
            raise ConfigError("observation.points.grid", f"[n_s, n_t] positive integers expected, got {grid!r}")
        margin = obs.number("margin", 0.1, lo=0, hi=0.49)
        observation = {"points": "grid", "grid": tuple(grid), "margin": margin}
    else:
        raise ConfigError("observation.points", f"'epicardial_nodes' or {{grid: [n_s, n_t]}} expected, got {points!r}")
    obs.done()
    root.done()
    cfg = ModelConfig(name, geometry, theta, estimation, inputs, noise, method, rate, reduction, observation,
                      raw=dict(data))
    cfg.parameter_space()  # validate bounds and estimated set now
    return cfg
