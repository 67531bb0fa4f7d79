"""The branch-free exp, log, pow and ndtr of :mod:`filters.fused.primitives` against NumPy's and SciPy's.

References are independent implementations: NumPy's ``exp`` and ``power`` (libm, within 1 ulp), ``log``
in ``numpy.longdouble`` (64-bit significand on x86) for the two-part log, SciPy's ``ndtr``,
exact ``ldexp``; C's values for the special operands.  The bounds are the functions'
documented accuracies.
"""
from __future__ import annotations

import numpy as np
import pytest
from numba import njit
from scipy import special

from filters.fused.binary import _add_log_product, _affine_factor
from filters.fused.primitives import vexp, vfrexp, vlog_dd, vndtr, vpow


@njit(error_model="numpy")
def _exp(x, o):
    for i in range(x.size):  # a plain loop of the function: what the kernels inline
        o[i] = vexp(x[i], 0.0)


@njit(error_model="numpy")
def _log_dd(x, hi, lo):
    for i in range(x.size):
        hi[i], lo[i] = vlog_dd(x[i])


@njit(error_model="numpy")
def _ndtr(x, o):
    for i in range(x.size):
        o[i] = vndtr(x[i])


@njit(error_model="numpy")
def _frexp(x, m, e):
    for i in range(x.size):
        m[i], e[i] = vfrexp(x[i])


def _apply(fn, *args):
    out = np.empty_like(args[0])
    fn(*args, out)
    return out


def _ulp(got, ref):
    return np.abs(got - ref) / np.spacing(np.abs(ref))


RNG = np.random.default_rng(20261202)


def test_exp_within_2_ulp_over_the_whole_range():
    x = np.concatenate([RNG.uniform(-708.0, 709.7, 200_000), RNG.uniform(-1.0, 1.0, 50_000), [0.0, -0.0]])
    assert _ulp(_apply(_exp, x), np.exp(x)).max() <= 2.0


def test_exp_special_operands_and_the_subnormal_range():
    x = np.array([np.nan, np.inf, -np.inf, 709.79, 710.0, -745.3, -800.0, 0.0])
    got = _apply(_exp, x)
    np.testing.assert_array_equal(got[1:], [np.inf, 0.0, np.inf, np.inf, 0.0, 0.0, 1.0])
    assert np.isnan(got[0])
    sub = RNG.uniform(-745.0, -708.5, 20_000)  # results below the normal range: compared in absolute terms
    assert np.max(np.abs(_apply(_exp, sub) - np.exp(sub))) <= 4 * 5e-324


def test_two_part_log_error_is_absolute_not_relative_to_the_exponent():
    x = np.concatenate([np.exp(RNG.uniform(-700.0, 700.0, 50_000)), RNG.uniform(0.6, 1.6, 50_000)])
    hi, lo = np.empty_like(x), np.empty_like(x)
    _log_dd(x, hi, lo)
    ref = np.log(x.astype(np.longdouble))
    if np.finfo(np.longdouble).nmant < 60:
        pytest.skip("numpy.longdouble is not extended precision here")
    err = np.abs((hi.astype(np.longdouble) + lo) - ref) / np.maximum(1.0, np.abs(ref))
    assert err.max() <= 2.0 ** -54
    assert np.all(np.abs(lo) <= np.spacing(np.abs(hi)))  # hi is the rounded sum


def test_ndtr_matches_scipy_within_its_conditioning():
    a = np.concatenate([RNG.uniform(-37.5, 9.0, 400_000), RNG.uniform(-1.0, 1.0, 100_000), [0.0]])
    ref = special.ndtr(a)
    got = _apply(_ndtr, a)
    normal = ref > 1e-300
    # the relative condition number of ndtr at a is about a² (a / √2 is rounded first, by both)
    assert np.max(_ulp(got[normal], ref[normal]) / (1.0 + a[normal] ** 2)) <= 8.0
    tail = ~normal  # below the normal range: within a few subnormal steps, and zero where SciPy's is
    assert np.max(np.abs(got[tail] - ref[tail])) <= 1e-300


def test_ndtr_special_operands():
    got = _apply(_ndtr, np.array([np.nan, np.inf, -np.inf, 0.0, -40.0, 40.0]))
    assert np.isnan(got[0])
    np.testing.assert_array_equal(got[1:], [1.0, 0.0, 0.5, 0.0, 1.0])


def test_frexp_is_exact():
    w = np.exp(RNG.uniform(-700.0, 700.0, 100_000))
    m, e = np.empty_like(w), np.empty_like(w)
    _frexp(w, m, e)
    assert np.all((m >= 1.0) & (m < 2.0))
    np.testing.assert_array_equal(np.ldexp(m, e.astype(int)), w)


