"""Study ``comparison``: the designed consensus EKF against centralized particle filters and a plain EKF.

No paper makes this comparison.  On the indoor robot (seed 003's 8 networked
ceiling cameras) every filter family faces one realisation of the same attack
law per run (:func:`filters.consensus.channel_draws`):

* **consensus EKF** (paper design and tuned design) — every camera is a node that
  estimates the pose from its own camera and its neighbours' estimates; the
  node-to-node channels suffer DoS (message lost) and FDI (``ξ = a sin(s)`` added
  to the estimate sent).  Messages per step: one per directed link (``2 |E|``).
* **centralized filters** — every camera sends its measurement to one fusion
  centre over an uplink with the same attack law (:mod:`filters.uplink`: DoS =
  lost packet, FDI = the measurement falsified as if the robot were displaced by
  ``ξ``).  Messages per step: one per camera.  Three filters: a bootstrap particle
  filter whose likelihood knows the attack law (a mixture with the falsified
  packets' moment-matched density), the same particle filter trusting every packet,
  and a plain EKF trusting every packet.

Metrics per filter: position RMSE over runs and steps (consensus filters: also
over the nodes, each node's own estimate), its 95 % bootstrap interval over runs,
the per-step curve, time per step (one run, the whole network or centre), messages
per step, runs where a consensus design's conditions failed or a filter diverged.
Sweeps: the DoS probability with FDI fixed, and the FDI probability with DoS fixed,
on the same runs (common random numbers: the same draws turn into more attacks as
the probability grows).

Randomness: run ``r`` uses ``SeedSequence(seed, spawn_key=(r,)).spawn(3)`` = (truth,
channel draws, particle filters); the particle filters reuse the same stream at
every sweep setting.  Runs are computed in chunks by :mod:`studies.runner`, so the
numbers are identical in-process, with ``--workers N`` or on a Dask cluster, and an
interrupted study resumes.
"""
from __future__ import annotations

import functools
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from designer.validation import InputError, check_int, check_probability
from filters.consensus import attack_pattern, channel_draws, run_consensus
from filters.ekf import run_ekf
from filters.particle import run_sir
from filters.uplink import fdi_covariances, receive, split_received, uplink_attacks, uplink_loglik

from .design import DESIGN_ASSUMPTIONS, consensus_design
from .results import curves_figure, markdown_table, save_figure, study_header, write_study, _plt
from .runner import Backend, monte_carlo
from .scenarios import load_scenario

__all__ = ["run_comparison", "FILTERS", "SWEEP_VALUES", "CHUNK_SIZE"]

TUNED, PAPER_DESIGN = "consensus EKF (tuned design)", "consensus EKF (paper design)"
PF_AWARE, PF_PLAIN, EKF_PLAIN = "centralized PF (attack-aware)", "centralized PF (trusts every packet)", \
    "centralized EKF (trusts every packet)"
FILTERS = (TUNED, PAPER_DESIGN, PF_AWARE, PF_PLAIN, EKF_PLAIN)
FAMILY = {TUNED: "consensus", PAPER_DESIGN: "consensus", PF_AWARE: "particle", PF_PLAIN: "particle",
          EKF_PLAIN: "EKF"}
DESCRIPTION = {
    TUNED: "distributed: each camera node runs the consensus EKF with sigma, beta and gains tuned by convex "
           "optimisation (Clarabel) at every step; exchanges estimates with its neighbours",
    PAPER_DESIGN: "distributed: the consensus EKF with the paper's fixed choices (sigma = beta = 0.1, "
                  "C = 0.01 Phi)",
    PF_AWARE: "centralized bootstrap particle filter; its likelihood models lost packets and falsified ones "
              "(mixture with the falsification's moment-matched density)",
    PF_PLAIN: "centralized bootstrap particle filter; skips lost packets, trusts every received one",
    EKF_PLAIN: "centralized EKF; skips lost packets, trusts every received one (ignores attacks)",
}
SWEEP_VALUES = (0.0, 0.1, 0.2, 0.3, 0.4)
CHUNK_SIZE = 10
SCENARIOS = ("indoor-robot", "target-range-bearing")
DEFAULT_RUNS = {"indoor-robot": 100, "target-range-bearing": 50}

