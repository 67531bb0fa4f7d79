"""The resampling schemes of :mod:`filters.resampling`, compiled for one run of the fused kernels.

The registry (names, codes, the schemes' definitions) is :mod:`filters.resampling`'s:
:data:`SCHEME_FUNCTIONS` maps a scheme's code (:func:`filters.resampling.scheme_code`) to
its compiled function, which draws the same uniforms from the run's Generator (its stream,
:mod:`filters.fused.streams`) in the same order as the NumPy function of that scheme, so both
engines resample alike (the tests compare them).
Systematic resampling, the default, is branch-free (:func:`systematic`).
"""
from __future__ import annotations

import math

import numpy as np

from filters.resampling import scheme_code

from .cache import njit
from .streams import draw_uniform, draw_uniforms

__all__ = ["SYSTEMATIC", "STRATIFIED", "MULTINOMIAL", "RESIDUAL", "SCHEME_FUNCTIONS", "systematic", "inverse_cdf",
           "cumsum_to_one", "heap_sort"]

SYSTEMATIC, STRATIFIED, MULTINOMIAL, RESIDUAL = (scheme_code(n) for n in ("systematic", "stratified", "multinomial",
                                                                         "residual"))


@njit()
def inverse_cdf(cdf, u, idx):
    """``idx[m] = min(searchsorted(cdf, u[m], 'right'), N - 1)`` for sorted ``u``."""
    N = cdf.shape[0]
    i = 0
    for m in range(u.shape[0]):
        while i < N and cdf[i] <= u[m]:
            i += 1
        idx[m] = i if i < N else N - 1


@njit()
def cumsum_to_one(W, scale, cdf):
    """Cumulative sums of ``W * scale`` (the normalised weights), the last forced to 1."""
    acc = 0.0
    for i in range(W.shape[0]):
        acc += W[i] * scale
        cdf[i] = acc
    cdf[W.shape[0] - 1] = 1.0  # guard the last bin against rounding


@njit()
def systematic(W, scale, u0, idx, cdf, ends):
    """Systematic resampling, ``u_m = (m + u0) / M``: the indices of ``cumsum_to_one`` + ``inverse_cdf``.

    Without a data-dependent branch (a merge of the cdf with the ``u_m`` mispredicts
    about once per particle: 10 ns per particle against 3): with ``c`` the cdf,
    ``J_i = #{m : u_m < c_i}`` (where particle ``i``'s copies end) is ``ceil(t)``,
    ``t = M c_i − u0``, clipped to ``[0, M]``, in a loop that vectorises.  Rounding
    moves ``t`` by about ``4 ε M`` at most (ε = 2^-53), so where ``t`` lies farther than
    ``δ = (M + 1) 2^-40`` from an integer, ``ceil(t)`` is exact; a step where some ``t``
    does not (about ``2 δ N`` of them: never at hundreds of particles) decides every
    ``J_i`` exactly instead, by comparing with ``u_m`` itself on both sides (rounding
    moves it by one at most).  ``J`` is non-decreasing as ``c`` is (the last bin, forced
    to 1, excepted: a running maximum there).  Then ``ends[J_{i-1}] = i`` (the last write
    to a position is the particle that has copies there) and ``idx[m]`` is the running
    maximum of ``ends`` (in floating point: an integer maximum becomes a branch), four
    positions per step of the chain of maxima (the maximum is exact in any order).
    ``cdf`` (N) and ``ends`` (M + 1) are scratch.
    """
    M = idx.shape[0]
    N = W.shape[0]
    Mf = float(M)
    delta = (Mf + 1.0) * 9.094947017729282e-13  # 2^-40
    cumsum_to_one(W, scale, cdf)
    near = False
    for i in range(N):
        t = cdf[i] * Mf - u0
        d = np.ceil(t) - t  # in [0, 1)
        near |= (d < delta) | (d > 1.0 - delta)
    if near:
        for i in range(N):
            c = cdf[i]
            g = min(max(np.ceil(c * Mf - u0), 0.0), Mf)
            down = (g > 0.0) & ((g - 1.0 + u0) / Mf >= c)  # u_(g-1) >= c: one fewer
            up = (g < Mf) & ((g + u0) / Mf < c)  # u_g < c: one more
            cdf[i] = g - 1.0 if down else (g + 1.0 if up else g)  # J_i
    else:
        for i in range(N):
            cdf[i] = min(max(np.ceil(cdf[i] * Mf - u0), 0.0), Mf)
    if N > 1:
        cdf[N - 1] = max(cdf[N - 1], cdf[N - 2])
    for m in range(M + 1):
        ends[m] = 0.0
    for i in range(1, N):
        ends[int(cdf[i - 1])] = float(i)
    run = 0.0
    m = 0
    while m + 4 <= M:  # the prefix maxima of four positions beside the chain, then one maximum on it
        e0, e1, e2, e3 = ends[m], ends[m + 1], ends[m + 2], ends[m + 3]
        p1 = max(e0, e1)
        p2 = max(p1, e2)
        idx[m] = int(max(run, e0))
        idx[m + 1] = int(max(run, p1))
        idx[m + 2] = int(max(run, p2))
        run = max(run, max(p2, e3))
        idx[m + 3] = int(run)
        m += 4
    while m < M:
        run = max(run, ends[m])
        idx[m] = int(run)
        m += 1


