"""Writing the reports' Markdown: numbers, plain text made safe, tables, any JSON value, the document.

Every text that comes from a results file goes through :func:`md_escape` (or
:func:`md_cell` in a table), which makes it render as exactly that text: no
emphasis, link, code span, entity, raw HTML or block structure can come out of it.
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from designer.validation import InputError

from .render import heading_anchors

__all__ = ["is_num", "fmt_num", "fmt_dur", "DURATION", "MEASURED", "is_time_key", "ci_pair", "with_ci",
           "metric_value", "compact",
           "flat_numbers", "md_escape", "md_cell", "md_table", "demote", "generic", "document", "figure_lines",
           "scenario_spec", "params_table", "network_lines", "assumption_section", "matrix_text", "recorded_elsewhere",
           "code_span", "rerun_lines",
           "read_json", "read_record"]


# ---------------------------------------------------------------------------------------------------------------
# Numbers.


def is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def fmt_num(v, sig: int = 4) -> str:
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


# What every measured duration of a report looks like (:func:`fmt_dur`'s output): the one part of a report that two
# runs of the same command may write differently; masking its matches leaves text that must be identical.
DURATION = re.compile(r"(?<![\w.])-?\d+(?:\.\d+)?(?:e[+-]?\d+)? (?:µs|ms|s|min|h)(?!\w)")

# The words that label a measurement (a time of this machine, never a ranking; no sentence depends on it).
MEASURED = "measured on this machine"


def fmt_dur(s) -> str:
    """A duration in seconds with a unit a reader can take in (a finite one matches :data:`DURATION`)."""
    if not is_num(s) or not math.isfinite(s):
        return fmt_num(s)
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


def is_time_key(key: str) -> bool:
    return key.endswith("_s") and ("time" in key or "wall" in key) and "breakdown" not in key


def ci_pair(ci) -> tuple[float, float] | None:
    if isinstance(ci, (list, tuple)) and len(ci) == 2 and all(is_num(x) for x in ci):
        return float(ci[0]), float(ci[1])
    return None


def with_ci(value, ci) -> str:
    pair = ci_pair(ci)
    if not is_num(value) or pair is None:
        return fmt_num(value)
    return f"{fmt_num(value)} [{fmt_num(pair[0], 3)}, {fmt_num(pair[1], 3)}]"


def metric_value(key: str, value, ci=None) -> str:
    """A metric for a table: durations with units, intervals beside values, short lists inline."""
    if is_time_key(key):
        return fmt_dur(value)
    if isinstance(value, list) and value and all(is_num(x) for x in value):
        cis = ci if isinstance(ci, list) and len(ci) == len(value) else [None] * len(value)
        if len(value) <= 6:
            return ", ".join(with_ci(v, c) for v, c in zip(value, cis))
        return compact(value)
    return with_ci(value, ci)


def compact(v, limit: int = 220) -> str:
    """Any JSON value on one line, numbers formatted, long numeric lists summarised."""
    text = _compact(v)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def flat_numbers(v) -> list | None:
    if is_num(v):
        return [v]
    if isinstance(v, list):
        out = []
        for x in v:
            sub = flat_numbers(x)
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


def _compact(v) -> str:
    if v is None or isinstance(v, (bool, int, float)):
        return fmt_num(v)
    if isinstance(v, str):
        return v
    if isinstance(v, list):
        nums = flat_numbers(v)
        if nums is not None and len(nums) > 40:
            shape = " x ".join(str(s) for s in _shape(v))
            return (f"{len(nums)} values ({shape}), from {fmt_num(min(nums))} to {fmt_num(max(nums))}, "
                    f"mean {fmt_num(sum(nums) / len(nums))}")
        if not v:
            return "none"
        return "[" + ", ".join(_compact(x) for x in v) + "]"
    if isinstance(v, dict):
        if not v:
            return "none"
        return "{" + ", ".join(f"{k}: {_compact(x)}" for k, x in v.items()) + "}"
    return str(v)


def matrix_text(m) -> str:
    """A small matrix in words: ``0.1 I``, ``diag(1, 2)``, ``0`` or its rows."""
    nums = flat_numbers(m)
    shape = _shape(m)
    if nums is None or len(shape) != 2 or not shape[0] or shape[0] != shape[1]:
        return compact(m)
    n = shape[0]
    diag = [m[i][i] for i in range(n)]
    off = [m[i][j] for i in range(n) for j in range(n) if i != j]
    if all(x == 0 for x in off):
        if all(x == 0 for x in diag):
            return f"0 ({n} x {n})"
        if all(x == diag[0] for x in diag):
            return f"{fmt_num(diag[0])} I ({n} x {n})"
        return "diag(" + ", ".join(fmt_num(x) for x in diag) + ")"
    return compact(m)


# ---------------------------------------------------------------------------------------------------------------
# Plain text as Markdown.

_MD_ALWAYS = str.maketrans({"\\": "\\\\", "`": "\\`", "*": "\\*"})
_LINE_START = re.compile(r"(#|>|[-+](\s|$)|-{3,}|\||=|~{3,}|\d{1,9}[.)](\s|$))")


def md_escape(text) -> str:
    """Plain text as Markdown that renders as the same text (here and in CommonMark viewers)."""
    s = str(text).translate(_MD_ALWAYS)
    s = re.sub(r"<(?=[A-Za-z/!?])", r"\\<", s)  # would start raw HTML or an autolink
    s = re.sub(r"&(?=#?\w+;)", r"\\&", s)  # would be an entity
    s = re.sub(r"(?<![A-Za-z0-9])_|_(?![A-Za-z0-9])", r"\\_", s)  # could open or close emphasis
    s = re.sub(r"\[(?=[^\]]*\][(:\[])", r"\\[", s)  # would start a link or a link definition
    s = re.sub(r"\s*[\r\n]+\s*", " ", s).strip()
    m = _LINE_START.match(s)
    if m:
        if s[0].isdigit():
            k = len(re.match(r"\d+", s).group(0))  # escape the "." or ")" of "1." / "1)"
            s = s[:k] + "\\" + s[k:]
        else:
            s = "\\" + s
    return s


def md_cell(text) -> str:
    return md_escape(text).replace("|", "\\|")


def md_table(header: Sequence[str], rows: Iterable[Sequence[str]], align: Sequence[str] | None = None) -> list[str]:
    """Markdown table lines; cells are already Markdown (use :func:`md_cell` for plain text)."""
    rows = list(rows)
    if not rows:
        return []
    align = align or ["l"] + ["r"] * (len(header) - 1)
    sep = "|" + "|".join("---:" if a == "r" else "---" for a in align) + "|"
    return ["| " + " | ".join(header) + " |", sep, *("| " + " | ".join(r) + " |" for r in rows), ""]


def demote(markdown: str, by: int) -> str:
    """Shift every ATX heading ``by`` levels down (at most level 6)."""
    def shift(m):
        return "#" * min(6, len(m.group(1)) + by) + m.group(2)

    return re.sub(r"(?m)^(#{1,6})(\s)", shift, markdown)


# ---------------------------------------------------------------------------------------------------------------
# Any JSON value.


def _cell_value(key: str, x) -> str:
    if key.endswith("_ci95") and ci_pair(x) is not None:
        lo, hi = ci_pair(x)
        return f"[{fmt_num(lo, 3)}, {fmt_num(hi, 3)}]"
    if isinstance(x, list) and 0 < len(x) <= 6 and all(is_num(y) for y in x):
        return metric_value(key, x)
    if isinstance(x, (dict, list)):
        return compact(x, 120)
    return metric_value(key, x)


def _is_records(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _is_complex(v) -> bool:
    return isinstance(v, dict) and bool(v) or _is_records(v) or len(compact(v, 100000)) > 160


def generic(v, depth: int = 0) -> list[str]:
    """Any JSON value as Markdown blocks: tables for maps of maps and lists of records, else lists."""
    if depth > 3:
        return [md_escape(compact(v)), ""]
    if _is_records(v):
        return generic({str(i + 1): x for i, x in enumerate(v)}, depth)
    if isinstance(v, dict) and v and all(isinstance(x, dict) for x in v.values()):
        cols: list[str] = []
        for x in v.values():
            cols += [k for k in x if k not in cols]
        nested = [c for c in cols if any(isinstance(x.get(c), dict) and x.get(c) or _is_records(x.get(c))
                                         for x in v.values())]
        flat = [c for c in cols if c not in nested]
        out = []
        if flat:
            rows = [[md_cell(name)] + [md_cell(_cell_value(str(k), x[k])) if k in x else "—" for k in flat]
                    for name, x in v.items()]
            out += md_table(["name"] + [md_cell(str(c).replace("_", " ")) for c in flat], rows)
        for c in nested:
            sub = {n: x[c] for n, x in v.items() if c in x}
            out += [f"**{md_escape(str(c).replace('_', ' '))}**:", "", *generic(sub, depth + 1)]
        return out
    if isinstance(v, dict):
        out, later = [], []
        for k, x in v.items():
            if _is_complex(x):
                later += [f"**{md_escape(k)}**:", "", *generic(x, depth + 1)]
            elif isinstance(x, (dict, list)):
                out.append(f"- **{md_escape(k)}**: {md_escape(compact(x))}")
            else:
                out.append(f"- **{md_escape(k)}**: {md_escape(metric_value(str(k), x))}")
        return out + [""] + later if out else later
    if isinstance(v, list) and v and flat_numbers(v) is None:
        return [f"- {md_escape(compact(x))}" for x in v] + [""]
    return [md_escape(compact(v)), ""]


# ---------------------------------------------------------------------------------------------------------------
# Pieces every report has.


def document(head: Sequence[str], sections: Iterable[Sequence[str]], summary: Sequence[str] = ()) -> str:
    """The report: ``head`` (its ``#`` title and lead), the ``summary`` (a ``## Summary`` section: what a reader
    acts on, on one screen), a table of contents, then every non-empty section.

    Each section starts with its ``## `` heading; the contents link to them by the anchors
    the HTML page gives them (:func:`studies.reports.render.heading_anchors`).
    """
    sections = [list(s) for s in sections if s]
    out = [*head, "", *summary, "", "## Contents", ""]
    body = "\n".join(line for s in sections for line in s)
    anchors = heading_anchors("\n".join(out) + "\n\n" + body)
    out += [f"- [{md_escape(text).replace(']', chr(92) + ']')}](#{anchor})"
            for level, text, anchor in anchors if level == 2 and anchor not in ("contents", "summary")]
    text = "\n".join(out) + "\n\n" + body
    return re.sub(r"\n{3,}", "\n\n", text).strip() + "\n"


def figure_lines(number: int, name: str, caption: str) -> list[str]:
    """A figure of ``report.md`` (an image line and its caption): a ``<figure>`` in the HTML page."""
    target = name if re.fullmatch(r"[\w.\-]+", name) else f"<{name}>"
    return [f"![Figure {number}: {md_escape(caption)}]({target})",
            f"**Figure {number}.** {md_escape(caption)} (`{name}`)", ""]


def scenario_spec(name):
    """The built-in scenario ``name`` (its title, summary and documented parameters), or None."""
    try:
        from ..scenarios import SCENARIOS
    except Exception:  # pragma: no cover - a report must not depend on the scenario registry importing
        return None
    return SCENARIOS.get(name) if isinstance(name, str) else None


def params_table(spec, params: Mapping) -> list[str]:
    """The scenario's parameters with their meaning and source (``--set NAME=VALUE`` changes one)."""
    docs = {p.name: p for p in spec.params} if spec is not None else {}
    rows = []
    for k, v in params.items():
        p = docs.get(k)
        source = "" if p is None else ("paper" if p.source == "paper" else "our assumption")
        rows.append([f"`{k}`" if "`" not in str(k) else md_cell(k), md_cell(compact(v)),
                     md_cell(p.doc if p is not None else ""), md_cell(source)])
    return md_table(["parameter", "value", "meaning", "source"], rows, ["l", "l", "l", "l"])


