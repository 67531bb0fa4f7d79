"""The consensus filter batched over Monte Carlo runs (filters.consensus_batch) against the per-run path.

The reference is the per-run, per-node loop of tests/consensus_reference.py (what run_consensus was
before the batch became the only implementation; production's run_consensus is a batch of one, tested
against the equations and independent filters in tests/test_consensus.py): run by run, the batch must give its numbers
(rtol 1e-9), its ``valid`` flags, its violations in the same order and its packet counts, on the
indoor robot, a user model with mixed sensor dimensions and bearings that cross ±π, and linear
models; with the fallback recursion, the neighbour rule, every linearisation rule, per-run inputs
and initial conditions, the bound-trace limit, a divergence in one run of the batch (the others go
on), a numerical breakdown in one run, and the first-step InputError; in modes paper, tuned and mse,
with and without the χ² gate, and replaying a fixed gain schedule; and one network per run (a sweep's
channel probabilities on one graph).
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import rules
from designer import Gaussian, Model, Sensor, SensorNetwork, simulate
from designer.attacks import FDISignal
from designer.design import ConsensusDesign, DesignOptions, make_design
from designer.validation import InputError
from filters.attacks import simulate_attacks
from consensus_reference import reference_consensus  # tests/ on the path
from filters.consensus import run_consensus
from filters.consensus_batch import EdgeAttacks, run_consensus_batch
from studies.scenarios import load_scenario

ARRAYS = ("x_post", "x_pred", "phi_post", "phi_pred", "K", "C", "margin28", "margin29", "theorem2", "sigma", "beta")


def assert_same_as_per_run(batch, refs):
    """Every run of the batch equals its per-run result: arrays (rtol 1e-9, NaN where NaN), flags, violations."""
    assert batch.runs == len(refs)
    for r, ref in enumerate(refs):
        got = batch.run(r)
        for name in ARRAYS:
            a, b = getattr(ref, name), getattr(got, name)
            assert a.shape == b.shape, (r, name)
            scale = np.nanmax(np.abs(np.where(np.isfinite(a), a, np.nan)), initial=0.0)
            np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-13 * max(scale, 1e-300), equal_nan=True,
                                       err_msg=f"run {r}, {name}")
        np.testing.assert_array_equal(got.valid, ref.valid, err_msg=f"run {r}, valid")
        assert len(got.violations) == len(ref.violations), r
        for v, w in zip(got.violations, ref.violations):
            assert {k: x for k, x in v.items() if k != "margin"} == {k: x for k, x in w.items() if k != "margin"}
            assert v["margin"] == pytest.approx(w["margin"], rel=1e-9, abs=1e-300), (r, v, w)
        assert got.feasible == ref.feasible and got.diverged == ref.diverged
        np.testing.assert_array_equal(got.gate_counts, ref.gate_counts, err_msg=f"run {r}, gate_counts")
    np.testing.assert_array_equal(batch.feasible, [ref.feasible for ref in refs])


# ----------------------------------------------------------------------------- the indoor robot
ROBOT_STEPS, ROBOT_RUNS = 25, 3


@pytest.fixture(scope="module")
def robot():
    sc = load_scenario("indoor-robot")
    net = sc.network.with_attacks(0.3, 0.2)
    traj = sc.simulate(np.random.default_rng(7), ROBOT_STEPS, batch=ROBOT_RUNS)
    atts = [simulate_attacks(net, ROBOT_STEPS, 3, np.random.default_rng(70 + r), signal=FDISignal(1.5, (0, 1)))
            for r in range(ROBOT_RUNS)]
    return sc, net, traj, atts


def robot_design(mode: str = "paper", **kw):
    return ConsensusDesign(epsilon=1 / 6, sigma=0.1, beta=0.1, tau=0.01, U=0.01 * np.eye(3), V=0.1 * np.eye(2),
                           delta=1.5 * np.sqrt(2), rule=rules.get(mode), **kw)


def per_run(model, net, z, des, inputs, atts, x0=None, phi0=None):
    out = []
    for r in range(z.shape[0]):
        u = None if inputs is None else (inputs if inputs.ndim == 2 else inputs[r])
        out.append(reference_consensus(model, net, z[r], des, inputs=u, attacks=None if atts is None else atts[r],
                                 x0=None if x0 is None else x0[r], phi0=None if phi0 is None else phi0[r]))
    return out


def test_robot_paper_design_matches_per_run(robot):
    """The paper's σ = β = 0.1 on the robot: (28), (29) and Theorem 2 fail at nodes along the runs."""
    sc, net, traj, atts = robot
    des = robot_design()
    batch = run_consensus_batch(sc.model, net, traj.z, des, inputs=traj.inputs, attacks=atts).detail
    refs = per_run(sc.model, net, traj.z, des, traj.inputs, atts)
    assert_same_as_per_run(batch, refs)
    conds = {v["condition"] for vs in batch.violations for v in vs}
    assert {"(28)", "(29)", "theorem2"} <= conds, "the case must exercise the fallback"
    assert batch.valid[:, 1:].any() and not batch.valid[:, -1].all()
    # the same attacks given in the batched form, and back
    ea = EdgeAttacks.from_patterns(net, atts)
    for r in range(ROBOT_RUNS):
        for f in ("dos", "fdi", "xi"):
            np.testing.assert_array_equal(getattr(ea.pattern(r, net.n_nodes), f), getattr(atts[r], f))
    again = run_consensus_batch(sc.model, net, traj.z, des, inputs=traj.inputs, attacks=ea).detail
    np.testing.assert_array_equal(again.x_post, batch.x_post)


