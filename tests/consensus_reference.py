"""The consensus EKF of seed 003 as a straightforward per-run, per-node loop: the tests' reference.

This is the per-run filter that ``filters.consensus.run_consensus`` was before the batched filter
(``filters.consensus_batch``, ``rules.mse.filter``) became the only implementation: node by node
and step by step, (3), (7), the bound recursion (26)-(27) and the gain (30) per node, the χ² gate
and the exchange on the dense adjacency, the tuned weights warm-started by neighbour, mode mse
with its joint covariance and certificate as lists of per-node gains, and the replay of a fixed
gain schedule.  The production batch is compared against it (``tests/test_consensus_batch.py``,
``tests/test_mse_batch.py``): a loop written per node and a stack over (runs, nodes, channels)
must agree run by run, so an error of indexing, masking or bookkeeping in the batch shows.

It shares with production the mathematical building blocks it calls (``designer.bounds``,
``designer.tuning``, ``designer.joint``, the gate's statistic ``filters.channels.gate_channels``),
which are tested against the equations on their own, and the result type.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from designer.bounds import (
    BOUND_LIMIT,
    condition28_margin,
    condition29_margin,
    optimal_gain,
    prediction_bound,
    spectrum,
    theorem2_margin,
    update_bound,
)
from designer.cores import one_blas_thread
from designer.design import ConsensusDesign, validate_design
from designer.linearization import prediction_scaling, update_scaling
from designer.model import Model
from designer.network import SensorNetwork
from designer.joint import (as_difference, certificate_predict, certificate_update, joint_predict, joint_prior,
                          joint_update, mse_gains)
from designer.tuning import lam_max, neighbour_groups, tune_prediction_batch, tune_weighted, warm_start_weights
from designer.validation import InputError
from filters.attacks import AttackPattern
from filters.channels import GATE_COUNTS, channel_difference_covariance, gate_channels, kept_fdi_moments
from filters.consensus import check_run_inputs, wrapped_residual
from filters.consensus_batch import ConsensusResult
from filters.result import DIVERGED

__all__ = ["reference_consensus", "gate", "exchange"]

class NodePrediction(NamedTuple):
    x_pred: np.ndarray
    phi_pred: np.ndarray
    margin28: float
    valid: bool
    sigma: float = np.nan
    F: np.ndarray | None = None  # the Jacobian the prediction was linearised with
    reason: str | None = None  # why (28) failed, when it is not its margin


def node_predict(model: Model, x_post, phi_post, k: int, u, design: ConsensusDesign, valid: bool) -> NodePrediction:
    """One node's prediction (3) and its bound (26), checking (28) on ``Φ_{k|k}``."""
    F = model.F_expected(x_post, k, u)
    x_pred = model.f_expected(x_post, k, u)
    Q = model.process_cov
    U, D = design.U, None
    reason = None
    if valid and not np.trace(phi_post) < BOUND_LIMIT:
        valid, reason = False, f"the bound's trace reached {BOUND_LIMIT:g}: it certifies nothing and (26) overflows"
        margin = -np.inf
    if valid:
        U, D = prediction_scaling(model, x_post, phi_post, k, u, design.linearization, design.radius, U)
    if valid and design.mode in ("tuned", "mse"):  # the σ of (26) does not depend on the gains
        S = spectrum(np.asarray(phi_post, dtype=float)[None])  # one item of the batched filter's stack
        choice = tune_prediction_batch(S, F[None], np.asarray(U, dtype=float)[None], Q, design.epsilon, D=D)
        margin = float(condition28_margin(S, choice.sigma, design.epsilon, D)[0])
        if margin > 0:
            return NodePrediction(x_pred, choice.phi_pred[0], margin, True, float(choice.sigma[0]), F)
    elif valid:
        pb = prediction_bound(phi_post, F, U, Q, design.sigma, design.epsilon, D)
        if pb.phi_pred is not None:
            return NodePrediction(x_pred, pb.phi_pred, pb.margin28, True, design.sigma, F)
        margin = pb.margin28
    elif reason is None:
        margin = np.nan
    # Fallback (sigma = 0, U = 0): F Φ F^T + Q.
    phi = F @ phi_post @ F.T + Q
    return NodePrediction(x_pred, 0.5 * (phi + phi.T), margin, False, F=F, reason=reason)



