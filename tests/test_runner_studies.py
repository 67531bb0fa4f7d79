"""consensus-robot and fdi-four-tank on the Monte Carlo runner: the same numbers with every backend, resume, refusal.

Small sizes keep this quick; one Dask LocalCluster serves the whole module.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

import studies.results as study_results
from designer import InputError
from filters.attacks import simulate_attacks
from filters.consensus import run_consensus
from designer.design import DesignOptions
from studies.consensus_design import consensus_design
from studies.pipeline import run_study
from studies.runner import CHUNKS_DIR, Backend, make_backend
from studies.scenarios import load_scenario

pytestmark = pytest.mark.slow  # a slow end-to-end file: every test runs a study, or fresh processes

TIMINGS = ("time_per_step_s", "wall_time_s", "time_per_step_single_run_s")


def _numbers(res: dict) -> dict:
    """results.json without what legitimately varies between calls (timings, how the runs were computed)."""
    def strip(d):
        if isinstance(d, dict):
            return {k: strip(v) for k, v in d.items() if k not in TIMINGS}
        if isinstance(d, list):
            return [strip(x) for x in d]
        return d

    res = json.loads(json.dumps(res))
    for key in ("versions", "runner", "workers", "threads"):  # how the runs were computed
        res.pop(key, None)
    return strip(res)


@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cl:
        yield cl


def _chunk_files(out, label):
    return sorted((out / CHUNKS_DIR / label).glob("runs_*.npz"))


# --- consensus-robot ----------------------------------------------------------------------------------------------

def run_consensus_robot(*, mode="paper", **kw) -> dict:
    """The study through the pipeline; its results.json content."""
    return run_study("consensus-robot", options=DesignOptions(mode=mode), **kw).results


CR = dict(runs=10, seed=2, quiet=True, chunk_size=4)  # chunks 0-3, 4-7, 8-9; run 9 of seed 2 diverges (paper)


@pytest.fixture
def few_runs_checked(monkeypatch):
    """Check the bound at every (node, step) valid in 5 runs, so that a 10-run study exercises Φ."""
    monkeypatch.setattr(study_results, "MIN_RUNS_FOR_CHECK", 5)  # the per-pair test's and whole_bounds' one home


def test_consensus_robot_same_numbers_with_every_backend(tmp_path, cluster, few_runs_checked):
    a = run_consensus_robot(out=tmp_path / "a", **CR)
    b = run_consensus_robot(out=tmp_path / "b", backend=Backend("processes", workers=2), **CR)
    c = run_consensus_robot(out=tmp_path / "c", backend=make_backend(dask=cluster.scheduler_address), **CR)
    assert _numbers(a) == _numbers(b) == _numbers(c)
    assert a["runner"]["chunks"] == 3 and b["runner"]["workers"] == 2 and c["runner"]["backend"] == "dask"
    # the 3 chunks on 2 workers each in 2 shares (studies.runner.split_into): the filters of a chunk split between
    # the workers, the same numbers
    assert a["runner"]["shares"] == 1 and b["runner"]["shares"] == 2 and c["runner"]["shares"] == 1
    assert _numbers(json.loads((tmp_path / "c" / "results.json").read_text())) == _numbers(a)
    checked = [f["bound_check"] for f in a["filters"].values() if f["bound_check"]]
    assert checked and all(bc["pairs_checked"] > 0 for bc in checked)
    # diverged runs are rebuilt from the stored arrays: rerunning one alone reproduces its node, step and reason
    sc = load_scenario("indoor-robot")
    name, f = next((n, f) for n, f in a["filters"].items() if f["diverged_runs"])
    for d in f["diverged_runs"]:
        assert d["seed"] == CR["seed"] and d["spawn_key"] == [d["run"]]
        ts, ats = np.random.SeedSequence(d["seed"], spawn_key=tuple(d["spawn_key"])).spawn(2)
        traj = sc.simulate(np.random.default_rng(ts), sc.steps)
        design = consensus_design(sc)
        att = simulate_attacks(sc.network, sc.steps, sc.model.n_x, np.random.default_rng(ats),
                               sc.resolved_attacks.signal)
        dv = run_consensus(sc.model, sc.network, traj.z, design, inputs=traj.inputs, attacks=att).diverged
        assert (dv["node"], dv["step"], dv["reason"]) == (d["node"], d["step"], d["error"])
    assert f["diverged_fraction"] == len(f["diverged_runs"]) / CR["runs"]


def test_consensus_robot_resumes_and_refuses_other_settings(tmp_path, few_runs_checked):
    out = tmp_path / "s"
    first = run_consensus_robot(out=out, **CR)
    again = run_consensus_robot(out=out, **CR)
    assert again["runner"]["chunks_reused"] == 3 and again["runner"]["chunks_computed"] == 0
    assert _numbers(again) == _numbers(first)
    _chunk_files(out, "consensus-robot")[1].unlink()  # as if interrupted in the middle chunk
    resumed = run_consensus_robot(out=out, **CR)
    assert (resumed["runner"]["chunks_reused"], resumed["runner"]["chunks_computed"]) == (2, 1)
    assert _numbers(resumed) == _numbers(first)
    with pytest.raises(InputError, match="other settings.*config.params"):
        run_consensus_robot(out=out, overrides={"dos_prob": 0.2}, **CR)
    with pytest.raises(InputError, match="other settings.*config.mode"):
        run_consensus_robot(out=out, mode="tuned", **{**CR, "runs": 2, "chunk_size": 4})
    forced = run_consensus_robot(out=out, overrides={"dos_prob": 0.2}, force=True, **CR)
    assert forced["runner"]["chunks_computed"] == 3 and forced["params"]["dos_prob"] == 0.2
    assert _numbers(forced) != _numbers(first)


def test_consensus_robot_runs_do_not_depend_on_the_chunking(few_runs_checked):
    kw = {**CR, "runs": 5}
    a = run_consensus_robot(out=None, **{**kw, "chunk_size": 5})
    b = run_consensus_robot(out=None, **{**kw, "chunk_size": 2})
    assert _numbers(a) == _numbers(b)
    assert b["runner"]["chunks"] == 3 and b["runner"]["chunk_size"] == 2


# --- fdi-four-tank ------------------------------------------------------------------------------------------------

FDI = dict(runs=3, particles=30, seed=1, quiet=True, chunk_size=2, overrides={"steps": 40})


def run_fdi_four_tank(**kw) -> dict:
    """The study through the pipeline; its results.json content."""
    return run_study("fdi-four-tank", **kw).results


def test_fdi_four_tank_same_numbers_with_every_backend(tmp_path, cluster):
    a = run_fdi_four_tank(out=tmp_path / "a", **FDI)
    b = run_fdi_four_tank(out=tmp_path / "b", backend=Backend("processes", workers=2), **FDI)
    c = run_fdi_four_tank(out=tmp_path / "c", backend=make_backend(dask=cluster.scheduler_address), **FDI)
    assert _numbers(a) == _numbers(b) == _numbers(c)
    assert a["runner"]["chunks"] == 2 and b["runner"]["workers"] == 2 and c["runner"]["backend"] == "dask"
    assert (a["workers"], b["workers"], c["workers"]) == (1, 2, None)
    assert c["threads"] == 1 and b["threads"] >= 1  # 'auto': 1 on Dask, the cores left by the worker processes
    assert _numbers(json.loads((tmp_path / "b" / "results.json").read_text())) == _numbers(a)
    for f in a["filters"].values():  # timings come from every chunk
        assert f["time_per_step_s"] > 0 and f["time_per_step_single_run_s"] > 0
    # a run's numbers do not depend on the runs computed with it (nothing is shared between runs): run 0 alone
    one = run_fdi_four_tank(out=None, **{**FDI, "runs": 2, "chunk_size": 1})
    for name, f in one["filters"].items():
        assert f["rmse_run0"] == a["filters"][name]["rmse_run0"], name
        if "detection" in f:
            assert f["detection"]["run0"] == a["filters"][name]["detection"]["run0"], name


def test_fdi_four_tank_resumes_and_refuses_other_settings(tmp_path):
    out = tmp_path / "s"
    first = run_fdi_four_tank(out=out, **FDI)
    again = run_fdi_four_tank(out=out, **FDI)
    assert again["runner"]["chunks_reused"] == 2 and again["runner"]["chunks_computed"] == 0
    assert _numbers(again) == _numbers(first)
    with pytest.raises(InputError, match="other settings.*config.particles"):
        run_fdi_four_tank(out=out, **{**FDI, "particles": 31})
    assert json.loads((out / "results.json").read_text())["particles"] == 30
    forced = run_fdi_four_tank(out=out, force=True, **{**FDI, "particles": 31})
    assert forced["runner"]["chunks_computed"] == 2 and forced["particles"] == 31
