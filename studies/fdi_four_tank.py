"""Study ``fdi-four-tank``: seed 004's simulation study (FDI detection with modified SIS particle filters).

The four-tank plant under the bias attack (3)-(4), filtered on the same runs and
the *same particles* by: the normal SIS PF without attack (the reference of the
paper's RMSE), the normal PF under attack (with its detector (14)/(17), log-domain
weights and, as an extra row, weights emulated in linear double precision), the
proposed modified PF (detection (36), (45), (46), (58); estimation (59)), its
non-Gaussian variant (corrected particles sampled from the measurement-corrected
proposal), and the method of [31] (seed 002's likelihood adapted: deception with
probability p_l per sensor, deception vector γ̄), plus the uniform-weight outcome
the paper states for it.  Tables 3 and 4, the detection figures (Figs. 8-11), the
attack-estimate error case (Figs. 13-14) and the γ̄ = 1 case, with the paper's
numbers beside ours.

It runs on ``four-tank`` by default and on any scenario whose channel is a
:class:`designer.attacks.BiasFDI` (a model file's ``CHANNEL``) and whose measurement
is linear, ``y = G x + v``.  There it runs the default setting, the noisy attack
estimate and γ̄ = 1; Table 3's two noise levels, the plant-noise and recomputed-η
sensitivity need the four-tank's parameters and, with the paper's numbers, are given
for ``four-tank`` only.

Randomness: run ``r`` uses ``SeedSequence(seed, spawn_key=(r,)).spawn(5)`` (=
``SeedSequence(seed).spawn(runs)[r].spawn(5)``) = (plant and measurement noise,
attack occurrences, particles, attack-estimate error, the sampled correction's
own draws).  Every filter of every setting draws its particles from a fresh
Generator on the third stream, so the filters of a run share their particles (the
paper: "the same set of particles is considered in both cases"); the noise levels
and the γ̄ = 1 case share the plant draws (the high noise is √5 times the low one,
draw for draw) and the attack occurrences ``l_k``.  The bootstrap intervals use
``SeedSequence(seed, spawn_key=(2**31,))``.  Nothing is shared between runs, so a
run's numbers depend only on ``seed`` and its index.

A :class:`studies.pipeline.Study` (``STUDY``): the runs are computed by
:mod:`studies.runner` in chunks of ``chunk_size`` runs (:func:`_runs` is the task:
every setting and filter on a chunk, the fused kernels run by run or one batched NumPy program per filter, returning
per-run arrays), in this process, in local worker processes or on a Dask cluster
with identical numbers, and an interrupted study resumes from the chunks stored in
``out``.  Metrics, tables and figures are computed afterwards from the concatenated
arrays.  Its options: ``engine``, ``"fast"`` (default; the fused SIS kernels of
:func:`filters.fused.sis_fdi`, one compiled call per run) or ``"numpy"`` (:func:`filters.fdi.run_sis`,
the reference; the two agree per run to rounding, the same draws), and ``threads``, the fused
engine's threads within a chunk (default ``"auto"``: :func:`studies.pfrun.study_threads`; no
effect on the numbers).
"""
from __future__ import annotations

import functools
import pickle
from dataclasses import replace
from pathlib import Path
from typing import Any, Mapping, NamedTuple

import numpy as np

from designer.attacks import BiasFDI
from designer.validation import InputError
from filters.attacks import attack_values, bias_attack
from filters.fdi import (attack_threshold, deception_mixture_loglik, detection_counts, detection_gain,
                         false_alarm_condition, measurement_cov, measurement_matrix, modified_detector,
                         normal_detector, residual_threshold, run_sis, uniform_loglik)

from .pfrun import THREADS_AUTO, check_threads, study_threads
from .pipeline import Plan, Study, StudyOptions, naming_filter
from .figures import curves_figure, filter_colours, legend_beside, save_figure
from .results import error_metrics, markdown_table
from .scenarios import Scenario, ScenarioRef, reference
from .study_registry import StudyText

__all__ = ["STUDY", "FILTERS", "PAPER_TABLE3", "PAPER_TABLE4", "TABLE3_COLUMNS", "CHUNK_SIZE"]

SCENARIO = "four-tank"
NOATT = "normal PF (no attack)"
NORMAL = "normal PF (under attack)"
NORMAL_LIN = "normal PF (under attack), linear-domain weights"
PROPOSED = "proposed (modified PF)"
SAMPLED = "proposed, sampled correction (non-Gaussian variant)"
L31 = "method of [31]"
L31_UNIFORM = "method of [31], weights 1/N (the paper's statement)"
FILTERS = (NOATT, NORMAL, NORMAL_LIN, PROPOSED, SAMPLED, L31, L31_UNIFORM)

# Seed 004, Table 3 (verbatim), gamma-bar = 0.5 [1 1 1 1]^T, the proposed method
TABLE3_COLUMNS = ("trace(R) = 0.003, gammahat_k = gamma_k", "trace(R) = 0.015, gammahat_k = gamma_k",
                  "trace(R) = 0.003, gammahat_k = gamma_k +- 10^-2")
PAPER_TABLE3 = {
    TABLE3_COLUMNS[0]: {"rmse": 2.8e-3, "false_alarms": 0, "stealthy": 2},
    TABLE3_COLUMNS[1]: {"rmse": 4.6e-3, "false_alarms": 5, "stealthy": 2},
    TABLE3_COLUMNS[2]: {"rmse": 8e-3, "false_alarms": 0, "stealthy": 2},
}
# Seed 004, Table 4 (verbatim): R = 1e-3 diag(1, 1, 0.5, 0.5), gamma-bar = 0.5 [1 1 1 1]^T; "CPU computation time
# (average)" by MATLAB tic-toc, units not stated (seconds per step assumed)
PAPER_TABLE4 = {
    NORMAL: {"rmse": 1.3e-2, "time_per_step_s": 1.9593e-4},
    L31: {"rmse": 8.2e-3, "time_per_step_s": 6.1460e-5},
    PROPOSED: {"rmse": 2.8e-3, "time_per_step_s": 6.9782e-4},
}
NORM_BANDS = (0.5, 1.0, 1.5)  # edges (besides ||gamma||_min) of the attack-norm bands of the gamma-bar = 1 case
SINGLE_RUN_REPEATS = 3  # one-run timings: the best of this many repetitions
CHUNK_SIZE = 25  # runs per chunk of the Monte Carlo runner: the plant of a chunk's runs is simulated in one batch, whose
# per-step cost (the NumPy translation of f, some 650 operations) hardly grows with the runs (default study 19 s -> 13.5 s)
BOOTSTRAP_KEY = 2**31  # spawn key of the bootstrap intervals' stream, outside the runs' keys

