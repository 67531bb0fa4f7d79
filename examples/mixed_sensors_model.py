"""A constant-velocity target watched by sensors of three kinds on a star network: range-bearing, range-only
and bearing-only (measurement dimensions 2, 1 and 1), with attacks declared per edge.

    cfdesign design examples/mixed_sensors_model.py --mode tuned --out d
    cfdesign study comparison examples/mixed_sensors_model.py --runs 20 --out c

State [px (m), vx (m/s), py (m), vy (m/s)]; bearings in radians (declared as angles, so every filter wraps
their residuals).  The hub (sensor 0, range-bearing) talks to every other sensor; the link to the far
bearing-only sensor is the one the attacker jams most.
"""
import casadi as ca
import numpy as np

from designer import AttackSpec, FDISignal, Gaussian, Model, SensorNetwork, Sensor

STEPS = 60
X0 = [0.0, 1.0, 10.0, 0.5]
SITES = [(0.0, 0.0), (40.0, 0.0), (0.0, 40.0), (40.0, 40.0), (-20.0, 20.0)]
NETWORK = SensorNetwork.from_edges(5, [(0, 1), (0, 2), (0, 3), (0, 4)])
ATTACKS = AttackSpec(
    dos={(0, 1): 0.1, (0, 2): 0.1, (0, 3): 0.1, (0, 4): 0.3},   # per undirected edge, both directions
    fdi=0.05,                                                   # every channel
    signal=FDISignal(amplitude=2.0, components=(0, 2)),          # 2 sin(s) m on px and py
)
ASSUMPTIONS = ["mixed-sensors example: sensor sites, noises and attack rates are illustrative"]


def model() -> Model:
    x = ca.SX.sym("x", 4)
    dt = 1.0
    f = ca.vertcat(x[0] + dt * x[1], x[1], x[2] + dt * x[3], x[3])
    q = 0.05**2
    Q = q * np.kron(np.eye(2), [[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    sensors = []
    for i, (sx, sy) in enumerate(SITES):
        dx, dy = x[0] - sx, x[2] - sy
        rng, brg = ca.sqrt(dx**2 + dy**2), ca.atan2(dy, dx)
        if i == 0:
            sensors.append(Sensor("hub", ca.vertcat(rng, brg), Gaussian.zero_mean(np.diag([1.0, 0.02**2])),
                                  (sx, sy), angles=(1,)))
        elif i in (1, 2):
            sensors.append(Sensor(f"range{i}", rng, Gaussian.zero_mean([[1.0]]), (sx, sy)))
        else:
            sensors.append(Sensor(f"bearing{i}", brg, Gaussian.zero_mean([[0.02**2]]), (sx, sy), angles=(0,)))
    return Model("mixed-sensors", x, f, sensors, process_noise=Gaussian.zero_mean(Q + 1e-9 * np.eye(4)),
                 prior=Gaussian(X0, np.diag([4.0, 0.25, 4.0, 0.25])),
                 state_names=("px", "vx", "py", "vy"), position_index=(0, 2), velocity_index=(1, 3))
