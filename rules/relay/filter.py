"""The relay filter: every node fuses the measurements of its L-hop ball in one update per step, batched over runs.

Each step every sensor's measurement is relayed over ``hops`` exchange rounds along its source's breadth-first tree
(``routing='tree'``, :func:`rules.relay.design.relay_routes`) or flooded, each node forwarding the first copy it gets
from any neighbour (``routing='flood'``), so that node ``i`` holds the step's measurements of every sensor within
``hops`` hops (its ball, :meth:`rules.relay.design.Routes.ball`) that arrived.  Node ``i`` at step ``k``::

    x̂⁻_i = f(x̂_i),   P⁻_i = F P_i Fᵀ + Q                              (F at its own estimate)
    W, P_i⁺ = rules.relay.design.relay_update(P⁻_i, Hw, moments_i, M, μ)    (the relay rule: one gain block per hop
                                                                        depth for whichever measurements arrive,
                                                                        designed for their expected arrivals and
                                                                        falsifications)
    x̂_i⁺ = x̂⁻_i + Σ_g W_g Σ_{a of depth g, arrived} H_aᵀ R_a⁻¹ (z̃_a - h_a(x̂⁻_i))

with ``Hw`` the whitened rows ``R_a^{-1/2} H_a(x̂⁻_i)`` of every sensor of its ball (its own first, then in the
order of :func:`rules.relay.design.node_moments`), ``H_a`` and ``h_a`` at the node's own prediction, angular residual
components wrapped (:func:`filters.consensus_batch.wrap_residuals`), and ``M = E[ξ ξᵀ]``, ``μ = E[ξ]`` of the
falsification's signal (:class:`designer.attacks.FDISignal`).  The node's own measurement always arrives and is
never falsified.

**Attacks** (:class:`filters.consensus_batch.EdgeAttacks`, one draw per channel and step for all rounds): pair ``p``
(sensor ``s``'s measurement at node ``i``, :class:`rules.relay.design.Routes`) arrives when the copy the routing takes
arrives (:meth:`rules.relay.design.Routes.realise`: along a tree, iff its channel is not lost to DoS and its parent pair
arrived; flooding, the first copy from any neighbour); it carries ``z_s + o_p`` with
``o_p = o_parent + fdi[k, channel_p] H_s(x̂⁻_sender) ξ[k, channel_p]``, parent, channel and sender those of the copy
taken (a falsified channel displaces what it forwards as if the state were displaced by its ``ξ``, ``H_s`` at the
forwarding node's prediction, as the scheduled filter falsifies a measurement).

**Messages**: ``2 |E| hops`` packets per step (one per directed channel and round, a packet lost to DoS counted);
delivered: the channels not lost to DoS times ``hops``.  **Divergence**: as the other batched filters, a run whose
prediction, estimate or covariance leaves finite numbers or exceeds :data:`filters.result.DIVERGED` at a node
stops there (NaN from that step, one ``'diverged'`` violation, :func:`filters.engine.run_batch`); the other runs
go on.

**How it is computed.**  The node moments are computed once (:func:`rules.relay.design.node_moments`, every node).
Each step, every sensor's ``h_s`` and ``H_s`` are evaluated once, at the predictions of every node of its ball
(the receivers and, among them, the forwarding nodes) over all runs; the values are kept in one flat array of
measurement rows laid out node by node (each node's rows contiguous, in its moments' order), so that the
arrivals and offsets are a pass over the rounds and each node's update takes a slice.  The nodes of one shape
(:func:`rules.relay.design.node_classes`) update in one :func:`rules.relay.design.relay_gain` over them and the runs.  A
run alone is a batch of one (the same numbers, tested).
"""
from __future__ import annotations

from typing import Mapping, NamedTuple, Sequence

import numpy as np

from designer.attacks import FDISignal
from designer.bounds import sqrtm_psd
from designer.design import ConsensusDesign, validate_design
from designer.model import Model
from designer.network import SensorNetwork
from designer.regions import Carried
from designer.validation import InputError, check_int

from filters.attacks import AttackPattern
from filters.consensus_batch import (PREDICTION_FIELDS, EdgeAttacks, batch_inputs, consensus_arrays, consensus_result,
                              edge_attacks, result_arrays, run_networks, wrap_residuals)
from filters.distributed import DistributedBatchResult, distributed_result
from filters.engine import Diagonal, Step, estimate_arrays, history, run_batch
from filters.node import NodeInputs, OwnRows, check_step, run_network
from filters.result import DIVERGED_REASON, FilterResult, diverged_nodes

from .design import (MAX_HOPS, RTOL, NodeMoments, Routes, moment_bytes, node_classes, relay_carried,
                     relay_gain, relay_moments, relay_routes)

__all__ = ["run_relay_batch", "run_relay_design", "RelayNode", "RelayNetwork"]


class _Layout(NamedTuple):
    """Where every measurement row of every node's ball lives in the flat row array of a step.

    A *slot* is one sensor's measurement at one node: slots ``0..N-1`` the nodes' own, slot ``N + p`` pair ``p``.
    Rows are laid out node by node (each node's own slot, then its pairs in pair order: the order of
    :func:`rules.relay.design.node_moments`), a slot of sensor ``s`` taking ``m_s`` consecutive rows."""

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
    node_of_row: np.ndarray  # (T,) the node (numbered as ``start``) whose ball each row belongs to


