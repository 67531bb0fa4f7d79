"""The literature's distributed filters (filters.distributed): KCF and HCMCI against their known properties.

References are computed here independently: a covariance-form Kalman filter on the stacked
measurements, ``run_ekf`` (Joseph form) for the local and centralized EKFs, the exact joint
error covariance of HCMCI on a linear model (derived below from the algorithm's equations),
Metropolis weights from the degrees, packet counts from the edge list; and the batched filter (the only
implementation: ``run_kcf`` / ``run_hcmci`` are a batch of one) against the node-by-node loop of
``tests/distributed_reference.py``.
"""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from designer.model import Model, Sensor
from designer.network import SensorNetwork
from designer.noise import Gaussian
from designer.simulate import simulate, simulate_runs
from designer.validation import InputError
from filters.attacks import AttackPattern
import filters.distributed as distributed
from designer.attacks import FDISignal
from filters.attacks import attack_pattern, channel_draws, simulate_attacks
from filters.distributed import FALSIFY_CHOICES, DistributedResult, run_hcmci, run_hcmci_batch, run_kcf, run_kcf_batch
from filters.ekf import run_ekf
from studies.scenarios import load_scenario

import distributed_reference  # tests/ on the path
from distributed_reference import reference_hcmci, reference_kcf

A = np.array([[1.0, 0.1], [-0.05, 0.98]])
N = 5
RING = [(i, (i + 1) % N) for i in range(N)]
H_ROWS = [np.array([[np.cos(0.6 * i), np.sin(0.6 * i)]]) for i in range(N)]  # no node observes the state alone
R_VARS = [0.2 + 0.1 * i for i in range(N)]


def linear_model(r_scale: float = 1.0) -> Model:
    x = ca.SX.sym("x", 2)
    sensors = [Sensor(f"s{i}", ca.mtimes(ca.DM(H_ROWS[i]), x), Gaussian.zero_mean([[r_scale * R_VARS[i]]]))
               for i in range(N)]
    return Model("linear ring", x, ca.mtimes(ca.DM(A), x), sensors, Gaussian.zero_mean(0.01 * np.eye(2)),
                 Gaussian([0.5, -0.5], np.eye(2)))


def oscillator(r_scale: float = 1.0) -> Model:
    """The README's nonlinear oscillator, four scalar sensors (measurement variances scaled by ``r_scale``)."""
    x = ca.SX.sym("x", 2)
    f = ca.vertcat(x[0] + 0.1 * x[1], x[1] - 0.1 * (ca.sin(x[0]) + 0.2 * x[1]))
    sensors = [Sensor(f"s{i}", np.cos(0.5 * i) * x[0] + np.sin(0.5 * i) * x[1], Gaussian.zero_mean([[r_scale * 0.05]]))
               for i in range(4)]
    return Model("oscillator", x, f, sensors, Gaussian.zero_mean(1e-3 * np.eye(2)), Gaussian([1.0, 0.0], 0.05 * np.eye(2)))


def ring(n: int = N) -> SensorNetwork:
    return SensorNetwork.from_edges(n, [(i, (i + 1) % n) for i in range(n)])


