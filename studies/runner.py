"""One Monte Carlo runner for every study and sweep: chunks of runs, three backends, resumable.

A study describes its Monte Carlo work as a **task**: a picklable callable
``task(run_ids, seeds) -> {name: array}`` that computes the runs ``run_ids``
(consecutive integers) from their seeds and returns arrays whose first axis is
the run (length ``len(run_ids)``).  Run ``r`` of a study with seed ``s`` always
gets ``SeedSequence(s, spawn_key=(r,))`` — the same as
``SeedSequence(s).spawn(n)[r]`` for any ``n > r`` — so a run's random numbers do
not depend on the number of runs, of chunks or of workers.

The runs are cut into **chunks** of at most ``chunk_size`` consecutive runs (as equal as whole runs allow); the cut
depends only on ``runs`` and ``chunk_size`` (a property of the study, never of
the backend), so a task that is deterministic given its inputs gives the same
bits with every backend:

* ``Backend("batched")`` — every chunk in this process, one after the other
  (each chunk is one batched computation);
* ``Backend("processes", workers=N)`` — ``N`` local worker processes (``fork``:
  they inherit what the parent has compiled or imported);
* ``Backend("dask", address=A)`` — the chunks are submitted to the existing Dask
  distributed scheduler at ``A`` (e.g. ``tcp://10.0.0.5:8786``).

**Resumable and loss-free.**  With a ``store`` directory, every finished chunk is
written at once, atomically (a temporary file renamed over the target), by the
parent process only, as ``store/.chunks/<label>/runs_<start>_<stop>.npz``, and a
line is appended to ``log.jsonl`` there.  ``manifest.json`` records what the
chunks were computed with (``config``, seed, chunk size).  A second call with the
same configuration loads the finished chunks and computes only the missing ones,
so an interrupted study (Ctrl-C, a killed worker) resumes where it stopped; a
different configuration is refused (it would mix results) unless ``force=True``,
which deletes the stored chunks and recomputes everything.  ``force`` deletes only what the
store wrote (its ``manifest.json``, ``log.jsonl`` and ``runs_<start>_<stop>.npz`` files);
any other file in the store's directory stays.  The store holds the directory's one-writer
lock (:func:`designer.fileio.output_lock`) while it works, and never reads, writes or removes
its files through a symbolic link: a link in place of the store, of its directory or of one
of its files is refused (InputError naming it).

**Verified.**  A stored chunk is used only if it proves what it is: every chunk file holds,
beside its arrays, the fingerprint of everything that determines it (the manifest: study,
configuration, seed, chunk size, and :func:`designer.fileio.code_fingerprint` of the code)
with its run range, and a SHA-256 checksum of its arrays (names, dtypes, shapes, bytes).  On
loading, the fingerprint, the run range, every array's row count and the checksum are
checked; a chunk that fails any of them (or cannot be read) is named with what differs
(:attr:`MonteCarloResult.rejected`, and a line on stderr) and recomputed, never
reused, so neither a deleted manifest, a chunk copied from another run or another
configuration, nor an edited or truncated file can enter the results.  The checksum detects
corruption and mixing, not a forger who recomputes it.  The arrays returned always hold
exactly one row per run (checked).

**Gathered as they come.**  A chunk's per-run arrays are written into the rows of the runs' arrays as the chunk
finishes (no chunk is kept, nothing is concatenated), so the parent holds the runs' results once.  An output named
``SUMMED + name`` (one row per run, as every output) is kept only as its sum over the runs (``SUMMED + name`` of the
result, without the run axis: what a study needs of an array too large to keep run by run, such as the bounds Φ):
the rows are added one run after the other in run order, whatever order the chunks finish in, so the sum is the
same bit for bit whatever the chunks, workers or backend (a chunk that comes early waits for those before it).

**Failures are reported, not swallowed.**  When a chunk raises, the runner
recomputes its runs one at a time to find the failing run and raises
:class:`RunFailed` naming the run, its seed and spawn key and the original error;
the chunks finished before are kept.
"""
from __future__ import annotations

import contextlib
import functools
import gc
import hashlib
import json
import math
import os
import pickle
import re
import select
import signal
import sys
import threading
import time
import warnings
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple

import multiprocessing
import numpy as np

from designer.fileio import (CHUNKS_DIR, append_line, atomic_write, code_fingerprint, open_own, own_dir,
                             refuse_link, temporary_of, write_json, writing)
from designer.progress import counter, line, progress
from designer.validation import ComputationError, InputError, check_int

from .interrupts import Interrupts
from .memory import available_memory

__all__ = ["SUMMED", "Backend", "Timed", "run_forked", "make_backend", "every_core", "load_security", "run_seed",
           "chunk_ranges",
           "monte_carlo", "MonteCarloResult", "RunFailed", "CHUNKS_DIR"]

_MANIFEST_SCHEMA = "cfdesign.chunks/2"
SUMMED = "summed_"  # a task's output named SUMMED + name is kept as its sum over the runs, added in run order
_META = "__cfdesign_chunk__"  # the entry of a chunk file that says what it is
BACKENDS = ("batched", "processes", "dask")

Task = Callable[[np.ndarray, list], Mapping[str, np.ndarray]]


