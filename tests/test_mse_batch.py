"""Mode 'mse' batched over Monte Carlo runs (rules.mse.filter) against the per-run path, and the stacked
functions of designer.joint against the same functions item by item.

The reference is the per-run, per-node loop of tests/consensus_reference.py in mode 'mse' (what
run_consensus was before it became a batch of one; the production filter is tested against the joint
covariance of a linear network and Monte Carlo in tests/test_mse_design.py): run by run the batch
must give its numbers (rtol 1e-9), its flags, violations and gate counts, on the indoor robot under
DoS and FDI with and without the χ² gate, the mixed-sensor example (sensor dimensions 2 and 1, a
bearing across ±π) with a gate, a hessian rule with per-run inputs and priors, a diverging run, and
in sub-batches.  The multipliers' root search is checked against scipy's bounded minimisation of the
trace written with explicit inverses.
"""
from __future__ import annotations

from types import SimpleNamespace

import casadi as ca
import numpy as np
import pytest
from scipy.linalg import block_diag
from scipy.optimize import minimize_scalar

import rules.mse.filter as mse_batch
import rules
from designer import Gaussian, Model, Sensor, SensorNetwork, simulate
from designer.attacks import FDISignal
from designer.design import ConsensusDesign, DesignOptions, make_design
from designer.joint import (
    certificate_predict,
    certificate_update,
    joint_multiplier,
    joint_predict,
    joint_prior,
    joint_update,
    mse_gains,
)
from designer.validation import InputError
from filters.attacks import simulate_attacks
from filters.consensus_batch import EdgeAttacks
from rules.mse.filter import run_mse_batch
from studies.consensus_design import consensus_design

from test_consensus_batch import SITES, assert_same_as_per_run, chain_model, mixed_model, per_run  # tests/ on the path
from test_consensus_batch import robot as robot_25_steps  # noqa: F401  (a fixture)


def assert_mse_batch_is_per_run(batch, refs):
    """The fields of tests/test_consensus_batch.py, and the predicted MSE (rtol 1e-9), the gains' condition numbers
    (rtol 1e-6: an eigenvalue ratio) and the gate's counts."""
    assert_same_as_per_run(batch, refs)
    for r, ref in enumerate(refs):
        np.testing.assert_allclose(batch.predicted_mse[r], ref.predicted_mse, rtol=1e-9, equal_nan=True)
        np.testing.assert_allclose(batch.gain_condition[r], ref.gain_condition, rtol=1e-6, equal_nan=True)
        np.testing.assert_array_equal(batch.gate_counts[r], ref.gate_counts)


# ----------------------------------------------------------------------------- the stacked functions
def _random_joint(rng, runs, N, n, indefinite_run=None):
    L = rng.normal(size=(runs, N * n, N * n))
    A = L @ np.swapaxes(L, -1, -2) / (N * n) + 0.1 * np.eye(N * n)
    if indefinite_run is not None:
        A[indefinite_run] -= 3.0 * np.eye(N * n) * np.abs(A[indefinite_run]).max()
    A = 0.5 * (A + np.swapaxes(A, -1, -2))
    return A.reshape(runs, N, n, N, n).swapaxes(2, 3).copy()


