"""The memory estimates of :mod:`studies.memory` against the peak memory of the real commands.

Each case runs in a fresh process: a small run of the same command first (the imports, the
compiled kernels, the model's CasADi functions), then the peak resident memory is reset
(``/proc/self/clear_refs``) and the measured command runs; the figure is ``VmHWM`` minus the
resident memory before it, beside the :class:`studies.memory.Need` that the command computed
for itself (captured from :func:`studies.memory.check`) and their ratio.  The model files are
the README's ``examples/ring_model.py`` and chains of ``NX`` states on ``NODES`` nodes written to a
temporary directory, the sizes chosen so that every case runs in seconds to a minute.

Run: ``python benchmarks/bench_memory.py [--only NAME ...]`` (Linux only: ``/proc``).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

CHAIN = """
import os
import casadi as ca
import numpy as np
from designer import AttackSpec, FDISignal, Gaussian, Model, SensorNetwork, Sensor
NX, NODES = {nx}, {nodes}
STEPS = {steps}
NETWORK = SensorNetwork.from_edges(NODES, [(i, i + 1) for i in range(NODES - 1)])
ATTACKS = AttackSpec(dos=0.1, fdi=0.1, signal=FDISignal(amplitude=0.2, components=(0,)))
def model() -> Model:
    x = ca.SX.sym("x", NX)
    f = ca.vertcat(*[0.99 * x[i] + 0.01 * ca.sin(x[(i + 1) % NX]) for i in range(NX)])
    per = max(1, NX // NODES)
    sensors = [Sensor(f"s{{i}}", x[(i * per) % NX:(i * per) % NX + per], Gaussian.zero_mean(0.05 * np.eye(per)))
               for i in range(NODES)]
    return Model("chain", x, f, sensors, process_noise=Gaussian.zero_mean(1e-3 * np.eye(NX)),
                 prior=Gaussian(np.zeros(NX), 0.05 * np.eye(NX)))
"""

# name -> (warm-up arguments, measured arguments); {ring} (examples/ring_model.py), {chainNX_NODES_STEPS} and
# {out} are filled in
CASES = {
    "simulate 200k steps": (["simulate", "{ring}", "--steps", "20", "--out", "{out}/w.npz"],
                            ["simulate", "{ring}", "--steps", "200000", "--out", "{out}/s.npz"]),
    "design 10k steps": (["design", "{ring}", "--out", "{out}/w"], ["design", "{ring}", "--steps", "10000",
                                                                    "--out", "{out}/d"]),
    "design 60 states (Hessians)": (["design", "{chain60_4_5}", "--u-scale", "0", "--v-scale", "0", "--out", "{out}/w"],
                                    ["design", "{chain60_4_5}", "--out", "{out}/d"]),
    "design 40 states x 8 nodes x 200 steps": (
        ["design", "{chain40_8_200}", "--steps", "3", "--u-scale", "0", "--v-scale", "0", "--out", "{out}/w"],
        ["design", "{chain40_8_200}", "--u-scale", "0", "--v-scale", "0", "--out", "{out}/d"]),
    "feasibility 5000 points": (["feasibility", "{ring}", "--mode", "paper", "--grid", "dos=0:0.5:3", "--out", "{out}/w",
                                 "--quiet"],
                                ["feasibility", "{ring}", "--mode", "paper", "--grid", "dos=0:0.5:100", "--grid", "fdi=0:0.4:50",
                                 "--out", "{out}/f", "--quiet"]),
    "feasibility 30 states x 64 points": (
        ["feasibility", "{chain30_4_20}", "--mode", "paper", "--grid", "dos=0:0.5:2", "--u-scale", "0", "--v-scale", "0", "--out",
         "{out}/w", "--quiet"],
        ["feasibility", "{chain30_4_20}", "--mode", "paper", "--grid", "dos=0:0.5:64", "--u-scale", "0", "--v-scale", "0", "--out",
         "{out}/f", "--quiet"]),
    "comparison 16 states x 4 nodes": (
        ["study", "comparison", "{chain16_4_30}", "--runs", "2", "--particles", "20", "--out", "{out}/w", "--quiet",
         "--set", "sweep_values=[0.1]"],
        ["study", "comparison", "{chain16_4_30}", "--runs", "10", "--particles", "200", "--out", "{out}/c",
         "--quiet"]),
    "consensus-robot 20 states x 8 nodes": (
        ["study", "consensus-robot", "{chain20_8_40}", "--runs", "2", "--out", "{out}/w", "--quiet"],
        ["study", "consensus-robot", "{chain20_8_40}", "--runs", "40", "--out", "{out}/r", "--quiet"]),
    "rrp-deception 20000 particles": (
        ["study", "rrp-deception", "--runs", "2", "--particles", "100", "--out", "{out}/w", "--quiet"],
        ["study", "rrp-deception", "--runs", "10", "--particles", "20000", "--out", "{out}/r", "--quiet"]),
}

CHILD = """
import contextlib, io, json, re, sys
from studies import memory
from studies.cli import main

def status(key):
    return int(re.search(rf"{key}:\\s+(\\d+) kB", open("/proc/self/status").read()).group(1)) * 1024

warm, args = json.loads(sys.argv[1]), json.loads(sys.argv[2])
needs, check = [], memory.check
memory.check = lambda need, available=None: (needs.append(need), check(need, available))[1]
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    main(warm)
needs.clear()
import gc; gc.collect()
with open("/proc/self/clear_refs", "w") as fh:
    fh.write("5")
base = status("VmRSS")
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as err:
    rc = main(args)
peak = status("VmHWM") - base
print(json.dumps({"rc": rc, "peak": peak, "estimate": max((n.nbytes for n in needs), default=0.0),
                  "parts": [str(p) for n in needs for p in sorted(n.peak, key=lambda p: -p.nbytes)][:4],
                  "error": err.getvalue()[-300:]}))
"""


def _files(tmp: Path) -> dict:
    files = {"ring": Path(__file__).resolve().parents[1] / "examples" / "ring_model.py"}
    for name in {a.split("}")[0] for w, m in CASES.values() for arg in w + m for a in arg.split("{")[1:]}:
        if name.startswith("chain"):
            nx, nodes, steps = name[5:].split("_")
            files[name] = tmp / f"{name}.py"
            files[name].write_text(CHAIN.format(nx=nx, nodes=nodes, steps=steps))
    return files


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", default=None, help="run only the cases whose name contains one of these")
    args = ap.parse_args(argv)
    env = dict(os.environ, MPLBACKEND="Agg", OPENBLAS_NUM_THREADS="1")
    print(f"{'case':42s} {'measured':>10s} {'estimated':>10s} {'ratio':>6s}  largest part of the estimate")
    with tempfile.TemporaryDirectory() as tmp:
        files = _files(Path(tmp))
        for name, (warm, measured) in CASES.items():
            if args.only and not any(o in name for o in args.only):
                continue
            out = Path(tmp) / name.replace(" ", "_")
            out.mkdir()
            fill = {k: str(v) for k, v in files.items()} | {"out": str(out)}
            w, m = ([a.format(**fill) for a in argv_] for argv_ in (warm, measured))
            r = subprocess.run([sys.executable, "-c", CHILD, json.dumps(w), json.dumps(m)], capture_output=True,
                               text=True, env=env, timeout=1800)
            if r.returncode != 0:
                print(f"{name:42s} failed: {r.stderr[-500:]}")
                continue
            res = json.loads(r.stdout.strip().splitlines()[-1])
            ratio = res["estimate"] / res["peak"] if res["peak"] > 0 else float("inf")
            part = res["parts"][0] if res["parts"] else res["error"].strip()
            print(f"{name:42s} {res['peak'] / 2**20:8.1f} MiB {res['estimate'] / 2**20:8.1f} MiB {ratio:6.2f}  "
                  f"{textwrap.shorten(part, 70)}" + (f"  (exit {res['rc']})" if res["rc"] not in (0, 1) else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
