"""Tests of the distributed consensus filter (filters.consensus) and its bounds (designer.bounds).

References are independent of the code under test: FilterPy's extended Kalman
filter with hand-written analytic Jacobians, python-control's ``dlqe``, the
equations (26)-(30) of seed 003 evaluated directly with explicit inverses,
finite differences, closed-form moments, and a hand-written one-step
re-implementation of the whole filter (unicycle and camera Jacobians by hand).
No reference number is copied from a run of this code.
"""
from __future__ import annotations

import casadi as ca
import control
import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter

import rules
from designer import Gaussian, Model, Sensor, SensorNetwork, simulate
from designer.bounds import (
    condition28_margin,
    condition29_margin,
    optimal_gain,
    prediction_bound,
    shifted_inverse,
    theorem2_margin,
    update_bound,
)
from designer.validation import InputError
from designer.attacks import FDISignal
from designer.design import ConsensusDesign, validate_design
from filters.attacks import simulate_attacks
from consensus_reference import exchange  # tests/ on the path: the reference's exchange, checked here
from filters.consensus import run_consensus
from studies.scenarios import load_scenario

inv = np.linalg.inv


# ----------------------------------------------------------------------------- helpers
def random_spd(rng, n, lo=0.5, hi=2.0):
    """A random symmetric positive-definite matrix with eigenvalues in [lo, hi]."""
    Qm, _ = np.linalg.qr(rng.standard_normal((n, n)))
    return (Qm * rng.uniform(lo, hi, n)) @ Qm.T


def isolated():
    return SensorNetwork(1, np.zeros((1, 1), int))


def ekf_design(n_x, n_z):
    """sigma = beta = 0, U = V = 0: the consensus filter of an isolated node is the EKF."""
    return ConsensusDesign(epsilon=0.5, sigma=0.0, beta=0.0, tau=0.3, U=np.zeros((n_x, n_x)),
                           V=np.zeros((n_z, n_z)), delta=0.0, rule=rules.get("paper"))


def assert_spd(a, what=""):
    assert np.all(np.isfinite(a)), what
    np.testing.assert_allclose(a, np.swapaxes(a, -1, -2), rtol=0, atol=1e-12 * max(1.0, np.abs(a).max()),
                               err_msg=what)
    assert np.all(np.linalg.eigvalsh(a)[..., 0] > 0), what


# ----------------------------------------------------------------------------- 1. EKF equivalence
# Both models are time-varying (a moving sensor; a periodic torque), so that the time index passed to
# f (k) and h (k + 1: z[k] measures x_{k+1}) is checked too.
DT_CV = 1.0


def cv_sensor(k):
    return -60.0 + 0.3 * k, -10.0 + 0.1 * k


def cv_model():
    x = ca.SX.sym("x", 4)  # [px, vx, py, vy]
    k = ca.SX.sym("k")
    f = ca.vertcat(x[0] + DT_CV * x[1], x[1], x[2] + DT_CV * x[3], x[3])
    sx, sy = cv_sensor(k)
    h = ca.vertcat(ca.sqrt((x[0] - sx) ** 2 + (x[2] - sy) ** 2), ca.atan2(x[2] - sy, x[0] - sx))
    R = np.diag([0.5**2, 0.01**2])
    q = 0.01
    blk = q * np.array([[DT_CV**3 / 3, DT_CV**2 / 2], [DT_CV**2 / 2, DT_CV]])
    Q = np.zeros((4, 4))
    Q[:2, :2] = blk
    Q[2:, 2:] = blk
    prior = Gaussian(np.array([0.5, 0.8, -0.5, 0.6]), np.diag([4.0, 1.0, 4.0, 1.0]))
    m = Model("cv-rb", x, f, [Sensor("rb", h, Gaussian.zero_mean(R))], Gaussian.zero_mean(Q), prior, k=k)
    return m, Q, R


def cv_f(x, k):
    return cv_F(x, k) @ x


def cv_F(x, k):
    F = np.eye(4)
    F[0, 1] = F[2, 3] = DT_CV
    return F


def cv_h(x, k):
    sx, sy = cv_sensor(k)
    dx, dy = x[0, 0] - sx, x[2, 0] - sy
    return np.array([[np.hypot(dx, dy)], [np.arctan2(dy, dx)]])


def cv_H(x, k):
    sx, sy = cv_sensor(k)
    dx, dy = x[0, 0] - sx, x[2, 0] - sy
    r2 = dx * dx + dy * dy
    r = np.sqrt(r2)
    return np.array([[dx / r, 0.0, dy / r, 0.0], [-dy / r2, 0.0, dx / r2, 0.0]])


PEND_DT, PEND_G, PEND_L, PEND_TORQUE = 0.05, 9.81, 1.0, 0.8
SENSOR_P = (0.3, -3.0)


def pendulum_model():
    x = ca.SX.sym("x", 2)  # [theta, omega]
    k = ca.SX.sym("k")
    f = ca.vertcat(x[0] + PEND_DT * x[1],
                   x[1] - PEND_DT * PEND_G / PEND_L * ca.sin(x[0]) + PEND_DT * PEND_TORQUE * ca.cos(0.15 * k))
    sx, sy = SENSOR_P
    bx, by = PEND_L * ca.sin(x[0]), -PEND_L * ca.cos(x[0])
    h = ca.vertcat(ca.sqrt((bx - sx) ** 2 + (by - sy) ** 2), ca.atan2(by - sy, bx - sx))
    R = np.diag([0.05**2, 0.02**2])
    Q = np.diag([1e-5, 1e-4])
    prior = Gaussian(np.array([0.6, 0.0]), np.diag([0.05, 0.05]))
    m = Model("pendulum", x, f, [Sensor("rb", h, Gaussian.zero_mean(R))], Gaussian.zero_mean(Q), prior, k=k)
    return m, Q, R


def pend_f(x, k):
    th, om = x[0, 0], x[1, 0]
    return np.array([[th + PEND_DT * om],
                     [om - PEND_DT * PEND_G / PEND_L * np.sin(th) + PEND_DT * PEND_TORQUE * np.cos(0.15 * k)]])


