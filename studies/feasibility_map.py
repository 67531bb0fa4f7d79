"""``cfdesign feasibility``: parameter-feasibility maps of the consensus-filter bounds.

At every grid point the steady-state bound recursion at the scenario's operating
point (its initial state ``x0`` and first input) is iterated to a fixed point
(:func:`designer.feasibility.steady_state`) with the design that ``cfdesign design``
would build from the same options, the grid's values replacing theirs.
``feasibility.csv`` gets one row per point (the grid parameters, ``feasible``,
``trace_bound``, ``binding``, ``theorem2``, ``iterations``) and a heat map is drawn
for one or two grid parameters.  The grid points go through the Monte Carlo runner
(:mod:`studies.runner`; a point plays the part of a run, chunks of ``CHUNK_SIZE``
points, each iterated as one batch, :func:`designer.feasibility.steady_state_batch`): in
this process, on ``--workers N`` local processes or on a Dask cluster (``--dask ADDRESS``),
stored under ``out/.chunks`` so that an interrupted map resumes.

**The grid's values** are the numbers ``START:STOP:COUNT`` means: value ``i`` is the double
nearest to ``START + i (STOP - START) / (COUNT - 1)`` computed exactly from the decimals
written, so ``dos=0:0.6:7`` is 0, 0.1, ..., 0.6 and the files write ``0.3`` (the shortest
decimal that reads back as the same double), never ``np.linspace``'s ``0.30000000000000004``.

**A point that fails** (its design cannot be built at those values, e.g. an amplitude whose
square overflows, or its iteration raises, e.g. an eigenvalue problem that does not converge
at an extreme scaling) is not feasible, has no bound and has ``binding`` ``"failed: <reason>"``;
the other points are mapped as they would be without it (:attr:`FeasibilityMap.failures`,
``failed_points`` in ``feasibility.json``, the report says how many and why).  Options wrong at
every point (not a grid value) are the user's input: an InputError before any point.

**The verdict of a point** (the ``verdict`` column; :func:`designer.verdict.verdict` on the stationary bound,
the function ``cfdesign design`` judges its bound with): ``certified`` where the stationary bound's tr Φ is below the
stationary open-loop covariance's trace at every node (the discrete Lyapunov solution at the operating point, or,
where ``F`` is not Schur stable, the open-loop covariance at the scenario's horizon): at a fixed point (certified
and bounded), or, where (28)-(29) held at every iterate but no fixed point was reached ("no convergence"), at the
last iterate (certified, not bounded); ``vacuous`` where some node's bound is at or above it, where the bound grew
without limit ("unbounded") or where there is none; ``infeasible`` where (28), (29) failed, the iteration diverged,
or the point has no design (``dos + fdi > 1``, a failed point); ``not computed`` where the rule did not compute its
stationary certificate (the scheduled one with rounds > 1).  ``feasible`` keeps its meaning (a bounded fixed point
exists) and is the point's ``bounded`` claim; ``feasibility.json`` counts the verdicts (``verdicts``) and records
the open-loop reference (``open_loop``).

**Two notions of feasibility.**  ``design`` checks (28)-(29) *along one simulated run*:
the nodes' own estimates, the realised DoS pattern (``s_i`` = packets actually
received) and the transient from the prior.  ``feasibility`` checks whether the
*stationary* recursion at the operating point, with the *expected* number of received
packets, has a bounded fixed point.  They disagree when the run leaves the operating
point (a nonlinear model linearised elsewhere), when a run's realised DoS pattern is
luckier or worse than its mean, or when the transient violates a condition that the
steady state satisfies (or the reverse: a run that is too short to reach an unbounded
steady state).
"""
from __future__ import annotations

import collections
import functools
import itertools
import math
from dataclasses import dataclass, replace
from fractions import Fraction
from pathlib import Path
from typing import Sequence

import numpy as np

import rules
from designer.design import DesignOptions, make_design
from designer.feasibility import steady_state, steady_state_batch
from designer.linearization import prediction_scaling, update_scaling
from designer.regions import region_traces
from designer.validation import ComputationError, InputError, check_strings
from designer.verdict import VERDICT_ASSUMPTIONS, count_verdicts, json_number, open_loop_reference, verdict

import studies.memory as memory
from .auto import (AUTO, BYTES_PER_NUMBER, below_local, best, budget_record, check_auto, label, offered, references,
                   refusal)
from .consensus_design import stationary_record
from .design_options import effective, rule_of
from .feasibility_terms import FAILED, GRID_PARAMETERS, OUTPUTS
from .invocation import feasibility_invocation
from .runner import Backend, monte_carlo
from .scenarios import Scenario, ScenarioRef, reference

__all__ = ["parse_grid", "FeasibilityMap", "MapCandidate", "run_feasibility", "map_points", "auto_rows", "CHUNK_SIZE",
           "AUTO_CHUNK_SIZE", "point_verdict", "stationary_open_loop"]