def gate(x_pred: np.ndarray, attacks_k, network: SensorNetwork, cov_diff: np.ndarray | None, alpha: float
         ) -> tuple[np.ndarray, np.ndarray]:
    """The χ² gate on received neighbour packets: which ones node ``i`` keeps.

    Node ``i`` tests the packet of ``j`` by ``d = x̂_j (+ ξ_ij) - x̂_i`` against the covariance
    ``cov_diff[i, j]`` that ``x̂_j - x̂_i`` has when nobody lies (None will do when ``α = 0``), and keeps it when
    ``dᵀ Σ⁻¹ d <= χ²_{n_x}(1 - α)``: a clean packet with that covariance (Gaussian) is lost
    with probability ``α``, the stated design parameter; a falsified one passes only if its
    displacement hides in the spread of the clean differences.  Returns the mask ``(N, N)``
    of packets kept (received and passed) and the counts of :data:`GATE_COUNTS` (what the
    simulation knows, not the node: which packets were falsified).  One run's form of
    :func:`gate_channels`, on the network's channels.
    """
    adj = network.adjacency
    i, j = np.nonzero(adj)
    if attacks_k is None:
        received, fdi, xi = np.ones(i.size, dtype=bool), None, None
    else:
        dos, fdi, xi = attacks_k
        received, fdi, xi = ~dos[i, j], fdi[i, j], None if xi is None else xi[i, j]
    kept, counts = gate_channels(x_pred, i, j, received, fdi, xi, None if cov_diff is None else cov_diff[i, j], alpha)
    keep = np.zeros(adj.shape, dtype=bool)
    keep[i[kept], j[kept]] = True
    return keep, counts