ASSUMPTIONS = (
    "fdi-four-tank: RMSE (primary, the paper's 'RMSE ... to compare the estimation results with the normal PF "
    "without the attack') = mean over k = 1..K of sqrt(mean over runs of ||xhat_k - xhat_k(normal PF, no attack)||^2)"
    ", all four levels, the reference filter using the same particles (common random numbers); rmse_truth is the "
    "same against the true levels. 95 % intervals: percentile bootstrap over runs. rmse_run0 is run 0 alone (the "
    "paper reports one realisation).",
    "fdi-four-tank: every filter is SIS without resampling, as in the paper (weights degenerate over 200 steps; "
    "that is faithful).",
    "fdi-four-tank: eta = varsigma ||gamma||_min from (45) with the low-noise R, kept at both noise levels (the "
    "paper: 'eta_k = 0.233 for all of the particles in this system'); the high-noise filters use the high R in their "
    "likelihood and in K of (35). The sensitivity block gives eta recomputed by (45) at the high R.",
    "fdi-four-tank: read as typos: 'p_I = 0.5' is p_l = 0.5; Table 4's caption 'gammabar = gamma_k' is gammahat_k "
    "= gamma_k; the paper's CPU times are taken as seconds per step (units not stated).",
    "fdi-four-tank: the three columns of Table 3 and the gamma-bar = 1 case use the same runs: the same plant draws "
    "and the same attack occurrences l_k (the paper's identical 'stealthy = 2' suggests one l_k sequence); the "
    "stealthy counts are whatever the seeds give (expected about 1 per run: l_k = 1 at k = 1, 2, 3 each with "
    "probability p_l, and k = 3 (||gamma_3|| = 0.271) is sometimes detected).",
    "fdi-four-tank: alpha = p_l N/(N - 1), the lower end of (53), so zeta = p_l; an attack is declared when "
    "beta > zeta.",
    "fdi-four-tank: the normal PF's detector is (14) with the residual weights (17) (the normalised likelihoods of "
    "the current step) and the same eta; the extra row with linear-domain weights emulates double precision: "
    "likelihoods below the smallest double are 0, (17) is then 0/0 and no attack is declared, and SIS weights "
    "that all underflow are reset to uniform (MATLAB would carry NaN).",
    "fdi-four-tank: 'stealthy' = an attack (l_k = 1) not detected with ||gamma_k|| <= ||gamma||_min; 'missed' = "
    "not detected with ||gamma_k|| > ||gamma||_min; false alarm = l_k = 0 and lhat_k = 1. Counts are totals over "
    "runs; per_run holds the means per run, run0 the first run's (the paper's counts are of one realisation).",
    "fdi-four-tank: estimation mode (59) subtracts lhat_k gammahat_k; gammahat_k = gamma_k, or gamma_k + e_k with "
    "e_k ~ N(0, attack_estimate_var I) independent per step (the text and Fig. 13; Table 3 writes '+- 10^-2').",
    "fdi-four-tank: method of [31] = seed 002's likelihood with phi-bar = alpha-bar = 0 and varphi-bar = p_l per "
    "sensor, the deception adding rho = gamma-bar: p(y_s | x) = (1 - p_l) p_v(y_s - h_s) + p_l p_v(y_s - rho_s - "
    "h_s). The paper states that its adaptation gives every particle likelihood 1 (weights 1/N); that outcome is "
    "the extra row 'weights 1/N'.",
    "fdi-four-tank: the non-Gaussian variant samples the corrected particles from N(f + K(y - G f), Q - K G Q) "
    "(35) given the previous particles (its importance correction uses the true transition density), residuals "
    "weighted 1/N as in (58); its own draws come from a fifth stream of each run, run by run.",
    "fdi-four-tank: time_per_step_s = a filter's wall time (its detector included) summed over the chunks of "
    "runs (engine fast: the compiled kernel's loop over the chunk's runs, on 'threads' threads, default the "
    "machine's cores; engine numpy: one batched NumPy program "
    "of chunk_size runs, the sampled correction's detector run by run; timed wherever it ran) / (runs x K); "
    "time_per_step_single_run_s = the same filter on run 0 alone / K, best of 3 (closer to the paper's tic-toc of "
    "one run; with the NumPy engine at N = 100 it is dominated by the fixed cost of a NumPy call per step).",
    "fdi-four-tank: randomness: run r uses SeedSequence(seed, spawn_key=(r,)).spawn(5) = (plant and measurement "
    "noise, attack occurrences, particles, attack-estimate error, the sampled correction's draws), the bootstrap "
    "intervals SeedSequence(seed, spawn_key=(2**31,)); nothing is shared between runs, so a run's numbers do not "
    "depend on the number of runs or the backend. The runs are computed in chunks of chunk_size consecutive runs; "
    "the NumPy engine batches the runs of a chunk, so there the last bits of floating-point sums may depend on "
    "chunk_size (the fused engine filters run by run).",
)


class _Data(NamedTuple):
    truth: np.ndarray  # (runs, K + 1, n_x)
    y: np.ndarray  # (runs, K, n_y) attack-free measurements
    y_att: np.ndarray  # (runs, K, n_y) received under attack
    l: np.ndarray  # (runs, K) bool
    gamma: np.ndarray  # (K, n_y)
    gamma_hat: np.ndarray  # (runs, K, n_y) gamma + e, the noisy attack estimate


