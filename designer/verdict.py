"""What a consensus design's bound is worth, in the papers' two senses: the home of the verdicts (``certified``,
``vacuous``, ``infeasible``, ``not computed``), of the separate claim ``bounded`` with its ``growing`` qualifier, and
of the one test of "informative" and the one window "after the prior's transient" that the design and the studies
share.

Conditions (28)-(29) holding (``feasible``) say only that Theorem 1's bound Φ exists; a bound of 1e46 exists too.
:func:`verdict` judges the bound itself, from nothing but its trajectory (tr Φ per node and step), its feasibility
and the references; it does not know the design mode, so every gain rule is judged alike.  The verdict is Theorem
1's kind of claim (a bound at every step):

``not computed``
    The certificate was not computed (the caller's ``not_computed`` reason, e.g. a stacked error beyond the size
    the scheduled certificate is computed for); never ``infeasible`` for that.
``infeasible``
    (28)/(29) failed or a node diverged somewhere (the caller's ``feasible`` is False).
``vacuous``
    Some node's tr Φ is at or above the trace of the **open-loop covariance** at the same step, or is not finite,
    at some step of the horizon, 1..K, the transient from the prior included (:func:`informative`): the prior
    covariance propagated through the linearised dynamics with the process noise and no measurement,
    ``P_{k+1} = F P_k Fᵀ + Q``, ``P_0 = P0``, at the same step (like with like: the same node-step trace).  Such a
    bound says less than ignoring every sensor does.
``certified``
    Feasible, finite and informative (below the open loop) at every node and every step of the horizon.

A separate claim, Theorem 2's kind, is **bounded** (:attr:`Verdict.bounded`): the bound is steady, or it is a
converged fixed point (``fixed_point=True``).  Steady: at every node the median tr Φ over the last window of
``W = max(2, ceil(K / 4))`` steps exceeds the median over the ``W`` steps before by at most
:data:`GROWTH_TOLERANCE` (5 %); the two windows are the steps after the prior's transient
(:func:`settled_steps`).  The medians ignore the isolated steps where a burst of lost packets lifts the bound
(window maxima would call such a bound growing whenever a burst falls in the last window); a bound growing
geometrically by a factor λ per step shows ``λ^W - 1``.  Not bounded: still growing, a horizon too short to show
it (``K < 2 W``, fewer than 4 steps), or no fixed point reached.  **growing** (:attr:`Verdict.growing`) qualifies
a certificate whose bound still rises at the horizon at some node by more than the tolerance: "certified, still
growing at the horizon" is a certificate over the horizon, not a failure.

The numbers behind the verdict (:attr:`Verdict.detail`) put every node's final tr Φ against the open-loop trace,
the centralized and the node's own local steady-state Kalman filter (the Riccati equation of python-control's
``dlqe``, :func:`designer.observability.kalman_references`), as ratios.

A feasibility map judges a *stationary* bound (the fixed point of the recursion at an operating point,
``fixed_point=True``: bounded by its iteration's convergence test), and compares it with the stationary open-loop
covariance (:func:`open_loop_reference`: the solution of the discrete Lyapunov equation when ``F`` is Schur stable,
else the open-loop covariance at the scenario's horizon, which grows without limit).

Every threshold the issue leaves open is stated in :data:`VERDICT_ASSUMPTIONS`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["VERDICTS", "RETIRED_VERDICTS", "known_verdict", "GROWTH_TOLERANCE", "WINDOW_FRACTION", "MIN_WINDOW",
           "VERDICT_ASSUMPTIONS", "GATE_CLAUSE", "NOT_COMPUTED", "Verdict", "verdict", "describe", "count_verdicts",
           "steadiness_window", "settled_steps", "informative", "open_loop_traces", "open_loop_reference",
           "json_number"]

VERDICTS = ("certified", "vacuous", "infeasible", "not computed")
#: The verdict of a certificate that was not computed; also the ``condition`` of the record a design's violations
#: carry for it (a design's own words, never a violation of (28)-(29)), and, with a colon, how the reason of a
#: stationary certificate not computed starts (:class:`designer.stationary.StationaryCertificate`).
NOT_COMPUTED = VERDICTS[3]
#: Verdicts of earlier versions that a file may still hold, shown as they were when read (``not steady``: the
#: bound still grew at the horizon, now the ``growing`` qualifier and ``bounded`` false).
RETIRED_VERDICTS = ("not steady",)
GROWTH_TOLERANCE = 0.05  # relative growth of the window median a steady bound may show
WINDOW_FRACTION = 0.25  # the last quarter of the horizon against the quarter before it
MIN_WINDOW = 2  # steps per window: a horizon of fewer than 2 x 2 steps cannot show steadiness
STABLE = 1.0 - 1e-9  # spectral radius below which F is Schur stable (a stationary open-loop covariance exists)

VERDICT_ASSUMPTIONS = (
    "verdict: a feasible bound is certified when, at every node and every step 1..K of the horizon (the transient "
    "from the prior included: Theorem 1 claims a bound at every step), tr Phi is finite and below the trace of the "
    "open-loop covariance at the same step (the prior covariance propagated by P <- F P F^T + Q with F the "
    "linearisation at the operating point, no measurement); else it is vacuous. A certificate that was not "
    "computed is 'not computed' with the reason, never infeasible.",
    f"verdict: 'bounded' is a separate claim (the bound settles): the bound is steady, i.e. at every node the "
    f"median tr Phi over the last W = max({MIN_WINDOW}, ceil({WINDOW_FRACTION:g} K)) steps of the K-step horizon "
    f"exceeds the median over the W steps before by at most {GROWTH_TOLERANCE:.0%} (a horizon shorter than "
    f"{2 * MIN_WINDOW} steps cannot show it), or it is a converged fixed point of the stationary recursion. A "
    "certified bound whose median still rises by more than that is reported 'certified, still growing at the "
    "horizon': a certificate over the horizon, not bounded.",
    "verdict: the last 2 W steps of the horizon are the steps after the prior's transient: the design's growth "
    "test and the studies' tightness (fill) are computed over them.",
    "verdict: a feasibility map's stationary bound is compared with the stationary open-loop covariance (discrete "
    "Lyapunov equation) when F is Schur stable (spectral radius < 1 - 1e-9), else with the open-loop covariance at "
    "the scenario's horizon.",
    "verdict: the centralized and local references are the steady-state Kalman filters (the Riccati equation of "
    "python-control dlqe) of the "
    "linearisation at the operating point; they are reported as ratios and decide no verdict.",
)

# With a chi-square gate the packets a node keeps depend on the errors: Theorem 1's bound is not proven for them.
GATE_CLAUSE = "with the chi-square gate the bound is a model validated by Monte Carlo only, not a proof"


def json_number(v) -> float | None:
    """A JSON number: None where not finite (JSON has no NaN nor infinity; what every record writes for them)."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


