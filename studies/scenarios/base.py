"""Scenario definitions: named, documented, overridable parameters around a model."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import numpy as np

from designer.model import Model
from designer.network import SensorNetwork
from designer.simulate import Trajectory, simulate
from designer.validation import InputError

__all__ = ["Param", "Scenario", "ScenarioSpec", "parse_assignments"]

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
            if float(value) != int(value):
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
        Communication graph between the sensors (consensus scenarios).
    input_fn : callable or None
        ``input_fn(steps) -> (steps, n_u)`` known inputs.
    extras : dict
        Scenario-specific settings for the channel and attack simulators.
    """

    name: str
    model: Model
    params: Mapping[str, Any]
    assumptions: tuple[str, ...]
    steps: int
    x0: np.ndarray | None = None
    network: SensorNetwork | None = None
    input_fn: Callable[[int], np.ndarray] | None = None
    extras: Mapping[str, Any] = field(default_factory=dict)

    def inputs(self, steps: int) -> np.ndarray | None:
        return None if self.input_fn is None else np.asarray(self.input_fn(steps), dtype=float)

    def simulate(self, rng: np.random.Generator, steps: int | None = None, *, batch=()) -> Trajectory:
        """Sample a run of the scenario (the paper's fixed ``x0`` when it has one)."""
        steps = self.steps if steps is None else steps
        return simulate(self.model, steps, rng, batch=batch, x0=self.x0, inputs=self.inputs(steps))


@dataclass(frozen=True, eq=False)
class ScenarioSpec:
    """A scenario family: parameters with defaults and a builder."""

    name: str
    title: str
    paper: str
    summary: str
    params: tuple[Param, ...]
    builder: Callable[[dict], Scenario]

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        known = ", ".join(p.name for p in self.params)
        raise InputError(f"scenario {self.name} has no parameter {name!r}; known parameters: {known}")

    def defaults(self) -> dict:
        return {p.name: p.default for p in self.params}

    def build(self, overrides: Mapping[str, Any] | None = None) -> Scenario:
        """Build the scenario with ``overrides`` (name -> value) applied and validated."""
        values = self.defaults()
        for name, value in (overrides or {}).items():
            values[name] = self.param(name).validate(value)
        return self.builder(values)

    def describe(self) -> dict:
        sc = self.build()
        return {
            "name": self.name,
            "title": self.title,
            "paper": self.paper,
            "summary": self.summary,
            "n_x": sc.model.n_x,
            "sensors": sc.model.n_sensors,
            "steps": sc.steps,
            "parameters": [p.describe() for p in self.params],
            "assumptions": list(sc.assumptions),
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