CHUNK_SIZE = 32  # grid points per chunk (the unit of resumption and of work sent to a worker; one batch)
AUTO_CHUNK_SIZE = 1  # grid points per chunk of an automatic map (each point maps every candidate, alone: spread them
#: out one by one, since points cost unlike: a 2 x 2 map of my 21-zone greenhouse in chunks of 2 kept one core idle
#: for a minute)

_PAPER_ONLY = ("tau", "sigma", "beta")


def _grid_spec(spec: str) -> tuple[str, Fraction, Fraction, int]:
    """``NAME=START:STOP:COUNT`` -> (name, start, stop, count), START and STOP as the exact numbers written, checked."""
    if not isinstance(spec, str):
        raise InputError(f"grid must be a string NAME=START:STOP:COUNT or a list of them, got {type(spec).__name__}")
    if "=" not in spec:
        raise InputError(f"--grid expects NAME=START:STOP:COUNT, got {spec!r}")
    name, rng = spec.split("=", 1)
    name = name.strip()
    if name not in GRID_PARAMETERS:
        raise InputError(f"--grid parameter {name!r} is unknown; allowed: {', '.join(GRID_PARAMETERS)}")
    parts = rng.split(":")
    try:
        if len(parts) != 3:
            raise ValueError
        count = int(parts[2])
        start, stop = (_exact(p) for p in parts[:2])
    except (ValueError, OverflowError):
        raise InputError(f"--grid {name} expects START:STOP:COUNT (finite numbers, COUNT an integer >= 1), "
                         f"got {rng!r}") from None
    if count < 1:
        raise InputError(f"--grid {name}: COUNT must be >= 1, got {rng!r}")
    ends = (float(start), float(stop)) if count > 1 else (float(start),)  # the values' extremes, as doubles
    lo, hi = min(ends), max(ends)
    if name in ("dos", "fdi") and (lo < 0 or hi >= 1):
        raise InputError(f"--grid {name} must lie in [0, 1), got {parts[0].strip()}:{parts[1].strip()}")
    if name == "epsilon" and lo <= 0:
        raise InputError(f"--grid epsilon must be > 0, got {parts[0].strip()}:{parts[1].strip()}")
    if lo < 0:
        raise InputError(f"--grid {name} must be >= 0, got {parts[0].strip()}:{parts[1].strip()}")
    return name, start, stop, count


def _exact(text: str) -> Fraction:
    """The number written in ``text`` exactly (``0.1`` is 1/10, not the double nearest to it); ValueError for
    anything ``float`` does not read and for inf and NaN."""
    value = float(text)  # the syntax float() reads, nothing more (no "1/3")
    if not math.isfinite(value):
        raise ValueError(text)
    try:
        return Fraction(text.strip())
    except ValueError:  # a spelling float() reads and Fraction does not (e.g. "1_000" before Python 3.12)
        return Fraction(value)


def _grid_values(start: Fraction, stop: Fraction, count: int) -> np.ndarray:
    """``start + i (stop - start) / (count - 1)``, i = 0 .. count - 1, each the double nearest to that exact number.

    The values the user wrote mean: ``dos=0:0.6:7`` is 0, 0.1, ..., 0.6, and each is written
    (CSV, JSON, report) as the shortest decimal that reads back as the same double, so ``0.3``
    and not ``np.linspace``'s ``0.30000000000000004``.  Integer arithmetic on a common denominator, one
    correctly rounded division per value.
    """
    if count == 1:
        return np.array([float(start)])
    den = start.denominator * stop.denominator * (count - 1)
    a = start.numerator * stop.denominator * (count - 1)
    step = (stop.numerator * start.denominator - start.numerator * stop.denominator)
    return np.array([(a + i * step) / den for i in range(count)])


def parse_grid(spec: str) -> tuple[str, np.ndarray]:
    """``NAME=START:STOP:COUNT`` -> (name, values), the values as :func:`_grid_values` gives them."""
    name, start, stop, count = _grid_spec(spec)
    return name, _grid_values(start, stop, count)


def _scaling(model, des, x0, u0, xp):
    """The Hessian-derived scalings at the operating point for the fixed-point iteration (None when fixed);
    ``phi_post`` (and ``phi_pred``) one matrix or a stack of them."""
    if des.linearization == "fixed":
        return None

    def scaling(i, phi_post, phi_pred):
        centre = np.broadcast_to(x0, np.shape(phi_post)[:-1])  # one centre per matrix of a stack
        pred = prediction_scaling(model, centre, phi_post, 0, u0, des.linearization, des.radius, des.U)
        upd = None if phi_pred is None else update_scaling(model, i, np.broadcast_to(xp, np.shape(phi_pred)[:-1]),
                                                           phi_pred, 1, des.linearization, des.radius, des.V[i])
        return pred, upd

    return scaling


