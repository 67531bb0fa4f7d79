"""Fused numba kernels: the model translation, the likelihoods and the filter against the NumPy engine.

The strongest check: the kernels' draws (filters.fused.streams, tests/test_streams.py) are
NumPy's, bit for bit, and the fused filter draws in the NumPy engine's order, so one run of it reproduces
``run_sir(runs=1)`` with the same seed to rounding — for every resampling
scheme, both ESS rules, the Round-Robin, all-sensor and binary likelihoods.
"""
from __future__ import annotations

import math

import casadi as ca
import numba
import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from designer import Gaussian, InputError, Model, Sensor, simulate
from designer.codegen import UnsupportedOperation
from designer.jit import _atan2, compile_source, jit_model, scalar_source
from designer.noise import GaussianMixture, TruncatedGaussian, spawn_generators
from filters.attacks import binary_sensor_channel, deception_attack, round_robin_schedule
from filters.binary import binary_coefficients, binary_loglik
from filters.fused import binary_affine_loglik, packets_loglik, sir_binary, sir_packets
from filters.fused.primitives import exp_nonpos, wrap_angle
from filters.fused.resampling import cumsum_to_one, inverse_cdf, systematic
from filters.particle import run_sir
from filters.resampling import SCHEMES
from filters.result import FilterResult
from filters.rrp import all_sensors_loglik, deception_terms, rrp_loglik, wrap_angles
from studies.scenarios import SCENARIOS, load_scenario

ETA = 0.2


# ----------------------------------------------------------------------------- shared data
@pytest.fixture(scope="module")
def rb():
    """target-range-bearing with Round-Robin and all-sensor packets, clean and attacked."""
    sc = load_scenario("target-range-bearing")
    m = sc.model
    R, K = 4, 30
    rng = np.random.default_rng(10)
    tr = sc.simulate(rng, K, batch=R)
    y = tr.per_sensor(m)
    y[..., 1] = wrap_angles(y, [1])[..., 1]
    sched = round_robin_schedule(K, m.n_sensors, 1)
    ys = y[:, np.arange(K), sched]
    box = sc.channel.deception
    return dict(sc=sc, m=m, R=R, K=K, x=tr.x, y=y, sched=sched, ys=ys, box=box,
                rr_att=deception_attack(ys, ETA, box, rng).y, all_att=deception_attack(y, ETA, box, rng).y)


@pytest.fixture(scope="module")
def binary():
    sc = load_scenario("target-binary-energy")
    ch = sc.channel
    kw = dict(threshold=ch.threshold, gain=ch.gain, channel_noise=ch.channel_noise, deception=ch.deception)
    probs = dict(dos_prob=0.1, deception_prob=0.1, flip_prob=0.1)
    R, K = 3, 25
    rng = np.random.default_rng(20)
    tr = sc.simulate(rng, K, batch=R)
    y = binary_sensor_channel(tr.z, **probs, rng=rng, **kw).y  # (R, K, S)
    return dict(sc=sc, m=sc.model, kw=kw, probs=probs, R=R, K=K, x=tr.x, y=y)


# ----------------------------------------------------------------------------- model translation
def _states(sc, n=300):
    rng = np.random.default_rng(1)
    X = sc.simulate(rng).x
    X = X[rng.integers(0, X.shape[0], n)]
    return X + 0.5 * rng.standard_normal(X.shape) * np.maximum(np.abs(X), 1.0)


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_jit_model_agrees_with_the_model_layer(name):
    sc = load_scenario(name)
    m = sc.model
    if m.n_u or m.n_modes:
        with pytest.raises(InputError, match="inputs" if m.n_u else "modes"):
            jit_model(m)
        return
    jm = jit_model(m)
    assert jit_model(m) is jm  # cached per model
    X = _states(sc)
    f_out, h_out, hall = np.empty(m.n_x), np.empty(max(m.sensor_dims)), np.empty(m.n_z)
    F, Hall = m.f(X, 3), m.h_all(X, 4)
    H = [m.h(i, X, 4) for i in range(m.n_sensors)]
    for n, x in enumerate(X):
        jm.f(x, 3.0, f_out)
        np.testing.assert_allclose(f_out, F[n], rtol=1e-12, atol=1e-12)
        jm.h_all(x, 4.0, hall)
        np.testing.assert_allclose(hall, Hall[n], rtol=1e-12, atol=1e-12)
        for i in range(m.n_sensors):
            jm.h(i, x, 4.0, h_out)
            np.testing.assert_allclose(h_out[:m.sensor_dims[i]], H[i][n], rtol=1e-12, atol=1e-12)


