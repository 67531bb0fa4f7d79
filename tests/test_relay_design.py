"""The gain rule ``relay`` (rules/relay): its filter behind the rule registry, its stationary certificate
(rules.relay.design.relay_stationary) and its design from a user's model file, against independent references.

* the rule's filter (``rules.get('relay').batch_filter()``, reached by ``run_consensus_batch``) is the
  relay filter of :func:`rules.relay.filter.run_relay_batch` run by itself on each run's network (runs on networks of
  different channel probabilities included) with the design's hops and FDI signal;
* the stationary certificate's fixed point is where the relay filter's own covariance recursion ends on a linear
  model (a second implementation: the certificate stacks the nodes by ball size, the filter runs every node), with
  sensors of different dimensions so that balls of equal rows hold different numbers of sensors; the LMI's optimum
  is that fixed point;
* a design from a model file written as a user would: the record says what the rule needs, its hops, the packets
  per hop count and the certificate; bad options exit 2 naming the parameter before anything is written.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

import rules
from designer.design import DesignOptions, make_design
from rules.relay.design import relay_stationary
from filters.consensus_batch import run_consensus_batch
from rules.relay.filter import run_relay_batch
from studies.cli import main
from test_relay import (N, SIGNAL, bearing_model, edge_attacks, linear_model, network,  # tests/ on the path
                        simulate_linear, varied_network)


def relay_design(model, net, hops, signal=SIGNAL, mode="relay"):
    return make_design(model, net, rule=rules.get(mode), delta=0.0, options=DesignOptions(mode=mode, rounds=hops),
                       x0=model.prior.mean, signal=signal)


@pytest.mark.parametrize("mode", ["relay", "flood"])
@pytest.mark.parametrize("stack", [True, False])
def test_the_rules_filter_is_the_relay_filter_on_each_runs_network(mode, stack, monkeypatch):
    """Runs on networks of other channel probabilities (a sweep's settings, one without FDI) update together, each
    with its own setting's moments (``stack``), or one setting at a time where the stacked moments would pass
    SETTINGS_STACK_BYTES: either way each run gets the numbers of the relay filter run alone on its network."""
    import rules.relay.filter as relay_filter

    if not stack:
        monkeypatch.setattr(relay_filter, "SETTINGS_STACK_BYTES", 1)
    model = bearing_model()
    nets = [network(0.1, 0.1), varied_network(), network(0.1, 0.1), network(0.3, 0.0)]
    rng = np.random.default_rng(3)
    runs = len(nets)
    z = np.abs(rng.normal(5.0, 1.0, (runs, 6, model.n_z)))  # any measurements: the filters must agree on them
    att = edge_attacks(nets[0], runs, 6, model.n_x, seed=5)
    design = relay_design(model, nets[0], 2, mode=mode)
    res = run_consensus_batch(model, nets, z, design, attacks=att).detail
    # Φ kept as its diagonals alone (a comparison's): the same numbers, the groups' diagonals gathered alike
    from test_consensus_batch import assert_variances_are_the_diagonals
    assert_variances_are_the_diagonals(model, nets, z, design, attacks=att)
    for r in range(runs):
        one = att._replace(dos=att.dos[r:r + 1], fdi=att.fdi[r:r + 1], xi=att.xi[r:r + 1])
        ref = run_relay_batch(model, nets[r], z[r:r + 1], 2, attacks=one, signal=SIGNAL,
                              routing=design.rule.routing).detail
        assert np.array_equal(res.x_post[r], ref.x_post[0]) and np.array_equal(res.phi_post[r], ref.P_post[0])
        assert np.array_equal(res.gate_counts[r, :, 0], ref.delivered_per_step[0])
    assert res.valid.all() and np.all(res.C == 0.0)
    assert np.allclose(res.predicted_mse, np.trace(res.phi_post, axis1=-2, axis2=-1))
    # the settings' moments differ: the run without FDI is not the first setting's numbers on its draws
    twin = run_relay_batch(model, nets[0], z[3:], 2, attacks=att._replace(dos=att.dos[3:], fdi=att.fdi[3:],
                                                                          xi=att.xi[3:]),
                           signal=SIGNAL, routing=design.rule.routing).detail
    assert not np.array_equal(twin.P_post[0], res.phi_post[3])


@pytest.mark.parametrize("hops", [1, 2])
@pytest.mark.slow
def test_stationary_certificate_is_where_the_filters_covariance_settles(hops):
    model = linear_model()  # node 3's sensor is two-dimensional: balls of 4 rows hold 3 or 4 sensors at one hop
    net = varied_network()
    design = relay_design(model, net, hops)
    cert = relay_stationary(model, net, design, x=np.zeros(model.n_x))
    assert cert.converged and cert.reason is None
    steps = 300
    z = np.zeros((1, steps, model.n_z))  # a linear model: the covariance does not depend on the measurements
    res = run_relay_batch(model, net, z, hops, signal=SIGNAL).detail
    assert np.allclose(res.P_post[0, -1], cert.Phi, rtol=1e-7, atol=1e-10)
    assert cert.lmi["status"] == "optimal" and cert.lmi["relative_residual"] < 1e-6
    assert cert.lmi["trace"] == pytest.approx(np.trace(cert.Phi, axis1=-2, axis2=-1).sum(), rel=1e-6)
    # the falsification's moments weigh on it: the same design without FDI settles lower
    clean = relay_stationary(model, network(0.0, 0.0), relay_design(model, network(0.0, 0.0), hops, None),
                             x=np.zeros(model.n_x), lmi=False)
    assert np.trace(clean.Phi, axis1=-2, axis2=-1).sum() < np.trace(cert.Phi, axis1=-2, axis2=-1).sum()


def test_a_fixed_point_out_of_reach_stops_the_stationary_recursion_early():
    """A mode no sensor sees, growing 0.3 % a step: its covariance reached the recursion's limit (1e12) after 4368
    iterations, and the recursion ran all of them to "grows without settling".  Its relative change per iteration
    hardly shrinks (towards the growth's 0.6 %), and the recursion stops within a few judgments of the first (at
    2 x REACH_WINDOW iterations), with the weaker verdict of the same kind (no fixed point) and the reason; the
    observed model's recursion still settles."""
    import casadi as ca

    from designer import Gaussian, Model, Sensor
    from designer.anderson import REACH_WINDOW

    x = ca.SX.sym("x", 2)
    sensors = [Sensor(f"s{i}", x[1], Gaussian.zero_mean([[0.1 + 0.05 * i]])) for i in range(N)]
    model = Model("unseen", x, ca.vertcat(1.003 * x[0], 0.9 * x[1]), sensors, Gaussian.zero_mean(0.02 * np.eye(2)),
                  Gaussian([0.0, 0.0], np.eye(2)))
    net = network(0.1, 0.1)
    cert = relay_stationary(model, net, relay_design(model, net, 1), x=np.zeros(2), lmi=False)
    assert not cert.converged and 2 * REACH_WINDOW <= cert.iterations <= 4 * REACH_WINDOW
    assert "did not settle (node 0: its change per iteration" in cert.reason and "beyond the 5000" in cert.reason
    seen = linear_model()
    assert relay_stationary(seen, net, relay_design(seen, net, 1), x=np.zeros(2), lmi=False).converged


def test_an_lmi_too_large_to_hold_is_not_solved_and_says_why(monkeypatch):
    """The relay LMI writes each node's update as an n² x n² matrix (8.6 GB on a 64-cell field): above
    LMI_MAX_ENTRIES numbers it is not solved, the reason names the sizes, and the fixed point is kept."""
    import rules.relay.design as relay

    model, net = linear_model(), varied_network()
    design = relay_design(model, net, 1)
    whole = relay_stationary(model, net, design, x=np.zeros(model.n_x))
    assert whole.lmi["status"] == "optimal"
    monkeypatch.setattr(relay, "LMI_MAX_ENTRIES", net.n_nodes * model.n_x**4 - 1)
    capped = relay_stationary(model, net, design, x=np.zeros(model.n_x))
    assert capped.converged and np.array_equal(capped.Phi, whole.Phi)
    assert capped.lmi["status"] == "not solved" and capped.lmi["trace"] is None
    assert f"N n⁴ = {net.n_nodes} x {model.n_x}⁴" in capped.lmi["reason"]


USER_MODEL = '''
import casadi as ca
import numpy as np
from designer import AttackSpec, FDISignal, Gaussian, Model, Sensor, SensorNetwork

STEPS = 25
X0 = [1.0, 2.0, 0.3, -0.2]
_POS = [(6.0 * (i % 4), 6.0 * (i // 4)) for i in range(12)]
NETWORK = SensorNetwork.from_edges(12, [(i, i + 1) for i in range(12) if i % 4 != 3]
                                   + [(i, i + 4) for i in range(8)])
ATTACKS = AttackSpec(dos=0.1, fdi=0.05, signal=FDISignal(amplitude=0.5, components=(0, 1)))


def model():
    x = ca.SX.sym("x", 4)
    f = ca.vertcat(x[0] + x[2], x[1] + x[3], 0.98 * x[2], 0.98 * x[3])
    sensors = []
    for i, (a, b) in enumerate(_POS):
        rng_ = ca.sqrt((x[0] - a) ** 2 + (x[1] - b) ** 2 + 1.0)
        brg = ca.atan2(x[1] - b, x[0] - a)
        if i % 2:
            sensors.append(Sensor(f"b{i}", brg, Gaussian.zero_mean([[0.003]]), angles=(0,)))
        else:
            sensors.append(Sensor(f"rb{i}", ca.vertcat(rng_, brg), Gaussian.zero_mean(np.diag([0.2, 0.003])),
                                  angles=(1,)))
    return Model("user grid", x, f, sensors, Gaussian.zero_mean(np.diag([0.01, 0.01, 0.01, 0.01])),
                 Gaussian(X0, np.diag([1.0, 1.0, 0.1, 0.1])), position_index=(0, 1))
'''


@pytest.mark.slow
def test_relay_design_of_a_users_model_file(tmp_path, capsys):
    path = tmp_path / "grid12.py"
    path.write_text(USER_MODEL)
    out = tmp_path / "d"
    code = main(["design", str(path), "--mode", "relay", "--rounds", "2", "--seed", "3", "--out", str(out)])
    assert code in (0, 1), capsys.readouterr().err  # 1: written, not certified (the verdict says why)
    rec = json.loads((out / "schedule.json").read_text())
    assert rec["gain_rule"]["name"] == "relay" and rec["gain_rule"]["runtime"] == "local"
    assert rec["exchange"] == "relay" and rec["rounds"] == 2 and rec["feasible"]
    assert (code == 0) == rec["certified"]
    cert = rec["stationary_certificate"]
    assert cert["converged"] and cert["verdict"] == "certified" and cert["lmi"]["status"] == "optimal"
    edges = 9 + 8  # a 4 x 3 grid
    rows = {r["rounds"]: r for r in rec["rounds_tradeoff"]["rows"]}
    assert set(rows) == {1, 2, 4} and rows[2]["designed"]  # the grid's diameter is 5: L = 8 adds nothing
    assert all(r["messages_per_step"] == 2 * edges * L for L, r in rows.items())
    # the tradeoff's L = 2 row is the certificate's own fixed point
    assert rows[2]["expected_rmse"] == pytest.approx(np.sqrt(np.mean(cert["trace"])), rel=1e-9)
    trace = np.asarray(rec["trace_bound"], dtype=float)
    assert trace.shape == (12, 25) and np.all(np.isfinite(trace)) and np.all(trace > 0)
    # its gains are computed online: replaying the design's run as a schedule is refused, saying what to run
    capsys.readouterr()
    code = main(["study", "consensus-robot", str(path), "--schedule", str(out), "--runs", "2", "--out",
                 str(tmp_path / "replay")])
    err = capsys.readouterr().err
    assert code == 2 and "is a relay design" in err and "--mode relay" in err, err


@pytest.mark.parametrize("mode", ["relay", "flood"])
@pytest.mark.parametrize("extra, needle", [
    (["--exchange", "predictions"], "exchange"),
    (["--rounds", "0"], "rounds must be an integer in [1, 64]"),
    (["--gate", "0.01"], "does not take a gate"),
])
def test_bad_relay_options_exit_2_before_anything_is_written(tmp_path, capsys, extra, needle, mode):
    path = tmp_path / "grid12.py"
    path.write_text(USER_MODEL)
    out = tmp_path / "d"
    capsys.readouterr()
    code = main(["design", str(path), "--mode", mode, *extra, "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and needle in err and err.startswith("cfdesign: error: "), err
    assert not out.exists()


def test_without_fdi_on_the_network_no_signal_is_needed():
    model = linear_model()
    net = network(0.2, 0.0)
    design = relay_design(model, net, 2, signal=None)
    _, z = simulate_linear(model, 2, 5, seed=2)
    res = run_consensus_batch(model, net, z, design).detail
    assert res.valid.all() and np.isfinite(res.x_post).all() and res.x_post.shape == (2, 6, N, 2)


@pytest.mark.parametrize("mode", ["relay", "flood"])
@pytest.mark.slow
def test_feasibility_map_of_a_relay_mode_is_the_designs_stationary_certificate(tmp_path, mode):
    """Map and design agree on the same options: each grid point's verdict and trace are those `design` records
    (the map computes no design run: the stationary certificate at the point's channel probabilities)."""
    from studies import api

    path = tmp_path / "grid12.py"
    path.write_text(USER_MODEL)
    fmap = api.feasibility(str(path), ["dos=0.1:0.4:2", "fdi=0:0.1:2"], mode=mode, rounds=2, out=tmp_path / "map")
    assert len(fmap.rows) == 4
    traces = {}
    for row in fmap.rows:
        dos, fdi = row["dos"], row["fdi"]
        d = api.design(str(path), mode=mode, rounds=2, dos=dos, fdi=fdi, steps=3, out=tmp_path / f"d{dos}_{fdi}")
        rec = d.schedule.meta["stationary_certificate"]
        assert row["verdict"] == rec["verdict"] == "certified"
        np.testing.assert_allclose(row["trace_bound"], np.mean(rec["trace"]), rtol=1e-12)
        traces[dos, fdi] = row["trace_bound"]
    # more losses or more falsification: a larger expected covariance
    assert traces[0.1, 0.0] < traces[0.4, 0.0] < traces[0.4, 0.1] and traces[0.1, 0.0] < traces[0.1, 0.1]


def test_every_batched_filter_refuses_a_model_with_inputs_run_without_them():
    """batch_inputs, which every batched filter calls, names ``inputs`` before the model is evaluated (KCF, HCMCI and
    the consensus filters used to fail deep in f with a CasADi shape error)."""
    import casadi as ca

    from designer.model import Model, Sensor
    from designer.noise import Gaussian
    from designer.validation import InputError
    from filters.distributed import run_hcmci_batch, run_kcf_batch

    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    driven = Model("driven", x, ca.vertcat(x[0] + u[0], x[1]),
                   [Sensor(f"s{i}", x[i % 2], Gaussian.zero_mean([[1.0]])) for i in range(N)],
                   Gaussian.zero_mean(np.eye(2)), Gaussian([0.0, 0.0], np.eye(2)), u=u)
    net = network()
    z = np.zeros((2, 5, N))
    paper = make_design(driven, net, rule=rules.get("paper"), delta=0.0, options=DesignOptions(mode="paper"), x0=driven.prior.mean,
                        u0=np.zeros(1))
    relay = make_design(driven, net, rule=rules.get("relay"), delta=0.0, options=DesignOptions(mode="relay", rounds=2), x0=driven.prior.mean,
                        u0=np.zeros(1))
    runs = [lambda **kw: run_kcf_batch(driven, net, z, **kw), lambda **kw: run_hcmci_batch(driven, net, z, **kw),
            lambda **kw: run_consensus_batch(driven, net, z, paper, **kw),
            lambda **kw: run_consensus_batch(driven, net, z, relay, **kw)]
    for run in runs:
        with pytest.raises(InputError, match=r"inputs must have shape \(5, 1\)"):
            run()
        with pytest.raises(InputError, match=r"inputs must have shape \(5, 1\)"):
            run(inputs=np.zeros((5, 2)))
        run(inputs=np.zeros((5, 1)))  # given: runs


def test_the_pseudo_inverse_is_the_inverse_only_where_the_inverse_is_certified():
    """rules.relay.design.pseudo_inverse against numpy's pinv (eigenvalues below rtol of the largest cut): a stack
    of well-conditioned positive definite matrices (their inverse, certified); a rank-2 4 x 4 one B Bᵀ whose Cholesky
    factor exists only by rounding (eigenvalues of 1e-15 and -1e-15: an LU inverse's trace is -5e16 there, and
    counting that as certified made the relay filter diverge); one whose condition number passes 1 / rtol (two
    eigenvalues cut).  Each equals pinv to rounding, alone and in a stack with a certified one (each item decided
    alone)."""
    from rules.relay.design import RTOL, pseudo_inverse

    rng = np.random.default_rng(5)
    A = rng.standard_normal((3, 4, 4))
    good = A @ np.swapaxes(A, -1, -2) + 0.5 * np.eye(4)
    B = np.random.default_rng(25).standard_normal((4, 2))
    low = B @ B.T
    np.linalg.cholesky(low)  # exists, by rounding
    assert np.trace(np.linalg.inv(low)) < 0
    Q, _ = np.linalg.qr(rng.standard_normal((4, 4)))
    wide = (Q * np.array([1.0, 0.5, 1e-14, 1e-15])) @ Q.T  # condition 1e15 > 1 / RTOL: two cut

    def agrees(M):
        got, ref = pseudo_inverse(M), np.linalg.pinv(M, rcond=RTOL, hermitian=True)
        assert np.allclose(got, ref, rtol=0, atol=1e-9 * np.abs(ref).max()), (got, ref)
        return got

    assert np.allclose(agrees(good), np.linalg.inv(good), rtol=0, atol=1e-12 * np.abs(np.linalg.inv(good)).max())
    assert np.linalg.matrix_rank(agrees(low)) == 2 and np.linalg.matrix_rank(agrees(wide)) == 2
    for bad in (low, wide):
        assert np.array_equal(agrees(np.stack([good[0], bad]))[1], pseudo_inverse(bad))
