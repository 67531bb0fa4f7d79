"""Study ``binary-multi-attack``: seed 002's simulation study (binary sensors under DoS, deception, flipping).

Three filters on the same runs (common random numbers): Sec-PF (Theorem 1's
likelihood (13)-(16)), Sta-PF-Neg (the binary-sensor likelihood that neglects the
attacks, attacked data) and Sta-PF (the same likelihood on attack-free data).
RMSE curves (Figs. 4-5), the one-parameter sweeps of φ̄ (DoS), ϕ̄ (deception) and
ᾱ (flipping) for Sec-PF (Figs. 6-11), and Table II (Sec-PF with M = 200, 400,
600: time per step, RMSE_p, RMSE_v), with the paper's numbers beside ours.

It runs on ``target-binary-energy`` by default and on any scenario whose channel is
a :class:`designer.attacks.BinarySensorChannel` (a model file's ``CHANNEL``; scalar
sensors): the attack probabilities, the deception law, the threshold and the channel
come from it.  The paper's Table II and the Kalman velocity reference are given for
``target-binary-energy`` only.

Randomness: run ``r`` uses ``SeedSequence(seed, spawn_key=(r,)).spawn(3)`` (=
``SeedSequence(seed).spawn(runs)[r].spawn(3)``) = (truth, channel, filters).  The
channel's draws (DoS, deception, deception signal, flips, channel noise, in that
order) are replayed from the same seed for every setting, so the attack-free data
of Sta-PF differ from the attacked data only where an attack happened, and a
larger attack probability attacks a superset of the packets.

A :class:`studies.pipeline.Study` (``STUDY``): the runs are computed by
:mod:`studies.runner` in chunks of ``chunk_size`` runs (:func:`_runs` is the task:
it simulates the chunk's data and runs every filter configuration, sweeps and Table
II included, on it); metrics, tables and figures come from the concatenated per-run
arrays.  With the fast engine (one Generator per run) the numbers do not depend on
the backend, the chunk size or the number of threads; the NumPy engine draws one
Generator per chunk.  With ``out`` the chunks are stored there and an interrupted
study resumes.  Its options: ``engine`` (``"fast"`` or ``"numpy"``, see
:mod:`studies.pfrun`), ``threads`` (of the fused engine within a chunk; no effect on
the numbers), ``sweep`` (the values of each attack probability in the
one-parameter sweeps, in [0, 1), empty to skip) and ``table2_particles`` (the
particle counts of Table II, empty to skip).
"""
from __future__ import annotations

import functools
from dataclasses import replace
from pathlib import Path
from typing import Mapping, NamedTuple, Sequence

import numpy as np

from designer.attacks import BinarySensorChannel
from designer.validation import InputError, check_int
from filters.attacks import binary_sensor_channel

from .filter_registry import FilterRegistry
from .pfrun import (THREADS_AUTO, Chunk, check_study_options, particle_entry, results_block, run_binary,
                    run_registry, score_configurations, study_threads)
from .pipeline import Plan, Study, StudyOptions
from .figures import curves_figure, filter_colours, legend_beside, plotting, save_figure, trajectory_figure
from .results import cv_velocity_at_position_rmse, markdown_table, rmse_with_ci
from .rrp_deception import plane_view
from .runner import run_seed
from .scenarios import Scenario, ScenarioRef, reference
from .study_registry import StudyText

__all__ = ["STUDY", "FILTERS", "PAPER_TABLE2", "SWEEP", "TABLE2_PARTICLES", "CHUNK_SIZE", "registry"]

SCENARIO = "target-binary-energy"
CHUNK_SIZE = 10  # runs per chunk of the Monte Carlo runner (part of the study, not of the backend)

FILTERS = ("Sec-PF", "Sta-PF-Neg", "Sta-PF")
SWEEP = (0.1, 0.3, 0.5)  # values not printed in the paper (assumption)
SWEEP_PARAMS = ("dos_prob", "deception_prob", "flip_prob")
TABLE2_PARTICLES = (200, 400, 600)
# Seed 002, Table II (verbatim): Sec-PF, "average running time for Steps 1-6 at each time instant" (2.5 GHz PC)
PAPER_TABLE2 = {
    "200": {"time_per_step_s": 0.0196, "rmse_position": 3.7008, "rmse_velocity": 0.1741},
    "400": {"time_per_step_s": 0.0387, "rmse_position": 3.5354, "rmse_velocity": 0.1699},
    "600": {"time_per_step_s": 0.0584, "rmse_position": 3.3978, "rmse_velocity": 0.1643},
}

