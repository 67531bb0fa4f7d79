"""The automatic design (``cfdesign design`` without ``--mode``, :mod:`studies.auto`): its pick, its budget, its
costs, its processes and its files.

The pick's rule is checked on made-up candidates (the order of the criteria, the tie, the budget, the nodes-alone
test); the costs against independent counts (the relay tree's routes, a flood simulated round by round); the
end-to-end design against a design of the picked rule made on its own (the same numbers) and the schemas.
"""
from __future__ import annotations

import contextlib
import functools
import io
import json
import time

import numpy as np
import pytest

import rules
from designer import SensorNetwork
from designer.design import DesignOptions
from designer.validation import InputError
from studies.auto import TIE, Candidate, message_budget, predicted_error
from studies.runner import run_forked


def _cand(rule="relay", predicted=1.0, certified=True, messages=10, nbytes=100, in_budget=True, better=True,
          status="designed", ratio_centralized=None, **kw) -> Candidate:
    return Candidate(rule=rule, options=kw, rounds=kw.get("rounds", 1), exchange="relay", messages=messages,
                     bytes=nbytes, status=status, verdict="certified" if certified else "vacuous",
                     certified=certified, predicted=predicted, in_budget=in_budget, better_than_local=better,
                     ratio_centralized=ratio_centralized)


def _choose(cands, cap=None, cap_bytes=None):
    from studies import auto

    return auto._choose(cands, cap, cap_bytes)  # noqa: SLF001 - the module's own rule, tested on made-up rows


def test_the_pick_is_the_eligible_candidate_with_the_smallest_predicted_error():
    cands = [_cand(predicted=2.0, rounds=1), _cand(predicted=0.5, certified=False, rounds=2),
             _cand(predicted=1.0, rounds=3), _cand(predicted=0.7, in_budget=False, rounds=4),
             _cand(predicted=0.6, better=False, rounds=5), _cand(predicted=0.8, rounds=6)]
    i, outcome, message = _choose(cands)
    assert (i, outcome) == (5, "picked")
    assert "rounds=6" in message


def test_a_pick_below_the_centralized_steady_state_says_what_that_reference_is():
    """The centralized reference is its steady state at the operating point: a pick predicted below it (a run that
    left that point's geometry) says so, one above it is a plain ratio."""
    _, _, below = _choose([_cand(predicted=0.4, ratio_centralized=0.4)])
    assert "0.4 x the centralized EKF's steady state at the operating point: below it only where the run has left" in below
    _, _, above = _choose([_cand(predicted=2.0, ratio_centralized=2.0)])
    assert "(2 x the centralized EKF's)" in above


def test_a_tie_within_the_tolerance_goes_to_the_fewest_bytes_and_beyond_it_does_not():
    near = 1.0 * (1 + TIE / 2)
    i, _, _ = _choose([_cand(predicted=1.0, nbytes=500), _cand(predicted=near, nbytes=100)])
    assert i == 1
    far = 1.0 * (1 + 2 * TIE)
    i, _, _ = _choose([_cand(predicted=1.0, nbytes=500), _cand(predicted=far, nbytes=100)])
    assert i == 0


def test_no_certified_candidate_in_the_budget_names_the_cheapest_certified_one_outside_it():
    cands = [_cand(predicted=1.0, certified=False, messages=10, rounds=1),
             _cand(predicted=0.5, in_budget=False, messages=40, rounds=4),
             _cand(predicted=0.6, in_budget=False, messages=20, rounds=2)]
    i, outcome, message = _choose(cands, cap=10)
    assert outcome == "none in budget"
    assert i == 0  # the best design inside the budget is written, its verdict its own
    assert "rounds=2" in message and "10 messages" in message


def test_certified_but_no_better_than_the_nodes_alone_is_never_picked():
    i, outcome, _ = _choose([_cand(predicted=1.0, better=False)])
    assert outcome == "none better than local"
    i, outcome, _ = _choose([_cand(status="cannot start", predicted=None)])
    assert (i, outcome) == (None, "nothing designed")


def test_the_message_budget_reads_kcf_and_whole_numbers_and_refuses_the_rest():
    net = SensorNetwork.from_edges(4, [(0, 1), (1, 2), (2, 3)])
    assert message_budget("kcf", net) == 6 == net.messages_per_step()
    assert message_budget("12", net) == 12 and message_budget(None, net) is None
    for bad in ("0", "-3", "many", "1.5"):
        with pytest.raises(InputError, match="budget"):
            message_budget(bad, net)