def _data(sc, seqs, simulated: dict) -> _Data:
    """The runs' truth and measurements (stream 0) and attacks (streams 1, 3) in setting ``sc``.

    ``simulated`` memoises the plant's runs by scenario parameters: settings that differ
    only in their channel (γ̄ = 1, the noisy estimate) simulate the same plant draw for draw.
    """
    ch = sc.channel
    key = pickle.dumps((sc.name, sorted(sc.params.items()), sc.steps, None if sc.x0 is None else np.asarray(sc.x0)))
    if key not in simulated:  # the runs together, each drawing from its own stream as a run of its own
        simulated[key] = sc.simulate([np.random.default_rng(s[0]) for s in seqs], batch=len(seqs))
    tr = simulated[key]
    ya, l, gh = [], [], []
    for s, z in zip(seqs, tr.z):
        att = bias_attack(z, bias=ch.bias, tau=ch.tau, prob=ch.prob, rng=np.random.default_rng(s[1]))
        e = np.random.default_rng(s[3]).standard_normal(att.gamma.shape) * np.sqrt(ch.estimate_var)
        ya.append(att.y), l.append(att.l), gh.append(att.gamma + e)
    return _Data(tr.x, tr.z, np.stack(ya), np.stack(l), att.gamma, np.stack(gh))


class _Design(NamedTuple):
    eta: float
    zeta: float
    alpha: float
    thresholds: dict


def _design(sc, sc_low, particles: int) -> _Design:
    """eta from (45) with the low-noise R (kept at both noise levels), zeta from (46), (53)."""
    m = sc.model
    G = measurement_matrix(m)
    th = residual_threshold(G, detection_gain(G, m.process_cov, measurement_cov(sc_low.model)),
                            sc.channel.norm_min)
    th_here = residual_threshold(G, detection_gain(G, m.process_cov, measurement_cov(m)), th.gamma_min)
    zeta, alpha = attack_threshold(particles, sc.channel.prob)
    lhs, holds = false_alarm_condition(measurement_cov(m), th.eta)
    return _Design(th.eta, zeta, alpha, {
        "eta": th.eta, "varsigma": th.varsigma, "sigma_bar": th.sigma_bar, "gamma_min": th.gamma_min,
        "eta_recomputed_here": th_here.eta, "zeta": zeta, "alpha": alpha,
        "noise_condition": {"three_sqrt_trace_R": lhs, "holds": holds},
    })


def _per_run(detector):
    """``detector`` applied run by run, run ``r`` drawing from ``rngs[r]`` (given to :func:`run_sis` as aux_rng).

    The sampled correction draws particles; one Generator for a batch of runs would make a
    run's draws depend on the runs batched with it (the chunking).
    """
    def detect(x_prev, x, k1, z_k, rngs):
        return np.concatenate([detector(x_prev[r:r + 1], x[r:r + 1], k1, z_k[r:r + 1], g)
                               for r, g in enumerate(rngs)])

    return detect


# Each filter: (measurements "y" or "y_att", its detector and likelihood as filters.fused.sis_fdi names them, takes
# gamma_hat); _numpy_filter builds the same filter for filters.fdi.run_sis.
_FILTER_SPECS = {
    NOATT: ("y", dict(detector="normal"), False),
    NORMAL: ("y_att", dict(detector="normal"), False),
    NORMAL_LIN: ("y_att", dict(detector="normal", linear_weights=True), False),
    PROPOSED: ("y_att", dict(detector="modified"), True),
    SAMPLED: ("y_att", dict(detector="sampled"), True),
    L31: ("y_att", dict(likelihood="mixture"), False),
    L31_UNIFORM: ("y_att", dict(likelihood="uniform"), False),
}


def _numpy_filter(sc, d: _Design, detector=None, likelihood="additive", linear_weights=False) -> dict:
    """run_sis's keyword arguments for the filter of :func:`filters.fused.sis_fdi` with these options."""
    m = sc.model
    kw = {"linear_weights": linear_weights} if linear_weights else {}
    if detector == "normal":
        kw.update(detector=normal_detector(m, d.eta, linear_weights=linear_weights), zeta=d.zeta)
    elif detector == "modified":
        kw.update(detector=modified_detector(m, d.eta), zeta=d.zeta)
    elif detector == "sampled":
        sampled = modified_detector(m, d.eta, correction="sampled", inputs=sc.inputs(sc.steps))
        kw.update(detector=_per_run(sampled), zeta=d.zeta)
    if likelihood == "mixture":
        kw["loglik"] = deception_mixture_loglik(m, attack_prob=sc.channel.prob, deception=sc.channel.bias)
    elif likelihood == "uniform":
        kw["loglik"] = uniform_loglik
    return kw


class _Setting(NamedTuple):
    """One setting of the study: its scenario, filters (the first is the no-attack reference) and design."""

    sc: Any
    which: tuple
    design: _Design
    specs: dict  # name -> _FILTER_SPECS[name]
    noisy_estimate: bool = False
    single_run: bool = False  # also time every filter on run 0 alone


_SETTINGS: dict[bytes, tuple[dict, dict]] = {}  # (scenario reference, particles) -> _settings(...), per process
_SETTINGS_MAX = 4


def _is_paper(sc: Scenario) -> bool:
    """The paper's own scenario (Table 3's noise levels, the sensitivity and the published numbers apply)."""
    return sc.source == SCENARIO


def _settings(ref: ScenarioRef, particles: int) -> tuple[dict, dict]:
    """The settings (key -> _Setting) and which of them is each noise level, built once per process.

    Every setting is the study's scenario with a few things changed: ``main`` (every
    filter), ``noisy`` (low noise, noisy attack estimate), ``bias1`` (γ̄ = 1) and, on the
    four-tank, the other noise level, ``plant`` (a plant with process noise) and
    ``eta_high`` (high noise, η by (45) at the high R).  A memo of a pure function
    (scenarios and CasADi functions are costly).
    """
    key = pickle.dumps((ref, particles))
    if key not in _SETTINGS:
        if len(_SETTINGS) >= _SETTINGS_MAX:
            _SETTINGS.clear()
        _SETTINGS[key] = _build_settings(ref, particles)
    return _SETTINGS[key]