def kalman_filter(model: Model, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Covariance-form KF on the stacked linear measurements (gain from the innovation covariance)."""
    H = np.vstack(H_ROWS)
    R = np.diag([model.measurement_cov(i)[0, 0] for i in range(N)])
    x, P = model.prior.mean.copy(), model.prior.cov.copy()
    xs, Ps = [x], [P]
    for zk in z:
        x, P = A @ x, A @ P @ A.T + model.process_cov
        G = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
        x, P = x + G @ (zk - H @ x), (np.eye(2) - G @ H) @ P
        xs.append(x)
        Ps.append(P)
    return np.array(xs), np.array(Ps)


def metropolis(adj: np.ndarray) -> np.ndarray:
    d = adj.sum(1)
    W = np.zeros(adj.shape)
    for i, j in zip(*np.nonzero(adj)):
        W[i, j] = 1.0 / (1 + max(d[i], d[j]))
    return W + np.diag(1.0 - W.sum(1))


def local_ekf(model: Model, z: np.ndarray, i: int, **kw) -> np.ndarray:
    """The EKF on sensor ``i`` alone (run_ekf with every other sensor missing)."""
    avail = np.zeros((z.shape[0], model.n_sensors), bool)
    avail[:, i] = True
    return run_ekf(model, np.where(np.repeat(avail, model.sensor_dims, axis=1), z, 0.0), available=avail, **kw)


def no_attacks(steps: int, n: int, nx: int) -> AttackPattern:
    none = np.zeros((steps, n, n), bool)
    return AttackPattern.dense(none, none.copy(), np.zeros((steps, n, n, nx)))


@pytest.fixture(scope="module")
def linear_run():
    m = linear_model()
    return m, simulate(m, 30, np.random.default_rng(1))


# ------------------------------------------------------------------------ HCMCI -> centralized as L grows
def test_hcmci_tends_to_the_centralized_kalman_filter(linear_run):
    m, traj = linear_run
    xs, Ps = kalman_filter(m, traj.z)
    errors = []
    for L in (1, 2, 5, 20, 200):
        res = run_hcmci(m, ring(), traj.z, iterations=L)
        assert res.diverged is None and res.iterations == L
        errors.append(max(np.abs(res.x_post - xs[:, None]).max(), np.abs(res.P_post - Ps[:, None]).max()))
    assert errors[-1] < 1e-10
    assert all(a > b for a, b in zip(errors, errors[1:])), errors
    # the consistent scaling tends to N as well, hence to the same limit
    res = run_hcmci(m, ring(), traj.z, iterations=200, omega="consistent")
    np.testing.assert_allclose(res.omega, N, rtol=1e-12)
    np.testing.assert_allclose(res.x_post, np.broadcast_to(xs[:, None], res.x_post.shape), atol=1e-10)


# ------------------------------------------------------------------------ consistency of consensus on information
def joint_error_covariance(m: Model, res, L: int, omega: np.ndarray) -> np.ndarray:
    """Each node's exact error covariance E[e_i e_iᵀ] of linear HCMCI without attacks, (steps + 1, N, 2, 2).

    With r = W^L, node i's posterior is x̂_i = P_i (Σ_j r_ij Ω_j x̄_j + ω_i Σ_j r_ij H_jᵀ R_j⁻¹ z_j), and since
    P_i⁻¹ = Σ_j r_ij Ω_j + ω_i Σ_j r_ij H_jᵀ R_j⁻¹ H_j, its error is
    e_i = P_i (Σ_j r_ij Ω_j ē_j - ω_i Σ_j r_ij H_jᵀ R_j⁻¹ v_j); the prediction errors ē_j = A e_j + w share w.
    """
    r = np.linalg.matrix_power(metropolis(ring().adjacency), L)
    n, nx = N, 2
    S = np.kron(np.ones((n, n)), m.prior.cov)  # every node starts from the same prior: one error
    out = [S]
    AA = np.kron(np.eye(n), A)
    QQ = np.kron(np.ones((n, n)), m.process_cov)
    for k in range(res.P_pred.shape[0]):
        S = AA @ S @ AA.T + QQ
        G = np.zeros((n * nx, n * nx))
        V = np.zeros((n * nx, n))
        for i in range(n):
            Pi = res.P_post[k + 1, i]
            for j in range(n):
                G[2 * i:2 * i + 2, 2 * j:2 * j + 2] = r[i, j] * Pi @ np.linalg.inv(res.P_pred[k, j])
                V[2 * i:2 * i + 2, j] = -omega[i] * r[i, j] * Pi @ H_ROWS[j][0] / R_VARS[j]
        S = G @ S @ G.T + V @ np.diag(R_VARS) @ V.T
        out.append(S)
    return np.array([[s[2 * i:2 * i + 2, 2 * i:2 * i + 2] for i in range(n)] for s in out])


@pytest.mark.parametrize("L", [1, 3])
def test_consensus_on_information_covariance_is_consistent(L):
    """omega='consistent': P_i >= E[e_i e_iᵀ] exactly (joint error covariance), and by Monte Carlo (NEES <= n_x)."""
    m = linear_model()
    steps, runs = 15, 150
    trajs = simulate_runs(m, steps, [np.random.default_rng(s) for s in np.random.SeedSequence(7 + L).spawn(runs)])
    nees, e_last = [], []
    for r in range(runs):
        res = run_hcmci(m, ring(), trajs.z[r], iterations=L, omega="consistent")
        e = trajs.x[r][:, None] - res.x_post
        nees.append(np.einsum("kia,kiab,kib->", e[1:], np.linalg.inv(res.P_post[1:]), e[1:]) / (steps * N))
        e_last.append(e[-1])
    exact = joint_error_covariance(m, res, L, res.omega[0])
    gap = np.linalg.eigvalsh(res.P_post - exact)  # the covariances do not depend on the data (linear model)
    assert gap.min() > -1e-12
    nees = np.array(nees)
    assert nees.mean() <= 2 + 3 * nees.std(ddof=1) / np.sqrt(runs)
    # the Monte Carlo error second moment agrees with the exact one (a check of the derivation, 5 standard errors)
    e_last = np.array(e_last)
    emp = np.einsum("ria,rib->iab", e_last, e_last) / runs
    se = np.sqrt(2.0 / runs) * np.abs(exact[-1]).max()
    assert np.abs(emp - exact[-1]).max() < 5 * se


def test_the_papers_omega_counts_measurements_more_than_once_at_small_L(linear_run):
    """omega = N at L = 1 weighs measurement j by N r_ij > 1 (3 on this ring): P is below the true error covariance."""
    m, traj = linear_run
    res = run_hcmci(m, ring(), traj.z[:10], iterations=1)
    assert N * metropolis(ring().adjacency).max() > 1
    exact = joint_error_covariance(m, res, 1, res.omega[0])
    assert np.linalg.eigvalsh(res.P_post[1:] - exact[1:]).min(axis=-1).max() < 0  # overconfident at every node-step


# ------------------------------------------------------------------------ KCF
def test_kcf_on_a_complete_graph_is_the_centralized_filter(linear_run):
    m, traj = linear_run
    complete = SensorNetwork(N, np.ones((N, N), int) - np.eye(N, dtype=int))
    xs, Ps = kalman_filter(m, traj.z)
    res = run_kcf(m, complete, traj.z)
    np.testing.assert_allclose(res.x_post, np.broadcast_to(xs[:, None], res.x_post.shape), atol=1e-10)
    np.testing.assert_allclose(res.P_post, np.broadcast_to(Ps[:, None], res.P_post.shape), atol=1e-10)
    # nonlinear: every node linearises at the same prediction, so it is the centralized EKF (run_ekf, Joseph form)
    sc = load_scenario("indoor-robot", {"steps": 12})
    n = sc.network.n_nodes
    tr = sc.simulate(np.random.default_rng(3), sc.steps)
    res = run_kcf(sc.model, SensorNetwork(n, np.ones((n, n), int) - np.eye(n, dtype=int)), tr.z, inputs=tr.inputs)
    ekf = run_ekf(sc.model, tr.z, inputs=tr.inputs)
    np.testing.assert_allclose(res.x_post, np.broadcast_to(ekf.x[:, None], res.x_post.shape), atol=1e-9)


def test_without_neighbours_both_are_the_local_ekf():
    """Isolated nodes: KCF and HCMCI ('consistent', ω = 1) are the EKF on each node's sensor, bearings wrapped."""
    sc = load_scenario("target-range-bearing", {"steps": 25})
    m, n = sc.model, sc.network.n_nodes
    isolated = SensorNetwork(n, np.zeros((n, n), int), require_connected=False)
    tr = sc.simulate(np.random.default_rng(2), sc.steps)
    kcf = run_kcf(m, isolated, tr.z)
    hc = run_hcmci(m, isolated, tr.z, iterations=2, omega="consistent")
    assert kcf.messages_per_step.sum() == hc.messages_per_step.sum() == 0
    np.testing.assert_allclose(hc.omega, 1.0)
    for i in range(n):
        ref = local_ekf(m, tr.z, i)
        np.testing.assert_allclose(kcf.x_post[:, i], ref.x, atol=1e-7)
        np.testing.assert_allclose(kcf.P_post[:, i], ref.P, atol=1e-9)
        np.testing.assert_allclose(hc.x_post[:, i], ref.x, atol=1e-7)


def test_under_dos_on_every_channel_both_reduce_to_the_local_filter():
    m, net = oscillator(), ring(4)
    tr = simulate(m, 30, np.random.default_rng(5), x0=[1.0, 0.0])
    att = no_attacks(30, 4, 2)
    att.dos[:] = net.adjacency
    att.fdi[:] = False
    kcf = run_kcf(m, net, tr.z, attacks=att)
    hc = run_hcmci(m, net, tr.z, attacks=att, iterations=3, omega="consistent")
    size = run_hcmci(m, net, tr.z, attacks=att, iterations=3)  # ω = N: its own measurement counted N times
    scaled = oscillator(r_scale=1 / 4)
    for res in (kcf, hc, size):
        assert res.delivered_per_step.sum() == 0 and res.diverged is None
    assert kcf.messages_per_step.tolist() == [8] * 30 and hc.messages_per_step.tolist() == [24] * 30
    for i in range(4):
        ref = local_ekf(m, tr.z, i)
        np.testing.assert_allclose(kcf.x_post[:, i], ref.x, atol=1e-9)
        np.testing.assert_allclose(hc.x_post[:, i], ref.x, atol=1e-9)
        np.testing.assert_allclose(hc.P_post[:, i], ref.P, atol=1e-11)
        np.testing.assert_allclose(size.x_post[:, i], local_ekf(scaled, tr.z, i).x, atol=1e-9)


# ------------------------------------------------------------------------ messages and attacks
def test_messages_per_step_are_counted_exactly():
    m, net = oscillator(), SensorNetwork.from_edges(4, [(0, 1), (1, 2), (2, 3), (3, 0), (0, 2)])
    steps = 20
    tr = simulate(m, steps, np.random.default_rng(8))
    rng = np.random.default_rng(9)
    att = no_attacks(steps, 4, 2)
    att.dos[:] = (rng.random((steps, 4, 4)) < 0.3) & net.adjacency
    directed = 2 * len(net.edges)
    lost = [sum(bool(att.dos[k, i, j]) for i, j in net.edges) + sum(bool(att.dos[k, j, i]) for i, j in net.edges)
            for k in range(steps)]
    assert 0 < sum(lost) < steps * directed
    for L in (1, 4):
        res = run_hcmci(m, net, tr.z, iterations=L, attacks=att)
        assert res.messages_per_step.tolist() == [L * directed] * steps  # sent, DoS or not
        assert res.delivered_per_step.tolist() == [L * (directed - lk) for lk in lost]
        assert run_hcmci(m, net, tr.z, iterations=L).delivered_per_step.tolist() == [L * directed] * steps
    res = run_kcf(m, net, tr.z, attacks=att)
    assert res.messages_per_step.tolist() == [directed] * steps
    assert res.delivered_per_step.tolist() == [directed - lk for lk in lost]


def test_a_falsified_packet_is_what_the_displaced_neighbour_would_send(linear_run):
    """One FDI'd channel j -> i at the first step: the shift of node i's estimate, from the documented semantics."""
    m, traj = linear_run
    net, z = ring(), traj.z[:1]
    i, j, xi = 0, 1, np.array([0.7, -0.4])
    fdi, signal = np.zeros((1, N, N), bool), np.zeros((1, N, N, 2))
    fdi[0, i, j], signal[0, i, j] = True, xi
    att = AttackPattern.dense(np.zeros_like(fdi), fdi, signal)
    U_j = H_ROWS[j].T @ H_ROWS[j] / R_VARS[j]
    clean = run_kcf(m, net, z)
    M = clean.P_post[1, i]
    gamma = (0.5 / 2) / (1 + np.linalg.norm(M))  # default epsilon = 0.5 / d_max
    for falsify, shift in (("estimate", gamma * M @ xi), ("packet", M @ (U_j @ xi) + gamma * M @ xi)):
        got = run_kcf(m, net, z, attacks=att, falsify=falsify).x_post[1] - clean.x_post[1]
        np.testing.assert_allclose(got[i], shift, atol=1e-12)
        np.testing.assert_allclose(np.delete(got, i, axis=0), 0.0, atol=1e-15)
    clean = run_hcmci(m, net, z)
    P, Om = clean.P_post[1, i], np.linalg.inv(clean.P_pred[0, j])
    w = metropolis(net.adjacency)[i, j]
    for falsify, shift in (("estimate", P @ (w * Om @ xi)), ("packet", P @ (w * (Om + N * U_j) @ xi))):
        got = run_hcmci(m, net, z, attacks=att, falsify=falsify).x_post[1] - clean.x_post[1]
        np.testing.assert_allclose(got[i], shift, atol=1e-12)


# ------------------------------------------------------------------------ divergence and bad inputs
def test_a_diverging_run_stops_with_nan_and_a_violation():
    x = ca.SX.sym("x", 1)
    m = Model("explodes", x, 1e4 * x, [Sensor(f"s{i}", x, Gaussian.zero_mean([[1.0]])) for i in range(3)],
              Gaussian.zero_mean([[1.0]]), Gaussian([1.0], [[1.0]]))
    net = ring(3)
    z = np.array([[10.0**(4 * (k + 1))] * 3 for k in range(6)])
    for res in (run_kcf(m, net, z), run_hcmci(m, net, z, iterations=2)):
        dv = res.diverged
        assert dv is not None and dv["condition"] == "diverged" and "1e+12" in dv["reason"]
        k = dv["step"]
        assert np.all(np.isfinite(res.x_post[:k])) and np.all(np.isnan(res.x_post[k:]))
        assert np.all(np.isnan(res.P_post[k:])) and not np.isinf(res.x_post).any()
    # a prediction that overflows (exp(800) = inf) is caught before any update uses it
    m = Model("overflows", x, ca.exp(x), [Sensor(f"s{i}", x, Gaussian.zero_mean([[1.0]])) for i in range(3)],
              Gaussian.zero_mean([[1.0]]), Gaussian([800.0], [[1.0]]))
    for res in (run_kcf(m, net, np.zeros((4, 3))), run_hcmci(m, net, np.zeros((4, 3)))):
        assert res.diverged["step"] == 1 and res.diverged["reason"].startswith("prediction")
        assert np.all(np.isnan(res.x_post[1:])) and np.all(np.isnan(res.x_pred)) and not np.isinf(res.P_post).any()


def test_bad_inputs_name_the_parameter(linear_run):
    m, traj = linear_run
    for bad in (0, 1.5, True, "3"):
        with pytest.raises(InputError, match="iterations must be an integer >= 1"):
            run_hcmci(m, ring(), traj.z, iterations=bad)
    with pytest.raises(InputError, match="omega must be one of 'size', 'consistent'"):
        run_hcmci(m, ring(), traj.z, omega="N")
    with pytest.raises(InputError, match="falsify must be one of"):
        run_kcf(m, ring(), traj.z, falsify="all")
    with pytest.raises(InputError, match="epsilon must be >= 0"):
        run_kcf(m, ring(), traj.z, epsilon=-0.1)
    with pytest.raises(InputError, match="z must have shape"):
        run_kcf(m, ring(), traj.z[:, :2])
    with pytest.raises(InputError, match="one node per sensor"):
        run_hcmci(m, ring(4), traj.z)
    with pytest.raises(InputError, match="attacks must be an AttackPattern"):
        run_kcf(m, ring(), traj.z, attacks=no_attacks(3, N, 2))
    with pytest.raises(InputError, match=r"z must have shape \(steps, 5\) with steps >= 1"):
        run_hcmci(m, ring(), traj.z[:0])


# ------------------------------------------------------------------------ many runs at once
def assert_batch_is_per_run(batch, refs, rtol=1e-9):
    """Run r of a batched result equals the per-run reference's result r (``tests/distributed_reference.py``, node
    by node): arrays to rounding (NaN where it is NaN; differences relative to each node-step's largest entry, so a
    structural zero computed as 1e-20 is rounding), violations, packet counts and ω.  Returns the largest relative
    difference."""
    assert len(batch.violations) == len(refs)
    worst = 0.0
    for r, ref in enumerate(refs):
        got = batch.run(r)
        assert got.violations == ref.violations, r
        assert got.iterations == ref.iterations
        assert np.array_equal(got.messages_per_step, ref.messages_per_step)
        assert np.array_equal(got.delivered_per_step, ref.delivered_per_step)
        for field, item in (("x_post", 1), ("P_post", 2), ("x_pred", 1), ("P_pred", 2), ("omega", 0)):
            a, b = getattr(got, field), getattr(ref, field)
            if b is None:
                assert a is None
                continue
            np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=f"run {r} {field}")
            axes = tuple(range(b.ndim - item, b.ndim))
            scale = np.max(np.abs(np.nan_to_num(b)), axis=axes, keepdims=True) if item else np.abs(np.nan_to_num(b))
            diff = np.nan_to_num(np.abs(a - b)) / np.where(scale > 0, scale, 1.0)
            assert diff.max(initial=0.0) <= rtol, (r, field, diff.max())
            worst = max(worst, float(diff.max(initial=0.0)))
    return worst


