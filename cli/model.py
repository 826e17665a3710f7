"""``heartcv model``: inspect a model file and simulate measurements from it (docs/cli.md §2, §3)."""

from __future__ import annotations

import logging
from pathlib import Path

import click

from .options import (
    MAX_COUNT,
    BadInput,
    Float,
    Int,
    StageFailed,
    announce,
    emit_json,
    guard_outputs,
    json_opt,
    load_model,
    seed_opt,
)

log = logging.getLogger(__name__)

MAX_DURATION_S = 86400.0   # one day of simulated time
MAX_SUBSTEPS = 1000        # truth integration substeps per frame
MAX_STIFFNESS_CYCLE = 20.0  # E(t) up to 21 E (as the scenes' stiffness_cycle.amplitude)


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
@click.option("--duration", required=True, type=Float(0, MAX_DURATION_S, lo_open=True),
              help="Simulated time in seconds (at most one day and 10^6 frames).")
@seed_opt
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Measurement file to write (.npz).")
@click.option("--truth", "truth_path", default=None, type=click.Path(dir_okay=False),
              help="Also write the ground truth here (.npz).")
@click.option("--substeps", default=1, show_default=True, type=Int(1, MAX_SUBSTEPS),
              help="Truth integration substeps per frame.")
@click.option("--missing", default=0.0, show_default=True, type=Float(0, 1),
              help="Probability that a point is not seen in a frame.")
@click.option("--stiffness-cycle", default=0.0, show_default=True, type=Float(0, MAX_STIFFNESS_CYCLE),
              help="Make E follow the cardiac cycle: E(t) = E (1 + a h(t)) with h the active-tension shape.")
@json_opt
def simulate(model_file, duration, seed, output, truth_path, substeps, missing, stiffness_cycle, as_json):
    """Simulate noisy 3-D measurements of MODEL_FILE's surface points."""
    import numpy as np
    from threadpoolctl import threadpool_limits

    from heartcv.tracker.io import file_hash, write_measurements, write_truth
    from heartcv.tracker.simulate import simulate as run
    from heartcv.tracker.simulate import stiffness_schedule, to_measurements

    _guard(model_file, output, truth_path)
    m = load_model(model_file)
    _check_size(duration, substeps, m.config.frame_rate)
    for label, path in (("-o/--output", output), ("--truth", truth_path)):
        if path is not None and Path(path).suffix.lower() != ".npz":
            raise BadInput(f"{label}: a .npz file expected, got {path}")
    theta = stiffness_schedule(m, stiffness_cycle, "active")
    try:
        with threadpool_limits(1):
            sim = run(m, duration, np.random.default_rng(seed), theta=theta, substeps=substeps,
                      missing_fraction=missing)
    except FloatingPointError as exc:  # the truth diverged: a model the integrator cannot follow
        raise StageFailed(f"{model_file}: {exc}; nothing written") from None
    meta = {"producer": "heartcv model simulate", "seed": seed, "model": str(model_file),
            "inputs_hash": {"model": file_hash(model_file)}, "stiffness_cycle": stiffness_cycle}
    write_measurements(output, to_measurements(sim, meta))
    if truth_path:   # the measurement file it belongs with: heartcv report refuses it beside another one
        write_truth(truth_path, sim, dict(meta, measurements_hash=file_hash(output)))
    summary = {"frames": int(sim.times.size), "points": int(sim.reference.shape[0]),
               "duration_s": float(sim.times[-1]), "output": output, "truth": truth_path,
               "peak_displacement_m": sim.peak_displacement_m,
               "measurement_std_m": sim.measurement_std}
    if as_json:
        emit_json(summary)
    else:
        announce(log, "wrote %s (%d frames, %d points)", output, summary["frames"], summary["points"])


def _guard(model_file, output, truth_path) -> None:
    """Refuse, before any work, outputs that are the model file or one another, and files heartcv did not
    write (exit 2)."""
    if truth_path is not None and Path(output).resolve() == Path(truth_path).resolve():
        raise BadInput(f"-o/--output and --truth name the same file ({output}); choose two paths")
    guard_outputs({"-o/--output": output, "--truth": truth_path}, {"MODEL_FILE": model_file},
                  files=[("-o/--output", output, ("heartcv.measurements",)),
                         ("--truth", truth_path, ("heartcv.truth",))])


def _check_size(duration: float, substeps: int, frame_rate: float) -> None:
    """At most MAX_COUNT frames and MAX_COUNT integration steps (exit 2 naming the options)."""
    frames = int(duration * frame_rate + 1e-9) + 1
    if frames > MAX_COUNT or frames * substeps > MAX_COUNT:
        raise BadInput(f"--duration {duration:g} s at the model's {frame_rate:g} Hz gives {frames} frames of "
                       f"{substeps} substeps; at most {MAX_COUNT} frames and {MAX_COUNT} integration steps")
