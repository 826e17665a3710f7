"""The text of a ``heartcv report`` folder: ``summary.md`` and ``index.html`` from the metrics.json document.

``index.html`` stands alone: every figure is embedded as a base64 data URI and linked to its PNG beside it.
"""

from __future__ import annotations

from pathlib import Path

from heartcv.tracker.params import NAMES, UNITS
from heartcv.tracker.unknown_input import PEAK_PROMINENCE

__all__ = ["markdown", "html", "mm"]

PARAMETER_HEAD = ["estimator", "parameter", "value", "truth", "unit"]


def mm(v, digits=4):
    return "–" if v is None else f"{v * 1e3:.{digits}g} mm"


def _num(v, fmt="{:.4g}"):
    return "–" if v is None else fmt.format(v)


def _rows(doc) -> tuple[list, list]:
    """Header and rows of the per-estimator table (display units)."""
    head = ["estimator", "steps", "pred. error mean", "pred. error std", "pred. error RMS", "held-out pred. error mean",
            "truth error mean",
            "pred. truth error mean", "NIS mean / dof", "NIS in band", "log lik. / point", "step median", "step p95"]
    rows = []
    for label, e in doc["estimators"].items():
        steps = f"{e['completed_steps']}/{e['steps']}" + (" (partial)" if e["partial"] else "")
        rows.append([label, steps, mm(e["prediction_error_mean_m"]), mm(e["prediction_error_std_m"]),
                     mm(e["prediction_error_rms_m"]),
                     mm(e.get("heldout_prediction_error_mean_m")) + (f" ({e['heldout_points']} tracks)"
                                                                     if e.get("heldout_points") else ""),
                     mm(e["truth_error_mean_m"]),
                     mm(e["prediction_truth_error_mean_m"]),
                     f"{_num(e['nis_mean'])} / {_num(e['nis_mean_dof'], '{:g}')}",
                     _num(e["nis_in_band_fraction"], "{:.0%}"),
                     _num(e.get("log_likelihood_per_point"), "{:.4f}"),
                     _num(None if e["step_time_median_s"] is None else e["step_time_median_s"] * 1e3, "{:.3g} ms"),
                     _num(None if e["step_time_p95_s"] is None else e["step_time_p95_s"] * 1e3, "{:.3g} ms")])
    return head, rows


def _parameter_rows(doc) -> list:
    rows = []
    for label, e in doc["estimators"].items():
        truth = e["theta_truth_final"]
        for n in e["estimated"]:
            rows.append([label, n, f"{_num(e['theta_final'][n])} ± {_num(e['theta_std_final'][n], '{:.2g}')}",
                         _num(truth[n]) if truth else "–", UNITS[NAMES.index(n)]])
    return rows


