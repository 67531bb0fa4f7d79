"""The ``cfdesign`` executable: one line and exit 130 for a Ctrl-C at any moment, also while starting up.

The command line (:mod:`studies.cli`) loads with click and NumPy only and imports the model
layer (CasADi, SciPy, numba) inside the command that runs, where :func:`studies.cli.main`
turns a Ctrl-C into that line; a Ctrl-C while the command line itself loads is caught here,
where it would otherwise print Python's traceback.  A Ctrl-C that a library swallows or drops
while the command runs is remembered (:class:`studies.interrupts.Interrupts`, also the Monte Carlo runner's) and
still ends the command as interrupted.
"""
from __future__ import annotations

import gc
import os
import signal
import sys

INTERRUPTED = 130


def _exit(code: int) -> None:
    if code != INTERRUPTED:
        # The command has ended and said so: a Ctrl-C from now on comes too late to interrupt anything.  Python
        # restores SIGINT's default action during its shutdown, where such a Ctrl-C would kill the process silently
        # (exit -2 instead of the code the command reported); an ignored signal stays ignored.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        # The interpreter's shutdown ends with a garbage collection over every object a command loaded (CasADi,
        # numba, matplotlib: about 0.1 s, a tenth of a small study); frozen, they are left to the exit itself.
        # Everything else of the shutdown runs (atexit handlers, threads joined, files flushed).
        gc.freeze()
        sys.exit(code)
    # A KeyboardInterrupt raised inside source that Python compiles from a string (dataclasses and namedtuples
    # build their methods so, at import) leaves CPython marked as interrupted even when it was caught, and under
    # ``python -m studies`` the interpreter would then end by SIGINT instead of with this code; the interrupted
    # command has cleaned up (its ``finally`` blocks ran), so leave without the interpreter's shutdown.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


# BLAS threads for the command line: its matrices are small (a few states per node), where OpenBLAS's threads
# cost far more than they save (800 solves of a 4 x 4 triangular system: 1.44 s with its threads on a shared
# 2-core machine, 0.04 s without); a study's parallelism is across runs (--workers, Dask).  Set before NumPy
# loads OpenBLAS (it reads the variable once), so that no BLAS thread is even started; a value the user set is
# kept.  The numbers do not depend on it: every computation of studies.api runs BLAS on one thread anyway
# (designer.cores.one_blas_thread), as a Python script calling the API does.
BLAS_THREADS = {"OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def run() -> None:
    for name, value in BLAS_THREADS.items():
        os.environ.setdefault(name, value)
    try:
        from .cli import main
    except KeyboardInterrupt:
        print("cfdesign: interrupted", file=sys.stderr)
        _exit(INTERRUPTED)
    _exit(main())
