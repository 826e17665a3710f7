"""``heartcv track``: run an estimator over a measurement file (docs/cli.md §4)."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import click

from .options import (
    BadInput,
    Float,
    Int,
    StageFailed,
    announce,
    emit_json,
    guard_outputs,
    json_opt,
    load_model,
    progress,
)

log = logging.getLogger(__name__)

from heartcv.tracker.estimator_names import BASELINES  # noqa: E402
from heartcv.tracker.estimator_names import NAMES as ESTIMATORS  # noqa: E402  (the one registry of names)

ESTIMATOR_HELP = ("kf: Kalman filter with the model file's parameters held fixed; ge: Rao-Blackwellised Gaussian "
                  "estimator of state and parameters (the paper's); ukf / ekf: joint unscented / extended Kalman "
                  "filters on the augmented state (baselines); hold / constvel / harmonic: per-point predictors "
                  "without physics (last measurement, constant velocity, periodic at the heart rate). See "
                  "docs/estimators.md.")
MAX_NODES = 51  # as estimation.ge.nodes of the model file
FIT_REFERENCES = "undeformed: heartcv fit"  # meta.reference of a set whose references are the fit's offsets
ADAPT_WINDOW_S = 0.03  # as tracker.adaptive.AdaptationOptions.window_s


def partial_path(output) -> Path:
    """Where a diverged run's steps go: OUTPUT with ``.partial`` before the suffix (appended without one)."""
    p = Path(output)
    return p.with_name(p.name[: -len(p.suffix)] + ".partial" + p.suffix if p.suffix else p.name + ".partial")


_UNSET = "unset"


def _track_offsets(ctx, param, value):
    """'none' -> None, 'auto', or a positive finite standard deviation (m per frame)."""
    import math

    if value is None:   # not given: 'auto' for the model-based estimators, nothing for the baselines
        return _UNSET
    v = str(value).strip().lower()
    if v in ("none", "auto"):
        return None if v == "none" else "auto"
    try:
        q = float(v)
    except ValueError:
        raise click.BadParameter(f"'none', 'auto' or a standard deviation in metres per frame expected, got "
                                 f"{value!r}") from None
    if not (math.isfinite(q) and 0 < q < 1):
        raise click.BadParameter(f"a standard deviation in (0, 1) m per frame expected, got {value!r}")
    return q


def _overdispersion(ctx, param, value):
    """None (not given: 'auto'), 'auto', or a finite factor in [1, 1e6]."""
    import math

    if value is None:
        return None
    v = str(value).strip().lower()
    if v == "auto":
        return v
    try:
        q = float(v)
    except ValueError:
        raise click.BadParameter(f"'auto' or a factor >= 1 expected, got {value!r}") from None
    if not (math.isfinite(q) and 1.0 <= q <= 1e6):
        raise click.BadParameter(f"a factor in [1, 1e6] expected (1: the plain update), got {value!r}")
    return q


def _odd_nodes(ctx, param, value):
    if value is not None and value % 2 == 0:
        raise click.BadParameter(f"D must be an odd integer >= 3 (shared centre node), got {value}")
    return value


@click.command()
@click.argument("measurements", type=click.Path(dir_okay=False))
@click.option("--model", "model_file", type=click.Path(exists=True, dir_okay=False), required=True,
              help="Model file (YAML).")
@click.option("--estimator", type=click.Choice(ESTIMATORS), default="kf", show_default=True, help=ESTIMATOR_HELP)
@click.option("--nodes", "nodes", type=Int(3, MAX_NODES), default=None, callback=_odd_nodes,
              help="GE: Dirac nodes per parameter axis D (odd, 3..51; default from the model file, 5).")
@click.option("--truncation", type=click.Choice(("sequential", "tallis", "none")), default=None,
              help="Box truncation of the parameters after every prediction and update: for ge the default comes "
                   "from the model file (sequential); ukf and ekf do not truncate unless asked.")
@click.option("--joseph", is_flag=True, help="Joseph-form covariance update (of the Cholesky-form update; frames "
                                            "with more measurement rows than states take the block form, which "
                                            "needs none).")
@click.option("--params", "params_file", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Parameters file of heartcv fit: its theta replaces the model file's parameters (kf: held at "
                   "them; ge/ukf/ekf: the prior mean, with the fit's standard deviation unless the model file's "
                   "prior is tighter); its registration is applied to rig-frame measurements.")
@click.option("--references", type=click.Choice(("auto", "fixed", "estimate")), default="auto", show_default=True,
              help="The points' undeformed reference positions: 'estimate' carries a correction of them as static "
                   "states of the model (docs/estimators.md 3.7); 'fixed' takes them as exact; 'auto' estimates "
                   "them when they are the fit's offsets (measured points with --params) and fixes them otherwise "
                   "(model simulate's exact references).")
@click.option("--adapt/--no-adapt", default=True, show_default=True,
              help="Scale the measurement covariances to the innovations while running (docs/estimators.md 3.8): "
                   "the part of a point's error that changes from frame to frame, plus what the model cannot "
                   "represent.")
@click.option("--adapt-random-walk", is_flag=True,
              help="ge/ukf/ekf: also raise the parameters' random walk where the data move them faster than the "
                   "model file's walk allows (covariance matching; never below the model file's).")
@click.option("--adapt-window", type=Float(1e-3, 60.0), default=ADAPT_WINDOW_S, show_default=True,
              help="Memory of the adaptation in seconds.")
