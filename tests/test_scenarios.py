"""Built-in scenarios: published values, parameters, overrides, documented assumptions."""
from __future__ import annotations

import numpy as np
import pytest

from designer import InputError
from studies.scenarios import SCENARIOS, get_spec, load_scenario, parse_assignments


def test_five_builtin_scenarios_with_their_papers():
    assert {n: s.paper for n, s in SCENARIOS.items()} == {
        "target-range-bearing": "000", "switching-2d": "001", "target-binary-energy": "002",
        "indoor-robot": "003", "four-tank": "004",
    }


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_every_assumption_parameter_is_documented(name):
    spec = SCENARIOS[name]
    desc = spec.describe()
    assert desc["assumptions"], "a scenario with gaps must state its assumptions"
    for p in desc["parameters"]:
        assert p["doc"] and p["allowed"]
    # Every parameter validates its own default and round-trips through the CLI parser.
    for p in spec.params:
        text = p.default if p.kind == "choice" else str(p.default).lower() if p.kind == "bool" else None
        if text is None:
            import json

            text = json.dumps(p.default)
        assert p.parse(text) == p.validate(p.default)


def test_range_bearing_published_values():
    sc = load_scenario("target-range-bearing")
    m = sc.model
    T = 1.0
    B = np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]])
    np.testing.assert_allclose(m.process_cov, 0.055**2 * np.kron(np.eye(2), B), rtol=1e-14)
    noise = m.sensors[0].noise
    np.testing.assert_allclose(noise.weights, [0.8, 0.2])
    np.testing.assert_allclose(noise.components[0].cov, np.diag([4.0, (np.pi / 180) ** 2]))
    np.testing.assert_allclose(noise.components[1].cov, np.diag([25.0, (np.pi / 90) ** 2]))
    np.testing.assert_allclose(sc.x0, [20, 0.3, 20, 0.3])
    # Range and bearing of a known geometry (closed form).
    x = np.array([3.0, 0.0, 4.0, 0.0])
    np.testing.assert_allclose(m.h(0, x), [5.0, np.arctan2(4.0, 3.0)], rtol=1e-15)
    assert sc.channel.deception_prob == 0.2 and sc.channel.start == 1
    np.testing.assert_allclose(np.exp(sc.channel.deception.logpdf([0.0, 0.0])), 1 / (90 * np.pi))
    assert m.angle_components == ((0, 1), (1, 1), (2, 1), (3, 1))  # every sensor's bearing


def test_switching_published_values():
    sc = load_scenario("switching-2d")
    m = sc.model
    x = np.array([0.3, -0.7])
    F = np.array([[0.85, -0.2], [-0.2, 0.76]])
    f = np.array([-0.25 * np.tanh(x[1]), 0.35 * np.tanh(x[0])])
    g = np.array([0.32 * np.tanh(x[0]), -0.28 * np.tanh(x[1])])
    np.testing.assert_allclose(m.f(x, 0, None, 1), F @ x + f, rtol=1e-14)
    np.testing.assert_allclose(m.f(x, 0, None, 0), F @ x + g, rtol=1e-14)
    np.testing.assert_allclose(m.h_all(x), [2 * np.sin(x[0] - x[1]), -2 * np.cos(x[0] + x[1])], rtol=1e-14)
    np.testing.assert_allclose(m.mode_probs, [0.5, 0.5])
    np.testing.assert_allclose(m.process_noise.cov, (0.8 * 0.02**2 + 0.2 * 0.1**2) * np.eye(2), rtol=1e-12)
    vn = m.sensors[0].noise
    assert np.isinf(vn.logpdf([2.01])) and np.isfinite(vn.logpdf([1.99]))


def test_binary_energy_published_values():
    sc = load_scenario("target-binary-energy")
    m = sc.model
    assert m.n_sensors == 16 and [10.0, 10.0] in sc.params["sensor_positions"]
    x = np.array([10.0 + 3.0, 0.0, 10.0 + 4.0, 0.0])  # 5 m from the sensor at (10, 10)
    assert m.h(0, x)[0] == pytest.approx(4000.0 * 5.0**-2.8, rel=1e-13)
    ch = sc.channel
    assert ch.threshold == 0.3 and ch.gain == 0.5 and ch.probabilities == (0.1, 0.1, 0.1)
    # The prior's mean velocity is (0.4, 0.3) up to the heading spread factor exp(-sd^2/2).
    c = np.exp(-0.5 * (np.pi / 6) ** 2)
    np.testing.assert_allclose(m.prior.mean, [15, 0.4 * c, 20, 0.3 * c], rtol=1e-12)


def test_indoor_robot_published_values_and_network():
    sc = load_scenario("indoor-robot")
    m = sc.model
    assert m.n_sensors == 8 and sc.network.n_nodes == 8 and sc.network.is_connected
    assert sc.network.d_max == 3
    x = np.array([1.0, 0.5, 0.3])
    cx, cy = 0.6, 0.6
    ku, kv = 9.0213283 / 2.1050, 9.0250141 / 2.1050
    p = ku * (-(cx - x[0]) * np.sin(x[2]) + (cy - x[1]) * np.cos(x[2]) - 0.0536) + 347.20436
    q = kv * (-(cx - x[0]) * np.cos(x[2]) - (cy - x[1]) * np.sin(x[2]) + 0.0668) + 284.34750
    np.testing.assert_allclose(m.h(0, x), [p, q], rtol=1e-14)
    paper = load_scenario("indoor-robot", assignments=["noise=paper"]).model
    np.testing.assert_allclose(paper.process_cov, np.eye(3))
    np.testing.assert_allclose(paper.measurement_cov(3), np.eye(2))


