"""The generic driver of the fused particle filters: one compiled call per Monte Carlo run.

A filter step, per **block** of ``BLOCK`` particles (the likelihood's scratch stays in the
L1 cache): propagate (``prop``, generated per model: :mod:`filters.fused.codegen`;
resampling is an ancestor index read by the propagation, no copy), weigh (``lik``,
generated per model and likelihood family), then over all particles the weights and the
weighted mean (``weigh``, generated per state dimension), the ESS and the log marginal
likelihood, and resampling (:mod:`filters.fused.resampling`).  The generated functions
reach the driver as numba first-class functions, so the driver is compiled once per
likelihood family (its data type) and a new model compiles only its own small functions;
both are cached on disk (:mod:`filters.fused.cache`).

Weights: the kernels never take a ``log`` per particle: a step's log-likelihood is kept as
``b + log s`` (the logs summed in ``b``, each log-sum-exp's remainder as a linear factor
``s >= 1``), and only a step that does not resample needs the log weights themselves.
A particle whose log-likelihood is not finite (NaN from an undefined measurement
function, ±inf) gets zero weight.  When *every* particle's weight vanishes at a step (a
**collapse**), the filter keeps the predicted particles with uniform weights, records the
event in ``collapsed`` and — since the estimate of ``p(z_k | z_1:k-1)`` is then zero —
sets the run's log marginal likelihood to ``-inf``; it resamples those uniform weights
when the step's rule asks (``ess_threshold`` 1: every step; below 1 never, the ESS being
``M``), as :func:`filters.particle.run_sir` does, so both engines draw the same numbers
through a collapse.  A weight below ``exp(-708)`` times the step's largest one counts as
zero (it changes no sum; libm would give a subnormal).

``linear_weights``: the NumPy engine's emulation of weights kept in linear double precision
(:func:`filters.particle.run_sir`): a particle whose normalised weight ``W_{k-1} p(z_k | x)``
underflows the smallest positive double (its log weight below the previous step's log
normaliser plus :data:`filters.particle.LOG_TINY`) gets zero weight, so a measurement far
from every particle collapses the run.  One comparison per particle (a ``log`` only for
those near the cut); the log-domain filter is the same code with the cut at ``-inf``.

Randomness: **one** :class:`numpy.random.Generator` **per run**, drawn from in a fixed
order (per step: the propagation's draws, then the resampler's uniforms), through its
stream (:mod:`filters.fused.streams`: the same numbers, drawn faster); a run's result
depends only on its own generator and data, never on how runs are split between
threads.  Nothing is allocated per particle and the GIL is released, so runs are spread
over ``threads`` threads (:func:`run_all`).  The input checks every family shares are
here too (:func:`check_particles`, :func:`check_generators`, :func:`check_options`).
"""
from __future__ import annotations

import itertools
import math
from typing import NamedTuple

import numpy as np
from numba.core import types

from designer.cores import kept_pool
from designer.model import Model
from designer.validation import InputError, check_int
from filters.particle import LOG_TINY, check_finite_means
from filters.resampling import SCHEMES, scheme_code
from filters.result import FilterResult, centralized_result

from .cache import njit
from .primitives import exp_nonpos, neginf_unless_finite
from .resampling import SCHEME_FUNCTIONS
from .streams import STREAM, drawing

__all__ = ["BLOCK", "FastSIRResult", "F1", "F2", "F3", "I1", "I2", "B1", "PROP_T", "WEIGH_T", "lik_type",
           "drivers", "resampler", "run_all", "spread", "likelihood_block", "loglik_rows", "covariance",
           "uniform_moments", "check_model",
           "check_particles", "check_generators", "check_options"]

#: Particles per block of a filter step: the likelihood's scratch stays in the L1 cache.
BLOCK = 128