def assert_run_is_its_row(run, batch_result, z, kw_of_run):
    """``run`` (``run_kcf`` / ``run_hcmci``: a batch of one) on run r alone gives row r of the batch, bit for bit."""
    for r in range(len(z)):
        one, row = run(z[r], **kw_of_run(r)), batch_result.run(r)
        for field in DistributedResult._fields:
            a, b = getattr(one, field), getattr(row, field)
            if isinstance(b, np.ndarray):
                assert np.array_equal(a, b, equal_nan=True), (r, field)
            else:
                assert a == b, (r, field)


def robot_runs(runs: int, dos: float, fdi: float, steps: int = 12):
    """The indoor robot's runs under DoS/FDI as the comparison draws them (inputs differ per run)."""
    sc = load_scenario("indoor-robot", {"steps": steps}).with_attacks(dos=dos, fdi=fdi)
    m, n = sc.model, sc.network.n_nodes
    z, u, att = [], [], []
    for seq in np.random.SeedSequence(11).spawn(runs):
        ts, cs = seq.spawn(2)
        tr = sc.simulate(np.random.default_rng(ts), steps)
        draws, sig = channel_draws(steps, n, np.random.default_rng(cs))
        att.append(attack_pattern(sc.network, draws, sig, m.n_x, sc.resolved_attacks.signal))
        z.append(tr.z)
        u.append(tr.inputs)
    return sc, np.stack(z), np.stack(u), att