def test_predicted_error_is_the_node_average_over_the_last_window():
    tr = np.vstack([np.arange(1.0, 13.0), 2 * np.arange(1.0, 13.0)])  # K = 12: W = 3
    assert predicted_error(tr) == pytest.approx(np.mean([10, 11, 12, 20, 22, 24]))
    tr[0, -1] = np.nan
    assert predicted_error(tr) is None


def _grid(rows, cols) -> SensorNetwork:
    edges = [(r * cols + c, r * cols + c + 1) for r in range(rows) for c in range(cols - 1)]
    edges += [(r * cols + c, (r + 1) * cols + c) for r in range(rows - 1) for c in range(cols)]
    return SensorNetwork.from_edges(rows * cols, edges)


@pytest.mark.parametrize("hops", [1, 2, 3, 5])
def test_relay_payload_counts_every_route_pair_once(hops):
    from rules.relay.design import relay_payload, relay_routes

    net = _grid(3, 4)
    dims = np.array([1, 2, 1, 3, 1, 1, 2, 1, 1, 1, 2, 1])
    routes = relay_routes(net, hops, "tree")
    expected = int(sum(dims[s] + 1 for s in routes.source))  # one transmission per (source, receiver) pair
    assert relay_payload(net, dims, hops, "tree") == expected


@pytest.mark.parametrize("hops", [1, 2, 4])
def test_flood_payload_matches_a_flood_simulated_round_by_round(hops):
    from rules.relay.design import relay_payload

    net = _grid(3, 3)
    adj = np.asarray(net.adjacency, dtype=bool)
    dims = np.arange(1, 10)
    held = {i: {i} for i in range(9)}  # what each node holds, by source
    fresh = {i: {i} for i in range(9)}  # what it first received in the last round (its own in round 1)
    sent = 0
    for _ in range(hops):
        arriving = {i: set() for i in range(9)}
        for j in range(9):
            for i in np.flatnonzero(adj[j]):
                sent += sum(dims[s] + 1 for s in fresh[j])
                arriving[int(i)] |= fresh[j]
        fresh = {i: arriving[i] - held[i] for i in range(9)}
        for i in range(9):
            held[i] |= fresh[i]
    assert relay_payload(net, dims, hops, "flood") == sent


def test_every_deployable_rule_offers_candidates_and_an_oracle_none():
    net = _grid(2, 3)
    for name, rule in rules.all_rules().items():
        cands = rule.candidates(net)
        assert bool(cands) == rule.deployable, name
    hops = rules.get("relay").rounds(net)
    assert [c["rounds"] for c in rules.get("relay").candidates(net)] == list(range(1, hops + 1))


def _sleep_then(x, seconds):
    time.sleep(seconds)
    return np.full(200_000, x)  # more than a pipe's buffer: read as it arrives


def _fail():
    raise ValueError("refused")


@pytest.mark.parametrize("workers", [1, 2])
def test_run_forked_returns_in_order_reports_failures_and_kills_at_the_deadline(workers):
    calls = [functools.partial(_sleep_then, 1.0, 0.0), _fail, functools.partial(_sleep_then, 2.0, 30.0),
             functools.partial(_sleep_then, 3.0, 0.0)]
    t0 = time.monotonic()
    if workers == 1:  # one after the other here: a call started before the deadline runs to its end
        calls[2] = functools.partial(_sleep_then, 2.0, 0.0)
    ended = []
    out = run_forked(calls, workers=workers, deadline=t0 + 3.0, on_done=lambda j, timed: ended.append((j, timed)))
    assert time.monotonic() - t0 < 20
    assert [o.status for o in out] == ["done", "failed", "timeout" if workers == 2 else "done", "done"]
    assert sorted(j for j, _ in ended) == [0, 1, 2, 3] and all(timed is out[j] for j, timed in ended)  # each once
    assert out[0].value[0] == 1.0 and out[3].value[-1] == 3.0 and out[0].value.size == 200_000
    assert "ValueError: refused" in out[1].value


def test_run_forked_past_the_deadline_starts_nothing():
    out = run_forked([functools.partial(_sleep_then, 1.0, 0.0)], workers=2, deadline=time.monotonic() - 1)
    assert out[0].status == "timeout"


RING = "examples/ring_model.py"


