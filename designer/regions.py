"""Regions: the states each node is responsible for (issue 41, item 1).

On a field or a grid the state grows with the network, and what a building controller or a grid operator asks of
node i is its own region's states, not the far end of the network that its measurements never see.  A model file
declares ``REGIONS`` (one entry per node: the indices or names of the states that node answers for), or
``REGIONS = "sensed"``: each node's region is the states its own sensor's measurement function depends on (the
structural support of its Jacobian, from CasADi's sparsity: a bus measuring its lines' flows answers for its own
angle and its neighbours').

With regions the studies score each node on its region's states (``rmse_region``: per node the squared error summed
over its region, averaged over the nodes), the centralized filters' single estimate on each node's region alike (the
centralized EKF restricted to the same states is the reference), and a design states each node's final bound on its
region against the centralized steady state on the same states.  Nodes still carry the whole state: a node filter
that carries its region and its neighbours' boundary states only (Khan and Moura's overlapping subsystems) is not
built yet.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .validation import InputError

__all__ = ["SENSED", "sensed_regions", "resolve_regions", "region_mask", "region_traces", "region_error2",
           "describe_regions", "region_detail"]

#: ``REGIONS = "sensed"``: each node's region is the states its own sensor's measurement depends on.
SENSED = "sensed"


def sensed_regions(model) -> tuple[np.ndarray, ...]:
    """Each sensor's structural support in the state: the indices of the states its measurement function ``h_s``
    depends on (the columns of its Jacobian's structural nonzeros), in increasing order."""
    import casadi as ca  # late: a scenario without regions (and a listing of scenarios) builds no CasADi expression

    out = []
    for s in model.sensors:
        jac = ca.jacobian(ca.vec(s.h), model.x)
        _, cols = jac.sparsity().get_triplet()
        out.append(np.unique(np.asarray(cols, dtype=int)))
    return tuple(out)


def resolve_regions(value, model, n_nodes: int, what: str = "REGIONS") -> tuple[np.ndarray, ...]:
    """The regions ``value`` declares (``"sensed"``, or one entry per node: a sequence of state indices ``0..n_x - 1``
    or state names, one index or name, or ``"sensed"`` for that node's sensed states), as one sorted index array per
    node; an InputError naming ``what`` and the allowed values otherwise.
    Every region must hold at least one state (a node whose sensor depends on no state has none to answer for)."""
    n = model.n_x
    if isinstance(value, str):
        if value != SENSED:
            raise InputError(f"{what} must be {SENSED!r} or one list of states per node (state indices 0..{n - 1} "
                             f"or names), got {value!r}")
        regions = sensed_regions(model)
    else:
        try:
            items = list(value)
        except TypeError:
            raise InputError(f"{what} must be {SENSED!r} or one list of states per node (state indices 0..{n - 1} "
                             f"or names), got {type(value).__name__}") from None
        if len(items) != n_nodes:
            raise InputError(f"{what} must have one entry per node ({n_nodes}), got {len(items)}")
        names = {name: j for j, name in enumerate(model.state_names)}
        sensed = sensed_regions(model) if any(isinstance(e, str) and e == SENSED and e not in names
                                              for e in items) else None
        regions = []
        for i, entry in enumerate(items):
            if sensed is not None and isinstance(entry, str) and entry == SENSED:  # this node's sensed states
                entry = sensed[i].tolist()
            if isinstance(entry, (str, int, np.integer)):
                entry = [entry]
            idx = []
            for s in entry:
                if isinstance(s, str) and s in names:
                    idx.append(names[s])
                elif isinstance(s, (int, np.integer)) and not isinstance(s, bool) and 0 <= s < n:
                    idx.append(int(s))
                else:
                    raise InputError(f"{what}[{i}] must hold state indices 0..{n - 1} or state names "
                                     f"({', '.join(model.state_names[:6])}{', ...' if n > 6 else ''}), got {s!r}")
            regions.append(np.unique(np.asarray(idx, dtype=int)))
        regions = tuple(regions)
    for i, r in enumerate(regions):
        if r.size == 0:
            raise InputError(f"{what}[{i}] is empty: every node's region must hold at least one state (a sensed "
                             "region is empty when the node's sensor depends on no state)")
    return regions


def region_mask(regions: Sequence[np.ndarray], n_x: int) -> np.ndarray:
    """(nodes, n_x) booleans: ``mask[i, j]`` whether state ``j`` is in node ``i``'s region."""
    mask = np.zeros((len(regions), n_x), dtype=bool)
    for i, r in enumerate(regions):
        mask[i, r] = True
    return mask


def region_traces(P: np.ndarray, regions: Sequence[np.ndarray]) -> np.ndarray:
    """Each node's covariance traced over its region: ``P`` (..., nodes, n, n), one matrix per node (a centralized
    filter's one matrix as (..., 1, n, n): broadcast to every node), gives (..., nodes)."""
    P = np.asarray(P, dtype=float)
    return np.where(region_mask(regions, P.shape[-1]), np.diagonal(P, axis1=-2, axis2=-1), 0.0).sum(-1)


def region_error2(err: np.ndarray, regions: Sequence[np.ndarray]) -> np.ndarray:
    """Each node's squared error summed over its region: ``err`` (..., nodes, n), a centralized filter's one error as
    (..., 1, n) (broadcast to every node), gives (..., nodes): what the studies average into ``rmse_region``."""
    return np.where(region_mask(regions, err.shape[-1]), err**2, 0.0).sum(-1)


def describe_regions(regions: Sequence[np.ndarray], state_names: Sequence[str]) -> list[list[str]]:
    """The regions by state name, one list per node (what a results file and a report show)."""
    return [[state_names[j] for j in r] for r in regions]


def region_detail(phi_final: np.ndarray, regions: Sequence[np.ndarray], centralized: Sequence[float | None] | None,
                  state_names: Sequence[str]) -> dict:
    """A design's bound on each node's region (a verdict detail's ``region``): ``phi_final`` (nodes, n, n) the final
    bound per node, ``centralized`` per node the centralized steady-state posterior traced over its region
    (:func:`designer.observability.kalman_references`' ``regions``; None where none exists).  Per node: its region's
    states, the final tr Φ over them, the centralized tr P over the same states and their ratio (None where not
    finite or no reference).  A statement beside the verdict, which still judges the whole state."""
    from .verdict import json_number

    final = region_traces(phi_final, regions)
    ref = [None] * len(regions) if centralized is None else list(centralized)
    return {"states": describe_regions(regions, state_names),
            "final_trace": [json_number(v) for v in final],
            "centralized": [json_number(v) for v in ref],
            "ratio_centralized": [None if r is None or not r else json_number(f / r) for f, r in zip(final, ref)]}
