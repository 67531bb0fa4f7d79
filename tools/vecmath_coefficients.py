"""Derive the polynomial coefficients of the branch-free functions in :mod:`filters.fused.primitives`.

Development script, not imported by the package: it needs ``mpmath`` (``pip install mpmath``)
and prints the coefficients (exact rationals or 50-digit evaluations rounded once to
double) that ``primitives.py`` holds as literals:

- ``exp``: Taylor coefficients ``1 / j!``, ``j = 0 .. 13`` (reduced argument ``|r| <= ln 2 / 2``);
- ``log``: ``log((1 + s) / (1 − s)) = 2 s + s R(s²)``, ``R(z) = Σ_{j=1..11} 2 z^j / (2j + 1)``
  (``|s| <= 3 − 2√2``);
- ``ndtr``: ``erfcx(z) (z + 5) / 5`` for ``z`` in [0, 28], as a polynomial of degree 23 in
  ``u = (19 z − 70) / (14 z + 70)`` (the map of [0, 28] onto [−1, 1]): Chebyshev
  interpolation at 24 Chebyshev nodes of ``u`` in 50-digit arithmetic, converted to the
  monomial basis in the same arithmetic (interpolation error below 1e-18 relative; the
  evaluation in double is within a few ulp, checked by ``tests/test_vecmath.py``).

Run ``python tools/vecmath_coefficients.py``.
"""
from fractions import Fraction
from math import factorial

import mpmath as mp


def exp_coefficients() -> list[float]:
    return [float(Fraction(1, factorial(j))) for j in range(14)]


def log_coefficients() -> list[float]:
    return [float(Fraction(2, 2 * j + 1)) for j in range(1, 12)]


def ndtr_coefficients(n: int = 24) -> list[float]:
    mp.mp.dps = 50
    nodes = [mp.cos(mp.pi * (j + mp.mpf(1) / 2) / n) for j in range(n)]
    values = [mp.exp(z * z) * mp.erfc(z) * (z + 5) / 5 for z in (70 * (1 + u) / (19 - 14 * u) for u in nodes)]
    cheb = [2 * mp.fsum(values[j] * mp.cos(mp.pi * i * (j + mp.mpf(1) / 2) / n) for j in range(n)) / n
            for i in range(n)]
    cheb[0] /= 2
    mono = [mp.mpf(0)] * n
    t_prev, t_cur = [mp.mpf(1)], [mp.mpf(0), mp.mpf(1)]  # monomial coefficients of T_0, T_1
    for i, c in enumerate(cheb):
        t = t_prev if i == 0 else t_cur
        if i >= 2:
            t_prev, t_cur = t_cur, [2 * a - b for a, b in zip([mp.mpf(0)] + t_cur, t_prev + [mp.mpf(0)] * 2)]
            t = t_cur
        for k, v in enumerate(t):
            mono[k] += c * v
    return [float(m) for m in mono]


if __name__ == "__main__":
    print("exp", exp_coefficients())
    print("log", log_coefficients())
    print("ndtr", ndtr_coefficients())
