"""The mean-square-error design of the consensus filter: the joint error covariance and its optimal gains.

Theorem 1's bound (26)-(27) holds for *any* gains ``K_i``, ``C_i`` as long as (28)-(29)
hold; the gain (30) only makes the bound smallest.  ``mode='mse'`` chooses the gains for
what the filter really does instead: at every step it propagates the linearised error
covariance of **all nodes jointly**, cross-covariances included, and gives each node the
gains that minimise its own mean-square error; the bound is then evaluated for those gains
as the certificate (:func:`designer.tuning.certify_update`).

With ``e_i = x - x̂_i`` and the linearisations ``F_i`` (at node i's estimate) and ``H_i``
(at its prediction), every node's prediction error is ``e_i⁻ = F_i e_i + w`` (one process
noise for all: the plant is the same), so the joint prediction is

    P⁻_ij = F_i P_ij F_jᵀ + Q.

At the update node ``i`` knows which packets arrived (the set ``R_i``, ``s_i = |R_i|``); a
received packet is falsified with probability ``q_ij = γ̄_ij / (1 - φ̄_ij)``, by ``ξ`` with
second moment ``M = E[ξ ξᵀ] = E[g²] a aᵀ`` (:class:`designer.attacks.FDISignal`).  Its
update (7) is ``e_i⁺ = e_i⁻ - Z_i y_i`` with ``Z_i = [K_i  C_i]`` and the innovations

    y_i = [H_i e_i⁻ + v_i ;  Σ_{j∈R_i} (e_i⁻ - e_j⁻ + γ_ij ξ_ij)],

so the gains minimising ``tr E[e_i⁺ e_i⁺ᵀ]`` are the linear MMSE ones,
``Z_i = E[e_i⁻ y_iᵀ] E[y_i y_iᵀ]⁻¹``, with

    E[e_i⁻ y_iᵀ] = [P_ii H_iᵀ,  Σ_j (P_ii - P_ij)]
    E[y_i y_iᵀ]  = [[H_i P_ii H_iᵀ + R_i,  H_i Σ_j (P_ii - P_ij)],
                    [·ᵀ,  Σ_{j,l} (P_ii - P_il - P_ji + P_jl) + Σ_j q_ij M]]

(``C_i = 0`` is one choice, so each node's predicted error is never larger than a local
EKF's from the same prior covariance).  With the gains fixed, ``e⁺ = T e⁻ - noise``
with ``T_ii = I - K_i H_i - s_i C_i``, ``T_ij = C_i`` for ``j ∈ R_i``, and noises independent
between nodes, so

    P⁺ = T P⁻ Tᵀ + blockdiag(K_i R_i K_iᵀ + C_i (Σ_{j∈R_i} q_ij M) C_iᵀ).

Blocks are stored as an array ``(N, N, n_x, n_x)``.  The linearisation errors are not in
this prediction (it is the EKF's own covariance, not a bound); the certificate is.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .bounds import symmetrize

__all__ = ["joint_prior", "joint_predict", "mse_gains", "joint_update"]


def joint_prior(cov: np.ndarray, n_nodes: int) -> np.ndarray:
    """``P_ij = cov`` for every pair: every node starts at the same estimate, so their errors are one error."""
    return np.broadcast_to(cov, (n_nodes, n_nodes) + cov.shape).copy()


def joint_predict(P: np.ndarray, F: Sequence[np.ndarray], Q: np.ndarray) -> np.ndarray:
    """``P⁻_ij = F_i P_ij F_jᵀ + Q``."""
    Fs = np.asarray(F)
    out = np.einsum("iab,ijbc,jdc->ijad", Fs, P, Fs) + Q
    return 0.5 * (out + np.swapaxes(np.swapaxes(out, 0, 1), -1, -2))


def _moments(Pm: np.ndarray, i: int, received: Sequence[int], H: np.ndarray, R: np.ndarray, fdi_second: np.ndarray):
    """``E[e_i⁻ y_iᵀ]`` and ``E[y_i y_iᵀ]`` (see the module docstring)."""
    n = Pm.shape[-1]
    Pii = Pm[i, i]
    rec = [int(j) for j in received]
    if rec:
        diff = Pii[None] - Pm[i, rec]  # (s, n, n): P_ii - P_ij
        sum_diff = diff.sum(axis=0)
        # Σ_{j,l} (P_ii - P_il - P_ji + P_jl) = s² P_ii - s Σ_l P_il - s Σ_j P_ji + Σ_{j,l} P_jl
        s = len(rec)
        row = Pm[i, rec].sum(axis=0)
        col = Pm[rec, i].sum(axis=0)
        block = Pm[np.ix_(rec, rec)].sum(axis=(0, 1))
        dd = s * s * Pii - s * row - s * col + block + fdi_second
    else:
        sum_diff = np.zeros((n, n))
        dd = np.zeros((n, n))
    ey = np.hstack([Pii @ H.T, sum_diff])
    yy = np.block([[H @ Pii @ H.T + R, H @ sum_diff], [sum_diff.T @ H.T, dd]])
    return ey, 0.5 * (yy + yy.T)


def mse_gains(Pm: np.ndarray, i: int, received: Sequence[int], H: np.ndarray, R: np.ndarray,
              fdi_second: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(K_i, C_i)`` minimising node i's mean-square error given its received packets.

    ``fdi_second``: ``Σ_{j∈R_i} q_ij M``, the second moment of what the attacker adds to the
    consensus innovation.  Without received packets ``C_i = 0`` and ``K_i`` is the EKF gain.
    A singular ``E[y yᵀ]`` (e.g. neighbours whose estimates equal node i's) is solved in the
    least-squares sense: the minimum-norm minimiser.
    """
    m = H.shape[0]
    ey, yy = _moments(Pm, i, received, H, R, fdi_second)
    if len(received) == 0:
        K = np.linalg.solve(yy[:m, :m], ey[:, :m].T).T
        return K, np.zeros((Pm.shape[-1],) * 2)
    scale = max(float(np.abs(np.diag(yy)).max()), 1e-300)
    try:
        c = np.linalg.cholesky(yy + 1e-14 * scale * np.eye(yy.shape[0]))
        Z = np.linalg.solve(c.T, np.linalg.solve(c, ey.T)).T
    except np.linalg.LinAlgError:
        Z = np.linalg.lstsq(yy, ey.T, rcond=None)[0].T
    return Z[:, :m], Z[:, m:]


def joint_update(Pm: np.ndarray, K: Sequence[np.ndarray], C: Sequence[np.ndarray], H: Sequence[np.ndarray],
                 R: Sequence[np.ndarray], received: Sequence[Sequence[int]],
                 fdi_second: Sequence[np.ndarray]) -> np.ndarray:
    """``P⁺ = T P⁻ Tᵀ + blockdiag(K_i R_i K_iᵀ + C_i S_i C_iᵀ)`` for the given gains (module docstring)."""
    N, n = Pm.shape[0], Pm.shape[-1]
    T = np.zeros((N, N, n, n))
    for i in range(N):
        T[i, i] = np.eye(n) - K[i] @ H[i] - len(received[i]) * C[i]
        for j in received[i]:
            T[i, j] += C[i]
    out = np.einsum("ikab,klbc,jldc->ijad", T, Pm, T)
    for i in range(N):
        out[i, i] += K[i] @ R[i] @ K[i].T + C[i] @ fdi_second[i] @ C[i].T
    out = 0.5 * (out + np.swapaxes(np.swapaxes(out, 0, 1), -1, -2))
    for i in range(N):
        out[i, i] = symmetrize(out[i, i])
    return out
