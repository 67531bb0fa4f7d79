"""A paper design that cannot start (σ, β beyond (28)/(29) at the first step) does not block a study (issue 26).

``study comparison`` and ``study consensus-robot`` on a user's model file whose paper design fails at the first
step of every run: exit 0, the paper design in results.json, table.md, the report and the command line's
lines as infeasible with its reason (never ranked or picked), and every other filter run on the same runs with
the numbers it has when the paper design runs.  Given σ, β or τ still refuse (tests/test_cli.py).
"""
from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from conftest import TANK_MODEL
from designer.design import DesignOptions
from designer.validation import InputError
from studies import api, schemas
from studies.cli import main
from studies.comparison import FILTERS, PAPER_DESIGN
from studies.runner import SUMMED, run_seed
from studies.scenarios import load_scenario, reference

# sigma = 0.1 breaks (28): sigma < 1/((1 + eps) lambda_max(P0)) with eps = 0.5/d_max = 0.25 (a 3-node path) and P0 = 25 I
WIDE = TANK_MODEL.replace("0.05 * np.eye(2)))", "25.0 * np.eye(2)))")
SIGMA_LIMIT = 1.0 / ((1.0 + 0.5 / 2) * 25.0)
# sigma = 0.1 passes (28) (P0 = 7 I: limit 0.114) and beta = 0.1 breaks (29): Phi_1|0 grows with x -> 1.3 x
GROWING = (TANK_MODEL.replace("ca.vertcat(x[0] + 0.1 * x[1], 0.95 * x[1])", "1.3 * x")
           .replace("0.05 * np.eye(2)))", "7.0 * np.eye(2)))"))
PAPER_VARIANTS = ("consensus-EKF (paper, tau=0.01)", "consensus-EKF (paper, tau=0, no consensus)")


def _write(tmp_path, name: str, text: str):
    path = tmp_path / f"{name}.py"
    path.write_text(text)
    return path


def _design_error(path) -> str:
    """The InputError ``cfdesign design`` gives for the paper design of ``path`` (the reason a study reports)."""
    with pytest.raises(InputError) as exc:
        api.design(str(path), mode="paper")
    return str(exc.value)


def _row(text: str, name: str) -> list[str]:
    """The cells of the Markdown table row of ``name`` (cell bars escaped as ``\\|`` do not split it)."""
    line = next(ln for ln in text.splitlines() if re.match(rf"\|( — \|)? {re.escape(name)} \|", ln))
    return [c.strip() for c in re.split(r"(?<!\\)\|", line)[1:-1]]


