"""Stored results are those of the model's content: an edited model file, a helper module it imports or an
in-memory model with other numbers is never mistaken for the one the runs were computed with."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import studies
from designer import AttackSpec, Gaussian, Model, Sensor, SensorNetwork
from designer.digest import content_digest, source_files, source_files_digest
from designer.validation import InputError
from studies.cli import main
from studies.scenarios import load_scenario, reference

ROOT = Path(__file__).resolve().parents[1]

# a user's model file: a damped oscillator, its transition coefficient and sensor noise taken from a helper module
_MODEL = textwrap.dedent("""
    import casadi as ca
    import numpy as np
    from designer import AttackSpec, FDISignal, Gaussian, Model, SensorNetwork, Sensor
    from coeffs import DAMPING
    STEPS = 12
    X0 = [1.0, 0.0]
    NETWORK = SensorNetwork.from_edges(3, [(0, 1), (1, 2), (2, 0)])
    ATTACKS = AttackSpec(dos=0.1, fdi=0.1, signal=FDISignal(amplitude=0.2, components=(0,)))
    def model() -> Model:
        x = ca.SX.sym("x", 2)
        f = ca.vertcat(x[0] + 0.1 * x[1], x[1] - 0.1 * (ca.sin(x[0]) + DAMPING * x[1]))
        sensors = [Sensor(f"s{i}", np.cos(0.7 * i) * x[0] + np.sin(0.7 * i) * x[1], Gaussian.zero_mean([[0.05]]))
                   for i in range(3)]
        return Model("osc", x, f, sensors, process_noise=Gaussian.zero_mean(1e-3 * np.eye(2)),
                     prior=Gaussian(X0, 0.05 * np.eye(2)))
""")


def _write(folder: Path, damping="0.2", model=_MODEL) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "coeffs.py").write_text(f"DAMPING = {damping}\n")
    path = folder / "osc.py"
    path.write_text(model)
    return path


def _model(coefficient: float = 0.1, noise: float = 0.05, angles=()) -> Model:
    x = ca.SX.sym("x", 2)
    f = ca.vertcat(x[0] + coefficient * x[1], 0.9 * x[1])
    sensors = [Sensor("r", ca.vertcat(ca.sqrt(x[0] ** 2 + 1), ca.atan2(x[1], 2.0)),
                      Gaussian.zero_mean(np.diag([noise, 0.01])), angles=angles),
               Sensor("p", x[0], Gaussian.zero_mean([[noise]]))]
    return Model("in-memory", x, f, sensors, Gaussian.zero_mean(1e-3 * np.eye(2)), Gaussian([0.0, 1.0], np.eye(2)))


def test_content_digest_is_canonical_and_sees_every_bit():
    base = {"a": [1.0, 2], "b": np.arange(3.0), (0, 1): {"x": None}}
    same = {(0, 1): {"x": None}, "b": np.arange(3.0), "a": [1.0, 2]}  # another insertion order
    assert content_digest(base) == content_digest(same)
    changed = {**base, "a": [np.nextafter(1.0, 2.0), 2]}  # one ulp
    assert content_digest(changed) != content_digest(base)
    assert content_digest(np.arange(3.0)) != content_digest(np.arange(3.0, dtype=np.float32))
    assert content_digest(np.zeros((2, 3))) != content_digest(np.zeros((3, 2)))
    assert content_digest([1, 2]) != content_digest((1, 2)) != content_digest([1.0, 2.0])
    cyclic = []
    cyclic.append(cyclic)
    assert len(content_digest(cyclic)) == 64


def test_functions_are_digested_by_code_and_closure():
    def make(c):
        return lambda steps: np.full((steps, 1), c)

    assert content_digest(make(1.0)) == content_digest(make(1.0))
    assert content_digest(make(1.0)) != content_digest(make(2.0))  # a closure value
    assert content_digest(lambda s: s + 1) != content_digest(lambda s: s + 2)  # a constant of the code


def test_model_digest_follows_its_content():
    a, b = _model(), _model()
    assert a.digest == b.digest  # built twice: the same content
    assert _model(coefficient=0.1000001).digest != a.digest  # a coefficient of f
    assert _model(noise=0.0500001).digest != a.digest  # a noise
    assert _model(angles=(1,)).digest != a.digest  # the bearing declared an angle


def test_digests_are_the_same_in_fresh_processes(tmp_path):
    path = _write(tmp_path / "m")
    script = ("import sys; from studies.scenarios import load_scenario; sc = load_scenario(sys.argv[1]); "
              "print(sc.digest, sc.model.digest)")
    outs = set()
    for hashseed in ("1", "2"):
        env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONHASHSEED=hashseed)
        r = subprocess.run([sys.executable, "-c", script, str(path)], capture_output=True, text=True, env=env,
                           timeout=300, check=True)
        outs.add(r.stdout.strip())
    sc = load_scenario(str(path))
    assert outs == {f"{sc.digest} {sc.model.digest}"}


def test_a_model_files_digest_covers_its_bytes_and_local_imports_not_its_path(tmp_path):
    path = _write(tmp_path / "a")
    assert [p.name for p in source_files(path)] == ["coeffs.py", "osc.py"]
    first = load_scenario(str(path)).digest
    moved = _write(tmp_path / "b")  # the same files elsewhere
    assert load_scenario(str(moved)).digest == first
    _write(tmp_path / "a", damping="0.25")  # only the helper module changes
    assert load_scenario(str(path)).digest != first
    before = source_files_digest(path)
    path.write_text(_MODEL + "# a comment\n")
    assert source_files_digest(path) != before


def test_a_rebuilt_reference_must_be_the_planned_model(tmp_path, monkeypatch):
    path = _write(tmp_path / "m")
    ref = reference(load_scenario(str(path)))
    import studies.scenarios as scenarios

    monkeypatch.setattr(scenarios, "_BUILT", {})  # another process: rebuilt from the file
    assert ref.build().digest == ref.digest
    monkeypatch.setattr(scenarios, "_BUILT", {})
    _write(tmp_path / "m", damping="0.3")  # edited while the study runs
    with pytest.raises(InputError, match="changed after the study started"):
        ref.build()


@pytest.mark.slow
def test_an_edited_model_file_never_reuses_the_old_runs(tmp_path, capsys):
    """The issue's case: run, change a coefficient of f, run the same command: the old runs are refused (exit 2,
    the model named as what changed), and with --force the new model's numbers replace them."""
    path = _write(tmp_path / "m")
    for cmd, result in (
            (["study", "consensus-robot", str(path), "--runs", "2", "--quiet"], "results.json"),
            (["feasibility", str(path), "--mode", "tuned", "--grid", "dos=0:0.4:3", "--quiet"], "feasibility.csv")):
        out = tmp_path / cmd[0]
        cmd = cmd + ["--out", str(out)]
        path.write_text(_MODEL)
        assert main(cmd) == 0
        numbers = _numbers(out / result)
        assert main(cmd) == 0  # unchanged: reused, the same numbers
        assert _numbers(out / result) == numbers
        assert "0 chunks computed" in capsys.readouterr().out or cmd[0] == "feasibility"
        written = (out / result).read_bytes()
        path.write_text(_MODEL.replace("x[0] + 0.1 * x[1]", "x[0] + 0.11 * x[1]"))
        assert main(cmd) == 2
        err = capsys.readouterr().err
        assert "config.model" in err, err
        assert (out / result).read_bytes() == written  # refused: nothing replaced
        assert main(cmd + ["--force"]) == 0
        assert _numbers(out / result) != numbers  # the edited model's numbers


