"""Run the particle filters of the studies on many Monte Carlo runs, with either engine.

* ``engine="numpy"`` — :func:`filters.particle.run_sir`, all runs batched in one
  array program; the reference implementation (any noise, any proposal).  It draws
  every run's particles from one Generator (the first run's filter stream), so its
  numbers depend on the number of runs in the batch.

Both return ``(mean, collapsed)``: weighted means (runs, K + 1, n_x) and the
(runs, K) collapse flags.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from designer.model import Model
from designer.noise import Noise
from designer.validation import InputError
from filters.binary import binary_loglik
from filters.particle import run_sir
from filters.rrp import packet_loglik

__all__ = ["ENGINES", "run_packets", "run_binary"]

ENGINES = ("numpy",)


def _check_engine(engine: str) -> None:
    if engine not in ENGINES:
        raise InputError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")


def run_packets(model: Model, y: np.ndarray, sensors: np.ndarray, rngs: Sequence[np.random.Generator], *,
                particles: int, attack_prob: float = 0.0, signal: Noise | None = None, angles: Sequence[int] = (),
                engine: str = "numpy", workers: int = 1, linear_weights: bool = False):
    """Filters of seed 000: ``y`` (runs, K, P, n_y) received packets, packet p at step k from ``sensors[k, p]``."""
    _check_engine(engine)
    R, K, P, ny = y.shape
    ll = packet_loglik(model, sensors, attack_prob=attack_prob, signal=signal, angles=angles)
    res = run_sir(model, y.reshape(R, K, P * ny), rngs[0], particles=particles, runs=R, loglik=ll,
                  linear_weights=linear_weights)
    return res.mean, res.collapsed


def run_binary(model: Model, y: np.ndarray, rngs: Sequence[np.random.Generator], *, particles: int,
               threshold: float, gain: float, channel_noise: Noise, deception: Noise, dos_prob: float = 0.0,
               deception_prob: float = 0.0, flip_prob: float = 0.0, engine: str = "numpy", workers: int = 1):
    """Filters of seed 002: ``y`` (runs, K, S) received binary-channel signals."""
    _check_engine(engine)
    kw = dict(threshold=threshold, gain=gain, channel_noise=channel_noise, deception=deception, dos_prob=dos_prob,
              deception_prob=deception_prob, flip_prob=flip_prob)
    res = run_sir(model, y, rngs[0], particles=particles, runs=y.shape[0], loglik=binary_loglik(model, **kw))
    return res.mean, res.collapsed
