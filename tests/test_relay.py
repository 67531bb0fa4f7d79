"""The relay filter (rules.relay.filter) and its routes and moments (rules.relay.design), against independent
references.

* routes: every route a shortest path (scipy), prefix-consistent, the balls exactly the nodes within ``hops``; the
  arrival probabilities and moments ``(p, A, F1, F2)`` against a Monte Carlo of the channels' draws
  (``filters.attacks.channel_draws`` turned into EdgeAttacks as the studies do), routes walked by their parents;
* no attacks, linear model: node i is the Kalman filter of its ball's sensors (``filters.ekf.run_ekf_batch`` with
  ``available`` = the ball);
* attacks (DoS and FDI on every channel, non-zero ξ), a nonlinear model with a bearing and a two-dimensional sensor:
  the batch equals a plain node-by-node, run-by-run loop written here (routes walked by their parents);
* a Monte Carlo of the generative linear model: each node's mean squared error approaches the trace of its ``P_post``
  (the relay rule's expected covariance), and the same check rejects a filter whose moments treat arrivals as
  independent;
* a batch of one is that row of a batch; bad inputs raise InputError naming the parameter.
"""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import scipy.linalg
from scipy.sparse.csgraph import shortest_path

import rules.relay.filter as relay_filter
from designer.attacks import FDISignal
from designer.model import Model, Sensor
from designer.network import SensorNetwork
from designer.noise import Gaussian
from rules.relay.design import node_moments, relay_moments, relay_routes, relay_update
from designer.validation import InputError
from filters.attacks import attack_pattern, channel_draws
from filters.consensus import wrapped_residual
from filters.consensus_batch import EdgeAttacks
from filters.ekf import run_ekf_batch
from rules.relay.filter import run_relay_batch

EDGES = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (1, 4), (0, 2)]
N = 6
SIGNAL = FDISignal(amplitude=(0.8, 0.5), components=(0, 1))


def network(dos=0.0, fdi=0.0) -> SensorNetwork:
    return SensorNetwork.from_edges(N, EDGES, dos_prob=dos, fdi_prob=fdi)


def varied_network() -> SensorNetwork:
    """Per-channel different DoS and FDI probabilities (not symmetric between the two directions)."""
    rng = np.random.default_rng(7)
    dos = rng.uniform(0.05, 0.35, (N, N))
    fdi = rng.uniform(0.0, 0.25, (N, N))
    return network(dos, fdi)


def edge_attacks(net: SensorNetwork, runs: int, steps: int, nx: int, seed: int, signal=SIGNAL) -> EdgeAttacks:
    """Channel draws turned into EdgeAttacks as the studies do (filters.attacks.channel_draws, attack_pattern)."""
    pats = []
    for seq in np.random.SeedSequence(seed).spawn(runs):
        u, s = channel_draws(steps, net.n_nodes, np.random.default_rng(seq))
        pats.append(attack_pattern(net, u, s, nx, signal))
    return EdgeAttacks.from_patterns(net, pats)


def route_channels(rt, p: int) -> list[int]:
    """The channels of pair p's route, walked by its parents (source end first)."""
    out = []
    while p >= 0:
        out.append(int(rt.channel[p]))
        p = int(rt.parent[p])
    return out[::-1]


# --------------------------------------------------------------------------- routes and moments
@pytest.mark.parametrize("hops", [1, 2, 3])
def test_routes_are_prefix_consistent_shortest_paths_covering_the_balls(hops):
    net = network()
    rt = relay_routes(net, hops)
    dist = shortest_path(net.adjacency.astype(float), unweighted=True)
    receiver, sender = np.nonzero(net.adjacency)
    assert np.all(np.diff(rt.depth) >= 0)
    for p in range(rt.n_pairs):
        s, i, j, par = rt.source[p], rt.node[p], rt.sender[p], rt.parent[p]
        assert receiver[rt.channel[p]] == i and sender[rt.channel[p]] == j  # the channel j -> i
        assert rt.depth[p] == dist[s, i]  # a shortest path
        if par < 0:
            assert j == s and rt.depth[p] == 1
        else:  # the parent pair is the route of s to the sender, earlier in the order
            assert par < p and rt.source[par] == s and rt.node[par] == j and rt.depth[par] == rt.depth[p] - 1
        chans = route_channels(rt, p)
        assert len(chans) == rt.depth[p]
        assert sorted(chans) == sorted(np.flatnonzero(rt.incidence[p].toarray()[0]).tolist())
    for i in range(N):
        ball = rt.ball(i)
        assert ball[0] == i
        assert sorted(ball.tolist()) == np.flatnonzero(dist[i] <= hops).tolist()
    assert np.array_equal(rt.ball_sizes(), (dist <= hops).sum(axis=1))


