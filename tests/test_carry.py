"""Nodes that carry their regions (``--carry region``, designer.regions.carried_states): the relay rules' nodes carry
their region and the states their ball's measurements and the dynamics of those need, and are the whole-state
filter on them.

* the carried sets against finite differences: no state left out moves a carried state's dynamics or a ball
  sensor's measurement, and every carried state beyond the region and the supports is read by a carried state's
  dynamics;
* the relay filter carrying regions (tree and flood routing, DoS and FDI on the channels, a bearing and a
  two-dimensional sensor, dynamics coupling some states) against the same filter carrying the whole state (a second
  run of the existing implementation): the same estimates and covariance blocks on the carried states;
* the node filters carrying regions replay the batched filter bit for bit;
* the stationary certificate carrying regions is the whole-state one's fixed point restricted to the carried states;
* a design from a model file that declares REGIONS carries them by default: its regional verdict's numbers are the
  whole-state design's (``--carry whole``) numbers on the regions, schedule.npz holds the carried coordinates and
  reads back; bad uses exit 2 naming --carry;
* the studies (consensus-robot, comparison) score nodes carrying their regions as the whole-state design on them.
"""
from __future__ import annotations

import csv
import re
import json

import casadi as ca
import numpy as np
import pytest

import rules
from designer.attacks import FDISignal
from designer.design import DesignOptions, make_design
from designer.model import Model, Sensor
from designer.network import SensorNetwork
from designer.noise import Gaussian
from designer.regions import Carried, carried_states, dynamics_support, sensed_regions
from designer.schedule import load_schedule
from designer.verdict import verdict
from filters.attacks import simulate_attacks
from filters.consensus_batch import run_consensus_batch
from filters.node import node_network
from rules.relay.design import relay_carried, relay_routes, relay_stationary
from rules.relay.filter import run_relay_batch
from studies.cli import main

N = 8
EDGES = [(i, (i + 1) % N) for i in range(N)] + [(0, 4)]
SIGNAL = FDISignal(amplitude=0.05)


def coupled_model(stable: bool = False) -> Model:
    """Eight angles on a ring: the even ones drift with their next neighbour (f_i reads x_{i+1}), the others walk;
    node i measures the flow sin(x_i - x_{i+1}), node 3 also a bearing to (x3, x4 + 3), node 6 its own angle (the
    absolute reference)."""
    x = ca.SX.sym("x", N)
    a = 0.95 if stable else 1.0
    f = ca.vertcat(*[a * x[i] + (0.05 * ca.sin(x[(i + 1) % N]) if i % 2 == 0 else 0.0) for i in range(N)])
    sensors = []
    for i in range(N):
        h = [5.0 * ca.sin(x[i] - x[(i + 1) % N])]
        var = [0.02 ** 2]
        if i == 3:
            h.append(ca.atan2(x[4] + 3.0, x[3] + 1.0))
            var.append(0.01 ** 2)
        if i == 6:
            h.append(x[6])
            var.append(0.01 ** 2)
        sensors.append(Sensor(f"s{i}", ca.vertcat(*h), Gaussian.zero_mean(np.diag(var)),
                              angles=(1,) if i == 3 else ()))
    return Model("ring", x, f, sensors, process_noise=Gaussian.zero_mean(1e-4 * np.eye(N)),
                 prior=Gaussian(np.linspace(0.1, -0.1, N), 0.05 ** 2 * np.eye(N)))


def network(dos=0.15, fdi=0.1) -> SensorNetwork:
    return SensorNetwork.from_edges(N, EDGES, dos_prob=dos, fdi_prob=fdi)


REGIONS = [np.array([i]) for i in range(N)]


