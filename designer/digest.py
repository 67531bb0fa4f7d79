"""Content digests: a SHA-256 of what an object *is*, the same in every process.

Stored results (the Monte Carlo chunk store of :mod:`studies.runner`) are reused only when
everything their numbers depend on is unchanged; a model is part of that, by content, not
by the path of the file it came from.  :func:`content_digest` walks an object and hashes a
canonical encoding of it:

* numbers by value (a float by its exact bits, ``float.hex``), strings, bytes, ``None``;
* NumPy arrays by dtype, shape and bytes;
* lists, tuples, mappings (in a canonical key order), sets;
* dataclasses by class name and their ``__init__`` fields (derived fields are functions of them);
* an object with a ``__digest__()`` method by what that method returns (e.g.
  :meth:`designer.model.Model.__digest__`: the translated expressions, noises and numbers);
* CasADi expressions by their serialisation;
* Python functions by their compiled code (bytecode, constants, names, nested code), default
  arguments and closure values; what they read from module globals is not seen (a model file's
  bytes cover it: :func:`source_files_digest`);
* other objects by class name and attributes, or their pickle.

Nothing here depends on ``id``, memory addresses, hash seeds or the order of a ``set``, so the
digest of the same content is the same in any process.
"""
from __future__ import annotations

import ast
import dataclasses
import enum
import functools
import hashlib
import math
import pickle
import struct
import sys
from pathlib import Path
from types import CodeType, FunctionType, MethodType
from typing import Any, Mapping

import numpy as np

__all__ = ["CFDESIGN_PACKAGES", "content_digest", "is_local_module", "source_files", "source_files_digest"]


