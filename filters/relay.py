"""The relay filter: every node fuses the measurements of its L-hop ball in one update per step, batched over runs.

Each step every sensor's measurement is relayed over ``hops`` exchange rounds along its source's breadth-first tree
(``routing='tree'``, :func:`designer.relay.relay_routes`) or flooded, each node forwarding the first copy it gets
from any neighbour (``routing='flood'``), so that node ``i`` holds the step's measurements of every sensor within
``hops`` hops (its ball, :meth:`designer.relay.Routes.ball`) that arrived.  Node ``i`` at step ``k``::

    x̂⁻_i = f(x̂_i),   P⁻_i = F P_i Fᵀ + Q                              (F at its own estimate)
    W, P_i⁺ = designer.relay.relay_update(P⁻_i, Hw, moments_i, M, μ)    (the relay rule: one gain block per hop
                                                                        depth for whichever measurements arrive,
                                                                        designed for their expected arrivals and
                                                                        falsifications)
    x̂_i⁺ = x̂⁻_i + Σ_g W_g Σ_{a of depth g, arrived} H_aᵀ R_a⁻¹ (z̃_a - h_a(x̂⁻_i))

with ``Hw`` the whitened rows ``R_a^{-1/2} H_a(x̂⁻_i)`` of every sensor of its ball (its own first, then in the
order of :func:`designer.relay.node_moments`), ``H_a`` and ``h_a`` at the node's own prediction, angular residual
components wrapped (:func:`filters.consensus_batch.wrap_residuals`), and ``M = E[ξ ξᵀ]``, ``μ = E[ξ]`` of the
falsification's signal (:class:`designer.attacks.FDISignal`).  The node's own measurement always arrives and is
never falsified.

**Attacks** (:class:`filters.consensus_batch.EdgeAttacks`, one draw per channel and step for all rounds): pair ``p``
(sensor ``s``'s measurement at node ``i``, :class:`designer.relay.Routes`) arrives when the copy the routing takes
arrives (:meth:`designer.relay.Routes.realise`: along a tree, iff its channel is not lost to DoS and its parent pair
arrived; flooding, the first copy from any neighbour); it carries ``z_s + o_p`` with
``o_p = o_parent + fdi[k, channel_p] H_s(x̂⁻_sender) ξ[k, channel_p]``, parent, channel and sender those of the copy
taken (a falsified channel displaces what it forwards as if the state were displaced by its ``ξ``, ``H_s`` at the
forwarding node's prediction, as the scheduled filter falsifies a measurement).

**Messages**: ``2 |E| hops`` packets per step (one per directed channel and round, a packet lost to DoS counted);
delivered: the channels not lost to DoS times ``hops``.  **Divergence**: as the other batched filters, a run whose
prediction, estimate or covariance leaves finite numbers or exceeds :data:`filters.consensus.DIVERGED` at a node
stops there (NaN from that step, one ``'diverged'`` violation, :func:`filters.result.stop_diverged`); the other runs
go on.

**How it is computed.**  The node moments are computed once (:func:`designer.relay.node_moments`, every node).
Each step, every sensor's ``h_s`` and ``H_s`` are evaluated once, at the predictions of every node of its ball
(the receivers and, among them, the forwarding nodes) over all runs; the values are kept in one flat array of
measurement rows laid out node by node (each node's rows contiguous, in its moments' order), so that the
arrivals and offsets are a pass over the rounds and each node's update takes a slice.  The nodes of one shape
(:func:`designer.relay.node_classes`) update in one :func:`designer.relay.relay_update` over them and the runs.  A
run alone is a batch of one (the same numbers, tested).
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from designer.attacks import FDISignal
from designer.design import ConsensusDesign, validate_design
from designer.gain_rules import gain_rule
from designer.model import Model
from designer.network import SensorNetwork
from designer.relay import (MAX_HOPS, NodeMoments, Routes, node_classes, relay_information, relay_moments,
                           relay_routes, relay_update)
from designer.scheduled import sqrtm_psd
from designer.validation import InputError, check_int

from .attacks import AttackPattern
from .consensus_batch import (ConsensusBatchResult, EdgeAttacks, batch_inputs, edge_attacks, register_filter,
                              result_arrays, run_networks, wrap_residuals)
from .distributed import DistributedBatchResult
from .result import DIVERGED_REASON, diverged_nodes, stop_diverged

__all__ = ["run_relay_batch", "run_relay_design"]


class _Layout(NamedTuple):
    """Where every measurement row of every node's ball lives in the flat row array of a step.

    A *slot* is one sensor's measurement at one node: slots ``0..N-1`` the nodes' own, slot ``N + p`` pair ``p``.
    Rows are laid out node by node (each node's own slot, then its pairs in pair order: the order of
    :func:`designer.relay.node_moments`), a slot of sensor ``s`` taking ``m_s`` consecutive rows."""

    start: np.ndarray  # (N + 1,) each node's first row (and the total number of rows)
    sensor_slots: list  # per sensor s: (its slots' nodes (n_s,), their rows (n_s, m_s), its pairs (pairs_s,))
    pair_local: np.ndarray  # (P,) each pair's index among its sensor's slots (the source's own slot is 0)
    zcol: np.ndarray  # (T,) each row's column of the stacked measurement z
    slot_first: np.ndarray  # (N + P,) each slot's first row
    pair_rows: np.ndarray  # the rows of the pairs (not a node's own measurement)
    pair_of_row: np.ndarray  # (len(pair_rows),) their pairs
    comp_of_row: np.ndarray  # (len(pair_rows),) their component within the measurement
    angle_rows: np.ndarray  # rows of angular components (wrapped)
    scale: np.ndarray | None  # (T,) R^{-1/2} of the rows of scalar sensors (1 elsewhere; None: all 1)
    whiten: list  # per sensor dimension m > 1: (the rows of its slots (n_m, m), R^{-1/2} of their sensors (n_m, m, m))


def _layout(model: Model, routes: Routes) -> _Layout:
    N, P = routes.n_nodes, routes.n_pairs
    dims = np.asarray(model.sensor_dims, dtype=int)
    slot_sensor = np.concatenate([np.arange(N), routes.source])
    slot_node = np.concatenate([np.arange(N), routes.node])
    order = np.argsort(slot_node, kind="stable")  # node by node: own slot (index i < N) first, pairs in pair order
    length = dims[slot_sensor]
    first = np.empty(N + P, dtype=int)
    first[order] = np.cumsum(length[order]) - length[order]
    T = int(length.sum())
    start = np.append(first[:N], T)
    comp = np.arange(T) - np.repeat(first[order], length[order])
    row_slot = np.repeat(order, length[order])
    offsets = np.concatenate([[0], np.cumsum(dims)])
    zcol = offsets[slot_sensor[row_slot]] + comp
    pair_rows = np.flatnonzero(row_slot >= N)
    pair_of_row = row_slot[pair_rows] - N
    sensor_slots = []
    pair_local = np.zeros(P, dtype=int)
    for s in range(model.n_sensors):
        pairs = np.flatnonzero(routes.source == s)
        slots = np.concatenate([[s], N + pairs])
        pair_local[pairs] = np.arange(1, slots.size)
        sensor_slots.append((slot_node[slots], first[slots][:, None] + np.arange(dims[s]), pairs))
    angle_rows = np.flatnonzero(np.array([c in model.sensors[s].angles
                                          for s, c in zip(slot_sensor[row_slot], comp)], dtype=bool)) \
        if any(sen.angles for sen in model.sensors) else np.zeros(0, dtype=int)
    root = [sqrtm_psd(model.measurement_cov(s), inverse=True) for s in range(model.n_sensors)]
    scale = np.ones(T)  # R^{-1/2} of a scalar sensor's rows (1 for the others, whitened by blocks)
    scalar = dims[slot_sensor[row_slot]] == 1
    scale[scalar] = np.array([r[0, 0] for r in root])[slot_sensor[row_slot[scalar]]]
    whiten = []
    for m in sorted(set(dims.tolist()) - {1}):
        slots = np.flatnonzero(length == m)
        whiten.append((first[slots][:, None] + np.arange(m), np.stack([root[s] for s in slot_sensor[slots]])))
    return _Layout(start, sensor_slots, pair_local, zcol, first, pair_rows, pair_of_row, comp[pair_rows], angle_rows,
                   None if np.all(scale == 1.0) else scale, whiten)


def _check_signal(signal, network: SensorNetwork, nx: int) -> tuple[np.ndarray, np.ndarray]:
    """``(M, μ)`` of the FDI signal the relay rule designs for (zero without FDI on the network)."""
    if signal is None:
        if np.any(network.fdi_prob > 0):
            raise InputError(f"signal: the network's channels are falsified (fdi_prob up to "
                             f"{float(network.fdi_prob.max()):g}) but no FDI signal was given; the relay rule "
                             "designs its gain for the signal's moments: pass a designer.FDISignal (e.g. the "
                             "scenario's resolved_attacks.signal)")
        return np.zeros((nx, nx)), np.zeros(nx)
    if not isinstance(signal, FDISignal):
        raise InputError(f"signal must be a designer.FDISignal or None, got {type(signal).__name__}")
    return signal.moment(nx), signal.mean(nx)


def run_relay_batch(model: Model, network: SensorNetwork, z: np.ndarray, hops: int, *, inputs=None,
                    attacks: EdgeAttacks | Sequence[AttackPattern] | None = None, x0=None, P0=None,
                    signal: FDISignal | None = None, routing: str = "tree") -> DistributedBatchResult:
    """The relay filter (module docstring) at every node over many runs of measurements ``z`` (runs, steps, n_z).

    Parameters
    ----------
    model, network : the model (sensor ``i`` at node ``i``) and the communication graph with its channels' DoS and
        FDI probabilities (the relay rule's moments are computed from them).
    z : ndarray (runs, steps, n_z); ``z[:, k]`` measures ``x_{k+1}``.
    hops : int in 1..``designer.relay.MAX_HOPS``: relay hops (exchange rounds) per step.
    inputs : (steps, n_u) shared or (runs, steps, n_u), optional.
    attacks : :class:`filters.consensus_batch.EdgeAttacks` (runs, steps, channels), optional (none when omitted).
    x0, P0 : every node's initial estimate and covariance, (n_x,) / (n_x, n_x) or one per run (default the prior's).
    signal : :class:`designer.attacks.FDISignal`, the falsification the relay rule designs for (its ``E[ξ ξᵀ]`` and
        ``E[ξ]``); required when the network's channels carry FDI.
    routing : {'tree', 'flood'} (:data:`designer.relay.ROUTINGS`): which copy of a relayed measurement a node takes,
        its tree parent's (default) or the first to arrive from any neighbour (:meth:`designer.relay.Routes.realise`;
        the moments then by Monte Carlo, :func:`designer.relay.flood_moments`).

    Returns a :class:`filters.distributed.DistributedBatchResult` (``iterations`` = ``hops``; ``P_post`` each node's
    expected posterior covariance of the relay rule).
    """
    if not isinstance(network, SensorNetwork) or network.n_nodes != model.n_sensors:
        raise InputError(f"network must be a SensorNetwork with one node per sensor ({model.n_sensors}), got "
                         f"{getattr(network, 'n_nodes', type(network).__name__)}")
    hops = check_int("hops", hops, 1, MAX_HOPS)
    z, u, x0, P0 = batch_inputs(model, z, inputs, x0, P0, "P0")
    runs, steps = z.shape[:2]
    attacks = edge_attacks(network, attacks, runs, steps, model.n_x)
    M, mu = _check_signal(signal, network, model.n_x)
    n, nx = network.n_nodes, model.n_x
    routes = relay_routes(network, hops, routing)
    lay = _layout(model, routes)
    classes = node_classes([_lean(mom, M, mu) for mom in relay_moments(routes, network, model.sensor_dims)],
                           free=True)
    x_post = np.full((runs, steps + 1, n, nx), np.nan)
    P_post = np.full((runs, steps + 1, n, nx, nx), np.nan)
    x_pred = np.full((runs, steps, n, nx), np.nan)
    P_pred = np.full((runs, steps, n, nx, nx), np.nan)
    x_post[:, 0], P_post[:, 0] = x0[:, None], P0[:, None]
    sent = np.full((runs, steps), network.messages_per_step(hops))
    delivered = np.zeros((runs, steps), int)
    violations: list[list[dict]] = [[] for _ in range(runs)]
    Q = model.process_cov
    act = np.arange(runs)
    for k in range(steps):
        if not act.size:
            break
        uk = u[k] if u.ndim == 2 else u[act, k][:, None, :]
        xk, Pk = x_post[act, k], P_post[act, k]
        xp = model.f_expected(xk, k, uk)
        F = model.F_expected(xk, k, uk)
        with np.errstate(over="ignore", invalid="ignore"):  # a run beyond finite numbers stops just below
            Pp = F @ Pk @ np.swapaxes(F, -1, -2) + Q
            Pp = 0.5 * (Pp + np.swapaxes(Pp, -1, -2))
        x_pred[act, k], P_pred[act, k] = xp, Pp
        go = stop_diverged(violations, act, diverged_nodes(xp, Pp), k + 1, "prediction: " + DIVERGED_REASON,
                           nan_before=(x_pred, P_pred))
        act, xp, Pp = act[go], xp[go], Pp[go]
        if not act.size:
            break
        if attacks is None:
            dos = fdi = xi = None
            delivered[act, k] = network.messages_per_step(hops)
        else:
            dos, fdi, xi = attacks.dos[act, k], attacks.fdi[act, k], attacks.xi[act, k]
            delivered[act, k] = (~dos).sum(axis=-1) * hops
        x, P = _update(model, routes, lay, classes, M, mu, k, z[act, k], xp, Pp, dos, fdi, xi)
        x_post[act, k + 1], P_post[act, k + 1] = x, P
        act = act[stop_diverged(violations, act, diverged_nodes(x, P), k + 1, nan_from=(x_post, P_post),
                                nan_before=(x_pred, P_pred))]
    return DistributedBatchResult(x_post, P_post, x_pred, P_pred, sent, delivered, violations, hops, None)


def _lean(mom: NodeMoments, M: np.ndarray, mu: np.ndarray) -> NodeMoments:
    """The moments a node keeps: ``F1`` only when the signal has a second moment, ``F2`` only when it has a mean
    (:func:`designer.relay.relay_update` weighs them by ``M`` and ``μ μᵀ``: a zero weight makes them irrelevant; at
    512 nodes and 8 hops each is ~150 MB)."""
    zero = np.broadcast_to(0.0, mom.A.shape)
    return mom._replace(F1=mom.F1 if np.any(M) else zero, F2=mom.F2 if np.any(mu) else zero)


def _update(model: Model, routes: Routes, lay: _Layout, classes: list, M, mu, k: int, zk, xp, Pp, dos, fdi, xi):
    """Every node's relay update at step ``k`` over the runs of the stacks ``zk`` (a, n_z), ``xp`` (a, N, n_x),
    ``Pp`` (a, N, n_x, n_x); ``dos``, ``fdi`` (a, E), ``xi`` (a, E, n_x) the step's attacks (None: none)."""
    a, n, nx = xp.shape
    T = int(lay.start[-1])
    Hw = np.empty((a, T, nx))
    h = np.empty((a, T))
    inj = np.zeros((a, T))
    rnd, parent, channel = routes.realise(np.ones((a, routes.incidence.shape[1]), dtype=bool)
                                          if dos is None else ~dos)
    for s, (nodes, rows, pairs) in enumerate(lay.sensor_slots):
        at = xp[:, nodes]  # (a, n_s, nx): the predictions of the nodes that hold s's measurement
        H = model.H(s, at, k + 1)  # (a, n_s, m_s, nx)
        h[:, rows] = model.h(s, at, k + 1)
        Hw[:, rows] = H  # whitened below
        if fdi is not None and pairs.size:
            chan = channel[:, pairs]  # the falsified copies of every run: H_s at the forwarding node's prediction,
            r, q = np.nonzero((chan >= 0) & np.take_along_axis(fdi, np.maximum(chan, 0), axis=1))  # times ξ
            if r.size:
                par = parent[r, pairs[q]]
                sender = np.where(par < 0, 0, lay.pair_local[np.maximum(par, 0)])
                inj[r[:, None], rows[1 + q]] = (H[r, sender] @ xi[r, chan[r, q], :, None])[..., 0]
    # the rounds in order (a pair after the pair it took its copy from): offsets per row, the parent's first
    offset = inj
    rr = rnd[:, lay.pair_of_row]  # (a, R) each pair row's arrival round (0: lost)
    pp = parent[:, lay.pair_of_row]
    parent_row = np.where(pp >= 0, lay.slot_first[n + np.maximum(pp, 0)] + lay.comp_of_row, -1)
    for r in range(2, routes.hops + 1):
        run, q = np.nonzero((rr == r) & (parent_row >= 0))
        if run.size:
            offset[run, lay.pair_rows[q]] += offset[run, parent_row[run, q]]
    arrived = np.ones((a, T), dtype=bool)
    arrived[:, lay.pair_rows] = rr > 0
    res = zk[:, lay.zcol] + offset - h
    if lay.angle_rows.size:
        res[:, lay.angle_rows] = wrap_residuals(res[:, lay.angle_rows], range(lay.angle_rows.size))
    if lay.scale is not None:  # R^{-1/2} of the scalar sensors' rows
        Hw *= lay.scale[:, None]
        res *= lay.scale
    for rows, root in lay.whiten:  # R^{-1/2} on the rows and the residuals of the other sensors' slots
        Hw[:, rows] = root @ Hw[:, rows]
        res[:, rows] = (root @ res[:, rows][..., None])[..., 0]
    res = np.where(arrived, res, 0.0)
    x = np.empty_like(xp)
    P = np.empty_like(Pp)
    for members, stacked in classes:  # the nodes of one shape together (designer.relay.node_classes), in chunks
        r = stacked.groups.shape[0]  # whose r x r temporaries stay within CLASS_CHUNK numbers per run (chunks
        size = max(1, CLASS_CHUNK // (r * r))  # independent of the runs: a run alone gets the numbers of a batch)
        for c in range(0, members.size, size):
            nodes = members[c:c + size]
            mom = stacked._replace(**{f: getattr(stacked, f)[c:c + size] for f in NodeMoments._fields
                                      if f != "groups"})
            rows = lay.start[nodes][:, None] + np.arange(r)  # (g, r): each node's rows
            Hc = Hw[:, rows]  # (a, g, r, nx)
            W, P[:, nodes] = _node_update(Pp[:, nodes], Hc, mom, M, mu)
            y = relay_information(Hc, mom, res[:, rows])  # (a, g, G nx): Σ_{arrived, depth g} Hwᵀ R^{-1/2} r
            x[:, nodes] = xp[:, nodes] + (W @ y[..., None])[..., 0]
    return x, P


#: The most numbers of one r x r temporary of a class's update per run (filters.relay._update): one call per node
#: costs Python overhead at every step (a single run at 512 nodes: most of the design's time), a whole class at once
#: temporaries beyond the caches (5 runs at 512 nodes: slower than one call per node).  An assumption, chosen on the
#: 512-node grid (8 nodes of 150 rows per call).
CLASS_CHUNK = 200_000


def _node_update(Pp, Hw, mom, M, mu):
    """:func:`designer.relay.relay_update` over the runs; a run where it breaks down (LinAlgError) gets NaN (and stops
    as diverged), the others their update."""
    try:
        return relay_update(Pp, Hw, mom, M, mu)
    except np.linalg.LinAlgError:
        n, G = Pp.shape[-1], mom.groups.shape[-1]
        W, P = np.full(Pp.shape[:-1] + (G * n,), np.nan), np.full(Pp.shape, np.nan)
        for r in range(Pp.shape[0]):
            try:
                W[r], P[r] = relay_update(Pp[r], Hw[r], mom, M, mu)
            except np.linalg.LinAlgError:
                pass
        return W, P


def run_relay_design(model: Model, network: SensorNetwork | Sequence[SensorNetwork], z: np.ndarray,
                     design: ConsensusDesign, *, inputs=None,
                     attacks: EdgeAttacks | Sequence[AttackPattern] | None = None, x0=None,
                     phi0=None) -> ConsensusBatchResult:
    """The filter of a gain rule that relays (``design.mode``, ``'relay'`` or ``'flood'``; :mod:`designer.gain_rules`):
    the relay filter (:func:`run_relay_batch`) over ``design.rounds`` hops with the rule's routing, for the FDI signal
    the design was made for, with the parameters of :func:`filters.consensus_batch.run_consensus_batch`.

    Runs on networks of different channel probabilities (one network per run, e.g. a sweep's settings) are run in
    groups of equal probabilities, each with its own arrival and falsification moments.  The result's ``phi_post``
    is each node's expected posterior covariance of the relay rule (its bound, ``valid`` where finite; the
    linearisation remainders are not in it), ``predicted_mse`` its trace, ``C`` zero (no consensus on estimates),
    ``K`` NaN (a node's gain weighs its whole ball, not one measurement of its own: none is recorded) and the first
    column of ``gate_counts`` the packets delivered (channels not lost to DoS, times the hops).
    """
    z, u, x0, phi0 = batch_inputs(model, z, inputs, x0, phi0)
    runs, steps = z.shape[:2]
    first, nets = run_networks(network, runs)
    design = validate_design(design, model, first)
    rule = gain_rule(design.mode)
    if not rule.relays:
        raise InputError(f"run_relay_design runs a gain rule that relays; got mode {design.mode!r}")
    attacks = edge_attacks(first, attacks, runs, steps, model.n_x)
    n, nx = first.n_nodes, model.n_x
    out = result_arrays(runs, steps, n, nx, max(model.sensor_dims))
    nets = nets or [first] * runs
    keys = [(net.dos_prob.tobytes(), net.fdi_prob.tobytes()) for net in nets]
    for key in dict.fromkeys(keys):  # each group of runs with the same channel probabilities, in order
        idx = np.array([r for r, k in enumerate(keys) if k == key])
        att = None if attacks is None else attacks._replace(dos=attacks.dos[idx], fdi=attacks.fdi[idx],
                                                             xi=attacks.xi[idx])
        res = run_relay_batch(model, nets[idx[0]], z[idx], design.rounds, inputs=u if u.ndim == 2 else u[idx],
                              attacks=att, x0=x0[idx], P0=phi0[idx], signal=design.fdi_signal, routing=rule.routing)
        out["x_post"][idx], out["x_pred"][idx] = res.x_post, res.x_pred
        out["phi_post"][idx], out["phi_pred"][idx] = res.P_post, res.P_pred
        out["gate_counts"][idx, :, 0] = res.delivered_per_step
        for r, vs in zip(idx, res.violations):
            out["violations"][r] = vs
    out["C"][:] = 0.0
    out["valid"][:] = np.isfinite(out["phi_post"]).all(axis=(-2, -1))
    out["predicted_mse"][:] = np.trace(out["phi_post"], axis1=-2, axis2=-1)
    return ConsensusBatchResult(**out)


register_filter("relay", run_relay_design)  # the filters of gain rules 'relay' and 'flood' (filters.consensus_batch)
register_filter("flood", run_relay_design)
