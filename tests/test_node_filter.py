"""Node filters (filters.node, studies.node_filter): the filter one node runs, a step at a time, with what it has.

Driven over a run they give the study's numbers bit for bit; a node that receives every measurement of a linear
model is the centralized Kalman filter (FilterPy); what a node cannot run is refused, saying why."""
from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

import studies
from designer import AttackSpec, Gaussian, Model, Sensor, SensorNetwork
from designer.validation import InputError
from test_recorded import USER_MODEL  # noqa: E402 (tests/ is on the path: the user's cart with posts)


@pytest.fixture(scope="module")
def cart(tmp_path_factory):
    path = tmp_path_factory.mktemp("user") / "cart.py"
    path.write_text(USER_MODEL)
    return path


@pytest.mark.parametrize("target, mode", [("indoor-robot", "relay"), ("indoor-robot", "flood"),
                                          ("user", "flood"), ("user", "relay")])
@pytest.mark.slow
def test_node_filters_driven_over_a_run_give_the_studys_numbers(target, mode, cart, tmp_path):
    """Run 1 of the comparison (seed 4) as a log: every node's filter stepped with what reached it gives the estimates
    and bounds of cfdesign filter (the study's batched filter), bit for bit, under DoS and FDI (the robot with
    inputs; the user's cart with inputs and bearings)."""
    scenario = str(cart) if target == "user" else target
    sim = studies.simulate(scenario, seed=4, run=1, out=tmp_path / "log.npz")
    assert sim.attacks.dos.any() and sim.attacks.fdi.any()
    ref = studies.filter(scenario, tmp_path / "log.npz", filter=mode)
    net = studies.node_filter(scenario, mode=mode)
    x, P = net.run(sim.z, sim.attacks, sim.inputs)
    assert np.array_equal(x, ref.x_hat) and np.array_equal(P, ref.cov)
    # one node alone, fed by hand what the network delivered to it, is the same node
    one = studies.node_filter(scenario, mode=mode, node=2)
    again = studies.node_filter(scenario, mode=mode)
    for k in range(sim.z.shape[0]):
        before = [nd.k for nd in again.nodes]
        delivered = _delivered(again, k, sim)
        one.step(*delivered[2], u=sim.inputs[k])
        assert before == [k] * len(again.nodes)
        assert np.array_equal(one.x, x[k + 1, 2]) and np.array_equal(one.P, P[k + 1, 2])


def _delivered(net, k, sim):
    """What the network ``net`` delivers to each node at step ``k`` of ``sim``, (z, received) per node, then the
    network steps."""
    from filters.consensus_batch import EdgeAttacks

    att = EdgeAttacks.from_patterns(net.network, [sim.attacks])
    e = (att.dos[0, k], att.fdi[0, k], att.xi[0, k])
    got = net.deliver(sim.z[k], *e, u=sim.inputs[k])
    net.step(sim.z[k], *e, u=sim.inputs[k])
    return got


def _line_model():
    import casadi as ca

    x = ca.SX.sym("x", 2)
    sensors = [Sensor(f"s{i}", x[0] + 0.1 * i * x[1], Gaussian.zero_mean([[0.2 + 0.1 * i]])) for i in range(4)]
    return Model("line", x, ca.vertcat(x[0] + x[1], 0.95 * x[1]), sensors,
                 Gaussian.zero_mean(np.diag([0.01, 0.02])), Gaussian([1.0, 0.5], np.diag([2.0, 1.0])))


def test_a_node_that_receives_every_measurement_is_the_centralized_kalman_filter():
    """No attack, rounds >= the diameter: the relay rule's update with every measurement is the Kalman filter on all
    sensors (FilterPy's, an independent implementation), at every step."""
    m = _line_model()
    net = SensorNetwork.from_edges(4, [(0, 1), (1, 2), (2, 3)])
    node = studies.node_filter(m, network=net, attacks=AttackSpec(dos=0.0, fdi=0.0), mode="relay", node=0)
    assert node.ball.tolist()[0] == 0 and sorted(node.ball.tolist()) == [0, 1, 2, 3]
    kf = KalmanFilter(dim_x=2, dim_z=4)
    kf.x, kf.P = np.array([1.0, 0.5]), np.diag([2.0, 1.0])
    kf.F, kf.Q = np.array([[1.0, 1.0], [0.0, 0.95]]), np.diag([0.01, 0.02])
    kf.H = np.array([[1.0, 0.1 * i] for i in range(4)])
    kf.R = np.diag([0.2 + 0.1 * i for i in range(4)])
    rng = np.random.default_rng(8)
    for _ in range(25):
        z = rng.normal(size=4) * 2.0
        kf.predict()
        kf.update(z)
        node.step(z[:1], {s: z[s:s + 1] for s in (1, 2, 3)})
        assert np.allclose(node.x, kf.x, rtol=1e-9, atol=1e-12) and np.allclose(node.P, kf.P, rtol=1e-9, atol=1e-14)


