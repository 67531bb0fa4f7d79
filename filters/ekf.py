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

from .result import FilterResult, centralized_result
from .rrp import angle_sets, wrap_angles

__all__ = ["EKFResult", "run_ekf", "run_ekf_batch"]


class EKFResult(NamedTuple):
    """The EKF's own arrays: a run of :func:`run_ekf`, or the ``detail`` of :func:`run_ekf_batch`'s result."""

    x: np.ndarray  # (K + 1, n_x) posterior means, x[0] the prior mean; (runs, K + 1, n_x) as run_ekf_batch's detail
    P: np.ndarray  # (K + 1, n_x, n_x); (runs, K + 1, n_x, n_x) as its detail



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


def run_ekf_batch(model: Model, z: np.ndarray, *, available: np.ndarray | None = None, inputs=None, x0=None,
                  P0=None, angles=None, uplinks: int | None = None) -> FilterResult:
    """:func:`run_ekf` on many runs at once: ``z`` (runs, K, n_z), ``available`` (runs, K, N) bool.

    ``inputs`` (K, n_u) shared or (runs, K, n_u); ``x0`` (n_x,) or (runs, n_x), ``P0`` (n_x, n_x) or
    (runs, n_x, n_x).  Returns the fusion centre's :class:`filters.result.FilterResult`
    (:func:`filters.result.centralized_result`: ``uplinks`` messages per step, default one per sensor), its
    ``detail`` the :class:`EKFResult` fields with a leading runs axis; run ``r`` equals ``run_ekf`` on run ``r``
    to rounding.  Every step updates all runs with every sensor's rows, those of a
    lost packet zeroed (H and the residual): its block of the innovation covariance is then R_i alone, its
    gain columns exactly zero, and the other rows' numbers those of the received sensors alone.  A run whose
    innovation covariance leaves finite numbers or positive definiteness is handed to :func:`run_ekf` (which
    raises what it raises for it).
    """
    z = np.asarray(z, dtype=float)
    if z.ndim != 3 or z.shape[2] != model.n_z:
        raise InputError(f"z must have shape (runs, K, {model.n_z}), got {z.shape}")
    runs, K, N = z.shape[0], z.shape[1], model.n_sensors
    avail = np.ones((runs, K, N), bool) if available is None else np.asarray(available, dtype=bool)
    if avail.shape != (runs, K, N):
        raise InputError(f"available must have shape ({runs}, {K}, {N}), got {avail.shape}")
    rows = np.repeat(avail, model.sensor_dims, axis=2)  # (runs, K, n_z): the received measurement rows
    check_finite("z", np.where(rows, z, 0.0))
    u = np.zeros((K, 0)) if inputs is None else np.asarray(inputs, dtype=float)
    if model.n_u and u.shape not in ((K, model.n_u), (runs, K, model.n_u)):
        raise InputError(f"inputs must have shape ({K}, {model.n_u}) or ({runs}, {K}, {model.n_u}), got {u.shape}")
    x = np.array(np.broadcast_to(model.prior.mean if x0 is None else check_finite("x0", x0), (runs, model.n_x)))
    P = np.array(np.broadcast_to(model.prior.cov if P0 is None else check_finite("P0", P0),
                                 (runs, model.n_x, model.n_x)))
    Q = model.process_cov
    R = block_diag(*[model.measurement_cov(i) for i in range(N)])
    wraps = angle_sets(model, model.angle_components if angles is None else angles)
    offsets = model._offsets
    xs, Ps = np.empty((runs, K + 1, model.n_x)), np.empty((runs, K + 1, model.n_x, model.n_x))
    xs[:, 0], Ps[:, 0] = x, P
    eye = np.eye(model.n_x)
    act = np.arange(runs)  # the runs in the batch (the others went to run_ekf)
    alone: list[int] = []
    for k in range(K):
        uk = None if not model.n_u else (u[k] if u.ndim == 2 else u[act, k])
        F = model.F_expected(x, k, uk)
        x = model.f_expected(x, k, uk)
        P = model.propagate(F, P) + Q
        got = rows[act, k]
        H = np.where(got[..., None], np.concatenate([model.H(i, x, k + 1) for i in range(N)], axis=-2), 0.0)
        r = np.concatenate([wrap_angles(z[act, k, offsets[i]:offsets[i + 1]] - model.h(i, x, k + 1), wraps[i])
                            for i in range(N)], axis=-1)
        r = np.where(got, r, 0.0)
        HP = H @ P
        S = HP @ np.swapaxes(H, -1, -2) + R
        S = 0.5 * (S + np.swapaxes(S, -1, -2))
        fine = np.isfinite(S).all(axis=(-2, -1))
        try:
            np.linalg.cholesky(S[fine])
        except np.linalg.LinAlgError:
            for j in np.flatnonzero(fine):
                try:
                    np.linalg.cholesky(S[j])
                except np.linalg.LinAlgError:
                    fine[j] = False
        if not fine.all():  # these runs as run_ekf runs them
            alone += act[~fine].tolist()
            act, x, P, S, HP, H, r = act[fine], x[fine], P[fine], S[fine], HP[fine], H[fine], r[fine]
        G = np.swapaxes(np.linalg.solve(S, HP), -1, -2)  # P Hᵀ S⁻¹
        x = x + (G @ r[..., None])[..., 0]
        A = eye - G @ H
        P = A @ P @ np.swapaxes(A, -1, -2) + G @ R @ np.swapaxes(G, -1, -2)
        P = 0.5 * (P + np.swapaxes(P, -1, -2))
        xs[act, k + 1], Ps[act, k + 1] = x, P
    for a in sorted(alone):
        ref = run_ekf(model, z[a], available=avail[a], inputs=None if inputs is None else (u if u.ndim == 2 else u[a]),
                      x0=None if x0 is None else np.broadcast_to(x0, (runs, model.n_x))[a],
                      P0=None if P0 is None else np.broadcast_to(P0, (runs, model.n_x, model.n_x))[a], angles=angles)
        xs[a], Ps[a] = ref.x, ref.P
    return centralized_result(xs, Ps, model.n_sensors if uplinks is None else uplinks, EKFResult(xs, Ps))