class FastSIRResult(NamedTuple):
    """Per-run outputs of the fused filters (``R`` runs, ``K`` steps): the ``detail`` of their
    :class:`filters.result.FilterResult` (whose ``x[:, :, 0]`` is ``mean``, ``cov[:, :, 0]`` is ``cov``)."""

    mean: np.ndarray  # (R, K + 1, n_x) weighted means (k = 0: the initial particles)
    cov: np.ndarray | None  # (R, K + 1, n_x, n_x) when covariance=True
    ess: np.ndarray  # (R, K) effective sample size after weighting
    loglik: np.ndarray  # (R,) log marginal likelihood estimate log p(z_1:K); -inf after a collapse
    resampled: np.ndarray  # (R, K) bool
    collapsed: np.ndarray  # (R, K) bool: every particle's weight vanished at that step


@njit()
def likelihood_block(lik, P, ne, X, m0, n, k1, data, t, b, s, ex):
    """The log-likelihood of step ``t``'s data for particles ``m0 .. m0 + n − 1`` of ``X`` as ``b + log s``.

    ``lik(X, m0, n, k1, data, t, b, ex)`` (generated per model) adds each particle's
    sum of logs to ``b[m]`` and writes the ``ne`` log-sum-exp remainders ``<= 0`` of
    each of the ``P`` packets into the scratch ``ex`` (slot ``q = p ne + i`` of
    particle ``m0 + mm`` at ``q BLOCK + mm``).  Here, in loops over the block that
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
        q = p * ne * BLOCK
        e0 = ex[q:q + n]
        for i in range(n):
            e0[i] = exp_nonpos(e0[i])
        for j in range(1, ne):
            ej = ex[q + j * BLOCK:q + j * BLOCK + n]
            for i in range(n):
                e0[i] += exp_nonpos(ej[i])
        for i in range(n):
            sb[i] *= 1.0 + e0[i]
        if (p + 1) % G == 0 and p + 1 < P:
            for i in range(n):
                bb[i] += math.log(sb[i])
                sb[i] = 1.0


def loglik_rows(lik, P, ne, X, k1, data, out):
    """``out[m]`` = the log-likelihood of step 0 of ``data`` for every particle (for tests and diagnostics)."""
    M = X.shape[0]
    ex = np.empty(BLOCK * P * ne)
    s = np.empty(M)
    out[:] = 0.0
    for m0 in range(0, M, BLOCK):
        likelihood_block(lik, P, ne, X, m0, min(BLOCK, M - m0), k1, data, 0, out, s, ex)
    for m in range(M):
        out[m] = neginf_unless_finite(out[m] + math.log(s[m]))


@njit()
def covariance(x, W, scale, mean, cov):
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


@njit()
def uniform_moments(x, mean, cov, do_cov, W):
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
        covariance(x, W, 1.0 / M, mean, cov)


@njit(inline="always")
def _largest(v):
    """``max(v)`` (no NaN in ``v``, -inf if empty) over four running maxima: four chains, not one (the maximum is
    exact in any order)."""
    n = v.shape[0]
    m0 = m1 = m2 = m3 = -math.inf
    i = 0
    while i + 4 <= n:
        m0 = max(m0, v[i])
        m1 = max(m1, v[i + 1])
        m2 = max(m2, v[i + 2])
        m3 = max(m3, v[i + 3])
        i += 4
    while i < n:
        m0 = max(m0, v[i])
        i += 1
    return max(max(m0, m1), max(m2, m3))


@njit()
def _step(prop, lik, P, ne, X, anc, XN, t, rng, data, lw, fresh, floor, b, s, ex, buf):
    """Propagate every particle and weigh it with step ``t``'s data, block by block; returns the largest ``b``.

    ``prop(X, anc, XN, m0, n, k, rng, buf)`` (generated per model) writes ``f(X[anc[m]], k)
    + G w`` into ``XN[m]`` (resampling is the ancestor index ``anc``, no copy); it is
    called for the blocks in order, so a propagation that must draw the whole step's
    random numbers first (NumPy's order for switching modes or mixture noise, see
    :func:`propagation_predrawn`) does so into ``buf`` at its first block; the
    new log weight ``lw[m] + log p(y_t | XN[m])`` is left as ``b[m] + log s[m]`` (see
    :func:`likelihood_block`): ``s`` is a linear factor >= 1, no ``log`` is taken
    here, and a NaN or infinite one becomes ``b = -inf``, ``s = 0`` (zero weight), as does one whose log weight
    ``b + log s`` lies below ``floor`` (linear-domain weights; ``-inf`` otherwise: no particle is below it).
    Blocks of ``BLOCK`` particles keep the scratch ``ex`` small; separate loops keep
    few values live across the generator and libm calls (which clobber every
    floating-point register) and let the branch-free ones vectorise.
    """
    M = X.shape[0]
    k = float(t)
    best = -math.inf
    for m0 in range(0, M, BLOCK):
        n = min(BLOCK, M - m0)
        prop(X, anc, XN, m0, n, k, rng, buf)
        bb = b[m0:m0 + n]  # views indexed from 0 (see likelihood_block)
        sb = s[m0:m0 + n]
        for i in range(n):
            bb[i] = 0.0 if fresh else lw[m0 + i]
        likelihood_block(lik, P, ne, XN, m0, n, k + 1.0, data, t, b, s, ex)
        for i in range(n):
            v = bb[i]
            if not (v > -math.inf and v < math.inf and sb[i] == sb[i]):  # NaN (e.g. h undefined) or infinite
                sb[i] = 0.0  # zero weight
                bb[i] = -math.inf
            elif v < floor and v + math.log(sb[i]) < floor:  # its linear-domain weight underflows (s >= 1)
                sb[i] = 0.0
                bb[i] = -math.inf
        best = max(best, _largest(bb))
    return best


def _sir_run(prop, nd, lik, P, ne, weigh, data, x0, rng, resampler, ess_thr, lin, do_cov, mean, cov, ess, resampled,
             collapsed):
    """One Monte Carlo run of the bootstrap filter; returns its log marginal likelihood.

    ``nd``: random numbers per particle that ``prop`` draws ahead of each step into
    its scratch (0 for a propagation that draws as it goes).  ``lin``: linear-domain
    weights (see the module notes).

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
    ex = np.empty(BLOCK * P * ne)  # the likelihood's scratch (see likelihood_block)
    buf = np.empty(M * nd)  # the propagation's scratch (see _step)
    Mf = float(M)
    lnM = math.log(Mf)
    uniform_moments(x, mean[0], cov[0], do_cov, W)
    prev = lnM  # log Σ exp(lw) of the previous step's weights
    # lw is all zeros (start, or just resampled); a comparison, not the constant True, so that numba types
    # _step's argument as bool at once instead of compiling it for Literal[bool](True) first (a second signature)
    fresh = M > 0
    total = 0.0
    for k in range(K):
        mk = mean[k + 1]
        ck = cov[k + 1] if do_cov else cov[0]
        # linear-domain weights: W_{k-1} p(z_k | x) = exp(lw + ll - prev) is 0.0 below exp(LOG_TINY)
        floor = prev + LOG_TINY if lin else -math.inf
        best = _step(prop, lik, P, ne, x, anc, xn, k, rng, data, lw, fresh, floor, b, s, ex, buf)
        x, xn = xn, x
        if best == -math.inf:
            # Collapse: every weight vanished.  Keep the predicted particles, uniformly weighted (W = 1), and
            # resample them if the step's rule asks (ESS = M), as run_sir does: the same draws
            collapsed[k] = True
            total = -math.inf
            ess[k] = Mf
            uniform_moments(x, mk, ck, do_cov, W)
            for m in range(M):
                lw[m] = 0.0
                anc[m] = m
            if ess_thr >= 1.0 or Mf < ess_thr * Mf - 1e-9:
                resampler(W, 1.0 / Mf, rng, anc, cdf, u)
                resampled[k] = True
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
            covariance(x, W, inv, mk, ck)
        if ess_thr >= 1.0 or e < ess_thr * Mf - 1e-9:
            resampler(W, inv, rng, anc, cdf, u)
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


