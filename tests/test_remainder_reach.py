"""The scheduled design's prior scalings follow the error's reach (rules.scheduled.design.remainder_reach) and its
gains count the remainder at that reach as noise (linearisation_noise): the scaling argument checked against the
true remainders of a model whose Hessian is known exactly, and the design on a curved model checked on fresh runs."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from designer import Gaussian, Model, Sensor, SensorNetwork
from designer.design import whitened_scaling
from rules.scheduled.design import linearisation_noise, remainder_reach

P0 = np.diag([0.04, 0.09])
X0 = np.array([0.3, -0.2])
A = 0.7  # f_1 = x1 - A x0^2: its Hessian is constant, so the prior scalings' supremum is exact


def _quadratic() -> Model:
    x = ca.SX.sym("x", 2)
    f = ca.vertcat(x[0] + 0.1 * x[1], x[1] - A * x[0] ** 2)
    return Model("quadratic", x, f, [Sensor("s", x[0], Gaussian.zero_mean([[0.01]]))],
                 process_noise=Gaussian.zero_mean(1e-4 * np.eye(2)), prior=Gaussian(X0, P0))


def test_the_reach_is_the_square_root_of_the_whitened_spread_at_most_one():
    W = np.diag(1 / np.sqrt(np.diag(P0)))
    assert remainder_reach(P0[None], W) == pytest.approx(1.0)
    assert remainder_reach(np.stack([0.25 * P0, 0.09 * P0]), W) == pytest.approx(0.5)  # the widest node
    assert remainder_reach(4.0 * P0[None], W) == 1.0  # beyond the prior: the prior scalings, as before
    assert remainder_reach(P0[None], None) == 1.0  # scalings the user gave: used as given
    VV = np.stack([np.eye(1) * 0.3, np.eye(1) * 0.2])
    noise = linearisation_noise(np.stack([0.25 * P0, 4 * P0]), W, VV)
    assert noise[0, 0, 0] == pytest.approx(0.25 * 0.3) and noise[1, 0, 0] == pytest.approx(0.2)
    assert linearisation_noise(P0[None], None, VV) == 0.0


@pytest.mark.parametrize("shrink", [1.0, 0.2, 0.03])
def test_the_scaled_remainder_bounds_the_true_one_within_the_reach_and_is_tight(shrink):
    """For errors in the 3-sigma ellipsoid of P = shrink P0, |r_j| <= reach u_j |W e| (the true remainder of f,
    sampled on the ellipsoid's surface and inside); at the Hessian's direction on the surface it is an equality, so the
    same scaling times 0.95 fails there (the negative control)."""
    m = _quadratic()
    U, _, W, _ = whitened_scaling(m, x0=X0, P0=P0, radius=3.0)
    u = np.diag(U)
    P = shrink * P0
    reach = remainder_reach(P[None], W)
    assert reach == pytest.approx(np.sqrt(shrink))
    F = m.F_expected(X0)
    fx = m.f_expected(X0)

    def ratio(e):
        r = m.f_expected(X0 + e) - fx - F @ e
        return np.abs(r) / np.maximum(reach * u * np.linalg.norm(W @ e), 1e-300)

    rng = np.random.default_rng(7)
    z = rng.standard_normal((4000, 2))
    z = z / np.linalg.norm(z, axis=1, keepdims=True) * 3.0 * rng.uniform(0, 1, (4000, 1)) ** 0.5
    errors = z @ np.linalg.cholesky(P).T  # inside the 3-sigma ellipsoid of P
    worst = max(ratio(e)[1] for e in errors)
    assert worst <= 1.0 + 1e-9
    tight = np.linalg.cholesky(P) @ np.array([3.0, 0.0])  # along x0 on the surface: where the Hessian acts
    assert ratio(tight)[1] == pytest.approx(1.0, rel=1e-9)
    assert ratio(tight)[1] / 0.95 > 1.0  # the scaling times 0.95 would not bound it


def _pendulum() -> Model:
    x = ca.SX.sym("x", 2)
    dt = 0.05
    f = ca.vertcat(x[0] + dt * x[1], x[1] - dt * (9.81 * ca.sin(x[0]) + 0.25 * x[1]))
    sensors = [Sensor("encoder", x[0], Gaussian.zero_mean([[2e-3]])),
               Sensor("camera", ca.vertcat(ca.sin(x[0]), -ca.cos(x[0])), Gaussian.zero_mean(1e-3 * np.eye(2))),
               Sensor("range", ca.sqrt((ca.sin(x[0]) - 2.5) ** 2 + (-ca.cos(x[0]) + 0.5) ** 2),
                      Gaussian.zero_mean([[1e-3]]))]
    return Model("pendulum3", x, f, sensors, process_noise=Gaussian.zero_mean(np.diag([1e-6, 2e-4])),
                 prior=Gaussian([0.6, 0.0], np.diag([0.05, 0.05])))


def test_a_curved_models_scheduled_bound_settles_and_holds_on_fresh_runs(monkeypatch):
    """A pendulum's scheduled bound with the prior scalings: bounded, and the errors of fresh runs below it after the
    transient (the study's bound check); with the remainders kept at their prior size (the reach 1, no noise for the
    gains: what the design did before) the same bound grows without settling."""
    import rules.scheduled.certificate as sc
    import rules.scheduled.design as sd
    from studies import api

    m = _pendulum()
    net = SensorNetwork.from_edges(3, [(0, 1), (1, 2), (2, 0)])
    # first, and over 59 steps: the tables of a design are computed once per scenario, design and horizon
    with monkeypatch.context() as mp:
        mp.setattr(sd, "remainder_reach", lambda P, W: 1.0)
        mp.setattr(sc, "remainder_reach", lambda P, W: 1.0)
        mp.setattr(sd, "linearisation_noise", lambda P, W, VV: 0.0)
        before = api.design(m, network=net, mode="scheduled", steps=59, seed=1)
    d = api.design(m, network=net, mode="scheduled", steps=60, seed=1)
    assert d.bounded and np.isfinite(d.trace_bound).all()
    assert not before.bounded
    assert before.trace_bound[:, -1].max() > 100 * d.trace_bound[:, -1].max()
    res = api.study("consensus-robot", m, network=net, runs=30, seed=5, mode="scheduled")
    name = next(n for n in res.results["filters"] if "scheduled" in n)
    check = res.results["filters"][name]["bound_check"]
    assert check["fill"] < 1.0, check
