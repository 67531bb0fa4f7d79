"""Study ``rrp-deception``: seed 000's simulation study (Round-Robin particle filters under deception).

Four filters on the same runs (common random numbers): RRP-PF-DA (the
attack-aware likelihood (14)), RRP-SPF-DA (standard likelihood, attacked
packets), RRP-SPF-NM (standard likelihood, attack-free packets) and PF-DA (all
sensors every step, attack-aware, an independent attack per packet).  Table 1
(average RMSE of position and velocity, time per step, communications), the RMSE
curves (Figs. 3-4), and the η̄ sweep of RRP-PF-DA (Figs. 5-6), with the paper's
published numbers beside ours.

It runs on ``target-range-bearing`` by default and on any scenario whose channel is
a :class:`designer.attacks.RoundRobinDeception` (a model file's ``CHANNEL``): the
schedule start, η̄ and the law of the fake packets come from it, the angular
measurement components (wrapped into (-π, π]) from the model's sensors
(``Sensor.angles``).  The paper's numbers and the Kalman velocity reference are
given for ``target-range-bearing`` only.

Randomness: run ``r`` uses ``SeedSequence(seed, spawn_key=(r,)).spawn(4)`` (=
``SeedSequence(seed).spawn(runs)[r].spawn(4)``) = (truth, Round-Robin attacks,
all-sensor attacks, filters); the filters' stream is spawned once more per filter
configuration.  The truth stream gives the run's initial state, then its K process
noises, then each sensor's K measurement noises
(:func:`designer.simulate.simulate_runs`: a chunk's runs are propagated together, each
from its own draws).  The attack draws are shared by every η̄ of the sweep (``eta = u <
η̄`` with the same ``u`` and ``ξ``), so the packets attacked at 0.2 are also
attacked at 0.4 and 0.6.

A :class:`studies.pipeline.Study` (``STUDY``): the runs are computed by
:mod:`studies.runner` in chunks of ``chunk_size`` runs (:func:`_runs` is the task:
it simulates the chunk's data and runs every filter configuration, sweep included,
on it); metrics, tables and figures come from the concatenated per-run arrays.  With
the fast engine (one Generator per run; every row, the linear-weights row included)
the numbers do not depend on the backend, the chunk size or the number of threads;
the NumPy engine draws one Generator per chunk.  With ``out`` the chunks are stored there and an
interrupted study resumes.  Its options: ``engine`` (``"fast"`` or ``"numpy"``, see
:mod:`studies.pfrun`), ``threads`` (of the fused engine within a chunk; no effect on
the numbers), ``sweep`` (η̄ values in [0, 1), empty to skip) and
``linear_weights_row`` (also RRP-SPF-DA with linear-domain weights, not in the paper).
"""
from __future__ import annotations

import functools
from pathlib import Path
from typing import Mapping, NamedTuple, Sequence

import numpy as np

from designer.attacks import RoundRobinDeception
from designer.simulate import simulate_runs
from designer.validation import InputError
from filters.attacks import deception_attack, round_robin_schedule
from filters.rrp import wrap_angles

from .filter_registry import FilterRegistry
from .pfrun import (THREADS_AUTO, Chunk, check_study_options, particle_entry, results_block, run_packets,
                    run_registry, score_configurations, study_threads)
from .pipeline import Plan, Study, StudyOptions
from .figures import curves_figure, filter_colours, trajectory_figure
from .results import cv_velocity_at_position_rmse, markdown_table, rmse_with_ci
from .runner import run_seed
from .scenarios import Scenario, ScenarioRef, reference
from .study_registry import StudyText

__all__ = ["STUDY", "FILTERS", "PAPER_TABLE1", "ETA_SWEEP", "CHUNK_SIZE", "LINEAR", "registry"]

SCENARIO = "target-range-bearing"
CHUNK_SIZE = 10  # runs per chunk of the Monte Carlo runner (part of the study, not of the backend)

