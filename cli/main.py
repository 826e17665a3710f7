"""The ``heartcv`` command group: verbosity and logging to stderr, commands registered lazily, and the one place
where errors become exit codes (docs/cli.md §1.3):

- :class:`heartcv.tracker.files.InputError` (input that failed validation; it names the file and the field) -> exit 2;
- click's own exceptions (usage errors exit 2, :class:`~heartcv.cli.options.StageFailed` exit 1) pass through;
- an ``OSError`` the machine causes (a full disk, a read-only file system, no permission: :data:`SYSTEM_ERRNOS`) ->
  exit 1 naming the file and the reason (:class:`SystemRefused`);
- anything else is a bug in heartcv: one line says so (exit 1), the traceback follows with ``-v``.
"""

from __future__ import annotations

import errno
import importlib
import logging
import sys
import traceback

import click

from heartcv.tracker.files import ConcurrentWrite, InputError, output_group, outputs_committed

log = logging.getLogger("heartcv")

# command name -> "module:attribute"; modules are imported only when the command runs (fast --help)
COMMANDS = {
    "model": "heartcv.cli.model:model",
    "track": "heartcv.cli.track:track",
    "simulate": "heartcv.cli.simulate:simulate",
    "target": "heartcv.cli.target:target",
    "calibrate": "heartcv.cli.calibrate:calibrate",
    "render": "heartcv.cli.render:render",
    "measure": "heartcv.cli.measure:measure",
    "report": "heartcv.cli.report:report",
    "fit": "heartcv.cli.fit:fit",
    "rig": "heartcv.cli.rig:rig",
}


class LazyGroup(click.Group):
    def list_commands(self, ctx):
        return sorted(COMMANDS)

    def get_command(self, ctx, name):
        if name not in COMMANDS:
            return None
        module, attr = COMMANDS[name].split(":")
        return getattr(importlib.import_module(module), attr)

    def invoke(self, ctx):
        try:
            with output_group():     # a stage's outputs go in place together, when it has finished (docs/cli.md §1.4)
                return super().invoke(ctx)
        except InputError as exc:
            raise _InputRefused(str(exc)) from None
        except Terminated:
            raise Interrupted("terminated (SIGTERM)", 143, outputs_committed()) from None
        except KeyboardInterrupt:
            raise Interrupted("interrupted (Ctrl-C)", 130, outputs_committed()) from None
        except (click.exceptions.ClickException, click.exceptions.Exit, click.exceptions.Abort, SystemExit):
            raise
        except ConcurrentWrite as exc:      # two runs on one output folder: a failed stage, not a bug
            raise click.ClickException(str(exc)) from None
        except OSError as exc:
            if exc.errno in SYSTEM_ERRNOS:   # the machine refused a file operation: neither the input nor a bug
                raise SystemRefused(exc) from None
            raise InternalError(exc, (ctx.obj or {}).get("verbosity", 0)) from None
        except Exception as exc:  # noqa: BLE001 - the one place that reports bugs (docs/cli.md §1.3)
            verbosity = (ctx.obj or {}).get("verbosity", 0)
            raise InternalError(exc, verbosity) from None


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the process is so that every open output's clean-up runs as for Ctrl-C."""


def _on_sigterm(signum, frame):
    raise Terminated()


class Interrupted(click.ClickException):
    """Ctrl-C (exit 130) or SIGTERM (exit 143): one line, no traceback; the outputs' temporary files were removed
    and every earlier output is as it was."""

    def __init__(self, what: str, code: int, written: bool = False):
        if written:     # the signal came after the outputs were put in place (held while they were)
            super().__init__(f"{what} after the outputs were put in place: they are this run's, complete")
        else:
            super().__init__(f"{what}: stopped; nothing was replaced (earlier outputs are as they were, temporary "
                             "files removed)")
        self.exit_code = code

    def show(self, file=None):
        click.echo(f"Error: {self.format_message()}", err=True)


