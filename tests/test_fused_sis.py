"""Seed 004's SIS filters on the fused kernels (:mod:`filters.fused.sis`) against the NumPy engine (``run_sis``).

The particles are drawn in ``run_sis``'s order (the prior's draws, then per step ``n_w``
normals per particle, as ``Gaussian.sample``), so with one Generator per run the fused
filter reproduces every filter of the fdi-four-tank study — every detector, likelihood,
the estimation mode and the linear-weights emulation — to rounding, and its detections
exactly.  Also: a user's model with inputs other than the four-tank, and the checks.
"""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from designer import Gaussian, InputError, Model, Sensor
from designer.validation import ComputationError
from filters.attacks import bias_attack
from filters.fdi import (attack_threshold, deception_mixture_loglik, detection_gain, measurement_cov,
                         measurement_matrix, modified_detector, normal_detector, residual_threshold, run_sis,
                         uniform_loglik)
from filters.fused import sis_fdi, sis_particles
from studies.scenarios import load_scenario

R, N = 3, 100


@pytest.fixture(scope="module")
def tank():
    sc = load_scenario("four-tank", {"steps": 80})
    m, K, ch = sc.model, sc.steps, sc.channel
    clean, attacked, gamma = [], [], None
    for r in range(R):
        tr = sc.simulate(np.random.default_rng(10 + r), K)
        att = bias_attack(tr.z, bias=ch.bias, tau=ch.tau, prob=ch.prob, rng=np.random.default_rng(20 + r))
        clean.append(tr.z), attacked.append(att.y)
        gamma = att.gamma
    G = measurement_matrix(m)
    eta = residual_threshold(G, detection_gain(G, m.process_cov, measurement_cov(m)), ch.norm_min).eta
    zeta, _ = attack_threshold(N, ch.prob)
    return dict(sc=sc, m=m, K=K, u=sc.inputs(K), clean=np.stack(clean), attacked=np.stack(attacked), gamma=gamma,
                eta=eta, zeta=zeta, ch=ch)


def _per_run(detector):
    def detect(x_prev, x, k1, z_k, rngs):
        return np.concatenate([detector(x_prev[r:r + 1], x[r:r + 1], k1, z_k[r:r + 1], g) for r, g in enumerate(rngs)])

    return detect


def _both(t, z, numpy_kw, fused_kw, aux=False):
    m, K, u = t["m"], t["K"], t["u"]
    extra = {"aux_rng": [np.random.default_rng(100 + r) for r in range(R)]} if aux else {}
    ref = run_sis(m, z, [np.random.default_rng(r) for r in range(R)], particles=N, inputs=u, **numpy_kw, **extra)
    gens = [np.random.default_rng(r) for r in range(R)]
    x0 = np.stack([m.prior.sample(g, N) for g in gens])
    parts = sis_particles(m, x0, gens, K, inputs=u)
    if aux:
        fused_kw = dict(fused_kw, aux_rngs=[np.random.default_rng(100 + r) for r in range(R)])
    return ref, sis_fdi(m, parts, z, **fused_kw), parts


