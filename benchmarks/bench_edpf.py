"""Study ``encrypted-switching`` (seed 001) on the fused kernels against the NumPy engine, in one run.

Workload (the target's): the study with the paper's three filters — PPF, PF-RSN and
PF-SR-DE — ``--runs`` 50 Monte Carlo runs of 120 steps with ``--particles`` 200, as
``studies.pipeline.run_study("encrypted-switching", ...)`` computes it with
``out=None``: data simulation, channel, the filters, metrics and the claim check;
figures are not drawn.  JIT compilation is excluded (done first by
:func:`studies.encrypted_switching.warm_up` and reported apart).

Measured: the fast engine with 2 threads (best of ``--repeats``; target <= 1 s
wall) and with 1 thread; the study's default with the extra "PF-RSN (mean
dynamics)" row (2 threads, reported); the NumPy engine
(:func:`filters.particle.run_sir`, one measurement: it takes seconds) on the same
study in the same process; the split of both (data, channel, each filter, the
rest: scenario set-up and metrics) and every filter's RMSE_1 / RMSE_2 on both
engines (different random numbers, so close, not equal).  ``--check`` exits 1 when
the target is missed.  ``--json FILE`` writes the figures.  The machine may be
shared: the load average is printed beside the figures.

Run: ``python benchmarks/bench_edpf.py [--runs 50] [--particles 200] [--check]``
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numba

from bench_sir import best_of  # the sibling script (benchmarks/ is on sys.path when run as a script)
from studies.encrypted_switching import RunConfig, warm_up
from studies.pipeline import run_study
from studies.scenarios import load_scenario, reference

TARGET_STUDY_S = 1.0


def study(runs: int, particles: int, seed: int, engine: str, threads: int, extra_row: bool = False):
    t = time.perf_counter()
    res = run_study("encrypted-switching", runs=runs, particles=particles, seed=seed, engine=engine, threads=threads,
                    mean_dynamics_row=extra_row).results
    return time.perf_counter() - t, res


def split(res: dict, wall: float) -> dict:
    tm = res["timing_s"]
    parts = {"data": tm["data"], "channel": tm["channel"], **tm["filters"]}
    parts["rest (set-up, metrics)"] = wall - sum(parts.values())
    return parts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--particles", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--check", action="store_true", help="exit 1 if the target is missed")
    ap.add_argument("--json", help="write the measurements to this file")
    args = ap.parse_args(argv)
    R, M = args.runs, args.particles
    load0 = os.getloadavg()[0]
    t_all = time.perf_counter()
    out: dict = {"runs": R, "particles": M, "cpus": os.cpu_count(), "numba": numba.__version__}

    t = time.perf_counter()
    warm_up(RunConfig(M, reference(load_scenario("switching-2d"))))
    out["compile_s"] = time.perf_counter() - t

    w2, res2 = best_of(lambda: study(R, M, args.seed, "fast", 2), args.repeats)
    w1, _ = study(R, M, args.seed, "fast", 1)
    w4, res4 = best_of(lambda: study(R, M, args.seed, "fast", 2, extra_row=True), args.repeats)
    wn, resn = study(R, M, args.seed, "numpy", 1)
    out["fast"] = {"wall_s_threads2": w2, "wall_s_threads1": w1, "split_s": split(res2, w2),
                   "with_mean_dynamics_row_wall_s_threads2": w4,
                   "mean_dynamics_row_s": res4["timing_s"]["filters"]["PF-RSN (mean dynamics)"]}
    out["numpy"] = {"wall_s": wn, "split_s": split(resn, wn)}
    out["rmse_state"] = {name: {"fast": f["rmse_state"], "numpy": resn["filters"][name]["rmse_state"]}
                         for name, f in res2["filters"].items()}
    out["claim_holds"] = {"fast": res2["claim_check"]["holds"], "numpy": resn["claim_check"]["holds"]}
    out["load_average"] = [load0, os.getloadavg()[0]]
    out["benchmark_wall_s"] = time.perf_counter() - t_all

    # ------------------------------------------------------------------ report
    K = res2["steps"]
    print(f"encrypted-switching, {R} runs x {K} steps x {M} particles, 3 filters ({out['cpus']} CPUs, load average "
          f"{load0:.2f} -> {out['load_average'][1]:.2f}; shared machines are noisy)")
    print(f"JIT compile (once per process, excluded below): {out['compile_s']:.2f} s")
    print(f"whole study, fast engine: {w2:.3f} s wall with 2 threads (best of {args.repeats}), {w1:.3f} s with 1   "
          f"target <= {TARGET_STUDY_S} s")
    print(f"  with the extra 'PF-RSN (mean dynamics)' row (the CLI's default): {w4:.3f} s (2 threads, best of "
          f"{args.repeats}; the row {out['fast']['mean_dynamics_row_s']:.3f} s)")
    print(f"whole study, NumPy engine: {wn:.3f} s ({wn / w2:.1f}x the fast study)")
    print(f"  {'part':26s} {'fast (2 thr.)':>13s} {'numpy':>9s}")
    for k, v in out["fast"]["split_s"].items():
        print(f"  {k:26s} {v:12.3f}s {out['numpy']['split_s'][k]:8.3f}s")
    print(f"  {'filter':26s} {'RMSE_1, RMSE_2 fast':>22s} {'numpy':>16s}")
    for name, r in out["rmse_state"].items():
        print(f"  {name:26s} {r['fast'][0]:10.3f} {r['fast'][1]:10.3f}  {r['numpy'][0]:7.3f} {r['numpy'][1]:7.3f}")
    print(f"paper's claim (PPF best on both states) holds: fast {out['claim_holds']['fast']}, "
          f"numpy {out['claim_holds']['numpy']}")
    print(f"benchmark wall time {out['benchmark_wall_s']:.1f} s")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=2)
    if args.check and w2 > TARGET_STUDY_S:
        print(f"FAIL: encrypted-switching study {w2:.3f} s > {TARGET_STUDY_S} s", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
