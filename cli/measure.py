"""``heartcv measure``: tracked 3-D surface points with covariances from a calibrated image sequence.

The stage itself is :func:`heartcv.measure.measure_sequence`; frame times, inputs, truth and the summary come from
:mod:`heartcv.measure_data`. This module parses the options, guards the outputs, reads the inputs, calls the core
and writes the measurement file (and the CSV).
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path
import time

import click
import numpy as np

from .options import BadInput, Float, Int, StageFailed, announce, emit_json, guard_outputs, json_opt, progress

log = logging.getLogger(__name__)

MAX_WORKERS = 1024


@click.command()
@click.argument("sequence", type=click.Path(file_okay=False))
@click.option("--rig", "rig_file", required=True, type=click.Path(dir_okay=False),
              help="Rig file (from `heartcv calibrate`); its camera names select the sequence's cameras.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Measurement file to write (.npz, heartcv.measurements v1, rig frame).")
@click.option("--mask", "mask_file", type=click.Path(dir_okay=False), default=None,
              help="Region of interest in the reference camera (image; nonzero = surface). Default: the moving, "
                   "textured surface of the first frames.")
@click.option("--inputs", "inputs_file", type=click.Path(dir_okay=False), default=None,
              help="Known inputs (CSV: time_s and one column per input, e.g. pressure_pa); default "
                   "SEQUENCE/inputs.csv if present. Interpolated linearly to the frame times.")
@click.option("--fps", type=Float(0, 10000, lo_open=True), default=None,
              help="Frame rate (Hz). Default: SEQUENCE/timestamps.csv, else the videos' rate, else 30.")
@click.option("--packed", type=click.Choice(("side-by-side", "top-bottom", "rows")), default=None,
              help="SEQUENCE holds one video or one folder of images whose every frame packs the views of the "
                   "rig's cameras, in the rig's order: side by side, top to bottom, or in interleaved rows (an "
                   "interlaced frame whose fields are the views).")
@click.option("--ref-camera", default=None, help="Camera where points are detected (default: the rig's first).")
@click.option("--points", "max_points", type=Int(1), default=300, show_default=True,
              help="Points to keep tracked (new ones are detected when fewer than 80 % are seen).")
@click.option("--min-distance", type=Float(1, 16384), default=None, metavar="PX",
              help="Least distance between detected corners (default: 15 px at 1080 rows, scaled with the image's "
                   "smaller side, at least 5).")
@click.option("--corner-block", type=Int(2, 255), default=None, metavar="PX",
              help="Shi-Tomasi structure-tensor block size (default: 7 px at 1080 rows, scaled, at least 3).")
@click.option("--corner-quality", type=Float(0, 1, lo_open=True), default=0.01, show_default=True,
              help="Keep corners whose response is at least this fraction of the strongest.")
@click.option("--frames", type=Int(1), default=None,
              help="Use only the first N frames (from --start; one instant is enough).")
@click.option("--start", type=Int(0), default=0, show_default=True, metavar="FRAME",
              help="Begin at this frame (0 the first): a segment of a long recording, with --frames its length. The "
                   "segment keeps the recording's clock (its times, inputs and frame names).")
@click.option("--dense", is_flag=True, default=False,
              help="Dense surface mode: semi-global stereo plus dense optical flow, thousands of points per frame "
                   "(two cameras: the reference and the widest baseline; heartcv.dense).")
@click.option("--fb-max", type=Float(0, 1000, lo_open=True), default=1.0, show_default=True, metavar="PX",
              help="Tracking gate: largest forward-backward error of a tracked view.")
@click.option("--ncc-allowance", type=Float(0, 2), default=0.25, show_default=True,
              help="Photometric gate of the tracking: accept an NCC down to the one image noise alone would leave "
                   "for that patch minus this (and at least 0.5).")
@click.option("--match-ncc-allowance", type=Float(0, 2), default=0.15, show_default=True,
              help="The same for matching new points across the cameras.")
@click.option("--min-ncc", type=Float(-1, 1), default=None,
              help="A fixed NCC gate (tracking and matching) instead of the noise-adaptive ones.")
@click.option("--max-depth-std", type=Float(0, 10, lo_open=True), default=0.05, show_default=True,
              help="Geometry gate: largest predicted depth standard deviation (rig geometry and pixel noise), as a "
                   "fraction of the depth.")
@click.option("--max-reprojection", type=Float(0, 1000, lo_open=True), default=1.0, show_default=True, metavar="PX",
              help="Triangulation gate: largest reprojection RMS (and per-view outlier threshold).")
@click.option("--min-angle", type=Float(0, 90), default=0.0, show_default=True, metavar="DEG",
              help="Optional least angle between the viewing rays (0: only the depth-uncertainty gate).")
@click.option("--max-gap", type=Int(1), default=60, show_default=True, metavar="FRAMES",
              help="A track unseen for more frames in a row ends (until then it is searched for and resumes).")
@click.option("--window", type=Int(5, 255), default=None, metavar="PX",
              help="Lucas-Kanade window (odd; default 21 px at 1080 rows, scaled with the image, at least 11).")
@click.option("--no-specular", "no_specular", is_flag=True, default=False,
              help="Do not mask specular highlights per frame.")
@click.option("--overlay", "overlay_dir", type=click.Path(file_okay=False), default=None,
              help="Write DIR/frames/*.png (the tracks drawn on the images) and DIR/tracks.png (points per frame, "
                   "track lengths).")
@click.option("--overlay-video", is_flag=True, default=False,
              help="With --overlay: one DIR/overlay.mp4 instead of the PNG frames.")
@click.option("--backend", type=click.Choice(("opencv", "kornia")), default="opencv", show_default=True,
              help="Detection, description and matching on OpenCV/numpy or on torch tensors with kornia.")
@click.option("--device", default=None, help="Torch device for --backend kornia (default: cuda if available).")
@click.option("--pixel-sigma", type=Float(0, 1000, lo_open=True), default=None, metavar="PX",
              help="Pixel noise for the covariances (default: estimated from the reprojection residuals).")
@click.option("--highpass", type=Float(0, 1000), default=3.0, show_default=True, metavar="SIGMA",
              help="Track on the high-pass image (gray minus its Gaussian blur of this sigma, px); 0 = raw gray.")
@click.option("--size-factor", default="auto", show_default=True, metavar="auto|K",
              help="Multiply every pixel size and threshold of the tracking (corner distance and block, window, NCC "
                   "patch, high-pass, forward-backward, reprojection) by K; auto: sharp video (its first frames' "
                   "texture blur at most 1 px) as it is; blurrier or oversampled video is tracked on frames reduced "
                   "until their texture reads 1 px (positions reported in the full frames' pixels).")
@click.option("--fields", type=click.Choice(["auto", "first", "second", "both", "none"]), default="auto",
              show_default=True,
              help="Interlaced video: measure one field of every frame (first: rows 0, 2, 4, ...; second: rows 1, 3, "
                   "...), positions in the full frames' pixels; both: each field an instant of its own, half a frame "
                   "apart (twice the frame rate; each field's rows interpolated back to the frame's, see "
                   "--field-order); none: the whole frames; auto: the first field when the first frames look "
                   "interlaced (combing ratio above 1, with a warning), else the whole frames.")
@click.option("--field-order", type=click.Choice(["auto", "top", "bottom"]), default="auto", show_default=True,
              help="With --fields both: which field was taken first (top: rows 0, 2, ...); auto: from the first "
                   "frames' motion (top when they cannot tell, with a warning).")
@click.option("--vertical-offset", type=click.Choice(["auto", "none"]), default="auto", show_default=True,
              help="A rig of a pre-rectified pair (rectified: true, heartcv rig rectified): auto measures how far "
                   "each camera's views lie below the reference camera's in the first frames (a pair rectified "
                   "slightly off; SIFT descriptors, then in sparse mode the tracks of repeated probes) and, where "
                   "that is significant, measures with its principal point moved by it; none: the rig as given. "
                   "Calibrated rigs are always used as given.")
@click.option("--repeated-frames", type=click.Choice(["drop", "keep"]), default="drop", show_default=True,
              help="A camera's frame that repeats its previous one (no new exposure: a frame-rate conversion, a "
                   "capture that froze or dropped frames; identical up to compression noise while the view was "
                   "moving): drop leaves it out of its instant as a missing image (with fewer than two views left "
                   "the instant has all points missing); keep measures it as a frame of its own.")
@click.option("--truth", "truth_file", type=click.Path(dir_okay=False), default=None,
              help="Render truth (truth.npz of `heartcv render sequence`): report the 3-D error of every point.")
@click.option("--csv", "csv_file", type=click.Path(dir_okay=False), default=None,
              help="Also write a long-form CSV (one row per frame and point).")
@click.option("--workers", type=Int(1, MAX_WORKERS), default=2, show_default=True, help="Image decoding threads.")
@json_opt
@click.pass_context
def measure(ctx, sequence, rig_file, output, mask_file, inputs_file, fps, packed, ref_camera, max_points, min_distance,
            corner_block, corner_quality, frames, start, dense, fb_max, ncc_allowance, match_ncc_allowance, min_ncc,
            max_depth_std, max_reprojection, min_angle, max_gap, window, no_specular, overlay_dir, overlay_video,
            backend, device, pixel_sigma, highpass, size_factor, fields, field_order, vertical_offset, repeated_frames,
            truth_file,
            csv_file, workers, as_json):
    """Track 3-D surface points through SEQUENCE (one folder of images or one video per camera; the same file
    name is the same instant; or, with --packed, one holding all the views) seen by the cameras of RIG, and write
    their positions and covariances per frame.

    Isolated bad images (missing, corrupt, wrong size) are named in a warning and that camera is left out of
    that frame. Exit 2 for bad input (cameras missing, different frame counts, a rig that does not fit the
    images, a rig not in metres) and for outputs that would replace an input or a file heartcv did not write;
    exit 1 when no point can be tracked (the message names the gates that removed the candidates).
    """
    from heartcv.io import FrameReader, open_frame_source, read_rig
    from heartcv.measure import FieldInstants
    from heartcv.measure_data import expand_to_grid
    from heartcv.tracker.files import InputError
    from heartcv.tracker.io import write_measurements

    seq = Path(sequence)
    inputs_path = Path(inputs_file) if inputs_file else seq / "inputs.csv"
    _guard(output, csv_file, {"SEQUENCE": seq, "--rig": rig_file, "--mask": mask_file, "--inputs": inputs_path,
                              "SEQUENCE/timestamps.csv": seq / "timestamps.csv", "--truth": truth_file}, overlay_dir)
    if overlay_dir is not None:
        from .measure_overlay import check_overlay_dir

        if seq.is_dir() and Path(overlay_dir).resolve().is_relative_to(seq.resolve()):
            # its images would read as another camera (or another camera's frames) the next time
            raise InputError(overlay_dir, f"inside SEQUENCE ({seq}): its images would be read as a camera's by the "
                                          "next measure or calibrate of that folder; choose a folder outside it",
                             "--overlay")
        check_overlay_dir(overlay_dir)
    elif overlay_video:
        raise BadInput("--overlay-video: only with --overlay DIR")
    if window is not None and window % 2 == 0:     # option values before anything is read
        raise BadInput(f"--window: an odd number expected, got {window}")
    _size_factor(size_factor)
    if dense:
        _refuse_sparse_options(ctx)
    both = fields == "both"
    if field_order != "auto" and not both:
        raise BadInput("--field-order applies to --fields both only")
    if both and truth_file is not None:
        raise BadInput("--truth: not with --fields both (a render truth is of whole frames)")
    rig = read_rig(rig_file)
    if len(rig) < 2:
        raise InputError(rig_file, f"{len(rig)} camera ({rig.names[0]}); measure triangulates from at least 2",
                         "cameras")
    _check_rig_scale(rig, rig_file)
    source = open_frame_source(sequence, cameras=rig.names, cameras_source=rig_file, packing=packed)
    names = rig.names
    ref = 0 if ref_camera is None else (names.index(ref_camera) if ref_camera in names else None)
    if ref is None:
        raise BadInput(f"--ref-camera: {ref_camera!r} is not a camera of {rig_file} ({names})")
    if source.missing():
        log.info("%d camera images missing in %s (each is named when its frame is read)", len(source.missing()),
                 sequence)
    recording = source
    if start:
        if start >= source.n_frames:
            raise BadInput(f"--start {start}: {sequence} has {source.n_frames} frames (0 to {source.n_frames - 1})")
        source = source.segment(start)
    count = source.n_frames if frames is None else min(frames, source.n_frames)
    if start:
        log.info("--start %d: frames %d to %d of %s", start, start, start + count - 1, sequence)
    if count < 1:
        raise BadInput(f"{sequence}: no frame")
    _check_sizes(source, rig, count, rig_file)
    times = _frame_times(recording, fps, start + count, ref)[start:]   # a segment keeps the recording's clock
    if both:
        if count < 2:
            raise BadInput(f"--fields both: {count} frame; at least 2 are needed (the fields' times)")
        from heartcv.measure_data import field_times

        times = field_times(times)
    stamps = seq / "timestamps.csv" if fps is None and (seq / "timestamps.csv").is_file() else None
    grid = _grid(times, stamps or seq)
    file_times = times if grid is None else grid[1]
    in_names, in_units, in_values = _inputs(inputs_path, file_times, required=inputs_file is not None,
                                            times_from=stamps)
    roi = _mask(mask_file, rig.cameras[ref].size)
    truth = _truth(truth_file, count, names, source.start)
    be = _backend(backend, device)
    if dense:
        opts = _dense_options(ref, pixel_sigma)
    else:
        opts = _options(ref, max_points, pixel_sigma, min_distance, corner_block, corner_quality, highpass,
                        fb_max=fb_max, ncc_allowance=ncc_allowance, match_ncc_allowance=match_ncc_allowance,
                        min_ncc=min_ncc, max_depth_std=max_depth_std,
                        max_reprojection=max_reprojection, min_angle=min_angle, max_gap=max_gap, window=window,
                        specular=not no_specular)

    t_start = time.perf_counter()
    mode = "gray" if dense else "color"
    sizing = {"fields": fields} if dense else {"size_factor": _size_factor(size_factor), "fields": fields}
    sizing["repeated_frames"] = repeated_frames
    first_field = None
    instant_names = list(source.frame_names[:count])
    with FrameReader(source, mode=mode, sizes=[c.size for c in rig.cameras], frames=range(count),
                     workers=workers) as reader:
        if both:
            first_field = _field_order(reader, count, ref, roi, field_order, rig.cameras[ref].name, sizing)
            reader = FieldInstants(reader, first_field)
            order = ("top", "bottom") if first_field == 0 else ("bottom", "top")
            instant_names = [f"{n}.{f}" for n in instant_names for f in order]
        matches = _descriptor_matches(reader, len(instant_names), ref, len(rig), roi)
        if vertical_offset == "auto" and rig.meta.get("rectified") and len(rig) >= 2:
            rig = _rectified_offsets(ctx, reader, rig, opts, roi, be, len(instant_names), sequence, rig_file, dense,
                                     sizing, ref, matches)
        _epipolar_distances(matches, rig, ref, rig_file, sizing)
        try:
            run = _run(ctx, reader, rig, opts, roi, be, len(instant_names), sequence, rig_file, dense, sizing)
        finally:   # after the run has chosen its working pixels; also when it found nothing
            _epipolar_warning(rig, ref, rig_file, sizing)
    wall = time.perf_counter() - t_start
    res = run.result
    hp = highpass * (sizing or {}).get("size_factor", 1.0) * (sizing or {}).get("reduction", 1.0)
    mset = _measurement_set(res, rig.cameras[ref], file_times, (in_names, in_units, in_values), be.name, source,
                            instant_names, ref, hp, rig_file, inputs_path, grid)
    from heartcv.io import file_hash

    if mask_file:   # the other files the measurement depends on (docs/cli.md §1.4 provenance)
        mset.meta["inputs_hash"]["mask"] = file_hash(mask_file)
    if fps is None and (seq / "timestamps.csv").is_file():
        mset.meta["inputs_hash"]["timestamps"] = file_hash(seq / "timestamps.csv")
    if (sizing or {}).get("vertical_offsets_px"):
        mset.meta["rig_vertical_offsets_px"] = dict(sizing["vertical_offsets_px"])
    if (sizing or {}).get("epipolar_px"):
        mset.meta["rig_epipolar_px"] = dict(sizing["epipolar_px"])
    if run.repeated:
        mset.meta["repeated_views"] = {n: [int(grid[0][k]) if grid is not None else int(k)
                                           for k, c in run.repeated if names[c] == n]
                                       for n in names if any(names[c] == n for _, c in run.repeated)}
    if grid is not None:
        sizing = dict(sizing or {}, frame_grid=mset.meta["frame_grid"])
    if csv_file:
        _write_csv(csv_file, mset, res.uv if grid is None else expand_to_grid(res.uv, grid[0], grid[1].size, np.nan),
                   names)
    write_measurements(output, mset)
    overlay = None
    if overlay_dir is not None:
        overlay = _overlay(ctx, overlay_dir, source, rig, run.result, count, ref, times, overlay_video, workers,
                           first_field, instant_names)
    _report(output, run, times, wall, names, "dense" if dense else be.name, truth, ref, as_json, overlay, sizing,
            ref_cam=rig.cameras[ref])


SPARSE_ONLY = {"max_points": "--points", "min_distance": "--min-distance", "corner_block": "--corner-block",
               "corner_quality": "--corner-quality", "fb_max": "--fb-max", "ncc_allowance": "--ncc-allowance",
               "match_ncc_allowance": "--match-ncc-allowance", "min_ncc": "--min-ncc",
               "max_depth_std": "--max-depth-std", "max_reprojection": "--max-reprojection", "min_angle": "--min-angle",
               "max_gap": "--max-gap", "window": "--window", "no_specular": "--no-specular", "backend": "--backend",
               "device": "--device", "highpass": "--highpass", "size_factor": "--size-factor"}
"""The sparse mode's options (parameter name -> option), which --dense does not use (docs/cli.md §10.4)."""