FILTERS = ("RRP-PF-DA", "RRP-SPF-DA", "RRP-SPF-NM", "PF-DA")
# Seed 000, Table 1 (verbatim): average RMSEs, running time (s per step, MATLAB, hardware not given), packets
PAPER_TABLE1 = {
    "RRP-PF-DA": {"rmse_position": 0.9012, "rmse_velocity": 0.1197, "time_per_step_s": 0.0205, "communications": 120},
    "RRP-SPF-DA": {"rmse_position": 9.7923, "rmse_velocity": 0.3760, "time_per_step_s": 0.0199, "communications": 120},
    "RRP-SPF-NM": {"rmse_position": 0.8044, "rmse_velocity": 0.1169, "time_per_step_s": 0.0200, "communications": 120},
    "PF-DA": {"rmse_position": 0.5746, "rmse_velocity": 0.1018, "time_per_step_s": 0.0764, "communications": 480},
}
ETA_SWEEP = (0.2, 0.4, 0.6)  # Figs. 5-6
LINEAR = "RRP-SPF-DA (linear-domain weights)"

ASSUMPTIONS = (
    "rrp-deception: 'average RMSE' = mean over k = 1..K of RMSE_k = sqrt(mean over runs of the squared position "
    "(velocity) error); 95 % intervals are percentile bootstraps over runs.",
    "rrp-deception: time_per_step_s = the filter's wall time summed over the chunks of runs (compilation "
    "excluded) divided by runs x K (our engine runs a chunk's runs together, on 'threads' threads (default: the "
    "machine's cores), so this is an amortised cost of the machine, not the latency of one run's step on one "
    "core; chunks computed in parallel, or resumed from an earlier call, keep the time "
    "measured where and when they ran); the paper's times are MATLAB on unstated hardware.",
    "rrp-deception: communications = packets sent over the whole run (one per step under Round-Robin, one per "
    "sensor and step for PF-DA).",
    "rrp-deception: resampling is systematic at every step (the paper resamples every step, scheme not named).",
    "rrp-deception: PF-DA uses the attack-aware likelihood (14) per sensor with an independent attack per packet "
    "(the paper says only that it 'considers the effect' of the attacks).",
    "rrp-deception: RRP-SPF-NM filters the same runs with no attack (eta = 0); the eta-bar sweep runs RRP-PF-DA "
    "with its eta-bar equal to the true one.",
    "rrp-deception: kalman_velocity_at_paper_rmse_position = the velocity RMSE of the steady-state Kalman "
    "filter of the paper's CV model (sigma_w = 0.055) when the position is measured directly with the noise that "
    "gives the paper's RMSE_p: about 0.17-0.20 against the published 0.10-0.12, so the published position and "
    "velocity figures do not fit one process-noise level; our velocity RMSEs sit near this reference.",
    "rrp-deception: weights are kept in the log domain; the extra row 'RRP-SPF-DA (linear-domain weights)' "
    "emulates weights kept in linear double precision (a weight below the smallest double becomes 0; a run whose "
    "weights all vanish keeps its predicted particles with uniform weights), to show how much the RRP-SPF-DA "
    "figure depends on that choice.",
    "rrp-deception: the runs are computed in chunks of chunk_size runs (default 10); the fast engine (every row, "
    "the linear-weights row included) draws from one Generator per run, so its numbers do not depend on the "
    "chunks, threads or backend; with engine='numpy' every filter draws the particles of a whole chunk from one "
    "Generator (the filter stream of the chunk's first run), so its numbers depend on chunk_size.",
)


class _Filter(NamedTuple):
    """One filter configuration computed by the task (picklable)."""

    name: str
    stream: int  # its random stream: run r's SeedSequence(seed, spawn_key=(r,)).spawn(4)[3].spawn(n)[stream]
    packets: str  # "rr" (the Round-Robin packet of each step) or "all" (every sensor's, PF-DA)
    data_prob: float | None  # deception probability of the packets it receives (None: attack-free)
    filter_prob: float  # the deception probability its likelihood assumes
    linear: bool  # linear-domain weights (emulated, in either engine)


def _is_paper(sc: Scenario) -> bool:
    """The paper's own scenario (its published numbers and the Kalman reference apply)."""
    return sc.source == SCENARIO


def _attacked(y: np.ndarray, prob: float, signal, ss: np.random.SeedSequence) -> np.ndarray:
    """Packets after deception with probability ``prob``; the same draws for every ``prob`` (a fresh Generator)."""
    return deception_attack(y, prob, signal, np.random.default_rng(ss)).y


def _setup(sc) -> dict:
    m, K, ch = sc.model, sc.steps, sc.channel
    sched = round_robin_schedule(K, m.n_sensors, ch.start)
    return {"angles": sorted({j for _, j in m.angle_components}), "box": ch.deception,
            "sched": sched, "sensors": {"rr": sched[:, None], "all": np.tile(np.arange(m.n_sensors), (K, 1))}}