def network_lines(net) -> list[str]:
    """The sensor network (``SensorNetwork.describe()``) in words."""
    if not isinstance(net, Mapping) or not net:
        return []
    out = []
    if is_num(net.get("n_nodes")):
        out.append(f"- {fmt_num(net['n_nodes'])} nodes (numbered from 0)")
    edges = net.get("edges")
    if isinstance(edges, list):
        shown = ", ".join(md_escape(compact(e)) for e in edges[:60]) + (" …" if len(edges) > 60 else "")
        out.append(f"- {len(edges)} undirected links: {shown}")
    if isinstance(net.get("degrees"), list):
        out.append(f"- degrees d_i: {md_escape(compact(net['degrees']))}")
    if net.get("d_max") is not None:
        out.append(f"- largest degree d_max: {md_escape(fmt_num(net['d_max']))} (ε must lie in (0, 1/d_max))")
    if net.get("connected") is not None:
        out.append(f"- connected: {md_escape(fmt_num(net['connected']))}")
    rest = {k: v for k, v in net.items() if k not in ("n_nodes", "edges", "degrees", "d_max", "connected")}
    return out + [""] + (generic(rest) if rest else [])


def assumption_section(assumptions, intro: str) -> list[str]:
    if not isinstance(assumptions, list) or not assumptions:
        return []
    return ["## Assumptions", "", intro, "", *(f"- {md_escape(x)}" for x in assumptions), ""]


