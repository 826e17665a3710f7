"""``heartcv fit``: weighted least-squares fit of the model's parameters to a measurement file (paper §IV;
docs/cli.md §12)."""

from __future__ import annotations

from dataclasses import replace
import logging
import math
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

MAX_STARTS = 1000


@click.command()
@click.argument("measurements", type=click.Path(dir_okay=False))
@click.option("--model", "model_file", type=click.Path(exists=True, dir_okay=False), required=True,
              help="Model file (YAML): estimation.estimate names the fitted parameters, estimation.bounds their box, "
                   "parameters the first start and the fixed values.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True,
              help="Parameters file to write (.yaml).")
@click.option("--frames", type=Int(2, MAX_COUNT), default=None,
              help="Fit the first N frames only (default: all), e.g. two cardiac cycles.")
@click.option("--duration", type=Float(0, 1e6, lo_open=True), default=None, metavar="SECONDS",
              help="Fit the frames of the first SECONDS only (times from the measurement file; default: all). "
                   "Not with --frames.")
@click.option("--starts", type=Int(1, MAX_STARTS), default=3, show_default=True,
              help="Starts: the model file's parameters plus STARTS-1 draws from its prior; the best converged wins.")
@seed_opt
@click.option("--max-evaluations", type=Int(1, MAX_COUNT), default=None,
              help="Residual evaluations per start (least_squares max_nfev; default 100 per parameter).")
@click.option("--input", "input_mode", type=click.Choice(("auto", "recorded", "estimate")), default="auto",
              show_default=True,
              help="The model's pressure: 'recorded' from the measurement file; 'estimate' from the tracks (heart "
                   "rate from their spectrum, the input's harmonics and a rigid motion fitted); 'auto': estimate "
                   "when the file has no pressure column.")
@click.option("--heart-rate-hz", type=Float(0, 1e6, lo_open=True), default=None, metavar="HZ",
              help="An estimated input's heart rate, known otherwise (an ECG, the monitor), in Hz (within "
                   "--heart-rate-band, 0.5-4 by default): used as given instead of the tracks' spectrum, and "
                   "without its tests of a heartbeat (default: from the tracks' spectrum).")
@click.option("--heart-rate-band", default=None, metavar="LO,HI",
              help="The heart rates an estimated input may take, in Hz (default 0.5,4: 30-240 bpm, a human or pig "
                   "heart; a rat's or mouse's beats 4-10 Hz): where the tracks' spectrum is searched, where "
                   "--heart-rate-hz may lie, and the box of the GE's sampled rate.")
@click.option("--harmonics", type=Int(1, 10), default=None,
              help="Harmonics of the heart rate in an estimated input (default 6).")
@click.option("--respiration", type=click.Choice(("auto", "none")), default="auto", show_default=True,
              help="An estimated input's rigid motion: 'auto' adds harmonics of a respiration rate when the fit's "
                   "translation shows one (at least 2 breaths in the fitted frames, explaining half its variance); "
                   "'none' leaves respiration to the random-walk translation.")
@click.option("--respiration-band", default=None, metavar="LO,HI",
              help="The respiration rates searched, in Hz (default 0.1,0.7: 6-42 breaths a minute; a rat breathes "
                   "1-2.5 Hz), capped at half the heart rate; also the box of the GE's sampled respiration rate.")
@click.option("--rigid-ar", type=click.Choice(("auto", "none", "1", "2", "3", "4")), default="auto",
              show_default=True,
              help="An estimated input's rigid translation beyond the heartbeat's and respiration's harmonics: its "
                   "increments a vector autoregression of this order fitted over the fitted frames; 'auto' the "
                   "order 0-4 with the least BIC (0: a random walk); 'none' a random walk (docs/model.md 17).")
@click.option("--rigid-harmonics", type=Int(0, 10), default=None,
              help="Harmonics of the heart rate in an estimated input's rigid motion (default: --harmonics); 0 "
                   "leaves the rigid motion to its autoregression alone. Fixed-rate harmonics predict the fitted "
                   "frames well but drift out of phase when the heart rate changes after them (docs/model.md 17).")
@click.option("--field-degree", type=click.Choice(("0", "1", "2")), default=None,
              help="An estimated input's rigid motion as a smooth displacement field of this degree along the "
                   "observed surface [default: 1, an affine field: translation, in-plane rotation, stretch and "
                   "shear, and tilt]; 0: a translation. With a field its increments are a vector autoregression, "
                   "its order and ridge chosen by predicting the last 30 % of the fitted frames "
                   "(docs/model.md 17).")