@dataclass(frozen=True)
class Verdict:
    """The verdict on a bound, its boundedness and the numbers behind them.

    Attributes
    ----------
    verdict : str
        One of :data:`VERDICTS`.
    reason : str or None
        Why the bound is not certified, naming the condition and the node(s); None when certified.
    nodes : list of int
        The nodes that prevent certification (empty when certified, infeasible or not computed).
    bounded : bool
        Theorem 2's kind of claim: steady by the window test, or a converged fixed point.
    growing : bool
        Some node's window median still rises by more than :data:`GROWTH_TOLERANCE` at the horizon (a qualifier
        of the certificate, not a failure).
    bounded_reason : str or None
        Why the bound is not bounded, in words; None when bounded.
    detail : dict
        JSON-ready: ``horizon``, ``fixed_point``, ``final_trace`` (per node), ``open_loop_trace`` (at the
        horizon) and ``open_loop`` (how it was computed), ``centralized``, ``local``, ``ratio_open_loop``,
        ``ratio_centralized``, ``ratio_local`` (per node, of the final tr Φ), ``judged_steps`` (first and last
        step judged for informativeness: the whole horizon), ``max_ratio_open_loop`` (per node, the largest
        tr Φ / open-loop trace over them: the vacuity measure), ``settled_steps`` (the steps after the prior's
        transient, :func:`settled_steps`), ``growth`` (per node, the steadiness measure), ``window``,
        ``tolerance``, ``open_loop_exceeded`` (node-steps at or above the open loop), ``nodes``, ``reason``,
        ``verdict``, ``bounded``, ``growing``, ``bounded_reason`` and ``bounded_by`` (``steady``, ``fixed point``
        or, for a design, ``stationary certificate``; None when not bounded).
    """

    verdict: str
    reason: str | None
    nodes: list = field(default_factory=list)
    detail: dict = field(default_factory=dict)
    bounded: bool = False
    growing: bool = False
    bounded_reason: str | None = None

    @property
    def certified(self) -> bool:
        return self.verdict == "certified"


