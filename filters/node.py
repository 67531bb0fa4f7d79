"""Node filters: the filter one sensor node runs, one step at a time, with only what the node has.

The studies run a design's filter at every node of a network over many runs at once (:mod:`rules.relay.filter`,
:mod:`rules.scheduled.filter`, ...).  A *node filter* is the same computation for one node, fed one step at a time with
what the node itself observes: its own measurement and the packets that reached it, with what they carried.  It is
what a researcher drives with a testbed's data, and what ``cfdesign export`` turns into C.  A *node network* drives
every node of a network over a recorded or simulated run: it simulates the exchange of each step from the run's
channel attacks and steps every node with what reached it; its numbers are the batched filter's, bit for bit.

A design's node filter is its gain rule's (``design.rule.node_filter()``, :mod:`rules`), e.g.

* one ``step(z, received, u)`` with the relayed measurements (:class:`rules.relay.filter.RelayNode`,
  :class:`rules.relay.filter.RelayNetwork`);
* two phases, ``predict(u)`` gives the packet the node sends, ``update(z, received, bounds)`` takes what arrived
  (:class:`filters.consensus_node.ConsensusNode`, ``ConsensusNetwork``);
* ``predict(z, u)``, ``update(received)``, then ``round(received)`` for its exchange rounds 2..L
  (:class:`rules.scheduled.filter.ScheduledNode`, ``ScheduledNetwork``).

Asking for the node filter of a rule that has none (an oracle) raises :class:`designer.validation.InputError` saying
why.  The baselines KCF and HCMCI have node filters too (:class:`filters.distributed.KCFNode`,
:class:`filters.distributed.HCMCINode`), by name through :func:`studies.node_filter`.  :class:`NodeNetwork` is what
the networks that exchange packets share: the step, the delivery over the attacked channels, the stop at a divergence.

Every public method of a node filter and of a network checks what it is given before it computes (:class:`NodeInputs`,
one place for all of them): finite numbers of the right shape (a measurement of the node's sensor, the model's
inputs, each packet's arrays), the keys of ``received`` among the node's in-neighbours (or its ball's sensors), flags
that are flags, and the phases' order; a refusal is an :class:`designer.validation.InputError` naming the argument,
the node and the step (``z of node 3 at step 7 must be 2 finite numbers, got [nan, 1.0]``) and leaves the node as
it was (its state, its step, its phase), so that the next call gives what it would have given without the refused
one.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from designer.design import ConsensusDesign
from designer.validation import InputError, check_int

__all__ = ["node_filter", "node_network", "run_network", "NodeNetwork",
           "NodeInputs", "OwnRows", "check_step"]

def node_filter(model, network, design: ConsensusDesign, node: int, **kw: Any):
    """The filter node ``node`` of ``network`` runs for ``design`` (its gain rule's node filter)."""
    check_int("node", node, 0, network.n_nodes - 1)
    return design.rule.node_filter()[0](model, network, design, node, **kw)


def node_network(model, network, design: ConsensusDesign, **kw: Any):
    """Every node of ``network`` as the node filters of ``design``, to drive over a run (``run``) or a step at a
    time (``step``)."""
    return design.rule.node_filter()[1](model, network, design, **kw)


def _shown(value) -> str:
    """``value`` as a refusal shows it: its numbers when few, else its shape or its type."""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError):  # ragged nesting
        arr = None
    if arr is None or arr.dtype.kind not in "biuf":
        text = repr(value)
        return f"{type(value).__name__} {text if len(text) <= 60 else text[:57] + '...'}"
    if arr.size > 8:
        return f"an array of shape {arr.shape}"
    return repr(arr.tolist())


def _numbers(shape: tuple) -> str:
    if len(shape) == 1:
        return f"{shape[0]} finite number{'s' if shape[0] != 1 else ''}"
    return "a " + "x".join(map(str, shape)) + " array of finite numbers"


class OwnRows:
    """What every node filter has (its ``model`` and ``node``): ``rows``, its own sensor's rows of a run's stacked
    measurement, so that ``z[k, node.rows]`` is what it measures at step k (:meth:`designer.model.Model.sensor_rows`:
    node ``i`` owns sensor ``i``)."""

    @property
    def rows(self) -> slice:
        return self.model.sensor_rows(self.node)