_NO_ATTACK_MODEL = {"feasible": 0, "trace_bound": float("nan"), "binding": "dos + fdi > 1", "theorem2": 0,
                    "iterations": 0, "verdict": "infeasible"}
_POINT_ERRORS = (ArithmeticError, ValueError, np.linalg.LinAlgError, ComputationError)  # ValueError: InputError too
_REASON_CHARS = 200


def _failed(exc: BaseException) -> dict:
    """The row of a grid point whose design or fixed-point iteration raised ``exc``: not feasible, no bound."""
    text = " ".join(str(exc).split())
    reason = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    if len(reason) > _REASON_CHARS:
        reason = reason[:_REASON_CHARS - 1] + "…"
    return {"feasible": 0, "trace_bound": float("nan"), "binding": FAILED + reason, "theorem2": 0, "iterations": 0,
            "verdict": "infeasible"}


def _design_at(sc: Scenario, options: DesignOptions, point: dict, *, strict: bool = False):
    """The scenario and the design of ``options`` with the point's values, or the row of a point that has none:
    dos + fdi > 1 (no attack model), or a design that cannot be built at these values (``strict``: raise instead,
    for the options without a point, whose errors are the user's input)."""
    try:
        sc_p, opts = effective(sc, options.merged(DesignOptions(**point)))
    except InputError as exc:
        if "dos + fdi" in str(exc):
            return dict(_NO_ATTACK_MODEL)  # DoS and FDI never occur together: dos + fdi > 1 is no attack model
        if strict:
            raise
        return _failed(exc)
    x0, u0 = sc_p.operating_point
    att = sc_p.resolved_attacks
    try:
        with np.errstate(over="ignore", invalid="ignore"):  # extreme values overflow: the finiteness checks judge
            return sc_p, make_design(sc_p.model, sc_p.network, rule=rule_of(opts), delta=att.delta, options=opts, x0=x0,
                                     u0=u0, signal=att.signal, regions=sc_p.regions)
    except _POINT_ERRORS as exc:
        if strict:
            raise
        return _failed(exc)


_NO_FIXED_POINT = ("no convergence", "unbounded")  # (28)-(29) held at every iterate, but no fixed point was reached


def point_verdict(r, open_loop: float, nodes: int) -> str:
    """The verdict (:func:`designer.verdict.verdict`) on the stationary bound of one grid point's iteration ``r``
    (a :class:`designer.feasibility.SteadyState`) against the stationary open-loop trace ``open_loop``.

    A fixed point is bounded: certified or vacuous.  An iteration that stopped without one while the conditions held
    at every iterate is judged by its last bound (not bounded): "unbounded" (the trace grew past the iteration's
    limit: no finite bound) is vacuous; "no convergence" is vacuous when the last iterate's mean tr Φ over the nodes
    is at or above the open loop (so some node's is), else certified (not bounded: the map's category
    "not bounded").  (28), (29) or a diverged iteration is infeasible.
    """
    if r.feasible:
        trace = np.trace(r.phi, axis1=1, axis2=2)[:, None]
        return verdict(trace, open_loop, feasible=True, fixed_point=True).verdict
    if r.binding in _NO_FIXED_POINT:
        last = np.inf if r.binding == "unbounded" or not np.isfinite(r.trace_bound) else r.trace_bound
        return verdict(np.full((nodes, 1), last), open_loop, feasible=True, fixed_point=False).verdict
    return verdict(np.full((nodes, 1), np.nan), open_loop, feasible=False).verdict


def _open_loop_record(sc: Scenario) -> dict:
    """``feasibility.json``'s ``open_loop``: the stationary open-loop trace (null when it overflows) and how."""
    trace, how = stationary_open_loop(sc)
    return {"trace": trace if math.isfinite(trace) else None, "how": how}


def _row(r, open_loop: float, nodes: int, regions=None) -> dict:
    """A point's row from its iteration ``r``; with ``regions`` its ``trace_bound`` is over each node's region (the
    node average of tr Φ̄ there, where it reached a fixed point), its verdict the whole state's, as ``design`` judges
    a design of this rule."""
    trace = r.trace_bound
    if regions is not None and r.phi is not None:
        trace = float(np.mean(region_traces(r.phi, regions)))
    return {"feasible": int(r.feasible), "trace_bound": trace, "binding": r.binding,
            "theorem2": int(r.theorem2), "iterations": r.iterations, "verdict": point_verdict(r, open_loop, nodes)}


def stationary_open_loop(sc: Scenario) -> tuple[float, str]:
    """The open-loop reference of ``sc``'s map (:func:`designer.verdict.open_loop_reference` at the operating point,
    the scenario's horizon where ``F`` is not Schur stable)."""
    m = sc.model
    x0, u0 = sc.operating_point
    return open_loop_reference(m.F_expected(x0, 0, u0), m.process_cov, m.prior.cov, sc.steps)