def _data(sc, seeds: Sequence[np.random.SeedSequence], filters: Sequence[_Filter], n_streams: int):
    """Truth, the packets each filter receives (keyed by ``(packets, data_prob)``) and the filter streams.

    The runs are simulated together (:func:`designer.simulate.simulate_runs`: each run draws its initial state
    and noises from its own truth stream, all of them before the propagation), the attacks run by run.
    """
    m, K, st = sc.model, sc.steps, _setup(sc)
    R, N, ny = len(seeds), m.n_sensors, m.sensor_dims[0]
    keys = list(dict.fromkeys((f.packets, f.data_prob) for f in filters))
    data = {key: np.empty((R, K, 1 if key[0] == "rr" else N, ny)) for key in keys}
    split = [seq.spawn(4) for seq in seeds]  # (truth, Round-Robin attacks, all-sensor attacks, filters) per run
    tr = simulate_runs(m, K, [np.random.default_rng(s[0]) for s in split], x0=sc.x0, inputs=sc.inputs(K))
    y_all = wrap_angles(tr.per_sensor(m), st["angles"])  # (R, K, N, ny)
    y_rr = y_all[:, np.arange(K), st["sched"]][:, :, None, :]  # (R, K, 1, ny): the scheduled packet
    for packets, prob in keys:
        y, which = (y_rr, 1) if packets == "rr" else (y_all, 2)
        data[packets, prob][:] = y if prob is None else \
            [_attacked(y[a], prob, st["box"], s[which]) for a, s in enumerate(split)]
    return tr.x, data, [s[3].spawn(n_streams) for s in split]


def _warm_up(sc, data: Mapping, filters: Sequence[_Filter], particles: int, engine: str) -> None:
    """Compile every fused-kernel variant the filters use (once compiled: one tiny call per filter)."""
    st = _setup(sc)
    for f in filters:
        run_packets(sc.model, data[f.packets, f.data_prob], st["sensors"][f.packets], [], particles=particles,
                    attack_prob=f.filter_prob, signal=st["box"], angles=st["angles"], engine=engine, warm_up=True)


def _compile(ref: ScenarioRef, seed: int, particles: int, engine: str, filters: Sequence[_Filter],
             n_streams: int) -> None:
    """``Plan.before``: compile the kernels in the parent, on the scenario object the tasks use, so that forked
    workers inherit them (a Dask worker compiles once, in its first chunk; every chunk also compiles what it lacks
    before timing, so timings never include compiling)."""
    sc = ref.build()
    _, data0, _ = _data(sc, [run_seed(seed, 0)], filters, n_streams)
    _warm_up(sc, data0, filters, particles, engine)


def _run(f: _Filter, model, st: dict, particles: int, engine: str, threads: int, chunk: Chunk, js, design):
    """Configuration ``f``'s filter on the chunk's runs (a registry entry's ``run``): its FilterResult."""
    return run_packets(model, chunk.data[f.packets, f.data_prob], st["sensors"][f.packets], chunk.rngs(f.stream),
                       particles=particles, attack_prob=f.filter_prob, signal=st["box"], angles=st["angles"],
                       engine=engine, threads=threads, linear_weights=f.linear)


def _describe(f: _Filter) -> str:
    what = "the Round-Robin packet" if f.packets == "rr" else "every sensor's packet"
    data = "attack-free" if f.data_prob is None else f"deceived with probability {f.data_prob:g}"
    return (f"bootstrap particle filter on {what} ({data}), its likelihood assuming deception probability "
            f"{f.filter_prob:g}" + (", weights in linear double precision" if f.linear else ""))


def registry(sc, filters: Sequence[_Filter], *, particles: int, engine: str, threads: int) -> FilterRegistry:
    """The study's filters on scenario ``sc``, one entry per configuration of ``filters`` (in their order)."""
    st = _setup(sc)
    return FilterRegistry(particle_entry(f.name, _describe(f), functools.partial(_run, f, sc.model, st, particles,
                                                                                 engine, threads),
                                         1 if f.packets == "rr" else sc.model.n_sensors) for f in filters)


