"""Output safety of the model and estimator stages (model simulate, track, fit, report, simulate): no stage ever
overwrites or deletes an input or a file or folder it did not write; unwritable outputs, NaN / infinite and
out-of-range options exit 2 before any work; a successful run logs its summary at INFO."""

import os
from pathlib import Path
import shutil

from click.testing import CliRunner
import pytest

from heartcv.cli.main import main
from heartcv.tracker.io import read_measurements, write_measurements
from heartcv.tracker.measurements import MeasurementSet
from tests.conftest import SAMPLES

PAPER = SAMPLES / "paper_patch.yaml"


def _run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _ok(*args):
    res = _run(*args)
    assert res.exit_code == 0, res.output
    return res


def _snapshot(folder: Path) -> dict:
    """{relative path: bytes} of every file under ``folder``."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A model file, its measurements and truth, a KF estimate and a fit's parameters file."""
    d = tmp_path_factory.mktemp("safety")
    shutil.copy(PAPER, d / "model.yaml")
    _ok("model", "simulate", d / "model.yaml", "--duration", "1", "--seed", "1", "-o", d / "m.npz",
        "--truth", d / "t.npz")
    _ok("track", d / "m.npz", "--model", d / "model.yaml", "-o", d / "kf.npz")
    _ok("fit", d / "m.npz", "--model", d / "model.yaml", "--starts", "1", "-o", d / "p.yaml")
    return d


@pytest.fixture
def here(work, tmp_path):
    """A private copy of ``work`` (tests may try to damage it)."""
    for p in work.iterdir():
        shutil.copy(p, tmp_path / p.name)
    return tmp_path


def _refused(res, *paths):
    """Exit 2, one line naming every path, no traceback."""
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output and "internal error" not in res.output
    for p in paths:
        assert str(p) in res.stderr, (p, res.stderr)


# -- an output that is an input ----------------------------------------------------------------------------------
@pytest.mark.parametrize("args, label", [
    (["model", "simulate", "{model}", "--duration", "1", "-o", "{model}"], "MODEL_FILE"),
    (["model", "simulate", "{model}", "--duration", "1", "-o", "{here}/x.npz", "--truth", "{model}"], "MODEL_FILE"),
    (["track", "{meas}", "--model", "{model}", "-o", "{meas}"], "MEASUREMENTS"),
    (["track", "{meas}", "--model", "{model}", "-o", "{model}"], "--model"),
    (["track", "{meas}", "--model", "{model}", "--params", "{params}", "-o", "{params}"], "--params"),
    (["fit", "{meas}", "--model", "{model}", "-o", "{model}"], "--model"),
    (["fit", "{meas}", "--model", "{model}", "-o", "{params}", "--starts", "1"], None),  # a re-run: allowed
])
def test_an_output_equal_to_an_input_is_refused_and_the_input_kept(here, args, label):
    subs = {"{model}": here / "model.yaml", "{meas}": here / "m.npz", "{params}": here / "p.yaml",
            "{here}": here}
    argv = [str(subs.get(a, a)).replace("{here}", str(here)) for a in args]
    before = _snapshot(here)
    res = _run(*argv)
    if label is None:
        assert res.exit_code == 0, res.output
        return
    out = argv[argv.index("--truth") + 1] if "--truth" in argv else argv[argv.index("-o") + 1]
    _refused(res, out)
    assert f"is the input {label} ({out})" in res.stderr
    assert _snapshot(here) == before


def test_model_simulate_output_and_truth_are_one_file(here):
    same = here / "both.npz"
    res = _run("model", "simulate", here / "model.yaml", "--duration", "1", "-o", same, "--truth", same)
    _refused(res, same)
    assert f"-o/--output and --truth name the same file ({same})" in res.stderr
    assert not same.exists()
    # an earlier file of that name (heartcv's own) stays as it was
    shutil.copy(here / "m.npz", same)
    before = same.read_bytes()
    _refused(_run("model", "simulate", here / "model.yaml", "--duration", "1", "-o", same, "--truth",
                  here / "." / "both.npz"), same)
    assert same.read_bytes() == before


