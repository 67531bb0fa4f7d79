"""A damped pendulum observed by two angle sensors: a user model in a short file.

Run it with ``cfdesign simulate examples/pendulum_model.py --steps 50 --out pend.npz``.
"""
import casadi as ca
import numpy as np

from designer import Gaussian, Model, Sensor

STEPS = 100          # default horizon for the command line
X0 = [0.5, 0.0]      # true initial state (omit to sample it from the prior)


def model() -> Model:
    x = ca.SX.sym("x", 2)                     # [angle (rad), angular rate (rad/s)]
    dt, g, length, damping = 0.05, 9.81, 1.0, 0.2
    f = ca.vertcat(x[0] + dt * x[1],
                   x[1] - dt * (g / length * ca.sin(x[0]) + damping * x[1]))
    sensors = [
        Sensor("encoder", x[0], Gaussian.zero_mean([[1e-3]])),
        Sensor("tip_xy", ca.vertcat(length * ca.sin(x[0]), -length * ca.cos(x[0])),
               Gaussian.zero_mean(4e-4 * np.eye(2))),
    ]
    return Model("pendulum", x, f, sensors,
                 process_noise=Gaussian.zero_mean(np.diag([1e-6, 1e-4])),
                 prior=Gaussian(X0, np.diag([0.05, 0.05])))