ASSUMPTIONS = (
    "comparison: the centralized filters receive every sensor's measurement over its own uplink, attacked with the "
    "network's law (DoS = packet lost and known to be lost; FDI = the measurement falsified as h(x + xi) instead "
    "of h(x), with the same xi = a sin(s) on the position components); uplink i uses the diagonal draw [k, i, i] "
    "of the channel draws whose off-diagonal entries attack the consensus links, so both families face one "
    "realisation of one attack law (not the same channels: the architectures have different channels).",
    "comparison: the attack-aware particle filter's likelihood per received packet is (1 - q) N(y; h, R) + "
    "q N(y; h, R + C) with q = fdi/(1 - dos), the sensor's own noise density in place of N(y; h, R) (glint on "
    "target-range-bearing), R its covariance, and C = a^2 E[sin^2 s] H_c H_c^T (E[sin^2 s] = (1 - e^-2)/2 for "
    "s ~ N(0, 1), H_c the sensor Jacobian's position columns at the prior mean): a moment-matched Gaussian of the "
    "falsification, not its exact density.",
    "comparison: particle filters resample systematically at every step and report the weighted mean; M = "
    "particles for both.",
    "comparison: consensus RMSE is over runs, steps 1..K and the nodes (each node's own estimate); centralized "
    "filters have one estimate. 95 % intervals are percentile bootstraps over runs. A run whose filter leaves "
    "finite numbers (or 1e12) counts as diverged and is left out of the RMSE; a run that stays finite but far off "
    "is kept (compare the RMSE with the median run's).",
    "comparison: time per step = a filter's wall time on one run (all nodes, or the centre) / K at the main "
    "setting, averaged over runs, single-threaded; the tuned design's time includes its convex programs (one per "
    "node and step). In the sweeps the two particle filters of all settings of a run are one NumPy batch.",
    "comparison: the consensus designs use the scenario's defaults (paper: sigma = beta = 0.1, C = 0.01 Phi, "
    "U = 0.01 I, V = 0.1 I, epsilon = 0.5/d_max) on both scenarios; they were published for the robot only.",
    "comparison: messages per step count transmissions attempted (a message lost to DoS still counts): 2|E| "
    "directed links for the consensus filters, one uplink per sensor for the centralized ones.",
    "comparison: the sweeps leave out the tuned design (about 0.4 s per run per setting, ten times the paper "
    "design) unless tuned_in_sweeps=True; at the main setting every filter runs.",
)


def _settings(dos: float, fdi: float, values: Sequence[float]) -> list[tuple[float, float]]:
    """The main setting first, then the DoS sweep (FDI fixed) and the FDI sweep (DoS fixed), without repeats."""
    out = [(dos, fdi)]
    for v in values:
        for s in ((v, fdi), (dos, v)):
            if s not in out and s[0] + s[1] <= 1.0:
                out.append(s)
    return out