def test_scalar_translation_covers_the_operations():
    x = ca.SX.sym("x", 3)
    a, b, c = x[0], x[1], x[2]
    exprs = [
        a + b, a - b, a * b, a / (1 + b**2), -a, 2 * a, a**2, 1 / (1 + c**2), ca.exp(a), ca.log(1 + b**2),
        ca.sqrt(1 + a**2), ca.fabs(a) ** 1.5, ca.fabs(a) ** b, ca.sin(a), ca.cos(b), ca.tan(0.3 * c),
        ca.asin(ca.tanh(a)), ca.acos(ca.tanh(b)), ca.atan(c), ca.atan2(a, b), ca.sinh(a), ca.cosh(b), ca.tanh(c),
        ca.asinh(a), ca.acosh(1 + b**2), ca.atanh(0.5 * ca.tanh(c)), ca.sign(b), ca.floor(3 * a), ca.ceil(3 * b),
        ca.fmod(5 * a, 1.3), ca.fmin(a, b), ca.fmax(b, c), ca.if_else(a > b, a * c, b - c),
        ca.logic_and(a > 0, b < 0), ca.logic_or(a > 0, b < 0), ca.logic_not(c > 0), a == b, a != c, a <= c,
        ca.erf(a), ca.log1p(b**2), ca.expm1(c), ca.hypot(a, c), ca.copysign(a, b), ca.DM(7.5), ca.DM(0.0) * a,
    ]
    fun = ca.Function("many", [x], [ca.vertcat(*exprs)])
    g = compile_source(scalar_source(fun, "g", ["x"]), "g", "many")
    X = np.random.default_rng(0).normal(size=(200, 3)) * 2
    X[0] = [1.0, 1.0, -2.0]  # ties for ==, fmin, if_else
    out = np.empty(len(exprs))
    for row in X:
        g(row, out)
        np.testing.assert_allclose(out, np.array(fun(row)).ravel(), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("expr, op", [(lambda v: ca.erfinv(v[0] / 10), "ERFINV"),
                                      (lambda v: ca.remainder(v[0], v[1]), "REMAINDER")])
def test_unsupported_operation_is_named(expr, op):
    x = ca.SX.sym("x", 2)
    with pytest.raises(UnsupportedOperation, match=op):
        scalar_source(ca.Function("r", [x], [expr(x)]), "r", ["x"])


# ----------------------------------------------------------------------------- branch-free numerics
@numba.njit
def _atan2_all(y, x, out):
    for i in range(x.shape[0]):
        out[i] = _atan2(y[i], x[i])


@numba.njit
def _exp_all(d, out):
    for i in range(d.shape[0]):
        out[i] = exp_nonpos(d[i])


@numba.njit
def _wrap_all(r, out):
    for i in range(r.shape[0]):
        out[i] = wrap_angle(r[i])


def _ulps(ours, exact):
    """|ours − exact| in units of the last place of the (double) exact value, exact in long double."""
    return np.abs((ours.astype(np.longdouble) - exact) / np.spacing(np.abs(exact.astype(np.float64))))


def test_branch_free_atan2_is_within_rounding_of_libm():
    rng = np.random.default_rng(3)
    n = 200_000
    base = rng.normal(size=n)
    cases = [
        (rng.normal(size=n), rng.normal(size=n)),
        tuple(rng.normal(size=n) * 10.0 ** rng.uniform(-300, 300, n) for _ in range(2)),  # every magnitude
        (base * np.choose(rng.integers(0, 3, n), [np.tan(np.pi / 16), np.tan(3 * np.pi / 16), np.tan(np.pi / 8)])
         * (1 + 1e-6 * rng.normal(size=n)), base),  # around the reduction's interval ends
        (rng.normal(size=n) * 1e-310, rng.normal(size=n) * 1e-310),  # subnormal operands
    ]
    out = np.empty(n)
    for y, x in cases:
        _atan2_all(y, x, out)
        exact = np.arctan2(y.astype(np.longdouble), x.astype(np.longdouble))
        assert _ulps(out, exact).max() <= 2.5
    special = [0.0, -0.0, 1.0, -2.5, np.inf, -np.inf, np.nan, 5e-324, -1.7e308]
    for y in special:
        for x in special:
            ours, ref = _atan2(y, x), math.atan2(y, x)
            same = ours == ref and math.copysign(1, ours) == math.copysign(1, ref)  # signed zeros too
            assert (np.isnan(ours) and np.isnan(ref)) or same or abs(ours - ref) <= 2 * np.spacing(abs(ref)), (y, x)


def test_branch_free_exp_is_within_rounding_and_flushes_below_the_normal_range():
    d = np.concatenate([-np.random.default_rng(4).uniform(0, 708, 200_000), [0.0, -1e-300, -707.9]])
    out = np.empty_like(d)
    _exp_all(d, out)
    assert _ulps(out, np.exp(d.astype(np.longdouble))).max() <= 1.25  # libm's exp: under 1
    special = np.array([-708.5, -745.0, -1e300, -np.inf, np.nan])
    out = np.empty_like(special)
    _exp_all(special, out)
    assert np.array_equal(out[:4], np.zeros(4)) and np.isnan(out[4])


def test_branch_free_wrap_is_numpys_mod():
    """Outside (−π, π] the same double as filters.rrp.wrap_angles (numpy.mod); inside, the residual itself."""
    rng = np.random.default_rng(5)
    r = np.concatenate([rng.uniform(-40, 40, 100_000), np.pi + 2 * np.pi * np.arange(-5, 6), [np.pi, -np.pi]])
    out = np.empty_like(r)
    _wrap_all(r, out)
    inside = (r > -np.pi) & (r <= np.pi)
    assert np.array_equal(out[inside], r[inside])
    assert np.array_equal(out[~inside], wrap_angles(r[:, None], [0])[~inside, 0])
    nan = np.empty(3)
    _wrap_all(np.array([np.nan, np.inf, -np.inf]), nan)
    assert np.all(np.isnan(nan))


@pytest.mark.parametrize("M", [60, 61, 63, 500])
def test_branch_free_systematic_resampling_matches_the_inverse_cdf(M):
    """Degenerate weights (zeros, one dominant particle, all but the last zero) and generic ones, u0 at its ends
    and a hair from them (with equal weights, ``M c_i - u0`` is then within the margin of an integer: the exact
    path), for particle counts that are and are not multiples of the four positions per step of the maxima."""
    rng = np.random.default_rng(6)
    cases = [np.ones(M), rng.exponential(size=M), np.where(rng.random(M) < 0.7, 0.0, rng.random(M)),
             np.eye(M)[17] + 1e-300, np.eye(M)[M - 1], np.eye(M)[0], np.exp(rng.normal(0, 8, M))]
    cdf, u, a, b = np.empty(M), np.empty(M), np.empty(M, np.int64), np.empty(M, np.int64)
    for W in cases:
        for u0 in np.concatenate([rng.random(20), [0.0, 1e-13, 0.5, 1 - 1e-13, 1 - 2.0**-53]]):
            systematic(W, 1.0 / W.sum(), u0, a, np.empty(M), np.empty(M + 1))
            cumsum_to_one(W, 1.0 / W.sum(), cdf)
            u[:] = (np.arange(M) + u0) / M
            inverse_cdf(cdf, u, b)
            assert np.array_equal(a, b)
            assert np.all(W[a][u < 1.0] > 0)  # u0 = 1 - 2^-53 rounds the last u_m to 1: the last particle


@pytest.mark.slow
def test_many_packets_fold_the_likelihood_factor(rb):
    """Hundreds of packets at one step: the product of the log-sum-exp factors is folded into the log part."""
    m, R, P = rb["m"], 1, 700  # 3^700 overflows a double: folded every 628 packets
    x = _particles_around(m, rb["x"][0, 8], R, 20, 7, np.array([3.0, 0.3, 3.0, 0.3]))
    y1 = rb["rr_att"][:1, 7]
    lc, att1 = deception_terms(y1, ETA, rb["box"])
    one = packets_loglik(m, x, 8, [2], y1, attack=att1, log_clean=lc, angles=[1])
    many = packets_loglik(m, x, 8, np.full(P, 2), np.repeat(y1[:, None], P, 1), attack=np.repeat(att1[:, None], P, 1),
                          log_clean=lc, angles=[1])
    assert np.all(np.isfinite(many))
    np.testing.assert_allclose(many, P * one, rtol=1e-12)


# ----------------------------------------------------------------------------- likelihoods
def _particles_around(m, x_true, R, M, seed, spread):
    rng = np.random.default_rng(seed)
    return x_true[None, None, :] + spread * rng.standard_normal((R, M, m.n_x))


def test_packet_likelihood_equals_the_rrp_likelihoods(rb):
    m, R, k = rb["m"], rb["R"], 7
    x = _particles_around(m, rb["x"][0, k + 1], R, 400, 0, np.array([6.0, 0.3, 6.0, 0.3]))
    s = rb["sched"][k]
    for y, kw, ref in (
        (rb["rr_att"][:, k], dict(), rrp_loglik(m, rb["sched"], angles=[1])),
        (rb["rr_att"][:, k], None, rrp_loglik(m, rb["sched"], attack_prob=ETA, signal=rb["box"], angles=[1])),
        (rb["ys"][:, k], dict(), rrp_loglik(m, rb["sched"], angles=[1])),
    ):
        if kw is None:
            lc, att = deception_terms(y, ETA, rb["box"])
            kw = dict(attack=att, log_clean=lc)
        ours = packets_loglik(m, x, k + 1, [s], y, angles=[1], **kw)
        np.testing.assert_allclose(ours, ref(x, k + 1, y), rtol=1e-12, atol=1e-12)
    # PF-DA: every sensor's packet, attack-aware, against all_sensors_loglik; (sensor, component) pairs
    y = rb["all_att"][:, k]  # (R, 4, 2)
    lc, att = deception_terms(y, ETA, rb["box"])
    ours = packets_loglik(m, x, k + 1, np.arange(4), y, attack=att, log_clean=lc,
                          angles=rb["sc"].model.angle_components)
    ref = all_sensors_loglik(m, attack_prob=ETA, signal=rb["box"], angles=[1])(x, k + 1, y.reshape(R, 8))
    np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=1e-12)