def _layout(model: Model, routes: Routes, nodes: Sequence[int] | None = None) -> _Layout:
    """The layout of every node's ball rows, or of the nodes ``nodes`` alone (a node filter's: its rows only, its
    nodes numbered 0.. in that order; the fields that route copies between nodes are then the network's
    restricted to these rows and only a node's own fusion may use them)."""
    N, P = routes.n_nodes, routes.n_pairs
    dims = np.asarray(model.sensor_dims, dtype=int)
    slot_sensor = np.concatenate([np.arange(N), routes.source])
    slot_node = np.concatenate([np.arange(N), routes.node])
    if nodes is not None:  # the chosen nodes' slots only, their nodes renumbered; the other slots have no rows
        local = np.full(N, -1)
        local[np.asarray(nodes, dtype=int)] = np.arange(len(nodes))
        slot_node = local[slot_node]
    keep = slot_node >= 0
    order = np.flatnonzero(keep)[np.argsort(slot_node[keep], kind="stable")]  # node by node: own slot first, pairs
    length = np.where(keep, dims[slot_sensor], 0)
    first = np.full(N + P, -1)
    first[order] = np.cumsum(length[order]) - length[order]
    T = int(length.sum())
    start = np.append(first[:N] if nodes is None else first[np.asarray(nodes, dtype=int)], T)
    comp = np.arange(T) - np.repeat(first[order], length[order])
    row_slot = np.repeat(order, length[order])
    offsets = model.sensor_offsets
    zcol = offsets[slot_sensor[row_slot]] + comp
    pair_rows = np.flatnonzero(row_slot >= N)
    pair_of_row = row_slot[pair_rows] - N
    sensor_slots = []
    pair_local = np.zeros(P, dtype=int)
    for s in range(model.n_sensors):
        pairs = np.flatnonzero(routes.source == s)
        slots = np.concatenate([[s], N + pairs])
        pair_local[pairs] = np.arange(1, slots.size)
        held = slots[keep[slots]]  # the slots of s among the chosen nodes' (all of them for the network)
        sensor_slots.append((slot_node[held], first[held][:, None] + np.arange(dims[s]),
                             pairs if nodes is None else pairs[:0]))
    angle_rows = np.flatnonzero(np.array([c in model.sensors[s].angles
                                          for s, c in zip(slot_sensor[row_slot], comp)], dtype=bool)) \
        if any(sen.angles for sen in model.sensors) else np.zeros(0, dtype=int)
    root = [sqrtm_psd(model.measurement_cov(s), inverse=True) for s in range(model.n_sensors)]
    scale = np.ones(T)  # R^{-1/2} of a scalar sensor's rows (1 for the others, whitened by blocks)
    scalar = dims[slot_sensor[row_slot]] == 1
    scale[scalar] = np.array([r[0, 0] for r in root])[slot_sensor[row_slot[scalar]]]
    whiten = []
    for m in sorted(set(dims.tolist()) - {1}):
        slots = np.flatnonzero(keep & (length == m))
        if slots.size:  # a node's ball may hold no sensor of this dimension
            whiten.append((first[slots][:, None] + np.arange(m), np.stack([root[s] for s in slot_sensor[slots]])))
    return _Layout(start, sensor_slots, pair_local, zcol, first, pair_rows, pair_of_row, comp[pair_rows], angle_rows,
                   None if np.all(scale == 1.0) else scale, whiten,
                   np.repeat(np.arange(start.size - 1), np.diff(start)))


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
                    signal: FDISignal | None = None, routing: str = "tree", regions=None) -> FilterResult:
    """The relay filter (module docstring) at every node over many runs of measurements ``z`` (runs, steps, n_z).

    Parameters
    ----------
    model, network : the model (sensor ``i`` at node ``i``) and the communication graph with its channels' DoS and
        FDI probabilities (the relay rule's moments are computed from them), or one network per run (one graph, e.g. a
        sweep's settings: the runs update together, each with its own network's moments).
    z : ndarray (runs, steps, n_z); ``z[:, k]`` measures ``x_{k+1}``.
    hops : int in 1..``rules.relay.design.MAX_HOPS``: relay hops (exchange rounds) per step.
    inputs : (steps, n_u) shared or (runs, steps, n_u), optional.
    attacks : :class:`filters.consensus_batch.EdgeAttacks` (runs, steps, channels), optional (none when omitted).
    x0, P0 : every node's initial estimate and covariance, (n_x,) / (n_x, n_x) or one per run (default the prior's).
    signal : :class:`designer.attacks.FDISignal`, the falsification the relay rule designs for (its ``E[ξ ξᵀ]`` and
        ``E[ξ]``); required when the network's channels carry FDI.
    routing : {'tree', 'flood'} (:data:`rules.relay.design.ROUTINGS`): which copy of a relayed measurement a node takes,
        its tree parent's (default) or the first to arrive from any neighbour (:meth:`rules.relay.design.Routes.realise`;
        the moments then by Monte Carlo, :func:`rules.relay.design.flood_moments`).
    regions : one sequence of state indices per node, optional: each node then carries only the states its region
        and its ball need (:func:`designer.regions.carried_states`), and its numbers on them are those of the
        whole-state filter (the dynamics and its ball's measurements never read the others).

    Returns :func:`filters.distributed.distributed_result` of the runs: ``cov`` each node's expected posterior
    covariance of the relay rule, ``detail`` a :class:`filters.distributed.DistributedBatchResult` (``iterations`` =
    ``hops``).  With ``regions``, ``carried`` (nodes, m) holds each node's carried states (``-1``: a place it does
    not use), ``cov`` is in those coordinates (nodes, m, m; zero in the unused places) and ``x`` is NaN at the states a
    node does not carry.
    """
    return distributed_result(_relay_runs(model, network, z, hops, inputs=inputs, attacks=attacks, x0=x0, P0=P0,
                                          signal=signal, routing=routing, regions=regions))


