"""Built-in scenarios, user model files and in-memory models: everything a command can run on."""
from __future__ import annotations

import builtins
import functools
import importlib.machinery
import importlib.util
import pickle
import re
import sys
import types
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from designer.attacks import AttackSpec
from designer.design import DesignOptions
from designer.network import SensorNetwork, connectivity_checked_later
from designer.validation import InputError

from . import four_tank, indoor_robot, switching_2d, target_binary_energy, target_range_bearing
from .base import CHANNEL_TYPES, Param, Scenario, ScenarioSpec, parse_assignments

__all__ = ["SCENARIOS", "Param", "Scenario", "ScenarioSpec", "get_spec", "load_scenario", "parse_assignments",
           "scenario_of", "MODEL_FILE_NAMES", "ScenarioRef", "reference", "CHANNEL_TYPES", "model_inputs"]

SCENARIOS: dict[str, ScenarioSpec] = {
    m.SPEC.name: m.SPEC
    for m in (target_range_bearing, switching_2d, target_binary_energy, indoor_robot, four_tank)
}

# What a model file may define (README, "Defining your own model").
MODEL_FILE_NAMES = {
    "model": "function model() -> designer.Model (required unless SPEC is given)",
    "SPEC": "a studies.scenarios.ScenarioSpec with named parameters (--set NAME=VALUE), instead of model()",
    "STEPS": "default horizon (an integer >= 1; default 50)",
    "X0": "true initial state (default: drawn from the prior in every run)",
    "inputs": "function inputs(steps) -> (steps, n_u) known inputs, for models with inputs",
    "NETWORK": "a designer.SensorNetwork with one node per sensor (the consensus filter's graph)",
    "ATTACKS": "a designer.AttackSpec: DoS/FDI per channel, the FDI signal and its bound, uplinks",
    "CHANNEL": "what the packets suffer on their way to the particle filters: a designer.attacks.RoundRobinDeception "
               "(rrp-deception), filters.encryption.EncryptedChannel (encrypted-switching), "
               "designer.attacks.BinarySensorChannel (binary-multi-attack) or designer.attacks.BiasFDI "
               "(fdi-four-tank)",
    "DESIGN": "a designer.DesignOptions with the model's design defaults (e.g. u_scale, v_scale)",
    "REGIONS": "the states each node is responsible for: one list of state indices or names per node, or 'sensed' "
               "(each node's region: the states its own sensor's measurement depends on); the studies then score "
               "each node on its region (rmse_region) and a design states its bound there (designer.regions)",
    "ASSUMPTIONS": "a list of strings carried into every result",
}


_IMPORT = builtins.__import__


class _SiblingImport:
    """``__import__`` for the code of a model file and of its siblings: a top-level name that is the file's
    own sibling (:func:`designer.digest.is_local_module`) is taken from the file's private package
    (``cfdesign_user_<digest>.name``), every other import is Python's own."""

    def __init__(self, package: str, folder: Path):
        self.package, self.folder = package, folder
        self.local: dict[str, bool] = {}

    def is_local(self, name: str) -> bool:
        from designer.digest import is_local_module

        if name not in self.local:
            self.local[name] = is_local_module(name, self.folder)
        return self.local[name]

    def __call__(self, name, globals=None, locals=None, fromlist=(), level=0):
        top = name.partition(".")[0]
        if level or not self.is_local(top):
            return _IMPORT(name, globals, locals, fromlist, level)
        module = _IMPORT(f"{self.package}.{name}", globals, locals, fromlist, 0)
        return module if fromlist else sys.modules[f"{self.package}.{top}"]


class _SiblingLoader(importlib.machinery.SourceFileLoader):
    """Runs a model file or a sibling module with :class:`_SiblingImport` as its ``__import__``, compiled from
    its bytes as they are now (no bytecode cache read or written beside the user's files)."""

    def __init__(self, fullname: str, path: str, importer: _SiblingImport):
        super().__init__(fullname, path)
        self.importer = importer

    def get_code(self, fullname):
        return self.source_to_code(self.get_data(self.path), self.path)

    def exec_module(self, module):
        module.__builtins__ = dict(vars(builtins), __import__=self.importer)
        super().exec_module(module)


