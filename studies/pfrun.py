"""Run the particle filters of the studies on many Monte Carlo runs, with either engine.

* ``engine="fast"`` (default) — the fused numba kernels of :mod:`filters.fused`:
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

Both return the fusion centre's :class:`filters.result.FilterResult`: the weighted means
(runs, K + 1, n_x) as its estimate, the (runs, K) collapse flags in ``detail.collapsed``.
``warm_up=True`` only compiles the fast engine's kernels (a few seconds per model at its
first run on a machine, then loaded from the on-disk cache) on a one-step problem and
returns None, so that timings measure filtering, not compilation.

The studies run these inside a :mod:`studies.runner` task, one chunk of runs at a
time; ``threads`` is the number of threads of the fused engine within a chunk (worker
*processes* are the runner's ``workers``).  The compiled kernels are kept in memory per
:class:`designer.Model` object and on disk per machine (:mod:`filters.fused`), so the
tasks rebuild their scenario from a :class:`studies.scenarios.ScenarioRef` (built once per
process and reference): a worker process forked after the parent compiled
(``Backend("processes")``) reuses the parent's kernels, and any other worker loads them
from the disk cache once per model, not once per chunk.

A study's filters are the entries of a :class:`studies.filter_registry.FilterRegistry`, as the comparison's
(:func:`particle_entry`: a fusion centre's particle filter whose ``run(chunk, js, design)`` returns its
:class:`filters.result.FilterResult` on a :class:`Chunk`); the task sends the study's picklable configurations
to the worker, which builds the registry from them (an entry holds the scenario's model, which does not pickle:
CasADi), and :func:`run_registry` runs every entry on the chunk.
:func:`score` turns a filter's concatenated runs into its metrics
(:func:`studies.results.error_metrics`, time, collapses); :func:`check_study_options`
checks the options the particle-filter studies share.
"""
from __future__ import annotations

import functools
import time
from typing import Callable, Mapping, NamedTuple, Sequence

import numpy as np

from designer.attacks import BinarySensorChannel
from designer.cores import usable_cores
from designer.model import Model
from designer.noise import Noise
from designer.progress import progress
from designer.validation import InputError, check_int
from filters.binary import binary_coefficients, binary_loglik
from filters.particle import run_sir
from filters.result import FilterResult
from filters.rrp import deception_terms, packet_loglik

from .filter_registry import FilterEntry, FilterRegistry
from .pipeline import naming_filter
from .results import error_metrics

__all__ = ["ENGINES", "run_packets", "run_binary", "score", "score_configurations",
           "Chunk", "particle_entry", "run_registry",
           "results_block", "THREADS_AUTO", "check_threads", "study_threads", "check_engine", "check_study_options",
           "position_velocity"]

ENGINES = ("fast", "numpy")


#: The default of the studies' ``threads`` option: see :func:`study_threads`.
THREADS_AUTO = "auto"


def check_threads(threads) -> int | str:
    """``threads``: threads of the fused engine within a chunk of runs, an integer >= 1 or ``'auto'``."""
    if isinstance(threads, str):
        if threads.strip() == THREADS_AUTO:
            return THREADS_AUTO
        raise InputError(f"threads must be 'auto' or an integer >= 1, got {threads!r}")
    return check_int("threads", threads, 1)


