"""Reports (``report.md``, self-contained ``report.html``): content, inlined figures, escaping, robustness.

Study reports: two real studies run at a tiny size (the particle-filter study
``encrypted-switching``, which writes its report through the pipeline's
:func:`studies.outputs.write_outputs`, and ``consensus-robot``, which records no
intervals); the other cases use small hand-written results files.  Design and
feasibility reports: real outputs of :func:`studies.api.design` and
:func:`studies.api.feasibility` on the small linear model of
``examples/linear_network_model.py`` (feasible) and on the indoor robot's paper design
(infeasible).
"""
from __future__ import annotations

import base64
import copy
import json
import re
import sys
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from designer.validation import InputError
from studies import api
from studies.reports import markdown_to_html, render_markdown, write_report
from studies.reports.text import md_escape
from studies.study_registry import study_text

VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source", "track", "wbr"}
PNG_1x1 = base64.b64decode(
    "iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8z8BQDwAEhQGAhKmMIQAAAABJRU5ErkJggg==")


class _Page(HTMLParser):
    """Collects the text, the images and every tag nesting error of a page."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.stack: list[str] = []
        self.errors: list[str] = []
        self.text: list[str] = []
        self.images: list[dict] = []
        self.links: list[str] = []
        self.tags: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        a = dict(attrs)
        if tag == "img":
            self.images.append(a)
        if tag == "a":
            self.links.append(a.get("href", ""))
        if tag not in VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):
        self.handle_starttag(tag, attrs)
        if tag not in VOID:
            self.stack.pop()

    def handle_endtag(self, tag):
        if tag in VOID:
            self.errors.append(f"end tag of void element <{tag}>")
        elif not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes <{self.stack[-1] if self.stack else 'nothing'}>")
        else:
            self.stack.pop()

    def handle_data(self, data):
        self.text.append(data)


def parse(html_text: str) -> _Page:
    page = _Page()
    page.feed(html_text)
    page.close()
    return page


def page_text(page: _Page) -> str:
    return re.sub(r"\s+", " ", "".join(page.text))


def md_plain(md: str) -> str:
    """The text a Markdown source shows, for the escapes the report uses."""
    return re.sub(r"\s+", " ", re.sub(r"\\([!-/:-@\[-`{-~])", r"\1", md))


def norm(s: str) -> str:
    return re.sub(r"\s+", " ", s)


RUN_STUDY = {
    "encrypted-switching": lambda out: api.study("encrypted-switching", out=out, runs=3, particles=30),
    "consensus-robot": lambda out: api.study("consensus-robot", out=out, runs=2),
}


@pytest.fixture(scope="module")
def studies(tmp_path_factory):
    """Each study's output directory, run on first use (one study failing leaves the other's tests alone)."""
    made: dict[str, Path] = {}

    def get(name: str) -> Path:
        if name not in made:
            out = tmp_path_factory.mktemp(name)
            RUN_STUDY[name](out)
            made[name] = out
        return made[name]

    return get


@pytest.fixture(params=list(RUN_STUDY))
def study_dir(request, studies) -> Path:
    return studies(request.param)


@pytest.mark.slow
def test_study_writes_both_reports(study_dir):
    results = json.loads((study_dir / "results.json").read_text())
    md = (study_dir / "report.md").read_text()
    page = (study_dir / "report.html").read_text()
    assert md.startswith(f"# Study report: {results['study']}")
    assert "<title>" in page and results["study"] in page
    for section in ("What this study compares", "Which filter to pick", "Scenario and parameters",
                    "Under which attacks", "Assumptions", "Timings", "Software and reproduction", "Figures"):
        assert f"## {section}" in md
        assert section in page_text(parse(page))


def test_every_assumption_filter_and_version_appears(study_dir):
    results = json.loads((study_dir / "results.json").read_text())
    text = page_text(parse((study_dir / "report.html").read_text()))
    md = md_plain((study_dir / "report.md").read_text())
    assert results["assumptions"]
    for a in results["assumptions"]:
        assert norm(a) in text
        assert norm(a) in md
    for name in results["filters"]:
        assert name in text and name in md
    for k, v in results["versions"].items():
        assert f"{k} | {v}" in md
    for k in results["params"]:
        assert f"`{k}`" in md


def test_every_png_is_inlined_with_identical_bytes(study_dir):
    page = parse((study_dir / "report.html").read_text())
    pngs = {p.name: p.read_bytes() for p in study_dir.glob("*.png")}
    assert len(pngs) >= 4
    inlined = {}
    for img in page.images:
        src = img["src"]
        assert src.startswith("data:image/png;base64,"), src[:40]
        inlined[img["data-file"]] = base64.b64decode(src.split(",", 1)[1], validate=True)
        assert img.get("alt")
    assert inlined == pngs
    md = (study_dir / "report.md").read_text()
    for name in pngs:
        assert f"]({name})" in md  # report.md links the files beside it


def test_html_is_well_formed_and_self_contained(study_dir):
    raw = (study_dir / "report.html").read_text()
    page = parse(raw)
    assert page.errors == []
    assert page.stack == []
    assert page.tags.count("table") >= 3
    assert "script" not in page.tags
    assert "link" not in page.tags  # no external style sheet
    assert all(h.startswith("#") for h in page.links)  # in-page links only
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:|//|file:)""", raw)
    ids = re.findall(r'id="([^"]+)"', raw)
    assert len(ids) == len(set(ids))
    assert {h[1:] for h in page.links} <= set(ids)


def test_pick_section_follows_the_numbers(study_dir):
    results = json.loads((study_dir / "results.json").read_text())
    md = (study_dir / "report.md").read_text()
    pick = md.split("## Which filter to pick", 1)[1].split("\n## ", 1)[0]
    refs = set(study_text(results["study"]).references)
    f = {n: m for n, m in results["filters"].items() if n not in refs}  # benchmarks are never picked
    if results["study"] == "consensus-robot":
        assert refs & set(results["filters"])  # the unattacked fusion centre is a benchmark
        best = min(f, key=lambda n: f[n]["rmse_position"])
        assert (f"**Most accurate (position RMSE over all nodes):** {best}, {f[best]['rmse_position']:.4g} "
                f"[{f[best]['rmse_position_ci95'][0]:.3g}, {f[best]['rmse_position_ci95'][1]:.3g}]") in pick
        fewest = min(v["communications"] for v in f.values())
        assert "**Fewest communications:** " in pick and f"({fewest} messages" in pick
    else:
        for i in range(2):
            best = min(f, key=lambda n: f[n]["rmse_state"][i])
            assert f"**Most accurate (RMSE of x{i + 1}):** {best}," in pick
    assert "**Time per step:** measured on this machine" in pick and "cheapest" not in pick.lower()


def _results(**extra) -> dict:
    base = {
        "schema": "cfdesign.study/1", "study": "comparison", "scenario": "indoor-robot", "runs": 40,
        "particles": 100, "steps": 30, "seed": 7,
        "assumptions": ["comparison: first assumption", "comparison: second, with 2|E| messages and x_{k+1}"],
        "wall_time_s": 12.5, "versions": {"python": "3.11.7", "numpy": "2.0.0"},
        "filters": {
            "fast": {"rmse_position": 1.0, "rmse_position_ci95": [0.9, 1.1], "time_per_step_s": 1e-5,
                     "communications": 8},
            "close": {"rmse_position": 1.05, "rmse_position_ci95": [0.95, 1.2], "time_per_step_s": 2e-3,
                      "communications": 20},
            "far": {"rmse_position": 3.0, "rmse_position_ci95": [2.5, 3.5], "time_per_step_s": 5e-4,
                    "communications": 8},
        },
        "sweeps": {"dos_prob": {"0.1": {"fast": {"rmse_position": 1.0, "rmse_position_ci95": [0.9, 1.1]},
                                        "far": {"rmse_position": 3.0}},
                                "0.4": {"fast": {"rmse_position": 1.7, "rmse_position_ci95": [1.5, 1.9]}}}},
        "paper": {"source": "nowhere", "note": "no numbers"},
    }
    base.update(extra)
    return base


