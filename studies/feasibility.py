"""``cfdesign feasibility``: parameter-feasibility maps of the consensus-filter bounds.

At every grid point the steady-state bound recursion at the scenario's operating
point (its initial state ``x0`` and first input) is iterated to a fixed point
(:func:`designer.feasibility.steady_state`); ``feasibility.csv`` gets one row per
point (the grid parameters, ``feasible``, ``trace_bound``, ``binding``,
``theorem2``, ``iterations``) and a heat map is drawn for one or two grid
parameters.  The grid points go through the Monte Carlo runner
(:mod:`studies.runner`; a point plays the part of a run, chunks of ``CHUNK_SIZE``
points): in this process, on ``--workers N`` local processes or on a Dask cluster
(``--dask ADDRESS``), stored under ``out/.chunks`` so that an interrupted map resumes.
"""
from __future__ import annotations

import csv
import functools
import io
import itertools
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from designer.feasibility import steady_state
from designer.fileio import atomic_write
from designer.validation import InputError

from .design import consensus_design
from .runner import Backend, make_backend, monte_carlo
from .scenarios import load_scenario

__all__ = ["GRID_PARAMETERS", "parse_grid", "feasibility_map", "CHUNK_SIZE"]

CHUNK_SIZE = 8  # grid points per chunk (the unit of resumption and of work sent to a worker)

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


def _point(point: dict, F, H, Q, R, network, design, phi0) -> dict:
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


_OUTPUTS = ("feasible", "trace_bound", "binding", "theorem2", "iterations")


def _points(run_ids, seeds, *, points, F, H, Q, R, network, design, phi0) -> dict:
    """Runner task: the grid points ``run_ids`` (deterministic: the seeds are not used)."""
    rows = [_point(points[int(i)], F, H, Q, R, network, design, phi0) for i in run_ids]
    return {k: np.array([r[k] for r in rows]) for k in _OUTPUTS}


def feasibility_map(
    scenario: str,
    grids: Sequence[str],
    *,
    out: str | Path | None = None,
    mode: str = "tuned",
    workers: int | None = None,
    quiet: bool = False,
    overrides: Mapping[str, Any] | None = None,
    assignments=(),
    design_options: Mapping[str, Any] | None = None,
    dask: str | None = None,
    backend: Backend | None = None,
    force: bool = False,
) -> list[dict]:
    """Compute the feasibility map over the grids (``NAME=START:STOP:COUNT`` strings).

    ``workers`` (local processes) or ``dask`` (a scheduler address), or an explicit
    ``backend``, choose where the chunks of grid points are computed (the map does not
    depend on it); with ``out`` the finished chunks are kept under ``out/.chunks`` and a
    second call resumes from them (``force`` recomputes).
    """
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
    if backend is None:
        backend = make_backend(workers, dask)
    elif workers is not None or dask is not None:
        raise InputError("give either backend or workers/dask, not both")
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
    task = functools.partial(_points, points=points, F=F, H=H, Q=m.process_cov, R=R, network=sc.network,
                             design=design, phi0=m.prior.cov)
    config = {"study": "feasibility", "scenario": sc.name, "grids": [[n, v.tolist()] for n, v in parsed],
              "mode": mode, "design_options": dict(design_options or {}),
              "params": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in sc.params.items()}}
    mc = monte_carlo(task, runs=len(points), seed=0, chunk_size=CHUNK_SIZE, backend=backend, store=out,
                     label="feasibility", config=config, force=force, quiet=quiet)
    a = mc.arrays
    rows = [{**p, "feasible": int(a["feasible"][i]), "trace_bound": float(a["trace_bound"][i]),
             "binding": str(a["binding"][i]), "theorem2": int(a["theorem2"][i]),
             "iterations": int(a["iterations"][i])} for i, p in enumerate(points)]
    if out is not None:
        out = Path(out)
        _write_csv(out / "feasibility.csv", rows, names)
        if len(names) <= 2:
            _figure(out / "feasibility.png", rows, parsed, sc.name, mode)
    return rows


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
