"""designer.cores and the stacked eigh that splits a stack over the cores (designer.bounds.eigh); the stacked inverse of
Cholesky factors (designer.bounds.lower_inverse)."""
from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from designer import cores
from designer.bounds import eigh, lower_inverse


def _stack(shape, seed=0):
    a = np.random.default_rng(seed).standard_normal(shape)
    return a @ np.swapaxes(a, -1, -2)


@pytest.mark.parametrize("shape", [(3, 5, 5), (200, 6, 6), (4, 50, 7, 7), (129, 24, 24)])
def test_eigh_of_a_stack_is_numpys_to_the_bit(shape):
    a = _stack(shape)
    lam, Q = eigh(a)
    ref_lam, ref_Q = np.linalg.eigh(a)
    assert lam.shape == ref_lam.shape and Q.shape == ref_Q.shape
    assert np.array_equal(lam, ref_lam) and np.array_equal(Q, ref_Q)


@pytest.mark.parametrize("shape", [(3, 5, 5), (2, 3, 15, 15), (4, 16, 16), (2, 2, 48, 48), (40, 40)])
def test_the_inverse_of_cholesky_factors_is_lower_triangular_and_the_same_bits_alone_or_stacked(shape):
    """lower_inverse (LAPACK's trtri from 16 rows, numpy's inv below) against numpy's inv to rounding, its strict
    upper triangle exactly zero, and each matrix alone giving the bits it gives in the stack."""
    m = shape[-1]
    L = np.linalg.cholesky(_stack(shape) + m * np.eye(m))
    Li = lower_inverse(L)
    ref = np.linalg.inv(L)
    assert Li.shape == L.shape and not np.triu(Li, 1).any()
    assert np.allclose(Li, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    assert np.allclose(Li @ L, np.eye(m), rtol=0, atol=1e-12)
    flat, one = L.reshape(-1, m, m), Li.reshape(-1, m, m)
    for k in range(flat.shape[0]):
        assert np.array_equal(lower_inverse(flat[k]), one[k])
    with pytest.raises(np.linalg.LinAlgError):
        lower_inverse(np.tril(np.ones((m, m))) - np.eye(m))


def _counted_eigh(monkeypatch, n_cores: int) -> list:
    """The sizes of the stacks numpy's eigh is called with, on ``n_cores`` cores."""
    calls = []
    real = np.linalg.eigh

    def counted(x):
        calls.append(x.shape[0])
        return real(x)

    monkeypatch.setattr(cores, "usable_cores", lambda: n_cores)
    monkeypatch.setattr(np.linalg, "eigh", counted)
    return calls


def test_eigh_splits_over_the_pool_when_there_are_cores(monkeypatch):
    calls = _counted_eigh(monkeypatch, 3)
    eigh(_stack((300, 4, 4)))
    assert sorted(calls) == [100, 100, 100]
    calls.clear()
    eigh(_stack((10, 4, 4)))  # a small stack: one call here
    assert calls == [10]


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork")
def test_a_forked_child_gets_its_own_pool():
    """The parent's pool has threads; a forked child's copy would have none and wait forever."""
    eigh(_stack((256, 8, 8)))  # the parent's pool exists now
    assert "numpy" in cores._POOLS or cores.usable_cores() < 2
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        import signal

        signal.alarm(60)
        ok = not cores._POOLS
        lam, _ = eigh(_stack((256, 8, 8)))
        ok = ok and np.array_equal(lam, np.linalg.eigh(_stack((256, 8, 8)))[0])
        sys.stdout.flush()
        os._exit(0 if ok else 1)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0


def test_eigh_splits_a_few_large_matrices_too(monkeypatch):
    # 28 matrices of 58 x 58 (a 28-node scheduled design's link gains) are worth two threads; 3 of 10 x 10 are not
    real = np.linalg.eigh
    calls = _counted_eigh(monkeypatch, 2)
    a = _stack((28, 58, 58))
    lam, Q = eigh(a)
    assert sorted(calls) == [14, 14]
    assert np.array_equal(lam, real(a)[0]) and np.array_equal(Q, real(a)[1])
    calls.clear()
    eigh(_stack((3, 10, 10)))
    assert calls == [3]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_the_allocator_keeps_freed_memory_so_temporaries_take_no_fresh_pages():
    """keep_freed_memory (set by one_blas_thread, which every public computation runs in): a filter's step on stacks of
    64 x 64 matrices over 2 runs and 64 nodes (4 MB each: products, a symmetrisation, inverses) repeated 30 times
    takes its temporaries' pages from the heap, not fresh from the kernel each time: a process that set it sees less
    than a quarter of the page faults of one that did not (measured: 2.6 against 32 thousand).  The numbers computed
    are the same bits."""
    import subprocess

    code = """
import hashlib, resource, sys, numpy as np
from designer import cores
if sys.argv[1] == "set":
    assert cores.keep_freed_memory() and cores.keep_freed_memory()  # once; again is a no-op
rng = np.random.default_rng(0)
P, F = rng.standard_normal((2, 64, 64, 64)), rng.standard_normal((2, 64, 64, 64))
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for i in range(30):
    Pp = F @ P @ np.swapaxes(F, -1, -2)
    Pp = 0.5 * (Pp + np.swapaxes(Pp, -1, -2))
    P = 1e-3 * (np.linalg.inv(Pp) + Pp)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before, hashlib.sha256(P.tobytes()).hexdigest())
"""
    out = {}
    for how in ("set", "default"):
        run = subprocess.run([sys.executable, "-c", code, how], capture_output=True, text=True, check=True,
                             env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
        faults, digest = run.stdout.split()
        out[how] = int(faults), digest
    if not cores.keep_freed_memory():
        pytest.skip("no glibc mallopt here")
    assert 4 * out["set"][0] < out["default"][0], out
    assert out["set"][1] == out["default"][1]
