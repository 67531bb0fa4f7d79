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
from scipy.optimize import brentq, minimize_scalar

from .bounds import shifted_inverse, symmetrize
from .validation import ComputationError

__all__ = [
    "MARGIN", "tuned_epsilon", "PredictionChoice", "UpdateChoice", "tune_prediction", "tune_update",
    "PredictionSDP", "UpdateSDP", "CertifySDP", "update_trace", "lam_max", "certify_update",
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
def _prediction(phi_post, F, UUt, Q, sigma, eps, D=None) -> np.ndarray:
    lin = UUt / (eps * sigma) if np.any(UUt) else 0.0 * UUt
    return symmetrize(F @ shifted_inverse(phi_post, (1.0 + eps) * sigma, D) @ F.T + lin + Q)


def _sigma_max(phi_post, eps, margin, D=None) -> float:
    return (1.0 - margin) / ((1.0 + eps) * lam_max(phi_post, D))


def tune_prediction(phi_post, F, U, Q, eps: float, margin: float = MARGIN, D=None) -> PredictionChoice:
    """Minimise ``tr Φ_{k+1|k}`` over σ with (28) kept at relative margin ``margin`` (scalar search).

    ``D``: structure of the remainder ``U Ω D e`` (``None``: ``D = I``, the paper's form).
    """
    UUt = U @ U.T
    smax = _sigma_max(phi_post, eps, margin, D)
    if not np.any(UUt):
        # Without linearisation error the trace only grows with σ: σ -> 0 (the EKF prediction).
        sigma = 0.0
    else:
        # tr F (Φ^-1 - cσ DᵀD)^-1 F^T = tr F Φ F^T + Σ_k g_k cσ / (1 - cσ μ_k) (Woodbury), with
        # D Φ Dᵀ = Σ μ_k q_k q_kᵀ and g_k = |F Φ Dᵀ q_k|²; the trace is convex in σ, so its derivative
        # Σ_k g_k c / (1 - cσ μ_k)² - a / σ² is increasing: find its root by bracketing.
        c = 1.0 + eps
        Dm = np.eye(phi_post.shape[0]) if D is None else D
        mu, vec = np.linalg.eigh(symmetrize(Dm @ phi_post @ Dm.T))
        g = np.sum((F @ phi_post @ Dm.T @ vec) ** 2, axis=0)
        a = np.trace(UUt) / eps

        def slope(sv):
            return float(np.sum(g * c / (1.0 - c * sv * mu) ** 2) - a / sv**2)

        lo = smax * 1e-12
        if slope(smax) <= 0:
            sigma = smax  # the margin on (28) binds
        elif slope(lo) >= 0:
            sigma = lo
        else:
            sigma = float(brentq(slope, lo, smax, xtol=smax * 1e-13, rtol=1e-14, maxiter=200))
    phi = _prediction(phi_post, F, UUt, Q, sigma, eps, D) if sigma > 0 else symmetrize(F @ phi_post @ F.T + Q)
    return PredictionChoice(sigma, phi, float(np.trace(phi)))


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

    def __init__(self, phi_pred, H, s, V, R, d_i, N, D=None):
        self.n, m = phi_pred.shape[0], H.shape[0]
        self.w = 1.0 + 2 * d_i
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


def tune_update(phi_pred, H, s: float, V, R, d_i: int, N, margin: float = MARGIN, D=None) -> UpdateChoice:
    """Minimise ``tr Φ_{k+1|k+1}`` over (β, C, K) with (29) kept at margin (closed form + scalar search)."""
    with np.errstate(over="ignore", invalid="ignore"):  # a diverging bound is caught by the caller's checks
        return _tune_update(phi_pred, H, s, V, R, d_i, N, margin, D)


def _tune_update(phi_pred, H, s, V, R, d_i, N, margin, D) -> UpdateChoice:
    bmax = (1.0 - margin) / lam_max(phi_pred, D)
    fixed = _FixedBeta(phi_pred, H, s, V, R, d_i, N, D)
    trace_at = fixed.trace

    if not np.any(V):
        # Without V the trace only grows with β (M grows): β = 0.
        beta = 0.0
    else:
        res = minimize_scalar(trace_at, bounds=(bmax * 1e-9, bmax), method="bounded",
                              options={"xatol": bmax * 1e-8, "maxiter": 500})
        beta = float(res.x)
    C, K = fixed.gains(beta)
    phi = update_trace(phi_pred, H, C, K, s, beta, V, R, d_i, N, D)
    return UpdateChoice(beta, C, K, phi, float(np.trace(phi)))


def certify_update(phi_pred, H, C, K, s: float, V, R, d_i: int, N, margin: float = MARGIN, D=None) -> UpdateChoice:
    """The smallest bound (27) for *given* gains ``(C, K)``: β minimising ``tr Φ_{k+1|k+1}`` with (29) at margin.

    Theorem 1's bound holds for any gains as long as (28)-(29) hold, so gains chosen for
    another purpose (``mode='mse'``) are certified by choosing only the multiplier.  For fixed
    gains ``tr Φ(β) = w tr A (Φ_pred^-1 - β DᵀD)^-1 Aᵀ + w tr K V Vᵀ Kᵀ / β + const`` is convex
    in β on ``0 < β < 1/λmax(D Φ_pred Dᵀ)`` (a matrix-fractional term in an affine matrix plus
    ``1/β``), so a bounded scalar search finds its minimum (:class:`CertifySDP` solves the same
    problem as an SDP; the tests compare them).
    """
    with np.errstate(over="ignore", invalid="ignore"):
        bmax = (1.0 - margin) / lam_max(phi_pred, D)
        if not np.any(V):
            beta = 0.0  # without V the trace only grows with β
        else:
            res = minimize_scalar(lambda b: float(np.trace(update_trace(phi_pred, H, C, K, s, b, V, R, d_i, N, D))),
                                  bounds=(bmax * 1e-9, bmax), method="bounded",
                                  options={"xatol": bmax * 1e-8, "maxiter": 500})
            beta = float(res.x)
        phi = update_trace(phi_pred, H, C, K, s, beta, V, R, d_i, N, D)
    return UpdateChoice(beta, C, K, phi, float(np.trace(phi)))


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
        UUt = U @ U.T
        phi = _prediction(phi_post, F, UUt, Q, sigma, eps, D) if sigma > 0 else symmetrize(F @ phi_post @ F.T + Q)
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


class CertifySDP:
    """The β problem of :func:`certify_update` (fixed gains) as an SDP, built once for dimensions (n, m)."""

    def __init__(self, n: int, m: int):
        import cvxpy as cp

        self.Pinv = cp.Parameter((n, n), symmetric=True)
        self.A = cp.Parameter((n, n))  # I - s C - K H
        self.KV = cp.Parameter((n, m))
        self.w = cp.Parameter(nonneg=True)
        self.const = cp.Parameter()  # tr C N Cᵀ + tr K R Kᵀ
        self.bmax = cp.Parameter(nonneg=True)
        self.DtD = cp.Parameter((n, n), PSD=True)
        self.beta = cp.Variable(nonneg=True)
        X = cp.Variable((n, n), symmetric=True)
        T = cp.Variable((n, n), symmetric=True)
        cons = [
            cp.bmat([[X, self.A], [self.A.T, self.Pinv - self.beta * self.DtD]]) >> 0,
            cp.bmat([[T, self.KV], [self.KV.T, self.beta * np.eye(m)]]) >> 0,
            self.beta <= self.bmax,
        ]
        self.problem = cp.Problem(cp.Minimize(self.w * cp.trace(X) + self.w * cp.trace(T) + self.const), cons)
        assert self.problem.is_dpp()

    def solve(self, phi_pred, H, C, K, s: float, V, R, d_i: int, N, margin: float = MARGIN, D=None) -> UpdateChoice:
        n = phi_pred.shape[0]
        Dm = np.eye(n) if D is None else D
        self.DtD.value = Dm.T @ Dm
        self.Pinv.value = symmetrize(np.linalg.inv(phi_pred))
        self.A.value = np.eye(n) - s * C - K @ H
        self.KV.value = K @ V
        self.w.value = 1.0 + 2 * d_i
        self.const.value = float(np.trace(C @ N @ C.T) + np.trace(K @ R @ K.T))
        self.bmax.value = (1.0 - margin) / lam_max(phi_pred, D)
        _solve(self.problem, "certification SDP")
        beta = max(float(self.beta.value), 0.0)
        phi = update_trace(phi_pred, H, C, K, s, beta, V, R, d_i, N, D)
        return UpdateChoice(beta, C, K, phi, float(np.trace(phi)))