ASSUMPTIONS = (
    "binary-multi-attack: 'average RMSE' = mean over k = 1..K of RMSE_k = sqrt(mean over runs of the squared "
    "position (velocity) error); 95 % intervals are percentile bootstraps over runs.",
    "binary-multi-attack: Sta-PF-Neg and Sta-PF use Theorem 1's likelihood with phi-bar = varphi-bar = alpha-bar "
    "= 0 (the binary-sensor likelihood without attacks); Sta-PF filters attack-free data from the same runs.",
    "binary-multi-attack: the sweeps vary one attack probability over {0.1, 0.3, 0.5} (values not printed in the "
    "paper) with the others at Table I's 0.1, and run Sec-PF with the true probabilities. alpha-bar = 0.5 is a "
    "limiting case: a fair-coin flip makes every received bit independent of the state (likelihood (13) is then "
    "constant in x), so Sec-PF runs on its prior and the error grows with the prior's velocity spread.",
    "binary-multi-attack: Table II is Sec-PF at the Table I setting (the paper does not say which filter).",
    "binary-multi-attack: time_per_step_s = the filter's wall time summed over the chunks of runs (compilation "
    "excluded) divided by runs x K (amortised over the runs of a chunk, run together on 'threads' threads "
    "(default: the machine's cores), so it is the machine's cost, not one core's; chunks computed in "
    "parallel, or resumed from an earlier call, keep the time measured where and when they ran); the paper's "
    "times are for one run's step in MATLAB on a 2.5 GHz PC.",
    "binary-multi-attack: kalman_velocity_at_paper_rmse_position = the velocity RMSE of the steady-state Kalman "
    "filter of the CV model (Xi = 0.045^2) when the position is measured directly with the noise that gives the "
    "paper's RMSE_p: about 0.27-0.28 against the published 0.16-0.17 (position and velocity figures do not fit "
    "one process-noise level).",
    "binary-multi-attack: resampling is systematic at every step (scheme not named).",
    "binary-multi-attack: the runs are computed in chunks of chunk_size runs (default 10); the fast engine draws "
    "from one Generator per run, so its numbers do not depend on the chunks, threads or backend; with "
    "engine='numpy' a whole chunk's particles come from one Generator (the filter stream of the chunk's first "
    "run), so those numbers depend on chunk_size.",
)


class _Filter(NamedTuple):
    """One filter configuration computed by the task (picklable)."""

    name: str
    stream: int  # its random stream: run r's SeedSequence(seed, spawn_key=(r,)).spawn(3)[2].spawn(n)[stream]
    data_probs: tuple  # (dos, deception, flip) probabilities of the channel that produced its data
    filter_probs: tuple  # the probabilities its likelihood assumes, same order
    particles: int


def _is_paper(sc: Scenario) -> bool:
    """The paper's own scenario (its published numbers and the Kalman reference apply)."""
    return sc.source == SCENARIO


def _with(channel: BinarySensorChannel, probs: tuple) -> BinarySensorChannel:
    """The channel with the attack probabilities ``probs`` (``SWEEP_PARAMS`` order)."""
    return replace(channel, **dict(zip(SWEEP_PARAMS, probs)))


def _data(sc, seeds: Sequence[np.random.SeedSequence], filters: Sequence[_Filter], n_streams: int):
    """Truth, the received signals of every channel setting the filters use, and the filter streams."""
    m, K, ch = sc.model, sc.steps, sc.channel
    R = len(seeds)
    truth = np.empty((R, K + 1, m.n_x))
    keys = list(dict.fromkeys(f.data_probs for f in filters))
    data = {key: np.empty((R, K, m.n_sensors)) for key in keys}
    law = dict(threshold=ch.threshold, gain=ch.gain, channel_noise=ch.channel_noise, deception=ch.deception)
    streams = []
    for a, seq in enumerate(seeds):
        s_truth, s_channel, s_filters = seq.spawn(3)
        tr = sc.simulate(np.random.default_rng(s_truth), K)
        truth[a] = tr.x
        for key in keys:  # the channel's draws replayed from the same seed for every setting
            data[key][a] = binary_sensor_channel(tr.z, **dict(zip(SWEEP_PARAMS, key)), **law,
                                                 rng=np.random.default_rng(s_channel)).y
        streams.append(s_filters.spawn(n_streams))
    return truth, data, streams


