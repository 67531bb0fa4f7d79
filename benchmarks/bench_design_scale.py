"""Designs at scale: the scheduled one on 8 to 512 nodes against the centralized EKF; every mode on a field and grids.

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
  ``--local`` adds the local EKFs (every node alone with its own range sensor; the comparison's,
  ``filters.distributed.run_local_batch``).

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

**Issue 41's models** (``--models``): a heat field and power grids, written as a user writes a model file
(``benchmarks/models/``), each design of ``--modes`` (default relay, flood, scheduled, auto) in a fresh process:

* ``field``: ``benchmarks/models/heat_field.py``, an R x C grid of cells (diffusion to the 4 neighbours, a leak, a
  small sine; one node per cell reading its own cell, every fifth a thermistor, exp(0.3 T); the network the grid's
  adjacency), copied with ``ROWS, COLS`` set to each of ``--field-sizes`` (default 4x4 5x4 8x8);
* ``grid14``: ``benchmarks/models/ieee14_grid.py``, the IEEE 14-bus grid (its 20 branches typed in the file): the
  13 non-slack bus angles as a slow random walk, each bus's node measuring its branches' real power flows
  sin(theta_i - theta_j) / x_ij and every third bus its own angle (a PMU), the network the branches;
* ``grid30``, ``grid118``: the same model with the data of ``pandapower.networks.case30()`` / ``case118()`` (29 and
  117 states; 118 nodes on 179 lines), read by a Python that imports pandapower (``--pandapower-python PY``; not a
  dependency of cfdesign or of CI).

A design is ``studies.design(MODEL, mode=MODE, seed=--seed)`` (and ``steps=--steps``, ``validate=--validate`` when
given) then ``.save(DIR)``, what ``cfdesign design MODEL --mode MODE --out DIR`` runs (mode ``auto``: every
candidate, the pick and its 20 validation runs), in a fresh process, so that its memory is its own: the process's
wall and CPU seconds (with the processes it starts: the stationary certificate is computed in a second one), its
phases (``load``: ``load_scenario``; ``design``: ``studies.design``; ``save``: the files and the report), the peak
memory of its processes together (their proportional set sizes, sampled every ``SAMPLE_S``, so that the pages a
forked helper shares count once) and of the largest one (``ru_maxrss``), its verdict, whether it is bounded and
the node-average tr Phi at the horizon; beside the 64-cell field's and the 118-bus grid's rows, the issue's target
(``TARGET_S`` = 120 s and ``TARGET_GB`` = 4 GB on 2 cores).  A design past ``--timeout`` (300 s) or ``--max-gb``
(8 GB) is stopped, its process group killed, and reported so.

``--carry region`` gives the relay, flood and automatic designs ``carry='region'`` (each node carrying its region
and what its ball's measurements and their dynamics need; the grids declare each bus's angle its node's region).

``--models field grid14 --check`` (CI: the fields 2 x 4 and 4 x 4 and the 14-bus grid, relay and scheduled, but the
2 x 4 field's scheduled design, whose stationary LMI runs away in memory; about a minute on 2 cores) exits 1 when a
design does not finish, its estimates or bound at the horizon are not finite, its processes hold more than
``CHECK_MAX_GB``, a relay design is not certified, the relay design's seconds per node grow more than
``FIELD_GROWTH_TOLERANCE`` times from 8 to 16 cells, or the scheduled designs take more than ``SCHEDULED_RELAY_MAX``
times the relay designs of the same models (their seconds summed; ratios measured in the same run, so that a shared
machine's load cancels).

Measured (seed 0, a shared 2-core machine at load averages 2-5; process wall seconds, peak memory of the processes
together): 14-bus grid relay 5-8 s, 0.25 GB, flood 9 s, scheduled 10-19 s, auto 32 s (all certified); 30-bus relay
73 s, 1.8 GB, flood 69 s, scheduled 92 s (vacuous), auto 104 s, 2.4 GB; 118-bus relay 135 s, 4.4 GB (certified; its
stationary recursion does not settle in 5000 iterations, so no LMI), flood 173 s, 4.4 GB, scheduled refused before
computing (its memory estimate: 83 GiB), auto refused after its candidates (60 s: the validation's estimate, 204 GiB;
``--validate 0``: 72 s, 6.0 GB, flood L = 2 picked).  Field 16 cells: relay 5-9 s, flood 9 s, scheduled 15-21 s
(vacuous), auto 44 s; 20 cells: relay 13 s, flood 14 s, scheduled 99 s (vacuous; its stationary certificate, 589
iterations of dense eigendecompositions of N n = 400 rows), auto 52 s; 64 cells: relay and flood stopped at 8 GB after
2 min (their stationary LMI builds each node's update as an n² x n² matrix), scheduled stopped at 300 s (its tables
over the horizon not done), auto refused after 53 s (the validation's estimate, 33 GiB; ``--validate 0``: 60 s,
1.3 GB, flood L = 4 picked).  The 2 x 4 field's scheduled design (N n = 64: its stationary LMI is solved) was stopped
at 8 GB after 47 s.  2026-12-06 (the relay rule's stationary recursion Anderson-accelerated, its update without
the dense grouped rows; load about 1.5): field 64 cells relay 32 s, 0.85 GB, flood 34 s, 1.5 GB; 118-bus grid (each
bus's node carrying its region, the default 8 hops) relay 102 s, flood 104 s, both certified, 3.6 GB (4.4-4.5 GB
before the report read schedule.npz one array at a time); auto of either stopped at 8 GB in its validation runs.

Run: ``python benchmarks/bench_design_scale.py --models field grid14 [grid30 grid118 --pandapower-python PY]
[--field-sizes 4x4 5x4 8x8] [--modes relay flood scheduled auto] [--seed 0] [--validate R] [--timeout 300]
[--max-gb 8] [--json FILE] [--check]``
"""
from __future__ import annotations

