"""Flooding (``routing='flood'``, gain rule ``flood``): every node forwards the first copy of each measurement it
receives, from any neighbour, against independent references.

* the copies a node takes (:meth:`rules.relay.design.Routes.realise`) equal a plain breadth-first flood written here,
  round by round, over random channel outages; flooding never loses a measurement the tree delivers and never
  delivers one sooner than its hop distance;
* the Monte Carlo moments (:func:`rules.relay.design.flood_moments`) equal the same draws' moments computed here with
  each copy's set of falsified channels walked explicitly (Python sets), and on a graph that is a tree (one path
  per pair) they agree with the tree's closed form within the Monte Carlo's error;
* the filter: the batch equals the node-by-node, run-by-run loop of test_relay with the flood written here (DoS,
  FDI with non-zero ξ, a bearing and a two-dimensional sensor); on a linear model its expected covariance is the mean
  squared error of a Monte Carlo of the generative model, and that check rejects a flood filter designed with the
  tree's moments;
* the gain rule ``flood``: its filter behind the rule registry, its stationary certificate where the filter's
  covariance settles, ``cfdesign design --mode flood`` of a user's model file.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

import rules.relay.filter as relay_filter
import rules
from designer.design import DesignOptions, make_design
from designer.model import Model
from designer.network import SensorNetwork
from rules.relay.design import flood_moments, node_moments, relay_routes, relay_stationary
from designer.validation import InputError
from filters.consensus_batch import run_consensus_batch
from rules.relay.filter import run_relay_batch
from studies.cli import main
from test_relay import (N, SIGNAL, bearing_model, edge_attacks, linear_model, network,  # tests/ on the path
                        reference_relay, simulate_linear, varied_network)

GRID = [(a * 3 + b, a * 3 + b + 1) for a in range(3) for b in range(2)] + \
       [(a * 3 + b, (a + 1) * 3 + b) for a in range(2) for b in range(3)] + [(0, 4), (4, 8), (2, 4)]


def grid(dos=0.0, fdi=0.0) -> SensorNetwork:
    """Nine nodes on a 3 x 3 grid with three diagonals: many paths between two nodes."""
    return SensorNetwork.from_edges(9, GRID, dos_prob=dos, fdi_prob=fdi)


def channel_index(net: SensorNetwork) -> dict:
    receiver, sender = np.nonzero(net.adjacency)
    return {(int(j), int(i)): c for c, (i, j) in enumerate(zip(receiver, sender))}  # (sender, receiver) -> channel


def reference_flood(net: SensorNetwork, hops: int, up: np.ndarray, s: int) -> dict:
    """Node -> (round, sender) of the first copy of source s's measurement (up: the channels that deliver): round by
    round, a node not reached takes the copy of its lowest-numbered neighbour that was reached in the round before."""
    chan = channel_index(net)
    got = {s: (0, None)}
    for r in range(1, hops + 1):
        new = {}
        for i in range(net.n_nodes):
            if i in got:
                continue
            for j in sorted(net.neighbours[i]):
                if j in got and got[j][0] == r - 1 and up[chan[(j, i)]]:
                    new[i] = (r, j)
                    break
        got.update(new)
    return got


@pytest.mark.parametrize("hops", [1, 2, 4])
def test_the_copies_taken_are_a_breadth_first_flood(hops):
    net = grid(0.35)
    rt = relay_routes(net, hops, "flood")
    chan = channel_index(net)
    rng = np.random.default_rng(hops)
    up = rng.random((30, len(chan))) > 0.35
    rnd, parent, channel = rt.realise(up)
    pair_of = {(int(s), int(i)): p for p, (s, i) in enumerate(zip(rt.source, rt.node))}
    for a in range(up.shape[0]):
        for s in range(net.n_nodes):
            ref = reference_flood(net, hops, up[a], s)
            for i in range(net.n_nodes):
                if i == s or (s, i) not in pair_of:
                    assert i == s or i not in ref
                    continue
                p = pair_of[(s, i)]
                if i not in ref:
                    assert rnd[a, p] == 0 and parent[a, p] == -1 and channel[a, p] == -1
                    continue
                r, j = ref[i]
                assert rnd[a, p] == r and channel[a, p] == chan[(j, i)]
                assert parent[a, p] == (-1 if j == s else pair_of[(s, j)])
    assert (rnd > 0).mean() < 1.0  # some copies lost


def test_flooding_never_loses_what_the_tree_delivers_and_is_never_early():
    net = grid(0.3)
    tree, flood = relay_routes(net, 3), relay_routes(net, 3, "flood")
    assert np.array_equal(tree.source, flood.source) and np.array_equal(tree.node, flood.node)
    up = np.random.default_rng(1).random((500, tree.incidence.shape[1])) > 0.3
    rt, _, _ = tree.realise(up)
    rf, _, _ = flood.realise(up)
    assert np.all(rt[rt > 0] == np.broadcast_to(tree.depth, rt.shape)[rt > 0])  # the tree: at its depth or never
    assert np.all(rf[rt > 0] > 0) and np.all(rf[rf > 0] >= np.broadcast_to(flood.depth, rf.shape)[rf > 0])
    assert (rf > 0).mean() > (rt > 0).mean() + 0.05  # other paths deliver what the tree lost
    assert np.all(tree.arrival_prob(net) <= (rf > 0).mean(0) + 0.07)
    assert flood.values_per_step() > tree.values_per_step() == tree.n_pairs
    with pytest.raises(InputError, match="no closed form"):
        flood.arrival_moments(net, 0)
    with pytest.raises(InputError, match="up must be"):
        flood.realise(up[:, 1:])


def explicit_moments(rt, net: SensorNetwork, u: np.ndarray, i: int):
    """Node i's (p, A, F1, F2) over draws u (samples, channels) of the channels, each copy's falsified channels
    walked back through the parents as a Python set."""
    dos = net.dos_prob[net.adjacency]
    fdi = net.fdi_prob[net.adjacency]  # np.nonzero(adjacency) order, as the channels
    lost = u < dos
    fals = ~lost & (u < dos + fdi)
    rnd, parent, channel = rt.realise(~lost)
    pairs = np.flatnonzero(rt.node == i)
    m = pairs.size + 1
    sums = {k: np.zeros((m, m)) for k in ("A", "F1", "F2")}
    p = np.zeros(m)
    for w in range(u.shape[0]):
        gamma = np.ones(m)
        sets = [set()]
        for q in pairs:
            gamma[len(sets)] = rnd[w, q] > 0
            S, c = set(), q
            while c >= 0 and rnd[w, q] > 0:
                if fals[w, channel[w, c]]:
                    S.add(int(channel[w, c]))
                c = parent[w, c]
            sets.append(S)
        p += gamma
        for a in range(m):
            for b in range(m):
                both = gamma[a] * gamma[b]
                shared = len(sets[a] & sets[b])
                sums["A"][a, b] += both
                sums["F1"][a, b] += both * shared
                sums["F2"][a, b] += both * (len(sets[a]) * len(sets[b]) - shared)
    n = u.shape[0]
    return p / n, sums["A"] / n, sums["F1"] / n, sums["F2"] / n


def test_flood_moments_are_the_draws_moments_with_explicit_falsified_sets():
    net = grid(0.25, 0.2)
    rt = relay_routes(net, 3, "flood")
    samples = 700
    got = flood_moments(rt, net, np.random.default_rng(5), samples)
    u = np.random.default_rng(5).random((samples, rt.incidence.shape[1]))  # the same draws, in one call
    for i in (0, 4, 7):
        ref = explicit_moments(rt, net, u, i)
        for name, a, b in zip(("p", "A", "F1", "F2"), got[i], ref):
            assert np.allclose(a, b, rtol=0, atol=1e-12), (i, name)
        assert ref[2].max() > 0.05 and ref[3].max() > 0.0  # falsified copies, some sharing channels


def test_on_a_tree_graph_flooding_is_the_tree_and_its_moments_its_closed_form():
    edges = [(0, 1), (1, 2), (2, 3), (1, 4), (4, 5)]  # a tree: one path between any two nodes
    net = SensorNetwork.from_edges(6, edges, dos_prob=0.2, fdi_prob=0.15)
    tree, flood = relay_routes(net, 3), relay_routes(net, 3, "flood")
    up = np.random.default_rng(2).random((300, tree.incidence.shape[1])) > 0.2
    assert np.array_equal(tree.realise(up)[0], flood.realise(up)[0])
    samples = 20000
    got = flood_moments(flood, net, np.random.default_rng(8), samples)
    for i in range(6):
        for name, a, b in zip(("p", "A", "F1", "F2"), got[i], tree.arrival_moments(net, i)):
            se = np.sqrt(np.maximum(b * (1 - np.minimum(b, 1)), 1e-4) / samples)  # a Bernoulli mean's error, at least
            assert np.all(np.abs(a - b) <= 5 * se + 1e-12), (i, name, np.max(np.abs(a - b) / se))


# --------------------------------------------------------------------------- the filter
def flood_copies(model: Model, net: SensorNetwork, rt, zk, dos, fdi, xi, xp, k: int) -> dict:
    """test_relay.tree_copies for flooding: the values that arrived, each source's copies spread by reference_flood,
    a falsified channel adding H_s(x̂⁻ of its sender) ξ to what it carries."""
    chan = channel_index(net)
    offsets = np.concatenate([[0], np.cumsum(model.sensor_dims)])
    values = {}
    for s in range(net.n_nodes):
        got = reference_flood(net, rt.hops, ~dos, s)
        values[(s, s)] = zk[offsets[s]:offsets[s + 1]].copy()
        for d in range(1, rt.hops + 1):
            for i, (rd, j) in got.items():
                if rd == d:
                    c = chan[(j, i)]
                    v = values[(s, j)]
                    values[(s, i)] = v + model.H(s, xp[j], k + 1) @ xi[c] if fdi[c] else v
    return values


def test_the_flood_filter_equals_the_node_by_node_reference():
    model = bearing_model()
    net = network(0.25, 0.25)
    runs, steps = 3, 6
    rng = np.random.default_rng(3)
    z = np.stack([model.h_all(model.prior.mean) + rng.normal(0, 0.2, (steps, model.n_z)) for _ in range(runs)])
    att = edge_attacks(net, runs, steps, model.n_x, seed=6)
    res = run_relay_batch(model, net, z, 3, attacks=att, signal=SIGNAL, routing="flood").detail
    xs, Ps = reference_relay(model, net, z, 3, att, SIGNAL, "flood", flood_copies)
    assert res.violations == [[], [], []]
    assert np.allclose(res.x_post, xs, rtol=0, atol=1e-10)
    assert np.allclose(res.P_post, Ps, rtol=0, atol=1e-10)
    tree = run_relay_batch(model, net, z, 3, attacks=att, signal=SIGNAL).detail
    assert not np.allclose(tree.x_post, res.x_post)  # the copies taken differ from the tree's


def tree_moments(routes, net, dims, rng=None):
    """A wrong relay_moments for flooding: the tree's closed form (the arrivals of one fixed path; the same pairs)."""
    tree = relay_routes(net, routes.hops)
    return [node_moments(tree, net, dims, i) for i in range(routes.n_nodes)]