def known_verdict(value) -> str:
    """``value`` when it is one of :data:`VERDICTS` or :data:`RETIRED_VERDICTS` (an older file's word, shown as it
    was), else ``"unknown"``: a verdict read from a file (a design directory's ``schedule.json``) as a word of this
    vocabulary, never as the file's text."""
    return value if isinstance(value, str) and value in VERDICTS + RETIRED_VERDICTS else "unknown"


def steadiness_window(horizon: int) -> int:
    """``W = max(MIN_WINDOW, ceil(WINDOW_FRACTION * horizon))``: the steps of each of the two compared windows."""
    return max(MIN_WINDOW, math.ceil(WINDOW_FRACTION * horizon))


def settled_steps(horizon: int) -> slice:
    """The steps after the prior's transient of a ``horizon``-step trajectory, as a slice of its columns (column
    ``j`` is step ``j + 1``): the last ``2 W`` steps (:func:`steadiness_window`), the whole horizon when it is
    shorter.  The design's growth test compares their two halves; the studies' tightness (``fill``) is computed
    over them."""
    return slice(max(0, horizon - 2 * steadiness_window(horizon)), horizon)


def informative(trace, open_loop) -> np.ndarray:
    """Per node: whether the bound ``trace`` (nodes, T: tr Φ per node and step) is informative at every step, i.e.
    finite and below ``open_loop`` (the open-loop covariance's trace at the same steps, (T,), one number for
    every step, or (nodes, T) one row per node: each node's own states, when the nodes are judged on their regions)
    at each of them.  A step where the bound is not finite (inf, or NaN: no bound claimed) is not
    informative; an open loop that overflowed (inf) makes any finite bound informative there.  The one test of
    "informative" of :func:`verdict` and of the studies' bound check."""
    trace = np.atleast_2d(np.asarray(trace, dtype=float))
    ol = np.asarray(open_loop, dtype=float)
    ol = np.broadcast_to(ol, trace.shape if ol.ndim == 2 else trace.shape[-1:])
    with np.errstate(invalid="ignore"):
        return np.all(np.isfinite(trace) & (trace < ol), axis=-1)


def _growth(trace: np.ndarray) -> tuple[np.ndarray | None, int]:
    """Per node: median tr Φ over the last window / median over the window before - 1 (None: horizon too short);
    the two windows are :func:`settled_steps`."""
    K = trace.shape[1]
    W = steadiness_window(K)
    if K < 2 * W:
        return None, W
    settled = trace[:, settled_steps(K)]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        g = np.median(settled[:, W:], axis=1) / np.median(settled[:, :W], axis=1) - 1.0
    return np.where(np.isfinite(g), g, np.inf), W


def _ratios(values, ref) -> list | None:
    """``values / ref`` as JSON numbers (None where not finite); None when there is no reference.  ``ref`` one
    number, or one per value (None where that value has none)."""
    if ref is not None and np.ndim(ref) == 1:
        return [None if r is None or not float(r) > 0 else json_number(v / float(r)) for v, r in zip(values, ref)]
    if ref is None or not float(ref) > 0:
        return None
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        return [json_number(v / float(ref)) for v in values]


