"""The design report: a consensus-filter gain schedule (``schedule.json`` + ``schedule.npz``) in plain words.

What ``cfdesign design`` computed and whether it can be used: the verdict (feasible
or not, and why: the first violation, which condition at which node and step, with
its margin), which of the conditions (28) and (29) binds where, the bound tr Φ and
the margins of (28)-(29) per node over time (the report draws ``fig_trace_bound.png``
and ``fig_margins.png`` itself, from ``schedule.npz``), per node ε, σ, β, the gain
magnitudes and the final bound, the attacks and δ, the linearisation (U, V_i), the
network, the scenario, the assumptions, and what the bound means: it holds along
the simulated run it was computed on, and a filter that replays the gains elsewhere
keeps the gains, not the guarantee.

Nodes and steps are numbered as in ``schedule.json`` (from 0).  ``margin28[i, k]``
is (28) on Φ_{k|k} (reported at step k), ``margin29[i, k]`` is (29) on Φ_{k+1|k}
(reported at step k + 1), as in the violations.
"""
from __future__ import annotations

import re
import zipfile
from pathlib import Path
from typing import Any, Mapping

import numpy as np


import studies.reports.text as text  # the formatting a rule's report words use
from designer.regions import carried_region_traces
from designer.validation import InputError

from .auto import auto_section, validation_section
from .text import (assumption_section, compact, document, figure_lines, fmt_num, generic, is_num, matrix_text,
                   md_cell, md_escape, md_table, network_lines, observability_section, params_table, read_record,
                   recorded_elsewhere, rerun_lines, scenario_spec)

__all__ = ["design_report", "render_design", "attack_lines", "HARD", "FIGURES", "software_lines", "gain_rule_record",
           "THEOREM2_KIND", "theorem2_words"]

HARD = ("(28)", "(29)", "diverged")  # the violations that make a design infeasible
FIGURES = {
    "fig_trace_bound.png": "tr Φ_{k|k} of every node over the run (log scale); a line ends where the node's Φ "
                           "stops being a bound (after a violation at the node or a neighbour), an x marks a "
                           "node's first violation.",
    "fig_margins.png": "Margins of (28) (top, on Φ_{k|k}) and (29) (bottom, on Φ_{k+1|k}) per node over the run "
                       "(symmetric log scale); below the red line a condition is violated.",
}
_KNOWN = {"schema", "scenario", "mode", "gain_rule", "runtime_information", "nodes",
          "steps", "epsilon", "feasible", "violations", "sigma",
          "beta", "trace_bound", "linearization", "tau", "delta", "U", "V", "radius", "sigma_fixed", "beta_fixed",
          "options", "sensors", "state_names", "seed", "trajectory", "replay", "boundedness_certified", "network",
          "attacks", "params", "assumptions", "source", "source_digest", "source_seal", "model_digest", "observability",
          "kalman_references", "predicted_mse", "gate",
          "versions", "invocation", "conditioning", "certified", "verdict", "verdict_detail", "bounded", "growing",
          "bounded_reason", "exchange", "stationary",
          "stationary_certificate", "robustness", "rounds", "rounds_tradeoff", "robustness_note", "bank",
          "bank_record", "remainder_structure", "carry", "carried", "table_kind", "tables_kind", "tables_own_steps"}
_CONDITION = {"(28)": "(28) asks 1/λmax(Φ_{k|k}) > (1+ε) σ, so that the prediction bound (26) exists",
              "(29)": "(29) asks 1/λmax(Φ_{k+1|k}) > β, so that the update bound (27) exists"}


# ---------------------------------------------------------------------------------------------------------------
# Reading the files.


def _float_array(v, shape=None) -> np.ndarray | None:
    """A JSON list of lists as floats (null as NaN), or None when it is not one."""
    try:
        a = np.array([[np.nan if x is None else x for x in row] for row in v], dtype=float)
    except (TypeError, ValueError):
        return None
    return a if a.ndim == 2 and (shape is None or a.shape == shape) else None


class _NpzArrays(Mapping):
    """``schedule.npz``'s arrays, each read when asked for and not kept: :class:`_Schedule` reduces the large ones
    (Φ to its traces, K and C to their norms) one at a time, so that the report never holds them together (3 x 0.8
    GB on a 118-node grid, beside the design that wrote them)."""

    def __init__(self, path: Path):
        self.path = path
        with np.load(path, allow_pickle=False) as z:
            self.names = list(z.files)

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self.names:
            raise KeyError(name)
        try:
            with np.load(self.path, allow_pickle=False) as z:
                return np.asarray(z[name])
        except Exception as exc:  # noqa: BLE001 - a damaged member: the report goes on without the arrays
            raise _Unreadable(f"schedule.npz cannot be read ({type(exc).__name__}: {exc})") from exc

    def __iter__(self):
        return iter(self.names)

    def __len__(self) -> int:
        return len(self.names)

    def shape(self, name: str) -> tuple:
        """A member's shape from its header, without reading its data."""
        try:
            with zipfile.ZipFile(self.path) as zf, zf.open(f"{name}.npy") as fh:
                version = np.lib.format.read_magic(fh)
                read = (np.lib.format.read_array_header_1_0 if version == (1, 0) else
                        np.lib.format.read_array_header_2_0)
                return tuple(read(fh)[0])
        except Exception as exc:  # noqa: BLE001 - a damaged member: the report goes on without the arrays
            raise _Unreadable(f"schedule.npz cannot be read ({type(exc).__name__}: {exc})") from exc


class _Unreadable(Exception):
    """A member of ``schedule.npz`` that cannot be read; its message is the report's note."""


def _load_arrays(d: Path) -> tuple[Mapping[str, np.ndarray] | None, str | None]:
    path = d / "schedule.npz"
    if not path.is_file():
        return None, "schedule.npz is missing"
    try:
        return _NpzArrays(path), None
    except Exception as exc:  # noqa: BLE001 - a damaged file: the report says so and goes on with the JSON
        return None, f"schedule.npz cannot be read ({type(exc).__name__}: {exc})"


def _schedule(meta: Mapping, arrays: Mapping | None, note: str | None
              ) -> tuple["_Schedule", Mapping | None, str | None]:
    """The report's :class:`_Schedule` of ``meta`` and ``arrays``; a member that cannot be read leaves every array
    out, with the note that says so: ``(schedule, arrays, note)``."""
    try:
        return _Schedule(meta, arrays), arrays, note
    except _Unreadable as exc:
        return _Schedule(meta, None), None, str(exc)


