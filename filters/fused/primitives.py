"""Branch-free scalar math of the fused kernels (numba): what libm would do, in loops that vectorise.

There is no vector libm here, so libm's ``exp`` is a call per particle, and every call
spills all floating-point registers: the kernels take their exps with
:func:`exp_nonpos` (branch-free, within 1.2 ulp), wrap angles with :func:`wrap_angle`
(``numpy.mod``'s result, branch-free) and the model's ``atan2`` with
:func:`designer.jit.fma`-based branch-free code (:mod:`designer.jit`).  :func:`ndtr` is
SciPy's normal CDF.
"""
from __future__ import annotations

import math

import numpy as np

from designer.jit import fma

from .cache import FAST, njit

__all__ = ["ndtr", "exp_nonpos", "neginf_unless_finite", "wrap_angle", "logaddexp"]


@njit()
def ndtr(a):
    # Standard normal CDF as scipy.special.ndtr computes it (erfc in the tails).
    x = a * 0.7071067811865476
    z = abs(x)
    if z < 0.7071067811865476:
        return 0.5 + 0.5 * math.erf(x)
    y = 0.5 * math.erfc(z)
    if x > 0.0:
        y = 1.0 - y
    return y


@njit(inline="always", fastmath=FAST)
def exp_nonpos(d):
    """``exp(d)`` for ``d <= 0`` (a difference to a maximum), without branches or calls.

    So that a loop of it vectorises (libm's ``exp`` is a call per element; there
    is no vector libm here): ``exp(d) = 2^k exp(r)``, ``k = round(d / ln 2)``,
    ``r = d - k ln 2`` in two parts (Cody-Waite, ``k ln2_hi`` exact), ``exp(r)`` by
    its Taylor polynomial of degree 13 (``|r| <= ln 2 / 2``: truncation below
    1e-17), ``2^k`` built in the exponent bits.  Within 1.2 ulp of the exact value
    (1.14 measured over millions of arguments; libm's: under 1).
    Below ``-708`` (results under 1e-307, below the normal range) it gives 0, where
    libm gives subnormals: a weight that small against the largest one (at least 1)
    changes no sum.  NaN gives NaN; ``d > 0`` is not supported (it gives 1).
    """
    x = d if d > -708.0 else -708.0  # also NaN and -inf: a finite k below
    x = x if x < 0.0 else 0.0
    kf = math.floor(x * 1.4426950408889634 + 0.5)
    r = (x - kf * 0.6931471803691238) - kf * 1.9082149292705877e-10  # ln 2 = 0x1.62e42feep-1 + 0x1.a39ef35793c76p-33
    p = 1.6059043836821613e-10  # 1 / 13!
    p = p * r + 2.08767569878681e-09
    p = p * r + 2.505210838544172e-08
    p = p * r + 2.755731922398589e-07
    p = p * r + 2.7557319223985893e-06
    p = p * r + 2.48015873015873e-05
    p = p * r + 0.0001984126984126984
    p = p * r + 0.001388888888888889
    p = p * r + 0.008333333333333333
    p = p * r + 0.041666666666666664
    p = p * r + 0.16666666666666666
    p = p * r + 0.5
    p = p * r + 1.0
    p = p * r + 1.0
    e = p * np.int64((np.int64(kf) + 1023) << 52).view(np.float64)  # p 2^k
    return e if d >= -708.0 else (0.0 if d < -708.0 else d)  # d < -708: 0; NaN: NaN


@njit(inline="always")
def neginf_unless_finite(v):
    return v if (v > -math.inf and v < math.inf) else -math.inf


@njit(inline="always")
def wrap_angle(r):
    """``r`` if in (−π, π], else ``π − mod(π − r, 2π)`` as :func:`filters.rrp.wrap_angles` (``numpy.mod``).

    Without branches or calls: ``mod`` is ``x − q 2π`` with ``q = floor(x / 2π)``
    (one less if that rounded up) and one FMA, i.e. the exact remainder rounded
    once, as ``numpy.mod``'s (``fmod`` and ``+ 2π``).  NaN and ±inf give NaN.
    """
    x = 3.141592653589793 - r
    q = np.floor(x / 6.283185307179586)
    q = q - 1.0 if fma(-q, 6.283185307179586, x) < 0.0 else q
    w = 3.141592653589793 - fma(-q, 6.283185307179586, x)
    return r if (r > -3.141592653589793 and r <= 3.141592653589793) else w


@njit(inline="always")
def logaddexp(x, y):
    """``numpy.logaddexp(x, y)``, as NumPy computes it (``log1p`` of the smaller term's ``exp``)."""
    if x == y:  # also both -inf or +inf
        return x + 0.6931471805599453
    d = x - y
    if d > 0.0:
        return x + math.log1p(math.exp(-d))
    if d <= 0.0:
        return y + math.log1p(math.exp(d))
    return d  # NaN