class NodeInputs:
    """What a node filter (or a network of them) is given, checked: every method names the argument and says where
    (``where``: ``'of node 3 at step 7'``) in the :class:`designer.validation.InputError` it raises, and returns the
    value as the filter uses it.  Cheap: a conversion and one ``isfinite`` per array."""

    __slots__ = ("where",)

    def __init__(self, where: str):
        self.where = where

    @classmethod
    def of(cls, node) -> "NodeInputs":
        """The checks of a node filter ``node`` (its ``node`` and ``k``) at its current step."""
        return cls(f"of node {node.node} at step {node.k}")

    def refuse(self, name: str, what: str) -> InputError:
        """The error for argument ``name``: ``'{name} {where} {what}'``."""
        return InputError(f"{name} {self.where} {what}")

    def array(self, name: str, value, shape: tuple) -> np.ndarray:
        """``value`` as a float array of ``shape``, every number finite (a single number for shape ``(1,)``);
        booleans, text, None and NaN or infinity are refused."""
        try:
            arr = np.asarray(value)
            ok = arr.dtype.kind in "iuf"
        except (TypeError, ValueError):
            ok = False
        if ok:
            if arr.shape != shape and not (arr.ndim == 0 and shape == (1,)):
                ok = False
            else:
                arr = arr.astype(float, copy=False).reshape(shape)
                ok = bool(np.isfinite(arr).all())
        if not ok:
            raise self.refuse(name, f"must be {_numbers(shape)}, got {_shown(value)}")
        return arr

    def inputs(self, u, n_u: int) -> np.ndarray:
        """The model's known inputs ``u`` (n_u,): None or empty when the model has none."""
        if n_u == 0:
            if u is not None and np.size(u) != 0:
                raise self.refuse("u", f"must be None or empty (the model has no known inputs), got {_shown(u)}")
            return np.zeros(0)
        if u is None:
            raise self.refuse("u", f"must be the model's {n_u} known input{'s' if n_u != 1 else ''}, got None")
        return self.array("u", u, (n_u,))

    def flags(self, name: str, value, n: int) -> np.ndarray | None:
        """``n`` flags (booleans, or 0 and 1) as a boolean array; None stays None (no attack)."""
        if value is None:
            return None
        try:
            arr = np.asarray(value)
            ok = arr.shape == (n,) and (arr.dtype.kind == "b" or (arr.dtype.kind in "iuf" and bool(
                np.isin(arr, (0, 1)).all())))
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise self.refuse(name, f"must be {n} flags (True/False, one per channel), got {_shown(value)}")
        return arr.astype(bool, copy=False)

    def flag(self, name: str, value) -> bool:
        """One flag: a boolean (Python's or NumPy's)."""
        if not isinstance(value, (bool, np.bool_)):
            raise self.refuse(name, f"must be True or False, got {_shown(value)}")
        return bool(value)

    def received(self, name: str, received, known, of: str, noun: str = "node") -> dict:
        """``received`` as a dict (None: empty), its keys among ``known`` (the node's in-neighbours, or the sensors of
        its ball; ``of`` says which, e.g. ``'an in-neighbour of node 1'``, ``noun`` what a key names)."""
        if received is None:
            return {}
        if not isinstance(received, Mapping):
            raise self.refuse(name, f"must be a dict {{{noun}: what arrived}}, got {_shown(received)}")
        known = list(known)
        for j in received:
            if isinstance(j, (bool, np.bool_)) or not isinstance(j, (int, np.integer)) or j not in known:
                raise self.refuse(name, f"holds {noun} {j!r}, which is not {of} {known}")
        return received

    def packet(self, name: str, packet, fields: tuple, kind: type) -> tuple:
        """The arrays of a packet ``packet`` (a ``kind`` or any object with its fields): ``fields`` ``((field, shape),
        ...)``, each checked as :meth:`array` (``name.field``)."""
        out = []
        for field, shape in fields:
            if not hasattr(packet, field):
                raise self.refuse(name, f"must be a {kind.__name__} (with {', '.join(f for f, _ in fields)}), got "
                                        f"{_shown(packet)}")
            out.append(self.array(f"{name}.{field}", getattr(packet, field), shape))
        return tuple(out)


def run_network(net, z, attacks=None, inputs=None):
    """Every step of a run through a node network ``net`` (its ``nodes`` with ``P``, its ``estimates()`` and its
    ``step(z, dos, fdi, xi, u)``): ``z`` (K, n_z), ``attacks`` the run's :class:`filters.attacks.AttackPattern`,
    ``inputs`` (K, n_u).  Returns ``(x (K + 1, N, n_x), P (K + 1, N, n_x, n_x))`` from the nodes' current state on
    (``P`` in each node's own coordinates: m x m when the nodes carry their regions)."""
    from .consensus_batch import edge_attacks

    k0 = net.nodes[0].k
    if np.ndim(z) != 2:
        raise NodeInputs(f"of the run from step {k0}").refuse("z", f"must be (steps, {net.model.n_z}): one row of "
                                                                   f"measurements per step, got {_shown(z)}")
    K = len(z)
    if inputs is not None and np.ndim(inputs) != 2:
        raise NodeInputs(f"of the run from step {k0}").refuse("inputs", f"must be ({K}, {net.model.n_u}): one row "
                                                                        f"per step, got {_shown(inputs)}")
    for k in range(K):  # every step's measurement and inputs before the first step: a refused run changes nothing
        check_step(net, z[k], None, None, None, None if inputs is None else inputs[k], k0 + k)
    z = np.asarray(z, dtype=float)
    att = edge_attacks(net.network, None if attacks is None else [attacks], 1, K, net.model.n_x)
    xs = [net.estimates()]
    Ps = [np.stack([nd.P for nd in net.nodes])]
    for k in range(K):
        e = (None, None, None) if att is None else (att.dos[0, k], att.fdi[0, k], att.xi[0, k])
        xs.append(net.step(z[k], *e, u=None if inputs is None else inputs[k]))
        Ps.append(np.stack([nd.P for nd in net.nodes]))
    return np.stack(xs), np.stack(Ps)


