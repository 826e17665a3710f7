"""The ``measure`` section on real endoscope stereo: the Hamlyn in-vivo beating heart (issue 14 acceptance: the
sparse default at >= 25 pairs per second at 360x288 on the project's 2-core machine, i.e. real time for PAL video;
the dense mode's rate and points per frame; GPU rates where a CUDA device is present).

Called by :func:`benchmarks.measure.bench_measure` (already under ``threadpoolctl.threadpool_limits(1)``: one BLAS
thread) through :func:`bench_real`. Everything runs in this process, as ``heartcv measure`` runs it
(``cli/measure.py``), without writing the output files:

1. **Input**: ``../shared/data/hamlyn_invivo_heart`` relative to the repository root (or ``$HEARTCV_BENCH_REAL``):
   300 rectified stereo pairs, ``cam0/`` and ``cam1/``, 360x288 colour PNG. N = 300 pairs (60 in ``--quick``).
   Where the folder (or enough pairs) is missing the section prints why it was skipped and returns
   ``{"skipped": reason}``; it never fails the benchmark. The rig is the one ``heartcv rig rectified --image-size
   360x288 --focal-px 390 --baseline-m 0.0055`` writes (:func:`heartcv.rig_formats.rectified_rig`, written to a
   temporary rig file with :func:`heartcv.io.write_rig` and read back with :func:`heartcv.io.read_rig`, as the CLI
   hands it to ``heartcv measure``).
2. **Sparse default** (``heartcv measure SEQ --rig RIG``, no option): ``open_frame_source``, a colour
   ``FrameReader`` (2 decoding threads, reads ahead), ``MeasureOptions()`` resolved for the image size
   (``for_image``: the CLI's defaults), the automatic region of interest ``auto_region(reference_frames(reader.read,
   N, 0), opts)``, then ``measure_sequence(reader, cameras, opts, roi=roi)`` with the OpenCV backend. 3 runs (1 in
   ``--quick``); the run with the median wall time is shown. *All frames* = N / wall from opening the source to
   the last step (region of interest and first detection included: the CLI's ``frames_per_s``); *steady state* =
   (N - 1) / time of frames 1 .. N-1. Split per pair from ``run.frames`` (``FrameStats``: decode wait, tracking,
   triangulation, detection + matching, rest of the loop) and the setup; points per frame (min / mean),
   ``track_length_median_frames`` (span first-to-last seen, :func:`heartcv.measure_data.track_lengths`),
   reprojection RMS, sigma and the candidates each gate removed (``run.result.rejected``), all from
   :func:`heartcv.measure_data.measurement_summary` as the CLI reports them. Target: 25 pairs/s (PASS/FAIL, all
   frames and steady state).
3. **Dense mode** (``heartcv measure SEQ --rig RIG --dense``): a gray ``FrameReader`` and
   ``heartcv.dense.dense_sequence(reader, cameras, DenseOptions(ref_camera=0))`` (whole image, no region of
   interest, as the CLI without ``--mask``). 3 runs (1 in ``--quick``). Pairs per second, split and points per
   frame; target >= 1000 points in every frame (PASS/FAIL).
4. **Other backends of the sparse stage** (1 run each): ``get_backend('kornia', 'cpu')`` with
   ``torch.set_num_threads(1)`` (what the CLI sets for a CPU kornia backend) when ``import kornia`` works, and
   ``get_backend('kornia', 'cuda')`` when ``torch.cuda.is_available()`` (after one untimed 10-frame warm-up run that
   initialises CUDA), else the line "no CUDA device: GPU rates not measured". The dense mode has no GPU
   implementation (OpenCV SGBM and DIS flow on the CPU; ``--device`` only applies to ``--backend kornia``): the
   output says so instead of reporting a GPU rate.
5. **Baseline in the same run**: decoding only, ``FrameReader`` iterated over the same N pairs with nothing else
   to do (colour, as the sparse stage reads them, and gray, as the dense mode does; median of 3 passes, 1 in
   ``--quick``, one warm-up pass): ratios stage per pair / decode-only per pair.
6. The load average (``os.getloadavg()``) at the start and the end, and after every timed run: other processes
   share the 2 cores.
"""

from __future__ import annotations

import os
from pathlib import Path
import tempfile
import time
import traceback

import numpy as np