import argparse
import json
import re
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from designer.cores import one_blas_thread
from designer.regions import Carried
from filters.attacks import attack_pattern, channel_draws, receive, uplink_attacks
from filters.consensus_batch import EdgeAttacks, run_consensus_batch
from filters.distributed import run_hcmci_batch, run_local_batch
from filters.ekf import run_ekf_batch
from filters.uplink import split_received
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
        res = run_local_batch(m, z).detail
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


# ---- issue 41: the relay, flood, scheduled and automatic designs of a heat field and of power grids ----

MODELS = Path(__file__).resolve().with_name("models")
FIELD_FILE, GRID_FILE = MODELS / "heat_field.py", MODELS / "ieee14_grid.py"
GRID_CASES = {"grid14": "case14", "grid30": "case30", "grid118": "case118"}  # pandapower.networks' names
MODEL_NAMES = ("field", *GRID_CASES)
DESIGN_MODES = ("relay", "flood", "scheduled", "auto")
FIELD_SIZES = ((4, 4), (5, 4), (8, 8))
TARGET_S, TARGET_GB = 120.0, 4.0  # issue 41: each design of a 64-cell field and of IEEE 118 on 2 cores
TARGET_NODES = {"field": 64, "grid118": 118}
DESIGN_TIMEOUT_S, DESIGN_MAX_GB = 300.0, 8.0  # a design beyond either is stopped and reported as such
# --models ... --check: the fields 2 x 4 and 4 x 4 and the 14-bus grid, relay and scheduled, but for the scheduled
# design of the 2 x 4 field (N n = 64 <= rules.scheduled.certificate.LMI_MAX_DIM: its stationary LMI, solved by
# Clarabel, held 8 GB within a minute when measured)
CHECK_FIELDS, CHECK_MODES, CHECK_SKIP = ((2, 4), (4, 4)), ("relay", "scheduled"), {("field 2x4", "scheduled")}
# the relay design's seconds per node, field 4 x 4 / 2 x 4: measured 1.2-1.5, 2.4 once at a load of 5 (the 8-cell
# design takes a second: a load spike weighs); a cost cubic in the states per node would give up to 8
FIELD_GROWTH_TOLERANCE = 4.0
SCHEDULED_RELAY_MAX = 6.0  # the scheduled designs' seconds / the relay designs', same models (measured 2.8-3.5)
CHECK_MAX_GB = 1.5  # the peak memory of a design's processes at the check's sizes (measured 0.2-0.35 GB)
SAMPLE_S = 0.2  # the memory of a design's processes sampled this often
RESULT, SIZE = "BENCH-DESIGN-RESULT ", "BENCH-DESIGN-SIZE "  # the lines a design's process prints its numbers on