def study_threads(so) -> int:
    """The threads of a study's fused engine within a chunk: its ``threads`` option, ``'auto'`` resolved.

    ``'auto'`` (the default): the cores this process may run on, shared among the runner's
    local worker processes (``--workers N``: ``cores // N``, at least 1); 1 on a Dask
    cluster, whose workers bring their own threads.  The NumPy engine (``engine='numpy'``)
    runs a chunk in one thread, whatever the option.  The numbers do not depend on it
    (one Generator per run); the time per step is the wall time shared among the runs
    computed together, so with more threads it is the machine's, not one core's.
    """
    threads = check_threads(so["threads"])
    if so["engine"] == "numpy":
        return 1
    if threads != THREADS_AUTO:
        return threads
    backend = so.backend
    if backend.kind == "dask":
        return 1
    return max(1, usable_cores() // (backend.workers if backend.kind == "processes" else 1))


def check_study_options(options) -> None:
    """The options the particle-filter studies share (``engine``, ``threads``), checked before any work.

    ``options`` is the study's :class:`studies.pipeline.StudyOptions`.
    """
    check_engine(options["engine"])
    check_threads(options["threads"])


def position_velocity(model: Model) -> tuple[list[int], list[int]]:
    """The components scored as position and velocity: the model's, the whole state as position without them."""
    return list(model.position_index) or list(range(model.n_x)), list(model.velocity_index)


def score(truth: np.ndarray, mean: np.ndarray, collapsed: np.ndarray, seconds: np.ndarray,
          position: Sequence[int], velocity: Sequence[int], rng: np.random.Generator) -> dict:
    """The metrics of one filter from the runner's per-run arrays: :func:`studies.results.error_metrics`, time,
    collapses.

    ``truth`` and ``mean`` (runs, K + 1, n_x), ``collapsed`` (runs, K), ``seconds`` (runs,):
    each run's share of its chunk's wall time for this filter.  ``wall_time_s`` is their
    sum (the filter's time over every chunk, however the chunks were spread) and
    ``time_per_step_s`` = ``wall_time_s`` / (runs x K).  Without ``velocity`` components
    the velocity metrics are None.
    """
    runs, K = collapsed.shape
    met = error_metrics(truth[:, 1:] - mean[:, 1:], position, velocity, rng)
    if not len(velocity):  # a model without velocity components: no velocity error (the draws are kept)
        met.update({"rmse_velocity": None, "rmse_velocity_ci95": None, "rmse_velocity_curve": None})
    wall = float(np.sum(seconds))
    met.update({"time_per_step_s": wall / (runs * K), "wall_time_s": wall, "collapsed_steps": int(collapsed.sum()),
                "collapsed_runs": int(collapsed.any(axis=1).sum())})
    return met


class Chunk(NamedTuple):
    """A particle study's input on a chunk of Monte Carlo runs: what its registry's entries run on (as the
    comparison's run on a :class:`studies.filter_registry.Batch`).

    ``truth`` (R, K + 1, n_x); ``streams[r][c]``: run ``r``'s SeedSequence of the ``c``-th configuration's
    stream; ``data``: the received data, keyed as the study keys it; ``run_ids``: the chunk's runs in the study.
    """

    truth: np.ndarray
    streams: Sequence
    data: Mapping
    run_ids: Sequence[int] | None = None

    def rngs(self, stream: int) -> list[np.random.Generator]:
        """Each run's Generator of stream ``stream`` (fresh at every call)."""
        return [np.random.default_rng(s[stream]) for s in self.streams]


def _per_step(n: int, network, iterations: int) -> int:
    return n


def particle_entry(name: str, description: str, run: Callable, messages: int) -> FilterEntry:
    """A particle study's filter as a registry entry: a fusion centre's particle filter (family ``particle``,
    runtime ``centralized``), ``run(chunk, js, design)`` its :class:`filters.result.FilterResult` on the runs of a
    :class:`Chunk` (one setting: ``js`` and ``design`` unused), ``messages`` the packets it receives per step.
    The studies build it in the worker from their configurations (``run`` a ``functools.partial`` of a
    module-level function), as the worker builds the scenario."""
    return FilterEntry(name, "particle", "centralized", description, run, functools.partial(_per_step, int(messages)),
                       particles=True)


def run_registry(chunk: Chunk, registry: FilterRegistry, *,
                 extra: Mapping[str, Callable[[FilterResult], np.ndarray]] | None = None,
                 label: str | None = None) -> dict:
    """The task's arrays of a particle study: every entry of ``registry`` on the chunk's runs.

    Returns ``truth`` and, along a filter axis in the registry's order, ``mean`` (the fusion centre's estimate),
    ``collapsed`` (``detail.collapsed``), ``seconds`` (each run's share of the filter's wall time) and, for every
    ``name: fn`` of ``extra``, ``fn(result)`` (runs, ...) of each filter's result (whose ``seconds`` is then that
    share), e.g. its family's arrays of ``detail``.  ``label``: a progress bar over the filters (shown on a
    terminal).  A filter whose numbers leave finite ones fails the chunk naming the filter, the study's run and
    the step.
    """
    truth = chunk.truth
    R, K1, n_x = truth.shape
    F = len(registry)
    mean = np.empty((R, F, K1, n_x))
    collapsed = np.empty((R, F, K1 - 1), dtype=bool)
    seconds = np.empty((R, F))
    extra = dict(extra or {})
    more: dict[str, list] = {name: [] for name in extra}
    for j, entry in enumerate(progress(registry, F, label is None, label or "")):
        t0 = time.perf_counter()
        with naming_filter(entry.name, chunk.run_ids):
            res = entry.run(chunk, (0,), None)
        seconds[:, j] = (time.perf_counter() - t0) / R
        mean[:, j], collapsed[:, j] = res.x[:, :, 0], res.detail.collapsed
        res = res._replace(seconds=seconds[:, j].copy())
        for name, fn in extra.items():
            more[name].append(fn(res))
    return {"truth": truth, "mean": mean, "collapsed": collapsed, "seconds": seconds,
            **{name: np.stack(arrays, axis=1) for name, arrays in more.items()}}


def score_configurations(arrays, filters: Sequence, reused: Mapping[str, str], names: Sequence[str], model: Model,
                         seed: int, describe: Callable) -> dict[str, dict]:
    """Every configuration's metrics (:func:`score`) from the runner's arrays of a seed 000 / 002 study.

    ``filters`` are the computed configurations (with ``name``; index ``j`` along the
    arrays' filter axis: ``truth`` (runs, K + 1, n_x), ``mean`` (runs, F, K + 1, n_x),
    ``collapsed`` (runs, F, K), ``seconds`` (runs, F)), ``reused`` maps a name to the
    configuration whose numbers it shares, and ``names`` is every configuration in order:
    the bootstrap draws follow it, from ``SeedSequence(seed).spawn(runs + 1)[runs]``.
    ``describe(f)`` adds a computed filter's own keys.
    """
    A = arrays
    runs = A["truth"].shape[0]
    pos, vel = position_velocity(model)
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(runs + 1)[runs])
    index = {f.name: j for j, f in enumerate(filters)}
    computed: dict[str, dict] = {}
    for name in names:
        if name in reused:
            computed[name] = computed[reused[name]]
            continue
        j = index[name]
        met = score(A["truth"], np.ascontiguousarray(A["mean"][:, j]), A["collapsed"][:, j], A["seconds"][:, j],
                    pos, vel, rng)
        met.update(describe(filters[j]))
        computed[name] = met
    return computed


