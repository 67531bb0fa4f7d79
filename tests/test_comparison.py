"""Comparison study: uplink attacks, the plain EKF, and the study itself (backends, resume, cross-checks)."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from scipy.stats import multivariate_normal

from designer.cores import usable_cores
from designer.model import Model, Sensor
from designer.noise import Gaussian
from designer.simulate import simulate
from designer.validation import InputError
from designer.attacks import FDISignal
from filters.attacks import attack_pattern, channel_draws, receive, simulate_attacks, uplink_attacks
from filters.ekf import run_ekf, run_ekf_batch
from filters.particle import additive_noise_loglik
from filters.uplink import fdi_covariances, split_received, uplink_loglik
from studies.cli import main
from studies.comparison import (EKF_PLAIN, FILTERS, HCMCI, KCF, LOCAL, PAPER_DESIGN, PF_AWARE, PF_PLAIN, SWEEP_VALUES,
                                TUNED)
from studies.pipeline import run_study
from studies.runner import CHUNKS_DIR, Backend, make_backend
from studies.scenarios import load_scenario
from test_runner import _interruptible  # noqa: E402  (tests/ is on the path: the SIGINT child's default action)

ROOT = Path(__file__).resolve().parents[1]


def run_comparison(*, scenarios=("indoor-robot", "target-range-bearing"), sweep_values=SWEEP_VALUES,
                   tuned_in_sweeps=False, **kw) -> dict:
    return run_study("comparison", list(scenarios), sweep_values=sweep_values, tuned_in_sweeps=tuned_in_sweeps,
                     **kw).results


def run_consensus_robot(*, mode="paper", **kw) -> dict:
    from designer.design import DesignOptions

    return run_study("consensus-robot", options=DesignOptions(mode=mode), **kw).results


@pytest.fixture(scope="module")
def robot():
    return load_scenario("indoor-robot")


# --- uplinks ---------------------------------------------------------------------------------------------------

def test_channel_draws_reproduce_simulate_attacks(robot):
    net, m = robot.network, robot.model
    a = simulate_attacks(net, 30, m.n_x, np.random.default_rng(4), signal=FDISignal(1.5, (0, 1)))
    u, s = channel_draws(30, net.n_nodes, np.random.default_rng(4))
    b = attack_pattern(net, u, s, m.n_x, signal=FDISignal(1.5, (0, 1)))
    for x, y in zip(a, b):
        assert np.array_equal(x, y)


def test_uplink_attack_frequencies_and_exclusivity():
    u, s = channel_draws(4000, 5, np.random.default_rng(1))
    att = uplink_attacks(u, s, 3, dos_prob=0.2, fdi_prob=0.3, signal=FDISignal(2.0, (0, 1)))
    n = att.dos.size
    for got, p in ((att.dos.mean(), 0.2), (att.fdi.mean(), 0.3)):
        assert abs(got - p) < 4 * np.sqrt(p * (1 - p) / n)
    assert not (att.dos & att.fdi).any()
    assert np.all(att.xi[~att.fdi] == 0) and np.all(att.xi[..., 2] == 0)
    v = att.xi[att.fdi][:, 0]
    assert np.abs(v).max() <= 2.0
    assert abs((v**2).mean() - 4.0 * FDISignal(1.0).second_moment) < 4 * (v**2).std() / np.sqrt(v.size)  # a^2 E[sin^2 s]
    with pytest.raises(InputError, match="dos_prob \\+ fdi_prob"):
        uplink_attacks(u, s, 3, dos_prob=0.7, fdi_prob=0.4, signal=FDISignal(1.0, (0,)))


def test_received_measurements_shift_by_the_jacobian_and_drop_lost_packets(robot):
    m = robot.model
    traj = robot.simulate(np.random.default_rng(2), 30)
    u, s = channel_draws(30, 8, np.random.default_rng(3))
    att = uplink_attacks(u, s, 3, dos_prob=0.2, fdi_prob=0.3, signal=FDISignal(1.5, (0, 1)))
    values, avail = split_received(m, receive(m, traj.x, traj.z, att))
    assert np.array_equal(avail, ~att.dos)
    for k in range(30):
        for i in range(8):
            sl = slice(2 * i, 2 * i + 2)
            if att.dos[k, i]:
                assert np.all(values[k, sl] == 0)
            else:  # the camera is affine in the position: the falsification is H_c xi exactly
                shift = m.H(i, traj.x[k + 1], k + 1)[:, :2] @ att.xi[k, i, :2]
                np.testing.assert_allclose(values[k, sl], traj.z[k, sl] + shift, atol=1e-9)
    assert att.fdi.any() and att.dos.any()


def test_uplink_likelihood_against_scipy(robot):
    m = robot.model
    covs = fdi_covariances(m, m.prior.mean, signal=FDISignal(1.5, (0, 1)))
    x = m.prior.sample(np.random.default_rng(0), (2, 7))
    traj = robot.simulate(np.random.default_rng(1), 3)
    avail = np.ones((2, 8), bool)
    avail[0, [1, 5]] = False
    y = np.concatenate([np.broadcast_to(traj.z[0], (2, 16)), avail.astype(float)], axis=1)
    got = uplink_loglik(m, fdi_prob=0.25, fdi_covs=covs)(x, 1, y)
    h = m.h_all(x, 1)
    R = m.measurement_cov(0)
    want = np.zeros((2, 7))
    for r in range(2):
        for p in range(7):
            for i in range(8):
                if avail[r, i]:
                    d = traj.z[0, 2 * i:2 * i + 2] - h[r, p, 2 * i:2 * i + 2]
                    want[r, p] += np.log(0.75 * multivariate_normal(np.zeros(2), R).pdf(d)
                                         + 0.25 * multivariate_normal(np.zeros(2), R + covs[i]).pdf(d))
    np.testing.assert_allclose(got, want, rtol=1e-10)
    plain = uplink_loglik(m)(x, 1, np.concatenate([np.broadcast_to(traj.z[0], (2, 16)), np.ones((2, 8))], 1))
    np.testing.assert_allclose(plain, additive_noise_loglik(m)(x, 1, np.broadcast_to(traj.z[0], (2, 16))),
                               rtol=1e-12)


# --- the plain EKF ----------------------------------------------------------------------------------------------

def _linear_two_sensors():
    x = ca.SX.sym("x", 2)
    A = np.array([[0.9, 0.2], [-0.1, 0.95]])
    H1, H2 = np.array([[1.0, 0.5]]), np.array([[0.0, 1.0], [1.0, -1.0]])
    model = Model("lin2", x, ca.mtimes(ca.DM(A), x),
                  [Sensor("a", ca.mtimes(ca.DM(H1), x), Gaussian.zero_mean([[0.3]])),
                   Sensor("b", ca.mtimes(ca.DM(H2), x), Gaussian.zero_mean(np.diag([0.2, 0.4])))],
                  Gaussian.zero_mean(0.05 * np.eye(2)), Gaussian([1.0, -1.0], 0.5 * np.eye(2)))
    return model, A, (H1, H2)


def test_ekf_is_the_kalman_filter_with_missing_sensors():
    model, A, Hs = _linear_two_sensors()
    traj = simulate(model, 20, np.random.default_rng(3))
    avail = np.random.default_rng(4).random((20, 2)) < 0.6
    res = run_ekf(model, traj.z, available=avail)
    m, P = model.prior.mean, model.prior.cov
    Rs = [model.measurement_cov(0), model.measurement_cov(1)]
    zs = [traj.z[:, :1], traj.z[:, 1:]]
    for k in range(20):  # textbook KF, information form of the update: an independent formula
        m, P = A @ m, A @ P @ A.T + model.process_cov
        info, vec = np.linalg.inv(P), np.linalg.inv(P) @ m
        for i in (0, 1):
            if avail[k, i]:
                info = info + Hs[i].T @ np.linalg.inv(Rs[i]) @ Hs[i]
                vec = vec + Hs[i].T @ np.linalg.inv(Rs[i]) @ zs[i][k]
        P = np.linalg.inv(info)
        m = P @ vec
        np.testing.assert_allclose(res.x[k + 1], m, atol=1e-10)
        np.testing.assert_allclose(res.P[k + 1], P, atol=1e-10)
    with pytest.raises(InputError, match="available"):
        run_ekf(model, traj.z, available=avail[:, :1])


def _uplink_runs(sc, runs: int, dos: float, fdi: float, seed: int = 21):
    """Received uplink measurements of ``runs`` runs of ``sc`` as the comparison draws them."""
    sc = sc.with_attacks(dos=dos, fdi=fdi)
    m, att = sc.model, sc.resolved_attacks
    values, avail, inputs = [], [], []
    for seq in np.random.SeedSequence(seed).spawn(runs):
        ts, cs = seq.spawn(2)
        tr = sc.simulate(np.random.default_rng(ts), sc.steps)
        u, s = channel_draws(sc.steps, m.n_sensors, np.random.default_rng(cs))
        y = receive(m, tr.x, tr.z, uplink_attacks(u, s, m.n_x, dos_prob=att.uplink_dos, fdi_prob=att.uplink_fdi,
                                                  signal=att.signal))
        v, a = split_received(m, y)
        values.append(v)
        avail.append(a)
        inputs.append(tr.inputs)
    return np.stack(values), np.stack(avail), None if inputs[0] is None else np.stack(inputs)


@pytest.mark.parametrize("name", ["indoor-robot", "target-range-bearing"])
def test_the_batched_ekf_is_the_ekf_run_by_run(name):
    """run_ekf_batch = run_ekf run by run to rounding: lost packets (a step without any too), inputs per run or
    shared, x0 / P0 per run, wrapped bearings on the target."""
    sc = load_scenario(name, {"steps": 25})
    m = sc.model
    z, avail, u = _uplink_runs(sc, 5, dos=0.4, fdi=0.3)
    avail[1, 3] = False  # a step where nothing arrives
    assert 0.3 < avail.mean() < 0.9
    x0 = m.prior.mean + 0.1 * np.arange(5)[:, None]
    P0 = m.prior.cov * (1.0 + np.arange(5))[:, None, None]
    for kw, per_run in (({"inputs": u}, lambda r: {"inputs": None if u is None else u[r]}),
                        ({"inputs": None if u is None else u[0], "x0": x0, "P0": P0},
                         lambda r: {"inputs": None if u is None else u[0], "x0": x0[r], "P0": P0[r]})):
        got = run_ekf_batch(m, z, available=avail, **kw).detail
        for r in range(5):
            ref = run_ekf(m, z[r], available=avail[r], **per_run(r))
            np.testing.assert_allclose(got.x[r], ref.x, rtol=1e-9, atol=1e-12 * np.abs(ref.x).max())
            np.testing.assert_allclose(got.P[r], ref.P, rtol=1e-9, atol=1e-12 * np.abs(ref.P).max())


def test_the_batched_ekf_hands_a_breaking_run_to_run_ekf():
    """A run whose covariance overflows: run_ekf fails on it (a non-finite innovation covariance), and so does the
    batch, on that run; without it the other runs come out as run_ekf's."""
    model, A, Hs = _linear_two_sensors()
    traj = simulate(model, 6, np.random.default_rng(3))
    z = np.stack([traj.z] * 3)
    P0 = np.stack([model.prior.cov, 1e305 * np.eye(2), 2.0 * model.prior.cov])
    with pytest.raises(ValueError) as alone:
        run_ekf(model, z[1], P0=P0[1])
    with pytest.raises(type(alone.value), match=str(alone.value)):
        run_ekf_batch(model, z, P0=P0)
    got = run_ekf_batch(model, z[[0, 2]], P0=P0[[0, 2]]).detail
    for j, r in enumerate((0, 2)):
        np.testing.assert_allclose(got.x[j], run_ekf(model, z[r], P0=P0[r]).x, rtol=1e-9, atol=1e-14)
    with pytest.raises(InputError, match="available must have shape"):
        run_ekf_batch(model, z, available=np.ones((3, 6, 1), bool))
    with pytest.raises(InputError, match="z must have shape"):
        run_ekf_batch(model, z[0])


