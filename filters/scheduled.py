"""The consensus EKF of mode ``scheduled`` (:mod:`designer.scheduled`) at every node, batched over Monte Carlo runs.

Node ``i`` at step ``k`` uses only what it has: its estimate ``x̂_i`` (its prediction and the Jacobians
``F``, ``H_i`` there), its own covariance ``P_ii`` (propagated by itself), its measurement, which of its
neighbours' packets arrived and what they carried, and the offline tables of step ``k`` (the whitened
covariance factors of its links; beyond the designed horizon the stationary ones)::

    x̂⁻_i = f(x̂_i),   P⁻ = F P_ii Fᵀ + Q
    G = P⁻^{1/2} Γ_ij P⁻^{1/2},  S = P⁻^{1/2} Σ̃_jl P⁻^{1/2}          (colour the tables)
    K_i, C_ij, P_ii⁺ = designer.scheduled.link_gains(P⁻, H_i(x̂⁻_i), R_i, G, S, p, q, M, μ, margin=δ)
    x̂⁺_i = x̂⁻_i + K_i (z_i - h_i(x̂⁻_i)) + Σ_{j arrived} [K_ij (z̃_j - h_j(x̂⁻_i)) + C_ij (x̃⁻_j - x̂⁻_i)]

and, with L > 1 exchange rounds (``tables.rounds``), rounds 2..L on the same arrived packets of the step: each
node sends its current estimate and applies ``x̂_i += Σ_{j arrived} C^(r)_ij (x̃_j - x̂_i)`` with the round's
tables coloured by its current covariance (no measurement); with the neighbours' measurements ``z̃_j`` in the
first round only when the design exchanges them (``tables.exchange``); a
falsified packet carries ``x̃⁻_j = x̂⁻_j + ξ_ij`` and ``z̃_j = z_j + H_j(x̂⁻_j) ξ_ij`` (what the sender would send
were the state displaced by ξ, as for KCF and HCMCI in :mod:`filters.distributed`).

The bound each node carries is the design's certificate (``ScheduledTables.Phi``: the same for every run,
since the design does not depend on the run); ``predicted_mse`` is the trace of each node's own ``P_ii``.
One run is a batch of one: :func:`run_scheduled_batch` is the only implementation.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from designer.design import ConsensusDesign, validate_design
from designer.model import Model
from designer.network import SensorNetwork
from designer.scheduled import colour, link_gains, pad_measurements, sqrtm_psd
from designer.validation import InputError

from .attacks import AttackPattern
from .result import diverged_nodes, stop_diverged
from .consensus_batch import (ConsensusBatchResult, EdgeAttacks, batch_inputs, edge_attacks, register_filter,
                              result_arrays, run_networks, wrap_residuals)

__all__ = ["run_scheduled_batch"]



def run_scheduled_batch(model: Model, network: SensorNetwork | Sequence[SensorNetwork], z: np.ndarray,
                        design: ConsensusDesign, *, inputs=None,
                        attacks: EdgeAttacks | Sequence[AttackPattern] | None = None, x0=None,
                        phi0=None) -> ConsensusBatchResult:
    """Run the scheduled consensus filter at every node over many runs of measurements ``z`` (runs, steps, n_z).

    The parameters are those of :func:`filters.consensus_batch.run_consensus_batch`; ``design`` is in mode
    ``'scheduled'`` with its tables (``design.tables``, :func:`designer.scheduled.design_scheduled`).  The runs'
    networks may differ only in what the tables were not designed for: the filter applies the tables it was
    given (a design for other channel statistics is the user's choice).
    """
    z, u, x0, phi0 = batch_inputs(model, z, inputs, x0, phi0)
    runs, steps = z.shape[:2]
    network, _ = run_networks(network, runs)
    design = validate_design(design, model, network)
    tables = design.tables
    if design.mode != "scheduled" or tables is None:
        raise InputError("run_scheduled_batch runs mode 'scheduled' with its tables (designer.scheduled."
                         "design_scheduled); got mode " + repr(design.mode))
    ch = tables.channels
    if not (np.array_equal(ch.receiver, np.nonzero(network.adjacency)[0])
            and np.array_equal(ch.sender, np.nonzero(network.adjacency)[1])):
        raise InputError("design.tables were designed for another network (other channels)")
    attacks = edge_attacks(network, attacks, runs, steps, model.n_x)
    n, nx = network.n_nodes, model.n_x
    nz = max(model.sensor_dims)
    Q = model.process_cov
    R = [model.measurement_cov(i) for i in range(n)]
    M = np.zeros((nx, nx)) if design.fdi_moment is None else np.asarray(design.fdi_moment, dtype=float)
    mu = np.zeros(nx) if design.fdi_mean is None else np.asarray(design.fdi_mean, dtype=float)
    offsets = np.concatenate([[0], np.cumsum(model.sensor_dims)])
    cols = [slice(int(a), int(b)) for a, b in zip(offsets[:-1], offsets[1:])]
    T = tables.steps
    out = result_arrays(runs, steps, n, nx, nz)
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
    d = chan.shape[1]
    slot = ch.slot
    p_slot, q_slot = ch.at_slots(ch.p), ch.at_slots(ch.q)
    R_pad = pad_measurements([np.zeros((m_i, nx)) for m_i in model.sensor_dims], R, nz)[1]  # (N, nz, nz)
    act = np.arange(runs)
    for k in range(steps):
        if not act.size:
            break
        uk = u[k] if u.ndim == 2 else u[act, k][:, None, :]
        xk, Pk = x[act], P[act]
        F = model.F_expected(xk, k, uk)
        xp = model.f_expected(xk, k, uk)
        Pp = F @ Pk @ np.swapaxes(F, -1, -2) + Q
        Pp = 0.5 * (Pp + np.swapaxes(Pp, -1, -2))
        root = sqrtm_psd(Pp)
        a = act.size
        choice = tables.choose(k, xp)  # (a, N): each node's tables, from its own prediction (None: no bank)
        Gam_f, Sig_f = _factors(tables.candidates(k), choice, ch, a, n)
        if attacks is None:
            arrived, fdi, xi = np.ones((a, rcv.size), dtype=bool), np.zeros((a, rcv.size), dtype=bool), None
        else:
            arrived, fdi, xi = ~attacks.dos[act, k], attacks.fdi[act, k], attacks.xi[act, k]
        out["gate_counts"][act, k, 0] = arrived.sum(-1)
        out["gate_counts"][act, k, 3] = out["gate_counts"][act, k, 4] = (arrived & fdi).sum(-1)
        diff = xp[:, snd] - xp[:, rcv]  # (a, E, nx): x̂⁻_j - x̂⁻_i on every channel
        if xi is not None:
            diff = diff + np.where(fdi[..., None], xi, 0.0)
        diff = np.where(arrived[..., None], diff, 0.0)
        zk = z[act, k]
        # every node's own measurement, padded to nz components (a padded component gets a zero gain)
        H_own, res_own = np.zeros((a, n, nz, nx)), np.zeros((a, n, nz))
        for i in range(n):
            m_i = model.sensor_dims[i]
            H_own[:, i, :m_i] = model.H(i, xp[:, i], k + 1)
            res_own[:, i, :m_i] = wrap_residuals(zk[:, cols[i]] - model.h(i, xp[:, i], k + 1),
                                                 model.sensors[i].angles)
        G = colour(root, Gam_f)  # (a, N, d, nx, nx)
        S = colour(root, Sig_f)  # (a, N, d, d, nx, nx)
        Hn = Rn = res_n = None
        if tables.exchange:  # the neighbours' measurements, at each receiver's own prediction
            Hn, res_n = np.zeros((a, n, d, nz, nx)), np.zeros((a, n, d, nz))
            for j in range(n):  # sensor j at the predictions of the nodes that receive it
                out_j = np.flatnonzero(snd == j)
                if not out_j.size:
                    continue
                m_j = model.sensor_dims[j]
                at = xp[:, rcv[out_j]]  # (a, r, nx)
                Hn[:, rcv[out_j], slot[out_j], :m_j] = model.H(j, at, k + 1)
                r_j = zk[:, None, cols[j]] - model.h(j, at, k + 1)
                if xi is not None:  # a falsified packet's measurement: as if the state were displaced by ξ, with
                    # H_j at the sender's prediction
                    shift = np.einsum("lab,leb->lea", model.H(j, xp[:, j], k + 1), xi[:, out_j])
                    r_j = r_j + np.where(fdi[:, out_j, None], shift, 0.0)
                r_j = wrap_residuals(r_j, model.sensors[j].angles)
                res_n[:, rcv[out_j], slot[out_j], :m_j] = np.where(arrived[:, out_j, None], r_j, 0.0)
            Rn = R_pad[ch.at_slots(snd, 0)]
        K, K_n, C, Pn, kappa = link_gains(Pp, H_own, R_pad, G, S, p_slot, q_slot, M, mu, Hn, Rn, tables.robustness)
        got = np.where(mask, arrived[:, chan], False)  # (a, N, d): the slots whose packet arrived
        diff_slot = np.where(got[..., None], diff[:, chan], 0.0)  # (a, N, d, nx)
        xn = xp + (K @ res_own[..., None])[..., 0] + np.einsum("lidab,lidb->lia", C, diff_slot)
        if K_n is not None:
            xn += np.einsum("lidab,lidb->lia", K_n, res_n)
        out["K"][act, k] = K
        out["C"][act, k] = np.einsum("lid,lidab->liab", got.astype(float), C)  # Σ_{arrived} C_ij (first round)
        out["gain_condition"][act, k] = kappa
        for rnd in range(2, tables.rounds + 1):  # rounds 2..L: the senders' current estimates, the same packets
            Gam_f, Sig_f = _factors(tables.candidates(k, rnd), choice, ch, a, n)
            root = sqrtm_psd(Pn)
            G, S = colour(root, Gam_f), colour(root, Sig_f)
            _, _, C, Pn, kappa = link_gains(Pn, np.zeros_like(H_own), R_pad, G, S, p_slot, q_slot, M, mu,
                                            margin=tables.robustness)
            diff = xn[:, snd] - xn[:, rcv]
            if xi is not None:
                diff = diff + np.where(fdi[..., None], xi, 0.0)
            diff_slot = np.where(got[..., None], diff[:, chan], 0.0)
            xn = xn + np.einsum("lidab,lidb->lia", C, diff_slot)
            out["gain_condition"][act, k] = np.maximum(out["gain_condition"][act, k], kappa)
        x[act], P[act] = xn, Pn
        out["x_pred"][act, k], out["x_post"][act, k + 1] = xp, xn
        out["predicted_mse"][act, k + 1] = np.trace(Pn, axis1=-2, axis2=-1)
        act = act[stop_diverged(out["violations"], act, diverged_nodes(xn, Pn), k + 1,
                                nan_from=(out["x_post"], out["phi_post"], out["predicted_mse"]),
                                invalid_from=(out["valid"],))]
    if steps > T:  # beyond the horizon the certificate was not computed: no bound claimed
        out["valid"][:, T + 1:] = False
    return ConsensusBatchResult(**out)


def _factors(candidates: tuple[np.ndarray, np.ndarray], choice: np.ndarray | None, ch, a: int, N: int):
    """Each node's whitened factors of its slots, ``(Gamma (a, N, d, n, n), Sigma (a, N, d, d, n, n))``, from the
    candidates' tables (:meth:`designer.scheduled.ScheduledTables.candidates`) and each node's ``choice`` (a, N)
    (None: the first candidate's, the step's own, for every node)."""
    Gam, Sig = candidates
    d = ch.d_max
    slots = ch.at_slots(np.moveaxis(Gam, 0, 1))  # (N, d, B + 1, n, n)
    if choice is None:
        return (np.broadcast_to(slots[:, :, 0], (a,) + slots[:, :, 0].shape),
                np.broadcast_to(Sig[0, :, :d, :d], (a,) + Sig[0, :, :d, :d].shape))
    nodes = np.arange(N)[None, :]
    return slots[nodes, :, choice], Sig[choice, nodes][:, :, :d, :d]


register_filter("scheduled", run_scheduled_batch)  # the filter of gain rule 'scheduled' (filters.consensus_batch)