def _facts(doc) -> list:
    s = doc["sequence"]
    left = s.get("points_left_out") or 0
    facts = [f"Sequence: {s['frames']} frames over {s['duration_s']:.4g} s, {s['points']} points"
             + (f" (the measurement file's other {left} left out by the fit's selection: off the patch or seen "
                "in fewer than two frames)" if left else "")
             + (" (mixed sequences: --allow-mixed)" if s["mixed"] else "") + "."]
    if doc.get("fit_frames") is not None and doc["fit_frames"] >= s["frames"]:
        facts.append(f"All {s['frames']} frames were fitted (heartcv fit --frames/--duration): every error and ratio "
                     "below is in sample; none tests the estimators on frames the fit did not see.")
    noise = doc["measurement_noise_m"]
    facts.append(f"Measurement noise σ per coordinate: {mm(noise)} (from {doc['measurement_noise_source']}); "
                 f"its mean 3-D norm E|v|: {mm(doc['measurement_noise_norm_mean_m'])}"
                 + (" (of the covariances themselves, anisotropy included)" if doc['measurement_noise_source']
                    == "measurements" else " (σ·√(8/π))") + "."
                 if noise is not None else "Measurement noise: unknown (give --measurements).")
    facts += _rig_facts(doc.get("rig_check"))
    facts += _track_facts(doc.get("tracks"), doc["measurement_noise_norm_mean_m"])
    for key, what in (("ratio_ge_to_kf_prediction_error", "prediction error"),
                      ("ratio_ge_to_kf_truth_error", "truth error (filtered)")):
        if doc[key] is not None:
            ci = doc.get(f"{key}_interval") if key.endswith("prediction_error") else None
            ge, kf = doc["estimators"].get("ge") or {}, doc["estimators"].get("kf") or {}
            steps = (ge.get("completed_steps"), kf.get("completed_steps"))
            uneven = (f" (over different frames: ge {steps[0]}, kf {steps[1]} completed steps; no paired interval)"
                      if None not in steps and steps[0] != steps[1] else "")
            facts.append(f"GE / KF mean {what}: {doc[key]:.3f}" + uneven + (
                f"; over the observations both predicted {_interval(ci)}" if ci else "") + ".")
    facts += _hold_ratio_facts(doc)
    if doc.get("difference_ge_minus_kf_log_likelihood_per_point") is not None:
        facts.append(f"GE − KF one-step predictive log-likelihood: "
                     f"{doc['difference_ge_minus_kf_log_likelihood_per_point']:+.3g} nats per measured point "
                     "(positive: the GE's predicted distribution fits the measurements better).")
    facts += _heart_rates(doc)
    for label, e in doc["estimators"].items():
        if e.get("without_input"):
            base = e["estimator"]
            facts.append(f"{label}: the estimated input's harmonics pinned at zero (heartcv track --without-input), "
                         f"the rigid motion unchanged: the difference to {base} is what the pressure-driven "
                         f"deformation adds" + _ablation_ratio(doc, label, base) + ".")
    tr = doc["truth"]
    facts.append(f"Truth: {tr['kind']} ({doc['inputs']['truth']})." if tr["kind"] else "Truth: none given.")
    if doc["measurement_truth_error_mean_m"] is not None:
        facts.append(f"Error of the measurements themselves against the truth: "
                     f"{mm(doc['measurement_truth_error_mean_m'])} (mean over the observations, k ≥ 1).")
    facts += [f"Note: {n}" for n in tr["notes"]]
    facts += _software_facts(doc)
    facts.append("Errors are Euclidean norms per point; overall means over frames k ≥ 1 (frame 0 is predicted "
                 "from the prior). Truth error: of the filtered estimates (after each frame's update); pred. truth "
                 "error: of the one-step predictions. Both over the points seen in each frame, the observations "
                 "of the measurements' own error against the truth.")
    return facts


def _interval(ci) -> str:
    """'1.013 (95 % interval 0.990–1.040, blocks of 12 frames)' of a :func:`tracker.metrics.paired_ratio_interval`."""
    n = ci["block_frames"]
    return (f"{ci['ratio']:.3f} ({ci['level'] * 100:.0f} % interval {ci['low']:.3f}–{ci['high']:.3f}, blocks of "
            f"{n} frame{'' if n == 1 else 's'})")


def _hold_ratio_facts(doc) -> list:
    """One line: every run's error over hold's on the observations both predicted, with its bootstrap interval
    (and the same on the held-out tracks)."""
    parts, first = [], None
    for label, e in doc["estimators"].items():
        ci, held = e.get("ratio_to_hold_interval"), e.get("heldout_ratio_to_hold_interval")
        if ci:
            first = first or ci
            parts.append(f"{label} {_interval(ci)}" + (f", held-out tracks {_interval(held)}" if held else ""))
    if not parts:
        return []
    return ["Mean prediction error over hold's on the observations both predicted (frames k ≥ 1), with bootstrap "
            f"intervals (circular blocks of consecutive frames, their length chosen per ratio, {first['resamples']} "
            "resamples; they cover the sampling of the frames, not which tracks were measured or held out): "
            + "; ".join(parts) + "."]


def _software_facts(doc) -> list:
    """One line: the software each input file was written with (its ``software`` metadata), grouped."""
    recorded = doc.get("inputs_software") or {}
    groups: dict = {}
    for role, sw in recorded.items():
        key = ", ".join(f"{k} {v}" for k, v in sw.items()) if sw else "not recorded (written before heartcv did)"
        groups.setdefault(key, []).append(role)
    if not groups:
        return []
    return ["Software the inputs were written with: " + "; ".join(f"{', '.join(roles)}: {key}"
                                                                 for key, roles in groups.items()) + "."]


def _ablation_ratio(doc, label, base) -> str:
    """'' or the ratio of a --without-input run's prediction error (overall; after the fit) to its base run's."""
    a, b = doc["estimators"][label], doc["estimators"].get(base)
    if not b or a["prediction_error_mean_m"] is None or not b["prediction_error_mean_m"]:
        return ""
    out = f" ({label} / {base} prediction error: {a['prediction_error_mean_m'] / b['prediction_error_mean_m']:.3f}"
    after_a, after_b = a.get("prediction_error_after_fit_mean_m"), b.get("prediction_error_after_fit_mean_m")
    if after_a is not None and after_b:
        out += f"; after the fitted frames {after_a / after_b:.3f}"
    return out + ")"


