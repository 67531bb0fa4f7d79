"""The same command writes the same report: no sentence depends on a measured time.

The comparison study is run twice on a tiny model with the clock replaced (two fake clocks that make different filters
look fastest); the two ``report.md`` and ``table.md`` must be identical once every measured duration (what
:func:`studies.reports.text.fmt_dur` writes, :data:`studies.reports.text.DURATION`) is masked, and every line that
shows a duration must say it is a measurement.
"""
from __future__ import annotations

import json
import time

import numpy as np
from conftest import scalar_spec_model

from studies.cli import main
from studies.reports.text import DURATION, MEASURED

SCALAR = scalar_spec_model()


def _fake_clock(seed: int):
    """A clock whose every reading advances by a random amount from its own stream: a different ranking of the
    filters' times for each seed."""
    rng = np.random.default_rng(seed)
    now = [1000.0]

    def perf_counter() -> float:
        now[0] += float(rng.exponential(1e-3 * (1 + 10 * seed)))
        return now[0]

    return perf_counter


def _study(tmp_path, monkeypatch, name: str, seed: int) -> tuple[str, str, dict]:
    monkeypatch.setattr(time, "perf_counter", _fake_clock(seed))
    out = tmp_path / name
    assert main(["study", "comparison", "--scenario", str(tmp_path / "scalar.py"), "--runs", "2", "--particles", "10",
                 "--seed", "3", "--workers", "1", "--set", "sweep_values=[0.1]", "--set", "tuned_in_sweeps=false",
                 "--set", "hcmci_iterations=1", "--quiet", "--out", str(out)]) == 0
    monkeypatch.undo()
    return ((out / "report.md").read_text(), (out / "table.md").read_text(),
            json.loads((out / "results.json").read_text()))


def _masked(text: str) -> str:
    return DURATION.sub("<measured>", text)


def test_a_comparison_report_is_the_same_whatever_the_clock_says(tmp_path, monkeypatch):
    (tmp_path / "scalar.py").write_text(SCALAR)
    a_md, a_table, a = _study(tmp_path, monkeypatch, "a", 0)
    b_md, b_table, b = _study(tmp_path, monkeypatch, "b", 1)
    times = [{n: f["time_per_step_s"] for n, f in r["filters"].items()} for r in (a, b)]
    assert times[0] != times[1]  # the clocks did differ ...
    order = [sorted(t, key=t.get) for t in times]
    assert order[0][0] != order[1][0]  # ... enough to change which filter looks fastest
    assert a["filters"].keys() == b["filters"].keys()
    for n in a["filters"]:  # and nothing else: the estimates are the same numbers
        assert a["filters"][n].get("rmse") == b["filters"][n].get("rmse"), n
    assert _masked(a_md) == _masked(b_md)
    assert _masked(a_table) == _masked(b_table)
    for md in (a_md, a_table):  # every duration stands in a line, or a table, that says it is a measurement
        lines = md.splitlines()
        for i, line in enumerate(lines):
            if DURATION.search(line):
                start = i
                while start > 0 and lines[start].startswith("|") and lines[start - 1].startswith("|"):
                    start -= 1  # a table row: its header says it
                heading = next((x for x in reversed(lines[:i + 1]) if x.startswith("#")), "")
                assert ("measured" in line or "measured" in lines[start] or "Timings" in heading
                        or "wall-clock" in line), line
    for word in ("cheapest", "fastest", "costs least"):
        assert word not in a_md.lower() and word not in a_table.lower(), word
    assert MEASURED in a_md


def _paragraphs(text: str) -> list[str]:
    return [p for p in text.split("\n\n") if p.strip()]


def test_theorem_2_is_never_printed_beside_a_verdict_without_why_both_hold(tmp_path, capsys):
    """A design certified along its run while Theorem 2's condition fails at some node-steps: every line of the
    command and every paragraph of the report that names Theorem 2's failure says why it does not contradict the
    verdict (Theorem 1's bound over the horizon against Theorem 2's boundedness for all time)."""
    (tmp_path / "scalar.py").write_text(SCALAR)
    out = tmp_path / "d"
    assert main(["design", str(tmp_path / "scalar.py"), "--mode", "paper", "--steps", "16", "--out", str(out)]) == 0
    meta = json.loads((out / "schedule.json").read_text())
    assert meta["verdict"] == "certified"
    assert any(v["condition"] == "theorem2" for v in meta["violations"])  # the case the wording is for
    stdout = capsys.readouterr().out
    said = [ln for ln in stdout.splitlines() if "Theorem 2" in ln]
    said += [p for p in _paragraphs((out / "report.md").read_text()) if "Theorem 2" in p]
    assert len(said) >= 3  # the command's line, the verdict's paragraph, the summary's sentence
    for text in said:
        assert "Theorem 1" in text and "does not contradict" in text, text
        assert "for all time" in text, text
        assert "not certified" not in text, text
    assert "does not contradict the verdict (certified)" in said[0]