@click.option("--patch", "patch_mode", type=click.Choice(("auto", "model", "observed")), default="auto",
              show_default=True,
              help="Rig-frame files: 'model' places the model file's patch by its surface and motion; 'observed' "
                   "fits the patch's extent, pose and curvature to the observed surface; 'auto': with a recorded "
                   "input 'model'; with an estimated one 'observed' when the observed surface fits inside the model "
                   "file's patch (an endoscope's view), else 'model' with the dominant deformation of the first "
                   "frames standing in for the input's motion (and 'observed' if that placement fails).")
@json_opt
def fit(measurements, model_file, output, frames, duration, starts, seed, max_evaluations, input_mode, heart_rate_hz,
        heart_rate_band, harmonics, respiration, respiration_band, rigid_ar, rigid_harmonics, field_degree, patch_mode,
        as_json):
    """Fit the parameters of MODEL's estimation.estimate to MEASUREMENTS by bounded weighted least squares.

    The patch is simulated from equilibrium at the first frame's input with the measured inputs; residuals are
    the measured displacements minus the model's, whitened by each observation's covariance. Rig-frame files
    (heartcv measure) are registered onto the patch first. A fit that does not converge exits 1 and writes
    nothing.
    """
    import numpy as np
    from threadpoolctl import threadpool_limits

    from heartcv.tracker.files import InputError
    from heartcv.tracker.fit import fit as run_fit
    from heartcv.tracker.io import file_hash, read_measurements, write_parameters
    from heartcv.tracker.measurements import frames_within
    from heartcv.tracker.unknown_input import BAND_HZ, HARMONICS

    if Path(output).suffix.lower() not in (".yaml", ".yml"):
        raise BadInput(f"-o/--output: a .yaml file expected, got {output}")
    if frames is not None and duration is not None:
        raise BadInput("--frames and --duration: give one of them")
    guard_outputs({"-o/--output": output}, {"MEASUREMENTS": measurements, "--model": model_file},
                  files=[("-o/--output", output, ("heartcv.parameters",))])
    meas = read_measurements(measurements)
    if duration is not None:
        frames = frames_within(meas.times, duration)
        if frames < 2:
            raise BadInput(f"--duration {duration:g}: the first {duration:g} s of {measurements} hold {frames} "
                           "frame(s); at least 2 are needed")
        log.info("--duration %g s: the first %d frames", duration, frames)
        if frames >= meas.n_frames:
            log.warning("--duration %g s: %s holds only %d frames (%.3g s): every frame is fitted, none is left "
                        "after the fit to test the estimators out of sample (give a shorter --duration or "
                        "--frames, e.g. half the recording)", duration, measurements, meas.n_frames,
                        float(meas.times[-1] - meas.times[0]) if meas.n_frames > 1 else 0.0)
    m = load_model(model_file)
    if not m.config.estimation.estimate:
        raise BadInput(f"{model_file}: estimation.estimate is empty; nothing to fit")
    estimate_input = _input_mode(input_mode, meas, m, measurements)
    if heart_rate_hz is not None and not estimate_input:
        raise BadInput("--heart-rate-hz applies to an estimated input (--input estimate) only")
    band = BAND_HZ if heart_rate_band is None else _band(heart_rate_band, "--heart-rate-band", 0.1, 20.0)
    resp_band = None if respiration_band is None else _band(respiration_band, "--respiration-band", 0.01, 10.0)
    if respiration == "none" and not estimate_input:
        raise BadInput("--respiration none applies to an estimated input (--input estimate) only: with a recorded "
                       "pressure the fit has no respiration oscillators to leave out")
    if respiration_band is not None and (not estimate_input or respiration == "none"):
        raise BadInput("--respiration-band applies to an estimated input (--input estimate) with --respiration auto")
    if heart_rate_band is not None and not estimate_input:
        raise BadInput("--heart-rate-band applies to an estimated input (--input estimate) only")
    if heart_rate_hz is not None and not band[0] <= heart_rate_hz <= band[1]:
        raise BadInput(f"--heart-rate-hz {heart_rate_hz:g}: {band[0]:g}-{band[1]:g} Hz expected "
                       f"({60 * band[0]:g}-{60 * band[1]:g} bpm; --heart-rate-band for another)")
    if harmonics is not None and not estimate_input:
        raise BadInput("--harmonics applies to an estimated input (--input estimate) only")
    if rigid_ar != "auto" and not estimate_input:
        raise BadInput("--rigid-ar applies to an estimated input (--input estimate) only")
    if field_degree is not None and not estimate_input:
        raise BadInput("--field-degree applies to an estimated input (--input estimate) only")
    if rigid_harmonics is not None and not estimate_input:
        raise BadInput("--rigid-harmonics applies to an estimated input (--input estimate) only")
    if rigid_harmonics is not None and rigid_harmonics > (HARMONICS if harmonics is None else harmonics):
        raise BadInput(f"--rigid-harmonics {rigid_harmonics}: at most --harmonics "
                       f"({HARMONICS if harmonics is None else harmonics}) expected")
    if patch_mode == "observed" and meas.frame != "rig":
        raise BadInput(f"--patch observed: {measurements} is already in the patch frame (registered)")
    registration = estimated_input = None
    try:
        with threadpool_limits(1):
            if meas.frame == "rig":
                m, meas, registration = _place_patch(meas, m, output, patch_mode, estimate_input)
            if estimate_input:
                result, estimated_input = _fit_unknown_input(m, meas, seed, frames, starts, max_evaluations,
                                                              harmonics, respiration == "auto",
                                                              None if rigid_ar == "auto" else
                                                              0 if rigid_ar == "none" else int(rigid_ar),
                                                              None if field_degree is None
                                                              else int(field_degree), rigid_harmonics,
                                                              heart_rate_hz, band, resp_band)
            else:
                result = run_fit(m, meas, np.random.default_rng(seed), frames=frames, starts=starts,
                                 max_evaluations=max_evaluations)
    except InputError as exc:  # the measurement file does not fit the model (validated by the core)
        raise exc.in_file(measurements) from None
    if not result.converged:
        raise StageFailed(f"fit did not converge: {result.message}; nothing written to {output}")
    meta = {"producer": "heartcv fit", "measurements": str(measurements), "model": str(model_file),
            "inputs_hash": {"measurements": file_hash(measurements), "model": file_hash(model_file)},
            "seed": seed}
    result = replace(result, registration=registration, estimated_input=estimated_input)
    write_parameters(output, result, meta)
    summary = _summary(result, output)
    if as_json:
        emit_json(summary)
    else:
        announce(log, "wrote %s: %s (reduced chi-square %.3g, %d frames, %d points)", output,
                 ", ".join(f"{n} = {summary['theta'][n]:.4g} ± {summary['theta_std'][n]:.2g}"
                           for n in result.estimated),
                 result.reduced_chi2, result.frames, result.points)
    if summary["poorly_determined"]:
        log.warning("poorly determined (std > 1 in phi, a factor e): %s; consider fixing them (estimation.estimate)",
                    ", ".join(summary["poorly_determined"]))
    if result.at_bound:
        log.warning("at a bound of estimation.bounds: %s (their std ignores the bound)", ", ".join(result.at_bound))