# run by a Python with pandapower: a case's branches (from, to, series reactance in p.u. on the system base; taps
# neglected), its slack bus and its AC power flow's bus angles (degrees), as JSON
PANDAPOWER_EXTRACT = r"""
import json, sys
import pandapower as pp
import pandapower.networks as pn
net = getattr(pn, sys.argv[1])()
pp.runpp(net)
bus = {b: i + 1 for i, b in enumerate(net.bus.index)}
sb, branches = net.sn_mva, []
for _, l in net.line.iterrows():
    zb = net.bus.vn_kv[l.from_bus] ** 2 / sb
    branches.append((bus[l.from_bus], bus[l.to_bus], l.x_ohm_per_km * l.length_km / l.parallel / zb))
for _, t in net.trafo.iterrows():
    vk, vkr = t.vk_percent / 100, t.vkr_percent / 100
    branches.append((bus[t.hv_bus], bus[t.lv_bus], (vk ** 2 - vkr ** 2) ** 0.5 * sb / t.sn_mva / t.parallel))
print(json.dumps({"branches": [(int(a), int(b), round(float(x), 6)) for a, b, x in branches],
                  "slack": bus[int(net.ext_grid.bus.iloc[0])],
                  "angles": [round(float(v), 3) for v in net.res_bus.va_degree]}))
"""


def field_file(folder: Path, rows: int, cols: int) -> Path:
    """``benchmarks/models/heat_field.py`` with ``ROWS, COLS = rows, cols``, written to ``folder``."""
    text, n = re.subn(r"^ROWS, COLS = .*$", f"ROWS, COLS = {rows}, {cols}", FIELD_FILE.read_text(), flags=re.M)
    assert n == 1, "heat_field.py: its ROWS, COLS line is missing"
    path = folder / f"field_{rows}x{cols}.py"
    path.write_text(text)
    return path


def grid_file(folder: Path, name: str, pandapower_python: str | None) -> Path:
    """The power-grid model of ``name`` (``grid14``: ``benchmarks/models/ieee14_grid.py`` itself; ``grid30``,
    ``grid118``: the same model with the case's data read from pandapower by ``pandapower_python``, written to
    ``folder``).  SystemExit naming the problem when pandapower is not at hand."""
    if name == "grid14":
        return GRID_FILE
    import subprocess

    python = pandapower_python or sys.executable
    r = subprocess.run([python, "-c", PANDAPOWER_EXTRACT, GRID_CASES[name]], capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(f"{name}: the IEEE case's data come from pandapower, which {python} cannot import "
                         f"(--pandapower-python PY names a Python that can): {r.stderr.strip().splitlines()[-1:]}")
    data = json.loads(r.stdout.strip().splitlines()[-1])
    head, marker, body = GRID_FILE.read_text().partition("\n# The model")
    assert marker, "ieee14_grid.py: its '# The model' line is missing"
    lines = ",\n".join("    " + ", ".join(f"({a}, {b}, {x!r})" for a, b, x in data["branches"][i:i + 5])
                        for i in range(0, len(data["branches"]), 5))
    angles = ",\n".join("    " + ", ".join(map(repr, data["angles"][i:i + 10]))
                         for i in range(0, len(data["angles"]), 10))
    imports = head[head.index("import casadi"):head.index("NAME = ")]
    path = folder / f"ieee{name[4:]}_grid.py"
    path.write_text(f'"""The IEEE {name[4:]}-bus power grid (written by benchmarks/bench_design_scale.py).\n\n'
                    f"The model of benchmarks/models/ieee14_grid.py with the data of pandapower.networks."
                    f"{GRID_CASES[name]}():\nits branches' series reactances in p.u. (taps neglected) and its AC "
                    'power flow\'s bus angles.\n"""\n'
                    f"{imports}NAME = {'ieee' + name[4:]!r}\nSLACK = {data['slack']}\nBRANCHES = [\n{lines},\n]\n"
                    f"ANGLES_DEG = [\n{angles},\n]\n{marker}{body}")
    return path


def _tree_memory(pid: int) -> int:
    """Resident bytes of process ``pid`` and of its descendants, pages shared between them (a forked helper's)
    counted once: the sum of their proportional set sizes (``Pss``, /proc/PID/smaps_rollup; 0 once it is gone)."""
    import os

    parents: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as fh:
                    ppid = int(fh.read().rpartition(")")[2].split()[1])
            except (OSError, ValueError, IndexError):
                continue
            parents.setdefault(ppid, []).append(int(entry))
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        todo.extend(parents.get(p, ()))
        try:
            with open(f"/proc/{p}/smaps_rollup") as fh:
                total += next(int(line.split()[1]) for line in fh if line.startswith("Pss:")) * 1024
        except (OSError, ValueError, IndexError, StopIteration):
            pass
    return total


def time_design(model: Path, mode: str, options: dict, timeout: float, max_bytes: float) -> dict:
    """``studies.design(model, mode=mode, **options)`` (``options``: e.g. ``seed``, ``steps``, ``validate``) then its
    ``.save(DIR)`` (what ``cfdesign design MODEL --mode MODE --seed S --out DIR`` runs) in a fresh process
    (:func:`design_child`): its numbers, the process's wall and CPU seconds (with the processes it started), and the
    peak resident memory of its processes together (their ``Pss``, sampled every ``SAMPLE_S``: :func:`_tree_memory`)
    and of the largest one (``ru_maxrss``).  A design past ``timeout`` seconds or ``max_bytes`` of memory is stopped
    (its process group killed) and reported as such: the CPU seconds of processes killed so are not counted."""
    import os
    import signal
    import subprocess

    with tempfile.TemporaryDirectory() as tmp:
        out, log = Path(tmp) / "design", Path(tmp) / "log"
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t = time.perf_counter()
        with open(log, "w+") as fh:
            cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(model), mode, str(out),
                   json.dumps(options)]
            proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=dict(os.environ, MPLBACKEND="Agg"),
                                    start_new_session=True)
            peak, stopped = 0, None
            while proc.poll() is None:
                peak = max(peak, _tree_memory(proc.pid))
                wall = time.perf_counter() - t
                if stopped is None and (wall > timeout or peak > max_bytes):
                    stopped = (f"stopped after {timeout:g} s" if wall > timeout else
                               f"stopped at {peak / 2 ** 30:.1f} GB (limit {max_bytes / 2 ** 30:g} GB)")
                    os.killpg(proc.pid, signal.SIGKILL)
                time.sleep(SAMPLE_S)
            wall = time.perf_counter() - t
            fh.seek(0)
            text = fh.read()
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    row = {"mode": mode, "wall_s": wall, "cpu_s": cpu,
           "peak_mb": peak / 2 ** 20, "stopped": stopped, "returncode": proc.returncode}
    for tag in (SIZE, RESULT):  # the model's size as soon as it is loaded, the design's numbers at the end
        found = [line for line in text.splitlines() if line.startswith(tag)]
        if found:
            row.update(json.loads(found[-1][len(tag):]))
    if "design_s" not in row and "error" not in row and stopped is None:
        row["error"] = (text.strip().splitlines() or ["no output"])[-1][-300:]
    return row