@pytest.mark.slow
def test_arrival_moments_match_a_monte_carlo_of_the_channels():
    net = varied_network()
    rt = relay_routes(net, 3)
    steps = 40000
    att = edge_attacks(net, 1, steps, 2, seed=11)
    dos, fdi = att.dos[0], att.fdi[0]  # (steps, E)
    arr_prob = rt.arrival_prob(net)
    for i in range(N):
        pairs = np.flatnonzero(rt.node == i)
        routes = [route_channels(rt, p) for p in pairs]
        gamma = np.ones((steps, 1 + pairs.size))
        phi = [np.zeros((steps, 0))] + [fdi[:, r] for r in routes]  # falsified channels of each route
        for a, r in enumerate(routes, start=1):
            gamma[:, a] = ~dos[:, r].any(axis=1)
        p, A, F1, F2 = rt.arrival_moments(net, i)
        m = gamma.shape[1]
        samples = {"p": gamma, "A": gamma[:, :, None] * gamma[:, None, :],
                   "F1": np.zeros((steps, m, m)), "F2": np.zeros((steps, m, m))}
        for a in range(m):
            for b in range(m):
                ra = routes[a - 1] if a else []
                rb = routes[b - 1] if b else []
                both = gamma[:, a] * gamma[:, b]
                shared = [c for c in ra if c in rb]
                samples["F1"][:, a, b] = both * fdi[:, shared].sum(1)
                samples["F2"][:, a, b] = both * sum((fdi[:, c] & fdi[:, d] for c in ra for d in rb if c != d),
                                                    np.zeros(steps))
        assert np.allclose(p[1:], arr_prob[pairs])
        for name, est in (("p", p), ("A", A), ("F1", F1), ("F2", F2)):
            mc = samples[name].mean(0)
            se = np.maximum(samples[name].std(0), 0.01) / np.sqrt(steps)  # the Monte Carlo's standard error
            assert np.all(np.abs(est - mc) <= 5 * se), (i, name, np.max(np.abs(est - mc) / se))
            assert np.any(est > 0.05) or name == "F2"
        assert F1[0].sum() == F2[0].sum() == 0 and A[0, 0] == p[0] == 1.0  # own: always arrives, never falsified


# --------------------------------------------------------------------------- models
def linear_model() -> Model:
    """A 2-D linear model, five scalar sensors and one two-dimensional sensor with correlated noise (node 3)."""
    x = ca.SX.sym("x", 2)
    sensors = []
    for i in range(N):
        if i == 3:
            sensors.append(Sensor("pair", ca.vertcat(x[0] + 0.3 * x[1], -0.2 * x[0] + x[1]),
                                  Gaussian.zero_mean([[0.3, 0.1], [0.1, 0.2]])))
        else:
            sensors.append(Sensor(f"s{i}", np.cos(0.7 * i) * x[0] + np.sin(0.7 * i) * x[1],
                                  Gaussian.zero_mean([[0.1 + 0.05 * i]])))
    F = np.array([[1.0, 0.1], [-0.1, 0.97]])
    return Model("linear relay", x, ca.mtimes(ca.DM(F), x), sensors, Gaussian.zero_mean(0.02 * np.eye(2)),
                 Gaussian([1.0, -0.5], np.diag([0.5, 0.3])))


def bearing_model() -> Model:
    """A nonlinear CV-like model: ranges, a bearing (an angle, wrapped) and a range-bearing pair (node 4)."""
    x = ca.SX.sym("x", 4)
    pos = [(0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0), (5.0, -5.0), (-5.0, 5.0)]
    sensors = []
    for i, (a, b) in enumerate(pos):
        rng_ = ca.sqrt((x[0] - a) ** 2 + (x[1] - b) ** 2)
        bearing = ca.atan2(x[1] - b, x[0] - a)
        if i == 2:
            sensors.append(Sensor("bearing", bearing, Gaussian.zero_mean([[0.01]]), angles=(0,)))
        elif i == 4:
            sensors.append(Sensor("rb", ca.vertcat(rng_, bearing), Gaussian.zero_mean([[0.5, 0.02], [0.02, 0.02]]),
                                  angles=(1,)))
        else:
            sensors.append(Sensor(f"r{i}", rng_, Gaussian.zero_mean([[0.4 + 0.1 * i]])))
    f = ca.vertcat(x[0] + x[2], x[1] + x[3], 0.99 * x[2], 0.99 * x[3])
    return Model("bearing relay", x, f, sensors, Gaussian.zero_mean(np.diag([0.01, 0.01, 0.02, 0.02])),
                 Gaussian([4.0, 3.0, 0.3, 0.2], np.diag([1.0, 1.0, 0.1, 0.1])))