def test_the_carried_states_leave_out_only_what_neither_the_dynamics_nor_the_ball_reads():
    model = coupled_model()
    routes = relay_routes(network(), 1)
    balls = [routes.ball(i) for i in range(N)]
    carried = carried_states(model, REGIONS, balls)
    rng = np.random.default_rng(2)
    dep = dynamics_support(model)
    support = sensed_regions(model)
    for i, c in enumerate(carried):
        assert set(REGIONS[i]) <= set(c)
        out = np.setdiff1d(np.arange(N), c)
        for _ in range(3):
            x = rng.normal(0.0, 0.3, N)
            y = x.copy()
            y[out] += rng.normal(0.0, 0.5, out.size)
            assert np.allclose(model.f_expected(x, 0, np.zeros(0))[c], model.f_expected(y, 0, np.zeros(0))[c],
                               rtol=0, atol=1e-14)
            for s in balls[i]:
                assert np.allclose(model.h(int(s), x, 1), model.h(int(s), y, 1), rtol=0, atol=1e-14)
        # every state carried beyond the region and the supports is read by a carried state's dynamics
        needed = set(REGIONS[i]).union(*[set(support[int(s)]) for s in balls[i]])
        for j in set(c) - needed:
            x = rng.normal(0.0, 0.3, N)
            y = x.copy()
            y[j] += 0.5
            assert np.any(np.abs(model.f_expected(x, 0, np.zeros(0))[c] - model.f_expected(y, 0, np.zeros(0))[c])
                          > 1e-6)
        assert not dep[np.ix_(c, out)].any()
    # node 0 measures x0 - x1, x7 - x0 (its ball at one hop: nodes 7, 1, 4) ... and x0's dynamics read x1: the
    # walks of the odd states read nothing else, so a node in the middle of the ring leaves some states out
    assert any(len(c) < N for c in carried)


@pytest.mark.parametrize("routing", ["tree", "flood"])
def test_carrying_the_regions_gives_the_whole_state_filter_on_the_carried_states(routing):
    model, net = coupled_model(), network()
    runs, steps = 3, 15
    rng = np.random.default_rng(7)
    z = rng.normal(0.0, 0.05, (runs, steps, model.n_z))  # any measurements: the two must agree on them
    att = [simulate_attacks(net, steps, N, np.random.default_rng(10 + r), SIGNAL) for r in range(runs)]
    whole = run_relay_batch(model, net, z, 2, attacks=att, signal=SIGNAL, routing=routing)
    part = run_relay_batch(model, net, z, 2, attacks=att, signal=SIGNAL, routing=routing, regions=REGIONS)
    carry = Carried(part.carried, N)
    assert part.cov.shape == (runs, steps + 1, N, carry.m, carry.m) and (carry.used.sum(1) < N).any()
    held = np.zeros((N, N), dtype=bool)
    for i, row in enumerate(part.carried):
        held[i, row[row >= 0]] = True
    assert np.isnan(part.x[..., ~held]).all() and np.isfinite(part.x[..., held]).all()
    scale = np.abs(whole.x).max()
    assert np.allclose(part.x[..., held], whole.x[..., held], rtol=0, atol=1e-10 * scale)
    block = carry.matrix(whole.cov)
    assert np.allclose(part.cov, block, rtol=1e-9, atol=1e-12 * np.abs(block).max())
    assert np.all(part.cov[..., ~carry.used, :] == 0.0)  # the unused places hold zero
    # and the whole state is not what a node carries: its covariance there differs from its carried block's
    assert not np.allclose(np.trace(whole.cov, axis1=-2, axis2=-1), np.trace(part.cov, axis1=-2, axis2=-1))


def relay_design(model, net, hops, regions=REGIONS, mode="relay"):
    return make_design(model, net, rule=rules.get(mode), delta=0.0,
                       options=DesignOptions(mode=mode, rounds=hops, carry="region" if regions else None),
                       x0=model.prior.mean, signal=SIGNAL, regions=regions)


