"""``heartcv calibrate``: calibrate a camera rig from views of a calibration target.

Outputs (guarded before any work): the rig file, its COLMAP export folder ``STEM_colmap/`` (written with
:func:`heartcv.tracker.files.atomic_folder`, producer ``heartcv calibrate``) and its Kalibr camchain
``STEM_camchain.yaml``; none may be or contain FOLDER or the target file, or replace what heartcv did not write.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import hashlib
import logging
import os
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
    progress,
)

log = logging.getLogger(__name__)

PRODUCER = "heartcv calibrate"
REPORT_PRODUCER = "heartcv calibrate --report"
MAX_JOBS = 1024


@click.command()
@click.argument("folder", type=click.Path(file_okay=False))
@click.option("--target", "target_file", type=click.Path(dir_okay=False), required=True,
              help="Target file (YAML, from `heartcv target`).")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True,
              help="Rig file (.yaml); exports are written beside it: STEM_colmap/ and STEM_camchain.yaml.")
@click.option("--dist", "dist_size", type=click.Choice(("4", "5", "8")), default="5", show_default=True,
              help="Distortion model: 5 = k1 k2 p1 p2 k3, 8 = + rational k4 k5 k6, 4 = k1 k2 p1 p2 (k3 = 0; the "
                   "model Kalibr's camchain can hold).")
@click.option("--max-view-rms", type=Float(0, 1000, lo_open=True), default=None, metavar="PX",
              help="Reject camera views whose reprojection RMS exceeds PX pixels (besides the relative rule: "
                   "3 x the camera's median view RMS, never below 0.25 px).")
@click.option("--every", type=Int(1, MAX_COUNT), default=1, show_default=True,
              help="Use every n-th instant (image name or video frame).")
@click.option("--min-views", type=Int(3, MAX_COUNT), default=4, show_default=True,
              help="Usable views needed per camera.")
@click.option("--jobs", type=Int(1, MAX_JOBS), default=None,
              help="Detection threads (default: the number of CPUs, at most 8).")
@click.option("--intrinsics", "intrinsics_file", type=click.Path(dir_okay=False), default=None, metavar="RIG.yaml",
              help="Intrinsics of an earlier or imported calibration (`heartcv rig import`): the start of the cameras "
                   "it names (matched by name), or kept with --hold.")
@click.option("--hold", default=None, metavar="all|CAM,...",
              help="Keep the --intrinsics of these cameras (all: every camera): only poses are estimated.")
@click.option("--timestamps", "timestamps_file", type=click.Path(dir_okay=False), default=None, metavar="CSV",
              help="Per-camera frame times of unsynchronised cameras (default: FOLDER/timestamps.csv when present; "
                   "else the cameras are taken as synchronised).")
@click.option("--intrinsic-views", "intrinsic_folder", type=click.Path(file_okay=False), default=None,
              metavar="DIR", help="Recordings seen by one camera each (DIR/CAM/ images or DIR/CAM.mp4, named like "
                                  "the cameras): used for that camera's intrinsics.")
@click.option("--packed", type=click.Choice(("side-by-side", "top-bottom", "rows")), default=None,
              help="FOLDER holds one video or one folder of images whose every frame packs the views of all the "
                   "cameras (side by side, top to bottom, or in interleaved rows); named by --packed-cameras.")
@click.option("--packed-cameras", default="cam0,cam1", show_default=True, metavar="NAME,NAME[,...]",
              help="With --packed: the cameras' names, one per view in packing order (left to right, top to bottom, "
                   "the first row's field first).")
@click.option("--folds", type=Int(0, 100), default=5, show_default=True,
              help="k of the k-fold check of the uncertainties (below 3: none).")
@click.option("--report", "report_dir", type=click.Path(file_okay=False), default=None, metavar="DIR",
              help="Write a calibration report (PNGs + index.html) to DIR.")
@json_opt
@click.pass_context
def calibrate(ctx, folder, target_file, output, dist_size, max_view_rms, every, min_views, jobs, intrinsics_file,
              hold, timestamps_file, intrinsic_folder, packed, packed_cameras, folds, report_dir, as_json):
    """Calibrate the cameras of FOLDER: intrinsics, distortion and cam_from_rig of every camera, in the frame
    of the first camera, from views of the target in TARGET.

    FOLDER holds one sub-folder of images per camera (cam0/, cam1/, ...; the same file name in two folders is
    the same instant) or one video file per camera (frames with the same index are the same instant); with
    --packed, one video or folder of images whose frames hold all the views. Cameras are taken in natural name
    order (--packed: in packing order); the first is the rig frame. Unreadable images, and a few images whose
    size differs from the rest of their camera, are named in a warning and skipped (more than 10 % of another
    size: exit 2).

    Exit 1 when the calibration fails: the target is found in no image, a camera has too few usable views
    (the counts per camera are given), or a camera shares no view with the others. Exit 2 for bad input and for
    outputs that would replace an input or something heartcv did not write.
    """
    from heartcv.io import read_target

    out = Path(output)
    inputs = {"--intrinsics": intrinsics_file, "--timestamps": timestamps_file,
              "--intrinsic-views": intrinsic_folder}
    exports = _guard(out, folder, target_file, {k: v for k, v in inputs.items() if v}, report_dir)
    spec = read_target(target_file)
    packing = _packing(packed, packed_cameras, timestamps_file)
    cameras = _find_cameras(Path(folder)) if packing is None else _find_packed(Path(folder), packing)
    if packing is None and timestamps_file and cameras[0][1] != "video":   # before any detection
        raise BadInput(f"--timestamps: {timestamps_file}: per-camera frame times apply to video input (image folders "
                       "are matched by file name)")
    names = [c[0] for c in cameras]
    given, held, given_sizes = _given_intrinsics(intrinsics_file, hold, names)
    extra = _find_intrinsic_views(intrinsic_folder, names)
    infos = _check_videos((cameras[:1] if packing else cameras) + [e for e in extra if e[1] == "video"])
    verbosity = (ctx.find_object(dict) or {}).get("verbosity", 0)
    jobs = jobs or min(os.cpu_count() or 1, 8)
    if packing is None:
        detections, sizes, view_names, used_files = _detect_all(cameras, spec, every, jobs, verbosity, infos)
        times = _frame_times(timestamps_file, Path(folder), cameras, infos, every, len(view_names))
    else:
        detections, sizes, view_names, used_files = _detect_packed(cameras, packing[0], spec, every, jobs,
                                                                   verbosity, infos)
        times = None                                      # the views of one frame are simultaneous
    if extra:
        detections, view_names, more = _append_intrinsic_views(detections, view_names, extra, names, spec, jobs,
                                                               verbosity, infos)
        used_files = sorted(set(used_files) | set(more))
        if times is not None:
            import numpy as np

            times = np.concatenate([times, np.full((len(names), len(view_names) - times.shape[1]), np.nan)], 1)
    _check_given_sizes(intrinsics_file, names, given_sizes, sizes)
    cal = _calibrate(detections, spec, sizes, names, view_names, int(dist_size), max_view_rms, min_views,
                     target_file, given=given, hold=held, times=times, folds=folds)
    from heartcv.rig_formats import side_warnings

    rig = cal.rig
    rig = type(rig)(rig.cameras, dict(rig.meta, producer=PRODUCER,
                                      inputs_hash=_inputs_hash(target_file, used_files),
                                      warnings=list(rig.meta["warnings"]) + [
                                          f"{msg.split(' (in ')[0]}: are the camera folders swapped (the left "
                                          "camera's images in the folder named right)?"
                                          for msg in side_warnings(rig)]))
    for msg in rig.meta["warnings"]:
        log.warning("%s", msg)
    written = _write(out, rig, **exports)
    if report_dir:
        from .calibration_report import write_calibration_report

        cal = type(cal)(rig, cal.rig_from_board, cal.used, cal.view_rms)
        written["report"] = str(write_calibration_report(Path(report_dir), cal, detections, spec,
                                                         title=f"heartcv calibrate: {out.name}",
                                                         warnings=rig.meta["warnings"]).get("index", report_dir))
    _summarise(rig, output, written, as_json)


def _guard(out: Path, folder, target_file, more_inputs=None, report_dir=None) -> dict:
    """The export paths beside the rig file; exit 2, before any work, for a rig file that is not YAML, an output
    that is or contains an input, or one that would replace what heartcv did not write."""
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise BadInput(f"-o/--output: a .yaml file expected, got {out}")
    stem = out.with_suffix("")
    colmap, kalibr = stem.parent / f"{stem.name}_colmap", stem.parent / f"{stem.name}_camchain.yaml"
    labels = {"-o/--output": out, "COLMAP export": colmap, "Kalibr export": kalibr}
    folders = [("COLMAP export", colmap, PRODUCER)]
    if report_dir:
        labels["--report"] = Path(report_dir)
        folders.append(("--report", Path(report_dir), REPORT_PRODUCER))
    guard_outputs(labels, {"FOLDER": folder, "--target": target_file, **(more_inputs or {})},
                  files=[("-o/--output", out, ("heartcv.rig",)), ("Kalibr export", kalibr, ("yaml",))],
                  folders=folders)
    return {"colmap": colmap, "kalibr": kalibr}


def _given_intrinsics(path, hold, names):
    """Per camera (K, dist) from --intrinsics (matched by name) or None, the held mask, and per camera the image
    size those intrinsics are of (or None); exit 2 for a --hold without --intrinsics, or naming a camera that is not
    in FOLDER or not in the file."""
    held = [False] * len(names)
    if path is None:
        if hold:
            raise BadInput("--hold needs --intrinsics (the values to keep)")
        return [None] * len(names), held, [None] * len(names)
    from heartcv.io import read_rig

    rig = read_rig(path)
    given = [(rig[n].K, rig[n].dist) if n in rig.names else None for n in names]
    missing = [n for n, g in zip(names, given) if g is None]
    if len(missing) == len(names):
        raise BadInput(f"--intrinsics: {path} names none of the cameras of FOLDER ({', '.join(names)}; the file has "
                       f"{', '.join(rig.names)}); name the videos or folders like the file's cameras")
    if missing:
        log.warning("--intrinsics: %s has no camera named %s: calibrated from the views", path, ", ".join(missing))
    if hold:
        want = names if hold.strip().lower() == "all" else [h.strip() for h in hold.split(",") if h.strip()]
        unknown = [h for h in want if h not in names]
        if unknown:
            raise BadInput(f"--hold: no camera named {', '.join(unknown)} in FOLDER ({', '.join(names)})")
        lacking = [h for h in want if given[names.index(h)] is None]
        if lacking and hold.strip().lower() != "all":
            raise BadInput(f"--hold: {path} has no intrinsics for {', '.join(lacking)}")
        held = [n in want and given[i] is not None for i, n in enumerate(names)]
    for i, n in enumerate(names):
        if given[i] is not None:
            cam = rig[n]
            log.info("%s: intrinsics from %s (fx %.1f px)%s", n, path, cam.K[0, 0], ", held" if held[i] else "")
    return given, held, [tuple(rig[n].size) if g is not None else None for n, g in zip(names, given, strict=True)]


def _check_given_sizes(path, names, given_sizes, sizes):
    """Exit 2 where --intrinsics gives a camera intrinsics of another image size than its views' (pixels of other
    images: a focal length and principal point off by the ratio)."""
    for n, g, size in zip(names, given_sizes, sizes, strict=True):
        if g is not None and size is not None and tuple(g) != tuple(size):
            raise BadInput(f"--intrinsics: {path}: camera {n} is {g[0]}x{g[1]} px, but its views "
                           f"in FOLDER are {size[0]}x{size[1]}: these intrinsics are of other images (another "
                           "resolution or crop); calibrate without --intrinsics or give the intrinsics of these "
                           "images")


def _check_videos(cameras):
    """Probe every video of the cameras before any processing (exit 2 naming a truncated or corrupt one);
    {path: VideoInfo}."""
    from heartcv.video import check_videos

    paths = [c[2][0] for c in cameras if c[1] == "video"]
    if not paths:
        return {}
    infos = check_videos(paths)
    for info in infos:
        log.info("%s: %d frames, %dx%d%s", info.path, info.n_frames, info.width, info.height,
                 f", {info.fps:g} fps" if info.fps else "")
    return {str(i.path): i for i in infos}


def _frame_times(timestamps_file, folder, cameras, infos, every, n_views):
    """Per-camera frame times (n_cam, n_views) of the instants used, or None (cameras taken as synchronised):
    --timestamps, else FOLDER/timestamps.csv, else none (a video's own timestamps count only from its start, so
    they cannot tell the cameras apart)."""
    import numpy as np

    from heartcv.video import read_camera_times

    path = Path(timestamps_file) if timestamps_file else folder / "timestamps.csv"
    if not path.is_file():
        if timestamps_file:
            from heartcv.tracker.files import InputError

            raise InputError(path, "no such file", "--timestamps")
        return None
    if cameras[0][1] != "video":
        raise BadInput(f"--timestamps: {path}: per-camera frame times apply to video input (image folders are "
                       "matched by file name)")
    names = [c[0] for c in cameras]
    counts = [infos[str(c[2][0])].n_frames for c in cameras]
    t = read_camera_times(path, names, counts)
    times = np.full((len(names), n_views), np.nan)
    for i, n in enumerate(names):
        sel = np.asarray(t[n], float)[::every][:n_views]
        times[i, :sel.size] = sel
    log.info("frame times from %s: cameras up to %.1f ms apart at one instant", path,
             1e3 * float(np.nanmax(np.nanmax(times, 0) - np.nanmin(times, 0))))
    return times


def _find_intrinsic_views(folder, names):
    """[(camera name, kind, paths)] of --intrinsic-views DIR: DIR/CAM/ (images) or DIR/CAM.<video>."""
    if folder is None:
        return []
    from heartcv.io import camera_entries
    from heartcv.tracker.files import InputError

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "no such folder" if not folder.exists() else "not a folder", "--intrinsic-views")
    images, videos = camera_entries(folder)
    out = [(n, "images", fs) for n, fs in images] + [(v.stem, "video", [v]) for v in videos]
    unknown = [e[0] for e in out if e[0] not in names]
    if unknown:
        raise InputError(folder, f"recordings named {', '.join(unknown)}, but the cameras are {', '.join(names)}",
                         "--intrinsic-views")
    if not out:
        raise InputError(folder, "no image folder or video found", "--intrinsic-views")
    return out


def _append_intrinsic_views(detections, view_names, extra, names, spec, jobs, verbosity, infos):
    """Detections of the intrinsic recordings appended as views seen by one camera each."""
    dets = [list(d) for d in detections]
    view_names = list(view_names)
    files = []
    for name, kind, paths in extra:
        c = names.index(name)
        found, _, vnames, used = _detect_all([(name, kind, paths)], spec, 1, jobs, verbosity, infos)
        for v, d in enumerate(found[0]):
            for k in range(len(dets)):
                dets[k].append(d if k == c else None)
            view_names.append(f"{name}:intrinsics/{vnames[v]}")
        files += used
        log.info("%s: %d intrinsic views", name, sum(d is not None and len(d) > 0 for d in found[0]))
    return dets, view_names, files


# -- inputs -----------------------------------------------------------------------------------------------------
def _find_cameras(folder: Path):
    """[(name, kind, paths)]: kind 'images' (paths: image files) or 'video' (paths: [video file])."""
    from heartcv.io import camera_entries
    from heartcv.tracker.files import InputError

    if not folder.is_dir():
        raise InputError(folder, "no such folder" if not folder.exists() else "not a folder", "FOLDER")
    images, videos = camera_entries(folder)
    found = {name for name, _ in images}
    for d in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        if d.name not in found:
            log.warning("%s: no images, not a camera", d)
    cams = [(v.stem, "video", [v]) for v in videos] if videos else [(n, "images", fs) for n, fs in images]
    if len(cams) < 2:
        raise InputError(folder, f"{len(cams)} camera(s) found; at least 2 expected (one sub-folder of images or "
                                 "one video file per camera)", "FOLDER")
    names = [c[0] for c in cams]
    if len(set(names)) != len(names) or any(any(ch.isspace() for ch in n) for n in names):
        raise InputError(folder, f"camera names must be unique and without spaces, got {names}", "FOLDER")
    if not videos:   # image folders are paired by file stem (or frame number): unpaired cameras refused now
        from heartcv.io import pair_instants

        try:
            _, _, by = pair_instants(names, [fs for _, _, fs in cams])
        except ValueError as exc:
            raise InputError(folder, str(exc), "FOLDER") from None
        if by == "number":
            log.info("%s: the cameras' files share no name; views paired by the last number in the names", folder)
        for name, _, fs in cams:
            _check_size_census(name, fs)
    return cams


def _check_size_census(name, files) -> None:
    """A camera's images in more than one size, the others more than :data:`OTHER_SIZE_FRACTION` of them (at
    least 2): exit 2 before any detection (intrinsics hold for one image size; the folder mixes recordings). Fewer
    are skipped image by image, with a warning each. Unreadable headers are left to the detection, which names
    them."""
    from collections import Counter

    from PIL import Image

    from heartcv.measure_data import OTHER_SIZE_FRACTION
    from heartcv.tracker.files import InputError

    sizes = {}
    for f in files:
        try:
            with Image.open(f) as im:
                sizes[f] = tuple(im.size)
        except Exception:       # noqa: BLE001 -- unreadable: named when it is read for detection
            continue
    counts = Counter(sizes.values())
    if len(counts) < 2:
        return
    (main, n_main), *_ = counts.most_common()
    others = sum(counts.values()) - n_main
    if others >= 2 and others > OTHER_SIZE_FRACTION * sum(counts.values()):
        first = next(f for f, s in sizes.items() if s != main)
        shown = ", ".join(f"{w}x{h} ({n})" for (w, h), n in counts.most_common())
        raise InputError(first, f"camera {name}'s {sum(counts.values())} images come in sizes {shown}; more than "
                                f"{OTHER_SIZE_FRACTION:.0%} of another size is not a few bad images: a calibration "
                                "holds for one image size (the folder mixes recordings; give each its own)",
                         "images")


def _packing(packed, packed_cameras, timestamps_file):
    """(layout, camera names) of --packed, or None; exit 2 for bad names or --timestamps with --packed."""
    if packed is None:
        return None
    names = [n.strip() for n in str(packed_cameras).split(",")]
    if len(names) < 2 or len(set(names)) != len(names) or any(not n or any(ch.isspace() for ch in n) for n in names):
        raise BadInput(f"--packed-cameras: at least 2 unique names without spaces, separated by commas, expected; "
                       f"got {packed_cameras!r}")
    if timestamps_file:
        raise BadInput("--timestamps: the views of a --packed frame are simultaneous; per-camera frame times apply "
                       "to one video per camera")
    return packed, names


def _find_packed(folder: Path, packing):
    """[(name, kind, paths)] of a packed FOLDER: every camera of ``packing``'s names with the one source's files
    (heartcv.io.open_frame_source, packed)."""
    from heartcv.io import open_frame_source, read_image, unpack_views
    from heartcv.tracker.files import InputError

    if not folder.is_dir():
        raise InputError(folder, "no such folder" if not folder.exists() else "not a folder", "FOLDER")
    layout, names = packing
    src = open_frame_source(folder, cameras=names, packing=layout)
    if src.kind == "video":
        return [(n, "video", [src.files[0][0]]) for n in names]
    for path in src.files[0]:                           # the first readable image must split into the views
        try:
            frame = read_image(path, mode="unchanged")
        except InputError:
            continue                                    # skipped later, with a warning naming it
        try:
            unpack_views(frame, layout, len(names))
        except ValueError as exc:
            raise _packed_error(path, exc) from None
        break
    return [(n, "images", list(src.files[0])) for n in names]


def _read_and_detect_packed(path, layout, n, spec):
    """[(size, Detection)] of the views of a packed image file, or [(None, message)] * n where it cannot be read
    or split."""
    from heartcv.io import read_image, unpack_views
    from heartcv.tracker.files import InputError

    try:
        views = unpack_views(read_image(path, mode="unchanged"), layout, n)
    except (InputError, ValueError) as exc:  # skipped with a warning naming it
        return [(None, f"{path}: {exc}" if isinstance(exc, ValueError) else str(exc))] * n
    return [_detect_view(v, spec) for v in views]


def _detect_view(view, spec):
    from heartcv.detect import detect

    return (view.shape[1], view.shape[0]), detect(view, spec)


def _detect_packed(cameras, layout, spec, every, jobs, verbosity, infos=None):
    """:func:`_detect_all` of one packed source whose frames hold every camera's view."""
    from heartcv.io import sort_names, unpack_views
    from heartcv.video import iter_frames

    n, (_, kind, paths) = len(cameras), cameras[0]
    results, files = {}, {}
    if kind == "images":
        ordered = sort_names(paths, stem=lambda p: p.stem)[::every]
        names = [p.stem for p in ordered]
        with ThreadPoolExecutor(jobs) as pool:
            done = pool.map(_read_and_detect_packed, ordered, [layout] * len(ordered), [n] * len(ordered),
                            [spec] * len(ordered))
            with progress(done, "detecting", len(ordered), verbosity) as it:
                for v, res in enumerate(it):
                    for c in range(n):
                        results[c, v], files[c, v] = res[c], ordered[v]
    else:
        path = paths[0]
        info = (infos or {}).get(str(path))
        total = None if info is None else -(-info.n_frames // every)
        with ThreadPoolExecutor(jobs) as pool:
            def detected():
                pending = []
                for k, frame in iter_frames(path, every):
                    try:
                        views = unpack_views(frame, layout, n)
                    except ValueError as exc:
                        raise _packed_error(path, exc) from None
                    pending.append((k // every, [pool.submit(_detect_view, v, spec) for v in views]))
                    if len(pending) >= 2 * jobs:
                        v, futs = pending.pop(0)
                        yield v, [f.result() for f in futs]
                for v, futs in pending:
                    yield v, [f.result() for f in futs]

            with progress(detected(), "detecting", total, verbosity) as it:
                for v, res in it:
                    for c in range(n):
                        results[c, v], files[c, v] = res[c], path
        names = [f"frame{v * every:06d}" for v in range(max((v for _, v in results), default=-1) + 1)]
    return _assemble(cameras, names, results, files)


def _packed_error(path, exc):
    from heartcv.tracker.files import InputError

    return InputError(path, str(exc), "--packed")


def _instants(cameras, every):
    """Instant names and, per camera, {instant: path} for image folders (matched by file stem, else by frame
    number: :func:`heartcv.io.pair_instants`)."""
    from heartcv.io import pair_instants

    names, per_cam, _ = pair_instants([c[0] for c in cameras], [paths for _, _, paths in cameras])
    return names[::every], per_cam


def _detect_all(cameras, spec, every, jobs, verbosity, infos=None):
    """Detections [camera][instant], image sizes (most common per camera), instant names, files used."""
    if cameras[0][1] == "video":
        return _detect_videos(cameras, spec, every, jobs, verbosity, infos)
    names, per_cam = _instants(cameras, every)
    tasks = [(c, v, per_cam[c].get(n)) for c in range(len(cameras)) for v, n in enumerate(names)]
    tasks = [t for t in tasks if t[2] is not None]
    paths = {(c, v): p for c, v, p in tasks}
    results = {}
    with ThreadPoolExecutor(jobs) as pool:
        done = pool.map(_read_and_detect, [t[2] for t in tasks], [spec] * len(tasks))
        with progress(done, "detecting", len(tasks), verbosity) as it:
            for (c, v, _), res in zip(tasks, it):
                results[c, v] = res
    return _assemble(cameras, names, results, paths)


def _read_and_detect(path, spec):
    """(size, Detection) of an image file, or (None, error message) if it cannot be read."""
    from heartcv.detect import detect
    from heartcv.io import read_image
    from heartcv.tracker.files import InputError

    try:
        img = read_image(path, mode="unchanged")
    except InputError as exc:  # an unreadable image is skipped with a warning naming it
        return None, str(exc)
    return (img.shape[1], img.shape[0]), detect(img, spec)


def _detect_videos(cameras, spec, every, jobs, verbosity, infos=None):
    """Detections in every ``every``-th frame of each camera's video (probed before: :func:`_check_videos`, whose
    frame counts size the progress bar). At most ``2 jobs`` decoded frames wait for detection at a time."""
    from heartcv.detect import detect
    from heartcv.video import iter_frames

    def detected(pool, path):
        pending = []
        for k, frame in iter_frames(path, every):
            pending.append((k // every, (frame.shape[1], frame.shape[0]), pool.submit(detect, frame, spec)))
            if len(pending) >= 2 * jobs:
                v, size, fut = pending.pop(0)
                yield v, size, fut.result()
        for v, size, fut in pending:
            yield v, size, fut.result()

    results = {}
    with ThreadPoolExecutor(jobs) as pool:
        for c, (name, _, (path,)) in enumerate(cameras):
            info = (infos or {}).get(str(path))
            n = None if info is None else -(-info.n_frames // every)
            found = used = 0
            with progress(detected(pool, path), f"detecting {name}", n, verbosity) as it:
                for v, size, det in it:
                    results[c, v] = (size, det)
                    found, used = found + (len(det) > 0), used + 1
            log.info("%s: target found in %d of %d frames used", name, found, used)
    n_views = max(v for _, v in results) + 1 if results else 0
    per_cam = [sum(1 for cc, _ in results if cc == c) for c in range(len(cameras))]
    if len(set(per_cam)) > 1:
        log.warning("the videos have different frame counts (%s); frames are matched by index",
                    ", ".join(f"{c[0]} {n}" for c, n in zip(cameras, per_cam)))
    names = [f"frame{v * every:06d}" for v in range(n_views)]
    paths = {(c, v): cameras[c][2][0] for c, v in results}
    return _assemble(cameras, names, results, paths)


def _assemble(cameras, names, results, paths):
    """:func:`heartcv.calibration.select_views` with its warnings logged: detections [camera][instant], camera
    sizes, instant names and the files used (for the inputs' hash)."""
    from heartcv.calibration import select_views

    sel = select_views(results, [c[0] for c in cameras], names)
    for msg in sel.warnings:
        log.warning("%s", msg)
    for (cam, _, _), (n, found) in zip(cameras, sel.counts):
        log.info("%s: %d images, target found in %d", cam, n, found)
    return sel.detections, sel.sizes, names, sorted({paths[key] for key in sel.used})


def _inputs_hash(target_file, files):
    from heartcv.io import file_hash

    h = hashlib.sha256()
    for p in files:
        h.update(f"{Path(p).parent.name}/{Path(p).name}:{file_hash(p)}\n".encode())
    return {"target": file_hash(target_file), "images": "sha256:" + h.hexdigest()}


# -- calibration and outputs ------------------------------------------------------------------------------------
def _calibrate(detections, spec, sizes, names, view_names, dist_size, max_view_rms, min_views, target_file, *,
               given, hold, times, folds):
    from heartcv.calibration import CalibrationError, usable_view
    from heartcv.calibration_rig import calibrate_rig_detailed

    if any(s is None for s in sizes):  # a camera without a single readable image
        counts = ", ".join(f"{n} {sum(usable_view(d, spec) for d in dets)}"
                           + (" (no readable image)" if s is None else "")
                           for n, dets, s in zip(names, detections, sizes))
        raise StageFailed(f"calibration failed: too few usable views: {counts} (at least {min_views} per camera "
                          f"needed); no rig file written")
    try:
        return calibrate_rig_detailed(detections, spec, sizes, names=names, view_names=view_names,
                                      dist_size=dist_size, max_view_rms=max_view_rms, min_views=min_views,
                                      given=given, hold=hold, times=times, folds=folds,
                                      progress=lambda msg: log.info("%s", msg))
    except CalibrationError as exc:
        raise StageFailed(f"calibration failed with the target {target_file}: {exc}; no rig file written") from None


def _write(out: Path, rig, colmap: Path, kalibr: Path) -> dict:
    """Exports first, the rig file last (its presence marks a complete run); returns the exports written. A
    camchain left by an earlier run (heartcv's: the outputs were guarded) is removed when Kalibr cannot hold the
    new rig, so it never contradicts it."""
    from heartcv.calibration_rig import kalibr_limitation
    from heartcv.io import write_colmap, write_kalibr, write_rig
    from heartcv.tracker.files import atomic_folder, is_heartcv_file, remove_output

    with atomic_folder(colmap, PRODUCER, {"rig_file": out.name}) as tmp:
        write_colmap(tmp, rig)
    exports = {"colmap": str(colmap), "kalibr": None}
    why = kalibr_limitation(rig)
    if why is None:
        write_kalibr(kalibr, rig)
        exports["kalibr"] = str(kalibr)
    else:
        log.warning("no Kalibr camchain written: %s", why)
        exports["kalibr_skipped"] = why
        if kalibr.is_file() and is_heartcv_file(kalibr):
            remove_output(kalibr)       # with the renames: an interrupted run keeps it
    write_rig(out, rig)
    return exports


def _summarise(rig, output, exports, as_json):
    meta = rig.meta
    cams = []
    for c in rig.cameras:
        m = meta["cameras"][c.name]
        cams.append({"name": c.name, "rms_px": m["rms_px"], "fx": c.K[0, 0], "fy": c.K[1, 1], "cx": c.K[0, 2],
                     "cy": c.K[1, 2], "views_used": m["views_used"], "views_rejected": len(m["rejected_views"]),
                     "image_size": [c.width, c.height], "dist": c.dist.tolist(), "std": m["std"],
                     "coverage": m.get("coverage"), "heldout_rms_px": m.get("heldout_rms_px"),
                     "intrinsics": m.get("intrinsics")})
    summary = {"rms_px": meta["rms_px"], "heldout_rms_px": meta.get("heldout_rms_px"),
               "warnings": meta.get("warnings", []), "sync": meta.get("sync"),
               "cameras": cams, "baselines_m": meta["baselines_m"],
               "views": len(meta["view_names"]), "views_used": meta["views_used"], "dist_model": meta["dist_model"],
               "target": meta["target"]["name"], "output": output, "exports": exports}
    if as_json:
        emit_json(summary)
    else:
        base = ", ".join(f"{k} {v * 1e3:.2f} mm" for k, v in meta["baselines_m"].items())
        announce(log, "wrote %s: %d cameras, RMS %.3f px, baselines %s", output, len(cams), meta["rms_px"], base)
