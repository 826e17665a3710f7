"""Speed of the measurement stage on PNG input: the rendered 1080p trinocular phantom (issue 5 acceptance: frame
triplets per second >= 5 on the project's 2-core machine, with the split between decoding, tracking and
triangulation) and real 360x288 endoscope stereo (issue 14: the sparse default at >= 25 pairs per second, real time
for PAL video; the dense mode's rate; GPU rates where a CUDA device is present; :mod:`benchmarks.measure_real`).

One section, :func:`bench_measure`, in one process. Everything runs under ``threadpoolctl.threadpool_limits(1)``
for the BLAS libraries (numpy's and scipy's OpenBLAS: **one BLAS thread**, printed; OpenCV keeps its own thread
count, printed; torch is set to one thread for the kornia CPU backend). Part A, the phantom:

1. **Input**: the phantom scene (``sample_sequences/phantom/scene.yaml``) rendered once to PNGs with
   ``heartcv render sequence ... --frames N --workers 2`` (N = 30, 10 in ``--quick``) into
   ``benchmarks/.cache/phantom_sequence`` (or ``$HEARTCV_BENCH_SEQ``); a folder that already holds at least N
   complete frame triplets and ``rig_truth.yaml`` is reused. The render time is printed, not measured. The rig is
   the true one (``rig_truth.yaml``): the speed does not depend on the calibration.
2. **The stage as the CLI runs it** (cli/measure.py ``_run``, without writing the output files):
   ``open_frame_source``, a colour ``FrameReader`` (2 decoding threads; it decodes the next triplet while the current
   one is processed), the automatic region of interest ``auto_region(reference_frames(reader.read, N, 0), opts)``
   (frames 0, 3, ... of the reference camera), then ``measure_sequence(reader, cameras, opts, roi=roi)`` with the
   CLI's defaults: ``MeasureOptions()`` resolved for the image size (``for_image``; checked against cli/measure.py's
   own option builder where it can be called, the result printed), OpenCV backend. Runs: 3 (1 in ``--quick``); the
   run with the median wall time is shown. Rates: *all frames* = N / wall from opening the source to the last step
   (region of interest, initial detection and matching included; what the CLI reports as ``frames_per_s``) and
   *steady state* = (N - 1) / time of frames 1 .. N-1 (without the one-off setup and first detection; later
   re-detections stay in). Split per triplet: decode (time spent waiting for the reader), tracking (high-pass
   prefilter + template LK with forward-backward and NCC checks), triangulation, detection/matching
   (``FrameStats`` of ``run.frames``, i.e. ``Measurer.timings`` differences per step) and the rest of the loop.
3. **Baselines in the same run** (median of 3 passes over the N triplets, 1 in ``--quick``): (a) decoding only,
   colour as the stage reads it: ``cv2.imread(path, IMREAD_COLOR)`` of the 3 PNGs of a triplet in one thread and in
   2 threads, ``heartcv.io.read_image(path, 'color')`` (with its truncation and size checks) in one thread, and
   ``FrameReader`` iterated with nothing else to do; (b) plain frame-to-frame ``cv2.calcOpticalFlowPyrLK`` of the
   points the stage accepted in the previous frame, each camera, full raw gray images, the stage's
   window/levels/criteria, no checks (the cheapest tracker), and the stage's high-pass prefilter alone; (c) the
   initial detection (``heartcv.features.detect_corners`` in the ROI minus clipped highlights) and trinocular
   matching (``heartcv.matching.match_points`` with the stage's noise-adaptive NCC gate) of frame 0 alone, with the
   OpenCV backend and, when ``import kornia`` works, ``get_backend('kornia', 'cpu')`` with
   ``torch.set_num_threads(1)``. Ratios: stage per triplet / decode-only per triplet, tracking / plain LK, kornia /
   OpenCV.
4. The machine's load average (``os.getloadavg()``) before and after: other processes may share the 2 cores.

Part B, the in-vivo heart (``../shared/data/hamlyn_invivo_heart``; skipped with the reason printed where it is not
reachable): :func:`benchmarks.measure_real.bench_real` -- the sparse default (pairs/s, split, points per frame,
median track span, reprojection RMS, candidates per gate; target 25 pairs/s), the dense mode (pairs/s, points per
frame; target >= 1000 in every frame), the kornia backend on the CPU and on CUDA where present, decoding alone as
the baseline, the load average; returned under ``real`` in the section's JSON.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import os
from pathlib import Path
import statistics
import subprocess
import sys
import time

import numpy as np

from ._harness import blas_threads, fmt_ratio, fmt_time, measure, single_threaded_blas, table
from .measure_real import bench_real

__all__ = ["bench_measure", "SCENE", "CACHE", "TARGET_TRIPLETS_PER_S"]

REPO = Path(__file__).resolve().parents[1]
SCENE = REPO / "sample_sequences" / "phantom" / "scene.yaml"
CACHE = REPO / "benchmarks" / ".cache" / "phantom_sequence"
TARGET_TRIPLETS_PER_S = 5.0
CLI_WORKERS = 2         # heartcv measure --workers default


# -- input ------------------------------------------------------------------------------------------------------
def _complete_frames(folder: Path) -> int:
    """Frame triplets available in a rendered sequence folder (0 if it is not a complete rendering)."""
    from heartcv.io import HeartcvIOError, open_frame_source, read_rig

    if not (folder / "rig_truth.yaml").is_file() or not (folder / "truth.npz").is_file():
        return 0
    try:
        rig = read_rig(folder / "rig_truth.yaml")
        src = open_frame_source(folder, cameras=rig.names)
    except HeartcvIOError:
        return 0
    n = 0
    for k in range(src.n_frames):
        if any(src.files[c][k] is None for c in range(src.n_cameras)):
            break
        n += 1
    return n


def _sequence(n_frames: int):
    """(folder, info): the cached rendering, rendered now if it has fewer than ``n_frames`` triplets."""
    folder = Path(os.environ.get("HEARTCV_BENCH_SEQ") or CACHE)
    have = _complete_frames(folder)
    info = {"folder": str(folder), "rendered_now": False, "render_s": None, "frames_available": have}
    if have >= n_frames:
        return folder, info
    exe = Path(sys.executable).parent / "heartcv"
    cmd = [str(exe)] if exe.is_file() else [sys.executable, "-c", "import sys; from heartcv.cli.main import main; "
                                                                  "sys.exit(main())"]
    cmd += ["-q", "render", "sequence", str(SCENE), "-o", str(folder), "--frames", str(n_frames), "--workers", "2"]
    print(f"rendering {n_frames} frames into {folder} (not part of the measurement): {' '.join(cmd[1:])}")
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=REPO)
    info.update(rendered_now=True, render_s=time.perf_counter() - t0, frames_available=_complete_frames(folder))
    if info["frames_available"] < n_frames:
        raise RuntimeError(f"{folder}: {info['frames_available']} complete frames after rendering {n_frames}")
    return folder, info


# -- the stage --------------------------------------------------------------------------------------------------
def _options(rig):
    """What cli/measure.py runs with its defaults: ``MeasureOptions()`` resolved for the reference camera's image
    size (``for_image``), and a note saying whether that equals the CLI's own builder."""
    from .measure_real import _sparse_options

    ref = rig.cameras[0]
    return _sparse_options(ref.width, ref.height)


