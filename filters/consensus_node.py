"""The node filters of the consensus gain rules ``paper`` and ``tuned``: one node's consensus EKF, in two phases.

A consensus node exchanges *estimates*, so each step has two phases (the batched filter of
:mod:`filters.consensus_batch` runs both for every node and run at once; here one node runs them)::

    packet = node.predict(u)                 x̂⁻_i = f(x̂_i), its bound Φ⁻_i by (26) when (28) holds
                                             (the EKF's F Φ Fᵀ + Q otherwise); it sends (x̂⁻_i, Φ⁻_i, ok)
    x̂_i = node.update(z, received, bounds)   x̂_i = x̂⁻_i + K_i (z_i - h_i(x̂⁻_i)) + C_i Σ_{j kept} (x̃_j - x̂⁻_i)
                                             and its bound Φ_i by (27) when (29) holds

``received`` maps each in-neighbour ``j`` whose packet arrived to the estimate it carried, ``x̃_j`` (falsified or
not: the node cannot tell); with a gate (``design.gate``) a packet failing the χ² test is dropped as if lost.
``bounds`` maps **every** in-neighbour to the packet it sent, for its ``Φ⁻_j`` and ``ok``: the bound (27) weighs
every neighbour's ``Φ⁻_j`` by its channel's arrival probability, whether this step's estimate arrived or not, so the
rule assumes a node learns its neighbours' bounds each step (a reliable side channel, an assumption of the rule as
published, stated in the gain rule's ``needs``); ``ok`` (the neighbour's prediction is a bound) decides whether this
node's update is a bound (``valid``).  The node's numbers are the batched filter's at that node, bit for bit (the
same functions, :func:`filters.consensus_batch.predict_nodes` and :func:`~filters.consensus_batch.update_nodes`, on
a block of one node; tested through :class:`ConsensusNetwork`).

:class:`ConsensusNetwork` drives every node over a run: each step every node predicts, the packets cross the
channels (DoS drops them, FDI adds ``ξ``: :func:`filters.channels.channel_packets`), and every node updates with
what reached it.  When one node's estimate leaves finite numbers (or :data:`filters.result.DIVERGED`), the
batched filter stops the whole run; so does the network (NaN from then on).
"""
from __future__ import annotations

from typing import Mapping, NamedTuple

import numpy as np

from designer.design import ConsensusDesign, validate_design
from designer.model import Model
from designer.network import SensorNetwork
from designer.validation import InputError, check_int

from .channels import channel_packets, gate_channels
from .consensus_batch import (Exchange, NodeRule, batch_inputs, first_step_error, node_groups, predict_nodes,
                              weighted_items, update_nodes)
from .node import NodeInputs, NodeNetwork, OwnRows

__all__ = ["Packet", "ConsensusNode", "ConsensusNetwork"]


class Packet(NamedTuple):
    """What a consensus node sends each step: its prediction ``x`` (n_x,), its covariance ``P`` (n_x, n_x) and
    ``ok``, whether ``P`` is a bound (its recursion held and it started from a bound)."""

    x: np.ndarray
    P: np.ndarray
    ok: bool


