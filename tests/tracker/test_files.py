"""heartcv.tracker.files: the one file-handling foundation (errors, atomic writes, output safety, safe YAML, safe
.npz, CSV). Exact answers: round trips, byte-for-byte unchanged inputs, the refusal of crafted hostile files."""

from __future__ import annotations

import contextlib
import io
import json
import os
from pathlib import Path
import tracemalloc
import zipfile

from click.testing import CliRunner
import numpy as np
import pytest

from benchmarks.files import alias_bomb, huge_claim_copy
from heartcv.cli.main import main
from heartcv.tracker import files as F
from heartcv.tracker.files import ArraySpec, InputError

FMT = ("heartcv.measurements", 1)


# -- the error type -----------------------------------------------------------------------------------------------
def test_input_error_carries_file_and_field():
    e = InputError("a/b.yaml", "must be > 0", "parameters.E")
    assert (e.path, e.field, e.reason) == ("a/b.yaml", "parameters.E", "must be > 0")
    assert str(e) == "a/b.yaml: parameters.E: must be > 0"
    assert isinstance(e, ValueError)
    loose = InputError(None, "bad", "times")
    assert str(loose) == "times: bad"
    attached = loose.in_file("m.npz")
    assert str(attached) == "m.npz: times: bad" and attached.field == "times"
    assert e.in_file("other") is e  # keeps the file it already names


# -- atomic writes ------------------------------------------------------------------------------------------------
def test_atomic_path_replaces_only_on_success(tmp_path):
    p = tmp_path / "x.txt"
    p.write_text("old")
    with pytest.raises(RuntimeError):
        with F.atomic_path(p) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert p.read_text() == "old" and sorted(os.listdir(tmp_path)) == ["x.txt"]
    with F.atomic_path(p) as tmp:
        tmp.write_text("new")
    assert p.read_text() == "new" and sorted(os.listdir(tmp_path)) == ["x.txt"]


def test_a_replaced_file_keeps_its_permissions(tmp_path):
    """A new file gets 0666 minus the umask; a rerun replacing it keeps the mode a person gave it (0640)."""
    p = tmp_path / "params.yaml"
    old = os.umask(0o022)
    try:
        with F.atomic_path(p) as tmp:
            tmp.write_text("1")
        assert p.stat().st_mode & 0o777 == 0o644
        os.chmod(p, 0o640)
        for group in (contextlib.nullcontext(), F.output_group()):
            with group:
                with F.atomic_path(p) as tmp:
                    tmp.write_text("2")
            assert p.stat().st_mode & 0o777 == 0o640 and p.read_text() == "2"
    finally:
        os.umask(old)


def test_atomic_path_unwritable_destination_is_an_input_error(tmp_path):
    blocker = tmp_path / "file.txt"
    blocker.write_text("I am a file")
    with pytest.raises(InputError, match="cannot write here") as exc:
        with F.atomic_path(blocker / "out.npz"):
            pass
    assert exc.value.path == str(blocker / "out.npz") and exc.value.field == "output"
    assert blocker.read_text() == "I am a file"


def test_an_output_in_a_folder_without_write_permission_is_refused_before_any_work(tmp_path, monkeypatch):
    """(The tests run as any user, root included, who may write anywhere: the permission is simulated.)"""
    locked = tmp_path / "locked"
    locked.mkdir()
    real = os.access
    monkeypatch.setattr(F.os, "access", lambda p, mode: False if Path(p) == locked else real(p, mode))
    for check in (lambda: F.check_output_file(locked / "p.yaml", "-o/--output"),
                  lambda: F.check_output_file(locked / "new" / "deeper" / "p.yaml", "-o/--output"),
                  lambda: F.check_output_folder(locked / "report", "heartcv report", "-o/--output")):
        with pytest.raises(InputError, match=f"cannot write here \\(no permission to write into {locked}\\)") as exc:
            check()
        assert exc.value.field == "-o/--output"
    F.check_output_file(tmp_path / "p.yaml")                    # elsewhere: fine
    F.check_output_folder(tmp_path / "new" / "report", "heartcv report")