def _run_stage(folder: Path, rig, n: int, opts) -> dict:
    """One run of the measurement stage as ``heartcv measure`` drives it (cli/measure.py ``_run``): a colour
    ``FrameReader``, the automatic region of interest, then :func:`heartcv.measure.measure_sequence` (the one frame
    loop), timed per frame."""
    from heartcv.backend import get_backend
    from heartcv.io import FrameReader, open_frame_source
    from heartcv.measure import auto_region, measure_sequence, reference_frames

    t_start = time.perf_counter()
    source = open_frame_source(folder, cameras=rig.names)
    with FrameReader(source, mode="color", sizes=[c.size for c in rig.cameras], frames=range(n),
                     workers=CLI_WORKERS) as reader:
        first = reference_frames(reader.read, n, opts.ref_camera)
        t_roi_read = time.perf_counter()
        roi = auto_region(first, opts)
        t_roi = time.perf_counter()
        run = measure_sequence(reader, rig.cameras, opts, roi=roi, backend=get_backend("opencv", None))
    wall = time.perf_counter() - t_start
    if run.problems or run.skipped:
        raise RuntimeError(f"{folder}: images left out: {run.problems}, frames skipped: {run.skipped}")
    per = [{"frame": f.frame, "total_s": f.total_s, "decode_s": f.wait_s, "tracking_s": f.tracking_s,
            "triangulation_s": f.triangulation_s, "detection_s": f.detection_s,
            "other_s": f.total_s - f.wait_s - f.tracking_s - f.triangulation_s - f.detection_s, "seen": f.seen,
            "detected": f.detected} for f in run.frames]
    res = run.result
    setup = (t_roi - t_start) + run.setup_s
    return {"wall_s": wall, "setup_s": setup, "roi_read_s": t_roi_read - t_start, "roi_compute_s": t_roi - t_roi_read,
            "tracker_setup_s": run.setup_s,
            "roi_frames": len(first), "frames": per, "roi": res.roi, "uv": res.uv, "tracks": int(res.point_ids.size),
            "points_mean": float(res.seen.sum(axis=1).mean()), "points_min": int(res.seen.sum(axis=1).min()),
            "redetections": int(sum(1 for f in per[1:] if f["detected"])),
            "sigma_px": float(res.sigma_px), "options": opts}


