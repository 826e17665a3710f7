"""``heartcv report``: compare estimator runs over one sequence in a report folder (index.html, PNG figures,
metrics.json, summary.md).

Loading, the checks that the files belong together and the folder output live here; the numbers come from
:mod:`tracker.metrics`, the figures from :mod:`cli.report_plots`, the text of summary.md and index.html from
:mod:`cli.report_doc`. Folder layout and metrics.json keys: docs/formats.md §14; the command: docs/cli.md §11.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import click

from .options import BadInput, emit_json, json_opt

log = logging.getLogger(__name__)

REPORT_FORMAT = ("heartcv.report", 1)
LEVEL = 0.95  # NIS bands


@click.command()
@click.argument("estimates", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--truth", "truth_file", type=click.Path(dir_okay=False),
              help="Ground truth: `heartcv model simulate --truth` file (parameters and point positions) or the "
                   "truth.npz of `heartcv render sequence` (parameters only).")
@click.option("--measurements", "meas_file", type=click.Path(dir_okay=False),
              help="The measurement file the estimates were made from (for the measurement noise level).")
@click.option("-o", "--output", type=click.Path(file_okay=True), required=True,
              help="Report folder (created; an existing report folder is replaced as a whole).")
@click.option("--allow-mixed", is_flag=True,
              help="Accept estimate, truth and measurement files of different sequences (warns instead of "
                   "exit 2).")
@click.option("--dpi", type=click.IntRange(72, 600), default=150, show_default=True, help="Resolution of the PNGs.")
@json_opt
def report(estimates, truth_file, meas_file, output, allow_mixed, dpi, as_json):
    """Compare the estimate files ESTIMATES (`heartcv track` outputs of one measurement file): one-step
    prediction error, parameter trajectories with ±2σ bands, NIS with its χ² band, error against the truth,
    step times. Writes the folder OUTPUT atomically."""
    from heartcv.tracker import metrics as tm
    from heartcv.tracker.io import file_hash

    from .report_doc import html, markdown, mm
    from .report_plots import write_figures

    runs = _load_estimates(estimates)
    _check_sequences(runs, allow_mixed)
    first = next(iter(runs.values()))
    noise, noise_source = _measurement_noise(meas_file, runs, allow_mixed)
    truth = _load_truth(truth_file, runs, allow_mixed, meas_file) if truth_file else None
    out = Path(output)
    _check_output(out)

    per = {label: tm.estimator_metrics(r["est"], truth["positions"].get(label) if truth else None, LEVEL)
           for label, r in runs.items()}
    for label, r in runs.items():
        pos = truth["positions"].get(label) if truth else None
        # the measurements' own error against the truth, over the observations of the truth errors (seen, k >= 1)
        per[label]["measurement_truth_error_mean_m"] = (
            tm.pooled_stats(tm.measurement_truth_error_norms(r["est"], pos)[1:])["mean"] if pos is not None
            else None)
        if pos is not None and r["est"].filtered is None:
            truth["notes"].append(f"{label}: the estimate file records no filtered positions (written before "
                                  "heartcv track recorded them); truth error of the one-step predictions only")
    metrics = _metrics_document(runs, per, first["est"], noise, noise_source, truth, allow_mixed)
    metrics["inputs"] = {"estimates": {k: str(r["path"]) for k, r in runs.items()},
                         "truth": truth_file, "measurements": meas_file}
    metrics["inputs_hash"] = {"estimates": {k: file_hash(r["path"]) for k, r in runs.items()}}
    for role, p in (("truth", truth_file), ("measurements", meas_file)):
        if p:
            metrics["inputs_hash"][role] = file_hash(p)
    from heartcv.io import atomic_folder

    with atomic_folder(out) as tmp:
        figures = write_figures(tmp, runs, per, truth, noise, dpi, LEVEL)
        metrics["figures"] = [f for f, _ in figures]
        metrics["files"] = [f for f, _ in figures] + ["metrics.json", "summary.md", "index.html"]
        doc = _jsonable(metrics)
        (tmp / "metrics.json").write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n", encoding="utf-8")
        (tmp / "summary.md").write_text(markdown(doc, figures), encoding="utf-8")
        (tmp / "index.html").write_text(html(doc, figures, tmp), encoding="utf-8")
    if as_json:
        emit_json(dict(doc, output=output))
    else:
        parts = [f"{k}: prediction error {mm(v['prediction_error_mean_m'])}"
                 + (f", truth error {mm(v['truth_error_mean_m'])}" if v["truth_error_mean_m"] is not None else "")
                 + (f" (predictions {mm(v['prediction_truth_error_mean_m'])})"
                    if v["prediction_truth_error_mean_m"] is not None else "")
                 for k, v in doc["estimators"].items()]
        if doc["measurement_truth_error_mean_m"] is not None:
            parts.append(f"measurements {mm(doc['measurement_truth_error_mean_m'])}")
        log.warning("wrote %s (%d figures); %s", output, len(figures), "; ".join(parts))


# -- inputs -----------------------------------------------------------------------------------------
def _load_estimates(paths) -> dict:
    """label -> {'path', 'est'}; labels are the estimator names, ``name:stem`` where a name repeats."""
    from heartcv.tracker.io import FileFormatError, read_estimates

    loaded = []
    for p in paths:
        try:
            est = read_estimates(p)
        except FileFormatError as exc:
            raise BadInput(str(exc)) from None
        if not est.complete:
            log.warning("%s: partial run (%d of %d steps completed); only the completed steps are used", p,
                        est.completed_steps, est.times.size)
        loaded.append((Path(p), est))
    names = [e.estimator for _, e in loaded]
    runs = {}
    for i, (p, est) in enumerate(loaded):
        label = est.estimator if names.count(est.estimator) == 1 else f"{est.estimator}:{p.stem}"
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
    import numpy as np

    ta, tb = np.asarray(times_a, float), np.asarray(times_b, float)
    same = ta.shape == tb.shape and np.allclose(ta, tb, rtol=0, atol=1e-9 * max(abs(ta[-1]), 1.0))
    if not same:
        msg = f"{label_a} and {label_b}: different frame times ({ta.size} vs {tb.size} frames)"
        if not allow_mixed:
            raise BadInput(f"{msg}; {what} of another sequence? use --allow-mixed to go on without it")
        log.warning("%s; %s left out", msg, what)
    return not same


def _measurement_noise(meas_file, runs: dict, allow_mixed: bool):
    """(σ in m, source) from --measurements, else from an estimate file's meta ``measurement_noise_m``."""
    import numpy as np

    from heartcv.tracker.io import FileFormatError, file_hash, read_measurements
    from heartcv.tracker.metrics import measurement_noise_level

    if meas_file:
        try:
            m = read_measurements(meas_file)
        except FileFormatError as exc:
            raise BadInput(str(exc)) from None
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
        return (sigma, "measurements") if np.isfinite(sigma) else (None, None)
    for r in runs.values():
        v = r["est"].meta.get("measurement_noise_m")
        if isinstance(v, (int, float)) and np.isfinite(v) and v > 0:
            return float(v), f"estimate meta ({r['path']})"
    return None, None