def _build_settings(ref: ScenarioRef, particles: int) -> tuple[dict, dict]:
    sc = ref.build()
    params = dict(ref.params)

    def variant(**changes):
        return ScenarioRef(ref.source, tuple(sorted({**params, **changes}.items())), ref.attacks).build()

    def setting(sc, which, design=None, **kw):
        d = _design(sc, sc_low, particles) if design is None else design
        return _Setting(sc, tuple(which), d, {n: _FILTER_SPECS[n] for n in which}, **kw)

    paper = _is_paper(sc)
    sc_low = variant(noise="low") if paper else sc
    settings = {"main": setting(sc, FILTERS, single_run=True)}
    levels = {params["noise"]: "main"} if paper else {"default": "main"}
    for lv in ("low", "high") if paper else ():
        if lv not in levels:
            settings[f"noise_{lv}"] = setting(variant(noise=lv), (NOATT, PROPOSED))
            levels[lv] = f"noise_{lv}"
    settings["noisy"] = setting(sc_low, (NOATT, PROPOSED), settings[levels["low" if paper else "default"]].design,
                                noisy_estimate=True)
    bias1 = replace(sc, channel=replace(sc.channel, bias=np.ones(sc.model.n_z)))
    settings["bias1"] = setting(bias1, (NOATT, NORMAL, NORMAL_LIN, PROPOSED))
    if paper:
        settings["plant"] = setting(variant(noise="low", plant_noise=True), (NOATT, PROPOSED))
        d_hi = settings[levels["high"]].design
        settings["eta_high"] = setting(variant(noise="high"), (NOATT, PROPOSED),
                                       d_hi._replace(eta=d_hi.thresholds["eta_recomputed_here"]))
    return settings, levels


def _key(setting: str, name: str, what: str) -> str:
    return f"{setting}_{FILTERS.index(name)}_{what}"


def _runs(run_ids, seeds, *, ref: ScenarioRef, particles: int, engine: str = "fast", threads: int = 1) -> dict:
    """Task of the runner: every setting and filter on the runs ``run_ids``; per-run arrays.

    Keys per setting ``s``: ``s_truth`` (R, K + 1, n_x), ``s_l`` (R, K) attack occurrences,
    ``s_gamma_hat`` (R, K, n_y) (the noisy setting); per filter ``f`` (index in ``FILTERS``):
    ``s_f_mean`` (R, K + 1, n_x), ``s_f_detected`` (R, K) (with a detector), ``s_f_collapsed``
    (R,) collapsed steps, ``s_f_final_ess`` (R,), ``s_f_seconds`` (R,) the chunk's wall time
    shared equally by its runs, and in the main setting ``s_f_single_s`` (R,) the best of
    ``SINGLE_RUN_REPEATS`` timings of run 0 alone (NaN for the other runs).
    """
    plans, _ = _settings(ref, particles)
    seqs = [s.spawn(5) for s in seeds]
    R = len(seqs)
    out, simulated = {}, {}
    for key, p in plans.items():
        sc = p.sc
        data = _data(sc, seqs, simulated)
        # the SIS particles depend on no measurement: every filter of the setting weighs the same ones (fast engine)
        shared = _particles(sc, seqs, particles, threads) if engine == "fast" else None
        out[f"{key}_truth"], out[f"{key}_l"] = data.truth, data.l
        if p.noisy_estimate:
            out[f"{key}_gamma_hat"] = data.gamma_hat
        gamma_hat = data.gamma_hat if p.noisy_estimate else data.gamma
        for name in p.which:
            zname, kw, takes_gamma = p.specs[name]
            z = getattr(data, zname)
            extra = {"gamma_hat": gamma_hat} if takes_gamma else {}
            with naming_filter(name, run_ids):
                res = _run(sc, p.design, engine, z, seqs, particles, shared=shared, threads=threads, **kw,
                           **extra)
            out[_key(key, name, "mean")] = res.mean
            if kw.get("detector"):
                out[_key(key, name, "detected")] = res.detected
            out[_key(key, name, "collapsed")] = res.collapsed.sum(axis=1)
            out[_key(key, name, "final_ess")] = res.ess[:, -1]
            out[_key(key, name, "seconds")] = np.full(R, res.wall_time_s / R)
            if p.single_run:
                single = np.full(R, np.nan)
                hit = np.flatnonzero(np.asarray(run_ids) == 0)
                if hit.size:
                    a = int(hit[0])
                    one = {"gamma_hat": gamma_hat[a:a + 1] if gamma_hat.ndim == 3 else gamma_hat} if takes_gamma \
                        else {}
                    single[a] = min(_run(sc, p.design, engine, z[a:a + 1], seqs[a:a + 1], particles, **kw,
                                         **one).wall_time_s
                                    for _ in range(SINGLE_RUN_REPEATS))
                out[_key(key, name, "single_s")] = single
    return out


def _particles(sc, seqs, particles: int, threads: int = 1):
    """The fused engine's SIS particles of the runs ``seqs``: each run's prior draws then its propagation, from its
    Generator on stream 2 (as run_sis draws them)."""
    from filters.fused import sis_particles

    rngs = [np.random.default_rng(s[2]) for s in seqs]
    x0 = np.stack([sc.model.prior.sample(g, particles) for g in rngs])
    return sis_particles(sc.model, x0, rngs, sc.steps, inputs=sc.inputs(sc.steps), threads=threads)