class _InputRefused(click.ClickException):
    exit_code = 2

    def show(self, file=None):
        click.echo(f"Error: {self.format_message()}", err=True)


SYSTEM_ERRNOS = frozenset(getattr(errno, n) for n in ("ENOSPC", "EDQUOT", "EROFS", "EACCES", "EPERM", "EIO", "EMFILE",
                                                     "ENFILE", "ENOMEM") if hasattr(errno, n))
"""Failed file operations that are the machine's condition (a full disk or quota, a read-only file system, missing
permission, an I/O error, too many open files, no memory): a failed stage (exit 1) naming the file, not a bug."""


class SystemRefused(click.ClickException):
    """The operating system refused a file operation (:data:`SYSTEM_ERRNOS`): exit 1 with its reason and the file."""

    exit_code = 1

    def __init__(self, exc: OSError):
        name = f": {exc.filename}" if exc.filename is not None else ""
        super().__init__(f"{exc.strerror or exc}{name} -- the system refused a file operation (free space or fix the "
                         "permissions and run again); the stage stopped, its outputs are incomplete or absent")

    def show(self, file=None):
        click.echo(f"Error: {self.format_message()}", err=True)


class InternalError(click.ClickException):
    """An unexpected exception: a bug in heartcv, never blamed on the user's input (exit 1)."""

    exit_code = 1

    def __init__(self, exc: BaseException, verbosity: int):
        where = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
        at = f" at {where.filename.rsplit('/', 1)[-1]}:{where.lineno}" if where else ""
        first = (str(exc).splitlines() or [""])[0][:300]
        super().__init__(f"internal error: {type(exc).__name__}{at}: {first} -- this is a bug in heartcv, not a "
                         "problem with your input; please report it"
                         + ("" if verbosity > 0 else " (run with -v for the traceback)"))
        self.exc = exc
        self.verbosity = verbosity

    def show(self, file=None):
        if self.verbosity > 0:
            traceback.print_exception(type(self.exc), self.exc, self.exc.__traceback__, file=sys.stderr)
        click.echo(f"Error: {self.format_message()}", err=True)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-v", "--verbose", count=True, help="More log output (repeatable).")
@click.option("-q", "--quiet", count=True, help="Less log output (repeatable).")
@click.version_option(package_name="heartcv")
@click.pass_context
def main(ctx, verbose, quiet):
    """heartcv: physics-based tracking of beating-heart surface motion.

    Available: `target`, `rig` (import, rectified), `render`, `calibrate`, `measure`, `model info`, `model
    simulate`, `fit`, `track` (kf, ge, ukf, ekf; baselines hold, constvel, harmonic), `report`, `simulate`
    (Monte-Carlo study of the estimators). Logs go to stderr; --json summaries to stdout.
    """
    verbosity = verbose - quiet
    # INFO by default: a stage's summary line is INFO, WARNING is kept for what the user should act on; -q
    # leaves warnings only, -qq errors only, -v adds debug output.
    logging.basicConfig(level=min(40, max(10, 20 - 10 * verbosity)), format="%(levelname)s %(name)s: %(message)s",
                        force=True)
    # scikit-fem logs every assembly at INFO: library chatter, shown only with -v
    logging.getLogger("skfem").setLevel(logging.DEBUG if verbosity > 0 else logging.WARNING)
    # FFmpeg prints a line per damaged packet of a video (thousands for a corrupt file): silenced before the first
    # video is opened, unless -v (docs/cli.md §8.2)
    from heartcv.video import silence_ffmpeg

    silence_ffmpeg(verbose=verbosity > 0)
    ctx.ensure_object(dict)
    ctx.obj["verbosity"] = verbosity
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():   # (not in a test runner's thread)
        before = signal.signal(signal.SIGTERM, _on_sigterm)
        ctx.call_on_close(lambda: signal.signal(signal.SIGTERM, before))     # a host process gets its own back


if __name__ == "__main__":  # pragma: no cover
    main()