FILTERS = {"kcf": (run_kcf, lambda *a, **k: run_kcf_batch(*a, **k).detail, reference_kcf),  # the family's arrays
           "hcmci": (run_hcmci, lambda *a, **k: run_hcmci_batch(*a, **k).detail, reference_hcmci)}


@pytest.mark.parametrize("kind", ["kcf", "hcmci-size", "hcmci-consistent"])
@pytest.mark.parametrize("falsify", ["packet", "estimate"])
def test_the_batch_is_the_per_run_filter_run_by_run(kind, falsify):
    sc, z, u, att = robot_runs(6, dos=0.3, fdi=0.3)
    m, net = sc.model, sc.network
    assert any(a.fdi.any() for a in att) and any(a.dos.any() for a in att)
    run, batch, ref = FILTERS[kind.split("-")[0]]
    kw = {"epsilon": 0.2} if kind == "kcf" else {"iterations": 2, "omega": kind.split("-")[1]}
    refs = [ref(m, net, z[r], inputs=u[r], attacks=att[r], falsify=falsify, **kw) for r in range(len(z))]
    got = batch(m, net, z, inputs=u, attacks=att, falsify=falsify, **kw)
    assert_batch_is_per_run(got, refs)
    assert_run_is_its_row(lambda zr, **k: run(m, net, zr, falsify=falsify, **kw, **k), got, z,
                          lambda r: {"inputs": u[r], "attacks": att[r]})
    # without attacks, with shared inputs and one x0 / P0 per run
    x0 = m.prior.mean + 0.05 * np.arange(len(z))[:, None]
    P0 = m.prior.cov * (1.0 + np.arange(len(z)))[:, None, None]
    refs = [ref(m, net, z[r], inputs=u[0], x0=x0[r], P0=P0[r], falsify=falsify, **kw) for r in range(len(z))]
    assert_batch_is_per_run(batch(m, net, z, inputs=u[0], x0=x0, P0=P0, falsify=falsify, **kw), refs)


