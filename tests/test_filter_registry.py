"""One result type for every filter family (filters.result.FilterResult) and the registry of filters the studies
iterate over (studies.filter_registry; issue 26, item 7).

* every entry of the comparison's registry, and the consensus-robot's own entries, returns a FilterResult of the
  shapes, kinds, run time and message counts it declares, on a user's model file (a tank watched by three nodes);
* each family's adapter keeps the family's numbers exactly (the same arrays), and a per-run result stacked into a
  batch is the per-run result;
* a filter registered in a test appears in the comparison's results with what it declared, and its numbers are
  those of the filter it runs (the registry drives the study).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import TANK_MODEL
from designer.design import DesignOptions
from designer.validation import InputError
from filters.consensus import run_consensus
from filters.consensus_batch import run_consensus_batch
from filters.distributed import run_hcmci, run_kcf, run_kcf_batch
from filters.ekf import run_ekf, run_ekf_batch
from filters.result import FilterResult, nonfinite_violations
from filters.uplink import split_received
from studies.comparison import FILTER_REGISTRY, LOCAL, realise
from studies.consensus_design import consensus_design
from studies.design_options import as_mode
from studies.filter_registry import (Batch, FilterEntry, FilterRegistry, centralized_consensus_ekf, hcmci, kcf,
                                     local_ekfs, replayed_schedule)
from studies.pipeline import run_study
from studies.scenarios import load_scenario

RUNS, STEPS = 2, 6


@pytest.fixture(scope="module")
def tank(tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "tank.py"
    path.write_text(TANK_MODEL.replace("STEPS = 20", f"STEPS = {STEPS}"))
    return load_scenario(str(path))


def _batch(sc, settings=((0.1, 0.1), (0.3, 0.1)), per_row_networks=True, seed=4) -> Batch:
    """Two runs of ``sc`` at ``settings`` (DoS, FDI): the comparison's realisations (common random numbers)."""
    seeds = [np.random.SeedSequence(seed, spawn_key=(r,)) for r in range(RUNS)]
    batch = realise([sc.with_attacks(dos=d, fdi=f) for d, f in settings], seeds, particles=30, iterations=2,
                    run_ids=range(RUNS))
    return dataclasses.replace(batch, per_row_networks=per_row_networks)


def _check_shapes(res: FilterResult, entry: FilterEntry, sc, rows: int, L: int) -> None:
    m, net = sc.model, sc.network
    nodes = entry.nodes(net)
    assert isinstance(res, FilterResult)
    assert res.x.shape == (rows, sc.steps + 1, nodes, m.n_x)
    assert res.cov.shape == (rows, sc.steps + 1, nodes, m.n_x, m.n_x)
    assert res.trace.shape == res.valid.shape == (rows, sc.steps + 1, nodes)
    # Φ of the consensus EKF's recursion is a bound; the EKFs (the design reduced to it) and KCF, HCMCI, the particle
    # filters carry their own covariance
    assert res.cov_kind == ("bound" if entry.family == "consensus" and entry.mode is not None else "covariance")
    assert res.runtime == entry.runtime
    assert len(res.violations) == rows and res.diverged_step.shape == (rows,)
    # the messages it counts are those the entry declares for the contract, at every step (a designed filter: its
    # design's exchange rounds, one with the default options)
    assert res.messages.shape == (rows, sc.steps)
    assert (res.messages == entry.messages_per_step(net, L, DesignOptions())).all()
    assert (res.delivered is not None) == entry.counts_delivered or entry.mode is not None
    if res.delivered is not None:
        assert ((0 <= res.delivered) & (res.delivered <= res.messages)).all()
    ok = res.diverged_step < 0
    assert np.isfinite(res.x[ok]).all()


def test_every_entry_of_the_comparison_returns_a_filter_result_of_its_shapes(tank):
    batch = _batch(tank)
    js = [0, 1]
    for e in FILTER_REGISTRY:
        design = None if e.mode is None else e.design_for(
            consensus_design(tank.with_attacks(dos=0.1, fdi=0.1), as_mode(None, e.mode)), tank.model)
        if e.start_check:
            design = design._replace(sigma=0.01, beta=0.01)  # within (28)-(29) at the first step
        res = e.run(batch, js if e.attacked else [0], design)
        _check_shapes(res, e, tank, RUNS * (len(js) if e.attacked else 1), batch.iterations)


