"""Observability of nodes and network, and the steady-state Kalman references (python-control) against scipy."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from scipy.linalg import solve_discrete_are

from designer import Gaussian, Model, Sensor
from designer.observability import kalman_references, observability


def model(F, rows):
    x = ca.SX.sym("x", 2)
    sensors = [Sensor(f"s{i}", ca.mtimes(ca.DM([r]), x), Gaussian.zero_mean([[0.1]])) for i, r in enumerate(rows)]
    return Model("lin", x, ca.mtimes(ca.DM(F), x), sensors, Gaussian.zero_mean(0.01 * np.eye(2)),
                 Gaussian([0.0, 0.0], np.eye(2)))


def test_ranks_of_coupled_and_decoupled_states():
    coupled = model([[0.9, 0.2], [0.0, 0.8]], [[0.0, 1.0], [1.0, 0.0]])
    o = observability(coupled, [0.0, 0.0])
    # x1 is seen through the coupling from x2's sensor only if x2 drives x1: sensor 0 (x2) cannot see x1
    assert [d["rank"] for d in o["nodes"]] == [1, 2] and o["network"] == {"rank": 2, "observable": True}
    assert o["unobservable_nodes"] == [0]
    decoupled = model(np.diag([0.9, 0.8]), [[1.0, 0.0], [1.0, 0.0]])
    o = observability(decoupled, [0.0, 0.0])
    assert o["network"]["observable"] is False and o["unobservable_nodes"] == [0, 1]


def test_kalman_references_are_the_riccati_solutions():
    F = np.array([[0.95, 0.1], [0.0, 0.9]])
    m = model(F, [[1.0, 0.0], [0.3, 1.0]])
    ref = kalman_references(m, [0.0, 0.0])
    Q, R = 0.01 * np.eye(2), 0.1 * np.eye(2)
    H = np.array([[1.0, 0.0], [0.3, 1.0]])

    def post(Hm, Rm):
        P = solve_discrete_are(F.T, Hm.T, Q, Rm)
        return np.trace(P - P @ Hm.T @ np.linalg.solve(Hm @ P @ Hm.T + Rm, Hm @ P))

    assert ref["centralized"] == pytest.approx(post(H, R), rel=1e-8)
    for i in range(2):
        assert ref["local"][i] == pytest.approx(post(H[i:i + 1], R[i:i + 1, i:i + 1]), rel=1e-8)
    assert ref["centralized"] < min(ref["local"])


def test_no_local_reference_without_detectability():
    # a random walk in x2 that node 0 never sees: no steady state for node 0 alone; a stable unseen mode is fine
    m = model([[0.9, 0.0], [0.0, 1.0]], [[1.0, 0.0], [0.0, 1.0]])
    ref = kalman_references(m, [0.0, 0.0])
    assert ref["local"][0] is None and ref["local"][1] is not None and ref["centralized"] is not None
    stable = model([[0.9, 0.0], [0.0, 0.5]], [[1.0, 0.0], [0.0, 1.0]])
    assert kalman_references(stable, [0.0, 0.0])["local"][0] is not None


def test_design_and_feasibility_reports_say_who_observes(tmp_path):
    from pathlib import Path

    import studies

    mixed = Path(__file__).resolve().parents[1] / "examples" / "mixed_sensors_model.py"
    d = studies.design(mixed, mode="tuned", steps=5, out=tmp_path / "d")
    obs = d.schedule.meta["observability"]
    assert obs["network"]["observable"] and obs["unobservable_nodes"] == [1, 2, 3, 4]
    md = (tmp_path / "d" / "report.md").read_text()
    assert "4 of 5 nodes cannot observe it alone" in md and "centralized steady-state Kalman filter" in md
    studies.feasibility(mixed, "dos=0:0.2:2", mode="tuned", out=tmp_path / "f")
    assert "## Observability and the Kalman references" in (tmp_path / "f" / "report.md").read_text()


def test_references_and_ranks_equal_python_control():
    # the Riccati solution and the observability matrix are python-control's, without importing it in production
    import control

    F = np.array([[1.0, 0.2], [-0.1, 0.97]])
    H = np.array([[1.0, 0.0], [0.0, 1.0]])
    m = model(F, H.tolist())
    ref = kalman_references(m, [0.0, 0.0])
    Q, R = 0.01 * np.eye(2), 0.1 * np.eye(2)
    for Hm, Rm, got in ((H, R, ref["centralized"]), (H[:1], R[:1, :1], ref["local"][0]),
                        (H[1:], R[1:, 1:], ref["local"][1])):
        _, P, _ = control.dlqe(F, np.eye(2), Hm, Q, Rm)
        P = np.asarray(P)
        post = np.trace(P - P @ Hm.T @ np.linalg.solve(Hm @ P @ Hm.T + Rm, Hm @ P))
        assert got == pytest.approx(post, rel=1e-12)
    o = observability(m, [0.0, 0.0])
    for i in range(2):
        assert o["nodes"][i]["rank"] == np.linalg.matrix_rank(np.asarray(control.obsv(F, H[i:i + 1])))
