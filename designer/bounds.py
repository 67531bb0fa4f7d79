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

**Batches.**  Every function also takes stacks of matrices ``(..., n, n)`` (many runs and
nodes at once, :mod:`filters.consensus_batch`): scalars such as σ, β, ``s_i`` and ``d_i``
may then be arrays over the leading axes, a margin is an array of margins, and
:func:`prediction_bound` returns NaN matrices where (28) fails (``None`` for one matrix).
One matrix gives the same numbers as an item of a stack, up to rounding.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .validation import InputError

__all__ = [
    "PredictionBound", "prediction_bound", "prediction_recursion", "optimal_gain", "optimal_gain_from",
    "update_bound", "update_bound_from", "condition28_margin", "condition29_margin", "theorem2_margin",
    "shifted_inverse", "symmetrize", "Spectrum", "spectrum", "eigh", "eigvalsh", "sqrtm_psd", "lower_inverse",
    "BOUND_LIMIT",
]

#: A bound whose trace reaches this certifies nothing, and the prediction bound (26) overflows beyond it: every
#: recursion of a bound (the consensus filters', the scheduled design's) stops there.
BOUND_LIMIT = 1e100


def symmetrize(a: np.ndarray) -> np.ndarray:
    out = np.add(a, np.swapaxes(a, -1, -2), dtype=np.result_type(a, 0.5))
    out *= 0.5  # in place: one temporary fewer than 0.5 * (a + aᵀ), the same numbers
    return out


def _t(a: np.ndarray) -> np.ndarray:
    return a.swapaxes(-1, -2)


def _stacked(x) -> bool:
    """``x`` holds one value per matrix of a stack (not one number for all)."""
    return isinstance(x, np.ndarray) and x.ndim > 0


def _per_matrix(x):
    """A number as it is, or an array of one value per matrix of a stack, shaped to multiply ``(..., n, n)``."""
    return x[..., None, None] if _stacked(x) else x


def _items(x, batch: tuple, mask, core: int) -> np.ndarray:
    """The items of ``x`` where ``mask``, ``x`` broadcast to ``batch`` plus its own last ``core`` axes."""
    x = np.asarray(x)
    return np.broadcast_to(x, batch + x.shape[x.ndim - core:])[mask]


def _one(out, batch: tuple):
    """A plain number for one matrix (``batch == ()``), the array of them for a stack."""
    return float(out) if batch == () else out


class Spectrum:
    """A (stack of) symmetric Φ with its eigenvalues and, when asked, its eigenvectors, each computed once
    (:func:`spectrum`), so that the margins (28)/(29), Theorem 2 and the shifted inverse of one Φ share them.

    ``lam`` (..., n): the eigenvalues, ascending, NaN for a non-finite Φ: the eigen-decomposition's when it has been
    computed, else :func:`eigvalsh`'s (less than half its work), computed on first use.  :meth:`eig` gives the
    eigen-decomposition ``(λ, Q)`` (:func:`eigh`, computed on first use): what needs the eigenvectors takes the pair
    from it (a shifted inverse, the tuned rule's search); a rule whose step will need them asks for them before the
    margins (:func:`spectrum` with ``vectors``, or :meth:`eig` first), so that one ``eigh`` serves both.  Where no
    step needs them (σ = β = 0: the local and centralized EKFs), a step costs one ``eigvalsh``.
    """

    __slots__ = ("phi", "_lam", "_eig")

    def __init__(self, phi: np.ndarray, lam: np.ndarray | None = None, eig: tuple | None = None):
        self.phi = phi  # (..., n, n), symmetrised
        self._lam, self._eig = lam, eig

    @property
    def lam(self) -> np.ndarray:
        if self._lam is None:
            self._lam = self._eig[0] if self._eig is not None else _finite_only(eigvalsh, self.phi, False)
        return self._lam

    def eig(self) -> tuple[np.ndarray, np.ndarray]:
        """``(λ, Q)``: the eigenvalues (ascending) and eigenvectors (columns) of Φ, NaN for a non-finite Φ."""
        if self._eig is None:
            self._eig = _finite_only(eigh, self.phi, True)
        return self._eig

    @property
    def Q(self) -> np.ndarray:
        """The eigenvectors (columns) of :meth:`eig`."""
        return self.eig()[1]

    def take(self, index) -> "Spectrum":
        """The items ``index`` (a mask or indices over the leading axes) of a stack (what has been computed of
        them)."""
        return Spectrum(self.phi[index], None if self._lam is None else self._lam[index],
                        None if self._eig is None else (self._eig[0][index], self._eig[1][index]))


