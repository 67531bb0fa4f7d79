"""The feasibility maps' batched fixed-point iteration: every point gets the answer it gets alone.

:func:`designer.feasibility.steady_state_batch` iterates the stationary recursion (26)-(27) at all the
points of a map at once; :func:`designer.feasibility.steady_state` is the per-point iteration.  Each
point's checks, Anderson acceleration (restarts, backtracking) and convergence test are its own, so
the two agree on the verdict, the binding condition, Theorem 2 and the iteration count, and the
fixed points agree to rounding (here they are bit for bit; the tolerance stated is 1e-12).
"""
from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from designer.design import DesignOptions
from designer.feasibility import steady_state, steady_state_batch
from designer.network import SensorNetwork
from designer.tuning import tune_prediction, tune_prediction_batch, tune_update, tune_update_batch
from designer.validation import InputError
from studies.feasibility_map import map_points, parse_grid
from studies.scenarios import scenario_of

ROOT = Path(__file__).resolve().parents[1]
RTOL = 1e-12


def _points(grids):
    parsed = [parse_grid(g) for g in grids]
    names = [n for n, _ in parsed]
    return [dict(zip(names, map(float, c))) for c in itertools.product(*[v for _, v in parsed])]


def _agree(a: dict, b: dict) -> bool:
    same = all(a[k] == b[k] for k in ("feasible", "binding", "theorem2", "iterations"))
    ta, tb = a["trace_bound"], b["trace_bound"]
    return same and (np.isnan(ta) and np.isnan(tb) or abs(ta - tb) <= RTOL * abs(tb))


# (target, mode, linearisation, grids): the robot and three user model files (the ring of the README, a
# linear path, and range-bearing, range-only and bearing-only sensors of different dimensions on a star), both
# modes, the three linearisations; together they reach every outcome (feasible, (28), (29), unbounded,
# dos + fdi > 1)
MAPS = [
    ("examples/ring_model.py", "tuned", "fixed", ["dos=0:0.8:3", "fdi=0:0.9:3"]),
    ("examples/linear_network_model.py", "paper", "fixed", ["sigma=0.002:0.5:3", "beta=0.002:0.5:3"]),
    ("indoor-robot", "paper", "fixed", ["tau=0:0.6:3", "beta=0.05:0.6:3"]),
    ("indoor-robot", "tuned", "hessian", ["fdi=0:0.4:2"]),
    ("examples/mixed_sensors_model.py", "tuned", "fixed", ["fdi=0:0.4:2", "epsilon=0.05:0.2:2"]),
    ("examples/mixed_sensors_model.py", "paper", "structured", ["dos=0:0.5:3", "beta=0.05:0.2:3"]),
]


@pytest.fixture(scope="module")
def compared():
    out = []
    for target, mode, lin, grids in MAPS:
        sc = scenario_of(str(ROOT / target) if target.endswith(".py") else target)
        points = _points(grids)
        opts = DesignOptions(mode=mode, linearization=lin)
        out.append((target, mode, lin, points, map_points(sc, opts, points, batched=True),
                    map_points(sc, opts, points, batched=False)))
    return out


@pytest.mark.parametrize("case", range(len(MAPS)), ids=[f"{t}-{m}-{lin}" for t, m, lin, _ in MAPS])
def test_batched_map_is_the_point_by_point_map(compared, case):
    target, mode, lin, points, batched, alone = compared[case]
    assert len(batched) == len(alone) == len(points)
    for p, a, b in zip(points, batched, alone):
        assert _agree(a, b), (target, mode, lin, p, a, b)


def test_the_compared_maps_reach_every_outcome(compared):
    rows = [r for *_, batched, _ in compared for r in batched]
    feasible = {r["binding"] for r in rows if r["feasible"]}
    infeasible = {r["binding"] for r in rows if not r["feasible"]}
    assert "none (interior optimum)" in feasible and feasible & {"(28)", "(29)"}
    assert {"(28)", "(29)", "unbounded", "dos + fdi > 1"} <= infeasible
    assert len({r["iterations"] for r in rows if r["feasible"]}) > 3  # points that converge after different steps


def _network_points():
    """A three-node path, linear, with per-point attack probabilities and design choices."""
    A = np.array([[0.98, 0.1], [0.0, 0.95]])
    H = [np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]]), np.array([[1.0, 1.0]])]
    Q, R = 0.01 * np.eye(2), [np.array([[0.05]]), np.array([[0.05]]), np.array([[0.5]])]
    settings = [dict(dos=d, fdi=f, delta=dl, epsilon=e, u=u, v=v, sigma=sg, beta=b, tau=t)
                for d, f, dl, e, u, v, sg, b, t in [
                    (0.0, 0.0, 0.0, 0.4, 0.01, 0.01, 0.1, 0.1, 0.01),
                    (0.3, 0.1, 0.5, 0.4, 0.01, 0.01, 0.05, 0.2, 0.1),
                    (0.5, 0.3, 2.0, 0.2, 0.05, 0.0, 0.5, 0.5, 0.3),
                    (0.1, 0.4, 5.0, 0.45, 0.0, 0.1, 0.01, 0.05, 0.5),
                    (0.9, 0.0, 0.0, 0.1, 0.2, 0.2, 2.0, 1.0, 0.0),
                    (0.2, 0.2, 1.0, 0.3, 0.01, 0.05, 0.2, 0.1, 0.05),
                    (0.1, 0.0, 0.0, 0.4, 0.001, 0.001, 0.001, 0.01, 0.3),
                    (0.1, 0.0, 0.0, 0.4, 0.0, 0.0, 0.001, 0.05, 0.1),
                ]]
    nets = [SensorNetwork.from_edges(3, [(0, 1), (1, 2)], dos_prob=s["dos"], fdi_prob=s["fdi"]) for s in settings]
    return A, H, Q, R, nets, settings