def check_step(net, z, dos, fdi, xi, u, k: int | None = None) -> tuple:
    """A network's step's arguments checked (:class:`NodeInputs`, ``'of the network at step k'``): ``z`` (n_z,),
    ``dos``, ``fdi`` (E,) flags and ``xi`` (E, n_x) over the network's E channels, or None, and ``u`` (n_u,).
    Returns them as the step uses them."""
    m = net.model
    chk = NodeInputs(f"of the network at step {net.nodes[0].k if k is None else k}")
    E = int(np.count_nonzero(net.network.adjacency))
    return (chk.array("z", z, (m.n_z,)), chk.flags("dos", dos, E), chk.flags("fdi", fdi, E),
            None if xi is None else chk.array("xi", xi, (E, m.n_x)), chk.inputs(u, m.n_u))


class NodeNetwork:
    """Every node's filter of a network driven a step at a time (the consensus, scheduled, KCF and HCMCI networks):
    a subclass holds ``model``, ``network``, ``nodes`` (each with ``x``, ``P``, ``k``, ``diverged``) and exchanges one
    step in ``_exchange(z, dos, fdi, xi, u)`` (``z`` each node's own measurement), which returns what was sent and
    delivered: ``last`` after a step, ``(sent, deliveries)``, the packets each node sent first and, per exchange
    round, what reached each node (its ``deliver``'s output; what a replay of the step feeds each node).  When a node
    diverges the run stops, as the batched filters stop it: NaN from then on."""

    stopped = False
    last = None
    attacks = (None, None)  # the last step's dos, fdi (E,) flags over the channels (None: none)

    def step(self, z, dos=None, fdi=None, xi=None, u=None) -> np.ndarray:
        """One step of every node: ``z`` (n_z,) every sensor's measurement, ``dos``, ``fdi`` (E,) and ``xi`` (E, n_x)
        the step's attacks on the network's channels (:class:`filters.consensus_batch.EdgeAttacks` order; None:
        none).  Returns every node's estimate (N, n_x)."""
        z, dos, fdi, xi, u = check_step(self, z, dos, fdi, xi, u)
        if self.stopped:
            for nd in self.nodes:
                nd.k += 1
        else:
            offsets = self.model.sensor_offsets
            self.last = self._exchange([z[offsets[i]:offsets[i + 1]] for i in range(len(self.nodes))], dos, fdi,
                                       xi, u)
            self.attacks = (dos, fdi)
            if any(nd.diverged for nd in self.nodes):
                self.stopped = True
                for nd in self.nodes:
                    nd.x, nd.P = np.full_like(nd.x, np.nan), np.full_like(nd.P, np.nan)
        return self.estimates()

    def estimates(self) -> np.ndarray:
        """Every node's current estimate (N, n_x)."""
        return np.stack([nd.x for nd in self.nodes])

    def run(self, z, attacks=None, inputs=None):
        """Every step of a run (:func:`run_network`): ``(x (K + 1, N, n_x), P (K + 1, N, n_x, n_x))``."""
        return run_network(self, z, attacks, inputs)

    def sent_finite(self, sent) -> bool:
        """Whether every number in ``sent`` (what each node sends in a round: a packet or an array) is finite.  A node
        whose packet is not has diverged (its neighbours would refuse the packet): it is marked so and every node takes
        the step, so that the network stops there (NaN from then on), as the batched filter stops the run."""
        bad = [nd for nd, p in zip(self.nodes, sent)
               if not all(np.isfinite(a).all() for a in ((p,) if isinstance(p, np.ndarray) else p)
                          if a is not None and not isinstance(a, (bool, np.bool_)))]
        for nd in bad:
            nd.diverged = True
        if bad:
            for nd in self.nodes:
                nd.k += 1
        return not bad

    def falsified(self) -> list[frozenset]:
        """Per node, the in-neighbours whose packets reached it falsified at the last step (every exchange round's:
        a channel's attack holds for the step), in :meth:`carry`'s channel order."""
        dos, fdi = self.attacks
        out, e = [], 0
        for nd in self.nodes:
            hit = set()
            for j in nd.senders.tolist():
                if fdi is not None and fdi[e] and (dos is None or not dos[e]):
                    hit.add(j)
                e += 1
            out.append(frozenset(hit))
        return out

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
