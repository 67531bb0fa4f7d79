"""Scenario definitions: named, documented, overridable parameters around a model."""
from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Callable, Mapping, NamedTuple

import numpy as np

from designer.attacks import (MISSING_BOUND, AttackSpec, BiasFDI, BinarySensorChannel, ResolvedAttacks,
                              RoundRobinDeception)
from designer.design import DesignOptions
from designer.network import SensorNetwork
from designer.regions import resolve_regions
from designer.simulate import Trajectory, check_inputs, simulate
from designer.validation import InputError, as_vector
from filters.encryption import EncryptedChannel

if TYPE_CHECKING:  # CasADi is imported where a model is built, not here
    from designer.model import Model

__all__ = ["Param", "Scenario", "ScenarioSpec", "Outline", "parse_assignments", "CHANNEL_TYPES"]

# What a scenario's ``channel`` (a model file's ``CHANNEL``) may be: one law per particle-filter paper.
CHANNEL_TYPES = (RoundRobinDeception, EncryptedChannel, BinarySensorChannel, BiasFDI)

_KINDS = ("float", "int", "array", "choice", "bool")


@dataclass(frozen=True)
class Param:
    """One named scenario parameter.

    Parameters
    ----------
    name : str
    default : object
        Default value (a float, int, bool, nested list or choice name).
    doc : str
        What it is, with its unit.
    kind : {'float', 'int', 'array', 'choice', 'bool'}
    low, high : float, optional
        Inclusive bounds of a number (or of every entry of an array).
    low_open, high_open : bool
        Make the corresponding bound exclusive.
    shape : tuple, optional
        Shape of an array parameter; ``None`` entries allow any size.
    choices : tuple of str
        Allowed names of a ``choice`` parameter (a named setting).
    source : str
        ``'paper'`` when the value is published, ``'assumption'`` when it fills a gap.
    """

    name: str
    default: Any
    doc: str
    kind: str = "float"
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    shape: tuple | None = None
    choices: tuple[str, ...] = ()
    source: str = "paper"

    def __post_init__(self):
        if self.kind not in _KINDS:
            raise ValueError(f"unknown parameter kind {self.kind!r}")
        self.validate(self.default)

    def allowed(self) -> str:
        """Human-readable allowed range."""
        if self.kind == "choice":
            return "one of " + ", ".join(self.choices)
        if self.kind == "bool":
            return "true or false"
        lo = "-inf" if self.low is None else repr(self.low)
        hi = "inf" if self.high is None else repr(self.high)
        rng = f"{'(' if self.low_open or self.low is None else '['}{lo}, {hi}{')' if self.high_open or self.high is None else ']'}"
        what = {"float": "a number", "int": "an integer", "array": "an array"}[self.kind]
        if self.kind == "array" and self.shape is not None:
            dims = ", ".join("n" if s is None else str(s) for s in self.shape)
            what = f"an array of shape ({dims})"
        return f"{what} in {rng}"

    def _bad(self, value) -> InputError:
        return InputError(f"parameter {self.name} must be {self.allowed()}, got {value!r}")

    def _check_range(self, arr: np.ndarray, value) -> None:
        if not np.all(np.isfinite(arr)):
            raise self._bad(value)
        if self.low is not None and np.any(arr <= self.low if self.low_open else arr < self.low):
            raise self._bad(value)
        if self.high is not None and np.any(arr >= self.high if self.high_open else arr > self.high):
            raise self._bad(value)

    def validate(self, value):
        """Coerce ``value`` to this parameter's type or raise :class:`InputError`."""
        if self.kind == "choice":
            if value not in self.choices:
                raise self._bad(value)
            return value
        if self.kind == "bool":
            if isinstance(value, (bool, np.bool_)):
                return bool(value)
            raise self._bad(value)
        if self.kind == "int":
            if isinstance(value, bool) or not isinstance(value, (int, np.integer, float)):
                raise self._bad(value)
            if not np.isfinite(float(value)) or float(value) != int(value):
                raise self._bad(value)
            self._check_range(np.asarray(float(value)), value)
            return int(value)
        if self.kind == "float":
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise self._bad(value)
            self._check_range(np.asarray(float(value)), value)
            return float(value)
        try:
            arr = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            raise self._bad(value) from None
        if self.shape is not None:
            if arr.ndim != len(self.shape) or any(s is not None and s != a for s, a in zip(self.shape, arr.shape)):
                raise self._bad(value)
        self._check_range(arr, value)
        return arr.tolist()

    def parse(self, text: str):
        """Parse a command-line value (``--set NAME=TEXT``)."""
        text = text.strip()
        if self.kind == "choice":
            return self.validate(text)
        if self.kind == "bool":
            low = text.lower()
            if low in ("true", "1", "yes", "on"):
                return True
            if low in ("false", "0", "no", "off"):
                return False
            raise self._bad(text)
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            if self.kind == "array":
                try:
                    value = [float(v) for v in text.split(",")]
                except ValueError:
                    raise self._bad(text) from None
            else:
                raise self._bad(text) from None
        if self.kind in ("float", "int") and isinstance(value, list):
            raise self._bad(text)
        return self.validate(value)

    def describe(self) -> dict:
        d = {"name": self.name, "default": self.default, "kind": self.kind, "allowed": self.allowed(),
             "doc": self.doc, "source": self.source}
        if self.choices:
            d["choices"] = list(self.choices)
        return d


