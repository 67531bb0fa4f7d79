"""Convex tuning of the consensus filter's multipliers and gains (cvxpy + Clarabel).

Per node and step, two small convex problems replace the paper's fixed choices
σ = β = 0.1 and C = τ Φ_{k+1|k}:

**Prediction** (26).  With ``c = (1+ε)``, ``tr Φ_{k+1|k}(σ)`` =
``tr F (Φ^-1 - c σ I)^-1 F^T + tr(U U^T) / (ε σ) + tr Q`` is convex in σ on
``0 < c σ < λ_min(Φ^-1)`` (a matrix-fractional function of an affine matrix plus
``1/σ``).  SDP::

    minimise tr X + t
    s.t. [[X, F], [F^T, Φ^-1 - c σ I]] >= 0,   [[t, a], [a, σ]] >= 0   (a^2 = tr(U U^T)/ε)
         c σ <= (1 - ρ) λ_min(Φ^-1)                                       ((28) with margin ρ)

**Update** (27).  With ``A = I - s C - K H`` (affine in C, K), ``w = 1 + 2 d_i``,
``N = Σ_j 3 (1-φ̄_ij) Φ_{j,k+1|k} + 3 δ² Σ_j γ̄_ij I`` and ``W(β) = w β^-1 V V^T + R``,
``tr Φ_{k+1|k+1} = w tr A (Φ_pred^-1 - β I)^-1 A^T + tr C N C^T + tr K W(β) K^T`` is jointly
convex in (β, C, K).  SDP::

    minimise w tr X + ||C L_N||² + ||K L_R||² + w tr T
    s.t. [[X, A], [A^T, Φ_pred^-1 - β I]] >= 0,   [[T, K V], [(K V)^T, β I]] >= 0
         β <= (1 - ρ) λ_min(Φ_pred^-1)                                    ((29) with margin ρ)

Both are built once with cvxpy Parameters (DPP) and re-solved with Clarabel.

**Weights** (:func:`tune_weighted`, the tuned mode's update).  (27)'s factors (1 + 2 d_i) and
3 bound the outer product of a sum of error groups.  With the groups written out — the node's
own ``a_0 = A e_i - K V Θ D e_i``, one per received neighbour ``a_j = C e_j`` and one for all
falsified packets ``b = C Σ_j γ_ij ξ_ij`` — the sharp form of that inequality is
``(Σ_l a_l)(Σ_l a_l)ᵀ <= Σ_l a_l a_lᵀ / p_l`` for any ``p_l > 0`` with ``Σ p_l = 1`` (no
independence needed), so the bound is::

    Φ⁺ = (A M Aᵀ + β^-1 K V Vᵀ Kᵀ) / p_0 + Σ_{j∈R_i} C Φ_{j,k+1|k} Cᵀ / p_j
         + δ² E[(Σ_j γ_ij)²] C Π Cᵀ / p_ξ + K R Kᵀ

(``R_i`` the packets that arrived, which the node knows; ``Π`` the projector onto the
components the FDI signal reaches; :func:`neighbour_groups`), with the weights optimised
jointly with (β, C, K).  The paper's factors are not such a choice in general (their
reciprocals sum to more than 1), so this bound is not always below the paper's for the
same gains; it is always valid.

**ε.**  σ enters (26) and (28) only through ``c σ`` and ``1/(ε σ)``: with
``σ' = (1+ε) σ`` the prediction trace is ``tr F (Φ^-1 - σ' I)^-1 F^T + ((1+ε)/ε) tr(U U^T)/σ'``
and (28) reads ``σ' < λ_min(Φ^-1)``.  The factor ``(1+ε)/ε`` decreases in ε, so for
every node and step the optimal trace decreases as ε grows: the best global ε is
the upper end of (0, 1/d_max); we take ``ε = (1 - ρ)/d_max`` (this convex
reparametrisation replaces an outer search; a test checks the monotonicity).

**Fast path.**  For fixed β the update objective is a convex quadratic in
``Z = [C K]`` with the closed-form minimiser ``Z = w M B (D + w B^T M B)^-1``,
``B = [s I, H^T]``, ``M = (Φ_pred^-1 - β I)^-1``, ``D = blockdiag(N, W(β))``; partial
minimisation keeps convexity in β, so a bounded scalar search over β gives the
same optimum (tests compare it with the SDP).  The σ problem is solved the same
way by a bounded scalar search.
"""
from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from .anderson import least_squares
from .bounds import Spectrum, prediction_recursion, shifted_inverse, spectrum, symmetrize
from .cores import SOLVER_SETTINGS
from .validation import ComputationError

__all__ = [
    "MARGIN", "tuned_epsilon", "PredictionChoice", "UpdateChoice", "tune_prediction", "tune_update",
    "PredictionBatch", "tune_prediction_batch", "UpdateBatch", "tune_update_batch", "load_kernels",
    "PredictionSDP", "UpdateSDP", "update_trace", "lam_max",
    "WeightedChoice", "own_term", "optimal_weights", "weighted_bound", "tune_weighted",
    "WeightedBatch", "tune_weighted_batch", "neighbour_group_stack", "warm_start_weights",
    "neighbour_groups", "best_multiplier", "increasing_root",
    "WeightedSDP",
]

MARGIN = 0.05  # relative margin kept in (28), (29) and in epsilon < 1/d_max


def tuned_epsilon(d_max: int, margin: float = MARGIN) -> float:
    """The optimal global ε: the upper end of (0, 1/d_max), less the margin."""
    return (1.0 - margin) / max(d_max, 1)


class PredictionChoice(NamedTuple):
    sigma: float
    phi_pred: np.ndarray
    trace: float


class UpdateChoice(NamedTuple):
    beta: float
    C: np.ndarray
    K: np.ndarray
    phi_post: np.ndarray
    trace: float


def lam_max(a, D=None):
    """``lambda_max(D a Dᵀ)`` (``D = I`` when None); one per matrix of a stack ``(m, n, n)``."""
    a = np.asarray(a, dtype=float)
    out = np.linalg.eigvalsh(symmetrize(a if D is None else D @ a @ np.swapaxes(D, -1, -2)))[..., -1]
    return float(out) if out.ndim == 0 else out


# --------------------------------------------------------------------------- prediction
def _sigma_max(phi_post, eps, margin, D=None) -> float:
    return (1.0 - margin) / ((1.0 + eps) * lam_max(phi_post, D))


class PredictionBatch(NamedTuple):
    """:func:`tune_prediction_batch`: one σ, Φ_{k+1|k} and trace per item."""

    sigma: np.ndarray  # (m,); NaN where the search left floats
    phi_pred: np.ndarray  # (m, n, n)
    trace: np.ndarray  # (m,)


def _spectrum_of(phi, D, one: bool = False) -> Spectrum:
    """``phi`` (a stack; with ``one`` a matrix, made a stack of one) as its :class:`~designer.bounds.Spectrum` (a
    Spectrum: itself), its eigen-decomposition computed now when ``D`` is None: :func:`_structure` needs its
    eigenvectors, and the margins then take the same ``eigh``'s eigenvalues."""
    S = phi if isinstance(phi, Spectrum) else spectrum(np.asarray(phi, dtype=float)[None] if one else phi)
    if D is None:
        S.eig()
    return S


def _structure(S: Spectrum, D) -> tuple[np.ndarray, np.ndarray]:
    """``μ`` (ascending) and ``G = Φ Dᵀ Q`` with ``D Φ Dᵀ = Q diag(μ) Qᵀ`` (``D = I``: Φ's own spectrum)."""
    if D is None:
        lam, Q = S.eig()
        return lam, S.phi @ Q
    mu, Q = np.linalg.eigh(symmetrize(D @ S.phi @ np.swapaxes(D, -1, -2)))
    return mu, S.phi @ np.swapaxes(D, -1, -2) @ Q


