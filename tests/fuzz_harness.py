"""Seeded fuzzing of heartcv's file readers through the command line (a library; the tests are in
``tests/test_fuzz_readers.py``, ``make fuzz`` runs the long pass).

For each of the ten readers (``READERS``) a small *valid* seed file is made with the project's own stages and
writers (``Seeds``), and the cheapest CLI command that reads the file completely is known (``Seeds.specs``). The
runner (``run_reader``) mutates the seed ``n`` times, each case with its own generator
``numpy.random.default_rng([seed, reader index, case index])`` (so one case is reproduced from seed and index
alone: ``reproduce``), writes the mutated file into a fresh folder and runs the command there with click's
``CliRunner`` in a **forked child process** (a per-case wall limit, a memory limit (``RLIMIT_AS``), and a crash
or a leaked global state in one case cannot touch the next).

A case is a FAILURE when an exception escapes the command (anything but ``SystemExit``), the output holds
``Traceback`` or ``internal error``, the exit code is not 0, 1 or 2, the command exits 1 or 2 without naming the
mutated file (its file name must appear in the output), the child dies of a signal, or it runs past the
per-case limit (``slow``). Every other case is counted as ``ok_exit0``, ``exit1`` or ``exit2``.

Mutations (``mutate``): byte level (bit flips, truncation, random bytes inserted or overwritten, a chunk
duplicated, an empty file, non-UTF-8 bytes) and structure-aware: YAML (one node of the parsed document changed
or deleted, an unknown key, a duplicated key, an alias bomb, deep nesting, ...), ``.npz`` (one member with a
wrong dtype incl. pickled object arrays, a wrong shape, NaN/inf, empty, removed or extra members, a broken
``meta_json``, a ``.npy`` header that claims a 1 GiB (or far larger) array, a corrupt zip member) and CSV (ragged
rows, non-numeric cells, NaN/inf, times that do not increase, huge values, no header, a BOM, non-UTF-8).

Reproduce one case from a shell (the repository root)::

    .venv/bin/python -m tests.fuzz_harness model --seed 7 --index 12 --keep /tmp/case
    .venv/bin/python -m tests.fuzz_harness rig -n 200 --seed 7          # a pass over one reader
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
import io
import json
import os
from pathlib import Path
import pickle
import re
import select
import shutil
import signal
import sys
import tempfile
import time
import traceback
import warnings
import zipfile

import numpy as np
import yaml

from heartcv.calibration import opencv_threads

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_sequences"

READERS = ("model", "measurements", "estimates", "truth", "parameters", "rig", "target", "scene", "inputs.csv",
           "timestamps.csv")
CASE_LIMIT_S = 10.0                 # a case running longer is a failure ('slow')
# a valid scene renders at its default size (1920x1080, 30 s a frame on 2 loaded cores) when a mutation deletes
# rig.image_size: not a hang, so scenes get a longer limit
READER_LIMIT_S = {"scene": 90.0}
MEMORY_HEADROOM = 4 << 30           # address space a case may add to the (forked) parent's, bytes
OUTPUT_TAIL = 2000                  # characters kept of the start and of the end of a case's output


class HarnessError(RuntimeError):
    """The harness itself cannot run (a seed that does not build or does not pass): not a product failure."""


# =====================================================================================================================
# Running one CLI command in a forked child
# =====================================================================================================================
@dataclass
class Outcome:
    """What one CLI run did. ``exception``: 'Type: message' of an escaping exception (None for SystemExit)."""

    exit_code: int | None = None
    output_tail: str = ""
    output_len: int = 0
    named: bool = False
    traceback_in_output: bool = False
    internal_error: bool = False
    exception: str | None = None
    exception_type: str | None = None
    where: str | None = None            # innermost frame of the escaping exception: 'file:line in func'
    tb_tail: str = ""
    escaped: bool = False               # the exception escaped the CLI (else: reported as an internal error)
    timed_out: bool = False
    signal: int | None = None
    harness_error: str | None = None
    wall_s: float = 0.0


def _plain_python_warnings():
    """The warning filters of a plain ``python`` process (pytest's own filters, e.g. RuntimeWarning -> error in
    heartcv.tracker, must not turn a CLI warning into an exception here)."""
    warnings.resetwarnings()
    warnings.filterwarnings("default", category=DeprecationWarning, module="__main__")
    for cat in (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning):
        warnings.filterwarnings("ignore", category=cat)


def _vm_size() -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def _exc_details(exc, tb):
    """'Type: message', the innermost heartcv frame ('file:line in func', plus where it was raised) and the
    formatted traceback's tail."""
    msg = str(exc)
    d = {"exception_type": type(exc).__name__,
         "exception": f"{type(exc).__name__}: {msg[:400]}{' ...' if len(msg) > 400 else ''}",
         "tb_tail": "".join(traceback.format_exception(type(exc), exc, tb))[-3000:]}
    frames = traceback.extract_tb(tb) if tb is not None else []
    if frames:
        mine = [f for f in frames if any(m in f.filename for m in ("/heartcv/", "/tracker/", "/cli/"))
                and "/tests/" not in f.filename and "click/" not in f.filename] or frames
        f = mine[-1]
        d["where"] = f"{_short(f.filename)}:{f.lineno} in {f.name}"
        inner = frames[-1]
        if inner is not f:
            d["where"] += f" (raised in {_short(inner.filename)}:{inner.lineno} in {inner.name})"
    return d


def _invoke(argv, name):
    """Run ``heartcv ARGV`` with CliRunner in this process; the Outcome fields the child reports. The exception
    behind an 'internal error' message of the CLI (``heartcv.cli.main.InternalError``) is captured too, for its
    place in the code."""
    from click.testing import CliRunner

    import heartcv.cli.main as cli_main

    caught = []
    internal = getattr(cli_main, "InternalError", None)
    if isinstance(internal, type):
        orig = internal.__init__

        def init(self, exc=None, *a, **k):
            if isinstance(exc, BaseException):
                caught.append(exc)
            orig(self, exc, *a, **k)

        internal.__init__ = init
    t0 = time.perf_counter()
    res = CliRunner().invoke(cli_main.main, [str(a) for a in argv], catch_exceptions=True)
    out = res.output or ""      # stdout and stderr: click >= 8.2 always, older click with its default mix_stderr
    tail = out if len(out) <= 2 * OUTPUT_TAIL else f"{out[:OUTPUT_TAIL]}\n[... {len(out) - 2 * OUTPUT_TAIL} " \
        f"characters left out ...]\n{out[-OUTPUT_TAIL:]}"
    d = {"exit_code": res.exit_code, "output_tail": tail, "output_len": len(out),
         "named": bool(name) and name in out, "traceback_in_output": "Traceback" in out,
         "internal_error": "internal error" in out.lower(), "wall_s": time.perf_counter() - t0}
    exc = res.exception
    if exc is not None and not isinstance(exc, SystemExit):
        d["escaped"] = True
        d.update(_exc_details(exc, res.exc_info[2] if res.exc_info else None))
    elif caught:
        d.update(_exc_details(caught[0], caught[0].__traceback__))
    return d


def _short(filename: str) -> str:
    for marker in ("/site-packages/", str(ROOT) + "/"):
        if marker in filename:
            return filename.split(marker, 1)[1]
    return filename