CASES = {
    "normal, no attack": ("clean", lambda t: dict(detector=normal_detector(t["m"], t["eta"]), zeta=t["zeta"]),
                          lambda t: dict(detector="normal", eta=t["eta"], zeta=t["zeta"]), False),
    "normal under attack": ("attacked", lambda t: dict(detector=normal_detector(t["m"], t["eta"]), zeta=t["zeta"]),
                            lambda t: dict(detector="normal", eta=t["eta"], zeta=t["zeta"]), False),
    "normal, linear weights": (
        "attacked", lambda t: dict(detector=normal_detector(t["m"], t["eta"], linear_weights=True), zeta=t["zeta"],
                                   linear_weights=True),
        lambda t: dict(detector="normal", eta=t["eta"], zeta=t["zeta"], linear_weights=True), False),
    "modified, estimation mode": (
        "attacked", lambda t: dict(detector=modified_detector(t["m"], t["eta"]), zeta=t["zeta"], gamma_hat=t["gamma"]),
        lambda t: dict(detector="modified", eta=t["eta"], zeta=t["zeta"], gamma_hat=t["gamma"]), False),
    "sampled correction": (
        "attacked", lambda t: dict(detector=_per_run(modified_detector(t["m"], t["eta"], correction="sampled",
                                                                       inputs=t["u"])),
                                   zeta=t["zeta"], gamma_hat=t["gamma"]),
        lambda t: dict(detector="sampled", eta=t["eta"], zeta=t["zeta"], gamma_hat=t["gamma"]), True),
    "method of [31]": ("attacked", lambda t: dict(loglik=deception_mixture_loglik(t["m"], attack_prob=t["ch"].prob,
                                                                                  deception=t["ch"].bias)),
                       lambda t: dict(likelihood="mixture", attack_prob=t["ch"].prob, deception=t["ch"].bias), False),
    "weights 1/N": ("attacked", lambda t: dict(loglik=uniform_loglik), lambda t: dict(likelihood="uniform"), False),
}


