"""The model layer: NumPy translation against CasADi, derivatives against finite differences."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from designer import Gaussian, InputError, Model, Sensor, simulate, to_numpy
from designer.codegen import UnsupportedOperation
from studies.scenarios import SCENARIOS


def _casadi_rows(fun: ca.Function, X: np.ndarray, *extra) -> list[np.ndarray]:
    """Evaluate a CasADi function row by row (the reference for the batched translation)."""
    return [np.array(fun(X[n], *extra)).astype(float) for n in range(X.shape[0])]


# ----------------------------------------------------------------------------- codegen
def test_translation_covers_many_operations():
    x = ca.SX.sym("x", 3)
    a, b, c = x[0], x[1], x[2]
    exprs = [
        a + b, a - b, a * b, a / (1 + b**2), -a, 2 * a, a**2, 1 / (1 + c**2), ca.exp(a), ca.log(1 + b**2),
        ca.sqrt(1 + a**2), a**b * 0 + ca.fabs(a) ** 1.5, ca.fabs(a) ** b, ca.sin(a), ca.cos(b), ca.tan(0.3 * c),
        ca.asin(ca.tanh(a)), ca.acos(ca.tanh(b)), ca.atan(c), ca.atan2(a, b), ca.sinh(a), ca.cosh(b), ca.tanh(c),
        ca.asinh(a), ca.acosh(1 + b**2), ca.atanh(0.5 * ca.tanh(c)), ca.fabs(a), ca.sign(b), ca.floor(3 * a),
        ca.ceil(3 * b), ca.fmod(5 * a, 1.3), ca.fmin(a, b), ca.fmax(b, c), ca.if_else(a > b, a * c, b - c),
        ca.logic_and(a > 0, b < 0), ca.logic_or(a > 0, b < 0), ca.logic_not(c > 0), a == b, a != c, a <= c,
        ca.erf(a), ca.log1p(b**2), ca.expm1(c), ca.hypot(a, c), ca.copysign(a, b), ca.DM(7.5),
    ]
    fun = ca.Function("many", [x], [ca.vertcat(*exprs)])
    g = to_numpy(fun)
    X = np.random.default_rng(0).normal(size=(200, 3)) * 2
    (batched,) = g(X)
    ref = np.stack([r.ravel() for r in _casadi_rows(fun, X)])
    assert batched.shape == (200, len(exprs))
    np.testing.assert_allclose(batched, ref, rtol=1e-12, atol=1e-12)


def test_translation_broadcasts_and_keeps_matrix_outputs():
    x = ca.SX.sym("x", 2)
    k = ca.SX.sym("k")
    out = ca.vertcat(x[0] * k, ca.sin(x[1]))
    fun = ca.Function("g", [x, k], [out, ca.jacobian(out, x)])
    g = to_numpy(fun)
    X = np.random.default_rng(1).normal(size=(4, 5, 2))
    val, jac = g(X, np.array([3.0]))
    assert val.shape == (4, 5, 2) and jac.shape == (4, 5, 2, 2)
    np.testing.assert_allclose(val[..., 0], 3.0 * X[..., 0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(jac[..., 1, 1], np.cos(X[..., 1]), rtol=1e-15)
    assert np.all(jac[..., 0, 1] == 0.0)  # structural zero stays zero
    # A single state (no batch dimension) works too.
    v1, _ = g(X[0, 0], 3.0)
    assert v1.shape == (2,)


def test_translation_rejects_unsupported_operation():
    x = ca.SX.sym("x", 2)
    fun = ca.Function("r", [x], [ca.remainder(x[0], x[1])])
    with pytest.raises(UnsupportedOperation, match="REMAINDER"):
        to_numpy(fun)


# ------------------------------------------------------------------- every scenario
def _states(scenario, n: int, seed: int) -> np.ndarray:
    """States the model actually visits: points of a simulated run, perturbed."""
    rng = np.random.default_rng(seed)
    tr = scenario.simulate(rng)
    idx = rng.integers(0, tr.x.shape[0], n)
    X = tr.x[idx]
    return X + 0.01 * np.abs(X).mean(axis=0) * rng.standard_normal(X.shape)


def _modes(model):
    return list(range(model.n_modes)) if model.n_modes else [None]


def _mode_arg(m):
    return np.zeros(0) if m is None else np.array([float(m)])


@pytest.fixture(scope="module", params=sorted(SCENARIOS))
def scenario(request):
    return SCENARIOS[request.param].build()


def test_batched_evaluation_matches_casadi(scenario):
    m = scenario.model
    X = _states(scenario, 40, 2)
    u = scenario.inputs(1)
    u0 = np.zeros(0) if u is None else u[0]
    for mode in _modes(m):
        ref_f = np.stack([r.ravel() for r in _casadi_rows(m.casadi_f, X, 3.0, u0, _mode_arg(mode))])
        ref_F = np.stack(_casadi_rows(m.casadi_F, X, 3.0, u0, _mode_arg(mode)))
        scale = max(1.0, np.abs(ref_f).max())
        np.testing.assert_allclose(m.f(X, 3, u0, mode), ref_f, rtol=1e-12, atol=1e-12 * scale)
        np.testing.assert_allclose(m.F(X, 3, u0, mode), ref_F, rtol=1e-12, atol=1e-12 * max(1.0, np.abs(ref_F).max()))
        hess = m.f_hessian(X, 3, u0, mode)
        for j in range(m.n_x):
            ref = np.stack([np.array(m.casadi_f_hess(X[n], 3.0, u0, _mode_arg(mode))[j]) for n in range(len(X))])
            np.testing.assert_allclose(hess[:, j], ref, rtol=1e-12, atol=1e-12 * max(1.0, np.abs(ref).max()))
    ref_all = np.stack([r.ravel() for r in _casadi_rows(m.casadi_h_all, X, 3.0)])
    np.testing.assert_allclose(m.h_all(X, 3), ref_all, rtol=1e-12, atol=1e-12 * max(1.0, np.abs(ref_all).max()))
    for i in range(m.n_sensors):
        ref_h = np.stack([r.ravel() for r in _casadi_rows(m.casadi_h[i], X, 3.0)])
        ref_H = np.stack(_casadi_rows(m.casadi_H[i], X, 3.0))
        np.testing.assert_allclose(m.h(i, X, 3), ref_h, rtol=1e-12, atol=1e-12 * max(1.0, np.abs(ref_h).max()))
        np.testing.assert_allclose(m.H(i, X, 3), ref_H, rtol=1e-12, atol=1e-12 * max(1.0, np.abs(ref_H).max()))
        np.testing.assert_allclose(np.concatenate(m.split(m.h_all(X, 3)), -1)[..., m._offsets[i]:m._offsets[i + 1]],
                                   m.h(i, X, 3), rtol=0, atol=0)


def _central_jacobian(fn, x: np.ndarray, step: np.ndarray) -> np.ndarray:
    cols = []
    for j in range(x.shape[0]):
        e = np.zeros_like(x)
        e[j] = step[j]
        cols.append((fn(x + e) - fn(x - e)) / (2 * step[j]))
    return np.stack(cols, axis=-1)


def _central_hessian(fn, x: np.ndarray, step: np.ndarray) -> np.ndarray:
    n = x.shape[0]
    out = np.empty(fn(x).shape + (n, n))
    for i in range(n):
        for j in range(n):
            ei, ej = np.zeros(n), np.zeros(n)
            ei[i], ej[j] = step[i], step[j]
            out[..., i, j] = (fn(x + ei + ej) - fn(x + ei - ej) - fn(x - ei + ej) + fn(x - ei - ej)) / (
                4 * step[i] * step[j])
    return out


def _close(ad, fd, rel, floor=0.0):
    """Agreement to ``rel`` of the largest entry, plus the rounding floor of the difference quotient."""
    scale = max(1e-8, np.abs(fd).max(), np.abs(ad).max())
    assert np.abs(ad - fd).max() <= rel * scale + floor, (np.abs(ad - fd).max(), scale, floor)


def _floor(values, step):
    """Rounding error of a second difference: ~eps |f| / h^2 (times a safety factor)."""
    return 20 * np.finfo(float).eps * np.abs(values).max() / step.min() ** 2


def test_jacobians_and_hessians_against_finite_differences(scenario):
    m = scenario.model
    X = _states(scenario, 6, 5)
    u = scenario.inputs(1)
    u0 = np.zeros(0) if u is None else u[0]
    for x in X:
        step_j = 1e-6 * np.maximum(1.0, np.abs(x))
        step_h = 1e-4 * np.maximum(1.0, np.abs(x))
        for mode in _modes(m):
            fx = lambda z: m.f(z, 2, u0, mode)  # noqa: E731
            _close(m.F(x, 2, u0, mode), _central_jacobian(fx, x, step_j), 1e-6)
            _close(m.f_hessian(x, 2, u0, mode), _central_hessian(fx, x, step_h), 1e-4, _floor(fx(x), step_h))
        for i in range(m.n_sensors):
            hx = lambda z: m.h(i, z, 2)  # noqa: E731
            _close(m.H(i, x, 2), _central_jacobian(hx, x, step_j), 1e-6)
            _close(m.h_hessian(i, x, 2), _central_hessian(hx, x, step_h), 1e-4, _floor(hx(x), step_h))


def test_expected_transition_averages_the_modes():
    m = SCENARIOS["switching-2d"].build().model
    X = np.random.default_rng(3).normal(size=(10, 2))
    p1 = m.mode_probs[1]
    expect = p1 * m.f(X, 0, None, 1) + (1 - p1) * m.f(X, 0, None, 0)
    np.testing.assert_allclose(m.f_expected(X), expect, rtol=1e-14)


# --------------------------------------------------------------------- simulation
def test_simulation_is_reproducible_bit_for_bit(scenario):
    a = scenario.simulate(np.random.default_rng(11))
    b = scenario.simulate(np.random.default_rng(11))
    c = scenario.simulate(np.random.default_rng(12))
    assert np.array_equal(a.x, b.x) and np.array_equal(a.z, b.z)
    assert not np.array_equal(a.z, c.z)
    assert a.x.shape == (scenario.steps + 1, scenario.model.n_x)
    assert a.z.shape == (scenario.steps, scenario.model.n_z)


def test_simulated_noise_has_the_stated_moments():
    """Residuals of a simulation are draws of the stated process and measurement noise."""
    sc = SCENARIOS["target-range-bearing"].build({"steps": 1})
    m = sc.model
    tr = simulate(m, 1, np.random.default_rng(4), batch=40000, x0=sc.x0)
    w = tr.x[:, 1] - m.f(tr.x[:, 0], 0)
    v = tr.z[:, 0] - m.h_all(tr.x[:, 1], 1)
    n = w.shape[0]
    for resid, cov in ((w, m.process_cov), (v[:, :2], m.measurement_cov(0))):
        se = np.sqrt(np.diag(cov) / n)
        assert np.all(np.abs(resid.mean(0)) < 5 * se)
        d = np.diag(cov)
        se_cov = np.sqrt((np.outer(d, d) + cov**2) / n)  # std error of a Gaussian sample covariance
        assert np.all(np.abs(np.cov(resid.T) - cov) < 6 * se_cov)


# --------------------------------------------------------------------- bad input
def _tiny():
    x = ca.SX.sym("x", 2)
    return x, [Sensor("s", x[0:1], Gaussian.zero_mean([[1.0]]))]


def test_model_rejects_bad_definitions():
    x, sensors = _tiny()
    y = ca.SX.sym("y")
    noise, prior = Gaussian.zero_mean(np.eye(2)), Gaussian(np.zeros(2), np.eye(2))
    with pytest.raises(InputError, match="f must have 2 rows"):
        Model("m", x, x[0], sensors, noise, prior)
    with pytest.raises(InputError, match="depends on symbols"):
        Model("m", x, ca.vertcat(x[0] * y, x[1]), sensors, noise, prior)
    with pytest.raises(InputError, match="noise has dimension"):
        Model("m", x, x, [Sensor("s", x, Gaussian.zero_mean([[1.0]]))], noise, prior)
    with pytest.raises(InputError, match="prior"):
        Model("m", x, x, sensors, noise, Gaussian(np.zeros(3), np.eye(3)))
    with pytest.raises(InputError, match="mode_probs"):
        Model("m", x, x, sensors, noise, prior, mode=ca.SX.sym("r"))
    with pytest.raises(InputError, match="x must be a purely symbolic"):
        Model("m", 2 * x, x, sensors, noise, prior)


def test_model_rejects_bad_evaluation_arguments():
    sc = SCENARIOS["indoor-robot"].build()
    m = sc.model
    with pytest.raises(InputError, match=r"x must have shape \(\.\.\., 3\)"):
        m.f(np.zeros((5, 2)), 0, [0.1, 0.1])
    with pytest.raises(InputError, match="finite"):
        m.h_all(np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(InputError, match="finite"):
        m.F(np.array([np.inf, 0.0, 0.0]), 0, [0.1, 0.1])
    with pytest.raises(InputError, match="u .*required"):
        m.f(np.zeros(3))
    with pytest.raises(InputError, match="sensor index"):
        m.h(8, np.zeros(3))
    sw = SCENARIOS["switching-2d"].build().model
    with pytest.raises(InputError, match="mode"):
        sw.f(np.zeros(2))
    with pytest.raises(InputError, match="mode must be an integer"):
        sw.f(np.zeros(2), 0, None, 2)
    with pytest.raises(InputError, match="steps"):
        simulate(m, 0, np.random.default_rng(0), inputs=np.zeros((0, 2)))
    with pytest.raises(InputError, match="rng"):
        simulate(m, 2, np.random.RandomState(0), inputs=np.zeros((2, 2)))
    with pytest.raises(InputError, match="inputs must have shape"):
        simulate(m, 2, np.random.default_rng(0), inputs=np.zeros((3, 2)))
    with pytest.raises(InputError, match="x0"):
        simulate(m, 2, np.random.default_rng(0), x0=[np.nan, 0, 0], inputs=np.zeros((2, 2)))


# ----------------------------------------------------------------------------- checks of a user's model
def _bearing_model(h_of, angles=()):
    x = ca.SX.sym("x", 3)
    dx, dy = x[0] - 1.0, x[1] + 2.0
    h = h_of(x, dx, dy)
    s = Sensor("b", h, Gaussian.zero_mean(np.eye(h.shape[0]) * 0.01), angles=angles)
    return Model("m", x, x, [s], Gaussian.zero_mean(np.eye(3)), Gaussian(np.zeros(3), np.eye(3)))


@pytest.mark.parametrize("h_of, angles, flagged", [
    (lambda x, dx, dy: ca.atan2(dy, dx), (), (0,)),
    (lambda x, dx, dy: np.arctan2(dy, dx), (), (0,)),  # NumPy's name, the same CasADi operation
    (lambda x, dx, dy: ca.atan2(dy, dx), (0,), ()),
    (lambda x, dx, dy: ca.vertcat(ca.sqrt(dx**2 + dy**2), ca.atan2(dy, dx) - x[2]), (), (1,)),  # relative bearing
    (lambda x, dx, dy: ca.vertcat(ca.sqrt(dx**2 + dy**2), ca.atan2(dy, dx) - x[2]), (1,), ()),
    (lambda x, dx, dy: ca.vertcat(ca.cos(ca.atan2(dy, dx)), ca.sin(ca.atan2(dy, dx))), (), ()),  # no jump left
    (lambda x, dx, dy: ca.atan(dy / dx), (), ()),  # not an atan2: no jump at +-pi
    (lambda x, dx, dy: ca.vertcat(dx, 3 * ca.atan2(dy, dx) + ca.sin(ca.atan2(dy, dx))), (), (1,)),
    # an elevation: atan2(z, sqrt(x^2 + y^2)) stays in [-pi/2, pi/2], no jump to wrap
    (lambda x, dx, dy: ca.vertcat(ca.atan2(x[2], ca.sqrt(dx**2 + dy**2)), ca.atan2(x[2], dx**2 + ca.fabs(dy) + 1)),
     (), ()),
    (lambda x, dx, dy: ca.atan2(x[2], ca.sqrt(dx**2 + dy**2) - 1), (), (0,)),
])
def test_an_atan2_not_declared_an_angle_is_named_in_a_warning(h_of, angles, flagged):
    import warnings

    from designer.validation import ModelWarning

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        m = _bearing_model(h_of, angles)
    mine = [w for w in seen if issubclass(w.category, ModelWarning)]
    assert m.sensors[0].undeclared_angles() == flagged
    assert len(mine) == (1 if flagged else 0)
    if flagged:
        text = str(mine[0].message)
        assert text.startswith("sensor 'b': an atan2 angle") and f"angles={tuple(sorted(angles + flagged))}" in text
        with warnings.catch_warnings(record=True) as again:  # the stacked model does not name them a second time
            warnings.simplefilter("always")
            m.with_stacked_sensors()
        assert not [w for w in again if issubclass(w.category, ModelWarning)]


def test_a_model_not_linearisable_at_its_operating_point_names_the_sensor():
    x = ca.SX.sym("x", 2)
    sensors = [Sensor("fine", x[0], Gaussian.zero_mean([[1.0]])),
               Sensor("at_point", ca.sqrt((x[0] - 1) ** 2 + (x[1] - 2) ** 2), Gaussian.zero_mean([[1.0]]))]
    m = Model("m", x, 0.9 * x, sensors, Gaussian.zero_mean(np.eye(2)), Gaussian([1.0, 2.0], np.eye(2)))
    m.check_finite_at([0.0, 0.0])
    with pytest.raises(InputError, match=r"sensor 'at_point': the Jacobian dh/dx is not finite at the operating "
                                         r"point x = \[1, 2\]"):
        m.check_finite_at([1.0, 2.0])
    # the filters' first update is at the prediction f(x0) = 0.9 x0
    with pytest.raises(InputError, match=r"sensor 'at_point'.*prediction f\(x0\) x = \[1, 2\]"):
        m.check_finite_at([1.0 / 0.9, 2.0 / 0.9])
    bad_f = Model("m", x, ca.vertcat(ca.log(x[0]), x[1]), sensors[:1], Gaussian.zero_mean(np.eye(2)),
                  Gaussian([1.0, 2.0], np.eye(2)))
    with pytest.raises(InputError, match="the transition: f is not finite"):
        bad_f.check_finite_at([-1.0, 0.0])


def test_a_simulated_nan_names_the_sensor_the_step_and_the_run():
    from designer.simulate import simulate_runs

    x = ca.SX.sym("x", 1)
    sensors = [Sensor("ok", x, Gaussian.zero_mean([[0.01]])),
               Sensor("bad", ca.if_else(x[0] > 2.5, np.nan, x[0]), Gaussian.zero_mean([[0.01]]))]
    m = Model("m", x, x + 1.0, sensors, Gaussian.zero_mean([[1e-12]]), Gaussian([0.0], [[1e-12]]))
    # x_k = k (to 1e-6): h of sensor 'bad' is NaN from x_3 on, measured at step 3
    with pytest.raises(InputError, match=r"sensor 'bad': h is not finite at step 3 \(x = \[3"):
        simulate(m, 5, np.random.default_rng(0))
    rngs = [np.random.default_rng(s) for s in range(3)]
    with pytest.raises(InputError, match=r"sensor 'bad': h is not finite at step 2 of run 1 \(of 3 simulated"):
        simulate_runs(m, 5, rngs, x0=np.array([[0.0], [1.0], [0.0]]))
    with pytest.raises(InputError, match=r"step 3 of run 2 \(of 3 simulated together\)"):
        simulate(m, 5, rngs, x0=np.array([[-5.0], [-5.0], [0.0]]))
    grows = Model("g", x, ca.if_else(x[0] > 1.5, np.inf, x[0] + 1.0), sensors[:1], Gaussian.zero_mean([[1e-12]]),
                  Gaussian([0.0], [[1e-12]]))
    with pytest.raises(InputError, match=r"the transition f is not finite at step 3: f\(x\) from x = \[2"):
        simulate(grows, 5, np.random.default_rng(0))


@pytest.mark.parametrize("coupled", [False, True])
def test_propagate_is_the_covariance_product_bit_for_bit(coupled):
    """Model.propagate(F, P) = F P Fᵀ: by elements where the dynamics' Jacobian is structurally diagonal (a
    state-dependent decay here), the same bits as numpy's products over a batch, and the products themselves where a
    state reads another (the elementwise form would drop the coupling)."""
    x = ca.SX.sym("x", 4)
    f = x + 0.1 * ca.sin(x) - 0.05 * x**3
    if coupled:
        f[0] += 0.2 * x[3]
    model = Model("decay", x, f, [Sensor("s", x[0], Gaussian.zero_mean([[1.0]]))], Gaussian.zero_mean(np.eye(4)),
                  Gaussian(np.zeros(4), np.eye(4)))
    rng = np.random.default_rng(7)
    xs = rng.normal(size=(3, 5, 4))
    F = model.F(xs)
    A = rng.normal(size=(3, 5, 4, 4))
    P = A @ np.swapaxes(A, -1, -2)
    want = F @ P @ np.swapaxes(F, -1, -2)
    assert np.array_equal(model.propagate(F, P), want)
    assert (np.abs(F[..., 0, 3]) > 0).all() == coupled  # the coupling the elementwise form would drop
