"""Linearisation-error scaling matrices U, V derived from the model's CasADi Hessians.

The consensus paper writes the Taylor remainders as ``U Ω e`` and ``V Θ e`` with
``Ω Ωᵀ <= I``, ``Θ Θᵀ <= I`` and "known" U, V, but gives no values.  Here they are
derived from the model over the region the bound itself describes.

For a twice-differentiable ``g`` (``f`` or ``h_i``) linearised at ``x̂`` with error
``e``, the mean-value form of Taylor's theorem gives, per component ``j``,
``r_j = ½ eᵀ ∇²g_j(ξ_j) e`` with ``ξ_j`` on the segment from ``x̂`` to ``x̂ + e``.
Hence ``||r|| <= ½ ||e||² L``, ``L = max_ξ sqrt(Σ_j ||∇²g_j(ξ)||₂²)``.  On the
ellipsoid ``E = {e : eᵀ Φ^-1 e <= c²}`` (``c`` standard deviations of the bound,
default 3), ``||e|| <= c sqrt(λ_max(Φ))``, so with

    U = u I,   u = ½ L c sqrt(λ_max(Φ))

``r = U Ω e`` holds with ``||Ω|| <= ||r|| / (u ||e||) <= 1`` for every error in E:
the bound then holds by construction for errors inside the ellipsoid (not for the
tails beyond it).  ``L`` is the largest Hessian norm over a fixed set of points of E
(its centre, the ends of its axes and the points on its diagonals): a sampled
supremum, exact when the Hessian norm is largest at those points and an estimate
otherwise (the Monte Carlo bound check is the arbiter).

Every function also takes stacks (centres ``(..., n)``, covariances ``(..., n, n)``, many
runs and nodes at once) and then returns one scale per item.
"""
from __future__ import annotations

import functools
import itertools

import numpy as np

from .bounds import symmetrize

__all__ = ["ellipsoid_points", "hessian_norm_bound", "remainder_scale", "component_scales", "hessian_cover",
           "structured_scale", "selection", "DEFAULT_RADIUS", "whitening", "whitened_scales", "WHITENING_FLOOR",
           "remainder_gram"]

DEFAULT_RADIUS = 3.0


def ellipsoid_points(center: np.ndarray, cov: np.ndarray, radius: float) -> np.ndarray:
    """Centre, axis ends and diagonal points of ``{center + e : eᵀ cov^-1 e <= radius²}``, shape (..., P, n)."""
    center = np.asarray(center, dtype=float)
    n = center.shape[-1]
    lam, vec = np.linalg.eigh(symmetrize(np.asarray(cov, dtype=float)))
    axes = np.swapaxes(vec * (radius * np.sqrt(np.clip(lam, 0.0, None)))[..., None, :], -1, -2)  # rows: semi-axes
    pts = [np.zeros(axes.shape[:-2] + (1, n)), np.stack([axes, -axes], axis=-2).reshape(axes.shape[:-2] + (2 * n, n))]
    if n <= 6:
        signs = np.array(list(itertools.product((-1.0, 1.0), repeat=n)))
        pts.append(signs @ axes / np.sqrt(n))
    return center[..., None, :] + np.concatenate(pts, axis=-2)


def _scalar(x, center: np.ndarray):
    """A plain number for one centre, the array of them for a stack of centres."""
    return float(x) if np.ndim(center) == 1 else x


def _lam_max(cov: np.ndarray) -> np.ndarray:
    return np.maximum(np.linalg.eigvalsh(symmetrize(np.asarray(cov, dtype=float)))[..., -1], 0.0)


def hessian_norm_bound(hessians: np.ndarray):
    """``max_points sqrt(Σ_j ||H_j||₂²)`` for hessians of shape (..., P, components, n, n)."""
    norms = np.linalg.norm(hessians, ord=2, axis=(-2, -1))  # (..., P, components)
    out = np.sqrt((norms**2).sum(axis=-1)).max(axis=-1)
    return float(out) if out.ndim == 0 else out


def remainder_scale(hessian_at, center: np.ndarray, cov: np.ndarray, radius: float = DEFAULT_RADIUS) -> float:
    """The scalar ``u`` of ``U = u I`` for the remainder of a function around ``center``.

    ``hessian_at(points)`` returns the Hessians of every component at points (..., P, n)
    as (..., P, components, n, n) (e.g. ``model.f_hessian``).
    """
    L = hessian_norm_bound(hessian_at(ellipsoid_points(center, cov, radius)))
    return _scalar(0.5 * L * radius * np.sqrt(_lam_max(cov)), center)


