"""Study ``encrypted-switching``: seed 001's simulation study (ED-PF under switching nonlinearities).

Three filters on the same runs (common random numbers): PPF (the mixture proposal
(11) and the interval likelihood (13)-(15)), PF-RSN (the same likelihood with a
model that ignores the switching, γ = 1) and PF-SR-DE (the decrypted values taken
as the measurements, the noise density as the likelihood); see
:mod:`filters.edpf`.  Outputs: RMSE_1(t) and RMSE_2(t) over the runs (Figs. 5-6)
and their time averages with bootstrap intervals, the one-run figures of the
states and estimates (Figs. 1-2) and of the ideal, resolution-limited and
decrypted measurements (Figs. 3-4), time per step (with, on the NumPy engine, where
it goes: proposal, likelihood, the rest of the engine), collapses.  The paper
prints no numbers; its claim is that PPF is best.

It runs on ``switching-2d`` by default and on any scenario whose channel is a
:class:`filters.encryption.EncryptedChannel` (a model file's ``CHANNEL``) and whose
model switches between modes (``mode`` with at least two modes; PF-RSN keeps mode 1
always, the paper's γ = 1), with scalar sensors of truncated-Gaussian noise and no
known inputs.  The paper's claim is quoted for ``switching-2d`` only (the claim
check, PPF against both baselines, is computed everywhere).

Engines (the ``engine`` option): ``"fast"`` (default) — the fused numba kernels of
:mod:`filters.fused.edpf`, runs spread over ``threads`` threads; ``"numpy"`` —
:func:`filters.particle.run_sir` with :mod:`filters.edpf`'s likelihoods, the
reference (``threads`` must be 1).  ``mean_dynamics_row`` adds PF-RSN with the
mode-averaged dynamics (not in the paper).

Structure: :func:`compute_runs` does the per-run work (data, channel, every filter)
for a chunk of runs given their SeedSequences and a :class:`RunConfig`, and returns
a mapping of arrays whose first axis is the run (``functools.partial(compute_runs,
config=config)`` is the task of the Monte Carlo runner); chunks are joined with
:func:`concatenate_runs` and :func:`summarize` computes the metrics, tables and
figures' data from the joined arrays.  The filters are the entries of a
:class:`studies.filter_registry.FilterRegistry` (:func:`registry`, built in the worker
from the picklable :class:`RunConfig`), run on the chunk by :func:`studies.pfrun.run_registry`
as the other particle studies' are; the NumPy engine's time split is the one
:func:`filters.particle.run_sir` measures (its ``detail``).  ``STUDY`` is the study's
:class:`studies.pipeline.Study`.

Randomness: run ``r`` uses ``SeedSequence(seed).spawn(runs)[r].spawn(3)`` =
(truth, channel, filters).  The truth's draws are taken per run before any
propagation (:func:`designer.simulate.simulate_runs`: x(0), the modes, the process
noises, each sensor's noises); the channel's are the key stream, then the bit-error
and dropout uniforms (:func:`filters.encryption.transmit_runs`, as ``transmit``).
The fast engine gives each run's filters a Generator built from the run's filter
stream (each filter starts it afresh, so the filters share their random numbers as
well as their data): a run's numbers depend only on ``seed`` and ``r``, not on the
number of runs, the chunks or ``threads``.  The NumPy engine runs a chunk in one
batch and draws all its particles from one Generator built from the chunk's first
run's filter stream (so its numbers depend on the chunking).
"""
from __future__ import annotations

import functools
import pickle
import time
from pathlib import Path
from typing import Any, Mapping, NamedTuple, Sequence

import numpy as np

from designer.noise import TruncatedGaussian
from designer.simulate import simulate_runs
from designer.validation import InputError, check_int
from filters.edpf import fixed_mode_model, interval_loglik, mean_dynamics_model, raw_loglik, received
from filters.encryption import CRC4_ITU, Codec, EncryptedChannel
from filters.particle import SIRResult, run_sir
from filters.result import FilterResult

