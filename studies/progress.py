"""Progress bars on long work: shown on a terminal, off with ``quiet`` or when stderr is not a terminal."""
from __future__ import annotations

import sys
from typing import Iterable


def progress(iterable: Iterable, total: int, quiet: bool, desc: str) -> Iterable:
    if quiet or not sys.stderr.isatty():
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, leave=False)
