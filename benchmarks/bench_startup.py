"""Start-up of the command line in fresh processes, against a fresh Python importing NumPy.

What a user waits for before anything is computed: ``cfdesign --help``, ``cfdesign design --help``
and ``cfdesign scenarios`` (which lists the built-ins without building their CasADi models), each
in a fresh process, beside ``python -c "import numpy"`` measured in the same run.  The runs are
interleaved (one of each in turn) and each figure is the best of ``--repeat`` (the machine is
shared: the best is the least disturbed).  Target (issue 15): every command within 2 x the NumPy
start-up; ``--check`` exits 1 when one is not.

Run: ``python benchmarks/bench_startup.py [--repeat 15] [--check]``
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

TARGET_RATIO = 2.0


def _cfdesign() -> list[str]:
    """The console script next to this interpreter (what a user runs), else ``python -m studies``."""
    script = Path(sys.executable).with_name("cfdesign")
    return [str(script)] if script.exists() else [sys.executable, "-m", "studies"]


def _run(cmd: list[str]) -> float:
    env = dict(os.environ, MPLBACKEND="Agg")
    t = time.perf_counter()
    r = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, timeout=300)
    dt = time.perf_counter() - t
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({r.returncode}): {r.stderr.decode()[-500:]}")
    return dt


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--check", action="store_true")
    args = ap.parse_args(argv)
    cli = _cfdesign()
    commands = {
        'python -c "import numpy"': [sys.executable, "-c", "import numpy"],
        "cfdesign --help": cli + ["--help"],
        "cfdesign design --help": cli + ["design", "--help"],
        "cfdesign scenarios": cli + ["scenarios"],
    }
    for cmd in commands.values():  # once, unmeasured: byte-compiled files and the disk cache
        _run(cmd)
    best = {name: float("inf") for name in commands}
    for _ in range(args.repeat):
        for name, cmd in commands.items():
            best[name] = min(best[name], _run(cmd))
    base = best['python -c "import numpy"']
    ok = True
    print(f"{'command':28s} {'best of ' + str(args.repeat):>12s}  ratio to NumPy (target <= {TARGET_RATIO:g})")
    for name, t in best.items():
        ratio = t / base
        mark = "" if name.startswith("python") else ("  met" if ratio <= TARGET_RATIO else "  MISSED")
        ok &= ratio <= TARGET_RATIO
        print(f"{name:28s} {t * 1e3:9.0f} ms  {ratio:5.2f}{mark}")
    return 1 if args.check and not ok else 0


if __name__ == "__main__":
    sys.exit(main())
