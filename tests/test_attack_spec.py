"""The typed attack specification: per-edge probabilities, the injected signal and its bound, overrides, uplinks."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm

from designer.attacks import AttackSpec, FDISignal
from designer.network import SensorNetwork
from designer.validation import InputError
from filters.attacks import channel_draws, simulate_attacks, uplink_attacks

RING = SensorNetwork.from_edges(4, [(0, 1), (1, 2), (2, 3), (3, 0)])


def test_edge_mapping_sets_both_directions_and_zero_elsewhere():
    r = AttackSpec(dos={(0, 1): 0.2, (2, 3): 0.4}, fdi=0.1, signal=FDISignal(1.0)).resolve(RING, 2)
    d = r.network.dos_prob
    assert d[0, 1] == d[1, 0] == 0.2 and d[2, 3] == d[3, 2] == 0.4 and d[1, 2] == 0.0 and d[0, 2] == 0.0
    np.testing.assert_array_equal(r.network.fdi_prob, 0.1 * RING.adjacency)
    # uplinks default to the mean of each node's incoming channels
    np.testing.assert_allclose(r.uplink_dos, [0.1, 0.1, 0.2, 0.2])
    np.testing.assert_array_equal(r.uplink_fdi, [0.1] * 4)


def test_matrix_entries_are_directed_channels_and_off_edge_entries_are_refused():
    m = np.zeros((4, 4))
    m[0, 1] = 0.3  # channel 1 -> 0 only
    r = AttackSpec(dos=m).resolve(RING, 2)
    assert r.network.dos_prob[0, 1] == 0.3 and r.network.dos_prob[1, 0] == 0.0
    m[0, 2] = 0.1  # 0 - 2 is not an edge of the ring
    with pytest.raises(InputError, match=r"dos\[0, 2\].*not a channel"):
        AttackSpec(dos=m).resolve(RING, 2)
    with pytest.raises(InputError, match="not an edge"):
        AttackSpec(dos={(0, 2): 0.1}).resolve(RING, 2)
    with pytest.raises(InputError, match=r"\[0, 1\)"):
        AttackSpec(fdi={(0, 1): 1.0}, delta=1.0).resolve(RING, 2)


def test_fdi_without_a_bound_names_both_and_dos_plus_fdi_is_checked():
    with pytest.raises(InputError, match="fdi probability > 0 but no FDI bound.*delta"):
        AttackSpec(fdi=0.1).resolve(RING, 2)
    assert AttackSpec(fdi=0.1).resolve(RING, 2, require_bound=False).delta is None
    with pytest.raises(InputError, match="fdi probability > 0 but no FDI bound"):
        AttackSpec(uplink_fdi=0.1).resolve(RING, 2)
    AttackSpec(fdi=0.1, delta=0.5).resolve(RING, 2)  # a bound alone is enough: the paper's law at the bound
    with pytest.raises(InputError, match="dos \\+ fdi must be <= 1"):
        AttackSpec(dos=0.6, fdi=0.5, delta=1.0).resolve(RING, 2)


def test_signal_bound_delta_and_overrides():
    sig = FDISignal(amplitude=(3.0, 4.0), components=(0, 2))
    assert sig.bound(3) == pytest.approx(5.0)
    assert FDISignal(1.5, (0, 1)).bound(3) == 1.5 * np.sqrt(2)  # the paper's 2.12, to the last bit
    r = AttackSpec(fdi=0.1, signal=sig).resolve(RING, 3)
    assert r.delta == pytest.approx(5.0)
    with pytest.raises(InputError, match="below the signal's bound"):
        AttackSpec(fdi=0.1, signal=sig, delta=4.0).resolve(RING, 3)
    # --delta alone scales the signal to the new bound (same direction); --amplitude sets it and its bound
    scaled = AttackSpec(fdi=0.1, signal=sig).override(delta=10.0).resolve(RING, 3)
    assert scaled.delta == 10.0 and scaled.signal.bound(3) == pytest.approx(10.0)
    np.testing.assert_allclose(scaled.signal.amplitude, (6.0, 8.0))
    amp = AttackSpec(fdi=0.1, signal=sig, delta=7.0).override(amplitude=2.0).resolve(RING, 3)
    assert amp.delta == pytest.approx(2.0 * np.sqrt(2)) and amp.signal.components == (0, 2)
    both = AttackSpec(fdi=0.1, signal=sig).override(amplitude=1.0, delta=3.0).resolve(RING, 3)
    assert both.delta == 3.0 and both.signal.amplitude == (1.0, 1.0)
    # dos / fdi overrides set every channel and every uplink
    o = AttackSpec(dos={(0, 1): 0.3}, fdi=0.1, signal=sig, uplink_dos=0.5).override(dos=0.2).resolve(RING, 3)
    np.testing.assert_array_equal(o.network.dos_prob, 0.2 * RING.adjacency)
    np.testing.assert_array_equal(o.uplink_dos, [0.2] * 4)
    with pytest.raises(InputError, match="dos"):
        AttackSpec().override(dos=1.2)


@pytest.mark.parametrize("law, g", [("sine", np.sin), ("uniform", lambda s: 2 * norm.cdf(s) - 1),
                                     ("constant", np.ones_like)])
def test_signal_laws_against_their_definition_and_moments(law, g):
    sig = FDISignal(amplitude=(0.5, 2.0), components=(1, 2), law=law)
    s = np.random.default_rng(3).standard_normal(200_000)
    xi = sig.inject(s, np.ones_like(s, bool), 3)
    np.testing.assert_allclose(xi[:, 1], 0.5 * g(s), atol=1e-12)
    np.testing.assert_allclose(xi[:, 2], 2.0 * g(s), atol=1e-12)
    assert np.all(xi[:, 0] == 0)
    assert np.linalg.norm(xi, axis=1).max() <= sig.bound(3) + 1e-12
    m2 = (g(s) ** 2).mean()
    assert abs(m2 - sig.second_moment) < 4 * (g(s) ** 2).std() / np.sqrt(s.size) + 1e-12
    assert np.all(sig.inject(s, np.zeros_like(s, bool), 3) == 0)


def test_channel_attack_frequencies_follow_per_edge_probabilities():
    spec = AttackSpec(dos={(0, 1): 0.3, (1, 2): 0.05, (2, 3): 0.05, (3, 0): 0.05}, fdi=0.1,
                      signal=FDISignal(1.0, (0,)))
    r = spec.resolve(RING, 2)
    att = simulate_attacks(r.network, 20_000, 2, np.random.default_rng(1), r.signal)
    for (i, j), p in (((0, 1), 0.3), ((1, 0), 0.3), ((1, 2), 0.05)):
        se = np.sqrt(p * (1 - p) / 20_000)
        assert abs(att.dos[:, i, j].mean() - p) < 4 * se
        assert abs(att.fdi[:, i, j].mean() - 0.1) < 4 * np.sqrt(0.09 / 20_000)
    assert not np.any(att.dos & att.fdi)
    assert not att.dos[:, 0, 2].any()  # not an edge
    u, s = channel_draws(20_000, 4, np.random.default_rng(2))
    up = uplink_attacks(u, s, 2, dos_prob=r.uplink_dos, fdi_prob=r.uplink_fdi, signal=r.signal)
    np.testing.assert_allclose(up.dos.mean(axis=0), r.uplink_dos, atol=4 * np.sqrt(0.25 / 20_000))


def test_scenario_checks_network_size_and_declared_attacks():
    import casadi as ca

    from designer import Gaussian, Model, Sensor
    from studies.scenarios import Scenario

    x = ca.SX.sym("x", 1)
    m = Model("m", x, 0.9 * x, [Sensor(f"s{i}", x, Gaussian.zero_mean([[0.1]])) for i in range(3)],
              Gaussian.zero_mean([[0.01]]), Gaussian([0.0], [[1.0]]))
    with pytest.raises(InputError, match="NETWORK has 4 nodes but the model has 3 sensors"):
        Scenario("m", m, {}, (), 5, network=RING)
    net = SensorNetwork.from_edges(3, [(0, 1), (1, 2)], fdi_prob=0.2)
    unbounded = Scenario("m", m, {}, (), 5, network=net)  # a command may still give --delta or --amplitude
    with pytest.raises(InputError, match="no FDI bound"):
        unbounded.resolved_attacks
    assert unbounded.with_attacks(delta=0.5).resolved_attacks.delta == 0.5
    assert unbounded.with_attacks(amplitude=0.5).resolved_attacks.delta == 0.5
    sc = Scenario("m", m, {}, (), 5, network=net.with_attacks(0.1, 0.0))
    assert sc.resolved_attacks.network.dos_prob[0, 1] == 0.1


def test_an_edge_given_in_both_directions_must_agree():
    with pytest.raises(InputError, match=r"fdi: the undirected edge 0 - 1 is given twice with different "
                                         r"probabilities, \(0, 1\): 0.3 and \(1, 0\): 0.01"):
        AttackSpec(fdi={(0, 1): 0.3, (1, 0): 0.01}, delta=1.0).resolve(RING, 2)
    with pytest.raises(InputError, match=r"dos: key \(0, 1.5\): node indices must be integers"):
        AttackSpec(dos={(0, 1.5): 0.1}).resolve(RING, 2)
    same = AttackSpec(dos={(0, 1): 0.3, (1, 0): 0.3}).resolve(RING, 2).network.dos_prob
    np.testing.assert_array_equal(same, AttackSpec(dos={(0, 1): 0.3}).resolve(RING, 2).network.dos_prob)