@pytest.mark.parametrize("mode", ["relay", "flood"])
def test_the_node_filters_carrying_regions_replay_the_batch_bit_for_bit(mode):
    model, net = coupled_model(), network()
    steps = 10
    rng = np.random.default_rng(3)
    z = rng.normal(0.0, 0.05, (1, steps, model.n_z))
    att = simulate_attacks(net, steps, N, np.random.default_rng(4), SIGNAL)
    design = relay_design(model, net, 2, mode=mode)
    batch = run_consensus_batch(model, net, z, design, attacks=[att])
    nodes = node_network(model, net, design)
    x, P = nodes.run(z[0], att)
    assert np.array_equal(x, batch.x[0], equal_nan=True)
    assert np.array_equal(P, batch.cov[0])
    # Φ kept as its diagonals alone (a comparison's), in the carried coordinates: the same numbers
    from test_consensus_batch import assert_variances_are_the_diagonals
    full, lean = assert_variances_are_the_diagonals(model, net, z, design, attacks=[att])
    assert lean.cov_diagonal.shape[-1] == batch.carried.shape[-1] and lean.carried is not None
    assert all(np.array_equal(nd.states, row) for nd, row in zip(nodes.nodes, batch.carried))


def test_the_stationary_certificate_carrying_regions_is_the_whole_ones_on_the_carried_states():
    model, net = coupled_model(stable=True), network()
    whole = relay_stationary(model, net, relay_design(model, net, 2, regions=None), x=model.prior.mean)
    part = relay_stationary(model, net, relay_design(model, net, 2), x=model.prior.mean)
    assert whole.converged and part.converged
    carry = relay_carried(model, relay_routes(net, 2), REGIONS)
    assert np.array_equal(part.carried, carry.index)
    assert np.allclose(part.Phi, carry.matrix(whole.Phi), rtol=1e-6, atol=1e-12)
    assert np.allclose(part.traces(), [whole.Phi[i, i, i] for i in range(N)], rtol=1e-6)
    for cert in (whole, part):  # the LMI confirms each fixed point
        assert cert.lmi["relative_residual"] <= 1e-6


def test_the_accelerated_stationary_recursion_reaches_the_plain_ones_fixed_point_carrying_regions(monkeypatch):
    """Anderson acceleration (designer.anderson) of each node's recursion: the same fixed point as the plain
    iteration, in fewer iterations, with every node padded to the widest carried set (its padded rows and columns
    zero: a first version took them for an indefinite matrix and never extrapolated)."""
    import rules.relay.design as relay

    model, net = coupled_model(stable=True), network()
    design = relay_design(model, net, 2)
    fast = relay_stationary(model, net, design, x=model.prior.mean, lmi=False)
    carry = relay_carried(model, relay_routes(net, 2), REGIONS)
    assert (carry.index < 0).any()  # some node is padded
    monkeypatch.setattr(relay, "STATIONARY_MEMORY", 0)
    plain = relay_stationary(model, net, design, x=model.prior.mean, lmi=False)
    assert fast.converged and plain.converged
    scale = np.abs(plain.Phi).max(axis=(1, 2))[:, None, None]
    assert np.all(np.abs(fast.Phi - plain.Phi) <= 1e-7 * scale)
    assert 2 * fast.iterations <= plain.iterations, (fast.iterations, plain.iterations)


MODEL_FILE = '''"""A ring of eight angles (tests/test_carry.py's coupled model) as a model file."""
import sys
sys.path.insert(0, {tests!r})
from designer import AttackSpec, FDISignal, SensorNetwork
from test_carry import EDGES, N, coupled_model

NETWORK = SensorNetwork.from_edges(N, EDGES)
ATTACKS = AttackSpec(dos=0.15, fdi=0.1, signal=FDISignal(amplitude=0.05))
STEPS = 20
{regions}


def model():
    return coupled_model(stable=True)
'''


def model_file(tmp_path, regions="REGIONS = [[i] for i in range(N)]"):
    import os

    path = tmp_path / "ring.py"
    path.write_text(MODEL_FILE.format(tests=os.path.dirname(__file__), regions=regions))
    return path


