"""``heartcv report``: compare estimator runs over one sequence in a report folder (index.html, PNG figures,
metrics.json, summary.md).

Loading, the checks that the files belong together and the folder output live here; the numbers come from
:mod:`tracker.metrics`, the figures from :mod:`cli.report_plots`, the text of summary.md and index.html from
:mod:`cli.report_doc`. Folder layout and metrics.json keys: docs/formats.md §14; the command: docs/cli.md §11.
"""

from __future__ import annotations

import functools
import json
import logging
import os
from pathlib import Path

import click

from .options import BadInput, Int, announce, emit_json, guard_outputs, json_opt, seed_opt

log = logging.getLogger(__name__)

REPORT_FORMAT = ("heartcv.report", 1)
PRODUCER = "heartcv report"
LEVEL = 0.95  # NIS bands


@click.command()
@click.argument("estimates", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--truth", "truth_file", type=click.Path(dir_okay=False),
              help="Ground truth: `heartcv model simulate --truth` file (parameters and point positions) or the "
                   "truth.npz of `heartcv render sequence` (parameters; with --measurements also the truth error).")
@click.option("--measurements", "meas_file", type=click.Path(dir_okay=False),
              help="The measurement file the estimates were made from (the measurement noise level, the tracks' "
                   "own motion, the truth error of a render truth).")
@click.option("-o", "--output", type=click.Path(file_okay=True), required=True,
              help="Report folder (created; replaces only a folder that heartcv report wrote, never one holding an "
                   "input).")
@click.option("--allow-mixed", is_flag=True,
              help="Accept estimate, truth and measurement files of different sequences (warns instead of "
                   "exit 2).")
@click.option("--dpi", type=Int(72, 600), default=150, show_default=True, help="Resolution of the PNGs.")
@click.option("--image", "images", multiple=True, type=click.Path(dir_okay=False),
              help="A PNG to show in the report, copied into it (e.g. a frame of `heartcv measure --overlay` with "
                   "the tracked points); repeatable.")
@click.option("--resamples", type=Int(0, 1_000_000), default=2000, show_default=True,
              help="Bootstrap resamples of the 95 % intervals of the error ratios (to hold, GE / KF): circular "
                   "blocks of frames, drawn with --seed; 0: no intervals, else at least 100.")