def _boundedness(growth: np.ndarray | None, W, T: int, fixed_point: bool | None) -> tuple[bool, bool, str | None]:
    """``(bounded, growing, bounded_reason)`` from the steadiness measure (module docstring)."""
    if fixed_point is not None:
        return (True, False, None) if fixed_point else (
            False, False, "the stationary bound recursion did not reach a fixed point")
    if growth is None:
        return False, False, (f"the horizon of {T} step{'s' * (T != 1)} is too short to show a steady bound (at least "
                              f"{2 * MIN_WINDOW} steps are needed)")
    grow = np.flatnonzero(~(growth <= GROWTH_TOLERANCE))
    if not grow.size:
        return True, False, None
    worst = int(grow[np.argmax(growth[grow])])
    more = f"{grow.size} of {growth.size} nodes; " if grow.size > 1 else ""
    g = growth[worst]
    above = f"{g:.1%} above" if g < 10 else f"{g + 1:.3g} x"  # a percentage of 20 digits says less than a factor
    return False, True, (f"node {worst}'s median tr Φ over the last {W} of {T} steps is {above} that over the {W} "
                         f"steps before ({more}a steady bound grows by at most {GROWTH_TOLERANCE:.0%})")


def verdict(trace, open_loop, *, feasible: bool, centralized: float | None = None,
            local: Sequence[float | None] | None = None, fixed_point: bool | None = None,
            infeasible_reason: str | None = None, open_loop_how: str = "",
            not_computed: str | None = None) -> Verdict:
    """The verdict on a bound and its boundedness (see the module docstring for the tests and their order).

    Parameters
    ----------
    trace : array (nodes, T)
        tr Φ per node and step: a design's ``tr Φ_{k|k}`` for k = 1..K (T = K), or, with
        ``fixed_point``, one column: the stationary bound.
    open_loop : float, array (T,) or (nodes, T)
        The open-loop covariance's trace at the same steps (:func:`open_loop_traces`), or the
        stationary reference (:func:`open_loop_reference`); one number applies to every step; one row per node
        when each node is judged on its own states (its region, :mod:`designer.regions`).
    feasible : bool
        Whether (28)-(29) held everywhere and no node diverged.
    centralized, local
        The centralized (one number, or one per node on its own states) and per-node local steady-state tr P (None
        where none exists): reported as ratios.
    fixed_point : bool or None
        None: ``trace`` is a trajectory, bounded by the window test.  True: it is the converged
        fixed point of the stationary recursion (bounded).  False: the stationary iteration did
        not converge (not bounded; ``trace`` its last iterate, NaN where there is none).
    infeasible_reason : str, optional
        The caller's words for why (28)/(29) failed (the first violation).
    open_loop_how : str
        How ``open_loop`` was computed (recorded in the detail).
    not_computed : str, optional
        Why the certificate was not computed: the verdict is then ``not computed`` with this reason, whatever
        ``feasible`` says.

    Notes
    -----
    A trajectory is judged for informativeness at every step 1..K (:func:`informative`): Theorem 1 claims its
    bound at every step, the transient from the prior included.  The growth test looks at the steps after the
    transient only (:func:`settled_steps`).
    """
    trace = np.atleast_2d(np.asarray(trace, dtype=float))
    N, T = trace.shape
    per_node = np.ndim(open_loop) == 2
    ol = np.array(np.broadcast_to(np.asarray(open_loop, dtype=float), (N, T) if per_node else (T,)))
    final, ol_final = trace[:, -1], ol[..., -1]
    if fixed_point is None:
        growth, W = _growth(trace)
        settled = settled_steps(T)
    else:
        growth, W, settled = (np.zeros(N) if fixed_point else None), None, None
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ratio = np.where(np.isinf(ol), 0.0, trace / ol)  # a finite bound against an open loop that overflowed: 0
        ratio = np.where(np.isinf(trace), np.inf, ratio)
        exceeded = int(np.sum(ratio >= 1.0))
    worst_ratio = np.where(np.isnan(ratio), np.inf, ratio).max(axis=1)  # per node, over every step (NaN: no bound)
    local = list(local) if local is not None else [None] * N
    bounded, growing, bounded_reason = _boundedness(growth, W, T, fixed_point)
    detail: dict[str, Any] = {
        "horizon": None if fixed_point is not None else T,
        "fixed_point": fixed_point is not None,
        "final_trace": [json_number(v) for v in final],
        "open_loop_trace": [json_number(v) for v in ol_final] if per_node else json_number(ol_final),
        "open_loop": open_loop_how or "the prior covariance propagated by P <- F P F^T + Q, no measurement",
        "centralized": ([json_number(v) for v in centralized] if np.ndim(centralized) == 1
                        else json_number(centralized)),
        "local": [json_number(v) for v in local],
        "ratio_open_loop": [json_number(v) for v in ratio[:, -1]],
        "ratio_centralized": _ratios(final, centralized),
        "ratio_local": [(_ratios([f], r) or [None])[0] for f, r in zip(final, local)],
        "judged_steps": None if fixed_point is not None else [1, T],
        "max_ratio_open_loop": [json_number(v) for v in worst_ratio],
        "settled_steps": None if settled is None else [settled.start + 1, T],
        "growth": None if growth is None else [json_number(g) for g in growth],
        "window": W,
        "tolerance": GROWTH_TOLERANCE,
        "open_loop_exceeded": exceeded if fixed_point is None else None,
    }
    if not_computed is not None:
        out = Verdict("not computed", not_computed)
        bounded, growing, bounded_reason = False, False, "the certificate was not computed"
    elif not feasible:
        out = Verdict("infeasible", infeasible_reason or "(28)/(29) failed or a node diverged")
        bounded, growing, bounded_reason = False, False, "infeasible"
    else:
        vac = np.flatnonzero(~informative(trace, ol))
        if vac.size:
            worst = int(vac[np.argmax(worst_ratio[vac])])
            row = np.where(np.isnan(ratio[worst]), np.inf, ratio[worst])
            j = int(np.argmax(row))
            f = trace[worst, j]
            if fixed_point is not None:
                where, ol_words = "at the fixed point", "the stationary open-loop covariance's trace"
            else:
                where, ol_words = f"at step {j + 1}", "the open-loop covariance's trace at that step"
            if fixed_point is False and np.isnan(f):
                words = f"node {worst} has no stationary bound (the recursion did not reach a fixed point)"
            elif np.isnan(f):
                words = f"node {worst} claims no bound {where}"
            elif not np.isfinite(f):
                if fixed_point is None:  # where it stopped being finite (an overflow)
                    where = f"from step {int(np.argmax(np.isinf(trace[worst]))) + 1} on (it overflowed)"
                words = f"node {worst}'s tr Φ is not finite {where}"
            else:
                o = float(ol[worst, j] if per_node else ol[j])
                words = f"node {worst}'s tr Φ {f:.4g} {where} is {f / o:.3g} x {ol_words}, {o:.4g}"
            more = f" ({vac.size} of {N} nodes)" if vac.size > 1 else ""
            out = Verdict("vacuous", f"{words}{more}", [int(i) for i in vac])
        else:
            out = Verdict("certified", None)
    detail.update({"verdict": out.verdict, "reason": out.reason, "nodes": out.nodes, "bounded": bounded,
                   "growing": growing, "bounded_reason": bounded_reason,
                   "bounded_by": None if not bounded else "fixed point" if fixed_point else "steady"})
    return Verdict(out.verdict, out.reason, out.nodes, detail, bounded, growing, bounded_reason)


