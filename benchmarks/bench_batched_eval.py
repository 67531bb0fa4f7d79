"""Batched model evaluation against hand-written NumPy, side by side in one run.

For every built-in scenario, evaluate ``f`` and all sensors' ``h_i`` at 10^4
particles through the model layer (CasADi expression translated to NumPy) and
through a hand-written NumPy version of the same functions, and report the ratio
of the best-of-N times.  Target: ratio <= 2.  ``--check`` exits 1 when a ratio
exceeds the target.  ``--json FILE`` writes the measurements.

Run: ``python benchmarks/bench_batched_eval.py [--particles 10000] [--check]``
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from studies.scenarios import SCENARIOS

TARGET = 2.0


# ------------------------------------------------------------------ hand-written versions
def hand_range_bearing(p):
    T = p["period"]
    pos = np.asarray(p["sensor_positions"])

    def f(x):
        return np.stack([x[:, 0] + T * x[:, 1], x[:, 1], x[:, 2] + T * x[:, 3], x[:, 3]], axis=-1)

    def h(x):
        out = []
        for sx, sy in pos:
            dx, dy = x[:, 0] - sx, x[:, 2] - sy
            out += [np.sqrt(dx * dx + dy * dy), np.arctan2(dy, dx)]
        return np.stack(out, axis=-1)

    return f, h


def hand_switching(p):
    F = np.asarray(p["F"])

    def f(x, mode):
        t1, t2 = np.tanh(x[:, 0]), np.tanh(x[:, 1])
        lin = x @ F.T
        fx = np.stack([-0.25 * t2, 0.35 * t1], axis=-1)
        gx = np.stack([0.32 * t1, -0.28 * t2], axis=-1)
        r = mode[:, None]
        return lin + r * fx + (1 - r) * gx

    def h(x):
        return np.stack([2 * np.sin(x[:, 0] - x[:, 1]), -2 * np.cos(x[:, 0] + x[:, 1])], axis=-1)

    return f, h


def hand_binary_energy(p):
    T = p["period"]
    pos = np.asarray(p["sensor_positions"])
    scale = p["energy"] * p["ref_distance"] ** p["path_loss"]
    e = -p["path_loss"] / 2

    def f(x):
        return np.stack([x[:, 0] + T * x[:, 1], x[:, 1], x[:, 2] + T * x[:, 3], x[:, 3]], axis=-1)

    def h(x):
        dx = x[:, 0:1] - pos[:, 0]
        dy = x[:, 2:3] - pos[:, 1]
        return scale * np.maximum(dx * dx + dy * dy, 1e-12) ** e

    return f, h


def hand_robot(p):
    cams = np.asarray(p["camera_positions"])
    ku, kv = p["gamma_u"] / p["zf"], p["gamma_v"] / p["zf"]
    b = p["wheel_base"]

    def f(x, u):
        d = 0.5 * (u[0] + u[1])
        return np.stack([x[:, 0] + d * np.cos(x[:, 2]), x[:, 1] + d * np.sin(x[:, 2]),
                         x[:, 2] + (u[0] - u[1]) / b], axis=-1)

    def h(x):
        s, c = np.sin(x[:, 2:3]), np.cos(x[:, 2:3])
        ex = cams[:, 0] - x[:, 0:1]
        ey = cams[:, 1] - x[:, 1:2]
        pp = ku * (-ex * s + ey * c - p["d2"]) + p["p0"]
        qq = kv * (-ex * c - ey * s - p["d1"]) + p["q0"]
        return np.stack([pp, qq], axis=-1).reshape(x.shape[0], -1)

    return f, h


def hand_four_tank(p):
    A = np.asarray(p["tank_area"])
    a = np.asarray(p["outlet_area"])
    k1, k2 = p["pump_gain"]
    g1, g2 = p["valve_split"]
    c = a * np.sqrt(2 * p["gravity"])
    G = np.asarray(p["G"])
    dt = p["period"] / p["substeps"]

    def rate(h, u):
        q = c * np.sqrt(np.maximum(h, 0.0))
        return np.stack([(-q[:, 0] + q[:, 2] + g1 * k1 * u[0]) / A[0],
                         (-q[:, 1] + q[:, 3] + g2 * k2 * u[1]) / A[1],
                         (-q[:, 2] + (1 - g2) * k2 * u[1]) / A[2],
                         (-q[:, 3] + (1 - g1) * k1 * u[0]) / A[3]], axis=-1)

    def f(x, u):
        h = x
        for _ in range(p["substeps"]):
            r1 = rate(h, u)
            r2 = rate(h + 0.5 * dt * r1, u)
            r3 = rate(h + 0.5 * dt * r2, u)
            r4 = rate(h + dt * r3, u)
            h = h + dt / 6 * (r1 + 2 * r2 + 2 * r3 + r4)
        return h

    def h(x):
        return x @ G.T

    return f, h


HAND = {
    "target-range-bearing": hand_range_bearing,
    "switching-2d": hand_switching,
    "target-binary-energy": hand_binary_energy,
    "indoor-robot": hand_robot,
    "four-tank": hand_four_tank,
}


def best_time(fn, repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def run(particles: int, repeats: int) -> list[dict]:
    rows = []
    for name, spec in SCENARIOS.items():
        sc = spec.build()
        m = sc.model
        rng = np.random.default_rng(0)
        X = sc.simulate(rng).x[rng.integers(0, sc.steps + 1, particles)]
        X = X + 0.01 * rng.standard_normal(X.shape)
        u = sc.inputs(1)
        u0 = None if u is None else u[0]
        mode = rng.integers(0, 2, particles) if m.n_modes else None
        hf, hh = HAND[name](sc.params)
        if name == "switching-2d":
            hand = lambda: (hf(X, mode), hh(X))  # noqa: E731
        elif u0 is not None:
            hand = lambda: (hf(X, u0), hh(X))  # noqa: E731
        else:
            hand = lambda: (hf(X), hh(X))  # noqa: E731
        ours = lambda: (m.f(X, 0, u0, mode), m.h_all(X, 1))  # noqa: E731
        # The two versions compute the same numbers (same operations).
        a, b = ours(), hand()
        assert np.allclose(a[0], b[0], rtol=1e-10, atol=1e-10) and np.allclose(a[1], b[1], rtol=1e-10, atol=1e-10), name
        ours(), hand()  # warm-up
        t_ours, t_hand = [], []
        for _ in range(3):  # interleave so that machine noise hits both alike
            t_ours.append(best_time(ours, repeats))
            t_hand.append(best_time(hand, repeats))
        to, th = min(t_ours), min(t_hand)
        rows.append({"scenario": name, "particles": particles, "model_layer_s": to, "hand_numpy_s": th,
                     "ratio": to / th})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=10_000)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--check", action="store_true", help=f"exit 1 if a ratio exceeds {TARGET}")
    ap.add_argument("--json", help="write the measurements to this file")
    args = ap.parse_args(argv)
    rows = run(args.particles, args.repeats)
    print(f"{'scenario':22s} {'model layer':>12s} {'hand numpy':>12s} {'ratio':>6s}   (f + all h_i, "
          f"{args.particles} particles, best of {args.repeats})")
    for r in rows:
        print(f"{r['scenario']:22s} {r['model_layer_s'] * 1e3:10.3f}ms {r['hand_numpy_s'] * 1e3:10.3f}ms "
              f"{r['ratio']:6.2f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)
    worst = max(r["ratio"] for r in rows)
    if args.check and worst > TARGET:
        print(f"FAIL: worst ratio {worst:.2f} exceeds the target {TARGET}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
