"""A Ctrl-C remembered even where a library swallows it: :class:`Interrupts`, the home of the command's and the
Monte Carlo runner's watch (the command line, :mod:`studies.cli`, and :mod:`studies.runner` use it; the executable,
:mod:`studies.launch`, catches a Ctrl-C while the command line loads).
"""
from __future__ import annotations

import signal
import sys


class Interrupts:
    """Remember a Ctrl-C even if a library swallows the KeyboardInterrupt it raises.

    Some extension code catches every exception (CasADi's SWIG conversions use bare
    ``except:``), and a KeyboardInterrupt raised inside a callback from C (numba's LLVM object
    cache notifications) is reported by Python as "Exception ignored" and dropped, so the
    computation goes on.  This handler records the signal before raising, and the dropped ones
    are recorded instead of printed (``sys.unraisablehook``); :meth:`check` raises the
    KeyboardInterrupt once the caller can act on it: a Monte Carlo chunk that was being computed
    is discarded, never stored, and the run stops; a command ends as interrupted.
    """

    def __init__(self):
        self.seen = False
        self._old = None
        self._old_hook = None

    def __enter__(self):
        import threading

        current = signal.getsignal(signal.SIGINT)
        # inside another one (the command's around a study's Monte Carlo runner) each records the Ctrl-C
        if threading.current_thread() is threading.main_thread() and (
                current is signal.default_int_handler or isinstance(getattr(current, "__self__", None), Interrupts)):
            self._old = signal.signal(signal.SIGINT, self._handle)
            self._old_hook, sys.unraisablehook = sys.unraisablehook, self._unraisable
        return self

    def _mark(self) -> None:
        self.seen = True
        outer = getattr(self._old, "__self__", None)
        if isinstance(outer, Interrupts):
            outer._mark()

    def _handle(self, signum, frame):
        self._mark()
        raise KeyboardInterrupt

    def _unraisable(self, unraisable) -> None:
        if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
            self._mark()  # a Ctrl-C dropped by a callback: check() raises it
            return
        self._old_hook(unraisable)

    def check(self) -> None:
        if self.seen:
            raise KeyboardInterrupt("interrupted: the chunk in progress was discarded")

    def __exit__(self, *exc):
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)
            sys.unraisablehook = self._old_hook
        return False
