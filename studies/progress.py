"""Progress bars on long work: shown on a terminal, off with ``quiet`` or when stderr is not a terminal."""
from __future__ import annotations

import sys
from typing import Iterable


def _shown(quiet: bool) -> bool:
    return not quiet and sys.stderr.isatty()


def progress(iterable: Iterable, total: int, quiet: bool, desc: str) -> Iterable:
    """``iterable`` wrapped in a bar of ``total`` items (or unchanged when no bar is shown)."""
    if not _shown(quiet):
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, leave=False)


class _NoBar:
    def update(self, n: int = 1) -> None:
        pass

    def close(self) -> None:
        pass


def counter(total: int, quiet: bool, desc: str):
    """A bar advanced by hand (``update()``, then ``close()``), for work that finishes out of order."""
    if not _shown(quiet):
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, leave=False)