def _write(tmp_path: Path, results, table: str | None = None, pngs=("fig_a.png",)) -> Path:
    (tmp_path / "results.json").write_text(json.dumps(results))
    if table is not None:
        (tmp_path / "table.md").write_text(table)
    for name in pngs:
        (tmp_path / name).write_bytes(PNG_1x1)
    return tmp_path


def test_comparison_results_are_rendered_generically(tmp_path):
    d = _write(tmp_path, _results())
    html_path, md_path = write_report(d)
    assert (html_path, md_path) == (d / "report.html", d / "report.md")
    md = md_path.read_text()
    # no table.md: our own table of the key metrics, intervals beside the values
    assert "| fast | 1 [0.9, 1.1] |" in md
    assert "### dos_prob" in md and "dos_prob = 0.4" in md and "1.7 [1.5, 1.9]" in md
    pick = md.split("## Which filter to pick", 1)[1].split("\n## ", 1)[0]
    assert "**Most accurate (position RMSE):** fast, 1 [0.9, 1.1]" in pick
    assert "overlaps that of close" in pick and "not significant" in pick  # [0.9, 1.1] meets [0.95, 1.2]
    assert "far" not in pick.split("Fewest")[0]  # [2.5, 3.5] is apart: not named as a tie
    assert "**Fewest communications:** fast, far (8 messages)" in pick
    assert "10 µs" not in pick and "so no filter is ranked or picked by it" in pick  # a time ranks nothing
    assert "Monte Carlo confidence intervals" in md and "± half-width" in md
    assert "12.5 s" in md  # the study's wall time, with a unit


def test_a_significant_lead_is_called_significant(tmp_path):
    r = _results()
    r["filters"]["close"]["rmse_position_ci95"] = [1.15, 1.3]
    r["filters"]["close"]["rmse_position"] = 1.2
    write_report(_write(tmp_path, r))
    pick = (tmp_path / "report.md").read_text().split("## Which filter to pick", 1)[1].split("\n## ", 1)[0]
    assert "overlaps no other filter's: the lead is significant" in pick
    assert "not significant" not in pick.split("\n- ")[1]


def test_study_table_and_paper_are_included(tmp_path):
    table = ("# demo (seed 9): Table 1\n\nSome words.\n\n| | RMSE (ours) | RMSE (paper) |\n|---|---:|---:|\n"
             "| fast | 1 [0.9, 1.1] | 0.95 |\n")
    paper = {"source": "seed 9, Table 1", "filters": {"fast": {"rmse_position": 0.95}}, "claims": ["A beats B"]}
    write_report(_write(tmp_path, _results(paper=paper), table))
    md = (tmp_path / "report.md").read_text()
    assert "#### demo (seed 9): Table 1" in md  # nested under the report's headings
    assert "| fast | 1 [0.9, 1.1] | 0.95 |" in md
    assert "- A beats B" in md and "Source: seed 9, Table 1." in md
    page = parse((tmp_path / "report.html").read_text())
    assert page.errors == [] and page.stack == []
    assert "0.95" in page_text(page)


def test_html_escaping(tmp_path):
    evil = '<script>alert("x")</script> & <b>bold</b> `tick` **star** [a](#b) \\ |pipe|'
    r = _results(assumptions=[evil, "- starts like a list", "# starts like a heading", "1. like a number"])
    r["filters"]['<img src=x onerror="alert(1)">'] = {"rmse_position": 2.0, "time_per_step_s": 1e-3}
    r["params"] = {"note<script>": "<script>bad()</script>"}
    table = "# T\n\n| | a |\n|---|---:|\n| <script>x()</script> | 1 |\n\n<iframe src=x></iframe>\n"
    write_report(_write(tmp_path, r, table))
    raw = (tmp_path / "report.html").read_text()
    assert "<script" not in raw.lower() and "<iframe" not in raw.lower() and "<b>" not in raw
    assert "<img src=x" not in raw
    assert "&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt; &amp; &lt;b&gt;bold&lt;/b&gt;" in raw
    page = parse(raw)
    assert page.errors == [] and page.stack == []
    assert "script" not in page.tags and "iframe" not in page.tags and "b" not in page.tags
    text = page_text(page)
    for a in r["assumptions"]:
        assert a in text  # shown literally, not interpreted
    assert '<img src=x onerror="alert(1)">' in text
    md = (tmp_path / "report.md").read_text()
    assert "\\<script>" in md  # the Markdown does not carry raw HTML either
    for a in r["assumptions"]:
        assert a in md_plain(md)
    assert len(page.images) == 1  # only the real figure


@pytest.mark.parametrize("drop", ["schema", "study", "scenario", "runs", "particles", "steps", "seed",
                                  "assumptions", "wall_time_s", "versions", "filters", "sweeps", "paper"])
def test_missing_optional_keys(tmp_path, drop):
    r = _results()
    del r[drop]
    html_path, md_path = write_report(_write(tmp_path, r))
    page = parse(html_path.read_text())
    assert page.errors == [] and page.stack == []
    assert md_path.read_text().startswith("# Study report")


def test_missing_and_odd_values_do_not_crash(tmp_path):
    r = _results()
    r["filters"]["fast"].update(rmse_position=None, rmse_position_ci95=None, time_per_step_s=None)
    r["filters"]["close"]["rmse_position_ci95"] = [1.0]
    r["filters"]["far"]["rmse_state"] = [1.0, None, float("nan")]
    r["filters"]["weird"] = {"rmse_position": float("inf"), "nested": {"a": {"b": {"c": {"d": [1, 2]}}}},
                             "communications": "many"}
    r["filters"]["not a map"] = 3
    r["sweeps"]["bad"] = [1, 2]
    r["sweeps"]["empty"] = {}
    r["paper"] = "a string"
    r["params"] = {"x": list(range(500)), "m": [[1, 2], [3, 4]], "empty": [], "none": None}
    r["extra"] = {"deep": [{"a": 1}, {"b": 2}], "numbers": list(range(100))}
    d = tmp_path
    (d / "results.json").write_text(json.dumps(r))  # NaN and Infinity as Python's json writes them
    for results in (r, {}, {"study": 5, "filters": []}, {"filters": {"a": {}}}):
        (d / "results.json").write_text(json.dumps(results))
        html_path, md_path = write_report(d)
        page = parse(html_path.read_text())
        assert page.errors == [] and page.stack == []
    md = render_markdown(r)
    assert "500 values" in md  # a long list is summarised


def test_rewriting_leaves_no_temporary_files(tmp_path):
    d = _write(tmp_path, _results(), pngs=("fig_a.png", "fig_b.png"))
    write_report(d)
    first = (d / "report.html").read_text()
    r = _results()
    r["assumptions"].append("comparison: added later")
    (d / "results.json").write_text(json.dumps(r))
    write_report(d)
    assert sorted(p.name for p in d.iterdir()) == ["fig_a.png", "fig_b.png", "report.html", "report.md",
                                                  "results.json"]
    assert "added later" in (d / "report.html").read_text() and "added later" not in first
    assert "added later" in (d / "report.md").read_text()


def test_a_failed_write_keeps_the_old_report(tmp_path, monkeypatch):
    d = _write(tmp_path, _results())
    write_report(d)
    before = (d / "report.html").read_bytes()
    import studies.reports as report

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(report, "markdown_to_html", boom)
    with pytest.raises(RuntimeError):
        write_report(d)
    assert (d / "report.html").read_bytes() == before
    assert not [p for p in d.iterdir() if p.name.startswith(".")]