def map_points(sc: Scenario, options: DesignOptions, points: Sequence[dict], *, batched: bool = True,
               lmi: bool = True, regions=None) -> list[dict]:
    """The rows (``OUTPUTS``) of the grid ``points`` (dicts of grid values) of ``sc``'s map for ``options``.

    ``batched``: every point's fixed-point iteration at once (:func:`designer.feasibility.steady_state_batch`);
    False: point by point (:func:`designer.feasibility.steady_state`), the same numbers, much more slowly.
    ``lmi`` False: a rule with a stationary certificate maps its fixed point without the LMI that confirms it (the
    automatic map's screening, :func:`auto_rows`).  ``regions`` (an automatic map of a model with ``REGIONS``): every
    row's ``trace_bound`` over each node's region, where the candidates are ranked as ``design --mode auto`` ranks
    them; each verdict stays the design's own (on the regions where its nodes carry them, else on the whole state).

    A point whose design cannot be built or whose iteration raises (an overflow, an eigenvalue problem that does
    not converge at an extreme value) is not feasible and has no bound; its ``binding`` is ``"failed: "`` and the
    error.  When a batch raises, its points are iterated one at a time (a batch's rows do not depend on each
    other), so that one extreme point does not take the others with it.
    """
    F, H, R, xp = _linearisation(sc)
    x0, u0 = sc.operating_point
    m = sc.model
    ol, _ = stationary_open_loop(sc)
    N = sc.network.n_nodes
    designed = [_design_at(sc, options, p) for p in points]
    ok = [d for d in designed if isinstance(d, tuple)]
    if rule_of(options).stationary_certificate:  # the design's own at each point
        res = iter([_scheduled_row(*item, lmi=lmi, regions=regions) for item in ok])
        return [d if isinstance(d, dict) else next(res) for d in designed]
    kw = dict(phi0=m.prior.cov, scaling=_scaling(m, ok[0][1], x0, u0, xp) if ok else None)

    def batch(items):
        des = [d for _, d in items]
        return steady_state_batch(F, H, m.process_cov, R, [s.network for s, _ in items],
                                  epsilon=[d.epsilon for d in des], delta=[d.delta for d in des],
                                  U=[d.U for d in des], V=[d.V for d in des],
                                  fixed_multipliers=des[0].rule.fixed_multipliers,
                                  sigma=[d.sigma for d in des], beta=[d.beta for d in des],
                                  tau=[d.tau for d in des], **kw)

    def one(item):
        s, d = item
        try:
            if batched:
                return _row(batch([item])[0], ol, N, regions)
            return _row(steady_state(F, H, m.process_cov, R, s.network, epsilon=d.epsilon, delta=d.delta, U=d.U,
                                     V=d.V, fixed_multipliers=d.rule.fixed_multipliers, sigma=d.sigma, beta=d.beta,
                                     tau=d.tau, fdi_span=d.fdi_span, **kw), ol, N, regions)
        except _POINT_ERRORS as exc:
            return _failed(exc)

    rows = None
    if batched and ok:
        try:
            rows = [_row(r, ol, N, regions) for r in batch(ok)]
        except _POINT_ERRORS:
            rows = None  # one of them raised: each point alone
    if rows is None:
        rows = [one(item) for item in ok]
    res = iter(rows)
    return [d if isinstance(d, dict) else next(res) for d in designed]


def _scheduled_row(sc: Scenario, design, *, lmi: bool = True, regions=None) -> dict:
    """A grid point of a rule with a stationary certificate (scheduled, relay): the stationary certificate that
    ``cfdesign design`` records for the same options (:func:`studies.consensus_design.stationary_record`), so that
    map and design agree by construction (a design whose nodes carry their regions judged on them, as its design
    is).  ``regions``: ``trace_bound`` over each node's region (:func:`map_points`)."""
    try:
        rec = stationary_record(sc, design, lmi=lmi, regions=regions)
    except _POINT_ERRORS as exc:
        return _failed(exc)
    tr = rec.get("region_trace") or rec["trace"]
    return {"feasible": int(rec["verdict"] not in ("infeasible", "not computed") and rec["converged"]),
            "trace_bound": float(np.mean(tr)) if tr else float("nan"),
            "binding": rec["reason"] or "none (a fixed point)", "theorem2": 0, "iterations": rec["iterations"],
            "verdict": rec["verdict"]}


def _linearisation(sc: Scenario):
    m = sc.model
    x0, u0 = sc.operating_point
    xp = m.f_expected(x0, 0, u0)
    F = m.F_expected(x0, 0, u0)
    H = [m.H(i, xp, 1) for i in range(m.n_sensors)]
    R = [m.measurement_cov(i) for i in range(m.n_sensors)]
    return F, H, R, xp


