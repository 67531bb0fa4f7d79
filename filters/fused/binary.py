"""Seed 002's binary-sensor likelihood on the fused kernels: :func:`sir_binary` (the NumPy twin: :mod:`filters.binary`).

``S`` scalar sensors, ``Σ_s log(A + B F_ν(T − h_s(x)))`` with ``F_ν`` the sensor noise's
CDF: seed 002's likelihood (13)-(16) is affine in ``c = F_ν(T − h)``, and
:func:`filters.binary.binary_coefficients` gives ``A`` and ``B`` from the received
signals (:func:`filters.binary.binary_loglik` is the NumPy engine's form).  Draws,
numerics and limitations as :mod:`filters.fused.packets`.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from numba.core import types

from designer.jit import scalar_statements
from designer.model import Model
from designer.noise import Gaussian, GaussianMixture
from designer.validation import InputError

from .codegen import compile_kernel, const, model_kernels, propagation, weights
from .driver import F2, FastSIRResult, check_generators, check_model, check_options, check_particles, drivers, \
    lik_type, run_all

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
) -> FastSIRResult:
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
                   threads)


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
def binary_lik(model: Model):
    """``lik`` of the binary likelihood (see :func:`likelihood_block`, no slots), ``data = (A, B, T)``:
    ``b[m] += Σ_s log(A[t, s] + B[t, s] F_ν_s(T − h_s(X[m], k)))``."""
    if "binary" in model_kernels(model):
        return model_kernels(model)["binary"]
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
            c = f"ndtr((u - {const(nz.mean[0])}) / {const(np.sqrt(nz.cov[0, 0]))})"
        elif isinstance(nz, GaussianMixture):  # sum of w * component cdf
            c = " + ".join(f"{const(w)} * ndtr((u - {const(g.mean[0])}) / {const(np.sqrt(g.cov[0, 0]))})"
                           for w, g in zip(nz.weights, nz.components))
        else:
            raise InputError(f"model.sensors[{s}] noise is {type(nz).__name__}; the fused kernels support Gaussian "
                             "and GaussianMixture")
        lines.append(f"        total += _m.log(A[t, {s}] + B[t, {s}] * ({c}))")
    lines.append("        bb[m] += total")
    return compile_kernel(model, "binary", "\n".join(lines), "lik", "the binary likelihood", LIK_T)


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
