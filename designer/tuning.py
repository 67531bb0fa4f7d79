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

import numpy as np
from scipy.optimize import minimize_scalar

from .bounds import Spectrum, prediction_recursion, shifted_inverse, spectrum, symmetrize
from .validation import ComputationError

__all__ = [
    "MARGIN", "tuned_epsilon", "PredictionChoice", "UpdateChoice", "tune_prediction", "tune_update",
    "PredictionBatch", "tune_prediction_batch",
    "PredictionSDP", "UpdateSDP", "update_trace", "lam_max",
    "WeightedChoice", "own_term", "optimal_weights", "weighted_bound", "tune_weighted",
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


def lam_max(a, D=None) -> float:
    """``lambda_max(D a Dᵀ)`` (``D = I`` when None)."""
    return float(np.linalg.eigvalsh(symmetrize(a if D is None else D @ a @ D.T))[-1])


# --------------------------------------------------------------------------- prediction
def _sigma_max(phi_post, eps, margin, D=None) -> float:
    return (1.0 - margin) / ((1.0 + eps) * lam_max(phi_post, D))


class PredictionBatch(NamedTuple):
    """:func:`tune_prediction_batch`: one σ, Φ_{k+1|k} and trace per item."""

    sigma: np.ndarray  # (m,); NaN where the search left floats
    phi_pred: np.ndarray  # (m, n, n)
    trace: np.ndarray  # (m,)


def _structure(S: Spectrum, D) -> tuple[np.ndarray, np.ndarray]:
    """``μ`` (ascending) and ``G = Φ Dᵀ Q`` with ``D Φ Dᵀ = Q diag(μ) Qᵀ`` (``D = I``: Φ's own spectrum)."""
    if D is None:
        return S.lam, S.phi @ S.Q
    mu, Q = np.linalg.eigh(symmetrize(D @ S.phi @ np.swapaxes(D, -1, -2)))
    return mu, S.phi @ np.swapaxes(D, -1, -2) @ Q


def tune_prediction_batch(phi_post, F, U, Q, eps: float, margin: float = MARGIN, D=None) -> PredictionBatch:
    """:func:`tune_prediction` for stacked items: ``phi_post`` (m, n, n) or its :class:`~designer.bounds.Spectrum`,
    ``F`` and ``U`` (m, n, n) or one (n, n) for all, ``Q`` (n, n), ``D`` None, (r, n) or (m, r, n).

    ``tr F (Φ^-1 - cσ DᵀD)^-1 Fᵀ = tr F Φ Fᵀ + Σ_k g_k cσ / (1 - cσ μ_k)`` (Woodbury, ``c = 1 + ε``,
    ``D Φ Dᵀ = Σ μ_k q_k q_kᵀ``, ``g_k = |F Φ Dᵀ q_k|²``), so the trace of (26) is convex in σ with the
    increasing slope ``p(σ) - a / σ²``, ``p(σ) = Σ_k g_k c / (1 - cσ μ_k)²`` and ``a = tr(U Uᵀ) / ε``: σ is its
    root (:func:`increasing_root`, all items at once, with the fixed point ``σ = sqrt(a / p(σ))`` as the
    proposal) below (28)'s bound at margin ``margin``; σ = 0 where ``U = 0`` (the trace only grows with σ).
    """
    S = phi_post if isinstance(phi_post, Spectrum) else spectrum(phi_post)
    m, n = S.phi.shape[:2]
    F = np.broadcast_to(np.asarray(F, dtype=float), (m, n, n))
    U = np.broadcast_to(np.asarray(U, dtype=float), (m, n, n))
    UUt = U @ np.swapaxes(U, -1, -2)
    mu, G = _structure(S, D)
    c = 1.0 + eps
    smax = (1.0 - margin) / (c * mu[:, -1])
    sigma = np.zeros(m)
    act = np.flatnonzero(UUt.any(axis=(-2, -1)))
    if act.size:
        g = np.sum((F[act] @ G[act]) ** 2, axis=-2)  # (k, r)
        a = np.trace(UUt[act], axis1=-2, axis2=-1) / eps
        mu_a = mu[act]

        def slope(sv, idx):
            p = np.sum(g[idx] * c / (1.0 - c * sv[:, None] * mu_a[idx]) ** 2, axis=-1)
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
    S = phi_post if isinstance(phi_post, Spectrum) else spectrum(np.asarray(phi_post, dtype=float)[None])
    out = tune_prediction_batch(S, np.asarray(F, dtype=float)[None], np.asarray(U, dtype=float)[None], Q, eps,
                                margin, D)
    return PredictionChoice(float(out.sigma[0]), out.phi_pred[0], float(out.trace[0]))


# ------------------------------------------------------------------------------ update
def update_trace(phi_pred, H, C, K, s, beta, V, R, d_i, N, D=None) -> np.ndarray:
    """Φ_{k+1|k+1} of (27) for given (β, C, K) (``N`` is the neighbour matrix, ``D`` the structure of V Θ D e)."""
    w = 1.0 + 2 * d_i
    M = shifted_inverse(phi_pred, beta, D)
    A = np.eye(phi_pred.shape[0]) - s * C - K @ H
    VVt = V @ V.T
    W = (w * VVt / beta if np.any(VVt) else 0.0 * VVt) + R
    return symmetrize(w * A @ M @ A.T + C @ N @ C.T + K @ W @ K.T)


class _FixedBeta:
    """For fixed β: the optimal ``Z = [C K]`` and the optimal trace, from one eigendecomposition of Φ_pred.

    ``f(Z) = w tr M - 2 w tr(Z B^T M) + tr(Z G Z^T)`` with ``G = D + w B^T M B``, so
    ``Z* = w M B G^-1`` and ``f* = w tr M - w^2 tr(M B G^-1 B^T M)``.
    """

    def __init__(self, phi_pred, H, s, V, R, w: float, N, D=None):
        self.n, m = phi_pred.shape[0], H.shape[0]
        self.w = float(w)
        Dm = np.eye(self.n) if D is None else D
        # M(β) = Φ + G diag(β / (1 - β μ)) Gᵀ with D Φ Dᵀ = Q diag(μ) Qᵀ and G = Φ Dᵀ Q (Woodbury).
        self.phi = symmetrize(phi_pred)
        self.mu, Qd = np.linalg.eigh(symmetrize(Dm @ phi_pred @ Dm.T))
        self.G = self.phi @ Dm.T @ Qd
        self.B = np.hstack([s * np.eye(self.n), H.T])  # n x (n + m)
        self.VVt = V @ V.T
        self.has_v = bool(np.any(self.VVt))
        self.R = R
        self.D = np.zeros((self.n + m, self.n + m))
        self.D[: self.n, : self.n] = N

    def _parts(self, beta):
        M = self.phi + (self.G * (beta / (1.0 - beta * self.mu))) @ self.G.T
        D = self.D.copy()
        D[self.n:, self.n:] = (self.w * self.VVt / beta if self.has_v else 0.0) + self.R
        MB = M @ self.B
        G = symmetrize(D + self.w * self.B.T @ MB)
        return M, MB, G

    @staticmethod
    def _solve(G, rhs):
        try:
            return np.linalg.solve(G, rhs)
        except np.linalg.LinAlgError:
            # G is singular when a block of Z does not matter (e.g. C with s = 0 and N = 0): minimum norm.
            return np.linalg.lstsq(G, rhs, rcond=None)[0]

    def trace(self, beta) -> float:
        M, MB, G = self._parts(beta)
        return float(self.w * np.trace(M) - self.w**2 * np.sum(MB * self._solve(G, MB.T).T))

    def gains(self, beta):
        M, MB, G = self._parts(beta)
        Z = self.w * self._solve(G, MB.T).T
        return Z[:, : self.n], Z[:, self.n:]

    def slope(self, beta) -> float:
        """``d f*/dβ`` by the envelope theorem: ``w tr A M'(β) Aᵀ - w tr K V Vᵀ Kᵀ / β²`` at the optimal Z,
        with ``M' = G diag(1/(1 - β μ)²) Gᵀ`` (increasing in β: f* is convex)."""
        beta = np.float64(beta)  # NumPy division: inf or NaN (caught by the caller) where floats end
        C, K = self.gains(beta)
        A = np.eye(self.n) - C @ self.B[:, : self.n].T - K @ self.B[:, self.n:].T  # I - s C - K H
        AG = A @ self.G
        out = self.w * float(np.sum(AG**2 / (1.0 - beta * self.mu) ** 2))
        if self.has_v:
            out -= self.w * float(np.sum((K @ self.VVt) * K)) / beta**2
        return out


def tune_update(phi_pred, H, s: float, V, R, d_i: int, N, margin: float = MARGIN, D=None) -> UpdateChoice:
    """Minimise ``tr Φ_{k+1|k+1}`` over (β, C, K) with (29) kept at margin (closed form + scalar search)."""
    with np.errstate(over="ignore", invalid="ignore"):  # a diverging bound is caught by the caller's checks
        return _tune_update(phi_pred, H, s, V, R, d_i, N, margin, D)


def _tune_update(phi_pred, H, s, V, R, d_i, N, margin, D) -> UpdateChoice:
    beta, C, K = _best_gains(phi_pred, H, s, V, R, 1.0 + 2 * d_i, N, margin, D)
    phi = update_trace(phi_pred, H, C, K, s, beta, V, R, d_i, N, D)
    return UpdateChoice(beta, C, K, phi, float(np.trace(phi)))


def _evaluate(slope, x, idx) -> tuple[np.ndarray, np.ndarray]:
    """``slope(x, idx)`` as (slopes, proposals), proposals NaN where the slope gives none."""
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        out = slope(x, idx)
        if isinstance(out, tuple):
            return np.asarray(out[0], float), np.asarray(out[1], float)
        return np.asarray(out, float), np.full(x.shape, np.nan)


def _log_width(a, b, geo):
    """The bracket's size: ``log(b/a)`` for a bracket of positive numbers (``geo``), else ``b - a``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(geo, np.log(np.where(geo, b, 1.0) / np.where(geo, a, 1.0)), b - a)


def increasing_root(slope, lo, hi, *, xtol, rtol: float = 1e-12, maxiter: int = 200) -> np.ndarray:
    """For many items at once: the point of ``[lo, hi]`` where an increasing ``slope`` crosses zero.

    ``slope(b, idx)`` returns the slopes of the items ``idx`` (an index array) at the points
    ``b`` (one per item of ``idx``), or a pair ``(slopes, proposals)``: ``proposals`` are the
    caller's guesses of each root from what it knows at ``b`` (e.g. the fixed point
    ``b = sqrt(q(b) / p(b))`` of a slope ``p(b) - q(b) / b²``; NaN: none).  Per item the result is
    ``hi`` where ``slope(hi) <= 0`` (the constraint binds), ``lo`` where ``slope(lo) >= 0``, and
    otherwise a point of a bracket ``[a, b]`` (``slope(a) < 0 < slope(b)``) that is within
    ``xtol + rtol |b|``.  The bracket shrinks by a safeguarded step per iteration: a proposal
    (refined by the secant through the last two proposals' residuals) when it falls inside the
    bracket, else the Illinois variant of false position; a bisection (geometric for a bracket of
    positive numbers, which may span decades) whenever three steps have not halved the bracket;
    and no point closer than half the tolerance to an end, so that once the steps converge the
    next point lands across the root and closes the bracket.  A non-finite slope at an end gives
    NaN (the caller decides); inside the bracket it counts as positive.  This is the multiplier
    search of the tuned and mse designs; a single item is a batch of one, so the per-run and the
    batched filters take the same steps.
    """
    lo = np.array(lo, dtype=float, ndmin=1)
    hi = np.array(np.broadcast_to(hi, lo.shape), dtype=float)
    xtol = np.broadcast_to(np.asarray(xtol, dtype=float), lo.shape)
    m = lo.size
    idx = np.arange(m)
    f, proposal = _evaluate(slope, np.concatenate([lo, hi]), np.concatenate([idx, idx]))  # both ends, one call
    f_lo, f_hi, proposal = f[:m], f[m:], proposal[m:]
    out = np.full(lo.shape, np.nan)
    finite = np.isfinite(f_lo) & np.isfinite(f_hi)
    out[finite & (f_hi <= 0)] = hi[finite & (f_hi <= 0)]
    low_end = finite & (f_hi > 0) & (f_lo >= 0)
    out[low_end] = lo[low_end]
    act = np.flatnonzero(finite & (f_hi > 0) & (f_lo < 0))
    a, b, fa, fb, prop = lo[act], hi[act], f_lo[act], f_hi[act], proposal[act]
    x0, r0 = np.full(act.size, np.nan), np.full(act.size, np.nan)  # the last two points with a proposal,
    x1, r1 = b.copy(), prop - b  # and their residuals proposal - point (the secant's data)
    geo = a > 0
    sizes = [np.full(act.size, np.inf), np.full(act.size, np.inf), _log_width(a, b, geo)]  # the last three
    side = np.zeros(act.size, dtype=int)  # which end was kept last (-1 a, +1 b): Illinois halves its value
    for _ in range(maxiter):
        if not act.size:
            break
        slow = sizes[2] > 0.5 * sizes[0]
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            secant = x1 - r1 * (x1 - x0) / (r1 - r0)
            fp = a - fa * (b - a) / (fb - fa)
        guess = np.where(np.isfinite(secant) & (secant > a) & (secant < b), secant, prop)
        mid = np.where(geo, np.sqrt(np.abs(a * b)), 0.5 * (a + b))
        c = np.where(np.isfinite(guess) & (guess > a) & (guess < b) & ~slow, guess,
                     np.where(slow | ~((fp > a) & (fp < b)), mid, fp))
        half = 0.5 * (xtol[act] + rtol * np.abs(c))  # keep half the tolerance away from the ends
        c = np.where(a + half < b - half, np.clip(c, a + half, b - half), 0.5 * (a + b))
        fc, pc = _evaluate(slope, c, act)
        nan = ~np.isfinite(fc)  # a slope beyond floats inside the bracket: treat as positive (shrink from above)
        up = nan | (fc > 0)  # the root is below c
        b = np.where(up, c, b)
        fb = np.where(up, np.where(nan, np.abs(fa) + 1.0, fc), fb)
        a = np.where(up, a, c)
        fa = np.where(up, fa, fc)
        fa = np.where(up & (side == -1), 0.5 * fa, fa)  # Illinois: an end kept twice has its value halved
        fb = np.where(~up & (side == 1), 0.5 * fb, fb)
        side = np.where(up, -1, 1)
        has = np.isfinite(pc) & ~nan
        x0, r0 = np.where(has, x1, x0), np.where(has, r1, r0)
        x1, r1 = np.where(has, c, x1), np.where(has, pc - c, r1)
        prop = np.where(has, pc, np.nan)
        done = (fc == 0) | (b - a <= xtol[act] + rtol * np.abs(c))
        out[act[done]] = np.where(fc[done] == 0, c[done], 0.5 * (a[done] + b[done]))
        keep = ~done
        act, a, b, fa, fb, side, prop, geo, x0, r0, x1, r1 = (
            v[keep] for v in (act, a, b, fa, fb, side, prop, geo, x0, r0, x1, r1))
        sizes = [sizes[1][keep], sizes[2][keep], _log_width(a, b, geo)]
    if act.size:  # maxiter reached: the middle of what is left
        out[act] = 0.5 * (a + b)
    return out


def best_multiplier(trace_at, bmax: float, has_v: bool) -> float:
    """The β in ``(0, bmax]`` minimising the convex ``trace_at(β)`` (0 without V: the trace only grows with β)."""
    if not has_v:
        return 0.0
    res = minimize_scalar(trace_at, bounds=(bmax * 1e-9, bmax), method="bounded",
                          options={"xatol": bmax * 1e-8, "maxiter": 500})
    return float(res.x)


def _best_gains(phi_pred, H, s, V, R, w, N, margin, D):
    """(β, C, K) minimising ``w tr(A M Aᵀ + K V Vᵀ Kᵀ / β) + tr C N Cᵀ + tr K R Kᵀ`` with (29) at margin."""
    bmax = (1.0 - margin) / lam_max(phi_pred, D)
    fixed = _FixedBeta(phi_pred, H, s, V, R, w, N, D)
    if not np.any(V):
        beta = 0.0  # without V the trace only grows with β (M grows)
    else:  # the root of the increasing slope of the convex f*(β), bracketed
        beta = float(increasing_root(lambda b, _idx: np.array([fixed.slope(x) for x in b]), bmax * 1e-9, bmax,
                                     xtol=bmax * 1e-9, rtol=1e-9)[0])
        if not np.isfinite(beta):
            beta = best_multiplier(fixed.trace, bmax, True)  # a bound beyond floats: the plain search
    C, K = fixed.gains(beta)
    return beta, C, K


# ----------------------------------------------------------------- optimised weights
class WeightedChoice(NamedTuple):
    beta: float
    C: np.ndarray
    K: np.ndarray
    phi_post: np.ndarray
    trace: float
    weights: np.ndarray  # (1 + G,) p_0 (the node's own group) then one per neighbour group; sums to 1


_P_FLOOR = 1e-12  # a group's weight is never below this (a zero weight would make its term 0/0)


def own_term(phi_pred, H, C, K, s: float, beta: float, V, D=None) -> np.ndarray:
    """The node's own error group of (27): ``A M Aᵀ + K V Vᵀ Kᵀ / β`` (``A = I - sC - KH``, M of (29))."""
    M = shifted_inverse(phi_pred, beta, D)
    A = np.eye(phi_pred.shape[0]) - s * C - K @ H
    KV = K @ V
    lin = KV @ KV.T / beta if np.any(KV) else 0.0 * M
    return symmetrize(A @ M @ A.T + lin)


def optimal_weights(traces) -> np.ndarray:
    """``p_l = √t_l / Σ √t_l``: the weights minimising ``Σ t_l / p_l`` over the simplex (floored at 1e-12)."""
    r = np.sqrt(np.maximum(np.asarray(traces, dtype=float), 0.0))
    if not r.sum() > 0:
        return np.full(r.size, 1.0 / r.size)
    p = np.maximum(r / r.sum(), _P_FLOOR)
    return p / p.sum()


def neighbour_groups(phi_nb, q_fdi, delta: float, receipt=None, span=None) -> np.ndarray:
    """The neighbour groups of the weighted (27), shape (G, n, n).

    One group per neighbour channel ``j`` (rows of ``phi_nb``, (J, n, n): the neighbours'
    ``Φ_{j,k+1|k}``, times ``receipt[j]``, the probability the packet arrives, 1 for a packet
    that did), and one for all falsified packets together: with independent FDI indicators
    ``γ_j`` of probabilities ``q_fdi[j]`` and ``||ξ_j|| <= δ`` (any signal, not only a
    zero-mean one), ``||Σ_j γ_j ξ_j||² <= δ² (Σ_j γ_j)²``, whose mean is
    ``δ² (Σ_j q_j (1 - q_j) + (Σ_j q_j)²)``; that group is ``δ² E[(Σ_j γ_j)²] Π`` (omitted when 0),
    with ``Π`` (``span``) the projector onto the components the signal can reach (default I).
    """
    phi_nb = np.asarray(phi_nb, dtype=float)
    q = np.asarray(q_fdi, dtype=float)
    groups = phi_nb if receipt is None else phi_nb * np.asarray(receipt, dtype=float)[:, None, None]
    m2 = float(np.sum(q * (1.0 - q)) + np.sum(q) ** 2) * delta**2
    if m2 > 0:
        span = np.eye(phi_nb.shape[-1]) if span is None else np.asarray(span, dtype=float)
        groups = np.concatenate([groups, m2 * span[None]])
    return groups


def _group_traces(C, groups) -> np.ndarray:
    return np.einsum("ab,gbc,ac->g", C, groups, C) if len(groups) else np.zeros(0)


def weighted_bound(phi_pred, H, C, K, s: float, beta: float, V, R, groups, weights, D=None) -> np.ndarray:
    """(27) with weights: ``own / p_0 + Σ_g C N_g Cᵀ / p_g + K R Kᵀ`` (``groups``: (G, n, n), ``weights``: (1+G,))."""
    p = np.asarray(weights, dtype=float)
    out = own_term(phi_pred, H, C, K, s, beta, V, D) / p[0] + K @ R @ K.T
    if len(groups):
        out = out + C @ np.einsum("gab,g->ab", groups, 1.0 / p[1:]) @ C.T
    return symmetrize(out)


def _weighted_choice(phi_pred, H, C, K, s, beta, V, R, groups, D) -> WeightedChoice:
    """The bound for given (β, C, K) with the weights that make its trace smallest (closed form)."""
    p = optimal_weights(np.concatenate([[np.trace(own_term(phi_pred, H, C, K, s, beta, V, D))],
                                        _group_traces(C, groups)]))
    phi = weighted_bound(phi_pred, H, C, K, s, beta, V, R, groups, p, D)
    return WeightedChoice(beta, C, K, phi, float(np.trace(phi)), p)


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
    (e.g. the node's weights at the previous step); default: equal weights.
    """
    groups = np.asarray(groups, dtype=float).reshape(-1, *phi_pred.shape)
    g = len(groups)
    p = np.full(g + 1, 1.0 / (g + 1)) if weights is None or len(weights) != g + 1 else np.asarray(weights, float)
    floor = np.log(_P_FLOOR)
    best, last = None, np.inf
    ys: list[np.ndarray] = []
    gs: list[np.ndarray] = []
    with np.errstate(over="ignore", invalid="ignore"):
        for _ in range(max_iter):
            N = np.einsum("gab,g->ab", groups, 1.0 / p[1:]) if g else np.zeros_like(phi_pred)
            beta, C, K = _best_gains(phi_pred, H, s, V, R, 1.0 / p[0], N, margin, D)
            choice = _weighted_choice(phi_pred, H, C, K, s, beta, V, R, groups, D)
            improved = best is None or choice.trace < best.trace
            if improved:
                best = choice
            y, gy = np.log(p), np.log(choice.weights)
            if g == 0 or np.abs(gy - y).max() <= 1e-9 or abs(last - choice.trace) <= tol * choice.trace:
                break
            last = choice.trace
            if not improved:  # the extrapolation overshot: restart from the best point
                ys, gs = [], []
                p = best.weights
                continue
            ys.append(y)
            gs.append(gy)
            ys, gs = ys[-memory - 1:], gs[-memory - 1:]
            nxt = gy
            if len(ys) > 1:
                Fm = np.array([b - a for a, b in zip(ys, gs)]).T
                gamma = np.linalg.lstsq(np.diff(Fm, axis=1), Fm[:, -1], rcond=None)[0]
                cand = gy - np.diff(np.array(gs).T, axis=1) @ gamma
                if np.all(np.isfinite(cand)):
                    nxt = cand
            q = np.exp(np.clip(nxt - nxt.max(), floor, 0.0))
            p = np.maximum(q / q.sum(), _P_FLOOR)
            p = p / p.sum()
    return best


# ------------------------------------------------------------------------------ SDPs
def _solve(problem, what: str) -> None:
    import cvxpy as cp

    try:
        problem.solve(solver=cp.CLARABEL)
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