def test_bad_input_names_the_directory(tmp_path):
    with pytest.raises(InputError, match="directory .* does not exist"):
        write_report(tmp_path / "nope")
    with pytest.raises(InputError, match="directory .* has no results.json, schedule.json or feasibility.csv"):
        write_report(tmp_path)
    with pytest.raises(InputError, match=r"expected one of results.json \(a study's.*schedule.json \(a design's"
                                         r".*feasibility.csv \(a feasibility map's"):
        write_report(tmp_path)
    (tmp_path / "results.json").write_text("{not json")
    with pytest.raises(InputError, match="directory .*results.json cannot be read"):
        write_report(tmp_path)
    (tmp_path / "results.json").write_text("[1, 2]")
    with pytest.raises(InputError, match="JSON object"):
        write_report(tmp_path)
    (tmp_path / "results.json").write_text(json.dumps({"schema": "cfdesign.schedule/1"}))
    with pytest.raises(InputError, match="not a study's"):
        write_report(tmp_path)
    with pytest.raises(InputError, match="directory must be a path"):
        write_report(3.5)
    assert not (tmp_path / "report.html").exists()
    design, feas = tmp_path / "design", tmp_path / "feas"
    design.mkdir(), feas.mkdir()
    (design / "schedule.json").write_text(json.dumps({"schema": "cfdesign.study/1"}))
    with pytest.raises(InputError, match="schedule.json has schema .* not a design's"):
        write_report(design)
    (design / "schedule.json").write_text("{")
    with pytest.raises(InputError, match="directory .*design.*schedule.json cannot be read"):
        write_report(design)
    (feas / "feasibility.csv").write_text("dos,trace_bound\n0.1,2\n")
    with pytest.raises(InputError, match="feasibility.csv has no 'feasible' column"):
        write_report(feas)
    (feas / "feasibility.csv").write_text("dos,feasible,trace_bound,binding,theorem2,iterations\n0.1,1,2,(28),1,3\n")
    (feas / "feasibility.json").write_text(json.dumps({"schema": "cfdesign.schedule/1"}))
    with pytest.raises(InputError, match="feasibility.json has schema .* not a feasibility map's"):
        write_report(feas)
    assert not (design / "report.html").exists() and not (feas / "report.html").exists()


def test_markdown_rendering():
    """markdown-it-py with tables, raw HTML off, anchors, figures inlined, outside links shown as text."""
    md = ("# Title *x*\n\nA paragraph with `a<b` and **bold \\*star\\*** <script>alert(1)</script> &amp; "
          "<b>b</b>.\n\n- one\n  - one.a\n  - one.b\n- two\n\n| | left | right |\n|---|---|---:|\n"
          "| r1 | a \\| b | 1 |\n| r2 | c |\n\n![A figure](fig_a.png)\n**Figure 1.** caption\n\n"
          "See [the title](#title-x), [out](https://example.com/x) and <https://example.com/y>.\n\n## Title *x*\n")
    raw = markdown_to_html(md, {"fig_a.png": PNG_1x1}, title="t<")
    page = parse(raw)
    assert page.errors == [] and page.stack == []
    flat = re.sub(r"\s*\n\s*", "", raw)
    assert '<h1 id="title-x">Title <em>x</em></h1>' in flat and '<h2 id="title-x-1">' in flat  # repeats: -1
    assert "<code>a&lt;b</code>" in raw and "<strong>bold *star*</strong>" in raw
    assert "&lt;script&gt;alert(1)&lt;/script&gt; &amp; &lt;b&gt;b&lt;/b&gt;" in raw  # raw HTML is text
    assert "script" not in page.tags and "b" not in page.tags
    assert "<ul><li>one<ul><li>one.a</li><li>one.b</li></ul></li><li>two</li></ul>" in flat
    assert '<td>a | b</td><td class="right">1</td>' in flat
    assert '<td>r2</td><td>c</td><td class="right"></td>' in flat  # short rows are padded
    assert '<div class="table-wrap"><table>' in flat and "style=" not in raw.split("</style>", 1)[1]
    assert 'width="1" height="1"' in raw
    assert "<figcaption><strong>Figure 1.</strong> caption</figcaption></figure>" in flat
    (img,) = page.images
    assert base64.b64decode(img["src"].split(",", 1)[1]) == PNG_1x1 and img["data-file"] == "fig_a.png"
    assert img["alt"] == "A figure"
    assert page.links == ["#title-x"]  # links out of the page are shown as their text
    assert "example.com" not in "".join(re.findall(r'(?:href|src)="([^"]*)"', raw))
    assert "<title>t&lt;</title>" in raw
    assert "default-src 'none'" in raw and "<script" not in raw
    missing = markdown_to_html("![gone](gone.png)\n")
    assert "<img" not in missing and "gone.png" in missing


def test_plain_text_renders_as_itself():
    """Every text from a results file goes through md_escape: no Markdown or HTML comes out of it."""
    texts = ["<script>alert('x')</script>", "*star* _under_ __dunder__ `tick` ~~strike~~", "&amp; &#60; &lt;",
             "[link](http://x) [ref][r] ![img](y.png)", "# heading", "> quote", "- item", "+ item", "1. one",
             "2) two", "---", "***", "___", "| a | b |", "=== setext", "~~~ fence", "    four spaces",
             "back\\slash \\*", "trailing  ", "x_{k+1} and rmse_position", "a\nb\r\nc", "<http://auto.link>"]
    for t in texts:
        raw = markdown_to_html(md_escape(t) + "\n")
        page = parse(raw)
        body = raw.split("<main>", 1)[1]
        assert not {"em", "strong", "code", "a", "img", "h1", "blockquote", "ul", "ol", "hr", "table", "pre",
                    "script", "del"} & set(page.tags), (t, body)
        assert page_text(parse(body)).strip() == " ".join(t.split()), (t, body)
        assert md_plain(md_escape(t)).strip() == " ".join(t.split())


def test_report_is_deterministic(tmp_path):
    r = _results()
    assert render_markdown(copy.deepcopy(r)) == render_markdown(r)
    d = _write(tmp_path, r)
    write_report(d)
    a = (d / "report.html").read_bytes()
    write_report(d)
    assert (d / "report.html").read_bytes() == a


def test_a_multi_scenario_comparison_is_ranked_per_scenario(tmp_path):
    """Errors of different scenarios are in different units: ranked within a scenario only; a filter that
    diverged in every run is never recommended for its cost."""
    a = _results()["filters"]
    b = {"cheap-but-diverged": {"rmse_position": None, "rmse_position_ci95": None, "time_per_step_s": 1e-7,
                                "communications": 1, "diverged_runs": 40},
         "ok": {"rmse_position": 50.0, "rmse_position_ci95": [45.0, 55.0], "time_per_step_s": 1e-3,
                "communications": 4}}
    r = _results(scenario="indoor-robot, target-range-bearing",
                 filters={**{f"indoor-robot: {n}": m for n, m in a.items()},
                          **{f"target-range-bearing: {n}": m for n, m in b.items()}},
                 by_scenario={"indoor-robot": {"runs": 40, "filters": a, "params": {"meas_var": 1.0}},
                              "target-range-bearing": {"runs": 40, "filters": b, "params": {"glint_prob": 0.2}}})
    write_report(_write(tmp_path, r))
    md = (tmp_path / "report.md").read_text()
    pick = md.split("## Which filter to pick", 1)[1].split("\n## ", 1)[0]
    robot, target = pick.split("### indoor-robot", 1)[1].split("### target-range-bearing", 1)
    assert "**Most accurate (position RMSE):** fast, 1 [0.9, 1.1]" in robot
    assert "**Most accurate (position RMSE):** ok, 50 [45, 55]" in target
    assert "(4)." in target.split("**Communications:**")[1] and "cheap-but-diverged" not in target.split("Caution")[0]
    scen = md.split("## Scenarios and parameters", 1)[1].split("\n## ", 1)[0]
    assert "`glint_prob`" in scen.split("### target-range-bearing", 1)[1]
    assert "`meas_var`" in scen.split("### indoor-robot", 1)[1].split("### target-range-bearing", 1)[0]