class _Schedule:
    """What the report needs of a schedule, from ``schedule.json`` and (if readable) ``schedule.npz``."""

    def __init__(self, meta: Mapping, arrays: Mapping[str, np.ndarray] | None):
        # each array read once (a schedule.npz's when asked for, _NpzArrays), the large ones kept only as what the
        # report shows of them: Φ's traces, K's and C's norms
        self.meta = meta
        arrays = arrays or {}
        self.shapes = {k: (arrays.shape(k) if isinstance(arrays, _NpzArrays) else np.shape(arrays[k])) for k in arrays}
        tb = _float_array(meta.get("trace_bound")) if isinstance(meta.get("trace_bound"), list) else None
        phi, valid = arrays.get("Phi"), arrays.get("valid")
        self.valid = valid
        self.trace = None  # (nodes, steps + 1): tr Φ_{k|k}, NaN where not a bound
        carried, mask = arrays.get("carried"), arrays.get("region_mask")
        fits = phi is not None and valid is not None and phi.ndim == 4 and valid.shape == phi.shape[:2]
        if fits and carried is not None:  # the nodes carry their regions, judged on them: arrays that agree only
            fits = (mask is not None and carried.shape == (phi.shape[0], phi.shape[-1]) and mask.ndim == 2
                    and mask.shape[0] == phi.shape[0] and np.all((carried >= -1) & (carried < mask.shape[1])))
            try:
                tr = carried_region_traces(phi, carried, mask.astype(bool)) if fits else None
            except InputError:  # a region the file says its node does not carry
                fits = False
        elif fits:
            with np.errstate(invalid="ignore"):
                tr = np.trace(phi, axis1=-2, axis2=-1)
        if fits:
            self.trace = np.where(valid.astype(bool), tr, np.nan)
        elif tb is not None:
            self.trace = np.concatenate([np.full((tb.shape[0], 1), np.nan), tb], axis=1)
        del phi
        n = meta.get("nodes")
        self.nodes = int(n) if is_num(n) else (self.trace.shape[0] if self.trace is not None else 0)
        k = meta.get("steps")
        self.steps = int(k) if is_num(k) else (self.trace.shape[1] - 1 if self.trace is not None else 0)
        shape = (self.nodes, self.steps)

        def arr(name):
            a = arrays.get(name)
            if a is not None and a.shape == shape:
                return a.astype(float)
            return _float_array(meta[name], shape) if name in meta and isinstance(meta[name], list) else None

        self.sigma, self.beta = arr("sigma"), arr("beta")
        m28, m29 = arrays.get("margin28"), arrays.get("margin29")
        self.m28 = m28 if _shaped(m28, shape) else None
        self.m29 = m29 if _shaped(m29, shape) else None
        # a bound without the multipliers σ, β of (26)-(27) (the relay rules' expected covariance): no margin of
        # (28)-(29) anywhere while some node has a bound; its report shows no margins and names no such conditions
        self.multipliers = not (self.m28 is not None and self.m29 is not None and self.trace is not None
                                and np.isfinite(self.trace).any() and not np.isfinite(self.m28).any()
                                and not np.isfinite(self.m29).any())
        if not self.multipliers:
            self.m28 = self.m29 = None
        self.gain_norms = {}  # per gain, each node's largest spectral norm over the steps (the per-node table)
        for name in ("K", "C"):
            a = arrays.get(name)
            self.gain_norms[name] = [_max_norm(a, i) for i in range(self.nodes)]
            del a
        v = meta.get("violations")
        self.violations = [x for x in v if isinstance(x, dict)] if isinstance(v, list) else []
        self.hard = [x for x in self.violations if x.get("condition") in HARD]
        self.theorem2 = [x for x in self.violations if x.get("condition") == "theorem2"]
        f = meta.get("feasible")
        self.feasible = f if isinstance(f, bool) else not self.hard

    def first_hard(self, node=None) -> dict | None:
        hard = [v for v in self.hard if node is None or v.get("node") == node]
        return min(hard, key=_order) if hard else None

    def sensor(self, i: int) -> str:
        s = self.meta.get("sensors")
        if isinstance(s, list) and i < len(s) and isinstance(s[i], dict) and s[i].get("name") is not None:
            return str(s[i]["name"])
        return ""


def _shaped(a, shape) -> bool:
    return a is not None and a.shape == shape


def _order(v: Mapping):
    step, node = v.get("step"), v.get("node")
    return (step if is_num(step) else float("inf"), node if is_num(node) else float("inf"))


# ---------------------------------------------------------------------------------------------------------------
# Figures.


