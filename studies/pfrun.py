"""Run the particle filters of the studies on many Monte Carlo runs, with either engine.

* ``engine="fast"`` (default) — the fused numba kernels of :mod:`filters.fastsir`:
  one Generator per run (spawned from the study seed), initial particles drawn
  from the model's prior with that Generator, runs spread over ``workers``
  threads.  A run's numbers depend only on its own seed, not on the number of
  workers or of runs.
* ``engine="numpy"`` — :func:`filters.particle.run_sir`, all runs batched in one
  array program; the reference implementation (any noise, any proposal).  It draws
  every run's particles from one Generator (the first run's filter stream), so its
  numbers depend on the number of runs in the batch.

Both return ``(mean, collapsed)``: weighted means (runs, K + 1, n_x) and the
(runs, K) collapse flags.  ``warm_up=True`` only compiles the fast engine's kernels
(a few seconds per model and process) on a one-step problem and returns None, so
that timings measure filtering, not compilation.
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

ENGINES = ("fast", "numpy")


def _check_engine(engine: str) -> None:
    if engine not in ENGINES:
        raise InputError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")


def _prior_particles(model: Model, rngs: Sequence[np.random.Generator], particles: int) -> np.ndarray:
    """Each run's initial particles from its own Generator (the first draws of its stream, as in run_sir)."""
    return np.stack([model.prior.sample(g, particles) for g in rngs])


def run_packets(model: Model, y: np.ndarray, sensors: np.ndarray, rngs: Sequence[np.random.Generator], *,
                particles: int, attack_prob: float = 0.0, signal: Noise | None = None, angles: Sequence[int] = (),
                engine: str = "fast", workers: int = 1, linear_weights: bool = False, warm_up: bool = False):
    """Filters of seed 000: ``y`` (runs, K, P, n_y) received packets, packet p at step k from ``sensors[k, p]``.

    ``linear_weights`` (emulated linear-domain weights) exists only in the NumPy engine.
    """
    _check_engine(engine)
    R, K, P, ny = y.shape
    if engine == "numpy":
        if warm_up:
            return None
        ll = packet_loglik(model, sensors, attack_prob=attack_prob, signal=signal, angles=angles)
        res = run_sir(model, y.reshape(R, K, P * ny), rngs[0], particles=particles, runs=R, loglik=ll,
                      linear_weights=linear_weights)
        return res.mean, res.collapsed
    if linear_weights:
        raise InputError("linear_weights needs engine='numpy' (the fused kernels keep log weights only)")
    from filters import fastsir

    log_clean, attack = fastsir.deception_terms(y, attack_prob, signal)
    if warm_up:  # compile outside the timed call: one run, two particles, one step
        g = np.random.default_rng(0)
        # the step whose attack terms are most often finite, so that the variant compiled is the one used
        k = int(np.argmax(np.isfinite(attack).sum(axis=(0, 2)))) if attack.ndim == 3 else 0
        fastsir.sir_packets(model, model.prior.sample(g, (1, 2)), [g], sensors[k:k + 1], y[:1, k:k + 1],
                            attack=attack[:1, k:k + 1], log_clean=log_clean, angles=angles)
        return None
    res = fastsir.sir_packets(model, _prior_particles(model, rngs, particles), rngs, sensors, y, attack=attack,
                              log_clean=log_clean, angles=angles, workers=workers)
    return res.mean, res.collapsed


def run_binary(model: Model, y: np.ndarray, rngs: Sequence[np.random.Generator], *, particles: int,
               threshold: float, gain: float, channel_noise: Noise, deception: Noise, dos_prob: float = 0.0,
               deception_prob: float = 0.0, flip_prob: float = 0.0, engine: str = "fast", workers: int = 1,
               warm_up: bool = False):
    """Filters of seed 002: ``y`` (runs, K, S) received binary-channel signals."""
    _check_engine(engine)
    kw = dict(threshold=threshold, gain=gain, channel_noise=channel_noise, deception=deception, dos_prob=dos_prob,
              deception_prob=deception_prob, flip_prob=flip_prob)
    if engine == "numpy":
        if warm_up:
            return None
        res = run_sir(model, y, rngs[0], particles=particles, runs=y.shape[0], loglik=binary_loglik(model, **kw))
        return res.mean, res.collapsed
    from filters import fastsir

    A, B = fastsir.binary_coefficients(y, **kw)
    if warm_up:  # compile outside the timed call: one run, two particles, one step
        g = np.random.default_rng(0)
        fastsir.sir_binary(model, model.prior.sample(g, (1, 2)), [g], A[:1, :1], B[:1, :1], threshold=threshold)
        return None
    res = fastsir.sir_binary(model, _prior_particles(model, rngs, particles), rngs, A, B, threshold=threshold,
                             workers=workers)
    return res.mean, res.collapsed