def count_verdicts(verdicts) -> dict[str, int]:
    """How many of ``verdicts`` (names of :data:`VERDICTS`) are each verdict, in the order of :data:`VERDICTS`."""
    verdicts = list(verdicts)
    return {v: verdicts.count(v) for v in VERDICTS}


def describe(detail: Mapping) -> str:
    """The verdict of ``detail`` (:attr:`Verdict.detail`, or ``verdict_detail`` read from a file) in one sentence:
    both claims (certified or why not; bounded, still growing, or why not), and the final bound against the open
    loop and the Kalman references.  A file written before ``bounded`` existed is described without it."""

    def top(key):
        r = [x for x in detail.get(key) or [] if x is not None]
        return max(r) if r else None

    v = detail.get("verdict")
    W, K = detail.get("window"), detail.get("horizon")
    fixed = bool(detail.get("fixed_point"))
    if v == "certified":
        ol, judged = top("max_ratio_open_loop"), detail.get("judged_steps")
        where = "" if fixed or not judged else f" over steps {judged[0]}..{judged[1]}"
        text = (f"certified{', still growing at the horizon' if detail.get('growing') else ''}: the bound is finite "
                "and informative at every step")
        if ol is not None:
            text += (f" (at most {ol:.3g} x the {'stationary ' if fixed else ''}open-loop covariance's trace at every "
                     f"node{where})")
    else:
        text = f"not certified ({v}): {detail.get('reason')}"
    if "bounded" in detail and v not in ("infeasible", NOT_COMPUTED):
        g, by = top("growth"), detail.get("bounded_by")
        if detail["bounded"]:
            text += "; bounded: " + (
                "a fixed point" if by == "fixed point" or fixed else
                "its stationary certificate is a fixed point with its LMI confirmed, below the stationary open loop"
                if by == "stationary certificate" else
                f"steady (median over the last {W} of {K} steps at most {max(g or 0.0, 0.0):.1%} above the {W} "
                "before)")
        else:
            text += f"; not bounded: {detail.get('bounded_reason')}"
    final = top("final_trace")
    if final is not None and v not in ("infeasible", NOT_COMPUTED):
        refs = [f"{r:.3g} x {words}" for r, words in (
            (top("ratio_open_loop") if v != "certified" else None, "the open loop"),
            (top("ratio_centralized"), "the centralized steady-state tr P"),
            (top("ratio_local"), "a node's own local one, at most")) if r is not None]
        text += (f"; {'at the fixed point' if fixed else f'at step {K}'} the largest tr Φ is {final:.4g}"
                 + (f" ({', '.join(refs)})" if refs else ""))
        if detail.get("judged") == "region":
            text += (" (each node judged on its region, which it carries with the states its measurements need: "
                     "the open loop and the references on the same states)")
        region = detail.get("region")
        ratios = [r for r in ((region or {}).get("ratio_centralized") or []) if r is not None]
        if ratios and detail.get("judged") != "region":
            text += (f"; on each node's region, tr Φ is {float(np.median(ratios)):.3g} x the centralized "
                     f"steady-state tr P on the same states at the median node, {max(ratios):.3g} x at most")
    return text


