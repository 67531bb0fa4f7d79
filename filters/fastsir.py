"""Fused, JIT-compiled bootstrap particle filters over many Monte Carlo runs.

The NumPy engine (:func:`filters.particle.run_sir`) runs every Monte Carlo run at
once as arrays of shape ``(runs, M, n_x)``, one NumPy call per operation.  This
module runs the same bootstrap filter with one compiled kernel call per run.
For each model it generates, from the model's CasADi functions
(:func:`designer.jit.scalar_statements`, the instruction walk of
:mod:`designer.jit`), two straight-line scalar functions compiled with
``numba.njit(nogil=True)``: the propagation of one particle (``f`` plus the
process noise ``G (mean + L z)``, with ``G L`` inlined as constants) and the
log-likelihood of one packet (``h_s``, residual, angle wrapping and the noise
density with its constants inlined).  A generic kernel loops over steps and
particles around them: propagate (resampling is an ancestor index read by the
propagation, no copy), weigh in the log domain (log-sum-exp), record the
weighted mean (and covariance if asked), the ESS and the log marginal
likelihood, resample.  Nothing is allocated per particle and the GIL is
released, so runs are spread over ``workers`` threads
(:class:`concurrent.futures.ThreadPoolExecutor`).  The generated functions are
cached per model (and wrap set); numba compiles them, and the kernel specialised
on them, at the first call (a few seconds per model and process).

Randomness: **one** :class:`numpy.random.Generator` **per run**, drawn from in
a fixed order (per step: ``n_w`` standard normals per particle, particle after
particle; then the resampler's uniforms).  A run's result depends only on its
own generator and data, never on how runs are split between threads.  numba's
``Generator.standard_normal`` and ``Generator.random`` reproduce NumPy's
streams bit for bit and that order is the NumPy engine's, so a one-run call
reproduces ``run_sir(..., runs=1)`` with the same generator to rounding
(given the same initial particles; the tests check it).

Initial particles are sampled by the caller (``x0``, shape ``(runs, M, n_x)``,
e.g. ``model.prior.sample(rngs[r], M)`` for each run), so any prior works.

Two likelihood families:

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

Numerics: log weights only.  A particle whose log-likelihood is not finite (NaN
from an undefined measurement function, ±inf) gets zero weight.  When *every*
particle's weight vanishes at a step (a **collapse**), the filter keeps the
predicted particles with uniform weights, does not resample at that step,
records the event in ``collapsed`` and — since the estimate of ``p(z_k | z_1:k-1)``
is then zero — sets the run's log marginal likelihood to ``-inf``.

Limitations: models without known inputs and without switching modes
(:func:`designer.jit.jit_model`); Gaussian process noise (any ``noise_gain``);
Gaussian or Gaussian-mixture measurement noise.
"""
from __future__ import annotations

import itertools
import math
import weakref
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple, Sequence

import numba
import numpy as np

from designer.jit import compile_source, jit_model, scalar_statements
from designer.model import Model
from designer.noise import Gaussian, GaussianMixture, Noise
from designer.validation import InputError, check_int, check_probability

__all__ = [
    "FastSIRResult", "RESAMPLER_CODES", "sir_packets", "sir_binary", "deception_terms", "binary_coefficients",
    "packets_loglik", "binary_affine_loglik",
]

_NJIT = dict(nogil=True, cache=False, error_model="numpy")
# Generated kernels may fuse a * b + c into one FMA (rounding only; no effect on inf/NaN handling).
_FAST = {"contract"}
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


@numba.njit(**dict(_NJIT, inline="always"))
def _exp0(d):
    """``exp(d)`` for ``d <= 0``: exactly 0 below -745.2 (where exp rounds to 0) without calling libm's slow
    underflow path; NaN stays NaN."""
    return 0.0 if d < -745.2 else math.exp(d)


@numba.njit(**dict(_NJIT, inline="always"))
def _neginf_unless_finite(v):
    return v if (v > -math.inf and v < math.inf) else -math.inf