def _relay_runs(model: Model, network: SensorNetwork | Sequence[SensorNetwork], z: np.ndarray, hops: int, *,
                inputs=None, attacks: EdgeAttacks | Sequence[AttackPattern] | None = None, x0=None, P0=None,
                signal: FDISignal | None = None, routing: str = "tree", regions=None,
                predictions: bool = True, variances: bool = False) -> DistributedBatchResult:
    """The runs of :func:`run_relay_batch` (its parameters), as the distributed family's arrays; without
    ``predictions`` no record of the predictions' covariances (``P_pred`` None); with ``variances`` ``P_post`` a
    :class:`filters.engine.Diagonal` (its diagonals and finiteness over the steps).  ``network`` may be one network
    per run (:func:`filters.consensus_batch.run_networks`: one graph, e.g. a sweep's settings): the runs then
    update together, each with its own network's moments (:func:`_setting_classes`)."""
    z, u, x0, P0 = batch_inputs(model, z, inputs, x0, P0, "P0")
    runs, steps = z.shape[:2]
    network, nets = run_networks(network, runs)
    if network.n_nodes != model.n_sensors:
        raise InputError(f"network must be a SensorNetwork with one node per sensor ({model.n_sensors}), got "
                         f"{network.n_nodes}")
    hops = check_int("hops", hops, 1, MAX_HOPS)
    attacks = edge_attacks(network, attacks, runs, steps, model.n_x)
    settings, which = _settings(nets or [network])
    n, nx = network.n_nodes, model.n_x
    routes = relay_routes(network, hops, routing)
    lay = _layout(model, routes)
    carry = None if regions is None else relay_carried(model, routes, regions)
    classes, M, mu = _setting_classes(model, routes, settings, signal, carry)
    which = None if len(settings) == 1 else which
    if carry is None:
        out = estimate_arrays(runs, steps, n, nx, x0, P0, network.messages_per_step(hops), predictions=predictions,
                              variances=variances)
    else:
        m = carry.m
        out = estimate_arrays(runs, steps, n, m, np.zeros((runs, m)), np.zeros((runs, m, m)),
                              network.messages_per_step(hops), predictions=predictions, variances=variances)
        out["x_post"][:, 0] = carry.vector(np.broadcast_to(x0[:, None], (runs, n, nx)))
        out["P_post"][:, 0] = carry.matrix(np.broadcast_to(P0[:, None], (runs, n, nx, nx)))
    violations: list[list[dict]] = [[] for _ in range(runs)]

    def step(k, act, at):
        uk = u[k] if u.ndim == 2 else u[act, k][:, None, :]
        xp, Pp, xf = _predict(model, k, out["x_post"][act, k], out["P_post"][act, k], uk, carry,
                              None if carry is None else x0[act][:, None, :])
        bad = diverged_nodes(xp, Pp)  # a prediction beyond finite numbers stops its run before the update
        go = ~bad.any(axis=-1)
        x, P = np.full(xp.shape, np.nan), np.full(Pp.shape, np.nan)
        delivered = np.zeros(act.size, int)
        if go.any():
            g = act[go]
            if attacks is None:
                dos = fdi = xi = None
                delivered[go] = network.messages_per_step(hops)
            else:
                dos, fdi, xi = attacks.dos[g, k], attacks.fdi[g, k], attacks.xi[g, k]
                delivered[go] = (~dos).sum(axis=-1) * hops
            x[go], P[go] = _update(model, routes, lay, classes, M, mu, k, z[g, k], xp[go], Pp[go], dos, fdi, xi,
                                   carry, xf[go], None if which is None else which[g])
            bad[go] = diverged_nodes(x[go], P[go])
        return Step(dict(x_pred=xp, P_pred=Pp, delivered=delivered), dict(x_post=x, P_post=P), bad,
                    lambda j, node: DIVERGED_REASON if go[j] else "prediction: " + DIVERGED_REASON)

    run_batch(step, out, violations, steps, nan_from=("x_post", "P_post"), nan_before=("x_pred", "P_pred"))
    xs = {f: out[f] if carry is None else carry.full(out[f], np.nan) for f in ("x_post", "x_pred")}
    return DistributedBatchResult(xs["x_post"], out["P_post"], xs["x_pred"], history(out["P_pred"]), out["sent"],
                                  out["delivered"], violations, hops, None,
                                  None if carry is None else carry.index)


def _settings(nets: Sequence[SensorNetwork]) -> tuple[list[SensorNetwork], np.ndarray]:
    """The distinct channel settings of the runs' networks (equal DoS and FDI probabilities), in order of first use,
    and each run's index among them."""
    keys = [(net.dos_prob.tobytes(), net.fdi_prob.tobytes()) for net in nets]
    first = dict.fromkeys(keys)
    index = {key: i for i, key in enumerate(first)}
    distinct = [nets[keys.index(key)] for key in first]
    return distinct, np.array([index[key] for key in keys], dtype=int)


#: The moments of a node class that differ between channel settings (:func:`_setting_classes`); the others (its
#: ball's sensors, rows and depths) are the routes' alone.
_SETTING_FIELDS = ("p", "A", "F1", "F2")