@pytest.mark.slow
def test_bearing_residuals_are_wrapped(rb):
    """Targets behind the sensors' line see bearings near ±π: a residual across the cut is small."""
    m = rb["m"]
    x = np.array([[[-30.0, 0.0, 30.0 + d, 0.0] for d in np.linspace(0.01, 0.5, 41)]])  # bearings just below π
    y = np.array([[30.0, -np.pi + 0.003]])  # measured just across the cut
    ref = rrp_loglik(m, np.array([1]), angles=[1])(x, 1, y)
    ours = packets_loglik(m, x, 1, [1], y, angles=[(1, 1)])
    np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=1e-12)
    unwrapped = packets_loglik(m, x, 1, [1], y)
    assert np.all(ours > unwrapped + 100)  # without wrapping the residual would be ~2π


def _custom_model(noise):
    """CV target with range-bearing sensors whose noise is ``noise`` (Gaussian with mean, or a 3-mixture)."""
    x = ca.SX.sym("x", 4)
    sensors = []
    for i, (sx, sy) in enumerate([(0.0, 0.0), (10.0, 40.0)]):
        dx, dy = x[0] - sx, x[2] - sy
        sensors.append(Sensor(f"s{i}", ca.vertcat(ca.sqrt(dx**2 + dy**2), ca.atan2(dy, dx)), noise))
    f = ca.vertcat(x[0] + x[1], x[1], x[2] + x[3], x[3])
    Q = 0.01 * np.array([[1 / 3, 1 / 2, 0, 0], [1 / 2, 1, 0, 0], [0, 0, 1 / 3, 1 / 2], [0, 0, 1 / 2, 1]])
    return Model("custom", x, f, sensors, Gaussian.zero_mean(Q), Gaussian([20, 0.3, 20, 0.3], np.eye(4)))


