"""Section ``calibrate`` of ``python -m benchmarks``: the cost of the rig calibration
(:func:`heartcv.calibration_rig.calibrate_rig_detailed`) and of its parts, against the single-camera OpenCV
calibrations of the same detections measured in the same run.

Data sets (detections made once, outside the timing):

* **synthetic**: the paper's rig (3 cameras 1920x1080, ``paper_rig``), 40 board poses of the issue's ChArUco target
  (``board_poses``, seed 5) and the projected corners with 0.1 px noise (``observe``, seed 1), from
  ``tests/heartcv/test_calibration.py`` (the accuracy tests' data; ``python -m benchmarks`` runs from the repository
  root, where the tests package imports). Synthetic frame times for the sync row: instant ``v`` at ``v`` seconds,
  each camera view offset by up to +-3 ms (seed 3).
* **caliscope** (when ``../shared/data/caliscope_4cam_charuco`` exists): the inverted 4x5 ChArUco board detected
  (:func:`heartcv.detect.detect`) in every frame of the 4 videos of ``calibration/extrinsic`` (1280x720, 57 frames
  each); the decoding and detection time per frame is reported separately. The sync row uses the recorder's
  ``timestamps.csv`` (:func:`heartcv.video.read_camera_times`).

Rows per data set: **baseline** = :func:`heartcv.calibration.calibrate_intrinsics` (``cv2.calibrateCameraExtended``
with outlier rejection) of every camera; then ``calibrate_rig_detailed`` with the default ``folds=5``, with
``folds=0`` (no k-fold check: the ratio shows the check's cost) and with ``times=`` (the sync path). The rows take
turns run by run (a slow spell of a shared machine hits all of them alike) after one warm-up of the baseline and of
``folds=0`` (on the first data set only; none in ``--quick``); median and min of the runs, ratio of the medians to
the baseline. Parts of each rig run are timed by wrapping, while the rig rows run, the functions
``heartcv.calibration_rig`` calls (outermost calls only): single-camera calibrations (two per camera when the
coverage restricts the distortion terms: the full one and the joint refinement's start), initial rig poses, sync
weights, joint refinement (``bundle_adjust``: the outlier rounds and the reruns after a distortion fold; the
``refinements`` column counts them), problem assembly, k-fold check (its refits included) and the rest. Everything
runs under
``threadpoolctl.threadpool_limits(1)`` for BLAS (OpenCV keeps its default thread count, printed, except in
``cv2.calibrateCameraExtended``, which :mod:`heartcv.calibration` runs on one thread for reproducible results).
"""

from __future__ import annotations

from collections import defaultdict
import contextlib
import os
from pathlib import Path
import statistics
import time

import numpy as np

from ._harness import Timing, blas_threads, fmt_ratio, fmt_time, measure, single_threaded_blas, table

__all__ = ["bench_calibrate", "CALISCOPE"]

REPO = Path(__file__).resolve().parents[1]
CALISCOPE = REPO.parent / "shared" / "data" / "caliscope_4cam_charuco" / "calibration" / "extrinsic"

# the functions of heartcv.calibration_rig timed as parts, and their labels
PARTS = {"calibrate_intrinsics": "single-camera calibrations (step 1)",
         "_initial_cam_from_rig": "initial rig poses (spanning tree)",
         "_sync": "sync weights (times=)",
         "_build_problem": "problem assembly",
         "bundle_adjust": "joint refinement (bundle_adjust rounds)",
         "_kfold": "k-fold check (refits included)"}
ROWS = ("baseline", "folds=5", "folds=0", "times=")


# -- data -------------------------------------------------------------------------------------------------------------
def _synthetic():
    """(detections, spec, sizes, names, times, source) of the paper rig, 40 views, 0.1 px noise."""
    from tests.heartcv.test_calibration import CHARUCO, board_poses, observe, paper_rig  # run from the repo root

    source = "tests.heartcv.test_calibration (paper_rig, board_poses seed 5, observe seed 1)"
    cams, c0w = paper_rig()
    poses = board_poses(40, np.random.default_rng(5), CHARUCO)
    dets = observe(cams, c0w, poses, CHARUCO, np.random.default_rng(1), noise=0.1)
    n_cam, n_views = len(cams), len(poses)
    rng = np.random.default_rng(3)
    times = np.arange(n_views, dtype=float)[None] + rng.uniform(-3e-3, 3e-3, (n_cam, n_views))
    return dets, CHARUCO, [(c.width, c.height) for c in cams], [c.name for c in cams], times, source


