"""Shared options, value handlers and error types of the command-line interface.

Exit codes (docs/design.md §1): 0 ok, 1 the stage failed (did not converge, diverged), 2 bad usage or bad input.

Shared options: ``json_opt`` (--json: machine-readable summary on stdout), ``seed_opt`` (--seed),
``output_opt`` (-o/--output). Used by: model info/simulate, track.
"""

from __future__ import annotations

import json
import sys

import click

json_opt = click.option("--json", "as_json", is_flag=True, help="Print a machine-readable summary on stdout.")
seed_opt = click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
                        help="Seed of the random generator (numpy.random.default_rng).")


def output_opt(help_text="Output file."):
    return click.option("-o", "--output", type=click.Path(dir_okay=False, writable=True), required=True,
                        help=help_text)


class BadInput(click.ClickException):
    """Bad input data or file: exit 2."""

    exit_code = 2

    def show(self, file=None):
        click.echo(f"Error: {self.format_message()}", err=True)


class StageFailed(click.ClickException):
    """The computation itself failed (no convergence, divergence): exit 1."""

    exit_code = 1

    def show(self, file=None):
        click.echo(f"Error: {self.format_message()}", err=True)


def emit_json(summary: dict) -> None:
    """Write a summary as one JSON document on stdout."""
    click.echo(json.dumps(summary, indent=2, sort_keys=True, default=_default))


def _default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def load_model(path):
    """Read and build a model file, turning input errors into exit 2."""
    from heartcv.tracker.config import ConfigError
    from heartcv.tracker.io import FileFormatError, read_model
    from heartcv.tracker.model import build_model

    try:
        cfg = read_model(path)
        return build_model(cfg)
    except (ConfigError, FileFormatError) as exc:
        raise BadInput(str(exc)) from None
    except ValueError as exc:
        raise BadInput(f"{path}: {exc}") from None


def progress(iterable, label, length=None, verbosity=0):
    """A click progress bar on stderr (hidden with -q or when stderr is not a terminal)."""
    show = verbosity >= 0 and sys.stderr.isatty()
    if not show:
        return _Null(iterable)
    return click.progressbar(iterable, label=label, length=length, file=sys.stderr)


class _Null:
    def __init__(self, it):
        self.it = it

    def __enter__(self):
        return self.it

    def __exit__(self, *a):
        return False