from .filter_registry import FilterRegistry
from .pfrun import THREADS_AUTO, Chunk, check_engine, check_threads, particle_entry, run_registry, study_threads
from .pipeline import Plan, Study, StudyOptions
from .figures import curves_figure, filter_colours
from .results import curve_mean_ci, markdown_table
from .scenarios import Scenario, ScenarioRef, reference
from .study_registry import StudyText

__all__ = ["STUDY", "RunConfig", "compute_runs", "concatenate_runs", "summarize", "warm_up", "filter_names",
           "registry", "FILTERS", "MEAN_DYNAMICS", "PAPER", "CHUNK_SIZE"]

SCENARIO = "switching-2d"
FILTERS = ("PPF", "PF-RSN", "PF-SR-DE")
MEAN_DYNAMICS = "PF-RSN (mean dynamics)"
PAPER = {
    "source": "seed 001, Sec. IV, Figs. 5-6 (RMSE_1(t), RMSE_2(t) over 50 runs)",
    "numbers": None,
    "claim": "the proposed algorithm (PPF) exhibits superior filtering performance when compared with the other "
             "two algorithms (PF-RSN, PF-SR-DE)",
    "runs": 50, "particles": 200, "steps": 120,
    "note": "no RMSE values are printed; Figs. 1-6 are not available in the text, so only the ordering is compared",
}
ESS_THRESHOLD = 0.5  # resample when ESS < M/2
CHUNK_SIZE = 25  # runs per stored chunk: part of the study (fixes the NumPy engine's batches), not of the backend

ASSUMPTIONS = (
    "encrypted-switching: resampling is systematic when ESS < M/2 (Algorithm 1 says only 'if necessary, e.g. when "
    "the effective sample size is less than a given value'); the estimate is the weighted mean before resampling.",
    "encrypted-switching: PF-RSN (the paper does not define its dynamics) assumes gamma = 1 at every step, "
    "x(t+1) = F x + f(x) + eta, with PPF's likelihood; the extra row 'PF-RSN (mean dynamics)', not in the paper, "
    "uses F x + 0.5 f(x) + 0.5 g(x) instead.",
    "encrypted-switching: PF-SR-DE (likelihood not defined in the paper) weighs the decrypted value as if it were "
    "z: the truncated-Gaussian density of z~ - h(x), zero where |z~ - h(x)| > 2; when every particle of a run gets "
    "zero weight, the run keeps its predicted particles with uniform weights and the step counts as a collapse.",
    "encrypted-switching: every filter starts from the true prior N([2, -2], 1.2^2 I); measurements at t = 1..120; "
    "RMSE_i(t) = sqrt(mean over runs of (x_i - xhat_i)^2), its time average is the mean over t = 1..T, 95 % "
    "intervals are percentile bootstraps over runs.",
    "encrypted-switching: run r's data come from its own streams (SeedSequence(seed).spawn(runs)[r].spawn(3) = "
    "truth, channel, filters; the truth's randomness drawn per run before the runs are propagated together). The "
    "filters share the data and the filter random numbers: on the fast engine (default) one Generator per run from "
    "its filter stream, restarted for every filter, so a run's numbers do not depend on the number of runs or "
    "threads; on the NumPy engine one Generator from the first run's filter stream for the whole batch, so the "
    "filter numbers depend on the number of runs.",
    "encrypted-switching: time_per_step_s = a filter's wall time over all runs divided by runs x T (amortised over "
    "the batch, and over the threads on the fast engine: 'threads', default the machine's cores); on the NumPy "
    "engine time_breakdown_s splits it into the "
    "proposal (mode and process-noise draws, f), the likelihood (h and the CDFs or densities) and the engine's "
    "remainder (weights, moments, ESS, resampling); the fast engine fuses them (its split is null).",
)
OTHER_MODEL = ("encrypted-switching (a model other than switching-2d): PF-RSN keeps mode 1 of the model's switching "
               "always; PF-RSN (mean dynamics) averages the modes' transitions with their probabilities; every "
               "filter starts from the model's prior.")


# ============================================================================ per-run work
class RunConfig(NamedTuple):
    """Everything a chunk of runs needs besides its seeds (picklable).

    ``scenario`` is a :class:`studies.scenarios.ScenarioRef` (``reference(sc)``) of a
    scenario with an :class:`filters.encryption.EncryptedChannel`.
    """

    particles: int
    scenario: ScenarioRef
    engine: str = "fast"
    threads: int = 1
    mean_dynamics_row: bool = True