def exchange(x_pred: np.ndarray, attacks_k: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
             network: SensorNetwork, keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The consensus exchange: what every node receives from its neighbours.

    Returns ``innovation`` (N, n_x), ``sum_j (1 - phi_ij)(x_pred_j + gamma_ij xi_ij - x_pred_i)``,
    and ``s`` (N,), the number of packets each node received (and kept, when ``keep`` — the
    mask of :func:`gate` — is given: a rejected packet counts as lost).
    """
    n = network.n_nodes
    adj = network.adjacency if keep is None else network.adjacency & keep
    if attacks_k is None:
        recv = adj
        injected = np.zeros((n, x_pred.shape[1]))
    else:
        dos, fdi, xi = attacks_k
        recv = adj & ~dos
        injected = np.einsum("ij,ijn->in", (recv & fdi).astype(float), xi)
    s = recv.sum(axis=1).astype(float)
    innovation = recv.astype(float) @ x_pred - s[:, None] * x_pred + injected
    return innovation, s


class NodeUpdate(NamedTuple):
    x_post: np.ndarray
    phi_post: np.ndarray
    K: np.ndarray
    C: np.ndarray
    margin29: float
    valid: bool
    beta: float = np.nan
    weights: np.ndarray | None = None  # modes tuned/mse: the weights p of the groups of (27)



def node_update(model: Model, i: int, pred: NodePrediction, z_i, k1: int, innovation_i, s_i: float,
                neighbour_terms: np.ndarray, design: ConsensusDesign, d_i: int, gains=None, groups=None,
                weights=None) -> NodeUpdate:
    """One node's update (7), gain (30) and bound (27), checking (29) on ``Φ_{k+1|k}``.

    ``gains``: an optional ``(K, C)`` pair to use instead of computing them: replayed from a
    schedule (no bound claimed).
    ``groups``: modes tuned/mse, the neighbour groups of the weighted (27)
    (:func:`designer.tuning.neighbour_groups`; ``neighbour_terms`` is then used only by the
    fallback); ``weights``: a start for the tuned mode's weights (the previous step's).
    """
    x_pred, phi_pred, valid = pred.x_pred, pred.phi_pred, pred.valid
    H = model.H(i, x_pred, k1)
    R = model.measurement_cov(i)
    V, D = design.V[i], None
    if valid:
        V, D = update_scaling(model, i, x_pred, phi_pred, k1, design.linearization, design.radius, V)
    beta = design.beta
    residual = wrapped_residual(model, i, z_i, x_pred, k1)
    choice = None
    if valid and design.mode == "tuned" and gains is None:
        S = spectrum(np.asarray(phi_pred, dtype=float)[None])  # one item of the batched filter's stack
        choice = tune_weighted(S, H, s_i, V, R, groups, D=D, weights=weights)
    if choice is not None:
        margin = float(condition29_margin(S, np.array([choice.beta]), D)[0])
        if margin > 0:
            x_post = x_pred + choice.K @ residual + choice.C @ innovation_i
            return NodeUpdate(x_post, choice.phi_post, choice.K, choice.C, margin, True, choice.beta, choice.weights)
        valid = False  # the chosen beta is inside (29) by construction; reaching here means Φ_pred broke down
    else:
        margin = condition29_margin(phi_pred, beta, D) if valid else np.nan
    if valid and margin <= 0:
        valid = False
    if not valid:
        # Fallback: beta = 0, V = 0 and no bounding inflation ((1 + 2 d_i) -> 1, 3 -> 1): a plain
        # covariance approximation of the consensus EKF, positive definite and free of inverses.
        beta, V, d_i, neighbour_terms, D = 0.0, np.zeros_like(V), 0, neighbour_terms / 3.0, None
    if gains is None:
        C = design.tau * phi_pred
        K = optimal_gain(phi_pred, H, C, s_i, beta, V, R, d_i, D)
    else:
        K, C = gains
    with np.errstate(over="ignore", invalid="ignore"):  # a bound beyond floats is caught as a divergence
        phi_post = update_bound(phi_pred, H, K, C, s_i, beta, V, R, d_i, neighbour_terms, D)
    x_post = x_pred + K @ residual + C @ innovation_i
    return NodeUpdate(x_post, phi_post, K, C, margin, valid, beta if valid else np.nan)



def reference_consensus(model: Model, network: SensorNetwork, z: np.ndarray, design: ConsensusDesign, *,
                        inputs=None, attacks: AttackPattern | None = None, x0=None, phi0=None,
                        gains: tuple[np.ndarray, np.ndarray] | None = None) -> ConsensusResult:
    """One run of the consensus filter, node by node: the parameters and result of
    :func:`filters.consensus.run_consensus` (``gains``: a fixed schedule replayed, no bound claimed)."""
    design = validate_design(design, model, network)
    z, u, x0, phi0 = check_run_inputs(model, z, inputs, x0, phi0, "phi0")
    steps = z.shape[0]
    if design.mode == "mse" and gains is None:
        return _run_mse(model, network, z, u, design, attacks, x0, phi0)
    if design.mode not in ("paper", "tuned") and gains is None:
        raise InputError(f"the reference runs modes paper, tuned and mse, got {design.mode!r}")
    n, nx, dims = network.n_nodes, model.n_x, model.sensor_dims
    nz = max(dims)
    d = network.degrees
    d_max = network.d_max
    zs = [model.split(z[k]) for k in range(steps)]
    # Weights of the neighbour terms in (27): 3 (1 - phibar_ij) and 3 delta^2 gammabar_ij.
    w_phi = 3.0 * (1.0 - network.dos_prob) * network.adjacency
    w_xi = 3.0 * design.delta**2 * (network.fdi_prob * network.adjacency).sum(axis=1)

    x_post, x_pred, phi_post, phi_pred, K, C, valid, m28, m29, th2, sig, bet = _arrays(steps, n, nx, nz, x0, phi0)
    proper = np.ones(n, dtype=bool)  # node still runs Theorem 1's recursion (no violation yet)
    violations: list[dict] = []
    valid[0] = gains is None
    counts = np.zeros((steps, len(GATE_COUNTS)), dtype=np.int64)
    weighted = design.mode == "tuned" and gains is None  # (27) with optimised weights
    q_fdi = _falsified_probability(network)
    weights = [{} for _ in range(n)]  # the tuned mode's weights at the previous step, by group (a warm start)

    def check_theorem2(k, i, sigma):
        th2[k, i] = theorem2_margin(phi_post[k, i], sigma, d_max)
        if th2[k, i] < 0:
            violations.append({"node": i, "step": k, "condition": "theorem2", "margin": float(th2[k, i])})

    def result():
        return ConsensusResult(x_post, x_pred, phi_post, phi_pred, K, C, valid, m28, m29, th2, violations, sig, bet,
                               None, counts)

    for k in range(steps):
        preds = []
        for i in range(n):
            p = node_predict(model, x_post[k, i], phi_post[k, i], k, u[k], design, bool(proper[i] and gains is None))
            preds.append(p)
            x_pred[k, i], phi_pred[k, i], m28[k, i], sig[k, i] = p.x_pred, p.phi_pred, p.margin28, p.sigma
            if p.valid:
                check_theorem2(k, i, p.sigma)
            if proper[i] and gains is None and not p.valid:
                if k == 0 and design.mode == "paper":
                    lam = float(np.linalg.eigvalsh(phi0)[-1])
                    raise InputError(
                        f"sigma must satisfy (28) at the first step: sigma < 1/((1+epsilon) lambda_max(Phi_0|0)) = "
                        f"{1.0 / ((1.0 + design.epsilon) * lam):.6g}, got {design.sigma!r}")
                proper[i] = False
                violations.append({"node": i, "step": k, "condition": "(28)", "margin": float(p.margin28),
                                   **({} if p.reason is None else {"reason": p.reason})})
        # A predicted Φ is a bound when the node's recursion is proper and its Φ_{k|k} was a bound.
        pred_ok = np.array([p.valid for p in preds]) & valid[k]
        att = None if attacks is None else (attacks.dos[k], attacks.fdi[k], attacks.xi[k])
        # The gate tests x̂_j - x̂_i against 2 (Φ_i + Φ_j) >= its covariance (bounds, no cross-covariances).
        cov = 2.0 * (phi_pred[k][:, None] + phi_pred[k][None, :]) if design.gate else None  # (N, N, n, n)
        keep, counts[k] = gate(x_pred[k], att, network, cov, design.gate)
        innovation, s = exchange(x_pred[k], att, network, keep)
        neigh = np.einsum("ij,jab->iab", w_phi, phi_pred[k]) + w_xi[:, None, None] * np.eye(nx)
        rec = [np.flatnonzero(keep[i]) for i in range(n)]
        for i in range(n):
            g = None if gains is None else (gains[0][k, i][:, :dims[i]], gains[1][k, i])
            failure = None
            try:
                groups = neighbour_groups(phi_pred[k, rec[i]], q_fdi[i, rec[i]], design.delta,
                                          span=design.fdi_span) if weighted else None
                upd = node_update(model, i, preds[i], zs[k][i], k + 1, innovation[i], s[i], neigh[i], design,
                                  int(d[i]), g, groups, _warm_start(weights[i], rec[i], groups))
            except np.linalg.LinAlgError as exc:
                failure = f"numerical breakdown: {exc}"
            else:
                if not (np.all(np.isfinite(upd.x_post)) and np.all(np.isfinite(upd.phi_post))
                        and np.abs(upd.x_post).max() < DIVERGED):
                    failure = f"estimate or covariance beyond {DIVERGED:g} or not finite"
            if failure is not None:
                _stop(violations, i, k, failure, (x_post, phi_post), (x_pred, phi_pred, K, C), valid)
                return result()
            x_post[k + 1, i], phi_post[k + 1, i], C[k, i] = upd.x_post, upd.phi_post, upd.C
            K[k, i] = 0.0
            K[k, i, :, :dims[i]] = upd.K
            m29[k, i], bet[k, i] = upd.margin29, upd.beta
            if upd.weights is not None:
                weights[i] = dict(zip(_group_keys(rec[i], len(upd.weights)), upd.weights))
            if preds[i].valid and not upd.valid:
                if k == 0 and design.mode == "paper":
                    lam = float(np.linalg.eigvalsh(phi_pred[0, i])[-1])
                    raise InputError(
                        f"beta must satisfy (29) at the first step: beta < 1/lambda_max(Phi_1|0) = {1.0 / lam:.6g} "
                        f"at node {i}, got {design.beta!r}")
                proper[i] = False
                violations.append({"node": i, "step": k + 1, "condition": "(29)", "margin": float(upd.margin29)})
            valid[k + 1, i] = upd.valid and pred_ok[i] and all(pred_ok[j] for j in network.neighbours[i])
    for i in range(n):  # Φ_{K|K} against the last σ the node used
        if valid[steps, i]:
            check_theorem2(steps, i, sig[steps - 1, i])
    return result()


def _arrays(steps: int, n: int, nx: int, nz: int, x0, phi0) -> tuple:
    """The result arrays of a run, NaN (False for ``valid``) except the initial estimate and Φ_0|0."""
    x_post, phi_post = np.full((steps + 1, n, nx), np.nan), np.full((steps + 1, n, nx, nx), np.nan)
    x_post[0], phi_post[0] = x0, phi0
    return (x_post, np.full((steps, n, nx), np.nan), phi_post, np.full((steps, n, nx, nx), np.nan),
            np.full((steps, n, nx, nz), np.nan), np.full((steps, n, nx, nx), np.nan),
            np.zeros((steps + 1, n), dtype=bool), np.full((steps, n), np.nan), np.full((steps, n), np.nan),
            np.full((steps + 1, n), np.nan), np.full((steps, n), np.nan), np.full((steps, n), np.nan))


def _stop(violations: list, node: int, k: int, reason: str, posts, steps_arrays, valid) -> None:
    """A divergence at step k+1: flag it, and NaN everything from there on (nothing is carried on)."""
    violations.append({"node": node, "step": k + 1, "condition": "diverged", "margin": -np.inf, "reason": reason})
    for arr in posts:
        arr[k + 1:] = np.nan
    for arr in steps_arrays:
        arr[k + 1:] = np.nan
    steps_arrays[2][k], steps_arrays[3][k] = np.nan, np.nan  # the gains of the failed step
    valid[k + 1:] = False


def _group_keys(received, count: int) -> list:
    """The groups of the weighted (27) by name: the node's own, each received neighbour's, the falsified packets'."""
    keys = ["own"] + [int(j) for j in received]
    return keys + ["fdi"] if count > len(keys) else keys