@numba.njit(**_NJIT)
def _packets_loglik_rows(term, ne, X, k1, data, out):
    """``out[m]`` = the packet log-likelihood of step 0 of ``data`` for every particle (helper, not the kernel)."""
    sens, y, att, log_clean = data
    ex = np.empty(ne)
    for m in range(X.shape[0]):
        total = 0.0
        for p in range(sens.shape[1]):
            mx = term(sens[0, p], X, m, k1, y, 0, p, log_clean, att[0, p], ex, 0)
            acc = 1.0
            for i in range(ne):
                acc += _exp0(ex[i])
            total += mx + math.log(acc)
        out[m] = _neginf_unless_finite(total)


@numba.njit(**_NJIT)
def _binary_loglik_rows(one, X, k1, data, out):
    A, B, T = data
    for m in range(X.shape[0]):
        out[m] = _neginf_unless_finite(one(X, m, k1, A, B, 0, T))


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
def _systematic(W, scale, u0, idx):
    """Systematic resampling, ``u_m = (m + u0) / M``: the indices of ``_cumsum_to_one`` + ``_inverse_cdf``.

    One merged pass over the cumulative weights (no cdf or u arrays): particle ``i``
    gets the ``m`` with ``cdf[i-1] <= u_m < cdf[i]``.
    """
    M = idx.shape[0]
    N = W.shape[0]
    Mf = float(M)
    acc = 0.0
    m = 0
    for i in range(N):
        acc += W[i] * scale
        c = acc if i < N - 1 else 1.0  # the last bin forced to 1, as _cumsum_to_one
        while m < M and (m + u0) / Mf < c:
            idx[m] = i
            m += 1
    while m < M:  # only if u_m >= 1 to rounding (never): as _inverse_cdf, the last particle
        idx[m] = N - 1
        m += 1


