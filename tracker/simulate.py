"""Truth simulator: node trajectories, exact surface-point positions and noisy 3-D measurements.

The truth follows the same linear model as the estimators but may use

* a time-varying ``theta(t)`` (for instance a stiffness that follows the cardiac cycle),
* ``substeps`` per frame (first-order-hold input sampled at the finer step), so the truth is closer to the
  continuous-time system than the filter's frame-rate discretisation,
* additive process noise ``w_k ~ N(0, Q)`` once per frame and measurement noise ``v ~ N(0, sigma^2 I)``.

Randomness enters only through the ``rng`` argument.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import inputs as inp
from .files import InputError
from .model import Observation, PatchModel

__all__ = ["InputSignals", "Simulation", "input_signals", "simulate", "to_measurements", "stiffness_schedule",
           "STIFFNESS_SHAPES"]

STIFFNESS_SHAPES = ("active", "pressure")


@dataclass(frozen=True)
class InputSignals:
    """Known inputs sampled at arbitrary times.

    Attributes
    ----------
    names : tuple of str
        Load-column names (``pressure``, ``active_tension``), in the model's order; units Pa.
    load : callable
        ``load(t) -> (len(t), n_u)`` in Pa.
    translation : callable or None
        ``translation(t) -> (len(t), 3)`` rigid respiration translation in m.
    """

    names: tuple
    load: Callable
    translation: Callable | None = None


def input_signals(model: PatchModel) -> InputSignals:
    """The inputs configured in the model file."""
    ic = model.config.inputs
    cols = []
    if ic.pressure == "lv":
        cols.append(lambda t: ic.pressure_scale * inp.lv_pressure(
            t, heart_rate_bpm=ic.heart_rate_bpm, rr_intervals=ic.rr_intervals))
    elif ic.pressure == "la":
        cols.append(lambda t: ic.pressure_scale * inp.la_pressure(
            t, heart_rate_bpm=ic.heart_rate_bpm, mean_mmhg=ic.la_mean_mmhg, rr_intervals=ic.rr_intervals))
    elif ic.pressure == "fourier60":
        cols.append(lambda t: ic.pressure_scale * inp.lv_pressure_fourier_60bpm(t))
    if ic.active_tension is not None:
        cols.append(lambda t: inp.active_tension(
            t, heart_rate_bpm=ic.heart_rate_bpm, t_max=ic.active_tension, rr_intervals=ic.rr_intervals))

    def load(t):
        t = np.atleast_1d(np.asarray(t, float))
        if not cols:
            return np.zeros((t.size, 0))
        return np.stack([c(t) for c in cols], axis=-1)

    translation = None
    if ic.respiration is not None:
        r = ic.respiration

        def translation(t):
            return inp.respiration(np.atleast_1d(np.asarray(t, float)), amplitude=r["amplitude"],
                                   frequency_hz=r["frequency_hz"], direction=r["direction"], n=r["n"],
                                   phase=r["phase"])

    return InputSignals(model.input_names, load, translation)


def stiffness_schedule(model: PatchModel, amplitude: float, shape: str = "active", *, load: Callable | None = None,
                       t_offset: float = 0.0) -> Callable | None:
    """True parameters whose Young's modulus follows the cardiac cycle, for :func:`simulate`'s ``theta``.

    ``theta(t)`` is the model file's theta with ``E(t) = E (1 + a h(t - t_offset))``; ``h`` in [0, 1] is

    * ``'active'``: the normalised double-Hill active-tension shape (:func:`tracker.inputs.active_tension` with
      peak 1) at the model file's heart rate and RR intervals (myocardium, active contraction;
      ``heartcv model simulate --stiffness-cycle``);
    * ``'pressure'``: the model's pressure input ``max(p(t), 0) / p_max``, ``p_max`` its maximum over the first
      three beats (silicone phantom, strain stiffening; ``heartcv render`` scenes).

    Parameters
    ----------
    model : PatchModel
    amplitude : float
        ``a >= 0``; 0 gives None (the model file's constant theta).
    shape : {'active', 'pressure'}
    load : callable, optional
        ``load(t) -> (len(t), n_u)`` in Pa, the inputs the truth is driven with (default: the model file's,
        :func:`input_signals`); ``'pressure'`` reads its ``pressure`` column.
    t_offset : float
        Time (s) of the cycle's origin on the simulation's clock (a pre-roll before the first frame).

    Returns
    -------
    callable or None
        ``theta(t) -> ndarray (5,)``.

    Raises
    ------
    InputError
        ``'pressure'`` for a model without a pressure input or whose pressure is never positive (field
        ``stiffness_cycle.shape``; no file: the caller attaches it).
    """
    if not (np.isfinite(amplitude) and amplitude >= 0):
        raise ValueError(f"amplitude: a finite value >= 0 expected, got {amplitude}")
    if shape not in STIFFNESS_SHAPES:
        raise ValueError(f"shape: one of {STIFFNESS_SHAPES} expected, got {shape!r}")
    if amplitude == 0:
        return None
    base = model.config.theta.copy()
    ic = model.config.inputs
    if shape == "pressure":
        h = _pressure_shape(model, input_signals(model).load if load is None else load)
    else:
        def h(t):
            return float(inp.active_tension(np.atleast_1d(t), heart_rate_bpm=ic.heart_rate_bpm, t_max=1.0,
                                            rr_intervals=ic.rr_intervals)[0])

    def theta(t):
        th = base.copy()
        th[3] = base[3] * (1.0 + amplitude * h(t - t_offset))
        return th

    return theta


def _pressure_shape(model: PatchModel, load: Callable) -> Callable:
    """``h(t) = max(p(t), 0) / p_max`` of the model's pressure column (:func:`stiffness_schedule`)."""
    if "pressure" not in model.input_names:
        raise InputError(None, "'pressure' needs a model with a pressure input (inputs.pressure)",
                         "stiffness_cycle.shape")
    col = model.input_names.index("pressure")
    tt = np.linspace(0.0, 60.0 / model.config.inputs.heart_rate_bpm * 3, 3001)
    p_max = float(np.max(load(tt)[:, col]))
    if not p_max > 0:
        raise InputError(None, "'pressure': the model's pressure is never positive", "stiffness_cycle.shape")

    def h(t):
        return max(float(load(np.atleast_1d(t))[0, col]), 0.0) / p_max

    return h


@dataclass(frozen=True)
class Simulation:
    """Result of :func:`simulate` (all SI, patch frame).

    Attributes
    ----------
    times : ndarray (K,)
    theta : ndarray (K, 5)             true parameters per frame
    inputs : ndarray (K, n_u)          load inputs per frame (Pa)
    translation : ndarray (K, 3)       rigid respiration translation (m), zeros if none
    states : ndarray (K, 2r)           true kinematic states
    node_displacements : ndarray (K, n_nodes, 3)
    point_param : ndarray (P, 3)       material coordinates (s, t, d) of the measured points
    reference : ndarray (P, 3)         their undeformed positions
    positions : ndarray (K, P, 3)      exact positions
    measurements : ndarray (K, P, 3)   noisy positions (NaN where not seen)
    measurement_std : float
    """

    times: np.ndarray
    theta: np.ndarray
    inputs: np.ndarray
    input_names: tuple
    translation: np.ndarray
    states: np.ndarray
    node_displacements: np.ndarray
    point_param: np.ndarray
    reference: np.ndarray
    positions: np.ndarray
    measurements: np.ndarray
    measurement_std: float

    @property
    def peak_displacement_m(self) -> float:
        """Largest |x_k - x_0| over frames, points and coordinates of the exact positions (m)."""
        return float(np.abs(self.positions - self.positions[:1]).max())


def _theta_schedule(theta, times, model):
    if theta is None:
        theta = model.config.theta
    if callable(theta):
        th = np.asarray([theta(t) for t in times], float)
    else:
        th = np.asarray(theta, float)
        th = np.broadcast_to(th, (times.size, 5)) if th.shape == (5,) else th
    if th.shape != (times.size, 5):
        raise ValueError(f"theta: (5,), (K, 5) or a callable expected; got shape {th.shape}")
    if not np.isfinite(th).all():
        raise ValueError("theta: non-finite values")
    return np.array(th)


def simulate(model: PatchModel, duration: float, rng: np.random.Generator, *, theta=None,
             signals: InputSignals | None = None, points=None, substeps: int = 1,
             process_noise: bool = True, initial_noise: bool = True,
             missing_fraction: float = 0.0) -> Simulation:
    """Simulate the patch for ``duration`` seconds at the model's frame rate.

    Parameters
    ----------
    model : PatchModel
    duration : float
        Seconds; ``K = floor(duration * frame_rate) + 1`` frames from t = 0.
    rng : numpy.random.Generator
    theta : None, ndarray (5,), ndarray (K*substeps, 5) or callable t -> (5,)
        True parameters (default: the model file's). A callable is evaluated at the start of every substep.
    signals : InputSignals, optional
        Default: the model file's inputs.
    points : ndarray (P, 3), optional
        Material coordinates of the measured points (default: ``model.default_points()``).
    substeps : int
        Integration substeps per frame for the truth.
    process_noise, initial_noise : bool
        Draw ``w_k ~ N(0, Q)`` per frame and the initial deviation ``~ N(0, P0)`` from equilibrium.
    missing_fraction : float
        Probability that a point is not seen in a frame (its row is NaN).
    """
    if not (np.isfinite(duration) and duration > 0):
        raise ValueError(f"duration: positive seconds expected, got {duration}")
    if substeps < 1:
        raise ValueError(f"substeps: >= 1 expected, got {substeps}")
    cfg = model.config
    K = int(np.floor(duration * cfg.frame_rate + 1e-9)) + 1
    dt = cfg.dt
    h = dt / substeps
    times = np.arange(K) * dt
    fine_t = np.arange((K - 1) * substeps + 1) * h
    signals = signals or input_signals(model)
    u_fine = signals.load(fine_t)
    theta_fine = _theta_schedule(theta, fine_t, model)
    pts = model.default_points() if points is None else np.atleast_2d(np.asarray(points, float))
    obs: Observation = model.observation(pts)
    Q = model.process_noise(theta_fine[0], dt)
    LQ = np.linalg.cholesky(Q + 1e-30 * np.eye(Q.shape[0])) if process_noise else None

    x = model.static_state(theta_fine[0], u_fine[0])
    if initial_noise:
        x = x + np.linalg.cholesky(model.initial_covariance()) @ rng.standard_normal(x.size)
    states = np.empty((K, model.state_dim))
    states[0] = x
    cache: dict = {}

    def system(th):
        key = th.tobytes()
        if key not in cache:
            if len(cache) > 256:
                cache.clear()
            cache[key] = model.system(th, h)
        return cache[key]

    for k in range(1, K):
        for j in range((k - 1) * substeps, k * substeps):
            sysd = system(theta_fine[j])
            x = sysd.A @ x + sysd.B0 @ u_fine[j] + sysd.B1 @ u_fine[j + 1]
        if LQ is not None:
            x = x + LQ @ rng.standard_normal(x.size)
        if not np.isfinite(x).all():
            raise FloatingPointError(f"simulation diverged at frame {k} (t = {times[k]:.4f} s)")
        states[k] = x

    translation = signals.translation(times) if signals.translation else np.zeros((K, 3))
    disp = model.node_displacements(states, translation)
    positions = obs.reference[None] + translation[:, None, :] + (states @ obs.H.T).reshape(K, -1, 3)
    sigma = cfg.noise.measurement_std
    meas = positions + sigma * rng.standard_normal(positions.shape)
    if missing_fraction > 0:
        hide = rng.random(positions.shape[:2]) < missing_fraction
        meas[hide] = np.nan
    return Simulation(times, theta_fine[::substeps].copy(), u_fine[::substeps].copy(), signals.names,
                      translation, states, disp, pts, obs.reference, positions, meas, sigma)


def to_measurements(sim: Simulation, meta: dict | None = None):
    """The patch-frame :class:`~tracker.measurements.MeasurementSet` of a simulation (isotropic covariance
    ``measurement_std^2 I``; respiration as input columns ``respiration_x/y/z`` in m)."""
    from .measurements import MeasurementSet

    K, P, _ = sim.positions.shape
    cov = np.broadcast_to(np.eye(3) * sim.measurement_std**2, (K, P, 3, 3)).copy()
    cov[~np.isfinite(sim.measurements).all(axis=2)] = np.nan
    inputs = np.hstack([sim.inputs, sim.translation])
    names = tuple(sim.input_names) + ("respiration_x", "respiration_y", "respiration_z")
    units = tuple("Pa" for _ in sim.input_names) + ("m", "m", "m")
    return MeasurementSet(sim.times, np.arange(P), sim.measurements, cov, sim.reference, inputs, names, units,
                          "patch", meta=dict(meta or {}))
