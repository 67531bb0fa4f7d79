"""The scheduled design's node-wise certificate: a bound ``Φ_i`` on each node's own error, computed from its own and
its neighbours' bounds alone, for networks whose stacked error is too large for the joint certificate
(:data:`rules.scheduled.design.CERTIFICATE_MAX_DIM` rows).

The joint certificate bounds the stacked error of all N nodes at once (N n rows, dense eigendecompositions: cubic in
N n).  This one keeps one n x n bound per node and never forms the stacked matrix: its cost is that of the links,
``O(E n³)`` per step.  It gives up what the joint bound knows about the correlations between neighbours' errors,
using instead, for node i's error after the update

    e_i⁺ = (A_i - Σ_j ρ_ij W_ij) e_i + Σ_j ρ_ij C_ij e_j - K_i ψ_i(e_i) - Σ_j ρ_ij K_ij ψ_j(e_i) + (noise) + (FDI),

the inequality ``(Σ_k a_k)(Σ_k a_k)ᵀ ⪯ Σ_k a_k a_kᵀ / w_k`` for any weights ``w_k > 0`` summing to one, which holds
for every realisation whatever the correlations, with ``E[a_k a_kᵀ]`` bounded by the bounds of the errors it
involves: ``E_ρ[(A_i - Σ ρ W) Φ_i (A_i - Σ ρ W)ᵀ] = T̄_ii Φ_i T̄_iiᵀ + Σ_j p(1-p) W_ij Φ_i W_ijᵀ`` for the node's
own error, ``p_ij C_ij Φ_j C_ijᵀ`` for a neighbour's, and for a remainder ``ψ = V Θ W e`` (``‖Θ‖ <= 1``)
``E[K ψ ψᵀ Kᵀ] ⪯ tr(W Φ_i Wᵀ) K V Vᵀ Kᵀ``.  The weights minimise the trace (``w_k ∝ sqrt(tr S_k)``, which makes
the trace ``(Σ_k sqrt(tr S_k))²``).  The measurement noises are independent of the errors and of each other and are
added: ``K_i R_i K_iᵀ + Σ_j p_ij K_ij R_j K_ijᵀ``; the falsification moment as in the joint certificate (a biased
signal split from the rest with ``(a + b)(a + b)ᵀ ⪯ a aᵀ/(1 - π) + b bᵀ/π``).  The prediction is bounded the same
way: ``F e + r`` with ``E[r rᵀ] ⪯ tr(W Φ_i Wᵀ) U Uᵀ``, plus the process noise.

Each node's map is monotone in the bounds (every term is a congruence of a bound, or a trace of one, with
nonnegative weights), so with the weights frozen at a fixed point ``Φ̄`` a bound below ``Φ̄`` stays below it: the
stationary fixed point (checked with its weights frozen, :func:`nodewise_stationary`) is the ``bounded`` claim.
For a linear model it is a bound, not the expected covariance (the joint certificate's equality is lost): looser
where the nodes' gains lean on their neighbours' correlations.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from designer.bounds import BOUND_LIMIT, symmetrize

__all__ = ["NodeBound", "nodewise_predict", "nodewise_update", "nodewise_stationary", "NODEWISE_TOL"]

#: Relative change of the nodes' traces below which the node-wise stationary recursion has converged.
NODEWISE_TOL = 1e-9


def _t(a: np.ndarray) -> np.ndarray:
    return np.swapaxes(a, -1, -2)


class NodeBound(NamedTuple):
    """One step of the node-wise certificate: ``phi`` (N, n, n) and the Jensen weights it used (per node, per summand:
    what a frozen-weight check repeats)."""

    phi: np.ndarray
    weights: tuple


def _tr(S: np.ndarray) -> np.ndarray:
    return np.maximum(np.trace(S, axis1=-2, axis2=-1), 0.0)


def _combine(parts: list[np.ndarray], weights=None) -> tuple[np.ndarray, np.ndarray]:
    """``Σ_k S_k / w_k`` per node for the summands ``parts`` (K, N, n, n), the weights minimising the trace
    (``w_k ∝ sqrt(tr S_k)``; a zero summand gets no weight) or ``weights`` (K, N) as given."""
    S = np.stack(parts)
    if weights is None:
        root = np.sqrt(_tr(S))  # (K, N)
        total = root.sum(axis=0)
        weights = np.where(total > 0, root / np.where(total > 0, total, 1.0), 0.0)
    w = np.asarray(weights)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(w > 0, 1.0 / np.where(w > 0, w, 1.0), 0.0)
    return np.einsum("kn,knab->nab", inv, S), w


def nodewise_predict(phi: np.ndarray, F: np.ndarray, U: np.ndarray, Q: np.ndarray, W: np.ndarray | None,
                     weights=None) -> NodeBound:
    """The prediction's bound per node: ``F Φ_i Fᵀ / w_1 + tr(W Φ_i Wᵀ) U Uᵀ / w_2 + Q`` (``U`` (N, n, n) the
    remainder scalings at the step's reach, ``W`` the remainders' structure, None: I)."""
    phi = np.asarray(phi, dtype=float)
    F = np.broadcast_to(np.asarray(F, dtype=float), phi.shape)
    U = np.broadcast_to(np.asarray(U, dtype=float), phi.shape)
    spread = _tr(phi if W is None else W @ phi @ _t(W))
    parts = [F @ phi @ _t(F), spread[:, None, None] * (U @ _t(U))]
    out, w = _combine(parts, weights)
    return NodeBound(symmetrize(out + np.asarray(Q, dtype=float)), (w,))


def nodewise_update(phi: np.ndarray, rule, ch, V: np.ndarray, Vn: np.ndarray | None, fdi: tuple,
                    W: np.ndarray | None, weights=None) -> NodeBound:
    """The update's bound per node from the predicted bounds ``phi`` (N, n, n) (module docstring): ``rule`` the
    step's gains (:class:`rules.scheduled.design._Rule` fields ``A``, ``C``, ``W``, ``K``, ``R``, ``Kn``, ``Rn``),
    ``ch`` the channels, ``V`` (N, mz, mz) and ``Vn`` (E, mz, mz) the measurement remainders' scalings at the step's
    reach, ``fdi`` the falsifications' own variance and mean per node (:func:`rules.scheduled.design.
    falsification_parts`), ``W`` the remainders' structure."""
    phi = np.asarray(phi, dtype=float)
    N, n = phi.shape[0], phi.shape[-1]
    i, j = ch.receiver, ch.sender
    E = i.size
    p = ch.p
    K = np.asarray(rule.K, dtype=float)
    spread = _tr(phi if W is None else W @ phi @ _t(W))  # tr(W Φ_i Wᵀ): the remainders' reach
    # the node's own error: E_ρ[(A - Σ ρ W) Φ_i (A - Σ ρ W)ᵀ] = T̄ Φ T̄ᵀ + Σ p(1-p) W Φ Wᵀ
    Tii = np.array(rule.A, dtype=float)
    if E:
        np.add.at(Tii, i, -p[:, None, None] * rule.W)
    own = Tii @ phi @ _t(Tii)
    if E:
        np.add.at(own, i, (p * (1 - p))[:, None, None] * (rule.W @ phi[i] @ _t(rule.W)))
    own_rem = spread[:, None, None] * (K @ V @ _t(V) @ _t(K))  # the node's own sensor's remainder
    parts = [own, own_rem]
    # one summand per incoming link slot: the neighbour's error, and the relayed measurement's remainder at e_i
    nbr = np.zeros((ch.d_max, N, n, n))
    rem = np.zeros((ch.d_max, N, n, n))
    if E:
        nbr[ch.slot, i] = p[:, None, None] * (rule.C @ phi[j] @ _t(rule.C))
        if rule.Kn is not None:
            rem[ch.slot, i] = (p * spread[i])[:, None, None] * (rule.Kn @ Vn @ _t(Vn) @ _t(rule.Kn))
    parts += list(nbr) + list(rem)
    lin, w = _combine(parts, weights)
    noise = K @ np.asarray(rule.R, dtype=float) @ _t(K)
    if E and rule.Kn is not None:
        np.add.at(noise, i, p[:, None, None] * (rule.Kn @ rule.Rn @ _t(rule.Kn)))
    own_fdi, c = fdi  # the diagonal of the joint certificate's moment
    fdi = own_fdi + c[:, :, None] * c[:, None, :]
    if np.any(c):  # a biased falsification: (a + b)(a + b)ᵀ <= a aᵀ/(1 - π) + b bᵀ/π, per node
        ta, tb = np.sqrt(_tr(lin)), np.sqrt(_tr(fdi))
        pi = np.where(ta + tb > 0, tb / np.where(ta + tb > 0, ta + tb, 1.0), 0.5)
        lin = lin / (1.0 - pi)[:, None, None]
        fdi = np.where(pi[:, None, None] > 0, fdi / np.where(pi > 0, pi, 1.0)[:, None, None], 0.0)
    return NodeBound(symmetrize(lin + fdi + noise), (w,))


def nodewise_stationary(phi0: np.ndarray, step, *, max_iterations: int = 1000, growth: float = 1e8):
    """The node-wise recursion ``Φ ← step(Φ)`` (``step(phi, weights=None)`` returning ``(phi, weights)``) from
    ``phi0`` until every node's trace changes by less than :data:`NODEWISE_TOL` (relative): ``(converged, Φ̄,
    iterations, reason)``.  A fixed point is confirmed with its weights frozen: the map with those weights, monotone,
    must take Φ̄ to at most Φ̄ (its largest eigenvalue of the excess within the tolerance of the trace), so that a
    bound below Φ̄ stays below it."""
    phi = np.asarray(phi0, dtype=float)
    prev = np.full(phi.shape[0], np.inf)
    first = None
    for it in range(1, max_iterations + 1):
        phi, w = step(phi)
        if not np.isfinite(phi).all():
            return False, None, it, f"the node-wise bound is not finite at iteration {it}"
        tr = np.trace(phi, axis1=-2, axis2=-1)
        first = tr if first is None else first
        if not (tr.max() < min(BOUND_LIMIT, growth * max(first.max(), 1e-300))):
            return False, None, it, f"the node-wise bound grows without settling (iteration {it})"
        if np.all(np.abs(prev - tr) <= NODEWISE_TOL * tr):
            again, _ = step(phi, w)
            excess = np.linalg.eigvalsh(symmetrize(again - phi))[..., -1]
            if np.all(excess <= 1e-6 * tr):
                return True, phi, it, None
            return False, None, it, "the node-wise fixed point is not confirmed with its weights frozen"
        prev = tr
    return False, None, max_iterations, f"the node-wise bound did not settle in {max_iterations} iterations"