from ._harness import fmt_ratio, fmt_time, measure, table

__all__ = ["bench_real", "DATA", "TARGET_PAIRS_PER_S", "TARGET_DENSE_POINTS"]

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "hamlyn_invivo_heart"
IMAGE_SIZE = (360, 288)
FOCAL_PX = 390.0
BASELINE_M = 0.0055
FPS = 25.0                      # PAL video (the data's README)
TARGET_PAIRS_PER_S = 25.0       # issue 14: real time for PAL video
TARGET_DENSE_POINTS = 1000      # issue 14: dense mode, points in every frame
CLI_WORKERS = 2                 # heartcv measure --workers default
RIG_COMMAND = (f"heartcv rig rectified --image-size {IMAGE_SIZE[0]}x{IMAGE_SIZE[1]} --focal-px {FOCAL_PX:g} "
               f"--baseline-m {BASELINE_M:g}")


def _fmt_load(la) -> str:
    return f"{la[0]:.2f} {la[1]:.2f} {la[2]:.2f}"


# -- input ------------------------------------------------------------------------------------------------------
def _folder() -> Path:
    return Path(os.environ.get("HEARTCV_BENCH_REAL") or DATA)


def _why_unusable(folder: Path, n: int) -> str | None:
    """Why the in-vivo data cannot be used (None: it can)."""
    if not folder.is_dir():
        return f"{folder} not found (the shared data folder is not reachable from this checkout)"
    for cam in ("cam0", "cam1"):
        d = folder / cam
        if not d.is_dir():
            return f"{d} not found"
        have = len(list(d.glob("*.png")))
        if have < n:
            return f"{d}: {have} PNG images, {n} needed"
    return None


def _rig(tmp: Path):
    """The rig ``heartcv rig rectified --image-size 360x288 --focal-px 390 --baseline-m 0.0055`` writes, through
    a rig file as ``heartcv measure --rig`` reads it."""
    from heartcv.io import read_rig, write_rig
    from heartcv.rig_formats import rectified_rig

    w, h = IMAGE_SIZE
    rig = rectified_rig(w, h, FOCAL_PX, BASELINE_M, None, ["cam0", "cam1"])
    # the meta cli/rig.py adds (provenance only)
    rig = type(rig)(rig.cameras, {"producer": "heartcv rig rectified", "rectified": True, "focal_px": FOCAL_PX,
                                  "baseline_m": BASELINE_M, "principal_point": list(rig.cameras[0].K[:2, 2])})
    path = tmp / "rig.yaml"
    write_rig(path, rig)
    return read_rig(path)


def _sparse_options(width: int, height: int):
    """``MeasureOptions()`` resolved for the image size, and whether it equals what cli/measure.py builds from its
    own defaults (checked when its private builder can be called; a note otherwise)."""
    from heartcv.measure import MeasureOptions

    opts = MeasureOptions().for_image(width, height)
    try:
        from heartcv.cli.measure import _options as cli_options

        cli = cli_options(0, 300, None, None, None, 0.01, 3.0).for_image(width, height)
        note = "equal to the CLI's defaults" if cli == opts else f"DIFFERS from the CLI's defaults: {cli}"
    except Exception as exc:  # the CLI's private builder changed: not checked
        note = f"not compared with cli/measure.py ({type(exc).__name__}: {exc})"
    return opts, note


# -- runs -------------------------------------------------------------------------------------------------------
def _frame_rows(run) -> list:
    return [{"frame": f.frame, "total_s": f.total_s, "decode_s": f.wait_s, "tracking_s": f.tracking_s,
             "triangulation_s": f.triangulation_s, "detection_s": f.detection_s,
             "other_s": f.total_s - f.wait_s - f.tracking_s - f.triangulation_s - f.detection_s, "seen": f.seen,
             "detected": f.detected} for f in run.frames]


