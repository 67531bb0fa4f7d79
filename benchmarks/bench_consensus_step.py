"""Cost of one consensus-filter step of all nodes, and its growth with the network size.

A step is the prediction, the bound (26), the exchange, the gain (30) and the
bound (27) at every node.  Networks: rings of 8, 64 and 512 cameras watching the
indoor robot (cameras on a circle around the room; attacks on).  The cost per
node and step must stay flat (linear growth): ``--check`` exits 1 when the cost
per node at the largest size exceeds ``LINEAR_TOLERANCE`` times the cost per node
at the smallest (both measured in this run).

Run: ``python benchmarks/bench_consensus_step.py [--sizes 8 64 512] [--check]``
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from designer.attacks import FDISignal
from filters.attacks import simulate_attacks
from filters.consensus import run_consensus
from studies.consensus_design import consensus_design
from studies.scenarios import load_scenario

LINEAR_TOLERANCE = 2.0
STEPS = 4


def ring_robot(n: int):
    ang = 2 * np.pi * np.arange(n) / n
    cams = np.stack([1.2 + 1.0 * np.cos(ang), 0.9 + 0.8 * np.sin(ang)], axis=1).tolist()
    edges = [[i, (i + 1) % n] for i in range(n)]
    return load_scenario("indoor-robot", {"camera_positions": cams, "edges": edges, "steps": STEPS})


def time_step(n: int, repeats: int) -> float:
    sc = ring_robot(n)
    rng = np.random.default_rng(0)
    traj = sc.simulate(rng)
    des = consensus_design(sc)
    att = simulate_attacks(sc.network, STEPS, 3, rng, signal=FDISignal(1.5, (0, 1)))
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        run_consensus(sc.model, sc.network, traj.z, des, inputs=traj.inputs, attacks=att)
        best = min(best, time.perf_counter() - t)
    return best / STEPS


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[8, 64, 512])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--check", action="store_true")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    rows = []
    for n in args.sizes:
        t = time_step(n, args.repeats)
        rows.append({"nodes": n, "step_s": t, "per_node_s": t / n})
    base = rows[0]["per_node_s"]
    print(f"{'nodes':>6s} {'one step (ms)':>14s} {'per node (us)':>14s} {'per node / smallest':>20s}")
    for r in rows:
        r["per_node_ratio"] = r["per_node_s"] / base
        print(f"{r['nodes']:6d} {r['step_s'] * 1e3:14.2f} {r['per_node_s'] * 1e6:14.1f} {r['per_node_ratio']:20.2f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)
    if args.check and rows[-1]["per_node_ratio"] > LINEAR_TOLERANCE:
        print(f"FAIL: cost per node grew {rows[-1]['per_node_ratio']:.2f}x (tolerance {LINEAR_TOLERANCE})",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
