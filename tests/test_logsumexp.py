"""designer.noise.logsumexp against scipy.special.logsumexp, its reference: the same numbers to the bit.

The particle filters' weights and the glint densities go through it, so the comparison study's numbers
stay those computed with SciPy's function; checked on the filters' shapes (reductions over the
particles and over mixture components) with ties, -inf, +inf and NaN entries, every entry -inf, and
magnitudes where exp overflows.
"""
from __future__ import annotations

import zlib

import numpy as np
import pytest
from scipy.special import logsumexp as scipy_logsumexp

from designer.noise import Gaussian, GaussianMixture, logsumexp


@pytest.mark.parametrize("shape, axis", [((2, 40, 50), 0), ((40, 50), -1), ((3, 7), 0), ((500,), 0), ((2,), 0),
                                         ((4, 1), -1), ((16, 60), 1)])
@pytest.mark.parametrize("case", ["plain", "wide", "overflow", "ties", "some -inf", "all -inf", "inf and nan"])
def test_scipys_numbers_to_the_bit(shape, axis, case):
    rng = np.random.default_rng(zlib.crc32(repr((shape, axis, case)).encode()))
    a = rng.normal(scale={"wide": 50.0, "overflow": 1e3}.get(case, 1.0), size=shape)
    if case == "ties":
        a = np.round(a)
    elif case == "some -inf":
        a.flat[::3] = -np.inf
    elif case == "all -inf":
        a[:] = -np.inf
    elif case == "inf and nan":
        a.flat[::5] = np.nan
        a.flat[1::7] = np.inf
    want, got = scipy_logsumexp(a, axis=axis), logsumexp(a, axis=axis)
    assert type(got) is type(want) and np.shape(got) == np.shape(want)
    np.testing.assert_array_equal(got, want)


def test_a_glint_mixtures_density_is_its_closed_form():
    """GaussianMixture.logpdf (through logsumexp) against the weighted sum of the components' densities."""
    mix = GaussianMixture.from_arrays([0.8, 0.2], [[0.0, 0.0], [0.0, 0.0]], [np.diag([4.0, 3e-4]), np.diag([25.0, 1e-3])])
    x = np.random.default_rng(1).normal(scale=[3.0, 0.02], size=(5, 7, 2))
    dens = sum(w * np.exp(Gaussian(c.mean, c.cov).logpdf(x)) for w, c in zip(mix.weights, mix.components))
    np.testing.assert_allclose(mix.logpdf(x), np.log(dens), rtol=1e-12)
