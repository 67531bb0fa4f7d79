"""studies.consensus_design.prefetch_tables: a comparison sweep's offline tables (one scheduled design per setting)
computed side by side in forked children, the same as one after another."""
from __future__ import annotations

import numpy as np

from designer.design import DesignOptions
from studies import consensus_design as cd
from studies.scenarios import load_scenario
from test_regions import chain  # noqa: E402 (tests/ is on the path: a user's five-cell chain)


def same(a, b) -> bool:
    """Equal, array for array (NaN equal to NaN), through tuples, lists and dicts."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
    if isinstance(a, (tuple, list)):
        return type(a) is type(b) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    return a == b


def test_tables_prefetched_side_by_side_are_the_tables_designed_one_after_another(tmp_path):
    sc = load_scenario(str(chain(tmp_path, "None")))
    settings = [sc.with_attacks(dos=d) for d in (0.0, 0.2, 0.4)]
    opts = DesignOptions(mode="scheduled")
    cd._TABLES.clear()  # noqa: SLF001 - the process's tables: start without them
    cd.prefetch_tables([(s, opts) for s in settings] + [(settings[0], opts)], workers=2)  # one asked twice
    assert len(cd._TABLES) == 3  # noqa: SLF001
    fetched = [cd.consensus_design(s, opts).tables for s in settings]
    assert len(cd._TABLES) == 3  # noqa: SLF001 - the designs found them
    cd._TABLES.clear()  # noqa: SLF001
    alone = [cd.consensus_design(s, opts).tables for s in settings]
    assert all(same(a, b) for a, b in zip(fetched, alone))
    assert not same(alone[0], alone[2])  # the settings' tables differ: the comparison has power