def test_ekf_matches_the_consensus_filter_reduced_to_one_node(robot):
    """Second implementation: consensus-robot's centralized baseline (sigma = beta = 0, no neighbours)."""
    from studies.consensus_robot import _variants
    from studies.consensus_design import consensus_design

    from studies.filter_registry import Batch

    v = _variants(robot, consensus_design(robot), None)["centralized EKF (all cameras)"]
    traj = robot.simulate(np.random.default_rng(7), robot.steps)
    ref = v.entry.run(Batch((robot,), traj.z[None], None if traj.inputs is None else traj.inputs[None], ((None,),),
                            per_row_networks=False), [0], v.design)
    ours = run_ekf(robot.model, traj.z, inputs=traj.inputs)
    assert ref.x.shape == (1, robot.steps + 1, 1, robot.model.n_x) and ref.runtime == "centralized"
    np.testing.assert_allclose(ours.x, ref.x[0, :, 0], atol=1e-9)


# --- the study --------------------------------------------------------------------------------------------------

SMALL = dict(runs=3, particles=60, seed=2, quiet=True, sweep_values=(0.3,), chunk_size=1,
             scenarios=("indoor-robot",))
ROBOT = ""  # one scenario: filters keyed by their own names


def _numbers(res: dict) -> dict:
    """results.json without what legitimately varies between calls (timings, how the runs were computed)."""
    res = json.loads(json.dumps(res))
    for key in ("wall_time_s", "runner", "versions"):
        res.pop(key)
    for block in [res] + list(res["by_scenario"].values()):
        for f in block["filters"].values():
            f.pop("time_per_step_s")
    for block in res["by_scenario"].values():
        block.pop("runner")
        block["recommendation"].pop("cheapest")
    for rec in res["recommendation"].values():
        rec.pop("cheapest")
    return res


