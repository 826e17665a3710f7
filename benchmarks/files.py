"""Section ``files`` of ``python -m benchmarks``: how fast and in how little memory the readers refuse hostile
files (issue acceptance: under 1 s and 100 MB each), against reading valid files of the same kind in the same run.

Hostile files, each a few hundred bytes: a YAML alias bomb (9 levels of 9 aliases: 3.9e8 nodes expanded), a YAML
document nested 100 levels deep, and an ``.npz`` whose ``.npy`` header claims a 1 GiB array. Baselines: the model
file ``sample_sequences/phantom/model.yaml`` and a measurement file of 240 frames x 300 points (the demo's size),
read by the same functions. Peak memory is the tracemalloc peak of one call (Python and numpy allocations).
"""

from __future__ import annotations

import io
from pathlib import Path
import tempfile
import tracemalloc
import zipfile

import numpy as np

from ._harness import fmt_time, measure, table

ROOT = Path(__file__).resolve().parents[1]


def alias_bomb() -> str:
    """A YAML alias bomb of about 500 bytes: 9 levels of 9 aliases (3.9e8 nodes once expanded)."""
    lines = ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, 9):
        prev, cur = chr(96 + i), chr(97 + i)
        lines.append(f"{cur}: &{cur} [" + ",".join([f"*{prev}"] * 9) + "]")
    return "\n".join(lines) + "\n"


def huge_claim_copy(src, dst, member: str = "times", nbytes: int = 1 << 30):
    """Copy the ``.npz`` file ``src`` to ``dst`` with ``member``'s ``.npy`` header claiming an array of ``nbytes``
    (float64) followed by 64 bytes of data: a file of a few kB that a naive reader allocates 1 GiB for."""
    b = io.BytesIO()
    np.lib.format.write_array_header_1_0(b, {"descr": "<f8", "fortran_order": False, "shape": (nbytes // 8,)})
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            zout.writestr(info.filename, b.getvalue() + b"\0" * 64 if info.filename == f"{member}.npy"
                          else zin.read(info))
    return Path(dst)


def _files(folder: Path) -> dict:
    from heartcv.tracker.io import write_measurements
    from heartcv.tracker.measurements import MeasurementSet

    (folder / "bomb.yaml").write_text(alias_bomb())
    (folder / "deep.yaml").write_text("geometry: " + "[" * 100 + "]" * 100 + "\n")
    K, P = 240, 300
    rng = np.random.default_rng(0)
    cov = np.broadcast_to(np.eye(3) * 1e-10, (K, P, 3, 3))
    m = MeasurementSet(np.arange(K) / 60.0, np.arange(P), rng.normal(size=(K, P, 3)) * 1e-3, cov,
                       rng.normal(size=(P, 3)) * 1e-3, np.zeros((K, 1)), ("lv_pressure",), ("Pa",), "patch")
    write_measurements(folder / "meas.npz", m)
    huge_claim_copy(folder / "meas.npz", folder / "big.npz")
    return {k: folder / n for k, n in (("bomb", "bomb.yaml"), ("deep", "deep.yaml"), ("meas", "meas.npz"),
                                       ("big", "big.npz"))}


def _peak(fn) -> int:
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def _refused(fn):
    from heartcv.tracker.files import InputError

    def call():
        try:
            fn()
        except InputError:
            return
        raise AssertionError("not refused")
    return call


def bench_files(quick: bool = False) -> dict:
    from heartcv.tracker.io import read_measurements, read_model

    repeats = 3 if quick else 7
    with tempfile.TemporaryDirectory() as tmp:
        f = _files(Path(tmp))
        cases = {
            "model.yaml (valid, baseline)": lambda: read_model(ROOT / "sample_sequences" / "phantom" / "model.yaml"),
            "alias bomb (refused)": _refused(lambda: read_model(f["bomb"])),
            "100-level nesting (refused)": _refused(lambda: read_model(f["deep"])),
            "measurements 240x300 (valid, baseline)": lambda: read_measurements(f["meas"]),
            "1 GiB .npy claim (refused)": _refused(lambda: read_measurements(f["big"])),
        }
        out, rows = {}, []
        for name, fn in cases.items():
            t = measure(fn, repeats=repeats, warmup=1)
            peak = _peak(fn)
            out[name] = dict(t.as_dict(), peak_bytes=peak)
            rows.append((name, fmt_time(t.median), f"{peak / 2**20:.2f} MiB"))
    base_yaml = out["model.yaml (valid, baseline)"]["median_s"]
    base_npz = out["measurements 240x300 (valid, baseline)"]["median_s"]
    for name in ("alias bomb (refused)", "100-level nesting (refused)"):
        out[name]["ratio_to_baseline"] = out[name]["median_s"] / base_yaml
    out["1 GiB .npy claim (refused)"]["ratio_to_baseline"] = out["1 GiB .npy claim (refused)"]["median_s"] / base_npz
    print(table(("case", "median", "peak memory"), rows))
    print("Ratios to reading the valid file of the same kind: " + ", ".join(
        f"{k.split(' (')[0]} {v['ratio_to_baseline']:.2f}x" for k, v in out.items() if "ratio_to_baseline" in v))
    worst_t = max(v["median_s"] for k, v in out.items() if "refused" in k)
    worst_m = max(v["peak_bytes"] for k, v in out.items() if "refused" in k)
    print(f"Slowest refusal {fmt_time(worst_t)} (limit 1 s), largest peak {worst_m / 2**20:.2f} MiB (limit 100 MB)")
    out["max_refusal_s"], out["max_refusal_peak_bytes"] = worst_t, worst_m
    return out