def _caliscope():
    """(detections, spec, sizes, names, times, detection info) of the caliscope session, or None without the data."""
    from heartcv.detect import detect
    from heartcv.targets import TargetSpec
    from heartcv.video import iter_frames, read_camera_times

    videos = [CALISCOPE / f"cam_{i}.mp4" for i in range(4)]
    if not all(p.is_file() for p in videos) or not (CALISCOPE / "timestamps.csv").is_file():
        return None
    spec = TargetSpec("charuco", (4, 5), 0.054, 0.0405, "DICT_4X4_1000", inverted=True)  # charuco.toml
    names = [p.stem for p in videos]
    dets, sizes, t_decode, t_detect = [], [], [], []
    for path in videos:
        found, it = [], iter_frames(path)
        while True:
            t0 = time.perf_counter()
            item = next(it, None)
            t1 = time.perf_counter()
            if item is None:
                break
            frame = item[1]
            found.append(detect(frame, spec))
            t_decode.append(t1 - t0)
            t_detect.append(time.perf_counter() - t1)
        dets.append(found)
        sizes.append((frame.shape[1], frame.shape[0]))
    t = read_camera_times(CALISCOPE / "timestamps.csv", names, [len(d) for d in dets])
    times = np.stack([np.asarray(t[n], float) for n in names])
    info = {"frames": len(t_detect), "frames_with_target": [int(sum(len(d) > 0 for d in ds)) for ds in dets],
            "detect_per_frame_median_s": statistics.median(t_detect),
            "detect_per_frame_mean_s": float(np.mean(t_detect)),
            "decode_per_frame_median_s": statistics.median(t_decode), "detect_total_s": float(np.sum(t_detect)),
            "decode_total_s": float(np.sum(t_decode)), "image_size": list(sizes[0])}
    return dets, spec, sizes, names, times, info


# -- parts ------------------------------------------------------------------------------------------------------------
class _Parts:
    """Wraps the functions of :mod:`heartcv.calibration_rig` named in PARTS while active; per call of the rig
    calibration (``start()`` .. ``stop()``) the time of their outermost calls and the call counts."""

    def __init__(self):
        self.stack, self.runs = [], []
        self.cur = self.calls = self.nested = None

    def start(self):
        self.cur, self.calls, self.nested = defaultdict(float), defaultdict(int), defaultdict(int)

    def stop(self, total):
        self.runs.append({"total_s": total, "parts_s": dict(self.cur), "calls": dict(self.calls),
                          "nested_calls": dict(self.nested)})

    def _wrap(self, name, fn):
        def timed(*args, **kwargs):
            outer = not self.stack
            self.stack.append(name)
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                dt = time.perf_counter() - t0
                self.stack.pop()
                if self.cur is not None:
                    if outer:
                        self.cur[name] += dt
                        self.calls[name] += 1
                    else:
                        self.nested[name] += 1
        return timed

    @contextlib.contextmanager
    def active(self):
        import heartcv.calibration_rig as mod

        saved = {n: getattr(mod, n) for n in PARTS}
        try:
            for n, fn in saved.items():
                setattr(mod, n, self._wrap(n, fn))
            yield self
        finally:
            for n, fn in saved.items():
                setattr(mod, n, fn)