def _points(run_ids, seeds, *, ref: ScenarioRef, options: DesignOptions, points: Sequence[dict], local,
            candidates=None, regions=None) -> dict:
    """Runner task: the grid points ``run_ids`` (deterministic: the seeds are not used), batched; ``candidates``: an
    automatic map's (:func:`auto_rows`), ranked on ``regions`` when given."""
    sc, mine = ref.build(), [points[int(i)] for i in run_ids]
    if candidates is not None:
        rows = auto_rows(sc, candidates, mine, local, regions)
    else:
        name = effective(sc, options)[1].mode or rules.DEFAULT
        rows = [{**r, "rule": name, "better_than_local": int(_better(r, local))} for r in map_points(sc, options, mine)]
    return {k: np.array([r[k] for r in rows]) for k in OUTPUTS}


# ---------------------------------------------------------------------------------------------------------------
# The automatic map: at every point, the best certified candidate of the rules it maps.


@dataclass(frozen=True)
class MapCandidate:
    """One candidate design of an automatic map (``feasibility.json``'s ``candidates``): a rule and the options that
    set it apart (:func:`studies.auto.offered`), its messages and bytes per step (they do not depend on the grid's
    parameters), and whether it was mapped (``status`` ``'mapped'``, ``'cannot start'`` or ``'outside the budget'``,
    with the reason)."""

    rule: str
    options: dict
    design_options: DesignOptions
    messages: int
    bytes: int
    status: str
    reason: str | None = None

    @property
    def label(self) -> str:
        return label(self.rule, self.options)

    def record(self, picked: int) -> dict:
        return {"rule": self.rule, "label": self.label, "options": dict(self.options),
                "messages_per_step": self.messages, "bytes_per_step": self.bytes, "status": self.status,
                "reason": self.reason, "picked_points": picked}


def _better(row: dict, local) -> bool:
    """Whether a row's bound is below the nodes' local EKFs (:func:`studies.auto.below_local`, the test ``design
    --mode auto`` applies to its candidates)."""
    return below_local(float(row["trace_bound"]), local)


def _eligible(row: dict, local) -> bool:
    """A point's candidate that may be picked: certified and bounded (a fixed point), and better than the nodes
    alone."""
    return row["verdict"] == "certified" and bool(row["feasible"]) and _better(row, local)


def auto_rows(sc: Scenario, candidates: Sequence[MapCandidate], points: Sequence[dict], local,
              regions=None) -> list[dict]:
    """The automatic map's rows of ``points``: every mapped candidate's row (:func:`map_points`, the rules with a
    stationary certificate screened without their LMI), and at each point the pick as ``design --mode auto`` picks:
    among the eligible candidates (certified, bounded, below the local EKFs' ``local``) the smallest steady-state
    bound, within 1 % the fewest bytes then messages (:func:`studies.auto.best`).  A pick of a rule with a
    stationary certificate is mapped again with its LMI; when the LMI does not confirm it, the next is tried.  With
    no eligible candidate, the best of the others (certified first, then bounded, then the smallest bound) is the
    point's row, its verdict its own.  Each row names its candidate (``rule``) and says whether it is below the
    local EKFs (``better_than_local``).  With ``regions`` (a model with ``REGIONS``) the bounds and ``local`` are over
    each node's region (:func:`map_points`), as ``design --mode auto`` ranks its candidates."""
    mapped = [c for c in candidates if c.status == "mapped"]
    screened = [map_points(sc, c.design_options, points, lmi=False, regions=regions) for c in mapped]
    out = []
    for p, point in enumerate(points):
        rows = [s[p] for s in screened]
        confirmed = set()
        while True:
            j = best((k, rows[k]["trace_bound"], c.bytes, c.messages) for k, c in enumerate(mapped)
                     if _eligible(rows[k], local))
            if j is None:
                j = min(range(len(mapped)), key=lambda k: (
                    rows[k]["verdict"] != "certified", not rows[k]["feasible"],
                    rows[k]["trace_bound"] if np.isfinite(rows[k]["trace_bound"]) else np.inf,
                    mapped[k].bytes, mapped[k].messages))
            if j in confirmed or not rules.get(mapped[j].rule).stationary_certificate or \
                    rows[j]["verdict"] != "certified":
                break
            rows[j] = map_points(sc, mapped[j].design_options, [point], regions=regions)[0]  # with its LMI
            confirmed.add(j)
        out.append({**rows[j], "rule": mapped[j].label, "better_than_local": int(_better(rows[j], local))})
    return out


