"""Sampling-importance-resampling engine over many Monte Carlo runs at once.

Particles have shape ``(runs, M, n_x)``; weights are kept in the log domain
(:class:`LogWeights`) and normalised with log-sum-exp.  A filter step is:
propagate through a proposal (the transition density by default), add
``log p(z | x) + log p(x | x_prev) - log q(x | x_prev, z)`` to the log weights,
accumulate the log marginal likelihood, report the weighted mean and covariance,
and resample (every step, or when ESS < ``ess_threshold * M``).

Numerics.  When every particle's likelihood of a run vanishes (all log weights
-inf, e.g. a measurement outside the support of every particle's density), the
weights stay finite: the run keeps its predicted particles with uniform weights
(resampled as any step, by the ESS rule: every step with ``ess_threshold`` 1, never below it)
and the step is recorded in ``SIRResult.collapsed``.  ``linear_weights=True``
emulates a filter that keeps weights in linear double precision (as the
published MATLAB-style implementations do): a weight ``W_{k-1} p(z | x)`` below
the smallest positive double becomes exactly zero, so a measurement that is far
from every particle collapses the run instead of being absorbed by the log-domain
normalisation (the fused kernels, :func:`filters.fused.sir_packets`, apply the same
rule).  Measurements with NaN are rejected unless ``missing="skip"``, which treats a
run's whole measurement at that step as missing (prediction only, recorded in
``SIRResult.skipped``).

A proposal is a callable ``proposal(x_prev, k, z_k, rng) -> (x, log_correction)``
with ``log_correction = log p(x | x_prev) - log q(x | x_prev, z_k)`` (zero for the
transition density).  A log-likelihood is ``loglik(x, k1, z_k) -> (runs, M)``.
"""
from __future__ import annotations

import time
from typing import Callable, NamedTuple, Sequence

import numpy as np
from designer.model import Model
from designer.noise import logsumexp
from designer.validation import InputError, NonFiniteError, check_int, check_rng

from .resampling import get_resampler
from .result import FilterResult, centralized_result

__all__ = ["LogWeights", "transition_proposal", "additive_noise_loglik", "SIRResult", "run_sir", "check_finite_means",
           "LOG_TINY", "effective_size", "DEGENERATE_ESS", "degenerate"]


def check_finite_means(mean: np.ndarray, engine: str) -> np.ndarray:
    """Raise :class:`~designer.validation.NonFiniteError` naming the first run and step whose filtered mean is
    not finite.

    ``mean`` (runs, K + 1, n_x), step 0 the initial particles.  Both particle engines call it:
    a NaN or an infinity in a filter's states or weights reaches its mean at the step it appears.
    """
    bad = ~np.isfinite(mean).all(axis=-1)
    if bad.any():
        r, k = map(int, np.argwhere(bad)[0])
        raise NonFiniteError(f"{engine}: the filtered mean of run {r} is not finite from step {k} on (particle "
                             "states or weights left finite numbers: check the model's f, h and noise densities)", r, k)
    return mean


def effective_size(W: np.ndarray) -> np.ndarray:
    """The effective sample size ``1 / Σ W²`` of normalised weights (..., M)."""
    return 1.0 / np.sum(W * W, axis=-1)


#: A particle filter whose typical effective sample size after weighting (the median over its runs of each run's
#: median over the steps) is below this many particles is degenerate: every step's weight sits on a handful of
#: particles and its estimate follows them, not the posterior (an assumption, chosen: the bootstrap filter with 500
#: particles on IEEE 14's 13 angles keeps 1.1 of them, its RMSE 14 x the EKF's; on a range-bearing target's 4 states
#: 320 of 500).  :func:`degenerate` says it.
DEGENERATE_ESS = 10.0


def degenerate(ess) -> tuple[float, bool] | None:
    """``(typical effective sample size, whether it is below DEGENERATE_ESS)`` of a particle filter's ``ess`` (runs,
    steps; NaN for a run not scored), or None when no run has one."""
    ess = np.asarray(ess, dtype=float)
    per_run = [np.median(e[np.isfinite(e)]) for e in ess.reshape(ess.shape[0], -1) if np.isfinite(e).any()]
    if not per_run:
        return None
    typical = float(np.median(per_run))
    return typical, typical < DEGENERATE_ESS


