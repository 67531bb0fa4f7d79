"""The ``cfdesign`` executable: one line and exit 130 for a Ctrl-C at any moment, also while starting up.

The command line (:mod:`studies.cli`) loads with click and NumPy only and imports the model
layer (CasADi, SciPy, numba) inside the command that runs, where :func:`studies.cli.main`
turns a Ctrl-C into that line; a Ctrl-C while the command line itself loads is caught here,
where it would otherwise print Python's traceback.
"""
from __future__ import annotations

import os
import sys

INTERRUPTED = 130


def _exit(code: int) -> None:
    if code != INTERRUPTED:
        sys.exit(code)
    # A KeyboardInterrupt raised inside source that Python compiles from a string (dataclasses and namedtuples
    # build their methods so, at import) leaves CPython marked as interrupted even when it was caught, and under
    # ``python -m studies`` the interpreter would then end by SIGINT instead of with this code; the interrupted
    # command has cleaned up (its ``finally`` blocks ran), so leave without the interpreter's shutdown.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def run() -> None:
    try:
        from .cli import main
    except KeyboardInterrupt:
        print("cfdesign: interrupted", file=sys.stderr)
        _exit(INTERRUPTED)
    _exit(main())
