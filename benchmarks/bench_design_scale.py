"""The scheduled design at scale: its seconds from 8 to 512 nodes and its Monte Carlo error against the centralized EKF.

The network: range sensors on a king's-move grid (each node linked to its 8 neighbours, d_max 8) of
4 x 2, 8 x 4, 16 x 8 and 32 x 16 nodes, 10 m apart, tracking a constant-velocity target (process noise of
the CV model with q = 0.01, range noise 1 m) that starts near the grid's centre (prior mean 3 m off it,
velocity (0.2, 0.1) m per step, prior variances 25 m² and 0.25 m²/step²); DoS 0.1 and FDI 0.05 on
every channel and uplink, the injected signal an :class:`designer.attacks.FDISignal` of amplitude 1 on
the position components.  Each grid is a model file written to a temporary directory and loaded with
:func:`studies.scenarios.load_scenario`, as a user's file is.

For every size, in this one process:

* **design**: ``consensus_design(sc, mode="scheduled")`` (:mod:`rules.scheduled.design`: the offline tables over
  ``--steps`` steps, default 100, then the stationary tables beyond them), wall and CPU seconds, BLAS and
  LAPACK on one thread (:class:`designer.cores.one_blas_thread`; the design's own thread pool may still use
  a second core for stacks of small eigendecompositions, which the CPU seconds show).  Not timed: building
  the model (the file's ``model()``, the CasADi-to-NumPy translations) and its first evaluation at the
  operating point, and a warm-up design of the smallest grid over 2 steps (imports, thread pool).  A design
  that takes less than ``REPEAT_BELOW_S`` is timed best of ``REPEATS`` (each on a fresh copy of the model
  file, so that the process's memo of designs does not answer).  Beside it the seconds per designed step
  (the horizon plus the extra steps to the stationary tables), the steps its certificate holds, and its own
  expected position RMSE (its expected covariance along the nominal trajectory, every node);
* **Monte Carlo** on ``--runs`` fresh runs (default 5; run ``r`` draws its trajectory and its channels from
  ``SeedSequence(--seed).spawn(runs)[r]``, never used by the design): the scheduled consensus filter at
  every node (:func:`filters.consensus_batch.run_consensus_batch`, every run in one batch: its milliseconds
  per step of one run, amortised over the batch) and two centralized EKFs (:func:`filters.ekf.run_ekf_batch`)
  receiving every sensor: the comparison study's (over uplinks attacked with the channels' law, trusting
  every packet that arrives: ``study comparison``'s "centralized EKF") and a clean one (every measurement
  arrives, none falsified: the best the sensors allow).  The error is the position RMSE over the runs, the
  steps 1..K and (for the consensus filter) every node, as the comparison scores it; a run whose error
  leaves ``DIVERGENCE_SPREAD`` prior spreads diverged and is left out of the RMSE (and counted).
  ``--local`` adds the local EKFs (every node alone with its own range sensor; the comparison's
  ``local_ekf_design``).

The issue's targets are printed beside the numbers: the 512-node design in <= ``TARGET_512_S`` = 120 s, and
an error within ``ERROR_TARGET`` = 3 x the centralized EKF's.

``--check`` (32 and 128 nodes, both of d_max 8, over 100 steps and 3 runs; about a minute) exits 1 when

* the design's seconds per node and designed step at 128 nodes exceed ``GROWTH_TOLERANCE`` = 3.5 times those
  at 32 (a ratio measured in the same run, so that a shared machine's load cancels).  Measured 2.2-2.8 on a
  shared 2-core machine: at 128 nodes the stacked certificate (N n = 512 rows, at most
  ``rules.scheduled.design.CERTIFICATE_MAX_DIM``) is computed with dense eigendecompositions, cubic in N, and takes
  about 60 % of the design; the rest grows about linearly (from 128 to 512 nodes, where the certificate is
  skipped, the ratio was 1.0).  A design whose time grew like N² or faster between 32 and 128 nodes (ratio
  >= 4) fails;
* the scheduled filter diverges or gives a non-finite estimate in a run, or
* its error exceeds ``ERROR_TARGET`` x the comparison's centralized EKF's at a size.

``--command MODEL.py`` instead times the whole command a user runs, ``cfdesign design MODEL.py --mode scheduled
--out DIR`` (model build, tables, stationary certificate and its LMI, the seeded run, the trade-off, the report), in
a fresh process, best of ``--repeat`` (default 3), and prints its wall and CPU seconds beside the issue's target for
a 28-node model (``TARGET_28_S`` = 10 s) and the machine's load average (a figure, not a check: a shared machine's
load enters it).

Run: ``python benchmarks/bench_design_scale.py [--sizes 8 32 128 512] [--steps 100] [--runs 5] [--seed 0]
[--exchange measurements|predictions] [--rounds L] [--bank A] [--hcmci L ...] [--local] [--json FILE] [--check]`` or
``python benchmarks/bench_design_scale.py --command MODEL.py [--repeat 3]``

``--bank A``: the design's bank of operating points over A axes (``cfdesign design --bank``; default 0, none).
``--hcmci L [L ...]``: beside it HCMCI (:func:`filters.distributed.run_hcmci_batch`, ``omega="consistent"``) with L
consensus rounds per step, a filter that needs no design, on the same runs **without channel attacks** (its batch
takes dense per-run attack patterns, N x N x n_x per step: gigabytes at 512 nodes), its RMSE over the clean
centralized EKF's (column ``clean``): where the literature's rounds reach at each size.
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from designer.cores import one_blas_thread
from designer.network import SensorNetwork
from filters.attacks import attack_pattern, channel_draws, receive, uplink_attacks
from filters.consensus_batch import EdgeAttacks, run_consensus_batch
from filters.distributed import run_hcmci_batch
from filters.ekf import run_ekf_batch
from filters.uplink import split_received
from studies.filter_registry import local_ekf_design
from studies.consensus_design import consensus_design
from studies.results import DIVERGENCE_SPREAD, divergence_limit, first_divergence
from studies.scenarios import load_scenario

GRIDS = {8: (4, 2), 32: (8, 4), 128: (16, 8), 512: (32, 16)}
TARGET_512_S = 120.0  # issue 26, item 6: the scheduled design of the 512-node grid on one process
ERROR_TARGET = 3.0  # ... with a Monte Carlo error within 3 x the centralized EKF's
TARGET_28_S = 10.0  # ... and the whole design command of a 28-node model within 10 s
GROWTH_TOLERANCE = 3.5  # --check: design seconds per node-step, 128 / 32 nodes (measured 2.2-2.8)
CHECK_SIZES, CHECK_RUNS = (32, 128), 3
REPEATS, REPEAT_BELOW_S = 3, 5.0  # a design shorter than this is timed best of 3 (a shared machine's noise)
CHUNK_STEPS = 10  # channel draws turned into per-link attacks this many steps at a time (dense N x N x n_x)

GRID = '''"""Range sensors on a {nx} x {ny} king's-move grid (d_max 8), 10 m apart, tracking a CV target."""
import casadi as ca
import numpy as np
from designer import AttackSpec, FDISignal, Gaussian, Model, SensorNetwork, Sensor

