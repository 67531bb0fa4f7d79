"""Undirected sensor networks with per-edge attack probabilities."""
from __future__ import annotations

import contextlib
import contextvars
from dataclasses import dataclass, field
from typing import Iterable, Iterator, Sequence

import numpy as np

from .validation import InputError, check_int, check_probability

__all__ = ["SensorNetwork", "connectivity_checked_later", "node_pair"]

_CONNECTIVITY_LATER = contextvars.ContextVar("cfdesign_connectivity_later", default=False)


@contextlib.contextmanager
def connectivity_checked_later() -> Iterator[None]:
    """Networks built in the block are not refused for being disconnected (yet).

    While a model file loads, its ``NETWORK`` cannot be compared with the sensors of its
    ``model()``: a network with a node more than there are sensors would be called
    disconnected (the extra node has no edge) instead of the wrong size.  Built in this block,
    a disconnected network that requires connection is refused when it is used with its
    attacks (:meth:`SensorNetwork.with_attacks`, after the scenario has compared the sizes).
    """
    token = _CONNECTIVITY_LATER.set(True)
    try:
        yield
    finally:
        _CONNECTIVITY_LATER.reset(token)


def node_pair(what: str, pair, n_nodes: int) -> tuple[int, int]:
    """``pair`` as two distinct node indices in ``0..n_nodes-1``; ``what`` names it in the error.

    Indices must be integers (not bools, not floats such as 1.7 that would be truncated).
    """
    try:
        items = tuple(pair)
    except TypeError:
        raise InputError(f"{what} must be a pair of node indices (i, j), got {pair!r}") from None
    if len(items) != 2:
        raise InputError(f"{what} must be a pair of node indices (i, j), got {pair!r}")
    for v in items:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
            raise InputError(f"{what} {pair!r}: node indices must be integers in 0..{n_nodes - 1}, got {v!r} "
                             f"({type(v).__name__})")
        if not 0 <= v < n_nodes:
            raise InputError(f"{what} {pair!r} names a node outside 0..{n_nodes - 1}")
    i, j = int(items[0]), int(items[1])
    if i == j:
        raise InputError(f"{what} {pair!r} is a self-loop; self-loops are not allowed")
    return i, j


