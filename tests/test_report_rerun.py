"""Every report's "To compute ... again" line computes exactly its own results.

Each case runs a command with options that change the numbers (a model file of a new user's, written here, with
``--set`` parameters; design options such as ``--beta`` and ``--amplitude``; a study's own options; ``--engine``,
``--schedule``), reads the line from ``report.md`` as a reader would copy it, runs it (in-process, from another
directory) into a new directory and compares every number of the two results exactly.  The API and the command
line record the same line.  An in-memory model gets no line, and the report says why.
"""
from __future__ import annotations

import json
import math
import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from studies.cli import main

# A user's model with named parameters and a network (the README's SPEC example, smaller).
SCALAR = '''
import casadi as ca

from designer import AttackSpec, FDISignal, Gaussian, Model, SensorNetwork, Sensor
from studies.scenarios import Param, Scenario, ScenarioSpec

NETWORK = SensorNetwork.from_edges(3, [(0, 1), (1, 2)])


def build(p: dict) -> Scenario:
    x = ca.SX.sym("x", 1)
    sensors = [Sensor(f"s{i}", x, Gaussian.zero_mean([[p["noise"]]])) for i in range(3)]
    m = Model("scalar", x, p["gain"] * x, sensors, Gaussian.zero_mean([[0.01]]), Gaussian([0.0], [[1.0]]))
    return Scenario("scalar", m, p, ("scalar: an example",), steps=25, network=NETWORK,
                    attacks=AttackSpec(dos=p["dos"], fdi=0.05, signal=FDISignal(0.2)))


SPEC = ScenarioSpec("scalar", "A scalar random walk watched by three sensors", "user", "an example", (
    Param("gain", 0.9, "transition gain", low=0.0, high=1.0),
    Param("noise", 0.05, "measurement variance", low=0.0, low_open=True),
    Param("dos", 0.1, "DoS probability on every channel", low=0.0, high=1.0, high_open=True),
), build)
'''


def _line(report: Path) -> list[str]:
    """The command of the report's "To compute ... again" paragraph, as a list of arguments."""
    md = report.read_text()
    m = re.search(r"To compute this \w+ again, with the same numbers[^\n]*\n\n(`+) ?(.+?) ?\1\n", md)
    assert m, md[-1500:]
    argv = shlex.split(m.group(2))
    assert argv[0] == "cfdesign" and argv[-2:] == ["--out", "DIR"]
    return argv


def _rerun(argv: list[str], out: Path) -> int:
    return main([*argv[1:-1], str(out)])


def _is_time(key: str) -> bool:
    """Timings, and what follows from them (the cheapest filter), differ from one computation to the next."""
    return "time" in key or key in ("runner", "versions", "timing_s", "seconds", "cheapest")


def _numbers(v, path="$"):
    """Every number (and string) of a results file by its path, timings and the runner left out."""
    if isinstance(v, dict):
        out = {}
        for k, x in v.items():
            if not _is_time(str(k)):
                out.update(_numbers(x, f"{path}.{k}"))
        return out
    if isinstance(v, list):
        out = {}
        for i, x in enumerate(v):
            out.update(_numbers(x, f"{path}[{i}]"))
        return out
    return {path: v}


def _same(a: dict, b: dict) -> None:
    na, nb = _numbers(a), _numbers(b)
    assert na.keys() == nb.keys()
    differ = [k for k in na if not (na[k] == nb[k] or (isinstance(na[k], float) and math.isnan(na[k])
                                                       and isinstance(nb[k], float) and math.isnan(nb[k])))]
    assert differ == [], differ[:10]
    assert len(na) > 20  # the comparison has something to compare


@pytest.fixture
def user(tmp_path, monkeypatch):
    """A new user's directory with the model file, the working directory of the first command."""
    home = tmp_path / "home"
    home.mkdir()
    (home / "scalar.py").write_text(SCALAR)
    monkeypatch.chdir(home)
    return home


