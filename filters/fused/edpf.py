"""Seed 001's filters (PPF, PF-RSN, PF-SR-DE) on the fused kernels (the NumPy twin: :mod:`filters.edpf`).

The NumPy versions are :func:`filters.edpf.interval_loglik` (PPF and PF-RSN, (13)-(15))
and :func:`filters.edpf.raw_loglik` (PF-SR-DE) with :func:`filters.particle.run_sir`
and the transition density as the proposal.  Here the same filters run with
:mod:`filters.fused.driver`'s generic kernel (one compiled call per run, runs over
threads, weights as ``b + log s``, systematic or other resampling, collapse
handling) and two generated, per-model pieces:

* the propagation of a model with **switching modes** and/or **Gaussian-mixture
  process noise** (:func:`filters.fused.codegen.propagation_predrawn`): per step, ``M``
  uniforms for the modes, ``M`` for the mixture's components, then ``M n_w``
  normals — :func:`filters.particle.transition_proposal`'s order (``choice`` with
  the mode probabilities, then ``GaussianMixture.sample``);
* the likelihood (family ``"edpf"``, data ``(Z, A)``: the decrypted values and the
  availabilities α_s of step ``t``, shape ``(K, N)`` per run), with every sensor's
  truncated-Gaussian constants and the codec's bounds ``L̄_s`` inlined:

  - ``likelihood="interval"`` (PPF, PF-RSN): ``Σ_s α_s log[Φ_ζ(z̃_s + L̄_s − h_s) −
    Φ_ζ(z̃_s − L̄_s − h_s)]`` evaluated as :func:`filters.edpf.interval_probability`
    (bounds clipped to the truncation, the difference of ``ndtr`` taken on the side
    where it does not cancel);
  - ``likelihood="raw"`` (PF-SR-DE): ``Σ_s α_s log p_ζ(z̃_s − h_s)``, ``−inf`` outside
    the truncation — so every particle of a run may get zero weight: the run then
    keeps its predicted particles with uniform weights, resamples them only if its
    ESS rule asks (``ess_threshold`` 1) and records a collapse (as ``run_sir``).

A sensor with ``α_s = 0`` contributes the factor 1 (Remark 2).  With the same
generator and the same initial particles, a one-run call reproduces ``run_sir(...,
runs=1)`` to rounding (numba's draws are NumPy's bit for bit; the tests check
1e-10).  Randomness is one Generator per run, so a run's result depends only on
its generator and data, not on the number of runs or of ``threads``.

Limitations: scalar sensors with :class:`~designer.noise.TruncatedGaussian` noise
(infinite bounds give a Gaussian); no known inputs; Gaussian or
Gaussian-mixture process noise.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from numba.core import types

from designer.codegen import literal
from designer.jit import scalar_statements
from designer.model import Model
from designer.noise import TruncatedGaussian
from designer.validation import InputError

from filters.edpf import sensor_bounds
from filters.encryption import Codec
from filters.result import FilterResult

from .codegen import compile_kernel, model_kernels, propagation_predrawn, weights
from .driver import F2, check_generators, check_model, check_options, check_particles, drivers, \
    lik_type, run_all

__all__ = ["LIKELIHOODS", "sir_edpf", "edpf_loglik"]

#: ``"interval"``: PPF's (13)-(15); ``"raw"``: PF-SR-DE's density at the decrypted value.
LIKELIHOODS = ("interval", "raw")
#: The family's data per run: decrypted values (K, N), availabilities (K, N).
DATA = types.Tuple((F2, F2))
LIK_T = lik_type(DATA)

def _c(v) -> str:
    """Source of a float constant (``±_m.inf`` for infinite truncation bounds)."""
    return literal(float(v), "_m")


# ============================================================================ checks
def _checked_model(model) -> Model:
    model = check_model(model, modes=True)
    if any(d != 1 for d in model.sensor_dims):
        raise InputError(f"model {model.name!r} must have scalar sensors (seed 001), got dimensions "
                         f"{model.sensor_dims}")
    for s, sensor in enumerate(model.sensors):
        if not isinstance(sensor.noise, TruncatedGaussian):
            raise InputError(f"model.sensors[{s}] noise is {type(sensor.noise).__name__}; the fused ED-PF kernels "
                             "need TruncatedGaussian measurement noise")
    return model


def _bound(model: Model, likelihood: str, codec) -> tuple:
    """The codec's ``L̄_s`` per sensor for the interval likelihood, ``()`` for the raw one."""
    if likelihood not in LIKELIHOODS:
        raise InputError(f"likelihood must be one of {', '.join(LIKELIHOODS)}, got {likelihood!r}")
    if likelihood == "raw":
        if codec is not None:
            raise InputError("codec applies to the interval likelihood only (the raw likelihood takes z~ as z)")
        return ()
    return tuple(float(v) for v in sensor_bounds(model, codec))


