"""A centralized extended Kalman filter over the model layer, with sensors that may be missing.

The plain EKF of the comparison study: it uses every measurement that arrives as
if it were genuine (it ignores false-data injection) and skips the sensors whose
packet was lost.  Predict ``x⁻ = E f(x, k, u)``, ``P⁻ = F P Fᵀ + G Q Gᵀ`` with
``F`` the model's CasADi Jacobian; update with the stacked rows of the available
sensors, gain from a Cholesky solve, Joseph form, symmetrised.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.linalg import block_diag, cho_factor, cho_solve

from designer.model import Model
from designer.validation import InputError, check_finite

from .rrp import angle_sets, wrap_angles

__all__ = ["EKFResult", "run_ekf"]


class EKFResult(NamedTuple):
    x: np.ndarray  # (K + 1, n_x) posterior means, x[0] the prior mean
    P: np.ndarray  # (K + 1, n_x, n_x)


def run_ekf(model: Model, z: np.ndarray, *, available: np.ndarray | None = None, inputs=None, x0=None,
            P0=None, angles=None) -> EKFResult:
    """Filter ``z`` (K, n_z), ``z[k]`` measuring ``x_{k+1}``; ``available`` (K, N) bool marks received sensors.

    ``angles``: ``(sensor, component)`` pairs of angular measurements, whose residuals are
    wrapped into (-π, π] (default: the sensors' declared ``angles``; ``()`` wraps nothing).
    """
    z = np.asarray(z, dtype=float)
    if z.ndim != 2 or z.shape[1] != model.n_z:
        raise InputError(f"z must have shape (K, {model.n_z}), got {z.shape}")
    K, N = z.shape[0], model.n_sensors
    avail = np.ones((K, N), bool) if available is None else np.asarray(available, dtype=bool)
    if avail.shape != (K, N):
        raise InputError(f"available must have shape ({K}, {N}), got {avail.shape}")
    check_finite("z", np.where(np.repeat(avail, model.sensor_dims, axis=1), z, 0.0))
    u = np.zeros((K, 0)) if inputs is None else np.asarray(inputs, dtype=float)
    if model.n_u and u.shape != (K, model.n_u):
        raise InputError(f"inputs must have shape ({K}, {model.n_u}), got {u.shape}")
    x = model.prior.mean.copy() if x0 is None else check_finite("x0", x0).copy()
    P = model.prior.cov.copy() if P0 is None else check_finite("P0", P0).copy()
    Q = model.process_cov
    wraps = angle_sets(model, model.angle_components if angles is None else angles)
    xs, Ps = np.empty((K + 1, model.n_x)), np.empty((K + 1, model.n_x, model.n_x))
    xs[0], Ps[0] = x, P
    eye = np.eye(model.n_x)
    for k in range(K):
        uk = u[k] if model.n_u else None
        F = model.F_expected(x, k, uk)
        x = model.f_expected(x, k, uk)
        P = F @ P @ F.T + Q
        idx = np.flatnonzero(avail[k])
        if idx.size:
            H = np.vstack([model.H(i, x, k + 1) for i in idx])
            R = block_diag(*[model.measurement_cov(i) for i in idx])
            r = np.concatenate([wrap_angles(z[k, model._offsets[i]:model._offsets[i + 1]] - model.h(i, x, k + 1),
                                            wraps[i]) for i in idx])
            S = H @ P @ H.T + R
            G = cho_solve(cho_factor(0.5 * (S + S.T)), H @ P).T  # P Hᵀ S⁻¹
            x = x + G @ r
            A = eye - G @ H
            P = A @ P @ A.T + G @ R @ G.T
        P = 0.5 * (P + P.T)
        xs[k + 1], Ps[k + 1] = x, P
    return EKFResult(xs, Ps)