@pytest.mark.slow
def test_what_a_node_filter_cannot_take_is_refused(cart):
    node = studies.node_filter(str(cart), mode="flood", node=1)
    with pytest.raises(InputError, match=r"z of node 1 at step 0 must be 1 finite number, got \[1.0, 2.0\]"):
        node.step([1.0, 2.0], {})
    with pytest.raises(InputError, match=r"received\[3\] of node 1 at step 0 must be 1 finite number"):
        node.step([0.3], {3: [1.0, 2.0]}, u=[0.0])
    from designer.design import DesignOptions
    from filters.node import node_filter
    from studies.consensus_design import consensus_design
    from studies.scenarios import load_scenario

    sc = load_scenario(str(cart))
    near = node_filter(sc.model, sc.network, consensus_design(sc, DesignOptions(mode="flood", rounds=1)), 1)
    assert near.ball.tolist() == [1, 0, 2, 6]  # itself, then its neighbours
    with pytest.raises(InputError, match=r"received of node 1 at step 0 holds sensor 4, which is not in node 1's "
                                         r"ball .*\[0, 2, 6\]"):
        near.step([0.3], {4: [1.0]}, u=[0.0])
    with pytest.raises(InputError, match="an oracle"):
        studies.node_filter(str(cart), mode="mse", node=0)
    import rules

    for rule in rules.all_rules().values():  # every rule a node can run has a node filter and its network
        if rule.deployable:
            assert all(isinstance(c, type) for c in rule.node_filter())
        else:
            with pytest.raises(InputError, match="an oracle"):
                rule.node_filter()
    with pytest.raises(InputError, match="give a design directory"):
        studies.node_filter(str(cart))
    with pytest.raises(InputError, match=r"node must be an integer in 0..6, got 7"):
        studies.node_filter(str(cart), mode="relay", node=7)


@pytest.mark.parametrize("target, mode, gate", [("indoor-robot", "paper", 0.0),
                                                pytest.param("indoor-robot", "tuned", 0.0, marks=pytest.mark.slow),
                                                ("indoor-robot", "paper", 0.05), ("user", "paper", 0.0),
                                                pytest.param("user", "tuned", 0.05, marks=pytest.mark.slow)])