def _warm_up(sc, data: Mapping, filters: Sequence[_Filter], engine: str) -> None:
    """Compile the fused kernels (one variant serves every filter here; once compiled: one tiny call)."""
    f = filters[0]
    run_binary(sc.model, data[f.data_probs], [], particles=f.particles, engine=engine, warm_up=True,
               channel=_with(sc.channel, f.filter_probs))


def _compile(ref: ScenarioRef, seed: int, engine: str, filters: Sequence[_Filter], n_streams: int) -> None:
    """``Plan.before``: compile the kernels in the parent, on the scenario object the tasks use, so that forked
    workers inherit them (a Dask worker compiles once, in its first chunk; every chunk also compiles what it lacks
    before timing, so timings never include compiling)."""
    sc = ref.build()
    _, data0, _ = _data(sc, [run_seed(seed, 0)], filters[:1], n_streams)
    _warm_up(sc, data0, filters, engine)


def _run(f: _Filter, sc, engine: str, threads: int, chunk: Chunk, js, design):
    """Configuration ``f``'s filter on the chunk's runs (a registry entry's ``run``): its FilterResult."""
    return run_binary(sc.model, chunk.data[f.data_probs], chunk.rngs(f.stream), particles=f.particles, engine=engine,
                      threads=threads, channel=_with(sc.channel, f.filter_probs))


def _describe(f: _Filter) -> str:
    def probs(p: tuple) -> str:
        return ", ".join(f"{k} {v:g}" for k, v in zip(SWEEP_PARAMS, p))

    return (f"bootstrap particle filter, M = {f.particles}, on the binary signals of a channel with "
            f"{probs(f.data_probs)}; its likelihood assuming {probs(f.filter_probs)}")


def registry(sc, filters: Sequence[_Filter], *, engine: str, threads: int) -> FilterRegistry:
    """The study's filters on scenario ``sc``, one entry per configuration of ``filters`` (in their order)."""
    return FilterRegistry(particle_entry(f.name, _describe(f), functools.partial(_run, f, sc, engine, threads),
                                         sc.model.n_sensors) for f in filters)


def _runs(run_ids, seeds, *, ref: ScenarioRef, engine: str, threads: int, filters: Sequence[_Filter],
          n_streams: int) -> dict:
    """Task of the runner: simulate the runs ``run_ids`` from their seeds and run every filter on them.

    The filters are the entries of :func:`registry`, built here from the configurations ``filters`` (what the
    task sends to a worker).  Returns per run: ``truth`` (K + 1, n_x), and per filter (in ``filters``' order)
    ``mean`` (K + 1, n_x), ``collapsed`` (K,) and ``seconds`` (its share of the chunk's
    wall time for that filter, compilation excluded).
    """
    sc = ref.build()  # once per process: the fused kernels are cached per Model object
    truth, data, streams = _data(sc, seeds, filters, n_streams)
    _warm_up(sc, data, filters, engine)
    return run_registry(Chunk(truth, streams, data, run_ids), registry(sc, filters, engine=engine, threads=threads))