def recorded_elsewhere(record: Mapping, shown, name: str) -> list[str]:
    """One line naming the keys of ``record`` the report leaves out (``name`` holds them): raw fields stay there."""
    rest = [str(k) for k in record if k not in shown]
    if not rest:
        return []
    return [f"`{name}` also records {', '.join(code_span(k) for k in rest)} (not shown here).", ""]


def code_span(text: str) -> str:
    """``text`` as a Markdown code span, whatever backticks it holds."""
    ticks = max((len(m) for m in re.findall(r"`+", text)), default=0)
    fence = "`" * (ticks + 1)
    pad = " " if text.startswith("`") or text.endswith("`") or ticks else ""
    return f"{fence}{pad}{text}{pad}{fence}"


def rerun_lines(record: Mapping, what: str) -> list[str]:
    """How to compute ``what`` again with the same numbers, from the ``invocation`` the file records
    (:mod:`studies.invocation`): the command line, or why there is none."""
    from ..invocation import command_text

    inv = record.get("invocation")
    cmd = command_text(inv)
    if cmd is not None:
        return [f"To compute {what} again, with the same numbers (DIR: a new output directory):", "",
                code_span(cmd), ""]
    if isinstance(inv, Mapping) and isinstance(inv.get("note"), str):
        return [f"No command line computes {what} again: {md_escape(inv['note'])}.", ""]
    return [f"No command line is recorded for {what} (the file has no `invocation`: an older cfdesign wrote it); "
            "the settings above are what it ran with.", ""]


