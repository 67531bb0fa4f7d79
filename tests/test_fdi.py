"""Seed 004's FDI attack, thresholds, corrected particles, detectors and SIS engine, against independent references."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from designer import InputError
from designer.model import Model, Sensor
from designer.noise import Gaussian, GaussianMixture
from filters.attacks import attack_values, bias_attack
from filters.fdi import (attack_threshold, correct_particles, corrected_proposal, deception_mixture_loglik,
                         detection_counts, detection_gain, false_alarm_condition, measurement_cov, measurement_matrix,
                         modified_detector, normal_detector, residual_threshold, run_sis, uniform_loglik)
from filters.particle import additive_noise_loglik, run_sir
from studies.scenarios import load_scenario


def _spd(rng, n, scale=1.0):
    A = rng.standard_normal((n, n))
    return scale * (A @ A.T + n * np.eye(n))


# --------------------------------------------------------------------------- thresholds (45), (46), (53)
def test_eta_of_the_default_four_tank_is_the_papers_0_233():
    sc = load_scenario("four-tank")
    m = sc.model
    G = measurement_matrix(m)
    np.testing.assert_array_equal(G, np.eye(4))
    th = residual_threshold(G, detection_gain(G, m.process_cov, measurement_cov(m)), sc.channel.norm_min)
    assert round(th.eta, 3) == 0.233
    # closed form with G = I, Q = q I, R = diag(r): G K = diag(q / (r + q)), the largest on the r = 5e-4 channels
    assert th.sigma_bar == pytest.approx(1e-4 / (5e-4 + 1e-4), rel=1e-12)
    assert th.eta == pytest.approx((1 - 1e-4 / 6e-4) * 0.28, rel=1e-12)
    lhs, holds = false_alarm_condition(measurement_cov(m), th.eta)
    assert lhs == pytest.approx(3 * np.sqrt(3e-3)) and holds  # Theorem 2 holds at the low noise ...
    high = load_scenario("four-tank", {"noise": "high"}).model
    assert not false_alarm_condition(measurement_cov(high), th.eta)[1]  # ... and fails at the high one (0.367)


@pytest.mark.parametrize("c", [1.0, 0.5, 3.0])
def test_varsigma_closed_form_for_a_scaled_identity_measurement(c):
    rng = np.random.default_rng(1)
    q, r = 10 ** rng.uniform(-5, -2), 10 ** rng.uniform(-4, -1, size=5)
    G = c * np.eye(5)
    K = detection_gain(G, q * np.eye(5), np.diag(r))
    gk = c * c * q / (r + c * c * q)  # eigen- and singular values of G K, all in (0, 1)
    th = residual_threshold(G, K, 0.7)
    assert th.varsigma == pytest.approx(abs(gk.max() - 1.0), rel=1e-10)
    assert th.eta == pytest.approx(0.7 * (1.0 - gk.max()), rel=1e-10)


def test_attack_threshold_from_53():
    zeta, alpha = attack_threshold(100, 0.5)
    assert alpha == pytest.approx(0.5 * 100 / 99) and zeta == pytest.approx(0.5)
    zeta, alpha = attack_threshold(10, alpha=0.9)
    assert zeta == pytest.approx(0.81)
    with pytest.raises(InputError, match="attack_prob"):
        attack_threshold(3, 0.9)  # p_l N/(N-1) = 1.35: no alpha satisfies (53)
    with pytest.raises(InputError, match="alpha"):
        attack_threshold(10, alpha=1.0)
    with pytest.raises(InputError, match="particles"):
        attack_threshold(1, 0.5)


# --------------------------------------------------------------------------- the corrected particle (36)
def test_corrected_particle_is_the_kalman_update_of_a_point_with_covariance_Q():
    rng = np.random.default_rng(2)
    n_x, n_y = 4, 3
    G = rng.standard_normal((n_y, n_x))
    Q, R = _spd(rng, n_x, 0.1), _spd(rng, n_y, 0.05)
    x = rng.standard_normal((2, 5, n_x))
    y = rng.standard_normal((2, n_y))
    got = correct_particles(x, y, G, detection_gain(G, Q, R))
    # information form: (Q^-1 + G' R^-1 G) x+ = Q^-1 x + G' R^-1 y
    Qi, Ri = np.linalg.inv(Q), np.linalg.inv(R)
    A = Qi + G.T @ Ri @ G
    b = x @ Qi.T + (y @ Ri.T @ G)[:, None, :]
    want = np.linalg.solve(A, b[..., None])[..., 0]
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


def _linear_model(process_noise, A, G, R, prior_var=1.0):
    n = A.shape[0]
    x = ca.SX.sym("x", n)
    sensors = [Sensor("y", ca.mtimes(ca.DM(G), x), Gaussian.zero_mean(R))]
    return Model("lin", x, ca.mtimes(ca.DM(A), x), sensors, process_noise, Gaussian(np.zeros(n), prior_var * np.eye(n)))


def test_corrected_proposal_importance_weights_integrate_to_the_predictive_density():
    """E_q[p(y|x) p(x|x_prev) / q] = p(y | x_prev) exactly, here for a Gaussian-mixture process noise."""
    A = np.array([[0.9, 0.2], [0.0, 0.8]])
    G = np.array([[1.0, 0.5]])
    R = np.array([[0.2]])
    w = GaussianMixture.from_arrays([0.7, 0.3], [[0.3, -0.1], [-0.7, 0.2333333333333333]],
                                    [np.diag([0.05, 0.02]), np.diag([0.4, 0.1])])
    m = _linear_model(w, A, G, R)
    x_prev = np.array([[[0.5, -1.0]]])
    y = np.array([[0.4]])
    propose = corrected_proposal(m)
    x, corr = propose(np.broadcast_to(x_prev, (1, 200_000, 2)), 0, y, np.random.default_rng(3))
    iw = np.exp(additive_noise_loglik(m)(x, 1, y) + corr)[0]
    fx = A @ x_prev[0, 0]
    want = sum(wc * Gaussian(G @ (fx + c.mean), R + G @ c.cov @ G.T).pdf(y[0])
               for wc, c in zip(w.weights, w.components))
    assert abs(iw.mean() - want) < 5 * iw.std() / np.sqrt(iw.size)
    # with Gaussian noise the proposal is exact: every importance weight equals p(y | x_prev)
    mg = _linear_model(Gaussian.zero_mean(w.cov), A, G, R)
    x, corr = corrected_proposal(mg)(np.broadcast_to(x_prev, (1, 50, 2)), 0, y, np.random.default_rng(4))
    iw = np.exp(additive_noise_loglik(mg)(x, 1, y) + corr)
    want = Gaussian(G @ fx, R + G @ w.cov @ G.T).pdf(y[0])
    np.testing.assert_allclose(iw, want, rtol=1e-9)


# --------------------------------------------------------------------------- the attack (3)-(4)
def test_attack_values_closed_form_and_bernoulli_frequency():
    bias, tau, K = np.array([0.5, -1.0, 2.0]), 0.85, 60
    k = np.arange(1, K + 1)[:, None]
    np.testing.assert_allclose(attack_values(K, bias, tau), (1 - tau**k) * bias, rtol=1e-12)
    y = np.random.default_rng(5).standard_normal((400, K, 3))
    att = bias_attack(y, bias=bias, tau=tau, prob=0.3, rng=np.random.default_rng(6))
    np.testing.assert_allclose(att.y - y, att.l[..., None] * att.gamma, atol=1e-15)
    n = att.l.size
    assert abs(att.l.mean() - 0.3) < 4 * np.sqrt(0.3 * 0.7 / n)
    # the paper's gamma-bar = 0.5 * 1: only k = 1, 2, 3 lie below ||gamma||_min = 0.28
    norms = np.linalg.norm(attack_values(10, 0.5 * np.ones(4), 0.9), axis=1)
    np.testing.assert_allclose(norms[:4], [0.1, 0.19, 0.271, 0.3439], rtol=1e-12)
    assert (norms <= 0.28).sum() == 3


# --------------------------------------------------------------------------- detectors (14)/(17) and (58)
def _identity_model(r=1e-3, q=1e-4, n=2):
    return _linear_model(Gaussian.zero_mean(q * np.eye(n)), np.eye(n), np.eye(n), r * np.eye(n), prior_var=1e-2)


def test_normal_detector_by_hand_and_its_underflow_in_linear_weights():
    m = _identity_model()
    x = np.array([[[0.0, 0.0], [0.3, 0.0], [0.0, 0.05]]])
    y = np.array([[0.0, 0.0]])
    ll = -0.5 * (np.sum(x**2, -1) / 1e-3)
    W = np.exp(ll - ll.max())
    W /= W.sum()
    beta = normal_detector(m, 0.2)(None, x, 1, y, None)
    np.testing.assert_allclose(beta, W[:, 1], rtol=1e-12)  # only particle 1's residual (0.3) exceeds 0.2
    far = np.array([[5.0, 5.0]])  # every likelihood is exp(-25000) < the smallest double
    assert normal_detector(m, 0.2)(None, x, 1, far, None)[0] == pytest.approx(1.0)
    assert np.isnan(normal_detector(m, 0.2, linear_weights=True)(None, x, 1, far, None)[0])
    np.testing.assert_allclose(normal_detector(m, 0.2, linear_weights=True)(None, x, 1, y, None), W[:, 1],
                               rtol=1e-9)


def test_modified_detector_counts_corrected_residuals():
    m = _identity_model(r=1e-3, q=1e-3)  # K = I/2: corrected residuals are half the raw ones
    x = np.array([[[0.0, 0.0], [0.3, 0.0], [0.5, 0.0], [0.0, 0.7]]])
    y = np.array([[0.0, 0.0]])
    beta = modified_detector(m, 0.2)(None, x, 1, y, None)
    np.testing.assert_allclose(beta, [0.5])  # residuals 0, 0.15, 0.25, 0.35
    with pytest.raises(InputError, match="aux_rng"):
        modified_detector(m, 0.2, correction="sampled")(x, x, 1, y, None)
    with pytest.raises(InputError, match="correction"):
        modified_detector(m, 0.2, correction="exact")


def test_detection_counts_by_hand():
    gamma = np.array([[0.1], [0.2], [0.5], [0.9]])
    l = np.array([[True, True, True, False], [False, True, False, True]])
    d = np.array([[False, True, False, True], [False, False, True, True]])
    c = detection_counts(l, d, gamma, 0.3)
    assert c._asdict() == {"false_alarms": 2, "missed": 1, "stealthy": 2, "attacks": 5, "detected": 2}


# --------------------------------------------------------------------------- the SIS engine
def test_sis_without_detector_is_run_sir_that_never_resamples():
    m = _identity_model(r=0.05, q=0.01)
    z = np.random.default_rng(7).standard_normal((3, 15, 2))
    a = run_sis(m, z, np.random.default_rng(8), particles=40)
    b = run_sir(m, z, np.random.default_rng(8), particles=40, ess_threshold=1e-6).detail  # ESS >= 1 > 4e-5: never
    assert not b.resampled.any()
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(a.ess, b.ess, rtol=1e-10)


def test_estimation_mode_with_a_perfect_detection_is_the_attack_free_filter():
    """(55)-(57): with l-hat = l and gamma-hat = gamma, the same particles give the attack-free estimate."""
    sc = load_scenario("four-tank", {"steps": 40})
    m, K = sc.model, 40
    y = np.stack([sc.simulate(np.random.default_rng(s)).z for s in (10, 11)])
    att = bias_attack(y, bias=sc.channel.bias, tau=0.9, prob=0.5, rng=np.random.default_rng(12))
    kw = dict(particles=50, inputs=sc.inputs(K))

    def gens():
        return [np.random.default_rng(s) for s in (20, 21)]

    def oracle(x_prev, x, k1, z_k, rng):
        return att.l[:, k1 - 1].astype(float)

    clean = run_sis(m, y, gens(), **kw)
    fixed = run_sis(m, att.y, gens(), detector=oracle, zeta=0.5, gamma_hat=att.gamma, **kw)
    np.testing.assert_allclose(fixed.mean, clean.mean, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(fixed.detected, att.l)
    blind = run_sis(m, att.y, gens(), **kw)
    assert np.abs(blind.mean - clean.mean).max() > 0.05  # the attack does bias the unprotected filter


def test_linear_weights_collapse_and_uniform_and_mixture_likelihoods():
    m = _identity_model(r=1e-3, q=1e-4)
    z = np.zeros((1, 3, 2))
    z[0, 1] = 10.0  # far from every particle: linear weights underflow
    res = run_sis(m, z, np.random.default_rng(0), particles=20, linear_weights=True)
    np.testing.assert_array_equal(res.collapsed[0], [False, True, False])
    assert not run_sis(m, z, np.random.default_rng(0), particles=20).collapsed.any()
    uni = run_sis(m, z, np.random.default_rng(0), particles=20, loglik=uniform_loglik)
    np.testing.assert_allclose(uni.ess, 20.0, rtol=1e-12)
    x = np.array([[[0.0, 0.0], [1.0, 1.0]]])
    ll = deception_mixture_loglik(m, attack_prob=0.25, deception=[1.0, 1.0])(x, 1, np.array([[1.0, 1.0]]))
    g = Gaussian.zero_mean(1e-3 * np.eye(2))  # one two-dimensional sensor: one deception indicator
    want = [np.log(0.75 * g.pdf([1.0, 1.0]) + 0.25 * g.pdf([0.0, 0.0])),
            np.log(0.75 * g.pdf([0.0, 0.0]) + 0.25 * g.pdf([-1.0, -1.0]))]
    np.testing.assert_allclose(ll[0], want, rtol=1e-12)
    # the four tank's four scalar sensors: a product of per-sensor mixtures (one indicator per sensor, as in [31])
    ft = load_scenario("four-tank").model
    rho, xs, ys = np.array([0.5, 0.5, 0.5, 0.5]), np.array([[[12.0, 12.0, 1.5, 1.5]]]), np.array([[12.1, 12.5, 1.5, 2.0]])
    r = ys[0] - xs[0, 0]
    sd = np.sqrt(np.diag(measurement_cov(ft)))
    want = np.sum(np.log(0.6 * Gaussian.zero_mean([[1.0]]).pdf((r / sd)[:, None]) / sd
                         + 0.4 * Gaussian.zero_mean([[1.0]]).pdf(((r - rho) / sd)[:, None]) / sd))
    got = deception_mixture_loglik(ft, attack_prob=0.4, deception=rho)(xs, 1, ys)
    np.testing.assert_allclose(got, [[want]], rtol=1e-12)


# --------------------------------------------------------------------------- bad inputs
@pytest.mark.parametrize("call, needle", [
    (lambda: attack_values(5, [0.5], 1.5), "tau"),
    (lambda: attack_values(0, [0.5], 0.5), "steps"),
    (lambda: attack_values(5, [[0.5]], 0.5), "bias"),
    (lambda: bias_attack(np.zeros((4, 2)), bias=[1, 1], tau=0.5, prob=1.2, rng=np.random.default_rng()), "prob"),
    (lambda: bias_attack(np.zeros((4, 2)), bias=[1, 1, 1], tau=0.5, prob=0.2, rng=np.random.default_rng()), "bias"),
    (lambda: bias_attack(np.zeros((4, 2)), bias=[1, 1], tau=0.5, prob=0.2, rng=1), "rng"),
    (lambda: detection_gain(np.eye(2), np.eye(2), -np.eye(2)), "R"),
    (lambda: detection_gain(np.eye(2), np.eye(3), np.eye(2)), "Q"),
    (lambda: residual_threshold(np.eye(2), np.eye(2), 0.0), "gamma_min"),
    (lambda: residual_threshold(np.eye(2), np.eye(3), 0.3), "K"),
    (lambda: normal_detector(_identity_model(), -1.0), "eta"),
    (lambda: deception_mixture_loglik(_identity_model(), attack_prob=1.0, deception=[1, 1]), "attack_prob"),
    (lambda: deception_mixture_loglik(_identity_model(), attack_prob=0.5, deception=[1]), "deception"),
    (lambda: run_sis(_identity_model(), np.zeros((2, 3, 2)), np.random.default_rng(), particles=0), "particles"),
    (lambda: run_sis(_identity_model(), np.zeros((3, 2)), np.random.default_rng(), particles=5), "z"),
    (lambda: run_sis(_identity_model(), np.zeros((2, 3, 2)), [np.random.default_rng()], particles=5), "rng"),
    (lambda: run_sis(_identity_model(), np.zeros((1, 3, 2)), np.random.default_rng(), particles=5,
                     detector=lambda *a: np.zeros(1)), "zeta"),
    (lambda: run_sis(_identity_model(), np.zeros((1, 3, 2)), np.random.default_rng(), particles=5,
                     detector=lambda *a: np.zeros(1), zeta=0.5, gamma_hat=np.zeros((3, 3))), "gamma_hat"),
    (lambda: run_sis(_identity_model(), np.zeros((1, 3, 2)), np.random.default_rng(), particles=5,
                     gamma_hat=np.zeros((3, 2))), "gamma_hat"),
    (lambda: run_sis(load_scenario("four-tank").model, np.zeros((1, 3, 4)), np.random.default_rng(), particles=5),
     "inputs"),
])
def test_bad_inputs_name_the_parameter(call, needle):
    with pytest.raises(InputError, match=needle):
        call()


def test_nonlinear_measurement_is_rejected():
    x = ca.SX.sym("x", 2)
    m = Model("nl", x, x, [Sensor("s", ca.sin(x[0:1]), Gaussian.zero_mean([[0.1]]))], Gaussian.zero_mean(np.eye(2)),
              Gaussian(np.zeros(2), np.eye(2)))
    with pytest.raises(InputError, match="model: the modified PF needs a linear"):
        measurement_matrix(m)
    with pytest.raises(InputError, match="model"):
        modified_detector(m, 0.2)
