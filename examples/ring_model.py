"""A damped oscillator watched by four scalar sensors on a ring, with attacks per edge (the README's model)."""
import casadi as ca
import numpy as np

from designer import AttackSpec, FDISignal, Gaussian, Model, SensorNetwork, Sensor

STEPS = 60                                   # default horizon
X0 = [1.0, 0.0]                              # true initial state (omit: drawn from the prior)
NETWORK = SensorNetwork.from_edges(4, [(0, 1), (1, 2), (2, 3), (3, 0)])
ATTACKS = AttackSpec(dos=0.1,                                 # DoS on every channel
                     fdi={(0, 1): 0.2, (2, 3): 0.05},         # FDI per undirected edge, 0 elsewhere
                     signal=FDISignal(amplitude=0.3, components=(0,)))  # xi = 0.3 sin(s) on x[0]


def model() -> Model:
    x = ca.SX.sym("x", 2)
    f = ca.vertcat(x[0] + 0.1 * x[1], x[1] - 0.1 * (ca.sin(x[0]) + 0.2 * x[1]))
    sensors = [Sensor(f"s{i}", np.cos(0.5 * i) * x[0] + np.sin(0.5 * i) * x[1], Gaussian.zero_mean([[0.05]]))
               for i in range(4)]
    return Model("oscillator", x, f, sensors, process_noise=Gaussian.zero_mean(1e-3 * np.eye(2)),
                 prior=Gaussian(X0, 0.05 * np.eye(2)), state_names=("angle", "rate"))
