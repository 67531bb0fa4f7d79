"""The study report: what a study (``results.json`` of schema ``cfdesign.study/1``) compares and found.

It opens with a one-screen **summary** (:func:`summary_blocks`): the filters ranked by the
study's accuracy metric with their 95 % intervals, time per step (measured on this machine:
shown, never ranked; :data:`studies.reports.text.DURATION` is what a measured time looks like)
and messages, whether each can be told apart from the best, the trade-off figure (``fig_tradeoff.png``, drawn from the
same blocks by :func:`studies.figures.tradeoff_figure`) and the pick in one sentence, never
stronger than the intervals allow (overlapping intervals: the data cannot tell the filters
apart).  Then, for a reader who has not read the papers: the pick metric by metric, what
the study compares and why (the study's own words, :func:`studies.study_registry.study_text`),
the scenario and its parameters, the attacks, our tables beside the paper's published
numbers, Monte Carlo intervals, sweeps, detection, the bound check and what diverged, the
figures (captioned by the study), every assumption, the software and the command line that
computes the same numbers again (from the recorded ``invocation``).  Raw fields the report
does not explain stay in ``results.json`` (the report names them).  A multi-scenario study
is summarised and ranked per scenario: errors in different units are never ranked together.
Cost is ranked by the messages counted; no sentence depends on a measured time, so the same
command writes the same report, its measured durations aside.

Every key of the results file is optional except that the file must be a JSON
object: a section whose data are missing is left out.
"""
from __future__ import annotations

import fnmatch
import math
import re
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

from designer.rule import DEPLOYABLE, FILTER_RUNTIMES, runtime_label
from designer.validation import InputError

from ..study_registry import StudyText, study_text
from .design import attack_lines
from .text import (MEASURED, assumption_section, ci_pair, compact, demote, document, figure_lines, fmt_dur, fmt_num,
                   generic, is_num, is_time_key, md_cell, md_escape, md_table, metric_value, params_table,
                   read_record, recorded_elsewhere, rerun_lines, scenario_spec, with_ci)

__all__ = ["render_markdown", "study_report", "GLOSSARY", "SummaryBlock", "summary_blocks", "bound_verdict",
           "figure_caption", "FEW_RUNS"]

FEW_RUNS = 30  # below this many runs the bootstrap intervals are rough, and the report says so

# Metric names: a short header and what the number means.
GLOSSARY: dict[str, tuple[str, str]] = {
    "rmse_position": ("RMSE position", "root-mean-square error of the estimated position, averaged over the time "
                                       "steps; lower is better"),
    "rmse_velocity": ("RMSE velocity", "the same for the velocity"),
    "rmse": ("RMSE", "root-mean-square error as the study defines it (see the assumptions); lower is better"),
    "rmse_truth": ("RMSE vs truth", "root-mean-square error against the true state"),
    "rmse_state": ("RMSE per state", "root-mean-square error of each state component"),
    "rmse_run0": ("RMSE run 0", "the RMSE of the first run alone"),
    "rmse_position_median_run": ("RMSE position, median run", "the median over runs of each run's position RMSE "
                                                              "(robust to a few bad runs)"),
    "rmse_median_run": ("RMSE, median run", "the median over runs of each run's RMSE (robust to a few bad runs)"),
    "rmse_state_median_run": ("RMSE per state, median run", "the median over runs of each run's RMSE"),
    "node_spread": ("node spread", "mean distance of the nodes' estimates from their average (consensus "
                                   "reached when small)"),
    "time_per_step_s": ("time per step (measured)", "wall-clock time per time step and run, measured on this "
                                                    "machine (how is among the assumptions); it varies from one run "
                                                    "of the same command to the next, so it ranks nothing"),
    "time_per_step_single_run_s": ("time per step, one run (measured)", "the same, timed on a single run"),
    "wall_time_s": ("wall time (measured)", "total wall-clock time, measured on this machine"),
    "messages_per_step": ("messages per step", "messages sent over the network per time step (a message lost to "
                                               "DoS still counts)"),
    "communications": ("communications", "messages sent over the network, as the study counts them (see the "
                                         "assumptions)"),
    "collapsed_steps": ("collapsed steps", "steps at which every particle weight vanished and the filter had to "
                                           "restart from its prediction"),
    "collapsed_runs": ("runs with a collapse", "runs with at least one collapsed step"),
    "diverged_fraction": ("diverged runs", "share of runs whose estimate blew up (left out of the RMSE)"),
    "final_ess": ("final ESS", "effective sample size of the particles at the last step"),
    "resampled_fraction": ("resampled steps", "share of steps at which the particles were resampled"),
    "particles": ("particles", "number of particles"),
}

# keys of results.json the report presents (the rest are named at its end and left to the file)
_HANDLED = {"schema", "study", "scenario", "runs", "particles", "steps", "seed", "engine", "threads", "workers", "mode",
            "assumptions", "wall_time_s", "versions", "filters", "sweeps", "paper", "params", "detection",
            "timing_s", "attacks", "recommendation", "by_scenario", "invocation"}
_ATTACK_WORDS = re.compile(r"attack|dos|fdi|decep|flip|jam|bit_error|dropout|eta_bar")


def _label(key: str) -> str:
    return GLOSSARY.get(key, (key.replace("_", " "), ""))[0]


def figure_caption(name: str, text: StudyText | None) -> str:
    """The caption of figure ``name``: the study's (:attr:`StudyText.figures`; a key with ``*`` matches a family of
    files, and ``{}`` in its caption is replaced by the part ``*`` matched, e.g. a scenario), else a sentence that
    says no caption was recorded."""
    figures = text.figures if text is not None else {}
    if name in figures:
        return figures[name]
    for pattern, caption in figures.items():
        if "*" in pattern and fnmatch.fnmatchcase(name, pattern):
            head, tail = pattern.split("*", 1)
            return caption.replace("{}", name[len(head):len(name) - len(tail)])
    return f"A figure the study wrote; it recorded no caption for {name}."


# ---------------------------------------------------------------------------------------------------------------
# The numbers the report ranks: one block per scenario.


def _filters(results: Mapping) -> dict[str, dict]:
    f = results.get("filters")
    if not isinstance(f, dict):
        return {}
    return {str(k): v for k, v in f.items() if isinstance(v, dict)}


def _accuracy_metrics(results: Mapping, text: StudyText | None) -> list[tuple[str, str]]:
    filters = _filters(results)
    present = lambda key: any(key in m for m in filters.values())  # noqa: E731
    wanted = list(text.accuracy) if text is not None and text.accuracy else []
    if not wanted:
        for key in ("rmse_position", "rmse", "rmse_state"):
            if present(key):
                wanted.append((key, _label(key)))
                break
        if present("rmse_velocity"):
            wanted.append(("rmse_velocity", _label("rmse_velocity")))
    return [(k, lab) for k, lab in wanted if present(k)]


