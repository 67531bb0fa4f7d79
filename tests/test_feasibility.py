"""Feasibility maps: fixed points, monotonicity in the attack strength, files, parallel runs, bad input."""
from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import scalar_spec_model

from designer.feasibility import steady_state
from designer.network import SensorNetwork
from designer.tuning import tune_prediction, tune_update
from designer.validation import InputError
from studies.api import feasibility
from studies.feasibility_map import parse_grid

ROOT = Path(__file__).resolve().parents[1]


def feasibility_map(scenario, grids, mode="tuned", **kw):
    """The rows of a tuned map (the command's default is the paper's design)."""
    return feasibility(scenario, grids, mode=mode, **kw).rows


def _robot_linearisation():
    from studies.consensus_design import consensus_design
    from studies.scenarios import load_scenario

    sc = load_scenario("indoor-robot")
    m = sc.model
    u0 = sc.inputs(1)[0]
    F = m.F(sc.x0, 0, u0)
    xp = m.f(sc.x0, 0, u0)
    H = [m.H(i, xp, 1) for i in range(8)]
    R = [m.measurement_cov(i) for i in range(8)]
    return sc, m, F, H, R, consensus_design(sc, mode="tuned")  # one V for every camera: d.V[0]


@pytest.mark.slow
def test_accelerated_and_plain_iterations_reach_the_same_fixed_point():
    sc, m, F, H, R, d = _robot_linearisation()
    kw = dict(epsilon=d.epsilon, delta=d.delta, U=d.U, V=d.V, phi0=m.prior.cov)
    fast = steady_state(F, H, m.process_cov, R, sc.network, **kw)
    plain = steady_state(F, H, m.process_cov, R, sc.network, accelerate=False, max_iter=2000, **kw)
    assert fast.feasible and plain.feasible and fast.iterations < plain.iterations
    np.testing.assert_allclose(fast.phi, plain.phi, rtol=1e-6, atol=1e-10)
    # It is a fixed point of the tuned recursion: one more step changes nothing.
    n = sc.network
    s = ((1 - n.dos_prob) * n.adjacency).sum(1)
    pred = [tune_prediction(p, F, d.U, m.process_cov, d.epsilon).phi_pred for p in fast.phi]
    neigh = np.einsum("ij,jab->iab", 3 * (1 - n.dos_prob) * n.adjacency, np.array(pred)) \
        + (3 * d.delta**2 * (n.fdi_prob * n.adjacency).sum(1))[:, None, None] * np.eye(3)
    again = [tune_update(pred[i], H[i], s[i], d.V[i], R[i], int(n.degrees[i]), neigh[i]).phi_post for i in range(8)]
    np.testing.assert_allclose(np.array(again), fast.phi, rtol=1e-6, atol=1e-10)


def test_linear_isolated_node_reaches_the_kalman_steady_state():
    """No neighbours, U = V = 0: the fixed point is the steady-state posterior covariance of the KF (dare)."""
    from scipy.linalg import solve_discrete_are

    A = np.array([[0.95, 0.1], [0.0, 0.9]])
    Hm = np.array([[1.0, 0.0]])
    Q, R = 0.01 * np.eye(2), np.array([[0.05]])
    net = SensorNetwork(1, np.zeros((1, 1), int))
    r = steady_state(A, [Hm], Q, [R], net, epsilon=0.5, delta=0.0, U=np.zeros((2, 2)), V=np.zeros((1, 1)),
                     tol=1e-12, max_iter=2000)
    P = solve_discrete_are(A.T, Hm.T, Q, R)  # prior steady state
    post = P - P @ Hm.T @ np.linalg.inv(Hm @ P @ Hm.T + R) @ Hm @ P
    assert r.feasible
    np.testing.assert_allclose(r.phi[0], post, rtol=1e-8)