def _split(run: dict, n: int):
    """Per-triplet means (all frames incl. setup, and steady state = frames 1..N-1)."""
    keys = ("decode_s", "tracking_s", "triangulation_s", "detection_s", "other_s")
    frames = run["frames"]
    all_ = {k: sum(f[k] for f in frames) / n for k in keys}
    all_["setup_s"] = run["setup_s"] / n
    all_["total_s"] = run["wall_s"] / n
    steady = {k: sum(f[k] for f in frames[1:]) / (n - 1) for k in keys}
    steady["setup_s"] = 0.0
    steady["total_s"] = sum(f["total_s"] for f in frames[1:]) / (n - 1)
    return all_, steady


# -- baselines --------------------------------------------------------------------------------------------------
def _per_triplet(fn, count: int, repeats: int, warmup: int) -> dict:
    """Median over ``repeats`` passes of ``fn`` (one pass handles ``count`` triplets), per triplet."""
    t = measure(fn, repeats=repeats, warmup=warmup, number=1)
    return {"per_triplet_s": t.median / count, "min_per_triplet_s": t.min / count, "pass": t.as_dict(),
            "triplets": count}


def _decode_baselines(folder: Path, rig, n: int, repeats: int, warmup: int) -> dict:
    import cv2

    from heartcv.io import FrameReader, open_frame_source, read_image

    src = open_frame_source(folder, cameras=rig.names)
    paths = [[str(src.files[c][k]) for c in range(src.n_cameras)] for k in range(n)]
    sizes = [c.size for c in rig.cameras]

    def imread_1():
        for trip in paths:
            for p in trip:
                cv2.imread(p, cv2.IMREAD_COLOR)

    pool = ThreadPoolExecutor(2)

    def imread_2():
        for trip in paths:
            list(pool.map(lambda p: cv2.imread(p, cv2.IMREAD_COLOR), trip))

    def read_image_1():
        for trip in paths:
            for p, size in zip(trip, sizes):
                read_image(p, "color", size)

    def reader_alone():
        with FrameReader(src, mode="color", sizes=sizes, frames=range(n), workers=CLI_WORKERS) as reader:
            for _ in reader:
                pass

    try:
        out = {"imread_1_thread": _per_triplet(imread_1, n, repeats, warmup),
               "imread_2_threads": _per_triplet(imread_2, n, repeats, warmup),
               "read_image_1_thread": _per_triplet(read_image_1, n, repeats, warmup),
               "frame_reader_alone": _per_triplet(reader_alone, n, repeats, warmup)}
    finally:
        pool.shutdown()
    return out