def _component_values(filters: Mapping[str, dict], key: str) -> list[tuple[str, dict[str, tuple[float, Any]]]]:
    """Per component of a metric: {filter: (value, ci)}; a scalar metric has one component named ''."""
    comps: dict[str, dict[str, tuple[float, Any]]] = {}
    for name, m in filters.items():
        v, ci = m.get(key), m.get(key + "_ci95")
        if is_num(v):
            comps.setdefault("", {})[name] = (float(v), ci)
        elif isinstance(v, list):
            cis = ci if isinstance(ci, list) and len(ci) == len(v) else [None] * len(v)
            for i, (x, c) in enumerate(zip(v, cis)):
                if is_num(x):
                    comps.setdefault(f"x{i + 1}", {})[name] = (float(x), c)
    return list(comps.items())


def _standing(values: Mapping[str, tuple[float, Any]], runs) -> tuple[str | None, dict[str, str]]:
    """The filter with the lowest finite value, and each other's standing against it: ``"tied"`` (95 % intervals
    overlap: the data cannot tell them apart), ``"apart"`` (the intervals are disjoint) or ``"no interval"``
    (one of the two has none; with fewer than 2 runs no interval counts)."""
    finite = {n: vc for n, vc in values.items() if is_num(vc[0]) and math.isfinite(vc[0])}
    if not finite:
        return None, {}
    best = min(finite, key=lambda n: finite[n][0])
    one_run = is_num(runs) and runs < 2
    bpair = None if one_run else ci_pair(finite[best][1])
    out = {}
    for n, (_, ci) in finite.items():
        if n == best:
            continue
        pair = None if one_run else ci_pair(ci)
        if bpair is None or pair is None:
            out[n] = "no interval"
        elif pair[0] <= bpair[1] and bpair[0] <= pair[1]:
            out[n] = "tied"
        else:
            out[n] = "apart"
    return best, out


def _messages(m: Mapping) -> tuple[float, bool] | None:
    """A filter's messages: (count, per step?) from ``messages_per_step`` or the study's ``communications``."""
    if is_num(m.get("messages_per_step")):
        return float(m["messages_per_step"]), True
    if is_num(m.get("communications")):
        return float(m["communications"]), False
    return None


def bound_verdict(bc) -> tuple[str, str] | None:
    """(word, sentence) for a consensus filter's ``bound_check``: the study's own ``verdict`` where it records one,
    else from the share of checked (node, step) pairs whose empirical covariance exceeded the bound."""
    if not isinstance(bc, Mapping):
        return None
    verdict = bc.get("verdict")
    checked, total = bc.get("pairs_checked"), bc.get("pairs_total")
    where = (f" (checked at {fmt_num(checked)} of {fmt_num(total)} (node, step) pairs)"
             if is_num(checked) and is_num(total) else "")
    frac = bc.get("fraction_exceeding")
    if isinstance(verdict, str) and verdict:
        why = bc.get("reason") or bc.get("verdict_reason")
        return verdict, f"the bound check's verdict: {verdict}" + (f" ({why})" if isinstance(why, str) else "") + where
    if not is_num(frac):
        need = bc.get("min_runs_per_pair")
        return "not checked", ("the bound was not checked: no (node, step) pair had a bound in enough runs"
                               + (f" (at least {fmt_num(need)}: run more)" if is_num(need) else ""))
    if frac > 0:
        return "exceeded", f"the empirical error covariance exceeded the bound at {fmt_num(100 * frac, 3)} % of the " \
                           f"checked pairs{where}"
    return "holds", f"the empirical error covariance stayed within the bound at every checked pair{where}"


@dataclass(frozen=True)
class SummaryBlock:
    """One scenario's numbers for the summary: every filter's value of the ranking metric and its interval."""

    title: str  # the scenario in a multi-scenario study, else ""
    filters: Mapping[str, dict]
    key: str | None  # the ranking metric (None: the study records none)
    label: str  # its words, with the component of a metric per state
    values: Mapping[str, tuple[float | None, tuple[float, float] | None]]
    references: frozenset  # the filters that are never the pick (reference_kind)
    runs: Any
    benchmarks: frozenset = frozenset()  # the study's own benchmarks (StudyText.references)

    def kind(self, name: str) -> str | None:
        """Why ``name`` is never the pick (None: it is an option): its recorded ``runtime`` when no node can run it
        (``"global"``: an oracle; ``"centralized"``: a fusion centre), else ``"benchmark"`` (the study's)."""
        rt = self.filters.get(name, {}).get("runtime")
        if rt in FILTER_RUNTIMES and rt not in DEPLOYABLE:
            return rt
        return "benchmark" if name in self.benchmarks else None

    def reference_note(self, name: str) -> str | None:
        """The kind of :meth:`kind` in a few words."""
        kind = self.kind(name)
        if kind is None:
            return None
        return "benchmark (not an option under attack)" if kind == "benchmark" else f"reference ({runtime_label(kind)})"

    @property
    def drawable(self) -> bool:
        return any(v is not None and is_num(self.filters[n].get("time_per_step_s"))
                   and self.filters[n]["time_per_step_s"] > 0 for n, (v, _) in self.values.items())

    @property
    def counts_messages(self) -> bool:
        return any(_messages(m) is not None for m in self.filters.values())

    def messages_text(self, name: str) -> str:
        msg = _messages(self.filters.get(name, {}))
        if msg is None:
            return "messages not counted"
        return f"{fmt_num(msg[0])} {'msgs/step' if msg[1] else 'messages'}"

    def standing(self) -> tuple[str | None, dict[str, str]]:
        """The best option (not a reference) and every other option's standing (:func:`_standing`)."""
        cand = {n: vc for n, vc in self.values.items() if n not in self.references and vc[0] is not None}
        return _standing(cand, self.runs)

    def ranked(self) -> list[str]:
        """The options from the lowest value, then the references from the lowest value (each without a value last)."""
        return sorted(self.values, key=lambda n: (n in self.references, self.values[n][0] is None,
                                                  self.values[n][0] or 0.0))

    def best_reference(self) -> str | None:
        """The reference with the lowest value (None: no reference has one)."""
        refs = [n for n in self.references if self.values[n][0] is not None]
        return min(refs, key=lambda n: self.values[n][0]) if refs else None


def _references(filters: Mapping[str, Mapping], text: StudyText | None) -> frozenset:
    """The filters that are never the pick: the study's benchmarks (``text.references``) and every filter whose
    recorded ``runtime`` no node can run (``global``: an oracle; ``centralized``: a fusion centre)."""
    return frozenset(n for n, m in filters.items()
                     if n in (text.references if text else ())
                     or (m.get("runtime") in FILTER_RUNTIMES and m.get("runtime") not in DEPLOYABLE))


def _block(title: str, results: Mapping, text: StudyText | None) -> SummaryBlock:
    filters = _filters(results)
    refs = _references(filters, text)
    acc = _accuracy_metrics(results, text)
    values: dict[str, tuple[float | None, tuple[float, float] | None]] = {n: (None, None) for n in filters}
    key, label = (acc[0] if acc else (None, "accuracy"))
    if key is not None:
        comps = _component_values(filters, key)
        if comps:
            comp, vals = comps[0]
            label = f"{label} of {comp}" if comp else label
            for n, (v, ci) in vals.items():
                if math.isfinite(v):
                    values[n] = (v, ci_pair(ci))
    return SummaryBlock(title, filters, key, label, values, refs, results.get("runs"),
                        frozenset(n for n in (text.references if text else ()) if n in filters))