def _refuse_sparse_options(ctx) -> None:
    """Exit 2 for a sparse-mode option given with --dense (accepted and ignored before 2026-11-29)."""
    from click.core import ParameterSource

    given = [flag for name, flag in SPARSE_ONLY.items()
             if ctx.get_parameter_source(name) in (ParameterSource.COMMANDLINE, ParameterSource.ENVIRONMENT)]
    if given:
        raise BadInput(f"--dense: {', '.join(given)} {'applies' if len(given) == 1 else 'apply'} to the sparse mode "
                       "only (the dense mode has its own matcher and gates; docs/cli.md §10.4)")


def _size_factor(value) -> float | None:
    """``--size-factor``: None for auto, else a positive number (exit 2 otherwise)."""
    if str(value).strip().lower() == "auto":
        return None
    try:
        k = float(value)
    except ValueError:
        k = math.nan
    if not (math.isfinite(k) and 0 < k <= 100):
        raise BadInput(f"--size-factor: 'auto' or a number in (0, 100] expected, got {value!r}")
    return k


# -- outputs are guarded before anything is read -------------------------------------------------------------------
def _guard(output, csv_file, inputs, overlay_dir=None):
    """Exit 2 before any work for an output that is not ``.npz``, that equals an input (the existing files inside
    SEQUENCE count as inputs: images, timestamps, inputs, truth), or that would replace a file heartcv did not
    write."""
    if Path(output).suffix.lower() != ".npz":
        raise BadInput(f"-o/--output: a .npz file expected, got {output}")
    outputs = {"-o/--output": output, "--csv": csv_file}
    for label, path in outputs.items():     # not inside the overlay folder, which is written (and replaced) whole
        if path is not None and overlay_dir is not None and Path(os.path.realpath(path)).is_relative_to(
                os.path.realpath(overlay_dir)):
            raise BadInput(f"{label}: {path} lies inside the --overlay folder {overlay_dir}, which measure writes "
                           "as a whole; choose a path outside it")
    if csv_file is not None and Path(csv_file).resolve() == Path(output).resolve():
        raise BadInput(f"--csv: {csv_file} is the -o/--output file; choose another path")
    seq = Path(inputs["SEQUENCE"]).resolve()
    inside = {f"SEQUENCE/{Path(p).resolve().relative_to(seq)}": p for p in outputs.values()
              if p is not None and Path(p).exists() and Path(p).resolve().is_relative_to(seq)}
    guard_outputs(outputs, {**inputs, **inside},
                  files=[("-o/--output", output, ("heartcv.measurements",)), ("--csv", csv_file, ("csv",))])