def mixed_user_model() -> Model:
    """A model as a user would write it: a nonlinear turning target, four nodes with sensors of dimension 1, 2, 1
    and 2 (a range, a range and bearing, a bearing, a position fix); the bearings are angles (wrapped)."""
    x = ca.SX.sym("x", 4)  # px, py, speed, heading
    dt = 0.2
    f = ca.vertcat(x[0] + dt * x[2] * ca.cos(x[3]), x[1] + dt * x[2] * ca.sin(x[3]), 0.99 * x[2], x[3] + 0.05)
    anchors = [(-4.0, 0.0), (0.0, -4.0), (4.0, 0.5), (0.0, 4.0)]  # node 2 sees the target across ±π
    rng = [ca.sqrt((x[0] - a) ** 2 + (x[1] - b) ** 2) for a, b in anchors]
    brg = [ca.atan2(x[1] - b, x[0] - a) for a, b in anchors]
    sensors = [Sensor("range0", rng[0], Gaussian.zero_mean([[0.05]])),
               Sensor("rb1", ca.vertcat(rng[1], brg[1]), Gaussian.zero_mean(np.diag([0.05, 0.01])), angles=[1]),
               Sensor("bearing2", brg[2], Gaussian.zero_mean([[0.01]]), angles=[0]),
               Sensor("fix3", ca.vertcat(x[0], x[1]), Gaussian.zero_mean(0.2 * np.eye(2)))]
    return Model("user turning target", x, f, sensors, Gaussian.zero_mean(np.diag([1e-3, 1e-3, 1e-3, 1e-4])),
                 Gaussian([0.5, 0.0, 1.0, 0.3], np.diag([0.1, 0.1, 0.05, 0.02])))


