"""The particle-filter studies of seeds 000 and 002 on the Monte Carlo runner: backends, stored chunks, resume.

Small sizes (a few runs in chunks of two, few particles): what is checked is that the
numbers do not depend on where the chunks run and that stored chunks are reused or
refused, not the papers' claims (tests/test_pf_studies.py).
"""
from __future__ import annotations

import functools
import json

import pytest

from designer.validation import InputError
from studies.pipeline import run_study
from studies.rrp_deception import LINEAR
from studies.runner import CHUNKS_DIR, Backend, make_backend

pytestmark = pytest.mark.slow  # a slow end-to-end file: every test runs a study, or fresh processes

# rrp: every row (the linear-weights row included) runs the fused engine (one Generator per run)
STUDIES = {
    "rrp-deception": (functools.partial(run_study, "rrp-deception"),
                      dict(runs=5, particles=60, seed=7, sweep=(0.2, 0.5), chunk_size=2)),
    "binary-multi-attack": (functools.partial(run_study, "binary-multi-attack"),
                            dict(runs=5, particles=60, seed=8, sweep=(0.3,), table2_particles=(40,), chunk_size=2)),
}
CHUNKS = 3  # 5 runs in chunks of 2


def _numbers(res: dict) -> dict:
    """results.json without what legitimately varies between calls (timings, how the runs were computed)."""
    def strip(d):
        if isinstance(d, dict):
            return {k: strip(v) for k, v in d.items() if k not in ("time_per_step_s", "wall_time_s")}
        return [strip(v) for v in d] if isinstance(d, list) else d

    res = json.loads(json.dumps(getattr(res, "results", res)))
    for key in ("runner", "versions"):
        res.pop(key)
    res.pop("threads", None)  # 'auto' resolves per backend (1 on Dask); the numbers do not depend on it
    return strip(res)


@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cl:
        yield cl


@pytest.fixture(scope="module")
def batched(tmp_path_factory):
    """Each study once, batched in this process, stored in its own directory."""
    out = {}
    for name, (run, kw) in STUDIES.items():
        d = tmp_path_factory.mktemp(name)
        out[name] = d, run(out=d, **kw)
    return out


@pytest.mark.parametrize("study", STUDIES)
def test_same_numbers_with_every_backend(study, batched, cluster, tmp_path):
    run, kw = STUDIES[study]
    _, a = batched[study]
    b = run(out=tmp_path / "b", backend=Backend("processes", workers=2), **kw)
    c = run(out=tmp_path / "c", backend=make_backend(dask=cluster.scheduler_address), **kw)
    assert _numbers(a) == _numbers(b) == _numbers(c)
    assert a["runner"]["chunks_computed"] == b["runner"]["chunks_computed"] == c["runner"]["chunks_computed"] == CHUNKS
    assert b["runner"]["backend"] == "processes" and c["runner"]["backend"] == "dask"
    assert _numbers(json.loads((tmp_path / "c" / "results.json").read_text())) == _numbers(a)
    if study == "rrp-deception":
        assert a["filters"][LINEAR]["engine"] == "fast" and a["filters"][LINEAR]["collapsed_steps"] > 0
    for res in (a, b, c):  # compilation (seconds) is outside the timed calls, in every backend
        for f in res["filters"].values():
            assert 0 < f["time_per_step_s"] < (1e-3 if f["engine"] == "fast" else 0.05), (res["runner"], f)


@pytest.mark.parametrize("study", STUDIES)
def test_stored_chunks_are_reused_and_other_settings_refused_unless_forced(study, batched):
    run, kw = STUDIES[study]
    out, a = batched[study]
    again = run(out=out, **kw)
    assert again["runner"]["chunks_reused"] == CHUNKS and again["runner"]["chunks_computed"] == 0
    assert again["filters"] == a["filters"]  # timings too: they were stored with the chunks
    assert _numbers(again) == _numbers(a)
    log = out / CHUNKS_DIR / study / "log.jsonl"
    assert len(log.read_text().splitlines()) == CHUNKS  # nothing computed twice
    with pytest.raises(InputError, match="other settings.*config.particles.*--force"):
        run(out=out, **{**kw, "particles": 50})
    forced = run(out=out, force=True, **{**kw, "particles": 50})
    assert forced["runner"]["chunks_computed"] == CHUNKS and forced["runner"]["chunks_reused"] == 0
    assert forced["particles"] == 50 and json.loads((out / "results.json").read_text())["particles"] == 50