def _auto_candidates(sc: Scenario, options: DesignOptions, cap, cap_bytes, need) -> list[MapCandidate]:
    """The automatic map's candidates (:func:`studies.auto.offered`, the rules it maps), each checked as ``design``
    checks a candidate before computing: its memory (``need(options)``) and its design at the options without a grid
    value; a candidate refused only with what the user gave is the user's input (InputError), one refused with the
    rule's defaults too cannot start on this model; one outside the budget is listed, not mapped."""
    sc_eff = sc.with_attacks(**options.attack_overrides())
    model, net = sc_eff.model, sc_eff.network
    out = []
    for name, rule, cand, opts in offered(options, net, where=lambda r: r.mappable):
        msgs = int(net.messages_per_step(rule.rounds(net, opts.rounds)))
        row = dict(rule=name, options=dict(cand), design_options=opts, messages=msgs, bytes=0)
        made = []  # the design of the candidate's own options: the first check's, when it passes

        def check(o):
            memory.check(need(o))
            made.append(_design_at(sc, o, {}, strict=True))

        reason = refusal(check, name, cand, opts)
        if reason is not None:
            out.append(MapCandidate(**row, status="cannot start", reason=reason))
            continue
        designed = made[0]
        if isinstance(designed, dict):  # dos + fdi > 1 without a grid value: every candidate alike
            raise InputError("dos + fdi must be at most 1 (DoS and FDI never occur together)")
        nbytes = BYTES_PER_NUMBER * int(rule.payload(model, net, designed[1]))
        row["bytes"] = nbytes
        if (cap is not None and msgs > cap) or (cap_bytes is not None and nbytes > cap_bytes):
            out.append(MapCandidate(**row, status="outside the budget",
                                    reason=f"{msgs} messages and {nbytes} bytes per step"))
            continue
        out.append(MapCandidate(**row, status="mapped"))
    if not any(c.status == "mapped" for c in out):
        refused = [c for c in out if c.status == "cannot start"]
        if refused and len(refused) == len(out):
            raise InputError(refused[0].reason)
        raise InputError("no candidate of the rules the map maps fits the budget (--budget, --budget-bytes): "
                         + "; ".join(f"{c.label}: {c.reason}" for c in out))
    return out