def test_consensus_node_filters_driven_over_a_run_give_the_studys_numbers(target, mode, gate, cart, tmp_path):
    """The two-phase consensus nodes (paper, tuned, with and without the χ² gate), every node predicting, the packets
    crossing the channels (DoS, FDI) and every node updating with what reached it: the batched filter's estimates and
    bounds bit for bit (run 1 of the comparison, seed 4); one node fed by hand its packets is that node."""
    from designer.design import DesignOptions
    from filters.consensus_batch import EdgeAttacks, run_consensus_batch
    from filters.node import node_filter, node_network
    from studies.consensus_design import consensus_design
    from studies.scenarios import load_scenario

    sc = load_scenario(str(cart) if target == "user" else target)
    sim = studies.simulate(sc, seed=4, run=1)
    assert sim.attacks.dos.any() and sim.attacks.fdi.any()
    small = dict(sigma=0.004, beta=0.0002) if target == "user" and mode == "paper" else {}  # (28), (29) at step 0
    design = consensus_design(sc, DesignOptions(mode=mode, gate=gate, **small))
    ref = run_consensus_batch(sc.model, sc.network, sim.z[None], design, inputs=sim.inputs,
                              attacks=[sim.attacks]).detail
    x, P = node_network(sc.model, sc.network, design).run(sim.z, sim.attacks, sim.inputs)
    finite = int(np.isfinite(ref.x_post[0]).all(axis=(1, 2)).sum())  # both rules diverge on the cart (paper at
    assert finite == x.shape[0] if target != "user" else 3 <= finite < x.shape[0]  # once): the network stops as well
    assert np.array_equal(x, ref.x_post[0], equal_nan=True) and np.array_equal(P, ref.phi_post[0], equal_nan=True)
    net = node_network(sc.model, sc.network, design)
    i = 3
    one = node_filter(sc.model, sc.network, design, i)
    att = EdgeAttacks.from_patterns(sc.network, [sim.attacks])
    offsets = np.concatenate([[0], np.cumsum(sc.model.sensor_dims)])
    valid = []
    for k in range(finite - 1):
        sent = [nd.predict(sim.inputs[k]) for nd in net.nodes]
        mine = one.predict(sim.inputs[k])
        assert np.array_equal(mine.x, sent[i].x) and np.array_equal(mine.P, sent[i].P)
        got = {}
        for edge in np.flatnonzero(att.receiver == i):  # by hand: what arrived, as it arrived
            j = int(att.sender[edge])
            if not att.dos[0, k, edge]:
                got[j] = sent[j].x + att.xi[0, k, edge] if att.fdi[0, k, edge] else sent[j].x
        delivered = net.deliver(sent, att.dos[0, k], att.fdi[0, k], att.xi[0, k])
        assert sorted(got) == sorted(delivered[i][0]) and all(np.array_equal(got[j], delivered[i][0][j]) for j in got)
        one.update(sim.z[k, offsets[i]:offsets[i + 1]], got, {j: sent[j] for j in one.senders.tolist()})
        for nd, (received, bounds) in zip(net.nodes, delivered):
            nd.update(sim.z[k, offsets[nd.node]:offsets[nd.node + 1]], received, bounds)
        assert np.array_equal(one.x, x[k + 1, i]) and np.array_equal(one.P, P[k + 1, i])
        valid.append(one.valid)
    assert valid == ref.valid[0, 1:finite, i].tolist()


def test_a_consensus_node_checks_its_phases_and_packets(cart):
    node = studies.node_filter(str(cart), mode="paper", node=1)
    with pytest.raises(InputError, match="node 1 must predict step 0 before its update"):
        node.update([0.3], {}, {})
    packet = node.predict([0.0])
    with pytest.raises(InputError, match="node 1 has predicted step 0 already"):
        node.predict([0.0])
    assert node.senders.tolist() == [0, 2, 6]
    with pytest.raises(InputError, match=r"bounds of node 1 at step 0 must hold every in-neighbour's packet "
                                         r"\(node 1: \[0, 2, 6\]\), missing 2"):
        node.update([0.3], {}, {0: packet, 6: packet})
    with pytest.raises(InputError, match=r"received of node 1 at step 0 holds node 4, which is not an in-neighbour "
                                         r"of node 1"):
        node.update([0.3], {4: packet.x}, {j: packet for j in (0, 2, 6)})
    with pytest.raises(InputError, match=r"beta must satisfy \(29\) at the first step: beta < 1/lambda_max"
                                         r"\(Phi_1\|0\) = 0.00612902 at node 1, got 0.1"):  # the batch's words
        node.update([0.3], {0: packet.x}, {j: packet for j in (0, 2, 6)})


@pytest.mark.parametrize("target, name, rounds", [("indoor-robot", "kcf", 1), ("indoor-robot", "local", 1),
                                                  ("indoor-robot", "hcmci", 3), ("user", "kcf", 1),
                                                  ("user", "local", 1), ("user", "hcmci", 2)])
