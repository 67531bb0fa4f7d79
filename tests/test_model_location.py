"""A model file works from any directory, the repository's root included: its siblings are imported under a
private name, never in place of cfdesign's own packages, the standard library or an installed package, and the
model's digest counts the same siblings the loader imports."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import textwrap
import uuid
from pathlib import Path

import numpy as np
import pytest

import designer
import studies.scenarios as scenarios
from designer.digest import is_local_module, source_files
from designer.validation import InputError
from studies.scenarios import load_scenario, reference

ROOT = Path(__file__).resolve().parents[1]


def _spec_example() -> str:
    """The documentation's SPEC model file (the README's, or the docs' page it moved to)."""
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        for block in re.findall(r"```python[^\n]*\n(.*?)```", page.read_text() if page.is_file() else "", flags=re.S):
            if "SPEC = ScenarioSpec(" in block and "def build" in block:
                return block
    raise AssertionError("no SPEC model file example in README.md or docs/")


EXAMPLES = {"spec": _spec_example(), "model": (ROOT / "examples" / "ring_model.py").read_text()}


def _cfdesign(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """The console script as a user runs it (this tree's packages first), from ``cwd``."""
    script = shutil.which("cfdesign", path=str(Path(sys.executable).parent))
    cmd = [script] if script else [sys.executable, "-m", "studies"]
    env = dict(os.environ, PYTHONPATH=str(ROOT), MPLBACKEND="Agg")
    return subprocess.run([*cmd, *args], capture_output=True, text=True, env=env, cwd=cwd, timeout=300)


def _uses_the_installed_classes(sc) -> None:
    assert type(sc.model) is designer.Model
    assert type(sc.network) is designer.SensorNetwork and type(sc.attacks) is designer.AttackSpec


@pytest.mark.parametrize("example", sorted(EXAMPLES))
def test_a_model_file_beside_a_foreign_designer_package(tmp_path, example):
    fake = tmp_path / "designer"
    fake.mkdir()
    (fake / "__init__.py").write_text("raise ImportError('the designer/ beside the model file was imported')\n")
    path = tmp_path / "m.py"
    path.write_text(EXAMPLES[example])
    assert not is_local_module("designer", tmp_path)
    assert source_files(path) == [path.resolve()]  # the foreign package is no part of the model
    sc = load_scenario(str(path))
    _uses_the_installed_classes(sc)
    (fake / "__init__.py").write_text("SensorNetwork = None\n")
    assert load_scenario(str(path)).digest == sc.digest
    r = _cfdesign("simulate", "m.py", "--steps", "4", "--seed", "1", "--out", "run.npz", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert np.load(tmp_path / "run.npz")["x"].shape[0] == 5
    assert not (tmp_path / "__pycache__").exists() and not (fake / "__pycache__").exists()  # nothing written there


@pytest.mark.parametrize("example", sorted(EXAMPLES))
def test_a_model_file_in_the_repository_root(tmp_path, example):
    path = ROOT / f"cfd_location_test_{uuid.uuid4().hex[:12]}.py"  # where set-up leaves a new user
    try:
        path.write_text(EXAMPLES[example])
        assert source_files(path) == [path.resolve()]  # the repository's packages are not the model's files
        sc = load_scenario(str(path))
        _uses_the_installed_classes(sc)
        assert type(reference(sc).build()) is scenarios.Scenario
        r = _cfdesign("simulate", f"./{path.name}", "--steps", "4", "--seed", "1", "--out", str(tmp_path / "r.npz"),
                      cwd=ROOT)
        assert r.returncode == 0, r.stderr
        assert (tmp_path / "r.npz").is_file()
    finally:
        path.unlink(missing_ok=True)


# a SPEC model file that takes its numbers from a sibling module and from a sibling package with a relative import
_HELPED = EXAMPLES["spec"].replace(
    "from studies.scenarios import Param, Scenario, ScenarioSpec",
    "from studies.scenarios import Param, Scenario, ScenarioSpec\nimport my_helpers\nfrom helpers.geometry import EDGES"
).replace("[(0, 1), (1, 2)]", "EDGES").replace("steps=30", "steps=my_helpers.STEPS").replace(
    "def build(p: dict) -> Scenario:\n",
    "def build(p: dict) -> Scenario:\n    from helpers.edges import RING  # when the scenario is built\n").replace(
    '("scalar: an example",)', '("scalar: an example", f"{len(RING)} edges")')


def _write_helped(folder: Path, steps: int) -> Path:
    (folder / "helpers").mkdir(parents=True, exist_ok=True)
    (folder / "my_helpers.py").write_text(f"STEPS = {steps}\n")
    (folder / "helpers" / "__init__.py").write_text("")
    (folder / "helpers" / "geometry.py").write_text("from .edges import RING as EDGES\n")
    (folder / "helpers" / "edges.py").write_text("RING = [(0, 1), (1, 2), (2, 0)]\n")
    path = folder / "helped.py"
    path.write_text(_HELPED)
    return path


def test_sibling_modules_are_imported_privately_and_read_again_after_an_edit(tmp_path, monkeypatch):
    assert "import my_helpers" in _HELPED and "steps=my_helpers.STEPS" in _HELPED and "EDGES)" in _HELPED
    assert "    from helpers.edges import RING" in _HELPED and "len(RING)" in _HELPED
    path = _write_helped(tmp_path, 7)
    assert [str(f.relative_to(tmp_path)) for f in source_files(path)] == [
        "helped.py", "helpers/__init__.py", "helpers/edges.py", "helpers/geometry.py", "my_helpers.py"]
    sc = load_scenario(str(path))
    _uses_the_installed_classes(sc)
    assert sc.steps == 7 and len(sc.network.edges) == 3 and "3 edges" in sc.assumptions
    assert not {"my_helpers", "helpers", "helpers.geometry"} & set(sys.modules)  # never under their plain names
    assert [m for m in sys.modules if m.endswith(".my_helpers")] == [
        m for m in sys.modules if m.startswith("cfdesign_user_") and m.endswith(".my_helpers")]
    (tmp_path / "my_helpers.py").write_text("STEPS = 9\n")  # an edited helper is read again
    edited = load_scenario(str(path))
    assert edited.steps == 9 and edited.digest != sc.digest
    monkeypatch.setattr(scenarios, "_BUILT", {})  # another process: rebuilt from the files
    assert reference(edited).build().digest == edited.digest
    assert not (tmp_path / "__pycache__").exists() and not (tmp_path / "helpers" / "__pycache__").exists()
    (tmp_path / "helpers" / "geometry.py").write_text("from .edges import RINGS as EDGES\n")
    with pytest.raises(InputError, match=r"cannot import name 'RINGS' from 'helpers\.edges'") as err:
        load_scenario(str(path))
    assert "cfdesign_user" not in str(err.value)  # the sibling by the name the file gives it


def test_a_sibling_named_like_a_standard_or_installed_module_does_not_shadow_it(tmp_path):
    model = tmp_path / "model"
    model.mkdir()
    for name in ("colorsys", "numpy", "casadi"):  # colorsys: standard, imported by nothing before the model
        (model / f"{name}.py").write_text("SHADOW = True\n")
    path = model / "m.py"
    path.write_text("import colorsys\nassert not hasattr(colorsys, 'SHADOW'), 'the sibling colorsys.py'\n"
                    + EXAMPLES["model"])
    assert source_files(path) == [path.resolve()]
    script = textwrap.dedent("""
        import sys
        assert "colorsys" not in sys.modules  # so a sibling could take its place
        from studies.scenarios import load_scenario
        sc = load_scenario(sys.argv[1])
        import colorsys, numpy, casadi
        assert not any(hasattr(m, "SHADOW") for m in (colorsys, numpy, casadi)), "shadowed"
        print(sc.model.n_x)
    """)
    env = dict(os.environ, PYTHONPATH=str(ROOT), MPLBACKEND="Agg")
    r = subprocess.run([sys.executable, "-c", script, str(path)], capture_output=True, text=True, env=env,
                       cwd=tmp_path, timeout=300)  # not from the model's directory: there Python itself finds them
    assert r.returncode == 0 and r.stdout.strip() == "2", r.stderr
    r = _cfdesign("simulate", "m.py", "--steps", "3", "--seed", "1", "--out", "run.csv", cwd=model)
    assert r.returncode == 0, r.stderr
    assert (model / "run.csv").is_file()
