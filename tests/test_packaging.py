"""Packaging: the folders tracker/ and cli/ install as heartcv.tracker and heartcv.cli, so another distribution's
top-level ``tracker`` or ``cli`` package can live beside heartcv; tracker/ depends on nothing in heartcv/ or cli/."""

from __future__ import annotations

import ast
from pathlib import Path
import subprocess
import sys

ROOT = Path(__file__).resolve().parents[1]

_CHECK = r"""
import importlib, pkgutil, sys
import tracker, cli                      # the dummy distributions, first on sys.path
assert tracker.WHO == "dummy-tracker" and cli.WHO == "dummy-cli", (tracker.__file__, cli.__file__)
import heartcv, heartcv.tracker, heartcv.cli
names = [m.name for m in pkgutil.walk_packages(heartcv.__path__, "heartcv.")]
names += [m.name for m in pkgutil.walk_packages(heartcv.tracker.__path__, "heartcv.tracker.")]
names += [m.name for m in pkgutil.walk_packages(heartcv.cli.__path__, "heartcv.cli.")]
skip = ("heartcv.backends.kornia_backend",)       # needs torch; imported only with --backend kornia
for n in sorted(set(names)):
    if n not in skip:
        importlib.import_module(n)
from heartcv.cli.main import COMMANDS
for target in COMMANDS.values():
    importlib.import_module(target.split(":")[0])
# nothing of heartcv replaced or extended the dummies
assert sys.modules["tracker"] is tracker and sys.modules["cli"] is cli
leaked = [m for m in sys.modules if m.startswith(("tracker.", "cli."))]
assert not leaked, leaked
print(heartcv.tracker.__file__, heartcv.cli.__file__, len(names))
"""


def test_heartcv_imports_beside_dummy_tracker_and_cli_packages(tmp_path):
    for name in ("tracker", "cli"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text(f'WHO = "dummy-{name}"\n')
    # run from the dummies' folder: the repository is not on sys.path, heartcv comes from the installed package
    res = subprocess.run([sys.executable, "-c", _CHECK], cwd=tmp_path, capture_output=True, text=True,
                         env={"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"})
    assert res.returncode == 0, res.stderr[-3000:]
    tracker_file, cli_file, count = res.stdout.split()
    assert Path(tracker_file).parent == ROOT / "tracker" and Path(cli_file).parent == ROOT / "cli"
    assert int(count) > 40


def _imports(path: Path):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                yield node.module or ""
            elif node.level >= 2:  # from .. import x: outside the package
                yield "." * node.level + (node.module or "")


def test_tracker_depends_on_nothing_in_heartcv_or_cli():
    bad = []
    for path in sorted((ROOT / "tracker").glob("*.py")):
        for mod in _imports(path):
            outside_heartcv = mod.startswith("heartcv") and not mod.startswith("heartcv.tracker")
            if outside_heartcv or mod.startswith((".", "cli", "tracker")):
                bad.append(f"{path.name}: {mod}")
    assert not bad, bad


def test_no_module_imports_the_old_top_level_names():
    bad = []
    for folder in ("heartcv", "tracker", "cli", "benchmarks", "tests"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for mod in _imports(path):
                if mod.split(".")[0] in ("tracker", "cli"):
                    bad.append(f"{path.relative_to(ROOT)}: {mod}")
    assert not bad, bad


def test_the_wheel_installs_heartcv_tracker_and_heartcv_cli_and_no_top_level_names(tmp_path):
    import zipfile

    res = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                          "-w", str(tmp_path), str(ROOT)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-3000:]
    (wheel,) = tmp_path.glob("heartcv-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert tops == {"heartcv"}, tops
    assert "heartcv/tracker/kalman.py" in names and "heartcv/cli/main.py" in names
    assert "heartcv/tracker/files.py" in names and "heartcv/render/scene.py" in names
    entry = next(n for n in names if n.endswith("entry_points.txt"))
    assert "heartcv = heartcv.cli.entry:run" in zipfile.ZipFile(wheel).read(entry).decode()
