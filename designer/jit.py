"""Translate a model's CasADi functions into scalar numba kernels (one particle per call).

:mod:`designer.codegen` walks the SX instruction list of a CasADi function and
emits vectorised NumPy, one array operation per instruction over all particles.
That is fast for large batches but allocates a temporary per instruction; a
particle filter that fuses propagation, likelihood and resampling over one
particle at a time wants the opposite shape: the same instructions as *scalar*
straight-line code, compiled with ``numba.njit(nogil=True)`` so that it can be
called from inside other compiled kernels (and from several threads at once).

:func:`jit_model` does that for a :class:`~designer.model.Model` and returns a
:class:`JitModel` whose compiled functions are

* ``f(x, k, out)`` — writes ``f(x, k)`` (``n_x`` values) into ``out``;
* ``h(i, x, k, out)`` — writes sensor ``i``'s ``h_i(x, k)`` into ``out[:dim_i]``;
* ``h_all(x, k, out)`` — writes every sensor's ``h_i`` stacked (``n_z`` values);

with ``x`` a 1-D float64 array of length ``n_x`` and ``k`` a float.  They are
numba dispatchers and may be passed as arguments to other ``njit`` functions
(numba specialises the caller on them).  The operations and their order are
those of CasADi's virtual machine (and of the NumPy translation), so the values
agree with ``model.f`` / ``model.h`` to rounding.

For the hottest loops, generating the kernel's source around
:func:`scalar_statements` is faster than calling these dispatchers: the
statements read ``X[m, j]`` (or a flat ``X[m * n_x + j]``) directly, write local
scalars, and the generated loop over many particles can be vectorised by LLVM
when it has no branch or call.  For that, ``atan2`` is translated to a
branch-free polynomial (``_atan2``, within about 2 ulp of libm's, C's values at
zeros, infinities and NaN) rather than a libm call; everything else maps to
numba's ``math`` functions.  Measured on the range-bearing bootstrap filter:
about 330 ns per particle-step through first-class dispatchers (with the noise
parameters in arrays), 80 with generated, inlined per-particle source and
constants, about 40 with the block loops of :mod:`filters.fused`.

:func:`jit_model` supports models **without known inputs and without switching
modes** and raises :class:`~designer.validation.InputError` for the others (the
fused kernels of :mod:`filters.fused` translate the inputs and modes themselves,
through :func:`scalar_statements`).  An SX operation that has no scalar
translation (e.g. ``erfinv``) raises :class:`~designer.codegen.UnsupportedOperation`
naming it.

Generated source is not compiled from memory: :func:`compile_source` writes it as a
module of the kernel cache and compiles it with numba's on-disk cache
(:mod:`designer.jitcache`), so a kernel compiles once per machine.
"""
from __future__ import annotations

import hashlib
import math
import weakref
from pathlib import Path
from dataclasses import dataclass, field
from typing import Callable

import casadi as ca
import numba
import numpy as np
from numba.core import types
from numba.extending import intrinsic

from .codegen import UnsupportedOperation, literal, op_templates, sx_statements
from .jitcache import cached_njit, generated_module, source_stamp
from .model import Model
from .validation import InputError

__all__ = ["JitModel", "jit_model", "scalar_statements", "scalar_source", "compile_source", "fma",
           "UnsupportedOperation"]

# error_model="numpy": x / 0 gives inf/nan as in NumPy instead of raising ZeroDivisionError.
_NJIT = dict(nogil=True, cache=False, error_model="numpy")


# ----------------------------------------------------------------- scalar helpers (NumPy semantics)
@numba.njit(**_NJIT)
def _sign(a):
    if a > 0.0:
        return 1.0
    if a < 0.0:
        return -1.0
    return a  # 0.0, -0.0 and NaN map to themselves, as numpy.sign


@numba.njit(**_NJIT)
def _fmin(a, b):
    return b if a != a else (a if (b != b or a <= b) else b)  # numpy.fmin: NaN only if both are


@numba.njit(**_NJIT)
def _fmax(a, b):
    return b if a != a else (a if (b != b or a >= b) else b)  # numpy.fmax


@numba.njit(**_NJIT)
def _b2f(c):
    return 1.0 if c else 0.0