def _absurd(meas_path: Path, out: Path) -> None:
    """The measurements with absurd (finite) positions from frame 5 on: the GE diverges at step 5."""
    m = read_measurements(meas_path)
    pos = m.positions.copy()
    pos[5:] += 1e10
    write_measurements(out, MeasurementSet(m.times, m.point_ids, pos, m.covariances, m.reference, m.inputs,
                                           m.input_names, m.input_units))


def test_track_partial_file_never_replaces_an_input(here):
    """A diverging run writes its steps to OUT.partial.npz: when that is the input, the run is refused first."""
    inp = here / "ge.partial.npz"
    _absurd(here / "m.npz", inp)
    before = inp.read_bytes()
    res = _run("track", inp, "--model", here / "model.yaml", "--estimator", "ge", "-o", here / "ge.npz")
    _refused(res, here / "ge.partial.npz")
    assert f"is the input MEASUREMENTS ({inp})" in res.stderr
    assert inp.read_bytes() == before and not (here / "ge.npz").exists()


def test_track_partial_file_replaces_only_a_heartcv_file(here):
    (here / "ge.partial.npz").write_text("my notes")
    _absurd(here / "m.npz", here / "absurd.npz")
    res = _run("track", here / "absurd.npz", "--model", here / "model.yaml", "--estimator", "ge", "-o",
               here / "ge.npz")
    _refused(res, here / "ge.partial.npz")
    assert "exists and was not written by heartcv; not replaced" in res.stderr
    assert (here / "ge.partial.npz").read_text() == "my notes"


@pytest.mark.parametrize("stage", ["model simulate", "track", "fit"])
def test_an_output_file_heartcv_did_not_write_is_kept(here, stage):
    mine = here / ("mine.yaml" if stage == "fit" else "mine.npz")
    mine.write_text("my own notes")
    args = {"model simulate": ["model", "simulate", here / "model.yaml", "--duration", "1"],
            "track": ["track", here / "m.npz", "--model", here / "model.yaml"],
            "fit": ["fit", here / "m.npz", "--model", here / "model.yaml", "--starts", "1"]}[stage]
    res = _run(*args, "-o", mine)
    _refused(res, mine)
    assert "exists and was not written by heartcv; not replaced (remove it or choose another path)" in res.stderr
    assert mine.read_text() == "my own notes"


@pytest.mark.parametrize("stage, victim, kind", [
    ("fit", "model.yaml", "heartcv.model"),           # a model file a person wrote: never replaced
    ("fit", "rig.yaml", "heartcv.rig"),               # another stage's file: not replaced by a fit
    ("track", "m.npz", "heartcv.measurements"),
    ("model simulate", "kf.npz", "heartcv.estimates"),
    ("model simulate", "m.npz", None),                # the same kind: replaced (a rerun)
])
def test_an_output_replaces_only_a_file_of_its_own_kind(here, stage, victim, kind):
    """A heartcv file of another kind than the output (written by another stage, or a model or scene file that a
    person wrote) is kept; one of the output's own kind is replaced, as a rerun does."""
    _ok("rig", "rectified", "--image-size", "360x288", "--focal-px", "390", "--baseline-m", "0.0055",
        "-o", here / "rig.yaml")
    target = here / f"copy_{victim}"
    shutil.copy(here / victim, target)
    before = target.read_bytes()
    args = {"model simulate": ["model", "simulate", here / "model.yaml", "--duration", "1", "--seed", "2"],
            "track": ["track", here / "m.npz", "--model", here / "model.yaml"],
            "fit": ["fit", here / "m.npz", "--model", here / "model.yaml", "--starts", "1"]}[stage]
    res = _run(*args, "-o", target)
    if kind is None:
        assert res.exit_code == 0, res.output
        assert target.read_bytes() != before
        return
    _refused(res, target)
    assert kind in res.stderr and "not replaced" in res.stderr
    assert target.read_bytes() == before