@click.option("--holdout", type=Float(0.0, 1.0, hi_open=True), default=0.0, show_default=True,
              help="Fraction of the tracks left out of every update (drawn with --seed): their one-step prediction "
                   "error, from the model alone, is reported apart (heldout_prediction_error_mean_m). The same "
                   "fraction and seed give every estimator the same tracks.")
@click.option("--seed", type=Int(0, 2**63 - 1), default=0, show_default=True, help="Seed of --holdout's draw.")
@click.option("--heart-rate-hz", type=Float(0.1, 10.0), default=None,
              help="harmonic: the heart rate of the periodic predictor (default: the dominant frequency of the "
                   "tracks' motion in 0.5-4 Hz).")
@click.option("--track-offsets", "track_offsets", default=None, show_default="auto", callback=_track_offsets,
              help="kf/ge/ukf/ekf: per-track offsets, a random walk beside the state that takes up what each point "
                   "does and the model cannot (a track sliding on the tissue; docs/estimators.md 3.9). 'auto': "
                   "its standard deviation per frame by maximum likelihood of the KF's innovations over the "
                   "fitted frames (--params; else the first 100), no offsets among the candidates; 'none'; or a "
                   "standard deviation per frame in metres.")
@click.option("--without-input", is_flag=True,
              help="kf/ge/ukf/ekf with an estimated input (--params of a fit without pressure): pin the input's "
                   "harmonics at zero, the rigid motion unchanged. An ablation: compared with the same run with the "
                   "input, it measures what the pressure-driven deformation adds (docs/model.md 17).")
@click.option("--sample-heart-rate/--hold-heart-rate", default=True, show_default=True,
              help="ge with an estimated input (--params of a fit without pressure): carry the heart rate (and the "
                   "respiration rate, when the fit saw one) among the sampled parameters (docs/model.md 17), or "
                   "hold them at the fit's values.")
@click.option("--heart-rate-walk", type=Float(0.0, 1.0), default=None,
              help="ge sampling the heart rate: the random walk of its log per square-root second (default 0.02, a "
                   "resting heart's beat-to-beat variability; 0: an unknown constant rate, a paced or steady heart; "
                   "docs/model.md 17).")
@click.option("--parameter-overdispersion", "overdispersion", default=None, callback=_overdispersion,
              help="ge/ukf/ekf: temper the parameters' update by the over-dispersion of their shifts, for errors "
                   "that neighbouring points share (docs/estimators.md 3.11). 'auto' (the default) estimates it from "
                   "the frames so far and leaves the update plain until it is beyond doubt; a factor >= 1 fixes it "
                   "(1: the plain update).")