@njit(inline="always")
def _sift_down(a, root, end):
    while 2 * root + 1 < end:
        child = 2 * root + 1
        if child + 1 < end and a[child] < a[child + 1]:
            child += 1
        if not a[root] < a[child]:
            return
        a[root], a[child] = a[child], a[root]
        root = child


@njit()
def heap_sort(a):
    """Sort ``a`` (no NaN) in place, ascending: a heapsort, the same result as ``np.sort`` (which takes numba a
    second longer to compile)."""
    n = a.shape[0]
    for root in range(n // 2 - 1, -1, -1):
        _sift_down(a, root, n)
    for end in range(n - 1, 0, -1):
        a[0], a[end] = a[end], a[0]
        _sift_down(a, 0, end)


@njit()
def systematic_scheme(W, scale, rng, idx, cdf, u):
    """Systematic: one uniform shared by all strata, ``u_m = (m + U) / M`` (:func:`systematic`)."""
    systematic(W, scale, draw_uniform(rng), idx, cdf, u)


@njit()
def stratified_scheme(W, scale, rng, idx, cdf, u):
    """Stratified: one uniform per stratum, ``u_m = (m + U_m) / M``."""
    M = idx.shape[0]
    cumsum_to_one(W, scale, cdf)
    draw_uniforms(rng, u, 0, M)
    for m in range(M):
        u[m] = (m + u[m]) / M
    inverse_cdf(cdf, u[:M], idx)


@njit()
def multinomial_scheme(W, scale, rng, idx, cdf, u):
    """Multinomial: ``M`` independent uniforms, sorted."""
    M = idx.shape[0]
    cumsum_to_one(W, scale, cdf)
    draw_uniforms(rng, u, 0, M)
    heap_sort(u[:M])
    inverse_cdf(cdf, u[:M], idx)


@njit()
def residual_scheme(W, scale, rng, idx, cdf, u):
    """Residual: ``floor(M W)`` copies, the rest multinomially from the residual weights."""
    M = idx.shape[0]
    Mf = float(M)
    N = W.shape[0]
    res = np.empty(N)
    counts = np.empty(N, np.int64)
    tot = 0
    for i in range(N):
        mw = Mf * (W[i] * scale)
        c = math.floor(mw)
        counts[i] = c
        tot += c
        res[i] = mw - c
    rest = M - tot
    if rest > 0:
        sres = 0.0
        for i in range(N):
            sres += res[i]
        cumsum_to_one(res, 1.0 / sres, cdf)
        ur = np.empty(rest)
        draw_uniforms(rng, ur, 0, rest)
        heap_sort(ur)
        extra = np.empty(rest, np.int64)
        inverse_cdf(cdf, ur, extra)
        for e in range(rest):
            counts[extra[e]] += 1
    m = 0
    for i in range(N):
        for _ in range(counts[i]):
            idx[m] = i
            m += 1


#: The compiled scheme of each code of :func:`filters.resampling.scheme_code`, all of one signature
#: ``(W, scale, rng, idx, cdf, u)``: indices ``idx`` (M) from the weights ``W * scale`` (normalised), drawing from
#: ``rng`` as the NumPy function of the scheme does; ``cdf`` (N) and ``u`` (M + 1) are scratch.  The driver takes
#: one as a first-class function, so only the schemes in use are compiled.
SCHEME_FUNCTIONS = {SYSTEMATIC: systematic_scheme, STRATIFIED: stratified_scheme, MULTINOMIAL: multinomial_scheme,
                    RESIDUAL: residual_scheme}
