"""The file-handling foundation of heartcv: one implementation for both packages and the command line.

Everything that touches a file goes through here (``heartcv.io`` and ``heartcv.tracker.io`` build their typed
readers and writers on it; ``heartcv.cli`` calls it for output safety). It depends on nothing in ``heartcv/`` or
``cli/`` (docs/design.md §2), so ``heartcv.tracker`` stays usable on its own.

- :class:`InputError` — the one error type for input that failed validation; it carries the file and the field.
  The command line turns it into exit 2; nothing else is ever reported as bad input (docs/cli.md, exit codes).
- Writes are atomic (:func:`atomic_path`, :func:`atomic_folder`): a temporary file or folder beside the
  destination, renamed over it only when complete. Unwritable destinations raise :class:`InputError`.
- Output safety (:func:`refuse_overlap`, :func:`check_output_file`, :func:`check_output_folder`): an output that
  equals or contains an input is refused, and a stage replaces only a file or folder that heartcv wrote.
- Safe YAML (:func:`read_yaml`): size, nesting-depth, alias and expanded-size limits, duplicate keys refused, UTF-8
  only, numbers such as ``1e-3`` read as floats (YAML 1.1 reads them as strings).
- Safe ``.npz`` (:func:`read_npz`): no pickles, limits on members, ``.npy`` headers and array sizes (checked from the
  headers before any array is allocated), and every array's dtype, shape and finiteness validated against a
  schema (:class:`ArraySpec`) with named dimensions shared between arrays.
- Typed getters for metadata and YAML fields (:func:`get_field`) that name the field when they refuse a value.

Limits are module constants (:data:`LIMITS`), documented in docs/formats.md §1.10.
"""

from __future__ import annotations

import contextlib
import contextvars
from dataclasses import dataclass
import errno
import hashlib
import io
import json
import math
import os
from pathlib import Path
import re
import secrets
import shutil
import tempfile
import tokenize
import zipfile
import zlib

import numpy as np

__all__ = [
    "InputError", "LIMITS", "file_hash", "atomic_path", "atomic_folder", "output_group", "written_at_once",
    "remove_output", "outputs_committed", "after_outputs", "MANIFEST_NAME", "read_manifest",
    "refuse_overlap", "check_output_file", "check_output_folder", "is_heartcv_file", "heartcv_format",
    "check_output_name", "file_kind", "NAME_MAX", "ConcurrentWrite",
    "HAND_WRITTEN_FORMATS", "read_text", "read_yaml",
    "parse_yaml", "dump_yaml", "write_yaml", "plain", "check_format", "get_field", "ArraySpec", "read_npz",
    "read_npz_meta", "check_provenance", "show",
    "write_npz", "read_csv_table", "get_matrix", "software_versions",
]

LIMITS = {
    "yaml_bytes": 4 << 20,          # a YAML file (model, rig, target, scene, parameters)
    "yaml_nodes_read": 50_000,      # nodes in the text of one document (PyYAML composes ~40 000 per second)
    "yaml_depth": 32,               # nesting of mappings and sequences
    "yaml_aliases": 256,            # alias nodes (*name) in one document
    "yaml_nodes": 2_000_000,        # nodes of the document with every alias expanded
    "text_bytes": 256 << 20,        # a CSV table
    "json_bytes": 64 << 20,         # the metadata of an .npz file
    "npz_members": 256,             # arrays in one .npz file
    "npy_header_bytes": 10_000,     # one .npy header (numpy's own default)
    "array_bytes": 8 << 30,         # one array, uncompressed
}


# =====================================================================================================================
# The error type
# =====================================================================================================================
class InputError(ValueError):
    """Input that failed validation. ``path`` names the file (None for a value not read from a file, e.g. an
    option), ``field`` the key, array, column or option inside it (None for the file as a whole).

    The message reads ``<path>: <field>: <reason>``; :meth:`in_file` attaches a file to an error raised by code
    that validated a mapping without knowing where it came from.
    """

    def __init__(self, path, reason: str, field: str | None = None):
        self.path = None if path is None else str(path)
        self.field = None if field is None else str(field)
        self.reason = str(reason)
        super().__init__(": ".join(p for p in (self.path, self.field, self.reason) if p))

    def __reduce__(self):  # picklable: raised in worker processes (heartcv simulate --workers)
        return type(self), (self.path, self.reason, self.field)

    def in_file(self, path) -> InputError:
        """The same error naming ``path`` (unchanged if it already names a file)."""
        if self.path is not None:
            return self
        err = InputError(path, self.reason, self.field)
        err.__cause__ = self.__cause__
        return err


def _unwritable(path, exc: OSError) -> InputError:
    return InputError(path, f"cannot write here ({exc.strerror or exc})", "output")


def _check_writable_parent(path, label: str) -> None:
    """Exit 2 before any work where the nearest existing folder above ``path`` cannot be written into (the
    output's temporary file and its rename need it)."""
    parent = Path(path).parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if parent.is_dir() and not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(path, f"cannot write here (no permission to write into {parent})", label)


# =====================================================================================================================
# Hashes and atomic writes
# =====================================================================================================================
def file_hash(path) -> str:
    """``sha256:<hex>`` of a file's bytes (of a file the running stage wrote and has not yet put in place, the
    bytes it will put there: :func:`output_group`)."""
    path = _pending_source(path)
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc.strerror or exc})") from None
    return "sha256:" + h.hexdigest()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _hidden(name: str, tag: str, tail: int) -> str:
    """The prefix ``.<name><tag>`` of a hidden temporary name beside ``name``, the name cut short so that the
    prefix and ``tail`` more bytes (the random part, a suffix) stay within :data:`NAME_MAX` bytes: an output
    name of up to 255 bytes can be written."""
    room = NAME_MAX - tail - len(os.fsencode(tag)) - 1
    raw = os.fsencode(name)
    if len(raw) > room:
        name = raw[:max(room, 1)].decode("utf-8", "ignore") or "x"
    return f".{name}{tag}"


# outputs of the running stage put in place together at its end (output_group); None outside one
_GROUP: contextvars.ContextVar = contextvars.ContextVar("heartcv_output_group", default=None)


class _PendingFile:
    """A finished temporary file waiting to be renamed over its destination (:func:`output_group`)."""

    def __init__(self, tmp: Path, path: Path):
        self.tmp, self.path, self.backup, self.existed = tmp, path, None, False

    keep_backup = True     # outside a group nothing is undone: no second name needed

    def commit(self) -> None:
        self.existed = os.path.lexists(self.path)
        if self.existed:    # a file replaced keeps its permissions (a person's chmod o-r survives a rerun)
            with contextlib.suppress(OSError):
                os.chmod(self.tmp, os.stat(self.path).st_mode & 0o7777)
        if self.existed and self.keep_backup:
            # a second name for the file being replaced, so that a later failure can put it back
            backup = self.path.parent / (_hidden(self.path.name, ".old-", 12) + secrets.token_hex(6))
            with contextlib.suppress(OSError):   # (a file system without hard links: no way back, as without a group)
                os.link(self.path, backup)
                self.backup = backup
        os.replace(self.tmp, self.path)

    def rollback(self) -> None:
        if self.backup is not None:
            os.replace(self.backup, self.path)
            self.backup = None
        elif not self.existed:
            os.unlink(self.path)

    def finish(self) -> None:
        if self.backup is not None:
            with contextlib.suppress(OSError):
                os.unlink(self.backup)

    def discard(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.tmp)