@pytest.mark.parametrize("mode, accelerate, max_iter", [("tuned", True, 400), ("paper", True, 400),
                                                        ("tuned", False, 400), ("tuned", True, 6),
                                                        ("paper", False, 3)])
def test_batch_is_steady_state_point_by_point(mode, accelerate, max_iter):
    """Every field, the fixed point included, with per-point ε, δ, U, V, σ, β, τ and probabilities; no
    convergence within a few iterations too."""
    A, H, Q, R, nets, st = _network_points()
    kw = dict(fixed_multipliers=mode == "paper", accelerate=accelerate, max_iter=max_iter, phi0=0.5 * np.eye(2))
    V = [[s["v"] * np.eye(1), 2 * s["v"] * np.eye(1), s["v"] * np.eye(1)] for s in st]
    batch = steady_state_batch(A, H, Q, R, nets, epsilon=[s["epsilon"] for s in st], delta=[s["delta"] for s in st],
                               U=[s["u"] * np.eye(2) for s in st], V=V, sigma=[s["sigma"] for s in st],
                               beta=[s["beta"] for s in st], tau=[s["tau"] for s in st], **kw)
    outcomes = set()
    for s, v, net, b in zip(st, V, nets, batch):
        a = steady_state(A, H, Q, R, net, epsilon=s["epsilon"], delta=s["delta"], U=s["u"] * np.eye(2), V=v,
                         sigma=s["sigma"], beta=s["beta"], tau=s["tau"], **kw)
        assert (a.feasible, a.binding, a.iterations, a.theorem2) == (b.feasible, b.binding, b.iterations, b.theorem2)
        np.testing.assert_allclose(b.trace_bound, a.trace_bound, rtol=RTOL)
        assert (a.phi is None) == (b.phi is None)
        if a.phi is not None:
            np.testing.assert_allclose(b.phi, a.phi, rtol=RTOL, atol=0)
        outcomes.add(a.binding)
    assert len(outcomes) >= 2, outcomes  # not one outcome everywhere
    assert any(b.feasible for b in batch) or max_iter < 10


def test_batch_refuses_what_it_does_not_iterate():
    A, H, Q, R, nets, st = _network_points()
    kw = dict(epsilon=0.3, delta=0.0, U=np.zeros((2, 2)), V=[np.zeros((1, 1))] * len(nets))
    with pytest.raises(InputError, match="one entry per point"):
        steady_state_batch(A, H, Q, R, nets, **{**kw, "V": [np.zeros((1, 1))]})
    with pytest.raises(InputError, match="same nodes"):
        steady_state_batch(A, H, Q, R, nets[:1] + [SensorNetwork.from_edges(2, [(0, 1)])], **{**kw, "V": kw["V"][:2]})
    assert steady_state_batch(A, H, Q, R, [], **{**kw, "V": []}) == []


def test_stacked_tuning_with_a_value_per_item_is_the_tuning_of_each_item():
    """tune_prediction_batch with one ε per item and tune_update_batch: each item as tuned alone (bit for bit)."""
    rng = np.random.default_rng(3)
    m, n = 7, 3
    B = rng.normal(size=(m, n, n))
    phi = 0.1 * B @ np.swapaxes(B, 1, 2) + 0.05 * np.eye(n)
    F = np.eye(n) + 0.1 * rng.normal(size=(n, n))
    U = np.array([0.01 * np.eye(n)] * (m - 1) + [np.zeros((n, n))])  # the last item: U = 0 (σ = 0)
    eps = rng.uniform(0.1, 0.5, m)
    pb = tune_prediction_batch(phi, F, U, 1e-3 * np.eye(n), eps)
    for j in range(m):
        one = tune_prediction(phi[j], F, U[j], 1e-3 * np.eye(n), eps[j])
        assert one.sigma == pb.sigma[j] and np.array_equal(one.phi_pred, pb.phi_pred[j])
    H = rng.normal(size=(m, 2, n))
    V = np.array([0.1 * np.eye(2)] * (m - 2) + [np.zeros((2, 2))] * 2)  # V = 0: β = 0
    R = np.array([np.eye(2)] * m)
    s, d = rng.uniform(0.5, 3.0, m), rng.integers(0, 4, m)
    N = 3 * phi + 0.5 * np.eye(n)
    ub = tune_update_batch(pb.phi_pred, H, s, V, R, d, N)
    for j in range(m):
        one = tune_update(pb.phi_pred[j], H[j], s[j], V[j], R[j], int(d[j]), N[j])
        assert one.beta == ub.beta[j] and one.trace == ub.trace[j]
        for x, y in ((one.C, ub.C[j]), (one.K, ub.K[j]), (one.phi_post, ub.phi_post[j])):
            assert np.array_equal(x, y)
    assert ub.beta[-1] == 0.0 and np.all(ub.beta[:-2] > 0)