def test_stacked_mse_functions_equal_item_by_item():
    """A stack of runs (masks for the kept packets, per-node arrays with a runs axis, sensors of dimensions 1 and 2)
    gives every run's numbers of the per-run calls (index lists, one matrix per node): prior, prediction, gains
    (with a node that kept nothing and a run whose E[y yᵀ] is indefinite: the least-squares fallback), update and
    both certificates (structure D on one node, a biased FDI signal)."""
    rng = np.random.default_rng(12)
    runs, N, n, dims = 4, 3, 2, (1, 2, 1)
    P = _random_joint(rng, runs, N, n, indefinite_run=2)
    F = rng.normal(size=(runs, N, n, n))
    U = 0.1 * rng.normal(size=(runs, N, n, n))
    Q = 0.05 * np.eye(n)
    H = [rng.normal(size=(runs, m, n)) for m in dims]
    R = [np.diag(rng.uniform(0.1, 1.0, m)) for m in dims]
    V = [0.2 * rng.normal(size=(runs, m, m)) for m in dims]
    kept = rng.random((runs, N, N)) < 0.6
    kept[:, np.arange(N), np.arange(N)] = False
    kept[0, 1] = False  # node 1 of run 0 kept nothing: C = 0, K the EKF gain
    q = np.where(kept, rng.uniform(0.0, 0.4, (runs, N, N)), 0.0)
    M = np.outer([0.3, -0.2], [0.3, -0.2])
    S = q.sum(-1)[..., None, None] * M
    mean = np.array([0.1, 0.05])
    D = [None, np.array([[1.0, 0.0]]), None]

    np.testing.assert_array_equal(joint_prior(P[:, 0, 0], N)[1], joint_prior(P[1, 0, 0], N))
    Pm = joint_predict(P, F, Q)
    gains = [mse_gains(Pm, i, kept[:, i], H[i], R[i], S[:, i]) for i in range(N)]
    K, C = [g[0] for g in gains], np.stack([g[1] for g in gains], axis=1)
    assert np.all(C[0, 1] == 0.0)
    Pu = joint_update(Pm, K, C, H, R, kept, S)
    cp = certificate_predict(P[[0, 1, 3]], F[[0, 1, 3]], U[[0, 1, 3]], Q, 0.3, D)
    cu = certificate_update(Pm[[0, 1, 3]], [k[[0, 1, 3]] for k in K], C[[0, 1, 3]], [h[[0, 1, 3]] for h in H], R,
                            [v[[0, 1, 3]] for v in V], kept[[0, 1, 3]], S[[0, 1, 3]], mean, q[[0, 1, 3]], D)
    for j, r in enumerate([0, 1, 2, 3]):
        rec = [np.flatnonzero(kept[r, i]) for i in range(N)]
        Pm_r = joint_predict(P[r], list(F[r]), Q)
        np.testing.assert_allclose(Pm[r], Pm_r, rtol=1e-12, atol=1e-14)
        g_r = [mse_gains(Pm_r, i, rec[i], H[i][r], R[i], S[r, i]) for i in range(N)]
        for i in range(N):
            np.testing.assert_allclose(K[i][r], g_r[i][0], rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(C[r, i], g_r[i][1], rtol=1e-10, atol=1e-12)
        Pu_r = joint_update(Pm_r, [g[0] for g in g_r], [g[1] for g in g_r], [h[r] for h in H], R, rec, list(S[r]))
        np.testing.assert_allclose(Pu[r], Pu_r, rtol=1e-10, atol=1e-12)
        if r == 2:
            continue  # the indefinite run has no certificate
        j = [0, 1, 3].index(r)
        ref = certificate_predict(P[r], list(F[r]), list(U[r]), Q, 0.3, D)
        np.testing.assert_allclose(cp.phi[j], ref.phi, rtol=1e-10)
        assert isinstance(ref.multiplier, float) and cp.multiplier[j] == pytest.approx(ref.multiplier, rel=1e-12)
        assert cp.margin[j] == pytest.approx(ref.margin, rel=1e-12)
        ref = certificate_update(Pm_r, [g[0] for g in g_r], [g[1] for g in g_r], [h[r] for h in H], R,
                                 [v[r] for v in V], rec, list(S[r]), mean, [q[r, i, rec[i]] for i in range(N)], D)
        np.testing.assert_allclose(cu.phi[j], ref.phi, rtol=1e-10)
        assert cu.multiplier[j] == pytest.approx(ref.multiplier, rel=1e-12) and ref.multiplier > 0
        assert cu.margin[j] == pytest.approx(ref.margin, rel=1e-12)


def _own_trace(P, T, KV, DtD):
    """``tr T (P⁻¹ - β DᵀD)⁻¹ Tᵀ + ||K V||² / β`` with explicit inverses (an independent form of the trace)."""
    Pinv = np.linalg.inv(P)
    return lambda b: float(np.trace(T @ np.linalg.inv(Pinv - b * DtD) @ T.T) + np.sum(KV**2) / b)


@pytest.mark.parametrize("seed, v_scale", [(0, 0.3), (1, 0.05), (2, 3.0), (3, 30.0)])
def test_beta_search_is_the_bounded_minimiser_of_the_trace(seed, v_scale):
    """certificate_update's β against scipy's bounded minimisation of the own term's trace (explicit inverses, a
    structure D on one node): never a larger trace, β within the flat minimum's resolution; a large V makes (29)
    bind (β at its bound), V = 0 gives β = 0."""
    rng = np.random.default_rng(seed)
    N, n, m = 3, 2, 1
    Pm = _random_joint(rng, 1, N, n)[0]
    K = [rng.normal(size=(n, m)) for _ in range(N)]
    C = [0.3 * rng.normal(size=(n, n)) for _ in range(N)]
    H = [rng.normal(size=(m, n)) for _ in range(N)]
    R = [np.eye(m)] * N
    V = [v_scale * np.eye(m)] * N
    rec = [[1], [0, 2], [1]]
    D = [None, np.array([[0.0, 1.0]]), None]
    cu = certificate_update(Pm, K, C, H, R, V, rec, [np.zeros((n, n))] * N, None, [np.zeros(len(r)) for r in rec],
                            D)
    T = np.zeros((N * n, N * n))
    for i in range(N):
        T[i * n:(i + 1) * n, i * n:(i + 1) * n] = np.eye(n) - K[i] @ H[i] - len(rec[i]) * C[i]
        for j in rec[i]:
            T[i * n:(i + 1) * n, j * n:(j + 1) * n] = C[i]
    Dd = block_diag(np.eye(n), D[1], np.eye(n))
    P = Pm.swapaxes(1, 2).reshape(N * n, N * n)
    bmax = 0.95 / np.linalg.eigvalsh(Dd @ P @ Dd.T)[-1]
    trace = _own_trace(P, T, block_diag(*[k @ v for k, v in zip(K, V)]), Dd.T @ Dd)
    ref = minimize_scalar(trace, bounds=(bmax * 1e-12, bmax), method="bounded",
                          options={"xatol": bmax * 1e-12, "maxiter": 2000}).x
    beta = cu.multiplier
    assert 0 < beta <= bmax * (1 + 1e-12)
    assert trace(beta) <= trace(ref) * (1 + 1e-12)
    assert beta == pytest.approx(ref, rel=1e-5)
    if v_scale == 30.0:
        assert beta == pytest.approx(bmax, rel=1e-12)  # the slope is still negative at (29)'s margin
    zero = certificate_update(Pm, K, C, H, R, [np.zeros((m, m))] * N, rec, [np.zeros((n, n))] * N, None,
                              [np.zeros(len(r)) for r in rec], D)
    assert zero.multiplier == 0.0


def test_joint_multiplier_on_many_items_at_once():
    """The stacked search of random convex traces equals scipy's bounded minimiser per item."""
    rng = np.random.default_rng(7)
    items, r = 40, 6
    mu = np.sort(rng.uniform(0.0, 2.0, (items, r)), axis=-1)
    h = rng.uniform(0.0, 3.0, (items, r))
    a = rng.uniform(0.0, 2.0, items) * 10.0 ** rng.uniform(-6, 1, items)
    a[3] = 0.0
    c = 1.3
    xmax = 0.95 / (c * mu[:, -1])
    x = joint_multiplier(h, mu, a, c, xmax)
    assert x[3] == 0.0
    for j in np.flatnonzero(a > 0):
        def trace(s, j=j):
            return float(np.sum(h[j] * c * s / (1.0 - c * s * mu[j])) + a[j] / s)

        ref = minimize_scalar(trace, bounds=(xmax[j] * 1e-12, xmax[j]), method="bounded",
                              options={"xatol": xmax[j] * 1e-13, "maxiter": 2000}).x
        assert trace(x[j]) <= trace(ref) * (1 + 1e-12), j
        assert x[j] == pytest.approx(ref, rel=1e-4), j


# ----------------------------------------------------------------------------- the filter, run by run
STEPS = 5


@pytest.fixture(scope="module")
def robot(robot_25_steps):
    """tests/test_consensus_batch.py's robot (three runs, DoS 0.3 and FDI 0.2 on every channel), first steps."""
    sc, net, traj, atts = robot_25_steps
    return sc, net, SimpleNamespace(z=traj.z[:, :STEPS], inputs=traj.inputs[:STEPS]), atts


@pytest.mark.parametrize("gate", [0.0, 0.05])
def test_robot_under_dos_and_fdi_matches_per_run(robot, gate):
    sc, net, traj, atts = robot
    des = consensus_design(sc, mode="mse", gate=gate)
    batch = run_mse_batch(sc.model, net, traj.z, des, inputs=traj.inputs, attacks=atts).detail
    assert_mse_batch_is_per_run(batch, per_run(sc.model, net, traj.z, des, traj.inputs, atts))
    counts = batch.gate_counts
    assert counts[..., 3].sum() > 0, "falsified packets must arrive"
    assert (counts[..., 1].sum() > 0) == (gate > 0), "the gate (and only the gate) rejects packets"
    assert np.isfinite(batch.sigma).all() and (batch.beta > 0).all() and batch.valid.all()


def test_robot_hessian_rule_per_run_inputs_priors_and_edge_attacks(robot):
    sc, net, traj, atts = robot
    rng = np.random.default_rng(9)
    runs = traj.z.shape[0]
    inputs = traj.inputs[None] * (1.0 + 0.2 * rng.standard_normal((runs, 1, 1)))
    x0 = sc.model.prior.mean + 0.05 * rng.standard_normal((runs, 3))
    phi0 = sc.model.prior.cov[None] * rng.uniform(0.5, 1.5, (runs, 1, 1))
    des = consensus_design(sc, mode="mse", linearization="hessian")
    batch = run_mse_batch(sc.model, net, traj.z, des, inputs=inputs, attacks=EdgeAttacks.from_patterns(net, atts),
                          x0=x0, phi0=phi0).detail
    assert_mse_batch_is_per_run(batch, per_run(sc.model, net, traj.z, des, inputs, atts, x0, phi0))


def test_mixed_sensor_dimensions_bearings_and_a_gate_match_per_run():
    """Sensors of dimensions 2 and 1 (gains zero-padded), a bearing that crosses ±π (wrapped residuals), a gate on
    the packets."""
    model, net = mixed_model()
    runs, steps = 3, 20
    traj = simulate(model, steps, np.random.default_rng(5), batch=runs)
    bearing3 = np.arctan2(traj.x[:, 1:, 2] - SITES[3][1], traj.x[:, 1:, 0] - SITES[3][0])
    assert np.any(np.abs(np.diff(bearing3, axis=1)) > np.pi, axis=1).all(), "sensor 3's bearing must cross ±π"
    signal = FDISignal(2.0, (0, 2))
    atts = [simulate_attacks(net, steps, 4, np.random.default_rng(60 + r), signal=signal) for r in range(runs)]
    des = make_design(model, net, rule=rules.get("mse"), delta=2.0 * np.sqrt(2.0), options=DesignOptions(mode="mse", gate=0.1),
                      x0=model.prior.mean, signal=signal)
    batch = run_mse_batch(model, net, traj.z, des, attacks=atts).detail
    assert_mse_batch_is_per_run(batch, per_run(model, net, traj.z, des, None, atts))
    assert batch.K.shape == (runs, steps, 5, 4, 2) and np.all(batch.K[:, :, 1:, :, 1] == 0.0)
    assert batch.gate_counts[..., 1].sum() > 0 and not any(batch.diverged)
    assert np.max(np.abs(batch.x_post[:, -1, :, 0] - traj.x[:, -1, None, 0])) < 10.0  # follows across the jump


def test_a_diverging_run_stops_alone_and_sub_batches_change_nothing(monkeypatch):
    """A linear chain (a nearly blind node) in mode mse; run 2 takes a huge measurement at step 10 and leaves
    finite numbers: it stops there, the others go on; the same runs in sub-batches of two give the same result."""
    model, net, des = chain_model()
    des = des._replace(rule=rules.get("mse"))
    runs, steps = 5, 12
    z = simulate(model, steps, np.random.default_rng(41), batch=runs).z
    z[2, 9, 2:4] = 1e14
    atts = [simulate_attacks(net, steps, 2, np.random.default_rng(42 + r), signal=FDISignal(0.1, (0,)))
            for r in range(runs)]
    batch = run_mse_batch(model, net, z, des, attacks=atts).detail
    assert_mse_batch_is_per_run(batch, per_run(model, net, z, des, None, atts))
    assert [d is not None for d in batch.diverged] == [False, False, True, False, False]
    assert batch.diverged[2]["step"] == 10 and np.isnan(batch.predicted_mse[2, 10:]).all()
    monkeypatch.setattr(mse_batch, "MEMORY_BUDGET", 2 * mse_batch.JOINT_COPIES * 8 * (3 * 2) ** 2)
    again = run_mse_batch(model, net, z, des, attacks=atts).detail
    for name in ("x_post", "phi_post", "K", "C", "predicted_mse", "sigma", "beta", "gate_counts"):
        np.testing.assert_array_equal(getattr(again, name), getattr(batch, name), err_msg=name)
    assert again.violations == batch.violations


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning", "ignore:invalid value:RuntimeWarning")
def test_bound_trace_limit_ends_the_certificate_then_overflow():
    """Blind sensors on an unstable plant (U = V = 0): the certificate follows the joint covariance until its trace
    reaches 1e100 (a (28) violation with its reason at the binding node, every flag down from there), then the
    covariance overflows and the run stops as diverged."""
    x = ca.SX.sym("x", 2)
    growth = ca.vertcat(1e3 * x[0], 5e2 * x[1])
    nodes = 3  # a path 0 - 1 - 2 of sensors that see nothing
    sensors = [Sensor(f"b{i}", 0.0 * x[1], Gaussian.zero_mean([[0.5]])) for i in range(nodes)]
    model = Model("unstable", x, growth, sensors,
                  Gaussian.zero_mean(1e-3 * np.eye(2)), Gaussian(np.zeros(2), np.eye(2)))
    net = SensorNetwork.from_edges(nodes, [(0, 1), (1, 2)])
    des = ConsensusDesign(0.4, 0.0, 0.0, 0.01, np.zeros((2, 2)), np.zeros((1, 1)), 0.0, rules.get("mse"))
    z = np.random.default_rng(0).standard_normal((2, 60, nodes))
    batch = run_mse_batch(model, net, z, des).detail
    assert_mse_batch_is_per_run(batch, per_run(model, net, z, des, None, None))
    limit = [v for v in batch.violations[0] if v["condition"] == "(28)"]
    assert len(limit) == 1 and "1e+100" in limit[0]["reason"] and batch.diverged[0] is not None
    k = limit[0]["step"]
    assert batch.valid[0, :k + 1].all() and not batch.valid[0, k + 1:].any()


def test_refusals(robot, monkeypatch):
    sc, net, traj, atts = robot
    with pytest.raises(InputError, match="runs a gain rule of the joint covariance"):
        run_mse_batch(sc.model, net, traj.z, consensus_design(sc, mode="tuned"), inputs=traj.inputs)
    with pytest.raises(InputError, match="one AttackPattern per run"):
        run_mse_batch(sc.model, net, traj.z, consensus_design(sc, mode="mse"), inputs=traj.inputs, attacks=atts[:2])
    monkeypatch.setattr(mse_batch, "MAX_JOINT_DIM", 16)
    with pytest.raises(InputError, match=r"N n = 8 x 3 = 24 .* MAX_JOINT_DIM = 16"):
        run_mse_batch(sc.model, net, traj.z, consensus_design(sc, mode="mse"), inputs=traj.inputs)
