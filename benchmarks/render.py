"""Rendering speed of the phantom scene (issue 4 acceptance: 1920x1080 frame triplets per second >= 1).

One section, :func:`bench_render`, on ``sample_sequences/phantom/scene.yaml`` exactly as shipped (3 cameras,
1920x1080, 50k-triangle phantom, sensor noise, PNG encoding as ``heartcv render sequence`` does it):

1. **Setup**: ``prepare_sequence`` once (truth simulation, phantom mesh, texture, the exact ray of every pixel),
   timed; triangles, vertices, pixels.
2. **Stage shares** (one process): ``render_frame`` with PNG encoding on a few frames after a warm-up; time per
   triplet in ray casting (Embree), shading (interpolation, texture, lighting), the BVH build, mesh/mask
   preparation, exposure (PSF, noise, quantisation) and PNG encoding; rays cast per triplet and the share of
   pixels inside the phantom's projected hull.
3. **Baselines in the same run** (one camera, one frame): casting every pixel instead of the hull's pixels, and
   trimesh's own Embree query (``RayMeshIntersector.intersects_id`` with locations) on the hull's rays.
4. **Throughput**: ``render_sequence`` over K frames on all cores (the CLI's default), wall time from the first
   job to the last result; triplets per second against the target of 1.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
import time

import numpy as np

from ._harness import fmt_ratio, fmt_time, single_threaded_blas, table

__all__ = ["bench_render", "SCENE", "TARGET_TRIPLETS_PER_S"]

REPO = Path(__file__).resolve().parents[1]
SCENE = REPO / "sample_sequences" / "phantom" / "scene.yaml"
TARGET_TRIPLETS_PER_S = 1.0


def _setup(frames: int, workers: int):
    from heartcv.io import read_scene, scene_file_path
    from heartcv.render.sequence import prepare_sequence
    from heartcv.tracker.io import read_model

    scene = read_scene(SCENE)
    scene = replace(scene, motion=replace(scene.motion, duration_s=(frames - 1) / scene.motion.frame_rate_hz))
    cfg = read_model(scene_file_path(SCENE, scene.motion.model))
    with single_threaded_blas():
        return prepare_sequence(scene, cfg, workers=workers)


def bench_render(*, quick: bool = False) -> dict:
    from heartcv.io import encode_png
    from heartcv.render.parallel import default_workers
    from heartcv.render.raycast import EmbreeScene, hull_mask
    from heartcv.render.sequence import render_frame, render_sequence

    workers = default_workers()
    n_frames = 8 if quick else 30
    n_single = 2 if quick else 4
    t0 = time.perf_counter()
    setup = _setup(n_frames, workers)
    t_prep = time.perf_counter() - t0
    cams = setup.rig.cameras
    W, H = cams[0].width, cams[0].height
    tri = int(setup.surface.phantom.faces.shape[0])
    print(f"scene {SCENE.relative_to(REPO)}: {len(cams)} cameras, {W}x{H}, {tri} triangles, "
          f"{setup.surface.phantom.n_vertices} vertices, {len(cams) * W * H} pixels per triplet; "
          f"{workers} worker processes")
    print(f"setup (truth simulation, mesh, texture, exact pixel rays of {len(cams)} cameras): {t_prep:.1f} s")

    # -- stage shares, one process ---------------------------------------------------------------------------
    render_frame(setup, 0, encode=encode_png)  # warm-up
    stages = {}
    rays = 0
    t0 = time.perf_counter()
    for k in range(1, 1 + n_single):
        r = render_frame(setup, k, encode=encode_png)
        rays += r.rays
        for key, v in r.timings.items():
            stages[key] = stages.get(key, 0.0) + v
    wall1 = (time.perf_counter() - t0) / n_single
    per = {k: v / n_single for k, v in stages.items()}
    per["other_s"] = max(wall1 - sum(per.values()), 0.0)
    names = {"cast_s": "ray casting (Embree)", "shade_s": "shading (interpolation, texture, lights)",
             "bvh_s": "BVH build (Embree scene)", "mesh_s": "deformed mesh, normals, pixel masks",
             "expose_s": "exposure (PSF, noise, quantisation)", "encode_s": "PNG encoding", "other_s": "other"}
    rows = [[names[k], fmt_time(v), f"{100 * v / wall1:.1f} %"] for k, v in per.items()]
    rows.append(["total per triplet (one process)", fmt_time(wall1), "100 %"])
    print()
    print(table(["stage", "per triplet", "share"], rows, title=f"Stage shares, one process, mean of {n_single} "
                                                                  "triplets (render_frame with PNG encoding)"))
    rays_per = rays / n_single
    print(f"rays per triplet: {rays_per:,.0f} ({100 * rays_per / (len(cams) * W * H):.1f} % of the pixels: "
          "only pixels inside the phantom's projected hull cast a ray)")

    # -- baselines, one camera ----------------------------------------------------------------------------------
    t = setup.frame_times[1]
    V = setup.surface.positions_world(t).astype(np.float32)
    es = EmbreeScene([(V, setup.surface.phantom.faces)], origin=V.mean(axis=0))
    cam = cams[0]
    d_all = setup.directions[0]
    idx = np.flatnonzero(hull_mask(cam, V).ravel())
    d_hull = d_all[idx]
    t_hull = _best(lambda: es.cast(cam.centre, d_hull))
    t_full = _best(lambda: es.cast(cam.centre, d_all))
    import trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    tm = RayMeshIntersector(trimesh.Trimesh(V.astype(float), setup.surface.phantom.faces, process=False))
    origins = np.broadcast_to(cam.centre, d_hull.shape)
    t_tm = _best(lambda: tm.intersects_id(origins, d_hull, multiple_hits=False, return_locations=True), n=1)
    rows = [["EmbreeScene.cast, hull pixels (used)", f"{idx.size:,}", fmt_time(t_hull), "1.00x"],
            ["EmbreeScene.cast, every pixel", f"{d_all.shape[0]:,}", fmt_time(t_full), fmt_ratio(t_full / t_hull)],
            ["trimesh intersects_id (+ locations), hull pixels", f"{idx.size:,}", fmt_time(t_tm),
             fmt_ratio(t_tm / t_hull)]]
    print()
    print(table(["ray casting, camera 0, one frame", "rays", "best of 3", "vs used"], rows,
                title="Baselines measured in this run"))

    # -- throughput on all cores ------------------------------------------------------------------------------
    t0 = time.perf_counter()
    count = 0
    for _ in render_sequence(setup, workers=workers, encode=encode_png):
        count += 1
    wall = time.perf_counter() - t0
    rate = count / wall
    verdict = "PASS" if rate >= TARGET_TRIPLETS_PER_S else "MISS"
    print()
    print(f"throughput: {count} triplets in {wall:.2f} s on {workers} workers = {rate:.2f} triplets/s "
          f"({rate * wall1:.2f}x one process); target >= {TARGET_TRIPLETS_PER_S:g}: {verdict}")
    return {"scene": str(SCENE.relative_to(REPO)), "cameras": len(cams), "width": W, "height": H, "triangles": tri,
            "vertices": int(setup.surface.phantom.n_vertices), "workers": workers, "setup_s": t_prep,
            "single_process_triplet_s": wall1, "stages_s": per, "stage_shares": {k: v / wall1 for k, v in per.items()},
            "rays_per_triplet": rays_per, "pixels_per_triplet": len(cams) * W * H,
            "baselines": {"cast_hull_s": t_hull, "cast_all_pixels_s": t_full, "trimesh_intersects_id_s": t_tm,
                          "hull_rays": int(idx.size), "all_rays": int(d_all.shape[0])},
            "frames": count, "wall_s": wall, "triplets_per_s": rate, "target_triplets_per_s": TARGET_TRIPLETS_PER_S,
            "verdict": verdict}


def _best(fn, n=3) -> float:
    best = np.inf
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best