@pytest.mark.parametrize("noise", [
    Gaussian([0.3, -0.01], [[4.0, 0.05], [0.05, 0.002]]),
    GaussianMixture.from_arrays([0.5, 0.3, 0.2], [[0, 0], [1.0, 0.01], [-2.0, 0.0]],
                                [np.diag([1.0, 1e-3]), [[9.0, 0.1], [0.1, 0.01]], np.diag([25.0, 0.05])]),
])
@pytest.mark.slow
def test_packet_likelihood_with_full_covariances_and_means(noise):
    m = _custom_model(noise)
    R = 2
    x = _particles_around(m, np.array([25.0, 0.3, 22.0, 0.3]), R, 300, 3, 4.0)
    y = np.array([[24.0, 0.9], [35.0, 0.5]])
    box = load_scenario("target-range-bearing").channel.deception
    for i in (0, 1):
        np.testing.assert_allclose(packets_loglik(m, x, 2, [i], y, angles=[1]),
                                   rrp_loglik(m, np.array([i, i]), angles=[1])(x, 2, y), rtol=1e-12, atol=1e-12)
        lc, att = deception_terms(y, 0.3, box)
        np.testing.assert_allclose(packets_loglik(m, x, 2, [i], y, attack=att, log_clean=lc, angles=[1]),
                                   rrp_loglik(m, np.array([i, i]), attack_prob=0.3, signal=box, angles=[1])(x, 2, y),
                                   rtol=1e-12, atol=1e-12)


def test_binary_coefficients_reproduce_the_binary_likelihood(binary):
    m, R = binary["m"], binary["R"]
    x = _particles_around(m, binary["x"][0, 5], R, 300, 4, np.array([15.0, 0.3, 15.0, 0.3]))
    y = binary["y"][:, 4]  # (R, S)
    for probs in (binary["probs"], dict(dos_prob=0.3, deception_prob=0.05, flip_prob=0.7), {}):
        A, B = binary_coefficients(y, **probs, **binary["kw"])
        h = m.h_all(x, 5)
        c = np.stack([s.noise.cdf(binary["kw"]["threshold"] - h[..., i:i + 1]) for i, s in enumerate(m.sensors)], -1)
        ref = binary_loglik(m, **probs, **binary["kw"])(x, 5, y)
        p = A[:, None, :] + B[:, None, :] * c  # the affine form, per sensor
        np.testing.assert_allclose(np.log(p).sum(-1), ref, rtol=1e-10, atol=1e-10)
        ours = binary_affine_loglik(m, x, 5, A, B, threshold=binary["kw"]["threshold"])
        np.testing.assert_allclose(ours, ref, rtol=1e-10, atol=1e-10)


