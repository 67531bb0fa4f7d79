"""The cores this process may use, and a thread pool for NumPy work that releases the GIL.

NumPy's linear algebra on a stack of small matrices (``eigh`` of 500 matrices of 24 x 24:
LAPACK once per matrix) holds no lock, so splitting the stack over threads divides its
wall time by the cores; each matrix is still decomposed alone, so the numbers are the
same bits (:func:`designer.bounds.eigh`).  The pool is made at its first use and not
inherited by a forked child (whose copy would have no threads).
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

__all__ = ["usable_cores", "thread_pool"]

_POOL: ThreadPoolExecutor | None = None


def usable_cores() -> int:
    """The cores this process may run on (its affinity mask where the platform has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - platforms without affinity masks
        return os.cpu_count() or 1


def thread_pool() -> ThreadPoolExecutor:
    """A pool of :func:`usable_cores` threads, shared by the callers of this process."""
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=usable_cores(), thread_name_prefix="cfdesign-numpy")
    return _POOL


def _forget_pool() -> None:
    global _POOL
    _POOL = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)
