"""Branch-free scalar math of the fused kernels (numba): what libm would do, in loops that vectorise.

There is no vector libm here, so libm's ``exp`` is a call per particle, and every call
spills all floating-point registers: the kernels take their exps with
:func:`exp_nonpos` (branch-free, within 1.2 ulp), wrap angles with :func:`wrap_angle`
(``numpy.mod``'s result, branch-free) and the model's ``atan2`` with
:func:`designer.jit.fma`-based branch-free code (:mod:`designer.jit`).  :func:`ndtr` is
SciPy's normal CDF.

The ``v*`` functions (:func:`vexp`, :func:`vlog_dd`, :func:`vpow`, :func:`vndtr`, :func:`vfrexp`) are
branch-free versions of libm's ``exp``, ``log``, ``pow``, ``frexp`` and SciPy's ``ndtr`` for
likelihood loops that must vectorise (the binary sensors' likelihood,
:mod:`filters.fused.binary`): selects instead of branches, no float-to-integer conversion
(AVX2 has none for 64-bit integers), every polynomial in Estrin's scheme with explicit FMAs
(short dependency chains; the same rounding whatever the caller's fastmath flags).  Their
coefficients are derived by ``tools/vecmath_coefficients.py`` (Taylor coefficients, and a
Chebyshev interpolation of ``erfcx`` in 50-digit arithmetic); ``tests/test_vecmath.py``
measures their errors against NumPy, SciPy and closed forms.  They agree with libm to a
few ulp, not to the bit.
"""
from __future__ import annotations

import math

import numpy as np

from designer.jit import fma

from .cache import FAST, njit

__all__ = ["LN2_HI", "LN2_LO", "ndtr", "exp_nonpos", "neginf_unless_finite", "wrap_angle", "logaddexp", "vexp",
           "vlog_dd", "vpow", "vndtr", "vfrexp", "vpow_rows"]


#: ln 2 = LN2_HI + LN2_LO (0x1.62e42feep-1 + 0x1.a39ef35793c76p-33); LN2_HI has 32 significant bits, so
#: ``k LN2_HI`` is exact for the exponents ``k`` of a double.
LN2_HI = 0.6931471803691238
LN2_LO = 1.9082149292705877e-10


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
    r = (x - kf * LN2_HI) - kf * LN2_LO
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


# ============================================================================ vectorisable exp, log, frexp, ndtr
@njit(inline="always")
def _int_to_float(i):
    """``float(i)`` for an integer ``i`` in [-2048, 2^51), without an integer-to-float conversion (AVX2 has none
    for 64-bit integers): ``i + 2048`` in the low bits of a mantissa of 2^52, less ``2^52 + 2048``."""
    return np.int64(i + 0x4330000000000800).view(np.float64) - 4503599627372544.0


@njit(inline="always")
def _two_pow(kf):
    """``2^kf`` for an integer-valued float ``kf`` in [-1022, 1023], without a float-to-integer conversion:
    the low bits of ``2^52 + 1023 + kf`` are ``kf + 1023``, shifted into the exponent field."""
    b = np.float64(kf + 4503599627371519.0).view(np.int64)
    return np.int64(b << 52).view(np.float64)


@njit(inline="always")
def vexp(hi, lo):
    """``exp(hi + lo)`` for ``|lo|`` below about 0.01 (``lo`` the low part of an argument given in two parts; 0.0
    for a plain ``exp``), branch-free.

    ``k = round(hi / ln 2)``, ``r = hi − k ln2_hi − k ln2_lo + lo`` (the first two terms exact),
    ``exp(r)`` by its Taylor polynomial of degree 13 (``|r| <= 0.36``: truncation below 1e-17),
    times ``2^k`` as two factors so that results in the subnormal range come out right.
    Within 2 ulp of the exact value (tests); ``hi`` above 709.78 gives inf, below −745.2 zero,
    NaN gives NaN.
    """
    x = hi if hi > -746.0 else -746.0
    x = x if x < 710.0 else 710.0
    kf = np.floor(fma(x, 1.4426950408889634, 0.5))
    r = fma(-kf, LN2_LO, fma(-kf, LN2_HI, x)) + lo
    e0_0 = fma(1.0, r, 1.0)
    e0_1 = fma(0.16666666666666666, r, 0.5)
    e0_2 = fma(0.008333333333333333, r, 0.041666666666666664)
    e0_3 = fma(0.0001984126984126984, r, 0.001388888888888889)
    e0_4 = fma(2.7557319223985893e-06, r, 2.48015873015873e-05)
    e0_5 = fma(2.505210838544172e-08, r, 2.755731922398589e-07)
    e0_6 = fma(1.6059043836821613e-10, r, 2.08767569878681e-09)
    r2 = r * r
    e1_0 = fma(e0_1, r2, e0_0)
    e1_1 = fma(e0_3, r2, e0_2)
    e1_2 = fma(e0_5, r2, e0_4)
    r4 = r2 * r2
    e2_0 = fma(e1_1, r4, e1_0)
    e2_1 = fma(e0_6, r4, e1_2)
    r8 = r4 * r4
    e3_0 = fma(e2_1, r8, e2_0)
    p = e3_0
    k1 = np.floor(kf * 0.5)
    e = (p * _two_pow(k1)) * _two_pow(kf - k1)
    e = e if hi < 709.782712893384 else math.inf
    e = e if hi > -745.2 else 0.0
    return e if hi == hi else hi