class LogWeights(NamedTuple):
    """Unnormalised log weights ``lw`` (..., M); NaN counts as -inf (zero weight)."""

    lw: np.ndarray

    @classmethod
    def of(cls, lw) -> "LogWeights":
        lw = np.asarray(lw, dtype=float)
        return cls(np.where(np.isnan(lw), -np.inf, lw))

    @property
    def log_norm(self) -> np.ndarray:
        """``log Σ exp(lw)`` over the particles."""
        return logsumexp(self.lw, axis=-1)

    @property
    def W(self) -> np.ndarray:
        """Normalised weights; a run whose weights all vanished gets uniform weights."""
        return self.normalised(self.log_norm)

    def normalised(self, ln: np.ndarray) -> np.ndarray:
        """:attr:`W` from the :attr:`log_norm` ``ln`` already computed."""
        dead = ~np.isfinite(ln)
        W = np.exp(self.lw - np.where(dead, 0.0, ln)[..., None])
        if np.any(dead):
            W[dead] = 1.0 / self.lw.shape[-1]
        off = np.abs(W.sum(axis=-1) - 1.0) > 1e-9  # log weights so large (|lw| ~ 1e308) that log_norm lost its digits
        if np.any(off):
            lw = self.lw[off]
            w = np.exp(lw - lw.max(axis=-1, keepdims=True))
            W[off] = w / w.sum(axis=-1, keepdims=True)
        return W

    @property
    def ess(self) -> np.ndarray:
        return effective_size(self.W)

    @property
    def log_mean(self) -> np.ndarray:
        """``log mean exp(lw)``: the step's contribution to the log marginal likelihood."""
        return self.log_norm - np.log(self.lw.shape[-1])


def transition_proposal(model: Model, inputs: np.ndarray | None = None) -> Callable:
    """The transition density of the model as the proposal (bootstrap filter)."""
    G = model.noise_gain

    def propose(x_prev, k, z_k, rng):
        shape = x_prev.shape[:-1]
        mode = rng.choice(model.n_modes, size=shape, p=model.mode_probs) if model.n_modes else None
        # inputs (K, n_u) for every run, or (runs, K, n_u): run r's for the particles x_prev[r]
        u = None if inputs is None or model.n_u == 0 else (inputs[k] if np.ndim(inputs) == 2 else inputs[:, k, None, :])
        x = model.f(x_prev, k, u, mode) + model.process_noise.sample(rng, shape) @ G.T
        return x, 0.0

    return propose


def additive_noise_loglik(model: Model) -> Callable:
    """``Σ_i log p_i(z_i - h_i(x))`` with each sensor's own noise density (any Noise, not only Gaussian)."""

    def loglik(x, k1, z_k):
        h = model.h_all(x, k1)
        total = 0.0
        for i, s in enumerate(model.sensors):
            a, b = model._offsets[i], model._offsets[i + 1]
            total = total + s.noise.logpdf(z_k[..., None, a:b] - h[..., a:b])
        return total

    return loglik


class SIRResult(NamedTuple):
    """The particle filter's own arrays, and where its time went: the ``detail`` of :func:`run_sir`'s result."""

    mean: np.ndarray  # (runs, K + 1, n_x) weighted means (k = 0: the prior sample)
    cov: np.ndarray  # (runs, K + 1, n_x, n_x)
    ess: np.ndarray  # (runs, K) effective sample size after weighting
    loglik: np.ndarray  # (runs,) log marginal likelihood estimate log p(z_1:K)
    resampled: np.ndarray  # (runs, K) bool
    collapsed: np.ndarray  # (runs, K) bool: every weight vanished; predicted particles kept, uniform weights
    skipped: np.ndarray  # (runs, K) bool: measurement missing (NaN) and skipped on request
    proposal_seconds: float  # wall time in the proposal's calls, all runs together (where the time goes)
    loglik_seconds: float  # wall time in the log-likelihood's calls, all runs together


#: log of the smallest positive (subnormal) double: ``exp(x) == 0.0`` below it (the cut of ``linear_weights``)
LOG_TINY = float(np.log(np.nextafter(0.0, 1.0)))


def _moments(x: np.ndarray, W: np.ndarray):
    mean = np.einsum("rm,rmn->rn", W, x)
    d = x - mean[:, None, :]
    cov = np.einsum("rm,rma,rmb->rab", W, d, d)
    return mean, cov


