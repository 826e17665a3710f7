"""``python -m benchmarks {model,discretise,kf,estimators,fit,render,measure,files,calibrate,all} [--json PATH]
[--quick]``."""

from __future__ import annotations

import argparse
import datetime as _dt
import json
from pathlib import Path
import sys
import time

from ._harness import environment
from .calibrate import bench_calibrate
from .estimators import bench_estimators
from .files import bench_files
from .fit import bench_fit
from .measure import bench_measure
from .model import SECTIONS as _MODEL_SECTIONS
from .model import blas_report
from .render import bench_render

SECTIONS = {**_MODEL_SECTIONS, "estimators": bench_estimators, "fit": bench_fit, "render": bench_render,
            "measure": bench_measure, "files": bench_files, "calibrate": bench_calibrate}
ORDER = ("model", "discretise", "kf", "estimators", "fit", "render", "measure", "files", "calibrate")


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (tuple, set)):
        return list(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m benchmarks",
        description="heartcv speed benchmarks: medians of repeated time.perf_counter runs, with ratios to a "
                    "baseline measured in the same run (see benchmarks/README.md).",
    )
    ap.add_argument("which", nargs="?", default="all", choices=ORDER + ("all",),
                    help="section to run (default: all)")
    ap.add_argument("--json", metavar="PATH", help="also write the numbers to this JSON file")
    ap.add_argument("--quick", action="store_true",
                    help="fewer repeats, frames and no fine mesh (a smoke run, not for reporting)")
    args = ap.parse_args(argv)

    sections = ORDER if args.which == "all" else (args.which,)
    env = environment()
    info, lines = blas_report()
    started = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    print(f"heartcv benchmarks ({', '.join(sections)}){' [quick]' if args.quick else ''} -- {started}")
    print(f"python {env['python']}, numpy {env['numpy']}, scipy {env['scipy']}, scikit-fem {env['scikit-fem']}, "
          f"heartcv {env['heartcv']}; {env['processor']}, {env['cpu_count']} CPUs")
    print("BLAS (threadpoolctl.threadpool_info(), library defaults):")
    print("\n".join(lines))
    print("Small-matrix sections (discretise, kf, estimators, fit) and measure run under "
          "threadpoolctl.threadpool_limits(1): one BLAS thread.")
    print("Times: median of repeats (time.perf_counter, GC off during a sample); n = repeats.")

    results = {"started": started, "environment": env, "blas": info, "quick": args.quick, "sections": {}}
    t_all = time.perf_counter()
    for name in sections:
        print()
        print(f"=== {name} " + "=" * (70 - len(name)))
        t0 = time.perf_counter()
        results["sections"][name] = SECTIONS[name](quick=args.quick)
        results["sections"][name]["section_wall_s"] = time.perf_counter() - t0
        print(f"({name}: {time.perf_counter() - t0:.1f} s)")
    results["total_wall_s"] = time.perf_counter() - t_all
    print()
    print(f"total: {results['total_wall_s']:.1f} s")
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(results, indent=2, default=_json_default) + "\n", encoding="utf-8")
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
