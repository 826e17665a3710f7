"""``heartcv track``: run an estimator over a measurement file."""

from __future__ import annotations

import logging

import click

from .options import BadInput, StageFailed, emit_json, json_opt, load_model

log = logging.getLogger(__name__)

ESTIMATORS = ("kf",)


@click.command()
@click.argument("measurements", type=click.Path(dir_okay=False))
@click.option("--model", "model_file", type=click.Path(exists=True, dir_okay=False), required=True,
              help="Model file (YAML).")
@click.option("--estimator", type=click.Choice(ESTIMATORS), default="kf", show_default=True,
              help="kf: Kalman filter with the model file's parameters held fixed.")
@click.option("--joseph", is_flag=True, help="Joseph-form covariance update.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True, help="Estimate file (.npz).")
@json_opt
def track(measurements, model_file, estimator, joseph, output, as_json):
    """Estimate the surface state from MEASUREMENTS and record one-step predictions."""
    import numpy as np

    from tracker.io import FileFormatError, file_hash, read_measurements, write_estimates
    from tracker.tracking import EstimationDiverged, run_kalman

    try:
        meas = read_measurements(measurements)
    except FileFormatError as exc:
        raise BadInput(str(exc)) from None
    m = load_model(model_file)
    from threadpoolctl import threadpool_limits

    try:
        with threadpool_limits(1):  # 168-sized matrices: one BLAS thread is far faster (spec/estimator §7.5)
            est = run_kalman(m, meas, joseph=joseph)
    except np.linalg.LinAlgError as exc:
        raise StageFailed(f"{estimator}: numerical failure ({exc}); no estimate file written") from None
    except EstimationDiverged as exc:
        raise StageFailed(f"{estimator} diverged at step {exc.step}; no estimate file written") from None
    except ValueError as exc:
        raise BadInput(f"{measurements}: {exc}") from None
    if est.meta.get("dropped_points"):
        log.warning("%d points lie off the patch and were ignored", len(est.meta["dropped_points"]))
    meta = {"producer": "heartcv track", "model": str(model_file),
            "inputs_hash": {"measurements": file_hash(measurements), "model": file_hash(model_file)}}
    write_estimates(output, est, meta)
    seen = np.isfinite(est.nis)
    summary = {
        "estimator": estimator,
        "steps": int(est.completed_steps),
        "nis_mean": float(np.mean(est.nis[seen])) if seen.any() else None,
        "nis_dof_mean": float(np.mean(est.nis_dof[seen])) if seen.any() else None,
        "prediction_rmse_m": est.prediction_rmse() if np.isfinite(est.prediction_rmse()) else None,
        "step_ms_median": float(np.median(est.step_time) * 1e3),
        "output": output,
    }
    if as_json:
        emit_json(summary)
    else:
        log.warning("wrote %s: %d steps, prediction RMSE %.4g mm", output, summary["steps"],
                    summary["prediction_rmse_m"] * 1e3)
