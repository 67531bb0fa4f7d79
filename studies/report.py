"""Reports people want to read: ``DIR/report.md`` and a self-contained ``DIR/report.html`` for a study.

:func:`write_report` reads what a study wrote into its directory (``results.json``
of schema ``cfdesign.study/1``, ``table.md`` and the PNG figures) and presents
it for a reader who has not read the papers: what the study compares and why,
the scenario and its parameters, the attacks, our tables beside the paper's
published numbers, Monte Carlo intervals, sweeps, timings, every assumption,
the software versions, and which filter to pick given the numbers.

Both files come from one Markdown document, so they say the same thing: the
Markdown is written as is and converted to HTML by :func:`markdown_to_html`, a
small converter for the subset this module and the studies' ``table.md`` use
(headings, paragraphs, pipe tables, nested ``-`` lists, images, ``**bold**``,
`` `code` ``, in-page links).  All text is HTML-escaped; figures are inlined as
base64 ``data:`` URIs and the style sheet is inline, so the HTML loads nothing
and needs no JavaScript (its Content-Security-Policy forbids anything else).

Every key of the results file is optional except that the file must be a JSON
object: a section whose data are missing is left out, and keys this module does
not know are shown generically under "Other recorded results".
"""
from __future__ import annotations

import base64
import html
import json
import math
import os
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from designer.fileio import atomic_write
from designer.validation import InputError

from .pipeline import StudyText, study_text

__all__ = ["write_report", "render_markdown", "markdown_to_html"]


# ---------------------------------------------------------------------------------------------------------------
# What each study is about, in plain language.


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

_HANDLED = {"schema", "study", "scenario", "runs", "particles", "steps", "seed", "engine", "workers", "mode",
            "assumptions", "wall_time_s", "versions", "filters", "sweeps", "paper", "params", "detection",
            "timing_s", "attacks", "recommendation"}
_ATTACK_WORDS = re.compile(r"attack|dos|fdi|decep|flip|jam|bit_error|dropout|eta_bar")


# ---------------------------------------------------------------------------------------------------------------
# Numbers and text.


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _num(v, sig: int = 4) -> str:
    """A number with ``sig`` significant digits (integers and integral large floats in full)."""
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "NaN"
        if math.isinf(v):
            return "∞" if v > 0 else "−∞"
        if v == 0:
            return "0"
        if 1e4 <= abs(v) < 1e12 and v == round(v):
            return f"{v:.0f}"
        return f"{v:.{sig}g}"
    return str(v)


def _dur(s) -> str:
    """A duration in seconds with a unit a reader can take in."""
    if not _is_num(s) or not math.isfinite(s):
        return _num(s)
    a = abs(s)
    if a == 0:
        return "0 s"
    if a < 1e-3:
        return f"{s * 1e6:.3g} µs"
    if a < 1:
        return f"{s * 1e3:.3g} ms"
    if a < 120:
        return f"{s:.3g} s"
    if a < 7200:
        return f"{s / 60:.3g} min"
    return f"{s / 3600:.3g} h"


def _is_time_key(key: str) -> bool:
    return key.endswith("_s") and ("time" in key or "wall" in key) and "breakdown" not in key


def _ci_pair(ci) -> tuple[float, float] | None:
    if isinstance(ci, (list, tuple)) and len(ci) == 2 and all(_is_num(x) for x in ci):
        return float(ci[0]), float(ci[1])
    return None


def _with_ci(value, ci) -> str:
    pair = _ci_pair(ci)
    if not _is_num(value) or pair is None:
        return _num(value)
    return f"{_num(value)} [{_num(pair[0], 3)}, {_num(pair[1], 3)}]"


def _metric_value(key: str, value, ci=None) -> str:
    """A metric for a table: durations with units, intervals beside values, short lists inline."""
    if _is_time_key(key):
        return _dur(value)
    if isinstance(value, list) and value and all(_is_num(x) for x in value):
        cis = ci if isinstance(ci, list) and len(ci) == len(value) else [None] * len(value)
        if len(value) <= 6:
            return ", ".join(_with_ci(v, c) for v, c in zip(value, cis))
        return _compact(value)
    return _with_ci(value, ci)


def _compact(v, limit: int = 220) -> str:
    """Any JSON value on one line, numbers formatted, long numeric lists summarised."""
    text = _compact_inner(v)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _flat_numbers(v) -> list | None:
    if _is_num(v):
        return [v]
    if isinstance(v, list):
        out = []
        for x in v:
            sub = _flat_numbers(x)
            if sub is None:
                return None
            out.extend(sub)
        return out
    return None


def _shape(v) -> tuple[int, ...]:
    shape = []
    while isinstance(v, list):
        shape.append(len(v))
        v = v[0] if v else None
    return tuple(shape)


def _compact_inner(v) -> str:
    if v is None or isinstance(v, (bool, int, float)):
        return _num(v)
    if isinstance(v, str):
        return v
    if isinstance(v, list):
        nums = _flat_numbers(v)
        if nums is not None and len(nums) > 40:
            shape = " x ".join(str(s) for s in _shape(v))
            return (f"{len(nums)} values ({shape}), from {_num(min(nums))} to {_num(max(nums))}, "
                    f"mean {_num(sum(nums) / len(nums))}")
        if not v:
            return "none"
        return "[" + ", ".join(_compact_inner(x) for x in v) + "]"
    if isinstance(v, dict):
        if not v:
            return "none"
        return "{" + ", ".join(f"{k}: {_compact_inner(x)}" for k, x in v.items()) + "}"
    return str(v)


_MD_ALWAYS = str.maketrans({"\\": "\\\\", "`": "\\`", "*": "\\*"})