# The generated per-model functions reach the generic code as function pointers of these signatures (numba
# first-class function types), so that the generic code — _sir_run and what it calls — is compiled once per
# likelihood family (its data type), not once per model, wrap set and likelihood variant; and cached on disk.
F1, F2, F3 = types.float64[::1], types.float64[:, ::1], types.float64[:, :, ::1]
I1, I2, B1 = types.int64[::1], types.int64[:, ::1], types.boolean[::1]
PROP_T = types.FunctionType(types.void(F2, I1, F2, types.int64, types.int64, types.float64, STREAM, F1))
WEIGH_T = types.FunctionType(types.UniTuple(types.float64, 2)(F2, F1, F1, types.float64, F1, F1))
SCHEME_T = types.FunctionType(types.void(F1, types.float64, STREAM, I1, F1, F1))
_DRIVERS: dict = {}
_SCHEMES: dict = {}


def resampler(code: int):
    """The compiled resampling scheme of ``code`` (:data:`filters.fused.resampling.SCHEME_FUNCTIONS`) as a
    first-class function: compiled (or loaded from the cache) at its first use only."""
    if code not in _SCHEMES:
        fn = SCHEME_FUNCTIONS[code]
        fn.compile(SCHEME_T.signature)
        _SCHEMES[code] = types.CompileResultWAP(fn.overloads[tuple(SCHEME_T.signature.args)])
    return _SCHEMES[code]


