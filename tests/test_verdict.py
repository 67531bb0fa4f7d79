"""Verdicts on a design's bound (designer.verdict): constructed trajectories, the open-loop references, and the
verdicts of ``cfdesign design`` and ``cfdesign feasibility`` on model files written here."""
from __future__ import annotations

import csv
import json
import math
import textwrap

import numpy as np
import pytest
from scipy.linalg import solve_discrete_lyapunov

from designer.verdict import (GROWTH_TOLERANCE, MIN_WINDOW, VERDICTS, count_verdicts, describe, informative,
                              known_verdict, open_loop_reference, open_loop_traces, settled_steps, steadiness_window,
                              verdict)
from studies.cli import main

K = 40
W = steadiness_window(K)
OL = np.full(K, 10.0)  # a flat open loop: every bound below 10 is informative


def _median_growth(row: np.ndarray, window: int) -> float:
    """The steadiness measure recomputed here: median of the last window over the median of the one before, - 1."""
    n = row.size
    return float(np.median(row[n - window:]) / np.median(row[n - 2 * window:n - window]) - 1.0)


# ------------------------------------------------------------------------------------------- constructed bounds
def test_a_settled_bound_below_the_open_loop_is_certified_and_bounded_with_its_ratios():
    k = np.arange(K)
    t = np.vstack([1.0 + 3.0 * 0.7**k, 2.0 + 0.5**k])
    v = verdict(t, OL, feasible=True, centralized=0.5, local=[0.8, None])
    assert v.verdict == "certified" and v.certified and v.reason is None and v.nodes == []
    assert v.bounded and not v.growing and v.bounded_reason is None
    d = v.detail
    assert d["final_trace"] == pytest.approx(t[:, -1])
    assert d["ratio_open_loop"] == pytest.approx(t[:, -1] / 10.0)
    assert d["ratio_centralized"] == pytest.approx(t[:, -1] / 0.5)
    assert d["ratio_local"][0] == pytest.approx(t[0, -1] / 0.8) and d["ratio_local"][1] is None
    assert d["growth"] == pytest.approx([_median_growth(r, W) for r in t], abs=1e-12)
    assert d["judged_steps"] == [1, K] and d["settled_steps"] == [K - 2 * W + 1, K]
    assert d["window"] == W and d["horizon"] == K
    assert d["verdict"] == "certified" and d["open_loop_exceeded"] == 0
    assert d["bounded"] is True and d["growing"] is False and d["bounded_by"] == "steady"
    assert describe(d).startswith("certified: the bound is finite and informative at every step")
    assert "; bounded: steady" in describe(d)


def test_a_growing_bound_below_the_open_loop_is_certified_growing_and_not_bounded():
    k = np.arange(1, K + 1)
    t = np.vstack([np.full(K, 1.0), 0.1 * 1.03**k])  # node 1 grows by 3 % a step: λ^W - 1 over a window
    v = verdict(t, OL, feasible=True)
    assert v.verdict == "certified" and v.certified and v.growing and not v.bounded
    assert v.detail["growth"][1] == pytest.approx(1.03**W - 1.0)
    assert "node 1" in v.bounded_reason and f"{1.03**W - 1:.1%}" in v.bounded_reason
    text = describe(v.detail)
    assert text.startswith("certified, still growing at the horizon: ") and "not bounded: node 1" in text


@pytest.mark.parametrize("factor, steady", [(1.0 + 0.9 * GROWTH_TOLERANCE, True), (1.0 + 1.1 * GROWTH_TOLERANCE, False)])
def test_the_growth_tolerance_separates_bounded_from_growing(factor, steady):
    """A bound whose last window sits ``factor`` above the window before: bounded within the tolerance only; certified
    either way (below the open loop at every step)."""
    t = np.concatenate([np.full(K - W, 1.0), np.full(W, factor)])[None]
    v = verdict(t, OL, feasible=True)
    assert v.verdict == "certified" and v.bounded is steady and v.growing is not steady


