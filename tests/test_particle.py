"""The particle-filter engine: resampling schemes and SIR against the Kalman filter on a linear model."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from designer import Gaussian, InputError, Model, Sensor, simulate
from filters.particle import LogWeights, run_sir
from filters.resampling import RESAMPLERS, get_resampler

SCHEMES = sorted(RESAMPLERS)


@pytest.mark.parametrize("name", SCHEMES)
def test_resampling_is_unbiased(name):
    rng = np.random.default_rng(0)
    W = rng.dirichlet(np.ones(7) * 0.7)
    M, reps = 50, 4000
    idx = get_resampler(name)(np.broadcast_to(W, (reps, 7)), M, rng)  # 4000 runs in one batched call
    counts = np.stack([np.bincount(row, minlength=7) for row in idx])
    mean = counts.mean(0)
    se = counts.std(0, ddof=1) / np.sqrt(reps) + 1e-12
    assert np.all(np.abs(mean - M * W) < 5 * se + 1e-9)


@pytest.mark.parametrize("name", ["systematic", "stratified", "residual"])
def test_low_variance_schemes_keep_counts_near_M_W(name):
    rng = np.random.default_rng(1)
    W = rng.dirichlet(np.ones(9))
    M = 40
    for _ in range(200):
        c = np.bincount(get_resampler(name)(W, M, rng), minlength=9)
        assert c.sum() == M
        if name == "systematic":
            assert np.all(c >= np.floor(M * W) - 1e-9) and np.all(c <= np.ceil(M * W) + 1e-9)
        if name == "residual":
            assert np.all(c >= np.floor(M * W))


@pytest.mark.parametrize("name", SCHEMES)
def test_degenerate_weights_and_batching(name):
    rng = np.random.default_rng(2)
    W = np.zeros((3, 5))
    W[0, 2] = W[1, 4] = W[2, 0] = 1.0
    idx = get_resampler(name)(W, 6, rng)
    assert idx.shape == (3, 6)
    assert np.all(idx[0] == 2) and np.all(idx[1] == 4) and np.all(idx[2] == 0)


def test_resampling_rejects_bad_input():
    rng = np.random.default_rng(0)
    with pytest.raises(InputError, match="sum to 1"):
        get_resampler("systematic")(np.array([0.5, 0.6]), 3, rng)
    with pytest.raises(InputError, match="M must be"):
        get_resampler("systematic")(np.array([0.5, 0.5]), 0, rng)
    with pytest.raises(InputError, match="Generator"):
        get_resampler("systematic")(np.array([0.5, 0.5]), 3, np.random.RandomState(0))
    with pytest.raises(InputError, match="one of"):
        get_resampler("bogus")


def test_log_weights_handle_underflow_and_nan():
    lw = LogWeights.of(np.array([[-1000.0, -1001.0, np.nan], [-np.inf, -np.inf, -np.inf]]))
    W = lw.W
    np.testing.assert_allclose(W[0], [1 / (1 + np.exp(-1)), np.exp(-1) / (1 + np.exp(-1)), 0.0])
    np.testing.assert_allclose(W[1], 1 / 3)  # every weight vanished: uniform, not NaN
    assert lw.ess[0] == pytest.approx(1 / np.sum(W[0] ** 2))


def _linear_model():
    x = ca.SX.sym("x", 2)
    A = np.array([[0.9, 0.2], [-0.1, 0.95]])
    Hm = np.array([[1.0, 0.5]])
    model = Model("lin", x, ca.mtimes(ca.DM(A), x), [Sensor("s", ca.mtimes(ca.DM(Hm), x),
                  Gaussian.zero_mean([[0.3]]))], Gaussian.zero_mean(0.05 * np.eye(2)),
                  Gaussian([1.0, -1.0], 0.5 * np.eye(2)))
    return model, A, Hm


def _kalman(A, Hm, Q, R, m0, P0, z):
    m, P, ll, means = m0, P0, 0.0, []
    for zk in z:
        m, P = A @ m, A @ P @ A.T + Q
        S = Hm @ P @ Hm.T + R
        r = zk - Hm @ m
        ll += -0.5 * (np.log(2 * np.pi * np.linalg.det(S)) + r @ np.linalg.solve(S, r))
        K = P @ Hm.T @ np.linalg.inv(S)
        m, P = m + K @ r, P - K @ S @ K.T
        means.append(m)
    return np.array(means), ll


@pytest.mark.parametrize("scheme, thr", [("systematic", 1.0), ("residual", 0.5), ("multinomial", 1.0)])
def test_sir_matches_the_kalman_filter_on_a_linear_model(scheme, thr):
    model, A, Hm = _linear_model()
    traj = simulate(model, 25, np.random.default_rng(5))
    means_kf, ll_kf = _kalman(A, Hm, model.process_cov, model.measurement_cov(0), model.prior.mean,
                              model.prior.cov, traj.z)
    runs = 16
    res = run_sir(model, traj.z, np.random.default_rng(6), particles=3000, runs=runs, resampler=scheme,
                  ess_threshold=thr).detail
    diff = res.mean[:, 1:] - means_kf[None]  # (runs, K, 2)
    avg = diff.mean(0)
    se = diff.std(0, ddof=1) / np.sqrt(runs)
    assert np.all(np.abs(avg) < 5 * se + 5e-3)
    assert np.sqrt((diff**2).mean()) < 0.05
    # The likelihood estimate is unbiased; its log is close at this particle count.
    assert abs(ll_kf - np.mean(res.loglik)) < 5 * res.loglik.std(ddof=1) / np.sqrt(runs) + 0.05
    if thr < 1.0:
        assert not res.resampled.all()


def test_sir_is_reproducible_and_runs_are_independent():
    model, _, _ = _linear_model()
    traj = simulate(model, 10, np.random.default_rng(5))
    a = run_sir(model, traj.z, np.random.default_rng(9), particles=200, runs=3).detail
    b = run_sir(model, traj.z, np.random.default_rng(9), particles=200, runs=3).detail
    assert np.array_equal(a.mean, b.mean) and np.array_equal(a.loglik, b.loglik)
    assert not np.allclose(a.mean[0], a.mean[1])


def test_sir_reports_the_seconds_in_its_proposal_and_in_its_likelihood():
    """detail.proposal_seconds / loglik_seconds: the wall time in each callable, within the filter's call; a
    callable that sleeps shows in its own field (the encrypted-switching study's time split)."""
    import time

    from filters.particle import additive_noise_loglik, transition_proposal

    model, _, _ = _linear_model()
    traj = simulate(model, 5, np.random.default_rng(5))

    def slow(fn, pause):
        def call(*args):
            time.sleep(pause)
            return fn(*args)
        return call

    for p_pause, l_pause in ((0.0, 0.01), (0.01, 0.0)):
        t = time.perf_counter()
        res = run_sir(model, traj.z, np.random.default_rng(9), particles=50, runs=2,
                      proposal=slow(transition_proposal(model), p_pause),
                      loglik=slow(additive_noise_loglik(model), l_pause))
        wall = time.perf_counter() - t
        d = res.detail
        assert d.proposal_seconds >= 5 * p_pause and d.loglik_seconds >= 5 * l_pause
        assert 0 < d.proposal_seconds + d.loglik_seconds < wall
        plain = run_sir(model, traj.z, np.random.default_rng(9), particles=50, runs=2).detail
        assert np.array_equal(d.mean, plain.mean)  # measured, not changed


def test_collapse_is_recorded_and_the_filter_recovers():
    """A measurement no particle can explain leaves finite weights, keeps the prediction and is recorded."""
    model, A, Hm = _linear_model()
    traj = simulate(model, 12, np.random.default_rng(5))
    base = run_sir(model, traj.z, np.random.default_rng(1), particles=500, runs=2).detail

    def loglik(x, k1, z):  # zero density at step 5 (k1 = 6), the model's Gaussian otherwise
        ll = model.sensors[0].noise.logpdf(z[..., None, :] - model.h(0, x, k1))
        return np.full_like(ll, -np.inf) if k1 == 6 else ll

    res = run_sir(model, traj.z, np.random.default_rng(1), particles=500, runs=2, loglik=loglik).detail
    assert res.collapsed[:, 5].all() and res.collapsed.sum() == 2
    assert np.all(np.isfinite(res.mean)) and np.all(np.isfinite(res.cov))
    assert np.all(res.loglik == -np.inf)  # p(z_6 | z_1:5) = 0 under this likelihood
    # the step without a usable measurement is a pure prediction: the mean follows A (within MC error)
    pred = np.einsum("ab,rb->ra", A, res.mean[:, 5])
    assert np.all(np.abs(res.mean[:, 6] - pred) < 4 * np.sqrt(np.diagonal(res.cov[:, 6], axis1=1, axis2=2) / 500) + 0.02)
    # and it recovers: the final estimates are as close to the truth as without the outage
    err = lambda r: np.abs(r.mean[:, -1] - traj.x[-1]).max()
    assert err(res) < err(base) + 1.0
    assert not base.collapsed.any()


def test_linear_weights_underflow_where_log_weights_do_not():
    """A 60-sigma outlier: every linear-domain weight underflows to 0 (collapse); log weights renormalise."""
    model, _, Hm = _linear_model()
    traj = simulate(model, 10, np.random.default_rng(5))
    z = traj.z.copy()
    z[4] += 60 * np.sqrt(0.3)  # log-likelihood about -1800 for every particle: exp() == 0 in double precision
    log = run_sir(model, z, np.random.default_rng(2), particles=300, runs=3).detail
    lin = run_sir(model, z, np.random.default_rng(2), particles=300, runs=3, linear_weights=True).detail
    assert not log.collapsed.any()
    assert lin.collapsed[:, 4].all() and lin.collapsed.sum() == 3
    # without the outlier the two are the same filter, bit for bit
    a = run_sir(model, traj.z, np.random.default_rng(2), particles=300, runs=3).detail
    b = run_sir(model, traj.z, np.random.default_rng(2), particles=300, runs=3, linear_weights=True).detail
    np.testing.assert_array_equal(a.mean, b.mean)


def test_nan_measurements_are_rejected_or_skipped_explicitly():
    model, A, _ = _linear_model()
    traj = simulate(model, 8, np.random.default_rng(5))
    z = traj.z.copy()
    z[3] = np.nan
    with pytest.raises(InputError, match="NaN.*step 3.*missing='skip'"):
        run_sir(model, z, np.random.default_rng(0), particles=50)
    with pytest.raises(InputError, match="missing must be"):
        run_sir(model, traj.z, np.random.default_rng(0), particles=50, missing="ignore")
    res = run_sir(model, z, np.random.default_rng(0), particles=2000, missing="skip").detail
    assert res.skipped[0, 3] and res.skipped.sum() == 1 and not res.collapsed.any()
    assert np.all(np.isfinite(res.mean)) and np.isfinite(res.loglik).all()
    # a skipped step is a prediction: the weights stay uniform (ESS = M) and the mean follows A
    assert res.ess[0, 3] == pytest.approx(2000)
    np.testing.assert_allclose(res.mean[0, 4], A @ res.mean[0, 3], atol=0.05)
