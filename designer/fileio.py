"""File output: atomic files (absent, the old version, or complete), one writer per output directory.

* :func:`atomic_write` writes a temporary file beside the target and renames it over it; the
  file gets the usual permissions (``0666`` less the process's umask, as ``open`` gives).
* :func:`output_lock` holds an OS-level lock (``fcntl.flock``) on ``<directory>/.cfdesign.lock``
  for as long as a command writes into the directory; a second writer is refused at once
  (:class:`designer.validation.InputError`, exit 2) with the holder's PID and command.  The
  lock goes with the process that holds it, however it ends (even SIGKILL).
* :func:`append_line` appends one line to a log in a single ``write`` of an ``O_APPEND``
  descriptor, so concurrent or interrupted appends never interleave or leave half a line.
* :func:`code_fingerprint` hashes the package's own source files: stored results computed by
  another version of the code are recognised as such.
* :func:`replaced_outputs` writes a command's outputs into a staging directory and then
  replaces the outputs of the last command as a whole: a failure leaves the old outputs
  complete, and no file of another command (a stale figure, another study's table) stays
  beside the new ones.  Only files cfdesign listed as its outputs are ever removed.
* :func:`check_json_finite` names the first non-finite number of a results document, so a
  NaN is refused before anything is written.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .validation import InputError

__all__ = ["atomic_write", "write_json", "write_npz", "output_lock", "append_line", "code_fingerprint",
           "check_output_file", "writing", "replaced_outputs", "check_json_finite", "LOCK_NAME", "OUTPUTS_NAME"]

LOCK_NAME = ".cfdesign.lock"
OUTPUTS_NAME = ".cfdesign-outputs.json"  # the files the last command wrote into an output directory


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write(path, write) -> Path:
    """Call ``write(fileobj)`` on a temporary file beside ``path``, then rename it over ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp's 0600 would make every output private
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def _jsonable(obj: Any):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_json(path, data: Any) -> Path:
    text = json.dumps(data, indent=2, default=_jsonable, allow_nan=False)
    return atomic_write(path, lambda fh: fh.write(text.encode() + b"\n"))


def write_npz(path, **arrays) -> Path:
    return atomic_write(path, lambda fh: np.savez_compressed(fh, **arrays))


def check_output_file(name: str, path, suffix: str) -> Path:
    """An output file's path, checked before any computation: ``suffix``, not a directory, a writable place."""
    path = Path(path)
    if path.suffix != suffix:
        raise InputError(f"{name} must be a {suffix} file, got {str(path)!r}")
    if path.is_dir():
        raise InputError(f"{name} must be a {suffix} file, got the existing directory {str(path)!r}")
    parent = next((p for p in [path.parent, *path.parent.parents] if p.exists()), Path("."))
    if not parent.is_dir():
        raise InputError(f"{name}: {str(parent)!r} is a file, not a directory, so {str(path)!r} cannot be written")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{name}: cannot write into {str(parent)!r} (permission denied)")
    return path


def append_line(path, line: str) -> None:
    """Append ``line`` (a newline is added) to ``path`` in one ``write`` of an ``O_APPEND`` descriptor."""
    data = (line.rstrip("\n") + "\n").encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
    try:
        written = os.write(fd, data)
        if written != len(data):  # a full disk: do not leave half a line that a reader would take for one
            os.ftruncate(fd, os.lseek(fd, 0, os.SEEK_END) - written)
            raise OSError(f"could not append to {path} (disk full?)")
    finally:
        os.close(fd)