def _md(text) -> str:
    """Plain text as Markdown that renders as the same text (here and in CommonMark viewers)."""
    s = str(text).translate(_MD_ALWAYS)
    s = re.sub(r"<(?=[A-Za-z/!?])", r"\\<", s)  # would start raw HTML
    s = re.sub(r"\[(?=[^\]]*\]\()", r"\\[", s)  # would start a link
    s = s.replace("\r", " ").replace("\n", " ")
    if re.match(r"\s*(#|>|[-+] |\d+[.)] |\|)", s):
        s = "\\" + s if not s[0].isdigit() else s.replace(".", "\\.", 1).replace(")", "\\)", 1)
    return s


def _cell(text) -> str:
    return _md(text).replace("|", "\\|")


def _label(key: str) -> str:
    return GLOSSARY.get(key, (key.replace("_", " "), ""))[0]


def _table(header: Sequence[str], rows: Iterable[Sequence[str]], align: Sequence[str] | None = None) -> list[str]:
    """Markdown table lines; cells are already Markdown (use :func:`_cell` for plain text)."""
    rows = list(rows)
    if not rows:
        return []
    align = align or ["l"] + ["r"] * (len(header) - 1)
    sep = "|" + "|".join("---:" if a == "r" else "---" for a in align) + "|"
    return ["| " + " | ".join(header) + " |", sep, *("| " + " | ".join(r) + " |" for r in rows), ""]


def _figure_caption(name: str, text: StudyText | None) -> str:
    if text is not None and name in text.figures:
        return text.figures[name]
    stem = Path(name).stem
    stem = stem[4:] if stem.startswith("fig_") else stem
    return stem.replace("_", " ").strip().capitalize() + "."


def _slug(text: str, seen: dict[str, int]) -> str:
    """GitHub's heading anchor: lower case, punctuation dropped, spaces to hyphens; repeats get -1, -2, ..."""
    base = re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")
    n = seen.get(base, 0)
    seen[base] = n + 1
    return base if n == 0 else f"{base}-{n}"


def _demote(markdown: str, by: int) -> str:
    """Shift every ATX heading ``by`` levels down (at most level 6)."""
    def shift(m):
        return "#" * min(6, len(m.group(1)) + by) + m.group(2)

    return re.sub(r"(?m)^(#{1,6})(\s)", shift, markdown)


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
        if _is_num(v):
            comps.setdefault("", {})[name] = (float(v), ci)
        elif isinstance(v, list):
            cis = ci if isinstance(ci, list) and len(ci) == len(v) else [None] * len(v)
            for i, (x, c) in enumerate(zip(v, cis)):
                if _is_num(x):
                    comps.setdefault(f"x{i + 1}", {})[name] = (float(x), c)
    return list(comps.items())


def _pick_accuracy(label: str, comp: str, values: Mapping[str, tuple[float, Any]], runs) -> str:
    what = f"{label} of {comp}" if comp else label
    finite = {n: vc for n, vc in values.items() if math.isfinite(vc[0])}
    if not finite:
        return ""
    best = min(finite, key=lambda n: finite[n][0])
    bv, bci = finite[best]
    line = f"**Most accurate ({_md(what)}):** {_md(best)}, {_with_ci(bv, bci)}"
    others = [n for n in finite if n != best]
    bpair = _ci_pair(bci)
    if bpair is None:
        if others:
            second = min(others, key=lambda n: finite[n][0])
            line += (f"; next {_md(second)}, {_num(finite[second][0])}. No confidence interval was recorded for "
                     f"this metric, so whether the difference is significant cannot be said"
                     + (f" from {runs} runs." if _is_num(runs) else "."))
        else:
            line += "."
        return line
    overlap, apart, no_ci = [], [], []
    for n in others:
        pair = _ci_pair(finite[n][1])
        if pair is None:
            no_ci.append(n)
        elif pair[0] <= bpair[1] and bpair[0] <= pair[1]:
            overlap.append(n)
        else:
            apart.append(n)
    if overlap:
        line += (". Its 95 % interval overlaps that of " + ", ".join(
            f"{_md(n)} ({_with_ci(*finite[n])})" for n in overlap)
                 + ": the difference is not significant at this number of runs; the data cannot tell them apart "
                   "on this metric.")
    elif others:
        line += ". Its 95 % interval overlaps no other filter's: the lead is significant."
    else:
        line += "."
    if no_ci:
        line += " (No interval for " + ", ".join(_md(n) for n in no_ci) + ".)"
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
            out += [f"### {_md(name)}", "", *_demote_lines(lines[2:])]
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
               + (f"; benchmarks left out: {', '.join(_md(r) for r in sorted(refs & set(filters)))}, since no "
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
              if not (_is_num(m.get("diverged_fraction")) and m["diverged_fraction"] >= 1)
              and not ("rmse_position" in m and m["rmse_position"] is None)}
    times = {n: float(m["time_per_step_s"]) for n, m in usable.items()
             if _is_num(m.get("time_per_step_s")) and m["time_per_step_s"] > 0}
    if times:
        cheap = min(times, key=times.get)
        line = f"**Cheapest per step:** {_md(cheap)}, {_dur(times[cheap])} per time step"
        if first_best is not None and first_best != cheap and first_best in times:
            ratio = times[first_best] / times[cheap]
            line += f" ({_num(ratio, 3)} times less than the most accurate, {_md(first_best)})"
        elif first_best == cheap:
            line += " — also the most accurate"
        line += ". Times are for this machine and engine; their ratios travel better than their values."
        items.append(line)
    comms = {n: m["communications"] for n, m in usable.items() if _is_num(m.get("communications"))}
    if comms:
        low = min(comms.values())
        fewest = [n for n, c in comms.items() if c == low]
        if len(set(comms.values())) == 1:
            items.append(f"**Communications:** every filter sends the same number of messages ({_num(low)}).")
        else:
            line = f"**Fewest communications:** {', '.join(_md(n) for n in fewest)} ({_num(low)} messages"
            if first_best is not None and first_best in comms and first_best not in fewest:
                line += f"; the most accurate, {_md(first_best)}, sends {_num(comms[first_best])}"
            items.append(line + ").")
    det = results.get("detection")
    if isinstance(det, dict):
        attacked = {n: d for n, d in det.items()
                    if isinstance(d, dict) and n not in refs and _is_num(d.get("attacks")) and d["attacks"] > 0}
        for key, label in (("missed", "fewest missed attacks"), ("false_alarms", "fewest false alarms")):
            vals = {n: d[key] for n, d in attacked.items() if _is_num(d.get(key))}
            if vals:
                low = min(vals.values())
                names = [n for n, v in vals.items() if v == low]
                items.append(f"**{label.capitalize()}:** {', '.join(_md(n) for n in names)} ({_num(low)} in total "
                             f"over the runs).")
    warn = []
    for n, m in cand.items():
        if _is_num(m.get("collapsed_runs")) and m["collapsed_runs"] > 0:
            warn.append(f"{_md(n)} collapsed in {_num(m['collapsed_runs'])} run(s)")
        if _is_num(m.get("diverged_fraction")) and m["diverged_fraction"] > 0:
            warn.append(f"{_md(n)} diverged in {_num(100 * m['diverged_fraction'], 3)} % of the runs")
        elif _is_num(m.get("diverged_runs")) and m["diverged_runs"] > 0:
            warn.append(f"{_md(n)} diverged in {_num(m['diverged_runs'])} run(s)")
    if warn:
        items.append("**Caution:** " + "; ".join(warn) + ".")
    runs = results.get("runs")
    if _is_num(runs) and runs < 30:
        items.append(f"**Few runs:** only {_num(runs)} Monte Carlo runs; the intervals are wide and rough. "
                     "Run the study with more runs (`--runs`) before relying on the ranking.")
    out += [f"- {i}" for i in items] + [""]
    rec = results.get("recommendation")
    if isinstance(rec, dict) and rec:
        out += ["The study's own recommendation (computed when it ran):", "", *_generic(rec)]
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
        line = f"- **{_md(name)}**"
        if desc:
            line += f": {_md(desc)}"
        if extras:
            line += f" ({_md('; '.join(extras))})"
        if name in refs:
            line += " — a benchmark, not an option under attack"
        out.append(line)
    return out + [""]