def pend_F(x, k):
    return np.array([[1.0, PEND_DT], [-PEND_DT * PEND_G / PEND_L * np.cos(x[0, 0]), 1.0]])


def _pend_geom(x):
    th = x[0, 0]
    sx, sy = SENSOR_P
    dx, dy = PEND_L * np.sin(th) - sx, -PEND_L * np.cos(th) - sy
    return th, dx, dy


def pend_h(x, k):
    _, dx, dy = _pend_geom(x)
    return np.array([[np.hypot(dx, dy)], [np.arctan2(dy, dx)]])


def pend_H(x, k):
    th, dx, dy = _pend_geom(x)
    ddx, ddy = PEND_L * np.cos(th), PEND_L * np.sin(th)  # d(bob)/d theta
    r2 = dx * dx + dy * dy
    return np.array([[(dx * ddx + dy * ddy) / np.sqrt(r2), 0.0], [(dx * ddy - dy * ddx) / r2, 0.0]])


class _NonlinearEKF(ExtendedKalmanFilter):
    """FilterPy's EKF with the prediction x = f(x, k) instead of x = F x (k set before predict)."""

    def __init__(self, dim_x, dim_z, fx):
        super().__init__(dim_x, dim_z)
        self._fx = fx
        self.k = 0

    def predict_x(self, u=0):
        self.x = self._fx(self.x, self.k)


