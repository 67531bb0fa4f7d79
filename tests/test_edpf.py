"""Seed 001's filters: the interval likelihood (13) against the whole transmission chain, the mixture proposal (11).

What holds exactly.  For a state x the decrypted value z̃ = c_k has the probability
``P(c_k | x) = P(z in A_k | x)`` with ``A_k`` the set of measurements that resolution and
quantizer map to cell k (computed below in exact arithmetic from (3)-(4), independently
of the code).  Every z in ``A_k`` satisfies ``|z - c_k| < L̄`` (12), so ``A_k`` lies inside
the interval of (13) and **(13) >= P(c_k | x)** for every x and every value; it is not
a probability mass (the intervals overlap: their sum exceeds one).  With no resolution
loss (l -> 0) the interval is the cell itself and (13) is the exact probability.
"""
from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from scipy import stats

from designer import InputError
from designer.noise import Gaussian, TruncatedGaussian
from filters.edpf import (fixed_mode_model, interval_loglik, interval_probability, mean_dynamics_model, raw_loglik,
                          received)
from filters.encryption import Codec, transmit
from filters.particle import run_sir, transition_proposal
from studies.scenarios import load_scenario

NOISE = stats.truncnorm(-2.0, 2.0)  # the paper's zeta: N(0, 1) truncated to [-2, 2]


@pytest.fixture(scope="module")
def sc():
    return load_scenario("switching-2d")


def _preimage(n: int, l: Fraction) -> tuple[Fraction, Fraction]:
    """The measurements z that resolution (3) maps to n l: [n l, (n+1) l), (-l, l) or ((n-1) l, n l]."""
    return (n * l, (n + 1) * l) if n > 0 else ((n - 1) * l, n * l) if n < 0 else (-l, l)


def _exact_pmf(h: float, l: Fraction, K: int = 8, lam: Fraction = Fraction(4)) -> np.ndarray:
    """P(z~ = c_k | h) for k = 1..K (omega = 1), in exact arithmetic up to the noise CDF.

    Cell k = [a, b) (half-open) holds the grid points n l with ceil(a / l) <= n <= ceil(b / l) - 1;
    their preimages tile one interval; saturated inputs go to the extreme cells.
    """
    p = np.zeros(K)
    for k in range(1, K + 1):
        a = -lam + 2 * (k - 1) * lam / K
        b = a + 2 * lam / K
        lo = -np.inf if k == 1 else float(_preimage(math.ceil(a / l), l)[0])
        hi = np.inf if k == K else float(_preimage(math.ceil(b / l) - 1, l)[1])
        p[k - 1] = NOISE.cdf(hi - h) - NOISE.cdf(lo - h)
    return p


def _one_sensor(sc, i):
    m = sc.model
    from designer.model import Model

    return Model("one", m.x, m.f_expr, [m.sensors[i]], m.process_noise, m.prior, mode=m.mode, mode_probs=m.mode_probs)


def test_interval_probability_closed_form_matches_the_noise_cdf(sc):
    noise = sc.model.sensors[0].noise
    lo = np.linspace(-5, 5, 401)
    for width in (0.01, 0.7, 1.4, 6.0):
        ref = noise.cdf((lo + width)[:, None]) - noise.cdf(lo[:, None])
        np.testing.assert_allclose(interval_probability(noise, lo, lo + width), ref, atol=1e-13)
    g = Gaussian([0.3], [[0.5]])  # any scalar noise goes through its cdf
    np.testing.assert_allclose(interval_probability(g, -1.0, 1.0),
                               stats.norm(0.3, np.sqrt(0.5)).cdf(1.0) - stats.norm(0.3, np.sqrt(0.5)).cdf(-1.0))
    far = TruncatedGaussian([0.0], [1.0], [-40.0], [40.0])  # upper tail: no cancellation
    assert interval_probability(far, 30.0, 31.0) == pytest.approx(stats.norm.sf(30) - stats.norm.sf(31), rel=1e-9)


