"""The mean-square-error design (mode 'mse'): the joint error covariance against Monte Carlo, its gains against the
local EKF, and its certificate."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from designer import AttackSpec, FDISignal, Gaussian, Model, Sensor, SensorNetwork
from designer.joint import joint_predict, joint_prior, joint_update, mse_gains
from filters.attacks import simulate_attacks
from filters.consensus import run_consensus
from filters.consensus_batch import run_consensus_batch
from filters.ekf import run_ekf
from rules.mse.filter import run_mse_batch
from studies.filter_registry import local_ekf_design
from studies.consensus_design import consensus_design
from studies.scenarios import scenario_of


def linear_ring(n_nodes=4, fdi=0.0, dos=0.0, amplitude=0.5, steps=15):
    """A linear 2-state plant, one scalar sensor per node on a ring (each node alone cannot observe the state)."""
    x = ca.SX.sym("x", 2)
    A = ca.DM([[0.98, 0.1], [-0.1, 0.98]])
    sensors = [Sensor(f"s{i}", np.cos(0.4 * i) * x[0] + np.sin(0.4 * i) * x[1], Gaussian.zero_mean([[0.2]]))
               for i in range(n_nodes)]
    m = Model("lin", x, ca.mtimes(A, x), sensors, Gaussian.zero_mean(0.01 * np.eye(2)),
              Gaussian([0.0, 0.0], 0.5 * np.eye(2)))
    net = SensorNetwork.from_edges(n_nodes, [(i, (i + 1) % n_nodes) for i in range(n_nodes)])
    att = AttackSpec(dos=dos, fdi=fdi, signal=FDISignal(amplitude))
    return scenario_of(m, network=net, attacks=att, steps=steps)


def _draw(sc, seed, key=()):
    """Run ``key`` of ``seed`` of the generative model: its trajectory and its channel attacks."""
    ts, at = np.random.SeedSequence(seed, spawn_key=key).spawn(2)
    traj = sc.simulate(np.random.default_rng(ts))
    return traj, simulate_attacks(sc.network, sc.steps, sc.model.n_x, np.random.default_rng(at),
                                  sc.resolved_attacks.signal)


def _one_run(sc, design, seed, key=()):
    """One run of the generative model and of the consensus filter on it (run ``key`` of ``seed``)."""
    traj, att = _draw(sc, seed, key)
    return traj, run_consensus(sc.model, sc.network, traj.z, design, attacks=att)


def _runs(sc, design, runs, seed):
    """Runs 0..runs-1 of ``seed``: the truths (runs, steps+1, n_x) and the filter on all of them at once (mode mse:
    rules.mse.filter, tested against the per-run reference in tests/test_mse_batch.py; else run_consensus_batch)."""
    draws = [_draw(sc, seed, (r,)) for r in range(runs)]
    z, attacks = np.stack([t.z for t, _ in draws]), [a for _, a in draws]
    if design.mode == "mse":
        res = run_mse_batch(sc.model, sc.network, z, design, attacks=attacks).detail
    else:
        res = run_consensus_batch(sc.model, sc.network, z, design, attacks=attacks).detail
    return np.stack([t.x for t, _ in draws]), res


def _mc(sc, design, runs, seed):
    """Errors of every node over runs (runs, steps+1, nodes, n_x) and the run's predicted MSE (first run)."""
    truth, res = _runs(sc, design, runs, seed)
    return truth[:, :, None, :] - res.x_post, res.predicted_mse[0]


