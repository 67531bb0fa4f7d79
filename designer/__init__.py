"""The model layer and the design layer.

Model layer: symbolic models (CasADi), noises, sensor networks, the attack
specification a model declares.  Design layer: the consensus design's parameters and
options, the covariance-bound recursions of the consensus paper (``bounds``), the convex
tuning layer (``tuning``), linearisation scalings, gain schedules and steady-state
feasibility.
"""
from .attacks import AttackSpec, FDISignal
from .codegen import to_numpy
from .design import ConsensusDesign, DesignOptions
from .model import Model, Sensor
from .network import SensorNetwork
from .noise import Gaussian, GaussianMixture, Noise, PolarVelocityPrior, TruncatedGaussian, UniformBox, spawn_generators
from .simulate import Trajectory, simulate
from .validation import CfdesignError, ComputationError, InputError

__all__ = [
    "Model", "Sensor", "SensorNetwork", "AttackSpec", "FDISignal", "DesignOptions", "ConsensusDesign", "Noise",
    "Gaussian", "GaussianMixture", "TruncatedGaussian", "UniformBox", "PolarVelocityPrior", "spawn_generators",
    "simulate", "Trajectory", "to_numpy", "CfdesignError", "InputError", "ComputationError",
]
