"""The mse design's numerics: its gains keep their digits where the nodes' errors nearly agree, and a design reports
where it is ill-conditioned.

The reference is the same recursion carried in long double (the joint covariance, its predictions, updates and the
moments the gains are solved from; the gains themselves then solved in double from those moments): the gains a
design computes in double must agree with it.  Carried as absolute blocks ``P_ij``, the gains of a 28-node
coordinated-turn design at its third step agreed with it to no digit (a relative error of 2.3, what made one and two
BLAS threads give different designs); in difference form they keep all but a few.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

import rules.mse.filter as fc  # the mse design's filter (a batch of one run)
from designer import AttackSpec, DesignOptions, FDISignal, Gaussian, Model, SensorNetwork, Sensor
from designer.joint import JointCovariance, conditioning, joint_predict, joint_update, mse_gains
from studies.consensus_design import run_design
from studies.reports.design import render_design
from studies.scenarios import scenario_of


def coordinated_turn_ring(nodes=28, steps=3):
    """A coordinated-turn target (px, vx, py, vy, omega) watched by range sensors on a ring with chords (d_max 4)."""
    x = ca.SX.sym("x", 5)
    px, vx, py, vy, w = (x[i] for i in range(5))
    f = ca.vertcat(px + vx, ca.cos(w) * vx - ca.sin(w) * vy, py + vy, ca.sin(w) * vx + ca.cos(w) * vy, w)
    sites = [(60.0 * np.cos(a), 60.0 * np.sin(a)) for a in 2 * np.pi * np.arange(nodes) / nodes]
    sensors = [Sensor(f"r{i}", ca.sqrt((px - sx) ** 2 + (py - sy) ** 2), Gaussian.zero_mean([[1.0]]))
               for i, (sx, sy) in enumerate(sites)]
    m = Model("ct-ring", x, f, sensors, Gaussian.zero_mean(np.diag([0.01, 0.0025, 0.01, 0.0025, 1e-4])),
              Gaussian([5.0, 1.0, -3.0, 0.5, 0.05], np.diag([4.0, 0.25, 4.0, 0.25, 0.01])))
    half = nodes // 2
    edges = ([(i, (i + 1) % nodes) for i in range(nodes)] + [(i, (i + 7) % nodes) for i in range(0, nodes, 2)]
             + [(i, i + half) for i in range(half)])
    att = AttackSpec(dos=0.1, fdi=0.05, signal=FDISignal(amplitude=1.0, components=(0, 2)))
    return scenario_of(m, network=SensorNetwork.from_edges(nodes, edges), attacks=att, steps=steps,
                       x0=[5.0, 1.0, -3.0, 0.5, 0.05])


def _long(x):
    if isinstance(x, JointCovariance):
        return JointCovariance(np.asarray(x.P, np.longdouble), np.asarray(x.G, np.longdouble))
    if isinstance(x, (list, tuple)):
        return [np.asarray(v, np.longdouble) for v in x]
    return np.asarray(x, np.longdouble)


def test_mse_gains_along_a_design_agree_with_the_recursion_in_long_double(monkeypatch):
    """Every step's gains of a 28-node mse design (consensus gains in the hundreds, innovations' covariances with
    directions ~1e-7 of their scale) against the same recursion in long double, given the same Jacobians and
    packets: relative error below 1e-6 (the double-precision recursion lost 2.3 of 1 before)."""
    calls = []
    for name in ("joint_predict", "joint_update", "mse_gains"):
        real = getattr(fc, name)

        def record(*args, _real=real, _name=name, **kw):
            out = _real(*args, **kw)
            calls.append((_name, args, out))
            return out

        monkeypatch.setattr(fc, name, record)
    sc = coordinated_turn_ring()
    d = run_design(sc, DesignOptions(mode="mse"), seed=1)
    monkeypatch.undo()
    N = sc.network.n_nodes
    gains = [c for c in calls if c[0] == "mse_gains"]
    assert len(gains) == N * sc.steps
    worst, largest, P = 0.0, 0.0, None
    for k in range(sc.steps):
        step = gains[k * N:(k + 1) * N]
        Pm = step[0][1][0]
        pred = next(c for c in calls if c[0] == "joint_predict" and c[2] is Pm)
        upd = next(c for c in calls if c[0] == "joint_update" and c[1][0] is Pm)
        P = _long(pred[1][0]) if P is None else P
        Pl = joint_predict(P, _long(pred[1][1]), _long(pred[1][2]))
        for (_, (_, i, received, H, R, S), out) in step:
            K, C = mse_gains(Pl, i, received, _long(H), _long(R), _long(S))
            largest = max(largest, float(np.abs(out[1]).max()))
            worst = max(worst, float(np.abs(out[1] - C).max() / max(np.abs(C).max(), 1e-300)),
                        float(np.abs(out[0] - K).max() / max(np.abs(K).max(), 1e-300)))
        P = joint_update(Pl, _long(upd[1][1]), _long(upd[1][2]), _long(upd[1][3]), _long(upd[1][4]), upd[1][5],
                         _long(upd[1][6]))
    assert largest > 100.0  # the gains this test is about: large, from nearly singular innovations' covariances
    assert worst < 1e-6, worst
    cond = d.schedule.meta["conditioning"]
    assert max(cond["gain_condition"]) > 1e4  # and the design says how ill-conditioned its solves were


def test_conditioning_record_and_the_report_sentence():
    kappa = np.array([[np.nan, 10.0, 20.0], [3e6, 40.0, np.nan], [5.0, 2e7, 1.0]])
    c = conditioning(kappa)
    assert c["gain_condition"] == [3e6, 2e7, 20.0] and c["gain_condition_step"] == [1, 2, 0]
    assert c["ill_conditioned"] == [0, 1] and c["threshold"] == 1e6
    assert conditioning(None)["gain_condition"] is None and conditioning(None)["ill_conditioned"] == []
    meta = {"scenario": "s", "mode": "mse", "nodes": 3, "steps": 3, "feasible": True, "violations": [],
            "conditioning": c}
    text = render_design(meta)
    assert "**Ill-conditioned at node(s) 0, 1.**" in text and "2.0e+07 (node 1, step 2" in text
    assert "about 8 of the 16 significant digits" in text
    well = render_design({**meta, "conditioning": conditioning(np.array([[3.0, 40.0, 2.0]]))})
    assert "Ill-conditioned" not in well
    assert "well-conditioned systems: condition number at most 40 (node 1, step 0)" in well
    assert "conditioned" not in render_design({**meta, "mode": "tuned", "conditioning": conditioning(None)})


def test_solved_gains_are_the_minimum_norm_solution_of_every_item():
    """``solve_gains`` (padding left out, items of one size together, an LU solve where every direction is kept)
    against the definition solved item by item with the eigendecomposition: ``Z = E[e yᵀ] S⁺`` in the units of
    ``scale``, the directions below ``GAIN_RCOND`` of the largest dropped, and ``λmax / λmin`` over the kept ones.
    The stack mixes items with zero-padded components (in varied places), rank-deficient ones (a direction to
    drop), items without packets (the measurement block alone) and a non-finite one."""
    from designer.joint import GAIN_RCOND, solve_gains

    rng = np.random.default_rng(3)
    k, n, m, w = 9, 3, 2, 11
    yy, ey = np.zeros((k, w, w)), np.zeros((k, n, w))
    for i in range(k):
        used = np.sort(rng.choice(np.arange(m, w), size=int(rng.integers(2, w - m)), replace=False))
        used = np.concatenate([np.arange(m), used])
        rank = used.size - (i % 3 == 0)  # every third item rank-deficient
        A = rng.standard_normal((used.size, rank)) * rng.uniform(0.5, 3, size=(used.size, 1))
        yy[i][np.ix_(used, used)] = A @ A.T
        ey[i][:, used] = rng.standard_normal((n, rank)) @ A.T  # in the range of yy, as E[e yᵀ] is
    scale = np.sqrt(np.diagonal(yy, axis1=-2, axis2=-1)) * rng.uniform(0.5, 2, size=(k, w))
    has = np.arange(k) % 4 != 1
    yy[5, 0, 0] = np.inf
    Z, kappa = solve_gains(ey, yy, scale, has, m)
    for i in range(k):
        if i == 5:
            assert np.isnan(Z[i]).all() and np.isnan(kappa[i])
            continue
        wi = w if has[i] else m
        d = np.where(scale[i, :wi] > 0, scale[i, :wi], 1.0)
        lam, V = np.linalg.eigh(yy[i, :wi, :wi] / np.outer(d, d))
        keep = lam > GAIN_RCOND * lam[-1]
        ref = (ey[i, :, :wi] / d) @ V[:, keep] @ np.diag(1 / lam[keep]) @ V[:, keep].T / d
        assert np.allclose(Z[i, :, :wi], ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max()), i
        assert np.all(Z[i, :, wi:] == 0.0)
        assert np.isclose(kappa[i], lam[-1] / lam[keep].min(), rtol=1e-8), i
