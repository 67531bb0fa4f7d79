"""Linear-domain weights in the fused engine against the NumPy engine's emulation (the reference).

``linear_weights=True`` (:func:`filters.particle.run_sir`) zeroes a particle whose normalised
weight ``W_{k-1} p(z_k | x)`` underflows double precision; a step where every weight does is a
collapse (predicted particles kept, uniform weights, recorded in ``collapsed``, the log marginal
likelihood ``-inf``).  The fused engine (:func:`filters.fused.sir_packets`, the
``rrp-deception`` study's linear-weights row) applies the same rule in its kernel:

* on a shared deterministic case (one run, the same Generator and initial particles) it
  reproduces ``run_sir`` to rounding, collapse steps, resampled steps and ESS included — with
  resampling at every step and below an ESS threshold (where the log weights are carried);
* a measurement far from every particle collapses exactly that step in both engines, and
  without one the cut never bites (the fused linear filter is the log-domain one bit for bit);
* through the study's route (:func:`studies.pfrun.run_packets`) with independent randomness
  in each engine, the per-run position errors and collapse counts agree within Monte Carlo
  error (paired over the same runs' data).
"""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from designer import Gaussian, InputError, Model, Sensor
from designer.noise import spawn_generators
from filters.attacks import deception_attack, round_robin_schedule
from filters.fused import sir_packets
from filters.particle import run_sir
from filters.rrp import deception_terms, rrp_loglik, wrap_angles
from studies.pfrun import run_packets
from studies.scenarios import load_scenario

ETA = 0.2


@pytest.fixture(scope="module")
def rr():
    """target-range-bearing, Round-Robin packets deceived with probability ETA (the study's linear row's data)."""
    sc = load_scenario("target-range-bearing")
    m = sc.model
    R, K = 40, 60
    rng = np.random.default_rng(31)
    tr = sc.simulate(rng, K, batch=R)
    sched = round_robin_schedule(K, m.n_sensors, sc.channel.start)
    y = wrap_angles(tr.per_sensor(m), [1])[:, np.arange(K), sched]  # (R, K, 2)
    att = deception_attack(y, ETA, sc.channel.deception, rng)
    return dict(sc=sc, m=m, R=R, K=K, x=tr.x, sched=sched, y=att.y, attacked=att.eta)


def _both(m, y, sched, seed, M, ess_threshold=1.0, attack=None, threads=1):
    """One run in each engine from the same Generator and initial particles: (NumPy detail, fused detail)."""
    kw = {} if attack is None else dict(attack_prob=ETA, signal=attack)
    ll = rrp_loglik(m, sched, angles=[1], **kw)
    ref = run_sir(m, y[None], np.random.default_rng(seed), particles=M, runs=1, loglik=ll, linear_weights=True,
                  ess_threshold=ess_threshold).detail
    g = np.random.default_rng(seed)
    x0 = m.prior.sample(g, (1, M))  # run_sir's first draws
    extra = {}
    if attack is not None:
        lc, att = deception_terms(y[None], ETA, attack)
        extra = dict(attack=att, log_clean=lc)
    ours = sir_packets(m, x0, [g], sched, y[None], angles=[1], linear_weights=True, ess_threshold=ess_threshold,
                       threads=threads, **extra).detail
    return ref, ours