# ---------------------------------------------------------------------------------------------------------------
# Design and feasibility reports, from real outputs.

LINEAR = str(Path(__file__).resolve().parents[1] / "examples" / "linear_network_model.py")
SMALL = dict(sigma=0.01, beta=0.01, u_scale=0, v_scale=0)  # feasible on the linear model
HARD = ("(28)", "(29)", "diverged")


@pytest.fixture(scope="module")
def designs(tmp_path_factory):
    """The linear model's feasible design and the indoor robot's infeasible paper design, written with reports."""
    lin, robot = tmp_path_factory.mktemp("lin-design"), tmp_path_factory.mktemp("robot-paper")
    a = api.design(LINEAR, mode="paper", seed=2, out=lin, **SMALL)
    b = api.design("indoor-robot", mode="paper", seed=1, out=robot)
    assert a.feasible and not b.feasible  # the premise of the tests below
    return {"feasible": (lin, a), "infeasible": (robot, b)}


@pytest.fixture(params=["feasible", "infeasible"])
def design_dir(request, designs) -> tuple[Path, object]:
    return designs[request.param]


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    """Feasibility maps of the linear model: 4 x 4 over (sigma, beta), part feasible, and 1-D over sigma."""
    two, one = tmp_path_factory.mktemp("map2"), tmp_path_factory.mktemp("map1")
    m2 = api.feasibility(LINEAR, ["sigma=0:12:4", "beta=0:12:4"], mode="paper", u_scale=0, v_scale=0, out=two)
    m1 = api.feasibility(LINEAR, ["sigma=0:20:6"], mode="paper", u_scale=0, v_scale=0, out=one)
    assert 0 < m2.feasible.sum() < m2.feasible.size and 0 < m1.feasible.sum() < m1.feasible.size
    return {"two": (two, m2), "one": (one, m1)}


def _section(md: str, title: str) -> str:
    return md.split(f"\n## {title}\n", 1)[1].split("\n## ", 1)[0].strip("\n") + "\n"


def _valid_png(data: bytes) -> tuple[int, int]:
    import io

    from PIL import Image

    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    with Image.open(io.BytesIO(data)) as im:
        im.load()  # decodes every pixel: a truncated or damaged file raises
        return im.size


def _check_self_contained(raw: str) -> _Page:
    page = parse(raw)
    assert page.errors == [] and page.stack == []
    assert "script" not in page.tags and "link" not in page.tags and "iframe" not in page.tags
    assert "Content-Security-Policy" in raw and "default-src 'none'" in raw
    srcs = re.findall(r"""(?:src|href)\s*=\s*["']([^"']*)""", raw)
    assert srcs and all(x.startswith(("data:image/png;base64,", "#")) for x in srcs), [x[:40] for x in srcs]
    ids = re.findall(r'id="([^"]+)"', raw)
    assert len(ids) == len(set(ids)) and {h[1:] for h in page.links} <= set(ids)
    return page


@pytest.mark.slow
def test_design_report_verdict(design_dir):
    d, res = design_dir
    sched = json.loads((d / "schedule.json").read_text())
    md = (d / "report.md").read_text()
    assert md.startswith(f"# Design report: {sched['scenario']}")
    verdict = _section(md, "Verdict")
    size = f"({sched['nodes']} nodes, {sched['steps']} steps)"
    if sched["feasible"]:
        assert verdict.startswith(f"**Feasible.** Conditions (28) and (29) held at every node and every step of the "
                                  f"run {size} and no node diverged")
    else:
        hard = [v for v in sched["violations"] if v["condition"] in HARD]
        first = min(hard, key=lambda v: (v["step"], v["node"]))
        nodes = len({v["node"] for v in hard})
        assert verdict.startswith(f"**Infeasible.** {len(hard)} violation(s) of (28)-(29) or divergence, at {nodes} "
                                  f"of {sched['nodes']} nodes {size}. The first violation: condition "
                                  f"{first['condition']} at node {first['node']}, step {first['step']}, margin "
                                  f"{first['margin']:.4g}.")
        # the same violation Design.reason() names
        assert (f"first at node {first['node']}, step {first['step']}, condition {first['condition']}, margin "
                f"{first['margin']:.4g}") in res.reason()
    if any(v["condition"] == "theorem2" for v in sched["violations"]):
        assert "Theorem 2's sufficient condition for mean-square boundedness of the error did not hold" in verdict
    page = page_text(parse((d / "report.html").read_text()))
    assert ("Feasible." if sched["feasible"] else "Infeasible.") in page


def test_a_bound_without_multipliers_is_reported_without_conditions_28_29(tmp_path):
    """A relay design's bound (each node's expected covariance) has no σ, β: its report neither says that (28)-(29)
    held nor that no node had a bound (it had one at every step), and shows no margins (the buoys of session 63:
    'Conditions (28) and (29) held' and 'No margin was checked at any node (no node had a bound)' for a certified
    flood design)."""
    d = tmp_path / "relay"
    res = api.design(LINEAR, mode="relay", seed=2, out=d, steps=8, validate=2)
    z = np.load(d / "schedule.npz")
    assert z["valid"].all() and not np.isfinite(z["margin28"]).any()  # the premise: bounds, no margins
    md = (d / "report.md").read_text()
    assert "(28) and (29) held" not in md and "(28)-(29) held" not in md and "no node had a bound" not in md
    assert "\n## Which condition binds where\n" not in md and "fig_margins.png" not in md
    assert not (d / "fig_margins.png").exists()
    verdict = _section(md, "Verdict")
    assert verdict.startswith("**Feasible.** This rule's bound has no multipliers σ, β: conditions (28)-(29) do "
                              "not apply to it") and res.feasible
    assert "Yes, along this run: every node's bound was finite at every step" in md
    assert "[Validation](#validation) checks it on fresh runs" in md and "\n## Validation\n" in md
    assert "| rank | node | sensor | first violation | final tr Φ |" in md


def test_design_report_binding_table_follows_the_margins(design_dir):
    d, _ = design_dir
    sched = json.loads((d / "schedule.json").read_text())
    z = np.load(d / "schedule.npz")
    m28, m29 = z["margin28"], z["margin29"]
    table = _section((d / "report.md").read_text(), "Which condition binds where")
    rows = [r for r in table.splitlines() if re.match(r"\| \d+ \|", r)]
    assert len(rows) == sched["nodes"]
    for i, row in enumerate(rows):
        cand = [(m28[i, k], k, "(28)", k) for k in range(m28.shape[1]) if np.isfinite(m28[i, k])]
        cand += [(m29[i, k], k + 1, "(29)", k + 1) for k in range(m29.shape[1]) if np.isfinite(m29[i, k])]
        margin, _, cond, step = min(cand)
        both = np.isfinite(m28[i]) & np.isfinite(m29[i])
        n29 = int(np.sum(both & (m29[i] < m28[i])))
        sensor = sched["sensors"][i]["name"]
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[:5] == [str(i), sensor, cond, str(step), f"{margin:.4g}"], row
        assert cells[6] == f"{100 * n29 / both.sum():.3g} %" and cells[7] == str(int(both.sum()))
    if not sched["feasible"]:
        # a node's tightest spot is its first violation
        for v in sched["violations"]:
            if v["condition"] in ("(28)", "(29)"):
                name = sched["sensors"][v["node"]]["name"]
                assert f"| {v['node']} | {name} | {v['condition']} | {v['step']} |" in table