@pytest.mark.slow
def test_a_design_carrying_regions_is_judged_on_them_with_the_whole_designs_numbers(tmp_path):
    path = model_file(tmp_path)
    a, b = tmp_path / "whole", tmp_path / "region"
    assert main(["design", str(path), "--mode", "relay", "--rounds", "2", "--carry", "whole", "--out", str(a)]) == 0
    assert main(["design", str(path), "--mode", "relay", "--rounds", "2", "--out", str(b)]) == 0  # REGIONS: carried
    ja, jb = (json.loads((d / "schedule.json").read_text()) for d in (a, b))
    ra, rb = ja["verdict_detail"]["region"], jb["verdict_detail"]["region"]
    assert np.allclose(rb["final_trace"], ra["final_trace"], rtol=1e-9)
    assert jb["verdict_detail"]["judged"] == "region" and ja["verdict_detail"]["judged"] == "whole state"
    assert np.allclose(jb["verdict_detail"]["final_trace"], ra["final_trace"], rtol=1e-9)
    assert np.allclose(jb["verdict_detail"]["ratio_centralized"], ra["ratio_centralized"], rtol=1e-9)
    # the trace bound is over each node's region, and reads back from schedule.npz
    sched = load_schedule(b, lambda name, param: rules.get(name))
    m = sched.carried.shape[1]
    assert sched.Phi.shape == (N, 21, m, m) and (sched.carried < 0).any()
    assert np.allclose(np.array(jb["trace_bound"], dtype=float), sched.judged_traces(), rtol=1e-12)
    with np.load(a / "schedule.npz") as whole:
        Phi = whole["Phi"]
    assert np.allclose(sched.judged_traces(), [Phi[i, 1:, i, i] for i in range(N)], rtol=1e-9)
    assert all(jb["state_names"][i] in jb["carried"][i] for i in range(N)) and jb["carry"] == "region"
    # the stationary certificates: the regional one on each node's region
    sb = jb["stationary_certificate"]
    assert sb["verdict"] == "certified" and sb["bounded"]
    assert sb["trace"] is not None and len(sb["trace"]) == N
    # cfdesign report reads the directory again; one whose carried arrays do not agree with Φ (a file from
    # elsewhere) is reported from schedule.json's trace_bound, not an internal error
    import shutil

    with np.load(b / "schedule.npz") as d:
        arrays = dict(d)
    for k, bad in enumerate(({"carried": arrays["carried"] + N}, {"region_mask": np.ones((2, 2), dtype=bool)})):
        copy = tmp_path / f"copy{k}"
        shutil.copytree(b, copy)
        np.savez(copy / "schedule.npz", **{**arrays, **bad})
        assert main(["report", str(copy)]) == 0 and (copy / "report.md").is_file()