def results_block(study: str, sc, so, mc, assumptions: Sequence[str], filters: dict, sweeps: dict,
                  paper: dict | None) -> dict:
    """The results of a seed 000 / 002 study (all but the header the pipeline stamps).

    ``paper`` (the published numbers and the Kalman velocity reference) is given for the
    paper's own scenario only; elsewhere it and the assumption on the Kalman reference are
    left out, and a model without position / velocity components says how it is scored.
    """
    m = sc.model
    notes = [a for a in assumptions if paper is not None or "kalman_velocity" not in a]
    if not (m.position_index and m.velocity_index):
        notes.append(f"{study}: the model declares no position components, so 'position' is the whole state; "
                     "without velocity components the velocity metrics are left out (null)."
                     if not m.position_index else
                     f"{study}: the model declares no velocity components; the velocity metrics are left out (null).")
    out = {"scenario": sc.name, "runs": int(so.runs), "particles": so.particles, "steps": int(sc.steps),
           "assumptions": list(sc.assumptions) + notes, "engine": so["engine"], "threads": study_threads(so),
           "runner": mc.describe(), "filters": filters, "sweeps": sweeps}
    if paper is not None:
        out["paper"] = paper
    out["params"] = dict(sc.params)
    return out


def check_engine(engine: str) -> None:
    if engine not in ENGINES:
        raise InputError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")


