"""Start-up: what the command line imports before it knows which command runs, and what it needs to list.

Timings are the benchmark's (``benchmarks/bench_startup.py``); these tests guard the structure that makes
start-up fast: the heavy packages are imported where they are used, not when the command line loads.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("casadi", "cvxpy", "numba", "matplotlib", "scipy.stats", "scipy.optimize", "scipy.signal", "control",
         "clarabel")


def _loaded(code: str) -> set[str]:
    """The modules a fresh interpreter holds after ``code``."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys, json; print(json.dumps(sorted(sys.modules)))"],
                         capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    return set(json.loads(out.stdout.splitlines()[-1]))


def _heavy(modules: set[str]) -> list[str]:
    return sorted(h for h in HEAVY if h in modules)


def test_the_command_line_loads_without_the_heavy_packages():
    assert _heavy(_loaded("import studies.cli")) == []
    assert _heavy(_loaded("import studies, designer, filters")) == []


def test_listing_the_scenarios_builds_no_model():
    """``cfdesign scenarios`` needs the built-ins' parameters and outlines, not their CasADi models."""
    mods = _loaded("from studies.api import list_scenarios; list_scenarios()")
    assert _heavy(mods) == [] and "scipy" not in mods


def test_the_public_names_import_on_first_use():
    """``from designer import Model`` as a model file does; ``designer.simulate`` is the function."""
    mods = _loaded("import designer\nassert callable(designer.simulate) and designer.simulate.__name__ == 'simulate'\n"
                   "import designer.simulate\nassert callable(designer.simulate)\n"
                   "from designer import Model, Sensor, Gaussian, AttackSpec, SensorNetwork, DesignOptions\n"
                   "assert Model.__module__ == 'designer.model'\n"
                   "import designer as d; assert d.noise.Gaussian is Gaussian and 'Model' in dir(d)\n"
                   "from designer import *\n"
                   "import studies; assert callable(studies.design) and callable(studies.feasibility)")
    assert "casadi" in mods  # Model imports it: a model file needs it anyway


def test_every_public_name_resolves():
    import designer

    for name in designer.__all__:
        assert getattr(designer, name) is not None
    with pytest.raises(AttributeError):
        designer.no_such_name  # noqa: B018


def test_help_lists_every_command():
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-m", "studies", "--help"], capture_output=True, text=True, env=env, cwd=ROOT,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    for command in ("scenarios", "simulate", "design", "feasibility", "study", "report"):
        assert command in r.stdout
    r = subprocess.run([sys.executable, "-m", "studies", "feasibility", "--help"], capture_output=True, text=True,
                       env=env, cwd=ROOT, timeout=120)
    assert r.returncode == 0 and "--grid" in r.stdout and "--workers" in r.stdout


def test_outlines_are_what_the_builds_give():
    """A built-in's outline (what ``cfdesign scenarios`` shows without building the model) is the built scenario's
    state dimension, sensor count, horizon and assumptions, at the defaults and with parameters set."""
    from studies.scenarios import SCENARIOS
    from studies.scenarios.base import Outline

    overrides = {
        "indoor-robot": {"camera_positions": [[0.6, 0.6], [1.2, 1.2], [1.8, 1.8], [2.4, 1.2]],
                         "edges": [[0, 1], [1, 2], [2, 3]], "x0": [0.5, 0.7, 0.1], "steps": 12, "process_var": 0.01},
        "target-range-bearing": {"sensor_positions": [[0, 10], [0, 30], [0, 50]], "edges": [[0, 1], [1, 2]],
                                 "rr_start": 2, "steps": 20},
        "target-binary-energy": {"sensor_positions": [[10, 10], [30, 30]], "steps": 7},
        "four-tank": {"substeps": 3, "plant_noise": True, "steps": 9},
        "switching-2d": {"steps": 11},
    }
    for name, spec in SCENARIOS.items():
        assert spec.outline is not None, name
        for values in ({}, overrides[name]):
            sc = spec.build(values)
            built = Outline(sc.model.n_x, sc.model.n_sensors, sc.steps, tuple(sc.assumptions))
            assert spec.outlined(values) == built, (name, values)


