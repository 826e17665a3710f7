"""``heartcv calibrate``: calibrate a camera rig from views of a calibration target."""

from __future__ import annotations

import hashlib
import logging
import os
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import click


from .options import BadInput, StageFailed, emit_json, json_opt, progress

log = logging.getLogger(__name__)


def _positive_float(ctx, param, value):
    if value is not None and not value > 0:
        raise click.BadParameter(f"must be positive, got {value}")
    return value


@click.command()
@click.argument("folder", type=click.Path(file_okay=False))
@click.option("--target", "target_file", type=click.Path(dir_okay=False), required=True,
              help="Target file (YAML, from `heartcv target`).")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True,
              help="Rig file (.yaml); exports are written beside it: STEM_colmap/ and STEM_camchain.yaml.")
@click.option("--dist", "dist_size", type=click.Choice(("4", "5", "8")), default="5", show_default=True,
              help="Distortion model: 5 = k1 k2 p1 p2 k3, 8 = + rational k4 k5 k6, 4 = k1 k2 p1 p2 (k3 = 0; the "
                   "model Kalibr's camchain can hold).")
@click.option("--max-view-rms", type=float, default=None, callback=_positive_float, metavar="PX",
              help="Reject camera views whose reprojection RMS exceeds PX pixels (besides the relative rule: "
                   "3 x the camera's median view RMS, never below 0.25 px).")
@click.option("--every", type=click.IntRange(min=1), default=1, show_default=True,
              help="Use every n-th instant (image name or video frame).")
@click.option("--min-views", type=click.IntRange(min=3), default=4, show_default=True,
              help="Usable views needed per camera.")
@click.option("--jobs", type=click.IntRange(min=1), default=None,
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
    (the counts per camera are given), or a camera shares no view with the others.
    """
    from heartcv.io import HeartcvIOError, read_target

    out = Path(output)
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise BadInput(f"-o/--output: a .yaml file expected, got {output}")
    try:
        spec = read_target(target_file)
    except HeartcvIOError as exc:
        raise BadInput(str(exc)) from None
    cameras = _find_cameras(Path(folder))
    verbosity = (ctx.find_object(dict) or {}).get("verbosity", 0)
    jobs = jobs or min(os.cpu_count() or 1, 8)
    names = [c[0] for c in cameras]
    detections, sizes, view_names, used_files = _detect_all(cameras, spec, every, jobs, verbosity)
    rig = _calibrate(detections, spec, sizes, names, view_names, int(dist_size), max_view_rms, min_views)
    rig = type(rig)(rig.cameras, dict(rig.meta, producer="heartcv calibrate",
                                      inputs_hash=_inputs_hash(target_file, used_files)))
    exports = _write(out, rig)
    _summarise(rig, output, exports, as_json)


# -- inputs -----------------------------------------------------------------------------------------------------
def _find_cameras(folder: Path):
    """[(name, kind, paths)]: kind 'images' (paths: image files) or 'video' (paths: [video file])."""
    from heartcv.io import HeartcvIOError, camera_entries

    if not folder.is_dir():
        raise BadInput(f"{folder}: no such folder" if not folder.exists() else f"{folder}: not a folder")
    try:
        images, videos = camera_entries(folder)
    except HeartcvIOError as exc:
        raise BadInput(str(exc)) from None
    found = {name for name, _ in images}
    for d in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        if d.name not in found:
            log.warning("%s: no images, not a camera", d)
    cams = [(v.stem, "video", [v]) for v in videos] if videos else [(n, "images", fs) for n, fs in images]
    if len(cams) < 2:
        raise BadInput(f"{folder}: {len(cams)} camera(s) found; at least 2 expected (one sub-folder of images or "
                       f"one video file per camera)")
    names = [c[0] for c in cams]
    if len(set(names)) != len(names) or any(any(ch.isspace() for ch in n) for n in names):
        raise BadInput(f"{folder}: camera names must be unique and without spaces, got {names}")
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
    from heartcv.io import HeartcvIOError, read_image

    try:
        img = read_image(path, mode="unchanged")
    except HeartcvIOError as exc:
        return None, str(exc)
    return (img.shape[1], img.shape[0]), detect(img, spec)


def _detect_videos(cameras, spec, every, jobs, verbosity):
    import cv2

    from heartcv.detect import detect

    results, counts = {}, []
    with ThreadPoolExecutor(jobs) as pool:
        for c, (name, _, (path,)) in enumerate(cameras):
            cap = cv2.VideoCapture(str(path))
            if not cap.isOpened():
                raise BadInput(f"{path}: cannot open the video (unsupported or corrupt)")
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
    """Drop unreadable and odd-sized images (with warnings): detections [camera][instant], camera sizes,
    instant names and the files used (for the inputs' hash)."""
    detections, sizes, used = [], [], set()
    for c, (cam, _, _) in enumerate(cameras):
        mine = {v: r for (cc, v), r in results.items() if cc == c}
        bad = {v: r[1] for v, r in mine.items() if r[0] is None}
        for v, msg in sorted(bad.items()):
            log.warning("skipped: %s", msg)
        ok_sizes = Counter(r[0] for r in mine.values() if r[0] is not None)
        if not ok_sizes:
            log.warning("%s: none of its %d images could be read", cam, len(mine))
        size = ok_sizes.most_common(1)[0][0] if ok_sizes else None
        for v, r in sorted(mine.items()):
            if r[0] is not None and r[0] != size:
                log.warning("skipped: %s/%s: image is %dx%d px, the camera's other images are %dx%d px",
                            cam, names[v], *r[0], *size)
        dets = [None] * len(names)
        for v, r in mine.items():
            if size is not None and r[0] == size:
                dets[v] = r[1]
                used.add(paths[c, v])
        detections.append(dets)
        sizes.append(size)
        log.info("%s: %d images, target found in %d", cam, len(mine),
                 sum(d is not None and len(d) > 0 for d in dets))
    return detections, sizes, names, sorted(used)


def _inputs_hash(target_file, files):
    from heartcv.io import file_hash

    h = hashlib.sha256()
    for p in files:
        h.update(f"{Path(p).parent.name}/{Path(p).name}:{file_hash(p)}\n".encode())
    return {"target": file_hash(target_file), "images": "sha256:" + h.hexdigest()}


# -- calibration and outputs ------------------------------------------------------------------------------------
def _calibrate(detections, spec, sizes, names, view_names, dist_size, max_view_rms, min_views):
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
        raise StageFailed(f"calibration failed: {exc}; no rig file written") from None


def _write(out: Path, rig):
    """Exports first, the rig file last (its presence marks a complete run); returns the exports written."""
    from heartcv.io import write_colmap, write_kalibr, write_rig

    stem = out.with_suffix("")
    colmap = stem.parent / f"{stem.name}_colmap"
    kalibr = stem.parent / f"{stem.name}_camchain.yaml"
    write_colmap(colmap, rig)
    exports = {"colmap": str(colmap), "kalibr": None}
    try:
        write_kalibr(kalibr, rig)
        exports["kalibr"] = str(kalibr)
    except ValueError as exc:  # Kalibr's radtan model holds k1 k2 p1 p2 only
        log.warning("no Kalibr camchain written: %s", exc)
        exports["kalibr_skipped"] = str(exc)
        if kalibr.exists():  # a stale export from an earlier run would contradict the new rig
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
        log.warning("wrote %s: %d cameras, RMS %.3f px, baselines %s", output, len(cams), meta["rms_px"], base)
