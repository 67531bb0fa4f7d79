"""Cost of the literature's distributed filters (KCF, HCMCI) and the centralized EKF: per run and batched.

The comparison study runs them on every run and sweep setting of a chunk at once.  Two paths, measured in
the same run on the built-in scenarios the comparison uses (the indoor robot, 8 cameras over 30 steps; the
range-bearing target, 4 sensors over 120 steps), under DoS 0.3 and FDI 0.2 on every channel and uplink:

* per run: :func:`filters.distributed.run_kcf`, :func:`~filters.distributed.run_hcmci` (L = 1; each a batch
  of one run of the batched filter, their only implementation) and :func:`filters.ekf.run_ekf`, ``--per-run``
  runs one after the other (their mean): what looping over the runs would cost;
* batched: :func:`~filters.distributed.run_kcf_batch`, :func:`~filters.distributed.run_hcmci_batch` and
  :func:`filters.ekf.run_ekf_batch` over ``--runs`` runs (default 90: the comparison's chunk of 10 runs at
  its 9 settings), the cost amortised per run (best of ``--repeats``); the batch's runs that the per-run
  path also ran are checked against it (rtol 1e-9; KCF and HCMCI a run alone and in a batch are the same
  loop, the EKF its own per-run filter).

``--check`` exits 1 when the batched path takes more than ``RATIO`` of the per-run path's time per run
(0.15; measured 0.02-0.06 on a shared 2-core machine).

Run: ``python benchmarks/bench_distributed_step.py [--runs 90] [--per-run 5] [--check]``
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from filters.attacks import attack_pattern, channel_draws, receive, uplink_attacks
from filters.distributed import run_hcmci, run_hcmci_batch, run_kcf, run_kcf_batch
from filters.ekf import run_ekf, run_ekf_batch
from filters.uplink import split_received
from studies.scenarios import load_scenario

from bench_batched_eval import best_time  # the benchmarks' folder (run as a script)

RATIO = 0.15
SCENARIOS = ("indoor-robot", "target-range-bearing")


def draws(name: str, runs: int):
    """``runs`` runs of scenario ``name`` as the comparison draws them: measurements, inputs, channel attacks and
    the uplinks' received values with their availability."""
    sc = load_scenario(name).with_attacks(dos=0.3, fdi=0.2)
    m, n, att = sc.model, sc.network.n_nodes, sc.resolved_attacks
    z, u, pats, vals, avail = [], [], [], [], []
    for seq in np.random.SeedSequence(0).spawn(runs):
        ts, cs = seq.spawn(2)
        tr = sc.simulate(np.random.default_rng(ts), sc.steps)
        d, s = channel_draws(sc.steps, n, np.random.default_rng(cs))
        pats.append(attack_pattern(sc.network, d, s, m.n_x, att.signal))
        v, a = split_received(m, receive(m, tr.x, tr.z, uplink_attacks(d, s, m.n_x, dos_prob=att.uplink_dos,
                                                                       fdi_prob=att.uplink_fdi, signal=att.signal)))
        z.append(tr.z), u.append(tr.inputs), vals.append(v), avail.append(a)
    return sc, np.stack(z), None if u[0] is None else np.stack(u), pats, np.stack(vals), np.stack(avail)


def measure(name: str, runs: int, per_run: int, repeats: int) -> list[dict]:
    sc, z, u, pats, vals, avail = draws(name, runs)
    m, net = sc.model, sc.network
    ui = (lambda r: None) if u is None else (lambda r: u[r])  # noqa: E731
    filters = {
        "KCF": (lambda r: run_kcf(m, net, z[r], inputs=ui(r), attacks=pats[r]).x_post,
                lambda: run_kcf_batch(m, net, z, inputs=u, attacks=pats).detail.x_post),
        "HCMCI": (lambda r: run_hcmci(m, net, z[r], inputs=ui(r), attacks=pats[r]).x_post,
                  lambda: run_hcmci_batch(m, net, z, inputs=u, attacks=pats).detail.x_post),
        "centralized EKF": (lambda r: run_ekf(m, vals[r], available=avail[r], inputs=ui(r)).x,
                            lambda: run_ekf_batch(m, vals, available=avail, inputs=u).detail.x),
    }
    rows = []
    for label, (one, batch) in filters.items():
        refs = []
        t0 = time.perf_counter()
        for r in range(per_run):
            refs.append(one(r))
        t_one = (time.perf_counter() - t0) / per_run
        out = {}
        t_batch = best_time(lambda: out.update(x=batch()), repeats) / runs
        for r, ref in enumerate(refs):
            assert np.allclose(out["x"][r], ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max()), f"{label}: batch != per run"
        rows.append({"scenario": name, "filter": label, "nodes": net.n_nodes, "steps": sc.steps, "runs": runs,
                     "per_run_s": t_one, "batched_per_run_s": t_batch, "ratio": t_batch / t_one})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=90, help="runs of the batched path")
    ap.add_argument("--per-run", type=int, default=5, help="runs of the per-run path (their mean)")
    ap.add_argument("--repeats", type=int, default=2, help="best of, batched path")
    ap.add_argument("--check", action="store_true")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    rows = [row for name in SCENARIOS for row in measure(name, args.runs, min(args.per_run, args.runs), args.repeats)]
    print(f"per run: mean of {args.per_run} runs; batched over {args.runs} runs, per run, best of {args.repeats}")
    print(f"{'scenario':>22s} {'filter':>16s} {'nodes':>6s} {'steps':>6s} {'per run (ms)':>13s} {'batched (ms)':>13s} "
          f"{'ratio':>7s} {'limit':>6s}")
    for r in rows:
        print(f"{r['scenario']:>22s} {r['filter']:>16s} {r['nodes']:6d} {r['steps']:6d} {r['per_run_s'] * 1e3:13.2f} "
              f"{r['batched_per_run_s'] * 1e3:13.3f} {r['ratio']:7.4f} {RATIO:6.2f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)
    if not args.check:
        return 0
    failed = [r for r in rows if r["ratio"] > RATIO]
    for r in failed:
        print(f"FAIL: {r['scenario']}, {r['filter']}: batched / per run = {r['ratio']:.4f} exceeds {RATIO}",
              file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
