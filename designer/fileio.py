"""File output: atomic files (absent, the old version, or complete), one writer per output directory.

* :func:`atomic_write` writes a temporary file beside the target and renames it over it; the
  file gets the usual permissions (``0666`` less the process's umask, as ``open`` gives).
* :func:`output_lock` holds an OS-level lock (``fcntl.flock``) on ``<directory>/.cfdesign.lock``
  for as long as a command writes into the directory; a second writer is refused at once
  (:class:`designer.validation.InputError`, exit 2) with the holder's PID and command.  The
  lock goes with the process that holds it, however it ends (even SIGKILL).  Taking it also
  checks the directory (below) and removes what a killed writer left (``.staging-*``
  directories, temporary files): with the lock held no other writer can be using them.
* :func:`append_line` appends one line to a log in a single ``write`` of an ``O_APPEND``
  descriptor, so concurrent or interrupted appends never interleave or leave half a line.
* :func:`code_fingerprint` hashes the package's own source files: stored results computed by
  another version of the code are recognised as such.
* :func:`replaced_outputs` writes a command's outputs into a staging directory and then
  replaces the outputs of the last command as a whole: a failure leaves the old outputs
  complete, and no file of another command (a stale figure, another study's table) stays
  beside the new ones.  Only files cfdesign listed as its outputs are ever removed or replaced.
* :func:`check_json_finite` names the first non-finite number of a results document, so a
  NaN is refused before anything is written.
* :func:`check_apart` refuses an output path equal to, inside or containing one of the command's
  inputs (a design directory, a log, a model file and its modules), before anything is written.

**cfdesign's own files in an output directory** are the lock, the list of outputs
(``OUTPUTS_NAME``), the chunk store (``CHUNKS_DIR`` and everything under it), staging
directories, and the outputs (``OUTPUT_PATTERNS``, and whatever the list names).  None of
them is ever written, read as cfdesign's or removed through a symbolic link: a link in
their place is refused (InputError naming it) when the lock is taken, before any
computation, and again where each is opened (``O_NOFOLLOW``).  The output directory itself
may be a link to a directory (the user chose where it points).  A file of an output's name
that cfdesign did not write (not in the list) is never replaced: refused, naming it.  A
failed write (a full disk) raises ``OSError`` whose ``filename`` is the file that was being
written, and leaves the old file.
"""
from __future__ import annotations

import contextlib
import errno
import fnmatch
import json
import math
import os
import re
import shutil
import stat
import sys
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .progress import line
from .validation import InputError

__all__ = ["atomic_write", "write_json", "write_npz", "Slabs", "output_lock", "append_line", "code_fingerprint",
           "check_output_file", "check_path", "check_apart", "writing", "replaced_outputs", "check_json_finite",
           "own_dir", "open_own", "refuse_link", "temporary_of", "LOCK_NAME", "OUTPUTS_NAME", "CHUNKS_DIR",
           "STAGING_PREFIX", "OUTPUT_PATTERNS", "REPORT_NAMES"]

LOCK_NAME = ".cfdesign.lock"
OUTPUTS_NAME = ".cfdesign-outputs.json"  # the files the last command wrote into an output directory
CHUNKS_DIR = ".chunks"  # the Monte Carlo runner's chunk store (studies.runner)
STAGING_PREFIX = ".staging-"  # replaced_outputs' staging directories
# the names cfdesign's commands give their outputs (study, design, feasibility, report)
OUTPUT_PATTERNS = ("results.json", "table.md", "report.md", "report.html", "schedule.json", "schedule.npz",
                   "feasibility.csv", "feasibility.json", "feasibility.png", "fig_*.png", "estimates.npz",
                   "estimates.csv", "*_node.c", "*_node.h", "*_model.c", "*_model.h", "*_test.c", "Makefile",
                   "replay.txt")  # the C export's files are PREFIX_... (cfd_ by default: export --prefix)
