"""Timing, BLAS reporting and table helpers shared by the benchmarks (no heartcv imports here)."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
import gc
import math
import os
import platform
import statistics
import time

__all__ = ["Timing", "measure", "fmt_time", "fmt_ratio", "table", "blas_info", "blas_lines",
           "blas_threads", "single_threaded_blas", "environment"]


@dataclass
class Timing:
    """Per-call times (s) of ``repeats`` samples, each the mean over ``number`` back-to-back calls."""

    samples: list = field(default_factory=list)
    number: int = 1

    # summaries of the samples (s), and their count
    median = property(lambda self: statistics.median(self.samples))
    min = property(lambda self: min(self.samples))
    max = property(lambda self: max(self.samples))
    repeats = property(lambda self: len(self.samples))

    def as_dict(self) -> dict:
        return {"median_s": self.median, "min_s": self.min, "max_s": self.max, "repeats": self.repeats,
                "number": self.number, "samples_s": list(self.samples)}


def _one(fn, number: int) -> float:
    gc.collect()
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        return (time.perf_counter() - t0) / number
    finally:
        if was_enabled:
            gc.enable()


def measure(fn, *, repeats: int = 5, warmup: int = 1, number: int | None = None,
            min_sample_s: float = 0.02) -> Timing:
    """Median-of-repeats timing of ``fn()`` with :func:`time.perf_counter`.

    ``number`` calls make one sample; by default it is chosen so that a sample lasts at least
    ``min_sample_s`` (taken from the warm-up call, or 1 when there is no warm-up). GC is off during a sample.
    """
    first = None
    for _ in range(warmup):
        first = _one(fn, 1)
    if number is None:
        number = 1 if not first else max(1, min(100_000, math.ceil(min_sample_s / max(first, 1e-9))))
    return Timing([_one(fn, number) for _ in range(max(1, repeats))], number)


# -- formatting ---------------------------------------------------------------------------------
def fmt_time(s) -> str:
    if s is None or (isinstance(s, float) and math.isnan(s)):
        return "-"
    if s >= 1.0:
        return f"{s:.3f} s"
    if s >= 1e-3:
        return f"{s * 1e3:.3f} ms"
    return f"{s * 1e6:.1f} us"


def fmt_ratio(r) -> str:
    if r is None or (isinstance(r, float) and math.isnan(r)):
        return "-"
    return f"{r:.2f}x" if r < 100 else f"{r:.0f}x"


def table(headers, rows, *, title: str | None = None) -> str:
    """Plain-text table; the first column is left-aligned, the others right-aligned."""
    cells = [[str(h) for h in headers]] + [[str(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]

    def line(r):
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True)))

    out = []
    if title:
        out.append(title)
    out.append(line(cells[0]))
    out.append("  ".join("-" * w for w in widths))
    out.extend(line(r) for r in cells[1:])
    return "\n".join(out)


# -- BLAS ---------------------------------------------------------------------------------------
def blas_info() -> list[dict]:
    """``threadpoolctl.threadpool_info()`` restricted to JSON-friendly fields."""
    from threadpoolctl import threadpool_info

    keys = ("user_api", "internal_api", "version", "num_threads", "threading_layer", "architecture",
            "prefix", "filepath")
    return [{k: d.get(k) for k in keys} for d in threadpool_info()]


def blas_lines(info=None) -> list[str]:
    info = blas_info() if info is None else info
    if not info:
        return ["  (threadpoolctl found no BLAS/OpenMP library)"]
    return [f"  {d['user_api']}: {d['internal_api']} {d['version']} ({d['prefix']}), arch {d['architecture']}, "
            f"threading {d['threading_layer']}, num_threads {d['num_threads']}" for d in info]


def blas_threads() -> str:
    """Thread counts of the BLAS libraries currently in effect, e.g. ``'1'`` or ``'2/2'``."""
    counts = sorted({str(d["num_threads"]) for d in blas_info() if d["user_api"] == "blas"})
    return "/".join(counts) or "?"


@contextlib.contextmanager
def single_threaded_blas():
    """``threadpoolctl.threadpool_limits(1)`` for the BLAS libraries (numpy's and scipy's OpenBLAS)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


def environment() -> dict:
    import numpy
    import scipy

    env = {"python": platform.python_version(), "numpy": numpy.__version__, "scipy": scipy.__version__,
           "machine": platform.machine(), "platform": platform.platform(), "cpu_count": os.cpu_count(),
           "processor": _cpu_model()}
    try:
        import skfem

        env["scikit-fem"] = skfem.__version__
    except Exception:  # pragma: no cover - skfem is a hard dependency of tracker
        env["scikit-fem"] = None
    try:
        import heartcv.tracker as tracker

        env["heartcv"] = getattr(tracker, "__version__", None)
    except Exception:  # pragma: no cover
        env["heartcv"] = None
    return env


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "?"