def test_isolated_bursts_are_not_growth_but_a_lifted_window_is():
    """A stationary bound lifted by 30 % at isolated steps (a burst of lost packets) in the last window is bounded;
    the same lift over the whole last window is growth (the negative control)."""
    base = np.full(K, 1.0)
    burst = base.copy()
    burst[[K - 7, K - 2]] = 1.3
    assert verdict(burst[None], OL, feasible=True).bounded
    lifted = base.copy()
    lifted[K - W:] = 1.3
    v = verdict(lifted[None], OL, feasible=True)
    assert v.certified and v.growing and not v.bounded


def test_a_periodic_or_decaying_bound_is_bounded():
    k = np.arange(K)
    t = np.vstack([1.0 + 0.5 * (k % 2), 5.0 * 0.9**k + 1.0])
    v = verdict(t, OL, feasible=True)
    assert v.certified and v.bounded


def test_a_bound_above_the_open_loop_at_some_step_is_vacuous():
    t = np.full((3, K), 2.0)
    t[1, K - 3] = 12.0  # node 1, step K - 2: 1.2 x the open loop there
    v = verdict(t, OL, feasible=True)
    assert v.verdict == "vacuous" and v.nodes == [1] and v.bounded  # vacuous, but steady: the two claims apart
    assert f"step {K - 2}" in v.reason and "node 1" in v.reason and "1.2 x" in v.reason
    assert v.detail["max_ratio_open_loop"] == pytest.approx([0.2, 1.2, 0.2])
    assert v.detail["ratio_open_loop"] == pytest.approx([0.2, 0.2, 0.2])  # at the horizon it looks fine


def test_a_bound_above_the_open_loop_only_at_step_1_is_vacuous():
    """Theorem 1 claims a bound at every step: the transient from the prior is judged too.  Above the open loop at
    step 1 alone is vacuous; the same bound just below it there is certified (the negative control)."""
    t = np.full((2, K), 2.0)
    t[0, 0] = 10.0  # at the open loop: not below it
    v = verdict(t, OL, feasible=True)
    assert v.verdict == "vacuous" and v.nodes == [0] and "at step 1 " in v.reason
    assert v.detail["open_loop_exceeded"] == 1
    t[0, 0] = 9.99
    assert verdict(t, OL, feasible=True).verdict == "certified"


def test_a_growing_bound_above_the_open_loop_is_vacuous_and_a_non_finite_bound_is_vacuous():
    k = np.arange(1, K + 1)
    growing_above = (2.0 * 1.2**k)[None]
    v = verdict(growing_above, OL, feasible=True)
    assert v.verdict == "vacuous" and v.growing and not v.bounded
    t = np.full((2, K), 1.0)
    t[1, -1] = np.inf
    v = verdict(t, OL, feasible=True)
    assert v.verdict == "vacuous" and v.nodes == [1] and "not finite" in v.reason
    assert v.detail["final_trace"][1] is None  # JSON: no inf


def test_an_infeasible_design_is_infeasible_whatever_its_bound():
    t = np.full((2, K), 1.0)
    v = verdict(t, OL, feasible=False, infeasible_reason="first at node 0, step 3, condition (29)")
    assert v.verdict == "infeasible" and not v.certified and v.reason == "first at node 0, step 3, condition (29)"
    assert not v.bounded


def test_a_certificate_not_computed_is_never_infeasible():
    """``not_computed`` wins over ``feasible=False`` and over any bound (none was computed: NaN), with the reason."""
    nan = np.full((2, K), np.nan)
    for feasible in (True, False):
        v = verdict(nan, OL, feasible=feasible, not_computed="the stacked error has 900 rows")
        assert v.verdict == "not computed" and v.reason == "the stacked error has 900 rows" and not v.bounded
        assert describe(v.detail) == "not certified (not computed): the stacked error has 900 rows"
    # without the reason, the same NaN bound claims nothing: vacuous, never certified
    assert verdict(nan, OL, feasible=True).verdict == "vacuous"