def _edpf_data(model: Model, R: int, y) -> tuple[np.ndarray, np.ndarray]:
    """``(Z, A)`` (R, K, N): values (0 where unavailable) and availabilities (0.0 / 1.0) of ``y``."""
    N = model.n_sensors
    try:
        yy = np.asarray(y, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"y must be numeric: {exc}") from None
    if yy.ndim != 3 or yy.shape[0] != R or yy.shape[1] < 1 or yy.shape[2] not in (N, 2 * N):
        raise InputError(f"y must have shape (runs, K, N) or (runs, K, 2 N) with runs = {R}, N = {N} (decrypted "
                         f"values, then their availabilities), got {yy.shape}")
    values = yy[..., :N]
    alpha = yy[..., N:] if yy.shape[2] == 2 * N else np.ones_like(values)
    if not np.all((alpha == 0.0) | (alpha == 1.0)):
        raise InputError("y's availabilities (its last N columns) must be 0 or 1")
    on = alpha == 1.0
    if not np.all(np.isfinite(values) | ~on):
        raise InputError("y must be finite in every available value (mark a missing value with availability 0)")
    return np.ascontiguousarray(np.where(on, values, 0.0)), np.ascontiguousarray(alpha)


# ============================================================================ generated likelihoods
def _interval_terms(s: int, noise: TruncatedGaussian, bound: float, ind: str) -> tuple[list[str], list[str]]:
    """(per step, per particle) statements adding sensor ``s``'s log interval probability to ``tot``."""
    loc, sc = float(noise.loc[0]), float(noise.scale[0])
    lo, up = float(noise.lower[0]), float(noise.upper[0])
    mass0 = float(noise._ab[3][0])
    step = [f"    on{s} = A[t, {s}] > 0.0", f"    vl{s} = Z[t, {s}] - {_c(bound)}",
            f"    vh{s} = Z[t, {s}] + {_c(bound)}"]
    body = []
    for name, v in (("lo", f"vl{s}"), ("hi", f"vh{s}")):
        # np.clip to the truncation (NaN stays NaN), then standardised
        body += [f"{ind}    u = {v} - h{s}",
                 f"{ind}    u = {_c(lo)} if u < {_c(lo)} else ({_c(up)} if u > {_c(up)} else u)",
                 f"{ind}    {name} = (u - {_c(loc)}) / {_c(sc)}"]
    body += [f"{ind}    p = (ndtr(-lo) - ndtr(-hi)) if lo > 0.0 else (ndtr(hi) - ndtr(lo))",
             f"{ind}    pr *= (0.0 if p < 0.0 else p) / {_c(mass0)}",
             # one log per particle for the product of the sensors' probabilities, unless it could underflow
             f"{ind}    if pr < 1e-280:",
             f"{ind}        tot += _m.log(pr)",
             f"{ind}        pr = 1.0"]
    return step, [f"{ind}if on{s}:"] + body


def _raw_terms(s: int, noise: TruncatedGaussian, ind: str) -> tuple[list[str], list[str]]:
    """(per step, per particle) statements adding sensor ``s``'s log density at ``z~ - h`` to ``tot``."""
    loc, sc = float(noise.loc[0]), float(noise.scale[0])
    a, b, _, mass = noise._ab
    const = float(np.log(np.sqrt(2 * np.pi) * noise.scale * mass)[0])  # as TruncatedGaussian.logpdf
    step = [f"    on{s} = A[t, {s}] > 0.0", f"    v{s} = Z[t, {s}]"]
    body = [f"{ind}if on{s}:",
            f"{ind}    u = ((v{s} - h{s}) - {_c(loc)}) / {_c(sc)}",
            f"{ind}    tot += (-0.5 * u * u - {_c(const)}) if (u >= {_c(a[0])} and u <= {_c(b[0])}) else -_m.inf"]
    return step, body