def test_more_fdi_never_helps():
    """Larger FDI probability or signal bound never lowers the trace nor makes an infeasible point feasible."""
    rows = feasibility_map("indoor-robot", ["fdi=0:0.6:4", "delta=0.5:3.5:4"], quiet=True,
                           assignments=["dos_prob=0.15"])
    tb = np.array([r["trace_bound"] if r["feasible"] else np.inf for r in rows]).reshape(4, 4)
    assert np.isfinite(tb).any() and np.isinf(tb).any(), "the grid should cross the feasibility boundary"
    for axis in (0, 1):  # axis 0: fdi grows, axis 1: delta grows
        a, b = np.take(tb, range(3), axis=axis), np.take(tb, range(1, 4), axis=axis)
        ok = np.isinf(b) | (b >= a * (1 - 1e-6))
        assert ok.all(), (axis, tb)


def _same_rows(rows1, rows2) -> bool:
    return len(rows1) == len(rows2) and all(
        r1.keys() == r2.keys() and all(r1[k] == r2[k] or (isinstance(r1[k], float) and np.isnan(r1[k])
                                                          and np.isnan(r2[k])) for k in r1)
        for r1, r2 in zip(rows1, rows2))


@pytest.mark.slow
def test_map_files_and_workers_agree(tmp_path, monkeypatch):
    rows1 = feasibility_map("indoor-robot", ["dos=0:0.3:3", "fdi=0:0.2:2"], out=tmp_path / "a", quiet=True)
    monkeypatch.setattr("studies.feasibility_map.CHUNK_SIZE", 2)  # three chunks: the workers compute them
    fmap = feasibility("indoor-robot", ["dos=0:0.3:3", "fdi=0:0.2:2"], mode="tuned", out=tmp_path / "b",
                       quiet=True, workers=2)
    assert fmap.runner["backend"] == "processes" and fmap.runner["chunks_computed"] == 3
    assert _same_rows(rows1, fmap.rows)
    with open(tmp_path / "a" / "feasibility.csv") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 6 and set(table[0]) == {"dos", "fdi", "feasible", "trace_bound", "binding", "theorem2",
                                                 "iterations", "verdict", "rule", "better_than_local"}
    assert {t["rule"] for t in table} == {"tuned"}
    assert [float(t["dos"]) for t in table] == [0.0, 0.0, 0.15, 0.15, 0.3, 0.3]
    assert (tmp_path / "a" / "feasibility.png").stat().st_size > 10_000
    # The feasible origin has the smallest bound of the map.
    feas = [float(t["trace_bound"]) for t in table if t["feasible"] == "1"]
    assert feas and float(table[0]["trace_bound"]) == min(feas)


@pytest.mark.parametrize("spec, needle", [
    ("dos", "NAME=START:STOP:COUNT"), ("bogus=0:1:3", "unknown"), ("dos=0:1:3", "[0, 1)"),
    ("delta=-1:1:3", ">= 0"), ("fdi=0:0.5", "START:STOP:COUNT"), ("fdi=0:0.5:0", "COUNT"),
])
def test_bad_grids(spec, needle):
    with pytest.raises(InputError, match=needle.replace("[", r"\[").replace("(", r"\(").replace(")", r"\)")):
        parse_grid(spec)


