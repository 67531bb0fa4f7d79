"""Study ``binary-multi-attack``: seed 002's simulation study (binary sensors under DoS, deception, flipping).

Three filters on the same runs (common random numbers): Sec-PF (Theorem 1's
likelihood (13)-(16)), Sta-PF-Neg (the binary-sensor likelihood that neglects the
attacks, attacked data) and Sta-PF (the same likelihood on attack-free data).
RMSE curves (Figs. 4-5), the one-parameter sweeps of φ̄ (DoS), ϕ̄ (deception) and
ᾱ (flipping) for Sec-PF (Figs. 6-11), and Table II (Sec-PF with M = 200, 400,
600: time per step, RMSE_p, RMSE_v), with the paper's numbers beside ours.

Randomness: run ``r`` uses ``SeedSequence(seed, spawn_key=(r,)).spawn(3)`` (=
``SeedSequence(seed).spawn(runs)[r].spawn(3)``) = (truth, channel, filters).  The
channel's draws (DoS, deception, deception signal, flips, channel noise, in that
order) are replayed from the same seed for every setting, so the attack-free data
of Sta-PF differ from the attacked data only where an attack happened, and a
larger attack probability attacks a superset of the packets.

The runs are computed by :func:`studies.runner.monte_carlo` in chunks of
``chunk_size`` runs (a task simulating the chunk's data and running every filter
configuration, sweeps and Table II included, on it); metrics, tables and figures
come from the concatenated per-run arrays.  With the fast engine (one Generator
per run) the numbers do not depend on the backend, the chunk size or the number
of threads; the NumPy engine draws one Generator per chunk.  With ``out`` the
chunks are stored there and an interrupted study resumes.
"""
from __future__ import annotations

import functools
import time
from pathlib import Path
from typing import Any, Mapping, NamedTuple, Sequence

import numpy as np

from designer.validation import InputError, check_int
from filters.channels import binary_sensor_channel

from .pfrun import cached_scenario, check_study_options, plain_params, run_binary, score
from .results import (curves_figure, cv_velocity_at_position_rmse, markdown_table, rmse_with_ci, save_figure,
                      study_header, trajectory_figure, write_study)
from .pipeline import StudyText
from .runner import Backend, monte_carlo, run_seed
from .scenarios import load_scenario

__all__ = ["run_binary_multi_attack", "FILTERS", "PAPER_TABLE2", "SWEEP", "TABLE2_PARTICLES", "CHUNK_SIZE"]

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
    "excluded) divided by runs x K (amortised over the runs of a chunk, run together; chunks computed in "
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


def _channel(sc) -> dict:
    ex = sc.extras
    return dict(threshold=ex["threshold"], gain=ex["channel_gain"], channel_noise=ex["channel_noise"],
                deception=ex["deception"])


def _data(sc, seeds: Sequence[np.random.SeedSequence], filters: Sequence[_Filter], n_streams: int):
    """Truth, the received signals of every channel setting the filters use, and the filter streams."""
    m, K, chan = sc.model, sc.steps, _channel(sc)
    R = len(seeds)
    truth = np.empty((R, K + 1, m.n_x))
    keys = list(dict.fromkeys(f.data_probs for f in filters))
    data = {key: np.empty((R, K, m.n_sensors)) for key in keys}
    streams = []
    for a, seq in enumerate(seeds):
        s_truth, s_channel, s_filters = seq.spawn(3)
        tr = sc.simulate(np.random.default_rng(s_truth), K)
        truth[a] = tr.x
        for key in keys:  # the channel's draws replayed from the same seed for every setting
            data[key][a] = binary_sensor_channel(tr.z, **dict(zip(SWEEP_PARAMS, key)), **chan,
                                                 rng=np.random.default_rng(s_channel)).y
        streams.append(s_filters.spawn(n_streams))
    return truth, data, streams


def _warm_up(sc, data: Mapping, filters: Sequence[_Filter], engine: str) -> None:
    """Compile the fused kernels (one variant serves every filter here; once compiled: one tiny call)."""
    f = filters[0]
    run_binary(sc.model, data[f.data_probs], [], particles=f.particles, engine=engine, warm_up=True,
               **_channel(sc), **dict(zip(SWEEP_PARAMS, f.filter_probs)))


