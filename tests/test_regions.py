"""REGIONS (designer.regions): the states each node answers for, declared by a model file or sensed from its sensor's
Jacobian; a comparison scores each node on its region and a design states its bound there."""
from __future__ import annotations

import json
import re

import casadi as ca
import numpy as np
import pytest

import studies
from designer import Gaussian, Model, Sensor
from designer.regions import SENSED, region_traces, resolve_regions, sensed_regions
from designer.validation import InputError
from designer.verdict import describe
from studies.cli import main
from studies.scenarios import load_scenario

CHAIN = '''"""Five temperatures on a chain, each cell leaking to its neighbours; each node reads its own cell, node 2 also
the difference to the next one, node 4 a thermistor (exp of its cell)."""
import casadi as ca
import numpy as np

from designer import AttackSpec, Gaussian, Model, SensorNetwork, Sensor

N = 5
STEPS = 12
NETWORK = SensorNetwork.from_edges(N, [(i, i + 1) for i in range(N - 1)])
ATTACKS = AttackSpec(dos=0.1)
REGIONS = {regions}


def model() -> Model:
    x = ca.SX.sym("x", N)
    f = ca.vertcat(*[x[i] + 0.1 * ((x[i - 1] if i else x[i]) - 2 * x[i] + (x[i + 1] if i < N - 1 else x[i]))
                     for i in range(N)])
    g = lambda v: Gaussian.zero_mean(np.diag(v))
    sensors = [Sensor(f"s{{i}}", x[i], g([0.01])) for i in range(N)]
    sensors[2] = Sensor("s2", ca.vertcat(x[2], x[2] - x[3]), g([0.01, 0.02]))
    sensors[4] = Sensor("s4", ca.exp(0.5 * x[4]), g([0.01]))
    return Model("chain", x, f, sensors, process_noise=Gaussian.zero_mean(1e-3 * np.eye(N)),
                 prior=Gaussian(np.ones(N), 0.1 * np.eye(N)), state_names=tuple(f"T{{i}}" for i in range(N)))
'''


def chain(tmp_path, regions: str):
    path = tmp_path / "chain.py"
    path.write_text(CHAIN.format(regions=regions))
    return path


def _model():
    x = ca.SX.sym("x", 4)
    sensors = [Sensor("a", ca.vertcat(x[0] * x[1], ca.sin(x[3])), Gaussian.zero_mean(np.eye(2))),
               Sensor("b", x[2] + 0.0 * x[1], Gaussian.zero_mean([[1.0]])),  # 0 * x1 is no dependence
               Sensor("c", ca.atan2(x[1], x[0]), Gaussian.zero_mean([[1.0]]), angles=(0,))]
    return Model("m", x, x, sensors, process_noise=Gaussian.zero_mean(np.eye(4)),
                 prior=Gaussian(np.zeros(4), np.eye(4)), state_names=("p", "q", "r", "s"))


def test_sensed_regions_are_the_states_a_finite_difference_moves():
    """Each sensor's sensed region is the set of states whose finite-difference perturbation moves its measurement
    at a generic point (an independent reference to CasADi's structural sparsity)."""
    m = _model()
    rng = np.random.default_rng(3)
    for i, region in enumerate(sensed_regions(m)):
        moved = set()
        for _ in range(3):
            x = rng.normal(size=4)
            for j in range(4):
                dx = np.zeros(4)
                dx[j] = 1e-6
                if np.any(np.abs(m.h(i, x + dx) - m.h(i, x - dx)) > 1e-12):
                    moved.add(j)
        assert region.tolist() == sorted(moved), (i, region, moved)


def test_declared_regions_resolve_by_index_name_or_sensed_and_wrong_ones_name_the_entry():
    m = _model()
    got = resolve_regions([[1, "p"], "r", SENSED], m, 3)
    assert [r.tolist() for r in got] == [[0, 1], [2], [0, 1]]
    assert [r.tolist() for r in resolve_regions(SENSED, m, 3)] == [[0, 1, 3], [2], [0, 1]]
    for bad, words in (([[0], [1]], "one entry per node (3), got 2"), ([[0], [4], [1]], "REGIONS[1]"),
                       ([[0], ["x"], [1]], "state indices 0..3 or state names"), ([[0], [True], [1]], "REGIONS[1]"),
                       ([[0], [], [1]], "REGIONS[1] is empty"), ("all", "'sensed' or one list"), (3, "got int")):
        with pytest.raises(InputError, match=re.escape(words)):
            resolve_regions(bad, m, 3)


