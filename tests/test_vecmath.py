"""The branch-free exp, log and ndtr of :mod:`filters.fused.primitives` against NumPy's and SciPy's.

References are independent implementations: NumPy's ``exp`` (libm, within 1 ulp), ``log``
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
from filters.fused.primitives import vexp, vfrexp, vlog_dd, vndtr


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