def component_scales(hessian_at, center: np.ndarray, cov: np.ndarray, radius: float = DEFAULT_RADIUS) -> np.ndarray:
    """One scale per component ``j`` of a function, for the diagonal scaling ``U = diag(u)``.

    ``|r_j| <= ½ L_j ||e||²`` with ``L_j`` the largest ``||∇²g_j||₂`` over the points of the
    ellipsoid, so on it ``|r_j| <= ½ L_j c sqrt(λ_max) ||e||``.  With ``m`` the number of
    components whose Hessian is not zero, ``u_j = ½ L_j c sqrt(λ_max) sqrt(m)`` gives
    ``||U⁻¹ r|| <= ||e||`` (the zero components have ``r_j = 0``), i.e. ``r = U Ω e`` with
    ``Ω = U⁻¹ r eᵀ / ||e||²`` and ``||Ω|| <= 1``.  Each ``u_j`` is in the unit of its own
    component (per metre of error, per radian, ...), which a single ``u I`` cannot be.

    ``hessian_at(points)`` returns the Hessians at the points (P, n): an array (P, components, n, n) (e.g.
    ``model.f_hessian``), or one block (P, s_j, s_j) per component, its Hessian on its structural support (e.g.
    ``model.hessian_blocks()``: the same norms, empty for a component linear in the state).
    """
    center, cov = np.asarray(center, dtype=float), np.asarray(cov, dtype=float)
    points, lam_max = _ellipsoid(center.tobytes(), center.shape, cov.tobytes(), cov.shape, float(radius))
    Hs = hessian_at(points)
    blocks = [Hs[:, j] for j in range(Hs.shape[1])] if isinstance(Hs, np.ndarray) else Hs
    L = np.array([np.linalg.norm(b, ord=2, axis=(-2, -1)).max() if b.shape[-1] else 0.0 for b in blocks])
    m = int(np.count_nonzero(L > 0))
    return 0.5 * L * radius * np.sqrt(lam_max) * np.sqrt(max(m, 1))


