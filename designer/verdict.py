"""What a consensus design's bound is worth: ``certified``, ``vacuous``, ``not steady`` or ``infeasible``.

Conditions (28)-(29) holding (``feasible``) say only that Theorem 1's bound Φ exists; a bound
of 1e46, or one still doubling at the end of the run, exists too.  :func:`verdict` judges the
bound itself, from nothing but its trajectory (tr Φ per node and step), its feasibility and
the references; it does not know the design mode, so every gain rule is judged alike:

``infeasible``
    (28)/(29) failed or a node diverged somewhere (the caller's ``feasible`` is False).
``vacuous``
    Some node's tr Φ is at or above the trace of the **open-loop covariance** (or is not
    finite) at some step of the judged part of the horizon (the last ``2 W`` steps, the two
    windows below): the prior covariance propagated through the linearised dynamics with the
    process noise and no measurement, ``P_{k+1} = F P_k Fᵀ + Q``, ``P_0 = P0``, at the same step
    (like with like: the same node-step trace).  Such a bound says less than ignoring every
    sensor does.
``not steady``
    Some node's bound is still growing at the horizon: the median tr Φ over the last window
    of ``W = max(2, ceil(K / 4))`` steps exceeds the median over the ``W`` steps before by
    more than :data:`GROWTH_TOLERANCE` (5 %), or the horizon (``K < 2 W``, i.e. fewer than 4
    steps) is too short to show it is not.  A bound that converged or decays counts as steady,
    and so does one in a stationary random regime: the medians ignore the isolated steps where
    a burst of lost packets lifts the bound (window maxima would call such a bound growing
    whenever a burst falls in the last window).  A bound growing geometrically by a factor λ
    per step shows ``λ^W - 1``.
``certified``
    Feasible, finite, steady and below the open-loop covariance at every node.

The verdicts are checked in that order (a bound above the open loop is called vacuous even
while it still grows).  The numbers behind the verdict (:attr:`Verdict.detail`) put every
node's final tr Φ against the open-loop trace, the centralized and the node's own local
steady-state Kalman filter (the Riccati equation of python-control's ``dlqe``,
:func:`designer.observability.kalman_references`),
as ratios.

A feasibility map judges a *stationary* bound (the fixed point of the recursion at an
operating point, ``fixed_point=True``): it is steady by its iteration's convergence test, and
it is compared with the stationary open-loop covariance (:func:`open_loop_reference`: the
solution of the discrete Lyapunov equation when ``F`` is Schur stable, else the open-loop
covariance at the scenario's horizon, which grows without limit).

Every threshold the issue leaves open is stated in :data:`VERDICT_ASSUMPTIONS`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["VERDICTS", "known_verdict", "GROWTH_TOLERANCE", "WINDOW_FRACTION", "MIN_WINDOW", "VERDICT_ASSUMPTIONS",
           "GATE_CLAUSE", "Verdict", "verdict", "describe", "count_verdicts", "steadiness_window", "open_loop_traces",
           "open_loop_reference", "json_number"]

VERDICTS = ("certified", "vacuous", "not steady", "infeasible")
GROWTH_TOLERANCE = 0.05  # relative growth of the window median a steady bound may show
WINDOW_FRACTION = 0.25  # the last quarter of the horizon against the quarter before it
MIN_WINDOW = 2  # steps per window: a horizon of fewer than 2 x 2 steps cannot show steadiness
STABLE = 1.0 - 1e-9  # spectral radius below which F is Schur stable (a stationary open-loop covariance exists)

VERDICT_ASSUMPTIONS = (
    "verdict: a feasible bound is vacuous when, at some node and some step of the last 2 W steps of the horizon (W "
    "below), tr Phi is at or above the trace of the open-loop covariance at the same step (the prior covariance "
    "propagated by P <- F P F^T + Q with F the linearisation at the operating point, no measurement), or is not "
    "finite; the earlier transient from the prior, where the bound's inflation can exceed the open loop, is not "
    "judged.",
    f"verdict: a bound is steady when, at every node, the median tr Phi over the last W = max({MIN_WINDOW}, "
    f"ceil({WINDOW_FRACTION:g} K)) steps of the K-step horizon exceeds the median over the W steps before by at most "
    f"{GROWTH_TOLERANCE:.0%}; a horizon shorter than {2 * MIN_WINDOW} steps cannot show it (not steady). A "
    "feasibility map's fixed point is steady by its convergence test.",
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
    """The verdict on a bound and the numbers behind it.

    Attributes
    ----------
    verdict : str
        One of :data:`VERDICTS`.
    reason : str or None
        Why the bound is not certified, naming the condition and the node(s); None when certified.
    nodes : list of int
        The nodes that prevent certification (empty when certified, and when the horizon is too short).
    detail : dict
        JSON-ready: ``horizon``, ``fixed_point``, ``final_trace`` (per node), ``open_loop_trace`` (at the
        horizon) and ``open_loop`` (how it was computed), ``centralized``, ``local``, ``ratio_open_loop``,
        ``ratio_centralized``, ``ratio_local`` (per node, of the final tr Φ), ``judged_steps`` (first and last
        step judged), ``max_ratio_open_loop`` (per node, the largest tr Φ / open-loop trace over the judged
        steps: the vacuity measure), ``growth`` (per node, the steadiness measure), ``window``,
        ``tolerance``, ``open_loop_exceeded`` (node-steps of the whole trajectory at or above the open loop),
        ``nodes``, ``reason`` and ``verdict``.
    """

    verdict: str
    reason: str | None
    nodes: list = field(default_factory=list)
    detail: dict = field(default_factory=dict)

    @property
    def certified(self) -> bool:
        return self.verdict == "certified"


def known_verdict(value) -> str:
    """``value`` when it is one of :data:`VERDICTS`, else ``"unknown"``: a verdict read from a file (a design
    directory's ``schedule.json``) as a word of this vocabulary, never as the file's text."""
    return value if isinstance(value, str) and value in VERDICTS else "unknown"


def steadiness_window(horizon: int) -> int:
    """``W = max(MIN_WINDOW, ceil(WINDOW_FRACTION * horizon))``: the steps of each of the two compared windows."""
    return max(MIN_WINDOW, math.ceil(WINDOW_FRACTION * horizon))


def _growth(trace: np.ndarray) -> tuple[np.ndarray | None, int]:
    """Per node: median tr Φ over the last window / median over the window before - 1 (None: horizon too short)."""
    K = trace.shape[1]
    W = steadiness_window(K)
    if K < 2 * W:
        return None, W
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        last = np.median(trace[:, K - W:], axis=1)
        before = np.median(trace[:, K - 2 * W:K - W], axis=1)
        g = last / before - 1.0
    return np.where(np.isfinite(g), g, np.inf), W


def _ratios(values, ref) -> list | None:
    """``values / ref`` as JSON numbers (None where not finite); None when there is no reference."""
    if ref is None or not float(ref) > 0:
        return None
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        return [json_number(v / float(ref)) for v in values]


def verdict(trace, open_loop, *, feasible: bool, centralized: float | None = None,
            local: Sequence[float | None] | None = None, fixed_point: bool | None = None,
            infeasible_reason: str | None = None, open_loop_how: str = "") -> Verdict:
    """The verdict on a bound (see the module docstring for the tests and their order).

    Parameters
    ----------
    trace : array (nodes, T)
        tr Φ per node and step: a design's ``tr Φ_{k|k}`` for k = 1..K (T = K), or, with
        ``fixed_point``, one column: the stationary bound.
    open_loop : float or array (T,)
        The open-loop covariance's trace at the same steps (:func:`open_loop_traces`), or the
        stationary reference (:func:`open_loop_reference`); one number applies to every step.
    feasible : bool
        Whether (28)-(29) held everywhere and no node diverged.
    centralized, local
        The centralized and per-node local steady-state tr P (None where none exists): reported as ratios.
    fixed_point : bool or None
        None: ``trace`` is a trajectory, judged by the window test.  True: it is the converged
        fixed point of the stationary recursion (steady).  False: the stationary iteration did
        not converge (not steady).
    infeasible_reason : str, optional
        The caller's words for why (28)/(29) failed (the first violation).
    open_loop_how : str
        How ``open_loop`` was computed (recorded in the detail).

    Notes
    -----
    A trajectory is judged over its last ``2 W`` steps (the two windows of the steadiness test;
    the whole horizon when it is shorter): the bound is vacuous when, at some node and step
    there, tr Φ is at or above the open-loop trace at that step (or is not finite).  The
    transient from the prior is left out: at the first steps the bound's inflation factors can
    put it above the open loop, which is not what the design delivers once it has settled.
    """
    trace = np.atleast_2d(np.asarray(trace, dtype=float))
    N, T = trace.shape
    ol = np.array(np.broadcast_to(np.asarray(open_loop, dtype=float), (T,)))
    final, ol_final = trace[:, -1], float(ol[-1])
    if fixed_point is None:
        growth, W = _growth(trace)
        first = max(0, T - 2 * W)
    else:
        growth, W, first = (np.zeros(N) if fixed_point else None), None, 0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ratio = np.where(np.isinf(ol), 0.0, trace / ol)  # a finite bound against an open loop that overflowed: 0
        ratio = np.where(np.isinf(trace), np.inf, ratio)
        exceeded = int(np.sum(ratio >= 1.0))
    judged = ratio[:, first:]
    worst_ratio = np.where(np.isnan(judged), -np.inf, judged).max(axis=1)  # per node, over the judged steps
    local = list(local) if local is not None else [None] * N
    detail: dict[str, Any] = {
        "horizon": None if fixed_point is not None else T,
        "fixed_point": fixed_point is not None,
        "final_trace": [json_number(v) for v in final],
        "open_loop_trace": json_number(ol_final),
        "open_loop": open_loop_how or "the prior covariance propagated by P <- F P F^T + Q, no measurement",
        "centralized": json_number(centralized),
        "local": [json_number(v) for v in local],
        "ratio_open_loop": [json_number(v) for v in ratio[:, -1]],
        "ratio_centralized": _ratios(final, centralized),
        "ratio_local": [(_ratios([f], r) or [None])[0] for f, r in zip(final, local)],
        "judged_steps": None if fixed_point is not None else [first + 1, T],
        "max_ratio_open_loop": [json_number(v) if np.isfinite(v) or v == np.inf else None for v in worst_ratio],
        "growth": None if growth is None else [json_number(g) for g in growth],
        "window": W,
        "tolerance": GROWTH_TOLERANCE,
        "open_loop_exceeded": exceeded if fixed_point is None else None,
    }
    if not feasible:
        out = Verdict("infeasible", infeasible_reason or "(28)/(29) failed or a node diverged")
    else:
        vac = np.flatnonzero(worst_ratio >= 1.0)
        if vac.size:
            worst = int(vac[np.argmax(worst_ratio[vac])])
            j = first + int(np.nanargmax(np.where(np.isnan(judged[worst]), -np.inf, judged[worst])))
            f = trace[worst, j]
            if fixed_point is not None:
                where, ol_words = "at the fixed point", "the stationary open-loop covariance's trace"
            else:
                where, ol_words = f"at step {j + 1}", "the open-loop covariance's trace at that step"
            if not np.isfinite(f) and fixed_point is None:  # where it stopped being finite (an overflow)
                where = f"from step {int(np.argmax(np.isinf(trace[worst]))) + 1} on (it overflowed)"
            words = (f"node {worst}'s tr Φ is not finite {where}" if not np.isfinite(f) else
                     f"node {worst}'s tr Φ {f:.4g} {where} is {f / ol[j]:.3g} x {ol_words}, {ol[j]:.4g}")
            more = f" ({vac.size} of {N} nodes)" if vac.size > 1 else ""
            span = "" if fixed_point is not None else f", over the judged steps {first + 1}..{T}"
            out = Verdict("vacuous", f"{words}{more}{span}", [int(i) for i in vac])
        elif growth is None:
            if fixed_point is False:
                why = "the stationary bound recursion did not reach a fixed point"
            else:
                why = (f"the horizon of {T} step{'s' * (T != 1)} is too short to show a steady bound (at least "
                       f"{2 * MIN_WINDOW} steps are needed)")
            out = Verdict("not steady", why)
        else:
            grow = np.flatnonzero(~(growth <= GROWTH_TOLERANCE))
            if grow.size:
                worst = int(grow[np.argmax(growth[grow])])
                more = f"{grow.size} of {N} nodes; " if grow.size > 1 else ""
                out = Verdict("not steady", f"node {worst}'s median tr Φ over the last {W} of {T} steps is "
                                            f"{growth[worst]:.1%} above that over the {W} steps before ({more}a "
                                            f"steady bound grows by at most {GROWTH_TOLERANCE:.0%})",
                              [int(i) for i in grow])
            else:
                out = Verdict("certified", None)
    detail.update({"verdict": out.verdict, "reason": out.reason, "nodes": out.nodes})
    return Verdict(out.verdict, out.reason, out.nodes, detail)


def count_verdicts(verdicts) -> dict[str, int]:
    """How many of ``verdicts`` (names of :data:`VERDICTS`) are each verdict, in the order of :data:`VERDICTS`."""
    verdicts = list(verdicts)
    return {v: verdicts.count(v) for v in VERDICTS}


def describe(detail: Mapping) -> str:
    """The verdict of ``detail`` (:attr:`Verdict.detail`, or ``verdict_detail`` read from a file) in one sentence:
    what it is, why when not certified, and the final bound against the open loop and the Kalman references."""

    def top(key):
        r = [x for x in detail.get(key) or [] if x is not None]
        return max(r) if r else None

    v = detail.get("verdict")
    W, K = detail.get("window"), detail.get("horizon")
    fixed = bool(detail.get("fixed_point"))
    if v == "certified":
        g, ol, judged = top("growth"), top("max_ratio_open_loop"), detail.get("judged_steps")
        steady = ("a fixed point" if fixed else f"median over the last {W} of {K} steps at most {max(g, 0.0):.1%} "
                  f"above the {W} before" if g is not None else "steady")
        where = "" if fixed or not judged else f" over steps {judged[0]}..{judged[1]}"
        text = f"certified: the bound is finite, steady ({steady}) and informative"
        if ol is not None:
            text += (f": at most {ol:.3g} x the {'stationary ' if fixed else ''}open-loop covariance's trace at every "
                     f"node{where}")
    else:
        text = f"not certified ({v}): {detail.get('reason')}"
    final = top("final_trace")
    if final is not None and v != "infeasible":
        refs = [f"{r:.3g} x {words}" for r, words in (
            (top("ratio_open_loop") if v != "certified" else None, "the open loop"),
            (top("ratio_centralized"), "the centralized steady-state tr P"),
            (top("ratio_local"), "a node's own local one, at most")) if r is not None]
        text += (f"; {'at the fixed point' if fixed else f'at step {K}'} the largest tr Φ is {final:.4g}"
                 + (f" ({', '.join(refs)})" if refs else ""))
    return text


def open_loop_traces(F: np.ndarray, Q: np.ndarray, P0: np.ndarray, steps: int) -> np.ndarray:
    """``tr P_k`` for k = 1..steps of ``P_{k+1} = F P_k Fᵀ + Q``, ``P_0 = P0`` (inf once it overflows)."""
    F, Q, P = (np.asarray(a, dtype=float) for a in (F, Q, P0))
    out = np.empty(steps)
    with np.errstate(over="ignore", invalid="ignore"):
        for k in range(steps):
            P = F @ P @ F.T + Q
            t = float(np.trace(P))
            if not math.isfinite(t):
                out[k:] = np.inf
                break
            out[k] = t
    return out


def open_loop_reference(F: np.ndarray, Q: np.ndarray, P0: np.ndarray, horizon: int) -> tuple[float, str]:
    """The stationary open-loop covariance's trace and how it was obtained.

    Schur-stable ``F`` (spectral radius < 1 - 1e-9): the solution of ``P = F P Fᵀ + Q``
    (``scipy.linalg.solve_discrete_lyapunov``).  Otherwise no stationary covariance exists and
    the open-loop covariance at ``horizon`` steps from ``P0`` is used (inf once it overflows).
    """
    from scipy.linalg import solve_discrete_lyapunov

    F, Q = np.asarray(F, dtype=float), np.asarray(Q, dtype=float)
    rho = float(np.max(np.abs(np.linalg.eigvals(F)))) if F.size else 0.0
    if rho < STABLE:
        P = solve_discrete_lyapunov(F, Q)
        return float(np.trace(P)), (f"stationary open-loop covariance (discrete Lyapunov equation; F Schur stable, "
                                    f"spectral radius {rho:.4g})")
    tr = open_loop_traces(F, Q, P0, horizon)[-1]
    return float(tr), (f"open-loop covariance at the horizon of {horizon} steps from the prior (F not Schur stable, "
                       f"spectral radius {rho:.4g}: no stationary covariance)")