def assert_variances_are_the_diagonals(model, net, z, des, **kw):
    """run_consensus_batch with variances keeps Φ's diagonals over the steps alone: the same estimates, validity,
    violations and predicted traces bit for bit, ``cov_diagonal`` the diagonals of the full run's Φ, ``cov`` None,
    and the comparison's verdicts on them those on the whole matrices."""
    from studies.consensus_design import bound_traces

    full = run_consensus_batch(model, net, z, des, **kw)
    lean = run_consensus_batch(model, net, z, des, variances=True, **kw)
    assert lean.cov is None and lean.detail.phi_post is None and full.cov_diagonal is None
    np.testing.assert_array_equal(lean.x, full.x)
    np.testing.assert_array_equal(lean.valid, full.valid)
    assert lean.violations == full.violations
    np.testing.assert_array_equal(lean.cov_diagonal, np.diagonal(full.cov, axis1=-2, axis2=-1))
    np.testing.assert_array_equal(lean.variance(), full.variance())
    if full.detail.predicted_mse is not None:
        np.testing.assert_array_equal(lean.detail.predicted_mse, full.detail.predicted_mse)
    np.testing.assert_array_equal(bound_traces(lean.variance(), lean.valid), bound_traces(full.cov, full.valid))
    return full, lean


def test_a_run_keeping_its_bounds_diagonals_alone_has_the_same_numbers(robot):
    """The paper design on the robot (its own steps, (28) and (29) failing at some nodes, the fallback taken)."""
    sc, net, traj, atts = robot
    assert_variances_are_the_diagonals(sc.model, net, traj.z, robot_design(), inputs=traj.inputs, attacks=atts)


@pytest.mark.parametrize("rule", ["hessian", "structured"])
def test_robot_linearisation_rules_with_inputs_and_priors_per_run(robot, rule):
    """Hessian-derived scalings per node and step; inputs, x0 and Φ0 that differ between runs."""
    sc, net, traj, atts = robot
    rng = np.random.default_rng(3)
    inputs = traj.inputs[None] * (1.0 + 0.2 * rng.standard_normal((ROBOT_RUNS, 1, 1)))
    x0 = sc.model.prior.mean + 0.05 * rng.standard_normal((ROBOT_RUNS, 3))
    phi0 = sc.model.prior.cov[None] * rng.uniform(0.5, 1.5, (ROBOT_RUNS, 1, 1))
    z = np.stack([sc.simulate(np.random.default_rng(20 + r), ROBOT_STEPS).z for r in range(ROBOT_RUNS)])
    des = robot_design(linearization=rule)
    batch = run_consensus_batch(sc.model, net, z, des, inputs=inputs, attacks=atts, x0=x0, phi0=phi0).detail
    assert_same_as_per_run(batch, per_run(sc.model, net, z, des, inputs, atts, x0, phi0))