def _prior_particles(model: Model, rngs: Sequence[np.random.Generator], particles: int) -> np.ndarray:
    """Each run's initial particles from its own Generator (the first draws of its stream, as in run_sir)."""
    return np.stack([model.prior.sample(g, particles) for g in rngs])


def run_packets(model: Model, y: np.ndarray, sensors: np.ndarray, rngs: Sequence[np.random.Generator], *,
                particles: int, attack_prob: float = 0.0, signal: Noise | None = None, angles: Sequence[int] = (),
                engine: str = "fast", threads: int = 1, linear_weights: bool = False,
                warm_up: bool = False) -> FilterResult | None:
    """Filters of seed 000: ``y`` (runs, K, P, n_y) received packets, packet p at step k from ``sensors[k, p]``;
    the fusion centre's :class:`filters.result.FilterResult` (``P`` messages per step), None with ``warm_up``.

    ``linear_weights``: emulated linear-domain weights, in either engine (the same rule:
    :func:`filters.particle.run_sir`, :func:`filters.fused.sir_packets`).
    """
    check_engine(engine)
    R, K, P, ny = y.shape
    if engine == "numpy":
        if warm_up:
            return None
        ll = packet_loglik(model, sensors, attack_prob=attack_prob, signal=signal, angles=angles)
        return run_sir(model, y.reshape(R, K, P * ny), rngs[0], particles=particles, runs=R, loglik=ll,
                       linear_weights=linear_weights, uplinks=P)
    from filters import fused

    log_clean, attack = deception_terms(y, attack_prob, signal)
    if warm_up:  # compile outside the timed call: one run, two particles, one step
        g = np.random.default_rng(0)
        # the step whose attack terms are most often finite, so that the variant compiled is the one used
        k = int(np.argmax(np.isfinite(attack).sum(axis=(0, 2)))) if attack.ndim == 3 else 0
        fused.sir_packets(model, model.prior.sample(g, (1, 2)), [g], sensors[k:k + 1], y[:1, k:k + 1],
                          attack=attack[:1, k:k + 1], log_clean=log_clean, angles=angles)
        return None
    return fused.sir_packets(model, _prior_particles(model, rngs, particles), rngs, sensors, y, attack=attack,
                             log_clean=log_clean, angles=angles, threads=threads, linear_weights=linear_weights)


def run_binary(model: Model, y: np.ndarray, rngs: Sequence[np.random.Generator], *, particles: int,
               channel: BinarySensorChannel, engine: str = "fast", threads: int = 1,
               warm_up: bool = False) -> FilterResult | None:
    """Filters of seed 002: ``y`` (runs, K, S) received binary-channel signals; the fusion centre's
    :class:`filters.result.FilterResult` (``S`` messages per step), None with ``warm_up``.

    ``channel`` is the channel the filter's likelihood assumes (its attack probabilities
    may differ from those that produced ``y``).
    """
    check_engine(engine)
    kw = dict(threshold=channel.threshold, gain=channel.gain, channel_noise=channel.channel_noise,
              deception=channel.deception, dos_prob=channel.dos_prob, deception_prob=channel.deception_prob,
              flip_prob=channel.flip_prob)
    if engine == "numpy":
        if warm_up:
            return None
        return run_sir(model, y, rngs[0], particles=particles, runs=y.shape[0], loglik=binary_loglik(model, **kw))
    from filters import fused

    A, B = binary_coefficients(y, **kw)
    threshold = channel.threshold
    if warm_up:  # compile outside the timed call: one run, two particles, one step
        g = np.random.default_rng(0)
        fused.sir_binary(model, model.prior.sample(g, (1, 2)), [g], A[:1, :1], B[:1, :1], threshold=threshold)
        return None
    return fused.sir_binary(model, _prior_particles(model, rngs, particles), rngs, A, B, threshold=threshold,
                            threads=threads)