@pytest.mark.slow
def test_a_study_line_has_the_model_file_and_every_option_and_computes_the_same_numbers(user, tmp_path,
                                                                                       monkeypatch):
    first = ["study", "comparison", "scalar.py", "--runs", "2", "--particles", "20", "--seed", "5",
             "--beta", "0.05", "--amplitude", "0.15", "--set", "gain=0.8", "--set", "hcmci_iterations=2",
             "--set", "tuned_in_sweeps=false", "--set", "sweep_values=[0.1]", "--quiet", "--out", "a"]
    assert main(first) == 0
    argv = _line(user / "a" / "report.md")
    assert str(user / "scalar.py") in argv  # the model file, by a path that works from anywhere
    for opt in (["--beta", "0.05"], ["--amplitude", "0.15"], ["--set", "gain=0.8"], ["--set", "hcmci_iterations=2"],
                ["--runs", "2"], ["--particles", "20"], ["--seed", "5"]):
        assert any(argv[i:i + 2] == opt for i in range(len(argv))), opt
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert _rerun(argv, elsewhere / "b") == 0
    a = json.loads((user / "a" / "results.json").read_text())
    b = json.loads((elsewhere / "b" / "results.json").read_text())
    assert a["invocation"] == b["invocation"]
    _same(a, b)


@pytest.mark.slow
def test_a_particle_study_line_keeps_the_engine_and_a_builtin_parameter(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["study", "rrp-deception", "--runs", "2", "--particles", "30", "--engine", "numpy", "--set",
                 "deception_prob=0.3", "--set", "steps=40", "--set", "sweep=[0.3]", "--quiet", "--out", "a"]) == 0
    argv = _line(tmp_path / "a" / "report.md")
    assert argv[:3] == ["cfdesign", "study", "rrp-deception"]
    assert "--engine" in argv and {"deception_prob=0.3", "steps=40"} <= set(argv)
    assert not any(a.startswith("period=") for a in argv)  # parameters at their defaults are left out
    assert _rerun(argv, tmp_path / "b") == 0
    _same(json.loads((tmp_path / "a" / "results.json").read_text()),
          json.loads((tmp_path / "b" / "results.json").read_text()))


@pytest.mark.slow
def test_design_and_map_lines_compute_the_same_numbers(user, tmp_path, monkeypatch):
    assert main(["design", "scalar.py", "--mode", "paper", "--beta", "0.05", "--sigma", "0.05", "--steps", "12",
                 "--seed", "3",
                 "--set", "noise=0.1", "--out", "d"]) in (0, 1)
    assert main(["feasibility", "scalar.py", "--grid", "dos=0:0.5:6", "--u-scale", "0", "--set", "gain=0.7",
                 "--quiet", "--out", "f"]) == 0
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    d = _line(user / "d" / "report.md")
    assert {"--beta", "--sigma", "--steps", "--seed", "noise=0.1"} <= set(d)
    assert _rerun(d, elsewhere / "d") in (0, 1)
    a, b = (json.loads((p / "schedule.json").read_text()) for p in (user / "d", elsewhere / "d"))
    _same(a, b)
    with np.load(user / "d" / "schedule.npz") as za, np.load(elsewhere / "d" / "schedule.npz") as zb:
        assert za.files == zb.files
        for k in za.files:
            assert za[k].tobytes() == zb[k].tobytes(), k
    assert [ln.split(",", 1)[0] for ln in (user / "f" / "feasibility.csv").read_text().splitlines()] == [
        "dos", "0.0", "0.1", "0.2", "0.3", "0.4", "0.5"]  # as given (numpy.linspace: 0.30000000000000004)
    f = _line(user / "f" / "report.md")
    assert {"--grid", "dos=0:0.5:6", "--u-scale", "gain=0.7"} <= set(f)
    assert _rerun(f, elsewhere / "f") == 0
    assert (user / "f" / "feasibility.csv").read_bytes() == (elsewhere / "f" / "feasibility.csv").read_bytes()
    _same(*(json.loads((p / "feasibility.json").read_text()) for p in (user / "f", elsewhere / "f")))