def test_a_horizon_too_short_to_show_steadiness_is_not_bounded():
    short = 2 * MIN_WINDOW - 1
    v = verdict(np.ones((2, short)), np.full(short, 10.0), feasible=True)
    assert v.verdict == "certified" and not v.bounded and not v.growing and "too short" in v.bounded_reason
    assert v.detail["growth"] is None
    enough = 2 * MIN_WINDOW
    assert verdict(np.ones((2, enough)), np.full(enough, 10.0), feasible=True).bounded


def test_an_open_loop_that_overflows_makes_any_finite_bound_informative():
    t = np.full((1, K), 1e3)
    v = verdict(t, np.full(K, np.inf), feasible=True)
    assert v.verdict == "certified" and v.detail["ratio_open_loop"] == [0.0] and v.detail["open_loop_trace"] is None


def test_informative_is_per_node_and_every_step():
    t = np.array([[1.0, 2.0, 3.0], [1.0, 11.0, 1.0], [1.0, np.nan, 1.0]])
    assert informative(t, 10.0).tolist() == [True, False, False]
    assert informative(t, np.array([10.0, 12.0, 10.0])).tolist() == [True, True, False]
    assert informative(t[1:2], np.inf).tolist() == [True]  # an open loop that overflowed: any finite bound


def test_the_settled_steps_are_the_last_two_windows():
    for horizon in (1, 3, 4, 30, 40):
        w = steadiness_window(horizon)
        sl = settled_steps(horizon)
        assert (sl.start, sl.stop) == (max(0, horizon - 2 * w), horizon)


def test_a_stationary_bound_is_judged_as_a_fixed_point():
    below, above = np.array([[1.0], [3.0]]), np.array([[1.0], [30.0]])
    v = verdict(below, 10.0, feasible=True, fixed_point=True)
    assert v.verdict == "certified" and v.bounded and v.detail["bounded_by"] == "fixed point"
    assert "; bounded: a fixed point" in describe(v.detail)
    v = verdict(above, 10.0, feasible=True, fixed_point=True)
    assert v.verdict == "vacuous" and v.nodes == [1] and "fixed point" in v.reason and v.bounded
    stuck = verdict(np.full((2, 1), np.nan), 10.0, feasible=True, fixed_point=False)
    assert stuck.verdict == "vacuous" and not stuck.bounded and "fixed point" in stuck.bounded_reason
    last_below = verdict(np.full((2, 1), 3.0), 10.0, feasible=True, fixed_point=False)
    assert last_below.verdict == "certified" and not last_below.bounded


def test_count_verdicts_and_old_words():
    assert count_verdicts(["vacuous", "certified", "vacuous"]) == {"certified": 1, "vacuous": 2, "infeasible": 0,
                                                                   "not computed": 0}
    assert list(count_verdicts([])) == list(VERDICTS)
    assert VERDICTS == ("certified", "vacuous", "infeasible", "not computed")
    # an older file's "not steady" is shown as it was; any other text is unknown
    assert known_verdict("not steady") == "not steady" and known_verdict("bounded") == "unknown"
    assert known_verdict("not computed") == "not computed"


# ------------------------------------------------------------------------------------------- open-loop references
def test_open_loop_traces_follow_the_scalar_closed_form():
    a, q, p0, n = 0.8, 0.3, 2.0, 25
    k = np.arange(1, n + 1)
    exact = a ** (2 * k) * p0 + q * (1 - a ** (2 * k)) / (1 - a**2)
    got = open_loop_traces(np.array([[a, 0.0], [0.0, 1.1]]), np.diag([q, 0.0]), np.diag([p0, 0.0]), n)
    assert got == pytest.approx(exact, rel=1e-12)
    grows = open_loop_traces(np.array([[1e3]]), np.array([[1.0]]), np.array([[1.0]]), 200)
    assert np.isinf(grows[-1]) and np.all(np.diff(grows[np.isfinite(grows)]) > 0)