def test_first_step_input_error_has_the_per_run_message(robot):
    sc, net, traj, atts = robot
    for change in (dict(sigma=1e5), dict(beta=1e5)):
        des = robot_design()._replace(**change)
        with pytest.raises(InputError) as ref:
            reference_consensus(sc.model, net, traj.z[0], des, inputs=traj.inputs, attacks=atts[0])
        with pytest.raises(InputError) as got:
            run_consensus_batch(sc.model, net, traj.z, des, inputs=traj.inputs, attacks=atts)
        assert str(got.value) == str(ref.value) and ("(28)" if "sigma" in change else "(29)") in str(got.value)


@pytest.mark.parametrize("rule", ["fixed", "structured"])
def test_robot_tuned_design_matches_per_run(robot, rule):
    """Mode tuned on the robot under DoS and FDI: the σ search, the weighted (27) with its per-node weights
    carried between steps (groups that come and go with the DoS pattern), Theorem 2 violations."""
    sc, net, traj, atts = robot
    steps = 4
    z = traj.z[:2, :steps]
    des = robot_design(mode="tuned", linearization=rule)
    batch = run_consensus_batch(sc.model, net, z, des, inputs=traj.inputs[:steps], attacks=atts[:2]).detail
    refs = per_run(sc.model, net, z, des, traj.inputs[:steps], atts[:2])
    assert_same_as_per_run(batch, refs)
    assert batch.valid.all() and np.isfinite(batch.beta).all() and (batch.beta > 0).all()
    assert any(v["condition"] == "theorem2" for vs in batch.violations for v in vs)
    lost = np.stack([a.dos[:steps][:, net.adjacency] for a in atts[:2]])
    assert lost.any() and not lost.all(), "the DoS pattern must change the nodes' groups"


@pytest.mark.parametrize("change", [dict(mode="mse"), dict(gate=0.05), dict(mode="tuned", gate=0.05),
                                    dict(mode="mse", gate=0.05)])
def test_other_modes_and_gates_match_per_run(robot, change):
    """Mode mse (rules.mse.filter) and gated designs (the χ² gate on the stacked channels) give the reference's
    numbers, predicted_mse and gate_counts (attacks given as EdgeAttacks; per-run x0)."""
    sc, net, traj, atts = robot
    steps = 3
    z = traj.z[:2, :steps]
    x0 = sc.model.prior.mean + 0.05 * np.random.default_rng(4).standard_normal((2, 3))
    des = robot_design(**change)
    batch = run_consensus_batch(sc.model, net, z, des, inputs=traj.inputs[:steps],
                                attacks=EdgeAttacks.from_patterns(net, atts[:2]), x0=x0).detail
    refs = per_run(sc.model, net, z, des, traj.inputs[:steps], atts, x0=x0)
    assert_same_as_per_run(batch, refs)
    for r, ref in enumerate(refs):
        np.testing.assert_array_equal(batch.gate_counts[r], ref.gate_counts)
        if ref.predicted_mse is None:
            assert batch.predicted_mse is None
        else:
            np.testing.assert_array_equal(batch.predicted_mse[r], ref.predicted_mse)
    if des.gate:
        assert batch.gate_counts[..., 1].sum() > 0, "the gate must reject some packets"


@pytest.mark.parametrize("change", [dict(), dict(gate=0.05), dict(mode="tuned", gate=0.05), dict(mode="mse"),
                                    dict(mode="mse", gate=0.05)])
def test_replayed_gain_schedule_matches_per_run(robot, change):
    """A fixed gain schedule replayed in every run (any mode: the gains are given, every node on the fallback
    recursion, nothing certified), with and without the gate: the reference's numbers run by run."""
    sc, net, traj, atts = robot
    steps = 5
    z = traj.z[:, :steps]
    first = reference_consensus(sc.model, net, traj.z[0], robot_design(), inputs=traj.inputs, attacks=atts[0])
    gains = (first.K, 0.7 * first.C)  # one schedule of ROBOT_STEPS steps, longer than the runs
    des = robot_design(**change)
    batch = run_consensus_batch(sc.model, net, z, des, inputs=traj.inputs[:steps], attacks=atts, gains=gains).detail
    refs = [reference_consensus(sc.model, net, z[r], des, inputs=traj.inputs[:steps], attacks=atts[r], gains=gains)
            for r in range(ROBOT_RUNS)]
    assert_same_as_per_run(batch, refs)
    assert not batch.valid.any() and all(not vs for vs in batch.violations)
    np.testing.assert_array_equal(batch.C, np.broadcast_to(gains[1][:steps], batch.C.shape))
    if des.gate:
        assert batch.gate_counts[..., 1].sum() > 0, "the gate must reject some packets"


