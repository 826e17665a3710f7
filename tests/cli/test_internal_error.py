"""A bug inside a computation is reported as a bug (exit 1, "internal error"), never as bad input (exit 2) that
blames the user's file; nothing is written; -v shows the traceback."""

import errno
import os

from click.testing import CliRunner
import pytest

from heartcv.cli.main import main
from tests.conftest import SAMPLES

PAPER = str(SAMPLES / "paper_patch.yaml")
SHAPE_ERROR = "operands could not be broadcast together with shapes (168,) (167,)"


@pytest.fixture(scope="module")
def meas_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("bug")
    path = d / "m.npz"
    res = CliRunner().invoke(main, ["model", "simulate", PAPER, "--duration", "1", "--seed", "2", "-o", str(path)])
    assert res.exit_code == 0, res.output
    return path


@pytest.fixture
def shape_bug(monkeypatch):
    """An injected bug in the GE's step: the conditional split raises numpy's shape-mismatch ValueError."""
    from heartcv.tracker import joint

    def broken(*args, **kwargs):
        raise ValueError(SHAPE_ERROR)

    monkeypatch.setattr(joint, "conditional_split", broken)


@pytest.mark.parametrize("verbose", [False, True])
def test_a_shape_error_inside_the_ge_is_an_internal_error(tmp_path, meas_file, shape_bug, verbose):
    out = tmp_path / "ge.npz"
    before = meas_file.read_bytes()
    args = (["-v"] if verbose else []) + ["track", str(meas_file), "--model", PAPER, "--estimator", "ge", "-o",
                                          str(out)]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 1, res.output
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("Error: internal error: ValueError at ")
    assert SHAPE_ERROR in last and "this is a bug in heartcv, not a problem with your input" in last
    assert str(meas_file) not in last  # the user's file is not blamed
    assert ("Traceback (most recent call last)" in res.stderr) is verbose
    assert ("run with -v for the traceback" in last) is not verbose
    if verbose:
        assert "in conditional_split" not in res.stderr and "in broken" in res.stderr
    assert os.listdir(tmp_path) == [] and meas_file.read_bytes() == before


def test_a_value_error_inside_the_fit_is_an_internal_error(tmp_path, meas_file, monkeypatch):
    """The fit no longer turns an evaluation's ValueError into "bad input" (exit 2) or "not converged" (exit 1):
    the internal-error message says it is a bug."""
    from heartcv.tracker.fit import FitProblem

    def broken(self, theta):
        raise ValueError(SHAPE_ERROR)

    monkeypatch.setattr(FitProblem, "residuals", broken)
    out = tmp_path / "p.yaml"
    res = CliRunner().invoke(main, ["fit", str(meas_file), "--model", PAPER, "-o", str(out)])
    assert res.exit_code == 1, res.output
    assert "Error: internal error: ValueError" in res.stderr and "did not converge" not in res.stderr
    assert not out.exists()


@pytest.mark.parametrize("code, system", [(errno.ENOSPC, True), (errno.EROFS, True), (errno.EINVAL, False)])
def test_a_full_disk_is_a_failed_stage_not_a_bug(tmp_path, monkeypatch, code, system):
    """An OSError the machine causes (a full disk, a read-only file system) while writing an output stops the stage
    with exit 1 and the system's reason, neither as a bug nor as bad input, and leaves no file under the output's
    name; any other OSError stays an internal error."""
    from pathlib import Path

    def refuse(self, data):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(Path, "write_bytes", refuse)
    out = tmp_path / "m.npz"
    res = CliRunner().invoke(main, ["model", "simulate", PAPER, "--duration", "0.2", "-o", str(out)])
    assert res.exit_code == 1, res.output
    last = res.stderr.strip().splitlines()[-1]
    if system:
        assert last == (f"Error: {os.strerror(code)} -- the system refused a file operation (free space or fix the "
                        "permissions and run again); the stage stopped, its outputs are incomplete or absent")
    else:
        assert last.startswith("Error: internal error: OSError at ") and "this is a bug in heartcv" in last
    assert "Traceback" not in res.stderr and os.listdir(tmp_path) == []


def test_ctrl_c_while_the_console_script_starts_is_one_line_and_exit_130():
    """The console script (heartcv.cli.entry:run) with a KeyboardInterrupt raised while it imports the command
    line, as a Ctrl-C in the first tenths of a second: one line on stderr, exit 130, no traceback (it was Python's
    traceback and exit -2). The same script runs a command otherwise."""
    import subprocess
    import sys

    code = ("import builtins, sys\n"
            "real = builtins.__import__\n"
            "def imp(name, *a, **k):\n"
            "    if name == 'heartcv.cli.main':\n"
            "        raise KeyboardInterrupt\n"
            "    return real(name, *a, **k)\n"
            "builtins.__import__ = imp\n"
            "from heartcv.cli.entry import run\n"
            "sys.argv = ['heartcv', '--version']\n"
            "run()\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 130 and "Traceback" not in res.stderr, res.stderr
    assert res.stderr == "Error: interrupted (Ctrl-C) while starting: nothing was done\n"
    ok = subprocess.run([sys.executable, "-c", "import sys; from heartcv.cli.entry import run; "
                         "sys.argv = ['heartcv', '--version']; run()"], capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0 and "heartcv, version" in ok.stdout
