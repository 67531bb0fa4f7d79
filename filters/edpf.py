"""Seed 001: the encryption-decryption particle filter (ED-PF, "PPF") and its two baselines.

Likelihoods and models for :func:`filters.particle.run_sir`; the proposal of every
filter is the model's transition density (:func:`filters.particle.transition_proposal`),
which for a switching model draws the mode per particle and so samples the mixture (11).

* **PPF** — the interval likelihood (13)-(15)::

      p(z̃_s | x) ≈ Φ_ζ(z̃_s + L̄_s - h_s(x)) - Φ_ζ(z̃_s - L̄_s - h_s(x)),   L̄_s = ω_s Λ / K + l_s  (12)

  with ``Φ_ζ`` the sensor noise's CDF, multiplied over the available sensors (Remark 2:
  a sensor with α_s = 0 contributes the factor 1).  The interval
  ``(z̃ - L̄, z̃ + L̄)`` contains every ``z`` that the chain maps to ``z̃``, so (13) bounds
  the exact probability ``P(z̃ | x)`` from above (it is not a normalised probability
  mass: it sums to more than one over the K values).
* **PF-RSN** — the same likelihood with a model that ignores the switching
  (:func:`fixed_mode_model`: the mode of ``f`` always active, γ = 1; G2).
* **PF-SR-DE** — ignores resolution and decryption errors: ``z̃`` is taken as ``z``
  and weighed with the noise density ``p_ζ(z̃_s - h_s(x))`` (:func:`raw_loglik`; G3).
  With the truncated noise it is zero where ``|z̃ - h(x)| > 2``; when every particle of
  a run gets zero weight, ``run_sir`` keeps the predicted particles with uniform
  weights and records a collapse.

Measurements: the likelihoods take ``z_k`` of shape ``(runs, 2 N)``: the decrypted
values of the ``N`` sensors followed by their availability indicators α_s in {0, 1}
(:func:`received`); an unavailable value is a placeholder (``run_sir`` would skip a
whole step on NaN, not one sensor).  A width of ``N`` means every sensor available.
"""
from __future__ import annotations

from typing import Callable

import casadi as ca
import numpy as np
from scipy import special

from designer.model import Model
from designer.noise import Noise, TruncatedGaussian
from designer.validation import InputError

from .encryption import Codec, Transmission

__all__ = ["received", "interval_probability", "sensor_bounds", "interval_loglik", "raw_loglik", "fixed_mode_model",
           "mean_dynamics_model"]


def received(tx: Transmission) -> np.ndarray:
    """The filters' measurements ``(..., 2 N)``: decrypted values (0 where unavailable), then α_s."""
    alpha = tx.available
    return np.concatenate([np.where(alpha, tx.decrypted, 0.0), alpha.astype(float)], axis=-1)


def interval_probability(noise: Noise, lo, hi) -> np.ndarray:
    """``P(lo < ζ <= hi)`` of a scalar noise (``lo <= hi``), shape of ``lo``.

    A truncated Gaussian is evaluated in closed form (``ndtr`` of the clipped,
    standardised bounds, upper tail by the survival function so that nothing cancels);
    any other scalar noise through its ``cdf``.
    """
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    if noise.dim != 1:
        raise InputError(f"noise must be scalar (dimension 1), got dimension {noise.dim}")
    if not isinstance(noise, TruncatedGaussian):
        return np.maximum(noise.cdf(hi[..., None]) - noise.cdf(lo[..., None]), 0.0)
    loc, s = float(noise.loc[0]), float(noise.scale[0])
    a0, b0 = (float(noise.lower[0]) - loc) / s, (float(noise.upper[0]) - loc) / s
    a = (np.clip(lo, noise.lower[0], noise.upper[0]) - loc) / s
    b = (np.clip(hi, noise.lower[0], noise.upper[0]) - loc) / s

    def mass(a, b):
        return np.where(a > 0, special.ndtr(-a) - special.ndtr(-b), special.ndtr(b) - special.ndtr(a))

    return np.maximum(mass(a, b), 0.0) / float(mass(np.float64(a0), np.float64(b0)))


def _scalar_sensors(model: Model) -> None:
    if any(d != 1 for d in model.sensor_dims):
        raise InputError(f"model {model.name!r} must have scalar sensors (seed 001), got dimensions "
                         f"{model.sensor_dims}")


