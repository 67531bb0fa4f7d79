"""Study ``encrypted-switching``: seed 001's simulation study (ED-PF under switching nonlinearities).

Three filters on the same runs (common random numbers): PPF (the mixture proposal
(11) and the interval likelihood (13)-(15)), PF-RSN (the same likelihood with a
model that ignores the switching, γ = 1) and PF-SR-DE (the decrypted values taken
as the measurements, the noise density as the likelihood); see
:mod:`filters.edpf`.  Outputs: RMSE_1(t) and RMSE_2(t) over the runs (Figs. 5-6)
and their time averages with bootstrap intervals, the one-run figures of the
states and estimates (Figs. 1-2) and of the ideal, resolution-limited and
decrypted measurements (Figs. 3-4), time per step with where it goes (proposal,
likelihood, the rest of the engine), collapses.  The paper prints no numbers;
its claim is that PPF is best.

Randomness: run ``r`` uses ``SeedSequence(seed).spawn(runs)[r].spawn(3)`` =
(truth, channel, filters).  The channel's draws are the key stream, then the
bit-error and dropout uniforms (:func:`filters.encryption.transmit`).  The NumPy
engine runs every run in one batch and draws all particles from one Generator
built from run 0's filter stream; every filter starts that same Generator, so
the filters share their random numbers as well as their data.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from designer.validation import InputError, check_int
from filters.edpf import fixed_mode_model, interval_loglik, mean_dynamics_model, raw_loglik, received
from filters.encryption import Codec, transmit
from filters.particle import run_sir, transition_proposal

from .progress import progress
from .results import curves_figure, error_metrics, evaluate_filter, markdown_table, study_header, write_study
from .scenarios import load_scenario

__all__ = ["run_encrypted_switching", "FILTERS", "MEAN_DYNAMICS", "PAPER"]

FILTERS = ("PPF", "PF-RSN", "PF-SR-DE")
MEAN_DYNAMICS = "PF-RSN (mean dynamics)"
ENGINES = ("numpy",)
PAPER = {
    "source": "seed 001, Sec. IV, Figs. 5-6 (RMSE_1(t), RMSE_2(t) over 50 runs)",
    "numbers": None,
    "claim": "the proposed algorithm (PPF) exhibits superior filtering performance when compared with the other "
             "two algorithms (PF-RSN, PF-SR-DE)",
    "runs": 50, "particles": 200, "steps": 120,
    "note": "no RMSE values are printed; Figs. 1-6 are not available in the text, so only the ordering is compared",
}

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
    "encrypted-switching: the filters share the data and the filter random numbers (one Generator from run 0's "
    "filter stream for the whole batch, so the filter numbers depend on the number of runs).",
    "encrypted-switching: time_per_step_s = a filter's wall time over all runs divided by runs x T (amortised over "
    "the batch); time_breakdown_s splits it into the proposal (mode and process-noise draws, f), the likelihood "
    "(h and the CDFs or densities) and the engine's remainder (weights, moments, ESS, resampling).",
)


class _Timed:
    """A callable that accumulates the wall time spent in it."""

    def __init__(self, fn):
        self.fn, self.seconds = fn, 0.0

    def __call__(self, *args):
        t = time.perf_counter()
        out = self.fn(*args)
        self.seconds += time.perf_counter() - t
        return out


def _state_metrics(err: np.ndarray, rng: np.random.Generator) -> dict:
    """Per-state time-averaged RMSE with its bootstrap interval, the RMSE_i(t) curves, the median run's RMSE."""
    per = [error_metrics(err, [i], [], rng) for i in range(err.shape[-1])]
    return {
        "rmse_state": [p["rmse_position"] for p in per],
        "rmse_state_ci95": [p["rmse_position_ci95"] for p in per],
        "rmse_state_curve": [p["rmse_position_curve"] for p in per],
        "rmse_state_median_run": [float(v) for v in np.median(np.sqrt((err**2).mean(axis=1)), axis=0)],
    }


