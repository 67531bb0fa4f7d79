"""What a node filter is given by hand is checked (filters.node.NodeInputs): a refusal is an InputError naming the
argument, the node and the step, and leaves the node as it was: the calls after it give, bit for bit, what a node
that never saw the refused call gives."""
from __future__ import annotations

import numpy as np
import pytest

import studies
from designer.validation import InputError

SCENARIO, NODE, STEPS, BAD_STEP = "indoor-robot", 1, 4, 2  # node 1: 3 states, 2 inputs, a 2-D sensor, senders 0, 2


@pytest.fixture(scope="module")
def sim():
    return studies.simulate(SCENARIO, seed=3)


def _make(kind: str):
    if kind in ("kcf", "hcmci", "local"):
        return lambda node=None: studies.node_filter(SCENARIO, filter=kind, node=node,
                                                     iterations=2 if kind == "hcmci" else None)
    return lambda node=None: studies.node_filter(SCENARIO, mode=kind, node=node)


@pytest.fixture(scope="module", params=["relay", "paper", "scheduled", "kcf", "hcmci", "local"])
def driven(request, sim):
    """``(make, calls)``: how to make node NODE of ``kind`` and, step by step, the calls ``(method, args)`` that feed
    it what its network delivered to it over STEPS steps of ``sim``."""
    kind, make = request.param, _make(request.param)
    net = make()
    offsets = np.concatenate([[0], np.cumsum(net.model.sensor_dims)])
    z_i = lambda k: sim.z[k, offsets[NODE]:offsets[NODE + 1]]  # noqa: E731
    calls = []
    for k in range(STEPS):
        net.step(sim.z[k], u=sim.inputs[k])
        sent, rounds = net.last
        u = sim.inputs[k]
        if kind == "relay":
            calls.append([("step", (*rounds[0][NODE], u))])
        elif kind == "local":  # every node alone: nothing delivered
            calls.append([("step", (z_i(k), u))])
        elif kind == "paper":
            calls.append([("predict", (u,)), ("update", (z_i(k), *rounds[0][NODE]))])
        elif kind == "kcf":
            calls.append([("predict", (z_i(k), u)), ("update", (rounds[0][NODE],))])
        elif kind == "scheduled":
            calls.append([("predict", (z_i(k), u)), ("update", (rounds[0][NODE],))]
                         + [("round", (got[NODE],)) for got in rounds[1:]])
        else:
            calls.append([("predict", (z_i(k), u))] + [("round", (got[NODE],)) for got in rounds])
    assert np.isfinite(net.step(sim.z[STEPS], u=sim.inputs[STEPS])).all()
    return kind, make, calls


def _nan_in(value):
    """``value`` (an array or a packet of arrays) with its first number NaN."""
    if isinstance(value, tuple):
        return type(value)(_nan_in(value[0]), *value[1:])
    bad = np.array(value, dtype=float)
    bad.flat[0] = np.nan
    return bad