def _run_facts(results: Mapping) -> list[str]:
    facts = []
    for key, label in (("scenario", "scenario"), ("runs", "Monte Carlo runs"), ("particles", "particles"),
                       ("steps", "time steps per run"), ("seed", "seed"), ("mode", "design mode"),
                       ("engine", "engine"), ("workers", "workers")):
        v = results.get(key)
        if v is not None and not isinstance(v, (dict, list)):
            facts.append(f"- {label}: {_md(_num(v))}")
    return facts


def _scenario_spec(name):
    try:
        from .scenarios import SCENARIOS
    except Exception:  # pragma: no cover - a report must not depend on the scenario registry importing
        return None
    return SCENARIOS.get(name) if isinstance(name, str) else None


def _scenario_section(results: Mapping) -> list[str]:
    if _scenario_blocks(results):
        return _per_scenario(results, _scenario_section, "Scenarios and parameters",
                             "Each scenario with the parameters used (`--set NAME=VALUE` changes one in every "
                             "compared scenario that has it).")
    spec = _scenario_spec(results.get("scenario"))
    params = results.get("params")
    out = ["## Scenario and parameters", ""]
    if spec is not None:
        summary = spec.summary.strip()
        if summary and summary[-1] not in ".!?":
            summary += "."
        out += [f"**{_md(spec.name)}**: {_md(spec.title)}. {_md(summary)}".rstrip(), ""]
    facts = _run_facts(results)
    if facts:
        out += ["How this run was made:", "", *facts, ""]
    if isinstance(params, dict) and params:
        docs = {p.name: p for p in spec.params} if spec is not None else {}
        rows = []
        for k, v in params.items():
            p = docs.get(k)
            source = "" if p is None else ("paper" if p.source == "paper" else "our assumption")
            rows.append([f"`{k}`" if "`" not in str(k) else _cell(k), _cell(_compact(v)),
                         _cell(p.doc if p is not None else ""), _cell(source)])
        out += ["The scenario's parameters (`--set NAME=VALUE` changes one):", ""]
        out += _table(["parameter", "value", "meaning", "source"], rows, ["l", "l", "l", "l"])
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
        out += [f"- `{k}` = {_md(_compact(params[k]))}" for k in names]
        out.append("")
    attacks = results.get("attacks")
    if isinstance(attacks, dict) and attacks:
        out += ["The attacks as the study recorded them:", "", *_generic(attacks)]
    return out


def _glossary_section(results: Mapping) -> list[str]:
    filters = _filters(results)
    keys = [k for k in GLOSSARY if any(k in m for m in filters.values())]
    if not keys:
        return []
    out = ["### How to read the numbers", ""]
    out += [f"- **{_md(GLOSSARY[k][0])}** (`{k}`): {_md(GLOSSARY[k][1])}." for k in keys]
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
            if _is_num(v) or (isinstance(v, list) and 0 < len(v) <= 6 and all(_is_num(x) for x in v)):
                keys.append(k)
    order = list(GLOSSARY)
    keys.sort(key=lambda k: order.index(k) if k in order else len(order))
    keys = keys[:10]
    if not keys:
        return []
    rows = [[_cell(n)] + [_metric_value(k, m.get(k), m.get(k + "_ci95")) if k in m else "—" for k in keys]
            for n, m in filters.items()]
    return _table([""] + [_cell(_label(k)) for k in keys], rows)