_THREADED_EIGH = 64  # matrices in a stack from which eigh is split over the cores
#: ... or the work (matrices x size³) from which it is: 5 matrices of 58 x 58 (a 28-node scheduled design's link
#: gains, 28 of them per step: 2.7 s of its 19 s on one core).
_THREADED_WORK = 64 * 24**3


def eigh(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``numpy.linalg.eigh(a)`` of symmetric matrices (..., n, n), a large stack split over the usable cores.

    LAPACK decomposes each matrix alone and NumPy releases the GIL, so the parts run in
    parallel (:func:`designer.cores.thread_pool`) and the result is the same bits; 40 % of
    the batched mse consensus filter's time was this call on one core.
    """
    return _split(np.linalg.eigh, a, vectors=True)


def eigvalsh(a: np.ndarray) -> np.ndarray:
    """``numpy.linalg.eigvalsh(a)`` (the eigenvalues alone: less than half of :func:`eigh`'s work), split alike."""
    return _split(np.linalg.eigvalsh, a, vectors=False)


#: rows from which :func:`lower_inverse` inverts matrix by matrix (below, one batched call costs less than the loop)
_TRTRI_ROWS = 16


def lower_inverse(L: np.ndarray) -> np.ndarray:
    """The inverses of lower triangular matrices ``L`` (..., m, m) with a nonzero diagonal (Cholesky factors: their
    strict upper triangle zero, as the inverse's is).  From :data:`_TRTRI_ROWS` rows by LAPACK's ``trtri``, matrix
    by matrix: a third of ``numpy.linalg.inv``'s time at 30 to 64 rows (it factors the triangle by LU first);
    below, numpy's.  Either way each matrix alone: the same bits for a matrix alone or in a stack."""
    L = np.asarray(L, dtype=float)
    m = L.shape[-1]
    if m < _TRTRI_ROWS:
        return np.linalg.inv(L)
    from scipy.linalg.lapack import dtrtri

    flat = L.reshape((-1, m, m))
    out = np.empty(flat.shape)
    for k, low in enumerate(flat):
        inv, info = dtrtri(low.T, lower=0)  # Lᵀ, upper, in Fortran's order as it lies: its inverse is (L⁻¹)ᵀ
        if info:
            raise np.linalg.LinAlgError("Singular matrix")
        out[k] = inv.T
    return out.reshape(L.shape)


def sqrtm_psd(P: np.ndarray, inverse: bool = False) -> np.ndarray:
    """The symmetric square root ``P^{1/2}`` of positive semidefinite matrices (..., n, n), or the
    pseudo-inverse root ``P^{-1/2}`` (directions below ``1e-14`` of the largest eigenvalue taken as 0).
    Unique and continuous in ``P``: nearby covariances give nearby roots (a Cholesky or eigenvector
    factor could turn within a repeated eigenvalue's space)."""
    lam, V = eigh(symmetrize(P))
    top = np.maximum(lam[..., -1:], 0.0)
    keep = lam > 1e-14 * top
    if inverse:
        s = np.where(keep, 1.0 / np.sqrt(np.where(keep, lam, 1.0)), 0.0)
    else:
        s = np.sqrt(np.maximum(lam, 0.0))
    return symmetrize((V * s[..., None, :]) @ _t(V))


def _split(fn, a: np.ndarray, vectors: bool):
    """``fn`` (numpy's eigh or eigvalsh) of a stack, split over the usable cores when the stack is large."""
    from .cores import thread_pool, usable_cores

    m = a.shape[-2:]
    k = int(np.prod(a.shape[:-2], dtype=np.int64))
    cores = usable_cores()
    work = k * m[0] ** 3
    if cores < 2 or k < 2 or (k < _THREADED_EIGH and work < _THREADED_WORK):
        return fn(a)
    flat = a.reshape(k, *m)
    lam = np.empty((k, m[0]))
    Q = np.empty((k, *m)) if vectors else None
    bounds = np.linspace(0, k, min(cores, k, max(k // (_THREADED_EIGH // 2), work // (_THREADED_WORK // 2))) + 1
                         ).astype(int)

    def part(i: int) -> None:
        s = slice(bounds[i], bounds[i + 1])
        if vectors:
            lam[s], Q[s] = fn(flat[s])
        else:
            lam[s] = fn(flat[s])

    list(thread_pool().map(part, range(len(bounds) - 1)))
    if not vectors:
        return lam.reshape(a.shape[:-1])
    return lam.reshape(a.shape[:-1]), Q.reshape(a.shape)


def spectrum(phi, vectors: bool = False) -> Spectrum:
    """The :class:`Spectrum` of ``phi`` (..., n, n), symmetrised; with ``vectors`` its eigen-decomposition computed
    now (its eigenvalues are then the decomposition's), else what is asked of it when it is asked."""
    S = Spectrum(symmetrize(np.asarray(phi, dtype=float)))
    if vectors:
        S.eig()
    return S


def _finite_only(fn, phi: np.ndarray, vectors: bool):
    """``fn`` (:func:`eigh` or :func:`eigvalsh`) of the finite matrices of a stack, NaN for the others."""
    if np.isfinite(phi).all():
        return fn(phi)
    lam = np.full(phi.shape[:-1], np.nan)
    Q = np.full(phi.shape, np.nan) if vectors else None
    finite = np.isfinite(phi).all(axis=(-2, -1))
    if finite.any():
        if vectors:
            lam[finite], Q[finite] = fn(phi[finite])
        else:
            lam[finite] = fn(phi[finite])
    return (lam, Q) if vectors else lam


def _matrix(phi) -> np.ndarray:
    return phi.phi if isinstance(phi, Spectrum) else np.asarray(phi, dtype=float)


def _eigenvalues(a) -> np.ndarray:
    """Eigenvalues (ascending) of symmetric matrices (..., n, n) or of a Spectrum; NaN for a non-finite matrix."""
    if isinstance(a, Spectrum):
        return a.lam
    a = np.asarray(a, dtype=float)
    if np.isfinite(a).all():
        return np.linalg.eigvalsh(symmetrize(a))
    lam = np.full(a.shape[:-1], np.nan)
    finite = np.isfinite(a).all(axis=(-2, -1))
    if finite.any():
        lam[finite] = np.linalg.eigvalsh(symmetrize(a[finite]))
    return lam


_RCOND = 1e-13


def _inv_lam_max(a):
    """``1 / lambda_max(a)``, or ``-inf`` when ``a`` is not numerically positive definite.

    "Numerically" means finite with a condition number below ``1 / _RCOND``: beyond
    that the smallest eigenvalues are rounding noise and the recursion means nothing.
    """
    lam = _eigenvalues(a)
    if lam.ndim == 1:  # one matrix (a NaN fails the comparison: -inf)
        return 1.0 / lam[-1] if lam[0] > _RCOND * lam[-1] else -np.inf
    pd = lam[..., 0] > _RCOND * lam[..., -1]
    return np.divide(1.0, lam[..., -1], out=np.full(pd.shape, -np.inf), where=pd)


def _inv_lam_max_d(a, D: np.ndarray | None):
    """``1 / lambda_max(D a Dᵀ)`` (``D = I`` when None), ``-inf`` when ``a`` is not numerically PD."""
    base = _inv_lam_max(a)
    if D is None:
        return base
    a = _matrix(a)
    batch = a.shape[:-2]
    out = np.array(base, dtype=float)
    pd = np.isfinite(out)
    if np.any(pd):
        Dm = _items(D, batch, pd, 2)
        out[pd] = 1.0 / np.linalg.eigvalsh(symmetrize(Dm @ a[pd] @ _t(Dm)))[:, -1]
    return _one(out, batch)


def condition28_margin(phi_post: np.ndarray, sigma, eps: float, D: np.ndarray | None = None):
    """``1/lambda_max(D Φ Dᵀ) - (1+eps) sigma`` (``D = I``: the paper's (28)); must be > 0.

    With a structure matrix ``D`` (the remainder is ``U Ω D e``), (28) reads
    ``Φ^-1 > (1+eps) sigma DᵀD``, i.e. this margin > 0.  ``-inf`` if Φ is not positive definite.
    """
    return _inv_lam_max_d(phi_post, D) - (1.0 + eps) * sigma


def condition29_margin(phi_pred: np.ndarray, beta, D: np.ndarray | None = None):
    """``1/lambda_max(D Φ_pred Dᵀ) - beta`` (``D = I``: the paper's (29)); must be > 0."""
    return _inv_lam_max_d(phi_pred, D) - beta


def shifted_inverse(phi: np.ndarray, c, D: np.ndarray | None = None) -> np.ndarray:
    """``(Φ^-1 - c DᵀD)^-1`` (``D = I`` when None), positive definite by construction.

    ``D = I``: ``Q diag(λ / (1 - c λ)) Qᵀ`` from the eigendecomposition of Φ.
    General ``D``: ``Φ + Φ Dᵀ (c^-1 I - D Φ Dᵀ)^-1 D Φ`` (Woodbury), from the
    eigendecomposition of ``D Φ Dᵀ``.  Both avoid the two explicit inverses (which
    lose the small eigenvalues when Φ is ill-conditioned).  Requires
    ``c lambda_max(D Φ Dᵀ) < 1`` (conditions (28)/(29)).  ``c = 0`` gives Φ itself.
    """
    if not isinstance(phi, Spectrum):
        phi = np.asarray(phi, dtype=float)
    if not _stacked(c):
        return symmetrize(_matrix(phi)) if c == 0 else _shifted(phi, c, D)
    m = _matrix(phi)
    batch = m.shape[:-2]
    shift = np.broadcast_to(c != 0, batch)  # one c per matrix: c = 0 gives Φ
    out = symmetrize(m)
    if np.any(shift):
        out[shift] = _shifted(phi.take(shift) if isinstance(phi, Spectrum) else phi[shift],
                              _items(c, batch, shift, 0)[:, None], None if D is None else _items(D, batch, shift, 2))
    return out


def _shifted(phi, c, D):
    """:func:`shifted_inverse` for ``c != 0`` (a number, or ``(m, 1)`` for a stack of m matrices)."""
    if D is None:
        lam, Q = phi.eig() if isinstance(phi, Spectrum) else np.linalg.eigh(symmetrize(phi))
        return symmetrize((Q * (lam / (1.0 - c * lam))[..., None, :]) @ _t(Q))
    phi = _matrix(phi)
    mu, Q = np.linalg.eigh(symmetrize(D @ phi @ _t(D)))
    G = phi @ _t(D) @ Q
    return symmetrize(phi + (G * (c / (1.0 - c * mu))[..., None, :]) @ _t(G))


def theorem2_margin(phi_post: np.ndarray, sigma, d_max: int):
    """``((1+d_max)/d_max) sigma - lambda_max(Phi_post^-1)``; must be >= 0 (inf when d_max = 0)."""
    batch = _matrix(phi_post).shape[:-2]
    if d_max == 0:
        return _one(np.full(batch, np.inf), batch)
    lam_min = _eigenvalues(phi_post)[..., 0]
    return _one((1.0 + d_max) / d_max * sigma - 1.0 / lam_min, batch)


def _scaled_outer(m: np.ndarray, scale, name: str, mult: str) -> np.ndarray:
    """``m m^T / scale``, taken as 0 when ``m = 0`` (whatever ``scale``); per matrix for stacks."""
    if not m.any():  # (the EKF's U = 0, V = 0: no product to form)
        return np.zeros(m.shape[:-1] + m.shape[-2:-1])
    mm = m @ _t(m)
    if not mm.any():
        return mm
    if _stacked(scale):
        bad = scale <= 0  # allowed only where m = 0
        if bad.any():
            nonzero = mm.any(axis=(-2, -1))
            if (nonzero & bad).any():
                raise InputError(f"{mult} must be > 0 when {name} is nonzero")
            scale = np.where(nonzero, scale, 1.0)
        return mm / scale[..., None, None]
    if scale <= 0:
        raise InputError(f"{mult} must be > 0 when {name} is nonzero")
    return mm / scale


class PredictionBound(NamedTuple):
    phi_pred: np.ndarray | None
    margin28: float | np.ndarray


def prediction_recursion(phi_post, F, U, Q, sigma, eps: float, D=None) -> np.ndarray:
    """The right-hand side of (26), without checking (28) (see :func:`prediction_bound`).

    ``sigma = 0`` with ``U = 0`` is the extended Kalman filter's ``F Φ Fᵀ + Q`` (the fallback
    of a node that left Theorem 1's recursion).
    """
    inner = shifted_inverse(phi_post, (1.0 + eps) * sigma, D)
    lin = _scaled_outer(np.asarray(U, dtype=float), eps * sigma, "U", "sigma")
    return symmetrize(F @ inner @ _t(F) + lin + Q)


def prediction_bound(phi_post, F, U, Q, sigma, eps: float, D=None) -> PredictionBound:
    """Evaluate (26) if (28) holds; otherwise return ``phi_pred=None`` and the (negative) margin.

    ``D``: structure of the remainder ``U Ω D e`` (``None``: the paper's ``D = I``).  For a
    stack of ``phi_post``, ``phi_pred`` is a stack with NaN matrices where (28) fails.
    """
    margin = condition28_margin(phi_post, sigma, eps, D)
    shape = _matrix(phi_post).shape
    batch = shape[:-2]
    if batch == ():
        if margin <= 0:
            return PredictionBound(None, margin)
        return PredictionBound(prediction_recursion(phi_post, F, U, Q, sigma, eps, D), margin)
    ok = margin > 0
    if ok.all():
        return PredictionBound(prediction_recursion(phi_post, F, U, Q, sigma, eps, D), margin)
    out = np.full(shape, np.nan)
    if np.any(ok):
        sub = phi_post.take(ok) if isinstance(phi_post, Spectrum) else np.asarray(phi_post, dtype=float)[ok]
        out[ok] = prediction_recursion(sub, _items(F, batch, ok, 2), _items(U, batch, ok, 2),
                                       _items(Q, batch, ok, 2), _items(sigma, batch, ok, 0), eps,
                                       None if D is None else _items(D, batch, ok, 2))
    return PredictionBound(out, margin)


def optimal_gain_from(M, H, C, s_i, beta, V, R, d_i) -> np.ndarray:
    """The gain (30) given ``M = (Φ_pred^-1 - β DᵀD)^-1`` (:func:`shifted_inverse`)."""
    n = M.shape[-1]
    S = H @ M @ _t(H) + _scaled_outer(V, beta, "V", "beta") + R / _per_matrix(1.0 + 2 * d_i)
    # K = (I - s C) M H^T S^-1 via a solve with the symmetric positive-definite S.
    return (np.eye(n) - _per_matrix(s_i) * C) @ _t(np.linalg.solve(symmetrize(S), H @ M))


def optimal_gain(phi_pred, H, C, s_i, beta, V, R, d_i, D=None) -> np.ndarray:
    """The gain (30) minimising ``tr Phi_post`` (requires (29))."""
    return optimal_gain_from(shifted_inverse(phi_pred, beta, D), H, C, s_i, beta, V, R, d_i)


def update_bound_from(M, H, K, C, s_i, beta, V, R, d_i, neighbour_terms: np.ndarray) -> np.ndarray:
    """(27) given ``M = (Φ_pred^-1 - β DᵀD)^-1`` (:func:`shifted_inverse`); see :func:`update_bound`."""
    n = M.shape[-1]
    w = _per_matrix(1.0 + 2 * d_i)
    A = np.eye(n) - _per_matrix(s_i) * C - K @ H
    meas = w * _scaled_outer(V, beta, "V", "beta") + R
    out = w * A @ M @ _t(A)
    if np.any(C):  # C = 0 (τ = 0: the EKF) weighs no neighbour
        out = out + C @ neighbour_terms @ _t(C)
    return symmetrize(out + K @ meas @ _t(K))


def update_bound(phi_pred, H, K, C, s_i, beta, V, R, d_i, neighbour_terms: np.ndarray,
                 D=None) -> np.ndarray:
    """Evaluate (27) (requires (29)).

    ``neighbour_terms`` is ``sum_j 3 (1 - phibar_ij) Phi_pred_j + 3 delta^2 gammabar_ij I``,
    the part sandwiched between ``C`` and ``C^T``; ``D`` the structure of ``V Θ D e``.
    """
    return update_bound_from(shifted_inverse(phi_pred, beta, D), H, K, C, s_i, beta, V, R, d_i, neighbour_terms)