def _configurations(default: tuple, sweep: Sequence[float], table2_particles: Sequence[int],
                    particles: int) -> tuple[list, dict, list]:
    """The filters to compute, the names that reuse another's numbers, and every name in order.

    Stream ``c`` belongs to the ``c``-th configuration (Table I's, the sweeps', Table II's),
    whether computed or reused, as in every version of this study.  ``FILTERS`` come
    first, in that order, and are always computed.
    """
    none = (0.0,) * len(SWEEP_PARAMS)
    configs = {  # name: (data's probabilities, filter's probabilities, particles)
        "Sec-PF": (default, default, particles),
        "Sta-PF-Neg": (default, none, particles),
        "Sta-PF": (none, none, particles),
    }
    for i, p in enumerate(SWEEP_PARAMS):
        for v in sweep:
            probs = tuple(v if j == i else d for j, d in enumerate(default))
            configs[f"sweep {p}={v:g}"] = (probs, probs, particles)
    for M in table2_particles:
        configs[f"M={M}"] = (default, default, M)
    filters, reused = [], {}
    for c, (name, (data_probs, filter_probs, M)) in enumerate(configs.items()):
        if name not in FILTERS and (data_probs, filter_probs, M) == configs["Sec-PF"]:
            reused[name] = "Sec-PF"  # the same filter on the same data: the Table I run
            continue
        filters.append(_Filter(name, c, data_probs, filter_probs, M))
    return filters, reused, list(configs)


def _options(so: StudyOptions) -> tuple[list[float], list[int]]:
    """The sweep's values and Table II's particle counts, checked."""
    try:
        sweep = [float(v) for v in so["sweep"]]
    except (TypeError, ValueError):
        raise InputError(f"sweep must be a sequence of probabilities in [0, 1), got {so['sweep']!r}") from None
    if any(not 0.0 <= v < 1.0 for v in sweep):
        raise InputError(f"sweep values (attack probabilities) must lie in [0, 1), got {sweep}")
    try:
        table2 = [check_int("table2_particles", int(v), 1) for v in so["table2_particles"]]
    except (TypeError, ValueError):
        raise InputError(f"table2_particles must be a sequence of particle counts, got "
                         f"{so['table2_particles']!r}") from None
    return sweep, table2


def _check(so: StudyOptions) -> None:
    check_study_options(so)
    _options(so)


def _accepts(sc: Scenario) -> str | None:
    if not isinstance(sc.channel, BinarySensorChannel):
        return ("binary-multi-attack needs binary sensors under DoS, deception and flipping: declare CHANNEL = "
                "BinarySensorChannel(...) (designer.attacks) in the model file")
    return None


def _configs_of(sc: Scenario, so: StudyOptions):
    sweep, table2 = _options(so)
    return _configurations(sc.channel.probabilities, sweep, table2, so.particles)


def _plan(sc: Scenario, so: StudyOptions) -> Plan:
    filters, _, names = _configs_of(sc, so)
    n_streams = len(names)  # one filter stream per configuration, computed or reused
    ref = reference(sc)
    engine = so["engine"]
    task = functools.partial(_runs, ref=ref, engine=engine, threads=study_threads(so), filters=tuple(filters),
                             n_streams=n_streams)
    config = {"study": "binary-multi-attack", "params": dict(ref.params), "particles": so.particles,
              "engine": engine, "filters": [f._asdict() for f in filters], "streams": n_streams,
              "channel": repr(sc.channel)}
    before = functools.partial(_compile, ref, so.seed, engine, tuple(filters), n_streams) if engine == "fast" \
        else None
    return Plan(task, "binary-multi-attack", config, before=before)


def _summarise(sc: Scenario, mc, so: StudyOptions) -> dict:
    m, K, engine = sc.model, sc.steps, so["engine"]
    sweep, table2_particles = _options(so)
    filters, reused, names = _configs_of(sc, so)
    computed = score_configurations(
        mc.arrays, filters, reused, names, m, so.seed,
        lambda f: {"particles": f.particles, "communications": int(K * m.n_sensors), "engine": engine,
                   "attack_probs_assumed": dict(zip(SWEEP_PARAMS, f.filter_probs))})
    filters_out = {k: computed[k] for k in FILTERS}
    sweeps = {p: {f"{v:g}": {"Sec-PF": computed[f"sweep {p}={v:g}"]} for v in sweep} for p in SWEEP_PARAMS} \
        if sweep else {}
    if table2_particles:
        sweeps["particles"] = {str(M): {"Sec-PF": computed[f"M={M}"]} for M in table2_particles}
    paper = None
    if _is_paper(sc):  # the Kalman reference is the paper's scenario's (its accel_var and period)
        paper = {
            "source": "seed 002, Table II (Sec-PF)", "table2": PAPER_TABLE2,
            "kalman_velocity_at_paper_rmse_position": {
                M: cv_velocity_at_position_rmse(sc.params["accel_var"], sc.params["period"], v["rmse_position"])
                for M, v in PAPER_TABLE2.items()},
            "runs": 50, "particles": 500,
            "note": "Figs. 4-11 are curves without printed numbers; the paper states Sec-PF is close to Sta-PF, "
                    "Sta-PF-Neg is worst, and RMSE grows with each attack probability."}
    return results_block("binary-multi-attack", sc, so, mc, ASSUMPTIONS, filters_out, sweeps, paper)


