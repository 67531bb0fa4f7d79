"""Hessian-derived linearisation scaling: the remainder bound holds inside the ellipsoid (Monte Carlo of Taylor)."""
from __future__ import annotations

import numpy as np
import pytest

from designer.linearization import ellipsoid_points, remainder_scale
from studies.scenarios import load_scenario


def _inside(rng, center, cov, radius, n):
    """Uniform-direction points inside the ellipsoid, many near its boundary."""
    L = np.linalg.cholesky(cov)
    d = rng.standard_normal((n, center.size))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = radius * rng.uniform(0.5, 1.0, n) ** (1 / center.size)
    return center + (d * r[:, None]) @ L.T


@pytest.mark.parametrize("seed", range(4))
def test_remainders_of_the_robot_are_within_u_and_v(seed):
    sc = load_scenario("indoor-robot")
    m = sc.model
    u0 = sc.inputs(1)[0]
    rng = np.random.default_rng(seed)
    xhat = sc.x0 + 0.2 * rng.standard_normal(3)
    B = rng.normal(size=(3, 3))
    cov = 0.02 * B @ B.T + 0.005 * np.eye(3)
    radius = 3.0
    u = remainder_scale(lambda p: m.f_hessian(p, 0, u0), xhat, cov, radius)
    x = _inside(rng, xhat, cov, radius, 4000)
    e = x - xhat
    r = m.f(x, 0, u0) - m.f(xhat, 0, u0) - e @ m.F(xhat, 0, u0).T  # the true Taylor remainder
    ratio = np.linalg.norm(r, axis=1) / np.linalg.norm(e, axis=1)
    assert ratio.max() <= u * (1 + 1e-9)
    for i in range(8):
        v = remainder_scale(lambda p: m.h_hessian(i, p, 1), xhat, cov, radius)
        rh = m.h(i, x, 1) - m.h(i, xhat, 1) - e @ m.H(i, xhat, 1).T
        assert (np.linalg.norm(rh, axis=1) / np.linalg.norm(e, axis=1)).max() <= v * (1 + 1e-9)
    # The scale is not vacuous: the largest remainder uses a good part of it.
    assert ratio.max() > 0.2 * u


def test_ellipsoid_points_lie_on_or_inside_the_ellipsoid():
    rng = np.random.default_rng(3)
    B = rng.normal(size=(3, 3))
    cov = B @ B.T + 0.1 * np.eye(3)
    c = rng.normal(size=3)
    pts = ellipsoid_points(c, cov, 2.5)
    q = np.einsum("pi,ij,pj->p", pts - c, np.linalg.inv(cov), pts - c)
    assert pts.shape == (1 + 6 + 8, 3)
    assert np.all(q <= 2.5**2 * (1 + 1e-9)) and np.isclose(q.max(), 2.5**2)


def test_linear_model_has_zero_scaling():
    m = load_scenario("four-tank").model
    v = remainder_scale(lambda p: m.h_hessian(0, p, 1), np.full(4, 10.0), np.eye(4), 3.0)
    assert v == 0.0


@pytest.mark.slow
def test_hessian_design_is_feasible_on_the_default_horizon_and_reports_its_divergence_on_a_long_one():
    """The Hessian remainders grow with the ellipsoid of Φ: a feedback that over 100 steps drives the bound
    beyond any meaning (the tuned nodes then run alone, C = 0, so FDI no longer matters to it)."""
    from studies.api import design

    ok = design("indoor-robot", mode="tuned", linearization="hessian", fdi=0.0, seed=0)
    assert ok.result.feasible and ok.schedule.meta["linearization"] == "hessian"
    bad = design("indoor-robot", mode="tuned", linearization="hessian", seed=0, steps=100)
    assert not bad.result.feasible
    assert any(v["condition"] in ("diverged", "(28)", "(29)") for v in bad.result.violations)


def test_hessian_cover_of_the_scenarios():
    """The symbolic Hessian sparsity gives the variables each model is nonlinear in."""
    from designer.linearization import hessian_cover

    robot = load_scenario("indoor-robot").model
    assert hessian_cover(robot.casadi_f_hess) == (2,)  # the unicycle is nonlinear in the heading only
    assert all(hessian_cover(h) == (2,) for h in robot.casadi_h_hess)  # cameras: every term involves theta
    rb = load_scenario("target-range-bearing").model
    assert hessian_cover(rb.casadi_f_hess) == () and hessian_cover(rb.casadi_h_hess[0]) == (0, 2)


@pytest.mark.parametrize("seed", range(3))
def test_structured_remainders_factor_through_the_cover(seed):
    """r = (u I) Ω D e with ||Ω|| <= 1: ||r|| <= u ||e_S|| for errors inside the ellipsoid."""
    from designer.linearization import hessian_cover, structured_scale

    sc = load_scenario("indoor-robot")
    m = sc.model
    u0 = sc.inputs(1)[0]
    rng = np.random.default_rng(10 + seed)
    xhat = sc.x0 + 0.2 * rng.standard_normal(3)
    B = rng.normal(size=(3, 3))
    cov = 0.02 * B @ B.T + 0.005 * np.eye(3)
    x = _inside(rng, xhat, cov, 3.0, 4000)
    e = x - xhat
    cover = hessian_cover(m.casadi_f_hess)
    u = structured_scale(lambda p: m.f_hessian(p, 0, u0), xhat, cov, cover, 3.0)
    r = m.f(x, 0, u0) - m.f(xhat, 0, u0) - e @ m.F(xhat, 0, u0).T
    eS = np.linalg.norm(e[:, list(cover)], axis=1)
    assert (np.linalg.norm(r, axis=1) / eS).max() <= u * (1 + 1e-9)
    for i in range(8):
        cov_h = hessian_cover(m.casadi_h_hess[i])
        v = structured_scale(lambda p: m.h_hessian(i, p, 1), xhat, cov, cov_h, 3.0)
        rh = m.h(i, x, 1) - m.h(i, xhat, 1) - e @ m.H(i, xhat, 1).T
        assert (np.linalg.norm(rh, axis=1) / np.linalg.norm(e[:, list(cov_h)], axis=1)).max() <= v * (1 + 1e-9)


@pytest.mark.slow
def test_structured_design_is_tighter_than_the_unstructured_one():
    from studies.api import design

    full = design("indoor-robot", mode="tuned", linearization="hessian", fdi=0.0, seed=1)
    struct = design("indoor-robot", mode="tuned", linearization="structured", fdi=0.0, seed=1)
    assert full.result.feasible and struct.result.feasible
    tr_full = np.trace(full.result.phi_post[1:], axis1=-2, axis2=-1).mean()
    tr_struct = np.trace(struct.result.phi_post[1:], axis1=-2, axis2=-1).mean()
    assert tr_struct < tr_full
