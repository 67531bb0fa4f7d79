"""Seed 002: likelihood of binary sensors under DoS, deception and bit flipping (Theorem 1, (13)-(16)).

For sensor s with energy ``h = h^s(x)``, ``c = F_ν(T_δ - h)`` (noise CDF), ``c_μ = F_μ(T_δ)``
(deception CDF) and channel density ``P_e``::

    L00 = P_e(y - τ) [ᾱ c + (1 - ᾱ)(1 - c)] + P_e(y) [ᾱ (1 - c) + (1 - ᾱ) c]
    L01 = L00 with c replaced by c_μ
    L1  = ᾱ P_e(y - τ) + (1 - ᾱ) P_e(y)
    p(y_s | x) = (1 - φ̄) [(1 - ϕ̄) L00 + ϕ̄ L01] + φ̄ L1

Sec-PF uses it with the attack probabilities; Sta-PF-Neg and Sta-PF use it with
φ̄ = ϕ̄ = ᾱ = 0 (the binary-sensor likelihood that ignores attacks).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from designer.model import Model
from designer.noise import Noise
from designer.validation import InputError, check_probability

__all__ = ["binary_loglik", "binary_coefficients"]


def binary_loglik(model: Model, *, threshold: float, gain: float, channel_noise: Noise, deception: Noise,
                  dos_prob: float = 0.0, deception_prob: float = 0.0, flip_prob: float = 0.0) -> Callable:
    """``loglik(x, k1, y) -> (runs, M)`` for received signals ``y`` of shape (runs, S)."""
    c_mu = float(deception.cdf(np.array([threshold])))
    a = flip_prob

    def loglik(x, k1, y):
        h = model.h_all(x, k1)  # (runs, M, S)
        c = np.stack([s.noise.cdf(threshold - h[..., i:i + 1]) for i, s in enumerate(model.sensors)], axis=-1)
        yy = y[..., None, :]
        pe1 = channel_noise.pdf((yy - gain)[..., None])  # bit 1 received
        pe0 = channel_noise.pdf(yy[..., None])  # bit 0 received
        L00 = pe1 * (a * c + (1 - a) * (1 - c)) + pe0 * (a * (1 - c) + (1 - a) * c)
        L01 = pe1 * (a * c_mu + (1 - a) * (1 - c_mu)) + pe0 * (a * (1 - c_mu) + (1 - a) * c_mu)
        L1 = a * pe1 + (1 - a) * pe0
        p = (1 - dos_prob) * ((1 - deception_prob) * L00 + deception_prob * L01) + dos_prob * L1
        with np.errstate(divide="ignore"):
            return np.sum(np.log(p), axis=-1)

    return loglik


def binary_coefficients(y, *, threshold: float, gain: float, channel_noise: Noise, deception: Noise,
                        dos_prob: float = 0.0, deception_prob: float = 0.0,
                        flip_prob: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``A``, ``B`` with ``p(y_s | x) = A + B c``, ``c = F_ν(T − h_s(x))`` (seed 002 (13)-(16)).

    :func:`binary_loglik`'s likelihood, affine in ``c``: the coefficients of the fused form
    (:func:`filters.fused.sir_binary`).

    With ``P_e`` the channel density, ``pe1 = P_e(y − τ)``, ``pe0 = P_e(y)``, ``a = ᾱ``::

        L00 = pe1 (1 − a) + pe0 a + c (2a − 1)(pe1 − pe0)
        L01 = L00 at c = c_μ = F_μ(T),   L1 = a pe1 + (1 − a) pe0
        p   = (1 − φ̄)[(1 − ϕ̄) L00 + ϕ̄ L01] + φ̄ L1

    Parameters as in :func:`binary_loglik`; ``y`` is any array of
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