@pytest.mark.slow
def test_comparison_reports_the_paper_design_infeasible_and_runs_the_others(tmp_path, capsys):
    model = _write(tmp_path, "growing", GROWING)
    reason = _design_error(model)
    assert reason.startswith("beta must satisfy (29) at the first step") and reason.endswith("got 0.1")
    out = tmp_path / "c"
    assert main(["study", "comparison", str(model), "--runs", "2", "--particles", "40", "--quiet",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"  {PAPER_DESIGN}: infeasible, not run: {reason}\n" in printed
    res = json.loads((out / "results.json").read_text())
    schemas.validate("study", res)
    paper = res["filters"][PAPER_DESIGN]
    assert paper["infeasible"] == reason
    assert all(paper[k] is None for k in ("rmse", "rmse_ci95", "rmse_curve", "rmse_median_run", "time_per_step_s",
                                          "diverged_runs"))
    assert paper["feasible_runs"] == 0
    # 40 particles on this model: the particle filters are degenerate on their pilot runs, left out of the default set
    assert all("pilot" in why for why in res["left_out"].values())
    for name in FILTERS:  # every other filter ran: a number, a curve, a time; none is called infeasible
        if name != PAPER_DESIGN and name not in res["left_out"]:
            f = res["filters"][name]
            assert "infeasible" not in f and math.isfinite(f["rmse"]) and len(f["rmse_curve"]) == res["steps"]
            assert f["time_per_step_s"] > 0
    for sweep in res["sweeps"].values():  # the sweeps: marked at every setting, the others there with numbers
        assert sweep
        for row in sweep.values():
            assert row[PAPER_DESIGN] == {"infeasible": reason, "rmse": None, "rmse_ci95": None,
                                         "rmse_median_run": None, "diverged_runs": None}
            assert all(row[n]["rmse"] is not None for n in row if n != PAPER_DESIGN)
    rec = res["recommendation"][res["scenario"]]
    assert PAPER_DESIGN not in (rec["most_accurate"], rec["cheapest"], *rec["not_significantly_worse"],
                                *rec["fewest_messages"])
    table = (out / "table.md").read_text()
    cells = _row(table, PAPER_DESIGN)
    header = _row(table, "filter")
    assert len(cells) == len(header) and cells[2] == f"infeasible, not run: {reason}".replace("|", r"\|")
    report = (out / "report.md").read_text()
    summary = report[report.index("## Summary"):report.index("## Contents")]
    cells = _row(summary, PAPER_DESIGN)
    assert cells[0] == "—" and cells[2] == "—" and cells[-1] == f"infeasible, not run: {reason}".replace("|", r"\|")
    pick = summary[summary.index("**Which to pick"):]
    assert "paper design" not in pick


def test_consensus_robot_runs_without_the_paper_designs(tmp_path, capsys):
    """The default mode compares the paper design with tau = 0: neither can start, both say so, the rest run."""
    model = _write(tmp_path, "wide", WIDE)
    reason = _design_error(model)
    assert reason.startswith("sigma must satisfy (28) at the first step") and f"= {SIGMA_LIMIT:.6g}," in reason
    out = tmp_path / "r"
    assert main(["study", "consensus-robot", str(model), "--runs", "2", "--quiet", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    res = json.loads((out / "results.json").read_text())
    schemas.validate("study", res)
    filters = res["filters"]
    assert set(PAPER_VARIANTS) < set(filters) and len(filters) == len(PAPER_VARIANTS) + 4  # KCF, HCMCI, local, central
    for name in PAPER_VARIANTS:
        f = filters[name]
        assert f["infeasible"] == reason and f["rmse_position"] is None and f["bound_check"] is None
        assert f["feasibility"] is None and f["time_per_step_s"] is None
        assert f"  {name}: infeasible, not run: {reason}\n" in printed
        assert _row((out / "table.md").read_text(), name)[1] == f"infeasible, not run: {reason}".replace("|", r"\|")
    for name, f in filters.items():
        if name not in PAPER_VARIANTS:
            assert "infeasible" not in f and math.isfinite(f["rmse_position"]) and f["time_per_step_s"] > 0
    summary = (out / "report.md").read_text()
    summary = summary[summary.index("## Summary"):summary.index("## Contents")]
    for name in PAPER_VARIANTS:
        cells = _row(summary, name)
        assert cells[0] == "—" and cells[-1] == f"infeasible, not run: {reason}".replace("|", r"\|")
    assert "paper" not in summary[summary.index("**Which to pick"):]


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and np.array_equal(a, b, equal_nan=True)


@pytest.mark.slow
def test_the_other_filters_do_not_depend_on_whether_the_paper_design_runs(tmp_path):
    """Per-run arrays of every other filter: the same, bit for bit, when the paper design cannot start (not run) and
    when σ, β small enough let it run (the common random numbers do not depend on it)."""
    from studies.comparison import _runs as comparison_runs
    from studies.comparison import _settings
    from studies.consensus_robot import _runs as robot_runs

    sc = load_scenario(str(_write(tmp_path, "wide", WIDE)))
    ref, ids = reference(sc), [0, 1, 2]

    def seeds():  # fresh: a SeedSequence spawns other children once it has spawned
        return [run_seed(5, r) for r in ids]

    small = DesignOptions(sigma=0.01, beta=0.01)  # within (28)-(29) at the first step
    kw = dict(ref=ref, settings=_settings(sc, [0.0, 0.3]), particles=30)  # every filter at every setting
    blocked = comparison_runs(ids, seeds(), options=DesignOptions(), **kw)
    runs = comparison_runs(ids, seeds(), options=small, **kw)
    p = FILTERS.index(PAPER_DESIGN)
    # not run: no design conditions, no time; run: both at every setting (here it diverges in every run)
    assert np.isnan(blocked["feasible"][:, :, p]).all() and np.isnan(blocked["seconds"][:, :, p]).all()
    assert not np.isnan(runs["feasible"][:, :, p]).any() and not np.isnan(runs["seconds"][:, :, p]).any()
    others = [f for f in range(len(FILTERS)) if f != p]
    for key in ("err2", "feasible", "delivered"):
        assert _same(blocked[key][:, :, others], runs[key][:, :, others]), key
    assert _same(blocked["estimate"][:, others], runs["estimate"][:, others])
    assert _same(blocked["truth"], runs["truth"])

    blocked = robot_runs(ids, seeds(), ref=ref, mode="paper", options=DesignOptions(), replay=None)
    runs = robot_runs(ids, seeds(), ref=ref, mode="paper", options=small, replay=None)
    assert (blocked["v0_seconds"] == 0).all() and (runs["v0_seconds"] > 0).all()  # variants 0, 1: the paper's
    keys = [k for k in runs if not k.removeprefix(SUMMED).startswith(("v0_", "v1_")) and not k.endswith("_seconds")]
    assert {k.split("_")[0] for k in keys} == {"truth", "v2", "v3", "v4", "v5"}  # KCF, HCMCI, local, centralized
    for k in keys:
        assert _same(blocked[k], runs[k]), k


@pytest.mark.slow
def test_no_filters_interval_depends_on_another_filters_runs(tmp_path):
    """Each filter bootstraps its 95 % intervals from its own stream: the others' intervals, at every setting, are
    the same whether the paper design kept every run, lost some to divergence or was not run at all."""
    from types import SimpleNamespace

    from studies.comparison import STUDY as COMPARISON, _summarise
    from studies.pipeline import StudyOptions
    from studies.runner import Backend

    path = str(_write(tmp_path, "tank", TANK_MODEL))
    kw = dict(runs=4, particles=30, sweep_values=[0.3], tuned_in_sweeps=False)
    res = api.study("comparison", path, **kw)
    sc = next(iter(res.scenarios.values()))
    arrays = next(iter(res.arrays.values()))
    p = FILTERS.index(PAPER_DESIGN)
    assert not res.filters[PAPER_DESIGN].get("infeasible") and np.isfinite(arrays["err2"][:, 0, p]).all()
    so = StudyOptions(4, 30, 0, COMPARISON.chunk_size(sc, 4), Backend(), DesignOptions(),
                      {**COMPARISON.options, "sweep_values": [0.3], "tuned_in_sweeps": False})
    lost = {k: v.copy() for k, v in arrays.items()}
    lost["err2"][[1, 3], :, p] = np.nan  # two of the paper design's runs diverged

    def intervals(a):
        block = _summarise(sc, SimpleNamespace(arrays=a, describe=lambda: {}), so)
        rows = {n: {k: v for k, v in f.items() if "ci95" in k} for n, f in block["filters"].items()}
        sweeps = {(prm, val, n): row[n] for prm, by in block["sweeps"].items() for val, row in by.items()
                  for n in row if n != PAPER_DESIGN}
        return rows, sweeps

    (full, sw_full), (part, sw_part) = intervals(arrays), intervals(lost)
    assert full[PAPER_DESIGN] != part[PAPER_DESIGN]  # the paper design's own interval does change
    assert {n: v for n, v in full.items() if n != PAPER_DESIGN} == {n: v for n, v in part.items() if n != PAPER_DESIGN}
    assert sw_full == sw_part