class _SiblingFinder:
    """Finds the modules of a model file's private package in the file's directory, loaded by
    :class:`_SiblingLoader` (on ``sys.meta_path`` from the first model file on)."""

    cfdesign_user_modules = True  # designer.digest leaves this finder out when it looks for installed modules
    packages: dict[str, _SiblingImport] = {}  # private package name -> the import of its files

    def find_spec(self, fullname, path=None, target=None):
        package, dot, _ = fullname.partition(".")
        importer = self.packages.get(package)
        if importer is None or not dot:
            return None
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        if spec is None or not isinstance(spec.loader, importlib.machinery.SourceFileLoader):
            return spec  # a namespace package (a directory without __init__.py) or a compiled module
        return importlib.util.spec_from_file_location(
            fullname, spec.origin, loader=_SiblingLoader(fullname, spec.origin, importer),
            submodule_search_locations=spec.submodule_search_locations)


_FINDER = _SiblingFinder()


def _private_package(path: Path) -> _SiblingImport:
    """A fresh private package for the siblings of the model file ``path`` (none of its modules imported yet).

    Named by the content of the file and its siblings (:func:`designer.digest.source_files_digest`), so its
    functions are named the same wherever the files lie, in every process; never a name a package has.  An
    earlier load's package stays (its functions may still import from it); one of the same name is replaced.
    """
    from designer.digest import source_files_digest

    folder = path.resolve().parent
    package = f"cfdesign_user_{source_files_digest(path)[:16]}"
    for name in [n for n in sys.modules if n == package or n.startswith(package + ".")]:
        del sys.modules[name]
    importer = _SiblingImport(package, folder)
    module = types.ModuleType(package, f"the sibling modules of the model file {str(path)!r}")
    module.__path__ = [str(folder)]
    module.__spec__ = importlib.machinery.ModuleSpec(package, None, is_package=True)
    module.__spec__.submodule_search_locations = module.__path__
    sys.modules[package] = module
    _SiblingFinder.packages[package] = importer
    if _FINDER not in sys.meta_path:
        sys.meta_path.insert(0, _FINDER)
    importlib.invalidate_caches()  # a sibling written since the last look at the directory is seen
    return importer


def _user_call(what: str, fn, *args):
    """``fn(*args)``, code of a user's model file (``what`` names it): any failure, an exit included, is an
    InputError naming it (a Ctrl-C stays an interruption)."""
    try:
        return fn(*args)
    except InputError as exc:
        raise InputError(f"{what}: {exc}") from exc
    except SystemExit as exc:  # sys.exit() in a model file would end cfdesign with nothing written
        raise InputError(f"{what} called sys.exit({exc.code!r}); a model file must not exit") from None
    except Exception as exc:  # noqa: BLE001 - a user's code: one line, exit 2
        plain = re.sub(r"\bcfdesign_user_[0-9a-f]{16}\.", "", str(exc))  # a sibling by the name the file uses
        raise InputError(f"{what} failed: {type(exc).__name__}: {plain}") from exc


def _guarded(what: str, fn):
    """``fn`` (a function of a user's model file) failing as :func:`_user_call` says."""
    return None if fn is None else functools.wraps(fn)(lambda *args: _user_call(what, fn, *args))


def _load_module(path: Path):
    if not path.is_file():
        raise InputError(f"model file {str(path)!r} does not exist")
    importer = _private_package(path)
    name = f"{importer.package}.{path.stem.replace('.', '_')}"  # in the package: its relative imports work
    spec = importlib.util.spec_from_file_location(name, path, loader=_SiblingLoader(name, str(path), importer))
    module = importlib.util.module_from_spec(spec)
    with connectivity_checked_later():  # a network's node count is checked against the sensors first
        _user_call(f"model file {str(path)!r}", spec.loader.exec_module, module)
    return module


def _file_steps(path: Path, module) -> int:
    steps = getattr(module, "STEPS", 50)
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise InputError(f"STEPS in model file {str(path)!r} must be an integer >= 1, got {steps!r}")
    return int(steps)