@pytest.mark.parametrize("kind, kw", [("kcf", {}), ("hcmci", {"iterations": 1, "omega": "size"}),
                                      ("hcmci", {"iterations": 3, "omega": "size"}),
                                      ("hcmci", {"iterations": 1, "omega": "consistent"}),
                                      ("hcmci", {"iterations": 3, "omega": "consistent"})])
def test_a_users_nonlinear_mixed_sensor_model_under_dos_and_fdi_matches_the_reference(kind, kw):
    """The batch against the node-by-node reference on a nonlinear model with sensors of mixed dimensions and
    wrapped bearings, under DoS and FDI (both falsifications), L = 1 and L = 3, both ω: equal to rounding (the
    largest relative difference measured is 2.2e-15), and each run alone is its row of the batch."""
    m = mixed_user_model()
    net = SensorNetwork.from_edges(4, [(0, 1), (1, 2), (2, 3), (3, 0), (0, 2)])
    steps, runs = 10, 4
    seqs = np.random.SeedSequence(26).spawn(runs)
    tr = simulate_runs(m, steps, [np.random.default_rng(s.spawn(1)[0]) for s in seqs])
    attacked, signal = net.with_attacks(0.3, 0.3), FDISignal(0.5, components=(0, 1)).resolve(m.n_x)
    att = [simulate_attacks(attacked, steps, m.n_x, np.random.default_rng(s.spawn(2)[1]), signal) for s in seqs]
    assert sum(a.dos.sum() for a in att) > 0 and sum(a.fdi.sum() for a in att) > 0
    run, batch, ref = FILTERS[kind]
    for falsify in FALSIFY_CHOICES:
        refs = [ref(m, net, tr.z[r], attacks=att[r], falsify=falsify, **kw) for r in range(runs)]
        assert not any(r.diverged for r in refs)
        got = batch(m, net, tr.z, attacks=att, falsify=falsify, **kw)
        assert assert_batch_is_per_run(got, refs) < 1e-9
        assert_run_is_its_row(lambda zr, **k: run(m, net, zr, falsify=falsify, **kw, **k), got, tr.z,
                              lambda r: {"attacks": att[r]})


