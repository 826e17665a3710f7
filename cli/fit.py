"""``heartcv fit``: weighted least-squares fit of the model's parameters to a measurement file (paper §IV)."""

from __future__ import annotations

from dataclasses import replace
import logging
from pathlib import Path

import click

from .options import BadInput, StageFailed, emit_json, json_opt, load_model, seed_opt

log = logging.getLogger(__name__)


def registration_to_dict(reg, meas) -> dict:
    """The ``registration`` entry of a parameters file: the transform, its RMS and the ids of the points on the
    patch (ids survive filtering, so the registration can be applied to the same file again)."""
    import numpy as np

    return {
        "patch_from_rig": np.asarray(reg.patch_from_rig, float).tolist(),
        "rms_m": float(reg.rms_m),
        "points_on_patch": [int(i) for i in np.asarray(meas.point_ids)[np.asarray(reg.on_patch, bool)]],
        "message": str(reg.message),
    }


def register_rig_measurements(meas, model, frames=10):
    """Register a rig-frame measurement set onto the model (``tracker.registration``); returns
    ``(patch-frame set, registration)``. BadInput when registration is not available or the data do not fit,
    StageFailed when it does not converge."""
    try:
        from heartcv.tracker.registration import register, to_patch_frame
    except ImportError:
        raise BadInput("the measurements are in the rig frame and registration onto the patch is not available "
                       "(tracker.registration); register them to the patch frame first") from None
    try:
        reg = register(meas, model, frames=frames)
    except ValueError as exc:
        raise BadInput(f"registration: {exc}") from None
    if not reg.converged:
        raise StageFailed(f"registration onto the patch did not converge ({reg.message}); nothing written")
    return to_patch_frame(meas, reg), reg


@click.command()
@click.argument("measurements", type=click.Path(dir_okay=False))
@click.option("--model", "model_file", type=click.Path(exists=True, dir_okay=False), required=True,
              help="Model file (YAML): estimation.estimate names the fitted parameters, estimation.bounds their box, "
                   "parameters the first start and the fixed values.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True,
              help="Parameters file to write (.yaml).")
@click.option("--frames", type=click.IntRange(min=2), default=None,
              help="Fit the first N frames only (default: all), e.g. two cardiac cycles.")
@click.option("--starts", type=click.IntRange(min=1), default=3, show_default=True,
              help="Starts: the model file's parameters plus STARTS-1 draws from its prior; the best converged wins.")
@seed_opt
@click.option("--max-evaluations", type=click.IntRange(min=1), default=None,
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

    from heartcv.tracker.fit import fit as run_fit
    from heartcv.tracker.io import FileFormatError, file_hash, read_measurements, write_parameters

    if Path(output).suffix.lower() not in (".yaml", ".yml"):
        raise BadInput(f"-o/--output: a .yaml file expected, got {output}")
    try:
        meas = read_measurements(measurements)
    except FileFormatError as exc:
        raise BadInput(str(exc)) from None
    m = load_model(model_file)
    if not m.config.estimation.estimate:
        raise BadInput(f"{model_file}: estimation.estimate is empty; nothing to fit")
    registration = None
    with threadpool_limits(1):
        if meas.frame == "rig":
            rig_meas = meas
            meas, reg = register_rig_measurements(rig_meas, m)
            registration = registration_to_dict(reg, rig_meas)
        try:
            result = run_fit(m, meas, np.random.default_rng(seed), frames=frames, starts=starts,
                             max_evaluations=max_evaluations)
        except ValueError as exc:
            raise BadInput(f"{measurements}: {exc}") from None
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
        log.warning("wrote %s: %s (reduced chi-square %.3g, %d frames, %d points)", output,
                    ", ".join(f"{n} = {summary['theta'][n]:.4g} ± {summary['theta_std'][n]:.2g}"
                              for n in result.estimated),
                    result.reduced_chi2, result.frames, result.points)
    if summary["poorly_determined"]:
        log.warning("poorly determined (std > 1 in phi, a factor e): %s; consider fixing them (estimation.estimate)",
                    ", ".join(summary["poorly_determined"]))
    if result.at_bound:
        log.warning("at a bound of estimation.bounds: %s (their std ignores the bound)", ", ".join(result.at_bound))


def _summary(result, output) -> dict:
    """The --json summary of a converged fit."""
    import numpy as np

    from heartcv.tracker.params import NAMES

    est = list(result.estimated)
    # a standard deviation above 1 in phi: the data do not pin the parameter down to a factor e (docs/spec/model.md §4.3)
    poor = [n for n, v in zip(est, np.diag(result.cov_phi)) if v > 1.0]
    summary = {
        "theta": dict(zip(NAMES, map(float, result.theta))),
        "theta_std": dict(zip(NAMES, map(float, result.theta_std))),
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
        "poorly_determined": poor,
        "registration_rms_m": None if result.registration is None else result.registration["rms_m"],
        "output": output,
    }
    return summary


def apply_stored_registration(meas, registration: dict, params_path):
    """Apply the registration stored in a parameters file to a rig-frame measurement set (``heartcv track
    --params``): a ``tracker.registration.Registration`` rebuilt from the file, points selected by id."""
    import numpy as np

    try:
        from heartcv.tracker.registration import Registration, to_patch_frame
    except ImportError:
        raise BadInput("the measurements are in the rig frame and registration onto the patch is not available "
                       "(tracker.registration)") from None
    ids = registration.get("points_on_patch") or []
    on_patch = np.isin(np.asarray(meas.point_ids), np.asarray(ids, np.int64))
    if not on_patch.any():
        raise BadInput(f"{params_path}: none of the registered points (registration.points_on_patch) is in the "
                       "measurement file: the parameters were fitted to another file")
    reg = Registration(patch_from_rig=np.asarray(registration["patch_from_rig"], float),
                       rms_m=float(registration.get("rms_m", float("nan"))), on_patch=on_patch,
                       n_points=int(on_patch.sum()), converged=True,
                       message=f"stored in {params_path}")
    try:
        return to_patch_frame(meas, reg)
    except ValueError as exc:
        raise BadInput(f"registration from {params_path}: {exc}") from None
