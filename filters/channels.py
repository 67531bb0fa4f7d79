"""Channel and attack simulators of the particle-filter papers (seeds 000 and 002).

All functions are batched over leading Monte Carlo dimensions and draw only from
the ``numpy.random.Generator`` passed in.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from designer.noise import Noise
from designer.validation import InputError, check_int, check_probability

__all__ = [
    "round_robin_schedule", "DeceptionOutcome", "deception_attack", "round_robin_received",
    "BinaryOutcome", "binary_sensor_channel",
]


def round_robin_schedule(steps: int, n_sensors: int, start: int = 1) -> np.ndarray:
    """Sensor with channel access at k = 1..K: ``gamma_k = mod(k + gamma_ini - 2, N) + 1`` (seed 000 (3)).

    Returns 0-based sensor indices of shape (K,); ``start`` is the paper's 1-based ``gamma_ini``.
    """
    n_sensors = check_int("n_sensors", n_sensors, 1)
    if not isinstance(start, (int, np.integer)) or not 1 <= start <= n_sensors:
        raise InputError(f"start (gamma_ini) must be an integer in [1, {n_sensors}], got {start!r}")
    steps = check_int("steps", steps, 1)
    k = np.arange(1, steps + 1)
    return np.mod(k + start - 2, n_sensors)  # (gamma_k - 1)


class DeceptionOutcome(NamedTuple):
    y: np.ndarray  # received values: (1 - eta) y + eta xi
    eta: np.ndarray  # bool, attack succeeded
    xi: np.ndarray  # the deception signal drawn at every step (used where eta)


def deception_attack(y, prob: float, signal: Noise, rng: np.random.Generator) -> DeceptionOutcome:
    """Bernoulli deception (seed 000 (4)-(6)): with probability ``prob`` the packet is replaced by ``xi ~ signal``.

    ``y`` has shape (..., n_y); one Bernoulli per packet (all leading dimensions).
    """
    y = np.asarray(y, dtype=float)
    p = float(check_probability("prob", prob, open_upper=True))
    if y.shape[-1] != signal.dim:
        raise InputError(f"y must have last dimension {signal.dim} (the deception signal's), got {y.shape}")
    eta = rng.random(y.shape[:-1]) < p
    xi = signal.sample(rng, y.shape[:-1])
    return DeceptionOutcome(np.where(eta[..., None], xi, y), eta, xi)


def round_robin_received(y_sched, schedule: np.ndarray, n_sensors: int, strategy: str = "zero-input"):
    """The stacked received vector ``ybar_k`` of seed 000 (7) (zero input) or its zero-order-hold variant.

    ``y_sched`` (..., K, n_y) holds the (possibly attacked) packet of the scheduled sensor
    at each step; the result has shape (..., K, n_sensors, n_y): the scheduled slot holds
    the packet, the others 0 (``zero-input``) or the last packet received from that sensor
    (``zero-order-hold``, 0 before the first one).
    """
    y_sched = np.asarray(y_sched, dtype=float)
    K = y_sched.shape[-2]
    if schedule.shape != (K,):
        raise InputError(f"schedule must have shape ({K},), got {schedule.shape}")
    if strategy not in ("zero-input", "zero-order-hold"):
        raise InputError(f"strategy must be 'zero-input' or 'zero-order-hold', got {strategy!r}")
    out = np.zeros(y_sched.shape[:-2] + (K, n_sensors, y_sched.shape[-1]))
    for k in range(K):
        if strategy == "zero-order-hold" and k > 0:
            out[..., k, :, :] = out[..., k - 1, :, :]
        out[..., k, schedule[k], :] = y_sched[..., k, :]
    return out


class BinaryOutcome(NamedTuple):
    y: np.ndarray  # received signal tau * theta_bar + eps (..., S)
    theta: np.ndarray  # sensor bits before the flip
    theta_bar: np.ndarray  # bits after the flipping attack
    dos: np.ndarray  # bool
    deception: np.ndarray  # bool
    flip: np.ndarray  # bool


def binary_sensor_channel(yhat, *, dos_prob: float, deception_prob: float, flip_prob: float, deception: Noise,
                          threshold: float, gain: float, channel_noise: Noise,
                          rng: np.random.Generator) -> BinaryOutcome:
    """Seed 002 (3)-(7): DoS and deception on the readings, thresholding, bit flipping, noisy channel.

    ``ybar = (1 - phi)(yhat + varphi (mu - yhat))`` with DoS ``phi`` and deception ``varphi``
    (independent Bernoullis, ``mu ~ deception``); ``theta = 1[ybar > threshold]``;
    ``theta_bar = theta`` XOR ``alpha`` (flip); ``y = gain * theta_bar + eps``.
    """
    yhat = np.asarray(yhat, dtype=float)
    pd = float(check_probability("dos_prob", dos_prob, open_upper=True))
    pv = float(check_probability("deception_prob", deception_prob, open_upper=True))
    pf = float(check_probability("flip_prob", flip_prob, open_upper=True))
    if threshold <= 0:
        raise InputError(f"threshold must be > 0, got {threshold!r}")
    shape = yhat.shape
    dos = rng.random(shape) < pd
    dec = rng.random(shape) < pv
    mu = deception.sample(rng, shape)[..., 0]
    ybar = np.where(dos, 0.0, np.where(dec, mu, yhat))
    theta = ybar > threshold
    flip = rng.random(shape) < pf
    theta_bar = theta ^ flip
    eps = channel_noise.sample(rng, shape)[..., 0]
    return BinaryOutcome(gain * theta_bar + eps, theta, theta_bar, dos, dec, flip)
