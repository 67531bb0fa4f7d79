"""The IEEE 14-bus power grid watched by one networked node per bus: bus voltage angles from line flows and PMUs.

Data: the IEEE 14-bus test case (University of Washington Power Systems Test Case Archive,
https://labs.ece.uw.edu/pstca/pf14/pg_tca14bus.htm; the same as MATPOWER's ``case14`` and pandapower's
``pandapower.networks.case14()``): its 20 branches (lines and transformers) with their series reactances in per unit
on the 100 MVA base, and the bus voltage angles of its AC power-flow solution (degrees), the prior's mean.  Bus 1 is
the slack (angle 0).

The state: the voltage angles (radians) of the 13 other buses, a slow random walk
(``theta' = theta + w``, ``w ~ N(0, 1e-6 I)``: 0.001 rad a step).  Each bus has a node that measures the real power
flow of each of its branches, ``P_ij = sin(theta_i - theta_j) / x_ij`` (per unit, |V| = 1, resistances and taps
neglected; noise 0.01 p.u.), and every third bus (3, 6, 9, 12) also its own angle (a PMU; noise 0.002 rad).  The
network is the grid's branches; DoS 0.1 and FDI 0.05 on every channel, the injected signal 0.01 sin(s) rad on every
angle.  Each node's region (``REGIONS``, docs/model-files.md) is its bus's angle.
``benchmarks/bench_design_scale.py --models grid30 grid118`` writes the same model for the 30- and 118-bus cases (their
data read from pandapower: the block above the line ``# The model``, replaced).
"""
import casadi as ca
import numpy as np

from designer import AttackSpec, FDISignal, Gaussian, Model, SensorNetwork, Sensor

NAME = "ieee14"
SLACK = 1
BRANCHES = [  # (from bus, to bus, series reactance x in p.u.)
    (1, 2, 0.05917), (1, 5, 0.22304), (2, 3, 0.19797), (2, 4, 0.17632), (2, 5, 0.17388),
    (3, 4, 0.17103), (4, 5, 0.04211), (4, 7, 0.20912), (4, 9, 0.55618), (5, 6, 0.25202),
    (6, 11, 0.19890), (6, 12, 0.25581), (6, 13, 0.13027), (7, 8, 0.17615), (7, 9, 0.11001),
    (9, 10, 0.08450), (9, 14, 0.27038), (10, 11, 0.19207), (12, 13, 0.19988), (13, 14, 0.34802),
]
ANGLES_DEG = [0.0, -4.98, -12.72, -10.31, -8.77, -14.22, -13.36, -13.36, -14.94, -15.10, -14.79, -15.08, -15.16,
              -16.03]

# The model (the same for any grid: the data above are the IEEE 14-bus case's).
BUSES = len(ANGLES_DEG)
STEPS = 60


def _lines() -> dict:
    """Each pair of buses once (0-based, lower first) with its susceptance 1/x: parallel branches add."""
    out: dict = {}
    for a, b, x in BRANCHES:
        key = (min(a, b) - 1, max(a, b) - 1)
        out[key] = out.get(key, 0.0) + 1.0 / x
    return out


LINES = _lines()
NETWORK = SensorNetwork.from_edges(BUSES, list(LINES))
ATTACKS = AttackSpec(dos=0.1, fdi=0.05, signal=FDISignal(amplitude=0.01))
STATE_BUSES = [b for b in range(BUSES) if b != SLACK - 1]  # the buses whose angle is a state
#: Each bus's node answers for its own angle; the slack bus (no state) for the angles its flows measure.
REGIONS = ["sensed" if b == SLACK - 1 else [STATE_BUSES.index(b)] for b in range(BUSES)]


def model() -> Model:
    x = ca.SX.sym("theta", BUSES - 1)
    theta = [0.0] * BUSES
    for k, b in enumerate(STATE_BUSES):
        theta[b] = x[k]
    sensors = []
    for b in range(BUSES):
        ends = sorted({j for i, j in LINES if i == b} | {i for i, j in LINES if j == b})  # its branches' other buses
        flows = [ca.sin(theta[b] - theta[k]) * LINES[min(b, k), max(b, k)] for k in ends]
        variances = [0.01 ** 2] * len(flows)
        if (b + 1) % 3 == 0 and b != SLACK - 1:  # a PMU
            flows.append(theta[b])
            variances.append(0.002 ** 2)
        sensors.append(Sensor(f"bus{b + 1}", ca.vertcat(*flows), Gaussian.zero_mean(np.diag(variances))))
    mean = np.radians([ANGLES_DEG[b] for b in STATE_BUSES])
    return Model(NAME, x, x, sensors, process_noise=Gaussian.zero_mean(1e-6 * np.eye(BUSES - 1)),
                 prior=Gaussian(mean, 0.02 ** 2 * np.eye(BUSES - 1)),
                 state_names=tuple(f"theta{b + 1}" for b in STATE_BUSES))