def _load_gray(folder: Path, rig, n: int):
    import cv2

    from heartcv.io import open_frame_source

    src = open_frame_source(folder, cameras=rig.names)
    return [[cv2.imread(str(src.files[c][k]), cv2.IMREAD_GRAYSCALE) for c in range(src.n_cameras)]
            for k in range(n)]


def _highpass(gray, sigma):
    """Measurer._prefilter: the high-pass ``128 + 2 (g - blur(g))`` (the gray image itself for sigma 0/None)."""
    import cv2

    if not sigma:
        return gray
    return cv2.addWeighted(gray, 2.0, cv2.GaussianBlur(gray, (0, 0), sigma), -2.0, 128.0)


def _tracking_baselines(gray, uv, opts, repeats: int, warmup: int) -> dict:
    """Plain frame-to-frame LK of the points accepted in the previous frame; the stage's prefilter alone."""
    import cv2

    lk = opts.lk
    n, C = len(gray), len(gray[0])
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, lk.iterations, lk.epsilon_px)
    pts = {}
    for k in range(1, n):
        for c in range(C):
            p = uv[k - 1, :, c]
            p = p[np.isfinite(p).all(axis=1)]
            if len(p):
                pts[k, c] = np.ascontiguousarray(p, np.float32).reshape(-1, 1, 2)
    n_pts = sum(len(p) for p in pts.values()) / (n - 1)

    def plain_lk():
        for (k, c), p in pts.items():
            cv2.calcOpticalFlowPyrLK(gray[k - 1][c], gray[k][c], p, None, winSize=(lk.window, lk.window),
                                     maxLevel=lk.levels, criteria=crit)

    sig = opts.highpass_sigma

    def prefilter():
        # Measurer._prefilter on the 3 images of each triplet
        for trip in gray[1:]:
            for g in trip:
                blur = cv2.GaussianBlur(g, (0, 0), sig)
                cv2.addWeighted(g, 2.0, blur, -2.0, 128.0)

    return {"plain_lk": _per_triplet(plain_lk, n - 1, repeats, warmup) | {"points_per_triplet": n_pts},
            "highpass_prefilter": _per_triplet(prefilter, n - 1, repeats, warmup)}