def _runs(run_ids, seeds, *, scenario: str, overrides: Mapping[str, Any], settings: Sequence[tuple[float, float]],
          particles: int, tuned_in_sweeps: bool) -> dict:
    """Task of the runner: every filter at every setting on the runs ``run_ids`` of ``scenario``.

    At the main setting each particle filter runs alone (its time is a single filter's); at
    the sweep settings both particle filters at every setting of one run form one batch of
    ``run_sir`` (rows ``(setting, filter)``), one NumPy call per operation instead of one per
    filter.  Every Generator comes from the run's own seed, so a run's numbers depend on it
    only.
    """
    scs = [load_scenario(scenario, {**overrides, "dos_prob": d, "fdi_prob": f}) for d, f in settings]
    sc = scs[0]
    m, K, n = sc.model, sc.steps, sc.network.n_nodes
    comps, amp = sc.extras["attack_components"], float(sc.extras["attack_amplitude"])
    angles = sc.extras.get("angle_components", ())
    designs = [{PAPER_DESIGN: consensus_design(s)} for s in scs]
    for j, s in enumerate(scs):
        if j == 0 or tuned_in_sweeps:
            designs[j][TUNED] = consensus_design(s, mode="tuned")
    covs = fdi_covariances(m, m.prior.mean, amplitude=amp, components=comps)
    S, F, R = len(settings), len(FILTERS), len(run_ids)
    pfs = [FILTERS.index(PF_AWARE), FILTERS.index(PF_PLAIN)]
    # q: probability that a received packet is falsified, per (setting, PF) row; 0 = trust every packet
    q = np.array([[f / (1.0 - d) if d < 1 else 0.0, 0.0] for d, f in settings]).ravel()
    ll_sweep = uplink_loglik(m, fdi_prob=q[2:], fdi_covs=covs, angles=angles)
    pos = list(m.position_index)
    err2 = np.full((R, S, F, K), np.nan)
    secs = np.full((R, S, F), np.nan)
    feasible = np.full((R, S, F), np.nan)
    est = np.full((R, F, K + 1, m.n_x), np.nan)
    truth = np.empty((R, K + 1, m.n_x))

    def score(a, j, f, xs, ok):
        if ok:
            e = truth[a, 1:, None][..., pos] - xs[1:][..., pos]  # (K, nodes, 2)
            err2[a, j, f] = (e**2).sum(-1).mean(axis=1)
            if j == 0:
                est[a, f] = xs[:, 0]

    for a, seq in enumerate(seeds):
        ts, cs, fs = seq.spawn(3)
        traj = sc.simulate(np.random.default_rng(ts), K)
        truth[a] = traj.x
        u, s = channel_draws(K, n, np.random.default_rng(cs))
        ys = []
        for j, ((dos, fdi), scj) in enumerate(zip(settings, scs)):
            att = attack_pattern(scj.network, u, s, m.n_x, amplitude=amp, components=comps)
            y = receive(m, traj.x, traj.z, uplink_attacks(u, s, m.n_x, dos_prob=dos, fdi_prob=fdi, amplitude=amp,
                                                          components=comps))
            ys += [y, y]
            for name in (TUNED, PAPER_DESIGN):
                if name in designs[j]:
                    f = FILTERS.index(name)
                    t0 = time.perf_counter()
                    res = run_consensus(m, scj.network, traj.z, designs[j][name], inputs=traj.inputs, attacks=att)
                    secs[a, j, f] = time.perf_counter() - t0
                    ok = res.diverged is None
                    feasible[a, j, f] = float(ok and not any(v["condition"] in ("(28)", "(29)")
                                                             for v in res.violations))
                    score(a, j, f, res.x_post, ok)  # x_post (K + 1, nodes, n_x)
            f = FILTERS.index(EKF_PLAIN)
            values, avail = split_received(m, y)
            t0 = time.perf_counter()
            xs = run_ekf(m, values, available=avail, inputs=traj.inputs, angles=angles).x[:, None]
            secs[a, j, f] = time.perf_counter() - t0
            score(a, j, f, xs, bool(np.all(np.isfinite(xs))))
        main_seqs = fs.spawn(3)  # the two particle filters at the main setting, then the sweep batch
        for c, f in enumerate(pfs):  # alone, so that their time per step is a single filter's
            t0 = time.perf_counter()
            res = run_sir(m, ys[0][None], np.random.default_rng(main_seqs[c]), particles=particles, runs=1,
                          inputs=traj.inputs, loglik=uplink_loglik(m, fdi_prob=q[c], fdi_covs=covs, angles=angles))
            secs[a, 0, f] = time.perf_counter() - t0
            score(a, 0, f, res.mean[0][:, None], bool(np.all(np.isfinite(res.mean))))
        if S > 1:
            t0 = time.perf_counter()
            res = run_sir(m, np.stack(ys[2:]), np.random.default_rng(main_seqs[2]), particles=particles,
                          runs=2 * (S - 1), inputs=traj.inputs, loglik=ll_sweep)
            per_filter = (time.perf_counter() - t0) / (2 * (S - 1))  # amortised over the batch
            for j in range(1, S):
                for c, f in enumerate(pfs):
                    xs = res.mean[2 * (j - 1) + c][:, None]
                    secs[a, j, f] = per_filter
                    score(a, j, f, xs, bool(np.all(np.isfinite(xs))))
    return {"err2": err2, "seconds": secs, "feasible": feasible, "estimate": est, "truth": truth}