class ConsensusNode(OwnRows):
    """The filter node ``node`` runs for a ``paper`` or ``tuned`` design: :meth:`predict`, then :meth:`update`.

    Its state: its estimate ``x``, its covariance ``P`` (the bound Φ while ``valid``), ``proper`` (still on Theorem
    1's recursion: once (28) or (29) fails it runs the fallback for good), ``valid``, and with the tuned rule its
    weights per incoming channel.  It knows its model, its design (σ, β, τ, ε, U, V_i, δ, the gate), its
    in-neighbours ``senders`` (in channel order) and their channels' DoS and FDI probabilities.
    """

    def __init__(self, model: Model, network: SensorNetwork, design: ConsensusDesign, node: int, *, x0=None,
                 P0=None):
        design = validate_design(design, model, network)
        rule = design.rule.batch_filter()
        if not isinstance(rule, NodeRule):
            raise InputError(f"ConsensusNode runs a gain rule each node applies on its own over Theorem 1 (paper, "
                             f"tuned); got mode {design.mode!r}")
        i = self.node = check_int("node", node, 0, network.n_nodes - 1)
        self.model, self.design, self._rule = model, design, rule
        self.senders = np.flatnonzero(network.adjacency[i])  # its incoming channels, in the batch's order
        self.d_max = network.d_max
        self._degrees = network.degrees
        self._w_phi = 3.0 * (1.0 - network.dos_prob[i, self.senders])  # (27)'s weight of each neighbour's bound
        self._w_xi = (3.0 * design.delta**2 * (network.fdi_prob * network.adjacency).sum(axis=1))[i]
        self._group = node_groups(model, design, i)
        self._fixed = design.rule.fixed_multipliers
        if rule.weighted:
            d = self.senders.size
            self._slots = np.where(np.arange(self.d_max) < d, np.arange(self.d_max), -1)[None]
            self._q = network.falsified_prob[i, self.senders][None]
            self.weights = np.full(self.d_max + 2, np.nan)
        _, _, x0, P0 = batch_inputs(model, np.zeros((1, 1, model.n_z)), np.zeros((1, model.n_u)), x0, P0, "P0")
        self.x, self.P = x0[0].copy(), P0[0].copy()
        self.proper, self.valid, self.diverged = True, True, False
        self.k = 0  # the steps taken: the next step measures the state at time k + 1
        self._pred = None

    def predict(self, u=None) -> Packet:
        """The prediction phase of the next step: returns the packet this node sends (its prediction, its
        covariance and whether that is a bound)."""
        if self._pred is not None:
            raise InputError(f"node {self.node} has predicted step {self.k} already: call update(z, received, "
                             "bounds) next")
        m = self.model
        u = NodeInputs.of(self).inputs(u, m.n_u)
        prop = np.array([[self.proper]])
        xp, Pp, m28, sigma, pvalid, th2, limit = predict_nodes(m, self.design, self._rule.predict, self.k,
                                                               self.x[None, None], self.P[None, None], prop, u,
                                                               self.d_max)
        self._pred = (xp, Pp, bool(pvalid[0, 0]), prop)
        return Packet(xp[0, 0], Pp[0, 0], bool(pvalid[0, 0]) and self.valid)

    def update(self, z, received: Mapping[int, np.ndarray] | None, bounds: Mapping[int, Packet]) -> np.ndarray:
        """The update phase: ``z`` its own measurement, ``received`` ``{neighbour: x̃_j}`` the estimates that
        arrived, ``bounds`` ``{neighbour: Packet}`` every in-neighbour's packet as sent (its ``P`` and ``ok``).
        Returns the new estimate (also ``self.x``; ``self.P`` its covariance, a bound while ``self.valid``)."""
        if self._pred is None:
            raise InputError(f"node {self.node} must predict step {self.k} before its update: call predict(u) first")
        m, i, design = self.model, self.node, self.design
        xp, Pp, pvalid, prop = self._pred
        dim, nx = m.sensor_dims[i], m.n_x
        chk = NodeInputs.of(self)
        z = chk.array("z", z, (dim,))
        senders = self.senders.tolist()
        received = chk.received("received", received, senders, f"an in-neighbour of node {i}")
        bounds = chk.received("bounds", bounds, senders, f"an in-neighbour of node {i}")
        missing = [j for j in senders if j not in bounds]
        if missing:
            raise chk.refuse("bounds", f"must hold every in-neighbour's packet (node {i}: {senders}), missing "
                                       f"{missing[0]}")
        d = len(senders)
        arrived = np.array([[j in received for j in senders]], dtype=bool)
        packets = np.zeros((1, d, nx))
        Pn = np.zeros((1, d, nx, nx))
        nb_ok = True
        for e, j in enumerate(senders):
            if j in received:
                packets[0, e] = chk.array(f"received[{j}]", received[j], (nx,))
            Pn[0, e], = chk.packet(f"bounds[{j}]", bounds[j], (("P", (nx, nx)),), Packet)
            nb_ok = chk.flag(f"bounds[{j}].ok", bounds[j].ok) and nb_ok
        keep = arrived
        if design.gate and d:
            own = np.zeros(d, dtype=int)
            keep, _ = gate_channels(np.concatenate([xp[0], packets[0]])[None], own, np.arange(1, d + 1), arrived,
                                    None, None, 2.0 * (Pp[:, [0] * d] + Pn), design.gate)
        s = Exchange.node_sum(keep.astype(float))[:, None]  # the sums over its incoming channels, as the batch's
        innovation = Exchange.node_sum(keep[..., None] * packets)[:, None] - s[..., None] * xp
        neigh = Exchange.node_sum(self._w_phi[None, :, None, None] * Pn)[:, None] + self._w_xi * np.eye(nx)

        def extra(grp):
            if not self._rule.weighted:
                return {}
            return weighted_items(self._slots, keep, Pn, np.arange(d), self._q, self.weights[None, None], design)

        xn, P, K, C, m29, beta, uvalid, failed, reasons, weights = update_nodes(
            m, design, self._group, self._rule.update, self.k, xp, Pp, np.array([[pvalid]]), s, innovation, neigh,
            z[None], self._degrees, max(m.sensor_dims), extra)
        for _, gW, gok in weights:
            if gok[0, 0]:
                self.weights = gW[0, 0].copy()
        v28 = prop & ~np.array([[pvalid]])
        v29 = np.array([[pvalid]]) & ~uvalid
        if self.k == 0 and self._fixed and (v28.any() or v29.any()):
            raise first_step_error(0, v28, v29, self.P[None], Pp, design, nodes=[i])
        self.valid = bool(uvalid[0, 0]) and pvalid and self.valid and nb_ok
        self.proper = bool((prop & ~v28 & ~v29)[0, 0])
        self.diverged = bool(failed[0, 0])
        self.x, self.P = xn[0, 0], P[0, 0]
        self.K, self.C = K[0, 0, :, :dim], C[0, 0]
        self.k += 1
        self._pred = None
        return self.x