def design_child(model: str, mode: str, out: str, options: dict) -> int:
    """In a fresh process: load ``model`` (the file, ``model()``, its translations), design it with
    :func:`studies.api.design`, save it to ``out``; print the phases' seconds, the verdict and the memory on one line
    (``RESULT`` and JSON)."""
    import studies

    t0 = time.perf_counter()
    sc = load_scenario(model)
    t1, c1 = time.perf_counter(), time.process_time()
    size = {"nodes": sc.network.n_nodes, "states": sc.model.n_x, "edges": int(sc.network.adjacency.sum()) // 2,
            "d_max": int(sc.network.d_max), "steps": options.get("steps", sc.steps)}
    print(SIZE + json.dumps(size), flush=True)
    if mode not in ("relay", "flood", "auto"):  # --carry: the modes whose nodes may carry their regions
        options = {k: v for k, v in options.items() if k != "carry"}
    try:
        res = studies.design(sc, mode=mode, **options)
    except Exception as exc:  # reported as the row's error: a design that fails is a result here
        print(RESULT + json.dumps({"error": f"{type(exc).__name__}: {exc}"[:300]}), flush=True)
        return 1
    t2, c2 = time.perf_counter(), time.process_time()
    res.save(out)
    t3 = time.perf_counter()
    pick = res.pick if mode == "auto" else res
    row = {**size, "load_s": t1 - t0, "design_s": t2 - t1,
           "design_cpu_self_s": c2 - c1, "save_s": t3 - t2, "certified": bool(res.certified),
           "verdict": res.verdict, "bounded": None if pick is None else bool(pick.bounded),
           "growing": None if pick is None else bool(pick.growing),
           "rss_self_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
           "rss_children_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}
    if pick is not None:
        tr = pick.trace_bound
        x = pick.result.x_post  # (steps + 1, nodes, n_x); NaN where a node carrying its region has no estimate
        held = np.ones(x.shape[-2:], bool) if pick.result.carried is None else Carried(pick.result.carried,
                                                                                       x.shape[-1]).held
        row.update(finite=bool(np.isfinite(x[..., held]).all() and np.isfinite(tr[:, -1]).all()),
                   trace_final=float(np.nanmean(tr[:, -1])), rule=pick.gain_rule.name,
                   rounds=int(pick.design.rounds))
    if mode == "auto":
        row.update(outcome=res.outcome, candidates=len(res.candidates),
                   candidate_s={c.label: round(c.seconds, 2) for c in res.candidates})
    print(RESULT + json.dumps(row), flush=True)
    return 0


def model_files(folder: Path, models: list[str], field_sizes: list[tuple[int, int]],
                pandapower_python: str | None) -> list[tuple[str, Path]]:
    files = []
    for name in models:
        if name == "field":
            files += [(f"field {r}x{c}", field_file(folder, r, c)) for r, c in field_sizes]
        else:
            files.append((name, grid_file(folder, name, pandapower_python)))
    return files


def measure_models(plan: list[tuple[str, Path, str]], options: dict, timeout: float, max_gb: float) -> list[dict]:
    """Each (label, model file, mode) of ``plan`` designed in a fresh process (:func:`time_design`)."""
    rows = []
    for label, path, mode in plan:
        row = {"model": label, **time_design(path, mode, options, timeout, max_gb * 2 ** 30)}
        rows.append(row)
        print(f"  {label} {mode}: " + _brief(row), flush=True)
    return rows


def _brief(r: dict) -> str:
    if r.get("stopped"):
        return f"{r['stopped']} (peak {r['peak_mb']:.0f} MB)"
    if "error" in r:
        return f"FAILED: {r['error']}"
    return (f"{r['wall_s']:.1f} s wall ({r['design_s']:.1f} s design), {r['cpu_s']:.1f} s CPU, "
            f"{r['peak_mb']:.0f} MB, {r['verdict']}")


def print_models(rows: list[dict], options: dict) -> None:
    import os

    given = "".join(f", {k}={v}" for k, v in options.items())
    print(f"designs in fresh processes (studies.design(MODEL, mode=...{given}) and .save(DIR), as "
          f"cfdesign design runs them), load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    print(f"{'model':>12s} {'nodes':>5s} {'n_x':>4s} {'mode':>9s} {'wall s':>7s} {'CPU s':>7s} {'load s':>6s} "
          f"{'design s':>8s} {'save s':>6s} {'peak MB':>8s} {'(1 proc)':>8s} {'verdict':>12s} {'bounded':>7s} "
          f"{'final trPhi':>11s}  pick/outcome")
    for r in rows:
        head = f"{r['model']:>12s} {r.get('nodes', 0):5d} {r.get('states', 0):4d} {r['mode']:>9s} "
        if "design_s" not in r:
            print(head + f"{r['wall_s']:7.1f} {r['cpu_s']:7.1f} {'':>6s} {'':>8s} {'':>6s} {r['peak_mb']:8.0f}  "
                  + (r.get("stopped") or f"FAILED: {r.get('error')}"))
            continue
        one = max(r["rss_self_mb"], r["rss_children_mb"])
        extra = (f"{r.get('rule')} L={r.get('rounds')}" if r["mode"] == "auto" and r.get("rule") else "")
        if r["mode"] == "auto":
            extra += f" ({r['outcome']}, {r['candidates']} candidates)"
        print(head + f"{r['wall_s']:7.1f} {r['cpu_s']:7.1f} {r['load_s']:6.1f} {r['design_s']:8.1f} "
              f"{r['save_s']:6.1f} {r['peak_mb']:8.0f} {one:8.0f} {str(r['verdict']):>12s} "
              f"{str(r.get('bounded')):>7s} {r.get('trace_final', float('nan')):11.3g}  {extra}"
              + ("" if r.get("finite", True) else "  NON-FINITE"))
    print("wall, CPU: the fresh process from start to exit (start-up, imports, model, design, files and report; CPU "
          "with the processes it started); load: load_scenario (the model file); design: studies.design; save: the "
          "files and the report; peak MB: its processes' resident memory together (shared pages once: Pss), sampled "
          f"every {SAMPLE_S:g} s; (1 proc): the largest single process's (ru_maxrss); final trPhi: the node-average "
          "tr Phi at the horizon")
    for r in rows:
        name = r["model"].split()[0]
        if r.get("nodes") == TARGET_NODES.get(name):
            peak = max(r["peak_mb"], r.get("rss_self_mb", 0), r.get("rss_children_mb", 0))
            met = r.get("design_s") is not None and r["wall_s"] <= TARGET_S and peak <= TARGET_GB * 1024
            print(f"issue 41 target, {r['model']} {r['mode']}: {r['wall_s']:.0f} s and {peak / 1024:.2f} GB "
                  f"(target {TARGET_S:g} s and {TARGET_GB:g} GB on 2 cores: {'met' if met else 'MISSED'})")


def check_models(rows: list[dict]) -> bool:
    ok = True

    def fail(text: str) -> None:
        nonlocal ok
        print(f"FAIL: {text}", file=sys.stderr)
        ok = False

    done = [r for r in rows if "design_s" in r]
    for r in rows:
        what = f"{r['model']} {r['mode']}"
        if "design_s" not in r:
            fail(f"{what}: the design did not finish: {r.get('stopped') or r.get('error')}")
            continue
        if not r.get("finite", False):
            fail(f"{what}: non-finite estimates or bound at the horizon")
        peak = max(r["peak_mb"], r["rss_self_mb"], r["rss_children_mb"])
        if peak > CHECK_MAX_GB * 1024:
            fail(f"{what}: its processes held {peak:.0f} MB, above {CHECK_MAX_GB:g} GB")
        if r["mode"] == "relay" and not r["certified"]:
            fail(f"{what}: not certified ({r['verdict']})")
    fields = [r for r in done if r["model"].startswith("field")]
    for mode in sorted({r["mode"] for r in fields}):
        small = min((r for r in fields if r["mode"] == mode), key=lambda r: r["nodes"])
        large = max((r for r in fields if r["mode"] == mode), key=lambda r: r["nodes"])
        if small["nodes"] == large["nodes"]:
            continue
        growth = (large["design_s"] / large["nodes"]) / (small["design_s"] / small["nodes"])
        print(f"field, {mode}: design seconds per node, {large['nodes']} / {small['nodes']} cells: {growth:.2f} "
              f"(tolerance {FIELD_GROWTH_TOLERANCE:g})")
        if growth > FIELD_GROWTH_TOLERANCE:
            fail(f"the field's {mode} design's seconds per node grew {growth:.2f}x from {small['nodes']} to "
                 f"{large['nodes']} cells (tolerance {FIELD_GROWTH_TOLERANCE:g})")
    pairs = []  # (scheduled, relay) of each model with both
    for model in dict.fromkeys(r["model"] for r in done):
        by = {r["mode"]: r for r in done if r["model"] == model}
        if "relay" in by and "scheduled" in by:
            pairs.append((by["scheduled"], by["relay"]))
    if pairs:  # summed over the models: one short relay design's noise weighs less
        ratio = sum(s["design_s"] for s, _ in pairs) / sum(r["design_s"] for _, r in pairs)
        each = ", ".join(f"{s['model']} {s['design_s'] / r['design_s']:.2f}" for s, r in pairs)
        print(f"scheduled / relay design seconds, summed over the models: {ratio:.2f} ({each}; at most "
              f"{SCHEDULED_RELAY_MAX:g})")
        if ratio > SCHEDULED_RELAY_MAX:
            fail(f"the scheduled designs took {ratio:.2f} x the relay designs of the same models (at most "
                 f"{SCHEDULED_RELAY_MAX:g})")
    return ok


def _size(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"(\d+)x(\d+)", text)
    if not m or min(map(int, m.groups())) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: a field size is ROWSxCOLS, e.g. 8x8")
    return int(m[1]), int(m[2])


def finish(rows: list, args, checker) -> int:
    """The end of either run: the rows written to ``--json`` when given; with ``--check`` the exit code of
    ``checker(rows)`` (1 when a target is missed), else 0."""
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)
    return (0 if checker(rows) else 1) if args.check else 0