def _load_truth(path, runs: dict, allow_mixed: bool, meas_file=None) -> dict:
    """{'kind', 'times', 'theta', 'positions': label -> (K, P, 3) where usable, 'notes'} of a truth file."""
    import numpy as np

    from heartcv.tracker.io import TRUTH_FORMAT, FileFormatError, read_truth

    fmt = _npz_format(path)
    truth = {"kind": None, "path": path, "positions": {}, "notes": []}
    if fmt == TRUTH_FORMAT[0]:
        try:
            data, _ = read_truth(path)
        except FileFormatError as exc:
            raise BadInput(str(exc)) from None
        truth.update(kind="simulation", times=data["times"], theta=data["theta"])
        for label, r in runs.items():
            est = r["est"]
            if _mismatch(est.times, data["times"], r["path"], path, allow_mixed, "the truth"):
                continue
            P = est.point_ids.size
            if data["positions"].shape[1] != P or not np.array_equal(est.point_ids, np.arange(P)):
                truth["notes"].append(f"{label}: the truth's {data['positions'].shape[1]} points are not the "
                                      f"estimate's point ids; no truth error")
                continue
            truth["positions"][label] = data["positions"]
        return truth
    if fmt == "heartcv.render_truth":
        data, meta = _read_npz_keys(path, ("times", "theta"))
        if meta.get("format_version") != 1:
            raise BadInput(f"{path}: heartcv.render_truth version 1 supported, got {meta.get('format_version')!r}")
        if meta.get("kind") != "sequence" or "theta" not in data or "times" not in data:
            raise BadInput(f"{path}: a render truth of kind 'sequence' expected, got {meta.get('kind')!r}")
        truth.update(kind="render", times=data["times"], theta=data["theta"])
        for r in runs.values():
            _mismatch(r["est"].times, data["times"], r["path"], path, allow_mixed, "the truth")
        _render_truth_positions(truth, path, runs, meas_file)
        return truth
    raise BadInput(f"{path}: a truth file (format 'heartcv.truth' or 'heartcv.render_truth') expected, got {fmt!r}")


