"""Design options: scalings U, V_i in every form, Hessian-derived per-component scalings, mixed sensor dimensions."""
from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from designer import AttackSpec, FDISignal, Gaussian, Model, Sensor, SensorNetwork
from designer.design import DesignOptions, parse_scale, resolve_scaling
from designer.linearization import component_scales
from designer.validation import InputError
from filters.consensus import run_consensus
from filters.ekf import run_ekf
from studies.filter_registry import local_ekf_design
from studies.consensus_design import consensus_design
from studies.scenarios import load_scenario, scenario_of

ROOT = Path(__file__).resolve().parents[1]
MIXED = str(ROOT / "examples" / "mixed_sensors_model.py")


def two_sensor_model():
    x = ca.SX.sym("x", 2)
    sensors = [Sensor("rb", ca.vertcat(ca.sqrt(x[0] ** 2 + x[1] ** 2 + 1), x[0] * x[1]), Gaussian.zero_mean(np.eye(2))),
               Sensor("r", x[0] ** 2, Gaussian.zero_mean([[1.0]]))]
    return Model("two", x, ca.vertcat(x[0] + 0.1 * x[1], x[1] - 0.1 * ca.sin(x[0])), sensors,
                 Gaussian.zero_mean(0.01 * np.eye(2)), Gaussian([1.0, 0.5], 0.04 * np.eye(2)))


@pytest.mark.parametrize("u, v, U, V", [
    (0.5, 0.1, 0.5 * np.eye(2), [0.1 * np.eye(2), 0.1 * np.eye(1)]),
    ([0.1, 0.2], [[0.3, 0.4], 0.5], np.diag([0.1, 0.2]), [np.diag([0.3, 0.4]), 0.5 * np.eye(1)]),
    ([[1, 0.5], [0.5, 1]], {"r": 2.0, "*": 0.0}, np.array([[1, 0.5], [0.5, 1]]), [np.zeros((2, 2)), 2 * np.eye(1)]),
])
def test_scalings_in_every_form(u, v, U, V):
    m = two_sensor_model()
    gotU, gotV = resolve_scaling(m, u, v, x0=m.prior.mean, P0=m.prior.cov)
    np.testing.assert_array_equal(gotU, U)
    for a, b in zip(gotV, V):
        np.testing.assert_array_equal(a, b)


def test_bad_scalings_name_the_parameter():
    m = two_sensor_model()
    with pytest.raises(InputError, match="u_scale as a diagonal must have 2"):
        resolve_scaling(m, [1.0, 2.0, 3.0], None, x0=m.prior.mean, P0=m.prior.cov)
    with pytest.raises(InputError, match="unknown sensors"):
        resolve_scaling(m, None, {"nope": 1.0}, x0=m.prior.mean, P0=m.prior.cov)
    with pytest.raises(InputError, match="'r' as a matrix must be 1 x 1"):
        resolve_scaling(m, None, [0.1, np.eye(2)], x0=m.prior.mean, P0=m.prior.cov)
    with pytest.raises(InputError, match=">= 0"):
        resolve_scaling(m, -0.1, None, x0=m.prior.mean, P0=m.prior.cov)
    assert parse_scale("u-scale", "prior") == "prior" and parse_scale("u-scale", "0.5") == 0.5
    assert parse_scale("v-scale", "0.1,0.2") == [0.1, 0.2] and parse_scale("u-scale", "[[1,0],[0,2]]") == [[1, 0], [0, 2]]
    with pytest.raises(InputError, match="--u-scale"):
        parse_scale("u-scale", "-0.01")
    with pytest.raises(InputError, match="--v-scale"):
        parse_scale("v-scale", "big")


def test_prior_scalings_bound_the_remainders_by_monte_carlo():
    """||U^-1 r|| <= ||e|| (and V_i likewise) for errors in the 3-sigma ellipsoid of the prior."""
    m = two_sensor_model()
    x0, P = m.prior.mean, m.prior.cov
    U, V = resolve_scaling(m, "prior", "prior", x0=x0, P0=P)
    # f_0 = x_0 + 0.1 x_1 is linear: no remainder, no scale; f_1 has sin(x_0)
    assert U[0, 0] == 0 and U[1, 1] > 0 and np.count_nonzero(U - np.diag(np.diag(U))) == 0
    rng = np.random.default_rng(0)
    L = np.linalg.cholesky(P)
    d = rng.standard_normal((20_000, 2))
    e = 3.0 * (d / np.linalg.norm(d, axis=1, keepdims=True)) * rng.random((20_000, 1)) ** 0.5 @ L.T
    F = m.F(x0)
    r = m.f(x0 + e) - m.f(x0) - e @ F.T
    assert np.abs(r[:, 0]).max() < 1e-12
    assert np.all(np.abs(r[:, 1]) / U[1, 1] <= np.linalg.norm(e, axis=1) * (1 + 1e-9))
    assert np.max(np.abs(r[:, 1]) / U[1, 1] / np.linalg.norm(e, axis=1)) > 0.05  # and not absurdly loose
    for i in range(m.n_sensors):
        H = m.H(i, x0, 1)
        r = m.h(i, x0 + e, 1) - m.h(i, x0, 1) - e @ H.T
        v = np.diag(V[i])
        assert np.all(np.linalg.norm(r / v, axis=1) <= np.linalg.norm(e, axis=1) * (1 + 1e-9))
    # each component gets its own unit: scaling the second state by 100 scales its U entry by 100
    assert component_scales(lambda pts: m.f_hessian(pts), x0, P).shape == (2,)