def simulate_linear(model: Model, runs: int, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Truths (runs, steps + 1, n_x) and measurements (runs, steps, n_z) of the generative linear model."""
    rng = np.random.default_rng(seed)
    nx = model.n_x
    Fm = model.F(np.zeros(nx))
    H = np.concatenate([model.H(i, np.zeros(nx)) for i in range(model.n_sensors)])
    R = scipy.linalg.block_diag(*[model.measurement_cov(i) for i in range(model.n_sensors)])
    x = rng.multivariate_normal(model.prior.mean, model.prior.cov, runs)
    xs, zs = [x], []
    for _ in range(steps):
        x = x @ Fm.T + rng.multivariate_normal(np.zeros(nx), model.process_cov, runs)
        zs.append(x @ H.T + rng.multivariate_normal(np.zeros(H.shape[0]), R, runs))
        xs.append(x)
    return np.stack(xs, 1), np.stack(zs, 1)


# --------------------------------------------------------------------------- the filter
@pytest.mark.parametrize("hops", [1, 2])
def test_without_attacks_each_node_is_the_kalman_filter_of_its_ball(hops):
    model = linear_model()
    net = network()
    _, z = simulate_linear(model, 3, 12, seed=1)
    res = run_relay_batch(model, net, z, hops).detail
    rt = relay_routes(net, hops)
    for i in range(N):
        mask = np.zeros((3, 12, N), dtype=bool)
        mask[:, :, rt.ball(i)] = True
        ekf = run_ekf_batch(model, z, available=mask).detail
        assert np.allclose(res.x_post[:, :, i], ekf.x, rtol=0, atol=1e-10)
        assert np.allclose(res.P_post[:, :, i], ekf.P, rtol=0, atol=1e-10)
    assert res.iterations == hops and res.violations == [[], [], []]
    assert np.all(res.messages_per_step == 2 * len(EDGES) * hops) and np.all(res.delivered_per_step == 2 * len(EDGES)
                                                                           * hops)


def tree_copies(model: Model, net: SensorNetwork, rt, zk, dos, fdi, xi, xp, k: int) -> dict:
    """The values that arrived at step k (one run: ``zk`` its measurement, ``dos``, ``fdi``, ``xi`` its channels'
    draws, ``xp`` the nodes' predictions), {(sensor, node): value}, each pair's route walked back by its parents."""
    offsets = np.concatenate([[0], np.cumsum(model.sensor_dims)])
    values = {(s, s): zk[offsets[s]:offsets[s + 1]].copy() for s in range(net.n_nodes)}
    for p in range(rt.n_pairs):
        s = int(rt.source[p])
        zs, arrived, q = zk[offsets[s]:offsets[s + 1]].copy(), True, p
        while q >= 0:  # walk the route back to the source
            c = rt.channel[q]
            arrived &= not dos[c]
            if fdi[c]:
                zs = zs + model.H(s, xp[rt.sender[q]], k + 1) @ xi[c]
            q = rt.parent[q]
        if arrived:
            values[(s, int(rt.node[p]))] = zs
    return values


def reference_relay(model: Model, net: SensorNetwork, z, hops: int, att: EdgeAttacks, signal: FDISignal,
                    routing: str = "tree", copies=tree_copies):
    """The relay filter written node by node and run by run: each step the values that arrived (``copies``, with
    tree_copies' parameters), then each node's update with rules.relay.design.relay_update and its moments
    (rules.relay.design.relay_moments): (x_post, P_post)."""
    rt = relay_routes(net, hops, routing)
    n = net.n_nodes
    runs, steps = z.shape[:2]
    nx = model.n_x
    M, mu = signal.moment(nx), signal.mean(nx)
    root = [np.linalg.inv(scipy.linalg.sqrtm(model.measurement_cov(s)).real) for s in range(model.n_sensors)]
    moms = relay_moments(rt, net, model.sensor_dims)
    xs = np.zeros((runs, steps + 1, n, nx))
    Ps = np.zeros((runs, steps + 1, n, nx, nx))
    for r in range(runs):
        x = np.tile(model.prior.mean, (n, 1))
        P = np.tile(model.prior.cov, (n, 1, 1))
        xs[r, 0], Ps[r, 0] = x, P
        for k in range(steps):
            xp = np.array([model.f(x[i], k) for i in range(n)])
            Pp = np.array([model.F(x[i], k) @ P[i] @ model.F(x[i], k).T + model.process_cov for i in range(n)])
            values = copies(model, net, rt, z[r, k], att.dos[r, k], att.fdi[r, k], att.xi[r, k], xp, k)
            for i in range(n):
                rows, info = [], np.zeros((hops + 1, nx))  # the information of each hop depth (0: its own)
                ball = [(i, 0)] + [(int(rt.source[p]), int(rt.depth[p])) for p in np.flatnonzero(rt.node == i)]
                for s, depth in ball:
                    Hw = root[s] @ model.H(s, xp[i], k + 1)
                    rows.append(Hw)
                    if (s, i) in values:
                        info[depth] += Hw.T @ root[s] @ wrapped_residual(model, s, values[(s, i)], xp[i], k + 1)
                W, Pn = relay_update(0.5 * (Pp[i] + Pp[i].T), np.concatenate(rows), moms[i], M, mu)
                x[i] = xp[i] + W @ info.reshape(-1)  # one gain block per depth
                P[i] = Pn
            xs[r, k + 1], Ps[r, k + 1] = x, P
    return xs, Ps


def test_with_attacks_equals_the_node_by_node_reference():
    model = bearing_model()
    net = network(0.2, 0.25)
    runs, steps = 3, 8
    rng = np.random.default_rng(3)
    z = np.stack([model.h_all(model.prior.mean) + rng.normal(0, 0.2, (steps, model.n_z)) for _ in range(runs)])
    att = edge_attacks(net, runs, steps, model.n_x, seed=5)
    assert att.dos.any() and att.fdi.any() and np.abs(att.xi).max() > 0.1
    res = run_relay_batch(model, net, z, 3, attacks=att, signal=SIGNAL).detail
    xs, Ps = reference_relay(model, net, z, 3, att, SIGNAL)
    assert res.violations == [[], [], []]
    assert np.allclose(res.x_post, xs, rtol=0, atol=1e-10)
    assert np.allclose(res.P_post, Ps, rtol=0, atol=1e-10)
    assert np.array_equal(res.delivered_per_step, (~att.dos).sum(-1) * 3)
    assert np.all(res.messages_per_step == net.messages_per_step(3))


def independent_moments(routes, net, dims, rng=None):
    """A wrong relay_moments: arrivals as if independent (A = p pᵀ off the diagonal)."""
    out = []
    for i in range(routes.n_nodes):
        mom = node_moments(routes, net, dims, i)
        A = np.outer(mom.p, mom.p)
        same = mom.rows[:, None] == mom.rows[None, :]
        out.append(mom._replace(A=np.where(same, mom.A, A)))
    return out


def mse_over_bound(model, net, hops, runs, steps, seed):
    """Per node: the mean over runs of (Σ_k |e_k|²) / (Σ_k tr P_k) and its standard error."""
    truth, z = simulate_linear(model, runs, steps, seed)
    att = edge_attacks(net, runs, steps, model.n_x, seed=seed + 1)
    res = run_relay_batch(model, net, z, hops, attacks=att, signal=SIGNAL).detail
    e2 = ((res.x_post[:, 1:] - truth[:, 1:, None]) ** 2).sum(-1).sum(1)  # (runs, N)
    tr = np.trace(res.P_post[:, 1:], axis1=-2, axis2=-1).sum(1)
    ratio = e2 / tr
    return ratio.mean(0), ratio.std(0, ddof=1) / np.sqrt(runs)


@pytest.mark.slow
def test_the_expected_covariance_matches_a_monte_carlo_and_the_check_has_power(monkeypatch):
    model = linear_model()
    line = SensorNetwork.from_edges(N, [(i, i + 1) for i in range(N - 1)], dos_prob=0.4, fdi_prob=0.2)
    mean, se = mse_over_bound(model, line, 4, 3000, 20, seed=21)
    assert np.all(np.abs(mean - 1.0) < 4 * se), (mean, se)
    # the same check against a filter designed for independent arrivals (its P_post is not the error's covariance)
    monkeypatch.setattr(relay_filter, "relay_moments", independent_moments)
    mean, se = mse_over_bound(model, line, 4, 3000, 20, seed=21)
    assert np.any(np.abs(mean - 1.0) > 4 * se), (mean, se)


def test_one_gain_block_per_depth_is_never_worse_than_one_gain_for_all():
    """The rule's gain has one block per hop depth: with every row in one group it is the single-gain formula written
    here (S = Σ p_a J_a, Q = S + Σ A_ab J_a P J_b + Σ F1_ab J_a M J_b + Σ F2_ab J_a μμᵀ J_b, W = P S Q⁻¹,
    P⁺ = P - W S P); with the groups its expected covariance is no larger (an optimum over more gains), and smaller
    when the depths' arrival and falsification statistics differ."""
    model = bearing_model()
    net = varied_network()
    rt = relay_routes(net, 3)
    signal = FDISignal(amplitude=(0.8, 0.5), components=(0, 1), law="constant")  # a mean: the F2 terms count
    M, mu = signal.moment(4), signal.mean(4)
    rng = np.random.default_rng(11)
    for i in range(N):
        mom = node_moments(rt, net, model.sensor_dims, i)
        Hw = rng.normal(size=(mom.rows.size, 4))
        B = rng.normal(size=(4, 4))
        P = B @ B.T + 0.1 * np.eye(4)
        one = mom._replace(groups=np.ones((mom.rows.size, 1)))
        W1, P1 = relay_update(P, Hw, one, M, mu)
        J = [np.outer(h, h) for h in Hw]  # the whitened rows: one row each
        S = sum(p * j for p, j in zip(mom.p, J))
        Q = S + sum(mom.A[a, b] * J[a] @ P @ J[b] + mom.F1[a, b] * J[a] @ M @ J[b]
                    + mom.F2[a, b] * J[a] @ np.outer(mu, mu) @ J[b]
                    for a in range(len(J)) for b in range(len(J)))
        W = P @ S @ np.linalg.inv(Q)
        assert np.allclose(W1, W, rtol=1e-8, atol=1e-10) and np.allclose(P1, P - W @ S @ P, rtol=1e-8, atol=1e-10)
        Wg, Pg = relay_update(P, Hw, mom, M, mu)
        assert Wg.shape == (4, 4 * 4)
        assert np.linalg.eigvalsh(P1 - Pg).min() > -1e-9  # the grouped covariance lies below, in every direction
        if np.unique(mom.groups.argmax(-1)).size > 2:
            assert np.trace(Pg) < np.trace(P1) * (1 - 1e-6)


def test_a_batch_of_one_is_that_row_of_the_batch():
    model = bearing_model()
    net = network(0.15, 0.1)
    rng = np.random.default_rng(4)
    z = np.stack([model.h_all(model.prior.mean) + rng.normal(0, 0.3, (6, model.n_z)) for _ in range(4)])
    att = edge_attacks(net, 4, 6, model.n_x, seed=9)
    full = run_relay_batch(model, net, z, 2, attacks=att, signal=SIGNAL).detail
    one = att._replace(dos=att.dos[2:3], fdi=att.fdi[2:3], xi=att.xi[2:3])
    alone = run_relay_batch(model, net, z[2:3], 2, attacks=one, signal=SIGNAL).detail
    for name in ("x_post", "P_post", "x_pred", "P_pred", "messages_per_step", "delivered_per_step"):
        assert np.array_equal(getattr(alone, name)[0], getattr(full, name)[2], equal_nan=True), name


def test_a_diverging_run_stops_alone():
    model = linear_model()
    net = network()
    _, z = simulate_linear(model, 3, 6, seed=2)
    z[1, 3] = 1e15  # one run's measurements beyond any finite estimate
    out = run_relay_batch(model, net, z, 2)
    res = out.detail
    assert res.violations[0] == res.violations[2] == []
    (v,) = res.violations[1]
    assert v["condition"] == "diverged" and v["step"] == 4
    assert np.isnan(res.x_post[1, 4:]).all() and np.isfinite(res.x_post[1, :4]).all()
    assert np.isfinite(res.x_post[[0, 2]]).all()
    assert out.diverged_step.tolist() == [-1, 4, -1]


def test_a_prediction_beyond_finite_numbers_stops_its_run_before_the_update():
    x = ca.SX.sym("x", 2)
    model = Model("blows up", x, ca.vertcat(0.9 * x[0], ca.exp(x[1]) - 1.0),
                  [Sensor(f"s{i}", x[0], Gaussian.zero_mean([[1.0]])) for i in range(N)],
                  Gaussian.zero_mean(0.01 * np.eye(2)), Gaussian([0.0, 0.0], np.eye(2)))
    res = run_relay_batch(model, network(), np.zeros((2, 4, N)), 2, x0=np.array([[0.0, 800.0], [0.0, 0.0]])).detail
    (v,) = res.violations[0]
    assert v["step"] == 1 and v["reason"].startswith("prediction") and np.isnan(res.x_post[0, 1:]).all()
    assert res.violations[1] == [] and np.isfinite(res.x_post[1]).all()


def test_bad_inputs_raise_input_errors_naming_the_parameter():
    model = linear_model()
    net = network(0.1, 0.1)
    _, z = simulate_linear(model, 2, 5, seed=0)
    att = edge_attacks(net, 2, 5, model.n_x, seed=0)
    with pytest.raises(InputError, match="hops"):
        run_relay_batch(model, net, z, 0, attacks=att, signal=SIGNAL)
    with pytest.raises(InputError, match="attacks"):
        run_relay_batch(model, net, z, 2, attacks=att._replace(dos=att.dos[:1]), signal=SIGNAL)
    with pytest.raises(InputError, match="attacks"):
        run_relay_batch(model, net, z, 2, attacks=att._replace(xi=att.xi[..., :1]), signal=SIGNAL)
    with pytest.raises(InputError, match="network"):
        run_relay_batch(model, SensorNetwork.from_edges(5, [(i, i + 1) for i in range(4)]), z, 2)
    with pytest.raises(InputError, match="signal"):
        run_relay_batch(model, net, z, 2, attacks=att)
    x = ca.SX.sym("x", 2)
    u = ca.SX.sym("u", 1)
    driven = Model("driven", x, ca.vertcat(x[0] + u[0], x[1]), [Sensor(f"s{i}", x[i % 2], Gaussian.zero_mean([[1.0]]))
                                                                for i in range(N)],
                   Gaussian.zero_mean(np.eye(2)), Gaussian([0.0, 0.0], np.eye(2)), u=u)
    with pytest.raises(InputError, match="inputs"):
        run_relay_batch(driven, network(), np.zeros((2, 5, N)), 2)
    with pytest.raises(InputError, match="inputs"):
        run_relay_batch(driven, network(), np.zeros((2, 5, N)), 2, inputs=np.zeros((5, 2)))
    with pytest.raises(InputError, match="z must"):
        run_relay_batch(model, net, z[..., :3], 2, attacks=att, signal=SIGNAL)


def test_the_gain_is_the_pseudo_inverse_formula_where_depths_are_rank_deficient():
    """relay_update (its active columns, its eigen-decomposition's cut) gives W = C Q⁺ and P⁺ = P - W Cᵀ with numpy's
    pseudo-inverse of the whole G n x G n Q (C and Q of update_moments' definitions written out here), over a batch
    with depths of fewer rows than states, a row repeated within a depth, a zero row and a row 1e4 x the others: the
    reference the C node's reduction to each depth's row basis is replayed against."""
    model = bearing_model()
    net = varied_network()
    rt = relay_routes(net, 3)
    signal = FDISignal(amplitude=(0.8, 0.5), components=(0, 1), law="constant")
    M, mu = signal.moment(4), signal.mean(4)
    rng = np.random.default_rng(5)
    checked = 0
    for i in range(N):
        mom = node_moments(rt, net, model.sensor_dims, i)
        r = mom.rows.size
        Hw = rng.normal(size=(3, r, 4))
        g = mom.groups.argmax(-1)
        same = [a for a in range(1, r) if g[a] == g[a - 1]]
        if same:
            Hw[:, same[0]] = 2.0 * Hw[:, same[0] - 1]  # a repeated direction within a depth
        Hw[1, r - 1] = 0.0  # a row that sees nothing at this point
        Hw[2, 0] *= 1e4
        A = rng.normal(size=(3, 4, 4))
        P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(4)
        W, Pn = relay_update(P, Hw, mom, M, mu)
        for b in range(3):
            _assert_pseudo_inverse_formula(W[b], Pn[b], P[b], Hw[b], mom, M, mu, (i, b))
            checked += 1
    assert checked == 3 * N


def _assert_pseudo_inverse_formula(W, Pn, P, Hw, mom, M, mu, where):
    """W = C Q⁺ and P⁺ = P - W Cᵀ with numpy's pseudo-inverse of the whole G n x G n Q, C and Q of update_moments'
    definitions written out (one item)."""
    from rules.relay.design import grouped

    Hg = grouped(Hw, mom.groups)
    K = np.diag(mom.p) + mom.F1 * (Hw @ M @ Hw.T) + mom.F2 * (Hw @ np.outer(mu, mu) @ Hw.T) + mom.A * (Hw @ P @ Hw.T)
    Q = Hg.T @ K @ Hg
    C = P @ Hw.T @ (mom.p[:, None] * Hg)
    Wr = C @ np.linalg.pinv(0.5 * (Q + Q.T), rcond=1e-12, hermitian=True)
    scale = np.abs(Wr).max()
    assert np.allclose(W, Wr, rtol=0, atol=1e-7 * scale), (where, np.abs(W - Wr).max() / scale)
    Pr = P - Wr @ C.T
    assert np.allclose(Pn, 0.5 * (Pr + Pr.T), rtol=0, atol=1e-9 * np.abs(P).max())


def test_the_update_in_the_balls_rows_and_in_qs_columns_are_the_same_formula(monkeypatch):
    """relay_update works in the ball's r rows (M = Lₛᵀ Ĥ Ĥᵀ Lₛ, r x r, the same nonzero eigenvalues as Q) where the
    rows are fewer than Q's G n columns and their weights S are positive definite, in Q's columns where they are
    not (a row that never arrives: p = 0) or where the rows are as many (a small state, many rows): each gives the
    pseudo-inverse formula, and the rows' way is taken exactly where it can be and pays.  In the rows, an item whose
    M is certified invertible is solved directly (K_r G0 = X S⁻¹); one with two rows of one depth along one
    direction (G0 singular) takes M's pseudo-inverse: both are seen, and both give the formula."""
    import rules.relay.design as rd

    model, net = bearing_model(), varied_network()
    rt = relay_routes(net, 3)
    signal = FDISignal(amplitude=(0.8, 0.5), components=(0, 1), law="constant")
    M, mu = signal.moment(4), signal.mean(4)
    rng = np.random.default_rng(6)
    taken, seen, direct = [], set(), []
    real = rd._row_space_update

    def spy(*a):
        out = real(*a)
        taken.append(out is not None)
        if out is not None:
            direct.extend(np.ravel(out[0].direct).tolist())
        return out

    monkeypatch.setattr(rd, "_row_space_update", spy)
    for i in range(N):
        mom = node_moments(rt, net, model.sensor_dims, i)
        r = mom.rows.size
        if r < 2:
            continue
        keep = (np.arange(r) != r - 1) * (np.arange(r) != r - 1)[:, None]  # the last row never arrives
        lost = mom._replace(p=np.where(np.arange(r) == r - 1, 0.0, mom.p), A=mom.A * keep, F1=mom.F1 * keep,
                            F2=mom.F2 * keep)
        fewer = r < mom.groups.shape[-1] * 4  # than Q's G n columns
        depth = mom.groups.argmax(axis=1)
        twice = [(a, b) for a in range(r) for b in range(a + 1, r) if depth[a] == depth[b]][:1]
        for m, way, repeat in ((mom, True, []), (mom, True, twice), (lost, False, [])):
            Hw = rng.normal(size=(2, r, 4))
            for a, b in repeat:  # one depth's two rows along one direction: G0 singular
                Hw[:, b] = -2.0 * Hw[:, a]
            A = rng.normal(size=(2, 4, 4))
            P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(4)
            taken.clear()
            W, Pn = relay_update(P, Hw, m, M, mu)
            assert taken == ([way] if fewer else []), (i, way, r)
            seen.add(way if fewer else "columns")
            for b in range(2):
                _assert_pseudo_inverse_formula(W[b], Pn[b], P[b], Hw[b], m, M, mu, (i, way, b))
        if fewer:  # its rows repeated (the same arrivals) until they are as many as Q's columns: Q's own way
            times = -(-mom.groups.shape[-1] * 4 // r)
            many = mom._replace(rows=np.tile(mom.rows, times), groups=np.tile(mom.groups, (times, 1)),
                                p=np.tile(mom.p, times), A=np.tile(mom.A, (times, times)),
                                F1=np.tile(mom.F1, (times, times)), F2=np.tile(mom.F2, (times, times)))
            Hw = rng.normal(size=(2, r * times, 4))
            taken.clear()
            W, Pn = relay_update(P, Hw, many, M, mu)
            assert taken == [], (i, r * times)
            seen.add("columns")
            for b in range(2):
                _assert_pseudo_inverse_formula(W[b], Pn[b], P[b], Hw[b], many, M, mu, (i, "many", b))
    assert {True, False, "columns"} <= seen, seen
    assert True in direct and False in direct, direct


def test_stacked_nodes_with_their_own_depths_update_as_each_alone():
    """relay_update over a stack whose items hold their depths at different rows (groups (k, r, G)): each item's
    gain and covariance are those it gets alone, and relay_information's too."""
    from rules.relay.design import relay_information

    model = bearing_model()
    net = varied_network()
    rt = relay_routes(net, 2)
    moms = [node_moments(rt, net, model.sensor_dims, i) for i in range(N)]
    r = moms[0].rows.size
    same = [m for m in moms if m.rows.size == r and not np.array_equal(m.groups, moms[0].groups)]
    assert same, "the network must give two nodes of the same rows at different depths"
    pair = [moms[0], same[0]]
    stacked = moms[0]._replace(**{f: np.stack([getattr(m, f) for m in pair]) for f in moms[0]._fields})
    rng = np.random.default_rng(2)
    Hw = rng.normal(size=(2, r, 4))
    A = rng.normal(size=(2, 4, 4))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(4)
    res = rng.normal(size=(2, r))
    M, mu = SIGNAL.moment(4), SIGNAL.mean(4)
    W, Pn = relay_update(P, Hw, stacked, M, mu)
    y = relay_information(Hw, stacked, res)
    for b, mom in enumerate(pair):
        Wb, Pb = relay_update(P[b], Hw[b], mom, M, mu)
        assert np.allclose(W[b], Wb, rtol=1e-12, atol=1e-14) and np.allclose(Pn[b], Pb, rtol=1e-12, atol=1e-14)
        assert np.allclose(y[b], relay_information(Hw[b], mom, res[b]), rtol=1e-12, atol=1e-14)


def test_a_depth_with_more_rows_than_columns_is_left_to_the_bases_as_its_factor_would_leave_it():
    """rules.relay.design._direct: a hop depth whose rows touch fewer columns than it has rows (two nodes of one
    depth reading one line's flow from its two ends) cannot be certified invertible; given the rows it says so for
    every item without trying the block's factor, the decision the factor's failure gives (without the rows), and
    the update through the bases is the pseudo-inverse formula."""
    import rules.relay.design as rd

    model, net = bearing_model(), varied_network()
    mom = next(m for m in (node_moments(relay_routes(net, 3), net, model.sensor_dims, i) for i in range(N))
               if np.bincount(m.groups.argmax(-1)).max() >= 3)
    r, depth = mom.rows.size, mom.groups.argmax(-1)
    g = np.bincount(depth).argmax()
    rows = np.flatnonzero(depth == g)
    rng = np.random.default_rng(9)
    Hw = rng.normal(size=(3, r, 4))
    Hw[:, rows, 2:] = 0.0  # the depth's rows on two columns
    Hw[:, rows[2:], :2] = rng.normal(size=(3, rows.size - 2, 2))
    A = rng.normal(size=(3, 4, 4))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(4)
    S = np.eye(r) + 0.1 * Hw @ P @ np.swapaxes(Hw, -1, -2)
    Li = np.linalg.inv(np.linalg.cholesky(S))
    G0 = (mom.groups @ mom.groups.T) * (Hw @ np.swapaxes(Hw, -1, -2))
    assert not rd._direct(S, Li, G0, mom.groups, rd.RTOL, rd._depth_columns(Hw, mom.groups)).any()
    assert not rd._direct(S, Li, G0, mom.groups, rd.RTOL).any()
    signal = FDISignal(amplitude=(0.8, 0.5), components=(0, 1), law="constant")
    M, mu = signal.moment(4), signal.mean(4)
    W, Pn = relay_update(P, Hw, mom, M, mu)
    for b in range(3):
        _assert_pseudo_inverse_formula(W[b], Pn[b], P[b], Hw[b], mom, M, mu, b)
