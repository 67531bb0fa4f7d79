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


def test_what_a_node_filter_cannot_take_is_refused(cart):
    node = studies.node_filter(str(cart), mode="flood", node=1)
    with pytest.raises(InputError, match=r"z must be node 1's measurement \(1 components\)"):
        node.step([1.0, 2.0], {})
    with pytest.raises(InputError, match=r"received\[3\] must be sensor 3's measurement \(1 components\)"):
        node.step([0.3], {3: [1.0, 2.0]}, u=[0.0])
    from designer.design import DesignOptions
    from filters.node import node_filter
    from studies.consensus_design import consensus_design
    from studies.scenarios import load_scenario

    sc = load_scenario(str(cart))
    near = node_filter(sc.model, sc.network, consensus_design(sc, DesignOptions(mode="flood", rounds=1)), 1)
    assert near.ball.tolist() == [1, 0, 2, 6]  # itself, then its neighbours
    with pytest.raises(InputError, match=r"received holds sensor 4, which is not in node 1's ball \[0, 2, 6\]"):
        near.step([0.3], {4: [1.0]}, u=[0.0])
    with pytest.raises(InputError, match="an oracle"):
        studies.node_filter(str(cart), mode="mse", node=0)
    with pytest.raises(InputError, match=r"gain rule 'scheduled' has no node filter yet \(node filters: relay, "
                                         r"flood\)"):
        studies.node_filter(str(cart), mode="scheduled")
    with pytest.raises(InputError, match="give a design directory"):
        studies.node_filter(str(cart))
    with pytest.raises(InputError, match=r"node must be an integer in 0..6, got 7"):
        studies.node_filter(str(cart), mode="relay", node=7)
