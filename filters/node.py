"""Node filters: the filter one sensor node runs, one step at a time, with only what the node has.

The studies run a design's filter at every node of a network over many runs at once (:mod:`filters.relay`,
:mod:`filters.scheduled`, ...).  A *node filter* is the same computation for one node, fed one step at a time with
what the node itself observes: its own measurement and the packets that reached it, with what they carried.  It is
what a researcher drives with a testbed's data, and what ``cfdesign export`` turns into C.  A *node network* drives
every node of a network over a recorded or simulated run: it simulates the exchange of each step from the run's
channel attacks and steps every node with what reached it; its numbers are the batched filter's, bit for bit.

A gain rule's node filter is registered here by the module of its filter (:func:`register_node_filter`):

* ``relay``, ``flood`` (:class:`filters.relay.RelayNode`, :class:`filters.relay.RelayNetwork`): one ``step(z,
  received, u)`` with the relayed measurements;
* ``paper``, ``tuned`` (:class:`filters.consensus_node.ConsensusNode`, ``ConsensusNetwork``): two phases,
  ``predict(u)`` gives the packet the node sends, ``update(z, received, bounds)`` takes what arrived;
* ``scheduled`` (:class:`filters.scheduled.ScheduledNode`, ``ScheduledNetwork``): ``predict(z, u)``,
  ``update(received)``, then ``round(received)`` for its exchange rounds 2..L.

Asking for the node filter of another rule (``mse``: an oracle) raises :class:`designer.validation.InputError` saying
why.  The baselines KCF and HCMCI have node filters too (:class:`filters.distributed.KCFNode`,
:class:`filters.distributed.HCMCINode`), by name through :func:`studies.node_filter`.  :class:`NodeNetwork` is what
the networks that exchange packets share: the step, the delivery over the attacked channels, the stop at a divergence.
"""
from __future__ import annotations

import importlib
from typing import Any

import numpy as np

from designer.design import ConsensusDesign
from designer.gain_rules import gain_rule
from designer.validation import InputError, check_int

__all__ = ["register_node_filter", "node_rules", "node_filter", "node_network", "run_network", "NodeNetwork"]

_NODE_FILTERS: dict[str, tuple[type, type]] = {}
# the modules that register the built-in rules' node filters (imported late: they import this one)
_MODULES = ("filters.relay", "filters.consensus_node", "filters.scheduled")


def register_node_filter(rule: str, node: type, network: type) -> None:
    """Register the node filter of gain rule ``rule``: ``node(model, network, design, i, *, x0, P0)`` one node's,
    with ``step(z, received, u)``, and ``network(model, network, design, *, x0, P0)`` every node's, with ``step`` and
    ``run``."""
    gain_rule(rule, "rule")
    if rule in _NODE_FILTERS:
        raise InputError(f"gain rule {rule!r} has a node filter already")
    _NODE_FILTERS[rule] = (node, network)


def node_rules() -> tuple[str, ...]:
    """The gain rules that have a node filter."""
    for module in _MODULES:
        importlib.import_module(module)
    return tuple(_NODE_FILTERS)


def _classes(design: ConsensusDesign) -> tuple[type, type]:
    rules = node_rules()
    rule = gain_rule(design.mode)
    if rule.runtime == "global":
        raise InputError(f"gain rule {rule.name!r} has no node filter: it is an oracle, its gains need the joint state "
                         "of the network, which no node has (a reference, not a design to deploy)")
    if rule.name not in _NODE_FILTERS:
        raise InputError(f"gain rule {rule.name!r} has no node filter yet (node filters: {', '.join(rules)}); its "
                         "filter runs in the studies and in cfdesign filter")
    return _NODE_FILTERS[rule.name]


def node_filter(model, network, design: ConsensusDesign, node: int, **kw: Any):
    """The filter node ``node`` of ``network`` runs for ``design`` (its gain rule's registered node filter)."""
    check_int("node", node, 0, network.n_nodes - 1)
    return _classes(design)[0](model, network, design, node, **kw)


def node_network(model, network, design: ConsensusDesign, **kw: Any):
    """Every node of ``network`` as the node filters of ``design``, to drive over a run (``run``) or a step at a
    time (``step``)."""
    return _classes(design)[1](model, network, design, **kw)


