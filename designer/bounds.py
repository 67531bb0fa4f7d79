"""Riccati-like covariance bounds of the distributed consensus filter (seed 003, Theorem 1).

Notation (one node ``i``, one step ``k -> k+1``)::

    (26) Phi_pred = F (Phi_post^-1 - (1+eps) sigma I)^-1 F^T + (eps sigma)^-1 U U^T + Q
    (27) Phi_post' = (1+2 d_i) A M A^T + sum_j 3 (1 - phibar_ij) C Phi_pred_j C^T
                     + sum_j 3 delta^2 gammabar_ij C C^T + K [(1+2 d_i) beta^-1 V V^T + R] K^T
         with A = I - s_i C - K H,  M = (Phi_pred^-1 - beta I)^-1,  s_i = sum_j (1 - phi_ij)
    (28) Phi_post^-1 > (1+eps) sigma I       (29) Phi_pred^-1 > beta I
    (30) K = (I - s_i C) M H^T [H M H^T + beta^-1 V V^T + R / (1+2 d_i)]^-1

Conditions are reported as *margins*: ``1/lambda_max(Phi) - (1+eps) sigma`` for (28)
and ``1/lambda_max(Phi_pred) - beta`` for (29); a margin <= 0 is a violation and
the bound is then undefined (the inverse in (26)/(27) is indefinite): the
functions here never compute it but return ``None``.

Theorem 2 (mean-square boundedness) asks, besides (28), for
``Phi_post^-1 <= ((1+d_max)/theta) sigma I`` with ``d_max < theta < (1+d_max)/(1+eps)``;
the most permissive theta tends to ``d_max``, so its margin is
``((1+d_max)/d_max) sigma - 1/lambda_min(Phi_post)`` (must be >= 0; an isolated node,
``d_max = 0``, has no upper condition).

``sigma = 0`` with ``U = 0`` (and ``beta = 0`` with ``V = 0``) is allowed: the
terms ``(eps sigma)^-1 U U^T`` and ``beta^-1 V V^T`` are then zero, and an isolated
node (no neighbours) reduces exactly to the extended Kalman filter.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .validation import InputError

__all__ = [
    "PredictionBound", "prediction_bound", "optimal_gain", "update_bound", "condition28_margin",
    "condition29_margin", "theorem2_margin", "shifted_inverse", "symmetrize",
]


def symmetrize(a: np.ndarray) -> np.ndarray:
    return 0.5 * (a + np.swapaxes(a, -1, -2))


_RCOND = 1e-13


def _inv_lam_max(a: np.ndarray) -> float:
    """``1 / lambda_max(a)``, or ``-inf`` when ``a`` is not numerically positive definite.

    "Numerically" means finite with a condition number below ``1 / _RCOND``: beyond
    that the smallest eigenvalues are rounding noise and the recursion means nothing.
    """
    if not np.all(np.isfinite(a)):
        return -np.inf
    lam = np.linalg.eigvalsh(symmetrize(a))
    return 1.0 / lam[-1] if lam[0] > _RCOND * lam[-1] else -np.inf


def _inv_lam_max_d(a: np.ndarray, D: np.ndarray | None) -> float:
    """``1 / lambda_max(D a Dᵀ)`` (``D = I`` when None), ``-inf`` when ``a`` is not numerically PD."""
    base = _inv_lam_max(a)
    if D is None or not np.isfinite(base):
        return base
    return 1.0 / float(np.linalg.eigvalsh(symmetrize(D @ a @ D.T))[-1])


def condition28_margin(phi_post: np.ndarray, sigma: float, eps: float, D: np.ndarray | None = None) -> float:
    """``1/lambda_max(D Φ Dᵀ) - (1+eps) sigma`` (``D = I``: the paper's (28)); must be > 0.

    With a structure matrix ``D`` (the remainder is ``U Ω D e``), (28) reads
    ``Φ^-1 > (1+eps) sigma DᵀD``, i.e. this margin > 0.  ``-inf`` if Φ is not positive definite.
    """
    return _inv_lam_max_d(phi_post, D) - (1.0 + eps) * sigma


def condition29_margin(phi_pred: np.ndarray, beta: float, D: np.ndarray | None = None) -> float:
    """``1/lambda_max(D Φ_pred Dᵀ) - beta`` (``D = I``: the paper's (29)); must be > 0."""
    return _inv_lam_max_d(phi_pred, D) - beta


def shifted_inverse(phi: np.ndarray, c: float, D: np.ndarray | None = None) -> np.ndarray:
    """``(Φ^-1 - c DᵀD)^-1`` (``D = I`` when None), positive definite by construction.

    ``D = I``: ``Q diag(λ / (1 - c λ)) Qᵀ`` from the eigendecomposition of Φ.
    General ``D``: ``Φ + Φ Dᵀ (c^-1 I - D Φ Dᵀ)^-1 D Φ`` (Woodbury), from the
    eigendecomposition of ``D Φ Dᵀ``.  Both avoid the two explicit inverses (which
    lose the small eigenvalues when Φ is ill-conditioned).  Requires
    ``c lambda_max(D Φ Dᵀ) < 1`` (conditions (28)/(29)).
    """
    if c == 0:
        return symmetrize(phi)
    if D is None:
        lam, Q = np.linalg.eigh(symmetrize(phi))
        return symmetrize((Q * (lam / (1.0 - c * lam))) @ Q.T)
    mu, Q = np.linalg.eigh(symmetrize(D @ phi @ D.T))
    G = phi @ D.T @ Q
    return symmetrize(phi + (G * (c / (1.0 - c * mu))) @ G.T)


def theorem2_margin(phi_post: np.ndarray, sigma: float, d_max: int) -> float:
    """``((1+d_max)/d_max) sigma - lambda_max(Phi_post^-1)``; must be >= 0 (inf when d_max = 0)."""
    if d_max == 0:
        return np.inf
    lam_min = float(np.linalg.eigvalsh(symmetrize(phi_post))[0])
    return (1.0 + d_max) / d_max * sigma - 1.0 / lam_min


def _scaled_outer(m: np.ndarray, scale: float, name: str, mult: str) -> np.ndarray:
    """``m m^T / scale``, taken as 0 when ``m = 0`` (whatever ``scale``)."""
    mm = m @ m.T
    if not np.any(mm):
        return mm
    if scale <= 0:
        raise InputError(f"{mult} must be > 0 when {name} is nonzero")
    return mm / scale


class PredictionBound(NamedTuple):
    phi_pred: np.ndarray | None
    margin28: float


def prediction_bound(phi_post, F, U, Q, sigma: float, eps: float, D=None) -> PredictionBound:
    """Evaluate (26) if (28) holds; otherwise return ``phi_pred=None`` and the (negative) margin.

    ``D``: structure of the remainder ``U Ω D e`` (``None``: the paper's ``D = I``).
    """
    margin = condition28_margin(phi_post, sigma, eps, D)
    if margin <= 0:
        return PredictionBound(None, margin)
    inner = shifted_inverse(phi_post, (1.0 + eps) * sigma, D)
    lin = _scaled_outer(U, eps * sigma, "U", "sigma")
    return PredictionBound(symmetrize(F @ inner @ F.T + lin + Q), margin)


def optimal_gain(phi_pred, H, C, s_i: float, beta: float, V, R, d_i: int, D=None) -> np.ndarray:
    """The gain (30) minimising ``tr Phi_post`` (requires (29))."""
    n = phi_pred.shape[0]
    M = shifted_inverse(phi_pred, beta, D)
    S = H @ M @ H.T + _scaled_outer(V, beta, "V", "beta") + R / (1.0 + 2 * d_i)
    # K = (I - s C) M H^T S^-1 via a solve with the symmetric positive-definite S.
    return (np.eye(n) - s_i * C) @ np.linalg.solve(symmetrize(S), H @ M).T


def update_bound(phi_pred, H, K, C, s_i: float, beta: float, V, R, d_i: int, neighbour_terms: np.ndarray,
                 D=None) -> np.ndarray:
    """Evaluate (27) (requires (29)).

    ``neighbour_terms`` is ``sum_j 3 (1 - phibar_ij) Phi_pred_j + 3 delta^2 gammabar_ij I``,
    the part sandwiched between ``C`` and ``C^T``; ``D`` the structure of ``V Θ D e``.
    """
    n = phi_pred.shape[0]
    M = shifted_inverse(phi_pred, beta, D)
    A = np.eye(n) - s_i * C - K @ H
    meas = (1.0 + 2 * d_i) * _scaled_outer(V, beta, "V", "beta") + R
    out = (1.0 + 2 * d_i) * A @ M @ A.T + C @ neighbour_terms @ C.T + K @ meas @ K.T
    return symmetrize(out)