def test_the_stationary_open_loop_is_the_lyapunov_solution_or_the_horizon():
    F = np.array([[0.9, 0.2], [-0.1, 0.7]])
    Q = np.diag([0.1, 0.2])
    tr, how = open_loop_reference(F, Q, np.eye(2), 30)
    P = solve_discrete_lyapunov(F, Q)
    assert np.allclose(F @ P @ F.T + Q, P) and tr == pytest.approx(np.trace(P)) and "Lyapunov" in how
    cv = np.array([[1.0, 1.0], [0.0, 1.0]])  # marginally stable: no stationary covariance
    tr, how = open_loop_reference(cv, Q, np.eye(2), 30)
    P = np.eye(2)
    for _ in range(30):
        P = cv @ P @ cv.T + Q
    assert tr == pytest.approx(np.trace(P)) and "horizon of 30 steps" in how


# ------------------------------------------------------------------------------------------- cfdesign design
CV4 = '''
import casadi as ca
import numpy as np
from designer import AttackSpec, Gaussian, Model, SensorNetwork, Sensor

STEPS = 40
X0 = [5.0, 0.5, 5.0, 0.3]
SITES = [(0.0, 0.0), (40.0, 0.0), (40.0, 40.0), (0.0, 40.0)]
NETWORK = SensorNetwork.from_edges(4, [(0, 1), (1, 2), (2, 3), (3, 0)])
ATTACKS = AttackSpec(dos=0.1, fdi=0.0)
Q = 0.05 ** 2 * np.kron(np.eye(2), [[1 / 3, 1 / 2], [1 / 2, 1]]) + 1e-9 * np.eye(4)
P0 = np.diag([4.0, 0.25, 4.0, 0.25])


def model():
    x = ca.SX.sym("x", 4)
    sensors = []
    for i, (sx, sy) in enumerate(SITES):
        dx, dy = x[0] - sx, x[2] - sy
        if i % 2:
            sensors.append(Sensor(f"b{i}", ca.atan2(dy, dx), Gaussian.zero_mean([[0.02 ** 2]]), (sx, sy), angles=(0,)))
        else:
            sensors.append(Sensor(f"r{i}", ca.sqrt(dx ** 2 + dy ** 2), Gaussian.zero_mean([[1.0]]), (sx, sy)))
    f = ca.vertcat(x[0] + x[1], x[1], x[2] + x[3], x[3])
    return Model("cv4", x, f, sensors, process_noise=Gaussian.zero_mean(Q), prior=Gaussian(X0, P0))
'''

SMALL = '''
import casadi as ca
import numpy as np
from designer import AttackSpec, Gaussian, Model, SensorNetwork, Sensor

STEPS = 30
X0 = [0.0, 0.0]
NETWORK = SensorNetwork.from_edges(3, [(0, 1), (1, 2)])
ATTACKS = AttackSpec(dos=0.1, fdi=0.0)


def model():
    x = ca.SX.sym("x", 2)
    sensors = [Sensor(f"s{i}", x, Gaussian.zero_mean(0.05 * np.eye(2))) for i in range(3)]
    return Model("small", x, 0.9 * x, sensors, process_noise=Gaussian.zero_mean(0.1 * np.eye(2)),
                 prior=Gaussian(X0, 0.2 * np.eye(2)))
'''


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def _open_loop(F, Q, P0, steps):
    """tr P_k, k = 1..steps, of P <- F P Fᵀ + Q propagated here."""
    out, P = [], P0
    for _ in range(steps):
        P = F @ P @ F.T + Q
        out.append(np.trace(P))
    return np.array(out)