def _bad_calls(kind: str, method: str, args: tuple):
    """``(bad args, what the refusal names)`` for a call ``method(*args)``: every argument made wrong in turn."""
    names = {"step": ("z", "u") if kind == "local" else ("z", "received", "u"), "predict": ("u",) if kind == "paper" else ("z", "u"),
             "update": ("z", "received", "bounds") if kind == "paper" else ("received",), "round": ("received",)}
    out = []
    for a, name in enumerate(names[method]):
        def swap(v):
            return args[:a] + (v,) + args[a + 1:]

        value = args[a]
        if name in ("z", "u"):
            out += [(swap(_nan_in(value)), rf"{name} of node {NODE} at step {BAD_STEP} must be 2 finite numbers, "
                                           r"got \[nan, "),
                    (swap(np.append(value, 1.0)), rf"{name} of node {NODE} at step {BAD_STEP} must be 2 finite"),
                    (swap("1 2"), rf"{name} of node {NODE} at step {BAD_STEP} must be 2 finite numbers, got str")]
            if name == "u":
                out.append((swap(None), rf"u of node {NODE} at step {BAD_STEP} must be the model's 2 known inputs"))
            else:
                out.append((swap(np.array([True, False])), rf"z of node {NODE} at step {BAD_STEP} must be 2 finite"))
            continue
        given = dict(value)
        out.append((swap({**given, 99: next(iter(given.values()), None)}),
                    rf"{name} of node {NODE} at step {BAD_STEP} holds (node|sensor) 99, which is not"))
        out.append((swap(list(given.values())), rf"{name} of node {NODE} at step {BAD_STEP} must be a dict"))
        if given:
            j = next(iter(given))
            field = r"\.\w+" if isinstance(given[j], tuple) else ""  # a packet's field, or the array itself
            if name == "bounds":  # the consensus rule reads a neighbour's P and ok from its packet
                field = r"\.P"
                out.append((swap({**given, j: given[j]._replace(ok=1)}),
                            rf"bounds\[{j}\]\.ok of node {NODE} at step {BAD_STEP} must be True or False"))
            bad = given[j]._replace(P=_nan_in(given[j].P)) if name == "bounds" else _nan_in(given[j])
            out.append((swap({**given, j: bad}),
                        rf"{name}\[{j}\]{field} of node {NODE} at step {BAD_STEP} must be .*finite numbers"))
            short = (given[j]._replace(P=given[j].P[:-1]) if name == "bounds" else
                     type(given[j])(given[j][0][:-1], *given[j][1:]) if isinstance(given[j], tuple) else given[j][:-1])
            out.append((swap({**given, j: short}), rf"{name}\[{j}\]{field} of node {NODE} at step {BAD_STEP} must be"))
        if name == "bounds":
            out.append((swap({}), rf"bounds of node {NODE} at step {BAD_STEP} must hold every in-neighbour's packet"))
    return out


def _state(node):
    return node.x.copy(), node.P.copy(), node.k


def test_a_refused_call_names_the_argument_node_and_step_and_changes_nothing(driven):
    """Every argument of every call of step BAD_STEP made wrong in turn (NaN, a wrong length, text, booleans, an
    unknown sender, a packet with NaN or a short array, a flag that is not one, a missing packet): each is refused
    naming it, the node and the step; the node then driven on with the right calls ends bit for bit where the node
    that never saw a refused call ends."""
    kind, make, calls = driven
    ref = make(NODE)
    for step in calls:
        for method, args in step:
            getattr(ref, method)(*args)
    node, refused = make(NODE), 0
    for k, step in enumerate(calls):
        for method, args in step:
            if k == BAD_STEP:
                for bad, words in _bad_calls(kind, method, args):
                    before = _state(node)
                    with pytest.raises(InputError, match=words):
                        getattr(node, method)(*bad)
                    after = _state(node)
                    assert all(np.array_equal(a, b) for a, b in zip(before, after))
                    refused += 1
            getattr(node, method)(*args)
    assert refused >= 6
    assert node.k == ref.k == STEPS and np.array_equal(node.x, ref.x) and np.array_equal(node.P, ref.P)


def test_a_call_out_of_its_phase_names_the_call_expected(driven):
    """Two-phase nodes: an update (or a round) before the prediction, a second prediction before the update: refused
    naming the call expected next; the node then goes on as if they had not been made."""
    kind, make, calls = driven
    if kind in ("relay", "local"):
        pytest.skip("one call a step: no phases")
    node, ref = make(NODE), make(NODE)
    (first, first_args), (second, second_args) = calls[0][:2]
    with pytest.raises(InputError, match=rf"node {NODE} .*step 0.*: call predict\((z, )?u\) (first|next)"):
        getattr(node, second)(*second_args)
    node.predict(*first_args)
    with pytest.raises(InputError, match=rf"node {NODE} .*step 0.*: call {second}\("):
        node.predict(*first_args)
    for step in calls:
        for method, args in step:
            getattr(ref, method)(*args)
    getattr(node, second)(*second_args)
    for method, args in calls[0][2:] + [c for step in calls[1:] for c in step]:
        getattr(node, method)(*args)
    assert node.k == ref.k and np.array_equal(node.x, ref.x) and np.array_equal(node.P, ref.P)


