"""Inputs and outputs never overlap: an output path equal to, inside or containing an input (a design directory, a
log, a model file and the modules it imports) is refused by every command that writes, with exit 2 and one line
naming both parameters, before anything is read, computed or written (designer.fileio.check_apart)."""
from __future__ import annotations

import os
import shutil

import pytest
from conftest import TANK_MODEL, file_tree

import studies
from designer.validation import InputError
from studies.cli import main

# the tank model reading its measurement noise from a package of its own directory (parts/noise.py)
MODEL = TANK_MODEL.replace("import numpy as np\n", "import numpy as np\nfrom parts.noise import VARIANCE\n", 1)
MODEL = MODEL.replace("Gaussian.zero_mean([[0.05]])", "Gaussian.zero_mean([[VARIANCE]])")


@pytest.fixture(scope="module")
def origin(tmp_path_factory):
    """A model file with a local package, a log of it and a design of it (written once)."""
    root = tmp_path_factory.mktemp("inputs")
    (root / "model" / "parts").mkdir(parents=True)
    (root / "model" / "tank.py").write_text(MODEL)
    (root / "model" / "parts" / "__init__.py").write_text("")
    (root / "model" / "parts" / "noise.py").write_text("VARIANCE = 0.05\n")
    studies.simulate(str(root / "model" / "tank.py"), steps=4, seed=1, out=root / "logs" / "log.npz")
    studies.design(str(root / "model" / "tank.py"), steps=4, out=root / "design")
    assert (root / "design" / "schedule.json").is_file()
    return root


@pytest.fixture
def work(origin, tmp_path, monkeypatch):
    """A fresh copy of the inputs as the current directory, with a link to the design directory (``linked``) and a
    hard link to the model file (``model/same.npz``)."""
    shutil.copytree(origin, tmp_path / "w")
    os.symlink("design", tmp_path / "w" / "linked")
    os.link(tmp_path / "w" / "model" / "tank.py", tmp_path / "w" / "model" / "same.npz")
    monkeypatch.chdir(tmp_path / "w")
    return tmp_path / "w"


FILTER = ["filter", "model/tank.py", "--data", "logs/log.npz"]
CASES = {
    "filter-out-is-schedule": ([*FILTER, "--schedule", "design", "--out", "design"],
                               "out 'design' is the design directory given as schedule"),
    "filter-out-inside-schedule": ([*FILTER, "--schedule", "design", "--out", "design/estimates"],
                                   "is inside the design directory given as schedule ('design')"),
    "filter-out-is-schedule-through-dots": ([*FILTER, "--schedule", "design", "--out", "logs/../design"],
                                            "is the design directory given as schedule"),
    "filter-out-is-schedule-through-a-link": ([*FILTER, "--schedule", "design", "--out", "linked"],
                                              "is the design directory given as schedule"),
    "filter-out-contains-log": ([*FILTER, "--filter", "kcf", "--out", "logs"],
                                "contains the log given as data ('logs/log.npz')"),
    "filter-out-contains-model": ([*FILTER, "--filter", "kcf", "--out", "model"],
                                  "contains the model file given as scenario"),
    "export-out-is-design": (["export", "design", "--out", "design"],
                             "out 'design' is the design directory given as design_dir"),
    "export-out-inside-design": (["export", "linked", "--out", "design/c"],
                                 "is inside the design directory given as design_dir"),
    "export-out-contains-log": (["export", "design", "--data", "logs/log.npz", "--out", "logs"],
                                "contains the log given as data"),
    "export-out-contains-module": (["export", "design", "--scenario", "model/tank.py", "--out", "model/parts"],
                                   "contains a module imported by the model file given as scenario"),
    "design-out-contains-model": (["design", "model/tank.py", "--steps", "2", "--out", "."],
                                  "contains the model file given as scenario"),
    "design-out-contains-module": (["design", "model/tank.py", "--steps", "2", "--out", "model/parts"],
                                   "contains a module imported by the model file given as scenario"),
    "simulate-out-is-model": (["simulate", "model/tank.py", "--steps", "2", "--out", "model/same.npz"],
                              "out 'model/same.npz' is the model file given as scenario"),
    "feasibility-out-contains-model": (["feasibility", "model/tank.py", "--grid", "dos=0:0.2:2", "--quiet", "--out",
                                        "model"], "contains the model file given as scenario"),
    "study-out-contains-model": (["study", "comparison", "model/tank.py", "--runs", "2", "--quiet", "--out", "model"],
                                 "contains the model file given as scenario"),
    "study-out-is-schedule": (["study", "consensus-robot", "--schedule", "design", "--runs", "2", "--quiet", "--out",
                               "design"], "out 'design' is the design directory given as schedule"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_an_out_that_overlaps_an_input_is_refused_and_nothing_changes(work, capsys, case):
    """Exit 2, one line naming out and the input's parameter; every file byte for byte as it was, none added."""
    args, needle = CASES[case]
    before = file_tree(work)
    assert main(args) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cfdesign: error: "), lines
    assert needle in lines[0] and lines[0].endswith("(nothing was written)"), lines[0]
    assert file_tree(work) == before


def test_an_out_beside_the_inputs_is_written(work, capsys):
    """The check refuses only overlaps: the same filter into a directory of its own runs, inputs unchanged."""
    before = file_tree(work)
    assert main([*FILTER, "--schedule", "design", "--out", "estimates"]) in (0, 1), capsys.readouterr().err
    assert (work / "estimates" / "estimates.npz").is_file()
    assert {k: v for k, v in file_tree(work).items() if not k.startswith("estimates")} == before


def test_the_api_and_the_results_save_refuse_an_overlapping_out(work):
    before = file_tree(work)
    with pytest.raises(InputError, match="out 'design' is the design directory given as schedule"):
        studies.filter("model/tank.py", "logs/log.npz", schedule="design", out="design")
    with pytest.raises(InputError, match="is inside the design directory given as design_dir"):
        studies.export(work / "design", out=work / "design" / "c")
    sim = studies.simulate("model/tank.py", steps=2)
    with pytest.raises(InputError, match="is the model file given as scenario"):
        sim.save("model/same.npz")
    run = studies.filter("model/tank.py", "logs/log.npz", schedule="design")
    with pytest.raises(InputError, match="out 'design' is the design directory given as schedule"):
        run.save("design")
    with pytest.raises(InputError, match="contains the log given as data"):
        run.save("logs")
    assert file_tree(work) == before


def test_a_design_map_or_study_saved_over_its_model_is_refused(work):
    """Design.save, FeasibilityMap.save and StudyResult.save refuse a directory that is, lies inside or contains the
    model file or a module it imports, as the commands do; a directory apart is written."""
    before = file_tree(work)
    d = studies.design("model/tank.py", steps=4)
    m = studies.feasibility("model/tank.py", ["dos=0:0.2:2"], quiet=True)
    s = studies.study("consensus-robot", "model/tank.py", runs=2, quiet=True)
    for result in (d, m, s):
        with pytest.raises(InputError, match="contains the model file given as scenario"):
            result.save(".")
        with pytest.raises(InputError, match="contains a module imported by the model file"):
            result.save("model/parts")
    assert file_tree(work) == before
    d.save(work.parent / "apart")
    assert (work.parent / "apart" / "schedule.json").is_file()
