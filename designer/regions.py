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
region against the centralized steady state on the same states.

**Carrying the region** (:func:`carried_states`).  A node of a rule that fuses its ball's measurements without
consensus on estimates (one that relays, :attr:`designer.rule.GainRule.regional`) may carry only the states that its
region and its ball's measurements need: the closure of its region and of its ball's sensors' structural supports under
the dynamics' structural dependence (a carried state's next value may depend only on carried states).  Its filter on
them is then exactly its whole-state filter restricted to them: with ``F`` and every ``H`` of its ball zero outside the
carried block, the block's prediction and update never read the rest.  Where the dynamics couple every state (a heat
field), the closure is the whole state and nothing is saved; boundary states taken from the neighbours (Khan and Moura's
overlapping subsystems) are not built.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .validation import InputError

__all__ = ["SENSED", "sensed_regions", "resolve_regions", "region_mask", "region_traces", "region_error2",
           "describe_regions", "region_detail", "region_sums", "dynamics_support", "carried_states", "carried_index",
           "carried_positions", "carried_region_traces", "Carried"]

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


def dynamics_support(model) -> np.ndarray:
    """(n_x, n_x) booleans: ``dep[j, l]`` whether ``f_j`` depends structurally on state ``l`` (the structural nonzeros
    of CasADi's Jacobian of the dynamics, every mode and input included)."""
    import casadi as ca

    rows, cols = ca.jacobian(model.f_expr, model.x).sparsity().get_triplet()
    dep = np.zeros((model.n_x, model.n_x), dtype=bool)
    dep[np.asarray(rows, dtype=int), np.asarray(cols, dtype=int)] = True
    return dep


def carried_states(model, regions: Sequence[np.ndarray], balls: Sequence[Sequence[int]]) -> tuple[np.ndarray, ...]:
    """The states each node carries (module docstring, "Carrying the region"): per node the smallest set holding its
    region, the structural support of every sensor of its ball (``balls[i]``, the sensors whose measurements it
    fuses) and every state the dynamics of a held state depend on, in increasing order."""
    dep = dynamics_support(model)
    support = sensed_regions(model)
    out = []
    for region, ball in zip(regions, balls):
        held = np.zeros(model.n_x, dtype=bool)
        held[np.asarray(region, dtype=int)] = True
        for s in ball:
            held[support[int(s)]] = True
        while True:  # add what the held states' dynamics read until nothing new is read
            more = held | dep[held].any(axis=0)
            if more.sum() == held.sum():
                break
            held = more
        out.append(np.flatnonzero(held))
    return tuple(out)


def carried_index(carried: Sequence[np.ndarray]) -> np.ndarray:
    """(nodes, m) the carried states of every node in one array, ``m`` the most any node carries, a node's
    unused places ``-1`` (the layout of the arrays of a filter whose nodes carry their regions)."""
    m = max(len(c) for c in carried)
    index = np.full((len(carried), m), -1, dtype=int)
    for i, c in enumerate(carried):
        index[i, :len(c)] = c
    return index


def carried_positions(index: np.ndarray, regions: Sequence[np.ndarray]) -> tuple[np.ndarray, ...]:
    """Each node's region as positions in its carried states (``index``, :func:`carried_index`); an InputError when
    a region is not carried."""
    out = []
    for i, (row, region) in enumerate(zip(index, regions)):
        where = {int(j): p for p, j in enumerate(row) if j >= 0}
        if any(int(j) not in where for j in region):
            raise InputError(f"node {i}'s region is not among the states it carries")
        out.append(np.array([where[int(j)] for j in region], dtype=int))
    return tuple(out)