def _trace_figure(path: Path, s: _Schedule, title: str) -> None:
    from ..figures import node_label, node_legend, plotting, save_figure

    plt = plotting()
    fig, ax = plt.subplots(figsize=(8, 4.6))
    tr = s.trace
    steps = np.arange(tr.shape[1])
    positive = np.isfinite(tr) & (tr > 0)
    if positive.any():
        for i in range(tr.shape[0]):
            y = np.where(positive[i], tr[i], np.nan)
            (line,) = ax.plot(steps, y, lw=1.3, label=node_label(i, tr.shape[0], first=0))
            first = s.first_hard(i)
            ok = np.nonzero(positive[i])[0]
            if first is not None and ok.size:
                ax.plot(steps[ok[-1]], y[ok[-1]], "x", color=line.get_color(), ms=9, mew=2)
        ax.set_yscale("log")
        node_legend(ax, tr.shape[0], 0.5)
    else:
        ax.text(0.5, 0.5, "no node has a bound at any step", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlim(0, max(1, tr.shape[1] - 1))
    ax.set_xlabel("step k")
    ax.set_ylabel(r"tr $\Phi_{k|k}$")
    ax.grid(True, which="both", alpha=0.3)
    ax.set_title(title, fontsize=10)
    save_figure(fig, path)


def _linthresh(values: np.ndarray) -> float:
    a = np.abs(values[np.isfinite(values) & (values != 0)])
    if not a.size:
        return 1.0
    return float(min(1.0, max(1e-6, 10.0 ** np.floor(np.log10(a.min())))))


def _margin_figure(path: Path, s: _Schedule, title: str) -> None:
    from ..figures import node_label, node_legend, plotting, save_figure

    plt = plotting()
    fig, axes = plt.subplots(2, 1, figsize=(8, 6.4), sharex=True)
    both = np.concatenate([s.m28.ravel(), s.m29.ravel()])
    thresh = _linthresh(both)
    k = np.arange(s.steps)
    for ax, m, shift, name in ((axes[0], s.m28, 0, "(28)"), (axes[1], s.m29, 1, "(29)")):
        for i in range(m.shape[0]):
            (line,) = ax.plot(k + shift, m[i], lw=1.2, label=node_label(i, m.shape[0], first=0))
            bad = np.isfinite(m[i]) & (m[i] <= 0)
            if bad.any():
                ax.plot((k + shift)[bad], m[i][bad], "x", color=line.get_color(), ms=9, mew=2)
        ax.axhline(0.0, color="crimson", lw=1, ls="--")
        if np.isfinite(m).any():
            ax.set_yscale("symlog", linthresh=thresh)
        ax.set_ylabel(f"margin of {name}")
        ax.grid(True, which="both", alpha=0.3)
    node_legend(axes[0], s.nodes, 0.0)
    axes[1].set_xlabel("step ((28) at k, (29) at k + 1)")
    axes[0].set_title(title, fontsize=10)
    save_figure(fig, path)


# ---------------------------------------------------------------------------------------------------------------
# Sections.


def _node(v) -> str:
    return md_escape(fmt_num(v))


def _violation_words(v: Mapping) -> str:
    cond = v.get("condition")
    where = f"at node {_node(v.get('node'))}, step {_node(v.get('step'))}"
    if cond == "diverged":
        reason = v.get("reason")
        return f"node {_node(v.get('node'))} diverged at step {_node(v.get('step'))}" + (
            f" ({md_escape(reason)})" if reason else "")
    margin = v.get("margin")
    m = fmt_num(margin) if is_num(margin) else "not finite (the matrix is not numerically positive definite)"
    return f"condition {md_escape(cond)} {where}, margin {md_escape(m)}"


def _tightest(s: _Schedule) -> list[tuple[int, str, int, float, int, int, int]]:
    """Per node: (node, condition, step, margin, steps (28) tighter, steps (29) tighter, steps with both)."""
    out = []
    for i in range(s.nodes):
        a, b = s.m28[i], s.m29[i]
        cand = []
        if np.isfinite(a).any():
            j = int(np.nanargmin(a))
            cand.append((float(a[j]), "(28)", j))
        if np.isfinite(b).any():
            j = int(np.nanargmin(b))
            cand.append((float(b[j]), "(29)", j + 1))
        both = np.isfinite(a) & np.isfinite(b)
        n28 = int(np.sum(both & (a <= b)))
        n29 = int(np.sum(both & (b < a)))
        if cand:
            m, cond, step = min(cand, key=lambda c: (c[0], c[2]))
            out.append((i, cond, step, m, n28, n29, int(both.sum())))
    return out


# Why a failed Theorem 2 condition never contradicts a design's verdict: the two theorems make different claims.
THEOREM2_KIND = ("the verdict judges Theorem 1's bound Φ (finite and informative at every step of a run's horizon, "
                 "or at a map's fixed point) and 'bounded' whether that bound is steady or a stationary fixed point, "
                 "while Theorem 2's condition (the error bounded in mean square for all time) is sufficient, not "
                 "necessary, so where it fails Theorem 2 claims nothing and the verdict stands")


def theorem2_words(where: str, verdict: str | None = None) -> str:
    """Theorem 2's condition failing ``where`` (e.g. "12 (node, step) pairs"), with why this does not contradict the
    design's ``verdict`` (:data:`THEOREM2_KIND`): the one wording of every report and of ``cfdesign design``."""
    return (f"Theorem 2's sufficient condition for mean-square boundedness of the error did not hold at {where}; "
            f"this does not contradict the verdict{f' ({verdict})' if verdict else ''}: {THEOREM2_KIND}")


def _not_computed_reason(s: _Schedule) -> str:
    """Why the certificate was not computed: the reason of the violations record of condition ``not computed``."""
    rec = next((v for v in s.violations if v.get("condition") == "not computed"), {})
    return str(rec.get("reason") or (s.meta.get("verdict_detail") or {}).get("reason") or "no reason recorded")


_BOUNDED_BY = {"steady": "steady: at every node its median over the last window is within the tolerance of the "
                         "window before",
               "fixed point": "a fixed point of the stationary recursion",
               "stationary certificate": "its stationary certificate is a fixed point with its LMI confirmed, below "
                                         "the stationary open loop"}


def _bounded_lines(s: _Schedule) -> list[str]:
    """The separate claim ``bounded`` (Theorem 2's kind of claim: steady, or a stationary fixed point; the paragraph
    does not name Theorem 2, whose sufficient condition the report discusses apart) and the ``growing`` qualifier in
    words; none for a file
    written before them, or where the bound is not certified nor vacuous."""
    b = s.meta.get("bounded")
    if not isinstance(b, bool) or s.meta.get("verdict") not in ("certified", "vacuous"):
        return []
    detail = s.meta.get("verdict_detail") if isinstance(s.meta.get("verdict_detail"), Mapping) else {}
    by = detail.get("bounded_by")
    if b:
        how = _BOUNDED_BY.get(by, _BOUNDED_BY["steady"])
        line = f"**Bounded** (a claim apart from the certificate, which is Theorem 1's bound at every step): {how}."
        if s.meta.get("growing") is True:
            line += " Along the run the bound still grows at the horizon; that qualifies the certificate only."
    else:
        line = ("**Not bounded** (a claim apart from the certificate, which is Theorem 1's bound at every step): "
                f"{md_escape(str(s.meta.get('bounded_reason') or 'no reason recorded'))}."
                + (" The certificate holds over the horizon: still growing at the horizon is a qualifier, not a "
                   "failure." if s.meta.get("verdict") == "certified" else ""))
    return [line, ""]


#: What the report says of a bound without multipliers (:attr:`_Schedule.multipliers`).
_NO_MULTIPLIERS = ("This rule's bound has no multipliers σ, β: conditions (28)-(29) do not apply to it, so there are "
                   "no margins to show.")


def _verdict_section(s: _Schedule, tight) -> list[str]:
    out = ["## Verdict", ""]
    size = f"{s.nodes} nodes, {s.steps} steps"
    if s.meta.get("verdict") == "not computed":
        out += [f"**Not computed.** The certificate was not computed ({md_escape(_not_computed_reason(s))}): "
                f"conditions (28)-(29) were not checked along the run ({size}), so the design claims no bound Φ. "
                "It is not infeasible: nothing failed.", ""]
        return out
    if s.feasible:
        line = (f"**Feasible.** Conditions (28) and (29) held at every node and every step of the run ({size}) and "
                "no node diverged: every node's Φ is a bound along the whole run.") if s.multipliers else (
                f"**Feasible.** {_NO_MULTIPLIERS} Every node's Φ was finite at every step of the run ({size}) and no "
                "node diverged: every node's Φ is a bound along the whole run.")
        if tight:
            i, cond, step, m, *_ = min(tight, key=lambda t: (t[3], t[0]))
            line += (f" The tightest spot: condition {cond} at node {i}, step {step}, margin {fmt_num(m)}.")
        if s.meta.get("certified") is False:
            line += (f" Feasible is not certified: the bound itself is {md_escape(s.meta.get('verdict'))} (the "
                     "summary's first line says why).")
        out += [line, "", *_bounded_lines(s)]
    else:
        first = s.first_hard()
        nodes = sorted({v.get("node") for v in s.hard if is_num(v.get("node"))})
        line = (f"**Infeasible.** {len(s.hard)} violation(s) of (28)-(29) or divergence, at {len(nodes)} of "
                f"{s.nodes} nodes ({size}).")
        if first is not None:
            line += f" The first violation: {_violation_words(first)}."
            if first.get("condition") in _CONDITION:
                line += f" A margin ≤ 0 is a violation: {_CONDITION[first['condition']]}."
        out += [line, "",
                "From its first violation on, a node runs a documented fallback (σ = β = 0, no bounding inflation) "
                "so that no indefinite matrix is carried on; its Φ is no longer a bound (NaN in schedule.npz, a gap "
                "in the figure of tr Φ), nor is that of a neighbour that used it. The table per node below gives "
                "each node's first violation.", ""]
    cert = s.meta.get("boundedness_certified")
    if s.theorem2:
        first = min(s.theorem2, key=_order)
        verdict = s.meta.get("verdict") if isinstance(s.meta.get("verdict"), str) else None
        out += [md_escape(theorem2_words(f"{len(s.theorem2)}{_theorem2_checked(s)} node-step(s) (first at node "
                                         f"{_node(first.get('node'))}, step {_node(first.get('step'))}, margin "
                                         f"{fmt_num(first.get('margin'))})", verdict))
                + ". Nor does it make the design infeasible: where Φ is a bound it still bounds the error covariance "
                "along this run. " + _THEOREM2_STEPS.format(
                    k=s.steps, n=s.steps + 1, nodes=s.nodes, all2=s.nodes * (s.steps + 1), all1=s.nodes * s.steps),
                ""]
    elif cert is True:
        out += ["Theorem 2's sufficient condition for mean-square boundedness of the error held at every node "
                "and step where Φ is a bound.", ""]
    return out


_THEOREM2_STEPS = ("Theorem 2's condition is checked on Φ_{{k|k}} at every step k = 0, …, {k} where it is a bound ({n} "
                   "per node, {all2} node-steps for {nodes} nodes), conditions (28)-(29) once per recursion step "
                   "k → k + 1 ({k} per node, {all1} node-steps): hence the two counts differ.")


def _theorem2_checked(s: _Schedule) -> str:
    """" of N" where N is the number of node-steps at which Theorem 2 was checked (Φ_{k|k} a bound), when known."""
    valid = s.valid
    if valid is None or valid.shape != (s.nodes, s.steps + 1):
        return ""
    return f" of the {int(np.count_nonzero(valid))} checked"


def _conditioning_section(meta: Mapping) -> list[str]:
    """One sentence on the conditioning of the gains (``schedule.json``'s ``conditioning``, mode mse)."""
    c = meta.get("conditioning")
    kappa = c.get("gain_condition") if isinstance(c, Mapping) else None
    if not isinstance(kappa, list) or not any(is_num(v) for v in kappa):
        return []
    node = max((i for i, v in enumerate(kappa) if is_num(v)), key=lambda i: kappa[i])
    steps = c.get("gain_condition_step") if isinstance(c.get("gain_condition_step"), list) else []
    where = f"node {node}" + (f", step {steps[node]}" if node < len(steps) and is_num(steps[node]) else "")
    ill = [i for i in c.get("ill_conditioned") or [] if is_num(i)]
    threshold = c.get("threshold") if is_num(c.get("threshold")) else 1e6
    if ill:
        digits = max(0, int(16 - np.log10(kappa[node])))
        return [f"**Ill-conditioned at node(s) {', '.join(str(i) for i in ill)}.** Their gains were solved from "
                f"systems with condition numbers up to {kappa[node]:.1e} ({where}; reported beyond "
                f"{threshold:.0e}): about {digits} of the 16 significant digits survive that solve, so these "
                "gains, and the bounds and estimates that follow from them, can change with the machine or the "
                "linear-algebra library. The gains exploit differences between the nodes' errors that are tiny "
                "against the errors themselves.", ""]
    return [f"The gains were solved from well-conditioned systems: condition number at most "
            f"{fmt_num(kappa[node])} ({where}).", ""]


def _binding_section(s: _Schedule, tight) -> list[str]:
    if s.m28 is None or s.m29 is None:
        return []
    out = ["## Which condition binds where", "",
           "A margin is how far a condition is from failing: for (28) 1/λmax(Φ_{k|k}) − (1+ε)σ, for (29) "
           "1/λmax(Φ_{k+1|k}) − β; at or below 0 the condition is violated and the bound does not exist. Per "
           "node: the step where the smaller of the two margins is smallest, which condition that is, and the "
           "share of the steps (where both are checked) at which each condition is the tighter one. Steps are "
           "named as in the violations: (28) at k, (29) at k + 1 of the same recursion step k → k + 1.", ""]
    if not tight:
        return out + ["No margin was checked at any node (no node had a bound).", ""]
    rows = []
    for i, cond, step, m, n28, n29, n in tight:
        share = (lambda c: f"{fmt_num(100 * c / n, 3)} %") if n else (lambda c: "—")
        rows.append([f"{i}", md_cell(s.sensor(i)), cond, f"{step}", fmt_num(m), share(n28), share(n29), f"{n}"])
    out += md_table(["node", "sensor", "tightest condition", "at step", "margin there", "(28) tighter",
                     "(29) tighter", "steps checked"], rows, ["l", "l", "l", "r", "r", "r", "r", "r"])
    tot = sum(t[6] for t in tight)
    if tot:
        n28, n29 = sum(t[4] for t in tight), sum(t[5] for t in tight)
        lead = "(29)" if n29 > n28 else "(28)"
        out += [f"Over all nodes, {lead} is the tighter condition at {fmt_num(100 * max(n28, n29) / tot, 3)} % of "
                f"the {tot} checked node-steps ((28) at {n28}, (29) at {n29}).", ""]
    rule = _rule_of(s.meta.get("mode"))
    out += rule.report_margins(s.meta) if rule is not None else []
    return out


def _stats(row: np.ndarray) -> str:
    f = row[np.isfinite(row)]
    if not f.size:
        return "—"
    return f"{fmt_num(float(f.min()))} / {fmt_num(float(np.median(f)))} / {fmt_num(float(f.max()))}"


def _fixed(value, row: np.ndarray | None) -> str:
    text = f"{fmt_num(value)} (fixed)"
    if row is not None and np.isnan(row).any():
        text += f"; fallback 0 from step {int(np.nonzero(np.isnan(row))[0][0])}"
    return text


def _max_norm(a: np.ndarray | None, i: int) -> str:
    if a is None or a.ndim != 4 or i >= a.shape[0]:
        return "—"
    g = a[i]
    ok = np.all(np.isfinite(g), axis=(-2, -1))
    if not ok.any():
        return "—"
    return fmt_num(float(np.linalg.norm(g[ok], ord=2, axis=(-2, -1)).max()))


def _final_bound(s: _Schedule, i: int) -> str:
    if s.trace is None or i >= s.trace.shape[0]:
        return "—"
    row = s.trace[i]
    if np.isfinite(row[-1]):
        return fmt_num(float(row[-1]))
    ok = np.nonzero(np.isfinite(row))[0]
    ok = ok[ok > 0]
    if not ok.size:
        return "none"
    return f"none (last {fmt_num(float(row[ok[-1]]))} at step {int(ok[-1])})"


def _rule_of(mode):
    """The schedule's gain rule (:mod:`rules`), None for a mode that is not a rule here (the record is data)."""
    import rules

    return rules.find(mode)


def _fixed_multipliers(mode) -> bool:
    """Whether the schedule's gain rule keeps the user's σ, β, τ (:attr:`designer.rule.GainRule.fixed_multipliers`;
    False for a mode that is not a rule here)."""
    rule = _rule_of(mode)
    return rule is not None and rule.fixed_multipliers


def _node_section(s: _Schedule) -> list[str]:
    if not s.nodes:
        return []
    fixed = _fixed_multipliers(s.meta.get("mode"))
    eps = s.meta.get("epsilon")
    rows = []
    for i in range(s.nodes):
        sig = s.sigma[i] if s.sigma is not None else None
        bet = s.beta[i] if s.beta is not None else None
        if fixed and is_num(s.meta.get("sigma_fixed")):
            sig_text = _fixed(s.meta["sigma_fixed"], sig)
        else:
            sig_text = _stats(sig) if sig is not None else "—"
        if fixed and is_num(s.meta.get("beta_fixed")):
            bet_text = _fixed(s.meta["beta_fixed"], bet)
        else:
            bet_text = _stats(bet) if bet is not None else "—"
        first = s.first_hard(i)
        rows.append([f"{i}", md_cell(s.sensor(i)), md_cell(fmt_num(eps)), md_cell(sig_text), md_cell(bet_text),
                     s.gain_norms["K"][i], s.gain_norms["C"][i], md_cell(_final_bound(s, i)),
                     md_cell(_plain_violation(first)) if first else "none"])
    what = ("the paper's fixed σ and β (a node on its fallback uses 0)" if fixed else
            "σ and β as min / median / max over the steps where the node had a bound" if s.multipliers else
            "this rule's bound has no σ and β (—)")
    out = ["## Per node: ε, σ, β, gains and the final bound", "",
           f"ε is the same at every node; {what}. Gains: the largest spectral norm over the steps of the update "
           "gain K_i and of the consensus gain C_i. Final tr Φ: the bound at the last step (or the last step that "
           "had one).", ""]
    out += md_table(["node", "sensor", "ε", "σ", "β", "max ‖K_i‖₂", "max ‖C_i‖₂", "final tr Φ", "first violation"],
                    rows, ["l", "l", "r", "r", "r", "r", "r", "r", "l"])
    return out


def _plain_violation(v: Mapping) -> str:
    if v.get("condition") == "diverged":
        return f"diverged at step {fmt_num(v.get('step'))}"
    return f"{v.get('condition')} at step {fmt_num(v.get('step'))}, margin {fmt_num(v.get('margin'))}"


def _figure_section(names: list[str]) -> list[str]:
    rest = [n for n in names if n != "fig_trace_bound.png"]  # the summary's figure
    if not rest:
        return []
    out = ["## The margins over time", ""]
    for i, name in enumerate(rest, 1 + (len(rest) < len(names))):
        out += figure_lines(i, name, FIGURES[name])
    return out


def _meaning_section(s: _Schedule) -> list[str]:
    meta = s.meta
    out = ["## What the bound means and where it holds", "",
           "Φ_{i,k|k} is Theorem 1's upper bound on the covariance of node i's estimation error at step k, so tr Φ "
           "bounds the node's mean-square error E‖x_k − x̂_{i,k}‖². It is a bound while (28) and (29) hold at the "
           "node and its neighbours; after a violation the schedule stores none (NaN)." if s.multipliers else
           "Φ_{i,k|k} is this rule's bound on the covariance of node i's estimation error at step k (what it is and "
           "what it leaves out: below), so tr Φ is its bound on the node's mean-square error E‖x_k − x̂_{i,k}‖². "
           "It has no multipliers σ, β, hence no conditions (28)-(29); a node that diverged has none (NaN).", ""]
    if isinstance(meta.get("carried"), list):
        out += ["Each node carries only its region and the states its ball's measurements and their dynamics need "
                "(`--carry region`; `carried` in `schedule.json`): its Φ is over those states, the same numbers as "
                "the whole-state design's there, and every trace in this report (the verdict, the figures, the "
                "tables) is over its region, against the open loop and the references on the same states.", ""]
    traj = meta.get("trajectory")
    out.append("It holds along the simulated run it was computed on"
               + (f": {md_escape(traj)}." if isinstance(traj, str) and traj else
                  " (the seeded run of the scenario that `cfdesign design` simulates)."))
    out.append("")
    replay = meta.get("replay")
    out += [("Replaying the schedule: " + md_escape(replay) + "." if isinstance(replay, str) and replay else
             "A filter that replays this schedule on another run keeps the gains, not the guarantee."), ""]
    out += ["A feasibility map (`cfdesign feasibility`) asks another question: whether the stationary recursion at "
            "the operating point, with the expected number of received packets, has a bounded fixed point. Its "
            "report explains when the two disagree.", ""]
    return out


def _settings_section(s: _Schedule) -> list[str]:
    meta = s.meta
    mode = meta.get("mode")
    out = ["## Design settings", ""]
    rule = _rule_of(mode)
    out += rule.report_settings(meta, text) if rule is not None else []
    if is_num(meta.get("gate")) and not meta.get("gate"):
        out += ["No χ² gate on the neighbour packets: every received packet is used.", ""]
    if meta.get("gate"):
        out += [f"χ² gate on the neighbour packets with false-rejection probability {meta['gate']:g}: a packet whose "
                "difference to the node's own prediction is improbable for its predicted covariance is dropped as "
                "if lost. Which packets pass depends on the errors, so with the gate the bound is validated by "
                "Monte Carlo only (`study consensus-robot` checks it).", ""]
    facts = [("mode", mode), ("ε", meta.get("epsilon")), ("σ (fixed)", meta.get("sigma_fixed")),
             ("β (fixed)", meta.get("beta_fixed")), ("τ", meta.get("tau") if _fixed_multipliers(mode) else None),
             ("δ (bound on the injected signal, ‖ξ‖ ≤ δ)", meta.get("delta")), ("nodes", meta.get("nodes")),
             ("steps", meta.get("steps")), ("seed of the run", meta.get("seed"))]
    out += [f"- {k}: {md_escape(fmt_num(v))}" for k, v in facts if v is not None and not isinstance(v, (dict, list))]
    out.append("")
    opts = meta.get("options")
    if isinstance(opts, dict):
        given = {k: v for k, v in opts.items() if v is not None}
        if given:
            out += ["The options the design was made with (the scenario's defaults merged with the given ones; "
                    "the rest are the package's defaults):", "", *generic(given)]
    return out


def _linearisation_section(meta: Mapping) -> list[str]:
    lin = meta.get("linearization")
    U, V = meta.get("U"), meta.get("V")
    if lin is None and U is None and V is None:
        return []
    out = ["## Linearisation", "",
           "The filter linearises f and h_i at the node's own estimates; the remainders are bounded as U Ω e and "
           "V_i Θ e with ‖Ω‖, ‖Θ‖ ≤ 1, which is what U and V_i enter (26)-(27) for.", ""]
    if lin == "fixed":
        out += ["Linearisation `fixed`: U and V_i are the constant matrices below.", ""]
        if meta.get("remainder_structure") is not None:
            out += ["The remainders act on the error in the prior's units, U Ω W e and V_i Θ W e with W = P0^(-1/2) "
                    f"= {md_escape(matrix_text(meta['remainder_structure']))} (the prior scalings of mode "
                    "`scheduled`: the Hessians whitened by the prior over its ellipsoid); the sensors' remainders "
                    "at one error are bounded jointly, so that opposite curvatures cancel.", ""]
    elif isinstance(lin, str):
        radius = meta.get("radius")
        out += [f"Linearisation `{md_escape(lin)}`: U and V_i are re-derived at every node and step from the "
                f"model's Hessians over the {md_escape(fmt_num(radius))}-sigma ellipsoid of Φ"
                + (" (restricted to the variables the model is nonlinear in)" if lin == "structured" else "")
                + "; the matrices below only fix the shapes.", ""]
    if U is not None:
        out += [f"- U = {md_escape(matrix_text(U))}"]
    if isinstance(V, list) and V:
        texts = [matrix_text(v) for v in V]
        sensors = meta.get("sensors") if isinstance(meta.get("sensors"), list) else []
        if len(set(texts)) == 1:
            out.append(f"- V_i = {md_escape(texts[0])} at every sensor")
        else:
            for i, t in enumerate(texts):
                name = sensors[i].get("name") if i < len(sensors) and isinstance(sensors[i], dict) else None
                out.append(f"- V_{i}" + (f" ({md_escape(name)})" if name else "") + f" = {md_escape(t)}")
    return out + [""]


def _probabilities(entries) -> tuple[str, list]:
    ps = [e[2] for e in entries if isinstance(e, list) and len(e) == 3 and is_num(e[2])]
    if not ps:
        return "", []
    if min(ps) == max(ps):
        return f"{fmt_num(ps[0])} on each of the {len(ps)} channels", ps
    return f"from {fmt_num(min(ps))} to {fmt_num(max(ps))} over the {len(ps)} channels", ps


def attack_lines(attacks) -> list[str]:
    """The attack specification (``AttackSpec.describe()``) in words; unknown keys generically."""
    if not isinstance(attacks, Mapping) or not attacks:
        return []
    out = []
    ch = attacks.get("channels") if isinstance(attacks.get("channels"), Mapping) else {}
    for key, name in (("dos", "DoS (the packet is lost)"), ("fdi", "false-data injection (ξ is added to it)")):
        words, _ = _probabilities(ch.get(key))
        prob = attacks.get(f"{key}_prob")
        if words:
            out.append(f"- {name}: probability {md_escape(words)}")
        elif prob is not None:
            out.append(f"- {name}: probability {md_escape(compact(prob))}")
    sig = attacks.get("signal")
    if isinstance(sig, Mapping):
        comps = sig.get("component_names") or sig.get("components")
        out.append(f"- injected signal: law {md_escape(compact(sig.get('law')))}, amplitude "
                   f"{md_escape(compact(sig.get('amplitude')))}"
                   + (f" on the components {md_escape(compact(comps))}" if comps is not None else ""))
        rest = {k: v for k, v in sig.items() if k not in ("law", "amplitude", "components", "component_names")}
        if rest:
            out.append(f"- signal, further: {md_escape(compact(rest))}")
    elif sig is not None:
        out.append(f"- injected signal: {md_escape(compact(sig))}")
    if attacks.get("delta") is not None:
        out.append(f"- δ = {md_escape(fmt_num(attacks['delta']))}: the bound ‖ξ‖ ≤ δ the design assumes")
    for key, name in (("uplink_dos", "uplink DoS"), ("uplink_fdi", "uplink FDI")):
        if attacks.get(key) is not None:
            out.append(f"- {name} (the centralized filters' uplinks, per node): {md_escape(compact(attacks[key]))}")
    out.append("")
    if ch:
        dos = {(e[0], e[1]): e[2] for e in ch.get("dos") or [] if isinstance(e, list) and len(e) == 3}
        fdi = {(e[0], e[1]): e[2] for e in ch.get("fdi") or [] if isinstance(e, list) and len(e) == 3}
        varied = len(set(dos.values())) > 1 or len(set(fdi.values())) > 1
        if varied and len(set(dos) | set(fdi)) <= 200:
            rows = [[md_cell(f"{fmt_num(j)} → {fmt_num(i)}"), md_cell(fmt_num(dos.get((i, j)))),
                     md_cell(fmt_num(fdi.get((i, j))))] for i, j in sorted(set(dos) | set(fdi), key=str)]
            out += ["Per channel:", "", *md_table(["channel (from → to)", "DoS", "FDI"], rows)]
        extra = {k: v for k, v in ch.items() if k not in ("dos", "fdi", "format")}
        if extra:
            out += generic(extra)
    rest = {k: v for k, v in attacks.items()
            if k not in ("dos_prob", "fdi_prob", "channels", "signal", "delta", "uplink_dos", "uplink_fdi")}
    return out + (generic(rest) if rest else [])


def _attack_section(meta: Mapping) -> list[str]:
    lines = attack_lines(meta.get("attacks"))
    if not lines and meta.get("delta") is None:
        return []
    out = ["## Attacks", "", "What the channels between the nodes suffer (the simulated run draws its DoS and FDI "
           "pattern from these probabilities; the bound uses the realised pattern):", "", *lines]
    if not lines:
        out += [f"- δ = {md_escape(fmt_num(meta['delta']))}: the bound ‖ξ‖ ≤ δ the design assumes", ""]
    return out


def _network_section(meta: Mapping) -> list[str]:
    lines = network_lines(meta.get("network"))
    return ["## Network", "", *lines] if lines else []


def scenario_lines(name, params) -> list[str]:
    """The scenario's description and parameter table (design and feasibility reports)."""
    spec = scenario_spec(name)
    out = []
    if spec is not None:
        summary = spec.summary.strip()
        if summary and summary[-1] not in ".!?":
            summary += "."
        out += [f"**{md_escape(spec.name)}**: {md_escape(spec.title)}. {md_escape(summary)}".rstrip(), ""]
    elif isinstance(name, str):
        out += [f"**{md_escape(name)}** (a model file or an in-memory model, not a built-in scenario).", ""]
    if isinstance(params, Mapping) and params:
        out += ["The scenario's parameters (`--set NAME=VALUE` changes one):", "", *params_table(spec, params)]
    return out


def _scenario_section(meta: Mapping) -> list[str]:
    lines = scenario_lines(meta.get("scenario"), meta.get("params"))
    return ["## Scenario and parameters", "", *lines] if lines else []


def software_lines(meta: Mapping) -> list[str]:
    """The software versions a design or a map was computed with (``versions``)."""
    v = meta.get("versions")
    if not isinstance(v, Mapping) or not v:
        return []
    return ["Computed with:", "", *md_table(["component", "version"], [[md_cell(k), md_cell(compact(x))]
                                                                     for k, x in v.items()], ["l", "l"])]


def _files_section(meta: Mapping, shapes: Mapping | None, note: str | None, figures: list[str]) -> list[str]:
    out = ["## Files and reproduction", ""]
    schema = meta.get("schema")
    out.append(f"- `schedule.json`: schema `{md_escape(schema)}`; feasibility, ε, σ, β, tr Φ per node and step, "
               "every violated condition with its node, step and margin" if isinstance(schema, str) else
               "- `schedule.json`")
    if shapes:
        out.append("- `schedule.npz`: " + ", ".join(f"`{k}` {md_escape(' x '.join(map(str, shape)))}"
                                                    for k, shape in shapes.items() if re.fullmatch(r"\w+", k)))
    if note:
        out.append(f"- {md_escape(note)}: the margins, the gains and the figures are left out")
    for name in figures:
        out.append(f"- `{name}`: drawn by this report from schedule.npz")
    out.append("")
    out += software_lines(meta)
    out += rerun_lines(meta, "this design")
    return out + recorded_elsewhere(meta, _KNOWN, "schedule.json")


def _summary_table(s: _Schedule, tight) -> list[str]:
    """The nodes from the closest to failing (smallest margin, a violation first) to the farthest."""
    if not s.nodes:
        return []
    at = {t[0]: t for t in tight}

    def order(i):
        first = s.first_hard(i)
        return (first is None, first.get("step") if first and is_num(first.get("step")) else 0,
                at[i][3] if i in at else float("inf"), i)

    rows = []
    for rank, i in enumerate(sorted(range(s.nodes), key=order), 1):
        first = s.first_hard(i)
        t = at.get(i)
        rows.append([f"{rank}", f"{i}", md_cell(s.sensor(i)) or "—",
                     md_cell(_plain_violation(first)) if first else "none",
                     f"{t[1]} at step {t[2]}, margin {fmt_num(t[3])}" if t else "—", md_cell(_final_bound(s, i))])
    if not s.multipliers:  # no condition to be tight
        return md_table(["rank", "node", "sensor", "first violation", "final tr Φ"], [r[:4] + r[5:] for r in rows],
                        ["r", "r", "l", "l", "r"])
    return md_table(["rank", "node", "sensor", "first violation", "tightest condition", "final tr Φ"], rows,
                    ["r", "r", "l", "l", "l", "r"])


_VERDICT_LEAD = {"certified": "Certified", "vacuous": "Not certified: the bound is vacuous",
                 "infeasible": "Not certified: infeasible",
                 "not computed": "Not certified: the certificate was not computed",
                 "not steady": "Not certified: the bound is not steady"}  # the last: a file of an earlier version


def _lead(meta: Mapping) -> str:
    """The first line's lead: the verdict (:data:`_VERDICT_LEAD`) and, for a certified or vacuous bound of a file
    that records it, the separate claim ``bounded`` and the ``growing`` qualifier."""
    v = meta.get("verdict")
    lead = _VERDICT_LEAD[v]
    if v not in ("certified", "vacuous") or not isinstance(meta.get("bounded"), bool):
        return lead
    if v == "vacuous":
        return lead + ("; bounded" if meta["bounded"] else "; not bounded")
    growing = ", still growing at the horizon" if meta.get("growing") is True else ""
    return lead + (f"{growing}{',' if growing else ''} and bounded" if meta["bounded"] else f"{growing}; not bounded")


def gain_rule_record(meta: Mapping) -> dict | None:
    """The design's gain rule ``{name, runtime, needs, deployable}``: ``schedule.json``'s ``gain_rule``, or for a file
    written before it existed the rule of its mode (:mod:`rules`); None when neither says."""
    from designer.rule import RUNTIMES

    rec = meta.get("gain_rule")
    if (isinstance(rec, Mapping) and rec.get("runtime") in RUNTIMES and isinstance(rec.get("needs"), str)
            and isinstance(rec.get("deployable"), bool)):
        return dict(rec, name=str(rec.get("name", meta.get("mode"))))
    rule = _rule_of(meta.get("mode"))
    return None if rule is None else rule.describe()


def _runtime_lines(meta: Mapping) -> list[str]:
    """The design's run-time class in words (the report's first lines): what a node needs to apply its gains and,
    for a rule that is not deployable, that it is an oracle."""
    rule = gain_rule_record(meta)
    if rule is None:
        return []
    name, runtime, needs = md_escape(rule["name"]), rule["runtime"], md_escape(rule["needs"].rstrip("."))
    if not rule["deployable"]:
        return [f"**Gain rule {name}, run time {runtime}: an oracle, a reference of what the structure can reach, not "
                f"a design to deploy.** Its gains need {needs}: no node can apply them with what it has.", ""]
    return [f"**Gain rule {name}, run time {runtime}: deployable on the nodes.** To apply its gains a node needs "
            f"{needs}.", ""]


def _verdict_words(s: _Schedule) -> str | None:
    """The report's first line: the verdict of ``schedule.json`` in words (None for a schedule written without one)."""
    from designer.rule import caveat
    from designer.verdict import GATE_CLAUSE, describe

    v, detail = s.meta.get("verdict"), s.meta.get("verdict_detail")
    if v not in _VERDICT_LEAD or not isinstance(detail, Mapping):
        return None
    try:
        text = describe(detail)
    except (TypeError, ValueError):  # a damaged detail: the verdict alone
        text = v
    text = text.split(": ", 1)[1] if ": " in text else text
    rule = gain_rule_record(s.meta)
    oracle = f"; {caveat(rule)}" if rule is not None and caveat(rule) else ""
    oracle += f"; {GATE_CLAUSE}" if s.meta.get("gate") else ""
    return f"**{_lead(s.meta)}.** {md_escape(text[0].upper() + text[1:])}{md_escape(oracle)}."


def _summary_sentence(s: _Schedule, tight, validated: bool = False) -> str:
    lead = "**Use this schedule?** "
    if s.meta.get("verdict") == "not computed":
        return (lead + "Not as a certified design: its certificate was not computed ("
                f"{md_escape(_not_computed_reason(s))}), so it claims no bound; it is not infeasible, and a study "
                "(`cfdesign study consensus-robot`) measures what it delivers.")
    held = "(28)-(29) held at every node and step" if s.multipliers else "every node's bound was finite at every step"
    if s.feasible and s.meta.get("certified") is False:
        return (lead + f"Not as a certified design: {held}, but the bound is "
                f"{md_escape(s.meta.get('verdict'))}, so it does not show what the filter delivers (see the first "
                "line; change the options or the horizon and design again).")
    if not s.feasible:
        first = s.first_hard()
        line = lead + "No: the design is infeasible along this run"
        if first is not None:
            line += f"; the first violation is {_violation_words(first)}, and from there on that node has no bound"
        return line + " (change the options, e.g. `--mode tuned`, or the attacks, and design again)."
    line = lead + f"Yes, along this run: {held}"
    if tight:
        i, cond, step, m, *_ = min(tight, key=lambda t: (t[3], t[0]))
        line += f"; the node closest to failing is {i} ({cond} at step {step}, margin {fmt_num(m)})"
    if s.meta.get("growing") is True:
        line += ("; the bound still grows at the horizon: it is certified over these steps, "
                 + ("and bounded by the design's stationary certificate" if s.meta.get("bounded") is True else
                    "not beyond them (not bounded)"))
    if s.theorem2:
        line += ("; Theorem 2's condition failed at some node-steps, which does not contradict this: it would claim "
                 "more (the error bounded for all time), and the verdict rests on Theorem 1's bound (see the verdict)")
    check = ("[Validation](#validation) checks it on fresh runs" if validated else
             "a study replaying the schedule (`cfdesign study consensus-robot ... --schedule DIR`) checks it over "
             "many runs")
    return line + f". The bound holds for this run's linearisation points and DoS pattern; {check}."


def _summary(s: _Schedule, tight, figures: list[str], validated: bool = False) -> list[str]:
    first = _verdict_words(s)
    out = ["## Summary", "", *([first, ""] if first else []),
           f"One seeded run of {s.steps} steps, so no Monte Carlo intervals: the nodes from the closest to failing "
           "to the farthest (a violation first, then the smallest margin of (28)-(29))." if s.multipliers else
           f"One seeded run of {s.steps} steps, so no Monte Carlo intervals: the nodes, a violation or divergence "
           "first (this rule's bound has no margins of (28)-(29)).", "", *_summary_table(s, tight)]
    if "fig_trace_bound.png" in figures:
        out += figure_lines(1, "fig_trace_bound.png", FIGURES["fig_trace_bound.png"])
    return out + [_summary_sentence(s, tight, validated), ""]


def render_design(meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray] | None = None,
                  figures: list[str] = (), note: str | None = None, extra: list[str] | None = None) -> str:
    """The design report as Markdown from ``schedule.json`` (``meta``) and ``schedule.npz`` (``arrays``); ``extra``:
    the automatic design's sections (:func:`studies.reports.auto.auto_section`), after the verdict."""
    s, arrays, note = _schedule(meta, arrays, note)
    return _render(s, meta, figures, note, extra)


