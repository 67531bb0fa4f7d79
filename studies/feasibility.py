"""``cfdesign feasibility``: parameter-feasibility maps of the consensus-filter bounds.

At every grid point the steady-state bound recursion at the scenario's operating
point (its initial state ``x0`` and first input) is iterated to a fixed point
(:func:`designer.feasibility.steady_state`); ``feasibility.csv`` gets one row per
point (the grid parameters, ``feasible``, ``trace_bound``, ``binding``,
``theorem2``, ``iterations``) and a heat map is drawn for one or two grid
parameters.  Points run in parallel with ``--workers``.
"""
from __future__ import annotations

import csv
import io
import itertools
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from designer.feasibility import steady_state
from designer.fileio import atomic_write
from designer.validation import InputError, check_int

from .design import consensus_design
from .progress import progress
from .scenarios import load_scenario

__all__ = ["GRID_PARAMETERS", "parse_grid", "feasibility_map"]

GRID_PARAMETERS = {
    "dos": "DoS probability on every channel, in [0, 1)",
    "fdi": "FDI probability on every channel, in [0, 1)",
    "delta": "bound on the injected signal, >= 0",
    "tau": "consensus gain C = tau Phi_pred (paper mode only), >= 0",
}


def parse_grid(spec: str) -> tuple[str, np.ndarray]:
    """``NAME=START:STOP:COUNT`` -> (name, values)."""
    if "=" not in spec:
        raise InputError(f"--grid expects NAME=START:STOP:COUNT, got {spec!r}")
    name, rng = spec.split("=", 1)
    name = name.strip()
    if name not in GRID_PARAMETERS:
        raise InputError(f"--grid parameter {name!r} is unknown; allowed: {', '.join(GRID_PARAMETERS)}")
    parts = rng.split(":")
    try:
        if len(parts) != 3:
            raise ValueError
        start, stop, count = float(parts[0]), float(parts[1]), int(parts[2])
    except ValueError:
        raise InputError(f"--grid {name} expects START:STOP:COUNT (COUNT an integer >= 1), got {rng!r}") from None
    if count < 1 or not (np.isfinite(start) and np.isfinite(stop)):
        raise InputError(f"--grid {name}: COUNT must be >= 1 and START, STOP finite, got {rng!r}")
    values = np.linspace(start, stop, count)
    if name in ("dos", "fdi") and (values.min() < 0 or values.max() >= 1):
        raise InputError(f"--grid {name} must lie in [0, 1), got {start}:{stop}")
    if name in ("delta", "tau") and values.min() < 0:
        raise InputError(f"--grid {name} must be >= 0, got {start}:{stop}")
    return name, values


def _point(args) -> dict:
    point, F, H, Q, R, network, design, phi0 = args
    try:
        net = network.with_attacks(point.get("dos"), point.get("fdi"))
    except InputError:  # DoS and FDI never occur together: dos + fdi > 1 is no attack model
        return {**point, "feasible": 0, "trace_bound": float("nan"), "binding": "dos + fdi > 1",
                "theorem2": 0, "iterations": 0}
    r = steady_state(F, H, Q, R, net, epsilon=design.epsilon, delta=point.get("delta", design.delta), U=design.U,
                     V=design.V, mode=design.mode, sigma=design.sigma, beta=design.beta,
                     tau=point.get("tau", design.tau), phi0=phi0)
    return {**point, "feasible": int(r.feasible), "trace_bound": r.trace_bound, "binding": r.binding,
            "theorem2": int(r.theorem2), "iterations": r.iterations}