@seed_opt
@json_opt
def report(estimates, truth_file, meas_file, output, allow_mixed, dpi, images, resamples, seed, as_json):
    """Compare the estimate files ESTIMATES (`heartcv track` outputs of one measurement file): one-step
    prediction error, parameter trajectories with ±2σ bands, NIS with its χ² band, error against the truth,
    step times. Writes the folder OUTPUT atomically."""
    import numpy as np
    from threadpoolctl import threadpool_limits

    from heartcv.tracker import metrics as tm
    from heartcv.tracker.files import atomic_folder

    if 0 < resamples < 100:
        raise BadInput(f"--resamples: 0 (no intervals) or at least 100 expected, got {resamples}")
    inputs = {"ESTIMATES" if len(estimates) == 1 else f"ESTIMATES #{i + 1}": p for i, p in enumerate(estimates)}
    inputs.update({"--truth": truth_file, "--measurements": meas_file})
    inputs.update({f"--image #{i + 1}": p for i, p in enumerate(images)})
    _check_images(images)
    guard_outputs({"-o/--output": output}, inputs, folders=[("-o/--output", output, PRODUCER)])
    runs = _load_estimates(estimates)
    _check_sequences(runs, allow_mixed)
    noise, noise_norm, noise_source = _measurement_noise(meas_file, runs, allow_mixed)
    phases = _phases(meas_file)
    truth = _load_truth(truth_file, runs, allow_mixed, meas_file) if truth_file else None
    for label, r in runs.items():
        if truth is not None and label in truth["positions"] and r["est"].filtered is None:
            truth["notes"].append(f"{label}: the estimate file records no filtered positions (written before "
                                  "heartcv track recorded them); truth error of the one-step predictions only")
    fit_frames = _fit_frames(runs)
    if truth is not None and truth["left_out"] >= set(runs):    # no run's sequence: its parameters drawn nowhere
        truth["theta"] = None
    theta = ({k: truth["theta"] for k in runs if k not in truth["left_out"]}
             if truth is not None and truth["theta"] is not None else None)
    with threadpool_limits(1):   # per-frame bootstrap sums: one BLAS thread (docs/spec/estimator.md §7.5)
        compared = tm.compare_runs({k: r["est"] for k, r in runs.items()}, truth["positions"] if truth else None,
                                   theta, LEVEL, fit_frames,
                                   rng=np.random.default_rng(seed) if resamples else None,
                                   resamples=resamples or 100)
    metrics = _metrics_document(runs, compared, noise, noise_norm, noise_source, truth)
    _warn_unpaired(runs, compared)
    with threadpool_limits(1):   # small matrices per frame (field_ar_prediction's 108 x 108 solves): one BLAS thread
        metrics["tracks"] = _track_motion(meas_file, runs)
    metrics["rig_check"] = _rig_check(meas_file)
    metrics.update(_provenance(runs, truth_file, meas_file))
    with atomic_folder(output, producer=PRODUCER) as tmp:
        doc = _write_folder(tmp, metrics, runs, compared["per_run"], truth, noise, dpi, phases, images)
    if as_json:
        emit_json(dict(doc, output=output))
    else:
        announce(log, "wrote %s (%d figures); %s", output, len(doc["figures"]), _headline(doc))


def _warn_unpaired(runs, compared) -> None:
    """Warn where runs are not compared on the same observations: other held-out tracks, or a run without a
    prediction for observations that hold predicted (its means then leave out those, possibly the hardest)."""
    held = {label: sorted(r["est"].meta.get("heldout_points") or []) for label, r in runs.items()}
    if len({tuple(v) for v in held.values()}) > 1:
        log.warning("runs hold out different tracks (track --holdout/--seed): %s; their errors are over different "
                    "tracks and the ratios to hold are left out", ", ".join(f"{k} {len(v)}" for k, v in held.items()))
    for label, m in compared["per_run"].items():
        iv = m.get("ratio_to_hold_interval") or {}
        if iv.get("numerator_missing"):
            log.warning("%s: no prediction for %d observations that hold predicted; its errors leave them out",
                        label, iv["numerator_missing"])


def _fit_frames(runs) -> int | None:
    """The frames that fitted the runs' parameters (``meta.fit_frames``, heartcv track --params), one split for
    every run: the largest where they differ (no run's in-sample frame counts as after its fit); None when no run
    records one."""
    found = {label: r["est"].meta["fit_frames"] for label, r in runs.items()      # an int >= 1 (read_estimates)
             if r["est"].meta.get("fit_frames") is not None}
    if not found:
        return None
    if len(set(found.values())) > 1:
        log.warning("the runs' parameters were fitted over different frames (%s): the split within / after the "
                    "fit uses the largest", ", ".join(f"{k}: {v}" for k, v in found.items()))
    return max(found.values())


def _provenance(runs, truth_file, meas_file) -> dict:
    from heartcv.tracker.io import file_hash

    hashes = {"estimates": {k: file_hash(r["path"]) for k, r in runs.items()}}
    for role, p in (("truth", truth_file), ("measurements", meas_file)):
        if p:
            hashes[role] = file_hash(p)
    from heartcv.tracker.files import software_versions

    recorded = {k: r["est"].meta.get("software") for k, r in runs.items()}
    if meas_file:
        recorded["measurements"] = _measurements(meas_file).meta.get("software")
    return {"inputs": {"estimates": {k: str(r["path"]) for k, r in runs.items()}, "truth": truth_file,
                       "measurements": meas_file},
            "inputs_hash": hashes, "software": software_versions(), "inputs_software": recorded}


