"""``heartcv track``: run an estimator over a measurement file."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import click

from .options import BadInput, StageFailed, emit_json, json_opt, load_model

log = logging.getLogger(__name__)

ESTIMATORS = ("kf", "ge", "ukf", "ekf")
ESTIMATOR_HELP = ("kf: Kalman filter with the model file's parameters held fixed; ge: Rao-Blackwellised Gaussian "
                  "estimator of state and parameters (the paper's); ukf / ekf: joint unscented / extended Kalman "
                  "filters on the augmented state (baselines). See docs/estimators.md.")


def _partial_path(output) -> Path:
    p = Path(output)
    return p.with_name(p.name[: -len(p.suffix)] + ".partial" + p.suffix if p.suffix else p.name + ".partial")


@click.command()
@click.argument("measurements", type=click.Path(dir_okay=False))
@click.option("--model", "model_file", type=click.Path(exists=True, dir_okay=False), required=True,
              help="Model file (YAML).")
@click.option("--estimator", type=click.Choice(ESTIMATORS), default="kf", show_default=True, help=ESTIMATOR_HELP)
@click.option("--nodes", "nodes", type=int, default=None,
              help="GE: Dirac nodes per parameter axis D (odd, >= 3; default from the model file, 5).")
@click.option("--truncation", type=click.Choice(("sequential", "tallis", "none")), default=None,
              help="Box truncation of the parameters after every prediction and update: for ge the default comes "
                   "from the model file (sequential); ukf and ekf do not truncate unless asked.")
@click.option("--joseph", is_flag=True, help="Joseph-form covariance update.")
@click.option("--params", "params_file", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Parameters file of heartcv fit: its theta replaces the model file's parameters (kf: held at "
                   "them; ge/ukf/ekf: the prior mean, with the fit's standard deviation unless the model file's "
                   "prior is tighter); its registration is applied to rig-frame measurements.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True, help="Estimate file (.npz).")
@json_opt
@click.pass_context
def track(ctx, measurements, model_file, estimator, nodes, truncation, joseph, params_file, output, as_json):
    """Estimate the surface state (and, for ge/ukf/ekf, the parameters) from MEASUREMENTS and record the
    one-step predictions of every point.

    A run whose estimate becomes non-finite stops with exit 1; the steps done are written to
    OUTPUT with `.partial` before the suffix (completed_steps < frames), never to OUTPUT itself.

    With --params (heartcv fit) the fitted parameters replace the model file's values.
    """
    import numpy as np

    from heartcv.tracker.io import FileFormatError, file_hash, read_measurements, read_parameters, write_estimates
    from heartcv.tracker.joint import JointOptions, run_joint
    from heartcv.tracker.params import NAMES
    from heartcv.tracker.tracking import EstimationDiverged, run_kalman

    try:
        meas = read_measurements(measurements)
    except FileFormatError as exc:
        raise BadInput(str(exc)) from None
    m = load_model(model_file)
    fitted = None
    if params_file is not None:
        try:
            fitted = read_parameters(params_file)
        except FileFormatError as exc:
            raise BadInput(str(exc)) from None
        was_rig = meas.frame == "rig"
        meas = _apply_params_registration(meas, fitted, params_file, measurements)
        if was_rig:
            # measured references are birth-frame (deformed) positions: use the fit's undeformed offsets
            from heartcv.tracker.fit import undeformed_references

            try:
                meas = undeformed_references(m, meas, fitted.theta, fitted.frames)
            except ValueError as exc:
                raise BadInput(f"{measurements}: {exc}") from None
            if meas.meta.get("dropped_points"):
                log.info("%d points seen in fewer than two of the fit's %d frames were left out",
                         len(meas.meta["dropped_points"]), fitted.frames)
        fitted_model = (fitted.meta.get("inputs_hash") or {}).get("model")
        if fitted_model is not None and fitted_model != file_hash(model_file):
            log.warning("%s was fitted with another model file than %s", params_file, model_file)
    if estimator == "kf" and truncation is not None:
        raise BadInput("--truncation applies to the joint estimators (ge, ukf, ekf) only")
    if estimator != "ge" and nodes is not None:
        raise BadInput("--nodes applies to the GE only")
    options = None
    if estimator != "kf":
        if not m.config.estimation.estimate:
            raise BadInput(f"{model_file}: estimation.estimate is empty; {estimator} needs at least one parameter")
        try:
            if estimator == "ge":
                options = JointOptions.from_config(m.config, nodes=nodes, truncation=truncation, joseph=joseph)
            else:
                options = JointOptions.from_config(m.config, baseline_truncation=truncation, joseph=joseph)
        except ValueError as exc:
            raise BadInput(f"--nodes/--truncation: {exc}") from None
    from threadpoolctl import threadpool_limits

    verbosity = (ctx.find_object(dict) or {}).get("verbosity", 0)
    meta = {"producer": "heartcv track", "model": str(model_file),
            "inputs_hash": {"measurements": file_hash(measurements), "model": file_hash(model_file)}}
    theta0 = prior_std = None
    if fitted is not None:
        from heartcv.tracker.fit import tracking_prior

        meta["params"] = str(params_file)
        meta["inputs_hash"]["params"] = file_hash(params_file)
        if isinstance(meas.meta.get("registration"), dict):     # rig-frame file: where the patch frame lies
            meta["patch_from_rig"] = meas.meta["registration"].get("patch_from_rig")
        if estimator != "kf":
            theta0, prior_std, source = tracking_prior(m.config, fitted)
            meta["prior_source"] = source
    try:
        with threadpool_limits(1):  # 168-sized matrices: one BLAS thread is far faster (docs/spec/estimator.md §7.5)
            if estimator == "kf":
                est = run_kalman(m, meas, None if fitted is None else fitted.theta, joseph=joseph)
            else:
                with click.progressbar(length=meas.n_frames, label=estimator, file=sys.stderr) \
                        if verbosity >= 0 and sys.stderr.isatty() else _NoBar() as bar:
                    est = run_joint(m, meas, estimator, theta0=theta0, prior_std=prior_std, options=options,
                                    progress=lambda done, total: bar.update(1))
    except np.linalg.LinAlgError as exc:
        raise StageFailed(f"{estimator}: numerical failure ({exc}); no estimate file written") from None
    except EstimationDiverged as exc:
        where = ""
        if exc.partial is not None and exc.partial.completed_steps > 0:
            part = _partial_path(output)
            write_estimates(part, exc.partial, dict(meta, partial=True))
            where = f"; the {exc.partial.completed_steps} steps done were written to {part} (marked partial)"
        raise StageFailed(f"{estimator} diverged at step {exc.step} (time {meas.times[exc.step]:.4g} s): the "
                          f"estimate became non-finite{where}; no estimate file written to {output}") from None
    except ValueError as exc:
        raise BadInput(f"{measurements}: {exc}") from None
    if est.meta.get("dropped_points"):
        log.warning("%d points lie off the patch and were ignored", len(est.meta["dropped_points"]))
    write_estimates(output, est, meta)
    seen = np.isfinite(est.nis)
    summary = {
        "estimator": estimator,
        "steps": int(est.completed_steps),
        "nis_mean": float(np.mean(est.nis[seen])) if seen.any() else None,
        "nis_dof_mean": float(np.mean(est.nis_dof[seen])) if seen.any() else None,
        "prediction_rmse_m": est.prediction_rmse() if np.isfinite(est.prediction_rmse()) else None,
        "step_ms_median": float(np.median(est.step_time[1:] if est.step_time.size > 1 else est.step_time) * 1e3),
        "theta_final": dict(zip(NAMES, map(float, est.theta[-1]))),
        "theta_std_final": dict(zip(NAMES, map(float, est.theta_std[-1]))),
        "truncation_events": int(est.truncation_events.sum()),
        "estimated": list(est.meta.get("estimated", [])),
        "output": output,
    }
    if as_json:
        emit_json(summary)
    else:
        rmse = summary["prediction_rmse_m"]
        msg = f"wrote {output}: {summary['steps']} steps, prediction RMSE " + (
            f"{rmse * 1e3:.4g} mm" if rmse is not None else "n/a (no point seen after frame 0)")
        if estimator != "kf":
            msg += ", " + ", ".join(f"{n} = {summary['theta_final'][n]:.4g} ± {summary['theta_std_final'][n]:.2g}"
                                    for n in summary["estimated"])
        log.warning(msg)


def _apply_params_registration(meas, fitted, params_file, measurements):
    """Rig-frame measurements: apply the registration stored by heartcv fit; patch frame: nothing to do."""
    if meas.frame == "rig":
        if fitted.registration is None:
            raise BadInput(f"{measurements}: rig-frame measurements, but {params_file} holds no registration "
                           "(it was fitted to patch-frame measurements)")
        from .fit import apply_stored_registration

        return apply_stored_registration(meas, fitted.registration, params_file)
    if fitted.registration is not None:
        log.warning("%s holds a registration but %s is in the patch frame: not applied", params_file, measurements)
    return meas


class _NoBar:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False

    def update(self, n):
        pass
