"""A small linear system watched by a path of three networked sensors: a user model for the consensus design.

``cfdesign design examples/linear_network_model.py --sigma 0.01 --beta 0.01 --out d`` gives a feasible
schedule (exit 0); the paper's sigma = beta = 0.1 on the same model does too or reports where it fails.
The model is linear, so the default scalings derived from its Hessians are U = 0 and V_i = 0.
"""
import casadi as ca
import numpy as np

from designer import AttackSpec, FDISignal, Gaussian, Model, SensorNetwork, Sensor

STEPS = 40
X0 = [1.0, -0.5]
NETWORK = SensorNetwork.from_edges(3, [(0, 1), (1, 2)])
# DoS 0.1 on every channel, FDI 0.05; the attacker adds 0.2 sin(s) to both components of a packet
ATTACKS = AttackSpec(dos=0.1, fdi=0.05, signal=FDISignal(amplitude=0.2))


def model() -> Model:
    x = ca.SX.sym("x", 2)
    A = ca.DM([[0.95, 0.1], [0.0, 0.9]])
    angles = (0.0, 0.7, 1.4)  # each sensor sees the state in its own rotated frame
    sensors = [
        Sensor(f"s{i + 1}", ca.mtimes(ca.DM([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]]), x),
               Gaussian.zero_mean(0.05 * np.eye(2)))
        for i, a in enumerate(angles)
    ]
    return Model("linear-network", x, ca.mtimes(A, x), sensors,
                 process_noise=Gaussian.zero_mean(0.01 * np.eye(2)),
                 prior=Gaussian(X0, 0.1 * np.eye(2)))