def _check_images(images) -> None:
    """Exit 2 for an --image that is missing, not a PNG, or a PNG that does not decode (cut short, damaged)."""
    from heartcv.io import HeartcvIOError, read_image

    for i, p in enumerate(images):
        path = Path(p)
        if not path.is_file():
            raise BadInput(f"--image #{i + 1}: {p}: no such file")
        with open(path, "rb") as f:
            if f.read(8) != b"\x89PNG\r\n\x1a\n":
                raise BadInput(f"--image #{i + 1}: {p}: not a PNG file")
        try:
            read_image(path, "unchanged")
        except HeartcvIOError as exc:
            raise BadInput(f"--image #{i + 1}: {p}: {exc.reason}") from None


def _write_folder(tmp: Path, metrics: dict, runs, per, truth, noise, dpi, phases=None, images=()) -> dict:
    """The figures, metrics.json, summary.md and index.html into ``tmp``; returns the metrics document."""
    import shutil

    from .report_doc import html, markdown
    from .report_plots import write_figures

    figures = []
    for i, p in enumerate(images):   # the user's images first: what was tracked, then how well
        name = f"image_{i + 1}_{Path(p).name}"
        shutil.copyfile(p, tmp / name)
        figures.append((name, f"{p} (given with --image)"))
    tracks = metrics.get("tracks") or {}
    figures += write_figures(tmp, runs, per, truth, noise, dpi, LEVEL, phases, tracks.get("noise_norm_bound_m"),
                             metrics.get("fit_frames"), (tracks.get("heart_rate_windows") or {}).get("windows"),
                             noise_norm=metrics.get("measurement_noise_norm_mean_m"))
    metrics["figures"] = [f for f, _ in figures]
    metrics["files"] = [f for f, _ in figures] + ["metrics.json", "summary.md", "index.html"]
    doc = _jsonable(metrics)
    (tmp / "metrics.json").write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    (tmp / "summary.md").write_text(markdown(doc, figures), encoding="utf-8")
    (tmp / "index.html").write_text(html(doc, figures, tmp), encoding="utf-8")
    return doc


def _headline(doc) -> str:
    from .report_doc import mm

    parts = [f"{k}: prediction error {mm(v['prediction_error_mean_m'])}"
             + (f", truth error {mm(v['truth_error_mean_m'])}" if v["truth_error_mean_m"] is not None else "")
             + (f" (predictions {mm(v['prediction_truth_error_mean_m'])})"
                if v["prediction_truth_error_mean_m"] is not None else "")
             for k, v in doc["estimators"].items()]
    if doc["measurement_truth_error_mean_m"] is not None:
        parts.append(f"measurements {mm(doc['measurement_truth_error_mean_m'])}")
    return "; ".join(parts)


# -- inputs -----------------------------------------------------------------------------------------
def _base_label(est) -> str:
    """The estimator's name, ``name-noinput`` for a run with its estimated input pinned at zero (--without-input),
    ``name-rigid-ar`` for one whose rigid motion has no heartbeat harmonics (fit --rigid-harmonics 0)."""
    return (est.estimator + ("-noinput" if est.meta.get("without_input") else "")
            + ("-rigid-ar" if est.meta.get("rigid_harmonics") == 0 else ""))


def _load_estimates(paths) -> dict:
    """label -> {'path', 'est'}; labels are the estimator names (``name-noinput`` for a --without-input run),
    ``name:stem`` where a name repeats."""
    from heartcv.tracker.io import read_estimates

    loaded = []
    for p in paths:
        est = read_estimates(p)
        if not est.complete:
            log.warning("%s: partial run (%d of %d steps completed); only the completed steps are used", p,
                        est.completed_steps, est.times.size)
        loaded.append((Path(p), est))
    names = [_base_label(e) for _, e in loaded]
    runs = {}
    for i, (p, est) in enumerate(loaded):
        label = names[i] if names.count(names[i]) == 1 else f"{names[i]}:{p.stem}"
        if label in runs:
            label = f"{label}-{i + 1}"
        runs[label] = {"path": p, "est": est}
    return runs


