"""A heat field of ROWS x COLS cells watched by one networked sensor per cell (issue 41's field).

Each cell's temperature (one state per cell, row by row) diffuses to its 4 neighbours (no flux across the border),
leaks towards 0 and carries a small nonlinearity:

    T_i' = T_i + 0.1 sum_{j ~ i} (T_j - T_i) - 0.02 T_i + 0.01 sin(T_i) + w_i,   w ~ N(0, 1e-3 I).

The node of a cell reads its own cell: a linear probe (noise 0.05) or, at every fifth cell, a thermistor reading
exp(0.3 T) (noise 0.02).  The network is the grid's adjacency (4 neighbours, d_max 4); DoS 0.1 and FDI 0.05 on every
channel, the injected signal 0.1 sin(s) on every cell.  The size is ``ROWS, COLS`` below (8 x 8 = 64 cells, the
size of the issue's target); ``benchmarks/bench_design_scale.py --models field`` writes copies of other sizes.
"""
import casadi as ca
import numpy as np

from designer import AttackSpec, FDISignal, Gaussian, Model, SensorNetwork, Sensor

ROWS, COLS = 8, 8
N = ROWS * COLS
STEPS = 60


def _neighbours(i: int) -> list[int]:
    r, c = divmod(i, COLS)
    return [a * COLS + b for a, b in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1))
            if 0 <= a < ROWS and 0 <= b < COLS]


NETWORK = SensorNetwork.from_edges(N, [(i, j) for i in range(N) for j in _neighbours(i) if i < j])
ATTACKS = AttackSpec(dos=0.1, fdi=0.05, signal=FDISignal(amplitude=0.1))


def model() -> Model:
    x = ca.SX.sym("x", N)
    f = ca.vertcat(*[x[i] + 0.1 * sum(x[j] - x[i] for j in _neighbours(i)) - 0.02 * x[i] + 0.01 * ca.sin(x[i])
                     for i in range(N)])
    sensors = [Sensor(f"thermistor{i}", ca.exp(0.3 * x[i]), Gaussian.zero_mean([[0.02 ** 2]])) if i % 5 == 0 else
               Sensor(f"cell{i}", x[i], Gaussian.zero_mean([[0.05 ** 2]])) for i in range(N)]
    mean = [0.5 + (r + c) / max(ROWS + COLS - 2, 1) for r in range(ROWS) for c in range(COLS)]  # a warm corner
    return Model(f"field{ROWS}x{COLS}", x, f, sensors, process_noise=Gaussian.zero_mean(1e-3 * np.eye(N)),
                 prior=Gaussian(mean, 0.04 * np.eye(N)))