class ConsensusNetwork(NodeNetwork):
    """Every node of a ``paper`` or ``tuned`` design as a :class:`ConsensusNode`, driven over a run: each step every
    node predicts, the packets cross the channels (the step's DoS drops, FDI adds ``ξ``), every node updates with what
    reached it and every neighbour's bound."""

    def __init__(self, model: Model, network: SensorNetwork, design: ConsensusDesign, *, x0=None, P0=None):
        design = validate_design(design, model, network)
        self.model, self.network = model, network
        self.nodes = [ConsensusNode(model, network, design, i, x0=x0, P0=P0) for i in range(network.n_nodes)]

    def _exchange(self, z, dos, fdi, xi, u):
        packets = [nd.predict(u) for nd in self.nodes]
        if not self.sent_finite(packets):
            return packets, []
        delivered = self.deliver(packets, dos, fdi, xi)
        for nd, z_i, (got, bounds) in zip(self.nodes, z, delivered):
            nd.update(z_i, got, bounds)
        return packets, [delivered]

    def deliver(self, packets, dos=None, fdi=None, xi=None) -> list[tuple[dict, dict]]:
        """What the nodes' ``packets`` (one :class:`Packet` per node, as :meth:`ConsensusNode.predict` returned them)
        deliver to every node over the step's channels: per node ``({neighbour: x̃_j that arrived}, {neighbour: its
        packet})``, the arguments of :meth:`ConsensusNode.update`."""
        got = self.carry(packets, dos, fdi, xi, lambda nd, j, p, f, x: channel_packets(p.x, f, x))
        return [(g, {j: packets[j] for j in nd.senders.tolist()}) for nd, g in zip(self.nodes, got)]