def _check_sequences(runs: dict, allow_mixed: bool) -> None:
    from heartcv.tracker.metrics import sequence_mismatch

    items = list(runs.values())
    problems = [f"{items[0]['path']} and {r['path']}: {why}" for r in items[1:]
                if (why := sequence_mismatch(items[0]["est"], r["est"]))]
    if problems and not allow_mixed:
        raise BadInput("estimate files of different sequences (" + "; ".join(problems) +
                       "); use --allow-mixed to compare them anyway")
    for p in problems:
        log.warning("mixed sequences: %s", p)


def _mismatch(times_a, times_b, label_a, label_b, allow_mixed, what) -> bool:
    """True if the frame times differ; exit 2 for that unless --allow-mixed (then a warning)."""
    from heartcv.tracker.metrics import times_mismatch

    why = times_mismatch(times_a, times_b)
    if why is not None:
        msg = f"{label_a} and {label_b}: different frame times ({why})"
        if not allow_mixed:
            raise BadInput(f"{msg}; {what} of another sequence? use --allow-mixed to go on without it")
        log.warning("%s; %s left out", msg, what)
    return why is not None


def _measurements(path):
    """The measurement file, read once per report (noise, phases, truth and the tracks' motion all use it)."""
    st = os.stat(path)
    return _read_measurements_once(str(path), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=1)
def _read_measurements_once(path, mtime_ns, size):
    from heartcv.tracker.io import read_measurements

    return read_measurements(path)


def _phases(meas_file):
    """(times, systole) from the pressure of --measurements (None without the file or a pressure input)."""
    if not meas_file:
        return None
    from heartcv.tracker.metrics import systole_mask

    m = _measurements(meas_file)
    if "pressure" not in m.input_names:
        return None
    return m.times, systole_mask(m.input_columns(("pressure",))[:, 0])


def _measurement_noise(meas_file, runs: dict, allow_mixed: bool):
    """(σ, E|v|, source), in m: from --measurements the per-coordinate level σ and the mean norm E|v| of the noise
    its covariances describe (a stereo point's depth noise several times its lateral noise: σ·√(8/π) would
    overstate the floor), else σ from an estimate file's meta ``measurement_noise_m`` and E|v| = σ·√(8/π)."""
    import numpy as np

    from heartcv.tracker.io import file_hash
    from heartcv.tracker.metrics import mean_noise_norm, mean_noise_norm_of_covariances, measurement_noise_level

    if meas_file:
        m = _measurements(meas_file)
        digest = file_hash(meas_file)
        for r in runs.values():
            recorded = (r["est"].meta.get("inputs_hash") or {}).get("measurements")
            if recorded and recorded != digest:
                msg = f"{meas_file}: not the measurement file {r['path']} was made from (inputs_hash differs)"
                if not allow_mixed:
                    raise BadInput(msg + "; use --allow-mixed to use it anyway")
                log.warning(msg)
            elif not recorded:
                _mismatch(r["est"].times, m.times, r["path"], meas_file, allow_mixed, "the measurement file")
        sigma = measurement_noise_level(m.covariances, m.seen)
        if not np.isfinite(sigma):
            return None, None, None
        return sigma, mean_noise_norm_of_covariances(m.covariances, m.seen), "measurements"
    for r in runs.values():
        v = r["est"].meta.get("measurement_noise_m")
        if isinstance(v, (int, float)) and np.isfinite(v) and v > 0:
            return float(v), mean_noise_norm(float(v)), f"estimate meta ({r['path']})"
    return None, None, None