@click.option("--rigid-dynamics", type=click.Choice(("refit", "fit")), default="refit", show_default=True,
              help="kf/ge/ukf/ekf with an estimated input: 'refit' learns the rigid motion's increment "
                   "autoregression again from the KF's filtered rigid motion over the fitted frames (when the "
                   "parameters were fitted to this file; docs/model.md 17); 'fit' keeps the parameters file's.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True, help="Estimate file (.npz).")
@json_opt
@click.pass_context
def track(ctx, measurements, model_file, estimator, nodes, truncation, joseph, params_file, references, adapt,
          adapt_random_walk, adapt_window, holdout, seed, heart_rate_hz, track_offsets, without_input,
          sample_heart_rate, heart_rate_walk, overdispersion, rigid_dynamics, output, as_json):
    """Estimate the surface state (and, for ge/ukf/ekf, the parameters) from MEASUREMENTS and record the
    one-step predictions of every point.

    A run whose estimate becomes non-finite stops with exit 1; the steps done are written to
    OUTPUT with `.partial` before the suffix (completed_steps < frames), never to OUTPUT itself.

    With --params (heartcv fit) the fitted parameters replace the model file's values.
    """
    import numpy as np

    from heartcv.tracker.files import InputError
    from heartcv.tracker.io import file_hash, read_measurements, read_parameters, write_estimates
    from heartcv.tracker.tracking import EstimationDiverged

    _check_scope(estimator, nodes, truncation, joseph, heart_rate_hz)
    if estimator in BASELINES and track_offsets != _UNSET:
        raise BadInput("--track-offsets applies to the model-based estimators (kf, ge, ukf, ekf) only")
    if track_offsets == _UNSET:
        track_offsets = None if estimator in BASELINES else "auto"
    if estimator in BASELINES and without_input:
        raise BadInput("--without-input applies to the model-based estimators (kf, ge, ukf, ekf) only")
    if without_input and params_file is None:
        raise BadInput("--without-input needs --params: the parameters file of a fit with an estimated input")
    if overdispersion is not None and estimator not in ("ge", "ukf", "ekf"):
        raise BadInput("--parameter-overdispersion applies to the estimators of parameters (ge, ukf, ekf) only")
    if heart_rate_walk is not None and (estimator != "ge" or not sample_heart_rate):
        raise BadInput("--heart-rate-walk applies to ge sampling the heart rate only (not with --hold-heart-rate)")
    given = _given(ctx)
    _check_given_scope(estimator, given)
    from heartcv.tracker.files import check_output_name

    check_output_name(output)
    part = partial_path(output)
    guard_outputs({"-o/--output": output, "the partial file of -o": part},
                  {"MEASUREMENTS": measurements, "--model": model_file, "--params": params_file},
                  files=[("-o/--output", output, ("heartcv.estimates",)),
                         ("the partial file of -o", part, ("heartcv.estimates",))])
    if Path(output).suffix.lower() != ".npz":
        raise BadInput(f"-o/--output: a .npz file expected, got {output}")
    meas = read_measurements(measurements)
    file_ids = np.asarray(meas.point_ids)
    m = load_model(model_file)
    if estimator not in BASELINES:     # before any work (the offsets' random walk runs KF passes)
        from heartcv.tracker.tracking import frame_interval

        try:
            dt = frame_interval(m, meas)
        except InputError as exc:
            raise exc.in_file(measurements) from None
        if dt > 1.0:
            log.warning("%s: times: a frame interval of %.3g s: a heartbeat (at least 0.5 Hz) needs frames under 1 s "
                        "apart; are the times in milliseconds? (measurement files hold seconds)", measurements, dt)
    fitted = read_parameters(params_file) if params_file is not None else None
    options = _joint_options(m, model_file, estimator, nodes, truncation, joseph)
    meta = {"producer": "heartcv track", "model": str(model_file),
            "inputs_hash": {"measurements": file_hash(measurements), "model": file_hash(model_file)}}
    theta0 = prior_std = None
    input_block = full_block = refs = None
    if fitted is not None:
        m = _fitted_patch(m, fitted, params_file)
        input_block = _input_block(m, meas, fitted, params_file, measurements)
        if input_block is not None:
            _check_rate_band(input_block, fitted, params_file)
        for name, option in (("sample_heart_rate", "--sample-heart-rate/--hold-heart-rate"),
                             ("rigid_dynamics", "--rigid-dynamics")):
            if name in given and input_block is None:
                raise BadInput(f"{option}: {params_file} holds no estimated input (estimated_input; the fit had a "
                               "recorded pressure), so there is no heart rate to sample or rigid motion to relearn")
        if heart_rate_walk is not None and input_block is None:
            raise BadInput(f"--heart-rate-walk: {params_file} holds no estimated input (estimated_input; the fit had "
                           "a recorded pressure), so the GE samples no heart rate")
        if without_input and input_block is None:
            raise BadInput(f"--without-input: {params_file} holds no estimated input (estimated_input; the fit had "
                           "a recorded pressure)")
        rig = meas.frame == "rig"
        meas = _registered(m, meas, fitted, measurements, params_file, model_file)   # the file's set let go
        meas, refs = _with_params(m, meas, fitted, measurements, input_block, rig)
        if without_input:   # after the references: the same points, offsets and held-out tracks as with the input
            full_block, input_block = input_block, input_block.without_input()
            meta["without_input"] = True
            log.info("--without-input: the estimated input's harmonics pinned at zero (an ablation)")
        meta["params"] = str(params_file)
        meta["inputs_hash"]["params"] = file_hash(params_file)
        if fitted.frames and (fitted.meta.get("inputs_hash") or {}).get("measurements") == \
                meta["inputs_hash"]["measurements"]:
            meta["fit_frames"] = int(fitted.frames)    # fitted to this very file: report splits in- / out-of-sample
        if isinstance(meas.meta.get("registration"), dict):     # rig-frame file: where the patch frame lies
            meta["patch_from_rig"] = meas.meta["registration"].get("patch_from_rig")
        if estimator in ("ge", "ukf", "ekf"):
            theta0, prior_std, meta["prior_source"] = _prior(m, fitted, params_file)
    verbosity = (ctx.find_object(dict) or {}).get("verbosity", 0)
    heldout = _heldout(m, meas, holdout, seed, measurements)
    if holdout:
        meta.update(holdout=holdout, seed=seed)
        if fitted is not None and meas.meta.get("late_points"):
            meas, heldout = _causal_heldout_references(m, refs, meas, heldout, measurements, meta)
    refs = None     # it holds the registered set: not needed by the run (a full copy of the covariances)
    left_out = np.setdiff1d(file_ids, np.asarray(meas.point_ids))
    if left_out.size:   # the fit's selection (off the patch, seen once; late held-out tracks without a reference)
        meta["left_out_points"] = [int(i) for i in left_out]
    rate = _fitted_heart_rate(fitted)
    if estimator in BASELINES:
        use_fit = estimator == "harmonic" and heart_rate_hz is None and rate
        if use_fit:
            heart_rate_hz = rate["heart_rate_hz"]   # the fit's rate (from its frames), not the whole sequence's
        est = _baseline(m, meas, estimator, heart_rate_hz, measurements, heldout)
        if use_fit:
            meta.update(rate)
        write_estimates(output, est, meta)
        _report(est, estimator, output, as_json, meta)
        return
    meta.update(rate)
    if references == "auto":
        references = "estimate" if str(meas.meta.get("reference", "")).startswith(FIT_REFERENCES) else "fixed"
    adaptation = _adaptation(adapt, adapt_random_walk, adapt_window)
    try:
        drift = _drift(track_offsets, m, meas, fitted, references, adaptation, heldout, input_block, meta)
        if input_block is not None and not without_input:
            input_block = _rigid_dynamics(rigid_dynamics, m, meas, fitted, input_block, references, adaptation,
                                          heldout, drift, meta)
        elif input_block is not None:   # the rigid motion's dynamics as the run with the input learns them
            full_drift = drift if track_offsets != "auto" else _drift(
                track_offsets, m, meas, fitted, references, adaptation, heldout, full_block, {})
            input_block = _rigid_dynamics(rigid_dynamics, m, meas, fitted, full_block, references, adaptation,
                                          heldout, full_drift, meta).without_input()
        est = _run(m, meas, estimator, joseph, fitted, theta0, prior_std, options, verbosity, references,
                   adaptation, heldout, input_block, drift, sample_heart_rate, heart_rate_walk,
                   "auto" if overdispersion is None else overdispersion)
    except InputError as exc:  # the measurement file does not fit the model (validated by the core)
        raise exc.in_file(measurements) from None
    except np.linalg.LinAlgError as exc:
        raise StageFailed(f"{estimator}: numerical failure ({exc}); no estimate file written") from None
    except EstimationDiverged as exc:
        raise StageFailed(_diverged(exc, estimator, meas, meta, part, output, measurements)) from None
    if est.meta.get("dropped_points"):
        log.warning("%d points lie off the patch and were ignored", len(est.meta["dropped_points"]))
    od = est.meta.get("parameter_overdispersion") or {}
    if od.get("frames_adjusted"):
        log.info("%s: the parameters' shifts spread %.2f x their predicted variance (NIS per degree of freedom over "
                 "%d); their update tempered by %.2f in %d of %d frames (docs/estimators.md 3.11)", estimator,
                 od["nis_per_dof"], od["dof"], od["kappa_final"], od["frames_adjusted"], est.completed_steps)
    for name in ("heart_rate", "respiration_rate"):   # the GE's sampled rates: their final posteriors
        trace = getattr(est, name)
        if trace is not None and est.completed_steps:
            f, sd = trace[est.completed_steps - 1]
            meta.update({f"{name}_hz": float(f), f"{name}_std_hz": float(sd),
                         f"{name}_source": "sampled by the GE (prior: the fit's rate, docs/model.md 17)"})
    if "track_offsets" in meta:   # the selection beside the run's own summary of the offsets
        meta["track_offsets"] = dict(est.meta.get("track_offsets") or {}, **meta["track_offsets"])
    write_estimates(output, est, meta)
    _report(est, estimator, output, as_json, meta)


def _drift(track_offsets, m, meas, fitted, references, adaptation, heldout, input_block, meta):
    """The per-track offsets' random walk per frame (None: no offsets); 'auto' selects it by maximum likelihood
    (:func:`tracker.tracking.select_track_drift`) and records the selection in ``meta``."""
    from threadpoolctl import threadpool_limits

    from heartcv.tracker.tracking import DRIFT_GRID, select_track_drift

    if track_offsets is None:
        return None
    if track_offsets != "auto":
        meta["track_offsets"] = {"std_per_frame_m": track_offsets, "source": "--track-offsets"}
        return float(track_offsets)
    frames = fitted.frames if fitted is not None and fitted.frames else 100
    log.info("track offsets: choosing their random walk by maximum likelihood (%d KF runs over the first %d frames)",
             len(DRIFT_GRID) + 2, min(frames, meas.n_frames))
    with threadpool_limits(1):
        sel = select_track_drift(m, meas, None if fitted is None else fitted.theta, frames=frames,
                                 references=references, adaptation=adaptation, heldout=heldout,
                                 input_block=input_block)
    meta["track_offsets"] = dict(sel.info(), source="maximum likelihood (--track-offsets auto)")
    log.info("track offsets: random walk %.3g mm per frame (%.2g x the measurement sigma) by maximum likelihood "
             "over %d frames%s", sel.std_per_frame_m * 1e3, sel.std_per_frame_m / sel.sigma_m, sel.frames,
             "" if sel.std_per_frame_m > 0 else ": none")
    return sel.std_per_frame_m or None


def _rigid_dynamics(mode, m, meas, fitted, input_block, references, adaptation, heldout, drift, meta):
    """The input block the run uses: with 'refit' and parameters fitted to this very file, its rigid motion's
    dynamics relearned from the KF's filtered motion over the fitted frames
    (:func:`tracker.tracking.relearn_rigid_dynamics`); else the parameters file's. Records which in ``meta``."""
    from threadpoolctl import threadpool_limits

    from heartcv.tracker.tracking import EstimationDiverged, relearn_rigid_dynamics
    from heartcv.tracker.unknown_input import MIN_RELEARN_FRAMES

    frames = meta.get("fit_frames")
    reason = ("fitted to another measurement file: nothing here to relearn them from without using the frames "
              "tracked" if not frames else f"{frames} fitted frames, fewer than {MIN_RELEARN_FRAMES}"
              if frames < MIN_RELEARN_FRAMES else None)
    if mode == "refit" and reason is None:
        try:
            with threadpool_limits(1):
                res = relearn_rigid_dynamics(m, meas, fitted.theta, input_block, frames=frames,
                                             references=references, adaptation=adaptation, heldout=heldout,
                                             drift=drift)
        except EstimationDiverged as exc:   # the run itself will say so, with its own partial file
            reason = f"the KF over the fitted frames diverged at step {exc.step}"
        else:
            meta["rigid_dynamics"] = res.info()
            log.info("rigid motion's dynamics relearned from the KF's filtered motion over the %d fitted frames: %s "
                     "(the fit's: order %d)", res.frames,
                     f"an order-{res.order} autoregression of its increments" if res.order else "a random walk",
                     res.order_before)
            return res.block
    meta["rigid_dynamics"] = {"source": "fit", "order": input_block.ar_order}
    if mode == "refit":
        meta["rigid_dynamics"]["reason"] = reason
        log.info("rigid motion's dynamics: the parameters file's (%s)", reason)
    return input_block


def _rate_prior(estimator, input_block, fitted, heart_rate_walk=None):
    """The GE with an estimated input samples the heart rate, and the respiration rate when the fit saw one: their
    priors from the fit (docs/model.md §17); ``heart_rate_walk`` (per square-root second) replaces the heart rate's
    default random walk."""
    from heartcv.tracker.unknown_input import (
        BAND_HZ,
        RATE_WALK_PER_SQRT_S,
        RESPIRATION_BAND_HZ,
        RatePrior,
        respiration_prior,
    )

    if estimator != "ge" or input_block is None:
        return None
    rate = _fitted_heart_rate(fitted)
    walk = RATE_WALK_PER_SQRT_S if heart_rate_walk is None else float(heart_rate_walk)
    band = rate.get("heart_rate_band_hz") or BAND_HZ
    rates = [RatePrior(input_block.frequency_hz, rate.get("heart_rate_std_hz") or 0.0, band=tuple(band),
                       walk_per_sqrt_s=walk)]
    if input_block.respiration_harmonics:
        resp = fitted.estimated_input.get("respiration") if fitted is not None else None
        std = resp.get("std_hz") if isinstance(resp, dict) else None
        rates.append(respiration_prior(input_block.respiration_hz,
                                       float(std) if isinstance(std, (int, float)) and math.isfinite(std) else 0.0,
                                       _rate_band(resp, None) or RESPIRATION_BAND_HZ))
    return rates


def _rate_band(entry, params_file, field=None):
    """The ``band_hz`` of a parameters file's ``heart_rate`` or ``respiration`` entry: ``(lo, hi)``, or None where it
    has none (files written before it); with ``params_file``, exit 2 naming ``field`` where it is not ``[lo, hi]``
    with 0 < lo < hi (without, a malformed band reads as none)."""
    from heartcv.tracker.files import InputError

    band = entry.get("band_hz") if isinstance(entry, dict) else None
    if band is None:
        return None
    if not (isinstance(band, (list, tuple)) and len(band) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in band)
            and 0 < band[0] < band[1]):
        if params_file is None:
            return None
        raise InputError(params_file, f"[lo, hi] in Hz with 0 < lo < hi expected, got {band!r}", field)
    return float(band[0]), float(band[1])


