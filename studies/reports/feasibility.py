"""The feasibility report: a parameter-feasibility map (``feasibility.csv`` + ``feasibility.json``) in plain words.

What was mapped (the grid, the design options, the operating point), how many grid
points have each verdict (certified and bounded, certified but not bounded, vacuous, infeasible, not computed)
and what binds, the
grid itself (for one or two grid parameters a matrix: the steady-state trace bound of the
certified points, the verdict and binding condition of the others), the map
``feasibility.png`` (the same categories apart), and how this notion of
feasibility differs from the one of ``cfdesign design`` (:data:`TWO_NOTIONS`, the
words of the docstring of the module that computes the map), then the attacks, the
network, the assumptions and the runner.

``feasibility.csv`` is enough: without ``feasibility.json`` the grid is read from the
CSV's columns (those before ``feasible``) and the sections that need the JSON are
left out.

Every sentence, count and table is derived from one classification of each grid point
(:func:`studies.feasibility_terms.map_category`: its ``verdict``), the one the map draws, so
the summary's "Certified at n of N" and "Where the design is certified" cannot disagree.
"""
from __future__ import annotations

import csv
import io
import math
import re
from collections import Counter
from pathlib import Path
from typing import Any, Mapping, Sequence

import rules
from designer.validation import InputError

from ..feasibility_terms import FAILED, GRID_PARAMETERS, MAP_CATEGORIES, MAP_WORDS, map_category
from .design import attack_lines, scenario_lines, software_lines
from .text import (MEASURED, assumption_section, compact, document, figure_lines, fmt_num, generic, is_num, md_cell,
                   md_escape, md_table, network_lines, observability_section, read_record, recorded_elsewhere,
                   rerun_lines)

__all__ = ["feasibility_report", "render_feasibility", "TWO_NOTIONS"]

TWO_NOTIONS = (
    "**Two notions of feasibility.** `design` checks (28)-(29) *along one simulated run*: the nodes' own estimates, "
    "the realised DoS pattern (`s_i` = packets actually received) and the transient from the prior. `feasibility` "
    "checks whether the *stationary* recursion at the operating point, with the *expected* number of received "
    "packets, has a bounded fixed point. They disagree when the run leaves the operating point (a nonlinear model "
    "linearised elsewhere), when a run's realised DoS pattern is luckier or worse than its mean, or when the "
    "transient violates a condition that the steady state satisfies (or the reverse: a run that is too short to "
    "reach an unbounded steady state).")
_KNOWN = {"schema", "scenario", "grids", "options", "points", "feasible_points", "failed_points", "operating_point",
          "network", "attacks", "assumptions", "runner", "source", "state_names", "observability", "kalman_references",
          "versions", "invocation", "verdicts", "open_loop"}
_THEOREM2 = {True: "holds", False: "fails", None: "—"}
_ROW_LIMIT = 400  # a longer map is listed up to here (the CSV has every point)


def _grid_docs() -> Mapping[str, str]:
    """What each grid parameter is (:data:`studies.feasibility_terms.GRID_PARAMETERS`)."""
    return GRID_PARAMETERS


# ---------------------------------------------------------------------------------------------------------------
# Reading the files.


def _number(text: str) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


def _read_csv(d: Path) -> tuple[list[str], list[dict]]:
    try:
        text = (d / "feasibility.csv").read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"directory {str(d)!r}: feasibility.csv cannot be read: {exc}") from None
    reader = csv.DictReader(io.StringIO(text))
    header = list(reader.fieldnames or [])
    if "feasible" not in header:
        raise InputError(f"directory {str(d)!r}: feasibility.csv has no 'feasible' column (columns: "
                         f"{', '.join(header) or 'none'})")
    names = header[:header.index("feasible")]
    rows = []
    for raw in reader:
        row: dict[str, Any] = {n: _number(raw.get(n)) for n in names}
        row["feasible"] = raw.get("feasible", "").strip() in ("1", "True", "true")
        row["trace_bound"] = _number(raw.get("trace_bound"))
        row["binding"] = raw.get("binding") or ""
        th2 = (raw.get("theorem2") or "").strip()
        row["theorem2"] = None if th2 == "" else th2 in ("1", "True", "true")
        row["iterations"] = raw.get("iterations") or ""
        row["verdict"] = (raw.get("verdict") or "").strip() or None  # None: a map written before the verdicts
        row["rule"] = (raw.get("rule") or "").strip() or None  # None: a map written before the picks
        btl = (raw.get("better_than_local") or "").strip()
        row["better_than_local"] = None if btl == "" else btl in ("1", "True", "true")
        rows.append(row)
    return names, rows