@pytest.mark.parametrize("stage", ["fit", "track", "report"])
def test_an_output_folder_without_write_permission_exits_2_before_any_work(here, stage, monkeypatch):
    """(Simulated: the tests may run as root.) Before, fit and track found it only after all their work."""
    import os

    locked = here / "locked"
    locked.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p) == locked else real(p, mode))
    args = {"fit": ["fit", here / "m.npz", "--model", here / "model.yaml", "--starts", "1", "-o", locked / "p.yaml"],
            "track": ["track", here / "m.npz", "--model", here / "model.yaml", "-o", locked / "kf.npz"],
            "report": ["report", here / "kf.npz", "-o", locked / "rep"]}[stage]
    res = _run(*args)
    _refused(res, locked)
    assert "cannot write here (no permission to write into" in res.stderr
    assert "INFO" not in res.stderr and "wrote" not in res.stderr and list(locked.iterdir()) == []


# -- output folders: report and simulate -------------------------------------------------------------------------
def test_report_into_a_report_folder_holding_an_input_is_refused(here):
    """The old report replaced any folder holding metrics.json, with the estimate file the user kept in it."""
    rep = here / "rep"
    _ok("report", here / "kf.npz", "-o", rep)
    shutil.copy(here / "kf.npz", rep / "kf.npz")
    before = _snapshot(rep)
    res = _run("report", rep / "kf.npz", "-o", rep)
    _refused(res, rep, rep / "kf.npz")
    assert f"contains the input ESTIMATES ({rep / 'kf.npz'}); the stage would replace it" in res.stderr
    assert _snapshot(rep) == before


@pytest.mark.parametrize("option", ["--truth", "--measurements"])
def test_report_folder_containing_the_truth_or_measurements_is_refused(here, option):
    rep = here / "rep"
    _ok("report", here / "kf.npz", "-o", rep)
    name = "t.npz" if option == "--truth" else "m.npz"
    shutil.copy(here / name, rep / name)
    before = _snapshot(rep)
    res = _run("report", here / "kf.npz", option, rep / name, "-o", rep)
    _refused(res, rep, rep / name)
    assert f"contains the input {option}" in res.stderr
    assert _snapshot(rep) == before


def test_report_replaces_only_a_folder_a_report_wrote(here):
    """A hand-made folder that happens to hold metrics.json is not a report folder (no manifest): kept."""
    mine = here / "mine"
    mine.mkdir()
    (mine / "metrics.json").write_text("{}")
    (mine / "notes.md").write_text("mine")
    before = _snapshot(mine)
    res = _run("report", here / "kf.npz", "-o", mine)
    _refused(res, mine)
    assert "exists and holds no heartcv manifest: heartcv report replaces only a folder it wrote itself" \
        in res.stderr
    assert _snapshot(mine) == before
    # a study folder is not a report folder either
    study = here / "study"
    _ok("simulate", here / "model.yaml", "--runs", "2", "--steps", "3", "--estimators", "kf", "--workers", "1",
        "-o", study)
    before = _snapshot(study)
    res = _run("report", here / "kf.npz", "-o", study)
    _refused(res, study)
    assert "exists and was written by 'heartcv simulate'" in res.stderr
    assert _snapshot(study) == before


def test_a_report_folder_holding_a_file_a_person_added_is_kept(here):
    """A rerun replaces its own report folder, but not one into which a person put a file (it would be deleted);
    the manifest lists every file the run wrote."""
    import json

    rep = here / "rep"
    _ok("report", here / "kf.npz", "-o", rep, "--resamples", "0")
    listed = json.loads((rep / "heartcv-manifest.json").read_text())["files"]
    assert sorted(listed) == sorted(p for p in _snapshot(rep) if p != "heartcv-manifest.json")
    (rep / "figs").mkdir(exist_ok=True)
    (rep / "figs" / "notes.txt").write_text("mine")
    before = _snapshot(rep)
    res = _run("report", here / "kf.npz", "-o", rep, "--resamples", "0")
    _refused(res, rep)
    assert "holds files heartcv report did not write (figs/notes.txt)" in res.stderr
    assert _snapshot(rep) == before
    (rep / "figs" / "notes.txt").unlink()
    res = _run("report", here / "kf.npz", "-o", rep, "--resamples", "0")   # the person's (now empty) folder too
    _refused(res, rep)
    assert "holds files heartcv report did not write (figs/)" in res.stderr
    (rep / "figs").rmdir()
    _ok("report", here / "kf.npz", "-o", rep, "--resamples", "0")