def _check_rate_band(input_block, fitted, params_file):
    """Exit 2 naming the parameters file where its heart-rate band (``estimated_input.heart_rate.band_hz``, heartcv
    fit --heart-rate-band; default 0.5-4 Hz) or respiration band (``estimated_input.respiration.band_hz``,
    --respiration-band; default 0.1-0.7 Hz) is malformed or does not hold its rate (the GE samples the rates inside
    their bands)."""
    from heartcv.tracker.files import InputError
    from heartcv.tracker.unknown_input import BAND_HZ, RESPIRATION_BAND_HZ

    ei = fitted.estimated_input if isinstance(fitted.estimated_input, dict) else {}
    checks = [("heart_rate", input_block.frequency_hz, BAND_HZ, "estimated_input.frequency_hz", "heart rate",
               "--heart-rate-band")]
    if input_block.respiration_harmonics:
        checks.append(("respiration", input_block.respiration_hz, RESPIRATION_BAND_HZ,
                       "estimated_input.respiration_hz", "respiration rate", "--respiration-band"))
    for key, f, default, rate_field, what, option in checks:
        field = f"estimated_input.{key}.band_hz"
        band = _rate_band(ei.get(key), params_file, field)
        if not (band or default)[0] <= f <= (band or default)[1]:
            lo, hi = band or default
            raise InputError(params_file, f"the {what} {f:.4g} Hz lies outside its band {lo:g}-{hi:g} Hz (heartcv "
                             f"fit {option})", field if band else rate_field)


