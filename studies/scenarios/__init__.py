"""Built-in scenarios and loading of user model files."""
from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any, Mapping

from designer.model import Model
from designer.validation import InputError

from . import four_tank, indoor_robot, switching_2d, target_binary_energy, target_range_bearing
from .base import Param, Scenario, ScenarioSpec, parse_assignments

__all__ = ["SCENARIOS", "Param", "Scenario", "ScenarioSpec", "get_spec", "load_scenario", "parse_assignments"]

SCENARIOS: dict[str, ScenarioSpec] = {
    m.SPEC.name: m.SPEC
    for m in (target_range_bearing, switching_2d, target_binary_energy, indoor_robot, four_tank)
}


def _spec_from_file(path: Path) -> ScenarioSpec:
    """A user model file defines ``SPEC`` (a ScenarioSpec) or ``model()`` returning a Model."""
    if not path.is_file():
        raise InputError(f"model file {str(path)!r} does not exist")
    spec = importlib.util.spec_from_file_location(f"cfdesign_user_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except InputError:
        raise
    except Exception as exc:  # a user's file: report, do not crash with a traceback
        raise InputError(f"model file {str(path)!r} failed to load: {type(exc).__name__}: {exc}") from exc
    if isinstance(getattr(module, "SPEC", None), ScenarioSpec):
        return module.SPEC
    fn = getattr(module, "model", None)
    if not callable(fn):
        raise InputError(f"model file {str(path)!r} must define SPEC (a ScenarioSpec) or a function model()")
    steps = int(getattr(module, "STEPS", 50))

    def builder(params: dict) -> Scenario:
        m = fn()
        if not isinstance(m, Model):
            raise InputError(f"model() in {str(path)!r} must return a designer.Model")
        x0 = getattr(module, "X0", None)
        inputs = getattr(module, "inputs", None)
        return Scenario(m.name, m, params, tuple(getattr(module, "ASSUMPTIONS", ())), steps,
                        x0=x0, network=getattr(module, "NETWORK", None), input_fn=inputs)

    return ScenarioSpec(path.stem, path.stem, "user", (module.__doc__ or "").strip(), (), builder)


def get_spec(name: str) -> ScenarioSpec:
    """The built-in scenario ``name`` or the scenario of a user model file (``*.py``)."""
    if name.endswith(".py"):
        return _spec_from_file(Path(name))
    try:
        return SCENARIOS[name]
    except KeyError:
        raise InputError(f"unknown scenario {name!r}; built-in scenarios: {', '.join(SCENARIOS)}") from None


def load_scenario(name: str, overrides: Mapping[str, Any] | None = None, assignments=()) -> Scenario:
    """Build a scenario by name or model file, with overrides and ``NAME=VALUE`` assignments."""
    spec = get_spec(name)
    values = dict(overrides or {})
    values.update(parse_assignments(spec, assignments))
    return spec.build(values)