def summary_blocks(results: Mapping, text: StudyText | None = None) -> list[SummaryBlock]:
    """The summary's blocks: one per scenario of a multi-scenario study, else one (``text``: the study's texts,
    by default those of ``results["study"]``)."""
    text = study_text(results.get("study")) if text is None else text
    blocks = _scenario_blocks(results)
    if blocks:
        return [_block(name, {**results, **b}, text) for name, b in blocks.items()]
    return [_block("", results, text)] if _filters(results) else []


# ---------------------------------------------------------------------------------------------------------------
# The summary.


def _names(names: Sequence[str]) -> str:
    names = [md_escape(n) for n in names]
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def _notes(name: str, b: SummaryBlock) -> str:
    m, runs = b.filters[name], b.runs
    notes = []
    if name in b.references:
        notes.append(b.reference_note(name))
    div = m.get("diverged_runs")
    ndiv = len(div) if isinstance(div, list) else div if is_num(div) else None
    if ndiv is None and is_num(m.get("diverged_fraction")) and is_num(runs):
        ndiv = round(m["diverged_fraction"] * runs)
    if isinstance(m.get("infeasible"), str):  # a design that could not start: not run, never ranked
        notes.append(f"infeasible, not run: {m['infeasible']}")
    elif b.values[name][0] is None:
        notes.append("no value: diverged in every run" if ndiv and is_num(runs) and ndiv >= runs else "no value")
    elif ndiv:
        notes.append(f"diverged in {fmt_num(ndiv)}" + (f" of {fmt_num(runs)}" if is_num(runs) else "")
                     + " runs (left out)")
    if is_num(m.get("collapsed_runs")) and m["collapsed_runs"] > 0:
        notes.append(f"collapsed in {fmt_num(m['collapsed_runs'])} runs")
    bc = m.get("bound_check")
    bv = bound_verdict(bc)
    if bv is not None:
        checked = (f" ({fmt_num(bc['pairs_checked'])} of {fmt_num(bc['pairs_total'])} (node, step) pairs checked"
                   if is_num(bc.get("pairs_checked")) and is_num(bc.get("pairs_total")) else "")
        if checked and bv[0] == "not checked" and is_num(bc.get("min_runs_per_pair")):
            checked += f": a pair needs a bound in {fmt_num(bc['min_runs_per_pair'])} runs"
        notes.append(f"bound {bv[0]}{checked + ')' if checked else ''}")
    return "; ".join(md_cell(x) for x in notes)


def _ranked_table(b: SummaryBlock) -> list[str]:
    """The options ranked; the references (never the pick) apart, in a table of their own after them."""
    best, standing = b.standing()
    words = {"tied": "cannot be told apart", "apart": "worse (intervals apart)", "no interval": "no interval"}
    has_msgs = any(_messages(m) is not None for m in b.filters.values())
    per_step = any((_messages(m) or (0, False))[1] for m in b.filters.values())
    rows: dict[bool, list] = {False: [], True: []}  # options, references
    rank = 0
    for n in b.ranked():
        v, ci = b.values[n]
        ref = n in b.references
        ranked = v is not None and not ref
        rank += ranked
        against = ("best" if n == best else ("benchmark" if b.kind(n) == "benchmark" else "reference") if ref else
                   words.get(standing.get(n, ""), "—"))
        t = b.filters[n].get("time_per_step_s")
        row = [str(rank) if ranked else "—", md_cell(n), with_ci(v, ci) if v is not None else "—", against,
               fmt_dur(t) if is_num(t) else "—"]
        if has_msgs:
            msg = _messages(b.filters[n])
            row.append(fmt_num(msg[0]) if msg is not None else "—")
        rows[ref].append(row + [_notes(n, b) or "—"])
    header = ["rank", "filter", md_cell(f"{b.label} [95 % interval]"), "against the best",
              f"time per step ({MEASURED})"]
    align = ["r", "l", "r", "l", "r"]
    if has_msgs:
        header.append("messages per step" if per_step else "messages")
        align.append("r")
    out = md_table(header + ["notes"], rows[False], align + ["l"]) if rows[False] else []
    if rows[True]:
        out += [f"**References**, apart and never the pick: {_reference_words(b)}.", ""]
        out += md_table(header + ["notes"], rows[True], align + ["l"])
    return out


def _reference_words(b: SummaryBlock) -> str:
    """What the block's references are, by kind."""
    kinds = {b.kind(n) for n in b.references}
    words = {"global": "global oracles, whose gains need the network's joint state (what the structure could reach)",
             "centralized": "centralized filters, a fusion centre receiving every sensor's uplink (no node runs them "
                            "alone)",
             "benchmark": "benchmarks, which see data no filter has under attack"}
    return "; ".join(words[k] for k in ("global", "centralized", "benchmark") if k in kinds)


_REFERENCE_WORDS = {
    "global": "a global oracle: what the structure could reach with the network's joint state, not a filter to deploy",
    "centralized": "a fusion centre receiving every uplink: what centralisation could reach, not a filter the nodes "
                   "run",
    "benchmark": "a benchmark: it sees data no filter has under attack"}


def _pick_sentence(b: SummaryBlock) -> str:
    """The pick in one sentence, no stronger than the intervals: never a reference; the best reference beside it."""
    line = _pick(b)
    ref = b.best_reference()
    if ref is None:
        return line
    v, ci = b.values[ref]
    return (line[:-1] + f"; for reference, {md_escape(ref)} reaches {with_ci(v, ci)} "
            f"({_REFERENCE_WORDS[b.kind(ref)]}).")


def _pick(b: SummaryBlock) -> str:
    """The pick among the options in one sentence (ending with a full stop), no stronger than the intervals."""
    lead = "**Which to pick" + (f" on {md_escape(b.title)}" if b.title else "") + ":** "
    label = md_escape(b.label)
    best, standing = b.standing()
    runs = b.runs
    if best is None:
        return lead + f"none can be named: no filter (references aside) has a finite {label}."
    v, ci = b.values[best]
    times = {n: b.filters[n].get("time_per_step_s") for n in b.values}
    if not standing:
        return lead + f"{md_escape(best)}, the only filter with a {label} ({with_ci(v, ci)})."
    if ci is None or all(s == "no interval" for s in standing.values()):
        second = min(standing, key=lambda n: b.values[n][0])
        return (lead + f"{md_escape(best)} has the lowest {label} ({fmt_num(v)}), but no 95 % interval was recorded, "
                f"so the data cannot say whether it is better than {md_escape(second)} "
                f"({fmt_num(b.values[second][0])}).")
    tied = [n for n, s in standing.items() if s == "tied"]
    few = is_num(runs) and runs < FEW_RUNS
    if tied:
        group = [best] + tied
        line = (lead + f"the data cannot tell {_names(group)} apart on {label} (their 95 % intervals overlap that of "
                f"{md_escape(best)}, the lowest, {with_ci(v, ci)})")
        msgs = {n: _messages(b.filters[n]) for n in group}
        counts = {n: m for n, m in msgs.items() if m is not None}
        if len({c[0] for c in counts.values()}) > 1:  # cost ranked by the messages counted, never by a measured time
            low = min(c[0] for c in counts.values())
            fewest = [n for n, c in counts.items() if c[0] == low]
            line += (f"; among them {_names(fewest)} {'sends' if len(fewest) == 1 else 'send'} the fewest messages"
                     f"{' per step' if counts[fewest[0]][1] else ''} ({fmt_num(low)})")
        return line + (f"; more than {fmt_num(runs)} runs would narrow the intervals." if few else ".")
    line = lead + f"{md_escape(best)}: the lowest {label} ({with_ci(v, ci)}), its 95 % interval apart from every " \
                  "other filter's"
    msg = _messages(b.filters[best])
    if msg is not None:
        line += f"; it sends {fmt_num(msg[0])} messages{' per step' if msg[1] else ''}"
    if is_num(times[best]):
        line += f" ({fmt_dur(times[best])} per step, {MEASURED})"
    return line + (f" (from only {fmt_num(runs)} runs, whose intervals are rough)." if few else ".")


