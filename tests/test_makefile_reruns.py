"""``make demo`` and ``make demo-invivo`` re-run what a change of recording or setting affects, and nothing else.

The Makefile's recipes run ``$(PY) -m heartcv.cli.main STAGE ...``; here PY is a stub that logs each stage and
writes the files the recipe expects, so the test checks make's decisions in a second, without running heartcv."""

from __future__ import annotations

import os
from pathlib import Path
import shutil
import subprocess
import sys

import pytest

ROOT = Path(__file__).resolve().parents[1]

_STUB = '''#!{python}
import os, sys
args = sys.argv[3:]                                  # after "-m heartcv.cli.main"
with open(os.environ["STUB_LOG"], "a") as log:
    log.write(" ".join(args) + "\\n")
def value(flag):
    return args[args.index(flag) + 1] if flag in args else None
out = value("-o")
if args[0] == "report":
    os.makedirs(out, exist_ok=True)
    for name in ("metrics.json", "summary.md"):
        open(os.path.join(out, name), "w").write("stub\\n")
elif out:
    open(out, "w").write("stub\\n")
overlay = value("--overlay")
if overlay:
    os.makedirs(os.path.join(overlay, "frames"), exist_ok=True)
    for name in ("frames/000000.png", "frames/000001.png", "tracks.png"):
        open(os.path.join(overlay, name), "w").write("stub\\n")
if "--json" in args:
    print("{{}}")
'''

ALL = ["rig", "measure", "fit", "fit", "track", "track", "track", "track", "track", "track", "track", "report"]
AFTER_MEASURE = ALL[2:]


@pytest.fixture
def make_stub(tmp_path):
    if shutil.which("make") is None:
        pytest.fail("GNU make is needed to build and test heartcv (the README's commands)")
    stub = tmp_path / "python"
    stub.write_text(_STUB.format(python=sys.executable))
    stub.chmod(0o755)
    log = tmp_path / "stages.log"
    for name in ("heart_a", "heart_b"):
        (tmp_path / name / "cam0").mkdir(parents=True)

    def run(*settings, goal="demo-invivo"):
        log.write_text("")
        res = subprocess.run(["make", "-C", str(ROOT / "sample_sequences"), goal, f"PY={stub}",
                              f"WORK={tmp_path / 'work'}", *settings],
                             capture_output=True, text=True, env={"STUB_LOG": str(log), "PATH": "/usr/bin:/bin"})
        assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
        return [line.split() for line in log.read_text().splitlines()]

    return run, tmp_path


def _stages(calls):
    return sorted(c[0] for c in calls)


def _arg(calls, stage, flag):
    """The value of ``flag`` in the (first) call of ``stage``."""
    call = next(c for c in calls if c[0] == stage)
    return call[call.index(flag) + 1]