def test_a_report_folder_of_an_older_manifest_is_kept(here):
    """A folder written before manifests listed their files (no ``files`` key): a file a person added cannot be told
    from the report's own, so the folder is not replaced (the earlier code replaced it and deleted the file)."""
    import json

    rep = here / "old"
    _ok("report", here / "kf.npz", "-o", rep, "--resamples", "0")
    man = json.loads((rep / "heartcv-manifest.json").read_text())
    del man["files"]
    (rep / "heartcv-manifest.json").write_text(json.dumps(man))
    (rep / "notes.txt").write_text("mine")
    before = _snapshot(rep)
    res = _run("report", here / "kf.npz", "-o", rep, "--resamples", "0")
    _refused(res, rep)
    assert "whose manifest does not list its files" in res.stderr
    assert _snapshot(rep) == before


def test_simulate_into_a_folder_it_did_not_write_is_refused(here):
    """The old study stage wrote its files into any folder, replacing a nis.png or study.npz kept there."""
    folder = here / "results"
    folder.mkdir()
    (folder / "nis.png").write_bytes(b"my figure")
    (folder / "summary.json").write_text('{"format": "heartcv.study", "files": ["nis.png"]}')
    before = _snapshot(folder)
    res = _run("simulate", here / "model.yaml", "--runs", "2", "--steps", "3", "--workers", "1", "-o", folder)
    _refused(res, folder)
    assert "holds no heartcv manifest: heartcv simulate replaces only a folder it wrote itself" in res.stderr
    assert _snapshot(folder) == before


def test_simulate_into_the_folder_of_its_model_file_is_refused(here):
    before = _snapshot(here)
    res = _run("simulate", here / "model.yaml", "--runs", "2", "--steps", "3", "-o", here)
    _refused(res, here, here / "model.yaml")
    assert f"contains the input MODEL_FILE ({here / 'model.yaml'})" in res.stderr
    assert _snapshot(here) == before


# -- unwritable outputs ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("stage", ["model simulate", "track", "fit", "report", "simulate"])
def test_output_below_a_file_exits_2_naming_it(here, stage):
    out = here / "m.npz" / ("p.yaml" if stage == "fit" else "out")
    args = {"model simulate": ["model", "simulate", here / "model.yaml", "--duration", "1"],
            "track": ["track", here / "m.npz", "--model", here / "model.yaml"],
            "fit": ["fit", here / "m.npz", "--model", here / "model.yaml"],
            "report": ["report", here / "kf.npz"],
            "simulate": ["simulate", here / "model.yaml", "--runs", "2", "--steps", "3"]}[stage]
    before = _snapshot(here)
    res = _run(*args, "-o", out)
    _refused(res, out)
    assert f"-o/--output: {here / 'm.npz'} is not a folder" in res.stderr
    assert _snapshot(here) == before


# -- option values: NaN, infinities, ranges ----------------------------------------------------------------------
SIM = ["model", "simulate", "{model}", "-o", "{out}"]