@pytest.mark.slow
def test_the_expected_covariance_matches_a_monte_carlo_and_the_check_has_power(monkeypatch):
    model = linear_model()
    ring = SensorNetwork.from_edges(N, [(i, (i + 1) % N) for i in range(N)] + [(0, 3)], dos_prob=0.45, fdi_prob=0.2)

    def mse_over_bound(runs=2000, steps=15, seed=31):
        truth, z = simulate_linear(model, runs, steps, seed)
        att = edge_attacks(ring, runs, steps, model.n_x, seed=seed + 1)
        res = run_relay_batch(model, ring, z, 3, attacks=att, signal=SIGNAL, routing="flood").detail
        e2 = ((res.x_post[:, 1:] - truth[:, 1:, None]) ** 2).sum(-1).sum(1)  # (runs, N)
        ratio = e2 / np.trace(res.P_post[:, 1:], axis1=-2, axis2=-1).sum(1)
        return ratio.mean(0), ratio.std(0, ddof=1) / np.sqrt(runs)

    mean, se = mse_over_bound()
    assert np.all(np.abs(mean - 1.0) < 4 * se + 0.01), (mean, se)  # 0.01: the moments' own Monte Carlo error
    monkeypatch.setattr(relay_filter, "relay_moments", tree_moments)
    mean, se = mse_over_bound()
    assert np.any(np.abs(mean - 1.0) > 4 * se + 0.01), (mean, se)