def test_the_consensus_robots_entries_return_filter_results_of_their_shapes(tank):
    batch = _batch(tank, settings=((0.1, 0.1),), per_row_networks=False)
    paper = consensus_design(tank)._replace(sigma=0.01, beta=0.01)
    K = np.zeros((tank.steps, tank.network.n_nodes, tank.model.n_x, 1))
    C = np.zeros((tank.steps, tank.network.n_nodes, tank.model.n_x, tank.model.n_x))
    for e in (centralized_consensus_ekf("centre", "c"), local_ekfs("alone", "a"), kcf("K", "k"), hcmci("H", "h"),
              replayed_schedule("replay", "r", (K, C))):
        res = e.run(batch, [0], None if e.mode is None else e.design_for(paper, tank.model))
        _check_shapes(res, e, tank, RUNS, batch.iterations)


def test_the_reference_filters_without_covariances_give_the_same_estimates(tank):
    """A batch without covariances (what the comparison and the consensus-robot study run the filters that are not
    designed on: they are scored on their estimates): KCF, HCMCI, the local and the centralized EKF give the same
    estimates, validity, violations and message counts, bit for bit, and no covariance (``cov`` None); a run that
    diverges stops as it does with them (run 1's measurements at step 3 are 1e300: every filter stops there)."""
    batch = _batch(tank, settings=((0.3, 0.2),), per_row_networks=False)
    z = batch.z.copy()
    z[1, 3] = 1e300
    batch = dataclasses.replace(batch, z=z)
    lean = dataclasses.replace(batch, covariances=False, cache={})
    paper = consensus_design(tank)
    for e in (centralized_consensus_ekf("centre", "c"), local_ekfs("alone", "a"), kcf("K", "k"), hcmci("H", "h")):
        design = None if e.mode is None else e.design_for(paper, tank.model)
        a, b = e.run(batch, [0], design), e.run(lean, [0], design)
        assert a.cov is not None and b.cov is None, e.name
        for name in ("x", "valid", "messages", "delivered"):
            got, want = getattr(b, name), getattr(a, name)
            assert (got is None) == (want is None) and (got is None or np.array_equal(got, want, equal_nan=True)), \
                (e.name, name)
        assert b.violations == a.violations, e.name
        assert b.detail.x_pred.tobytes() == a.detail.x_pred.tobytes(), e.name
        assert a.diverged[0] is None and a.diverged[1]["step"] <= 4 and b.diverged == a.diverged, e.name


def test_the_designed_filters_without_their_predictions_records_give_the_same_estimates_and_bounds(tank):
    """The same batch for the designed filters of the comparison (every gain rule it runs): the estimates, the bounds
    Φ, their validity and the violations bit for bit; the predictions' Φ and the gains not recorded (None in the
    detail) where the rule's filter leaves them out (mse keeps them: its filter runs the joint covariance)."""
    batch = _batch(tank, settings=((0.1, 0.1),), per_row_networks=False)
    lean = dataclasses.replace(batch, covariances=False, cache={})
    dropped = []
    for e in FILTER_REGISTRY:
        if not e.designed:
            continue
        design = e.design_for(consensus_design(tank.with_attacks(dos=0.1, fdi=0.1), as_mode(None, e.mode)),
                              tank.model)
        if e.start_check:
            design = design._replace(sigma=0.01, beta=0.01)
        a, b = e.run(batch, [0], design), e.run(lean, [0], design)
        for name in ("x", "cov", "valid"):
            assert np.array_equal(getattr(b, name), getattr(a, name), equal_nan=True), (e.name, name)
        assert b.violations == a.violations and a.detail.phi_pred is not None, e.name
        if b.detail.phi_pred is None:
            assert b.detail.K is None and b.detail.C is None, e.name
            dropped.append(e.mode)
    assert {"paper", "relay", "flood", "scheduled"} <= set(dropped), dropped


