"""The command line: outputs, reproducibility, exit codes and one-line errors."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from studies.cli import main
from studies.scenarios import SCENARIOS, load_scenario

ROOT = Path(__file__).resolve().parents[1]


def run_cli(*args: str) -> subprocess.CompletedProcess:
    """Run the real console entry point in a subprocess (exit code and streams as a user sees them)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "studies", *args], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=300)


def test_scenarios_json_lists_parameters():
    r = run_cli("scenarios", "--json")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert [s["name"] for s in info] == list(SCENARIOS)
    robot = next(s for s in info if s["name"] == "indoor-robot")
    assert robot["n_x"] == 3 and robot["sensors"] == 8 and robot["paper"] == "003"
    params = {p["name"]: p for p in robot["parameters"]}
    assert params["noise"]["default"] == "realistic" and params["noise"]["choices"] == ["realistic", "paper"]
    assert params["process_var"]["source"] == "assumption"


def test_simulate_writes_states_and_measurements_reproducibly(tmp_path):
    a, b, c = tmp_path / "a.npz", tmp_path / "b.npz", tmp_path / "c.npz"
    assert main(["simulate", "target-range-bearing", "--steps", "25", "--seed", "5", "--out", str(a)]) == 0
    assert main(["simulate", "target-range-bearing", "--steps", "25", "--seed", "5", "--out", str(b)]) == 0
    assert main(["simulate", "target-range-bearing", "--steps", "25", "--seed", "6", "--out", str(c)]) == 0
    da, db, dc = np.load(a), np.load(b), np.load(c)
    assert da["x"].shape == (26, 4) and da["y"].shape == (25, 4, 2)
    assert np.array_equal(da["x"], db["x"]) and np.array_equal(da["y"], db["y"])
    assert not np.array_equal(da["y"], dc["y"])
    # The file is the model's own generative process: y[k] = h(x[k+1]) + noise of the stated size.
    m = load_scenario("target-range-bearing").model
    resid = da["z"] - m.h_all(da["x"][1:], 1)
    assert np.abs(resid[:, 0::2]).max() < 5 * 5.0  # range noise: std <= 5 per component
    assert str(da["scenario"]) == "target-range-bearing" and int(da["seed"]) == 5


def test_simulate_with_override_and_modes(tmp_path):
    out = tmp_path / "s.npz"
    assert main(["simulate", "switching-2d", "--steps", "10", "--out", str(out), "--set", "switch_prob=1"]) == 0
    d = np.load(out)
    assert np.all(d["modes"] == 1)
    assert json.loads(str(d["params"]))["switch_prob"] == 1.0


@pytest.mark.parametrize(
    "args, needle",
    [
        (["simulate", "no-such", "--out", "x.npz"], "unknown scenario"),
        (["simulate", "indoor-robot", "--set", "process_var=-1", "--out", "x.npz"], "process_var"),
        (["simulate", "indoor-robot", "--set", "dos_prob=2", "--out", "x.npz"], "dos_prob"),
        (["simulate", "indoor-robot", "--set", "bogus=1", "--out", "x.npz"], "bogus"),
        (["simulate", "indoor-robot", "--steps", "0", "--out", "x.npz"], "steps"),
        (["simulate", "indoor-robot", "--seed", "-3", "--out", "x.npz"], "seed"),
        (["simulate", "indoor-robot", "--out", "x.txt"], "out"),
        (["simulate", "indoor-robot", "--steps", "abc", "--out", "x.npz"], "--steps"),
        (["simulate", "indoor-robot"], "--out"),
        (["nosuchcommand"], "nosuchcommand"),
    ],
)
def test_bad_input_exits_2_with_one_line(tmp_path, args, needle):
    args = [a if not a.endswith((".npz", ".txt")) else str(tmp_path / a) for a in args]
    r = run_cli(*args)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert needle in lines[0] and "Traceback" not in r.stderr
    assert not list(tmp_path.iterdir()), "nothing may be written on bad input"


_MODEL = """
import casadi as ca
import numpy as np
from designer import AttackSpec, FDISignal, Gaussian, Model, SensorNetwork, Sensor
STEPS = 20
NETWORK = SensorNetwork.from_edges(3, [(0, 1), (1, 2)])
ATTACKS = AttackSpec(dos=0.1, fdi=0.1, signal=FDISignal(amplitude=0.2, components=(0,)))
def model() -> Model:
    x = ca.SX.sym("x", 2)
    f = ca.vertcat(x[0] + 0.1 * x[1], 0.95 * x[1])
    sensors = [Sensor(f"s{i}", x[0] + 0.1 * i * x[1], Gaussian.zero_mean([[0.05]])) for i in range(3)]
    return Model("tank", x, f, sensors, process_noise=Gaussian.zero_mean(1e-3 * np.eye(2)),
                 prior=Gaussian([0.0, 1.0], 0.05 * np.eye(2)))
"""