def _spec_from_file(path: Path) -> ScenarioSpec:
    """A user model file defines ``SPEC`` (a ScenarioSpec) or ``model()`` returning a Model (see MODEL_FILE_NAMES)."""
    module = _load_module(path)
    if isinstance(getattr(module, "SPEC", None), ScenarioSpec):
        return replace(module.SPEC, builder=_guarded(f"SPEC's builder in {str(path)!r}", module.SPEC.builder),
                       outline=_guarded(f"SPEC's outline in {str(path)!r}", module.SPEC.outline))
    fn = getattr(module, "model", None)
    if not callable(fn):
        raise InputError(f"model file {str(path)!r} must define SPEC (a ScenarioSpec) or a function model()")
    steps = _file_steps(path, module)
    network, attacks = getattr(module, "NETWORK", None), getattr(module, "ATTACKS", None)
    if network is not None and attacks is not None and isinstance(network, SensorNetwork) and (
            np.any(network.dos_prob) or np.any(network.fdi_prob)):
        raise InputError(f"model file {str(path)!r} gives attack probabilities both on NETWORK and in ATTACKS; "
                         "declare them in ATTACKS only")

    def builder(params: dict) -> Scenario:
        m = _user_call(f"model() in {str(path)!r}", fn)
        from designer.model import Model  # the file imported CasADi already

        if not isinstance(m, Model):
            raise InputError(f"model() in {str(path)!r} must return a designer.Model, got {type(m).__name__}")
        if callable(getattr(module, "inputs", None)) != bool(m.n_u):
            raise InputError(f"model file {str(path)!r} defines inputs() but its model has no inputs u" if m.n_u == 0
                             else f"model file {str(path)!r}: the model has inputs u ({m.n_u}); define inputs(steps) "
                                  f"returning them, shape (steps, {m.n_u})")
        try:
            return Scenario(m.name, m, params, tuple(getattr(module, "ASSUMPTIONS", ())), steps,
                            x0=getattr(module, "X0", None), network=network,
                            input_fn=_guarded(f"inputs() in {path.name!r}", getattr(module, "inputs", None)),
                            attacks=attacks, design=getattr(module, "DESIGN", None),
                            channel=getattr(module, "CHANNEL", None), regions=getattr(module, "REGIONS", None))
        except InputError as exc:
            raise InputError(f"model file {str(path)!r}: {exc}") from exc

    return ScenarioSpec(path.stem, path.stem, "user", (module.__doc__ or "").strip(), (), builder)


def get_spec(name: str) -> ScenarioSpec:
    """The built-in scenario ``name`` or the scenario of a user model file (``*.py``)."""
    if not isinstance(name, (str, Path)):
        raise InputError(f"scenario must be a built-in name or a model file path, got {type(name).__name__}")
    name = str(name)
    if name.endswith(".py"):
        return _spec_from_file(Path(name))
    try:
        return SCENARIOS[name]
    except KeyError:
        raise InputError(f"unknown scenario {name!r}; built-in scenarios: {', '.join(SCENARIOS)} "
                         "(or a model file ending in .py)") from None


def load_scenario(name: str, overrides: Mapping[str, Any] | None = None, assignments=()) -> Scenario:
    """Build a scenario by name or model file, with overrides and ``NAME=VALUE`` assignments."""
    from designer.digest import source_files_digest

    is_file = isinstance(name, (str, Path)) and str(name).endswith(".py")
    # the file's bytes (and its local imports') as they are when it is executed, for Scenario.digest
    files = source_files_digest(name) if is_file and Path(name).is_file() else None
    spec = get_spec(name)
    values = dict(overrides or {})
    values.update(parse_assignments(spec, assignments))
    sc = spec.build(values)
    object.__setattr__(sc, "source", str(Path(name).resolve()) if is_file else str(name))
    object.__setattr__(sc, "source_digest", files)
    sc.__dict__.pop("_digest", None)  # the digest covers the source
    return sc


_MEMORY: dict[str, Scenario] = {}  # in-memory scenarios by token; forked workers inherit them
_BUILT: dict[bytes, Scenario] = {}  # scenarios rebuilt from references in this process


@dataclass(frozen=True)
class ScenarioRef:
    """A picklable reference to a scenario, for Monte Carlo tasks that run in other processes.

    ``source`` is a built-in name, an absolute model file path, or ``memory:<token>`` for a
    scenario built in memory (usable in this process and in forked ``--workers``, not on a
    Dask cluster); ``params`` its parameters and ``attacks`` its attack specification
    (with any overrides).
    """

    source: str
    params: tuple
    attacks: AttackSpec | None
    digest: str = ""  # Scenario.digest of the scenario it stands for: a rebuilt one must have the same

    @property
    def in_memory(self) -> bool:
        return self.source.startswith("memory:")

    def build(self) -> Scenario:
        """The scenario (built once per process and reference).

        Raises :class:`InputError` when the model file no longer builds the scenario of the reference
        (edited while a study ran): its runs would not be the runs of the study.
        """
        key = pickle.dumps(self)
        sc = _BUILT.get(key)
        if sc is None:
            if self.in_memory:
                if self.source not in _MEMORY:
                    raise InputError("an in-memory scenario cannot be rebuilt in another process (e.g. on a Dask "
                                     "cluster); write the model to a model file")
                sc = _MEMORY[self.source]
            else:
                sc = load_scenario(self.source, dict(self.params))
            if self.attacks is not None and sc.network is not None:
                from dataclasses import replace

                sc = replace(sc, attacks=self.attacks)
            if self.digest and sc.digest != self.digest:
                raise InputError(f"model {self.source!r} changed after the study started (its content differs from "
                                 "the model the study was planned with); run the command again")
            _BUILT[key] = sc
        return sc