@pytest.mark.slow
def test_a_map_judges_and_ranks_nodes_carrying_regions_as_their_design_does(tmp_path):
    """cfdesign feasibility on a model with REGIONS: a relay map's nodes carry their regions and each point is the
    design's stationary certificate there (the map had judged the whole state: 'vacuous' where the design said
    'certified' on a 24-buoy model); --carry whole maps the whole state; an automatic map ranks its whole-state
    candidates on the regions too, with the references on the same states."""
    from studies.consensus_design import consensus_design, stationary_record
    from studies.scenarios import load_scenario

    path = model_file(tmp_path)
    grid = "dos=0.1:0.3:2"
    assert main(["feasibility", str(path), "--mode", "relay", "--rounds", "2", "--grid", grid, "--workers", "1",
                 "--out", str(tmp_path / "m")]) == 0
    rows = list(csv.DictReader((tmp_path / "m" / "feasibility.csv").open()))
    rec = json.loads((tmp_path / "m" / "feasibility.json").read_text())
    assert rec["options"]["carry"] == "region" and rec["references"]["over"] == "each node's region"
    sc = load_scenario(str(path))
    for row in rows:
        d = consensus_design(sc, mode="relay", rounds=2, dos=float(row["dos"]))  # REGIONS: carried, as design
        assert d.carried_regions is not None
        want = stationary_record(sc.with_attacks(dos=float(row["dos"])), d)
        assert row["verdict"] == want["verdict"]
        assert float(row["trace_bound"]) == pytest.approx(np.mean(want["trace"]), rel=1e-12)
    assert main(["feasibility", str(path), "--mode", "relay", "--rounds", "2", "--grid", grid, "--carry", "whole",
                 "--workers", "1", "--out", str(tmp_path / "w")]) == 0
    whole = list(csv.DictReader((tmp_path / "w" / "feasibility.csv").open()))
    assert json.loads((tmp_path / "w" / "feasibility.json").read_text())["references"]["over"] == "the whole state"
    assert all(float(w["trace_bound"]) > float(r["trace_bound"]) for w, r in zip(whole, rows))
    # the automatic map: every row's bound over the regions, a whole-state pick's too
    from studies import api
    from studies.feasibility_map import map_points

    m = api.feasibility(str(path), grid, workers=1)
    assert m.references["over"] == "each node's region"
    # whatever its nodes carry, as design --mode auto ranks its candidates
    assert api.feasibility(str(path), grid, workers=1, carry="whole").references["over"] == "each node's region"
    assert set(m.rule.ravel()) <= {c["label"] for c in m.auto["candidates"]}
    # a whole-state candidate (scheduled, screened without its LMI): ranked by the node average of its fixed point's
    # trace over each node's region, judged (its verdict) on the whole state as its design is
    from rules.scheduled.certificate import stationary_certificate

    opts = DesignOptions(mode="scheduled")
    ranked = map_points(sc, opts, [{"dos": 0.1}], lmi=False, regions=sc.regions)[0]
    plain = map_points(sc, opts, [{"dos": 0.1}], lmi=False)[0]
    assert plain["feasible"] and ranked["verdict"] == plain["verdict"] == "certified"  # the premise: a fixed point
    d = consensus_design(sc, opts, dos=0.1)
    cert = stationary_certificate(sc.model, sc.with_attacks(dos=0.1).network, d, x=sc.operating_point[0], lmi=False)
    by_hand = np.mean([np.trace(cert.Phi[i][np.ix_(r, r)]) for i, r in enumerate(sc.regions)])
    assert ranked["trace_bound"] == pytest.approx(by_hand, rel=1e-9)
    assert plain["trace_bound"] == pytest.approx(np.mean(np.trace(cert.Phi, axis1=-2, axis2=-1)), rel=1e-9)


def test_carry_region_needs_regions_and_a_rule_that_may_and_exits_2(tmp_path, capsys):
    bare = model_file(tmp_path, regions="")
    assert main(["design", str(bare), "--mode", "relay", "--carry", "region", "--out", str(tmp_path / "a")]) == 2
    assert "carry" in capsys.readouterr().err
    path = model_file(tmp_path)
    assert main(["design", str(path), "--mode", "tuned", "--carry", "region", "--out", str(tmp_path / "b")]) == 2
    assert "carry" in capsys.readouterr().err
    assert main(["design", str(path), "--mode", "relay", "--carry", "half", "--out", str(tmp_path / "c")]) == 2
    assert not any((tmp_path / d).exists() for d in "abc")


def test_a_verdict_judged_per_node_uses_each_nodes_own_open_loop():
    trace = np.array([[0.5, 0.5], [0.5, 0.5]])
    shared = verdict(trace, [1.0, 1.0], feasible=True)
    assert shared.verdict == "certified"
    own = verdict(trace, np.array([[1.0, 1.0], [1.0, 0.4]]), feasible=True, centralized=[0.25, None])
    assert own.verdict == "vacuous" and own.nodes == [1]
    assert own.detail["ratio_centralized"] == [2.0, None] and own.detail["open_loop_trace"] == [1.0, 0.4]