def _rig_check(meas_file) -> dict | None:
    """What ``heartcv measure`` found of the rig against its views (the measurement file's ``rig_epipolar_px`` and
    ``rig_vertical_offsets_px``), for the report; None without --measurements or a file that records neither."""
    if meas_file is None:
        return None
    meta = _measurements(meas_file).meta
    epi, off = meta.get("rig_epipolar_px"), meta.get("rig_vertical_offsets_px")
    if not epi and not off:
        return None
    return {"epipolar_px": dict(epi) if epi else None, "vertical_offsets_px": dict(off) if off else None}


def _track_motion(meas_file, runs=None) -> dict | None:
    """What the tracks' own motion says, without any model (docs/formats.md §14 ``tracks``): the residual of a
    quadratic displacement field per frame over one frame (an upper bound of the noise) and over half a second, the
    data-driven autoregressive field predictor against ``hold`` (:func:`tracker.metrics.field_ar_prediction`),
    when the runs used a heart rate the tracks' own rate in windows and each run's agreement with it
    (:func:`tracker.metrics.windowed_heart_rate`, :func:`tracker.metrics.rate_agreement`) and, when the runs held
    tracks out, the neighbour oracle for them (:func:`tracker.metrics.heldout_neighbour_oracle`); None without
    --measurements or with too few frames."""
    import math

    import numpy as np

    from heartcv.tracker.metrics import (
        RATE_STEP_S,
        RATE_WINDOW_S,
        field_ar_prediction,
        heldout_neighbour_oracle,
        rate_agreement,
        smooth_field_residual,
        windowed_heart_rate,
    )

    from .report_plots import run_rates

    if not meas_file:
        return None
    m = _measurements(meas_file)
    dt = float(np.median(np.diff(m.times))) if m.n_frames > 1 else float("nan")
    if m.n_frames < 2 or not dt > 0:
        return None
    lag = max(1, int(round(0.5 / dt)))

    def mean(v):
        return float(np.nanmean(v)) if np.isfinite(v).any() else None

    r1 = mean(smooth_field_residual(m.positions, lag=1))
    out = {"field_residual_lag1_mean_m": r1,
           "noise_norm_bound_m": None if r1 is None else r1 / math.sqrt(2),
           "field_residual_half_second_mean_m": mean(smooth_field_residual(m.positions, lag=lag))
           if m.n_frames > lag else None, "half_second_lag_frames": lag, "field_ar": None}
    start = 60
    if m.n_frames > start + 10:
        fp = field_ar_prediction(m.positions, start=start)
        if np.isfinite(fp.predicted).any():
            hold = float(np.nanmean(fp.hold))
            out["field_ar"] = {"order": fp.order, "ridge": fp.ridge, "start_frame": start,
                               "hold_error_mean_m": hold, "error_mean_m": float(np.nanmean(fp.predicted)),
                               "ratio_to_hold": fp.ratio(),
                               "oracle_ratio_to_hold": float(np.nanmean(fp.oracle)) / hold if hold > 0 else None}
    out["heart_rate_windows"] = out["heart_rate_agreement"] = None
    rates = run_rates(runs or {}, "heart_rate")
    if rates:   # the runs used a heart rate: what the tracks' own spectrum says of it, window by window
        band = next((r["est"].meta["heart_rate_band_hz"] for r in (runs or {}).values()
                     if r["est"].meta.get("heart_rate_band_hz")), None)
        windows = windowed_heart_rate(m.times, m.positions, band=band)
        out["heart_rate_windows"] = {"window_s": RATE_WINDOW_S, "step_s": RATE_STEP_S, "windows": windows}
        out["heart_rate_agreement"] = {k: a for k, (t, f, sd) in rates.items()
                                       if (a := rate_agreement(windows, t, f, sd)) is not None} or None
    out["heldout_oracle"] = None
    ids = next((r["est"].meta["heldout_points"] for r in (runs or {}).values()
                if r["est"].meta.get("heldout_points")), None)
    if ids:
        held = np.isin(np.asarray(m.point_ids), np.asarray(ids))
        neighbours = 8
        err, hold = heldout_neighbour_oracle(m.positions, held, neighbours)
        if math.isfinite(err) and hold > 0:
            out["heldout_oracle"] = {"neighbours": neighbours, "points": int(held.sum()), "error_mean_m": err,
                                     "hold_error_mean_m": hold, "ratio_to_hold": err / hold}
    return out