# -- one data set -----------------------------------------------------------------------------------------------------
def _bench_set(label, dets, spec, sizes, names, times, *, repeats, warmup):
    from heartcv.calibration import calibrate_intrinsics
    from heartcv.calibration_rig import calibrate_rig_detailed

    parts = {r: _Parts() for r in ROWS[1:]}
    last = {}

    def baseline():
        last["baseline"] = [calibrate_intrinsics(d, spec, s, name=n) for d, s, n in zip(dets, sizes, names)]

    def rig(row, **kw):
        def run():
            p = parts[row]
            with p.active():
                p.start()
                t0 = time.perf_counter()
                last[row] = calibrate_rig_detailed(dets, spec, sizes, names=names, **kw)
                p.stop(time.perf_counter() - t0)
        return run

    fns = {"baseline": baseline, "folds=5": rig("folds=5", folds=5), "folds=0": rig("folds=0", folds=0),
           "times=": rig("times=", folds=5, times=times)}
    for _ in range(warmup):  # the baseline and the cheapest rig run: imports, caches, OpenCV's first calls
        measure(fns["baseline"], repeats=1, warmup=0, number=1)
        measure(fns["folds=0"], repeats=1, warmup=0, number=1)
    for p in parts.values():
        p.runs.clear()
    samples = {r: [] for r in ROWS}
    for _ in range(repeats):  # the rows take turns, run by run
        for r in ROWS:
            samples[r] += measure(fns[r], repeats=1, warmup=0, number=1).samples
    timings = {r: Timing(samples[r], 1) for r in ROWS}
    base = timings["baseline"].median

    # -- table of the rows
    views = len(dets[0])
    seen = [int(sum(d is not None and len(d) > 0 for d in ds)) for ds in dets]
    rows, out_rows = [], {}
    for r in ROWS:
        t = timings[r]
        if r == "baseline":
            rms = "/".join(f"{x.rms_px:.3f}" for x in last[r])
            rounds, folds, note = "-", "-", f"{len(dets)} x calibrate_intrinsics"
            extra = {"rms_px_per_camera": [float(x.rms_px) for x in last[r]],
                     "views_used": [int(x.used.sum()) for x in last[r]]}
        else:
            meta = last[r].rig.meta
            rms = f"{meta['rms_px']:.3f}"
            rounds = statistics.median(run["calls"].get("bundle_adjust", 0) for run in parts[r].runs)
            folds = meta["uncertainty"]["folds"]
            sync = meta["sync"]
            note = (f"sync: {sync['downweighted']} down-weighted, {sync['dropped']} dropped, max offset "
                    f"{1e3 * sync['max_offset_s']:.1f} ms" if sync["times_given"] else
                    (f"held-out RMS {meta['heldout_rms_px']:.3f} px" if meta["heldout_rms_px"] is not None else ""))
            extra = {"rms_px": meta["rms_px"], "heldout_rms_px": meta["heldout_rms_px"], "folds": folds,
                     "refinement_rounds": rounds, "solver_iterations": meta["solver_iterations"],
                     "views_used": meta["views_used"], "observations": meta["observations"],
                     "sync": sync, "std_scale": meta["uncertainty"]["std_scale"]}
        out_rows[r] = dict(t.as_dict(), ratio_to_baseline=t.median / base, **extra)
        rows.append([("baseline: single-camera OpenCV" if r == "baseline" else f"calibrate_rig_detailed {r}"),
                     t.repeats, fmt_time(t.median), fmt_time(t.min), fmt_ratio(t.median / base), rms, rounds, folds,
                     note])
    print()
    print(table(["case", "n", "median", "min", "/ baseline", "RMS px", "refinements", "folds", "note"], rows,
                title=f"{label}: {len(dets)} cameras, {views} instants (views per camera with the target: "
                      f"{', '.join(map(str, seen))})"))

    # -- table of the parts
    part_rows, out_parts = [], {}
    for key, lab in list(PARTS.items()) + [("other", "the rest (checks, coverage, fold checks, results)")]:
        line, d = [lab], {}
        for r in ROWS[1:]:
            runs = parts[r].runs
            vals = [(run["total_s"] - sum(run["parts_s"].values())) if key == "other" else run["parts_s"].get(key, 0.0)
                    for run in runs]
            calls = statistics.median(run["calls"].get(key, 0) for run in runs) if key != "other" else None
            med = statistics.median(vals)
            share = med / statistics.median(run["total_s"] for run in runs)
            d[r] = {"median_s": med, "share": share, "ratio_to_baseline": med / base, "calls": calls,
                    "samples_s": vals}
            line.append(f"{fmt_time(med)} ({100 * share:.0f} %, {fmt_ratio(med / base)})"
                        + (f" x{calls:g}" if calls else ""))
        out_parts[key] = d
        part_rows.append(line)
    print()
    print(table(["part of calibrate_rig_detailed"] + list(ROWS[1:]), part_rows,
                title=f"{label}: parts, each cell: median over the runs (share of the run, / baseline) x outermost "
                      "calls"))
    nested = parts["folds=5"].runs[-1]["nested_calls"].get("bundle_adjust", 0)

    r5, r0, rt = (timings[r].median for r in ROWS[1:])
    ratios = {"rig_over_baseline": r5 / base, "folds5_over_folds0": r5 / r0,
              "kfold_share": out_parts["_kfold"]["folds=5"]["share"], "times_over_folds5": rt / r5,
              "kfold_bundle_adjusts": nested}
    print(f"ratios: rig (folds=5) / single-camera = {r5 / base:.2f}x; folds=5 / folds=0 = {r5 / r0:.2f}x (the k-fold "
          f"check: {100 * ratios['kfold_share']:.0f} % of the folds=5 run, {nested} bundle adjustments); "
          f"times= / folds=5 = {rt / r5:.2f}x")
    return {"cameras": len(dets), "instants": views, "views_with_target": seen, "image_sizes": [list(s) for s in sizes],
            "rows": out_rows, "parts": out_parts, "ratios": ratios}