@pytest.mark.parametrize("x", [np.array([2.0, -2.0]), np.array([0.3, 1.1]), np.array([12.0, -8.5])])
def test_decrypted_frequencies_match_the_exact_cell_probabilities_and_13_bounds_them(sc, x):
    """Simulate sensor -> resolution -> quantizer -> cipher -> decipher; compare with the exact pmf; check (13)."""
    m = sc.model
    codec = sc.channel.codec
    rng = np.random.default_rng(7)
    n = 200_000
    h = m.h_all(x)
    z = h + np.stack([s.noise.sample(rng, n)[:, 0] for s in m.sensors], axis=-1)
    tx = transmit(z, codec, rng)
    values = codec.reconstruct(np.arange(1, 9))
    for s in range(m.n_sensors):
        exact = _exact_pmf(float(h[s]), Fraction(1, 5))
        assert exact.sum() == pytest.approx(1.0, abs=1e-12)
        freq = np.array([np.mean(tx.decrypted[:, s] == v) for v in values])
        assert freq.sum() == 1.0
        assert np.all(np.abs(freq - exact) <= 5 * np.sqrt(exact * (1 - exact) / n) + 1e-12), (freq, exact)
        # (13) for this sensor at every value: an upper bound of the exact probability, not a pmf
        one = _one_sensor(sc, s)
        ll = interval_loglik(one, codec)
        p13 = np.array([np.exp(ll(x[None, None, :], 1, np.array([[v]]))[0, 0]) for v in values])
        assert np.all(p13 >= exact - 1e-12)
        assert p13.sum() > 1.0
        reachable = exact > 1e-12
        assert np.all(p13[reachable] > 0)


def test_interval_likelihood_is_exact_without_resolution_loss(sc):
    """l -> 0: the interval of (13) is the quantizer cell, (13) = P(z~ | x) for every value and state."""
    m = sc.model
    tiny = Fraction(1, 10**7)
    codec = Codec(float(tiny), 1.0, 8, 4.0)
    one = _one_sensor(sc, 0)
    ll = interval_loglik(one, codec)
    values = codec.reconstruct(np.arange(1, 9))
    for x in (np.array([0.2, -0.1]), np.array([1.0, 0.1]), np.array([-0.6, 0.4])):
        exact = _exact_pmf(float(m.h(0, x)[0]), tiny)
        p13 = np.array([np.exp(ll(x[None, None, :], 1, np.array([[v]]))[0, 0]) for v in values])
        np.testing.assert_allclose(p13, exact, atol=1e-6)


def test_likelihoods_skip_unavailable_sensors_and_match_the_formulas(sc):
    m = sc.model
    codec = sc.channel.codec
    rng = np.random.default_rng(3)
    x = m.prior.sample(rng, (2, 5))
    h = m.h_all(x)
    v = np.array([[0.5, -1.5], [2.5, 3.5]])  # (runs, N)
    noise = m.sensors[0].noise
    with np.errstate(divide="ignore"):  # some particles are incompatible with 3.5: log 0
        ref13 = np.log(noise.cdf((v[:, None, :] + 0.7 - h)[..., None])
                       - noise.cdf((v[:, None, :] - 0.7 - h)[..., None]))
    refraw = noise.logpdf((v[:, None, :] - h)[..., None])
    assert np.isfinite(ref13).any() and np.isneginf(ref13).any()
    for make, ref in ((lambda: interval_loglik(m, codec), ref13), (lambda: raw_loglik(m), refraw)):
        ll = make()
        np.testing.assert_allclose(ll(x, 1, v), ref.sum(-1), atol=1e-12)  # width N: all available
        both = np.concatenate([v, np.ones_like(v)], -1)
        np.testing.assert_allclose(ll(x, 1, both), ref.sum(-1), atol=1e-12)
        first = np.concatenate([v, [[1.0, 0.0], [1.0, 0.0]]], -1)
        np.testing.assert_allclose(ll(x, 1, first), ref[..., 0], atol=1e-12)
        none = np.concatenate([np.full_like(v, 123.0), np.zeros_like(v)], -1)
        np.testing.assert_array_equal(ll(x, 1, none), 0.0)


def test_received_packs_values_and_availabilities(sc):
    codec = sc.channel.codec
    z = np.random.default_rng(0).normal(size=(40, 2))
    tx = transmit(z, codec, np.random.default_rng(1), dropout_prob=0.5)
    y = received(tx)
    assert y.shape == (40, 4) and not np.isnan(y).any()
    np.testing.assert_array_equal(y[:, 2:] == 1.0, tx.available)
    np.testing.assert_array_equal(y[:, :2][tx.available], tx.decrypted[tx.available])