def _load_truth(path, runs: dict, allow_mixed: bool, meas_file=None) -> dict:
    """{'kind', 'times', 'theta', 'positions': label -> (K, P, 3) where usable, 'notes'} of a truth file."""
    import numpy as np

    from heartcv.io import read_render_truth
    from heartcv.tracker.files import InputError
    from heartcv.tracker.io import read_truth

    truth = {"kind": None, "path": path, "positions": {}, "notes": [], "left_out": set()}
    try:
        data, tmeta = read_truth(path)
    except InputError as exc:
        if exc.field != "meta.format":
            raise
        try:
            data, meta = read_render_truth(path)
        except InputError as exc2:
            if exc2.field != "meta.format":
                raise
            raise InputError(path, "a truth file expected: format 'heartcv.truth' (heartcv model simulate --truth) "
                                   "or 'heartcv.render_truth' (heartcv render sequence)", "meta.format") from None
        _render_truth(truth, data, meta, path, runs, allow_mixed, meas_file)
        return truth
    truth.update(kind="simulation", times=data["times"], theta=data["theta"])
    made_with = tmeta.get("measurements_hash")      # the measurement file simulated with it (absent in older files)
    if made_with is not None and meas_file:
        from heartcv.tracker.io import file_hash

        if file_hash(meas_file) != made_with and _other_simulation(path, meas_file, allow_mixed):
            truth["notes"].append(f"the truth was simulated with another measurement file than {meas_file}: left out")
            truth["left_out"] = set(runs)
            return truth
    for label, r in runs.items():
        est = r["est"]
        if _mismatch(est.times, data["times"], r["path"], path, allow_mixed, "the truth"):
            truth["left_out"].add(label)
            truth["notes"].append(f"{label}: other frame times than the truth's: no truth error or true parameters")
            continue
        measured = (est.meta.get("inputs_hash") or {}).get("measurements")
        if made_with is not None and measured is not None and measured != made_with:
            if _other_simulation(path, r["path"], allow_mixed):
                truth["left_out"].add(label)
                truth["notes"].append(f"{label}: estimated from another measurement file than the truth was "
                                      "simulated with: no truth error or true parameters")
                continue
        P = est.point_ids.size
        if data["positions"].shape[1] != P or not np.array_equal(est.point_ids, np.arange(P)):
            truth["notes"].append(f"{label}: the truth's {data['positions'].shape[1]} points are not the "
                                  f"estimate's point ids; no truth error")
            continue
        truth["positions"][label] = data["positions"]
    return truth


def _other_simulation(truth_path, other, allow_mixed) -> bool:
    """A truth simulated with another measurement file than ``other`` was read from (its ``meta.measurements_hash``
    against the file's hash): exit 2 unless --allow-mixed, then a warning and True (left out)."""
    msg = (f"{truth_path}: meta.measurements_hash: the truth was simulated with another measurement file than "
           f"{other} (another seed or model?)")
    if not allow_mixed:
        raise BadInput(f"{msg}; use --allow-mixed to go on without it")
    log.warning("%s; the truth left out", msg)
    return True