@contextlib.contextmanager
def output_lock(directory) -> Iterator[Path]:
    """Hold the one-writer lock of ``directory`` (created if missing) for the ``with`` block.

    Raises InputError at once, naming the holder (PID, command, start time), when another
    process holds it.  On platforms without ``fcntl`` nothing is locked.
    """
    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise InputError(f"out must be a directory, got the existing file {str(directory)!r}")
    created = [p for p in [directory, *directory.parents] if not p.exists()]  # what to remove if nothing is written
    try:
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / LOCK_NAME
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as exc:
        raise InputError(f"out: cannot write into {str(directory)!r} ({exc.strerror or exc})") from exc
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        fcntl = None
    try:
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                try:
                    holder = json.loads(os.pread(fd, 65536, 0).decode() or "{}")
                except (OSError, ValueError):
                    holder = {}
                who = (f"process {holder.get('pid', '?')} ({holder.get('command', '?')}, started "
                       f"{holder.get('started', '?')})") if holder else "another process"
                raise InputError(f"out: {str(directory)!r} is being written by {who}; wait for it to finish or "
                                 "choose another --out") from None
        info = json.dumps({"pid": os.getpid(), "command": " ".join([Path(sys.argv[0]).name] + sys.argv[1:])[:500],
                           "started": time.strftime("%Y-%m-%d %H:%M:%S")}).encode()
        os.ftruncate(fd, 0)
        os.pwrite(fd, info, 0)
        yield directory
    except BaseException:
        if created:  # refused or failed before writing anything: leave no empty directory behind
            with contextlib.suppress(OSError):
                if [p.name for p in directory.iterdir()] == [LOCK_NAME]:
                    path.unlink()
                    for p in created:
                        p.rmdir()
        raise
    finally:
        os.close(fd)  # releases the flock


def writing(directory):
    """:func:`output_lock` of ``directory``, or nothing to hold when there is no output directory (None)."""
    return contextlib.nullcontext() if directory is None else output_lock(directory)


_FINGERPRINT: str | None = None


def code_fingerprint() -> str:
    """SHA-256 of the package's source files (``designer``, ``filters``, ``studies``), computed once per process."""
    global _FINGERPRINT
    if _FINGERPRINT is None:
        import hashlib  # here: the command line's start-up (cfdesign scenarios) has no use for it

        root = Path(__file__).resolve().parent.parent
        h = hashlib.sha256()
        for pkg in ("designer", "filters", "studies"):
            for f in sorted((root / pkg).rglob("*.py")):
                h.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes() + b"\0")
        _FINGERPRINT = h.hexdigest()
    return _FINGERPRINT


@contextlib.contextmanager
def replaced_outputs(directory) -> Iterator[Path]:
    """Yield a staging directory inside ``directory``; on success its files replace the last outputs.

    The files the previous command listed in ``OUTPUTS_NAME`` and that the new outputs do not
    have are removed, the new files are renamed in (each rename atomic), and the list is
    rewritten.  Hidden entries (the chunk store, the lock) and files cfdesign did not write are
    left alone.  On failure nothing in ``directory`` changes.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(dir=directory, prefix=".staging-"))
    try:
        yield stage
        try:
            old = set(json.loads((directory / OUTPUTS_NAME).read_text())["files"])
        except (OSError, ValueError, KeyError, TypeError):
            old = set()
        new = sorted(p.name for p in stage.iterdir())
        for name in sorted(old - set(new)):
            target = directory / name
            if "/" in name or name.startswith("."):  # a list that was edited: touch nothing outside
                continue
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target, ignore_errors=True)
            else:
                with contextlib.suppress(FileNotFoundError):
                    target.unlink()
        for name in new:
            os.replace(stage / name, directory / name)
        write_json(directory / OUTPUTS_NAME, {"files": new})
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def check_json_finite(data: Any, name: str) -> None:
    """Raise :class:`designer.validation.ComputationError` at the first NaN or infinity in ``data``."""
    from .validation import ComputationError

    def walk(x, path):
        if isinstance(x, dict):
            for k, v in x.items():
                walk(v, f"{path}.{k}" if path else str(k))
        elif isinstance(x, (list, tuple)):
            for i, v in enumerate(x):
                walk(v, f"{path}[{i}]")
        elif isinstance(x, np.ndarray):
            if x.dtype.kind in "fc" and not np.all(np.isfinite(x)):
                raise ComputationError(f"{name}: {path} holds non-finite values; nothing was written")
        elif isinstance(x, (float, np.floating)) and not math.isfinite(float(x)):
            raise ComputationError(f"{name}: {path} is {float(x)!r} (not a finite number); nothing was written")

    walk(data, "")