# -- inputs ------------------------------------------------------------------------------------------------------
def _check_sizes(source, rig, count, rig_file):
    """Exit 2 if a camera's first readable image does not have the rig's image size (the rig does not belong to
    the images), or more than a tenth of its images have another size (image folders)."""
    from heartcv.io import FrameReader
    from heartcv.measure_data import check_image_size_census, check_image_sizes

    def locate(c, k):
        return source.files[c][k if source.kind == "images" else 0]

    with FrameReader(source, frames=range(count), workers=1) as reader:
        if source.packing:
            _check_packed(reader, source, count, locate)
        check_image_sizes(rig.cameras, reader.read, count, locate, f"the rig {rig_file}")
    if source.kind == "images" and not source.packing:
        check_image_size_census(rig.cameras, [fs[:count] for fs in source.files], f"the rig {rig_file}")


def _check_packed(reader, source, count, locate):
    """Exit 2 if the first readable frame of a packed source does not split into the rig's cameras' views."""
    from heartcv.io import unpack_views
    from heartcv.tracker.files import InputError

    for k in range(count):
        frame, _ = reader.read_packed(k)
        if frame is not None:
            try:
                unpack_views(frame, source.packing, source.n_cameras)
            except ValueError as exc:
                raise InputError(locate(0, k), f"{exc} (one per camera of the rig: {list(source.camera_names)})",
                                 "--packed") from None
            return