def _run(sc, d: _Design, engine: str, z, seqs, particles: int, gamma_hat=None, shared=None, threads: int = 1,
         **spec):
    """One filter (``spec``: its detector and likelihood, see ``_FILTER_SPECS``) on the runs ``seqs``.

    Each run's particles from its Generator on stream 2 (the prior's draws first; the fused
    engine takes them from ``shared`` if given, see :func:`_particles`), the sampled
    correction's from its own Generator on stream 4; the fused kernels
    (:func:`filters.fused.sis_fdi`) or :func:`filters.fdi.run_sis`.  The fused engine's
    wall time includes the particles' (drawn once per setting, every filter's cost).
    """
    aux = [np.random.default_rng(s[4]) for s in seqs]
    extra = {} if gamma_hat is None else {"gamma_hat": gamma_hat}
    if engine == "numpy":
        rngs = [np.random.default_rng(s[2]) for s in seqs]
        return run_sis(sc.model, z, rngs, particles=particles, inputs=sc.inputs(sc.steps), aux_rng=aux,
                       **_numpy_filter(sc, d, **spec), **extra)
    from filters.fused import sis_fdi

    if spec.get("likelihood") == "mixture":
        extra.update(attack_prob=sc.channel.prob, deception=sc.channel.bias)
    if spec.get("detector"):
        extra.update(eta=d.eta, zeta=d.zeta)
    if spec.get("detector") == "sampled":
        extra["aux_rngs"] = aux
    return sis_fdi(sc.model, shared or _particles(sc, seqs, particles, threads), z, threads=threads, **spec, **extra)


class _View(NamedTuple):
    """One setting's per-run arrays (from the runner's arrays)."""

    mean: dict  # name -> (runs, K + 1, n_x)
    detected: dict  # name -> (runs, K) bool, filters with a detector
    truth: np.ndarray  # (runs, K + 1, n_x)
    l: np.ndarray  # (runs, K) bool
    gamma: np.ndarray  # (K, n_y)
    gamma_hat: np.ndarray | None  # (runs, K, n_y) of the noisy setting


class _Outcome(NamedTuple):
    """One setting's results over all runs."""

    filters: dict  # name -> metrics
    view: _View
    design: _Design


def _view(key: str, p: _Setting, A: Mapping) -> _View:
    """Setting ``key``'s arrays in ``A`` (filters in ``p.which`` order)."""
    sc = p.sc
    means = {name: A[_key(key, name, "mean")] for name in p.which}
    detected = {name: A[_key(key, name, "detected")] for name in p.which if _key(key, name, "detected") in A}
    return _View(means, detected, A[f"{key}_truth"], A[f"{key}_l"],
                 attack_values(sc.steps, sc.channel.bias, sc.channel.tau), A.get(f"{key}_gamma_hat"))


def _counts(detected, l, gamma, gamma_min: float, attacked: bool) -> dict:
    l = l if attacked else np.zeros_like(l)
    total = detection_counts(l, detected, gamma, gamma_min)._asdict()
    first = detection_counts(l[:1], detected[:1], gamma, gamma_min)._asdict()
    runs = l.shape[0]
    return {**total, "runs": runs, "steps": int(l.shape[1]),
            "per_run": {k: v / runs for k, v in total.items()}, "run0": first}


def _scores(mean, ref_mean, truth, seconds, collapsed, final_ess, rng) -> dict:
    n_x = truth.shape[-1]
    err = mean[:, 1:] - ref_mean[:, 1:]
    a = error_metrics(err, range(n_x), (), rng)
    b = error_metrics(mean[:, 1:] - truth[:, 1:], range(n_x), (), rng)
    K = err.shape[1]
    wall = float(seconds.sum())
    return {
        "rmse": a["rmse_position"], "rmse_ci95": a["rmse_position_ci95"],
        "rmse_run0": float(np.linalg.norm(err[0], axis=-1).mean()),
        "rmse_components": a["rmse_state"], "rmse_curve": a["rmse_position_curve"],
        "rmse_truth": b["rmse_position"], "rmse_truth_ci95": b["rmse_position_ci95"], "rmse_state": b["rmse_state"],
        "rmse_truth_curve": b["rmse_position_curve"],
        "time_per_step_s": wall / (err.shape[0] * K), "wall_time_s": wall,
        "collapsed_steps": int(collapsed.sum()), "final_ess": float(final_ess.mean()),
    }


def _outcome(key: str, p: _Setting, A: Mapping, rng) -> _Outcome:
    """Metrics of setting ``key`` from the concatenated arrays ``A`` (filters in ``p.which`` order)."""
    v = _view(key, p, A)
    gmin = p.design.thresholds["gamma_min"]
    filters = {}
    for name in p.which:
        met = _scores(v.mean[name], v.mean[NOATT], v.truth, A[_key(key, name, "seconds")],
                      A[_key(key, name, "collapsed")], A[_key(key, name, "final_ess")], rng)
        if p.single_run:
            met["time_per_step_single_run_s"] = float(A[_key(key, name, "single_s")][0]) / p.sc.steps
        if name in v.detected:
            met["detection"] = _counts(v.detected[name], v.l, v.gamma, gmin, attacked=name != NOATT)
        filters[name] = met
    return _Outcome(filters, v, p.design)


def _bands(detected, l, gamma, gamma_min: float) -> list[dict]:
    norms = np.linalg.norm(gamma, axis=-1)
    edges = [0.0, gamma_min, *[e for e in NORM_BANDS if e > gamma_min], np.inf]
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (norms > lo) & (norms <= hi)
        att = l[:, sel]
        rows.append({"norm_above": lo, "norm_up_to": None if np.isinf(hi) else hi, "attacks": int(att.sum()),
                     "missed": int((att & ~detected[:, sel]).sum())})
    return rows


OTHER_MODEL = ("fdi-four-tank (a model other than four-tank): the default setting, the noisy attack estimate and "
               "gamma-bar = 1 are run with the model's own measurement noise (eta from (45) at its R); Table 3's "
               "two noise levels and the sensitivity block need the four-tank's parameters and are left out.")


def _accepts(sc: Scenario) -> str | None:
    if not isinstance(sc.channel, BiasFDI):
        return ("fdi-four-tank needs a bias false-data-injection attack: declare CHANNEL = BiasFDI(...) "
                "(designer.attacks) in the model file")
    try:
        measurement_matrix(sc.model)
    except InputError as exc:
        return f"fdi-four-tank's detectors need a linear measurement y = G x + v ({exc})"
    return None


def _check(so: StudyOptions) -> None:
    if so["engine"] not in ("fast", "numpy"):
        raise InputError(f"engine must be 'fast' or 'numpy', got {so['engine']!r}")
    check_threads(so["threads"])