@pytest.mark.slow
def test_cli_feasibility(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-m", "studies", "feasibility", "indoor-robot", "--grid", "fdi=0:0.2:2",
                        "--out", str(tmp_path / "f")], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "f" / "feasibility.csv").exists()
    r = subprocess.run([sys.executable, "-m", "studies", "feasibility", "indoor-robot", "--grid", "tau=0:1:2",
                        "--mode", "tuned", "--out", str(tmp_path / "g")], capture_output=True, text=True, env=env,
                       timeout=300)
    assert r.returncode == 2 and "tau" in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_map_on_dask_and_resumed_from_its_chunks(tmp_path, monkeypatch):
    distributed = pytest.importorskip("distributed")
    from studies.runner import CHUNKS_DIR

    monkeypatch.setattr("studies.feasibility_map.CHUNK_SIZE", 8)
    grids = ["dos=0:0.3:4", "fdi=0:0.3:3"]  # 12 points: two chunks
    ref = feasibility_map("indoor-robot", grids, quiet=True)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl:
        rows = feasibility_map("indoor-robot", grids, out=tmp_path, quiet=True, dask=cl.scheduler_address)
    assert _same_rows(ref, rows)
    chunks = sorted((tmp_path / CHUNKS_DIR / "feasibility").glob("runs_*.npz"))
    assert len(chunks) == 2
    chunks[1].unlink()  # as if interrupted: the second call computes only that chunk
    again = feasibility_map("indoor-robot", grids, out=tmp_path, quiet=True)
    assert _same_rows(ref, again)
    log = (tmp_path / CHUNKS_DIR / "feasibility" / "log.jsonl").read_text().splitlines()
    assert len(log) == 3
    with pytest.raises(InputError, match="--force"):
        feasibility_map("indoor-robot", grids, out=tmp_path, quiet=True, mode="paper")


@pytest.mark.slow
def test_optimal_weights_steady_state_is_a_fixed_point_and_below_the_paper_factors_here():
    """weights='optimal': accelerated and plain iterations reach one fixed point of the weighted recursion,
    and one more weighted step (converged weights) leaves it where it is."""
    from designer.tuning import neighbour_groups, tune_weighted

    A = np.array([[0.95, 0.1], [0.0, 0.9]])
    H = [np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]]), np.array([[1.0, 1.0]])]
    Q, R = 0.01 * np.eye(2), [np.array([[0.05]])] * 3
    net = SensorNetwork.from_edges(3, [(0, 1), (1, 2)], dos_prob=0.1, fdi_prob=0.1)
    kw = dict(epsilon=0.4, delta=0.5, U=0.01 * np.eye(2), V=0.01 * np.eye(1), tol=1e-10,
              max_iter=3000)
    fast = steady_state(A, H, Q, R, net, weights="optimal", **kw)
    plain = steady_state(A, H, Q, R, net, weights="optimal", accelerate=False, **kw)
    assert fast.feasible and plain.feasible
    np.testing.assert_allclose(fast.phi, plain.phi, rtol=1e-6, atol=1e-12)
    pred = [tune_prediction(p, A, kw["U"], Q, kw["epsilon"]).phi_pred for p in fast.phi]
    s = ((1 - net.dos_prob) * net.adjacency).sum(1)
    for i in range(3):
        nb = list(net.neighbours[i])
        g = neighbour_groups(np.array(pred)[nb], net.fdi_prob[i, nb], kw["delta"], 1 - net.dos_prob[i, nb])
        again = tune_weighted(pred[i], H[i], s[i], kw["V"], R[i], g, tol=1e-12, max_iter=2000).phi_post
        np.testing.assert_allclose(again, fast.phi[i], rtol=1e-5, atol=1e-12)
    paper = steady_state(A, H, Q, R, net, **kw)
    assert paper.feasible and fast.trace_bound < paper.trace_bound
    with pytest.raises(InputError, match="weights"):
        steady_state(A, H, Q, R, net, weights="best", **kw)


@pytest.fixture
def tank(tank_model):
    return tank_model()


@pytest.mark.parametrize("spec", ["dos=0:0.6:7", "delta=0.1:0.7:13", "amplitude=1e-3:2.5e3:9", "fdi=0.9:0:4",
                                  "tau=0.3:0.3:1", "sigma=1.5e-3:0.0315:11"])
def test_grid_values_are_the_exact_numbers_meant(spec):
    """Value i is the double nearest to START + i (STOP - START) / (COUNT - 1), computed exactly (np.linspace's
    0.09999999999999999 for dos=0:0.6:7 is not the 0.1 the user wrote)."""
    from fractions import Fraction

    name, values = parse_grid(spec)
    start, stop, count = spec.split("=")[1].split(":")
    a, b, n = Fraction(start), Fraction(stop), int(count)
    exact = [a] if n == 1 else [a + i * (b - a) / (n - 1) for i in range(n)]
    assert values.tolist() == [float(v) for v in exact]