def _with_ci(f: dict) -> dict:
    return {**f, "rmse_position": rmse_with_ci(f)}


def table_markdown(results: dict) -> str:
    """The three filters, the sweeps and Table II with the paper's numbers."""
    paper = results.get("paper") or {}
    title = "(seed 002)" if paper else f"on {results['scenario']}"
    text = (f"# binary-multi-attack {title}\n\n{results['runs']} runs, M = {results['particles']} particles, "
            f"K = {results['steps']} steps, seed {results['seed']}, engine {results['engine']}. "
            "RMSE_p with its 95 % bootstrap interval over runs."
            + (" The paper prints no numbers for these (Figs. 4-5)." if paper else "") + "\n\n")
    text += markdown_table({n: _with_ci(f) for n, f in results["filters"].items()},
                           [("rmse_position", "RMSE_p"), ("rmse_velocity", "RMSE_v"),
                            ("time_per_step_s", "time/step s"), ("communications", "communications")], "filter")
    sw = results["sweeps"]
    for p, title in (("dos_prob", "DoS probability phi-bar (Figs. 6-7)"),
                     ("deception_prob", "deception probability varphi-bar (Figs. 8-9)"),
                     ("flip_prob", "flipping probability alpha-bar (Figs. 10-11)")):
        if p in sw:
            text += f"\n## Sec-PF against the {title}\n\n" + markdown_table(
                {f"{p} = {v}": _with_ci(d["Sec-PF"]) for v, d in sw[p].items()},
                [("rmse_position", "RMSE_p"), ("rmse_velocity", "RMSE_v")], "setting")
    if "particles" in sw:
        rows = {}
        for M, d in sw["particles"].items():
            published = paper.get("table2", {}).get(M, {})
            rows[f"M = {M}"] = {**_with_ci(d["Sec-PF"]), **{f"paper_{k}": v for k, v in published.items()},
                                "kalman_v": paper.get("kalman_velocity_at_paper_rmse_position", {}).get(M)}
        cols = [("time_per_step_s", "time/step s (ours)"), ("paper_time_per_step_s", "time/step s (paper)"),
                ("rmse_position", "RMSE_p (ours)"), ("paper_rmse_position", "RMSE_p (paper)"),
                ("rmse_velocity", "RMSE_v (ours)"), ("paper_rmse_velocity", "RMSE_v (paper)"),
                ("kalman_v", "Kalman RMSE_v at the paper's RMSE_p")]
        if not paper:
            cols = [(k, h.replace(" (ours)", "")) for k, h in cols if not k.startswith(("paper_", "kalman"))]
        text += "\n## Table II: Sec-PF against the number of particles\n\n" + markdown_table(rows, cols, "particles")
    return text


