"""``heartcv simulate``: Monte-Carlo study of the parameter estimators on the model itself (paper §VI.A;
docs/cli.md §5)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
import time

import click

from .options import BadInput, Int, StageFailed, emit_json, guard_outputs, json_opt, load_model, progress, seed_opt

log = logging.getLogger(__name__)

SUMMARY = "summary.json"
PRODUCER = "heartcv simulate"
MAX_RUNS = 10_000
MAX_STEPS = 100_000
MAX_RUN_STEPS = 10**7      # runs x steps: the study's arrays grow with it
MAX_WORKERS = 1024


def _estimators_handler(ctx, param, value):
    from heartcv.tracker.study import ESTIMATORS  # imported here, not at module level: `heartcv --help` stays fast

    names = [v.strip().lower() for v in value.split(",") if v.strip()]
    if not names:
        raise click.BadParameter(f"at least one of {', '.join(ESTIMATORS)} expected")
    unknown = [n for n in names if n not in ESTIMATORS]
    if unknown:
        raise click.BadParameter(f"unknown estimator {unknown[0]!r} (choose from {', '.join(ESTIMATORS)})")
    return tuple(dict.fromkeys(names))


@click.command()
@click.argument("model_file", type=click.Path(exists=True, dir_okay=False))
@click.option("--runs", type=Int(2, MAX_RUNS), default=50, show_default=True,
              help="Monte-Carlo runs (the paper uses 50).")
@click.option("--steps", type=Int(2, MAX_STEPS), default=100, show_default=True,
              help="Frames per run (at the model's frame rate).")
@seed_opt
@click.option("--estimators", default="ge,ukf,ekf,kf", show_default=True, callback=_estimators_handler,
              help="Comma-separated estimators: ge, ukf, ekf (joint) and kf (parameters held at the initial "
                   "guess).")
@click.option("--workers", type=Int(1, MAX_WORKERS), default=2, show_default=True,
              help="Worker processes (1: run in this process).")
@click.option("-o", "--output", type=click.Path(file_okay=False), required=True,
              help="Study folder (replaces only a folder that heartcv simulate wrote).")
@json_opt
@click.pass_context
def simulate(ctx, model_file, runs, steps, seed, estimators, workers, output, as_json):
    """Monte-Carlo study of the estimators on MODEL_FILE (paper §VI.A).

    Each run draws a random initial parameter guess, simulates fresh measurements with the model file's
    parameters and runs every estimator from the guess. Writes study.npz, the figures and summary.json
    (error, consistency and timing statistics) into the folder given by -o, built beside it and renamed into
    place when complete."""
    from threadpoolctl import threadpool_limits

    from heartcv.tracker import study as st
    from heartcv.tracker.files import InputError

    t_start = time.perf_counter()
    if runs * steps > MAX_RUN_STEPS:
        raise BadInput(f"--runs {runs} x --steps {steps}: at most {MAX_RUN_STEPS} run-steps in one study")
    guard_outputs({"-o/--output": output}, {"MODEL_FILE": model_file}, folders=[("-o/--output", output, PRODUCER)])
    verbosity = (ctx.find_root().obj or {}).get("verbosity", 0)
    m = load_model(model_file)
    with progress(range(runs), "runs", length=runs, verbosity=verbosity) as bar:
        tick = (lambda done, total: bar.update(1)) if hasattr(bar, "update") else None
        try:
            estimators = st.check_estimators(estimators, m.config.parameter_space().dim)
            with threadpool_limits(1):  # small matrices: one BLAS thread is far faster (docs/spec/estimator.md §7.5)
                study = st.run_study(m, runs=runs, steps=steps, seed=seed, estimators=estimators,
                                     workers=workers, progress=tick)
        except InputError as exc:  # the model file's estimation section does not allow the study
            raise exc.in_file(model_file) from None
        except FloatingPointError as exc:  # the truth simulation itself diverged
            raise StageFailed(f"{model_file}: {exc}; nothing written") from None
    statistics = study.statistics()
    for name, s in statistics.items():
        if s.diverged:
            log.warning("%s diverged in %d of %d runs (left out of its statistics)", name, s.diverged, runs)
    if all(s.runs_used == 0 for s in statistics.values()):
        raise StageFailed(f"every run diverged for every estimator ({', '.join(estimators)}); nothing written")

    summary = st.summary(study, statistics)
    summary.update({"output": output, "model": str(model_file), "workers": workers})
    _write(Path(output), study, statistics, summary, model_file, t_start)
    if as_json:
        emit_json(summary)
    else:
        _log_table(summary)


def _write(out: Path, study, statistics, summary: dict, model_file, t_start: float) -> None:
    """Write study.npz, the figures and summary.json into a folder built beside ``out`` and renamed to it when
    complete (an older study there is replaced as a whole); sets ``summary['wall_s']``."""
    from heartcv.tracker import __version__
    from heartcv.tracker import study as st
    from heartcv.tracker.files import atomic_folder
    from heartcv.tracker.io import STUDY_FORMAT, file_hash, write_study

    meta = {"producer": PRODUCER, "model": str(model_file), "inputs_hash": {"model": file_hash(model_file)}}
    with atomic_folder(out, producer=PRODUCER) as tmp:
        write_study(tmp / "study.npz", st.arrays(study, statistics), meta)
        files = ["study.npz"] + _figures(tmp, study, statistics) + [SUMMARY]
        summary["wall_s"] = time.perf_counter() - t_start
        doc = dict(summary)
        doc.update(meta)
        doc.update({"files": files, "format": STUDY_FORMAT[0], "format_version": STUDY_FORMAT[1],
                    "heartcv_version": __version__})
        (tmp / SUMMARY).write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n", encoding="utf-8")


def _figures(out: Path, study, statistics) -> list:
    import numpy as np

    from heartcv.tracker.params import NAMES, UNITS

    from .plots import SYMBOLS, TITLES, consistency_figure, error_figure, save_png

    k = np.arange(study.steps)
    dt = study.dt
    written = []
    div = [f"{e.upper()} {s.diverged}" for e, s in statistics.items() if s.diverged]
    n_label = f"{study.runs} Monte-Carlo runs" if not div else f"{study.runs} runs (diverged: {', '.join(div)})"
    for j, name in enumerate(study.estimated):
        series = {e: (s.abs_error_mean[:, j], s.abs_error_var[:, j]) for e, s in statistics.items()
                  if s.runs_used}
        fig = error_figure(k, series, quantity=SYMBOLS[name], unit=UNITS[NAMES.index(name)], dt=dt,
                           title=f"Error of {TITLES[name]} over {n_label}")
        save_png(fig, out / f"fig2_{name}.png")
        written.append(f"fig2_{name}.png")
    joint = {e: s for e, s in statistics.items() if s.anees is not None and s.runs_used}
    if joint:
        band, band_label = _band(joint, "anees_band")
        M = len(study.estimated)
        fig = consistency_figure(k, {e: s.anees for e, s in joint.items()}, band, reference=M, dt=dt,
                                 band_label=band_label,
                                 ylabel=f"ANEES of the parameters ({M} dof)",
                                 title=f"Parameter consistency (ANEES) over {n_label}")
        save_png(fig, out / "anees.png")
        written.append("anees.png")
    used = {e: s for e, s in statistics.items() if s.runs_used}
    band, band_label = _band(used, "nis_band")
    fig = consistency_figure(k, {e: s.nis_per_dof for e, s in used.items()}, band, band_label=band_label,
                             reference=1.0, dt=dt,
                             ylabel="mean NIS per degree of freedom",
                             title=f"Measurement consistency (NIS) over {n_label}")
    save_png(fig, out / "nis.png")
    written.append("nis.png")
    return written


def _band(stats: dict, key: str):
    """The 95 % band to shade and its legend label: the common band, or (divergences changed n) the band of
    the estimator with the fewest runs used, named, rather than none."""
    bands = {getattr(s, key) for s in stats.values()} - {None}
    if len(bands) <= 1:
        return (bands.pop() if bands else None), "95 % χ² band"
    name, s = min(stats.items(), key=lambda kv: kv[1].runs_used)
    return getattr(s, key), f"95 % χ² band ({name.upper()}, {s.runs_used} runs)"


def _fmt(v, scale=1.0):
    return "-" if v is None else f"{v * scale:.4g}"


def _log_table(summary):
    from heartcv.tracker.params import NAMES, UNITS

    from .plots import si_scale

    names = summary["estimated"]
    ests = summary["estimators"]
    scale, unit = {}, {}
    for n in names:
        values = [s["rmse_initial"][n] for s in ests.values() if s["rmse_initial"][n] is not None]
        scale[n], unit[n] = si_scale(values, UNITS[NAMES.index(n)])
    head = "".join(f"  {n + ' [' + unit[n] + '] init->final':>28}" for n in names)
    log.info("%d runs x %d steps, seed %d, estimated %s -> %s (%.1f s)", summary["runs"], summary["steps"],
                summary["seed"], ", ".join(names) or "none", summary["output"], summary["wall_s"])
    log.info("%-4s %4s%s  %8s %17s %6s %8s %8s", "est", "div", head, "ANEES", "band", "in", "NIS/dof",
             "ms/step")
    for e, s in ests.items():
        cols = "".join(f"  {_fmt(s['rmse_initial'][n], scale[n]) + ' -> ' + _fmt(s['rmse_final'][n], scale[n]):>28}"
                       for n in names)
        band = "-" if s["anees_band"] is None else f"[{s['anees_band'][0]:.3g}, {s['anees_band'][1]:.3g}]"
        log.info("%-4s %4d%s  %8s %17s %6s %8s %8s", e, s["diverged"], cols, _fmt(s["anees"]), band,
                 _fmt(s["anees_in_band_fraction"]), _fmt(s["nis_per_dof_mean"]), _fmt(s["step_ms_median"]))
