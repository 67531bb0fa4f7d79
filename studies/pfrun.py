"""Run the particle filters of the studies on many Monte Carlo runs, with either engine.

* ``engine="fast"`` (default) — the fused numba kernels of :mod:`filters.fastsir`:
  one Generator per run (spawned from the study seed), initial particles drawn
  from the model's prior with that Generator, runs spread over ``threads``
  threads.  A run's numbers depend only on its own seed, not on the number of
  threads, of runs or on how the runs are cut into chunks.
* ``engine="numpy"`` — :func:`filters.particle.run_sir`, all runs of a call batched
  in one array program; the reference implementation (any noise, any proposal).
  It draws every run's particles from one Generator (the first run's filter
  stream), so its numbers depend on the runs batched together: in the studies,
  one chunk of the Monte Carlo runner (``chunk_size`` consecutive runs, the first
  run's stream).

Both return ``(mean, collapsed)``: weighted means (runs, K + 1, n_x) and the
(runs, K) collapse flags.  ``warm_up=True`` only compiles the fast engine's kernels
(a few seconds per model and process) on a one-step problem and returns None, so
that timings measure filtering, not compilation.

The studies run these inside a :mod:`studies.runner` task, one chunk of runs at a
time; ``threads`` is the number of threads of the fused engine within a chunk.
The compiled kernels are cached per :class:`designer.Model` object, so the tasks
take their scenario from :func:`cached_scenario`: a worker process forked after the
parent compiled (``Backend("processes")``) reuses the parent's kernels, and any
other worker compiles once per model, not once per chunk.  :func:`score` turns a
filter's concatenated runs into its metrics (:func:`studies.results.error_metrics`, time, collapses).
"""
from __future__ import annotations

import json
import warnings
from typing import Any, Mapping, Sequence

import numpy as np

from designer.model import Model
from designer.noise import Noise
from designer.validation import InputError, check_int
from filters.binary import binary_loglik
from filters.particle import run_sir
from filters.rrp import packet_loglik

from .results import error_metrics
from .scenarios import load_scenario

__all__ = ["ENGINES", "run_packets", "run_binary", "cached_scenario", "plain_params", "score", "check_threads",
           "check_engine"]

ENGINES = ("fast", "numpy")


_SCENARIOS: dict = {}  # (name, parameters as JSON) -> Scenario; see cached_scenario
_SCENARIOS_MAX = 8


def cached_scenario(name: str, params: Mapping[str, Any]):
    """The scenario ``name`` built with every parameter given in ``params``, once per process.

    A memo, not state: the same ``(name, params)`` always builds the same scenario.  It
    exists because the fused engine caches its compiled kernels per Model object; a
    task that rebuilt its scenario for every chunk would recompile them every time.
    """
    key = (name, json.dumps(dict(params), sort_keys=True, default=str))
    sc = _SCENARIOS.get(key)
    if sc is None:
        if len(_SCENARIOS) >= _SCENARIOS_MAX:
            _SCENARIOS.clear()
        sc = _SCENARIOS[key] = load_scenario(name, dict(params))
    return sc


def plain_params(params: Mapping[str, Any]) -> dict:
    """A scenario's parameters as JSON values (arrays as nested lists), for tasks and stored configs."""
    return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in params.items()}


def check_threads(threads, workers) -> int:
    """``threads``, or the deprecated ``workers`` given in its place (both given: they must agree)."""
    if workers is not None:
        workers = check_int("workers", workers, 1)
        warnings.warn("the 'workers' parameter of the particle-filter studies is now 'threads' (threads of the "
                      "fused engine within a chunk of runs); pass backend= for worker processes",
                      DeprecationWarning, stacklevel=3)
        if threads is not None and check_int("threads", threads, 1) != workers:
            raise InputError(f"threads ({threads}) and its deprecated alias workers ({workers}) disagree")
        return workers
    return check_int("threads", 1 if threads is None else threads, 1)


def check_study_options(*, runs, particles, seed, threads, workers, engine, chunk_size, backend):
    """The run options shared by the particle-filter studies, checked before any work:
    ``(runs, particles, seed, threads, chunk_size, backend)``."""
    from .runner import Backend

    runs = check_int("runs", runs, 2)
    particles = check_int("particles", particles, 1)
    seed = check_int("seed", seed, 0)
    threads = check_threads(threads, workers)
    check_engine(engine)
    chunk_size = check_int("chunk_size", chunk_size, 1)
    backend = backend or Backend()
    if not isinstance(backend, Backend):
        raise InputError(f"backend must be a studies.runner.Backend, got {type(backend).__name__}")
    return runs, particles, seed, threads, chunk_size, backend


def score(truth: np.ndarray, mean: np.ndarray, collapsed: np.ndarray, seconds: np.ndarray,
          position: Sequence[int], velocity: Sequence[int], rng: np.random.Generator) -> dict:
    """The metrics of one filter from the runner's per-run arrays: :func:`studies.results.error_metrics`, time, collapses.

    ``truth`` and ``mean`` (runs, K + 1, n_x), ``collapsed`` (runs, K), ``seconds`` (runs,):
    each run's share of its chunk's wall time for this filter.  ``wall_time_s`` is their
    sum (the filter's time over every chunk, however the chunks were spread) and
    ``time_per_step_s`` = ``wall_time_s`` / (runs x K).
    """
    runs, K = collapsed.shape
    met = error_metrics(truth[:, 1:] - mean[:, 1:], position, velocity, rng)
    wall = float(np.sum(seconds))
    met.update({"time_per_step_s": wall / (runs * K), "wall_time_s": wall, "collapsed_steps": int(collapsed.sum()),
                "collapsed_runs": int(collapsed.any(axis=1).sum())})
    return met


def check_engine(engine: str) -> None:
    if engine not in ENGINES:
        raise InputError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")


def _prior_particles(model: Model, rngs: Sequence[np.random.Generator], particles: int) -> np.ndarray:
    """Each run's initial particles from its own Generator (the first draws of its stream, as in run_sir)."""
    return np.stack([model.prior.sample(g, particles) for g in rngs])


def run_packets(model: Model, y: np.ndarray, sensors: np.ndarray, rngs: Sequence[np.random.Generator], *,
                particles: int, attack_prob: float = 0.0, signal: Noise | None = None, angles: Sequence[int] = (),
                engine: str = "fast", threads: int = 1, linear_weights: bool = False, warm_up: bool = False):
    """Filters of seed 000: ``y`` (runs, K, P, n_y) received packets, packet p at step k from ``sensors[k, p]``.

    ``linear_weights`` (emulated linear-domain weights) exists only in the NumPy engine.
    """
    check_engine(engine)
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
                              log_clean=log_clean, angles=angles, workers=threads)
    return res.mean, res.collapsed


def run_binary(model: Model, y: np.ndarray, rngs: Sequence[np.random.Generator], *, particles: int,
               threshold: float, gain: float, channel_noise: Noise, deception: Noise, dos_prob: float = 0.0,
               deception_prob: float = 0.0, flip_prob: float = 0.0, engine: str = "fast", threads: int = 1,
               warm_up: bool = False):
    """Filters of seed 002: ``y`` (runs, K, S) received binary-channel signals."""
    check_engine(engine)
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
                             workers=threads)
    return res.mean, res.collapsed