def test_design_report_figures_are_written_and_inlined(design_dir):
    d, _ = design_dir
    page = _check_self_contained((d / "report.html").read_text())
    inlined = {img["data-file"]: base64.b64decode(img["src"].split(",", 1)[1], validate=True) for img in page.images}
    assert set(inlined) == {"fig_trace_bound.png", "fig_margins.png"}
    for name, data in inlined.items():
        assert data == (d / name).read_bytes()
        w, h = _valid_png(data)
        assert w > 300 and h > 200
    md = (d / "report.md").read_text()
    assert "](fig_trace_bound.png)" in md and "](fig_margins.png)" in md
    assert page.tags.count("table") >= 2  # binding, per node (and the scenario's parameters of a built-in one)


def test_design_report_per_node_table(design_dir):
    d, res = design_dir
    sched = json.loads((d / "schedule.json").read_text())
    z = np.load(d / "schedule.npz")
    md = (d / "report.md").read_text()
    nodes = _section(md, "Per node: ε, σ, β, gains and the final bound")
    for i in range(sched["nodes"]):
        row = next(r for r in nodes.splitlines() if r.startswith(f"| {i} | "))
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[2] == f"{sched['epsilon']:.4g}"
        k = z["K"][i][np.all(np.isfinite(z["K"][i]), axis=(1, 2))]
        assert cells[5] == f"{np.linalg.norm(k, 2, axis=(1, 2)).max():.4g}"
        tb = sched["trace_bound"][i][-1]
        if tb is not None:
            assert cells[7] == f"{tb:.4g}" and cells[8] == "none"
        else:
            assert cells[7].startswith("none (last ") and cells[8] != "none"
        if sched["mode"] == "paper":
            assert cells[3].startswith(f"{sched['sigma_fixed']:.4g} (fixed)")
        else:
            sig = np.array([np.nan if x is None else x for x in sched["sigma"][i]])
            assert cells[3] == f"{np.nanmin(sig):.4g} / {np.nanmedian(sig):.4g} / {np.nanmax(sig):.4g}"


def test_design_report_explains_the_bound_and_lists_the_design(design_dir):
    d, res = design_dir
    sched = json.loads((d / "schedule.json").read_text())
    md = (d / "report.md").read_text()
    text = md_plain(md)
    meaning = md_plain(_section(md, "What the bound means and where it holds"))
    assert "It holds along the simulated run it was computed on" in meaning
    assert sched["trajectory"] in meaning and sched["replay"] in meaning
    for title in ("Design settings", "Linearisation", "Attacks", "Network", "Assumptions",
                  "Files and reproduction"):
        assert f"\n## {title}\n" in md
    assert f"δ = {sched['delta']:.4g}" in text and "U = " in text and "V_i" in text
    for a in sched["assumptions"]:
        assert norm(a) in norm(text)
    page = page_text(parse((d / "report.html").read_text()))
    for a in sched["assumptions"]:
        assert norm(a) in page


@pytest.mark.slow
def test_design_report_escapes_texts_from_the_schedule(designs, tmp_path):
    src, _ = designs["feasible"]
    d = tmp_path / "evil"
    d.mkdir()
    for name in ("schedule.json", "schedule.npz"):
        (d / name).write_bytes((src / name).read_bytes())
    sched = json.loads((d / "schedule.json").read_text())
    evil = '<script>alert("x")</script> & <img src=x onerror="alert(1)"> [a](https://example.com) *b*'
    sched["assumptions"].append(evil)
    sched["scenario"] = "<b>bold</b>"
    sched["sensors"][0]["name"] = "<script>s()</script>"
    sched["extra_field"] = {"note": "<iframe src=x></iframe>"}
    (d / "schedule.json").write_text(json.dumps(sched))
    write_report(d)
    raw = (d / "report.html").read_text()
    assert "<script" not in raw.lower() and "<iframe" not in raw.lower() and "<b>" not in raw
    assert "<img src=x" not in raw
    page = _check_self_contained(raw)
    text = page_text(page)
    assert evil in text and "<script>s()</script>" in text
    assert "<iframe" not in text and "schedule.json also records extra_field (not shown here)." in text
    assert "Design report: <b>bold</b>" in text
    assert len(page.images) == 2 and not [t for t in page.tags if t == "b"]


@pytest.mark.slow
def test_design_report_is_deterministic(designs):
    d, _ = designs["infeasible"]
    before = {n: (d / n).read_bytes() for n in ("report.html", "report.md", "fig_trace_bound.png", "fig_margins.png")}
    write_report(d)
    assert {n: (d / n).read_bytes() for n in before} == before


def test_design_report_with_a_damaged_array_leaves_every_array_out_and_says_so(designs, tmp_path):
    """schedule.npz opens but one member's data are damaged (the report reads each member when it needs it, not
    all at once): the report says so and gives what schedule.json has, as for a lost file; the same file intact
    gives the arrays' figures and the files line with every member's shape from its header."""
    import zipfile

    src, _ = designs["infeasible"]
    (tmp_path / "schedule.json").write_bytes((src / "schedule.json").read_bytes())
    with zipfile.ZipFile(src / "schedule.npz") as zin, zipfile.ZipFile(tmp_path / "schedule.npz", "w") as zout:
        for name in zin.namelist():
            data = zin.read(name)
            zout.writestr(name, data[:-8] if name == "C.npy" else data)  # C's data cut short
    write_report(tmp_path)
    md = (tmp_path / "report.md").read_text()
    assert "schedule.npz cannot be read" in md and "**Infeasible.**" in md
    assert "fig_margins.png" not in md and "- `schedule.npz`: " not in md
    _check_self_contained((tmp_path / "report.html").read_text())
    whole = (src / "report.md").read_text()
    with np.load(src / "schedule.npz") as z:
        shapes = {k: z[k].shape for k in z.files}
    line = next(x for x in whole.splitlines() if x.startswith("- `schedule.npz`: "))
    assert all(f"`{k}` {' x '.join(map(str, v))}" in line for k, v in shapes.items())


def test_design_report_without_the_arrays(designs, tmp_path):
    """schedule.npz lost: the report says so and gives what schedule.json has (the bound from its trace_bound)."""
    src, _ = designs["infeasible"]
    (tmp_path / "schedule.json").write_bytes((src / "schedule.json").read_bytes())
    write_report(tmp_path)
    md = (tmp_path / "report.md").read_text()
    assert "schedule.npz is missing" in md and "**Infeasible.**" in md
    assert "](fig_trace_bound.png)" in md and "fig_margins.png" not in md
    assert _valid_png((tmp_path / "fig_trace_bound.png").read_bytes())
    _check_self_contained((tmp_path / "report.html").read_text())


@pytest.mark.slow
def test_feasibility_report_counts_and_grid(maps):
    d, fmap = maps["two"]
    md = (d / "report.md").read_text()
    n_cert = int(fmap.certified.sum())
    assert md.startswith(f"# Feasibility report: {fmap.scenario.name}")
    assert f"**{n_cert} of {len(fmap.rows)} grid points are certified.**" in md
    grid = _section(md, "The grid")
    (n1, v1), (n2, v2) = fmap.grids
    assert f"| {n1} \\\\ {n2} | " + " | ".join(f"{b:.4g}" for b in v2) + " |" in grid
    for a in v1:
        row = next(r for r in grid.splitlines() if r.startswith(f"| {a:.4g} | "))
        cells = [c.strip() for c in row.strip("|").split("|")][1:]
        for b, cell in zip(v2, cells):
            r = next(x for x in fmap.rows if x[n1] == a and x[n2] == b)
            dagger = "" if r["theorem2"] or not r["feasible"] else " †"
            if r["verdict"] == "certified":
                assert cell == f"{r['trace_bound']:.3g}" + dagger
            elif r["verdict"] == "vacuous" and r["feasible"]:
                assert cell == f"vacuous {r['trace_bound']:.3g}" + dagger
            elif r["verdict"] == "infeasible":
                assert cell == f"✗ {r['binding']}"
            else:
                assert cell.startswith(r["verdict"]) and r["binding"] in cell
    html_raw = (d / "report.html").read_text()
    page = _check_self_contained(html_raw)
    assert page.tags.count("table") >= 1
    (img,) = page.images
    data = base64.b64decode(img["src"].split(",", 1)[1], validate=True)
    assert img["data-file"] == "feasibility.png" and data == (d / "feasibility.png").read_bytes()
    assert _valid_png(data)[0] > 300