def feasibility_map(
    scenario: str,
    grids: Sequence[str],
    *,
    out: str | Path | None = None,
    mode: str = "tuned",
    workers: int = 1,
    quiet: bool = False,
    overrides: Mapping[str, Any] | None = None,
    assignments=(),
    design_options: Mapping[str, Any] | None = None,
) -> list[dict]:
    """Compute the feasibility map over the grids (``NAME=START:STOP:COUNT`` strings)."""
    if not grids:
        raise InputError("give at least one --grid NAME=START:STOP:COUNT")
    parsed = [parse_grid(g) for g in grids]
    names = [n for n, _ in parsed]
    if len(set(names)) != len(names):
        raise InputError("each --grid parameter may be given once")
    if mode not in ("paper", "tuned"):
        raise InputError(f"mode must be 'paper' or 'tuned', got {mode!r}")
    if "tau" in names and mode == "tuned":
        raise InputError("--grid tau applies to mode 'paper' only (the tuned design chooses C itself)")
    workers = check_int("workers", workers, 1)
    sc = load_scenario(scenario, overrides, assignments)
    if sc.network is None:
        raise InputError(f"scenario {sc.name!r} has no sensor network; the consensus design needs one")
    design = consensus_design(sc, mode=mode, **dict(design_options or {}))
    m = sc.model
    u = sc.inputs(1)
    u0 = None if u is None else u[0]
    x0 = m.prior.mean if sc.x0 is None else sc.x0
    F = m.F_expected(x0, 0, u0)
    xp = m.f_expected(x0, 0, u0)
    H = [m.H(i, xp, 1) for i in range(m.n_sensors)]
    R = [m.measurement_cov(i) for i in range(m.n_sensors)]
    points = [dict(zip(names, map(float, combo))) for combo in itertools.product(*[v for _, v in parsed])]
    jobs = [(p, F, H, m.process_cov, R, sc.network, design, m.prior.cov) for p in points]
    rows = _run(jobs, workers, quiet)
    if out is not None:
        out = Path(out)
        _write_csv(out / "feasibility.csv", rows, names)
        if len(names) <= 2:
            _figure(out / "feasibility.png", rows, parsed, sc.name, mode)
    return rows


def _run(jobs, workers: int, quiet: bool) -> list[dict]:
    if workers == 1:
        return list(progress(map(_point, jobs), len(jobs), quiet, "feasibility"))
    with ProcessPoolExecutor(max_workers=workers) as pool:
        it = pool.map(_point, jobs, chunksize=max(1, len(jobs) // (8 * workers)))
        return list(progress(it, len(jobs), quiet, "feasibility"))  # map keeps the grid order


def _write_csv(path: Path, rows: list[dict], names: list[str]) -> None:
    buf = io.StringIO()
    cols = names + ["feasible", "trace_bound", "binding", "theorem2", "iterations"]
    w = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if isinstance(r[k], float) and np.isnan(r[k]) else r[k]) for k in cols})
    atomic_write(path, lambda fh: fh.write(buf.getvalue().encode()))


def _figure(path: Path, rows: list[dict], parsed, scenario: str, mode: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    tb = np.array([r["trace_bound"] if r["feasible"] else np.nan for r in rows])
    fig, ax = plt.subplots(figsize=(7, 5))
    if len(parsed) == 1:
        (name, vals), = parsed
        ax.semilogy(vals, tb, "o-")
        bad = np.isnan(tb)
        ax.plot(vals[bad], np.full(bad.sum(), np.nanmin(tb) if np.any(~bad) else 1.0), "rx", label="infeasible")
        ax.set_xlabel(name)
        ax.set_ylabel("steady-state tr Φ (mean over nodes)")
        ax.legend()
    else:
        (n1, v1), (n2, v2) = parsed
        grid = tb.reshape(len(v1), len(v2))
        finite = grid[np.isfinite(grid)]
        norm = LogNorm(finite.min(), finite.max()) if finite.size and finite.min() > 0 else None
        mesh = ax.pcolormesh(v2, v1, np.ma.masked_invalid(grid), norm=norm, shading="nearest", cmap="viridis")
        ii, jj = np.nonzero(~np.isfinite(grid))
        ax.plot(v2[jj], v1[ii], "x", color="crimson", ms=7, label="infeasible")
        fig.colorbar(mesh, ax=ax, label="steady-state tr Φ (mean over nodes)")
        ax.set_xlabel(n2)
        ax.set_ylabel(n1)
        if ii.size:
            ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"{scenario}: feasibility of the {mode} consensus design at the operating point", fontsize=10)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    atomic_write(path, lambda fh: fh.write(buf.getvalue()))