def _scenario_assignments(scenarios: Sequence[str], assignments) -> dict[str, list[str]]:
    """Route each ``NAME=VALUE`` to every scenario that has the parameter NAME; unknown names are an error."""
    from .scenarios import get_spec

    names = {sc: {p.name for p in get_spec(sc).params} for sc in scenarios}
    out: dict[str, list[str]] = {sc: [] for sc in scenarios}
    for a in assignments:
        name = str(a).split("=", 1)[0].strip()
        hit = [sc for sc in scenarios if name in names[sc]]
        if not hit:
            raise InputError(f"--set {name}: no parameter of that name in the compared scenarios "
                             f"({', '.join(scenarios)}); see 'cfdesign scenarios'")
        for sc in hit:
            out[sc].append(a)
    return out


def run_comparison(
    *,
    out: str | Path | None,
    runs: int | None = None,
    particles: int = 500,
    seed: int = 0,
    quiet: bool = False,
    scenarios: Sequence[str] = SCENARIOS,
    overrides: Mapping[str, Any] | None = None,
    assignments=(),
    backend: Backend | None = None,
    force: bool = False,
    sweep_values: Sequence[float] = SWEEP_VALUES,
    tuned_in_sweeps: bool = False,
    chunk_size: int = CHUNK_SIZE,
) -> dict:
    """Run the comparison and write ``results.json``, ``table.md`` and the figures into ``out``.

    Parameters
    ----------
    runs : int, optional
        Monte Carlo runs per scenario (default: 100 on indoor-robot, 50 on target-range-bearing).
    particles, seed : int
        Particles of both particle filters; the study seed.
    scenarios : names among ``SCENARIOS``
    overrides, assignments
        Scenario parameters (``overrides`` for every scenario; each ``NAME=VALUE`` goes to the
        scenarios that have ``NAME``); ``dos_prob`` and ``fdi_prob`` set the main setting.
    backend : studies.runner.Backend
        Batched in this process (default), local processes, or a Dask cluster: identical numbers.
    force : bool
        Recompute runs already stored in ``out`` by an earlier (or interrupted) call.
    sweep_values : probabilities for the DoS and the FDI sweeps.
    tuned_in_sweeps : bool
        Also run the tuned design at every sweep setting (about 10x the cost of the paper design).
    chunk_size : int
        Runs per stored chunk (the unit of resumption and of work sent to a worker); part of the
        study's configuration, never derived from the backend.

    Results: ``filters`` and ``sweeps`` keyed ``"<scenario>: <filter>"``; ``by_scenario`` holds
    each scenario's own block (filters, sweeps, recommendation, attacks, parameters, runner).
    """
    runs = None if runs is None else check_int("runs", runs, 2)
    particles = check_int("particles", particles, 2)
    seed = check_int("seed", seed, 0)
    scenarios = list(dict.fromkeys([scenarios] if isinstance(scenarios, str) else scenarios))
    bad = [sc for sc in scenarios if sc not in SCENARIOS]
    if not scenarios or bad:
        raise InputError(f"scenarios must be among {', '.join(SCENARIOS)}, got {bad or scenarios}")
    values = [float(check_probability("sweep_values", v)) for v in np.atleast_1d(sweep_values)]
    t_start = time.perf_counter()
    routed = _scenario_assignments(scenarios, assignments)
    blocks, arrays, built = {}, {}, {}
    for sc_name in scenarios:
        sc = load_scenario(sc_name, overrides, routed[sc_name])
        params = dict(sc.params)
        dos, fdi = float(params["dos_prob"]), float(params["fdi_prob"])
        settings = _settings(dos, fdi, values)
        ov = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in params.items()}
        n_runs = DEFAULT_RUNS[sc_name] if runs is None else runs
        task = functools.partial(_runs, scenario=sc_name, overrides=ov, settings=settings, particles=particles,
                                 tuned_in_sweeps=bool(tuned_in_sweeps))
        config = {"study": "comparison", "scenario": sc_name, "params": ov, "settings": settings,
                  "particles": particles, "tuned_in_sweeps": bool(tuned_in_sweeps)}
        mc = monte_carlo(task, runs=n_runs, seed=seed, chunk_size=chunk_size, backend=backend, store=out,
                         label=f"comparison-{sc_name}", config=config, force=force, quiet=quiet)
        blocks[sc_name] = _summarise(sc, mc, settings, dos, fdi, values, particles, seed)
        arrays[sc_name], built[sc_name] = mc.arrays, sc
    first = blocks[scenarios[0]]
    results = study_header(
        "comparison", ", ".join(scenarios), runs=first["runs"], particles=particles, steps=first["steps"], seed=seed,
        assumptions=list(dict.fromkeys(a for sc in built.values() for a in sc.assumptions))
        + list(DESIGN_ASSUMPTIONS) + list(ASSUMPTIONS),
        runner={sc: b["runner"] for sc, b in blocks.items()})
    sweeps: dict = {"dos_prob": {}, "fdi_prob": {}}
    for sc_name, b in blocks.items():
        for key in sweeps:
            for val, row in b["sweeps"][key].items():
                sweeps[key].setdefault(val, {}).update({f"{sc_name}: {n}": v for n, v in row.items()})
    results.update({
        "filters": {f"{sc_name}: {n}": {**f, "scenario": sc_name}
                    for sc_name, b in blocks.items() for n, f in b["filters"].items()},
        "sweeps": sweeps,
        "paper": {"source": None, "numbers": None,
                  "note": "no paper compares these filter families; seed 003 gives the consensus filter alone"},
        "by_scenario": blocks,
        "recommendation": {sc: b["recommendation"] for sc, b in blocks.items()},
        "params": {sc: b["params"] for sc, b in blocks.items()},
    })
    return write_study(out, results, t_start, lambda d: _figures(d, arrays, built, blocks), table_markdown)


