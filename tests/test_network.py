"""Tests of designer.network.SensorNetwork.

Reference values are derived here from the edge lists (sets, counting) or with
scipy.sparse.csgraph, never copied from a run of the code.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.sparse import csgraph

from designer.network import SensorNetwork
from designer.validation import InputError

EDGES = [(0, 1), (2, 1), (1, 3), (3, 2), (4, 3)]  # some listed as (j, i)
N = 5


def ring_adjacency(n):
    a = np.zeros((n, n), dtype=int)
    for i in range(n):
        a[i, (i + 1) % n] = a[(i + 1) % n, i] = 1
    return a


def ref_neighbours(n, edges):
    nb = [set() for _ in range(n)]
    for i, j in edges:
        nb[i].add(j)
        nb[j].add(i)
    return tuple(tuple(sorted(s)) for s in nb)


# ---------------------------------------------------------------------------
# Graph structure
# ---------------------------------------------------------------------------

def test_from_edges_structure():
    net = SensorNetwork.from_edges(N, EDGES)
    nb = ref_neighbours(N, EDGES)
    assert net.n_nodes == N
    assert net.neighbours == nb
    np.testing.assert_array_equal(net.degrees, [len(s) for s in nb])
    assert net.d_max == max(len(s) for s in nb)
    assert net.edges == sorted({(min(e), max(e)) for e in EDGES})
    assert net.adjacency.dtype == bool
    np.testing.assert_array_equal(net.adjacency, net.adjacency.T)
    assert not net.adjacency.diagonal().any()
    assert net.is_connected and net.n_components == 1


def test_hand_computed_example():
    # path 0-1-2-3 plus chord 1-3: degrees by hand 1, 3, 2, 2
    net = SensorNetwork.from_edges(4, [(0, 1), (1, 2), (2, 3), (3, 1)])
    assert net.neighbours == ((1,), (0, 2, 3), (1, 3), (1, 2))
    np.testing.assert_array_equal(net.degrees, [1, 3, 2, 2])
    assert net.d_max == 3
    assert net.edges == [(0, 1), (1, 2), (1, 3), (2, 3)]


def test_from_edges_order_and_duplicates_do_not_matter():
    a = SensorNetwork.from_edges(N, EDGES)
    b = SensorNetwork.from_edges(N, [(j, i) for i, j in reversed(EDGES)] + EDGES)
    np.testing.assert_array_equal(a.adjacency, b.adjacency)
    assert a.edges == b.edges


def test_from_edges_equals_adjacency_constructor():
    adj = ring_adjacency(6)
    net = SensorNetwork(6, adj)
    net2 = SensorNetwork.from_edges(6, [(i, (i + 1) % 6) for i in range(6)])
    np.testing.assert_array_equal(net.adjacency, net2.adjacency)
    np.testing.assert_array_equal(net.degrees, np.full(6, 2))
    assert net.d_max == 2
    assert net.neighbours[0] == (1, 5)


@pytest.mark.parametrize("seed", range(5))
def test_random_graphs_against_csgraph(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 15))
    upper = np.triu(rng.random((n, n)) < 0.25, k=1)
    adj = (upper | upper.T).astype(int)
    n_comp, _ = csgraph.connected_components(adj, directed=False)
    net = SensorNetwork(n, adj, require_connected=False)
    assert net.n_components == n_comp
    assert net.is_connected == (n_comp == 1)
    edges = [(int(i), int(j)) for i, j in zip(*np.nonzero(upper))]
    assert net.edges == sorted(edges)
    nb = ref_neighbours(n, edges)
    assert net.neighbours == nb
    np.testing.assert_array_equal(net.degrees, [len(s) for s in nb])
    assert net.d_max == max(len(s) for s in nb)
    if n_comp > 1:
        with pytest.raises(InputError, match="disconnected"):
            SensorNetwork(n, adj)


def test_single_node_network():
    net = SensorNetwork(1, np.zeros((1, 1), dtype=int))
    assert net.is_connected and net.n_components == 1
    assert net.d_max == 0 and net.edges == [] and net.neighbours == ((),)


def test_boolean_adjacency_accepted():
    adj = ring_adjacency(4).astype(bool)
    net = SensorNetwork(4, adj)
    np.testing.assert_array_equal(net.adjacency, adj)


def test_network_is_immutable():
    net = SensorNetwork.from_edges(N, EDGES)
    with pytest.raises(dataclasses.FrozenInstanceError):
        net.n_nodes = 3


# ---------------------------------------------------------------------------
# Rejected graphs
# ---------------------------------------------------------------------------

def test_self_loop_rejected_in_from_edges():
    with pytest.raises(InputError, match="self-loop"):
        SensorNetwork.from_edges(3, [(0, 1), (1, 2), (2, 2)])


def test_self_loop_rejected_in_adjacency():
    adj = ring_adjacency(4)
    adj[2, 2] = 1
    with pytest.raises(InputError, match=r"self-loop.*2|2.*self-loop"):
        SensorNetwork(4, adj)


def test_asymmetric_adjacency_rejected():
    adj = ring_adjacency(4)
    adj[0, 2] = 1  # 0 -> 2 only
    with pytest.raises(InputError, match="symmetric"):
        SensorNetwork(4, adj)


@pytest.mark.parametrize(
    "adj, match",
    [
        (np.array([[0, 2], [2, 0]]), "adjacency"),
        (np.array([[0, 0.5], [0.5, 0]]), "adjacency"),
        (np.array([[0, -1], [-1, 0]]), "adjacency"),
        (np.array([[0, np.nan], [np.nan, 0]]), "adjacency"),
        (np.zeros((2, 3)), "adjacency"),
        (np.zeros((3, 3)), "adjacency"),
    ],
)
def test_bad_adjacency_rejected(adj, match):
    with pytest.raises(InputError, match=match):
        SensorNetwork(2, adj)


@pytest.mark.parametrize("n", [0, -1, 2.5, "3", None])
def test_bad_n_nodes_rejected(n):
    with pytest.raises(InputError, match="n_nodes"):
        SensorNetwork(n, np.zeros((1, 1)))


@pytest.mark.parametrize("edges, match", [([(0, 5)], "outside"), ([(-1, 0)], "outside"), ([(0, 1, 2)], "pair")])
def test_bad_edges_rejected(edges, match):
    with pytest.raises(InputError, match=match):
        SensorNetwork.from_edges(3, edges)


def test_disconnected_rejected_by_default():
    with pytest.raises(InputError, match=r"disconnected.*2 components.*require_connected"):
        SensorNetwork.from_edges(4, [(0, 1), (2, 3)])


def test_disconnected_accepted_and_flagged():
    net = SensorNetwork.from_edges(4, [(0, 1), (2, 3)], require_connected=False)
    assert net.is_connected is False
    assert net.n_components == 2
    assert net.edges == [(0, 1), (2, 3)]
    # isolated nodes each form a component
    net = SensorNetwork.from_edges(6, [(0, 1), (1, 2)], require_connected=False)
    assert net.n_components == 4
    assert not net.is_connected
    np.testing.assert_array_equal(net.degrees, [1, 2, 1, 0, 0, 0])
    net = SensorNetwork(3, np.zeros((3, 3)), require_connected=False)
    assert net.n_components == 3 and net.d_max == 0


def test_connected_graph_flagged_connected_with_require_false():
    net = SensorNetwork.from_edges(N, EDGES, require_connected=False)
    assert net.is_connected is True and net.n_components == 1


# ---------------------------------------------------------------------------
# Attack probabilities
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["dos_prob", "fdi_prob"])
@pytest.mark.parametrize("value", [1.5, -0.1, np.nan, np.inf])
def test_scalar_probability_out_of_range_rejected(name, value):
    with pytest.raises(InputError, match=name):
        SensorNetwork.from_edges(N, EDGES, **{name: value})


@pytest.mark.parametrize("name", ["dos_prob", "fdi_prob"])
@pytest.mark.parametrize("value", [1.01, -1e-3])
def test_per_edge_probability_out_of_range_rejected(name, value):
    p = np.full((N, N), 0.1)
    i, j = EDGES[2]
    p[i, j] = value
    with pytest.raises(InputError, match=name):
        SensorNetwork.from_edges(N, EDGES, **{name: p})


@pytest.mark.parametrize("name", ["dos_prob", "fdi_prob"])
def test_probability_matrix_of_wrong_shape_rejected(name):
    with pytest.raises(InputError, match=name):
        SensorNetwork.from_edges(N, EDGES, **{name: np.full((N, N - 1), 0.1)})
    with pytest.raises(InputError, match=name):
        SensorNetwork.from_edges(N, EDGES, **{name: np.full(N, 0.1)})


def test_probability_bounds_inclusive():
    net = SensorNetwork.from_edges(N, EDGES, dos_prob=1.0, fdi_prob=0.0)
    np.testing.assert_array_equal(net.dos_prob, net.adjacency.astype(float))
    net = SensorNetwork.from_edges(N, EDGES, dos_prob=0.0, fdi_prob=1.0)
    np.testing.assert_array_equal(net.fdi_prob, net.adjacency.astype(float))


def test_dos_plus_fdi_above_one_rejected():
    with pytest.raises(InputError, match=r"dos_prob \+ fdi_prob"):
        SensorNetwork.from_edges(N, EDGES, dos_prob=0.6, fdi_prob=0.5)
    # per-edge: only one channel j -> i violates
    dos = np.full((N, N), 0.3)
    fdi = np.full((N, N), 0.3)
    i, j = EDGES[4]
    dos[i, j], fdi[i, j] = 0.7, 0.4
    with pytest.raises(InputError, match=r"dos_prob \+ fdi_prob"):
        SensorNetwork.from_edges(N, EDGES, dos_prob=dos, fdi_prob=fdi)
    # a sum of exactly one is allowed
    net = SensorNetwork.from_edges(N, EDGES, dos_prob=0.25, fdi_prob=0.75)
    np.testing.assert_allclose((net.dos_prob + net.fdi_prob)[net.adjacency], 1.0)


def test_scalar_probabilities_apply_to_every_edge_only():
    net = SensorNetwork.from_edges(N, EDGES, dos_prob=0.3, fdi_prob=0.2)
    adj = net.adjacency
    assert net.dos_prob.shape == (N, N) and net.fdi_prob.shape == (N, N)
    np.testing.assert_array_equal(net.dos_prob[adj], 0.3)
    np.testing.assert_array_equal(net.fdi_prob[adj], 0.2)
    np.testing.assert_array_equal(net.dos_prob[~adj], 0.0)
    np.testing.assert_array_equal(net.fdi_prob[~adj], 0.0)


def test_probabilities_off_edges_stored_as_zero_and_directions_kept():
    rng = np.random.default_rng(3)
    dos = rng.uniform(0.0, 0.5, size=(N, N))
    fdi = rng.uniform(0.0, 0.5, size=(N, N))
    # off the edges the sum may exceed 1: those entries are ignored
    off = [(0, 2), (2, 0), (0, 0), (4, 1)]
    for i, j in off:
        dos[i, j], fdi[i, j] = 0.9, 0.9
    net = SensorNetwork.from_edges(N, EDGES, dos_prob=dos, fdi_prob=fdi)
    adj = np.zeros((N, N), dtype=bool)
    for i, j in EDGES:
        adj[i, j] = adj[j, i] = True
    for i, j in off:
        assert not adj[i, j]
    np.testing.assert_array_equal(net.dos_prob, np.where(adj, dos, 0.0))
    np.testing.assert_array_equal(net.fdi_prob, np.where(adj, fdi, 0.0))
    # entry [i, j] is the channel j -> i: an asymmetric matrix stays asymmetric
    i, j = EDGES[0]
    assert net.dos_prob[i, j] == dos[i, j] and net.dos_prob[j, i] == dos[j, i]
    assert dos[i, j] != dos[j, i]


def test_default_probabilities_are_zero():
    net = SensorNetwork.from_edges(N, EDGES)
    np.testing.assert_array_equal(net.dos_prob, np.zeros((N, N)))
    np.testing.assert_array_equal(net.fdi_prob, np.zeros((N, N)))


# ---------------------------------------------------------------------------
# with_attacks
# ---------------------------------------------------------------------------

def test_with_attacks_keeps_graph_and_replaces_probabilities():
    net = SensorNetwork.from_edges(N, EDGES, dos_prob=0.1, fdi_prob=0.2)
    new = net.with_attacks(dos_prob=0.4)
    assert new is not net
    assert new.n_nodes == net.n_nodes
    np.testing.assert_array_equal(new.adjacency, net.adjacency)
    assert new.neighbours == net.neighbours
    assert new.edges == net.edges
    np.testing.assert_array_equal(new.degrees, net.degrees)
    adj = net.adjacency
    np.testing.assert_array_equal(new.dos_prob, np.where(adj, 0.4, 0.0))
    np.testing.assert_array_equal(new.fdi_prob, np.where(adj, 0.2, 0.0))  # kept
    # the original is untouched
    np.testing.assert_array_equal(net.dos_prob, np.where(adj, 0.1, 0.0))
    both = net.with_attacks(dos_prob=0.0, fdi_prob=0.5)
    np.testing.assert_array_equal(both.dos_prob, np.zeros((N, N)))
    np.testing.assert_array_equal(both.fdi_prob, np.where(adj, 0.5, 0.0))
    same = net.with_attacks()
    np.testing.assert_array_equal(same.dos_prob, net.dos_prob)
    np.testing.assert_array_equal(same.fdi_prob, net.fdi_prob)


def test_with_attacks_masks_and_validates():
    net = SensorNetwork.from_edges(N, EDGES, fdi_prob=0.5)
    full = np.full((N, N), 0.3)
    new = net.with_attacks(dos_prob=full)
    np.testing.assert_array_equal(new.dos_prob, np.where(net.adjacency, 0.3, 0.0))
    with pytest.raises(InputError, match=r"dos_prob \+ fdi_prob"):
        net.with_attacks(dos_prob=0.6)
    with pytest.raises(InputError, match="fdi_prob"):
        net.with_attacks(fdi_prob=1.2)


def test_with_attacks_keeps_disconnected_flag():
    net = SensorNetwork.from_edges(4, [(0, 1), (2, 3)], require_connected=False)
    new = net.with_attacks(dos_prob=0.2)
    assert new.require_connected is False
    assert new.n_components == 2 and not new.is_connected
    np.testing.assert_array_equal(new.adjacency, net.adjacency)


def test_describe():
    net = SensorNetwork.from_edges(N, EDGES)
    d = net.describe()
    nb = ref_neighbours(N, EDGES)
    assert d["n_nodes"] == N
    assert d["edges"] == sorted({(min(e), max(e)) for e in EDGES})
    assert d["degrees"] == [len(s) for s in nb]
    assert d["d_max"] == max(len(s) for s in nb)
    assert d["connected"] is True


@pytest.mark.parametrize("edges, match", [
    ([(0, 1.7)], r"edge \(0, 1.7\): node indices must be integers in 0..1, got 1.7"),  # was silently (0, 1)
    ([(0, True)], "node indices must be integers"),
    ([(np.float64(0.0), 1)], "node indices must be integers"),
    ([(0, -1)], "outside 0..1"),
    ([(1, 1)], "self-loop"),
    ([0], "pair"),
])
def test_an_edge_is_two_integer_node_indices(edges, match):
    with pytest.raises(InputError, match=match):
        SensorNetwork.from_edges(2, edges)
    assert SensorNetwork.from_edges(np.int64(2), [(np.int32(0), np.int64(1))]).edges == [(0, 1)]


def test_a_disconnected_network_names_the_nodes_cut_off():
    with pytest.raises(InputError, match=r"network of 5 nodes is disconnected \(2 components; node 4 cut off from "
                                         r"node 0\)"):
        SensorNetwork.from_edges(5, [(0, 1), (1, 2), (2, 3)])
    assert SensorNetwork.from_edges(5, [(0, 1), (3, 4)], require_connected=False).components == [[0, 1], [2], [3, 4]]


def test_connectivity_checked_later_refuses_when_the_network_is_used():
    from designer.network import connectivity_checked_later

    with connectivity_checked_later():
        net = SensorNetwork.from_edges(3, [(0, 1)])
    assert not net.is_connected
    with pytest.raises(InputError, match="node 2 cut off"):
        net.with_attacks(dos_prob=0.1)