def _rig_facts(rc) -> list:
    """The rig against its views, as ``heartcv measure`` found it (``doc["rig_check"]``)."""
    if not rc:
        return []
    parts = []
    if rc.get("epipolar_px"):
        parts.append("SIFT features matched between the views lie a median "
                     + ", ".join(f"{'–' if v is None else f'{v:.2f}'} px ({k})" for k, v in rc["epipolar_px"].items())
                     + " from the rig's epipolar lines (a rig that describes the cameras: a fraction of a pixel of "
                       "the frames as measured)")
    if rc.get("vertical_offsets_px"):
        parts.append("a rectified pair's vertical offset measured and taken into the rig: "
                     + ", ".join(f"{k} {v:+.3f} px" for k, v in rc["vertical_offsets_px"].items()))
    return ["Rig checked against its views (heartcv measure): " + "; ".join(parts) + "."]


def _track_facts(tr, noise_norm) -> list:
    """The tracks' own motion (report ``tracks``): the bound of the frame-to-frame noise (compared with the
    covariances' noise when under 0.8 of it) and the data-driven references."""
    if not tr or tr.get("field_residual_lag1_mean_m") is None:
        return []
    bound = tr["noise_norm_bound_m"]
    r1 = mm(tr["field_residual_lag1_mean_m"])
    out = [f"The tracks' own motion: a quadratic displacement field per frame leaves {r1} of the motion over one "
           f"frame, so the noise that changes from frame to frame has a mean 3-D norm of at most {mm(bound)} (that "
           f"over √2; a track's persistent error cancels in its motion)"
           + (f", below the {mm(noise_norm)} of the measurement covariances (what they hold beyond it persists "
              "from frame to frame, or is not there)" if noise_norm is not None and bound < 0.8 * noise_norm else "")
           + (f"; over {tr['half_second_lag_frames']} frames (0.5 s) it leaves "
              f"{mm(tr['field_residual_half_second_mean_m'])}" if tr.get("field_residual_half_second_mean_m")
              is not None else "") + "."]
    ar = tr.get("field_ar")
    if ar:
        out.append(f"Data-driven reference (no physics, tracker.metrics.field_ar_prediction): an order-{ar['order']} "
                   f"autoregressive predictor of that field, refitted on the past every frame, predicts "
                   f"{ar['ratio_to_hold']:.2f}× hold's error on the same points from frame {ar['start_frame']} "
                   f"({mm(ar['error_mean_m'])} against {mm(ar['hold_error_mean_m'])}); knowing each frame's field: "
                   f"{ar['oracle_ratio_to_hold']:.2f}×.")
    ho = tr.get("heldout_oracle")
    if ho:
        out.append(f"Held-out reference (an oracle, not causal): a held-out track predicted by its position at birth "
                   f"plus the mean displacement since of its {ho['neighbours']} nearest updated tracks in the very "
                   f"frame predicted: {ho['ratio_to_hold']:.2f}× hold's error on the same observations "
                   f"({mm(ho['error_mean_m'])} against {mm(ho['hold_error_mean_m'])}, {ho['points']} tracks).")
    return out


def _rate_windows(doc) -> list:
    """One line on the tracks' own heart rate in windows (report --measurements) and each run's agreement with it."""
    tracks = doc.get("tracks") or {}
    hw = tracks.get("heart_rate_windows")
    if not hw:
        return []
    if not hw.get("windows"):       # a recording shorter than one window: the runs' rate goes unchecked; say so
        return [f"The recording ({doc['sequence']['duration_s']:.3g} s) is shorter than the {hw['window_s']:g}-s "
                "windows in which the tracks' own heart rate is measured: the runs' heart rate is not checked "
                "against it here."]
    rated = [60 * w["frequency_hz"] for w in hw["windows"] if w.get("frequency_hz") is not None]
    line = (f"The tracks' own heart rate in {hw['window_s']:g}-s windows every {hw['step_s']:g} s (heartcv fit's "
            "estimator on the measurements, no model): ")
    if rated:
        line += (f"{min(rated):.4g}–{max(rated):.4g} bpm in {len(rated)} of {len(hw['windows'])} windows"
                 + (" (the others show no clear heartbeat)" if len(rated) < len(hw["windows"]) else ""))
        faint = sum(1 for w in hw["windows"] if w.get("frequency_hz") is not None
                    and w.get("peak_prominence") is not None and w["peak_prominence"] < PEAK_PROMINENCE)
        if faint:
            line += (f"; in {faint} of them the spectral peak stands less than {PEAK_PROMINENCE:g}x above the spectrum "
                     "at half and one and a half times its frequency: it may be drift, not a heartbeat")
    else:
        line += f"no clear heartbeat in any of the {len(hw['windows'])} windows"
    groups = {}   # runs that held the same rate agree alike: one entry for them all
    for label, a in (tracks.get("heart_rate_agreement") or {}).items():
        groups.setdefault(tuple(sorted(a.items())), []).append(label)
    parts = []
    for key, labels in groups.items():
        a = dict(key)
        parts.append(f"{', '.join(labels)} within {a['z']:g}σ of it in {a['agree']} of {a['windows']} (mean "
                     f"|difference| {60 * a['mean_abs_difference_hz']:.2g} bpm, largest "
                     f"{60 * a['max_abs_difference_hz']:.2g})")
    return [line + ("; " + "; ".join(parts) if parts else "") + "."]