@intrinsic
def fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (LLVM's fma; a hardware FMA where there is one).  For use in ``njit`` code."""
    if not all(isinstance(v, (types.Float, types.Integer)) for v in (a, b, c)):
        return None

    def codegen(context, builder, signature, args):
        return builder.fma(*[context.cast(builder, v, t, types.float64) for v, t in zip(args, signature.args)])

    return types.float64(a, b, c), codegen  # integer operands are converted


@numba.njit(**dict(_NJIT, inline="always"))
def _atan2(y, x):
    """``atan2(y, x)`` without branches or calls, so that a loop of it vectorises (there is no vector libm here).

    Within 2.5 ulp of the exact value (2.2 measured over millions of operands of every
    magnitude; libm's is within 1), so it agrees with CasADi's and NumPy's ``atan2``
    to rounding (tests check both, and the special operands).

    ``t = min(|x|, |y|) / max(|x|, |y|)`` in [0, 1] is reduced with ``atan t = atan c + atan((t − c) / (1 + t c))``,
    ``c`` in {0, tan(π/8), 1} so that ``|u| <= tan(π/16)``, computed as one division
    ``(mn − c mx) / (mx + c mn)`` (FMAs); ``atan u`` is its Taylor polynomial to ``u^25`` (truncation below
    1e-18 there) in Estrin's scheme; then ``π/2 − ·`` when ``|y| > |x|``, ``π − ·`` for a negative ``x``
    (sign bit, so ``-0.0`` too) and the sign of ``y``, with the constants in two parts.  Zeros, infinities and
    NaN give C's ``atan2`` values (the operands are replaced by selects, no branch).
    """
    ax = abs(x)
    ay = abs(y)
    swap = ay > ax
    mn = ax if swap else ay
    mx = ay if swap else ax
    # special operands: both zero -> t = 0; max infinite -> t = 1 (both infinite) or 0; huge/tiny: scale by 2^-/+600
    zero = mx == 0.0
    inf = mx == math.inf
    mn = (1.0 if mn == math.inf else 0.0) if inf else (0.0 if zero else mn)
    mx = 1.0 if (inf or zero) else mx
    sc = 2.409919865102884e-181 if mx > 1e300 else (4.149515568880993e+180 if mx < 1e-300 else 1.0)
    mn = mn * sc
    mx = mx * sc
    # reduction
    hi = mn > 0.6681786379192989 * mx  # tan(3π/16)
    mid = mn > 0.198912367379658 * mx  # tan(π/16)
    c = 1.0 if hi else (0.41421356237309503 if mid else 0.0)
    u = fma(-c, mx, mn) / fma(c, mn, mx)
    z = u * u
    z2 = z * z
    z4 = z2 * z2
    q0 = fma(0.2, z, -0.3333333333333333)
    q1 = fma(0.1111111111111111, z, -0.14285714285714285)
    q2 = fma(0.07692307692307693, z, -0.09090909090909091)
    q3 = fma(0.058823529411764705, z, -0.06666666666666667)
    q4 = fma(0.047619047619047616, z, -0.05263157894736842)
    q5 = fma(0.04, z, -0.043478260869565216)
    poly = fma(fma(q5, z2, q4), z4 * z4, fma(fma(q3, z2, q2), z4, fma(q1, z2, q0)))  # Σ (-1)^k z^(k-1) / (2k+1)
    base_hi = 0.7853981633974483 if hi else (0.39269908169872414 if mid else 0.0)  # atan c, two parts
    base_lo = 3.06287113727155e-17 if hi else (3.06287113727155e-18 if mid else 0.0)
    r = base_hi + (u + fma(u * z, poly, base_lo))
    r = (1.5707963267948966 - r) + 6.1257422745431e-17 if swap else r
    r = (3.141592653589793 - r) + 1.22514845490862e-16 if math.copysign(1.0, x) < 0.0 else r
    r = math.copysign(r, y)
    return x + y if (x != x or y != y) else r


# One template per SX operation over the argument names a, b (scalars).
_TEMPLATES = op_templates(
    "_m", 1, "_b2f", POW="{a} ** {b}", CONSTPOW="{a} ** {b}", ATAN2="_atan2({a}, {b})", FABS="abs({a})",
    SIGN="_sign({a})", COPYSIGN="_m.copysign({a}, {b})", FLOOR="_np.floor({a})", CEIL="_np.ceil({a})",
    FMOD="_np.fmod({a}, {b})", FMIN="_fmin({a}, {b})", FMAX="_fmax({a}, {b})", HYPOT="_m.hypot({a}, {b})",
    ERF="_m.erf({a})", AND="_b2f(({a} != 0.0) and ({b} != 0.0))", OR="_b2f(({a} != 0.0) or ({b} != 0.0))",
    IF_ELSE_ZERO="({b} if {a} != 0.0 else 0.0)",
)


def scalar_statements(fun: ca.Function, inputs: list[str | None], output: str, indent: str = "    ") -> list[str]:
    """Scalar statements evaluating ``fun``'s (single, column) output for one point.

    The CasADi work registers become local variables ``w0, w1, ...`` (reused as
    CasADi reuses them), so several bodies may follow each other in one function.

    Parameters
    ----------
    fun : casadi.Function
        An SX function (an MX function is expanded) with one column-vector output.
    inputs : list of str or None
        For each input of ``fun``, a format string for element ``j`` of it, e.g.
        ``"x[{}]"`` or ``"X[m, {}]"``, or a plain name (no ``{}``) for a scalar
        input such as the time ``k``; ``None`` for an input the expression must not
        use (an :class:`InputError` is raised if it does).
    output : str
        Format string of the destination of output row ``i``, e.g. ``"out[{}]"``
        or ``"h{}"`` (a local scalar).  Structural zeros are written as ``0.0``.
    """
    if fun.is_a("MXFunction"):
        fun = fun.expand()
    if fun.n_out() != 1:
        raise UnsupportedOperation(f"{fun.name()!r} must have exactly one output for the scalar translation")
    sp = fun.sparsity_out(0)
    if sp.size2() != 1:
        raise UnsupportedOperation(f"output of {fun.name()!r} must be a column vector")
    nz_rows = sp.row()
    present = set(nz_rows)
    # rows never written by the instruction list are structural zeros
    lines = [f"{indent}{output.format(r)} = 0.0" for r in range(sp.size1()) if r not in present]

    def load(i: int, j: int) -> str:
        spec = inputs[i]
        if spec is None:
            raise InputError(f"{fun.name()!r} uses its input {fun.name_in(i)!r}; the scalar kernels support models "
                             "without known inputs and switching modes only")
        return spec.format(j) if "{}" in spec else spec

    lines += sx_statements(fun, _TEMPLATES, load=load, store=lambda o, nz: output.format(nz_rows[nz]),
                           constant=lambda v: literal(v, "_m"), target="scalar (numba)", indent=indent)
    if not lines:
        lines.append(f"{indent}pass")
    return lines


def scalar_source(fun: ca.Function, fname: str, inputs: list[str | None]) -> str:
    """Python source of ``def fname(<args>, out)`` writing ``fun``'s output for one point into ``out``.

    ``inputs`` names each input's argument: ``"x"`` for an array, ``"k!"`` for a
    scalar, ``None`` for an input the expression must not use.
    """
    args = [n.rstrip("!") for n in inputs if n is not None]
    specs = [None if n is None else (n[:-1] if n.endswith("!") else n + "[{}]") for n in inputs]
    return "\n".join([f"def {fname}({', '.join(args)}, out):"] + scalar_statements(fun, specs, "out[{}]"))


def compile_source(src: str, fname: str, label: str, namespace: dict | None = None, *, stamp: str = "",
                   **options) -> Callable:
    """Generated source as a module of the kernel cache, and ``fname`` of it compiled with numba, cached on disk.

    The source is written into :func:`designer.jitcache.kernels_dir` (once per text,
    :func:`designer.jitcache.generated_module`) and ``fname`` is compiled with
    ``numba.njit(nogil=True, error_model='numpy')`` and ``options``, its compiled code
    kept in the same cache (:func:`designer.jitcache.cached_njit`), so that the next
    process loads instead of compiling it.  The module's namespace has ``_m`` (math),
    ``_np`` (numpy) and the scalar helpers of :func:`scalar_statements`, plus
    ``namespace`` (functions only; constants belong in ``src``).  ``stamp`` is the code
    version of the caller's generator and of the helpers it binds (:func:`designer.jitcache.source_stamp`).
    The dispatcher's ``source`` is ``src`` and its ``path`` the module's file.
    """
    ns = dict(_NAMESPACE)
    ns.update(namespace or {})
    mod = generated_module(src, label, ns, hashlib.sha256(f"{stamp} {_STAMP}".encode()).hexdigest())
    fn = getattr(mod, fname)
    fn.__doc__ = f"Scalar translation of {label} (numba, nogil)."
    disp = cached_njit(mod.__key__, **dict(_NJIT, **options))(fn)
    disp.source = src
    disp.path = mod.__file__
    return disp


# The code version of the generated kernels' helpers: this file, the instruction walk, the cache.
_STAMP = source_stamp([__file__, Path(__file__).with_name("codegen.py"), Path(__file__).with_name("jitcache.py")])
_NAMESPACE = {"_m": math, "_np": np, "_sign": _sign, "_fmin": _fmin, "_fmax": _fmax, "_b2f": _b2f, "_atan2": _atan2,
              "_fma": fma}


@dataclass(frozen=True, eq=False)
class JitModel:
    """Compiled scalar kernels of one model (see the module docstring).

    Attributes
    ----------
    name : str
        The model's name.
    n_x : int
    sensor_dims : tuple of int
    offsets : ndarray of int64, shape (n_sensors + 1,)
        Where each sensor's rows start in ``h_all``'s output.
    f, h, h_all : numba dispatchers
        ``f(x, k, out)``, ``h(i, x, k, out)``, ``h_all(x, k, out)``.
    source : dict of str
        The generated Python source of each kernel (for inspection).
    """

    name: str
    n_x: int
    sensor_dims: tuple[int, ...]
    offsets: np.ndarray
    f: Callable
    h: Callable
    h_all: Callable
    source: dict = field(repr=False)

    @property
    def n_sensors(self) -> int:
        return len(self.sensor_dims)

    @property
    def n_z(self) -> int:
        return int(self.offsets[-1])


_CACHE: "weakref.WeakKeyDictionary[Model, JitModel]" = weakref.WeakKeyDictionary()


def jit_model(model: Model) -> JitModel:
    """Compile ``model``'s transition and measurement functions into scalar numba kernels.

    The result is cached per model object, so that kernels specialised on its
    dispatchers are compiled once per model and process.  Compilation itself is
    lazy (at the first call), as numba's always is.

    Raises
    ------
    InputError
        If the model has known inputs or switching modes (not supported by the kernels).
    UnsupportedOperation
        If an expression uses an SX operation without a scalar translation.
    """
    if not isinstance(model, Model):
        raise InputError(f"model must be a designer.Model, got {type(model).__name__}")
    hit = _CACHE.get(model)
    if hit is not None:
        return hit
    if model.n_u:
        raise InputError(f"model {model.name!r} has known inputs u; the numba kernels support models without inputs")
    if model.n_modes:
        raise InputError(f"model {model.name!r} has switching modes; the numba kernels support models without modes")
    source = {}
    # casadi_f inputs: x, k, u, mode (u and mode are empty here); casadi_h[i] inputs: x, k.
    source["f"] = scalar_source(model.casadi_f, "f", ["x", "k!", None, None])
    f = compile_source(source["f"], "f", f"f of {model.name!r}")

    h_lines = ["def h(i, x, k, out):"]
    for i, fun in enumerate(model.casadi_h):
        h_lines.append(f"    {'if' if i == 0 else 'elif'} i == {i}:")
        h_lines += scalar_statements(fun, ["x[{}]", "k"], "out[{}]", indent="        ")
    h_lines += ["    else:", "        for j in range(out.shape[0]):", "            out[j] = _m.nan"]
    source["h"] = "\n".join(h_lines)
    h = compile_source(source["h"], "h", f"h_i of {model.name!r}")

    all_lines = ["def h_all(x, k, out):"]
    offsets = np.asarray(model._offsets, dtype=np.int64)
    for i, fun in enumerate(model.casadi_h):
        all_lines += scalar_statements(fun, ["x[{}]", "k"], f"out[{int(offsets[i])} + {{}}]")
    source["h_all"] = "\n".join(all_lines)
    h_all = compile_source(source["h_all"], "h_all", f"h_all of {model.name!r}")

    out = JitModel(model.name, model.n_x, tuple(model.sensor_dims), offsets, f, h, h_all, source)
    _CACHE[model] = out
    return out