class RunFailed(ComputationError):
    """A Monte Carlo run raised; ``run``, ``seed`` and ``spawn_key`` reproduce it."""

    def __init__(self, message: str, run: int | None = None, seed: int | None = None,
                 spawn_key: tuple | None = None):
        super().__init__(message)
        self.run, self.seed, self.spawn_key = run, seed, spawn_key

    def __reduce__(self):  # keep the fields across processes and Dask
        return (RunFailed, (str(self), self.run, self.seed, self.spawn_key))


@dataclass(frozen=True)
class Backend:
    """Where the chunks run: ``batched`` (this process), ``processes`` (``workers``) or ``dask`` (``address``)."""

    kind: str = "batched"
    workers: int = 1
    address: str | None = None
    security: str | None = None  # Dask: a JSON file of distributed.Security's TLS options (see load_security)

    def __post_init__(self):
        if self.kind not in BACKENDS:
            raise InputError(f"backend must be one of {', '.join(BACKENDS)}, got {self.kind!r}")
        check_int("workers", self.workers, 1)
        if self.kind == "dask" and not self.address:
            raise InputError("dask backend needs a scheduler address (e.g. tcp://host:8786)")
        if self.security is not None:
            if self.kind != "dask":
                raise InputError("dask_security applies to a Dask scheduler only (give --dask ADDRESS)")
            load_security(self.security)  # checked now, before any computation

    def describe(self) -> dict:
        return {"backend": self.kind, "workers": self.workers if self.kind == "processes" else None,
                "dask_address": self.address, "dask_tls": self.security is not None}


SECURITY_KEYS = ("tls_ca_file", "tls_client_cert", "tls_client_key", "require_encryption")