@pytest.mark.slow
def test_a_feasible_design_with_a_vacuous_bound_says_so_and_exits_1(tmp_path, capsys):
    """The mse design of a constant-velocity target seen by range and bearing sensors: (28)-(29) hold (feasible, exit
    0 before verdicts existed), but its bound rises above the open-loop covariance: vacuous, exit 1, and the message
    names the node; the nodes named are those at or above the open loop at some step (the transient included)."""
    path = _write(tmp_path, "cv4.py", CV4)
    out = tmp_path / "d"
    assert main(["design", str(path), "--mode", "mse", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    sched = json.loads((out / "schedule.json").read_text())
    assert sched["feasible"] is True and sched["certified"] is False and sched["verdict"] == "vacuous"
    detail = sched["verdict_detail"]
    worst = int(np.argmax([-1.0 if x is None else x for x in detail["max_ratio_open_loop"]]))
    assert "not certified (vacuous)" in err and f"node {worst}'s tr Φ" in err and "joint state" in err
    # independently: some node's bound reaches the open loop (propagated here) at some step of the run
    cv = np.kron(np.eye(2), [[1.0, 1.0], [0.0, 1.0]])
    ns = {}
    exec(compile(CV4, "cv4", "exec"), ns)  # the file's Q and P0
    ol = _open_loop(cv, ns["Q"], ns["P0"], sched["steps"])
    tb = np.array([[np.inf if v is None else v for v in row] for row in sched["trace_bound"]])
    assert np.any(tb >= ol)
    assert set(detail["nodes"]) == {i for i in range(sched["nodes"]) if np.any(tb[i] >= ol)}
    lead = "**Not certified: the bound is vacuous; " + ("bounded" if sched["bounded"] else "not bounded") + ".**"
    assert lead in (out / "report.md").read_text().split("## Summary", 1)[1]


@pytest.mark.slow
def test_a_certified_design_reports_its_ratios_against_the_references(tmp_path):
    import studies
    from designer.observability import kalman_references

    path = _write(tmp_path, "small.py", SMALL)
    assert main(["design", str(path), "--mode", "tuned", "--out", str(tmp_path / "d")]) == 0
    sched = json.loads((tmp_path / "d" / "schedule.json").read_text())
    assert sched["certified"] is True and sched["verdict"] == "certified"
    d = sched["verdict_detail"]
    final = np.array([row[-1] for row in sched["trace_bound"]])
    ol = _open_loop(0.9 * np.eye(2), 0.1 * np.eye(2), 0.2 * np.eye(2), sched["steps"])
    assert d["open_loop_trace"] == pytest.approx(ol[-1]) and d["ratio_open_loop"] == pytest.approx(final / ol[-1])
    res = studies.design(path, mode="tuned")  # the API: the same verdict
    assert res.certified and res.verdict == "certified" and res.verdict_detail == d
    refs = kalman_references(res.scenario.model, *res.scenario.operating_point)
    assert d["ratio_centralized"] == pytest.approx(final / refs["centralized"])
    assert d["ratio_local"] == pytest.approx(final / np.array(refs["local"]))
    summary = (tmp_path / "d" / "report.md").read_text().split("## Summary", 1)[1].strip()
    assert summary.startswith("**Certified and bounded.** The bound is finite and informative at every step")
    assert sched["bounded"] is True and res.bounded and sched["growing"] is False


@pytest.mark.slow
def test_a_design_too_short_to_show_steadiness_is_certified_not_bounded_and_exits_0(tmp_path, capsys):
    """Certified (informative at each of its 3 steps) exits 0; that 3 steps cannot show a steady bound is the separate
    claim, said on the verdict line and recorded as bounded false."""
    path = _write(tmp_path, "small.py", SMALL)
    assert main(["design", str(path), "--mode", "tuned", "--steps", "3", "--out", str(tmp_path / "d")]) == 0
    out = capsys.readouterr().out
    assert "verdict certified, bounded false" in out
    assert "not bounded: the horizon of 3 steps is too short" in out
    sched = json.loads((tmp_path / "d" / "schedule.json").read_text())
    assert sched["certified"] is True and sched["bounded"] is False and "too short" in sched["bounded_reason"]


def test_a_scheduled_design_beyond_the_joint_size_gets_the_node_wise_certificate(tmp_path, monkeypatch, capsys):
    """The joint scheduled certificate is computed up to CERTIFICATE_MAX_DIM rows of the stacked error; beyond, each
    node's own bound (rules.scheduled.nodewise) is: a verdict, never 'not computed' nor 'infeasible' for want of one,
    and (the model is linear, so the joint certificate is the nodes' mean-square error) no smaller than the joint
    bound at any step; the limit lowered here below the small model's N n = 6 rows.  With rounds > 1 neither is
    computed: 'not computed' with the reason, and the command exits 1 saying so."""
    import rules.scheduled.certificate as certificate
    import rules.scheduled.design as scheduled
    import studies

    path = _write(tmp_path, "small.py", SMALL)
    joint = studies.design(path, mode="scheduled", steps=9)
    assert joint.verdict != "not computed" and "node-wise" not in joint.schedule.meta["stationary_certificate"]["where"]
    for module in (scheduled, certificate):
        monkeypatch.setattr(module, "CERTIFICATE_MAX_DIM", 5)
    res = studies.design(path, mode="scheduled", steps=10)  # another horizon: not the tables this process keeps
    assert res.feasible and not res.hard_violations and res.verdict in ("certified", "vacuous")
    assert (res.trace_bound[:, :9] >= joint.trace_bound * (1 - 1e-9)).all()
    stationary = res.schedule.meta["stationary_certificate"]
    assert stationary["verdict"] != "not computed" and "node-wise" in stationary["where"] and "6 rows" in \
        stationary["where"]
    assert main(["design", str(path), "--mode", "scheduled", "--rounds", "2", "--steps", "9",
                 "--out", str(tmp_path / "d")]) == 1
    err = capsys.readouterr().err
    assert "not certified (not computed)" in err and "infeasible" not in err
    sched = json.loads((tmp_path / "d" / "schedule.json").read_text())
    assert sched["feasible"] is True and sched["verdict"] == "not computed"
    assert [v["condition"] for v in sched["violations"] if v["step"] == 0] == ["not computed"]


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["relay", "scheduled"])
def test_the_robots_relay_and_scheduled_designs_are_certified(mode):
    """The indoor robot's deployable designs are certified (informative at every step of the 30); the relay bound is
    steady (bounded), the scheduled one still grows at the horizon and is bounded by its stationary certificate."""
    import studies

    d = studies.design("indoor-robot", mode=mode, seed=1)
    assert d.certified and d.verdict == "certified" and d.bounded
    assert d.growing is (mode == "scheduled")
    assert d.verdict_detail["bounded_by"] == ("steady" if mode == "relay" else "stationary certificate")
    assert d.schedule.meta["stationary_certificate"]["verdict"] == "certified"


# ------------------------------------------------------------------------------------------- cfdesign feasibility
@pytest.mark.slow
def test_the_map_verdict_column_judges_each_fixed_point_against_the_stationary_open_loop(tmp_path):
    """v_scale from 0 to 1: certified fixed points, one above the open loop (vacuous), one whose bound grows without
    limit (unbounded: vacuous); each verdict recomputed here from the point's fixed point per node."""
    from designer.design import DesignOptions, make_design
    from designer.feasibility import steady_state
    from studies.design_options import effective, rule_of
    from studies.scenarios import scenario_of

    path = _write(tmp_path, "small.py", SMALL)
    out = tmp_path / "m"
    assert main(["feasibility", str(path), "--mode", "tuned", "--grid", "v_scale=0:1:6", "--quiet",
                 "--out", str(out)]) == 0
    with open(out / "feasibility.csv") as fh:
        rows = list(csv.DictReader(fh))
    meta = json.loads((out / "feasibility.json").read_text())
    ol = np.trace(solve_discrete_lyapunov(0.9 * np.eye(2), 0.1 * np.eye(2)))
    assert meta["open_loop"]["trace"] == pytest.approx(ol)
    assert meta["verdicts"] == count_verdicts(r["verdict"] for r in rows)
    H, R = [np.eye(2)] * 3, [0.05 * np.eye(2)] * 3
    for r in rows:
        sc, opts = effective(scenario_of(str(path)), DesignOptions(mode="tuned", v_scale=float(r["v_scale"])))
        des = make_design(sc.model, sc.network, rule=rule_of(opts), delta=0.0, options=opts,
                          x0=np.zeros(2))
        st = steady_state(0.9 * np.eye(2), H, 0.1 * np.eye(2), R, sc.network, epsilon=des.epsilon, delta=0.0, U=des.U,
                          V=des.V, phi0=0.2 * np.eye(2))
        if st.feasible:
            top = max(np.trace(p) for p in st.phi)
            assert r["verdict"] == ("vacuous" if top >= ol else "certified"), r
        else:
            # no fixed point: not bounded (feasible 0); its last iterate judged against the open loop
            want = {"unbounded": "vacuous", "no convergence": "certified" if st.trace_bound < ol else "vacuous"}
            assert r["verdict"] == want.get(st.binding, "infeasible") and r["feasible"] == "0"
    assert {"certified", "vacuous"} <= {r["verdict"] for r in rows} and any(r["binding"] == "unbounded" for r in rows)
    summary = (out / "report.md").read_text().split("## Summary", 1)[1]
    assert summary.strip().startswith(f"**Certified at {meta['verdicts']['certified']} of {len(rows)} grid points.**")
    assert math.isfinite(meta["open_loop"]["trace"])


# ------------------------------------------------------------------------------------------- the studies
def _check_counts(f: dict, runs: int, feasible_runs: int) -> None:
    """A designed filter's runs by verdict: every run once; a run that met (28)-(29) is certified, vacuous or not
    computed, the others infeasible; the bounded runs are among the first."""
    v = f["verdicts"]
    assert list(v) == list(VERDICTS) and sum(v.values()) == runs
    assert v["certified"] + v["vacuous"] + v["not computed"] == feasible_runs
    assert v["infeasible"] == runs - feasible_runs and 0 <= f["bounded_runs"] <= feasible_runs


@pytest.mark.slow
def test_the_studies_record_each_designed_filters_runs_by_verdict(tmp_path):
    from studies.comparison import FILTER_REGISTRY, PAPER_DESIGN

    DESIGNED = [e.name for e in FILTER_REGISTRY if e.designed]

    path = _write(tmp_path, "small.py", SMALL)
    wide = _write(tmp_path, "wide.py", SMALL.replace("prior=Gaussian(X0, 0.2 * np.eye(2))",
                                                     "prior=Gaussian(X0, 25.0 * np.eye(2))"))
    for model, name in ((path, "c"), (wide, "w")):
        assert main(["study", "comparison", str(model), "--runs", "2", "--particles", "40", "--quiet",
                     "--out", str(tmp_path / name)]) == 0
        res = json.loads((tmp_path / name / "results.json").read_text())
        for f in DESIGNED:
            _check_counts(res["filters"][f], 2, res["filters"][f]["feasible_runs"])
        for row in res["sweeps"]["dos_prob"].values():
            for f in DESIGNED:
                if "feasible_runs" in row.get(f, {}):
                    assert 0 <= row[f]["certified_runs"] <= row[f]["feasible_runs"]
        assert all("verdicts" not in res["filters"][f] for f in res["filters"] if f not in DESIGNED)
    # sigma = 0.1 breaks (28) on the wide prior at the first step: not run, infeasible in every run
    assert res["filters"][PAPER_DESIGN]["verdicts"] == {"certified": 0, "vacuous": 0, "infeasible": 2,
                                                         "not computed": 0}
    assert res["filters"][PAPER_DESIGN]["bounded_runs"] == 0
    assert main(["study", "consensus-robot", str(path), "--runs", "2", "--mode", "tuned", "--quiet",
                 "--out", str(tmp_path / "r")]) == 0
    res = json.loads((tmp_path / "r" / "results.json").read_text())
    checked = [f for f in res["filters"].values() if f.get("feasibility")]
    assert checked
    for f in checked:
        _check_counts(f, 2, f["feasibility"]["runs_feasible"])
    assert all(f["verdicts"] is None for f in res["filters"].values() if f["family"] != "consensus")