def _warm_start(previous: dict, received, groups) -> np.ndarray | None:
    """Last step's weights of the groups that are still there (new ones: their mean), at least 1e-6, renormalised
    (:func:`designer.tuning.warm_start_weights` of one node)."""
    if groups is None or not previous:
        return None
    keys = _group_keys(received, len(groups) + 1)
    prev = np.array([previous.get(k, np.nan) for k in keys], dtype=float)
    return warm_start_weights(prev[None], np.ones((1, len(keys)), dtype=bool))[0]


def _falsified_probability(network: SensorNetwork) -> np.ndarray:
    """``q_ij``: the probability that a received packet is falsified (DoS and FDI are exclusive)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(network.adjacency, network.fdi_prob / (1.0 - network.dos_prob), 0.0)


def _binding_node(phi_blocks: np.ndarray, D) -> int:
    """The node whose bound is largest along the structure (where a joint condition binds)."""
    return int(np.argmax([lam_max(phi_blocks[i, i], None if D is None else D[i]) for i in range(len(phi_blocks))]))


@one_blas_thread()  # its joint matrices are N n wide: the same bits in any process
def _run_mse(model: Model, network: SensorNetwork, z, u, design: ConsensusDesign, attacks, x0, phi0
             ) -> ConsensusResult:
    """Mode mse: the gains of :func:`designer.joint.mse_gains` and the joint certificate of :mod:`designer.joint`.

    One σ and one β certify the stacked error of all nodes, so (28)-(29) are conditions on
    the network: a violation is recorded at the node where it binds and ends every node's
    certificate (the filter goes on with the same gains, its Φ then the joint covariance
    without the remainders' inflation, not a bound).
    """
    steps = z.shape[0]
    n, nx, dims = network.n_nodes, model.n_x, model.sensor_dims
    nz, d_max = max(dims), network.d_max
    zs = [model.split(z[k]) for k in range(steps)]
    q_fdi = _falsified_probability(network)
    ch = np.nonzero(network.adjacency)  # the directed channels (receiver, sender), the gate's order
    R_all = [model.measurement_cov(i) for i in range(n)]
    Q = model.process_cov
    x_post, x_pred, phi_post, phi_pred, K, C, valid, m28, m29, th2, sig, bet = _arrays(steps, n, nx, nz, x0, phi0)
    pmse = np.full((steps + 1, n), np.nan)
    kappa = np.full((steps, n), np.nan)
    violations: list[dict] = []
    valid[0], pmse[0] = True, np.trace(phi0)
    counts = np.zeros((steps, len(GATE_COUNTS)), dtype=np.int64)
    # Every node starts at the same estimate: their errors are one error (Φ_0|0 >= P_0|0 for the stack too).
    Pj = as_difference(joint_prior(phi0, n))  # the joint error covariance the gains are chosen for (difference form)
    Bj = joint_prior(phi0, n)  # its certificate (the bound of the stacked error)
    proper = True

    def result():
        return ConsensusResult(x_post, x_pred, phi_post, phi_pred, K, C, valid, m28, m29, th2, violations, sig, bet,
                               pmse, counts, kappa)

    for k in range(steps):
        F = [model.F_expected(x_post[k, i], k, u[k]) for i in range(n)]
        for i in range(n):
            x_pred[k, i] = model.f_expected(x_post[k, i], k, u[k])
        if proper and not np.trace(_diag(Bj), axis1=1, axis2=2).max() < BOUND_LIMIT:
            proper = False
            violations.append({"node": _binding_node(Bj, None), "step": k, "condition": "(28)", "margin": -np.inf,
                               "reason": f"the bound's trace reached {BOUND_LIMIT:g}: it certifies nothing and "
                                         "(26) overflows"})
        if proper:
            sc = [prediction_scaling(model, x_post[k, i], Bj[i, i], k, u[k], design.linearization, design.radius,
                                     design.U) for i in range(n)]
            Df = None if all(s[1] is None for s in sc) else [s[1] for s in sc]
            jp = certificate_predict(Bj, F, [s[0] for s in sc], Q, design.epsilon, Df)
            m28[k], sig[k] = jp.margin, jp.multiplier
            if jp.margin > 0:
                Bp = jp.phi
                for i in range(n):
                    th2[k, i] = theorem2_margin(phi_post[k, i], jp.multiplier, d_max)
                    if th2[k, i] < 0:
                        violations.append({"node": i, "step": k, "condition": "theorem2", "margin": float(th2[k, i])})
            else:
                proper = False
                violations.append({"node": _binding_node(Bj, Df), "step": k, "condition": "(28)",
                                   "margin": float(jp.margin)})
        if not proper:
            Bp = joint_predict(Bj, F, Q)
        phi_pred[k] = _diag(Bp)
        att = None if attacks is None else (attacks.dos[k], attacks.fdi[k], attacks.xi[k])
        Pm = joint_predict(Pj, F, Q)
        cov_diff = _difference_covariance(Pm) if design.gate else None
        keep, counts[k] = gate(x_pred[k], att, network, cov_diff, design.gate)
        innovation, s = exchange(x_pred[k], att, network, keep)
        rec = [np.flatnonzero(keep[i]) for i in range(n)]
        Hs = [model.H(i, x_pred[k, i], k + 1) for i in range(n)]
        # What the falsified packets add: all of them without a gate; with one, those that pass (a model of the
        # gate that the Monte Carlo bound check validates: which packets pass depends on the errors).
        S = [q_fdi[i, rec[i]].sum() * design.fdi_moment for i in range(n)] \
            if design.gate == 0 or design.fdi_signal is None else \
            kept_fdi_moments(design, keep[ch], q_fdi[ch], cov_diff[ch], ch[0], n)
        gains = [mse_gains(Pm, i, rec[i], Hs[i], R_all[i], S[i], condition=True) for i in range(n)]
        Ks, Cs, kappa[k] = [g[0] for g in gains], [g[1] for g in gains], [g[2] for g in gains]
        for i in range(n):
            residual = wrapped_residual(model, i, zs[k][i], x_pred[k, i], k + 1)
            x_post[k + 1, i] = x_pred[k, i] + Ks[i] @ residual + Cs[i] @ innovation[i]
            K[k, i] = 0.0
            K[k, i, :, :dims[i]] = Ks[i]
            C[k, i] = Cs[i]
        Pj = joint_update(Pm, Ks, Cs, Hs, R_all, rec, S)
        pmse[k + 1] = np.trace(Pj.P, axis1=-2, axis2=-1)
        if proper:
            sc = [update_scaling(model, i, x_pred[k, i], Bp[i, i], k + 1, design.linearization, design.radius,
                                 design.V[i]) for i in range(n)]
            Dh = None if all(s[1] is None for s in sc) else [s[1] for s in sc]
            with np.errstate(over="ignore", invalid="ignore"):
                ju = certificate_update(Bp, Ks, Cs, Hs, R_all, [s[0] for s in sc], rec, S, design.fdi_mean,
                                        [q_fdi[i, rec[i]] for i in range(n)], Dh)
            m29[k], bet[k] = ju.margin, ju.multiplier
            if ju.margin > 0:
                Bj = ju.phi
            else:
                proper = False
                violations.append({"node": _binding_node(Bp, Dh), "step": k + 1, "condition": "(29)",
                                   "margin": float(ju.margin)})
        if not proper:
            with np.errstate(over="ignore", invalid="ignore"):
                Bj = joint_update(Bp, Ks, Cs, Hs, R_all, rec, S)
        phi_post[k + 1] = _diag(Bj)
        valid[k + 1] = proper
        bad = next((i for i in range(n) if not (np.all(np.isfinite(x_post[k + 1, i]))
                                               and np.all(np.isfinite(phi_post[k + 1, i]))
                                               and np.abs(x_post[k + 1, i]).max() < DIVERGED)), None)
        if bad is not None:
            _stop(violations, bad, k, f"estimate or covariance beyond {DIVERGED:g} or not finite",
                  (x_post, phi_post, pmse), (x_pred, phi_pred, K, C, kappa), valid)
            kappa[k] = np.nan
            return result()
    if proper:
        for i in range(n):
            th2[steps, i] = theorem2_margin(phi_post[steps, i], sig[steps - 1, i], d_max)
            if th2[steps, i] < 0:
                violations.append({"node": i, "step": steps, "condition": "theorem2", "margin": float(th2[steps, i])})
    return result()


def _difference_covariance(P) -> np.ndarray:
    """``Cov(e_j - e_i)`` (N, N, n, n) for every pair of nodes from the joint covariance."""
    N, n = P.P.shape[-3], P.P.shape[-1]
    i, j = np.indices((N, N)).reshape(2, -1)
    return channel_difference_covariance(P, i, j).reshape(N, N, n, n)


def _diag(P: np.ndarray) -> np.ndarray:
    """The diagonal blocks ``P[i, i]`` (N, n, n) of a joint (N, N, n, n) array."""
    idx = np.arange(P.shape[0])
    return P[idx, idx]