def _pending_source(path):
    """The temporary file holding what the running stage will put at ``path``; ``path`` when none is pending."""
    group = _GROUP.get()
    if group:
        target = os.path.abspath(path)
        for item in group:
            if isinstance(item, _PendingFile) and os.path.abspath(item.path) == target:
                return item.tmp
    return path


class _PendingRemoval:
    """An output of an earlier run that this run removes (a Kalibr camchain the new rig cannot be written as),
    removed with the renames (:func:`remove_output`)."""

    def __init__(self, path: Path):
        self.path, self.backup = path, None

    def commit(self) -> None:
        if os.path.lexists(self.path):
            backup = self.path.parent / (_hidden(self.path.name, ".old-", 12) + secrets.token_hex(6))
            os.replace(self.path, backup)
            self.backup = backup

    def rollback(self) -> None:
        if self.backup is not None:
            os.replace(self.backup, self.path)
            self.backup = None

    def finish(self) -> None:
        if self.backup is not None:
            with contextlib.suppress(OSError):
                os.unlink(self.backup)

    def discard(self) -> None:
        pass


def remove_output(path) -> None:
    """Remove an earlier run's output that this run does not write again; inside an :func:`output_group`, with
    the renames (an interrupted or failed stage keeps it, as it keeps every other earlier output)."""
    _place(_PendingRemoval(Path(path)))


class _Announcement:
    """What a stage says it wrote (its "wrote ..." line, its ``--json`` summary), said once its outputs are in
    place (:func:`after_outputs`): a rename that fails never follows a line saying the file was written."""

    def __init__(self, say):
        self.say = say

    def commit(self) -> None:
        pass

    rollback = finish = discard = commit


def after_outputs(say) -> None:
    """Call ``say()`` (a stage's summary: its log line, its ``--json`` document) when the running
    :func:`output_group` has put every output in place; at once outside a group. Nothing is said when the
    group's block fails or a rename does."""
    group = _GROUP.get()
    if group is None:
        say()
    else:
        group.append(_Announcement(say))


def _place(item) -> None:
    """Put a finished output (or a removal) in place: inside an :func:`output_group` with the group's renames,
    else now, with signals held (a replaced file then keeps no backup: there is nothing to undo it with)."""
    group = _GROUP.get()
    if group is not None:
        group.append(item)
        return
    if isinstance(item, _PendingFile):
        item.keep_backup = False
    with _signals_held():
        try:
            item.commit()
        except BaseException:
            item.discard()
            raise
        item.finish()


_COMMITTED: contextvars.ContextVar = contextvars.ContextVar("heartcv_outputs_committed", default=False)


def outputs_committed() -> bool:
    """Whether the last :func:`output_group` of this context put its outputs in place (for the message of a stage
    interrupted after that: its outputs are complete, not the earlier ones)."""
    return _COMMITTED.get()


@contextlib.contextmanager
def _signals_held():
    """SIGINT and SIGTERM held back while the block runs (the renames of a stage's outputs and their undoing),
    then delivered to the handlers they had: a Ctrl-C never leaves a replaced folder hidden under its ``.old-``
    name, or one output new and another old. The handlers are swapped (a signal mask would hold them in this
    thread only, and the interpreter runs its handlers for a signal any thread receives); main thread only."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list = []
    before = {sig: signal.signal(sig, lambda signum, frame: caught.append(signum))
              for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        for sig in dict.fromkeys(caught):       # each once, in the order they came
            handler = before[sig]
            if callable(handler):
                handler(sig, None)              # Python's KeyboardInterrupt, the command line's Terminated
            elif handler == signal.SIG_DFL:
                os.kill(os.getpid(), sig)


@contextlib.contextmanager
def output_group():
    """Put every output that :func:`atomic_path` and :func:`atomic_folder` write inside the block in place together,
    when the block ends without an exception.

    A stage with several outputs (a measurement file, its CSV and its overlay; a rig, its COLMAP folder and its
    report) writes each to a temporary file or folder as before, but renames none until all are complete: a stage
    that fails or is interrupted half-way leaves every earlier output as it was, not a new measurement file beside
    last run's CSV. Should one of the final renames fail, those already done are undone (a replaced file is put
    back from a hard link kept for the purpose; a replaced folder from where it was moved). Inside an
    :func:`atomic_folder` block, files written into its temporary folder are renamed at once (the folder is the
    unit). Nested groups join the outer one. The command line runs every stage in one group.
    """
    if _GROUP.get() is not None:
        yield
        return
    pending: list = []
    token = _GROUP.set(pending)
    _COMMITTED.set(False)
    try:
        yield
    except BaseException:
        _GROUP.reset(token)
        with _signals_held():
            for item in pending:
                item.discard()
        raise
    _GROUP.reset(token)
    with _signals_held():       # a Ctrl-C now waits until every output is in place, or every one undone
        done = []
        try:
            for item in pending:      # (signals held: nothing lands between a rename and its record)
                item.commit()
                done.append(item)
        except BaseException:
            for item in reversed(done):
                with contextlib.suppress(OSError):
                    item.rollback()
            for item in pending[len(done):]:
                item.discard()
            raise
        for item in done:
            item.finish()
        _COMMITTED.set(True)
    for item in pending:       # the stage's summary, now true (signals no longer held: a Ctrl-C here is reported
        if isinstance(item, _Announcement):     # as coming after the outputs were put in place)
            item.say()


@contextlib.contextmanager
def written_at_once():
    """Inside an :func:`output_group`, a block whose outputs go in place as soon as each is complete: what a
    failing stage writes to show what it did (a diverged ``track``'s partial file) before it exits 1."""
    token = _GROUP.set(None)
    try:
        yield
    finally:
        _GROUP.reset(token)


@contextlib.contextmanager
def atomic_path(path, suffix=None):
    """Yield a temporary path beside ``path``; rename it over ``path`` only if the block succeeds (inside an
    :func:`output_group`, when the group's block does).

    The temporary name is ``.<name>.<random><suffix>`` (hidden, so folder listings skip it); missing parent
    folders are created; the final file gets the ordinary permissions of the umask, or the permissions of the file
    it replaces. A destination that cannot be
    written (a parent that is a file, no permission, read-only file system) raises :class:`InputError` naming it
    before anything is computed into the temporary file.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        suffix = suffix or path.suffix or ".tmp"
        fd, tmp = tempfile.mkstemp(prefix=_hidden(path.name, ".", 8 + len(os.fsencode(suffix))), suffix=suffix,
                                   dir=path.parent)
        os.close(fd)
    except OSError as exc:
        raise _unwritable(path, exc) from None
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    _place(_PendingFile(Path(tmp), path))


MANIFEST_NAME = "heartcv-manifest.json"


def read_manifest(folder) -> dict | None:
    """The manifest a stage wrote into its output folder (``producer``, ``format``, ``heartcv_version``), or None
    when the folder holds none or an unreadable one."""
    p = Path(folder) / MANIFEST_NAME
    try:
        if not p.is_file() or p.stat().st_size > (1 << 20):
            return None
        d = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError):
        return None
    return d if isinstance(d, dict) else None


class ConcurrentWrite(Exception):
    """Another process wrote the same output folder while this one replaced it (the check and the renames are not
    one atomic step): nothing of this run was put in place; the folder holds the other run's output."""

    def __init__(self, path):
        super().__init__(f"{path}: another run wrote this output folder at the same time; this run's output was "
                         "not put in place (run again, one at a time)")
        self.path = path


@contextlib.contextmanager
def atomic_folder(path, producer: str, manifest: dict | None = None):
    """Yield a hidden temporary folder beside ``path``; only if the block succeeds is it renamed to ``path``.

    The folder receives a manifest (:data:`MANIFEST_NAME`: ``producer``, ``heartcv_version``, ``manifest``'s
    keys and ``files``, every file the block wrote). An existing ``path`` is replaced only if it is a folder whose
    manifest names the same ``producer`` (a previous run of the same stage) and that holds no file beyond those
    its manifest lists (one a person added); anything else raises :class:`InputError` before the block runs, so a
    stage never deletes a folder it did not write. On failure the temporary folder is removed.
    """
    from . import __version__

    path = Path(path)
    check_output_folder(path, producer)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=_hidden(path.name, ".tmp-", 8), dir=path.parent))
    except OSError as exc:
        raise _unwritable(path, exc) from None
    token = _GROUP.set(None)     # files written into the temporary folder go in at once: the folder is the unit
    try:
        yield tmp
        info = {"producer": producer, "heartcv_version": __version__}
        info.update(manifest or {})
        files = sorted(q for q in tmp.rglob("*") if not q.is_dir())
        info["files"] = [q.relative_to(tmp).as_posix() for q in files]
        info["folders"] = sorted(q.relative_to(tmp).as_posix() for q in tmp.rglob("*") if q.is_dir())
        # size and modification time of each: a file a person edited since is not replaced (a rename keeps both)
        info["stat"] = {q.relative_to(tmp).as_posix(): [q.lstat().st_size, q.lstat().st_mtime_ns] for q in files}
        (tmp / MANIFEST_NAME).write_text(json.dumps(plain(info), indent=1, sort_keys=True) + "\n", encoding="utf-8")
        os.chmod(tmp, 0o777 & ~_umask())
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        _GROUP.reset(token)
    _place(_PendingFolder(tmp, path, producer))


