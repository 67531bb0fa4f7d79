"""Measurement relay over L hops: the routes a measurement travels and the statistics of its arrival.

A node alone, or with its neighbours' measurements, sees a small part of a large network: on a 512-node grid
one exchange per step spreads information one hop per step across a graph 31 hops wide.  With **relay**, every
sensor's measurement travels L hops per step: in exchange round r (1..L) every node forwards, in its one packet
per channel, the measurements it received in round r - 1 (its own in round 1), so that after L rounds node i holds
the step's measurements of every sensor within L hops, and fuses them in one update.

**Routes.**  Each measurement travels along one tree, its source's: the breadth-first tree of the network from
node ``s`` in which node ``i`` at distance ``d`` receives ``s``'s measurement from the lowest-numbered neighbour at
distance ``d - 1`` (:func:`relay_routes`).  A route is therefore a shortest path, the route of ``s`` to ``i`` passes
through the route of ``s`` to every node before ``i`` on it (a node forwards what it received itself, once), and a
node receives each measurement of its L-hop ball at most once per step.  A copy arriving over another path is not
used: the routes are fixed by the network, so the probability that a measurement arrives is a product over the
channels of its route, and two measurements whose routes share channels arrive together more often than
independent ones (:meth:`Routes.arrival_moments`).

**Attacks.**  As for every exchange in cfdesign, the channels' draws hold for all the rounds of a step: a channel
lost to DoS loses everything it carries in the step (the measurements whose routes cross it do not arrive); a
falsified channel displaces every measurement it carries as if the state were displaced by its ``ξ``:
``z̃_s = z_s + H_s(x̂⁻_j) ξ`` with ``j`` the forwarding node, each falsified channel of a route adding its own.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import shortest_path

from .network import SensorNetwork
from .validation import InputError, check_int

__all__ = ["Routes", "relay_routes", "MAX_HOPS", "NodeMoments", "node_moments", "relay_update"]

MAX_HOPS = 64  # the most relay hops (exchange rounds) per step a design takes, as designer.design.MAX_ROUNDS


class Routes(NamedTuple):
    """The routes of every measurement over at most ``hops`` channels, as pairs (source ``s``, receiving node ``i``).

    Pair ``p`` is node ``node[p]`` receiving sensor ``source[p]``'s measurement after ``depth[p]`` hops (1..hops),
    from node ``sender[p]`` over channel ``channel[p]`` (the index of ``sender -> node`` among the network's
    directed channels in ``np.nonzero(adjacency)`` order, as :class:`filters.consensus_batch.EdgeAttacks`); the
    sender received it as pair ``parent[p]`` (-1 when the sender is the source).  Pairs are sorted by depth, then
    node, then source, so that a pass in order meets every pair after its parent.  ``incidence`` (pairs x
    channels, sparse 0/1) marks the channels of each pair's route.
    """

    hops: int
    n_nodes: int
    source: np.ndarray
    node: np.ndarray
    depth: np.ndarray
    sender: np.ndarray
    channel: np.ndarray
    parent: np.ndarray
    incidence: sp.csr_matrix

    @property
    def n_pairs(self) -> int:
        return int(self.source.size)

    def ball(self, i: int) -> np.ndarray:
        """The sensors whose measurements node ``i`` fuses: its own first, then its pairs' sources in pair order."""
        return np.concatenate([[i], self.source[self.node == i]]).astype(int)

    def ball_sizes(self) -> np.ndarray:
        """(N,) the number of sensors each node fuses (its own included)."""
        return 1 + np.bincount(self.node, minlength=self.n_nodes)

    def arrival_prob(self, network: SensorNetwork) -> np.ndarray:
        """(pairs,) the probability that the pair's measurement arrives: no channel of its route lost to DoS."""
        return np.exp(self.incidence @ _log_up(network))

    def messages_per_step(self, network: SensorNetwork) -> int:
        """Packets per step: one per directed channel and round, ``2 |E| hops`` (as for the exchange rounds)."""
        return network.messages_per_step(self.hops)

    def values_per_step(self) -> int:
        """Measurements forwarded per step over all channels (a packet carries those of its round): one per pair."""
        return self.n_pairs

    def arrival_moments(self, network: SensorNetwork, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                        np.ndarray]:
        """Node ``i``'s second moments over its ball (:meth:`ball` order, its own measurement first, which always
        arrives and is never falsified): ``(p, A, F1, F2)``, with ``γ_a`` the arrival of measurement ``a`` and
        ``φ_ℓ`` channel ``ℓ``'s falsification given that it delivered (probability ``q_ℓ``,
        :attr:`SensorNetwork.falsified_prob`):

        * ``p`` (m,): ``E[γ_a]``;
        * ``A`` (m, m): ``E[γ_a γ_b]``, the product of ``1 - dos`` over the union of the two routes;
        * ``F1`` (m, m): ``E[γ_a γ_b Σ_{ℓ ∈ a ∩ b} φ_ℓ]`` (the weight of ``M = E[ξ ξᵀ]`` between the two
          measurements' injections);
        * ``F2`` (m, m): ``E[γ_a γ_b Σ_{ℓ ∈ a, k ∈ b, ℓ ≠ k} φ_ℓ φ_k]`` (the weight of ``μ μᵀ``).
        """
        rows = np.flatnonzero(self.node == i)
        B = self.incidence[rows]
        logup = _log_up(network)
        q = _channel_values(network, network.falsified_prob)
        own = np.zeros(1)
        s_up = np.concatenate([own, B @ logup])
        shared_up = np.zeros((rows.size + 1,) * 2)
        shared_up[1:, 1:] = (B.multiply(logup) @ B.T).toarray()
        A = np.exp(s_up[:, None] + s_up[None, :] - shared_up)
        sq = np.concatenate([own, B @ q])
        F1 = np.zeros_like(A)
        F1[1:, 1:] = (B.multiply(q) @ B.T).toarray()
        F2 = np.zeros_like(A)
        F2[1:, 1:] = (B.multiply(q * q) @ B.T).toarray()
        F2 = A * (sq[:, None] * sq[None, :] - F2)
        return np.exp(s_up), A, A * F1, F2