def _render(s: "_Schedule", meta: Mapping[str, Any], figures, note: str | None, extra: list[str] | None) -> str:
    """:func:`render_design` of the schedule ``s`` already read."""
    scenario = meta.get("scenario") if isinstance(meta.get("scenario"), str) else "unnamed scenario"
    mode = meta.get("mode") if isinstance(meta.get("mode"), str) else "unknown"
    head = [f"# Design report: {md_escape(scenario)}", "",
            f"A gain schedule of the distributed consensus filter ({md_escape(mode)} mode) for {s.nodes} nodes over "
            f"{s.steps} steps, computed by `cfdesign design` along one seeded simulated run. Nodes and steps are "
            "numbered from 0, as in `schedule.json`.", "", *_runtime_lines(meta)]
    if extra and extra[0] == "## Automatic design":
        head += ["", "**Picked by the automatic design** (`cfdesign design` without `--mode`): "
                 "[Automatic design](#automatic-design) lists every candidate, its cost, predicted error and verdict"
                 + ("; [Validation](#validation) gives its errors on fresh runs." if "## Validation" in extra else
                    ".")]
    tight = _tightest(s) if s.m28 is not None and s.m29 is not None else []
    return document(head, [
        _verdict_section(s, tight), extra or [], _conditioning_section(meta), _binding_section(s, tight),
        _figure_section(list(figures)),
        _node_section(s), _meaning_section(s), _settings_section(s), _linearisation_section(meta),
        _attack_section(meta), _network_section(meta), observability_section(meta), _scenario_section(meta),
        assumption_section(meta.get("assumptions"), "Everything the paper leaves open and the scenario or the "
                           "design had to decide:"),
        _files_section(meta, s.shapes, note, list(figures))], _summary(s, tight, list(figures),
                                                                   "## Validation" in (extra or [])))


