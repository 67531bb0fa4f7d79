"""``cfdesign design``: a consensus-filter gain schedule along a stated trajectory.

The schedule is computed along a **seeded simulated run** of the scenario: the
true trajectory and measurements are drawn from ``SeedSequence(seed).spawn(2)[0]``
and the channel attacks (DoS pattern, FDI indicators and signals) from
``spawn(2)[1]``; every node runs the online consensus filter on that run, so
``F`` and ``H`` are linearised at the node's own estimates and ``s_i`` is the
realised number of received packets.  Φ, K and C are therefore those of that
run.  A filter that *replays* the schedule on another run keeps the gains but
loses the guarantee: Theorem 1's bound holds for the linearisation points and
DoS pattern it was computed along, not for another realisation (the bound must
then be recomputed online, which is what the studies do).
"""
from __future__ import annotations

import contextlib
import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from designer.design import DESIGN_ASSUMPTIONS, ConsensusDesign, DesignOptions, describe_design, make_design
from designer.rule import GainRule
from designer.joint import conditioning
from designer.observability import kalman_references, observability
from designer.regions import carried_positions, region_detail, region_mask, region_sums, region_traces
from designer.progress import phase
from designer.schedule import GainSchedule
from designer.validation import InputError, check_int
from designer.verdict import (GATE_CLAUSE, NOT_COMPUTED, VERDICT_ASSUMPTIONS, Verdict, describe,
                              open_loop_reference, open_loop_traces, verdict)
from filters.consensus import run_consensus
from filters.consensus_batch import ConsensusResult, EdgeAttacks
from filters.result import HARD_CONDITIONS

from .design_options import effective, rule_of
from .invocation import design_invocation
from .provenance import design_seal
from .results import versions
from .runner import Background, run_forked
from .scenarios import Scenario

__all__ = ["Design", "consensus_design", "effective_design", "with_tables", "run_design", "DESIGN_ASSUMPTIONS",
           "check_first_step", "prefetch_tables", "design_verdict", "bound_verdicts", "trace_verdicts", "bound_traces",
           "scenario_open_loop", "judged_positions"]


def consensus_design(sc: Scenario, options: DesignOptions | None = None, *, steps: int | None = None,
                     **kw) -> ConsensusDesign:
    """The consensus design of ``sc`` for ``options`` (or keyword options), merged with the scenario's defaults.

    Mode ``'scheduled'`` gets its offline tables for ``steps`` steps (default the scenario's horizon;
    :func:`with_tables`).

    Attack overrides in the options are applied to the scenario first (its FDI bound
    becomes the design's δ); use :func:`studies.design_options.effective` to get that scenario too.
    """
    if kw:
        options = (options or DesignOptions()).merged(DesignOptions(**kw))
    sc, _, des = effective_design(sc, options)
    return with_tables(sc, des, steps)


def effective_design(sc: Scenario, options: DesignOptions | None) -> tuple[Scenario, DesignOptions, ConsensusDesign]:
    """The scenario with the options' attacks, the effective options (:func:`studies.design_options.effective`) and
    the design they make at the scenario's operating point, without offline tables (:func:`with_tables` adds
    them): what every design command starts from, checked (InputError naming the problem) before any run."""
    sc, opts = effective(sc, options)
    x0, u0 = sc.operating_point
    att = sc.resolved_attacks
    des = make_design(sc.model, sc.network, rule=rule_of(opts), delta=att.delta, options=opts, x0=x0, u0=u0,
                      signal=att.signal, regions=sc.regions)
    return sc, opts, des


def with_tables(sc: Scenario, design: ConsensusDesign, steps: int | None = None) -> ConsensusDesign:
    """``design`` with its rule's offline tables for ``steps`` steps of ``sc`` (default its horizon): designed
    along the nominal trajectory from the operating point with the scenario's known inputs, from the prior
    covariance (:meth:`designer.rule.GainRule.tables`).  A design of a rule without ``offline_tables`` is returned
    as it is."""
    if not design.rule.offline_tables:
        return design
    steps = sc.steps if steps is None else int(steps)
    key = _tables_key(sc, design, steps)
    if key not in _TABLES:  # a deterministic function of the scenario's content and the design: computed once
        x0, _ = sc.operating_point
        _remember(key, design.rule.tables(sc.model, sc.network, design, steps, x0=x0, inputs=sc.inputs(steps)))
    return design._replace(tables=_TABLES[key])