@pytest.mark.parametrize("case", list(CASES))
def test_fused_sis_reproduces_run_sis(tank, case):
    zname, numpy_kw, fused_kw, aux = CASES[case]
    ref, ours, _ = _both(tank, tank[zname], numpy_kw(tank), fused_kw(tank), aux)
    np.testing.assert_allclose(ours.mean, ref.mean, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(ours.ess, ref.ess, rtol=1e-8)
    np.testing.assert_array_equal(ours.detected, ref.detected)
    np.testing.assert_allclose(ours.beta, ref.beta, rtol=0, atol=1e-9)  # NaN where ref has NaN
    np.testing.assert_array_equal(ours.collapsed, ref.collapsed)
    if "detector" in fused_kw(tank) and zname == "attacked" and case != "normal, linear weights":
        assert ours.detected.any()  # the case exercises detection (and, with gamma_hat, the estimation mode)


def test_linear_weights_collapse_and_undefined_detection_as_run_sis(tank):
    """A far measurement: every linear-domain weight underflows (a collapse) and (17) is 0/0 (beta NaN)."""
    z = tank["attacked"] + 50.0
    ref, ours, _ = _both(tank, z, CASES["normal, linear weights"][1](tank), CASES["normal, linear weights"][2](tank))
    assert ref.collapsed.any() and np.isnan(ref.beta).any()
    np.testing.assert_array_equal(ours.collapsed, ref.collapsed)
    np.testing.assert_array_equal(np.isnan(ours.beta), np.isnan(ref.beta))
    np.testing.assert_allclose(ours.mean, ref.mean, rtol=1e-9, atol=1e-9)


def test_filters_share_the_particles_and_threads_change_nothing(tank):
    m, K, u, z = tank["m"], tank["K"], tank["u"], tank["attacked"]
    gens = [np.random.default_rng(r) for r in range(R)]
    x0 = np.stack([m.prior.sample(g, N) for g in gens])
    one = sis_particles(m, x0, gens, K, inputs=u)
    gens = [np.random.default_rng(r) for r in range(R)]
    x0 = np.stack([m.prior.sample(g, N) for g in gens])
    two = sis_particles(m, x0, gens, K, inputs=u, threads=2)
    assert np.array_equal(one.x, two.x) and np.array_equal(one.fx, two.fx)
    kw = dict(detector="modified", eta=tank["eta"], zeta=tank["zeta"])
    a, b = sis_fdi(m, one, z, **kw), sis_fdi(m, one, z, threads=2, **kw)
    assert np.array_equal(a.mean, b.mean) and np.array_equal(a.detected, b.detected)
    # run 1 alone: the same numbers as in the batch (nothing shared between runs)
    g = np.random.default_rng(1)
    alone = sis_particles(m, m.prior.sample(g, N)[None], [g], K, inputs=u)
    assert np.array_equal(alone.x[0], one.x[1])
    assert np.array_equal(sis_fdi(m, alone, z[1:2], **kw).mean[0], a.mean[1])


def test_a_user_model_with_inputs_and_a_noise_gain():
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    f = ca.vertcat(0.9 * x[0] + 0.1 * ca.tanh(x[1]) + u[0], 0.8 * x[1] + 0.05 * ca.sin(x[0]))
    m = Model("user", x, f, [Sensor("a", x[0:1], Gaussian.zero_mean([[0.05]])),
                             Sensor("b", x[0:1] + 2.0 * x[1:2], Gaussian([0.1], [[0.2]]))],
              Gaussian([0.01], [[0.02]]), Gaussian([0.0, 1.0], 0.3 * np.eye(2)), u=u,
              noise_gain=np.array([[1.0], [0.5]]))
    K, M = 30, 64
    inputs = np.cos(0.3 * np.arange(K))[:, None]
    z = np.random.default_rng(5).normal(size=(2, K, 2))
    ref = run_sis(m, z, [np.random.default_rng(r) for r in range(2)], particles=M, inputs=inputs)
    gens = [np.random.default_rng(r) for r in range(2)]
    parts = sis_particles(m, np.stack([m.prior.sample(g, M) for g in gens]), gens, K, inputs=inputs)
    ours = sis_fdi(m, parts, z)
    np.testing.assert_allclose(ours.mean, ref.mean, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(ours.ess, ref.ess, rtol=1e-8)


@pytest.mark.parametrize("kw, needle", [
    (dict(detector="normal"), "eta"),
    (dict(detector="nosuch", eta=0.1, zeta=0.1), "detector"),
    (dict(likelihood="nosuch"), "likelihood"),
    (dict(likelihood="mixture", attack_prob=0.2), "deception"),
    (dict(deception=[0.5] * 4), "mixture"),
    (dict(eta=0.1, zeta=0.1), "detector"),
    (dict(gamma_hat=np.zeros((80, 4))), "gamma_hat"),
    (dict(detector="sampled", eta=0.1, zeta=0.1), "aux_rngs"),
    (dict(aux_rngs=[np.random.default_rng(0)]), "aux_rngs"),
    (dict(linear_weights=1), "linear_weights"),
])
def test_bad_input_is_an_input_error_naming_it(tank, kw, needle):
    m, K, u = tank["m"], tank["K"], tank["u"]
    g = np.random.default_rng(0)
    parts = sis_particles(m, m.prior.sample(g, 8)[None], [g], K, inputs=u)
    with pytest.raises(InputError, match=needle):
        sis_fdi(m, parts, tank["attacked"][:1], **kw)


def test_particles_need_the_inputs_and_the_right_shapes(tank):
    m, K, u = tank["m"], tank["K"], tank["u"]
    g = np.random.default_rng(0)
    x0 = m.prior.sample(g, 8)[None]
    with pytest.raises(InputError, match="inputs"):
        sis_particles(m, x0, [g], K)
    with pytest.raises(InputError, match="inputs"):
        sis_particles(m, x0, [g], K, inputs=u[:-1])
    parts = sis_particles(m, x0, [g], K, inputs=u)
    with pytest.raises(InputError, match="z must have shape"):
        sis_fdi(m, parts, tank["attacked"][:1, :-1])


def test_a_mean_that_leaves_the_reals_is_named_by_run_and_step():
    x = ca.SX.sym("x", 1)
    m = Model("blowup", x, ca.sqrt(x - 10.0), [Sensor("s", x, Gaussian.zero_mean([[0.1]]))],
              Gaussian.zero_mean([[0.01]]), Gaussian([1.0], [[0.1]]))  # sqrt of a negative number: NaN at step 1
    g = np.random.default_rng(0)
    parts = sis_particles(m, m.prior.sample(g, 16)[None], [g], 5)
    with pytest.raises(ComputationError, match="run 0 is not finite from step 1"):
        sis_fdi(m, parts, np.zeros((1, 5, 1)))
