"""Gain schedules of the consensus filter: the files ``schedule.json`` + ``schedule.npz``.

Schema ``cfdesign.schedule/1`` (see ``shared/DESIGN.md``): ``schedule.json`` holds
``schema, scenario, mode, gain_rule, nodes, steps, epsilon, feasible, violations, sigma, beta,
trace_bound`` (nodes x steps; entry k is tr Φ_{k+1|k+1}, ``null`` where Φ is not a
bound), where ``gain_rule`` is the mode's run-time record ``{name, runtime, needs,
deployable}`` (:mod:`designer.rule`; a file written before it existed loads without
it), and ``schedule.npz`` holds ``K`` (nodes, steps, n_x, n_z; with sensors of
different dimensions ``n_z = max n_z_i`` and node i's gain in its first ``n_z_i``
columns, zero beyond), ``C`` (nodes, steps, n_x, n_x), ``Phi`` (nodes, steps + 1,
n_x, n_x; NaN where Φ is not a bound), ``valid`` (nodes, steps + 1), ``sigma`` and
``beta`` (nodes, steps) and the condition margins ``margin28`` and ``margin29``
(nodes, steps; NaN where not checked).  A design whose nodes carry their regions (``--carry region``,
:mod:`designer.regions`) adds ``carried`` (nodes, m), each node's carried states (-1: a place not used), and
``region_mask`` (nodes, n_x), each node's region; ``K``, ``C`` and ``Phi`` are then in the carried coordinates
(``m`` wide, zero at the unused places) and ``trace_bound`` is tr Φ over each node's region, what its verdict judges.
A ``scheduled`` design adds the tables its nodes carry,
``table_<name>`` (:meth:`designer.rule.GainRule.table_arrays`).  The JSON Schema is
``studies/schemas/schedule.schema.json``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .fileio import write_json, write_npz
from .rule import GainRule
from .validation import InputError

__all__ = ["SCHEMA", "GainSchedule", "load_schedule"]

SCHEMA = "cfdesign.schedule/1"


def _finite_or_none(v: float):
    v = float(v)
    return v if np.isfinite(v) else None


@dataclass(frozen=True, eq=False)
class GainSchedule:
    """A designed (or replayable) gain schedule with its bound and feasibility record."""

    scenario: str
    rule: GainRule  # the design's gain rule (what a node needs at run time to apply the schedule)
    epsilon: float
    sigma: np.ndarray  # (nodes, steps)
    beta: np.ndarray  # (nodes, steps)
    K: np.ndarray  # (nodes, steps, n_x, n_z)
    C: np.ndarray  # (nodes, steps, n_x, n_x)
    Phi: np.ndarray  # (nodes, steps + 1, n_x, n_x), NaN where not a bound
    valid: np.ndarray  # (nodes, steps + 1) bool
    violations: list
    meta: dict[str, Any] = field(default_factory=dict)
    margin28: np.ndarray | None = None  # (nodes, steps) 1/λmax(Φ_k|k) - (1+ε)σ, NaN where not checked
    margin29: np.ndarray | None = None  # (nodes, steps) 1/λmax(Φ_k+1|k) - β
    tables: dict[str, np.ndarray] | None = None  # mode 'scheduled': what the nodes carry (schedule.npz's table_*)
    carried: np.ndarray | None = None  # (nodes, m) each node's carried states (-1: unused); None: the whole state
    region_mask: np.ndarray | None = None  # (nodes, n_x) each node's region, beside ``carried``

    @property
    def mode(self) -> str:
        """The gain rule's name (``--mode``)."""
        return self.rule.name

    @property
    def nodes(self) -> int:
        return self.K.shape[0]

    @property
    def steps(self) -> int:
        return self.K.shape[1]

    @property
    def feasible(self) -> bool:
        return not any(v["condition"] in ("(28)", "(29)", "diverged") for v in self.violations)

    def judged_traces(self) -> np.ndarray:
        """(nodes, steps) tr Φ_{k|k}, k = 1..steps, over what a node's verdict judges: its region when the nodes
        carry their regions, else the whole state (NaN where Φ is not a finite number)."""
        with np.errstate(invalid="ignore"):
            if self.carried is None:
                return np.trace(self.Phi[:, 1:], axis1=-2, axis2=-1)
            from .regions import carried_region_traces

            return carried_region_traces(self.Phi[:, 1:], self.carried, self.region_mask)

    def trace_bound(self) -> list[list[float | None]]:
        tr = self.judged_traces()
        return [[_finite_or_none(t) if ok else None for t, ok in zip(row, vrow)]
                for row, vrow in zip(tr, self.valid[:, 1:])]

    def to_json(self) -> dict:
        return {
            "schema": SCHEMA,
            "scenario": self.scenario,
            "mode": self.mode,
            "gain_rule": self.rule.describe(),
            "runtime_information": self.rule.describe(),  # the contract's name for it (shared/DESIGN.md)
            "nodes": self.nodes,
            "steps": self.steps,
            "epsilon": self.epsilon,
            "feasible": self.feasible,
            "violations": [
                {**v, "margin": _finite_or_none(v["margin"]),
                 **({} if np.isfinite(v["margin"]) or "reason" in v
                    else {"note": "matrix not numerically positive definite"})}
                for v in self.violations
            ],
            "sigma": [[_finite_or_none(v) for v in row] for row in self.sigma],  # null: fallback, no σ
            "beta": [[_finite_or_none(v) for v in row] for row in self.beta],
            "trace_bound": self.trace_bound(),
            **self.meta,
        }

    def write(self, out_dir) -> Path:
        """Write ``schedule.json`` and ``schedule.npz`` atomically into ``out_dir``."""
        out_dir = Path(out_dir)
        margins = {} if self.margin28 is None else {"margin28": self.margin28, "margin29": self.margin29}
        tables = {f"table_{k}": v for k, v in (self.tables or {}).items()}
        carried = {} if self.carried is None else {"carried": self.carried, "region_mask": self.region_mask}
        write_npz(out_dir / "schedule.npz", K=self.K, C=self.C, Phi=self.Phi, valid=self.valid,
                  sigma=self.sigma, beta=self.beta, **margins, **tables, **carried)
        write_json(out_dir / "schedule.json", self.to_json())
        return out_dir