def test_linear_model_gets_zero_prior_scalings():
    sc = load_scenario(str(ROOT / "examples" / "linear_network_model.py"))
    des = consensus_design(sc)
    assert not np.any(des.U) and not any(np.any(v) for v in des.V)


def test_options_merge_and_refuse():
    import rules
    from studies.api import design
    from studies.design_options import as_mode

    base = DesignOptions(u_scale=0.01, v_scale=0.1, sigma=0.2)
    assert as_mode(base.merged(DesignOptions(mode="tuned")), "tuned").sigma is None  # paper multipliers: not carried
    assert as_mode(base, "paper").sigma == 0.2
    assert base.merged(DesignOptions(v_scale={"s1": 0.5})).v_scale == {"*": 0.1, "s1": 0.5}
    with pytest.raises(InputError, match="sigma is chosen by the design in mode 'tuned'"):
        rules.get("tuned").check_options(DesignOptions(mode="tuned", sigma=0.1))
    with pytest.raises(InputError, match="tau is chosen by the design in mode 'mse'"):
        rules.get("mse").check_options(DesignOptions(mode="mse", tau=0.1))
    with pytest.raises(InputError, match="sigma is chosen by the design in mode 'tuned'"):  # the API checks it
        design(MIXED, mode="tuned", sigma=0.1)
    with pytest.raises(InputError, match="dos must be a probability"):
        DesignOptions(dos=1.0)


def test_local_filters_of_mixed_sensor_dimensions_are_the_ekf_on_each_sensor():
    """An isolated node with sigma = beta = 0, U = V = 0 is the EKF on its own sensor (run_ekf, another code)."""
    sc = load_scenario(MIXED)
    m = sc.model
    assert sorted(set(m.sensor_dims)) == [1, 2]
    traj = sc.simulate(np.random.default_rng(4), 40)
    n = m.n_sensors
    des = local_ekf_design(consensus_design(sc))
    res = run_consensus(m, SensorNetwork(n, np.zeros((n, n), int), require_connected=False), traj.z, des)
    assert res.K.shape == (40, n, 4, 2)
    for i in range(n):
        avail = np.zeros((40, n), bool)
        avail[:, i] = True
        ekf = run_ekf(m, np.where(np.repeat(avail, m.sensor_dims, axis=1), traj.z, 0.0), available=avail)
        np.testing.assert_allclose(res.x_post[:, i], ekf.x, rtol=1e-9, atol=1e-9)
        if m.sensor_dims[i] == 1:
            assert np.all(res.K[:, i, :, 1] == 0)  # padding beyond the node's own measurement


def test_mixed_dimensions_design_and_replay():
    sc = load_scenario(MIXED)
    from studies.api import design

    d = design(sc, mode="tuned", seed=3, steps=20)
    assert d.schedule.K.shape == (5, 20, 4, 2) and d.feasible
    assert [v.shape for v in d.design.V] == [(2, 2), (1, 1), (1, 1), (1, 1), (1, 1)]
    from filters.attacks import simulate_attacks

    traj_ss, att_ss = np.random.SeedSequence(3).spawn(2)
    traj = d.scenario.simulate(np.random.default_rng(traj_ss), 20)
    att = simulate_attacks(d.scenario.network, 20, 4, np.random.default_rng(att_ss), d.scenario.resolved_attacks.signal)
    rep = run_consensus(sc.model, d.scenario.network, traj.z, d.design, attacks=att,
                        gains=(d.schedule.K.swapaxes(0, 1), d.schedule.C.swapaxes(0, 1)))
    np.testing.assert_allclose(rep.x_post, d.result.x_post, rtol=0, atol=1e-10)