def _render_truth_positions(truth, path, runs, meas_file):
    """Patch-frame true trajectories of the estimates' points from a render truth: each point's material point
    is the one its reference-camera pixel saw in its birth frame (the measurement file's ``reference_uv`` and
    ``reference_frame_index``; heartcv/evaluate.py: true camera ray and mesh, barycentric motion), mapped from the
    truth's world frame into the rig frame by the gauge fitted to the birth positions and into the patch frame
    by the estimate's ``patch_from_rig``. Notes say why a run gets no truth positions."""
    import numpy as np

    def note(msg):
        truth["notes"].append(msg)

    if not meas_file:
        note("render truth: --measurements (the rig-frame file of heartcv measure) is needed for the truth error")
        return
    from heartcv.evaluate import truth_errors
    from heartcv.io import HeartcvIOError, read_render_truth
    from heartcv.tracker.io import FileFormatError, read_measurements

    try:
        meas = read_measurements(meas_file)
        arrays, tmeta = read_render_truth(path)
    except (FileFormatError, HeartcvIOError) as exc:
        raise BadInput(str(exc)) from None
    uv = meas.meta.get("reference_uv")
    birth = meas.meta.get("reference_frame_index")
    if meas.frame != "rig" or uv is None or birth is None:
        note(f"render truth: {meas_file} is not a rig-frame file of heartcv measure with reference_uv; no truth "
             "error")
        return
    K = arrays["vertex_positions"].shape[0]
    if K < meas.n_frames:
        note(f"render truth: {K} frames for {meas.n_frames} measured; no truth error")
        return
    arrays = dict(arrays, vertex_positions=arrays["vertex_positions"][:meas.n_frames])
    names = list(tmeta.get("camera_names", []))
    ref = names.index(meas.meta["ref_camera"]) if meas.meta.get("ref_camera") in names else 0
    te = truth_errors(meas.positions, np.asarray(uv, float), np.asarray(birth, int), arrays, ref_camera=ref)
    if te.truth_from_rig is None:
        note("render truth: too few material points found; no truth error")
        return
    rig_from_truth = np.linalg.inv(te.truth_from_rig)
    true_rig = te.true_positions @ rig_from_truth[:3, :3].T + rig_from_truth[:3, 3]       # (K, P_meas, 3)
    col = {int(i): j for j, i in enumerate(meas.point_ids)}
    for label, r in runs.items():
        est = r["est"]
        T = est.meta.get("patch_from_rig")
        if T is None or est.times.size != meas.n_frames:
            note(f"{label}: no patch_from_rig in the estimate file (or another sequence); no truth error")
            continue
        T = np.asarray(T, float)
        idx = [col.get(int(i), -1) for i in est.point_ids]
        pos = np.full((est.times.size, est.point_ids.size, 3), np.nan)
        have = np.array([i >= 0 for i in idx])
        if have.any():
            pos[:, have] = true_rig[:, [i for i in idx if i >= 0]] @ T[:3, :3].T + T[:3, 3]
        truth["positions"][label] = pos
    R = te.truth_from_rig[:3, :3]
    note(f"render truth: material points by the reference camera's ray at birth; gauge of the calibrated rig "
         f"removed ({np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))):.3f} deg, "
         f"{np.linalg.norm(te.truth_from_rig[:3, 3]) * 1e3:.3f} mm)")


def _npz_format(path):
    data, meta = _read_npz_keys(path, ())
    return meta.get("format")