def tune_prediction_batch(phi_post, F, U, Q, eps, margin: float = MARGIN, D=None) -> PredictionBatch:
    """:func:`tune_prediction` for stacked items: ``phi_post`` (m, n, n) or its :class:`~designer.bounds.Spectrum`,
    ``F`` and ``U`` (m, n, n) or one (n, n) for all, ``Q`` (n, n), ``eps`` one number or one per item (m,),
    ``D`` None, (r, n) or (m, r, n).

    ``tr F (Φ^-1 - cσ DᵀD)^-1 Fᵀ = tr F Φ Fᵀ + Σ_k g_k cσ / (1 - cσ μ_k)`` (Woodbury, ``c = 1 + ε``,
    ``D Φ Dᵀ = Σ μ_k q_k q_kᵀ``, ``g_k = |F Φ Dᵀ q_k|²``), so the trace of (26) is convex in σ with the
    increasing slope ``p(σ) - a / σ²``, ``p(σ) = Σ_k g_k c / (1 - cσ μ_k)²`` and ``a = tr(U Uᵀ) / ε``: σ is its
    root (:func:`increasing_root`, all items at once, with the fixed point ``σ = sqrt(a / p(σ))`` as the
    proposal) below (28)'s bound at margin ``margin``; σ = 0 where ``U = 0`` (the trace only grows with σ).
    """
    S = _spectrum_of(phi_post, D)
    m, n = S.phi.shape[:2]
    F = np.broadcast_to(np.asarray(F, dtype=float), (m, n, n))
    U = np.broadcast_to(np.asarray(U, dtype=float), (m, n, n))
    UUt = U @ np.swapaxes(U, -1, -2)
    mu, G = _structure(S, D)
    eps = np.asarray(eps, dtype=float)
    c = 1.0 + eps
    smax = (1.0 - margin) / (c * mu[:, -1])
    sigma = np.zeros(m)
    act = np.flatnonzero(UUt.any(axis=(-2, -1)))
    if act.size:
        g = np.sum((F[act] @ G[act]) ** 2, axis=-2)  # (k, r)
        eps_a = np.broadcast_to(eps, (m,))[act]
        c_a = (1.0 + eps_a)[:, None]
        a = np.trace(UUt[act], axis1=-2, axis2=-1) / eps_a
        mu_a = mu[act]

        def slope(sv, idx):
            p = np.sum(g[idx] * c_a[idx] / (1.0 - c_a[idx] * sv[:, None] * mu_a[idx]) ** 2, axis=-1)
            return p - a[idx] / sv**2, np.sqrt(a[idx] / p)

        sigma[act] = increasing_root(slope, smax[act] * 1e-12, smax[act], xtol=smax[act] * 1e-13, rtol=1e-14)
    used = sigma > 0  # σ = 0 or a failed search (NaN): the EKF's F Φ Fᵀ + Q
    phi = prediction_recursion(S, F, np.where(used[:, None, None], U, 0.0), Q, np.where(used, sigma, 0.0), eps, D)
    return PredictionBatch(sigma, phi, np.trace(phi, axis1=-2, axis2=-1))


def tune_prediction(phi_post, F, U, Q, eps: float, margin: float = MARGIN, D=None) -> PredictionChoice:
    """Minimise ``tr Φ_{k+1|k}`` over σ with (28) kept at relative margin ``margin`` (scalar search).

    ``D``: structure of the remainder ``U Ω D e`` (``None``: ``D = I``, the paper's form).  One item
    of :func:`tune_prediction_batch` (the batched filter's search, step for step).
    """
    S = _spectrum_of(phi_post, D, one=True)
    out = tune_prediction_batch(S, np.asarray(F, dtype=float)[None], np.asarray(U, dtype=float)[None], Q, eps,
                                margin, D)
    return PredictionChoice(float(out.sigma[0]), out.phi_pred[0], float(out.trace[0]))


# ------------------------------------------------------------------------------ update
def update_trace(phi_pred, H, C, K, s, beta, V, R, d_i, N, D=None) -> np.ndarray:
    """Φ_{k+1|k+1} of (27) for given (β, C, K) (``N`` is the neighbour matrix, ``D`` the structure of V Θ D e).

    Stacks ``(m, ...)`` with ``s``, ``beta`` and ``d_i`` per item are taken too (``phi_pred`` may then be a
    :class:`~designer.bounds.Spectrum`).
    """
    t = lambda a: np.swapaxes(a, -1, -2)  # noqa: E731
    w = _per_item(1.0 + 2 * np.asarray(d_i, dtype=float))
    M = shifted_inverse(phi_pred, beta, D)
    A = np.eye(M.shape[-1]) - _per_item(s) * C - K @ H
    VVt = V @ t(V)
    with np.errstate(divide="ignore", invalid="ignore"):  # β = 0 where V = 0: that term is 0
        lin = np.where(VVt.any(axis=(-2, -1))[..., None, None], w * VVt / _per_item(beta), 0.0 * VVt)
    return symmetrize(w * A @ M @ t(A) + C @ N @ t(C) + K @ (lin + R) @ t(K))


def _per_item(x):
    """A number as it is; one value per item, shaped to multiply stacked ``(m, n, n)`` matrices."""
    x = np.asarray(x, dtype=float)
    return x[..., None, None] if x.ndim else x