@pytest.mark.parametrize("lapack_from", [1, 10**9])
def test_the_spd_inverse_either_way_is_the_inverse_and_a_matrix_is_inverted_alike_alone_or_stacked(lapack_from,
                                                                                                   monkeypatch):
    """``_spd_inverse`` (LAPACK's Cholesky inverse a matrix at a time from SPD_LAPACK_MIN states, NumPy's stacked
    Cholesky and triangular solve below): the inverse to rounding, exactly symmetric, each matrix's bits the same alone
    as in a stack (a node filter's numbers are the batch's), and a matrix that is not positive definite raises
    LinAlgError; and the information filters on it match the node-by-node reference."""
    monkeypatch.setattr(distributed, "SPD_LAPACK_MIN", lapack_from)
    rng = np.random.default_rng(3)
    for n in (3, 20):
        B = rng.standard_normal((2, 4, n, n))
        A = B @ np.swapaxes(B, -1, -2) + n * np.eye(n)
        X = distributed._spd_inverse(A)
        assert np.abs(X @ A - np.eye(n)).max() < 1e-12 * n and np.array_equal(X, np.swapaxes(X, -1, -2))
        assert np.array_equal(distributed._spd_inverse(A[1, 2]), X[1, 2])
        bad = A[0, 0] - 2 * np.linalg.eigvalsh(A[0, 0])[-1] * np.outer(np.eye(n)[0], np.eye(n)[0])
        with pytest.raises(np.linalg.LinAlgError):
            distributed._spd_inverse(np.stack([A[0, 1], bad]))
    m = mixed_user_model()
    net = SensorNetwork.from_edges(4, [(0, 1), (1, 2), (2, 3), (3, 0), (0, 2)])
    seqs = np.random.SeedSequence(26).spawn(3)
    tr = simulate_runs(m, 8, [np.random.default_rng(s.spawn(1)[0]) for s in seqs])
    attacked, signal = net.with_attacks(0.3, 0.3), FDISignal(0.5, components=(0, 1)).resolve(m.n_x)
    att = [simulate_attacks(attacked, 8, m.n_x, np.random.default_rng(s.spawn(2)[1]), signal) for s in seqs]
    for kind, kw in (("kcf", {}), ("hcmci", {"iterations": 2, "omega": "size"})):
        run, batch, ref = FILTERS[kind]
        refs = [ref(m, net, tr.z[r], attacks=att[r], **kw) for r in range(3)]
        assert assert_batch_is_per_run(batch(m, net, tr.z, attacks=att, **kw), refs) < 1e-9


def test_a_diverging_run_stops_alone_in_the_batch():
    """Runs that diverge in the update, in the prediction and by a numerical breakdown stop at their step with the
    reference's violation; the other runs go on."""
    x = ca.SX.sym("x", 1)
    m = Model("explodes", x, 1e4 * x, [Sensor(f"s{i}", x, Gaussian.zero_mean([[1.0]])) for i in range(3)],
              Gaussian.zero_mean([[1.0]]), Gaussian([1.0], [[1.0]]))
    net = ring(3)
    big = np.array([[10.0**(4 * (k + 1))] * 3 for k in range(6)])
    z = np.stack([big, np.zeros((6, 3)), 1e-3 * big, np.ones((6, 3))])
    x0 = np.array([[1.0], [1e9], [1.0], [0.0]])  # run 1: 1e13 after one step, beyond 1e12
    for kind, kw in (("kcf", {}), ("hcmci", {"iterations": 2})):
        run, batch, ref = FILTERS[kind]
        refs = [ref(m, net, z[r], x0=x0[r], **kw) for r in range(4)]
        assert [r.diverged is not None for r in refs] == [True, True, True, False]
        assert refs[1].diverged["step"] == 1 and refs[1].diverged["reason"].startswith("prediction")
        assert refs[0].diverged["step"] != refs[2].diverged["step"]
        got = batch(m, net, z, x0=x0, **kw)
        assert_batch_is_per_run(got, refs)
        assert_run_is_its_row(lambda zr, **k: run(m, net, zr, **kw, **k), got, z, lambda r: {"x0": x0[r]})


def test_a_numerical_breakdown_in_the_batch_is_found_run_by_run(monkeypatch):
    """A LinAlgError in one run's update: that run stops with the reference's 'numerical breakdown', the
    others are updated as if alone (the inverse is made to fail on the prediction that marks run 2)."""
    m, net = oscillator(), ring(4)
    tr = simulate_runs(m, 8, [np.random.default_rng(s) for s in (1, 2, 3)])
    P0 = np.stack([m.prior.cov, 2.0 * m.prior.cov, 7.0 * m.prior.cov])

    def failing(inverse):
        def inv(A):
            if np.any(np.isclose(A[..., 0, 0], 7.0 * m.prior.cov[0, 0] + m.process_cov[0, 0], rtol=0.2)):
                raise np.linalg.LinAlgError("Matrix is not positive definite")
            return inverse(A)
        return inv

    monkeypatch.setattr(distributed, "_spd_inverse", failing(distributed._spd_inverse))
    monkeypatch.setattr(distributed_reference, "spd_inverse", failing(distributed_reference.spd_inverse))
    for kind in ("kcf", "hcmci"):
        run, batch, ref = FILTERS[kind]
        refs = [ref(m, net, tr.z[r], P0=P0[r]) for r in range(3)]
        assert [r.diverged is not None for r in refs] == [False, False, True]
        assert refs[2].diverged["reason"].startswith("numerical breakdown") and refs[2].diverged["step"] == 1
        got = batch(m, net, tr.z, P0=P0)
        assert_batch_is_per_run(got, refs)
        assert_run_is_its_row(lambda zr, **k: run(m, net, zr, **k), got, tr.z, lambda r: {"P0": P0[r]})


