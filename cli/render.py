"""``heartcv render calibration|sequence``: render a scene file's calibration set or image sequence.

The output folder is written with :func:`heartcv.tracker.files.atomic_folder` (producer ``heartcv render``): it
replaces an existing folder only if a previous render wrote it, and an output that is or contains the scene file
or a file the scene names (``motion.model``, ``calibration.target``) is refused before any work.
"""

from __future__ import annotations

import logging
from pathlib import Path
import time

import click

from .options import (
    MAX_COUNT,
    MAX_SEED,
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

PRODUCER = "heartcv render"
MAX_WORKERS = 1024

def _scene_options(f):
    """SCENE_FILE, -o/--output, --seed and --workers: the arguments both commands take."""
    for option in (_WORKERS, _SEED, _OUT, _SCENE):
        f = option(f)
    return f


_SCENE = click.argument("scene_file", type=click.Path(exists=True, dir_okay=False))
_OUT = click.option("-o", "--output", type=click.Path(file_okay=False), required=True,
                    help="Folder to write (replaced as a whole once complete, only if a previous render wrote it).")
_SEED = click.option("--seed", type=Int(0, MAX_SEED), default=None,
                     help="Seed of the render (default: the scene file's `seed`).")
_WORKERS = click.option("--workers", type=Int(1, MAX_WORKERS), default=None,
                        help="Worker processes (default: all cores).")


@click.group()
def render():
    """Render a SCENE.yaml: calibration images of the target, or the moving phantom (docs/cli.md)."""


def _load_scene(scene_file, seed, output):
    """The scene (its ``seed`` replaced by ``--seed``) and the files it names; refuses, before any work, an output
    folder that is or contains one of them, or that another stage (or a person) made."""
    from dataclasses import replace

    from heartcv.io import read_scene, scene_file_path

    scene = read_scene(scene_file)
    files = {"motion.model": scene_file_path(scene_file, scene.motion.model),
             "calibration.target": (None if scene.calibration.target is None
                                    else scene_file_path(scene_file, scene.calibration.target))}
    guard_outputs({"-o/--output": output}, {"SCENE_FILE": scene_file, **files},
                  folders=[("-o/--output", output, PRODUCER)])
    return (scene if seed is None else replace(scene, seed=seed)), files


def _named_file(scene_file, field, reader, path):
    """``reader(path)`` of a file the scene names; an invalid file is reported as the scene's field."""
    from heartcv.tracker.files import InputError

    try:
        return reader(path)
    except InputError as exc:
        raise InputError(scene_file, str(exc), field) from None


def _prepared(scene_file, prepare):
    """``prepare()``; a scene the core refuses (InputError without a file) names the scene file."""
    from heartcv.tracker.files import InputError

    try:
        return prepare()
    except InputError as exc:
        raise exc.in_file(scene_file) from None


def _require_embree():
    from heartcv.render.raycast import embree_available

    if not embree_available():
        raise StageFailed("the renderer needs Embree through the embreex package (pip install embreex), "
                          "which is not importable")


def _workers(n):
    from heartcv.render.parallel import default_workers

    return n or default_workers()


def _write_frames(folder, names, results, label, ctx, count):
    """Write each result's encoded images to ``folder/<camera>/<k:06d>.png``; returns per result its ``rays``,
    ``timings`` and, for sequences, its instrument mask bit-packed along the rows (the images are not kept)."""
    import numpy as np

    kept = []
    for name in names:
        (folder / name).mkdir()
    with progress(results, label, length=count, verbosity=ctx.obj.get("verbosity", 0) if ctx.obj else 0) as bar:
        for res in bar:
            for name, data in zip(names, res.images):
                (folder / name / f"{res.index:06d}.png").write_bytes(data)
            mask = getattr(res, "instrument_mask", None)
            kept.append({"rays": res.rays, "timings": getattr(res, "timings", {}),
                         "mask": None if mask is None else np.packbits(mask, axis=-1)})
    return kept


@render.command()
@_scene_options
@click.option("--views", type=Int(1, MAX_COUNT), default=None,
              help="Number of board views (default: the scene's calibration.views).")
@json_opt
@click.pass_context
def calibration(ctx, scene_file, output, seed, workers, views, as_json):
    """Render the calibration target at the scene's seeded poses: OUTPUT/cam0/000000.png ... (one file name per
    view in every camera folder), truth.npz (true cameras and board poses) and rig_truth.yaml."""
    from dataclasses import replace

    from heartcv.io import encode_png, file_hash, read_target, write_render_truth, write_rig
    from heartcv.render.board import calibration_truth, prepare_calibration, render_calibration
    from heartcv.render.scene import DEFAULT_TARGET
    from heartcv.targets import TargetSpec
    from heartcv.tracker.files import atomic_folder

    scene, files = _load_scene(scene_file, seed, output)
    _check_other_file(scene_file, files, "motion.model")
    if views is not None:
        scene = replace(scene, calibration=replace(scene.calibration, views=views))
    target_path = files["calibration.target"]
    if target_path is None:
        target = TargetSpec.from_dict(DEFAULT_TARGET)
    else:
        target = _named_file(scene_file, "calibration.target", read_target, target_path)
    n_workers = _workers(workers)
    t0 = time.perf_counter()
    setup = _prepared(scene_file, lambda: prepare_calibration(scene, target, workers=n_workers))
    names = [c.name for c in setup.rig.cameras]
    with atomic_folder(output, PRODUCER, {"kind": "calibration"}) as tmp:
        res = _write_frames(tmp, names, render_calibration(setup, workers=n_workers, encode=encode_png),
                            "rendering calibration views", ctx, setup.n_views)
        arrays, meta = calibration_truth(setup)
        meta.update({"producer": "heartcv render calibration", "scene_file": str(scene_file),
                     "inputs_hash": {"scene": file_hash(scene_file)} | (
                         {"target": file_hash(target_path)} if target_path else {}),
                     "file_names": [f"{i:06d}.png" for i in range(setup.n_views)]})
        write_render_truth(tmp / "truth.npz", arrays, meta)
        write_rig(tmp / "rig_truth.yaml", setup.rig)
        (tmp / "scene.yaml").write_bytes(Path(scene_file).read_bytes())
    wall = time.perf_counter() - t0
    summary = {"output": output, "views": setup.n_views, "partial_views": int(setup.partial.sum()),
               "cameras": names, "image_size": [setup.rig.cameras[0].width, setup.rig.cameras[0].height],
               "target": target.name, "seed": scene.seed, "rays": int(sum(r["rays"] for r in res)), "wall_s": wall,
               "corners_visible": arrays["corners_visible"].sum(axis=2).tolist()}
    if as_json:
        emit_json(summary)
    else:
        announce(log, "wrote %s (%d views x %d cameras) in %.1f s", output, setup.n_views, len(names), wall)


def _check_other_file(scene_file, files, field):
    """Exit 2 for a missing or invalid file of the scene that this kind of render does not use (a sequence's
    calibration target, a calibration's model): the scene file is checked as a whole, whichever part is
    rendered, so an error in it shows on the first render, not on the other kind's weeks later."""
    from heartcv.io import read_target
    from heartcv.tracker.io import read_model

    if files.get(field) is not None:
        _named_file(scene_file, field, read_target if field == "calibration.target" else read_model, files[field])


def _prepare_sequence(scene_file, scene, cfg, n_workers):
    """The sequence's set-up; exit 1 if the truth simulation diverges."""
    from threadpoolctl import threadpool_limits

    from heartcv.render.sequence import prepare_sequence

    try:
        with threadpool_limits(1):
            return _prepared(scene_file, lambda: prepare_sequence(scene, cfg, workers=n_workers))
    except FloatingPointError as exc:  # the truth simulator's divergence check (heartcv.tracker.simulate)
        raise StageFailed(f"{scene_file}: truth simulation: {exc}") from None


@render.command()
@_scene_options
@click.option("--frames", type=Int(1, MAX_COUNT), default=None,
              help="Render only the first N frames (default: all of motion.duration_s).")
@click.option("--stiffness-cycle", "stiffness_cycle", type=Float(0, 20), default=None,
              help="Override motion.stiffness_cycle.amplitude (0: a constant stiffness, e.g. to check that "
                   "heartcv fit recovers the truth's parameters).")
@json_opt
@click.pass_context
def sequence(ctx, scene_file, output, seed, workers, frames, stiffness_cycle, as_json):
    """Render the moving phantom: OUTPUT/cam0/000000.png ... per frame, inputs.csv (known inputs per frame),
    truth.npz (true parameters, mesh and vertex trajectories, camera truth, instrument masks), rig_truth.yaml."""
    from dataclasses import replace

    import numpy as np

    from heartcv.io import encode_png, file_hash, write_inputs_csv, write_render_truth, write_rig
    from heartcv.render.sequence import inputs_table, render_sequence, sequence_truth
    from heartcv.tracker.files import atomic_folder
    from heartcv.tracker.io import read_model

    scene, files = _load_scene(scene_file, seed, output)
    _check_other_file(scene_file, files, "calibration.target")
    if stiffness_cycle is not None:
        scene = replace(scene, motion=replace(scene.motion, stiffness_amplitude=float(stiffness_cycle)))
    _require_embree()
    model_path = files["motion.model"]
    cfg = _named_file(scene_file, "motion.model", read_model, model_path)
    n_workers = _workers(workers)
    t0 = time.perf_counter()
    setup = _prepare_sequence(scene_file, scene, cfg, n_workers)
    t_prep = time.perf_counter() - t0
    count = setup.n_frames if frames is None else min(frames, setup.n_frames)
    if frames is not None and frames > setup.n_frames:
        log.warning("--frames %d: the scene holds %d frames (motion.duration_s %g s at %g Hz); rendering those",
                    frames, setup.n_frames, scene.motion.duration_s, scene.motion.frame_rate_hz)
    names = [c.name for c in setup.rig.cameras]
    with atomic_folder(output, PRODUCER, {"kind": "sequence"}) as tmp:
        t1 = time.perf_counter()
        res = _write_frames(tmp, names, render_sequence(setup, frames=range(count), workers=n_workers,
                                                        encode=encode_png), "rendering frames", ctx, count)
        t_render = time.perf_counter() - t1
        masks = np.stack([r["mask"] for r in res]) if setup.instrument is not None else None
        arrays, meta = sequence_truth(setup, masks, frames=count)
        meta.update({"producer": "heartcv render sequence", "scene_file": str(scene_file),
                     "inputs_hash": {"scene": file_hash(scene_file), "model": file_hash(model_path)},
                     "file_names": [f"{k:06d}.png" for k in range(count)]})
        write_render_truth(tmp / "truth.npz", arrays, meta)
        cols, vals = inputs_table(setup)
        write_inputs_csv(tmp / "inputs.csv", cols, vals[:count],
                         "heartcv render sequence: known inputs at the frame times (docs/formats.md, inputs.csv)\n"
                         "time_s: s from the first frame; *_pa: Pa; respiration_*_m: m, patch frame")
        write_inputs_csv(tmp / "timestamps.csv", ["time_s"], np.asarray(setup.frame_times[:count])[:, None],
                         "heartcv render sequence: the time of each frame (s from the first frame), one row per "
                         "frame in file-name order")
        write_rig(tmp / "rig_truth.yaml", setup.rig)
        (tmp / "scene.yaml").write_bytes(Path(scene_file).read_bytes())
    wall = time.perf_counter() - t0
    timings = {k: float(sum(r["timings"].get(k, 0.0) for r in res)) for k in res[0]["timings"]} if res else {}
    pos, phantom = arrays["point_positions"], setup.surface.phantom
    summary = {"output": output, "frames": count, "cameras": names, "seed": scene.seed,
               "image_size": [setup.rig.cameras[0].width, setup.rig.cameras[0].height],
               "duration_s": float(setup.frame_times[count - 1]), "frame_rate_hz": scene.motion.frame_rate_hz,
               "triangles": int(phantom.faces.shape[0]), "vertices": int(phantom.n_vertices),
               "rays": int(sum(r["rays"] for r in res)), "prepare_s": t_prep, "render_s": t_render, "wall_s": wall,
               "frames_per_s": count / t_render if t_render > 0 else None, "worker_timings_s": timings,
               "peak_displacement_m": float(np.linalg.norm(pos - pos[:1], axis=2).max()),
               "instrument": setup.instrument is not None}
    if as_json:
        emit_json(summary)
    else:
        announce(log, "wrote %s (%d frames x %d cameras) in %.1f s", output, count, len(names), wall)