@pytest.mark.parametrize("M, ess_threshold", [(100, 1.0), (300, 1.0), (200, 0.5)])
def test_one_run_reproduces_run_sir_through_the_collapses(rr, M, ess_threshold):
    """The study's linear row (standard likelihood on deceived packets): the same collapse steps, the same
    resampling, the same estimates to rounding, on several runs' data and seeds."""
    m, sched = rr["m"], rr["sched"]
    collapses = 0
    for r, seed in ((0, 1), (1, 2), (2, 3), (3, 4)):
        ref, ours = _both(m, rr["y"][r], sched, seed, M, ess_threshold)
        assert np.array_equal(ours.collapsed, ref.collapsed), (r, np.flatnonzero(ours.collapsed),
                                                                np.flatnonzero(ref.collapsed))
        assert np.array_equal(ours.resampled, ref.resampled)
        np.testing.assert_allclose(ours.mean, ref.mean, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(ours.ess, ref.ess, rtol=1e-8)
        assert (ours.loglik[0] == -np.inf) == (ref.loglik[0] == -np.inf) == ref.collapsed.any()
        if not ref.collapsed.any():
            np.testing.assert_allclose(ours.loglik, ref.loglik, rtol=1e-10)
        assert np.all(ours.ess[0][ours.collapsed[0]] == M)
        collapses += int(ours.collapsed.sum())
        # a collapse is a deceived packet no particle explains
        assert rr["attacked"][r][ours.collapsed[0]].all()
    assert collapses >= 4  # the case exercises the rule
    if ess_threshold < 1.0:  # carried log weights: some steps not resampled
        assert not ours.resampled.all()


def test_attack_aware_likelihood_absorbs_what_the_linear_cut_would_zero(rr):
    """The attack-aware likelihood (14) with linear weights: its attack term keeps every weight above the cut, in
    both engines alike (no collapse), and the two agree to rounding."""
    m, sched = rr["m"], rr["sched"]
    ref, ours = _both(m, rr["y"][0], sched, 5, 200, attack=rr["sc"].channel.deception)
    assert not ref.collapsed.any() and not ours.collapsed.any()
    np.testing.assert_allclose(ours.mean, ref.mean, rtol=1e-9, atol=1e-9)


def _linear_model():
    x = ca.SX.sym("x", 2)
    A = np.array([[0.9, 0.2], [-0.1, 0.95]])
    return Model("lin", x, ca.mtimes(ca.DM(A), x), [Sensor("s", ca.mtimes(ca.DM([[1.0, 0.5]]), x),
                 Gaussian.zero_mean([[0.3]]))], Gaussian.zero_mean(0.05 * np.eye(2)),
                 Gaussian([1.0, -1.0], 0.5 * np.eye(2)))


def test_an_outlier_collapses_that_step_in_both_engines_and_nothing_else_changes():
    """A 60-sigma outlier at steps 4 and 7: every run collapses there with linear weights, in both engines; the
    log-domain filter absorbs it; without the outlier the fused linear filter is the log-domain one, bit for bit."""
    m = _linear_model()
    R, K, M = 6, 10, 300
    rng = np.random.default_rng(5)
    from designer import simulate
    z = simulate(m, K, rng, batch=R).z  # (R, K, 1)
    bad = np.zeros(K, bool)
    bad[[4, 7]] = True
    zo = z.copy()
    zo[:, bad] += 60 * np.sqrt(0.3)  # log-likelihood about -1800 for every particle: exp() == 0 in double

    def fused(zz, lin, seed=3):
        gens = spawn_generators(seed, R)
        x0 = np.stack([m.prior.sample(g, M) for g in gens])
        return sir_packets(m, x0, gens, np.zeros((K, 1), int), zz[:, :, None, :], linear_weights=lin,
                           threads=2).detail

    lin, log = fused(zo, True), fused(zo, False)
    ref = run_sir(m, zo, np.random.default_rng(2), particles=M, runs=R, linear_weights=True).detail
    want = np.broadcast_to(bad, (R, K))
    assert np.array_equal(lin.collapsed, want) and np.array_equal(ref.collapsed, want)
    assert not log.collapsed.any()
    assert np.all(lin.loglik == -np.inf) and np.isfinite(log.loglik).all()
    # a collapsed step is a pure prediction: both engines' estimates there follow the dynamics from the step before
    A = np.array([[0.9, 0.2], [-0.1, 0.95]])
    for d in (lin, ref):
        pred = np.einsum("ab,rb->ra", A, d.mean[:, 4])
        assert np.abs(d.mean[:, 5] - pred).max() < 0.15
    # without outliers the cut never bites: the same numbers as the log-domain filter
    a, b = fused(z, True), fused(z, False)
    assert np.array_equal(a.mean, b.mean) and np.array_equal(a.loglik, b.loglik) and not a.collapsed.any()


def test_linear_row_agrees_with_the_numpy_engine_over_monte_carlo_runs(rr):
    """The study's route (studies.pfrun.run_packets) for the linear row in each engine, independent randomness,
    the same 40 runs' data: per-run position MSE and collapse counts agree within Monte Carlo error (paired)."""
    m, R, M = rr["m"], rr["R"], 150
    y = rr["y"][:, :, None, :]
    kw = dict(particles=M, signal=rr["sc"].channel.deception, angles=[1], linear_weights=True)
    fast = run_packets(m, y, rr["sched"][:, None], spawn_generators(11, R), engine="fast", threads=2, **kw).detail
    slow = run_packets(m, y, rr["sched"][:, None], spawn_generators(12, R), engine="numpy", **kw).detail
    pos = list(m.position_index)

    def mse(d):  # (R,): each run's mean squared position error over the steps
        return ((d.mean[:, 1:, pos] - rr["x"][:, 1:, pos]) ** 2).sum(-1).mean(-1)

    for a, b, what in ((mse(fast), mse(slow), "position MSE"),
                       (fast.collapsed.sum(1).astype(float), slow.collapsed.sum(1).astype(float), "collapses")):
        d = a - b
        se = d.std(ddof=1) / np.sqrt(R)
        assert abs(d.mean()) < 4 * se + 1e-3 * abs(b.mean()), (what, d.mean(), se, a.mean(), b.mean())
    assert slow.collapsed.sum() > R  # collapses are common on this data: the comparison is not vacuous
    # the collapse steps are those of deceived packets, in both
    assert rr["attacked"][fast.collapsed].all() and rr["attacked"][slow.collapsed].all()


def test_linear_weights_results_do_not_depend_on_threads(rr):
    m, R = rr["m"], 8
    gens = lambda: spawn_generators(21, R)  # noqa: E731
    x0 = np.stack([m.prior.sample(g, 120) for g in gens()])
    one, two = (sir_packets(m, x0, gens(), rr["sched"], rr["y"][:R], angles=[1], linear_weights=True,
                            threads=t).detail for t in (1, 2))
    for f in ("mean", "ess", "loglik", "resampled", "collapsed"):
        assert np.array_equal(getattr(one, f), getattr(two, f)), f
    assert one.collapsed.any()


def test_linear_weights_must_be_a_bool(rr):
    m = rr["m"]
    g = np.random.default_rng(0)
    with pytest.raises(InputError, match="linear_weights"):
        sir_packets(m, m.prior.sample(g, (1, 4)), [g], rr["sched"], rr["y"][:1], linear_weights=1)