def _place_patch(rig_meas, m, output, patch_mode, estimate_input):
    """Bring a rig-frame set onto a patch (``--patch``): ``(model, patch-frame set, registration entry)``."""
    import numpy as np

    from heartcv.tracker.patch_fit import check_view_scale, view_within_patch
    from heartcv.tracker.registration import deformation_signal

    check_view_scale(rig_meas)     # positions in millimetres: exit 2, before any placement
    if patch_mode == "observed" or (patch_mode == "auto" and estimate_input
                                    and view_within_patch(rig_meas, m.config.geometry)):
        return _observed_patch(rig_meas, m, output)
    proxy = None
    if estimate_input:  # the model's pressure column driven by the dominant deformation, any other input held
        proxy = np.zeros((rig_meas.n_frames, len(m.input_names)))
        proxy[:, m.input_names.index("pressure")] = deformation_signal(rig_meas)[:, 0]
    from heartcv.tracker.registration import register_rig_measurements, registration_to_dict

    meas, reg = register_rig_measurements(rig_meas, m, inputs=proxy)
    if meas is None:
        why = f"registration onto the patch did not converge ({reg.message})"
        if patch_mode == "auto" and estimate_input:
            log.warning("%s; fitting the patch to the observed surface instead", why)
            return _observed_patch(rig_meas, m, output)
        raise StageFailed(f"{why}; nothing written to {output}; if the cameras see a part of the heart (an "
                          "endoscope's view of a few centimetres), --patch observed fits the patch to the surface "
                          "they see")
    log.info("patch placed: %s", reg.message)
    return m, meas, registration_to_dict(reg, rig_meas)