def with_horizon_tables(sc: Scenario, design: ConsensusDesign, steps: int, stack: contextlib.ExitStack
                        ) -> tuple[ConsensusDesign, Callable[[], ConsensusDesign]]:
    """:func:`with_tables` in two parts: ``design`` with the tables of the horizon (all that a run over the horizon
    uses) and a function that returns it with the complete tables, the part beyond the horizon (the stationary
    tables, :meth:`designer.rule.GainRule.stationary_tables`) computed meanwhile beside this process
    (:class:`studies.runner.Background`, entered on ``stack``).  The same tables as :func:`with_tables`; a design
    with a bank of operating points (its nodes use the bank within the horizon too), of a rule without offline
    tables, or whose tables this process has, is complete at once."""
    if not design.rule.offline_tables or design.bank or _tables_key(sc, design, steps) in _TABLES:
        done = with_tables(sc, design, steps)
        return done, lambda: done
    x0, _ = sc.operating_point
    inputs = sc.inputs(steps)
    horizon = design.rule.tables(sc.model, sc.network, design, steps, x0=x0, inputs=inputs, stationary=False)
    late = stack.enter_context(Background(design.rule.stationary_tables, sc.model, sc.network, design, horizon,
                                          inputs=inputs))

    def complete() -> ConsensusDesign:
        tables = horizon._replace(**late.result(), horizon_state=None)
        _remember(_tables_key(sc, design, steps), tables)
        return design._replace(tables=tables)

    return design._replace(tables=horizon), complete


def prefetch_tables(items: Sequence[tuple[Scenario, DesignOptions]], steps: int | None = None,
                    workers: int | None = None) -> None:
    """The offline tables that :func:`consensus_design` of each ``(scenario, options)`` will need and this process does
    not have yet, computed side by side in forked children (:func:`studies.runner.run_forked`, at most ``workers``)
    and kept here, so that those designs then find them.  The same numbers as one after the other (a deterministic
    function of the scenario and the design); an item that cannot start, or a child that fails, is left to the design
    itself, which raises as it would have.  With fewer than two to compute it does nothing."""
    todo, keys = [], set()
    for sc, options in items:
        try:
            sc_eff, _, des = effective_design(sc, options)
        except InputError:
            continue
        n = sc_eff.steps if steps is None else int(steps)
        key = _tables_key(sc_eff, des, n) if des.rule.offline_tables else None
        if key is not None and key not in _TABLES and key not in keys:
            keys.add(key)
            todo.append((key, sc_eff, des, n))
    if len(todo) < 2:
        return
    calls = [lambda sc=sc, des=des, n=n: des.rule.tables(sc.model, sc.network, des, n, x0=sc.operating_point[0],
                                                         inputs=sc.inputs(n)) for _, sc, des, n in todo]
    done = run_forked(calls, workers=workers, desc="offline tables of the designs computed")
    for (key, *_), result in zip(todo, done):
        if result.status == "done":
            _remember(key, result.value)


def _tables_key(sc: Scenario, design: ConsensusDesign, steps: int) -> tuple:
    return (sc.digest, steps, json.dumps(describe_design(design), sort_keys=True),
            None if design.fdi_moment is None else design.fdi_moment.tobytes(),
            None if design.fdi_mean is None else design.fdi_mean.tobytes())


def _remember(key: tuple, tables) -> None:
    while len(_TABLES) >= _TABLES_KEPT:
        _TABLES.pop(next(iter(_TABLES)))
    _TABLES[key] = tables


_TABLES: dict = {}  # the scheduled tables of this process, by scenario digest, horizon and design (oldest first)
_TABLES_KEPT = 16