def _grids(names: Sequence[str], rows: Sequence[Mapping], meta: Mapping) -> list[tuple[str, list[float]]]:
    """The grid parameters and their values, from feasibility.json or, without it, from the CSV."""
    given = meta.get("grids")
    if isinstance(given, list) and [g.get("name") for g in given if isinstance(g, dict)] == list(names):
        if all(isinstance(g.get("values"), list) and all(is_num(v) for v in g["values"]) for g in given):
            return [(g["name"], [float(v) for v in g["values"]]) for g in given]
    out = []
    for n in names:
        seen: list[float] = []
        for r in rows:
            if r[n] not in seen:
                seen.append(r[n])
        out.append((n, seen))
    return out


# ---------------------------------------------------------------------------------------------------------------
# Sections.


def _category(row: Mapping) -> str | None:
    """The one classification of a grid point every sentence, table and the map are derived from
    (:func:`studies.feasibility_terms.map_category`: its verdict; None for a feasible point of a map written without
    verdicts)."""
    return map_category(row)


def _judged(rows: Sequence[Mapping]) -> bool:
    """Whether the map recorded a verdict at every point (a map written before the verdicts has none)."""
    return all(_category(r) is not None for r in rows)


def _good(rows: Sequence[Mapping]) -> tuple[list[Mapping], str]:
    """The points the design works at, lowest bound first, and the word for them: the certified ones, or, for a map
    written without verdicts, the feasible ones."""
    word = "certified" if _judged(rows) else "feasible"
    good = [r for r in rows if (_category(r) == "certified" if word == "certified" else r["feasible"])
            and math.isfinite(r["trace_bound"])]
    return sorted(good, key=lambda r: r["trace_bound"]), word


# a number in a binding reason, or an equation's label such as (28), which is kept
_NUMBER = re.compile(r"\(\d+\)|(?<![\w.])[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?(?![\w.])")


def _reasons(these: Sequence[Mapping]) -> str:
    """The binding reasons of ``these`` points, alike reasons counted together: their numbers (the growth, the
    iteration, a margin) differ from point to point and are shown as ``…``; the three most common, then how many
    other kinds."""
    why = Counter(_NUMBER.sub(lambda m: m[0] if m[0].startswith("(") else "…", r["binding"] or "not recorded")
                  for r in these)
    top = [f"{md_escape(b)} at {c}" for b, c in why.most_common(3)]
    rest = len(why) - len(top)
    return ", ".join(top) + (f", and {rest} other reason{'s' if rest > 1 else ''} (the grid below)" if rest else "")


def _others(rows: Sequence[Mapping], word: str) -> tuple[int, str]:
    """How many points are not ``word`` (certified, or feasible), and what they are, with their reasons."""
    if word == "feasible":
        bad = [r for r in rows if not r["feasible"]]
        return len(bad), f"infeasible ({_reasons(bad)})"
    parts = []
    for cat in MAP_CATEGORIES[1:]:
        these = [r for r in rows if _category(r) == cat]
        if these:
            parts.append(f"{len(these)} {cat} (binding: {_reasons(these)})")
    return sum(_category(r) != "certified" for r in rows), "; ".join(parts)


def _cell(row: Mapping | None) -> str:
    if row is None:
        return "—"
    cat = _category(row)
    dagger = " †" if row["feasible"] and row["theorem2"] is False else ""
    if cat in ("certified", None):
        return fmt_num(row["trace_bound"], 3) + dagger
    if cat == "vacuous":
        bound = fmt_num(row["trace_bound"], 3) if row["feasible"] else md_cell(row["binding"] or "no bound")
        return f"vacuous {bound}{dagger}"
    if cat == "not bounded":
        return "not bounded: " + md_cell(row["binding"] or "no fixed point")
    if cat == "not computed":
        return "not computed: " + md_cell(row["binding"] or "the stationary certificate")
    return "✗ " + md_cell(row["binding"] or "infeasible")


def _mode(meta: Mapping) -> str:
    options = meta.get("options") if isinstance(meta.get("options"), Mapping) else {}
    return str(options.get("mode") or rules.DEFAULT)