def run_encrypted_switching(
    *,
    out: str | Path | None,
    runs: int = 50,
    particles: int = 200,
    seed: int = 0,
    quiet: bool = False,
    overrides: Mapping[str, Any] | None = None,
    assignments=(),
    workers: int = 1,
    engine: str = "numpy",
    mean_dynamics_row: bool = True,
) -> dict:
    """Run the study and write ``results.json``, ``table.md`` and the figures into ``out`` (None: no files).

    Parameters
    ----------
    runs, particles : int
        Monte Carlo runs (paper: 50) and particles M (paper: 200).
    overrides, assignments
        Scenario parameters of ``switching-2d`` (e.g. ``bit_error_prob``, ``dropout_prob``).
    workers : int
        Only 1: the NumPy engine runs all runs in one batch.
    engine : {"numpy"}
        Only the NumPy engine: the fused kernels do not support switching modes yet.
    mean_dynamics_row : bool
        Also run PF-RSN with the mode-averaged dynamics (not in the paper).
    """
    runs = check_int("runs", runs, 2)
    particles = check_int("particles", particles, 1)
    seed = check_int("seed", seed, 0)
    if check_int("workers", workers, 1) != 1:
        raise InputError(f"workers must be 1 for encrypted-switching (the NumPy engine runs all runs in one batch), "
                         f"got {workers}")
    if engine not in ENGINES:
        raise InputError(f"engine must be 'numpy' for encrypted-switching (the fused kernels do not support "
                         f"switching modes yet), got {engine!r}")
    t_start = time.perf_counter()
    sc = load_scenario("switching-2d", overrides, assignments)
    m, K = sc.model, sc.steps
    codec = Codec.of(sc.extras)
    errors = dict(bit_error_prob=sc.extras["bit_error_prob"], dropout_prob=sc.extras["dropout_prob"])

    seqs = [ss.spawn(3) for ss in np.random.SeedSequence(seed).spawn(runs)]
    truth = np.empty((runs, K + 1, m.n_x))
    z = np.empty((runs, K, m.n_z))
    t0 = time.perf_counter()
    for r in progress(range(runs), runs, quiet, "encrypted-switching data"):
        tr = sc.simulate(np.random.default_rng(seqs[r][0]), K)
        truth[r], z[r] = tr.x, tr.z
    t1 = time.perf_counter()
    txs = [transmit(z[r], codec, np.random.default_rng(seqs[r][1]), **errors) for r in range(runs)]
    y = np.stack([received(tx) for tx in txs])
    t2 = time.perf_counter()

    rsn = fixed_mode_model(m, 1)  # mode 1 <=> gamma = 1 (f active) in switching-2d
    configs = {  # name: (filter model, likelihood, description)
        "PPF": (m, interval_loglik(m, codec), "mixture proposal (11), interval likelihood (13)"),
        "PF-RSN": (rsn, interval_loglik(rsn, codec), "gamma = 1 always, interval likelihood (13)"),
        "PF-SR-DE": (m, raw_loglik(m), "mixture proposal (11), noise density at the decrypted value"),
    }
    if mean_dynamics_row:
        avg = mean_dynamics_model(m)
        configs[MEAN_DYNAMICS] = (avg, interval_loglik(avg, codec), "F x + 0.5 f + 0.5 g, interval likelihood (13)")

    metrics_rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(runs + 1)[runs])
    filters: dict[str, dict] = {}
    means: dict[str, np.ndarray] = {}
    for name, (model, ll, what) in progress(configs.items(), len(configs), quiet, "encrypted-switching filters"):
        prop, lik, kept = _Timed(transition_proposal(model)), _Timed(ll), {}

        def run(model=model, prop=prop, lik=lik, kept=kept):
            res = run_sir(model, y, np.random.default_rng(seqs[0][2]), particles=particles, runs=runs, loglik=lik,
                          proposal=prop, resampler="systematic", ess_threshold=0.5)
            kept["res"] = res
            return res.mean, res.collapsed

        met, _ = evaluate_filter(run, truth, (), (), metrics_rng)
        res = kept["res"]
        means[name] = res.mean
        for key in [k for k in met if k.startswith(("rmse_position", "rmse_velocity"))]:
            del met[key]  # no positions or velocities in this model: per-state metrics instead
        met.update(_state_metrics(truth[:, 1:] - res.mean[:, 1:], metrics_rng))
        met.update({
            "description": what, "particles": particles, "engine": engine,
            "resampled_fraction": float(res.resampled.mean()),
            "time_breakdown_s": {"proposal": prop.seconds, "likelihood": lik.seconds,
                                 "engine": met["wall_time_s"] - prop.seconds - lik.seconds},
        })
        filters[name] = met
    if mean_dynamics_row:
        filters[MEAN_DYNAMICS]["note"] = "not in the paper: PF-RSN with the mode-averaged dynamics"

    results = study_header("encrypted-switching", "switching-2d", runs=runs, particles=particles, steps=K, seed=seed,
                           assumptions=list(sc.assumptions) + list(ASSUMPTIONS), engine=engine, workers=workers)
    results.update({
        "filters": filters,
        "sweeps": {},
        "paper": PAPER,
        "claim_check": _claim_check(filters, truth, means),
        "transmission": _transmission_summary(txs, codec),
        "timing_s": {"data": t1 - t0, "channel": t2 - t1,
                     "filters": {n: f["wall_time_s"] for n, f in filters.items()},
                     "paper_filters": sum(filters[n]["wall_time_s"] for n in FILTERS)},
        "params": dict(sc.params),
    })
    return write_study(out, results, t_start, lambda d: _figures(d, truth[0], txs[0], means, filters),
                       table_markdown)


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


