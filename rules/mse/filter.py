"""The consensus EKF in mode ``'mse'`` batched over Monte Carlo runs: :func:`run_mse_batch`.

:func:`filters.consensus_batch.run_consensus_batch` (and so :func:`filters.consensus.run_consensus`, a
batch of one) dispatches ``design.mode == 'mse'`` here: every node's gains are the linear-MMSE ones
from the joint error covariance of all nodes, and one σ and one β certify the stacked error of all
nodes (:mod:`designer.joint`).  Here every quantity of a step is a stack over the runs still going:
the joint covariance ``(runs, N, N, n, n)`` and its certificate go through the functions of
:mod:`designer.joint` with a leading runs axis, the gains are solved per node over all runs at once
(the kept packets as masks), and the χ² gate on neighbour packets works on the network's directed
channels of every run (:func:`filters.channels.gate_channels`,
:func:`~filters.channels.channel_difference_covariance`, :func:`~filters.channels.kept_fdi_moments`: the
gate's one home).

Run ``r`` of the result equals the per-node loop of the tests' reference (``tests/consensus_reference.py``)
to rounding: estimates, bounds, gains, predicted MSE, σ, β, margins, the ``valid`` flags, the violations in
the same order (the trace limit, (28), Theorem 2, (29) at the node where a joint condition
binds), the gate's counts, and divergence, which stops only its run (its step runs on
:func:`filters.engine.run_batch`, once per sub-batch).  Without a gate the two
take the same floating-point steps (equal to the bit on the built-in scenarios).  With a
gate and an FDI signal, what the kept falsified packets add (:func:`kept_fdi_moments`) comes from
:meth:`designer.attacks.FDISignal.passing`, whose quadrature (a matrix-vector product) rounds
differently with the number of packets it is given: the runs then agree to rounding, and a flag
can differ only where a margin is itself at rounding level (e.g. a bound that has blown up).

**Memory.**  Each run holds a few joint ``(N n) x (N n)`` matrices (the covariance, its
certificate, their predictions, the transition, eigenvectors and products: about
:data:`JOINT_COPIES` of them at once), so the runs are processed in sub-batches of at most
:data:`MEMORY_BUDGET` bytes of joint matrices, and ``N n`` beyond :data:`MAX_JOINT_DIM` is
refused (one run alone would need more than the budget).  The cost per node and step grows as
``(N n)²`` (the eigendecompositions of the joint matrices), not linearly like the paper mode's.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from designer.cores import one_blas_thread
from designer.bounds import BOUND_LIMIT, theorem2_margin
from designer.design import ConsensusDesign, validate_design
from designer.linearization import prediction_scaling, update_scaling
from designer.model import Model
from designer.joint import (
    as_difference,
    certificate_predict,
    certificate_update,
    joint_predict,
    joint_prior,
    joint_update,
    mse_gains,
    node_blocks,
)
from designer.network import SensorNetwork
from designer.tuning import lam_max
from designer.validation import InputError

from filters.attacks import AttackPattern
from filters.channels import channel_difference_covariance, gate_channels, kept_fdi_moments
from filters.consensus_batch import (LIMIT_REASON, ConsensusBatchResult, EdgeAttacks, batch_inputs, consensus_result,
                              edge_attacks, per_run, result_arrays, run_networks, wrap_residuals)
from filters.engine import Step, run_batch
from filters.result import FilterResult, diverged_nodes

from .memory import JOINT_COPIES, MEMORY_BUDGET  # the rule's own, which the memory estimate reads too

__all__ = ["run_mse_batch", "MAX_JOINT_DIM", "MEMORY_BUDGET"]

MAX_JOINT_DIM = 1024  # N n beyond this is refused: one run's joint matrices alone exceed MEMORY_BUDGET


# --------------------------------------------------------------------------- the filter
@one_blas_thread()  # its joint matrices are N n wide: the same bits in any process
def run_mse_batch(model: Model, network: SensorNetwork | Sequence[SensorNetwork], z: np.ndarray, design: ConsensusDesign, *,
                  inputs=None, attacks: EdgeAttacks | Sequence[AttackPattern] | None = None, x0=None,
                  phi0=None, predictions: bool = True) -> FilterResult:
    """Run the consensus filter in mode ``'mse'`` at every node over many runs of measurements ``z``.

    The parameters are those of :func:`filters.consensus_batch.run_consensus_batch` (one network or one per
    run, ``z`` (runs, steps, n_z), inputs shared or per run, attacks as :class:`EdgeAttacks` or one AttackPattern per run, ``x0``
    and ``phi0`` shared or per run); ``design`` is in mode ``'mse'``, with or without a gate
    (``design.gate``), under any linearisation rule.

    Returns
    -------
    FilterResult
        :func:`filters.consensus_batch.consensus_result` of the runs: ``detail`` a ``ConsensusBatchResult`` with
        ``predicted_mse`` (runs, steps+1, N) and ``gate_counts`` (runs, steps, 5).

    Raises
    ------
    InputError
        For bad input, a mode other than ``'mse'``, and a joint covariance too large to hold:
        ``N n`` above :data:`MAX_JOINT_DIM` (= 1024).  Below it the runs are processed in
        sub-batches whose joint matrices take at most :data:`MEMORY_BUDGET` bytes (256 MiB).
    """
    z, u, x0, phi0 = batch_inputs(model, z, inputs, x0, phi0)
    runs, steps = z.shape[:2]
    network, nets = run_networks(network, runs)
    design = validate_design(design, model, network)
    if not design.rule.joint_covariance:
        raise InputError(f"run_mse_batch runs a gain rule of the joint covariance (mse), got mode {design.mode!r} "
                         "(filters.consensus_batch runs the others)")
    q = per_run(lambda net: net.falsified_prob, network, nets)  # (1 or runs, N, N)
    n, nx = network.n_nodes, model.n_x
    if n * nx > MAX_JOINT_DIM:
        raise InputError(f"run_mse_batch holds the joint error covariance of all nodes, N n = {n} x {nx} = {n * nx} "
                         f"rows per run; at most MAX_JOINT_DIM = {MAX_JOINT_DIM} fit its memory budget")
    attacks = edge_attacks(network, attacks, runs, steps, nx)
    nz = max(model.sensor_dims)
    out = result_arrays(runs, steps, n, nx, nz)
    out["x_post"][:, 0], out["phi_post"][:, 0], out["valid"][:, 0] = x0[:, None], phi0[:, None], True
    out["predicted_mse"][:, 0] = np.trace(phi0, axis1=-2, axis2=-1)[:, None]
    chunk = max(1, MEMORY_BUDGET // (JOINT_COPIES * 8 * (n * nx) ** 2))
    for start in range(0, runs, chunk):
        sl = slice(start, min(start + chunk, runs))
        part = {key: v[sl] for key, v in out.items()}  # views (and the runs' own violation lists)
        att = None if attacks is None else EdgeAttacks(attacks.receiver, attacks.sender, attacks.dos[sl],
                                                       attacks.fdi[sl], attacks.xi[sl])
        _Runs(model, network, design, part, z[sl], u if u.ndim == 2 else u[sl], att, phi0[sl],
              q if nets is None else q[sl]).run()
    return consensus_result(ConsensusBatchResult(**out), network, design)


def _binding_node(phi_blocks: np.ndarray, D) -> int:
    """The node whose bound is largest along the structure (where a joint condition binds)."""
    return int(np.argmax([lam_max(phi_blocks[i, i], None if D is None else D[i]) for i in range(len(phi_blocks))]))


class _Runs:
    """One sub-batch of runs; writes into the views ``out`` of the result arrays."""

    def __init__(self, model: Model, network: SensorNetwork, design: ConsensusDesign, out: dict, z, u, attacks,
                 phi0, q):
        self.model, self.network, self.design, self.out = model, network, design, out
        self.z, self.u, self.attacks = z, u, attacks
        self.n, self.nx = network.n_nodes, model.n_x
        self.receiver, self.sender = np.nonzero(network.adjacency)
        self.q = q  # (1 or runs, N, N): the probability that a received packet is falsified, per channel (and run)
        self.R = [model.measurement_cov(i) for i in range(self.n)]
        offsets = model.sensor_offsets
        self.columns = [slice(int(a), int(b)) for a, b in zip(offsets[:-1], offsets[1:])]
        self.Bj = joint_prior(phi0, self.n)  # the certificate (the bound of the stacked error), absolute blocks
        self.Pj = as_difference(self.Bj)  # the joint error covariance the gains are chosen for (difference form)
        self.act = np.arange(z.shape[0])  # the runs still going (indices into the sub-batch)
        self.proper = np.ones(z.shape[0], dtype=bool)

    def violation(self, r: int, node: int, step: int, condition: str, margin: float, reason: str | None = None):
        self.out["violations"][int(self.act[r])].append(
            {"node": int(node), "step": int(step), "condition": condition, "margin": float(margin),
             **({} if reason is None else {"reason": reason})})

    def theorem2_violations(self, runs: np.ndarray, margins: np.ndarray, step: int) -> None:
        """:meth:`violation` for every negative theorem-2 margin of ``margins`` (runs, N) of the sub-batch's
        ``runs`` (the loose certificates of mode mse give one per run and node at most steps: the Python
        conversions are made once per array, not per violation)."""
        j, i = np.nonzero(margins < 0)
        lists, step = self.out["violations"], int(step)
        for r, node, m in zip(self.act[runs[j]].tolist(), i.tolist(), margins[j, i].tolist()):
            lists[r].append({"node": node, "step": step, "condition": "theorem2", "margin": m})

    def run(self) -> None:
        """The steps (:meth:`step` on :func:`filters.engine.run_batch`), then Theorem 2 on ``Φ_{K|K}``."""
        steps = self.z.shape[1]
        o = self.out
        self.act = act = run_batch(self.step, o, o["violations"], steps,
                                   nan_from=("x_post", "phi_post", "predicted_mse"),
                                   nan_before=("K", "C", "gain_condition"), invalid_from=("valid",),
                                   stopped=self.stopped)
        if not act.size:
            return
        last = np.flatnonzero(self.proper)
        if last.size:
            th = theorem2_margin(o["phi_post"][act[last], steps], o["sigma"][act[last], steps - 1], self.network.d_max)
            o["theorem2"][act[last], steps] = th
            self.theorem2_violations(last, th, steps)

    def step(self, k: int, runs: np.ndarray, act) -> Step:
        """Step ``k`` of the ``runs`` going on (``act`` them as an index: a view while none stopped)."""
        model, design, o, n, nx = self.model, self.design, self.out, self.n, self.nx
        self.act = runs
        a = runs.size
        Q = model.process_cov
        xk = o["x_post"][act, k]
        uk = self.u[k] if self.u.ndim == 2 else self.u[act, k][:, None, :]
        F = model.F_expected(xk, k, uk)
        xp = model.f_expected(xk, k, uk)
        Bj, Pj = self.Bj, self.Pj
        # ---- the certificate's prediction (26), (28)
        tr = np.trace(node_blocks(Bj), axis1=-2, axis2=-1)
        for r in np.flatnonzero(self.proper & ~(tr.max(axis=-1) < BOUND_LIMIT)):
            self.proper[r] = False
            self.violation(r, _binding_node(Bj[r], None), k, "(28)", -np.inf, LIMIT_REASON)
        Bp = None
        done = np.zeros(a, dtype=bool)
        sel = np.flatnonzero(self.proper)
        if sel.size:
            every = sel.size == a
            pick = (lambda x: x) if every else (lambda x: x[sel])  # noqa: E731  (no copies when every run is in)
            ub = uk if uk.ndim == 1 else np.broadcast_to(pick(uk), (sel.size, n, uk.shape[-1]))
            U, D = prediction_scaling(model, pick(xk), node_blocks(pick(Bj)), k, ub, design.linearization,
                                      design.radius, design.U)
            Df = None if D is None else [D] * n
            jp = certificate_predict(pick(Bj), pick(F), np.broadcast_to(U, (sel.size, n, nx, nx)), Q,
                                     design.epsilon, Df)
            Bp, ok = self.certified(jp, sel, Bj, k, "margin28", "sigma")
            rows = self.act[sel]
            done[sel[ok]] = True
            th = theorem2_margin(o["phi_post"][rows, k], jp.multiplier[:, None], self.network.d_max)
            o["theorem2"][rows[ok], k] = th[ok]
            self.theorem2_violations(sel[ok], th[ok], k)
            for j in np.flatnonzero(~ok):
                self.proper[sel[j]] = False
                self.violation(sel[j], _binding_node(Bj[sel[j]], Df), k, "(28)", jp.margin[j])
        if not done.all():
            if Bp is None:
                Bp = np.empty_like(Bj)
            Bp[~done] = joint_predict(Bj[~done], F[~done], Q)
        # ---- the gate and the exchange, on the channels
        Pm = joint_predict(Pj, F, Q)
        rcv, snd = self.receiver, self.sender
        att = self.attacks
        if att is None:
            received, fdi, xi = np.ones((a, rcv.size), dtype=bool), np.zeros((a, rcv.size), dtype=bool), None
        else:
            received, fdi, xi = ~att.dos[act, k], att.fdi[act, k], att.xi[act, k]
        cov_diff = None if not design.gate else channel_difference_covariance(Pm, rcv, snd)
        keep, counts = gate_channels(xp, rcv, snd, received, fdi, xi, cov_diff, design.gate)
        kept = np.zeros((a, n, n), dtype=bool)
        kept[:, rcv, snd] = keep
        s = kept.sum(axis=-1)
        innovation = kept.astype(float) @ xp - s[..., None] * xp
        if xi is not None:
            falsified = np.zeros((a, n, n, nx))
            falsified[:, rcv, snd] = (keep & fdi)[..., None] * xi
            innovation = innovation + falsified.sum(axis=-2)
        q = self.q if self.q.shape[0] == 1 else self.q[act]
        q_kept = np.where(kept, q, 0.0)
        if design.gate == 0 or design.fdi_signal is None:
            S = q_kept.sum(axis=-1)[..., None, None] * design.fdi_moment
        else:
            S = kept_fdi_moments(design, keep, q[:, rcv, snd], cov_diff, rcv, n)
        # ---- the gains (per node, over the runs) and the estimates
        H, Ks = [], []
        C = np.empty((a, n, nx, nx))
        zk = self.z[act, k]
        x_new = np.empty((a, n, nx))
        K = np.zeros((a, n, nx, o["K"].shape[-1]))
        condition = np.empty((a, n))
        for i in range(n):
            Hi = model.H(i, xp[:, i], k + 1)
            res = wrap_residuals(zk[:, self.columns[i]] - model.h(i, xp[:, i], k + 1), model.sensors[i].angles)
            Ki, C[:, i], condition[:, i] = mse_gains(Pm, i, kept[:, i], Hi, self.R[i], S[:, i], condition=True)
            x_new[:, i] = xp[:, i] + (Ki @ res[..., None])[..., 0] + (C[:, i] @ innovation[:, i, :, None])[..., 0]
            H.append(Hi)
            Ks.append(Ki)
            K[:, i, :, :Ki.shape[-1]] = Ki
        self.Pj = joint_update(Pm, Ks, C, H, self.R, kept, S)
        # ---- the certificate's update (27), (29)
        Bn = None
        done = np.zeros(a, dtype=bool)
        sel = np.flatnonzero(self.proper)
        if sel.size:
            every = sel.size == a
            pick = (lambda x: x) if every else (lambda x: x[sel])  # noqa: E731
            Vs, Ds = [], []
            for i in range(n):
                Vi, Di = update_scaling(model, i, pick(xp[:, i]), pick(Bp[:, i, i]), k + 1, design.linearization,
                                        design.radius, design.V[i])
                Vs.append(Vi)
                Ds.append(Di)
            Dh = None if all(d is None for d in Ds) else Ds
            ju = certificate_update(pick(Bp), [pick(Ki) for Ki in Ks], pick(C), [pick(Hi) for Hi in H], self.R, Vs,
                                    pick(kept), pick(S), design.fdi_mean, pick(q_kept), Dh)
            Bn, ok = self.certified(ju, sel, Bp, k, "margin29", "beta")
            done[sel[ok]] = True
            for j in np.flatnonzero(~ok):
                self.proper[sel[j]] = False
                self.violation(sel[j], _binding_node(Bp[sel[j]], Dh), k + 1, "(29)", ju.margin[j])
        if not done.all():
            if Bn is None:
                Bn = np.empty_like(Bp)
            with np.errstate(over="ignore", invalid="ignore"):
                Bn[~done] = joint_update(Bp[~done], [Ki[~done] for Ki in Ks], C[~done], [Hi[~done] for Hi in H],
                                         self.R, kept[~done], S[~done])
        self.Bj = Bn
        phi = node_blocks(Bn)
        return Step(dict(x_pred=xp, phi_pred=node_blocks(Bp), gate_counts=counts, gain_condition=condition, K=K, C=C),
                    dict(x_post=x_new, predicted_mse=np.trace(node_blocks(self.Pj), axis1=-2, axis2=-1), phi_post=phi,
                         valid=self.proper[:, None]), diverged_nodes(x_new, phi))

    def certified(self, bound, sel: np.ndarray, like: np.ndarray, k: int, margin: str, multiplier: str):
        """A joint certificate of the runs ``sel``: its margin and multiplier recorded at every node, and the
        joint array with its bound where the condition holds (the other runs' entries are the caller's to fill),
        with the mask of those runs."""
        rows = self.act[sel]
        self.out[margin][rows, k] = bound.margin[:, None]
        self.out[multiplier][rows, k] = bound.multiplier[:, None]
        ok = bound.margin > 0
        if sel.size == like.shape[0] and ok.all():
            return bound.phi, ok
        out = np.empty_like(like)
        out[sel[ok]] = bound.phi[ok]
        return out, ok

    def stopped(self, alive: np.ndarray) -> None:
        """The runs that stopped (``alive`` False) leave the sub-batch's state."""
        self.proper, self.Pj, self.Bj = self.proper[alive], self.Pj.take(alive), self.Bj[alive]