def _summary_section(results: Mapping, text: StudyText | None, figures: Sequence[str]) -> list[str]:
    blocks = summary_blocks(results, text)
    if not blocks:
        return []
    out = ["## Summary", ""]
    n = len(blocks[0].filters)
    what = [f"{n} filters" if n != 1 else "1 filter"]
    if is_num(results.get("runs")):
        what.append(f"{fmt_num(results['runs'])} Monte Carlo runs"
                    + (f" of {fmt_num(results['steps'])} steps" if is_num(results.get("steps")) else ""))
    scen = results.get("scenario")
    out += [f"{', '.join(what)} on {md_escape(scen) if isinstance(scen, str) else 'the study scenario'}"
            + (f", seed {fmt_num(results['seed'])}" if is_num(results.get("seed")) else "")
            + ". Ranked by " + ("each scenario's " if len(blocks) > 1 else "")
            + f"{md_escape(blocks[0].label)} (lower is better); a filter whose 95 % interval overlaps the best's "
              "cannot be told apart from it at this number of runs.", ""]
    from ..figures import TRADEOFF

    if len(blocks) == 1:  # one scenario: no heading of its own
        blocks = [replace(blocks[0], title="")]
    for b in blocks:
        if b.title:
            out += [f"### {md_escape(b.title)}", ""]
        out += _ranked_table(b)
    if TRADEOFF in figures:
        caption = ("Accuracy (the ranking metric, with its 95 % interval) against the time per step (measured on the "
                   "machine that ran the study: a measurement, not a ranking), one colour per filter as in every "
                   "figure of this report")
        if any(b.counts_messages for b in blocks):
            caption += "; the legend gives each filter's messages"
        if any(b.references for b in blocks):
            caption += "; hollow markers are the references, never the pick"
        out += figure_lines(1, TRADEOFF, caption + ".")
    for b in blocks:
        out += [_pick_sentence(b), ""]
    return out


def _pick_accuracy(label: str, comp: str, values: Mapping[str, tuple[float, Any]], runs) -> str:
    what = f"{label} of {comp}" if comp else label
    best, standing = _standing(values, runs)
    if best is None:
        return ""
    bv, bci = values[best]
    line = f"**Most accurate ({md_escape(what)}):** {md_escape(best)}, {with_ci(bv, bci)}"
    others = list(standing)
    if ci_pair(bci) is None or (is_num(runs) and runs < 2):
        if others:
            second = min(others, key=lambda n: values[n][0])
            line += (f"; next {md_escape(second)}, {fmt_num(values[second][0])}. No confidence interval was "
                     f"recorded for this metric, so whether the difference is significant cannot be said"
                     + (f" from {runs} runs." if is_num(runs) else "."))
        else:
            line += "."
        return line
    overlap = [n for n, s in standing.items() if s == "tied"]
    no_ci = [n for n, s in standing.items() if s == "no interval"]
    if overlap:
        line += (". Its 95 % interval overlaps that of " + ", ".join(
            f"{md_escape(n)} ({with_ci(*values[n])})" for n in overlap)
                 + ": the difference is not significant at this number of runs; the data cannot tell them apart "
                   "on this metric.")
    elif others:
        line += ". Its 95 % interval overlaps no other filter's: the lead is significant."
    else:
        line += "."
    if no_ci:
        line += " (No interval for " + ", ".join(md_escape(n) for n in no_ci) + ".)"
    return line


def _scenario_blocks(results: Mapping) -> dict[str, Mapping]:
    """A multi-scenario study's per-scenario blocks (``by_scenario``: each with its own ``filters``), else {}."""
    blocks = results.get("by_scenario")
    if isinstance(blocks, dict) and blocks and all(isinstance(b, dict) and isinstance(b.get("filters"), dict)
                                                   for b in blocks.values()):
        return blocks
    return {}


def _per_scenario(results: Mapping, section, heading: str, intro: str, *args) -> list[str]:
    """``section`` once per scenario block, under ``heading``: errors in different scenarios are in
    different units and are never ranked together."""
    out = [f"## {heading}", "", intro, ""]
    for name, b in _scenario_blocks(results).items():
        sub = {**results, **b, "scenario": name, "by_scenario": None}
        lines = section(sub, *args)
        if lines:
            out += [f"### {md_escape(name)}", "", *_demote_lines(lines[2:])]
    return out


def _demote_lines(lines: list[str]) -> list[str]:
    return ["#" + ln if ln.startswith("##") else ln for ln in lines]