def _numbers(path: Path):
    """A study's filters' metrics, or a map's rows."""
    return json.loads(path.read_text())["filters"] if path.suffix == ".json" else path.read_text()


@pytest.mark.slow
def test_an_in_memory_model_with_other_numbers_is_refused_through_the_api(tmp_path):
    net = SensorNetwork.from_edges(2, [(0, 1)])
    kw = dict(runs=2, out=tmp_path / "c", network=net, attacks=AttackSpec(dos=0.1), quiet=True)
    first = studies.study("consensus-robot", _model(), **kw)
    again = studies.study("consensus-robot", _model(), **kw)  # the same content, built anew
    assert again.results["runner"]["chunks_reused"] >= 1
    assert again.filters == first.filters
    with pytest.raises(InputError, match="config.model"):
        studies.study("consensus-robot", _model(coefficient=0.2), **kw)
    other = studies.study("consensus-robot", _model(coefficient=0.2), **{**kw, "force": True})
    assert other.filters != first.filters


@pytest.mark.parametrize("name", ["target-range-bearing", "switching-2d", "target-binary-energy", "indoor-robot",
                                  "four-tank"])
def test_every_built_in_rebuilt_from_its_reference_is_the_same_scenario(name, monkeypatch):
    """What a worker process (or a Dask worker) rebuilds from the reference has the planned digest."""
    import studies.scenarios as scenarios

    sc = load_scenario(name)
    if sc.network is not None:
        sc = sc.with_attacks(dos=0.2)
    ref = reference(sc)
    monkeypatch.setattr(scenarios, "_BUILT", {})
    assert ref.build().digest == sc.digest


def test_a_model_file_has_one_digest_whatever_path_names_it(tmp_path, monkeypatch):
    """The same file, named by an absolute and by a relative path: the same content, the same digest (its known
    inputs included: their error messages name the file, not the path)."""
    from test_recorded import USER_MODEL  # noqa: E402 (tests/ is on the path: a user's model with inputs())

    (tmp_path / "cart.py").write_text(USER_MODEL)
    monkeypatch.chdir(tmp_path)
    relative, absolute = load_scenario("cart.py"), load_scenario(str(tmp_path / "cart.py"))
    assert relative.input_fn is not None and relative.digest == absolute.digest