def check_first_step(sc: Scenario, design: ConsensusDesign, name: str,
                     options: DesignOptions | None = None) -> str | None:
    """Why a paper design whose fixed σ or β breaks (28)/(29) at the first step cannot start (None: it can).

    Every node of every run starts at the prior mean with ``Φ_0|0 = P0`` and the scenario's first
    input, so the first step's (28) on ``Φ_0|0`` and (29) on ``Φ_1|0`` are the same in every run
    (neither depends on the measurements or the attacks): one step of the filter at that point tells,
    before any run, whether the design can run at all.  A study then reports such a design as
    infeasible, with the returned reason (the :class:`InputError` message of ``cfdesign design``), and
    runs the other filters.  When ``options`` (the study's, merged over the scenario's ``DESIGN``) set
    the paper design's own σ, β or τ, the user asked for that design: the reason is raised instead as
    an :class:`InputError` prefixed with the filter's ``name``.
    """
    if not design.rule.fixed_multipliers:
        return None
    m = sc.model
    u = sc.inputs(1)
    z = m.h_all(m.prior.mean, 1)[None]
    try:
        run_consensus(m, sc.network, z, design, inputs=u)
    except InputError as exc:
        reason = str(exc)
        if "at the first step" not in reason:
            raise
        opts = (sc.design or DesignOptions()).merged(options)
        given = [k for k in ("sigma", "beta", "tau") if getattr(opts, k) is not None]
        if given:
            raise InputError(f"{name}: {reason} ({' and '.join(given)} given by the options or the model's DESIGN: "
                             "set --sigma / --beta within the limit, or give none of sigma, beta, tau to report this "
                             "design as infeasible and run the other filters)") from None
        return reason
    return None


#: A stationary LMI solution whose own recursion step exceeds it by more than this (relative to its largest
#: eigenvalue) does not certify it: the solver's tolerance, not a bound.
LMI_TOLERANCE = 1e-6


def stationary_record(sc: Scenario, design: ConsensusDesign, *, lmi: bool = True, regions=None) -> dict:
    """The design's stationary certificate at the operating point (its rule's,
    :meth:`designer.rule.GainRule.stationary`) with its verdict and boundedness (:func:`designer.verdict.verdict`
    with ``fixed_point``): ``certified`` and ``bounded`` when the bound's recursion with the stationary gains reaches
    a fixed point, the LMI (where solved) confirms it within :data:`LMI_TOLERANCE`, and it lies below the
    stationary open loop; ``vacuous`` and not bounded when the recursion holds the conditions but reaches no fixed
    point; ``infeasible`` when it breaks (28)/(29) or the LMI does not confirm the fixed point; ``not computed``
    (with the reason) when the rule did not compute it
    (:attr:`designer.stationary.StationaryCertificate.not_computed`).  ``lmi`` False: the fixed point without the
    LMI that confirms it (a screening: its verdict is what the LMI would confirm or refuse).  ``regions``: the record
    also holds ``region_trace``, each node's tr Φ̄ over its region, for a design whose nodes carry the whole state
    (what an automatic map ranks it by on a model with ``REGIONS``; its verdict stays the whole state's)."""
    x0, u0 = sc.operating_point
    m = sc.model
    cert, where = design.rule.stationary(m, sc.network, design, x=x0, u=u0, lmi=lmi)
    open_loop, how = open_loop_reference(m.F_expected(x0, 0, u0), m.process_cov, m.prior.cov, sc.steps,
                                         design.carried_regions)  # on each node's region when it carries its own
    lmi = cert.lmi
    confirmed = lmi is None or lmi.get("trace") is None and lmi.get("status") == "not solved" or (
        lmi.get("relative_residual") is not None and lmi["relative_residual"] <= LMI_TOLERANCE)
    N = sc.network.n_nodes
    trace = cert.traces()[:, None] if cert.converged else np.full((N, 1), np.nan)
    skipped = cert.not_computed
    broken = not skipped and not cert.converged and cert.reason is not None and cert.reason.startswith(
        ("(28)", "(29)"))
    if cert.converged and not confirmed:
        broken, cert = True, cert._replace(reason="the stationary LMI does not confirm the fixed point")
    # a recursion that holds the conditions but does not settle is not bounded; one that breaks them is infeasible
    if design.carried_regions is not None:
        open_loop = np.asarray(open_loop)[:, None]  # one reference per node: its region's
    v = verdict(trace, open_loop, feasible=not broken, fixed_point=cert.converged and not broken,
                infeasible_reason=cert.reason if broken else None, open_loop_how=how,
                not_computed=cert.reason if skipped else None)
    extra = {}
    if regions is not None and cert.converged and cert.positions is None and cert.Phi is not None:
        extra["region_trace"] = [float(t) for t in region_traces(cert.Phi, regions)]
    return {**cert.describe(), "verdict": v.verdict, "bounded": v.bounded, "growing": v.growing,
            "bounded_reason": v.bounded_reason, "lmi_tolerance": LMI_TOLERANCE, "where": where, **extra}