def _split(model: Model, z) -> tuple[np.ndarray, np.ndarray]:
    N = model.n_sensors
    if z.shape[-1] == N:
        return z, np.ones_like(z)
    if z.shape[-1] != 2 * N:
        raise InputError(f"z must have N = {N} decrypted values, or 2 N = {2 * N} with their availabilities, "
                         f"per step; got width {z.shape[-1]}")
    return z[..., :N], z[..., N:]


def _per_sensor(model: Model, term: Callable) -> Callable:
    """``loglik(x, k1, z)``: Σ over available sensors of ``term(i, z̃_i (runs, 1), h_i(x) (runs, M))``."""
    _scalar_sensors(model)

    def loglik(x, k1, z):
        values, alpha = _split(model, np.asarray(z, dtype=float))
        h = model.h_all(x, k1)
        total = np.zeros(h.shape[:-1])
        for i in range(model.n_sensors):
            with np.errstate(divide="ignore"):
                t = term(i, values[..., i:i + 1], h[..., i])
            total = total + np.where(alpha[..., i:i + 1] > 0, t, 0.0)
        return total

    return loglik


def sensor_bounds(model: Model, codec: Codec) -> np.ndarray:
    """``L̄_s = ω_s Λ / K + l_s`` of (12) for each of the model's sensors, shape (N,).

    ``codec.resolution`` and ``codec.quant_scale`` must be scalars or one value per sensor.
    """
    if not isinstance(codec, Codec):
        raise InputError(f"codec must be a Codec, got {type(codec).__name__}")
    bound = codec.bound
    if bound.ndim > 1 or bound.size not in (1, model.n_sensors):
        raise InputError(f"codec resolution and quant_scale must be scalars or have one value per sensor "
                         f"({model.n_sensors}) for the likelihood, got bound of shape {bound.shape}")
    return np.broadcast_to(bound, (model.n_sensors,))


def interval_loglik(model: Model, codec: Codec) -> Callable:
    """PPF's ``log p(Z(t) | x)`` of (13)-(14) for ``run_sir``: Σ_s α_s log[Φ(H+) - Φ(H-)].

    ``codec.resolution`` and ``codec.quant_scale`` are scalars or one value per sensor.
    """
    bound = sensor_bounds(model, codec)
    noises = [s.noise for s in model.sensors]

    def term(i, v, h):
        return np.log(interval_probability(noises[i], v - bound[i] - h, v + bound[i] - h))

    return _per_sensor(model, term)


def raw_loglik(model: Model) -> Callable:
    """PF-SR-DE's ``log p(Z(t) | x)``: Σ_s α_s log p_ζ(z̃_s - h_s(x)), the decrypted value taken as ``z``."""
    noises = [s.noise for s in model.sensors]

    def term(i, v, h):
        return noises[i].logpdf((v - h)[..., None])

    return _per_sensor(model, term)


def _copy(model: Model, name: str, f, *, mode: bool, mode_probs=None) -> Model:
    return Model(name, model.x, f, model.sensors, model.process_noise, model.prior, k=model.k,
                 u=model.u if model.n_u else None, mode=model.mode if mode else None, mode_probs=mode_probs,
                 noise_gain=model.noise_gain, state_names=model.state_names,
                 position_index=model.position_index, velocity_index=model.velocity_index,
                 description=model.description)


def _check_switching(model: Model) -> None:
    if not model.n_modes:
        raise InputError(f"model {model.name!r} has no switching modes")


def fixed_mode_model(model: Model, mode: int) -> Model:
    """The model with one mode always active (probability one), e.g. PF-RSN's γ = 1.

    The mode symbol is kept, so the proposal still draws a mode per particle (always
    ``mode``) and consumes the same random numbers as the switching model's.
    """
    _check_switching(model)
    if isinstance(mode, bool) or not isinstance(mode, (int, np.integer)) or not 0 <= mode < model.n_modes:
        raise InputError(f"mode must be an integer in 0..{model.n_modes - 1}, got {mode!r}")
    probs = np.zeros(model.n_modes)
    probs[int(mode)] = 1.0
    return _copy(model, f"{model.name} (mode {int(mode)} only)", model.f_expr, mode=True, mode_probs=probs)


def mean_dynamics_model(model: Model) -> Model:
    """The model without switching whose transition is the mode average ``Σ_m p_m f(x, m)``."""
    _check_switching(model)
    f = sum(float(p) * ca.substitute(model.f_expr, model.mode, ca.SX(m)) for m, p in enumerate(model.mode_probs))
    return _copy(model, f"{model.name} (mean dynamics)", f, mode=False)
