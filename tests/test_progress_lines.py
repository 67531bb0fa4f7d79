"""Progress lines (designer.progress): a long command says what it is doing on stderr, in a pipe too; --quiet, a
library call and a forked worker say nothing."""
from __future__ import annotations

import os
import re
import time

import numpy as np
import pytest

from designer import progress
from studies.cli import main

LINE = re.compile(r"^cfdesign: (.+) \((\d+) s\)$")


def _lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if LINE.match(ln)]


@pytest.fixture
def eager(monkeypatch):
    """A line whenever one is asked for (the command's first after 0 s, then none skipped)."""
    monkeypatch.setattr(progress, "FIRST_S", 0.0)
    monkeypatch.setattr(progress, "EVERY_S", 0.0)


def test_a_design_names_its_phase_and_step_on_stderr(tmp_path, capsys, eager):
    assert main(["design", "examples/ring_model.py", "--mode", "scheduled", "--steps", "6",
                 "--out", str(tmp_path / "d")]) in (0, 1)
    err = capsys.readouterr().err
    lines = _lines(err)
    assert any(ln.startswith("cfdesign: gain tables: step ") for ln in lines), err
    steps = [ln for ln in lines if ln.startswith("cfdesign: seeded run: step ")]
    assert [ln.split("step ")[1].split(" ")[0].rstrip(",") for ln in steps] == [f"{k}/6" for k in range(6)]
    assert any(ln.startswith("cfdesign: writing the schedule") for ln in lines)
    assert any(ln.startswith("cfdesign: writing the report") for ln in lines)
    seconds = [int(LINE.match(ln).group(2)) for ln in lines]
    assert seconds == sorted(seconds)


def test_lines_are_at_most_every_few_seconds_and_none_in_the_first(monkeypatch, capsys):
    clock = iter([100.0, 101.0, 104.9, 105.0, 110.0, 114.0, 115.5])
    monkeypatch.setattr(progress.time, "perf_counter", lambda: next(clock))
    with progress.showing():  # started at 100
        for k in range(6):  # asked at 101, 104.9, 105 (first), 110 (too soon), 114 (too soon), 115.5 (10.5 s later)
            progress.line(f"step {k}/6")
    err = capsys.readouterr().err.splitlines()
    assert err == ["cfdesign: step 2/6 (5 s)", "cfdesign: step 5/6 (16 s)"]