def read_json(d: Path, name: str) -> Any:
    """``d/name`` parsed, or an InputError naming the directory."""
    try:
        return json.loads((d / name).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as exc:  # ValueError: not JSON, not UTF-8, an integer too long
        why = "its JSON is nested too deeply" if isinstance(exc, RecursionError) else exc
        raise InputError(f"directory {str(d)!r}: {name} cannot be read: {why}") from None


def read_record(d: Path, name: str, schema: str, whose: str, required: bool = True) -> dict:
    """``d/name``: a JSON object whose ``schema`` is ``schema`` (any version); else an InputError naming ``d``.

    ``required=False`` lets the ``schema`` key be absent (a hand-written or older file).
    """
    record = read_json(d, name)
    if not isinstance(record, dict):
        raise InputError(f"directory {str(d)!r}: {name} must hold a JSON object, got {type(record).__name__}")
    family = schema.rsplit("/", 1)[0] + "/"
    given = record.get("schema")
    if (given is not None or required) and not (isinstance(given, str) and given.startswith(family)):
        raise InputError(f"directory {str(d)!r}: {name} has schema {given!r}, not {whose} ({schema})")
    return record


def observability_section(meta: Mapping) -> list[str]:
    """Which nodes observe the state alone, whether the network does, and the steady-state Kalman references.

    Reads ``meta["observability"]`` and ``meta["kalman_references"]`` (:mod:`designer.observability`); empty
    when neither was recorded.
    """
    obs, ref = meta.get("observability"), meta.get("kalman_references")
    if not isinstance(obs, Mapping) and not isinstance(ref, Mapping):
        return []
    out = ["## Observability and the Kalman references", ""]
    nodes = obs.get("nodes") if isinstance(obs, Mapping) else None
    local = ref.get("local") if isinstance(ref, Mapping) and isinstance(ref.get("local"), list) else []
    if isinstance(nodes, list) and nodes:
        n_x = obs.get("n_x")
        net = obs.get("network") if isinstance(obs.get("network"), Mapping) else {}
        alone = [d for d in nodes if isinstance(d, Mapping) and not d.get("observable")]
        out.append(("**The network observes the state** (every sensor together: rank "
                    f"{md_escape(fmt_num(net.get('rank')))} of {md_escape(fmt_num(n_x))})" if net.get("observable") else
                    "**The network does not observe the state**: no gain can make every node's error converge "
                    f"(every sensor together: rank {md_escape(fmt_num(net.get('rank')))} of {md_escape(fmt_num(n_x))})")
                   + ("; every node also observes it alone." if not alone else
                      f"; {len(alone)} of {len(nodes)} nodes cannot observe it alone and depend on their "
                      "neighbours: " + ", ".join(f"{md_escape(d.get('node'))} ({md_escape(d.get('sensor'))})"
                                                 for d in alone) + "."))
        out += ["", f"At the operating point ({md_escape(obs.get('where', 'linearisation'))}; ranks of the "
                "observability matrices [H; HF; ...]; steady-state Kalman filters (the Riccati equation of "
                "python-control's `dlqe`), "
                "trace of the posterior covariance, — where the node alone has no steady state):", ""]
        rows = []
        for d in nodes:
            if not isinstance(d, Mapping):
                continue
            i = d.get("node")
            tr = local[i] if isinstance(i, int) and 0 <= i < len(local) else None
            rows.append([md_escape(fmt_num(i)), md_cell(d.get("sensor")), md_escape(fmt_num(d.get("rank"))),
                         "yes" if d.get("observable") else "no", "—" if tr is None else md_escape(fmt_num(tr))])
        out += md_table(["node", "sensor", "rank", "observes alone", "local steady-state tr P"], rows,
                        ["r", "l", "r", "l", "r"])
        out.append("")
    if isinstance(ref, Mapping) and ref.get("centralized") is not None:
        out += [f"The centralized steady-state Kalman filter (every sensor, no attack) reaches tr P = "
                f"{md_escape(fmt_num(ref['centralized']))}: no distributed filter can do better at this point, and a "
                "bound far above it measures the design's conservatism.", ""]
    return out
