"""A convex problem solved in a process forked after its parent solved one (a design's certificate beside its run,
an automatic design's candidates, a study's workers) must finish: every solve passes
:data:`designer.cores.SOLVER_SETTINGS` (Clarabel on one thread; its default rayon pool, created at the parent's first
solve, is not inherited by the child, which waited for it for ever)."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = """
import os, cvxpy as cp, numpy as np
from designer.cores import SOLVER_SETTINGS
def solve():
    X = cp.Variable((30, 30), PSD=True)
    A = np.random.default_rng(0).normal(size=(30, 30)); A = A @ A.T
    cp.Problem(cp.Minimize(cp.trace(A @ X)), [X >> np.eye(30), cp.trace(X) <= 100]).solve(solver=cp.CLARABEL,
                                                                                       **SOLVER_SETTINGS)
solve()
pid = os.fork()
if pid == 0:
    solve()
    os._exit(0)
_, status = os.waitpid(pid, 0)
print("child", status)
"""


def test_a_solve_in_a_child_forked_after_a_solve_finishes():
    proc = subprocess.run([sys.executable, "-c", SCRIPT], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "child 0" in proc.stdout, proc.stderr[-1000:]


def test_every_clarabel_solve_passes_the_settings():
    """Each ``.solve(solver=cp.CLARABEL, ...)`` in the package passes ``**SOLVER_SETTINGS``."""
    calls = 0
    for path in [p for d in ("designer", "filters", "rules", "studies") for p in (ROOT / d).rglob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "solve":
                solver = [k for k in node.keywords if k.arg == "solver"]
                if solver and "CLARABEL" in ast.unparse(solver[0].value):
                    calls += 1
                    spread = [ast.unparse(k.value) for k in node.keywords if k.arg is None]
                    assert "SOLVER_SETTINGS" in spread, f"{path.relative_to(ROOT)}:{node.lineno}"
    assert calls >= 3
