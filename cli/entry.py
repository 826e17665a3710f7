"""The ``heartcv`` console script. It imports the command line (click, numpy, the stages' registry: a few tenths
of a second) under its own guard, so that a Ctrl-C while the program starts is one line and exit 130, not a
traceback (once the command runs, :mod:`heartcv.cli.main` turns signals into exit codes, docs/cli.md §1.3)."""

import sys


def run() -> None:
    try:
        from heartcv.cli.main import main
    except KeyboardInterrupt:
        sys.stderr.write("Error: interrupted (Ctrl-C) while starting: nothing was done\n")
        raise SystemExit(130) from None
    main()