def _ordered_sum(x: np.ndarray) -> np.ndarray:
    """``x.sum(-1)`` added in order, term by term: the same number whatever zeros pad the last axis
    (a group absent from an item of a stack adds an exact zero), unlike NumPy's pairwise sums."""
    out = np.array(x[..., 0], dtype=float)
    for j in range(1, x.shape[-1]):
        out = out + x[..., j]
    return out


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _fixed_beta_kernel(phi, G, mu, H, s, VVt, R, has_v, it, beta, w, N, M, C, K, A, out):  # pragma: no cover
    """:class:`_FixedBeta` at one β per item ``it[j]``: writes ``M, C, K, A`` (j) and ``out[j] = (f*, slope,
    proposal)``.  Item by item in compiled loops (these systems are 3-8 wide, where NumPy's stacked calls
    cost microseconds per item); the same arithmetic for an item in any stack.  The (C, K) system is solved
    by Cholesky on its lower triangle; a pivot that is not positive (an exactly zero block: C of a node
    that received no packet) drops its unknown (zero gains, the minimum-norm solution for such a block).

    Every sum runs over its terms in a fixed order, and the loops are written row by row (``y[:] += f x[:]``, the
    innermost loop along a row) rather than as one dot product per entry: the same additions in the same order,
    which the compiler vectorises across the row (a dot product's order it may not change).  At 40 states a call
    took 0.49 ms as dot products."""
    n, r, mz = phi.shape[1], mu.shape[1], H.shape[1]
    kk = n + mz
    d = np.empty(r)
    Mm = np.empty((n, n))
    HM = np.empty((mz, n))
    Gm = np.empty((kk, kk))
    rhs = np.empty((kk, n))
    L = np.zeros((kk, kk))
    inv = np.empty(kk)
    Y = np.empty((kk, n))
    X = np.empty((kk, n))
    Gt = np.empty((r, n))
    row = np.empty(r)
    for j in range(it.size):
        i = it[j]
        b, wj, sj = beta[j], w[j], s[i]
        for l in range(r):
            d[l] = b / (1.0 - b * mu[i, l])
        for c in range(n):
            for l in range(r):
                Gt[l, c] = G[i, c, l]
        for a in range(n):  # M = Φ + Γ diag(d) Γᵀ
            for c in range(n):
                Mm[a, c] = phi[i, a, c]
            for l in range(r):
                f = G[i, a, l] * d[l]
                for c in range(n):
                    Mm[a, c] += f * Gt[l, c]
        for p in range(mz):
            for c in range(n):
                HM[p, c] = 0.0
            for a in range(n):
                f = H[i, p, a]
                for c in range(n):
                    HM[p, c] += f * Mm[a, c]
        lin = wj / b if has_v[i] else 0.0
        ws = wj * sj
        for a in range(n):  # the system's lower triangle and right-hand side w Bᵀ M
            for c in range(n):
                Gm[a, c] = N[j, a, c] + ws * sj * Mm[a, c]
                rhs[a, c] = ws * Mm[a, c]
        for p in range(mz):
            for c in range(n):
                Gm[n + p, c] = ws * HM[p, c]
                rhs[n + p, c] = wj * HM[p, c]
            for q in range(mz):
                acc = 0.0
                for a in range(n):
                    acc += HM[p, a] * H[i, q, a]
                Gm[n + p, n + q] = R[i, p, q] + lin * VVt[i, p, q] + wj * acc
        for c in range(kk):  # Cholesky
            dd = Gm[c, c]
            for l in range(c):
                dd -= L[c, l] * L[c, l]
            inv[c] = 1.0 / np.sqrt(dd) if dd > 0.0 else 0.0
            for q in range(c + 1, kk):
                acc = Gm[q, c]
                for l in range(c):
                    acc -= L[q, l] * L[c, l]
                L[q, c] = acc * inv[c]
        for c in range(kk):  # L Y = rhs
            for e in range(n):
                Y[c, e] = rhs[c, e]
            for l in range(c):
                f = L[c, l]
                for e in range(n):
                    Y[c, e] -= f * Y[l, e]
            for e in range(n):
                Y[c, e] *= inv[c]
        for c in range(kk - 1, -1, -1):  # Lᵀ X = Y
            for e in range(n):
                X[c, e] = Y[c, e]
            for l in range(c + 1, kk):
                f = L[l, c]
                for e in range(n):
                    X[c, e] -= f * X[l, e]
            for e in range(n):
                X[c, e] *= inv[c]
        trace, fit = 0.0, 0.0
        for a in range(n):
            trace += Mm[a, a]
            for c in range(n):
                M[j, a, c] = Mm[a, c]
                C[j, a, c] = X[c, a]
            for p in range(mz):
                K[j, a, p] = X[n + p, a]
        for c in range(kk):
            for e in range(n):
                fit += X[c, e] * rhs[c, e]
        for a in range(n):  # A = I - sC - KH
            for c in range(n):
                A[j, a, c] = (1.0 if a == c else 0.0) - sj * C[j, a, c]
            for p in range(mz):
                f = K[j, a, p]
                for c in range(n):
                    A[j, a, c] -= f * H[i, p, c]
        pos, neg = 0.0, 0.0
        for a in range(n):  # the envelope slope: w tr A M'(β) Aᵀ and w tr K V Vᵀ Kᵀ
            for l in range(r):
                row[l] = 0.0
            for c in range(n):
                f = A[j, a, c]
                for l in range(r):
                    row[l] += f * G[i, c, l]
            for l in range(r):
                e = 1.0 - b * mu[i, l]
                pos += row[l] * row[l] / (e * e)
            for p in range(mz):
                for q in range(mz):
                    neg += K[j, a, p] * VVt[i, p, q] * K[j, a, q]
        pos, neg = wj * pos, wj * neg
        out[j, 0] = wj * trace - fit
        out[j, 1] = pos - neg / (b * b)
        out[j, 2] = np.sqrt(neg / pos)


class _FixedBeta:
    """For stacked items and fixed β: the optimal ``Z = [C K]``, the optimal trace and its slope in β.

    ``f(Z) = w tr M - 2 w tr(Z Bᵀ M) + tr(Z G Zᵀ)`` with ``B = [s I, Hᵀ]``, ``G = blockdiag(N, W(β)) + w Bᵀ M B``
    and ``W(β) = w β⁻¹ V Vᵀ + R``, so ``Z* = w M B G⁻¹`` and ``f* = w tr M - w tr(Z* Bᵀ M)``;
    ``M(β) = Φ + Γ diag(β / (1 - β μ)) Γᵀ`` with ``D Φ Dᵀ = Q diag(μ) Qᵀ`` and ``Γ = Φ Dᵀ Q`` (Woodbury), so
    one eigendecomposition per item serves every β and every weight.  ``w`` and ``N`` (the weights of
    (27): ``1 + 2 d_i`` and the paper's neighbour matrix, or ``1/p_0`` and ``Σ_g N_g / p_g``) are given
    per call, for the items ``it``.  The slope ``d f*/dβ = p(β) - q(β) / β²`` is the envelope theorem's at
    the optimal Z, ``p = w tr A M'(β) Aᵀ`` (``M' = Γ diag(1/(1 - β μ)²) Γᵀ``, ``A = I - sC - KH``) and
    ``q = w tr K V Vᵀ Kᵀ`` (increasing in β: f* is convex); its fixed point ``β = sqrt(q / p)`` is the
    proposal for :func:`increasing_root`.
    """

    def __init__(self, S: Spectrum, H, s, V, R, margin: float, D=None):
        def c(x):  # contiguous and writeable whatever the caller passed: one compiled signature of the kernel
            return np.require(x, dtype=float, requirements=("C", "W"))

        self.phi = c(S.phi)
        mu, G = _structure(S, D)
        self.mu, self.G = c(mu), c(G)
        self.bmax = (1.0 - margin) / self.mu[:, -1]  # (29) at the margin
        self.H, self.s, self.R = c(H), c(s), c(R)
        self.VVt = c(V @ np.swapaxes(V, -1, -2))
        self.has_v = self.VVt.any(axis=(-2, -1))

    def _run(self, it, beta, w, N):
        k, n, m = it.size, self.phi.shape[-1], self.H.shape[-2]
        M, C, A = np.empty((k, n, n)), np.empty((k, n, n)), np.empty((k, n, n))
        K, out = np.empty((k, n, m)), np.empty((k, 3))
        _fixed_beta_kernel(self.phi, self.G, self.mu, self.H, self.s, self.VVt, self.R, self.has_v,
                           np.ascontiguousarray(it, dtype=np.intp), np.ascontiguousarray(beta, dtype=float),
                           np.ascontiguousarray(w, dtype=float), np.ascontiguousarray(N, dtype=float), M, C, K, A, out)
        return M, C, K, A, out

    def solve(self, it, beta, w, N):
        """``(M, C, K, A)`` of the items ``it`` at ``beta`` (one per item)."""
        return self._run(it, beta, w, N)[:4]

    def slope(self, it, beta, w, N):
        """The slope of f* at ``beta`` and the proposal ``sqrt(q / p)``."""
        out = self._run(it, beta, w, N)[4]
        return out[:, 1], out[:, 2]

    def trace(self, it, beta, w, N) -> np.ndarray:
        return self._run(it, beta, w, N)[4][:, 0]


def _best_gains(fixed: _FixedBeta, it, w, N, guess=None):
    """Per item of ``it``: (β, M, C, K, A) minimising ``w tr(A M Aᵀ + K V Vᵀ Kᵀ / β) + tr C N Cᵀ + tr K R Kᵀ``
    with (29) at the margin.  β = 0 without V (the trace only grows with β: M grows); otherwise the root of
    the slope of the convex f*(β) (:func:`increasing_root`, all items at once), and where that slope leaves
    floats, the bounded scalar search of the trace (:func:`best_multiplier`, item by item).  ``guess``: a start
    per item (the β of the previous weights, NaN: none)."""
    beta = np.zeros(it.size)
    v = np.flatnonzero(fixed.has_v[it])
    if v.size:
        bmax = fixed.bmax[it[v]]

        def slope(b, idx):
            j = v[idx]
            return fixed.slope(it[j], b, w[j], N[j])

        beta[v] = increasing_root(slope, bmax * 1e-9, bmax, xtol=bmax * 1e-9, rtol=1e-9,
                                  guess=None if guess is None else guess[v])
        for j in v[~np.isfinite(beta[v])]:
            one = it[[j]]
            beta[j] = best_multiplier(lambda b: float(fixed.trace(one, np.array([b]), w[[j]], N[[j]])[0]),
                                      float(fixed.bmax[it[j]]), True)
    M, C, K, A = fixed.solve(it, beta, w, N)
    return beta, M, C, K, A