@dataclass(frozen=True, eq=False)
class SensorNetwork:
    """An undirected graph on ``n_nodes`` sensors.

    Parameters
    ----------
    n_nodes : int
        Number of nodes (sensors), labelled ``0 .. n_nodes - 1``.
    adjacency : array_like, shape (n_nodes, n_nodes)
        Symmetric 0/1 matrix with zero diagonal.  Use :meth:`from_edges` to
        build one from an edge list.
    dos_prob, fdi_prob : float or array_like, shape (n_nodes, n_nodes)
        Probability of a denial-of-service / false-data-injection attack on the
        channel j -> i (entry ``[i, j]``); scalars apply to every edge.  Entries
        off the edges are ignored and stored as 0.  DoS and FDI never occur
        together on one channel, so ``dos + fdi <= 1`` is required.
    require_connected : bool
        Reject a disconnected graph (default).  With ``False`` it is accepted
        and flagged by :attr:`is_connected`.
    """

    n_nodes: int
    adjacency: np.ndarray
    dos_prob: np.ndarray | float = 0.0
    fdi_prob: np.ndarray | float = 0.0
    require_connected: bool = True
    neighbours: tuple[tuple[int, ...], ...] = field(init=False)

    def __post_init__(self):
        n = self.n_nodes
        if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) or n < 1:
            raise InputError(f"n_nodes must be a positive integer, got {n!r}")
        adj = np.asarray(self.adjacency)
        if adj.shape != (n, n):
            raise InputError(f"adjacency must have shape ({n}, {n}), got {adj.shape}")
        if not np.all((adj == 0) | (adj == 1)):
            raise InputError("adjacency must contain only 0 and 1")
        adj = adj.astype(bool)
        loops = np.flatnonzero(np.diag(adj))
        if loops.size:
            raise InputError(f"adjacency has a self-loop at node {int(loops[0])}; self-loops are not allowed")
        asym = np.argwhere(adj != adj.T)
        if asym.size:
            i, j = (int(v) for v in asym[0])
            raise InputError(f"adjacency must be symmetric (undirected graph): edge {i}-{j} is present in one direction only")
        dos = self._edge_probs("dos_prob", self.dos_prob, adj)
        fdi = self._edge_probs("fdi_prob", self.fdi_prob, adj)
        if np.any(dos + fdi > 1.0 + 1e-12):
            raise InputError("dos_prob + fdi_prob must be <= 1 on every edge (DoS and FDI never occur together)")
        object.__setattr__(self, "n_nodes", int(n))
        object.__setattr__(self, "adjacency", adj)
        object.__setattr__(self, "dos_prob", dos)
        object.__setattr__(self, "fdi_prob", fdi)
        object.__setattr__(self, "neighbours", tuple(tuple(int(j) for j in np.flatnonzero(row)) for row in adj))
        if self.require_connected and not _CONNECTIVITY_LATER.get():
            self.check_connected()

    def check_connected(self) -> None:
        """Refuse a disconnected network that requires connection, naming the nodes cut off."""
        if not self.require_connected or self.is_connected:
            return
        parts = sorted(self.components, key=len, reverse=True)
        cut = sorted(v for p in parts[1:] for v in p)
        listed = ", ".join(map(str, cut[:10])) + (", ..." if len(cut) > 10 else "")
        raise InputError(
            f"the sensor network of {self.n_nodes} nodes is disconnected ({len(parts)} components; node"
            f"{'s' if len(cut) > 1 else ''} {listed} cut off from node {parts[0][0]}): a node cut off from the "
            "others cannot reach consensus with them; connect them (in a model file: add edges to NETWORK), or "
            "build it with SensorNetwork(..., require_connected=False) in Python to study it anyway"
        )

    @staticmethod
    def _edge_probs(name: str, value, adj: np.ndarray) -> np.ndarray:
        p = check_probability(name, value)
        n = adj.shape[0]
        if p.ndim == 0:
            p = np.full((n, n), float(p))
        elif p.shape != (n, n):
            raise InputError(f"{name} must be a scalar or have shape ({n}, {n}), got {p.shape}")
        return np.where(adj, p, 0.0)

    @classmethod
    def from_edges(cls, n_nodes: int, edges: Iterable[Sequence[int]], **kwargs) -> "SensorNetwork":
        """Build from undirected edges ``(i, j)`` of integer node indices (in either order; one listed twice counts
        once)."""
        n_nodes = check_int("n_nodes", n_nodes, 1)
        try:
            edges = list(edges)
        except TypeError:
            raise InputError(f"edges must be a list of node pairs (i, j), got {type(edges).__name__}") from None
        adj = np.zeros((n_nodes, n_nodes), dtype=int)
        for e in edges:  # an edge listed twice (in either order) is the same edge
            i, j = node_pair("edge", e, n_nodes)
            adj[i, j] = adj[j, i] = 1
        return cls(n_nodes, adj, **kwargs)

    @property
    def edges(self) -> list[tuple[int, int]]:
        return [(int(i), int(j)) for i, j in np.argwhere(np.triu(self.adjacency))]

    def messages_per_step(self, rounds: int = 1) -> int:
        """Packets sent per step: one per directed channel and exchange round, ``2 |E| rounds`` (a packet lost to
        DoS counts: it was sent)."""
        return int(np.asarray(self.adjacency).sum()) * int(rounds)

    @property
    def falsified_prob(self) -> np.ndarray:
        """``q_ij`` (N, N): the probability that a packet node ``i`` receives from ``j`` is falsified (DoS and FDI
        are exclusive, so ``fdi_prob / (1 - dos_prob)``; 0 off the edges)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.adjacency, self.fdi_prob / (1.0 - self.dos_prob), 0.0)

    @property
    def degrees(self) -> np.ndarray:
        """Degree ``d_i`` of every node."""
        return self.adjacency.sum(axis=1).astype(int)

    @property
    def d_max(self) -> int:
        return int(self.degrees.max())

    @property
    def n_components(self) -> int:
        return len(self.components)

    @property
    def components(self) -> list[list[int]]:
        """The connected components, each a sorted list of nodes, in the order of their smallest node."""
        label = np.full(self.n_nodes, -1)
        parts = []
        for start in range(self.n_nodes):
            if label[start] >= 0:
                continue
            label[start] = len(parts)
            stack, part = [start], [start]
            while stack:
                for j in self.neighbours[stack.pop()]:
                    if label[j] < 0:
                        label[j] = len(parts)
                        stack.append(j)
                        part.append(j)
            parts.append(sorted(part))
        return parts

    @property
    def is_connected(self) -> bool:
        return self.n_components == 1

    def with_attacks(self, dos_prob=None, fdi_prob=None) -> "SensorNetwork":
        """The same graph with other attack probabilities."""
        return SensorNetwork(
            self.n_nodes,
            self.adjacency.astype(int),
            self.dos_prob if dos_prob is None else dos_prob,
            self.fdi_prob if fdi_prob is None else fdi_prob,
            self.require_connected,
        )

    def describe(self) -> dict:
        return {
            "n_nodes": self.n_nodes,
            "edges": self.edges,
            "degrees": self.degrees.tolist(),
            "d_max": self.d_max,
            "connected": self.is_connected,
        }