def _interruptible():  # pragma: no cover - runs in the child
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.parametrize("delay", [0.2, 0.5, 1.0, 2.5])
def test_ctrl_c_while_starting_is_one_line_and_exit_130(tmp_path, delay):
    """A Ctrl-C while the model layer is being imported (now inside the command) or while computing."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.Popen([sys.executable, "-m", "studies", "design", "indoor-robot", "--mode", "tuned", "--out",
                          str(tmp_path / "d")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                         cwd=ROOT, preexec_fn=_interruptible)
    time.sleep(delay)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=120)
    if p.returncode == 0 or (p.returncode == 1 and err.startswith("cfdesign: failed: design not certified")):
        return  # finished before the signal (the tuned robot design is not certified: exit 1): nothing to check
    if p.returncode == -signal.SIGINT:  # before Python set up its handler (a loaded machine): killed, silent
        assert err == ""
        return
    assert p.returncode == 130, (p.returncode, err)
    assert err == "cfdesign: interrupted\n", err


@pytest.mark.parametrize("command", [["scenarios"], ["design", "nowhere.py"]])
def test_a_ctrl_c_after_the_command_ended_keeps_its_exit_code(command):
    """A Ctrl-C that arrives while the interpreter shuts down (the command has printed its outcome) neither kills
    the process by the signal nor prints a traceback: the exit code is the command's.  The signal is sent from an
    atexit handler, which runs during the shutdown."""
    code = ("import atexit, os, signal, sys\n"
            "atexit.register(lambda: os.kill(os.getpid(), signal.SIGINT))\n"
            f"sys.argv = ['cfdesign'] + {command!r}\n"
            "from studies.launch import run\nrun()\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, timeout=120,
                       preexec_fn=_interruptible)
    expected = 0 if command == ["scenarios"] else 2
    assert p.returncode == expected, (p.returncode, p.stderr)
    assert "Traceback" not in p.stderr and "KeyboardInterrupt" not in p.stderr, p.stderr


SWALLOWED = """
import os, signal, sys, time
import studies.api
from designer.validation import ComputationError

class Dropped:
    def __del__(self):
        raise KeyboardInterrupt  # Python reports it as "Exception ignored" and goes on (as in a C callback)

def design(*args, **kwargs):
    if {how!r} == "swallowed":
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.5)  # the signal is handled here
        except KeyboardInterrupt:  # a library's bare except
            pass
    else:
        Dropped()
    raise ComputationError("design not certified: what the command would have said next")

studies.api.design = design
sys.argv = ["cfdesign", "design", "indoor-robot", "--out", {out!r}]
from studies.launch import run
run()
"""


@pytest.mark.parametrize("how", ["swallowed", "dropped"])
def test_a_ctrl_c_that_a_library_swallows_still_ends_the_command_as_interrupted(tmp_path, how):
    """A Ctrl-C caught by a library's bare ``except`` (CasADi's conversions) or raised in a callback whose exception
    Python drops ("Exception ignored": numba's LLVM cache notifications) does not let the command go on to another
    outcome: one line, exit 130."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, "-c", SWALLOWED.format(how=how, out=str(tmp_path / "d"))],
                       capture_output=True, text=True, env=env, cwd=ROOT, timeout=120, preexec_fn=_interruptible)
    assert (p.returncode, p.stderr) == (130, "cfdesign: interrupted\n")


def test_a_swallowed_ctrl_c_is_seen_by_every_enclosing_watch():
    """The command's watch encloses a study's Monte Carlo runner's: a Ctrl-C swallowed inside is seen by both (the
    runner discards its chunk, the command ends as interrupted), and each restores what it found."""
    from studies.interrupts import Interrupts

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers are set from the main thread")
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with Interrupts() as outer:
            with Interrupts() as inner:
                try:
                    signal.raise_signal(signal.SIGINT)
                except KeyboardInterrupt:  # a library's bare except
                    pass
            assert inner.seen and outer.seen
            with Interrupts() as later:
                pass
            assert not later.seen
            assert getattr(signal.getsignal(signal.SIGINT), "__self__", None) is outer
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        with pytest.raises(KeyboardInterrupt):
            outer.check()
    finally:
        signal.signal(signal.SIGINT, old)
