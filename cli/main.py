"""The ``heartcv`` command group: verbosity and logging to stderr; commands are registered lazily."""

from __future__ import annotations

import importlib
import logging

import click

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
}


class LazyGroup(click.Group):
    def list_commands(self, ctx):
        return sorted(COMMANDS)

    def get_command(self, ctx, name):
        if name not in COMMANDS:
            return None
        module, attr = COMMANDS[name].split(":")
        return getattr(importlib.import_module(module), attr)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-v", "--verbose", count=True, help="More log output (repeatable).")
@click.option("-q", "--quiet", count=True, help="Less log output (repeatable).")
@click.version_option(package_name="heartcv")
@click.pass_context
def main(ctx, verbose, quiet):
    """heartcv: physics-based tracking of beating-heart surface motion.

    Available: `target`, `render`, `calibrate`, `measure`, `model info`, `model simulate`, `track` (kf, ge,
    ukf, ekf), `fit`, `report`, `simulate` (Monte-Carlo study of the estimators). Logs go to stderr; --json summaries to stdout.
    """
    verbosity = verbose - quiet
    logging.basicConfig(level=max(10, 30 - 10 * verbosity), format="%(levelname)s %(name)s: %(message)s",
                        force=True)
    ctx.ensure_object(dict)
    ctx.obj["verbosity"] = verbosity


if __name__ == "__main__":  # pragma: no cover
    main()