def models_main(args, ap) -> int:
    if args.timeout <= 0 or args.max_gb <= 0:
        ap.error("--timeout and --max-gb must be > 0")
    if args.validate is not None and args.validate < 0:
        ap.error("--validate must be >= 0")
    if args.steps is not None and args.steps < 1:
        ap.error("--steps must be >= 1")
    options = {"seed": args.seed, **{k: v for k, v in (("steps", args.steps), ("validate", args.validate),
                                                       ("carry", args.carry)) if v is not None}}
    fields = args.field_sizes or list(CHECK_FIELDS if args.check else FIELD_SIZES)
    modes = args.modes or list(CHECK_MODES if args.check else DESIGN_MODES)
    with tempfile.TemporaryDirectory() as tmp:
        files = model_files(Path(tmp), args.models, fields, args.pandapower_python)
        plan = [(label, path, mode) for label, path in files for mode in modes
                if not (args.check and (label, mode) in CHECK_SKIP)]
        rows = measure_models(plan, options, args.timeout, args.max_gb)
    print_models(rows, options)
    return finish(rows, args, check_models)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:  # a design's fresh process (time_design)
        model, mode, out, options = argv[1:5]
        return design_child(model, mode, out, json.loads(options))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", choices=sorted(GRIDS), default=None,
                    help=f"node counts (default {sorted(GRIDS)}; --check: {list(CHECK_SIZES)})")
    ap.add_argument("--steps", type=int, default=None, help="the design's horizon and the runs' length (default 100; "
                    "--models: the model's STEPS, 60)")
    ap.add_argument("--runs", type=int, default=None, help=f"Monte Carlo runs (default 5; --check: {CHECK_RUNS})")
    ap.add_argument("--seed", type=int, default=0, help="the runs' SeedSequence (--models: the designs' seed)")
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
    ap.add_argument("--models", nargs="+", choices=MODEL_NAMES, help="issue 41's models instead of the king's-move "
                    "grids: the heat field at --field-sizes, the IEEE 14-bus grid, and (their data read from "
                    "pandapower) the IEEE 30- and 118-bus grids; each design in a fresh process")
    ap.add_argument("--modes", nargs="+", choices=DESIGN_MODES, default=None,
                    help=f"--models: the design modes (default {' '.join(DESIGN_MODES)}; --check: "
                    f"{' '.join(CHECK_MODES)})")
    ap.add_argument("--field-sizes", type=_size, nargs="+", default=None, metavar="ROWSxCOLS",
                    help=f"--models field: the fields' sizes (default {' '.join(f'{r}x{c}' for r, c in FIELD_SIZES)};"
                    f" --check: {' '.join(f'{r}x{c}' for r, c in CHECK_FIELDS)})")
    ap.add_argument("--timeout", type=float, default=DESIGN_TIMEOUT_S, help="--models: stop a design after this many "
                    "seconds")
    ap.add_argument("--max-gb", type=float, default=DESIGN_MAX_GB, help="--models: stop a design whose processes hold "
                    "more memory than this")
    ap.add_argument("--carry", choices=["whole", "region"], default=None,
                    help="--models: the relay, flood and automatic designs' --carry (the models declare REGIONS)")
    ap.add_argument("--validate", type=int, default=None, metavar="R", help="--models: the designs' fresh validation "
                    "runs (studies.design's validate; default its own: 20 in mode auto, 0 with a rule)")
    ap.add_argument("--pandapower-python", metavar="PY", help="--models grid30 grid118: a Python that imports "
                    "pandapower, to read the IEEE cases' data (default: this one)")
    args = ap.parse_args(argv)
    kings = {"--sizes": args.sizes, "--runs": args.runs, "--exchange": args.exchange, "--rounds": args.rounds != 1,
             "--bank": args.bank, "--hcmci": args.hcmci, "--local": args.local, "--command": args.command}
    models = {"--modes": args.modes, "--field-sizes": args.field_sizes, "--validate": args.validate is not None,
              "--pandapower-python": args.pandapower_python, "--timeout": args.timeout != DESIGN_TIMEOUT_S,
              "--max-gb": args.max_gb != DESIGN_MAX_GB}
    wrong = [k for k, v in (kings if args.models else models).items() if v]
    if wrong:
        ap.error(f"{', '.join(wrong)}: {'not an option' if len(wrong) == 1 else 'not options'} of "
                 + ("--models" if args.models else "the king's-move grids (an option of --models)"))
    if args.models:
        return models_main(args, ap)
    args.steps = 100 if args.steps is None else args.steps
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
    return finish(rows, args, check)


if __name__ == "__main__":
    sys.exit(main())