def _setting_classes(model: Model, routes: Routes, settings: Sequence[SensorNetwork], signal, carry):
    """``(classes, M, μ)``: the node classes (:func:`rules.relay.design.node_classes`) of the channel settings
    ``settings`` (one graph) and the signal's moments (in each node's carried coordinates with ``carry``).  With one
    setting, its classes; with several, every class's :data:`_SETTING_FIELDS` stacked over the settings on a first
    axis (the classes' members and shapes are the routes', the same for every setting), so that the runs of all
    settings update in one call (a sweep's settings: one call a class and step in place of one per setting).  A
    setting without falsification has zero ``F1`` and ``F2`` (its moments), which add exact zeros where the signal's
    moments weigh them: its runs get the numbers they get alone (tested)."""
    for net in settings:  # the signal is the design's, the same for every setting: each checked against it
        M, mu = _check_signal(signal, net, model.n_x)
    if carry is not None:  # each node's moments of the signal on its own states
        M, mu = carry.matrix(M), carry.vector(mu)
    per = [node_classes([_lean(mom, M, mu) for mom in relay_moments(routes, net, model.sensor_dims)], free=True)
           for net in settings]
    if len(per) == 1:
        return per[0], M, mu
    classes = []
    for c, (nodes, mom) in enumerate(per[0]):
        shape = mom.A.shape
        stacked = {f: np.broadcast_to(0.0, (len(per),) + shape) if not any(np.any(getattr(p[c][1], f)) for p in per)
                   else np.stack([np.broadcast_to(getattr(p[c][1], f), getattr(mom, f).shape) for p in per])
                   for f in _SETTING_FIELDS}
        classes.append((nodes, mom._replace(**stacked)))
    return classes, M, mu


def _predict(model: Model, k: int, x, P, u, carry: Carried | None = None, fill=None):
    """Every node's prediction from its own estimate ``x`` (..., nodes, n_x) and covariance ``P``:
    ``(f(x), F P Fᵀ + Q, f(x))`` with ``F`` at the estimate (``u`` the step's known inputs, broadcast against ``x``).
    With ``carry`` ``x`` and ``P`` are in each node's carried coordinates (:class:`designer.regions.Carried`), the
    prediction too, and the third value is the prediction in the whole state's (the states a node does not carry
    at ``fill``, which its carried states' dynamics never read): where its ball's measurement functions are
    evaluated."""
    xf = x if carry is None else carry.full(x, fill)
    xp = model.f_expected(xf, k, u)
    F = model.F_expected(xf, k, u)
    Q = model.process_cov
    if carry is not None:
        xp, F, Q = carry.vector(xp), carry.matrix(F), carry.matrix(Q)
    with np.errstate(over="ignore", invalid="ignore"):  # a run beyond finite numbers stops just below
        Pp = model.propagate(F, P) + Q
        Pp = 0.5 * (Pp + np.swapaxes(Pp, -1, -2))
    return xp, Pp, (xp if carry is None else carry.full(xp, fill))


def _lean(mom: NodeMoments, M: np.ndarray, mu: np.ndarray) -> NodeMoments:
    """The moments a node keeps: ``F1`` only when the signal has a second moment, ``F2`` only when it has a mean
    (:func:`rules.relay.design.relay_update` weighs them by ``M`` and ``μ μᵀ``: a zero weight makes them irrelevant; at
    512 nodes and 8 hops each is ~150 MB)."""
    zero = np.broadcast_to(0.0, mom.A.shape)
    return mom._replace(F1=mom.F1 if np.any(M) else zero, F2=mom.F2 if np.any(mu) else zero)


def _update(model: Model, routes: Routes, lay: _Layout, classes: list, M, mu, k: int, zk, xp, Pp, dos, fdi, xi,
            carry: Carried | None = None, xf=None, which=None):
    """Every node's relay update at step ``k`` over the runs of the stacks ``zk`` (a, n_z), ``xp`` (a, N, n_x),
    ``Pp`` (a, N, n_x, n_x); ``dos``, ``fdi`` (a, E), ``xi`` (a, E, n_x) the step's attacks (None: none).  With
    ``carry``, ``xp`` and ``Pp`` are in the nodes' carried coordinates and ``xf`` is ``xp`` in the whole state's;
    ``which`` (a,) each run's channel setting where ``classes`` stack several (:func:`_setting_classes`)."""
    h, H = _ball_rows(model, lay, k, xp if carry is None else xf)
    values, arrived = _relayed(routes, lay, zk, H, dos, fdi, xi)
    if carry is not None:
        H = carry.columns(H, lay.node_of_row)
    return _fuse(lay, classes, M, mu, xp, Pp, h, H, values, arrived, which=which)


def _ball_rows(model: Model, lay: _Layout, k: int, xp):
    """``(h (a, T), H (a, T, n_x))``: every row of the layout's balls, each node's at its own prediction ``xp``
    (a, nodes, n_x) (what the node computes itself)."""
    a, _, nx = xp.shape
    T = int(lay.start[-1])
    H_rows = np.empty((a, T, nx))
    h = np.empty((a, T))
    for s, (nodes, rows, _) in enumerate(lay.sensor_slots):
        if not nodes.size:
            continue
        at = xp[:, nodes]  # (a, n_s, nx): the predictions of the nodes that hold s's measurement
        H_rows[:, rows] = model.H(s, at, k + 1)  # (a, n_s, m_s, nx)
        h[:, rows] = model.h(s, at, k + 1)
    return h, H_rows