@pytest.mark.slow
def test_consensus_rows_equal_the_consensus_robot_study(tmp_path):
    """Same seeds, same attack draws: the comparison's consensus EKFs reproduce consensus-robot's numbers."""
    cr = run_consensus_robot(out=None, runs=3, seed=2, mode="tuned", quiet=True)
    res = run_comparison(out=None, **SMALL)
    fl = res["filters"]
    assert fl[ROBOT + TUNED]["rmse_position"] == pytest.approx(
        cr["filters"]["consensus-EKF (tuned)"]["rmse_position"], rel=1e-12)
    assert fl[ROBOT + PAPER_DESIGN]["rmse_position"] == pytest.approx(
        cr["filters"]["consensus-EKF (paper, tau=0.01)"]["rmse_position"], rel=1e-12)
    assert fl[ROBOT + LOCAL]["rmse_position"] == pytest.approx(
        cr["filters"]["local EKF per camera"]["rmse_position"], rel=1e-12)
    for name in (KCF, HCMCI):  # the literature's filters face the same channel realisations in both studies
        assert fl[ROBOT + name]["rmse_position"] == pytest.approx(cr["filters"][name]["rmse_position"], rel=1e-12)
        assert fl[ROBOT + name]["family"] == "consensus" and fl[ROBOT + name]["messages_per_step"] == 20
        assert "feasible_runs" not in fl[ROBOT + name]  # no design, no design conditions
        assert 0 < fl[ROBOT + name]["delivered_per_step"] < 20  # DoS 0.1 on every channel
        assert {v for v in sw_values(res, ROBOT + name)} == {"0.1", "0.3"}
    assert set(fl) == {ROBOT + n for n in FILTERS}
    assert fl[ROBOT + PF_AWARE]["messages_per_step"] == 8 and fl[ROBOT + TUNED]["communications"] == 20
    assert fl[ROBOT + LOCAL]["messages_per_step"] == 0
    # no network, nothing attacked: the local EKFs' numbers are the same at every sweep setting
    assert {row[ROBOT + LOCAL]["rmse_position"] for sw_ in res["sweeps"].values() for row in sw_.values()} == {
        fl[ROBOT + LOCAL]["rmse_position"]}
    sw = res["sweeps"]
    assert set(sw["dos_prob"]) == {"0.1", "0.3"} and set(sw["fdi_prob"]) == {"0.1", "0.3"}
    assert ROBOT + TUNED not in sw["fdi_prob"]["0.3"] and ROBOT + TUNED in sw["fdi_prob"]["0.1"]
    # the main setting is one of the sweeps' points: the same numbers from the same runs
    assert sw["fdi_prob"]["0.1"][ROBOT + PF_PLAIN]["rmse_position"] == fl[ROBOT + PF_PLAIN]["rmse_position"]


def sw_values(res: dict, name: str) -> set:
    """The sweep values at which filter ``name`` ran (either sweep)."""
    return {v for sw_ in res["sweeps"].values() for v, row in sw_.items() if name in row}


def test_hcmci_iterations_is_a_study_option():
    with pytest.raises(InputError, match="hcmci_iterations must be an integer >= 1, got 0"):
        run_comparison(out=None, hcmci_iterations=0, **SMALL)
    res = run_consensus_robot(out=None, runs=2, seed=3, quiet=True, hcmci_iterations=3, overrides={"steps": 5})
    hc, kcf = res["filters"]["HCMCI"], res["filters"]["KCF"]
    assert hc["communications"] == 3 * kcf["communications"] == 60 and hc["consensus_iterations"] == 3


def test_without_attacks_the_centralized_filters_agree(tmp_path):
    """No attack: the plain EKF equals consensus-robot's centralized EKF; the two PFs are the same filter."""
    res = run_comparison(out=None, runs=3, particles=60, seed=1, quiet=True, sweep_values=(),
                         overrides={"dos_prob": 0.0, "fdi_prob": 0.0}, scenarios=("indoor-robot",))
    cr = run_consensus_robot(out=None, runs=3, seed=1, quiet=True, overrides={"dos_prob": 0.0, "fdi_prob": 0.0})
    assert res["filters"][ROBOT + EKF_PLAIN]["rmse_position"] == pytest.approx(
        cr["filters"]["centralized EKF (all cameras)"]["rmse_position"], rel=1e-9)
    # q = 0 makes the attack-aware likelihood the plain one; the two PFs differ only in their random streams
    a, b = res["filters"][ROBOT + PF_AWARE], res["filters"][ROBOT + PF_PLAIN]
    assert a["rmse_position"] != b["rmse_position"]
    assert abs(a["rmse_position"] - b["rmse_position"]) < 0.25 * b["rmse_position"]


