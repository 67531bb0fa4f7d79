"""Study ``comparison``: every filter family on the same model, runs and attack realisations.

It runs on any scenario with a sensor network: the built-in indoor robot and
range-bearing target by default, or a user's model file.  Every filter family faces
one realisation of the same attack law per run (:func:`filters.attacks.channel_draws`):

* **consensus EKF** (paper design and tuned design) — every sensor is a node that
  estimates the state from its own sensor and its neighbours' estimates; the
  node-to-node channels suffer DoS (message lost) and FDI (the model's injected signal
  added to the estimate sent).  Messages per step: one per directed link (``2 |E|``).
* **the literature's distributed filters** (:mod:`filters.distributed`) on the same network and
  channel realisations — ``KCF``, Olfati-Saber's Kalman consensus filter (CDC 2007 / CDC 2009:
  neighbours' measurement information plus a consensus term on their predictions; ``2 |E|``
  messages per step), and ``HCMCI``, the hybrid consensus on measurements and information of
  Battistelli, Chisci, Mugnai, Farina, Graziano (IEEE TAC 2015: ``L`` consensus rounds per step,
  study option ``hcmci_iterations``, default 1, so ``2 |E| L`` messages per step).  A DoS'ed packet
  is lost; an FDI'd packet is the one its sender would send if the state were displaced by ``ξ``.
* **local EKF at every node** — every node alone with its own sensor, no network (the
  baseline a networked design must beat).  Messages per step: 0.
* **centralized filters** — every sensor sends its measurement to one fusion centre
  over an uplink with the same attack law (:func:`filters.attacks.receive`: DoS = lost
  packet, FDI = the measurement falsified as if the state were displaced by ``ξ``).
  Messages per step: one per sensor.  Three filters: a bootstrap particle filter whose
  likelihood knows the attack law (a mixture with the falsified packets' moment-matched
  density), the same particle filter trusting every packet, and a plain EKF trusting
  every packet.

Metrics per filter: RMSE of the position (or, for a model without declared position
components, of the whole state) over runs and steps (consensus and local filters: also
over the nodes, each node's own estimate), its 95 % bootstrap interval over runs, the
median run, the per-step curve, time per step (one run, the whole network or centre),
messages per step, runs where a consensus design's conditions failed or a filter
diverged.  A paper design that cannot start (σ or β beyond (28)/(29) at the first step, the
same in every run) is not run: it is reported as infeasible, with the reason, and every other
filter runs.  Sweeps: the DoS probability with FDI as declared, and the FDI probability
with DoS as declared, on the same runs (common random numbers: the same draws turn into
more attacks as the probability grows).

Randomness: run ``r`` uses ``SeedSequence(seed, spawn_key=(r,)).spawn(3)`` = (truth,
channel draws, particle filters); the particle filters reuse the same stream at every
sweep setting.  Runs are computed in chunks by :mod:`studies.runner`, so the numbers
are identical in-process, with ``--workers N`` or on a Dask cluster, and an interrupted
study resumes.
"""
from __future__ import annotations

import dataclasses
import functools
import re
import time
from pathlib import Path
from typing import Sequence

import numpy as np

import rules
from designer.cores import ALLOCATOR
from designer.design import DESIGN_ASSUMPTIONS, DesignOptions
from designer.progress import phase
from designer.regions import Carried, describe_regions, region_error2
from designer.rule import DEPLOYABLE, runtime_label
from designer.validation import InputError, check_int, check_positive, check_probability
from filters.attacks import channel_draws
from filters.consensus_batch import EdgeAttacks
from filters.particle import DEGENERATE_ESS, degenerate
from filters.result import HARD_CONDITIONS

from designer.verdict import VERDICT_ASSUMPTIONS, VERDICTS, count_verdicts

from .consensus_design import bound_verdicts, check_first_step, consensus_design, prefetch_tables
from .design_options import as_mode
from .filter_registry import (Batch, FilterEntry, FilterRegistry, centralized_ekf, designed_consensus, hcmci, kcf,
                              local_ekfs, particle_filters)
from .pipeline import Plan, Study, StudyOptions
from .recorded import uplinks_received
from .figures import curves_figure, filter_colours, legend_beside, plotting, save_figure
from .results import (DIVERGENCE_SPREAD, bootstrap_rmse_ci, compared_with_local, divergence_limit,
                      first_divergence, local_ratio_text, markdown_table, per_run_mse)
from .reports.text import MEASURED, fmt_dur
from .scenarios import Scenario, reference
from .study_registry import StudyText

__all__ = ["STUDY", "FILTERS", "FILTER_REGISTRY", "SWEEP_VALUES", "CHUNK_SIZE", "CHUNK_ROWS", "CHUNKS_LARGE", "chunk_size", "HCMCI_ITERATIONS", "realise",
           "chosen_filters", "left_out", "JOINT_ROWS_DEFAULT", "TABLES_ROWS_DEFAULT", "sweeps_left_out", "SWEEP_ROWS",
           "particle_pilot", "PILOT_RUNS"]

TUNED, PAPER_DESIGN = "consensus EKF (tuned design)", "consensus EKF (paper design)"
PF_AWARE, PF_PLAIN, EKF_PLAIN = "centralized PF (attack-aware)", "centralized PF (trusts every packet)", \
    "centralized EKF (trusts every packet)"
LOCAL = "local EKF at every node (no network)"
MSE = "consensus EKF (mse design)"
SCHEDULED = "consensus EKF (scheduled design)"
RELAY = "relay EKF (relay design)"
FLOOD = "relay EKF (flood design)"
KCF, HCMCI = "KCF", "HCMCI"
HCMCI_ITERATIONS = 1  # default L: the same 2|E| messages per step as the consensus EKF and KCF
_DESCRIPTION = {
    PF_AWARE: "centralized bootstrap particle filter; its likelihood models lost packets and falsified ones "
              "(mixture with the falsification's moment-matched density)",
    PF_PLAIN: "centralized bootstrap particle filter; skips lost packets, trusts every received one",
    EKF_PLAIN: "centralized EKF; skips lost packets, trusts every received one (ignores attacks)",
    LOCAL: "every node alone: an EKF on its own sensor, no communication (nothing to attack)",
    KCF: "distributed, from the literature: Olfati-Saber's Kalman consensus filter (IEEE CDC 2007; CDC 2009, "
         "Algorithm 1), extended form: each node fuses its own and its neighbours' measurement information and adds "
         "a consensus term on their predictions with gain eps M_i / (1 + ||M_i||_F), eps = 0.5/d_max",
    HCMCI: "distributed, from the literature: hybrid consensus on measurements and on information of Battistelli, "
           "Chisci, Mugnai, Farina, Graziano (IEEE TAC 60(5), 2015), extended form: L Metropolis consensus rounds per "
           "step on the prior and measurement information (covariance intersection), measurements scaled by the "
           "network size N (the centralized EKF as L grows, without attacks)",
}
# The filters compared, in the order of the arrays and tables: a new filter is one entry (FILTER_REGISTRY.register),
# a new gain rule's design filter joins by itself (its study_label and study_description). Each records what it
# needs at run time (designer.rule.FILTER_RUNTIMES): a designed filter its gain rule's
# (mse: global, an oracle); KCF, HCMCI and the local EKFs local; the centralized filters centralized (a fusion
# centre). Oracles and centralized filters are references: ranked apart, never the pick.
_RULES = {rule.study_label: rule for rule in rules.all_rules().values()}  # every gain rule's filter, by its label


def _designed(label: str) -> list[FilterEntry]:
    """The filter of the gain rule whose comparison label is ``label`` (none when no rule has it)."""
    rule = _RULES.pop(label, None)
    return [] if rule is None else [designed_consensus(label, rule.name, rule.study_description,
                                                       start_check=rule.fixed_multipliers)]


FILTER_REGISTRY = FilterRegistry([
    *_designed(TUNED),
    *_designed(PAPER_DESIGN),
    *particle_filters((PF_AWARE, _DESCRIPTION[PF_AWARE]), (PF_PLAIN, _DESCRIPTION[PF_PLAIN])),
    centralized_ekf(EKF_PLAIN, _DESCRIPTION[EKF_PLAIN]),
    local_ekfs(LOCAL, _DESCRIPTION[LOCAL]),
    *_designed(MSE),
    kcf(KCF, _DESCRIPTION[KCF]),
    hcmci(HCMCI, _DESCRIPTION[HCMCI]),
    *_designed(SCHEDULED),
    *_designed(RELAY),
    *_designed(FLOOD),
    *(entry for label in list(_RULES) for entry in _designed(label)),  # every other rule's (a package added), after
])
FILTERS = FILTER_REGISTRY.names()  # the built-in filters (a registered one joins FILTER_REGISTRY, not this tuple)
# every filter bootstraps its intervals from a stream of its own, numbered in this order first, then the registry's
_STREAM_ORDER = (LOCAL, MSE, KCF, HCMCI)
SWEEP_VALUES = (0.0, 0.1, 0.2, 0.3, 0.4)
CHUNK_SIZE = 10
#: Above this many rows N n a run costs more than batching saves: the runs are cut into CHUNKS_LARGE chunks instead
#: (a chunk per core on 2 and 4 cores; the numbers do not depend on the cut), e.g. IEEE 14's 14 nodes x 13 states.
CHUNK_ROWS = 100
CHUNKS_LARGE = 4