def _lik(model: Model, bound: tuple):
    """``lik`` of the ``"edpf"`` family (see :func:`filters.fused.driver.likelihood_block`, no slots):
    ``b[m] += Σ_s α_s term_s(X[m])``, interval terms for a non-empty ``bound``, raw densities for ``()``."""
    key = ("edpf", bound)
    cache = model_kernels(model)
    if key in cache:
        return cache[key]
    ind = "        "
    step, body = [], []
    for s, sensor in enumerate(model.sensors):
        st, bd = (_interval_terms(s, sensor.noise, bound[s], ind) if bound else _raw_terms(s, sensor.noise, ind))
        step += st
        body += bd
    lines = ["def lik(X, m0, n, k, data, t, b, ex):", "    Z, A = data", "    Xb = X[m0:m0 + n]",
             "    bb = b[m0:m0 + n]", *step, "    for m in range(n):"]
    lines += scalar_statements(model.casadi_h_all, ["Xb[m, {}]", "k"], "h{}", indent=ind)
    lines += [f"{ind}tot = 0.0", f"{ind}pr = 1.0", *body, f"{ind}bb[m] += tot + _m.log(pr)" if bound
              else f"{ind}bb[m] += tot"]
    what = "the interval likelihood" if bound else "the raw truncated-Gaussian likelihood"
    cache[key] = compile_kernel(model, ("lik", key), "\n".join(lines), "lik", what, LIK_T)
    return cache[key]


# ============================================================================ public
def sir_edpf(
    model: Model,
    x0: np.ndarray,
    rngs: Sequence[np.random.Generator],
    y: np.ndarray,
    *,
    likelihood: str = "interval",
    codec: Codec | None = None,
    resampler: str = "systematic",
    ess_threshold: float = 1.0,
    covariance: bool = False,
    threads: int = 1,
) -> FilterResult:
    """Bootstrap filter of seed 001 on decrypted measurements, many runs, fused numba kernels.

    Parameters
    ----------
    model : Model
        Switching modes allowed (the proposal draws a mode per particle); no known
        inputs; Gaussian or GaussianMixture process noise; scalar sensors with
        TruncatedGaussian noise.  PF-RSN is :func:`filters.edpf.fixed_mode_model`.
    x0 : ndarray, shape (R, M, n_x)
        Initial particles of every run (sampled by the caller, e.g. ``model.prior.sample(rngs[r], M)``).
    rngs : sequence of R numpy.random.Generator
        One distinct generator per run.
    y : ndarray, shape (R, K, 2 N) or (R, K, N)
        Per step the ``N`` decrypted values, then their availabilities α_s in {0, 1}
        (:func:`filters.edpf.received`); width ``N``: every sensor available.
        ``y[:, k]`` measures ``x_{k+1}``.
    likelihood : {'interval', 'raw'}
        PPF's interval likelihood (13)-(15) (needs ``codec``) or PF-SR-DE's density.
    codec : Codec
        Resolution and quantizer settings (``L̄_s = ω_s Λ / K + l_s``), interval likelihood only.
    resampler, ess_threshold, covariance, threads
        As in :func:`filters.fused.sir_packets` (the study resamples systematically when ESS < M/2).

    Returns
    -------
    FilterResult
        As :func:`filters.fused.sir_packets` returns it; in its ``detail``, ``collapsed[r, k]``: every weight
        of run ``r`` vanished at step ``k`` (predicted particles kept, uniform weights, resampled only with
        ``ess_threshold`` 1; ``loglik[r] = -inf``).
    """
    model = _checked_model(model)
    bound = _bound(model, likelihood, codec)
    x0 = check_particles(x0, model.n_x)
    R = x0.shape[0]
    gens = check_generators(rngs, R)
    scheme, thr, threads, covariance = check_options(resampler, ess_threshold, threads, covariance)
    Z, A = _edpf_data(model, R, y)
    prop, nd = propagation_predrawn(model)
    kernels = (prop, nd, _lik(model, bound), 0, 0, weights(model))
    return run_all(DATA, kernels, lambda r: (Z[r], A[r]), x0, gens, Z.shape[1], scheme, thr, covariance, threads,
                   model.n_sensors)


def edpf_loglik(model: Model, x, k1: int, y, *, likelihood: str = "interval", codec: Codec | None = None) -> np.ndarray:
    """One step's log-likelihood for particles ``x`` (R, M, n_x) and ``y`` (R, 2 N) or (R, N), by the kernels' code.

    Returns (R, M), a non-finite value as ``-inf`` (as the filter weighs it); ``k1`` is
    the time of the measured state.  For tests and diagnostics (see :func:`sir_edpf`).
    """
    model = _checked_model(model)
    bound = _bound(model, likelihood, codec)
    x = check_particles(x, model.n_x, "x")
    R = x.shape[0]
    yy = np.asarray(y, dtype=np.float64)
    if yy.ndim != 2:
        raise InputError(f"y must have shape (runs, N) or (runs, 2 N), got {yy.shape}")
    Z, A = _edpf_data(model, R, yy[:, None])
    lik = _lik(model, bound)
    rows = drivers(DATA, 1)
    out = np.empty(x.shape[:2])
    for r in range(R):
        rows(lik, 0, 0, x[r], float(k1), (Z[r], A[r]), out[r])
    return out