def test_consensus_filter_wraps_bearings_that_cross_pi():
    """A bearing-only node right of the target: its residual crosses ±π; unwrapped it diverges."""
    x = ca.SX.sym("x", 4)
    f = ca.vertcat(x[0] + x[1], x[1], x[2] + x[3], x[3])
    sensors = [Sensor("b", ca.atan2(x[2] - 20.0, x[0] - 60.0), Gaussian.zero_mean([[1e-4]]), angles=(0,)),
               Sensor("r", ca.sqrt((x[0] - 60) ** 2 + (x[2] - 20) ** 2), Gaussian.zero_mean([[0.25]]))]
    m = Model("cross", x, f, sensors, Gaussian.zero_mean(1e-3 * np.eye(4)),
              Gaussian([20.0, 0.3, 17.0, 0.3], np.diag([1.0, 0.01, 1.0, 0.01])))
    sc = scenario_of(m, network=SensorNetwork.from_edges(2, [(0, 1)]), x0=[20.0, 0.3, 17.0, 0.3], steps=60)
    traj = sc.simulate(np.random.default_rng(0), 60)
    assert (traj.z[:, 0] > 3.0).any() and (traj.z[:, 0] < -3.0).any()
    des = local_ekf_design(consensus_design(sc, u_scale=0, v_scale=0))
    iso = SensorNetwork(2, np.zeros((2, 2), int), require_connected=False)
    res = run_consensus(m, iso, traj.z, des)
    ekf = run_ekf(m, traj.z)
    # node 0 alone sees the bearing only; the centralized EKF wraps too: compare node 0's own filter with run_ekf on
    # sensor 0 alone
    avail = np.zeros((60, 2), bool)
    avail[:, 0] = True
    alone = run_ekf(m, np.where(np.repeat(avail, [1, 1], axis=1), traj.z, 0.0), available=avail)
    np.testing.assert_allclose(res.x_post[:, 0], alone.x, rtol=1e-9, atol=1e-9)
    assert np.sqrt(((ekf.x[1:, [0, 2]] - traj.x[1:, [0, 2]]) ** 2).sum(-1).mean()) < 3.0


def test_in_memory_model_with_network_and_attacks_designs():
    from studies.api import design

    x = ca.SX.sym("x", 2)
    m = Model("mem", x, ca.vertcat(x[0] + 0.1 * x[1], 0.95 * x[1]),
              [Sensor(f"s{i}", x[i % 2], Gaussian.zero_mean([[0.1]])) for i in range(4)],
              Gaussian.zero_mean(0.01 * np.eye(2)), Gaussian([0.0, 0.0], np.eye(2)))
    net = SensorNetwork.from_edges(4, [(0, 1), (1, 2), (2, 3), (3, 0)])
    d = design(m, network=net, attacks=AttackSpec(dos=0.1, fdi=0.1, signal=FDISignal(0.5)), steps=15, mode="tuned")
    assert d.feasible and d.design.delta == pytest.approx(0.5 * np.sqrt(2))
    with pytest.raises(InputError, match="no FDI bound"):
        design(m, network=net, attacks=AttackSpec(fdi=0.1), steps=5)


def test_scalar_state_models_have_matrix_jacobians_and_hessians():
    """n_x = 1: F, H_i and the Hessians keep their matrix axes (the translation returns 1-column outputs flat)."""
    x = ca.SX.sym("x", 1)
    m = Model("s", x, 0.8 * x + 0.1 * ca.sin(x), [Sensor("a", ca.vertcat(x**2, ca.sin(x)), Gaussian.zero_mean(np.eye(2))),
                                                 Sensor("b", 3 * x, Gaussian.zero_mean([[1.0]]))],
              Gaussian.zero_mean([[0.01]]), Gaussian([0.2], [[1.0]]))
    pts = np.full((5, 1), 0.7)
    assert m.F(pts).shape == (5, 1, 1) and m.H(0, pts).shape == (5, 2, 1) and m.H(1, pts).shape == (5, 1, 1)
    assert m.f_hessian(pts).shape == (5, 1, 1, 1) and m.h_hessian(0, pts).shape == (5, 2, 1, 1)
    np.testing.assert_allclose(m.F(pts)[:, 0, 0], 0.8 + 0.1 * np.cos(0.7))
    np.testing.assert_allclose(m.h_hessian(0, pts)[:, :, 0, 0], np.tile([2.0, -np.sin(0.7)], (5, 1)))
    sc = scenario_of(m, network=SensorNetwork.from_edges(2, [(0, 1)]), steps=10)
    des = consensus_design(sc, mode="tuned")
    res = run_consensus(m, sc.network, sc.simulate(np.random.default_rng(1)).z, des)
    assert res.feasible and res.K.shape == (10, 2, 1, 2)
