"""The test run's progress line (``tests/progress_line.py``): pytest in a subprocess on a tiny generated test file."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from progress_line import elapsed_text

TESTS = Path(__file__).resolve().parent
TINY = '''
import time
import pytest

def test_passes():
    pass

@pytest.mark.skip(reason="skipped at setup")
def test_skipped():
    pass

def test_fails():
    assert False

def test_sleeps():
    time.sleep({sleep})
'''
LINE = re.compile(r"^\[progress\] (\d+)/(\d+) tests done, (\d+) failed, (?:\d+ min )?\d+ s$")


def run_pytest(tmp_path, *args, sleep=2.0, env=None):
    """pytest on the tiny file with the progress plugin: the finished process (its output as text)."""
    (tmp_path / "test_tiny.py").write_text(TINY.format(sleep=sleep))
    environ = {k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_", "CFDESIGN_TEST_PROGRESS"))}
    environ["PYTHONPATH"] = os.pathsep.join([str(TESTS)] + [p for p in [os.environ.get("PYTHONPATH")] if p])
    environ.update(env or {})
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "progress_line",
                           *args, "test_tiny.py"], cwd=tmp_path, env=environ, capture_output=True, text=True,
                          timeout=120)


@pytest.mark.parametrize("workers", [[], ["-n", "2"]], ids=["one process", "xdist"])
def test_progress_line_counts_tests_done_and_failed_while_a_long_test_runs(tmp_path, workers):
    proc = run_pytest(tmp_path, "--progress-interval", "0.3", *workers)
    out = proc.stdout
    assert proc.returncode == 1, out
    counts = [tuple(int(g) for g in m.groups()) for m in map(LINE.match, out.splitlines()) if m]
    # three of the four are done (one failed, one skipped at setup) while the sleeping test runs
    assert (3, 4, 1) in counts, out
    assert all(total == 4 and failed <= done <= 4 for done, total, failed in counts), out
    assert counts == sorted(counts), out  # the counts never go back
    # pytest's summary stays the last line
    assert re.search(r"1 failed, 2 passed, 1 skipped in [\d.]+s", out.strip().splitlines()[-1]), out


def test_progress_line_is_off_with_the_environment_variable_at_0(tmp_path):
    out = run_pytest(tmp_path, sleep=1.0, env={"CFDESIGN_TEST_PROGRESS": "0"}).stdout
    assert "1 failed, 2 passed, 1 skipped" in out and "[progress]" not in out, out
    out = run_pytest(tmp_path, "--progress-interval", "0.2", sleep=1.0, env={"CFDESIGN_TEST_PROGRESS": "0"}).stdout
    assert "[progress] 3/4 tests done, 1 failed" in out, out  # the option wins


def test_a_bad_interval_is_a_usage_error_naming_the_option(tmp_path):
    proc = run_pytest(tmp_path, "--progress-interval", "-1", sleep=0)
    assert proc.returncode == pytest.ExitCode.USAGE_ERROR, proc.stdout + proc.stderr
    assert "--progress-interval must be a number of seconds in [0, 86400]" in proc.stderr and "'-1'" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_elapsed_time_reads_minutes_and_seconds():
    assert elapsed_text(35.9) == "35 s"
    assert elapsed_text(4 * 60 + 10.2) == "4 min 10 s"
    assert LINE.match(f"[progress] 812/1704 tests done, 0 failed, {elapsed_text(250)}")