@pytest.mark.parametrize("args, message", [
    (SIM + ["--duration", "nan"], "Invalid value for '--duration': 'nan': a finite number expected"),
    (SIM + ["--duration", "inf"], "Invalid value for '--duration': 'inf': a finite number expected"),
    (SIM + ["--duration", "0"], "Invalid value for '--duration': 0 is not in the range (0, 86400]"),
    (SIM + ["--duration", "86401"], "Invalid value for '--duration': 86401 is not in the range (0, 86400]"),
    (SIM + ["--duration", "86400"], "--duration 86400 s at the model's 30 Hz gives 2592001 frames of 1 substeps; "
                                    "at most 1000000 frames and 1000000 integration steps"),
    (SIM + ["--duration", "3600", "--substeps", "10"], "gives 108001 frames of 10 substeps"),
    (SIM + ["--duration", "1", "--missing", "nan"], "Invalid value for '--missing': 'nan': a finite number expected"),
    (SIM + ["--duration", "1", "--missing", "1.5"], "Invalid value for '--missing': 1.5 is not in the range [0, 1]"),
    (SIM + ["--duration", "1", "--missing", "-0.1"], "Invalid value for '--missing': -0.1 is not in the range"),
    (SIM + ["--duration", "1", "--substeps", "0"], "Invalid value for '--substeps': 0 is not in the range 1<=x<=1000"),
    (SIM + ["--duration", "1", "--substeps", "1001"], "1001 is not in the range 1<=x<=1000"),
    (SIM + ["--duration", "1", "--stiffness-cycle", "inf"], "'--stiffness-cycle': 'inf': a finite number expected"),
    (SIM + ["--duration", "1", "--stiffness-cycle", "21"], "'--stiffness-cycle': 21 is not in the range [0, 20]"),
    (SIM + ["--duration", "1", "--seed", "-1"], "Invalid value for '--seed': -1 is not in the range"),
    (["simulate", "{model}", "-o", "{out}", "--runs", "10001"], "10001 is not in the range 2<=x<=10000"),
    (["simulate", "{model}", "-o", "{out}", "--steps", "100001"], "100001 is not in the range 2<=x<=100000"),
    (["simulate", "{model}", "-o", "{out}", "--runs", "1000", "--steps", "100000"],
     "--runs 1000 x --steps 100000: at most 10000000 run-steps in one study"),
    (["simulate", "{model}", "-o", "{out}", "--workers", "0"], "0 is not in the range 1<=x<=1024"),
    (["simulate", "{model}", "-o", "{out}", "--workers", "1025"], "1025 is not in the range 1<=x<=1024"),
    (["fit", "{meas}", "--model", "{model}", "-o", "{out}.yaml", "--frames", "1"], "1 is not in the range "
                                                                                  "2<=x<=1000000"),
    (["fit", "{meas}", "--model", "{model}", "-o", "{out}.yaml", "--frames", "1000001"], "1000001 is not in the"),
    (["fit", "{meas}", "--model", "{model}", "-o", "{out}.yaml", "--starts", "0"], "0 is not in the range "
                                                                                  "1<=x<=1000"),
    (["fit", "{meas}", "--model", "{model}", "-o", "{out}.yaml", "--starts", "1001"], "1001 is not in the range"),
    (["fit", "{meas}", "--model", "{model}", "-o", "{out}.yaml", "--max-evaluations", "0"], "0 is not in the range "
                                                                                           "1<=x<=1000000"),
    (["fit", "{meas}", "--model", "{model}", "-o", "{out}.yaml", "--max-evaluations", "1e9"], "'1e9' is not a "
                                                                                             "valid integer"),
    (["report", "{kf}", "-o", "{out}", "--dpi", "71"], "71 is not in the range 72<=x<=600"),
    (["report", "{kf}", "-o", "{out}", "--dpi", "601"], "601 is not in the range 72<=x<=600"),
])
def test_bad_option_values_exit_2_before_any_work(here, args, message):
    subs = {"{model}": here / "model.yaml", "{meas}": here / "m.npz", "{kf}": here / "kf.npz"}
    out = here / "out"
    argv = [str(subs.get(a, a)).replace("{out}", str(out)) for a in args]
    before = _snapshot(here)
    res = _run(*argv)
    assert res.exit_code == 2, res.output
    assert message in res.stderr and res.stdout == ""
    assert _snapshot(here) == before


# -- the summary of a successful run is INFO ---------------------------------------------------------------------
@pytest.mark.parametrize("stage, line", [
    ("model simulate", "INFO heartcv.cli.model: wrote {out} (31 frames, 14 points)"),
    ("track", "INFO heartcv.cli.track: wrote {out}: 31 steps, prediction RMSE "),
    ("fit", "INFO heartcv.cli.fit: wrote {out}: E = "),
    ("report", "INFO heartcv.cli.report: wrote {out} (3 figures); kf: prediction error "),
    ("simulate", "INFO heartcv.cli.simulate: 2 runs x 3 steps, seed 0, estimated E, nu -> {out}"),
])
def test_a_successful_run_logs_its_summary_at_info(here, stage, line):
    out = here / ("o.yaml" if stage == "fit" else "o.npz" if stage in ("model simulate", "track") else "o")
    args = {"model simulate": ["model", "simulate", here / "model.yaml", "--duration", "1"],
            "track": ["track", here / "m.npz", "--model", here / "model.yaml"],
            "fit": ["fit", here / "m.npz", "--model", here / "model.yaml", "--starts", "1"],
            "report": ["report", here / "kf.npz"],
            "simulate": ["simulate", here / "model.yaml", "--runs", "2", "--steps", "3", "--estimators", "kf",
                         "--workers", "1"]}[stage]
    res = _ok(*args, "-o", out)
    assert line.format(out=out) in res.stderr
    assert "WARNING" not in res.stderr and res.stdout == ""
    quiet = _ok("-q", *args, "-o", out)  # -q: warnings only, and a re-run replaces the stage's own output
    assert quiet.stderr == "" and quiet.stdout == ""