def _paper_side_by_side(filters: Mapping[str, dict], paper: Mapping) -> list[str]:
    pf = paper.get("filters")
    if not isinstance(pf, dict) or not pf:
        return []
    keys: list[str] = []
    for m in pf.values():
        if isinstance(m, dict):
            keys += [k for k, v in m.items() if _is_num(v) and k not in keys]
    if not keys:
        return []
    names = list(filters) + [n for n in pf if n not in filters]
    header = [""]
    for k in keys:
        header += [_cell(f"{_label(k)} (ours)"), _cell(f"{_label(k)} (paper)")]
    rows = []
    for n in names:
        ours, theirs = filters.get(n, {}), pf.get(n) if isinstance(pf.get(n), dict) else {}
        row = [_cell(n)]
        for k in keys:
            row += [_metric_value(k, ours.get(k), ours.get(k + "_ci95")) if k in ours else "—",
                    _metric_value(k, theirs.get(k)) if k in theirs else "—"]
        rows.append(row)
    return ["Our numbers beside the paper's:", "", *_table(header, rows)]


def _paper_text(paper: Mapping) -> list[str]:
    out = []
    if isinstance(paper.get("source"), str):
        out.append(f"Source: {_md(paper['source'])}.")
    for key in ("claim", "note"):
        if isinstance(paper.get(key), str):
            out.append(f"{'The paper claims' if key == 'claim' else 'Note'}: {_md(paper[key])}")
    out = [x for line in out for x in (line, "")]
    claims = paper.get("claims")
    if isinstance(claims, list) and claims:
        out += ["The paper's claims:", ""] + [f"- {_md(_compact(c))}" for c in claims] + [""]
    settings = {k: v for k, v in paper.items() if k not in ("source", "claim", "note", "claims", "filters")
                and (v is None or isinstance(v, (bool, int, float, str)))}
    if settings:
        out += ["The paper's settings and scalars:", ""]
        out += [f"- {_md(k)}: {_md(_compact(v))}" for k, v in settings.items()] + [""]
    rest = {k: v for k, v in paper.items() if isinstance(v, (dict, list)) and k not in ("claims", "filters")}
    for k, v in rest.items():
        out += [f"#### Paper: {_md(k)}", "", *_generic(v), ""]
    return out


def _results_section(results: Mapping, table_md: str | None) -> list[str]:
    filters = _filters(results)
    paper = results.get("paper") if isinstance(results.get("paper"), dict) else {}
    out = ["## Results", ""]
    if table_md and table_md.strip():
        out += ["### The study's tables (ours beside the paper's published numbers)", "",
                _demote(table_md.strip(), 3), ""]
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
                pair = _ci_pair(c)
                if pair is None:
                    continue
                rel = "—"
                if _is_num(x) and x != 0:
                    rel = f"{_num(100 * (pair[1] - pair[0]) / 2 / abs(x), 2)} %"
                rows.append([_cell(name), f"`{label}`", _num(x), f"[{_num(pair[0], 3)}, {_num(pair[1], 3)}]", rel])
    if not rows:
        return []
    runs = results.get("runs")
    return ["## Monte Carlo confidence intervals", "",
            f"95 % intervals over the {_num(runs) + ' ' if _is_num(runs) else ''}runs (how they are computed is "
            "among the assumptions). The half-width in per cent of the value shows how settled each number is; "
            "more runs narrow the intervals roughly as one over the square root of the number of runs.", "",
            *_table(["filter", "metric", "value", "95 % interval", "± half-width"], rows)]


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
                    if _is_num(m) and (fname, "") not in cols:
                        cols.append((fname, ""))
                    continue
                keys = ([k for k in preferred if _is_num(m.get(k))] or [k for k in ("rmse_state",) if k in m]
                        or [k for k, v in m.items() if _is_num(v)][:4])
                cols += [(fname, k) for k in keys if (fname, k) not in cols]
        if not cols:
            continue
        def entry(value, f, k):
            per_filter = by_value[value]
            m = per_filter.get(f) if isinstance(per_filter, dict) else None
            if k == "":
                return _num(m) if _is_num(m) else "—"
            if isinstance(m, dict) and k in m:
                return _metric_value(k, m[k], m.get(k + "_ci95"))
            return "—"

        metrics = {k for _, k in cols}
        if len(metrics) == 1 and len({f for f, _ in cols}) == len(cols):
            # one metric: a row per filter reads better than a column per filter
            (k,) = metrics
            header = [_cell(_label(k) if k else "")] + [_cell(f"{param} = {v}") for v in by_value]
            rows = [[_cell(f)] + [entry(v, f, k) for v in by_value] for f, _ in cols]
        else:
            header = [_cell(param)] + [_cell(f"{f}: {_label(k)}" if k else f) for f, k in cols]
            rows = [[_cell(v)] + [entry(v, f, k) for f, k in cols] for v in by_value]
        out += [f"### {_md(param)}", "", *_table(header, rows)]
    return out if len(out) > 4 else []