@pytest.mark.slow
def test_same_numbers_with_every_backend(tmp_path):
    distributed = pytest.importorskip("distributed")
    kw = {**SMALL, "runs": 2, "particles": 40, "scenarios": ("indoor-robot", "target-range-bearing")}
    a = run_comparison(out=tmp_path / "a", backend=Backend(), **kw)
    b = run_comparison(out=tmp_path / "b", backend=Backend("processes", workers=2), **kw)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl:
        c = run_comparison(out=tmp_path / "c", backend=make_backend(dask=cl.scheduler_address), **kw)
    d = run_comparison(out=None, **kw)  # no backend given: the study's default, a worker per usable core
    assert _numbers(a) == _numbers(b) == _numbers(c) == _numbers(d)
    assert d["runner"]["indoor-robot"]["backend"] == ("processes" if usable_cores() > 1 else "batched")
    assert a["runner"]["indoor-robot"]["backend"] == "batched"
    assert len(a["filters"]) == 2 * len(FILTERS) and "indoor-robot: " + LOCAL in a["filters"]
    rc, rb = c["runner"]["target-range-bearing"], b["runner"]["indoor-robot"]
    assert rc["backend"] == "dask" and rb["workers"] == 2 and rb["chunks_computed"] == 2
    on_disk = json.loads((tmp_path / "b" / "results.json").read_text())
    assert _numbers(on_disk) == _numbers(a)


@pytest.mark.slow
def test_the_attack_aware_pf_beats_the_trusting_filters_under_heavy_fdi():
    res = run_comparison(out=None, runs=6, particles=200, seed=3, quiet=True, sweep_values=(0.4,), chunk_size=6,
                         scenarios=("indoor-robot",))
    row = res["sweeps"]["fdi_prob"]["0.4"]
    assert row[ROBOT + PF_AWARE]["rmse_position"] < row[ROBOT + PF_PLAIN]["rmse_position"]
    assert row[ROBOT + PF_AWARE]["rmse_position"] < row[ROBOT + EKF_PLAIN]["rmse_position"]


SIGINT_SCRIPT = textwrap.dedent("""
    import sys
    from studies.pipeline import run_study
    run_study("comparison", ["indoor-robot"], out=sys.argv[1], runs=5, particles=60, seed=4, quiet=True,
              sweep_values=(0.3,), chunk_size=1, tuned_in_sweeps=False)  # as run_comparison below
""")


@pytest.mark.slow
def test_sigint_then_resume_equals_an_uninterrupted_study(tmp_path):
    script = tmp_path / "run.py"
    script.write_text(SIGINT_SCRIPT)
    out = tmp_path / "study"
    log = out / CHUNKS_DIR / "comparison-indoor-robot" / "log.jsonl"
    p = subprocess.Popen([sys.executable, str(script), str(out)], cwd=ROOT, stderr=subprocess.PIPE,
                         preexec_fn=_interruptible)
    deadline = time.time() + 120
    while time.time() < deadline and (not log.exists() or not log.read_text().strip()):
        time.sleep(0.05)
    assert p.poll() is None, p.stderr.read().decode()
    p.send_signal(signal.SIGINT)
    err = p.communicate(timeout=60)[1].decode()
    assert p.returncode != 0 and "KeyboardInterrupt" in err, (p.returncode, err)
    assert not (out / "results.json").exists()
    written = len(log.read_text().splitlines())
    assert 1 <= written < 5
    kw = dict(runs=5, particles=60, seed=4, quiet=True, sweep_values=(0.3,), chunk_size=1, scenarios=("indoor-robot",))
    resumed = run_comparison(out=out, **kw)
    rn = resumed["runner"]["indoor-robot"]
    assert rn["chunks_reused"] == written and rn["chunks_computed"] == 5 - written
    chunks = [tuple(json.loads(line)["chunk"]) for line in log.read_text().splitlines()]
    assert sorted(chunks) == [(r, r + 1) for r in range(5)]  # none computed twice
    whole = run_comparison(out=None, **kw)
    assert _numbers(resumed) == _numbers(whole)


def test_cli_comparison_options(tmp_path, capsys):
    assert main(["study", "comparison", "--out", str(tmp_path), "--engine", "fast"]) == 2
    assert "--engine does not apply" in capsys.readouterr().err
    assert main(["study", "comparison", "--out", str(tmp_path), "--workers", "2", "--dask", "tcp://x:1"]) == 2
    assert "exclude each other" in capsys.readouterr().err
    assert main(["study", "rrp-deception", "--out", str(tmp_path), "--workers", "2", "--dask", "tcp://x:1"]) == 2
    assert main(["study", "comparison", "--out", str(tmp_path), "--set", "dos_prob=0.8", "--set",
                 "fdi_prob=0.5"]) == 2
    assert main(["study", "comparison", "--out", str(tmp_path), "--set", "no_such_parameter=1"]) == 2
    assert "no parameter of that name" in capsys.readouterr().err
    assert main(["study", "comparison", "--out", str(tmp_path), "--scenario", "four-tank"]) == 2
    assert main(["study", "rrp-deception", "--out", str(tmp_path), "--scenario", "indoor-robot"]) == 2


def test_assignments_go_to_the_scenarios_that_have_the_parameter():
    from studies.pipeline import _route
    from studies.scenarios import get_spec

    names = ("indoor-robot", "target-range-bearing")
    got = _route(names, {n: get_spec(n) for n in names},
                                ["meas_var=2", "dos_prob=0.2", "glint_prob=0.1"])
    assert got == {"indoor-robot": ["meas_var=2", "dos_prob=0.2"],
                   "target-range-bearing": ["dos_prob=0.2", "glint_prob=0.1"]}


def test_target_scenario_tracks_with_wrapped_bearings():
    """A sensor right of the target sees bearings near +-pi: the EKF must wrap its residuals."""
    sc = load_scenario("target-range-bearing", {"sensor_positions": [[60.0, 20.0], [60.0, 35.0]],
                                                "edges": [[0, 1]], "x0": [20.0, 0.3, 17.0, 0.3]})
    traj = sc.simulate(np.random.default_rng(0), 60)
    b = traj.z[:, 1]
    assert (b > 3.0).any() and (b < -3.0).any()  # the bearing of sensor 1 crosses +-pi
    wrapped = run_ekf(sc.model, traj.z)  # the sensors declare their bearing as an angle
    raw = run_ekf(sc.model, traj.z, angles=())
    err = lambda res: np.sqrt(((res.x[1:, [0, 2]] - traj.x[1:, [0, 2]]) ** 2).sum(-1).mean())  # noqa: E731
    assert err(wrapped) < 3.0 < err(raw)
    ll = uplink_loglik(sc.model)
    x = traj.x[5][None, None]
    y0 = np.concatenate([traj.z[4], [1.0, 1.0]])[None]
    y1 = y0.copy()
    y1[0, 1] += 2 * np.pi
    np.testing.assert_allclose(ll(x, 5, y0), ll(x, 5, y1), rtol=1e-12)