def _offline_extras(sc: Scenario, design: ConsensusDesign, steps: int) -> tuple[dict, object]:
    """What a design of a rule with a stationary certificate records beside its run and does not compute from it:
    the certificate (:func:`stationary_record`) and what its trade-off needs (:meth:`designer.rule.GainRule.
    tradeoff_parts`: the other exchange rounds or hops)."""
    x0, u0 = sc.operating_point
    record = stationary_record(sc, design)
    return record, design.rule.tradeoff_parts(sc.model, sc.network, design, steps, x=x0, u=u0, inputs_of=sc.inputs,
                                              record=record)


def _infeasible_reason(violations: list[dict]) -> str | None:
    """The first hard violation ((28), (29), divergence) in one line; None when there is none."""
    hard = [v for v in violations if v["condition"] in HARD_CONDITIONS]
    if not hard:
        return None
    first = min(hard, key=lambda v: (v["step"], v["node"]))
    detail = first["reason"] if "reason" in first else f"margin {first['margin']:.4g}"
    return (f"{len(hard)} violations of (28)-(29) or divergence; first at node {first['node']}, step "
            f"{first['step']}, condition {first['condition']}, {detail}")


def _open_loop(model, x0, u0, steps: int, regions=None) -> tuple[np.ndarray, str]:
    """The open-loop covariance's trace at steps 1..``steps`` (the prior covariance propagated through the
    linearisation at the operating point with the process noise, no measurement) and how it was computed; with
    ``regions`` (nodes, steps), traced over each node's region."""
    ol = open_loop_traces(model.F_expected(x0, 0, u0), model.process_cov, model.prior.cov, steps, regions)
    return ol, (f"the prior covariance propagated by P <- F P F^T + Q over the {steps} steps, F the linearisation "
                "at the operating point, no measurement" + ("; traced over each node's region" if regions else ""))


def scenario_open_loop(sc: Scenario, steps: int, regions=None) -> np.ndarray:
    """The open-loop covariance's trace of ``sc`` at steps 1..``steps``: what a bound along a run of ``sc`` is
    judged informative against (:func:`designer.verdict.informative`), by the design and by the studies alike;
    with ``regions`` (nodes carrying their regions) (nodes, steps), over each node's region."""
    return _open_loop(sc.model, *sc.operating_point, steps, regions)[0]


def _not_computed(violations: list[dict]) -> str | None:
    """The reason the certificate was not computed (a violations record of condition ``not computed``), or None."""
    return next((v.get("reason") or NOT_COMPUTED for v in violations if v["condition"] == NOT_COMPUTED), None)


