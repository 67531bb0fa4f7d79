"""Fused, JIT-compiled bootstrap particle filters over many Monte Carlo runs.

The NumPy engine (:func:`filters.particle.run_sir`) runs every Monte Carlo run at
once as arrays of shape ``(runs, M, n_x)``, one NumPy call per operation.  This
module runs the same bootstrap filter with one compiled kernel call per run.
For each model it generates, from the model's CasADi functions
(:func:`designer.jit.scalar_statements`, the instruction walk of
:mod:`designer.codegen`), three small functions compiled with
``numba.njit(nogil=True)``, each a loop over a **block** of particles: the
propagation (``f`` plus the process noise ``G (mean + L z)``, ``G L`` inlined as
constants), the likelihood (``h_s``, residual, angle wrapping and the noise
density with its constants inlined; sensors that differ only in constants share
one loop) and the weights with the weighted mean.  A generic kernel, compiled
once per likelihood family and process, runs them over the steps: propagate
(resampling is an ancestor index read by the propagation, no copy), weigh,
record the weighted mean (and covariance if asked), the ESS and the log
marginal likelihood, resample (systematic: one merged pass over the cumulative
weights).  The generated functions reach it as numba first-class functions, so
a new model or likelihood variant compiles only its own small functions
(a few seconds at its first call; the generic kernel once per process).

Where the time goes, and why it is laid out so: there is no vector libm here,
so libm's ``exp`` and ``atan2`` are a call per particle, and every call spills
all floating-point registers.  The kernels therefore never take a ``log`` per
particle (a step's log-likelihood is kept as ``b + log s``: the logs summed in
``b``, each log-sum-exp's remainder as a linear factor ``s``), take their exps
and the model's ``atan2`` with branch-free polynomial versions
(:func:`_exp_nonpos`, :func:`designer.jit.fma`-based ``_atan2``; within 1.2 and
2.5 ulp of the exact values), and split each block into loops that LLVM vectorises
(the likelihood when ``h`` has no branch or call, the exps) and loops that must
stay scalar (the generator's draws, the sums of the weights).  Measured on
target-range-bearing (Round-Robin, 500 particles, one thread): about 40 ns per
particle-step, of which the four normal draws are about 15; it was 80 with a
per-particle log-sum-exp through libm.  Nothing is allocated per particle and
the GIL is released, so runs are spread over ``threads`` threads (each takes the
next run until none is left).

Randomness: **one** :class:`numpy.random.Generator` **per run**, drawn from in
a fixed order (per step: ``n_w`` standard normals per particle, particle after
particle; then the resampler's uniforms).  A model with switching modes or
Gaussian-mixture process noise (the family of :mod:`filters.fastedpf`) draws per
step the modes' uniforms, then the components' uniforms, then the normals
(:func:`_prop_predrawn`), as :func:`filters.particle.transition_proposal` does.
A run's result depends only on its own generator and data, never on how runs are
split between threads.  numba's ``Generator.standard_normal`` and
``Generator.random`` reproduce NumPy's streams bit for bit and that order is the
NumPy engine's, so a one-run call reproduces ``run_sir(..., runs=1)`` with the
same generator to rounding (given the same initial particles; the tests check it).

Initial particles are sampled by the caller (``x0``, shape ``(runs, M, n_x)``,
e.g. ``model.prior.sample(rngs[r], M)`` for each run), so any prior works.

Two likelihood families here (a third, seed 001's interval and truncated-density
likelihoods on decrypted values, in :mod:`filters.fastedpf`):

* :func:`sir_packets` — at step ``k`` a set of ``P`` packets, packet ``p`` from
  sensor ``sensors[k, p]`` with received value ``y[r, k, p]``::

      log p(y_k | x) = Σ_p logaddexp(log_clean + log p_ν(wrap(y − h_s(x))), attack[r, k, p])

  with ``p_ν`` the sensor's Gaussian or Gaussian-mixture noise.  ``log_clean = 0``
  and ``attack = −inf`` give the standard likelihood; ``log_clean = log(1 − η̄)``
  and ``attack = log η̄ + log p_ξ(y)`` (:func:`deception_terms`) the attack-aware
  one of seed 000 (14).  ``P = 1`` with the Round-Robin schedule gives the RRP
  filters, ``P = N`` with every sensor PF-DA (:mod:`filters.rrp`).
* :func:`sir_binary` — ``S`` scalar sensors, ``Σ_s log(A + B F_ν(T − h_s(x)))``
  with ``F_ν`` the sensor noise's CDF; seed 002's likelihood (13)-(16) is affine
  in ``c = F_ν(T − h)`` and :func:`binary_coefficients` gives ``A`` and ``B``.

Numerics: log weights (as ``b + log s``) only.  A particle whose log-likelihood is not finite (NaN
from an undefined measurement function, ±inf) gets zero weight.  When *every*
particle's weight vanishes at a step (a **collapse**), the filter keeps the
predicted particles with uniform weights, does not resample at that step,
records the event in ``collapsed`` and — since the estimate of ``p(z_k | z_1:k-1)``
is then zero — sets the run's log marginal likelihood to ``-inf``.  A weight
below ``exp(-708)`` times the step's largest one counts as zero (it changes no
sum; libm would give a subnormal).

Limitations of :func:`sir_packets` and :func:`sir_binary`: models without known
inputs and without switching modes (:func:`designer.jit.jit_model`); Gaussian
process noise (any ``noise_gain``); Gaussian or Gaussian-mixture measurement noise.
"""
from __future__ import annotations

import itertools
import math
import re
import weakref
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple, Sequence

import numba
import numpy as np
from numba.core import types

from designer.jit import compile_source, fma, jit_model, scalar_statements
from designer.model import Model
from designer.noise import Gaussian, GaussianMixture, Noise
from designer.validation import InputError, check_int, check_probability

from .particle import check_finite_means
from .rrp import angle_sets

__all__ = [
    "FastSIRResult", "RESAMPLER_CODES", "sir_packets", "sir_binary", "deception_terms", "binary_coefficients",
    "packets_loglik", "binary_affine_loglik",
]

_NJIT = dict(nogil=True, cache=False, error_model="numpy")
# Generated kernels may fuse a * b + c into one FMA (rounding only; no effect on inf/NaN handling).
_FAST = {"contract"}
#: Particles per block of a filter step: the likelihood's scratch stays in the L1 cache.
_BLOCK = 128
_LOG_2PI = float(np.log(2.0 * np.pi))

#: Resampling schemes of :mod:`filters.resampling`, by name, as the kernels' codes.
RESAMPLER_CODES = {"systematic": 0, "stratified": 1, "multinomial": 2, "residual": 3}


class FastSIRResult(NamedTuple):
    """Per-run outputs of the fused filters (``R`` runs, ``K`` steps)."""

    mean: np.ndarray  # (R, K + 1, n_x) weighted means (k = 0: the initial particles)
    cov: np.ndarray | None  # (R, K + 1, n_x, n_x) when covariance=True
    ess: np.ndarray  # (R, K) effective sample size after weighting
    loglik: np.ndarray  # (R,) log marginal likelihood estimate log p(z_1:K); -inf after a collapse
    resampled: np.ndarray  # (R, K) bool
    collapsed: np.ndarray  # (R, K) bool: every particle's weight vanished at that step


# ============================================================================ compiled pieces
@numba.njit(**_NJIT)
def _ndtr(a):
    # Standard normal CDF as scipy.special.ndtr computes it (erfc in the tails).
    x = a * 0.7071067811865476
    z = abs(x)
    if z < 0.7071067811865476:
        return 0.5 + 0.5 * math.erf(x)
    y = 0.5 * math.erfc(z)
    if x > 0.0:
        y = 1.0 - y
    return y