# --- a subset of the filters ---------------------------------------------------------------------------------------

def test_a_subset_of_the_filters_gives_each_the_numbers_it_has_in_the_full_comparison(tmp_path):
    """``filters``: only the filters named run (their designs alone are made), each with the numbers, intervals and
    verdicts it has in the full comparison of the same runs; the others are absent from every file."""
    from studies import schemas

    kw = dict(scenarios=["examples/ring_model.py"], runs=4, particles=20, seed=3, sweep_values=[0.2], quiet=True)
    full = run_comparison(**kw)["filters"]
    sub = run_comparison(filters="relay, kcf,centralized-ekf", out=tmp_path / "s", **kw)
    picked = ["relay EKF (relay design)", "KCF", "centralized EKF (trusts every packet)"]
    assert sorted(sub["filters"]) == sorted(picked)
    for name in picked:
        a, b = full[name], sub["filters"][name]
        for key in ("rmse", "rmse_ci95", "rmse_median_run", "messages_per_step", "verdicts"):
            assert a.get(key) == b.get(key), (name, key, a.get(key), b.get(key))
    schemas.validate_output(tmp_path / "s")
    text = (tmp_path / "s" / "table.md").read_text()
    assert "| KCF" in text and "| HCMCI" not in text and "| centralized PF" not in text  # the rows, not the title


def test_filters_names_are_checked_before_any_run(tmp_path, capsys):
    with pytest.raises(InputError, match="filter must be one of"):
        run_comparison(scenarios=["examples/ring_model.py"], runs=2, filters="kcf,nonesuch")
    with pytest.raises(InputError, match="at least one filter"):
        run_comparison(scenarios=["examples/ring_model.py"], runs=2, filters=" , ")
    assert main(["study", "comparison", "examples/ring_model.py", "--runs", "2", "--filters", "nonesuch",
                 "--out", str(tmp_path / "x")]) == 2
    assert "filter must be one of" in capsys.readouterr().err and not (tmp_path / "x" / "results.json").exists()
    assert main(["study", "consensus-robot", "--runs", "2", "--filters", "kcf", "--out", str(tmp_path / "y")]) == 2
    assert "does not apply to study 'consensus-robot'" in capsys.readouterr().err


def test_the_memory_estimate_counts_only_the_filters_chosen():
    """``filters`` leaving out the particle filters and the designs leaves their memory out of the estimate made
    before any computation (a large state's particles no longer refuse a comparison that does not run them)."""
    from designer.design import DesignOptions
    from studies import memory
    from studies.comparison import STUDY
    from studies.pipeline import StudyOptions

    sc = load_scenario("indoor-robot")

    def need(filters):
        so = StudyOptions(10, 5000, 0, 10, Backend(), DesignOptions(), {**STUDY.options, "filters": filters})
        return memory.study_need("comparison", sc, so, STUDY.uses(sc, so)).nbytes

    every, some = need(None), need("kcf,hcmci")
    assert some < every
    kcf_only = StudyOptions(10, 50, 0, 10, Backend(), DesignOptions(), {**STUDY.options, "filters": "kcf"})
    assert STUDY.uses(sc, kcf_only) == ((), False, ())


FIELD15 = '''"""A 15-cell rod (15 temperatures), one thermometer a cell, nodes on a chain: N n = 225 rows."""
import casadi as ca
import numpy as np

from designer import AttackSpec, FDISignal, Gaussian, Model, SensorNetwork, Sensor

N = 15
STEPS = 6
NETWORK = SensorNetwork.from_edges(N, [(i, i + 1) for i in range(N - 1)])
ATTACKS = AttackSpec(dos=0.1, fdi={(3, 4): 0.1}, signal=FDISignal(amplitude=0.1, components=(3,)))


def model() -> Model:
    x = ca.SX.sym("x", N)
    f = ca.vertcat(*[x[i] + 0.2 * ((x[i - 1] if i else x[i]) - 2 * x[i] + (x[i + 1] if i < N - 1 else x[i]))
                     for i in range(N)])
    sensors = [Sensor(f"cell{i}", x[i], Gaussian.zero_mean([[0.01]])) for i in range(N)]
    return Model("rod15", x, f, sensors, process_noise=Gaussian.zero_mean(1e-3 * np.eye(N)),
                 prior=Gaussian(np.zeros(N), 0.1 * np.eye(N)))
'''