def _runs(run_ids, seeds, *, ref: ScenarioRef, particles: int, engine: str, threads: int,
          filters: Sequence[_Filter], n_streams: int) -> dict:
    """Task of the runner: simulate the runs ``run_ids`` from their seeds and run every filter on them.

    The filters are the entries of :func:`registry`, built here from the configurations ``filters`` (what the
    task sends to a worker).  Returns per run: ``truth`` (K + 1, n_x), and per filter (in ``filters``' order)
    ``mean`` (K + 1, n_x), ``collapsed`` (K,) and ``seconds`` (its share of the chunk's
    wall time for that filter, compilation excluded).
    """
    sc = ref.build()  # once per process: the fused kernels are cached per Model object
    truth, data, streams = _data(sc, seeds, filters, n_streams)
    _warm_up(sc, data, filters, particles, engine)
    return run_registry(Chunk(truth, streams, data, run_ids),
                        registry(sc, filters, particles=particles, engine=engine, threads=threads))


def _configurations(eta: float, sweep: Sequence[float], linear_weights_row: bool) -> tuple[list, dict, list]:
    """The filters to compute, the names that reuse another's numbers, and every name in order.

    Stream ``c`` belongs to the ``c``-th configuration (Table 1's, the linear row, the
    sweep's), whether computed or reused, as in every version of this study.  Table 1's
    filters come first, in ``FILTERS`` order, and are always computed.
    """
    rr_eta = ("rr", eta)
    configs = {  # name: (packets, data's deception probability, filter's, linear weights)
        "RRP-PF-DA": (*rr_eta, eta, False),
        "RRP-SPF-DA": (*rr_eta, 0.0, False),
        "RRP-SPF-NM": ("rr", None, 0.0, False),
        "PF-DA": ("all", eta, eta, False),
    }
    if linear_weights_row:
        configs[LINEAR] = (*rr_eta, 0.0, True)
    for v in sweep:
        configs[f"sweep eta={v:g}"] = ("rr", v, v, False)
    filters, reused = [], {}
    for c, (name, (packets, data_prob, filter_prob, linear)) in enumerate(configs.items()):
        if name.startswith("sweep eta=") and float(name.split("=")[1]) == eta:
            reused[name] = "RRP-PF-DA"  # the sweep's default point is the Table 1 run
            continue
        filters.append(_Filter(name, c, packets, data_prob, filter_prob, linear))
    return filters, reused, list(configs)


def _sweep(so: StudyOptions) -> list[float]:
    return [float(v) for v in so["sweep"]]


def _check(so: StudyOptions) -> None:
    check_study_options(so)
    try:
        sweep = _sweep(so)
    except (TypeError, ValueError):
        raise InputError(f"sweep must be a sequence of eta-bar values in [0, 1), got {so['sweep']!r}") from None
    if any(not 0.0 <= v < 1.0 for v in sweep):
        raise InputError(f"sweep values (eta-bar) must lie in [0, 1), got {sweep}")


def _accepts(sc: Scenario) -> str | None:
    if not isinstance(sc.channel, RoundRobinDeception):
        return ("rrp-deception needs a Round-Robin deception channel: declare CHANNEL = RoundRobinDeception(...) "
                "(designer.attacks) in the model file")
    return None


def _configs_of(sc: Scenario, so: StudyOptions):
    return _configurations(sc.channel.deception_prob, _sweep(so), bool(so["linear_weights_row"]))


def _plan(sc: Scenario, so: StudyOptions) -> Plan:
    filters, _, names = _configs_of(sc, so)
    n_streams = len(names)  # one filter stream per configuration, computed or reused
    ref = reference(sc)
    engine, threads = so["engine"], study_threads(so)
    task = functools.partial(_runs, ref=ref, particles=so.particles, engine=engine, threads=threads,
                             filters=tuple(filters), n_streams=n_streams)
    config = {"study": "rrp-deception", "params": dict(ref.params), "particles": so.particles, "engine": engine,
              "filters": [f._asdict() for f in filters], "streams": n_streams,
              "channel": repr(sc.channel)}
    before = functools.partial(_compile, ref, so.seed, so.particles, engine, tuple(filters), n_streams) \
        if engine == "fast" else None
    return Plan(task, "rrp-deception", config, before=before)


@functools.lru_cache(maxsize=8)
def _kalman_values(accel_var: float, period: float) -> tuple:
    return tuple((n, cv_velocity_at_position_rmse(accel_var, period, v["rmse_position"]))
                 for n, v in PAPER_TABLE1.items())


def _kalman_reference(accel_var: float, period: float) -> dict:
    """The Kalman velocity reference of each published RMSE_p (a tenth of a second of bisections: computed once
    per process and parameters, a fresh dict at every call)."""
    return dict(_kalman_values(accel_var, period))