def test_batch_bad_inputs_name_the_parameter():
    sc, z, u, att = robot_runs(2, dos=0.1, fdi=0.1, steps=4)
    m, net = sc.model, sc.network
    with pytest.raises(InputError, match="attacks must hold one AttackPattern per run"):
        run_kcf_batch(m, net, z, inputs=u, attacks=att[:1])
    with pytest.raises(InputError, match="z must have shape"):
        run_hcmci_batch(m, net, z[0], inputs=u[0])
    with pytest.raises(InputError, match="P0 must have shape"):
        run_kcf_batch(m, net, z, inputs=u, P0=np.stack([m.prior.cov] * 3))
    with pytest.raises(InputError, match="iterations must be an integer >= 1"):
        run_hcmci_batch(m, net, z, inputs=u, iterations=0)
    with pytest.raises(InputError, match="epsilon must be >= 0"):
        run_kcf_batch(m, net, z, inputs=u, epsilon=-1.0)
    with pytest.raises(InputError, match="one node per sensor"):
        run_kcf_batch(m, ring(4), z, inputs=u)


# ------------------------------------------------------------------------ the local EKFs: every node alone
def test_the_local_ekfs_are_the_ekf_on_each_nodes_sensor_alone():
    """run_local_batch against run_ekf with every other sensor missing (another implementation: Joseph's form in full,
    the gain from a Cholesky solve on the sensor's own rows, no whitening): on a user's model of sensors of dimension
    1 and 2 (bearings wrapped across ±π, so padding rows) and on the robot, whose known inputs differ per run.  Equal
    to rounding; nothing sent or counted; each run alone (a batch of one) is its row of the batch, bit for bit."""
    m = mixed_user_model()
    tr = simulate_runs(m, 25, [np.random.default_rng(s) for s in np.random.SeedSequence(8).spawn(3)])
    sc, zr, ur, _ = robot_runs(3, 0.0, 0.0, steps=20)
    for model, z, u in ((m, tr.z, None), (sc.model, zr, ur)):
        res = distributed.run_local_batch(model, z, inputs=u)
        assert res.runtime == "local" and res.cov_kind == "covariance" and res.delivered is None
        assert not res.messages.any() and not any(res.violations) and np.isfinite(res.cov).all()
        for r in range(len(z)):
            for i in range(model.n_sensors):
                ref = local_ekf(model, z[r], i, inputs=None if u is None else u[r])
                scale = np.abs(ref.P).max(axis=(-2, -1))[:, None, None]
                assert np.abs(res.x[r, :, i] - ref.x).max() < 1e-9 * max(1.0, np.abs(ref.x).max()), (r, i)
                assert (np.abs(res.cov[r, :, i] - ref.P) / scale).max() < 1e-10, (r, i)
            one = distributed.run_local_batch(model, z[r:r + 1], inputs=None if u is None else u[r:r + 1])
            assert np.array_equal(one.x[0], res.x[r]) and np.array_equal(one.cov[0], res.cov[r])


def test_the_local_ekfs_node_filters_are_the_batch_bit_for_bit_and_stop_where_it_stops():
    """LocalEKFNetwork (every node's LocalEKFNode, step(z, u)) over each run of a user's mixed-sensor model: the batch's
    estimates and covariances bit for bit; a run whose measurement at step 3 is 1e300 stops there in both, with one
    'diverged' violation at that step (NaN from it on), the other runs untouched; a node refuses a measurement of the
    wrong size, naming node and step, and is left as it was."""
    m = mixed_user_model()
    z = simulate_runs(m, 12, [np.random.default_rng(s) for s in np.random.SeedSequence(9).spawn(3)]).z.copy()
    z[1, 3, 0] = 1e300
    res = distributed.run_local_batch(m, z)
    for r in range(3):
        x, P = distributed.LocalEKFNetwork(m).run(z[r])
        assert np.array_equal(x, res.x[r], equal_nan=True) and np.array_equal(P, res.cov[r], equal_nan=True), r
    assert res.violations[0] == res.violations[2] == []
    (stop,) = res.violations[1]
    assert stop["condition"] == "diverged" and stop["step"] == 4 and stop["node"] == 0
    assert np.isfinite(res.x[1, :4]).all() and np.isnan(res.x[1, 4:]).all()
    node = distributed.LocalEKFNode(m, 1)
    node.step(z[0, 0, 1:3])
    x, P = node.x.copy(), node.P.copy()
    with pytest.raises(InputError, match=r"z of node 1 at step 1 must be 2 finite numbers"):
        node.step([0.3])
    assert node.k == 1 and np.array_equal(node.x, x) and np.array_equal(node.P, P)
    assert node.senders.size == 0
