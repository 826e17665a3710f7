"""``heartcv fit``: weighted least-squares fit of the model's parameters to a measurement file (paper §IV;
docs/cli.md §12)."""

from __future__ import annotations

from dataclasses import replace
import logging
from pathlib import Path

import click

from .options import MAX_COUNT, BadInput, Int, StageFailed, emit_json, guard_outputs, json_opt, load_model, seed_opt

log = logging.getLogger(__name__)

MAX_STARTS = 1000


@click.command()
@click.argument("measurements", type=click.Path(dir_okay=False))
@click.option("--model", "model_file", type=click.Path(exists=True, dir_okay=False), required=True,
              help="Model file (YAML): estimation.estimate names the fitted parameters, estimation.bounds their box, "
                   "parameters the first start and the fixed values.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True,
              help="Parameters file to write (.yaml).")
@click.option("--frames", type=Int(2, MAX_COUNT), default=None,
              help="Fit the first N frames only (default: all), e.g. two cardiac cycles.")
@click.option("--starts", type=Int(1, MAX_STARTS), default=3, show_default=True,
              help="Starts: the model file's parameters plus STARTS-1 draws from its prior; the best converged wins.")
@seed_opt
@click.option("--max-evaluations", type=Int(1, MAX_COUNT), default=None,
              help="Residual evaluations per start (least_squares max_nfev; default 100 per parameter).")
@json_opt
def fit(measurements, model_file, output, frames, starts, seed, max_evaluations, as_json):
    """Fit the parameters of MODEL's estimation.estimate to MEASUREMENTS by bounded weighted least squares.

    The patch is simulated from equilibrium at the first frame's input with the measured inputs; residuals are
    the measured displacements minus the model's, whitened by each observation's covariance. Rig-frame files
    (heartcv measure) are registered onto the patch first. A fit that does not converge exits 1 and writes
    nothing.
    """
    import numpy as np
    from threadpoolctl import threadpool_limits

    from heartcv.tracker.files import InputError
    from heartcv.tracker.fit import fit as run_fit
    from heartcv.tracker.io import file_hash, read_measurements, write_parameters

    if Path(output).suffix.lower() not in (".yaml", ".yml"):
        raise BadInput(f"-o/--output: a .yaml file expected, got {output}")
    guard_outputs({"-o/--output": output}, {"MEASUREMENTS": measurements, "--model": model_file},
                  files=[("-o/--output", output)])
    meas = read_measurements(measurements)
    m = load_model(model_file)
    if not m.config.estimation.estimate:
        raise BadInput(f"{model_file}: estimation.estimate is empty; nothing to fit")
    registration = None
    try:
        with threadpool_limits(1):
            if meas.frame == "rig":
                meas, registration = _register(meas, m, output)
            result = run_fit(m, meas, np.random.default_rng(seed), frames=frames, starts=starts,
                             max_evaluations=max_evaluations)
    except InputError as exc:  # the measurement file does not fit the model (validated by the core)
        raise exc.in_file(measurements) from None
    if not result.converged:
        raise StageFailed(f"fit did not converge: {result.message}; nothing written to {output}")
    meta = {"producer": "heartcv fit", "measurements": str(measurements), "model": str(model_file),
            "inputs_hash": {"measurements": file_hash(measurements), "model": file_hash(model_file)},
            "seed": seed}
    result = replace(result, registration=registration)
    write_parameters(output, result, meta)
    summary = _summary(result, output)
    if as_json:
        emit_json(summary)
    else:
        log.info("wrote %s: %s (reduced chi-square %.3g, %d frames, %d points)", output,
                 ", ".join(f"{n} = {summary['theta'][n]:.4g} ± {summary['theta_std'][n]:.2g}"
                           for n in result.estimated),
                 result.reduced_chi2, result.frames, result.points)
    if summary["poorly_determined"]:
        log.warning("poorly determined (std > 1 in phi, a factor e): %s; consider fixing them (estimation.estimate)",
                    ", ".join(summary["poorly_determined"]))
    if result.at_bound:
        log.warning("at a bound of estimation.bounds: %s (their std ignores the bound)", ", ".join(result.at_bound))


def _register(rig_meas, m, output):
    """Register a rig-frame set onto the patch: ``(patch-frame set, registration entry of the parameters file)``;
    StageFailed (exit 1) when the registration does not converge."""
    from heartcv.tracker.registration import register_rig_measurements, registration_to_dict

    meas, reg = register_rig_measurements(rig_meas, m)
    if meas is None:
        raise StageFailed(f"registration onto the patch did not converge ({reg.message}); nothing written to "
                          f"{output}")
    return meas, registration_to_dict(reg, rig_meas)


def _summary(result, output) -> dict:
    """The --json summary of a converged fit."""
    from heartcv.tracker.params import NAMES

    est = list(result.estimated)
    summary = {
        "theta": dict(zip(NAMES, map(float, result.theta), strict=True)),
        "theta_std": dict(zip(NAMES, map(float, result.theta_std), strict=True)),
        "estimated": est,
        "fixed": list(result.fixed),
        "cost": result.cost,
        "reduced_chi2": result.reduced_chi2,
        "covariance_scaled": result.covariance_scaled,
        "covariance_kind": result.covariance_kind,
        "dof": result.dof,
        "converged": result.converged,
        "message": result.message,
        "iterations": result.iterations,
        "evaluations": result.evaluations,
        "frames": result.frames,
        "points": result.points,
        "observations": result.observations,
        "starts": len(result.starts),
        "starts_converged": sum(1 for s in result.starts if s["status"] > 0),
        "at_bound": list(result.at_bound),
        "poorly_determined": list(result.poorly_determined),
        "registration_rms_m": None if result.registration is None else result.registration["rms_m"],
        "output": output,
    }
    return summary