def test_raw_likelihood_collapses_and_the_filter_keeps_going(sc):
    """PF-SR-DE: a decrypted value more than 2 from every particle's h gives zero weights everywhere."""
    m = sc.model
    x = np.array([2.0, -2.0])
    h = m.h_all(x)  # (2 sin 4, -2 cos 0) = (-1.51, -2)
    z = np.tile([[0.5, -1.5]], (3, 1))  # |0.5 - h1| = 2.01: beyond the noise's support, within 2 + L-bar
    assert 2.0 < abs(z[0, 0] - h[0]) < 2.7
    from designer.model import Model
    from designer.noise import Gaussian as G

    pinned = Model("pinned", m.x, m.f_expr, m.sensors, G.zero_mean(1e-12 * np.eye(2)), G(x, 1e-12 * np.eye(2)),
                   mode=m.mode, mode_probs=[0.0, 1.0])  # particles stay near x
    stay = lambda xp, k, zk, rng: (xp, 0.0)  # noqa: E731 - keep the particles where they are
    res = run_sir(pinned, z, np.random.default_rng(0), particles=20, runs=1, loglik=raw_loglik(pinned),
                  proposal=stay).detail
    assert res.collapsed.all() and np.isfinite(res.mean).all()
    res13 = run_sir(pinned, z, np.random.default_rng(0), particles=20, runs=1,
                    loglik=interval_loglik(pinned, sc.channel.codec), proposal=stay).detail
    assert not res13.collapsed.any()  # (13) keeps them


def _paper_one_step(x, p=0.5):
    """Mean and covariance of x(t+1) | x(t) from the paper's F, f, g and noise mixture (written out here)."""
    F = np.array([[0.85, -0.2], [-0.2, 0.76]])
    f = np.array([-0.25 * np.tanh(x[1]), 0.35 * np.tanh(x[0])])
    g = np.array([0.32 * np.tanh(x[0]), -0.28 * np.tanh(x[1])])
    d = f - g
    mean = F @ x + p * f + (1 - p) * g
    cov = p * (1 - p) * np.outer(d, d) + (0.8 * 0.02**2 + 0.2 * 0.1**2) * np.eye(2)
    return mean, cov, F @ x + f, F @ x + g


@pytest.mark.parametrize("x", [np.array([2.0, 2.0]), np.array([2.0, -2.0]), np.array([-0.4, 0.9])])
def test_mixture_proposal_reproduces_the_one_step_distribution(sc, x):
    n = 400_000
    rng = np.random.default_rng(11)
    xs, corr = transition_proposal(sc.model)(np.tile(x, (1, n, 1)), 0, None, rng)
    s = xs[0]
    assert corr == 0.0
    mean, cov, mf, mg = _paper_one_step(x)
    d = s - s.mean(0)
    se_mean = np.sqrt(np.diag(np.cov(s.T)) / n)
    assert np.all(np.abs(s.mean(0) - mean) < 5 * se_mean)
    prods = d[:, :, None] * d[:, None, :]
    se_cov = prods.reshape(n, 4).std(0).reshape(2, 2) / np.sqrt(n)
    assert np.all(np.abs(np.cov(s.T) - cov) < 5 * se_cov + 1e-12)
    if np.linalg.norm(mf - mg) > 0.5:  # well separated branches: each drawn with probability 1/2
        share = np.mean(np.linalg.norm(s - mf, axis=1) < np.linalg.norm(s - mg, axis=1))
        assert abs(share - 0.5) < 5 * np.sqrt(0.25 / n)


def test_baseline_models(sc):
    m = sc.model
    x = np.array([[2.0, 2.0], [0.3, -1.0]])
    _, _, mf, mg = _paper_one_step(x[0])
    rsn = fixed_mode_model(m, 1)
    np.testing.assert_allclose(rsn.mode_probs, [0.0, 1.0])
    n = 100_000
    s, _ = transition_proposal(rsn)(np.tile(x[0], (1, n, 1)), 0, None, np.random.default_rng(2))
    assert np.all(np.abs(s[0].mean(0) - mf) < 5 * 0.05 / np.sqrt(n))  # gamma = 1 always: F x + f
    avg = mean_dynamics_model(m)
    assert avg.n_modes == 0
    for xi in x:
        mean, _, _, _ = _paper_one_step(xi)
        np.testing.assert_allclose(avg.f(xi), mean, rtol=1e-13)
    with pytest.raises(InputError, match="mode"):
        fixed_mode_model(m, 2)
    with pytest.raises(InputError, match="switching"):
        fixed_mode_model(avg, 0)


def test_bad_inputs_name_the_parameter(sc):
    m = sc.model
    codec = sc.channel.codec
    with pytest.raises(InputError, match="codec"):
        interval_loglik(m, {"resolution": 0.2})
    with pytest.raises(InputError, match="per sensor"):
        interval_loglik(m, Codec([0.2, 0.2, 0.2], 1.0, 8, 4.0))
    with pytest.raises(InputError, match="z must"):
        interval_loglik(m, codec)(m.prior.sample(np.random.default_rng(0), (1, 3)), 1, np.zeros((1, 3)))
    with pytest.raises(InputError, match="noise"):
        interval_probability(Gaussian(np.zeros(2), np.eye(2)), 0.0, 1.0)
    stacked = load_scenario("target-range-bearing").model
    with pytest.raises(InputError, match="scalar sensors"):
        raw_loglik(stacked)