@numba.njit(**dict(_NJIT, inline="always", fastmath=_FAST))
def _exp_nonpos(d):
    """``exp(d)`` for ``d <= 0`` (a difference to a maximum), without branches or calls.

    So that a loop of it vectorises (libm's ``exp`` is a call per element; there
    is no vector libm here): ``exp(d) = 2^k exp(r)``, ``k = round(d / ln 2)``,
    ``r = d - k ln 2`` in two parts (Cody-Waite, ``k ln2_hi`` exact), ``exp(r)`` by
    its Taylor polynomial of degree 13 (``|r| <= ln 2 / 2``: truncation below
    1e-17), ``2^k`` built in the exponent bits.  Within 1.2 ulp of the exact value
    (1.14 measured over millions of arguments; libm's: under 1).
    Below ``-708`` (results under 1e-307, below the normal range) it gives 0, where
    libm gives subnormals: a weight that small against the largest one (at least 1)
    changes no sum.  NaN gives NaN; ``d > 0`` is not supported (it gives 1).
    """
    x = d if d > -708.0 else -708.0  # also NaN and -inf: a finite k below
    x = x if x < 0.0 else 0.0
    kf = math.floor(x * 1.4426950408889634 + 0.5)
    r = (x - kf * 0.6931471803691238) - kf * 1.9082149292705877e-10  # ln 2 = 0x1.62e42feep-1 + 0x1.a39ef35793c76p-33
    p = 1.6059043836821613e-10  # 1 / 13!
    p = p * r + 2.08767569878681e-09
    p = p * r + 2.505210838544172e-08
    p = p * r + 2.755731922398589e-07
    p = p * r + 2.7557319223985893e-06
    p = p * r + 2.48015873015873e-05
    p = p * r + 0.0001984126984126984
    p = p * r + 0.001388888888888889
    p = p * r + 0.008333333333333333
    p = p * r + 0.041666666666666664
    p = p * r + 0.16666666666666666
    p = p * r + 0.5
    p = p * r + 1.0
    p = p * r + 1.0
    e = p * np.int64((np.int64(kf) + 1023) << 52).view(np.float64)  # p 2^k
    return e if d >= -708.0 else (0.0 if d < -708.0 else d)  # d < -708: 0; NaN: NaN


@numba.njit(**dict(_NJIT, inline="always"))
def _neginf_unless_finite(v):
    return v if (v > -math.inf and v < math.inf) else -math.inf


@numba.njit(**dict(_NJIT, inline="always"))
def _wrap_angle(r):
    """``r`` if in (−π, π], else ``π − mod(π − r, 2π)`` as :func:`filters.rrp.wrap_angles` (``numpy.mod``).

    Without branches or calls: ``mod`` is ``x − q 2π`` with ``q = floor(x / 2π)``
    (one less if that rounded up) and one FMA, i.e. the exact remainder rounded
    once, as ``numpy.mod``'s (``fmod`` and ``+ 2π``).  NaN and ±inf give NaN.
    """
    x = 3.141592653589793 - r
    q = np.floor(x / 6.283185307179586)
    q = q - 1.0 if fma(-q, 6.283185307179586, x) < 0.0 else q
    w = 3.141592653589793 - fma(-q, 6.283185307179586, x)
    return r if (r > -3.141592653589793 and r <= 3.141592653589793) else w


@numba.njit(**_NJIT)
def _likelihood_block(lik, P, ne, X, m0, n, k1, data, t, b, s, ex):
    """The log-likelihood of step ``t``'s data for particles ``m0 .. m0 + n − 1`` of ``X`` as ``b + log s``.

    ``lik(X, m0, n, k1, data, t, b, ex)`` (generated per model) adds each particle's
    sum of logs to ``b[m]`` and writes the ``ne`` log-sum-exp remainders ``<= 0`` of
    each of the ``P`` packets into the scratch ``ex`` (slot ``q = p ne + i`` of
    particle ``m0 + mm`` at ``q _BLOCK + mm``).  Here, in loops over the block that
    vectorise: ``s[m] = Π_p (1 + Σ_i exp(slot))`` (no ``log``); every ``G`` packets
    (``(ne + 1)^G < 1e300``) the product so far is folded into ``b`` (only with
    hundreds of packets).
    """
    lik(X, m0, n, k1, data, t, b, ex)
    # views indexed from 0: numba then needs no negative-index wraparound and the loops vectorise
    bb = b[m0:m0 + n]
    sb = s[m0:m0 + n]
    sb[:] = 1.0
    if ne == 0:
        return
    G = max(1, int(690.0 / math.log(ne + 1.0)))
    for p in range(P):
        q = p * ne * _BLOCK
        e0 = ex[q:q + n]
        for i in range(n):
            e0[i] = _exp_nonpos(e0[i])
        for j in range(1, ne):
            ej = ex[q + j * _BLOCK:q + j * _BLOCK + n]
            for i in range(n):
                e0[i] += _exp_nonpos(ej[i])
        for i in range(n):
            sb[i] *= 1.0 + e0[i]
        if (p + 1) % G == 0 and p + 1 < P:
            for i in range(n):
                bb[i] += math.log(sb[i])
                sb[i] = 1.0


def _loglik_rows(lik, P, ne, X, k1, data, out):
    """``out[m]`` = the log-likelihood of step 0 of ``data`` for every particle (helper, not the kernel)."""
    M = X.shape[0]
    ex = np.empty(_BLOCK * P * ne)
    s = np.empty(M)
    out[:] = 0.0
    for m0 in range(0, M, _BLOCK):
        _likelihood_block(lik, P, ne, X, m0, min(_BLOCK, M - m0), k1, data, 0, out, s, ex)
    for m in range(M):
        out[m] = _neginf_unless_finite(out[m] + math.log(s[m]))


@numba.njit(**_NJIT)
def _inverse_cdf(cdf, u, idx):
    """``idx[m] = min(searchsorted(cdf, u[m], 'right'), N - 1)`` for sorted ``u``."""
    N = cdf.shape[0]
    i = 0
    for m in range(u.shape[0]):
        while i < N and cdf[i] <= u[m]:
            i += 1
        idx[m] = i if i < N else N - 1


@numba.njit(**_NJIT)
def _cumsum_to_one(W, scale, cdf):
    """Cumulative sums of ``W * scale`` (the normalised weights), the last forced to 1."""
    acc = 0.0
    for i in range(W.shape[0]):
        acc += W[i] * scale
        cdf[i] = acc
    cdf[W.shape[0] - 1] = 1.0  # guard the last bin against rounding


@numba.njit(**_NJIT)
def _systematic(W, scale, u0, idx, cdf, ends):
    """Systematic resampling, ``u_m = (m + u0) / M``: the indices of ``_cumsum_to_one`` + ``_inverse_cdf``.

    Without a data-dependent branch (a merge of the cdf with the ``u_m`` mispredicts
    about once per particle: 10 ns per particle against 3): with ``c`` the cdf,
    ``J_i = #{m : u_m < c_i}`` (where particle ``i``'s copies end) is
    ``ceil(M c_i − u0)`` decided exactly by comparing with ``u_m`` itself on both
    sides (rounding moves it by one at most), in a loop that vectorises; ``J`` is
    non-decreasing as ``c`` is (the last bin, forced to 1, excepted: a running
    maximum there).  Then ``ends[J_{i-1}] = i`` (the last write to a position is
    the particle that has copies there) and ``idx[m]`` is the running maximum of
    ``ends`` (in floating point: an integer maximum becomes a branch).
    ``cdf`` (N) and ``ends`` (M + 1) are scratch.
    """
    M = idx.shape[0]
    N = W.shape[0]
    Mf = float(M)
    _cumsum_to_one(W, scale, cdf)
    for i in range(N):
        c = cdf[i]
        g = min(max(np.ceil(c * Mf - u0), 0.0), Mf)
        down = (g > 0.0) & ((g - 1.0 + u0) / Mf >= c)  # u_(g-1) >= c: one fewer
        up = (g < Mf) & ((g + u0) / Mf < c)  # u_g < c: one more
        cdf[i] = g - 1.0 if down else (g + 1.0 if up else g)  # J_i
    if N > 1:
        cdf[N - 1] = max(cdf[N - 1], cdf[N - 2])
    for m in range(M + 1):
        ends[m] = 0.0
    for i in range(1, N):
        ends[int(cdf[i - 1])] = float(i)
    run = 0.0
    for m in range(M):
        run = max(run, ends[m])
        idx[m] = int(run)