def _pick_section(results: Mapping, text: StudyText | None) -> list[str]:
    if _scenario_blocks(results):
        return _per_scenario(results, _pick_section, "Which filter to pick, metric by metric",
                             "Per scenario: filters are ranked only against the filters of the same scenario.",
                             text)
    filters = _filters(results)
    block = _block("", results, text)
    refs = block.references
    cand = {n: m for n, m in filters.items() if n not in refs}
    if not cand:
        return []
    out = ["## Which filter to pick, metric by metric", ""]
    out.append("Derived from the numbers of this run only (lower is better for every metric below"
               + (f"; references left out: {', '.join(md_escape(r) for r in sorted(refs))}, being "
                  f"{_reference_words(block)}" if refs else "")
               + "). Differences between filters whose 95 % intervals overlap are not significant.")
    out.append("")
    items = []
    acc = _accuracy_metrics(results, text)
    first_best = None
    for key, label in acc:
        for comp, values in _component_values(cand, key):
            line = _pick_accuracy(label, comp, values, results.get("runs"))
            if line:
                items.append(line)
                if first_best is None:
                    first_best = _standing(values, results.get("runs"))[0]
    # a filter that diverged in every run has no accuracy: never recommend it for its cost or messages
    usable = {n: m for n, m in cand.items()
              if not (is_num(m.get("diverged_fraction")) and m["diverged_fraction"] >= 1)
              and not any(k in m and m[k] is None for k in ("rmse_position", "rmse"))}
    # cost is ranked by the messages counted (deterministic), never by a measured time
    msgs = {n: _messages(m) for n, m in usable.items()}
    comms = {n: m[0] for n, m in msgs.items() if m is not None}
    if comms:
        per_step = any(m[1] for m in msgs.values() if m is not None)
        what, unit = ("messages per step", " per step") if per_step else ("communications", "")
        low = min(comms.values())
        fewest = [n for n, c in comms.items() if c == low]
        if len(set(comms.values())) == 1:
            items.append(f"**{what.capitalize()}:** every filter sends the same number of messages{unit} "
                         f"({fmt_num(low)}).")
        else:
            line = f"**Fewest {what}:** {', '.join(md_escape(n) for n in fewest)} ({fmt_num(low)} messages{unit}"
            if first_best is not None and first_best in comms and first_best not in fewest:
                line += f"; the most accurate, {md_escape(first_best)}, sends {fmt_num(comms[first_best])}"
            items.append(line + ").")
    if any(is_num(m.get("time_per_step_s")) for m in usable.values()):
        items.append(f"**Time per step:** {MEASURED} and listed under Timings; it varies from one run of the same "
                     "command to the next, so no filter is ranked or picked by it.")
    det = results.get("detection")
    if isinstance(det, dict):
        attacked = {n: d for n, d in det.items()
                    if isinstance(d, dict) and n not in refs and is_num(d.get("attacks")) and d["attacks"] > 0}
        for key, label in (("missed", "fewest missed attacks"), ("false_alarms", "fewest false alarms")):
            vals = {n: d[key] for n, d in attacked.items() if is_num(d.get(key))}
            if vals:
                low = min(vals.values())
                names = [n for n, v in vals.items() if v == low]
                items.append(f"**{label.capitalize()}:** {', '.join(md_escape(n) for n in names)} "
                             f"({fmt_num(low)} in total over the runs).")
    warn = []
    for n, m in cand.items():
        if is_num(m.get("collapsed_runs")) and m["collapsed_runs"] > 0:
            warn.append(f"{md_escape(n)} collapsed in {fmt_num(m['collapsed_runs'])} run(s)")
        if is_num(m.get("diverged_fraction")) and m["diverged_fraction"] > 0:
            warn.append(f"{md_escape(n)} diverged in {fmt_num(100 * m['diverged_fraction'], 3)} % of the runs")
        elif is_num(m.get("diverged_runs")) and m["diverged_runs"] > 0:
            warn.append(f"{md_escape(n)} diverged in {fmt_num(m['diverged_runs'])} run(s)")
        bv = bound_verdict(m.get("bound_check"))
        if bv is not None and bv[0] not in ("holds", "not checked"):
            warn.append(f"{md_escape(n)}: {md_escape(bv[1])}")
    if warn:
        items.append("**Caution:** " + "; ".join(warn) + ".")
    runs = results.get("runs")
    if is_num(runs) and runs < FEW_RUNS:
        items.append(f"**Few runs:** only {fmt_num(runs)} Monte Carlo runs; the intervals are wide and rough. "
                     "Run the study with more runs (`--runs`) before relying on the ranking.")
    return out + [f"- {i}" for i in items] + [""]


def _filters_section(results: Mapping, text: StudyText | None) -> list[str]:
    filters = _filters(results)
    if not filters:
        return []
    block = _block("", results, text)
    out = ["### The filters", ""]
    for name, m in filters.items():
        desc = (text.filters.get(name) if text else None) or m.get("description") or ""
        extras = []
        for key in ("family", "engine", "note"):
            if key == "note" and text is not None and name in text.filters:
                continue
            if key == "engine" and m.get(key) == results.get("engine"):
                continue  # the study's engine is listed with the run's settings
            if isinstance(m.get(key), str) and m[key] != desc:
                extras.append(m[key] if key == "note" else f"{key} {m[key]}")
        line = f"- **{md_escape(name)}**"
        if desc:
            line += f": {md_escape(desc)}"
        if extras:
            line += f" ({md_escape('; '.join(extras))})"
        if block.kind(name) is not None:
            line += f" — {block.reference_note(name)}"
        out.append(line)
    return out + [""]


# how the computation was spread over this machine (the Timings section's): the numbers do not depend on it
_WHERE_IT_RAN = (("threads", "threads per worker"), ("workers", "worker processes"))


def _run_facts(results: Mapping) -> list[str]:
    facts = []
    for key, label in (("scenario", "scenario"), ("runs", "Monte Carlo runs"), ("particles", "particles"),
                       ("steps", "time steps per run"), ("seed", "seed"), ("mode", "design mode"),
                       ("engine", "engine")):
        v = results.get(key)
        if v is not None and not isinstance(v, (dict, list)):
            facts.append(f"- {label}: {md_escape(fmt_num(v))}")
    return facts


def _scenario_section(results: Mapping) -> list[str]:
    if _scenario_blocks(results):
        return _per_scenario(results, _scenario_section, "Scenarios and parameters",
                             "Each scenario with the parameters used (`--set NAME=VALUE` changes one in every "
                             "compared scenario that has it).")
    spec = scenario_spec(results.get("scenario"))
    params = results.get("params")
    out = ["## Scenario and parameters", ""]
    if spec is not None:
        summary = spec.summary.strip()
        if summary and summary[-1] not in ".!?":
            summary += "."
        out += [f"**{md_escape(spec.name)}**: {md_escape(spec.title)}. {md_escape(summary)}".rstrip(), ""]
    facts = _run_facts(results)
    if facts:
        out += ["How this run was made:", "", *facts, ""]
    if isinstance(params, dict) and params:
        out += ["The scenario's parameters (`--set NAME=VALUE` changes one):", "", *params_table(spec, params)]
    return out if len(out) > 2 else []


def _attack_section(results: Mapping, text: StudyText | None) -> list[str]:
    params = results.get("params") if isinstance(results.get("params"), dict) else {}
    names = [k for k in (text.attack_params if text else ()) if k in params]
    if not names:
        names = [k for k in params if _ATTACK_WORDS.search(str(k))]
    blocks = _scenario_blocks(results)
    declared = {name: b["attacks"]["declared"] for name, b in blocks.items()
                if isinstance(b.get("attacks"), dict) and isinstance(b["attacks"].get("declared"), dict)}
    attacks = results.get("attacks")
    if not (text and text.attacks) and not names and not isinstance(attacks, dict) and not declared:
        return []
    out = ["## Under which attacks", ""]
    if text and text.attacks:
        out += [text.attacks, ""]
    if names:
        out += ["Attack settings of this run:", ""]
        out += [f"- `{k}` = {md_escape(compact(params[k]))}" for k in names]
        out.append("")
    if isinstance(attacks, dict) and attacks:
        lines = attack_lines(attacks)
        if lines:
            out += ["The attacks the runs drew from:", "", *lines]
    for name, spec in declared.items():
        out += [f"### {md_escape(name)}", "", *attack_lines(spec)]
    return out