def test_feasibility_report_one_parameter(maps):
    d, fmap = maps["one"]
    md = (d / "report.md").read_text()
    grid = _section(md, "The grid")
    (name, values), = fmap.grids
    for r in fmap.rows:
        cells = [c.strip() for c in next(x for x in grid.splitlines()
                                         if x.startswith(f"| {r[name]:.4g} | ")).strip("|").split("|")]
        assert cells[1] == r["verdict"] and cells[2] == ("yes" if r["feasible"] else "no")
        assert cells[3] == (f"{r['trace_bound']:.4g}" if r["feasible"] else "—") and cells[4] == r["binding"]
    why = _section(md, "How much is certified")
    assert f"**{int(fmap.certified.sum())} of {len(values)} grid points are certified.**" in why
    assert f"- {int(fmap.feasible.sum())} of {len(values)} points are feasible: " in why


def test_feasibility_report_explains_the_two_notions_in_the_module_words(maps):
    d, fmap = maps["two"]
    md = (d / "report.md").read_text()
    notions = _section(md, "Two notions of feasibility")
    module = sys.modules[type(fmap).__module__]  # the module that computes the map

    def words(s):
        return " ".join(s.replace("`", "").replace("*", "").split())

    paragraph = next(p for p in notions.split("\n\n") if p.startswith("**Two notions of feasibility.**"))
    assert words(paragraph) in words(module.__doc__)
    for phrase in ("along one simulated run", "realised DoS pattern", "transient from the prior", "stationary",
                   "expected number of received packets", "leaves the operating point", "luckier or worse",
                   "too short to reach an unbounded steady state"):
        assert phrase in words(paragraph)
    assert "Two notions of feasibility" in page_text(parse((d / "report.html").read_text()))


def test_feasibility_report_sections_and_escaping(maps, tmp_path):
    src, fmap = maps["two"]
    meta = json.loads((src / "feasibility.json").read_text())
    md = (src / "report.md").read_text()
    for title in ("Summary", "What was mapped", "Attacks", "Network", "How it was computed",
                  "Files and reproduction") + (("Assumptions",) if meta["assumptions"] else ()):
        assert f"\n## {title}\n" in md
    mapped = md_plain(_section(md, "What was mapped"))
    assert "`sigma`" in _section(md, "What was mapped") and "x0 = [1, -0.5]" in mapped
    for a in meta["assumptions"]:
        assert norm(a) in norm(md_plain(md))
    # negative control: texts from the files are shown, never interpreted
    for name in ("feasibility.csv", "feasibility.png"):
        (tmp_path / name).write_bytes((src / name).read_bytes())
    evil = "<script>alert(1)</script> <img src=x onerror=alert(2)>"
    meta["assumptions"] = [evil]
    meta["scenario"] = "<i>x</i>"
    (tmp_path / "feasibility.json").write_text(json.dumps(meta))
    write_report(tmp_path)
    raw = (tmp_path / "report.html").read_text()
    assert "<script" not in raw.lower() and "<img src=x" not in raw and "<i>" not in raw
    page = _check_self_contained(raw)
    assert evil in page_text(page) and "Feasibility report: <i>x</i>" in page_text(page)


def test_feasibility_report_from_the_csv_alone(maps, tmp_path):
    src, fmap = maps["two"]
    (tmp_path / "feasibility.csv").write_bytes((src / "feasibility.csv").read_bytes())
    write_report(tmp_path)
    md = (tmp_path / "report.md").read_text()
    assert f"**{int(fmap.certified.sum())} of {len(fmap.rows)} grid points are certified.**" in md
    assert "| sigma \\\\ beta |" in md and "feasibility.png" not in md
    _check_self_contained((tmp_path / "report.html").read_text())


@pytest.mark.slow
def test_design_report_survives_divergence_and_odd_values(designs, tmp_path):
    src, _ = designs["infeasible"]
    base = json.loads((src / "schedule.json").read_text())
    (tmp_path / "schedule.npz").write_bytes((src / "schedule.npz").read_bytes())
    diverged = {**base, "violations": [{"node": 3, "step": 2, "condition": "diverged", "margin": None,
                                        "reason": "estimate or covariance beyond 1e+08 or not finite"}]}
    for sched in (diverged, {**base, "violations": "?", "sensors": None, "network": [], "attacks": 3, "U": "x",
                             "V": [[1]], "options": None, "mode": None},
                  {"schema": "cfdesign.schedule/1"}, {**base, "trace_bound": [[None]], "nodes": "8"}):
        (tmp_path / "schedule.json").write_text(json.dumps(sched))
        html_path, md_path = write_report(tmp_path)
        _check_self_contained(html_path.read_text())
    (tmp_path / "schedule.json").write_text(json.dumps({**diverged, "feasible": False}))
    write_report(tmp_path)
    verdict = _section((tmp_path / "report.md").read_text(), "Verdict")
    assert ("The first violation: node 3 diverged at step 2 (estimate or covariance beyond 1e+08 or not finite)."
            in verdict)


# ---------------------------------------------------------------------------------------------------------------
# The summary every report opens with, and reports a reader can act on.

RING = str(Path(__file__).resolve().parents[1] / "examples" / "ring_model.py")


@pytest.fixture(scope="module")
def comparison_dir(tmp_path_factory):
    """A real comparison on a 4-node model file (the report the issue measured at 752 lines)."""
    out = tmp_path_factory.mktemp("comparison")
    api.study("comparison", RING, out=out, runs=2, particles=20, assignments=["sweep_values=[0.1, 0.3]"])
    return out


def _summary(md: str) -> str:
    head, rest = md.split("\n## Summary\n", 1)
    assert "\n## " not in head  # the summary comes first, before the contents
    summary = rest.split("\n## ", 1)[0]
    assert rest.split("\n## ", 1)[1].startswith("Contents\n")
    return summary


def _table_headers(md: str) -> list[list[str]]:
    """The header cells of every Markdown table of ``md``."""
    lines = md.splitlines()
    return [[c.strip() for c in re.split(r"(?<!\\)\|", lines[i - 1].strip())[1:-1]]
            for i in range(1, len(lines))
            if re.fullmatch(r"\|(\s*-{3,}:?\s*\|)+", lines[i].strip()) and lines[i - 1].startswith("|")]


def _ranked_rows(summary: str) -> list[list[str]]:
    rows = [r for r in summary.splitlines() if re.match(r"\| (\d+|—) \| ", r)]
    return [[c.strip() for c in re.split(r"(?<!\\)\|", r.strip())[1:-1]] for r in rows]


def _lead_number(cell: str) -> float:
    return float(cell.split(" [", 1)[0])