def _mapped_section(scenario: str, grids, meta: Mapping) -> list[str]:
    docs = _grid_docs()
    options = meta.get("options") if isinstance(meta.get("options"), Mapping) else {}
    mode = _mode(meta)
    if mode == "auto":
        what = (f"At every grid point every candidate design of **{md_escape(scenario)}** that the map maps (each "
                "deployable rule's, as `cfdesign design` tries them: relay and flood at L = 1 .. L_max hops, "
                "scheduled with and without the senders' measurements, tuned, paper) has its stationary bound "
                "iterated at the scenario's operating point to a fixed point, and the point shows its **pick**, "
                "the candidate `cfdesign design --mode auto` would pick by the same rule: certified and bounded, "
                "below the nodes' local EKFs, the smallest bound (within 1 %, the fewest bytes per step); a pick "
                "with a stationary LMI has it solved (the others are screened without it), and where no candidate "
                "is eligible the point shows the best of the others, its verdict its own. The grid's values "
                "replace the options of the same name.")
    else:
        what = (f"At every grid point the steady-state bound recursion (26)-(27) of the {md_escape(mode)} consensus "
                f"design of **{md_escape(scenario)}** is iterated at the scenario's operating point to a fixed point, "
                "with the design `cfdesign design` would build from the same options; the grid's values replace "
                "the options of the same name.")
    out = ["## What was mapped", "", what, "", "The grid:", ""]
    for name, values in grids:
        shown = ", ".join(fmt_num(v) for v in values[:12]) + (", …" if len(values) > 12 else "")
        doc = docs.get(name)
        out.append(f"- `{md_escape(name)}`" + (f" ({md_escape(doc)})" if doc else "")
                   + f": {len(values)} values ({md_escape(shown)})")
    out.append("")
    given = {k: v for k, v in options.items() if v is not None}
    if given:
        out += ["The design options at every point (besides the grid's):", "", *generic(given)]
    out += _candidates_lines(meta)
    op = meta.get("operating_point")
    if isinstance(op, Mapping) and op:
        out += ["The operating point (the linearisation of the stationary recursion):", ""]
        out += [f"- {md_escape(k)} = {md_escape('none' if v is None else compact(v))}" for k, v in op.items()] + [""]
    return out


def _candidates_lines(meta: Mapping) -> list[str]:
    """An automatic map's candidates: messages and bytes per step, status, and the points each won."""
    cands = meta.get("candidates")
    if not isinstance(cands, list) or not cands:
        return []
    budget = meta.get("budget") if isinstance(meta.get("budget"), Mapping) else {}
    caps = [f"{budget[k]} {w}" for k, w in (("messages_per_step", "messages"), ("bytes_per_step", "bytes"))
            if is_num(budget.get(k))]
    refs = meta.get("references") if isinstance(meta.get("references"), Mapping) else {}
    ref = [f"{w} {fmt_num(refs[k])}" for k, w in (("centralized", "the centralized EKF's"),
                                                  ("local_mean", "the local EKFs' (node average)"))
           if is_num(refs.get(k))]
    # a model with REGIONS: the candidates ranked on the regions (studies.feasibility_map.run_feasibility)
    over = ", over each node's region, where the candidates are ranked" if refs.get("over") == "each node's region" \
        else ""
    body = [[md_cell(c.get("label")), str(c.get("messages_per_step")), str(c.get("bytes_per_step")),
             md_cell(c.get("status") if not c.get("reason") else f"{c.get('status')}: {c.get('reason')}"),
             str(c.get("picked_points"))] for c in cands if isinstance(c, Mapping)]
    return (["The candidates (" + (f"budget: {', '.join(caps)} per step" if caps else "no budget") + "):", "",
             *md_table(["candidate", "messages / step", "bytes / step", "status", "picked at"], body,
                       ["l", "r", "r", "l", "r"])]
            + ([f"The references (steady-state tr P at the operating point{over}): {'; '.join(ref)}.", ""]
               if ref else []))