def test_baselines_node_filters_by_name_give_the_studys_numbers(target, name, rounds, cart, tmp_path):
    """KCF (two phases: predict with the node's measurement -> its packet, update with the packets that arrived),
    HCMCI (predict, then its L consensus rounds, each with what arrived) and the local EKFs (every node alone) by the
    comparison's short names: over run 1 of the comparison (seed 4), the study's numbers bit for bit (cfdesign
    filter on the log, HCMCI with L rounds); one KCF node fed by hand what arrived is that node."""
    from filters.consensus_batch import EdgeAttacks

    scenario = str(cart) if target == "user" else target
    sim = studies.simulate(scenario, seed=4, run=1, out=tmp_path / "log.npz")
    given = {"iterations": rounds} if name == "hcmci" else {}  # HCMCI's only: refused for another filter
    ref = studies.filter(scenario, tmp_path / "log.npz", filter=name, **given)
    net = studies.node_filter(scenario, filter=name, **given)
    x, P = net.run(sim.z, sim.attacks, sim.inputs)
    assert np.isfinite(ref.x_hat).all() and np.array_equal(x, ref.x_hat) and np.array_equal(P, ref.cov)
    if name == "hcmci":
        assert all(nd.rounds == rounds for nd in net.nodes)
        return
    if name != "kcf":
        assert all(nd.senders.size == 0 for nd in net.nodes)  # alone: nothing to receive
        return
    i = 2
    one, again = studies.node_filter(scenario, filter="kcf", node=i), studies.node_filter(scenario, filter="kcf")
    att = EdgeAttacks.from_patterns(again.network, [sim.attacks])
    offsets = np.concatenate([[0], np.cumsum(again.model.sensor_dims)])
    for k in range(sim.z.shape[0]):
        sent = [nd.predict(sim.z[k, offsets[j]:offsets[j + 1]], sim.inputs[k]) for j, nd in enumerate(again.nodes)]
        mine = one.predict(sim.z[k, offsets[i]:offsets[i + 1]], sim.inputs[k])
        assert all(np.array_equal(a, b) for a, b in zip(mine, sent[i]))
        got = {}
        for edge in np.flatnonzero(att.receiver == i):  # by hand: u + U ξ and x + ξ where falsified
            j, p = int(att.sender[edge]), sent[int(att.sender[edge])]
            if not att.dos[0, k, edge]:
                xi = att.xi[0, k, edge]
                got[j] = (p._replace(u=p.u + p.L.T @ (p.L @ xi), x=p.x + xi) if att.fdi[0, k, edge] else p)
        delivered = again.deliver(sent, att.dos[0, k], att.fdi[0, k], att.xi[0, k])
        assert sorted(got) == sorted(delivered[i])
        assert all(np.allclose(a, b, rtol=1e-12, atol=0) for j in got for a, b in zip(got[j], delivered[i][j]))
        one.update(delivered[i])
        for nd, given in zip(again.nodes, delivered):
            nd.update(given)
        assert np.array_equal(one.x, x[k + 1, i]) and np.array_equal(one.P, P[k + 1, i])


def test_a_filter_without_node_filter_is_refused_by_name(cart):
    with pytest.raises(InputError, match=r"filter 'centralized EKF \(trusts every packet\)' has no node filter "
                                         r"\(filters with one: .*KCF, .*HCMCI"):
        studies.node_filter(str(cart), filter="centralized-ekf")
    with pytest.raises(InputError, match="give a design directory .schedule., a gain rule .mode. or a filter's name"):
        studies.node_filter(str(cart), filter="kcf", mode="paper")
    node = studies.node_filter(str(cart), filter="kcf", node=1)
    with pytest.raises(InputError, match="node 1 must predict step 0 before its update"):
        node.update({})
    node.predict([0.3], [0.0])
    with pytest.raises(InputError, match=r"received of node 1 at step 0 holds node 4, which is not an in-neighbour "
                                         r"of node 1 \[0, 2, 6\]"):
        node.update({4: None})
    hc = studies.node_filter(str(cart), filter="hcmci", iterations=2, node=1)
    with pytest.raises(InputError, match="node 1 must predict step 0 before its rounds"):
        hc.round({})
    first = hc.predict([0.3], [0.0])
    second = hc.round({0: first})
    with pytest.raises(InputError, match="round 2 of node 1 at step 0 must hear the neighbours of its first round"):
        hc.round({0: second, 2: second})
    assert hc.round({0: second}) is None and hc.k == 1


@pytest.mark.parametrize("target, options", [("indoor-robot", {}), ("indoor-robot", {"rounds": 3,
                                                                                   "exchange": "predictions"}),
                                             ("user", {"rounds": 2, "bank": 2})])
