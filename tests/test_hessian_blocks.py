"""Model.hessian_blocks: every component's Hessian on its structural support, against the dense Hessians."""
from __future__ import annotations

import casadi as ca
import numpy as np

from designer import Gaussian, Model, Sensor
from designer.design import resolve_scaling
from designer.linearization import component_scales


def _model(modes: bool):
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 1)
    r = ca.SX.sym("r") if modes else None
    f = ca.vertcat(x[0] + 0.1 * ca.sin(x[1]) * (1 + (r if modes else 0)), x[1] * x[2] + u[0], 2 * x[2], x[3])
    sensors = [Sensor("quad", ca.vertcat(x[0] ** 2, x[1]), Gaussian.zero_mean(np.eye(2))),
               Sensor("range", ca.sqrt(x[2] ** 2 + x[3] ** 2 + 1), Gaussian.zero_mean([[0.1]])),
               Sensor("plain", x[3], Gaussian.zero_mean([[1.0]]))]
    kw = {"mode": r, "mode_probs": [0.5, 0.5]} if modes else {}
    return Model("blocks", x, f, sensors, process_noise=Gaussian.zero_mean(np.eye(4)),
                 prior=Gaussian(np.array([0.3, -0.2, 1.0, 2.0]), 0.5 * np.eye(4)), u=u, **kw)


def _dense(blocks, supports, n):
    out = np.zeros(blocks[0].shape[:-2] + (len(blocks), n, n))
    for j, (b, S) in enumerate(zip(blocks, supports)):
        out[..., j, S[:, None], S] = b
    return out


def test_blocks_placed_on_their_supports_are_the_dense_hessians():
    m = _model(False)
    pts = np.random.default_rng(0).normal(size=(7, 4))
    u = np.array([0.5])
    supports, at = m.hessian_blocks()
    np.testing.assert_array_equal(_dense(at(pts, 0, u), supports, 4), m.f_hessian(pts, 0, u))
    assert [S.tolist() for S in supports] == [[1], [1, 2], [], []]  # linear components: empty support
    for i in range(m.n_sensors):
        supports, at = m.hessian_blocks(i)
        np.testing.assert_array_equal(_dense(at(pts, 1), supports, 4), m.h_hessian(i, pts, 1))
    assert m.hessian_blocks(2)[0][0].size == 0
    assert m.hessian_blocks(1)[0][0].tolist() == [2, 3]


def test_component_scales_from_blocks_equal_those_from_the_dense_hessians():
    m = _model(False)
    x0, P0 = m.prior.mean, m.prior.cov
    u = np.array([0.5])
    dense = component_scales(lambda p: m.f_hessian(p, 0, u), x0, P0)
    blocks = component_scales(lambda p: m.hessian_blocks()[1](p, 0, u), x0, P0)
    np.testing.assert_allclose(blocks, dense, rtol=1e-14, atol=0)
    assert blocks[2] == blocks[3] == 0.0
    for i in range(m.n_sensors):
        np.testing.assert_allclose(component_scales(lambda p: m.hessian_blocks(i)[1](p, 1), x0, P0),
                                   component_scales(lambda p: m.h_hessian(i, p, 1), x0, P0), rtol=1e-14, atol=0)


def test_the_prior_scaling_of_a_model_with_modes_and_inputs_matches_the_dense_one():
    m = _model(True)
    x0, P0, u0 = m.prior.mean, m.prior.cov, np.array([0.5])
    U, V = resolve_scaling(m, None, None, x0=x0, P0=P0, u0=u0)
    dense = component_scales(lambda p: np.concatenate([m.f_hessian(p, 0, u0, r) for r in range(2)], axis=1), x0, P0)
    np.testing.assert_allclose(np.diag(U), dense.reshape(2, 4).max(0), rtol=1e-14, atol=0)
    for i, Vi in enumerate(V):
        np.testing.assert_allclose(np.diag(np.atleast_2d(Vi)) if np.ndim(Vi) == 2 else Vi,
                                   component_scales(lambda p, i=i: m.h_hessian(i, p, 1), x0, P0), rtol=1e-14, atol=0)