class UpdateBatch(NamedTuple):
    """:func:`tune_update_batch`: the fields of :class:`UpdateChoice` per item."""

    beta: np.ndarray  # (m,)
    C: np.ndarray  # (m, n, n)
    K: np.ndarray  # (m, n, n_z)
    phi_post: np.ndarray  # (m, n, n)
    trace: np.ndarray  # (m,)


def tune_update_batch(phi_pred, H, s, V, R, d, N, margin: float = MARGIN, D=None) -> UpdateBatch:
    """:func:`tune_update` for stacked items: ``phi_pred`` (m, n, n) or its :class:`~designer.bounds.Spectrum`,
    ``H`` (m, n_z, n), ``s`` and ``d`` (the node's degree d_i) (m,), ``V``, ``R`` (m, n_z, n_z), ``N`` (m, n, n),
    ``D`` None, (r, n) or (m, r, n).  Each item takes the steps it takes alone (its β search is an item of
    :func:`increasing_root`), so an item of a stack has the numbers of a batch of one."""
    S = _spectrum_of(phi_pred, D)
    m = S.phi.shape[0]
    H, V, R, N = (np.asarray(x, dtype=float) for x in (H, V, R, N))
    s, d = (np.broadcast_to(np.asarray(x, dtype=float), (m,)) for x in (s, d))
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # a diverging bound: the caller's checks
        fixed = _FixedBeta(S, H, s, V, R, margin, D)
        beta, _, C, K, _ = _best_gains(fixed, np.arange(m), 1.0 + 2 * d, N)
        phi = update_trace(phi_pred, H, C, K, s, beta, V, R, d, N, D)
    return UpdateBatch(beta, C, K, phi, np.trace(phi, axis1=-2, axis2=-1))


def load_kernels() -> None:
    """Load the compiled kernels of the multiplier searches and the fixed-β update into this process (from
    numba's cache, or compile them): worker processes forked afterwards inherit them instead of loading them
    each, which costs 0.6-0.8 s of CPU per process."""
    tune_update(np.eye(1), np.eye(1), 1.0, np.eye(1), np.eye(1), 1, np.eye(1))


def tune_update(phi_pred, H, s: float, V, R, d_i: int, N, margin: float = MARGIN, D=None) -> UpdateChoice:
    """Minimise ``tr Φ_{k+1|k+1}`` over (β, C, K) with (29) kept at margin (closed form + scalar search).

    One item of :func:`tune_update_batch` (the feasibility maps' steps).
    """
    out = tune_update_batch(np.asarray(phi_pred, dtype=float)[None], np.asarray(H, float)[None], [float(s)],
                            np.asarray(V, float)[None], np.asarray(R, float)[None], [d_i], np.asarray(N, float)[None],
                            margin, D)
    return UpdateChoice(float(out.beta[0]), out.C[0], out.K[0], out.phi_post[0], float(out.trace[0]))


def _evaluate(slope, x, idx) -> tuple[np.ndarray, np.ndarray]:
    """``slope(x, idx)`` as (slopes, proposals), proposals NaN where the slope gives none."""
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        out = slope(x, idx)
        if isinstance(out, tuple):
            return np.asarray(out[0], float), np.asarray(out[1], float)
        return np.asarray(out, float), np.full(x.shape, np.nan)


_LAZY_STEPS = 8  # proposal steps taken before an end not yet evaluated is
_ROOT_NJIT = dict(nogil=True, cache=True, error_model="numpy")


@numba.njit(**_ROOT_NJIT)
def _root_points(live, it, a, b, fa, fb, ka, kb, prop, x0, r0, x1, r1, sizes, geo, xtol, rtol, c):  # pragma: no cover
    """:func:`increasing_root`'s next point ``c[j]`` for every item ``j`` of ``live`` (step ``it`` >= 1)."""
    for j in live:
        slow = ka[j] and kb[j] and sizes[j, 2] > 0.5 * sizes[j, 0]
        secant = x1[j] - r1[j] * (x1[j] - x0[j]) / (r1[j] - r0[j])
        g = secant if a[j] < secant < b[j] else prop[j]
        fp = a[j] - fa[j] * (b[j] - a[j]) / (fb[j] - fa[j]) if ka[j] and kb[j] else np.nan
        mid = np.sqrt(abs(a[j] * b[j])) if geo[j] else 0.5 * (a[j] + b[j])
        if a[j] < g < b[j] and not slow:
            x = g
        elif slow or not a[j] < fp < b[j]:
            x = mid
        else:
            x = fp
        half = 0.5 * (xtol[j] + rtol * abs(x))  # keep half the tolerance away from the ends ...
        x = min(max(x, a[j] + half), b[j] - half) if a[j] + half < b[j] - half else 0.5 * (a[j] + b[j])
        # ... or take an end not evaluated yet: where a proposal points beyond it, where a proposal would come
        # within half the tolerance of it, or where no proposal is usable
        lazy = np.isfinite(g) and not slow and it <= _LAZY_STEPS
        if not ka[j] and (x <= a[j] + half or not lazy or g <= a[j]):
            x = a[j]
        elif not kb[j] and (x >= b[j] - half or not lazy or g >= b[j]):
            x = b[j]
        c[j] = x


@numba.njit(**_ROOT_NJIT)
def _root_update(live, c, fc, pc, a, b, fa, fb, ka, kb, side, prop, x0, r0, x1, r1, sizes, geo, xtol, rtol,
                 out):  # pragma: no cover
    """:func:`increasing_root`'s bracket after the slopes ``fc`` (and proposals ``pc``) at ``c`` of the items
    ``live``; returns which of them are done (their result in ``out``: NaN where an evaluated end is not finite)."""
    done = np.zeros(live.size, dtype=np.bool_)
    for k in range(live.size):
        j = live[k]
        x, f = c[j], fc[k]
        finite = np.isfinite(f)
        at_end = (not ka[j] and x == a[j]) or (not kb[j] and x == b[j])  # an end evaluated: it may be the answer
        at_hi = not kb[j] and x == b[j]
        at_lo = not ka[j] and x == a[j]
        if at_end and not finite:
            done[k] = True  # out stays NaN: the caller decides
            continue
        if (at_hi and f <= 0) or (at_lo and f >= 0):
            out[j] = x
            done[k] = True
            continue
        up = not finite or f > 0  # the root is below x (a slope beyond floats inside the bracket counts as positive)
        if up:
            fb[j] = f if finite else (abs(fa[j]) + 1.0 if ka[j] else 1.0)
            b[j], kb[j] = x, True
            if side[j] == -1:
                fa[j] *= 0.5  # Illinois: an end kept twice has its value halved
            side[j] = -1
        else:
            a[j], fa[j], ka[j] = x, f, True
            if side[j] == 1:
                fb[j] *= 0.5
            side[j] = 1
        if np.isfinite(pc[k]) and finite and not (at_end and np.isfinite(prop[j])):  # an end's proposal: last resort
            x0[j], r0[j], x1[j], r1[j] = x1[j], r1[j], x, pc[k] - x
            prop[j] = pc[k]
        elif not at_end:
            prop[j] = np.nan
        if ka[j] and kb[j] and (f == 0 or b[j] - a[j] <= xtol[j] + rtol * abs(x)):
            out[j] = x if f == 0 else 0.5 * (a[j] + b[j])
            done[k] = True
            continue
        sizes[j, 0], sizes[j, 1] = sizes[j, 1], sizes[j, 2]
        sizes[j, 2] = np.log(b[j] / a[j]) if geo[j] else b[j] - a[j]
    return done