def _result_section(rows: Sequence[Mapping]) -> list[str]:
    from .design import theorem2_words

    n = len(rows)
    feasible = [r for r in rows if r["feasible"]]
    failed = [r for r in rows if r["binding"].startswith(FAILED)]
    good, word = _good(rows)
    out = ["## How much is certified", ""]
    if _judged(rows):
        counts = Counter(_category(r) for r in rows)
        out += [f"**{counts['certified']} of {n} grid points are certified.** Each point has one verdict, the one "
                "its cell of the grid below and its colour in the map show:", "",
                *md_table(["verdict", "points"], [[md_escape(MAP_WORDS[c]), str(counts[c])] for c in MAP_CATEGORIES],
                          ["l", "r"]),
                f"- {len(feasible)} of {n} points are feasible: (28)-(29) hold and the iteration reached a fixed "
                "point; a feasible point is certified only where its bound is also below the open-loop covariance"]
    else:
        out += [f"**{len(feasible)} of {n} grid points are feasible; this map recorded no verdicts** (a map written "
                "before them: compute it again to have each point judged).", ""]
    if good:
        lo, hi = good[0], good[-1]
        spread = (f"is {fmt_num(lo['trace_bound'])}" if lo is hi else
                  f"ranges from {fmt_num(lo['trace_bound'])} to {fmt_num(hi['trace_bound'])}")
        out.append(f"- the steady-state trace bound (mean over nodes of tr Φ) of the {word} points {spread}")
        binding = Counter(r["binding"] or "not recorded" for r in good)
        out.append(f"- the condition with the least relative slack at the fixed point of the {word} points: "
                   + ", ".join(f"{md_escape(b)} at {c}" for b, c in binding.most_common()))
    worse = [r for r in rows if _category(r) == "certified" and r.get("better_than_local") is False]
    if worse:
        out.append(f"- **{len(worse)} of the certified points are no better than the nodes running alone**: their "
                   "bound is not below the local EKFs' steady-state tr P (feasibility.json's references)")
    th2 = [r for r in feasible if r["theorem2"] is False]
    if th2:
        out.append("- " + md_escape(theorem2_words(f"the fixed point of {len(th2)} of the {len(feasible)} feasible "
                                                   "points (marked † below)")))
    elif feasible and all(r["theorem2"] is True for r in feasible):
        out.append("- Theorem 2's sufficient condition for mean-square boundedness of the error holds at the "
                   "fixed point of every feasible point")
    bad = [r for r in rows if not r["feasible"] and not r["binding"].startswith(FAILED)]
    if bad:
        why = Counter(r["binding"] or "not recorded" for r in bad)
        out.append("- why the points without a fixed point have none: "
                   + ", ".join(f"{md_escape(b)} at {c}" for b, c in why.most_common()))
    if failed:
        why = Counter(r["binding"][len(FAILED):] for r in failed)
        out.append(f"- **{len(failed)} of {n} grid points failed**: their design or fixed-point iteration raised, so "
                   "they are infeasible, not mapped (the other points are mapped): "
                   + "; ".join(f"{md_escape(b)} at {c}" for b, c in why.most_common()))
    return out + [""]


def _legend() -> str:
    return ("A number is the steady-state trace bound (mean over nodes of tr Φ) of a certified point; \"vacuous\" "
            "marks a point whose bound (given where a fixed point exists) is at or above the open-loop covariance or "
            "unbounded; \"not bounded\" a point below it (certified) whose iteration reached no fixed point; \"not "
            "computed\" one whose stationary certificate the rule did not compute; ✗ an infeasible point "
            "with the condition that failed ((28), (29)) or why; † a feasible point where Theorem 2's condition fails "
            "at its fixed point (no contradiction: see above).")


def _picked(row: Mapping | None, auto: bool) -> str:
    """A 2-D grid's cell, with the pick of an automatic map."""
    cell = _cell(row)
    return cell if row is None or not auto or not row.get("rule") else f"{cell} ({md_cell(row['rule'])})"


def _grid_section(grids, rows: Sequence[Mapping], auto: bool = False) -> list[str]:
    out = ["## The grid", ""]
    if len(grids) == 2:
        (n1, v1), (n2, v2) = grids
        at = {(r[n1], r[n2]): r for r in rows}
        out += [_legend() + f" Rows: `{md_escape(n1)}`, columns: `{md_escape(n2)}`.", ""]
        header = [md_cell(f"{n1} \\ {n2}")] + [md_cell(fmt_num(b)) for b in v2]
        body = [[md_cell(fmt_num(a))] + [_picked(at.get((a, b)), auto) for b in v2] for a in v1]
        return out + md_table(header, body)
    names = [n for n, _ in grids]
    out += [_legend(), ""]
    shown = rows[:_ROW_LIMIT]
    body = [[md_cell(fmt_num(r[n])) for n in names]
            + [md_cell(_category(r) or "not judged"), "yes" if r["feasible"] else "no",
               fmt_num(r["trace_bound"], 4) if r["feasible"] else "—",
               md_cell(r["binding"]), _THEOREM2[r["theorem2"]] if r["feasible"] else "—", md_cell(r["iterations"])]
            + ([md_cell(r.get("rule") or "—"), {True: "yes", False: "no", None: "—"}[r.get("better_than_local")]]
               if auto else [])
            for r in shown]
    out += md_table([md_cell(n) for n in names] + ["verdict", "feasible", "trace bound", "binding", "Theorem 2",
                                                   "iterations"] + (["pick", "below local"] if auto else []),
                    body, ["r"] * len(names) + ["l", "l", "r", "l", "l", "r"] + (["l", "l"] if auto else []))
    if len(rows) > len(shown):
        out += [f"The first {len(shown)} of {len(rows)} points; feasibility.csv has them all.", ""]
    return out