def test_an_oracle_carrying_the_joint_covariance_is_left_out_of_the_default_set_at_size(tmp_path, capsys):
    """On a 15-node, 15-state rod (N n = 225 > JOINT_ROWS_DEFAULT) the default comparison leaves out exactly the
    filters of the gain rules that carry all nodes' joint covariance, says why in results.json (left_out), in its
    assumptions and on the command line, and does not count their designs in its memory estimate; named in
    --filters, such a filter runs.  On the robot (N n = 24) nothing is left out."""
    import rules
    from designer.design import DesignOptions
    from studies import memory
    from studies.comparison import FILTER_REGISTRY, JOINT_ROWS_DEFAULT, STUDY, left_out
    from studies.pipeline import StudyOptions

    path = tmp_path / "rod15.py"
    path.write_text(FIELD15)
    sc = load_scenario(str(path))
    assert sc.network.n_nodes * sc.model.n_x > JOINT_ROWS_DEFAULT
    joint = {e.name for e in FILTER_REGISTRY if e.mode is not None and rules.get(e.mode).joint_covariance}
    assert joint and set(left_out(sc)) == joint and all("N n = 225 rows" in why for why in left_out(sc).values())
    assert left_out(load_scenario("indoor-robot")) == {}
    # above TABLES_ROWS_DEFAULT the designs of offline tables and of a convex problem a step are left out too
    from studies.comparison import TABLES_ROWS_DEFAULT

    tables = {e.name for e in FILTER_REGISTRY if e.mode is not None and (rules.get(e.mode).offline_tables
                                                                          or rules.get(e.mode).solves_online)}
    wide = tmp_path / "rod32.py"
    wide.write_text(FIELD15.replace("N = 15", "N = 32"))
    assert 32 * 32 > TABLES_ROWS_DEFAULT >= 31 * 31
    assert tables and set(left_out(load_scenario(str(wide)))) == joint | tables
    narrow = tmp_path / "rod31.py"
    narrow.write_text(FIELD15.replace("N = 15", "N = 31"))
    assert set(left_out(load_scenario(str(narrow)))) == joint

    def options(filters):
        return StudyOptions(2, 50, 0, 10, Backend(), DesignOptions(), {**STUDY.options, "filters": filters})

    modes, _, main_only = STUDY.uses(sc, options(None))
    assert not any(rules.get(m).joint_covariance for m in modes)
    # above SWEEP_ROWS the tuned and scheduled designs run at the main setting only: so says the estimate's input
    assert set(main_only) == {m for m in modes if rules.get(m).solves_online or rules.get(m).offline_tables}
    named = ",".join(FILTER_REGISTRY.names())
    assert set(STUDY.uses(sc, options(named))[0]) > set(modes) and STUDY.uses(sc, options(named))[2] == ()
    assert (memory.study_need("comparison", sc, options(None), STUDY.uses(sc, options(None))).nbytes
            < memory.study_need("comparison", sc, options(named), STUDY.uses(sc, options(named))).nbytes)
    # a design run at the main setting only holds the chunk's runs of that setting alone, not of every setting
    settings = 1 + 2 * len(STUDY.options["sweep_values"])
    for mode in main_only:
        key = f"the {mode} design: the bounds, gains and estimates of every node and step"
        alone = {p.what: p.nbytes for p in memory.STUDY_NEEDS["comparison"](sc, options(None),
                                                                          uses=((mode,), False, (mode,)))[1]}
        swept = {p.what: p.nbytes for p in memory.STUDY_NEEDS["comparison"](sc, options(None),
                                                                          uses=((mode,), False, ()))[1]}
        assert alone[key] * settings == pytest.approx(swept[key]), mode
    kw = dict(scenarios=[str(path)], runs=2, particles=20, sweep_values=[0.1], quiet=True)
    named_run = run_comparison(filters="kcf", **kw)  # named: nothing is left out
    assert named_run["left_out"] == {}
    capsys.readouterr()  # the command line, as run_comparison's options: what it runs and what it says
    assert main(["study", "comparison", str(path), "--runs", "2", "--particles", "20", "--set", "sweep_values=[0.1]",
                 "--set", "tuned_in_sweeps=false", "--quiet", "--out", str(tmp_path / "d")]) == 0
    told = capsys.readouterr().out
    res = json.loads((tmp_path / "d" / "results.json").read_text())
    pfs = {e.name for e in FILTER_REGISTRY if e.particles}  # 20 particles on 15 precise cells: degenerate in the pilot
    assert set(res["left_out"]) == joint | pfs and not set(res["filters"]) & (joint | pfs)
    assert all(f"  {n}: left out: {res['left_out'][n]}\n" in told for n in joint | pfs), told
    said = (tmp_path / "d" / "table.md").read_text().split("Left out of the default filters")[1]
    assert all(f"{n}: {res['left_out'][n]}" in said for n in joint | pfs)
    assert any("left out of the default filters" in a for a in res["assumptions"])
    from studies import schemas

    schemas.validate_output(tmp_path / "d")


def test_the_costliest_filters_run_at_the_main_setting_only_above_sweep_rows(tmp_path):
    """On an 11-cell rod (N n = 121: above SWEEP_ROWS, within JOINT_ROWS_DEFAULT) the default comparison runs the
    filters carrying all nodes' joint covariance and those whose nodes solve a convex problem every step at its main
    setting only: the oracles' numbers there are those of a comparison that runs them everywhere
    (oracles_in_sweeps=true), they have no sweep cell, results.json says why (sweeps_left_out) and so do the
    assumptions; every other filter's numbers are the same in both.  Below SWEEP_ROWS (the robot) and with --filters
    nothing is run at the main setting only by size; a value other than true, false or none is refused."""
    import rules
    from designer.design import DesignOptions
    from studies.comparison import FILTER_REGISTRY, JOINT_ROWS_DEFAULT, STUDY, SWEEP_ROWS, sweeps_left_out
    from studies.pipeline import StudyOptions

    path = tmp_path / "rod11.py"
    path.write_text(FIELD15.replace("N = 15", "N = 11"))
    sc = load_scenario(str(path))
    assert SWEEP_ROWS < sc.network.n_nodes * sc.model.n_x <= JOINT_ROWS_DEFAULT
    joint = {e.name for e in FILTER_REGISTRY if e.mode is not None and rules.get(e.mode).joint_covariance}
    online = {e.name for e in FILTER_REGISTRY if e.mode is not None and rules.get(e.mode).solves_online}
    tables = {e.name for e in FILTER_REGISTRY if e.mode is not None and rules.get(e.mode).offline_tables}
    assert joint and online and tables and not (joint & online or joint & tables or online & tables)

    def options(**own):
        return StudyOptions(2, 50, 0, 10, Backend(), DesignOptions(), {**STUDY.options, **own})

    assert set(sweeps_left_out(sc, options())) == joint | online | tables
    assert all("N n = 121 rows" in why for why in sweeps_left_out(sc, options()).values())
    assert set(sweeps_left_out(sc, options(oracles_in_sweeps=True))) == online | tables
    assert set(sweeps_left_out(sc, options(tuned_in_sweeps=True))) == joint | tables
    assert set(sweeps_left_out(sc, options(tables_in_sweeps=True))) == joint | online
    assert sweeps_left_out(sc, options(filters="mse,tuned,kcf,scheduled")) == {}
    assert sweeps_left_out(load_scenario("indoor-robot"), options()) == {}
    assert set(sweeps_left_out(load_scenario("indoor-robot"), options(oracles_in_sweeps=False))) == joint
    assert set(sweeps_left_out(load_scenario("indoor-robot"), options(tuned_in_sweeps=False))) == online
    assert set(sweeps_left_out(load_scenario("indoor-robot"), options(tables_in_sweeps=False))) == tables
    big = tmp_path / "rod15.py"  # N n = 225: the oracle left out of the default set, the tuned and scheduled
    big.write_text(FIELD15)  # designs main-only
    assert set(sweeps_left_out(load_scenario(str(big)), options())) == online | tables
    for name in ("oracles_in_sweeps", "tables_in_sweeps"):
        with pytest.raises(InputError, match=f"{name} must be true or false"):
            STUDY.check(options(**{name: "maybe"}))
    kw = dict(scenarios=[str(path)], runs=2, particles=20, sweep_values=[0.0, 0.2], tuned_in_sweeps=True,
              tables_in_sweeps=True, quiet=True)
    cut, full = run_comparison(**kw), run_comparison(oracles_in_sweeps=True, **kw)
    assert set(cut["sweeps_left_out"]) == joint and full["sweeps_left_out"] == {}
    assert any("run at the main setting only" in a for a in cut["assumptions"])

    def numbers(filters):  # what a filter scored, not how long it took
        return {n: {k: v for k, v in m.items() if k != "time_per_step_s"} for n, m in filters.items()}

    assert numbers(cut["filters"]) == numbers(full["filters"])  # the main setting: every filter alike
    # better_than_local: a filter the nodes run whose RMSE over the local EKFs' (the floor), on the same runs, has a
    # paired interval entirely below 1
    from designer.rule import DEPLOYABLE
    from studies.comparison import LOCAL, table_markdown

    alone = cut["filters"][LOCAL]
    for name, f in cut["filters"].items():
        if name == LOCAL or f["runtime"] not in DEPLOYABLE or f["rmse_ci95"] is None:
            assert f["better_than_local"] is None and f["rmse_ratio_local"] is None, name
            continue
        lo, hi = f["rmse_ratio_local_ci95"]
        assert lo <= f["rmse_ratio_local"] <= hi and f["better_than_local"] is (hi < 1), name
        if not f["diverged_runs"] and not alone["diverged_runs"]:  # the same runs: the ratio of the two RMSEs
            assert f["rmse_ratio_local"] == pytest.approx(f["rmse"] / alone["rmse"], rel=1e-12), name
    worse = [n for n, f in cut["filters"].items() if f["better_than_local"] is False]
    said = table_markdown(cut)
    assert ("No better than the nodes running alone on these runs" in said) == bool(worse)
    assert all(n in said.split("No better than the nodes running alone")[1] for n in worse)
    for key in ("dos_prob", "fdi_prob"):
        for value, row in full["sweeps"][key].items():
            assert joint <= set(row) and not joint & set(cut["sweeps"][key][value])
            assert cut["sweeps"][key][value] == {n: m for n, m in row.items() if n not in joint}