def _detection_section(results: Mapping) -> list[str]:
    det = results.get("detection")
    if not isinstance(det, dict) or not det:
        return []
    out = ["## Attack detection", "", "Totals over the runs at the default settings: attacks counted as missed are "
           "above the smallest norm the detector is designed for; smaller undetected ones count as stealthy.", ""]
    return out + _generic(det)


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
        out += [f"### {_md(k.replace('_', ' '))}", "", *_generic(rows), ""]
    node_rows = {}
    for n, m in filters.items():
        nodes = m.get("nodes")
        if isinstance(nodes, list) and len(nodes) > 1 and all(isinstance(x, dict) for x in nodes):
            node_rows[n] = {f"node {x.get('node', i) + 1 if _is_num(x.get('node', i)) else x.get('node')}":
                            x.get("rmse_position") for i, x in enumerate(nodes)}
    if node_rows:
        out += ["### Position RMSE of each node", "", *_generic(node_rows), ""]
    for n, m in filters.items():
        runs = m.get("diverged_runs")
        if isinstance(runs, list) and runs:
            out += [f"### Diverged runs of {_md(n)}", "", *_generic(runs), ""]
    return (["## Details per filter", ""] + out) if out else []


def _timing_section(results: Mapping) -> list[str]:
    filters = _filters(results)
    out = ["## Timings", ""]
    wall = results.get("wall_time_s")
    if _is_num(wall):
        out += [f"The whole study took {_dur(wall)} of wall-clock time (figures not included).", ""]
    keys = []
    for m in filters.values():
        keys += [k for k, v in m.items() if _is_time_key(k) and _is_num(v) and k not in keys]
    if keys:
        rows = [[_cell(n)] + [_dur(m.get(k)) if k in m else "—" for k in keys] for n, m in filters.items()]
        out += _table([""] + [_cell(_label(k)) for k in keys], rows)
    timing = results.get("timing_s")
    if isinstance(timing, dict) and timing:
        out += ["Where the time went:", ""]
        for k, v in timing.items():
            if isinstance(v, dict):
                out.append(f"- {_md(k)}: " + ", ".join(f"{_md(a)} {_dur(b)}" for a, b in v.items()))
            else:
                out.append(f"- {_md(k)}: {_dur(v)}")
        out.append("")
    return out if len(out) > 2 else []


def _figures_section(figures: Sequence[str], text: StudyText | None) -> list[str]:
    if not figures:
        return []
    out = ["## Figures", ""]
    for i, name in enumerate(figures, 1):
        cap = _figure_caption(name, text)
        target = name if re.fullmatch(r"[\w.\-]+", name) else f"<{name}>"
        out += [f"![Figure {i}: {_md(cap)}]({target})", f"**Figure {i}.** {_md(cap)} (`{name}`)", ""]
    return out


def _assumption_section(results: Mapping) -> list[str]:
    a = results.get("assumptions")
    if not isinstance(a, list) or not a:
        return []
    return ["## Assumptions", "", "Everything the papers leave open and this study had to decide, and how its "
            "numbers are defined:", "", *(f"- {_md(x)}" for x in a), ""]


def _other_section(results: Mapping) -> list[str]:
    rest = {k: v for k, v in results.items() if k not in _HANDLED}
    if not rest:
        return []
    out = ["## Other recorded results", ""]
    for k, v in rest.items():
        out += [f"### {_md(k)}", "", *_generic(v), ""]
    return out


def _software_section(results: Mapping) -> list[str]:
    out = ["## Software and reproduction", ""]
    v = results.get("versions")
    if isinstance(v, dict) and v:
        out += _table(["component", "version"], [[_cell(k), _cell(_compact(x))] for k, x in v.items()], ["l", "l"])
    if results.get("schema") is not None:
        out += [f"Results schema `{_md(results['schema'])}`.", ""]
    study = results.get("study")
    if isinstance(study, str) and re.fullmatch(r"[\w.\-]+", study):
        cmd = f"cfdesign study {study} --out DIR"
        for key, flag in (("runs", "--runs"), ("particles", "--particles"), ("seed", "--seed")):
            if _is_num(results.get(key)):
                cmd += f" {flag} {results[key]}"
        if isinstance(results.get("mode"), str) and re.fullmatch(r"\w+", results["mode"]):
            cmd += f" --mode {results['mode']}"
        out += [f"To run it again with the same seed: `{cmd}` (add `--set NAME=VALUE` for any parameter "
                "changed from its default above).", ""]
    return out if len(out) > 2 else []


def _cell_value(key: str, x) -> str:
    if key.endswith("_ci95") and _ci_pair(x) is not None:
        lo, hi = _ci_pair(x)
        return f"[{_num(lo, 3)}, {_num(hi, 3)}]"
    if isinstance(x, list) and 0 < len(x) <= 6 and all(_is_num(y) for y in x):
        return _metric_value(key, x)
    if isinstance(x, (dict, list)):
        return _compact(x, 120)
    return _metric_value(key, x)