def _channel_values(network: SensorNetwork, matrix: np.ndarray) -> np.ndarray:
    """A per-channel quantity ``matrix[receiver, sender]`` (N x N) in channel order."""
    receiver, sender = np.nonzero(network.adjacency)
    return np.asarray(matrix, float)[receiver, sender]


def _log_up(network: SensorNetwork) -> np.ndarray:
    """(channels,) ``log(1 - dos)`` of every channel: the log-probability that it delivers."""
    with np.errstate(divide="ignore"):
        return np.log1p(-_channel_values(network, network.dos_prob))


def relay_routes(network: SensorNetwork, hops: int) -> Routes:
    """The routes of every sensor's measurement over at most ``hops`` channels (``1 <= hops <= MAX_HOPS``)."""
    if not isinstance(network, SensorNetwork):
        raise InputError(f"network must be a designer.SensorNetwork, got {type(network).__name__}")
    hops = check_int("hops", hops, 1, MAX_HOPS)
    N = network.n_nodes
    adj = network.adjacency
    dist = shortest_path(sp.csr_matrix(adj.astype(float)), unweighted=True)  # dist[s, i]
    channel_of = np.full((N, N), -1)
    receiver, sender = np.nonzero(adj)
    channel_of[receiver, sender] = np.arange(receiver.size)
    pair_of = {}
    src, nod, dep, snd, chan, par = [], [], [], [], [], []
    for d in range(1, hops + 1):
        s_idx, i_idx = np.nonzero(dist == d)
        order = np.lexsort((s_idx, i_idx))
        for s, i in zip(s_idx[order], i_idx[order]):
            nb = np.flatnonzero(adj[i] & (dist[s] == d - 1))
            j = int(nb[0])  # the lowest-numbered neighbour one hop nearer the source
            pair_of[(int(s), int(i))] = len(src)
            src.append(int(s)), nod.append(int(i)), dep.append(d), snd.append(j), chan.append(channel_of[i, j])
            par.append(-1 if j == s else pair_of[(int(s), j)])
    P = len(src)
    parent = np.array(par, dtype=int)
    channel = np.array(chan, dtype=int)
    # each pair's route: its own channel and its parent's route (parents come first)
    rows, cols = [], []
    routes: list[np.ndarray] = []
    for p in range(P):
        r = np.array([channel[p]]) if parent[p] < 0 else np.append(routes[parent[p]], channel[p])
        routes.append(r)
        rows.append(np.full(r.size, p)), cols.append(r)
    E = receiver.size
    inc = sp.csr_matrix((np.ones(sum(r.size for r in routes)), (np.concatenate(rows) if rows else [],
                                                                 np.concatenate(cols) if cols else [])),
                        shape=(P, E))
    return Routes(hops, N, np.array(src, dtype=int), np.array(nod, dtype=int), np.array(dep, dtype=int),
                  np.array(snd, dtype=int), channel, parent, inc)