@numba.njit(**_NJIT)
def _resample(scheme, W, scale, rng, idx, cdf, u):
    """Indices from the weights ``W * scale`` (normalised): the schemes of filters.resampling, same draws."""
    M = idx.shape[0]
    Mf = float(M)
    if scheme == 0:  # systematic: one uniform shared by all strata
        _systematic(W, scale, rng.random(), idx)
        return
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
            ur = np.sort(rng.random(rest))
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
        u.sort()
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
def _sir_run(stepper, weigh, data, x0, rng, scheme, ess_thr, do_cov, mean, cov, ess, resampled, collapsed):
    """One Monte Carlo run of the bootstrap filter; returns its log marginal likelihood.

    ``stepper(x, anc, xn, k, rng, data, lw, fresh, b, s)`` (generated per model and
    likelihood) writes ``f(x[anc[m]], k) + G w`` of every particle into ``xn``
    (resampling is the ancestor index ``anc``, no copy) and its new log weight
    ``lw[m] + log p(y_k | xn[m])`` as ``b[m] + log s[m]`` — ``b`` a sum of logs, ``s``
    a linear factor in [1, ...) (the log-sum-exp remainders, not logged: ``-inf`` and
    0 for a zero weight) — and returns the largest ``b``.  ``weigh(x, b, s, best, W,
    mean)`` (generated per model) sets ``W = exp(b - best) s`` and the weighted mean
    and returns ``(Σ W, Σ W²)``.  Only a step that does not resample needs the log
    weights themselves (one ``log`` per particle).
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
    u = np.empty(M)
    Mf = float(M)
    lnM = math.log(Mf)
    _uniform_moments(x, mean[0], cov[0], do_cov, W)
    prev = lnM  # log Σ exp(lw) of the previous step's weights
    fresh = True  # lw is all zeros (start, or just resampled)
    total = 0.0
    for k in range(K):
        mk = mean[k + 1]
        ck = cov[k + 1] if do_cov else cov[0]
        best = stepper(x, anc, xn, k, rng, data, lw, fresh, b, s)
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


# ============================================================================ generated per-model code
_KERNELS: "weakref.WeakKeyDictionary[Model, dict]" = weakref.WeakKeyDictionary()
_NS = {"_ndtr": _ndtr, "_exp0": _exp0, "_finite": _neginf_unless_finite}
#: Particles per block of the packet stepper: propagation and log terms, then the block's exps (L1-resident).
_BLOCK = 128


def _kernels(model: Model) -> dict:
    d = _KERNELS.get(model)
    if d is None:
        d = _KERNELS[model] = {}
    return d


def _c(v: float) -> str:
    return repr(float(v))


def _prop_one(model: Model):
    """``prop_one(X, a, XN, m, k, rng)``: ``XN[m] = f(X[a], k) + G (mean + L z)``, z ~ N(0, I) (NumPy's order)."""
    cache = _kernels(model)
    if "prop" in cache:
        return cache["prop"]
    noise = model.process_noise
    if not isinstance(noise, Gaussian):
        raise InputError(f"process_noise of model {model.name!r} is {type(noise).__name__}; "
                         "the fused kernels need Gaussian process noise")
    G = model.noise_gain
    gm, GL = G @ noise.mean, G @ noise._chol
    n_x, n_w = model.n_x, GL.shape[1]
    lines = ["def prop_one(X, a, XN, m, k, rng):"]
    lines += scalar_statements(model.casadi_f, ["X[a, {}]", "k", None, None], "f{}")
    lines += [f"    z{j} = rng.standard_normal()" for j in range(n_w)]  # one particle's n_w normals in a row
    for i in range(n_x):
        terms = [f"{_c(GL[i, j])} * z{j}" for j in range(n_w) if GL[i, j] != 0.0]
        lines.append(f"    XN[m, {i}] = f{i} + ({_c(gm[i])} + ({' + '.join(terms) if terms else '0.0'}))")
    cache["prop"] = compile_source("\n".join(lines), "prop_one", f"the propagation of {model.name!r}", _NS,
                                   inline="always", fastmath=_FAST)
    return cache["prop"]


def _weigh(model: Model):
    """``weigh(x, b, s, best, W, mean) -> (Σ W, Σ W²)``: ``W = exp(b - best) s`` and the weighted mean.

    Generated per state dimension so that the mean's sums are local scalars.
    """
    cache = _kernels(model)
    if "weigh" in cache:
        return cache["weigh"]
    n = model.n_x
    lines = ["def weigh(x, b, s, best, W, mean):", "    acc = 0.0", "    s2 = 0.0"]
    lines += [f"    a{i} = 0.0" for i in range(n)]
    lines += ["    for m in range(x.shape[0]):", "        e = _exp0(b[m] - best) * s[m]", "        W[m] = e",
              "        acc += e", "        s2 += e * e"]
    lines += [f"        a{i} += e * x[m, {i}]" for i in range(n)]
    lines.append("    inv = 1.0 / acc")
    lines += [f"    mean[{i}] = a{i} * inv" for i in range(n)]
    lines.append("    return acc, s2")
    cache["weigh"] = compile_source("\n".join(lines), "weigh", f"the weights of {model.name!r}", _NS, fastmath=_FAST)
    return cache["weigh"]


# One step of every particle: propagate, then the step's log-likelihood as b[m] + log s[m] (see _sir_run).
_STEPPER = {
    # Per block of particles, three loops: propagate; each packet's largest log term (into b) and the others
    # relative to it (into ex, NE per packet); the block's exps, s[m] = Π_p (1 + Σ exp(ex)), with no log:
    # the log-sum-exp of each packet is b + log s.  Split loops keep fewer values live across the libm and
    # generator calls (which clobber every floating-point register) and let the calls of many particles
    # overlap instead of waiting on each particle's chain of h, residual and log terms.
    "packets": """
def stepper(X, anc, XN, step, rng, data, lw, fresh, b, s):
    sens, y, att, log_clean = data
    P = sens.shape[1]
    k = float(step)
    k1 = k + 1.0
    M = X.shape[0]
    ex = _np.empty(BLOCK * P * NE)
    best = -_m.inf
    for m0 in range(0, M, BLOCK):
        m1 = min(m0 + BLOCK, M)
        j = 0
        for m in range(m0, m1):
            PROP(X, anc[m], XN, m, k, rng)
        for m in range(m0, m1):
            v = 0.0 if fresh else lw[m]
            for p in range(P):
                v += LIK(sens[step, p], XN, m, k1, y, step, p, log_clean, att[step, p], ex, j)
                j += NE
            b[m] = v
        j = 0
        for m in range(m0, m1):
            v = b[m]
            sm = 1.0
            for p in range(P):
                acc = 1.0
                for i in range(NE):
                    acc += _exp0(ex[j + i])
                j += NE
                sm *= acc
                if sm > 1e250:  # many packets: fold the factor into the log part
                    v += _m.log(sm)
                    sm = 1.0
            if v > -_m.inf and v < _m.inf and sm == sm:
                b[m] = v
                s[m] = sm
                best = v if v > best else best
            else:  # NaN (e.g. h undefined) or infinite: zero weight
                b[m] = -_m.inf
                s[m] = 0.0
    return best
""",
    "binary": """
def stepper(X, anc, XN, step, rng, data, lw, fresh, b, s):
    A, B, T = data
    k = float(step)
    k1 = k + 1.0
    best = -_m.inf
    for m in range(X.shape[0]):
        PROP(X, anc[m], XN, m, k, rng)
        v = LIK(XN, m, k1, A, B, step, T)
        v = _finite(v if fresh else lw[m] + v)
        b[m] = v
        s[m] = 1.0 if v > -_m.inf else 0.0
        best = v if v > best else best
    return best
""",
}


def _stepper(model: Model, family: str, lik, ne: int = 0):
    cache = _kernels(model)
    key = ("stepper", family, lik)
    if key not in cache:
        ns = dict(_NS, PROP=_prop_one(model), LIK=lik, BLOCK=_BLOCK, NE=ne)
        src = _STEPPER[family].replace("BLOCK", str(_BLOCK)).replace("NE", str(ne))
        cache[key] = compile_source(src, "stepper", f"the {family} filter step of {model.name!r}", ns,
                                    fastmath=_FAST)
    return cache[key]


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
    """Statements returning ``mx = max(terms)`` and writing the others minus it into ``ex[j:j + ne]``.

    ``log Σ exp(terms) = mx + log(1 + Σ exp(ex))``.  The maximum is kept by selects
    (no data-dependent branch); the slots past ``len(terms) - 1`` get ``-inf``.  A
    NaN term ends up in ``mx`` or in a slot, so the packet's likelihood is NaN
    (zero weight) as with ``logaddexp``; all terms ``-inf`` give ``mx = -inf``.
    """
    out = [f"{indent}mx = {terms[0]}"]
    for i, t in enumerate(terms[1:]):
        out += [f"{indent}u = {t}", f"{indent}o{i} = mx if u > mx else u", f"{indent}mx = u if u > mx else mx"]
    out += [f"{indent}ex[j + {i}] = o{i} - mx" for i in range(len(terms) - 1)]
    out += [f"{indent}ex[j + {i}] = -_m.inf" for i in range(len(terms) - 1, ne)]
    out.append(f"{indent}return mx")
    return out


def _packet_term(model: Model, wrap: tuple, attacked: bool):
    """``(term, NE)``: ``term(s, X, m, k, Y, t, p, lc, a, ex, j) -> mx`` with, for ``r = wrap(Y[t, p] − h_s(X[m], k))``,

        logaddexp(lc + log p_ν_s(r), a) = mx + log(1 + Σ_{i < NE} exp(ex[j + i]))

    the log-sum-exp over ``lc +`` each mixture component's log term and ``a``, split
    into its largest term and the others relative to it (no ``exp`` or ``log``
    here).  Model, noise constants and the wrapping are inlined (generated per
    model, wrap set and ``attacked``); ``NE`` is the largest number of components
    of a sensor, less one unless ``attacked``.  ``attacked=False`` leaves ``a`` out
    (for ``a = -inf`` everywhere: one slot and its test fewer per packet).
    """
    cache = _kernels(model)
    key = ("packet", wrap, attacked)
    if key in cache:
        return cache[key]
    comps = [_components(sensor.noise, f"model.sensors[{s}]") for s, sensor in enumerate(model.sensors)]
    ne = max(len(c) for c in comps) - (0 if attacked else 1)  # the terms less the largest
    lines = ["def term(s, X, m, k, Y, t, p, lc, a, ex, j):"]
    for s, (sensor, fun) in enumerate(zip(model.sensors, model.casadi_h)):
        lines.append(f"    {'if' if s == 0 else 'elif'} s == {s}:")
        ind = "        "
        lines += scalar_statements(fun, ["X[m, {}]", "k"], "h{}", indent=ind)
        r = []
        for j in range(sensor.dim):
            lines.append(f"{ind}r{j} = Y[t, p, {j}] - h{j}")
            if (s, j) in wrap:  # into (-pi, pi] as filters.rrp.wrap_angles (a no-op inside, to rounding)
                pi, tau = _c(np.pi), _c(2 * np.pi)
                lines.append(f"{ind}if not (-{pi} < r{j} <= {pi}): r{j} = {pi} - (({pi} - r{j}) % {tau})")
            r.append(f"r{j}")
        lines += _component_lines(comps[s], r, ind)
        terms = [f"lc + t{c}" for c in range(len(comps[s]))] + (["a"] if attacked else [])
        lines += _max_others_lines(terms, ne, ind)
    lines += [f"    for i in range({ne}):", "        ex[j + i] = _m.nan", "    return _m.nan"]
    src = "\n".join(lines)
    term = compile_source(src, "term", f"the packet likelihood of {model.name!r}", _NS, inline="always",
                          fastmath=_FAST)
    cache[key] = term, ne
    return cache[key]


def _binary_one(model: Model):
    """``one(X, m, k, A, B, t, T) = Σ_s log(A[t, s] + B[t, s] F_ν_s(T − h_s(X[m], k)))``, inlined."""
    cache = _kernels(model)
    if "binary" in cache:
        return cache["binary"]
    if any(d != 1 for d in model.sensor_dims):
        raise InputError("sir_binary needs scalar sensors (every sensor of dimension 1)")
    lines = ["def one(X, m, k, A, B, t, T):"]
    lines += scalar_statements(model.casadi_h_all, ["X[m, {}]", "k"], "h{}")
    lines.append("    total = 0.0")
    for s, sensor in enumerate(model.sensors):
        nz = sensor.noise
        lines.append(f"    u = T - h{s}")
        if isinstance(nz, Gaussian):  # Gaussian.cdf: ndtr((x - mean) / sd)
            c = f"_ndtr((u - {_c(nz.mean[0])}) / {_c(np.sqrt(nz.cov[0, 0]))})"
        elif isinstance(nz, GaussianMixture):  # sum of w * component cdf
            c = " + ".join(f"{_c(w)} * _ndtr((u - {_c(g.mean[0])}) / {_c(np.sqrt(g.cov[0, 0]))})"
                           for w, g in zip(nz.weights, nz.components))
        else:
            raise InputError(f"model.sensors[{s}] noise is {type(nz).__name__}; the fused kernels support Gaussian "
                             "and GaussianMixture")
        lines.append(f"    total += _m.log(A[t, {s}] + B[t, {s}] * ({c}))")
    lines.append("    return total")
    src = "\n".join(lines)
    cache["binary"] = compile_source(src, "one", f"the binary likelihood of {model.name!r}", _NS, inline="always",
                                     fastmath=_FAST)
    return cache["binary"]


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
    return np.ascontiguousarray(x)


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


def _options(resampler, ess_threshold, workers, covariance) -> tuple[int, float, int, bool]:
    if not isinstance(resampler, str) or resampler not in RESAMPLER_CODES:
        raise InputError(f"resampler must be one of {', '.join(RESAMPLER_CODES)}, got {resampler!r}")
    if isinstance(ess_threshold, bool) or not isinstance(ess_threshold, (int, float, np.integer, np.floating)) \
            or not (0.0 < float(ess_threshold) <= 1.0):
        raise InputError(f"ess_threshold must lie in (0, 1], got {ess_threshold!r}")
    if not isinstance(covariance, (bool, np.bool_)):
        raise InputError(f"covariance must be True or False, got {covariance!r}")
    return RESAMPLER_CODES[resampler], float(ess_threshold), check_int("workers", workers, 1), bool(covariance)


def _wrap_set(angles, model: Model) -> tuple:
    S, dims = model.n_sensors, model.sensor_dims
    if isinstance(angles, (str, bytes)):
        raise InputError("angles must be a sequence of component indices or (sensor, component) pairs")
    try:
        items = list(angles)
    except TypeError:
        raise InputError("angles must be a sequence of component indices or (sensor, component) pairs") from None
    out = set()

    def is_int(v):
        return isinstance(v, (int, np.integer)) and not isinstance(v, bool)

    for a in items:
        if is_int(a):
            pairs = [(s, int(a)) for s in range(S)]
        elif isinstance(a, (tuple, list)) and len(a) == 2 and all(is_int(v) for v in a):
            pairs = [(int(a[0]), int(a[1]))]
        else:
            raise InputError(f"angles must hold component indices or (sensor, component) pairs, got {a!r}")
        for s, j in pairs:
            if not (0 <= s < S) or not (0 <= j < dims[s]):
                raise InputError(f"angles entry {a!r} is out of range (sensors 0..{S - 1}, and each sensor's "
                                 "components)")
            out.add((s, j))
    return tuple(sorted(out))


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
    sens = np.ascontiguousarray(sens, dtype=np.int64)
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
        att = np.ascontiguousarray(att)
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
        arrs.append(np.ascontiguousarray(a))
    if arrs[0].shape != arrs[1].shape:
        raise InputError(f"A and B must have the same shape, got {arrs[0].shape} and {arrs[1].shape}")
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float, np.integer, np.floating)) \
            or not np.isfinite(threshold):
        raise InputError(f"threshold must be a finite number, got {threshold!r}")
    return arrs[0], arrs[1], float(threshold)


