"""``heartcv model``: inspect a model file and simulate measurements from it."""

from __future__ import annotations

import logging

import click

from .options import BadInput, StageFailed, emit_json, json_opt, load_model, seed_opt

log = logging.getLogger(__name__)


@click.group()
def model():
    """Inspect and simulate the physics model of a MODEL.yaml file."""


@model.command()
@click.argument("model_file", type=click.Path(exists=True, dir_okay=False))
@json_opt
def info(model_file, as_json):
    """Sizes, state dimension and lowest frequencies of MODEL_FILE as configured."""
    m = load_model(model_file)
    summary = m.info()
    if as_json:
        emit_json(summary)
        return
    for key, val in summary.items():
        click.echo(f"{key:>16}: {val}")


@model.command()
@click.argument("model_file", type=click.Path(exists=True, dir_okay=False))
@click.option("--duration", type=click.FloatRange(min=0, min_open=True), required=True,
              help="Simulated time in seconds.")
@seed_opt
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True,
              help="Measurement file to write (.npz).")
@click.option("--truth", "truth_path", type=click.Path(dir_okay=False), default=None,
              help="Also write the ground truth here (.npz).")
@click.option("--substeps", type=click.IntRange(min=1), default=1, show_default=True,
              help="Truth integration substeps per frame.")
@click.option("--missing", type=click.FloatRange(0, 1), default=0.0, show_default=True,
              help="Probability that a point is not seen in a frame.")
@click.option("--stiffness-cycle", type=click.FloatRange(min=0), default=0.0, show_default=True,
              help="Make E follow the cardiac cycle: E(t) = E (1 + a h(t)) with h the active-tension shape.")
@json_opt
def simulate(model_file, duration, seed, output, truth_path, substeps, missing, stiffness_cycle, as_json):
    """Simulate noisy 3-D measurements of MODEL_FILE's surface points."""
    import numpy as np

    from heartcv.tracker import inputs as inp
    from heartcv.tracker.io import file_hash, write_measurements, write_truth
    from heartcv.tracker.simulate import simulate as run, to_measurements


    m = load_model(model_file)
    rng = np.random.default_rng(seed)
    theta = None
    if stiffness_cycle > 0:
        base = m.config.theta.copy()
        ic = m.config.inputs

        def theta(t):
            h = inp.active_tension(np.atleast_1d(t), heart_rate_bpm=ic.heart_rate_bpm, t_max=1.0,
                                   rr_intervals=ic.rr_intervals)[0]
            th = base.copy()
            th[3] = base[3] * (1.0 + stiffness_cycle * h)
            return th

    from threadpoolctl import threadpool_limits

    try:
        with threadpool_limits(1):
            sim = run(m, duration, rng, theta=theta, substeps=substeps, missing_fraction=missing)
    except FloatingPointError as exc:
        raise StageFailed(f"{model_file}: {exc}; nothing written") from None
    except ValueError as exc:
        raise BadInput(str(exc)) from None
    meta = {"producer": "heartcv model simulate", "seed": seed, "model": str(model_file),
            "inputs_hash": {"model": file_hash(model_file)}, "stiffness_cycle": stiffness_cycle}
    meas = to_measurements(sim, meta)
    write_measurements(output, meas)
    if truth_path:
        write_truth(truth_path, sim, meta)
    summary = {"frames": int(sim.times.size), "points": int(sim.reference.shape[0]),
               "duration_s": float(sim.times[-1]), "output": output, "truth": truth_path,
               "peak_displacement_m": float(np.abs(sim.positions - sim.positions[:1]).max()),
               "measurement_std_m": sim.measurement_std}
    if as_json:
        emit_json(summary)
    else:
        log.warning("wrote %s (%d frames, %d points)", output, summary["frames"], summary["points"])