def load_schedule(path, rule_of: Callable[[str, str], GainRule]) -> GainSchedule:
    """Load a schedule written by :meth:`GainSchedule.write` (a directory or its ``schedule.json``); ``rule_of(name,
    param)`` resolves its mode to the gain rule (:func:`rules.get`), or raises InputError naming ``param``."""
    path = Path(path)
    if path.is_dir():
        path = path / "schedule.json"
    if not path.is_file():
        raise InputError(f"schedule {str(path)!r} does not exist")
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"schedule {str(path)!r} is not valid JSON: {exc}") from None
    if meta.get("schema") != SCHEMA:
        raise InputError(f"schedule {str(path)!r} has schema {meta.get('schema')!r}, expected {SCHEMA!r}")
    npz_path = path.with_suffix(".npz")
    if not npz_path.is_file():
        raise InputError(f"schedule arrays {str(npz_path)!r} are missing")
    import zipfile

    if not zipfile.is_zipfile(npz_path):  # np.load would take it for a pickle and say so
        raise InputError(f"schedule arrays {str(npz_path)!r} are not an .npz archive (the file is damaged or not "
                         "written by cfdesign design)")
    try:
        with np.load(npz_path, allow_pickle=False) as d:
            missing = [k for k in ("K", "C", "Phi", "valid", "sigma", "beta") if k not in d.files]
            if missing:
                raise InputError(f"schedule arrays {str(npz_path)!r} lack {', '.join(missing)}")
            arrays = {k: d[k] for k in d.files}
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - a damaged or foreign file: one line, exit 2
        raise InputError(f"schedule arrays {str(npz_path)!r} cannot be read: {type(exc).__name__}: {exc}") from None
    rule = rule_of(meta.get("mode"), f"mode of schedule {str(path)!r}")
    record = meta.get("gain_rule")  # absent from a file written before the gain rules declared their run time
    if record is not None and (not isinstance(record, dict) or record.get("name") != rule.name
                               or record.get("runtime") != rule.runtime):
        raise InputError(f"schedule {str(path)!r}: gain_rule {record!r} is not that of mode {rule.name!r} "
                         f"(runtime {rule.runtime!r})")
    known = {"schema", "scenario", "mode", "gain_rule", "runtime_information", "nodes",
             "steps", "epsilon", "feasible", "violations", "sigma",
             "beta", "trace_bound"}
    violations = [{**v, "margin": -np.inf if v["margin"] is None else v["margin"]} for v in meta["violations"]]
    for v in violations:
        v.pop("note", None)
    return GainSchedule(meta["scenario"], rule, float(meta["epsilon"]), arrays["sigma"], arrays["beta"],
                        arrays["K"], arrays["C"], arrays["Phi"], arrays["valid"].astype(bool), violations,
                        {k: v for k, v in meta.items() if k not in known}, arrays.get("margin28"),
                        arrays.get("margin29"), {k[6:]: v for k, v in arrays.items() if k.startswith("table_")} or None,
                        *_carried(arrays, npz_path))


def _carried(arrays: dict, npz_path) -> tuple:
    """``(carried, region_mask)`` of a schedule's arrays (None, None: its nodes carry the whole state), checked."""
    if "carried" not in arrays:
        return None, None
    carried, mask = arrays["carried"], arrays.get("region_mask")
    N, n = arrays["valid"].shape[0], None if mask is None else mask.shape[-1]
    m = arrays["Phi"].shape[-1]
    if (mask is None or carried.shape != (N, m) or mask.shape[0] != N or not np.issubdtype(carried.dtype, np.integer)
            or carried.min() < -1 or carried.max() >= n):
        raise InputError(f"schedule arrays {str(npz_path)!r}: carried must be ({N}, {m}) state indices (-1: unused) "
                         f"beside region_mask (nodes, n_x)")
    return carried, mask.astype(bool)
