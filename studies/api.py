"""The public functions behind every command of the ``cfdesign`` command line.

Design scripts call these directly; the CLI is a thin layer over them.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from designer.simulate import Trajectory
from designer.validation import InputError, check_int

from designer.fileio import write_npz
from .scenarios import SCENARIOS, load_scenario

__all__ = ["list_scenarios", "simulate_scenario", "report"]


def list_scenarios() -> list[dict]:
    """Describe every built-in scenario: name, dimensions, source paper, parameters and assumptions."""
    return [spec.describe() for spec in SCENARIOS.values()]


def simulate_scenario(
    scenario: str,
    *,
    steps: int | None = None,
    seed: int = 0,
    out: str | Path | None = None,
    overrides: Mapping[str, Any] | None = None,
    assignments=(),
) -> Trajectory:
    """Simulate a scenario and optionally write ``out`` (``.npz``).

    The file holds ``x`` (K+1, n_x) true states, ``y`` (K, n_sensors, max n_z)
    measurements per sensor (NaN-padded when sensor dimensions differ; ``y[k]``
    measures ``x[k+1]``), ``z`` (K, n_z) stacked, ``inputs``, ``modes`` when the
    model switches, and metadata (scenario, seed, parameters as JSON).
    """
    seed = check_int("seed", seed, 0)
    sc = load_scenario(scenario, overrides, assignments)
    if steps is not None:
        steps = check_int("steps", steps, 1)
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    traj = sc.simulate(rng, steps)
    if out is not None:
        out = Path(out)
        if out.suffix != ".npz":
            raise InputError(f"out must be a .npz file, got {str(out)!r}")
        arrays = dict(
            x=traj.x,
            y=traj.per_sensor(sc.model),
            z=traj.z,
            inputs=traj.inputs,
            sensor_names=np.array([s.name for s in sc.model.sensors]),
            state_names=np.array(sc.model.state_names),
            scenario=np.array(sc.name),
            seed=np.array(seed),
            params=np.array(json.dumps(sc.params)),
        )
        if traj.modes is not None:
            arrays["modes"] = traj.modes
        write_npz(out, **arrays)
    return traj


def report(directory: str | Path) -> tuple[Path, Path]:
    """Write ``report.html`` (self-contained) and ``report.md`` for the study results in ``directory``.

    ``cfdesign study`` writes them already; this rebuilds them, e.g. after editing a study's
    output or for results from an older version.  See :func:`studies.report.write_report`.
    """
    from .report import write_report

    return write_report(directory)
