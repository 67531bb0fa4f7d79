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

**Flooding** (``routing='flood'``, gain rule ``flood``).  A node forwards, in round r, every measurement it first
received in round r - 1, to all its neighbours, and keeps the first copy of each measurement that reaches it (of
copies arriving in the same round, its lowest-numbered neighbour's): a measurement arrives whenever some path of
the step's surviving channels reaches the node within L hops (:meth:`Routes.realise`), and the copy taken is
falsified by the channels of the path it took.  The packets are the same one per channel and round; they carry
more values.  The probability that some path survives has no closed form (network reliability): the arrival and
falsification moments are estimated by Monte Carlo of the channels (:func:`flood_moments`), once per network from
a fixed seed, and carry that sampling error.

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

from designer.anderson import REACH_WINDOW, Anderson, out_of_reach
from designer.bounds import lower_inverse, sqrtm_psd, symmetrize
from designer.cores import SOLVER_SETTINGS
from designer.network import SensorNetwork
from designer.regions import Carried, carried_positions, carried_states
from designer.stationary import StationaryCertificate
from designer.validation import InputError, check_int

#: Which copy of a relayed measurement a node takes (:class:`Routes`): its shortest-path tree parent's, or the first
#: to arrive from any neighbour (the flood rule's).
ROUTINGS = ("tree", "flood")
#: What a packet of a rule that relays carries (``ConsensusDesign.exchange``): the measurements relayed.
RELAY = "relay"

__all__ = ["RTOL", "FLOAT_RTOL", "Routes", "relay_routes", "ROUTINGS", "RELAY", "MAX_HOPS", "DEFAULT_HOPS_MAX",
           "default_hops", "diameter",
           "relay_payload", "pair_sum", "relay_stationary", "LMI_MAX_ENTRIES", "whitened_rows", "NodeMoments",
           "node_moments", "relay_update", "relay_gain", "RelayGain", "grouped", "relay_carried",
           "update_moments", "relay_information", "flood_moments", "relay_moments", "flood_samples", "node_classes",
           "hop_distances", "moment_bytes",
           "pseudo_inverse"]

MAX_HOPS = 64  # the most relay hops (exchange rounds) per step a design takes, as designer.design.ROUNDS_MAX
#: The default hops of a relay design: the network's diameter (every node then holds every measurement that arrives),
#: at most this many (an assumption, chosen: on a 512-node range grid 31 hops wide, 8 hops bring the nodes' error
#: within about 2 x the centralized filter's on runs without attacks, README; the packets then carry up to a few
#: hundred measurements).
DEFAULT_HOPS_MAX = 8


class Routes(NamedTuple):
    """The routes of every measurement over at most ``hops`` channels, as pairs (source ``s``, receiving node ``i``).

    Pair ``p`` is node ``node[p]`` receiving sensor ``source[p]``'s measurement after ``depth[p]`` hops (1..hops),
    from node ``sender[p]`` over channel ``channel[p]`` (the index of ``sender -> node`` among the network's
    directed channels in ``np.nonzero(adjacency)`` order, as :class:`filters.consensus_batch.EdgeAttacks`); the
    sender received it as pair ``parent[p]`` (-1 when the sender is the source).  Pairs are sorted by depth, then
    node, then source, so that a pass in order meets every pair after its parent.  ``incidence`` (pairs x
    channels, sparse 0/1) marks the channels of each pair's route.

    ``routing`` says which copy a node takes: ``'tree'``, the copy of its tree parent ``sender`` only (the route
    above); ``'flood'``, the first copy to arrive from any neighbour (module docstring, "Flooding").  The copies a
    node may take are its *candidates* ``cand_parent``, ``cand_channel`` (pairs x D, in the order the node prefers
    them, -1-padded channels): the pair of the neighbour that forwards it (-1: the neighbour is the source) and the
    channel.  A tree has one candidate per pair, its parent; flooding every neighbour that holds the measurement
    within ``hops - 1`` hops, lowest-numbered first (:meth:`realise`).
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
    routing: str = "tree"
    cand_parent: np.ndarray | None = None
    cand_channel: np.ndarray | None = None

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
        """(pairs,) the probability that the pair's measurement arrives along its tree route: no channel of its route
        lost to DoS (for ``routing='tree'``; flooding's is at least this, :func:`flood_moments`)."""
        return np.exp(self.incidence @ _log_up(network))

    def realise(self, up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which copy of every pair arrives in one step, over a batch: ``up`` (a, channels) bool, the channels that
        deliver (not lost to DoS).  Returns ``(rnd, parent, channel)`` (a, pairs): the round in which the pair's
        measurement first arrived (0: it did not), the pair of the copy taken (-1: from the source itself, or none)
        and its channel (-1: none).

        Round by round (1..hops), a pair that has not arrived takes its first candidate (:class:`Routes`) whose
        forwarding node received the measurement in the previous round (the source: round 0) and whose channel
        delivers: what a node does that forwards, in round r, the measurements it first received in round r - 1
        and keeps the first copy of each, from its lowest-numbered neighbour among those that arrive together."""
        up = np.ascontiguousarray(up, dtype=bool)
        E = self.incidence.shape[1]
        if up.ndim != 2 or up.shape[1] != E:
            raise InputError(f"up must be a (batch, {E}) array of the network's channels, got shape {up.shape}")
        a, P = up.shape[0], self.n_pairs
        rnd = np.zeros((a, P), dtype=np.int16)
        parent = np.full((a, P), -1)
        channel = np.full((a, P), -1)
        if P:
            ends = np.searchsorted(self.depth, np.arange(1, self.hops + 1), side="right")  # pairs sorted by depth
            _kernel(_realise_loop)(up, np.ascontiguousarray(self.cand_parent),
                                   np.ascontiguousarray(self.cand_channel), ends, rnd, parent, channel)
        return rnd, parent, channel

    def messages_per_step(self, network: SensorNetwork) -> int:
        """Packets per step: one per directed channel and round, ``2 |E| hops`` (as for the exchange rounds)."""
        return network.messages_per_step(self.hops)

    def values_per_step(self) -> int:
        """Measurements forwarded per step over all channels (a packet carries those of its round): along a tree one
        per pair; flooding, at most one per candidate (every node forwards each measurement it holds within
        ``hops - 1`` hops to every neighbour but its source, once)."""
        return self.n_pairs if self.routing == "tree" else int(np.count_nonzero(self.cand_channel >= 0))

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

        In closed form for a tree's routes only (flooding's: :func:`flood_moments`).
        """
        if self.routing != "tree":
            raise InputError(f"arrival_moments: the moments of routing {self.routing!r} have no closed form; use "
                             "rules.relay.design.relay_moments (flood_moments, by Monte Carlo of the channels)")
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


def _realise_loop(up, cand_parent, cand_channel, ends, rnd, parent, channel):  # pragma: no cover (compiled)
    """:meth:`Routes.realise`'s loop (compiled by :func:`_kernel`): in round r only the pairs of depth <= r
    (``ends[r - 1]`` first pairs) that have not arrived are examined, a node being reached no sooner than its depth."""
    for w in range(up.shape[0]):
        for r in range(1, ends.size + 1):
            for p in range(ends[r - 1]):
                if rnd[w, p] != 0:
                    continue
                for c in range(cand_parent.shape[1]):
                    ch = cand_channel[p, c]
                    if ch < 0 or not up[w, ch]:
                        continue
                    q = cand_parent[p, c]
                    if (r == 1 and q >= 0) or (r > 1 and (q < 0 or rnd[w, q] != r - 1)):
                        continue
                    rnd[w, p] = r
                    parent[w, p] = q
                    channel[w, p] = ch
                    break


def _falsified_loop(rnd, parent, channel, fals, node, local, offset, width, hops, f1):  # pragma: no cover (compiled)
    """:func:`flood_moments`' walk (compiled by :func:`_kernel`): for every copy that arrived, the falsified channels
    of its path (its own and its parents' up to the source, at most ``hops``).  Returns ``count`` (a, P), how many;
    adds to ``f1`` (flat, node ``i``'s block of ``width[i]`` x ``width[i]`` from ``offset[i]``, its pairs in the
    order ``local``) how many falsified channels the paths of each two of node ``i``'s pairs share, over the draws:
    ``Σ_draws |S_a ∩ S_b|``, sums of ones (exact: the same numbers in any order)."""
    a, P = rnd.shape
    E = fals.shape[1]
    count = np.zeros((a, P), dtype=np.float32)
    keys = np.empty(max(P * hops, 1), dtype=np.int64)  # (node, channel) of every falsified channel of every path
    locs = np.empty(max(P * hops, 1), dtype=np.int64)  # its pair's place at that node
    for w in range(a):
        k = 0
        for p in range(P):
            if rnd[w, p] == 0:
                continue
            q = p
            c = 0
            while q >= 0:
                ch = channel[w, q]
                if fals[w, ch]:
                    c += 1
                    keys[k] = node[p] * E + ch
                    locs[k] = local[p]
                    k += 1
                q = parent[w, q]
            count[w, p] = c
        order = np.argsort(keys[:k])  # the paths through one falsified channel, node by node, together
        s = 0
        while s < k:
            e = s + 1
            while e < k and keys[order[e]] == keys[order[s]]:
                e += 1
            i = keys[order[s]] // E
            base, wd = offset[i], width[i]
            for x in range(s, e):
                row = base + locs[order[x]] * wd
                for y in range(s, e):
                    f1[row + locs[order[y]]] += 1.0
            s = e
    return count


_KERNELS: dict = {}


def _kernel(loop):
    """``loop`` compiled with numba (on first use, cached on disk: once per machine; numba imported here, not when
    the routes are listed)."""
    if loop.__name__ not in _KERNELS:
        import numba

        _KERNELS[loop.__name__] = numba.njit(nogil=True, cache=True)(loop)
    return _KERNELS[loop.__name__]


def _channel_values(network: SensorNetwork, matrix: np.ndarray) -> np.ndarray:
    """A per-channel quantity ``matrix[receiver, sender]`` (N x N) in channel order."""
    receiver, sender = np.nonzero(network.adjacency)
    return np.asarray(matrix, float)[receiver, sender]


def _log_up(network: SensorNetwork) -> np.ndarray:
    """(channels,) ``log(1 - dos)`` of every channel: the log-probability that it delivers."""
    with np.errstate(divide="ignore"):
        return np.log1p(-_channel_values(network, network.dos_prob))


def hop_distances(network: SensorNetwork) -> np.ndarray:
    """(N, N) the hops of the shortest path between every two nodes (``inf`` between components)."""
    return shortest_path(sp.csr_matrix(network.adjacency.astype(float)), unweighted=True)


def diameter(network: SensorNetwork) -> int:
    """The network's diameter in hops (the longest shortest path; of the largest component when disconnected)."""
    dist = hop_distances(network)
    return int(dist[np.isfinite(dist)].max())


def default_hops(network: SensorNetwork) -> int:
    """The hops of a relay design that gives none: the network's diameter, at most :data:`DEFAULT_HOPS_MAX` (1 for
    a network without edges)."""
    return max(1, min(diameter(network), DEFAULT_HOPS_MAX))


def relay_payload(network: SensorNetwork, sensor_dims, hops: int, routing: str = "tree") -> int:
    """The numbers relayed per step over ``hops`` rounds: each relayed measurement carries its values and its
    sensor's index (one number).  ``'tree'``: every sensor ``s``'s measurement crosses one channel into each node
    within ``hops`` hops of ``s`` (its route's last channel), once; ``'flood'``: every node forwards each
    measurement it holds after fewer than ``hops`` rounds (its own included) to all its neighbours."""
    hops = check_int("hops", hops, 1, MAX_HOPS)
    dist = hop_distances(network)  # (s, i)
    size = np.asarray(sensor_dims, dtype=int) + 1
    if routing == "tree":
        return int(((dist >= 1) & (dist <= hops)).sum(axis=1) @ size)
    degree = np.asarray(network.adjacency, dtype=bool).sum(axis=1)
    return int(size @ (dist <= hops - 1) @ degree)


def moment_bytes(network: SensorNetwork, sensor_dims, hops: int) -> int:
    """The bytes of the node moments of one network over ``hops`` hops, at most: every node's r x r ``A``, ``F1`` and
    ``F2`` (:class:`NodeMoments`), r the measurement rows of its ball (the sensors within ``hops`` hops)."""
    rows = ((hop_distances(network) <= hops) * np.asarray(sensor_dims, dtype=float)[:, None]).sum(axis=0)
    return int(3 * 8 * np.sum(rows ** 2))


def relay_routes(network: SensorNetwork, hops: int, routing: str = "tree") -> Routes:
    """The routes of every sensor's measurement over at most ``hops`` channels (``1 <= hops <= MAX_HOPS``), the
    copies a node takes chosen by ``routing`` (:data:`ROUTINGS`, :class:`Routes`)."""
    if not isinstance(network, SensorNetwork):
        raise InputError(f"network must be a designer.SensorNetwork, got {type(network).__name__}")
    hops = check_int("hops", hops, 1, MAX_HOPS)
    if routing not in ROUTINGS:
        raise InputError(f"routing must be one of {', '.join(map(repr, ROUTINGS))}, got {routing!r}")
    N = network.n_nodes
    adj = network.adjacency
    dist = hop_distances(network)  # dist[s, i]
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
    source, node = np.array(src, dtype=int), np.array(nod, dtype=int)
    if routing == "tree":
        cand_parent, cand_channel = parent[:, None], channel[:, None]
    else:  # every neighbour j of the node holding the measurement within hops - 1 hops, lowest-numbered first
        pair_index = np.full((N, N), -2)  # pair_index[s, j]: the pair of s's measurement at j (-1: j is s)
        pair_index[source, node] = np.arange(P)
        pair_index[np.arange(N), np.arange(N)] = -1
        deg = adj.sum(axis=1)
        D = max(int(deg.max()) if N else 0, 1)
        nbr = np.full((N, D), -1)
        for i in range(N):
            nbr[i, :deg[i]] = np.flatnonzero(adj[i])
        j = nbr[node]  # (P, D)
        ok = (j >= 0) & (dist[source[:, None], np.maximum(j, 0)] <= hops - 1)
        cand_parent = np.where(ok, pair_index[source[:, None], np.maximum(j, 0)], -1)
        cand_channel = np.where(ok, channel_of[node[:, None], np.maximum(j, 0)], -1)
    return Routes(hops, N, source, node, np.array(dep, dtype=int), np.array(snd, dtype=int), channel, parent, inc,
                  routing, cand_parent, cand_channel)


class NodeMoments(NamedTuple):
    """One node's arrival and falsification moments over its ball (:meth:`Routes.arrival_moments`), expanded to the
    rows of the stacked measurement (a sensor of dimension m contributes m rows): ``p`` (r,), ``A``, ``F1``, ``F2``
    (r, r), ``sensors`` (its ball, own first), ``rows`` (r,) the sensor of each row and ``groups`` (r, hops + 1),
    each row's hop depth one-hot (0: the node's own measurement): the relay rule's gain has one block per depth."""

    sensors: np.ndarray
    rows: np.ndarray
    p: np.ndarray
    A: np.ndarray
    F1: np.ndarray
    F2: np.ndarray
    groups: np.ndarray


def node_moments(routes: Routes, network: SensorNetwork, dims, i: int, ball_moments=None) -> NodeMoments:
    """Node ``i``'s :class:`NodeMoments`; ``dims`` (n_sensors,) each sensor's measurement dimension;
    ``ball_moments`` its ``(p, A, F1, F2)`` over its ball (default :meth:`Routes.arrival_moments`, a tree's)."""
    ball = routes.ball(i)
    p, A, F1, F2 = routes.arrival_moments(network, i) if ball_moments is None else ball_moments
    depth = np.concatenate([[0], routes.depth[routes.node == i]]).astype(int)
    owner = np.repeat(np.arange(ball.size), np.asarray(dims, int)[ball])
    ix = np.ix_(owner, owner)
    groups = np.eye(routes.hops + 1)[depth[owner]]
    return NodeMoments(ball, ball[owner], p[owner], A[ix], F1[ix], F2[ix], groups)


#: The channel draws of flooding's Monte Carlo moments (:func:`flood_moments`): as many as fit in this many pair
#: draws, between FLOOD_SAMPLES_MIN and FLOOD_SAMPLES_MAX (an assumption, chosen: about 10 s on the 512-node grid).
FLOOD_PAIR_DRAWS = 40_000_000
FLOOD_SAMPLES_MIN = 256
FLOOD_SAMPLES_MAX = 8_000
#: The seed of the Generator behind a design's flooding moments when none is given: the moments are part of the
#: design, the same network gives the same moments in the design, its certificate and its filter.
FLOOD_SEED = 20261204


def flood_samples(routes: Routes) -> int:
    """The channel draws :func:`flood_moments` takes by default for ``routes``."""
    return int(np.clip(FLOOD_PAIR_DRAWS // max(routes.n_pairs, 1), FLOOD_SAMPLES_MIN, FLOOD_SAMPLES_MAX))


def flood_moments(routes: Routes, network: SensorNetwork, rng: np.random.Generator | None = None,
                  samples: int | None = None) -> list[tuple]:
    """Every node's ``(p, A, F1, F2)`` over its ball (the quantities of :meth:`Routes.arrival_moments`) for the
    copies :meth:`Routes.realise` takes, by Monte Carlo over ``samples`` (default :func:`flood_samples`) draws of
    the channels (DoS with probability ``dos_prob``, else FDI with ``fdi_prob``, as the simulations draw them)
    from ``rng`` (default ``numpy.random.default_rng(FLOOD_SEED)``).  A measurement's falsification is the sum
    of the offsets of the falsified channels of the path its copy took (``S_a``), so that ``F1 = E[γ_a γ_b |S_a ∩
    S_b|]`` and ``F2 = E[γ_a γ_b (|S_a| |S_b| - |S_a ∩ S_b|)]``.  The estimates are unbiased (sample means of the
    same products); their sampling error is that of ``samples`` draws."""
    rng = np.random.default_rng(FLOOD_SEED) if rng is None else rng
    samples = flood_samples(routes) if samples is None else check_int("samples", samples, 1, 10 ** 7)
    P, N = routes.n_pairs, routes.n_nodes
    dos = _channel_values(network, network.dos_prob)
    fdi = _channel_values(network, network.fdi_prob)
    E = dos.size
    D = routes.cand_parent.shape[1] if P else 1
    chunk = int(max(1, 4_000_000 // max(P * D, 1)))
    arrived = np.zeros((samples, P), dtype=bool)
    count = np.zeros((samples, P), dtype=np.float32)  # |S_a|: the falsified channels on the copy's path
    nodes = np.asarray(routes.node, dtype=np.int64)
    width = np.bincount(nodes, minlength=N).astype(np.int64)  # each node's pairs (its ball less its own sensor)
    offset = np.concatenate([[0], np.cumsum(width ** 2)]).astype(np.int64)
    local = np.zeros(P, dtype=np.int64)  # each pair's place among its node's, in pair order
    for i in range(N):
        local[nodes == i] = np.arange(width[i])
    shared = np.zeros(int(offset[-1]))  # Σ_draws |S_a ∩ S_b| of each two pairs of a node
    for start in range(0, samples, chunk):
        a = min(chunk, samples - start)
        u = rng.random((a, E))
        lost = u < dos
        fals = ~lost & (u < dos + fdi)
        rnd, parent, channel = routes.realise(~lost)
        arrived[start:start + a] = rnd > 0
        count[start:start + a] = _kernel(_falsified_loop)(rnd, parent, channel, np.ascontiguousarray(fals), nodes,
                                                          local, offset, width, int(routes.hops), shared)
    out = []
    for i in range(N):
        idx = np.flatnonzero(routes.node == i)
        G = arrived[:, idx].astype(float)  # (samples, m - 1)
        C = count[:, idx].astype(float)
        m = idx.size + 1
        p = np.ones(m)
        p[1:] = G.mean(axis=0)
        A = np.ones((m, m))
        A[1:, 1:] = G.T @ G / samples
        A[0, 1:] = A[1:, 0] = p[1:]
        F1 = np.zeros((m, m))
        F1[1:, 1:] = shared[offset[i]:offset[i + 1]].reshape(m - 1, m - 1) / samples
        F2 = np.zeros((m, m))
        F2[1:, 1:] = C.T @ C / samples - F1[1:, 1:]
        out.append((p, A, F1, F2))
    return out


def relay_moments(routes: Routes, network: SensorNetwork, dims, rng: np.random.Generator | None = None
                  ) -> list[NodeMoments]:
    """Every node's :class:`NodeMoments` for ``routes``: in closed form for a tree (:meth:`Routes.arrival_moments`),
    by Monte Carlo for flooding (:func:`flood_moments`, ``rng`` its Generator)."""
    if routes.routing == "tree":
        return [node_moments(routes, network, dims, i) for i in range(routes.n_nodes)]
    if rng is not None:
        balls = flood_moments(routes, network, rng)
    else:  # the design's own moments (FLOOD_SEED): its certificate, its run and its filter take the same, once
        key = (routes.hops, network.adjacency.tobytes(), network.dos_prob.tobytes(), network.fdi_prob.tobytes())
        balls = _FLOOD_MEMO.pop(key, None)
        if balls is None:
            balls = flood_moments(routes, network)
        _FLOOD_MEMO[key] = balls  # the newest last
        size = {k: sum(a.nbytes for ball in v for a in ball) for k, v in _FLOOD_MEMO.items()}
        while len(_FLOOD_MEMO) > 1 and sum(size.values()) > FLOOD_MEMO_BYTES:
            size.pop(oldest := next(iter(_FLOOD_MEMO)))
            del _FLOOD_MEMO[oldest]
    return [node_moments(routes, network, dims, i, b) for i, b in enumerate(balls)]


#: The flooding moments kept in a process (the latest network's always, the least recently asked let go first; a
#: study's sweep settings are networks of other channel probabilities, each chunk of runs asks for all of them): up
#: to this many bytes.  At 512
#: nodes and 8 hops one network's take a few hundred MB; on IEEE 14 at 1 hop 0.1 MB.
FLOOD_MEMO_BYTES = 64 * 2**20
_FLOOD_MEMO: dict = {}


def grouped(Hw: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """``Ĥ`` (..., r, G n): each row ``Hw_a`` (..., r, n) placed in the column block of its group (``groups`` (..., r,
    G) one-hot), zero elsewhere: ``Ĥᵀ y`` stacks the groups' sums ``Σ_{a in g} Hw_aᵀ y_a``."""
    r, n = Hw.shape[-2:]
    G = groups.shape[-1]
    return (groups[..., :, :, None] * Hw[..., :, None, :]).reshape(Hw.shape[:-2] + (r, G * n))


def pair_sum(Hw: np.ndarray, weights: np.ndarray, X: np.ndarray, Hg: np.ndarray | None = None,
             groups: np.ndarray | None = None) -> np.ndarray:
    """``Σ_ab w_ab J_a X J_b = Hwᵀ (w ∘ (Hw X Hwᵀ)) Hw`` (..., n, n), linear in ``X``; with ``Hg`` (:func:`grouped`
    from the one-hot ``groups``) the blocks of every pair of groups, ``Ĥᵀ (w ∘ (Hw X Hwᵀ)) Ĥ`` (..., G n, G n)."""
    Ht = np.swapaxes(Hw, -1, -2)
    K = weights * (Hw @ X @ Ht)
    if Hg is None:
        return Ht @ K @ Hw
    return np.swapaxes(Hg, -1, -2) @ _times_grouped(K, Hw, Hg, groups)


def _times_grouped(K: np.ndarray, Hw: np.ndarray, Hg: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """``K Ĥ`` (..., r, G n).  One node's rows (``groups`` (r, G), its rows in depth order, as
    :func:`node_moments` lays them): each group's columns ``K[:, g] Hw[g]``, one product per group, r² n operations
    instead of r² G n; nodes stacked (``groups`` (..., r, G), their depths at different rows): the product itself."""
    depth = groups.argmax(-1)
    if groups.ndim != 2 or np.any(np.diff(depth) < 0):
        return K @ Hg
    r, n = Hw.shape[-2:]
    G = groups.shape[-1]
    out = np.zeros(K.shape[:-1] + (G * n,))
    bounds = np.searchsorted(depth, np.arange(G + 1))
    for g in range(G):
        a, b = bounds[g], bounds[g + 1]
        if b > a:
            out[..., g * n:(g + 1) * n] = K[..., :, a:b] @ Hw[..., a:b, :]
    return out


def update_moments(Hw: np.ndarray, mom: NodeMoments, M: np.ndarray, mu: np.ndarray) -> tuple:
    """The parts of the relay rule's expected update that do not depend on the prediction: ``(Hg, Sg, K0)`` with
    ``Hg`` :func:`grouped`, ``Sg = Σ_a p_a Hw_aᵀ Ĥ_a`` (..., n, G n) (``E[e⁻ yᵀ] = P⁻ Sg``) and ``K0`` (..., r, r)
    the row weights of the noises' and falsifications' part of ``E[y yᵀ]``, ``Ĥᵀ K0 Ĥ``:
    ``K0 = diag(p) + F1 ∘ (Hw M Hwᵀ) + F2 ∘ (Hw μμᵀ Hwᵀ)``."""
    Hg = grouped(Hw, mom.groups)
    return Hg, np.swapaxes(Hw, -1, -2) @ (mom.p[..., :, None] * Hg), _row_weights(Hw, mom, M, mu)


def _row_weights(Hw: np.ndarray, mom: NodeMoments, M: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """:func:`update_moments`'s ``K0`` (..., r, r)."""
    K0 = np.zeros(Hw.shape[:-1] + Hw.shape[-2:-1])
    idx = np.arange(Hw.shape[-2])
    K0[..., idx, idx] = mom.p
    Ht = np.swapaxes(Hw, -1, -2)
    if np.any(mom.F1) and np.any(M):
        K0 = K0 + mom.F1 * (Hw @ M @ Ht)
    if np.any(mu) and np.any(mom.F2):
        hmu = (Hw @ mu[..., :, None])[..., 0]  # μ one, or one per node: Hw μμᵀ Hwᵀ = (Hw μ)(Hw μ)ᵀ
        K0 = K0 + mom.F2 * (hmu[..., :, None] * hmu[..., None, :])
    return K0


def _rows_to_groups(K: np.ndarray, Hw: np.ndarray, Hg: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """``Ĥᵀ K Ĥ`` (..., G n, G n) of row weights ``K`` (..., r, r)."""
    return np.swapaxes(Hg, -1, -2) @ _times_grouped(K, Hw, Hg, groups)


#: the pseudo-inverse's cut in :func:`relay_update`: eigenvalues below this times the largest are left out (double's);
#: a float C node's (``-DCFD_REAL=float``, rules.relay.export_c), which float cannot resolve below
RTOL = 1e-12
FLOAT_RTOL = 1e-5
#: :func:`_basis_update`'s cut of a depth's Gram eigenvalues, relative to the largest and per row or column of the
#: Gram: directions at rounding's level (a row that repeats a direction of its depth) are left out
BASIS_TOL = 64 * np.finfo(float).eps


class RelayGain(NamedTuple):
    """The relay rule's gain at a node (:func:`relay_gain`), as it was computed: in the ball's rows, ``Kr`` (..., n, r)
    and ``G0`` (..., r, r) the products of two rows of one hop depth (``W = K_r Ĥ``, so that ``W y = K_r G0 res``:
    the n x G n matrix ``W`` is never formed), or ``W`` (..., n, G n) itself (``Kr``, ``G0`` None).  ``direct``
    (...,) marks the items whose gain was solved directly (``K_r = X S⁻¹``, ``G0`` the identity there, so that
    ``W = K_r G0⁻¹ Ĥ`` with the products' ``G0``)."""

    Kr: np.ndarray | None
    G0: np.ndarray | None
    W: np.ndarray | None
    direct: np.ndarray | None = None

    def correction(self, Hw: np.ndarray, mom: NodeMoments, res: np.ndarray) -> np.ndarray:
        """``W y`` (..., n) for the whitened residuals ``res`` (..., r) (zero where a measurement did not arrive),
        ``y`` their groups' information (:func:`relay_information`): in the rows ``K_r (G0 res)``, as the C node
        computes it (``(Ĥ y)_a = Σ_b G0_ab res_b``, ``b`` the rows of ``a``'s depth)."""
        if self.W is None:
            return (self.Kr @ (self.G0 @ res[..., None]))[..., 0]
        return (self.W @ relay_information(Hw, mom, res)[..., None])[..., 0]

    def matrix(self, Hw: np.ndarray, mom: NodeMoments) -> np.ndarray:
        """``W`` (..., n, G n), one n x n block per hop depth: in the rows ``K_r Ĥ``, depth g's block from its rows
        alone."""
        if self.W is not None:
            return self.W
        n, G = Hw.shape[-1], mom.groups.shape[-1]
        lead = self.Kr.shape[:-2]
        Hw = np.broadcast_to(Hw, lead + Hw.shape[-2:])
        direct = np.zeros(lead, dtype=bool) if self.direct is None else self.direct
        W = np.zeros(lead + (n, G * n))
        for g in range(G):
            rows = np.flatnonzero(mom.groups[:, g])
            if rows.size:
                Hr = np.array(Hw[..., rows, :])
                if direct.any():  # G0⁻¹ Ĥ on depth g's rows: (Hw_g Hw_gᵀ)⁻¹ Hw_g
                    Hd = Hr[direct]
                    Hr[direct] = np.linalg.solve(Hd @ np.swapaxes(Hd, -1, -2), Hd)
                W[..., g * n:(g + 1) * n] = self.Kr[..., rows] @ Hr
        return W


def relay_update(P_pred: np.ndarray, Hw: np.ndarray, mom: NodeMoments, M: np.ndarray, mu: np.ndarray,
                 rtol: float = RTOL) -> tuple[np.ndarray, np.ndarray]:
    """:func:`relay_gain` with its gain as the matrix ``W`` (..., n, G n): ``(W, P_post)``."""
    gain, P = relay_gain(P_pred, Hw, mom, M, mu, rtol)
    return gain.matrix(Hw, mom), P


def relay_gain(P_pred: np.ndarray, Hw: np.ndarray, mom: NodeMoments, M: np.ndarray, mu: np.ndarray,
               rtol: float = RTOL) -> tuple[RelayGain, np.ndarray]:
    """The relay rule's gain and expected posterior covariance at one node, over a batch: ``(gain, P_post)``, the
    gain a :class:`RelayGain` (``W`` (..., n, G n), one n x n block per hop depth, or its factors in the ball's rows).

    ``P_pred`` (..., n, n) the node's predicted covariance; ``Hw`` (..., r, n) the whitened Jacobian rows
    ``R_a^{-1/2} H_a`` of its ball's measurements (``mom.rows`` order) at its prediction; ``M``, ``mu`` the
    falsification's second moment and mean (:class:`designer.attacks.FDISignal`).  The node updates with
    ``x̂⁺ = x̂⁻ + Σ_g W_g y_g``, ``y_g = Σ_{a in g, arrived} H_aᵀ R_a⁻¹ (z̃_a - h_a(x̂⁻))`` the information of the
    measurements of hop depth g (0: its own; ``mom.groups``) that arrived: one gain block per depth for whichever
    measurements arrive, chosen to minimise ``tr E[e⁺ e⁺ᵀ]`` over the arrivals, the falsifications and the noises
    (the linearised error ``e⁺ = e⁻ - W y``, ``y = Σ_a γ_a Ĥ_aᵀ (Hw_a e⁻ + w_a + η_a)``, ``J_a = H_aᵀ R_a⁻¹ H_a``,
    ``w_a`` the whitened noise, ``η_a`` the whitened falsification, the draws independent of ``e⁻``)::

        C = E[e⁻ yᵀ] = P⁻ Sg,   Q = E[y yᵀ] = Ĥᵀ (A ∘ (Hw P⁻ Hwᵀ) + K0) Ĥ
        W = C Q⁺,               P⁺ = P⁻ - W Cᵀ

    (:func:`update_moments`; ``Q⁺`` the pseudo-inverse on ``Q``'s range, eigenvalues below ``rtol`` times the
    largest dropped: directions no measurement sees).  Far measurements arrive less often and are falsified more
    often than near ones: a block per depth weighs them apart (one gain for all would weigh every measurement by
    its ``R⁻¹`` alone).  With every measurement arriving and none falsified, ``P⁺`` is the Kalman filter's of the
    ball's measurements (its gain applied to ``Σ_g y_g``).  For a linear model ``P⁺`` is the expected covariance
    of the node's error over the attacks; a node computes it itself (its own estimate's Jacobians, its design's
    moments)."""
    # Q = Ĥᵀ S Ĥ (G n x G n, S = E[(...)(...)ᵀ]'s row weights, r x r) has rank at most r, the ball's rows, far below
    # G n on a field or a grid (a 64-cell field at 5 hops: 26-51 rows, 84-216 active columns).  With S = Lₛ Lₛᵀ
    # positive definite (every row arrives with a positive probability: S ≥ diag(p)) and G = Lₛᵀ Ĥ, Q = GᵀG and
    # M = G Gᵀ = Lₛᵀ (Ĥ Ĥᵀ) Lₛ (r x r) have the same nonzero eigenvalues, so that with the same cut
    # C Q⁺ = X Lₛ⁻ᵀ M⁺ Lₛᵀ Ĥ = K_r Ĥ (C = X Ĥ, X = P⁻ Hwᵀ diag(p)) and P⁺ = P⁻ - K_r (Ĥ Ĥᵀ) Xᵀ: the eigendecomposition
    # of M, r x r, in place of Q's (:func:`_row_space_update`), where the rows are fewer than Q's G n columns (with
    # as many rows, M is singular and its work the larger: the robot's 16 rows against 15 columns) and S is positive
    # definite (else a row never arrives); otherwise Q's own (below).  The C node decides alike
    # (rules/relay/c/cfd_node.c.in: 5 x slower on the robot in the rows), and where M has no certified inverse (rows
    # that repeat a direction of their depth: Q's rank below r) both reduce Q to a basis of each depth's rows, in Q's
    # range, the same P⁺ to rounding, in place of M's eigendecomposition (:func:`_basis_update`; in C 2.4 x less time
    # a step on a 24-state beam of 26 rows).
    groups = mom.groups
    if groups.ndim > 2:  # depths at different rows for different items: one item at a time
        lead = Hw.shape[:-2]
        Pb, Hb = np.broadcast_to(P_pred, lead + P_pred.shape[-2:]), Hw
        out = [relay_update(Pb[i], Hb[i], _take(mom, i)._replace(groups=groups[i]), M if M.ndim == 2 else M[i],
                            mu if mu.ndim == 1 else mu[i], rtol) for i in np.ndindex(lead)]
        return (RelayGain(None, None, np.stack([w for w, _ in out]).reshape(lead + out[0][0].shape)),
                np.stack([p for _, p in out]).reshape(lead + out[0][1].shape))
    n, G = P_pred.shape[-1], groups.shape[-1]
    HP = Hw @ P_pred
    S = _row_weights(Hw, mom, M, mu) + mom.A * (HP @ np.swapaxes(Hw, -1, -2))
    fast = None if Hw.shape[-2] >= G * n else _row_space_update(P_pred, Hw, HP, 0.5 * (S + np.swapaxes(S, -1, -2)),
                                                                   mom, rtol)
    if fast is not None:
        return fast
    # the columns of Ĥ that are zero throughout (an empty depth, a state component no sensor of a depth sees) are
    # zero rows and columns of Q and zero columns of C: left out from the start (the same W; on a field or a grid,
    # where a depth's sensors see a few of the states, products and an eigh a few times smaller than G n); Ĥ is
    # never formed: its depth g's block is the depth's rows Hw_g on their nonzero columns, so that each product with
    # it takes that depth's rows alone
    blocks = [(g * n + cols, rows, Hw[..., rows[:, None], cols])  # (columns, rows, Hw_g on them) of each depth
              for g, rows, cols in _depth_columns(Hw, groups) if cols.size]  # with a nonzero column
    W = np.zeros(Hw.shape[:-2] + (n, G * n))
    if not blocks:  # no measurement sees a state: no update
        return RelayGain(None, None, W), np.array(np.broadcast_to(0.5 * (P_pred + np.swapaxes(P_pred, -1, -2)),
                                                                  Hw.shape[:-2] + (n, n)))
    act = np.concatenate([c for c, _, _ in blocks])
    SH = np.concatenate([S[..., :, rows] @ B for _, rows, B in blocks], axis=-1)  # S Ĥ on the active columns
    Q = np.concatenate([np.swapaxes(B, -1, -2) @ SH[..., rows, :] for _, rows, B in blocks], axis=-2)
    Qp = pseudo_inverse(Q, rtol)
    C = np.concatenate([np.swapaxes(mom.p[..., rows, None] * HP[..., rows, :], -1, -2) @ B
                        for _, rows, B in blocks], axis=-1)  # P⁻ Hwᵀ diag(p) Ĥ
    W[..., act] = C @ Qp
    P = P_pred - W[..., act] @ np.swapaxes(C, -1, -2)
    return RelayGain(None, None, W), 0.5 * (P + np.swapaxes(P, -1, -2))


def _depth_columns(Hw: np.ndarray, groups: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Each hop depth's rows and the columns they touch in some item of ``Hw`` (..., r, n): ``(g, rows, cols)``, the
    depths without rows left out (``cols`` may be empty: rows that see no state)."""
    out = []
    for g in range(groups.shape[-1]):
        rows = np.flatnonzero(groups[:, g])
        if rows.size:
            out.append((g, rows, np.flatnonzero(np.any(Hw[..., rows, :] != 0.0,
                                                       axis=tuple(range(Hw.ndim - 2)) + (-2,)))))
    return out


def _row_space_update(P_pred, Hw, HP, S, mom: NodeMoments, rtol: float):
    """:func:`relay_gain` in the ball's rows (its comment says why and how): ``(gain, P⁺)``, the gain's ``K_r`` and
    ``G0`` (:class:`RelayGain`), or None where some item's ``S`` is not positive definite (then Q's own
    eigendecomposition).

    Where ``M`` keeps every eigenvalue above ``rtol`` of the largest (:func:`_direct` certifies it without forming
    ``M``), ``M⁺ = M⁻¹ = Lₛ⁻¹ G0⁻¹ Lₛ⁻ᵀ`` and the gain reduces to ``K_r G0 = X S⁻¹``: ``x⁺ = x⁻ + X S⁻¹ res`` and
    ``P⁺ = P⁻ - X S⁻¹ Xᵀ``, a Kalman update in the ball's rows with the attack-weighted ``S`` (``Ĥ`` of full row
    rank: ``Ĥ (Ĥᵀ S Ĥ)⁺ Ĥᵀ = S⁻¹``).  Those items' ``G0`` is the identity (``K_r = X S⁻¹``, ``direct`` set); the
    others reduce ``Q`` to a basis of each depth's rows (:func:`_basis_update`), as the C node does."""
    try:
        Ls = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return None
    n, r = Hw.shape[-1], Hw.shape[-2]
    lead = np.broadcast_shapes(P_pred.shape[:-2], Hw.shape[:-2], S.shape[:-2])
    Ls, Hw, P_pred, S = (np.broadcast_to(a, lead + a.shape[-2:]) for a in (Ls, Hw, P_pred, S))
    same = mom.groups @ mom.groups.T  # (r, r) 1 where two rows are of the same hop depth
    G0 = same * (Hw @ np.swapaxes(Hw, -1, -2))  # Ĥ Ĥᵀ
    X = np.broadcast_to(mom.p[..., :, None] * HP, lead + (r, n))  # Xᵀ = diag(p) Hw P⁻
    Li = lower_inverse(Ls)
    Y = Li @ X  # Lₛ⁻¹ Xᵀ (r x n)
    depths = _depth_columns(Hw, mom.groups)
    direct = _direct(S, Li, G0, mom.groups, rtol, depths)
    if direct.all():  # every item direct (a field's balls of independent rows): no item's arrays gathered
        Yt = np.swapaxes(Y, -1, -2)
        return (RelayGain(Yt @ Li, np.broadcast_to(np.eye(r), lead + (r, r)), None, direct),
                symmetrize(P_pred - Yt @ Y))
    Kr, G, P = np.empty(lead + (n, r)), np.empty(lead + (r, r)), np.empty(lead + (n, n))
    if direct.any():
        Yd = Y[direct]
        Kr[direct] = np.swapaxes(Yd, -1, -2) @ Li[direct]  # X S⁻¹ = Yᵀ Lₛ⁻¹
        G[direct] = np.eye(r)
        P[direct] = P_pred[direct] - np.swapaxes(Yd, -1, -2) @ Yd
    rest = ~direct
    if rest.any():
        Kr[rest], dP = _basis_update(S[rest], Hw[rest], X[rest], depths, rtol)
        G[rest] = G0[rest]
        P[rest] = P_pred[rest] + dP
    return RelayGain(Kr, G, None, direct), symmetrize(P)


def _basis_update(S, Hw, X, depths, rtol: float):
    """:func:`_row_space_update` for the items whose ``M`` is not certified (rows of one hop depth that repeat a
    direction: a line's flow measured at both its ends, the lines of a loop): ``(K_r, P⁺ - P⁻)`` over a basis of each
    depth's rows, as the C node reduces ``Q`` (rules/relay/c/cfd_node.c.in), in place of ``M``'s eigendecomposition.

    Depth g's rows ``Hw_g`` (on their nonzero columns) are ``B_g T_g`` with ``T_g`` an orthonormal basis of their span
    from the eigenvectors of their smaller Gram matrix (``Hw_gᵀ Hw_g = V diag(μ) Vᵀ``: ``T_g = Vᵀ``, ``B_g = Hw_g V``;
    or ``Hw_g Hw_gᵀ = U diag(μ) Uᵀ``: ``B_g = U diag(μ)^½``), the directions with ``μ`` at rounding's level of the
    largest left out (``B``'s column zero).  Then ``Q = Tᵀ Q' T`` with ``Q' = Bᵀ S B`` holding ``Q``'s nonzero
    eigenvalues, so ``W = C Q⁺ = E Q'⁺ T`` (``E = P⁻ Hwᵀ diag(p) B``) and ``P⁺ = P⁻ - E Q'⁺ Eᵀ``; in the rows,
    ``K_r = E Q'⁺ diag(μ)⁻¹ Bᵀ`` (``Bᵀ B = diag(μ)``, ``B Bᵀ = G0``, so ``K_r G0 res = E Q'⁺ Bᵀ res = W y``).  A
    left-out direction keeps a diagonal entry in ``Q'`` (the mean of the kept ones', so the items keep one shape)
    that no ``E`` reads.  ``depths``: :func:`_depth_columns` of ``Hw``."""
    swap = lambda a: np.swapaxes(a, -1, -2)  # noqa: E731
    lead, r = Hw.shape[:-2], Hw.shape[-2]
    k = sum(min(rows.size, cols.size) for _, rows, cols in depths)  # each depth's basis: its smaller Gram's size
    Bf = np.zeros(lead + (r, k))
    mu = np.empty(lead + (k,))
    keep = np.empty(lead + (k,), dtype=bool)
    c = 0
    for _, rows, cols in depths:
        if not cols.size:
            continue
        Ha = Hw[..., rows[:, None], cols]
        if cols.size <= rows.size:
            m, V = np.linalg.eigh(swap(Ha) @ Ha)
            B = Ha @ V
        else:
            m, U = np.linalg.eigh(Ha @ swap(Ha))
            B = U * np.sqrt(np.maximum(m, 0.0))[..., None, :]
        kp = m > BASIS_TOL * max(rows.size, cols.size) * m[..., -1:]
        end = c + m.shape[-1]
        Bf[..., rows, c:end] = np.where(kp[..., None, :], B, 0.0)
        mu[..., c:end], keep[..., c:end] = np.where(kp, m, 1.0), kp
        c = end
    Qr = swap(Bf) @ S @ Bf
    d = np.einsum("...ii->...i", Qr)
    scale = np.sum(d, axis=-1, keepdims=True) / np.maximum(np.sum(keep, axis=-1, keepdims=True), 1)
    Qr[..., np.arange(k), np.arange(k)] = np.where(keep, d, scale)
    E = swap(X) @ Bf  # (n, k)
    K = E @ pseudo_inverse(Qr, rtol)
    return (K / mu[..., None, :]) @ swap(Bf), -(K @ swap(E))


def _direct(S: np.ndarray, Li: np.ndarray, G0: np.ndarray, groups: np.ndarray, rtol: float,
            depths: list | None = None) -> np.ndarray:
    """Which items' ``M = Lₛᵀ G0 Lₛ`` is certified to keep every eigenvalue above ``rtol`` times the largest, without
    forming it (:func:`_row_space_update`): ``M``'s eigenvalues lie in ``[λmin(S) λmin(G0), λmax(S) λmax(G0)]``,
    ``G0`` is block-diagonal by hop depth, and for ``S`` and each block ``λmax ≤ tr`` and ``1 / λmin ≤ tr`` of the
    inverse (``|L⁻¹|²`` of a Cholesky factor ``L``).  A block without a Cholesky factor (rows of one depth that
    repeat a direction, or see no state) leaves its item to the bases (:func:`_basis_update`); so does, for every
    item at once and without trying its factor, a depth with more rows than the columns its rows touch (``depths``,
    :func:`_depth_columns`: its block singular by its structure, as where a line's flow is measured at both ends by
    two nodes of one depth).  The C node certifies alike."""
    lead = G0.shape[:-2]
    if depths is not None and any(cols.size < rows.size for _, rows, cols in depths):
        return np.zeros(lead, dtype=bool)
    bound = np.trace(S, axis1=-2, axis2=-1) * np.sum(Li * Li, axis=(-2, -1))  # ≥ cond(S)
    top, inv = np.zeros(lead), np.zeros(lead)
    rows = [np.flatnonzero(groups[:, g]) for g in range(groups.shape[-1])]
    for size in {r.size for r in rows} - {0}:  # the blocks of one size at once: (..., blocks, size, size)
        idx = np.stack([r for r in rows if r.size == size])
        B = G0[..., idx[:, :, None], idx[:, None, :]]
        top = np.maximum(top, np.trace(B, axis1=-2, axis2=-1).max(axis=-1))
        inv = np.maximum(inv, _inverse_trace(B).max(axis=-1))
    return np.asarray(bound * top * inv * rtol < 1.0)


def _inverse_trace(B: np.ndarray) -> np.ndarray:
    """``tr B⁻¹ = |L⁻¹|²`` (``B = L Lᵀ``) of symmetric matrices (..., m, m), ``inf`` where one has no Cholesky factor
    (found item by item, only when the batch's factorisation fails)."""
    try:
        Li = lower_inverse(np.linalg.cholesky(B))
    except np.linalg.LinAlgError:
        if B.ndim == 2:
            return np.array(np.inf)
        return np.array([_inverse_trace(b) for b in B.reshape((-1,) + B.shape[-2:])]).reshape(B.shape[:-2])
    return np.sum(Li * Li, axis=(-2, -1))


def pseudo_inverse(M: np.ndarray, rtol: float = RTOL) -> np.ndarray:
    """The pseudo-inverse of symmetric positive semidefinite matrices ``M`` (..., m, m) with the eigenvalues below
    ``rtol`` times the largest left out, as the C node computes it: ``M⁻¹ = L⁻ᵀ L⁻¹`` where every eigenvalue
    is certified above that without an eigen-decomposition (a Cholesky factor ``M = L Lᵀ`` exists and
    ``tr(M) |L⁻¹|² < 1 / rtol``, since ``λmax ≤ tr M`` and ``1 / λmin ≤ tr M⁻¹ = |L⁻¹|²``, positive by construction
    where an inverse of an indefinite M could have a negative trace), else ``V diag(1 / λ) Vᵀ`` over the
    eigenvalues kept, for the matrices not certified (every one where some has no Cholesky factor).  The inverse
    costs a few times less than the eigen-decomposition (a flood node's over 8 hops on a 64-cell field: 60 % of its
    filter's time)."""
    M = 0.5 * (M + np.swapaxes(M, -1, -2))
    out = np.empty_like(M)
    todo = np.ones(M.shape[:-2], dtype=bool)  # the matrices not certified
    try:
        Li = lower_inverse(np.linalg.cholesky(M))  # M = L Lᵀ, M⁻¹ = L⁻ᵀ L⁻¹, tr M⁻¹ = |L⁻¹|² > 0
    except np.linalg.LinAlgError:
        pass
    else:
        todo = ~(np.trace(M, axis1=-2, axis2=-1) * np.sum(Li * Li, axis=(-2, -1)) * rtol < 1.0)
        out[~todo] = (np.swapaxes(Li, -1, -2) @ Li)[~todo]
    if todo.any():
        lam, V = np.linalg.eigh(M[todo])
        keep = lam > rtol * lam[..., -1:]
        ilam = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
        out[todo] = (V * ilam[..., None, :]) @ np.swapaxes(V, -1, -2)
    return out


def relay_information(Hw: np.ndarray, mom: NodeMoments, res: np.ndarray) -> np.ndarray:
    """``y`` (..., G n): the groups' information ``Σ_{a in g} Hw_aᵀ res_a`` of the whitened residuals ``res`` (..., r)
    (zero where a measurement did not arrive), to which the gain of :func:`relay_update` applies.  A sum over the rows
    in their order (not a matrix-vector product, whose BLAS path depends on the batch's shape): the same numbers for
    a run alone or in a batch."""
    groups = mom.groups
    n, G = Hw.shape[-1], groups.shape[-1]
    if groups.ndim > 2:
        return (grouped(Hw, groups) * res[..., :, None]).sum(axis=-2)
    y = np.zeros(Hw.shape[:-2] + (G * n,))
    for g in range(G):  # each depth's rows alone (the other rows add exact zeros to its block)
        rows = np.flatnonzero(groups[:, g])
        if rows.size:
            y[..., g * n:(g + 1) * n] = (Hw[..., rows, :] * res[..., rows, None]).sum(axis=-2)
    return y


def whitened_rows(model, x: np.ndarray, k: int) -> np.ndarray:
    """(..., n_z, n) every sensor's whitened Jacobian rows ``R_s^{-1/2} H_s(x)`` at the points ``x`` (..., n), in
    the model's measurement order (``model.sensor_dims``)."""
    x = np.asarray(x, dtype=float)
    return np.concatenate([sqrtm_psd(model.measurement_cov(s), inverse=True) @ np.asarray(model.H(s, x, k), dtype=float)
                           for s in range(model.n_sensors)], axis=-2)


def _ball_rows(mom: NodeMoments, offsets: np.ndarray) -> np.ndarray:
    """The rows of the model's stacked measurement (``offsets``: each sensor's first row) that a node's ball holds,
    in its moments' order."""
    return np.concatenate([np.arange(offsets[s], offsets[s + 1]) for s in mom.sensors])


#: The most numbers the relay LMI's maps may hold (each node's expected update written as an n² x n² matrix, and one
#: node's image of the n² basis matrices through its ball's r rows): 2^24 doubles, 128 MB.  Above it the LMI is not
#: solved and says why (a 64-cell field: 1.1e9, 8.6 GB); the recursion's fixed point is still computed.
LMI_MAX_ENTRIES = 2**24
#: The relative change of every node's trace below which the stationary recursion has reached its fixed point.
STATIONARY_TOL = 1e-9
#: The differences of past iterates the stationary recursion's Anderson acceleration keeps (as
#: :mod:`designer.feasibility`'s): at 3 hops on a 118-bus grid the plain recursion contracts by about 0.8 an
#: iteration in its tail, 84 iterations a node on average to :data:`STATIONARY_TOL`.
STATIONARY_MEMORY = 5
#: The most iterations of the stationary recursion.
STATIONARY_MAX = 5000
#: Every how many iterations, from ``2 REACH_WINDOW`` on, the stationary recursion asks whether a node's fixed point is
#: out of reach (:func:`designer.anderson.out_of_reach`): my 20-bus swing grid at DoS 0.5 and one hop ran a node's
#: recursion to its 5000 iterations, 6 s of a feasibility map point's 84.
REACH_EVERY = 10
#: A node's trace beyond which the stationary recursion is taken to grow without settling.
_BOUND_LIMIT = 1e12


def node_classes(moments: list[NodeMoments], free: bool = False) -> list[tuple[np.ndarray, NodeMoments]]:
    """The nodes in classes of equal shape, each with its members' moments stacked: ``[(nodes, stacked), ...]``, the
    members of a class having as many measurement rows and sensors and the same hop depth at every row, so that
    one batched :func:`relay_update` serves them all (``stacked.groups`` their shared (r, G) one-hot depths, the
    other fields stacked along a first axis).  The interior nodes of a regular network share a class.  ``free``:
    drop each node's own moments from the list once stacked (the memory of one copy)."""
    keys = [(m.rows.size, m.sensors.size, m.groups.argmax(-1).tobytes()) for m in moments]
    out = []
    for key in dict.fromkeys(keys):
        nodes = np.array([i for i, k in enumerate(keys) if k == key])
        groups = moments[nodes[0]].groups
        fields = {f: np.stack([getattr(moments[i], f) for i in nodes]) for f in NodeMoments._fields if f != "groups"}
        out.append((nodes, NodeMoments(groups=groups, **fields)))
        if free:
            for i in nodes:
                moments[i] = None
    return out


def relay_carried(model, routes: Routes, regions) -> Carried:
    """The states every node of ``routes`` carries with ``regions`` (:func:`designer.regions.carried_states`: its
    region, its ball's sensors' supports, closed under the dynamics)."""
    if len(regions) != routes.n_nodes:
        raise InputError(f"regions must hold one entry per node ({routes.n_nodes}), got {len(regions)}")
    carried = carried_states(model, regions, [routes.ball(i) for i in range(routes.n_nodes)])
    return Carried.of(carried, model.n_x)


def _take(mom: NodeMoments, idx: np.ndarray) -> NodeMoments:
    """The members ``idx`` of a class's stacked moments (:func:`node_classes`)."""
    return NodeMoments(groups=mom.groups, **{f: getattr(mom, f)[idx] for f in NodeMoments._fields if f != "groups"})


def _stationary_point(P: np.ndarray, Hw, mom: NodeMoments, F, Q, M, mu, per_node: bool):
    """The fixed point of ``Φ <- relay_update(F Φ Fᵀ + Q)`` for a class's members (``P`` (k, n, n) their start;
    ``Hw``, ``mom`` stacked; ``F``, ``Q``, ``M``, ``mu`` shared, or one per member when ``per_node``), each member
    Anderson-accelerated (:class:`designer.anderson.Anderson`, :data:`STATIONARY_MEMORY`) until its image ``T(Φ)``
    differs from ``Φ`` by less than :data:`STATIONARY_TOL` (relative) in trace and in Frobenius norm; a member
    leaves the iteration when it has converged.  Returns ``(W, Φ, iterations, None, None)`` (Φ the images ``T(Φ)``
    at the last points, W their gains), or ``(None, None, iterations, i, why)``: member ``i``'s trace beyond
    :data:`_BOUND_LIMIT` or not finite at a plain step (``why`` None), or its fixed point out of reach
    (:func:`designer.anderson.out_of_reach` on its relative change per iteration: ``why`` says why), or no fixed
    point in :data:`STATIONARY_MAX` iterations (``i`` and ``why`` None)."""
    k, n = P.shape[0], P.shape[-1]
    acc = Anderson(k, STATIONARY_MEMORY)
    W = np.empty((k, n, mom.groups.shape[-1] * n))
    out = np.empty_like(P)
    x = P
    act = np.arange(k)
    changes = np.full((k, STATIONARY_MAX), np.nan)  # each member's relative change from its point to its image
    for it in range(1, STATIONARY_MAX + 1):
        Fa, Qa, Ma, mua = (F[act], Q[act], M[act], mu[act]) if per_node else (F, Q, M, mu)
        Wg, g = relay_update(Fa @ x[act] @ np.swapaxes(Fa, -1, -2) + Qa, Hw[act], _take(mom, act), Ma, mua)
        tr = np.trace(g, axis1=-2, axis2=-1)
        bad = ~np.isfinite(tr) | (tr > _BOUND_LIMIT)
        if np.any(bad & ~acc.extrapolated[act]):
            return None, None, it, int(act[np.argmax(bad & ~acc.extrapolated[act])]), None
        if bad.any():  # an extrapolated point the map cannot take: back to the plain step it replaced
            x[act[bad]] = acc.retreat(act[bad]).reshape(-1, n, n)
        good = ~bad
        xa = x[act]
        gnorm = np.linalg.norm(g.reshape(act.size, -1), axis=1)
        change = np.linalg.norm((g - xa).reshape(act.size, -1), axis=1)
        done = good & (np.abs(tr - np.trace(xa, axis1=-2, axis2=-1)) <= STATIONARY_TOL * tr) & (
            change <= STATIONARY_TOL * gnorm)
        out[act[done]], W[act[done]] = g[done], Wg[done]
        go = good & ~done
        changes[act[go], it - 1] = change[go] / gnorm[go]
        if it >= 2 * REACH_WINDOW and it % REACH_EVERY == 0:  # a member that would end unsettled: said now
            for j in act[go]:
                stuck = out_of_reach(changes[j, :it][np.isfinite(changes[j, :it])], STATIONARY_TOL, STATIONARY_MAX)
                if stuck is not None:
                    return None, None, it, int(j), stuck
        if go.any():
            x[act[go]] = acc.step(act[go], xa[go], g[go])
        act = act[~done]
        if not act.size:
            return W, out, it, None, None
    return None, None, STATIONARY_MAX, None, None


def relay_stationary(model, network: SensorNetwork, design, *, x, u=None, lmi: bool = True,
                     routes: Routes | None = None):
    """The relay design's stationary certificate at the point ``x`` (input ``u``), every node's Jacobians there:
    each node's recursion ``Φ ← relay_update(F Φ Fᵀ + Q)`` from the prior covariance, Anderson-accelerated, to
    its fixed point (its image differing from it by less than :data:`STATIONARY_TOL`, relative, in trace and in
    Frobenius norm: :func:`_stationary_point`), then, for the fixed point's gains ``W_i``, the
    stationary inequality ``Φ_i ⪰ T_i(F Φ_i Fᵀ + Q)`` (``T_i`` the expected update with the gain held at ``W_i``:
    linear in Φ) minimised in trace by cvxpy + Clarabel and its solution checked in NumPy.  Since the online gain
    minimises the expected covariance, ``relay_update``'s map lies below ``T_i`` and is monotone: a Φ̄ that satisfies
    the inequality bounds every later covariance of the node once one lies below it.  The bound is the expected
    covariance of the linearised error: exact for a linear model; the linearisation remainders are not in it.

    ``routes``: the design's :func:`relay_routes` when the caller has them (default: built here).  A design whose
    nodes carry their regions (``design.carried_regions``) runs each node's recursion and LMI in its carried
    coordinates (:func:`relay_carried`), as its filter does.

    Returns a :class:`designer.stationary.StationaryCertificate` (``sigma``, ``beta`` NaN: the rule has none; with
    carried regions ``Phi`` in the carried coordinates, ``carried`` and ``positions`` where each region sits)."""

    routing = design.rule.routing
    if routes is None:
        routes = relay_routes(network, design.rounds, routing)
    elif (routes.hops, routes.routing, routes.n_nodes) != (design.rounds, routing, network.n_nodes):
        raise InputError(f"routes must be the design's: {design.rounds} hops, routing {routing!r}, "
                         f"{network.n_nodes} nodes; got {routes.hops}, {routes.routing!r}, {routes.n_nodes}")
    x = np.asarray(x, dtype=float)
    n = model.n_x
    F = np.asarray(model.F_expected(x, 0, u), dtype=float)
    Q = np.asarray(model.process_cov, dtype=float)
    Hall = whitened_rows(model, x, 1)
    M = np.zeros((n, n)) if design.fdi_moment is None else np.asarray(design.fdi_moment, dtype=float)
    mu = np.zeros(n) if design.fdi_mean is None else np.asarray(design.fdi_mean, dtype=float)
    offsets = model.sensor_offsets
    moments = relay_moments(routes, network, model.sensor_dims)
    N = network.n_nodes
    P0 = np.asarray(model.prior.cov, dtype=float)
    carry = None if design.carried_regions is None else relay_carried(model, routes, design.carried_regions)
    if carry is not None:  # every node's own: (N, m, m), (N, m)
        n = carry.m
        F, Q, M, mu, P0 = carry.matrix(F), carry.matrix(Q), carry.matrix(M), carry.vector(mu), carry.matrix(P0)
    Phi = np.empty((N, n, n))
    W = np.empty((N, n, moments[0].groups.shape[-1] * n))  # each node's gain, one n x n block per hop depth
    Hws = [None] * N  # each node's whitened ball rows, in its coordinates
    iterations = 0
    for nodes, mom in node_classes(moments):
        rows = np.stack([_ball_rows(moments[i], offsets) for i in nodes])
        Hw = Hall[rows]  # (g, r, n)
        if carry is not None:  # each node's rows in its carried coordinates
            Hw = carry.columns(Hw.reshape(-1, Hw.shape[-1]), np.repeat(nodes, Hw.shape[1])).reshape(Hw.shape[:2] + (n,))
        for i, h in zip(nodes, Hw):
            Hws[i] = h
        Fn, Qn, Mn, mun = (F, Q, M, mu) if carry is None else (F[nodes], Q[nodes], M[nodes], mu[nodes])
        P = np.array(np.broadcast_to(P0, (nodes.size, n, n)) if carry is None else P0[nodes])
        Wg, P, it, member, why = _stationary_point(P, Hw, mom, Fn, Qn, Mn, mun, per_node=carry is not None)
        if Wg is None:
            return StationaryCertificate(False, None, np.nan, np.nan, it, (
                f"the expected covariance did not settle in {STATIONARY_MAX} iterations" if member is None else
                f"the expected covariance grows without settling (node {int(nodes[member])})" if why is None else
                f"the expected covariance did not settle (node {int(nodes[member])}: {why})"), None)
        iterations = max(iterations, it)
        Phi[nodes], W[nodes] = P, Wg
    out = StationaryCertificate(True, Phi, np.nan, np.nan, iterations, None, None,
                                None if carry is None else carry.index,
                                None if carry is None else carried_positions(carry.index, design.carried_regions))
    if lmi:
        out = out._replace(lmi=_relay_lmi(Phi, W, F, Q, Hws, moments, M, mu))
    return out


def _relay_lmi(Phi: np.ndarray, W: np.ndarray, F, Q, Hws, moments, M, mu) -> dict:
    """Minimise Σ_i tr Φ_i subject to ``Φ_i ⪰ T_i(F Φ_i Fᵀ + Q)`` for the fixed gains ``W_i`` (n x G n; one n x n
    unknown per node; ``T_i`` written as an n² x n² matrix from its action on a basis), then the solution checked in
    NumPy.  ``Hws`` each node's whitened ball rows; ``F``, ``Q``, ``M``, ``mu`` shared, or one per node (its carried
    coordinates)."""
    import warnings

    import cvxpy as cp

    N, n = Phi.shape[0], Phi.shape[-1]
    rows = max(h.shape[0] for h in Hws)
    size = max(N * n**4, n**2 * rows**2)  # the maps of every node; one node's image of the basis through pair_sum
    if size > LMI_MAX_ENTRIES:
        return {"status": "not solved", "reason": f"its maps hold {size:.3g} numbers (N n⁴ = {N} x {n}⁴, n² r² = "
                f"{n}² x {rows}²) > {LMI_MAX_ENTRIES:.3g}", "trace": None, "max_residual": None}
    basis = np.eye(n * n).reshape(n * n, n, n)
    maps, consts = [], []
    own = F.ndim == 3  # one per node
    for i, mom in enumerate(moments):
        Hw = Hws[i]
        Fi, Qi = (F[i], Q[i]) if own else (F, Q)
        Hg, Sg, K0 = update_moments(Hw, mom, M[i] if own else M, mu[i] if own else mu)
        Q0 = _rows_to_groups(K0, Hw, Hg, mom.groups)
        Wi = W[i]

        def lin(X, Hw=Hw, Hg=Hg, mom=mom, Wi=Wi, Sg=Sg):  # the expected update's part linear in the prediction X
            C = X @ Sg
            return X - Wi @ np.swapaxes(C, -1, -2) - C @ Wi.T + Wi @ pair_sum(Hw, mom.A, X, Hg, mom.groups) @ Wi.T

        col = lin(Fi @ basis @ Fi.T)  # (n², n, n): the image of each basis matrix
        maps.append(col.reshape(n * n, n * n).T)  # vec (row-major) of T_i(F E F^T), one column per basis E
        consts.append(lin(Qi) + Wi @ Q0 @ Wi.T)
    P = [cp.Variable((n, n), symmetric=True) for _ in range(N)]
    cons = []
    for i in range(N):
        image = cp.reshape(maps[i] @ cp.vec(P[i], order="C"), (n, n), order="C")
        cons.append((P[i] - image + (P[i] - image).T) / 2 - consts[i] >> 0)
    prob = cp.Problem(cp.Minimize(sum(cp.trace(p) for p in P)), cons)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11, **SOLVER_SETTINGS)
    except cp.error.SolverError as exc:
        return {"status": "solver error", "reason": str(exc), "trace": None, "max_residual": None}
    if prob.status not in ("optimal", "optimal_inaccurate") or any(p.value is None for p in P):
        return {"status": str(prob.status), "reason": None, "trace": None, "max_residual": None}
    Pv = np.stack([0.5 * (p.value + p.value.T) for p in P])
    step = np.stack([(maps[i] @ Pv[i].reshape(-1)).reshape(n, n) + consts[i] for i in range(N)])
    resid = np.linalg.eigvalsh(0.5 * (step + np.swapaxes(step, -1, -2)) - Pv).max(axis=-1)
    top = np.maximum(np.linalg.eigvalsh(Pv).max(axis=-1), 1e-300)
    return {"status": str(prob.status), "reason": None, "trace": float(np.trace(Pv, axis1=-2, axis2=-1).sum()),
            "node_trace": [float(v) for v in np.trace(Pv, axis1=-2, axis2=-1)],
            "max_residual": float(resid.max()), "relative_residual": float((resid / top).max())}