class _PendingFolder:
    """A finished temporary folder waiting to replace its destination (:func:`atomic_folder`)."""

    def __init__(self, tmp: Path, path: Path, producer: str):
        self.tmp, self.path, self.producer, self.old = tmp, path, producer, None

    def commit(self) -> None:
        try:
            if self.path.exists():
                # still ours (checked again: the stage may have run long)
                check_output_folder(self.path, self.producer)
                old = Path(tempfile.mkdtemp(prefix=_hidden(self.path.name, ".old-", 8), dir=self.path.parent))
                os.rmdir(old)
                os.replace(self.path, old)
                self.old = old
            os.replace(self.tmp, self.path)
        except OSError as exc:
            if self.old is not None:    # the previous output back where it was, unless another run's is there now
                with contextlib.suppress(OSError):
                    os.replace(self.old, self.path)
                    self.old = None
                self.finish()
            if exc.errno in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOENT):   # another run renamed in between
                raise ConcurrentWrite(self.path) from None
            raise

    def rollback(self) -> None:
        aside = Path(tempfile.mkdtemp(prefix=_hidden(self.path.name, ".failed-", 8), dir=self.path.parent))
        os.rmdir(aside)
        os.replace(self.path, aside)
        if self.old is not None:
            os.replace(self.old, self.path)
            self.old = None
        shutil.rmtree(aside, ignore_errors=True)

    def finish(self) -> None:
        if self.old is not None:
            shutil.rmtree(self.old, onerror=lambda *_: None)
            if self.old.exists():
                import logging

                logging.getLogger(__name__).warning("%s: the replaced folder could not be removed entirely (%s "
                                                    "left; permissions?)", self.path, self.old)

    def discard(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)


# =====================================================================================================================
# Output safety
# =====================================================================================================================
def _resolved(p) -> Path:
    # realpath resolves each symlink before the '..' after it (abspath first would drop 'lnk/..' by its text and
    # name another file than the one the system opens)
    return Path(os.path.realpath(os.path.expanduser(str(p))))


def refuse_overlap(outputs: dict, inputs: dict) -> None:
    """Refuse outputs that equal or contain an input, before any work.

    Parameters
    ----------
    outputs, inputs : dict of {label: path or None}
        Labels name the option or argument (``"-o/--output"``, ``"MEASUREMENTS"``, ``"--model"``); None entries are
        skipped. An output equals an input when both name the same file (links resolved, or the same inode); it
        contains an input when the input lies inside the output (a folder the stage would replace).

    Raises
    ------
    InputError
        Naming both paths and both labels.
    """
    ins = [(label, Path(p), _resolved(p)) for label, p in inputs.items() if p is not None]
    outs = [(label, op) for label, op in outputs.items() if op is not None]
    for i, (olabel, op) in enumerate(outs):
        for other_label, other in outs[:i]:
            if _resolved(op) == _resolved(other):
                raise InputError(op, f"is also the output {other_label}; two outputs need two paths", olabel)
            for (la, a), (lb, b) in (((olabel, op), (other_label, other)), ((other_label, other), (olabel, op))):
                if _resolved(a).is_relative_to(_resolved(b)):
                    raise InputError(a, f"lies inside the output {lb} ({b}), which the stage writes as a whole; "
                                        "choose a path outside it", la)
    for olabel, op in outputs.items():
        if op is None:
            continue
        ro = _resolved(op)
        for ilabel, ip, ri in ins:
            same = ri == ro
            if not same and ro.exists() and ri.exists():
                with contextlib.suppress(OSError):
                    same = os.path.samefile(ro, ri)
            if same:
                raise InputError(op, f"is the input {ilabel} ({ip}); choose another output path", olabel)
            if ri.is_relative_to(ro):
                raise InputError(op, f"contains the input {ilabel} ({ip}); the stage would replace it; choose "
                                     "another output path", olabel)


_PNG_SOFTWARE = re.compile(rb"tEXtSoftware\x00heartcv")


# heartcv formats that people write and no stage does: such a file is never replaced by an output
HAND_WRITTEN_FORMATS = ("heartcv.model", "heartcv.scene")
_YAML_FORMAT = re.compile(rb"(?m)^format:\s*['\"]?(heartcv\.[A-Za-z0-9_.]+)")