def open_loop_traces(F: np.ndarray, Q: np.ndarray, P0: np.ndarray, steps: int, regions=None) -> np.ndarray:
    """``tr P_k`` for k = 1..steps of ``P_{k+1} = F P_k Fᵀ + Q``, ``P_0 = P0`` (inf once it overflows); with
    ``regions`` (one index array per node) (nodes, steps), ``P_k`` traced over each node's region."""
    F, Q, P = (np.asarray(a, dtype=float) for a in (F, Q, P0))
    out = np.empty(steps if regions is None else (len(regions), steps))
    with np.errstate(over="ignore", invalid="ignore"):
        for k in range(steps):
            P = F @ P @ F.T + Q
            d = np.diagonal(P)
            t = float(np.trace(P)) if regions is None else np.array([d[r].sum() for r in regions])
            if not np.all(np.isfinite(t)):
                out[..., k:] = np.inf
                break
            out[..., k] = t
    return out


def open_loop_reference(F: np.ndarray, Q: np.ndarray, P0: np.ndarray, horizon: int, regions=None) -> tuple:
    """The stationary open-loop covariance's trace and how it was obtained (with ``regions``, one index array per
    node, one trace per node over its region).

    Schur-stable ``F`` (spectral radius < 1 - 1e-9): the solution of ``P = F P Fᵀ + Q``
    (``scipy.linalg.solve_discrete_lyapunov``).  Otherwise no stationary covariance exists and
    the open-loop covariance at ``horizon`` steps from ``P0`` is used (inf once it overflows).
    """
    from scipy.linalg import solve_discrete_lyapunov

    F, Q = np.asarray(F, dtype=float), np.asarray(Q, dtype=float)
    rho = float(np.max(np.abs(np.linalg.eigvals(F)))) if F.size else 0.0
    if rho < STABLE:
        d = np.diagonal(solve_discrete_lyapunov(F, Q))
        tr = float(d.sum()) if regions is None else [float(d[r].sum()) for r in regions]
        return tr, (f"stationary open-loop covariance (discrete Lyapunov equation; F Schur stable, "
                    f"spectral radius {rho:.4g})")
    tr = open_loop_traces(F, Q, P0, horizon, regions)[..., -1]
    return (float(tr) if regions is None else [float(v) for v in tr]), (
        f"open-loop covariance at the horizon of {horizon} steps from the prior (F not Schur stable, "
        f"spectral radius {rho:.4g}: no stationary covariance)")