def _detect_match(cameras, images, roi, opts, backend, repeats: int, warmup: int) -> dict:
    """Measurer._spawn's first call on frame 0: corners in the ROI minus highlights, then match_points."""
    from heartcv.features import detect_corners, saturation_mask
    from heartcv.klt import LKParams, expected_ncc, template_patches
    from heartcv.matching import match_points
    from heartcv.tissue import noise_sigma

    o = opts
    ref = o.ref_camera
    gray = images[ref]
    state = {}

    def detect():
        mask = roi & ~saturation_mask(gray, o.saturation_level, grow=o.lk.window // 2)
        state["uv"], _ = detect_corners(gray, mask, max_points=o.max_points, min_distance=o.min_distance_px,
                                        block_size=o.corner_block_size, quality=o.corner_quality,
                                        exclude=np.zeros((0, 2)), backend=backend)

    noise_var = max(noise_sigma(_highpass(im, o.highpass_sigma)) ** 2 for im in images)

    def match():
        imgs = [np.asarray(im, np.float32) for im in images]
        min_ncc = o.match_min_ncc
        if min_ncc is None:       # Measurer._spawn's adaptive gate (what noise alone leaves, minus the allowance)
            patch = template_patches(gray, state["uv"], LKParams(ncc_radius=o.match_radius))
            min_ncc = np.maximum(o.ncc_floor, expected_ncc(patch, noise_var) - o.match_ncc_allowance)
        state["m"] = match_points(cameras, imgs, ref, state["uv"], radius=o.match_radius, min_ncc=min_ncc,
                                  backend=backend)

    td = measure(detect, repeats=repeats, warmup=warmup, number=1)
    tm = measure(match, repeats=repeats, warmup=warmup, number=1)
    return {"detect": td.as_dict(), "match": tm.as_dict(), "total_s": td.median + tm.median,
            "corners": int(len(state["uv"])), "matched": int(state["m"].ok.sum()), "uv": state["m"].uv}


# -- the section ------------------------------------------------------------------------------------------------
def bench_measure(*, quick: bool = False) -> dict:
    import cv2

    from heartcv.io import read_rig

    n = 10 if quick else 30
    runs_n = 1 if quick else 3
    reps = 1 if quick else 3
    warm = 0 if quick else 1
    load0 = os.getloadavg()
    print(f"load average (1, 5, 15 min) at start: {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f} on "
          f"{os.cpu_count()} CPUs (other processes share the cores: read the numbers with that in mind)")
    folder, seq = _sequence(n)
    if seq["rendered_now"]:
        print(f"rendered in {seq['render_s']:.1f} s (not part of the measurement)")
    rig = read_rig(folder / "rig_truth.yaml")
    cams = rig.cameras
    W, H = cams[0].width, cams[0].height
    where = os.path.relpath(folder, REPO) if folder.is_relative_to(REPO) else str(folder)
    print(f"input: {where}, first {n} of {seq['frames_available']} frame triplets, {len(cams)} cameras "
          f"{W}x{H} PNG ({'rendered now' if seq['rendered_now'] else 'cached rendering reused'}); true rig "
          "rig_truth.yaml")

    with single_threaded_blas():
        print(f"BLAS threads in effect: {blas_threads()} (threadpoolctl.threadpool_limits(1)); "
              f"OpenCV threads: {cv2.getNumThreads()}; FrameReader workers: {CLI_WORKERS}")

        # -- the stage ---------------------------------------------------------------------------------------------
        opts, opts_note = _options(rig)
        print(f"options: MeasureOptions().for_image({W}, {H}) ({opts_note})")
        runs = [_run_stage(folder, rig, n, opts) for _ in range(runs_n)]
        order = sorted(range(runs_n), key=lambda i: runs[i]["wall_s"])
        run = runs[order[runs_n // 2]]
        all_, steady = _split(run, n)
        rate_all = 1.0 / all_["total_s"]
        rate_steady = 1.0 / steady["total_s"]
        names = {"decode_s": "decode (waiting for the reader)",
                 "tracking_s": "tracking (high-pass + template LK, FB + NCC)",
                 "triangulation_s": "triangulation", "detection_s": "detection + matching",
                 "other_s": "other (loop, bookkeeping)",
                 "setup_s": f"setup: read {run['roi_frames']} ROI frames + region of interest"}
        rows = []
        for key in ("decode_s", "tracking_s", "triangulation_s", "detection_s", "other_s", "setup_s"):
            rows.append([names[key], fmt_time(all_[key]), f"{100 * all_[key] / all_['total_s']:.1f} %",
                         fmt_time(steady[key]) if key != "setup_s" else "-",
                         f"{100 * steady[key] / steady['total_s']:.1f} %" if key != "setup_s" else "-"])
        rows.append(["total per triplet", fmt_time(all_["total_s"]), "100 %", fmt_time(steady["total_s"]), "100 %"])
        rows.append(["triplets per second", f"{rate_all:.2f}", "", f"{rate_steady:.2f}", ""])
        print()
        print(table(["per triplet", f"all {n} frames", "share", f"steady (1..{n - 1})", "share"], rows,
                    title=f"The stage as `heartcv measure` runs it (FrameReader + Measurer, {opts.max_points} points, "
                          f"highpass {opts.highpass_sigma:g}, OpenCV backend); run with the median wall of "
                          f"{runs_n}"))
        f0 = run["frames"][0]
        print(f"frame 0: {fmt_time(f0['total_s'])} (decode wait {fmt_time(f0['decode_s'])}, detection + matching "
              f"{fmt_time(f0['detection_s'])}); setup {fmt_time(run['setup_s'])} (ROI frames read "
              f"{fmt_time(run['roi_read_s'])}, auto_region {fmt_time(run['roi_compute_s'])}, tracker "
              f"{fmt_time(run['tracker_setup_s'])})")
        print(f"tracks {run['tracks']}, points per frame {run['points_mean']:.0f} (min {run['points_min']}), "
              f"re-detections after frame 0: {run['redetections']}, sigma {run['sigma_px']:.3f} px")
        if runs_n > 1:
            print("all runs: " + "; ".join(
                f"{n / r['wall_s']:.2f} all / {(n - 1) / sum(f['total_s'] for f in r['frames'][1:]):.2f} steady "
                "triplets/s" for r in runs))

        # -- baselines -----------------------------------------------------------------------------------------
        dec = _decode_baselines(folder, rig, n, reps, warm)
        gray = _load_gray(folder, rig, n)
        trk = _tracking_baselines(gray, run["uv"], opts, reps, warm)
        from heartcv.backend import get_backend

        dm = {"opencv": _detect_match(cams, gray[0], run["roi"], opts, get_backend("opencv", None), reps, warm)}
        kornia_note = None
        try:
            import kornia  # noqa: F401
            import torch
        except Exception as exc:  # kornia/torch missing or broken
            kornia_note = f"kornia backend skipped: import kornia failed ({type(exc).__name__}: {exc})"
        if kornia_note is None:
            threads = torch.get_num_threads()
            torch.set_num_threads(1)
            try:
                dm["kornia"] = _detect_match(cams, gray[0], run["roi"], opts, get_backend("kornia", "cpu"),
                                             reps, warm)
            finally:
                torch.set_num_threads(threads)
            kornia_note = (f"kornia {kornia.__version__}, torch {torch.__version__}, cpu, torch.set_num_threads(1) "
                           f"(default {threads})")
            a, b = dm["opencv"]["uv"], dm["kornia"]["uv"]
            if a.shape == b.shape:
                both = np.isfinite(a) & np.isfinite(b)
                same = np.array_equal(np.isfinite(a), np.isfinite(b))
                diff = float(np.abs(a[both] - b[both]).max()) if both.any() else 0.0
                kornia_note += f"; matches vs OpenCV: same views {same}, max |duv| {diff:.2e} px"
            else:
                kornia_note += f"; {len(b)} vs {len(a)} corners (OpenCV)"

    d1 = dec["imread_1_thread"]["per_triplet_s"]
    d2 = dec["imread_2_threads"]["per_triplet_s"]
    lk = trk["plain_lk"]["per_triplet_s"]
    rows = [["cv2.imread x3, 1 thread", fmt_time(d1), "1.00x", fmt_ratio(steady["total_s"] / d1)],
            ["cv2.imread x3, 2 threads", fmt_time(d2), fmt_ratio(d2 / d1), fmt_ratio(steady["total_s"] / d2)],
            ["heartcv.io.read_image x3, 1 thread", fmt_time(dec["read_image_1_thread"]["per_triplet_s"]),
             fmt_ratio(dec["read_image_1_thread"]["per_triplet_s"] / d1), "-"],
            [f"FrameReader alone ({CLI_WORKERS} workers, prefetch)",
             fmt_time(dec["frame_reader_alone"]["per_triplet_s"]),
             fmt_ratio(dec["frame_reader_alone"]["per_triplet_s"] / d1), "-"]]
    print()
    print(table(["decoding only, per triplet", f"median of {reps}", "vs 1 thread", "steady stage / this"], rows,
                title=f"Baselines measured in this run ({n} triplets per pass)"))
    rows = [[f"plain LK frame to frame ({trk['plain_lk']['points_per_triplet']:.0f} points x views), full images",
             fmt_time(lk), "1.00x"],
            ["high-pass prefilter of 3 images (stage's, alone)", fmt_time(trk["highpass_prefilter"]["per_triplet_s"]),
             fmt_ratio(trk["highpass_prefilter"]["per_triplet_s"] / lk)],
            ["stage tracking, steady state", fmt_time(steady["tracking_s"]), fmt_ratio(steady["tracking_s"] / lk)]]
    print()
    print(table(["tracking, per triplet", f"median of {reps}", "vs plain LK"], rows))
    rows = []
    base = dm["opencv"]["total_s"]
    for name, r in dm.items():
        rows.append([f"{name} backend", f"{r['corners']}", f"{r['matched']}", fmt_time(statistics.median(
            r["detect"]["samples_s"])), fmt_time(statistics.median(r["match"]["samples_s"])), fmt_time(r["total_s"]),
            fmt_ratio(r["total_s"] / base)])
    rows.append(["in the stage (frame 0, Measurer.timings)", "", "", "", "", fmt_time(f0["detection_s"]),
                 fmt_ratio(f0["detection_s"] / base)])
    print()
    print(table(["initial detection + matching, frame 0", "corners", "matched", "detect", "match", "total",
                 "vs opencv"], rows))
    print(kornia_note or "kornia backend: not measured")

    cpu = d1 + steady["tracking_s"] + steady["triangulation_s"]
    print(f"CPU budget, steady state: decoding {fmt_time(d1)} (1-thread baseline, mostly hidden by the reader's "
          f"prefetch) + tracking + triangulation {fmt_time(steady['tracking_s'] + steady['triangulation_s'])} = "
          f"{fmt_time(cpu)} per triplet, / 2 cores = {fmt_time(cpu / 2)} vs {fmt_time(steady['total_s'])} measured")
    verdict_steady = "PASS" if rate_steady >= TARGET_TRIPLETS_PER_S else "MISS"
    verdict_all = "PASS" if rate_all >= TARGET_TRIPLETS_PER_S else "MISS"
    print()
    print(f"ratios: steady stage / decode-only = {steady['total_s'] / d1:.2f}x (1 thread), "
          f"{steady['total_s'] / d2:.2f}x (2 threads); stage tracking / plain LK = {steady['tracking_s'] / lk:.2f}x; "
          f"decode wait / decode-only (1 thread) = {steady['decode_s'] / d1:.2f}")
    print(f"throughput: {rate_all:.2f} triplets/s over all {n} frames, {rate_steady:.2f} triplets/s steady state; "
          f"target >= {TARGET_TRIPLETS_PER_S:g}: all frames {verdict_all}, steady state {verdict_steady}")
    load1 = os.getloadavg()
    print(f"load average at the end of the phantom part: {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")

    # -- real endoscope stereo (issue 14) ---------------------------------------------------------------------------
    print()
    print("--- in-vivo stereo endoscope (Hamlyn heart, 360x288): sparse default, dense mode, backends (issue 14) ---")
    with single_threaded_blas():
        print(f"BLAS threads in effect: {blas_threads()} (threadpoolctl.threadpool_limits(1))")
        real = bench_real(quick=quick)

    def clean(r):
        return {k: v for k, v in r.items() if k != "uv"}

    return {"input": {"scene": str(SCENE.relative_to(REPO)), **seq, "frames": n, "cameras": len(cams), "width": W,
                      "height": H},
            "blas_threads": "1", "opencv_threads": cv2.getNumThreads(), "reader_workers": CLI_WORKERS,
            "runs": [{"wall_s": r["wall_s"], "setup_s": r["setup_s"],
                      "steady_s": sum(f["total_s"] for f in r["frames"][1:])} for r in runs],
            "frames": run["frames"],
            "setup": {"total_s": run["setup_s"], "roi_read_s": run["roi_read_s"], "roi_compute_s": run["roi_compute_s"],
                      "tracker_s": run["tracker_setup_s"]},
            "per_triplet_all_s": all_, "per_triplet_steady_s": steady, "triplets_per_s_all": rate_all,
            "triplets_per_s_steady": rate_steady, "tracks": run["tracks"], "points_mean": run["points_mean"],
            "points_min": run["points_min"], "redetections": run["redetections"],
            "cpu_per_triplet_steady_s": cpu,
            "baselines": {"decode": dec, "tracking": trk, "detect_match": {k: clean(v) for k, v in dm.items()},
                          "kornia_note": kornia_note},
            "ratios": {"steady_over_imread_1_thread": steady["total_s"] / d1,
                       "steady_over_imread_2_threads": steady["total_s"] / d2,
                       "tracking_over_plain_lk": steady["tracking_s"] / lk,
                       **({"kornia_over_opencv_detect_match": dm["kornia"]["total_s"] / base} if "kornia" in dm
                          else {})},
            "target_triplets_per_s": TARGET_TRIPLETS_PER_S, "verdict_all": verdict_all,
            "verdict_steady": verdict_steady, "options_note": opts_note, "load_average_start": list(load0),
            "load_average_end": list(load1), "real": real}