def test_the_files_write_the_grid_values_as_given(tmp_path, tank):
    feasibility(str(tank), "dos=0:0.6:7", out=tmp_path / "f", quiet=True)
    with open(tmp_path / "f" / "feasibility.csv") as fh:
        assert [row["dos"] for row in csv.DictReader(fh)] == ["0.0", "0.1", "0.2", "0.3", "0.4", "0.5", "0.6"]
    import json

    text = (tmp_path / "f" / "feasibility.json").read_text()
    assert json.loads(text)["grids"] == [{"name": "dos", "values": [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6]}]
    assert "0.30000000000000004" not in text and "0.09999999999999999" not in text


def test_a_point_whose_design_fails_is_marked_and_the_rest_is_mapped(tmp_path, tank):
    """amplitude 1e200: the signal's second moment overflows, the design at that point cannot be built."""
    from studies import schemas

    fmap = feasibility(str(tank), ["amplitude=0:1e200:3", "dos=0:0.2:2"], out=tmp_path / "f", quiet=True)
    failed = [r for r in fmap.rows if r["binding"].startswith("failed: ")]
    assert [r["amplitude"] for r in failed] == [5e199, 5e199, 1e200, 1e200] and fmap.failures == failed
    assert all("fdi_moment must be finite" in r["binding"] and r["feasible"] == 0 and np.isnan(r["trace_bound"])
               for r in failed)
    alone = feasibility(str(tank), ["amplitude=0:0:1", "dos=0:0.2:2"], quiet=True).rows
    assert _same_rows(fmap.rows[:2], alone)  # the points without the failing ones, as mapped alone
    schemas.validate_output(tmp_path / "f")
    import json

    assert json.loads((tmp_path / "f" / "feasibility.json").read_text())["failed_points"] == 4
    report = (tmp_path / "f" / "report.md").read_text()
    assert "4 of 6 grid points failed" in report and "fdi_moment must be finite" in report


def test_a_point_whose_iteration_raises_fails_alone(monkeypatch):
    """A batch that raises (an eigenvalue problem that does not converge at an extreme value) is iterated point by
    point: the point that raises is marked failed, the others get the numbers of the batch without it."""
    import designer.feasibility as dfeas
    import studies.feasibility_map as fm
    from designer.design import DesignOptions
    from studies.scenarios import load_scenario

    real = dfeas.steady_state_batch

    def fragile(*args, U, **kw):
        if any(np.max(u) > 1e3 for u in U):
            raise np.linalg.LinAlgError("Eigenvalues did not converge")
        return real(*args, U=U, **kw)

    monkeypatch.setattr(fm, "steady_state_batch", fragile)
    sc = load_scenario("indoor-robot")
    opts = DesignOptions(mode="tuned")
    points = [{"u_scale": 0.0}, {"u_scale": 1e6}, {"u_scale": 0.01}]
    rows = fm.map_points(sc, opts, points)
    assert rows[1]["binding"] == "failed: LinAlgError: Eigenvalues did not converge" and rows[1]["feasible"] == 0
    assert _same_rows([rows[0], rows[2]], fm.map_points(sc, opts, [points[0], points[2]]))
    assert rows[0]["feasible"] == 1  # mapped, not failed


def test_bad_options_of_a_map_stay_bad_input(tank):
    """An option wrong at every point is the user's input (exit 2), not a map of failed points."""
    with pytest.raises(InputError, match="u_scale"):
        feasibility(str(tank), "dos=0:0.5:2", u_scale=[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], quiet=True)