def _point(names: Sequence[str], row: Mapping) -> str:
    return ", ".join(f"{n} = {fmt_num(row[n])}" for n in names)


def _summary(names: Sequence[str], rows: Sequence[Mapping], figures: Sequence[str], meta: Mapping) -> list[str]:
    good, word = _good(rows)
    mode = _mode(meta)
    out = ["## Summary", "", *_verdict_lines(rows, meta)]
    if good:
        out += [f"The {word} points ranked by the steady-state trace bound (mean over nodes of tr Φ), lowest first "
                f"({'the pick at each point' if mode == 'auto' else md_escape(mode) + ' design'}, at the operating "
                "point; a deterministic fixed point, so no "
                "Monte Carlo intervals)" + (f" (the {min(5, len(good))} lowest and the highest):" if len(good) > 6
                                            else ":"), ""]
        shown = good[:5] + (good[-1:] if len(good) > 6 else good[5:6])
        rank = {id(r): i for i, r in enumerate(good, 1)}
        auto = mode == "auto"
        out += md_table(["rank", "grid point", "trace bound", "least slack"] + (["pick"] if auto else []),
                        [[f"{rank[id(r)]}", md_cell(_point(names, r)), fmt_num(r["trace_bound"], 4),
                          md_cell(r["binding"] or "—")] + ([md_cell(r.get("rule") or "—")] if auto else [])
                         for r in shown], ["r", "l", "r", "l"] + (["l"] if auto else []))
    if "feasibility.png" in figures:
        out += figure_lines(1, "feasibility.png", _HEAT_MAP)
    lead = f"**Where the design is {word}:** "
    n_other, other = _others(rows, word)
    if not good:
        line = lead + f"nowhere on this grid ({other})."
    else:
        span = (f"at {md_escape(_point(names, good[0]))} ({fmt_num(good[0]['trace_bound'])})" if len(good) == 1 else
                f"from {fmt_num(good[0]['trace_bound'])} at {md_escape(_point(names, good[0]))} to "
                f"{fmt_num(good[-1]['trace_bound'])} at {md_escape(_point(names, good[-1]))}")
        line = lead + (f"everywhere on this grid, with a bound {span}" if not n_other else
                       f"at {len(good)} of {len(rows)} points, with a bound {span}; elsewhere {other}; the grid "
                       "below shows where")
        line += "; a point's transient along a run is `cfdesign design`'s question (see the two notions below)."
    return out + [line, ""]


def _verdict_lines(rows: Sequence[Mapping], meta: Mapping) -> list[str]:
    """The report's first line: how many points have each verdict (none for a map written without them)."""
    if not _judged(rows):
        return []
    counts = Counter(_category(r) for r in rows)
    n_cert = counts.get("certified", 0)
    parts = [f"{counts[v]} {md_escape(MAP_WORDS[v])}" for v in MAP_CATEGORIES if counts.get(v)]
    ol = meta.get("open_loop") if isinstance(meta.get("open_loop"), Mapping) else {}
    ref = (f" The open-loop reference: tr = {fmt_num(ol['trace'])}, {md_escape(ol.get('how'))}."
           if is_num(ol.get("trace")) else "")
    lead = ("**No point is certified.**" if not n_cert else
            f"**Certified at {n_cert} of {len(rows)} grid points.**")
    return [f"{lead} Verdicts of the stationary bound: " + ", ".join(parts) + "." + ref, ""]


_HEAT_MAP = ("The verdict at each grid point in the colours of the legend (certified and bounded, certified but "
             "not bounded, vacuous, infeasible, not computed, with their counts, as in the first line), and the "
             "steady-state trace bound (mean over nodes of tr Φ, log scale) where a fixed point exists; grey squares "
             "frame the points that failed.")