def _summarise(sc, mc, settings, dos, fdi, values, particles, seed) -> dict:
    """One scenario's block of results from the runner's arrays."""
    A, net, K = mc.arrays, sc.network, sc.steps
    boot_rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2**31,)))
    messages = {"consensus": 2 * len(net.edges), "particle": net.n_nodes, "EKF": net.n_nodes}
    filters = {}
    for f, name in enumerate(FILTERS):
        met = _metrics(A["err2"][:, 0, f], boot_rng)
        fam = FAMILY[name]
        met.update({
            "family": fam, "description": DESCRIPTION[name],
            "time_per_step_s": float(np.nanmean(A["seconds"][:, 0, f]) / K),
            "communications": messages[fam], "messages_per_step": messages[fam],
            "particles": particles if fam == "particle" else None,
        })
        if fam == "consensus":
            met["feasible_runs"] = int(np.nansum(A["feasible"][:, 0, f]))
        filters[name] = met
    sweeps: dict = {"dos_prob": {}, "fdi_prob": {}}
    for key, axis, fixed in (("dos_prob", 0, fdi), ("fdi_prob", 1, dos)):
        for val, j in sorted((st[axis], j) for j, st in enumerate(settings) if st[1 - axis] == fixed):
            row = {}
            for f, name in enumerate(FILTERS):
                if np.all(np.isnan(A["seconds"][:, j, f])):
                    continue  # not run at this setting
                mm = _metrics(A["err2"][:, j, f], boot_rng, curve=False)
                row[name] = {"rmse_position": mm["rmse_position"], "rmse_position_ci95": mm["rmse_position_ci95"],
                             "rmse_position_median_run": mm["rmse_position_median_run"],
                             "diverged_runs": mm["diverged_runs"]}
            sweeps[key][f"{val:g}"] = row
    return {
        "scenario": sc.name, "runs": int(A["err2"].shape[0]), "steps": int(K), "nodes": int(net.n_nodes),
        "links": [list(e) for e in net.edges], "filters": filters, "sweeps": sweeps,
        "attacks": {"dos_prob": dos, "fdi_prob": fdi, "amplitude": float(sc.extras["attack_amplitude"]),
                    "components": [sc.model.state_names[c] for c in sc.extras["attack_components"]],
                    "sweep_values": values},
        "recommendation": _recommend(filters), "params": dict(sc.params), "runner": mc.describe(),
    }