@pytest.mark.slow
def test_a_study_of_nodes_carrying_regions_scores_them_as_the_whole_state_design_on_the_regions(tmp_path):
    """study consensus-robot carrying the regions (the default with REGIONS): the same runs give the same errors on the
    regions as the whole-state design (rmse_region, per node too); the whole-state metrics are null (a node has no
    estimate of what it does not carry) and the bound is checked in the carried coordinates, judged on the regions."""
    path = model_file(tmp_path)
    out = {}
    for name, extra in (("whole", ["--carry", "whole"]), ("region", [])):
        assert main(["study", "consensus-robot", str(path), "--mode", "relay", "--rounds", "2", "--runs", "6",
                     "--quiet", "--out", str(tmp_path / name)] + extra) == 0
        res = json.loads((tmp_path / name / "results.json").read_text())["filters"]
        out[name] = next(f for k, f in res.items() if k.startswith("consensus-EKF"))
    whole, part = out["whole"], out["region"]
    assert part["rmse_region"] == pytest.approx(whole["rmse_region"], rel=1e-9)
    per_node = np.array([n["rmse_region"] for n in part["nodes"]])  # the nodes' own: their mean square is the whole
    assert np.mean(per_node ** 2) == pytest.approx(part["rmse_region"] ** 2, rel=1e-9)
    assert part["rmse_position"] is None and "rmse_state" not in part and whole["rmse_position"] is not None
    assert part["verdicts"]["certified"] == 6 and part["bound_check"]["verdict"] == "holds"
    assert part["bound_check"]["informative"] == 6
    # the curves the figures draw with regions: the carried design's equal the whole design's, each step's mean square
    # over the nodes is the filter's, and the steps' mean square is rmse_region
    curves = {k: np.array([n["rmse_region_curve"] for n in f["nodes"]]) for k, f in out.items()}
    np.testing.assert_allclose(curves["region"], curves["whole"], rtol=1e-9)
    for f in (whole, part):
        node = np.array([n["rmse_region_curve"] for n in f["nodes"]])
        np.testing.assert_allclose(np.mean(node ** 2, axis=0), np.square(f["rmse_region_curve"]), rtol=1e-9)
        assert np.mean(np.square(f["rmse_region_curve"])) == pytest.approx(f["rmse_region"] ** 2, rel=1e-9)
    assert {"fig_compare.png", "fig_rmse_nodes.png"} <= {p.name for p in (tmp_path / "region").iterdir()}


@pytest.mark.slow
def test_a_comparison_with_carried_regions_scores_the_relay_nodes_as_carrying_the_whole_state(tmp_path):
    """study comparison on a model with REGIONS: the relay and flood rows run carrying the regions and score the same
    rmse_region as with --carry whole (the same runs); the other rows do not change."""
    path = model_file(tmp_path)
    got = {}
    for name, extra in (("whole", ["--carry", "whole"]), ("region", [])):
        assert main(["study", "comparison", str(path), "--runs", "3", "--quiet",
                     "--filters", "relay,flood,kcf", "--out", str(tmp_path / name)] + extra) == 0
        got[name] = json.loads((tmp_path / name / "results.json").read_text())
    rows = {k: got[k]["settings"][0]["filters"] if "settings" in got[k] else got[k]["filters"] for k in got}
    assert rows["whole"].keys() == rows["region"].keys() and len(rows["whole"]) == 3
    for f in rows["whole"]:
        assert rows["region"][f]["rmse_region"] == pytest.approx(rows["whole"][f]["rmse_region"], rel=1e-9), f


def test_the_trade_off_leaves_out_the_hop_counts_that_cost_more_than_the_designs_own(monkeypatch):
    """rules.relay.study.relay_tradeoff: a row whose recursion costs more than TRADEOFF_COST_MAX x the design's own
    (and the floor) is not computed and says why; the cheaper ones are, over each node's region when it carries it."""
    import rules.relay.study as study

    model, net = coupled_model(stable=True), network()
    design = relay_design(model, net, 1)
    monkeypatch.setattr(study, "TRADEOFF_COST_FLOOR", 0.0)
    monkeypatch.setattr(study, "TRADEOFF_COST_MAX", 1.5)
    rows = {r["rounds"]: r for r in study.relay_tradeoff(model, net, design, x=model.prior.mean, u=None)["rows"]}
    routes = {L: relay_routes(net, L) for L in rows}
    cost = {L: float((((L + 1) * relay_carried(model, routes[L], REGIONS).used.sum(1)) ** 3).sum()) for L in rows}
    for L, r in rows.items():
        skipped = cost[L] > 1.5 * cost[1]
        assert (r["expected_rmse"] is None and "not computed" in r["reason"]) if skipped else "reason" not in r
    assert any("reason" in r for r in rows.values()) and rows[1]["expected_rmse"] is not None
    cert = relay_stationary(model, net, design, x=model.prior.mean, lmi=False)
    assert rows[1]["expected_rmse"] == pytest.approx(float(np.sqrt(cert.traces().mean())), rel=1e-12)


