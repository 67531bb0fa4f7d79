"""What a user waits for: every study at its default size and the feasibility map, end to end through the CLI.

Each case is a new ``cfdesign`` process, first with an empty kernel cache (cold: every numba kernel
compiles, as after ``cfdesign cache clear``), then with the cache it left (warm: what every later
run of the machine takes).  ``CFDESIGN_CACHE_DIR`` is a temporary directory, never the user's
cache; every run writes into a fresh ``--out`` (no stored chunk is reused).  Wall time and the CPU
time of the process are printed (the machine may be shared: its load average is printed too; CPU
time is the steadier figure there), beside the targets of issue 15 for the default sizes.

``--reduced`` runs every case at a small size (what CI runs).  ``--check`` exits 1 when a warm run
of a study with compiled particle kernels takes more than ``WARM_RATIO`` of its cold run, both
measured in this run: the cache must spare a fresh process the compilation.  The absolute targets
are printed, not checked (they are for an unshared 2-core machine).

Run: ``python benchmarks/bench_studies.py [--reduced] [--only NAME ...] [--check] [--markdown FILE]``
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

WARM_RATIO = 0.5  # --check: warm / cold of the particle-filter studies (compiled kernels)


class Case(NamedTuple):
    name: str
    args: tuple[str, ...]  # after ``cfdesign``; ``{out}`` is the output directory
    target_s: float | None  # issue 15's target, warm, one process (default size only)
    kernels: bool  # compiles numba particle kernels (the cache must spare them)
    ratio_target: float | None = None  # issue 15's target of warm / cold (reported, not --check'ed: noisy)


_GRID = ("--grid", "dos=0:0.6:13", "--grid", "fdi=0:0.6:13")
DEFAULT = (
    Case("rrp-deception --runs 2 --particles 100", ("study", "rrp-deception", "--runs", "2", "--particles", "100"),
         4.0, True, 0.15),
    Case("rrp-deception", ("study", "rrp-deception"), 10.0, True),
    Case("binary-multi-attack", ("study", "binary-multi-attack"), 10.0, True),
    Case("encrypted-switching", ("study", "encrypted-switching"), 5.0, True),
    Case("fdi-four-tank", ("study", "fdi-four-tank"), 10.0, True),
    Case("consensus-robot", ("study", "consensus-robot"), None, False),
    Case("feasibility 13 x 13 (robot, tuned)", ("feasibility", "indoor-robot", "--mode", "tuned", *_GRID), 20.0,
         False),
    Case("comparison", ("study", "comparison"), 240.0, False),
)
REDUCED = (
    Case("rrp-deception --runs 2 --particles 100", ("study", "rrp-deception", "--runs", "2", "--particles", "100"),
         4.0, True, 0.15),
    Case("binary-multi-attack --runs 2 --particles 100",
         ("study", "binary-multi-attack", "--runs", "2", "--particles", "100"), None, True),
    Case("encrypted-switching --runs 2", ("study", "encrypted-switching", "--runs", "2"), None, True),
    Case("fdi-four-tank --runs 2", ("study", "fdi-four-tank", "--runs", "2"), None, True),
    Case("consensus-robot --runs 20", ("study", "consensus-robot", "--runs", "20"), None, False),
    Case("feasibility 5 x 5 (robot, tuned)",
         ("feasibility", "indoor-robot", "--mode", "tuned", "--grid", "dos=0:0.6:5", "--grid", "fdi=0:0.6:5"),
         None, False),
    Case("comparison (robot) --runs 2 --particles 100, one sweep point",
         ("study", "comparison", "indoor-robot", "--runs", "2", "--particles", "100", "--set", "sweep_values=[0.2]"),
         None, False),
)


class Timing(NamedTuple):
    wall_s: float
    cpu_s: float  # user + system time of the process


def run_case(case: Case, cache: Path, out: Path) -> Timing:
    """One fresh ``cfdesign`` process for ``case`` with the kernel cache ``cache``, writing into ``out``."""
    cli = Path(sys.executable).with_name("cfdesign")
    cmd = [str(cli), *case.args, "--quiet", "--out", str(out)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    res = subprocess.run(cmd, env={**os.environ, "CFDESIGN_CACHE_DIR": str(cache)}, capture_output=True, text=True)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({res.returncode}): {res.stderr.strip()}")
    return Timing(wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime))


def measure(cases, repeats: int) -> list[tuple[Case, Timing, Timing]]:
    """``(case, cold, best warm)`` for every case; each case has a cache of its own (its cold run is cold)."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="cfdesign-bench-studies-") as tmp:
        for i, case in enumerate(cases):
            cache = Path(tmp) / f"cache{i}"
            cold = run_case(case, cache, Path(tmp) / f"out{i}-cold")
            warm = min((run_case(case, cache, Path(tmp) / f"out{i}-warm{r}") for r in range(repeats)),
                       key=lambda t: t.wall_s)
            rows.append((case, cold, warm))
            print(f"  {case.name}: cold {cold.wall_s:.1f} s, warm {warm.wall_s:.1f} s", file=sys.stderr, flush=True)
    return rows


def table(rows) -> str:
    lines = ["| case | warm wall (s) | warm CPU (s) | cold wall (s) | warm / cold | target, warm (s) |",
             "|---|---|---|---|---|---|"]
    for case, cold, warm in rows:
        target = "" if case.target_s is None else (f"{case.target_s:g} "
                                                   f"({'met' if warm.wall_s <= case.target_s else 'missed'})")
        ratio = warm.wall_s / cold.wall_s
        if case.ratio_target is not None:
            ratio = f"{ratio:.3f} ({case.ratio_target:g}: {'met' if ratio <= case.ratio_target else 'missed'})"
        else:
            ratio = f"{ratio:.2f}"
        lines.append(f"| `{case.name}` | {warm.wall_s:.2f} | {warm.cpu_s:.1f} | {cold.wall_s:.1f} | {ratio} | "
                     f"{target} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reduced", action="store_true", help="small sizes (CI)")
    ap.add_argument("--only", nargs="+", metavar="NAME", help="the cases whose name starts with one of these")
    ap.add_argument("--repeats", type=int, default=1, help="warm runs per case (the fastest is kept)")
    ap.add_argument("--check", action="store_true",
                    help=f"exit 1 if a study with particle kernels takes more than {WARM_RATIO} of its cold time warm")
    ap.add_argument("--markdown", type=Path, help="also write the table to this file")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error("--repeats must be >= 1")
    cases = [c for c in (REDUCED if args.reduced else DEFAULT)
             if not args.only or any(c.name.startswith(p) for p in args.only)]
    if not cases:
        ap.error("--only matches no case")
    load = os.getloadavg()[0]
    print(f"fresh cfdesign processes, cold (empty kernel cache) then warm; load average {load:.1f} on "
          f"{os.cpu_count()} cores", file=sys.stderr)
    rows = measure(cases, args.repeats)
    text = table(rows)
    print(text)
    if args.markdown:
        args.markdown.write_text(text + "\n")
    failed = [case.name for case, cold, warm in rows if case.kernels and warm.wall_s > WARM_RATIO * cold.wall_s]
    if args.check and failed:
        print(f"FAILED: warm > {WARM_RATIO} x cold for {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