def _plan(sc: Scenario, so: StudyOptions) -> Plan:
    ref = reference(sc)
    plans, _ = _settings(ref, so.particles)  # builds the settings and checks the designs before any run
    task = functools.partial(_runs, ref=ref, particles=so.particles, engine=so["engine"], threads=study_threads(so))
    config = {"study": "fdi-four-tank", "scenario": sc.name, "params": dict(ref.params), "particles": so.particles,
              "engine": so["engine"], "settings": {k: list(p.which) for k, p in plans.items()},
              "streams": "run r: SeedSequence(seed, spawn_key=(r,)).spawn(5)",
              "channel": repr(sc.channel)}
    return Plan(task, "fdi-four-tank", config)


def _summarise(sc0: Scenario, mc, so: StudyOptions) -> dict:
    runs, particles, seed = so.runs, so.particles, so.seed
    plans, levels = _settings(reference(sc0), particles)
    paper = _is_paper(sc0)
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(BOOTSTRAP_KEY,)))
    res = {key: _outcome(key, p, mc.arrays, rng) for key, p in plans.items()}  # in the settings' order
    main, noisy, b1 = res["main"], res["noisy"], res["bias1"]
    lv = {name: res[key] for name, key in levels.items()}

    # gamma-bar = 1: the normal PF misses small and large attacks (Fig. 9), the proposed detects them (Fig. 10)
    gmin = main.design.thresholds["gamma_min"]
    shown = (NORMAL_LIN, NORMAL, PROPOSED)
    bias1 = {"attack_bias": [1.0] * sc0.model.n_z,
             "detection": {n: b1.filters[n]["detection"] for n in shown},
             "missed_by_attack_norm": {n: _bands(b1.view.detected[n], b1.view.l, b1.view.gamma, gmin)
                                       for n in shown}}
    detection = {n: {k: f["detection"][k] for k in ("false_alarms", "missed", "stealthy", "attacks", "detected",
                                                     "runs", "steps", "per_run", "run0")}
                 for n, f in main.filters.items() if "detection" in f}
    b = mc.backend
    out = {"scenario": sc0.name, "runs": int(runs), "particles": particles, "steps": int(sc0.steps),
           "assumptions": list(sc0.assumptions) + list(ASSUMPTIONS) + ([] if paper else [OTHER_MODEL]),
           "engine": so["engine"], "threads": study_threads(so),
           "workers": b.workers if b.kind == "processes" else (1 if b.kind == "batched" else None),
           "runner": mc.describe(), "filters": main.filters, "detection": detection,
           "thresholds": {name: st.design.thresholds for name, st in lv.items()}}
    if paper:
        out["table3"] = {col: _table3_column(setting, st.filters[PROPOSED])
                         for col, setting, st in zip(TABLE3_COLUMNS, ("low", "high", "low, noisy gamma-hat"),
                                                     (lv["low"], lv["high"], noisy))}
    out["attack_bias_1"] = bias1
    if paper:
        # Sensitivity: a plant with process noise; eta recomputed by (45) at the high noise
        plant, recomputed = res["plant"], res["eta_high"]
        out["sensitivity"] = {
            "plant_noise_low_R": {"rmse": plant.filters[PROPOSED]["rmse"],
                                  "detection": plant.filters[PROPOSED]["detection"],
                                  "note": "the plant simulated with the process noise N(0, Q) that the filters "
                                          "assume"},
            "eta_recomputed_high_R": {"eta": recomputed.design.eta, "rmse": recomputed.filters[PROPOSED]["rmse"],
                                      "detection": recomputed.filters[PROPOSED]["detection"]},
        }
        out["paper"] = {"source": "seed 004, Tables 3 and 4", "table3": PAPER_TABLE3, "table4": PAPER_TABLE4,
                        "eta": 0.233, "gamma_min": 0.28, "particles": 100,
                        "claims": ["Fig. 8: every attack with ||gamma_k|| > 0.28 detected, no false alarm (low R)",
                                   "Fig. 9: the normal PF misses small and large attacks (gamma-bar = 1)",
                                   "Fig. 10: the proposed PF detects every attack above ||gamma||_min (gamma-bar "
                                   "= 1)",
                                   "Fig. 11: 5 false alarms at the high R",
                                   "Table 4: RMSE proposed < method of [31] < normal PF under attack"]}
    out["params"] = dict(sc0.params)
    return out


def _table3_column(setting: str, f: dict) -> dict:
    det = f["detection"]
    return {"setting": setting, "rmse": f["rmse"], "rmse_ci95": f["rmse_ci95"], "rmse_run0": f["rmse_run0"],
            "rmse_truth": f["rmse_truth"], "false_alarms": det["per_run"]["false_alarms"],
            "stealthy": det["per_run"]["stealthy"], "missed": det["per_run"]["missed"],
            "false_alarms_run0": det["run0"]["false_alarms"], "stealthy_run0": det["run0"]["stealthy"],
            "detection": det}