def increasing_root(slope, lo, hi, *, xtol, rtol: float = 1e-12, maxiter: int = 200, guess=None) -> np.ndarray:
    """For many items at once: the point of ``[lo, hi]`` where an increasing ``slope`` crosses zero.

    ``slope(b, idx)`` returns the slopes of the items ``idx`` (an index array) at the points
    ``b`` (one per item of ``idx``), or a pair ``(slopes, proposals)``: ``proposals`` are the
    caller's guesses of each root from what it knows at ``b`` (e.g. the fixed point
    ``b = sqrt(q(b) / p(b))`` of a slope ``p(b) - q(b) / b²``; NaN: none).  Per item the result is
    ``hi`` where ``slope(hi) <= 0`` (the constraint binds), ``lo`` where ``slope(lo) >= 0``, and
    otherwise a point of a bracket ``[a, b]`` (``slope(a) < 0 < slope(b)``) that is within
    ``xtol + rtol |b|``.  The search starts at ``guess`` (per item, inside ``(lo, hi)``; NaN or
    omitted: at ``hi``) and evaluates the other end only when no proposal is usable, a proposal
    points beyond it or comes within half the tolerance of it, or the proposals have not closed the
    bracket in ``_LAZY_STEPS`` steps (so a slope without proposals has both ends evaluated first).  The bracket shrinks
    by a safeguarded step per iteration: a proposal (refined by the secant through the last two
    proposals' residuals) when it falls inside the bracket, else the Illinois variant of false
    position; a bisection (geometric for a bracket of positive numbers, which may span decades)
    whenever three steps have not halved the bracket; and no point closer than half the tolerance
    to an end, so that once the steps converge the next point lands across the root and closes the
    bracket.  A non-finite slope at an end it evaluates gives NaN (the caller decides); inside the
    bracket it counts as positive.  This is the multiplier search of the tuned and mse designs; a
    single item is a batch of one, so the per-run and the batched filters take the same steps.
    """
    lo = np.array(lo, dtype=float, ndmin=1)
    hi = np.array(np.broadcast_to(hi, lo.shape), dtype=float)
    xtol = np.array(np.broadcast_to(np.asarray(xtol, dtype=float), lo.shape))
    m = lo.size
    out = np.full(m, np.nan)
    start = hi if guess is None else np.broadcast_to(np.asarray(guess, dtype=float), lo.shape)
    c = np.where((start > lo) & (start < hi), start, hi)
    a, b = lo.copy(), hi.copy()
    fa, fb = np.full(m, np.nan), np.full(m, np.nan)
    ka, kb = np.zeros(m, dtype=bool), np.zeros(m, dtype=bool)  # the slope's sign is known at a, at b
    geo = lo > 0
    side = np.zeros(m, dtype=np.int64)  # which end was kept last (-1 a, +1 b): Illinois halves its value
    prop, x0, r0, x1, r1 = (np.full(m, np.nan) for _ in range(5))  # the last proposal; the secant's data
    sizes = np.full((m, 3), np.inf)  # the bracket's size at the last three steps
    live = np.arange(m)
    for it in range(maxiter + 1):
        if it:
            _root_points(live, it, a, b, fa, fb, ka, kb, prop, x0, r0, x1, r1, sizes, geo, xtol, float(rtol), c)
        fc, pc = _evaluate(slope, c[live], live)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            done = _root_update(live, c, np.ascontiguousarray(fc), np.ascontiguousarray(pc), a, b, fa, fb, ka, kb,
                                side, prop, x0, r0, x1, r1, sizes, geo, xtol, float(rtol), out)
        live = live[~done]
        if not live.size:
            break
    if live.size:  # maxiter reached: the middle of what is left
        out[live] = 0.5 * (a[live] + b[live])
    return out


def best_multiplier(trace_at, bmax: float, has_v: bool) -> float:
    """The β in ``(0, bmax]`` minimising the convex ``trace_at(β)`` (0 without V: the trace only grows with β)."""
    if not has_v:
        return 0.0
    from scipy.optimize import minimize_scalar  # here: scipy.optimize takes a second to import

    res = minimize_scalar(trace_at, bounds=(bmax * 1e-9, bmax), method="bounded",
                          options={"xatol": bmax * 1e-8, "maxiter": 500})
    return float(res.x)


# ----------------------------------------------------------------- optimised weights
class WeightedChoice(NamedTuple):
    beta: float
    C: np.ndarray
    K: np.ndarray
    phi_post: np.ndarray
    trace: float
    weights: np.ndarray  # (1 + G,) p_0 (the node's own group) then one per neighbour group; sums to 1


class WeightedBatch(NamedTuple):
    """:func:`tune_weighted_batch`: the fields of :class:`WeightedChoice` per item."""

    beta: np.ndarray  # (m,)
    C: np.ndarray  # (m, n, n)
    K: np.ndarray  # (m, n, n_z)
    phi_post: np.ndarray  # (m, n, n)
    trace: np.ndarray  # (m,)
    weights: np.ndarray  # (m, 1 + G): own group, then the groups' slots; NaN where a group is absent


_P_FLOOR = 1e-12  # a group's weight is never below this (a zero weight would make its term 0/0)
_WARM_FLOOR = 1e-6  # a warm-started weight is at least this: a group at the floor may re-enter


def own_term(phi_pred, H, C, K, s, beta, V, D=None) -> np.ndarray:
    """The node's own error group of (27): ``A M Aᵀ + K V Vᵀ Kᵀ / β`` (``A = I - sC - KH``, M of (29)).

    Stacks ``(..., n, n)`` with ``s``, ``beta`` per item are taken too.
    """
    M = shifted_inverse(phi_pred, beta, D)
    A = np.eye(M.shape[-1]) - _per_item(s) * C - K @ H
    KV = K @ V
    KVt = KV @ np.swapaxes(KV, -1, -2)
    with np.errstate(divide="ignore", invalid="ignore"):
        lin = np.divide(KVt, _per_item(beta), out=np.zeros(KVt.shape), where=KVt != 0)
    return symmetrize(A @ M @ np.swapaxes(A, -1, -2) + lin)


def _optimal_weights(traces: np.ndarray, present: np.ndarray | None = None) -> np.ndarray:
    """:func:`optimal_weights` per row of ``traces`` (m, L) over the groups ``present`` (default all; the others
    get weight 1, which their zero terms ignore); sums added in order, so absent groups change no number."""
    if present is None:
        present = np.ones(traces.shape, dtype=bool)
    r = np.where(present, np.sqrt(np.maximum(traces, 0.0)), 0.0)
    total = _ordered_sum(r)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(present, np.maximum(r / total[:, None], _P_FLOOR), 0.0)
    p = p / _ordered_sum(p)[:, None]
    p = np.where((total > 0)[:, None], p, 1.0 / present.sum(axis=1, keepdims=True))
    return np.where(present, p, 1.0)


def optimal_weights(traces) -> np.ndarray:
    """``p_l = √t_l / Σ √t_l``: the weights minimising ``Σ t_l / p_l`` over the simplex (floored at 1e-12)."""
    return _optimal_weights(np.asarray(traces, dtype=float)[None])[0]


