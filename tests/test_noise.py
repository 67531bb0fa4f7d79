"""Tests of designer.noise against independent references.

References: scipy.stats (norm, multivariate_normal, truncnorm, uniform), closed
forms written out here, numerical integration (scipy.integrate), and Monte
Carlo of the generative model with n-sigma thresholds.  All randomness comes
from seeded numpy.random.Generator objects.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate, special, stats

from designer.noise import (
    Gaussian,
    GaussianMixture,
    PolarVelocityPrior,
    TruncatedGaussian,
    UniformBox,
    spawn_generators,
)
from designer.validation import InputError

N_MC = 200_000
NSIG = 5.0


# ---------------------------------------------------------------------------
# Distributions under test
# ---------------------------------------------------------------------------

COV3 = np.array([[2.0, 0.6, -0.3], [0.6, 1.0, 0.2], [-0.3, 0.2, 0.5]])
COV2 = np.array([[2.0, 0.6], [0.6, 1.0]])


def gauss1():
    return Gaussian([0.7], [[2.25]])


def gauss2():
    return Gaussian([1.0, -2.0], COV2)


def gauss3():
    return Gaussian([0.5, -1.0, 2.0], COV3)


def gauss_diag():
    return Gaussian([1.0, 2.0], [[1.0, 0.0], [0.0, 4.0]])


MIX1_W = [0.2, 0.5, 0.3]
MIX1_M = [[-2.0], [0.5], [3.0]]
MIX1_C = [[[0.5]], [[1.0]], [[2.0]]]


def mix1():
    return GaussianMixture.from_arrays(MIX1_W, MIX1_M, MIX1_C)


MIX2_W = [0.35, 0.65]
MIX2_M = [[0.0, 1.0], [2.0, -1.0]]
MIX2_C = [[[1.0, 0.3], [0.3, 0.5]], [[2.0, -0.4], [-0.4, 1.5]]]


def mix2():
    return GaussianMixture.from_arrays(MIX2_W, MIX2_M, MIX2_C)


def trunc1():
    return TruncatedGaussian([0.5], [1.2], [-1.0], [2.5])


TR2 = dict(loc=[0.0, 1.0], scale=[1.0, 2.0], lower=[-0.5, -np.inf], upper=[1.5, 2.0])


def trunc2():
    return TruncatedGaussian(**TR2)


def ubox():
    return UniformBox([-1.0, 0.0, 2.0], [1.0, 3.0, 2.5])


POS_M = np.array([1.0, -1.0])
POS_C = np.array([[1.0, 0.3], [0.3, 0.5]])

# (speed_mean, speed_std, heading_mean, heading_std): a typical prior, one with
# a lot of negative-speed mass (tests the branch sum), one with a heading mean
# far from (-pi, pi] and one with a wide heading (tests the 2 pi wrap sum).
POLAR_PARAMS = [
    (2.0, 0.6, 0.8, 0.4),
    (0.4, 1.0, 0.5, 0.3),
    (3.0, 0.5, 20.0, 0.3),
    (0.5, 1.0, -0.5, 5.0),
]


def polar(params=POLAR_PARAMS[0]):
    return PolarVelocityPrior(POS_M, POS_C, *params)


ALL = {
    "gauss1": gauss1,
    "gauss2": gauss2,
    "gauss3": gauss3,
    "gauss_diag": gauss_diag,
    "mix1": mix1,
    "mix2": mix2,
    "trunc1": trunc1,
    "trunc2": trunc2,
    "ubox": ubox,
    "polar": polar,
    "polar_branch": lambda: polar(POLAR_PARAMS[1]),
    "polar_wrap": lambda: polar(POLAR_PARAMS[2]),
}


def _rng(seed=0):
    return np.random.default_rng(seed)


# ---------------------------------------------------------------------------
# Independent reference densities
# ---------------------------------------------------------------------------

def ref_trunc_logpdf_1d(x, loc, scale, lo, hi):
    """Closed form of the truncated normal written with scipy.stats.norm only."""
    z = stats.norm.cdf((hi - loc) / scale) - stats.norm.cdf((lo - loc) / scale)
    with np.errstate(divide="ignore"):
        lp = stats.norm.logpdf(x, loc, scale) - np.log(z)
    return np.where((x >= lo) & (x <= hi), lp, -np.inf)


def ref_trunc_cdf_1d(x, loc, scale, lo, hi):
    a = stats.norm.cdf((lo - loc) / scale)
    z = stats.norm.cdf((hi - loc) / scale) - a
    return np.clip((stats.norm.cdf((x - loc) / scale) - a) / z, 0.0, 1.0)


def ref_mix_pdf(x, weights, means, covs):
    return sum(w * stats.multivariate_normal(m, c).pdf(x) for w, m, c in zip(weights, means, covs))


def ref_polar_sample(rng, n, params):
    """The generative model written out: position Gaussian, speed and heading normal."""
    sm, ss, hm, hs = params
    pos = rng.multivariate_normal(POS_M, POS_C, size=n)
    s = rng.normal(sm, ss, size=n)
    a = rng.normal(hm, hs, size=n)
    return np.column_stack([pos[:, 0], s * np.cos(a), pos[:, 1], s * np.sin(a)])


# ---------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------

def assert_moments(x, mean, cov, nsig=NSIG):
    """Sample mean / covariance within ``nsig`` standard errors of ``mean`` / ``cov``."""
    x = x.reshape(-1, x.shape[-1])
    n = x.shape[0]
    mean = np.asarray(mean, float)
    cov = np.asarray(cov, float)
    se_mean = np.sqrt(np.diag(cov) / n)
    dev = np.abs(x.mean(axis=0) - mean)
    assert np.all(dev <= nsig * se_mean), (dev, se_mean)
    c = x - mean
    prod = c[:, :, None] * c[:, None, :]
    cov_hat = prod.mean(axis=0)
    se_cov = prod.std(axis=0) / np.sqrt(n)
    dev = np.abs(cov_hat - cov)
    assert np.all(dev <= nsig * se_cov + 1e-12), (cov_hat, cov, se_cov)


def ks_distance(samples, cdf):
    x = np.sort(np.asarray(samples).ravel())
    n = x.size
    f = cdf(x)
    i = np.arange(1, n + 1)
    return max(np.max(i / n - f), np.max(f - (i - 1) / n))


def dkw_bound(n, alpha=1e-6):
    """Dvoretzky-Kiefer-Wolfowitz: P(sup|F_n - F| > eps) <= alpha."""
    return np.sqrt(np.log(2.0 / alpha) / (2.0 * n))


def polar_velocity_mass(prior, params, pos, r_max):
    """Integral over the velocity plane of pdf(x) / N(pos) at a fixed position.

    Integrated in polar coordinates (vx, vy) = (r cos t, r sin t), dvx dvy = r dr dt,
    with adaptive cubature.
    """
    pos_pdf = stats.multivariate_normal(POS_M, POS_C).pdf(pos)

    def f(u):
        r, t = u[:, 0], u[:, 1]
        x = np.column_stack([np.full_like(r, pos[0]), r * np.cos(t), np.full_like(r, pos[1]), r * np.sin(t)])
        return prior.pdf(x) / pos_pdf * r

    res = integrate.cubature(f, [0.0, -np.pi], [r_max, np.pi], rtol=1e-9, atol=1e-12)
    assert res.status == "converged"
    return float(res.estimate)


# ---------------------------------------------------------------------------
# Batched densities
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("make", [gauss1, gauss2, gauss3, gauss_diag], ids=["d1", "d2", "d3", "diag"])
def test_gaussian_logpdf_batched_matches_scipy(make):
    g = make()
    d = g.dim
    x = _rng(1).normal(size=(3, 5, d)) * 2.0 + 0.5
    ref = stats.multivariate_normal(np.asarray(g.mean), np.asarray(g.cov)).logpdf(x.reshape(-1, d)).reshape(3, 5)
    lp = g.logpdf(x)
    assert lp.shape == (3, 5)
    np.testing.assert_allclose(lp, ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g.pdf(x), np.exp(lp), rtol=1e-14)
    # a single point gives a scalar
    assert np.shape(g.logpdf(x[0, 0])) == ()
    np.testing.assert_allclose(g.logpdf(x[0, 0]), ref[0, 0], rtol=1e-12)


def test_gaussian_1d_accepts_points_without_trailing_axis():
    g = gauss1()
    x = _rng(2).normal(size=(3, 5))
    ref = stats.norm(0.7, 1.5).logpdf(x)
    np.testing.assert_allclose(g.logpdf(x), ref, rtol=1e-12)
    np.testing.assert_allclose(g.logpdf(x[..., None]), ref, rtol=1e-12)
    np.testing.assert_allclose(g.logpdf(0.3), stats.norm(0.7, 1.5).logpdf(0.3), rtol=1e-12)
    # scalar parameters are the same 1-D Gaussian
    np.testing.assert_allclose(Gaussian(0.7, 2.25).logpdf(x), ref, rtol=1e-12)


def test_gaussian_zero_mean():
    g = Gaussian.zero_mean(COV2)
    np.testing.assert_array_equal(g.mean, [0.0, 0.0])
    x = _rng(3).normal(size=(4, 2))
    np.testing.assert_allclose(g.logpdf(x), stats.multivariate_normal([0, 0], COV2).logpdf(x), rtol=1e-12)


@pytest.mark.parametrize(
    "make, w, m, c", [(mix1, MIX1_W, MIX1_M, MIX1_C), (mix2, MIX2_W, MIX2_M, MIX2_C)], ids=["d1", "d2"]
)
def test_mixture_pdf_batched_matches_sum_of_scipy_pdfs(make, w, m, c):
    mix = make()
    d = mix.dim
    x = _rng(4).normal(size=(3, 5, d)) * 2.5
    ref = ref_mix_pdf(x.reshape(-1, d), w, m, c).reshape(3, 5)
    p = mix.pdf(x)
    assert p.shape == (3, 5)
    np.testing.assert_allclose(p, ref, rtol=1e-12)
    np.testing.assert_allclose(mix.logpdf(x), np.log(ref), rtol=1e-12)
    np.testing.assert_allclose(p, np.exp(mix.logpdf(x)), rtol=1e-14)


def test_mixture_logpdf_stable_in_far_tails():
    # pdf underflows to 0 there, but the log-density must stay finite and exact.
    mix = mix1()
    x = np.array([-60.0, 80.0])
    terms = np.stack([np.log(w) + stats.norm.logpdf(x, m[0], np.sqrt(c[0][0]))
                      for w, m, c in zip(MIX1_W, MIX1_M, MIX1_C)])
    ref = special.logsumexp(terms, axis=0)
    lp = mix.logpdf(x)
    assert np.all(np.isfinite(lp))
    np.testing.assert_allclose(lp, ref, rtol=1e-12)


def test_mixture_zero_weight_component_is_ignored():
    mix = GaussianMixture.from_arrays([1.0, 0.0], [[0.0], [5.0]], [[[1.0]], [[1.0]]])
    x = np.linspace(-3, 8, 7)
    np.testing.assert_allclose(mix.logpdf(x), stats.norm.logpdf(x), rtol=1e-12)


@pytest.mark.parametrize("make", [trunc1, trunc2], ids=["d1", "d2"])
def test_truncated_logpdf_batched(make):
    tg = make()
    d = tg.dim
    x = _rng(5).normal(size=(3, 5, d)) * 1.5 + 0.5
    loc, scale = np.asarray(tg.loc), np.asarray(tg.scale)
    lo, hi = np.asarray(tg.lower), np.asarray(tg.upper)
    ref_closed = sum(ref_trunc_logpdf_1d(x[..., i], loc[i], scale[i], lo[i], hi[i]) for i in range(d))
    ref_scipy = sum(
        stats.truncnorm((lo[i] - loc[i]) / scale[i], (hi[i] - loc[i]) / scale[i], loc=loc[i], scale=scale[i]).logpdf(
            x[..., i]
        )
        for i in range(d)
    )
    lp = tg.logpdf(x)
    assert lp.shape == (3, 5)
    inside = np.isfinite(ref_closed)
    assert inside.any() and (~inside).any()  # the test points straddle the bounds
    assert np.all(lp[~inside] == -np.inf)
    np.testing.assert_allclose(lp[inside], ref_closed[inside], rtol=1e-10)
    np.testing.assert_allclose(lp[inside], ref_scipy[inside], rtol=1e-10)
    np.testing.assert_allclose(tg.pdf(x), np.exp(lp), rtol=1e-14)
    assert np.all(tg.pdf(x)[~inside] == 0.0)


def test_uniform_logpdf_batched():
    ub = ubox()
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([1.0, 3.0, 2.5])
    rng = _rng(6)
    x = rng.uniform(lo - 0.3, hi + 0.3, size=(3, 5, 3))
    ref = np.prod(stats.uniform(loc=lo, scale=hi - lo).pdf(x), axis=-1)
    p = ub.pdf(x)
    assert p.shape == (3, 5)
    assert (ref == 0).any() and (ref > 0).any()
    np.testing.assert_allclose(p, ref, rtol=1e-12)
    with np.errstate(divide="ignore"):
        np.testing.assert_allclose(ub.logpdf(x), np.log(ref), rtol=1e-12)
    np.testing.assert_allclose(p, np.exp(ub.logpdf(x)), rtol=1e-14)
    # box corners belong to the closed box
    assert ub.pdf(lo) == pytest.approx(1.0 / np.prod(hi - lo))
    assert ub.pdf(hi) == pytest.approx(1.0 / np.prod(hi - lo))


def test_polar_logpdf_batched_and_factorises():
    pr = polar()
    x = ref_polar_sample(_rng(7), 15, POLAR_PARAMS[0]).reshape(3, 5, 4)
    lp = pr.logpdf(x)
    assert lp.shape == (3, 5)
    assert np.all(np.isfinite(lp))
    np.testing.assert_allclose(pr.pdf(x), np.exp(lp), rtol=1e-14)
    # batched evaluation equals point-by-point evaluation
    single = np.array([[pr.logpdf(x[i, j]) for j in range(5)] for i in range(3)])
    np.testing.assert_allclose(lp, single, rtol=1e-13)
    # position and velocity are independent: log p - log N(pos) depends on velocity only
    pos_lp = stats.multivariate_normal(POS_M, POS_C).logpdf(x[..., [0, 2]])
    vel_part = lp - pos_lp
    moved = x.copy()
    moved[..., [0, 2]] = _rng(8).normal(size=(3, 5, 2))
    vel_part_moved = pr.logpdf(moved) - stats.multivariate_normal(POS_M, POS_C).logpdf(moved[..., [0, 2]])
    np.testing.assert_allclose(vel_part, vel_part_moved, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("params", POLAR_PARAMS, ids=["typical", "negative_speed", "far_heading", "wide_heading"])
def test_polar_velocity_density_integrates_to_one(params):
    """Checks the 1/|v| Jacobian, the +-speed branch sum and the 2 pi heading sum."""
    pr = polar(params)
    r_max = abs(params[0]) + 12.0 * params[1]
    for pos in (POS_M, np.array([0.0, 0.5])):
        assert polar_velocity_mass(pr, params, pos, r_max) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize(
    "params, box",
    [
        (POLAR_PARAMS[0], ([0.5, 2.0], [0.5, 2.0])),
        # opposite to the heading: mass there comes only from negative speeds
        (POLAR_PARAMS[1], ([-2.0, -0.3], [-1.5, -0.1])),
        (POLAR_PARAMS[1], ([0.2, 1.5], [0.0, 1.2])),
        (POLAR_PARAMS[2], ([-1.0, 3.0], [1.0, 4.0])),
    ],
)
def test_polar_velocity_box_probability_matches_monte_carlo(params, box):
    """Integral of the density over a velocity box against the frequency in draws of the model."""
    pr = polar(params)
    (x0, x1), (y0, y1) = box
    pos = POS_M
    pos_pdf = stats.multivariate_normal(POS_M, POS_C).pdf(pos)

    def f(u):
        x = np.column_stack([np.full(len(u), pos[0]), u[:, 0], np.full(len(u), pos[1]), u[:, 1]])
        return pr.pdf(x) / pos_pdf

    res = integrate.cubature(f, [x0, y0], [x1, y1], rtol=1e-8, atol=1e-10)
    prob = float(res.estimate)
    s = ref_polar_sample(_rng(9), N_MC, params)
    hit = (s[:, 1] >= x0) & (s[:, 1] <= x1) & (s[:, 3] >= y0) & (s[:, 3] <= y1)
    freq = hit.mean()
    se = np.sqrt(prob * (1 - prob) / N_MC)
    assert prob > 0.01
    assert abs(freq - prob) <= NSIG * se, (freq, prob, se)


# ---------------------------------------------------------------------------
# Distribution functions
# ---------------------------------------------------------------------------

def test_gaussian_cdf_1d_and_diagonal_match_norm_cdf():
    x = _rng(10).normal(size=(3, 5)) * 2
    np.testing.assert_allclose(gauss1().cdf(x), stats.norm.cdf(x, 0.7, 1.5), rtol=1e-12)
    np.testing.assert_allclose(gauss1().cdf(x[..., None]), stats.norm.cdf(x, 0.7, 1.5), rtol=1e-12)
    x2 = _rng(11).normal(size=(3, 5, 2)) * 2 + 1
    ref = stats.norm.cdf(x2[..., 0], 1.0, 1.0) * stats.norm.cdf(x2[..., 1], 2.0, 2.0)
    c = gauss_diag().cdf(x2)
    assert c.shape == (3, 5)
    np.testing.assert_allclose(c, ref, rtol=1e-12)


def test_gaussian_cdf_full_covariance_matches_multivariate_normal_cdf():
    g = gauss3()
    x = _rng(12).normal(size=(2, 3, 3)) + g.mean
    ref = np.array([[stats.multivariate_normal(g.mean, COV3).cdf(x[i, j]) for j in range(3)] for i in range(2)])
    c = g.cdf(x)
    assert c.shape == (2, 3)
    np.testing.assert_allclose(c, ref, atol=1e-4)
    assert np.shape(g.cdf(x[0, 0])) == ()


def test_gaussian_cdf_full_covariance_2d_matches_integration():
    g = gauss2()
    mvn = stats.multivariate_normal([1.0, -2.0], COV2)
    sd = np.sqrt(np.diag(COV2))
    lo = g.mean - 12 * sd
    for pt in ([1.5, -1.0], [-0.5, -2.5], [3.0, -3.0]):
        res = integrate.cubature(mvn.pdf, lo, pt, rtol=1e-10, atol=1e-13)
        assert float(g.cdf(np.array(pt))) == pytest.approx(float(res.estimate), abs=1e-4)


def test_mixture_cdf_1d_matches_integration():
    mix = mix1()
    for x in (-3.0, -1.0, 0.4, 2.0, 5.5):
        ref, _ = integrate.quad(lambda t: ref_mix_pdf(t, MIX1_W, MIX1_M, MIX1_C), -np.inf, x, epsabs=1e-12)
        assert float(mix.cdf(x)) == pytest.approx(ref, abs=1e-9)
    xs = _rng(13).normal(size=(3, 5)) * 3
    ref = sum(w * stats.norm.cdf(xs, m[0], np.sqrt(c[0][0])) for w, m, c in zip(MIX1_W, MIX1_M, MIX1_C))
    np.testing.assert_allclose(mix.cdf(xs), ref, rtol=1e-12)


def test_mixture_cdf_2d_matches_sum_of_multivariate_normal_cdfs():
    mix = mix2()
    x = _rng(14).normal(size=(2, 2, 2)) + 1
    ref = np.array(
        [[sum(w * stats.multivariate_normal(m, c).cdf(x[i, j]) for w, m, c in zip(MIX2_W, MIX2_M, MIX2_C))
          for j in range(2)] for i in range(2)]
    )
    np.testing.assert_allclose(mix.cdf(x), ref, atol=1e-4)


def test_truncated_cdf_1d_matches_integration_and_truncnorm():
    tg = trunc1()
    a, b = (-1.0 - 0.5) / 1.2, (2.5 - 0.5) / 1.2
    tn = stats.truncnorm(a, b, loc=0.5, scale=1.2)
    for x in (-0.7, 0.0, 1.3, 2.4):
        ref, _ = integrate.quad(lambda t: np.exp(ref_trunc_logpdf_1d(t, 0.5, 1.2, -1.0, 2.5)), -1.0, x, epsabs=1e-13)
        assert float(tg.cdf(x)) == pytest.approx(ref, abs=1e-10)
        assert float(tg.cdf(x)) == pytest.approx(tn.cdf(x), abs=1e-12)
    # outside the support
    np.testing.assert_allclose(tg.cdf([-5.0, -1.0, 2.5, 9.0]), [0.0, 0.0, 1.0, 1.0], atol=1e-15)


def test_truncated_cdf_2d_is_product_of_marginals():
    tg = trunc2()
    x = _rng(15).normal(size=(3, 5, 2)) + [0.5, 0.5]
    ref = np.ones((3, 5))
    for i in range(2):
        ref = ref * ref_trunc_cdf_1d(x[..., i], TR2["loc"][i], TR2["scale"][i], TR2["lower"][i], TR2["upper"][i])
    c = tg.cdf(x)
    assert c.shape == (3, 5)
    np.testing.assert_allclose(c, ref, rtol=1e-10, atol=1e-14)


def test_uniform_cdf_matches_scipy_uniform():
    ub = ubox()
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([1.0, 3.0, 2.5])
    x = _rng(16).uniform(lo - 0.5, hi + 0.5, size=(3, 5, 3))
    ref = np.prod(stats.uniform(loc=lo, scale=hi - lo).cdf(x), axis=-1)
    c = ub.cdf(x)
    assert c.shape == (3, 5)
    np.testing.assert_allclose(c, ref, rtol=1e-12, atol=1e-15)
    assert float(ub.cdf(hi + 1)) == 1.0 and float(ub.cdf(lo - 1)) == 0.0


# ---------------------------------------------------------------------------
# Normalisation
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("make", [gauss1, mix1], ids=["gauss", "mixture"])
def test_1d_pdf_integrates_to_one(make):
    dist = make()
    total, _ = integrate.quad(lambda t: float(dist.pdf(t)), -np.inf, np.inf, epsabs=1e-12)
    assert total == pytest.approx(1.0, abs=1e-8)


def test_1d_truncated_and_uniform_pdf_integrate_to_one():
    tg = trunc1()
    total, _ = integrate.quad(lambda t: float(tg.pdf(t)), -4.0, 6.0, points=[-1.0, 2.5], epsabs=1e-12)
    assert total == pytest.approx(1.0, abs=1e-8)
    ub = UniformBox([-0.5], [1.5])
    total, _ = integrate.quad(lambda t: float(ub.pdf(t)), -3.0, 4.0, points=[-0.5, 1.5], epsabs=1e-12)
    assert total == pytest.approx(1.0, abs=1e-8)


@pytest.mark.parametrize("make", [gauss2, gauss_diag, mix2], ids=["gauss", "diag", "mixture"])
def test_2d_pdf_integrates_to_one(make):
    dist = make()
    sd = np.sqrt(np.diag(dist.cov))
    lo, hi = dist.mean - 14 * sd, dist.mean + 14 * sd
    res = integrate.cubature(dist.pdf, lo, hi, rtol=1e-10, atol=1e-13)
    assert float(res.estimate) == pytest.approx(1.0, abs=1e-7)


def test_2d_truncated_and_uniform_pdf_integrate_to_one():
    tg = trunc2()
    res = integrate.cubature(tg.pdf, [-0.5, -25.0], [1.5, 2.0], rtol=1e-10, atol=1e-13)
    assert float(res.estimate) == pytest.approx(1.0, abs=1e-7)
    ub = UniformBox([-1.0, 0.0], [1.0, 3.0])
    res = integrate.cubature(ub.pdf, [-1.0, 0.0], [1.0, 3.0], rtol=1e-10)
    assert float(res.estimate) == pytest.approx(1.0, abs=1e-10)
    # and no mass outside the box
    res = integrate.cubature(ub.pdf, [1.0, 0.0], [2.0, 3.0], rtol=1e-10, atol=1e-14)
    assert float(res.estimate) == pytest.approx(0.0, abs=1e-12)


# ---------------------------------------------------------------------------
# Sampling
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("name", list(ALL))
@pytest.mark.parametrize("shape, expect", [((), ()), (7, (7,)), ((3, 5), (3, 5))])
def test_sample_shape(name, shape, expect):
    dist = ALL[name]()
    s = dist.sample(_rng(17), shape)
    assert s.shape == expect + (dist.dim,)
    assert np.all(np.isfinite(s))


@pytest.mark.parametrize("name", list(ALL))
def test_sample_moments_match_mean_and_cov(name):
    dist = ALL[name]()
    s = dist.sample(_rng(18), (N_MC // 1000, 1000))
    assert np.asarray(dist.mean).shape == (dist.dim,)
    assert np.asarray(dist.cov).shape == (dist.dim, dist.dim)
    np.testing.assert_allclose(dist.cov, np.asarray(dist.cov).T, atol=1e-14)
    assert_moments(s, dist.mean, dist.cov)


@pytest.mark.parametrize("make, cdf", [
    (gauss1, lambda x: stats.norm.cdf(x, 0.7, 1.5)),
    (mix1, lambda x: sum(w * stats.norm.cdf(x, m[0], np.sqrt(c[0][0])) for w, m, c in zip(MIX1_W, MIX1_M, MIX1_C))),
    (trunc1, lambda x: ref_trunc_cdf_1d(x, 0.5, 1.2, -1.0, 2.5)),
    (lambda: UniformBox([-0.5], [1.5]), lambda x: stats.uniform(-0.5, 2.0).cdf(x)),
], ids=["gauss", "mixture", "truncated", "uniform"])
def test_1d_samples_follow_distribution_dkw(make, cdf):
    s = make().sample(_rng(19), N_MC)
    assert ks_distance(s, cdf) <= dkw_bound(N_MC)


def test_truncated_and_uniform_samples_stay_in_support():
    s = trunc2().sample(_rng(20), 50_000)
    assert np.all(s >= np.array(TR2["lower"])) and np.all(s <= np.array(TR2["upper"]))
    u = ubox().sample(_rng(21), 50_000)
    assert np.all(u >= [-1.0, 0.0, 2.0]) and np.all(u <= [1.0, 3.0, 2.5])


@pytest.mark.parametrize("make, w, m, c", [(mix1, MIX1_W, MIX1_M, MIX1_C), (mix2, MIX2_W, MIX2_M, MIX2_C)],
                         ids=["d1", "d2"])
def test_mixture_mean_cov_formulas(make, w, m, c):
    """Law of total variance, written as within + between component spread."""
    mix = make()
    w, m, c = np.asarray(w), np.asarray(m, float), np.asarray(c, float)
    mean = np.einsum("c,ci->i", w, m)
    dm = m - mean
    cov = np.einsum("c,cij->ij", w, c) + np.einsum("c,ci,cj->ij", w, dm, dm)
    np.testing.assert_allclose(mix.mean, mean, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(mix.cov, cov, rtol=1e-12, atol=1e-14)


def test_mixture_1d_moments_by_integration():
    mix = mix1()
    p = lambda t: ref_mix_pdf(t, MIX1_W, MIX1_M, MIX1_C)  # noqa: E731
    mean, _ = integrate.quad(lambda t: t * p(t), -np.inf, np.inf, epsabs=1e-12)
    var, _ = integrate.quad(lambda t: (t - mean) ** 2 * p(t), -np.inf, np.inf, epsabs=1e-12)
    assert float(mix.mean[0]) == pytest.approx(mean, abs=1e-9)
    assert float(mix.cov[0, 0]) == pytest.approx(var, rel=1e-9)


def test_mixture_component_frequencies():
    """Draws near each well-separated component occur with its weight."""
    mix = GaussianMixture.from_arrays([0.2, 0.5, 0.3], [[-20.0], [0.0], [20.0]], [[[1.0]], [[1.0]], [[1.0]]])
    s = mix.sample(_rng(22), N_MC)[:, 0]
    freqs = np.array([(s < -10).mean(), (np.abs(s) < 10).mean(), (s > 10).mean()])
    se = np.sqrt(np.array([0.2, 0.5, 0.3]) * (1 - np.array([0.2, 0.5, 0.3])) / N_MC)
    assert np.all(np.abs(freqs - [0.2, 0.5, 0.3]) <= NSIG * se)


@pytest.mark.parametrize("make", [trunc1, trunc2], ids=["d1", "d2"])
def test_truncated_moments_by_integration(make):
    tg = make()
    for i in range(tg.dim):
        loc, sc, lo, hi = (float(np.asarray(getattr(tg, k))[i]) for k in ("loc", "scale", "lower", "upper"))
        p = lambda t: np.exp(ref_trunc_logpdf_1d(t, loc, sc, lo, hi))  # noqa: E731
        mean, _ = integrate.quad(lambda t: t * p(t), lo, hi, epsabs=1e-12)
        var, _ = integrate.quad(lambda t: (t - mean) ** 2 * p(t), lo, hi, epsabs=1e-12)
        assert float(tg.mean[i]) == pytest.approx(mean, abs=1e-9)
        assert float(tg.cov[i, i]) == pytest.approx(var, rel=1e-8)
    np.testing.assert_array_equal(tg.cov, np.diag(np.diag(tg.cov)))


def test_uniform_moments_by_integration():
    ub = ubox()
    for i, (lo, hi) in enumerate([(-1.0, 1.0), (0.0, 3.0), (2.0, 2.5)]):
        mean, _ = integrate.quad(lambda t: t / (hi - lo), lo, hi)
        var, _ = integrate.quad(lambda t: (t - mean) ** 2 / (hi - lo), lo, hi)
        assert float(ub.mean[i]) == pytest.approx(mean, rel=1e-12, abs=1e-14)
        assert float(ub.cov[i, i]) == pytest.approx(var, rel=1e-10)


@pytest.mark.parametrize("params", POLAR_PARAMS, ids=["typical", "negative_speed", "far_heading", "wide_heading"])
def test_polar_mean_cov_match_monte_carlo_of_model(params):
    pr = polar(params)
    s = ref_polar_sample(_rng(23), N_MC, params)
    # reversed roles: the stated moments are the reference, the model draws the data
    assert_moments(s, pr.mean, pr.cov)
    # position block is exactly the position Gaussian, no position/velocity coupling
    np.testing.assert_allclose(pr.mean[[0, 2]], POS_M)
    np.testing.assert_allclose(pr.cov[np.ix_([0, 2], [0, 2])], POS_C)
    np.testing.assert_array_equal(pr.cov[np.ix_([0, 2], [1, 3])], 0.0)


def test_polar_sample_matches_model_monte_carlo():
    """Samples of sample() and of the written-out model agree in distribution (speed, heading)."""
    params = (3.0, 0.5, 0.8, 0.4)
    a = polar(params).sample(_rng(24), N_MC)
    speed = np.hypot(a[:, 1], a[:, 3])
    # speed ~ |N(3, 0.5^2)|; heading ~ N(0.8, 0.4^2): P(speed < 0) ~ 1e-9 and
    # P(heading outside (-pi, pi]) ~ 1e-8, so arctan2 recovers the heading draw.
    sm, ss, hm, hs = params
    assert ks_distance(speed, lambda x: stats.norm.cdf(x, sm, ss) - stats.norm.cdf(-x, sm, ss)) <= dkw_bound(N_MC)
    heading = np.arctan2(a[:, 3], a[:, 1])
    assert ks_distance(heading, lambda x: stats.norm.cdf(x, hm, hs)) <= dkw_bound(N_MC) + 1e-9


# ---------------------------------------------------------------------------
# Reproducibility and generators
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("name", list(ALL))
def test_same_seed_gives_identical_samples(name):
    dist = ALL[name]()
    a = dist.sample(np.random.default_rng(1234), (4, 6))
    b = dist.sample(np.random.default_rng(1234), (4, 6))
    c = dist.sample(np.random.default_rng(1235), (4, 6))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("name", list(ALL))
def test_sampling_uses_only_the_generator_passed(name):
    dist = ALL[name]()
    state = np.random.get_state()
    rng = np.random.default_rng(99)
    dist.sample(rng, 10)
    after = np.random.get_state()
    assert state[0] == after[0]
    np.testing.assert_array_equal(state[1], after[1])
    assert state[2:] == after[2:]
    # and it advances the generator that was passed
    assert not np.array_equal(rng.random(3), np.random.default_rng(99).random(3))


def test_spawn_generators_reproducible_and_independent():
    gens = spawn_generators(2024, 4)
    assert len(gens) == 4
    assert all(isinstance(g, np.random.Generator) for g in gens)
    draws = np.array([g.standard_normal(50_000) for g in gens])
    again = np.array([g.standard_normal(50_000) for g in spawn_generators(2024, 4)])
    np.testing.assert_array_equal(draws, again)
    from_ss = np.array([g.standard_normal(50_000) for g in spawn_generators(np.random.SeedSequence(2024), 4)])
    np.testing.assert_array_equal(draws, from_ss)
    other = np.array([g.standard_normal(50_000) for g in spawn_generators(2025, 4)])
    assert not np.array_equal(draws, other)
    # pairwise different and uncorrelated streams (|r| < 5/sqrt(n))
    corr = np.corrcoef(draws)
    for i in range(4):
        for j in range(i + 1, 4):
            assert not np.array_equal(draws[i], draws[j])
            assert abs(corr[i, j]) < NSIG / np.sqrt(draws.shape[1])
    # the children are not the parent stream either
    parent = np.random.default_rng(2024).standard_normal(50_000)
    assert all(not np.array_equal(parent, d) for d in draws)


def test_spawn_generators_drive_reproducible_monte_carlo_runs():
    g = gauss2()
    runs = [g.sample(r, 5) for r in spawn_generators(7, 3)]
    again = [g.sample(r, 5) for r in spawn_generators(7, 3)]
    for a, b in zip(runs, again):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(runs[0], runs[1])


# ---------------------------------------------------------------------------
# Input validation
# ---------------------------------------------------------------------------

def test_input_error_is_value_error():
    assert issubclass(InputError, ValueError)


@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: Gaussian([0.0, 0.0], [[1.0, 0.5], [0.2, 1.0]]), r"cov.*symmetric"),
        (lambda: Gaussian([0.0, 0.0], [[1.0, 2.0], [2.0, 1.0]]), r"cov.*positive definite"),
        (lambda: Gaussian([0.0, 0.0], [[1.0, 1.0], [1.0, 1.0]]), r"cov.*positive definite"),
        (lambda: Gaussian([0.0, 0.0], [[0.0, 0.0], [0.0, 1.0]]), r"cov.*positive definite"),
        (lambda: Gaussian([0.0, 0.0], [[-1.0]]), r"cov"),
        (lambda: Gaussian([0.0, 0.0], np.eye(3)), r"cov"),
        (lambda: Gaussian([0.0, 0.0], [1.0, 1.0]), r"cov.*square"),
        (lambda: Gaussian([np.nan, 0.0], np.eye(2)), r"mean.*finite"),
        (lambda: Gaussian([np.inf, 0.0], np.eye(2)), r"mean.*finite"),
        (lambda: Gaussian([0.0, -np.inf], np.eye(2)), r"mean.*finite"),
        (lambda: Gaussian([0.0, 0.0], [[1.0, np.nan], [np.nan, 1.0]]), r"cov.*finite"),
        (lambda: GaussianMixture.from_arrays([0.5, 0.6], [[0.0], [1.0]], [[[1.0]], [[1.0]]]), r"weights.*sum to 1"),
        (lambda: GaussianMixture.from_arrays([0.3, 0.3], [[0.0], [1.0]], [[[1.0]], [[1.0]]]), r"weights.*sum to 1"),
        (lambda: GaussianMixture.from_arrays([1.2, -0.2], [[0.0], [1.0]], [[[1.0]], [[1.0]]]), r"weights"),
        (lambda: GaussianMixture.from_arrays([np.nan, 1.0], [[0.0], [1.0]], [[[1.0]], [[1.0]]]), r"weights"),
        (lambda: GaussianMixture.from_arrays([0.5, 0.3, 0.2], [[0.0], [1.0]], [[[1.0]], [[1.0]]]), r"weights"),
        (lambda: GaussianMixture.from_arrays([0.5, 0.5], [[0.0], [1.0]], [[[1.0]], [[-1.0]]]), r"cov.*positive"),
        (lambda: GaussianMixture.from_arrays([0.5, 0.5], [[0.0], [np.nan]], [[[1.0]], [[1.0]]]), r"mean"),
        (lambda: GaussianMixture(np.array([1.0]), ()), r"components"),
        (lambda: GaussianMixture(np.array([0.5, 0.5]), (Gaussian([0.0], [[1.0]]), Gaussian([0.0, 0.0], np.eye(2)))),
         r"components"),
        (lambda: UniformBox([0.0, 1.0], [1.0, 1.0]), r"lower.*upper"),
        (lambda: UniformBox([0.0, 2.0], [1.0, 1.0]), r"lower.*upper"),
        (lambda: UniformBox([0.0, 0.0], [1.0, 1.0, 1.0]), r"upper"),
        (lambda: UniformBox([0.0, np.nan], [1.0, 1.0]), r"lower"),
        (lambda: TruncatedGaussian([0.0], [1.0], [1.0], [1.0]), r"lower.*upper"),
        (lambda: TruncatedGaussian([0.0], [1.0], [2.0], [1.0]), r"lower.*upper"),
        (lambda: TruncatedGaussian([0.0, 0.0], [1.0, 1.0], [0.0, np.inf], [1.0, np.inf]), r"lower.*upper"),
        (lambda: TruncatedGaussian([0.0], [1.0], [np.nan], [1.0]), r"lower"),
        (lambda: TruncatedGaussian([0.0, 0.0], [1.0, 1.0], [-1.0, -1.0, -1.0], [1.0, 1.0]), r"lower"),
        (lambda: TruncatedGaussian([0.0, 0.0], [1.0, 1.0], [-1.0, -1.0], np.ones((3, 2))), r"upper"),
        (lambda: TruncatedGaussian([0.0], [0.0], [-1.0], [1.0]), r"scale"),
        (lambda: TruncatedGaussian([0.0], [-1.0], [-1.0], [1.0]), r"scale"),
        (lambda: TruncatedGaussian([np.nan], [1.0], [-1.0], [1.0]), r"loc"),
        (lambda: PolarVelocityPrior([0, 0], np.eye(2), 1.0, 0.0, 0.0, 0.1), r"speed_std"),
        (lambda: PolarVelocityPrior([0, 0], np.eye(2), 1.0, 0.5, 0.0, -0.1), r"heading_std"),
        (lambda: PolarVelocityPrior([0, 0], np.eye(2), np.nan, 0.5, 0.0, 0.1), r"speed_mean"),
        (lambda: PolarVelocityPrior([0, 0], np.eye(2), 1.0, 0.5, np.inf, 0.1), r"heading_mean"),
        (lambda: PolarVelocityPrior([0, 0], np.eye(2), [1.0, 2.0], 0.5, 0.0, 0.1), r"speed_mean"),
        (lambda: PolarVelocityPrior([0, 0, 0], np.eye(2), 1.0, 0.5, 0.0, 0.1), r"position_mean"),
        (lambda: PolarVelocityPrior([0, 0], [[1.0, 2.0], [2.0, 1.0]], 1.0, 0.5, 0.0, 0.1), r"position_cov"),
        (lambda: PolarVelocityPrior([0, 0], [[1.0, 0.5], [0.0, 1.0]], 1.0, 0.5, 0.0, 0.1), r"position_cov"),
    ],
)
def test_bad_parameters_raise_input_error_naming_parameter(build, match):
    with pytest.raises(InputError, match=match):
        build()


WRONG_X = {
    "gauss1": None,  # any trailing size is a batch axis in one dimension
    "gauss2": [np.zeros((5, 3)), np.zeros(3), 1.0],
    "gauss3": [np.zeros((5, 2)), np.zeros(4), 0.0],
    "gauss_diag": [np.zeros((2, 3)), 2.0],
    "mix2": [np.zeros((5, 3)), 1.0],
    "trunc2": [np.zeros((5, 3)), 0.5],
    "ubox": [np.zeros((5, 2)), np.zeros(4), 0.0],
    "polar": [np.zeros((5, 2)), np.zeros(3), 1.0],
}


@pytest.mark.parametrize(
    "name, method",
    [(k, m) for k, v in WRONG_X.items() if v is not None for m in ("logpdf", "pdf", "cdf")
     if not (m == "cdf" and k.startswith("polar"))],  # PolarVelocityPrior has no cdf
)
def test_wrong_dimension_x_raises_input_error(name, method):
    dist = ALL[name]()
    for x in WRONG_X[name]:
        with pytest.raises(InputError, match=r"\bx\b"):
            getattr(dist, method)(x)


def test_polar_has_no_cdf():
    with pytest.raises(NotImplementedError):
        polar().cdf(np.zeros(4))


@pytest.mark.parametrize("name", list(ALL))
@pytest.mark.parametrize(
    "bad_rng", [np.random.RandomState(0), 0, None, np.random.default_rng(0).bit_generator],
    ids=["RandomState", "int", "None", "BitGenerator"],
)
def test_sample_rejects_non_generator_rng(name, bad_rng):
    with pytest.raises(InputError, match="rng"):
        ALL[name]().sample(bad_rng, 3)


def test_truncated_far_tail_is_accurate():
    """Truncation to [6, 8] of N(0, 1) (mass ~1e-9): closed forms stay accurate where 1 - Phi cancels."""
    t = TruncatedGaussian([0.0], [1.0], [6.0], [8.0])
    ref = stats.truncnorm(6.0, 8.0)
    x = np.linspace(5.5, 8.5, 31)[:, None]
    np.testing.assert_allclose(t.cdf(x), ref.cdf(x[:, 0]), rtol=1e-9, atol=1e-15)
    inside = (x[:, 0] >= 6) & (x[:, 0] <= 8)
    np.testing.assert_allclose(t.logpdf(x)[inside], ref.logpdf(x[inside, 0]), rtol=1e-9)
    assert np.all(np.isneginf(t.logpdf(x)[~inside]))
    s = t.sample(np.random.default_rng(0), 20_000)[:, 0]
    assert s.min() >= 6.0 and s.max() <= 8.0
    assert abs(s.mean() - ref.mean()) < 5 * ref.std() / np.sqrt(s.size)


@pytest.mark.parametrize("make", [mix1, mix2], ids=["d1", "d2"])
@pytest.mark.parametrize("shape", [(), (7,), (3, 4)])
def test_mixture_sample_draws_what_generator_choice_and_the_components_draw(make, shape):
    """A seed's samples are those of the plain recipe, bit for bit, and leave the Generator where it leaves it:
    the label from ``rng.choice(p=weights)``, then the normals, each point from its own component."""
    mix = make()
    a, b = _rng(11), _rng(11)
    for _ in range(200):
        got = mix.sample(a, shape)
        labels = b.choice(len(mix.components), size=shape, p=mix.weights)
        z = b.standard_normal(shape + (mix.dim,))
        ref = np.empty(shape + (mix.dim,))
        for c, comp in enumerate(mix.components):
            sel = labels == c
            ref[sel] = comp.mean + z[sel] @ comp._chol.T
        assert got.shape == ref.shape
        np.testing.assert_array_equal(got, ref)
    assert a.bit_generator.state == b.bit_generator.state