@dataclass(frozen=True, eq=False)
class Scenario:
    """A built scenario: the model, its network and everything needed to simulate it.

    Attributes
    ----------
    name : str
    model : Model
    params : dict
        The parameter values used (defaults merged with overrides).
    assumptions : tuple of str
        Every value chosen where the paper is silent, in words.
    steps : int
        Default horizon of the paper's study.
    x0 : ndarray or None
        True initial state of the paper's study; ``None`` samples it from the prior.
    network : SensorNetwork or None
        Communication graph between the sensors (consensus scenarios), one node per sensor;
        its per-channel probabilities are those of ``attacks``.
    attacks : AttackSpec or None
        What the channels and uplinks suffer (:mod:`designer.attacks`); without it, the
        network's own probabilities with no FDI signal (an FDI probability > 0 then needs a
        bound and is an error).
    design : DesignOptions or None
        The scenario's own design defaults (e.g. its scalings U, V); every option given to a
        command overrides them.
    input_fn : callable or None
        ``input_fn(steps) -> (steps, n_u)`` known inputs.
    channel : one of :data:`CHANNEL_TYPES` or None
        What the sensors' packets suffer on their way to the particle filters of seeds
        000-002 and 004 (:class:`designer.attacks.RoundRobinDeception`,
        :class:`filters.encryption.EncryptedChannel`, :class:`designer.attacks.BinarySensorChannel`,
        :class:`designer.attacks.BiasFDI`); checked against the model.
    regions : tuple of int arrays or None
        The states each node is responsible for (:mod:`designer.regions`; a model file's ``REGIONS``: one list of
        state indices or names per node, or ``"sensed"``), one sorted index array per node once built; the studies
        then score each node on its region and a design states its bound there.
    """

    name: str
    model: Model
    params: Mapping[str, Any]
    assumptions: tuple[str, ...]
    steps: int
    x0: np.ndarray | None = None
    network: SensorNetwork | None = None
    input_fn: Callable[[int], np.ndarray] | None = None
    channel: Any = None
    attacks: AttackSpec | None = None
    design: DesignOptions | None = None
    source: str | None = None  # the built-in name or model file it was loaded from (None: built in memory)
    regions: Any = None  # a model file's REGIONS (designer.regions): resolved to one index array per node
    source_digest: str | None = field(default=None, repr=False)  # a model file's bytes when it was loaded

    def __post_init__(self):
        if self.x0 is not None:  # a model file's X0, the API's x0
            x0 = as_vector("X0", self.x0)
            if x0.shape != (self.model.n_x,):
                raise InputError(f"X0 must have {self.model.n_x} entries (the model's n_x), got {x0.size}")
            object.__setattr__(self, "x0", x0)
        ch = self.channel
        if ch is not None:
            if not isinstance(ch, CHANNEL_TYPES):
                raise InputError(f"CHANNEL must be one of {', '.join(t.__name__ for t in CHANNEL_TYPES)}, got "
                                 f"{type(ch).__name__}")
            ch.check(self.model)
        net = self.network
        if net is None:
            if self.attacks is not None:
                raise InputError(f"scenario {self.name!r} declares attacks but no NETWORK")
            if self.regions is not None:
                raise InputError(f"scenario {self.name!r} declares REGIONS but no NETWORK (a region is a node's)")
            object.__setattr__(self, "_resolution", None)
            return
        if not isinstance(net, SensorNetwork):
            raise InputError(f"NETWORK must be a designer.SensorNetwork, got {type(net).__name__}")
        if net.n_nodes != self.model.n_sensors:
            raise InputError(f"NETWORK has {net.n_nodes} nodes but the model has {self.model.n_sensors} sensors "
                             "(one node per sensor, in the order of the model's sensors)")
        spec = self.attacks
        if spec is None:
            spec = AttackSpec(dos=net.dos_prob, fdi=net.fdi_prob)
        elif not isinstance(spec, AttackSpec):
            raise InputError(f"ATTACKS must be a designer.AttackSpec, got {type(spec).__name__}")
        resolved = spec.resolve(net, self.model.n_x, require_bound=False)  # a command may still give the bound
        object.__setattr__(self, "attacks", spec)
        object.__setattr__(self, "network", resolved.network)
        object.__setattr__(self, "_resolution", resolved)
        if self.design is not None and not isinstance(self.design, DesignOptions):
            raise InputError(f"DESIGN must be a designer.DesignOptions, got {type(self.design).__name__}")
        if self.regions is not None:
            object.__setattr__(self, "regions", resolve_regions(self.regions, self.model, net.n_nodes))

    _resolution: ResolvedAttacks | None = field(init=False, default=None, repr=False)

    @property
    def resolved_attacks(self) -> ResolvedAttacks | None:
        """The attack specification checked against the network (None without a network).

        Raises :class:`InputError` when an FDI probability is > 0 and no bound was given.
        """
        r = self._resolution
        if r is not None and r.delta is None:
            raise MISSING_BOUND
        return r

    def with_attacks(self, *, dos=None, fdi=None, delta=None, amplitude=None) -> "Scenario":
        """The scenario with its attack specification overridden (see :meth:`AttackSpec.override`)."""
        if self.network is None:
            raise InputError(f"scenario {self.name!r} has no sensor network; dos, fdi, delta and amplitude apply "
                             "to network channels")
        if dos is None and fdi is None and delta is None and amplitude is None:
            return self
        return replace(self, attacks=self.attacks.override(dos=dos, fdi=fdi, delta=delta, amplitude=amplitude))

    @property
    def digest(self) -> str:
        """SHA-256 of everything the scenario's numbers depend on: the model's content
        (:attr:`designer.model.Model.digest`), every parameter and number of the network, attacks, design
        defaults, channel, initial state and horizon, the inputs function (its code and its inputs over the
        horizon) and, for a model file, the file's bytes and those of the modules it imports from its own
        directory (:func:`designer.digest.source_files_digest`) — never the file's path.  Stored results
        carry it, so an edited model is never mistaken for the one they were computed with."""
        d = self.__dict__.get("_digest")
        if d is None:
            from designer.digest import content_digest, source_files_digest

            src = self.source
            if src is None:
                origin = None
            elif src.endswith(".py"):
                origin = ("file", self.source_digest or source_files_digest(src))
            else:
                origin = ("built-in", src)
            try:
                inputs = self.inputs(self.steps)
            except Exception as exc:  # noqa: BLE001 - reported where the inputs are used; here a value like any
                inputs = f"inputs({self.steps}) raised {type(exc).__name__}: {exc}"
            d = content_digest(self.name, self.model, self.params, self.assumptions, self.steps, self.x0,
                               self.network, self.attacks, self.design, self.channel, self.input_fn, inputs,
                               origin)
            object.__setattr__(self, "_digest", d)
        return d

    @property
    def operating_point(self) -> tuple[np.ndarray, np.ndarray | None]:
        """``(x0, u0)``: the true initial state (or the prior mean) and the first input."""
        u = self.inputs(1)
        return (self.model.prior.mean if self.x0 is None else np.asarray(self.x0, dtype=float),
                None if u is None else u[0])

    def inputs(self, steps: int) -> np.ndarray | None:
        return None if self.input_fn is None else check_inputs(self.model, steps, self.input_fn(steps))

    def simulate(self, rng: np.random.Generator, steps: int | None = None, *, batch=()) -> Trajectory:
        """Sample a run of the scenario (the paper's fixed ``x0`` when it has one)."""
        steps = self.steps if steps is None else steps
        return simulate(self.model, steps, rng, batch=batch, x0=self.x0, inputs=self.inputs(steps))


