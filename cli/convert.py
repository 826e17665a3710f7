"""Conversions between core results and file-level sets (no algorithms)."""

from __future__ import annotations

import numpy as np


def simulation_to_measurements(sim, meta: dict):
    """A :class:`tracker.measurements.MeasurementSet` (patch frame) from a simulation."""
    from tracker.measurements import MeasurementSet

    K, P, _ = sim.positions.shape
    cov = np.broadcast_to(np.eye(3) * sim.measurement_std**2, (K, P, 3, 3)).copy()
    cov[~np.isfinite(sim.measurements).all(axis=2)] = np.nan
    inputs = np.hstack([sim.inputs, sim.translation])
    names = tuple(sim.input_names) + ("respiration_x", "respiration_y", "respiration_z")
    units = tuple("Pa" for _ in sim.input_names) + ("m", "m", "m")
    return MeasurementSet(sim.times, np.arange(P), sim.measurements, cov, sim.reference, inputs, names, units,
                          "patch", meta=meta)