def _summarise(run, n: int, wall: float, setup: dict) -> dict:
    from heartcv.measure_data import measurement_summary

    res = run.result
    if run.problems or run.skipped:
        raise RuntimeError(f"images left out: {list(run.problems)[:3]}, frames skipped: {run.skipped[:10]}")
    frames = _frame_rows(run)
    summary = measurement_summary(res, np.arange(n) / FPS, wall, run.wait_s)
    keys = ("decode_s", "tracking_s", "triangulation_s", "detection_s", "other_s")
    setup_s = sum(setup.values()) + run.setup_s
    all_ = {k: sum(f[k] for f in frames) / n for k in keys}
    all_["setup_s"] = setup_s / n
    all_["total_s"] = wall / n
    steady = {k: sum(f[k] for f in frames[1:]) / (n - 1) for k in keys}
    steady["setup_s"] = 0.0
    steady["total_s"] = sum(f["total_s"] for f in frames[1:]) / (n - 1)
    return {"wall_s": wall, "setup_s": setup_s, "setup": {**setup, "tracker_s": run.setup_s},
            "pairs_per_s_all": n / wall, "pairs_per_s_steady": 1.0 / steady["total_s"],
            "per_pair_all_s": all_, "per_pair_steady_s": steady, "frames": frames,
            "redetections": int(sum(1 for f in frames[1:] if f["detected"])), "summary": summary,
            "load_after": list(os.getloadavg())}


def _sparse_run(folder: Path, rig, n: int, opts, backend) -> dict:
    """One run of the sparse stage as cli/measure.py ``_run`` drives it (no mask: the automatic region)."""
    from heartcv.io import FrameReader, open_frame_source
    from heartcv.measure import auto_region, measure_sequence, reference_frames

    t0 = time.perf_counter()
    source = open_frame_source(folder, cameras=rig.names)
    with FrameReader(source, mode="color", sizes=[c.size for c in rig.cameras], frames=range(n),
                     workers=CLI_WORKERS) as reader:
        t1 = time.perf_counter()
        first = reference_frames(reader.read, n, opts.ref_camera)
        t2 = time.perf_counter()
        roi = auto_region(first, opts)
        t3 = time.perf_counter()
        run = measure_sequence(reader, rig.cameras, opts, roi=roi, backend=backend)
    wall = time.perf_counter() - t0
    out = _summarise(run, n, wall, {"open_s": t1 - t0, "roi_read_s": t2 - t1, "roi_compute_s": t3 - t2})
    out["roi_frames"] = len(first)
    return out


def _dense_run(folder: Path, rig, n: int) -> dict:
    """One run of ``heartcv measure --dense`` (no mask: the whole image)."""
    from heartcv.dense import DenseOptions, dense_sequence
    from heartcv.io import FrameReader, open_frame_source

    t0 = time.perf_counter()
    source = open_frame_source(folder, cameras=rig.names)
    with FrameReader(source, mode="gray", sizes=[c.size for c in rig.cameras], frames=range(n),
                     workers=CLI_WORKERS) as reader:
        t1 = time.perf_counter()
        run = dense_sequence(reader, rig.cameras, DenseOptions(ref_camera=0), roi=None)
    wall = time.perf_counter() - t0
    return _summarise(run, n, wall, {"open_s": t1 - t0})


def _rig_check(folder: Path, rig, n: int, repeats: int, warmup: int) -> dict:
    """The SIFT checks ``heartcv measure`` runs before measuring (cli/measure.py ``_descriptor_matches``, then the
    rectified pair's descriptor offset, the epipolar distance and the share of matches in front of the cameras):
    median seconds of ``repeats``, against decoding the same instants alone."""
    from heartcv.io import FrameReader, open_frame_source
    from heartcv.matching import (
        descriptor_epipolar_distance,
        descriptor_front_fraction,
        descriptor_matches,
        descriptor_v_offset,
    )

    ks = [int(k) for k in np.unique(np.linspace(0, min(n, 30) - 1, 5).round())]
    source = open_frame_source(folder, cameras=rig.names)
    with FrameReader(source, mode="color", sizes=[c.size for c in rig.cameras], frames=range(n), workers=1) as rd:
        result = {}

        def check():
            matches = []
            for k in ks:
                views = rd.read(k)[0]
                matches.append(descriptor_matches(views[0], views[1]))
                if sum(len(m[0]) for m in matches) >= 500:
                    break
            result.update(instants=len(matches), matches=int(sum(len(m[0]) for m in matches)),
                          offset_px=descriptor_v_offset(matches)[0],
                          epipolar_px=descriptor_epipolar_distance(rig.cameras[0], rig.cameras[1], matches)[0],
                          front_fraction=descriptor_front_fraction(rig.cameras[0], rig.cameras[1], matches)[0])

        def decode():
            for k in ks[:max(result.get("instants", len(ks)), 1)]:
                rd.read(k)

        t = measure(check, repeats=repeats, warmup=warmup)
        d = measure(decode, repeats=repeats, warmup=warmup)
    return dict(result, seconds=t.median, decode_s=d.median)


