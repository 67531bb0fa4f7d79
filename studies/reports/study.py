"""The study report: what a study (``results.json`` of schema ``cfdesign.study/1``) compares and found.

For a reader who has not read the papers: what the study compares and why (the
study's own words, :func:`studies.pipeline.study_text`), which filter to pick from
the numbers (significance from the 95 % intervals; per scenario for a
multi-scenario study; never a filter that diverged in every run), the scenario and
its parameters, the attacks, our tables beside the paper's published numbers,
Monte Carlo intervals, sweeps, detection, timings, the figures, every assumption,
keys this module does not know (shown generically under "Other recorded
results") and the software versions.

Every key of the results file is optional except that the file must be a JSON
object: a section whose data are missing is left out.
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any, Mapping, Sequence

from designer.validation import InputError

from ..pipeline import StudyText, study_text
from .text import (assumption_section, ci_pair, compact, demote, document, figure_lines, fmt_dur, fmt_num, generic,
                   is_num, is_time_key, md_cell, md_escape, md_table, metric_value, other_section, params_table,
                   read_record, scenario_spec, with_ci)

__all__ = ["render_markdown", "study_report", "GLOSSARY"]

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
    "rmse_state_median_run": ("RMSE per state, median run", "the median over runs of each run's RMSE"),
    "node_spread": ("node spread", "mean distance of the nodes' estimates from their average (consensus "
                                   "reached when small)"),
    "time_per_step_s": ("time per step", "wall-clock time per time step and run on this machine (how it is "
                                         "measured is among the assumptions)"),
    "time_per_step_single_run_s": ("time per step, one run", "the same, timed on a single run"),
    "wall_time_s": ("wall time", "total wall-clock time"),
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

_HANDLED = {"schema", "study", "scenario", "runs", "particles", "steps", "seed", "engine", "threads", "workers", "mode",
            "assumptions", "wall_time_s", "versions", "filters", "sweeps", "paper", "params", "detection",
            "timing_s", "attacks", "recommendation"}
_ATTACK_WORDS = re.compile(r"attack|dos|fdi|decep|flip|jam|bit_error|dropout|eta_bar")


def _label(key: str) -> str:
    return GLOSSARY.get(key, (key.replace("_", " "), ""))[0]


def _figure_caption(name: str, text: StudyText | None) -> str:
    if text is not None and name in text.figures:
        return text.figures[name]
    stem = Path(name).stem
    stem = stem[4:] if stem.startswith("fig_") else stem
    return stem.replace("_", " ").strip().capitalize() + "."


# ---------------------------------------------------------------------------------------------------------------
# The document.


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


def _pick_accuracy(label: str, comp: str, values: Mapping[str, tuple[float, Any]], runs) -> str:
    what = f"{label} of {comp}" if comp else label
    finite = {n: vc for n, vc in values.items() if math.isfinite(vc[0])}
    if not finite:
        return ""
    best = min(finite, key=lambda n: finite[n][0])
    bv, bci = finite[best]
    line = f"**Most accurate ({md_escape(what)}):** {md_escape(best)}, {with_ci(bv, bci)}"
    others = [n for n in finite if n != best]
    bpair = ci_pair(bci)
    if bpair is None:
        if others:
            second = min(others, key=lambda n: finite[n][0])
            line += (f"; next {md_escape(second)}, {fmt_num(finite[second][0])}. No confidence interval was "
                     f"recorded for this metric, so whether the difference is significant cannot be said"
                     + (f" from {runs} runs." if is_num(runs) else "."))
        else:
            line += "."
        return line
    overlap, apart, no_ci = [], [], []
    for n in others:
        pair = ci_pair(finite[n][1])
        if pair is None:
            no_ci.append(n)
        elif pair[0] <= bpair[1] and bpair[0] <= pair[1]:
            overlap.append(n)
        else:
            apart.append(n)
    if overlap:
        line += (". Its 95 % interval overlaps that of " + ", ".join(
            f"{md_escape(n)} ({with_ci(*finite[n])})" for n in overlap)
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
        return _per_scenario(results, _pick_section, "Which filter to pick",
                             "Per scenario: filters are ranked only against the filters of the same scenario.",
                             text)
    filters = _filters(results)
    refs = set(text.references if text else ())
    cand = {n: m for n, m in filters.items() if n not in refs}
    if not cand:
        return []
    out = ["## Which filter to pick", ""]
    out.append("Derived from the numbers of this run only (lower is better for every metric below"
               + (f"; benchmarks left out: {', '.join(md_escape(r) for r in sorted(refs & set(filters)))}, since no "
                  "filter can have their data under attack" if refs & set(filters) else "")
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
                    first_best = min(values, key=lambda n: values[n][0])
    # a filter that diverged in every run has no accuracy: never recommend it for its cost or messages
    usable = {n: m for n, m in cand.items()
              if not (is_num(m.get("diverged_fraction")) and m["diverged_fraction"] >= 1)
              and not ("rmse_position" in m and m["rmse_position"] is None)}
    times = {n: float(m["time_per_step_s"]) for n, m in usable.items()
             if is_num(m.get("time_per_step_s")) and m["time_per_step_s"] > 0}
    if times:
        cheap = min(times, key=times.get)
        line = f"**Cheapest per step:** {md_escape(cheap)}, {fmt_dur(times[cheap])} per time step"
        if first_best is not None and first_best != cheap and first_best in times:
            ratio = times[first_best] / times[cheap]
            line += f" ({fmt_num(ratio, 3)} times less than the most accurate, {md_escape(first_best)})"
        elif first_best == cheap:
            line += " — also the most accurate"
        line += ". Times are for this machine and engine; their ratios travel better than their values."
        items.append(line)
    comms = {n: m["communications"] for n, m in usable.items() if is_num(m.get("communications"))}
    if comms:
        low = min(comms.values())
        fewest = [n for n, c in comms.items() if c == low]
        if len(set(comms.values())) == 1:
            items.append(f"**Communications:** every filter sends the same number of messages ({fmt_num(low)}).")
        else:
            line = f"**Fewest communications:** {', '.join(md_escape(n) for n in fewest)} ({fmt_num(low)} messages"
            if first_best is not None and first_best in comms and first_best not in fewest:
                line += f"; the most accurate, {md_escape(first_best)}, sends {fmt_num(comms[first_best])}"
            items.append(line + ").")
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
    if warn:
        items.append("**Caution:** " + "; ".join(warn) + ".")
    runs = results.get("runs")
    if is_num(runs) and runs < 30:
        items.append(f"**Few runs:** only {fmt_num(runs)} Monte Carlo runs; the intervals are wide and rough. "
                     "Run the study with more runs (`--runs`) before relying on the ranking.")
    out += [f"- {i}" for i in items] + [""]
    rec = results.get("recommendation")
    if isinstance(rec, dict) and rec:
        out += ["The study's own recommendation (computed when it ran):", "", *generic(rec)]
    return out


def _filters_section(results: Mapping, text: StudyText | None) -> list[str]:
    filters = _filters(results)
    if not filters:
        return []
    refs = set(text.references if text else ())
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
        if name in refs:
            line += " — a benchmark, not an option under attack"
        out.append(line)
    return out + [""]


def _run_facts(results: Mapping) -> list[str]:
    facts = []
    for key, label in (("scenario", "scenario"), ("runs", "Monte Carlo runs"), ("particles", "particles"),
                       ("steps", "time steps per run"), ("seed", "seed"), ("mode", "design mode"),
                       ("engine", "engine"), ("threads", "threads per worker"), ("workers", "worker processes")):
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
    if not (text and text.attacks) and not names and not isinstance(results.get("attacks"), dict):
        return []
    out = ["## Under which attacks", ""]
    if text and text.attacks:
        out += [text.attacks, ""]
    if names:
        out += ["Attack settings of this run:", ""]
        out += [f"- `{k}` = {md_escape(compact(params[k]))}" for k in names]
        out.append("")
    attacks = results.get("attacks")
    if isinstance(attacks, dict) and attacks:
        out += ["The attacks as the study recorded them:", "", *generic(attacks)]
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
    return md_table([""] + [md_cell(_label(k)) for k in keys], rows)


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
    header = [""]
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
                and (v is None or isinstance(v, (bool, int, float, str)))}
    if settings:
        out += ["The paper's settings and scalars:", ""]
        out += [f"- {md_escape(k)}: {md_escape(compact(v))}" for k, v in settings.items()] + [""]
    rest = {k: v for k, v in paper.items() if isinstance(v, (dict, list)) and k not in ("claims", "filters")}
    for k, v in rest.items():
        out += [f"#### Paper: {md_escape(k)}", "", *generic(v), ""]
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
            header = [md_cell(_label(k) if k else "")] + [md_cell(f"{param} = {v}") for v in by_value]
            rows = [[md_cell(f)] + [entry(v, f, k) for v in by_value] for f, _ in cols]
        else:
            header = [md_cell(param)] + [md_cell(f"{f}: {_label(k)}" if k else f) for f, k in cols]
            rows = [[md_cell(v)] + [entry(v, f, k) for f, k in cols] for v in by_value]
        out += [f"### {md_escape(param)}", "", *md_table(header, rows)]
    return out if len(out) > 4 else []


def _detection_section(results: Mapping) -> list[str]:
    det = results.get("detection")
    if not isinstance(det, dict) or not det:
        return []
    out = ["## Attack detection", "", "Totals over the runs at the default settings: attacks counted as missed are "
           "above the smallest norm the detector is designed for; smaller undetected ones count as stealthy.", ""]
    return out + generic(det)


def _details_section(results: Mapping) -> list[str]:
    filters = _filters(results)
    out = []
    nested = []
    for m in filters.values():
        for k, v in m.items():
            if isinstance(v, dict) and k not in nested and not (k == "detection" and "detection" in results):
                nested.append(k)
    for k in nested:
        rows = {n: m[k] for n, m in filters.items() if isinstance(m.get(k), dict)}
        out += [f"### {md_escape(k.replace('_', ' '))}", "", *generic(rows), ""]
    node_rows = {}
    for n, m in filters.items():
        nodes = m.get("nodes")
        if isinstance(nodes, list) and len(nodes) > 1 and all(isinstance(x, dict) for x in nodes):
            node_rows[n] = {f"node {x.get('node', i) + 1 if is_num(x.get('node', i)) else x.get('node')}":
                            x.get("rmse_position") for i, x in enumerate(nodes)}
    if node_rows:
        out += ["### Position RMSE of each node", "", *generic(node_rows), ""]
    for n, m in filters.items():
        runs = m.get("diverged_runs")
        if isinstance(runs, list) and runs:
            out += [f"### Diverged runs of {md_escape(n)}", "", *generic(runs), ""]
    return (["## Details per filter", ""] + out) if out else []


def _timing_section(results: Mapping) -> list[str]:
    filters = _filters(results)
    out = ["## Timings", ""]
    wall = results.get("wall_time_s")
    if is_num(wall):
        out += [f"The whole study took {fmt_dur(wall)} of wall-clock time (figures not included).", ""]
    keys = []
    for m in filters.values():
        keys += [k for k, v in m.items() if is_time_key(k) and is_num(v) and k not in keys]
    if keys:
        rows = [[md_cell(n)] + [fmt_dur(m.get(k)) if k in m else "—" for k in keys] for n, m in filters.items()]
        out += md_table([""] + [md_cell(_label(k)) for k in keys], rows)
    timing = results.get("timing_s")
    if isinstance(timing, dict) and timing:
        out += ["Where the time went:", ""]
        for k, v in timing.items():
            if isinstance(v, dict):
                out.append(f"- {md_escape(k)}: " + ", ".join(f"{md_escape(a)} {fmt_dur(b)}" for a, b in v.items()))
            else:
                out.append(f"- {md_escape(k)}: {fmt_dur(v)}")
        out.append("")
    return out if len(out) > 2 else []


def _figures_section(figures: Sequence[str], text: StudyText | None) -> list[str]:
    if not figures:
        return []
    out = ["## Figures", ""]
    for i, name in enumerate(figures, 1):
        out += figure_lines(i, name, _figure_caption(name, text))
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
    study = results.get("study")
    if isinstance(study, str) and re.fullmatch(r"[\w.\-]+", study):
        cmd = f"cfdesign study {study} --out DIR"
        for key, flag in (("runs", "--runs"), ("particles", "--particles"), ("seed", "--seed")):
            if is_num(results.get(key)):
                cmd += f" {flag} {results[key]}"
        if isinstance(results.get("mode"), str) and re.fullmatch(r"\w+", results["mode"]):
            cmd += f" --mode {results['mode']}"
        out += [f"To run it again with the same seed: `{cmd}` (add `--set NAME=VALUE` for any parameter "
                "changed from its default above).", ""]
    return out if len(out) > 2 else []


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
    for part in (_pick_section(results, text), _scenario_section(results), _attack_section(results, text),
                 _results_section(results, table_md), _ci_section(results), _sweep_section(results),
                 _detection_section(results), _details_section(results), _timing_section(results),
                 _figures_section(figures, text), _assumption_section(results),
                 other_section(results, _HANDLED, "Other recorded results"), _software_section(results)):
        sections.append(part)
    return document(out, sections)


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
