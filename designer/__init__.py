"""The model layer and the design layer.

Model layer: symbolic models (CasADi), noises, sensor networks, the attack
specification a model declares.  Design layer: the consensus design's parameters and
options, the covariance-bound recursions of the consensus paper (``bounds``), the convex
tuning layer (``tuning``), linearisation scalings, gain schedules and steady-state
feasibility.

The names below are imported from their modules on first use (``from designer import
Model`` imports :mod:`designer.model` and CasADi then), so that a program that needs only
part of the package, such as ``cfdesign --help``, does not pay for the rest.
"""
from __future__ import annotations

import importlib

# ``simulate`` is both a submodule and the function it defines: imported here, so that the package
# attribute is the function whichever is imported first (the module is light: NumPy only).
from .simulate import Trajectory, simulate
from .validation import CfdesignError, ComputationError, InputError

# name -> the module that defines it (imported on first use)
_EXPORTS = {
    "AttackSpec": "attacks", "FDISignal": "attacks",
    "to_numpy": "codegen",
    "ConsensusDesign": "design", "DesignOptions": "design",
    "Model": "model", "Sensor": "model",
    "SensorNetwork": "network",
    "Gaussian": "noise", "GaussianMixture": "noise", "Noise": "noise", "PolarVelocityPrior": "noise",
    "TruncatedGaussian": "noise", "UniformBox": "noise", "spawn_generators": "noise",
}

__all__ = [
    "Model", "Sensor", "SensorNetwork", "AttackSpec", "FDISignal", "DesignOptions", "ConsensusDesign", "Noise",
    "Gaussian", "GaussianMixture", "TruncatedGaussian", "UniformBox", "PolarVelocityPrior", "spawn_generators",
    "simulate", "Trajectory", "to_numpy", "CfdesignError", "InputError", "ComputationError",
]


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None and not name.startswith("_"):
        try:  # a submodule used as an attribute (``designer.noise`` after ``import designer``)
            return importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":
                raise
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
