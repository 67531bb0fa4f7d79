"""The README stays true: its two set-up commands are what CI runs, its model example is the shipped one, its
five-minute section runs as written (the shell block and the design script write the same numbers). The SPEC
example and the rest of the reference are in docs/ (tests/test_docs.py)."""
from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from studies.comparison import FILTERS

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README, flags=re.S)


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


def _files(d: Path) -> dict:
    """What the five-minute commands write, number by number: the simulated run, the design (JSON and arrays), the
    map (CSV and JSON) and the study's results; timings (and the cheapest filter, which follows from them) and the
    runner's bookkeeping left out (they differ by machine load and by whether the runs were stored already)."""
    import numpy as np

    def strip(v):
        if isinstance(v, dict):  # cheapest: by the timings; seconds: an automatic design's candidates'
            return {k: strip(x) for k, x in v.items()
                    if "time" not in k and "seconds" not in k and k not in ("runner", "versions", "cheapest")}
        if isinstance(v, list):
            return [strip(x) for x in v]
        return v

    out = {}
    for name in ("ring.npz", "ring-design/schedule.npz", "ring-kcf/estimates.npz", "ring-pick/estimates.npz",
                 "ring-relay/schedule.npz"):
        with np.load(d / name) as z:
            out[name] = {k: (z[k].dtype.str, z[k].shape, z[k].tobytes()) for k in z.files}
    for name in ("ring-map/feasibility.csv", "ring-run3.csv", "ring-kcf/estimates.csv", "ring-c/replay.txt",
                 "ring-c/cfd_node.c"):
        out[name] = (d / name).read_text()
    for name in ("ring-design/schedule.json", "ring-design/candidates.json", "ring-design/validation.json",
                 "ring-map/feasibility.json", "ring-compare/results.json"):
        out[name] = strip(json.loads((d / name).read_text()))
    return out


@pytest.mark.slow
def test_the_five_minute_section_runs_as_written_and_both_blocks_write_the_same_numbers(tmp_path, monkeypatch):
    """The model file, then the shell block as a reader runs it (the set-up's virtual environment activated, as
    the README says, in a shell where cfdesign is not on the PATH before), then the design script in the same
    directory: every block as written, in order, and the script's files hold the shell's numbers exactly."""
    model, script = _blocks("python")
    (shell,) = _blocks("sh")
    assert ". .venv/bin/activate" in README.split("```sh", 1)[0].rsplit("```", 1)[1]  # said before the block
    (tmp_path / "ring.py").write_text(model)
    bindir = Path(sys.executable).parent
    activate = bindir / "activate"
    assert (bindir / "cfdesign").is_file()  # the set-up command installs it beside this Python
    env = dict(os.environ)
    env.pop("VIRTUAL_ENV", None)
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep)
                                  if p and Path(p).resolve() != bindir.resolve())
    setup = (f". {shlex.quote(str(activate))}" if activate.is_file()  # the README's `. .venv/bin/activate`
             else f'export PATH={shlex.quote(str(bindir))}:"$PATH"')  # a venv without its scripts (not the README's)
    proc = subprocess.run(["bash", "-c", f"set -euo pipefail\n{setup}\n{shell}"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    shell_files = _files(tmp_path)
    for out in ("ring-design", "ring-map", "ring-compare"):
        assert (tmp_path / out / "report.html").is_file()
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(script, "README script", "exec"), namespace)
    d, m, c = namespace["d"], namespace["m"], namespace["c"]
    assert d.pick.trace_bound.shape == (4, 60) and m.feasible.shape == (6, 6) and m.verdict.shape == (6, 6)
    assert d.certified  # the automatic design's pick is certified (the shell block exits 0 on it)
    assert d.validation is not None and d.validation["runs"] == 20
    assert {"consensus", "local", "particle", "EKF"} == {f["family"] for f in c.filters.values()}
    k, t, node = namespace["k"], namespace["t"], namespace["node"]
    assert node.ball[0] == 0 and node.k == 1 and np.isfinite(node.x).all()
    assert k.x_hat.shape == (61, 4, 2) and t.name == d.gain_rule.study_label and t.verdict is not None
    # the log of run 3 filtered gives that run's KCF estimate in the study (node 1's, as the study keeps it)
    est = c.arrays[next(iter(c.arrays))]["estimate"]
    assert np.array_equal(k.x_hat[:, 0], est[3, FILTERS.index("KCF")])
    python_files = _files(tmp_path)
    assert python_files.keys() == shell_files.keys()
    for name in shell_files:
        assert python_files[name] == shell_files[name], name