def _input_mode(mode, meas, m, measurements) -> bool:
    """Whether the input is estimated (``--input``); BadInput for a model without a pressure to estimate or a
    recorded input that is missing."""
    has = "pressure" in m.input_names and "pressure" in meas.input_names
    if mode == "recorded" and not has and "pressure" in m.input_names:
        from heartcv.tracker.files import InputError

        raise InputError(measurements, "--input recorded: the measurement file has no pressure column (its inputs: "
                                       f"{', '.join(meas.input_names) or 'none'}); --input estimate (or auto) "
                                       "estimates it from the tracks", "inputs")
    if mode == "recorded" or (mode == "auto" and (has or "pressure" not in m.input_names)):
        return False
    if "pressure" not in m.input_names:
        raise BadInput("--input estimate: the model file has no pressure input to estimate (inputs.pressure)")
    if mode == "auto":
        log.info("%s has no pressure column: the input is estimated (heart rate, harmonics, rigid motion)",
                 measurements)
    return True


def _observed_patch(rig_meas, m, output):
    """The patch fitted to the observed surface: ``(model on that patch, patch-frame set, registration entry)``."""
    from dataclasses import replace as dc_replace

    from heartcv.tracker.model import build_model
    from heartcv.tracker.patch_fit import fit_observed_patch, geometry_to_dict
    from heartcv.tracker.registration import registration_to_dict, to_patch_frame

    op = fit_observed_patch(rig_meas, m.config.geometry)
    if not op.registration.converged:
        raise StageFailed(f"fitting a patch to the observed surface failed ({op.registration.message}); nothing "
                          f"written to {output}")
    info = op.info()
    log.info("patch fitted to the observed surface: %.1f x %.1f mm, radii %.0f and %.0f mm, %d points on it, %d "
             "dropped, surface RMS %.2f mm", 1e3 * info["length_m"], 1e3 * info["width_m"],
             1e3 * info["radius_long_m"], 1e3 * info["radius_circ_m"], info["points_on_patch"],
             info["points_dropped"], 1e3 * info["rms_m"])
    model = build_model(dc_replace(m.config, geometry=op.geometry))
    reg = registration_to_dict(op.registration, rig_meas)
    reg["geometry"] = geometry_to_dict(op.geometry)
    reg["patch"] = info
    return model, to_patch_frame(rig_meas, op.registration), reg