NX, NY, SPACING = {nx}, {ny}, 10.0
STEPS = {steps}


def _edges():
    out = []
    for a in range(NX):
        for b in range(NY):
            for da, db in ((1, 0), (0, 1), (1, 1), (1, -1)):
                if 0 <= a + da < NX and 0 <= b + db < NY:
                    out.append((a * NY + b, (a + da) * NY + b + db))
    return out


NETWORK = SensorNetwork.from_edges(NX * NY, _edges())
ATTACKS = AttackSpec(dos=0.1, fdi=0.05, signal=FDISignal(amplitude=1.0, components=(0, 1)))


def model() -> Model:
    x = ca.SX.sym("x", 4)  # px, py, vx, vy
    f = ca.vertcat(x[0] + x[2], x[1] + x[3], x[2], x[3])
    sensors = [Sensor(f"r{{a}}_{{b}}", ca.sqrt((x[0] - a * SPACING) ** 2 + (x[1] - b * SPACING) ** 2),
                      Gaussian.zero_mean([[1.0]])) for a in range(NX) for b in range(NY)]
    q = 0.01
    Q = q * np.array([[1 / 3, 0, 1 / 2, 0], [0, 1 / 3, 0, 1 / 2], [1 / 2, 0, 1, 0], [0, 1 / 2, 0, 1]])
    cx, cy = (NX - 1) * SPACING / 2 + 3.0, (NY - 1) * SPACING / 2 + 3.0
    return Model("grid", x, f, sensors, process_noise=Gaussian.zero_mean(Q),
                 prior=Gaussian([cx, cy, 0.2, 0.1], np.diag([25.0, 25.0, 0.25, 0.25])), position_index=(0, 1))
