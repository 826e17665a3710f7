"""``heartcv measure``: tracked 3-D surface points with covariances from a calibrated image sequence."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import click

from .options import BadInput, StageFailed, emit_json, json_opt, progress

log = logging.getLogger(__name__)

# inputs.csv column suffix -> (unit written to the measurement file, factor to SI)
UNIT_SUFFIXES = {"_pa": ("Pa", 1.0), "_kpa": ("Pa", 1e3), "_mmhg": ("Pa", 133.322387415), "_m": ("m", 1.0),
                 "_mm": ("m", 1e-3)}


@click.command()
@click.argument("sequence", type=click.Path(file_okay=False))
@click.option("--rig", "rig_file", type=click.Path(dir_okay=False), required=True,
              help="Rig file (from `heartcv calibrate`); its camera names select the sequence's cameras.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True,
              help="Measurement file to write (.npz, heartcv.measurements v1, rig frame).")
@click.option("--mask", "mask_file", type=click.Path(dir_okay=False), default=None,
              help="Region of interest in the reference camera (image; nonzero = surface). Default: the moving, "
                   "textured surface of the first frames.")
@click.option("--inputs", "inputs_file", type=click.Path(dir_okay=False), default=None,
              help="Known inputs (CSV: time_s and one column per input, e.g. pressure_pa); default "
                   "SEQUENCE/inputs.csv if present. Interpolated linearly to the frame times.")
@click.option("--fps", type=float, default=None,
              help="Frame rate (Hz). Default: SEQUENCE/timestamps.csv, else the videos' rate, else 30.")
@click.option("--ref-camera", default=None, help="Camera where points are detected (default: the rig's first).")
@click.option("--points", "max_points", type=click.IntRange(min=1), default=300, show_default=True,
              help="Points to keep tracked (new ones are detected when fewer than 80 % are seen).")
@click.option("--min-distance", type=click.FloatRange(min=1), default=15.0, show_default=True, metavar="PX",
              help="Least distance between detected corners (small images: e.g. 5).")
@click.option("--corner-block", type=click.IntRange(min=2), default=7, show_default=True, metavar="PX",
              help="Shi-Tomasi structure-tensor block size (small images: e.g. 3).")
@click.option("--corner-quality", type=click.FloatRange(min=0, max=1, min_open=True), default=0.02,
              show_default=True, help="Keep corners whose response is at least this fraction of the strongest.")
@click.option("--frames", type=click.IntRange(min=2), default=None, help="Use only the first N frames.")
@click.option("--backend", type=click.Choice(("opencv", "kornia")), default="opencv", show_default=True,
              help="Detection, description and matching on OpenCV/numpy or on torch tensors with kornia.")
@click.option("--device", default=None, help="Torch device for --backend kornia (default: cuda if available).")
@click.option("--pixel-sigma", type=float, default=None, metavar="PX",
              help="Pixel noise for the covariances (default: estimated from the reprojection residuals).")
@click.option("--highpass", type=float, default=3.0, show_default=True, metavar="SIGMA",
              help="Track on the high-pass image (gray minus its Gaussian blur of this sigma, px); 0 = raw gray.")
@click.option("--truth", "truth_file", type=click.Path(dir_okay=False), default=None,
              help="Render truth (truth.npz of `heartcv render sequence`): report the 3-D error of every point.")
@click.option("--csv", "csv_file", type=click.Path(dir_okay=False), default=None,
              help="Also write a long-form CSV (one row per frame and point).")
@click.option("--workers", type=click.IntRange(min=1), default=2, show_default=True,
              help="Image decoding threads.")
@json_opt
@click.pass_context
def measure(ctx, sequence, rig_file, output, mask_file, inputs_file, fps, ref_camera, max_points, min_distance,
            corner_block, corner_quality, frames, backend, device, pixel_sigma, highpass, truth_file, csv_file,
            workers, as_json):
    """Track 3-D surface points through SEQUENCE (one folder of images or one video per camera; the same file
    name is the same instant) seen by the cameras of RIG, and write their positions and covariances per frame.

    Isolated bad images (missing, corrupt, wrong size) are named in a warning and that camera is left out of
    that frame. Exit 2 for bad input (cameras missing, different frame counts, a rig that does not fit the
    images); exit 1 when no point can be tracked.
    """
    import numpy as np

    from heartcv.io import HeartcvIOError, FrameReader, file_hash, open_frame_source, read_mask, read_rig

    out = Path(output)
    if out.suffix.lower() != ".npz":
        raise BadInput(f"-o/--output: a .npz file expected, got {output}")
    if fps is not None and not fps > 0:
        raise BadInput(f"--fps: positive expected, got {fps}")
    if pixel_sigma is not None and not pixel_sigma > 0:
        raise BadInput(f"--pixel-sigma: positive expected, got {pixel_sigma}")
    try:
        rig = read_rig(rig_file)
        source = open_frame_source(sequence, cameras=rig.names)
    except HeartcvIOError as exc:
        raise BadInput(str(exc)) from None
    names = rig.names
    ref = 0 if ref_camera is None else (names.index(ref_camera) if ref_camera in names else None)
    if ref is None:
        raise BadInput(f"--ref-camera: {ref_camera!r} is not a camera of {rig_file} ({names})")
    if source.missing():
        log.info("%d camera images missing in %s (each is named when its frame is read)", len(source.missing()),
                 sequence)
    count = source.n_frames if frames is None else min(frames, source.n_frames)
    if count < 2:
        raise BadInput(f"{sequence}: {count} frame(s); at least 2 expected")
    _check_sizes(source, rig)
    times = _frame_times(source, fps, count)
    inputs_path = Path(inputs_file) if inputs_file else Path(sequence) / "inputs.csv"
    in_names, in_units, in_values = _inputs(inputs_path, times, required=inputs_file is not None)
    roi = None
    if mask_file:
        try:
            roi = read_mask(mask_file, rig.cameras[ref].size)
        except HeartcvIOError as exc:
            raise BadInput(str(exc)) from None
    truth = _read_truth(truth_file, count, names) if truth_file else None
    be = _backend(backend, device)

    from heartcv.klt import LKParams
    from heartcv.measure import MeasureOptions, Measurer

    opts = MeasureOptions(ref_camera=ref, max_points=max_points, pixel_sigma=pixel_sigma,
                          min_distance_px=min_distance, corner_block_size=corner_block,
                          corner_quality=corner_quality,
                          highpass_sigma=highpass or None, lk=LKParams())
    sizes = [c.size for c in rig.cameras]
    verbosity = (ctx.find_object(dict) or {}).get("verbosity", 0)
    t_start = time.perf_counter()
    decode = 0.0
    with FrameReader(source, sizes=sizes, frames=range(count), workers=workers) as reader:
        first = []
        for k in range(0, min(count, 30), 3):
            imgs, _ = reader.read(k)
            if imgs[ref] is not None:
                first.append(imgs[ref])
        if roi is None and not first:
            raise BadInput(f"{sequence}: none of the first frames of camera {names[ref]} can be read")
        try:
            measurer = Measurer(rig.cameras, opts, roi_frames=first, roi=roi, backend=be)
        except ValueError as exc:
            raise StageFailed(f"{sequence}: {exc}") from None
        n_bad = 0
        it = iter(reader)
        with progress(range(count), "measuring", count, verbosity) as bar:
            for _ in bar:
                t0 = time.perf_counter()
                k, imgs, problems = next(it)
                decode += time.perf_counter() - t0
                for msg in problems:
                    log.warning("frame %d: %s; left out", k, msg)
                if sum(im is not None for im in imgs) < 2:
                    n_bad += 1
                    measurer.skip(k, f"frame {k}: fewer than two readable images")
                    continue
                measurer.step(k, imgs)
    wall = time.perf_counter() - t_start
    res = measurer.result()
    if res.point_ids.size == 0 or not res.seen.any():
        raise StageFailed(f"{sequence}: no surface point could be tracked (region of interest "
                          f"{int(res.roi.sum())} px in {names[ref]}); check the rig, the mask or the images")
    if n_bad:
        log.warning("%d of %d frames had fewer than two readable images: all points missing there", n_bad, count)

    from heartcv.tracker.io import write_measurements
    from heartcv.tracker.measurements import MeasurementSet

    meta = {"producer": "heartcv measure", "frame_rig": rig_file, "camera_names": names,
            "ref_camera": names[ref], "backend": be.name, "sigma_px": res.sigma_px,
            "sigma_estimated": res.sigma_estimated, "reference_frame_index": res.birth_frame.tolist(),
            "reference_uv": [[float(v) for v in res.uv[b, p, ref]] for p, b in enumerate(res.birth_frame)],
            "frame_names": list(source.frame_names[:count]), "highpass_sigma": highpass,
            "inputs_hash": {"rig": file_hash(rig_file)} | ({"inputs": file_hash(inputs_path)}
                                                          if in_names else {}),
            "sequence": str(sequence)}
    try:
        mset = MeasurementSet(times=times, point_ids=res.point_ids, positions=res.positions,
                              covariances=res.covariances, reference=res.reference, inputs=in_values,
                              input_names=in_names, input_units=in_units, frame="rig", views=res.views,
                              reprojection_rms=res.reprojection_rms, meta=meta)
    except ValueError as exc:   # a bug rather than bad input: say so plainly
        raise StageFailed(f"internal error assembling the measurements: {exc}") from None
    if csv_file:
        _write_csv(csv_file, mset, res, names)
    write_measurements(output, mset, meta)
    summary = _summary(output, res, times, wall, decode, names, be.name)
    if truth is not None:
        summary.update(_truth_summary(res, truth, ref))
    if as_json:
        emit_json(summary)
    else:
        log.warning("wrote %s: %d frames, %d tracks, %.0f points per frame (min %d), reprojection RMS %.3f px",
                    output, summary["frames"], summary["tracks"], summary["points_mean"], summary["points_min"],
                    summary["reprojection_rms_px"])


# -- inputs -----------------------------------------------------------------------------------------------------
def _check_sizes(source, rig):
    """Exit 2 if a camera's first readable image does not have the rig's image size."""
    from heartcv.io import HeartcvIOError, read_image

    for c, cam in enumerate(rig.cameras):
        if source.kind == "video":
            import cv2

            cap = cv2.VideoCapture(str(source.files[c][0]))
            ok, img = cap.read()
            cap.release()
            if not ok:
                raise BadInput(f"{source.files[c][0]}: the first frame cannot be decoded")
            size, where = (img.shape[1], img.shape[0]), source.files[c][0]
        else:
            size = where = None
            for f in source.files[c]:
                if f is None:
                    continue
                try:
                    img = read_image(f, "gray")
                except HeartcvIOError:
                    continue
                size, where = (img.shape[1], img.shape[0]), f
                break
            if size is None:
                raise BadInput(f"{source.folder / cam.name}: no readable image")
        if size != cam.size:
            raise BadInput(f"{where}: image is {size[0]}x{size[1]} px, but the rig's camera {cam.name} is "
                           f"{cam.width}x{cam.height}: the rig does not belong to these images")


def _frame_times(source, fps, count):
    import numpy as np

    from heartcv.io import HeartcvIOError, read_timestamps

    ts = source.folder / "timestamps.csv"
    if fps is None and ts.is_file():
        try:
            return read_timestamps(ts, source.frame_names)[:count]
        except HeartcvIOError as exc:
            raise BadInput(str(exc)) from None
    rate = fps or source.fps or 30.0
    if fps is None and source.fps is None:
        log.info("no timestamps.csv and no --fps: assuming %g frames per second", rate)
    return np.arange(count) / rate


def _inputs(path, times, required):
    """(names, units, values (K, n)) of an inputs table interpolated linearly at the frame times."""
    import numpy as np

    from heartcv.io import HeartcvIOError, read_inputs_csv_columns

    K = len(times)
    if not path.is_file():
        if required:
            raise BadInput(f"{path}: no such inputs file")
        log.warning("no inputs file (%s): the measurement file has no inputs (heartcv track needs pressure)", path)
        return (), (), np.zeros((K, 0))
    try:
        cols, n = read_inputs_csv_columns(path)
    except HeartcvIOError as exc:
        raise BadInput(str(exc)) from None
    if "time_s" not in cols:
        raise BadInput(f"{path}: a 'time_s' column expected, got {list(cols)}")
    t = cols.pop("time_s")
    if n < 2 or not np.isfinite(t).all() or (np.diff(t) <= 0).any():
        raise BadInput(f"{path}: time_s must hold at least two finite, strictly increasing values")
    half = 0.5 * float(np.median(np.diff(t)))
    if times[0] < t[0] - half or times[-1] > t[-1] + half:
        raise BadInput(f"{path}: the inputs cover {t[0]:.4g}..{t[-1]:.4g} s, the frames "
                       f"{times[0]:.4g}..{times[-1]:.4g} s")
    names, units, vals = [], [], []
    for name, v in cols.items():
        if not np.isfinite(v).all():
            raise BadInput(f"{path}: column {name!r} has non-finite values")
        base, unit, factor = name, "", 1.0
        for suf, (u, f) in UNIT_SUFFIXES.items():
            if name.lower().endswith(suf):
                base, unit, factor = name[: -len(suf)], u, f
                break
        names.append(base)
        units.append(unit)
        vals.append(np.interp(times, t, v) * factor)
    return tuple(names), tuple(units), np.stack(vals, axis=1) if vals else np.zeros((K, 0))


def _read_truth(path, count, names):
    from heartcv.io import HeartcvIOError, read_render_truth

    try:
        arrays, meta = read_render_truth(path)
    except HeartcvIOError as exc:
        raise BadInput(str(exc)) from None
    if meta.get("kind") != "sequence":
        raise BadInput(f"{path}: a sequence truth expected, got kind {meta.get('kind')!r}")
    if arrays["vertex_positions"].shape[0] < count:
        raise BadInput(f"{path}: {arrays['vertex_positions'].shape[0]} frames of truth for {count} measured")
    if list(meta.get("camera_names", names)) != list(names):
        raise BadInput(f"{path}: cameras {meta.get('camera_names')} differ from the rig's {names}")
    arrays = dict(arrays)
    for key in ("vertex_positions", "instrument_mask"):
        if key in arrays:
            arrays[key] = arrays[key][:count]
    return arrays


def _backend(name, device):
    from heartcv.backend import get_backend

    try:
        be = get_backend(name, device)
        if name == "kornia" and str(getattr(be, "device", "cpu")).startswith("cpu"):
            import torch

            torch.set_num_threads(1)     # measured: 2 threads beside the decoding threads are ~9x slower on 2 cores
        return be
    except ImportError as exc:
        raise BadInput(f"--backend {name}: {exc}") from None
    except (ValueError, RuntimeError) as exc:
        raise BadInput(f"--backend {name} --device {device}: {exc}") from None


# -- outputs ----------------------------------------------------------------------------------------------------
def _summary(output, res, times, wall, decode, names, backend):
    import numpy as np

    seen = res.seen
    per_frame = seen.sum(axis=1)
    r = res.reprojection_rms[seen]
    return {"output": str(output), "frames": int(len(times)), "cameras": names, "backend": backend,
            "tracks": int(res.point_ids.size), "points_mean": float(per_frame.mean()),
            "points_min": int(per_frame.min()), "points_max": int(per_frame.max()),
            "reprojection_rms_px": float(np.sqrt(np.mean(r ** 2))) if r.size else None,
            "sigma_px": res.sigma_px, "sigma_estimated": res.sigma_estimated,
            "views_mean": float(res.views[seen].mean()) if seen.any() else 0.0,
            "frames_per_s": len(times) / wall if wall > 0 else None, "wall_s": wall,
            "timings_s": {"decode": decode, **res.timings}, "roi_px": int(res.roi.sum())}


def _truth_summary(res, truth, ref):
    import numpy as np

    from heartcv.evaluate import occluded_observations, truth_errors

    P = res.point_ids.size
    uv_ref = np.array([res.uv[res.birth_frame[p], p, ref] for p in range(P)], float).reshape(P, 2)
    te = truth_errors(res.positions, uv_ref, res.birth_frame, truth, ref_camera=ref)
    out = {"error_rms_m": te.rms_m, "error_p99_m": te.p99_m, "error_mean_m": te.mean_m,
           "error_max_m": te.max_m, "error_observations": te.n,
            "tracks_off_surface": int((te.material_face < 0).sum()),
           "occluded_observations": occluded_observations(res.uv, truth)}
    if te.aligned is not None:
        from heartcv.evaluate import displacement_consistency

        R = te.truth_from_rig[:3, :3]
        dc = displacement_consistency(res.positions, res.covariances, te.true_positions, res.birth_frame, R)
        out.update({"displacement_error_rms_m": dc["rms_m"], "displacement_nees_per_dof": dc["nees_per_dof"]})
        out.update({"aligned_error_rms_m": te.aligned.rms_m, "aligned_error_p99_m": te.aligned.p99_m,
                    "aligned_error_mean_m": te.aligned.mean_m, "aligned_error_max_m": te.aligned.max_m,
                    "rig_gauge_rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))),
                    "rig_gauge_translation_m": float(np.linalg.norm(te.truth_from_rig[:3, 3]))})
    return out


def _write_csv(path, mset, res, names):
    """Long form: one row per (frame, seen point): time, id, position, covariance (6 entries), views, RMS,
    and the pixel position in each camera (empty where that view was not used)."""
    import numpy as np

    from heartcv.io import atomic_path

    cols = ["frame", "time_s", "point_id", "x_m", "y_m", "z_m", "cxx_m2", "cxy_m2", "cxz_m2", "cyy_m2",
            "cyz_m2", "czz_m2", "views", "reprojection_rms_px"]
    for n in names:
        cols += [f"u_{n}_px", f"v_{n}_px"]
    lines = ["# heartcv measure: tracked points in the rig frame (docs/formats.md, measurement CSV)",
             ",".join(cols)]
    ks, ps = np.nonzero(mset.seen)
    X = mset.positions[ks, ps]
    Cv = mset.covariances[ks, ps]
    uv = res.uv[ks, ps].reshape(len(ks), -1)
    for i, (k, p) in enumerate(zip(ks, ps)):
        c = Cv[i]
        row = [str(k), repr(float(mset.times[k])), str(int(mset.point_ids[p])),
               *(repr(float(v)) for v in X[i]),
               *(repr(float(v)) for v in (c[0, 0], c[0, 1], c[0, 2], c[1, 1], c[1, 2], c[2, 2])),
               str(int(mset.views[k, p])), repr(float(mset.reprojection_rms[k, p]))]
        row += ["" if not np.isfinite(v) else repr(float(v)) for v in uv[i]]
        lines.append(",".join(row))
    with atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n", encoding="utf-8")