def _band(text, option, lowest, highest):
    """``option LO,HI`` -> (lo, hi) Hz, ``lowest`` <= lo < hi <= ``highest``; exit 2 otherwise."""
    try:
        lo, hi = (float(v) for v in str(text).split(","))
    except ValueError:
        raise BadInput(f"{option}: LO,HI in Hz expected (e.g. 0.5,4), got {text!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lowest <= lo < hi <= highest):
        raise BadInput(f"{option} {text}: {lowest:g} <= LO < HI <= {highest:g} Hz expected")
    return lo, hi


def _fit_unknown_input(m, meas, seed, frames, starts, max_evaluations, harmonics, respiration=True,
                       rigid_ar_order=None, field_degree=None, rigid_harmonics=None, heart_rate_hz=None,
                       band=None, respiration_band=None):
    """The fit with an estimated input (heart rate from the tracks, or ``heart_rate_hz`` as given; harmonics and
    rigid motion profiled; the respiration rate from the rigid motion when ``respiration`` and one is seen):
    ``(FitResult, estimated_input entry)``; StageFailed (exit 1) for a recording without a heartbeat."""
    from dataclasses import replace as dc_replace

    import numpy as np

    from heartcv.tracker.files import InputError
    from heartcv.tracker.fit import UnknownInputProblem
    from heartcv.tracker.fit import fit as run_fit
    from heartcv.tracker.model import build_model
    from heartcv.tracker.unknown_input import (
        BAND_HZ,
        FIELD_DEGREE,
        HARMONICS,
        PEAK_PROMINENCE,
        RESPIRATION_BAND_HZ,
        NoHeartbeat,
        NotProminent,
        Respiration,
        estimate_heart_rate,
        estimate_respiration,
        harmonics_below_nyquist,
        heart_rate_at,
        input_block_from_fit,
    )

    band = BAND_HZ if band is None else tuple(band)
    H = HARMONICS if harmonics is None else harmonics
    field_degree = FIELD_DEGREE if field_degree is None else int(field_degree)
    K = meas.n_frames if frames is None else min(frames, meas.n_frames)
    if K < 2:       # the file's problem, as the fit with a recorded pressure says it (exit 2)
        raise InputError(None, f"a fit needs at least 2 frames, the file has {meas.n_frames}", "times")
    if not (np.isfinite(meas.positions[:K]).all(axis=2).sum(axis=0) >= 2).any():
        raise InputError(None, f"no point is seen in two of the first {K} frames", "positions")
    try:
        if heart_rate_hz is None:
            hr = estimate_heart_rate(meas.times[:K], meas.positions[:K], H, band, prominent=True)
        else:
            hr = heart_rate_at(meas.times[:K], meas.positions[:K], heart_rate_hz, band)
    except NotProminent as exc:
        raise StageFailed(f"no heart rate in the first {K} frames: {exc}; nothing written (if the recording does "
                          "show a heartbeat, give its rate with --heart-rate-hz)") from None
    except NoHeartbeat as exc:
        raise StageFailed(f"no heart rate in the first {K} frames: {exc}; nothing written") from None
    if hr.left_out:
        ids = ", ".join(str(meas.point_ids[p]) for p in hr.left_out)
        log.warning("the tracks show a heartbeat, or another heart rate, only without track%s %s, which carr%s the "
                    "largest share of their motion (a stereo match that slipped for a while?): the heart rate is the "
                    "other tracks' (%s still fitted)", "s" if len(hr.left_out) > 1 else "", ids,
                    "y" if len(hr.left_out) > 1 else "ies", "they are" if len(hr.left_out) > 1 else "the track is")
    if heart_rate_hz is None:
        log.info("heart rate %.4g ± %.2g Hz (%.1f bpm) from the tracks' spectrum: %.1f beats, peak %.0fx the band's "
                 "median, %.0fx the power between its harmonics and %.2gx its surroundings", hr.frequency_hz,
                 hr.std_hz, 60 * hr.frequency_hz, hr.beats, hr.peak_ratio, hr.background_ratio, hr.prominence)
    else:
        log.info("heart rate %.4g Hz (%.1f bpm) as given (--heart-rate-hz): %.1f beats; the tracks' spectrum there "
                 "%.2gx the band's median, %.2gx the power between its harmonics and %.2gx its surroundings",
                 hr.frequency_hz, 60 * hr.frequency_hz, hr.beats, hr.peak_ratio, hr.background_ratio, hr.prominence)
    dt = float(np.median(np.diff(meas.times[:K])))
    resolved = harmonics_below_nyquist(hr.frequency_hz, dt, H, hr.std_hz)
    if resolved < H:
        log.warning("%d harmonics of the heart rate %.3g Hz (+ 2 standard errors) reach the Nyquist frequency %.3g Hz "
                    "of %.3g frames per second: %d harmonics used", H, hr.frequency_hz, 0.5 / dt, 1.0 / dt, resolved)
        H = resolved
        rigid_harmonics = None if rigid_harmonics is None else min(rigid_harmonics, H)
    if heart_rate_hz is not None and not hr.prominence >= PEAK_PROMINENCE:
        log.warning("the tracks' spectrum at the given heart rate %.3g Hz stands %.2gx above its values at half and "
                    "one and a half times that frequency (a heartbeat's peak: %gx and more): the tracks do not show "
                    "this rate clearly", hr.frequency_hz, hr.prominence, PEAK_PROMINENCE)
    cfg = m.config
    held = [n for n in cfg.estimation.estimate if n == "E"]
    fit_model = m
    if held and len(cfg.estimation.estimate) > 1:
        # the input's scale and E are not separable without a recorded pressure: E stays at the model's value
        fit_model = build_model(dc_replace(cfg, estimation=dc_replace(
            cfg.estimation, estimate=tuple(n for n in cfg.estimation.estimate if n != "E"))))
        log.info("E held at the model file's %.4g Pa: without a recorded pressure only E/scale is determined",
                 cfg.theta[3])
    column = m.input_names.index("pressure")
    prob = UnknownInputProblem(fit_model, meas, hr.frequency_hz, H, column, frames=K, centred=True)
    result = run_fit(fit_model, meas, np.random.default_rng(seed), starts=starts, max_evaluations=max_evaluations,
                     problem=prob)
    if not result.converged:
        return result, None
    alpha, alpha_std, rigid = prob.input_solution(result.theta, result.reduced_chi2)
    resp_band = RESPIRATION_BAND_HZ if respiration_band is None else tuple(respiration_band)
    resp = estimate_respiration(meas.times[:K], rigid[:, :3], hr.frequency_hz, heart_harmonics=H, band=resp_band) \
        if respiration else Respiration(None, reason="--respiration none")
    if resp.seen:
        log.info("respiration %.3g ± %.2g Hz (%.1f per minute) from the fit's rigid motion: %.1f breaths, its "
                 "harmonics explain %.0f %% of the translation", resp.frequency_hz, resp.std_hz,
                 60 * resp.frequency_hz, resp.cycles, 100 * resp.explained)
    else:
        log.info("no respiration rate: %s (the random-walk translation takes it up)", resp.reason)
    field = frame = None
    if field_degree:
        frame = prob.field_frame()
        field = prob.residual_field(result.theta, field_degree, frame)
    block = input_block_from_fit(hr.frequency_hz, H, prob.dt, len(m.input_names), column, alpha, alpha_std,
                                 rigid[:, :3], meas.times[:K], respiration_hz=resp.frequency_hz,
                                 rigid_ar_order=rigid_ar_order, field=field, field_degree=field_degree,
                                 field_frame=frame, centred=True, rigid_harmonics=rigid_harmonics)
    how = " (BIC)" if field_degree == 0 else " (predicting the last 30 % of the fitted frames)"
    log.info("rigid %s: %s beyond %d harmonics of the heart rate",
             "translation" if field_degree == 0 else f"motion, a degree-{field_degree} field",
             (f"an order-{block.ar_order} autoregression of its increments" if block.ar_order else "a random walk")
             + (how if rigid_ar_order is None else ""), block.rigid_harmonics)
    entry = block.to_dict()
    entry.update(heart_rate={"frequency_hz": hr.frequency_hz, "std_hz": hr.std_hz, "bpm": 60 * hr.frequency_hz,
                             "source": "spectrum" if heart_rate_hz is None else "given",
                             "peak_hz": hr.peak_hz,
                             "peak_ratio": hr.peak_ratio if math.isfinite(hr.peak_ratio) else None,
                             "peak_prominence": hr.prominence if math.isfinite(hr.prominence) else None,
                             "peak_background_ratio": hr.background_ratio if math.isfinite(hr.background_ratio)
                             else None,
                             "beats": hr.beats, "points": hr.points, "band_hz": [float(band[0]), float(band[1])]}
                 | ({"left_out_tracks": [int(meas.point_ids[p]) for p in hr.left_out]} if hr.left_out else {}),
                 respiration=dict(resp.to_dict(), band_hz=[float(resp_band[0]), float(resp_band[1])]),
                 amplitudes_pa=[float(v) for v in alpha], amplitudes_std_pa=[float(v) for v in alpha_std],
                 held_fixed=["E"] if fit_model is not m else [], fit_frames=K, rigid_ar_order=block.ar_order,
                 field_degree=int(field_degree),
                 translation_std_m=[float(v) for v in np.std(rigid[:, :3], axis=0)])
    return result, entry


def _summary(result, output) -> dict:
    """The --json summary of a converged fit."""
    from heartcv.tracker.params import NAMES

    est = list(result.estimated)
    summary = {
        "theta": dict(zip(NAMES, map(float, result.theta), strict=True)),
        "theta_std": dict(zip(NAMES, map(float, result.theta_std), strict=True)),
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
        "poorly_determined": list(result.poorly_determined),
        "registration_rms_m": None if result.registration is None else result.registration["rms_m"],
        "patch": None if result.registration is None else result.registration.get("patch"),
        "heart_rate_hz": None if result.estimated_input is None else result.estimated_input["frequency_hz"],
        "heart_rate_source": None if result.estimated_input is None
        else (result.estimated_input.get("heart_rate") or {}).get("source", "spectrum"),
        "heart_rate_peak_prominence": None if result.estimated_input is None
        else (result.estimated_input.get("heart_rate") or {}).get("peak_prominence"),
        "input_amplitudes_pa": None if result.estimated_input is None else result.estimated_input["amplitudes_pa"],
        "respiration_hz": None if result.estimated_input is None
        else (result.estimated_input.get("respiration") or {}).get("frequency_hz"),
        "rigid_ar_order": None if result.estimated_input is None else result.estimated_input.get("rigid_ar_order"),
        "field_degree": None if result.estimated_input is None else result.estimated_input.get("field_degree"),
        "rigid_harmonics": None if result.estimated_input is None
        else result.estimated_input.get("rigid_harmonics"),
        "output": output,
    }
    return summary
