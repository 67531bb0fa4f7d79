"""Resampling schemes as pure functions ``(W, M, rng) -> indices``: the one registry of both engines.

``W`` holds normalised weights of shape ``(..., N)`` (leading dimensions are
independent Monte Carlo runs, resampled in one call); the result has shape
``(..., M)`` with indices into the last axis.  Randomness only from the
``numpy.random.Generator`` passed in.

:data:`RESAMPLERS` names the schemes and defines them (these functions); the fused
kernels take a scheme by its code (:func:`scheme_code`, its index in :data:`SCHEMES`)
and :mod:`filters.fused.resampling` compiles the same schemes with the same draws from
the Generator (one run at a time), which its tests check against these functions.
A scheme is added here first.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from designer.validation import InputError, check_int, check_rng

__all__ = ["multinomial", "stratified", "systematic", "residual", "RESAMPLERS", "SCHEMES", "get_resampler",
           "scheme_code"]


def _check(W, M: int, rng) -> np.ndarray:
    W = np.asarray(W, dtype=float)
    if W.ndim < 1 or W.shape[-1] < 1:
        raise InputError(f"W must have shape (..., N) with N >= 1, got {W.shape}")
    check_int("M", M, 1)
    check_rng(rng)
    if np.any(W < 0) or not np.all(np.isfinite(W)) or np.any(np.abs(W.sum(-1) - 1.0) > 1e-8):
        raise InputError("W must be finite, non-negative and sum to 1 along its last axis")
    return W


def _inverse_cdf(W: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Indices ``i`` with ``cumsum(W)[i-1] <= u < cumsum(W)[i]`` for sorted ``u`` in [0, 1), batched.

    Shifting run ``r``'s cumulative weights and uniforms by ``r`` makes one flat
    ``searchsorted`` serve every run at once.
    """
    lead = W.shape[:-1]
    N, M = W.shape[-1], u.shape[-1]
    runs = int(np.prod(lead, dtype=int))
    cdf = np.cumsum(W.reshape(runs, N), axis=1)
    cdf[:, -1] = 1.0  # guard the last bin against rounding
    offset = np.arange(runs, dtype=float)[:, None]
    flat = np.searchsorted((cdf + offset).ravel(), (u.reshape(runs, M) + offset).ravel(), side="right")
    idx = flat.reshape(runs, M) - np.arange(runs)[:, None] * N
    return np.minimum(idx, N - 1).reshape(lead + (M,))


def multinomial(W, M: int, rng: np.random.Generator) -> np.ndarray:
    """Independent draws from the weights (sorted uniforms, so the output is ordered)."""
    W = _check(W, M, rng)
    u = np.sort(rng.random(W.shape[:-1] + (M,)), axis=-1)
    return _inverse_cdf(W, u)


def stratified(W, M: int, rng: np.random.Generator) -> np.ndarray:
    """One uniform in each stratum ``[m/M, (m+1)/M)``."""
    W = _check(W, M, rng)
    u = (np.arange(M) + rng.random(W.shape[:-1] + (M,))) / M
    return _inverse_cdf(W, u)


def systematic(W, M: int, rng: np.random.Generator) -> np.ndarray:
    """One uniform shared by all strata: ``(m + U) / M``."""
    W = _check(W, M, rng)
    u = (np.arange(M) + rng.random(W.shape[:-1] + (1,))) / M
    return _inverse_cdf(W, u)


def residual(W, M: int, rng: np.random.Generator) -> np.ndarray:
    """``floor(M W_i)`` deterministic copies, the rest multinomially from the residual weights."""
    W = _check(W, M, rng)
    lead, N = W.shape[:-1], W.shape[-1]
    flatW = W.reshape(-1, N)
    out = np.empty((flatW.shape[0], M), dtype=int)
    for r, w in enumerate(flatW):
        counts = np.floor(M * w).astype(int)
        rest = M - counts.sum()
        if rest > 0:
            res = M * w - counts
            res /= res.sum()
            counts += np.bincount(multinomial(res, int(rest), rng), minlength=N)
        out[r] = np.repeat(np.arange(N), counts)
    return out.reshape(lead + (M,))


RESAMPLERS: dict[str, Callable] = {
    "multinomial": multinomial,
    "stratified": stratified,
    "systematic": systematic,
    "residual": residual,
}


#: The schemes' names in the order of their codes (:func:`scheme_code`).
SCHEMES: tuple[str, ...] = tuple(RESAMPLERS)


def scheme_code(name: str) -> int:
    """The code of scheme ``name`` (its index in :data:`SCHEMES`); an :class:`InputError` for an unknown name."""
    if not isinstance(name, str) or name not in RESAMPLERS:
        raise InputError(f"resampling scheme must be one of {', '.join(RESAMPLERS)}, got {name!r}")
    return SCHEMES.index(name)


def get_resampler(name: str) -> Callable:
    """The NumPy function of scheme ``name`` (see :data:`RESAMPLERS`)."""
    return RESAMPLERS[SCHEMES[scheme_code(name)]]