@pytest.mark.parametrize("case", ["cv-range-bearing", "pendulum"])
def test_isolated_node_is_exactly_the_ekf(case):
    if case == "cv-range-bearing":
        model, Q, R = cv_model()
        fx, Fx, hx, Hx = cv_f, cv_F, cv_h, cv_H
        x_true0 = np.array([0.0, 1.0, 0.0, 0.5])
    else:
        model, Q, R = pendulum_model()
        fx, Fx, hx, Hx = pend_f, pend_F, pend_h, pend_H
        x_true0 = np.array([0.8, 0.0])
    steps = 60
    traj = simulate(model, steps, np.random.default_rng(11), x0=x_true0)
    n_x, n_z = model.n_x, model.n_z
    # the bearing stays far from the +-pi cut (true state and measurements)
    assert np.all(np.abs(traj.z[:, 1]) < 2.5)
    res = run_consensus(model, isolated(), traj.z, ekf_design(n_x, n_z))

    ekf = _NonlinearEKF(n_x, n_z, fx)
    ekf.x = model.prior.mean.reshape(-1, 1).copy()
    ekf.P = model.prior.cov.copy()
    ekf.Q = Q
    ekf.R = R
    xs, Ps, xp, Pp = [], [], [], []
    for k in range(steps):
        ekf.k = k
        ekf.F = Fx(ekf.x, k)
        ekf.predict()
        xp.append(ekf.x.ravel().copy())
        Pp.append(ekf.P.copy())
        ekf.update(traj.z[k].reshape(-1, 1), Hx, hx, args=(k + 1,), hx_args=(k + 1,))
        xs.append(ekf.x.ravel().copy())
        Ps.append(ekf.P.copy())
    xs, Ps, xp, Pp = map(np.array, (xs, Ps, xp, Pp))

    # the filter must actually have done something (guards against a vacuous comparison)
    assert np.abs(Ps[-1] - model.prior.cov).max() > 1e-3
    np.testing.assert_allclose(res.x_pred[:, 0], xp, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.phi_pred[:, 0], Pp, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(res.x_post[1:, 0], xs, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.phi_post[1:, 0], Ps, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(res.x_post[0, 0], model.prior.mean)
    np.testing.assert_array_equal(res.phi_post[0, 0], model.prior.cov)
    # an isolated node: no violations of (28)/(29), Theorem 2 has no upper condition, valid all along
    assert res.feasible and res.violations == []
    assert res.valid.all()
    assert np.all(np.isinf(res.theorem2))


# ----------------------------------------------------------------------------- 2. steady state vs dlqe
def test_isolated_linear_node_converges_to_dlqe_steady_state():
    A = np.array([[1.0, 0.1, 0.005], [0.0, 1.0, 0.1], [0.0, 0.0, 0.95]])
    G = np.array([[0.0, 0.0], [0.1, 0.0], [0.3, 1.0]])
    Cm = np.array([[1.0, 0.0, 0.0]])
    Qw = np.diag([0.02, 0.05])
    Rv = np.array([[0.4]])
    x = ca.SX.sym("x", 3)
    model = Model("lin", x, ca.mtimes(ca.DM(A), x), [Sensor("s", ca.mtimes(ca.DM(Cm), x), Gaussian.zero_mean(Rv))],
                  Gaussian.zero_mean(Qw), Gaussian(np.zeros(3), 3.0 * np.eye(3)), noise_gain=G)
    steps = 300
    traj = simulate(model, steps, np.random.default_rng(5))
    res = run_consensus(model, isolated(), traj.z, ekf_design(3, 1))

    _, P, _ = control.dlqe(A, G, Cm, Qw, Rv)
    P = np.asarray(P)
    post = P - P @ Cm.T @ inv(Cm @ P @ Cm.T + Rv) @ Cm @ P
    np.testing.assert_allclose(res.phi_pred[-1, 0], P, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(res.phi_post[-1, 0], post, rtol=1e-8, atol=1e-10)
    # not there from the start (the test could fail)
    assert np.abs(res.phi_post[1, 0] - post).max() > 1e-3


# ----------------------------------------------------------------------------- 3. optimal gain (30)
def _gain_problem(seed):
    rng = np.random.default_rng(seed)
    n, m = 3, 2
    phi_pred = random_spd(rng, n, 0.3, 2.0)
    H = rng.standard_normal((m, n))
    tau = 0.05
    C = tau * phi_pred
    s_i = float(rng.integers(0, 4))
    d_i = 3
    beta = 0.5 / np.linalg.eigvalsh(phi_pred)[-1]  # (29) holds with margin
    V = 0.3 * rng.standard_normal((m, m))
    R = random_spd(rng, m, 0.2, 1.0)
    neigh = random_spd(rng, n, 0.5, 3.0)
    return phi_pred, H, C, s_i, beta, V, R, d_i, neigh


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_optimal_gain_minimises_trace_of_update_bound(seed):
    phi_pred, H, C, s_i, beta, V, R, d_i, neigh = _gain_problem(seed)
    assert condition29_margin(phi_pred, beta) > 0
    K = optimal_gain(phi_pred, H, C, s_i, beta, V, R, d_i)
    assert K.shape == (3, 2)

    def tr(Km):
        return np.trace(update_bound(phi_pred, H, Km, C, s_i, beta, V, R, d_i, neigh))

    rng = np.random.default_rng(100 + seed)
    t0 = tr(K)
    # tr Phi(K) is quadratic in K with Hessian tr(dK W dK^T), W = (1+2d) H M H^T + (1+2d) V V^T/beta + R
    M = inv(inv(phi_pred) - beta * np.eye(3))
    W = (1 + 2 * d_i) * H @ M @ H.T + (1 + 2 * d_i) * V @ V.T / beta + R
    for scale in (1e-4, 1e-2, 1.0):
        for _ in range(20):
            dK = scale * rng.standard_normal(K.shape)
            t1 = tr(K + dK)
            assert t1 > t0
            np.testing.assert_allclose(t1 - t0, np.trace(dK @ W @ dK.T), rtol=1e-6, atol=1e-13)

    def fd_grad(Km, h=1e-6):
        g = np.zeros_like(Km)
        for idx in np.ndindex(*Km.shape):
            e = np.zeros_like(Km)
            e[idx] = h
            g[idx] = (tr(Km + e) - tr(Km - e)) / (2 * h)
        return g

    g_opt = fd_grad(K)
    K_off = K + 0.3 * rng.standard_normal(K.shape)
    g_off = fd_grad(K_off)
    # the finite-difference gradient is accurate (checked away from the optimum) ...
    np.testing.assert_allclose(g_off, 2 * (K_off - K) @ W, rtol=1e-5, atol=1e-6)
    # ... and vanishes at K of (30)
    assert np.abs(g_opt).max() < 1e-6 * max(1.0, np.abs(g_off).max())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_optimal_gain_and_update_bound_match_direct_formulas(seed):
    phi_pred, H, C, s_i, beta, V, R, d_i, neigh = _gain_problem(seed)
    n = 3
    M = inv(inv(phi_pred) - beta * np.eye(n))
    K_ref = (np.eye(n) - s_i * C) @ M @ H.T @ inv(H @ M @ H.T + V @ V.T / beta + R / (1 + 2 * d_i))
    K = optimal_gain(phi_pred, H, C, s_i, beta, V, R, d_i)
    np.testing.assert_allclose(K, K_ref, rtol=1e-10, atol=1e-12)
    K2 = K + 0.1 * np.random.default_rng(seed).standard_normal(K.shape)
    A = np.eye(n) - s_i * C - K2 @ H
    ref = ((1 + 2 * d_i) * A @ M @ A.T + C @ neigh @ C.T
           + K2 @ ((1 + 2 * d_i) * V @ V.T / beta + R) @ K2.T)
    np.testing.assert_allclose(update_bound(phi_pred, H, K2, C, s_i, beta, V, R, d_i, neigh), ref,
                               rtol=1e-10, atol=1e-12)


# ----------------------------------------------------------------------------- 4. (26), (28), (29), Theorem 2
@pytest.mark.parametrize("seed", range(5))
def test_shifted_inverse_matches_explicit_inverses(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 6))
    phi = random_spd(rng, n, 0.2, 3.0)
    lam_max = np.linalg.eigvalsh(phi)[-1]
    for c in (0.0, 0.1 / lam_max, 0.9 / lam_max, -0.7):
        np.testing.assert_allclose(shifted_inverse(phi, c), inv(inv(phi) - c * np.eye(n)), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_prediction_bound_matches_formula_26(seed):
    rng = np.random.default_rng(seed)
    n = 4
    phi = random_spd(rng, n, 0.2, 2.0)
    F = rng.standard_normal((n, n))
    U = 0.2 * rng.standard_normal((n, n))
    Q = random_spd(rng, n, 0.01, 0.1)
    eps = 0.3
    lam_max = np.linalg.eigvalsh(phi)[-1]
    sigma = 0.6 / ((1 + eps) * lam_max)
    pb = prediction_bound(phi, F, U, Q, sigma, eps)
    ref = F @ inv(inv(phi) - (1 + eps) * sigma * np.eye(n)) @ F.T + U @ U.T / (eps * sigma) + Q
    np.testing.assert_allclose(pb.phi_pred, ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(pb.margin28, 1 / lam_max - (1 + eps) * sigma, rtol=1e-12)
    assert pb.margin28 > 0
    # sigma = 0 with U = 0: the plain EKF prediction
    pb0 = prediction_bound(phi, F, np.zeros((n, n)), Q, 0.0, eps)
    np.testing.assert_allclose(pb0.phi_pred, F @ phi @ F.T + Q, rtol=1e-12, atol=1e-12)
    # (28) fails: no bound, a negative margin equal to 1/lambda_max - (1+eps) sigma
    big = 1.5 / ((1 + eps) * lam_max)
    bad = prediction_bound(phi, F, U, Q, big, eps)
    assert bad.phi_pred is None
    assert bad.margin28 < 0
    np.testing.assert_allclose(bad.margin28, 1 / lam_max - (1 + eps) * big, rtol=1e-12)
    # exactly on the boundary is a violation too (margin <= 0)
    edge = prediction_bound(2.0 * np.eye(n), F, U, Q, 0.5 / (1 + eps), eps)
    assert edge.phi_pred is None and edge.margin28 <= 0


def test_prediction_bound_rejects_U_without_sigma():
    n = 2
    with pytest.raises(InputError, match="sigma"):
        prediction_bound(np.eye(n), np.eye(n), np.eye(n), np.eye(n), 0.0, 0.5)


@pytest.mark.parametrize("seed", range(4))
def test_condition_margins(seed):
    rng = np.random.default_rng(seed)
    n = 3
    phi = random_spd(rng, n, 0.1, 5.0)
    lam = np.linalg.eigvalsh(phi)
    sigma, eps, beta = 0.07, 0.2, 0.13
    assert condition28_margin(phi, sigma, eps) == pytest.approx(1 / lam[-1] - (1 + eps) * sigma, rel=1e-12)
    assert condition29_margin(phi, beta) == pytest.approx(1 / lam[-1] - beta, rel=1e-12)
    for d_max in (1, 2, 3):
        assert theorem2_margin(phi, sigma, d_max) == pytest.approx((1 + d_max) / d_max * sigma - 1 / lam[0],
                                                                    rel=1e-12)
    assert theorem2_margin(phi, sigma, 0) == np.inf
    # an indefinite (or singular) matrix is never a bound
    indef = phi - (lam[0] + 0.1) * np.eye(n)
    assert condition28_margin(indef, sigma, eps) == -np.inf
    assert condition29_margin(indef, beta) == -np.inf
    assert condition29_margin(np.diag([1.0, 1.0, 0.0]), 0.0) == -np.inf


# ----------------------------------------------------------------------------- 5. simulate_attacks
@pytest.fixture(scope="module")
def robot():
    return load_scenario("indoor-robot")


def test_simulate_attacks_statistics(robot):
    net = robot.network.with_attacks(0.3, 0.2)
    steps, amp, comps = 20000, 1.5, (0, 1)
    att = simulate_attacks(net, steps, 3, np.random.default_rng(7), signal=FDISignal(amp, comps))
    adj = net.adjacency
    assert att.dos.shape == att.fdi.shape == (steps, 8, 8) and att.xi.shape == (steps, 8, 8, 3)
    # nothing off the edges, never both attacks on one channel
    assert not np.any(att.dos[:, ~adj]) and not np.any(att.fdi[:, ~adj])
    assert not np.any(att.xi[:, ~adj])
    assert not np.any(att.dos & att.fdi)
    # per-channel frequencies within 5 standard errors
    for p, ind in ((0.3, att.dos), (0.2, att.fdi)):
        freq = ind[:, adj].mean(axis=0)
        se = np.sqrt(p * (1 - p) / steps)
        assert np.all(np.abs(freq - p) < 5 * se), (p, freq)
    # xi: zero without FDI, only on the listed components, bounded
    assert not np.any(att.xi[~att.fdi])
    assert not np.any(att.xi[..., 2])
    norms = np.linalg.norm(att.xi, axis=-1)
    assert norms.max() <= amp * np.sqrt(len(comps)) + 1e-12
    # xi = amp sin(s), s ~ N(0,1): E sin(s) = 0, E sin^2(s) = (1 - e^-2) / 2 (closed forms)
    vals = att.xi[att.fdi][:, 0] / amp
    np.testing.assert_array_equal(att.xi[att.fdi][:, 0], att.xi[att.fdi][:, 1])
    m2 = (1 - np.exp(-2.0)) / 2
    m4 = (3 - 4 * np.exp(-2.0) + np.exp(-8.0)) / 8  # E sin^4(s)
    nv = vals.size
    assert abs(vals.mean()) < 5 * np.sqrt(m2 / nv)
    assert abs((vals**2).mean() - m2) < 5 * np.sqrt((m4 - m2**2) / nv)


def test_simulate_attacks_reproducible(robot):
    net = robot.network.with_attacks(0.3, 0.2)
    a = simulate_attacks(net, 50, 3, np.random.default_rng(3), signal=FDISignal(1.5, (0, 1)))
    b = simulate_attacks(net, 50, 3, np.random.default_rng(3), signal=FDISignal(1.5, (0, 1)))
    c = simulate_attacks(net, 50, 3, np.random.default_rng(4), signal=FDISignal(1.5, (0, 1)))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a.dos, c.dos)
    with pytest.raises(InputError, match="rng"):
        simulate_attacks(net, 5, 3, 3, signal=FDISignal(1.0, (0,)))


def test_an_attack_pattern_keeps_the_signal_where_it_was_injected(robot):
    """A pattern holds ξ at its falsified entries alone: the dense ξ it gives is the channel law's dense draw on the
    same uniforms and normals (``channel_attacks``, a second computation), bit for bit; ``xi_of`` is the dense array's
    entries for any index; a pattern through the channels' form (``EdgeAttacks``) and back is itself; and a pattern
    whose signals do not match its falsified entries is refused by the filters, naming what it needs."""
    from filters.attacks import AttackPattern, channel_attacks, channel_draws, attack_pattern
    from filters.consensus_batch import EdgeAttacks
    from filters.distributed import run_kcf

    net = robot.network.with_attacks(0.2, 0.3)
    steps, n, nx = 40, net.n_nodes, 3
    u, s = channel_draws(steps, n, np.random.default_rng(11))
    signal = FDISignal(0.8, (0, 2))
    att = attack_pattern(net, u, s, nx, signal)
    dos, fdi, xi = channel_attacks(u, s, net.dos_prob[None], net.fdi_prob[None], nx, signal, net.adjacency[None])
    assert att.fdi.sum() > 20 and att.xi_fdi.shape == (att.fdi.sum(), nx)
    np.testing.assert_array_equal(att.dos, dos)
    np.testing.assert_array_equal(att.fdi, fdi)
    np.testing.assert_array_equal(att.xi, xi)
    receiver, sender = np.nonzero(net.adjacency)
    for index in ((5,), (slice(None), receiver, sender), (slice(3, 9), 2), (np.array([0, 7, 7]), 1, 0), att.fdi,
                  0, 5, np.int64(9), -1):  # an integer: one step, its entries a run of xi_fdi
        np.testing.assert_array_equal(att.xi_of(index), xi[index])
    np.testing.assert_array_equal(AttackPattern.dense(dos, fdi, xi + 1.0).xi, np.where(fdi[..., None], xi + 1.0, 0.0))
    back = EdgeAttacks.from_patterns(net, [att]).pattern(0, n)
    for a, b in zip(back, att):
        np.testing.assert_array_equal(a, b)
    m = robot.model
    torn = att._replace(fdi=att.fdi | net.adjacency[None].astype(bool))  # more falsified entries than signals
    with pytest.raises(InputError, match="one signal of 3 components per falsified entry"):  # refused before a step
        run_kcf(m, net, np.zeros((steps, m.n_z)), inputs=np.zeros((steps, m.n_u)), attacks=torn)


# ----------------------------------------------------------------------------- 6. exchange
def _exchange_ref(x_pred, net, dos=None, fdi=None, xi=None):
    n, nx = x_pred.shape
    out = np.zeros((n, nx))
    s = np.zeros(n)
    for i in range(n):
        for j in net.neighbours[i]:
            phi = 0.0 if dos is None else float(dos[i, j])
            gam = 0.0 if fdi is None else float(fdi[i, j])
            x_in = x_pred[j] + (gam * xi[i, j] if xi is not None else 0.0)
            out[i] += (1 - phi) * (x_in - x_pred[i])
            s[i] += 1 - phi
    return out, s


def test_exchange_matches_double_loop(robot):
    net = robot.network.with_attacks(0.3, 0.3)
    rng = np.random.default_rng(21)
    att = simulate_attacks(net, 40, 3, np.random.default_rng(22), signal=FDISignal(1.5, (0, 1)))
    seen_dos = seen_fdi = False
    for k in range(40):
        x_pred = rng.standard_normal((8, 3))
        inn, s = exchange(x_pred, (att.dos[k], att.fdi[k], att.xi[k]), net)
        ref, s_ref = _exchange_ref(x_pred, net, att.dos[k], att.fdi[k], att.xi[k])
        np.testing.assert_allclose(inn, ref, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(s, s_ref)
        seen_dos |= att.dos[k].any()
        seen_fdi |= att.fdi[k].any()
    assert seen_dos and seen_fdi
    # no attacks: plain consensus with s_i = d_i
    x_pred = rng.standard_normal((8, 3))
    inn, s = exchange(x_pred, None, net)
    ref, s_ref = _exchange_ref(x_pred, net)
    np.testing.assert_allclose(inn, ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(s, net.degrees)


def test_exchange_uses_fdi_indicator(robot):
    net = robot.network.with_attacks(0.3, 0.3)
    rng = np.random.default_rng(31)
    att = simulate_attacks(net, 1, 3, np.random.default_rng(32), signal=FDISignal(1.5, (0, 1)))
    dos, fdi = att.dos[0], att.fdi[0]
    xi = rng.uniform(-1, 1, (8, 8, 3)) * net.adjacency[..., None]  # an attacker's signal on every channel
    x_pred = rng.standard_normal((8, 3))
    inn, _ = exchange(x_pred, (dos, fdi, xi), net)
    ref, _ = _exchange_ref(x_pred, net, dos, fdi, xi)
    np.testing.assert_allclose(inn, ref, rtol=1e-12, atol=1e-12)


# ----------------------------------------------------------------------------- 7. indoor robot, paper-like design
def paper_design():
    return ConsensusDesign(epsilon=1 / 6, sigma=0.1, beta=0.1, tau=0.01, U=0.01 * np.eye(3), V=0.1 * np.eye(2),
                           delta=1.5 * np.sqrt(2), rule=rules.get("paper"))


@pytest.fixture(scope="module")
def robot_run(robot):
    net = robot.network.with_attacks(0.3, 0.2)
    steps = 30
    traj = robot.simulate(np.random.default_rng(1), steps)
    att = simulate_attacks(net, steps, 3, np.random.default_rng(2), signal=FDISignal(1.5, (0, 1)))
    des = paper_design()
    res = run_consensus(robot.model, net, traj.z, des, inputs=traj.inputs, attacks=att)
    return net, traj, att, des, res


def _first_violation(res, i):
    vs = [v for v in res.violations if v["node"] == i and v["condition"] in ("(28)", "(29)")]
    if not vs:
        return None
    assert len(vs) == 1, "a node's (28)/(29) violation is recorded once, when it leaves the recursion"
    return vs[0]


def test_robot_paper_design_run_is_well_formed(robot_run):
    net, traj, att, des, res = robot_run
    steps, n = 30, 8
    assert res.x_post.shape == (steps + 1, n, 3) and res.phi_post.shape == (steps + 1, n, 3, 3)
    for name in ("x_post", "x_pred", "phi_post", "phi_pred", "K", "C"):
        assert np.all(np.isfinite(getattr(res, name))), name
    assert_spd(res.phi_post, "phi_post")
    assert_spd(res.phi_pred, "phi_pred")
    for v in res.violations:
        assert set(v) == {"node", "step", "condition", "margin"}
        assert 0 <= v["node"] < n and 0 <= v["step"] <= steps
        assert v["condition"] in ("(28)", "(29)", "theorem2")
        if v["condition"] == "theorem2":
            assert v["margin"] < 0
        else:
            assert v["margin"] <= 0
    # margins recomputed from the stored matrices (1/lambda_max - threshold)
    for v in res.violations:
        i, k = v["node"], v["step"]
        if v["condition"] == "(28)":
            ref = 1 / np.linalg.eigvalsh(res.phi_post[k, i])[-1] - (1 + des.epsilon) * des.sigma
        elif v["condition"] == "(29)":
            ref = 1 / np.linalg.eigvalsh(res.phi_pred[k - 1, i])[-1] - des.beta
        else:
            ref = (1 + net.d_max) / net.d_max * des.sigma - 1 / np.linalg.eigvalsh(res.phi_post[k, i])[0]
        assert v["margin"] == pytest.approx(ref, rel=1e-9, abs=1e-12)
    # valid: never comes back, and is False from a node's first (28)/(29) violation on.
    # (28) is checked on Phi_{k|k}, itself still a bound: the flag drops from k+1; (29) on Phi_{k|k-1}: from k.
    assert res.valid[0].all()
    assert not np.any(res.valid[1:] & ~res.valid[:-1])
    for i in range(n):
        v = _first_violation(res, i)
        if v is None:
            continue
        first = v["step"] + 1 if v["condition"] == "(28)" else v["step"]
        assert not res.valid[first:, i].any()


def test_robot_paper_design_exercises_the_fallback(robot_run):
    """The scenario is chosen so that both conditions fail somewhere (otherwise the tests above are vacuous)."""
    _, _, att, _, res = robot_run
    conds = {v["condition"] for v in res.violations}
    assert {"(28)", "(29)"} <= conds
    assert att.dos.any() and att.fdi.any()


# --- a hand-written re-implementation of one step of the whole filter, for every node and step
def _robot_funcs(params):
    ku, kv = params["gamma_u"] / params["zf"], params["gamma_v"] / params["zf"]
    d1, d2, p0, q0, b = params["d1"], params["d2"], params["p0"], params["q0"], params["wheel_base"]
    cams = np.asarray(params["camera_positions"], dtype=float)

    def f(x, u):
        v = 0.5 * (u[0] + u[1])
        return np.array([x[0] + v * np.cos(x[2]), x[1] + v * np.sin(x[2]), x[2] + (u[0] - u[1]) / b])

    def F(x, u):
        v = 0.5 * (u[0] + u[1])
        return np.array([[1.0, 0.0, -v * np.sin(x[2])], [0.0, 1.0, v * np.cos(x[2])], [0.0, 0.0, 1.0]])

    def h(i, x):
        cx, cy = cams[i]
        s, c = np.sin(x[2]), np.cos(x[2])
        return np.array([ku * (-(cx - x[0]) * s + (cy - x[1]) * c - d2) + p0,
                         kv * (-(cx - x[0]) * c - (cy - x[1]) * s - d1) + q0])

    def H(i, x):
        cx, cy = cams[i]
        s, c = np.sin(x[2]), np.cos(x[2])
        return np.array([[ku * s, -ku * c, ku * (-(cx - x[0]) * c - (cy - x[1]) * s)],
                         [kv * c, kv * s, kv * ((cx - x[0]) * s - (cy - x[1]) * c)]])

    return f, F, h, H


def check_against_reference(res, net, att, des, z, u, f, F, h, H, Q, Rs):
    """Re-derive every step of a run from (3), (7), (26), (27), (30) and the documented fallback.

    Each step starts from the run's own stored ``x_post[k]`` / ``phi_post[k]`` (so errors do not
    accumulate); which recursion a node runs is read from its recorded first violation and checked
    against the margins computed here.  Returns the number of proper (Theorem 1) updates checked.
    """
    steps, n = res.K.shape[:2]
    nx = res.x_post.shape[-1]
    nz = Rs[0].shape[0]
    Ix = np.eye(nx)
    eps, sigma, beta, tau, U, V, delta = des.epsilon, des.sigma, des.beta, des.tau, des.U, des.V, des.delta
    d_max = net.d_max
    pred_fallback_from = np.full(n, 10**9)
    upd_fallback_from = np.full(n, 10**9)
    for i in range(n):
        v = _first_violation(res, i)
        if v is not None:
            if v["condition"] == "(28)":
                pred_fallback_from[i] = upd_fallback_from[i] = v["step"]
            else:
                pred_fallback_from[i], upd_fallback_from[i] = v["step"], v["step"] - 1

    def th2_ref(P):
        return np.inf if d_max == 0 else (1 + d_max) / d_max * sigma - 1 / np.linalg.eigvalsh(P)[0]

    exp_valid = np.zeros_like(res.valid)
    exp_valid[0] = True
    n_proper = 0
    for k in range(steps):
        pred_proper = np.zeros(n, bool)
        for i in range(n):
            xp = res.x_post[k, i]
            Fi = F(xp, k, u[k])
            np.testing.assert_allclose(res.x_pred[k, i], f(xp, k, u[k]), rtol=1e-12, atol=1e-12)
            P = res.phi_post[k, i]
            m28 = 1 / np.linalg.eigvalsh(P)[-1] - (1 + eps) * sigma
            if k < pred_fallback_from[i]:
                assert m28 > 0
                np.testing.assert_allclose(res.margin28[k, i], m28, rtol=1e-9)
                ref = Fi @ inv(inv(P) - (1 + eps) * sigma * Ix) @ Fi.T + U @ U.T / (eps * sigma) + Q
                pred_proper[i] = True
            else:
                if k == pred_fallback_from[i] and upd_fallback_from[i] == k:  # the (28) violation itself
                    assert m28 <= 0
                ref = Fi @ P @ Fi.T + Q
            np.testing.assert_allclose(res.phi_pred[k, i], ref, rtol=1e-9, atol=1e-13)
        pred_ok = pred_proper & exp_valid[k]
        for i in range(n):
            nb = net.neighbours[i]
            recv = [j for j in nb if att is None or not att.dos[k, i, j]]
            s_i = float(len(recv))
            innov = np.zeros(nx)
            for j in recv:
                injected = att.xi[k, i, j] if (att is not None and att.fdi[k, i, j]) else 0.0
                innov += res.x_pred[k, j] + injected - res.x_pred[k, i]
            Pp = res.phi_pred[k, i]
            xpi = res.x_pred[k, i]
            Hi = H(i, xpi, k + 1)
            Ci = tau * Pp
            proper = k < upd_fallback_from[i]
            m29 = 1 / np.linalg.eigvalsh(Pp)[-1] - beta
            if proper:
                assert m29 > 0
                d, c3 = len(nb), 3.0
                M = inv(inv(Pp) - beta * Ix)
                VV = V @ V.T / beta if beta > 0 else np.zeros((nz, nz))
                n_proper += 1
            else:
                if k == upd_fallback_from[i] and pred_fallback_from[i] == k + 1:  # the (29) violation itself
                    assert m29 <= 0
                d, c3 = 0, 1.0
                M = Pp
                VV = np.zeros((nz, nz))
            R = Rs[i]
            Ki = (Ix - s_i * Ci) @ M @ Hi.T @ inv(Hi @ M @ Hi.T + VV + R / (1 + 2 * d))
            A = Ix - s_i * Ci - Ki @ Hi
            neigh = np.zeros((nx, nx))
            for j in nb:
                neigh += c3 * (1 - net.dos_prob[i, j]) * res.phi_pred[k, j] + c3 * delta**2 * net.fdi_prob[i, j] * Ix
            phi = (1 + 2 * d) * A @ M @ A.T + Ci @ neigh @ Ci.T + Ki @ ((1 + 2 * d) * VV + R) @ Ki.T
            np.testing.assert_allclose(res.C[k, i], Ci, rtol=1e-12, atol=1e-15)
            np.testing.assert_allclose(res.K[k, i], Ki, rtol=1e-8, atol=1e-12)
            np.testing.assert_allclose(res.phi_post[k + 1, i], phi, rtol=1e-8, atol=1e-13)
            z_i = z[k, nz * i:nz * (i + 1)]
            x_ref = xpi + Ki @ (z_i - h(i, xpi, k + 1)) + Ci @ innov
            np.testing.assert_allclose(res.x_post[k + 1, i], x_ref, rtol=1e-9, atol=1e-9)
            exp_valid[k + 1, i] = proper and pred_ok[i] and all(pred_ok[j] for j in nb)
    np.testing.assert_array_equal(res.valid, exp_valid)
    # Theorem 2 is checked on Phi_{k|k}: at least at every step where the node still runs Theorem 1's
    # recursion (and on a final Phi that is a bound), never on a fallback Phi; wherever it is reported it
    # equals ((1+d_max)/d_max) sigma - 1/lambda_min, and the negative ones are exactly the violations.
    th2 = res.theorem2
    for i in range(n):
        for k in range(steps + 1):
            required = k < min(pred_fallback_from[i], steps) or (k == steps and exp_valid[steps, i])
            allowed = k <= upd_fallback_from[i]
            if required:
                assert np.isfinite(th2[k, i]) or (d_max == 0 and th2[k, i] == np.inf), (k, i)
            if not allowed:
                assert np.isnan(th2[k, i]), (k, i)
            if not np.isnan(th2[k, i]):
                np.testing.assert_allclose(th2[k, i], th2_ref(res.phi_post[k, i]), rtol=1e-9)
    neg = {(int(i), int(k)) for k, i in zip(*np.nonzero(th2 < 0))}
    reported = [(v["node"], v["step"]) for v in res.violations if v["condition"] == "theorem2"]
    assert len(reported) == len(set(reported)) and set(reported) == neg
    return n_proper


def test_robot_run_matches_hand_written_recursion(robot, robot_run):
    net, traj, att, des, res = robot_run
    f, F, h, H = _robot_funcs(robot.params)
    Rs = [robot.model.measurement_cov(i) for i in range(8)]
    n_proper = check_against_reference(res, net, att, des, traj.z, traj.inputs, lambda x, k, u: f(x, u),
                                       lambda x, k, u: F(x, u), lambda i, x, k: h(i, x), lambda i, x, k: H(i, x),
                                       robot.model.process_cov, Rs)
    assert n_proper > 8


# A path 0 - 1 - 2 on a linear model: node 0's sensor is nearly useless, so its bound blows up and
# leaves Theorem 1's recursion while nodes 1 and 2 stay proper; their flags must still drop, node 1
# through its neighbour's non-bound Phi_{0,k+1|k}, node 2 one step later through node 1's.
CHAIN_A = np.array([[1.0, 0.1], [-0.05, 0.98]])
CHAIN_R = [1e4 * np.eye(2), 0.01 * np.eye(2), 0.02 * np.eye(2)]
CHAIN_Q = 1e-3 * np.eye(2)


@pytest.fixture(scope="module")
def chain_run():
    x = ca.SX.sym("x", 2)
    sensors = [Sensor(f"s{i}", ca.vertcat(x[0] + 0.1 * i * x[1], x[1]), Gaussian.zero_mean(R))
               for i, R in enumerate(CHAIN_R)]
    model = Model("chain", x, ca.mtimes(ca.DM(CHAIN_A), x), sensors, Gaussian.zero_mean(CHAIN_Q),
                  Gaussian(np.zeros(2), 0.01 * np.eye(2)))
    net = SensorNetwork.from_edges(3, [(0, 1), (1, 2)], dos_prob=0.2, fdi_prob=0.2)
    steps = 25
    traj = simulate(model, steps, np.random.default_rng(41))
    att = simulate_attacks(net, steps, 2, np.random.default_rng(42), signal=FDISignal(0.1, (0,)))
    des = ConsensusDesign(epsilon=0.25, sigma=0.1, beta=0.1, tau=0.01, U=0.01 * np.eye(2), V=0.01 * np.eye(2),
                          delta=0.1, rule=rules.get("paper"))
    res = run_consensus(model, net, traj.z, des, attacks=att)
    return model, net, traj, att, des, res


def chain_H(i, x, k):
    return np.array([[1.0, 0.1 * i], [0.0, 1.0]])


def test_chain_validity_propagates_through_neighbours(chain_run):
    model, net, traj, att, des, res = chain_run
    bad = [v for v in res.violations if v["condition"] in ("(28)", "(29)")]
    assert [v["node"] for v in bad] == [0], "the scenario needs node 0, and only node 0, to leave the recursion"
    v = bad[0]
    assert v["condition"] == "(28)"
    # (28) fails on Phi_{0,s|s} (still a bound): node 0's flag drops from s + 1; its prediction at s is
    # not a bound, so node 1's Phi_{s+1|s+1} is not either; node 2 follows one step later.
    s = v["step"]
    assert 0 < s < 20
    for node, drop in ((0, s + 1), (1, s + 1), (2, s + 2)):
        assert res.valid[:drop, node].all() and not res.valid[drop:, node].any(), node
    check_against_reference(res, net, att, des, traj.z, np.zeros((25, 0)), lambda x, k, u: CHAIN_A @ x,
                            lambda x, k, u: CHAIN_A, lambda i, x, k: chain_H(i, x, k) @ x, chain_H,
                            CHAIN_Q, CHAIN_R)


# ----------------------------------------------------------------------------- 8. bad input
def _robot_inputs(robot, steps=5):
    traj = robot.simulate(np.random.default_rng(0), steps)
    return traj


DESIGN_CASES = [
    (dict(epsilon=0.0), "epsilon"),
    (dict(epsilon=-0.1), "epsilon"),
    (dict(epsilon=1 / 3), "epsilon"),  # d_max = 3
    (dict(epsilon=0.5), "epsilon"),
    (dict(sigma=-0.1), "sigma"),
    (dict(beta=-0.1), "beta"),
    (dict(tau=-0.01), "tau"),
    (dict(delta=-1.0), "delta"),
    (dict(sigma=float("nan")), "sigma"),
    (dict(U=0.01 * np.eye(2)), "U"),
    (dict(U=0.01 * np.ones(3)), "U"),
    (dict(V=0.1 * np.eye(3)), "V"),
    (dict(sigma=0.0), "sigma"),  # with U = 0.01 I nonzero
    (dict(beta=0.0), "beta"),  # with V = 0.1 I nonzero
]


@pytest.mark.parametrize("change, word", DESIGN_CASES)
def test_validate_design_rejects(robot, change, word):
    with pytest.raises(InputError, match=word):
        validate_design(paper_design()._replace(**change), robot.model, robot.network)


@pytest.mark.parametrize("change, word", DESIGN_CASES + [
    (dict(sigma=100.0), "sigma"),  # (28) fails at step 0: lambda_max(Phi_0|0) = 0.01
    (dict(beta=1000.0), "beta"),  # (29) fails at the first step
])
def test_bad_design_raises_input_error(robot, change, word):
    traj = _robot_inputs(robot)
    des = paper_design()._replace(**change)
    with pytest.raises(InputError, match=word):
        run_consensus(robot.model, robot.network, traj.z, des, inputs=traj.inputs)


def test_design_checks_pass_for_the_nominal_design(robot):
    """The bad-input cases differ from a design that runs (so every one of them can fail)."""
    traj = _robot_inputs(robot)
    run_consensus(robot.model, robot.network, traj.z, paper_design(), inputs=traj.inputs)
    # just inside the (28) limit at step 0: 1/((1+eps) lambda_max(Phi_0|0)) with Phi_0|0 = 0.01 I
    lim = 1 / ((1 + 1 / 6) * 0.01)
    with pytest.raises(InputError, match="sigma"):
        run_consensus(robot.model, robot.network, traj.z, paper_design()._replace(sigma=lim * 1.001),
                      inputs=traj.inputs)


def test_dos_probability_one_rejected(robot):
    traj = _robot_inputs(robot)
    p = np.zeros((8, 8))
    p[0, 1] = 1.0
    net = robot.network.with_attacks(p, 0.0)
    with pytest.raises(InputError, match="dos"):
        run_consensus(robot.model, net, traj.z, paper_design(), inputs=traj.inputs)


@pytest.mark.parametrize("phi0", [np.diag([0.01, 0.01, -0.01]), np.diag([0.01, 0.01, 0.0]),
                                  np.array([[0.01, 0.02, 0], [0.0, 0.01, 0], [0, 0, 0.01]]), 0.01 * np.eye(2)])
def test_bad_phi0_rejected(robot, phi0):
    traj = _robot_inputs(robot)
    with pytest.raises(InputError, match="phi0"):
        run_consensus(robot.model, robot.network, traj.z, paper_design(), inputs=traj.inputs, phi0=phi0)


@pytest.mark.parametrize("shape", [(5, 15), (5, 17), (16,), (5, 16, 1)])
def test_bad_z_shape_rejected(robot, shape):
    traj = _robot_inputs(robot)
    z = np.ones(shape)
    with pytest.raises(InputError, match="z"):
        run_consensus(robot.model, robot.network, z, paper_design(), inputs=traj.inputs)


@pytest.mark.parametrize("x0", [0.5, np.array([0.45, 0.6])])
def test_bad_x0_shape_rejected(robot, x0):
    traj = _robot_inputs(robot)
    with pytest.raises(InputError, match="x0"):
        run_consensus(robot.model, robot.network, traj.z, paper_design(), inputs=traj.inputs, x0=x0)


def test_short_inputs_rejected(robot):
    traj = _robot_inputs(robot)
    with pytest.raises(InputError, match="inputs"):
        run_consensus(robot.model, robot.network, traj.z, paper_design(), inputs=traj.inputs[:3])


# ----------------------------------------------------------------------------- 9. replayed schedule
def test_replayed_schedule_reproduces_estimates(robot):
    net = robot.network.with_attacks(0.3, 0.2)
    steps = 12
    traj = robot.simulate(np.random.default_rng(1), steps)
    att = simulate_attacks(net, steps, 3, np.random.default_rng(2), signal=FDISignal(1.5, (0, 1)))
    des = ConsensusDesign(epsilon=1 / 6, sigma=1e-3, beta=1e-3, tau=0.01, U=np.zeros((3, 3)), V=np.zeros((2, 2)),
                          delta=1.5 * np.sqrt(2), rule=rules.get("paper"))
    first = run_consensus(robot.model, net, traj.z, des, inputs=traj.inputs, attacks=att)
    assert first.feasible
    assert not any(v["condition"] in ("(28)", "(29)") for v in first.violations)
    again = run_consensus(robot.model, net, traj.z, des, inputs=traj.inputs, attacks=att, gains=(first.K, first.C))
    np.testing.assert_array_equal(again.x_post, first.x_post)
    np.testing.assert_array_equal(again.K, first.K)
    np.testing.assert_array_equal(again.C, first.C)
    assert not again.valid[1:].any()
    # a different schedule gives different estimates (the replay is really used)
    other = run_consensus(robot.model, net, traj.z, des, inputs=traj.inputs, attacks=att,
                          gains=(0.5 * first.K, first.C))
    assert np.abs(other.x_post[1:] - first.x_post[1:]).max() > 1e-6
