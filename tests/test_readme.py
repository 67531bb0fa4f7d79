"""The README stays true: its two set-up commands are what CI runs, its model example is the shipped one."""
from __future__ import annotations

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
    (code,) = _blocks("python")
    shipped = (ROOT / "examples" / "pendulum_model.py").read_text()
    assert code.strip() in shipped
    namespace: dict = {}
    exec(compile(code, "README", "exec"), namespace)
    m = namespace["model"]()
    assert m.n_x == 2 and m.n_sensors == 2 and m.n_z == 3