def test_atomic_folder_replaces_only_its_own_folder(tmp_path):
    out = tmp_path / "report"
    with F.atomic_folder(out, "heartcv report", {"inputs": 2}) as tmp:
        (tmp / "index.html").write_text("v1")
    man = F.read_manifest(out)
    assert man["producer"] == "heartcv report" and man["inputs"] == 2
    with F.atomic_folder(out, "heartcv report") as tmp:        # a re-run replaces it
        (tmp / "index.html").write_text("v2")
    assert (out / "index.html").read_text() == "v2"
    with pytest.raises(InputError, match="heartcv render replaces only a folder it wrote"):
        with F.atomic_folder(out, "heartcv render"):            # another stage's folder
            raise AssertionError("the block must not run")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "scene.yaml").write_text("precious")
    with pytest.raises(InputError, match="holds no heartcv manifest"):
        with F.atomic_folder(mine, "heartcv render"):
            raise AssertionError("the block must not run")
    assert (mine / "scene.yaml").read_text() == "precious" and os.listdir(mine) == ["scene.yaml"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine", "report"]  # no temporary folder left


def test_an_output_folder_that_is_a_link_is_named_as_one(tmp_path):
    """A link to a folder the stage wrote: refused as a link (it said 'not a folder'), link and folder kept; the
    folder it points to may be given instead."""
    with F.atomic_folder(tmp_path / "rep", "heartcv report") as tmp:
        (tmp / "a").write_text("1")
    (tmp_path / "lnk").symlink_to(tmp_path / "rep")
    with pytest.raises(InputError, match=r"lnk: -o/--output: is a symbolic link \(to .*rep\); not replaced"):
        F.check_output_folder(tmp_path / "lnk", "heartcv report")
    assert (tmp_path / "lnk").is_symlink() and (tmp_path / "lnk" / "a").read_text() == "1"
    F.check_output_folder(tmp_path / "rep", "heartcv report")


def test_atomic_folder_failure_keeps_the_previous_folder(tmp_path):
    out = tmp_path / "study"
    with F.atomic_folder(out, "heartcv simulate") as tmp:
        (tmp / "a").write_text("1")
    with pytest.raises(KeyError):
        with F.atomic_folder(out, "heartcv simulate") as tmp:
            (tmp / "a").write_text("2")
            raise KeyError("fail")
    assert (out / "a").read_text() == "1"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["study"]


def test_atomic_folder_raced_by_another_run_says_so(tmp_path, monkeypatch):
    """Another run renaming its folder into place between this run's check and its rename (ENOTEMPTY): a
    ConcurrentWrite naming the folder (the command line's exit 1, not an internal error); the other run's folder
    is kept and this run's temporary folder removed."""
    import errno

    out = tmp_path / "study"
    real = os.replace

    def raced(src, dst):
        if Path(dst) == out:
            out.mkdir(exist_ok=True)
            (out / "theirs").write_text("x")
            raise OSError(errno.ENOTEMPTY, "Directory not empty", str(dst))
        return real(src, dst)

    monkeypatch.setattr(F.os, "replace", raced)
    with pytest.raises(F.ConcurrentWrite, match="another run wrote this output folder at the same time"):
        with F.atomic_folder(out, "heartcv simulate") as tmp:
            (tmp / "a").write_text("1")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["study"] and (out / "theirs").read_text() == "x"


def _listing(root):
    return sorted((p.relative_to(root).as_posix(), p.read_text() if p.is_file() else None) for p in root.rglob("*"))


def _previous_run(tmp_path):
    (tmp_path / "m.csv").write_text("heartcv 1\n")
    with F.atomic_folder(tmp_path / "ov", "heartcv measure --overlay") as tmp:
        (tmp / "f.png").write_text("old")
    return _listing(tmp_path)


def test_output_group_puts_outputs_in_place_together_or_not_at_all(tmp_path):
    """Outputs of one stage: none renamed before the group's block ends; a failure or Ctrl-C half-way leaves the
    previous run's outputs byte for byte and no temporary file; success replaces all three."""
    before = _previous_run(tmp_path)
    for exc in (RuntimeError("overlay failed"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with F.output_group():
                with F.atomic_path(tmp_path / "m.csv") as tmp:
                    tmp.write_text("heartcv 2\n")
                with F.atomic_path(tmp_path / "new.npz") as tmp:
                    tmp.write_text("n")
                assert (tmp_path / "m.csv").read_text() == "heartcv 1\n" and not (tmp_path / "new.npz").exists()
                with F.atomic_folder(tmp_path / "ov", "heartcv measure --overlay") as tmp:
                    with F.atomic_path(tmp / "inner.txt") as t2:    # inside the folder: renamed at once
                        t2.write_text("i")
                    assert (tmp / "inner.txt").read_text() == "i"
                raise exc
        assert _listing(tmp_path) == before
    with F.output_group():
        with F.atomic_path(tmp_path / "m.csv") as tmp:
            tmp.write_text("heartcv 2\n")
        with F.atomic_folder(tmp_path / "ov", "heartcv measure --overlay") as tmp:
            (tmp / "f.png").write_text("new")
    assert (tmp_path / "m.csv").read_text() == "heartcv 2\n" and (tmp_path / "ov" / "f.png").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv", "ov"]


def test_output_group_undoes_the_renames_done_when_a_later_one_fails(tmp_path, monkeypatch):
    """The second of three renames fails (a full disk, say): the first output is put back from its hard link, the
    folder from where it was moved; nothing hidden is left behind."""
    import errno

    before = _previous_run(tmp_path)
    real = os.replace

    def failing(src, dst):
        if Path(dst) == tmp_path / "ov" and ".tmp-" in str(src):
            raise OSError(errno.EIO, "Input/output error", str(dst))
        return real(src, dst)

    monkeypatch.setattr(F.os, "replace", failing)
    with pytest.raises(OSError, match="Input/output"):
        with F.output_group():
            with F.atomic_path(tmp_path / "m.csv") as tmp:
                tmp.write_text("heartcv 2\n")
            with F.atomic_path(tmp_path / "new.npz") as tmp:
                tmp.write_text("n")
            with F.atomic_folder(tmp_path / "ov", "heartcv measure --overlay") as tmp:
                (tmp / "f.png").write_text("new")
    assert _listing(tmp_path) == before


def test_after_outputs_speaks_only_once_every_output_is_in_place(tmp_path, monkeypatch):
    """A stage's "wrote ..." line and --json summary (after_outputs): said after the renames, in the order given;
    never when the block or a rename fails; at once outside a group."""
    import errno

    said = []
    with F.output_group():
        with F.atomic_path(tmp_path / "a.txt") as tmp:
            tmp.write_text("a")
        F.after_outputs(lambda: said.append(("first", (tmp_path / "a.txt").exists())))
        F.after_outputs(lambda: said.append(("second", (tmp_path / "a.txt").exists())))
        assert said == []
    assert said == [("first", True), ("second", True)]
    F.after_outputs(lambda: said.append("outside"))
    assert said[-1] == "outside"
    said.clear()
    with pytest.raises(RuntimeError), F.output_group():
        F.after_outputs(lambda: said.append("failed block"))
        raise RuntimeError("stage failed")
    real = os.replace

    def failing(src, dst):
        raise OSError(errno.ENOSPC, "No space left on device", str(dst))

    monkeypatch.setattr(F.os, "replace", failing)
    with pytest.raises(OSError, match="No space"), F.output_group():
        with F.atomic_path(tmp_path / "b.txt") as tmp:
            tmp.write_text("b")
        F.after_outputs(lambda: said.append("failed rename"))
    monkeypatch.setattr(F.os, "replace", real)
    assert said == [] and not (tmp_path / "b.txt").exists()


def test_a_stage_whose_rename_fails_prints_no_summary(tmp_path, monkeypatch):
    """heartcv target --json with a full disk at the rename: exit 1 naming the reason, and neither the JSON
    summary on stdout nor a "wrote" line (both came before the renames); the same command prints both when the
    renames succeed."""
    import errno
    import json

    args = ["target", "--type", "chessboard", "--square-mm", "25", "--inner-corners", "8x5",
            "-o", str(tmp_path / "t.yaml")]
    ok = CliRunner().invoke(main, args + ["--json"])
    assert ok.exit_code == 0 and json.loads(ok.stdout)["output"].endswith("t.yaml")
    wrote = CliRunner().invoke(main, args)
    assert wrote.exit_code == 0 and "wrote " in wrote.stderr
    for p in list(tmp_path.iterdir()):
        p.unlink()

    def full(src, dst):
        raise OSError(errno.ENOSPC, "No space left on device", str(dst))

    monkeypatch.setattr(F.os, "replace", full)
    for extra in (["--json"], []):
        res = CliRunner().invoke(main, args + extra)
        assert res.exit_code == 1 and "No space left on device" in res.stderr
        assert res.stdout == "" and "wrote " not in res.stderr
    assert list(tmp_path.iterdir()) == []


class _Term(Exception):
    pass


@pytest.mark.parametrize("nth", [1, 2, 3])
def test_a_signal_during_the_renames_waits_until_they_are_done(tmp_path, monkeypatch, nth):
    """SIGTERM arriving just as the nth rename of the final commit returns (where the fault injection of the
    command line left a report folder hidden under its .old- name, or one output new and another old): held
    until every output is in place, then raised; all outputs new, nothing hidden left, outputs_committed() true.
    (The handler raises _Term here; the command line's raises Terminated.)"""
    import signal

    _previous_run(tmp_path)
    calls = {"n": 0}
    real = os.replace

    def replace(src, dst):
        real(src, dst)
        calls["n"] += 1
        if calls["n"] == nth:
            os.kill(os.getpid(), signal.SIGTERM)

    def handler(signum, frame):
        raise _Term()

    old = signal.signal(signal.SIGTERM, handler)
    try:
        monkeypatch.setattr(F.os, "replace", replace)
        with pytest.raises(_Term):
            with F.output_group():
                with F.atomic_path(tmp_path / "m.csv") as tmp:
                    tmp.write_text("heartcv 2\n")
                with F.atomic_folder(tmp_path / "ov", "heartcv measure --overlay") as tmp:
                    (tmp / "f.png").write_text("new")
                F.remove_output(tmp_path / "gone.yaml")
        assert F.outputs_committed()
    finally:
        signal.signal(signal.SIGTERM, old)
    assert (tmp_path / "m.csv").read_text() == "heartcv 2\n" and (tmp_path / "ov" / "f.png").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv", "ov"]


def test_sigterm_during_a_stages_renames_exits_143_with_its_outputs_complete(tmp_path, monkeypatch):
    """heartcv target over an earlier target, SIGTERM as its first output is renamed (the fault injection's
    yaml-new, png-and-pdf-old case): exit 143 saying the outputs are this run's and complete; all three new."""
    import signal

    args = ["target", "--type", "chessboard", "--square-mm", "25", "-o", str(tmp_path / "t.yaml")]
    assert CliRunner().invoke(main, args + ["--inner-corners", "8x5"]).exit_code == 0
    old = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    real, calls = os.replace, []

    def replace(src, dst):
        real(src, dst)
        calls.append(dst)
        if len(calls) == 1:
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(F.os, "replace", replace)
    res = CliRunner().invoke(main, args + ["--inner-corners", "9x6"])
    assert res.exit_code == 143 and "terminated (SIGTERM) after the outputs were put in place" in res.output
    new = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert sorted(new) == ["t.pdf", "t.png", "t.yaml"] and all(new[k] != old[k] for k in new) and len(calls) == 3


def test_an_output_removed_by_a_stage_is_kept_when_the_stage_fails(tmp_path):
    """calibrate removes the earlier Kalibr camchain when the new rig cannot be written as one: it deleted it at
    once, and an interrupted run lost it. Now removed with the renames."""
    cam = tmp_path / "rig_camchain.yaml"
    cam.write_text("# heartcv camchain\n")
    with pytest.raises(KeyboardInterrupt):
        with F.output_group():
            F.remove_output(cam)
            assert cam.read_text() == "# heartcv camchain\n"
            raise KeyboardInterrupt
    assert cam.read_text() == "# heartcv camchain\n" and sorted(p.name for p in tmp_path.iterdir()) == [cam.name]
    with F.output_group():
        F.remove_output(cam)
    assert list(tmp_path.iterdir()) == []


def test_a_failing_stage_on_the_command_line_leaves_its_earlier_outputs(tmp_path, monkeypatch):
    """End to end through the command line: model simulate writes its measurement file, then fails writing the
    truth file; the previous run's measurement file is unchanged and no new file appears."""
    from heartcv.tracker import io as tio

    model = tmp_path / "m.yaml"
    model.write_bytes((Path(__file__).resolve().parents[2] / "sample_sequences" / "paper_patch.yaml").read_bytes())
    args = ["model", "simulate", str(model), "-o", str(tmp_path / "meas.npz"), "--truth", str(tmp_path / "t.npz"),
            "--duration", "0.2", "--seed", "1"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    before = _listing_bytes(tmp_path)

    def broken(*a, **k):
        raise RuntimeError("boom")

    monkeypatch.setattr(tio, "write_truth", broken, raising=True)
    r = CliRunner().invoke(main, args[:-1] + ["2"])
    assert r.exit_code == 1 and "internal error" in r.output
    assert _listing_bytes(tmp_path) == before


def _listing_bytes(root):
    return sorted((p.name, p.read_bytes()) for p in root.iterdir())


# -- output safety ------------------------------------------------------------------------------------------------
def test_refuse_overlap_same_file_link_and_containing_folder(tmp_path):
    inp = tmp_path / "data" / "meas.npz"
    inp.parent.mkdir()
    inp.write_bytes(b"x")
    with pytest.raises(InputError, match=r"is the input MEASUREMENTS \(.*meas.npz\)") as exc:
        F.refuse_overlap({"-o/--output": inp}, {"MEASUREMENTS": inp})
    assert exc.value.field == "-o/--output"
    rel = os.path.relpath(inp, Path.cwd())
    with pytest.raises(InputError, match="is the input"):
        F.refuse_overlap({"-o": rel}, {"IN": str(inp)})           # relative vs absolute
    link = tmp_path / "link.npz"
    link.symlink_to(inp)
    with pytest.raises(InputError, match="is the input"):
        F.refuse_overlap({"-o": link}, {"IN": inp})
    hard = tmp_path / "hard.npz"
    os.link(inp, hard)
    with pytest.raises(InputError, match="is the input"):
        F.refuse_overlap({"-o": hard}, {"IN": inp})
    with pytest.raises(InputError, match="contains the input IN"):
        F.refuse_overlap({"-o": tmp_path / "data"}, {"IN": inp})
    F.refuse_overlap({"-o": tmp_path / "data" / "est.npz"}, {"IN": inp, "none": None})  # beside it: fine


def test_check_output_file_replaces_only_heartcv_files(tmp_path):
    ours = tmp_path / "est.npz"
    F.write_npz(ours, FMT, {"times": np.arange(2.0)}, {})
    F.check_output_file(ours)
    yaml_ours = tmp_path / "p.yaml"
    F.write_yaml(yaml_ours, {"format": "heartcv.parameters", "format_version": 1})
    F.check_output_file(yaml_ours)
    (tmp_path / "empty.npz").write_bytes(b"")
    F.check_output_file(tmp_path / "empty.npz")
    F.check_output_file(tmp_path / "new.npz")
    foreign = tmp_path / "notes.yaml"
    foreign.write_text("shopping: [milk]\n")
    with pytest.raises(InputError, match="was not written by heartcv"):
        F.check_output_file(foreign)
    other_npz = tmp_path / "other.npz"
    np.savez(other_npz, a=np.zeros(3))
    with pytest.raises(InputError, match="was not written by heartcv"):
        F.check_output_file(other_npz)
    with pytest.raises(InputError, match="is a folder"):
        F.check_output_file(tmp_path)


# -- YAML ---------------------------------------------------------------------------------------------------------
def test_yaml_alias_bomb_deep_nesting_and_duplicates_are_refused(tmp_path):
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(alias_bomb())
    assert len(bomb.read_bytes()) < 600
    with pytest.raises(InputError, match="with its aliases expanded"):
        F.read_yaml(bomb)
    deep = tmp_path / "deep.yaml"
    deep.write_text("a: " + "[" * 100 + "]" * 100 + "\n")
    with pytest.raises(InputError, match="nested deeper than 32"):
        F.read_yaml(deep)
    deep_maps = tmp_path / "deep2.yaml"
    deep_maps.write_text("".join("  " * i + f"k{i}:\n" for i in range(100)) + "  " * 100 + "v: 1\n")
    with pytest.raises(InputError, match="nested deeper"):
        F.read_yaml(deep_maps)
    dup = tmp_path / "dup.yaml"
    dup.write_text("parameters:\n  E: 1.0\n  E: 2.0\n")
    with pytest.raises(InputError, match="duplicate key 'E'"):
        F.read_yaml(dup)
    ok = "a: &x [1, 2]\nb: *x\nc: *x\n"                      # a few aliases are fine
    assert F.parse_yaml(ok) == {"a": [1, 2], "b": [1, 2], "c": [1, 2]}


@pytest.mark.parametrize("text, message", [
    ("a: 1\n\tb: 2\n", "found character '\\t' that cannot start any token (line 2, column 1)"),
    ("a: 1\na: 2\n", "duplicate key 'a' (line 2, column 1)"),
    ("a: [1, 2\n", "(line 2, column 1)"),
    ("a: !!python/object:os.system x\n", "could not determine a constructor for the tag"),
])
def test_yaml_syntax_errors_are_one_line_with_where(text, message):
    """Before 2026-11-29 the parser's own message came through: 4-6 lines with the source echoed and a caret."""
    with pytest.raises(InputError) as exc:
        F.parse_yaml(text, "x.yaml")
    reason = str(exc.value)
    assert "\n" not in reason and reason.startswith("x.yaml: not valid YAML: ") and message in reason, reason


def test_yaml_numbers_text_and_limits(tmp_path, monkeypatch):
    assert F.parse_yaml("a: 1e-3\nb: -2E+5\nc: 1.5\nd: 7\ne: '1e3'\nf: .inf\ng: 0x10\n") == {
        "a": 1e-3, "b": -2e5, "c": 1.5, "d": 7, "e": "1e3", "f": float("inf"), "g": 16}
    bad = tmp_path / "latin1.yaml"
    bad.write_bytes("name: caf\xe9\n".encode("latin-1"))
    with pytest.raises(InputError, match=r"not UTF-8 text \(byte 9\)"):
        F.read_yaml(bad)
    bom = tmp_path / "bom.yaml"
    bom.write_bytes("\ufeffa: 1\n".encode())
    assert F.read_yaml(bom) == {"a": 1}
    monkeypatch.setitem(F.LIMITS, "yaml_bytes", 4)
    with pytest.raises(InputError, match="at most 4 bytes"):
        F.read_yaml(bom)
    with pytest.raises(InputError, match="no such model file"):
        F.read_yaml(tmp_path / "missing.yaml", "model file")


def test_dump_yaml_round_trips_floats_exactly():
    rng = np.random.default_rng(3)
    x = rng.normal(size=20) * 10.0 ** rng.integers(-12, 12, 20)
    d = {"x": x, "m": rng.normal(size=(3, 3)), "s": "0.1.0", "i": np.int64(4)}
    back = F.parse_yaml(F.dump_yaml(d))
    assert back["x"] == x.tolist() and back["m"] == d["m"].tolist() and back["s"] == "0.1.0" and back["i"] == 4


# -- .npz ---------------------------------------------------------------------------------------------------------
_SCHEMA = {"times": ArraySpec("f", ("K",)), "positions": ArraySpec("f", ("K", "P", 3), finite="nan"),
           "ids": ArraySpec("iu", ("P",)), "opt": ArraySpec("f", ("K",), required=False)}


def _npz(path, arrays, meta=None, raw_members=None):
    meta = {"format": FMT[0], "format_version": FMT[1]} if meta is None else meta
    with zipfile.ZipFile(path, "w") as z:
        for k, v in arrays.items():
            b = io.BytesIO()
            np.save(b, v, allow_pickle=True)
            z.writestr(k + ".npy", b.getvalue())
        b = io.BytesIO()
        np.save(b, np.frombuffer(json.dumps(meta).encode(), np.uint8))
        z.writestr("meta_json.npy", b.getvalue())
        for name, data in (raw_members or {}).items():
            z.writestr(name, data)
    return path


def _good():
    return {"times": np.arange(3.0), "positions": np.zeros((3, 2, 3)), "ids": np.arange(2)}


def test_npz_round_trip_and_fortran_order(tmp_path):
    a = _good()
    a["positions"] = np.asfortranarray(np.random.default_rng(0).normal(size=(3, 2, 3)))
    a["positions"][1, 0] = np.nan
    F.write_npz(tmp_path / "m.npz", FMT, a, {"note": "x"})
    data, meta = F.read_npz(tmp_path / "m.npz", FMT, _SCHEMA)
    np.testing.assert_array_equal(data["positions"], a["positions"])
    assert meta["note"] == "x" and meta["format"] == FMT[0] and "opt" not in data


@pytest.mark.parametrize("edit, match", [
    (lambda a: a.update(times=np.arange(4.0)), "positions: axis 0 has 3 entries, times has 4"),
    (lambda a: a.update(ids=np.arange(3)), "axis 0 has 3 entries"),
    (lambda a: a.update(times=np.array([0, np.nan, 2])), "times: 1 non-finite values"),
    (lambda a: a["positions"].__setitem__((0, 0, 0), np.inf), "positions: 1 infinite values"),
    (lambda a: a.update(positions=np.zeros((3, 2))), r"positions: 3-D \(K, P, 3\) expected"),
    (lambda a: a.update(ids=np.array(["a", "b"])), "ids: dtype <U1 not accepted"),
    (lambda a: a.update(times=np.arange(3.0) + 0j), "times: dtype complex128 not accepted"),
    (lambda a: a.pop("ids"), r"missing arrays \['ids'\]"),
])
def test_npz_schema_violations_name_the_array(tmp_path, edit, match):
    a = _good()
    edit(a)
    _npz(tmp_path / "m.npz", a)
    with pytest.raises(InputError, match=match):
        F.read_npz(tmp_path / "m.npz", FMT, _SCHEMA)


def test_npz_refuses_pickles_corrupt_members_and_bad_metadata(tmp_path):
    a = _good()
    a["times"] = np.array([1.0, "x", None], dtype=object)
    with pytest.raises(InputError, match="times: holds Python objects"):
        F.read_npz(_npz(tmp_path / "pickle.npz", a), FMT, _SCHEMA)
    for meta, match in (([1, 2], "a JSON object expected, got list"), ({"format": "heartcv.truth",
                        "format_version": 1}, "meta.format: 'heartcv.measurements' expected")):
        with pytest.raises(InputError, match=match):
            F.read_npz(_npz(tmp_path / "meta.npz", _good(), meta), FMT, _SCHEMA)
    p = _npz(tmp_path / "nan.npz", _good(), raw_members={})
    raw = p.read_bytes()
    with zipfile.ZipFile(p, "w") as z:  # meta_json holding NaN, which is not JSON
        b = io.BytesIO()
        np.save(b, np.frombuffer(b'{"format": NaN}', np.uint8))
        z.writestr("meta_json.npy", b.getvalue())
    with pytest.raises(InputError, match="corrupt metadata"):
        F.read_npz(p, FMT, _SCHEMA)
    good = tmp_path / "good.npz"
    F.write_npz(good, FMT, {"times": np.arange(1000.0)}, {})
    raw = bytearray(good.read_bytes())
    i = raw.find(b"times.npy") + 200
    raw[i:i + 8] = b"\xff" * 8                                 # damage the compressed data
    (tmp_path / "corrupt.npz").write_bytes(bytes(raw))
    with pytest.raises(InputError):
        F.read_npz(tmp_path / "corrupt.npz", FMT, {"times": ArraySpec("f", ("K",))})
    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(InputError, match="not a readable .npz file"):
        F.read_npz(tmp_path / "text.npz", FMT, _SCHEMA)


def _huge_claim(path, nbytes=1 << 30):
    b = io.BytesIO()
    np.lib.format.write_array_header_1_0(b, {"descr": "<f8", "fortran_order": False, "shape": (nbytes // 8,)})
    return _npz(path, {"positions": np.zeros((1, 1, 3)), "ids": np.arange(1)},
                raw_members={"times.npy": b.getvalue() + b"\0" * 64})


def test_a_1gb_header_claim_is_refused_without_allocating(tmp_path):
    p = _huge_claim(tmp_path / "big.npz")
    assert p.stat().st_size < 2000
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match="header claims 1073741824 bytes but the entry holds"):
            F.read_npz(p, FMT, _SCHEMA)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 10 << 20


def test_too_many_members_and_huge_headers(tmp_path, monkeypatch):
    monkeypatch.setitem(F.LIMITS, "npz_members", 3)
    with pytest.raises(InputError, match="5 entries; at most 3"):
        F.read_npz(_npz(tmp_path / "m.npz", dict(_good(), opt=np.arange(3.0))), FMT, _SCHEMA)
    monkeypatch.setitem(F.LIMITS, "npz_members", 256)
    header = b"\x93NUMPY\x01\x00" + (60000).to_bytes(2, "little") + b" " * 60000
    with pytest.raises(InputError, match="not a valid .npy header"):
        F.read_npz(_npz(tmp_path / "h.npz", {"ids": np.arange(1), "positions": np.zeros((1, 1, 3))},
                        raw_members={"times.npy": header}), FMT, _SCHEMA)


# -- CSV and typed fields -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("text, match", [
    ("", "empty table"),
    ("# only a comment\n", "empty table"),
    ("time_s,p\n0,1\n1\n", r"row 2: 1 values for 2 columns"),
    ("time_s,p\n0,abc\n", r"column 'p': not numeric"),
    ("time_s,p\n0,nan\n", r"column 'p': non-finite value 'nan' in row 1"),
    ("time_s,p\n0,1e400\n", r"column 'p': non-finite value"),
    ("time_s,time_s\n0,1\n", "distinct, non-empty column names"),
    ("time_s,\n0,1\n", "distinct, non-empty column names"),
])
def test_csv_errors_name_column_or_row(tmp_path, text, match):
    p = tmp_path / "inputs.csv"
    p.write_text(text)
    with pytest.raises(InputError, match=match):
        F.read_csv_table(p)


def test_csv_reads_comments_bom_and_string_columns(tmp_path):
    p = tmp_path / "t.csv"
    p.write_bytes("\ufeff# comment\nframe,time_s\nf001,0.0\nf002,0.5\n".encode())
    cols, n = F.read_csv_table(p, numeric_except=("frame",))
    assert n == 2 and cols["frame"] == ["f001", "f002"] and cols["time_s"].tolist() == [0.0, 0.5]


def test_get_field_and_get_matrix():
    d = {"n": 3, "x": "1e-3", "b": True, "s": "hi", "l": ["a", "b"], "nan": float("nan"), "ragged": [[1, 2], [3]]}
    assert F.get_field(d, "n", "int", lo=0, hi=5) == 3
    assert F.get_field(d, "x", "float") == 1e-3
    assert F.get_field(d, "l", "str-list") == ["a", "b"]
    assert F.get_field(d, "missing", "float", default=2.0) == 2.0
    for key, kind, match in (("b", "int", "an integer expected"), ("n", "str", "a str expected"),
                             ("nan", "float", "a finite number expected"), ("missing", "int", "required"),
                             ("s", "float", "a number expected"), ("l", "float-list", "a number expected")):
        with pytest.raises(InputError, match=match) as exc:
            F.get_field(d, key, kind, "f.yaml", prefix="meta.")
        assert exc.value.path == "f.yaml" and exc.value.field.startswith("meta.")
    with pytest.raises(InputError, match=r"outside the valid range \[0, 2\]"):
        F.get_field(d, "n", "int", lo=0, hi=2)
    with pytest.raises(InputError, match="ragged or non-numeric"):
        F.get_matrix(d["ragged"], (2, 2), "f.yaml", "K")
    np.testing.assert_array_equal(F.get_matrix([[1, 2], [3, 4]], (2, None)), [[1, 2], [3, 4]])


# -- the acceptance cases through the command line ------------------------------------------------------------------
def _cli_peak(args):
    runner = CliRunner()
    runner.invoke(main, ["model", "info", "--help"])  # imports done before measuring
    tracemalloc.start()
    try:
        res = runner.invoke(main, args)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return res, peak


def test_cli_refuses_alias_bomb_nested_yaml_and_huge_npy_claim_in_bounded_memory(tmp_path):
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(alias_bomb())
    res, peak = _cli_peak(["model", "info", str(bomb)])
    assert res.exit_code == 2 and str(bomb) in res.output and "aliases expanded" in res.output
    assert len(res.output) < 1000 and peak < 100 << 20
    deep = tmp_path / "deep.yaml"
    deep.write_text("geometry: " + "[" * 100 + "]" * 100 + "\n")
    res, peak = _cli_peak(["model", "info", str(deep)])
    assert res.exit_code == 2 and "nested deeper than 32" in res.output and peak < 100 << 20
    from heartcv.tracker.io import read_measurements

    model = Path(__file__).resolve().parents[2] / "sample_sequences" / "paper_patch.yaml"
    good = tmp_path / "meas.npz"
    res = CliRunner().invoke(main, ["model", "simulate", str(model), "--duration", "0.2", "-o", str(good)])
    assert res.exit_code == 0, res.output
    assert read_measurements(good).n_frames > 1
    big = huge_claim_copy(good, tmp_path / "big.npz")   # times.npy claims 1 GiB
    res, peak = _cli_peak(["track", str(big), "--model", str(model), "-o", str(tmp_path / "est.npz")])
    assert res.exit_code == 2 and "header claims 1073741824 bytes" in res.output and str(big) in res.output
    assert peak < 100 << 20 and not (tmp_path / "est.npz").exists()


def test_input_error_pickles_and_two_outputs_need_two_paths(tmp_path):
    import pickle

    e = pickle.loads(pickle.dumps(InputError("f.yaml", "bad", "x")))
    assert (e.path, e.reason, e.field, str(e)) == ("f.yaml", "bad", "x", "f.yaml: x: bad")
    with pytest.raises(InputError, match="is also the output -o"):
        F.refuse_overlap({"-o": tmp_path / "a.npz", "--truth": tmp_path / "." / "a.npz"}, {})
    F.write_npz(tmp_path / "m.npz", FMT, {"times": np.arange(2.0)}, {"x": 1})
    assert F.read_npz_meta(tmp_path / "m.npz")["x"] == 1


def test_a_header_numpy_cannot_tokenize_is_an_input_error(tmp_path):
    """Found by the fuzz run (NUL bytes inside an .npy header): numpy's header parser raised tokenize.TokenError."""
    hdr = b"{'descr': '<f8', 'fortran_order': False, 'shape': (3,\x00\x00\n"
    raw = b"\x93NUMPY\x01\x00" + len(hdr).to_bytes(2, "little") + hdr + b"\0" * 24
    p = _npz(tmp_path / "tok.npz", {"positions": np.zeros((3, 1, 3)), "ids": np.arange(1)},
             raw_members={"times.npy": raw})
    with pytest.raises(InputError, match="times: not a valid .npy header"):
        F.read_npz(p, FMT, _SCHEMA)