@pytest.mark.slow
def test_the_automatic_designs_validation_line_says_whether_the_picks_bound_held(tmp_path, capsys):
    """The terminal says what validation.json's bound check found for the pick (held, or violated with why): a
    certified pick whose bound the fresh runs exceed must not read as sound.  Where no check finds an excess it says
    the runs' error energy over the bound on average; above 1, that the bound is not refuted (not that it holds),
    with the excess these runs cannot see."""
    from studies.cli import _held_how

    path = model_file(tmp_path)
    assert main(["design", str(path), "--validate", "3", "--out", str(tmp_path / "a")]) in (0, 1)
    out = capsys.readouterr().out
    check = json.loads((tmp_path / "a" / "validation.json").read_text())["filters"]["pick"]["bound_check"]
    line = next(x for x in out.splitlines() if "fresh runs" in x and "its bound" in x)
    mean = check["run_test"]["ratio_mean"]
    if check["verdict"] == "violated":
        assert f"its bound violated on these runs ({check['verdict_reason']})" in line
    else:
        words = "is not refuted" if mean > 1 else "holds"
        assert f"its bound {words} on these runs (their error energy {mean:.3g} x the bound on average" in line
    # both sides of 1, as the command line and a study's line say them
    below = {"verdict": "holds", "run_test": {"ratio_mean": 0.887, "tolerance": 0.15}}
    above = {"verdict": "holds", "run_test": {"ratio_mean": 1.18, "tolerance": 0.28}}
    assert _held_how(below) == " (their error energy 0.887 x the bound on average)"
    assert _held_how(above) == (" (not refuted: their error energy 1.18 x the bound on average; an excess below "
                                "1.28 x goes unseen in these runs)")
    assert _held_how(above, said=True).startswith(" (their error energy 1.18 x") and _held_how({}) == ""


@pytest.mark.slow
def test_a_whole_state_filter_on_a_log_is_scored_on_the_regions_too(tmp_path, capsys):
    """``cfdesign filter --filter kcf`` on a model with REGIONS says its RMSE on each node's region first, as the
    studies and a design's validation score every filter (it had said the whole state's alone, beside a carried
    design's regional one): the number from the written estimates and the truth, by hand; the whole state's after."""
    path = model_file(tmp_path, regions="REGIONS = [[i, (i + 1) % N] for i in range(N)]")
    log, out = tmp_path / "log.npz", tmp_path / "kcf"
    assert main(["simulate", str(path), "--seed", "2", "--out", str(log)]) == 0
    capsys.readouterr()
    assert main(["filter", str(path), "--data", str(log), "--filter", "kcf", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    with np.load(out / "estimates.npz") as d:
        e = d["x"][1:, None, :] - d["x_hat"][1:]  # (K, N, n)
    region = np.sqrt(np.mean([[e[k, i, i] ** 2 + e[k, i, (i + 1) % N] ** 2 for i in range(N)]
                              for k in range(e.shape[0])]))
    whole = np.sqrt(np.mean(np.sum(e ** 2, axis=-1)))
    m = re.search(r"RMSE (\S+) against the log's truth on each node's region \((\S+) over the whole state\)", said)
    assert m, said
    assert float(m.group(1)) == pytest.approx(region, rel=1e-3) and float(m.group(2)) == pytest.approx(whole, rel=1e-3)
    assert "On each node's region (the model's `REGIONS`" in (out / "report.md").read_text()
