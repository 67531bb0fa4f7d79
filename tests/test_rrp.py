"""Seed 000 likelihoods: (14) against the generative channel, angle wrapping, the paper's ordering."""
from __future__ import annotations

import numpy as np

from filters.attacks import deception_attack, round_robin_schedule
from filters.particle import run_sir
from filters.rrp import all_sensors_loglik, rrp_loglik, wrap_angles
from studies.scenarios import load_scenario


def test_wrap_angles():
    r = np.array([[3.5, 2 * np.pi + 0.1], [-3.5, -0.2]])
    w = wrap_angles(r, [0, 1])
    np.testing.assert_allclose(w, [[3.5 - 2 * np.pi, 0.1], [2 * np.pi - 3.5, -0.2]], atol=1e-12)
    assert np.all((w > -np.pi) & (w <= np.pi))


def _box_prob(cdf, lo, hi):
    """P(lo <= Y <= hi) for a 2-D CDF by inclusion-exclusion."""
    return (cdf([hi[0], hi[1]]) - cdf([lo[0], hi[1]]) - cdf([hi[0], lo[1]]) + cdf([lo[0], lo[1]]))


def test_likelihood_14_is_the_density_of_the_received_packet():
    """Box probabilities of simulated received packets match those of (1-eta) p_nu(y - h) + eta p_xi(y)."""
    sc = load_scenario("target-range-bearing")
    m = sc.model
    box, p = sc.channel.deception, 0.2
    x = np.array([30.0, 0.3, 40.0, 0.3])
    h = m.h(1, x)
    rng = np.random.default_rng(0)
    n = 400_000
    y = h + m.sensors[1].noise.sample(rng, n)
    rec = deception_attack(y, p, box, rng).y
    nu = m.sensors[1].noise
    for lo, hi in (([h[0] - 2, h[1] - 0.01], [h[0] + 1, h[1] + 0.02]), ([0.0, -1.0], [30.0, 0.5])):
        lo, hi = np.array(lo), np.array(hi)
        freq = np.mean(np.all((rec >= lo) & (rec <= hi), axis=1))
        exact = (1 - p) * _box_prob(lambda v: nu.cdf(np.array(v) - h), lo, hi) + p * _box_prob(box.cdf, lo, hi)
        assert abs(freq - exact) < 5 * np.sqrt(exact * (1 - exact) / n)
    # and the function itself is that mixture, in the log domain
    sched = np.array([1])
    ll = rrp_loglik(m, sched, attack_prob=p, signal=box)(x[None, None, :], 1, rec[:1])
    direct = np.log((1 - p) * nu.pdf(rec[0] - h) + p * box.pdf(rec[0]))
    np.testing.assert_allclose(ll[0, 0], direct, rtol=1e-12)


def test_paper_ordering_of_the_rrp_filters():
    """RRP-SPF-DA (ignoring the attack) is far worse than RRP-PF-DA; PF-DA with all sensors is best."""
    sc = load_scenario("target-range-bearing")
    m = sc.model
    runs, K, M = 6, 60, 300
    rng = np.random.default_rng(3)
    tr = sc.simulate(rng, K, batch=runs)
    y = tr.per_sensor(m)
    y[..., 1] = wrap_angles(y, [1])[..., 1]
    sched = round_robin_schedule(K, 4, 1)
    ys = y[:, np.arange(K), sched]
    sig = sc.channel.deception
    att = deception_attack(ys, 0.2, sig, rng)
    att_all = deception_attack(y, 0.2, sig, rng).y.reshape(runs, K, 8)

    def rmse_p(z, ll):
        res = run_sir(m, z, np.random.default_rng(4), particles=M, runs=runs, loglik=ll).detail
        e = res.mean[:, 1:] - tr.x[:, 1:]
        return np.sqrt((e[..., [0, 2]] ** 2).sum(-1).mean())

    aware = rmse_p(att.y, rrp_loglik(m, sched, attack_prob=0.2, signal=sig, angles=[1]))
    naive = rmse_p(att.y, rrp_loglik(m, sched, angles=[1]))
    full = rmse_p(att_all, all_sensors_loglik(m, attack_prob=0.2, signal=sig, angles=[1]))
    assert naive > 3 * aware
    assert full < aware