def _median_run(runs: list) -> dict:
    order = sorted(range(len(runs)), key=lambda i: runs[i]["wall_s"])
    return runs[order[len(runs) // 2]]


def _decode_baseline(folder: Path, rig, n: int, mode: str, repeats: int, warmup: int) -> dict:
    from heartcv.io import FrameReader, open_frame_source

    src = open_frame_source(folder, cameras=rig.names)
    sizes = [c.size for c in rig.cameras]

    def reader_alone():
        with FrameReader(src, mode=mode, sizes=sizes, frames=range(n), workers=CLI_WORKERS) as reader:
            for _ in reader:
                pass

    t = measure(reader_alone, repeats=repeats, warmup=warmup, number=1)
    return {"per_pair_s": t.median / n, "min_per_pair_s": t.min / n, "pairs_per_s": n / t.median,
            "pass": t.as_dict(), "pairs": n, "mode": mode}


# -- printing ---------------------------------------------------------------------------------------------------
_NAMES = {"decode_s": "decode (waiting for the reader)", "tracking_s": "tracking", "triangulation_s": "triangulation",
          "detection_s": "detection + matching", "other_s": "other (loop, bookkeeping)"}


def _split_table(run: dict, n: int, title: str, names=None) -> str:
    names = {**_NAMES, **(names or {})}
    a, s = run["per_pair_all_s"], run["per_pair_steady_s"]
    setup = ", ".join(k[:-2].replace("_", " ") for k in run["setup"])
    rows = []
    for key in ("decode_s", "tracking_s", "triangulation_s", "detection_s", "other_s"):
        rows.append([names[key], fmt_time(a[key]), f"{100 * a[key] / a['total_s']:.1f} %", fmt_time(s[key]),
                     f"{100 * s[key] / s['total_s']:.1f} %"])
    rows.append([f"setup ({setup})", fmt_time(a["setup_s"]), f"{100 * a['setup_s'] / a['total_s']:.1f} %", "-",
                 "-"])
    rows.append(["total per pair", fmt_time(a["total_s"]), "100 %", fmt_time(s["total_s"]), "100 %"])
    rows.append(["pairs per second", f"{run['pairs_per_s_all']:.2f}", "", f"{run['pairs_per_s_steady']:.2f}", ""])
    return table(["per stereo pair", f"all {n} frames", "share", f"steady (1..{n - 1})", "share"], rows, title=title)


def _quality_line(run: dict) -> str:
    s = run["summary"]
    setup = ", ".join(f"{k[:-2].replace('_', ' ')} {fmt_time(v)}" for k, v in run["setup"].items())
    rms = s["reprojection_rms_px"]
    rej = ", ".join(f"{g} {v}" for g, v in s["rejected"].items()) or "none recorded"
    return (f"points per frame min {s['points_min']} / mean {s['points_mean']:.0f} / max {s['points_max']}, "
            f"tracks {s['tracks']}, track_length_median_frames {s['track_length_median_frames']:g} (seen "
            f"{s['track_seen_median_frames']:g}), reprojection RMS {'-' if rms is None else f'{rms:.3f} px'}, "
            f"sigma {s['sigma_px']:.3f} px, views {s['views_mean']:.2f}, region {s['roi_px']} px, "
            f"re-detections after frame 0: {run['redetections']}\n  setup: {setup}\n"
            f"  candidates removed per gate: {rej}")


def _rates_line(runs: list) -> str:
    return "all runs: " + "; ".join(f"{r['pairs_per_s_all']:.2f} all / {r['pairs_per_s_steady']:.2f} steady pairs/s "
                                    f"(load {r['load_after'][0]:.2f})" for r in runs)


def _verdict(rate: float, target: float) -> str:
    return "PASS" if rate >= target else "FAIL"


# -- the section ------------------------------------------------------------------------------------------------
def bench_real(*, quick: bool = False) -> dict:
    """The in-vivo part of the ``measure`` section (module docstring); call it under single-threaded BLAS."""
    import cv2

    n = 60 if quick else 300
    runs_n = 1 if quick else 3
    reps = 1 if quick else 3
    warm = 0 if quick else 1
    folder = _folder()
    load0 = os.getloadavg()
    print(f"load average (1, 5, 15 min) at start of the in-vivo part: {_fmt_load(load0)} on {os.cpu_count()} CPUs")
    why = _why_unusable(folder, n)
    if why is not None:
        print(f"in-vivo stereo (Hamlyn heart) SKIPPED: {why}")
        return {"skipped": why, "folder": str(folder)}
    out = {"input": {"folder": str(folder), "pairs": n, "image_size": list(IMAGE_SIZE), "rig_command": RIG_COMMAND,
                     "fps_assumed": FPS},
           "reader_workers": CLI_WORKERS, "opencv_threads": cv2.getNumThreads(),
           "target_pairs_per_s": TARGET_PAIRS_PER_S, "target_dense_points_min": TARGET_DENSE_POINTS,
           "load_average_start": list(load0)}
    with tempfile.TemporaryDirectory(prefix="heartcv-bench-rig-") as tmp:
        rig = _rig(Path(tmp))
    W, H = rig.cameras[0].width, rig.cameras[0].height
    where = os.path.relpath(folder, REPO)
    print(f"input: {where}, first {n} stereo pairs, 2 cameras {W}x{H} colour PNG; rig as `{RIG_COMMAND}` writes it; "
          f"FrameReader workers {CLI_WORKERS}, OpenCV threads {cv2.getNumThreads()}")
    opts, opts_note = _sparse_options(W, H)
    out["options"] = {"note": opts_note, "max_points": opts.max_points, "min_distance_px": opts.min_distance_px,
                      "corner_block_size": opts.corner_block_size, "corner_quality": opts.corner_quality,
                      "highpass_sigma": opts.highpass_sigma, "lk_window": opts.lk.window,
                      "match_radius": opts.match_radius}
    print(f"sparse options: MeasureOptions().for_image({W}, {H}) ({opts_note}): {opts.max_points} points, "
          f"min distance {opts.min_distance_px:g} px, corner block {opts.corner_block_size}, quality "
          f"{opts.corner_quality:g}, LK window {opts.lk.window}, NCC radius {opts.match_radius}, highpass "
          f"{opts.highpass_sigma:g}")

    from heartcv.backend import get_backend

    # -- baseline: decoding only ----------------------------------------------------------------------------------
    dec = {"color": _decode_baseline(folder, rig, n, "color", reps, warm),
           "gray": _decode_baseline(folder, rig, n, "gray", reps, warm)}
    out["decode"] = dec

    # -- sparse default, OpenCV -----------------------------------------------------------------------------------
    sparse = None
    try:
        runs = [_sparse_run(folder, rig, n, opts, get_backend("opencv", None)) for _ in range(runs_n)]
        sparse = _median_run(runs)
        out["sparse_opencv"] = {"runs": runs, "median_run": runs.index(sparse)}
        print()
        print(_split_table(sparse, n, f"Sparse default (`heartcv measure`, OpenCV backend) on the in-vivo heart; run "
                                      f"with the median wall of {runs_n}",
                           {"tracking_s": "tracking (high-pass + template LK, FB + NCC)"}))
        print(_quality_line(sparse))
        if runs_n > 1:
            print(_rates_line(runs))
    except Exception as exc:
        print(f"sparse stage FAILED: {type(exc).__name__}: {exc}")
        traceback.print_exc()
        out["sparse_opencv"] = {"error": f"{type(exc).__name__}: {exc}"}

    # -- dense ----------------------------------------------------------------------------------------------------
    dense = None
    try:
        runs = [_dense_run(folder, rig, n) for _ in range(runs_n)]
        dense = _median_run(runs)
        out["dense"] = {"runs": runs, "median_run": runs.index(dense)}
        print()
        print(_split_table(dense, n, f"Dense mode (`heartcv measure --dense`: SGBM + DIS flow, CPU) on the same "
                                     f"pairs; run with the median wall of {runs_n}",
                           {"tracking_s": "tracking (DIS flow, FB check)",
                            "detection_s": "rectify + SGBM disparity + reseeding",
                            "triangulation_s": "noise probe + triangulation"}))
        print(_quality_line(dense))
        if runs_n > 1:
            print(_rates_line(runs))
    except Exception as exc:
        print(f"dense mode FAILED: {type(exc).__name__}: {exc}")
        traceback.print_exc()
        out["dense"] = {"error": f"{type(exc).__name__}: {exc}"}

    # -- the rig check (SIFT descriptors: vertical offset, epipolar distance, cameras in front) ----------------------
    try:
        out["rig_check"] = _rig_check(folder, rig, n, reps, warm)
        rc = out["rig_check"]
        base = f"{fmt_ratio(rc['seconds'] / sparse['wall_s'])} of the sparse stage's wall" if sparse else ""
        print(f"rig check (`heartcv measure`'s SIFT matches on {rc['instants']} instants of the first 30, "
              f"{rc['matches']} matches; offset {rc['offset_px']:+.3f} px, epipolar {rc['epipolar_px']:.3f} px, "
              f"{100 * rc['front_fraction']:.0f} % in front): {fmt_time(rc['seconds'])} (median of {reps}), "
              f"{fmt_ratio(rc['seconds'] / rc['decode_s'])} decoding those instants; {base}")
    except Exception as exc:
        print(f"rig check FAILED: {type(exc).__name__}: {exc}")
        traceback.print_exc()
        out["rig_check"] = {"error": f"{type(exc).__name__}: {exc}"}

    # -- kornia backend (CPU, and CUDA where present) ---------------------------------------------------------------
    others = {}
    try:
        import kornia
        import torch
    except Exception as exc:  # kornia/torch missing or broken
        kornia = torch = None
        out["kornia_note"] = f"kornia backend not measured: import failed ({type(exc).__name__}: {exc})"
    if torch is not None:
        out["kornia_note"] = f"kornia {kornia.__version__}, torch {torch.__version__}"
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            others["kornia_cpu"] = _sparse_run(folder, rig, n, opts, get_backend("kornia", "cpu"))
        except Exception as exc:
            print(f"kornia CPU run FAILED: {type(exc).__name__}: {exc}")
            traceback.print_exc()
            others["kornia_cpu"] = {"error": f"{type(exc).__name__}: {exc}"}
        finally:
            torch.set_num_threads(threads)
        cuda = bool(torch.cuda.is_available())
        out["cuda_available"] = cuda
        if cuda:
            out["cuda_device"] = torch.cuda.get_device_name(0)
            try:
                be = get_backend("kornia", "cuda")
                _sparse_run(folder, rig, min(n, 10), opts, be)          # CUDA context and kernels: not timed
                others["kornia_cuda"] = _sparse_run(folder, rig, n, opts, be)
            except Exception as exc:
                print(f"kornia CUDA run FAILED: {type(exc).__name__}: {exc}")
                traceback.print_exc()
                others["kornia_cuda"] = {"error": f"{type(exc).__name__}: {exc}"}
            out["cuda_note"] = f"CUDA device {out['cuda_device']}: sparse stage with get_backend('kornia', 'cuda')"
        else:
            out["cuda_note"] = (f"no CUDA device (torch {torch.__version__}: torch.cuda.is_available() is False): "
                                "GPU rates not measured")
    else:
        out["cuda_available"] = False
        out["cuda_note"] = "no CUDA device (torch not importable): GPU rates not measured"
    out["dense_gpu_note"] = ("dense mode: no GPU implementation (cv2.StereoSGBM and cv2.DISOpticalFlow on the CPU; "
                             "--device applies to --backend kornia only): no GPU rate for it")
    out.update(others)

    # -- summary ----------------------------------------------------------------------------------------------------
    rows = []
    if sparse is not None:
        rows.append(["sparse, OpenCV (default)", f"{sparse['pairs_per_s_all']:.2f}",
                     f"{sparse['pairs_per_s_steady']:.2f}", f"{sparse['summary']['points_min']}",
                     f"{sparse['summary']['points_mean']:.0f}", f"{sparse['summary']['track_length_median_frames']:g}",
                     fmt_ratio(sparse["per_pair_steady_s"]["total_s"] / dec["color"]["per_pair_s"])])
    for key, label in (("kornia_cpu", "sparse, kornia CPU (1 torch thread)"), ("kornia_cuda", "sparse, kornia CUDA")):
        r = others.get(key)
        if r and "error" not in r:
            rows.append([label, f"{r['pairs_per_s_all']:.2f}", f"{r['pairs_per_s_steady']:.2f}",
                         f"{r['summary']['points_min']}", f"{r['summary']['points_mean']:.0f}",
                         f"{r['summary']['track_length_median_frames']:g}",
                         fmt_ratio(r["per_pair_steady_s"]["total_s"] / dec["color"]["per_pair_s"])])
    if dense is not None:
        rows.append(["dense (SGBM + DIS, CPU)", f"{dense['pairs_per_s_all']:.2f}", f"{dense['pairs_per_s_steady']:.2f}",
                     f"{dense['summary']['points_min']}", f"{dense['summary']['points_mean']:.0f}",
                     f"{dense['summary']['track_length_median_frames']:g}",
                     fmt_ratio(dense["per_pair_steady_s"]["total_s"] / dec["gray"]["per_pair_s"])])
    for mode in ("color", "gray"):
        d = dec[mode]
        rows.append([f"baseline: FrameReader alone, {mode} (median of {reps})", f"{d['pairs_per_s']:.2f}", "-", "-",
                     "-", "-", "1.00x"])
    print()
    print(table(["in-vivo heart, 360x288 stereo", f"pairs/s all {n}", "steady", "points min", "mean",
                 "track median", "steady / decode"], rows, title="Summary (steady / decode: per pair, against the "
                                                                  "FrameReader of the same mode)"))
    for key, label in (("kornia_cpu", "kornia CPU"), ("kornia_cuda", "kornia CUDA")):
        r = others.get(key)
        if r and "error" not in r and sparse is not None:
            a, b = sparse["per_pair_steady_s"], r["per_pair_steady_s"]
            same = [f["seen"] for f in r["frames"]] == [f["seen"] for f in sparse["frames"]]
            r["same_points_per_frame_as_opencv"] = same
            print(f"{label}: steady per pair {fmt_time(b['total_s'])} ({fmt_ratio(b['total_s'] / a['total_s'])} "
                  f"OpenCV), detection + matching {fmt_time(b['detection_s'])} per pair vs "
                  f"{fmt_time(a['detection_s'])}; setup {fmt_time(r['setup_s'])} vs {fmt_time(sparse['setup_s'])}; "
                  f"same points per frame as OpenCV: {same}")
    print(out["kornia_note"])
    print(out["cuda_note"])
    print(out["dense_gpu_note"])

    if sparse is not None:
        va = _verdict(sparse["pairs_per_s_all"], TARGET_PAIRS_PER_S)
        vs = _verdict(sparse["pairs_per_s_steady"], TARGET_PAIRS_PER_S)
        out.update(pairs_per_s_all=sparse["pairs_per_s_all"], pairs_per_s_steady=sparse["pairs_per_s_steady"],
                   verdict_all=va, verdict_steady=vs,
                   stage_over_decode_steady=sparse["per_pair_steady_s"]["total_s"] / dec["color"]["per_pair_s"],
                   stage_over_decode_all=sparse["per_pair_all_s"]["total_s"] / dec["color"]["per_pair_s"])
        print(f"sparse default: {sparse['pairs_per_s_all']:.2f} pairs/s over all {n} frames, "
              f"{sparse['pairs_per_s_steady']:.2f} steady state; stage / decode-only = "
              f"{out['stage_over_decode_all']:.2f}x (all frames), {out['stage_over_decode_steady']:.2f}x (steady); "
              f"target >= {TARGET_PAIRS_PER_S:g} pairs/s: all frames {va}, steady state {vs}")
    if dense is not None:
        pts = dense["summary"]["points_min"]
        vd = _verdict(pts, TARGET_DENSE_POINTS)
        out.update(dense_pairs_per_s_all=dense["pairs_per_s_all"], dense_pairs_per_s_steady=dense["pairs_per_s_steady"],
                   dense_points_min=pts, dense_verdict_points=vd)
        print(f"dense mode: {dense['pairs_per_s_all']:.2f} pairs/s over all {n} frames, "
              f"{dense['pairs_per_s_steady']:.2f} steady state; points per frame min {pts} (target >= "
              f"{TARGET_DENSE_POINTS} in every frame: {vd})")
    load1 = os.getloadavg()
    out["load_average_end"] = list(load1)
    print(f"load average at the end of the in-vivo part: {_fmt_load(load1)}")
    return out