def test_scheduled_node_filters_driven_over_a_run_give_the_studys_numbers(target, options, cart):
    """The scheduled design's nodes (its tables; the neighbours' measurements exchanged or not, 1-3 exchange rounds,
    a bank of operating points): every node predicting, the packets crossing the channels (DoS; FDI on estimates
    and, with exchange, on measurements through H_j at the sender's prediction), first round and rounds 2..L: the
    batched filter's estimates and own covariances bit for bit; one node fed by hand what arrived is that node."""
    from designer.design import DesignOptions
    from filters.consensus_batch import EdgeAttacks, run_consensus_batch
    from filters.node import node_filter, node_network
    from studies.consensus_design import consensus_design
    from studies.scenarios import load_scenario

    sc = load_scenario(str(cart) if target == "user" else target)
    sim = studies.simulate(sc, seed=4, run=1)
    design = consensus_design(sc, DesignOptions(mode="scheduled", **options))
    ref = run_consensus_batch(sc.model, sc.network, sim.z[None], design, inputs=sim.inputs,
                              attacks=[sim.attacks]).detail
    net = node_network(sc.model, sc.network, design)
    x, P = net.run(sim.z, sim.attacks, sim.inputs)
    assert np.isfinite(ref.x_post).all() and np.array_equal(x, ref.x_post[0])
    assert np.array_equal(np.trace(P, axis1=-2, axis2=-1), ref.predicted_mse[0])
    i, m = 4, sc.model
    one, again = node_filter(m, sc.network, design, i), node_network(m, sc.network, design)
    assert one.rounds == options.get("rounds", 1)
    att = EdgeAttacks.from_patterns(sc.network, [sim.attacks])
    offsets = np.concatenate([[0], np.cumsum(m.sensor_dims)])
    for k in range(sim.z.shape[0]):
        e = (att.dos[0, k], att.fdi[0, k], att.xi[0, k])
        sent = [nd.predict(sim.z[k, offsets[j]:offsets[j + 1]], sim.inputs[k]) for j, nd in enumerate(again.nodes)]
        one.predict(sim.z[k, offsets[i]:offsets[i + 1]], sim.inputs[k])
        delivered = again.deliver(sent, *e)
        for edge in np.flatnonzero(att.receiver == i):  # by hand: what arrived, as it arrived
            j = int(att.sender[edge])
            assert (j in delivered[i]) == (not att.dos[0, k, edge])
            if j in delivered[i] and att.fdi[0, k, edge]:
                assert np.allclose(delivered[i][j].x, sent[j].x + att.xi[0, k, edge], rtol=1e-13, atol=0)
        one.update(delivered[i])
        for nd, got in zip(again.nodes, delivered):
            nd.update(got)
        for _ in range(2, one.rounds + 1):
            delivered = again.deliver([nd.x for nd in again.nodes], *e)
            one.round(delivered[i])
            for nd, got in zip(again.nodes, delivered):
                nd.round(got)
        assert np.array_equal(one.x, x[k + 1, i]) and np.array_equal(one.P, P[k + 1, i])
        assert np.array_equal(one.bound, ref.phi_post[0, k + 1, i], equal_nan=True)


def test_a_scheduled_node_keeps_its_phases(cart):
    node = studies.node_filter(str(cart), mode="scheduled", node=1)
    with pytest.raises(InputError, match="node 1 is at its predict of step 0, not its update"):
        node.update({})
    with pytest.raises(InputError, match="not an exchange round"):
        node.round({})
    packet = node.predict([0.3], [0.0])
    with pytest.raises(InputError, match=r"received of node 1 at step 0 holds node 4, which is not an in-neighbour "
                                         r"of node 1 \[0, 2, 6\]"):
        node.update({4: packet})
    node.update({0: packet})
    assert node.k == 1 and np.isfinite(node.x).all()


@pytest.mark.parametrize("mode", ["relay", "flood"])
def test_a_relay_network_stops_where_the_batch_stops_its_run(mode, tmp_path):
    """A measurement beyond any finite estimate (1e300 at step 6) makes the batched relay filter stop the run (NaN
    from there on); the node network stops there too (``stopped``) and gives the batch's numbers bit for bit, NaN
    included, instead of feeding its neighbours packets they would refuse."""
    sim = studies.simulate("indoor-robot", seed=4, run=1, out=tmp_path / "log.npz")
    with np.load(tmp_path / "log.npz") as f:
        arrays = {k: f[k] for k in f.files}
    for key in ("z", "uplink"):
        if key in arrays:
            arrays[key] = arrays[key].copy()
            arrays[key][5, 0] = 1e300
    np.savez(tmp_path / "bad.npz", **arrays)
    ref = studies.filter("indoor-robot", tmp_path / "bad.npz", filter=mode)
    finite = np.isfinite(ref.x_hat).all(axis=(1, 2))
    assert 0 < finite.sum() < finite.size  # the batch stopped the run
    net = studies.node_filter("indoor-robot", mode=mode)
    x, P = net.run(arrays["z"], sim.attacks, sim.inputs)
    assert net.stopped
    assert np.array_equal(x, ref.x_hat, equal_nan=True) and np.array_equal(P, ref.cov, equal_nan=True)