@dataclass(frozen=True, eq=False)
class FeasibilityMap:
    """A feasibility map: one row per grid point (what ``cfdesign feasibility`` computes).

    Attributes
    ----------
    scenario : Scenario
    options : DesignOptions
        The effective design options at every point (the grid's values replace theirs).
    grids : list of (name, values)
    rows : list of dict
        Per point: the grid values, ``feasible`` (0/1), ``trace_bound`` (mean over nodes of the
        steady-state tr Φ, NaN when infeasible), ``binding`` (``"failed: <reason>"`` where the point's
        design or iteration raised: :attr:`failures`), ``theorem2``, ``iterations``, ``verdict`` (the
        stationary bound's verdict, :func:`point_verdict`), ``rule`` (the design mapped: the rule, or in an
        automatic map the point's pick), ``better_than_local`` (0/1: its bound below the local EKFs').
    references : dict
        ``centralized`` and ``local_mean``: the centralized and the nodes' local steady-state tr P.
    auto : dict or None
        An automatic map's ``candidates`` (:meth:`MapCandidate.record`, with the points each won) and ``budget``.
    runner : dict
        What the Monte Carlo runner computed and reused.
    """

    scenario: Scenario
    options: DesignOptions
    grids: list
    rows: list
    runner: dict
    invocation: dict | None = None
    references: dict | None = None  # the centralized and the local EKFs' steady-state tr P (node average)
    auto: dict | None = None  # an automatic map's candidates and budget

    @property
    def mode(self) -> str:
        """``'auto'`` or the rule mapped."""
        return self.options.mode or rules.DEFAULT

    @property
    def names(self) -> list[str]:
        return [n for n, _ in self.grids]

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(len(v) for _, v in self.grids)

    @property
    def feasible(self) -> np.ndarray:
        """Feasibility per point, shaped like the grid (first grid parameter first)."""
        return np.array([bool(r["feasible"]) for r in self.rows]).reshape(self.shape)

    @property
    def trace_bound(self) -> np.ndarray:
        return np.array([r["trace_bound"] for r in self.rows], dtype=float).reshape(self.shape)

    @property
    def verdict(self) -> np.ndarray:
        """The verdict per point (``certified``, ``vacuous``, ``infeasible``, ``not computed``), shaped like the grid;
        a point is bounded where it is feasible (a fixed point)."""
        return np.array([r["verdict"] for r in self.rows], dtype=object).reshape(self.shape)

    @property
    def certified(self) -> np.ndarray:
        """Whether each point is certified and bounded (the map's category ``certified``: a fixed point, finite and
        below the stationary open loop at every node), shaped like the grid."""
        return (self.verdict == "certified") & self.bounded

    @property
    def rule(self) -> np.ndarray:
        """The design mapped at each point (in an automatic map, the point's pick: ``"flood (rounds=3)"``), shaped
        like the grid."""
        return np.array([r["rule"] for r in self.rows], dtype=object).reshape(self.shape)

    @property
    def bounded(self) -> np.ndarray:
        """Whether each point's stationary recursion reached a fixed point (``feasible``: the claim ``bounded``)."""
        return np.array([bool(r["feasible"]) for r in self.rows]).reshape(self.shape)

    @property
    def verdict_counts(self) -> dict[str, int]:
        """How many points have each verdict."""
        return count_verdicts(r["verdict"] for r in self.rows)

    @property
    def failures(self) -> list[dict]:
        """The rows of the points whose design or iteration raised (``binding`` ``"failed: <reason>"``)."""
        return [r for r in self.rows if str(r["binding"]).startswith(FAILED)]

    def save(self, directory) -> Path:
        """Write ``feasibility.csv``, ``feasibility.json``, ``feasibility.png`` and the reports into ``directory``
        (:func:`studies.outputs.save_map`: replacing the directory's last outputs as a whole,
        :func:`designer.fileio.replaced_outputs`; refused when it is, lies inside or contains the model's files:
        :func:`designer.fileio.check_apart`)."""
        from .outputs import save_map

        return save_map(self, directory)

    def record(self) -> dict:
        """The content of ``feasibility.json`` (schema ``cfdesign.feasibility/1``): the grids, the options, the counts
        of feasible and failed points and of each verdict, the open-loop reference, the operating point, the network,
        the attacks, observability, the Kalman references, the assumptions, the runner and the software versions."""
        from designer.design import DESIGN_ASSUMPTIONS
        from designer.observability import kalman_references, observability

        from .results import versions

        sc = self.scenario
        return {
            "schema": "cfdesign.feasibility/1", "scenario": sc.name, "source": sc.source,
            "state_names": list(sc.model.state_names),
            "grids": [{"name": n, "values": v.tolist()} for n, v in self.grids],
            "options": self.options.as_dict(), "points": len(self.rows),
            "feasible_points": int(sum(r["feasible"] for r in self.rows)), "failed_points": len(self.failures),
            "verdicts": self.verdict_counts, "open_loop": _open_loop_record(sc),
            "operating_point": {"x0": sc.operating_point[0].tolist(),
                                "u0": None if sc.operating_point[1] is None else sc.operating_point[1].tolist()},
            "network": sc.network.describe(), "attacks": sc.resolved_attacks.describe(sc.model.state_names),
            "observability": observability(sc.model, *sc.operating_point),
            "kalman_references": kalman_references(sc.model, *sc.operating_point),
            "assumptions": list(sc.assumptions) + list(DESIGN_ASSUMPTIONS) + list(VERDICT_ASSUMPTIONS),
            "runner": self.runner, "references": self.references,
            **({} if self.auto is None else self.auto),
            "invocation": self.invocation, "versions": versions(),
        }