@njit(inline="always")
def vlog_dd(x):
    """``log(x)`` as an unevaluated sum ``hi + lo`` for a finite ``x > 0``, branch-free: within
    ``2^-54 max(1, |log x|)`` (tests): the error does not grow with the exponent of ``x``.

    ``x = 2^k (1 + f)`` with ``1 + f`` in [√2/2, √2) (subnormals scaled by 2^54 first),
    ``s = f / (2 + f)``, ``log(1 + f) = f − f²/2 + s (f²/2 + R(s²))`` with
    ``R(z) = Σ_{j=1..11} 2 z^j / (2j + 1)`` (the series of ``2 atanh s − 2 s``; ``|s| <= 0.172``:
    truncation below 1e-18); ``k ln 2`` in two parts.  Zero, negative, infinite or NaN ``x`` give meaningless
    values: the caller selects.
    """
    sub = x < 2.2250738585072014e-308
    xs = x * 18014398509481984.0 if sub else x
    bits = np.int64(np.float64(xs).view(np.int64) & 0x7fffffffffffffff)
    hx = bits >> 32
    i = ((hx & 0x000fffff) + 0x95f64) & 0x100000  # 0x100000 when the significand is >= √2: halve it
    k = (hx >> 20) - 1023 + (i >> 20) - (54 if sub else 0)
    f = np.int64((bits & 0x000fffffffffffff) | ((i ^ 0x3ff00000) << 32)).view(np.float64) - 1.0
    s = f / (2.0 + f)
    z = s * s
    l0_0 = fma(0.4, z, 0.6666666666666666)
    l0_1 = fma(0.2222222222222222, z, 0.2857142857142857)
    l0_2 = fma(0.15384615384615385, z, 0.18181818181818182)
    l0_3 = fma(0.11764705882352941, z, 0.13333333333333333)
    l0_4 = fma(0.09523809523809523, z, 0.10526315789473684)
    z2 = z * z
    l1_0 = fma(l0_1, z2, l0_0)
    l1_1 = fma(l0_3, z2, l0_2)
    l1_2 = fma(0.08695652173913043, z2, l0_4)
    z4 = z2 * z2
    l2_0 = fma(l1_1, z4, l1_0)
    z8 = z4 * z4
    l3_0 = fma(l1_2, z8, l2_0)
    q = l3_0
    R = q * z
    hfsq = 0.5 * f * f
    dk = _int_to_float(k)
    a = dk * LN2_HI  # exact
    hi = a + f
    lo = (f - (hi - a)) + (fma(s, hfsq + R, -hfsq) + dk * LN2_LO)  # |a| >= |f| or a = 0
    h2 = hi + lo
    return h2, lo - (h2 - hi)


@njit(inline="always")
def vpow(x, y):
    """``x ** y`` (C's ``pow``), branch-free: ``exp(y log|x|)`` with ``log|x|`` in two parts and ``y log|x|`` split
    exactly by an FMA, so within 2 ulp (tests) whatever the magnitudes.

    C's special cases (tests): ``y = 0`` gives 1 (also for a NaN ``x``); a negative ``x`` with an odd integer ``y``
    negates the result, with a non-integer ``y`` gives NaN (a finite ``x``); a zero ``x`` gives 0 (``y > 0``) or
    inf (``y < 0``), signed for a negative zero and an odd ``y``; an infinite ``x`` gives inf or 0 (signed likewise).
    """
    ax = abs(x)
    hi, lo = vlog_dd(ax)
    ph = y * hi
    r = vexp(ph, fma(y, hi, -ph) + y * lo)
    r = r if ax < math.inf else (math.inf if y > 0.0 else 0.0)
    r = (0.0 if y > 0.0 else math.inf) if ax == 0.0 else r
    yint = np.floor(y) == y
    odd = yint and np.floor(y * 0.5) != y * 0.5
    r = -r if (math.copysign(1.0, x) < 0.0 and odd) else r
    r = r if (x >= 0.0 or yint or x != x or x == -math.inf) else math.nan
    r = 1.0 if y == 0.0 else r
    return r if (x == x and y == y) or y == 0.0 else x + y