REPORT_NAMES = ("report.md", "report.html")  # what every command that writes a directory writes
_TEMPORARY = re.compile(r"\.(?P<of>.+)\.[a-z0-9_]{8}\.tmp")  # atomic_write's temporary files (mkstemp's 8 characters)
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


def check_path(name: str, value) -> Path:
    """``value`` as a path, checked: a ``str`` or path-like that is not empty or only blanks.

    An empty ``--out`` (an unset shell variable) would otherwise mean the current directory.
    """
    try:
        text = os.fspath(value)
    except TypeError:
        raise InputError(f"{name} must be a path, got {type(value).__name__}") from None
    if isinstance(text, bytes):
        text = os.fsdecode(text)
    if not text.strip():
        raise InputError(f"{name} is empty ({text!r}): give a path (an unset shell variable?)")
    return Path(text)


def _identity(path) -> tuple[int, int] | None:
    """The (device, inode) of an existing ``path`` (links followed), else None."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


def check_apart(name: str, out, inputs, *, kind: str = "directory") -> None:
    """Refuse the output path ``out`` (the parameter ``name``, an output ``kind``) when it is, lies inside or
    contains an input.

    ``inputs``: ``(parameter, what, paths)`` triples, e.g. ``("schedule", "the design directory", "d")``;
    ``paths`` one path or an iterable of them (each then named in the message), None for none.  Paths are
    compared as the filesystem resolves them: the device and inode of each existing path and of each
    directory above it, symbolic links and ``..`` followed, relative paths from the current directory,
    letter case as the filesystem has it.  An input that does not exist is not compared (it is refused
    where it is read).  Raises InputError naming both parameters, before anything is written.
    """
    if out is None:
        return
    out_path = Path(os.path.realpath(check_path(name, out)))
    above = {_identity(p) for p in out_path.parents} - {None}  # the directories out would be inside
    out_id = _identity(out_path)
    for parameter, what, paths in inputs:
        single = paths is None or isinstance(paths, (str, bytes, os.PathLike))
        for given in ([] if paths is None else [paths] if single else paths):
            path = Path(os.path.realpath(os.fspath(given)))
            ident = _identity(path)
            if ident is None:
                continue
            if ident == out_id:
                problem = "is"
            elif ident in above and path.is_dir():
                problem = "is inside"
            elif out_id is not None and any(_identity(p) == out_id for p in path.parents):
                problem = "contains"
            else:
                continue
            shown = "" if problem == "is" and single else f" ({os.fsdecode(os.fspath(given))!r})"
            raise InputError(f"{name} {os.fsdecode(os.fspath(out))!r} {problem} {what} given as {parameter}{shown}: "
                             f"choose another output {kind} (nothing was written)")


def _link(path) -> InputError:
    return InputError(f"{str(path)!r} is a symbolic link: cfdesign never writes or removes its own files through a "
                      "link; remove the link or choose another output path")


def refuse_link(path) -> None:
    """Raise InputError naming ``path`` if it is a symbolic link (cfdesign's files are never links)."""
    if os.path.islink(path):
        raise _link(path)


def own_dir(path) -> Path:
    """Create (if missing) the directory ``path`` of cfdesign's own and check it is one: not a link, not a file."""
    path = Path(path)
    with contextlib.suppress(FileExistsError):
        os.mkdir(path)
    mode = os.lstat(path).st_mode
    if stat.S_ISLNK(mode):
        raise _link(path)
    if not stat.S_ISDIR(mode):
        raise InputError(f"{str(path)!r} must be a directory (cfdesign keeps its files there), got a file")
    return path


def open_own(path):
    """Open cfdesign's file ``path`` for reading, never through a link (InputError naming it); a missing file
    raises FileNotFoundError."""
    try:
        fd = os.open(path, os.O_RDONLY | _NOFOLLOW)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise _link(path) from None
        raise
    return os.fdopen(fd, "rb")


def _naming(exc: OSError, path) -> OSError:
    """``exc`` as an OSError of the same kind whose ``filename`` is ``path`` (the file being written)."""
    return OSError(exc.errno, exc.strerror or str(exc), str(path))


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write(path, write) -> Path:
    """Call ``write(fileobj)`` on a temporary file beside ``path``, then rename it over ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    refuse_link(path)  # os.replace would replace the link, not write through it; refused all the same
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp's 0600 would make every output private
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(exc, OSError):  # a full disk: name the file (the error of a write names none)
            raise _naming(exc, path) from exc
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


#: zlib's level for ``.npz`` files: the fastest.  Doubles hardly compress (a design's bounds at a hundred states: 1.6
#: GB to 469 MB at the default level 6, 20 s; level 1 writes them 3-4 times faster); runs of zeros (a rule without
#: consensus gains) compress as well at either.
NPZ_LEVEL = 1


class Slabs:
    """An array given slab by slab along its first axis, ``slab(k)`` of shape ``shape[1:]``, so that
    :func:`write_npz` writes it without it ever being whole in memory (a log's channel signal: dense N x N x n_x a
    step, nearly all zeros).  ``a[k, ...]`` indexes it (the slab of ``k`` is kept until another is asked for)."""

    def __init__(self, shape: tuple, dtype, slab):
        self.shape, self.dtype, self._slab = tuple(int(n) for n in shape), np.dtype(dtype), slab
        self._kept: tuple[int, np.ndarray] | None = None

    def slab(self, k: int) -> np.ndarray:
        if self._kept is None or self._kept[0] != k:
            a = np.ascontiguousarray(self._slab(k), dtype=self.dtype)
            if a.shape != self.shape[1:]:
                raise ValueError(f"slab {k} has shape {a.shape}, not {self.shape[1:]}")
            self._kept = (k, a)
        return self._kept[1]

    def __getitem__(self, index):
        index = index if isinstance(index, tuple) else (index,)
        return self.slab(int(index[0]))[index[1:]]


#: Bytes of an array :func:`write_npz` writes at a time (what ``np.lib.format.write_array`` writes at a time too):
#: between two pieces a progress line may be due (a 64-cell field's scheduled design writes 3.4 GB, about a minute).
NPZ_PIECE = 16 << 20


def write_npz(path, **arrays) -> Path:
    """Write ``arrays`` as a compressed ``.npz`` (what ``np.savez_compressed`` writes, at zlib level
    :data:`NPZ_LEVEL`; ``np.load`` reads it) atomically; a :class:`Slabs` value is written slab by slab (the same
    ``.npy`` member as its whole array's), a large array :data:`NPZ_PIECE` bytes at a time (the same bytes), with a
    progress line when due (:func:`designer.progress.line`: the megabytes written of the file's)."""
    values = {name: value if isinstance(value, Slabs) else np.asanyarray(value) for name, value in arrays.items()}
    total = sum(math.prod(v.shape) * v.dtype.itemsize for v in values.values())
    done = 0

    def written(nbytes: int) -> None:
        nonlocal done
        done += nbytes
        line("MB written", done >> 20, total >> 20)

    def write(fh):
        with zipfile.ZipFile(fh, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=NPZ_LEVEL) as zf:
            for name, value in values.items():
                with zf.open(f"{name}.npy", "w", force_zip64=True) as member:
                    if isinstance(value, Slabs):
                        np.lib.format.write_array_header_1_0(member, {
                            "descr": np.lib.format.dtype_to_descr(value.dtype), "fortran_order": False,
                            "shape": value.shape})
                        for k in range(value.shape[0]):
                            piece = value.slab(k).tobytes()
                            member.write(piece)
                            written(len(piece))
                    elif value.nbytes > NPZ_PIECE and value.flags.c_contiguous and not value.dtype.hasobject:
                        np.lib.format.write_array_header_1_0(member, np.lib.format.header_data_from_array_1_0(value))
                        flat, step = value.reshape(-1), max(1, NPZ_PIECE // value.dtype.itemsize)
                        for start in range(0, flat.size, step):
                            member.write(flat[start:start + step].tobytes())
                            written(min(step, flat.size - start) * value.dtype.itemsize)
                    else:
                        np.lib.format.write_array(member, value, allow_pickle=False)
                        written(value.nbytes)

    return atomic_write(path, write)


def check_output_file(name: str, path, suffix: str) -> Path:
    """An output file's path, checked before any computation: ``suffix``, not a directory, a writable place."""
    path = check_path(name, path)
    refuse_link(path)
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
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | _NOFOLLOW, 0o666)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise _link(path) from None
        raise
    try:
        try:
            written = os.write(fd, data)
        except OSError as exc:
            raise _naming(exc, path) from exc
        if written != len(data):  # a full disk: do not leave half a line that a reader would take for one
            os.ftruncate(fd, os.lseek(fd, 0, os.SEEK_END) - written)
            raise OSError(errno.ENOSPC, "only part of a line could be appended (disk full?)", str(path))
    finally:
        os.close(fd)


_HELD: dict[tuple[int, int], tuple[int, int]] = {}  # directories this process holds: (dev, inode) -> (pid, depth)


def _nothing_written(directory: Path) -> bool:
    """The directory holds only its lock and a chunk store without a chunk (its manifests: written before the
    first chunk is computed), none of them through a link."""
    entries = {p.name: p for p in directory.iterdir()}
    if set(entries) - {LOCK_NAME, CHUNKS_DIR}:
        return False
    store = entries.get(CHUNKS_DIR)
    if store is None:
        return True
    if store.is_symlink():
        return False
    for root, dirs, files in os.walk(store):
        if any(Path(root, d).is_symlink() for d in dirs) or any(f != "manifest.json" for f in files):
            return False
    return True


@contextlib.contextmanager
def output_lock(directory, *, name: str = "out", replaces=REPORT_NAMES) -> Iterator[Path]:
    """Hold the one-writer lock of ``directory`` (created if missing) for the ``with`` block.

    Raises InputError at once, naming the holder (PID, command, start time), when another
    process holds it.  On platforms without ``fcntl`` nothing is locked.  Re-entrant: a
    process that holds the lock of a directory (through any path to it) holds it again at once.

    When the lock is taken, before the caller computes anything, the directory is checked: a
    symbolic link in place of one of cfdesign's own files is refused (see the module docstring),
    so is a file named as in ``replaces`` (glob patterns: the outputs this command replaces)
    that cfdesign did not write; and what a killed writer left (staging directories, temporary
    files) is removed, since no other writer can be using it.  ``name`` is the parameter that
    gave ``directory`` (in messages).
    """
    directory = check_path(name, directory)
    if directory.exists() and not directory.is_dir():
        raise InputError(f"{name} must be a directory, got the existing file {str(directory)!r}")
    created = [p for p in [directory, *directory.parents] if not p.exists()]  # what to remove if nothing is written
    try:
        directory.mkdir(parents=True, exist_ok=True)
        st = os.stat(directory)
    except OSError as exc:
        raise InputError(f"{name}: cannot write into {str(directory)!r} ({exc.strerror or exc})") from exc
    key = (st.st_dev, st.st_ino)
    held = _HELD.get(key)
    if held is not None and held[0] == os.getpid():  # a forked child holds nothing of its parent's
        _HELD[key] = (held[0], held[1] + 1)
        try:
            yield directory
        finally:
            _HELD[key] = held
        return
    path = directory / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | _NOFOLLOW, 0o666)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise _link(path) from None
        raise InputError(f"{name}: cannot write into {str(directory)!r} ({exc.strerror or exc})") from exc
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        fcntl = None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise InputError(f"{name}: {str(path)!r} is not a regular file; remove it")
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
                other = " or choose another output directory" if name == "out" else ""
                raise InputError(f"{name}: {str(directory)!r} is being written by {who}; wait for it to finish"
                                 f"{other}") from None
        info = json.dumps({"pid": os.getpid(), "command": " ".join([Path(sys.argv[0]).name] + sys.argv[1:])[:500],
                           "started": time.strftime("%Y-%m-%d %H:%M:%S")}).encode()
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, info, 0)
        except OSError as exc:
            raise _naming(exc, path) from exc
        _HELD[key] = (os.getpid(), 1)
        try:
            _check_and_clean(directory, replaces)
            yield directory
        finally:
            _HELD.pop(key, None)
    except BaseException:
        if created:  # refused or failed before writing anything: leave no empty directory behind
            with contextlib.suppress(OSError):
                if _nothing_written(directory):
                    shutil.rmtree(directory / CHUNKS_DIR, ignore_errors=True)
                    path.unlink()
                    for p in created:
                        p.rmdir()
        raise
    finally:
        os.close(fd)  # releases the flock


def _is_output(name: str, patterns=OUTPUT_PATTERNS) -> bool:
    return any(fnmatch.fnmatchcase(name, p) for p in patterns)


def temporary_of(name: str) -> str | None:
    """The file whose :func:`atomic_write` left the temporary file ``name`` (when a writer was killed), else None."""
    m = _TEMPORARY.fullmatch(name)
    return None if m is None else m["of"]


def _stale_temporary(name: str) -> bool:
    """``name`` is a temporary file of the output list or of an output (in an output directory)."""
    of = temporary_of(name)
    return of is not None and (of == OUTPUTS_NAME or _is_output(of))


def _listed(directory: Path) -> set[str]:
    """The outputs the last command listed in ``directory`` (plain names only; the list is never read through a
    link)."""
    try:
        with open_own(directory / OUTPUTS_NAME) as fh:
            files = json.loads(fh.read())["files"]
    except (FileNotFoundError, ValueError, KeyError, TypeError):
        return set()
    except OSError as exc:
        raise _naming(exc, directory / OUTPUTS_NAME) from exc
    if not isinstance(files, list):
        return set()
    return {f for f in files if isinstance(f, str) and f and "/" not in f and not f.startswith(".")}


def _check_and_clean(directory: Path, replaces) -> None:
    """With the lock held: refuse links in place of cfdesign's files and files of ``replaces`` names it did not
    write; remove the staging directories and temporary files of writers that were killed."""
    listed = _listed(directory)
    with os.scandir(directory) as it:
        entries = sorted(it, key=lambda e: e.name)
    for e in entries:
        ours = (e.name in (LOCK_NAME, OUTPUTS_NAME, CHUNKS_DIR) or e.name.startswith(STAGING_PREFIX)
                or e.name in listed or _is_output(e.name) or _stale_temporary(e.name))
        if ours and e.is_symlink():
            raise _link(e.path)
        if replaces and _is_output(e.name, replaces) and e.name not in listed and e.is_file(follow_symlinks=False):
            raise InputError(f"{e.path!r} exists and was not written by cfdesign (it is not among the outputs listed "
                             f"in {OUTPUTS_NAME}); move it away or choose another output directory")
    chunks = directory / CHUNKS_DIR
    if os.path.lexists(chunks):
        own_dir(chunks)
        for root, dirs, files in os.walk(chunks):  # links are never followed: refused
            for n in dirs + files:
                if os.path.islink(os.path.join(root, n)):
                    raise _link(os.path.join(root, n))
    for e in entries:
        if e.name.startswith(STAGING_PREFIX) and e.is_dir(follow_symlinks=False):
            shutil.rmtree(e.path, ignore_errors=True)  # rmtree never follows a link inside
        elif _stale_temporary(e.name) and e.is_file(follow_symlinks=False):
            with contextlib.suppress(OSError):
                os.unlink(e.path)


def writing(directory, *, name: str = "out", replaces=REPORT_NAMES):
    """:func:`output_lock` of ``directory``, or nothing to hold when there is no output directory (None)."""
    return contextlib.nullcontext() if directory is None else output_lock(directory, name=name, replaces=replaces)


_FINGERPRINT: str | None = None


def code_fingerprint() -> str:
    """SHA-256 of the package's source files (``designer``, ``filters``, ``rules``, ``studies``, and the folders of
    further rule packages that ``CFDESIGN_RULE_PATH`` names), computed once per process."""
    global _FINGERPRINT
    if _FINGERPRINT is None:
        import hashlib  # here: the command line's start-up (cfdesign scenarios) has no use for it

        root = Path(__file__).resolve().parent.parent
        h = hashlib.sha256()
        for pkg in ("designer", "filters", "rules", "studies"):
            for f in sorted((root / pkg).rglob("*.py")):
                h.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes() + b"\0")
        for folder in filter(None, os.environ.get("CFDESIGN_RULE_PATH", "").split(os.pathsep)):
            for f in sorted(Path(folder).resolve().rglob("*.py")):  # a rule kept outside this repository (rules)
                h.update(str(f).encode() + b"\0" + f.read_bytes() + b"\0")
        _FINGERPRINT = h.hexdigest()
    return _FINGERPRINT