# -- outputs that are not plain files, links, odd names (a safety audit of 2026-11-29) ---------------------------------
def test_an_output_that_is_not_a_regular_file_is_refused_before_any_work(here):
    """A FIFO (the stage hung reading it, then replaced it with its file), a device (as root, -o /dev/null became a
    148 KB estimate file), a symbolic link (the user's link became a file) and '..' after a symlinked folder (the
    output check took 'lnk/..' by its text and wrote over an input): exit 2 naming the path, nothing touched."""
    import os
    import stat

    fifo = here / "fifo.npz"
    os.mkfifo(fifo)
    res = _run("track", here / "m.npz", "--model", here / "model.yaml", "-o", fifo)
    _refused(res, fifo)
    assert "is not a regular file (a device, a FIFO or a socket)" in res.stderr
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    if os.geteuid() == 0:   # a device node of one's own (never the system's /dev/null)
        dev = here / "null.npz"
        os.mknod(dev, stat.S_IFCHR | 0o666, os.makedev(1, 3))
        res = _run("track", here / "m.npz", "--model", here / "model.yaml", "-o", dev)
        _refused(res, dev)
        assert stat.S_ISCHR(os.lstat(dev).st_mode)
    (here / "keep").mkdir()
    _ok("track", here / "m.npz", "--model", here / "model.yaml", "-o", here / "keep" / "v1.npz")
    link = here / "latest.npz"
    link.symlink_to(here / "keep" / "v1.npz")
    before = (here / "keep" / "v1.npz").read_bytes()
    res = _run("track", here / "m.npz", "--model", here / "model.yaml", "-o", link)
    _refused(res, link)
    assert "is a symbolic link" in res.stderr and link.is_symlink()
    assert (here / "keep" / "v1.npz").read_bytes() == before
    (here / "real" / "sub").mkdir(parents=True)
    (here / "lnk").symlink_to(here / "real" / "sub")
    shutil.copy(here / "m.npz", here / "real" / "m.npz")
    before = _snapshot(here / "real")
    res = _run("track", here / "real" / "m.npz", "--model", here / "model.yaml", "-o", "%s/lnk/../m.npz" % here)
    _refused(res)
    assert "is the input MEASUREMENTS" in res.stderr, res.stderr
    assert _snapshot(here / "real") == before


@pytest.mark.parametrize("name, message", [
    ("", "an empty path; a file path expected"),
    ("x" * 300 + ".npz", "a name of 304 bytes; at most 255 expected"),
    ("new/", "ends with a path separator (a folder); a file path expected"),
])
def test_output_names_the_system_cannot_create_exit_2(here, name, message):
    """An empty -o, a name beyond 255 bytes, a folder path: exit 2 before any work (they were internal errors, or
    wrote a file 'new')."""
    target = name if name in ("",) else (str(here / name) + ("/" if name.endswith("/") else ""))
    res = _run("track", here / "m.npz", "--model", here / "model.yaml", "-o", target)
    assert res.exit_code == 2 and message in res.stderr and "internal error" not in res.output, res.output
    assert not (here / "new").exists()


def test_names_of_up_to_255_bytes_are_written_and_rewritten(here):
    """Output names of 241-255 bytes were refused ('File name too long'): the temporary name beside them was
    longer. A 255-byte file name (multi-byte characters included) and folder name: written, then replaced by a
    rerun (its hidden names too), leaving nothing else behind."""
    files = [here / ("é" * 125 + "a.npz"), here / ("t" * 251 + ".npz")]
    folder = here / ("r" * 255)
    assert [len(os.fsencode(p.name)) for p in files + [folder]] == [255, 255, 255]
    before = set(os.listdir(here))
    for seed in ("1", "2"):
        _ok("model", "simulate", here / "model.yaml", "--duration", "0.2", "--seed", seed, "-o", files[0],
            "--truth", files[1])
        _ok("report", files[0].with_name("kf.npz"), "-o", folder, "--resamples", "0")
    assert set(os.listdir(here)) - before == {p.name for p in files + [folder]}
    assert (folder / "metrics.json").is_file()