def chunk_size(sc, runs: int) -> int:
    """Runs per stored chunk: :data:`CHUNK_SIZE`, or a quarter of the runs for a model of more than
    :data:`CHUNK_ROWS` rows N n (a property of the model and the runs, never of the machine)."""
    if sc.network is not None and sc.network.n_nodes * sc.model.n_x > CHUNK_ROWS:
        return max(1, min(CHUNK_SIZE, -(-int(runs) // CHUNKS_LARGE)))
    return CHUNK_SIZE
JOINT_ROWS_DEFAULT = 200  # above, the default comparison leaves out an oracle carrying all nodes' joint covariance
#: Above this many rows N n the default comparison leaves out a design whose tables are designed offline along the
#: joint error covariance of all nodes (the scheduled design: about 0.2 s a step on a 20-cell field's 400 rows, 7 s on
#: a 64-cell field's 4096, a design a setting), and one whose nodes solve a convex problem at every step (the tuned
#: design: 36 s a run on the 64-cell field, a fifth of its comparison): an assumption, chosen (about a minute for a
#: design of 60 steps).
TABLES_ROWS_DEFAULT = 1000
#: Runs of the particle filters' pilot (:func:`particle_pilot`): runs of their own at the main setting, seeded from
#: the study's seed, before the study; a particle filter of the default set whose typical effective sample size there
#: is below :data:`filters.particle.DEGENERATE_ESS` is left out of it (an assumption, chosen: two runs cost about one
#: run of the study's particle filters; on IEEE 14 both filters carried 1.1-2.9 of 500 particles in every run of a
#: 10-run comparison).
PILOT_RUNS = 2
#: Above this many rows N n the default comparison runs its costliest filters a step at the main setting only, not at
#: the sweeps' settings: an oracle carrying the joint covariance (up to JOINT_ROWS_DEFAULT; on IEEE 14's 14 x 13 it
#: was a fifth of the study, its sweeps nine tenths of that) and a design whose nodes solve a convex problem at every
#: step (on a 20-pool canal, 20 x 20, half of the study)
SWEEP_ROWS = 100
SCENARIOS = ("indoor-robot", "target-range-bearing")
DEFAULT_RUNS = {"indoor-robot": 100, "target-range-bearing": 50, None: 50}

ASSUMPTIONS = (
    "comparison: the centralized filters receive every sensor's measurement over its own uplink, attacked with the "
    "model's uplink law (DoS = packet lost and known to be lost; FDI = the measurement falsified as h(x + xi) "
    "instead of h(x), with the model's injected signal xi); uplink i uses the diagonal draw [k, i, i] of the "
    "channel draws whose off-diagonal entries attack the consensus links, so both families face one realisation "
    "of one attack law (not the same channels: the architectures have different channels).",
    "comparison: the attack-aware particle filter's likelihood per received packet is (1 - q) p(y - h) + q N(y; h, "
    "R + C) with q = fdi/(1 - dos) of the sensor's uplink, p the sensor's own noise density (glint on "
    "target-range-bearing), R its covariance, and C = E[g(s)^2] sum_c a_c^2 h_c h_c^T (the signal xi_c = a_c g(s), "
    "h_c the sensor Jacobian's attacked columns at the prior mean): a moment-matched Gaussian of the falsification "
    "that treats the attacked components as independent, not its exact density.",
    "comparison: particle filters resample systematically at every step and report the weighted mean; M = "
    "particles for both.",
    f"comparison: a particle filter whose typical effective sample size after weighting (the median over runs of each "
    f"run's median over the steps) is below {DEGENERATE_ESS:g} particles is reported as degenerate: its weight sits on "
    "a handful of particles, its estimate follows them rather than the posterior, and its error is no measure of what "
    "a particle filter could reach on the model (an assumption, chosen: filters.particle.DEGENERATE_ESS). Before the "
    f"study each particle filter runs on a pilot of {PILOT_RUNS} runs of its own at the main setting (seeded from the "
    "study's seed); one degenerate there is left out of the default set, with its pilot's effective sample size in "
    "left_out (named in --filters it runs, and is reported degenerate where it is).",
    "comparison: consensus and local RMSE is over runs, steps 1..K and the nodes (each node's own estimate); "
    "centralized filters have one estimate. 95 % intervals are percentile bootstraps over runs. A run whose filter "
    "leaves finite numbers (or 1e12), or whose error leaves divergence_spread (default 100) times the prior's spread "
    "sqrt(tr P0), counts as diverged and is left out of the RMSE; a run that stays within that scale but "
    "far off is kept (compare the RMSE with the median run's).",
    "comparison: time per step = a filter's wall time on one run (all nodes, or the centre) / K at the main "
    "setting, averaged over runs, single-threaded; the designed consensus filters, KCF, HCMCI and the centralized "
    "EKF run every run of a chunk (chunk_size runs) at every setting in one batch per filter (filters.consensus_batch, "
    "filters.distributed, filters.ekf), the local EKFs every run of a chunk, and their time is the batch's divided "
    "by its runs (runs x settings); the tuned design's time includes its weight optimisation (every node and step); "
    "the two particle filters of every run and setting of a chunk are one NumPy batch (each run's draws from its own "
    "streams), each filter's time the batch's divided by its rows.",
    "comparison: the consensus designs use the scenario's design defaults (paper: sigma = beta = 0.1, C = 0.01 "
    "Phi, epsilon = 0.5/d_max, the scenario's U and V_i); on the indoor robot U = 0.01 I and V_i = 0.1 I (assumed: "
    "the paper gives none), on the range-bearing target U = 0 (its transition is linear) and V_i per component "
    "from the Hessians over the prior, as for a model file that declares none.",
    "comparison: messages per step count transmissions attempted (a message lost to DoS still counts): 2|E| "
    "directed links for the consensus filters and KCF, 2|E| L for HCMCI (L rounds), one uplink per sensor for the "
    "centralized ones, none for the local EKFs; delivered_per_step (KCF, HCMCI) counts those that arrived.",
    "comparison: KCF and HCMCI (filters.distributed) are the literature's distributed filters on the same network, "
    "channel realisations and measurements as the consensus EKF, the papers' algorithms in their EKF-linearised "
    "forms; the papers do not treat attacks: a DoS'ed packet is left out (KCF) or its Metropolis weight goes to the "
    "receiving node (HCMCI), one attack realisation holds for all L rounds of a step, and an FDI'd packet is the "
    "one its sender would send if the state were displaced by xi (estimate x_j + xi, measurement information "
    "u_j + U_j xi, HCMCI's information vectors q_j + Omega_j xi and dq_j + dOmega_j xi in every round).",
    "comparison: KCF's consensus gain is CDC 2009 Algorithm 1's gamma M_i with gamma = eps/(1 + ||M_i||_F); eps = "
    "0.5/d_max is an assumption (the papers give no value). HCMCI's measurement scaling omega = N (the paper's, "
    "the centralized filter as L grows; for small L it counts a measurement more than once and its covariance is "
    "overconfident), Metropolis weights 1/(1 + max(d_i, d_j)); L = hcmci_iterations (default 1: the same messages "
    "per step as the consensus EKF).",
    "comparison: every design runs at every setting, but for the study options --set tuned_in_sweeps=false, "
    "oracles_in_sweeps=false and tables_in_sweeps=false, which leave the tuned design, the mse oracle and the "
    "scheduled design (its tables designed offline per setting) out of the sweeps, and, above SWEEP_ROWS = 100 rows "
    "N n, the default set, which runs those three at the main setting only (the options set true run them at every "
    "setting); the sweep tables give each design's feasible_runs (runs meeting (28)-(29) "
    "throughout) and certified_runs (runs whose bound is certified: finite, steady and below the open-loop "
    "covariance, designer.verdict).",
    "comparison: the mse design's gains come from the joint linearised error covariance of all nodes (designer.joint:"
    " the realised DoS pattern, FDI as noise of second moment E[g^2] a a^T with probability fdi/(1 - dos) per "
    "received packet); its certificate is the bound (26)-(27) of the stacked error of all nodes for those gains "
    "(one sigma and one beta for the network, the cross-covariances propagated).",
    "comparison: the scheduled design's tables are designed offline for each setting's DoS/FDI probabilities along "
    "the nominal trajectory (rules.scheduled.design), never along the runs it is scored on; its packets carry the "
    "sender's measurement beside its prediction (the same messages per step as the other consensus filters and "
    "KCF; set --exchange predictions for the paper's packets).",
    "comparison: a paper design whose fixed sigma or beta breaks (28) or (29) at the first step (the same in every "
    "run: every node starts at the prior mean with Phi = P0) cannot start: it is not run at that setting and is "
    "reported as infeasible with the reason (no RMSE), and every other filter runs on the same runs; when sigma, "
    "beta or tau were given (--sigma, --beta, --tau or the model's DESIGN) the study refuses such a design before "
    "any run instead.",
    "comparison: each filter records its runtime, what it needs at run time: local (a node's own measurement and its "
    "neighbours' messages: the paper and tuned designs, KCF, HCMCI, the local EKFs), global (the mse design, whose "
    "gains need the network's joint state: an oracle) or centralized (a fusion centre receiving every uplink); the "
    "global and centralized filters are references of what the structure or a fusion centre could reach, ranked "
    "apart and never recommended.",
    "comparison: the local EKF of a node is the consensus filter of that node with no neighbours and sigma = "
    "beta = 0, U = V = 0 (exactly the EKF on the node's own sensor); a node that cannot observe the state alone "
    "drifts.",
)

TEXT = StudyText(
    title="Every filter family of the project side by side under the same attacks",
    paper="none: no paper makes this comparison (seed 003 gives the consensus filter alone)",
    summary=(
        "The filter families of this project run on the same scenario, the same runs and the same attack "
        "law: distributed consensus Kalman filters, where every sensor node estimates the state from its own "
        "sensor and its neighbours' messages, against an EKF at every node that uses no network at all, and "
        "against centralized filters (particle filters and a plain extended Kalman filter) that receive every "
        "sensor's measurement at one fusion centre over attacked uplinks, and against two distributed filters of the "
        "literature, Olfati-Saber's Kalman consensus filter (KCF) and Battistelli and Chisci's hybrid consensus on "
        "measurements and information (HCMCI). The question: which family gives the "
        "best accuracy for its computing cost and its number of messages, and how does each degrade as the "
        "attacks become more frequent?"),
    filters={e.name: e.description for e in FILTER_REGISTRY},
    attacks=(
        "Every channel suffers denial of service (the message is lost, and the receiver knows it) with "
        "probability `dos_prob`, and false-data injection (a bounded signal of amplitude `attack_amplitude` "
        "added to what is sent) with probability `fdi_prob` (on a model file: its ATTACKS). The sweeps raise one "
        "probability with the other fixed, on the same random draws."),
    attack_params=("dos_prob", "fdi_prob", "attack_amplitude"),
    accuracy=(("rmse_position", "position RMSE"), ("rmse_position_median_run", "median-run position RMSE"),
              ("rmse", "state RMSE"), ("rmse_median_run", "median-run state RMSE"),
              ("rmse_region", "region RMSE (each node on its region)"),
              ("rmse_region_median_run", "median-run region RMSE")),
    figures={
        "fig_rmse_*.png": "The error of every filter at each time step on scenario {}, over the runs at the main "
                          "attack setting (log scale).",
        "fig_sweeps_*.png": "How each filter degrades on scenario {} as the DoS probability (left, FDI fixed) and the "
                            "FDI probability (right, DoS fixed) grow, with 95 % intervals (shaded; log scale).",
        "fig_trajectory_*.png": "Run 1 on scenario {}: the truth and each filter's estimate (node 1's for the "
                                "networked filters); a filter that diverged in that run is left out.",
    },
)


#: What a comparison's error metric measures, in words (the state's, without a word here).
_ERROR_WORDS = {"rmse_position": "position", "rmse_region": "region"}


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", name).strip("-") or "scenario"


def _uniform(sc: Scenario) -> tuple[float, float] | None:
    """``(dos, fdi)`` when every channel and uplink has the same probabilities (None otherwise)."""
    att, net = sc.resolved_attacks, sc.network
    adj = net.adjacency
    vals = []
    for ch, up in ((net.dos_prob, att.uplink_dos), (net.fdi_prob, att.uplink_fdi)):
        v = np.concatenate([ch[adj], up])
        if not np.all(v == v[0]):
            return None
        vals.append(float(v[0]))
    return vals[0], vals[1]


def _settings(sc: Scenario, values: Sequence[float]) -> list[tuple]:
    """The main setting first, then the DoS sweep (FDI as declared) and the FDI sweep (DoS as declared).

    A setting is ``(dos, fdi)`` with ``None`` meaning "as declared".  With uniform
    probabilities the main setting is ``(dos, fdi)`` itself and a sweep point equal to it
    is not repeated.  A model that declares neither an injected signal nor its bound has no FDI
    to sweep: its FDI sweep keeps the points without FDI.
    """
    main = _uniform(sc)
    fdi_values = [v for v in values if v == 0 or sc.attacks.signal is not None or sc.attacks.delta is not None]
    if main is None:
        return [(None, None)] + [(v, None) for v in values] + [(None, v) for v in fdi_values]
    dos, fdi = main
    out = [(dos, fdi)]
    for v in values:
        for s in ((v, fdi), (dos, v)):
            if s not in out and s[0] + s[1] <= 1.0 and (s[1] == fdi or s[1] in fdi_values):
                out.append(s)
    return out


def realise(scs: Sequence[Scenario], seeds, *, particles: int | None, iterations: int, run_ids: Sequence[int],
            truth: np.ndarray | None = None, covariances: bool = True, variances: bool = False) -> Batch:
    """The comparison's realisations of the runs ``seeds`` at the settings ``scs`` (the main one first), as the
    :class:`studies.filter_registry.Batch` every filter runs on: run ``r`` draws its truth and measurements, the
    channel draws that every setting turns into its attacks (common random numbers) and its particle filters' seed
    from ``seeds[r].spawn(3)``.  ``truth`` (runs, K + 1, n_x), when given, receives each run's true states;
    ``covariances``, ``variances``: the batch's (:class:`studies.filter_registry.Batch`)."""
    sc = scs[0]
    K, n = sc.steps, sc.network.n_nodes
    trajs, draws, ys, fss = [], [], [[] for _ in scs], []
    for a, seq in enumerate(seeds):  # the realisations first: every filter then faces the same ones
        ts, cs, fs = seq.spawn(3)
        traj = sc.simulate(np.random.default_rng(ts), K)
        if truth is not None:
            truth[a] = traj.x
        u, s = channel_draws(K, n, np.random.default_rng(cs))
        for j, scj in enumerate(scs):
            ys[j].append(uplinks_received(scj, u, s, traj.x, traj.z))
        draws.append((u, s))
        trajs.append(traj)
        fss.append(fs)
    # each setting's attacks of the runs on the channels alone (a dense pattern: N² x n_x numbers a step and run)
    edges = tuple(EdgeAttacks.from_draws(scj.network, draws, sc.model.n_x, scj.resolved_attacks.signal) for scj in scs)
    return Batch(tuple(scs), np.stack([t.z for t in trajs]),
                 None if trajs[0].inputs is None else np.stack([t.inputs for t in trajs]), edges,
                 received=tuple(map(tuple, ys)), particle_seeds=tuple(fss), particles=particles,
                 iterations=iterations, run_ids=tuple(run_ids), covariances=covariances, variances=variances)


def _runs(run_ids, seeds, *, ref, settings: Sequence[tuple], particles: int, main_only: Sequence[str] = (),
          options: DesignOptions, hcmci_iterations: int = HCMCI_ITERATIONS,
          divergence_spread: float = DIVERGENCE_SPREAD, filters: Sequence[str] | None = None) -> dict:
    """Task of the runner: every filter of :data:`FILTER_REGISTRY` at every setting on the runs ``run_ids``
    (``filters``: the names the study planned, checked against this process's registry; those in ``main_only`` at
    the main setting only).

    Each filter runs every run of the chunk at every setting as one batch (the designed consensus
    filters: one per group of equal designs, a filter that uses no channel once), so that a step costs
    one NumPy call per operation for all of them; the batched filters give each run the numbers of the
    per-run filters (filters.consensus_batch, filters.distributed, filters.ekf, and
    ``run_sir``'s blocks: run ``a``'s particle filters draw from its own streams as three separate
    filters would, the two at the main setting alone and the sweep's rows together).  Every
    Generator comes from the run's own seed, so a run's numbers depend on it only.
    """
    scs = _setting_scenarios(ref, settings)
    sc = scs[0]
    m, K = sc.model, sc.steps
    if filters is not None and any(f not in FILTER_REGISTRY for f in filters):
        raise InputError(f"the comparison was planned with the filters {list(filters)} but this process registers "
                         f"{list(FILTER_REGISTRY.names())}: a filter registered in a script is known to that process "
                         "only; run the study in it (without --workers or --dask)")
    entries = _entries(filters)
    # per setting: each needed gain rule's design, and the filters that cannot start there (not run: their arrays
    # stay NaN and the summary says why)
    designs = _designs(scs, options, main_only, entries)
    cannot = _cannot_start(scs, options, designs, entries)
    S, F, R = len(settings), len(entries), len(run_ids)
    idx = list(m.position_index) or list(range(m.n_x))
    err2 = np.full((R, S, F, K), np.nan)
    secs = np.full((R, S, F), np.nan)
    feasible = np.full((R, S, F), np.nan)
    verdict = np.full((R, S, F), np.nan)  # index into designer.verdict.VERDICTS of each run's bound
    bounded = np.full((R, S, F), np.nan)  # 1 where that bound is bounded (designer.verdict.Verdict.bounded)
    delivered = np.full((R, S, F), np.nan)  # packets delivered per step (KCF, HCMCI), mean over the steps
    ess = np.full((R, S, F), np.nan)  # a particle filter's effective sample size after weighting, median over steps
    est = np.full((R, F, K + 1, m.n_x), np.nan)
    truth = np.empty((R, K + 1, m.n_x))

    limit = divergence_limit(m.prior.cov, divergence_spread)

    def score(a, j, f, xs, ok, held=True):
        if ok and first_divergence(np.where(held, truth[a][:, None] - xs, 0.0), limit) is not None:
            ok = False  # finite, but off the problem's scale (on what each node carries): diverged
        if ok:
            e = truth[a, 1:, None] - xs[1:]  # (K, nodes or 1, n)
            # with regions each node on its region's states (a centralized filter's one estimate on each node's)
            e2 = (e[..., idx] ** 2).sum(-1) if sc.regions is None else region_error2(e, sc.regions)
            err2[a, j, f] = e2.mean(axis=1)
            if j == 0:
                est[a, f] = xs[:, 0]

    # the filters that are not designed are scored on their estimates alone (no covariance over the steps), the designed
    # ones on their estimates and their bounds' traces (their diagonals over the steps)
    batch = realise(scs, seeds, particles=particles, iterations=hcmci_iterations, run_ids=run_ids, truth=truth,
                    covariances=False, variances=True)

    for f, e in enumerate(entries):
        if not e.attacked:  # uses no channel: the same numbers at every setting, run once
            groups = [[0]]
        elif e.mode is None:
            groups = [list(range(S))]
        else:  # one batch per group of settings with equal designs
            groups = _alike([j for j in range(S) if e.mode in designs[j] and cannot[j].get(e.name) is None],
                            lambda j: designs[j][e.mode])
        for js in _heap_sized(groups, R, sc.network.n_nodes, m.n_x):
            t0 = time.perf_counter()
            with phase(e.name):
                res = e.run(batch, js, None if e.mode is None else e.design_for(designs[js[0]][e.mode], m))
            per_row = (np.full(res.runs, (time.perf_counter() - t0) / res.runs) if res.seconds is None
                       else res.seconds)
            rows = [(j, a) for j in js for a in range(R)]
            held = True if res.carried is None else Carried(res.carried, m.n_x).held  # nodes carrying their regions
            for row, ((j, a), dv) in enumerate(zip(rows, res.diverged)):
                secs[a, j, f] = per_row[row]
                if e.counts_delivered:
                    delivered[a, j, f] = res.delivered[row].mean()
                if res.ess is not None:
                    ess[a, j, f] = np.median(res.ess[row])
                for jj in (range(S) if not e.attacked else (j,)):
                    score(a, jj, f, res.x[row], dv is None, held)
                if e.designed:
                    feasible[a, j, f] = float(dv is None and not any(v["condition"] in HARD_CONDITIONS[:2]
                                                                       for v in res.violations[row]))
            if not e.attacked:
                secs[:, :, f] = secs[:, :1, f]
            if e.designed:
                design = e.design_for(designs[js[0]][e.mode], m)
                for (j, a), v in zip(rows, bound_verdicts(sc, res.variance(), res.valid,
                                                          [feasible[a, j, f] == 1 for j, a in rows], design,
                                                          res.carried)):
                    verdict[a, j, f], bounded[a, j, f] = VERDICTS.index(v.verdict), float(v.bounded)
    return {"err2": err2, "seconds": secs, "feasible": feasible, "verdict": verdict, "bounded": bounded,
            "delivered": delivered, "ess": ess, "estimate": est, "truth": truth}


def left_out(sc: Scenario) -> dict[str, str]:
    """The filters the comparison leaves out of its default set on ``sc`` (no ``--filters``), each with why: a gain
    rule's filter that carries the joint error covariance of all nodes (an oracle, a reference: its cost a step
    grows as (N n)³) once N n exceeds :data:`JOINT_ROWS_DEFAULT` rows, and one whose tables are designed offline
    along the joint error covariance of all nodes (``GainRule.offline_tables``: its design's cost a step grows as
    (N n)³ too) or whose nodes solve a convex problem at every step (``GainRule.solves_online``) once N n exceeds
    :data:`TABLES_ROWS_DEFAULT`.  Named in ``--filters``, it runs."""
    rows = int(sc.network.n_nodes) * int(sc.model.n_x)
    out = {}
    if rows > JOINT_ROWS_DEFAULT:
        out.update({e.name: f"it carries the joint error covariance of all nodes, N n = {rows} rows (more than "
                            f"{JOINT_ROWS_DEFAULT}), at a cost that grows as (N n)^3 a step and run; name it in "
                            "--filters to run it"
                    for e in FILTER_REGISTRY if e.mode is not None and rules.get(e.mode).joint_covariance})
    if rows > TABLES_ROWS_DEFAULT:
        out.update({e.name: f"its tables are designed offline along the joint error covariance of all nodes, N n = "
                            f"{rows} rows (more than {TABLES_ROWS_DEFAULT}), at a cost that grows as (N n)^3 a step "
                            "(on a 64-cell field, 4096 rows: about 7 s a step, 7 minutes for 60 steps); name it in "
                            "--filters to run it"
                    for e in FILTER_REGISTRY if e.mode is not None and rules.get(e.mode).offline_tables})
        out.update({e.name: f"its nodes solve a convex problem at every step and run, N n = {rows} rows (more than "
                            f"{TABLES_ROWS_DEFAULT}; on a 64-cell field, 4096 rows: about 36 s a run at the main "
                            "setting alone); name it in --filters to run it"
                    for e in FILTER_REGISTRY if e.mode is not None and rules.get(e.mode).solves_online})
    return out


def sweeps_left_out(sc: Scenario, so: StudyOptions) -> dict[str, str]:
    """The filters the comparison runs at its main setting only, not at the sweeps' settings, each with why: a gain
    rule's filter that carries the joint error covariance of all nodes (an oracle), one whose nodes solve a
    convex problem at every step (the costliest a step of each kind, ``GainRule.joint_covariance`` and
    ``GainRule.solves_online``) and one whose tables are designed offline for every setting (the costliest design,
    ``GainRule.offline_tables``), when their study option (``oracles_in_sweeps``, ``tuned_in_sweeps``,
    ``tables_in_sweeps``) is false, or is left out (None) and the default set (no ``--filters``) runs on more than
    :data:`SWEEP_ROWS` rows N n."""
    # given: the filters run (the default set less what it left out, or --filters); no particle filter is a design's
    given, left = _chosen(sc, so, pilot=False)
    named = chosen_filters(so["filters"]) is not None
    rows = int(sc.network.n_nodes) * int(sc.model.n_x)
    out = {}
    for option, kind, cost in (("oracles_in_sweeps", "joint_covariance", "it carries the joint error covariance of "
                                "all nodes, at a cost that grows as (N n)^3 a step and run"),
                               ("tuned_in_sweeps", "solves_online", "each node solves a convex problem at every step "
                                "and run, the costliest of the filters a node runs"),
                               ("tables_in_sweeps", "offline_tables", "its tables are designed offline for each "
                                "setting, with its certificate: a recursion of the joint error covariance of all nodes "
                                "over the horizon, (N n)^3 a step, at every setting")):
        wanted = so[option]
        if wanted is True or (wanted is None and (named or rows <= SWEEP_ROWS)):
            continue
        why = (f"{cost}; N n = {rows} rows, more than {SWEEP_ROWS}: --set {option}=true runs it at every setting"
               if wanted is None else f"the study option {option} is false")
        out.update({e.name: why for e in _entries(given) if e.mode is not None and e.name not in left
                    and getattr(rules.get(e.mode), kind)})
    return out


def _chosen(sc: Scenario, so: StudyOptions, pilot: bool = True) -> tuple[tuple[str, ...] | None, dict[str, str]]:
    """The filters the study runs on ``sc`` (None: every one) and those its default set leaves out, with why: the
    names ``--filters`` gives (:func:`chosen_filters`; nothing left out), else every filter but :func:`left_out` and
    the particle filters that are degenerate on their pilot runs (:func:`particle_pilot`; without ``pilot``, before
    the study computes, as if none were: what the memory estimate counts)."""
    given = chosen_filters(so["filters"])
    out = {}
    if given is None:
        out = left_out(sc)
        typical = particle_pilot(sc, so) if so.particles and pilot else {}
        out.update({name: f"its weights were degenerate on its pilot's {PILOT_RUNS} runs at the main setting "
                          f"(runs of their own): typical effective sample size {ess:.3g} of {so.particles} particles, "
                          f"below {DEGENERATE_ESS:g}, so its estimate would follow a handful of particles and its "
                          "error measure them, not what a particle filter can reach on this model (a bootstrap "
                          "proposal's weights collapse as the measurements grow informative about many states); "
                          "name it in --filters to run it, or give more --particles"
                    for name, ess in typical.items() if ess < DEGENERATE_ESS})
    if not out:
        return given, {}
    return tuple(n for n in FILTER_REGISTRY.names() if n not in out), out


_PILOTS: dict = {}  # particle_pilot's results in this process, by scenario content, particles and seed


def particle_pilot(sc: Scenario, so: StudyOptions) -> dict[str, float]:
    """The typical effective sample size after weighting (:func:`filters.particle.degenerate`: the median over runs of
    each run's median over the steps) of every particle filter of the registry on ``sc``'s main setting, over
    :data:`PILOT_RUNS` runs of their own seeded from the study's seed (``SeedSequence(seed, spawn_key=(2**31 + 1,
    r))``), at the study's particles: what :func:`_chosen` leaves a degenerate filter out of the default set by (NaN
    where it diverged in every pilot run: no weights to judge, so it stays).  Computed once per process for a
    scenario's content, particles and seed."""
    entries = [e for e in FILTER_REGISTRY if e.particles]
    key = (sc.digest, int(so.particles), int(so.seed), tuple(e.name for e in entries))
    if key not in _PILOTS:
        out = {}
        if entries:
            main = _setting_scenarios(reference(sc), _settings(sc, []))[:1]
            seeds = [np.random.SeedSequence(so.seed, spawn_key=(2**31 + 1, r)) for r in range(PILOT_RUNS)]
            batch = realise(main, seeds, particles=int(so.particles), iterations=int(so["hcmci_iterations"]),
                            run_ids=range(PILOT_RUNS), covariances=False)
            for e in entries:
                with phase(f"pilot of {e.name}"):
                    res = e.run(batch, [0], None)
                weights = degenerate(np.median(res.ess, axis=-1))
                out[e.name] = np.nan if weights is None else weights[0]
        _PILOTS[key] = out
    return _PILOTS[key]


def _entries(filters: Sequence[str] | None) -> list:
    """The registry's entries the study runs, in the registry's order: ``filters`` (names) or every one (None)."""
    return [e for e in FILTER_REGISTRY if filters is None or e.name in filters]


def chosen_filters(value) -> tuple[str, ...] | None:
    """The study option ``filters`` checked: None (every filter), or the registry's names of the filters given (a
    comma-separated string or a list of names, each a filter's name, short name or the start of exactly one short
    name: :func:`studies.recorded.find_filter`), in the registry's order."""
    from .recorded import find_filter

    if value is None:
        return None
    if isinstance(value, str):
        value = [v for v in value.split(",")]
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
        raise InputError(f"filters must be filter names, comma-separated or a list, got {value!r}")
    names = [v.strip() for v in value if v.strip()]
    if not names:
        raise InputError("filters must name at least one filter (leave it out to run every filter)")
    picked = {find_filter(FILTER_REGISTRY, v).name for v in names}
    return tuple(n for n in FILTER_REGISTRY.names() if n in picked)


def _needed(scs: Sequence[Scenario], main_only: Sequence[str] = (), entries=None) -> list[tuple[int, str]]:
    """``(setting, gain rule)`` of every design the filters (``entries``, default every one) need at the settings of
    ``scs``, once each (the filters named in ``main_only`` at the main setting only: :func:`sweeps_left_out`)."""
    out: dict = {}
    for e in (FILTER_REGISTRY if entries is None else entries):
        for j in range(len(scs)):
            if e.mode is not None and (j == 0 or e.name not in main_only):
                out.setdefault((j, e.mode), None)
    return list(out)


def _designs(scs: Sequence[Scenario], options: DesignOptions, main_only: Sequence[str] = (), entries=None
             ) -> list[dict]:
    """Per setting of ``scs``: the design of every gain rule its filters need (:func:`_needed`), by rule."""
    designs: list[dict] = [{} for _ in scs]
    for j, mode in _needed(scs, main_only, entries):
        with phase(f"design {mode}, setting {j + 1}/{len(scs)}"):
            designs[j][mode] = consensus_design(scs[j], as_mode(options, mode))
    return designs


def _design_first(ref, settings: Sequence[tuple], options: DesignOptions, main_only: Sequence[str] = (),
                  filters: Sequence[str] | None = None) -> None:
    """The plan's step in the parent process: every setting's designs once, so that the offline tables they keep
    (:func:`studies.consensus_design.with_tables`, remembered per process) are computed once and inherited by the
    forked workers instead of once in each; the tables of the settings side by side on the usable cores
    (:func:`studies.consensus_design.prefetch_tables`: a sweep's scheduled designs, one per setting)."""
    scs, entries = _setting_scenarios(ref, settings), _entries(filters)
    prefetch_tables([(scs[j], as_mode(options, mode)) for j, mode in _needed(scs, main_only, entries)])
    _designs(scs, options, main_only, entries)


def _setting_scenarios(ref, settings: Sequence[tuple]) -> list[Scenario]:
    """The scenario of every setting ``(dos, fdi)``, built from the reference ``ref`` (the main setting first)."""
    base = ref.build()
    return [base.with_attacks(dos=d, fdi=f) for d, f in settings]


def _verdict_counts(codes: np.ndarray) -> dict[str, int]:
    """How many runs' bounds have each verdict (``codes``: indices into VERDICTS, NaN where not run)."""
    return count_verdicts(VERDICTS[int(c)] for c in codes[~np.isnan(codes)])


def _cannot_start(scs: Sequence[Scenario], options: DesignOptions, designs: list[dict] | None = None,
                  entries=None) -> list[dict]:
    """Per setting: ``{name: why}`` for every filter whose design cannot start there (:func:`check_first_step`; None:
    it can), for the entries (default every one) that declare ``start_check`` (``designs``: the settings' designs by
    gain rule, made when not given)."""
    out = []
    for j, s in enumerate(scs):
        row = {}
        for e in (FILTER_REGISTRY if entries is None else entries):
            if e.start_check:
                design = (designs[j][e.mode] if designs is not None and e.mode in designs[j]
                          else consensus_design(s, as_mode(options, e.mode)))
                row[e.name] = check_first_step(s, design, e.name)
        out.append(row)
    return out


def _heap_sized(groups: list[list], runs: int, nodes: int, n_x: int) -> list[list]:
    """``groups`` of settings, each split so that a batch of its settings' ``runs`` rows keeps a stack of the nodes'
    ``n_x`` x ``n_x`` matrices within half glibc's largest heap block (:data:`designer.cores.ALLOCATOR`): above it
    every temporary is a fresh mapping whose pages the kernel faults in and zeroes (HCMCI on the 64-cell field, 3 runs
    at 10 settings: one batch of 30 rows 72.9 s, 29 s of it in the kernel; ten batches of 3 rows 48.9 s).  A row's
    numbers do not depend on its batch."""
    per_setting = runs * nodes * n_x * n_x * 8
    k = max(1, ALLOCATOR["mmap_threshold"] // 2 // max(per_setting, 1))
    return [g[i:i + k] for g in groups for i in range(0, len(g), k)]


def _alike(items: list, key) -> list[list]:
    """``items`` in groups of equal ``key(item)`` (arrays, tuples and dataclasses compared by value), in order."""
    groups: list[list] = []
    for it in items:
        home = next((g for g in groups if _same(key(g[0]), key(it))), None)
        if home is None:
            groups.append([it])
        else:
            home.append(it)
    return groups


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.shape(a) == np.shape(b) and np.array_equal(a, b)
    if dataclasses.is_dataclass(a) and type(a) is type(b):
        return all(_same(getattr(a, fl.name), getattr(b, fl.name)) for fl in dataclasses.fields(a))
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(map(_same, a, b))
    return type(a) is type(b) and a == b


def _accepts(sc: Scenario) -> str | None:
    if sc.network is None:
        return "it has no sensor network (a model file defines NETWORK, one node per sensor)"
    return None


def _uses(sc: Scenario, so: StudyOptions) -> tuple[tuple[str, ...], bool, tuple[str, ...]]:
    """What the chosen filters need on ``sc`` (``Study.uses``): the gain rules designed, whether a particle filter
    runs, and the gain rules whose filters run at the main setting only (:func:`sweeps_left_out`)."""
    entries = _entries(_chosen(sc, so, pilot=False)[0])  # before the study computes: its particle filters counted
    main_only = sweeps_left_out(sc, so)
    return (tuple(dict.fromkeys(e.mode for e in entries if e.mode is not None)), any(e.particles for e in entries),
            tuple(dict.fromkeys(e.mode for e in entries if e.mode is not None and e.name in main_only)))


def _check(so: StudyOptions) -> None:
    if so.design.mode is not None:
        raise InputError("option --mode does not apply to study 'comparison' (it runs the paper and the tuned "
                         "designs side by side)")
    for v in np.atleast_1d(so["sweep_values"]):
        check_probability("sweep_values", v)
    check_int("hcmci_iterations", so["hcmci_iterations"], 1)
    for name in ("tuned_in_sweeps", "oracles_in_sweeps", "tables_in_sweeps"):
        if not (so[name] is None or isinstance(so[name], bool)):
            raise InputError(f"{name} must be true or false (or left out: by the network's size N n), got "
                             f"{so[name]!r}")
    chosen_filters(so["filters"])


def _plan(sc: Scenario, so: StudyOptions) -> Plan:
    values = [float(v) for v in np.atleast_1d(so["sweep_values"])]
    settings = _settings(sc, values)
    # a paper design that cannot start is reported as infeasible; one whose sigma, beta or tau was given is refused
    for e in _entries(_chosen(sc, so, pilot=False)[0]):
        if e.start_check:
            check_first_step(sc, consensus_design(sc, as_mode(so.design, e.mode)), e.name, so.design)
    filters = _chosen(sc, so)[0]  # then the particle filters' pilot
    ref = reference(sc)
    main_only = tuple(sweeps_left_out(sc, so))
    task = functools.partial(_runs, ref=ref, settings=settings, particles=so.particles, main_only=main_only,
                             options=so.design,
                             hcmci_iterations=int(so["hcmci_iterations"]),
                             divergence_spread=check_positive("divergence_spread", so["divergence_spread"]).item(),
                             filters=FILTER_REGISTRY.names() if filters is None else filters)
    config = {"study": "comparison", "scenario": sc.name, "params": dict(ref.params),
              "attacks": sc.attacks.describe(), "settings": settings,
              "particles": so.particles, "main_only": list(main_only),
              "hcmci_iterations": int(so["hcmci_iterations"]), "divergence_spread": float(so["divergence_spread"]),
              "options": so.design.as_dict(),
              "filters": list(FILTER_REGISTRY.names() if filters is None else filters)}
    return Plan(task, f"comparison-{_slug(sc.name)}", config,
                before=functools.partial(_design_first, ref, settings, so.design, main_only, filters))


def _summarise(sc: Scenario, mc, so: StudyOptions) -> dict:
    """One scenario's block of results from the runner's arrays."""
    A, net, K = mc.arrays, sc.network, sc.steps
    values = [float(v) for v in np.atleast_1d(so["sweep_values"])]
    main = _uniform(sc)
    settings = _settings(sc, values)
    # per setting: why a filter's design cannot start there (None: it ran), as _runs decided
    chosen, out = _chosen(sc, so)
    main_only = sweeps_left_out(sc, so)
    entries = _entries(chosen)
    cannot = _cannot_start([sc.with_attacks(dos=d, fdi=f) for d, f in settings], so.design, entries=entries)
    R = int(A["err2"].shape[0])
    key = "rmse_region" if sc.regions is not None else "rmse_position" if sc.model.position_index else "rmse"
    # every filter bootstraps its intervals from a stream of its own, so that no filter's interval depends on another
    # (on how many of its runs diverged, or on whether it ran at all)
    order = ([n for n in _STREAM_ORDER if n in FILTER_REGISTRY]  # the registry's: a subset changes no filter's stream
             + [e.name for e in FILTER_REGISTRY if e.name not in _STREAM_ORDER])
    own = {name: np.random.default_rng(np.random.SeedSequence(so.seed, spawn_key=(2**31, c)))
           for c, name in enumerate(order, start=1)}
    L = int(so["hcmci_iterations"])
    filters = {}
    for f, e in enumerate(entries):
        name = e.name
        reason = cannot[0].get(name)
        met = (_metrics(A["err2"][:, 0, f], own[name], key) if reason is None else
               _not_run(reason, key))
        messages = e.messages_per_step(net, L, so.design)
        met.update({
            "family": e.family, "runtime": e.runtime, "description": e.description,
            "time_per_step_s": None if reason is not None else float(np.nanmean(A["seconds"][:, 0, f]) / K),
            "communications": messages, "messages_per_step": messages,
            "particles": so.particles if e.particles else None,
        })
        if e.designed:
            met["feasible_runs"] = int(np.nansum(A["feasible"][:, 0, f]))
            met["verdicts"] = (_verdict_counts(A["verdict"][:, 0, f]) if reason is None else
                               count_verdicts(["infeasible"] * R))  # cannot start: infeasible in every run
            met["bounded_runs"] = int(np.nansum(A["bounded"][:, 0, f])) if reason is None else 0
        if e.counts_delivered:
            met["delivered_per_step"] = float(np.nanmean(A["delivered"][:, 0, f]))
        weights = degenerate(A["ess"][:, 0, f]) if reason is None else None
        if weights is not None:  # a filter with weights: how many particles carry them
            met["weights_ess"], met["degenerate"] = weights
        if e.rounds:
            met["consensus_iterations"] = L
        filters[name] = met
    ran = {e.name: f for f, e in enumerate(entries) if cannot[0].get(e.name) is None}
    for name, met in filters.items():  # the nodes alone are the floor a network must beat, on the same runs
        if name == LOCAL or met["runtime"] not in DEPLOYABLE or name not in ran or LOCAL not in ran:
            met.update(compared_with_local())
            continue
        met.update(compared_with_local(per_run_mse(A["err2"][:, 0, ran[name]]),
                                       per_run_mse(A["err2"][:, 0, ran[LOCAL]]),
                                       np.random.default_rng(np.random.SeedSequence(  # a stream of its own
                                           so.seed, spawn_key=(2**31 + 1, order.index(name) + 1)))))
    sweeps: dict = {"dos_prob": {}, "fdi_prob": {}}
    for skey, axis in (("dos_prob", 0), ("fdi_prob", 1)):
        if main is None:
            pts = [(st[axis], j) for j, st in enumerate(settings) if st[axis] is not None and st[1 - axis] is None]
        else:
            pts = sorted((st[axis], j) for j, st in enumerate(settings) if st[1 - axis] == main[1 - axis])
        for val, j in pts:
            row = {}
            for f, e in enumerate(entries):
                name = e.name
                if cannot[j].get(name) is not None:
                    row[name] = _not_run(cannot[j][name], key, curve=False)
                    continue
                if np.all(np.isnan(A["seconds"][:, j, f])):
                    continue  # not run at this setting
                if not e.attacked:  # nothing attacked: the same numbers at every setting
                    row[name] = {k: filters[name][k] for k in (key, f"{key}_ci95", f"{key}_median_run",
                                                               "diverged_runs")}
                    continue
                mm = _metrics(A["err2"][:, j, f], own[name], key, curve=False)
                row[name] = {k: mm[k] for k in (key, f"{key}_ci95", f"{key}_median_run", "diverged_runs")}
                weights = degenerate(A["ess"][:, j, f])
                if weights is not None:  # a filter with weights: how many particles carry them at this setting
                    row[name]["weights_ess"], row[name]["degenerate"] = weights
                if e.designed:  # runs whose design held (28)-(29) throughout: certified at this setting
                    row[name]["feasible_runs"] = int(np.nansum(A["feasible"][:, j, f]))
                    row[name]["certified_runs"] = _verdict_counts(A["verdict"][:, j, f])["certified"]
            sweeps[skey][f"{val:g}"] = row
    att = sc.resolved_attacks
    sig = att.signal
    return {
        "scenario": sc.name, "runs": R, "steps": int(K), "nodes": int(net.n_nodes),
        "links": [list(e) for e in net.edges], "filters": filters, "sweeps": sweeps,
        "error": {"metric": key, "components": [sc.model.state_names[c] for c in
                                                (sc.model.position_index or range(sc.model.n_x))]}
        if sc.regions is None else
        {"metric": key, "components": list(sc.model.state_names),
         "regions": describe_regions(sc.regions, sc.model.state_names)},
        "attacks": {"dos_prob": None if main is None else main[0], "fdi_prob": None if main is None else main[1],
                    "amplitude": sig.amplitude[0] if len(set(sig.amplitude)) == 1 else list(sig.amplitude),
                    "components": [sc.model.state_names[c] for c in sig.components], "law": sig.law,
                    "delta": att.delta, "declared": att.describe(sc.model.state_names), "sweep_values": values},
        "recommendation": _recommend(filters, key), "params": dict(sc.params), "runner": mc.describe(),
        "left_out": dict(out), "sweeps_left_out": main_only,
        "assumptions": list(sc.assumptions) + [f"comparison: left out of the default filters on {sc.name}: {name} "
                                               f"({why})" for name, why in out.items()]
        + [f"comparison: run at the main setting only on {sc.name}, not in the sweeps: {name} ({why})"
           for name, why in main_only.items()],
    }


def _combine(blocks: dict) -> dict:
    """The scenarios' blocks: ``filters`` and ``sweeps`` keyed ``"<scenario>: <filter>"`` (just ``"<filter>"``
    when there is one scenario), and ``by_scenario`` with each block."""
    first = next(iter(blocks.values()))
    label = (lambda sc, n: n) if len(blocks) == 1 else (lambda sc, n: f"{sc}: {n}")  # noqa: E731
    sweeps: dict = {"dos_prob": {}, "fdi_prob": {}}
    for sc_name, b in blocks.items():
        for key in sweeps:
            for val, row in b["sweeps"][key].items():
                sweeps[key].setdefault(val, {}).update({label(sc_name, n): v for n, v in row.items()})
    return {
        "scenario": ", ".join(blocks), "runs": first["runs"], "steps": first["steps"],
        "assumptions": list(dict.fromkeys(a for b in blocks.values() for a in b["assumptions"]))
        + list(DESIGN_ASSUMPTIONS) + list(VERDICT_ASSUMPTIONS) + list(ASSUMPTIONS),
        "runner": {sc: b["runner"] for sc, b in blocks.items()},
        "filters": {label(sc_name, n): {**f, "scenario": sc_name}
                    for sc_name, b in blocks.items() for n, f in b["filters"].items()},
        "sweeps": sweeps,
        "paper": {"source": None, "numbers": None,
                  "note": "no paper compares these filter families; seed 003 gives the consensus filter alone"},
        "left_out": {label(sc_name, n): why for sc_name, b in blocks.items() for n, why in b["left_out"].items()},
        "sweeps_left_out": {label(sc_name, n): why for sc_name, b in blocks.items()
                            for n, why in b["sweeps_left_out"].items()},
        "by_scenario": {k: {kk: vv for kk, vv in b.items() if kk != "assumptions"} for k, b in blocks.items()},
        "recommendation": {sc: b["recommendation"] for sc, b in blocks.items()},
        "params": {sc: b["params"] for sc, b in blocks.items()},
    }


def _metrics(err2: np.ndarray, rng: np.random.Generator, key: str, curve: bool = True) -> dict:
    """RMSE over runs and steps of the runs that did not diverge, bootstrap interval, per-step curve."""
    ok = ~np.isnan(err2).any(axis=1)
    e = err2[ok]
    out = {"diverged_runs": int((~ok).sum())}
    if not len(e):
        return {**out, key: None, f"{key}_ci95": None, f"{key}_curve": None, f"{key}_median_run": None}
    per_run = e.mean(axis=1)
    out.update({key: float(np.sqrt(per_run.mean())), f"{key}_ci95": bootstrap_rmse_ci(per_run, rng),
                f"{key}_median_run": float(np.median(np.sqrt(per_run)))})
    if curve:
        out[f"{key}_curve"] = [float(v) for v in np.sqrt(e.mean(axis=0))]
    return out


def _not_run(reason: str, key: str, curve: bool = True) -> dict:
    """The metrics of a design that cannot start (not run): ``infeasible`` with the reason, no error statistics
    (like a filter that diverged in every run, it draws nothing from the bootstrap stream)."""
    out = {"infeasible": reason, "diverged_runs": None, key: None, f"{key}_ci95": None, f"{key}_median_run": None}
    return {**out, f"{key}_curve": None} if curve else out


def _recommend(filters: dict, key: str) -> dict:
    """Among the filters a user can deploy (run time local or scheduled): the most accurate, whether its lead is
    significant (disjoint intervals), the cheapest, the leanest; and the most accurate reference (a global oracle or
    a centralized filter: what the structure or a fusion centre could reach, never the pick)."""
    scored = {n: f for n, f in filters.items() if f[key] is not None and f["runtime"] in DEPLOYABLE}
    refs = {n: f for n, f in filters.items() if f[key] is not None and f["runtime"] not in DEPLOYABLE}
    best_ref = min(refs, key=lambda n: refs[n][key]) if refs else None
    if not scored:
        return {"most_accurate": None, "not_significantly_worse": [], "cheapest": None, "fewest_messages": [],
                "best_reference": best_ref}
    best = min(scored, key=lambda n: scored[n][key])
    lo_best = scored[best][f"{key}_ci95"][1]
    tied = [n for n in scored if n != best and scored[n][f"{key}_ci95"][0] <= lo_best]
    fewest = min(f["messages_per_step"] for f in scored.values())
    return {"most_accurate": best, "not_significantly_worse": tied,
            "cheapest": min(scored, key=lambda n: scored[n]["time_per_step_s"]),
            "fewest_messages": [n for n in scored if scored[n]["messages_per_step"] == fewest],
            "best_reference": best_ref}


def table_markdown(results: dict) -> str:
    """Per scenario: the trade-off table (accuracy, cost, communication) and the sweeps."""
    text = ("# comparison: consensus EKF vs local EKFs vs KCF and HCMCI vs centralized particle filters and EKF\n\n"
            f"Seed {results['seed']}, M = {results['particles']} particles. No paper makes this comparison; "
            "every filter faces one realisation of the same attack law per run.\n")
    for sc_name, b in results["by_scenario"].items():
        at, key = b["attacks"], b["error"]["metric"]
        what = _ERROR_WORDS.get(key, "state")
        rows = {n: {"family": f["family"], "runtime": runtime_label(f["runtime"]),
                    "rmse": f"infeasible, not run: {f['infeasible']}" if f.get("infeasible") else
                    "diverged in every run" if f[key] is None else
                    f"{f[key]:.4g} [{f[f'{key}_ci95'][0]:.3g}, {f[f'{key}_ci95'][1]:.3g}]",
                    "median": f[f"{key}_median_run"],
                    "time": None if f["time_per_step_s"] is None else fmt_dur(f["time_per_step_s"]),
                    "msgs": f["messages_per_step"], "div": f["diverged_runs"],
                    "feas": f.get("feasible_runs")} for n, f in b["filters"].items()}
        probs = ("as declared per channel (see the attacks section)" if at["dos_prob"] is None else
                 f"DoS {at['dos_prob']:g}, FDI {at['fdi_prob']:g}")
        amp = at["amplitude"] if isinstance(at["amplitude"], list) else f"{at['amplitude']:g}"
        text += (f"\n## {sc_name}: accuracy, cost and communication\n\n{b['runs']} runs, K = {b['steps']} steps, "
                 f"{b['nodes']} sensor nodes, links {b['links']}. Attacks on every channel: {probs}, injected "
                 f"xi = {amp} {at['law']}(s) on {', '.join(at['components'])} (bound delta = {at['delta']:.4g}). "
                 + (f"Error over {', '.join(b['error']['components'])}.\n\n" if "regions" not in b["error"] else
                    "Each node's error over its own region's states (REGIONS; a centralized filter's one estimate "
                    "on each node's region): " + "; ".join(f"node {i}: {', '.join(r)}" for i, r in
                                                         enumerate(b["error"]["regions"])) + ".\n\n"))
        text += markdown_table(rows, [("family", "family"), ("rmse", f"{what} RMSE [95 % CI]"),
                                      ("median", "median run RMSE"), ("time", f"time/step ({MEASURED})"),
                                      ("msgs", "messages/step"), ("div", "diverged runs"),
                                      ("feas", "runs with design conditions met"), ("runtime", "run time")],
                               "filter")
        if b.get("left_out"):
            text += ("\nLeft out of the default filters (`--filters NAME` runs one): " + "; ".join(
                f"{n}: {why}" for n, why in b["left_out"].items()) + ".\n")
        rec = b["recommendation"]
        if rec["most_accurate"] is not None:
            text += (f"\nMost accurate of the filters the nodes can run: {rec['most_accurate']}"
                     + (f" (not significantly better than {', '.join(rec['not_significantly_worse'])})"
                        if rec["not_significantly_worse"] else " (95 % interval disjoint from every other one's)")
                     + f"; fewest messages per step: {', '.join(rec['fewest_messages'])} (cost is ranked by the "
                     "messages counted, not by the measured times).\n")
        stuck = {n: f for n, f in b["filters"].items() if f.get("degenerate")}
        if stuck:
            text += ("\nDegenerate particle filters (their weight on a handful of particles at every step: their "
                     "estimates follow those particles, not the posterior, and their error is no measure of what a "
                     "particle filter could reach here): " + ", ".join(
                         f"{n} (typical effective sample size {f['weights_ess']:.3g} of {f['particles']})"
                         for n, f in stuck.items()) + ".\n")
        alone = [n for n, f in b["filters"].items() if f.get("better_than_local") is False]
        if alone:
            text += ("\nNo better than the nodes running alone on these runs (the 95 % paired interval of their RMSE "
                     "over the local EKFs', on the same runs, not entirely below 1): " + ", ".join(
                         f"{n} ({local_ratio_text(b['filters'][n])})" for n in alone) + ".\n")
        ref = rec.get("best_reference")
        if ref is not None:
            f = b["filters"][ref]
            text += (f"\nThe most accurate reference, {ref} ({runtime_label(f['runtime'])}), reaches {f[key]:.4g}: "
                     "what the structure or a fusion centre could reach, not a filter the nodes run.\n")
        for skey, title in (("dos_prob", "DoS probability (FDI fixed)"), ("fdi_prob", "FDI probability (DoS fixed)")):
            sw = b["sweeps"][skey]
            names = [n for n in b["filters"] if any(n in row for row in sw.values())]
            text += (f"\n### {sc_name}: {what} RMSE against the {title}\n\nRMSE over all runs (median run's "
                     "RMSE in brackets: a few exploding runs dominate the first, not the second).\n\n")
            text += markdown_table({v: {n: _sweep_cell(row.get(n), key) for n in names} for v, row in sw.items()},
                                   [(n, n) for n in names], skey)
    return text


def _sweep_cell(m: dict | None, key: str) -> str | None:
    if m is None:
        return None
    if m.get("infeasible"):
        return "infeasible (not run)"
    if m[key] is None:
        return "diverged"
    return f"{m[key]:.4g} ({m[f'{key}_median_run']:.3g})" + (", degenerate" if m.get("degenerate") else "")


def _figures(out: Path, results: dict, built: dict, arrays: dict) -> None:
    """Per scenario: the error over time, the sweeps and run 1's trajectory, one colour per filter (the summary's
    trade-off figure is :func:`studies.figures.tradeoff_figure`'s)."""
    plt = plotting()
    blocks = results["by_scenario"]
    for sc_name, b in blocks.items():
        A, sc = arrays[sc_name], built[sc_name]
        key, slug = b["error"]["metric"], _slug(sc_name)
        colours = filter_colours(b["filters"])
        what = _ERROR_WORDS.get(key, "state")
        curves_figure(out / f"fig_rmse_{slug}.png",
                      {n: f[f"{key}_curve"] for n, f in b["filters"].items() if f[f"{key}_curve"] is not None},
                      f"{what} RMSE", f"{sc_name}: {what} RMSE over time at the main attack setting", log=True,
                      colours=colours)
        fig, axs = plt.subplots(1, 2, figsize=(12.5, 4.2), sharey=True)
        for ax, (skey, label) in zip(axs, (("dos_prob", "DoS probability (FDI fixed)"),
                                           ("fdi_prob", "FDI probability (DoS fixed)"))):
            xs = sorted(b["sweeps"][skey], key=float)
            for n in b["filters"]:
                pts = [(float(v), b["sweeps"][skey][v][n]) for v in xs if n in b["sweeps"][skey][v]
                       and b["sweeps"][skey][v][n][key] is not None]
                if len(pts) < 2:
                    continue
                x = [p[0] for p in pts]
                ax.plot(x, [p[1][key] for p in pts], "o-", color=colours[n], label=n)
                ax.fill_between(x, [p[1][f"{key}_ci95"][0] for p in pts], [p[1][f"{key}_ci95"][1] for p in pts],
                                color=colours[n], alpha=0.15)
            ax.set(xlabel=label, ylabel=f"{what} RMSE (log scale)", yscale="log",
                   title=f"{sc_name}: degradation with the {label.split(' (')[0]}")
        legend_beside(axs[1])
        save_figure(fig, out / f"fig_sweeps_{slug}.png")
        _trajectory(out / f"fig_trajectory_{slug}.png", sc, A, sc_name, colours, list(b["filters"]))


def _trajectory(path: Path, sc: Scenario, A: dict, sc_name: str, colours: dict, names: list) -> None:
    """Run 1's truth and estimates (``names``: the filters run, in the order of the arrays): in the plane of the
    position, or per state component over time."""
    plt = plotting()
    m = sc.model
    tr = A["truth"][0]
    if len(m.position_index) == 2:
        fig, ax = plt.subplots(figsize=(8, 5))
        i, j = m.position_index
        sens = [s.position for s in m.sensors if s.position is not None and len(s.position) >= 2]
        if sens:
            sens = np.array(sens)
            ax.plot(sens[:, 0], sens[:, 1], "ks", ms=5, label="sensors")
        ax.plot(tr[:, i], tr[:, j], "k-", lw=2, label="truth")
        for f, entry in enumerate(FILTER_REGISTRY[n] for n in names):
            e, n = A["estimate"][0, f], entry.name
            if np.all(np.isfinite(e)):
                ax.plot(e[:, i], e[:, j], lw=1, color=colours[n],
                        label=n + (" (node 1)" if entry.family in ("consensus", "local") else ""))
        ax.set(xlabel=f"{m.state_names[i]}", ylabel=f"{m.state_names[j]}", title=f"{sc_name}, run 1: truth and "
               "estimates")
        legend_beside(ax)
    else:
        comps = list(m.position_index) or list(range(min(m.n_x, 4)))
        fig, axs = plt.subplots(len(comps), 1, figsize=(10, 2.2 * len(comps) + 0.6), sharex=True, squeeze=False)
        t = np.arange(tr.shape[0])
        for ax, c in zip(axs[:, 0], comps):
            ax.plot(t, tr[:, c], "k-", lw=2, label="truth")
            for f, n in enumerate(names):
                e = A["estimate"][0, f]
                if np.all(np.isfinite(e)):
                    ax.plot(t, e[:, c], lw=1, color=colours[n], label=n)
            ax.set_ylabel(m.state_names[c])
        axs[0, 0].set_title(f"{sc_name}, run 1: truth and estimates (node 1 for the networked filters)")
        axs[-1, 0].set_xlabel("time step k")
        legend_beside(axs[0, 0])
    save_figure(fig, path)


STUDY = Study(
    name="comparison",
    text=TEXT,
    scenarios=SCENARIOS,
    runs=DEFAULT_RUNS,
    particles=500,
    chunk_size=chunk_size,
    plan=_plan,
    summarise=_summarise,
    table=table_markdown,
    figures=_figures,
    options={"sweep_values": SWEEP_VALUES, "tuned_in_sweeps": None, "oracles_in_sweeps": None, "tables_in_sweeps": None,
             "hcmci_iterations": HCMCI_ITERATIONS, "divergence_spread": DIVERGENCE_SPREAD, "filters": None},
    uses_design=True,
    many_scenarios=True,
    every_core=True,
    accepts=_accepts,
    combine=_combine,
    check=_check,
    uses=_uses,
)