def design_verdict(model, x0, u0, trace: np.ndarray, violations: list[dict], references: dict,
                   regions=None) -> Verdict:
    """The verdict (:func:`designer.verdict.verdict`) on a bound computed along a run of ``model``.

    ``trace``: tr Φ_{k|k} per node for k = 1..K (NaN where Φ is not a bound); the open-loop covariance is
    the prior covariance propagated through the linearisation at the operating point (``x0``, ``u0``, where
    ``references`` were computed) with the process noise over the same K steps.  A certificate the rule did not
    compute (a violations record of condition ``not computed``) is ``not computed``, with its reason.  With
    ``regions`` (the nodes carry their regions), ``trace`` is over each node's region and so are the open loop and
    the references it is judged against (``references['regions']``).
    """
    ol, how = _open_loop(model, x0, u0, trace.shape[1], regions)
    refs = references if regions is None else references["regions"]
    feasible = not any(v["condition"] in HARD_CONDITIONS for v in violations)
    ver = verdict(trace, ol, feasible=feasible, centralized=refs["centralized"], local=refs["local"],
                  infeasible_reason=_infeasible_reason(violations), open_loop_how=how,
                  not_computed=_not_computed(violations))
    ver.detail["judged"] = "whole state" if regions is None else "region"
    return ver


def bound_traces(phi: np.ndarray, valid: np.ndarray, positions=None) -> np.ndarray:
    """tr Φ per run, node and step, (runs, nodes, steps), NaN where Φ is not a bound: what
    :func:`designer.verdict.verdict` and :func:`designer.verdict.informative` judge.  ``phi`` (runs, steps, nodes,
    n_x, n_x), or its diagonals (runs, steps, nodes, n_x: :meth:`filters.result.FilterResult.variance`, the same
    traces), and ``valid`` (runs, steps, nodes) of a consensus filter run along each run; ``positions``: when the
    nodes carry their regions, where each region sits in ``phi``'s coordinates (:func:`judged_positions`), the
    trace then over each node's region."""
    d = phi if np.ndim(phi) == np.ndim(valid) + 1 else np.diagonal(phi, axis1=-2, axis2=-1)
    with np.errstate(invalid="ignore", over="ignore"):
        tr = d.sum(axis=-1) if positions is None else region_sums(d, positions)
        return np.where(valid, tr, np.nan).swapaxes(1, 2)


def judged_positions(carried, design: ConsensusDesign):
    """Where each node's region sits in the coordinates of a result's ``carried`` states (None: the nodes carry the
    whole state, judged on it): what the studies judge a design's bound on, as the design judges its own."""
    return None if carried is None else carried_positions(carried, design.carried_regions)


def bound_verdicts(sc: Scenario, phi_post: np.ndarray, valid: np.ndarray, feasible,
                   design: ConsensusDesign | None = None, carried=None) -> list[Verdict]:
    """The verdict of each run's bound, as ``cfdesign design`` judges its own (:func:`design_verdict`).

    ``phi_post`` (runs, K + 1, nodes, n_x, n_x) and ``valid`` (runs, K + 1, nodes) of a consensus filter run along
    each run; ``feasible`` (runs,) whether (28)-(29) held throughout and the run did not diverge (a run that
    diverged or broke a condition is ``infeasible``, whatever its arrays hold).  A feasible run whose Φ is a bound
    at no step 1..K carries no certificate: ``not computed``.  With ``carried`` (the result's, its nodes carrying
    ``design``'s regions) each node is judged on its region against the open loop on the same states.
    """
    return trace_verdicts(sc, bound_traces(phi_post[:, 1:], valid[:, 1:], judged_positions(carried, design)),
                          feasible, design if carried is not None else None)


def trace_verdicts(sc: Scenario, tr: np.ndarray, feasible, design: ConsensusDesign | None = None) -> list[Verdict]:
    """:func:`bound_verdicts` from the runs' traces ``tr`` (runs, nodes, K) at steps 1..K
    (:func:`bound_traces`: NaN where Φ is not a bound), judged on ``design``'s carried regions when it is given (its
    nodes carry them), else on the whole state."""
    feasible = np.asarray(feasible, dtype=bool)
    K = tr.shape[-1]
    ol = scenario_open_loop(sc, K) if design is None else scenario_open_loop(sc, K, design.carried_regions)
    none = "Φ is a bound at no step of the run (no certificate was computed for it)"
    return [verdict(t, ol, feasible=bool(f), not_computed=none if f and np.isnan(t).all() else None)
            for t, f in zip(tr, feasible)]