@pytest.mark.parametrize(
    "args, needle",
    [
        (["simulate", "{many}", "--out", "{tmp}/a.npz"], "STEPS"),
        (["simulate", "{raising}", "--out", "{tmp}/a.npz"], "model() in"),
        (["simulate", "{model}", "--out", "{tmp}/dir.npz"], "existing directory"),
        (["simulate", "{model}", "--set", "x0=[1,2]", "--out", "{tmp}/a.npz"], "takes no --set parameters"),
        (["simulate", "indoor-robot", "--set", "x0=[1e308,0,0]", "--out", "{tmp}/a.npz"], "not finite"),
        (["design", "{model}", "--out", "{model}"], "existing file"),
        (["design", "{model}", "--u-scale", "-0.01", "--out", "{tmp}/d"], "--u-scale"),
        (["study", "comparison", "{model}", "--runs", "10000000000", "--out", "{tmp}/c"], "runs must be an integer in"),
        (["study", "comparison", "{model}", "--runs", "inf", "--out", "{tmp}/c"], "--runs"),
        (["study", "comparison", "{model}", "--particles", "1e11", "--out", "{tmp}/c"], "--particles"),
        (["study", "consensus-robot", "--set", "steps=1e400", "--out", "{tmp}/c"], "steps"),
        (["study", "consensus-robot", "--set", "steps=nan", "--out", "{tmp}/c"], "steps"),
        (["study", "consensus-robot", "--schedule", "{garbage}", "--out", "{tmp}/c"], "schedule"),
        # the paper design's sigma = 0.1 breaks (28) at the first step of every run for a prior this wide
        (["study", "comparison", "{wide}", "--runs", "2", "--out", "{tmp}/c"], "consensus EKF (paper design): sigma"),
        (["study", "consensus-robot", "{wide}", "--runs", "2", "--out", "{tmp}/c"], "(paper, tau=0.01): sigma"),
        # sizes no machine holds (petabytes): refused with the estimate before computing, not a MemoryError
        (["simulate", "{model}", "--steps", "100000000000000", "--out", "{tmp}/a.npz"], "steps = 100000000000000"),
        (["design", "{endless}", "--out", "{tmp}/d"], "steps = 1000000000000000"),
        (["feasibility", "{model}", "--grid", "dos=0:0.5:1000000000000", "--out", "{tmp}/f"], "--grid"),
        (["study", "comparison", "{endless}", "--runs", "2", "--out", "{tmp}/c"], "would need about"),
    ],
)
def test_bad_user_input_exits_2_before_computing(tmp_path, args, needle):
    """The cases of the review: model files, output paths, sizes, integers and files that are not what they say."""
    files = {"model": _MODEL, "many": _MODEL.replace("STEPS = 20", 'STEPS = "many"'),
             "raising": _MODEL.replace('    x = ca.SX.sym("x", 2)', '    raise RuntimeError("boom")'),
             "wide": _MODEL.replace("0.05 * np.eye(2)))", "25.0 * np.eye(2)))"),
             "endless": _MODEL.replace("STEPS = 20", "STEPS = 10**15")}
    paths = {}
    for name, text in files.items():
        paths[name] = tmp_path / f"{name}.py"
        paths[name].write_text(text)
    (tmp_path / "dir.npz").mkdir()
    garbage = tmp_path / "garbage"
    garbage.mkdir()
    (garbage / "schedule.json").write_text("{}")
    (garbage / "schedule.npz").write_bytes(b"garbage")
    paths.update(tmp=tmp_path, garbage=garbage)
    before = sorted(p.name for p in tmp_path.iterdir())
    r = run_cli(*[a.format(**paths) for a in args])
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in r.stderr, r.stderr
    assert sorted(p.name for p in tmp_path.iterdir() if p.name != "__pycache__") == before


def test_debug_shows_traceback():
    r = run_cli("--debug", "simulate", "indoor-robot", "--set", "process_var=-1", "--out", "x.npz")
    assert r.returncode == 2 and "Traceback" in r.stderr


def test_write_is_atomic_on_failure(tmp_path, monkeypatch):
    """A failure while writing leaves the old file intact and no temporary file behind."""
    from designer import fileio as io

    target = tmp_path / "keep.npz"
    assert main(["simulate", "indoor-robot", "--steps", "3", "--out", str(target)]) == 0
    before = target.read_bytes()

    def boom(fh, **arrays):
        fh.write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(io.np, "savez_compressed", boom)
    assert main(["simulate", "indoor-robot", "--steps", "4", "--out", str(target)]) == 1
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["keep.npz"]


def test_study_help_lists_every_registered_study():
    from studies.pipeline import STUDIES

    r = run_cli("study", "--help")
    assert r.returncode == 0
    text = " ".join(r.stdout.split())
    for name in STUDIES:
        assert name in text, name