def _runs(run_ids, seeds, *, params: Mapping[str, Any], engine: str, threads: int, filters: Sequence[_Filter],
          n_streams: int) -> dict:
    """Task of the runner: simulate the runs ``run_ids`` from their seeds and run every filter on them.

    Returns per run: ``truth`` (K + 1, n_x), and per filter (in ``filters``' order)
    ``mean`` (K + 1, n_x), ``collapsed`` (K,) and ``seconds`` (its share of the chunk's
    wall time for that filter, compilation excluded).
    """
    sc = cached_scenario(SCENARIO, params)
    m, K, chan = sc.model, sc.steps, _channel(sc)
    truth, data, streams = _data(sc, seeds, filters, n_streams)
    _warm_up(sc, data, filters, engine)
    R, F = len(seeds), len(filters)
    mean = np.empty((R, F, K + 1, m.n_x))
    collapsed = np.empty((R, F, K), dtype=bool)
    seconds = np.empty((R, F))
    for j, f in enumerate(filters):
        rngs = [np.random.default_rng(s[f.stream]) for s in streams]
        t0 = time.perf_counter()
        mean[:, j], collapsed[:, j] = run_binary(m, data[f.data_probs], rngs, particles=f.particles, engine=engine,
                                                 threads=threads, **chan, **dict(zip(SWEEP_PARAMS, f.filter_probs)))
        seconds[:, j] = (time.perf_counter() - t0) / R
    return {"truth": truth, "mean": mean, "collapsed": collapsed, "seconds": seconds}