def _with_stationary(ver: Verdict, stationary: dict | None) -> Verdict:
    """``ver`` with the design's boundedness: bounded when the run's bound is steady or the stationary certificate
    (:func:`stationary_record`) is a confirmed fixed point below the stationary open loop (certified and bounded);
    the detail records which (``bounded_by``)."""
    fixed = stationary is not None and stationary.get("verdict") == "certified" and bool(stationary.get("bounded"))
    if ver.verdict in ("infeasible", NOT_COMPUTED) or ver.bounded or not fixed:
        return ver
    detail = {**ver.detail, "bounded": True, "bounded_reason": None, "bounded_by": "stationary certificate"}
    return replace(ver, bounded=True, bounded_reason=None, detail=detail)


@dataclass(frozen=True, eq=False)
class Design:
    """A consensus filter designed along one seeded run (what ``cfdesign design`` computes).

    Attributes
    ----------
    scenario : Scenario
        The scenario with the attack overrides applied.
    options : DesignOptions
        The effective options (scenario defaults merged with the given ones).
    design : ConsensusDesign
        The design the nodes ran (ε, σ, β, τ, U, V_i, δ, mode, linearisation).
    result : ConsensusResult
        Every node's estimates, bounds, gains, multipliers and condition margins along the run.
    schedule : GainSchedule
        The exportable gain schedule (``schedule.json`` / ``schedule.npz``).
    truth : ndarray (steps + 1, n_x)
        The simulated true states.
    seed : int
    """

    scenario: Scenario
    options: DesignOptions
    design: ConsensusDesign
    result: ConsensusResult
    schedule: GainSchedule
    truth: np.ndarray
    seed: int
    validation: dict | None = None  # the design on fresh Monte Carlo runs (studies.auto.validation; --validate R)

    @property
    def feasible(self) -> bool:
        """(28)-(29) held at every node and step and no node diverged."""
        return self.schedule.feasible

    @property
    def violations(self) -> list[dict]:
        return self.schedule.violations

    @property
    def hard_violations(self) -> list[dict]:
        """The violations that make the design infeasible ((28), (29), divergence)."""
        return [v for v in self.violations if v["condition"] in HARD_CONDITIONS]

    @property
    def trace_bound(self) -> np.ndarray:
        """tr Φ_{k+1|k+1} per node and step, (nodes, steps); NaN where Φ is not a bound."""
        return np.array([[np.nan if v is None else v for v in row] for row in self.schedule.trace_bound()])

    @property
    def region_trace_bound(self) -> np.ndarray:
        """tr Φ_{k+1|k+1} over each node's region (:mod:`designer.regions`), (nodes, steps); NaN where Φ is not a
        bound; the whole state's (:attr:`trace_bound`) without regions."""
        if self.scenario.regions is None or self.schedule.carried is not None:  # the latter judged on its regions
            return self.trace_bound
        with np.errstate(invalid="ignore"):
            return region_traces(np.swapaxes(self.schedule.Phi[:, 1:], 0, 1), self.scenario.regions).T

    @property
    def verdict(self) -> str:
        """``certified``, ``vacuous``, ``infeasible`` or ``not computed`` (:mod:`designer.verdict`)."""
        return self.schedule.meta["verdict"]

    @property
    def certified(self) -> bool:
        """Feasible, with a bound finite and informative at every step of the horizon (``verdict ==
        'certified'``): Theorem 1's kind of claim."""
        return bool(self.schedule.meta["certified"])

    @property
    def bounded(self) -> bool:
        """Theorem 2's kind of claim: the bound along the run is steady, or the design's stationary certificate
        (a fixed point with its LMI confirmed, below the stationary open loop: ``stationary_certificate``) holds
        (``schedule.json``'s ``bounded``; ``bounded_reason`` says why not)."""
        return bool(self.schedule.meta["bounded"])

    @property
    def growing(self) -> bool:
        """The bound still rises at the horizon at some node (a qualifier of the certificate, not a failure)."""
        return bool(self.schedule.meta["growing"])

    @property
    def verdict_detail(self) -> dict:
        """The numbers behind the verdict: final tr Φ per node, the open-loop trace, the references, the ratios,
        the steadiness measure (``schedule.json``'s ``verdict_detail``)."""
        return self.schedule.meta["verdict_detail"]

    def reason(self) -> str | None:
        """Why the design is infeasible, in one line (None when feasible)."""
        return _infeasible_reason(self.violations)

    @property
    def gain_rule(self) -> GainRule:
        """The design's gain rule (:mod:`designer.rule`): its run-time class (``local``, ``scheduled`` or
        ``global``), what a node needs to apply it, and whether it is ``deployable`` (a ``global`` rule is an
        oracle: a reference of what the structure can reach, not a design to deploy)."""
        return self.design.rule

    def verdict_line(self) -> str:
        """The verdict in one sentence: what it is and, when not certified, which condition or node prevents it;
        an oracle's (a gain rule that is not deployable) says so."""
        caveat = self.gain_rule.caveat
        return (describe(self.verdict_detail) + (f"; {caveat}" if caveat else "")
                + (f"; {GATE_CLAUSE}" if self.design.gate else ""))

    def save(self, directory) -> Path:
        """Write ``schedule.json``, ``schedule.npz``, the report's figures and ``report.html`` / ``report.md`` into
        ``directory`` (:func:`studies.outputs.save_design`; refused when it is, lies inside or contains the model's
        files: :func:`designer.fileio.check_apart`)."""
        from .outputs import save_design

        return save_design(self, directory)


