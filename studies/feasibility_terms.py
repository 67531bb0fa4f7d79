"""The feasibility map's words: the home of what its computation (:mod:`studies.feasibility_map`), its files
(:mod:`studies.outputs`), its figure (:func:`studies.figures.map_figure`) and its report
(:mod:`studies.reports.feasibility`) all name: the grid parameters, the columns of ``feasibility.csv``, the mark of a
point that failed, and the categories of a point with their colours and words.
"""
from __future__ import annotations

from designer.verdict import VERDICTS

__all__ = ["GRID_PARAMETERS", "OUTPUTS", "FAILED", "MAP_CATEGORIES", "MAP_COLOURS", "MAP_WORDS", "map_category"]

#: The parameters a grid may vary, with what each is.
GRID_PARAMETERS = {
    "dos": "DoS probability on every channel, in [0, 1)",
    "fdi": "FDI probability on every channel, in [0, 1)",
    "delta": "bound on the injected signal, >= 0",
    "amplitude": "amplitude of the injected signal per attacked component, >= 0",
    "tau": "consensus gain C = tau Phi_pred (paper mode), >= 0",
    "sigma": "sigma of (26) (paper mode), >= 0",
    "beta": "beta of (27) (paper mode), >= 0",
    "epsilon": "epsilon in (0, 1/d_max)",
    "u_scale": "U = u I, >= 0",
    "v_scale": "V_i = v I at every sensor, >= 0",
}
#: The columns of ``feasibility.csv`` after the grid's parameters: what each point is mapped to (``rule``: the design
#: mapped there, the rule or, in an automatic map, the point's pick; ``better_than_local``: 1 where its bound is below
#: the nodes' local EKFs).
OUTPUTS = ("feasible", "trace_bound", "binding", "theorem2", "iterations", "verdict", "rule", "better_than_local")
FAILED = "failed: "  # the start of the binding of a point whose design or iteration raised

#: The map's categories of a grid point, each drawn apart (:func:`studies.figures.map_figure`): the verdicts of
#: :data:`designer.verdict.VERDICTS` in the order a reader asks for them, ``certified`` split by the separate claim
#: ``bounded`` (a point is bounded where its iteration reached a fixed point: ``feasible``): ``certified`` is
#: certified and bounded, ``not bounded`` certified without a fixed point; and their colours.
MAP_CATEGORIES = ("certified", "not bounded", "vacuous", "infeasible", "not computed")
MAP_COLOURS = {"certified": "#1a9850", "not bounded": "#fdae61", "vacuous": "#8073ac", "infeasible": "#d73027",
               "not computed": "#bababa"}
MAP_WORDS = {"certified": "certified (finite, informative and bounded: a fixed point)",
             "not bounded": "not bounded (certified below the open loop, no fixed point)",
             "vacuous": "vacuous (at or above the open loop, unbounded, or no bound)",
             "infeasible": "infeasible ((28)/(29) fail, diverged or no design)",
             "not computed": "not computed (the rule did not compute the stationary certificate)"}


def map_category(row) -> str | None:
    """The category of a grid point's row (:data:`MAP_CATEGORIES`): its ``verdict``, ``certified`` split by whether
    the point is bounded (``feasible``: a fixed point); an earlier version's ``not steady`` (below the open loop, no
    fixed point) is ``not bounded``; a row without a verdict of :data:`designer.verdict.VERDICTS` (a map written
    before the verdicts) is ``infeasible`` when not feasible, else ``None`` (not judged)."""
    v = row.get("verdict")
    if v == "certified" and not row.get("feasible") or v == "not steady":
        return "not bounded"
    if v in VERDICTS:
        return v
    return None if row.get("feasible") else "infeasible"
