"""Seed 002's binary-sensor likelihood on the fused kernels: :func:`sir_binary` (the NumPy twin: :mod:`filters.binary`).

``S`` scalar sensors, ``Σ_s log(A + B F_ν(T − h_s(x)))`` with ``F_ν`` the sensor noise's
CDF: seed 002's likelihood (13)-(16) is affine in ``c = F_ν(T − h)``, and
:func:`filters.binary.binary_coefficients` gives ``A`` and ``B`` from the received
signals (:func:`filters.binary.binary_loglik` is the NumPy engine's form).  Draws and
limitations as :mod:`filters.fused.packets`.  Numerics: the CDFs and the log are the
branch-free ones of :mod:`filters.fused.primitives`, and so are the model's powers (the
likelihood loops vectorise; on target-binary-energy a filter step takes 0.25 ms instead of
libm's 0.52), within a few ulp of the NumPy twin's: the default binary-multi-attack study's
results agree with the libm version's to 3.8e-15 relative.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from numba.core import types

from designer.jit import fma, scalar_statements
from designer.model import Model
from designer.validation import InputError
from filters.result import FilterResult

from .cache import njit
from .codegen import compile_kernel, components, const, model_kernels, propagation, split_powers, weights
from .driver import F2, check_generators, check_model, check_options, check_particles, drivers, \
    lik_type, run_all
from .primitives import LN2_HI, LN2_LO, vfrexp, vlog_dd, vndtr, vpow_rows

__all__ = ["sir_binary", "binary_affine_loglik"]

#: The family's data per run: A (K, S), B (K, S), the threshold.
DATA = types.Tuple((F2, F2, types.float64))
LIK_T = lik_type(DATA)


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
) -> FilterResult:
    """Bootstrap filter with the affine-in-CDF likelihood of binary sensors, many runs, fused kernels.

    The log-likelihood of step ``k`` is ``Σ_s log(A[r, k, s] + B[r, k, s] F_ν(T − h_s(x)))``
    with ``F_ν`` the CDF of sensor ``s``'s scalar Gaussian or Gaussian-mixture
    noise and ``T`` the threshold.  :func:`filters.binary.binary_coefficients` gives the ``A`` and
    ``B`` of seed 002's likelihood (13)-(16) from the received signals.

    Parameters
    ----------
    A, B : ndarray, shape (R, K, S)
        Coefficients per run, step and sensor (independent of the state).
    threshold : float
        ``T_δ``.

    Other parameters as in :func:`sir_packets`.
    """
    model = check_model(model)
    x0 = check_particles(x0, model.n_x)
    R = x0.shape[0]
    gens = check_generators(rngs, R)
    scheme, thr, threads, covariance = check_options(resampler, ess_threshold, threads, covariance)
    AA, BB, T = binary_data(model, R, A, B, threshold)
    kernels = (propagation(model), 0, binary_lik(model), 0, 0, weights(model))
    return run_all(DATA, kernels, lambda r: (AA[r], BB[r], T), x0, gens, AA.shape[1], scheme, thr, covariance,
                   threads, model.n_sensors)


def binary_affine_loglik(model: Model, x, k1: int, A, B, *, threshold: float) -> np.ndarray:
    """One step's ``Σ_s log(A + B F_ν(T − h_s(x)))`` for particles ``x`` (R, M, n_x); ``A``, ``B`` (R, S).

    Returns (R, M) from the same generated code as :func:`sir_binary` (non-finite as ``-inf``).
    """
    model = check_model(model)
    x = check_particles(x, model.n_x, "x")
    R = x.shape[0]
    AA, BB, T = binary_data(model, R, np.asarray(A, dtype=float)[:, None], np.asarray(B, dtype=float)[:, None],
                            threshold)
    lik = binary_lik(model)
    rows = drivers(DATA, 1)
    out = np.empty(x.shape[:2])
    for r in range(R):
        rows(lik, 0, 0, x[r], float(k1), (AA[r], BB[r], T), out[r])
    return out


# ============================================================================ generated likelihood and checks
@njit()
def _cdf_term(u, n, C, w, mu, sd, add):
    """``C[m] (+)= w F((u[m] − mu) / sd)`` for ``m < n``, ``F`` the standard normal CDF (branch-free, vectorises)."""
    if add:
        for m in range(n):
            C[m] += w * vndtr((u[m] - mu) / sd)
    else:
        for m in range(n):
            C[m] = w * vndtr((u[m] - mu) / sd)


@njit()
def _affine_factor(C, n, a, c, mant, expo):
    """Multiply the running products ``mant[m] 2^expo[m]`` by ``a + c C[m]``; a factor that is not positive (or
    NaN) makes ``expo[m]`` NaN.  Factors below 1e-290 are scaled by 2^64 first, so the mantissa stays normal."""
    for m in range(n):
        v = a + c * C[m]
        tiny = v < 1e-290
        fm, fe = vfrexp(mant[m] * (v * 1.8446744073709552e19 if tiny else v))
        mant[m] = fm
        expo[m] += (fe - 64.0 if tiny else fe) if v > 0.0 else math.nan


@njit()
def _add_log_product(mant, expo, n, b):
    """``b[m] += log(mant[m] 2^expo[m])``: one branch-free ``log`` per particle (``ln 2`` in two parts)."""
    for m in range(n):
        hi, lo = vlog_dd(mant[m])
        e = expo[m]
        b[m] += fma(e, LN2_HI, hi) + fma(e, LN2_LO, lo)


_HELPERS = {"_cdf_term": _cdf_term, "_affine_factor": _affine_factor, "_add_log_product": _add_log_product,
            "_vpow_rows": vpow_rows}


def binary_lik(model: Model):
    """``lik`` of the binary likelihood (see :func:`likelihood_block`, no slots), ``data = (A, B, T)``:
    ``b[m] += log Π_s (A[t, s] + B[t, s] F_ν_s(T − h_s(X[m], k)))``.

    The generated part computes ``T − h_s`` for every particle of the block (the model's
    ``h``, as the other families, its powers taken out into one pass of the branch-free
    ``pow``: :func:`filters.fused.codegen.split_powers`); the rest is generic and vectorises
    (branch-free ``ndtr`` and ``log`` of :mod:`filters.fused.primitives`): per sensor the noise's CDF
    (one pass per mixture component), the factor, the running product kept as
    ``mantissa 2^exponent`` (no underflow), and one ``log`` per particle.  A factor that is
    not positive (or NaN) gives the particle NaN: zero weight.  The NumPy twin sums the
    logs of libm's values; the two agree to a few ulp.
    """
    if "binary" in model_kernels(model):
        return model_kernels(model)["binary"]
    if any(d != 1 for d in model.sensor_dims):
        raise InputError("sir_binary needs scalar sensors (every sensor of dimension 1)")
    S = model.n_sensors
    h = scalar_statements(model.casadi_h_all, ["Xb[m, {}]", "k"], "h{}", indent="        ")
    lines = ["def lik(X, m0, n, k, data, t, b, ex):", "    A, B, T = data", "    Xb = X[m0:m0 + n]",
             f"    U = _np.empty(({S}, n))"]
    split = split_powers(h)
    if split is not None:  # the model's powers in one vectorised pass (received energy: d² ** (−λ/2) per sensor)
        first, h, J = split
        lines += [f"    PA = _np.empty(({J}, n))", f"    PB = _np.empty(({J}, n))", f"    PR = _np.empty(({J}, n))",
                  "    for m in range(n):", *first, "    _vpow_rows(PA, PB, PR, n)"]
    lines += ["    for m in range(n):", *h]
    lines += [f"        U[{s}, m] = T - h{s}" for s in range(S)]
    lines += ["    C = _np.empty(n)", "    mant = _np.ones(n)", "    expo = _np.zeros(n)"]
    for s, sensor in enumerate(model.sensors):  # Gaussian.cdf: ndtr((x - mean) / sd); a mixture's: Σ w_c cdf_c
        terms = components(sensor.noise, f"model.sensors[{s}]")
        lines += [f"    _cdf_term(U[{s}], n, C, {const(1.0 if w is None else w)}, {const(g.mean[0])}, "
                  f"{const(np.sqrt(g.cov[0, 0]))}, {j > 0})" for j, (w, g) in enumerate(terms)]
        lines.append(f"    _affine_factor(C, n, A[t, {s}], B[t, {s}], mant, expo)")
    lines.append("    _add_log_product(mant, expo, n, b[m0:m0 + n])")
    return compile_kernel(model, "binary", "\n".join(lines), "lik", "the binary likelihood", LIK_T, _HELPERS)


def binary_data(model: Model, R: int, A, B, threshold):
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