def _relayed(routes: Routes, lay: _Layout, zk, H_rows, dos, fdi, xi):
    """What the step's relaying delivers to every node's rows (the network's part, simulated): ``(values (a, T),
    arrived (a, T))``, a row's value its sensor's measurement plus the displacement its copy took on falsified
    channels (``H_s`` at the forwarding node's prediction, from ``H_rows``, times the channel's ``ξ``)."""
    a, T = zk.shape[0], int(lay.start[-1])
    inj = np.zeros((a, T))
    rnd, parent, channel = routes.realise(np.ones((a, routes.incidence.shape[1]), dtype=bool)
                                          if dos is None else ~dos)
    for s, (nodes, rows, pairs) in enumerate(lay.sensor_slots):
        if fdi is not None and pairs.size:
            chan = channel[:, pairs]  # the falsified copies of every run: H_s at the forwarding node's prediction,
            r, q = np.nonzero((chan >= 0) & np.take_along_axis(fdi, np.maximum(chan, 0), axis=1))  # times ξ
            if r.size:
                par = parent[r, pairs[q]]
                sender = np.where(par < 0, 0, lay.pair_local[np.maximum(par, 0)])
                inj[r[:, None], rows[1 + q]] = (H_rows[r[:, None], rows[sender]] @ xi[r, chan[r, q], :, None])[..., 0]
    # the rounds in order (a pair after the pair it took its copy from): offsets per row, the parent's first
    offset = inj
    n = routes.n_nodes
    rr = rnd[:, lay.pair_of_row]  # (a, R) each pair row's arrival round (0: lost)
    pp = parent[:, lay.pair_of_row]
    parent_row = np.where(pp >= 0, lay.slot_first[n + np.maximum(pp, 0)] + lay.comp_of_row, -1)
    for r in range(2, routes.hops + 1):
        run, q = np.nonzero((rr == r) & (parent_row >= 0))
        if run.size:
            offset[run, lay.pair_rows[q]] += offset[run, parent_row[run, q]]
    arrived = np.ones((a, T), dtype=bool)
    arrived[:, lay.pair_rows] = rr > 0
    return zk[:, lay.zcol] + offset, arrived


