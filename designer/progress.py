"""Progress of long work: the code says where it is, the command line shows it.

Code that may run long marks where it is: :func:`phase` (a named stage, nested phases read left to right) and
:func:`progress` / :func:`counter` (the items of a stage).  What is shown:

* a bar (``tqdm``) over a stage's items where stderr is a terminal and the caller is not ``quiet``;
* otherwise, once the command line has installed its sink (:func:`showing`; every ``cfdesign`` command but those
  run with ``--quiet``), a line on stderr, ``cfdesign: <phase> > <phase>: <k>/<n> (<s> s)`` (once the count has
  advanced since its first line, ``<k>/<n>, about <t> left``: at its rate from that line to its last advance, less
  the time since that advance, so that the time left shrinks while an item is under way), the first
  :data:`FIRST_S` seconds after the command started and then at most every :data:`EVERY_S` seconds, so that a
  command that runs longer than a few seconds says what it is doing in a log or a pipe too.

Only the process that installed the sink writes lines (a worker process forked from it stays silent: its parent
reports the chunks).  Called from a library (no sink), nothing is written.
"""
from __future__ import annotations

import contextlib
import os
import sys
import time
from typing import Iterable, Iterator

__all__ = ["FIRST_S", "EVERY_S", "showing", "hush", "phase", "progress", "counter", "line"]

#: Seconds after the command's start before its first progress line.
FIRST_S = 5.0
#: Seconds at least between two progress lines.
EVERY_S = 10.0


class _Sink:
    def __init__(self, stream, start: float):
        self.stream, self.start, self.pid, self.last = stream, start, os.getpid(), None
        self.phases: list[str] = []
        # (phases, what, total) -> [time, k] of the count's first line and [time, k] of its last advance since
        self.counts: dict = {}

    def due(self, now: float) -> bool:
        if os.getpid() != self.pid:
            return False
        return now - self.start >= FIRST_S if self.last is None else now - self.last >= EVERY_S

    def advance(self, now: float, what: str, k: int, total) -> None:
        """Note when a count written before last advanced (called at every :func:`line`, due or not)."""
        seen = self.counts.get((" > ".join(self.phases), what, total))
        if seen is not None and k > seen[3]:
            seen[2], seen[3] = now, k

    def write(self, now: float, where: str, count: tuple | None = None) -> None:
        """A line: the phases, ``where``, the seconds since the command started; with ``count`` ``(what, k, total)``
        ``what k/total`` and, once the count has advanced since its first line, the time left (``about 7 min
        left``): the remaining items at the rate from its first line to its last advance, less the time since that
        advance; once that is spent (the items under way take longer than the rate says), that the time left is
        unknown, not "about 0 s" (a map's last grid point had said so for a minute)."""
        self.last = now
        label = " > ".join(self.phases)
        if count is not None:
            what, k, total = count
            where = f"{what} {k}/{total}".strip()
            t0, k0, t1, k1 = self.counts.setdefault((label, what, total), [now, k, now, k])
            if total is not None and k0 < k1 < total and k1 == k:
                left = (t1 - t0) / (k1 - k0) * (total - k) - (now - t1)
                where += f", about {_duration(left)} left" if left >= 0.5 else \
                    ", slower than so far: time left unknown"
        text = f"cfdesign: {label}: {where}" if label and where else f"cfdesign: {label or where}"
        text += f" ({now - self.start:.0f} s)"
        if self.stream.isatty():  # above a bar a runner may be drawing on the terminal, not through it
            from tqdm import tqdm

            tqdm.write(text, file=self.stream)
        else:
            print(text, file=self.stream, flush=True)


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"


_SINK: _Sink | None = None


@contextlib.contextmanager
def showing(stream=None) -> Iterator[None]:
    """Write progress lines on ``stream`` (stderr) while the block runs (the command line, around a command)."""
    global _SINK
    before, _SINK = _SINK, _Sink(stream if stream is not None else sys.stderr, time.perf_counter())
    try:
        yield
    finally:
        _SINK = before


def hush() -> None:
    """No progress lines for the rest of the command (``--quiet``)."""
    global _SINK
    _SINK = None


def line(what: str = "", k: int | None = None, total: int | None = None) -> None:
    """Say where the work is, if a line is due: ``what`` (e.g. ``step``), then ``k/total`` when given (formatted only
    when a line is written: this is called at every step of a filter's loop)."""
    sink = _SINK
    if sink is not None:
        now = time.perf_counter()
        if k is not None:
            sink.advance(now, what, k, total)
        if sink.due(now):
            sink.write(now, what, None if k is None else (what, k, total))


@contextlib.contextmanager
def phase(name: str) -> Iterator[None]:
    """A named stage of the work: the lines written inside it name it (nested stages, outermost first)."""
    sink = _SINK
    if sink is None:
        yield
        return
    sink.phases.append(name)
    try:
        line()
        yield
    finally:
        sink.phases.pop()


def _bar(quiet: bool) -> bool:
    return not quiet and sys.stderr.isatty()


def progress(iterable: Iterable, total: int, quiet: bool = False, desc: str = "") -> Iterable:
    """``iterable`` with its progress shown: a bar of ``total`` items on a terminal, else progress lines (unless
    ``quiet``)."""
    if _bar(quiet):
        from tqdm import tqdm

        return tqdm(iterable, total=total, desc=desc, leave=False)
    if quiet or _SINK is None:
        return iterable
    return _lines(iterable, total, desc)


def _lines(iterable: Iterable, total: int, desc: str) -> Iterator:
    for k, item in enumerate(iterable):
        line(desc, k, total)
        yield item


class _Lines:
    def __init__(self, total: int, desc: str, quiet: bool):
        self.k, self.total, self.desc, self.quiet = 0, total, desc, quiet

    def update(self, n: int = 1) -> None:
        self.k += n
        if not self.quiet:
            line(self.desc, self.k, self.total)

    def close(self) -> None:
        pass


def counter(total: int, quiet: bool = False, desc: str = ""):
    """A progress advanced by hand (``update()``, then ``close()``), for work that finishes out of order."""
    if _bar(quiet):
        from tqdm import tqdm

        return tqdm(total=total, desc=desc, leave=False)
    return _Lines(total, desc, quiet)
