"""The on-disk cache of compiled kernels (:mod:`designer.jitcache`): compiled once per machine.

Processes are real processes here (``subprocess``): what is cached must serve the
*next* process.  Whether a process compiled or loaded is read from the cache itself: a
compile writes numba's index and data files, a load leaves them untouched.  Every test
uses its own cache directory (``CFDESIGN_CACHE_DIR`` = a tmp dir), never the user's.
"""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from designer import Gaussian, Model, Sensor
from designer.jitcache import cache_dir, cached_njit, clear_cache, generated_module
from filters.fused import kernel_paths, sir_packets

ROOT = Path(__file__).resolve().parent.parent

# A generated kernel of the scalar translation: small, so that a cold process compiles it in about a second.
KERNEL = textwrap.dedent("""
    import sys
    from designer.jit import compile_source
    g = compile_source("def g(x):\\n    return _atan2(x, {c}) + _m.sin(x)\\n", "g", "test kernel")
    print(repr(g(0.5)), g.stats.cache_hits.total(), g.stats.cache_misses.total(), g.path)
""")


def _run(code: str, cache: Path, **env) -> str:
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600,
                         env={**os.environ, "CFDESIGN_CACHE_DIR": str(cache), **env})
    assert out.returncode == 0, out.stderr
    return out.stdout


def _compiled(cache: Path) -> dict:
    """numba's files in the cache: name -> modification time (a compile writes them, a load does not)."""
    return {p.name: p.stat().st_mtime_ns for p in (cache / "numba").rglob("*") if p.is_file()}


def test_a_second_process_loads_the_kernel_instead_of_compiling(tmp_path):
    first = _run(KERNEL.format(c=1.0), tmp_path).split()
    assert first[1:3] == ["0", "1"]  # compiled (a cache miss)
    files = _compiled(tmp_path)
    assert any(n.endswith(".nbi") for n in files) and any(n.endswith(".nbc") for n in files)
    second = _run(KERNEL.format(c=1.0), tmp_path).split()
    assert second[1:3] == ["1", "0"]  # loaded
    assert second[0] == first[0] and second[3] == first[3]
    assert _compiled(tmp_path) == files  # nothing written again
    path = Path(first[3])
    assert path.parent == tmp_path / "kernels" and "def g(x):" in path.read_text()


@pytest.mark.slow
def test_a_changed_kernel_is_a_new_cache_entry(tmp_path):
    a = _run(KERNEL.format(c=1.0), tmp_path).split()
    b = _run(KERNEL.format(c=2.0), tmp_path).split()
    assert b[1:3] == ["0", "1"] and a[3] != b[3] and a[0] != b[0]
    assert len(list((tmp_path / "kernels").glob("*.py"))) == 2


@pytest.mark.slow
def test_a_changed_generator_version_recompiles(tmp_path):
    a = _run(KERNEL.format(c=1.0), tmp_path).split()
    # the code version of the translation's own files is part of every generated module's text
    bumped = "import designer.jit as j; j._STAMP = 'another version'\n" + KERNEL.format(c=1.0)
    b = _run(bumped, tmp_path).split()
    assert b[1:3] == ["0", "1"] and a[3] != b[3] and a[0] == b[0]


def test_cached_njit_is_valid_for_its_stamp_only(tmp_path, monkeypatch):
    monkeypatch.setenv("CFDESIGN_CACHE_DIR", str(tmp_path / "cache"))
    mod = generated_module("def twice(x):\n    return 2.0 * x\n", "stamp test", stamp="s")

    def compiled(stamp):
        f = cached_njit(stamp)(mod.twice)
        assert f(1.5) == 3.0
        return f.stats.cache_hits.total(), f.stats.cache_misses.total()

    assert compiled("one") == (0, 1)
    assert compiled("one") == (1, 0)  # a new dispatcher loads what the first one saved
    assert compiled("two") == (0, 1)  # another stamp: numba's index of the function is not used


