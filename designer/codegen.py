"""Translate a CasADi SX function into a vectorised NumPy function.

``casadi.Function.map`` evaluates one sample per call of the compiled kernel and
was measured about 20x slower than plain NumPy for a range-bearing function at
500 particles.  Instead, we walk the SX instruction list of the function once
and emit straight-line Python source in which every CasADi work register is a
NumPy array over the batch dimensions.  The result evaluates the *same*
operations in the *same* order as CasADi's virtual machine, so it agrees with
CasADi to rounding (1e-12 is checked in the tests), while each operation is one
vectorised NumPy call over all particles.

Inputs of the generated function are arrays of shape ``(..., n_in)`` (scalars
and shape-``(n_in,)`` arrays broadcast); each output has shape
``(..., n_rows)`` for a column vector or ``(..., n_rows, n_cols)`` otherwise.

The instruction walk itself (:func:`sx_statements`) and the operation templates
(:func:`op_templates`) are shared with the scalar numba translation of
:mod:`designer.jit`, which differs only in what a work register holds.
"""
from __future__ import annotations

import math
from typing import Callable, Iterator

import casadi as ca
import numpy as np

__all__ = ["to_numpy", "UnsupportedOperation", "sx_statements", "op_templates", "literal"]


class UnsupportedOperation(NotImplementedError):
    """The CasADi expression uses an operation the NumPy translation lacks."""


def _op(name: str) -> int:
    return int(getattr(ca, "OP_" + name))


# The operations every translation writes alike (templates over the argument names a, b) ...
_ARITHMETIC = {"ASSIGN": "{a}", "ADD": "{a} + {b}", "SUB": "{a} - {b}", "MUL": "{a} * {b}", "DIV": "{a} / {b}",
               "NEG": "-{a}", "TWICE": "2.0 * {a}", "SQ": "{a} * {a}", "INV": "1.0 / {a}"}
# ... the functions of one argument, by their NumPy and their Python ``math`` names ...
_FUNCTIONS = {"EXP": ("exp", "exp"), "LOG": ("log", "log"), "SQRT": ("sqrt", "sqrt"), "SIN": ("sin", "sin"),
              "COS": ("cos", "cos"), "TAN": ("tan", "tan"), "ASIN": ("arcsin", "asin"), "ACOS": ("arccos", "acos"),
              "ATAN": ("arctan", "atan"), "SINH": ("sinh", "sinh"), "COSH": ("cosh", "cosh"), "TANH": ("tanh", "tanh"),
              "ASINH": ("arcsinh", "asinh"), "ACOSH": ("arccosh", "acosh"), "ATANH": ("arctanh", "atanh"),
              "LOG1P": ("log1p", "log1p"), "EXPM1": ("expm1", "expm1")}
# ... and the comparisons, as booleans that each translation turns into 0.0 / 1.0.
_COMPARISONS = {"LT": "{a} < {b}", "LE": "{a} <= {b}", "EQ": "{a} == {b}", "NE": "{a} != {b}", "NOT": "{a} == 0.0"}


def op_templates(module: str, names: int, to_float: str, **special: str) -> dict[int, str]:
    """``{op: template}`` of a translation: the shared arithmetic, ``module.<name>({a})`` for the
    functions of one argument (``names`` 0: NumPy's names, 1: ``math``'s), the comparisons
    wrapped in ``to_float(...)``, and ``special`` (by operation name) for the rest."""
    out = {_op(k): v for k, v in _ARITHMETIC.items()}
    out.update({_op(k): f"{module}.{v[names]}({{a}})" for k, v in _FUNCTIONS.items()})
    out.update({_op(k): f"{to_float}({v})" for k, v in _COMPARISONS.items()})
    out.update({_op(k): v for k, v in special.items()})
    return out


_TEMPLATES = op_templates(
    "_np", 0, "_f64", POW="_np.power({a}, {b})", CONSTPOW="_np.power({a}, {b})", ATAN2="_np.arctan2({a}, {b})",
    FABS="_np.abs({a})", SIGN="_np.sign({a})", COPYSIGN="_np.copysign({a}, {b})", FLOOR="_np.floor({a})",
    CEIL="_np.ceil({a})", FMOD="_np.fmod({a}, {b})", FMIN="_np.fmin({a}, {b})", FMAX="_np.fmax({a}, {b})",
    HYPOT="_np.hypot({a}, {b})", ERF="_erf({a})", ERFINV="_erfinv({a})", AND="_f64(({a} != 0.0) & ({b} != 0.0))",
    OR="_f64(({a} != 0.0) | ({b} != 0.0))", IF_ELSE_ZERO="_np.where({a} != 0.0, {b}, 0.0)",
)

_OP_NAMES = {int(getattr(ca, n)): n for n in dir(ca) if n.startswith("OP_")}
_INPUT, _OUTPUT, _CONST = _op("INPUT"), _op("OUTPUT"), _op("CONST")


def _f64(a):
    return np.asarray(a, dtype=np.float64)


def _erf(a):
    from scipy.special import erf

    return erf(a)


def _erfinv(a):
    from scipy.special import erfinv

    return erfinv(a)