def _glossary_section(results: Mapping) -> list[str]:
    filters = _filters(results)
    keys = [k for k in GLOSSARY if any(k in m for m in filters.values())]
    if not keys:
        return []
    out = ["### How to read the numbers", ""]
    out += [f"- **{md_escape(GLOSSARY[k][0])}** (`{k}`): {md_escape(GLOSSARY[k][1])}." for k in keys]
    if any(k.endswith("_ci95") for m in filters.values() for k in m):
        out.append("- **[lo, hi]** after a number: its 95 % Monte Carlo confidence interval (a bootstrap over "
                   "the runs, unless the assumptions say otherwise).")
    return out + [""]


def _key_metric_table(filters: Mapping[str, dict]) -> list[str]:
    keys: list[str] = []
    for m in filters.values():
        for k, v in m.items():
            if k in keys or k.endswith("_ci95") or k.endswith("_curve") or k == "wall_time_s":
                continue
            if is_num(v) or (isinstance(v, list) and 0 < len(v) <= 6 and all(is_num(x) for x in v)):
                keys.append(k)
    order = list(GLOSSARY)
    keys.sort(key=lambda k: order.index(k) if k in order else len(order))
    keys = keys[:10]
    if not keys:
        return []
    rows = [[md_cell(n)] + [metric_value(k, m.get(k), m.get(k + "_ci95")) if k in m else "—" for k in keys]
            for n, m in filters.items()]
    return md_table(["filter"] + [md_cell(_label(k)) for k in keys], rows)


def _paper_side_by_side(filters: Mapping[str, dict], paper: Mapping) -> list[str]:
    pf = paper.get("filters")
    if not isinstance(pf, dict) or not pf:
        return []
    keys: list[str] = []
    for m in pf.values():
        if isinstance(m, dict):
            keys += [k for k, v in m.items() if is_num(v) and k not in keys]
    if not keys:
        return []
    names = list(filters) + [n for n in pf if n not in filters]
    header = ["filter"]
    for k in keys:
        header += [md_cell(f"{_label(k)} (ours)"), md_cell(f"{_label(k)} (paper)")]
    rows = []
    for n in names:
        ours, theirs = filters.get(n, {}), pf.get(n) if isinstance(pf.get(n), dict) else {}
        row = [md_cell(n)]
        for k in keys:
            row += [metric_value(k, ours.get(k), ours.get(k + "_ci95")) if k in ours else "—",
                    metric_value(k, theirs.get(k)) if k in theirs else "—"]
        rows.append(row)
    return ["Our numbers beside the paper's:", "", *md_table(header, rows)]


def _paper_text(paper: Mapping) -> list[str]:
    out = []
    if isinstance(paper.get("source"), str):
        out.append(f"Source: {md_escape(paper['source'])}.")
    for key in ("claim", "note"):
        if isinstance(paper.get(key), str):
            out.append(f"{'The paper claims' if key == 'claim' else 'Note'}: {md_escape(paper[key])}")
    out = [x for line in out for x in (line, "")]
    claims = paper.get("claims")
    if isinstance(claims, list) and claims:
        out += ["The paper's claims:", ""] + [f"- {md_escape(compact(c))}" for c in claims] + [""]
    settings = {k: v for k, v in paper.items() if k not in ("source", "claim", "note", "claims", "filters")
                and isinstance(v, (bool, int, float, str))}
    if settings:
        out += ["The paper's settings:", ""]
        out += [f"- {md_escape(k)}: {md_escape(compact(v))}" for k, v in settings.items()] + [""]
    rest = {k: v for k, v in paper.items() if isinstance(v, (dict, list)) and v and k not in ("claims", "filters")}
    for k, v in rest.items():
        out += [f"#### Paper: {md_escape(k.replace('_', ' '))}", "", *generic(v), ""]
    return out


def _results_section(results: Mapping, table_md: str | None) -> list[str]:
    filters = _filters(results)
    paper = results.get("paper") if isinstance(results.get("paper"), dict) else {}
    out = ["## Results", ""]
    if table_md and table_md.strip():
        out += ["### The study's tables (ours beside the paper's published numbers)", "",
                demote(table_md.strip(), 3), ""]
    else:
        table = _key_metric_table(filters)
        if table:
            out += ["### Our numbers", "", *table]
        out += _paper_side_by_side(filters, paper)
    text = _paper_text(paper)
    if text:
        out += ["### What the paper reports", "", *text]
    return out if len(out) > 2 else []


def _ci_section(results: Mapping) -> list[str]:
    rows = []
    for name, m in _filters(results).items():
        for k, ci in m.items():
            if not k.endswith("_ci95"):
                continue
            base = k[: -len("_ci95")]
            v = m.get(base)
            pairs = [(base, v, ci)]
            if isinstance(v, list) and isinstance(ci, list) and len(v) == len(ci):
                pairs = [(f"{base}[{i + 1}]", x, c) for i, (x, c) in enumerate(zip(v, ci))]
            for label, x, c in pairs:
                pair = ci_pair(c)
                if pair is None:
                    continue
                rel = "—"
                if is_num(x) and x != 0:
                    rel = f"{fmt_num(100 * (pair[1] - pair[0]) / 2 / abs(x), 2)} %"
                rows.append([md_cell(name), f"`{label}`", fmt_num(x),
                             f"[{fmt_num(pair[0], 3)}, {fmt_num(pair[1], 3)}]", rel])
    if not rows:
        return []
    runs = results.get("runs")
    return ["## Monte Carlo confidence intervals", "",
            f"95 % intervals over the {fmt_num(runs) + ' ' if is_num(runs) else ''}runs (how they are computed is "
            "among the assumptions). The half-width in per cent of the value shows how settled each number is; "
            "more runs narrow the intervals roughly as one over the square root of the number of runs.", "",
            *md_table(["filter", "metric", "value", "95 % interval", "± half-width"], rows)]


def _sweep_section(results: Mapping) -> list[str]:
    sweeps = results.get("sweeps")
    if not isinstance(sweeps, dict) or not sweeps:
        return []
    out = ["## Sweeps", "", "One parameter varied at a time, everything else at its default.", ""]
    preferred = ["rmse_position", "rmse_velocity", "rmse", "rmse_truth", "time_per_step_s"]
    for param, by_value in sweeps.items():
        if not isinstance(by_value, dict) or not by_value:
            continue
        cols: list[tuple[str, str]] = []
        for per_filter in by_value.values():
            if not isinstance(per_filter, dict):
                continue
            for fname, m in per_filter.items():
                if not isinstance(m, dict):
                    if is_num(m) and (fname, "") not in cols:
                        cols.append((fname, ""))
                    continue
                keys = ([k for k in preferred if is_num(m.get(k))] or [k for k in ("rmse_state",) if k in m]
                        or [k for k, v in m.items() if is_num(v)][:4])
                cols += [(fname, k) for k in keys if (fname, k) not in cols]
        if not cols:
            continue

        def entry(value, f, k):
            per_filter = by_value[value]
            m = per_filter.get(f) if isinstance(per_filter, dict) else None
            if k == "":
                return fmt_num(m) if is_num(m) else "—"
            if isinstance(m, dict) and k in m:
                return metric_value(k, m[k], m.get(k + "_ci95"))
            return "—"

        metrics = {k for _, k in cols}
        if len(metrics) == 1 and len({f for f, _ in cols}) == len(cols):
            # one metric: a row per filter reads better than a column per filter
            (k,) = metrics
            out += [f"### {md_escape(param)}: {md_escape(_label(k)) if k else 'value'} of each filter", ""]
            header = ["filter"] + [md_cell(f"{param} = {v}") for v in by_value]
            rows = [[md_cell(f)] + [entry(v, f, k) for v in by_value] for f, _ in cols]
        else:
            out += [f"### {md_escape(param)}", ""]
            header = [md_cell(param)] + [md_cell(f"{f}: {_label(k)}" if k else f) for f, k in cols]
            rows = [[md_cell(v)] + [entry(v, f, k) for f, k in cols] for v in by_value]
        out += md_table(header, rows)
    return out if len(out) > 4 else []