def design_report(d: Path, into: Path | None = None) -> tuple[str, dict[str, bytes], str]:
    """The design report of directory ``d`` (which holds ``schedule.json``): (Markdown, figures, title).

    Draws ``fig_trace_bound.png`` (from ``schedule.npz``, else from the JSON's
    ``trace_bound``) and ``fig_margins.png`` (from ``schedule.npz``) into ``into`` (default ``d``).
    """
    into = d if into is None else into
    meta = read_record(d, "schedule.json", "cfdesign.schedule/1", "a design's")
    s, _, note = _schedule(meta, *_load_arrays(d))
    scenario = meta.get("scenario") if isinstance(meta.get("scenario"), str) else "design"
    mode = meta.get("mode") if isinstance(meta.get("mode"), str) else ""
    label = f"{scenario[:80]}, {mode[:40]} design".replace("$", r"\$")  # no mathtext from a name; a title's size
    from ..figures import figure_batch

    figures = []
    with figure_batch():  # drawn side by side where there are cores
        if s.trace is not None and s.trace.size:
            _trace_figure(into / "fig_trace_bound.png", s, f"{label}: tr Φ per node (gaps: no bound)")
            figures.append("fig_trace_bound.png")
        if s.m28 is not None and s.m29 is not None and s.m28.size:
            _margin_figure(into / "fig_margins.png", s, f"{label}: margins of (28) and (29) per node")
            figures.append("fig_margins.png")
        auto = auto_section(d, into) if (d / "candidates.json").is_file() else \
            (validation_section(d), []) if (d / "validation.json").is_file() else None
    if auto is not None:
        figures += auto[1]
    images = {name: (into / name).read_bytes() for name in figures}
    md = _render(s, meta, [f for f in figures if auto is None or f not in auto[1]], note,
                 None if auto is None else auto[0])
    return md, images, f"cfdesign design report: {scenario}"