class _Setup(NamedTuple):
    scenario: Any
    channel: EncryptedChannel
    filters: dict  # name -> (model, likelihood kind, description)


_SETUPS: dict[bytes, _Setup] = {}  # per process: the fused kernels are compiled per model, so the models are reused
_SETUPS_MAX = 8


def _setup(config: RunConfig) -> _Setup:
    key = pickle.dumps(config.scenario)
    setup = _SETUPS.get(key)
    if setup is None:
        sc = config.scenario.build()
        m = sc.model
        rsn = fixed_mode_model(m, 1)  # mode 1 <=> gamma = 1 (f active) in switching-2d
        filters = {
            "PPF": (m, "interval", "mixture proposal (11), interval likelihood (13)"),
            "PF-RSN": (rsn, "interval", "gamma = 1 always, interval likelihood (13)"),
            "PF-SR-DE": (m, "raw", "mixture proposal (11), noise density at the decrypted value"),
            MEAN_DYNAMICS: (mean_dynamics_model(m), "interval", "F x + 0.5 f + 0.5 g, interval likelihood (13)"),
        }
        if len(_SETUPS) >= _SETUPS_MAX:
            _SETUPS.clear()
        setup = _SETUPS[key] = _Setup(sc, sc.channel, filters)
    return setup


def filter_names(config: RunConfig) -> tuple[str, ...]:
    """The filters of ``config`` in the order of the filter axis of :func:`compute_runs`' arrays."""
    return (*FILTERS, *([MEAN_DYNAMICS] if config.mean_dynamics_row else []))


def _filters(config: RunConfig) -> dict:
    return {n: _setup(config).filters[n] for n in filter_names(config)}


def _streams(ss: np.random.SeedSequence) -> list[np.random.SeedSequence]:
    """``ss.spawn(3)`` of a fresh ``ss`` (truth, channel, filters), without changing ``ss``'s spawn counter."""
    if not isinstance(ss, np.random.SeedSequence):
        raise InputError(f"seeds must hold numpy.random.SeedSequence, got {type(ss).__name__}")
    return [np.random.SeedSequence(ss.entropy, spawn_key=ss.spawn_key + (i,), pool_size=ss.pool_size)
            for i in range(3)]


def _check_engine_threads(engine: str, threads) -> None:
    check_engine(engine)
    threads = check_threads(threads)
    if engine == "numpy" and threads not in (1, THREADS_AUTO):
        raise InputError(f"threads must be 1 with engine 'numpy' (it runs all runs in one batch), got {threads}")


def _check_config(config: RunConfig) -> RunConfig:
    if not isinstance(config, RunConfig):
        raise InputError(f"config must be a RunConfig, got {type(config).__name__}")
    check_int("particles", config.particles, 1)
    if not isinstance(config.scenario, ScenarioRef):
        raise InputError(f"config.scenario must be a studies.scenarios.ScenarioRef (reference(scenario)), got "
                         f"{type(config.scenario).__name__}")
    _check_engine_threads(config.engine, config.threads)
    return config


def _run(model, kind: str, codec: Codec, config: RunConfig, chunk: Chunk, js, design) -> FilterResult:
    """One filter on the chunk's received data ``chunk.data["received"]`` (n, T, 2 N) (a registry entry's
    ``run``): its :class:`filters.result.FilterResult`, every run's filter stream started afresh."""
    y, M = chunk.data["received"], config.particles
    if config.engine == "numpy":  # one Generator for the batch: the chunk's first run's filter stream
        ll = interval_loglik(model, codec) if kind == "interval" else raw_loglik(model)
        return run_sir(model, y, np.random.default_rng(chunk.streams[0][0]), particles=M, runs=y.shape[0],
                       loglik=ll, resampler="systematic", ess_threshold=ESS_THRESHOLD)
    from filters.fused import sir_edpf

    gens = chunk.rngs(0)
    x0 = np.stack([model.prior.sample(g, M) for g in gens])  # the first draws of each run's stream, as run_sir
    return sir_edpf(model, x0, gens, y, likelihood=kind, codec=codec if kind == "interval" else None,
                    resampler="systematic", ess_threshold=ESS_THRESHOLD, threads=config.threads)