@pytest.mark.slow
def test_auto_design_picks_a_certified_candidate_the_same_as_its_rule_designed_alone(tmp_path):
    from studies import schemas
    from studies.api import design

    auto = design(RING, seed=1, steps=40, validate=4, out=tmp_path / "auto")
    assert auto.certified and auto.outcome == "picked"
    c = auto.candidates[auto.pick_index]
    assert c.certified and c.in_budget
    eligible = [x for x in auto.candidates if x.eligible]
    assert c.predicted <= min(x.predicted for x in eligible) * (1 + TIE)
    assert {x.rule for x in auto.candidates} == {n for n, r in rules.all_rules().items() if r.deployable}
    alone = design(RING, mode=c.rule, seed=1, steps=40, **c.options)
    assert np.array_equal(alone.trace_bound, auto.pick.trace_bound, equal_nan=True)
    assert alone.verdict == auto.verdict
    files = {p.name for p in schemas.validate_output(tmp_path / "auto")}
    assert {"schedule.json", "candidates.json", "validation.json"} <= files
    val = json.loads((tmp_path / "auto" / "validation.json").read_text())
    assert val["runs"] == 4 and {"pick", "KCF", "HCMCI"} <= set(val["filters"])
    report = (tmp_path / "auto" / "report.md").read_text()
    assert "## Automatic design" in report and "## Validation" in report


@pytest.mark.slow
def test_auto_design_with_the_kcf_budget_sends_no_more_than_kcf(tmp_path):
    from studies.api import design
    from studies.scenarios import scenario_of

    auto = design(RING, seed=1, steps=40, validate=0, budget="kcf")
    kcf = scenario_of(RING).network.messages_per_step()
    assert auto.budget["messages_per_step"] == kcf
    assert all(x.in_budget == (x.messages <= kcf) for x in auto.candidates)
    if auto.pick is not None:
        assert auto.candidates[auto.pick_index].messages <= kcf


def test_auto_options_are_refused_with_a_rule_before_any_computation(tmp_path):
    from studies.api import design

    with pytest.raises(InputError, match="budget"):
        design(RING, mode="relay", budget=10, out=tmp_path / "d")
    assert not (tmp_path / "d").exists()
    with pytest.raises(InputError, match="budget"):
        design(RING, budget="none", out=tmp_path / "e")


def test_a_validation_that_cannot_fit_is_refused_before_any_candidate(tmp_path, monkeypatch):
    """The validation's memory (its consensus-robot runs) is checked before the candidates are designed: refused
    with the most runs that fit, nothing computed nor written."""
    from studies import auto, memory
    from studies.api import design
    from studies.scenarios import load_scenario

    sc = load_scenario(RING)
    need, limit = {}, float("inf")

    def check(n, available=None):  # the validation of more than 6 runs does not fit; everything else does
        if n.command.startswith("study consensus-robot"):
            need[n.command] = n.nbytes
            if n.nbytes > limit:
                raise InputError(f"{n.command} would need too much")

    monkeypatch.setattr(memory, "check", check)
    auto._check_validation(sc, DesignOptions(mode="relay"), 6)
    limit = max(need.values())
    monkeypatch.setattr(auto, "run_forked", lambda *a, **k: pytest.fail("a candidate was designed"))
    with pytest.raises(InputError, match=r"^--validate 20: the validation's .*; --validate 6 fits$"):
        design(RING, validate=20, out=tmp_path / "d")
    assert not (tmp_path / "d").exists()


@pytest.mark.slow
def test_a_value_the_user_gives_is_every_candidates_and_twins_are_tried_once():
    from studies.api import design

    auto = design(RING, seed=1, steps=20, validate=0, rounds=1, exchange="predictions")
    labels = [c.label for c in auto.candidates]
    assert len(labels) == len(set(labels))
    for c in auto.candidates:
        if c.rule in ("relay", "flood", "scheduled"):
            assert c.options.get("rounds") == 1 and c.rounds == 1, c.label
        if c.rule == "scheduled":
            assert c.options["exchange"] == "predictions" == c.exchange
    assert sum(c.rule == "scheduled" for c in auto.candidates) == 1