def lik_type(data):
    """The function type of a likelihood ``lik(X, m0, n, k1, data, t, b, ex)`` of a family whose data has numba
    type ``data``."""
    return types.FunctionType(types.void(F2, types.int64, types.int64, types.float64, data, types.int64, F1, F1))


def _entry(fn, sig):
    disp = njit()(fn)
    disp.compile(sig)
    return disp.overloads[tuple(sig.args)].entry_point


def drivers(data, which: int = 0):
    """:func:`_sir_run` (``which`` 0) or :func:`loglik_rows` (1) compiled for a family's data type ``data``.

    Compiled at the first call per process, or loaded from the on-disk cache.  Returned
    as the compiled entry point, not a dispatcher: the argument types are fixed (the
    callers validate and allocate the arrays accordingly), so the dispatcher's type
    resolution at every call (about 50 µs with the function arguments, serial under the
    GIL) is skipped.
    """
    key = (data, which)
    if key not in _DRIVERS:
        lik, i8, f8 = lik_type(data), types.int64, types.float64
        if which == 0:
            bo = types.boolean
            sig = f8(PROP_T, i8, lik, i8, i8, WEIGH_T, data, F2, STREAM, SCHEME_T, f8, bo, bo, F2, F3, F1, B1, B1)
            _DRIVERS[key] = _entry(_sir_run, sig)
        else:
            _DRIVERS[key] = _entry(loglik_rows, types.void(lik, i8, i8, F2, f8, data, F1))
    return _DRIVERS[key]


def spread(one, R: int, threads: int) -> None:
    """``one(r)`` for every run ``r < R``, on ``threads`` threads (the kernels release the GIL).

    Each thread takes the next run until none is left (``itertools.count`` is atomic under
    the GIL): as balanced as one task per run on a busy machine, without a future per run.
    """
    if threads == 1 or R == 1:
        for r in range(R):
            one(r)
        return
    runs = itertools.count()

    def worker() -> None:
        for r in runs:
            if r >= R:
                return
            one(r)

    ex = kept_pool("particles", min(threads, R))  # its own pool: designer.cores.thread_pool's tasks may wait on it
    for f in [ex.submit(worker) for _ in range(min(threads, R))]:
        f.result()  # re-raise any exception from a worker


