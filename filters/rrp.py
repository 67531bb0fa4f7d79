"""Seed 000: particle filters under the Round-Robin protocol with randomly occurring deception attacks.

Likelihoods for :func:`filters.particle.run_sir` (bootstrap proposal):

* ``RRP-PF-DA`` — only the scheduled sensor's packet, attack-aware (14):
  ``p(ỹ | x) = (1 - η̄) p_ν(ỹ - h^γ(x)) + η̄ p_ξ(ỹ)``;
* ``RRP-SPF-DA`` — the same packet with the standard likelihood ``p_ν(ỹ - h^γ(x))``
  (ignores the attack);
* ``RRP-SPF-NM`` — the standard likelihood on attack-free packets;
* ``PF-DA`` — every sensor every step, the product of the per-sensor attack-aware
  likelihoods (independent attacks per packet).

Angle components of the residual are wrapped into (-π, π] before ``p_ν`` (a
bearing of 179° against a prediction of -179° is a 2° error); ``p_ξ`` is
evaluated at the received value itself.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from designer.model import Model
from designer.noise import Noise
from designer.validation import InputError, check_probability

__all__ = ["wrap_angles", "angle_sets", "packet_loglik", "rrp_loglik", "all_sensors_loglik", "deception_terms"]


def wrap_angles(r: np.ndarray, components: Sequence[int]) -> np.ndarray:
    """Wrap the listed components of residuals into (-π, π]."""
    if not components:
        return r
    r = np.array(r, dtype=float, copy=True)
    c = list(components)
    r[..., c] = np.pi - np.mod(np.pi - r[..., c], 2 * np.pi)
    return r


def angle_sets(model: Model, angles) -> list[list[int]]:
    """Per sensor, its angular components, from component indices (every sensor) or (sensor, component) pairs."""
    S, dims = model.n_sensors, model.sensor_dims
    msg = "angles must be a sequence of component indices or (sensor, component) pairs"
    if isinstance(angles, (str, bytes)):
        raise InputError(msg)
    try:
        items = list(angles)
    except TypeError:
        raise InputError(msg) from None

    def is_int(v):
        return isinstance(v, (int, np.integer)) and not isinstance(v, bool)

    out: list[set] = [set() for _ in range(S)]
    for a in items:
        if is_int(a):
            pairs = [(s, int(a)) for s in range(S)]
        elif isinstance(a, (tuple, list)) and len(a) == 2 and all(is_int(v) for v in a):
            pairs = [(int(a[0]), int(a[1]))]
        else:
            raise InputError(f"angles must hold component indices or (sensor, component) pairs, got {a!r}")
        for s, j in pairs:
            if not (0 <= s < S) or not (0 <= j < dims[s]):
                raise InputError(f"angles entry {a!r} is out of range (sensors 0..{S - 1}, and each sensor's "
                                 "components)")
            out[s].add(j)
    return [sorted(c) for c in out]


def _sensor_loglik(model: Model, i: int, x, k1, y, attack_prob: float, signal: Noise | None,
                   angles: Sequence[int]) -> np.ndarray:
    r = wrap_angles(y[..., None, :] - model.h(i, x, k1), angles)
    lp = model.sensors[i].noise.logpdf(r)
    if attack_prob <= 0.0 or signal is None:
        return lp
    lxi = signal.logpdf(y)[..., None]  # (runs, 1)
    return np.logaddexp(np.log1p(-attack_prob) + lp, np.log(attack_prob) + lxi)


def packet_loglik(model: Model, sensors, *, attack_prob: float = 0.0, signal: Noise | None = None,
                  angles: Sequence[int] = ()) -> Callable:
    """Log-likelihood of ``P`` packets per step, packet ``p`` at step ``k`` from sensor ``sensors[k, p]``.

    The measurement passed at step ``k`` (``z[:, k]``) stacks the ``P`` received
    packets, shape (runs, Σ n_y); each packet is attack-aware (14) when
    ``attack_prob > 0`` (independent attacks per packet), standard otherwise.
    """
    sensors = np.asarray(sensors)
    if sensors.ndim != 2 or not np.issubdtype(sensors.dtype, np.integer):
        raise InputError(f"sensors must be an integer array (K, P), got {sensors.dtype} {sensors.shape}")
    if sensors.size and (sensors.min() < 0 or sensors.max() >= model.n_sensors):
        raise InputError(f"sensors must hold sensor indices in [0, {model.n_sensors - 1}]")
    dims = np.asarray(model.sensor_dims)

    def loglik(x, k1, z):
        row = sensors[k1 - 1]
        ends = np.cumsum(dims[row])
        total = 0.0
        for i, b, n in zip(row, ends, dims[row]):
            total = total + _sensor_loglik(model, int(i), x, k1, z[..., b - n:b], attack_prob, signal, angles)
        return total

    return loglik


def rrp_loglik(model: Model, schedule: np.ndarray, *, attack_prob: float = 0.0, signal: Noise | None = None,
               angles: Sequence[int] = ()) -> Callable:
    """Log-likelihood of the scheduled sensor's packet; ``attack_prob = 0`` gives the standard one.

    The measurement passed at step ``k`` (``z[:, k]``) is the received packet of the
    scheduled sensor ``schedule[k]``, shape (runs, n_y).
    """
    return packet_loglik(model, np.asarray(schedule)[:, None], attack_prob=attack_prob, signal=signal, angles=angles)


def all_sensors_loglik(model: Model, *, attack_prob: float = 0.0, signal: Noise | None = None,
                       angles: Sequence[int] = ()) -> Callable:
    """Product over sensors of the per-packet likelihoods (``z[:, k]`` stacks all sensors)."""

    def loglik(x, k1, z):
        total = 0.0
        for i, (a, b) in enumerate(zip(model._offsets[:-1], model._offsets[1:])):
            total = total + _sensor_loglik(model, i, x, k1, z[..., a:b], attack_prob, signal, angles)
        return total

    return loglik


def deception_terms(y, attack_prob: float, signal: Noise | None) -> tuple[float, np.ndarray]:
    """``(log_clean, attack)`` of seed 000's attack-aware likelihood (14) for received packets ``y`` (..., n_y).

    The terms of the fused packet likelihood (:func:`filters.fused.sir_packets`), the same (14) as
    :func:`packet_loglik`.

    ``log_clean = log(1 − η̄)`` and ``attack = log η̄ + log p_ξ(y)`` (shape ``y.shape[:-1]``);
    ``attack_prob = 0`` or no signal gives the standard likelihood ``(0, −inf)``.
    """
    p = float(check_probability("attack_prob", attack_prob, open_upper=True))
    y = np.asarray(y, dtype=np.float64)
    if p <= 0.0 or signal is None:
        return 0.0, np.full(y.shape[:-1], -np.inf)
    if not isinstance(signal, Noise):
        raise InputError(f"signal must be a Noise distribution, got {type(signal).__name__}")
    with np.errstate(divide="ignore"):
        return float(np.log1p(-p)), np.log(p) + signal.logpdf(y)