def reference(sc: Scenario) -> ScenarioRef:
    """A :class:`ScenarioRef` that rebuilds ``sc`` (registering it in memory when it has no source).

    ``sc`` itself stands for the reference in this process (and in processes forked from it).
    """
    params = tuple(sorted((k, v.tolist() if isinstance(v, np.ndarray) else v) for k, v in sc.params.items()))
    if sc.source is None:
        token = f"memory:{id(sc)}"
        _MEMORY[token] = sc
        ref = ScenarioRef(token, params, None, sc.digest)
    else:
        ref = ScenarioRef(sc.source, params, sc.attacks, sc.digest)
    _BUILT.setdefault(pickle.dumps(ref), sc)
    return ref


def scenario_of(target, *, network: SensorNetwork | None = None, attacks: AttackSpec | None = None,
                design: DesignOptions | None = None, steps: int | None = None, x0=None,
                inputs: Callable[[int], np.ndarray] | None = None, overrides: Mapping[str, Any] | None = None,
                assignments=(), channel=None) -> Scenario:
    """What every public function runs on: a built-in name, a model file path, a Scenario or a Model.

    Parameters
    ----------
    target : str, path, Scenario or designer.Model
        A built-in scenario name, a ``.py`` model file, a built :class:`Scenario`, or an
        in-memory model (then ``network``, ``attacks``, ``design``, ``steps``, ``x0`` and
        ``inputs`` and ``channel`` play the part of the model file's ``NETWORK``, ``ATTACKS``,
        ``DESIGN``, ``STEPS``, ``X0``, ``inputs`` and ``CHANNEL``; ``steps`` applies to a Model
        only, the commands take their own ``steps``).
    overrides, assignments
        Named scenario parameters (built-ins and ``SPEC`` files).
    """
    from designer.model import Model  # here: listing the scenarios needs no CasADi

    if x0 is not None:  # named as the caller gave it (a model file's is X0, checked by the Scenario)
        from designer.validation import as_vector

        x0 = as_vector("x0", x0)
        n_x = target.n_x if isinstance(target, Model) else None
        if n_x is not None and x0.size != n_x:
            raise InputError(f"x0 must have {n_x} entries (the model's n_x), got {x0.size}")
    if isinstance(target, Model):
        if overrides or assignments:
            raise InputError("an in-memory Model has no named parameters to override")
        return Scenario(target.name, target, {}, (), 50 if steps is None else int(steps), x0=x0, network=network,
                        input_fn=inputs, attacks=attacks, design=design, channel=channel)
    given = {k: v for k, v in (("network", network), ("attacks", attacks), ("design", design), ("x0", x0),
                               ("inputs", inputs), ("channel", channel)) if v is not None}
    if isinstance(target, Scenario):
        if overrides or assignments:
            raise InputError("a built Scenario has no parameters to override; build it with them")
        sc = target
    else:
        sc = load_scenario(target, overrides, assignments)
    if given:
        from dataclasses import replace

        if "inputs" in given:
            given["input_fn"] = given.pop("inputs")
        sc = replace(sc, **given, source=None)  # no longer what its source builds: keep it in memory
    return sc


def model_inputs(scenario) -> list[tuple]:
    """The files a model given as ``scenario`` is read from (a model file, a Scenario built from one, or a sequence of
    them; none for a built-in or in-memory model): the file and the modules of its directory that it imports
    (:func:`designer.digest.source_files`), as :func:`designer.fileio.check_apart` takes its inputs."""
    from designer.digest import source_files

    found = []
    for s in scenario if isinstance(scenario, (list, tuple)) else [scenario]:
        path = getattr(s, "source", s)
        if isinstance(path, (str, Path)) and str(path).endswith(".py") and Path(path).is_file():
            first = Path(path).resolve()
            found += [("scenario", "the model file", path),
                      ("scenario", "a module imported by the model file", [f for f in source_files(path)
                                                                            if f != first])]
    return found