def test_a_large_model_is_cut_into_smaller_chunks_with_the_same_numbers(tmp_path):
    """studies.comparison.chunk_size: above CHUNK_ROWS rows N n the runs are cut into CHUNKS_LARGE chunks (so a
    default --runs 10 keeps two or four cores busy), below it CHUNK_SIZE; the numbers are those of one chunk."""
    from studies.comparison import CHUNK_ROWS, CHUNK_SIZE, CHUNKS_LARGE, chunk_size

    path = tmp_path / "rod15.py"
    path.write_text(FIELD15)
    sc = load_scenario(str(path))
    assert sc.network.n_nodes * sc.model.n_x > CHUNK_ROWS
    assert [chunk_size(sc, r) for r in (1, 4, 10, 40, 100)] == [1, 1, 3, 10, CHUNK_SIZE]
    robot = load_scenario("indoor-robot")
    assert robot.network.n_nodes * robot.model.n_x <= CHUNK_ROWS and chunk_size(robot, 10) == CHUNK_SIZE
    kw = dict(scenarios=[str(path)], runs=CHUNKS_LARGE, particles=20, sweep_values=[0.2],
              filters="KCF,relay EKF (relay design),local EKF at every node (no network)")
    cut = run_study("comparison", kw.pop("scenarios"), quiet=True, **kw)
    whole = run_study("comparison", [str(path)], quiet=True, chunk_size=CHUNKS_LARGE, **kw)
    a, b = next(iter(cut.arrays.values())), next(iter(whole.arrays.values()))
    assert set(a) == set(b)
    for name in a:
        if name != "seconds":
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)


SCALAR2 = '''"""One slow scalar seen by two noisy thermometers: a particle filter's weights stay spread."""
import casadi as ca
import numpy as np

from designer import AttackSpec, FDISignal, Gaussian, Model, SensorNetwork, Sensor

STEPS = 8
NETWORK = SensorNetwork.from_edges(2, [(0, 1)])
ATTACKS = AttackSpec(dos=0.1, fdi=0.1, signal=FDISignal(amplitude=0.1))


def model() -> Model:
    x = ca.SX.sym("x", 1)
    sensors = [Sensor(f"t{i}", x[0], Gaussian.zero_mean([[1.0]])) for i in range(2)]
    return Model("scalar2", x, 0.95 * x, sensors, process_noise=Gaussian.zero_mean([[0.01]]),
                 prior=Gaussian(np.zeros(1), [[0.1]]))
'''