def test_better_than_the_nodes_alone_is_paired_over_the_same_runs():
    """studies.results.better_than: the runs' shared truth and attacks cancel in the paired ratio.  A filter whose
    error is 0.9 of the local EKFs' in every run, the runs' scales spread over two decades, is better (its ratio
    0.9 exactly, interval [0.9, 0.9]), though the two unpaired intervals overlap widely (the former test: no
    evidence); one whose ratio varies around 1 is not; a run lost where the nodes alone kept it makes it not better;
    the interval is the percentile bootstrap of the ratio (a second computation from the same draws)."""
    from studies.results import BOOTSTRAP, better_than, bootstrap_rmse_ci

    rng = np.random.default_rng(40)
    local = 10 ** rng.uniform(-1, 1, 20)  # each run's mean squared error
    mine = 0.81 * local  # RMSE 0.9 of theirs in every run
    got = better_than(mine, local, np.random.default_rng(1))
    assert got["better"] is True and got["ratio"] == pytest.approx(0.9) and got["runs"] == 20
    assert got["ratio_ci95"] == pytest.approx([0.9, 0.9])
    a = bootstrap_rmse_ci(mine, np.random.default_rng(2))
    b = bootstrap_rmse_ci(local, np.random.default_rng(3))
    assert a[1] > b[0]  # unpaired: the intervals overlap
    noisy = local * rng.lognormal(0.0, 0.3, 20)
    got = better_than(noisy, local, np.random.default_rng(4))
    idx = np.random.default_rng(4).integers(0, 20, size=(BOOTSTRAP, 20))
    want = np.percentile(np.sqrt(noisy[idx].mean(1) / local[idx].mean(1)), [2.5, 97.5])
    assert got["ratio_ci95"] == pytest.approx(list(want)) and got["better"] is bool(want[1] < 1)
    assert got["ratio_ci95"][0] < 1 < got["ratio_ci95"][1] and got["better"] is False
    lost = mine.copy()
    lost[3] = np.nan  # diverged where the nodes alone did not
    got = better_than(lost, local, np.random.default_rng(5))
    assert got["better"] is False and "diverged in 1 run" in got["reason"] and got["ratio_ci95"] is None
    from studies.results import local_ratio_text

    said = local_ratio_text({"better_than_local": False, "rmse_ratio_local": got["ratio"],
                             "rmse_ratio_local_ci95": None})
    assert "diverged" in said and "x" not in said.split("diverged")[0]  # not a ratio that would read as the reason
    theirs = local.copy()
    theirs[3] = np.nan  # the nodes alone diverged there: that run is left out
    assert better_than(lost, theirs, np.random.default_rng(5))["runs"] == 19
    assert better_than(mine[:1], local[:1], np.random.default_rng(6))["better"] is None


def test_the_validation_says_no_better_than_the_nodes_alone_with_the_paired_ratio():
    """The validation's lines and report say "no better than the nodes alone" with the pick's paired ratio and
    interval, from the study's better_than_local (the one definition), not from the point ratio."""
    from studies.reports.auto import validation_lines

    def val(ratio_ci, flag):
        return {"runs": 3, "seeds": "s", "pick_rmse_ratio": {"local EKF per node": 0.9},
                "filters": {"pick": {"filter": "relay", "rmse": 0.9, "rmse_ci95": [0.7, 1.1],
                                     "better_than_local": flag, "rmse_ratio_local": 0.9,
                                     "rmse_ratio_local_ci95": ratio_ci},
                            "local EKF per node": {"filter": "local EKF per node", "rmse": 1.0,
                                                   "rmse_ci95": [0.8, 1.2]}}}

    said = "\n".join(validation_lines(val([0.7, 1.1], False)))
    assert "no better than the nodes alone" in said and "0.9 x [0.7, 1.1]" in said  # ratio 0.9 < 1, yet no evidence
    said = "\n".join(validation_lines(val([0.8, 0.95], True)))
    assert "no better than the nodes alone" not in said
    from studies.cli import _validation_lines  # the command line's lines: the same words, with the ratio

    for ci, flag, words in (([0.7, 1.1], False, "no better than"), ([0.8, 0.95], True, "better than")):
        with contextlib.redirect_stdout(io.StringIO()) as out:
            _validation_lines(val(ci, flag))
        line = next(x for x in out.getvalue().splitlines() if ": relay:" in x)
        assert f"{words} the nodes alone (its RMSE over theirs on the same runs 0.9 x [{ci[0]:g}, {ci[1]:g}]" in line
        assert line.count("better than") == 1