def test_a_model_files_regions_reach_the_scenario_and_a_bad_one_exits_2(tmp_path, capsys):
    sc = load_scenario(str(chain(tmp_path, '["T0", [1, "T2"], "sensed", 3, "sensed"]')))
    assert [r.tolist() for r in sc.regions] == [[0], [1, 2], [2, 3], [3], [4]]
    bad = chain(tmp_path, '[[0]] * 4')
    assert main(["design", str(bad), "--mode", "relay", "--out", str(tmp_path / "d")]) == 2
    assert "REGIONS must have one entry per node (5), got 4" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()


def test_region_traces_sum_each_nodes_diagonal_over_its_region():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(2, 3, 4, 4))
    P = A @ np.swapaxes(A, -1, -2)
    regions = [np.array([0, 2]), np.array([3]), np.array([0, 1, 2, 3])]
    got = region_traces(P, regions)
    want = np.array([[[np.trace(P[a, i][np.ix_(r, r)]) for i, r in enumerate(regions)] for a in range(2)]])[0]
    assert np.allclose(got, want, rtol=1e-14)
    one = region_traces(P[:, :1], regions)  # one matrix for every node: broadcast
    assert np.allclose(one, [[np.trace(P[a, 0][np.ix_(r, r)]) for r in regions] for a in range(2)], rtol=1e-14)


def test_a_comparison_scores_each_node_on_its_region_and_whole_regions_give_the_state_rmse(tmp_path):
    """With every node's region the whole state, rmse_region equals the study's rmse without regions (the same runs,
    to rounding); with one state per node it is that state's error at that node, smaller than the whole state's."""
    filters = "relay,centralized-ekf-trusts-every-packet,local-ekf-at-every-node-no-network"
    out = {}
    for name, regions in (("none", "None"), ("all", "[list(range(5))] * 5"), ("own", "[[i] for i in range(5)]")):
        folder = tmp_path / name
        folder.mkdir()
        res = studies.study("comparison", str(chain(folder, regions)), runs=2, filters=filters,
                            out=folder / "out").results
        out[name] = res
    for f in out["none"]["filters"]:
        whole, every = out["none"]["filters"][f]["rmse"], out["all"]["filters"][f]["rmse_region"]
        assert every == pytest.approx(whole, rel=1e-12), f
        assert out["own"]["filters"][f]["rmse_region"] < whole
    assert out["own"]["by_scenario"]["chain"]["error"]["regions"] == [[f"T{i}"] for i in range(5)]
    assert "Each node's error over its own region" in (tmp_path / "own" / "out" / "table.md").read_text()


def test_a_design_states_each_nodes_bound_on_its_region_beside_the_verdict(tmp_path):
    """verdict_detail.region: each node's final tr Φ over its region, from the schedule's own Φ, and the centralized
    steady-state tr P over the same states; whole-state regions repeat the whole-state numbers (the nodes carrying the
    whole state, --carry whole: the verdict on it, the regions beside it)."""
    for regions in ("[[i, (i + 1) % 5] for i in range(5)]", "[list(range(5))] * 5"):
        path = chain(tmp_path, regions)
        des = tmp_path / ("d" + str(len(regions)))
        assert main(["design", str(path), "--mode", "relay", "--carry", "whole", "--out", str(des)]) in (0, 1)
        meta = json.loads((des / "schedule.json").read_text())
        detail, region = meta["verdict_detail"], meta["verdict_detail"]["region"]
        phi = np.load(des / "schedule.npz")["Phi"][:, -1]  # (nodes, n, n) at step K
        sc = load_scenario(str(path))
        want = [np.trace(phi[i][np.ix_(r, r)]) for i, r in enumerate(sc.regions)]
        assert np.allclose(region["final_trace"], want, rtol=1e-12)
        assert region["states"] == [[f"T{j}" for j in r] for r in sc.regions]
        if regions.startswith("[list"):
            assert np.allclose(region["final_trace"], detail["final_trace"], rtol=1e-12)
            assert np.allclose(region["ratio_centralized"], detail["ratio_centralized"], rtol=1e-12)
            assert np.allclose(region["centralized"], detail["centralized"], rtol=1e-12)
        else:
            ratios = np.array(region["ratio_centralized"])
            assert np.all(ratios > 0) and np.allclose(ratios, np.array(want) / np.array(region["centralized"]))
            assert "on each node's region, tr Φ is" in describe(detail)


