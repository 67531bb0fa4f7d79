"""Seed 002 likelihood (13)-(16) against the generative binary channel, and the paper's ordering."""
from __future__ import annotations

import numpy as np
from scipy.integrate import quad

from designer import Model
from filters.binary import binary_loglik
from filters.attacks import binary_sensor_channel
from filters.particle import run_sir
from studies.scenarios import load_scenario


def _setup():
    sc = load_scenario("target-binary-energy")
    ch = sc.channel
    kw = dict(deception=ch.deception, threshold=ch.threshold, gain=ch.gain, channel_noise=ch.channel_noise)
    return sc, kw


def test_likelihood_is_the_density_of_the_received_signal():
    sc, kw = _setup()
    m = sc.model
    one = Model("one", m.x, m.f_expr, [m.sensors[0]], m.process_noise, m.prior)
    probs = dict(dos_prob=0.2, deception_prob=0.3, flip_prob=0.15)
    ll = binary_loglik(one, **probs, **kw)
    rng = np.random.default_rng(0)
    for x in (np.array([20.0, 0, 25.0, 0]), np.array([45.0, 0, 40.0, 0])):  # near: h > T, far: h < T
        n = 300_000
        yhat = one.h(0, x) + one.sensors[0].noise.sample(rng, n)[:, 0]
        y = binary_sensor_channel(yhat[:, None], **probs, rng=rng, **kw).y[:, 0]
        dens = lambda v: float(np.exp(ll(x[None, None, :], 1, np.array([[v]]))[0, 0]))  # noqa: E731
        assert abs(quad(dens, -1.5, 2.0, limit=200)[0] - 1.0) < 1e-6
        for lo, hi in ((-0.2, 0.2), (0.3, 0.7), (0.1, 0.45)):
            freq = np.mean((y >= lo) & (y <= hi))
            exact = quad(dens, lo, hi)[0]
            assert abs(freq - exact) < 5 * np.sqrt(exact * (1 - exact) / n)


def test_paper_ordering_sec_pf():
    """Sec-PF is close to Sta-PF on clean data; Sta-PF-Neg (ignoring the attacks) is the worst."""
    sc, kw = _setup()
    m = sc.model
    runs, K = 6, 60
    rng = np.random.default_rng(1)
    tr = sc.simulate(rng, K, batch=runs)
    att = binary_sensor_channel(tr.z, dos_prob=0.1, deception_prob=0.1, flip_prob=0.1, rng=rng, **kw).y
    clean = binary_sensor_channel(tr.z, dos_prob=0.0, deception_prob=0.0, flip_prob=0.0, rng=rng, **kw).y

    def rmse_p(y, **probs):
        res = run_sir(m, y, np.random.default_rng(2), particles=300, runs=runs,
                      loglik=binary_loglik(m, **probs, **kw)).detail
        e = res.mean[:, 1:] - tr.x[:, 1:]
        return np.sqrt((e[..., [0, 2]] ** 2).sum(-1).mean())

    sec = rmse_p(att, dos_prob=0.1, deception_prob=0.1, flip_prob=0.1)
    neg = rmse_p(att)
    sta = rmse_p(clean)
    assert neg > 2 * sec and sec < 2 * sta


def test_fair_coin_flipping_makes_the_bits_uninformative():
    """With alpha-bar = 1/2 a received bit says nothing about the state: (13) is constant in x."""
    sc, kw = _setup()
    m = sc.model
    x = m.prior.sample(np.random.default_rng(0), (1, 200))
    y = np.random.default_rng(1).normal(0.25, 0.3, size=(1, m.n_sensors))
    ll = binary_loglik(m, dos_prob=0.2, deception_prob=0.3, flip_prob=0.5, **kw)(x, 1, y)
    assert np.ptp(ll) < 1e-9 * np.abs(ll).max()
    assert np.ptp(binary_loglik(m, dos_prob=0.2, deception_prob=0.3, flip_prob=0.4, **kw)(x, 1, y)) > 1e-3
