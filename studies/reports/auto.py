"""The automatic design's part of a design report (``cfdesign design --mode auto``, :mod:`studies.auto`): the
candidates' table and figure from ``candidates.json``, the validation from ``validation.json``.

The files are data (a directory may come from elsewhere): every text is escaped, every number checked before use.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

from ..results import local_ratio_text
from .text import document, fmt_num, md_cell, md_escape, md_table, read_record

__all__ = ["auto_section", "validation_section", "validation_lines", "auto_report", "CANDIDATES_FIGURE"]

CANDIDATES_FIGURE = "fig_candidates.png"


def _num(v) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None


def _rows(record: Mapping) -> list[Mapping]:
    rows = record.get("candidates")
    return [r for r in rows if isinstance(r, Mapping)] if isinstance(rows, list) else []


def _validation_rows(val: Mapping) -> dict[str, Mapping]:
    rows = val.get("filters")
    return {str(k): v for k, v in rows.items() if isinstance(v, Mapping)} if isinstance(rows, Mapping) else {}


def _mse(f: Mapping) -> float | None:
    """The mean squared error over the state (``mse``: Σ of the per-state RMSE squared)."""
    return _num(f.get("mse"))


def _measured(val: Mapping | None, record: Mapping, pick: Mapping | None) -> dict[str, tuple]:
    """name -> (bytes per step, mean squared error) of the validated filters."""
    if not val:
        return {}
    costs = (record.get("references") or {}).get("costs") or {}
    out = {}
    for name, f in _validation_rows(val).items():
        mse = _mse(f)
        if mse is None:
            continue
        if name == "pick":
            b = _num((pick or {}).get("bytes_per_step"))
            out["pick (measured)"] = (b, mse)
            continue
        key = next((k for k in costs if str(name).startswith(k.split(" ")[0])), None)
        out[name] = (_num((costs.get(key) or {}).get("bytes_per_step")) if key else None, mse)
    return out


def _words(c: Mapping) -> str:
    status = c.get("status")
    if status == "designed":
        v = str(c.get("verdict"))
        extra = "" if c.get("bounded") is not False else ", not bounded"
        if c.get("better_than_local") is False:
            extra += ", no better than the local EKFs"
        if c.get("in_budget") is False:
            extra += ", over the budget"
        return md_cell(v + extra)
    return md_cell(f"{status}: {c.get('reason')}")


def auto_section(d: Path, into: Path) -> tuple[list[str], list[str]]:
    """The report's "Automatic design" and "Validation" sections from ``d``'s ``candidates.json`` (and
    ``validation.json``), and the figures drawn into ``into`` (their file names)."""
    from ..figures import candidates_figure

    record = read_record(d, "candidates.json", "cfdesign.candidates/1", "an automatic design's")
    val = read_record(d, "validation.json", "cfdesign.validation/1", "a validation's") \
        if (d / "validation.json").is_file() else None
    rows = _rows(record)
    pick = record.get("pick") if isinstance(record.get("pick"), int) and 0 <= record["pick"] < len(rows) else None
    refs = record.get("references") if isinstance(record.get("references"), Mapping) else {}
    budget = record.get("budget") if isinstance(record.get("budget"), Mapping) else {}
    out = ["## Automatic design", "",
           f"**{md_escape(record.get('message'))}.** `cfdesign design` without `--mode` designs every deployable gain "
           "rule's candidates along the same seeded run and picks, among those certified (finite and informative at "
           "every step of the horizon), inside the budget and better than the nodes' local EKFs, the one with the "
           "smallest predicted error: the node-average tr Φ over the last steps of the horizon; within 1 % the "
           "fewest bytes win.", ""]
    cap, cap_b = _num(budget.get("messages_per_step")), _num(budget.get("bytes_per_step"))
    out += [f"Budget: {fmt_num(cap) + ' messages' if cap is not None else 'no cap on messages'} and "
            f"{fmt_num(cap_b) + ' bytes' if cap_b is not None else 'no cap on bytes'} per step (KCF sends "
            f"{fmt_num(budget.get('kcf_messages_per_step'))} messages). References: the centralized EKF's steady-"
            f"state tr P {fmt_num(refs.get('centralized'))}, the local EKFs' node average "
            f"{fmt_num(refs.get('local_mean'))}.", ""]
    table = []
    for i, c in enumerate(rows):
        table.append([("**" + md_cell(c.get("label")) + " (pick)**") if i == pick else md_cell(c.get("label")),
                      fmt_num(c.get("messages_per_step")), fmt_num(c.get("bytes_per_step")),
                      fmt_num(c.get("predicted_trace")), fmt_num(c.get("ratio_centralized"), 3),
                      fmt_num(c.get("ratio_local"), 3), _words(c), fmt_num(c.get("design_seconds"), 3)])
    out += md_table(["candidate", "messages/step", "bytes/step", "predicted tr Φ", "x centralized", "x local",
                     "verdict", "design s"], table, ["l", "r", "r", "r", "r", "r", "l", "r"])
    figures = []
    measured = _measured(val, record, rows[pick] if pick is not None else None)
    if candidates_figure(into / CANDIDATES_FIGURE, rows, refs, measured, pick,
                         f"{str(record.get('scenario'))[:80]}: predicted error against bytes per step"
                         .replace("$", r"\$")):
        figures.append(CANDIDATES_FIGURE)
        out += [f"![predicted error against bytes per step]({CANDIDATES_FIGURE})", ""]
    if val is not None:
        out += validation_lines(val)
    return out, figures


def validation_section(d: Path) -> list[str]:
    """The "Validation" section of a design directory with ``validation.json`` and no candidates (``--validate R``
    with a named rule)."""
    return validation_lines(read_record(d, "validation.json", "cfdesign.validation/1", "a validation's"))


def validation_lines(val: Mapping[str, Any]) -> list[str]:
    """The "Validation" section: the pick and the references on the fresh runs."""
    rows = _validation_rows(val)
    out = ["## Validation", "",
           f"The design on {fmt_num(val.get('runs'))} fresh Monte Carlo runs ({md_escape(val.get('seeds'))}), beside "
           "KCF, HCMCI, the local and the centralized EKF on the same runs and channel attacks.", ""]
    # with regions each filter is ranked, and the ratios taken, on each node's region (studies.auto.validation)
    regional = any(f.get("rmse_region") is not None for f in rows.values())
    table = []
    for name, f in rows.items():
        bc = f.get("bound_check") if isinstance(f.get("bound_check"), Mapping) else {}
        table.append([md_cell(f.get("filter", name)) + (" (pick)" if name == "pick" else "")]
                     + ([fmt_num(f.get("rmse_region"))] if regional else [])
                     + [fmt_num(f.get("rmse")), fmt_num(_mse(f)), fmt_num(f.get("diverged_runs")),
                        md_cell(bc.get("verdict", "—")) if bc else "—",
                        md_cell(bc.get("verdict_reason", "")) if bc else ""])
    out += md_table(["filter"] + (["RMSE on each node's region", "RMSE, whole state", "mean squared error, whole state"]
                                  if regional else ["RMSE", "mean squared error"])
                    + ["diverged runs", "bound check", "why"], table, ["l"] + ["r"] * (3 + regional) + ["l", "l"])
    if regional and rows.get("pick", {}).get("rmse") is None and rows.get("pick", {}).get("rmse_region") is not None:
        out += ["The pick's nodes carry their regions: a node has no estimate of the other states, so the pick has "
                "no whole-state RMSE (—).", ""]
    ratios = val.get("pick_rmse_ratio") if isinstance(val.get("pick_rmse_ratio"), Mapping) else {}
    said = [f"{fmt_num(r, 3)} x {md_escape(n)}'s" for n, r in ratios.items() if _num(r) is not None]
    if said:
        on = " on each node's region" if regional else ""
        out += [f"The design's RMSE{on} on these runs is {', '.join(said)}.", ""]
    if rows.get("pick", {}).get("better_than_local") is False:  # studies.results.better_than: the one definition
        out += ["**On these runs the design is no better than the nodes alone**: its RMSE over the local EKFs' on "
                f"the same runs is {local_ratio_text(rows['pick'])}, the 95 % paired interval not entirely below 1.",
                ""]
    return out


def auto_report(d: Path, into: Path | None = None) -> tuple[str, dict[str, bytes], str]:
    """The report of an automatic design that wrote no design (no candidate could be designed): its candidates."""
    into = d if into is None else into
    from ..figures import figure_batch

    with figure_batch():
        lines, figures = auto_section(d, into)
    images = {name: (into / name).read_bytes() for name in figures if (into / name).is_file()}
    record = read_record(d, "candidates.json", "cfdesign.candidates/1", "an automatic design's")
    scenario = str(record.get("scenario"))
    head = [f"# Automatic design report: {md_escape(scenario)}", "",
            "No design was written: no candidate could be designed. Each candidate's reason is in the table.", ""]
    return document(head, [lines]), images, f"cfdesign automatic design: {scenario}"