def neighbour_group_stack(phi_nb, q_fdi, present, delta: float, span=None, receipt=None
                          ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`neighbour_groups` for stacked items with padded channels: ``phi_nb`` (m, J, n, n), ``q_fdi`` and
    ``present`` (m, J) (the packets that arrived; the others are ignored).

    Returns the groups ``(m, J + 1, n, n)`` (slot ``J``: the falsified packets') and which are present
    ``(m, J + 1)``; sums over the channels are added in order, so padding changes no number.
    """
    phi_nb = np.asarray(phi_nb, dtype=float)
    present = np.asarray(present, dtype=bool)
    q = np.where(present, np.asarray(q_fdi, dtype=float), 0.0)
    J, n = phi_nb.shape[1], phi_nb.shape[-1]
    if J:
        m2 = (_ordered_sum(q * (1.0 - q)) + _ordered_sum(q) ** 2) * delta**2
    else:
        m2 = np.zeros(phi_nb.shape[0])
    nb = phi_nb if receipt is None else phi_nb * np.asarray(receipt, dtype=float)[..., None, None]
    span = np.eye(n) if span is None else np.asarray(span, dtype=float)
    groups = np.concatenate([np.where(present[..., None, None], nb, 0.0), m2[:, None, None, None] * span], axis=1)
    return groups, np.concatenate([present, (m2 > 0)[:, None]], axis=1)


def neighbour_groups(phi_nb, q_fdi, delta: float, receipt=None, span=None) -> np.ndarray:
    """The neighbour groups of the weighted (27), shape (G, n, n).

    One group per neighbour channel ``j`` (rows of ``phi_nb``, (J, n, n): the neighbours'
    ``Φ_{j,k+1|k}``, times ``receipt[j]``, the probability the packet arrives, 1 for a packet
    that did), and one for all falsified packets together: with independent FDI indicators
    ``γ_j`` of probabilities ``q_fdi[j]`` and ``||ξ_j|| <= δ`` (any signal, not only a
    zero-mean one), ``||Σ_j γ_j ξ_j||² <= δ² (Σ_j γ_j)²``, whose mean is
    ``δ² (Σ_j q_j (1 - q_j) + (Σ_j q_j)²)``; that group is ``δ² E[(Σ_j γ_j)²] Π`` (omitted when 0),
    with ``Π`` (``span``) the projector onto the components the signal can reach (default I).
    One item of :func:`neighbour_group_stack`.
    """
    phi_nb = np.asarray(phi_nb, dtype=float)
    q = np.asarray(q_fdi, dtype=float)
    groups, present = neighbour_group_stack(phi_nb[None], q[None], np.ones((1, q.size), dtype=bool), delta, span,
                                            None if receipt is None else np.asarray(receipt, dtype=float)[None])
    return groups[0][present[0]]


def warm_start_weights(previous, present) -> np.ndarray:
    """The tuned mode's start for a node's weights (m, L), from its weights at its previous tuned update.

    ``previous`` (m, L): those weights by group (own, each neighbour channel, the falsified packets),
    NaN for a group absent then, a row of NaN where there was no previous update; ``present`` (m, L):
    the groups there now.  A group still there keeps its weight, a new one gets the mean of the known
    ones; normalised, floored at 1e-6 (a group at the floor may re-enter: the block steps cannot
    revive a zero) and renormalised.  NaN for absent groups and rows without a previous update.
    """
    prev = np.asarray(previous, dtype=float)
    present = np.asarray(present, dtype=bool)
    known = present & np.isfinite(prev)
    count = known.sum(axis=-1)
    fill = np.where(count > 0, _ordered_sum(np.where(known, prev, 0.0)) / np.maximum(count, 1), 1.0)
    p = np.where(present, np.where(known, prev, fill[:, None]), 0.0)
    p = np.where(present, np.maximum(p / _ordered_sum(p)[:, None], _WARM_FLOOR), 0.0)
    p = p / _ordered_sum(p)[:, None]
    return np.where(present & np.isfinite(prev).any(axis=-1)[:, None], p, np.nan)


def _group_sum(groups: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``Σ_g N_g / p_g`` over stacked groups (..., G, n, n), weights (..., 1 + G), added in order."""
    out = np.zeros(groups.shape[:-3] + groups.shape[-2:])
    for g in range(groups.shape[-3]):
        out = out + groups[..., g, :, :] / _per_item(p[..., 1 + g])
    return out


def weighted_bound(phi_pred, H, C, K, s, beta, V, R, groups, weights, D=None) -> np.ndarray:
    """(27) with weights: ``own / p_0 + Σ_g C N_g Cᵀ / p_g + K R Kᵀ`` (``groups``: (G, n, n), ``weights``: (1+G,)).

    Stacks (``groups`` (m, G, n, n), ``weights`` (m, 1 + G), ``s``, ``beta`` per item) are taken too.
    """
    p = np.asarray(weights, dtype=float)
    groups = np.asarray(groups, dtype=float)
    out = own_term(phi_pred, H, C, K, s, beta, V, D) / _per_item(p[..., 0]) + K @ R @ np.swapaxes(K, -1, -2)
    if groups.shape[-3]:
        out = out + C @ _group_sum(groups, p) @ np.swapaxes(C, -1, -2)
    return symmetrize(out)


def _anderson_coefficients(A: np.ndarray, b: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The least-squares ``γ`` of ``A γ ≈ b`` per item (``A`` (m, L, c), ``b`` (m, L);
    :func:`designer.anderson.least_squares`), ``Aᵀ A`` and ``Aᵀ b`` added over the rows in order (zero rows,
    absent groups, change no number), ``rows`` each item's rows."""
    m, L, c = A.shape
    gram = np.zeros((m, c, c))
    rhs = np.zeros((m, c))
    for l in range(L):
        gram = gram + A[:, l, :, None] * A[:, l, None, :]
        rhs = rhs + A[:, l] * b[:, l, None]
    return least_squares(gram, rhs, rows)


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _term_traces(it, M, C, K, A, beta, VVt, R, groups):  # pragma: no cover
    """The traces of the weighted (27)'s terms for the items ``it`` (M, C, K, A, β aligned with ``it``): the own
    group ``tr(A M Aᵀ) + tr(K V Vᵀ Kᵀ) / β`` (0 / 0 = 0), each group's ``tr(C N_g Cᵀ)``, and ``tr(K R Kᵀ)``."""
    k, n, mz, G = it.size, M.shape[1], K.shape[2], groups.shape[1]
    traces = np.zeros((k, G + 1))
    krk = np.zeros(k)
    for j in range(k):
        i = it[j]
        own, kvv, kr = 0.0, 0.0, 0.0
        for a in range(n):
            for c in range(n):
                am = 0.0
                for e in range(n):
                    am += A[j, a, e] * M[j, e, c]
                own += am * A[j, a, c]
            for p in range(mz):
                for q in range(mz):
                    kvv += K[j, a, p] * VVt[i, p, q] * K[j, a, q]
                    kr += K[j, a, p] * R[i, p, q] * K[j, a, q]
        traces[j, 0] = own + (kvv / beta[j] if kvv != 0.0 else 0.0)
        krk[j] = kr
        for g in range(G):
            t = 0.0
            for a in range(n):
                for b in range(n):
                    cn = 0.0
                    for e in range(n):
                        cn += C[j, a, e] * groups[i, g, e, b]
                    t += cn * C[j, a, b]
            traces[j, 1 + g] = t
    return traces, krk


def _tune_weighted(S: Spectrum, H, s, V, R, groups, present, p, margin, D, tol, max_iter, memory):
    """:func:`tune_weighted_batch`'s iteration over items with padded ``groups`` (k, G, n, n), zero where absent,
    ``present`` (k, 1 + G) (own group first) and starting weights ``p`` (k, 1 + G), 1 where absent."""
    k, G = groups.shape[:2]
    n = S.phi.shape[-1]
    rows = present.sum(axis=1)
    fixed = _FixedBeta(S, H, s, V, R, margin, D)
    best_trace = np.full(k, np.nan)
    best_beta = np.full(k, np.nan)
    best_C = np.full((k, n, n), np.nan)
    best_K = np.full((k, n, H.shape[-2]), np.nan)
    best_p = np.ones((k, G + 1))
    has = np.zeros(k, dtype=bool)
    last = np.full(k, np.inf)
    last_beta = np.full(k, np.nan)  # the β search of the next weights starts at the last one's
    # Anderson histories of log p and log G(p), the newest last, zero where absent or not yet there
    ys = np.zeros((k, memory + 1, G + 1))
    gs = np.zeros((k, memory + 1, G + 1))
    count = np.zeros(k, dtype=int)
    floor = np.log(_P_FLOOR)
    p = np.array(p, dtype=float)
    act = np.arange(k)
    for _ in range(max_iter):
        if not act.size:
            break
        pa, pres = p[act], present[act]
        # the gains for these weights: w = 1/p_0 and N = Σ_g N_g / p_g in the fast path of tune_update
        beta, M, C, K, A = _best_gains(fixed, act, 1.0 / pa[:, 0], _group_sum(groups[act], pa), last_beta[act])
        last_beta[act] = beta
        # the weights for these gains, in closed form, and the trace of the bound they give
        traces, krk = _term_traces(act, M, C, K, A, beta, fixed.VVt, fixed.R, groups)
        q = _optimal_weights(traces, pres)
        trace = _ordered_sum(np.where(pres, traces / q, 0.0)) + krk
        improved = ~has[act] | (trace < best_trace[act])
        i = act[improved]
        best_trace[i], best_beta[i], best_C[i], best_K[i], best_p[i] = (
            trace[improved], beta[improved], C[improved], K[improved], q[improved])
        has[i] = True
        y, gy = np.log(pa), np.log(q)  # 0 where absent (weight 1)
        stop = (np.abs(gy - y).max(axis=1) <= 1e-9) | (np.abs(last[act] - trace) <= tol * trace) | (rows[act] == 1)
        last[act] = trace
        go = ~stop
        back = act[go & ~improved]  # the extrapolation overshot: restart from the best point
        count[back] = 0
        ys[back], gs[back] = 0.0, 0.0
        p[back] = best_p[back]
        on = go & improved
        i = act[on]
        ys[i, :-1], gs[i, :-1] = ys[i, 1:], gs[i, 1:]
        ys[i, -1], gs[i, -1] = y[on], gy[on]
        count[i] = np.minimum(count[i] + 1, memory + 1)
        nxt = gy[on]
        if memory and i.size:  # Anderson acceleration in log p over the last count[i] steps
            res = np.swapaxes(gs[i] - ys[i], -1, -2)  # (., L, memory + 1) residuals g(y) - y
            there = np.arange(memory) >= memory + 1 - count[i][:, None]  # both ends of a difference there
            dres = np.where(there[:, None, :], np.diff(res, axis=-1), 0.0)
            dgs = np.where(there[:, None, :], np.diff(np.swapaxes(gs[i], -1, -2), axis=-1), 0.0)
            gamma = _anderson_coefficients(dres, res[..., -1], rows[i])
            cand = nxt - _ordered_sum(dgs * gamma[:, None, :])
            fine = (count[i] > 1) & np.isfinite(cand).all(axis=1)
            nxt[fine] = cand[fine]
        pres = present[i]
        top = np.where(pres, nxt, -np.inf).max(axis=1, keepdims=True)
        e = np.where(pres, np.exp(np.clip(nxt - top, floor, 0.0)), 0.0)
        pn = np.where(pres, np.maximum(e / _ordered_sum(e)[:, None], _P_FLOOR), 0.0)
        p[i] = np.where(pres, pn / _ordered_sum(pn)[:, None], 1.0)
        act = act[go]
    phi = weighted_bound(S, H, best_C, best_K, s, best_beta, V, R, groups, best_p, D)
    return best_beta, best_C, best_K, phi, best_trace, np.where(present, best_p, np.nan)


def tune_weighted_batch(phi_pred, H, s, V, R, groups, present=None, margin: float = MARGIN, D=None, *,
                        weights=None, tol: float = 1e-6, max_iter: int = 30, memory: int = 3) -> WeightedBatch:
    """:func:`tune_weighted` for stacked items, each with its own groups, Anderson history, convergence,
    restarts and warm start.

    ``phi_pred`` (m, n, n) or its :class:`~designer.bounds.Spectrum`; ``H`` (m, n_z, n), ``s`` (m,),
    ``V``, ``R`` (m, n_z, n_z); ``groups`` (m, G, n, n) padded, ``present`` (m, G) which of them an item
    has (default all), in order (:func:`neighbour_group_stack`); ``D`` None, (r, n) or (m, r, n);
    ``weights`` (m, 1 + G) a start per item (own group first; NaN where a group is absent; a row with a
    present group NaN starts from equal weights).  Every sum over groups is added in order and an absent
    group is an exact zero in it, so each item takes the steps it takes alone (a batch of one).
    """
    S = _spectrum_of(phi_pred, D)
    m, n = S.phi.shape[:2]
    groups = np.asarray(groups, dtype=float).reshape(m, -1, n, n)
    G = groups.shape[1]
    present = np.ones((m, G), dtype=bool) if present is None else np.asarray(present, dtype=bool)
    full = np.concatenate([np.ones((m, 1), dtype=bool), present], axis=1)
    start = np.full((m, G + 1), np.nan) if weights is None else np.asarray(weights, dtype=float)
    warm = np.where(full, np.isfinite(start), True).all(axis=1)
    start = np.where(full, np.where(warm[:, None], start, 1.0 / full.sum(axis=1, keepdims=True)), 1.0)
    H, V, R = (np.asarray(x, dtype=float) for x in (H, V, R))
    s = np.broadcast_to(np.asarray(s, dtype=float), (m,))
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # a diverging bound: the caller's checks
        out = _tune_weighted(S, H, s, V, R, np.where(present[..., None, None], groups, 0.0), full, start, margin,
                             D, tol, max_iter, memory)
    return WeightedBatch(*out)


def tune_weighted(phi_pred, H, s: float, V, R, groups, margin: float = MARGIN, D=None, *, weights=None,
                  tol: float = 1e-6, max_iter: int = 30, memory: int = 3) -> WeightedChoice:
    """Minimise the weighted bound (27) jointly over (β, C, K) and the weights, with (29) at margin.

    With ``b = p_0 β`` the trace is jointly convex in (C, K, b, p) (matrix-fractional terms
    ``A (p_0 Φ_pred^-1 - b DᵀD)^-1 Aᵀ``, ``K V Vᵀ Kᵀ / b``, ``C N_g Cᵀ / p_g``); we minimise it by
    blocks: for fixed weights, (β, C, K) by the fast path of :func:`tune_update` with
    ``w = 1/p_0`` and ``N = Σ_g N_g / p_g``; for fixed (β, C, K), the weights in closed form.
    Every block step lowers the trace, and a point where neither block can is stationary,
    hence optimal.  The weight step ``p <- G(p)`` converges linearly, often slowly, so it is
    Anderson-accelerated in ``log p`` (``memory`` steps; a step that raises the trace restarts
    from the best point).  Any weights give a valid bound, so ``tol`` (relative change of the
    trace at which to stop) trades tightness for time, never validity.  ``weights``: a start
    (e.g. the node's weights at the previous step); default: equal weights.  ``phi_pred``: the
    matrix or the :class:`~designer.bounds.Spectrum` of a stack of it alone.  One item of
    :func:`tune_weighted_batch` (the batched filter's steps).
    """
    S = _spectrum_of(phi_pred, D, one=True)
    n = S.phi.shape[-1]
    groups = np.asarray(groups, dtype=float).reshape(1, -1, n, n)
    g = groups.shape[1]
    start = None if weights is None or len(weights) != g + 1 else np.asarray(weights, dtype=float)[None]
    out = tune_weighted_batch(S, np.asarray(H, dtype=float)[None], [float(s)], np.asarray(V, dtype=float)[None],
                              np.asarray(R, dtype=float)[None], groups, None, margin, D, weights=start, tol=tol,
                              max_iter=max_iter, memory=memory)
    return WeightedChoice(float(out.beta[0]), out.C[0], out.K[0], out.phi_post[0], float(out.trace[0]),
                          out.weights[0])


# ------------------------------------------------------------------------------ SDPs
def _solve(problem, what: str) -> None:
    import cvxpy as cp

    try:
        problem.solve(solver=cp.CLARABEL, **SOLVER_SETTINGS)
    except cp.SolverError as exc:
        raise ComputationError(f"{what}: solver failed ({exc})") from None
    if problem.status == cp.OPTIMAL_INACCURATE:
        import warnings

        warnings.warn(f"{what}: solver status optimal_inaccurate", RuntimeWarning, stacklevel=3)
    elif problem.status != cp.OPTIMAL:
        raise ComputationError(f"{what}: solver status {problem.status}")


class PredictionSDP:
    """The σ problem as an SDP, built once for state dimension ``n`` and re-solved."""

    def __init__(self, n: int):
        import cvxpy as cp

        self.Pinv = cp.Parameter((n, n), symmetric=True)
        self.F = cp.Parameter((n, n))
        self.cDtD = cp.Parameter((n, n), PSD=True)  # (1 + eps) DᵀD
        self.a = cp.Parameter(nonneg=True)  # sqrt(tr(U U^T) / eps)
        self.smax = cp.Parameter(nonneg=True)
        self.sigma = cp.Variable(nonneg=True)
        X = cp.Variable((n, n), symmetric=True)
        t = cp.Variable()
        cons = [
            cp.bmat([[X, self.F], [self.F.T, self.Pinv - self.sigma * self.cDtD]]) >> 0,
            cp.bmat([[cp.reshape(t, (1, 1), order="C"), cp.reshape(self.a, (1, 1), order="C")],
                     [cp.reshape(self.a, (1, 1), order="C"), cp.reshape(self.sigma, (1, 1), order="C")]]) >> 0,
            self.sigma <= self.smax,
        ]
        self.problem = cp.Problem(cp.Minimize(cp.trace(X) + t), cons)
        assert self.problem.is_dpp()

    def solve(self, phi_post, F, U, Q, eps: float, margin: float = MARGIN, D=None) -> PredictionChoice:
        n = phi_post.shape[0]
        Dm = np.eye(n) if D is None else D
        self.Pinv.value = symmetrize(np.linalg.inv(phi_post))
        self.F.value = F
        self.cDtD.value = (1.0 + eps) * Dm.T @ Dm
        self.a.value = float(np.sqrt(np.trace(U @ U.T) / eps))
        self.smax.value = _sigma_max(phi_post, eps, margin, D)
        _solve(self.problem, "prediction SDP")
        sigma = max(float(self.sigma.value), 0.0)
        phi = prediction_recursion(phi_post, F, U if sigma > 0 else 0.0 * U, Q, sigma, eps, D)
        return PredictionChoice(sigma, phi, float(np.trace(phi)))


class UpdateSDP:
    """The (β, C, K) problem as an SDP, built once for dimensions (n, m) and re-solved."""

    def __init__(self, n: int, m: int):
        import cvxpy as cp

        self.Pinv = cp.Parameter((n, n), symmetric=True)
        self.H = cp.Parameter((m, n))
        self.s = cp.Parameter(nonneg=True)
        self.w = cp.Parameter(nonneg=True)
        self.LN = cp.Parameter((n, n))
        self.LR = cp.Parameter((m, m))
        self.V = cp.Parameter((m, m))
        self.bmax = cp.Parameter(nonneg=True)
        self.DtD = cp.Parameter((n, n), PSD=True)
        self.C = cp.Variable((n, n))
        self.K = cp.Variable((n, m))
        self.beta = cp.Variable(nonneg=True)
        X = cp.Variable((n, n), symmetric=True)
        T = cp.Variable((n, n), symmetric=True)
        A = np.eye(n) - self.s * self.C - self.K @ self.H
        G = self.K @ self.V
        cons = [
            cp.bmat([[X, A], [A.T, self.Pinv - self.beta * self.DtD]]) >> 0,
            cp.bmat([[T, G], [G.T, self.beta * np.eye(m)]]) >> 0,
            self.beta <= self.bmax,
        ]
        obj = self.w * cp.trace(X) + cp.sum_squares(self.C @ self.LN) + cp.sum_squares(self.K @ self.LR) \
            + self.w * cp.trace(T)
        self.problem = cp.Problem(cp.Minimize(obj), cons)
        assert self.problem.is_dpp()

    def solve(self, phi_pred, H, s: float, V, R, d_i: int, N, margin: float = MARGIN, D=None) -> UpdateChoice:
        n = phi_pred.shape[0]
        Dm = np.eye(n) if D is None else D
        self.DtD.value = Dm.T @ Dm
        self.Pinv.value = symmetrize(np.linalg.inv(phi_pred))
        self.H.value = H
        self.s.value = float(s)
        self.w.value = 1.0 + 2 * d_i
        self.LN.value = np.linalg.cholesky(symmetrize(N) + 1e-15 * np.eye(n)) if np.any(N) else np.zeros((n, n))
        self.LR.value = np.linalg.cholesky(R)
        self.V.value = V
        self.bmax.value = (1.0 - margin) / lam_max(phi_pred, D)
        _solve(self.problem, "update SDP")
        beta = max(float(self.beta.value), 0.0)
        C, K = self.C.value, self.K.value
        phi = update_trace(phi_pred, H, C, K, s, beta, V, R, d_i, N, D) if beta > 0 or not np.any(V) else None
        if phi is None:
            raise ComputationError("update SDP returned beta = 0 with V nonzero")
        return UpdateChoice(beta, C, K, phi, float(np.trace(phi)))


class WeightedSDP:
    """The weighted (27) problem of :func:`tune_weighted` as one SDP in ``b = p_0 β``, over (C, K, b, p).

    Built once for dimensions ``(n, m)`` and ``groups`` neighbour groups.
    """

    def __init__(self, n: int, m: int, groups: int):
        import cvxpy as cp

        self.Pinv = cp.Parameter((n, n), symmetric=True)
        self.DtD = cp.Parameter((n, n), PSD=True)
        self.H = cp.Parameter((m, n))
        self.s = cp.Parameter(nonneg=True)
        self.V = cp.Parameter((m, m))
        self.LR = cp.Parameter((m, m))
        self.L = [cp.Parameter((n, n)) for _ in range(groups)]
        self.bmax = cp.Parameter(nonneg=True)
        self.C, self.K = cp.Variable((n, n)), cp.Variable((n, m))
        self.b = cp.Variable(nonneg=True)
        self.p = cp.Variable(groups + 1, nonneg=True)
        X = cp.Variable((n, n), symmetric=True)
        T = cp.Variable((n, n), symmetric=True)
        Y = [cp.Variable((n, n), symmetric=True) for _ in range(groups)]
        A = np.eye(n) - self.s * self.C - self.K @ self.H
        KV = self.K @ self.V
        cons = [
            cp.bmat([[X, A], [A.T, self.p[0] * self.Pinv - self.b * self.DtD]]) >> 0,
            cp.bmat([[T, KV], [KV.T, self.b * np.eye(m)]]) >> 0,
            self.b <= self.p[0] * self.bmax,
            cp.sum(self.p) == 1,
        ]
        for g in range(groups):
            CL = self.C @ self.L[g]
            cons.append(cp.bmat([[Y[g], CL], [CL.T, self.p[g + 1] * np.eye(n)]]) >> 0)
        obj = cp.trace(X) + cp.trace(T) + sum(cp.trace(y) for y in Y) + cp.sum_squares(self.K @ self.LR)
        self.problem = cp.Problem(cp.Minimize(obj), cons)
        assert self.problem.is_dpp()

    def solve(self, phi_pred, H, s: float, V, R, groups, margin: float = MARGIN, D=None) -> WeightedChoice:
        n = phi_pred.shape[0]
        Dm = np.eye(n) if D is None else D
        self.Pinv.value = symmetrize(np.linalg.inv(phi_pred))
        self.DtD.value = Dm.T @ Dm
        self.H.value, self.s.value, self.V.value = H, float(s), V
        self.LR.value = np.linalg.cholesky(R)
        for g, Ng in enumerate(groups):
            self.L[g].value = np.linalg.cholesky(symmetrize(Ng) + 1e-15 * np.eye(n))
        self.bmax.value = (1.0 - margin) / lam_max(phi_pred, D)
        _solve(self.problem, "weighted update SDP")
        p = np.maximum(np.asarray(self.p.value, dtype=float), _P_FLOOR)
        p = p / p.sum()
        beta = max(float(self.b.value), 0.0) / p[0]
        groups = np.asarray(groups, dtype=float).reshape(-1, n, n)
        phi = weighted_bound(phi_pred, H, self.C.value, self.K.value, s, beta, V, R, groups, p, D)
        return WeightedChoice(beta, self.C.value, self.K.value, phi, float(np.trace(phi)), p)