def test_a_scaling_whose_square_overflows_is_not_feasible():
    """u_scale = 5e153: tr U Uᵀ overflows, the tuned σ search finds no σ (NaN). That is (28) failing, as in the
    filters, not the EKF's bound without the linearisation term (which made such points feasible with the bound of
    U = 0)."""
    from designer.design import DesignOptions
    from studies.feasibility_map import map_points
    from studies.scenarios import load_scenario

    sc = load_scenario("indoor-robot")
    points = [{"u_scale": 0.0}, {"u_scale": 50.0}, {"u_scale": 5e153}]
    for batched in (True, False):
        rows = map_points(sc, DesignOptions(mode="tuned"), points, batched=batched)
        assert [r["feasible"] for r in rows] == [1, 0, 0], rows
        assert rows[2]["binding"] == "(28)" and np.isnan(rows[2]["trace_bound"])


# A scalar model whose map has certified, vacuous and infeasible points (the bound crosses the open loop with tau).
SCALAR = scalar_spec_model(noise=0.07, steps=25)


def _cells(md: str, section: str) -> list[list[str]]:
    text = md.split(f"\n## {section}\n", 1)[1].split("\n## ", 1)[0]
    return [[c.strip() for c in ln.strip().strip("|").split("|")] for ln in text.splitlines() if ln.startswith("| ")]


def test_the_report_and_the_map_say_what_the_table_says(tmp_path):
    """Every sentence of the report and the map's categories are derived from the table's verdicts: the counts,
    where the design is certified (never "everywhere" when a point is not), the ranked points, each cell of the grid
    and each cell of the map, and the map's legend with its counts."""
    from studies.feasibility_terms import MAP_CATEGORIES
    from studies.figures import map_figure

    (tmp_path / "scalar.py").write_text(SCALAR)
    out = tmp_path / "f"
    fmap = feasibility(str(tmp_path / "scalar.py"), ["tau=0:1:5", "dos=0:0.6:4"], mode="paper", out=out,
                       quiet=True)
    with open(out / "feasibility.csv") as fh:
        table = list(csv.DictReader(fh))
    # the map's category: the verdict, a certified point without a fixed point (feasible 0) "not bounded"
    verdict = {(float(t["tau"]), float(t["dos"])): "not bounded" if t["verdict"] == "certified" and t["feasible"] == "0"
               else t["verdict"] for t in table}
    counts = {c: sum(v == c for v in verdict.values()) for c in MAP_CATEGORIES}
    n, n_cert = len(table), counts["certified"]
    assert 0 < n_cert < n and counts["vacuous"] and counts["infeasible"]  # the case the report got wrong
    md = (out / "report.md").read_text()
    summary = md.split("\n## Summary\n", 1)[1].split("\n## ", 1)[0]
    assert f"**Certified at {n_cert} of {n} grid points.**" in summary
    where = next(ln for ln in summary.splitlines() if ln.startswith("**Where the design is certified:**"))
    assert f"at {n_cert} of {n} points" in where and "everywhere" not in where and "nowhere" not in where
    for c in MAP_CATEGORIES[1:]:
        assert (f"{counts[c]} {c} (" in where) == (counts[c] > 0), c
    ranked = [r for r in _cells(md, "Summary") if r[0].isdigit()]
    certified = sorted((float(t["trace_bound"]), (float(t["tau"]), float(t["dos"]))) for t in table
                       if verdict[(float(t["tau"]), float(t["dos"]))] == "certified")
    assert len(ranked) == n_cert and [r[1] for r in ranked] == [f"tau = {p[0]:g}, dos = {p[1]:g}"
                                                              for _, p in certified]
    counted = {r[0].split(" (")[0]: int(r[1]) for r in _cells(md, "How much is certified") if r[1].isdigit()}
    assert counted == counts
    grid = _cells(md, "The grid")
    (_, taus), (_, doses) = fmap.grids
    for row in grid[1:]:
        for dos, cell in zip(doses, row[1:]):
            v = verdict[(float(row[0]), float(dos))]
            shown = ("infeasible" if cell.startswith("✗") else "vacuous" if cell.startswith("vacuous") else
                     "not bounded" if cell.startswith("not bounded") else "certified")
            assert shown == v, (row[0], dos, cell)
    # the map: one cell per point in its category, every category in the legend with its count
    fig = map_figure(fmap.rows, fmap.grids, "scalar", "paper")
    ax = fig.axes[0]
    (mesh,) = [c for c in ax.collections if c.get_gid() == "categories"]
    codes = np.asarray(mesh.get_array()).reshape(len(taus), len(doses))
    for i, tau in enumerate(taus):
        for j, dos in enumerate(doses):
            assert MAP_CATEGORIES[int(codes[i, j])] == verdict[(float(tau), float(dos))]
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    for c in MAP_CATEGORIES:
        assert sum(t.startswith(c) and t.endswith(f": {counts[c]}") for t in legend) == 1, (c, legend)


