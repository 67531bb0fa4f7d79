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
SCENARIO = "indoor-robot"

ASSUMPTIONS = (
    "comparison: the centralized filters receive every camera's measurement over its own uplink, attacked with the "
    "network's law (DoS = packet lost and known to be lost; FDI = the measurement falsified as h(x + xi) instead "
    "of h(x), with the same xi = a sin(s) on the position components); uplink i uses the diagonal draw [k, i, i] "
    "of the channel draws whose off-diagonal entries attack the consensus links, so both families face one "
    "realisation of one attack law (not the same channels: the architectures have different channels).",
    "comparison: the attack-aware particle filter's likelihood per received packet is (1 - q) N(y; h, R) + "
    "q N(y; h, R + C) with q = fdi/(1 - dos) and C = a^2 E[sin^2 s] H_c H_c^T (E[sin^2 s] = (1 - e^-2)/2 for "
    "s ~ N(0, 1), H_c the camera Jacobian's position columns at the prior mean): a moment-matched Gaussian of the "
    "falsification, not its exact density.",
    "comparison: particle filters resample systematically at every step and report the weighted mean; M = "
    "particles for both.",
    "comparison: consensus RMSE is over runs, steps 1..K and the 8 nodes (each node's own estimate); centralized "
    "filters have one estimate. 95 % intervals are percentile bootstraps over runs.",
    "comparison: time per step = a filter's wall time on one run (all nodes, or the centre) / K, averaged over runs, "
    "single-threaded; the tuned design's time includes its convex programs (one per node and step).",
    "comparison: messages per step count transmissions attempted (a message lost to DoS still counts): 2|E| "
    "directed links for the consensus filters, one uplink per camera for the centralized ones.",
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


def _runs(run_ids, seeds, *, overrides: Mapping[str, Any], settings: Sequence[tuple[float, float]],
          particles: int, tuned_in_sweeps: bool) -> dict:
    """Task of the runner: every filter at every setting on the runs ``run_ids``."""
    scs = [load_scenario(SCENARIO, {**overrides, "dos_prob": d, "fdi_prob": f}) for d, f in settings]
    sc = scs[0]
    m, K, n = sc.model, sc.steps, sc.network.n_nodes
    comps, amp = sc.extras["attack_components"], float(sc.extras["attack_amplitude"])
    designs = [{PAPER_DESIGN: consensus_design(s)} for s in scs]
    for j, s in enumerate(scs):
        if j == 0 or tuned_in_sweeps:
            designs[j][TUNED] = consensus_design(s, mode="tuned")
    covs = fdi_covariances(m, m.prior.mean, amplitude=amp, components=comps)
    S, F, R = len(settings), len(FILTERS), len(run_ids)
    pos = list(m.position_index)
    err2 = np.full((R, S, F, K), np.nan)
    secs = np.full((R, S, F), np.nan)
    feasible = np.full((R, S, F), np.nan)
    est = np.full((R, F, K + 1, m.n_x), np.nan)
    truth = np.empty((R, K + 1, m.n_x))
    for a, seq in enumerate(seeds):
        ts, cs, fs = seq.spawn(3)
        traj = sc.simulate(np.random.default_rng(ts), K)
        truth[a] = traj.x
        u, s = channel_draws(K, n, np.random.default_rng(cs))
        pf_seqs = fs.spawn(2)
        for j, ((dos, fdi), scj) in enumerate(zip(settings, scs)):
            att = attack_pattern(scj.network, u, s, m.n_x, amplitude=amp, components=comps)
            y = receive(m, traj.x, traj.z, uplink_attacks(u, s, m.n_x, dos_prob=dos, fdi_prob=fdi, amplitude=amp,
                                                          components=comps))
            values, avail = split_received(m, y)
            for f, name in enumerate(FILTERS):
                if name in (TUNED, PAPER_DESIGN) and name not in designs[j]:
                    continue
                t0 = time.perf_counter()
                if name in (TUNED, PAPER_DESIGN):
                    res = run_consensus(m, scj.network, traj.z, designs[j][name], inputs=traj.inputs, attacks=att)
                    xs = res.x_post  # (K + 1, nodes, n_x)
                    ok = res.diverged is None
                    feasible[a, j, f] = float(ok and not any(v["condition"] in ("(28)", "(29)")
                                                             for v in res.violations))
                elif name == EKF_PLAIN:
                    xs = run_ekf(m, values, available=avail, inputs=traj.inputs).x[:, None]
                    ok = bool(np.all(np.isfinite(xs)))
                else:
                    q = fdi / (1.0 - dos) if name == PF_AWARE and dos < 1 else 0.0
                    ll = uplink_loglik(m, fdi_prob=q, fdi_covs=covs)
                    g = np.random.default_rng(pf_seqs[0 if name == PF_AWARE else 1])
                    xs = run_sir(m, y[None], g, particles=particles, runs=1, inputs=traj.inputs,
                                 loglik=ll).mean[0][:, None]
                    ok = bool(np.all(np.isfinite(xs)))
                secs[a, j, f] = time.perf_counter() - t0
                if ok:
                    e = traj.x[1:, None, pos] - xs[1:, :, pos]
                    err2[a, j, f] = (e**2).sum(-1).mean(axis=1)
                    if j == 0:
                        est[a, f] = xs[:, 0]
    return {"err2": err2, "seconds": secs, "feasible": feasible, "estimate": est, "truth": truth}


def run_comparison(
    *,
    out: str | Path | None,
    runs: int = 100,
    particles: int = 500,
    seed: int = 0,
    quiet: bool = False,
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
    runs, particles, seed : int
        Monte Carlo runs, particles of both particle filters, the study seed.
    overrides, assignments
        Parameters of the ``indoor-robot`` scenario; ``dos_prob`` and ``fdi_prob`` set the main setting.
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
    """
    runs = check_int("runs", runs, 2)
    particles = check_int("particles", particles, 2)
    seed = check_int("seed", seed, 0)
    values = [float(check_probability("sweep_values", v)) for v in np.atleast_1d(sweep_values)]
    t_start = time.perf_counter()
    sc = load_scenario(SCENARIO, overrides, assignments)
    params = dict(sc.params)
    dos, fdi = float(params["dos_prob"]), float(params["fdi_prob"])
    settings = _settings(dos, fdi, values)
    ov = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in params.items()}
    task = functools.partial(_runs, overrides=ov, settings=settings, particles=particles,
                             tuned_in_sweeps=bool(tuned_in_sweeps))
    config = {"study": "comparison", "params": ov, "settings": settings, "particles": particles,
              "tuned_in_sweeps": bool(tuned_in_sweeps)}
    mc = monte_carlo(task, runs=runs, seed=seed, chunk_size=chunk_size, backend=backend, store=out,
                     label="comparison", config=config, force=force, quiet=quiet)
    A = mc.arrays
    m, net, K = sc.model, sc.network, sc.steps
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
    sweeps = {"dos_prob": {}, "fdi_prob": {}}
    for key, axis, fixed in (("dos_prob", 0, fdi), ("fdi_prob", 1, dos)):
        on_axis = sorted((st[axis], j) for j, st in enumerate(settings) if st[1 - axis] == fixed)
        for val, j in on_axis:
            row = {}
            for f, name in enumerate(FILTERS):
                if np.all(np.isnan(A["seconds"][:, j, f])):
                    continue  # not run at this setting
                mm = _metrics(A["err2"][:, j, f], boot_rng, curve=False)
                row[name] = {"rmse_position": mm["rmse_position"], "rmse_position_ci95": mm["rmse_position_ci95"],
                             "diverged_runs": mm["diverged_runs"]}
            sweeps[key][f"{val:g}"] = row
    results = study_header("comparison", SCENARIO, runs=runs, particles=particles, steps=K, seed=seed,
                           assumptions=list(sc.assumptions) + list(DESIGN_ASSUMPTIONS) + list(ASSUMPTIONS),
                           runner=mc.describe())
    results.update({
        "filters": filters,
        "sweeps": sweeps,
        "paper": {"source": None, "numbers": None,
                  "note": "no paper compares these filter families; seed 003 gives the consensus filter alone"},
        "attacks": {"dos_prob": dos, "fdi_prob": fdi, "amplitude": float(sc.extras["attack_amplitude"]),
                    "components": list(sc.extras["attack_components"]), "sweep_values": values},
        "recommendation": _recommend(filters),
        "params": params,
    })
    return write_study(out, results, t_start, lambda d: _figures(d, A, sc, filters, sweeps), table_markdown)


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
    """The trade-off table (accuracy, cost, communication) and the sweeps."""
    fl = results["filters"]
    rows = {n: {"family": f["family"],
                "rmse": "—" if f["rmse_position"] is None else
                f"{f['rmse_position']:.4g} [{f['rmse_position_ci95'][0]:.3g}, {f['rmse_position_ci95'][1]:.3g}]",
                "median": f["rmse_position_median_run"], "ms": 1e3 * f["time_per_step_s"],
                "msgs": f["messages_per_step"], "div": f["diverged_runs"],
                "feas": f.get("feasible_runs")} for n, f in fl.items()}
    at = results["attacks"]
    text = (f"# comparison: consensus EKF vs centralized particle filters vs plain EKF\n\n"
            f"Scenario {results['scenario']} (8 networked cameras), {results['runs']} runs, K = {results['steps']} "
            f"steps, M = {results['particles']} particles, seed {results['seed']}. Attacks on every channel: DoS "
            f"{at['dos_prob']:g}, FDI {at['fdi_prob']:g}, injected xi = {at['amplitude']:g} sin(s) m on x and y. "
            "No paper makes this comparison.\n\n## Accuracy, cost and communication\n\n")
    text += markdown_table(rows, [("family", "family"), ("rmse", "position RMSE m [95 % CI]"),
                                  ("median", "median run RMSE m"), ("ms", "time/step ms"),
                                  ("msgs", "messages/step"), ("div", "diverged runs"),
                                  ("feas", "runs with design conditions met")])
    rec = results["recommendation"]
    text += (f"\nMost accurate: {rec['most_accurate']}"
             + (f" (not significantly better than {', '.join(rec['not_significantly_worse'])})"
                if rec["not_significantly_worse"] else " (95 % intervals disjoint from every other filter's)")
             + f"; cheapest per step: {rec['cheapest']}; fewest messages: {', '.join(rec['fewest_messages'])}.\n")
    for key, title in (("dos_prob", "DoS probability (FDI fixed)"), ("fdi_prob", "FDI probability (DoS fixed)")):
        sw = results["sweeps"][key]
        names = [n for n in fl if any(n in row for row in sw.values())]
        text += f"\n## Position RMSE (m) against the {title}\n\n" + markdown_table(
            {v: {n: (row[n]["rmse_position"] if n in row else None) for n in names} for v, row in sw.items()},
            [(n, n) for n in names])
    return text


def _figures(out: Path, A: dict, sc, filters: dict, sweeps: dict) -> None:
    plt = _plt()
    curves_figure(out / "fig_rmse.png", {n: f["rmse_position_curve"] for n, f in filters.items()
                                         if f["rmse_position_curve"] is not None},
                  "position RMSE (m)", "Position RMSE over time at the main attack setting")
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for n, f in filters.items():
        if f["rmse_position"] is None:
            continue
        lo, hi = f["rmse_position_ci95"]
        ax.errorbar(1e3 * f["time_per_step_s"], f["rmse_position"],
                    yerr=[[f["rmse_position"] - lo], [hi - f["rmse_position"]]], fmt="o", capsize=3,
                    label=f"{n} ({f['messages_per_step']} msgs/step)")
    ax.set(xscale="log", xlabel="time per step (ms, log scale)", ylabel="position RMSE (m) with 95 % CI",
           title="Accuracy against cost; legend: messages per step")
    ax.legend(fontsize=7)
    save_figure(fig, out / "fig_tradeoff.png")
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for ax, (key, label) in zip(axes, (("dos_prob", "DoS probability (FDI fixed)"),
                                       ("fdi_prob", "FDI probability (DoS fixed)"))):
        xs = sorted(sweeps[key], key=float)
        for n in filters:
            pts = [(float(v), sweeps[key][v][n]) for v in xs if n in sweeps[key][v]
                   and sweeps[key][v][n]["rmse_position"] is not None]
            if len(pts) < 2:
                continue
            x = [p[0] for p in pts]
            ax.plot(x, [p[1]["rmse_position"] for p in pts], "o-", label=n)
            ax.fill_between(x, [p[1]["rmse_position_ci95"][0] for p in pts],
                            [p[1]["rmse_position_ci95"][1] for p in pts], alpha=0.15)
        ax.set(xlabel=label, ylabel="position RMSE (m)", title=f"Degradation with the {label.split(' (')[0]}")
    axes[0].legend(fontsize=7)
    save_figure(fig, out / "fig_sweeps.png")
    fig, ax = plt.subplots(figsize=(6, 5))
    tr = A["truth"][0]
    cams = np.array([s.position for s in sc.model.sensors])
    ax.plot(cams[:, 0], cams[:, 1], "ks", ms=5, label="cameras")
    ax.plot(tr[:, 0], tr[:, 1], "k-", lw=2, label="robot")
    for f, n in enumerate(FILTERS):
        e = A["estimate"][0, f]
        if np.all(np.isfinite(e)):
            ax.plot(e[:, 0], e[:, 1], lw=1, label=n + (" (node 1)" if FAMILY[n] == "consensus" else ""))
    ax.set(xlabel="x (m)", ylabel="y (m)", title="Run 1: the robot and each filter's estimate")
    ax.legend(fontsize=7)
    save_figure(fig, out / "fig_trajectory.png")