class Carried:
    """The carried states of every node (:func:`carried_index`'s ``index`` (nodes, m), ``-1`` where a node carries
    fewer than ``m``) and the moves between the whole state's coordinates and each node's own, the first
    ``count[i]`` places of its ``m``: a place a node does not use holds zero (in a vector, and in a matrix's row and
    column), so that traces, products and a rule's update run on the padded arrays unchanged."""

    def __init__(self, index: np.ndarray, n_x: int):
        self.index = np.asarray(index, dtype=int)
        self.n_x = int(n_x)
        self.used = self.index >= 0  # (nodes, m)
        self.safe = np.where(self.used, self.index, 0)  # a place not used reads state 0 (then zeroed)
        self.nodes, self.m = self.index.shape
        self._pairs = self.used[:, :, None] & self.used[:, None, :]

    @classmethod
    def of(cls, carried: Sequence[np.ndarray], n_x: int) -> "Carried":
        return cls(carried_index(carried), n_x)

    @property
    def held(self) -> np.ndarray:
        """(nodes, n_x) booleans: ``held[i, j]`` whether node ``i`` carries state ``j``."""
        return region_mask([row[row >= 0] for row in self.index], self.n_x)

    def vector(self, x: np.ndarray) -> np.ndarray:
        """(..., nodes, m) each node's carried states of ``x`` (..., nodes, n_x), or (nodes, m) of one ``x`` (n_x,)
        shared by the nodes."""
        x = np.asarray(x, dtype=float)
        if x.ndim == 1:
            x = np.broadcast_to(x, (self.nodes, self.n_x))
        return np.where(self.used, np.take_along_axis(x, np.broadcast_to(self.safe, x.shape[:-1] + (self.m,)),
                                                      axis=-1), 0.0)

    def matrix(self, A: np.ndarray) -> np.ndarray:
        """(..., nodes, m, m) each node's carried block of ``A`` (..., nodes, n_x, n_x), or (nodes, m, m) of one
        ``A`` (n_x, n_x) shared by the nodes."""
        A = np.asarray(A, dtype=float)
        if A.ndim == 2:
            out = A[..., self.safe[:, :, None], self.safe[:, None, :]]
        else:
            out = A[..., np.arange(self.nodes)[:, None, None], self.safe[:, :, None], self.safe[:, None, :]]
        return np.where(self._pairs, out, 0.0)

    def columns(self, H: np.ndarray, node_of_row: np.ndarray) -> np.ndarray:
        """(..., T, m) rows ``H`` (..., T, n_x), row ``t`` belonging to node ``node_of_row[t]``, in that node's
        carried coordinates."""
        idx = self.safe[node_of_row]  # (T, m)
        out = np.take_along_axis(H, np.broadcast_to(idx, H.shape[:-1] + (self.m,)), axis=-1)
        return np.where(self.used[node_of_row], out, 0.0)

    def full(self, x: np.ndarray, fill) -> np.ndarray:
        """(..., nodes, n_x) each node's carried values ``x`` (..., nodes, m) in the whole state's coordinates, the
        states it does not carry ``fill`` (a number, or (n_x,) one per state)."""
        x = np.asarray(x, dtype=float)
        out = np.empty(x.shape[:-1] + (self.n_x + 1,))
        out[..., :self.n_x] = fill
        np.put_along_axis(out, np.broadcast_to(np.where(self.used, self.index, self.n_x), x.shape), x, axis=-1)
        return out[..., :self.n_x]


def carried_region_traces(phi: np.ndarray, carried: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(nodes, steps) each node's tr over its region of ``phi`` (nodes, steps, m, m), a design's bounds in the carried
    coordinates ``carried`` (nodes, m) with the regions ``mask`` (nodes, n_x): schedule.npz's ``Phi``, ``carried`` and
    ``region_mask``, as its verdict judges them."""
    pos = carried_positions(carried, [np.flatnonzero(r) for r in mask])
    return region_traces(np.swapaxes(phi, 0, 1), pos).T


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
    return region_sums(np.diagonal(np.asarray(P, dtype=float), axis1=-2, axis2=-1), regions)


def region_sums(d: np.ndarray, regions: Sequence[np.ndarray]) -> np.ndarray:
    """:func:`region_traces` of the covariances' diagonals ``d`` (..., nodes, n)."""
    d = np.asarray(d, dtype=float)
    return np.where(region_mask(regions, d.shape[-1]), d, 0.0).sum(-1)


def region_error2(err: np.ndarray, regions: Sequence[np.ndarray]) -> np.ndarray:
    """Each node's squared error summed over its region: ``err`` (..., nodes, n), a centralized filter's one error as
    (..., 1, n) (broadcast to every node), gives (..., nodes): what the studies average into ``rmse_region``."""
    return np.where(region_mask(regions, err.shape[-1]), err**2, 0.0).sum(-1)


def describe_regions(regions: Sequence[np.ndarray], state_names: Sequence[str]) -> list[list[str]]:
    """The regions by state name, one list per node (what a results file and a report show)."""
    return [[state_names[j] for j in r] for r in regions]


def region_detail(phi_final: np.ndarray, regions: Sequence[np.ndarray], centralized: Sequence[float | None] | None,
                  state_names: Sequence[str], positions: Sequence[np.ndarray] | None = None) -> dict:
    """A design's bound on each node's region (a verdict detail's ``region``): ``phi_final`` (nodes, n, n) the final
    bound per node, ``centralized`` per node the centralized steady-state posterior traced over its region
    (:func:`designer.observability.kalman_references`' ``regions``; None where none exists).  Per node: its region's
    states, the final tr Φ over them, the centralized tr P over the same states and their ratio (None where not
    finite or no reference).  ``positions``: where each region sits in ``phi_final``'s coordinates when the nodes
    carry their regions (:func:`carried_positions`; default the regions themselves, ``phi_final`` in the whole
    state's)."""
    from .verdict import json_number

    final = region_traces(phi_final, regions if positions is None else positions)
    ref = [None] * len(regions) if centralized is None else list(centralized)
    return {"states": describe_regions(regions, state_names),
            "final_trace": [json_number(v) for v in final],
            "centralized": [json_number(v) for v in ref],
            "ratio_centralized": [None if r is None or not r else json_number(f / r) for f, r in zip(final, ref)]}