def _metrics(err2: np.ndarray, rng: np.random.Generator, curve: bool = True) -> dict:
    """RMSE over runs and steps of the runs that did not diverge, bootstrap interval, per-step curve."""
    ok = ~np.isnan(err2).any(axis=1)
    e = err2[ok]
    out = {"diverged_runs": int((~ok).sum())}
    if not len(e):
        return {**out, "rmse_position": None, "rmse_position_ci95": None, "rmse_position_curve": None,
                "rmse_position_median_run": None}
    per_run = e.mean(axis=1)
    idx = rng.integers(0, len(e), size=(1000, len(e)))
    lo, hi = np.percentile(np.sqrt(per_run[idx].mean(axis=1)), [2.5, 97.5])
    out.update({"rmse_position": float(np.sqrt(per_run.mean())), "rmse_position_ci95": [float(lo), float(hi)],
                "rmse_position_median_run": float(np.median(np.sqrt(per_run)))})
    if curve:
        out["rmse_position_curve"] = [float(v) for v in np.sqrt(e.mean(axis=0))]
    return out


def _recommend(filters: dict) -> dict:
    """The most accurate filter, whether its lead is significant (disjoint intervals), the cheapest, the leanest."""
    scored = {n: f for n, f in filters.items() if f["rmse_position"] is not None}
    best = min(scored, key=lambda n: scored[n]["rmse_position"])
    lo_best = scored[best]["rmse_position_ci95"][1]
    tied = [n for n in scored if n != best and scored[n]["rmse_position_ci95"][0] <= lo_best]
    fewest = min(f["messages_per_step"] for f in scored.values())
    return {"most_accurate": best, "not_significantly_worse": tied,
            "cheapest": min(scored, key=lambda n: scored[n]["time_per_step_s"]),
            "fewest_messages": [n for n in scored if scored[n]["messages_per_step"] == fewest]}


def table_markdown(results: dict) -> str:
    """Per scenario: the trade-off table (accuracy, cost, communication) and the sweeps."""
    text = ("# comparison: consensus EKF vs centralized particle filters vs plain EKF\n\n"
            f"Seed {results['seed']}, M = {results['particles']} particles. No paper makes this comparison; "
            "every filter faces one realisation of the same attack law per run.\n")
    for sc_name, b in results["by_scenario"].items():
        at = b["attacks"]
        rows = {n: {"family": f["family"],
                    "rmse": "diverged in every run" if f["rmse_position"] is None else
                    f"{f['rmse_position']:.4g} [{f['rmse_position_ci95'][0]:.3g}, {f['rmse_position_ci95'][1]:.3g}]",
                    "median": f["rmse_position_median_run"], "ms": 1e3 * f["time_per_step_s"],
                    "msgs": f["messages_per_step"], "div": f["diverged_runs"],
                    "feas": f.get("feasible_runs")} for n, f in b["filters"].items()}
        text += (f"\n## {sc_name}: accuracy, cost and communication\n\n{b['runs']} runs, K = {b['steps']} steps, "
                 f"{b['nodes']} sensor nodes, links {b['links']}. Attacks on every channel: DoS {at['dos_prob']:g}, "
                 f"FDI {at['fdi_prob']:g}, injected xi = {at['amplitude']:g} sin(s) on "
                 f"{', '.join(at['components'])}.\n\n")
        text += markdown_table(rows, [("family", "family"), ("rmse", "position RMSE [95 % CI]"),
                                      ("median", "median run RMSE"), ("ms", "time/step ms"),
                                      ("msgs", "messages/step"), ("div", "diverged runs"),
                                      ("feas", "runs with design conditions met")])
        rec = b["recommendation"]
        text += (f"\nMost accurate: {rec['most_accurate']}"
                 + (f" (not significantly better than {', '.join(rec['not_significantly_worse'])})"
                    if rec["not_significantly_worse"] else " (95 % interval disjoint from every other filter's)")
                 + f"; cheapest per step: {rec['cheapest']}; fewest messages: "
                 f"{', '.join(rec['fewest_messages'])}.\n")
        for key, title in (("dos_prob", "DoS probability (FDI fixed)"), ("fdi_prob", "FDI probability (DoS fixed)")):
            sw = b["sweeps"][key]
            names = [n for n in b["filters"] if any(n in row for row in sw.values())]
            text += (f"\n### {sc_name}: position RMSE against the {title}\n\nRMSE over all runs (median run's "
                     "RMSE in brackets: a few exploding runs dominate the first, not the second).\n\n") + markdown_table(
                {v: {n: _sweep_cell(row.get(n)) for n in names} for v, row in sw.items()}, [(n, n) for n in names])
    return text