def _fitted_heart_rate(fitted) -> dict:
    """``heart_rate_hz``, ``heart_rate_std_hz`` and ``heart_rate_source`` of a parameters file's estimated input
    (empty without one); recorded in the estimate file's meta for the report."""
    entry = None if fitted is None else fitted.estimated_input
    if not isinstance(entry, dict) or "frequency_hz" not in entry:
        return {}
    hr = entry.get("heart_rate") if isinstance(entry.get("heart_rate"), dict) else {}
    std = hr.get("std_hz")
    how = "given: --heart-rate-hz" if hr.get("source") == "given" else "the tracks' spectrum"
    band = _rate_band(hr, None)
    out = {"heart_rate_hz": float(entry["frequency_hz"]),
           "heart_rate_std_hz": float(std) if isinstance(std, (int, float)) else None,
           "heart_rate_source": f"parameters file (heartcv fit, {how})"}
    if band is not None:
        out["heart_rate_band_hz"] = list(band)
    resp = entry.get("respiration") if isinstance(entry.get("respiration"), dict) else {}
    if isinstance(resp.get("frequency_hz"), (int, float)):
        rstd = resp.get("std_hz")
        out.update(respiration_rate_hz=float(resp["frequency_hz"]),
                   respiration_rate_std_hz=float(rstd) if isinstance(rstd, (int, float)) else None,
                   respiration_rate_source="parameters file (heartcv fit, the rigid motion's spectrum)")
    return out


