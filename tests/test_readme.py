"""The README stays true: its two set-up commands are what CI runs, its model example is the shipped one, its
design script and its SPEC example run."""
from __future__ import annotations

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _blocks(lang: str) -> list[str]:
    text = (ROOT / "README.md").read_text()
    return re.findall(rf"```{lang}\n(.*?)```", text, flags=re.S)


def test_setup_commands_are_the_ones_ci_runs():
    bash = [b.strip() for b in _blocks("bash")]
    assert len(bash) == 2, "the README keeps exactly two set-up commands"
    ci = (ROOT / ".ci" / "run").read_text()
    for cmd in bash:
        assert "\n" not in cmd and cmd in ci.splitlines(), cmd
    assert "pytest" in bash[1] and "cfdesign" in bash[0]


def test_model_example_is_the_shipped_example_and_builds():
    code = _blocks("python")[0]
    shipped = (ROOT / "examples" / "ring_model.py").read_text()
    assert code.strip() in shipped
    namespace: dict = {}
    exec(compile(code, "README", "exec"), namespace)
    m = namespace["model"]()
    assert m.n_x == 2 and m.n_sensors == 4 and namespace["NETWORK"].n_nodes == 4


def test_design_script_and_spec_example_run(tmp_path, monkeypatch):
    """The README's script on its model file, in a fresh directory, as a reader would run them."""
    import numpy as np

    model, script, spec = _blocks("python")
    (tmp_path / "ring.py").write_text(model)
    (tmp_path / "scalar.py").write_text(spec)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(script, "README script", "exec"), namespace)
    d, m, c = namespace["d"], namespace["m"], namespace["c"]
    assert d.trace_bound.shape == (4, 60) and m.feasible.shape == (6, 6)
    assert {"consensus", "local", "particle", "EKF"} == {f["family"] for f in c.filters.values()}
    for out in ("ring-design", "ring-map", "ring-compare"):
        assert (tmp_path / out / "report.html").is_file()
    from studies.cli import main

    assert main(["design", "scalar.py", "--set", "gain=0.8", "--set", "dos=0.3", "--out", "d"]) in (0, 1)
    assert json.loads((tmp_path / "d" / "schedule.json").read_text())["params"]["gain"] == 0.8
    assert np.isfinite(json.loads((tmp_path / "d" / "schedule.json").read_text())["epsilon"])