def run_feasibility(sc: Scenario, grids: Sequence[str], options: DesignOptions | None = None, *,
                    backend: Backend | None = None, store=None, force: bool = False,
                    quiet: bool = False, budget=None, budget_bytes: int | None = None) -> FeasibilityMap:
    """Compute the feasibility map of ``sc`` over ``grids`` (``NAME=START:STOP:COUNT`` strings).

    Mode ``auto`` (the default, unless the model's ``DESIGN`` names a rule): at every point the best eligible
    candidate of the rules the map maps (:func:`auto_rows`), inside ``budget`` (messages per step, or ``"kcf"``) and
    ``budget_bytes`` (bytes per step) as ``design --mode auto`` counts them."""
    from designer.observability import kalman_references

    if isinstance(grids, str):
        grids = [grids]
    if not isinstance(grids, (list, tuple)):
        raise InputError(f"grid must be a string NAME=START:STOP:COUNT or a list of them, got {type(grids).__name__}")
    check_strings("grid", grids, "'NAME=START:STOP:COUNT' strings")
    if not grids:
        raise InputError("give at least one --grid NAME=START:STOP:COUNT")
    specs = [_grid_spec(g) for g in grids]
    names = [n for n, *_ in specs]
    if len(set(names)) != len(names):
        raise InputError("each --grid parameter may be given once")
    options = options or DesignOptions()
    auto = (options.mode or (sc.design.mode if sc.design is not None else None) or AUTO) == AUTO
    if not auto and (budget is not None or budget_bytes is not None):
        raise InputError("budget and budget_bytes are options of mode 'auto' (the automatic map), not of mode "
                         f"{options.mode or sc.design.mode!r}")
    if auto:
        base = replace(options, mode=None)
        cap, budget_bytes, _, _ = check_auto(sc, budget, budget_bytes)  # the network, the budget
        sc_eff, opts = sc.with_attacks(**base.attack_overrides()), replace(base, mode=AUTO)
        bad = [n for n in names if n in _PAPER_ONLY]
        if bad:
            raise InputError(f"--grid {bad[0]} applies to a mode of fixed multipliers only (mode auto chooses among "
                             "rules; give --mode paper to map it)")
    else:
        sc_eff, opts = effective(sc, options)
        mode = opts.mode or rules.DEFAULT
        rule = rules.get(mode)
        if not rule.mappable:
            raise InputError(f"mode {mode!r} is not mapped yet: its gains come from the joint error covariance of a "
                             "run (use cfdesign design or a study); feasibility maps every other mode")
        bad = [n for n in names if n in _PAPER_ONLY and not rule.fixed_multipliers]
        if bad:
            raise InputError(f"--grid {bad[0]} applies to a mode of fixed multipliers only (the {mode} design "
                             "chooses it itself)")
    d_max = max(sc_eff.network.d_max, 1)
    for n, start, stop, count in specs:
        top = float(max(start, stop) if count > 1 else start)
        if n == "epsilon" and top >= 1.0 / d_max:
            raise InputError(f"--grid epsilon must lie in (0, 1/d_max) = (0, {1.0 / d_max:.6g}), got up to {top:g}")
    if backend is not None and backend.kind == "dask" and sc.source is None:
        raise InputError("an in-memory model cannot be sent to a Dask cluster; write it to a model file")
    n_points = math.prod(c for *_, c in specs)
    chunk = AUTO_CHUNK_SIZE if auto else CHUNK_SIZE

    def need(o):
        return memory.feasibility_need(sc, o, n_points, len(specs), chunk, backend)

    candidates = None
    if auto:
        candidates = _auto_candidates(sc, base, cap, budget_bytes, need)
    else:
        memory.check(need(options))
        _design_at(sc, options, {}, strict=True)  # the options' own errors: bad input, before any point
    x0, u0 = sc_eff.operating_point
    # on a model with REGIONS: an automatic map ranks every candidate on the regions, whatever its nodes carry (as
    # design --mode auto), a map of one rule whose nodes carry their regions judges them there (as its design); the
    # references on the same states
    regions = None
    if sc_eff.regions is not None and (auto or opts.carry == "region"):
        regions = sc_eff.regions
    refs = kalman_references(sc_eff.model, x0, u0, regions)
    c_ref, l_ref = references(refs)
    parsed = [(n, _grid_values(start, stop, count)) for n, start, stop, count in specs]
    points = [dict(zip(names, map(float, combo))) for combo in itertools.product(*[v for _, v in parsed])]
    ref = reference(sc)
    if backend is None or backend.kind != "dask":
        ref.build()  # here, once: the chunks computed in this process and forked workers use it
    if backend is not None and backend.kind == "processes":
        from designer.tuning import load_kernels

        load_kernels()  # once, before the workers are forked, rather than in every worker
    task = functools.partial(_points, ref=ref, options=opts if auto else options, points=points, local=l_ref,
                             candidates=candidates, regions=regions if auto else None)
    config = {"study": "feasibility", "scenario": sc.name, "model": ref.digest,
              "grids": [[n, v.tolist()] for n, v in parsed], "options": opts.as_dict() if auto else options.as_dict(),
              "params": dict(ref.params), "attacks": sc.attacks.describe(),
              "ranked_on": "the whole state" if regions is None else "each node's region"}
    if auto:
        config["candidates"] = [[c.label, c.status] for c in candidates]
    mc = monte_carlo(task, runs=len(points), seed=0, chunk_size=chunk, backend=backend, store=store,
                     label="feasibility", config=config, force=force, quiet=quiet, unit="grid points")
    a = mc.arrays
    rows = [{**p, "feasible": int(a["feasible"][i]), "trace_bound": float(a["trace_bound"][i]),
             "binding": str(a["binding"][i]), "theorem2": int(a["theorem2"][i]),
             "iterations": int(a["iterations"][i]), "verdict": str(a["verdict"][i]), "rule": str(a["rule"][i]),
             "better_than_local": int(a["better_than_local"][i])} for i, p in enumerate(points)]
    auto_record = None
    if auto:
        picked = collections.Counter(r["rule"] for r in rows)
        auto_record = {"candidates": [c.record(picked.get(c.label, 0) if c.status == "mapped" else 0)
                                      for c in candidates],
                       "budget": budget_record(sc_eff.network, cap, budget, budget_bytes)}
    return FeasibilityMap(sc_eff, opts, parsed, rows, mc.describe(), feasibility_invocation(sc, grids, options),
                          references={"centralized": json_number(c_ref), "local_mean": json_number(l_ref),
                                      "over": "the whole state" if regions is None else "each node's region"},
                          auto=auto_record)
