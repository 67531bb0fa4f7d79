"""The public API on a user's own model file: every command, the same numbers as the CLI, clear errors."""
from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import studies
from studies.cli import main

ROOT = Path(__file__).resolve().parents[1]

# A user's model file, written where the repository is not: the README's model with a shorter horizon.
MODEL = (ROOT / "examples" / "ring_model.py").read_text().replace("STEPS = 60", "STEPS = 20")


@pytest.fixture()
def model_file(tmp_path):
    p = tmp_path / "oscillator.py"
    p.write_text(MODEL)
    return p


def cli(*args) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "studies", *map(str, args)], capture_output=True, text=True,
                          env=env, timeout=900)


def test_the_api_is_reexported_by_studies():
    for name in ("list_scenarios", "simulate", "design", "feasibility", "study", "report"):
        assert callable(getattr(studies, name)), name
    assert getattr(studies, "design").__module__ == "studies.api"


@pytest.mark.slow
def test_design_and_feasibility_give_the_cli_numbers(model_file, tmp_path):
    d = studies.design(model_file, mode="tuned", seed=3, out=tmp_path / "api")
    r = cli("design", model_file, "--mode", "tuned", "--seed", "3", "--out", tmp_path / "cli")
    assert r.returncode == (0 if d.feasible else 1), r.stderr
    a = json.loads((tmp_path / "api" / "schedule.json").read_text())
    b = json.loads((tmp_path / "cli" / "schedule.json").read_text())
    assert a["trace_bound"] == b["trace_bound"] and a["sigma"] == b["sigma"] and a["beta"] == b["beta"]
    np.testing.assert_array_equal(np.load(tmp_path / "api" / "schedule.npz")["K"],
                                  np.load(tmp_path / "cli" / "schedule.npz")["K"])
    assert a["attacks"]["delta"] == pytest.approx(0.3)
    # the per-edge FDI probabilities reached the bound: more FDI on the declared edge, larger bound
    hi = studies.design(model_file, mode="tuned", seed=3, fdi=0.4)
    lo = studies.design(model_file, mode="tuned", seed=3, fdi=0.0)
    assert np.nanmean(hi.trace_bound[:, -1]) > np.nanmean(lo.trace_bound[:, -1])

    grid = ["dos=0:0.4:3", "fdi=0:0.2:2"]
    fm = studies.feasibility(model_file, grid, mode="tuned", u_scale=0.01, out=tmp_path / "fapi")
    r = cli("feasibility", model_file, "--grid", grid[0], "--grid", grid[1], "--mode", "tuned", "--u-scale", "0.01",
            "--out", tmp_path / "fcli")
    assert r.returncode == 0, r.stderr
    with open(tmp_path / "fapi" / "feasibility.csv") as fa, open(tmp_path / "fcli" / "feasibility.csv") as fb:
        assert list(csv.DictReader(fa)) == list(csv.DictReader(fb))
    assert fm.feasible.shape == (3, 2) and fm.options.u_scale == 0.01


@pytest.mark.slow
def test_comparison_on_a_user_model_gives_the_cli_numbers(model_file, tmp_path):
    res = studies.study("comparison", model_file, runs=2, particles=40, seed=1, out=tmp_path / "api")
    r = cli("study", "comparison", model_file, "--runs", 2, "--particles", 40, "--seed", 1, "--quiet",
            "--out", tmp_path / "cli")
    assert r.returncode == 0, r.stderr
    on_disk = json.loads((tmp_path / "cli" / "results.json").read_text())
    def numbers(f):
        return {k: v for k, v in f.items() if k != "time_per_step_s"}

    assert res.filters.keys() == on_disk["filters"].keys()
    for name, f in res.filters.items():
        assert numbers(json.loads(json.dumps(f))) == numbers(on_disk["filters"][name]), name
    families = {f["family"] for f in res.filters.values()}
    assert families == {"consensus", "local", "particle", "EKF"}
    # no position components declared: the error is over the whole state
    block = res.results["by_scenario"]["oscillator"]
    assert block["error"] == {"metric": "rmse", "components": ["angle", "rate"]}
    html = (tmp_path / "cli" / "report.html").read_text()
    for word in ("consensus EKF (tuned design)", "local EKF at every node", "centralized PF (attack-aware)"):
        assert word in html


@pytest.mark.slow
def test_bad_model_files_exit_2_with_one_line(tmp_path):
    bad_fdi = tmp_path / "bad_fdi.py"
    bad_fdi.write_text(MODEL.replace("signal=FDISignal(amplitude=0.3, components=(0,)))", ")"))
    assert "signal=" not in bad_fdi.read_text()
    bad_net = tmp_path / "bad_net.py"
    bad_net.write_text(MODEL.replace("from_edges(4, [(0, 1), (1, 2), (2, 3), (3, 0)])",
                                     "from_edges(3, [(0, 1), (1, 2)])"))
    for path, cmd, needle in ((bad_fdi, "design", "fdi probability > 0 but no FDI bound"),
                              (bad_net, "simulate", "NETWORK has 3 nodes but the model has 4 sensors")):
        out = tmp_path / ("x.npz" if cmd == "simulate" else "x")
        r = cli(cmd, path, "--out", out)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and needle in lines[0], r.stderr
        assert not out.exists()
    assert "delta" in cli("design", bad_fdi, "--out", tmp_path / "y").stderr
    assert main(["design", str(bad_fdi), "--delta", "0.5", "--steps", "5", "--out", str(tmp_path / "z")]) in (0, 1)


def test_set_reaches_a_studys_own_options_and_the_scenarios_parameters():
    """``--set NAME=VALUE``: a study option (read as JSON) is peeled off, the rest goes to the scenarios."""
    from studies.pipeline import _study_assignments
    from studies.study_registry import get_study

    rest, own = _study_assignments(get_study("comparison"), ["hcmci_iterations=3", "tuned_in_sweeps=true",
                                                             "steps=12", "sweep_values=[0, 0.2]"])
    assert own == {"hcmci_iterations": 3, "tuned_in_sweeps": True, "sweep_values": [0, 0.2]}
    assert rest == ["steps=12"]
    rest, own = _study_assignments(get_study("consensus-robot"), ["hcmci_iterations=two"])
    assert own == {"hcmci_iterations": "two"} and rest == []
