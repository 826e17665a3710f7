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

from .options import MAX_COUNT, BadInput, Float, Int, StageFailed, emit_json, guard_outputs, json_opt, progress

log = logging.getLogger(__name__)

PRODUCER = "heartcv calibrate"
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
@json_opt
@click.pass_context
def calibrate(ctx, folder, target_file, output, dist_size, max_view_rms, every, min_views, jobs, as_json):
    """Calibrate the cameras of FOLDER: intrinsics, distortion and cam_from_rig of every camera, in the frame
    of the first camera, from views of the target in TARGET.

    FOLDER holds one sub-folder of images per camera (cam0/, cam1/, ...; the same file name in two folders is
    the same instant) or one video file per camera (frames with the same index are the same instant). Cameras
    are taken in natural name order; the first is the rig frame. Unreadable images, and images whose size
    differs from the rest of their camera, are named in a warning and skipped.

    Exit 1 when the calibration fails: the target is found in no image, a camera has too few usable views
    (the counts per camera are given), or a camera shares no view with the others. Exit 2 for bad input and for
    outputs that would replace an input or something heartcv did not write.
    """
    from heartcv.io import read_target

    out = Path(output)
    exports = _guard(out, folder, target_file)
    spec = read_target(target_file)
    cameras = _find_cameras(Path(folder))
    verbosity = (ctx.find_object(dict) or {}).get("verbosity", 0)
    jobs = jobs or min(os.cpu_count() or 1, 8)
    names = [c[0] for c in cameras]
    detections, sizes, view_names, used_files = _detect_all(cameras, spec, every, jobs, verbosity)
    rig = _calibrate(detections, spec, sizes, names, view_names, int(dist_size), max_view_rms, min_views,
                     target_file)
    rig = type(rig)(rig.cameras, dict(rig.meta, producer=PRODUCER,
                                      inputs_hash=_inputs_hash(target_file, used_files)))
    _summarise(rig, output, _write(out, rig, **exports), as_json)


def _guard(out: Path, folder, target_file) -> dict:
    """The export paths beside the rig file; exit 2, before any work, for a rig file that is not YAML, an output
    that is or contains FOLDER or the target, or one that would replace what heartcv did not write."""
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise BadInput(f"-o/--output: a .yaml file expected, got {out}")
    stem = out.with_suffix("")
    colmap, kalibr = stem.parent / f"{stem.name}_colmap", stem.parent / f"{stem.name}_camchain.yaml"
    labels = {"-o/--output": out, "COLMAP export": colmap, "Kalibr export": kalibr}
    guard_outputs(labels, {"FOLDER": folder, "--target": target_file},
                  files=[("-o/--output", out), ("Kalibr export", kalibr)],
                  folders=[("COLMAP export", colmap, PRODUCER)])
    return {"colmap": colmap, "kalibr": kalibr}


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
    return cams


def _instants(cameras, every):
    """Instant names and, per camera, {instant: path} for image folders (matched by file stem)."""
    from heartcv.io import natural_key

    per_cam = [{p.stem: p for p in paths} for _, _, paths in cameras]
    names = sorted(set().union(*per_cam), key=natural_key)[::every]
    return names, per_cam


def _detect_all(cameras, spec, every, jobs, verbosity):
    """Detections [camera][instant], image sizes (most common per camera), instant names, files used."""
    if cameras[0][1] == "video":
        return _detect_videos(cameras, spec, every, jobs, verbosity)
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


def _detect_videos(cameras, spec, every, jobs, verbosity):
    import cv2

    from heartcv.detect import detect
    from heartcv.tracker.files import InputError

    results, counts = {}, []
    with ThreadPoolExecutor(jobs) as pool:
        for c, (_, _, (path,)) in enumerate(cameras):
            cap = cv2.VideoCapture(str(path))
            if not cap.isOpened():
                raise InputError(path, "cannot open the video (unsupported or corrupt)")
            k, batch = 0, []
            try:
                while True:
                    ok, frame = cap.read()
                    if not ok:
                        break
                    if k % every == 0:
                        size = (frame.shape[1], frame.shape[0])
                        batch.append((k // every, pool.submit(detect, frame, spec), size))
                    k += 1
                    if len(batch) >= 2 * jobs:
                        for v, fut, size in batch:
                            results[c, v] = (size, fut.result())
                        batch = []
                for v, fut, size in batch:
                    results[c, v] = (size, fut.result())
            finally:
                cap.release()
            counts.append(k)
            log.info("%s: %d frames, %d used", path, k, (k + every - 1) // every)
    if len(set(counts)) > 1:
        log.warning("the videos have different frame counts (%s); frames are matched by index",
                    ", ".join(f"{c[0]} {n}" for c, n in zip(cameras, counts)))
    n_views = max(v for _, v in results) + 1 if results else 0
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
def _calibrate(detections, spec, sizes, names, view_names, dist_size, max_view_rms, min_views, target_file):
    from heartcv.calibration import CalibrationError, usable_view
    from heartcv.calibration_rig import calibrate_rig

    if any(s is None for s in sizes):  # a camera without a single readable image
        counts = ", ".join(f"{n} {sum(usable_view(d, spec) for d in dets)}"
                           + (" (no readable image)" if s is None else "")
                           for n, dets, s in zip(names, detections, sizes))
        raise StageFailed(f"calibration failed: too few usable views: {counts} (at least {min_views} per camera "
                          f"needed); no rig file written")
    try:
        return calibrate_rig(detections, spec, sizes, names=names, view_names=view_names, dist_size=dist_size,
                             max_view_rms=max_view_rms, min_views=min_views)
    except CalibrationError as exc:
        raise StageFailed(f"calibration failed with the target {target_file}: {exc}; no rig file written") from None


def _write(out: Path, rig, colmap: Path, kalibr: Path) -> dict:
    """Exports first, the rig file last (its presence marks a complete run); returns the exports written. A
    camchain left by an earlier run (heartcv's: the outputs were guarded) is removed when Kalibr cannot hold the
    new rig, so it never contradicts it."""
    from heartcv.calibration_rig import kalibr_limitation
    from heartcv.io import write_colmap, write_kalibr, write_rig
    from heartcv.tracker.files import atomic_folder, is_heartcv_file

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
            kalibr.unlink()
    write_rig(out, rig)
    return exports


def _summarise(rig, output, exports, as_json):
    meta = rig.meta
    cams = []
    for c in rig.cameras:
        m = meta["cameras"][c.name]
        cams.append({"name": c.name, "rms_px": m["rms_px"], "fx": c.K[0, 0], "fy": c.K[1, 1], "cx": c.K[0, 2],
                     "cy": c.K[1, 2], "views_used": m["views_used"], "views_rejected": len(m["rejected_views"]),
                     "image_size": [c.width, c.height], "dist": c.dist.tolist()})
    summary = {"rms_px": meta["rms_px"], "cameras": cams, "baselines_m": meta["baselines_m"],
               "views": len(meta["view_names"]), "views_used": meta["views_used"], "dist_model": meta["dist_model"],
               "target": meta["target"]["name"], "output": output, "exports": exports}
    if as_json:
        emit_json(summary)
    else:
        base = ", ".join(f"{k} {v * 1e3:.2f} mm" for k, v in meta["baselines_m"].items())
        log.info("wrote %s: %d cameras, RMS %.3f px, baselines %s", output, len(cams), meta["rms_px"], base)