def _check_rig_scale(rig, rig_file):
    """Exit 2 for a rig whose cameras are farther apart than :data:`heartcv.measure_data.MAX_BASELINE_M` (a rig
    written in millimetres) or share one centre, or whose ``rectified``/``baseline_m`` are wrong."""
    from heartcv.measure_data import check_rectified_meta, check_rig_scale

    check_rig_scale(rig.cameras, rig_file)
    check_rectified_meta(rig, rig_file)


SLOW_FRAME_S = 1.0
"""A median frame interval above this (s) is warned about: no heartbeat's frequency shows below 1 / (2 s)."""


def _frame_times(source, fps, count, ref=0):
    """The frames' times: ``timestamps.csv``, else ``--fps``, else the reference camera's video's own frame times
    where its stated rate does not describe them (:func:`heartcv.measure_data.container_times`), else that rate,
    else :data:`heartcv.measure_data.DEFAULT_FPS` with a warning."""
    import numpy as np

    from heartcv.io import read_timestamps
    from heartcv.measure_data import DEFAULT_FPS, container_times, frame_times

    ts = source.folder / "timestamps.csv"
    if fps is not None and ts.is_file():
        log.warning("--fps %g given: %s is not read (the frames are taken at a constant %g per second)", fps, ts, fps)
    stamps = read_timestamps(ts, source.frame_names) if fps is None and ts.is_file() else None
    if stamps is not None and len(stamps) > 1 and float(np.median(np.diff(stamps))) > SLOW_FRAME_S:
        log.warning("%s: a median frame interval of %.3g s: a heartbeat (at least 0.5 Hz) needs frames under %g s "
                    "apart; are the times in milliseconds? (time_s holds seconds)", ts,
                    float(np.median(np.diff(stamps))), SLOW_FRAME_S)
    if stamps is None and fps is None and source.kind == "video" and source.videos:
        info = source.videos[0 if source.packing else ref]
        stamps = container_times(info.times_s, source.fps, count)
        if stamps is not None:
            log.info("frame times from %s's own presentation times (%s): its frames are not at a constant rate",
                     info.path, f"stated {source.fps:g} fps" if source.fps else "no rate stated")
    if stamps is None and fps is None and source.fps is None:
        log.warning("no timestamps.csv, no video frame rate and no --fps: assuming %g frames per second (the times, "
                    "and every rate fitted from them, scale with it; pass --fps)", DEFAULT_FPS)
    return frame_times(count, timestamps=stamps, fps=fps, video_fps=source.fps)


def _inputs(path: Path, times, required, times_from=None):
    """(names, units, values (K, n)) of an inputs table at the frame times; none without the file."""
    import numpy as np

    from heartcv.io import read_inputs_csv_columns
    from heartcv.measure_data import inputs_at_frames
    from heartcv.tracker.files import InputError

    if not path.is_file():
        if required:
            raise InputError(path, "no such inputs file", "--inputs")
        log.warning("no inputs file (%s): the measurement file has no inputs (heartcv fit will estimate the input "
                    "from the tracks: heart rate, harmonics, rigid motion)", path)
        return (), (), np.zeros((len(times), 0))
    cols, _ = read_inputs_csv_columns(path)
    try:
        return inputs_at_frames(cols, times)
    except InputError as exc:
        where = f" (frame times from {times_from})" if times_from is not None and exc.field == "time_s" else ""
        raise InputError(path, exc.reason + where, exc.field) from None


def _mask(mask_file, size):
    from heartcv.io import read_mask

    return None if mask_file is None else read_mask(mask_file, size)


def _truth(truth_file, count, names, start=0):
    from heartcv.evaluate import TRUTH_FOR_ERRORS
    from heartcv.io import read_render_truth
    from heartcv.measure_data import truth_for_frames
    from heartcv.tracker.files import InputError

    if truth_file is None:
        return None
    arrays, meta = read_render_truth(truth_file, require=TRUTH_FOR_ERRORS, what="the truth error of measure")
    try:
        return truth_for_frames(arrays, meta, count, names, start)
    except InputError as exc:
        raise exc.in_file(truth_file) from None


def _backend(name, device):
    from heartcv.backend import get_backend

    try:
        be = get_backend(name, device)
    except ImportError as exc:
        raise BadInput(f"--backend {name}: {exc}") from None
    if name == "kornia" and str(getattr(be, "device", "cpu")).startswith("cpu"):
        import torch

        torch.set_num_threads(1)     # measured: 2 threads beside the decoding threads are ~9x slower on 2 cores
    return be


def _options(ref, max_points, pixel_sigma, min_distance, corner_block, corner_quality, highpass, *, fb_max=1.0,
             ncc_allowance=0.25, match_ncc_allowance=0.15, min_ncc=None, max_depth_std=0.05, max_reprojection=1.0,
             min_angle=0.0, max_gap=60, window=None, specular=True):
    from heartcv.measure import MeasureOptions

    base = MeasureOptions(ref_camera=ref, max_points=max_points, pixel_sigma=pixel_sigma,
                          min_distance_px=min_distance, corner_block_size=corner_block,
                          corner_quality=corner_quality, highpass_sigma=highpass or None,
                          match_min_ncc=min_ncc, match_ncc_allowance=match_ncc_allowance,
                          track_ncc_allowance=ncc_allowance,
                          max_reprojection_px=max_reprojection, outlier_px=max_reprojection, min_angle_deg=min_angle,
                          max_depth_std_ratio=max_depth_std, max_gap_frames=max_gap, specular=specular,
                          window_px=window, fb_max_px=fb_max, track_min_ncc=min_ncc)
    return base


def _dense_options(ref, pixel_sigma):
    from heartcv.dense import DenseOptions

    return DenseOptions(ref_camera=ref, pixel_sigma=pixel_sigma)