class _Encoder:
    def __init__(self):
        self.h = hashlib.sha256()
        self.active: set[int] = set()  # objects being encoded (a cycle is encoded as a back-reference)

    def tag(self, t: bytes, payload: bytes = b"") -> None:
        self.h.update(t + struct.pack("<Q", len(payload)) + payload)

    def encode(self, obj: Any) -> None:  # noqa: C901 - one branch per kind, in the order of the module's list
        if obj is None:
            return self.tag(b"N")
        if isinstance(obj, (bool, np.bool_)):
            return self.tag(b"B", b"1" if obj else b"0")
        if isinstance(obj, (int, np.integer)):
            return self.tag(b"I", str(int(obj)).encode())
        if isinstance(obj, (float, np.floating)):
            v = float(obj)
            return self.tag(b"F", (repr(v) if math.isnan(v) else v.hex()).encode())
        if isinstance(obj, (complex, np.complexfloating)):
            return self.tag(b"Z", f"{complex(obj).real.hex()},{complex(obj).imag.hex()}".encode())
        if isinstance(obj, str):
            return self.tag(b"S", obj.encode("utf-8", "surrogatepass"))
        if isinstance(obj, (bytes, bytearray, memoryview)):
            return self.tag(b"Y", bytes(obj))
        if isinstance(obj, enum.Enum):
            return self.tag(b"E", f"{type(obj).__qualname__}.{obj.name}".encode())
        if isinstance(obj, Path):
            return self.tag(b"P", str(obj).encode())
        if isinstance(obj, np.ndarray):
            if obj.dtype == object:
                self.tag(b"O", repr(obj.shape).encode())
                for v in obj.ravel():
                    self.encode(v)
                return None
            a = np.ascontiguousarray(obj)
            return self.tag(b"A", f"{a.dtype.str}{a.shape}".encode() + b"\0" + a.tobytes())
        key = id(obj)
        if key in self.active:
            return self.tag(b"R", type(obj).__qualname__.encode())
        self.active.add(key)
        try:
            self._container(obj)
        finally:
            self.active.discard(key)
        return None

    def _sub(self, obj: Any) -> bytes:
        """The digest of ``obj`` alone (to order the members of a mapping or a set canonically)."""
        e = _Encoder()
        e.active = self.active
        e.encode(obj)
        return e.h.digest()

    def _container(self, obj: Any) -> None:
        if isinstance(obj, (list, tuple)):
            self.tag(b"L" if isinstance(obj, list) else b"T", str(len(obj)).encode())
            for v in obj:
                self.encode(v)
            return
        if isinstance(obj, Mapping):
            items = sorted(((self._sub(k), v) for k, v in obj.items()), key=lambda kv: kv[0])
            self.tag(b"D", str(len(items)).encode())
            for kd, v in items:
                self.tag(b"K", kd)
                self.encode(v)
            return
        if isinstance(obj, (set, frozenset)):
            subs = sorted(self._sub(v) for v in obj)
            self.tag(b"U", b"".join(subs))
            return
        digest = getattr(type(obj), "__digest__", None)
        if digest is not None:
            self.tag(b"G", type(obj).__qualname__.encode())
            self.encode(digest(obj))
            return
        if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
            self.tag(b"C", f"{type(obj).__module__}.{type(obj).__qualname__}".encode())
            for f in dataclasses.fields(obj):
                if f.init:
                    self.tag(b"f", f.name.encode())
                    self.encode(getattr(obj, f.name))
            return
        if isinstance(obj, MethodType):
            self.tag(b"M")
            self.encode(obj.__func__)
            self.encode(obj.__self__)
            return
        if isinstance(obj, FunctionType):
            self.tag(b"Q", f"{obj.__module__}.{obj.__qualname__}".encode())
            self._code(obj.__code__)
            self.encode(obj.__defaults__)
            self.encode(obj.__kwdefaults__)
            self.encode(None if obj.__closure__ is None else [_cell(c) for c in obj.__closure__])
            return
        if isinstance(obj, CodeType):
            return self._code(obj)
        casadi = _casadi_text(obj)
        if casadi is not None:
            self.tag(b"X", casadi.encode())
            return
        if isinstance(obj, type):
            self.tag(b"t", f"{obj.__module__}.{obj.__qualname__}".encode())
            return
        if callable(obj) and hasattr(obj, "func") and hasattr(obj, "args"):  # functools.partial
            self.tag(b"p")
            self.encode(obj.func)
            self.encode(obj.args)
            self.encode(obj.keywords)
            return
        state = getattr(obj, "__dict__", None)
        if isinstance(state, dict):
            self.tag(b"o", f"{type(obj).__module__}.{type(obj).__qualname__}".encode())
            self.encode({k: v for k, v in state.items()})
            return
        try:
            self.tag(b"k", pickle.dumps(obj, protocol=4))
        except Exception:  # noqa: BLE001 - neither data nor picklable: its type is all that can be said
            self.tag(b"?", f"{type(obj).__module__}.{type(obj).__qualname__}".encode())

    def _code(self, code: CodeType) -> None:
        self.tag(b"c", code.co_code)
        self.encode(code.co_names)
        self.encode(code.co_varnames)
        self.encode([c for c in code.co_consts if not isinstance(c, CodeType)])
        for c in code.co_consts:
            if isinstance(c, CodeType):
                self._code(c)


def _cell(cell) -> Any:
    try:
        return cell.cell_contents
    except ValueError:  # an empty cell
        return None


def _casadi_text(obj: Any) -> str | None:
    """A CasADi object's serialisation (None: not a CasADi object)."""
    module = type(obj).__module__ or ""
    if not module.startswith("casadi"):
        return None
    import casadi as ca

    if isinstance(obj, ca.Function):
        return obj.serialize()
    if isinstance(obj, (ca.SX, ca.MX)):
        sym = ca.symvar(obj)
        return ca.Function("digest", sym, [obj]).serialize() + "|" + ",".join(s.name() for s in sym)
    if isinstance(obj, (ca.DM, ca.Sparsity)):
        return obj.serialize()
    return repr(obj)


def content_digest(*objects: Any) -> str:
    """SHA-256 (hex) of the content of ``objects`` (see the module docstring)."""
    e = _Encoder()
    for obj in objects:
        e.encode(obj)
    return e.h.hexdigest()


# cfdesign's own top-level packages (pyproject.toml's packages): never a model file's sibling, installed or not
CFDESIGN_PACKAGES = frozenset({"designer", "filters", "studies"})


@functools.cache
def _distribution_packages() -> frozenset[str]:
    """Top-level names of the installed distributions (an editable install's too, wherever its sources lie)."""
    import importlib.metadata

    return frozenset(importlib.metadata.packages_distributions())