def _given(ctx) -> set:
    """The parameters named on the command line (or in the environment), not left at their defaults."""
    from click.core import ParameterSource

    return {name for name in ctx.params
            if ctx.get_parameter_source(name) in (ParameterSource.COMMANDLINE, ParameterSource.ENVIRONMENT)}


def _check_given_scope(estimator, given) -> None:
    """Exit 2 for an option given to an estimator it does not apply to (each was accepted and ignored before
    2026-11-29, some reported as used: ``adaptation.random_walk`` true for a KF)."""
    joint = ("ge", "ukf", "ekf")
    rules = (("adapt_random_walk", "--adapt-random-walk", joint, "the estimators of parameters (ge, ukf, ekf)"),
             ("sample_heart_rate", "--sample-heart-rate/--hold-heart-rate", ("ge",), "the GE"),
             ("references", "--references", ("kf",) + joint, "the model-based estimators (kf, ge, ukf, ekf)"),
             ("rigid_dynamics", "--rigid-dynamics", ("kf",) + joint, "the model-based estimators (kf, ge, ukf, ekf)"),
             ("adapt", "--adapt/--no-adapt", ("kf",) + joint, "the model-based estimators (kf, ge, ukf, ekf)"),
             ("adapt_window", "--adapt-window", ("kf",) + joint, "the model-based estimators (kf, ge, ukf, ekf)"))
    for name, option, applies, who in rules:
        if name in given and estimator not in applies:
            raise BadInput(f"{option} applies to {who} only, not to {estimator}")


def _check_scope(estimator, nodes, truncation, joseph=False, heart_rate_hz=None) -> None:
    if estimator in ("kf",) + BASELINES and truncation is not None:
        raise BadInput("--truncation applies to the joint estimators (ge, ukf, ekf) only")
    if estimator != "ge" and nodes is not None:
        raise BadInput("--nodes applies to the GE only")
    if estimator in BASELINES and joseph:
        raise BadInput(f"--joseph applies to the Kalman-type estimators, not to {estimator}")
    if estimator != "harmonic" and heart_rate_hz is not None:
        raise BadInput("--heart-rate-hz applies to the harmonic baseline only")


def _heldout(m, meas, fraction, seed, measurements):
    """The held-out points (indices into ``meas``) among those on the patch; None without --holdout."""
    import numpy as np

    from heartcv.tracker.estimators import holdout_points
    from heartcv.tracker.files import InputError
    from heartcv.tracker.tracking import locate_points

    if not fraction:
        return None
    try:
        keep = locate_points(m, meas).keep
    except InputError as exc:
        raise exc.in_file(measurements) from None
    held = holdout_points(keep, fraction, np.random.default_rng(seed), ids=meas.point_ids[keep])
    if held.size == keep.size or held.size == 0:
        raise BadInput(f"--holdout {fraction:g}: {held.size} of {keep.size} tracks; leave some in and some out")
    log.info("%d of %d tracks held out of the updates (seed %d)", held.size, keep.size, seed)
    return held


def _baseline(m, meas, estimator, heart_rate_hz, measurements, heldout=None):
    """A baseline on the points the model-based estimators use (those on the patch)."""
    from heartcv.tracker.baselines import run_baseline
    from heartcv.tracker.files import InputError
    from heartcv.tracker.tracking import locate_points

    try:
        keep = locate_points(m, meas).keep
    except InputError as exc:
        raise exc.in_file(measurements) from None
    try:
        return run_baseline(estimator, meas, keep=keep, frequency_hz=heart_rate_hz, heldout=heldout)
    except ValueError as exc:
        raise StageFailed(f"{estimator}: {exc}") from None


def _joint_options(m, model_file, estimator, nodes, truncation, joseph):
    """JointOptions of the joint estimators (None for kf); the options were validated by click."""
    from heartcv.tracker.joint import JointOptions

    if estimator == "kf" or estimator in BASELINES:
        return None
    if not m.config.estimation.estimate:
        raise BadInput(f"{model_file}: estimation.estimate is empty; {estimator} needs at least one parameter")
    if estimator == "ge":
        return JointOptions.from_config(m.config, nodes=nodes, truncation=truncation, joseph=joseph)
    return JointOptions.from_config(m.config, baseline_truncation=truncation, joseph=joseph)


def _fitted_patch(m, fitted, params_file):
    """The model on the patch the fit fitted to the observed surface (registration.geometry), else ``m``."""
    from dataclasses import replace

    from heartcv.tracker.files import InputError
    from heartcv.tracker.model import build_model
    from heartcv.tracker.patch_fit import geometry_from_dict

    geometry = (fitted.registration or {}).get("geometry")
    if geometry is None:
        return m
    try:
        g = geometry_from_dict(geometry)
    except ValueError as exc:
        raise InputError(params_file, str(exc), "registration.geometry") from None
    log.info("patch fitted to the observed surface: %.1f x %.1f mm", 1e3 * g.length, 1e3 * g.width)
    return build_model(replace(m.config, geometry=g))