@njit()
def vpow_rows(base, expo, out, n):
    """``out[j, m] = vpow(base[j, m], expo[j, m])`` for ``m < n``: a loop that vectorises (one inlined copy of
    :func:`vpow`, however many powers a generated kernel has)."""
    for j in range(base.shape[0]):
        bj, ej, oj = base[j], expo[j], out[j]
        for m in range(n):
            oj[m] = vpow(bj[m], ej[m])


@njit(inline="always")
def vndtr(a):
    """The standard normal CDF (SciPy's ``ndtr``), branch-free: within ``8 (1 + a²)`` ulp of SciPy's where it is
    above 1e-300 (tests; ``a / √2`` is rounded first, by both, and the condition number is about ``a²``).

    With ``z = |a| / √2``: ``erfc(z) = exp(−z²) erfcx(z)``; ``exp(−z²)`` from ``z`` split so that the high
    part's square is exact (:func:`vexp` of the two parts), ``erfcx(z) = 5 g(u) / (z + 5)`` with ``g`` a
    polynomial of degree 23 in ``u = (19 z − 70) / (14 z + 70)`` (``z`` in [0, 28] onto [−1, 1]; larger ``z``
    give 0 or 1); ``ndtr(a) = erfc(z) / 2`` for ``a < 0``, ``1 − erfc(z) / 2`` otherwise.  NaN gives NaN.
    """
    x = a * 0.7071067811865476
    z = abs(x)
    z = z if z < 28.0 else 28.0
    zh = np.int64(np.float64(z).view(np.int64) & np.int64(-134217728)).view(np.float64)  # 26 significant bits
    d = (z - zh) * (z + zh)
    e = vexp(-(zh * zh), -d)
    u = fma(19.0, z, -70.0) / fma(14.0, z, 70.0)
    c0_0 = fma(-0.2290221700558824, u, 0.25709987043323457)
    c0_1 = fma(-0.1351972853789182, u, 0.18483279466388966)
    c0_2 = fma(-0.053473955995216434, u, 0.08951161291063277)
    c0_3 = fma(-0.013671454775825192, u, 0.028666895412736176)
    c0_4 = fma(-0.002053173953481785, u, 0.005720917892270939)
    c0_5 = fma(-0.00013360112763466118, u, 0.0006059441252490909)
    c0_6 = fma(2.782711902237343e-06, u, 1.5186877919311374e-05)
    c0_7 = fma(3.363105012039262e-07, u, -1.8165032965624879e-06)
    c0_8 = fma(-3.2891699875713325e-08, u, 3.6905498648812856e-08)
    c0_9 = fma(1.6821532583559989e-09, u, 4.3178780309721495e-09)
    c0_10 = fma(-4.3125637440080306e-11, u, -5.9099669278051e-10)
    c0_11 = fma(-8.653882333287405e-13, u, 3.68911785747779e-11)
    u2 = u * u
    c1_0 = fma(c0_1, u2, c0_0)
    c1_1 = fma(c0_3, u2, c0_2)
    c1_2 = fma(c0_5, u2, c0_4)
    c1_3 = fma(c0_7, u2, c0_6)
    c1_4 = fma(c0_9, u2, c0_8)
    c1_5 = fma(c0_11, u2, c0_10)
    u4 = u2 * u2
    c2_0 = fma(c1_1, u4, c1_0)
    c2_1 = fma(c1_3, u4, c1_2)
    c2_2 = fma(c1_5, u4, c1_4)
    u8 = u4 * u4
    c3_0 = fma(c2_1, u8, c2_0)
    u16 = u8 * u8
    c4_0 = fma(c2_2, u16, c3_0)
    g = c4_0
    y = (2.5 * e) * g / (z + 5.0)
    r = y if x < 0.0 else 1.0 - y
    return r if a == a else a


@njit(inline="always")
def vfrexp(w):
    """``(m, e)`` with ``w = m 2^e``, ``m`` in [1, 2) and ``e`` an integer-valued float, for a positive normal ``w``;
    branch-free (a running product kept as ``m 2^e`` cannot underflow)."""
    bits = np.float64(w).view(np.int64)
    e = _int_to_float(((bits >> 52) & 0x7ff) - 1023)
    return np.int64((bits & 0x000fffffffffffff) | 0x3ff0000000000000).view(np.float64), e