class _Child:
    """One forked CLI run: started at once; ``read`` what it sends until EOF, then ``finish`` (or ``finish(killed=
    True)`` past its deadline)."""

    def __init__(self, argv, cwd, name, limit_s, headroom):
        self.limit_s = limit_s
        self.start = time.perf_counter()
        self.buf = bytearray()
        # where a case that runs past its limit is stuck: faulthandler writes the stacks here shortly before
        self.stack_file = Path(cwd) / ".fuzz_stacks.txt" if cwd is not None else None
        r, w = os.pipe()
        sys.stdout.flush()
        sys.stderr.flush()
        # OpenCV's thread pool does not survive fork: a child forked after an earlier test ran a parallel OpenCV call
        # hangs in its first cv2.getNumThreads (tests/heartcv/test_calibration.py before the fuzz tests: the valid
        # target seed's calibrate ran into its 60 s limit). Fork with one thread, so that no pool thread runs; parent
        # and child each restore the count after it and start a pool of their own (as heartcv.render.parallel).
        with opencv_threads(1):
            pid = os.fork()
        if pid == 0:                                  # the child: never returns
            code = 0
            try:
                os.close(r)
                os.setpgid(0, 0)                      # its own process group: a kill takes any helpers along
                signal.signal(signal.SIGINT, signal.SIG_DFL)
                if self.stack_file is not None and limit_s > 1:
                    import faulthandler

                    self._stacks = open(self.stack_file, "w")   # noqa: SIM115 - lives as long as the child
                    faulthandler.dump_traceback_later(max(0.5, limit_s - 0.5), file=self._stacks)
                _plain_python_warnings()
                vm = _vm_size()
                if headroom and vm:
                    import resource

                    lim = vm + headroom
                    resource.setrlimit(resource.RLIMIT_AS, (lim, lim))
                if cwd is not None:
                    os.chdir(cwd)
                try:
                    payload = _invoke(argv, name)
                except BaseException as exc:          # noqa: BLE001 - anything here is the harness's problem
                    payload = {"harness_error": f"{type(exc).__name__}: {exc}",
                               "tb_tail": traceback.format_exc()[-3000:]}
                data = pickle.dumps(payload)
                view = memoryview(data)
                while view:
                    n = os.write(w, view)
                    view = view[n:]
            except BaseException:                     # noqa: BLE001
                code = 3
            finally:
                os._exit(code)
        os.close(w)
        self.pid, self.fd = pid, r
        self.outcome: Outcome | None = None

    @property
    def deadline(self):
        return self.start + self.limit_s

    def _stuck_at(self) -> dict:
        """The main thread's stack that faulthandler wrote before the limit: 'where' and 'tb_tail'."""
        try:
            text = self.stack_file.read_text(errors="replace") if self.stack_file else ""
        except OSError:
            text = ""
        blocks = [b for b in text.split("\n\n") if b.strip()]
        main = next((b for b in blocks if "most recent call first" in b and "Current thread" in b),
                    blocks[0] if blocks else "")
        frames = re.findall(r'File "([^"]+)", line (\d+) in (\S+)', main)    # innermost first
        mine = [f for f in frames if any(m in f[0] for m in ("/heartcv/", "/tracker/", "/cli/"))
                and "/tests/" not in f[0]]
        where = None
        if mine or frames:
            f = (mine or frames)[0]
            where = f"{_short(f[0])}:{f[1]} in {f[2]}"
            if frames and frames[0] is not f:
                where += f" (running {_short(frames[0][0])}:{frames[0][1]} in {frames[0][2]})"
        return {"where": where, "tb_tail": main[-3000:]}

    def read(self):
        """Read what the child wrote; True at EOF."""
        try:
            chunk = os.read(self.fd, 1 << 16)
        except OSError:
            chunk = b""
        if chunk:
            self.buf += chunk
            return False
        return True

    def finish(self, killed=False):
        if killed:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.pid, signal.SIGKILL)   # the child's own group (setpgid in the child)
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGKILL)
        _, status = os.waitpid(self.pid, 0)
        os.close(self.fd)
        wall = time.perf_counter() - self.start
        if killed:
            self.outcome = Outcome(timed_out=True, wall_s=wall, **self._stuck_at())
        elif os.WIFSIGNALED(status):
            self.outcome = Outcome(signal=os.WTERMSIG(status), wall_s=wall)
        else:
            try:
                d = pickle.loads(bytes(self.buf))
            except Exception as exc:                  # noqa: BLE001
                d = {"harness_error": f"no result from the child (exit status {status}): {exc}"}
            self.outcome = Outcome(**d)
            self.outcome.wall_s = wall
        return self.outcome


def run_cli(argv, cwd=None, name=None, limit_s=CASE_LIMIT_S, headroom=MEMORY_HEADROOM) -> Outcome:
    """Run ``heartcv ARGV`` in a forked child with a wall limit and a memory limit; ``name``: the file name
    whose presence in the output is reported as ``Outcome.named``."""
    child = _Child(argv, cwd, name, limit_s, headroom)
    while True:
        left = child.deadline - time.perf_counter()
        if left <= 0:
            return child.finish(killed=True)
        ready, _, _ = select.select([child.fd], [], [], left)
        if ready and child.read():
            return child.finish()


def _run_many(jobs, limit_s, headroom, cases, budget_s=None):
    """Run ``cases`` (an iterator of (key, argv, cwd, name)) with up to ``jobs`` children at a time; yields
    (key, Outcome) as they finish. No new case starts once ``budget_s`` has passed."""
    t0 = time.perf_counter()
    running: dict[int, tuple] = {}
    cases = iter(cases)
    exhausted = False
    while True:
        while not exhausted and len(running) < jobs and (budget_s is None or time.perf_counter() - t0 < budget_s):
            try:
                key, argv, cwd, name = next(cases)
            except StopIteration:
                exhausted = True
                break
            child = _Child(argv, cwd, name, limit_s, headroom)
            running[child.fd] = (key, child)
        if not running:
            return
        timeout = max(0.0, min(c.deadline for _, c in running.values()) - time.perf_counter())
        ready, _, _ = select.select(list(running), [], [], timeout)
        for fd in ready:
            key, child = running[fd]
            if child.read():
                del running[fd]
                yield key, child.finish()
        now = time.perf_counter()
        for fd in [fd for fd, (_, c) in running.items() if c.deadline <= now]:
            key, child = running.pop(fd)
            yield key, child.finish(killed=True)
        if exhausted is False and budget_s is not None and time.perf_counter() - t0 >= budget_s:
            exhausted = True


# =====================================================================================================================
# Seed files and the command that reads each
# =====================================================================================================================
@dataclass
class Spec:
    """A reader's valid seed file and its command. ``command(case_dir, path)`` -> argv reading ``path``;
    ``prepare(case_dir)`` -> the path the mutated file is written to (default: case_dir / file_name)."""

    reader: str
    kind: str                           # 'yaml', 'npz' or 'csv'
    seed_file: Path
    file_name: str
    command: object
    prepare: object = None
    label: str = ""

    def case_path(self, case_dir: Path) -> Path:
        return Path(self.prepare(case_dir)) if self.prepare else case_dir / self.file_name


def _cli_ok(argv, what):
    out = run_cli(argv, limit_s=300, headroom=None)
    if out.exit_code != 0 or out.exception or out.harness_error:
        raise HarnessError(f"building the fuzz seeds: {what} failed (exit {out.exit_code}): "
                           f"{out.exception or out.harness_error or ''}\n{out.output_tail[-2000:]}\n{out.tb_tail}")
    return out


MEASURE_OPTS = ("--points", "20", "--min-distance", "5", "--corner-block", "3", "--workers", "1")