def test_a_particle_filter_whose_weight_sits_on_a_few_particles_is_called_degenerate(tmp_path, capsys):
    """The comparison reports each particle filter's typical effective sample size after weighting
    (filters.particle.degenerate: the median over runs of each run's median over the steps, each step's ESS the run's
    own 1 / Σ W²): on a 15-cell rod with precise thermometers 30 particles put their weight on fewer than
    DEGENERATE_ESS of them (degenerate, and the table and the command line say so); on a scalar seen through noisy
    thermometers they keep most of it (not degenerate); so at every sweep setting, whose cells say it.  Either way
    1 <= ESS <= M."""
    from filters.particle import DEGENERATE_ESS, degenerate, effective_size
    from studies import schemas
    from studies.cli import main

    assert effective_size(np.full(30, 1 / 30)) == pytest.approx(30) and effective_size(np.eye(30)[3]) == 1.0
    assert degenerate(np.array([[1.0, 2.0, 50.0], [3.0, np.nan, 4.0]])) == (2.75, True)  # medians 2 and 3.5
    assert degenerate(np.full((2, 3), np.nan)) is None
    pfs = ["centralized PF (attack-aware)", "centralized PF (trusts every packet)"]
    rod, scalar = tmp_path / "rod15.py", tmp_path / "scalar2.py"
    rod.write_text(FIELD15)
    scalar.write_text(SCALAR2)
    seen = {}
    for path, out in ((rod, tmp_path / "rod"), (scalar, tmp_path / "scalar")):
        res = run_comparison(scenarios=[str(path)], runs=3, particles=30, seed=2, sweep_values=[0.1], quiet=True,
                             filters=",".join(pfs + ["local"]), out=out)
        schemas.validate_output(out)
        for name in pfs:
            f = res["filters"][name]
            assert 1.0 <= f["weights_ess"] <= 30 and f["degenerate"] == (f["weights_ess"] < DEGENERATE_ESS)
        assert "weights_ess" not in res["filters"]["local EKF at every node (no network)"]
        seen[path.stem] = [res["filters"][n]["degenerate"] for n in pfs]
        cells = [row[n] for sweep in res["sweeps"].values() for row in sweep.values() for n in pfs if n in row]
        assert cells and all(c["degenerate"] == (c["weights_ess"] < DEGENERATE_ESS) for c in cells)
        assert {c["degenerate"] for c in cells} == {path.stem == "rod15"}  # at every setting too
        text = (out / "table.md").read_text()
        assert ("Degenerate particle filters" in text) == any(seen[path.stem])
        assert (", degenerate" in text) == any(c["degenerate"] for c in cells)
    assert seen == {"rod15": [True, True], "scalar2": [False, False]}
    capsys.readouterr()
    assert main(["study", "comparison", str(rod), "--runs", "2", "--particles", "30", "--filters",
                 ",".join(pfs), "--set", "sweep_values=[0.1]", "--out", str(tmp_path / "cli")]) == 0
    said = capsys.readouterr().out
    assert said.count("degenerate: its weight on") == 2, said


def test_a_particle_filter_degenerate_on_its_pilot_runs_is_left_out_of_the_default_set(tmp_path):
    """Before the study each particle filter runs on PILOT_RUNS runs of its own at the main setting: on the 15-cell
    rod with precise thermometers 30 particles are degenerate there (typical ESS below DEGENERATE_ESS), so the default
    comparison leaves both particle filters out and says why, with the pilot's ESS (results.json left_out); named in
    --filters they run, and the study finds them degenerate too; on the scalar seen through noisy thermometers, and on
    the robot at the default 500 particles, they stay.  The pilot is the runs it names: the study's batched particle
    filter on those seeds, and it depends on the seed, not on the worker."""
    from designer.design import DesignOptions
    from filters.particle import DEGENERATE_ESS, degenerate
    from studies.comparison import FILTER_REGISTRY, PILOT_RUNS, STUDY, _chosen, particle_pilot, realise
    from studies.pipeline import StudyOptions

    pfs = [e.name for e in FILTER_REGISTRY if e.particles]
    rod, scalar = tmp_path / "rod15.py", tmp_path / "scalar2.py"
    rod.write_text(FIELD15)
    scalar.write_text(SCALAR2)

    def options(particles, seed=2):
        return StudyOptions(2, particles, seed, 10, Backend(), DesignOptions(), dict(STUDY.options))

    sc = load_scenario(str(rod))
    pilot = particle_pilot(sc, options(30))
    assert set(pilot) == set(pfs) and all(1.0 <= v < DEGENERATE_ESS for v in pilot.values())
    left = _chosen(sc, options(30))[1]
    assert set(pfs) <= set(left) and all(f"of 30 particles, below {DEGENERATE_ESS:g}" in left[n] for n in pfs)
    # the pilot is its runs: the study's particle filter on PILOT_RUNS runs seeded SeedSequence(seed, (2**31 + 1, r))
    seeds = [np.random.SeedSequence(2, spawn_key=(2**31 + 1, r)) for r in range(PILOT_RUNS)]
    batch = realise([sc], seeds, particles=30, iterations=1, run_ids=range(PILOT_RUNS), covariances=False)
    res = FILTER_REGISTRY[pfs[0]].run(batch, [0], None)
    assert pilot[pfs[0]] == degenerate(np.median(res.ess, axis=-1))[0]
    assert particle_pilot(load_scenario(str(scalar)), options(30)).keys() == set(pfs)
    assert not set(pfs) & set(_chosen(load_scenario(str(scalar)), options(30))[1])
    robot = particle_pilot(load_scenario("indoor-robot"), options(500, 0))
    assert all(v >= DEGENERATE_ESS for v in robot.values()), robot
    assert _chosen(load_scenario("indoor-robot"), options(500, 0))[1] == {}
    out = run_comparison(scenarios=[str(rod)], runs=2, particles=30, seed=2, sweep_values=[0.1], quiet=True,
                         filters="local,kcf," + ",".join(pfs))  # named: they run, and are degenerate
    assert out["left_out"] == {} and all(out["filters"][n]["degenerate"] for n in pfs)


def test_a_comparisons_numbers_do_not_depend_on_how_its_settings_are_batched(tank_model, monkeypatch):
    """Each group of settings runs in batches small enough for glibc's heap (studies.comparison._heap_sized: on the
    64-cell field two settings of 3 runs a batch, where one batch of 30 rows spent a third of its time faulting in
    fresh pages).  With the heap's limit forced down to one setting a batch, every filter's numbers in results.json
    are the same bits as with every setting in one batch (the small tank's default)."""
    import studies.comparison as comparison

    kw = dict(runs=2, particles=30, seed=3, quiet=True, sweep_values=(0.2, 0.4), tuned_in_sweeps=False)
    path = str(tank_model(steps=12))
    whole = run_study("comparison", [path], **kw).results
    assert comparison._heap_sized([[0, 1, 2]], 2, 3, 2) == [[0, 1, 2]]  # the tank: one batch
    monkeypatch.setitem(comparison.ALLOCATOR, "mmap_threshold", 2)
    assert comparison._heap_sized([[0, 1, 2], [3]], 2, 3, 2) == [[0], [1], [2], [3]]
    split = run_study("comparison", [path], **kw).results
    keys = ("rmse", "rmse_curve", "rmse_median_run", "diverged_runs", "verdicts", "bounded_runs")
    assert whole["filters"].keys() == split["filters"].keys()
    for name, f in whole["filters"].items():
        for key in keys:
            assert f.get(key) == split["filters"][name].get(key), (name, key)
    assert whole["sweeps"] == split["sweeps"]
