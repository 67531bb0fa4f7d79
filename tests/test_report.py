"""Study reports (``report.md``, self-contained ``report.html``): content, inlined figures, escaping, robustness.

Two real studies run at a tiny size (the particle-filter study ``encrypted-switching``,
which writes its report through :func:`studies.results.write_study`, and
``consensus-robot``, which has no ``table.md`` and no intervals); the other cases use
small hand-written results files.
"""
from __future__ import annotations

import base64
import copy
import json
import re
from html.parser import HTMLParser
from pathlib import Path

import pytest

from designer.validation import InputError
from studies.consensus_robot import run_consensus_robot
from studies.encrypted_switching import run_encrypted_switching
from studies.report import markdown_to_html, render_markdown, write_report

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


@pytest.fixture(scope="module")
def studies(tmp_path_factory):
    enc = tmp_path_factory.mktemp("enc")
    run_encrypted_switching(out=enc, runs=3, particles=30, quiet=True)
    con = tmp_path_factory.mktemp("con")
    run_consensus_robot(out=con, runs=2, quiet=True)
    return {"encrypted-switching": enc, "consensus-robot": con}


@pytest.fixture(params=["encrypted-switching", "consensus-robot"])
def study_dir(request, studies) -> Path:
    return studies[request.param]


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
    f = results["filters"]
    if results["study"] == "consensus-robot":
        best = min(f, key=lambda n: f[n]["rmse_position"])
        assert f"**Most accurate (position RMSE over all nodes):** {best}," in pick
        assert "No confidence interval was recorded" in pick
        fewest = min(v["communications"] for v in f.values())
        assert f"**Fewest communications:** " in pick and f"({fewest} messages" in pick
    else:
        for i in range(2):
            best = min(f, key=lambda n: f[n]["rmse_state"][i])
            assert f"**Most accurate (RMSE of x{i + 1}):** {best}," in pick
    cheapest = min(f, key=lambda n: f[n]["time_per_step_s"])
    assert f"**Cheapest per step:** {cheapest}," in pick


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
    assert "far" not in pick.split("Cheapest")[0]  # [2.5, 3.5] is apart: not named as a tie
    assert "**Cheapest per step:** fast, 10 µs" in pick
    assert "**Fewest communications:** fast, far (8 messages)" in pick
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
    import studies.report as report

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
    with pytest.raises(InputError, match="directory .* has no results.json"):
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


def test_markdown_converter_subset():
    md = ("# Title *x*\n\nA paragraph with `a<b` and **bold \\*star\\***.\n\n- one\n  - one.a\n  - one.b\n"
          "- two\n\n| | left | right |\n|---|---|---:|\n| r1 | a \\| b | 1 |\n| r2 | c |\n\n"
          "![A figure](fig_a.png)\n**Figure 1.** caption\n\nSee [the title](#title-x).\n")
    raw = markdown_to_html(md, {"fig_a.png": PNG_1x1}, title="t<")
    page = parse(raw)
    assert page.errors == [] and page.stack == []
    assert '<h1 id="title-x">Title *x*</h1>' in raw
    assert "<code>a&lt;b</code>" in raw and "<strong>bold *star*</strong>" in raw
    assert "<ul><li>one<ul><li>one.a</li><li>one.b</li></ul></li><li>two</li></ul>" in raw
    assert '<td>a | b</td><td class="right">1</td>' in raw
    assert "<td>r2</td><td>c</td><td class=\"right\"></td>" in raw  # short rows are padded
    assert 'width="1" height="1"' in raw and "<figcaption><strong>Figure 1.</strong> caption</figcaption>" in raw
    assert '<a href="#title-x">the title</a>' in raw
    assert "<title>t&lt;</title>" in raw
    missing = markdown_to_html("![gone](gone.png)\n")
    assert "<img" not in missing and "gone.png" in missing


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
    assert "**Cheapest per step:** ok" in target and "cheap-but-diverged" not in target.split("Caution")[0]
    scen = md.split("## Scenarios and parameters", 1)[1].split("\n## ", 1)[0]
    assert "`glint_prob`" in scen.split("### target-range-bearing", 1)[1]
    assert "`meas_var`" in scen.split("### indoor-robot", 1)[1].split("### target-range-bearing", 1)[0]