class Seeds:
    """The valid seed files, built on first use under ``root`` (a few seconds in all; each part only when a
    reader needs it)."""

    def __init__(self, root):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self._built: set = set()
        self._specs: dict = {}
        self.checked: set = set()

    # -- parts ------------------------------------------------------------------------------------------------------
    def _base(self):
        """model.yaml (paper patch), meas.npz (4 frames, 14 points, some missing), truth.npz, est.npz (GE),
        params.yaml (fit)."""
        d = self.root / "base"
        if "base" in self._built:
            return d
        d.mkdir(exist_ok=True)
        model = d / "model.yaml"
        shutil.copy(SAMPLES / "paper_patch.yaml", model)
        _cli_ok(["-q", "model", "simulate", model, "--duration", "0.1", "--seed", "1", "--missing", "0.1",
                 "-o", d / "meas.npz", "--truth", d / "truth.npz"], "model simulate")
        _cli_ok(["-q", "track", d / "meas.npz", "--model", model, "--estimator", "ge", "-o", d / "est.npz"],
                "track --estimator ge")
        _cli_ok(["-q", "fit", d / "meas.npz", "--model", model, "-o", d / "params.yaml", "--starts", "1"], "fit")
        self._built.add("base")
        return d

    def _sequence(self):
        """A rendered 3-frame sequence, 2 cameras at 480x270 (cam0, cam1, inputs.csv, timestamps.csv, truth.npz,
        rig_truth.yaml) that ``heartcv measure`` tracks in a quarter of a second."""
        d = self.root / "render_seq"
        if "seq" in self._built:
            return d / "seq"
        from tests.heartcv.render_scenes import scene_dict, write_truth_model

        d.mkdir(exist_ok=True)
        model = write_truth_model(d / "model.yaml", grid=(7, 5, 2))
        sc = scene_dict(model, scale=4, motion={"duration_s": 0.1, "substeps": 1},
                        phantom={"mesh_edge_m": 0.003, "texture": {"texel_m": 2e-4}})
        sc["rig"]["cameras"] = 2
        (d / "scene.yaml").write_text(yaml.safe_dump(sc))
        _cli_ok(["-q", "render", "sequence", d / "scene.yaml", "-o", d / "seq", "--frames", "3", "--workers", "1"],
                "render sequence")
        self._built.add("seq")
        return d / "seq"

    def _calibration(self):
        """target.yaml (the default ChArUco board, 11x8 squares of 12 mm, written with heartcv.io.write_target) and
        a rendered calibration set of 4 views x 2 cameras at 480x270 that ``heartcv calibrate`` solves in half a
        second."""
        d = self.root / "render_cal"
        if "cal" in self._built:
            return d
        from heartcv.io import write_target
        from heartcv.targets import TargetSpec
        from tests.heartcv.render_scenes import scene_dict, write_truth_model

        d.mkdir(exist_ok=True)
        write_target(d / "target.yaml", TargetSpec("charuco", (11, 8), 0.012, 0.009, "DICT_5X5_250", name="default"))
        model = write_truth_model(d / "model.yaml", grid=(5, 4, 2))
        sc = scene_dict(model, scale=4, calibration={"target": str(d / "target.yaml"), "views": 4,
                                                     "supersampling": 1, "max_tilt_deg": 30,
                                                     "partial_fraction": 0.0})
        sc["rig"]["cameras"] = 2
        (d / "scene.yaml").write_text(yaml.safe_dump(sc))
        _cli_ok(["-q", "render", "calibration", d / "scene.yaml", "-o", d / "cal", "--workers", "1"],
                "render calibration")
        self._built.add("cal")
        return d

    def _scene(self):
        """The smallest scene that renders: 2 cameras at 120x67, a 5x4x2 model, coarse mesh and texture."""
        d = self.root / "scene"
        if "scene" in self._built:
            return d
        from tests.heartcv.render_scenes import scene_dict, write_truth_model

        d.mkdir(exist_ok=True)
        model = write_truth_model(d / "model.yaml", grid=(5, 4, 2))
        sc = scene_dict(model, scale=16, motion={"duration_s": 0.04, "substeps": 1},
                        phantom={"mesh_edge_m": 0.005, "texture": {"texel_m": 5e-4}})
        sc["rig"]["cameras"] = 2
        (d / "scene.yaml").write_text(yaml.safe_dump(sc, sort_keys=False))
        self._built.add("scene")
        return d

    # -- the specs ----------------------------------------------------------------------------------------------------
    def specs(self, reader) -> list[Spec]:
        """The seed(s) of ``reader``: one Spec, or two for 'truth' (the simulation truth read by ``report``, the
        render truth read by ``measure --truth``); case i uses spec i % len."""
        if reader in self._specs:
            return self._specs[reader]
        if reader not in READERS:
            raise KeyError(f"unknown reader {reader!r}; known: {READERS}")
        specs = getattr(self, "_spec_" + reader.replace(".", "_"))()
        self._specs[reader] = specs
        return specs

    def _spec_model(self):
        return [Spec("model", "yaml", SAMPLES / "paper_patch.yaml", "fuzz_model.yaml",
                     lambda c, p: ["model", "info", p], label="model info")]

    def _spec_measurements(self):
        b = self._base()
        return [Spec("measurements", "npz", b / "meas.npz", "fuzz_meas.npz",
                     lambda c, p: ["track", p, "--model", b / "model.yaml", "-o", c / "est.npz"], label="track (kf)")]

    def _spec_estimates(self):
        b = self._base()
        return [Spec("estimates", "npz", b / "est.npz", "fuzz_est.npz",
                     lambda c, p: ["report", p, "-o", c / "report", "--dpi", "72"], label="report")]

    def _spec_truth(self):
        b, seq = self._base(), self._sequence()
        return [Spec("truth", "npz", b / "truth.npz", "fuzz_truth.npz",
                     lambda c, p: ["report", b / "est.npz", "--truth", p, "-o", c / "report", "--dpi", "72"],
                     label="report --truth (heartcv.truth)"),
                Spec("truth", "npz", seq / "truth.npz", "fuzz_render_truth.npz",
                     lambda c, p: ["measure", seq, "--rig", seq / "rig_truth.yaml", "-o", c / "meas.npz",
                                   "--truth", p, *MEASURE_OPTS],
                     label="measure --truth (heartcv.render_truth)")]

    def _spec_parameters(self):
        b = self._base()
        return [Spec("parameters", "yaml", b / "params.yaml", "fuzz_params.yaml",
                     lambda c, p: ["track", b / "meas.npz", "--model", b / "model.yaml", "--estimator", "ge",
                                   "--params", p, "-o", c / "est.npz"], label="track --params (ge)")]

    def _spec_rig(self):
        seq = self._sequence()
        return [Spec("rig", "yaml", seq / "rig_truth.yaml", "fuzz_rig.yaml",
                     lambda c, p: ["measure", seq, "--rig", p, "-o", c / "meas.npz", *MEASURE_OPTS],
                     label="measure --rig")]

    def _spec_target(self):
        cal = self._calibration()
        return [Spec("target", "yaml", cal / "target.yaml", "fuzz_target.yaml",
                     lambda c, p: ["calibrate", cal / "cal", "--target", p, "-o", c / "rig.yaml", "--min-views", "3",
                                   "--dist", "4", "--jobs", "1"], label="calibrate --target")]

    def _spec_scene(self):
        d = self._scene()
        return [Spec("scene", "yaml", d / "scene.yaml", "fuzz_scene.yaml",
                     lambda c, p: ["render", "sequence", p, "-o", c / "render", "--frames", "1", "--workers", "1"],
                     label="render sequence --frames 1")]

    def _seq_case(self, keep):
        """A per-case sequence folder: the camera folders linked, ``keep`` copied, the mutated file beside them."""
        seq = self._sequence()

        def prepare(case_dir, name):
            s = case_dir / "seq"
            s.mkdir(exist_ok=True)
            for cam in ("cam0", "cam1"):
                if not (s / cam).exists():
                    (s / cam).symlink_to(seq / cam, target_is_directory=True)
            shutil.copy(seq / keep, s / keep)
            return s / name

        return seq, prepare

    def _spec_inputs_csv(self):
        seq, prep = self._seq_case("timestamps.csv")
        return [Spec("inputs.csv", "csv", seq / "inputs.csv", "inputs.csv",
                     lambda c, p: ["measure", c / "seq", "--rig", seq / "rig_truth.yaml", "-o", c / "meas.npz",
                                   *MEASURE_OPTS],
                     prepare=lambda c: prep(c, "inputs.csv"), label="measure (SEQ/inputs.csv)")]

    def _spec_timestamps_csv(self):
        seq, prep = self._seq_case("inputs.csv")
        return [Spec("timestamps.csv", "csv", seq / "timestamps.csv", "timestamps.csv",
                     lambda c, p: ["measure", c / "seq", "--rig", seq / "rig_truth.yaml", "-o", c / "meas.npz",
                                   *MEASURE_OPTS],
                     prepare=lambda c: prep(c, "timestamps.csv"), label="measure (SEQ/timestamps.csv)")]


def warm_imports():
    """Import what the commands use in this (parent) process, so that each forked case starts warm."""
    import importlib

    for mod in ("heartcv.cli.main", "heartcv.cli.model", "heartcv.cli.track", "heartcv.cli.report",
                "heartcv.cli.fit", "heartcv.cli.measure", "heartcv.cli.calibrate", "heartcv.cli.render",
                "heartcv.cli.report_plots", "heartcv.cli.report_doc", "heartcv.tracker.model",
                "heartcv.tracker.joint", "heartcv.tracker.fit", "heartcv.tracker.metrics",
                "heartcv.tracker.registration", "heartcv.measure", "heartcv.calibration", "heartcv.calibration_rig",
                "heartcv.calibration_ba", "heartcv.detect", "heartcv.evaluate", "heartcv.render.sequence",
                "heartcv.render.board", "heartcv.render.raycast", "matplotlib.pyplot", "scipy.optimize",
                "scipy.stats", "skfem", "cv2", "trimesh"):
        with contextlib.suppress(Exception):
            importlib.import_module(mod)
    with contextlib.suppress(Exception):     # threadpoolctl's scan of the loaded libraries: 0.2 s in every case
        import threadpoolctl

        threadpoolctl.threadpool_info()


# =====================================================================================================================
# Mutators
# =====================================================================================================================
def _pick(rng, seq):
    return seq[int(rng.integers(len(seq)))]


# -- byte level -------------------------------------------------------------------------------------------------------
_NON_UTF8 = (b"\xff", b"\xfe\xff", b"\xc3\x28", b"\xa0\xa1", b"\xed\xa0\x80", b"\xf8\x88\x80\x80\x80", b"\x80",
             b"\xe9t\xe9")