def _is_records(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _is_complex(v) -> bool:
    return isinstance(v, dict) and bool(v) or _is_records(v) or len(_compact(v, 100000)) > 160


def _generic(v, depth: int = 0) -> list[str]:
    """Any JSON value as Markdown blocks: tables for maps of maps and lists of records, else lists."""
    if depth > 3:
        return [_md(_compact(v)), ""]
    if _is_records(v):
        return _generic({str(i + 1): x for i, x in enumerate(v)}, depth)
    if isinstance(v, dict) and v and all(isinstance(x, dict) for x in v.values()):
        cols: list[str] = []
        for x in v.values():
            cols += [k for k in x if k not in cols]
        nested = [c for c in cols if any(isinstance(x.get(c), dict) and x.get(c) or _is_records(x.get(c))
                                         for x in v.values())]
        flat = [c for c in cols if c not in nested]
        out = []
        if flat:
            rows = [[_cell(name)] + [_cell(_cell_value(str(k), x[k])) if k in x else "—" for k in flat]
                    for name, x in v.items()]
            out += _table([""] + [_cell(str(c).replace("_", " ")) for c in flat], rows)
        for c in nested:
            sub = {n: x[c] for n, x in v.items() if c in x}
            out += [f"**{_md(str(c).replace('_', ' '))}**:", "", *_generic(sub, depth + 1)]
        return out
    if isinstance(v, dict):
        out, later = [], []
        for k, x in v.items():
            if _is_complex(x):
                later += [f"**{_md(k)}**:", "", *_generic(x, depth + 1)]
            elif isinstance(x, (dict, list)):
                out.append(f"- **{_md(k)}**: {_md(_compact(x))}")
            else:
                out.append(f"- **{_md(k)}**: {_md(_metric_value(str(k), x))}")
        return out + [""] + later if out else later
    if isinstance(v, list) and v and _flat_numbers(v) is None:
        return [f"- {_md(_compact(x))}" for x in v] + [""]
    return [_md(_compact(v)), ""]


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
        The Markdown text of ``report.md``; :func:`markdown_to_html` turns it into the HTML report.
    """
    study = results.get("study")
    text = study_text(study)
    name = study if isinstance(study, str) else "unnamed study"
    out = [f"# Study report: {_md(name)}", ""]
    if text is not None:
        out += [f"**{_md(text.title)}.**" + (f" Source paper: {_md(text.paper)}." if text.paper else ""), ""]
    sections: list[list[str]] = []
    intro = ["## What this study compares", ""]
    if text is not None:
        intro += [text.summary, ""]
    else:
        filters = _filters(results)
        desc = f"This report presents the results of the study **{_md(name)}**"
        if isinstance(results.get("scenario"), str):
            desc += f" on the scenario **{_md(results['scenario'])}**"
        if filters:
            desc += f". It compares {len(filters)} filter(s) on the same runs: " + ", ".join(_md(n) for n in filters)
        intro += [desc + ". The metrics, their intervals and the paper's numbers (if any) follow.", ""]
    intro += _filters_section(results, text)
    intro += _glossary_section(results)
    sections.append(intro)
    for part in (_pick_section(results, text), _scenario_section(results), _attack_section(results, text),
                 _results_section(results, table_md), _ci_section(results), _sweep_section(results),
                 _detection_section(results), _details_section(results), _timing_section(results),
                 _figures_section(figures, text), _assumption_section(results), _other_section(results),
                 _software_section(results)):
        if part:
            sections.append(part)
    seen: dict[str, int] = {}
    toc = ["## Contents", ""]
    for sec in sections:
        title = sec[0][3:]
        toc.append(f"- [{title}](#{_slug(_inline_text(title), seen)})")
    out += toc + [""]
    for sec in sections:
        out += sec
    text_out = "\n".join(out)
    text_out = re.sub(r"\n{3,}", "\n\n", text_out).strip() + "\n"
    return text_out


# ---------------------------------------------------------------------------------------------------------------
# Markdown to HTML (the subset above).

_PUNCT = set("!\"#$%&'()*+,-./:;<=>?@[\\]^_`{|}~")
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
_IMAGE = re.compile(r"^!\[(.*)\]\((<[^>]*>|[^\s)]+)\)\s*$")
_LIST = re.compile(r"^( *)[-*+] (.*)$")
_LINK = re.compile(r"\[((?:[^\]\\]|\\.)+)\]\((#[\w\-]*)\)")


def _esc(s: str) -> str:
    return html.escape(s, quote=True)


def _inline(text: str) -> str:
    """Inline Markdown to HTML: backslash escapes, `code`, **bold**, in-page links; everything else escaped."""
    out = []
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c == "\\" and i + 1 < n and text[i + 1] in _PUNCT:
            out.append(_esc(text[i + 1]))
            i += 2
        elif c == "`":
            j = text.find("`", i + 1)
            if j < 0:
                out.append(_esc(c))
                i += 1
            else:
                out.append("<code>" + _esc(text[i + 1:j]) + "</code>")
                i = j + 1
        elif text.startswith("**", i):
            j = _find_unescaped(text, "**", i + 2)
            if j < 0 or j == i + 2:
                out.append(_esc("**"))
                i += 2
            else:
                out.append("<strong>" + _inline(text[i + 2:j]) + "</strong>")
                i = j + 2
        elif c == "[" and (m := _LINK.match(text, i)):
            out.append(f'<a href="{_esc(m.group(2))}">{_inline(m.group(1))}</a>')
            i = m.end()
        else:
            out.append(_esc(c))
            i += 1
    return "".join(out)


def _inline_text(text: str) -> str:
    """The plain text an inline Markdown string shows (for anchors)."""
    return html.unescape(re.sub(r"<[^>]+>", "", _inline(text)))


def _find_unescaped(text: str, token: str, start: int) -> int:
    i = start
    while True:
        j = text.find(token, i)
        if j < 0:
            return -1
        k, slashes = j - 1, 0
        while k >= 0 and text[k] == "\\":
            slashes += 1
            k -= 1
        if slashes % 2 == 0:
            # skip code spans: a ** inside `...` is not a delimiter
            if text.count("`", start, j) % 2 == 0:
                return j
        i = j + 1


def _split_row(line: str) -> list[str]:
    s = line.strip()
    if s.startswith("|"):
        s = s[1:]
    cells, cur, i = [], [], 0
    while i < len(s):
        if s[i] == "\\" and i + 1 < len(s):
            cur.append(s[i:i + 2])
            i += 2
            continue
        if s[i] == "|":
            cells.append("".join(cur).strip())
            cur = []
        else:
            cur.append(s[i])
        i += 1
    tail = "".join(cur).strip()
    if tail or not s.endswith("|"):
        cells.append(tail)
    return cells


def _table_html(lines: list[str]) -> str:
    rows = [_split_row(x) for x in lines]
    align: list[str] = []
    header = None
    if len(rows) >= 2 and rows[1] and all(re.fullmatch(r":?-{1,}:?", c.strip()) for c in rows[1]):
        header = rows[0]
        align = ["right" if c.strip().endswith(":") and not c.strip().startswith(":") else
                 "center" if c.strip().startswith(":") and c.strip().endswith(":") else "" for c in rows[1]]
        body = rows[2:]
    else:
        body = rows
    width = max(len(r) for r in rows)

    def cells(row, tag):
        row = list(row) + [""] * (width - len(row))
        parts = []
        for j, c in enumerate(row[:width]):
            a = align[j] if j < len(align) else ""
            attr = f' class="{a}"' if a else ""
            parts.append(f"<{tag}{attr}>{_inline(c)}</{tag}>")
        return "<tr>" + "".join(parts) + "</tr>"

    out = ['<div class="table-wrap"><table>']
    if header is not None:
        out.append("<thead>" + cells(header, "th") + "</thead>")
    out.append("<tbody>")
    out += [cells(r, "td") for r in body]
    out.append("</tbody></table></div>")
    return "\n".join(out)


def _list_html(items: list[tuple[int, str]]) -> str:
    out, cur = [], -1
    for level, text in items:
        level = min(level, cur + 1)
        if level > cur:
            out.append("<ul>")
            cur = level
        else:
            out.append("</li>")
            while cur > level:
                out.append("</ul></li>")
                cur -= 1
        out.append("<li>" + _inline(text))
    out.append("</li>")
    while cur > 0:
        out.append("</ul></li>")
        cur -= 1
    out.append("</ul>")
    return "".join(out)


def _png_size(data: bytes) -> tuple[int, int] | None:
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) >= 24:
        return struct.unpack(">II", data[16:24])
    return None


def _figure_html(alt: str, target: str, caption: list[str], images: Mapping[str, bytes]) -> str:
    name = target[1:-1] if target.startswith("<") and target.endswith(">") else target
    data = images.get(name)
    cap = " ".join(caption) if caption else alt
    if data is None:
        return f'<figure><p class="missing">{_inline(alt)} (figure {_esc(name)} not found)</p></figure>'
    size = _png_size(data)
    dims = f' width="{size[0]}" height="{size[1]}"' if size else ""
    src = "data:image/png;base64," + base64.b64encode(data).decode("ascii")
    alt_text = _esc(_inline_text(alt))
    return (f'<figure><img src="{src}" alt="{alt_text}" title="{_esc(name)}" data-file="{_esc(name)}"{dims}>'
            f"<figcaption>{_inline(cap)}</figcaption></figure>")


_CSS = """
:root { color-scheme: light; }
body { font: 16px/1.55 system-ui, -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif;
       color: #1d232a; background: #fff; margin: 0; }
main { max-width: 72rem; margin: 0 auto; padding: 1.5rem 2rem 4rem; }
h1 { font-size: 1.9rem; margin: 0.5rem 0 0.75rem; border-bottom: 3px solid #2b6cb0; padding-bottom: 0.3rem; }
h2 { font-size: 1.45rem; margin-top: 2.4rem; border-bottom: 1px solid #cbd5e0; padding-bottom: 0.2rem; }
h3 { font-size: 1.2rem; margin-top: 1.8rem; }
h4, h5, h6 { font-size: 1.02rem; margin-top: 1.4rem; }
p, li { max-width: 60rem; }
li { margin: 0.2rem 0; }
code { font-family: ui-monospace, SFMono-Regular, Menlo, Consolas, monospace; font-size: 0.88em;
       background: #f1f4f8; padding: 0.05em 0.3em; border-radius: 3px; }
.table-wrap { overflow-x: auto; margin: 0.8rem 0 1.2rem; }
table { border-collapse: collapse; font-size: 0.9rem; }
th, td { border: 1px solid #d5dce4; padding: 0.3rem 0.6rem; vertical-align: top; }
th { background: #edf2f7; text-align: left; }
tbody tr:nth-child(even) { background: #f8fafc; }
td.right, th.right { text-align: right; font-variant-numeric: tabular-nums; }
td.right { white-space: nowrap; }
tbody td:first-child { min-width: 12rem; }
td.center, th.center { text-align: center; }
figure { margin: 1.2rem 0 2rem; }
figure img { max-width: 100%; height: auto; border: 1px solid #e2e8f0; }
figcaption { font-size: 0.92rem; color: #4a5568; margin-top: 0.4rem; }
a { color: #2b6cb0; }
.missing { color: #9b2c2c; }
@media print { main { max-width: none; } h2 { page-break-after: avoid; } figure { page-break-inside: avoid; } }
"""


def markdown_to_html(markdown: str, images: Mapping[str, bytes] | None = None, title: str = "Report") -> str:
    """A complete, self-contained HTML page from the Markdown subset of :func:`render_markdown`.

    Parameters
    ----------
    markdown : str
        ATX headings, paragraphs, pipe tables (first row a header when the second is a
        ``|---|---:|`` separator), ``-`` lists nested by two spaces, ``![alt](file)`` lines
        (a figure; the following lines of the block are its caption), and inline
        ``**bold**``, `` `code` ``, ``[text](#anchor)`` and backslash escapes.  Any other
        text, HTML included, is shown literally (escaped).
    images : mapping of str to bytes, optional
        PNG bytes by file name; an image whose file is not here is replaced by its alt text.
    title : str
        The page title.

    Returns
    -------
    str
        HTML5 with inline CSS, images as ``data:`` URIs and a Content-Security-Policy that
        forbids loading anything else.
    """
    images = images or {}
    lines = markdown.replace("\r\n", "\n").split("\n")
    body: list[str] = []
    seen: dict[str, int] = {}
    i, n = 0, len(lines)

    def starts_block(line: str) -> bool:
        return bool(_HEADING.match(line) or line.lstrip().startswith("|") or _LIST.match(line)
                    or _IMAGE.match(line))

    while i < n:
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        m = _HEADING.match(line)
        if m:
            level, text = len(m.group(1)), m.group(2)
            anchor = _slug(_inline_text(text), seen)
            body.append(f'<h{level} id="{_esc(anchor)}">{_inline(text)}</h{level}>')
            i += 1
            continue
        if line.lstrip().startswith("|"):
            j = i
            while j < n and lines[j].lstrip().startswith("|"):
                j += 1
            body.append(_table_html(lines[i:j]))
            i = j
            continue
        if _LIST.match(line):
            items = []
            while i < n and (lm := _LIST.match(lines[i])):
                items.append((len(lm.group(1)) // 2, lm.group(2)))
                i += 1
            body.append(_list_html(items))
            continue
        m = _IMAGE.match(line)
        if m:
            i += 1
            caption = []
            while i < n and lines[i].strip() and not starts_block(lines[i]):
                caption.append(lines[i].strip())
                i += 1
            body.append(_figure_html(m.group(1), m.group(2), caption, images))
            continue
        para = []
        while i < n and lines[i].strip() and (not para or not starts_block(lines[i])):
            para.append(lines[i].strip())
            i += 1
        body.append("<p>" + _inline("\n".join(para)) + "</p>")
    csp = "default-src 'none'; img-src data:; style-src 'unsafe-inline'"
    return ("<!DOCTYPE html>\n"
            '<html lang="en">\n<head>\n<meta charset="utf-8">\n'
            f'<meta http-equiv="Content-Security-Policy" content="{csp}">\n'
            '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
            '<meta name="generator" content="cfdesign studies.report">\n'
            f"<title>{_esc(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n<main>\n"
            + "\n".join(body) + "\n</main>\n</body>\n</html>\n")


# ---------------------------------------------------------------------------------------------------------------
# Files.


def _read_directory(directory) -> tuple[Path, dict, str | None, list[str]]:
    try:
        d = Path(os.fspath(directory))
    except TypeError:
        raise InputError(f"directory must be a path, got {type(directory).__name__}") from None
    if not d.is_dir():
        raise InputError(f"directory {str(d)!r} does not exist or is not a directory")
    rfile = d / "results.json"
    if not rfile.is_file():
        raise InputError(f"directory {str(d)!r} has no results.json (write one with `cfdesign study STUDY --out "
                         f"{d}` first)")
    try:
        results = json.loads(rfile.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"directory {str(d)!r}: results.json cannot be read: {exc}") from None
    if not isinstance(results, dict):
        raise InputError(f"directory {str(d)!r}: results.json must hold a JSON object, got "
                         f"{type(results).__name__}")
    schema = results.get("schema")
    if schema is not None and not (isinstance(schema, str) and schema.startswith("cfdesign.study/")):
        raise InputError(f"directory {str(d)!r}: results.json has schema {schema!r}, not a study's "
                         "(cfdesign.study/1)")
    table_md = None
    tfile = d / "table.md"
    if tfile.is_file():
        try:
            table_md = tfile.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"directory {str(d)!r}: table.md cannot be read: {exc}") from None
    figures = sorted(p.name for p in d.iterdir() if p.suffix.lower() == ".png" and p.is_file()
                     and not p.name.startswith("."))
    return d, results, table_md, figures


def write_report(directory) -> tuple[Path, Path]:
    """Write ``report.html`` and ``report.md`` for the study whose results are in ``directory``.

    Reads ``directory/results.json`` (schema ``cfdesign.study/1``), ``table.md`` if
    present and every ``*.png`` in ``directory``.  Both reports present the same
    content: what the study compares (in plain language), which filter to pick
    from the numbers, the scenario and its parameters, the attacks, our tables
    beside the paper's, Monte Carlo intervals, sweeps, detection, timings, the
    figures, every assumption, other recorded results, and software versions.
    ``report.md`` links the figures by file name; ``report.html`` is
    self-contained (figures inline as base64 ``data:`` URIs, inline CSS, no
    JavaScript).  Each file is written atomically (a temporary file in
    ``directory``, then renamed), so a reader sees the old report or the new one.

    Parameters
    ----------
    directory : str or path-like
        A study's output directory (``cfdesign study STUDY --out DIR``).

    Returns
    -------
    (Path, Path)
        The paths of ``report.html`` and ``report.md``.

    Raises
    ------
    designer.validation.InputError
        ``directory`` does not exist, has no ``results.json``, or it is not a
        readable JSON object of a study (the message names ``directory``).
    """
    d, results, table_md, figures = _read_directory(directory)
    md = render_markdown(results, table_md, figures)
    images = {}
    for name in figures:
        try:
            images[name] = (d / name).read_bytes()
        except OSError as exc:
            raise InputError(f"directory {str(d)!r}: figure {name} cannot be read: {exc}") from None
    study = results.get("study") if isinstance(results.get("study"), str) else "study"
    page = markdown_to_html(md, images, title=f"cfdesign report: {study}")
    md_path = atomic_write(d / "report.md", lambda fh: fh.write(md.encode("utf-8")))
    html_path = atomic_write(d / "report.html", lambda fh: fh.write(page.encode("utf-8")))
    return html_path, md_path