@pytest.mark.parametrize("dos, fdi", [(0.0, 0.0), (0.0, 0.3)])
def test_predicted_mse_is_the_monte_carlo_mse_of_a_linear_network(dos, fdi):
    """Linear plant, no linearisation error: tr P_ii of the joint recursion is each node's mean-square error.

    Without DoS the received sets are the same in every run, so the predicted MSE is one deterministic sequence
    (FDI enters through its second moment), and the Monte Carlo of the generative model must agree with it.
    """
    sc = linear_ring(fdi=fdi, dos=dos, steps=10)
    des = consensus_design(sc, mode="mse", u_scale=0, v_scale=0)
    err, pred = _mc(sc, des, runs=500, seed=3)
    e2 = (err ** 2).sum(-1)  # (runs, steps+1, nodes)
    emp = e2.mean(axis=0)
    se = e2.std(axis=0, ddof=1) / np.sqrt(err.shape[0])
    z = (emp[1:] - pred[1:]) / se[1:]
    assert np.abs(z).max() < 4.5, np.abs(z).max()  # 40 (step, node) cells: 4.5 sigma
    assert np.abs(z.mean()) < 1.0


def test_isolated_nodes_get_the_ekf_and_networked_nodes_are_never_worse_in_prediction():
    sc = linear_ring()
    m, n = sc.model, sc.network.n_nodes
    traj = sc.simulate(np.random.default_rng(0))
    iso = SensorNetwork(n, np.zeros((n, n), int), require_connected=False)
    des = consensus_design(sc, mode="mse", u_scale=0, v_scale=0)
    alone = run_consensus(m, iso, traj.z, des)
    for i in range(n):
        avail = np.zeros((sc.steps, n), bool)
        avail[:, i] = True
        ekf = run_ekf(m, np.where(avail, traj.z, 0.0), available=avail)
        np.testing.assert_allclose(alone.x_post[:, i], ekf.x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(alone.predicted_mse[:, i], np.trace(ekf.P, axis1=1, axis2=2), rtol=1e-9)
    net = run_consensus(m, sc.network, traj.z, des)
    assert np.all(net.predicted_mse <= alone.predicted_mse * (1 + 1e-9))
    assert np.all(net.predicted_mse[-1] < 0.8 * alone.predicted_mse[-1])  # the neighbours' information helps


def test_gains_are_the_linear_mmse_of_the_innovations():
    """Perturbing the mse gains in any direction never lowers node i's predicted error (first-order optimality)."""
    rng = np.random.default_rng(1)
    n, N = 2, 3
    L = rng.normal(size=(N * n, N * n))
    big = L @ L.T + np.eye(N * n)
    Pm = big.reshape(N, n, N, n).swapaxes(1, 2)
    H = [rng.normal(size=(1, n)) for _ in range(N)]
    R = [np.array([[0.3]])] * N
    received = [[1, 2], [0], [0, 1]]
    S = [0.2 * len(r) * np.eye(n) for r in received]
    gains = [mse_gains(Pm, i, received[i], H[i], R[i], S[i]) for i in range(N)]
    base = joint_update(Pm, [g[0] for g in gains], [g[1] for g in gains], H, R, received, S)
    for trial in range(20):
        i = trial % N
        dK, dC = 1e-3 * rng.normal(size=(n, 1)), 1e-3 * rng.normal(size=(n, n))
        Ks = [g[0] + (dK if j == i else 0) for j, g in enumerate(gains)]
        Cs = [g[1] + (dC if j == i else 0) for j, g in enumerate(gains)]
        other = joint_update(Pm, Ks, Cs, H, R, received, S)
        assert np.trace(other[i, i]) >= np.trace(base[i, i]) - 1e-12


def test_joint_prediction_and_update_against_a_stacked_linear_system():
    """The block formulas equal the covariance of the stacked error vector computed as one linear system."""
    rng = np.random.default_rng(4)
    n, N = 2, 3
    L = rng.normal(size=(N * n, N * n))
    P = (L @ L.T).reshape(N, n, N, n).swapaxes(1, 2)
    F = [rng.normal(size=(n, n)) for _ in range(N)]
    Q = 0.1 * np.eye(n)
    Pm = joint_predict(P, F, Q)
    Fbig = np.zeros((N * n, N * n))
    for i in range(N):
        Fbig[i * n:(i + 1) * n, i * n:(i + 1) * n] = F[i]
    G = np.tile(np.eye(n), (N, 1))  # one process noise for every node
    ref = Fbig @ P.swapaxes(1, 2).reshape(N * n, N * n) @ Fbig.T + G @ Q @ G.T
    np.testing.assert_allclose(Pm.swapaxes(1, 2).reshape(N * n, N * n), ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(joint_prior(np.eye(n), N)[0, 2], np.eye(n))


def test_the_mse_design_certifies_its_own_error_on_a_linear_network():
    """Theorem 1 holds for any gains: along a run, Φ_i bounds the predicted covariance P_ii of the same gains."""
    sc = linear_ring(fdi=0.2, dos=0.1)
    des = consensus_design(sc, mode="mse", u_scale=0, v_scale=0)
    m = sc.model
    traj, res = _one_run(sc, des, 7)
    assert res.feasible and res.valid.all()
    assert np.all(np.trace(res.phi_post, axis1=-2, axis2=-1) >= res.predicted_mse * (1 - 1e-9))
    local = run_consensus(m, SensorNetwork(4, np.zeros((4, 4), int), require_connected=False), traj.z,
                          local_ekf_design(des))
    assert np.isfinite(local.x_post).all()


def test_joint_certificate_of_a_linear_network_with_a_zero_mean_signal_is_its_predicted_covariance():
    """U = V = 0 and a zero-mean FDI signal: the certificate of the stacked error adds nothing to the joint
    covariance of the gains (σ = β = 0, no cross terms): every node's bound is its predicted covariance."""
    sc = linear_ring(fdi=0.2, dos=0.1)
    des = consensus_design(sc, mode="mse", u_scale=0, v_scale=0)
    traj, res = _one_run(sc, des, 11)
    assert res.feasible and res.valid.all()
    np.testing.assert_allclose(np.trace(res.phi_post, axis1=-2, axis2=-1), res.predicted_mse, rtol=1e-9)


@pytest.mark.parametrize("mode, law, runs", [("mse", "constant", 200), ("mse", "sine", 200), ("tuned", "constant", 40)])
def test_certificates_bound_the_monte_carlo_error_of_a_nonlinear_network(mode, law, runs):
    """A range-measuring ring (nonlinear h, 'prior' remainder scales) under DoS and FDI, a biased (constant) or a
    zero-mean (sine) signal: at every (step, node) the Monte Carlo mean-square error of the generative model stays
    below the run-averaged bound (4 standard errors): the joint certificate of the mse design and the per-node
    bound with optimised weights of the tuned design."""
    x = ca.SX.sym("x", 2)
    A = ca.DM([[0.98, 0.1], [-0.1, 0.98]])
    anchors = [(3.0, 0.0), (0.0, 3.0), (-3.0, 0.0), (0.0, -3.0)]
    sensors = [Sensor(f"r{i}", ca.sqrt((x[0] - a) ** 2 + (x[1] - b) ** 2), Gaussian.zero_mean([[0.05]]))
               for i, (a, b) in enumerate(anchors)]
    m = Model("ranges", x, ca.mtimes(A, x), sensors, Gaussian.zero_mean(0.01 * np.eye(2)),
              Gaussian([0.0, 0.0], 0.2 * np.eye(2)))
    net = SensorNetwork.from_edges(4, [(i, (i + 1) % 4) for i in range(4)])
    sc = scenario_of(m, network=net, attacks=AttackSpec(dos=0.1, fdi=0.2, signal=FDISignal(0.3, law=law)), steps=10)
    des = consensus_design(sc, mode=mode)
    truth, res = _runs(sc, des, runs, 5)
    assert res.valid.all()
    e2 = ((truth[:, :, None, :] - res.x_post) ** 2).sum(-1)
    bound = np.trace(res.phi_post, axis1=-2, axis2=-1).mean(axis=0)
    se = e2.std(axis=0, ddof=1) / np.sqrt(runs)
    assert np.all(e2.mean(axis=0)[1:] <= bound[1:] + 4 * se[1:])
    assert np.mean(e2.mean(axis=0)[1:] / bound[1:]) > 0.05  # a certificate, not a vacuous one


def test_gate_rejects_a_clean_packet_with_its_stated_probability():
    """Clean differences drawn from the covariance the gate is given are dropped at rate α (binomial tolerance);
    a large injected signal is dropped; the counts add up."""
    from filters.channels import GATE_COUNTS, gate_channels

    rng = np.random.default_rng(0)
    receiver, sender = np.array([0, 1]), np.array([1, 0])  # the two channels 1 -> 0 and 0 -> 1
    S = np.array([[0.04, 0.01], [0.01, 0.02]])
    cov = np.broadcast_to(S, (2, 2, 2)).copy()
    L = np.linalg.cholesky(S)
    alpha, trials = 0.05, 4000
    x = np.zeros((trials, 2, 2))
    x[:, 1] = (L @ rng.normal(size=(trials, 2, 1)))[..., 0]  # x̂_1 - x̂_0 ~ N(0, S), every trial a run
    keep, counts = gate_channels(x, receiver, sender, np.ones((trials, 2), bool), None, None,
                                 np.broadcast_to(cov, (trials, 2, 2, 2)), alpha)
    rate = 1.0 - keep[:, 0].mean()
    assert abs(rate - alpha) < 4 * np.sqrt(alpha * (1 - alpha) / trials)
    assert (counts[:, 1] == (~keep).sum(axis=1)).all()
    fdi = np.array([True, False])
    xi = np.array([[1.0, -1.0], [0.0, 0.0]])  # on channel 1 -> 0: 5 standard deviations and more
    keep, counts = gate_channels(np.zeros((2, 2)), receiver, sender, np.ones(2, bool), fdi, xi, cov, 0.01)
    c = dict(zip(GATE_COUNTS, counts))
    assert not keep[0] and keep[1]
    assert c == {"received": 2, "rejected": 1, "clean_rejected": 0, "fdi_received": 1, "fdi_passed": 0}
    keep, counts = gate_channels(np.zeros((2, 2)), receiver, sender, np.ones(2, bool), fdi, xi, cov, 0.0)  # no gate
    assert keep.all() and dict(zip(GATE_COUNTS, counts))["fdi_passed"] == 1


def test_gated_mse_design_drops_the_falsified_packets_and_is_more_accurate():
    """A strong FDI attacker on a linear ring: the gate keeps few falsified packets and few clean ones are lost,
    and the Monte Carlo error falls (the same runs with and without the gate)."""
    sc = linear_ring(fdi=0.3, amplitude=3.0, steps=12)
    plain = consensus_design(sc, mode="mse", u_scale=0, v_scale=0)
    gated = consensus_design(sc, mode="mse", u_scale=0, v_scale=0, gate=0.01)
    e_plain, _ = _mc(sc, plain, runs=60, seed=2)
    e_gated, _ = _mc(sc, gated, runs=60, seed=2)
    counts = _runs(sc, gated, 20, 2)[1].gate_counts.sum(axis=(0, 1))
    received, rejected, clean_rejected, fdi_received, fdi_passed = counts
    print(counts, np.mean(e_gated[:, 1:] ** 2), np.mean(e_plain[:, 1:] ** 2))
    assert fdi_passed < 0.2 * fdi_received
    assert clean_rejected < 0.05 * (received - fdi_received)
    assert np.mean(e_gated[:, 1:] ** 2) < np.mean(e_plain[:, 1:] ** 2)


def test_gate_option_range():
    from designer.design import DesignOptions
    from designer.validation import InputError

    with pytest.raises(InputError, match="gate must be a probability"):
        DesignOptions(gate=1.0)
    with pytest.raises(InputError, match="gate must be >= 0"):
        DesignOptions(gate=-0.1)