@contextlib.contextmanager
def replaced_outputs(directory, *, keep_others: bool = False, retire=()) -> Iterator[Path]:
    """Yield a staging directory inside ``directory``; on success its files replace the last outputs.

    The directory's one-writer lock is held throughout (:func:`output_lock`; at once if this
    process holds it already).  On success: every new file's place is checked first (not a
    link, not a directory, not a file cfdesign did not write), then the files the previous
    command listed in ``OUTPUTS_NAME`` and that the new outputs do not have are removed (only
    those named as outputs, ``OUTPUT_PATTERNS``), the new files are renamed in (each rename
    atomic), and the list is rewritten.  Hidden entries (the chunk store, the lock) and files
    cfdesign did not write are left alone.  On failure nothing in ``directory`` changes, and an
    ``OSError`` names the output's place in ``directory`` (not the staging directory).

    ``keep_others``: the new files are added to the last outputs instead (``cfdesign report``:
    the directory's report is rebuilt, its results kept) and replace files of their names whoever
    wrote them (the user asked for this directory's report); of the last outputs, those named in ``retire`` (the
    report's own figures) that the new files do not have are removed all the same.
    """
    directory = check_path("out", directory)
    with output_lock(directory, replaces=() if keep_others else REPORT_NAMES):
        stage = Path(tempfile.mkdtemp(dir=directory, prefix=STAGING_PREFIX))
        try:
            try:
                yield stage
            except OSError as exc:
                name = exc.filename if isinstance(exc.filename, str) else None
                if name is not None and Path(name).parent == stage:
                    raise _naming(exc, directory / Path(name).name) from exc
                raise
            _commit(directory, stage, keep_others, frozenset(retire))
        finally:
            shutil.rmtree(stage, ignore_errors=True)