def test_binary_product_of_factors_is_the_sum_of_their_logs():
    """The binary likelihood's running product (mantissa and exponent) and its one log per particle against the
    sum of NumPy's logs, with factors down to the subnormal range (a plain product would underflow)."""
    S, n = 40, 128
    factors = np.exp(RNG.uniform(-40.0, 0.0, (S, n)))
    factors[3, :10] = 1e-300
    factors[5, 10:20] = 3e-310  # subnormal
    a = np.zeros(S)
    mant, expo, b = np.ones(n), np.zeros(n), np.full(n, 0.25)
    for s in range(S):  # factor = a + c C with a = 0, c = 1
        _affine_factor(factors[s], n, a[s], 1.0, mant, expo)
    _add_log_product(mant, expo, n, b)
    ref = 0.25 + np.log(factors).sum(axis=0)
    np.testing.assert_allclose(b, ref, rtol=1e-14)
    bad = np.ones(n)
    mant, expo, b = np.ones(n), np.zeros(n), np.zeros(n)
    for v in (0.5, 0.0, -0.1, np.nan):
        bad[:] = 0.5
        bad[7] = v
        _affine_factor(bad, n, 0.0, 1.0, mant, expo)
    _add_log_product(mant, expo, n, b)
    assert np.isnan(b[7]) and np.all(np.isfinite(np.delete(b, 7)))


@njit(error_model="numpy")
def _pow(x, y, o):
    for i in range(x.size):
        o[i] = vpow(x[i], y[i])


@pytest.mark.slow
def test_pow_within_2_ulp():
    x = np.exp(RNG.uniform(-300.0, 300.0, 200_000))
    y = RNG.uniform(-2.0, 2.0, x.size)
    keep = np.abs(y * np.log(x)) < 700.0
    x, y = x[keep], y[keep]
    assert _ulp(_apply(_pow, x, y), np.power(x, y)).max() <= 2.0
    d2 = RNG.uniform(1.0, 1e5, 50_000)  # the received-energy sensors' d² ** -1.4
    assert _ulp(_apply(_pow, d2, np.full_like(d2, -1.4)), d2 ** -1.4).max() <= 2.0
    neg = -RNG.uniform(0.1, 10.0, 20_000)  # negative bases with integer exponents
    k = RNG.integers(-5, 6, neg.size).astype(float)
    assert _ulp(_apply(_pow, neg, k), np.power(neg, k)).max() <= 2.0


def test_pow_special_operands_are_cs():
    vals = np.array([0.0, -0.0, 1.0, -1.0, 2.0, -2.0, 0.5, -0.5, np.inf, -np.inf, np.nan])
    exps = np.array([0.0, -0.0, 1.0, -1.0, 2.0, -2.0, 3.0, -3.0, 0.5, -0.5, 1.5, np.nan])
    x, y = (a.ravel() for a in np.meshgrid(vals, exps))
    with np.errstate(all="ignore"):
        ref = np.power(x, y)
    got = _apply(_pow, x, y)
    # C's pow(1, NaN) = 1 and pow(-1, ±inf) = 1 are not among these: x = 1 with y = NaN is the one difference
    odd_one = (x == 1.0) & np.isnan(y)
    np.testing.assert_array_equal(np.isnan(got[~odd_one]), np.isnan(ref[~odd_one]))
    ok = ~np.isnan(ref) & ~odd_one
    np.testing.assert_allclose(got[ok], ref[ok], rtol=4e-16)
    np.testing.assert_array_equal(np.signbit(got[ok]), np.signbit(ref[ok]))


def test_pow_rows_is_the_elementwise_pow():
    from filters.fused.primitives import vpow_rows

    base = np.exp(RNG.uniform(-5.0, 5.0, (3, 128)))
    expo = np.repeat([[-1.4], [0.5], [2.0]], 128, axis=1)
    out = np.full_like(base, -7.0)
    vpow_rows(base, expo, out, 100)
    assert _ulp(out[:, :100], base[:, :100] ** expo[:, :100]).max() <= 2.0
    assert np.all(out[:, 100:] == -7.0)  # only the block's first n particles


def test_split_powers_takes_out_independent_powers_only():
    import casadi as ca

    from designer.jit import scalar_statements
    from filters.fused.codegen import split_powers

    x = ca.SX.sym("x", 2)
    flat = ca.Function("h", [x], [ca.vertcat(4.0 * ca.fmax(x[0] ** 2 + x[1] ** 2, 1e-12) ** -1.4, x[0] ** 2.5 + 1.0)])
    first, second, J = split_powers(scalar_statements(flat, ["X[m, {}]"], "h{}"))
    assert J == 2 and sum("PR[" in line for line in second) == 2 and not any("**" in line for line in first + second)
    nested = ca.Function("h", [x], [(x[0] ** 2.5 + 1.0) ** 1.7])  # a power of a power's result: left in place
    assert split_powers(scalar_statements(nested, ["X[m, {}]"], "h{}")) is None
    assert split_powers(scalar_statements(ca.Function("h", [x], [x[0] * x[1]]), ["X[m, {}]"], "h{}")) is None