def registry(config: RunConfig) -> FilterRegistry:
    """The study's filters of ``config`` (in the order of :func:`filter_names`), one particle entry each: a fusion
    centre receiving every sensor's packet, on the models built once per process (:func:`_setup`)."""
    setup = _setup(config)
    codec, n_sensors = setup.channel.codec, setup.scenario.model.n_sensors
    return FilterRegistry(particle_entry(name, what, functools.partial(_run, model, kind, codec, config), n_sensors)
                          for name, (model, kind, what) in _filters(config).items())


def _breakdown(res: FilterResult) -> np.ndarray:
    """(runs, 3): each run's share of the seconds in the proposal, in the likelihood and in the rest of the
    filter's call (the NumPy engine's split, measured by :func:`filters.particle.run_sir`); NaN on the fast
    engine, which fuses them."""
    d = res.detail
    if not isinstance(d, SIRResult):
        return np.full((res.runs, 3), np.nan)
    split = np.array([d.proposal_seconds, d.loglik_seconds]) / res.runs
    return np.column_stack([np.broadcast_to(split, (res.runs, 2)), res.seconds - split.sum()])


def warm_up(config: RunConfig) -> None:
    """Compile the fast engine's kernels for every filter of ``config`` (one run, two particles, one step).

    A few seconds per model and process at the first call, nothing later; the NumPy engine needs none.
    """
    config = _check_config(config)
    if config.engine != "fast":
        return
    from filters.fused import sir_edpf

    setup = _setup(config)
    y = np.zeros((1, 1, 2 * setup.scenario.model.n_sensors))
    for model, kind, _ in _filters(config).values():
        g = np.random.default_rng(0)
        sir_edpf(model, model.prior.sample(g, (1, 2)), [g], y, likelihood=kind,
                 codec=setup.channel.codec if kind == "interval" else None, ess_threshold=ESS_THRESHOLD)


#: The channel's per-run arrays of :func:`compute_runs` (``Transmission`` fields), each (n, T, N).
CHANNEL = ("z", "zr", "decrypted", "available", "dropped", "detected", "undetected", "saturated")


def compute_runs(run_ids: Sequence[int], seeds: Sequence[np.random.SeedSequence], config: RunConfig, *,
                 quiet: bool = True) -> dict[str, np.ndarray]:
    """Data, channel and every filter for the runs ``run_ids``, run ``run_ids[i]`` from its SeedSequence ``seeds[i]``.

    ``seeds[i]`` is ``SeedSequence(seed).spawn(total_runs)[run_ids[i]]`` (``=
    SeedSequence(seed, spawn_key=(run_ids[i],))``); it is not modified (its three
    streams are derived as ``spawn(3)`` of a fresh copy would be).  On the fast
    engine a run's arrays do not depend on the other runs of the chunk, so chunks may
    be computed anywhere and joined with :func:`concatenate_runs`.

    Returns arrays whose first axis is the chunk's run (``n`` of them), ``F`` filters
    in the order of :func:`filter_names`:

    ``run`` (n,), ``truth`` (n, T + 1, n_x), the channel's :data:`CHANNEL` arrays
    (n, T, N), ``mean`` (n, F, T + 1, n_x) weighted means, ``collapsed`` and
    ``resampled`` (n, F, T) bool, ``seconds`` (n, F) each run's share of the chunk's
    wall time per filter (compilation excluded), ``seconds_data`` and
    ``seconds_channel`` (n,) likewise, ``breakdown`` (n, F, 3) the NumPy engine's
    shares of proposal, likelihood and the rest (NaN on the fast engine, which fuses
    them).
    """
    config = _check_config(config)
    run_ids = np.asarray(run_ids, dtype=np.int64).reshape(-1)
    seeds = list(seeds)
    if run_ids.size < 1 or len(seeds) != run_ids.size:
        raise InputError(f"run_ids and seeds must be non-empty and of equal length, got {run_ids.size} and "
                         f"{len(seeds)}")
    streams = [_streams(ss) for ss in seeds]
    setup = _setup(config)
    sc, channel = setup.scenario, setup.channel
    n, K = run_ids.size, sc.steps
    warm_up(config)  # a no-op once compiled in this process
    t0 = time.perf_counter()
    tr = simulate_runs(sc.model, K, [np.random.default_rng(st[0]) for st in streams], x0=sc.x0,
                       inputs=sc.inputs(K))
    t1 = time.perf_counter()
    tx = channel.transmit_runs(tr.z, [np.random.default_rng(st[1]) for st in streams])
    y = received(tx)
    t2 = time.perf_counter()
    chunk = Chunk(tr.x, [(st[2],) for st in streams], {"received": y}, run_ids)  # every filter: stream 0
    a = run_registry(chunk, registry(config), extra={"resampled": lambda res: res.detail.resampled,
                                                     "breakdown": _breakdown},
                     label=None if quiet else "encrypted-switching filters")
    return {"run": run_ids, "truth": tr.x, **{k: getattr(tx, k) for k in CHANNEL},
            "mean": a["mean"], "collapsed": a["collapsed"], "resampled": a["resampled"], "seconds": a["seconds"],
            "seconds_data": np.full(n, (t1 - t0) / n), "seconds_channel": np.full(n, (t2 - t1) / n),
            "breakdown": a["breakdown"]}