def test_a_count_says_the_time_left_at_its_rate_since_its_first_line(monkeypatch, capsys):
    """A count (``line(what, k, total)``: a design's steps, a study's chunks) says, once it has advanced since its
    first line, the time left at its rate since then: 4 steps in 20 s, 6 to go: about 30 s; in minutes or hours when
    longer.  Its first line has none (no rate yet), nor its last, nor a line without a count; the seconds since the
    command started stay last."""
    clock = iter([100.0, 105.0, 125.0, 140.0, 140.0, 400.0, 401.0])
    monkeypatch.setattr(progress.time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(progress, "EVERY_S", 0.0)
    with progress.showing():  # started at 100
        progress.line("step", 2, 12)  # 105: the count's first line
        progress.line("step", 6, 12)  # 125: 4 steps in 20 s
        progress.line("step", 12, 12)  # 140: done
        progress.line("writing")  # 140: no count
        with progress.phase("tables"):  # 400: another count: its own first line, then 300 s a step for 1 step
            progress.line("step", 1, 40)
    err = capsys.readouterr().err.splitlines()
    assert err[:4] == ["cfdesign: step 2/12 (5 s)", "cfdesign: step 6/12, about 30 s left (25 s)",
                       "cfdesign: step 12/12 (40 s)", "cfdesign: writing (40 s)"], err
    assert err[4:] == ["cfdesign: tables (300 s)", "cfdesign: tables: step 1/40 (301 s)"], err
    assert all(LINE.match(ln) for ln in err), err
    clock = iter([0.0, 10.0, 3610.0])
    monkeypatch.setattr(progress.time, "perf_counter", lambda: next(clock))
    with progress.showing():
        progress.line("step", 1, 60)
        progress.line("step", 2, 60)  # an hour a step, 58 to go
    assert capsys.readouterr().err.splitlines()[-1] == "cfdesign: step 2/60, about 58.0 h left (3610 s)"


def test_the_time_left_shrinks_while_an_item_is_under_way(monkeypatch, capsys):
    """Between two advances of a count the time left counts down from the last advance (the validation's last chunk
    on a 118-bus grid had said 25, 30, 35 s left while it ran); once spent, the time left is unknown (not "about 0 s",
    a minute long); an advance not written (no line due) still sets the rate and the time it is counted from."""
    clock = iter([100.0, 105.0, 125.0, 135.0, 170.0, 180.0, 190.0])
    monkeypatch.setattr(progress.time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(progress, "EVERY_S", 0.0)
    with progress.showing():  # started at 100
        progress.line("chunk", 0, 4)  # 105: the count's first line
        progress.line("chunk", 2, 4)  # 125: 2 in 20 s, 2 to go: 20 s
        progress.line("chunk", 2, 4)  # 135: 10 s of them spent
        progress.line("chunk", 2, 4)  # 170: overdue
        monkeypatch.setattr(progress, "EVERY_S", 100.0)
        progress.line("chunk", 3, 4)  # 180: no line due, but the advance is noted: 3 in 75 s
        monkeypatch.setattr(progress, "EVERY_S", 0.0)
        progress.line("chunk", 3, 4)  # 190: 25 s for the last, 10 s spent
    err = capsys.readouterr().err.splitlines()
    assert err == ["cfdesign: chunk 0/4 (5 s)", "cfdesign: chunk 2/4, about 20 s left (25 s)",
                   "cfdesign: chunk 2/4, about 10 s left (35 s)", "cfdesign: chunk 2/4, slower than so far: time left unknown (70 s)",
                   "cfdesign: chunk 3/4, about 15 s left (90 s)"], err


def test_quiet_library_and_forked_worker_write_nothing(tmp_path, capsys, eager, monkeypatch):
    assert main(["feasibility", "examples/ring_model.py", "--grid", "dos=0:0.2:2", "--quiet",
                 "--out", str(tmp_path / "f")]) == 0
    assert _lines(capsys.readouterr().err) == []
    progress.line("step 1/2")  # a library call: no sink installed
    assert capsys.readouterr().err == ""
    with progress.showing():
        pid = os.getpid()
        monkeypatch.setattr(progress.os, "getpid", lambda: pid + 1)  # as in a process forked from this one
        progress.line("step 1/2")
    assert capsys.readouterr().err == ""


def _slow_task(run_ids, seeds):
    time.sleep(1.5)
    return {"x": np.asarray(run_ids, dtype=float)}


def test_the_parent_says_where_its_worker_processes_are_while_they_compute(capsys, eager, monkeypatch):
    """Chunks computed by forked workers: the parent's line while none has finished yet, and none with quiet."""
    from studies.runner import Backend, monte_carlo

    monkeypatch.setattr("designer.cores.usable_cores", lambda: 2)
    with progress.showing():
        out = monte_carlo(_slow_task, runs=2, seed=0, chunk_size=1, backend=Backend("processes", workers=2),
                          label="slow")
    assert out.arrays["x"].tolist() == [0.0, 1.0]
    lines = _lines(capsys.readouterr().err)
    assert any(re.match(r"^cfdesign: .*\b0/2 \(\d+ s\)$", ln) for ln in lines), lines
    with progress.showing():
        monte_carlo(_slow_task, runs=2, seed=0, chunk_size=1, backend=Backend("processes", workers=2), label="slow",
                    quiet=True)
    assert _lines(capsys.readouterr().err) == []


def test_a_designs_validation_says_it_is_the_validation(tmp_path, capsys, eager):
    """The Monte Carlo runs of --validate are the consensus-robot study on the user's model: its lines name the
    validation first, so that a user designing a field is not told about a robot."""
    assert main(["design", "examples/ring_model.py", "--mode", "relay", "--steps", "6", "--validate", "2",
                 "--out", str(tmp_path / "d")]) in (0, 1)
    lines = _lines(capsys.readouterr().err)
    runs = [ln for ln in lines if re.search(r"\d+ chunks(, each in \d+ shares)?\)", ln)]  # the runner's lines
    assert runs and all(ln.startswith("cfdesign: validation, 2 fresh runs: ") for ln in runs), lines
    assert not any("robot" in ln for ln in lines), lines


def test_a_feasibility_map_counts_grid_points_not_monte_carlo_runs(tmp_path, capsys, eager):
    """A map's chunks are of grid points: its lines say so (they had said 'Monte Carlo runs')."""
    assert main(["feasibility", "examples/ring_model.py", "--grid", "dos=0:0.2:3", "--mode", "relay",
                 "--workers", "1", "--out", str(tmp_path / "m")]) == 0
    lines = _lines(capsys.readouterr().err)
    assert any("grid points (" in ln for ln in lines), lines
    assert not any("Monte Carlo" in ln for ln in lines), lines