def _heart_rates(doc) -> list:
    """One line per distinct heart rate (and respiration rate) the runs used (an estimated input's, or the harmonic
    predictor's)."""
    lines = []
    for key, title, unit in (("heart_rate", "Heart rate", "bpm"), ("respiration_rate", "Respiration rate", "/min")):
        groups = {}
        for label, e in doc["estimators"].items():
            f = e.get(f"{key}_hz")
            if f is not None:
                groups.setdefault((f, e.get(f"{key}_std_hz"), e.get(f"{key}_source")), []).append(label)
        for (f, std, source), labels in groups.items():
            band = "" if std is None else f" ± {60 * std:.2g}"
            how = "sampled; final posterior" if source and source.startswith("sampled") else "held constant"
            lines.append(f"{title}: {60 * f:.4g}{band} {unit} ({f:.4g} Hz{'' if std is None else f' ± {std:.2g}'}; "
                         f"{source or 'source not recorded'}), {how} by {', '.join(labels)}.")
    lines += _rate_windows(doc)
    orders = {}
    for label, e in doc["estimators"].items():
        if e.get("rigid_ar_order") is not None:
            hr = e.get("rigid_harmonics")
            orders.setdefault((int(e["rigid_ar_order"]), int(e.get("field_degree") or 0),
                               None if hr is None else int(hr), e.get("rigid_dynamics") == "refit"),
                              []).append(label)
    for (p, d, hr, refit), labels in orders.items():
        what = f"an order-{p} autoregression of its increments" if p else "a random walk"
        motion = "translation" if d == 0 else f"motion (a degree-{d} displacement field along the surface)"
        beyond = ("the harmonics" if hr is None else "no harmonics of the heart rate" if hr == 0
                  else f"{hr} harmonic{'s' if hr > 1 else ''} of the heart rate")
        how = ("relearned by heartcv track from the KF's filtered motion over the fitted frames" if refit
               else "heartcv fit")
        lines.append(f"Rigid {motion} beyond {beyond}: {what} ({how}, docs/model.md 17), in {', '.join(labels)}.")
    for label, e in doc["estimators"].items():
        od = e.get("parameter_overdispersion") or {}
        if od.get("frames_adjusted"):
            lines.append(f"Parameters' update of {label} tempered by their over-dispersion {od['kappa_final']:.3g} "
                         f"(their shifts' NIS per degree of freedom; 1 where the model holds) in "
                         f"{od['frames_adjusted']} frames: its parameter bands allow for errors the points share "
                         f"(docs/estimators.md 3.11).")
    return lines