@functools.lru_cache(maxsize=4)
def _ellipsoid(center: bytes, center_shape: tuple, cov: bytes, cov_shape: tuple, radius: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`component_scales`'s points and largest eigenvalue, once per prior (a design asks once per sensor: at a
    hundred states, an eigendecomposition each)."""
    c = np.frombuffer(center, dtype=float).reshape(center_shape)
    P = np.frombuffer(cov, dtype=float).reshape(cov_shape)
    points = ellipsoid_points(c, P, radius)
    points.flags.writeable = False
    return points, _lam_max(P)


# ------------------------------------------------------------------ structured variant
def hessian_cover(fun) -> tuple[int, ...]:
    """A smallest set S of variables touching every structural nonzero of the Hessians of ``fun``.

    ``fun`` is a CasADi function whose outputs are the Hessians (n x n) of the
    components (e.g. ``model.casadi_f_hess``).  Every nonzero (a, b) needs a or b in S
    (a diagonal entry needs a); then ``eᵀ ∇²g_j e = e_Sᵀ M_j e`` with
    ``M_j = [∇²g_j[S, S], 2 ∇²g_j[S, N]]`` (N the other variables): the remainder
    depends on the error only through ``e_S`` times ``e``.
    """
    n = fun.sparsity_out(0).size1()
    pairs = set()
    for j in range(fun.n_out()):
        rows, cols = fun.sparsity_out(j).get_triplet()
        pairs.update((min(a, b), max(a, b)) for a, b in zip(rows, cols))
    if not pairs:
        return ()
    for size in range(1, n + 1):
        for S in itertools.combinations(range(n), size):
            s = set(S)
            if all(a in s or b in s for a, b in pairs):
                return S
    return tuple(range(n))


def structured_scale(hessian_at, center: np.ndarray, cov: np.ndarray, cover: tuple[int, ...],
                     radius: float = DEFAULT_RADIUS) -> float:
    """The scalar ``u`` of the structured remainder ``r = (u I) Ω D e``, ``D`` selecting ``cover``.

    ``|r_j| = ½ |e_Sᵀ M_j e| <= ½ ||e_S|| ||M_j|| ||e||``, so ``||r|| <= ½ L_M ||e_S|| ||e||``
    with ``L_M = max sqrt(Σ_j ||M_j||²)``; with ``||e|| <= c sqrt(λ_max(Φ))`` on the
    ellipsoid, ``Ω = r e_Sᵀ / (u ||e_S||²)`` has norm ``||r|| / (u ||e_S||) <= 1``.
    """
    if not cover:
        return _scalar(np.zeros(np.shape(center)[:-1]), center)
    S = list(cover)
    N = [k for k in range(np.shape(center)[-1]) if k not in cover]
    Hs = hessian_at(ellipsoid_points(center, cov, radius))  # (..., P, comps, n, n)
    M = np.concatenate([Hs[..., S, :][..., :, S], 2.0 * Hs[..., S, :][..., :, N]], axis=-1)
    L = hessian_norm_bound(M)
    return _scalar(0.5 * L * radius * np.sqrt(_lam_max(cov)), center)


def whitening(cov: np.ndarray) -> np.ndarray:
    """``W = cov^{-1/2}`` (symmetric): ``|W e| <= c`` on the ellipsoid ``eᵀ cov⁻¹ e <= c²``.  Eigenvalues below
    :data:`WHITENING_FLOOR` of the largest are raised to it (a direction the ellipsoid all but lacks: its errors'
    component there is as small)."""
    return _root(cov, -0.5)


#: The smallest eigenvalue, relative to the largest, that :func:`whitening` and :func:`whitened_scales` keep.
WHITENING_FLOOR = 1e-12


def _root(cov, power: float) -> np.ndarray:
    lam, vec = np.linalg.eigh(symmetrize(np.asarray(cov, dtype=float)))
    top = max(float(lam[-1]), 1e-300)
    lam = np.maximum(lam, WHITENING_FLOOR * top)
    return symmetrize((vec * lam**power) @ vec.T)


def whitened_scales(hessian_at, center: np.ndarray, cov: np.ndarray, radius: float = DEFAULT_RADIUS) -> np.ndarray:
    """One scale per component for the remainder written ``r = diag(u) Ω W e`` with ``W = cov^{-1/2}``
    (:func:`whitening`): the error measured in the ellipsoid's own units instead of its longest axis.

    With ``e = cov^{1/2} z``, ``|r_j| = ½ |zᵀ cov^{1/2} ∇²g_j cov^{1/2} z| <= ½ L̃_j |z|²`` and ``|z| <= c`` on the
    ellipsoid, so ``u_j = ½ L̃_j c sqrt(m)`` (``L̃_j`` the largest ``||cov^{1/2} ∇²g_j cov^{1/2}||₂`` over the points of
    :func:`ellipsoid_points`, ``m`` the components whose Hessian is not zero) gives ``||diag(u)⁻¹ r|| <= |W e|``.
    A function that is nonlinear only in components of small variance (a turn rate times a velocity) gets a
    scale that small, where :func:`component_scales` multiplies its Hessian by the longest axis (a position's).
    The same ``L̃`` bounds the Jacobian's change, ``|∇r_j(a) - ∇r_j(b)|``: ``|r_j(a) - r_j(b)| <= 2 u_j / sqrt(m)
    |W (a - b)|`` on the ellipsoid (:mod:`designer.joint`, **Shared remainders**)."""
    cov = symmetrize(np.asarray(cov, dtype=float))
    root = _root(cov, 0.5)  # the inverse of whitening(cov)
    Hs = hessian_at(ellipsoid_points(center, cov, radius))  # (P, comps, n, n)
    L = np.linalg.norm(root @ Hs @ root, ord=2, axis=(-2, -1)).max(axis=0)  # (comps,)
    m = int(np.count_nonzero(L > 0))
    return 0.5 * L * radius * np.sqrt(max(m, 1))


def remainder_gram(hessians_at, center: np.ndarray, cov: np.ndarray, radius: float = DEFAULT_RADIUS) -> np.ndarray:
    """A matrix ``Γ`` (c, c) over the ``c`` components of several functions linearised at one point with one error (the
    sensors' measurements at a common error), such that their stacked remainder ``ψ`` satisfies
    ``(yᵀ ψ)² <= |W e|² yᵀ Γ y`` for every ``y`` and every error in the ellipsoid (``W = cov^{-1/2}``):
    ``ψ = Γ^{1/2} Ω W e`` with one ``||Ω|| <= 1`` for all of them, where one scale per component (:func:`whitened_scales`) lets each
    component's remainder take its largest value independently, so that ``c`` of them add up ``c``-fold.

    ``hessians_at(points)`` gives the Hessians (..., P, c, n, n) of every component.  With ``z = W e``, ``|z| <= r``
    (the radius), the whitened Hessians ``H̃_j = cov^{1/2} ∇²ψ_j cov^{1/2}`` at the centre ``H̃⁰_j`` and their largest
    change ``δ_j`` over the points of :func:`ellipsoid_points`: ``yᵀ ψ = ½ zᵀ (Σ_j y_j H̃_j(ξ_j)) z``, whose first part
    is at most ``½ r |z| ||Σ_j y_j H̃⁰_j||_F`` (``||·||_F² = yᵀ G y``, ``G`` the Frobenius Gram matrix of the ``H̃⁰_j``:
    Hessians of opposite signs cancel there) and whose second at most ``½ r |z| sqrt(m Σ_j y_j² δ_j²)``
    (``m`` the components that change); with ``(a + b)² <= (1 + 1/τ) a² + (1 + τ) b²``,
    ``Γ = ¼ r² [(1 + 1/τ) G + (1 + τ) m diag(δ²)]``, ``τ = sqrt(tr(m diag(δ²)) / tr G)``.  A sampled supremum, as for
    :func:`component_scales`."""
    cov = symmetrize(np.asarray(cov, dtype=float))
    root = _root(cov, 0.5)
    center = np.asarray(center, dtype=float)
    H0 = root @ np.asarray(hessians_at(center[None, :]), dtype=float)[0] @ root  # (c, n, n)
    Hs = root @ np.asarray(hessians_at(ellipsoid_points(center, cov, radius)), dtype=float) @ root  # (P, c, n, n)
    delta = np.linalg.norm(Hs - H0[None], ord=2, axis=(-2, -1)).max(axis=0)  # (c,)
    G = np.einsum("iab,jab->ij", H0, H0)
    B = np.count_nonzero(delta > 0) * np.diag(delta**2)
    ta, tb = float(np.trace(G)), float(np.trace(B))
    if ta > 0 and tb > 0:
        tau = np.sqrt(tb / ta)
        out = (1 + 1 / tau) * G + (1 + tau) * B
    else:
        out = G + B
    return 0.25 * radius**2 * symmetrize(out)


def selection(cover: tuple[int, ...], n: int) -> np.ndarray:
    """The matrix D (|S| x n) selecting the variables of ``cover``."""
    return np.eye(n)[list(cover)]


# ------------------------------------------------------------------ per node and step
def _f_hessians(model, k, u):
    if u is not None and np.ndim(u) > 1:  # one input per centre: broadcast over the points of each ellipsoid
        u = np.asarray(u)[..., None, :]
    if model.n_modes == 0:
        return lambda pts: model.f_hessian(pts, k, u)
    return lambda pts: np.concatenate([model.f_hessian(pts, k, u, m) for m in range(model.n_modes)], axis=-3)


def _times_identity(scale, n: int) -> np.ndarray:
    """``scale I`` (n x n), or a stack of them for an array of scales."""
    return np.asarray(scale, dtype=float)[..., None, None] * np.eye(n)


def prediction_scaling(model, x_post, phi_post, k, u, rule: str, radius: float, U: np.ndarray):
    """``(U, D)`` of the remainder of ``f`` at ``x_post`` for the linearisation ``rule``.

    ``'fixed'``: the given ``U`` and ``D = None`` (the paper's ``D = I``); ``'hessian'``:
    ``u I`` over the ``radius``-sigma ellipsoid of ``phi_post``; ``'structured'``: the same
    with ``D`` selecting the variables ``f`` is nonlinear in (``U = 0``, ``D = None`` when
    ``f`` is linear).  Stacks of ``x_post``, ``phi_post`` (and ``u``, one per centre) give stacks of ``U``.
    """
    if rule == "fixed":
        return U, None
    hess = _f_hessians(model, k, u)
    if rule == "structured":
        cover = hessian_cover(model.casadi_f_hess)
        if not cover:  # f is linear: no remainder, no multiplier
            return np.zeros_like(U), None
        return (_times_identity(structured_scale(hess, x_post, phi_post, cover, radius), model.n_x),
                selection(cover, model.n_x))
    return _times_identity(remainder_scale(hess, x_post, phi_post, radius), model.n_x), None


def update_scaling(model, i: int, x_pred, phi_pred, k1, rule: str, radius: float, V: np.ndarray):
    """``(V_i, D)`` of the remainder of ``h_i`` at ``x_pred`` (see :func:`prediction_scaling`)."""
    if rule == "fixed":
        return V, None
    hess = lambda pts: model.h_hessian(i, pts, k1)  # noqa: E731
    if rule == "structured":
        cover = hessian_cover(model.casadi_h_hess[i])
        D = selection(cover, model.n_x) if cover else None
        return _times_identity(structured_scale(hess, x_pred, phi_pred, cover, radius), V.shape[-1]), D
    return _times_identity(remainder_scale(hess, x_pred, phi_pred, radius), V.shape[-1]), None