# ----------------------------------------------------------------------------- the filter against run_sir
def _same_as_run_sir(ours, ref, covariance=False):
    np.testing.assert_allclose(ours.mean, ref.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(ours.ess, ref.ess, rtol=1e-10)
    np.testing.assert_allclose(ours.loglik, ref.loglik, rtol=1e-10)
    assert np.array_equal(ours.resampled, ref.resampled)
    assert not ours.collapsed.any()
    if covariance:
        np.testing.assert_allclose(ours.cov, ref.cov, rtol=0, atol=1e-10)


@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("thr", [1.0, 0.5])
def test_one_run_reproduces_run_sir_round_robin(rb, scheme, thr):
    m, M = rb["m"], 300
    for r, attack in ((0, False), (1, True)):
        y = rb["rr_att"][r:r + 1]
        kw, ll = {}, rrp_loglik(m, rb["sched"], angles=[1])
        if attack:
            lc, att = deception_terms(y, ETA, rb["box"])
            kw, ll = dict(attack=att, log_clean=lc), rrp_loglik(m, rb["sched"], attack_prob=ETA, signal=rb["box"],
                                                               angles=[1])
        ref = run_sir(m, y, np.random.default_rng(100 + r), particles=M, runs=1, loglik=ll, resampler=scheme,
                      ess_threshold=thr).detail
        g = np.random.default_rng(100 + r)
        x0 = m.prior.sample(g, (1, M))  # run_sir's first draw
        ours = sir_packets(m, x0, [g], rb["sched"], y, angles=[1], resampler=scheme, ess_threshold=thr,
                           covariance=True, **kw).detail
        _same_as_run_sir(ours, ref, covariance=True)
        if thr < 1.0:
            assert not ours.resampled.all()


@pytest.mark.parametrize("bit_generator", [np.random.PCG64, np.random.MT19937], ids=lambda b: b.__name__)
def test_one_run_reproduces_run_sir_all_sensors(rb, bit_generator):
    """Also with a Generator on another bit generator than NumPy's default (its stream calls its C functions)."""
    m, M, K = rb["m"], 300, rb["K"]
    y = rb["all_att"][2:3]
    lc, att = deception_terms(y, ETA, rb["box"])
    ref = run_sir(m, y.reshape(1, K, 8), np.random.Generator(bit_generator(5)), particles=M, runs=1,
                  loglik=all_sensors_loglik(m, attack_prob=ETA, signal=rb["box"], angles=[1])).detail
    g = np.random.Generator(bit_generator(5))
    ours = sir_packets(m, m.prior.sample(g, (1, M)), [g], np.tile(np.arange(4), (K, 1)), y, attack=att,
                       log_clean=lc, angles=[1]).detail
    _same_as_run_sir(ours, ref)
    assert ours.cov is None


@pytest.mark.parametrize("scheme", ["systematic", "residual"])
def test_one_run_reproduces_run_sir_binary(binary, scheme):
    m, M = binary["m"], 300
    y = binary["y"][1:2]
    ref = run_sir(m, y, np.random.default_rng(8), particles=M, runs=1, resampler=scheme, ess_threshold=0.7,
                  loglik=binary_loglik(m, **binary["probs"], **binary["kw"])).detail
    g = np.random.default_rng(8)
    A, B = binary_coefficients(y, **binary["probs"], **binary["kw"])
    ours = sir_binary(m, m.prior.sample(g, (1, M)), [g], A, B, threshold=binary["kw"]["threshold"],
                      resampler=scheme, ess_threshold=0.7).detail
    _same_as_run_sir(ours, ref)


def test_matches_the_kalman_filter_on_a_linear_model():
    """Against filterpy's Kalman filter (an independent implementation): means and log-likelihood."""
    x = ca.SX.sym("x", 2)
    A, Hm = np.array([[0.9, 0.2], [-0.1, 0.95]]), np.array([[1.0, 0.5]])
    sensor = Sensor("s", ca.mtimes(ca.DM(Hm), x), Gaussian.zero_mean([[0.3]]))
    model = Model("lin", x, ca.mtimes(ca.DM(A), x), [sensor], Gaussian.zero_mean(0.05 * np.eye(2)),
                  Gaussian([1.0, -1.0], 0.5 * np.eye(2)))
    K = 25
    traj = simulate(model, K, np.random.default_rng(5))
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x, kf.P, kf.F, kf.H = model.prior.mean.copy(), model.prior.cov.copy(), A, Hm
    kf.Q, kf.R = model.process_cov, model.measurement_cov(0)
    means_kf, ll_kf = [], 0.0
    for zk in traj.z:
        kf.predict()
        kf.update(zk)
        means_kf.append(kf.x.copy())
        ll_kf += kf.log_likelihood
    runs, M = 16, 3000
    gens = spawn_generators(6, runs)
    x0 = np.stack([model.prior.sample(g, M) for g in gens])
    y = np.broadcast_to(traj.z[None, :, None, :], (runs, K, 1, 1))
    res = sir_packets(model, x0, gens, np.zeros((K, 1), int), y, threads=2).detail
    diff = res.mean[:, 1:] - np.array(means_kf)[None]
    se = diff.std(0, ddof=1) / np.sqrt(runs)
    assert np.all(np.abs(diff.mean(0)) < 5 * se + 5e-3)
    assert np.sqrt((diff**2).mean()) < 0.05
    assert abs(ll_kf - res.loglik.mean()) < 5 * res.loglik.std(ddof=1) / np.sqrt(runs) + 0.05


# ----------------------------------------------------------------------------- threads, seeds, numerics
def _runs(rb, seed, threads, R=None):
    m, R = rb["m"], R or rb["R"]
    gens = spawn_generators(seed, R)
    x0 = np.stack([m.prior.sample(g, 200) for g in gens])
    lc, att = deception_terms(rb["rr_att"][:R], ETA, rb["box"])
    return sir_packets(m, x0, gens, rb["sched"], rb["rr_att"][:R], attack=att, log_clean=lc, angles=[1],
                       threads=threads).detail


def test_results_do_not_depend_on_threads_and_are_seeded(rb):
    a, b, c = _runs(rb, 3, 1), _runs(rb, 3, 2), _runs(rb, 3, 2)
    for f in ("mean", "ess", "loglik", "resampled", "collapsed"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
        assert np.array_equal(getattr(b, f), getattr(c, f)), f
    d = _runs(rb, 4, 2)
    assert not np.allclose(a.mean, d.mean)
    assert not np.allclose(a.mean[0], a.mean[1])  # runs are independent
    # a run's result depends on its own generator only: run 2 alone equals run 2 of the batch
    m = rb["m"]
    g = spawn_generators(3, rb["R"])[2]
    x0 = m.prior.sample(g, (1, 200))
    lc, att = deception_terms(rb["rr_att"][2:3], ETA, rb["box"])
    alone = sir_packets(m, x0, [g], rb["sched"], rb["rr_att"][2:3], attack=att, log_clean=lc, angles=[1]).detail
    assert np.array_equal(alone.mean[0], a.mean[2]) and alone.loglik[0] == a.loglik[2]


def test_collapse_is_recorded_and_weights_stay_finite(rb, binary):
    """Every particle's likelihood is -inf at chosen steps: uniform weights, resampled as run_sir resamples them (its
    rule: every step here), the filter goes on; one run reproduces run_sir through the collapses."""
    m, R, K = rb["m"], 2, rb["K"]
    y = rb["ys"][:R].copy()
    y[:, [5, 6, 20]] = 1e200  # finite, but every squared residual overflows: log p = -inf
    gens = spawn_generators(1, R)
    x0 = np.stack([m.prior.sample(g, 300) for g in gens])
    res = sir_packets(m, x0, gens, rb["sched"], y, angles=[1], covariance=True).detail
    bad = np.zeros(K, bool)
    bad[[5, 6, 20]] = True
    assert np.array_equal(res.collapsed, np.broadcast_to(bad, (R, K)))
    assert np.all(np.isfinite(res.mean)) and np.all(np.isfinite(res.cov)) and np.all(np.isfinite(res.ess))
    assert np.all(res.ess[:, bad] == 300) and res.resampled.all()
    assert np.all(res.loglik == -np.inf)
    g = spawn_generators(1, R)[1]  # run 1 again with the NumPy engine: the same draws through the collapses
    ref = run_sir(m, y[1:2], g, particles=300, runs=1, loglik=rrp_loglik(m, rb["sched"], angles=[1])).detail
    assert np.array_equal(ref.collapsed[0], bad) and np.array_equal(ref.resampled, res.resampled[1:2])
    np.testing.assert_allclose(res.mean[1], ref.mean[0], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.ess[1], ref.ess[0], rtol=1e-9)
    # below an ESS threshold (< 1) a collapsed step is not resampled (its ESS is M), in either engine
    half = sir_packets(m, x0, spawn_generators(1, R), rb["sched"], y, angles=[1], ess_threshold=0.5).detail
    assert np.array_equal(half.collapsed, res.collapsed) and not half.resampled[:, bad].any()
    # and it keeps tracking: after the collapses the estimate is as good as before them
    e = np.linalg.norm((res.mean[:, 1:] - rb["x"][:R, 1:])[..., [0, 2]], axis=-1)
    assert np.all(e[:, 22:] < 10.0)
    # binary family: A = B = 0 at one step is the same event
    mb = binary["m"]
    A, B = binary_coefficients(binary["y"][:1], **binary["probs"], **binary["kw"])
    A[:, 3], B[:, 3] = 0.0, 0.0
    g = np.random.default_rng(0)
    rb2 = sir_binary(mb, mb.prior.sample(g, (1, 200)), [g], A, B, threshold=binary["kw"]["threshold"]).detail
    assert rb2.collapsed[0].tolist() == [k == 3 for k in range(binary["K"])]
    assert np.all(np.isfinite(rb2.mean))



def test_fused_filters_return_the_one_result_type(rb):
    """sir_packets returns the fusion centre's FilterResult as run_sir does: the means as its one node's estimate
    (the same array), ``cov`` None unless asked for (then the detail's covariances), its packets as messages."""
    m, R, K = rb["m"], 2, rb["K"]
    y = rb["ys"][:R]
    for covariance in (False, True):
        gens = spawn_generators(3, R)
        x0 = np.stack([m.prior.sample(g, 100) for g in gens])
        res = sir_packets(m, x0, gens, rb["sched"], y, angles=[1], covariance=covariance)
        assert isinstance(res, FilterResult) and res.check() is res
        assert (res.runs, res.steps, res.nodes, res.runtime) == (R, K, 1, "centralized")
        assert np.shares_memory(res.x, res.detail.mean) and np.array_equal(res.x[:, :, 0], res.detail.mean)
        assert res.valid.all() and res.violations == [[], []]
        assert (res.messages == 1).all()  # Round-Robin: one packet a step
        if covariance:
            assert np.array_equal(res.cov[:, :, 0], res.detail.cov) and res.trace.shape == (R, K + 1, 1)
        else:
            assert res.cov is None and res.detail.cov is None and res.trace is None
        one = res.row(1)
        assert np.array_equal(one.x[0], res.x[1]) and (one.cov is None) == (not covariance)

def test_nan_likelihood_counts_as_zero_weight():
    """A measurement function undefined (NaN) for some particles gives them zero weight, not NaN estimates."""
    x = ca.SX.sym("x", 1)
    m = Model("sqrt", x, x, [Sensor("s", ca.sqrt(x), Gaussian.zero_mean([[0.01]]))],
              Gaussian.zero_mean([[1e-4]]), Gaussian([1.0], [[1.0]]))
    g = np.random.default_rng(0)
    x0 = m.prior.sample(g, (1, 400))  # about 16 % negative: sqrt is NaN there
    res = sir_packets(m, x0, [g], np.zeros((3, 1), int), np.ones((1, 3, 1, 1)), ess_threshold=0.5).detail
    assert np.all(np.isfinite(res.mean)) and np.all(res.mean[0, 1:] > 0.5) and not res.collapsed.any()


def test_bad_inputs_raise_input_error_naming_the_parameter(rb):
    m, K = rb["m"], rb["K"]
    g = [np.random.default_rng(0)]
    x0 = m.prior.sample(g[0], (1, 10))
    y = rb["ys"][:1]
    ok = dict(angles=[1])
    cases = [
        ("x0", lambda: sir_packets(m, x0[0], g, rb["sched"], y)),
        ("x0", lambda: sir_packets(m, np.full((1, 10, 4), np.nan), g, rb["sched"], y)),
        ("rngs", lambda: sir_packets(m, x0, g[0], rb["sched"], y)),
        ("rngs", lambda: sir_packets(m, np.concatenate([x0, x0]), g * 2, rb["sched"], np.concatenate([y, y]))),
        ("rngs", lambda: sir_packets(m, x0, [np.random.RandomState(0)], rb["sched"], y)),
        ("sensors", lambda: sir_packets(m, x0, g, rb["sched"] + 4, y)),
        ("sensors", lambda: sir_packets(m, x0, g, rb["sched"] * 1.0, y)),
        ("y", lambda: sir_packets(m, x0, g, rb["sched"], y[:, :-1])),
        ("y", lambda: sir_packets(m, x0, g, rb["sched"], np.where(np.arange(K)[None, :, None] == 3, np.nan, y))),
        ("attack", lambda: sir_packets(m, x0, g, rb["sched"], y, attack=np.full((1, K), np.nan))),
        ("attack", lambda: sir_packets(m, x0, g, rb["sched"], y, attack=np.zeros((1, K + 1)))),
        ("log_clean", lambda: sir_packets(m, x0, g, rb["sched"], y, log_clean=0.5)),
        ("resampler", lambda: sir_packets(m, x0, g, rb["sched"], y, resampler="bogus")),
        ("ess_threshold", lambda: sir_packets(m, x0, g, rb["sched"], y, ess_threshold=0.0)),
        ("threads", lambda: sir_packets(m, x0, g, rb["sched"], y, threads=0)),
        ("covariance", lambda: sir_packets(m, x0, g, rb["sched"], y, covariance="yes")),
        ("angles", lambda: sir_packets(m, x0, g, rb["sched"], y, angles=[2])),
        ("angles", lambda: sir_packets(m, x0, g, rb["sched"], y, angles=["bearing"])),
        ("scalar sensors", lambda: sir_binary(m, x0, g, np.ones((1, K, 4)), np.ones((1, K, 4)), threshold=1.0)),
        ("model", lambda: sir_packets("target-range-bearing", x0, g, rb["sched"], y)),
        ("attack_prob", lambda: deception_terms(y, 1.0, rb["box"])),
    ]
    for name, call in cases:
        with pytest.raises(InputError, match=name):
            call()
    sir_packets(m, x0, g, rb["sched"], y, **ok)  # and the valid call runs
    bsc = load_scenario("target-binary-energy")
    mb, S = bsc.model, bsc.model.n_sensors
    xb = mb.prior.sample(np.random.default_rng(0), (1, 5))
    for name, A, B, T in (("A", np.ones((1, 3, S - 1)), np.ones((1, 3, S - 1)), 0.3),
                          ("B", np.ones((1, 3, S)), np.full((1, 3, S), np.inf), 0.3),
                          ("threshold", np.ones((1, 3, S)), np.ones((1, 3, S)), np.nan)):
        with pytest.raises(InputError, match=name):
            sir_binary(mb, xb, [np.random.default_rng(1)], A, B, threshold=T)


def test_unsupported_models_raise_input_error():
    four_tank, switching = load_scenario("four-tank").model, load_scenario("switching-2d").model
    g = np.random.default_rng(0)
    for model, what in ((four_tank, "inputs"), (switching, "modes")):
        with pytest.raises(InputError, match=what):
            sir_packets(model, model.prior.sample(g, (1, 5)), [g], np.zeros((2, 1), int), np.zeros((1, 2, 1, 1)))
    # measurement noise without a closed-form kernel, and non-Gaussian process noise
    x = ca.SX.sym("x", 1)
    odd = Model("odd", x, x, [Sensor("s", x, TruncatedGaussian([0.0], [1.0], -1.0, 1.0))],
                Gaussian.zero_mean([[1.0]]), Gaussian([0.0], [[1.0]]))
    with pytest.raises(InputError, match="TruncatedGaussian"):
        sir_packets(odd, np.zeros((1, 5, 1)), [g], np.zeros((2, 1), int), np.zeros((1, 2, 1, 1)))
    glint_w = GaussianMixture.from_arrays([0.5, 0.5], [[0.0], [0.0]], [[[1.0]], [[4.0]]])
    odd_w = Model("odd-w", x, x, [Sensor("s", x, Gaussian.zero_mean([[1.0]]))], glint_w, Gaussian([0.0], [[1.0]]))
    with pytest.raises(InputError, match="process_noise"):
        sir_packets(odd_w, np.zeros((1, 5, 1)), [g], np.zeros((2, 1), int), np.zeros((1, 2, 1, 1)))


def test_non_finite_states_are_flagged_at_their_step_by_both_engines():
    """x_{k+1} = 10^4 x_k overflows to inf after a few steps: both engines name the run and the step (no NaN means)."""
    from designer.validation import ComputationError

    x = ca.SX.sym("x", 1)
    model = Model("overflow", x, 1e4 * x, [Sensor("s", x, Gaussian.zero_mean([[1.0]]))],
                  process_noise=Gaussian.zero_mean([[1e-6]]), prior=Gaussian([1.0], [[0.01]]))
    K, M = 120, 50  # 1e4^k passes 1.8e308 at k = 78
    y = np.zeros((1, K, 1, 1))
    g = np.random.default_rng(0)
    with pytest.raises(ComputationError, match=r"fused particle filter: the filtered mean of run 0 is not finite "
                                               r"from step (7[0-9]|8[0-9])"):
        sir_packets(model, model.prior.sample(g, (1, M)), [g], np.zeros((K, 1), int), y)
    with pytest.raises(ComputationError, match=r"run 0 has particle states that are not finite at step (7|8)[0-9]"):
        run_sir(model, y[:, :, 0], np.random.default_rng(0), particles=M, runs=1)
    # A log-likelihood of +inf for one particle would make the weights uniform: flagged at its step instead.
    def singular(xp, k1, z):
        out = np.zeros(xp.shape[:2])
        out[0, 3] = np.inf if k1 == 4 else 0.0
        return out

    with pytest.raises(ComputationError, match=r"run 0 has a log-likelihood of \+inf .* at step 4"):
        run_sir(model, y[:, :10, 0], np.random.default_rng(0), particles=M, runs=1, loglik=singular)