def test_the_comparisons_channel_attacks_are_the_dense_patterns_on_the_channels(tank):
    """realise holds each setting's attacks on the network's channels alone (EdgeAttacks.from_draws): run by run
    and setting by setting the numbers of the dense AttackPattern that studies.recorded.realised_attacks makes of
    the same draws (what `simulate --run` and a log hold), and the uplinks' deliveries are its too."""
    from filters.attacks import channel_draws
    from studies.recorded import realised_attacks

    settings = ((0.1, 0.1), (0.3, 0.2), (0.0, 0.0))
    batch = _batch(tank, settings=settings)
    K, n = tank.steps, tank.network.n_nodes
    for r in range(RUNS):
        ts, cs, _ = np.random.SeedSequence(4, spawn_key=(r,)).spawn(3)
        traj = tank.simulate(np.random.default_rng(ts), K)
        u, s = channel_draws(K, n, np.random.default_rng(cs))
        for j, (d, f) in enumerate(settings):
            pattern, received = realised_attacks(tank.with_attacks(dos=d, fdi=f), u, s, traj.x, traj.z)
            dense = batch.attacks[j].pattern(r, n)
            for name in ("dos", "fdi", "xi"):
                assert np.array_equal(getattr(dense, name), getattr(pattern, name)), (r, j, name)
            assert np.array_equal(batch.received[j][r], received, equal_nan=True)
    assert batch.attacks[1].dos.any() and batch.attacks[1].fdi.any() and not batch.attacks[2].dos.any()


def test_the_filters_results_keep_each_familys_numbers(tank):
    batch = _batch(tank, settings=((0.2, 0.1),))
    m, net = tank.model, tank.network
    design = consensus_design(tank, as_mode(None, "tuned"))
    res = run_consensus_batch(m, net, batch.z, design, attacks=batch.attacks[0])
    cb = res.detail
    assert res.x is cb.x_post and res.cov is cb.phi_post and res.valid is cb.valid
    assert res.violations is cb.violations and res.diverged == cb.diverged
    assert res.cov_kind == "bound" and res.runtime == design.rule.runtime == "local"
    assert (res.delivered == cb.gate_counts[..., 0]).all() and (res.messages == 2 * len(net.edges)).all()
    # a run alone (a batch of one) is exactly its row of the batch: nothing leaks between the runs of a batch
    for r in range(RUNS):
        ref = run_consensus(m, net, batch.z[r], design, attacks=batch.attacks[0].pattern(r, net.n_nodes))
        got = cb.run(r)
        for f in ("x_post", "phi_post", "K", "C", "valid", "sigma", "beta", "gate_counts"):
            assert np.array_equal(getattr(got, f), getattr(ref, f), equal_nan=True), f
        assert got.violations == ref.violations
    kr = run_kcf_batch(m, net, batch.z, attacks=batch.attacks[0])
    kb = kr.detail
    assert kr.runtime == "local" and kr.x is kb.x_post and kr.cov is kb.P_post and kr.cov_kind == "covariance"
    assert (kr.messages == kb.messages_per_step).all() and (kr.delivered == kb.delivered_per_step).all()
    # the registry's KCF and HCMCI entries: row r is run_kcf / run_hcmci on run r alone (a batch of one)
    u = batch.input_rows([0])
    assert batch.iterations == 2
    for entry, run, kw in ((kcf("K", "k"), run_kcf, {}), (hcmci("H", "h"), run_hcmci, {"iterations": 2})):
        res = entry.run(batch, [0], None)
        for r in range(RUNS):
            ref = run(m, net, batch.z[r], inputs=None if u is None else u[r],
                      attacks=batch.attacks[0].pattern(r, net.n_nodes), **kw)
            assert res.detail.iterations == ref.iterations
            for f in ("x_post", "P_post", "messages_per_step", "delivered_per_step"):
                assert np.array_equal(getattr(res.detail.run(r), f), getattr(ref, f), equal_nan=True), f
    values, avail = split_received(m, np.stack(batch.received[0]))
    er = run_ekf_batch(m, values, available=avail)
    eb = er.detail
    assert np.array_equal(er.x[:, :, 0], eb.x) and np.array_equal(er.cov[:, :, 0], eb.P)
    assert er.nodes == 1 and er.runtime == "centralized" and (er.messages == m.n_sensors).all()
    assert (run_ekf_batch(m, values, available=avail, uplinks=7).messages == 7).all()
    one = run_ekf(m, values[0], available=avail[0])  # a run is a batch of one, to rounding
    assert np.allclose(one.x, eb.x[0], rtol=0, atol=1e-9, equal_nan=True)