def _render_truth(truth, data, meta, path, runs, allow_mixed, meas_file) -> None:
    """The parameters of a render truth of kind 'sequence', and the true positions where they can be had."""
    from heartcv.tracker.files import InputError

    if meta.get("kind") != "sequence":
        raise InputError(path, f"a render truth of kind 'sequence' expected, got {meta.get('kind')!r}", "meta.kind")
    for key in ("times", "theta"):
        if key not in data:
            raise InputError(path, "required for a sequence truth, missing", key)
    if "vertex_positions" in data:
        from heartcv.evaluate import TRUTH_FOR_ERRORS

        missing = [k for k in TRUTH_FOR_ERRORS if k not in data]
        if missing:
            raise InputError(path, f"missing arrays {missing} (a truth with vertex positions needs them for the "
                                   "truth error)")
    truth.update(kind="render", times=data["times"], theta=data["theta"])
    for label, r in runs.items():
        if _mismatch(r["est"].times, data["times"], r["path"], path, allow_mixed, "the truth"):
            truth["left_out"].add(label)
            truth["notes"].append(f"{label}: other frame times than the truth's: no truth error or true parameters")
    _render_truth_positions(truth, data, meta, runs, meas_file)


def _render_truth_positions(truth, arrays, tmeta, runs, meas_file):
    """Patch-frame true trajectories of the estimates' points from a render truth: each point's material point
    is the one its reference-camera pixel saw in its birth frame (the measurement file's ``reference_uv`` and
    ``reference_frame_index``; heartcv/evaluate.py: true camera ray and mesh, barycentric motion), mapped from the
    truth's world frame into the rig frame by the gauge fitted to the birth positions and into the patch frame
    by the estimate's ``patch_from_rig`` (:func:`tracker.metrics.truth_in_patch_frame`). Notes say why a run
    gets no truth positions."""
    import numpy as np

    from heartcv.tracker import metrics as tm

    def note(msg):
        truth["notes"].append(msg)

    if not meas_file:
        note("render truth: --measurements (the rig-frame file of heartcv measure) is needed for the truth error")
        return
    from heartcv.evaluate import truth_errors

    meas = _measurements(meas_file)
    uv = meas.meta.get("reference_uv")
    birth = meas.meta.get("reference_frame_index")
    if meas.frame != "rig" or uv is None or birth is None:
        note(f"render truth: {meas_file} is not a rig-frame file of heartcv measure with reference_uv; no truth "
             "error")
        return
    if "vertex_positions" not in arrays or arrays["vertex_positions"].shape[0] < meas.n_frames:
        note(f"render truth: no mesh positions for the {meas.n_frames} measured frames; no truth error")
        return
    arrays = dict(arrays, vertex_positions=arrays["vertex_positions"][:meas.n_frames])
    names = list(tmeta.get("camera_names", []))
    ref = names.index(meas.meta["ref_camera"]) if meas.meta.get("ref_camera") in names else 0
    te = truth_errors(meas.positions, np.asarray(uv, float), np.asarray(birth, int), arrays, ref_camera=ref)
    if te.truth_from_rig is None:
        note("render truth: too few material points found; no truth error")
        return
    for label, r in runs.items():
        est = r["est"]
        T = est.meta.get("patch_from_rig")
        if label in truth["left_out"]:
            continue
        if T is None or est.times.size != meas.n_frames:
            note(f"{label}: no patch_from_rig in the estimate file (or another sequence); no truth error")
            continue
        truth["positions"][label] = tm.truth_in_patch_frame(te.true_positions, te.truth_from_rig, meas.point_ids,
                                                            est.point_ids, T)
    angle, shift = tm.pose_magnitude(te.truth_from_rig)
    note(f"render truth: material points by the reference camera's ray at birth; gauge of the calibrated rig "
         f"removed ({angle:.3f} deg, {shift * 1e3:.3f} mm)")


