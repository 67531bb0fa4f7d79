"""KCF and HCMCI as a straightforward per-run, per-node loop: the tests' reference.

This is the per-run filter that ``filters.distributed.run_kcf`` / ``run_hcmci`` were before the batched
filter (``run_kcf_batch`` / ``run_hcmci_batch``) became the only implementation, written out node by node
and step by step from the equations of the module docstring of :mod:`filters.distributed`: every node's
prediction and Jacobian, its measurement information, KCF's update over the packets it heard, HCMCI's ``L``
rounds of consensus with Metropolis weights built here from the degrees, the FDI injections per channel, ``ω``,
and the bookkeeping of packets and divergence.  The production batch (a stack over runs and nodes) is compared
against it run by run (``tests/test_distributed.py``), so an error of indexing, masking or bookkeeping shows.

It shares with production only the model layer (``f``, ``F``, ``h``, ``H``), the wrapped residual
(``filters.consensus.wrapped_residual``), the divergence threshold and the result type.  Not imported by
production or benchmarks.
"""
from __future__ import annotations

import numpy as np

from designer.model import Model
from designer.network import SensorNetwork
from filters.attacks import AttackPattern
from filters.consensus import check_run_inputs, wrapped_residual
from filters.result import DIVERGED
from filters.distributed import DistributedResult

__all__ = ["reference_kcf", "reference_hcmci", "spd_inverse"]

BEYOND = f"estimate or covariance beyond {DIVERGED:g} or not finite"


def spd_inverse(A: np.ndarray) -> np.ndarray:
    """The inverse of one symmetric positive-definite matrix (raises LinAlgError where Cholesky fails)."""
    np.linalg.cholesky(0.5 * (A + A.T))
    return np.linalg.inv(A)


def _fails(x: np.ndarray, P: np.ndarray) -> bool:
    return not (np.isfinite(x).all() and np.isfinite(P).all() and np.abs(x).max() < DIVERGED)


def _weights(network: SensorNetwork, recv: np.ndarray) -> np.ndarray:
    """Metropolis weights on the channels whose packet arrived; a lost channel's weight goes to the node."""
    n = network.n_nodes
    deg = [sum(1 for a, b in network.edges if i in (a, b)) for i in range(n)]
    W = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            if j != i and recv[i, j]:
                W[i, j] = 1.0 / (1.0 + max(deg[i], deg[j]))
        W[i, i] = 1.0 - W[i].sum()
    return W


def _kcf_node(i, eps, packet, xp, Pp, U, u, recv, fdi, xi):
    heard = [j for j in range(len(xp)) if j == i or recv[i, j]]
    S = sum(U[j] for j in heard)
    y = sum(u[j] for j in heard)
    M = spd_inverse(spd_inverse(Pp[i]) + S)
    gamma = eps / (1.0 + np.linalg.norm(M))
    diff = np.zeros_like(xp[i])
    for j in heard:
        if j == i:
            continue
        lie = fdi is not None and fdi[i, j]
        diff += xp[j] + (xi[i, j] if lie else 0.0) - xp[i]
        if lie and packet:
            y = y + U[j] @ xi[i, j]
    return xp[i] + M @ (y - S @ xp[i] + gamma * diff), M


def _hcmci_all(network, L, omega, packet, xp, Pp, U, u, recv, fdi, xi):
    n = len(xp)
    W = _weights(network, recv)
    O = [spd_inverse(Pp[i]) for i in range(n)]
    q = [O[i] @ xp[i] for i in range(n)]
    dO, dq = list(U), list(u)
    for _ in range(L):
        q_new, dq_new, O_new, dO_new = [], [], [], []
        for i in range(n):
            qi, dqi = np.zeros_like(q[i]), np.zeros_like(dq[i])
            for j in range(n):
                lie = fdi is not None and j != i and recv[i, j] and fdi[i, j]
                qi = qi + W[i, j] * (q[j] + (O[j] @ xi[i, j] if lie else 0.0))
                dqi = dqi + W[i, j] * (dq[j] + (dO[j] @ xi[i, j] if lie and packet else 0.0))
            q_new.append(qi)
            dq_new.append(dqi)
            O_new.append(sum(W[i, j] * O[j] for j in range(n)))
            dO_new.append(sum(W[i, j] * dO[j] for j in range(n)))
        q, dq, O, dO = q_new, dq_new, O_new, dO_new
    WL = np.linalg.matrix_power(W, L)
    om = np.array([float(n) if omega == "size" else 1.0 / WL[i].max() for i in range(n)])
    x, P = [], []
    for i in range(n):
        Pi = spd_inverse(O[i] + om[i] * dO[i])
        x.append(Pi @ (q[i] + om[i] * dq[i]))
        P.append(Pi)
    return np.array(x), np.array(P), om