def run_all(data_type, kernels, data_of_run, x0, gens, K, scheme, thr, covariance, threads,
            uplinks: int, linear_weights: bool = False) -> FilterResult:
    """Every run of a family with data type ``data_type``, spread over ``threads`` threads.

    ``kernels = (prop, nd, lik, P, ne, weigh)`` of :func:`_sir_run`, ``data_of_run(r)`` run
    ``r``'s data, ``scheme`` the resampling scheme's code, ``linear_weights`` the emulation of
    linear-domain weights (see the module notes).  Returns the fusion centre's
    :class:`filters.result.FilterResult` (:func:`filters.result.centralized_result`: ``uplinks``
    messages per step; ``cov`` None unless ``covariance``), ``detail`` the :class:`FastSIRResult`.
    """
    run, scheme = drivers(data_type), resampler(scheme)
    lin = bool(linear_weights)
    R, M, n_x = x0.shape
    mean = np.empty((R, K + 1, n_x))
    cov = np.empty((R, K + 1, n_x, n_x)) if covariance else np.zeros((R, 1, 0, 0))
    ess = np.empty((R, K))
    resampled = np.zeros((R, K), dtype=np.bool_)
    collapsed = np.zeros((R, K), dtype=np.bool_)
    loglik = np.empty(R)

    def one(r: int) -> None:
        loglik[r] = drawing(gens[r], lambda st: run(*kernels, data_of_run(r), x0[r], st, scheme, thr, lin,
                                                    covariance, mean[r], cov[r], ess[r], resampled[r], collapsed[r]))

    spread(one, R, threads)
    cov = cov if covariance else None
    return centralized_result(check_finite_means(mean, "fused particle filter"), cov, uplinks,
                              FastSIRResult(mean, cov, ess, loglik, resampled, collapsed))._replace(ess=ess)


# ============================================================================ input checks
def check_model(model, *, inputs: bool = False, modes: bool = False) -> Model:
    """``model`` if it is a :class:`designer.Model` whose known inputs and switching modes the caller supports."""
    if not isinstance(model, Model):
        raise InputError(f"model must be a designer.Model, got {type(model).__name__}")
    if model.n_u and not inputs:
        raise InputError(f"model {model.name!r} has known inputs u; this fused filter supports models without inputs "
                         "(filters.fused.sir_sis takes them)")
    if model.n_modes and not modes:
        raise InputError(f"model {model.name!r} has switching modes; this fused filter supports models without modes "
                         "(filters.fused.sir_edpf draws them)")
    return model


def check_particles(x0, n_x: int, name: str = "x0") -> np.ndarray:
    try:
        x = np.asarray(x0, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be numeric: {exc}") from None
    if x.ndim != 3 or x.shape[2] != n_x or x.shape[0] < 1 or x.shape[1] < 1:
        raise InputError(f"{name} must have shape (runs, particles, {n_x}), got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise InputError(f"{name} must be finite (no NaN or inf particles)")
    return np.require(x, np.float64, ["C", "W"])  # the kernels' argument types: C-contiguous, writeable


def check_generators(rngs, R: int) -> list[np.random.Generator]:
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


def check_options(resampler, ess_threshold, threads, covariance) -> tuple[int, float, int, bool]:
    if not isinstance(resampler, str) or resampler not in SCHEMES:
        raise InputError(f"resampler must be one of {', '.join(SCHEMES)}, got {resampler!r}")
    if isinstance(ess_threshold, bool) or not isinstance(ess_threshold, (int, float, np.integer, np.floating)) \
            or not (0.0 < float(ess_threshold) <= 1.0):
        raise InputError(f"ess_threshold must lie in (0, 1], got {ess_threshold!r}")
    if not isinstance(covariance, (bool, np.bool_)):
        raise InputError(f"covariance must be True or False, got {covariance!r}")
    return scheme_code(resampler), float(ess_threshold), check_int("threads", threads, 1), bool(covariance)