def _detection_section(results: Mapping) -> list[str]:
    det = results.get("detection")
    if not isinstance(det, dict) or not det:
        return []
    rows = {n: d for n, d in det.items() if isinstance(d, dict)}
    keys = [k for k in ("attacks", "detected", "missed", "stealthy", "false_alarms")
            if any(is_num(d.get(k)) for d in rows.values())]
    if not rows or not keys:
        return []
    out = ["## Attack detection", "", "Totals over the runs at the default settings: attacks counted as missed are "
           "above the smallest norm the detector is designed for; smaller undetected ones count as stealthy "
           "(per-run counts and run 0's are in results.json).", ""]
    return out + md_table(["filter", *(k.replace("_", " ") for k in keys)],
                          [[md_cell(n), *(fmt_num(d.get(k)) for k in keys)] for n, d in rows.items()])


def _bound_rows(filters: Mapping[str, dict]) -> list[str]:
    rows, reasons = [], []
    for n, m in filters.items():
        bc = m.get("bound_check")
        bv = bound_verdict(bc)
        if bv is None:
            continue
        rt = bc.get("run_test") if isinstance(bc.get("run_test"), Mapping) else {}
        steps = bc.get("fill_steps") if isinstance(bc.get("fill_steps"), list) and len(bc["fill_steps"]) == 2 else None
        rows.append([md_cell(n), md_cell(bv[0]), fmt_num(bc.get("runs")),
                     f"{fmt_num(bc.get('pairs_checked'))} of {fmt_num(bc.get('pairs_total'))}",
                     fmt_num(bc.get("fraction_exceeding")), fmt_num(bc.get("trace_ratio_mean")),
                     fmt_num(rt.get("ratio_mean")), fmt_num(rt.get("ratio_max")),
                     fmt_num(bc.get("informative")) if is_num(bc.get("informative")) else "—",
                     (fmt_num(bc.get("fill")) + (f" (steps {fmt_num(steps[0])}..{fmt_num(steps[1])})" if steps else ""))
                     if is_num(bc.get("fill")) else "—"])
        reasons.append(f"- **{md_escape(n)}**: {md_escape(bv[1])}.")
    if not rows:
        return []
    return ["### Does the bound hold?", "",
            "Per consensus filter with a bound: the bound check's verdict and why; the runs it used; the (node, step) "
            "pairs where Φ was a bound in enough runs to compare, of all, and the share of them whose empirical "
            "error covariance exceeded the mean bound beyond Monte Carlo tolerance; the mean ratio tr P̂ / tr Φ over "
            "those pairs; each run's error energy over its bound's (mean and largest over the runs; a valid bound "
            "keeps the mean at most 1). Below 1 the bound is above the error. Then what the bound is worth, in the "
            "design's words: the runs whose bound is informative (below the open-loop covariance at every node and "
            "step, as `cfdesign design` certifies), and the fill, the runs' error energy over their bound's trace "
            "over the steps after the prior's transient (the design's window; 1 is a bound the errors fill). Every "
            "field of the check is in results.json.", "",
            *md_table(["filter", "verdict", "runs", "pairs checked", "share exceeding", "mean tr P̂ / tr Φ",
                       "run ratio, mean", "run ratio, largest", "runs informative", "fill"], rows,
                      ["l", "l", "r", "r", "r", "r", "r", "r", "r", "r"]),
            *reasons, ""]


def _feasible_rows(filters: Mapping[str, dict]) -> list[str]:
    rows = []
    for n, m in filters.items():
        fe = m.get("feasibility")
        if not isinstance(fe, dict):
            continue
        vd = m.get("verdicts") if isinstance(m.get("verdicts"), dict) else {}
        certified = (f"{fmt_num(vd.get('certified'))} of {fmt_num(sum(x for x in vd.values() if is_num(x)))}"
                     if is_num(vd.get("certified")) else "—")
        bounded = fmt_num(m["bounded_runs"]) if is_num(m.get("bounded_runs")) else "—"
        rows.append([md_cell(n), f"{fmt_num(fe.get('runs_feasible'))} of {fmt_num(fe.get('runs'))}", certified, bounded,
                     fmt_num(fe.get("first_violation_step_min")), fmt_num(fe.get("first_violation_step_median")),
                     fmt_num(fe.get("fraction_pairs_bounded"))])
    if not rows:
        return []
    return ["### Were the design conditions met?", "",
            "Per designed consensus filter: the runs in which (28)-(29) held at every node and step, the runs whose "
            "bound is certified (finite and below the open-loop covariance at every step: `verdicts` in results.json) "
            "and those whose bound is bounded (steady at the horizon: `bounded_runs`), the earliest and the median "
            "step of the first violation in the others, and the share of (node, step) "
            "pairs at which Φ was a bound.", "",
            *md_table(["filter", "runs meeting (28)-(29)", "runs certified", "runs bounded",
                       "first violation, earliest step", "median step", "share of pairs bounded"], rows,
                      ["l", "r", "r", "r", "r", "r", "r"])]


def _diverged_lines(filters: Mapping[str, dict]) -> list[str]:
    out = []
    for n, m in filters.items():
        runs = m.get("diverged_runs")
        if not isinstance(runs, list) or not runs or not all(isinstance(x, dict) for x in runs):
            continue
        ids = [fmt_num(x.get("run")) for x in runs]
        steps = [x["step"] for x in runs if is_num(x.get("step"))]
        why = Counter(re.sub(r"\s*\([^)]*\)|\bat step \d+", "", str(x.get("error", "not recorded"))).strip()
                      for x in runs)
        line = (f"- **{md_escape(n)}**: {len(runs)} run(s) diverged (run{'s' if len(ids) > 1 else ''} "
                f"{md_escape(', '.join(ids[:12]) + (', …' if len(ids) > 12 else ''))}")
        if steps:
            line += f"; first step {fmt_num(min(steps))}" + (f" to {fmt_num(max(steps))}" if max(steps) > min(steps)
                                                            else "")
        line += "): " + "; ".join(f"{md_escape(w)} ({c})" for w, c in why.most_common()) + "."
        out.append(line)
    if not out:
        return []
    return ["### What diverged", "", "A diverged run is left out of its filter's RMSE; each run's node, step and "
            "reason are in results.json (`diverged_runs`).", "", *out, ""]