def table_markdown(results: dict) -> str:
    """Tables 4 and 3 with ours beside the paper's, detection counts, the gamma-bar = 1 case, sensitivity."""
    f, paper, params = results["filters"], results.get("paper") or {}, results["params"]
    ths = results["thresholds"]
    th = ths.get(params.get("noise"), next(iter(ths.values())))
    rows4 = {}
    for name, v in f.items():
        pp = paper.get("table4", {}).get(name, {})
        rows4[name] = {**v, "rmse_ci": f"{v['rmse']:.3g} [{v['rmse_ci95'][0]:.3g}, {v['rmse_ci95'][1]:.3g}]",
                       "paper_rmse": pp.get("rmse"), "paper_time": pp.get("time_per_step_s")}
    setting = (f", noise {params['noise']}, gamma-bar = {params['attack_bias']}, plant noise "
               f"{params['plant_noise']}" if paper else "")
    text = (f"# fdi-four-tank {'(seed 004)' if paper else 'on ' + results['scenario']}\n\n{results['runs']} runs, "
            f"N = {results['particles']} particles, K = {results['steps']} steps, seed {results['seed']}{setting}. "
            f"eta = {th['eta']:.4g} ({'paper 0.233; ' if paper else ''}varsigma = {th['varsigma']:.4g}, "
            f"||gamma||_min = {th['gamma_min']:.3g}), zeta = {th['zeta']:.4g} (alpha = {th['alpha']:.4g}); "
            f"3 tr(R)^0.5 = {th['noise_condition']['three_sqrt_trace_R']:.4g} "
            f"({'<=' if th['noise_condition']['holds'] else '>'} eta).\n\n"
            "RMSE = against the normal PF without attack on the same particles (the paper's definition, mean over "
            "steps of the RMSE over runs, with its 95 % bootstrap interval); RMSE vs truth = against the true "
            f"{'levels' if paper else 'state'}.\n\n"
            + ("## Table 4: RMSE and time per step (low R unless set otherwise)\n\n" if paper else
               "## RMSE and time per step\n\n"))
    cols4 = [("rmse_ci", "RMSE (ours)"), ("paper_rmse", "RMSE (paper)"), ("rmse_run0", "RMSE run 0"),
             ("rmse_truth", "RMSE vs truth"), ("time_per_step_s", "time/step s, batched"),
             ("time_per_step_single_run_s", "time/step s, one run"), ("paper_time", "time/step (paper)"),
             ("collapsed_steps", "collapsed steps")]
    if not paper:
        cols4 = [(k, h.replace(" (ours)", "")) for k, h in cols4 if not k.startswith("paper_")]
    text += markdown_table(rows4, cols4, "filter")
    if "table3" in results:
        rows3 = {}
        for col, v in results["table3"].items():
            pp = paper["table3"][col]
            rows3[col] = {**v, "paper_rmse": pp["rmse"], "paper_fa": pp["false_alarms"], "paper_st": pp["stealthy"]}
        text += "\n## Table 3: the proposed method (counts per run: mean over runs, and run 0)\n\n" + markdown_table(
            rows3, [("rmse", "RMSE (ours)"), ("paper_rmse", "RMSE (paper)"), ("rmse_run0", "RMSE run 0"),
                    ("false_alarms", "false alarms/run"), ("false_alarms_run0", "false alarms run 0"),
                    ("paper_fa", "false alarms (paper)"), ("stealthy", "stealthy/run"),
                    ("stealthy_run0", "stealthy run 0"), ("paper_st", "stealthy (paper)"),
                    ("missed", "missed above min/run")], "setting")
    cols = [("false_alarms", "false alarms"), ("missed", "missed (> min)"), ("stealthy", "stealthy (<= min)"),
            ("attacks", "attacks"), ("detected", "detected")]
    text += ("\n## Detection at the default setting (totals over runs)\n\n"
             + markdown_table(results["detection"], cols, "filter"))
    b1 = results["attack_bias_1"]
    text += ("\n## gamma-bar = 1 (Figs. 9-10): totals over runs\n\n"
             + markdown_table(b1["detection"], cols, "filter")
             + "\nMissed attacks by attack norm (missed / attacks):\n\n")
    bands = next(iter(b1["missed_by_attack_norm"].values()))
    heads = [(f"b{i}", f"({b['norm_above']:.3g}, " + ("inf" if b["norm_up_to"] is None else f"{b['norm_up_to']:.3g}")
              + "]") for i, b in enumerate(bands)]
    rowsb = {n: {f"b{i}": f"{b['missed']} / {b['attacks']}" for i, b in enumerate(v)}
             for n, v in b1["missed_by_attack_norm"].items()}
    text += markdown_table(rowsb, heads, "filter (missed / attacks by attack norm)")
    if "sensitivity" in results:
        s = results["sensitivity"]
        rows_s = {"plant with process noise, low R": {**s["plant_noise_low_R"]["detection"],
                                                      "rmse": s["plant_noise_low_R"]["rmse"]},
                  f"high R, eta recomputed by (45) = {s['eta_recomputed_high_R']['eta']:.3g}":
                      {**s["eta_recomputed_high_R"]["detection"], "rmse": s["eta_recomputed_high_R"]["rmse"]}}
        text += "\n## Sensitivity of the proposed method (totals over runs)\n\n" + markdown_table(
            rows_s, [("rmse", "RMSE"), *cols], "setting")
    return text


def _detection_panel(ax, l, detected, title, color=None):
    k = np.arange(1, len(l) + 1)
    ax.step(k, l.astype(int) - detected.astype(int), where="mid", lw=1.0, color=color)
    ax.set(ylim=(-1.3, 1.3), yticks=[-1, 0, 1], ylabel="l_k - lhat_k", title=title)