def test_replayed_gains_are_checked(robot):
    sc, net, traj, atts = robot
    K, C = np.zeros((ROBOT_STEPS, 8, 3, 2)), np.zeros((ROBOT_STEPS, 8, 3, 3))
    for bad in ((K[:3], C[:3]), (K[..., :1], C), (K, C[:, :4]), (K,)):
        with pytest.raises(InputError, match="gains must"):
            run_consensus_batch(sc.model, net, traj.z, robot_design(), inputs=traj.inputs, gains=bad)


def test_a_run_alone_is_its_row_of_the_batch(robot):
    """run_consensus (a batch of one) gives, bit for bit, the row of the same run in a batch of several, in every
    mode, with the gate and with a replayed schedule: a run's numbers do not depend on the other runs."""
    sc, net, traj, atts = robot
    steps = 4
    z = traj.z[:, :steps]
    gains = (np.full((steps, 8, 3, 2), 0.05), np.full((steps, 8, 3, 3), 0.01))
    for change, g in ((dict(gate=0.05), None), (dict(mode="tuned"), None), (dict(mode="mse", gate=0.05), None),
                      (dict(), gains)):
        des = robot_design(**change)
        batch = run_consensus_batch(sc.model, net, z, des, inputs=traj.inputs[:steps], attacks=atts, gains=g).detail
        for r in range(ROBOT_RUNS):
            alone = run_consensus(sc.model, net, z[r], des, inputs=traj.inputs[:steps], attacks=atts[r], gains=g)
            for name in ARRAYS + ("valid", "gate_counts"):
                np.testing.assert_array_equal(getattr(alone, name), getattr(batch.run(r), name), err_msg=name)
            assert alone.violations == batch.violations[r]


def test_bad_shapes_are_refused(robot):
    sc, net, traj, atts = robot
    with pytest.raises(InputError, match="runs, steps"):
        run_consensus_batch(sc.model, net, traj.z[0], robot_design(), inputs=traj.inputs)
    with pytest.raises(InputError, match="one AttackPattern per run"):
        run_consensus_batch(sc.model, net, traj.z, robot_design(), inputs=traj.inputs, attacks=atts[:2])
    with pytest.raises(InputError, match="x0"):
        run_consensus_batch(sc.model, net, traj.z, robot_design(), inputs=traj.inputs, x0=np.zeros((2, 3)))


# ----------------------------------------------------------------------------- mixed sensors, bearings across ±π
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SITES = [(0.0, 0.0), (40.0, 0.0), (0.0, 40.0), (30.0, 12.0), (-20.0, 20.0)]