def test_every_batched_filter_returns_a_checked_filter_result_with_what_its_parameters_say(tank):
    from filters.particle import SIRResult, run_sir
    from rules.relay.filter import run_relay_batch

    batch = _batch(tank, settings=((0.2, 0.1),))
    m, net = tank.model, tank.network
    paper = consensus_design(tank)._replace(sigma=0.01, beta=0.01)
    links = 2 * len(net.edges)
    K = np.zeros((tank.steps, net.n_nodes, m.n_x, 1))
    C = np.zeros((tank.steps, net.n_nodes, m.n_x, m.n_x))
    replay = run_consensus_batch(m, net, batch.z, paper, gains=(K, C))
    assert replay.runtime == "scheduled" and replay.cov_kind == "bound" and (replay.messages == links).all()
    assert not replay.valid.any() and np.array_equal(replay.detail.K, K[None].repeat(RUNS, 0))
    centre = run_consensus_batch(m, net, batch.z, paper, runtime="centralized", cov_kind="covariance", messages=3)
    assert centre.runtime == "centralized" and centre.cov_kind == "covariance" and (centre.messages == 3).all()
    assert np.array_equal(centre.x, run_consensus_batch(m, net, batch.z, paper).x, equal_nan=True)
    relay = run_relay_batch(m, net, batch.z, 2, signal=tank.resolved_attacks.signal)
    assert relay.runtime == "local" and relay.cov_kind == "covariance" and (relay.messages == 2 * links).all()
    assert relay.detail.iterations == 2 and relay.x is relay.detail.x_post
    values, avail = split_received(m, np.stack(batch.received[0]))
    pf = run_sir(m, np.where(np.repeat(avail, m.sensor_dims, axis=-1), values, 0.0), np.random.default_rng(0),
                 particles=20, uplinks=5)
    assert isinstance(pf.detail, SIRResult) and pf.nodes == 1 and pf.runtime == "centralized"
    assert np.array_equal(pf.x[:, :, 0], pf.detail.mean) and np.array_equal(pf.cov[:, :, 0], pf.detail.cov)
    assert (pf.messages == 5).all() and (run_sir(m, np.zeros((1, 2, m.n_z)), np.random.default_rng(0),
                                                  particles=5).messages == m.n_sensors).all()
    for res in (replay, centre, relay, pf):
        assert isinstance(res, FilterResult) and res.check() is res


def test_a_run_is_diverged_at_its_first_non_finite_estimate():
    x = np.zeros((3, 8, 2))
    x[1, 5, 1] = np.nan
    x[2, 2, 0] = np.inf
    x[2, 6, 0] = np.nan
    assert [[v["step"] for v in vs] for vs in nonfinite_violations(x)] == [[], [5], [2]]


def test_a_result_of_wrong_shapes_or_kinds_is_refused():
    x = np.zeros((2, 4, 3, 2))
    good = FilterResult(x, np.zeros((2, 4, 3, 2, 2)), "bound", np.ones((2, 4, 3), bool), [[], []],
                        np.zeros((2, 3), np.int64), "local")
    assert good.check() is good
    with pytest.raises(InputError, match="cov must have shape"):
        good._replace(cov=np.zeros((2, 4, 3, 2))).check()
    with pytest.raises(InputError, match="cov_kind must be"):
        good._replace(cov_kind="guess").check()
    with pytest.raises(InputError, match="messages must have shape"):
        good._replace(messages=np.zeros((2, 4))).check()
    with pytest.raises(InputError, match="runtime must be"):
        good._replace(runtime="cloud").check()
    reg = FilterRegistry([local_ekfs("a", "a")])
    with pytest.raises(InputError, match="registered already"):
        reg.register(local_ekfs("a", "again"))
    with pytest.raises(InputError, match="family must be"):
        reg.register(local_ekfs("b", "b")._replace(family="magic"))
    with pytest.raises(InputError, match="gain rule"):
        reg.register(local_ekfs("c", "c")._replace(mode=None, designed=True))