def heartcv_format(path) -> str | None:
    """The ``format`` of an existing heartcv YAML or ``.npz`` file (``heartcv.rig``, ...); None for any other file
    or one that cannot be read."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16)
    except OSError:
        return None
    if head.startswith(b"PK"):
        with contextlib.suppress(InputError):
            fmt = str(_npz_meta_only(path).get("format", ""))
            return fmt if fmt.startswith("heartcv.") else None
        return None
    if path.suffix.lower() in (".yaml", ".yml"):
        m = _YAML_FORMAT.search(head)
        return m.group(1).decode("ascii") if m else None
    return None


def is_heartcv_file(path) -> bool:
    """Whether an existing file was written by heartcv (and so may be replaced by a later run of a stage).

    Recognised: YAML and ``.npz`` files whose ``format`` starts with ``heartcv.``, except the formats people
    write (:data:`HAND_WRITTEN_FORMATS`: model and scene files); text files (CSV, Markdown, HTML, COLMAP/Kalibr
    exports) whose first line carries ``heartcv``; PNG files with the ``Software: heartcv`` text chunk and PDF
    files whose creator is heartcv (both as written by heartcv); empty files (a previous run that was interrupted
    while creating it).
    """
    path = Path(path)
    if heartcv_format(path) in HAND_WRITTEN_FORMATS:
        return False
    try:
        size = path.stat().st_size
        if size == 0:
            return True
        with open(path, "rb") as f:
            head = f.read(1 << 16)
    except OSError:
        return False
    suffix = path.suffix.lower()
    if head.startswith(b"PK"):
        with contextlib.suppress(InputError):
            meta = _npz_meta_only(path)
            return str(meta.get("format", "")).startswith("heartcv.")
        return False
    if head.startswith(b"\x89PNG"):
        return bool(_PNG_SOFTWARE.search(head))
    if head.startswith(b"%PDF"):
        with open(path, "rb") as f:
            return b"heartcv" in f.read(min(size, 4 << 20))
    first = head.split(b"\n", 1)[0]
    if b"heartcv" in first:
        return True
    if suffix in (".yaml", ".yml"):
        return bool(re.search(rb"(?m)^format:\s*['\"]?heartcv\.", head))
    return False


NAME_MAX = 255
"""Longest file name (bytes) the usual file systems take."""


def file_kind(path, fmt: str | None = None) -> str:
    """What an existing file holds, for :func:`check_output_file`'s ``kinds``: its heartcv ``format``
    (:func:`heartcv_format`), else ``png`` or ``pdf`` by its first bytes, else its suffix without the dot (``csv``,
    ``yaml``, ``md``; ``""`` without one)."""
    fmt = heartcv_format(path) if fmt is None else fmt
    if fmt:
        return fmt
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError:
        head = b""
    if head.startswith(b"\x89PNG"):
        return "png"
    if head.startswith(b"%PDF"):
        return "pdf"
    return Path(path).suffix.lower().lstrip(".")


def check_output_name(path, label: str = "-o/--output", folder: bool = False) -> None:
    """Refuse, before any work, an output path the system cannot create as a file (``folder``: as a folder): an
    empty name, one ending in a path separator (a file's), a name longer than :data:`NAME_MAX` bytes."""
    text = os.fspath(path)
    if not str(text).strip():
        raise InputError(None, f"an empty path; a {'folder' if folder else 'file'} path expected", label)
    if not folder and str(text).endswith((os.sep, "/")):
        raise InputError(text, "ends with a path separator (a folder); a file path expected", label)
    for part in Path(text).parts:
        if len(os.fsencode(part)) > NAME_MAX:
            raise InputError(text, f"a name of {len(os.fsencode(part))} bytes; at most {NAME_MAX} expected", label)


def check_output_file(path, label: str = "-o/--output", kinds=None) -> None:
    """Refuse an output file path that holds something heartcv did not write (:func:`is_heartcv_file`), a heartcv
    file of another kind than ``kinds`` (the formats the stage writes there, e.g. ``("heartcv.rig",)``, or the
    :func:`file_kind` of a text or image output, ``("csv",)``: a fit does not replace a rig, a CSV export not a
    parameters file), a folder, a device, FIFO or socket (opened, not replaced), a symbolic link (the link is the
    user's) and a file the user may not write; a missing file, or one that a stage of that kind wrote before, may
    be (re)written."""
    import stat

    check_output_name(path, label)
    path = Path(path)
    try:
        st = os.lstat(path)
    except (FileNotFoundError, NotADirectoryError):     # (a parent that is a file: named below)
        st = None
    except OSError as exc:
        raise InputError(path, f"cannot be examined ({exc.strerror or exc})", label) from None
    if st is not None and stat.S_ISLNK(st.st_mode):
        raise InputError(path, f"is a symbolic link (to {os.readlink(path)}); not replaced: give the path it points "
                               "to, or another path", label)
    if st is not None and stat.S_ISDIR(st.st_mode):
        raise InputError(path, "is a folder; a file path expected", label)
    if st is not None and not stat.S_ISREG(st.st_mode):
        raise InputError(path, "is not a regular file (a device, a FIFO or a socket); not replaced (choose a file "
                               "path)", label)
    if st is not None:
        if not os.access(path, os.W_OK):
            raise InputError(path, "is read-only; not replaced (make it writable, or choose another path)", label)
        fmt = heartcv_format(path)
        if fmt in HAND_WRITTEN_FORMATS:
            raise InputError(path, f"exists and is a {fmt} file (written by a person, not by a stage); not "
                                   "replaced (choose another path)", label)
        if not is_heartcv_file(path):
            raise InputError(path, "exists and was not written by heartcv; not replaced (remove it or choose "
                                   "another path)", label)
        kind = file_kind(path, fmt) if kinds is not None and path.stat().st_size else None
        if kind is not None and kind not in kinds:
            raise InputError(path, f"exists and holds a {kind or 'suffix-less'} file, not a {' or '.join(kinds)} "
                                   "file as this output; not replaced (remove it or choose another path)", label)
    if path.parent.exists() and not path.parent.is_dir():
        raise InputError(path, f"{path.parent} is not a folder", label)
    _check_writable_parent(path, label)


def check_output_folder(path, producer: str, label: str = "-o/--output") -> None:
    """Refuse an output folder that exists and was not written by ``producer`` (its manifest, :func:`atomic_folder`).
    """
    check_output_name(path, label, folder=True)
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        if path.parent.exists() and not path.parent.is_dir():
            raise InputError(path, f"{path.parent} is not a folder", label)
        _check_writable_parent(path, label)
        return
    if path.is_symlink():
        raise InputError(path, f"is a symbolic link (to {os.readlink(path)}); not replaced (the link is yours): give "
                               "the path it points to, or another path", label)
    if not path.is_dir():
        raise InputError(path, "exists and is not a folder; not replaced", label)
    man = read_manifest(path)
    if man is None or man.get("producer") != producer:
        what = "holds no heartcv manifest" if man is None else f"was written by {man.get('producer')!r}"
        raise InputError(path, f"exists and {what}: {producer} replaces only a folder it wrote itself; remove it "
                               "or choose another path", label)
    if not isinstance(man.get("files"), list):
        # written before manifests listed their files (heartcv before 2026-11-29): its files cannot be told from
        # ones a person added, and replacing the folder would delete those
        raise InputError(path, f"was written by an older {producer} whose manifest does not list its files, so files "
                               "added to it since cannot be told apart and would be deleted on replacing it: remove "
                               "the folder or choose another path", label)
    # the manifest lists its files (checked above): anything else in the folder is a person's
    wrote = {str(f) for f in man["files"]} | {MANIFEST_NAME}
    parents = {p.as_posix() for f in wrote for p in Path(f).parents} | {str(d) for d in man.get("folders") or []}
    added = []
    for q in path.rglob("*"):
        rel = q.relative_to(path).as_posix()
        if q.is_symlink() or not q.is_dir():
            if rel not in wrote or q.is_symlink():      # a file, or a link, a person put there
                added.append(rel)
        elif rel not in parents:                        # a folder the run did not make (empty, or a person's)
            added.append(rel + "/")
    added = sorted(a for a in added if not (a.endswith("/") and any(o != a and o.startswith(a) for o in added)))
    if added:
        shown = ", ".join(added[:5]) + (f" and {len(added) - 5} more" if len(added) > 5 else "")
        raise InputError(path, f"holds files {producer} did not write ({shown}); it would delete them on "
                               "replacing the folder: move them out or choose another path", label)
    stats = man.get("stat")
    if isinstance(stats, dict):
        changed = sorted(f for f, v in stats.items() if isinstance(v, list) and len(v) == 2
                         and (path / f).is_file() and [(path / f).lstat().st_size,
                                                      (path / f).lstat().st_mtime_ns] != v)
        if changed:
            shown = ", ".join(changed[:5]) + (f" and {len(changed) - 5} more" if len(changed) > 5 else "")
            raise InputError(path, f"holds files changed since {producer} wrote them ({shown}); it would lose "
                                   "the changes on replacing the folder: move them out or choose another path",
                             label)
    _check_writable_parent(path, label)


# =====================================================================================================================
# Text and YAML
# =====================================================================================================================
def read_text(path, what: str = "text file", max_bytes: int | None = None) -> str:
    """A UTF-8 text file (a leading BOM is dropped); InputError for a missing, oversized, unreadable or non-UTF-8
    file."""
    path = Path(path)
    max_bytes = LIMITS["text_bytes"] if max_bytes is None else max_bytes
    if not path.is_file():
        raise InputError(path, f"no such {what}" if not path.exists() else f"not a file ({what} expected)")
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise InputError(path, f"{size} bytes; a {what} of at most {max_bytes} bytes expected")
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(path, f"cannot read {what} ({exc.strerror or exc})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(path, f"not UTF-8 text (byte {exc.start}); a {what} must be UTF-8") from None
    return text[1:] if text.startswith("\ufeff") else text


_FLOAT_RE = re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                          |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                          |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                          |[-+]?\.(?:inf|Inf|INF)
                          |\.(?:nan|NaN|NAN))$""", re.X)


def _loader_class():
    import yaml

    class Loader(yaml.SafeLoader):
        """SafeLoader with limits (depth, aliases, expanded size), duplicate keys refused and YAML 1.2 floats."""

        def __init__(self, stream):
            super().__init__(stream)
            self._depth = 0
            self._aliases = 0
            self._nodes = 0

        def compose_node(self, parent, index):
            if self.check_event(yaml.AliasEvent):
                self._aliases += 1
                if self._aliases > LIMITS["yaml_aliases"]:
                    raise _Limit(f"more than {LIMITS['yaml_aliases']} aliases")
                return super().compose_node(parent, index)
            self._depth += 1
            self._nodes += 1
            if self._nodes > LIMITS["yaml_nodes_read"]:
                raise _Limit(f"more than {LIMITS['yaml_nodes_read']} nodes long")
            if self._depth > LIMITS["yaml_depth"]:
                raise _Limit(f"nested deeper than {LIMITS['yaml_depth']} levels")
            try:
                return super().compose_node(parent, index)
            finally:
                self._depth -= 1

        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                self.flatten_mapping(node)
                seen = set()
                for key_node, _ in node.value:
                    key = self.construct_object(key_node, deep=True)
                    try:
                        hash(key)
                    except TypeError:
                        raise yaml.constructor.ConstructorError(
                            None, None, "a mapping key must be a scalar", key_node.start_mark) from None
                    if key in seen:
                        raise yaml.constructor.ConstructorError(
                            None, None, f"duplicate key {key!r}", key_node.start_mark)
                    seen.add(key)
            return super().construct_mapping(node, deep)

    Loader.yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
    for ch in "-+0123456789.":
        Loader.yaml_implicit_resolvers[ch] = [r for r in Loader.yaml_implicit_resolvers.get(ch, [])
                                              if r[0] != "tag:yaml.org,2002:float"]
    Loader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_RE, list("-+0123456789."))
    return Loader


class _Limit(Exception):
    pass


def _expanded_size(node, limit: int) -> int:
    """Node count of a composed YAML tree with aliases expanded (shared sub-trees counted once per use)."""
    import yaml

    memo: dict[int, int] = {}

    def count(n, depth=0):
        key = id(n)
        if key in memo:
            return memo[key]
        c = 1
        if isinstance(n, yaml.SequenceNode):
            c += sum(count(v) for v in n.value)
        elif isinstance(n, yaml.MappingNode):
            c += sum(count(k) + count(v) for k, v in n.value)
        memo[key] = min(c, limit + 1)
        return memo[key]

    return count(node)


def _yaml_problem(exc) -> str:
    """A YAML parser's error on one line: its problem and where (``line L, column C``), without the echoed source
    lines and caret the parser adds."""
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    parts = [str(p) for p in (getattr(exc, "context", None), getattr(exc, "problem", None)) if p]
    text = "; ".join(parts) if parts else " ".join(str(exc).split())
    where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
    return (text + where)[:400]


def parse_yaml(text: str, path=None):
    """Parse YAML text with the limits of :data:`LIMITS`; InputError naming ``path`` for invalid YAML, duplicate keys,
    or a document past a limit (alias bombs, deep nesting)."""
    import yaml

    try:
        loader = _loader_class()(text)   # the reader refuses non-printable characters here
    except yaml.YAMLError as exc:
        raise InputError(path, f"not valid YAML: {_yaml_problem(exc)}") from None
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        if _expanded_size(node, LIMITS["yaml_nodes"]) > LIMITS["yaml_nodes"]:
            raise _Limit(f"more than {LIMITS['yaml_nodes']} nodes with its aliases expanded")
        return loader.construct_document(node)
    except _Limit as exc:
        raise InputError(path, f"refused: the YAML document is {exc}") from None
    except yaml.YAMLError as exc:
        raise InputError(path, f"not valid YAML: {_yaml_problem(exc)}") from None
    except RecursionError:
        raise InputError(path, "refused: the YAML document is nested too deeply") from None
    except ValueError as exc:  # construction of a scalar: an integer of more than 4300 digits (Python's limit)
        raise InputError(path, f"not a valid YAML value: {str(exc)[:200]}") from None
    finally:
        loader.dispose()


def read_yaml(path, what: str = "YAML file"):
    """Read and parse a YAML file (:func:`read_text`, :func:`parse_yaml`)."""
    return parse_yaml(read_text(path, what, LIMITS["yaml_bytes"]), path)


def plain(obj):
    """numpy scalars/arrays, tuples and paths -> plain Python (YAML- and JSON-safe) values."""
    if isinstance(obj, dict):
        return {str(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return plain(obj.tolist())
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, Path):
        return str(obj)
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    raise TypeError(f"not representable in YAML or JSON: {type(obj).__name__}")


def _yaml_dumper():
    import yaml

    class Dumper(yaml.SafeDumper):
        # OpenCV's YAML parser (cv2.FileStorage) needs sequences inside mappings to be indented
        def increase_indent(self, flow=False, indentless=False):
            return super().increase_indent(flow, False)

        # ... and reads no scalar folded onto a second line (a long warning, a method in words): never split one
        def write_plain(self, text, split=True):
            return super().write_plain(text, False)

        def write_single_quoted(self, text, split=True):
            return super().write_single_quoted(text, False)

        def write_double_quoted(self, text, split=True):
            return super().write_double_quoted(text, False)

    def represent_str(dumper, s):
        # cv2.FileStorage misreads plain scalars that start like a number ('0.1.0') or hold a colon or a hash
        # ('sha256:0a1b...'): quote them
        style = "'" if s[:1] and (s[0].isdigit() or s[0] in "+-." or ":" in s or "#" in s) else None
        return dumper.represent_scalar("tag:yaml.org,2002:str", s, style=style)

    Dumper.add_representer(str, represent_str)
    return Dumper


def dump_yaml(data: dict, header: str | None = None) -> str:
    """YAML text of plain data readable by PyYAML, by :func:`read_yaml` and by ``cv2.FileStorage``.

    Mappings keep their order; lists of scalars are written in flow style (``[1.0, 2.0]``), lists of lists as
    indented block sequences of flow rows; floats use ``repr`` (exact round trip); strings that start like a number
    are quoted. ``header`` lines become ``#`` comments.
    """
    import yaml

    text = yaml.dump(plain(data), Dumper=_yaml_dumper(), sort_keys=False, default_flow_style=None, width=110,
                     allow_unicode=True)
    if header:
        text = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines()) + text
    return text


def write_yaml(path, data: dict, header: str | None = None) -> None:
    """Write :func:`dump_yaml` text atomically."""
    text = dump_yaml(data, header)
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def check_format(path, d, fmt: tuple, required: bool = True) -> None:
    """Check that ``d`` is a mapping with ``format == fmt[0]`` and ``format_version == fmt[1]`` (absent keys are
    accepted when ``required`` is False: hand-written files)."""
    if not isinstance(d, dict):
        raise InputError(path, f"a YAML mapping expected ({fmt[0]} file), got {type(d).__name__}")
    if required and "format" not in d:
        raise InputError(path, f"no 'format' key: not a {fmt[0]} file", "format")
    if d.get("format", fmt[0]) != fmt[0]:
        raise InputError(path, f"{fmt[0]!r} expected, got {_short(d.get('format'))}", "format")
    if d.get("format_version", fmt[1]) != fmt[1]:
        raise InputError(path, f"{fmt[1]} supported, got {_short(d.get('format_version'))}", "format_version")


def show(v, n: int = 80) -> str:
    """``repr`` of a value for a message, cut to ``n`` characters: messages never print a whole file (a huge
    integer is given by its size, a long list by its length)."""
    if isinstance(v, int) and not isinstance(v, bool) and v.bit_length() > 64:
        return f"an integer of about {'-' if v < 0 else ''}10^{int(v.bit_length() * math.log10(2))}"
    if isinstance(v, (list, tuple)) and len(v) > 16:
        return f"a list of {len(v)} entries"
    try:
        r = repr(v)
    except ValueError:  # an integer too long to print, nested in a list
        r = f"<{type(v).__name__}>"
    return r if len(r) <= n else r[: n - 4] + " ..."


_short = show


_KINDS = {"str": str, "bool": bool, "int": int, "float": float, "list": list, "dict": dict}


def get_field(d: dict, key: str, kind: str, path=None, *, default=..., lo=None, hi=None, prefix: str = ""):
    """A typed field of a mapping (YAML file or ``.npz`` metadata), validated.

    Parameters
    ----------
    kind : {'str', 'bool', 'int', 'float', 'list', 'dict', 'str-list', 'float-list'}
        ``float`` accepts ints and numeric strings (``1e-3``) and refuses NaN and infinities; ``int`` refuses
        bools; ``str-list`` is a list of strings.
    default
        Returned when the key is absent (or null); without it the key is required.
    lo, hi : float, optional
        Inclusive bounds for ``int`` and ``float``.
    prefix : str
        Prepended to the field name in messages (``"meta."``).
    """
    name = prefix + key
    if not isinstance(d, dict):
        raise InputError(path, f"a mapping expected, got {type(d).__name__}", prefix.rstrip(".") or None)
    v = d.get(key)
    if v is None:
        if default is ...:
            raise InputError(path, "required, missing", name)
        return default
    if kind == "float":
        if isinstance(v, str):
            try:
                v = float(v)
            except ValueError:
                raise InputError(path, f"a number expected, got {_short(v)}", name) from None
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise InputError(path, f"a number expected, got {_short(v)}", name)
        v = float(v)
        if not math.isfinite(v):
            raise InputError(path, f"a finite number expected, got {v}", name)
    elif kind == "int":
        if isinstance(v, bool) or not isinstance(v, int):
            raise InputError(path, f"an integer expected, got {_short(v)}", name)
    elif kind in ("str-list", "float-list"):
        if not isinstance(v, list):
            raise InputError(path, f"a list expected, got {_short(v)}", name)
        return [get_field({key: x}, key, kind[:-5], path, prefix=prefix) for x in v]
    elif not isinstance(v, _KINDS[kind]) or (kind != "bool" and isinstance(v, bool)):
        raise InputError(path, f"{'a' if kind != 'int' else 'an'} {kind} expected, got {_short(v)}", name)
    if kind in ("int", "float") and ((lo is not None and v < lo) or (hi is not None and v > hi)):
        raise InputError(path, f"{v} outside the valid range [{lo}, {hi}]", name)
    return v


# =====================================================================================================================
# .npz files: arrays plus one meta_json entry
# =====================================================================================================================
@dataclass(frozen=True)
class ArraySpec:
    """What one array of an ``.npz`` file must be.

    Attributes
    ----------
    kinds : str
        Allowed numpy dtype kinds (``'f'`` float, ``'i'``/``'u'`` integer, ``'b'`` bool, ``'U'`` text); integers are
        accepted where floats are and converted.
    shape : tuple
        One entry per axis: an int (fixed length), a str (a named dimension that must have the same length in every
        array of the file that names it, e.g. ``'K'`` frames) or None (any length).
    finite : {'all', 'nan', 'any'}
        ``'all'``: every value finite; ``'nan'``: NaN allowed (missing), infinities not; ``'any'``: unchecked.
    required : bool
    max_abs : float, optional
        Largest magnitude accepted (physical plausibility: values such as 1e308 pass the finiteness check but
        overflow every computation that squares them).
    """

    kinds: str = "f"
    shape: tuple = ()
    finite: str = "all"
    required: bool = True
    max_abs: float | None = None


def _npz_members(zf: zipfile.ZipFile, path) -> dict:
    infos = [i for i in zf.infolist() if not i.is_dir()]
    if len(infos) > LIMITS["npz_members"]:
        raise InputError(path, f"{len(infos)} entries; at most {LIMITS['npz_members']} expected in a heartcv file")
    out = {}
    for info in infos:
        if not info.filename.endswith(".npy"):
            raise InputError(path, f"entry {info.filename!r} is not an .npy array")
        name = info.filename[:-4]
        if name in out:
            raise InputError(path, f"entry {info.filename!r} appears twice")
        out[name] = info
    return out


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, path, max_bytes: int) -> np.ndarray:
    """One .npy member, its header checked before anything is allocated."""
    fmt = np.lib.format
    name = info.filename[:-4]
    if info.file_size > max_bytes + LIMITS["npy_header_bytes"] + 128:
        raise InputError(path, f"{info.file_size} bytes uncompressed; at most {max_bytes} accepted", name)
    try:
        f = zf.open(info)
    except (zipfile.BadZipFile, NotImplementedError, RuntimeError, OSError, ValueError) as exc:  # RuntimeError:
        raise InputError(path, f"cannot open the entry ({_short(str(exc), 120)})", name) from None  # encrypted
    with f:
        try:
            version = fmt.read_magic(f)
            if version == (1, 0):
                shape, fortran, dtype = fmt.read_array_header_1_0(f, max_header_size=LIMITS["npy_header_bytes"])
            elif version in ((2, 0), (3, 0)):
                shape, fortran, dtype = fmt.read_array_header_2_0(f, max_header_size=LIMITS["npy_header_bytes"])
            else:
                raise ValueError(f"unsupported .npy version {version}")
        except (ValueError, EOFError, OSError, SyntaxError, TypeError, zipfile.BadZipFile, zlib.error,
                tokenize.TokenError) as exc:  # numpy tokenizes old-style headers (tokenize.TokenError)
            raise InputError(path, f"not a valid .npy header ({_short(str(exc), 120)})", name) from None
        if dtype.hasobject:
            raise InputError(path, "holds Python objects (a pickle); heartcv files hold numbers and text only", name)
        if dtype.kind not in "biufcUS" or dtype.fields is not None or dtype.subdtype is not None:
            raise InputError(path, f"dtype {dtype} not accepted", name)
        count = math.prod(shape) if shape else 1
        nbytes = count * dtype.itemsize
        if nbytes > max_bytes:
            raise InputError(path, f"header claims {nbytes} bytes; at most {max_bytes} accepted", name)
        if nbytes > info.file_size:
            raise InputError(path, f"header claims {nbytes} bytes but the entry holds {info.file_size}: truncated "
                                   "or corrupt", name)
        try:
            data = f.read(nbytes + 1)
        except (zipfile.BadZipFile, OSError, EOFError, ValueError, zlib.error) as exc:  # CRC errors, bad deflate data
            raise InputError(path, f"corrupt entry ({_short(str(exc), 120)})", name) from None
        if len(data) != nbytes:
            raise InputError(path, f"{len(data)} bytes of data for a header of {nbytes}: truncated or corrupt", name)
    arr = np.frombuffer(data, dtype=dtype, count=count)
    if fortran:
        return arr.reshape(shape[::-1]).T.copy()
    return arr.reshape(shape).copy()


def read_npz_meta(path) -> dict:
    """The ``meta_json`` object of a heartcv ``.npz`` file (its arrays are not read); InputError as :func:`read_npz`.
    """
    return _npz_meta_only(path)


def _npz_meta_only(path) -> dict:
    with _open_zip(path) as zf:
        members = _npz_members(zf, path)
        if "meta_json" not in members:
            raise InputError(path, "no meta_json entry: not a heartcv file")
        return _decode_meta(_read_member(zf, members["meta_json"], path, LIMITS["json_bytes"]), path)


@contextlib.contextmanager
def _open_zip(path):
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file" if not path.exists() else "not a file (.npz expected)")
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, NotImplementedError) as exc:
        raise InputError(path, f"not a readable .npz file (truncated or corrupt: {_short(str(exc), 120)})") from None
    try:
        yield zf
    except NotImplementedError as exc:  # compression method zipfile cannot read
        raise InputError(path, f"not a readable .npz file ({exc})") from None
    finally:
        zf.close()


def _decode_meta(raw: np.ndarray, path) -> dict:
    if raw.dtype != np.uint8 or raw.ndim != 1:
        raise InputError(path, f"UTF-8 bytes (uint8, 1-D) expected, got {raw.dtype} of shape {raw.shape}", "meta_json")
    try:
        meta = json.loads(raw.tobytes().decode("utf-8"), parse_constant=_no_constant)
    except (UnicodeDecodeError, ValueError) as exc:
        raise InputError(path, f"corrupt metadata ({_short(str(exc), 120)})", "meta_json") from None
    except RecursionError:
        raise InputError(path, "metadata nested too deeply", "meta_json") from None
    if not isinstance(meta, dict):
        raise InputError(path, f"a JSON object expected, got {type(meta).__name__}", "meta_json")
    return meta


def _no_constant(name):
    raise ValueError(f"{name} is not valid JSON")


def _check_array(path, name: str, a: np.ndarray, spec: ArraySpec, dims: dict) -> np.ndarray:
    if a.dtype.kind not in spec.kinds and not (a.dtype.kind in "iub" and "f" in spec.kinds):
        raise InputError(path, f"dtype {a.dtype} not accepted (kinds {spec.kinds!r} expected)", name)
    if spec.shape is not None:
        if a.ndim != len(spec.shape):
            raise InputError(path, f"{len(spec.shape)}-D {_shape_text(spec.shape)} expected, got shape {a.shape}",
                             name)
        for ax, (want, got) in enumerate(zip(spec.shape, a.shape)):
            if isinstance(want, int) and got != want:
                raise InputError(path, f"shape {_shape_text(spec.shape)} expected, got {a.shape}", name)
            if isinstance(want, str):
                if want in dims and dims[want][0] != got:
                    other, n = dims[want][1], dims[want][0]
                    raise InputError(path, f"axis {ax} has {got} entries, {other} has {n} ({want} expected to agree)",
                                     name)
                dims.setdefault(want, (got, name))
    if "f" in spec.kinds and a.dtype.kind in "iub":
        a = a.astype(float)
    if a.dtype.kind in "fc" and spec.finite != "any":
        bad = ~np.isfinite(a) if spec.finite == "all" else np.isinf(a)
        if bad.any():
            what = "non-finite values" if spec.finite == "all" else "infinite values"
            raise InputError(path, f"{int(bad.sum())} {what} (first at index {np.argwhere(bad)[0].tolist()})", name)
    if spec.max_abs is not None and a.size and a.dtype.kind in "fiu":
        big = np.abs(a) > spec.max_abs   # NaN compares False
        if big.any():
            raise InputError(path, f"{int(big.sum())} values beyond +-{spec.max_abs:g} (first at index "
                                   f"{np.argwhere(big)[0].tolist()}): not a plausible value in SI units", name)
    return a


def _shape_text(shape) -> str:
    return "(" + ", ".join("any" if s is None else str(s) for s in shape) + ")"


def read_npz(path, fmt: tuple, schema: dict[str, ArraySpec], *, allow_extra: bool = True) -> tuple[dict, dict]:
    """``(arrays, meta)`` of a heartcv ``.npz`` file, validated.

    Parameters
    ----------
    fmt : (format, version)
        ``meta_json`` must name exactly this format and version.
    schema : dict of {name: ArraySpec}
        The arrays the file may hold; required ones must be present. Named dimensions must agree across arrays.
    allow_extra : bool
        Whether arrays not in ``schema`` are kept (unchecked beyond the safe-loading limits) or refused.

    Raises
    ------
    InputError
        Missing, corrupt or foreign file, a pickled or oversized array, an array of the wrong dtype, shape or with
        non-finite values, metadata that is not a JSON object of the right format.
    """
    with _open_zip(path) as zf:
        members = _npz_members(zf, path)
        if "meta_json" not in members:
            raise InputError(path, "no meta_json entry: not a heartcv file")
        meta = _decode_meta(_read_member(zf, members.pop("meta_json"), path, LIMITS["json_bytes"]), path)
        if meta.get("format") != fmt[0]:
            raise InputError(path, f"{fmt[0]!r} expected, got {_short(meta.get('format'))}", "meta.format")
        if meta.get("format_version") != fmt[1]:
            raise InputError(path, f"{fmt[0]} version {fmt[1]} supported, got {_short(meta.get('format_version'))}",
                             "meta.format_version")
        check_provenance(meta, path, "meta.")
        missing = [k for k, s in schema.items() if s.required and k not in members]
        if missing:
            raise InputError(path, f"missing arrays {missing}")
        extra = [k for k in members if k not in schema]
        if extra and not allow_extra:
            raise InputError(path, f"unexpected arrays {extra}")
        arrays = {k: _read_member(zf, info, path, LIMITS["array_bytes"]) for k, info in members.items()}
    dims: dict = {}
    for k, spec in schema.items():
        if k in arrays:
            arrays[k] = _check_array(path, k, arrays[k], spec, dims)
    return arrays, meta


def check_provenance(d: dict, path=None, prefix: str = "") -> None:
    """Types of the provenance keys every heartcv file may carry (docs/formats.md §1.8): ``producer`` and
    ``heartcv_version`` strings, ``inputs_hash`` a mapping of role -> ``"sha256:<hex>"`` string."""
    for key in ("producer", "heartcv_version"):
        if d.get(key) is not None:
            get_field(d, key, "str", path, prefix=prefix)
    h = d.get("inputs_hash")
    if h is not None and (not isinstance(h, dict) or not all(isinstance(k, str) and (v is None or isinstance(v, str))
                                                             for k, v in h.items())):
        raise InputError(path, "a mapping of input role -> 'sha256:<hex>' expected", f"{prefix}inputs_hash")
    sw = d.get("software")
    if sw is not None and (not isinstance(sw, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                               for k, v in sw.items())):
        raise InputError(path, "a mapping of library -> version string expected", f"{prefix}software")


#: Libraries whose version a file records when the writing process has loaded them (:func:`software_versions`)
SOFTWARE_MODULES = (("scipy", "scipy"), ("opencv", "cv2"), ("torch", "torch"), ("kornia", "kornia"),
                    ("pycolmap", "pycolmap"))


def software_versions() -> dict:
    """``{"python": ..., "numpy": ..., ...}``: the versions of Python, NumPy and of the libraries of
    :data:`SOFTWARE_MODULES` this process has loaded, the software that shaped a stage's numbers (the tracks of
    real frames depend on the OpenCV build, the filters' last digits on the linear algebra). Recorded in every
    ``.npz`` file's metadata as ``software`` (docs/formats.md §1.8)."""
    import platform
    import sys

    out = {"python": platform.python_version(), "numpy": np.__version__}
    for name, module in SOFTWARE_MODULES:
        version = getattr(sys.modules.get(module), "__version__", None)
        if version is not None:
            out[name] = str(version)
    return out


def write_npz(path, fmt: tuple, arrays: dict, meta: dict) -> None:
    """Write arrays plus ``meta_json`` (with ``format``, ``format_version``, ``heartcv_version`` and ``software``,
    :func:`software_versions`) atomically, compressed. None arrays are left out."""
    from . import __version__

    meta = dict(meta)
    meta.update({"format": fmt[0], "format_version": fmt[1], "heartcv_version": __version__,
                 "software": software_versions()})
    payload = {k: np.asarray(v) for k, v in arrays.items() if v is not None}
    for k, v in payload.items():
        if v.dtype.hasobject:
            raise TypeError(f"array {k!r} holds Python objects; not written")
    payload["meta_json"] = np.frombuffer(json.dumps(plain(meta), sort_keys=True, allow_nan=False).encode(),
                                         dtype=np.uint8)
    buf = io.BytesIO()
    np.savez_compressed(buf, **payload)
    with atomic_path(path, suffix=".npz") as tmp:
        tmp.write_bytes(buf.getvalue())


# =====================================================================================================================
# CSV tables
# =====================================================================================================================
def read_csv_table(path, numeric_except=(), what: str = "table") -> tuple[dict, int]:
    """``({column: values}, n_rows)`` of a comma-separated UTF-8 table with ``#`` comment lines and a header row.

    Columns named in ``numeric_except`` are kept as strings, the others parsed as finite floats. InputError naming
    the file and the column (or row) for an empty table, duplicate or empty column names, ragged rows, cells that
    are not numbers, NaN or infinite values.
    """
    text = read_text(path, what)
    rows = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows:
        raise InputError(path, f"empty {what} (a header row of column names expected)")
    header = [c.strip() for c in rows[0].split(",")]
    if any(not c for c in header) or len(set(header)) != len(header):
        raise InputError(path, f"header row: distinct, non-empty column names expected, got {_short(header)}")
    cells = [[c.strip() for c in r.split(",")] for r in rows[1:]]
    for i, r in enumerate(cells):
        if len(r) != len(header):
            raise InputError(path, f"{len(r)} values for {len(header)} columns {_short(header)}", f"row {i + 1}")
    out = {}
    for j, name in enumerate(header):
        col = [r[j] for r in cells]
        if name in numeric_except:
            out[name] = col
            continue
        try:
            values = np.array([float(v) for v in col], float)
        except ValueError as exc:
            raise InputError(path, f"not numeric ({exc})", f"column {name!r}") from None
        bad = ~np.isfinite(values)
        if bad.any():
            raise InputError(path, f"non-finite value {col[int(np.argmax(bad))]!r} in row {int(np.argmax(bad)) + 1}",
                             f"column {name!r}")
        out[name] = values
    return out, len(cells)


def get_matrix(v, shape, path=None, field: str | None = None, *, allow_none: bool = False):
    """A finite float array of ``shape`` (None entries: any length; ``shape=None``: a flat list) from YAML/JSON
    data (lists of lists); InputError naming the field for ragged, non-numeric, non-finite or misshapen data."""
    if v is None and allow_none:
        return None
    if not isinstance(v, (list, tuple)):
        raise InputError(path, f"a list of numbers expected, got {_short(v)}", field)
    try:
        a = np.array(v, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise InputError(path, f"a {'list' if shape is None else 'matrix'} of numbers expected (ragged or "
                               f"non-numeric: {_short(v)})", field) from None
    if shape is None:
        if a.ndim != 1:
            raise InputError(path, f"a flat list of numbers expected, got shape {a.shape}", field)
    elif a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
        raise InputError(path, f"shape {_shape_text(shape)} expected, got {a.shape}", field)
    if not np.isfinite(a).all():
        raise InputError(path, "finite numbers expected", field)
    return a