def _fit_split_rows(doc):
    """Title, introduction, header and rows of the table within / after the fitted frames; None without a
    split."""
    n = doc.get("fit_frames")
    est = doc["estimators"]
    if n is None or all(e.get("prediction_error_after_fit_mean_m") is None for e in est.values()):
        return None
    hold = est.get("hold") or {}

    def ratio(e, key):
        v, h = e.get(key), hold.get(key)
        return f"{v / h:.3f}" if v is not None and h else "–"

    def paired(e):      # on the observations both predicted (hold cannot predict a track's first sighting)
        r = e.get("prediction_error_after_fit_ratio_to_hold")
        return "–" if r is None else f"{r:.3f}"

    head = ["estimator", f"pred. error within the fit (1 ≤ k < {n})", f"pred. error after it (k ≥ {n})",
            "after it / hold's", "after it, tracks seen the frame before", "the same / hold's",
            "held-out pred. error after it", "log lik. / point within / after"]
    rows = []
    for label, e in est.items():
        rows.append([label, mm(e.get("prediction_error_within_fit_mean_m")),
                     mm(e.get("prediction_error_after_fit_mean_m")), paired(e),
                     mm(e.get("prediction_error_after_fit_continuing_mean_m")),
                     ratio(e, "prediction_error_after_fit_continuing_mean_m"),
                     mm(e.get("heldout_prediction_error_after_fit_mean_m")),
                     f"{_num(e.get('log_likelihood_within_fit_per_point'), '{:.4f}')} / "
                     f"{_num(e.get('log_likelihood_after_fit_per_point'), '{:.4f}')}"])
    intro = (f"The parameters (and an estimated input) were fitted to frames 0–{n - 1} (heartcv fit --frames or "
             f"--duration): the predictions of frames 1–{n - 1} are in-sample, those from frame {n} on "
             "out-of-sample. The ratios to hold's are over the observations both predicted (hold cannot predict a "
             "track's first sighting). Tracks seen the frame before leave out those re-appearing after a gap, which "
             "hold predicts at their last position.")
    return "Within and after the fitted frames", intro, head, rows


def markdown(doc, figures) -> str:
    head, rows = _rows(doc)
    lines = ["# heartcv report", ""] + [f"- {f}" for f in _facts(doc)] + ["", "## Estimators", ""]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + ["| " + " | ".join(r) + " |" for r in rows]
    split = _fit_split_rows(doc)
    if split:
        title, intro, shead, srows = split
        lines += ["", f"## {title}", "", intro, "", "| " + " | ".join(shead) + " |", "|" + "---|" * len(shead)]
        lines += ["| " + " | ".join(r) + " |" for r in srows]
    prow = _parameter_rows(doc)
    if prow:
        lines += ["", "## Final parameters (mean ± std)", "", "| " + " | ".join(PARAMETER_HEAD) + " |",
                  "|" + "---|" * len(PARAMETER_HEAD)] + ["| " + " | ".join(r) + " |" for r in prow]
    lines += ["", "## Figures", ""]
    for name, caption in figures:
        lines += [f"![{name}]({name})", "", f"*{name}*: {caption}", ""]
    lines += ["Inputs:", ""] + [f"- `{v}` ({k})" for k, v in doc["inputs"]["estimates"].items()]
    return "\n".join(lines) + "\n"


def html(doc, figures, folder: Path) -> str:
    """index.html: the summary with every figure embedded as a base64 data URI (the file stands alone) and
    linked to its PNG beside it."""
    import base64
    from html import escape

    def table(head, rows):
        return ("<table><tr>" + "".join(f"<th>{escape(h)}</th>" for h in head) + "</tr>"
                + "".join("<tr>" + "".join(f"<td>{escape(c)}</td>" for c in r) + "</tr>" for r in rows) + "</table>")

    prow = _parameter_rows(doc)
    ptable = ("<h2>Final parameters (mean ± std)</h2>" + table(PARAMETER_HEAD, prow)) if prow else ""
    split = _fit_split_rows(doc)
    if split:
        title, intro, shead, srows = split
        ptable = f"<h2>{escape(title)}</h2><p>{escape(intro)}</p>" + table(shead, srows) + ptable
    figs = []
    for name, caption in figures:
        data = base64.b64encode((folder / name).read_bytes()).decode("ascii")
        figs.append(f'<figure><img src="data:image/png;base64,{data}" alt="{escape(name)}">'
                    f'<figcaption><a href="{escape(name)}">{escape(name)}</a>: {escape(caption)}</figcaption>'
                    "</figure>")
    facts = "".join(f"<li>{escape(f)}</li>" for f in _facts(doc))
    style = ("body{font-family:sans-serif;max-width:1000px;margin:2em auto;color:#222}"
             "table{border-collapse:collapse;font-size:90%}td,th{border:1px solid #ccc;padding:3px 8px;"
             "text-align:right}td:first-child,th:first-child{text-align:left}figure{margin:2em 0}"
             "img{max-width:100%}figcaption{font-size:90%;color:#444}")
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>heartcv report</title>"
            f"<style>{style}</style></head><body><h1>heartcv report</h1><ul>{facts}</ul><h2>Estimators</h2>"
            f"{table(*_rows(doc))}{ptable}<h2>Figures</h2>{''.join(figs)}"
            "<p>Numbers: <a href=\"metrics.json\">metrics.json</a>, "
            "<a href=\"summary.md\">summary.md</a>.</p></body></html>\n")