def test_a_registered_filter_appears_in_the_comparison(tank_model):
    """The registry drives the study: a filter registered here (the local EKFs under another name and description)
    is run on the same runs, reported with what it declared, and has the numbers of the filter it runs."""
    mine = local_ekfs("my isolated EKFs", "a test's filter: the local EKFs again")
    FILTER_REGISTRY.register(mine)
    try:
        res = run_study("comparison", [str(tank_model(steps=STEPS))], runs=2, particles=30, seed=1, quiet=True,
                        sweep_values=(0.3,), tuned_in_sweeps=False).results
    finally:
        FILTER_REGISTRY.unregister(mine.name)
    assert mine.name not in FILTER_REGISTRY
    got, ref = res["filters"][mine.name], res["filters"][LOCAL]
    assert got["description"] == mine.description and got["family"] == "local" and got["runtime"] == "local"
    assert got["messages_per_step"] == 0
    for key in ("rmse", "rmse_curve", "rmse_median_run", "diverged_runs"):
        assert got[key] == ref[key], key
    assert all(mine.name in row for row in res["sweeps"]["dos_prob"].values())


def test_a_diverged_run_stops_alone_at_its_first_failing_node():
    """filters.result.stop_diverged, the bookkeeping of every batched consensus filter: the runs with a failed node
    stop at the first one, their arrays NaN (posteriors from the step, gains at the update) and invalid; the other runs
    keep every number."""
    from filters.result import DIVERGED_REASON, diverged_nodes, stop_diverged

    rng = np.random.default_rng(3)
    runs, steps, n, nx = 4, 5, 3, 2
    x = rng.normal(size=(runs, steps + 1, n, nx))
    P = np.broadcast_to(np.eye(nx), (runs, steps + 1, n, nx, nx)).copy()
    K = rng.normal(size=(runs, steps, n, nx))
    valid = np.ones((runs, steps + 1, n), bool)
    x[1, 3, 2, 0] = np.nan  # run 1: node 2 fails at step 3 ...
    x[1, 3, 1, 1] = 2e12  # ... and node 1 (beyond filters.result.DIVERGED): it stops at node 1
    P[3, 3, 0, 0, 0] = np.inf  # run 3: node 0
    active = np.array([0, 1, 3])  # run 2 stopped earlier
    bad = diverged_nodes(x[active, 3], P[active, 3])
    assert bad.tolist() == [[False] * 3, [False, True, True], [True, False, False]]
    before = (x.copy(), K.copy(), valid.copy())
    violations = [[] for _ in range(runs)]
    going = stop_diverged(violations, active, bad, 3, nan_from=(x,), nan_before=(K,), invalid_from=(valid,))
    assert active[going].tolist() == [0]
    assert [[(v["node"], v["step"], v["condition"], v["reason"]) for v in vs] for vs in violations] == [
        [], [(1, 3, "diverged", DIVERGED_REASON)], [], [(0, 3, "diverged", DIVERGED_REASON)]]
    for r in (1, 3):
        assert np.isnan(x[r, 3:]).all() and np.isnan(K[r, 2]).all() and not valid[r, 3:].any()
        assert np.array_equal(x[r, :3], before[0][r, :3]) and np.array_equal(K[r, :2], before[1][r, :2])
    for r in (0, 2):
        assert np.array_equal(x[r], before[0][r]) and np.array_equal(K[r], before[1][r]) and valid[r].all()


def test_a_process_without_the_planned_filters_refuses_the_task(tank):
    """A filter registered in one process is unknown to a worker process: the task says so instead of returning
    arrays of other filters (a study planned with it would misread them)."""
    from designer.design import DesignOptions
    from studies.comparison import _runs
    from studies.scenarios import reference

    planned = FILTER_REGISTRY.names() + ("my filter",)
    with pytest.raises(InputError, match="registered in a script is known to that process only"):
        _runs([0], [np.random.SeedSequence(1)], ref=reference(tank), settings=[(0.1, 0.1)], particles=20,
              options=DesignOptions(), filters=planned)
