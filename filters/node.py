"""Node filters: the filter one sensor node runs, one step at a time, with only what the node has.

The studies run a design's filter at every node of a network over many runs at once (:mod:`filters.relay`,
:mod:`filters.scheduled`, ...).  A *node filter* is the same computation for one node, fed one step at a time with
what the node itself observes: its own measurement and the packets that reached it, with what they carried.  It is
what a researcher drives with a testbed's data, and what ``cfdesign export`` turns into C.  A *node network* drives
every node of a network over a recorded or simulated run: it simulates the exchange of each step from the run's
channel attacks and steps every node with what reached it; its numbers are the batched filter's, bit for bit.

A gain rule's node filter is registered here by the module of its filter (:func:`register_node_filter`); today
``relay`` and ``flood`` (:class:`filters.relay.RelayNode`, :class:`filters.relay.RelayNetwork`: one ``step(z,
received, u)`` with the relayed measurements) and ``paper`` and ``tuned`` (:class:`filters.consensus_node.ConsensusNode`,
:class:`filters.consensus_node.ConsensusNetwork`: two phases, ``predict(u)`` gives the packet the node sends,
``update(z, received, bounds)`` takes what arrived) and ``scheduled`` (:class:`filters.scheduled.ScheduledNode`,
:class:`filters.scheduled.ScheduledNetwork`: ``predict(z, u)``, ``update(received)``, then ``round(received)`` for its
exchange rounds 2..L).  Asking for the node filter of another rule (``mse``: an oracle) raises
:class:`designer.validation.InputError` saying why.
"""
from __future__ import annotations

import importlib
from typing import Any

import numpy as np

from designer.design import ConsensusDesign
from designer.gain_rules import gain_rule
from designer.validation import InputError, check_int

__all__ = ["register_node_filter", "node_rules", "node_filter", "node_network", "run_network"]

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
