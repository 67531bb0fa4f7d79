"""The model layer: symbolic models, noise, sensor networks (and, later, bounds and tuning)."""
from .codegen import to_numpy
from .model import Model, Sensor
from .network import SensorNetwork
from .noise import Gaussian, GaussianMixture, Noise, PolarVelocityPrior, TruncatedGaussian, UniformBox, spawn_generators
from .simulate import Trajectory, simulate
from .validation import CfdesignError, ComputationError, InputError

__all__ = [
    "Model", "Sensor", "SensorNetwork", "Noise", "Gaussian", "GaussianMixture", "TruncatedGaussian", "UniformBox",
    "PolarVelocityPrior", "spawn_generators", "simulate", "Trajectory", "to_numpy",
    "CfdesignError", "InputError", "ComputationError",
]