def test_demo_invivo_reruns_what_a_changed_setting_affects(make_stub):
    run, tmp = make_stub
    heart_a, heart_b = str(tmp / "heart_a"), str(tmp / "heart_b")
    calls = run(f"INVIVO={heart_a}")
    assert _stages(calls) == sorted(ALL), calls
    assert next(c for c in calls if c[0] == "measure")[1] == heart_a
    # a recording of the user's: its own frame rate (measure reads it), the first 4 s fitted
    assert "--fps" not in next(c for c in calls if c[0] == "measure")
    assert {_arg([c], "fit", "--duration") for c in calls if c[0] == "fit"} == {"4"}
    assert run(f"INVIVO={heart_a}") == []                           # nothing changed: nothing runs
    # a setting of the fit and the trackers: the measurement is kept
    calls = run(f"INVIVO={heart_a}", "HOLDOUT=0.2")
    assert _stages(calls) == sorted(AFTER_MEASURE), calls
    assert all(c[c.index("--holdout") + 1] == "0.2" for c in calls if c[0] == "track")
    # another recording: everything again, on it (before the stamps, the earlier recording's report was shown)
    calls = run(f"INVIVO={heart_b}", "HOLDOUT=0.2")
    assert _stages(calls) == sorted(ALL), calls
    assert next(c for c in calls if c[0] == "measure")[1] == heart_b
    # its geometry: the views' size read off it, the shared recording's field of view at that size
    assert _arg(calls, "rig", "--size-of") == heart_b and _arg(calls, "rig", "--hfov-deg") == "49.55"
    assert "--image-size" not in next(c for c in calls if c[0] == "rig")
    assert "--focal-px" not in next(c for c in calls if c[0] == "rig")
    # a frame rate given: measure takes it; the fitted window stays 4 s (IV_FIT_S), or is given in frames
    calls = run(f"INVIVO={heart_b}", "HOLDOUT=0.2", "IV_FPS=50")
    assert _stages(calls) == sorted(ALL), calls
    assert _arg(calls, "measure", "--fps") == "50" and _arg(calls, "fit", "--duration") == "4"
    calls = run(f"INVIVO={heart_b}", "HOLDOUT=0.2", "IV_FPS=50", "IV_FIT_S=6")
    assert _stages(calls) == sorted(AFTER_MEASURE) and _arg(calls, "fit", "--duration") == "6"
    calls = run(f"INVIVO={heart_b}", "HOLDOUT=0.2", "IV_FPS=50", "IV_FIT_FRAMES=120")
    assert _arg(calls, "fit", "--frames") == "120" and "--duration" not in next(c for c in calls if c[0] == "fit")
    # extra options of fit (a heart rate known otherwise): both fits take them, the measurement is kept
    calls = run(f"INVIVO={heart_b}", "HOLDOUT=0.2", "IV_FPS=50", "IV_FIT_FRAMES=120", "IV_FIT=--heart-rate-hz 1.2")
    assert _stages(calls) == sorted(AFTER_MEASURE), calls
    assert [_arg([c], "fit", "--heart-rate-hz") for c in calls if c[0] == "fit"] == ["1.2", "1.2"]
    # the rig's geometry: the rig and everything after it
    calls = run(f"INVIVO={heart_b}", "HOLDOUT=0.2", "IV_FOCAL=400")
    assert _stages(calls) == sorted(ALL), calls
    assert _arg(calls, "rig", "--focal-px") == "400" and "--hfov-deg" not in next(c for c in calls if c[0] == "rig")
    assert run(f"INVIVO={heart_b}", "HOLDOUT=0.2", "IV_FOCAL=400") == []
    calls = run(f"INVIVO={heart_b}", "HOLDOUT=0.2", "IV_FOCAL=400", "IV_SIZE=640x480")
    assert _stages(calls) == sorted(ALL), calls
    assert _arg(calls, "rig", "--image-size") == "640x480"
    assert "--size-of" not in next(c for c in calls if c[0] == "rig")
    # the cameras' folder names (a recording in left/ and right/): the rig and everything after it
    assert _arg(calls, "rig", "--names") == "cam0,cam1"
    calls = run(f"INVIVO={heart_b}", "HOLDOUT=0.2", "IV_FOCAL=400", "IV_NAMES=left,right")
    assert _stages(calls) == sorted(ALL), calls
    assert _arg(calls, "rig", "--names") == "left,right"
    # a rig file of the user's (calibrated, imported): no rectified rig; measure reads it, and re-runs when it
    # changes; the user's file is only read
    rig = tmp / "my_rig.yaml"
    rig.write_text("stub rig\n")
    calls = run(f"INVIVO={heart_b}", "HOLDOUT=0.2", f"IV_RIG={rig}")
    assert _stages(calls) == sorted(ALL[1:]), calls
    assert _arg(calls, "measure", "--rig") == str(rig)
    assert run(f"INVIVO={heart_b}", "HOLDOUT=0.2", f"IV_RIG={rig}") == []
    os.utime(rig, (rig.stat().st_atime, rig.stat().st_mtime + 10))
    assert _stages(run(f"INVIVO={heart_b}", "HOLDOUT=0.2", f"IV_RIG={rig}")) == sorted(ALL[1:])
    assert rig.read_text() == "stub rig\n"


def test_demo_invivo_on_the_shared_recording_takes_its_25_fps(make_stub):
    """The shared recording has no timestamps; its README gives 25 fps, which the Makefile passes (dry run)."""
    shared = ROOT.parent / "shared" / "data" / "hamlyn_invivo_heart"
    res = subprocess.run(["make", "-n", "-C", str(ROOT / "sample_sequences"), "demo-invivo", "PY=python",
                          f"WORK={make_stub[1] / 'work'}", f"INVIVO={shared}/"], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]
    assert " --fps 25 " in res.stdout and "--duration 4" in res.stdout, res.stdout[-3000:]
    assert f"--size-of {shared}/ " in res.stdout and "--focal-px 390 " in res.stdout, res.stdout[-3000:]


def test_demo_reruns_what_a_changed_setting_affects(make_stub):
    run, _ = make_stub
    first = run(goal="demo")
    assert _stages(first) == sorted(["target", "render", "render", "calibrate", "measure", "fit", "track", "track",
                                     "report"]), first
    assert run(goal="demo") == []
    calls = run("SEED=2", goal="demo")                               # the fit's seed: the fit and what follows
    assert _stages(calls) == ["fit", "report", "track", "track"], calls
    assert _arg(calls, "fit", "--seed") == "2"
    calls = run("SEED=2", "FRAMES=120", goal="demo")                # the sequence's length: not the calibration
    assert _stages(calls) == ["fit", "measure", "render", "report", "track", "track"], calls
    assert _arg(calls, "render", "--frames") == "120"
    assert run("SEED=2", "FRAMES=120", goal="demo") == []


def test_sample_sequences_makefile_runs_with_the_repositorys_environment(tmp_path):
    """`make -C sample_sequences phantom95` as the README writes it (no PY): the recipes run the repository's
    .venv python when there is one (they ran the system python3, which has no heartcv: exit 2 at the first step);
    a given PY still wins (dry runs)."""
    args = ["make", "-n", "-B", "-C", str(ROOT / "sample_sequences"), "phantom95", f"WORK={tmp_path / 'w'}"]
    res = subprocess.run(args, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]
    venv = ROOT / ".venv" / "bin" / "python"
    want = f"{venv} -m heartcv.cli.main render sequence" if venv.exists() else "python3 -m heartcv.cli.main render"
    assert want in res.stdout, res.stdout[:2000]
    res = subprocess.run(args + ["PY=/opt/other/python"], capture_output=True, text=True)
    assert "/opt/other/python -m heartcv.cli.main render sequence" in res.stdout