def test_a_one_parameter_map_draws_each_category_apart():
    """A 1-D map: one labelled set of markers per category, holding exactly that category's points (a point
    without a bound on the lowest bound's level); an unbounded iteration is vacuous, a stalled one below the open
    loop certified but not bounded (the category "not bounded"), one not computed apart."""
    from designer.feasibility import SteadyState
    from studies.feasibility_map import point_verdict
    from studies.feasibility_terms import MAP_CATEGORIES
    from studies.figures import map_figure

    assert point_verdict(SteadyState(False, np.nan, "unbounded", 9, False, None), 1.0, 2) == "vacuous"
    assert point_verdict(SteadyState(False, 0.5, "no convergence", 400, False, None), 1.0, 2) == "certified"
    assert point_verdict(SteadyState(False, 2.0, "no convergence", 400, False, None), 1.0, 2) == "vacuous"
    kinds = ["certified", "certified", "not bounded", "vacuous", "vacuous", "infeasible", "not computed"]
    rows = [{"feasible": int(k in ("certified", "vacuous") and i != 4), "trace_bound": 0.1 * (i + 1),
             "binding": "(28)" if k == "infeasible" else "unbounded" if i == 4 else "none", "theorem2": 1,
             "iterations": 10, "verdict": "certified" if k == "not bounded" else k} for i, k in enumerate(kinds)]
    values = np.linspace(0.0, 0.5, len(rows))
    ax = map_figure(rows, [("dos", values)], "toy", "paper").axes[0]
    for c in MAP_CATEGORIES:
        (line,) = [ln for ln in ax.get_lines() if ln.get_gid() == f"category:{c}"]
        assert list(line.get_xdata()) == [v for v, k in zip(values, kinds) if k == c], c
        assert line.get_label().startswith(c) and line.get_label().endswith(f": {kinds.count(c)}")


def test_the_summary_counts_alike_reasons_together_and_keeps_equation_labels(tmp_path):
    """Binding reasons that differ only in their numbers (a growth factor, an iteration) are one kind of reason in
    the summary's sentence, counted together, while the conditions' labels (28), (29) stay apart: on a map of a
    random walk where no point settles, the sentence has one reason for all its points, not one per point."""
    (tmp_path / "walk.py").write_text(scalar_spec_model(gain=1.02, noise=7e3, steps=25))
    out = tmp_path / "f"
    feasibility(str(tmp_path / "walk.py"), ["dos=0:0.6:4"], mode="scheduled", out=out, quiet=True)
    with open(out / "feasibility.csv") as fh:
        table = list(csv.DictReader(fh))
    md = (out / "report.md").read_text()
    where = next(ln for ln in md.splitlines() if ln.startswith("**Where the design is certified:**"))
    kinds = {b for t in table for b in [t["binding"]]}
    assert len(kinds) > 1  # the points' reasons differ (in their numbers): the case the sentence listed one by one
    for t in table:
        assert t["binding"] not in where
    n = {c: sum(t["verdict"] == c for t in table) for c in {t["verdict"] for t in table}}
    for c, count in n.items():
        assert f"{count} {c} (binding: " in where
    assert where.count(" at ") <= 3 * len(n) + 1
