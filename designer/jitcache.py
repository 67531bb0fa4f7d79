"""The on-disk cache of compiled numba kernels: compiled once per machine, not once per process.

numba compiles a kernel at its first call in every process (seconds per kernel) unless
the kernel is cached on disk, and its on-disk cache needs a function defined in a real
source file.  So the kernels generated from a model (:func:`designer.jit.compile_source`,
the fused particle filters of :mod:`filters.fused`) are written as Python modules into
the cache directory and imported from there, and they and the generic numba code that
calls them are compiled with :func:`cached_njit`, whose compiled code is kept in the same
directory.

Location: the environment variable ``CFDESIGN_CACHE_DIR`` if set, else the platform's
user cache directory: ``$XDG_CACHE_HOME/cfdesign`` (default ``~/.cache/cfdesign``) on
Linux, ``~/Library/Caches/cfdesign`` on macOS, ``%LOCALAPPDATA%\\cfdesign\\Cache`` on
Windows (:func:`cache_dir`).  Layout::

    <cache>/kernels/<label>-<key>.py      generated kernel modules (readable Python)
    <cache>/numba/<source dir>/*.nbi|nbc  numba's compiled code, one index per function
    <cache>/keys/design.key               this account's design key (studies.provenance): not a cache, never removed

A generated module's ``<key>`` hashes its whole text, whose header names the code
version (a hash of the generator's source files) and numba's and Python's versions: a
changed model, generator or numba writes a new module and compiles it anew.  The
generic kernels' compiled code is valid for one ``stamp`` (:func:`source_stamp` of the
files whose code it inlines, which numba alone would not track) and numba's own version.

Concurrency: a generated module is written to a temporary file and renamed into place
(:func:`designer.fileio.atomic_write`; two processes write the same text), and numba
writes its index and data files the same way, one data file per signature named by it
(:class:`_KeyedFiles`), so two processes compiling the same kernel, or different
signatures of one function, at once both succeed and leave a usable cache.
Any failure to write the cache (a read-only directory) leaves the kernels compiled in
memory only.  :func:`clear_cache` (``cfdesign cache clear``) removes the cache.
"""
from __future__ import annotations

import hashlib
import importlib.util
import os
import re
import shutil
import sys
import types as pytypes
from pathlib import Path
from typing import Callable, Iterable

import numba
from numba.core import caching
from numba.core.runtime import rtsys

from .fileio import atomic_write

__all__ = ["ENV", "cache_dir", "kernels_dir", "source_stamp", "cached_njit", "generated_module", "clear_cache"]

#: The environment variable naming the cache directory.
ENV = "CFDESIGN_CACHE_DIR"
_VERSIONS = f"numba {numba.__version__}, Python {sys.version_info[0]}.{sys.version_info[1]}"


def cache_dir() -> Path:
    """The cache directory: ``$CFDESIGN_CACHE_DIR``, else the platform's user cache directory (see the module notes).

    Read at every call (a test or a script may set the variable before its first kernel).
    """
    env = os.environ.get(ENV)
    if env:
        return Path(env).expanduser()
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches" / "cfdesign"
    if os.name == "nt":
        return Path(os.environ.get("LOCALAPPDATA", Path.home() / "AppData" / "Local")) / "cfdesign" / "Cache"
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "cfdesign"


_TAG = "CACHEDIR.TAG"  # the standard mark of a cache directory (backup tools skip it); clear_cache requires it


def _root() -> Path:
    """The cache directory, made and marked as cfdesign's (``CACHEDIR.TAG``) if it is not yet."""
    root = cache_dir()
    tag = root / _TAG
    if not tag.is_file():
        atomic_write(tag, lambda fh: fh.write(b"Signature: 8a477f597d28d172789f06886806bc55\n"
                                              b"# cfdesign's compiled kernels: cfdesign cache clear removes them.\n"))
    return root