def mutate_bytes(data: bytes, rng) -> tuple[bytes, str]:
    n = len(data)
    op = _pick(rng, ("bitflip", "bitflip", "truncate", "truncate", "insert", "overwrite", "duplicate", "empty",
                     "non_utf8", "zeros", "repeat"))
    if op == "empty" or n == 0:
        return b"", "bytes: empty file"
    if op == "bitflip":
        b = bytearray(data)
        k = int(rng.integers(1, 9))
        pos = rng.integers(0, n, k)
        for p in pos:
            b[p] ^= 1 << int(rng.integers(8))
        return bytes(b), f"bytes: {k} bit flip(s) at {sorted(int(p) for p in pos)[:8]}"
    if op == "truncate":
        at = int(rng.integers(0, n))
        return data[:at], f"bytes: truncated at {at} of {n}"
    if op == "insert":
        at, k = int(rng.integers(0, n + 1)), int(rng.integers(1, 65))
        return data[:at] + rng.bytes(k) + data[at:], f"bytes: {k} random bytes inserted at {at}"
    if op == "overwrite":
        at, k = int(rng.integers(0, n)), int(rng.integers(1, 65))
        return data[:at] + rng.bytes(k) + data[at + k:], f"bytes: {k} bytes overwritten at {at}"
    if op == "duplicate":
        a = int(rng.integers(0, n))
        b = min(n, a + int(rng.integers(1, max(2, min(4096, n // 2 + 2)))))
        at = int(rng.integers(0, n + 1))
        return data[:at] + data[a:b] + data[at:], f"bytes: chunk [{a}:{b}] duplicated at {at}"
    if op == "non_utf8":
        at, junk = int(rng.integers(0, n + 1)), _pick(rng, _NON_UTF8)
        return data[:at] + junk + data[at:], f"bytes: non-UTF-8 {junk!r} inserted at {at}"
    if op == "zeros":
        at, k = int(rng.integers(0, n)), int(rng.integers(1, 257))
        return data[:at] + b"\0" * k + data[at + k:], f"bytes: {k} NUL bytes written at {at}"
    return data + data, "bytes: the whole file twice"


# -- YAML -----------------------------------------------------------------------------------------------------------
_PLACEHOLDER = "__FUZZ_PLACEHOLDER__"
_YAML_VALUES = [
    ("NaN", float("nan")), (".inf", float("inf")), ("-.inf", float("-inf")), ("-1", -1), ("0", 0), ("1", 1),
    ("1e308", 1e308), ("-1e308", -1e308), ("huge int 10**30", 10 ** 30), ("-2**63", -2 ** 63), ("2**64", 2 ** 64),
    ("1e-320", 1e-320), ("0.5", 0.5), ("string 'fuzz'", "fuzz"), ("empty string", ""), ("string '1.5'", "1.5"),
    ("string 'nan'", "nan"), ("null", None), ("true", True), ("false", False), ("list [1, 2, 3]", [1, 2, 3]),
    ("empty list", []), ("ragged list", [[1, 2], [3]]), ("list of strings", ["a", "b"]),
    ("nested mapping", {"fuzz": {"nested": [1, {"deeper": None}]}}), ("empty mapping", {}),
    ("long string", "x" * 100_000), ("non-ASCII string", "\u00e9\u4e2d\U0001f600"), ("path '.'", "."),
    ("path '/nonexistent.yaml'", "/nonexistent/fuzz.yaml"), ("path '/dev/null'", "/dev/null"),
    ("list of 10^5 zeros", [0] * 100_000),
]


def _yaml_paths(doc, limit=20_000):
    """Every node below the root as a path of keys / indices (ValueError past ``limit`` nodes: an alias bomb of
    an earlier step)."""
    out, stack = [], [((), doc)]
    while stack:
        path, node = stack.pop()
        items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
        for k, v in items:
            out.append(path + (k,))
            if len(out) > limit:
                raise ValueError("too many YAML nodes")
            stack.append((path + (k,), v))
    return sorted(out, key=lambda p: [str(x) for x in p])


def _path_str(path):
    s = ""
    for p in path:
        s += f"[{p}]" if isinstance(p, int) else (f".{p}" if s else str(p))
    return s or "<root>"


def _get(doc, path):
    for p in path:
        doc = doc[p]
    return doc


def _numeric_variant(v, rng):
    f = _pick(rng, (-1.0, 0.0, 1e-9, 1e-3, 0.5, 2.0, 1e3, 1e9, 1e200))
    if isinstance(v, bool):
        return (not v), f"{v!r} -> {not v!r}"
    nv = v * f
    if isinstance(v, int) and abs(nv) < 2 ** 63:
        nv = int(nv)                                 # an int stays an int where it can
    return nv, f"{v!r} * {f:g}"


class _Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):    # libyaml when there is one: only speed differs
    """Safe YAML that reads ``1e-3`` and ``1.0e8`` as floats, as heartcv's readers do (YAML 1.1 reads them as
    strings: a mutation of a document holding one would otherwise also turn that number into a string)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?|[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)"
               r"|\.[0-9_]+(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"),
    list("-+0123456789."))
_DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


def _yaml_dump(doc) -> str:
    return yaml.dump(doc, Dumper=_DUMPER, sort_keys=False, allow_unicode=True, default_flow_style=None, width=120)


def _alias_bomb(rng):
    levels, width = int(rng.integers(6, 10)), 9
    parts = ["&a0 [" + ", ".join(["lol"] * width) + "]"]
    for i in range(1, levels):
        parts.append(f"&a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]")
    return "[" + ", ".join(parts) + "]", f"alias bomb ({width}^{levels} leaves)"


def _deep_nesting(rng):
    depth = int(_pick(rng, (100, 500, 2000, 20000)))
    if rng.random() < 0.5:
        return "[" * depth + "1" + "]" * depth, f"nested flow lists, depth {depth}"
    return "{a: " * depth + "1" + "}" * depth, f"nested flow mappings, depth {depth}"


def mutate_yaml(data: bytes, rng) -> tuple[bytes, str]:
    text = data.decode("utf-8")
    doc = yaml.load(text, Loader=_Loader)
    r = rng.random()
    if r < 0.12:                                     # text level
        return _mutate_yaml_text(text, doc, rng)
    paths = list(_yaml_paths(doc))
    if not paths or r < 0.15:                        # the root
        label, val = _pick(rng, _YAML_VALUES[:26])
        return _yaml_dump(val).encode(), f"yaml: whole document replaced by {label}"
    depths = sorted({len(p) for p in paths})         # a depth first, then a node there: the top-level keys
    depth = depths[int(rng.integers(len(depths)))]   # are chosen as often as the numbers deep inside matrices
    at_depth = [p for p in paths if len(p) == depth]
    path = at_depth[int(rng.integers(len(at_depth)))]
    parent, key = _get(doc, path[:-1]), path[-1]
    old = parent[key]
    where = _path_str(path)
    op = rng.random()
    if op < 0.12:                                    # delete
        del parent[key]
        desc = f"yaml: {where} deleted"
    elif op < 0.2 and isinstance(parent, dict):      # unknown key beside it, or renamed
        if rng.random() < 0.5:
            parent["fuzz_unknown_key"] = 1
            desc = f"yaml: unknown key 'fuzz_unknown_key' added beside {where}"
        else:
            parent[f"{key}x"] = parent.pop(key)
            desc = f"yaml: key {where} renamed to '{key}x'"
    elif op < 0.28 and isinstance(old, (int, float)) and not isinstance(old, bool):
        parent[key], how = _numeric_variant(old, rng)
        desc = f"yaml: {where} = {how}"
    elif op < 0.36 and isinstance(old, list) and old:
        how = _pick(rng, ("drop last", "duplicate first", "append 0", "scalar"))
        if how == "drop last":
            old.pop()
        elif how == "duplicate first":
            old.insert(0, old[0])
        elif how == "append 0":
            old.append(0)
        else:
            parent[key] = old[0]
        desc = f"yaml: list {where}: {how}"
    elif op < 0.42:                                  # placeholder-based: alias bomb, deep nesting, python tag
        parent[key] = _PLACEHOLDER
        kind = _pick(rng, ("bomb", "deep", "tag"))
        if kind == "bomb":
            repl, what = _alias_bomb(rng)
        elif kind == "deep":
            repl, what = _deep_nesting(rng)
        else:
            repl, what = "!!python/object/apply:os.getcwd []", "a !!python/object tag"
        out = _yaml_dump(doc).replace(_PLACEHOLDER, repl, 1)
        return out.encode(), f"yaml: {where} = {what}"
    else:
        label, val = _pick(rng, _YAML_VALUES)
        parent[key] = val
        desc = f"yaml: {where} = {label} (was {type(old).__name__})"
    return _yaml_dump(doc).encode(), desc


_KEY_LINE = re.compile(r"^(\s*)([A-Za-z_][\w\-]*):(.*)$")


def _mutate_yaml_text(text, doc, rng):
    lines = text.splitlines()
    op = _pick(rng, ("dupkey", "dupkey", "tab", "quote", "multidoc", "bom", "crlf", "utf16", "nul", "indent"))
    keyed = [i for i, ln in enumerate(lines) if _KEY_LINE.match(ln)]
    if op == "dupkey" and keyed:
        i = keyed[int(rng.integers(len(keyed)))]
        ind, key, rest = _KEY_LINE.match(lines[i]).groups()
        val = _pick(rng, ("12345", "-1", ".nan", "fuzz", "null", "[1, 2]", "{a: 1}"))
        dup = f"{ind}{key}: {val}"
        if rest.strip() and not rest.strip().startswith("#"):
            lines.insert(i + 1, dup)                 # the duplicate wins
            how = "after (it wins)"
        else:
            lines.insert(i, dup)                     # before a block: the original wins
            how = "before"
        return ("\n".join(lines) + "\n").encode(), f"yaml text: duplicated key '{key}' = {val} {how} line {i + 1}"
    if op == "tab":
        ind = [i for i, ln in enumerate(lines) if ln.startswith(" ")]
        if ind:
            i = ind[int(rng.integers(len(ind)))]
            lines[i] = "\t" + lines[i].lstrip(" ")
            return ("\n".join(lines) + "\n").encode(), f"yaml text: tab indentation on line {i + 1}"
    if op == "quote" and lines:
        i = int(rng.integers(len(lines)))
        lines[i] += ' "unterminated'
        return ("\n".join(lines) + "\n").encode(), f"yaml text: unterminated quote on line {i + 1}"
    if op == "multidoc":
        return (text + "\n---\nfuzz: 1\n").encode(), "yaml text: a second document"
    if op == "bom":
        return b"\xef\xbb\xbf" + text.encode(), "yaml text: UTF-8 BOM"
    if op == "crlf":
        return text.replace("\n", "\r\n").encode(), "yaml text: CRLF line ends"
    if op == "utf16":
        return text.encode("utf-16"), "yaml text: encoded as UTF-16"
    if op == "nul" and lines:
        i = int(rng.integers(len(lines)))
        lines[i] += "\0"
        return ("\n".join(lines) + "\n").encode(), f"yaml text: NUL character on line {i + 1}"
    if lines:                                        # indent: one line shifted by one space
        i = int(rng.integers(len(lines)))
        lines[i] = " " + lines[i]
        return ("\n".join(lines) + "\n").encode(), f"yaml text: line {i + 1} indented by one space"
    return b"", "yaml text: empty"


# -- npz ------------------------------------------------------------------------------------------------------------
_KNOWN_META = ("format", "format_version", "frame", "input_names", "input_units", "estimator", "completed_steps",
               "estimated", "dropped_points", "partial", "dt", "theta0", "prior_std_phi", "options", "kind",
               "camera_names", "file_names", "image_width", "image_height", "world_frame", "reference_uv",
               "reference_frame_index", "registration", "measurement_noise_m", "inputs_hash", "seed",
               "stiffness_cycle", "frame_rate_hz", "model")
_JSON_VALUES = [
    ("null", "null"), ("true", "true"), ("false", "false"), ("0", "0"), ("-1", "-1"), ("1", "1"), ("2", "2"),
    ("1.5", "1.5"), ("1e308", "1e308"), ("-1e308", "-1e308"), ("1e999 (inf)", "1e999"), ("NaN", "NaN"),
    ("Infinity", "Infinity"), ("10**400", "1" + "0" * 400), ("string ''", '""'), ("string 'fuzz'", '"fuzz"'),
    ("string '1'", '"1"'), ("empty list", "[]"), ("list [1, 'a', null]", '[1, "a", null]'),
    ("empty object", "{}"), ("object", '{"a": {"b": [1]}}'),
    ("list of 10^5 ints", "[" + ",".join(["7"] * 100_000) + "]"),
    ("string of 10^5 chars", '"' + "x" * 100_000 + '"'),
]


def _npz_read(data: bytes):
    """[(arcname, raw member bytes)] of a zip archive."""
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        return [(i.filename, z.read(i.filename)) for i in z.infolist()]


def _npy_bytes(arr) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.asanyarray(arr), allow_pickle=True)
    return buf.getvalue()


def _npy_array(raw: bytes):
    return np.lib.format.read_array(io.BytesIO(raw), allow_pickle=False)


def _npz_write(members, compress=True) -> bytes:
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")              # duplicate names are one of the mutations
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED) as z:
            for name, raw in members:
                z.writestr(name, raw)
    return buf.getvalue()


def _huge_header(shape, descr="<f8") -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": tuple(shape)})
    return buf.getvalue() + b"\0" * 64


def _array_variant(arr: np.ndarray, rng):
    """(new array, description) for one change of one array."""
    op = _pick(rng, ("dtype", "dtype", "shape", "shape", "value", "value", "value", "fill", "empty", "ragged",
                     "scale"))
    if op == "dtype":
        dt = _pick(rng, ("object", "complex128", "<U8", "bool", "int8", "float16", "uint64", ">f8", "V8",
                         "datetime64[s]", "struct", "float32", "int64", "float64"))
        try:
            if dt == "struct":
                new = np.zeros(arr.shape, dtype=[("a", "<f8"), ("b", "<i4")])
            elif dt == "V8":
                new = np.zeros(arr.shape, dtype="V8")
            elif dt == "datetime64[s]":
                new = np.zeros(arr.shape, dtype="datetime64[s]")
            else:
                with np.errstate(all="ignore"), warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    new = arr.astype(dt)
        except (TypeError, ValueError, OverflowError):
            new = arr.astype(object)
            dt = "object"
        return new, f"dtype {arr.dtype} -> {dt}" + (" (pickled)" if dt == "object" else "")
    if op == "shape":
        how = _pick(rng, ("transpose", "ravel", "leading axis", "drop last", "extra row", "0-d", "trailing axis"))
        if how == "transpose" and arr.ndim >= 2:
            new = arr.T.copy()
        elif how == "ravel":
            new = arr.ravel()
        elif how == "leading axis":
            new = arr[None]
        elif how == "trailing axis":
            new = arr[..., None]
        elif how == "drop last" and arr.ndim and arr.shape[-1]:
            ax = int(rng.integers(arr.ndim))
            new = np.delete(arr, arr.shape[ax] - 1, axis=ax) if arr.shape[ax] else arr
        elif how == "extra row" and arr.ndim and arr.size:
            ax = int(rng.integers(arr.ndim))
            new = np.concatenate([arr, np.take(arr, [0], axis=ax)], axis=ax)
        else:
            new = np.asarray(arr.flat[0] if arr.size else 0)
            how = "0-d"
        return new, f"shape {arr.shape} -> {new.shape} ({how})"
    if op == "value" and arr.size:
        new = arr.copy()
        idx = tuple(int(rng.integers(s)) for s in arr.shape)
        if new.dtype.kind == "f":
            v = _pick(rng, (np.nan, np.inf, -np.inf, 1e308, -1e308, 0.0, -1.0, 1e-320, 1e30))
        elif new.dtype.kind in "iu":
            info = np.iinfo(new.dtype)
            v = _pick(rng, (-1, 0, info.max, info.min, 10 ** 9, 2 ** 31))
            v = min(max(v, info.min), info.max)
        elif new.dtype.kind == "b":
            v = not bool(new[idx])
        else:
            return arr.astype(object), f"dtype {arr.dtype} -> object (pickled)"
        new[idx] = v
        return new, f"element {list(idx)} = {v!r}"
    if op == "fill" and arr.size:
        new = arr.copy()
        v = _pick(rng, (np.nan, np.inf, 0, -1)) if new.dtype.kind == "f" else _pick(rng, (0, -1, 1))
        with np.errstate(all="ignore"):
            new[...] = v
        return new, f"every element = {v!r}"
    if op == "scale" and arr.size and arr.dtype.kind == "f":
        f = _pick(rng, (-1.0, 1e3, 1e-3, 1e6, 1e300))
        with np.errstate(all="ignore"):
            return arr * f, f"scaled by {f:g}"
    if op == "ragged":
        n = max(2, arr.shape[0] if arr.ndim else 2)
        new = np.empty(n, dtype=object)
        for i in range(n):
            new[i] = list(range(i % 3 + 1))
        return new, f"ragged object array of {n} lists (pickled)"
    shape = (0,) + arr.shape[1:] if arr.ndim else (0,)
    return np.zeros(shape, dtype=arr.dtype if arr.dtype != object else float), f"empty, shape {shape}"


def _meta_variant(raw_meta: bytes, rng):
    """(new meta_json member bytes (npy), description)."""
    try:
        meta = json.loads(bytes(_npy_array(raw_meta)).decode())
    except Exception:                                # noqa: BLE001
        meta = {}
    op = _pick(rng, ("nondict", "field", "field", "field", "field", "missing", "missing", "utf8", "badjson",
                     "dtype", "empty", "deep", "dupkey"))
    text = None
    if op == "nondict":
        text = _pick(rng, ("[]", "1", '"heartcv"', "null", "true", "1.5", '[{"format": "x"}]'))
        desc = f"meta_json = {text}"
    elif op == "field" and isinstance(meta, dict):
        keys = sorted(set(meta) | set(_KNOWN_META))
        key = _pick(rng, keys)
        label, val = _pick(rng, _JSON_VALUES)
        body = json.dumps({k: v for k, v in meta.items() if k != key}, sort_keys=True)
        text = body[:-1] + (", " if len(body) > 2 else "") + json.dumps(key) + ": " + val + "}"
        desc = f"meta_json.{key} = {label}"
    elif op == "missing" and isinstance(meta, dict) and meta:
        key = _pick(rng, sorted(meta))
        text = json.dumps({k: v for k, v in meta.items() if k != key}, sort_keys=True)
        desc = f"meta_json: key {key!r} removed"
    elif op == "utf8":
        b = json.dumps(meta, sort_keys=True).encode()
        at = int(rng.integers(0, len(b) + 1))
        junk = _pick(rng, _NON_UTF8)
        return _npy_bytes(np.frombuffer(b[:at] + junk + b[at:], np.uint8)), f"meta_json: invalid UTF-8 {junk!r} at {at}"
    elif op == "badjson":
        b = json.dumps(meta, sort_keys=True)
        at = int(rng.integers(0, max(1, len(b))))
        text = b[:at]
        desc = f"meta_json: JSON cut at {at} of {len(b)}"
    elif op == "dtype":
        b = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), np.uint8)
        how = _pick(rng, ("float64", "2-D", "int32", "str", "object"))
        new = {"float64": lambda: b.astype(np.float64), "2-D": lambda: b[None, :],
               "int32": lambda: b.astype(np.int32), "str": lambda: np.array(json.dumps(meta)),
               "object": lambda: np.array([json.dumps(meta)], dtype=object)}[how]()
        return _npy_bytes(new), f"meta_json stored as {how} array"
    elif op == "empty":
        text = ""
        desc = "meta_json empty"
    elif op == "deep":
        depth = int(_pick(rng, (1000, 100_000)))
        text = json.dumps(meta)[:-1] + (", " if meta else "") + '"fuzz": ' + "[" * depth + "]" * depth + "}"
        desc = f"meta_json with a list nested {depth} deep"
    else:
        body = json.dumps(meta, sort_keys=True)
        key = _pick(rng, sorted(meta)) if isinstance(meta, dict) and meta else "format"
        text = body[:-1] + (", " if len(body) > 2 else "") + f'"{key}": 12345}}'
        desc = f"meta_json: key {key!r} duplicated (12345 wins)"
    return _npy_bytes(np.frombuffer(text.encode(), np.uint8)), desc


def mutate_npz(data: bytes, rng) -> tuple[bytes, str]:
    members = _npz_read(data)
    names = [n for n, _ in members]
    arrays = [i for i, n in enumerate(names) if n != "meta_json.npy"]
    meta_i = names.index("meta_json.npy") if "meta_json.npy" in names else None
    op = _pick(rng, ("array", "array", "array", "array", "meta", "meta", "meta", "remove", "extra", "huge",
                     "corrupt", "garbage", "duplicate", "truncated_member", "stored"))
    if op == "array" and arrays:
        i = arrays[int(rng.integers(len(arrays)))]
        arr = _npy_array(members[i][1])
        new, how = _array_variant(arr, rng)
        members[i] = (members[i][0], _npy_bytes(new))
        return _npz_write(members), f"npz: {members[i][0][:-4]}: {how}"
    if op == "meta" and meta_i is not None:
        raw, how = _meta_variant(members[meta_i][1], rng)
        members[meta_i] = ("meta_json.npy", raw)
        return _npz_write(members), f"npz: {how}"
    if op == "remove" and members:
        i = int(rng.integers(len(members)))
        name = members.pop(i)[0]
        return _npz_write(members), f"npz: member {name} removed"
    if op == "extra":
        how = _pick(rng, ("fuzz_extra.npy", "times", "dir/x.npy", "meta_json", "big"))
        if how == "big":
            members.append(("fuzz_big.npy", _npy_bytes(np.zeros((2000, 2000)))))
            return _npz_write(members), "npz: extra member of 32 MB (zeros)"
        members.append((how, _npy_bytes(rng.standard_normal(5))))
        return _npz_write(members), f"npz: extra member {how!r}"
    if op == "huge" and members:
        i = int(rng.integers(len(members)))
        shape = _pick(rng, ((1 << 27,), (1 << 27,), (1 << 14, 1 << 13, 1), (1 << 40,), (1 << 31, 1 << 31)))
        members[i] = (members[i][0], _huge_header(shape))
        gib = int(np.prod(shape, dtype=object)) * 8 / 2 ** 30
        return _npz_write(members), f"npz: {members[i][0]} header claims shape {shape} ({gib:g} GiB), no data"
    if op == "corrupt" and members:
        i = int(rng.integers(len(members)))
        z = bytearray(_npz_write(members))
        with zipfile.ZipFile(io.BytesIO(bytes(z))) as zf:
            info = zf.infolist()[i]
        start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
        k = int(rng.integers(1, 5))
        for _ in range(k):
            p = start + int(rng.integers(0, max(1, info.compress_size)))
            z[p] ^= 0xFF
        return bytes(z), f"npz: {k} byte(s) of member {info.filename}'s compressed data flipped"
    if op == "garbage" and members:
        i = int(rng.integers(len(members)))
        members[i] = (members[i][0], rng.bytes(int(rng.integers(0, 200))))
        return _npz_write(members), f"npz: member {members[i][0]} replaced by random bytes"
    if op == "duplicate" and members:
        i = int(rng.integers(len(members)))
        name = members[i][0]
        other = arrays[int(rng.integers(len(arrays)))] if arrays else i
        members.append((name, members[other][1]))
        return _npz_write(members), f"npz: a second member named {name} (holding {members[other][0]})"
    if op == "truncated_member" and members:
        i = int(rng.integers(len(members)))
        raw = members[i][1]
        at = int(rng.integers(0, max(1, len(raw))))
        members[i] = (members[i][0], raw[:at])
        return _npz_write(members), f"npz: member {members[i][0]} cut at {at} of {len(raw)} bytes"
    if op == "stored":
        return _npz_write(members, compress=False), "npz: uncompressed (ZIP_STORED) archive (valid)"
    return mutate_bytes(data, rng)


# -- CSV ------------------------------------------------------------------------------------------------------------
_CELLS = ("abc", "", " ", "1.0.0", "0x10", "1e", "--1", "true", "'1'", '"1"', "\u221e", "nan", "inf", "-inf",
          "1e308", "-1e308", "1e400", "-0", "1e-400", "9" * 400, "NaN", "+inf", "1_000")


def mutate_csv(data: bytes, rng) -> tuple[bytes, str]:
    text = data.decode("utf-8")
    lines = text.splitlines()
    comments = [i for i, ln in enumerate(lines) if ln.startswith("#")]
    body = [i for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")]
    if not body:
        return mutate_bytes(data, rng)
    h, rows = body[0], body[1:]
    header = lines[h].split(",")

    def done(desc, ls=None):
        return ("\n".join(lines if ls is None else ls) + "\n").encode(), f"csv: {desc}"

    op = _pick(rng, ("ragged", "cell", "cell", "cell", "order", "order", "huge", "noheader", "header", "header",
                     "bom", "latin1", "onlyheader", "droprows", "duprow", "manyrows", "column", "delimiter", "crlf",
                     "blank", "comment", "framecol", "trailing"))
    if op == "ragged" and rows:
        i = _pick(rng, rows)
        if rng.random() < 0.5 and "," in lines[i]:
            lines[i] = lines[i].rsplit(",", 1)[0]
            return done(f"row {i + 1}: last cell dropped")
        lines[i] += ",1.0"
        return done(f"row {i + 1}: an extra cell")
    if op == "cell" and rows:
        i, j = _pick(rng, rows), int(rng.integers(len(header)))
        cells = lines[i].split(",")
        if j < len(cells):
            v = _pick(rng, _CELLS)
            cells[j] = v
            lines[i] = ",".join(cells)
            return done(f"row {i + 1}, column {header[j]!r} = {v[:20]!r}")
    if op == "order" and len(rows) >= 2:
        how = _pick(rng, ("swap", "repeat", "reverse", "negate"))
        t = [ln.split(",") for ln in (lines[i] for i in rows)]
        col = header.index("time_s") if "time_s" in header else 0
        if how == "swap":
            a, b = sorted(rng.choice(len(t), 2, replace=False))
            t[a][col], t[b][col] = t[b][col], t[a][col]
        elif how == "repeat":
            a = int(rng.integers(1, len(t)))
            t[a][col] = t[a - 1][col]
        elif how == "reverse":
            vals = [r[col] for r in t][::-1]
            for r, v in zip(t, vals):
                r[col] = v
        else:
            for r in t:
                with contextlib.suppress(ValueError):
                    r[col] = repr(-float(r[col]))
        for i, r in zip(rows, t):
            lines[i] = ",".join(r)
        return done(f"times: {how}")
    if op == "huge" and rows:
        i = _pick(rng, rows)
        cells = lines[i].split(",")
        j = int(rng.integers(len(cells)))
        with contextlib.suppress(ValueError):
            cells[j] = repr(float(cells[j]) * _pick(rng, (1e300, -1e300, 1e15)) or 1e300)
        lines[i] = ",".join(cells)
        return done(f"row {i + 1}, column {j}: huge value {cells[j]}")
    if op == "noheader":
        del lines[h]
        return done("header row removed")
    if op == "header":
        how = _pick(rng, ("rename time_s", "case", "duplicate", "unit", "empty", "spaces", "quoted"))
        cols = list(header)
        j = int(rng.integers(len(cols)))
        if how == "rename time_s":
            cols = ["time" if c == "time_s" else c for c in cols]
        elif how == "case":
            cols[j] = cols[j].upper()
        elif how == "duplicate":
            cols[j] = cols[(j + 1) % len(cols)] if len(cols) > 1 else cols[j]
            if len(cols) == 1:
                cols.append(cols[0])
                for i in rows:
                    lines[i] += "," + lines[i].split(",")[0]
        elif how == "unit":
            cols[j] = re.sub(r"_[a-z]+$", "_psi", cols[j]) if "_" in cols[j] else cols[j] + "_psi"
        elif how == "empty":
            cols[j] = ""
        elif how == "spaces":
            cols[j] = f"  {cols[j]}  "
        else:
            cols[j] = f'"{cols[j]}"'
        lines[h] = ",".join(cols)
        return done(f"header: {how} ({lines[h][:60]!r})")
    if op == "bom":
        return ("\ufeff" + text).encode(), "csv: UTF-8 BOM"
    if op == "latin1":
        lines[h] = lines[h] + "\u00e9"
        return ("\n".join(lines) + "\n").encode("latin-1", errors="replace"), "csv: non-UTF-8 (latin-1 \\xe9) in header"
    if op == "onlyheader":
        return done("header only, no rows", [ln for i, ln in enumerate(lines) if i not in rows])
    if op == "droprows" and rows:
        k = int(rng.integers(1, len(rows) + 1))
        drop = set(int(x) for x in rng.choice(rows, k, replace=False))
        return done(f"{k} row(s) removed", [ln for i, ln in enumerate(lines) if i not in drop])
    if op == "duprow" and rows:
        i = _pick(rng, rows)
        lines.insert(i + 1, lines[i])
        return done(f"row {i + 1} duplicated")
    if op == "manyrows" and len(rows) >= 2:
        last = [float(c) if re.fullmatch(r"[-+0-9.eE]+", c) else 0.0 for c in lines[rows[-1]].split(",")]
        n = int(_pick(rng, (100, 10_000, 200_000)))
        extra = [",".join(repr(v + k * 0.001) for v in last) for k in range(1, n + 1)]
        return done(f"{n} rows appended", lines + extra)
    if op == "column":
        if rng.random() < 0.5 and len(header) > 1:
            j = int(rng.integers(len(header)))
            for i in [h] + rows:
                cells = lines[i].split(",")
                if j < len(cells):
                    del cells[j]
                lines[i] = ",".join(cells)
            return done(f"column {header[j]!r} removed")
        lines[h] += ",fuzz_mmhg"
        for i in rows:
            lines[i] += ",1.0"
        return done("extra column 'fuzz_mmhg'")
    if op == "delimiter":
        d = _pick(rng, (";", "\t", " "))
        return done(f"delimiter {d!r}", [ln.replace(",", d) for ln in lines])
    if op == "crlf":
        return text.replace("\n", "\r\n").encode(), "csv: CRLF line ends"
    if op == "blank" and rows:
        lines.insert(_pick(rng, rows), "   ")
        return done("a blank line among the rows")
    if op == "comment" and rows:
        i = _pick(rng, rows)
        lines[i] = lines[i] + " # trailing comment"
        return done(f"trailing comment on row {i + 1}")
    if op == "framecol":
        how = _pick(rng, ("right", "wrong", "numbers"))
        lines[h] += ",frame"
        for k, i in enumerate(rows):
            lines[i] += "," + {"right": f"{k:06d}", "wrong": f"{k + 7:06d}", "numbers": str(k)}[how]
        return done(f"'frame' column ({how} stems)")
    if op == "trailing":
        return done("trailing comma on every line", [ln + "," if not ln.startswith("#") else ln for ln in lines])
    if comments:
        return done("comment lines removed", [ln for i, ln in enumerate(lines) if i not in comments])
    return mutate_bytes(data, rng)


_STRUCTURED = {"yaml": mutate_yaml, "npz": mutate_npz, "csv": mutate_csv}


def mutate(kind: str, data: bytes, rng) -> tuple[bytes, str]:
    """One mutated version of ``data`` (a file of ``kind`` 'yaml', 'npz' or 'csv') and what was done. About a
    quarter byte level, the rest structure-aware; one case in eight stacks two or three mutations."""
    steps = 1 if rng.random() < 0.875 else int(rng.integers(2, 4))
    descs = []
    for _ in range(steps):
        try:
            if rng.random() < 0.25:
                data, d = mutate_bytes(data, rng)
            else:
                data, d = _STRUCTURED[kind](data, rng)
        except Exception as exc:                      # a previous step left no structure to work on
            data, d = mutate_bytes(data, rng)
            d += f" (structure-aware step impossible: {type(exc).__name__})"
        descs.append(d)
    return data, " + ".join(descs)


# =====================================================================================================================
# The runner
# =====================================================================================================================
@dataclass
class Failure:
    reader: str
    seed: int
    index: int
    kind: str
    mutation: str
    command: str
    exit_code: int | None
    exception: str | None
    where: str | None
    output_tail: str
    tb_tail: str = ""
    kept: str | None = None

    def signature(self) -> str:
        """What groups failures of one cause: the kind and the exception type and place, or the first error line
        with numbers and paths blanked."""
        if self.exception or (self.kind == "slow" and self.where):
            return f"{self.kind} at {self.where}"
        if self.kind.startswith("exit"):
            line = next((ln for ln in self.output_tail.splitlines() if ln.startswith("Error")), "")
            line = re.sub(r"/[^\s:'\"]+", "PATH", line)
            line = re.sub(r"[-+]?\d[\d.eE+-]*", "N", line)
            return f"{self.kind}: {line[:140]}"
        return self.kind

    def describe(self, lines=4) -> str:
        out = self.output_tail.strip().splitlines()
        errors = [ln for ln in out if ln.startswith("Error")][-2:]
        tail = "\n      ".join([ln[:400] for ln in errors] + [ln[:400] for ln in out[-lines:] if ln not in errors])
        s = (f"[{self.reader} seed={self.seed} index={self.index}] {self.kind} (exit {self.exit_code})\n"
             f"    mutation: {self.mutation}\n    command: heartcv {self.command}\n")
        if self.exception:
            s += f"    exception: {self.exception}\n    at: {self.where}\n"
        if tail:
            s += f"    output: {tail}\n"
        if self.kept:
            s += f"    mutated file kept: {self.kept}\n"
        return s


@dataclass
class FuzzResult:
    reader: str
    seed: int
    requested: int
    run: int = 0
    ok_exit0: int = 0
    exit1: int = 0
    exit2: int = 0
    failures: list = field(default_factory=list)
    wall_s: float = 0.0
    budget_hit: bool = False

    def counts(self) -> dict:
        return {"cases": self.run, "ok_exit0": self.ok_exit0, "exit1": self.exit1, "exit2": self.exit2,
                "failures": len(self.failures)}

    def groups(self) -> list[tuple[str, int, Failure]]:
        """(signature, count, first example), most frequent first."""
        by: dict[str, list] = {}
        for f in self.failures:
            by.setdefault(f.signature(), []).append(f)
        return sorted(((s, len(fs), fs[0]) for s, fs in by.items()), key=lambda t: -t[1])

    def as_dict(self) -> dict:
        return {**self.counts(), "seed": self.seed, "requested": self.requested, "wall_s": round(self.wall_s, 2),
                "budget_hit": self.budget_hit,
                "failure_kinds": [{"signature": s, "count": n, "example": {
                    "index": f.index, "mutation": f.mutation, "exit_code": f.exit_code, "exception": f.exception,
                    "where": f.where, "output_tail": f.output_tail[-600:]}} for s, n, f in self.groups()]}

    def report(self, max_groups=25) -> str:
        c = self.counts()
        s = (f"fuzz {self.reader} (seed {self.seed}): {c['cases']} cases in {self.wall_s:.1f} s: exit 0 "
             f"{c['ok_exit0']}, exit 1 {c['exit1']}, exit 2 {c['exit2']}, FAILURES {c['failures']}\n")
        for sig, n, f in self.groups()[:max_groups]:
            s += f"--- {n} x {sig}\n{f.describe()}"
        return s


def _classify(o: Outcome) -> str | None:
    """The failure kind of an outcome, or None when it is a clean exit 0, 1 or 2."""
    if o.timed_out:
        return "slow"
    if o.signal is not None:
        return f"crash (signal {o.signal})"
    if o.harness_error:
        return "harness error"
    if o.escaped:
        return f"exception {o.exception_type}"
    if o.traceback_in_output:
        return "Traceback in output"
    if o.internal_error:
        return f"internal error ({o.exception_type})" if o.exception_type else "'internal error' in output"
    if o.exit_code not in (0, 1, 2):
        return f"exit code {o.exit_code}"
    if o.exit_code in (1, 2) and not o.named:
        return f"exit {o.exit_code} without the file name"
    return None


def make_case(reader, seed, index, case_dir, seeds: Seeds):
    """Write case ``index`` of ``reader`` into ``case_dir``: (argv, mutated path, description, spec)."""
    specs = seeds.specs(reader)
    spec = specs[index % len(specs)]
    rng = np.random.default_rng([seed, READERS.index(reader), index])
    data, desc = mutate(spec.kind, spec.seed_file.read_bytes(), rng)
    case_dir.mkdir(parents=True, exist_ok=True)
    path = spec.case_path(case_dir)
    path.write_bytes(data)
    if len(specs) > 1:
        desc = f"[{spec.label}] {desc}"
    return [str(a) for a in spec.command(case_dir, path)], path, desc, spec


def check_seeds(reader, seeds: Seeds, workdir):
    """Run every valid seed of ``reader`` through its command (once per Seeds); HarnessError unless each exits 0
    cleanly."""
    if reader in seeds.checked:
        return
    for k, spec in enumerate(seeds.specs(reader)):
        case = Path(workdir) / f"seed-{k}"
        case.mkdir(parents=True, exist_ok=True)
        path = spec.case_path(case)
        shutil.copy(spec.seed_file, path)
        argv = spec.command(case, path)
        o = run_cli(argv, cwd=case, name=spec.file_name, limit_s=60)
        if o.exit_code != 0 or _classify(o):
            raise HarnessError(f"the valid {reader} seed ({spec.label}) does not pass: exit {o.exit_code} "
                               f"{o.exception or o.harness_error or ''}\n{o.output_tail[-2000:]}")
        shutil.rmtree(case, ignore_errors=True)
    seeds.checked.add(reader)


def run_reader(reader, n, seed=0, *, seeds: Seeds, workdir, budget_s=None, jobs=None, limit_s=CASE_LIMIT_S,
               headroom=MEMORY_HEADROOM, keep_failures=20, start=0, progress=None) -> FuzzResult:
    """Run cases ``start`` … ``start + n - 1`` of ``reader`` (fewer when ``budget_s`` seconds pass first) and count
    them. Every case gets a fresh folder under ``workdir`` (removed afterwards); the mutated files of the first
    ``keep_failures`` failures are kept in ``workdir/failures``."""
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    if limit_s == CASE_LIMIT_S:
        limit_s = READER_LIMIT_S.get(reader, limit_s)
    jobs = jobs or max(1, min(2, os.cpu_count() or 1))
    warm_imports()
    check_seeds(reader, seeds, workdir / "seeds")
    res = FuzzResult(reader, seed, n)
    t0 = time.perf_counter()
    cases: dict[int, tuple] = {}

    def gen():
        for i in range(start, start + n):
            case_dir = Path(tempfile.mkdtemp(prefix=f"{reader.replace('.', '_')}-{i}-", dir=workdir))
            argv, path, desc, spec = make_case(reader, seed, i, case_dir, seeds)
            cases[i] = (case_dir, argv, path, desc, spec)
            yield i, argv, case_dir, spec.file_name

    for i, o in _run_many(jobs, limit_s, headroom, gen(), budget_s):
        case_dir, argv, path, desc, spec = cases.pop(i)
        res.run += 1
        kind = _classify(o)
        if kind is None:
            if o.exit_code == 0:
                res.ok_exit0 += 1
            elif o.exit_code == 1:
                res.exit1 += 1
            else:
                res.exit2 += 1
        else:
            kept = None
            if len(res.failures) < keep_failures:
                (workdir / "failures").mkdir(exist_ok=True)
                dest = workdir / "failures" / f"{reader}-{seed}-{i}-{spec.file_name}"
                with contextlib.suppress(OSError):
                    shutil.copy(path, dest)
                    kept = str(dest)
            cmd = " ".join(a.replace(str(case_dir), "CASE") for a in argv)
            res.failures.append(Failure(reader, seed, i, kind, desc, cmd, o.exit_code, o.exception, o.where,
                                        o.output_tail, o.tb_tail, kept))
        shutil.rmtree(case_dir, ignore_errors=True)
        if progress:
            progress(res)
    res.failures.sort(key=lambda f: f.index)
    res.wall_s = time.perf_counter() - t0
    res.budget_hit = res.run < n
    return res


def reproduce(reader, seed, index, folder, seeds: Seeds | None = None, limit_s=CASE_LIMIT_S):
    """Write case (seed, index) of ``reader`` into ``folder`` and run it: (Outcome, kind or None, argv,
    description). The folder is kept."""
    folder = Path(folder)
    seeds = seeds or Seeds(folder / "seeds")
    argv, path, desc, spec = make_case(reader, seed, index, folder / "case", seeds)
    warm_imports()
    o = run_cli(argv, cwd=folder / "case", name=spec.file_name, limit_s=limit_s)
    return o, _classify(o), argv, desc


def _main(argv=None):
    import argparse

    ap = argparse.ArgumentParser(prog="python -m tests.fuzz_harness", description=__doc__.split("\n\n")[0])
    ap.add_argument("reader", choices=READERS + ("all",))
    ap.add_argument("-n", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--index", type=int, default=None, help="reproduce this one case (kept under --keep)")
    ap.add_argument("--keep", default=None, help="folder for the seeds and cases (default: a temporary one)")
    ap.add_argument("--budget", type=float, default=None)
    ap.add_argument("--jobs", type=int, default=None)
    ap.add_argument("--json", default=None, help="write the counts and failure kinds here")
    a = ap.parse_args(argv)
    root = Path(a.keep or tempfile.mkdtemp(prefix="heartcv-fuzz-"))
    seeds = Seeds(root / "seeds")
    if a.index is not None:
        o, kind, cmd, desc = reproduce(a.reader, a.seed, a.index, root, seeds)
        print(f"mutation: {desc}\ncommand: heartcv {' '.join(cmd)}\nexit {o.exit_code}: {kind or 'ok'}\n"
              f"{o.output_tail}\n{o.tb_tail}")
        return 0 if kind is None else 1
    readers = READERS if a.reader == "all" else (a.reader,)
    out, bad = {}, 0
    for r in readers:
        res = run_reader(r, a.n, a.seed, seeds=seeds, workdir=root / "work", budget_s=a.budget, jobs=a.jobs)
        print(res.report(), flush=True)
        out[r] = res.as_dict()
        bad += len(res.failures)
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=2))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(_main())