def _loop(model: Model, network: SensorNetwork, z, inputs, attacks: AttackPattern | None, x0, P0, rounds: int,
          update) -> DistributedResult:
    """Predict at every node, ``update(k, xp, Pp, U, u, recv)`` all of them, stop at the first divergence."""
    z, u_in, x0, P0 = check_run_inputs(model, z, inputs, x0, P0)
    n, nx, steps = network.n_nodes, model.n_x, z.shape[0]
    x_post = np.full((steps + 1, n, nx), np.nan)
    P_post = np.full((steps + 1, n, nx, nx), np.nan)
    x_pred = np.full((steps, n, nx), np.nan)
    P_pred = np.full((steps, n, nx, nx), np.nan)
    omega = np.full((steps, n), np.nan)
    x_post[0], P_post[0] = x0, P0
    sent = np.full(steps, 2 * len(network.edges) * rounds)
    delivered = np.zeros(steps, int)
    violations = []
    R_inv = [np.linalg.inv(model.measurement_cov(i)) for i in range(n)]
    for k in range(steps):
        recv = np.array(network.adjacency, dtype=bool)
        if attacks is not None:
            recv &= ~attacks.dos[k]
        delivered[k] = int(recv.sum()) * rounds
        zs = model.split(z[k])
        for i in range(n):
            x_pred[k, i] = model.f_expected(x_post[k, i], k, u_in[k])
            F = model.F_expected(x_post[k, i], k, u_in[k])
            Pp = F @ P_post[k, i] @ F.T + model.process_cov
            P_pred[k, i] = 0.5 * (Pp + Pp.T)
        bad = [i for i in range(n) if _fails(x_pred[k, i], P_pred[k, i])]
        node, reason = (bad[0], f"prediction: {BEYOND}") if bad else (None, None)
        if reason is None:
            U, uu = [], []
            for i in range(n):
                H = model.H(i, x_pred[k, i], k + 1)
                U.append(H.T @ R_inv[i] @ H)
                uu.append(H.T @ R_inv[i] @ (wrapped_residual(model, i, zs[i], x_pred[k, i], k + 1) + H @ x_pred[k, i]))
            try:
                x, P, om = update(k, x_pred[k], P_pred[k], U, uu, recv)
            except np.linalg.LinAlgError as exc:
                node, reason = 0, f"numerical breakdown: {exc}"
                for i in range(n):
                    try:
                        np.linalg.cholesky(P_pred[k, i])
                    except np.linalg.LinAlgError:
                        node = i
                        break
            else:
                bad = [i for i in range(n) if _fails(x[i], P[i])]
                node, reason = (bad[0], BEYOND) if bad else (None, None)
        if reason is not None:
            violations.append({"node": node, "step": k + 1, "condition": "diverged", "margin": -np.inf,
                               "reason": reason})
            x_pred[k:] = P_pred[k:] = np.nan
            break
        x_post[k + 1] = x
        P_post[k + 1] = [0.5 * (p + p.T) for p in P]
        if om is not None:
            omega[k] = om
    return DistributedResult(x_post, P_post, x_pred, P_pred, sent, delivered, violations, rounds, omega)


def reference_kcf(model, network, z, *, inputs=None, attacks=None, x0=None, P0=None, epsilon=None,
                  falsify="packet") -> DistributedResult:
    """KCF node by node (the parameters of :func:`filters.distributed.run_kcf`, assumed valid)."""
    eps = (0.5 / network.d_max if network.d_max else 0.0) if epsilon is None else float(epsilon)

    def update(k, xp, Pp, U, u, recv):
        fdi, xi = (None, None) if attacks is None else (attacks.fdi[k], attacks.xi[k])
        out = [_kcf_node(i, eps, falsify == "packet", xp, Pp, U, u, recv, fdi, xi) for i in range(len(xp))]
        return np.array([o[0] for o in out]), np.array([o[1] for o in out]), None

    return _loop(model, network, z, inputs, attacks, x0, P0, 1, update)._replace(omega=None)


def reference_hcmci(model, network, z, *, iterations=1, omega="size", inputs=None, attacks=None, x0=None, P0=None,
                    falsify="packet") -> DistributedResult:
    """HCMCI node by node (the parameters of :func:`filters.distributed.run_hcmci`, assumed valid)."""

    def update(k, xp, Pp, U, u, recv):
        fdi, xi = (None, None) if attacks is None else (attacks.fdi[k], attacks.xi[k])
        return _hcmci_all(network, iterations, omega, falsify == "packet", xp, Pp, U, u, recv, fdi, xi)

    return _loop(model, network, z, inputs, attacks, x0, P0, iterations, update)