def literal(value: float, module: str) -> str:
    """Python source of a float constant; ``inf`` and ``nan`` as attributes of ``module`` (e.g. ``"_np"``)."""
    if math.isnan(value):
        return f"{module}.nan"
    if math.isinf(value):
        return f"{module}.inf" if value > 0 else f"-{module}.inf"
    return repr(float(value))


def sx_statements(fun: ca.Function, templates: dict[int, str], *, load: Callable[[int, int], str],
                  store: Callable[[int, int], str], constant: Callable[[float], str], target: str,
                  indent: str = "    ") -> Iterator[str]:
    """The SX instruction list of ``fun`` as Python assignments, one per instruction.

    CasADi's work registers become variables ``w0, w1, ...`` (reused as CasADi
    reuses them).  The emitters (:func:`to_numpy` here, :mod:`designer.jit`) differ
    only in what a register holds and so in the callables:

    load(i, j)
        source of element ``j`` of input ``i`` (it may raise to refuse an input);
    store(o, nz)
        destination of structural nonzero ``nz`` of output ``o``;
    constant(value)
        source of a constant;
    templates
        ``{op: template}`` over the argument names ``{a}``, ``{b}``.

    Raises :class:`UnsupportedOperation` naming an operation without a template
    (``target`` says which translation lacks it) or a sparse input.
    """
    for j in range(fun.n_in()):
        if not fun.sparsity_in(j).is_dense():
            raise UnsupportedOperation(f"input {fun.name_in(j)!r} of {fun.name()!r} is sparse")
    for n in range(fun.n_instructions()):
        op = fun.instruction_id(n)
        ins = fun.instruction_input(n)
        outs = fun.instruction_output(n)
        if op == _INPUT:
            line = f"w{outs[0]} = {load(ins[0], ins[1])}"
        elif op == _OUTPUT:
            line = f"{store(outs[0], outs[1])} = w{ins[0]}"
        elif op == _CONST:
            line = f"w{outs[0]} = {constant(float(fun.instruction_constant(n)))}"
        elif op in templates:
            b = f"w{ins[1]}" if len(ins) > 1 else ""
            line = f"w{outs[0]} = " + templates[op].format(a=f"w{ins[0]}", b=b)
        else:
            raise UnsupportedOperation(
                f"CasADi operation {_OP_NAMES.get(op, op)} in {fun.name()!r} has no {target} translation"
            )
        yield indent + line


def _source(fun: ca.Function, fname: str) -> str:
    """Python source of the vectorised translation of ``fun``."""
    n_in, n_out = fun.n_in(), fun.n_out()
    args = [f"i{j}" for j in range(n_in)]
    lines = [f"def {fname}({', '.join(args)}):"]
    for j in range(n_in):
        lines.append(f"    i{j} = _np.asarray(i{j}, dtype=_np.float64)")
        lines.append(f"    if i{j}.ndim == 0: i{j} = i{j}.reshape(1)")
    batch = ", ".join(f"i{j}.shape[:-1]" for j in range(n_in))
    lines.append(f"    _shape = _np.broadcast_shapes({batch}{',' if n_in == 1 else ''})")
    # Destination index of every structural nonzero of every output.
    dest = []
    for j in range(n_out):
        sp = fun.sparsity_out(j)
        rows, cols = sp.size1(), sp.size2()
        shape = (rows,) if cols == 1 else (rows, cols)
        lines.append(f"    o{j} = _np.zeros(_shape + {shape!r})")
        r, c = sp.get_triplet()
        dest.append([f"{ri}" for ri in r] if cols == 1 else [f"{ri}, {ci}" for ri, ci in zip(r, c)])
    lines += sx_statements(fun, _TEMPLATES, load=lambda i, j: f"i{i}[..., {j}]",
                           store=lambda o, nz: f"o{o}[..., {dest[o][nz]}]",
                           constant=lambda v: literal(v, "_np"), target="NumPy")
    rets = ", ".join(f"o{j}" for j in range(n_out))
    lines.append(f"    return {rets}{',' if n_out == 1 else ''}")
    return "\n".join(lines)


def to_numpy(fun: ca.Function) -> Callable[..., tuple[np.ndarray, ...]]:
    """Compile a CasADi function into a batched NumPy function.

    Parameters
    ----------
    fun : casadi.Function
        A function of SX type (an MX function is expanded first).

    Returns
    -------
    callable
        ``g(*inputs) -> tuple of outputs``; inputs have shape ``(..., n_in)``
        and broadcast against each other over the leading dimensions.
    """
    if fun.is_a("MXFunction"):
        fun = fun.expand()
    fname = "_cg_" + "".join(ch if ch.isalnum() else "_" for ch in fun.name())
    src = _source(fun, fname)
    namespace = {"_np": np, "_f64": _f64, "_erf": _erf, "_erfinv": _erfinv}
    exec(compile(src, f"<cfdesign numpy translation of {fun.name()}>", "exec"), namespace)
    g = namespace[fname]
    g.__doc__ = f"NumPy translation of CasADi function {fun.name()!r}."
    g.source = src
    return g