def _summarise(sc: Scenario, mc, so: StudyOptions) -> dict:
    m, K, engine = sc.model, sc.steps, so["engine"]
    filters, reused, names = _configs_of(sc, so)
    sweep, linear_weights_row = _sweep(so), bool(so["linear_weights_row"])
    computed = score_configurations(
        mc.arrays, filters, reused, names, m, so.seed,
        lambda f: {"communications": int(K * (1 if f.packets == "rr" else m.n_sensors)),
                   "engine": engine, "attack_prob_assumed": f.filter_prob})
    filters_out = {k: computed[k] for k in (*FILTERS, *([LINEAR] if linear_weights_row else []))}
    if linear_weights_row:
        filters_out[LINEAR]["note"] = "not in the paper: RRP-SPF-DA with weights emulated in linear double precision"
    sweep_keys = [f"sweep eta={v:g}" for v in sweep]
    sweeps = {"deception_prob": {f"{v:g}": {"RRP-PF-DA": computed[k]} for v, k in zip(sweep, sweep_keys)}} \
        if sweep else {}
    paper = None
    if _is_paper(sc):  # the Kalman reference is the paper's scenario's (its accel_std and period)
        paper = {
            "source": "seed 000, Table 1", "filters": PAPER_TABLE1,
            "kalman_velocity_at_paper_rmse_position": _kalman_reference(float(sc.params["accel_std"]) ** 2,
                                                                        float(sc.params["period"])),
            "runs": 50, "particles": 500, "deception_prob": 0.2,
            "note": "Figs. 3-6 are curves without printed numbers; the paper states RMSE grows with eta-bar."}
    return results_block("rrp-deception", sc, so, mc, ASSUMPTIONS, filters_out, sweeps, paper)


def table_markdown(results: dict) -> str:
    """Table 1 with ours beside the paper's (its own scenario), and the η̄ sweep."""
    paper = results.get("paper") or {}
    cols = [("rmse_position", "RMSE_p (ours)"), ("paper_rmse_position", "RMSE_p (paper)"),
            ("rmse_velocity", "RMSE_v (ours)"), ("paper_rmse_velocity", "RMSE_v (paper)"),
            ("time_per_step_s", "time/step s (ours)"), ("paper_time_per_step_s", "time/step s (paper)"),
            ("communications", "communications (ours)"), ("paper_communications", "communications (paper)"),
            ("kalman_v", "Kalman RMSE_v at the paper's RMSE_p"), ("collapsed_steps", "collapsed steps")]
    if not paper:
        cols = [(k, h.replace(" (ours)", "")) for k, h in cols if not k.startswith(("paper_", "kalman"))]
    rows = {}
    for name, f in results["filters"].items():
        published = paper.get("filters", {}).get(name, {})
        rows[name] = {**f, **{f"paper_{k}": v for k, v in published.items()},
                      "kalman_v": paper.get("kalman_velocity_at_paper_rmse_position", {}).get(name)}
        rows[name]["rmse_position"] = rmse_with_ci(f)
    title = "(seed 000): Table 1" if paper else f"on {results['scenario']}"
    text = (f"# rrp-deception {title}\n\n{results['runs']} runs, M = {results['particles']} particles, "
            f"K = {results['steps']} steps, seed {results['seed']}, engine {results['engine']}. "
            "RMSE_p with its 95 % bootstrap interval over runs.\n\n" + markdown_table(rows, cols, "filter"))
    sw = results["sweeps"].get("deception_prob")
    if sw:
        srows = {f"eta-bar = {v}": d["RRP-PF-DA"] for v, d in sw.items()}
        text += "\n## RRP-PF-DA against eta-bar (Figs. 5-6)\n\n" + markdown_table(
            srows, [("rmse_position", "RMSE_p"), ("rmse_velocity", "RMSE_v")], "deception probability")
    return text


def plane_view(model) -> np.ndarray | None:
    """The sensors' positions (S, 2) for a trajectory figure in the plane, or None (no 2-D position to draw)."""
    if len(model.position_index) != 2 or any(s.position is None or len(s.position) < 2 for s in model.sensors):
        return None
    return np.array([s.position[:2] for s in model.sensors], dtype=float)


