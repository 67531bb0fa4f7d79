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

__all__ = ["binary_loglik"]


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