def _notions_section() -> list[str]:
    return ["## Two notions of feasibility", "",
            "Here `design` is `cfdesign design` (`studies.api.design`) and `feasibility` is this map "
            "(`cfdesign feasibility`).", "", TWO_NOTIONS, "",
            "So a feasible point here says that a bounded bound exists in the long run around the operating point, "
            "not that every run is feasible from its first step; an infeasible point says the stationary recursion "
            "has no bounded fixed point there, which a short run may not reach. To see a point's transient along a "
            "run, design at it (`cfdesign design SCENARIO` with the point's values, e.g. `--dos 0.2 --fdi 0.1`) "
            "and compare the verdicts.", ""]


def _runner_section(meta: Mapping) -> list[str]:
    runner = meta.get("runner")
    if not isinstance(runner, Mapping) or not runner:
        return []
    return ["## How it was computed", "",
            "The grid points go through the Monte Carlo runner in chunks (a point plays the part of a run), stored "
            "under `.chunks` so that an interrupted map resumes; the map does not depend on where the chunks ran. "
            "Where they ran (the backend, the worker processes, the chunks computed and reused, the wall time "
            f"{MEASURED}) differs from one run of the same command to the next: it is recorded in feasibility.json "
            "(`runner`), not here.", ""]


def _files_section(meta: Mapping, grids, figures: Sequence[str]) -> list[str]:
    out = ["## Files and reproduction", "",
           "- `feasibility.csv`: one row per grid point (the grid values, `feasible`, `trace_bound`, `binding`, "
           "`theorem2`, `iterations`, `verdict`)"]
    if isinstance(meta.get("schema"), str):
        out.append(f"- `feasibility.json`: schema `{md_escape(meta['schema'])}`; the grid, the options, the "
                   "operating point, the network, the attacks, the assumptions and the runner")
    if figures:
        out.append("- `feasibility.png`: the heat map")
    out.append("")
    out += software_lines(meta)
    if meta:
        out += rerun_lines(meta, "this map")
    return out + recorded_elsewhere(meta, _KNOWN, "feasibility.json")


def render_feasibility(names: Sequence[str], rows: Sequence[Mapping], meta: Mapping | None = None,
                       figures: Sequence[str] = ()) -> str:
    """The feasibility report as Markdown from the CSV's grid ``names`` and ``rows`` and ``feasibility.json``."""
    meta = meta if isinstance(meta, Mapping) else {}
    scenario = meta.get("scenario") if isinstance(meta.get("scenario"), str) else "unnamed scenario"
    grids = _grids(names, rows, meta)
    head = [f"# Feasibility report: {md_escape(scenario)}", "",
            "Where the consensus design's stationary bound is certified and bounded, certified but not bounded, "
            "vacuous, infeasible or not computed, over a grid of parameters "
            f"({' x '.join(f'{len(v)} {md_escape(n)}' for n, v in grids)} = {len(rows)} points), as computed by "
            "`cfdesign feasibility`.", ""]
    attacks = attack_lines(meta.get("attacks"))
    network = network_lines(meta.get("network"))
    scen = scenario_lines(meta.get("scenario"), None) if "scenario" in meta else []
    return document(head, [
        _mapped_section(scenario, grids, meta), _result_section(rows),
        _grid_section(grids, rows, _mode(meta) == "auto"),
        _notions_section(),
        ["## Attacks", "", "The attack specification of the scenario with the options applied; a grid parameter "
         "(`dos`, `fdi`, `delta`, `amplitude`) replaces its value at every point:", "", *attacks] if attacks else [],
        ["## Network", "", *network] if network else [],
        observability_section(meta),
        ["## Scenario", "", *scen] if scen else [],
        assumption_section(meta.get("assumptions"), "Everything the paper leaves open and the scenario had to "
                           "decide:"),
        _runner_section(meta), _files_section(meta, grids, figures)], _summary(names, rows, figures, meta))


def feasibility_report(d: Path) -> tuple[str, dict[str, bytes], str]:
    """The feasibility report of directory ``d`` (``feasibility.csv``, optionally ``feasibility.json``, ``.png``)."""
    names, rows = _read_csv(d)
    meta: Mapping = {}
    if (d / "feasibility.json").is_file():
        meta = read_record(d, "feasibility.json", "cfdesign.feasibility/1", "a feasibility map's")
    images = {}
    if (d / "feasibility.png").is_file():
        try:
            images["feasibility.png"] = (d / "feasibility.png").read_bytes()
        except OSError as exc:
            raise InputError(f"directory {str(d)!r}: feasibility.png cannot be read: {exc}") from None
    scenario = meta.get("scenario") if isinstance(meta.get("scenario"), str) else "feasibility map"
    return (render_feasibility(names, rows, meta, list(images)), images,
            f"cfdesign feasibility report: {scenario}")
