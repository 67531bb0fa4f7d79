"""The test session's compiled-kernel cache: never the user's.

Every test process (and every command a test starts, which inherits the environment)
compiles into ``$CFDESIGN_TEST_CACHE_DIR`` if set — a developer may keep one between
sessions so that the numba kernels compile once — or else into a fresh directory
removed at the end of the session (CI: a fresh machine compiles cold anyway).  With
pytest-xdist (``-n 2``) the worker processes share the directory their controller made
(they inherit its environment), so a kernel compiles once per session; the controller,
which ends after its workers, removes it.  Set at import, before any test module imports
the kernels.

The run prints a progress line (``progress_line``: tests done, failures, time) every 20 seconds;
``--progress-interval 0`` or ``CFDESIGN_TEST_PROGRESS=0`` turns it off.
"""
from __future__ import annotations

import os
import shutil
import tempfile

import pytest
from progress_line import pytest_addoption, pytest_configure  # noqa: F401  (the progress line's hooks)

_SHARED = "CFDESIGN_TEST_SESSION_CACHE"  # the controller's directory, seen by its xdist workers
_OWN = None
if os.environ.get("CFDESIGN_TEST_CACHE_DIR"):
    os.environ["CFDESIGN_CACHE_DIR"] = os.environ["CFDESIGN_TEST_CACHE_DIR"]
elif os.environ.get("PYTEST_XDIST_WORKER") and os.environ.get(_SHARED):
    os.environ["CFDESIGN_CACHE_DIR"] = os.environ[_SHARED]
else:
    _OWN = os.environ["CFDESIGN_CACHE_DIR"] = os.environ[_SHARED] = tempfile.mkdtemp(prefix="cfdesign-test-cache-")


def pytest_sessionfinish(session, exitstatus):
    if _OWN is not None:
        shutil.rmtree(_OWN, ignore_errors=True)


def file_tree(root) -> dict:
    """Every entry under ``root`` (links not followed): path -> the file's bytes, the link's target, or a dir; two
    trees compare equal when nothing under ``root`` was written, removed or changed."""
    from pathlib import Path

    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            out[str(p.relative_to(root))] = (("link", os.readlink(p)) if p.is_symlink() else ("dir",) if p.is_dir()
                                             else p.read_bytes())
    return out


def scalar_spec_model(*, gain: float = 0.9, noise: float = 0.05, steps: int = 12) -> str:
    """A model file defining ``SPEC``: a scalar state ``x+ = gain x`` watched by three sensors of variance ``noise``
    on a line network, DoS 0.1 and FDI 0.05 on every channel, ``steps`` steps."""
    return f'''
import casadi as ca

from designer import AttackSpec, FDISignal, Gaussian, Model, SensorNetwork, Sensor
from studies.scenarios import Param, Scenario, ScenarioSpec

NETWORK = SensorNetwork.from_edges(3, [(0, 1), (1, 2)])


def build(p: dict) -> Scenario:
    x = ca.SX.sym("x", 1)
    sensors = [Sensor(f"s{{i}}", x, Gaussian.zero_mean([[{noise!r}]])) for i in range(3)]
    m = Model("scalar", x, {gain!r} * x, sensors, Gaussian.zero_mean([[0.01]]), Gaussian([0.0], [[1.0]]))
    return Scenario("scalar", m, p, ("scalar: an example",), steps={steps}, network=NETWORK,
                    attacks=AttackSpec(dos=0.1, fdi=0.05, signal=FDISignal(0.2)))


SPEC = ScenarioSpec("scalar", "A scalar random walk watched by three sensors", "user", "an example", (), build)
'''


TANK_MODEL = '''
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
'''


@pytest.fixture
def tank_model(tmp_path):
    """A user's model file (a two-state tank on three nodes, STEPS = 20) written as ``tank.py`` in ``tmp_path``;
    ``tank_model(steps=K, name="other.py")`` writes another one with ``STEPS = K``."""
    def write(steps: int = 20, name: str = "tank.py"):
        path = tmp_path / name
        path.write_text(TANK_MODEL.replace("STEPS = 20", f"STEPS = {steps}"))
        return path

    return write