def _commit(directory: Path, stage: Path, keep_others: bool, retire: frozenset = frozenset()) -> None:
    old = _listed(directory)
    new = sorted(p.name for p in stage.iterdir())
    gone = sorted(n for n in old - set(new) if _is_output(n) and (not keep_others or n in retire))
    for n in new + gone:  # everything checked before anything changes
        target = directory / n
        try:
            mode = os.lstat(target).st_mode
        except FileNotFoundError:
            continue
        if stat.S_ISLNK(mode):
            raise _link(target)
        if n in new and stat.S_ISDIR(mode):
            raise InputError(f"{str(target)!r} is a directory; cfdesign writes its output {n} there as a file: move "
                             "it away or choose another output directory")
        if n in new and n not in old and not keep_others:
            raise InputError(f"{str(target)!r} exists and was not written by cfdesign (it is not among the outputs "
                             f"listed in {OUTPUTS_NAME}); move it away or choose another output directory")
    write_json(directory / OUTPUTS_NAME, {"files": sorted(old | set(new))})  # first: nothing cfdesign wrote unlisted
    for n in gone:
        target = directory / n
        if not os.path.islink(target) and os.path.isfile(target):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(target)
    for n in new:
        os.replace(stage / n, directory / n)
    write_json(directory / OUTPUTS_NAME, {"files": sorted((old - set(gone)) | set(new)) if keep_others else new})


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