@pytest.mark.slow
def test_a_replayed_schedule_is_part_of_the_line(user, tmp_path, monkeypatch):
    assert main(["design", "scalar.py", "--mode", "paper", "--sigma", "0.05", "--beta", "0.05", "--out",
                 "sched"]) in (0, 1)
    assert main(["study", "consensus-robot", "scalar.py", "--runs", "2", "--schedule", "sched", "--set", "dos=0.2",
                 "--quiet", "--out", "a"]) == 0
    argv = _line(user / "a" / "report.md")
    i = argv.index("--schedule")
    assert argv[i + 1] == str(user / "sched") and "dos=0.2" in argv
    monkeypatch.chdir(tmp_path)
    assert _rerun(argv, tmp_path / "b") == 0
    _same(json.loads((user / "a" / "results.json").read_text()),
          json.loads((tmp_path / "b" / "results.json").read_text()))


@pytest.mark.slow
def test_the_api_records_the_line_the_command_line_records(user):
    import studies

    d = studies.design("scalar.py", mode="paper", beta=0.05, sigma=0.05, steps=12, seed=3, overrides={"noise": 0.1},
                       out="api-d")
    assert main(["design", "scalar.py", "--mode", "paper", "--beta", "0.05", "--sigma", "0.05", "--steps", "12",
                 "--seed", "3",
                 "--set", "noise=0.1", "--out", "cli-d"]) in (0, 1)
    api = json.loads((user / "api-d" / "schedule.json").read_text())["invocation"]
    cli = json.loads((user / "cli-d" / "schedule.json").read_text())["invocation"]
    assert api == cli and api["argv"] and d.schedule is not None


def test_an_in_memory_model_has_no_line_and_the_report_says_why(tmp_path):
    import studies
    from studies.scenarios import load_scenario

    (tmp_path / "scalar.py").write_text(SCALAR)
    sc = load_scenario(str(tmp_path / "scalar.py"))
    studies.design(sc.model, network=sc.network, attacks=sc.attacks, sigma=0.05, beta=0.05, steps=5,
                   out=tmp_path / "d")
    meta = json.loads((tmp_path / "d" / "schedule.json").read_text())
    assert meta["invocation"]["argv"] is None and "in-memory" in meta["invocation"]["note"]
    md = (tmp_path / "d" / "report.md").read_text()
    assert "No command line computes this design again: it ran on an in-memory model" in md
    assert "To compute this design again" not in md


def test_every_design_option_reaches_the_recorded_line_as_a_flag_the_commands_take():
    """Each field of DesignOptions, when set, appears on the recorded line as a flag ``design`` and ``study`` accept
    (a new option without its flag made every study given it fail with an internal error)."""
    from dataclasses import fields

    from designer.design import DesignOptions
    from studies.cli import cli
    from studies.invocation import design_invocation
    from studies.scenarios import load_scenario

    sc = load_scenario("indoor-robot")
    paper = DesignOptions(mode="paper", epsilon=0.1, sigma=0.2, beta=0.3, tau=0.01, u_scale=0.5, v_scale=0.5,
                          linearization="hessian", radius=2.0, dos=0.1, fdi=0.1, delta=1.0, amplitude=1.0,
                          gate=0.01)
    scheduled = DesignOptions(mode="scheduled", exchange="predictions", robustness=0.5, rounds=2, bank=1,
                              table_kind="stationary")
    relay = DesignOptions(mode="relay", rounds=2, carry="whole")
    given = {f.name for o in (paper, scheduled, relay) for f in fields(o) if getattr(o, f.name) is not None}
    assert given == {f.name for f in fields(DesignOptions)}  # the three sets together set every option
    lines = [design_invocation(sc, o, steps=None, seed=0)["argv"] for o in (paper, scheduled, relay)]
    flags = {a for line in lines for a in line if a.startswith("--")}
    for command in ("design", "study"):
        taken = {o for p in cli.commands[command].params for o in p.opts}
        assert flags - {"--seed"} <= taken, (command, flags - taken)
    for f in fields(DesignOptions):
        assert "--" + f.name.replace("_", "-") in flags, f.name
    for line in lines:  # and the commands read the recorded values back (an integer option as '2', not '2.0')
        ctx = cli.commands["design"].make_context("design", [*line[2:], "--out", "unused"])
        assert ctx.params["rounds"] in (None, 2) and ctx.params["bank"] in (None, 1)