class NodeMoments(NamedTuple):
    """One node's arrival and falsification moments over its ball (:meth:`Routes.arrival_moments`), expanded to the
    rows of the stacked measurement (a sensor of dimension m contributes m rows): ``p`` (r,), ``A``, ``F1``, ``F2``
    (r, r) and ``sensors`` (its ball, own first), ``rows`` (r,) the sensor of each row."""

    sensors: np.ndarray
    rows: np.ndarray
    p: np.ndarray
    A: np.ndarray
    F1: np.ndarray
    F2: np.ndarray


def node_moments(routes: Routes, network: SensorNetwork, dims, i: int) -> NodeMoments:
    """Node ``i``'s :class:`NodeMoments`; ``dims`` (n_sensors,) each sensor's measurement dimension."""
    ball = routes.ball(i)
    p, A, F1, F2 = routes.arrival_moments(network, i)
    owner = np.repeat(np.arange(ball.size), np.asarray(dims, int)[ball])
    ix = np.ix_(owner, owner)
    return NodeMoments(ball, ball[owner], p[owner], A[ix], F1[ix], F2[ix])


def relay_update(P_pred: np.ndarray, Hw: np.ndarray, mom: NodeMoments, M: np.ndarray, mu: np.ndarray,
                 rtol: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """The relay rule's gain and expected posterior covariance at one node, over a batch: ``(W, P_post)``.

    ``P_pred`` (..., n, n) the node's predicted covariance; ``Hw`` (..., r, n) the whitened Jacobian rows
    ``R_a^{-1/2} H_a`` of its ball's measurements (``mom.rows`` order) at its prediction; ``M``, ``mu`` the
    falsification's second moment and mean (:class:`designer.attacks.FDISignal`).  The node updates with
    ``x̂⁺ = x̂⁻ + W Σ_{a arrived} H_aᵀ R_a⁻¹ (z̃_a - h_a(x̂⁻))``: one gain ``W`` for whichever measurements arrive,
    chosen to minimise ``tr E[e⁺ e⁺ᵀ]`` over the arrivals, the falsifications and the noises (the linearised error
    ``e⁺ = (I - W Σ_a γ_a J_a) e⁻ - W Σ_a γ_a H_aᵀ R_a⁻¹ (v_a + η_a)``, ``J_a = H_aᵀ R_a⁻¹ H_a``, the draws
    independent of ``e⁻``)::

        S = Σ_a p_a J_a,   Q = Σ_ab A_ab J_a P⁻ J_b + S + Σ_ab (F1_ab J_a M J_b + F2_ab J_a μμᵀ J_b)
        W = P⁻ S Q⁺,       P⁺ = P⁻ - W S P⁻

    (``Q⁺`` the pseudo-inverse on ``Q``'s range, eigenvalues below ``rtol`` times the largest dropped: directions no
    measurement of the ball sees).  With every measurement arriving and none falsified, ``W = (P⁻⁻¹ + S)⁻¹`` and
    this is the Kalman filter of the ball's measurements.  For a linear model ``P⁺`` is the expected covariance of
    the node's error over the attacks; a node computes it itself (its own estimate's Jacobians, its design's
    moments)."""
    Ht = np.swapaxes(Hw, -1, -2)
    S = Ht @ (mom.p[:, None] * Hw)
    Q = S + Ht @ ((mom.A * (Hw @ P_pred @ Ht)) @ Hw)
    if np.any(mom.F1):
        Q = Q + Ht @ ((mom.F1 * (Hw @ M @ Ht)) @ Hw)
    if np.any(mu) and np.any(mom.F2):
        h = Hw @ mu
        Q = Q + Ht @ ((mom.F2 * (h[..., :, None] * h[..., None, :])) @ Hw)
    Q = 0.5 * (Q + np.swapaxes(Q, -1, -2))
    lam, V = np.linalg.eigh(Q)
    keep = lam > rtol * lam[..., -1:]
    inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    Qp = (V * inv[..., None, :]) @ np.swapaxes(V, -1, -2)
    W = P_pred @ S @ Qp
    P = P_pred - W @ S @ P_pred
    return W, 0.5 * (P + np.swapaxes(P, -1, -2))