# -- metrics.json ------------------------------------------------------------------------------------
PER_ESTIMATOR_KEYS = (
    "completed_steps", "prediction_error_mean_m", "prediction_error_std_m", "prediction_error_rms_m",
    "prediction_error_count", "truth_error_mean_m", "truth_error_std_m", "truth_error_rms_m",
    "prediction_truth_error_mean_m", "prediction_truth_error_std_m", "prediction_truth_error_rms_m",
    "measurement_truth_error_mean_m", "nis_mean", "nis_mean_dof", "nis_mean_band", "nis_in_band_fraction",
    "nis_steps", "theta_final", "theta_std_final", "step_time_median_s", "step_time_p95_s", "truncation_events",
    "heldout_prediction_error_mean_m", "heldout_prediction_error_rms_m", "heldout_prediction_error_count",
    "heldout_points", "prediction_error_within_fit_mean_m", "prediction_error_within_fit_count",
    "prediction_error_after_fit_mean_m", "prediction_error_after_fit_count",
    "prediction_error_after_fit_continuing_mean_m", "prediction_error_after_fit_continuing_count",
    "heldout_prediction_error_after_fit_mean_m", "log_likelihood_per_point", "log_likelihood_points",
    "log_likelihood_within_fit_per_point", "log_likelihood_after_fit_per_point", "ratio_to_hold_interval",
    "heldout_ratio_to_hold_interval", "prediction_error_after_fit_ratio_to_hold")


def _metrics_document(runs, compared, noise, noise_norm, noise_source, truth) -> dict:
    """The metrics.json document (docs/formats.md §14) from :func:`tracker.metrics.compare_runs`."""
    from heartcv.tracker import __version__

    estimators = {}
    for label, r in runs.items():
        est, m = r["est"], compared["per_run"][label]
        d = {k: m[k] for k in PER_ESTIMATOR_KEYS + ("theta_truth_final", "theta_truth_correlation",
                                                         "theta_truth_coverage_2sigma")}
        d.update(estimator=est.estimator, file=str(r["path"]), steps=int(est.times.size), partial=not est.complete,
                 estimated=list(est.meta.get("estimated", [])), rigid_ar_order=est.meta.get("rigid_ar_order"),
                 field_degree=est.meta.get("field_degree"), rigid_harmonics=est.meta.get("rigid_harmonics"),
                 rigid_dynamics=(est.meta.get("rigid_dynamics") or {}).get("source"),
                 without_input=bool(est.meta.get("without_input", False)),
                 parameter_overdispersion=est.meta.get("parameter_overdispersion"),
                 **{f"{r}_{k}": est.meta.get(f"{r}_{k}") for r in ("heart_rate", "respiration_rate")
                    for k in ("hz", "std_hz", "source")})
        estimators[label] = d
    return {
        "format": REPORT_FORMAT[0], "format_version": REPORT_FORMAT[1], "heartcv_version": __version__,
        "producer": PRODUCER, "nis_level": LEVEL, "sequence": compared["sequence"],
        "measurement_noise_m": noise, "measurement_noise_source": noise_source,
        "measurement_noise_norm_mean_m": noise_norm,
        "measurement_truth_error_mean_m": compared["measurement_truth_error_mean_m"],
        "truth": {"kind": truth["kind"] if truth else None, "positions": bool(truth and truth["positions"]),
                  "notes": truth["notes"] if truth else []},
        "estimators": estimators,
        "ratio_ge_to_kf_prediction_error": compared["ratio_ge_to_kf_prediction_error"],
        "ratio_ge_to_kf_truth_error": compared["ratio_ge_to_kf_truth_error"],
        "difference_ge_minus_kf_log_likelihood_per_point": compared["difference_ge_minus_kf_log_likelihood_per_point"],
        "ratio_ge_to_kf_prediction_error_interval": compared["ratio_ge_to_kf_prediction_error_interval"],
        "fit_frames": compared["fit_frames"],
    }


def _jsonable(o):
    """NaN / inf -> None, tuples and arrays -> lists, numpy scalars -> Python (metrics.json is strict JSON)."""
    import math

    import numpy as np

    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple, np.ndarray)):
        return [_jsonable(v) for v in (o.tolist() if isinstance(o, np.ndarray) else o)]
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o
