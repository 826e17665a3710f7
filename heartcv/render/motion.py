"""Truth motion of the phantom surface from the tracker's truth simulator.

The patch moves as ``tracker.simulate.simulate`` computes it on the scene's (fine) model, at ``q`` times the
frame rate when motion blur needs sub-frame instants, with ``substeps`` integration substeps, a stiffness that
follows the cardiac cycle and the model's own load inputs (pressure, and active tension when the model has it):

* ``stiffness_cycle.shape: pressure`` (silicone phantom, strain stiffening): ``E(t) = E (1 + a p(t) / p_max)``;
* ``stiffness_cycle.shape: active`` (myocardium, active contraction): ``E(t) = E (1 + a h(t))`` with ``h`` the
  normalised double-Hill active-tension shape (as ``heartcv model simulate --stiffness-cycle``).

The model file's own respiration section is ignored; the scene's ``motion.respiration`` adds a rigid
translation ``r(t)`` (patch frame, ``tracker.inputs.respiration``) of the whole phantom. Outside the patch the
surface also swells along its normal by ``outside_motion_m * g(t)`` with ``g`` the load normalised to [0, 1]
(first load column), weighted by the phantom's fall-off (0 on the patch, continuous at its rim).

Scene time 0 is the first frame; the simulation starts ``t_pre`` earlier so that the exposure of frame 0 is
covered, from the static equilibrium of the inputs at that instant.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math
from typing import Callable

import numpy as np
import scipy.sparse as sp

from ..tracker.files import InputError
from .phantom import PhantomMesh, displacement_operator

__all__ = ["TruthMotion", "SurfaceMotion", "simulate_truth", "surface_motion", "frame_count"]


def frame_count(duration_s, frame_rate_hz) -> int:
    """``floor(duration * rate) + 1`` frames from t = 0 (as ``tracker.simulate.simulate``)."""
    return int(math.floor(duration_s * frame_rate_hz + 1e-9)) + 1


@dataclass(frozen=True)
class TruthMotion:
    """The simulated truth on a time grid (scene time, patch frame).

    Attributes
    ----------
    grid_times : ndarray (G,)      simulation instants (s), step ``dt / q``, from ``-t_pre``
    states : ndarray (G, 2r)       kinematic states [q; q'] of the model
    frame_index : ndarray (K,)     grid index of each frame (frames are grid instants)
    theta : ndarray (K, 5)         true parameters at the frames
    inputs : ndarray (K, n_u)      load inputs at the frames (Pa); names in ``input_names``
    point_param : ndarray (P, 3)   material coordinates of the model's observed points
    point_positions : ndarray (K, P, 3)   their exact positions (patch frame, respiration included)
    translation : callable or None ``r(t)`` (N,) -> (N, 3), m, patch frame
    pulse : callable               ``g(t)`` (N,) -> (N,) in [0, 1]
    """

    frame_times: np.ndarray
    grid_times: np.ndarray
    states: np.ndarray
    frame_index: np.ndarray
    theta: np.ndarray
    inputs: np.ndarray
    input_names: tuple
    point_param: np.ndarray
    point_positions: np.ndarray
    translation: Callable | None
    pulse: Callable

    def state(self, t) -> np.ndarray:
        """State at scene time t (linear interpolation on the grid; clamped at its ends)."""
        g = self.grid_times
        i = int(np.clip(np.searchsorted(g, t, side="right") - 1, 0, g.size - 2))
        w = float(np.clip((t - g[i]) / (g[i + 1] - g[i]), 0.0, 1.0))
        return (1 - w) * self.states[i] + w * self.states[i + 1]

    def shift(self, t) -> np.ndarray:
        if self.translation is None:
            return np.zeros(3)
        return self.translation(np.atleast_1d(float(t)))[0]


def _stiffness_schedule(model, spec, load, t_pre):
    """The scene's E(t) (``motion.stiffness_cycle``): :func:`heartcv.tracker.simulate.stiffness_schedule` with the
    cycle's origin at the first frame (after the pre-roll ``t_pre``)."""
    from heartcv.tracker.simulate import stiffness_schedule

    try:
        return stiffness_schedule(model, spec.stiffness_amplitude, spec.stiffness_shape, load=load, t_offset=t_pre)
    except InputError as exc:  # the field inside the scene file
        raise InputError(None, exc.reason, f"motion.{exc.field}") from None


def simulate_truth(model_config, spec, blur, rng: np.random.Generator):
    """Build the scene's model at the simulation rate and simulate it (module docstring).

    Parameters
    ----------
    model_config : tracker.config.ModelConfig    the scene's ``motion.model``
    spec : heartcv.render.scene.MotionSpec
    blur : heartcv.render.scene.BlurSpec
    rng : numpy.random.Generator                 (process noise only, when ``spec.process_noise``)

    Returns
    -------
    model : tracker.model.PatchModel             built at ``frame_rate_hz * q``
    truth : TruthMotion
    """
    from heartcv.tracker import inputs as inp
    from heartcv.tracker.model import build_model
    from heartcv.tracker.simulate import InputSignals, input_signals, simulate

    q = blur.subsamples if blur.subsamples > 1 else 1
    model = build_model(replace(model_config, frame_rate=spec.frame_rate_hz * q))
    h = 1.0 / (spec.frame_rate_hz * q)
    m = int(math.ceil(blur.exposure_fraction * q / 2 - 1e-9)) if q > 1 else 0
    t_pre = m * h
    K = frame_count(spec.duration_s, spec.frame_rate_hz)
    sig = input_signals(model)

    def load(t):
        return sig.load(np.asarray(t, float) - t_pre)

    theta = _stiffness_schedule(model, spec, sig.load, t_pre)
    sim = simulate(model, (K - 1) / spec.frame_rate_hz + 2 * t_pre, rng, theta=theta,
                   signals=InputSignals(sig.names, load, None), substeps=spec.substeps,
                   process_noise=spec.process_noise, initial_noise=False)
    grid_times = sim.times - t_pre
    idx = m + q * np.arange(K)
    frame_times = grid_times[idx]
    translation = None
    if spec.respiration is not None:
        r = spec.respiration

        def translation(t):
            return inp.respiration(np.atleast_1d(np.asarray(t, float)), amplitude=r["amplitude"],
                                   frequency_hz=r["frequency_hz"], direction=r["direction"], n=r["n"],
                                   phase=r["phase"])
    shift = translation(frame_times) if translation else np.zeros((K, 3))
    if sig.names:
        tt = np.linspace(0.0, 60.0 / model.config.inputs.heart_rate_bpm * 3, 3001)
        first = sig.load(tt)[:, 0]
        lo, hi = float(first.min()), float(first.max())
    else:
        lo, hi = 0.0, 0.0

    def pulse(t):
        t = np.atleast_1d(np.asarray(t, float))
        if hi <= lo:
            return np.zeros(t.shape)
        return (sig.load(t)[:, 0] - lo) / (hi - lo)

    truth = TruthMotion(frame_times, grid_times, sim.states, idx, sim.theta[idx], sim.inputs[idx], sim.input_names,
                        sim.point_param, sim.positions[idx] + shift[:, None, :], translation, pulse)
    return model, truth


@dataclass(frozen=True)
class SurfaceMotion:
    """Positions of every phantom vertex at any instant: ``X_ref + B q(t) + w g(t) a n_ref + r(t)`` in the patch
    frame (``B`` maps the model's generalised coordinates to the vertices), then ``world_from_patch``."""

    phantom: PhantomMesh
    truth: TruthMotion
    basis: object  # (3V, r) ndarray or sparse matrix
    world_from_patch: np.ndarray
    outside_motion_m: float
    r: int

    def displacement(self, t) -> np.ndarray:
        """Vertex displacements (V, 3) at scene time t, patch frame, respiration included."""
        q = self.truth.state(t)[: self.r]
        d = np.asarray(self.basis @ q).reshape(-1, 3)
        if self.outside_motion_m:
            g = float(self.truth.pulse(t)[0])
            d = d + (self.outside_motion_m * g) * self.phantom.falloff[:, None] * self.phantom.normals
        return d + self.truth.shift(t)

    def positions_patch(self, t) -> np.ndarray:
        return self.phantom.vertices + self.displacement(t)

    def positions_world(self, t) -> np.ndarray:
        T = self.world_from_patch
        return self.positions_patch(t) @ T[:3, :3].T + T[:3, 3]


def surface_motion(phantom: PhantomMesh, model, truth: TruthMotion, world_from_patch,
                   outside_motion_m: float) -> SurfaceMotion:
    """Precompute the vertex basis ``B = (D kron I3)[:, free] V`` (D from
    :func:`heartcv.render.phantom.displacement_operator`, V the model's Ritz basis or the identity)."""
    D = displacement_operator(phantom, model)
    D3 = sp.kron(D, sp.identity(3), format="csr")[:, model.free_dofs]
    basis = D3 if model.basis is None else np.asarray(D3 @ model.basis)
    return SurfaceMotion(phantom, truth, basis, np.asarray(world_from_patch, float), float(outside_motion_m),
                         model.r)