@pytest.mark.parametrize("which", ["encrypted-switching", "consensus-robot", "comparison"])
@pytest.mark.slow
def test_a_study_report_opens_with_the_ranking_the_figure_and_the_pick(which, studies, comparison_dir):
    d = comparison_dir if which == "comparison" else studies(which)
    results = json.loads((d / "results.json").read_text())
    md = (d / "report.md").read_text()
    summary = _summary(md)
    assert len([ln for ln in summary.splitlines() if ln.strip()]) <= 30  # one screen
    assert ["rank", "filter"] == _table_headers(summary)[0][:2]
    rows = _ranked_rows(summary)
    blocks = results.get("by_scenario") or {"": results}
    assert len(rows) == sum(len(b["filters"]) for b in blocks.values())
    text = study_text(results["study"])
    key = next(k for k, _ in text.accuracy if any(k in f for b in blocks.values() for f in b["filters"].values()))
    value = lambda m: m[key][0] if isinstance(m[key], list) else m[key]  # noqa: E731

    def reference(name: str, m: dict) -> bool:  # never the pick: a benchmark, a global oracle, a fusion centre
        return name in text.references or m.get("runtime") in ("global", "centralized")

    for b in blocks.values():
        f = b["filters"]
        names = [r[1] for r in rows if r[1] in f]
        # the options ranked from the lowest, then the references apart, from the lowest
        assert [reference(n, f[n]) for n in names] == sorted(reference(n, f[n]) for n in names)
        for refs in (False, True):
            values = [value(f[n]) for n in names if f[n][key] is not None and reference(n, f[n]) == refs]
            assert values == sorted(values)
        for r in rows:
            if r[1] in f and f[r[1]].get(f"{key}_ci95") is not None:
                assert re.search(r"\[[-\d.e]+, [-\d.e]+\]", r[2]), r  # the value with its interval
    if which != "encrypted-switching":  # consensus studies record what each filter needs at run time
        assert {f["runtime"] for b in blocks.values() for f in b["filters"].values()} >= {"local", "centralized"}
    if which == "comparison":  # the mse design is a global oracle, the centralized filters a fusion centre's
        assert all(b["filters"]["consensus EKF (mse design)"]["runtime"] == "global" for b in blocks.values())
        assert all(f["runtime"] == "centralized" for b in blocks.values() for n, f in b["filters"].items()
                   if n.startswith("centralized"))
    assert "](fig_tradeoff.png)" in summary and (d / "fig_tradeoff.png").is_file()
    picks = [ln for ln in summary.splitlines() if ln.startswith("**Which to pick")]
    assert len(picks) == len(blocks)
    for pick, b in zip(picks, blocks.values()):
        cand = {n: m for n, m in b["filters"].items() if not reference(n, m) and m[key] is not None}
        best = min(cand, key=lambda n: value(cand[n]))
        picked, _, beside = pick.partition("; for reference, ")
        assert best in picked
        assert not any(reference(n, m) and n in picked for n, m in b["filters"].items())
        refs = {n: m for n, m in b["filters"].items() if reference(n, m) and m[key] is not None}
        if refs:  # the best reference beside the pick, as what the structure could reach
            assert beside.startswith(min(refs, key=lambda n: value(refs[n])))
        assert pick.count(".") >= 1 and "\n" not in pick
    page = parse((d / "report.html").read_text())
    assert page.errors == [] and "Which to pick" in page_text(page)


def _pick(results: dict) -> str:
    return next(ln for ln in render_markdown(results).splitlines() if ln.startswith("**Which to pick"))


def test_the_pick_is_never_stronger_than_the_intervals():
    r = _results()  # fast [0.9, 1.1] and close [0.95, 1.2] overlap; far [2.5, 3.5] is apart
    pick = _pick(r)
    assert "the data cannot tell fast and close apart on position RMSE" in pick and "far" not in pick
    assert "costs" not in pick and "among them fast sends the fewest messages (8)" in pick
    r["filters"]["close"].update(rmse_position=1.2, rmse_position_ci95=[1.15, 1.3])
    pick = _pick(r)
    assert pick.startswith("**Which to pick:** fast: the lowest position RMSE (1 [0.9, 1.1]), its 95 % interval "
                           "apart from every other filter's") and "rough" not in pick
    assert "(from only 4 runs, whose intervals are rough)." in _pick({**r, "runs": 4})
    for m in r["filters"].values():
        m.pop("rmse_position_ci95")
    assert ("fast has the lowest position RMSE (1), but no 95 % interval was recorded, so the data cannot say "
            "whether it is better than close (1.2)") in _pick(r)
    one = _results(runs=1)  # one run: zero-width "intervals" say nothing
    for m in one["filters"].values():
        m["rmse_position_ci95"] = [m["rmse_position"]] * 2
    assert "apart" not in _pick(one) and "cannot say" in _pick(one)
    gone = _results()
    for m in gone["filters"].values():
        m.update(rmse_position=None, rmse_position_ci95=None)
    assert "none can be named" in _pick(gone)


def test_a_benchmark_is_ranked_but_never_picked():
    r = _results(study="rrp-deception")
    r["filters"]["RRP-SPF-NM"] = {"rmse_position": 0.1, "rmse_position_ci95": [0.05, 0.15], "time_per_step_s": 1e-6}
    md = render_markdown(r)
    picked, _, beside = _pick(r).partition("; for reference, ")
    assert "RRP-SPF-NM" not in picked and "fast" in picked
    assert beside.startswith("RRP-SPF-NM reaches 0.1 [0.05, 0.15] (a benchmark")
    row = next(x for x in _ranked_rows(_summary(md)) if x[1] == "RRP-SPF-NM")
    assert row[0] == "—" and row[3] == "benchmark"


def test_an_oracle_or_a_fusion_centre_is_shown_apart_and_never_picked():
    """The comparison where the global oracle (mse) and a centralized filter are the most accurate: the summary ranks
    the filters the nodes can run, shows the references in a table of their own after them, and picks the best of the
    deployable ones, naming the best reference beside it as what the structure could reach."""
    from studies.comparison import _recommend  # the recommendation results.json records

    r = _results()
    f = r["filters"]
    for m in f.values():
        m["runtime"] = "local"
    f["consensus EKF (mse design)"] = {"rmse_position": 0.5, "rmse_position_ci95": [0.45, 0.55],
                                       "time_per_step_s": 1e-3, "communications": 20, "runtime": "global"}
    f["centralized EKF"] = {"rmse_position": 0.7, "rmse_position_ci95": [0.65, 0.75], "time_per_step_s": 1e-5,
                            "communications": 4, "runtime": "centralized"}
    md = render_markdown(r)
    summary = _summary(md)
    options, refs = summary.split("**References**", 1)
    assert [x[1] for x in _ranked_rows(options)] == ["fast", "close", "far"]
    assert [x[:2] for x in _ranked_rows(options)] == [["1", "fast"], ["2", "close"], ["3", "far"]]
    rows = _ranked_rows(refs)
    assert [(x[0], x[1], x[3]) for x in rows] == [("—", "consensus EKF (mse design)", "reference"),
                                                 ("—", "centralized EKF", "reference")]
    assert "oracle" in rows[0][-1] and "fusion centre" in rows[1][-1]
    pick = _pick(r)
    picked, _, beside = pick.partition("; for reference, ")
    assert picked.startswith("**Which to pick:** the data cannot tell fast and close apart")
    assert "mse" not in picked and "centralized" not in picked
    assert beside.startswith("consensus EKF (mse design) reaches 0.5 [0.45, 0.55] (a global oracle: what the "
                             "structure could reach")
    metric_by_metric = md.split("## Which filter to pick", 1)[1].split("\n## ", 1)[0]
    assert "**Most accurate (position RMSE):** fast" in metric_by_metric
    # the comparison's own recommendation (results.json) and table: the same pick, the oracle as the best reference
    rows = {n: {"rmse": m["rmse_position"], "rmse_ci95": m["rmse_position_ci95"], "time_per_step_s":
                m["time_per_step_s"], "messages_per_step": m["communications"], "runtime": m["runtime"]}
            for n, m in f.items()}
    rec = _recommend(rows, "rmse")
    assert rec["most_accurate"] == "fast" and rec["best_reference"] == "consensus EKF (mse design)"
    assert rec["not_significantly_worse"] == ["close"] and rec["cheapest"] == "fast"