# --------------------------------------------------------------------------- the gain rule
def flood_design(model, net, hops):
    return make_design(model, net, rule=rules.get("flood"), delta=0.0, options=DesignOptions(mode="flood", rounds=hops),
                       x0=model.prior.mean, signal=SIGNAL)


def test_the_rules_filter_is_the_flood_filter_and_its_certificate_where_it_settles():
    assert rules.get("flood").relays and rules.get("flood").routing == "flood" and rules.get("flood").deployable
    model = linear_model()
    net = varied_network()
    design = flood_design(model, net, 2)
    assert design.exchange == "relay" and design.rounds == 2
    _, z = simulate_linear(model, 2, 30, seed=4)
    att = edge_attacks(net, 2, 30, model.n_x, seed=9)
    got = run_consensus_batch(model, net, z, design, attacks=att).detail
    ref = run_relay_batch(model, net, z, 2, attacks=att, signal=SIGNAL, routing="flood").detail
    assert np.array_equal(got.x_post, ref.x_post) and np.array_equal(got.phi_post, ref.P_post)
    cert = relay_stationary(model, net, design, x=np.zeros(model.n_x))
    assert cert.converged and cert.lmi["status"] == "optimal"
    # a linear model: the expected covariance recursion depends on neither the measurements nor the draws
    settled = run_relay_batch(model, net, np.zeros((1, 300, model.n_z)), 2, signal=SIGNAL, routing="flood").detail
    assert np.allclose(settled.P_post[0, -1], cert.Phi, rtol=1e-7, atol=1e-10)
    with pytest.raises(InputError, match="routes must be the design's"):
        relay_stationary(model, net, design, x=np.zeros(model.n_x), routes=relay_routes(net, 2))
    tree = relay_stationary(model, net, design._replace(rule=rules.get("relay")), x=np.zeros(model.n_x))
    assert np.trace(cert.Phi, axis1=-2, axis2=-1).mean() < np.trace(tree.Phi, axis1=-2, axis2=-1).mean()