def _figures(out: Path, results: dict, built: Mapping, arrays: Mapping) -> None:
    sc, A = next(iter(built.values())), next(iter(arrays.values()))
    filters, sweeps = results["filters"], results["sweeps"]
    colours = filter_colours(filters)
    pos = plane_view(sc.model)
    if pos is not None:  # Table 1's filters are the first configurations, in FILTERS order
        trajectory_figure(out / "fig_trajectory.png", A["truth"][0],
                          {n: A["mean"][0, j] for j, n in enumerate(FILTERS)}, pos, sc.model.position_index,
                          "One run: target and estimates (cf. Fig. 2)", colours)
    sw = sweeps.get("deception_prob")
    for metric, fig_no, sw_no in (("position", "3", "5"), ("velocity", "4", "6")):
        if any(f[f"rmse_{metric}_curve"] is None for f in filters.values()):
            continue  # no velocity components
        curves_figure(out / f"fig_rmse_{metric}.png", {n: f[f"rmse_{metric}_curve"] for n, f in filters.items()},
                      f"RMSE of {metric}", f"RMSE of {metric} (cf. Fig. {fig_no})", log=True, colours=colours)
        if sw:
            curves_figure(out / f"fig_eta_sweep_{metric}.png",
                          {f"RRP-PF-DA, eta-bar = {v}": d["RRP-PF-DA"][f"rmse_{metric}_curve"] for v, d in sw.items()},
                          f"RMSE of {metric}", f"RMSE of {metric} against eta-bar (cf. Fig. {sw_no})")


TEXT = StudyText(
    title="Tracking a moving target over a Round-Robin network under deception attacks",
    paper="Song, Wang, Wang, Shan: Particle filtering for a class of CPSs under Round-Robin protocol subject "
          "to randomly occurring deception attacks (seed 000)",
    summary=(
        "A target moves in a plane at a roughly constant velocity. Four sensors measure its range and bearing, "
        "but the network lets only one sensor transmit per time step, in turn (the Round-Robin protocol), and "
        "an attacker now and then replaces a transmitted packet with a fake one (a deception attack). Particle "
        "filters estimate the target's position and velocity from the packets that arrive. The question: how "
        "much accuracy does a filter that knows attacks can happen recover, compared with one that trusts "
        "every packet, and what does it cost to send one packet per step instead of four?"),
    filters={
        "RRP-PF-DA": "the paper's filter: one packet per step, weighs each packet by an attack-aware likelihood",
        "RRP-SPF-DA": "the standard likelihood on the same attacked packets (it ignores the attack)",
        "RRP-SPF-NM": "the standard likelihood on packets that were never attacked: a best case, not "
                      "available to anyone under attack",
        "PF-DA": "every sensor transmits every step (four times the packets), attack-aware likelihood",
        "RRP-SPF-DA (linear-domain weights)": "not in the paper: RRP-SPF-DA with its weights computed in "
                                              "plain double precision, to show the numerical collapses",
    },
    attacks=(
        "Deception: each transmitted packet is, with probability eta-bar (`deception_prob`), replaced by a "
        "fake range and bearing drawn uniformly from a box of plausible values (`deception_lower`, "
        "`deception_upper`). The sweep repeats the paper's filter at larger eta-bar."),
    attack_params=("deception_prob", "deception_lower", "deception_upper"),
    accuracy=(("rmse_position", "position RMSE"), ("rmse_velocity", "velocity RMSE")),
    references=("RRP-SPF-NM",),
    figures={
        "fig_trajectory.png": "One run (run 0): the target's true path, each filter's estimate and the sensors.",
        "fig_rmse_position.png": "Position RMSE at each time step over the runs (the paper's Fig. 3).",
        "fig_rmse_velocity.png": "Velocity RMSE at each time step over the runs (the paper's Fig. 4).",
        "fig_eta_sweep_position.png": "Position RMSE of RRP-PF-DA for each deception probability eta-bar "
                                      "(the paper's Fig. 5).",
        "fig_eta_sweep_velocity.png": "Velocity RMSE of RRP-PF-DA for each deception probability eta-bar "
                                      "(the paper's Fig. 6).",
    },
)


STUDY = Study(
    name="rrp-deception",
    text=TEXT,
    scenarios=(SCENARIO,),
    runs=50,
    particles=500,
    chunk_size=CHUNK_SIZE,
    plan=_plan,
    summarise=_summarise,
    table=table_markdown,
    figures=_figures,
    options={"engine": "fast", "threads": THREADS_AUTO, "sweep": ETA_SWEEP, "linear_weights_row": True},
    accepts=_accepts,
    check=_check,
)