def test_an_output_of_another_kind_is_not_replaced(here, tmp_path):
    """The kind of an output is checked for every file a stage writes: an estimate file is not written over the
    printable target (PNG/PDF of heartcv target), a CSV export not over a parameters file; and an output that lies
    inside another output folder of the same run is refused before any work."""
    from heartcv.tracker.files import InputError, check_output_file, refuse_overlap

    _ok("target", "--type", "chessboard", "--inner-corners", "6x4", "--square-mm", "10", "-o", here / "t.yaml")
    for f in ("t.pdf", "t.png"):
        before = (here / f).read_bytes()
        res = _run("track", here / "m.npz", "--model", here / "model.yaml", "-o", here / f)
        _refused(res, here / f)
        assert (here / f).read_bytes() == before
    with pytest.raises(InputError, match="holds a heartcv.parameters file, not a csv file"):
        check_output_file(here / "p.yaml", "--csv", ("csv",))
    with pytest.raises(InputError, match=r"lies inside the output --report"):
        refuse_overlap({"-o/--output": tmp_path / "rep" / "rig.yaml", "--report": tmp_path / "rep"}, {})


def test_a_report_folder_with_a_link_or_an_edited_file_is_kept(here):
    """A rerun deleted a link a person put into the report folder and lost text appended to its summary.md."""
    rep = here / "rep"
    _ok("report", here / "kf.npz", "-o", rep, "--resamples", "0")
    (rep / "elsewhere").symlink_to(here)
    res = _run("report", here / "kf.npz", "-o", rep, "--resamples", "0")
    _refused(res, rep)
    assert "did not write (elsewhere)" in res.stderr and (rep / "elsewhere").is_symlink()
    (rep / "elsewhere").unlink()
    with open(rep / "summary.md", "a") as f:
        f.write("\nmy notes\n")
    res = _run("report", here / "kf.npz", "-o", rep, "--resamples", "0")
    _refused(res, rep)
    assert "holds files changed since heartcv report wrote them (summary.md)" in res.stderr
    assert (rep / "summary.md").read_text().endswith("my notes\n")


@pytest.mark.parametrize("sig, code, what", [("SIGINT", 130, "interrupted (Ctrl-C)"),
                                             ("SIGTERM", 143, "terminated (SIGTERM)")])
def test_an_interrupted_stage_keeps_the_earlier_output_and_leaves_no_temporary_files(here, sig, code, what):
    """Ctrl-C and SIGTERM during a Monte-Carlo study with worker processes: one line and exit 130 / 143 (was
    click's 'Aborted!' exit 1 with a traceback per worker; SIGTERM left the hidden temporary folders behind), the
    earlier study folder byte for byte, no temporary folder, no worker left."""
    import signal
    import subprocess
    import sys
    import time

    _ok("simulate", here / "model.yaml", "--runs", "2", "--steps", "5", "--workers", "1", "-o", here / "st")
    before = _snapshot(here / "st")
    cmd = [sys.executable, "-m", "heartcv.cli.main", "-q", "simulate", str(here / "model.yaml"), "--runs", "400",
           "--steps", "200", "--workers", "2", "-o", str(here / "st")]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, start_new_session=True)
    time.sleep(4.0)         # imports, the model, the workers started: 400 runs take minutes
    assert proc.poll() is None, "the study ended before it could be interrupted"
    proc.send_signal(getattr(signal, sig))
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code, err
    assert f"Error: {what}: stopped; nothing was replaced" in err and "Traceback" not in err, err
    assert _snapshot(here / "st") == before
    assert not list(here.glob(".st.*")), list(here.glob(".st.*"))
    time.sleep(0.5)
    ps = subprocess.run(["pgrep", "-s", str(proc.pid)], capture_output=True, text=True)
    assert ps.stdout.strip() == "", ps.stdout