def test_the_automatic_design_ranks_candidates_by_their_bound_on_the_regions(tmp_path):
    """With REGIONS the automatic design predicts each candidate's node-average tr Φ over the regions and puts it
    against the centralized steady state over the same states: whole-state regions give the numbers of the design
    without regions; one state per node gives each candidate's own design's region traces (an independent
    recomputation from that rule's whole-state design) and smaller predictions.  With regions the relay and flood
    candidates carry them."""
    from studies.auto import predicted_error

    found = {}
    for name, regions in (("none", "None"), ("all", "[list(range(5))] * 5"), ("own", "[[i] for i in range(5)]")):
        folder = tmp_path / name
        folder.mkdir()
        auto = studies.design(str(chain(folder, regions)), mode="auto", validate=0, budget=40)
        if auto.pick is not None and auto.pick.gain_rule.regional:  # with regions its nodes carry them
            assert auto.pick.schedule.meta["carry"] == ("whole" if regions == "None" else "region")
        found[name] = (auto, {c.label: c for c in auto.candidates if c.predicted is not None})
    none, every, own = (found[k][1] for k in ("none", "all", "own"))
    assert none.keys() == every.keys() == own.keys() and none
    for label in none:
        assert every[label].predicted == pytest.approx(none[label].predicted, rel=1e-12)
        assert every[label].ratio_centralized == pytest.approx(none[label].ratio_centralized, rel=1e-12)
        assert own[label].predicted < none[label].predicted
    auto = found["own"][0]
    refs = auto.references
    sc = load_scenario(str(tmp_path / "own" / "chain.py"))
    relay = own["relay (rounds=1)"]
    des = studies.design(sc, mode="relay", rounds=1, carry="whole")
    traces = np.array([[np.trace(des.schedule.Phi[i, k][np.ix_(r, r)]) for k in range(1, des.schedule.Phi.shape[1])]
                       for i, r in enumerate(sc.regions)])
    assert relay.predicted == pytest.approx(predicted_error(traces), rel=1e-12)
    assert relay.ratio_centralized == pytest.approx(relay.predicted / refs["centralized"], rel=1e-12)
    assert "over each node's region" in auto.message



def test_a_relay_node_whose_ball_holds_no_sensor_of_some_dimension_runs_as_the_network_filter(tmp_path):
    """The chain's node 0 relays over one hop: its ball (sensors 0 and 1) holds no two-row sensor, which sensor 2 is.
    Its node filter (studies.node_filter, what export replays) runs, and every node's estimate is the batched
    filter's on the same log (studies.filter with the schedule)."""
    path = chain(tmp_path, "None")
    des, log = tmp_path / "design", tmp_path / "log.npz"
    studies.design(str(path), mode="relay", rounds=1, out=des)
    sim = studies.simulate(str(path), seed=4, out=log)
    x, _ = studies.node_filter(str(path), schedule=des).run(sim.z, sim.attacks, sim.inputs)
    batch = studies.filter(str(path), log, schedule=des)
    assert x.shape == batch.x_hat.shape and np.allclose(x, batch.x_hat, rtol=1e-10, atol=1e-12)



def test_the_automatic_designs_validation_scores_the_pick_on_the_regions(tmp_path):
    """With REGIONS, validation.json's rows carry rmse_region and pick_rmse_ratio is of it: whole-state regions give
    each row's whole-state rmse, one state per node a smaller error for every filter."""
    every, own = tmp_path / "every", tmp_path / "own"
    every.mkdir()
    own.mkdir()
    auto = studies.design(str(chain(every, "[list(range(5))] * 5")), mode="auto", validate=3, budget=40)
    rows = auto.validation["filters"]
    for name, row in rows.items():
        if row["rmse"] is not None:
            assert row["rmse_region"] == pytest.approx(row["rmse"], rel=1e-10), name
    for name, ratio in auto.validation["pick_rmse_ratio"].items():
        assert ratio == pytest.approx(rows["pick"]["rmse_region"] / rows[name]["rmse_region"], rel=1e-12)
    # better than the nodes alone, in study comparison's one sense: the paired interval of the pick's RMSE over the
    # local EKFs' on the same runs entirely below 1
    from studies.consensus_robot import baseline_names
    from studies.scenarios import load_scenario

    local = rows[baseline_names(load_scenario(str(every / "chain.py")))[0]]
    for row in (rows["pick"], local):
        lo, hi = row["rmse_region_ci95"]
        assert lo <= hi and "rmse_ci95" not in row
    lo, hi = rows["pick"]["rmse_ratio_local_ci95"]
    assert rows["pick"]["better_than_local"] is (hi < 1) and lo <= rows["pick"]["rmse_ratio_local"] <= hi
    if not rows["pick"]["diverged_runs"] and not local["diverged_runs"]:
        assert rows["pick"]["rmse_ratio_local"] == pytest.approx(rows["pick"]["rmse_region"] / local["rmse_region"])
    mine = studies.design(str(chain(own, "[[i] for i in range(5)]")), mode="auto", validate=3, budget=40)
    assert all(r["rmse_region"] < r["rmse"] for r in mine.validation["filters"].values() if r["rmse"] is not None)