class Outline(NamedTuple):
    """What ``cfdesign scenarios`` shows of a scenario besides its parameters, known without building its model."""

    n_x: int
    sensors: int
    steps: int
    assumptions: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class ScenarioSpec:
    """A scenario family: parameters with defaults and a builder.

    ``outline(values) -> Outline`` (optional) gives the state dimension, the number of sensors, the
    horizon and the assumptions without building the model (a CasADi model and its NumPy translation
    take seconds): :meth:`describe` uses it when given, and builds the scenario otherwise.
    """

    name: str
    title: str
    paper: str
    summary: str
    params: tuple[Param, ...]
    builder: Callable[[dict], Scenario]
    outline: Callable[[dict], Outline] | None = None

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        if not self.params:
            raise InputError(f"scenario {self.name} has no parameter {name!r}: it takes no --set parameters (a model "
                             "file's values, e.g. X0 or STEPS, are set in the file)")
        known = ", ".join(p.name for p in self.params)
        raise InputError(f"scenario {self.name} has no parameter {name!r}; known parameters: {known}")

    def defaults(self) -> dict:
        return {p.name: p.default for p in self.params}

    def _values(self, overrides: Mapping[str, Any] | None) -> dict:
        # the defaults in their validated form too (a float parameter's 30 is 30.0, an array a list), so that a
        # scenario rebuilt from its parameters (ScenarioRef) has the very same values as the one built here
        values = {p.name: p.validate(p.default) for p in self.params}
        for name, value in (overrides or {}).items():
            values[name] = self.param(name).validate(value)
        return values

    def build(self, overrides: Mapping[str, Any] | None = None) -> Scenario:
        """Build the scenario with ``overrides`` (name -> value) applied and validated."""
        return self.builder(self._values(overrides))

    def outlined(self, overrides: Mapping[str, Any] | None = None) -> Outline:
        """The :class:`Outline` of the scenario with ``overrides``: from ``outline`` when given, else built."""
        if self.outline is not None:
            return self.outline(self._values(overrides))
        sc = self.build(overrides)
        return Outline(sc.model.n_x, sc.model.n_sensors, sc.steps, tuple(sc.assumptions))

    def describe(self) -> dict:
        o = self.outlined()
        return {
            "name": self.name,
            "title": self.title,
            "paper": self.paper,
            "summary": self.summary,
            "n_x": o.n_x,
            "sensors": o.sensors,
            "steps": o.steps,
            "parameters": [p.describe() for p in self.params],
            "assumptions": list(o.assumptions),
        }


def parse_assignments(spec: ScenarioSpec, assignments) -> dict:
    """Parse ``NAME=VALUE`` strings against a scenario's parameters."""
    out = {}
    for item in assignments or ():
        if "=" not in item:
            raise InputError(f"--set expects NAME=VALUE, got {item!r}")
        name, text = item.split("=", 1)
        out[name.strip()] = spec.param(name.strip()).parse(text)
    return out