def _configurations(default: tuple, sweep: Sequence[float], table2_particles: Sequence[int],
                    particles: int) -> tuple[list, dict, list]:
    """The filters to compute, the names that reuse another's numbers, and every name in order.

    Stream ``c`` belongs to the ``c``-th configuration (Table I's, the sweeps', Table II's),
    whether computed or reused, as in every version of this study.
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


def run_binary_multi_attack(
    *,
    out: str | Path | None,
    runs: int = 50,
    particles: int = 500,
    seed: int = 0,
    quiet: bool = False,
    overrides: Mapping[str, Any] | None = None,
    assignments=(),
    sweep: Sequence[float] = SWEEP,
    table2_particles: Sequence[int] = TABLE2_PARTICLES,
    engine: str = "fast",
    threads: int | None = None,
    backend: Backend | None = None,
    force: bool = False,
    chunk_size: int = CHUNK_SIZE,
    workers: int | None = None,
) -> dict:
    """Run the study and write ``results.json``, ``table.md`` and the figures into ``out``.

    Parameters
    ----------
    runs, particles : int
        Monte Carlo runs (paper: 50) and particles ``M`` (paper: 500).
    sweep : sequence of float in [0, 1)
        Values of each attack probability in the one-parameter sweeps (empty to skip).
    table2_particles : sequence of int
        Particle counts of Table II (empty to skip).
    engine : {"fast", "numpy"}
        Particle-filter engine (see :mod:`studies.pfrun`).
    threads : int
        Threads of the fused engine within a chunk of runs (default 1); no effect on the numbers.
    backend : studies.runner.Backend
        Where the chunks of runs are computed: batched in this process (default), local
        processes, or a Dask cluster; the numbers are the same.
    force : bool
        Recompute runs already stored in ``out`` by an earlier (or interrupted) call, even
        if they were computed with other settings.
    chunk_size : int
        Runs per chunk (default ``CHUNK_SIZE`` = 10): the unit of work sent to a worker and
        of resumption; part of the study (the NumPy engine's numbers depend on it), never
        derived from the backend.
    workers : int
        Deprecated alias of ``threads``.
    """
    runs, particles, seed, threads, chunk_size, backend = check_study_options(
        runs=runs, particles=particles, seed=seed, threads=threads, workers=workers, engine=engine,
        chunk_size=chunk_size, backend=backend)
    sweep = [float(v) for v in sweep]
    if any(not 0.0 <= v < 1.0 for v in sweep):
        raise InputError(f"sweep values (attack probabilities) must lie in [0, 1), got {sweep}")
    table2_particles = [check_int("table2_particles", int(v), 1) for v in table2_particles]
    t_start = time.perf_counter()
    sc = load_scenario(SCENARIO, overrides, assignments)
    params = plain_params(sc.params)
    sc = cached_scenario(SCENARIO, params)  # the object whose kernels forked workers inherit
    m, K = sc.model, sc.steps
    default = tuple(float(sc.extras[p]) for p in SWEEP_PARAMS)
    filters, reused, names = _configurations(default, sweep, table2_particles, particles)
    n_streams = len(names)  # one filter stream per configuration, computed or reused

    if engine == "fast" and backend.kind != "dask":
        # compile here so that forked workers inherit the kernels (a Dask worker compiles once, in its first
        # chunk); every chunk also compiles what it lacks before timing, so timings never include compiling
        _, data0, _ = _data(sc, [run_seed(seed, 0)], filters[:1], n_streams)
        _warm_up(sc, data0, filters, engine)
    task = functools.partial(_runs, params=params, engine=engine, threads=threads, filters=tuple(filters),
                             n_streams=n_streams)
    config = {"study": "binary-multi-attack", "params": params, "particles": particles, "engine": engine,
              "filters": [f._asdict() for f in filters], "streams": n_streams}
    mc = monte_carlo(task, runs=runs, seed=seed, chunk_size=chunk_size, backend=backend, store=out,
                     label="binary-multi-attack", config=config, force=force, quiet=quiet)
    A = mc.arrays

    pos, vel = list(m.position_index), list(m.velocity_index)
    metrics_rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(runs + 1)[runs])
    index = {f.name: j for j, f in enumerate(filters)}
    computed: dict[str, dict] = {}
    for name in names:  # the configurations' order: the bootstrap draws follow it
        if name in reused:
            computed[name] = computed[reused[name]]
            continue
        j, f = index[name], filters[index[name]]
        met = score(A["truth"], np.ascontiguousarray(A["mean"][:, j]), A["collapsed"][:, j], A["seconds"][:, j],
                    pos, vel, metrics_rng)
        met.update({"particles": f.particles, "communications": int(K * m.n_sensors), "engine": engine,
                    "attack_probs_assumed": dict(zip(SWEEP_PARAMS, f.filter_probs))})
        computed[name] = met
    means0 = {f.name: A["mean"][0, j] for j, f in enumerate(filters)}

    filters_out = {k: computed[k] for k in FILTERS}
    sweeps = {p: {f"{v:g}": {"Sec-PF": computed[f"sweep {p}={v:g}"]} for v in sweep} for p in SWEEP_PARAMS} \
        if sweep else {}
    if table2_particles:
        sweeps["particles"] = {str(M): {"Sec-PF": computed[f"M={M}"]} for M in table2_particles}
    results = study_header("binary-multi-attack", SCENARIO, runs=runs, particles=particles, steps=K,
                           seed=seed, assumptions=list(sc.assumptions) + list(ASSUMPTIONS), engine=engine,
                           workers=threads, threads=threads, runner=mc.describe())
    results.update({
        "filters": filters_out,
        "sweeps": sweeps,
        "paper": {"source": "seed 002, Table II (Sec-PF)", "table2": PAPER_TABLE2,
                  "kalman_velocity_at_paper_rmse_position": {
                      M: cv_velocity_at_position_rmse(sc.params["accel_var"], sc.params["period"],
                                                      v["rmse_position"]) for M, v in PAPER_TABLE2.items()},
                  "runs": 50, "particles": 500,
                  "note": "Figs. 4-11 are curves without printed numbers; the paper states Sec-PF is close to "
                          "Sta-PF, Sta-PF-Neg is worst, and RMSE grows with each attack probability."},
        "params": dict(sc.params),
    })
    return write_study(out, results, t_start,
                       lambda d: _figures(d, sc, A["truth"][0], means0, filters_out, sweeps, K), table_markdown)


def _with_ci(f: dict) -> dict:
    return {**f, "rmse_position": rmse_with_ci(f)}


def table_markdown(results: dict) -> str:
    """The three filters, the sweeps and Table II with the paper's numbers."""
    text = (f"# binary-multi-attack (seed 002)\n\n{results['runs']} runs, M = {results['particles']} particles, "
            f"K = {results['steps']} steps, seed {results['seed']}, engine {results['engine']}. "
            "RMSE_p with its 95 % bootstrap interval over runs. The paper prints no numbers for these "
            "(Figs. 4-5).\n\n")
    text += markdown_table({n: _with_ci(f) for n, f in results["filters"].items()},
                           [("rmse_position", "RMSE_p"), ("rmse_velocity", "RMSE_v"),
                            ("time_per_step_s", "time/step s"), ("communications", "communications")])
    sw = results["sweeps"]
    for p, title in (("dos_prob", "DoS probability phi-bar (Figs. 6-7)"),
                     ("deception_prob", "deception probability varphi-bar (Figs. 8-9)"),
                     ("flip_prob", "flipping probability alpha-bar (Figs. 10-11)")):
        if p in sw:
            text += f"\n## Sec-PF against the {title}\n\n" + markdown_table(
                {f"{p} = {v}": _with_ci(d["Sec-PF"]) for v, d in sw[p].items()},
                [("rmse_position", "RMSE_p"), ("rmse_velocity", "RMSE_v")])
    if "particles" in sw:
        rows = {}
        for M, d in sw["particles"].items():
            paper = results["paper"]["table2"].get(M, {})
            rows[f"M = {M}"] = {**_with_ci(d["Sec-PF"]), **{f"paper_{k}": v for k, v in paper.items()},
                                "kalman_v": results["paper"]["kalman_velocity_at_paper_rmse_position"].get(M)}
        text += "\n## Table II: Sec-PF against the number of particles\n\n" + markdown_table(
            rows, [("time_per_step_s", "time/step s (ours)"), ("paper_time_per_step_s", "time/step s (paper)"),
                   ("rmse_position", "RMSE_p (ours)"), ("paper_rmse_position", "RMSE_p (paper)"),
                   ("rmse_velocity", "RMSE_v (ours)"), ("paper_rmse_velocity", "RMSE_v (paper)"),
                   ("kalman_v", "Kalman RMSE_v at the paper's RMSE_p")])
    return text


def _figures(out: Path, sc, truth0, means0, filters, sweeps, K) -> None:
    pos = np.array([s.position for s in sc.model.sensors])
    trajectory_figure(out / "fig_trajectory.png", truth0, {n: means0[n] for n in FILTERS}, pos,
                      sc.model.position_index, "One run: target and estimates (cf. Figs. 2-3)")
    for metric, fig_no in (("position", "4"), ("velocity", "5")):
        curves_figure(out / f"fig_rmse_{metric}.png", {n: f[f"rmse_{metric}_curve"] for n, f in filters.items()},
                      f"RMSE of {metric}", f"RMSE of {metric} (cf. Fig. {fig_no})")
    present = [p for p in SWEEP_PARAMS if p in sweeps]
    if not present:
        return
    import matplotlib.pyplot as plt

    names = {"dos_prob": "phi-bar (DoS)", "deception_prob": "varphi-bar (deception)", "flip_prob": "alpha-bar (flip)"}
    k = np.arange(1, K + 1)
    fig, axes = plt.subplots(2, len(present), figsize=(4.5 * len(present), 6), squeeze=False)
    for j, p in enumerate(present):
        for i, metric in enumerate(("position", "velocity")):
            ax = axes[i, j]
            for v, d in sweeps[p].items():
                ax.plot(k, d["Sec-PF"][f"rmse_{metric}_curve"], lw=1.1, label=f"{names[p]} = {v}")
            ax.set(xlabel="time step k", ylabel=f"RMSE of {metric}")
            ax.legend(fontsize=7)
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
