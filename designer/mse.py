"""The mean-square-error design of the consensus filter: the joint error covariance and its optimal gains.

Theorem 1's bound (26)-(27) holds for *any* gains ``K_i``, ``C_i`` as long as (28)-(29)
hold; the gain (30) only makes the bound smallest.  ``mode='mse'`` chooses the gains for
what the filter really does instead: at every step it propagates the linearised error
covariance of **all nodes jointly**, cross-covariances included, and gives each node the
gains that minimise its own mean-square error; the bound of the stacked error of all nodes
is then evaluated for those gains as the certificate (see **The certificate** below).

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

**The certificate** (:func:`certificate_predict`, :func:`certificate_update`) is the bound
(26)-(27) written for the *stacked* error ``e = [e_1; ...; e_N]`` of all nodes, so that the
cross-covariances are propagated instead of bounded by Cauchy-Schwarz across neighbours
(the per-node bound treats neighbours' errors as arbitrarily correlated, and for gains
that exploit their real correlation, as these do, it grows geometrically).  The remainders
``r_i = U_i Ω_i D_i e_i`` stack into ``U Ω D e`` with a block-diagonal ``Ω``, ``||Ω|| <= 1``,
so the same lemma gives, with one σ and one β for the network,

    Φ⁻ = F (Φ^-1 - (1+ε) σ DᵀD)^-1 Fᵀ + (εσ)^-1 U Uᵀ + 1 1ᵀ ⊗ Q          (28): Φ^-1 > (1+ε) σ DᵀD
    Φ⁺ = T (Φ⁻^-1 - β DᵀD)^-1 Tᵀ + β^-1 (K V)(K V)ᵀ + blockdiag(K_i R_i K_iᵀ) + B   (29): Φ⁻^-1 > β DᵀD

with ``F = blockdiag(F_i)``, ``T`` the transition above, ``K V = blockdiag(K_i V_i)``, and
``B`` the falsified packets' term ``b = [C_i Σ_{j∈R_i} γ_ij ξ_ij]``: its second moment is
``E[b_i b_kᵀ] = C_i [δ_ik (S_i - Σ_j q_ij² μμᵀ) + n_i n_k μμᵀ] C_kᵀ`` (``μ = E[ξ]``,
``n_i = Σ_{j∈R_i} q_ij``, channels independent); a zero-mean signal (the sine and uniform
laws) is independent of everything else at its step, so ``B = E[b bᵀ]`` adds without cross
terms; with ``μ ≠ 0`` the cross terms are bounded by ``(a + b)(a + b)ᵀ <= a aᵀ / (1 - π) +
b bᵀ / π`` with the ``π`` that makes the trace smallest.  Each node's bound is its diagonal
block.  For a linear model (``U = V = 0``) with a zero-mean signal the certificate *is* the
predicted covariance.
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np
from scipy.linalg import block_diag

from .bounds import shifted_inverse, symmetrize
from .tuning import MARGIN, best_multiplier, lam_max, tune_prediction

__all__ = ["joint_prior", "joint_predict", "mse_gains", "joint_update", "certificate_predict", "certificate_update",
           "JointBound"]


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
    N = Pm.shape[0]
    T = _transition(K, C, H, received, Pm.shape[-1])
    out = np.einsum("ikab,klbc,jldc->ijad", T, Pm, T)
    for i in range(N):
        out[i, i] += K[i] @ R[i] @ K[i].T + C[i] @ fdi_second[i] @ C[i].T
    out = 0.5 * (out + np.swapaxes(np.swapaxes(out, 0, 1), -1, -2))
    for i in range(N):
        out[i, i] = symmetrize(out[i, i])
    return out


def _transition(K, C, H, received, n: int) -> np.ndarray:
    """``T`` (N, N, n, n): ``T_ii = I - K_i H_i - s_i C_i``, ``T_ij = C_i`` for ``j ∈ R_i``."""
    N = len(K)
    T = np.zeros((N, N, n, n))
    for i in range(N):
        T[i, i] = np.eye(n) - K[i] @ H[i] - len(received[i]) * C[i]
        for j in received[i]:
            T[i, j] += C[i]
    return T


def _dense(P: np.ndarray) -> np.ndarray:
    """(N, N, n, m) blocks -> (N n, N m) matrix."""
    N, M, n, m = P.shape
    return P.transpose(0, 2, 1, 3).reshape(N * n, M * m)


def _blocks(A: np.ndarray, N: int) -> np.ndarray:
    n = A.shape[0] // N
    return A.reshape(N, n, N, n).transpose(0, 2, 1, 3)


def _structure(D: Sequence[np.ndarray | None] | None, n: int) -> np.ndarray | None:
    if D is None or all(d is None for d in D):
        return None
    return block_diag(*[np.eye(n) if d is None else d for d in D])


class JointBound(NamedTuple):
    phi: np.ndarray  # (N, N, n, n) the bound of the stacked error; node i's bound is phi[i, i]
    multiplier: float  # σ of (26) or β of (27), one for the network
    margin: float  # 1/λmax(D Φ Dᵀ) - (1+ε) σ, or 1/λmax(D Φ⁻ Dᵀ) - β: > 0 where the bound holds


def certificate_predict(Phi: np.ndarray, F: Sequence[np.ndarray], U: Sequence[np.ndarray], Q: np.ndarray,
                        eps: float, D=None, margin: float = MARGIN) -> JointBound:
    """(26) for the stacked error, σ minimising the trace with (28) at ``margin`` (module docstring)."""
    N, n = Phi.shape[0], Phi.shape[-1]
    P, Db = _dense(Phi), _structure(D, n)
    ch = tune_prediction(P, block_diag(*F), block_diag(*U), np.kron(np.ones((N, N)), Q), eps, margin, Db)
    return JointBound(_blocks(ch.phi_pred, N), ch.sigma, 1.0 / lam_max(P, Db) - (1.0 + eps) * ch.sigma)


def certificate_update(Pm: np.ndarray, K, C, H, R, V, received, fdi_second, fdi_mean, q_fdi, D=None,
                       margin: float = MARGIN) -> JointBound:
    """(27) for the stacked error and the given gains, β minimising the trace with (29) at ``margin``.

    ``fdi_second[i] = Σ_{j∈R_i} q_ij E[ξ ξᵀ]``, ``fdi_mean = E[ξ]`` (n,), ``q_fdi[i]`` the
    probabilities ``q_ij`` of node i's received packets (module docstring).
    """
    N, n = Pm.shape[0], Pm.shape[-1]
    P, Db = _dense(Pm), _structure(D, n)
    T = _dense(_transition(K, C, H, received, n))
    KV = block_diag(*[k @ v for k, v in zip(K, V)])
    has_v = bool(np.any(KV))

    def own(b):
        lin = KV @ KV.T / b if has_v else 0.0
        return symmetrize(T @ shifted_inverse(P, b, Db) @ T.T + lin)

    with np.errstate(over="ignore", invalid="ignore"):
        bmax = (1.0 - margin) / lam_max(P, Db)
        beta = best_multiplier(lambda b: float(np.trace(own(b))), bmax, has_v)
        a = own(beta)
        mu = np.asarray(fdi_mean, dtype=float)
        q = [np.asarray(qi, dtype=float) for qi in q_fdi]
        fdi = block_diag(*[c @ (s - np.sum(qi**2) * np.outer(mu, mu)) @ c.T for c, s, qi in zip(C, fdi_second, q)])
        c_mu = np.concatenate([np.sum(qi) * (c @ mu) for c, qi in zip(C, q)])
        fdi = fdi + np.outer(c_mu, c_mu)
        if np.any(c_mu):  # a biased signal: bound the cross terms with the split of the smallest trace
            ta, tb = np.sqrt(max(np.trace(a), 0.0)), np.sqrt(max(np.trace(fdi), 0.0))
            pi = tb / (ta + tb)
            a, fdi = a / (1.0 - pi), fdi / pi
        out = a + fdi + block_diag(*[k @ r @ k.T for k, r in zip(K, R)])
    return JointBound(_blocks(symmetrize(out), N), beta, 1.0 / lam_max(P, Db) - beta)