def _sweep_cell(m: dict | None) -> str | None:
    if m is None:
        return None
    if m["rmse_position"] is None:
        return "diverged"
    return f"{m['rmse_position']:.4g} ({m['rmse_position_median_run']:.3g})"


def _figures(out: Path, arrays: dict, built: dict, blocks: dict) -> None:
    plt = _plt()
    names = list(blocks)
    fig, axes = plt.subplots(1, len(names), figsize=(6.5 * len(names), 4.8), squeeze=False)
    for ax, sc_name in zip(axes[0], names):
        for n, f in blocks[sc_name]["filters"].items():
            if f["rmse_position"] is None:
                continue
            lo, hi = f["rmse_position_ci95"]
            ax.errorbar(1e3 * f["time_per_step_s"], f["rmse_position"],
                        yerr=[[f["rmse_position"] - lo], [hi - f["rmse_position"]]], fmt="o", capsize=3,
                        label=f"{n} ({f['messages_per_step']} msgs/step)")
        ax.set(xscale="log", yscale="log", xlabel="time per step (ms, log scale)",
               ylabel="position RMSE with 95 % CI (log scale)", title=f"{sc_name}: accuracy against cost")
        ax.legend(fontsize=7, title="filter (messages per step)", title_fontsize=7)
    save_figure(fig, out / "fig_tradeoff.png")
    for sc_name in names:
        b, A, sc = blocks[sc_name], arrays[sc_name], built[sc_name]
        curves_figure(out / f"fig_rmse_{sc_name}.png",
                      {n: f["rmse_position_curve"] for n, f in b["filters"].items()
                       if f["rmse_position_curve"] is not None},
                      "position RMSE", f"{sc_name}: position RMSE over time at the main attack setting", log=True)
        fig, axs = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
        for ax, (key, label) in zip(axs, (("dos_prob", "DoS probability (FDI fixed)"),
                                          ("fdi_prob", "FDI probability (DoS fixed)"))):
            xs = sorted(b["sweeps"][key], key=float)
            for n in b["filters"]:
                pts = [(float(v), b["sweeps"][key][v][n]) for v in xs if n in b["sweeps"][key][v]
                       and b["sweeps"][key][v][n]["rmse_position"] is not None]
                if len(pts) < 2:
                    continue
                x = [p[0] for p in pts]
                ax.plot(x, [p[1]["rmse_position"] for p in pts], "o-", label=n)
                ax.fill_between(x, [p[1]["rmse_position_ci95"][0] for p in pts],
                                [p[1]["rmse_position_ci95"][1] for p in pts], alpha=0.15)
            ax.set(xlabel=label, ylabel="position RMSE (log scale)", yscale="log",
                   title=f"{sc_name}: degradation with the {label.split(' (')[0]}")
        axs[0].legend(fontsize=7)
        save_figure(fig, out / f"fig_sweeps_{sc_name}.png")
        fig, ax = plt.subplots(figsize=(6, 5))
        tr = A["truth"][0]
        i, j = sc.model.position_index
        sens = np.array([s.position for s in sc.model.sensors])
        ax.plot(sens[:, 0], sens[:, 1], "ks", ms=5, label="sensors")
        ax.plot(tr[:, i], tr[:, j], "k-", lw=2, label="truth")
        for f, n in enumerate(FILTERS):
            e = A["estimate"][0, f]
            if np.all(np.isfinite(e)):
                ax.plot(e[:, i], e[:, j], lw=1, label=n + (" (node 1)" if FAMILY[n] == "consensus" else ""))
        ax.set(xlabel="x position", ylabel="y position", title=f"{sc_name}, run 1: truth and estimates")
        ax.legend(fontsize=7)
        save_figure(fig, out / f"fig_trajectory_{sc_name}.png")
