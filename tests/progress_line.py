"""A progress line during the test run: how many tests are done out of how many, the failures so far and the time.

Every ``--progress-interval`` seconds (20 by default) the controlling process prints one line such as
``[progress] 812/1704 tests done, 0 failed, 4 min 10 s``, from a timer thread, so the line comes also while one long
test runs.  With pytest-xdist (``-n 2``) that process is the controller, which receives every worker's reports; without
it, the process that runs the tests.  A test is done when its call phase is reported, or its setup when that did not
pass (skipped or an error); a test is failed when any of its phases failed.

The line goes to the terminal the session started on (a copy of its standard output taken before any test runs, so
that a test's output capture never swallows it), beginning on a fresh line; when pytest continues its partial line
of dots, the fresh line is first padded back to that width, so pytest's own columns stay aligned.  The timer stops
when the tests end, before pytest's summary: the summary line stays the last line.  ``--progress-interval 0`` or
``CFDESIGN_TEST_PROGRESS=0`` turns it off; ``CFDESIGN_TEST_PROGRESS=SECONDS`` sets the interval (the option wins).

Loaded by ``tests/conftest.py``; any other run loads it with ``-p progress_line`` (``tests/`` on the path).
"""
from __future__ import annotations

import os
import sys
import threading
import time

import pytest

ENV = "CFDESIGN_TEST_PROGRESS"
DEFAULT_INTERVAL = 20.0
_OFF = {"0", "off", "no", "false"}


def interval_seconds(text: str, name: str) -> float:
    """The interval ``text`` (from the option or environment variable ``name``) in seconds; 0 (or off) is off."""
    if text.strip().lower() in _OFF:
        return 0.0
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0.0 <= value <= 86400.0:
        raise pytest.UsageError(f"{name} must be a number of seconds in [0, 86400] (0 turns the progress line off), "
                                f"got {text!r}")
    return value


def elapsed_text(seconds: float) -> str:
    """``4 min 10 s`` (``35 s`` under a minute)."""
    whole = int(seconds)
    return f"{whole // 60} min {whole % 60} s" if whole >= 60 else f"{whole} s"


def pytest_addoption(parser):
    parser.addoption("--progress-interval", default=None, metavar="SECONDS",
                     help=f"print a progress line every SECONDS (default {DEFAULT_INTERVAL:g}, or ${ENV}); 0: off")


def pytest_configure(config):
    if hasattr(config, "workerinput"):  # an xdist worker: its controller reports
        return
    option = config.getoption("--progress-interval")
    if option is not None:
        interval = interval_seconds(option, "--progress-interval")
    else:
        interval = interval_seconds(os.environ.get(ENV, str(DEFAULT_INTERVAL)), ENV)
    if interval > 0:
        config.pluginmanager.register(ProgressLine(config, interval), "cfdesign-progress-line")


class ProgressLine:
    """The counts from the reports and the timer thread that prints them."""

    def __init__(self, config, interval: float):
        self.config = config
        self.interval = interval
        self.start = time.monotonic()
        self.done = 0
        self.failed: set[str] = set()
        self.lock = threading.Lock()  # held while pytest's reporter or the timer writes to the terminal
        self.stop = threading.Event()
        self.thread = None
        self.session = None
        self.pad = None  # after a progress line: the width of pytest's partial line, to pad before it continues
        self.fd = None
        try:  # the terminal as it is now, outside any capture (pytest suspends its capture during configure)
            sys.stdout.flush()
            self.fd = os.dup(sys.stdout.fileno())
        except (AttributeError, OSError, ValueError):
            self.fd = None

    def line(self) -> str:
        total = self.session.testscollected if self.session is not None and self.session.testscollected else "?"
        return (f"[progress] {self.done}/{total} tests done, {len(self.failed)} failed, "
                f"{elapsed_text(time.monotonic() - self.start)}")

    def emit(self) -> None:
        with self.lock:
            reporter = self.config.pluginmanager.get_plugin("terminalreporter")
            writer = getattr(reporter, "_tw", None)
            width = getattr(writer, "width_of_current_line", 0) if writer is not None else 0
            self.write(("\n" if width and self.pad is None else "") + self.line() + "\n")
            self.pad = width

    def write(self, text: str) -> None:
        if self.fd is not None:
            try:
                os.write(self.fd, text.encode())
            except OSError:
                pass
        else:
            reporter = self.config.pluginmanager.get_plugin("terminalreporter")
            if reporter is not None:
                reporter.write(text, flush=True)

    def resume(self) -> None:
        """Before pytest's reporter writes again: pad the fresh line back to the width of its partial line."""
        if self.pad:
            self.write(" " * self.pad)
        self.pad = None

    def run(self) -> None:
        while not self.stop.wait(self.interval):
            self.emit()

    def pytest_sessionstart(self, session):
        self.session = session

    @pytest.hookimpl(wrapper=True)
    def pytest_runtestloop(self, session):
        self.session = session
        self.thread = threading.Thread(target=self.run, name="progress-line", daemon=True)
        self.thread.start()
        try:
            return (yield)
        finally:
            self.halt()

    def halt(self) -> None:
        self.stop.set()
        if self.thread is not None:
            self.thread.join()
            self.thread = None
            self.resume()

    @pytest.hookimpl(wrapper=True)
    def pytest_runtest_logstart(self, nodeid, location):
        with self.lock:
            self.resume()
            return (yield)

    @pytest.hookimpl(wrapper=True)
    def pytest_runtest_logfinish(self, nodeid, location):
        with self.lock:
            self.resume()
            return (yield)

    @pytest.hookimpl(wrapper=True)
    def pytest_runtest_logreport(self, report):
        with self.lock:
            self.resume()
            if report.when == "call" or (report.when == "setup" and not report.passed):
                self.done += 1
            if report.failed:
                self.failed.add(report.nodeid)
            return (yield)

    def pytest_unconfigure(self, config):
        self.halt()
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