def _figures(out: Path, results: dict, built: Mapping, arrays: Mapping) -> None:
    from .figures import plotting

    plt = plotting()
    sc, A = next(iter(built.values())), next(iter(arrays.values()))
    plans, levels = _settings(reference(sc), results["particles"])
    colours = filter_colours(results["filters"])
    views = {key: _view(key, p, A) for key, p in plans.items()}
    paper = _is_paper(sc)
    gmin = plans["main"].design.thresholds["gamma_min"]
    K = sc.steps
    k = np.arange(1, K + 1)

    def detection_figure(path, st, names, title):
        fig, axes = plt.subplots(1 + len(names), 1, figsize=(8, 2.2 * (1 + len(names))), sharex=True)
        gn = np.linalg.norm(st.gamma, axis=-1)
        axes[0].plot(k, gn, "k-", lw=1.2, label="||gamma_k||")
        axes[0].step(k, st.l[0] * gn.max(), where="mid", lw=0.6, alpha=0.6, label="l_k (scaled)")
        axes[0].axhline(gmin, color="r", ls="--", lw=0.8, label="||gamma||_min")
        axes[0].legend(fontsize=7, loc="lower right")
        axes[0].set(title=title)
        for ax, n in zip(axes[1:], names):
            _detection_panel(ax, st.l[0], st.detected[n][0], n, colours.get(n))
        axes[-1].set(xlabel="time step k")
        save_figure(fig, path)

    if paper:
        detection_figure(out / "fig_detection_low.png", views[levels["low"]], (PROPOSED,),
                         "Detection, low R, gamma-bar = 0.5 (cf. Fig. 8), run 0")
        detection_figure(out / "fig_detection_high.png", views[levels["high"]], (PROPOSED,),
                         "Detection, high R (cf. Fig. 11), run 0")
    else:
        detection_figure(out / "fig_detection.png", views["main"], (PROPOSED,), "Detection (cf. Fig. 8), run 0")
    detection_figure(out / "fig_detection_bias1.png", views["bias1"], (NORMAL_LIN, NORMAL, PROPOSED),
                     "gamma-bar = 1: normal PF (cf. Fig. 9) and proposed (cf. Fig. 10), run 0")

    main = views["main"]
    n_x = sc.model.n_x
    fig, axes = plt.subplots((n_x + 1) // 2, 2 if n_x > 1 else 1, figsize=(10, 3 * ((n_x + 1) // 2)), sharex=True,
                             squeeze=False)
    for j, ax in enumerate(axes.ravel()):
        if j >= n_x:
            ax.set_visible(False)
            continue
        ax.plot(np.arange(K + 1), main.truth[0, :, j], "k-", lw=1.5, label="truth")
        for n in (NOATT, NORMAL, PROPOSED, L31):
            ax.plot(np.arange(K + 1), main.mean[n][0, :, j], lw=1.0, color=colours[n], label=n)
        ax.set(ylabel=f"{sc.model.state_names[j]}{' (cm)' if paper else ''}")
    legend_beside(axes[0, -1])
    for ax in axes[-1]:
        ax.set_xlabel("time step k")
    fig.suptitle(f"One run: {'levels' if paper else 'states'} and estimates (cf. Figs. 7, 15)")
    save_figure(fig, out / "fig_estimates.png")

    noisy = views["noisy"]
    var = sc.channel.estimate_var
    fig, ax = plt.subplots(figsize=(8, 3))
    ax.plot(k, np.linalg.norm(noisy.gamma, axis=-1), "k-", label="||gamma_k||")
    ax.plot(k, np.linalg.norm(noisy.gamma_hat[0], axis=-1), lw=0.8, label="||gammahat_k||")
    ax.set(xlabel="time step k", title=f"Attack estimate with error covariance {var:g} I (cf. Fig. 13), run 0")
    ax.legend(fontsize=8)
    save_figure(fig, out / "fig_gamma_hat.png")

    curves_figure(out / "fig_rmse.png", {n: f["rmse_curve"] for n, f in results["filters"].items() if n != NOATT},
                  "RMSE against the no-attack normal PF", "RMSE over runs at each step (same particles)", log=True,
                  colours=colours)


TEXT = StudyText(
    title="Detecting false-data injection and estimating the levels of a four-tank process",
    paper="Sadeghzadeh-Nokhodberiz, Meskin, Hasanzadeh: Modified particle filters for detection of FDI "
          "attacks and state estimation in networked nonlinear systems (seed 004)",
    summary=(
        "Four connected water tanks are measured by four level sensors. At random times an attacker adds a "
        "bias to the readings (false-data injection, FDI). A filter must both tell when an attack happens "
        "(detection) and keep estimating the true levels. All filters of a run share the same particles. "
        "The paper's RMSE measures how far each filter under attack strays from the normal filter that sees "
        "no attack; we also give the error against the true levels. The question: does the modified filter "
        "detect attacks without false alarms and estimate as if there were no attack?"),
    filters={
        "normal PF (no attack)": "the normal particle filter on attack-free readings: the reference of the "
                                 "paper's RMSE",
        "normal PF (under attack)": "the normal particle filter on attacked readings, with its detector",
        "normal PF (under attack), linear-domain weights": "not in the paper: the same with weights in plain "
                                                           "double precision",
        "proposed (modified PF)": "the paper's filter: detects attacks with measurement-corrected particles "
                                  "and removes the estimated bias",
        "proposed, sampled correction (non-Gaussian variant)": "the paper's non-Gaussian variant of the "
                                                               "proposed filter",
        "method of [31]": "the binary multi-attack paper's likelihood adapted to this plant",
        "method of [31], weights 1/N (the paper's statement)": "the outcome the paper states for [31]",
    },
    attacks=(
        "False-data injection: at each step, with probability p_l (`attack_prob`), a bias vector gamma_k "
        "that drifts towards gamma-bar (`attack_bias`, rate `attack_tau`) is added to the four readings. "
        "Attacks smaller than ||gamma||_min (`attack_norm_min`) are undetectable by design and counted as "
        "stealthy, not missed."),
    attack_params=("attack_prob", "attack_bias", "attack_tau", "attack_norm_min", "attack_estimate_var"),
    accuracy=(("rmse", "RMSE against the attack-free normal PF (the paper's measure)"),
              ("rmse_truth", "RMSE against the true levels")),
    references=("normal PF (no attack)",),
    figures={
        "fig_estimates.png": "One run: the tank levels and the estimates (the paper's Figs. 7 and 15).",
        "fig_detection_low.png": "Detection with the low measurement noise, run 0 (the paper's Fig. 8).",
        "fig_detection_high.png": "Detection with the high measurement noise, run 0 (the paper's Fig. 11).",
        "fig_detection.png": "Detection at the model's measurement noise, run 0 (the paper's Fig. 8, on a model "
                             "other than the four-tank).",
        "fig_detection_bias1.png": "With gamma-bar = 1: the normal PF and the proposed filter, run 0 (the paper's "
                                   "Figs. 9-10).",
        "fig_gamma_hat.png": "The attack estimate with an error of covariance 1e-2 I, run 0 (the paper's "
                             "Fig. 13).",
        "fig_rmse.png": "RMSE against the attack-free normal PF at each step (same particles).",
    },
)


STUDY = Study(
    name="fdi-four-tank",
    text=TEXT,
    scenarios=(SCENARIO,),
    runs=50,
    particles=100,
    chunk_size=CHUNK_SIZE,
    plan=_plan,
    summarise=_summarise,
    table=table_markdown,
    figures=_figures,
    options={"engine": "fast", "threads": THREADS_AUTO},
    accepts=_accepts,
    check=_check,
)