def _found_elsewhere(name: str, folder: Path) -> bool:
    """Whether the import system finds a top-level module ``name`` outside ``folder`` (that folder left off
    ``sys.path``): installed, on the path, or given by an import hook such as an editable install's."""
    path = []
    for p in sys.path:
        try:
            if Path(p or ".").resolve() != folder:
                path.append(p)
        except (OSError, RuntimeError, ValueError):
            path.append(p)
    for finder in sys.meta_path:
        if getattr(finder, "cfdesign_user_modules", False):  # the model loader's own finder
            continue
        try:
            spec = finder.find_spec(name, path)
        except Exception:  # noqa: BLE001 - a third-party hook that cannot answer for this name
            continue
        # a namespace package's portion is no module of its own (an installed one is a distribution's)
        if spec is not None and spec.origin and (not spec.has_location
                                                 or not Path(spec.origin).resolve().is_relative_to(folder)):
            return True
    return False


def is_local_module(name: str, folder) -> bool:
    """Whether ``import name`` (a top-level name) in a model file in ``folder`` means the file's own sibling.

    It does when ``folder`` holds ``name.py`` or a package ``name/`` and no module of that name exists
    outside it: not a built-in or standard-library module, not one of cfdesign's own packages, not a
    module the import system finds elsewhere, not a top-level package of an installed distribution.  So a
    model file in the repository's root imports the installed ``designer``, and a ``json.py`` beside a
    model never stands for the standard library.  The model loader (:mod:`studies.scenarios`) imports the
    siblings under a private name; :func:`source_files` counts the same ones.
    """
    folder = Path(folder).resolve()
    if not name.isidentifier() or not ((folder / f"{name}.py").is_file() or (folder / name).is_dir()):
        return False
    if name in sys.builtin_module_names or name in sys.stdlib_module_names or name in CFDESIGN_PACKAGES:
        return False
    return not _found_elsewhere(name, folder) and name not in _distribution_packages()


def source_files(path) -> list[Path]:
    """A Python file and the modules it imports from its own directory (recursively), in a fixed order.

    Found statically, so the list does not depend on what happens to be imported in this process:
    ``import name`` and ``from name import ...`` where ``name`` is a sibling (:func:`is_local_module`)
    whose module is ``<dir>/name.py`` or a package ``<dir>/name/``, and relative imports (``from .name
    import ...``, ``from . import name``) from the importing file's package.
    """
    first = Path(path).resolve()
    root = first.parent
    local: dict[str, bool] = {}
    seen: dict[Path, None] = {}
    todo = [first]
    while todo:
        f = todo.pop()
        if f in seen or not f.is_file():
            continue
        seen[f] = None
        try:
            tree = ast.parse(f.read_bytes())
        except (SyntaxError, ValueError, OSError):
            continue
        for node in ast.walk(tree):
            base, found, relative = root, [], False  # a package directory and the modules' paths in it
            if isinstance(node, ast.Import):
                found = [a.name.split(".") for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                parts = node.module.split(".") if node.module else []
                found = ([parts] if parts else []) + [parts + [a.name] for a in node.names]
                relative = node.level > 0
                if relative:  # from the importing file's package, never above the model's directory
                    base = f.parent
                    for _ in range(node.level - 1):
                        base = base.parent
                    if not base.is_relative_to(root):
                        continue
            for parts in found:
                if not relative and not local.setdefault(parts[0], is_local_module(parts[0], root)):
                    continue
                for k in range(1, len(parts) + 1):  # importing a.b runs a/__init__.py and a/b.py
                    cand = base.joinpath(*parts[:k])
                    for target in (cand.with_suffix(".py"), cand / "__init__.py"):
                        if target.is_file():
                            todo.append(target.resolve())
    return sorted(seen)


def source_files_digest(path) -> str:
    """SHA-256 of a Python file and of the local modules it imports (:func:`source_files`): names and bytes."""
    files = source_files(path)
    root = Path(path).resolve().parent
    h = hashlib.sha256()
    for f in files:
        rel = f.relative_to(root) if f.is_relative_to(root) else f
        data = f.read_bytes()
        h.update(str(rel).encode() + b"\0" + struct.pack("<Q", len(data)) + data)
    return h.hexdigest()