@numba.njit(**dict(_NJIT, inline="always"))
def _sift_down(a, root, end):
    while 2 * root + 1 < end:
        child = 2 * root + 1
        if child + 1 < end and a[child] < a[child + 1]:
            child += 1
        if not a[root] < a[child]:
            return
        a[root], a[child] = a[child], a[root]
        root = child


@numba.njit(**_NJIT)
def _sort(a):
    """Sort ``a`` (no NaN) in place, ascending: a heapsort, the same result as ``np.sort`` (which takes numba a
    second longer to compile)."""
    n = a.shape[0]
    for root in range(n // 2 - 1, -1, -1):
        _sift_down(a, root, n)
    for end in range(n - 1, 0, -1):
        a[0], a[end] = a[end], a[0]
        _sift_down(a, 0, end)


@numba.njit(**_NJIT)
def _resample(scheme, W, scale, rng, idx, cdf, u):
    """Indices from the weights ``W * scale`` (normalised): the schemes of filters.resampling, same draws.

    ``cdf`` (N) and ``u`` (M + 1) are scratch.
    """
    M = idx.shape[0]
    Mf = float(M)
    if scheme == 0:  # systematic: one uniform shared by all strata
        _systematic(W, scale, rng.random(), idx, cdf, u)
        return
    u = u[:M]
    if scheme == 3:  # residual: floor(M W) copies, the rest multinomially from the residual weights
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
            _cumsum_to_one(res, 1.0 / sres, cdf)
            ur = rng.random(rest)
            _sort(ur)
            extra = np.empty(rest, np.int64)
            _inverse_cdf(cdf, ur, extra)
            for e in range(rest):
                counts[extra[e]] += 1
        m = 0
        for i in range(N):
            for _ in range(counts[i]):
                idx[m] = i
                m += 1
        return
    _cumsum_to_one(W, scale, cdf)
    if scheme == 1:  # stratified: one uniform per stratum
        for m in range(M):
            u[m] = (m + rng.random()) / Mf
    else:  # multinomial: sorted independent uniforms
        for m in range(M):
            u[m] = rng.random()
        _sort(u)
    _inverse_cdf(cdf, u, idx)


@numba.njit(**_NJIT)
def _covariance(x, W, scale, mean, cov):
    n = x.shape[1]
    for i in range(n):
        for j in range(n):
            cov[i, j] = 0.0
    for m in range(x.shape[0]):
        wm = W[m] * scale
        for i in range(n):
            di = wm * (x[m, i] - mean[i])
            for j in range(i + 1):
                cov[i, j] += di * (x[m, j] - mean[j])
    for i in range(n):
        for j in range(i):
            cov[j, i] = cov[i, j]


@numba.njit(**_NJIT)
def _uniform_moments(x, mean, cov, do_cov, W):
    M, n = x.shape
    for m in range(M):
        W[m] = 1.0
    for i in range(n):
        mean[i] = 0.0
    for m in range(M):
        for i in range(n):
            mean[i] += x[m, i]
    for i in range(n):
        mean[i] /= M
    if do_cov:
        _covariance(x, W, 1.0 / M, mean, cov)


@numba.njit(**_NJIT)
def _step(prop, lik, P, ne, X, anc, XN, t, rng, data, lw, fresh, b, s, ex, buf):
    """Propagate every particle and weigh it with step ``t``'s data, block by block; returns the largest ``b``.

    ``prop(X, anc, XN, m0, n, k, rng, buf)`` (generated per model) writes ``f(X[anc[m]], k)
    + G w`` into ``XN[m]`` (resampling is the ancestor index ``anc``, no copy); it is
    called for the blocks in order, so a propagation that must draw the whole step's
    random numbers first (NumPy's order for switching modes or mixture noise, see
    :func:`_prop_predrawn`) does so into ``buf`` at its first block; the
    new log weight ``lw[m] + log p(y_t | XN[m])`` is left as ``b[m] + log s[m]`` (see
    :func:`_likelihood_block`): ``s`` is a linear factor >= 1, no ``log`` is taken
    here, and a NaN or infinite one becomes ``b = -inf``, ``s = 0`` (zero weight).
    Blocks of ``_BLOCK`` particles keep the scratch ``ex`` small; separate loops keep
    few values live across the generator and libm calls (which clobber every
    floating-point register) and let the branch-free ones vectorise.
    """
    M = X.shape[0]
    k = float(t)
    best = -math.inf
    for m0 in range(0, M, _BLOCK):
        n = min(_BLOCK, M - m0)
        prop(X, anc, XN, m0, n, k, rng, buf)
        bb = b[m0:m0 + n]  # views indexed from 0 (see _likelihood_block)
        sb = s[m0:m0 + n]
        for i in range(n):
            bb[i] = 0.0 if fresh else lw[m0 + i]
        _likelihood_block(lik, P, ne, XN, m0, n, k + 1.0, data, t, b, s, ex)
        for i in range(n):
            v = bb[i]
            if not (v > -math.inf and v < math.inf and sb[i] == sb[i]):  # NaN (e.g. h undefined) or infinite
                v = -math.inf
                sb[i] = 0.0  # zero weight
            bb[i] = v
            best = v if v > best else best
    return best


def _sir_run(prop, nd, lik, P, ne, weigh, data, x0, rng, scheme, ess_thr, do_cov, mean, cov, ess, resampled,
             collapsed):
    """One Monte Carlo run of the bootstrap filter; returns its log marginal likelihood.

    ``nd``: random numbers per particle that ``prop`` draws ahead of each step into
    its scratch (0 for a propagation that draws as it goes).

    Each step: :func:`_step` (propagation, and the new log weights as ``b + log s``);
    ``weigh(x, b, s, best, W, mean)`` (generated per model) sets ``W = exp(b - best) s``
    and the weighted mean and returns ``(Σ W, Σ W²)``; resample.  Only a step that
    does not resample needs the log weights themselves (one ``log`` per particle).
    """
    M, n_x = x0.shape
    K = ess.shape[0]
    x = x0.copy()
    xn = np.empty((M, n_x))
    lw = np.zeros(M)
    b = np.empty(M)
    s = np.empty(M)
    W = np.empty(M)  # unnormalised weights exp(b - best) s
    anc = np.arange(M)
    cdf = np.empty(M)
    u = np.empty(M + 1)  # the resampler's scratch
    ex = np.empty(_BLOCK * P * ne)  # the likelihood's scratch (see _likelihood_block)
    buf = np.empty(M * nd)  # the propagation's scratch (see _step)
    Mf = float(M)
    lnM = math.log(Mf)
    _uniform_moments(x, mean[0], cov[0], do_cov, W)
    prev = lnM  # log Σ exp(lw) of the previous step's weights
    fresh = True  # lw is all zeros (start, or just resampled)
    total = 0.0
    for k in range(K):
        mk = mean[k + 1]
        ck = cov[k + 1] if do_cov else cov[0]
        best = _step(prop, lik, P, ne, x, anc, xn, k, rng, data, lw, fresh, b, s, ex, buf)
        x, xn = xn, x
        if best == -math.inf:
            # Collapse: every weight vanished.  Keep the predicted particles, uniformly weighted.
            collapsed[k] = True
            total = -math.inf
            ess[k] = Mf
            _uniform_moments(x, mk, ck, do_cov, W)
            for m in range(M):
                lw[m] = 0.0
                anc[m] = m
            fresh = True
            prev = lnM
            continue
        acc, s2 = weigh(x, b, s, best, W, mk)  # acc >= 1: the best particle's W is its s >= 1
        inv = 1.0 / acc
        ln = best + math.log(acc)
        total += ln - prev  # log p(z_k | z_1:k-1): the change of the log normaliser
        e = acc * acc / s2  # 1 / Σ W², W = e / acc
        ess[k] = e
        if do_cov:
            _covariance(x, W, inv, mk, ck)
        if ess_thr >= 1.0 or e < ess_thr * Mf - 1e-9:
            _resample(scheme, W, inv, rng, anc, cdf, u)
            resampled[k] = True
            fresh = True
            prev = lnM
        else:
            for m in range(M):
                anc[m] = m
                lw[m] = b[m] + math.log(s[m])  # -inf + log 0 = -inf for a zero weight
            fresh = False
            prev = ln
    return total


# The generated per-model functions reach the generic code as function pointers of these signatures (numba
# first-class function types), so that the generic code — _sir_run and what it calls — is compiled once per
# likelihood family and process, not once per model, wrap set and likelihood variant.
_F1, _F2, _F3 = types.float64[::1], types.float64[:, ::1], types.float64[:, :, ::1]
_I1, _I2, _B1 = types.int64[::1], types.int64[:, ::1], types.boolean[::1]
_GEN = numba.typeof(np.random.default_rng(0))  # one type for every numpy.random.Generator
_DATA = {"packets": types.Tuple((_I2, _F3, _F2, types.float64)),  # sens, Y, att, log_clean (see sir_packets)
         "binary": types.Tuple((_F2, _F2, types.float64)),  # A, B, threshold (see sir_binary)
         "edpf": types.Tuple((_F2, _F2))}  # decrypted values, availabilities (see filters.fastedpf)
_PROP_T = types.FunctionType(types.void(_F2, _I1, _F2, types.int64, types.int64, types.float64, _GEN, _F1))
_WEIGH_T = types.FunctionType(types.UniTuple(types.float64, 2)(_F2, _F1, _F1, types.float64, _F1, _F1))
_DRIVERS: dict = {}


def _lik_type(family: str):
    return types.FunctionType(types.void(_F2, types.int64, types.int64, types.float64, _DATA[family], types.int64, _F1,
                                         _F1))


def _drivers(family: str) -> tuple:
    """``(run, rows)``: :func:`_sir_run` and :func:`_loglik_rows` compiled for ``family`` (at the first call).

    Returned as the compiled entry points, not dispatchers: the argument types are
    fixed (the callers validate and allocate the arrays accordingly), so the
    dispatcher's type resolution at every call (about 50 µs with the function
    arguments, serial under the GIL) is skipped.
    """
    if family not in _DRIVERS:
        lik, data, i8, f8 = _lik_type(family), _DATA[family], types.int64, types.float64
        sigs = (f8(_PROP_T, i8, lik, i8, i8, _WEIGH_T, data, _F2, _GEN, i8, f8, types.boolean, _F2, _F3, _F1, _B1, _B1),
                types.void(lik, i8, i8, _F2, f8, data, _F1))
        out = []
        for fn, sig in zip((_sir_run, _loglik_rows), sigs):
            disp = numba.njit(sig, **_NJIT)(fn)
            out.append(disp.overloads[disp.signatures[0]].entry_point)
        _DRIVERS[family] = tuple(out)
    return _DRIVERS[family]


# ============================================================================ generated per-model code
_KERNELS: "weakref.WeakKeyDictionary[Model, dict]" = weakref.WeakKeyDictionary()
_NS = {"_ndtr": _ndtr, "_exp": _exp_nonpos, "_wrap": _wrap_angle}


def _kernels(model: Model) -> dict:
    d = _KERNELS.get(model)
    if d is None:
        d = _KERNELS[model] = {}
    return d


def _c(v: float) -> str:
    return repr(float(v))


def _compile(model: Model, key, src: str, fname: str, what: str, ftype, namespace: dict | None = None):
    """``fname`` of ``src`` (generated for ``model``) compiled for the function type ``ftype``, cached per model.

    Returned as a first-class function value (numba's wrapper address protocol) rather
    than a dispatcher: passing it to the drivers then costs no signature lookup per call.
    """
    cache = _kernels(model)
    if key not in cache:
        fn = compile_source(src, fname, f"{what} of {model.name!r}", dict(_NS, **(namespace or {})), fastmath=_FAST)
        sig = ftype.signature
        fn.compile(sig)
        cache[key] = types.CompileResultWAP(fn.overloads[tuple(sig.args)])
    return cache[key]


def _noise_terms(model: Model, comp: Gaussian, z: str) -> list[str]:
    """Per state component ``i``, the source of ``(G (mean + L z))_i`` for the Gaussian ``comp`` (constants inlined)."""
    G = model.noise_gain
    gm, GL = G @ comp.mean, G @ comp._chol
    out = []
    for i in range(model.n_x):
        noise_i = " + ".join(f"{_c(GL[i, j])} * {z}{j}" for j in range(GL.shape[1]) if GL[i, j] != 0.0) or "0.0"
        out.append(noise_i if gm[i] == 0.0 else f"{_c(gm[i])} + ({noise_i})")
    return out


def _prop(model: Model):
    """``prop(X, anc, XN, m0, n, k, rng, buf)``: ``XN[m] = f(X[anc[m]], k) + G (mean + L z)``, ``z ~ N(0, I)``,
    for ``m = m0 .. m0 + n − 1``: one particle's ``n_w`` normals in a row, particle after particle (NumPy's
    order), drawn as it goes (``buf`` unused: ``nd = 0``)."""
    noise = model.process_noise
    if not isinstance(noise, Gaussian):
        raise InputError(f"process_noise of model {model.name!r} is {type(noise).__name__}; "
                         "the fused kernels need Gaussian process noise")
    lines = ["def prop(X, anc, XN, m0, n, k, rng, buf):", "    for m in range(m0, m0 + n):", "        a = anc[m]"]
    lines += scalar_statements(model.casadi_f, ["X[a, {}]", "k", None, None], "f{}", indent="        ")
    lines += [f"        z{j} = rng.standard_normal()" for j in range(noise.dim)]
    lines += [f"        XN[m, {i}] = f{i} + ({t})" for i, t in enumerate(_noise_terms(model, noise, "z"))]
    return _compile(model, "prop", "\n".join(lines), "prop", "the propagation", _PROP_T)


def _choice_count(u: str, probs) -> str:
    """Source of ``Generator.choice(len(probs), p=probs)`` given its uniform ``u``: NumPy's
    ``searchsorted(cdf, u, 'right')`` with ``cdf = cumsum(p) / sum(p)``, i.e. the number of ``cdf`` entries
    ``<= u`` (the last, 1, never is)."""
    cdf = np.cumsum(np.asarray(probs, dtype=np.float64))
    cdf /= cdf[-1]
    return " + ".join(["0"] + [f"({u} >= {_c(c)})" for c in cdf[:-1]])


def _prop_predrawn(model: Model) -> tuple:
    """``(prop, nd)``: the propagation of a model with switching modes and/or Gaussian-mixture process noise.

    It draws as :func:`filters.particle.transition_proposal` does, in blocks per step:
    ``M`` uniforms for the modes (``Generator.choice`` with ``model.mode_probs``), ``M``
    uniforms for the mixture's components (``GaussianMixture.sample``: ``choice`` with
    its weights), then ``M n_w`` standard normals, particle after particle.  These
    ``nd`` numbers per particle are drawn into ``buf`` at the step's first block
    (``m0 = 0``, see :func:`_step`), then ``XN[m] = f(X[anc[m]], k, mode) + G (mean_c +
    L_c z)`` with the particle's mode and component ``c``.  A model without modes and
    with Gaussian noise gets :func:`_prop` (``nd = 0``), which draws as it goes.
    """
    noise = model.process_noise
    if not model.n_modes and isinstance(noise, Gaussian):
        return _prop(model), 0
    if isinstance(noise, Gaussian):
        comps, weights = [noise], None
    elif isinstance(noise, GaussianMixture):
        comps, weights = list(noise.components), noise.weights
    else:
        raise InputError(f"process_noise of model {model.name!r} is {type(noise).__name__}; the fused kernels "
                         "support Gaussian and GaussianMixture process noise")
    n_w = noise.dim
    nu = int(model.n_modes > 0) + int(weights is not None)  # blocks of M uniforms: the modes', the labels'
    nd = nu + n_w
    cache = _kernels(model)
    if "prop_predrawn" in cache:
        return cache["prop_predrawn"], nd
    lines = ["def prop(X, anc, XN, m0, n, k, rng, buf):", "    M = X.shape[0]", f"    zo = {nu} * M",
             "    if m0 == 0:  # the whole step's draws, in NumPy's order"]
    for b in range(nu):
        lines += [f"        for i in range({b} * M, {b + 1} * M):", "            buf[i] = rng.random()"]
    lines += [f"        for i in range(zo, zo + M * {n_w}):", "            buf[i] = rng.standard_normal()",
              "    for m in range(m0, m0 + n):", "        a = anc[m]"]
    if model.n_modes:
        lines.append(f"        md = float({_choice_count('buf[m]', model.mode_probs)})")
    lines += scalar_statements(model.casadi_f, ["X[a, {}]", "k", None, "md" if model.n_modes else None], "f{}",
                               indent="        ")
    lines += [f"        z{j} = buf[zo + m * {n_w} + {j}]" for j in range(n_w)]
    terms = [_noise_terms(model, g, "z") for g in comps]
    if weights is not None:
        lines.append(f"        lab = {_choice_count(f'buf[{nu - 1} * M + m]', weights)}")
    for i in range(model.n_x):
        sel = terms[-1][i]
        for c in range(len(comps) - 2, -1, -1):
            sel = f"({terms[c][i]}) if lab == {c} else ({sel})"
        lines.append(f"        XN[m, {i}] = f{i} + ({sel})")
    return _compile(model, "prop_predrawn", "\n".join(lines), "prop", "the propagation", _PROP_T), nd


def _weigh(model: Model):
    """``weigh(x, b, s, best, W, mean) -> (Σ W, Σ W²)``: ``W = exp(b - best) s`` and the weighted mean.

    Generated per state dimension so that the mean's sums are local scalars; the
    exps in a loop of their own, which vectorises.
    """
    n = model.n_x
    lines = ["def weigh(x, b, s, best, W, mean):", "    M = x.shape[0]", "    for m in range(M):",
             "        W[m] = _exp(b[m] - best) * s[m]", "    acc = 0.0", "    s2 = 0.0"]
    lines += [f"    a{i} = 0.0" for i in range(n)]
    lines += ["    for m in range(M):", "        e = W[m]", "        acc += e", "        s2 += e * e"]
    lines += [f"        a{i} += e * x[m, {i}]" for i in range(n)]
    lines.append("    inv = 1.0 / acc")
    lines += [f"    mean[{i}] = a{i} * inv" for i in range(n)]
    lines.append("    return acc, s2")
    return _compile(model, "weigh", "\n".join(lines), "weigh", "the weights", _WEIGH_T)


def _components(noise: Noise, label: str) -> list:
    if isinstance(noise, Gaussian):
        return [(None, noise)]
    if isinstance(noise, GaussianMixture):
        return [(w, g) for w, g in zip(noise.weights, noise.components) if w > 0.0]
    raise InputError(f"{label} noise is {type(noise).__name__}; the fused kernels support Gaussian and "
                     "GaussianMixture")


def _component_lines(comps: list, r: list[str], indent: str) -> list[str]:
    """Statements setting ``t{c} = log w_c + log N(r; mean_c, cov_c)`` (as Gaussian.logpdf), constants inlined."""
    out = []
    d = len(r)
    for c, (w, g) in enumerate(comps):
        dv = []
        for j in range(d):
            if g.mean[j] == 0.0:
                dv.append(r[j])
            else:
                out.append(f"{indent}d{j} = {r[j]} - {_c(g.mean[j])}")
                dv.append(f"d{j}")
        L = g._chol_inv  # lower triangular: z = L (r - mean)
        for i in range(d):
            t = [f"{_c(L[i, j])} * {dv[j]}" for j in range(i + 1) if L[i, j] != 0.0]
            out.append(f"{indent}e{i} = {' + '.join(t) if t else '0.0'}")
        quad = " + ".join(f"e{i} * e{i}" for i in range(d))
        lp = f"-0.5 * ({_c(d * _LOG_2PI + g._logdet)} + ({quad}))"
        out.append(f"{indent}t{c} = {lp}" if w is None else f"{indent}t{c} = {_c(np.log(w))} + ({lp})")
    return out


def _max_others_lines(terms: list[str], ne: int, indent: str) -> list[str]:
    """Statements adding ``mx = max(terms)`` to ``b[m]`` and writing the others minus it into the ``ne`` slots.

    ``log Σ exp(terms) = mx + log(1 + Σ exp(slots))``.  The maximum is kept by
    selects (no data-dependent branch); slots past ``len(terms) - 1`` get ``-inf``.
    A NaN term ends up in ``mx`` or in a slot, so the log-likelihood is NaN (zero
    weight) as with ``logaddexp``; all terms ``-inf`` give ``mx = -inf``.
    """
    out = [f"{indent}mx = {terms[0]}"]
    for i, t in enumerate(terms[1:]):
        out += [f"{indent}u = {t}", f"{indent}o{i} = mx if u > mx else u", f"{indent}mx = u if u > mx else mx"]
    slots = [f"o{i} - mx" for i in range(len(terms) - 1)] + ["-_m.inf"] * (ne - len(terms) + 1)
    out += [f"{indent}x{i}[mm] = {v}" for i, v in enumerate(slots)]
    out.append(f"{indent}bb[mm] += mx")
    return out


def _packet_lik(model: Model, wrap: tuple, attacked: bool):
    """``(lik, NE)`` of the packet likelihood (see :func:`_likelihood_block`), ``data = (sens, Y, att, lc)``.

    For packet ``p`` of step ``t`` from sensor ``s = sens[t, p]`` with ``a = att[t, p]``
    and, per particle, ``r = wrap(Y[t, p] − h_s(X[m], k))``::

        logaddexp(lc + log p_ν_s(r), a) = mx + log(1 + Σ_{i < NE} exp(slot_i))

    the log-sum-exp over ``lc +`` each mixture component's log term and ``a``, split
    into its largest term (added to ``b[m]``) and the others relative to it (the
    ``NE`` slots of the packet).  Model, noise constants and the wrapping are
    inlined (generated per model, wrap set and ``attacked``); ``NE`` is the largest
    number of components of a sensor, less one unless ``attacked``
    (``attacked=False`` leaves ``a`` out: for ``a = -inf`` everywhere).  One loop over
    the block per sensor, without branches or calls when ``h`` has none, so that
    it vectorises.
    """
    key = ("packet", wrap, attacked)
    cache = _kernels(model)
    if key in cache:
        return cache[key]
    comps = [_components(sensor.noise, f"model.sensors[{s}]") for s, sensor in enumerate(model.sensors)]
    ne = max(len(c) for c in comps) - (0 if attacked else 1)  # the terms less the largest
    # views indexed from 0 (no negative-index wraparound in the loop, which then vectorises), X flat: the stride
    # of its rows a constant
    nx = model.n_x
    lines = ["def lik(X, m0, n, k, data, t, b, ex):", "    sens, Y, att, lc = data",
             f"    Xf = X.reshape(-1)[m0 * {nx}:(m0 + n) * {nx}]", "    bb = b[m0:m0 + n]",
             "    for p in range(sens.shape[1]):", "        s = sens[t, p]", "        a = att[t, p]"]
    for i in range(ne):  # the packet's slots
        q = f"p * {ne * _BLOCK} + {i * _BLOCK}"
        lines.append(f"        x{i} = ex[{q}:{q} + n]")
    ind = " " * 16
    bodies = []
    for s, (sensor, fun) in enumerate(zip(model.sensors, model.casadi_h)):
        body = [f"            y{j} = Y[t, p, {j}]" for j in range(sensor.dim)] + ["            for mm in range(n):"]
        body += scalar_statements(fun, [f"Xf[mm * {nx} + {{}}]", "k"], "h{}", indent=ind)
        # angles into (-pi, pi] as filters.rrp.wrap_angles (a no-op inside, to rounding)
        body += [f"{ind}r{j} = {'_wrap(' if (s, j) in wrap else '('}y{j} - h{j})" for j in range(sensor.dim)]
        body += _component_lines(comps[s], [f"r{j}" for j in range(sensor.dim)], ind)
        terms = [f"lc + t{c}" for c in range(len(comps[s]))] + (["a"] if attacked else [])
        bodies.append("\n".join(body + _max_others_lines(terms, ne, ind)))
    tables = {}
    for g, (members, body, table) in enumerate(_shared_bodies(bodies)):
        lines.append(f"        {'if' if g == 0 else 'elif'} {' or '.join(f's == {i}' for i in members)}:")
        lines += [f"            c{j} = _K{g}[s, {j}]" for j in range(table.shape[1])]
        lines.append(body)
        tables[f"_K{g}"] = table
    lines += ["        else:", "            bb[:] = _m.nan"]
    cache[key] = _compile(model, ("lik", key), "\n".join(lines), "lik", "the packet likelihood",
                          _lik_type("packets"), tables), ne
    return cache[key]


_FLOAT = re.compile(r"(?<![\w.])(?:\d+\.\d*(?:e[+-]?\d+)?|\d+e[+-]?\d+)")  # a float literal (repr), not an index


def _shared_bodies(bodies: list[str]) -> list[tuple[list[int], str, np.ndarray]]:
    """Sensors whose generated bodies differ only in float literals (e.g. sensor positions) share one body.

    Returns ``(members, body, table)`` per group: in ``body`` the literals that differ
    between the members read ``c0, c1, ...``, which row ``s`` of ``table`` holds for
    member ``s``.  Fewer, not more, loops to compile for a network of alike sensors.
    """
    groups: dict[str, list[int]] = {}
    for s, body in enumerate(bodies):
        groups.setdefault(_FLOAT.sub("#", body), []).append(s)
    out = []
    for members in groups.values():
        values = np.array([[float(v) for v in _FLOAT.findall(bodies[s])] for s in members]).reshape(len(members), -1)
        varies = np.flatnonzero(np.any(values != values[:1], axis=0))
        table = np.zeros((len(bodies), len(varies)))
        table[members] = values[:, varies]
        slot = {int(i): j for j, i in enumerate(varies)}
        count = iter(range(values.shape[1]))

        def literal(match, slot=slot, count=count):
            i = next(count)
            return f"c{slot[i]}" if i in slot else match.group(0)

        out.append((members, _FLOAT.sub(literal, bodies[members[0]]), table))
    return out


def _binary_lik(model: Model):
    """``lik`` of the binary likelihood (see :func:`_likelihood_block`, no slots), ``data = (A, B, T)``:
    ``b[m] += Σ_s log(A[t, s] + B[t, s] F_ν_s(T − h_s(X[m], k)))``."""
    if any(d != 1 for d in model.sensor_dims):
        raise InputError("sir_binary needs scalar sensors (every sensor of dimension 1)")
    lines = ["def lik(X, m0, n, k, data, t, b, ex):", "    A, B, T = data", "    Xb = X[m0:m0 + n]",
             "    bb = b[m0:m0 + n]", "    for m in range(n):"]
    lines += scalar_statements(model.casadi_h_all, ["Xb[m, {}]", "k"], "h{}", indent="        ")
    lines.append("        total = 0.0")
    for s, sensor in enumerate(model.sensors):
        nz = sensor.noise
        lines.append(f"        u = T - h{s}")
        if isinstance(nz, Gaussian):  # Gaussian.cdf: ndtr((x - mean) / sd)
            c = f"_ndtr((u - {_c(nz.mean[0])}) / {_c(np.sqrt(nz.cov[0, 0]))})"
        elif isinstance(nz, GaussianMixture):  # sum of w * component cdf
            c = " + ".join(f"{_c(w)} * _ndtr((u - {_c(g.mean[0])}) / {_c(np.sqrt(g.cov[0, 0]))})"
                           for w, g in zip(nz.weights, nz.components))
        else:
            raise InputError(f"model.sensors[{s}] noise is {type(nz).__name__}; the fused kernels support Gaussian "
                             "and GaussianMixture")
        lines.append(f"        total += _m.log(A[t, {s}] + B[t, {s}] * ({c}))")
    lines.append("        bb[m] += total")
    return _compile(model, "binary", "\n".join(lines), "lik", "the binary likelihood", _lik_type("binary"))


# ============================================================================ input checks
def _model(model) -> Model:
    if not isinstance(model, Model):
        raise InputError(f"model must be a designer.Model, got {type(model).__name__}")
    jit_model(model)  # raises InputError for inputs or modes, UnsupportedOperation for an untranslatable op
    return model


def _particles(x0, n_x: int, name: str = "x0") -> np.ndarray:
    try:
        x = np.asarray(x0, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be numeric: {exc}") from None
    if x.ndim != 3 or x.shape[2] != n_x or x.shape[0] < 1 or x.shape[1] < 1:
        raise InputError(f"{name} must have shape (runs, particles, {n_x}), got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise InputError(f"{name} must be finite (no NaN or inf particles)")
    return np.require(x, np.float64, ["C", "W"])  # the kernels' argument types: C-contiguous, writeable


def _generators(rngs, R: int) -> list[np.random.Generator]:
    if isinstance(rngs, np.random.Generator):
        raise InputError("rngs must be a sequence of numpy.random.Generator, one per run (got a single Generator)")
    try:
        gens = list(rngs)
    except TypeError:
        raise InputError(f"rngs must be a sequence of numpy.random.Generator, got {type(rngs).__name__}") from None
    if len(gens) != R:
        raise InputError(f"rngs must hold one Generator per run ({R}), got {len(gens)}")
    for i, g in enumerate(gens):
        if not isinstance(g, np.random.Generator):
            raise InputError(f"rngs[{i}] must be a numpy.random.Generator, got {type(g).__name__}")
    if len({id(g.bit_generator) for g in gens}) != R:
        raise InputError("rngs must be distinct Generators with distinct bit generators (one per run; runs may "
                         "execute concurrently)")
    return gens


def _options(resampler, ess_threshold, threads, covariance) -> tuple[int, float, int, bool]:
    if not isinstance(resampler, str) or resampler not in RESAMPLER_CODES:
        raise InputError(f"resampler must be one of {', '.join(RESAMPLER_CODES)}, got {resampler!r}")
    if isinstance(ess_threshold, bool) or not isinstance(ess_threshold, (int, float, np.integer, np.floating)) \
            or not (0.0 < float(ess_threshold) <= 1.0):
        raise InputError(f"ess_threshold must lie in (0, 1], got {ess_threshold!r}")
    if not isinstance(covariance, (bool, np.bool_)):
        raise InputError(f"covariance must be True or False, got {covariance!r}")
    return RESAMPLER_CODES[resampler], float(ess_threshold), check_int("threads", threads, 1), bool(covariance)


def _wrap_set(angles, model: Model) -> tuple:
    """Sorted ``(sensor, component)`` pairs of the angular components (:func:`filters.rrp.angle_sets`)."""
    return tuple((s, j) for s, comps in enumerate(angle_sets(model, angles)) for j in comps)


def _packet_data(model: Model, R: int, sensors, y, attack, log_clean):
    """Validated ``(sens (K, P), y (R, K, P, n_y), attack (R, K, P), log_clean)``."""
    S = model.n_sensors
    dims = np.asarray(model.sensor_dims, dtype=np.int64)
    width = int(dims.max())
    sens = np.asarray(sensors)
    if sens.dtype.kind not in "iu":
        raise InputError(f"sensors must be an integer array, got dtype {sens.dtype}")
    if sens.ndim == 1:
        sens = sens[:, None]
    if sens.ndim != 2 or sens.shape[0] < 1 or sens.shape[1] < 1:
        raise InputError(f"sensors must have shape (K, P) (or (K,) for one packet per step), got {np.shape(sensors)}")
    if np.any((sens < 0) | (sens >= S)):
        raise InputError(f"sensors must hold sensor indices in 0..{S - 1}")
    sens = np.require(sens, np.int64, ["C", "W"])
    K, P = sens.shape
    try:
        yy = np.asarray(y, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"y must be numeric: {exc}") from None
    if P == 1 and yy.ndim == 3:
        yy = yy[:, :, None, :]
    if yy.shape != (R, K, P, width):
        raise InputError(f"y must have shape (runs, K, P, n_y) = ({R}, {K}, {P}, {width}), got {np.shape(y)}")
    used = np.arange(width) < dims[sens][..., None]  # (K, P, width): the components each packet carries
    if not np.all(np.isfinite(yy) | ~used):
        raise InputError("y must be finite in every received component (NaN measurements are not treated as missing)")
    yy = np.ascontiguousarray(np.where(used, yy, 0.0))
    if attack is None:
        att = np.full((R, K, P), -np.inf)
    else:
        try:
            att = np.asarray(attack, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(f"attack must be numeric: {exc}") from None
        if P == 1 and att.shape == (R, K):
            att = att[..., None]
        if att.shape != (R, K, P):
            raise InputError(f"attack must have shape (runs, K, P) = ({R}, {K}, {P}), got {np.shape(attack)}")
        if np.any(np.isnan(att) | (att == np.inf)):
            raise InputError("attack must hold finite values or -inf (no NaN or +inf log terms)")
        att = np.require(att, np.float64, ["C", "W"])
    if isinstance(log_clean, bool) or not isinstance(log_clean, (int, float, np.integer, np.floating)) \
            or not float(log_clean) <= 0.0:
        raise InputError(f"log_clean must be a number <= 0 (a log probability), got {log_clean!r}")
    return sens, yy, att, float(log_clean)


def _binary_data(model: Model, R: int, A, B, threshold):
    S = model.n_sensors
    arrs = []
    for name, v in (("A", A), ("B", B)):
        try:
            a = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(f"{name} must be numeric: {exc}") from None
        if a.ndim != 3 or a.shape[0] != R or a.shape[2] != S or a.shape[1] < 1:
            raise InputError(f"{name} must have shape (runs, K, sensors) = ({R}, K, {S}), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InputError(f"{name} must be finite")
        arrs.append(np.require(a, np.float64, ["C", "W"]))
    if arrs[0].shape != arrs[1].shape:
        raise InputError(f"A and B must have the same shape, got {arrs[0].shape} and {arrs[1].shape}")
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float, np.integer, np.floating)) \
            or not np.isfinite(threshold):
        raise InputError(f"threshold must be a finite number, got {threshold!r}")
    return arrs[0], arrs[1], float(threshold)


# ============================================================================ driver
def _run_all(family, kernels, data_of_run, x0, gens, K, scheme, thr, covariance, threads) -> FastSIRResult:
    """``kernels = (prop, nd, lik, P, ne, weigh)`` of :func:`_sir_run`; runs spread over ``threads`` threads."""
    run = _drivers(family)[0]
    R, M, n_x = x0.shape
    mean = np.empty((R, K + 1, n_x))
    cov = np.empty((R, K + 1, n_x, n_x)) if covariance else np.zeros((R, 1, 0, 0))
    ess = np.empty((R, K))
    resampled = np.zeros((R, K), dtype=np.bool_)
    collapsed = np.zeros((R, K), dtype=np.bool_)
    loglik = np.empty(R)

    def one(r: int) -> None:
        loglik[r] = run(*kernels, data_of_run(r), x0[r], gens[r], scheme, thr, covariance, mean[r], cov[r],
                             ess[r], resampled[r], collapsed[r])

    if threads == 1 or R == 1:
        for r in range(R):
            one(r)
    else:
        # Each thread takes the next run until none is left (itertools.count is atomic under the GIL): as
        # balanced as one task per run on a busy machine, without a future per run.
        runs = itertools.count()

        def worker() -> None:
            for r in runs:
                if r >= R:
                    return
                one(r)

        with ThreadPoolExecutor(max_workers=min(threads, R)) as ex:
            for f in [ex.submit(worker) for _ in range(min(threads, R))]:
                f.result()  # re-raise any exception from a worker
    return FastSIRResult(check_finite_means(mean, "fused particle filter"), cov if covariance else None, ess, loglik,
                         resampled, collapsed)


def sir_packets(
    model: Model,
    x0: np.ndarray,
    rngs: Sequence[np.random.Generator],
    sensors: np.ndarray,
    y: np.ndarray,
    *,
    attack: np.ndarray | None = None,
    log_clean: float = 0.0,
    angles: Sequence = (),
    resampler: str = "systematic",
    ess_threshold: float = 1.0,
    covariance: bool = False,
    threads: int = 1,
) -> FastSIRResult:
    """Bootstrap filter on packets of sensor measurements, many runs, fused numba kernels.

    Parameters
    ----------
    model : Model
        Without known inputs or switching modes; Gaussian process noise; every
        sensor's noise Gaussian or GaussianMixture.
    x0 : ndarray, shape (R, M, n_x)
        Initial particles of every run (sampled by the caller, e.g. with each run's generator).
    rngs : sequence of R numpy.random.Generator
        One distinct generator per run.
    sensors : int ndarray, shape (K, P) (or (K,) for P = 1)
        Sensor of packet ``p`` at step ``k`` (the step's packets measure ``x_{k+1}``).
    y : ndarray, shape (R, K, P, n_y) (or (R, K, n_y) for P = 1)
        Received values; ``n_y`` is the largest sensor dimension and a smaller
        sensor uses the leading components.  Must be finite where used.
    attack : ndarray, shape (R, K, P) (or (R, K) for P = 1), optional
        ``log η̄ + log p_ξ(y)`` per packet (:func:`deception_terms`); ``-inf`` (the
        default, everywhere) gives the standard likelihood.
    log_clean : float
        ``log(1 − η̄)`` (0 for the standard likelihood).
    angles : sequence
        Residual components wrapped into (−π, π]: component indices (for every
        sensor) or ``(sensor, component)`` pairs (as a model's
        ``angle_components``, from its sensors' ``angles``).
    resampler : {'systematic', 'stratified', 'multinomial', 'residual'}
    ess_threshold : float in (0, 1]
        Resample when ESS < ``ess_threshold * M``; 1 resamples at every step.
    covariance : bool
        Also return the weighted covariance at every step.
    threads : int
        Threads the runs are spread over (the results do not depend on it).

    Returns
    -------
    FastSIRResult
    """
    model = _model(model)
    x0 = _particles(x0, model.n_x)
    R = x0.shape[0]
    gens = _generators(rngs, R)
    scheme, thr, threads, covariance = _options(resampler, ess_threshold, threads, covariance)
    sens, yy, att, lc = _packet_data(model, R, sensors, y, attack, log_clean)
    lik, ne = _packet_lik(model, _wrap_set(angles, model), bool(np.any(att > -np.inf)))
    kernels = (_prop(model), 0, lik, sens.shape[1], ne, _weigh(model))
    return _run_all("packets", kernels, lambda r: (sens, yy[r], att[r], lc), x0, gens, sens.shape[0], scheme, thr,
                    covariance, threads)


def sir_binary(
    model: Model,
    x0: np.ndarray,
    rngs: Sequence[np.random.Generator],
    A: np.ndarray,
    B: np.ndarray,
    *,
    threshold: float,
    resampler: str = "systematic",
    ess_threshold: float = 1.0,
    covariance: bool = False,
    threads: int = 1,
) -> FastSIRResult:
    """Bootstrap filter with the affine-in-CDF likelihood of binary sensors, many runs, fused kernels.

    The log-likelihood of step ``k`` is ``Σ_s log(A[r, k, s] + B[r, k, s] F_ν(T − h_s(x)))``
    with ``F_ν`` the CDF of sensor ``s``'s scalar Gaussian or Gaussian-mixture
    noise and ``T`` the threshold.  :func:`binary_coefficients` gives the ``A`` and
    ``B`` of seed 002's likelihood (13)-(16) from the received signals.

    Parameters
    ----------
    A, B : ndarray, shape (R, K, S)
        Coefficients per run, step and sensor (independent of the state).
    threshold : float
        ``T_δ``.

    Other parameters as in :func:`sir_packets`.
    """
    model = _model(model)
    x0 = _particles(x0, model.n_x)
    R = x0.shape[0]
    gens = _generators(rngs, R)
    scheme, thr, threads, covariance = _options(resampler, ess_threshold, threads, covariance)
    AA, BB, T = _binary_data(model, R, A, B, threshold)
    kernels = (_prop(model), 0, _binary_lik(model), 0, 0, _weigh(model))
    return _run_all("binary", kernels, lambda r: (AA[r], BB[r], T), x0, gens, AA.shape[1], scheme, thr, covariance,
                    threads)


# ============================================================================ likelihood helpers
def deception_terms(y, attack_prob: float, signal: Noise | None) -> tuple[float, np.ndarray]:
    """``(log_clean, attack)`` of seed 000's attack-aware likelihood (14) for received packets ``y`` (..., n_y).

    ``log_clean = log(1 − η̄)`` and ``attack = log η̄ + log p_ξ(y)`` (shape ``y.shape[:-1]``);
    ``attack_prob = 0`` or no signal gives the standard likelihood ``(0, −inf)``.
    """
    p = float(check_probability("attack_prob", attack_prob, open_upper=True))
    y = np.asarray(y, dtype=np.float64)
    if p <= 0.0 or signal is None:
        return 0.0, np.full(y.shape[:-1], -np.inf)
    if not isinstance(signal, Noise):
        raise InputError(f"signal must be a Noise distribution, got {type(signal).__name__}")
    with np.errstate(divide="ignore"):
        return float(np.log1p(-p)), np.log(p) + signal.logpdf(y)


def binary_coefficients(y, *, threshold: float, gain: float, channel_noise: Noise, deception: Noise,
                        dos_prob: float = 0.0, deception_prob: float = 0.0,
                        flip_prob: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``A``, ``B`` with ``p(y_s | x) = A + B c``, ``c = F_ν(T − h_s(x))`` (seed 002 (13)-(16)).

    With ``P_e`` the channel density, ``pe1 = P_e(y − τ)``, ``pe0 = P_e(y)``, ``a = ᾱ``::

        L00 = pe1 (1 − a) + pe0 a + c (2a − 1)(pe1 − pe0)
        L01 = L00 at c = c_μ = F_μ(T),   L1 = a pe1 + (1 − a) pe0
        p   = (1 − φ̄)[(1 − ϕ̄) L00 + ϕ̄ L01] + φ̄ L1

    Parameters as in :func:`filters.binary.binary_loglik`; ``y`` is any array of
    received signals (e.g. (runs, K, S)); ``A`` and ``B`` have its shape.
    """
    y = np.asarray(y, dtype=np.float64)
    if not np.all(np.isfinite(y)):
        raise InputError("y must be finite (NaN measurements are not treated as missing)")
    pd = float(check_probability("dos_prob", dos_prob, open_upper=True))
    pv = float(check_probability("deception_prob", deception_prob, open_upper=True))
    a = float(check_probability("flip_prob", flip_prob, open_upper=True))
    for name, nz in (("channel_noise", channel_noise), ("deception", deception)):
        if not isinstance(nz, Noise) or nz.dim != 1:
            raise InputError(f"{name} must be a one-dimensional Noise distribution")
    c_mu = float(deception.cdf(np.array([float(threshold)])))
    pe1 = channel_noise.pdf((y - gain)[..., None])
    pe0 = channel_noise.pdf(y[..., None])
    base = pe1 * (1 - a) + pe0 * a
    slope = (2 * a - 1) * (pe1 - pe0)
    L01 = base + c_mu * slope
    L1 = a * pe1 + (1 - a) * pe0
    A = (1 - pd) * ((1 - pv) * base + pv * L01) + pd * L1
    B = (1 - pd) * (1 - pv) * slope
    return A, B


def packets_loglik(model: Model, x, k1: int, sensors, y, *, attack=None, log_clean: float = 0.0,
                   angles: Sequence = ()) -> np.ndarray:
    """One step's packet log-likelihood for particles ``x`` (R, M, n_x), evaluated by the kernels' code.

    ``sensors`` (P,), ``y`` (R, P, n_y) (or (R, n_y) for P = 1), ``attack`` (R, P) (or (R,));
    returns (R, M), a non-finite value as ``-inf`` (as the filter weighs it).  ``k1`` is
    the time of the measured state (``h(x, k1)``).  For tests and diagnostics: it runs
    the same generated code as :func:`sir_packets`.
    """
    model = _model(model)
    x = _particles(x, model.n_x, "x")
    R = x.shape[0]
    sens = np.asarray(sensors)
    sens = sens.reshape(1, -1) if sens.ndim <= 1 else sens
    yy = np.asarray(y, dtype=np.float64)
    yy = yy[:, None] if yy.ndim in (2, 3) else yy
    att = None if attack is None else np.asarray(attack, dtype=np.float64)[:, None]
    sens, yy, att, lc = _packet_data(model, R, sens, yy, att, log_clean)
    lik, ne = _packet_lik(model, _wrap_set(angles, model), bool(np.any(att > -np.inf)))
    rows = _drivers("packets")[1]
    out = np.empty(x.shape[:2])
    for r in range(R):
        rows(lik, sens.shape[1], ne, x[r], float(k1), (sens, yy[r], att[r], lc), out[r])
    return out


def binary_affine_loglik(model: Model, x, k1: int, A, B, *, threshold: float) -> np.ndarray:
    """One step's ``Σ_s log(A + B F_ν(T − h_s(x)))`` for particles ``x`` (R, M, n_x); ``A``, ``B`` (R, S).

    Returns (R, M) from the same generated code as :func:`sir_binary` (non-finite as ``-inf``).
    """
    model = _model(model)
    x = _particles(x, model.n_x, "x")
    R = x.shape[0]
    AA, BB, T = _binary_data(model, R, np.asarray(A, dtype=float)[:, None], np.asarray(B, dtype=float)[:, None],
                             threshold)
    lik = _binary_lik(model)
    rows = _drivers("binary")[1]
    out = np.empty(x.shape[:2])
    for r in range(R):
        rows(lik, 0, 0, x[r], float(k1), (AA[r], BB[r], T), out[r])
    return out