# -- the stage -----------------------------------------------------------------------------------------------------
def _run(ctx, reader, rig, opts, roi, backend, count, sequence, rig_file, dense=False, sizing=None, quiet=False):
    """:func:`heartcv.measure.measure_sequence` (or :func:`heartcv.dense.dense_sequence`) over the reader, with a
    progress bar; its problems as warnings. ``sizing["size_factor"]`` None (sparse mode, ``--size-factor auto``):
    the size factor is 1 and the frames' reduction is chosen here from the reference camera's first frames
    (:func:`heartcv.measure.auto_reduction`), their blur recorded."""
    from dataclasses import replace

    from heartcv.measure import (
        MeasureFailed,
        auto_reduction,
        auto_region,
        field_image,
        measure_sequence,
        reduced_size,
        reference_frames,
    )
    from heartcv.tracker.files import InputError

    verbosity = -1 if quiet else (ctx.find_object(dict) or {}).get("verbosity", 0)

    def region(first):
        """The automatic region of interest (the moving tissue of the first frames), logged."""
        out = auto_region(first, opts)
        log.info("automatic region of interest: %d px (%.0f %% of camera %s); --mask to choose it",
                 out.sum(), 100 * out.mean(), rig.cameras[opts.ref_camera].name)
        return out

    try:
        if dense:
            from heartcv.dense import StereoPair, dense_sequence

            try:
                StereoPair.from_cameras(rig.cameras, opts.ref_camera)
            except ValueError as exc:
                raise InputError(rig_file, f"--dense: {exc}", "cameras") from None
            first = reference_frames(reader.read, count, opts.ref_camera)
            if roi is None:   # as the sparse mode: no points on instruments, highlights or a static background
                roi = region(first)
            field = _choose_field(first, roi, rig.cameras[opts.ref_camera].name, sizing)
            with progress(reader, "measuring (dense)", count, verbosity) as frames:
                run = dense_sequence(frames, rig.cameras, opts, roi=roi, field=field,
                                     drop_repeats=(sizing or {}).get("repeated_frames", "drop") == "drop")
        else:
            ref_cam = rig.cameras[opts.ref_camera]
            sizing = {} if sizing is None else sizing
            auto = sizing.get("size_factor") is None
            first = reference_frames(reader.read, count, opts.ref_camera)
            if roi is None:
                roi = region(first)
            field = _choose_field(first, roi, ref_cam.name, sizing)
            if auto:
                if not first:
                    raise InputError(None, "none of the reference camera's first frames can be read (needed by "
                                           "--size-factor auto)", "images")
                if field is not None:
                    first, roi_w = [field_image(f, field) for f in first], field_image(roi, field)
                else:
                    roi_w = roi
                reduction, blur, reduced_blur = auto_reduction(first, roi_w)
                sizing.update(size_factor=1.0, reduction=reduction,
                              texture_blur_px=blur if math.isfinite(blur) else None)     # None: a flat image
                if reduction > 1.0:
                    sizing["texture_blur_reduced_px"] = reduced_blur
                    w, h = reduced_size(ref_cam.width, ref_cam.height // (1 if field is None else 2), reduction)
                    log.info("texture blur %.2f px (camera %s): tracking on frames reduced %.2fx (%dx%d px, blur "
                             "%.2f px; --size-factor auto); positions in the full frames' pixels",
                             blur, ref_cam.name, reduction, w, h, reduced_blur)
            opts = replace(opts, size_factor=sizing["size_factor"])
            with progress(reader, "measuring", count, verbosity) as frames:
                run = measure_sequence(frames, rig.cameras, opts, roi=roi, backend=backend,
                                       reduction=sizing.get("reduction", 1.0), field=field,
                                       drop_repeats=sizing.get("repeated_frames", "drop") == "drop")
    except InputError as exc:
        raise (exc if exc.path is not None else exc.in_file(sequence)) from None
    except MeasureFailed as exc:   # the images or the rig's cameras: name both
        raise StageFailed(f"{sequence}: {exc} (cameras of {rig_file})") from None
    for k, msg in run.problems:
        log.warning("frame %d: %s; left out", k, msg)
    if run.repeated:
        counts = {c: sum(1 for _, v in run.repeated if v == c) for c in sorted({c for _, c in run.repeated})}
        if sizing is not None:
            sizing["repeated_views"] = {rig.cameras[c].name: n for c, n in counts.items()}
        if not quiet:
            log.warning("%s repeat%s the camera's previous image (no new exposure: a frame-rate conversion, or a "
                        "capture that froze or dropped frames): left out as missing images (--repeated-frames keep "
                        "measures them)", ", ".join(f"{n} of {count} images of camera {rig.cameras[c].name}"
                                                    for c, n in counts.items()),
                        "s" if sum(counts.values()) == 1 else "")
    if run.skipped:
        log.warning("%d of %d frames had fewer than two usable images (missing, unreadable or repeating the previous "
                    "one): all points missing there", len(run.skipped), count)
    empty = [f.frame for f in run.frames if not f.skipped and f.seen == 0]
    if empty and not quiet:
        from heartcv.measure_data import frame_spans

        budget = getattr(opts, "max_points", None)
        log.warning("no point was measured in %d of %d frames (%s): blank, dark, blurred or covered views?%s",
                    len(empty), count, frame_spans(empty),
                    f" (or a budget of --points {budget} too small to keep one in view)"
                    if budget is not None and budget < 20 else "")
    rejected = run.result.rejected
    if rejected:
        log.info("candidates removed per gate: %s", ", ".join(f"{g} {n}" for g, n in rejected.items()))
    return run


def _choose_field(first, roi, camera, sizing):
    """The field to measure (0, 1 or None: the whole frames) for ``sizing["fields"]`` (``--fields``): the reference
    camera's first frames' combing ratio over the region of interest (:func:`heartcv.measure.auto_field`) goes to
    ``sizing["combing_ratio"]``; with ``auto`` frames that look interlaced get their first field, with a warning;
    with ``none`` they get a warning. ``sizing["fields"]`` becomes the field measured (``first``, ``second`` or
    None)."""
    from heartcv.measure import COMBING_RATIO, auto_field

    asked = sizing.get("fields") or "auto"
    if asked == "both":      # the instants are fields already (FieldInstants; _field_order checked the frames)
        return None
    auto, comb = auto_field(first or (), roi)
    comb = comb if math.isfinite(comb) else None
    sizing["combing_ratio"] = comb
    if asked == "auto":
        field = auto
        if field is not None:
            log.warning("camera %s's first frames look interlaced (combing ratio %.2f; progressive video reads below "
                        "%g): measuring the first field of every frame (--fields both for both fields as instants of "
                        "their own, --fields second for the other, --fields none for the whole frames)", camera, comb,
                        COMBING_RATIO)
    else:
        field = {"none": None, "first": 0, "second": 1}[asked]
        if asked == "none" and auto is not None:
            log.warning("camera %s's first frames look interlaced (combing ratio %.2f; progressive video reads "
                        "below %g): their two fields are two instants, which breaks the tracks; measure one field "
                        "with --fields first (or second, or auto)", camera, comb, COMBING_RATIO)
    sizing["fields"] = {None: None, 0: "first", 1: "second"}[field]
    return field


def _field_order(reader, count, ref, roi, asked, camera, sizing) -> int:
    """The field taken first (0 top, 1 bottom) for ``--fields both``: ``--field-order`` top or bottom as given; auto
    from the reference camera's first (up to 30) consecutive frames (:func:`heartcv.measure.field_order`), decided
    when its frames' votes are a majority a binomial sign test finds at the 5 % level, else top with a warning.
    Records ``combing_ratio``, ``field_order`` (and for auto ``field_order_votes``, ``_pairs`` and ``_ratio``) in
    ``sizing``; warns when the frames do not look interlaced."""
    from heartcv.measure import COMBING_RATIO, field_order, field_order_clear, frames_combing_ratio

    frames = [reader.read(k)[0][ref] for k in range(min(count, 30))]
    comb = frames_combing_ratio([f for f in frames if f is not None], roi)
    sizing["combing_ratio"] = comb if math.isfinite(comb) else None
    if not (math.isfinite(comb) and comb > COMBING_RATIO):
        log.warning("--fields both: camera %s's first frames do not look interlaced (combing ratio %s; interlaced "
                    "video reads above %g): their two fields are then one instant, measured twice", camera,
                    f"{comb:.2f}" if math.isfinite(comb) else "undefined", COMBING_RATIO)
    if asked != "auto":
        first = 0 if asked == "top" else 1
    else:
        first, ratio, votes, pairs = field_order(frames, roi)
        sizing.update(field_order_votes=votes, field_order_pairs=pairs,
                      field_order_ratio=ratio if math.isfinite(ratio) else None)
        if not field_order_clear(votes, pairs):
            log.warning("--fields both: the first %d frames do not tell which field was taken first (%d of %d "
                        "votes, ratio %s): assuming the top field (--field-order top|bottom to choose)", len(frames),
                        votes, pairs, f"{ratio:.3g}" if math.isfinite(ratio) else "undefined")
            first = 0
        else:
            log.info("--fields both: the %s field is taken first (%d of %d frames say so; ratio %.3g)",
                     "top" if first == 0 else "bottom", votes, pairs, ratio)
    sizing.update(fields="both", field_order="top first" if first == 0 else "bottom first")
    return first


PROBE_FRAMES = 30
"""Instants measured first, for :func:`_rectified_offsets`: a second at 30 fps, several hundred tracks."""

PROBE_ROUNDS = 6
"""At most this many probes of :func:`_rectified_offsets`. Each moves the rig to the offset it measured; the matching
refines a view's match at most ``match_points``' ``refine_2d_px`` (1 px) off the rig's epipolar line, so an offset of
a few pixels takes a round per pixel or so."""

DESCRIPTOR_FRAMES = 5
"""At most this many instants (spread over the probe's) whose views :func:`_descriptor_matches` matches by SIFT."""

DESCRIPTOR_MATCHES = 500
""":func:`_descriptor_matches` stops reading instants when every camera has this many SIFT matches."""

EPIPOLAR_WARN_PX = 1.0
""":func:`_epipolar_warning` warns where the views' SIFT matches lie farther than this many working pixels (median)
from the rig's epipolar lines: how far off them the matching refines a match (``heartcv.matching.match_points``'
``refine_2d_px``)."""

EPIPOLAR_MIN_MATCHES = 10
"""Fewer SIFT matches than this say nothing in :func:`_epipolar_distances` (a low-texture phantom's pair gives 18)."""

DESCRIPTOR_BIAS_PX = 0.1
"""How far SIFT's pooled vertical offset may lie from the truth (measured: 0.03-0.1 px on shifted noise textures,
+0.06-0.11 px on the in-vivo heart against measure's own tracks, +0.18 px on a soft HD stand-in): ``--dense``, which
has no probe of its own, moves a camera only where the descriptors' offset differs from the rig's by more than this
plus three standard errors (a pair rectified exactly is not moved by SIFT's bias alone)."""

DESCRIPTOR_REACH_PX = 1.0
"""The probes start from the descriptors' offset where it lies farther than this from the rig's: how far off the
rig's epipolar line the matching refines a match (``heartcv.matching.match_points``' ``refine_2d_px``)."""


class _Prefix:
    """The first ``n`` instants of a reader (``read`` and iteration), for a probe run."""

    def __init__(self, reader, n):
        self.reader, self.n = reader, n

    def read(self, k):
        return self.reader.read(k)

    def __iter__(self):
        return ((k, *self.reader.read(k)) for k in range(self.n))


def _descriptor_matches(reader, count, ref, cameras, roi):
    """SIFT matches between the reference camera's views and each other camera's (:func:`heartcv.matching.
    descriptor_matches`), for the rig-free checks (:func:`_rectified_offsets`, :func:`_epipolar_distances`): camera ->
    a list of ``(uv_ref, uv_c)`` per instant, over up to :data:`DESCRIPTOR_FRAMES` instants spread over the first
    :data:`PROBE_FRAMES`, until every camera has :data:`DESCRIPTOR_MATCHES` (a textured HD view has them at once, a
    low-resolution endoscope's take all five)."""
    from heartcv.matching import descriptor_matches

    n = min(count, PROBE_FRAMES)
    out = {c: [] for c in range(cameras) if c != ref}
    for k in np.unique(np.linspace(0, n - 1, DESCRIPTOR_FRAMES).round()):
        views = reader.read(int(k))[0]
        for c in out:
            if views[ref] is not None and views[c] is not None:
                out[c].append(descriptor_matches(views[ref], views[c], roi))
        if all(sum(len(m[0]) for m in out[c]) >= DESCRIPTOR_MATCHES for c in out):
            break
    return out


def _epipolar_distances(matches, rig, ref, rig_file, sizing):
    """Whether the rig describes the cameras that took the views: per camera the median symmetric epipolar distance
    of the SIFT ``matches`` between its views and the reference camera's (:func:`_descriptor_matches`) that agree
    with one epipolar geometry found without the rig (:func:`heartcv.matching.descriptor_inliers`;
    :func:`heartcv.matching.descriptor_epipolar_distance`), in ``sizing["epipolar_px"]`` (camera -> px; None where
    too few matches) and, with the matches' count, ``sizing["_epipolar"]`` for :func:`_epipolar_warning`. And
    whether the rig puts the matches in front of the cameras (:func:`heartcv.matching.descriptor_front_fraction`):
    a warning naming the rig file where fewer than half are (cameras swapped, a baseline the wrong way)."""
    from heartcv.matching import descriptor_epipolar_distance, descriptor_front_fraction, descriptor_inliers

    if not matches:
        return
    sizing["epipolar_px"], sizing["_epipolar"] = {}, {}
    for c, found in matches.items():
        cam = rig.cameras[c]
        m = descriptor_inliers(rig.cameras[ref], cam, found)
        med, n = descriptor_epipolar_distance(rig.cameras[ref], cam, m, min_matches=EPIPOLAR_MIN_MATCHES)
        sizing["epipolar_px"][cam.name] = med if math.isfinite(med) else None
        sizing["_epipolar"][cam.name] = (med, n, len(found))
        front, n_front = descriptor_front_fraction(rig.cameras[ref], cam, m, min_matches=EPIPOLAR_MIN_MATCHES)
        log.debug("epipolar check: %d SIFT matches between cameras %s and %s, median distance %.3g px from the rig's "
                  "epipolar lines, %.0f %% of %d in front of both", n, rig.cameras[ref].name, cam.name, med,
                  100 * front, n_front)
        if math.isfinite(front) and front < 0.5:
            log.warning("%s: the rig puts what cameras %s and %s see behind them: %.0f %% of the %d SIFT features "
                        "matched between their views triangulate in front of both (a rig that describes them: "
                        "nearly all). Are the two cameras swapped (the left one's images under the right one's "
                        "name: rig rectified --names LEFT,RIGHT, the sequence's folder names), or does the rig's "
                        "baseline point the wrong way?", rig_file, rig.cameras[ref].name, cam.name, 100 * front,
                        n_front)


def _epipolar_warning(rig, ref, rig_file, sizing):
    """A warning naming the rig file for each camera whose :func:`_epipolar_distances` exceeds what the matching
    reaches: :data:`EPIPOLAR_WARN_PX` working pixels (the matching searches a point's match along the rig's epipolar
    curve and refines it at most that far off it, in the frames as measured: reduced by ``sizing["reduction"]``, a
    field's rows twice as tall), so such a rig finds few points, and wrong ones. Soft HD video, measured on reduced
    frames, has SIFT matches a pixel apart under a rig that describes it (the in-vivo heart upsampled 3x and blurred:
    0.97 px, reduced 4x), which is why the threshold is in working pixels."""
    scale = sizing.get("reduction", 1.0) * (2.0 if sizing.get("fields") in ("first", "second") else 1.0)
    for name, (med, n, instants) in sizing.pop("_epipolar", {}).items():
        if math.isfinite(med) and med > EPIPOLAR_WARN_PX * scale:
            log.warning("%s: the rig does not describe these cameras: SIFT features matched between camera %s's and "
                        "camera %s's views lie a median %.2f px from the rig's epipolar lines (%d matches that agree "
                        "with one epipolar geometry, on %d of the first instants; a rig that describes them gives a "
                        "fraction of the pixels measured). The matching looks for a point's match along those lines "
                        "and at most %.3g px off them, so it finds few points, and wrong ones. A calibration from "
                        "before the focus or zoom changed, swapped camera names, another rig's file? Recalibrate "
                        "(heartcv calibrate) or check the rig's cameras", rig_file, rig.cameras[ref].name, name, med,
                        n, instants, EPIPOLAR_WARN_PX * scale)


def _rectified_offsets(ctx, reader, rig, opts, roi, backend, count, sequence, rig_file, dense, sizing, ref, matches):
    """``--vertical-offset auto`` for a rectified rig: measure the first :data:`PROBE_FRAMES` instants quietly,
    take each camera's vertical offset from the reference camera's views (:func:`heartcv.measure_data.
    rectified_v_offsets`) and, where it differs from the rig's by more than three standard errors, give that camera
    the principal point that puts its views there (``cy_ref`` + the offset, with the rig's focal lengths;
    :func:`heartcv.measure_data.rectified_cameras`).

    The matching searches around the rig's geometry and refines a match at most a pixel off it, which pulls the
    measured offset towards the rig's: by about a tenth for half a pixel (the in-vivo heart: 0.415 px measured with
    the rig as given, 0.455 with the rig moved by that), to under a pixel for three (0.67 px measured where 2.96 are
    true); several pixels off it finds wrong matches on the rig's rows and no offset at all. So the offset is first
    measured without the rig, from the SIFT ``matches`` of :func:`_descriptor_matches`
    (:func:`heartcv.matching.descriptor_v_offset`), and where that lies more than :data:`DESCRIPTOR_REACH_PX` from
    the rig's, the probes start from it; then the probe is repeated with the moved rig until no camera moves by more
    than three standard errors (at most :data:`PROBE_ROUNDS` probes, a warning if it still moves), and the last
    measurement is used. ``--dense`` has no probe: it takes the descriptors' offset where that differs from the
    rig's by more than :data:`DESCRIPTOR_BIAS_PX` plus three standard errors. Recorded in
    ``sizing["vertical_offsets_px"]``. A probe that fails leaves the rig as the last one that worked (the run that
    follows says why)."""
    from heartcv.camera import Rig
    from heartcv.matching import descriptor_v_offset
    from heartcv.measure_data import rectified_cameras, rectified_v_offsets
    from heartcv.tracker.files import InputError

    n = min(count, PROBE_FRAMES)
    names = [c.name for c in rig.cameras]

    def probe(r):
        logger = logging.getLogger("heartcv")
        level = logger.level
        logger.setLevel(logging.ERROR)
        try:
            run = _run(ctx, _Prefix(reader, n), r, opts, roi, backend, n, sequence, rig_file, dense, dict(sizing),
                       quiet=True)
        except (StageFailed, InputError) as exc:
            logger.setLevel(level)
            log.info("--vertical-offset auto: the first %d instants could not be measured (%s); the rig as %s", n,
                     getattr(exc, "message", exc), "given" if r is rig else "last measured")
            return None
        finally:
            logger.setLevel(level)
        return rectified_v_offsets(run.result.uv, ref)

    cy = [float(np.asarray(c.K)[1, 2]) for c in rig.cameras]
    described = [(0.0, 0.0, 0) if c == ref else descriptor_v_offset(matches[c]) for c in range(len(rig))]
    sizing["vertical_offsets_px"] = {}
    if dense:
        moved = [c for c, (off, se, _) in enumerate(described) if c != ref and math.isfinite(off) and
                 abs(off - (cy[c] - cy[ref])) > 3.0 * se + DESCRIPTOR_BIAS_PX]
        for c, (off, se, found) in enumerate(described):
            if c != ref and math.isfinite(off):
                log.info("rectified pair: SIFT descriptors matched between the views put camera %s's %+.2f ± %.2f px "
                         "below camera %s's (%d matches of %d instants; the rig's %+.2f px): %s", names[c], off, se,
                         names[ref], found, len(matches[c]), cy[c] - cy[ref],
                         "measuring with its principal point there (--vertical-offset none to keep the rig as given)"
                         if c in moved else "the rig as given")
                if c in moved:
                    sizing["vertical_offsets_px"][names[c]] = off
        return Rig(tuple(rectified_cameras(rig.cameras, described, ref, among=moved)[0]), dict(rig.meta)) if moved \
            else rig
    far = [c for c, (off, _, _) in enumerate(described)
           if c != ref and math.isfinite(off) and abs(off - (cy[c] - cy[ref])) > DESCRIPTOR_REACH_PX]
    start = rig
    if far:
        start = Rig(tuple(rectified_cameras(rig.cameras, described, ref, among=far)[0]), dict(rig.meta))
        for c in far:
            log.info("rectified pair: SIFT descriptors matched between the views put camera %s's %+.2f px below "
                     "camera %s's (%d matches), farther than the matching reaches from the rig's %+.2f px: probing "
                     "from there", names[c], described[c][0], names[ref], described[c][2], cy[c] - cy[ref])
    first = probe(start)
    if first is None:
        return rig
    last, current, moved, rounds = first, start, list(far), 1
    for c, (off, se, tracks) in enumerate(first):
        if c != ref and c not in far and math.isfinite(off) and c not in rectified_cameras(rig.cameras, first, ref)[1]:
            log.info("rectified pair: camera %s's views lie %+.3f ± %.3f px below camera %s's (%d tracks of the first "
                     "%d instants), as the rig has them: the rig as given", names[c], off, se, names[ref], tracks, n)
    while True:
        cams, significant = rectified_cameras(current.cameras, last, ref)
        if not significant:
            break
        moved += [c for c in significant if c not in moved]
        if rounds == PROBE_ROUNDS:
            log.warning("rectified pair: the vertical offset still moved by more than three standard errors in the "
                        "last of %d probes (camera %s: %+.3f px): the pair may be rectified several pixels off; "
                        "measuring with the last one (rectify the pair again, or --vertical-offset none for the rig "
                        "as given)", rounds, ", ".join(names[c] for c in significant), last[significant[0]][0])
            break
        current = Rig(tuple(cams), dict(rig.meta))
        m = probe(current)
        if m is None:
            break
        last = [m[c] if math.isfinite(m[c][0]) else last[c] for c in range(len(m))]
        rounds += 1
    if not moved:
        return rig
    for c in moved:
        off, se, tracks = last[c]
        was = f"SIFT descriptors {described[c][0]:+.3f}" if c in far else f"{first[c][0]:+.3f} with the rig as given"
        log.info("rectified pair: camera %s's views lie %+.3f ± %.3f px below camera %s's (%d tracks of the first %d "
                 "instants, %d probes; %s): measuring with its principal point there (--vertical-offset none to keep "
                 "the rig as given)", names[c], off, se, names[ref], tracks, n, rounds, was)
        sizing["vertical_offsets_px"][names[c]] = off
    return Rig(tuple(rectified_cameras(rig.cameras, last, ref, among=moved)[0]), dict(rig.meta))


def _grid(times, stamps):
    """None for equally spaced frame times (to 1e-6); else the uniform grid of frames that jitter or skip
    (:func:`heartcv.measure_data.frame_grid`: ``(index, grid times, interval, offsets)``), logged; exit 2 naming
    the timestamps file for timing too irregular for it."""
    from heartcv.measure_data import frame_grid, uniform_times
    from heartcv.tracker.files import InputError

    if uniform_times(times):
        return None
    try:
        grid = frame_grid(times)
    except ValueError as exc:
        raise InputError(stamps, str(exc), "time_s") from None
    index, grid_times, dt, offset = grid
    missing = grid_times.size - len(times)
    log.warning("the frame times are not equally spaced (%s): the measurement file puts the frames on a uniform grid "
                "of %.6g ms fitted to them (frames at most %.2f of an interval off it)%s", stamps or "frame times",
                1e3 * dt, float(np.abs(offset).max()),
                f", with {missing} missing frame(s) as frames where nothing was seen" if missing else "")
    return grid


def _measurement_set(res, ref_cam, times, inputs, backend, source, frame_names, ref, highpass, rig_file,
                     inputs_path, grid=None):
    from heartcv.io import file_hash
    from heartcv.measure_data import expand_to_grid, reference_pixels
    from heartcv.tracker.measurements import MeasurementSet

    in_names, in_units, in_values = inputs
    names = list(source.camera_names)
    hashes = {"rig": file_hash(rig_file)} | ({"inputs": file_hash(inputs_path)} if in_names else {})
    meta = {"producer": "heartcv measure", "frame_rig": rig_file, "camera_names": names, "ref_camera": names[ref],
            "backend": backend, "sigma_px": res.sigma_px, "sigma_estimated": res.sigma_estimated,
            "reference_frame_index": res.birth_frame.tolist(),
            "reference_uv": reference_pixels(res, ref_cam, ref).tolist(),
            "frame_names": list(frame_names), "highpass_sigma": highpass, "inputs_hash": hashes,
            "sequence": str(source.folder), "start_frame": int(source.start)} \
        | ({"packed": source.packing} if source.packing else {})
    arrays = dict(positions=res.positions, covariances=res.covariances, views=res.views,
                  reprojection_rms=res.reprojection_rms)
    if grid is not None:    # frames on the uniform grid; grid points without a frame hold nothing seen
        index, G = grid[0], grid[1].size
        arrays = {k: expand_to_grid(v, index, G, 0 if k == "views" else np.nan) for k, v in arrays.items()}
        slots = np.full(G, "(missing)", dtype=object)
        slots[index] = list(frame_names)
        meta.update(frame_names=[str(n) for n in slots],
                    reference_frame_index=[int(index[b]) for b in res.birth_frame],
                    frame_grid={"interval_s": grid[2], "frames": int(G), "measured_frames": int(len(index)),
                                "missing_frames": int(G - len(index)),
                                "offset_max_intervals": float(np.abs(grid[3]).max())})
    return MeasurementSet(times=times, point_ids=res.point_ids, reference=res.reference, inputs=in_values,
                          input_names=in_names, input_units=in_units, frame="rig", meta=meta, **arrays)


# -- outputs -------------------------------------------------------------------------------------------------------
def _write_csv(path, mset, uv, names):
    from heartcv.measure_data import measurement_csv_lines
    from heartcv.tracker.files import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(measurement_csv_lines(mset, uv, names)) + "\n", encoding="utf-8")


