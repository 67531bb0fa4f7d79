"""How the fused engine compiles: its code version, its numba options, its kernels on disk.

Every numba function of :mod:`filters.fused` and every kernel it generates from a model
is compiled with numba's on-disk cache in :func:`designer.jitcache.cache_dir`
(``$CFDESIGN_CACHE_DIR``, default ``~/.cache/cfdesign``): compiled once per machine,
loaded by every later process.  :data:`STAMP`, the code version, hashes this package's
source files and the scalar translation's (:mod:`designer.jit`, :mod:`designer.codegen`,
:mod:`designer.jitcache`): numba tracks a function's own file only, and the kernels
inline code from all of them, so any change to one recompiles them all.
"""
from __future__ import annotations

from pathlib import Path

import designer.jit
from designer.jitcache import cached_njit, source_stamp

__all__ = ["STAMP", "NJIT", "FAST", "njit"]

_DESIGNER = Path(designer.jit.__file__).parent
#: The code version of the fused kernels (see the module notes).
STAMP = source_stamp([*sorted(Path(__file__).parent.glob("*.py")),
                      *(_DESIGNER / f for f in ("jit.py", "codegen.py", "jitcache.py"))])
#: numba options of every kernel: no GIL (runs spread over threads), x / 0 gives inf or NaN as in NumPy.
NJIT = dict(nogil=True, error_model="numpy")
#: Generated kernels may fuse ``a * b + c`` into one FMA (rounding only; no effect on inf/NaN handling).
FAST = {"contract"}


def njit(**options):
    """``numba.njit`` with :data:`NJIT` and ``options``, cached on disk for :data:`STAMP`."""
    return cached_njit(STAMP, **dict(NJIT, **options))