def mixed_model():
    """The user model examples/mixed_sensors_model.py (sensor dimensions 2, 1, 1, 1, 1 on a star) with
    bearing-only sensor 3 moved to (30, 12): the target passes left of it through its horizon, so its
    bearing crosses ±π and the residuals need wrapping; a tighter prior, channels attacked as below."""
    spec = importlib.util.spec_from_file_location("mixed_sensors_example", EXAMPLES / "mixed_sensors_model.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    example.SITES = SITES
    m = example.model()
    model = Model(m.name, m.x, m.f_expr, m.sensors, m.process_noise,
                  Gaussian(example.X0, np.diag([0.25, 0.01, 0.25, 0.01])))
    net = SensorNetwork.from_edges(5, [(0, 1), (0, 2), (0, 3), (0, 4)], dos_prob=0.1, fdi_prob=0.05)
    return model, net


@pytest.mark.parametrize("rule", ["fixed", "hessian", "structured"])
def test_mixed_sensor_dimensions_and_wrapped_bearings(rule):
    model, net = mixed_model()
    runs, steps = 4, 20
    traj = simulate(model, steps, np.random.default_rng(5), batch=runs)
    bearing3 = np.arctan2(traj.x[:, 1:, 2] - SITES[3][1], traj.x[:, 1:, 0] - SITES[3][0])
    assert np.any(np.abs(np.diff(bearing3, axis=1)) > np.pi, axis=1).all(), "sensor 3's bearing must cross ±π"
    atts = [simulate_attacks(net, steps, 4, np.random.default_rng(50 + r), signal=FDISignal(2.0, (0, 2)))
            for r in range(runs)]
    des = make_design(model, net, rule=rules.get("paper"), delta=2.0 * np.sqrt(2.0), options=DesignOptions(linearization=rule),
                      x0=model.prior.mean)
    batch = run_consensus_batch(model, net, traj.z, des, attacks=atts).detail
    refs = per_run(model, net, traj.z, des, None, atts)
    assert_same_as_per_run(batch, refs)
    assert batch.K.shape == (runs, steps, 5, 4, 2) and np.all(batch.K[..., 1:, :, 1] == 0.0)
    # the filter follows the target across the bearing's jump (no 2π residual taken as an error)
    assert not any(batch.diverged)
    assert np.max(np.abs(batch.x_post[:, -1, :, 0] - traj.x[:, -1, None, 0])) < 10.0


def test_mixed_sensor_dimensions_tuned():
    """Mode tuned on the user model with sensors of dimensions 2 and 1 (two groups of nodes, gains padded)
    and a star whose centre has four neighbours while the leaves have one."""
    model, net = mixed_model()
    runs, steps = 3, 6
    traj = simulate(model, steps, np.random.default_rng(6), batch=runs)
    atts = [simulate_attacks(net, steps, 4, np.random.default_rng(60 + r), signal=FDISignal(2.0, (0, 2)))
            for r in range(runs)]
    des = make_design(model, net, rule=rules.get("tuned"), delta=2.0 * np.sqrt(2.0), options=DesignOptions(mode="tuned"), x0=model.prior.mean,
                      signal=FDISignal(2.0, (0, 2)))
    batch = run_consensus_batch(model, net, traj.z, des, attacks=atts).detail
    assert_same_as_per_run(batch, per_run(model, net, traj.z, des, None, atts))
    assert batch.K.shape == (runs, steps, 5, 4, 2) and np.all(batch.K[..., 1:, :, 1] == 0.0)
    assert batch.valid.all()


# ----------------------------------------------------------------------------- linear models
CHAIN_A = np.array([[1.0, 0.1], [-0.05, 0.98]])


def chain_model(R0=1e4):
    """A path 0 - 1 - 2; node 0's sensor is nearly useless, so its bound blows up and leaves Theorem 1's
    recursion, and its neighbours' flags drop through its non-bound prediction (tests/test_consensus.py)."""
    x = ca.SX.sym("x", 2)
    Rs = [R0 * np.eye(2), 0.01 * np.eye(2), 0.02 * np.eye(2)]
    sensors = [Sensor(f"s{i}", ca.vertcat(x[0] + 0.1 * i * x[1], x[1]), Gaussian.zero_mean(R)) for i, R in enumerate(Rs)]
    model = Model("chain", x, ca.mtimes(ca.DM(CHAIN_A), x), sensors, Gaussian.zero_mean(1e-3 * np.eye(2)),
                  Gaussian(np.zeros(2), 0.01 * np.eye(2)))
    net = SensorNetwork.from_edges(3, [(0, 1), (1, 2)], dos_prob=0.2, fdi_prob=0.2)
    des = ConsensusDesign(epsilon=0.25, sigma=0.1, beta=0.1, tau=0.01, U=0.01 * np.eye(2), V=0.01 * np.eye(2),
                          delta=0.1, rule=rules.get("paper"))
    return model, net, des


def test_linear_chain_neighbour_rule_and_a_diverging_run():
    model, net, des = chain_model()
    runs, steps = 5, 25
    traj = simulate(model, steps, np.random.default_rng(41), batch=runs)
    z = traj.z.copy()
    z[2, 9, 2:4] = 1e14  # run 2: node 1 takes a huge measurement at step 10 and leaves finite numbers
    atts = [simulate_attacks(net, steps, 2, np.random.default_rng(42 + r), signal=FDISignal(0.1, (0,)))
            for r in range(runs)]
    batch = run_consensus_batch(model, net, z, des, attacks=atts).detail
    refs = per_run(model, net, z, des, None, atts)
    assert_same_as_per_run(batch, refs)
    div = batch.diverged
    assert [d is not None for d in div] == [False, False, True, False, False]
    assert div[2]["step"] == 10 and div[2]["node"] == 1
    assert np.isnan(batch.x_post[2, 10:]).all() and np.isfinite(batch.x_post[[0, 1, 3, 4]]).all()
    # node 0 leaves the recursion; nodes 1 and 2 lose their flags through it (a neighbour rule case)
    assert any(v["node"] == 0 and v["condition"] in ("(28)", "(29)") for vs in batch.violations for v in vs)
    assert not batch.valid[0, -1].any() and batch.valid[0, 1].all()


def test_linear_chain_tuned_with_a_diverging_run():
    """Mode tuned on the chain: run 2 diverges at step 10 and stops there, the others go on."""
    model, net, des = chain_model()
    des = des._replace(rule=rules.get("tuned"))
    runs, steps = 3, 12
    traj = simulate(model, steps, np.random.default_rng(41), batch=runs)
    z = traj.z.copy()
    z[2, 9, 2:4] = 1e14
    atts = [simulate_attacks(net, steps, 2, np.random.default_rng(42 + r), signal=FDISignal(0.1, (0,)))
            for r in range(runs)]
    batch = run_consensus_batch(model, net, z, des, attacks=atts).detail
    assert_same_as_per_run(batch, per_run(model, net, z, des, None, atts))
    assert [d is not None for d in batch.diverged] == [False, False, True]
    assert batch.diverged[2]["step"] == 10 and np.isfinite(batch.x_post[[0, 1]]).all()


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning", "ignore:invalid value:RuntimeWarning")
@pytest.mark.parametrize("mode", ["paper", "tuned"])
def test_bound_trace_limit_then_overflow(mode):
    """σ = β = 0, U = V = 0 (paper) or the tuned searches, and a blind sensor on an unstable plant: every node
    keeps Theorem 1's recursion until the bound's trace reaches 1e100 (a (28) violation with its reason), then the
    fallback overflows."""
    x = ca.SX.sym("x", 2)
    sensors = [Sensor(f"blind{i}", 0.0 * x[0], Gaussian.zero_mean([[1.0]])) for i in range(2)]
    model = Model("unstable", x, 1e3 * x, sensors, Gaussian.zero_mean(1e-3 * np.eye(2)),
                  Gaussian(np.zeros(2), np.eye(2)))
    net = SensorNetwork.from_edges(2, [(0, 1)])
    des = ConsensusDesign(epsilon=0.5, sigma=0.0, beta=0.0, tau=0.01, U=np.zeros((2, 2)), V=np.zeros((1, 1)),
                          delta=0.0, rule=rules.get("paper"))
    if mode == "tuned":  # the tuned searches at every node until the limit (σ > 0 and β > 0: U, V nonzero)
        des = des._replace(rule=rules.get("tuned"), U=0.01 * np.eye(2), V=0.1 * np.eye(1), delta=0.1)
    z = np.random.default_rng(0).standard_normal((2, 60, 2))
    batch = run_consensus_batch(model, net, z, des).detail
    assert_same_as_per_run(batch, per_run(model, net, z, des, None, None))
    reasons = [v.get("reason", "") for v in batch.violations[0]]
    assert any("1e+100" in r for r in reasons) and batch.diverged[0] is not None


def test_numerical_breakdown_in_one_run(monkeypatch):
    """A LinAlgError in one item of a stacked solve is found item by item: only that run stops."""
    model, net, _ = chain_model(R0=1.0)
    des = ConsensusDesign(epsilon=0.25, sigma=0.0, beta=0.0, tau=0.01, U=np.zeros((2, 2)), V=np.zeros((2, 2)),
                          delta=0.0, rule=rules.get("paper"))
    runs, steps = 3, 6
    z = simulate(model, steps, np.random.default_rng(1), batch=runs).z
    phi0 = np.stack([0.01 * np.eye(2), 1e7 * np.eye(2), 0.01 * np.eye(2)])  # run 1: a huge Φ_0|0
    solve = np.linalg.solve

    def fragile_solve(a, b):  # "singular" whenever the right-hand side H M is huge
        if np.any(np.abs(b) > 1e6):
            raise np.linalg.LinAlgError("Singular matrix")
        return solve(a, b)

    monkeypatch.setattr(np.linalg, "solve", fragile_solve)
    batch = run_consensus_batch(model, net, z, des, phi0=phi0).detail
    refs = per_run(model, net, z, des, None, None, phi0=phi0)
    assert_same_as_per_run(batch, refs)
    assert [d is not None for d in batch.diverged] == [False, True, False]
    assert batch.diverged[1]["reason"] == "numerical breakdown: Singular matrix"


@pytest.mark.parametrize("mode", ["paper", "tuned", "mse"])
def test_per_run_inputs_without_columns_are_no_inputs(mode):
    """A model without inputs simulated per run has inputs of shape (runs, steps, 0): the same numbers as none."""
    from studies.consensus_design import consensus_design

    sc = load_scenario("target-range-bearing")
    traj = sc.simulate(np.random.default_rng(3), 5, batch=2)
    des = consensus_design(sc, DesignOptions(mode=mode))
    a = run_consensus_batch(sc.model, sc.network, traj.z, des, inputs=np.zeros((2, 5, 0))).detail
    b = run_consensus_batch(sc.model, sc.network, traj.z, des).detail
    np.testing.assert_array_equal(a.x_post, b.x_post)
    np.testing.assert_array_equal(a.phi_post, b.phi_post)


@pytest.mark.parametrize("change", [dict(), dict(mode="tuned"), dict(mode="mse"), dict(mode="tuned", gate=0.05),
                                    dict(mode="mse", gate=0.05)])
def test_one_network_per_run_is_each_runs_own_filter(robot, change, monkeypatch):
    """The runs of a sweep in one batch: each run with its own channel probabilities (DoS, FDI; the statistics of
    its bounds, tuned weights and mse gains) on the shared graph gives the reference on its own network; runs given
    the same network give what one network for all gives."""
    sc, net, traj, atts = robot
    steps = 4
    nets = [sc.network.with_attacks(0.0, 0.3), net, sc.network.with_attacks(0.35, 0.05)]
    z = traj.z[:, :steps]
    sig = FDISignal(1.5, (0, 1))  # the attacks' signal: the mse gains use its moments and the falsified share q
    des = robot_design(**change)._replace(fdi_moment=sig.moment(3), fdi_mean=sig.mean(3), fdi_span=sig.span(3),
                                          fdi_signal=sig)
    batch = run_consensus_batch(sc.model, nets, z, des, inputs=traj.inputs[:steps], attacks=atts).detail
    refs = [reference_consensus(sc.model, nets[r], z[r], des, inputs=traj.inputs[:steps], attacks=atts[r])
            for r in range(len(nets))]
    assert_same_as_per_run(batch, refs)
    if batch.predicted_mse is not None:
        for r, ref in enumerate(refs):
            np.testing.assert_allclose(batch.predicted_mse[r], ref.predicted_mse, rtol=1e-9)
    # the probabilities matter (in mode tuned little: the weights absorb them), far more than the batch's rounding:
    # run 0 on run 2's network is farther from run 0 than the batch's run 0 is
    other = reference_consensus(sc.model, nets[2], z[0], des, inputs=traj.inputs[:steps], attacks=atts[0])

    def gap(res):
        return max(np.nanmax(np.abs(getattr(res, f) - getattr(refs[0], f)), initial=0.0)
                   for f in ("x_post", "phi_post", "K", "C"))

    assert gap(other) > 1e3 * gap(batch.run(0)) and gap(other) > 0
    same = run_consensus_batch(sc.model, [net] * 3, z, des, inputs=traj.inputs[:steps], attacks=atts).detail
    one = run_consensus_batch(sc.model, net, z, des, inputs=traj.inputs[:steps], attacks=atts).detail
    np.testing.assert_array_equal(same.x_post, one.x_post)
    np.testing.assert_array_equal(same.phi_post, one.phi_post)
    if des.mode == "mse":  # in sub-batches of one run each, every run keeps its own network
        import rules.mse.filter as mse_batch

        monkeypatch.setattr(mse_batch, "MEMORY_BUDGET", 1)
        apart = run_consensus_batch(sc.model, nets, z, des, inputs=traj.inputs[:steps], attacks=atts).detail
        np.testing.assert_array_equal(apart.x_post, batch.x_post)
        np.testing.assert_array_equal(apart.phi_post, batch.phi_post)


def test_networks_per_run_are_checked(robot):
    sc, net, traj, atts = robot
    with pytest.raises(InputError, match=r"network must be a SensorNetwork or one per run \(3\)"):
        run_consensus_batch(sc.model, [net, net], traj.z, robot_design(), inputs=traj.inputs)
    ring = SensorNetwork.from_edges(8, [(i, (i + 1) % 8) for i in range(8)])
    with pytest.raises(InputError, match="share one graph"):
        run_consensus_batch(sc.model, [net, net, ring], traj.z, robot_design(), inputs=traj.inputs)


def test_edge_attacks_simulated_on_the_channels_are_the_dense_patterns_channels():
    """EdgeAttacks.simulate draws as simulate_attacks does and applies the same law (filters.attacks.channel_attacks)
    to the network's channels alone: the same numbers, bit for bit, as EdgeAttacks.from_patterns of the dense patterns,
    on a network with channel-by-channel probabilities and a signal with a mean."""
    rng = np.random.default_rng(4)
    adj = np.zeros((6, 6), bool)
    for i, j in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (0, 3)]:
        adj[i, j] = adj[j, i] = True
    dos = np.where(adj, rng.uniform(0.0, 0.3, (6, 6)), 0.0)
    fdi = np.where(adj, rng.uniform(0.0, 0.3, (6, 6)), 0.0)
    net = SensorNetwork(6, adj, dos_prob=dos, fdi_prob=fdi)
    signal = FDISignal(amplitude=(0.5, 0.2), components=(0, 2), law="constant")
    seeds = np.random.SeedSequence(9).spawn(3)
    dense = EdgeAttacks.from_patterns(net, [simulate_attacks(net, 12, 4, np.random.default_rng(s), signal)
                                            for s in seeds])
    edge = EdgeAttacks.simulate(net, 12, 4, [np.random.default_rng(s) for s in seeds], signal)
    for field in EdgeAttacks._fields:
        assert np.array_equal(getattr(edge, field), getattr(dense, field)), field
    assert edge.fdi.any() and edge.dos.any() and np.any(edge.xi != 0.0)
    with pytest.raises(InputError, match="one Generator per run"):
        EdgeAttacks.simulate(net, 12, 4, [], signal)