def concatenate_runs(parts: Sequence[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Chunks of :func:`compute_runs` joined along the runs, in the given order."""
    parts = list(parts)
    if not parts or any(set(p) != set(parts[0]) for p in parts):
        raise InputError("parts must be one or more outputs of compute_runs (with the same arrays)")
    return {k: np.concatenate([np.asarray(p[k]) for p in parts]) for k in parts[0]}


# ============================================================================ summary
def _state_metrics(err: np.ndarray, rng: np.random.Generator) -> dict:
    """Per-state time-averaged RMSE with its bootstrap interval, the RMSE_i(t) curves, the median run's RMSE."""
    e2 = err**2
    per = [curve_mean_ci(e2[..., i], rng) for i in range(err.shape[-1])]
    return {
        "rmse_state": [v for v, _ in per],
        "rmse_state_ci95": [ci for _, ci in per],
        "rmse_state_curve": [[float(x) for x in c] for c in np.sqrt(e2.mean(axis=0)).T],
        "rmse_state_median_run": [float(v) for v in np.median(np.sqrt(e2.mean(axis=1)), axis=0)],
    }


def summarize(arrays: Mapping[str, np.ndarray], config: RunConfig, *, metrics_rng: np.random.Generator) -> dict:
    """The study's results (``results.json`` but the header the pipeline stamps) from the joined arrays of every
    run (:func:`compute_runs`)."""
    setup = _setup(config)
    sc, a = setup.scenario, arrays
    truth = a["truth"]
    runs, K = truth.shape[0], truth.shape[1] - 1
    filters: dict[str, dict] = {}
    means = {}
    for j, entry in enumerate(registry(config)):
        name, what = entry.name, entry.description
        means[name] = a["mean"][:, j]
        col = a["collapsed"][:, j]
        wall = float(a["seconds"][:, j].sum())
        split = a["breakdown"][:, j].sum(axis=0)
        met = _state_metrics(truth[:, 1:] - means[name][:, 1:], metrics_rng)
        met.update({
            "time_per_step_s": wall / (runs * K), "wall_time_s": wall, "collapsed_steps": int(col.sum()),
            "collapsed_runs": int(col.any(axis=1).sum()), "description": what, "particles": config.particles,
            "engine": config.engine, "resampled_fraction": float(a["resampled"][:, j].mean()),
            "time_breakdown_s": {k: None if np.isnan(v) else float(v)
                                 for k, v in zip(("proposal", "likelihood", "engine"), split)},
        })
        filters[name] = met
    if config.mean_dynamics_row:
        filters[MEAN_DYNAMICS]["note"] = "not in the paper: PF-RSN with the mode-averaged dynamics"
    paper = _is_paper(sc)
    out = {"scenario": sc.name, "runs": int(runs), "particles": config.particles, "steps": int(K),
           "assumptions": list(sc.assumptions) + list(ASSUMPTIONS) + ([] if paper else [OTHER_MODEL]),
           "engine": config.engine, "threads": config.threads, "filters": filters, "sweeps": {}}
    if paper:
        out["paper"] = PAPER
    out.update({
        "claim_check": _claim_check(filters, truth, means),
        "transmission": _transmission_summary(a, setup.channel.codec),
        "timing_s": {"data": float(a["seconds_data"].sum()), "channel": float(a["seconds_channel"].sum()),
                     "filters": {n: f["wall_time_s"] for n, f in filters.items()},
                     "paper_filters": sum(filters[n]["wall_time_s"] for n in FILTERS)},
        "params": dict(sc.params),
    })
    return out


def _is_paper(sc: Scenario) -> bool:
    """The paper's own scenario (its claim is quoted)."""
    return sc.source == SCENARIO


def _accepts(sc: Scenario) -> str | None:
    m = sc.model
    if not isinstance(sc.channel, EncryptedChannel):
        return ("encrypted-switching needs an encrypted channel: declare CHANNEL = EncryptedChannel(Codec(...)) "
                "(filters.encryption) in the model file")
    if m.n_modes < 2:
        return "encrypted-switching needs a model that switches between modes (Model mode= with two or more modes)"
    if m.n_u:
        return "encrypted-switching runs models without known inputs"
    bad = [s for s in m.sensors if not isinstance(s.noise, TruncatedGaussian)]
    if bad:
        return (f"encrypted-switching needs truncated-Gaussian measurement noise (PF-SR-DE's density and the fused "
                f"kernels), sensor {bad[0].name!r} has {type(bad[0].noise).__name__}")
    return None


def _check(so: StudyOptions) -> None:
    _check_engine_threads(so["engine"], so["threads"])


def _config(sc: Scenario, so: StudyOptions) -> RunConfig:
    return RunConfig(so.particles, reference(sc), so["engine"], study_threads(so), bool(so["mean_dynamics_row"]))


def _plan(sc: Scenario, so: StudyOptions) -> Plan:
    config = _config(sc, so)
    _setup(config)  # builds the filters' models once per process and reference
    ref = config.scenario
    manifest = {"study": "encrypted-switching", "particles": config.particles, "engine": config.engine,
                "mean_dynamics_row": config.mean_dynamics_row, "params": dict(ref.params),
                "channel": repr(sc.channel)}
    # compile before timing; forked workers inherit the kernels
    return Plan(functools.partial(compute_runs, config=config), "encrypted-switching", manifest,
                before=functools.partial(warm_up, config))


def _summarise(sc: Scenario, mc, so: StudyOptions) -> dict:
    metrics_rng = np.random.default_rng(np.random.SeedSequence(so.seed, spawn_key=(2**31,)))
    results = summarize(mc.arrays, _config(sc, so), metrics_rng=metrics_rng)
    results["runner"] = mc.describe()
    return results


def _claim_check(filters: dict, truth: np.ndarray, means: dict) -> dict:
    """PPF against each baseline: the ratio of time-averaged RMSEs and the share of runs where PPF is better."""
    def per_run(name):
        return np.sqrt(((truth[:, 1:] - means[name][:, 1:]) ** 2).mean(axis=1))  # (runs, n_x)

    ppf = filters["PPF"]["rmse_state"]
    out = {}
    for base in FILTERS[1:]:
        other = filters[base]["rmse_state"]
        out[base] = {
            "ppf_lower": [bool(a < b) for a, b in zip(ppf, other)],
            "rmse_ratio": [float(b / a) for a, b in zip(ppf, other)],
            "runs_ppf_lower_fraction": [float(v) for v in (per_run("PPF") < per_run(base)).mean(axis=0)],
        }
    out["holds"] = all(all(v["ppf_lower"]) for v in out.values())
    return out


def _transmission_summary(a: Mapping[str, np.ndarray], codec: Codec) -> dict:
    err = np.abs(a["z"] - a["decrypted"])
    return {
        "packets": int(a["available"].size), "available_fraction": float(a["available"].mean()),
        "dropped": int(a["dropped"].sum()), "crc_detected": int(a["detected"].sum()),
        "crc_undetected": int(a["undetected"].sum()), "saturated": int(a["saturated"].sum()),
        "bits_per_packet": codec.bits, "crc_bits": CRC4_ITU.bit_length() - 1,
        "bound_L_bar": np.broadcast_to(codec.bound, (a["z"].shape[-1],)).tolist(),
        "max_abs_z_minus_decrypted": np.nanmax(err, axis=(0, 1)).tolist() if a["available"].any() else None,
    }


def table_markdown(results: dict) -> str:
    """Time-averaged RMSE per state with intervals, time per step and its split, collapses; the claim check."""
    rows = {}
    for name, f in results["filters"].items():
        row = {"time_per_step_s": f["time_per_step_s"], "collapsed_steps": f["collapsed_steps"],
               "collapsed_runs": f["collapsed_runs"]}
        for i, (v, (lo, hi), med) in enumerate(zip(f["rmse_state"], f["rmse_state_ci95"],
                                                   f["rmse_state_median_run"]), 1):
            row[f"rmse{i}"] = f"{v:.4g} [{lo:.3g}, {hi:.3g}]"
            row[f"median{i}"] = med
        tb = f["time_breakdown_s"]
        row["split"] = "fused" if tb["proposal"] is None else " / ".join(
            f"{100 * tb[k] / f['wall_time_s']:.0f}" for k in ("proposal", "likelihood", "engine"))
        rows[name] = row
    n_x = len(next(iter(results["filters"].values()))["rmse_state"])
    states = range(1, n_x + 1)
    cols = [*((f"rmse{i}", f"RMSE_{i}") for i in states), *((f"median{i}", f"RMSE_{i} median run") for i in states),
            ("time_per_step_s", "time/step s"), ("split", "% proposal / likelihood / engine"),
            ("collapsed_steps", "collapsed steps"), ("collapsed_runs", "runs with a collapse")]
    xs = ", ".join(f"x{i}" for i in states)
    paper = results.get("paper")
    title = "(seed 001)" if paper else f"on {results['scenario']}"
    claim = f" The paper prints no numbers; its claim: {paper['claim']}." if paper else ""
    text = (f"# encrypted-switching {title}\n\n{results['runs']} runs, M = {results['particles']} particles, "
            f"T = {results['steps']} steps, seed {results['seed']}, engine {results['engine']}. Time-averaged "
            f"RMSE_i = mean over t of RMSE_i(t), with its 95 % bootstrap interval over runs.{claim}\n\n"
            + markdown_table(rows, cols, "filter"))
    cc = results["claim_check"]
    text += "\n## The paper's claim\n\n" + markdown_table(
        {f"PPF vs {b}": {"lower": ", ".join("yes" if v else "no" for v in c["ppf_lower"]),
                         "ratio": ", ".join(f"{v:.3g}" for v in c["rmse_ratio"]),
                         "runs": ", ".join(f"{v:.2f}" for v in c["runs_ppf_lower_fraction"])}
         for b, c in cc.items() if b != "holds"},
        [("lower", f"PPF lower ({xs})"), ("ratio", f"baseline / PPF RMSE ({xs})"),
         ("runs", f"share of runs where PPF is lower ({xs})")], "comparison")
    text += (f"\nClaim holds on {'both states' if n_x == 2 else 'every state'} against both baselines: "
             f"{'yes' if cc['holds'] else 'no'}.\n")
    tm, tx = results["timing_s"], results["transmission"]
    text += (f"\n## Time and transmission\n\nData (truth and measurements) {tm['data']:.3g} s, channel "
             f"{tm['channel']:.3g} s, the paper's three filters {tm['paper_filters']:.3g} s, whole study "
             f"{results['wall_time_s']:.3g} s (figures not included). Packets {tx['packets']}, available "
             f"{tx['available_fraction']:.4g}, dropped {tx['dropped']}, CRC-detected errors {tx['crc_detected']}, "
             f"undetected {tx['crc_undetected']}, saturated {tx['saturated']}; max |z - z~| per sensor "
             f"{tx['max_abs_z_minus_decrypted']} (bound L-bar {tx['bound_L_bar']}).\n")
    return text


def _figures(out: Path, results: dict, built: Mapping, arrays: Mapping) -> None:
    a, filters = next(iter(arrays.values())), results["filters"]
    truth0, j = a["truth"][0], {n: i for i, n in enumerate(filters)}
    colours = {"true state": "black", **filter_colours(filters)}
    for i in range(truth0.shape[-1]):
        curves_figure(out / f"fig_state{i + 1}.png",
                      {"true state": truth0[1:, i], **{n: a["mean"][0, j[n], 1:, i] for n in FILTERS}},
                      f"x{i + 1}(t)", f"One run: x{i + 1} and its estimates (cf. Fig. {i + 1})", colours=colours)
        curves_figure(out / f"fig_rmse_{i + 1}.png", {n: f["rmse_state_curve"][i] for n, f in filters.items()},
                      f"RMSE_{i + 1}(t)", f"RMSE of x{i + 1} (cf. Fig. {i + 5})", log=True, colours=colours)
    for s in range(a["z"].shape[-1]):
        curves_figure(out / f"fig_measurements_s{s + 1}.png",
                      {"ideal z": a["z"][0, :, s], "actual (resolution) zr": a["zr"][0, :, s],
                       "decrypted z~": a["decrypted"][0, :, s]},
                      f"sensor {s + 1}", f"Sensor {s + 1}: ideal, actual and decrypted measurements (cf. Fig. {s + 3})")


TEXT = StudyText(
    title="Estimating a switching nonlinear system from encrypted, quantized measurements",
    paper="Song, Wang, Li: Encryption-decryption-based particle filtering for stochastic systems with randomly "
          "switching nonlinearities and sensor resolutions (seed 001)",
    summary=(
        "A two-dimensional system whose dynamics switch at random between two nonlinear laws is observed by "
        "two sensors of limited resolution. Their readings are quantized, encrypted and sent over a network, "
        "so after decryption the filter only knows each measurement up to an interval. Particle filters "
        "estimate both states. The question: does a filter that models the switching and the measurement "
        "intervals beat simpler filters that ignore one or the other?"),
    filters={
        "PPF": "the paper's filter: a proposal that mixes both dynamics and an interval likelihood",
        "PF-RSN": "the same likelihood with a model that ignores the switching",
        "PF-SR-DE": "takes the decrypted values as exact measurements (ignores resolution and quantization)",
        "PF-RSN (mean dynamics)": "not in the paper: PF-RSN with the average of the two dynamics",
    },
    attacks=(
        "There is no active attacker here: encryption protects the measurements against eavesdropping, at "
        "the price of coarser information. The channel can also flip bits (`bit_error_prob`, caught by a CRC) "
        "and drop packets (`dropout_prob`); both are 0 by default."),
    attack_params=("bit_error_prob", "dropout_prob"),
    accuracy=(("rmse_state", "RMSE"),),
    figures={
        "fig_state1.png": "State x1: truth and each filter's estimate, run 0 (the paper's Fig. 1).",
        "fig_state2.png": "State x2: truth and each filter's estimate, run 0 (the paper's Fig. 2).",
        "fig_measurements_s1.png": "Sensor 1: ideal, resolution-limited and decrypted measurements, run 0 "
                                   "(the paper's Fig. 3).",
        "fig_measurements_s2.png": "Sensor 2: ideal, resolution-limited and decrypted measurements, run 0 "
                                   "(the paper's Fig. 4).",
        "fig_rmse_1.png": "RMSE of x1 at each time step over the runs (the paper's Fig. 5).",
        "fig_rmse_2.png": "RMSE of x2 at each time step over the runs (the paper's Fig. 6).",
    },
)


STUDY = Study(
    name="encrypted-switching",
    text=TEXT,
    scenarios=(SCENARIO,),
    runs=50,
    particles=200,
    chunk_size=CHUNK_SIZE,
    plan=_plan,
    summarise=_summarise,
    table=table_markdown,
    figures=_figures,
    options={"engine": "fast", "threads": THREADS_AUTO, "mean_dynamics_row": True},
    accepts=_accepts,
    check=_check,
)