@pytest.mark.parametrize("check, word", [({"verdict": "violated", "fraction_exceeding": 0.0,
                                           "verdict_reason": "the runs' error is 35 times their bound's"}, "violated"),
                                         ({"fraction_exceeding": 0.25, "pairs_checked": 8, "pairs_total": 40},
                                          "exceeded"),
                                         ({"fraction_exceeding": 0.0, "pairs_checked": 8, "pairs_total": 40}, "holds")])
def test_the_bound_check_verdict_reaches_the_summary(check, word):
    """The study's own verdict where it records one (a bound exceeded on average is violated even when no
    single pair's exceedance is significant), else the share of pairs exceeding."""
    r = _results()
    r["filters"]["far"]["bound_check"] = {"runs": 40, **check}
    md = render_markdown(r)
    row = next(x for x in _ranked_rows(_summary(md)) if x[1] == "far")
    assert f"bound {word}" in row[-1]
    details = md.split("### Does the bound hold?", 1)[1]
    assert f"| far | {word} |" in details
    assert ("the runs' error is 35 times their bound's" in details) == ("verdict_reason" in check)
    caution = next(ln for ln in md.splitlines() if ln.startswith("- **Caution:**")) if word != "holds" else ""
    assert (word in caution) == (word != "holds")


def test_raw_fields_stay_in_results_json(comparison_dir, studies):
    """No section dumps fields the report does not explain: they are named once, their values left to the file."""
    r = _results(runner={"backend": "batched", "chunks": 3}, extra={"deep": [{"a": 123456}], "nums": [7] * 50})
    md = render_markdown(r)
    assert "Other recorded" not in md and "123456" not in md and "batched" not in md
    assert "`results.json` also records `runner`, `extra` (not shown here)." in md
    for d in (comparison_dir, studies("consensus-robot")):
        md = (d / "report.md").read_text()
        assert "Other recorded" not in md and "{oscillator:" not in md and "values (" not in md
        assert len(md.splitlines()) < 320, len(md.splitlines())


def test_figure_captions_are_sentences_the_studies_wrote(comparison_dir, studies):
    from studies.reports.study import figure_caption

    for d in (comparison_dir, studies("consensus-robot"), studies("encrypted-switching")):
        md = (d / "report.md").read_text()
        captions = dict((f, c) for c, f in re.findall(r"^\*\*Figure \d+\.\*\* (.+) \(`([^`]+)`\)$", md, flags=re.M))
        assert set(captions) == {p.name for p in d.glob("*.png")}
        for name, caption in captions.items():
            stem = Path(name).stem.removeprefix("fig_").replace("_", " ")
            assert caption[0].isupper() and caption.endswith(".") and len(caption.split()) >= 6, caption
            assert stem.capitalize() not in caption and "no caption" not in caption, caption
    assert "recorded no caption" in figure_caption("fig_new.png", study_text("comparison"))


def test_no_empty_paper_section():
    r = _results(paper={"source": None, "numbers": None, "note": "no paper compares these"})
    md = render_markdown(r)
    assert "numbers" not in md.split("### What the paper reports", 1)[1].split("\n## ", 1)[0]
    assert "Note: no paper compares these" in md
    assert "What the paper reports" not in render_markdown(_results(paper={"source": None, "numbers": None}))


def test_every_table_labels_its_first_column_and_the_sweeps_appear_once(comparison_dir, studies, designs, maps):
    docs = [(d / name).read_text() for d in (comparison_dir, studies("consensus-robot"), studies("encrypted-switching"))
            for name in ("report.md", "table.md")]
    docs += [(d / "report.md").read_text() for d, _ in (*designs.values(), *maps.values())]
    docs.append(render_markdown(_results()))
    for md in docs:
        headers = _table_headers(md)
        assert headers and all(h[0] for h in headers), [h for h in headers if not h[0]]
    table = "# T\n\n| setting | RMSE |\n|---|---:|\n| dos_prob = 0.1 | 1 |\n"
    assert "## Sweeps" not in render_markdown(_results(), table)  # the study's own tables show its sweeps
    assert render_markdown(_results()).count("### dos_prob") == 1
    sweeps = (comparison_dir / "report.md").read_text()
    assert sweeps.count("against the DoS probability") == 1 and "## Sweeps" not in sweeps


def test_design_and_map_reports_open_with_a_summary(designs, maps):
    for d, res in designs.values():
        md = (d / "report.md").read_text()
        summary = _summary(md)
        assert _table_headers(summary)[0][:2] == ["rank", "node"]
        assert "](fig_trace_bound.png)" in summary
        assert ("**Use this schedule?** Yes, along this run" if res.feasible else
                "**Use this schedule?** No: the design is infeasible along this run") in summary
        assert "### gate" not in md and "Other recorded" not in md
        sched = json.loads((d / "schedule.json").read_text())
        if any(v["condition"] == "theorem2" for v in sched["violations"]):
            k, n = sched["steps"], sched["nodes"]
            assert (f"({k + 1} per node, {n * (k + 1)} node-steps for {n} nodes), conditions (28)-(29) once per "
                    f"recursion step k → k + 1 ({k} per node, {n * k} node-steps)") in md
    for d, fmap in maps.values():
        summary = _summary((d / "report.md").read_text())
        assert "**Where the design is certified:**" in summary
        ok = sorted(r["trace_bound"] for r in fmap.rows if r["verdict"] == "certified")
        rows = [x for x in summary.splitlines() if re.match(r"\| \d+ \| ", x)]
        assert len(rows) == min(len(ok), 6) and (not ok or f"{ok[0]:.4g}" in rows[0])
        if len(fmap.grids) <= 2:
            assert "](feasibility.png)" in summary


def test_the_report_again_retires_a_figure_it_no_longer_draws_and_keeps_the_rest(tmp_path):
    """``cfdesign report`` on an older design directory: a figure the design report drew then (an empty margins
    figure of a relay design, whose bound has no (28)-(29)) and no longer draws is removed with the new report; the
    results, the figures it draws and a user's own file stay."""
    import studies
    from designer.fileio import OUTPUTS_NAME

    d = tmp_path / "relay"
    studies.design("indoor-robot", mode="relay", out=d)
    assert (d / "fig_trace_bound.png").is_file() and not (d / "fig_margins.png").exists()
    (d / "fig_margins.png").write_bytes(b"\x89PNG an older version's")  # as an older version left it, listed
    listed = json.loads((d / OUTPUTS_NAME).read_text())
    (d / OUTPUTS_NAME).write_text(json.dumps({"files": sorted(listed["files"] + ["fig_margins.png"])}))
    (d / "notes.txt").write_text("mine")
    npz = (d / "schedule.npz").read_bytes()
    studies.report(d)
    assert not (d / "fig_margins.png").exists()
    assert "fig_margins.png" not in json.loads((d / OUTPUTS_NAME).read_text())["files"]
    assert (d / "fig_trace_bound.png").is_file() and (d / "report.html").is_file()
    assert (d / "schedule.npz").read_bytes() == npz and (d / "notes.txt").read_text() == "mine"
    p = tmp_path / "paper"  # a report that draws its margins keeps them
    studies.design("indoor-robot", mode="paper", out=p)
    studies.report(p)
    assert (p / "fig_margins.png").is_file() and "fig_margins.png" in json.loads((p / OUTPUTS_NAME).read_text())["files"]