'''


def grid_scenario(folder: Path, nodes: int, steps: int, copy: int = 0):
    """The grid of ``nodes`` nodes as a model file in ``folder``, loaded as a user's file is; the model evaluated
    once at its operating point (every sensor's h and H, f and F).  ``copy`` > 0 adds a comment to the file: another
    scenario digest, so that its design is computed again rather than taken from the process's memo."""
    nx, ny = GRIDS[nodes]
    path = folder / f"grid_{nx}x{ny}.py"
    path.write_text(GRID.format(nx=nx, ny=ny, steps=steps) + (f"# copy {copy}\n" if copy else ""))
    sc = load_scenario(str(path))
    m, (x0, u0) = sc.model, sc.operating_point
    m.f_expected(x0, 0, u0), m.F_expected(x0, 0, u0)
    for i in range(m.n_sensors):
        m.h(i, x0, 1), m.H(i, x0, 1)
    return sc


def timed_design(sc, exchange: str | None = None, rounds: int = 1, bank: int = 0):
    """The scheduled design of ``sc`` (``exchange``: what its packets carry, default the design's; ``rounds``: its
    exchange rounds per step; ``bank``: the axes of its bank of operating points): (design, wall s, CPU s)."""
    t, c = time.perf_counter(), time.process_time()
    des = consensus_design(sc, mode="scheduled", rounds=rounds, bank=bank,
                           **({"exchange": exchange} if exchange else {}))
    return des, time.perf_counter() - t, time.process_time() - c


def draw_runs(sc, runs: int, seed: int):
    """``runs`` fresh runs: the truths, the clean measurements, the channel attacks on the network's links
    (EdgeAttacks) and what the centre receives over the uplinks (values, availability)."""
    m, net, steps = sc.model, sc.network, sc.steps
    att = sc.resolved_attacks
    xs, zs, dos, fdi, xi, vals, avail = [], [], [], [], [], [], []
    receiver, sender = np.nonzero(net.adjacency)
    for seq in np.random.SeedSequence(seed).spawn(runs):
        ts, cs = seq.spawn(2)
        traj = sc.simulate(np.random.default_rng(ts), steps)
        u, s = channel_draws(steps, net.n_nodes, np.random.default_rng(cs))
        parts = [EdgeAttacks.from_patterns(net, [attack_pattern(net, u[k:k + CHUNK_STEPS], s[k:k + CHUNK_STEPS],
                                                                m.n_x, att.signal)])
                 for k in range(0, steps, CHUNK_STEPS)]
        dos.append(np.concatenate([p.dos[0] for p in parts]))
        fdi.append(np.concatenate([p.fdi[0] for p in parts]))
        xi.append(np.concatenate([p.xi[0] for p in parts]))
        up = uplink_attacks(u, s, m.n_x, dos_prob=att.uplink_dos, fdi_prob=att.uplink_fdi, signal=att.signal)
        v, a = split_received(m, receive(m, traj.x, traj.z, up)[None])
        xs.append(traj.x), zs.append(traj.z), vals.append(v[0]), avail.append(a[0])
    edges = EdgeAttacks(receiver, sender, np.stack(dos), np.stack(fdi), np.stack(xi))
    return np.stack(xs), np.stack(zs), edges, np.stack(vals), np.stack(avail)


def position_rmse(sc, truth: np.ndarray, est: np.ndarray) -> tuple[float, int]:
    """(position RMSE over the runs that did not diverge, steps 1..K and nodes; the number that diverged).

    ``truth`` (runs, K + 1, n_x), ``est`` (runs, K + 1, nodes, n_x)."""
    idx = list(sc.model.position_index)
    limit = divergence_limit(sc.model.prior.cov, DIVERGENCE_SPREAD)
    err2, diverged = [], 0
    for t, e in zip(truth, est):
        d = t[:, None] - e
        if first_divergence(d, limit) is not None:
            diverged += 1
            continue
        err2.append((d[1:, :, idx] ** 2).sum(-1).mean())
    return (float(np.sqrt(np.mean(err2))) if err2 else float("nan")), diverged


def measure(folder: Path, nodes: int, steps: int, runs: int, seed: int, local: bool, exchange: str | None,
            rounds: int = 1, bank: int = 0, hcmci: tuple[int, ...] = ()) -> dict:
    """One row of the table: the design of the ``nodes`` grid timed (best of ``REPEATS`` when it takes less than
    ``REPEAT_BELOW_S``), then the Monte Carlo runs."""
    best = None
    for copy in range(REPEATS):
        sc = grid_scenario(folder, nodes, steps, copy)
        timing = timed_design(sc, exchange, rounds, bank)
        best = timing if best is None or timing[1] < best[1] else best
        if timing[1] >= REPEAT_BELOW_S:
            break
    des, wall, cpu = best
    tab = des.tables
    designed_steps = tab.steps + tab.stationary["extra_steps"]  # STATIONARY_MAX when they did not converge
    truth, z, edges, vals, avail = draw_runs(sc, runs, seed)
    m, net = sc.model, sc.network
    t = time.perf_counter()
    res = run_consensus_batch(m, net, z, des, attacks=edges).detail
    filter_s = time.perf_counter() - t
    finite = bool(np.isfinite(res.x_post).all())
    sched, sched_div = position_rmse(sc, truth, res.x_post)
    pos = list(sc.model.position_index)
    expected = float(np.sqrt(np.trace(tab.P_post[1:, :, pos][..., pos], axis1=-2, axis2=-1).mean()))
    engine_div = sum(d is not None for d in res.diverged)
    cekf, cekf_div = position_rmse(sc, truth, run_ekf_batch(m, vals, available=avail).detail.x[:, :, None])
    clean, clean_div = position_rmse(sc, truth, run_ekf_batch(m, z).detail.x[:, :, None])
    row = {"nodes": nodes, "grid": "x".join(map(str, GRIDS[nodes])), "edges": int(net.adjacency.sum()) // 2,
           "d_max": int(net.d_max), "exchange": des.exchange, "rounds": des.rounds, "bank": des.bank,
           "bank_points": 0 if tab.bank_record is None else tab.bank_record["points"],
           "messages_per_step": net.messages_per_step(des.rounds), "steps": steps, "runs": runs,
           "design_s": wall, "design_cpu_s": cpu, "stationary": dict(tab.stationary),
           "designed_steps": designed_steps, "design_s_per_step": wall / designed_steps,
           "design_s_per_node_step": wall / (designed_steps * nodes),
           "certificate": f"{int(tab.valid.sum()) - 1} of {tab.steps} steps",
           "filter_ms_per_step": 1e3 * filter_s / (steps * runs),
           "rmse_scheduled": sched, "rmse_design": expected, "rmse_centralized": cekf,
           "rmse_centralized_clean": clean, "ratio": sched / cekf, "ratio_clean": sched / clean, "finite": finite,
           "diverged": {"scheduled": max(sched_div, engine_div), "centralized": cekf_div,
                        "centralized (clean)": clean_div},
           "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
    if local:
        isolated = SensorNetwork(nodes, np.zeros((nodes, nodes), int), require_connected=False)
        res = run_consensus_batch(m, isolated, z, local_ekf_design(consensus_design(sc))).detail
        row["rmse_local"], row["diverged"]["local"] = position_rmse(sc, truth, res.x_post)
        row["ratio_local"] = row["rmse_local"] / cekf
    for L in hcmci:  # the literature's rounds on the clean runs, against the clean centralized EKF
        res = run_hcmci_batch(m, net, z, iterations=L, omega="consistent").detail
        e, div = position_rmse(sc, truth, res.x_post)
        row.setdefault("hcmci", []).append({"rounds": L, "rmse_clean_runs": e, "ratio_clean": e / clean,
                                            "diverged": div})
    return row


def print_table(rows: list[dict]) -> None:
    runs, steps = rows[0]["runs"], rows[0]["steps"]
    print(f"scheduled design (--steps {steps}, exchange {rows[0]['exchange']}, {rows[0]['rounds']} exchange round(s) "
          f"per step, bank of {rows[0]['bank_points']} operating points) and {runs} fresh Monte Carlo runs; "
          "BLAS on one thread; model building and its first evaluation not timed")
    local = "rmse_local" in rows[0]
    print(f"{'nodes':>5s} {'grid':>6s} {'edges':>5s} {'msgs':>6s} {'design s':>9s} {'(CPU s)':>8s} {'steps':>6s} "
          f"{'s/step':>7s} "
          f"{'filter ms/step':>15s} {'RMSE sched':>11s} {'(design)':>9s} {'RMSE CEKF':>10s} {'ratio':>7s} "
          f"{'clean':>7s}" + (f" {'local':>7s}" if local else "") + f" {'certificate':>16s}")
    for r in rows:
        div = ", ".join(f"{k} {v}" for k, v in r["diverged"].items() if v)
        print(f"{r['nodes']:5d} {r['grid']:>6s} {r['edges']:5d} {r['messages_per_step']:6d} {r['design_s']:9.2f} "
              f"{r['design_cpu_s']:8.2f} "
              f"{r['designed_steps']:6d} {r['design_s_per_step']:7.3f} {r['filter_ms_per_step']:15.1f} "
              f"{r['rmse_scheduled']:11.4f} {r['rmse_design']:9.4f} {r['rmse_centralized']:10.4f} "
              f"{r['ratio']:7.2f} {r['ratio_clean']:7.2f}" + (f" {r['ratio_local']:7.2f}" if local else "")
              + f" {r['certificate']:>16s}" + (f"  diverged runs: {div}" if div else "")
              + ("" if r["finite"] else "  NON-FINITE estimates"))
        for h in r.get("hcmci", []):
            print(f"      HCMCI, L = {h['rounds']} rounds, clean runs: RMSE {h['rmse_clean_runs']:.4f}, "
                  f"{h['ratio_clean']:.2f} x the clean centralized EKF" + (f" ({h['diverged']} runs diverged)"
                                                                          if h["diverged"] else ""))
    print("msgs: messages per step (2 |E| L); steps: the horizon plus the extra steps to the stationary tables; "
          "filter ms/step: per step of one run, "
          "amortised over the batch of runs; RMSE: position, over the runs, steps and (consensus) nodes; (design): the "
          "design's own expected RMSE (its expected covariance along the nominal trajectory); ratio: the scheduled "
          "filter's RMSE / the centralized EKF's (attacked uplinks, as in study comparison); clean: / the "
          f"centralized EKF's with every measurement, unattacked; local: the local EKFs' / the centralized EKF's; "
          f"target ratio <= {ERROR_TARGET:g}")
    for r in rows:
        if r["nodes"] == 512:
            print(f"512 nodes: design {r['design_s']:.1f} s (target {TARGET_512_S:g} s: "
                  f"{'met' if r['design_s'] <= TARGET_512_S else 'MISSED'}), error ratio {r['ratio']:.2f} "
                  f"(target {ERROR_TARGET:g}: {'met' if r['ratio'] <= ERROR_TARGET else 'MISSED'})")


def check(rows: list[dict]) -> bool:
    ok = True
    growth = rows[-1]["design_s_per_node_step"] / rows[0]["design_s_per_node_step"]
    print(f"design seconds per node-step, {rows[-1]['nodes']} / {rows[0]['nodes']} nodes: {growth:.2f} (tolerance "
          f"{GROWTH_TOLERANCE:g})")
    if len(rows) > 1 and growth > GROWTH_TOLERANCE:
        print(f"FAIL: the design's seconds per node-step grew {growth:.2f}x from {rows[0]['nodes']} to "
              f"{rows[-1]['nodes']} nodes (tolerance {GROWTH_TOLERANCE:g})", file=sys.stderr)
        ok = False
    for r in rows:
        if not r["finite"] or r["diverged"]["scheduled"]:
            print(f"FAIL: {r['nodes']} nodes: the scheduled filter diverged in {r['diverged']['scheduled']} of "
                  f"{r['runs']} runs" + ("" if r["finite"] else " (non-finite estimates)"), file=sys.stderr)
            ok = False
        if not r["ratio"] <= ERROR_TARGET:
            print(f"FAIL: {r['nodes']} nodes: error ratio {r['ratio']:.2f} above {ERROR_TARGET:g}", file=sys.stderr)
            ok = False
    return ok


def time_command(model: str, repeat: int) -> int:
    """Best of ``repeat`` fresh processes of ``cfdesign design MODEL --mode scheduled --out TMP``: wall and CPU s."""
    import os
    import subprocess

    script = Path(sys.executable).with_name("cfdesign")
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "studies"]
    best = None
    for _ in range(repeat):
        with tempfile.TemporaryDirectory() as tmp:
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t = time.perf_counter()
            r = subprocess.run(cmd + ["design", model, "--mode", "scheduled", "--out", tmp], stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, env=dict(os.environ, MPLBACKEND="Agg"), timeout=900)
            wall = time.perf_counter() - t
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if r.returncode not in (0, 1):  # 1: designed but not certified, a result like any other here
            print(f"FAIL: cfdesign design {model} exited {r.returncode}: {r.stderr.decode()[-400:]}", file=sys.stderr)
            return 1
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        if best is None or wall < best[0]:
            best = (wall, cpu)
    load = os.getloadavg()[0]
    print(f"cfdesign design {model} --mode scheduled: {best[0]:.1f} s wall, {best[1]:.1f} s CPU (best of {repeat}; "
          f"issue 26's target for 28 nodes: {TARGET_28_S:g} s; load average {load:.1f} on {os.cpu_count()} cores)")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", choices=sorted(GRIDS), default=None,
                    help=f"node counts (default {sorted(GRIDS)}; --check: {list(CHECK_SIZES)})")
    ap.add_argument("--steps", type=int, default=100, help="the design's horizon and the runs' length")
    ap.add_argument("--runs", type=int, default=None, help=f"Monte Carlo runs (default 5; --check: {CHECK_RUNS})")
    ap.add_argument("--seed", type=int, default=0, help="the runs' SeedSequence")
    ap.add_argument("--exchange", choices=["measurements", "predictions"], default=None,
                    help="what the scheduled design's packets carry (default: the design's default)")
    ap.add_argument("--rounds", type=int, default=1, help="the scheduled design's exchange rounds per step L")
    ap.add_argument("--bank", type=int, default=0, help="the axes of the scheduled design's bank of operating points")
    ap.add_argument("--hcmci", type=int, nargs="*", default=(), help="also HCMCI with these rounds per step L, on "
                    "the runs without channel attacks, against the clean centralized EKF")
    ap.add_argument("--local", action="store_true", help="also the local EKFs (every node alone)")
    ap.add_argument("--json", help="write the rows to this file")
    ap.add_argument("--check", action="store_true")
    ap.add_argument("--command", metavar="MODEL.py", help="time the whole design command of this model instead")
    ap.add_argument("--repeat", type=int, default=3, help="--command: fresh processes, the best kept")
    args = ap.parse_args(argv)
    if args.command:
        if args.repeat < 1:
            ap.error("--repeat must be >= 1")
        return time_command(args.command, args.repeat)
    if args.steps < 1 or (args.runs is not None and args.runs < 1):
        ap.error("--steps and --runs must be >= 1")
    if any(L < 1 for L in args.hcmci):
        ap.error("--hcmci rounds must be >= 1")
    sizes = sorted(args.sizes or (CHECK_SIZES if args.check else GRIDS))
    runs = args.runs or (CHECK_RUNS if args.check else 5)
    rows = []
    with one_blas_thread(), tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        consensus_design(grid_scenario(folder, min(GRIDS), 2), mode="scheduled")  # warm-up, not timed
        for nodes in sizes:
            rows.append(measure(folder, nodes, args.steps, runs, args.seed, args.local, args.exchange, args.rounds,
                                args.bank, tuple(args.hcmci)))
            print(f"  {nodes} nodes measured: design {rows[-1]['design_s']:.1f} s", flush=True)
    print_table(rows)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)
    if args.check:
        return 0 if check(rows) else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
