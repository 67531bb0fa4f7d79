"""run_sir's blocks: many separately seeded particle filters in one batch give each its own call's numbers.

The reference is run_sir called on each block alone with that block's generator (itself tested against
the Kalman filter in tests/test_particle.py): the batch must reproduce it bit for bit — the initial
sample, the proposals (the transition with per-run known inputs, switching modes, a custom proposal
with a correction), the resampling of each block from its own stream (also when only some runs
resample), the log-likelihood estimate and the flags.
"""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from designer import Gaussian, InputError, Model, Sensor
from filters.particle import run_sir
from filters.uplink import uplink_loglik
from studies.scenarios import load_scenario

FIELDS = ("mean", "cov", "ess", "loglik", "resampled", "collapsed", "skipped")


def assert_blocks_are_separate_calls(batch, alone):
    """The batch's rows, block by block, equal the separate calls' rows bit for bit."""
    start = 0
    for res in alone:
        rows = slice(start, start + res.mean.shape[0])
        for f in FIELDS:
            np.testing.assert_array_equal(getattr(batch, f)[rows], getattr(res, f), err_msg=f)
        start = rows.stop
    assert start == batch.mean.shape[0]


def switching_model() -> Model:
    """Two modes (a switching gain), a scalar sensor: the proposal draws the mode of every particle."""
    x, md = ca.SX.sym("x", 2), ca.SX.sym("m")
    f = ca.vertcat(x[0] + 0.1 * x[1], (0.9 - 0.3 * md) * x[1])
    return Model("switching", x, f, [Sensor("s", x[0] + 0.2 * x[1] ** 2, Gaussian.zero_mean([[0.1]]))],
                 Gaussian.zero_mean(0.01 * np.eye(2)), Gaussian([0.5, 0.0], 0.2 * np.eye(2)), mode=md,
                 mode_probs=[0.7, 0.3])


@pytest.mark.parametrize("threshold", [1.0, 0.6])
def test_robot_runs_with_their_own_inputs_and_streams(threshold):
    """The indoor robot: three runs with their own inputs and measurements, blocks of 1, 2 and 1 rows (the middle
    block two likelihoods on one run's data), resampling at every step or when the ESS falls."""
    sc = load_scenario("indoor-robot", {"steps": 8})
    m = sc.model
    trs = [sc.simulate(np.random.default_rng(s), 8) for s in (1, 2, 3)]
    z = np.stack([trs[0].z, trs[1].z, trs[1].z, trs[2].z])
    u = np.stack([trs[0].inputs, trs[1].inputs, trs[1].inputs, trs[2].inputs])
    blocks = [1, 2, 1]
    seeds = np.random.SeedSequence(5).spawn(3)
    kw = dict(particles=60, ess_threshold=threshold)
    batch = run_sir(m, z, [np.random.default_rng(s) for s in seeds], blocks=blocks, inputs=u, **kw).detail
    alone, start = [], 0
    for seq, b in zip(seeds, blocks):
        rows = slice(start, start + b)
        alone.append(run_sir(m, z[rows], np.random.default_rng(seq), inputs=u[rows.start], **kw).detail)
        start += b
    assert_blocks_are_separate_calls(batch, alone)
    if threshold < 1:
        assert batch.resampled.any() and not batch.resampled.all(), "some runs must resample and some not"


def test_uplink_likelihood_per_row_and_default_blocks():
    """The comparison's use: per-row falsification probabilities (0 = trust every packet), one run per generator
    by default; and a switching model whose proposal draws modes."""
    sc = load_scenario("target-range-bearing", {"steps": 10})
    m = sc.model
    tr = sc.simulate(np.random.default_rng(4), 10)
    y = np.concatenate([tr.z, np.ones((10, m.n_sensors))], axis=1)  # every packet received
    q = np.array([0.0, 0.2, 0.4])
    covs = [np.eye(2)] * m.n_sensors
    gens = lambda: [np.random.default_rng(s) for s in (7, 8, 9)]  # noqa: E731
    batch = run_sir(m, np.stack([y] * 3), gens(), particles=50,
                    loglik=uplink_loglik(m, fdi_prob=q, fdi_covs=covs)).detail
    alone = [run_sir(m, y[None], g, particles=50, loglik=uplink_loglik(m, fdi_prob=qi, fdi_covs=covs)).detail
             for g, qi in zip(gens(), q)]
    assert_blocks_are_separate_calls(batch, alone)
    sw = switching_model()
    zs = np.random.default_rng(0).normal(size=(2, 12, 1))
    batch = run_sir(sw, zs, [np.random.default_rng(1), np.random.default_rng(2)], particles=40).detail
    alone = [run_sir(sw, zs[r:r + 1], np.random.default_rng(1 + r), particles=40).detail for r in range(2)]
    assert_blocks_are_separate_calls(batch, alone)


def test_a_custom_proposal_is_called_per_block():
    """A proposal with a log correction (a shifted Gaussian random walk): each block's call sees its own runs and
    generator."""
    x = ca.SX.sym("x", 1)
    m = Model("walk", x, x, [Sensor("s", x, Gaussian.zero_mean([[0.5]]))], Gaussian.zero_mean([[0.2]]),
              Gaussian([0.0], [[1.0]]))
    seen = []

    def proposal(x_prev, k, z_k, rng):
        seen.append(x_prev.shape[0])
        shift = 0.3 * (z_k[:, None, :] - x_prev)
        new = x_prev + shift + np.sqrt(0.2) * rng.standard_normal(x_prev.shape)
        trans = Gaussian.zero_mean([[0.2]])
        return new, trans.logpdf(new - x_prev) - trans.logpdf(new - x_prev - shift)

    z = np.random.default_rng(3).normal(size=(3, 6, 1))
    batch = run_sir(m, z, [np.random.default_rng(4), np.random.default_rng(5)], blocks=[2, 1], particles=30,
                    proposal=proposal).detail
    assert seen == [2, 1] * 6
    alone = [run_sir(m, z[:2], np.random.default_rng(4), particles=30, proposal=proposal).detail,
             run_sir(m, z[2:], np.random.default_rng(5), particles=30, proposal=proposal).detail]
    assert_blocks_are_separate_calls(batch, alone)


def test_blocks_are_checked():
    sc = load_scenario("indoor-robot", {"steps": 3})
    z = np.zeros((3, 3, sc.model.n_z))
    u = np.zeros((3, sc.model.n_u))
    gens = [np.random.default_rng(i) for i in range(2)]
    with pytest.raises(InputError, match="blocks must give one size per generator"):
        run_sir(sc.model, z, gens, particles=5, inputs=u)
    with pytest.raises(InputError, match="blocks must give one size per generator"):
        run_sir(sc.model, z, gens, blocks=[1, 1], particles=5, inputs=u)
    with pytest.raises(InputError, match="blocks go with a sequence of generators"):
        run_sir(sc.model, z, gens[0], blocks=[3], particles=5, inputs=u)
    with pytest.raises(InputError, match="rng must be a numpy.random.Generator"):
        run_sir(sc.model, z, [gens[0], 7], blocks=[2, 1], particles=5, inputs=u)
    with pytest.raises(InputError, match="inputs must have shape"):
        run_sir(sc.model, z, gens, blocks=[2, 1], particles=5, inputs=np.zeros((2, 3, sc.model.n_u)))