def _overlay(ctx, folder, source, rig, result, count, ref, times, video, workers, first_field, names):
    """The overlay of ``count`` frames (``names``: the instants' names; both fields of each frame as instants
    when ``first_field`` is not None)."""
    from heartcv.io import FrameReader
    from heartcv.measure import FieldInstants

    from .measure_overlay import write_overlay

    fps = 1.0 / float(np.median(np.diff(times))) if len(times) > 1 else 25.0
    verbosity = (ctx.find_object(dict) or {}).get("verbosity", 0)
    with FrameReader(source, mode="color", sizes=[c.size for c in rig.cameras], frames=range(count),
                     workers=workers) as reader:
        instants = reader if first_field is None else FieldInstants(reader, first_field)
        with progress(instants, "overlay", len(names), verbosity) as frames:
            summary = write_overlay(folder, frames, result, list(source.camera_names), list(names), ref=ref,
                                    fps=fps, video=video)
    announce(log, "wrote the overlay %s", folder)
    return summary


def _report(output, run, times, wall, names, backend, truth, ref, as_json, overlay=None, sizing=None, ref_cam=None):
    from heartcv.measure_data import measurement_summary, truth_statistics

    summary = {"output": str(output), "cameras": names, "backend": backend,
               **measurement_summary(run.result, times, wall, run.wait_s), **(sizing or {})}
    if overlay is not None:
        summary["overlay"] = str(overlay.get("folder"))
    if truth is not None:
        summary.update(truth_statistics(run.result, truth, ref, ref_cam))
    if as_json:
        emit_json(summary)
    else:
        announce(log, "wrote %s: %d frames, %d tracks, %.0f points per frame (min %d), median track %g frames, "
                 "reprojection RMS %.3f px", output, summary["frames"], summary["tracks"], summary["points_mean"],
                 summary["points_min"], summary["track_length_median_frames"], summary["reprojection_rms_px"] or 0)
