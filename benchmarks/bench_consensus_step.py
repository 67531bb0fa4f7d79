"""Cost of one consensus-filter step of all nodes: per run, and batched over Monte Carlo runs.

A step is the prediction, the bound (26), the exchange, the gain (30) and the bound (27) at
every node (paper mode).  Networks: rings of 8, 64 and 512 cameras watching the indoor robot
(cameras on a circle around the room; attacks on).  Two paths, measured in the same run:

* per run: :func:`filters.consensus.run_consensus`, one run, node by node (best of ``--repeats``);
* batched: :func:`filters.consensus_batch.run_consensus_batch` over ``--runs`` runs (default 500),
  the cost amortised per run and node-step (best of ``--batch-repeats``); its first run is
  checked against the per-run path.

``--check`` exits 1 when

* the cost per node and step is not flat (linear growth): at the largest size it exceeds
  ``LINEAR_TOLERANCE`` times the cost at the smallest, on either path;
* the batched path misses the issue's target, paper mode <= 15 µs per node-step over 500 runs,
  stated as a ratio to the per-run path (350-400 µs per node-step when the target was set):
  batched / per run <= ``TARGET_RATIO`` = 15 / 375 at every size.

The attack realisations of the batch cycle over ``DISTINCT_ATTACKS`` draws (drawing a dense
512 x 512 pattern per run costs more than filtering it; the filter's cost does not depend on
which packets are attacked).  The peak resident memory of the process is reported.

Run: ``python benchmarks/bench_consensus_step.py [--sizes 8 64 512] [--runs 500] [--check]``
"""
from __future__ import annotations

import argparse
import json
import resource
import sys

import numpy as np

from designer.attacks import FDISignal
from filters.attacks import simulate_attacks
from filters.consensus import run_consensus
from filters.consensus_batch import EdgeAttacks, run_consensus_batch
from studies.consensus_design import consensus_design
from studies.scenarios import load_scenario

from bench_batched_eval import best_time  # the benchmarks' folder (run as a script)

LINEAR_TOLERANCE = 2.0
STEPS = 4
PAPER_TARGET_US = 15.0  # issue 13: paper mode, per node-step, amortised over 500 runs ...
PER_RUN_REFERENCE_US = 375.0  # ... when the per-run path took 350-400 µs per node-step
TARGET_RATIO = PAPER_TARGET_US / PER_RUN_REFERENCE_US
DISTINCT_ATTACKS = 20


def ring_robot(n: int):
    ang = 2 * np.pi * np.arange(n) / n
    cams = np.stack([1.2 + 1.0 * np.cos(ang), 0.9 + 0.8 * np.sin(ang)], axis=1).tolist()
    edges = [[i, (i + 1) % n] for i in range(n)]
    return load_scenario("indoor-robot", {"camera_positions": cams, "edges": edges, "steps": STEPS})


def measure(n: int, runs: int, repeats: int, batch_repeats: int) -> dict:
    sc = ring_robot(n)
    rng = np.random.default_rng(0)
    traj = sc.simulate(rng, batch=runs)
    des = consensus_design(sc)
    patterns = [simulate_attacks(sc.network, STEPS, 3, rng, signal=FDISignal(1.5, (0, 1)))
                for _ in range(min(runs, DISTINCT_ATTACKS))]
    first = patterns[0]
    edge = [EdgeAttacks.from_patterns(sc.network, [p]) for p in patterns]
    del patterns
    cycle = np.arange(runs) % len(edge)
    att = EdgeAttacks(edge[0].receiver, edge[0].sender, *(np.concatenate([getattr(e, f) for e in edge])[cycle]
                                                          for f in ("dos", "fdi", "xi")))
    per_run = best_time(lambda: run_consensus(sc.model, sc.network, traj.z[0], des, inputs=traj.inputs, attacks=first),
                   repeats)
    out = {}

    def batched():
        out["result"] = run_consensus_batch(sc.model, sc.network, traj.z, des, inputs=traj.inputs, attacks=att)

    t_batch = best_time(batched, batch_repeats)
    ref = run_consensus(sc.model, sc.network, traj.z[0], des, inputs=traj.inputs, attacks=first)
    got = out.pop("result").run(0)
    assert np.allclose(got.x_post, ref.x_post, rtol=1e-9, atol=1e-12, equal_nan=True), "batched != per run"
    assert np.allclose(got.phi_post, ref.phi_post, rtol=1e-9, atol=1e-15, equal_nan=True), "batched != per run"
    key = [[(v["node"], v["step"], v["condition"]) for v in r.violations] for r in (got, ref)]
    assert key[0] == key[1] and np.array_equal(got.valid, ref.valid), "batched != per run"
    per_node_step = per_run / (n * STEPS)
    batch_node_step = t_batch / (runs * n * STEPS)
    return {"nodes": n, "runs": runs, "per_run_node_step_s": per_node_step, "batched_node_step_s": batch_node_step,
            "ratio": batch_node_step / per_node_step,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[8, 64, 512])
    ap.add_argument("--runs", type=int, default=500, help="Monte Carlo runs of the batched path")
    ap.add_argument("--repeats", type=int, default=3, help="best of, per-run path")
    ap.add_argument("--batch-repeats", type=int, default=2, help="best of, batched path")
    ap.add_argument("--check", action="store_true")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    rows = [measure(n, args.runs, args.repeats, args.batch_repeats) for n in args.sizes]
    print(f"paper mode, {STEPS} steps; batched over {args.runs} runs; per node-step, best of "
          f"{args.repeats} (per run) / {args.batch_repeats} (batched)")
    print(f"{'nodes':>6s} {'per run (us)':>13s} {'batched (us)':>13s} {'ratio':>7s} {'target':>7s} "
          f"{'growth per run':>15s} {'growth batched':>15s} {'peak RSS (MB)':>14s}")
    for r in rows:
        r["per_run_growth"] = r["per_run_node_step_s"] / rows[0]["per_run_node_step_s"]
        r["batched_growth"] = r["batched_node_step_s"] / rows[0]["batched_node_step_s"]
        print(f"{r['nodes']:6d} {r['per_run_node_step_s'] * 1e6:13.1f} {r['batched_node_step_s'] * 1e6:13.2f} "
              f"{r['ratio']:7.4f} {TARGET_RATIO:7.4f} {r['per_run_growth']:15.2f} {r['batched_growth']:15.2f} "
              f"{r['peak_rss_mb']:14.0f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)
    if not args.check:
        return 0
    failed = False
    for path in ("per_run", "batched"):
        if rows[-1][f"{path}_growth"] > LINEAR_TOLERANCE:
            print(f"FAIL: {path.replace('_', ' ')} cost per node grew {rows[-1][f'{path}_growth']:.2f}x "
                  f"(tolerance {LINEAR_TOLERANCE})", file=sys.stderr)
            failed = True
    for r in rows:
        if r["ratio"] > TARGET_RATIO:
            print(f"FAIL: {r['nodes']} nodes: batched / per run = {r['ratio']:.4f} exceeds {TARGET_RATIO:.4f} "
                  f"({PAPER_TARGET_US:g} us at the per-run path's {PER_RUN_REFERENCE_US:g} us)", file=sys.stderr)
            failed = True
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
