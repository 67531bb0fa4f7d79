"""The ``cfdesign`` executable: one line and exit 130 for a Ctrl-C at any moment, also while starting up.

The command line (:mod:`studies.cli`) imports the model layer (CasADi, NumPy, SciPy) when
it loads; a Ctrl-C during those imports would otherwise print Python's traceback.
"""
from __future__ import annotations

import sys


def run() -> None:
    try:
        from .cli import main
    except KeyboardInterrupt:
        print("cfdesign: interrupted", file=sys.stderr)
        sys.exit(130)
    sys.exit(main())