def run_design(sc: Scenario, options: DesignOptions | None = None, *, steps: int | None = None,
               seed: int = 0, screen: bool = False) -> Design:
    """Design the consensus filter of ``sc`` along a seeded simulated run (see the module docstring).

    ``screen``: the run and its verdict only, as an automatic design screens its candidates (:mod:`studies.auto`):
    no stationary certificate, no trade-off and no tables beyond the horizon (the same run, bounds and verdict)."""
    seed = check_int("seed", seed, 0)
    invocation = design_invocation(sc, options, steps=None if steps is None else check_int("steps", steps, 1),
                                   seed=seed)
    sc, opts, des = effective_design(sc, options)
    steps = check_int("steps", sc.steps if steps is None else steps, 1)
    x0, u0 = sc.operating_point
    att = sc.resolved_attacks
    m, net, rule = sc.model, sc.network, des.rule
    with contextlib.ExitStack() as stack:
        # the stationary certificate and the other exchange rounds do not depend on the tables nor on the seeded
        # run: computed beside them, in a second process where there is a second core (the same numbers)
        extras = stack.enter_context(Background(_offline_extras, sc, des, steps)) \
            if rule.stationary_certificate and not screen else None
        with phase("gain tables"):
            if screen and rule.offline_tables:
                des = des._replace(tables=rule.tables(m, net, des, steps, x0=x0, inputs=sc.inputs(steps),
                                                      stationary=False))
                complete = lambda: des  # noqa: E731 - the horizon's tables are all a screened run uses
            else:
                des, complete = with_horizon_tables(sc, des, steps, stack)  # the tables beyond the horizon meanwhile
        traj_ss, att_ss = np.random.SeedSequence(seed).spawn(2)
        traj = sc.simulate(np.random.default_rng(traj_ss), steps)
        attacks = EdgeAttacks.simulate(net, steps, m.n_x, [np.random.default_rng(att_ss)], att.signal)
        with phase("seeded run"):
            res = run_consensus(m, net, traj.z, des, inputs=traj.inputs, attacks=attacks)
        with phase("tables beyond the horizon"):
            des = complete()
        with phase("stationary certificate"):
            stationary, others = extras.result() if extras is not None else (None, None)
    Phi = np.where(res.valid[..., None, None], res.phi_post, np.nan).swapaxes(0, 1)
    refs = kalman_references(m, x0, u0, sc.regions)
    carried = des.carried_regions  # the nodes carry their regions: Φ in their carried coordinates, judged there
    pos = judged_positions(res.carried, des)
    trace = bound_traces(np.swapaxes(Phi[:, 1:], 0, 1)[None], res.valid[None, 1:], pos)[0]
    ver = _with_stationary(design_verdict(m, x0, u0, trace, res.violations, refs, carried), stationary)
    if sc.regions is not None:  # each node's final bound on its region (beside the verdict on the whole state)
        ver.detail["region"] = region_detail(Phi[:, -1], sc.regions, refs["regions"]["centralized"], m.state_names,
                                             pos)
    schedule = GainSchedule(
        scenario=sc.name,
        rule=des.rule,
        epsilon=des.epsilon,
        sigma=res.sigma.T.copy(),
        beta=res.beta.T.copy(),
        K=res.K.swapaxes(0, 1),
        C=res.C.swapaxes(0, 1),
        Phi=Phi,
        valid=res.valid.T.copy(),
        violations=res.violations,
        margin28=res.margin28.T.copy(),
        margin29=res.margin29.T.copy(),
        tables=None if des.tables is None else des.rule.table_arrays(des.tables),
        carried=res.carried,
        region_mask=None if carried is None else region_mask(carried, m.n_x),
        meta={
            **{k: v for k, v in describe_design(des).items() if k not in ("mode", "epsilon", "sigma", "beta")},
            "sigma_fixed": des.sigma if rule.fixed_multipliers else None,
            "beta_fixed": des.beta if rule.fixed_multipliers else None,
            "options": opts.as_dict(),
            "sensors": [{"name": s.name, "dim": s.dim} for s in m.sensors],
            "state_names": list(m.state_names),
            "carried": None if carried is None else [[m.state_names[j] for j in row if j >= 0] for row in res.carried],
            "seed": seed,
            **rule.record_notes(),
            "stationary": None if des.tables is None else des.tables.stationary,
            "tables_kind": None if des.tables is None else des.tables.kind,
            "tables_own_steps": None if des.tables is None else des.tables.own_steps,
            "bank_record": None if des.tables is None else des.tables.bank_record,
            "stationary_certificate": stationary,
            "rounds_tradeoff": rule.tradeoff(net, m.n_x, des, steps, others) if extras is not None else None,
            "boundedness_certified": not any(v["condition"] == "theorem2" for v in res.violations),
            "certified": ver.certified,
            "verdict": ver.verdict,
            "bounded": ver.bounded,
            "growing": ver.growing,
            "bounded_reason": ver.bounded_reason,
            "verdict_detail": ver.detail,
            # mode 'mse': the trace of each node's predicted error covariance (nodes x steps + 1), the accuracy the
            # gains were chosen for (the bound is the certificate)
            "predicted_mse": None if res.predicted_mse is None else [
                [float(v) if np.isfinite(v) else None for v in row] for row in res.predicted_mse.T],
            "conditioning": conditioning(res.gain_condition),
            "network": net.describe(),
            "observability": observability(m, x0, u0),
            "kalman_references": refs,
            "attacks": att.describe(m.state_names),
            "params": dict(sc.params),
            "source": sc.source,
            # a model file's bytes (and its local imports') as it was run: export checks a file against it before
            # importing it (a design directory from elsewhere names a file that may not be this one)
            "source_digest": sc.source_digest,
            "model_digest": sc.digest,
            "invocation": invocation,
            "assumptions": list(sc.assumptions) + list(DESIGN_ASSUMPTIONS) + list(VERDICT_ASSUMPTIONS),
            "versions": versions(),
        },
    )
    # a model file's record sealed under this account's key (studies.provenance): export imports the file only
    # when the seal verifies, so a directory from elsewhere naming a file and its digest is not enough
    schedule.meta["source_seal"] = design_seal({"scenario": schedule.scenario, **schedule.meta})
    return Design(sc, opts, des, res, schedule, traj.x, seed)