def _details_section(results: Mapping) -> list[str]:
    filters = _filters(results)
    out = _bound_rows(filters) + _feasible_rows(filters)
    node_rows = {}
    for n, m in filters.items():
        nodes = m.get("nodes")
        if isinstance(nodes, list) and len(nodes) > 1 and all(isinstance(x, dict) for x in nodes):
            node_rows[n] = {f"node {x.get('node', i) + 1 if is_num(x.get('node', i)) else x.get('node')}":
                            x.get("rmse_position") for i, x in enumerate(nodes)}
    if node_rows:
        cols = list(dict.fromkeys(c for r in node_rows.values() for c in r))
        out += ["### Position RMSE of each node", "", *md_table(
            ["filter", *cols], [[md_cell(n), *(fmt_num(r.get(c)) for c in cols)] for n, r in node_rows.items()])]
    out += _diverged_lines(filters)
    return (["## Details per filter", ""] + out) if out else []


def _timing_section(results: Mapping) -> list[str]:
    filters = _filters(results)
    out = ["## Timings", "", f"Wall-clock times, {MEASURED}: they vary from one run of the same command to the next, "
           "and no other section depends on them.", ""]
    wall = results.get("wall_time_s")
    if is_num(wall):
        out += [f"The whole study took {fmt_dur(wall)} of wall-clock time (figures not included).", ""]
    facts = [f"{label}: {md_escape(fmt_num(results[key]))}" for key, label in _WHERE_IT_RAN
             if is_num(results.get(key))]
    if facts:
        out += ["Where it ran (this machine's, not the numbers'): " + ", ".join(facts) + ".", ""]
    keys = []
    for m in filters.values():
        keys += [k for k, v in m.items() if is_time_key(k) and is_num(v) and k not in keys]
    if keys:
        rows = [[md_cell(n)] + [fmt_dur(m.get(k)) if k in m else "—" for k in keys] for n, m in filters.items()]
        out += md_table(["filter"] + [md_cell(_label(k)) for k in keys], rows)
    timing = results.get("timing_s")
    if isinstance(timing, dict) and timing:
        out += ["Where the time went:", ""]
        for k, v in timing.items():
            if isinstance(v, dict):
                out.append(f"- {md_escape(k)}: " + ", ".join(f"{md_escape(a)} {fmt_dur(b)}" for a, b in v.items()))
            else:
                out.append(f"- {md_escape(k)}: {fmt_dur(v)}")
        out.append("")
    return out if len(out) > 4 else []


def _figures_section(figures: Sequence[str], text: StudyText | None) -> list[str]:
    from ..figures import TRADEOFF

    rest = [f for f in figures if f != TRADEOFF]
    if not rest:
        return []
    out = ["## Figures", "", "Each filter has one colour in every figure." if len(rest) > 1 else "", ""]
    first = 2 if TRADEOFF in figures else 1
    for i, name in enumerate(rest, first):
        out += figure_lines(i, name, figure_caption(name, text))
    return out


def _assumption_section(results: Mapping) -> list[str]:
    return assumption_section(results.get("assumptions"), "Everything the papers leave open and this study had to "
                              "decide, and how its numbers are defined:")


def _software_section(results: Mapping) -> list[str]:
    out = ["## Software and reproduction", ""]
    v = results.get("versions")
    if isinstance(v, dict) and v:
        out += md_table(["component", "version"], [[md_cell(k), md_cell(compact(x))] for k, x in v.items()], ["l", "l"])
    if results.get("schema") is not None:
        out += [f"Results schema `{md_escape(results['schema'])}`.", ""]
    out += rerun_lines(results, "this study")
    out += recorded_elsewhere(results, _HANDLED, "results.json")
    return out


def render_markdown(results: Mapping[str, Any], table_md: str | None = None,
                    figures: Sequence[str] = ()) -> str:
    """The report as Markdown.

    Parameters
    ----------
    results : mapping
        The contents of a study's ``results.json``; every key is optional.
    table_md : str, optional
        The study's ``table.md`` (its headings are nested under the report's).
    figures : sequence of str
        File names of the figures, relative to the report's directory.

    Returns
    -------
    str
        The Markdown text of ``report.md``; :func:`studies.reports.render.markdown_to_html` turns it
        into the HTML report.
    """
    study = results.get("study")
    text = study_text(study)
    name = study if isinstance(study, str) else "unnamed study"
    out = [f"# Study report: {md_escape(name)}", ""]
    if text is not None:
        out += [f"**{md_escape(text.title)}.**" + (f" Source paper: {md_escape(text.paper)}." if text.paper else ""),
                ""]
    sections: list[list[str]] = []
    intro = ["## What this study compares", ""]
    if text is not None:
        intro += [text.summary, ""]
    else:
        filters = _filters(results)
        desc = f"This report presents the results of the study **{md_escape(name)}**"
        if isinstance(results.get("scenario"), str):
            desc += f" on the scenario **{md_escape(results['scenario'])}**"
        if filters:
            desc += (f". It compares {len(filters)} filter(s) on the same runs: "
                     + ", ".join(md_escape(n) for n in filters))
        intro += [desc + ". The metrics, their intervals and the paper's numbers (if any) follow.", ""]
    intro += _filters_section(results, text)
    intro += _glossary_section(results)
    sections.append(intro)
    has_table = bool(table_md and table_md.strip())
    for part in (_pick_section(results, text), _scenario_section(results), _attack_section(results, text),
                 _results_section(results, table_md), _ci_section(results),
                 *(([], []) if has_table else (_sweep_section(results), _detection_section(results))),
                 _details_section(results), _timing_section(results),  # (the study's tables show those two)
                 _figures_section(figures, text), _assumption_section(results), _software_section(results)):
        sections.append(part)
    return document(out, sections, _summary_section(results, text, figures))


def study_report(d: Path) -> tuple[str, dict[str, bytes], str]:
    """The study report of directory ``d`` (which holds ``results.json``): (Markdown, figures, title).

    Reads ``results.json`` (a JSON object; a ``schema`` other than ``cfdesign.study/*`` is an
    error), ``table.md`` if present and every ``*.png`` of ``d``.
    """
    results = read_record(d, "results.json", "cfdesign.study/1", "a study's", required=False)
    table_md = None
    tfile = d / "table.md"
    if tfile.is_file():
        try:
            table_md = tfile.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"directory {str(d)!r}: table.md cannot be read: {exc}") from None
    figures = sorted(p.name for p in d.iterdir() if p.suffix.lower() == ".png" and p.is_file()
                     and not p.name.startswith("."))
    images = {}
    for name in figures:
        try:
            images[name] = (d / name).read_bytes()
        except OSError as exc:
            raise InputError(f"directory {str(d)!r}: figure {name} cannot be read: {exc}") from None
    study = results.get("study") if isinstance(results.get("study"), str) else "study"
    return render_markdown(results, table_md, figures), images, f"cfdesign report: {study}"