def _fuse(lay: _Layout, classes: list, M, mu, xp, Pp, h, H_rows, values, arrived, rtol: float = RTOL, which=None):
    """Every node's relay update from what arrived at its rows (what the node computes itself): the residuals
    ``values - h`` (angles wrapped) and ``H_rows`` whitened by ``R^{-1/2}`` (in place), then per class of nodes
    :func:`rules.relay.design.relay_gain` (its pseudo-inverse cut at ``rtol``) and the update its gain makes of the
    residuals (in the ball's rows ``K_r G0 res``, the C node's way: :class:`rules.relay.design.RelayGain`; the
    n x G n gain itself is never formed there); ``which`` (a,) each run's setting where the classes stack several
    (:func:`_setting_classes`).  Returns ``(x, P)``."""
    Hw = H_rows
    res = values - h
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
    for members, stacked in classes:  # the nodes of one shape together (rules.relay.design.node_classes), in chunks
        r = stacked.groups.shape[0]  # whose r x r temporaries stay within CLASS_CHUNK numbers per run (chunks
        size = max(1, CLASS_CHUNK // (r * r))  # independent of the runs: a run alone gets the numbers of a batch)
        for c in range(0, members.size, size):
            nodes = members[c:c + size]
            mom = stacked._replace(**{f: getattr(stacked, f)[c:c + size] if which is None or f not in _SETTING_FIELDS
                                      else getattr(stacked, f)[which, c:c + size]
                                      for f in NodeMoments._fields if f != "groups"})
            rows = lay.start[nodes][:, None] + np.arange(r)  # (g, r): each node's rows
            dx, P[:, nodes] = _node_update(Pp[:, nodes], Hw[:, rows], mom, M if M.ndim == 2 else M[nodes],
                                           mu if mu.ndim == 1 else mu[nodes], res[:, rows], rtol, which is not None)
            x[:, nodes] = xp[:, nodes] + dx
    return x, P


#: The most numbers of one r x r temporary of a class's update per run (rules.relay.filter._update): one call per node
#: costs Python overhead at every step (a single run at 512 nodes: most of the design's time), a whole class at once
#: temporaries beyond the caches (5 runs at 512 nodes: slower than one call per node).  An assumption, chosen on the
#: 512-node grid (8 nodes of 150 rows per call).
CLASS_CHUNK = 200_000


def _node_update(Pp, Hw, mom, M, mu, res, rtol: float = RTOL, per_run: bool = False):
    """:func:`rules.relay.design.relay_gain` over the runs, and the update it makes of the whitened residuals ``res``
    (..., r) (zero where a row did not arrive): ``(W y, P⁺)`` (:meth:`rules.relay.design.RelayGain.correction`, ``y``
    the depths' information ``Σ_{arrived, depth g} Hwᵀ R^{-1/2} r``); a run where it breaks down (LinAlgError) gets
    NaN (and stops as diverged), the others their update.  ``per_run``: ``mom``'s :data:`_SETTING_FIELDS` have a
    first axis over the runs (their settings')."""
    try:
        gain, P = relay_gain(Pp, Hw, mom, M, mu, rtol)
        return gain.correction(Hw, mom, res), P
    except np.linalg.LinAlgError:
        dx, P = np.full(Pp.shape[:-1], np.nan), np.full(Pp.shape, np.nan)
        for r in range(Pp.shape[0]):
            own = mom._replace(**{f: getattr(mom, f)[r] for f in _SETTING_FIELDS}) if per_run else mom
            try:
                gain, P[r] = relay_gain(Pp[r], Hw[r], own, M, mu, rtol)
            except np.linalg.LinAlgError:
                continue
            dx[r] = gain.correction(Hw[r], own, res[r])
        return dx, P


def run_relay_design(model: Model, network: SensorNetwork | Sequence[SensorNetwork], z: np.ndarray,
                     design: ConsensusDesign, *, inputs=None,
                     attacks: EdgeAttacks | Sequence[AttackPattern] | None = None, x0=None,
                     phi0=None, predictions: bool = True, variances: bool = False) -> FilterResult:
    """The filter of a gain rule that relays (``design.rule``, :attr:`designer.rule.GainRule.relays`):
    the relay filter (:func:`run_relay_batch`) over ``design.rounds`` hops with the rule's routing, for the FDI signal
    the design was made for, with the parameters of :func:`filters.consensus_batch.run_consensus_batch`.

    Runs on networks of different channel probabilities (one network per run, e.g. a sweep's settings) are run in
    groups of equal probabilities, each with its own arrival and falsification moments.  The result's ``phi_post``
    is each node's expected posterior covariance of the relay rule (its bound, ``valid`` where finite; the
    linearisation remainders are not in it), ``predicted_mse`` its trace, ``C`` zero (no consensus on estimates),
    ``K`` NaN (a node's gain weighs its whole ball, not one measurement of its own: none is recorded) and the first
    column of ``gate_counts`` the packets delivered (channels not lost to DoS, times the hops): the ``detail`` of
    the :func:`filters.consensus_batch.consensus_result` it returns.  A design whose nodes carry their regions
    (``design.carried_regions``) gives ``carried`` and Φ, K and C in the carried coordinates
    (:func:`run_relay_batch`'s ``regions``).  Without ``predictions`` the detail has no ``phi_pred``, ``K`` nor
    ``C`` (None: :meth:`designer.rule.GainRule.batch_filter`); with ``variances`` Φ over the steps is kept as its
    diagonals alone (``phi_variances``, ``phi_post`` None: :func:`filters.consensus_batch.run_consensus_batch`).
    """
    z, u, x0, phi0 = batch_inputs(model, z, inputs, x0, phi0)
    runs, steps = z.shape[:2]
    first, nets = run_networks(network, runs)
    design = validate_design(design, model, first)
    rule = design.rule
    if not rule.relays:
        raise InputError(f"run_relay_design runs a gain rule that relays; got mode {design.mode!r}")
    attacks = edge_attacks(first, attacks, runs, steps, model.n_x)
    n, nx = first.n_nodes, model.n_x
    nets = nets or [first] * runs
    settings, which = _settings(nets)
    per = moment_bytes(first, model.sensor_dims, design.rounds)  # one setting's moments, at most
    size = max(1, int(SETTINGS_STACK_BYTES // max(per, 1)))
    groups = [np.flatnonzero((which >= b) & (which < b + size)) for b in range(0, len(settings), size)]
    out = None
    for idx in groups:  # the runs of a batch of channel settings (all of a sweep's but at scale), in order
        att = None if attacks is None else attacks._replace(dos=attacks.dos[idx], fdi=attacks.fdi[idx],
                                                             xi=attacks.xi[idx])
        res = _relay_runs(model, [nets[r] for r in idx], z[idx], design.rounds, inputs=u if u.ndim == 2 else u[idx],
                          attacks=att, x0=x0[idx], P0=phi0[idx], signal=design.fdi_signal, routing=rule.routing,
                          regions=design.carried_regions, predictions=predictions, variances=variances)
        own = dict(x_post=res.x_post, x_pred=res.x_pred, phi_post=res.P_post)
        if predictions:
            own["phi_pred"] = res.P_pred
        if out is None:  # C zero: no consensus on estimates (np.zeros: pages the system gives only when written)
            m = res.x_post.shape[-1] if res.carried is None else res.carried.shape[-1]  # the states a node carries
            if len(groups) == 1:  # one group: its arrays, not a copy of them
                given = own
            else:  # the groups' arrays gathered (carried ones m x m, not the whole state's)
                given = {} if res.carried is None else {"phi_post": (Diagonal((runs, steps + 1, n, m, m)) if variances
                                                                     else np.full((runs, steps + 1, n, m, m), np.nan)),
                                                        "phi_pred": np.full((runs, steps, n, m, m), np.nan)}
                given = {name: value for name, value in given.items() if name in own}
            gains = {} if not predictions else dict(C=np.zeros((runs, steps, n, m, m)),
                                                    K=np.full((runs, steps, n, m, max(model.sensor_dims)), np.nan))
            out = result_arrays(runs, steps, n, nx, max(model.sensor_dims), **gains, **given,
                                latest=() if predictions else PREDICTION_FIELDS, variances=variances)
            carried = res.carried
        if len(groups) > 1:
            for name, value in own.items():
                if isinstance(value, Diagonal):  # Φ's diagonals and finiteness over the steps
                    out[name].diagonal[idx], out[name].finite[idx] = value.diagonal, value.finite
                else:
                    out[name][idx] = value
        out["gate_counts"][idx, :, 0] = res.delivered_per_step
        for r, vs in zip(idx, res.violations):
            out["violations"][r] = vs
    phi = out["phi_post"]
    if isinstance(phi, Diagonal):
        out["valid"][:], out["predicted_mse"][:] = phi.finite, phi.diagonal.sum(axis=-1)
    else:
        out["valid"][:] = np.isfinite(phi).all(axis=(-2, -1))
        out["predicted_mse"][:] = np.trace(phi, axis1=-2, axis2=-1)
    return consensus_result(consensus_arrays(out)._replace(carried=carried), first, design)


#: The most bytes of node moments stacked over channel settings (:func:`_setting_classes`): the settings of a sweep
#: update together in batches of as many settings as fit (every one of a sweep on a grid of a hundred nodes; one
#: at a time on a 512-node grid at 8 hops, a few hundred MB each).  An assumption, chosen.
SETTINGS_STACK_BYTES = 256 * 2**20



class RelayNode(OwnRows):
    """The filter one node of a ``relay`` or ``flood`` design runs (gain rule ``local``), step by step.

    Its state is its estimate ``x`` and its expected covariance ``P`` (the relay rule's bound; the linearisation
    remainders are not in it).  It knows its model, its design's rounds, routing and the arrival and falsification
    moments of its ball (:func:`rules.relay.design.node_moments`: the sensors whose measurements reach it within the
    rounds, ``ball``, its own first), computed once here.  Each step (:meth:`step`)::

        x⁻, P⁻ = f(x), F P Fᵀ + Q                      (its own Jacobian at its own estimate)
        x, P   = the relay rule's update from its own measurement and the relayed ones that arrived

    with ``received`` = ``{sensor: value}`` for the sensors of its ball (other than its own) whose measurement
    reached it this step, each value as it arrived (falsified or not).  It needs nothing else: no neighbour's
    estimate, no channel record.  The numbers are those of :func:`run_relay_batch` at this node (the same
    functions on this node's rows; tested against the batch, bit for bit, through :class:`RelayNetwork`).

    A design whose nodes carry their regions (``design.carried_regions``, :mod:`designer.regions`) gives the node
    the states ``states`` only: ``x`` and ``P`` are in those coordinates (the batch's width ``m``, zero at a place
    ``states`` marks ``-1``).
    """

    def __init__(self, model: Model, network: SensorNetwork, design: ConsensusDesign, node: int, *, x0=None,
                 P0=None, routes: Routes | None = None, moments: Sequence[NodeMoments] | None = None,
                 carry: Carried | None = None):
        design = validate_design(design, model, network)
        rule = design.rule
        if not rule.relays:
            raise InputError(f"RelayNode runs a gain rule that relays (relay, flood); got mode {design.mode!r}")
        self.node = check_int("node", node, 0, network.n_nodes - 1)
        self.model = model
        routes = relay_routes(network, design.rounds, rule.routing) if routes is None else routes
        self.ball = routes.ball(self.node)
        self._lay = _layout(model, routes, [self.node])
        M, mu = _check_signal(design.fdi_signal, network, model.n_x)
        if design.carried_regions is not None:  # its own row of the network's carried states
            carry = relay_carried(model, routes, design.carried_regions) if carry is None else carry
            self._carry = Carried(carry.index[[self.node]], model.n_x)
            M, mu = self._carry.matrix(M), self._carry.vector(mu)
        else:
            self._carry = None
        #: the states it carries, in the order of ``x`` (``-1``: a place not used, where ``x`` and ``P`` hold 0)
        self.states = np.arange(model.n_x) if self._carry is None else self._carry.index[0]
        mom = (relay_moments(routes, network, model.sensor_dims) if moments is None else moments)[self.node]
        self._classes = node_classes([_lean(mom, M, mu)])
        self._M, self._mu = M, mu
        _, _, x0, P0 = batch_inputs(model, np.zeros((1, 1, model.n_z)), np.zeros((1, model.n_u)), x0, P0, "P0")
        self._fill = x0[0].copy()  # the states it does not carry, where its carried states' dynamics never look
        if self._carry is None:
            self.x, self.P = x0[0].copy(), P0[0].copy()
        else:
            self.x, self.P = self._carry.vector(x0[0])[0], self._carry.matrix(P0[0])[0]
        self.k = 0  # the steps taken: the next step measures the state at time k + 1
        #: the pseudo-inverse's cut of its update (relay_update's rtol): a double's; an export's float twin sets a
        #: float node's (rules.relay.design.FLOAT_RTOL)
        self.rtol = RTOL

    def step(self, z, received: Mapping[int, np.ndarray] | None = None, u=None) -> np.ndarray:
        """One step: predict, then fuse ``z`` (its own measurement) and the relayed measurements ``received``.
        Returns the new estimate (also ``self.x``; ``self.P`` its expected covariance)."""
        m, i = self.model, self.node
        chk = NodeInputs.of(self)
        z = chk.array("z", z, (m.sensor_dims[i],))
        received = chk.received("received", received, self.ball[1:].tolist(), f"in node {i}'s ball (the other "
                                "sensors whose measurements reach it)", "sensor")
        u = chk.inputs(u, m.n_u)
        T = int(self._lay.start[-1])
        values, arrived = np.zeros((1, T)), np.zeros((1, T), dtype=bool)
        row = 0
        for j, s in enumerate(self.ball):
            width = m.sensor_dims[s]
            v = z if j == 0 else received.get(int(s))
            if v is not None:
                if j:
                    v = chk.array(f"received[{s}]", v, (width,))
                values[0, row:row + width], arrived[0, row:row + width] = v, True
            row += width
        xp, Pp, xf = _predict(m, self.k, self.x[None, None], self.P[None, None], u, self._carry, self._fill)
        h, H = _ball_rows(m, self._lay, self.k, xf)
        if self._carry is not None:
            H = self._carry.columns(H, self._lay.node_of_row)
        x, P = _fuse(self._lay, self._classes, self._M, self._mu, xp, Pp, h, H, values, arrived, self.rtol)
        self.x, self.P = x[0, 0], P[0, 0]
        self.k += 1
        return self.x


class RelayNetwork:
    """Every node of a ``relay`` or ``flood`` design as a :class:`RelayNode`, driven over a run: each step the
    relaying is simulated from the step's channel attacks (which copy of every measurement reaches which node, what
    falsified channels add: :meth:`rules.relay.design.Routes.realise`, ``H_s`` at the forwarding node's prediction
    times ``ξ``), and every node steps with what reached it.  When a node diverges the run stops, as the batch stops
    it: NaN from then on."""

    stopped = False
    last = None

    def __init__(self, model: Model, network: SensorNetwork, design: ConsensusDesign, *, x0=None, P0=None):
        design = validate_design(design, model, network)
        rule = design.rule
        self.model, self.network = model, network
        self.routes = relay_routes(network, design.rounds, rule.routing)
        moments = relay_moments(self.routes, network, model.sensor_dims)
        self.carry = None if design.carried_regions is None else relay_carried(model, self.routes,
                                                                                design.carried_regions)
        self.nodes = [RelayNode(model, network, design, i, x0=x0, P0=P0, routes=self.routes, moments=moments,
                                carry=self.carry) for i in range(network.n_nodes)]
        self._lay = _layout(model, self.routes)

    def step(self, z, dos=None, fdi=None, xi=None, u=None) -> np.ndarray:
        """One step of every node: ``z`` (n_z,) the sensors' measurements, ``dos``, ``fdi`` (E,) and ``xi``
        (E, n_x) the step's attacks on the network's channels (:class:`filters.consensus_batch.EdgeAttacks` order;
        None: none).  Returns every node's estimate (N, n_x) (:meth:`estimates`)."""
        z, dos, fdi, xi, u = check_step(self, z, dos, fdi, xi, u)
        if not self.stopped:
            delivered = self.deliver(z, dos, fdi, xi, u)
            # a measurement relayed through a diverged node's prediction is not finite: the run stops there
            self.stopped = not all(np.isfinite(v).all() for _, got in delivered for v in got.values())
        if self.stopped:
            for nd in self.nodes:
                nd.k += 1
        else:
            for nd, (own, got) in zip(self.nodes, delivered):
                nd.step(own, got, u)
            self.last = (None, [delivered])  # as filters.node.NodeNetwork.last: what reached each node
            self.stopped = bool(diverged_nodes(np.stack([nd.x for nd in self.nodes]),
                                               np.stack([nd.P for nd in self.nodes])).any())
        if self.stopped:  # as the batch stops a run at a node's divergence: NaN from then on
            for nd in self.nodes:
                nd.x, nd.P = np.full_like(nd.x, np.nan), np.full_like(nd.P, np.nan)
        return self.estimates()

    def estimates(self) -> np.ndarray:
        """Every node's current estimate (N, n_x); NaN at the states a node does not carry (when the nodes carry
        their regions), as the batched filter reports them."""
        x = np.stack([nd.x for nd in self.nodes])
        return x if self.carry is None else self.carry.full(x, np.nan)

    def deliver(self, z, dos=None, fdi=None, xi=None, u=None) -> list[tuple[np.ndarray, dict]]:
        """What reaches every node at the next step (the arguments of :meth:`step`), without stepping: per node
        ``(its own measurement, {sensor: the relayed measurement that arrived}``)."""
        z, dos, fdi, xi, u = check_step(self, z, dos, fdi, xi, u)
        m = self.model
        k = self.nodes[0].k
        x = np.stack([nd.x for nd in self.nodes])[None]
        P = np.stack([nd.P for nd in self.nodes])[None]
        fill = None if self.carry is None else np.stack([nd._fill for nd in self.nodes])[None]
        _, _, xp = _predict(m, k, x, P, np.asarray(u, dtype=float).reshape(m.n_u) if m.n_u else np.zeros(0),
                            self.carry, fill)
        _, H = _ball_rows(m, self._lay, k, xp)  # what the forwarding nodes compute: the falsifications' H
        values, arrived = _relayed(self.routes, self._lay, np.asarray(z, dtype=float)[None], H,
                                   None if dos is None else np.asarray(dos)[None],
                                   None if fdi is None else np.asarray(fdi)[None],
                                   None if xi is None else np.asarray(xi)[None])
        dims = m.sensor_dims
        out = []
        for i, nd in enumerate(self.nodes):
            row, got = int(self._lay.start[i]), {}
            own = values[0, row:row + dims[i]]
            row += dims[i]
            for s in nd.ball[1:]:
                if arrived[0, row]:
                    got[int(s)] = values[0, row:row + dims[s]]
                row += dims[s]
            out.append((own, got))
        return out

    def run(self, z, attacks: AttackPattern | None = None, inputs=None) -> tuple[np.ndarray, np.ndarray]:
        """Every step of a run: ``z`` (K, n_z), ``attacks`` its channel attacks, ``inputs`` (K, n_u).  Returns
        ``(x (K + 1, N, n_x), P (K + 1, N, n_x, n_x))`` from the nodes' current state on."""
        return run_network(self, z, attacks, inputs)