def test_the_validation_runs_no_paper_design_and_its_memory_counts_one_bound():
    """The validation's consensus-robot runs leave the paper's design out (study option paper_reference: it is no
    reference of the automatic design), and the memory estimate counts one design's bounds instead of two."""
    from studies import auto
    from studies.memory import study_need
    from studies.pipeline import StudyOptions, run_study
    from studies.runner import Backend
    from studies.scenarios import load_scenario
    from studies.study_registry import get_study

    opts = DesignOptions(mode="relay")
    kw = dict(runs=2, seed=0, options=opts, quiet=True)
    lean = run_study("consensus-robot", [RING], **kw, **auto.VALIDATION_OPTIONS).results["filters"]
    full = run_study("consensus-robot", [RING], **kw).results["filters"]
    paper = [n for n in full if n.startswith("consensus-EKF (paper")]
    assert paper and not any(n in lean for n in paper)
    assert set(lean) == set(full) - set(paper)
    for name in lean:  # the same runs: the others' numbers unchanged
        assert lean[name]["rmse_state"] == full[name]["rmse_state"], name
    sc, study = load_scenario(RING), get_study("consensus-robot")

    def need(extra):
        so = StudyOptions(20, None, 0, 20, Backend(), opts, dict(study.options, **extra))
        return study_need("consensus-robot", sc, so).nbytes

    assert need(auto.VALIDATION_OPTIONS) < need({})


def test_the_default_validation_is_cut_on_a_large_network_by_its_rows_and_says_how_to_run_the_rest():
    """default_validation: 20 runs while N n x 20 stays within VALIDATE_ROWS, then VALIDATE_ROWS // (N n) runs, never
    fewer than VALIDATE_MIN_RUNS, with a message naming the runs, the rows and --validate 20; check_auto takes it as
    the default and keeps runs the user gave."""
    from types import SimpleNamespace

    from studies.auto import VALIDATE_MIN_RUNS, VALIDATE_ROWS, VALIDATE_RUNS, check_auto, default_validation

    def ring(n):
        return SensorNetwork.from_edges(n, [(i, (i + 1) % n) for i in range(n)])

    assert default_validation(ring(64), 64) == (VALIDATE_RUNS, None)  # the 64-cell field keeps its 20
    for nodes, n_x in ((65, 64), (100, 100), (118, 117), (400, 400)):
        runs, why = default_validation(ring(nodes), n_x)
        assert runs == max(VALIDATE_MIN_RUNS, VALIDATE_ROWS // (nodes * n_x)) < VALIDATE_RUNS
        assert f"validated on {runs} fresh runs" in why and f"{nodes * n_x} node-state rows" in why
        assert f"--validate {VALIDATE_RUNS}" in why
        sc = SimpleNamespace(network=ring(nodes), model=SimpleNamespace(n_x=n_x))
        assert check_auto(sc)[2] == runs and check_auto(sc, validate=VALIDATE_RUNS)[2] == VALIDATE_RUNS
    assert default_validation(ring(118), 117)[0] == 5


def test_the_validation_report_with_regions_shows_the_region_rmse_its_ratios_are_of():
    """With regions the validation's ratios are of each node's region RMSE (studies.auto.validation): the report's
    table shows that column beside the whole-state one, says the ratios are on the regions, and says why a pick whose
    nodes carry their regions has no whole-state RMSE; without regions neither appears."""
    from studies.reports.auto import validation_lines

    rows = {"pick": {"filter": "flood", "rmse": None, "rmse_region": 0.0008, "rmse_region_ci95": [0.0007, 0.0009]},
            "KCF": {"filter": "KCF", "rmse": 0.21, "mse": 0.044, "rmse_region": 0.0023}}
    said = "\n".join(validation_lines({"runs": 5, "seeds": "s", "filters": rows,
                                       "pick_rmse_ratio": {"KCF": 0.0008 / 0.0023}}))
    assert "| RMSE on each node's region | RMSE, whole state |" in said
    assert "| KCF | 0.0023 | 0.21 | 0.044 |" in said and "| flood (pick) | 0.0008 | — | — |" in said
    assert "RMSE on each node's region on these runs is 0.348 x KCF's" in said
    assert "no whole-state RMSE" in said
    plain = {"pick": {"filter": "relay", "rmse": 0.9}, "KCF": {"filter": "KCF", "rmse": 1.8}}
    said = "\n".join(validation_lines({"runs": 5, "seeds": "s", "filters": plain, "pick_rmse_ratio": {"KCF": 0.5}}))
    assert "region" not in said and "| filter | RMSE | mean squared error |" in said
    assert "The design's RMSE on these runs is 0.5 x KCF's" in said