@pytest.mark.slow
def test_two_processes_compiling_the_same_kernel_at_once_both_succeed(tmp_path):
    env = {**os.environ, "CFDESIGN_CACHE_DIR": str(tmp_path)}
    procs = [subprocess.Popen([sys.executable, "-c", KERNEL.format(c=3.0)], cwd=ROOT, env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE) for _ in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [e for _, e in outs]
    values = {o.split()[0] for o, _ in outs}
    assert len(values) == 1
    files = _compiled(tmp_path)
    third = _run(KERNEL.format(c=3.0), tmp_path).split()  # the cache they left is usable
    assert third[1:3] == ["1", "0"] and third[0] in values
    assert _compiled(tmp_path) == files
    assert not list(tmp_path.rglob("*.tmp"))  # no temporary file left behind


@pytest.mark.slow
def test_cache_clear_removes_the_kernels(tmp_path):
    _run(KERNEL.format(c=1.0), tmp_path)
    assert (tmp_path / "kernels").is_dir() and (tmp_path / "numba").is_dir()
    cli = [str(Path(sys.executable).with_name("cfdesign")), "cache", "clear"]
    env = {**os.environ, "CFDESIGN_CACHE_DIR": str(tmp_path)}
    out = subprocess.run(cli, capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    assert f"removed {tmp_path / 'kernels'}" in out.stdout and f"removed {tmp_path / 'numba'}" in out.stdout
    assert not (tmp_path / "kernels").exists() and not (tmp_path / "numba").exists()
    again = subprocess.run(cli, capture_output=True, text=True, env=env, timeout=300)
    assert again.returncode == 0 and "nothing to remove" in again.stdout
    assert _run(KERNEL.format(c=1.0), tmp_path).split()[1:3] == ["0", "1"]  # compiled anew


def test_clear_touches_only_a_directory_marked_as_the_cache(tmp_path, monkeypatch):
    (tmp_path / "kernels").mkdir()
    (tmp_path / "kernels" / "mine.txt").write_text("a user's file")
    monkeypatch.setenv("CFDESIGN_CACHE_DIR", str(tmp_path))
    assert clear_cache() == []
    assert (tmp_path / "kernels" / "mine.txt").exists()


def test_cache_dir_honours_the_variable_and_the_platform_default(tmp_path, monkeypatch):
    monkeypatch.setenv("CFDESIGN_CACHE_DIR", str(tmp_path / "here"))
    assert cache_dir() == tmp_path / "here"
    monkeypatch.delenv("CFDESIGN_CACHE_DIR")
    if sys.platform.startswith("linux"):
        monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
        assert cache_dir() == tmp_path / "xdg" / "cfdesign"
        monkeypatch.delenv("XDG_CACHE_HOME")
        assert cache_dir() == Path.home() / ".cache" / "cfdesign"


def _scalar_model(gain: float) -> Model:
    x = ca.SX.sym("x", 1)
    return Model("scalar", x, gain * x, [Sensor("s", x, Gaussian.zero_mean([[0.1]]))], Gaussian.zero_mean([[0.01]]),
                 Gaussian([0.0], [[1.0]]))


@pytest.mark.slow
def test_a_changed_model_gets_its_own_kernels_and_a_reader_finds_them():
    runs = []
    for gain in (0.9, 0.8, 0.9):
        m = _scalar_model(gain)
        g = np.random.default_rng(1)
        res = sir_packets(m, m.prior.sample(g, (1, 50)), [g], np.zeros(5, dtype=int), np.full((1, 5, 1), 0.2)).detail
        runs.append((kernel_paths(m), res.mean))
    (a, mean_a), (b, mean_b), (c, mean_c) = runs
    assert set(a) == set(b) == {"prop", "weigh", "('lik', ('packet', (), False))"}
    assert a["prop"] != b["prop"] and a["weigh"] == b["weigh"]  # f changed; the weights do not depend on it
    assert "0.9" in a["prop"].read_text() and "0.9" not in b["prop"].read_text()
    assert c == a and np.array_equal(mean_c, mean_a) and not np.array_equal(mean_a, mean_b)
    assert all(p.parent == cache_dir() / "kernels" for p in a.values())


@pytest.mark.slow
def test_a_fresh_process_runs_a_fused_filter_from_the_cache():
    """End to end: the generic driver and the model's kernels, loaded by a second process.

    In the test session's cache (tests/conftest.py), where the other tests may have
    compiled the driver already: what matters is that the second process compiles nothing.
    Each process counts numba's compile events (a kernel loaded from the cache raises none);
    the cache's files cannot tell, as another test worker sharing the session's cache
    (pytest -n 2) may add signatures of the same driver functions meanwhile.
    """
    cache = Path(os.environ["CFDESIGN_CACHE_DIR"])
    code = textwrap.dedent("""
        import numpy as np, casadi as ca
        from numba.core import event
        from designer import Gaussian, Model, Sensor
        from filters.fused import sir_packets
        compiled = []
        class Compiles(event.Listener):
            def on_start(self, ev):
                pass
            def on_end(self, ev):
                compiled.append(ev.data["dispatcher"].py_func.__name__)
        event.register("numba:compile", Compiles())
        x = ca.SX.sym("x", 2)
        m = Model("osc", x, ca.vertcat(x[0] + 0.1 * x[1], x[1] - 0.1 * ca.sin(x[0])),
                  [Sensor("s", ca.atan2(x[1], x[0] + 3.0), Gaussian.zero_mean([[0.01]]))],
                  Gaussian.zero_mean(1e-3 * np.eye(2)), Gaussian([1.0, 0.0], 0.1 * np.eye(2)))
        g = np.random.default_rng(3)
        res = sir_packets(m, m.prior.sample(g, (1, 64)), [g], np.zeros(8, dtype=int), np.full((1, 8, 1), 0.1)).detail
        print(repr(float(res.mean.sum())))
        print(" ".join(compiled))
        import sys
        print("numba.np.arraymath" in sys.modules)
    """)
    mean, first_compiled = (_run(code, cache) + "\n").split("\n")[:2]
    again, second_compiled, registries = (_run(code, cache) + "\n").split("\n")[:3]
    assert again == mean
    assert second_compiled == "", f"the second process compiled {second_compiled}"
    # nor did loading refresh numba's target context (importing all of numba's implementations: a quarter second),
    # on the numba versions where the loaded code is known to need none of it
    from designer import jitcache

    assert registries == str(not jitcache._LIGHT_LOAD)


@pytest.mark.slow
def test_processes_compiling_different_signatures_of_one_function_at_once_leave_a_correct_cache(tmp_path):
    """numba would number the data files in arrival order; ours are named by signature (designer.jitcache)."""
    code = textwrap.dedent("""
        import sys
        from designer.jit import compile_source
        g = compile_source("def g(x):\\n    return x * 3 + 1\\n", "g", "signatures")
        arg = {"f": 1.5, "i": 2, "c": 1j}[sys.argv[1]]
        print(repr(g(arg)))
    """)
    env = {**os.environ, "CFDESIGN_CACHE_DIR": str(tmp_path)}
    for _ in range(2):
        procs = [subprocess.Popen([sys.executable, "-c", code, a], cwd=ROOT, env=env, text=True,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE) for a in "fic"]
        outs = [p.communicate(timeout=600) for p in procs]
        assert [p.returncode for p in procs] == [0, 0, 0], [e for _, e in outs]
        assert [o.strip() for o, _ in outs] == ["5.5", "7", "(1+3j)"]
    assert len(list((tmp_path / "numba").rglob("*.nbc"))) == 3  # one data file per signature
