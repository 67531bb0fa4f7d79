"""Undirected sensor networks with per-edge attack probabilities."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np

from .validation import InputError, check_int, check_probability, check_type

__all__ = ["SensorNetwork"]


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
        if not isinstance(n, (int, np.integer)) or n < 1:
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
        if self.require_connected and not self.is_connected:
            raise InputError(
                f"the sensor network is disconnected ({self.n_components} components): a node cut off from the "
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
        """Build from undirected edges ``(i, j)`` (each listed once, in either order)."""
        n_nodes = check_int("n_nodes", n_nodes, 1)
        adj = np.zeros((n_nodes, n_nodes), dtype=int)
        for e in check_type("edges", edges, (list, tuple), "a list of node pairs (i, j)"):
            if len(e) != 2:
                raise InputError(f"edges must be pairs (i, j), got {tuple(e)!r}")
            i, j = int(e[0]), int(e[1])
            if not (0 <= i < n_nodes and 0 <= j < n_nodes):
                raise InputError(f"edge ({i}, {j}) names a node outside 0..{n_nodes - 1}")
            if i == j:
                raise InputError(f"edge ({i}, {j}) is a self-loop; self-loops are not allowed")
            adj[i, j] = adj[j, i] = 1
        return cls(n_nodes, adj, **kwargs)

    @property
    def edges(self) -> list[tuple[int, int]]:
        return [(int(i), int(j)) for i, j in np.argwhere(np.triu(self.adjacency))]

    @property
    def degrees(self) -> np.ndarray:
        """Degree ``d_i`` of every node."""
        return self.adjacency.sum(axis=1).astype(int)

    @property
    def d_max(self) -> int:
        return int(self.degrees.max())

    @property
    def n_components(self) -> int:
        seen = np.zeros(self.n_nodes, dtype=bool)
        count = 0
        for start in range(self.n_nodes):
            if seen[start]:
                continue
            count += 1
            stack = [start]
            seen[start] = True
            while stack:
                for j in self.neighbours[stack.pop()]:
                    if not seen[j]:
                        seen[j] = True
                        stack.append(j)
        return count

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