def _read_npz_keys(path, keys) -> tuple[dict, dict]:
    """Only ``keys`` (if present) and the metadata of an ``.npz`` (docs/formats.md §1.7), exit 2 if unreadable."""
    import zipfile

    import numpy as np

    try:
        with np.load(path, allow_pickle=False) as z:
            if "meta_json" not in z.files:
                raise BadInput(f"{path}: no meta_json entry: not a heartcv file")
            meta = json.loads(bytes(z["meta_json"]).decode())
            return {k: z[k] for k in keys if k in z.files}, meta
    except (OSError, zipfile.BadZipFile, ValueError, EOFError) as exc:
        raise BadInput(f"{path}: not a readable .npz file ({exc})") from None


def _check_output(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise BadInput(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / "metrics.json").is_file():
        raise BadInput(f"{out}: a non-empty folder that is not a report (no metrics.json); not replaced")


# -- metrics.json ------------------------------------------------------------------------------------
PER_ESTIMATOR_KEYS = (
    "completed_steps", "prediction_error_mean_m", "prediction_error_std_m", "prediction_error_rms_m",
    "prediction_error_count", "truth_error_mean_m", "truth_error_std_m", "truth_error_rms_m",
    "prediction_truth_error_mean_m", "prediction_truth_error_std_m", "prediction_truth_error_rms_m",
    "measurement_truth_error_mean_m", "nis_mean", "nis_mean_dof", "nis_mean_band", "nis_in_band_fraction",
    "nis_steps", "theta_final", "theta_std_final", "step_time_median_s", "step_time_p95_s", "truncation_events")


def _metrics_document(runs, per, first, noise, noise_source, truth, allow_mixed) -> dict:
    import numpy as np

    from heartcv.tracker import __version__
    from heartcv.tracker.metrics import mean_noise_norm
    from heartcv.tracker.params import NAMES

    t = np.asarray(first.times, float)
    estimators = {}
    for label, r in runs.items():
        est, m = r["est"], per[label]
        d = {k: m[k] for k in PER_ESTIMATOR_KEYS}
        d.update(estimator=est.estimator, file=str(r["path"]), steps=int(est.times.size), partial=not est.complete,
                 estimated=list(est.meta.get("estimated", [])))
        if truth is None or label not in truth["positions"]:
            d.update(dict.fromkeys(k for k in PER_ESTIMATOR_KEYS if "truth_error" in k))
        c = est.completed_steps
        d["theta_truth_final"] = (dict(zip(NAMES, map(float, truth["theta"][c - 1])))
                                  if truth is not None and 0 < c <= len(truth["theta"]) else None)
        estimators[label] = d

    def ratio(key):
        a, b = (estimators.get(k, {}).get(key) for k in ("ge", "kf"))
        return a / b if a is not None and b is not None and np.isfinite(a) and np.isfinite(b) and b > 0 else None

    with_truth = [v for d in estimators.values()
                  if (v := d["measurement_truth_error_mean_m"]) is not None and np.isfinite(v)]
    return {
        "format": REPORT_FORMAT[0], "format_version": REPORT_FORMAT[1], "heartcv_version": __version__,
        "producer": "heartcv report", "nis_level": LEVEL,
        "sequence": {"frames": int(t.size), "duration_s": float(t[-1] - t[0]), "points": int(first.point_ids.size),
                     "dt_s": float(np.median(np.diff(t))) if t.size > 1 else None, "mixed": allow_mixed and
                     any(first is not r["est"] and _differs(first, r["est"]) for r in runs.values())},
        "measurement_noise_m": noise, "measurement_noise_source": noise_source,
        "measurement_noise_norm_mean_m": mean_noise_norm(noise) if noise is not None else None,
        "measurement_truth_error_mean_m": with_truth[0] if with_truth else None,
        "truth": {"kind": truth["kind"] if truth else None, "positions": bool(truth and truth["positions"]),
                  "notes": truth["notes"] if truth else []},
        "estimators": estimators,
        "ratio_ge_to_kf_prediction_error": ratio("prediction_error_mean_m"),
        "ratio_ge_to_kf_truth_error": ratio("truth_error_mean_m"),
    }


def _differs(a, b) -> bool:
    from heartcv.tracker.metrics import sequence_mismatch

    return sequence_mismatch(a, b) is not None


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
