"""The consensus EKF of mode ``scheduled`` (:mod:`rules.scheduled.design`) at every node, batched over Monte Carlo runs.

Node ``i`` at step ``k`` uses only what it has: its estimate ``x̂_i`` (its prediction and the Jacobians
``F``, ``H_i`` there), its own covariance ``P_ii`` (propagated by itself), its measurement, which of its
neighbours' packets arrived and what they carried, and the offline tables of step ``k`` (the whitened
covariance factors of its links; beyond the designed horizon the stationary ones)::

    x̂⁻_i = f(x̂_i),   P⁻ = F P_ii Fᵀ + Q
    G = P⁻^{1/2} Γ_ij P⁻^{1/2},  S = P⁻^{1/2} Σ̃_jl P⁻^{1/2}          (colour the tables)
    K_i, C_ij, P_ii⁺ = rules.scheduled.design.link_gains(P⁻, H_i(x̂⁻_i), R_i, G, S, p, q, M, μ, margin=δ)
    x̂⁺_i = x̂⁻_i + K_i (z_i - h_i(x̂⁻_i)) + Σ_{j arrived} [K_ij (z̃_j - h_j(x̂⁻_i)) + C_ij (x̃⁻_j - x̂⁻_i)]

and, with L > 1 exchange rounds (``tables.rounds``), rounds 2..L on the same arrived packets of the step: each
node sends its current estimate and applies ``x̂_i += Σ_{j arrived} C^(r)_ij (x̃_j - x̂_i)`` with the round's
tables coloured by its current covariance (no measurement); with the neighbours' measurements ``z̃_j`` in the
first round only when the design exchanges them (``tables.exchange``); a
falsified packet carries ``x̃⁻_j = x̂⁻_j + ξ_ij`` and ``z̃_j = z_j + H_j(x̂⁻_j) ξ_ij`` (what the sender would send
were the state displaced by ξ, as for KCF and HCMCI in :mod:`filters.distributed`).

The bound each node carries is the design's certificate (``ScheduledTables.Phi``: the same for every run,
since the design does not depend on the run); ``predicted_mse`` is the trace of each node's own ``P_ii``.
One run is a batch of one: :func:`run_scheduled_batch` (on :func:`filters.engine.run_batch`) is the only
implementation.  Its step is three functions of a block of nodes (:func:`scheduled_prediction`,
:func:`scheduled_update`, :func:`scheduled_round`), each received packet formed first
(:func:`filters.channels.channel_packets`) and the slots' terms added slot by slot, so that one node alone computes the batch's numbers: :class:`ScheduledNode`, the node filter (``predict``, ``update``, then
``round`` for rounds 2..L), and :class:`ScheduledNetwork`, every node over a run.
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from designer.bounds import sqrtm_psd
from designer.design import ConsensusDesign, validate_design
from designer.model import Model
from designer.network import SensorNetwork
from designer.validation import InputError, check_int

from filters.attacks import AttackPattern
from filters.channels import channel_packets
from filters.node import NodeInputs, NodeNetwork, OwnRows
from filters.result import FilterResult, diverged_nodes
from filters.consensus_batch import (PREDICTION_FIELDS, EdgeAttacks, batch_inputs, consensus_arrays,
                              consensus_result, edge_attacks, result_arrays, run_networks, wrap_residuals)
from filters.engine import Step, run_batch

from .design import colour, link_gains, pad_measurements

__all__ = ["run_scheduled_batch", "scheduled_prediction", "scheduled_update", "scheduled_round", "ScheduledPacket",
           "ScheduledNode", "ScheduledNetwork"]



def run_scheduled_batch(model: Model, network: SensorNetwork | Sequence[SensorNetwork], z: np.ndarray,
                        design: ConsensusDesign, *, inputs=None,
                        attacks: EdgeAttacks | Sequence[AttackPattern] | None = None, x0=None,
                        phi0=None, predictions: bool = True) -> FilterResult:
    """Run the scheduled consensus filter at every node over many runs of measurements ``z`` (runs, steps, n_z).

    The parameters are those of :func:`filters.consensus_batch.run_consensus_batch` (``predictions``: without, no
    record of the gains K and C nor of ``phi_pred``, which this filter does not compute); ``design`` is in mode
    ``'scheduled'`` with its tables (``design.tables``, :func:`rules.scheduled.design.design_scheduled`).  The runs'
    networks may differ only in what the tables were not designed for: the filter applies the tables it was
    given (a design for other channel statistics is the user's choice).  Returns
    :func:`filters.consensus_batch.consensus_result` of the runs (``detail`` a ``ConsensusBatchResult``).
    """
    z, u, x0, phi0 = batch_inputs(model, z, inputs, x0, phi0)
    runs, steps = z.shape[:2]
    network, _ = run_networks(network, runs)
    design = validate_design(design, model, network)
    tables = design.tables
    if not design.rule.offline_tables or tables is None:
        raise InputError("run_scheduled_batch runs mode 'scheduled' with its tables (rules.scheduled.design."
                         "design_scheduled); got mode " + repr(design.mode))
    ch = tables.channels
    if not (np.array_equal(ch.receiver, np.nonzero(network.adjacency)[0])
            and np.array_equal(ch.sender, np.nonzero(network.adjacency)[1])):
        raise InputError("design.tables were designed for another network (other channels)")
    attacks = edge_attacks(network, attacks, runs, steps, model.n_x)
    n, nx = network.n_nodes, model.n_x
    nz = max(model.sensor_dims)
    M = np.zeros((nx, nx)) if design.fdi_moment is None else np.asarray(design.fdi_moment, dtype=float)
    mu = np.zeros(nx) if design.fdi_mean is None else np.asarray(design.fdi_mean, dtype=float)
    offsets = model.sensor_offsets
    cols = [slice(int(a), int(b)) for a, b in zip(offsets[:-1], offsets[1:])]
    T = tables.steps
    out = result_arrays(runs, steps, n, nx, nz, latest=() if predictions else PREDICTION_FIELDS)
    # the certificate: the design's, the same in every run, up to its horizon
    H_ = min(steps, T)
    out["phi_post"][:, : H_ + 1] = tables.Phi[None, : H_ + 1]
    out["valid"][:, : H_ + 1] = tables.valid[None, : H_ + 1, None]
    for key in ("sigma", "beta", "margin28", "margin29"):
        out[key][:, :H_] = getattr(tables, key)[None, :H_, None]
    out["theorem2"][:, : H_ + 1] = tables.theorem2[None, : H_ + 1]
    for r in range(runs):
        out["violations"][r] = [dict(v) for v in tables.violations if v["step"] <= steps]
    x = np.broadcast_to(x0[:, None, :], (runs, n, nx)).copy()
    P = np.broadcast_to(phi0[:, None], (runs, n, nx, nx)).copy()
    out["x_post"][:, 0] = x
    out["predicted_mse"][:, 0] = np.trace(P, axis1=-2, axis2=-1)
    rcv, snd = ch.receiver, ch.sender
    chan, mask = ch.slots  # (N, d): each node's incoming channels in its slots
    nodes = np.arange(n)

    def step(k, act, at):
        uk = u[k] if u.ndim == 2 else u[act, k][:, None, :]
        a = act.size
        xp, Pp, choice = scheduled_prediction(model, tables, k, x[act], P[act], uk)
        if attacks is None:
            arrived, fdi, xi = np.ones((a, rcv.size), dtype=bool), np.zeros((a, rcv.size), dtype=bool), None
        else:
            arrived, fdi, xi = ~attacks.dos[act, k], attacks.fdi[act, k], attacks.xi[act, k]
        counts = np.zeros((a, out["gate_counts"].shape[-1]), dtype=np.int64)  # no gate: received and falsified
        counts[:, 0] = arrived.sum(-1)
        counts[:, 3] = counts[:, 4] = (arrived & fdi).sum(-1)
        got = np.where(mask, arrived[:, chan], False)  # (a, N, d): the slots whose packet arrived
        # what every channel carries (a falsified packet: x̂⁻_j + ξ, and z_j + H_j(x̂⁻_j) ξ), laid out by slot
        sent_x = channel_packets(xp[:, snd], fdi, xi)[:, chan]  # (a, N, d, nx)
        sent_z = None
        if tables.exchange:
            zk = z[act, k]
            sent_z = np.zeros((a, rcv.size, nz))
            for j in range(n):
                out_j = np.flatnonzero(snd == j)
                if out_j.size:
                    shift = None if xi is None else np.einsum("lab,leb->lea", model.H(j, xp[:, j], k + 1),
                                                              xi[:, out_j])
                    sent_z[:, out_j, :model.sensor_dims[j]] = channel_packets(
                        np.broadcast_to(zk[:, None, cols[j]], (a, out_j.size, model.sensor_dims[j])),
                        None if xi is None else fdi[:, out_j], shift)
            sent_z = sent_z[:, chan]
        xn, Pn, K, C, kappa = scheduled_update(model, tables, design, k, nodes, xp, Pp, choice, z[act, k], got,
                                               sent_x, sent_z, M, mu)
        C = np.einsum("lid,lidab->liab", got.astype(float), C)  # Σ_{arrived} C_ij (first round)
        condition = kappa
        for rnd in range(2, tables.rounds + 1):  # rounds 2..L: the senders' current estimates, the same packets
            sent_x = channel_packets(xn[:, snd], fdi, xi)[:, chan]
            xn, Pn, kappa = scheduled_round(model, tables, rnd, k, nodes, xn, Pn, choice, got, sent_x, M, mu)
            condition = np.maximum(condition, kappa)
        x[act], P[act] = xn, Pn
        return Step(dict(gate_counts=counts, K=K, C=C, gain_condition=condition, x_pred=xp),
                    dict(x_post=xn, predicted_mse=np.trace(Pn, axis1=-2, axis2=-1)), diverged_nodes(xn, Pn))

    run_batch(step, out, out["violations"], steps, nan_from=("x_post", "phi_post", "predicted_mse"),
              invalid_from=("valid",))
    if steps > T:  # beyond the horizon the certificate was not computed: no bound claimed
        out["valid"][:, T + 1:] = False
    return consensus_result(consensus_arrays(out), network, design)


def scheduled_prediction(model: Model, tables, k: int, x, P, u):
    """The prediction of stacked nodes ``(a, n)`` (a batch's runs × nodes, or one node alone: the same numbers):
    ``x̂⁻ = f(x̂)``, ``P⁻ = F P Fᵀ + Q`` at each node's own estimate, and each node's choice of tables (None without
    a bank)."""
    F = model.F_expected(x, k, u)
    xp = model.f_expected(x, k, u)
    Pp = model.propagate(F, P) + model.process_cov
    Pp = 0.5 * (Pp + np.swapaxes(Pp, -1, -2))
    return xp, Pp, tables.choose(k, xp)


def scheduled_update(model: Model, tables, design: ConsensusDesign, k: int, nodes, xp, Pp, choice, z, got, sent_x,
                     sent_z, M, mu):
    """The first exchange round of the stacked nodes ``nodes`` (their ids; ``xp``, ``Pp`` (a, g, ...) their
    predictions, ``choice`` their tables): ``z`` (a, n_z) the measurements (each node reads its own), ``got`` (a, g,
    d) which slots' packets arrived, ``sent_x`` (a, g, d, n_x) the predictions they carried and ``sent_z`` (a, g, d,
    mz) the measurements (exchange; None without).  Returns ``(x, P, K, C (a, g, d, n, n), condition)``."""
    ch = tables.channels
    a, g, nx = xp.shape
    dims = model.sensor_dims
    nz = max(dims)
    offsets = model.sensor_offsets
    chan, mask = ch.slots
    R_all = _padded_R(model, nz)  # (N, nz, nz)
    R_pad = R_all[nodes]
    root = sqrtm_psd(Pp)
    Gam_f, Sig_f = _factors(tables.candidates(k), choice, ch, a, nodes)
    G = colour(root, Gam_f)  # (a, g, d, nx, nx)
    S = colour(root, Sig_f)  # (a, g, d, d, nx, nx)
    H_own, res_own = np.zeros((a, g, nz, nx)), np.zeros((a, g, nz))
    for t, i in enumerate(nodes.tolist()):  # each node's own measurement, padded to nz (a padded component: no gain)
        H_own[:, t, :dims[i]] = model.H(i, xp[:, t], k + 1)
        res_own[:, t, :dims[i]] = wrap_residuals(z[:, offsets[i]:offsets[i + 1]] - model.h(i, xp[:, t], k + 1),
                                                 model.sensors[i].angles)
    Hn = Rn = res_n = None
    d = chan.shape[1]
    if tables.exchange:  # the neighbours' measurements, at each receiver's own prediction
        Hn, res_n = np.zeros((a, g, d, nz, nx)), np.zeros((a, g, d, nz))
        senders = ch.sender[chan[nodes]]  # (g, d)
        for t, i in enumerate(nodes.tolist()):
            for e in np.flatnonzero(mask[i]).tolist():
                j = int(senders[t, e])
                Hn[:, t, e, :dims[j]] = model.H(j, xp[:, t], k + 1)
                r_j = wrap_residuals(sent_z[:, t, e, :dims[j]] - model.h(j, xp[:, t], k + 1), model.sensors[j].angles)
                res_n[:, t, e, :dims[j]] = np.where(got[:, t, e, None], r_j, 0.0)
        Rn = R_all[ch.at_slots(ch.sender, 0)[nodes]]  # (g, d, nz, nz); an empty slot: sensor 0's (no gain there)
    K, K_n, C, Pn, kappa = link_gains(Pp, H_own, R_pad, G, S, ch.at_slots(ch.p)[nodes], ch.at_slots(ch.q)[nodes],
                                      M, mu, Hn, Rn, tables.robustness)
    diff_slot = np.where(got[..., None], sent_x - xp[:, :, None], 0.0)  # (a, g, d, nx)
    xn = xp + (K @ res_own[..., None])[..., 0] + _slot_sum(C, diff_slot)
    if K_n is not None:
        xn += _slot_sum(K_n, res_n)
    return xn, Pn, K, C, kappa


def _slot_sum(gains: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``Σ_slots gain @ value`` over the slots (axis -3 of ``gains`` (a, g, d, n, m), -2 of ``values`` (a, g, d, m)),
    added slot by slot in order: the same bits for a node alone and in a batch (an einsum's order of additions
    depends on the shapes)."""
    terms = (gains @ values[..., None])[..., 0]
    out = np.zeros(terms.shape[:2] + terms.shape[3:])
    for e in range(terms.shape[2]):
        out = out + terms[:, :, e]
    return out


def scheduled_round(model: Model, tables, rnd: int, k: int, nodes, x, P, choice, got, sent_x, M, mu):
    """Exchange round ``rnd`` (2..L) of the stacked nodes ``nodes``: the estimates ``x`` and covariances ``P`` after
    the previous round, ``sent_x`` (a, g, d, n_x) the neighbours' current estimates on the slots ``got`` whose
    packets arrived.  Returns ``(x, P, condition)``."""
    ch = tables.channels
    a, g, nx = x.shape
    Gam_f, Sig_f = _factors(tables.candidates(k, rnd), choice, ch, a, nodes)
    root = sqrtm_psd(P)
    G, S = colour(root, Gam_f), colour(root, Sig_f)
    nz = max(model.sensor_dims)  # no measurement in these rounds: zero rows (no gain), as in the first's padding
    _, _, C, Pn, kappa = link_gains(P, np.zeros((a, g, nz, nx)), _padded_R(model, nz)[nodes], G, S,
                                    ch.at_slots(ch.p)[nodes], ch.at_slots(ch.q)[nodes], M, mu,
                                    margin=tables.robustness)
    diff_slot = np.where(got[..., None], sent_x - x[:, :, None], 0.0)
    return x + _slot_sum(C, diff_slot), Pn, kappa


def _padded_R(model: Model, nz: int) -> np.ndarray:
    """Every sensor's noise covariance padded to ``nz`` components (identity padding): (N, nz, nz)."""
    nx = model.n_x
    R = [model.measurement_cov(i) for i in range(model.n_sensors)]
    return pad_measurements([np.zeros((m, nx)) for m in model.sensor_dims], R, nz)[1]


def _factors(candidates: tuple[np.ndarray, np.ndarray], choice: np.ndarray | None, ch, a: int, nodes):
    """The whitened factors of the slots of ``nodes`` (their ids), ``(Gamma (a, g, d, n, n), Sigma (a, g, d, d, n,
    n))``, from the candidates' tables (:meth:`rules.scheduled.design.ScheduledTables.candidates`) and each node's
    ``choice`` (a, g) (None: the first candidate's, the step's own, for every node)."""
    Gam, Sig = candidates
    d = ch.d_max
    slots = ch.at_slots(np.moveaxis(Gam, 0, 1))[nodes]  # (g, d, B + 1, n, n)
    if choice is None:
        return (np.broadcast_to(slots[:, :, 0], (a,) + slots[:, :, 0].shape),
                np.broadcast_to(Sig[0, nodes, :d, :d], (a,) + Sig[0, nodes, :d, :d].shape))
    at = np.arange(len(nodes))[None, :]
    return slots[at, :, choice], Sig[choice, np.asarray(nodes)[None, :]][:, :, :d, :d]




# --------------------------------------------------------------------------- the node filter
class ScheduledPacket(NamedTuple):
    """What a scheduled node sends in a step's first round: its prediction ``x`` and, when the design exchanges
    measurements, its measurement ``z`` (else None)."""

    x: np.ndarray
    z: np.ndarray | None


class ScheduledNode(OwnRows):
    """The filter node ``node`` of a ``scheduled`` design runs, with the design's tables (the whitened covariance
    factors of its links per step, :class:`rules.scheduled.design.ScheduledTables`), in phases:

    * ``packet = node.predict(z, u)``: its prediction ``f(x̂)``, ``F P Fᵀ + Q`` (its own covariance) and its choice of
      tables (a bank's nearest point): the packet it sends (with its measurement when the design exchanges them);
    * ``node.update(received)``: the first round, ``{neighbour: ScheduledPacket}`` as they arrived (falsified or not);
    * rounds 2..L (``node.rounds``), ``node.round(received)``: ``{neighbour: x̃_j}`` the neighbours' current estimates
      on the same channels (the packets of a step arrive or not in every round alike).

    ``x``, ``P`` its estimate and own covariance; ``bound`` the design's certificate Φ at its step (the same at every
    run: NaN where the design certifies nothing).  Driven over a run through :class:`ScheduledNetwork`, the batch's
    numbers bit for bit (the same functions on this node's slots)."""

    def __init__(self, model: Model, network: SensorNetwork, design: ConsensusDesign, node: int, *, x0=None,
                 P0=None):
        design = validate_design(design, model, network)
        if not design.rule.offline_tables or design.tables is None:
            raise InputError(f"ScheduledNode runs a rule of offline tables with its tables; got mode {design.mode!r}")
        i = self.node = check_int("node", node, 0, network.n_nodes - 1)
        self.model, self.design, self.tables = model, design, design.tables
        ch = self.tables.channels
        chan, mask = ch.slots
        self.senders = ch.sender[chan[i][mask[i]]]  # its in-neighbours, slot by slot
        self.rounds = self.tables.rounds
        nx = model.n_x
        self._M = np.zeros((nx, nx)) if design.fdi_moment is None else np.asarray(design.fdi_moment, dtype=float)
        self._mu = np.zeros(nx) if design.fdi_mean is None else np.asarray(design.fdi_mean, dtype=float)
        self._nodes = np.array([i])
        _, _, x0, P0 = batch_inputs(model, np.zeros((1, 1, model.n_z)), np.zeros((1, model.n_u)), x0, P0, "P0")
        self.x, self.P = x0[0].copy(), P0[0].copy()
        self.k, self.diverged = 0, False
        self._phase, self._step = "predict", None

    @property
    def bound(self) -> np.ndarray:
        """The design's certificate Φ at this node's step (NaN where it claims none: beyond the horizon, not valid)."""
        T = self.tables.steps
        if self.k > T or not self.tables.valid[self.k]:
            return np.full_like(self.P, np.nan)
        return self.tables.Phi[self.k, self.node]

    _CALLS = {"predict": "predict(z, u)", "update": "update(received)"}

    def _expect(self, phase: str) -> None:
        if self._phase != phase:
            raise InputError(f"node {self.node} is at its {self._phase} of step {self.k}, not its {phase}: call "
                             f"{self._CALLS.get(self._phase, 'round(received)')} next")

    def predict(self, z, u=None) -> ScheduledPacket:
        """The prediction phase with the node's measurement ``z``: the packet it sends."""
        return _predict_together([self], [z], u)[0]

    def _predict_inputs(self, z, u) -> tuple:
        """The prediction phase's checked inputs: ``(z, u)``."""
        self._expect("predict")
        chk = NodeInputs.of(self)
        return chk.array("z", z, (self.model.sensor_dims[self.node],)), chk.inputs(u, self.model.n_u)

    def _arrived(self, received, fields):
        """``received`` checked (its keys in-neighbours, each packet's ``fields`` as :meth:`NodeInputs.packet`, or
        with ``fields`` None an estimate): ``(got (1, 1, d_max), sent_x (1, 1, d_max, n_x), sent_z)`` (``sent_z``
        the measurements per channel with ``fields``' ``z``)."""
        chk = NodeInputs.of(self)
        senders = self.senders.tolist()
        received = chk.received("received", received, senders, f"an in-neighbour of node {self.node}")
        m, d = self.model, self.tables.channels.d_max
        got = np.zeros((1, 1, d), dtype=bool)
        sent_x, sent_z = np.zeros((1, 1, d, m.n_x)), np.zeros((1, 1, d, max(m.sensor_dims)))
        for e, j in enumerate(senders):
            if j in received:
                got[0, 0, e] = True
                if fields is None:
                    sent_x[0, 0, e] = chk.array(f"received[{j}]", received[j], (m.n_x,))
                else:
                    got_j = chk.packet(f"received[{j}]", received[j], fields(j), ScheduledPacket)
                    sent_x[0, 0, e] = got_j[0]
                    if len(got_j) > 1:
                        sent_z[0, 0, e, :m.sensor_dims[j]] = got_j[1]
        return got, sent_x, sent_z

    def update(self, received=None) -> np.ndarray:
        """The first round: ``received`` ``{neighbour: ScheduledPacket}`` as they arrived.  Returns the estimate."""
        _update_together([self], [received])
        return self.x

    def _update_inputs(self, received) -> tuple:
        """The first round's inputs of :func:`scheduled_update` for this node (``received`` checked): ``(xp, Pp,
        choice, z (1, n_z) with its own measurement in place, got, sent_x, sent_z)``."""
        self._expect("update")
        m, i, nx = self.model, self.node, self.model.n_x
        got, sent_x, sent_z = self._arrived(received, lambda j: (("x", (nx,)),) + (
            (("z", (m.sensor_dims[j],)),) if self.tables.exchange else ()))
        z, xp, Pp, choice = self._step
        zk = np.zeros((1, m.n_z))
        offsets = m.sensor_offsets
        zk[0, offsets[i]:offsets[i + 1]] = z
        return xp, Pp, choice, zk, got, sent_x, sent_z

    def round(self, received=None) -> np.ndarray:
        """Exchange round r (2..``rounds``): ``{neighbour: x̃_j}`` the neighbours' current estimates that arrived
        (on the channels whose first-round packet arrived).  Returns the estimate."""
        _round_together([self], [received])
        return self.x

    def _round_inputs(self, received) -> tuple:
        """Exchange round r's inputs of :func:`scheduled_round` for this node (``received`` checked): ``(r, xn, Pn,
        choice, got, sent_x)``."""
        if not self._phase.startswith("round"):
            raise InputError(f"node {self.node} is at its {self._phase} of step {self.k}, not an exchange round: "
                             f"call {self._CALLS[self._phase]} next")
        r = int(self._phase.split()[1])
        got, sent_x, _ = self._arrived(received, None)
        choice, first, xn, Pn = self._step
        if not np.array_equal(got, first):
            raise InputError(f"round {r} of node {self.node} at step {self.k} must receive from the neighbours whose "
                             f"first packet arrived ({self.senders[first[0, 0, :self.senders.size]].tolist()})")
        return r, xn, Pn, choice, got, sent_x

    def _next(self, r: int) -> None:
        choice, got, xn, Pn = self._step
        self.x, self.P = xn[0, 0], Pn[0, 0]
        if r <= self.rounds:
            self._phase = f"round {r}"
            return
        self.diverged = bool(diverged_nodes(xn, Pn)[0, 0])
        self.k += 1
        self._phase, self._step = "predict", None


def _joined(parts, axis: int = 1):
    """The nodes' arrays side by side along ``axis`` (None where the nodes have none)."""
    return None if parts[0] is None else np.concatenate(parts, axis=axis)


def _predict_together(nodes: Sequence[ScheduledNode], z: Sequence, u) -> list[ScheduledPacket]:
    """The prediction phase of ``nodes`` (one design, one step), each with its measurement, in one call of
    :func:`scheduled_prediction` over them (each node's own numbers, bit for bit): the packets they send.  Every
    node's input is checked before any node changes."""
    checked = [nd._predict_inputs(z_i, u) for nd, z_i in zip(nodes, z)]
    one = nodes[0]
    x = np.stack([nd.x for nd in nodes])[None]
    P = np.stack([nd.P for nd in nodes])[None]
    xp, Pp, choice = scheduled_prediction(one.model, one.tables, one.k, x, P, checked[0][1])
    sent = []
    for t, (nd, (z_t, _)) in enumerate(zip(nodes, checked)):
        nd._step = (z_t, xp[:, t:t + 1], Pp[:, t:t + 1], None if choice is None else choice[:, t:t + 1])
        nd._phase = "update"
        sent.append(ScheduledPacket(xp[0, t], z_t.copy() if one.tables.exchange else None))
    return sent


def _update_together(nodes: Sequence[ScheduledNode], received: Sequence) -> None:
    """The first round of ``nodes`` (one design, one step), each with what reached it, in one call of
    :func:`scheduled_update` over them: each node's numbers are the ones it computes alone, bit for bit (the
    batched filter's functions act on each node's slots alone).  Every node's input is checked before any node
    changes."""
    parts = list(zip(*(nd._update_inputs(got) for nd, got in zip(nodes, received))))
    one = nodes[0]
    xp, Pp, choice, got, sent_x, sent_z = (_joined(parts[c]) for c in (0, 1, 2, 4, 5, 6))
    z = np.sum(parts[3], axis=0)  # each node's row holds its own measurement alone, zeros elsewhere: exact
    xn, Pn, *_ = scheduled_update(one.model, one.tables, one.design, one.k, np.array([nd.node for nd in nodes]), xp,
                                  Pp, choice, z, got, sent_x, sent_z if one.tables.exchange else None, one._M, one._mu)
    for t, nd in enumerate(nodes):
        nd._step = (None if choice is None else choice[:, t:t + 1], got[:, t:t + 1], xn[:, t:t + 1], Pn[:, t:t + 1])
        nd._next(2)


def _round_together(nodes: Sequence[ScheduledNode], received: Sequence) -> None:
    """Exchange round r (2..L) of ``nodes`` in one call of :func:`scheduled_round` (as :func:`_update_together`)."""
    parts = list(zip(*(nd._round_inputs(got) for nd, got in zip(nodes, received))))
    one = nodes[0]
    r = parts[0][0]
    xn, Pn, choice, got, sent_x = (_joined(parts[c]) for c in range(1, 6))
    xn, Pn, _ = scheduled_round(one.model, one.tables, r, one.k, np.array([nd.node for nd in nodes]), xn, Pn, choice,
                                got, sent_x, one._M, one._mu)
    for t, nd in enumerate(nodes):
        nd._step = (None if choice is None else choice[:, t:t + 1], got[:, t:t + 1], xn[:, t:t + 1], Pn[:, t:t + 1])
        nd._next(r + 1)


class ScheduledNetwork(NodeNetwork):
    """Every node of a ``scheduled`` design as a :class:`ScheduledNode`, driven over a run: each step every node
    predicts, the packets cross the channels (DoS drops them; FDI: ``x̂⁻_j + ξ`` and ``z_j + H_j(x̂⁻_j) ξ``), every
    node updates, then rounds 2..L exchange the current estimates on the same channels."""

    def __init__(self, model: Model, network: SensorNetwork, design: ConsensusDesign, *, x0=None, P0=None):
        design = validate_design(design, model, network)
        self.model, self.network = model, network
        self.nodes = [ScheduledNode(model, network, design, i, x0=x0, P0=P0) for i in range(network.n_nodes)]

    def deliver(self, sent, dos=None, fdi=None, xi=None) -> list[dict]:
        """What ``sent`` (per node: a :class:`ScheduledPacket` of the first round, or its current estimate in a later
        round) delivers to every node over the step's channels (``dos``, ``fdi`` (E,), ``xi`` (E, n_x) in
        :class:`filters.consensus_batch.EdgeAttacks` order): per node ``{neighbour: what arrived}``."""
        m, k1 = self.model, self.nodes[0].k + 1

        def falsified(nd, j, p, f, x):
            if not isinstance(p, ScheduledPacket):
                return channel_packets(p, f, x)
            z = p.z
            if z is not None and x is not None:  # the measurement as if the state were displaced by ξ
                shift = np.einsum("lab,leb->lea", m.H(j, p.x[None], k1), x[None, None])[0, 0]
                z = channel_packets(z, f, shift)
            return ScheduledPacket(channel_packets(p.x, f, x), z)

        return self.carry(sent, dos, fdi, xi, falsified)

    def _exchange(self, z, dos, fdi, xi, u):
        sent = _predict_together(self.nodes, z, u)  # every node's prediction in one batch: each node's own numbers
        if not self.sent_finite(sent):
            return sent, []
        rounds = [self.deliver(sent, dos, fdi, xi)]
        _update_together(self.nodes, rounds[0])  # every node's update in one batch: each node's own numbers
        for _ in range(2, self.nodes[0].rounds + 1):
            if not self.sent_finite([nd.x for nd in self.nodes]):
                return sent, rounds
            rounds.append(self.deliver([nd.x for nd in self.nodes], dos, fdi, xi))
            _round_together(self.nodes, rounds[-1])
        return sent, rounds