def _figures(out: Path, results: dict, built: Mapping, arrays: Mapping) -> None:
    sc, A = next(iter(built.values())), next(iter(arrays.values()))
    filters, sweeps, K = results["filters"], results["sweeps"], sc.steps
    colours = filter_colours(filters)
    pos = plane_view(sc.model)
    if pos is not None:  # the three filters are the first configurations, in FILTERS order
        trajectory_figure(out / "fig_trajectory.png", A["truth"][0],
                          {n: A["mean"][0, j] for j, n in enumerate(FILTERS)}, pos, sc.model.position_index,
                          "One run: target and estimates (cf. Figs. 2-3)", colours)
    metrics = [mt for mt in ("position", "velocity") if all(f[f"rmse_{mt}_curve"] is not None
                                                             for f in filters.values())]
    for metric in metrics:
        fig_no = {"position": "4", "velocity": "5"}[metric]
        curves_figure(out / f"fig_rmse_{metric}.png", {n: f[f"rmse_{metric}_curve"] for n, f in filters.items()},
                      f"RMSE of {metric}", f"RMSE of {metric} (cf. Fig. {fig_no})", colours=colours)
    present = [p for p in SWEEP_PARAMS if p in sweeps]
    if not present:
        return
    plt = plotting()
    names = {"dos_prob": "phi-bar (DoS)", "deception_prob": "varphi-bar (deception)", "flip_prob": "alpha-bar (flip)"}
    k = np.arange(1, K + 1)
    fig, axes = plt.subplots(len(metrics), len(present), figsize=(4.5 * len(present), 3 * len(metrics)),
                             squeeze=False)
    for j, p in enumerate(present):
        for i, metric in enumerate(metrics):
            ax = axes[i, j]
            for v, d in sweeps[p].items():
                ax.plot(k, d["Sec-PF"][f"rmse_{metric}_curve"], lw=1.1, label=f"{names[p]} = {v}")
            ax.set(xlabel="time step k", ylabel=f"RMSE of {metric}")
            if i == 0:  # one legend per column
                legend_beside(ax)
    fig.suptitle("Sec-PF against each attack probability (cf. Figs. 6-11)")
    save_figure(fig, out / "fig_attack_sweeps.png")


TEXT = StudyText(
    title="Tracking a target with one-bit sensors under denial-of-service, deception and bit-flipping attacks",
    paper="Song, Wang, Wang, Alsaadi, Shan: Secure particle filtering for CPSs with binary sensors under "
          "multiple attacks (seed 002)",
    summary=(
        "A target moves in a plane watched by 16 binary sensors on a grid: each sensor only reports one bit, "
        "whether the energy it receives from the target exceeds a threshold. On the way to the filter three "
        "attacks hit the readings: denial of service (the reading is lost), deception (the reading is replaced "
        "by a fake value) and bit flipping (the bit is inverted). Particle filters estimate the target's "
        "position and velocity from the bits. The question: how close does a filter that models all three "
        "attacks come to one that receives clean data, and how badly does ignoring the attacks fail?"),
    filters={
        "Sec-PF": "the paper's secure filter: its likelihood accounts for all three attacks",
        "Sta-PF-Neg": "the standard binary-sensor likelihood on the attacked data (it neglects the attacks)",
        "Sta-PF": "the standard likelihood on attack-free data: a best case, not available under attack",
    },
    attacks=(
        "Each sensor reading is independently jammed with probability phi-bar (`dos_prob`; the reading "
        "becomes 0), replaced with probability varphi-bar (`deception_prob`) by a value drawn uniformly from "
        "[`deception_low`, `deception_high`], and after thresholding its bit is flipped with probability "
        "alpha-bar (`flip_prob`). The sweeps raise one probability at a time."),
    attack_params=("dos_prob", "deception_prob", "flip_prob", "deception_low", "deception_high"),
    accuracy=(("rmse_position", "position RMSE"), ("rmse_velocity", "velocity RMSE")),
    references=("Sta-PF",),
    figures={
        "fig_trajectory.png": "One run (run 0): the target's true path, each filter's estimate and the sensors.",
        "fig_rmse_position.png": "Position RMSE at each time step over the runs (the paper's Fig. 4).",
        "fig_rmse_velocity.png": "Velocity RMSE at each time step over the runs (the paper's Fig. 5).",
        "fig_attack_sweeps.png": "Sec-PF's RMSE against each attack probability (the paper's Figs. 6-11).",
    },
)


STUDY = Study(
    name="binary-multi-attack",
    text=TEXT,
    scenarios=(SCENARIO,),
    runs=50,
    particles=500,
    chunk_size=CHUNK_SIZE,
    plan=_plan,
    summarise=_summarise,
    table=table_markdown,
    figures=_figures,
    options={"engine": "fast", "threads": THREADS_AUTO, "sweep": SWEEP, "table2_particles": TABLE2_PARTICLES},
    accepts=_accepts,
    check=_check,
)