def _input_block(m, meas, fitted, params_file, measurements):
    """The estimated input of the parameters file at the measurement file's frame interval, or None."""
    from heartcv.tracker.files import InputError
    from heartcv.tracker.tracking import frame_interval
    from heartcv.tracker.unknown_input import InputBlock

    entry = fitted.estimated_input
    if entry is None:
        return None
    try:
        dt = frame_interval(m, meas)
    except InputError as exc:
        raise exc.in_file(measurements) from None
    try:
        block = InputBlock.from_dict(entry, dt)
    except ValueError as exc:
        raise InputError(params_file, str(exc), "estimated_input") from None
    if block.n_u != len(m.input_names):
        raise InputError(params_file, f"fitted for {block.n_u} model inputs, the model has {len(m.input_names)}",
                         "estimated_input.n_u")
    log.info("estimated input: heart rate %.4g Hz, %d harmonics, rigid motion (%d states)", block.frequency_hz,
             block.harmonics, block.size)
    return block


def _registered(m, meas, fitted, measurements, params_file, model_file):
    """The measurement set in the patch frame: the stored registration applied to a rig-frame file (a patch-frame
    file as it is). The caller lets go of the rig-frame set: the two are not needed at once."""
    from heartcv.tracker.files import InputError
    from heartcv.tracker.io import file_hash
    from heartcv.tracker.registration import apply_stored_registration

    fitted_model = (fitted.meta.get("inputs_hash") or {}).get("model")
    if fitted_model is not None and fitted_model != file_hash(model_file):
        log.warning("%s was fitted with another model file than %s", params_file, model_file)
    if meas.frame != "rig":
        if fitted.registration is not None:
            log.warning("%s holds a registration but %s is in the patch frame: not applied", params_file,
                        measurements)
        return meas
    if fitted.registration is None:
        raise BadInput(f"{measurements}: rig-frame measurements, but {params_file} holds no registration (it was "
                       "fitted to patch-frame measurements)")
    try:
        return apply_stored_registration(meas, fitted.registration, str(params_file))
    except InputError as exc:
        raise exc.in_file(params_file) from None


def _with_params(m, meas, fitted, measurements, input_block, rig):
    """``(meas, references)``: the measurement set as the fit saw it (``meas``: :func:`_registered`'s; ``rig``:
    registered from a rig-frame file), its references replaced by the fit's undeformed offsets where it holds
    birth-frame references (a rig-frame file) or where an estimated input has no mean (the offsets took it); and the
    :class:`tracker.fit.UndeformedReferences` that gave them (None when the references were kept), which
    :func:`_causal_heldout_references` asks again rather than fitting the window's offsets a second time."""
    if not rig and input_block is None:
        return meas, None
    refs = _references(m, meas, fitted, measurements, input_block)
    meas = _applied(refs, measurements)
    if not rig:
        return meas, refs
    if meas.meta.get("late_points"):
        log.info("%d points born after the fit's %d frames: offsets from their own frames",
                 len(meas.meta["late_points"]), fitted.frames)
    if meas.meta.get("dropped_points"):
        log.info("%d points off the patch or seen in fewer than two frames were left out",
                 len(meas.meta["dropped_points"]))
    return meas, refs


def _references(m, source, fitted, measurements, input_block):
    """The fit's undeformed offsets of the patch-frame set ``source`` (:class:`tracker.fit.UndeformedReferences`)."""
    from heartcv.tracker.files import InputError
    from heartcv.tracker.fit import UndeformedReferences

    try:
        return UndeformedReferences(m, source, fitted.theta, fitted.frames, input_block=input_block)
    except InputError as exc:
        raise exc.in_file(measurements) from None


def _applied(refs, measurements, causal_ids=None):
    """``refs``'s set (``causal_ids``: late points whose references come from their first frames only,
    :func:`tracker.fit.undeformed_references`)."""
    from heartcv.tracker.files import InputError

    try:
        return refs.apply(causal_ids)
    except InputError as exc:
        raise exc.in_file(measurements) from None


def _causal_heldout_references(m, refs, meas, heldout, measurements, meta):
    """``(meas, heldout)`` with the held-out tracks born after the fitted frames given references from their first
    frames only (their later measurements never enter; every other point's reference unchanged), by ``refs``, the
    :class:`tracker.fit.UndeformedReferences` that gave ``meas`` (:func:`_with_params`). A held-out late
    track whose first frames put it off the patch (or on it, where all its frames did not) is left out of the run:
    predicting it from a reference its later measurements made would use them. Records the ids in
    ``meta['heldout_late_references']`` (``left_out``: those left out)."""
    import numpy as np

    from heartcv.tracker.fit import LATE_REFERENCE_FRAMES, causal_heldout_selection

    late = np.intersect1d(np.asarray(meas.point_ids)[heldout], np.asarray(meas.meta["late_points"], np.int64))
    if not late.size:
        return meas, heldout
    # none: the references were kept (a patch-frame file without an estimated input), as they are for these
    again = meas if refs is None else _applied(refs, measurements, causal_ids=late)
    chosen = causal_heldout_selection(m, meas, again, heldout, late)
    if chosen is None:
        log.warning("held-out tracks born after the fitted frames keep references from all their frames: from "
                    "their first %d other tracks would move on or off the patch", LATE_REFERENCE_FRAMES)
        return meas, heldout
    again, heldout, kept, moved = chosen
    if moved.size:
        log.warning("%d of the %d held-out tracks born after the fitted frames are left out of the run: their first "
                    "%d frames put them off the patch where all their frames put them on it, or the reverse",
                    moved.size, late.size, LATE_REFERENCE_FRAMES)
    meta["heldout_late_references"] = {"points": [int(i) for i in kept], "frames": LATE_REFERENCE_FRAMES}
    if moved.size:
        meta["heldout_late_references"]["left_out"] = [int(i) for i in moved]
    log.info("%d held-out tracks born after the fitted frames: references from their first %d frames only",
             kept.size, LATE_REFERENCE_FRAMES)
    return again, heldout


