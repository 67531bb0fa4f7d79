"""Pieces shared by several built-in scenarios."""
from __future__ import annotations

import numpy as np

from designer.noise import Gaussian, GaussianMixture

__all__ = ["cv_transition", "cv_process_cov", "glint"]


def cv_transition(x, period: float):
    """Constant-velocity transition for the state ``[px, vx, py, vy]`` (``x`` a ``casadi.SX`` symbol)."""
    import casadi as ca

    return ca.vertcat(x[0] + period * x[1], x[1], x[2] + period * x[3], x[3])


def cv_process_cov(accel_var: float, period: float) -> np.ndarray:
    """``accel_var * blockdiag(B, B)``, ``B = [[T^3/3, T^2/2], [T^2/2, T]]`` (white-noise acceleration)."""
    T = period
    B = np.array([[T**3 / 3.0, T**2 / 2.0], [T**2 / 2.0, T]])
    Q = np.zeros((4, 4))
    Q[:2, :2] = B
    Q[2:, 2:] = B
    return accel_var * Q


def glint(weight: float, cov1, cov2) -> GaussianMixture:
    """Zero-mean glint noise ``(1 - weight) N(0, cov1) + weight N(0, cov2)``."""
    cov1 = np.atleast_2d(np.asarray(cov1, dtype=float))
    cov2 = np.atleast_2d(np.asarray(cov2, dtype=float))
    return GaussianMixture(np.array([1.0 - weight, weight]), (Gaussian.zero_mean(cov1), Gaussian.zero_mean(cov2)))