USER_MODEL = '''"""Five range(-bearing) posts around a slow target, on a ring with one chord (a user's file)."""
import casadi as ca
import numpy as np
from designer import AttackSpec, FDISignal, Gaussian, Model, Sensor, SensorNetwork

STEPS = 25
X0 = [9.0, 11.0, 0.05, -0.02]
POSTS = [(0.0, 0.0), (20.0, 0.0), (20.0, 20.0), (0.0, 20.0), (10.0, 30.0)]
NETWORK = SensorNetwork.from_edges(5, [(0, 1), (1, 2), (2, 3), (3, 4), (4, 0), (1, 3)])
ATTACKS = AttackSpec(dos=0.3, fdi=0.05, signal=FDISignal(amplitude=0.5, components=(0, 1)))


def model():
    x = ca.SX.sym("x", 4)
    sensors = []
    for i, (a, b) in enumerate(POSTS):
        r = ca.sqrt((x[0] - a) ** 2 + (x[1] - b) ** 2)
        if i % 2:
            sensors.append(Sensor(f"post{i}", ca.vertcat(r, ca.atan2(x[1] - b, x[0] - a)),
                                  Gaussian.zero_mean(np.diag([0.3, 0.003])), angles=(1,)))
        else:
            sensors.append(Sensor(f"post{i}", r, Gaussian.zero_mean([[0.4]])))
    return Model("posts", x, ca.vertcat(x[0] + x[2], x[1] + x[3], x[2], x[3]), sensors,
                 Gaussian.zero_mean(np.diag([0.001, 0.001, 0.002, 0.002])),
                 Gaussian(X0, np.diag([1.0, 1.0, 0.01, 0.01])), position_index=(0, 1))
'''


def test_flood_design_of_a_users_model_file(tmp_path, capsys):
    path = tmp_path / "posts.py"
    path.write_text(USER_MODEL)
    out = tmp_path / "design"
    code = main(["design", str(path), "--mode", "flood", "--rounds", "2", "--seed", "3", "--out", str(out)])
    err = capsys.readouterr().err
    rec = json.loads((out / "schedule.json").read_text())
    assert rec["gain_rule"]["name"] == "flood" and rec["gain_rule"]["runtime"] == "local", err
    assert rec["exchange"] == "relay" and rec["rounds"] == 2 and rec["feasible"]
    assert code in (0, 1) and (code == 0) == rec["certified"]
    rows = rec["rounds_tradeoff"]["rows"]
    assert [r["rounds"] for r in rows] == [1, 2] and all(r["messages_per_step"] == 2 * 6 * r["rounds"] for r in rows)
    net = SensorNetwork.from_edges(5, [(0, 1), (1, 2), (2, 3), (3, 4), (4, 0), (1, 3)])
    assert rows[1]["values_per_step"] == relay_routes(net, 2, "flood").values_per_step() > relay_routes(
        net, 2).values_per_step()