def _prior(m, fitted, params_file):
    from heartcv.tracker.files import InputError
    from heartcv.tracker.fit import tracking_prior

    try:
        return tracking_prior(m.config, fitted)
    except InputError as exc:
        raise exc.in_file(params_file) from None


def _adaptation(adapt, random_walk, window):
    from heartcv.tracker.adaptive import AdaptationOptions

    if not (adapt or random_walk):
        return None
    return AdaptationOptions(measurement_scale=adapt, random_walk=random_walk, window_s=window)


def _run(m, meas, estimator, joseph, fitted, theta0, prior_std, options, verbosity, references, adaptation,
         heldout=None, input_block=None, drift=None, sample_heart_rate=True, heart_rate_walk=None,
         overdispersion="auto"):
    from threadpoolctl import threadpool_limits

    from heartcv.tracker.joint import run_joint
    from heartcv.tracker.tracking import run_kalman

    # 168-sized matrices: one BLAS thread is far faster (docs/spec/estimator.md §7.5)
    with threadpool_limits(1), progress(None, estimator, meas.n_frames, verbosity) as bar:
        tick = lambda done, total: bar.update(1)  # noqa: E731
        if estimator == "kf":
            return run_kalman(m, meas, None if fitted is None else fitted.theta, joseph=joseph,
                              references=references, adaptation=adaptation, heldout=heldout,
                              input_block=input_block, drift=drift, progress=tick)
        return run_joint(m, meas, estimator, theta0=theta0, prior_std=prior_std, options=options, progress=tick,
                         references=references, adaptation=adaptation, heldout=heldout, input_block=input_block,
                         drift=drift, rate=(_rate_prior(estimator, input_block, fitted, heart_rate_walk)
                                            if sample_heart_rate else None),
                         parameter_overdispersion=overdispersion)


def _diverged(exc, estimator, meas, meta, part, output, measurements) -> str:
    """Write the steps done of a diverged run to the partial file; the failure message (naming the measurement
    file: its positions, covariances or inputs are what drove the estimate off)."""
    from heartcv.tracker.files import written_at_once
    from heartcv.tracker.io import write_estimates

    where = ""
    if exc.partial is not None and exc.partial.completed_steps > 0:
        with written_at_once():     # kept although the stage fails (exit 1)
            write_estimates(part, exc.partial, dict(meta, partial=True))
        where = f"; the {exc.partial.completed_steps} steps done were written to {part} (marked partial)"
    return (f"{estimator} diverged on {measurements} at step {exc.step} (time {meas.times[exc.step]:.4g} s): the "
            f"estimate became non-finite (do its positions, covariances and inputs fit the model?){where}; no "
            f"estimate file written to {output}")


def _report(est, estimator, output, as_json, meta=None) -> None:
    """The summary: JSON on stdout, or one INFO line (``meta``: what the stage adds to the file's meta)."""
    import math

    from heartcv.tracker.metrics import log_likelihood_statistics, nis_statistics, step_time_statistics
    from heartcv.tracker.params import NAMES

    def finite(v):
        return float(v) if math.isfinite(v) else None

    nis = nis_statistics(est.nis, est.nis_dof)
    summary = {
        "estimator": estimator,
        "steps": int(est.completed_steps),
        "nis_mean": finite(nis["mean"]),
        "nis_dof_mean": finite(nis["mean_dof"]),
        "prediction_rmse_m": finite(est.prediction_rmse()),
        "log_likelihood_per_point": log_likelihood_statistics(est)["log_likelihood_per_point"],
        "step_ms_median": step_time_statistics(est.step_time)["median"] * 1e3,
        "theta_final": dict(zip(NAMES, map(finite, est.theta[-1]), strict=True)),
        "theta_std_final": dict(zip(NAMES, map(finite, est.theta_std[-1]), strict=True)),
        "truncation_events": int(est.truncation_events.sum()),
        "estimated": list(est.meta.get("estimated", [])),
        "references": None if est.estimator in BASELINES else est.meta.get("references", "fixed"),
        "adaptation": est.meta.get("adaptation"),
        "parameter_overdispersion": est.meta.get("parameter_overdispersion"),
        "heart_rate_hz": dict(est.meta, **(meta or {})).get("heart_rate_hz"),
        "respiration_rate_hz": dict(est.meta, **(meta or {})).get("respiration_rate_hz"),
        "track_offsets_std_per_frame_m": (dict(est.meta, **(meta or {})).get("track_offsets") or {}).get(
            "std_per_frame_m"),
        "heldout_points": len(est.meta.get("heldout_points") or []),
        "output": output,
    }
    if as_json:
        emit_json(summary)
        return
    rmse = summary["prediction_rmse_m"]
    msg = f"wrote {output}: {summary['steps']} steps, prediction RMSE " + (
        f"{rmse * 1e3:.4g} mm" if rmse is not None else "n/a (no point seen after frame 0)")
    if estimator in ("ge", "ukf", "ekf"):
        msg += ", " + ", ".join(f"{n} = {summary['theta_final'][n]:.4g} ± {summary['theta_std_final'][n]:.2g}"
                                for n in summary["estimated"])
    announce(log, "%s", msg)
