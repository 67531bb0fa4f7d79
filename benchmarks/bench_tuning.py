"""Speed of the convex tuning layer.

Reports: one re-solve of the update SDP and of the prediction SDP (cvxpy Parameters,
Clarabel), the same problems by the closed-form fast path, and the whole tuned
schedule of the indoor robot (8 nodes x 30 steps).  Targets (issue 4): a single
SDP re-solve <= 5 ms, the tuned schedule <= 2 s.  ``--check`` exits 1 when the
schedule target is missed (the SDP figure is reported; the schedule uses the fast
path, which the tests show agrees with the SDP).

Run: ``python benchmarks/bench_tuning.py [--check]``
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from designer.tuning import PredictionSDP, UpdateSDP, tune_prediction, tune_update

SCHEDULE_TARGET_S = 2.0
SDP_TARGET_S = 5e-3


def _instances(count: int):
    rng = np.random.default_rng(0)
    for _ in range(count):
        B = rng.normal(size=(3, 3))
        phi = 0.1 * B @ B.T + 0.05 * np.eye(3)
        yield (phi, np.eye(3) + 0.05 * rng.normal(size=(3, 3)), 0.01 * np.eye(3), 1e-3 * np.eye(3),
               rng.normal(size=(2, 3)), 0.1 * np.eye(2), np.eye(2), 3 * phi + 0.5 * np.eye(3))


def _median_time(fn, items) -> float:
    times = []
    for it in items:
        t = time.perf_counter()
        fn(*it)
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=60)
    ap.add_argument("--check", action="store_true")
    args = ap.parse_args(argv)
    items = list(_instances(args.count))
    psdp, usdp = PredictionSDP(3), UpdateSDP(3, 2)
    psdp.solve(*items[0][:4], 0.3)  # first solve compiles the problem
    usdp.solve(items[0][0], items[0][4], 3.0, items[0][5], items[0][6], 3, items[0][7])
    rows = {
        "prediction SDP re-solve": _median_time(lambda p, F, U, Q, *_: psdp.solve(p, F, U, Q, 0.3), items),
        "update SDP re-solve": _median_time(lambda p, F, U, Q, H, V, R, N: usdp.solve(p, H, 3.0, V, R, 3, N), items),
        "prediction fast path": _median_time(lambda p, F, U, Q, *_: tune_prediction(p, F, U, Q, 0.3), items),
        "update fast path": _median_time(lambda p, F, U, Q, H, V, R, N: tune_update(p, H, 3.0, V, R, 3, N), items),
    }
    from studies.api import design

    design("indoor-robot", mode="tuned", seed=0, steps=2)  # warm-up (imports, CasADi functions)
    t = time.perf_counter()
    design("indoor-robot", mode="tuned", seed=0)
    rows["tuned schedule, indoor robot (8 x 30)"] = time.perf_counter() - t
    for name, v in rows.items():
        unit = f"{v * 1e3:9.2f} ms" if v < 1 else f"{v:9.2f} s "
        print(f"{name:40s} {unit}")
    sdp = max(rows["prediction SDP re-solve"], rows["update SDP re-solve"])
    print(f"SDP re-solve target {SDP_TARGET_S * 1e3:.0f} ms: {'met' if sdp <= SDP_TARGET_S else 'MISSED'}")
    sched = rows["tuned schedule, indoor robot (8 x 30)"]
    print(f"schedule target {SCHEDULE_TARGET_S:.0f} s: {'met' if sched <= SCHEDULE_TARGET_S else 'MISSED'}")
    if args.check and sched > SCHEDULE_TARGET_S:
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