def test_a_network_refuses_a_bad_step_or_run_before_it_steps(sim):
    """A network's step: the measurement, the channels' flags and ξ, the inputs, checked before any node steps; a run
    with a NaN measurement in its fourth row is refused before its first step."""
    net, ref = _make("paper")(), _make("paper")()
    E = int(np.count_nonzero(net.network.adjacency))
    net.step(sim.z[0], u=sim.inputs[0])
    ref.step(sim.z[0], u=sim.inputs[0])
    z = sim.z[1].copy()
    z[3] = np.inf
    for args, words in [((z,), r"z of the network at step 1 must be 16 finite numbers"),
                        ((sim.z[1], np.full(E, 2)), rf"dos of the network at step 1 must be {E} flags"),
                        ((sim.z[1], None, np.zeros(E - 1, bool)), rf"fdi of the network at step 1 must be {E} flags"),
                        ((sim.z[1], None, None, np.full((E, 3), np.nan)), r"xi of the network at step 1 must be a "
                                                                          rf"{E}x3 array of finite numbers")]:
        with pytest.raises(InputError, match=words):
            net.step(*args, u=sim.inputs[1])
    with pytest.raises(InputError, match=r"u of the network at step 1 must be the model's 2 known inputs, got None"):
        net.step(sim.z[1])
    bad = sim.z[1:6].copy()
    bad[3, 0] = np.nan
    with pytest.raises(InputError, match=r"z of the network at step 4 must be 16 finite numbers, got an array"):
        net.run(bad, inputs=sim.inputs[1:6])
    assert [nd.k for nd in net.nodes] == [1] * len(net.nodes)
    assert np.array_equal(net.run(sim.z[1:6], inputs=sim.inputs[1:6])[0], ref.run(sim.z[1:6], inputs=sim.inputs[1:6])[0])


def test_nan_into_a_relay_node_is_refused_at_once():
    """The issue's case: NaN as a node's measurement no longer returns NaN for the next step to trip on."""
    node = studies.node_filter(SCENARIO, mode="relay", node=3)
    with pytest.raises(InputError, match=r"^z of node 3 at step 0 must be 2 finite numbers, got \[nan, 1.0\]$"):
        node.step([np.nan, 1.0], {}, [0.0, 0.0])
    assert node.k == 0 and np.isfinite(node.step([0.1, 1.0], {}, [0.0, 0.0])).all() and node.k == 1


def test_a_node_names_its_own_rows_of_the_stacked_measurement(driven, sim):
    """``node.rows`` is node i's sensor's rows of a run's ``z`` (the test counts them itself from the sensors'
    dimensions), for every node of every kind; the rows of all nodes in order tile ``z`` exactly."""
    kind, make, _ = driven
    dims = [s.dim for s in make().model.sensors]
    starts = np.concatenate([[0], np.cumsum(dims)])
    nodes = [make(i) for i in range(len(dims))]
    assert [nd.rows for nd in nodes] == [slice(a, b) for a, b in zip(starts[:-1], starts[1:])]
    np.testing.assert_array_equal(np.concatenate([sim.z[0, nd.rows] for nd in nodes]), sim.z[0])


def test_a_nodes_rows_on_a_model_of_mixed_sensor_sizes():
    """On a user's model whose sensors have 1, 2, 1 and 2 rows, node i's rows are not i: they start after the rows of
    the sensors before it, and a node stepped on ``z[k, node.rows]`` is the local EKFs' batch on that run.  A sensor
    that does not exist is refused by name."""
    from designer.simulate import simulate_runs
    from filters.distributed import LocalEKFNode, run_local_batch
    from test_distributed import mixed_user_model

    m = mixed_user_model()
    nodes = [LocalEKFNode(m, i) for i in range(m.n_sensors)]
    assert [nd.rows for nd in nodes] == [slice(0, 1), slice(1, 3), slice(3, 4), slice(4, 6)]
    assert [m.sensor_rows(i) for i in range(4)] == [nd.rows for nd in nodes]
    np.testing.assert_array_equal(m.sensor_offsets, [0, 1, 3, 4, 6])
    z = simulate_runs(m, 3, [np.random.default_rng(5)]).z
    batch = run_local_batch(m, z)
    for k in range(3):
        for nd in nodes:
            nd.step(z[0, k, nd.rows])
    np.testing.assert_array_equal(np.stack([nd.x for nd in nodes]), batch.x[0, -1])
    with pytest.raises(InputError, match="sensor must be an integer in 0..3, got 4"):
        m.sensor_rows(4)