def _rng_blocks(rng, blocks, runs: int) -> tuple[list[np.random.Generator], list[slice]]:
    """The generators of :func:`run_sir` and the runs each drives (consecutive spans covering ``runs``)."""
    if isinstance(rng, np.random.Generator) or not isinstance(rng, (list, tuple)):
        if blocks is not None:
            raise InputError("blocks go with a sequence of generators (one per block)")
        return [check_rng(rng)], [slice(0, runs)]
    gens = [check_rng(g) for g in rng]
    sizes = [1] * len(gens) if blocks is None else [check_int("blocks", b, 1) for b in blocks]
    if len(sizes) != len(gens) or sum(sizes) != runs:
        raise InputError(f"blocks must give one size per generator ({len(gens)}) summing to the runs ({runs}), "
                         f"got {list(sizes)}")
    ends = np.cumsum(sizes)
    return gens, [slice(int(e - b), int(e)) for e, b in zip(ends, sizes)]


def run_sir(
    model: Model,
    z: np.ndarray,
    rng: np.random.Generator | Sequence[np.random.Generator],
    *,
    particles: int,
    runs: int | None = None,
    inputs: np.ndarray | None = None,
    loglik: Callable | None = None,
    proposal: Callable | None = None,
    resampler: str = "systematic",
    ess_threshold: float = 1.0,
    linear_weights: bool = False,
    missing: str = "reject",
    blocks=None,
    uplinks: int | None = None,
) -> FilterResult:
    """Run a SIR particle filter on every run's measurements at once.

    Parameters
    ----------
    z : ndarray, shape (runs, K, n_z) or (K, n_z)
        Measurements; ``z[..., k, :]`` measures ``x_{k+1}``.
    rng : numpy.random.Generator, or a sequence of them
        One generator for every run, or one per block of consecutive runs (``blocks``): block ``b`` draws
        from ``rng[b]`` what a call with its runs alone would draw, so the batch gives every block the
        numbers of its own call (many separately seeded filters in one batch).
    blocks : sequence of int, optional
        With a sequence of generators: the number of runs of each block (default: one run each).
    inputs : ndarray, shape (K, n_u) or (runs, K, n_u), optional
        Known inputs of the default (transition) proposal, shared or per run.
    particles : int
        Particles per run ``M``.
    ess_threshold : float in (0, 1]
        Resample when ESS < ``ess_threshold * M``; 1 resamples at every step.
    linear_weights : bool
        Emulate linear-domain weights: a normalised weight that underflows double
        precision becomes zero (see the module notes).  Default: log domain.
    missing : {"reject", "skip"}
        NaN in ``z``: raise (default) or skip that run's measurement at that step.
    uplinks : int, optional
        Messages per step the fusion centre receives (default: one per sensor of ``model``).

    Returns
    -------
    FilterResult
        The fusion centre's (:func:`filters.result.centralized_result`: the weighted means and covariances,
        ``uplinks`` messages per step, ``ess`` the effective sample size after each step's weighting), ``detail``
        the :class:`SIRResult` of the runs (with the seconds spent in the proposal and in the likelihood: where
        the time goes).
    """
    check_int("particles", particles, 1)
    if not (0.0 < ess_threshold <= 1.0):
        raise InputError(f"ess_threshold must lie in (0, 1], got {ess_threshold!r}")
    z = np.asarray(z, dtype=float)
    if z.ndim == 2:
        z = np.broadcast_to(z, (runs or 1,) + z.shape)
    width = model.n_z if loglik is None else z.shape[-1]  # a custom likelihood defines what a measurement is
    if z.ndim != 3 or z.shape[-1] != width:
        raise InputError(f"z must have shape (runs, K, {width}) or (K, {width}), got {z.shape}")
    if runs is not None and z.shape[0] != runs:
        raise InputError(f"z has {z.shape[0]} runs, expected {runs}")
    if missing not in ("reject", "skip"):
        raise InputError(f"missing must be 'reject' or 'skip', got {missing!r}")
    nan_rows = np.isnan(z).any(axis=-1)  # (runs, K)
    if missing == "reject" and nan_rows.any():
        r, k = map(int, np.argwhere(nan_rows)[0])
        raise InputError(f"z has NaN (first at run {r}, step {k}); pass missing='skip' to treat it as missing")
    R, K = z.shape[0], z.shape[1]
    M = int(particles)
    resample = get_resampler(resampler)
    loglik = additive_noise_loglik(model) if loglik is None else loglik
    gens, spans = _rng_blocks(rng, blocks, R)
    if inputs is not None and np.ndim(inputs) == 3 and np.shape(inputs)[0] != R:
        raise InputError(f"inputs must have shape (K, n_u) or ({R}, K, n_u), got {np.shape(inputs)}")
    props = [transition_proposal(model, inputs if np.ndim(inputs) != 3 else np.asarray(inputs)[sl])
             if proposal is None else proposal for sl in spans]

    def draw(sample):  # sample(generator, span) for every block, stacked over the runs
        parts = [sample(g, sl) for g, sl in zip(gens, spans)]
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    x = draw(lambda g, sl: model.prior.sample(g, (sl.stop - sl.start, M)))
    lw = LogWeights.of(np.zeros((R, M)))
    mean = np.empty((R, K + 1, model.n_x))
    cov = np.empty((R, K + 1, model.n_x, model.n_x))
    ess = np.empty((R, K))
    did = np.zeros((R, K), dtype=bool)
    collapsed = np.zeros((R, K), dtype=bool)
    total = np.zeros(R)
    spent = [0.0, 0.0]  # seconds in the proposal, in the likelihood
    mean[:, 0], cov[:, 0] = _moments(x, lw.W)
    for k in range(K):
        zk = np.where(nan_rows[:, k, None], 0.0, z[:, k])  # skipped rows get a placeholder, then no weight
        t = time.perf_counter()
        moved = [p(x[sl], k, zk[sl], g) for p, g, sl in zip(props, gens, spans)]
        spent[0] += time.perf_counter() - t
        x = moved[0][0] if len(moved) == 1 else np.concatenate([mv[0] for mv in moved])
        corr = moved[0][1] if len(moved) == 1 or all(np.ndim(mv[1]) == 0 and mv[1] == 0 for mv in moved) else \
            np.concatenate([np.broadcast_to(mv[1], (sl.stop - sl.start, M)) for mv, sl in zip(moved, spans)])
        prev_log_norm = lw.log_norm
        if not np.isfinite(x).all():
            r = int(np.flatnonzero(~np.isfinite(x).all(axis=(1, 2)))[0])
            raise NonFiniteError(f"particle filter: run {r} has particle states that are not finite at step {k + 1}",
                                 r, k + 1)
        t = time.perf_counter()
        ll = loglik(x, k + 1, zk)
        spent[1] += time.perf_counter() - t
        ll = np.where(nan_rows[:, k, None], 0.0, ll)
        if np.isposinf(ll).any():
            r = int(np.flatnonzero(np.isposinf(ll).any(axis=-1))[0])
            raise NonFiniteError(f"particle filter: run {r} has a log-likelihood of +inf (a density evaluated at a "
                                 f"singularity) at step {k + 1}", r, k + 1)
        new = LogWeights.of(lw.lw + ll + corr).lw
        if linear_weights:
            new = np.where(new - prev_log_norm[:, None] < LOG_TINY, -np.inf, new)
        dead = np.isneginf(new).all(axis=-1)
        if np.any(dead):
            collapsed[dead, k] = True
            new[dead] = 0.0  # predicted particles, uniform weights; contributes nothing to the likelihood
        lw = LogWeights(new)
        # p(z_k | z_1:k-1) = Σ W_{k-1} w_k: the change of the log normaliser (-inf on a collapse).
        ln = lw.log_norm
        total += np.where(dead, -np.inf, ln - prev_log_norm)
        W = lw.normalised(ln)  # (each computed once per step)
        mean[:, k + 1], cov[:, k + 1] = _moments(x, W)
        ess[:, k] = effective_size(W)
        need = ess[:, k] < ess_threshold * M - 1e-9 if ess_threshold < 1.0 else np.ones(R, dtype=bool)
        if np.any(need):
            for g, sl in zip(gens, spans):  # each block from its own generator (x[sl] is a view)
                nb, xb = need[sl], x[sl]
                if np.any(nb):
                    idx = resample(W[sl][nb], M, g)
                    xb[nb] = np.take_along_axis(xb[nb], idx[..., None], axis=1)
            new = lw.lw.copy()
            new[need] = 0.0
            lw = LogWeights(new)
            did[:, k] = need
    return centralized_result(mean, cov, model.n_sensors if uplinks is None else uplinks,
                              SIRResult(mean, cov, ess, total, did, collapsed, nan_rows.copy(), *spent)
                              )._replace(ess=ess)