def run_network(net, z, attacks=None, inputs=None):
    """Every step of a run through a node network ``net`` (its ``nodes`` with ``x`` and ``P``, its ``step(z, dos, fdi,
    xi, u)``): ``z`` (K, n_z), ``attacks`` the run's :class:`filters.attacks.AttackPattern`, ``inputs`` (K, n_u).
    Returns ``(x (K + 1, N, n_x), P (K + 1, N, n_x, n_x))`` from the nodes' current state on."""
    from .consensus_batch import edge_attacks

    z = np.asarray(z, dtype=float)
    K = z.shape[0]
    att = edge_attacks(net.network, None if attacks is None else [attacks], 1, K, net.model.n_x)
    xs = [np.stack([nd.x for nd in net.nodes])]
    Ps = [np.stack([nd.P for nd in net.nodes])]
    for k in range(K):
        e = (None, None, None) if att is None else (att.dos[0, k], att.fdi[0, k], att.xi[0, k])
        xs.append(net.step(z[k], *e, u=None if inputs is None else inputs[k]))
        Ps.append(np.stack([nd.P for nd in net.nodes]))
    return np.stack(xs), np.stack(Ps)


class NodeNetwork:
    """Every node's filter of a network driven a step at a time (the consensus, scheduled, KCF and HCMCI networks):
    a subclass holds ``model``, ``network``, ``nodes`` (each with ``x``, ``P``, ``k``, ``diverged``) and exchanges one
    step in ``_exchange(z, dos, fdi, xi, u)`` (``z`` each node's own measurement), which returns what was sent and
    delivered: ``last`` after a step, ``(sent, deliveries)``, the packets each node sent first and, per exchange
    round, what reached each node (its ``deliver``'s output; what a replay of the step feeds each node).  When a node
    diverges the run stops, as the batched filters stop it: NaN from then on."""

    stopped = False
    last = None

    def step(self, z, dos=None, fdi=None, xi=None, u=None) -> np.ndarray:
        """One step of every node: ``z`` (n_z,) every sensor's measurement, ``dos``, ``fdi`` (E,) and ``xi`` (E, n_x)
        the step's attacks on the network's channels (:class:`filters.consensus_batch.EdgeAttacks` order; None:
        none).  Returns every node's estimate (N, n_x)."""
        if self.stopped:
            for nd in self.nodes:
                nd.k += 1
        else:
            offsets = np.concatenate([[0], np.cumsum(self.model.sensor_dims)])
            z = np.asarray(z, dtype=float)
            self.last = self._exchange([z[offsets[i]:offsets[i + 1]] for i in range(len(self.nodes))], dos, fdi,
                                       xi, u)
            if any(nd.diverged for nd in self.nodes):
                self.stopped = True
                for nd in self.nodes:
                    nd.x, nd.P = np.full_like(nd.x, np.nan), np.full_like(nd.P, np.nan)
        return np.stack([nd.x for nd in self.nodes])

    def run(self, z, attacks=None, inputs=None):
        """Every step of a run (:func:`run_network`): ``(x (K + 1, N, n_x), P (K + 1, N, n_x, n_x))``."""
        return run_network(self, z, attacks, inputs)

    def carry(self, sent, dos, fdi, xi, falsified) -> list[dict]:
        """What ``sent`` (one packet per node) delivers over the step's channels, node by node (receiver-major, each
        node's in-neighbours ``senders`` in order, as :class:`filters.consensus_batch.EdgeAttacks`): ``{sender: the
        packet as it arrived}``, a packet lost to ``dos`` left out, ``falsified(receiver, sender, packet, fdi, xi)``
        what channel ``e`` makes of it (``fdi[e]``, ``xi[e]``; None without attacks)."""
        out, e = [], 0
        for nd in self.nodes:
            got = {}
            for j in nd.senders.tolist():
                if dos is None or not dos[e]:
                    got[j] = falsified(nd, j, sent[j], None if fdi is None else fdi[e],
                                       None if xi is None else xi[e])
                e += 1
            out.append(got)
        return out