def test_run_consensus_takes_one_runs_edge_attacks(robot):
    sc, net, traj, atts = robot
    des = robot_design()
    u = traj.inputs if traj.inputs.ndim == 2 else traj.inputs[0]
    dense = run_consensus(sc.model, net, traj.z[0], des, inputs=u, attacks=atts[0])
    edge = run_consensus(sc.model, net, traj.z[0], des, inputs=u, attacks=EdgeAttacks.from_patterns(net, atts[:1]))
    assert np.array_equal(dense.x_post, edge.x_post) and np.array_equal(dense.phi_post, edge.phi_post)
    with pytest.raises(InputError, match="attacks must cover"):
        run_consensus(sc.model, net, traj.z[0], des, inputs=u, attacks=EdgeAttacks.from_patterns(net, atts))


def test_the_channel_sums_add_each_nodes_channels_in_order_alone_or_in_the_batch():
    """Exchange.sum, Exchange.weighted_sum and Exchange.node_sum add a node's incoming channels from the first,
    ((v0 + v1) + v2) + ..., to the bit (a Python loop is the reference), on a graph with degrees 1 to 9 and values
    over 16 orders of magnitude (where another association shows)."""
    from filters.consensus_batch import Exchange

    rng = np.random.default_rng(3)
    n = 24
    edges = [(i, i + 1) for i in range(n - 1)] + [(0, j) for j in range(2, 10)] + [(5, 17), (9, 20), (3, 12)]
    ex = Exchange(SensorNetwork.from_edges(n, edges))
    E, deg = ex.receiver.size, np.bincount(ex.receiver, minlength=n)
    assert deg.min() >= 1 and deg.max() >= 9
    w = rng.random((2, E)) * (rng.random((2, E)) > 0.2)
    for tail in ((), (5,), (4, 4)):
        values = rng.normal(size=(2, n) + tail) * 10.0 ** rng.uniform(-8, 8, size=(2, n) + tail)
        products = w.reshape(w.shape + (1,) * len(tail)) * values[:, ex.sender]
        total, weighted = ex.sum(products), ex.weighted_sum(w, values)
        assert np.array_equal(total, weighted)
        for i in range(n):
            chans = np.flatnonzero(ex.receiver == i)
            ref = products[:, chans[0]].copy()
            for c in chans[1:]:
                ref = ref + products[:, c]
            assert np.array_equal(total[:, i], ref), (i, tail)
            assert np.array_equal(Exchange.node_sum(products[:, chans]), ref), (i, tail)
