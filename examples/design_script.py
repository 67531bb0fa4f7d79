"""A design script: design, map, compare and report a consensus filter for a user's own model, in Python.

The model is ``mixed_sensors_model.py`` beside this file (a target watched by range-bearing, range-only and
bearing-only sensors on a star network, attacks declared per edge).  Everything the command line does is one
function of ``studies`` here, with the same numbers.

Run: ``python examples/design_script.py [OUT]`` (default OUT: ``out/design-script``; about a minute).
"""
import sys
from pathlib import Path

import numpy as np

import studies

HERE = Path(__file__).resolve().parent
MODEL = HERE / "mixed_sensors_model.py"
out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/design-script")

# 1. Design the consensus filter along a seeded simulated run, with the convex tuning layer.
d = studies.design(MODEL, mode="tuned", seed=1, out=out / "design")
print(f"tuned design: feasible {d.feasible}; epsilon {d.design.epsilon:.3g}, delta {d.design.delta:.3g}")
print("  verdict:", d.verdict_line())  # certified, or which condition and node prevent it
print("  V_i (per sensor, in its own units):", [np.round(np.diag(v), 4).tolist() for v in d.design.V])
print("  final tr Phi per node:", np.round(d.trace_bound[:, -1], 3).tolist())
paper = studies.design(MODEL, mode="paper", seed=1)
print(f"paper design: feasible {paper.feasible}" + ("" if paper.feasible else f" ({paper.reason()})"))

# 2. Where does the tuned design keep a bounded steady-state bound?  The same design options as above.
fmap = studies.feasibility(MODEL, ["dos=0:0.4:5", "fdi=0:0.3:4"], mode="tuned", out=out / "feasibility")
print(f"feasibility map: {int(fmap.feasible.sum())} of {fmap.feasible.size} grid points feasible; verdicts "
      f"{fmap.verdict_counts}")

# 3. Compare every filter family on the same runs and attack realisations (reduced size).
cmp = studies.study("comparison", MODEL, runs=6, particles=200, seed=1, out=out / "comparison")
for name, f in cmp.filters.items():
    rmse = "diverged" if f["rmse_position"] is None else f"{f['rmse_position']:.3g} m"
    print(f"  {name}: RMSE_p {rmse}, {f['messages_per_step']} messages/step")

# 4. Rebuild a report (the functions above wrote theirs already).
html, md = studies.report(out / "comparison")
print("reports:", out / "design" / "report.html", out / "feasibility" / "report.html", html)