def _transmission_summary(txs, codec: Codec) -> dict:
    avail = np.stack([tx.available for tx in txs])
    err = np.stack([np.abs(tx.z - tx.decrypted) for tx in txs])
    return {
        "packets": int(avail.size), "available_fraction": float(avail.mean()),
        "dropped": int(sum(tx.dropped.sum() for tx in txs)),
        "crc_detected": int(sum(tx.detected.sum() for tx in txs)),
        "crc_undetected": int(sum(tx.undetected.sum() for tx in txs)),
        "saturated": int(sum(tx.saturated.sum() for tx in txs)),
        "bits_per_packet": codec.bits, "crc_bits": int(txs[0].checksum.shape[-1]),
        "bound_L_bar": np.broadcast_to(codec.bound, (txs[0].z.shape[-1],)).tolist(),
        "max_abs_z_minus_decrypted": np.nanmax(err, axis=(0, 1)).tolist() if avail.any() else None,
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
        row["split"] = " / ".join(f"{100 * tb[k] / f['wall_time_s']:.0f}" for k in ("proposal", "likelihood", "engine"))
        rows[name] = row
    cols = [("rmse1", "RMSE_1"), ("rmse2", "RMSE_2"), ("median1", "RMSE_1 median run"),
            ("median2", "RMSE_2 median run"), ("time_per_step_s", "time/step s"),
            ("split", "% proposal / likelihood / engine"), ("collapsed_steps", "collapsed steps"),
            ("collapsed_runs", "runs with a collapse")]
    text = (f"# encrypted-switching (seed 001)\n\n{results['runs']} runs, M = {results['particles']} particles, "
            f"T = {results['steps']} steps, seed {results['seed']}, engine {results['engine']}. Time-averaged "
            "RMSE_i = mean over t of RMSE_i(t), with its 95 % bootstrap interval over runs. The paper prints no "
            f"numbers; its claim: {results['paper']['claim']}.\n\n" + markdown_table(rows, cols))
    cc = results["claim_check"]
    text += "\n## The paper's claim\n\n" + markdown_table(
        {f"PPF vs {b}": {"lower": ", ".join("yes" if v else "no" for v in c["ppf_lower"]),
                         "ratio": ", ".join(f"{v:.3g}" for v in c["rmse_ratio"]),
                         "runs": ", ".join(f"{v:.2f}" for v in c["runs_ppf_lower_fraction"])}
         for b, c in cc.items() if b != "holds"},
        [("lower", "PPF lower (x1, x2)"), ("ratio", "baseline / PPF RMSE (x1, x2)"),
         ("runs", "share of runs where PPF is lower (x1, x2)")])
    text += f"\nClaim holds on both states against both baselines: {'yes' if cc['holds'] else 'no'}.\n"
    tm, tx = results["timing_s"], results["transmission"]
    text += (f"\n## Time and transmission\n\nData (truth and measurements) {tm['data']:.3g} s, channel "
             f"{tm['channel']:.3g} s, the paper's three filters {tm['paper_filters']:.3g} s, whole study "
             f"{results['wall_time_s']:.3g} s (figures not included). Packets {tx['packets']}, available "
             f"{tx['available_fraction']:.4g}, dropped {tx['dropped']}, CRC-detected errors {tx['crc_detected']}, "
             f"undetected {tx['crc_undetected']}, saturated {tx['saturated']}; max |z - z~| per sensor "
             f"{tx['max_abs_z_minus_decrypted']} (bound L-bar {tx['bound_L_bar']}).\n")
    return text


def _figures(out: Path, truth0: np.ndarray, tx0, means: dict, filters: dict) -> None:
    for i in range(truth0.shape[-1]):
        curves_figure(out / f"fig_state{i + 1}.png",
                      {"true state": truth0[1:, i], **{n: means[n][0, 1:, i] for n in FILTERS}},
                      f"x{i + 1}(t)", f"One run: x{i + 1} and its estimates (cf. Fig. {i + 1})")
        curves_figure(out / f"fig_rmse_{i + 1}.png", {n: f["rmse_state_curve"][i] for n, f in filters.items()},
                      f"RMSE_{i + 1}(t)", f"RMSE of x{i + 1} (cf. Fig. {i + 5})", log=True)
    for s in range(tx0.z.shape[-1]):
        curves_figure(out / f"fig_measurements_s{s + 1}.png",
                      {"ideal z": tx0.z[:, s], "actual (resolution) zr": tx0.zr[:, s],
                       "decrypted z~": tx0.decrypted[:, s]},
                      f"sensor {s + 1}", f"Sensor {s + 1}: ideal, actual and decrypted measurements (cf. Fig. {s + 3})")