# ============================================================================ driver
def _run_all(stepper, weigh, data_of_run, x0, gens, K, scheme, thr, covariance, workers) -> FastSIRResult:
    R, M, n_x = x0.shape
    mean = np.empty((R, K + 1, n_x))
    cov = np.empty((R, K + 1, n_x, n_x)) if covariance else np.zeros((R, 1, 0, 0))
    ess = np.empty((R, K))
    resampled = np.zeros((R, K), dtype=np.bool_)
    collapsed = np.zeros((R, K), dtype=np.bool_)
    loglik = np.empty(R)

    def one(r: int) -> None:
        loglik[r] = _sir_run(stepper, weigh, data_of_run(r), x0[r], gens[r], scheme, thr, covariance, mean[r], cov[r],
                             ess[r], resampled[r], collapsed[r])

    if workers == 1 or R == 1:
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

        with ThreadPoolExecutor(max_workers=min(workers, R)) as ex:
            for f in [ex.submit(worker) for _ in range(min(workers, R))]:
                f.result()  # re-raise any exception from a worker
    return FastSIRResult(mean, cov if covariance else None, ess, loglik, resampled, collapsed)


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
    workers: int = 1,
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
        sensor) or ``(sensor, component)`` pairs (as a scenario's
        ``extras["angle_components"]``).
    resampler : {'systematic', 'stratified', 'multinomial', 'residual'}
    ess_threshold : float in (0, 1]
        Resample when ESS < ``ess_threshold * M``; 1 resamples at every step.
    covariance : bool
        Also return the weighted covariance at every step.
    workers : int
        Threads the runs are spread over (the results do not depend on it).

    Returns
    -------
    FastSIRResult
    """
    model = _model(model)
    x0 = _particles(x0, model.n_x)
    R = x0.shape[0]
    gens = _generators(rngs, R)
    scheme, thr, workers, covariance = _options(resampler, ess_threshold, workers, covariance)
    sens, yy, att, lc = _packet_data(model, R, sensors, y, attack, log_clean)
    term, ne = _packet_term(model, _wrap_set(angles, model), bool(np.any(att > -np.inf)))
    stepper = _stepper(model, "packets", term, ne)
    return _run_all(stepper, _weigh(model), lambda r: (sens, yy[r], att[r], lc), x0, gens, sens.shape[0], scheme, thr, covariance,
                    workers)


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
    workers: int = 1,
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
    scheme, thr, workers, covariance = _options(resampler, ess_threshold, workers, covariance)
    AA, BB, T = _binary_data(model, R, A, B, threshold)
    stepper = _stepper(model, "binary", _binary_one(model))
    return _run_all(stepper, _weigh(model), lambda r: (AA[r], BB[r], T), x0, gens, AA.shape[1], scheme, thr, covariance, workers)


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
    term, ne = _packet_term(model, _wrap_set(angles, model), bool(np.any(att > -np.inf)))
    out = np.empty(x.shape[:2])
    for r in range(R):
        _packets_loglik_rows(term, ne, x[r], float(k1), (sens, yy[r], att[r], lc), out[r])
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
    lik = _binary_one(model)
    out = np.empty(x.shape[:2])
    for r in range(R):
        _binary_loglik_rows(lik, x[r], float(k1), (AA[r], BB[r], T), out[r])
    return out
