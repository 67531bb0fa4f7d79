"""The fused engine: bootstrap particle filters compiled with numba, one kernel call per Monte Carlo run.

The NumPy engine (:func:`filters.particle.run_sir`) runs every Monte Carlo run at once
as arrays of shape ``(runs, M, n_x)``, one NumPy call per operation.  This package runs
the same filters with one compiled call per run, each step fused over blocks of
particles, the model's functions and constants inlined as generated code:

* :mod:`~filters.fused.primitives` — branch-free scalar math (``exp``, angle wrapping, the normal CDF);
* :mod:`~filters.fused.resampling` — the schemes of :mod:`filters.resampling` (one registry), compiled;
* :mod:`~filters.fused.codegen` — a model's propagation, weights and likelihood pieces as source;
* :mod:`~filters.fused.driver` — the generic filter loop, threads over runs, the shared input checks;
* :mod:`~filters.fused.cache` — the code version and numba options; kernels compiled once per machine;
* one module per likelihood family, each beside its NumPy twin: :mod:`~filters.fused.packets`
  (seed 000, twin :mod:`filters.rrp`), :mod:`~filters.fused.binary` (seed 002, :mod:`filters.binary`),
  :mod:`~filters.fused.edpf` (seed 001, :mod:`filters.edpf`), :mod:`~filters.fused.sis` (seed 004's SIS
  filters for models with known inputs, :mod:`filters.fdi`).

Compiled once per machine: every generated kernel is written as a Python module into
``<cache>/kernels/`` and compiled with numba's on-disk cache, as is the generic code
(:mod:`designer.jitcache`; ``<cache>`` is ``$CFDESIGN_CACHE_DIR``, default
``~/.cache/cfdesign``).  A first run compiles (seconds per model), later processes load
the compiled code; a changed model, code version or numba compiles anew, and
``cfdesign cache clear`` (:func:`designer.jitcache.clear_cache`) empties the cache.
:func:`kernel_paths` gives the files of a model's kernels, to read them.

Randomness: one :class:`numpy.random.Generator` per run, drawn in the NumPy engine's
order, so a one-run call reproduces the NumPy engine with the same generator to
rounding (the tests check it); a run's result never depends on the number of threads.
Initial particles are sampled by the caller (``x0``, shape ``(runs, M, n_x)``, e.g.
``model.prior.sample(rngs[r], M)`` for each run), so any prior works.
"""
from __future__ import annotations

import importlib

# name -> the module that defines it: a study loads the likelihood family it runs, not all four (each
# family's NumPy twin pulls in its own dependencies: 1.5 s of imports for a study that needs one)
_WHERE = {"FastSIRResult": "driver", "kernel_paths": "codegen", "sir_packets": "packets", "packets_loglik": "packets",
          "sir_binary": "binary", "binary_affine_loglik": "binary", "sir_edpf": "edpf", "edpf_loglik": "edpf",
          "LIKELIHOODS": "edpf", "sis_fdi": "sis", "sis_particles": "sis", "SISParticles": "sis"}
__all__ = list(_WHERE)


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(importlib.import_module(f".{_WHERE[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
