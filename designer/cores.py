"""The cores this process may use, a thread pool for NumPy work that releases the GIL, BLAS on one thread, and the
allocator (:func:`keep_freed_memory`).

NumPy's linear algebra on a stack of small matrices (``eigh`` of 500 matrices of 24 x 24:
LAPACK once per matrix) holds no lock, so splitting the stack over threads divides its
wall time by the cores; each matrix is still decomposed alone, so the numbers are the
same bits (:func:`designer.bounds.eigh`).  The pool is made at its first use and not
inherited by a forked child (whose copy would have no threads).

BLAS's own threads (OpenBLAS, MKL: ``OPENBLAS_NUM_THREADS`` unset means every core) split a
product or a factorisation of a matrix of some 80 rows or more into blocks whose order of
summation depends on the number of threads, so the same design gave different bits with one
BLAS thread (the command line's) and with two (a Python session's).  Every public computation
runs inside :func:`one_blas_thread`: BLAS and LAPACK on one thread whatever the environment, the
numbers the same in every process (the pool above still runs its matrices in parallel, each
on one BLAS thread); the matrices here are too small for BLAS's threads to pay anyway.
"""
from __future__ import annotations

import functools
import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor

__all__ = ["usable_cores", "thread_pool", "kept_pool", "one_blas_thread", "keep_freed_memory", "SOLVER_SETTINGS",
           "ALLOCATOR"]

#: Clarabel's settings for every convex problem cfdesign solves (``problem.solve(solver=cp.CLARABEL,
#: **SOLVER_SETTINGS)``): one thread.  Clarabel's sparse factorisation (faer) otherwise runs on a rayon thread pool
#: created at the process's first solve; a process forked after it (a design's certificate computed beside its run,
#: :class:`studies.runner.Background`, an automatic design's candidates, a study's workers) inherits the pool's
#: bookkeeping without its threads and waits for them for ever at its own first solve.  One thread also keeps the
#: factorisation's summation order, hence every digit, the same on every machine.
SOLVER_SETTINGS = {"max_threads": 1}

_POOLS: dict[str, tuple[ThreadPoolExecutor, int]] = {}  # kept_pool's pools by name, with their threads


def usable_cores() -> int:
    """The cores this process may run on (its affinity mask where the platform has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - platforms without affinity masks
        return os.cpu_count() or 1


def kept_pool(name: str, threads: int) -> ThreadPoolExecutor:
    """A pool of at least ``threads`` threads named ``name``, kept for this process's later calls (starting threads
    at every call was 9 % of a warm ``rrp-deception`` study, 70 calls).  One pool per name, so that one pool's tasks
    never wait on their own pool; forgotten in a forked child, whose copy would have no threads."""
    held = _POOLS.get(name)
    if held is None or held[1] < threads:
        if held is not None:
            held[0].shutdown(wait=False)
        held = _POOLS[name] = (ThreadPoolExecutor(max_workers=threads, thread_name_prefix=f"cfdesign-{name}"),
                               threads)
    return held[0]


def thread_pool() -> ThreadPoolExecutor:
    """A pool of :func:`usable_cores` threads, shared by the callers of this process (:func:`kept_pool`)."""
    return kept_pool("numpy", usable_cores())


def _forget_pools() -> None:
    _POOLS.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pools)


#: glibc's allocator as cfdesign sets it (mallopt(3)): a block of up to ``mmap_threshold`` bytes from the heap, and up
#: to ``trim_threshold`` bytes freed at the heap's top kept.  Its defaults give every array above 128 kB fresh pages
#: from the kernel, or return them once the array is freed: the filters' per-step temporaries (a stack of 64 x 64
#: covariances over the runs and nodes is 4 MB) then cost a page fault every 4 kB each time.  Measured on the 64-cell
#: field's comparison: 252 s of system time of 813 s of CPU, 45 million page faults; HCMCI alone, 2 runs: 3.0 -> 2.3 s.
#: Both are set, or neither: one alone stops glibc's own adjustment of the other, and was slower than its defaults.
ALLOCATOR = {"mmap_threshold": 32 << 20, "trim_threshold": 256 << 20}
_ALLOCATOR_SET: list = []  # [True] once keep_freed_memory has run in this process (a forked child inherits it)


def keep_freed_memory() -> bool:
    """Set glibc's allocator to :data:`ALLOCATOR` in this process (once; worker processes forked after inherit it).
    Returns whether it was set: False where the C library has no ``mallopt`` (not glibc), and nothing changes there.
    Allocation only: the numbers computed are the same."""
    if not _ALLOCATOR_SET:
        _ALLOCATOR_SET.append(False)
        try:
            import ctypes

            libc = ctypes.CDLL("libc.so.6")
            M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # malloc.h
            _ALLOCATOR_SET[0] = bool(libc.mallopt(M_MMAP_THRESHOLD, ALLOCATOR["mmap_threshold"])
                                     and libc.mallopt(M_TRIM_THRESHOLD, ALLOCATOR["trim_threshold"]))
        except (OSError, AttributeError):  # no glibc
            pass
    return _ALLOCATOR_SET[0]


class one_blas_thread:
    """A context and decorator: BLAS and LAPACK on one thread inside, the previous limits restored after (and the
    allocator set once per process, :func:`keep_freed_memory`).

    ``with one_blas_thread(): ...`` or ``@one_blas_thread()``; every BLAS library is limited (threadpoolctl),
    also in the threads of :func:`thread_pool` and in worker processes forked inside.  SciPy's own
    OpenBLAS is loaded first (with ``import scipy.linalg``, unless the environment already makes every
    library load on one thread) so that it is limited too.  Nested contexts (a public function calling
    another, from any thread) limit once: only the outermost restores.
    """

    _depth = 0
    _lock = threading.Lock()
    _limits = None

    def __enter__(self):
        cls = one_blas_thread
        with cls._lock:
            cls._depth += 1
            if cls._depth == 1:
                keep_freed_memory()
                if "scipy.linalg" not in sys.modules and os.environ.get("OPENBLAS_NUM_THREADS") != "1":
                    import scipy.linalg  # noqa: F401
                from threadpoolctl import threadpool_limits

                cls._limits = threadpool_limits(limits=1, user_api="blas")
        return self

    def __exit__(self, *exc) -> None:
        cls = one_blas_thread
        with cls._lock:
            cls._depth -= 1
            if cls._depth == 0 and cls._limits is not None:
                cls._limits.restore_original_limits()
                cls._limits = None

    def __call__(self, fn):
        @functools.wraps(fn)
        def wrapped(*args, **kwargs):
            with one_blas_thread():
                return fn(*args, **kwargs)

        return wrapped


def _fresh_lock() -> None:
    one_blas_thread._lock = threading.Lock()  # a child forked while another thread held it gets a free one


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_fresh_lock)
