"""Shared options, value types, output guards and error types of the command-line interface.

Exit codes (docs/cli.md §1.3): 0 ok; 1 the stage failed on valid input (did not converge, diverged) or an
internal error (a bug: one line says so, ``-v`` shows the traceback); 2 bad usage or input that failed validation
(the message names the file and the field, or the option).

Shared options: ``json_opt`` (--json: machine-readable summary on stdout), ``seed_opt`` (--seed),
``output_opt`` (-o/--output). Value types: :class:`Float` (finite, bounded), :func:`Int` (bounded).
Output safety: :func:`guard_outputs` (before any work).
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time

import click

from heartcv.tracker.files import after_outputs, check_output_file, check_output_folder, refuse_overlap

# Upper bounds of counts and sizes that no real run needs and that would exhaust the machine (docs/cli.md §1.4)
MAX_SEED = 2**63 - 1
MAX_COUNT = 10**6          # runs, steps, frames, starts, workers...
MAX_IMAGE_SIDE = 16384     # pixels


class IntPair(click.ParamType):
    """``AxB`` (e.g. ``11x8`` or ``360x288``) -> (a, b), each in ``low`` .. ``limit`` (an int, or a callable giving
    it, for limits that live in modules imported only when the option is used)."""

    def __init__(self, metavar: str, example: str, limit, unit: str = "", low: int = 1):
        self.name, self.example, self.limit, self.unit, self.low = metavar, example, limit, unit, low

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        parts = str(value).lower().replace("×", "x").split("x")
        try:
            a, b = (int(p) for p in parts)
        except ValueError:
            self.fail(f"{self.name} expected (e.g. {self.example}), got {value!r}", param, ctx)
        hi = self.limit() if callable(self.limit) else self.limit
        if not (self.low <= a <= hi and self.low <= b <= hi):
            self.fail(f"{a}x{b}: {self.low} to {hi}{self.unit} each way expected", param, ctx)
        return a, b


class Float(click.ParamType):
    """A finite float in ``[lo, hi]`` (open ends with ``lo_open``/``hi_open``); NaN and infinities are refused,
    which click.FloatRange lets through."""

    name = "float"

    def __init__(self, lo=None, hi=None, lo_open=False, hi_open=False):
        self.lo, self.hi, self.lo_open, self.hi_open = lo, hi, lo_open, hi_open

    def convert(self, value, param, ctx):
        try:
            v = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number", param, ctx)
        if not math.isfinite(v):
            self.fail(f"{value!r}: a finite number expected", param, ctx)
        lo_bad = self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo)
        hi_bad = self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi)
        if lo_bad or hi_bad:
            self.fail(f"{v:g} is not in the range {self._range()}", param, ctx)
        return v

    def _range(self) -> str:
        lo = "-inf" if self.lo is None else f"{self.lo:g}"
        hi = "inf" if self.hi is None else f"{self.hi:g}"
        left = "(" if self.lo_open or self.lo is None else "["
        right = ")" if self.hi_open or self.hi is None else "]"
        return f"{left}{lo}, {hi}{right}"

    def get_metavar(self, param, ctx=None):
        return f"FLOAT {self._range()}"


def Int(lo=0, hi=MAX_COUNT):  # noqa: N802 - reads like a type
    """An integer in ``[lo, hi]`` (both bounds always set: no option takes an unbounded count)."""
    return click.IntRange(min=lo, max=hi)


def guard_outputs(outputs: dict, inputs: dict, *, files=(), folders=()) -> None:
    """Refuse, before any work, outputs that equal or contain an input (:func:`refuse_overlap`), output files that
    hold something heartcv did not write, and output folders that another stage (or a person) made.

    Parameters
    ----------
    outputs, inputs : dict of {label: path or None}
        Labels are the option or argument names the messages show (``"-o/--output"``, ``"MEASUREMENTS"``).
    files : iterable of (label, path) or (label, path, kinds)
        Output files to check with :func:`check_output_file` (``kinds``: the heartcv formats the stage writes
        there; an existing heartcv file of another format is refused).
    folders : iterable of (label, path, producer)
        Output folders that ``producer`` replaces as a whole (:func:`check_output_folder`).
    """
    from heartcv.tracker.files import check_output_name

    for label, path in outputs.items():     # names the system cannot create, before any path is resolved
        if path is not None:
            check_output_name(path, label, folder=any(path == f[1] for f in folders))
    refuse_overlap(outputs, inputs)
    for label, path, *kinds in files:
        if path is not None:
            check_output_file(path, label, kinds[0] if kinds else None)
    for label, path, producer in folders:
        if path is not None:
            check_output_folder(path, producer, label)

json_opt = click.option("--json", "as_json", is_flag=True, help="Print a machine-readable summary on stdout.")
seed_opt = click.option("--seed", type=Int(0, MAX_SEED), default=0, show_default=True,
                        help="Seed of the random generator (numpy.random.default_rng).")


def output_opt(help_text="Output file."):
    return click.option("-o", "--output", type=click.Path(dir_okay=False, writable=True), required=True,
                        help=help_text)


class BadInput(click.ClickException):
    """Bad usage that click cannot see (options that do not go together): exit 2. Input files that fail
    validation raise :class:`heartcv.tracker.files.InputError`, which the command group turns into this."""

    exit_code = 2

    def show(self, file=None):
        click.echo(f"Error: {self.format_message()}", err=True)


class StageFailed(click.ClickException):
    """The computation itself failed (no convergence, divergence): exit 1."""

    exit_code = 1

    def show(self, file=None):
        click.echo(f"Error: {self.format_message()}", err=True)


def announce(logger: logging.Logger, fmt: str, *args) -> None:
    """Log a stage's "wrote ..." line (INFO, on ``logger``) once its outputs are in place (:func:`emit_json`'s
    rule)."""
    after_outputs(lambda: logger.info(fmt, *args))


def emit_json(summary: dict) -> None:
    """Write a summary as one JSON document on stdout, once the stage's outputs are in place (never for a stage
    whose renames failed: :func:`~heartcv.tracker.files.after_outputs`)."""
    text = json.dumps(summary, indent=2, sort_keys=True, default=_default)
    after_outputs(lambda: click.echo(text))


def _default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def load_model(path):
    """Read, validate and build a model file (InputError naming the file and field -> exit 2)."""
    from heartcv.tracker.io import read_model
    from heartcv.tracker.model import build_model

    return build_model(read_model(path))


PROGRESS_LOG_S = 30.0
"""Seconds between the progress lines of a long stage whose stderr is not a terminal (a Makefile's log, a batch
job): one INFO line ``label: done/total (percent), elapsed`` at most this often, none for a stage that ends sooner."""


def progress(iterable, label, length=None, verbosity=0):
    """Progress on stderr: a click progress bar on a terminal; elsewhere an INFO log line at most every
    :data:`PROGRESS_LOG_S` seconds; nothing with -q. Iterate over what the ``with`` gives, or call its
    ``update(n)`` (``iterable`` None: ``length`` steps counted by ``update`` only)."""
    if verbosity < 0:
        return _Null(iterable)
    if sys.stderr.isatty():
        return click.progressbar(iterable, label=label, length=length, file=sys.stderr)
    return _LogProgress(iterable, label, length)


class _Null:
    def __init__(self, it):
        self.it = it

    def __enter__(self):
        return self if self.it is None else self.it

    def __exit__(self, *a):
        return False

    def update(self, n):
        pass


class _LogProgress:
    """:func:`progress` where stderr is not a terminal: counts steps (by iteration or ``update``) and logs."""

    def __init__(self, iterable, label, length=None):
        self.it = iterable
        self.label = label
        self.length = length if length is not None else (len(iterable) if hasattr(iterable, "__len__") else None)
        self.done = 0
        self.start = self.last = time.monotonic()

    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False

    def __iter__(self):
        for item in self.it:
            yield item
            self.update(1)

    def update(self, n):
        self.done += n
        now = time.monotonic()
        if now - self.last < PROGRESS_LOG_S:
            return
        self.last = now
        of = f"/{self.length} ({100.0 * self.done / self.length:.0f} %)" if self.length else ""
        logging.getLogger("heartcv.cli").info("%s: %d%s, %.0f s", self.label, self.done, of, now - self.start)