def _left_room(x):
    return ((x[..., 0] < 0) | (x[..., 0] > 2.4) | (x[..., 1] < 0) | (x[..., 1] > 1.8)).any(-1)


def test_indoor_robot_noise_assumption_is_what_the_text_says():
    """The documented reason for the default Q: a Monte Carlo of the generative model."""
    rng = np.random.default_rng(7)
    frac = {}
    for label, over in (("paper", {"noise": "paper"}), ("0.01", {"process_var": 0.01}), ("default", {})):
        sc = load_scenario("indoor-robot", over)
        frac[label] = _left_room(sc.simulate(rng, batch=2000).x).mean()
    assert frac["paper"] == 1.0
    assert 0.3 < frac["0.01"] < 0.5
    assert frac["default"] < 0.02


def test_four_tank_operating_point_is_near_equilibrium():
    sc = load_scenario("four-tank")
    m = sc.model
    u = sc.inputs(1)[0]
    # Johansson's h0 is an approximate equilibrium: one step changes the levels by < 0.01 cm.
    assert np.abs(m.f(sc.x0, 0, u) - sc.x0).max() < 0.01
    # The continuous-time equilibrium from the closed form of the tank equations.
    a = np.array([0.071, 0.057, 0.071, 0.057])
    g, k1, k2, g1, g2 = 981.0, 3.33, 3.35, 0.70, 0.60
    h3 = ((1 - g2) * k2 * 3.0 / a[2]) ** 2 / (2 * g)
    h4 = ((1 - g1) * k1 * 3.0 / a[3]) ** 2 / (2 * g)
    h1 = ((g1 * k1 * 3.0 + a[2] * np.sqrt(2 * g * h3)) / a[0]) ** 2 / (2 * g)
    h2 = ((g2 * k2 * 3.0 + a[3] * np.sqrt(2 * g * h4)) / a[1]) ** 2 / (2 * g)
    heq = np.array([h1, h2, h3, h4])
    np.testing.assert_allclose(m.f(heq, 0, u), heq, atol=1e-9)
    np.testing.assert_allclose(m.measurement_cov(2), [[0.5e-3]])
    high = load_scenario("four-tank", assignments=["noise=high"]).model
    np.testing.assert_allclose(high.measurement_cov(0), [[5e-3]])


def test_overrides_are_validated():
    spec = get_spec("indoor-robot")
    assert parse_assignments(spec, ["process_var=0.5", "noise=paper"]) == {"process_var": 0.5, "noise": "paper"}
    assert parse_assignments(spec, ["x0=[1, 1, 0]"]) == {"x0": [1.0, 1.0, 0.0]}
    assert parse_assignments(spec, ["x0=1,1,0"]) == {"x0": [1.0, 1.0, 0.0]}
    with pytest.raises(InputError, match="process_var must be a number in"):
        parse_assignments(spec, ["process_var=abc"])
    with pytest.raises(InputError, match="x0 must be an array of shape"):
        parse_assignments(spec, ["x0=[1, 2]"])
    with pytest.raises(InputError, match="no parameter 'nosuch'"):
        parse_assignments(spec, ["nosuch=1"])
    with pytest.raises(InputError, match="NAME=VALUE"):
        parse_assignments(spec, ["process_var"])
    with pytest.raises(InputError, match="steps must be an integer"):
        parse_assignments(spec, ["steps=2.5"])
    with pytest.raises(InputError, match="dos_prob must be a number in \\[0.0, 1.0\\]"):
        load_scenario("indoor-robot", {"dos_prob": 1.5})
    with pytest.raises(InputError, match="dos_prob \\+ fdi_prob"):
        load_scenario("indoor-robot", {"dos_prob": 0.7, "fdi_prob": 0.6})
    with pytest.raises(InputError, match="disconnected"):
        load_scenario("indoor-robot", {"edges": [[0, 1], [2, 3]]})
    with pytest.raises(InputError, match="unknown scenario"):
        get_spec("no-such-scenario")
    with pytest.raises(InputError, match="quant_levels must be a power of two"):
        load_scenario("switching-2d", {"quant_levels": 6})


def test_override_changes_the_model():
    a = load_scenario("target-range-bearing").model
    b = load_scenario("target-range-bearing", assignments=["accel_std=0.1"]).model
    np.testing.assert_allclose(b.process_cov, a.process_cov * (0.1 / 0.055) ** 2, rtol=1e-12)


def test_user_model_file(tmp_path):
    from pathlib import Path

    example = Path(__file__).resolve().parents[1] / "examples" / "pendulum_model.py"
    sc = load_scenario(str(example))
    assert sc.model.name == "pendulum" and sc.steps == 100
    tr = sc.simulate(np.random.default_rng(0), 10)
    assert tr.x.shape == (11, 2) and tr.z.shape == (10, 3)
    bad = tmp_path / "bad.py"
    bad.write_text("x = 1\n")
    with pytest.raises(InputError, match="must define SPEC"):
        load_scenario(str(bad))
    broken = tmp_path / "broken.py"
    broken.write_text("raise RuntimeError('boom')\n")
    with pytest.raises(InputError, match="failed: RuntimeError: boom"):
        load_scenario(str(broken))
    with pytest.raises(InputError, match="does not exist"):
        load_scenario(str(tmp_path / "missing.py"))
