"""``cfdesign design --mode auto`` (the default): the best certified design a node can run, within a message budget.

An automatic design designs every deployable gain rule that can run on the model (each rule's
:meth:`designer.rule.GainRule.candidates`: the relay and flood rules at L = 1 .. L_max hops, the scheduled rule with
and without the senders' measurements, the tuned and the paper rules; an oracle, ``global``, none), each along the
same seeded simulated run as ``cfdesign design --mode NAME`` (:func:`studies.consensus_design.run_design`: the same
numbers), the candidates computed side by side on the usable cores (:func:`studies.runner.run_forked`), and picks:

1. **eligible**: certified (:mod:`designer.verdict`: finite and informative at every step of the horizon), inside
   the budget (``budget``: messages per step over the network as the studies count them, ``2 |E| L``; ``"kcf"``:
   no more than KCF sends, ``2 |E|``; ``budget_bytes``: the numbers its packets carry per step,
   :meth:`designer.rule.GainRule.payload`, times :data:`BYTES_PER_NUMBER`), and better than the nodes alone: its
   predicted error below the local EKFs' (a certified bound no better than a node running alone is listed, never
   picked);
2. the **smallest predicted error** among them: the node-average tr Φ over the last ``W`` steps of the horizon (the
   steadiness window of :func:`designer.verdict.steadiness_window`: the horizon's end, smoothed over one DoS draw);
   predicted errors within :data:`TIE` of the smallest are a tie, and a tie goes to the fewest bytes per step, then
   the fewest messages.

With ``REGIONS`` (:mod:`designer.regions`) every candidate is ranked on the regions, and the candidates of a rule whose
nodes may carry their regions alone (:attr:`designer.rule.GainRule.regional`) carry them, as every design of such a
rule does on such a model (:func:`studies.design_options.effective`; ``--carry whole`` keeps the whole state): the
same numbers on the regions, a node's work and memory on its carried states only, and a verdict and certificate on
the regions, where the whole state's far end would make them vacuous or unbounded.

The pick is designed again in this process (the candidates' designs stay in their processes: their arrays are large)
and its verdict checked against its candidate's: the same numbers, or the command fails.  With no eligible
candidate the command says why, names the cheapest certified candidate outside the budget, writes the best design
inside it (its verdict its own) and exits 1.  A candidate that cannot start (its design refused the model or broke
(28)/(29) at its first step), failed, or did not finish within ``seconds`` (:data:`AUTO_SECONDS`) is listed with the
reason.

With ``validate`` R > 0, the pick runs on R fresh Monte Carlo runs (the ``consensus-robot`` study's runs of the same
seed, ``SeedSequence(seed).spawn(R)[r]``: a different stream from the design's run, ``SeedSequence(seed).spawn(2)``)
beside KCF, HCMCI, the local EKFs and the centralized EKF; the RMSEs and the bound check go to ``validation.json``
and the report.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

import rules
from designer.design import DesignOptions
from designer.progress import counter, phase
from designer.validation import ComputationError, InputError, check_int
from designer.verdict import json_number, steadiness_window

from .consensus_design import Design, check_first_step, effective_design, run_design
from .design_options import as_mode
from .runner import run_forked
from .scenarios import Scenario

__all__ = ["AUTO", "AUTO_SECONDS", "TIE", "BYTES_PER_NUMBER", "VALIDATE_RUNS", "AUTO_ASSUMPTIONS", "Candidate",
           "AutoDesign", "run_auto", "check_auto", "offered", "refusal", "label", "best", "below_local", "budget_record", "message_budget", "predicted_error", "references", "reference_costs",
           "validation", "default_validation", "VALIDATE_ROWS", "VALIDATE_MIN_RUNS"]

AUTO = "auto"  # the --mode of the automatic design (not a gain rule: it chooses among them)
AUTO_SECONDS = 45.0  # the candidates' time budget (s): with the pick's design and 20 validation runs, within a minute
TIE = 0.01  # predicted errors within 1 % of the smallest are a tie (the cheaper wins)
BYTES_PER_NUMBER = 8  # a number in a packet: a float64 (an index too: no header is counted)
VALIDATE_RUNS = 20  # fresh Monte Carlo runs of an automatic design's validation, by default
#: The node-state rows N n a default validation's runs hold together, at most (fewer runs, VALIDATE_MIN_RUNS at the
#: least, on a larger network): the validation's whole-state references cost about N n³ a step and run, and its
#: answers are averages over the nodes as well as the runs, so a large network's run weighs like several small
#: ones'.  An assumption, chosen: every model to the 64-cell field (4096 rows) keeps its 20 runs; the 118-bus grid
#: (13 806 rows) gets 5, whose paired interval of the pick over the local EKFs was [0.084, 0.096] from 8 runs,
#: [0.089, 0.097] from 20.
VALIDATE_ROWS = 20 * 4096
VALIDATE_MIN_RUNS = 5

AUTO_ASSUMPTIONS = (
    "auto: the predicted error of a design is the node-average tr Phi over the last W = max(2, ceil(K/4)) steps of "
    "its K-step horizon along the seeded design run (the steadiness window: the horizon's end, smoothed over one DoS "
    "draw); predicted errors within 1 % of the smallest are a tie, won by the fewest bytes per step.",
    "auto: bytes per step count 8 bytes per number a packet carries (its values and, for a relayed measurement, its "
    "sensor's index), every packet attempted (a packet lost to DoS was sent), no header.",
    "auto: a certified candidate whose predicted error is not below the node-average steady-state tr P of the "
    "nodes' local EKFs (python-control dlqe at the operating point) is no better than the nodes alone: listed, not "
    "picked.",
    f"auto: the candidates are designed within {AUTO_SECONDS:g} s (--auto-seconds); one that did not finish is "
    "listed as not computed.",
)


def message_budget(value, network) -> int | None:
    """``--budget``: None (no cap), ``"kcf"`` (KCF's messages per step, ``2 |E|``) or a whole number >= 1."""
    if value is None:
        return None
    if isinstance(value, str):
        if value.strip().lower() == "kcf":
            return int(network.messages_per_step())
        try:
            value = int(value)
        except ValueError:
            raise InputError(f"budget must be 'kcf' or a whole number of messages per step >= 1, got {value!r}") \
                from None
    return check_int("budget", value, 1)


def default_validation(network, n_x: int) -> tuple[int, str | None]:
    """The default validation's runs on ``network`` with ``n_x`` states: :data:`VALIDATE_RUNS`, or fewer where they
    would hold more than :data:`VALIDATE_ROWS` node-state rows (at least :data:`VALIDATE_MIN_RUNS`), and why (None
    where not cut).  A property of the model, never of the machine."""
    rows = int(network.n_nodes) * int(n_x)
    runs = min(VALIDATE_RUNS, max(VALIDATE_MIN_RUNS, VALIDATE_ROWS // rows))
    if runs == VALIDATE_RUNS:
        return runs, None
    return runs, (f"validated on {runs} fresh runs, not the default {VALIDATE_RUNS}: a run of this network holds "
                  f"{rows} node-state rows, and the default runs hold at most {VALIDATE_ROWS} together "
                  f"(--validate {VALIDATE_RUNS} runs them)")


def check_auto(sc: Scenario, budget=None, budget_bytes=None, validate=None, seconds=None) -> tuple:
    """The automatic design's own arguments checked (InputError naming the parameter and its range) before any
    computation: ``(messages cap or None, bytes cap or None, validation runs, seconds)``."""
    if sc.network is None:
        raise InputError(f"scenario {sc.name!r} has no sensor network; the consensus design needs one "
                         "(a model file defines NETWORK)")
    cap = message_budget(budget, sc.network)
    if budget_bytes is not None:
        budget_bytes = check_int("budget_bytes", budget_bytes, 1)
    validate = default_validation(sc.network, sc.model.n_x)[0] if validate is None else \
        check_int("validate", validate, 0)
    seconds = AUTO_SECONDS if seconds is None else seconds
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not (0 < seconds < math.inf):
        raise InputError(f"auto_seconds must be a positive number of seconds, got {seconds!r}")
    return cap, budget_bytes, validate, float(seconds)


def below_local(value, local) -> bool:
    """Whether a predicted error or bound ``value`` is below the nodes' local EKFs' ``local`` (node-average steady-state
    tr P; None or inf: any finite value is): a design better than the nodes running alone."""
    return value is not None and math.isfinite(value) and (local is None or value < local)


def budget_record(network, cap, budget, budget_bytes) -> dict:
    """``candidates.json``'s and ``feasibility.json``'s ``budget``: the caps (None: none), ``--budget`` as given and
    what KCF sends per step."""
    return {"messages_per_step": cap, "given": None if budget is None else str(budget), "bytes_per_step": budget_bytes,
            "kcf_messages_per_step": int(network.messages_per_step())}


def predicted_error(trace: np.ndarray) -> float | None:
    """The node-average tr Φ over the last ``W`` steps (:func:`designer.verdict.steadiness_window`) of ``trace``
    (nodes, K); None where it is not finite (no bound somewhere in the window)."""
    trace = np.asarray(trace, dtype=float)
    if trace.ndim != 2 or trace.shape[1] == 0:
        return None
    W = min(trace.shape[1], steadiness_window(trace.shape[1]))
    with np.errstate(invalid="ignore", over="ignore"):
        v = float(np.mean(trace[:, -W:]))
    return v if math.isfinite(v) else None


def references(refs: dict) -> tuple[float | None, float | None]:
    """The centralized steady-state tr P and the local EKFs' node-average one (inf when some node alone has no steady
    state: then any finite bound beats the nodes alone), from :func:`designer.observability.kalman_references`; with
    regions (its ``regions``) both over each node's region, node-averaged (None when some node has no centralized
    reference)."""
    regional = refs.get("regions")
    local = (regional or refs).get("local") or []
    loc = float(np.mean([np.inf if v is None else v for v in local])) if local else None
    if regional is None:
        return refs.get("centralized"), loc
    central = regional["centralized"]
    return (None if not central or None in central else float(np.mean(central))), loc


@dataclass(frozen=True)
class Candidate:
    """One design an automatic design tried, and what came of it (``candidates.json``'s rows)."""

    rule: str
    options: dict  # the design options that set it apart (e.g. {"rounds": 2})
    rounds: int
    exchange: str
    messages: int  # per step over the network
    bytes: int  # per step over the network
    status: str  # 'designed', 'cannot start', 'failed' or 'not computed'
    verdict: str | None = None
    certified: bool = False
    bounded: bool | None = None
    reason: str | None = None  # the verdict in words, or why it was not designed
    predicted: float | None = None  # node-average tr Φ at the horizon (predicted_error), over regions with regions
    ratio_centralized: float | None = None
    ratio_local: float | None = None
    seconds: float = 0.0
    in_budget: bool = True
    better_than_local: bool | None = None

    @property
    def label(self) -> str:
        return label(self.rule, self.options)

    @property
    def eligible(self) -> bool:
        return self.status == "designed" and self.certified and self.in_budget and self.better_than_local is not False

    def record(self) -> dict:
        return {"rule": self.rule, "label": self.label, "options": dict(self.options), "rounds": self.rounds,
                "exchange": self.exchange, "messages_per_step": self.messages, "bytes_per_step": self.bytes,
                "status": self.status, "verdict": self.verdict, "certified": self.certified, "bounded": self.bounded,
                "reason": self.reason, "predicted_trace": json_number(self.predicted),
                "ratio_centralized": json_number(self.ratio_centralized), "ratio_local": json_number(self.ratio_local),
                "better_than_local": self.better_than_local, "in_budget": self.in_budget,
                "design_seconds": round(float(self.seconds), 3)}


@dataclass(frozen=True, eq=False)
class AutoDesign:
    """What ``cfdesign design --mode auto`` computes: the candidates, the pick (a :class:`Design`, or None when no
    candidate was designed) and, with validation, its fresh runs.

    ``certified`` is True only when the pick is eligible (certified, inside the budget, better than the nodes
    alone); ``outcome`` says which: ``'picked'``, ``'none in budget'`` (certified candidates exist outside it),
    ``'none certified'``, ``'none better than local'`` or ``'nothing designed'``; ``message`` in words.
    """

    scenario: Scenario
    options: DesignOptions
    candidates: list
    pick: Design | None
    pick_index: int | None
    outcome: str
    message: str
    budget: dict
    references: dict
    seed: int
    steps: int
    seconds: float
    validation: dict | None = None
    assumptions: tuple = field(default=AUTO_ASSUMPTIONS)

    @property
    def certified(self) -> bool:
        return self.outcome == "picked" and self.pick is not None and self.pick.certified

    @property
    def schedule(self):
        return None if self.pick is None else self.pick.schedule

    @property
    def verdict(self) -> str | None:
        return None if self.pick is None else self.pick.verdict

    @property
    def gain_rule(self):
        return None if self.pick is None else self.pick.gain_rule

    def verdict_line(self) -> str:
        return self.message if self.pick is None else f"{self.message}; {self.pick.verdict_line()}"

    def record(self) -> dict:
        """``candidates.json`` (schema ``cfdesign.candidates/1``)."""
        c_ref, l_ref = self.references.get("centralized"), self.references.get("local_mean")
        return {"schema": "cfdesign.candidates/1", "scenario": self.scenario.name, "seed": self.seed,
                "steps": self.steps, "budget": self.budget, "outcome": self.outcome, "message": self.message,
                "pick": self.pick_index, "seconds": round(float(self.seconds), 3),
                "references": {**self.references, "centralized": json_number(c_ref), "local_mean": json_number(l_ref)},
                "candidates": [c.record() for c in self.candidates], "assumptions": list(self.assumptions)}

    def save(self, directory) -> Path:
        """Write the pick's design directory (:meth:`Design.save`'s files) with ``candidates.json``, the candidates'
        figure and, after validation, ``validation.json`` (:func:`studies.outputs.save_auto`)."""
        from .outputs import save_auto

        return save_auto(self, directory)


def offered(base: DesignOptions, network, *, where=None) -> list[tuple]:
    """Every deployable rule's candidate designs on ``network`` (:meth:`designer.rule.GainRule.candidates`), with what
    the user gave in ``base`` kept: ``(name, rule, candidate, options)`` per design, ``candidate`` the fields that set
    it apart with the values it designs (a value the user gave wins: a candidate it makes another's twin is tried
    once).  ``where``: only the rules for which ``where(rule)`` holds (the map: the rules it maps)."""
    out = []
    for name, rule in rules.all_rules().items():
        if where is not None and not where(rule):
            continue
        seen = set()
        for offer in rule.candidates(network):
            opts = _fields(as_mode(base, name), offer)
            cand = {k: getattr(opts, k) for k in offer}
            key = tuple(sorted(cand.items()))
            if key not in seen:
                seen.add(key)
                out.append((name, rule, cand, opts))
    return out


def refusal(check, name: str, cand: dict, opts: DesignOptions) -> str | None:
    """Why candidate ``cand`` of rule ``name`` (its options ``opts``, the user's included) cannot start, by
    ``check(options)`` (raising InputError when refused); None when it can.  A candidate refused only with what the
    user gave (its rule's defaults pass) is the user's input at fault, for every rule alike: that InputError is
    raised."""
    try:
        check(opts)
        return None
    except InputError as exc:
        try:
            check(DesignOptions(mode=name, **cand))
        except InputError:
            return str(exc)  # this rule cannot start on this model
        raise


def label(rule: str, options: dict) -> str:
    """A candidate's name: its rule and the options that set it apart (``"flood (rounds=3)"``)."""
    extra = [f"{k}={v}" for k, v in options.items()]
    return rule + (f" ({', '.join(extra)})" if extra else "")


def best(entries) -> int | None:
    """The pick among eligible ``(key, predicted, bytes, messages)`` entries: the smallest predicted error, predicted
    errors within :data:`TIE` of it a tie won by the fewest bytes, then the fewest messages; its key (None: none)."""
    entries = list(entries)
    if not entries:
        return None
    low = min(e[1] for e in entries)
    tied = [e for e in entries if e[1] <= low * (1.0 + TIE)]
    return min(tied, key=lambda e: (e[2], e[3], e[1]))[0]


def _fields(options: DesignOptions, cand: dict) -> DesignOptions:
    """The user's options with a candidate's values where the user set none (a value the user gave is kept)."""
    given = {k: v for k, v in cand.items() if getattr(options, k) is None}
    return replace(options, **given)


def _validation_backend():
    """Where the validation's chunks run: every usable core (the same numbers on every backend)."""
    from designer.cores import usable_cores

    from .runner import Backend

    cores = usable_cores()
    return Backend("processes", workers=cores) if cores > 1 else Backend()


def _check_validation(sc: Scenario, options: DesignOptions, runs: int, given: bool = True) -> tuple[int, str | None]:
    """The memory of ``runs`` validation runs (the consensus-robot study's, of the candidate of ``options``: every
    deployable rule's filter holds the same per-node arrays), checked before any candidate is designed: InputError
    naming ``--validate`` and the most runs that fit when the user ``given`` them; for the default runs, the most that
    fit instead, and why (``(runs, None)`` when they fit)."""
    from .memory import check, study_need
    from .pipeline import StudyOptions
    from .study_registry import get_study

    study = get_study("consensus-robot")

    def need(r):
        chunk = study.chunk_size(sc, r) if callable(study.chunk_size) else study.chunk_size
        so = StudyOptions(r, study.particles, 0, chunk, _validation_backend(), options,
                          dict(study.options, **VALIDATION_OPTIONS))
        return study_need("consensus-robot", sc, so, None if study.uses is None else study.uses(sc, so))

    try:
        check(need(runs))
    except InputError as exc:
        fits = next((r for r in range(runs - 1, 0, -1) if _fits(need(r))), 0)
        why = str(exc).split("; to fit, use")[0]  # the study's advice names options the design does not take
        if given:
            raise InputError(f"--validate {runs}: the validation's {why}; --validate {fits} fits") from None
        size = why.split(": ")[0]  # the study on the model would need about X of memory, more than Y available
        return fits, (f"validated on {fits} fresh runs, not the default {runs}, which would not fit ({size})" if fits
                      else f"not validated: one fresh run would not fit ({size})")
    return runs, None


def _fits(need) -> bool:
    from .memory import check

    try:
        check(need)
    except InputError:
        return False
    return True


def _check_candidate(sc: Scenario, options: DesignOptions, steps: int) -> None:
    """What ``design --mode NAME`` checks before computing (the options, the model at its operating point, the
    memory a design needs): InputError naming the problem."""
    from .memory import check, design_need

    check(design_need(sc, options, steps))  # first: the design of the scalings may be what does not fit
    sc_c, _, des = effective_design(sc, options)
    rule = des.rule
    if rule.fixed_multipliers:  # σ, β kept as given: they may break (28)/(29) at the first step
        reason = check_first_step(sc_c, des, f"mode {rule.name!r}", options)
        if reason is not None:
            raise InputError(reason)


def _summary(design: Design) -> dict:
    """What the parent keeps of a candidate's design (its arrays stay in its process)."""
    meta = design.schedule.meta
    return {"verdict": design.verdict, "certified": design.certified, "bounded": meta.get("bounded"),
            "reason": design.verdict_line(), "predicted": predicted_error(design.region_trace_bound),
            "rounds": int(design.design.rounds), "exchange": str(design.design.exchange),
            "payload": int(design.gain_rule.payload(design.scenario.model, design.scenario.network, design.design))}


def _design_summary(sc: Scenario, options: DesignOptions, steps: int, seed: int) -> dict:
    return _summary(run_design(sc, options, steps=steps, seed=seed, screen=True))


def run_auto(sc: Scenario, options: DesignOptions | None = None, *, steps: int | None = None, seed: int = 0,
             budget=None, budget_bytes: int | None = None, validate: int | None = None,
             seconds: float | None = None, workers: int | None = None) -> AutoDesign:
    """The automatic design of ``sc`` (module docstring): every candidate, the pick, and its validation."""
    from designer.observability import kalman_references

    t0 = time.monotonic()
    options = options or DesignOptions()
    seed = check_int("seed", seed, 0)
    steps = check_int("steps", sc.steps if steps is None else steps, 1)
    given = validate is not None  # the user's runs are refused when they cannot fit; the default ones are cut
    cap, budget_bytes, validate, seconds = check_auto(sc, budget, budget_bytes, validate, seconds)
    base = replace(options, mode=None)
    sc_eff = sc.with_attacks(**base.attack_overrides())  # what every candidate designs for (effective's scenario)
    net, model = sc_eff.network, sc_eff.model
    x0, u0 = sc_eff.operating_point
    refs = kalman_references(model, x0, u0, sc_eff.regions)
    c_ref, l_ref = references(refs)

    # the candidates: every deployable rule's, with what the user gave kept
    plans = []
    for name, rule, cand, opts in offered(base, net):
        reason = refusal(lambda o: _check_candidate(sc, o, steps), name, cand, opts)
        plans.append((name, rule, cand, None if reason else opts, reason))
    if not any(p[3] is not None for p in plans):  # nothing can start: the model (or its size) is the problem
        raise InputError(next(p[4] for p in plans)) if plans else InputError(
            "no deployable gain rule offers a design on this network (rules.names() lists the rules)")
    cut = None if given else default_validation(net, model.n_x)[1]  # the default runs of a large network: fewer
    if validate:  # before the candidates are designed: a validation that cannot fit is refused now, not after
        validate, memory_cut = _check_validation(sc, next(p[3] for p in plans if p[3] is not None), validate, given)
        cut = memory_cut or cut
    # the cheap ones first: the rules that relay by their hops (each hop's designs side by side), then the others'
    # single exchange, the rules of offline tables last; within the time the candidates are given, every rule gets
    # its cheapest designs before any gets its dearest
    plans.sort(key=lambda p: (p[1].offline_tables, not p[1].relays, p[2].get("rounds") or 1, p[0],
                              sorted(p[2].items())))
    todo = [j for j, p in enumerate(plans) if p[3] is not None]
    bar = counter(len(todo), False, "automatic design: candidates")  # a terminal's progress bar
    try:
        done = run_forked([lambda o=plans[j][3]: _design_summary(sc, o, steps, seed) for j in todo],
                          workers=workers, deadline=t0 + seconds, on_done=lambda j, timed: bar.update(),
                          desc="automatic design: candidates designed")
    finally:
        bar.close()
    run_refused = [d.value for d in done if d.status == "failed" and d.value.startswith("InputError: ")]
    if len(run_refused) == len(done):  # every candidate refused the model's run (say h not finite at some step)
        raise InputError(run_refused[0].split(": ", 1)[1])
    results = dict(zip(todo, done))

    candidates = []
    for j, (name, rule, cand, opts, refused) in enumerate(plans):
        L = rule.rounds(net, opts.rounds if opts is not None else cand.get("rounds"))
        msgs = int(net.messages_per_step(L))
        row = dict(rule=name, options=dict(cand), rounds=L,
                   exchange=rule.design_fields(opts if opts is not None else DesignOptions(**cand))["exchange"],
                   messages=msgs, bytes=0, in_budget=cap is None or msgs <= cap)
        if refused is not None:
            candidates.append(Candidate(**row, status="cannot start", reason=refused))
            continue
        out = results[j]
        if out.status == "timeout":
            candidates.append(Candidate(**row, status="not computed", seconds=out.seconds,
                                        reason=f"not designed within the automatic design's {seconds:g} s "
                                               "(--auto-seconds)"))
            continue
        if out.status == "failed":
            status = "cannot start" if out.value.startswith("InputError") else "failed"
            candidates.append(Candidate(**row, status=status, seconds=out.seconds,
                                        reason=out.value.split(": ", 1)[-1]))
            continue
        s = out.value
        nbytes = BYTES_PER_NUMBER * s["payload"]
        row.update(rounds=s["rounds"], exchange=s["exchange"], bytes=nbytes,
                   in_budget=row["in_budget"] and (budget_bytes is None or nbytes <= budget_bytes))
        pred = s["predicted"]
        candidates.append(Candidate(
            **row, status="designed", verdict=s["verdict"], certified=bool(s["certified"]), bounded=s["bounded"],
            reason=s["reason"], predicted=pred, seconds=out.seconds,
            ratio_centralized=None if pred is None or not c_ref else pred / c_ref,
            ratio_local=None if pred is None or not l_ref or not math.isfinite(l_ref) else pred / l_ref,
            better_than_local=None if pred is None else below_local(pred, l_ref)))

    pick_index, outcome, message = _choose(candidates, cap, budget_bytes, regions=sc_eff.regions is not None)
    pick = None
    if pick_index is not None:
        chosen = candidates[pick_index]
        opts = _fields(as_mode(base, chosen.rule), chosen.options)
        # the pick in full: its stationary certificate where its run's bound is not steady (it may make it bounded)
        # and its tables beyond the horizon (its export needs them); a steady pick of a rule without tables is
        # its screened run (the certificate would repeat what its steady run shows, at a cost that grows with
        # the network: an LMI over every node)
        lean = not rules.get(chosen.rule).offline_tables and chosen.bounded is True
        pick = run_design(sc, opts, steps=steps, seed=seed, screen=lean)
        if lean:
            message += (f"; its stationary certificate was not computed (its run's bound is steady: bounded); "
                        f"--mode {chosen.rule} with the same options computes it")
        again = _summary(pick)
        if again["verdict"] != chosen.verdict or again["predicted"] != chosen.predicted:
            raise ComputationError(f"the pick {chosen.label} designed again here gives verdict {again['verdict']} and "
                                   f"predicted tr Phi {again['predicted']}, its candidate {chosen.verdict} and "
                                   f"{chosen.predicted}: the design is not reproducible")
    if cut is not None:
        message += f"; {cut}"
    budget_rec = budget_record(net, cap, budget, budget_bytes)
    ref_record = {"centralized": c_ref, "local_mean": l_ref, "where": refs.get("where"),
                  "costs": reference_costs(model, net)}
    auto = AutoDesign(sc_eff, options, candidates, pick, pick_index, outcome, message, budget_rec, ref_record,
                      seed, steps, time.monotonic() - t0)
    if validate and pick is not None:
        auto = replace(auto, validation=validation(pick, validate, seed))
    return auto


def reference_costs(model, network) -> dict:
    """Messages and bytes per step of the references on ``network``: KCF, HCMCI (one round), the local EKFs and
    the centralized EKF (their registry entries' counts, :mod:`studies.filter_registry`)."""
    from .filter_registry import centralized_consensus_ekf, hcmci, kcf, local_ekfs

    out = {}
    for entry in (kcf("KCF", ""), hcmci("HCMCI", ""), local_ekfs("local EKFs", ""),
                  centralized_consensus_ekf("centralized EKF", "")):
        out[entry.name] = {"messages_per_step": int(entry.messages(network, 1)),
                           "bytes_per_step": BYTES_PER_NUMBER * int(entry.payload(model, network, 1))}
    return out


def _choose(candidates: list[Candidate], cap, cap_bytes, regions: bool = False) -> tuple[int | None, str, str]:
    """The pick's index, the outcome and the message (module docstring); ``regions``: the predictions are over each
    node's region (:mod:`designer.regions`)."""
    designed = [i for i, c in enumerate(candidates) if c.status == "designed"]
    if not designed:
        return None, "nothing designed", "no candidate could be designed (see candidates.json for each reason)"
    eligible = [i for i in designed if candidates[i].eligible and candidates[i].predicted is not None]
    if eligible:
        i = best((j, candidates[j].predicted, candidates[j].bytes, candidates[j].messages) for j in eligible)
        c = candidates[i]
        return i, "picked", (f"picked {c.label}: certified, predicted node-average tr Φ "
                             + ("over each node's region " if regions else "") + f"{c.predicted:.4g}"
                             + (f" ({c.ratio_centralized:.3g} x the centralized EKF's"
                                + (" on the same states" if regions else "")
                                + (" steady state at the operating point: below it only where the run has left that "
                                   "point's geometry" if c.ratio_centralized < 1 else "") + ")"
                                if c.ratio_centralized else "")
                             + f", {c.messages} messages and {c.bytes} bytes per step"
                             + f", of {len(candidates)} candidates ({len(eligible)} eligible)")
    in_budget = [i for i in designed if candidates[i].in_budget]
    fallback = min(in_budget, key=lambda j: (not candidates[j].certified, candidates[j].predicted or np.inf),
                   default=None)
    certified = [i for i in designed if candidates[i].certified]
    outside = [i for i in certified if not candidates[i].in_budget]
    if outside and not any(candidates[i].certified for i in in_budget):
        j = min(outside, key=lambda k: (candidates[k].messages, candidates[k].bytes))
        limit = " and ".join(x for x in (f"{cap} messages" if cap is not None else "",
                                         f"{cap_bytes} bytes" if cap_bytes is not None else "") if x)
        return fallback, "none in budget", (
            f"no certified candidate within the budget of {limit} per step; the cheapest certified one outside it is "
            f"{candidates[j].label} ({candidates[j].messages} messages, {candidates[j].bytes} bytes per step)")
    if certified:
        return fallback, "none better than local", (
            "the certified candidates inside the budget predict no smaller an error than the nodes' local EKFs "
            "running alone: no design worth deploying was found")
    return fallback, "none certified", "no candidate is certified (see candidates.json for each verdict)"


#: The consensus-robot study's options in a validation: the paper's design is not run beside the pick (it is no
#: reference of the automatic design; on a 64-cell field its bounds held half the validation's memory).
VALIDATION_OPTIONS = {"paper_reference": False}


def validation(pick: Design, runs: int, seed: int) -> dict:
    """The pick on ``runs`` fresh Monte Carlo runs beside KCF, HCMCI, the local and the centralized EKF
    (``validation.json``, schema ``cfdesign.validation/1``): the ``consensus-robot`` study with the pick's options.

    Per filter: ``rmse`` (over every state component, the root of ``mse``, the mean ‖e‖² over the runs, steps and
    nodes), ``rmse_state``, ``rmse_position`` where the model has a position, ``diverged_runs`` (how many), the
    messages per step, ``rmse_ci95`` (the 95 % bootstrap interval over the runs); for the pick its ``bound_check``,
    verdict counts and ``better_than_local`` (:func:`studies.results.better_than`: the 95 % paired interval of its RMSE
    over the local EKFs' on the same runs, ``rmse_ratio_local_ci95``, entirely below 1; None when not judged);
    ``ratios``: the pick's RMSE over each reference's.  With regions
    (:mod:`designer.regions`) each row also has ``rmse_region`` (each node on its own region's states) and
    ``rmse_region_ci95`` in place of ``rmse_ci95``, and the ratios and the comparison with the local EKFs are of
    it."""
    from .pipeline import run_study

    opts = replace(pick.options, mode=pick.gain_rule.name)
    with phase(f"validation, {runs} fresh runs"):  # its lines say so, not only the study it runs
        res = run_study("consensus-robot", [pick.scenario], runs=runs, seed=seed, options=opts, quiet=False,
                        backend=_validation_backend(), **VALIDATION_OPTIONS)  # the runner's progress bar on a terminal
    filters = res.results["filters"]
    mine = next((n for n in filters if n.startswith("consensus-EKF") and f"({pick.gain_rule.name}" in n), None)
    key = "rmse_region" if pick.scenario.regions is not None else "rmse"  # what the pick was ranked by
    rows = {}
    for name, f in filters.items():
        if name.startswith("consensus-EKF") and name != mine:
            continue  # the study's paper design: not a reference of the automatic design
        per = f.get("rmse_state")
        mse = float(sum(v * v for v in per)) if isinstance(per, list) and per and None not in per else None
        row = {"filter": name, "rmse": None if mse is None else math.sqrt(mse), "mse": mse, "rmse_state": per,
               "diverged_runs": len(f.get("diverged_runs") or []), "messages_per_step": f.get("communications")}
        if f.get("rmse_position") is not None:
            row["rmse_position"] = f["rmse_position"]
        if f.get("rmse_region") is not None:  # the model declares regions: each node on its own states
            row["rmse_region"] = f["rmse_region"]
        row[f"{key}_ci95"] = f.get(f"{key}_ci95")
        if name == mine:
            row.update(bound_check=f.get("bound_check"), verdicts=f.get("verdicts"))
        rows["pick" if name == mine else name] = row
    ratios = {n: json_number(rows["pick"][key] / r[key]) for n, r in rows.items()
              if n != "pick" and rows.get("pick", {}).get(key) is not None and r.get(key)}
    if "pick" in rows:  # the one definition of "better than the nodes alone" (studies.results.better_than), the study's
        f = filters[mine]
        rows["pick"].update(better_than_local=f.get("better_than_local"), rmse_ratio_local=f.get("rmse_ratio_local"),
                            rmse_ratio_local_ci95=f.get("rmse_ratio_local_ci95"))
    return {"schema": "cfdesign.validation/1", "runs": runs, "seed": seed,
            "seeds": f"SeedSequence({seed}).spawn({runs})[r].spawn(2) = (truth and measurements, channel attacks) of "
                     f"run r; the design's run is SeedSequence({seed}).spawn(2), a different stream",
            "pick": pick.gain_rule.name, "filters": rows, "pick_rmse_ratio": ratios}