def load_security(path) -> dict:
    """The TLS options of ``distributed.Security`` from a JSON file, checked.

    The file is a JSON object with ``tls_ca_file``, ``tls_client_cert``, ``tls_client_key``
    (paths to PEM files; relative paths are relative to the file) and ``require_encryption``
    (true or false), e.g. ``{"tls_ca_file": "ca.pem", "tls_client_cert": "client.pem",
    "tls_client_key": "client.key", "require_encryption": true}``; the scheduler's address
    is then ``tls://host:port``.  TLS authenticates the scheduler and encrypts the traffic;
    results still come back through Dask's pickle protocol, so the scheduler and its
    workers must be trusted.
    """
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except OSError as exc:
        raise InputError(f"dask_security: cannot read {str(p)!r} ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise InputError(f"dask_security: {str(p)!r} is not valid JSON ({exc})") from None
    if not isinstance(data, dict) or not data:
        raise InputError(f"dask_security: {str(p)!r} must hold a JSON object with some of {', '.join(SECURITY_KEYS)}")
    unknown = sorted(set(data) - set(SECURITY_KEYS))
    if unknown:
        raise InputError(f"dask_security: unknown key {unknown[0]!r} in {str(p)!r}; allowed: {', '.join(SECURITY_KEYS)}")
    out = {}
    for k, v in data.items():
        if k == "require_encryption":
            if not isinstance(v, bool):
                raise InputError(f"dask_security: require_encryption must be true or false, got {v!r}")
            out[k] = v
            continue
        f = Path(v) if isinstance(v, str) else None
        if f is None:
            raise InputError(f"dask_security: {k} must be a path to a PEM file, got {v!r}")
        f = f if f.is_absolute() else p.parent / f
        if not f.is_file():
            raise InputError(f"dask_security: {k} file {str(f)!r} does not exist")
        out[k] = str(f)
    return out


def make_backend(workers: int | None = None, dask: str | None = None, dask_security: str | None = None) -> Backend:
    """The backend of the CLI options ``--workers N`` and ``--dask ADDRESS`` (mutually exclusive),
    with ``--dask-security FILE`` (TLS options, :func:`load_security`) for the Dask scheduler.

    Neither, or ``workers == 1``: batched in this process.
    """
    if workers is not None and dask is not None:
        raise InputError("options --workers and --dask exclude each other (local processes or a Dask cluster)")
    if dask is not None:
        if not isinstance(dask, str) or not dask.strip():
            raise InputError(f"dask must be a scheduler address such as tcp://host:8786, got {dask!r}")
        return Backend("dask", address=dask.strip(), security=dask_security)
    if dask_security is not None:
        raise InputError("--dask-security applies to a Dask scheduler only (give --dask ADDRESS)")
    if workers is None:
        return Backend("batched")
    workers = check_int("workers", workers, 1)
    return Backend("batched") if workers == 1 else Backend("processes", workers=workers)


def every_core() -> Backend:
    """A worker process per usable core (:func:`designer.cores.usable_cores`), or this process when it may use one
    core only: the default of the commands whose chunks cost seconds each (a comparison study, a feasibility map)."""
    from designer.cores import usable_cores

    cores = usable_cores()
    return Backend("processes", workers=cores) if cores > 1 else Backend()


def run_seed(seed: int, run: int) -> np.random.SeedSequence:
    """Run ``run``'s seed: ``SeedSequence(seed, spawn_key=(run,))`` (= ``SeedSequence(seed).spawn(n)[run]``)."""
    return np.random.SeedSequence(seed, spawn_key=(int(run),))


def chunk_ranges(runs: int, chunk_size: int) -> list[tuple[int, int]]:
    """``[(start, stop), ...]`` covering ``0..runs`` in ``ceil(runs / chunk_size)`` pieces of at most ``chunk_size``,
    as equal as whole runs allow (their sizes differ by at most one, the larger first: 10 runs in pieces of 3 are
    3, 3, 2, 2, not 3, 3, 3, 1, so that two workers finish together)."""
    runs = check_int("runs", runs, 1)
    chunk_size = check_int("chunk_size", chunk_size, 1)
    count = -(-runs // chunk_size)
    cuts = [c * (runs // count) + min(c, runs % count) for c in range(count + 1)]
    return list(zip(cuts[:-1], cuts[1:]))


def _check_output(out, start: int, stop: int) -> dict:
    if not isinstance(out, Mapping) or not out:
        raise ComputationError(f"a Monte Carlo task must return a non-empty mapping of arrays, got "
                               f"{type(out).__name__} for runs {start}..{stop - 1}")
    arrays = {}
    for k, v in out.items():
        a = np.asarray(v)
        if str(k).startswith(SUMMED) and not np.issubdtype(a.dtype, np.number):
            raise ComputationError(f"task output {k!r} (kept as its sum over the runs) must be numeric, got dtype "
                                   f"{a.dtype} for runs {start}..{stop - 1}")
        if a.ndim == 0 or a.shape[0] != stop - start or a.dtype == object:
            raise ComputationError(f"task output {k!r} must be a numeric array with one row per run "
                                   f"({stop - start}), got shape {a.shape} dtype {a.dtype}")
        arrays[str(k)] = a
    return arrays


def _compute(task: Task, start: int, stop: int, seed: int, share: tuple[int, int] | None = None) -> dict:
    """One chunk (with ``share`` ``(k, s)``: its k-th of s shares, :func:`monte_carlo`'s ``shares``); on failure,
    find the failing run by recomputing the runs one at a time."""
    call = task if share is None else functools.partial(task, share=share)
    try:
        return _check_output(call(np.arange(start, stop), [run_seed(seed, r) for r in range(start, stop)]),
                             start, stop)
    except (KeyboardInterrupt, SystemExit, RunFailed):
        raise
    except Exception as exc:  # noqa: BLE001 - re-raised with the run that fails
        first = exc
    for r in range(start, stop):
        try:
            _check_output(call(np.arange(r, r + 1), [run_seed(seed, r)]), r, r + 1)
        except Exception as exc:  # noqa: BLE001
            raise RunFailed(f"run {r} failed (seed {seed}, spawn key ({r},)): {type(exc).__name__}: {exc}",
                            run=r, seed=seed, spawn_key=(r,)) from exc
    raise RunFailed(f"runs {start}..{stop - 1} failed together (seed {seed}) but each alone succeeds: "
                    f"{type(first).__name__}: {first}", run=None, seed=seed, spawn_key=None) from first


@dataclass
class MonteCarloResult:
    """The runs' arrays concatenated in run order, and how they were obtained."""

    arrays: dict[str, np.ndarray]
    computed: list[tuple[int, int]] = field(default_factory=list)  # chunks computed by this call
    reused: list[tuple[int, int]] = field(default_factory=list)  # chunks loaded from the store
    backend: Backend = Backend()
    chunk_size: int = 1
    wall_time_s: float = 0.0
    rejected: list[dict] = field(default_factory=list)  # stored chunks not reused: {"runs": [start, stop], "reason"}
    shares: int = 1  # each computed chunk's shares (monte_carlo's shares)

    def describe(self) -> dict:
        """For ``results.json``: backend, chunking and what was resumed (not part of the numbers)."""
        return {**self.backend.describe(), "chunk_size": self.chunk_size, "shares": self.shares,
                "chunks": len(self.computed) + len(self.reused), "chunks_computed": len(self.computed),
                "chunks_reused": len(self.reused), "chunks_rejected": list(self.rejected),
                "wall_time_s": self.wall_time_s}

    @property
    def runs(self) -> int:
        """The number of runs the arrays hold (one row each)."""
        return int(next(iter(self.arrays.values())).shape[0])


def checksum(arrays: Mapping[str, np.ndarray]) -> str:
    """SHA-256 of a chunk's arrays: names, dtypes, shapes and bytes, in name order."""
    h = hashlib.sha256()
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        h.update(json.dumps([k, a.dtype.str, list(a.shape)]).encode() + b"\0")
        h.update(a.tobytes())
    return h.hexdigest()


def _fingerprint(manifest: Mapping[str, Any]) -> str:
    return hashlib.sha256(json.dumps(manifest, sort_keys=True).encode()).hexdigest()


_FORCE = "--force (force=True from Python)"  # how a caller of the command line or of the API recomputes
_OWN = re.compile(r"manifest\.json|log\.jsonl|runs_\d{7,}_\d{7,}\.npz")  # the names the store gives its files


def _settings_differ(where: Path, old: Mapping, new: Mapping) -> InputError:
    """The refusal of a store computed with other settings, naming every key that differs."""
    keys = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
    was = old.get("config") if isinstance(old.get("config"), dict) else {}
    diff = keys if "config" not in keys else keys + sorted(
        f"config.{k}" for k in set(was) | set(new["config"]) if was.get(k) != new["config"].get(k))
    hints = [h for key, h in (("config.model", "the model changed since these runs were computed"),
                              ("code", "the code changed since they were computed")) if key in diff]
    return InputError(f"{where} holds runs computed with other settings ({', '.join(diff)}); "
                      + "".join(h + "; " for h in hints)
                      + f"use {_FORCE} to recompute them or choose another output directory")


class _Store:
    """The chunk files of one task under ``store/.chunks/<label>``; only the parent process writes.

    Created with the store's lock held (:func:`monte_carlo`).  Its directories and files are
    never used through a link (refused by name); ``force`` removes only the files it names
    itself (``_OWN``), and temporary files that a killed writer left are removed.
    """

    def __init__(self, root: Path, label: str, manifest: dict, force: bool):
        self.dir = own_dir(own_dir(Path(root) / CHUNKS_DIR) / label)
        self.fingerprint = _fingerprint(manifest)
        path = self.dir / "manifest.json"
        self._clean(force)
        try:
            with open_own(path) as fh:
                raw = fh.read()
        except FileNotFoundError:
            write_json(path, manifest)
            return
        except OSError as exc:
            raise InputError(f"cannot read {path} ({exc}); use {_FORCE} to recompute") from exc
        try:
            old = json.loads(raw)
        except ValueError as exc:
            raise InputError(f"cannot read {path} ({exc}); use {_FORCE} to recompute") from exc
        if not isinstance(old, dict):
            raise InputError(f"cannot read {path} (not a JSON object); use {_FORCE} to recompute")
        if old != manifest:
            raise _settings_differ(self.dir, old, manifest)

    def _clean(self, force: bool) -> None:
        """Remove the temporary files of a killed writer and, with ``force``, the store's own files (no other)."""
        with os.scandir(self.dir) as it:
            entries = list(it)
        for e in entries:
            own = _OWN.fullmatch(e.name) is not None
            if (own or temporary_of(e.name) is not None) and e.is_symlink():
                refuse_link(e.path)
            stale = temporary_of(e.name)
            if (force and own or stale is not None and _OWN.fullmatch(stale)) and e.is_file(follow_symlinks=False):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(e.path)

    def file(self, c: tuple[int, int]) -> Path:
        return self.dir / f"runs_{c[0]:07d}_{c[1]:07d}.npz"

    def load(self, c: tuple[int, int]) -> tuple[dict | None, str | None]:
        """``(arrays, None)`` for a chunk that proves to be chunk ``c`` of this store, else ``(None, why)``
        (``(None, None)``: not there)."""
        f = self.file(c)
        try:
            fh = open_own(f)  # a link: refused by name
        except FileNotFoundError:
            return None, None
        except OSError as exc:
            return None, f"unreadable ({type(exc).__name__}: {exc})"
        try:
            with fh, np.load(fh, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except Exception as exc:  # noqa: BLE001 - whatever the file holds, it is not a chunk
            return None, f"unreadable ({type(exc).__name__}: {exc})"
        meta = arrays.pop(_META, None)
        try:
            info = json.loads(meta.tobytes().decode()) if meta is not None else None
        except (ValueError, UnicodeDecodeError):
            info = None
        if not isinstance(info, dict):
            return None, "it carries no fingerprint (written by another version, or not by cfdesign)"
        if info.get("fingerprint") != self.fingerprint:
            return None, "its fingerprint differs: it was computed with another configuration, seed or code"
        if info.get("runs") != list(c):
            return None, f"it holds runs {info.get('runs')}, not {list(c)}"
        rows = {k: (a.shape[0] if a.ndim else None) for k, a in arrays.items()}
        wrong = sorted(k for k, r in rows.items() if r != c[1] - c[0])
        if not arrays or wrong:
            return None, (f"array {wrong[0]!r} has {rows[wrong[0]]} rows, not {c[1] - c[0]}" if wrong else "no arrays")
        if info.get("checksum") != checksum(arrays):
            return None, "its checksum does not match its arrays (the file was changed)"
        return arrays, None

    def save(self, c: tuple[int, int], arrays: dict) -> None:
        meta = json.dumps({"fingerprint": self.fingerprint, "runs": list(c), "checksum": checksum(arrays)})
        atomic_write(self.file(c), lambda fh: np.savez(fh, **arrays, **{_META: np.frombuffer(meta.encode(),
                                                                                          np.uint8)}))
        append_line(self.dir / "log.jsonl", json.dumps({"chunk": list(c), "pid": os.getpid(), "time": time.time()}))


def _normalised(config: Mapping[str, Any]) -> dict:
    try:
        return json.loads(json.dumps(dict(config), sort_keys=True, default=str))
    except (TypeError, ValueError) as exc:
        raise InputError(f"config must be JSON-serialisable, got {exc}") from exc


def fork_worker(parent: int) -> int:
    """``os.fork()``; in the child, Ctrl-C is the parent's and the child dies with it (:func:`worker_init`).

    The child never collects garbage (it computes or draws, then ends with ``os._exit``): a collection
    would write into the header of every object it inherited, and so copy nearly all of the
    parent's memory page by page.  Its inherited objects are frozen too (``gc.freeze`` around
    the fork; the parent's are unfrozen at once), so that not even an explicit collection in
    the child visits them.
    """
    sys.stdout.flush()
    sys.stderr.flush()
    gc.freeze()
    try:
        with warnings.catch_warnings():  # Python 3.12+ warns of forking with threads; the child uses none it inherits
            warnings.simplefilter("ignore", DeprecationWarning)
            pid = os.fork()
    except BaseException:
        gc.unfreeze()
        raise
    if pid == 0:  # pragma: no cover - the child (coverage does not follow it)
        gc.disable()
        worker_init(parent)
    else:
        gc.unfreeze()
    return pid


class Background:
    """``fn(*args, **kwargs)`` computed in a forked child process while this one goes on; :meth:`result` returns it.

    For the parts of one command that do not depend on each other (the scheduled design's stationary certificate
    and its other exchange rounds beside its tables and seeded run): on a machine with one usable core, where the
    platform does not fork, or when the child fails for any reason (an exception, killed, a result that does not
    pickle), :meth:`result` computes the call here instead, so the value, and any exception, are those of a
    call in this process; the numbers do not depend on where they were computed.  The warnings the child's call
    raised are raised again here, through this process's filters.  Used as a context manager, the child is killed
    when the block ends without :meth:`result` having been called (an exception, Ctrl-C).
    """

    def __init__(self, fn: Callable, *args, **kwargs):
        from designer.cores import usable_cores

        self._fn, self._args, self._kwargs, self._pid, self._fd = fn, args, kwargs, None, None
        if usable_cores() < 2 or not sys.platform.startswith("linux"):
            return
        parent = os.getpid()
        r, w = os.pipe()
        try:
            pid = fork_worker(parent)
        except OSError:  # no more processes: computed here
            os.close(r)
            os.close(w)
            return
        if pid == 0:  # pragma: no cover - the child
            try:
                os.close(r)
                with warnings.catch_warnings(record=True) as caught:  # this process's filters, inherited
                    value = fn(*args, **kwargs)
                payload = pickle.dumps((value, [(w_.message, w_.category, w_.filename, w_.lineno) for w_ in caught]))
                with os.fdopen(w, "wb") as fh:
                    fh.write(payload)
            finally:
                os._exit(0)
        os.close(w)
        self._pid, self._fd = pid, r

    @property
    def pid(self) -> int | None:
        """The child's process id while it computes (None: computed here, or its result taken)."""
        return self._pid

    def result(self):
        """The value of ``fn(*args, **kwargs)``: the child's, or computed here (see the class)."""
        if self._pid is None:
            return self._fn(*self._args, **self._kwargs)
        fd, self._fd = self._fd, None  # closed by the reader whatever happens (a Ctrl-C while reading)
        with os.fdopen(fd, "rb") as fh:
            while not select.select([fh], [], [], 1.0)[0]:  # the child still computing: a progress line when due
                line()
            payload = fh.read()
        os.waitpid(self._pid, 0)
        self._pid = None
        try:
            value, caught = pickle.loads(payload)
        except Exception:  # noqa: BLE001 - the child failed (its exception, if any, is raised by the call here)
            return self._fn(*self._args, **self._kwargs)
        for message, category, filename, lineno in caught:
            warnings.warn_explicit(message, category, filename, lineno)
        return value

    def __enter__(self) -> "Background":
        return self

    def __exit__(self, *exc) -> None:
        if self._pid is not None:
            os.kill(self._pid, signal.SIGKILL)
            os.waitpid(self._pid, 0)
            self._pid = None
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


class Timed(NamedTuple):
    """One call of :func:`run_forked`: ``status`` ``'done'`` (``value`` is its result), ``'failed'`` (``value`` is
    the exception's text) or ``'timeout'`` (it did not end before the deadline: ``value`` is None); ``seconds`` its
    wall time (up to the deadline)."""

    status: str
    value: Any
    seconds: float


#: How often (seconds) :func:`run_forked` looks up from waiting for its children (to write a progress line).
_POLL_S = 1.0


def run_forked(calls: list[Callable[[], Any]], *, workers: int | None = None,
               deadline: float | None = None, on_done: Callable[[int, "Timed"], None] | None = None,
               desc: str = "computed") -> list[Timed]:
    """Each of ``calls`` (functions of no argument) computed in a forked child, at most ``workers`` at once (default:
    :func:`designer.cores.usable_cores`), in their order; a call still running at ``deadline`` (a
    ``time.monotonic()`` instant) is killed, and one not started by then is not started (both ``'timeout'``).

    For independent computations of one command that may be too slow to wait for (the candidates of an automatic
    design, :mod:`studies.auto`).  Each child sends its result back pickled through a pipe (read as it arrives, so
    a large result never blocks it); a child that raised, died or sent what does not unpickle is ``'failed'``.  With
    one usable core or where the platform does not fork, the calls run here one after the other (a call started
    before the deadline runs to its end).  The numbers do not depend on where they were computed.  ``on_done(j,
    timed)`` is called as each call ends (a progress bar's tick), in the order they end.  While it waits it writes a
    progress line when one is due (:func:`designer.progress.line`): ``desc`` and how many calls ended.
    """
    import select

    from designer.cores import usable_cores

    workers = usable_cores() if workers is None else max(1, int(workers))
    out: list[Timed | None] = [None] * len(calls)
    if workers < 2 or not sys.platform.startswith("linux"):
        for j, call in enumerate(calls):
            t0 = time.monotonic()
            if deadline is not None and t0 >= deadline:
                out[j] = Timed("timeout", None, 0.0)
                continue
            try:
                out[j] = Timed("done", call(), time.monotonic() - t0)
            except (InputError, ComputationError, ArithmeticError, ValueError, MemoryError) as exc:
                out[j] = Timed("failed", f"{type(exc).__name__}: {exc}", time.monotonic() - t0)
            if on_done is not None:
                on_done(j, out[j])
        return out  # type: ignore[return-value]
    parent, pending, running = os.getpid(), list(range(len(calls))), {}  # fd -> (j, pid, chunks, start)
    try:
        while pending or running:
            now = time.monotonic()
            while pending and len(running) < workers:
                j = pending.pop(0)
                if deadline is not None and now >= deadline:
                    out[j] = Timed("timeout", None, 0.0)
                    continue
                r, w = os.pipe()
                pid = fork_worker(parent)
                if pid == 0:  # pragma: no cover - the child
                    try:
                        os.close(r)
                        try:
                            payload = pickle.dumps(("done", calls[j]()))
                        except BaseException as exc:  # noqa: BLE001 - reported to the parent as the call's failure
                            payload = pickle.dumps(("failed", f"{type(exc).__name__}: {exc}"))
                        with os.fdopen(w, "wb") as fh:
                            fh.write(payload)
                    finally:
                        os._exit(0)
                os.close(w)
                running[r] = (j, pid, [], now)
            if not running:
                continue
            wait_s = _POLL_S if deadline is None else min(_POLL_S, max(0.0, deadline - time.monotonic()))
            ready, _, _ = select.select(list(running), [], [], wait_s)
            line(desc, sum(o is not None for o in out), len(calls))  # a progress line, when one is due
            if not ready and deadline is not None and time.monotonic() >= deadline:
                for fd, (j, pid, _, start) in list(running.items()):
                    os.kill(pid, signal.SIGKILL)
                    os.waitpid(pid, 0)
                    os.close(fd)
                    out[j] = Timed("timeout", None, time.monotonic() - start)
                    del running[fd]
                    if on_done is not None:
                        on_done(j, out[j])
                continue
            for fd in ready:
                j, pid, chunks, start = running[fd]
                data = os.read(fd, 1 << 20)
                if data:
                    chunks.append(data)
                    continue
                os.close(fd)
                os.waitpid(pid, 0)
                del running[fd]
                try:
                    status, value = pickle.loads(b"".join(chunks))
                except Exception:  # noqa: BLE001 - the child died before sending a result
                    status, value = "failed", "the process computing it ended without a result"
                out[j] = Timed(status, value, time.monotonic() - start)
                if on_done is not None:
                    on_done(j, out[j])
    finally:
        for fd, (j, pid, _, _) in running.items():  # an exception or Ctrl-C here: no child lives on
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            os.close(fd)
    return out  # type: ignore[return-value]


def worker_init(parent: int) -> None:
    """A worker process: Ctrl-C is the parent's to handle, and the worker dies with its parent.

    However the parent ends (SIGKILL, SIGTERM, a crash), its workers must not live on: blocked
    on a pipe write they would hold the caller's stdout and stderr open.  On Linux the kernel
    sends SIGKILL to the worker when the parent dies (``PR_SET_PDEATHSIG``); everywhere a
    watchdog thread ends the worker within half a second of being orphaned (its parent PID changes).
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):  # not Linux: the watchdog alone
        pass
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(1)

    def watch():
        while True:
            time.sleep(0.5)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="cfdesign-parent-watchdog", daemon=True).start()


def monte_carlo(
    task: Task,
    *,
    runs: int,
    seed: int,
    chunk_size: int,
    backend: Backend | None = None,
    store: str | Path | None = None,
    label: str = "runs",
    config: Mapping[str, Any] | None = None,
    force: bool = False,
    quiet: bool = False,
    unit: str = "Monte Carlo runs",
    shares: int = 1,
) -> MonteCarloResult:
    """Run ``task`` on runs ``0..runs-1`` in chunks and return their arrays in run order.

    Parameters
    ----------
    task : callable ``(run_ids (n,), seeds [SeedSequence] * n) -> {name: array (n, ...)}``
        Must be picklable for the ``processes`` and ``dask`` backends (a module-level
        function, or ``functools.partial`` of one with picklable arguments) and
        deterministic given its arguments.
    runs, seed, chunk_size : int
        ``chunk_size`` is part of the study (it fixes the cut into chunks); never derive
        it from the backend, or results would depend on it.
    backend : Backend, optional
        Default: batched in this process.
    store : path, optional
        Directory under which finished chunks are kept (``.chunks/<label>``); None keeps
        nothing (no resume).
    config : mapping
        JSON-serialisable description of everything the runs depend on besides seed and
        run index (scenario parameters, particles, filters...); stored chunks computed with
        another config are refused unless ``force``.
    force : bool
        Delete the stored chunks first (only the files the store wrote) and recompute every run.
    unit : str
        What the progress shows the runs as (a feasibility map's are its grid points).
    shares : int
        Into how many shares the task can cut a chunk's work (say one per filter it runs): with ``shares`` > 1 it
        takes ``share=(k, s)``, its k-th of s shares (s <= ``shares``), whose outputs together are the chunk's (an
        output that several shares return, such as the runs' truth, must be the same in each: checked).  The
        ``processes`` backend cuts each chunk into the fewest shares that make the pieces of work a multiple of
        its workers (:func:`split_into`), so that the last chunk does not compute alone while the other cores idle
        (a design's validation: 5 runs of a 118-bus grid in chunks of 2, 2 and 1 on 2 cores); other backends
        compute whole chunks.  The numbers do not depend on it: a chunk's outputs are the same whatever its shares
        (the task's contract), and the store keeps whole chunks.
    """
    runs = check_int("runs", runs, 1)
    seed = check_int("seed", seed, 0)
    ranges = chunk_ranges(runs, chunk_size)
    backend = backend or Backend()
    if not isinstance(backend, Backend):
        raise InputError(f"backend must be a Backend, got {type(backend).__name__}")
    if not isinstance(label, str) or not label or "/" in label or label.startswith("."):
        raise InputError(f"label must be a plain non-empty name, got {label!r}")
    with writing(store, name="store", replaces=()):  # the store's one-writer lock (held already under a command)
        return _monte_carlo(task, runs, seed, ranges, int(chunk_size), backend, store, label, config, force, quiet,
                            unit, check_int("shares", shares, 1))


def _monte_carlo(task, runs, seed, ranges, chunk_size, backend, store, label, config, force, quiet,
                 unit, shares) -> MonteCarloResult:
    t0 = time.perf_counter()
    st = None
    if store is not None:
        manifest = {"schema": _MANIFEST_SCHEMA, "label": label, "seed": seed, "chunk_size": chunk_size,
                    "config": _normalised(config or {}), "code": code_fingerprint()}
        st = _Store(Path(store), label, manifest, force)
    done = _Gather(ranges, runs)
    reused, rejected = [], []
    if st is not None:
        for c in ranges:
            arrays, why = st.load(c)
            if arrays is not None:
                done.add(c, arrays, stored=True)
                reused.append(c)
            elif why is not None:
                rejected.append({"runs": [c[0], c[1]], "reason": why})
                print(f"cfdesign: stored chunk {st.file(c)} (runs {c[0]}..{c[1] - 1}) not reused: {why}; "
                      "recomputing it", file=sys.stderr)
    pending = [c for c in ranges if c not in reused]
    computed: list[tuple[int, int]] = []

    sized = []

    def finish(c, arrays):
        interrupts.check()
        if not sized:
            sized.append(_check_memory(arrays, c, runs))
        if st is not None:
            st.save(c, arrays)
        done.add(c, arrays)
        computed.append(c)

    # not the label (the study's name): a design's validation runs study consensus-robot on the user's model
    bar_desc = f"{unit} ({len(pending)} of {len(ranges)} chunks)"
    cut = split_into(shares, len(pending), backend.workers) if backend.kind == "processes" else 1
    with Interrupts() as interrupts:
        if not pending:
            pass
        elif backend.kind == "processes" and (len(pending) > 1 or cut > 1):
            _run_processes(task, pending, seed, backend.workers, finish, quiet, bar_desc, cut)
        elif backend.kind in ("batched", "processes"):
            for c in progress(pending, len(pending), quiet, bar_desc):
                finish(c, _compute(task, c[0], c[1], seed))
        else:
            _run_dask(task, pending, seed, backend, finish, quiet, bar_desc)
    return MonteCarloResult(done.result(), computed, reused, backend, chunk_size, time.perf_counter() - t0, rejected,
                            cut if computed else 1)


class _Gather:
    """The chunks' arrays gathered as they finish: per-run arrays written into their runs' rows, the rows of a
    :data:`SUMMED` output added one run after the other in run order (a chunk that comes early waits for the chunks
    before it)."""

    def __init__(self, ranges: list[tuple[int, int]], runs: int):
        self.ranges, self.runs = ranges, runs
        self.keys: list[str] | None = None
        self.rows: dict[str, np.ndarray] = {}
        self.totals: dict[str, np.ndarray] = {}
        self.waiting: dict[tuple[int, int], dict] = {}
        self.filled = 0  # chunks added
        self.summed = 0  # chunks (in run order) whose totals are added

    def add(self, c: tuple[int, int], arrays: Mapping[str, np.ndarray], stored: bool = False) -> None:
        keys = sorted(arrays)
        if self.keys is None:
            self.keys = keys
            self.rows = {k: np.empty((self.runs,) + a.shape[1:], a.dtype) for k, a in arrays.items()
                         if not k.startswith(SUMMED)}
        elif keys != self.keys:
            raise ComputationError(f"chunk {c} has outputs {keys}, expected {self.keys}"
                                   + (f"; use {_FORCE} if the stored chunks are from an older version" if stored
                                      else ""))
        for k, a in arrays.items():
            if k.startswith(SUMMED):
                if a.shape[0] != c[1] - c[0]:
                    raise ComputationError(f"chunk {c}'s {k!r} has {a.shape[0]} rows for {c[1] - c[0]} runs")
                continue
            into = self.rows[k]
            if a.shape[1:] != into.shape[1:]:
                raise ComputationError(f"chunk {c}'s {k!r} has rows of shape {a.shape[1:]}, the chunks before "
                                       f"{into.shape[1:]}")
            if np.result_type(a.dtype, into.dtype) != into.dtype:  # as a concatenation would promote
                self.rows[k] = into = into.astype(np.result_type(a.dtype, into.dtype))
            into[c[0]:c[1]] = a
        self.waiting[c] = {k: a for k, a in arrays.items() if k.startswith(SUMMED)}
        self.filled += 1
        while self.summed < len(self.ranges) and self.ranges[self.summed] in self.waiting:
            for k, a in self.waiting.pop(self.ranges[self.summed]).items():
                for row in a:  # one run after the other: the same bits whatever the chunks
                    if k not in self.totals:
                        self.totals[k] = np.array(row, dtype=np.result_type(row.dtype, np.float64), copy=True)
                    elif self.totals[k].shape != row.shape:
                        raise ComputationError(f"chunk {c}'s rows of {k!r} have shape {row.shape}, the runs before "
                                               f"{self.totals[k].shape}")
                    else:
                        self.totals[k] += row
            self.summed += 1

    def result(self) -> dict[str, np.ndarray]:
        if self.filled != len(self.ranges) or self.summed != len(self.ranges):
            raise ComputationError(f"{self.filled} of {len(self.ranges)} chunks gathered")
        return {**self.rows, **self.totals}


def _check_memory(arrays: Mapping[str, np.ndarray], c: tuple[int, int], runs: int) -> bool:
    """After the first chunk: refuse (InputError) a study whose per-run results cannot fit in memory."""
    rows = sum(a.nbytes for k, a in arrays.items() if not k.startswith(SUMMED))  # kept for every run
    summed = sum(a.nbytes for k, a in arrays.items() if k.startswith(SUMMED))  # a chunk's, then their sum
    need = rows / (c[1] - c[0]) * runs + summed * (1 + 1 / (c[1] - c[0]))
    have = available_memory()
    if have is not None and need > have:
        raise InputError(f"runs = {runs} would hold {need / 1e9:.3g} GB of per-run results, more than the "
                         f"{have / 1e9:.3g} GB of memory available; use fewer runs")
    return True


def split_into(shares: int, chunks: int, workers: int) -> int:
    """The shares each of ``chunks`` chunks is cut into on ``workers`` processes (:func:`monte_carlo`'s ``shares``):
    the fewest that make the pieces of work a multiple of the workers (so that none idles at the end while another
    computes a last chunk alone), at most ``shares``: on 2 workers one for an even number of chunks, two for an odd."""
    return max(1, min(shares, workers // math.gcd(max(chunks, 1), workers))) if workers > 1 else 1


def merge_shares(c: tuple[int, int], parts: list[Mapping[str, np.ndarray]]) -> dict:
    """A chunk's outputs from its shares' (:func:`monte_carlo`'s ``shares``): their union, an output several shares
    return being the same in each (else the task's shares are not one chunk's work: ComputationError)."""
    out: dict = {}
    for part in parts:
        for k, a in part.items():
            if k not in out:
                out[k] = a
            elif not (a.shape == out[k].shape and np.array_equal(a, out[k], equal_nan=a.dtype.kind in "fc")):
                raise ComputationError(f"the shares of runs {c[0]}..{c[1] - 1} return different {k!r}: a task's "
                                       "shares must compute the same numbers where they overlap")
    return out


def _run_processes(task, pending, seed, workers, finish, quiet, desc, shares: int = 1) -> None:
    items = [(c, k) for c in pending for k in range(shares)]  # a chunk's shares one after the other
    pool = ProcessPoolExecutor(max_workers=min(workers, len(items)),
                               mp_context=multiprocessing.get_context("fork"), initializer=worker_init,
                               initargs=(os.getpid(),))
    futures, got = {}, {}
    if shares > 1:
        desc = f"{desc[:-1]}, each in {shares} shares)" if desc.endswith(")") else f"{desc} ({shares} shares each)"
    try:
        futures = {pool.submit(_compute, task, c[0], c[1], seed, None if shares == 1 else (k, shares)): (c, k)
                   for c, k in items}
        left = set(futures)
        bar = counter(len(items), quiet, desc)
        while left:
            finished, left = wait(left, timeout=1.0, return_when=FIRST_COMPLETED)
            if not finished:  # the chunks still computing: a progress line when due (not with --quiet)
                if not quiet:
                    line(desc, len(items) - len(left), len(items))
                continue
            for f in sorted(finished, key=lambda f: futures[f]):
                c, k = futures.pop(f)  # the future holds its chunk's arrays: gathered, they go
                try:
                    arrays = f.result()
                except BrokenProcessPool as exc:
                    raise ComputationError(
                        f"a worker process died while computing runs {c[0]}..{c[1] - 1}; the chunks finished "
                        f"before are kept, rerun the same command to resume") from exc
                parts = got.setdefault(c, {})
                parts[k] = arrays
                del arrays
                if len(parts) == shares:
                    del got[c]
                    finish(c, merge_shares(c, [parts[j] for j in range(shares)]))
                bar.update()
            del finished
        bar.close()
    except BaseException:
        for f in futures:
            f.cancel()
        for p in list(getattr(pool, "_processes", {}).values()):  # stop work in flight now, not after it ends
            p.terminate()
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


def _run_dask(task, pending, seed, backend: Backend, finish, quiet, desc) -> None:
    try:
        from distributed import Client, Security, as_completed
    except ImportError as exc:
        raise InputError("--dask needs the 'distributed' package: pip install 'cfdesign[dask]'") from exc
    address = backend.address
    security = None if backend.security is None else Security(**load_security(backend.security))
    try:
        client = Client(address, set_as_default=False, timeout="20s", security=security)
    except (OSError, TimeoutError, TypeError) as exc:  # TypeError: a tls:// address without TLS options
        hint = "; a tls:// scheduler needs --dask-security FILE" if address.startswith("tls://") and \
            security is None else ""
        raise InputError(f"dask: cannot reach a scheduler at {address!r} ({str(exc).splitlines()[0]}){hint}") from exc
    futures = {}
    try:
        with client.as_current():  # as_completed looks for the current client
            futures = {client.submit(_compute, task, c[0], c[1], seed, pure=False): c for c in pending}
            for f in progress(as_completed(list(futures)), len(futures), quiet, desc):
                finish(futures.pop(f), f.result())  # the future holds its chunk's arrays: gathered, they go
    except BaseException:
        client.cancel(list(futures))
        raise
    finally:
        client.close()