# -- the section ------------------------------------------------------------------------------------------------------
def bench_calibrate(*, quick: bool = False) -> dict:
    import cv2

    repeats = 1 if quick else 3
    warmup = 0 if quick else 1  # before the first data set only: the second runs the same code, already warm
    load0 = os.getloadavg()
    print(f"load average (1, 5, 15 min) at start: {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f} on {os.cpu_count()} "
          "CPUs (other processes share the cores: read the numbers with that in mind)")
    out = {"repeats": repeats, "warmup": warmup, "opencv_threads": cv2.getNumThreads()}
    with single_threaded_blas():
        print(f"BLAS threads in effect: {blas_threads()} (threadpoolctl.threadpool_limits(1)); OpenCV threads: "
              f"{cv2.getNumThreads()}; runs per row: {repeats} (taking turns), warm-up runs: {warmup} (first data set)")
        out["blas_threads"] = blas_threads()
        dets, spec, sizes, names, times, source = _synthetic()
        print(f"synthetic data: {source}; 0.1 px corner noise; frame times (times= row): instant v at v s "
              "+ U(-3, 3) ms per camera view")
        out["synthetic"] = _bench_set("synthetic (paper rig, 11x8 ChArUco)", dets, spec, sizes, names, times,
                                      repeats=repeats, warmup=warmup) | {"source": source}
        print()
        t0 = time.perf_counter()
        cal = _caliscope()
        if cal is None:
            print(f"caliscope: {CALISCOPE} not found; skipped")
            out["caliscope"] = None
        else:
            dets, spec, sizes, names, times, info = cal
            info["wall_s"] = time.perf_counter() - t0
            print(f"caliscope: {info['frames']} frames of 4 videos {sizes[0][0]}x{sizes[0][1]} "
                  f"(target in {', '.join(map(str, info['frames_with_target']))}), detected once outside the timing "
                  f"in {info['wall_s']:.1f} s: detection {fmt_time(info['detect_per_frame_median_s'])} per frame "
                  f"(median; mean {fmt_time(info['detect_per_frame_mean_s'])}), decoding "
                  f"{fmt_time(info['decode_per_frame_median_s'])} per frame (median), one thread")
            out["caliscope"] = _bench_set("caliscope (4 webcams, inverted 4x5 ChArUco)", dets, spec, sizes, names,
                                          times, repeats=repeats, warmup=0) | {"detection": info}
    load1 = os.getloadavg()
    print(f"load average at end: {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")
    out["load_average_start"], out["load_average_end"] = list(load0), list(load1)
    return out