def kernels_dir() -> Path:
    """Where the generated kernel modules are (``<cache>/kernels``)."""
    return cache_dir() / "kernels"


def source_stamp(files: Iterable) -> str:
    """SHA-256 (hex) of the named source files' contents, in the given order: a code version."""
    h = hashlib.sha256()
    for f in files:
        h.update(Path(f).read_bytes() + b"\0")
    return h.hexdigest()


# ------------------------------------------------------------------------------ numba's cache, redirected
class _Locator(caching._CacheLocator):
    """numba's cache of one function in ``<cache>/numba/<source dir>``, valid for one stamp.

    numba's own locators stamp a function by its file alone and keep its cache beside the
    source; a kernel that inlines code of other files (or a generated module) needs the
    stamp of all of them, and ``cfdesign cache clear`` needs the cache in one place.
    """

    def __init__(self, py_func, py_file, stamp: str):
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        self._stamp = stamp
        parent = Path(py_file).resolve().parent
        tag = hashlib.sha256(str(parent).encode()).hexdigest()[:12]
        self._cache_path = str(_root() / "numba" / f"{parent.name}_{tag}")

    def get_cache_path(self) -> str:
        return self._cache_path

    def get_source_stamp(self) -> str:
        return self._stamp

    def get_disambiguator(self) -> str:
        return str(self._lineno)

    @classmethod
    def from_function(cls, py_func, py_file):
        stamp = getattr(py_func, "_cfdesign_stamp", None)
        if stamp is None or not os.path.exists(py_file):
            return None
        try:
            self = cls(py_func, py_file, stamp)
            self.ensure_cache_path()
        except OSError:  # not writable: no on-disk cache
            return None
        return self


class _Impl(caching.CompileResultCacheImpl):
    _locator_classes = [_Locator]


class _KeyedFiles(caching.IndexDataCacheFile):
    """numba's index and data files of a function, with a data file per key (named by the key's hash).

    numba numbers the data files in the order the keys (signatures) arrive, so two
    processes adding different signatures of one function at once could leave an index
    entry that names the other signature's code.  Here a data file's name is its key's:
    the worst such a race can do is drop an index entry (compiled again next time).
    """

    def save(self, key, data):
        name = f"{self._index_name[:-4]}.{hashlib.sha256(repr(key).encode()).hexdigest()[:16]}.nbc"
        self._save_data(name, data)  # first: an index entry never names a missing file
        overloads = self._load_index()
        overloads[key] = name
        self._save_index(overloads)


#: numba versions whose cached code needs only NRT's symbols from the target context's refresh (tested: 0.68)
_LIGHT_LOAD = (0, 60) <= tuple(int(p) for p in numba.__version__.split(".")[:2]) < (0, 69)


class _Cache(caching.FunctionCache):
    _impl_class = _Impl

    def __init__(self, py_func):
        super().__init__(py_func)
        self._cache_file = _KeyedFiles(cache_path=self._cache_path, filename_base=self._impl.filename_base,
                                       source_stamp=self._impl.locator.get_source_stamp())

    def load_overload(self, sig, target_context):
        # numba refreshes the target context first (imports and installs every implementation registry of
        # numba: a quarter of a second, the largest part of a warm process's kernel loading); the loaded code
        # needs none of them, and a compilation refreshes the context itself.  Only for the numba versions
        # where that is known (a symbol the loaded code needs and nobody defined aborts the process).
        if not _LIGHT_LOAD:
            return super().load_overload(sig, target_context)
        rtsys.initialize(target_context)  # the part of the refresh that loaded code needs: NRT's symbols
        with self._guard_against_spurious_io_errors():
            return self._load_overload(sig, target_context)

    def save_overload(self, sig, data):
        # the directory may have been cleared since this process found it (cfdesign cache clear)
        try:
            os.makedirs(self._cache_path, exist_ok=True)
            super().save_overload(sig, data)
        except OSError:
            pass  # a cache that cannot be written leaves the kernel compiled in memory


def cached_njit(stamp: str, **options) -> Callable:
    """``numba.njit(**options)`` whose compiled code is cached in :func:`cache_dir`, valid for ``stamp``.

    ``stamp`` must change whenever code that the function inlines changes (its own file
    and the files of the njit functions it calls: :func:`source_stamp`); numba's version is
    part of it.  Without a usable cache directory the function compiles in memory.
    """
    def decorate(fn):
        disp = numba.njit(**options)(fn)
        fn._cfdesign_stamp = f"{stamp} {_VERSIONS}"
        try:
            disp._cache = _Cache(fn)  # what numba's enable_caching() does, with the locator above
        except RuntimeError:  # no locator: the directory cannot be written
            pass
        return disp

    return decorate


# ------------------------------------------------------------------------------ generated modules
_SLUG = re.compile(r"[^A-Za-z0-9_]+")


def generated_module(source: str, label: str, namespace: dict | None = None, stamp: str = "") -> pytypes.ModuleType:
    """Python ``source`` (generated) as a module in ``<cache>/kernels``, written once and imported.

    The file is ``<label>-<key>.py`` with ``key`` the hash of its text (a header naming
    the label, the generator's code version ``stamp`` and numba's and Python's versions,
    then ``source``); its ``__key__`` is that hash.  A module of the same text is reused,
    in this process and in later ones.  ``namespace`` binds helper names the source
    uses (functions and modules only: data must be written into the source, so that the
    key covers it).  The module's ``__file__`` is its path.
    """
    for name, value in (namespace or {}).items():
        if not callable(value) and not isinstance(value, pytypes.ModuleType):
            raise TypeError(f"namespace[{name!r}] must be a function or a module (data belongs in the source)")
    helpers = ", ".join(sorted(namespace or {})) or "none"
    text = (f"# cfdesign generated kernel: {label}\n# generator {stamp[:16] or '-'}, {_VERSIONS}\n"
            f"# bound by the generator, not defined here: {helpers}\n"
            f"# Do not edit: the file name is the hash of this text.\n{source}\n")
    key = hashlib.sha256(text.encode()).hexdigest()[:20]
    modname = f"cfdesign_kernel_{key}"
    mod = sys.modules.get(modname)
    if mod is not None:
        return mod
    try:
        path = _root() / "kernels" / f"{_SLUG.sub('_', label).strip('_')[:60]}-{key}.py"
        if not path.is_file() or path.read_text() != text:
            atomic_write(path, lambda fh: fh.write(text.encode()))
    except OSError:
        path = None  # not writable: compiled from memory, without the on-disk cache
    mod = pytypes.ModuleType(modname)
    mod.__dict__.update(namespace or {})
    if path is None:
        mod.__file__ = f"<cfdesign generated kernel: {label}>"
        exec(compile(text, mod.__file__, "exec"), mod.__dict__)
    else:
        spec = importlib.util.spec_from_file_location(modname, path)
        mod = importlib.util.module_from_spec(spec)
        mod.__dict__.update(namespace or {})
        sys.modules[modname] = mod  # numba's cached code finds its module's globals by the module's name
        spec.loader.exec_module(mod)
    mod.__key__ = key
    sys.modules[modname] = mod
    return mod


def clear_cache() -> list[Path]:
    """Remove the compiled kernels (the generated modules and numba's code); returns the paths removed.

    Only a directory marked as cfdesign's cache (its ``CACHEDIR.TAG``) is touched, and in
    it only what cfdesign writes.  Kernels compiled in a running process stay usable
    there; the next process compiles them again.
    """
    root = cache_dir()
    if not (root / _TAG).is_file():
        return []
    removed = []
    for sub in ("kernels", "numba"):
        p = root / sub
        if p.exists():
            shutil.rmtree(p)
            removed.append(p)
    return removed
