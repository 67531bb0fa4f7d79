"""Gain rules (designer.gain_rules): the registry of design modes, what each needs at run time, and where it goes
(designer.design.MODES, the mode errors, the command line, schedule.json, the design report, the API)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from designer.design import MODES, DesignOptions
from designer.gain_rules import (DEPLOYABLE, FILTER_RUNTIMES, GAIN_RULES, RUNTIMES, GainRule, gain_rule, register,
                                 unregister)
from designer.schedule import load_schedule
from designer.validation import InputError
from studies import api, schemas
from studies.cli import main
from studies.reports.design import render_design

LINEAR = str(Path(__file__).resolve().parents[1] / "examples" / "linear_network_model.py")


@pytest.fixture
def dummy():
    """A rule registered for one test, removed afterwards whatever the test does."""
    rule = register(GainRule("dummy-rule", "scheduled", needs="the step and which neighbour packets arrived.",
                             summary="a rule of the tests"))
    try:
        yield rule
    finally:
        if rule.name in GAIN_RULES:
            unregister(rule.name)


@pytest.fixture(scope="module")
def designs(tmp_path_factory):
    """Short designs of the small linear model, written with their reports: the oracle (mse) and a local rule."""
    out = {}
    for mode in ("mse", "tuned"):
        d = tmp_path_factory.mktemp(mode)
        out[mode] = (d, api.design(LINEAR, mode=mode, seed=2, steps=6, out=d))
    return out


def test_the_built_in_rules_and_their_run_time():
    assert list(GAIN_RULES)[:3] == ["paper", "tuned", "mse"]  # the built-in rules first (more may follow)
    assert MODES == tuple(GAIN_RULES)
    assert set(RUNTIMES) == {"local", "scheduled", "global"} and set(FILTER_RUNTIMES) == {*RUNTIMES, "centralized"}
    for name, rule in GAIN_RULES.items():
        assert gain_rule(name) is rule and rule.name == name
        assert rule.deployable == (rule.runtime != "global") == (rule.runtime in DEPLOYABLE)
        assert rule.describe() == {"name": name, "runtime": rule.runtime, "needs": rule.needs,
                                   "deployable": rule.deployable}
        assert (rule.caveat is None) == rule.deployable
    assert [GAIN_RULES[n].runtime for n in ("paper", "tuned", "mse")] == ["local", "local", "global"]
    assert "oracle" in gain_rule("mse").label and "not deployable" in gain_rule("mse").label
    assert "central computer" in gain_rule("mse").needs and "joint" in gain_rule("mse").caveat
    with pytest.raises(TypeError):  # a registered rule cannot be changed behind the registry's back
        GAIN_RULES["mse"] = gain_rule("paper")  # type: ignore[index]


def test_the_schemas_describe_the_same_run_time_classes():
    """The JSON Schemas are read by other tools: their run-time classes are the registry's."""
    rule = schemas.load("schedule")["properties"]["gain_rule"]["properties"]
    assert rule["runtime"]["enum"] == list(RUNTIMES)
    metrics = schemas.load("study")["$defs"]["metrics"]["properties"]
    assert metrics["runtime"]["enum"] == list(FILTER_RUNTIMES)


@pytest.mark.parametrize("call", [lambda: gain_rule("bogus"), lambda: DesignOptions(mode="bogus")])
def test_an_unknown_mode_names_the_parameter_and_every_rule(call):
    with pytest.raises(InputError) as err:
        call()
    message = str(err.value)
    assert message.startswith("mode must be ") and message.endswith("got 'bogus'")
    assert all(repr(n) in message for n in GAIN_RULES)


def test_the_command_line_offers_the_registered_rules(capsys):
    assert main(["design", "indoor-robot", "--mode", "bogus", "--out", "/nonexistent/never-written"]) == 2
    err = capsys.readouterr().err
    assert "--mode" in err and all(n in err for n in GAIN_RULES)
    assert not Path("/nonexistent/never-written").exists()
    assert main(["design", "--help"]) == 0
    helptext = " ".join(capsys.readouterr().out.split())
    for rule in GAIN_RULES.values():
        assert f"{rule.name}: {' '.join(rule.summary.split())} [{rule.runtime}:" in helptext


def test_a_registered_rule_is_known_everywhere_it_is_looked_up_and_leaves(dummy):
    assert list(GAIN_RULES)[-1] == "dummy-rule" and gain_rule("dummy-rule") is dummy
    assert DesignOptions(mode="dummy-rule").mode == "dummy-rule"
    with pytest.raises(InputError, match="'dummy-rule', got 'bogus'"):
        gain_rule("bogus")
    with pytest.raises(InputError, match="registered already"):
        register(GainRule("dummy-rule", "local", needs="x", summary="y"))
    assert dummy.deployable and dummy.caveat is None
    before = dict(GAIN_RULES)
    assert unregister("dummy-rule") is dummy
    assert "dummy-rule" not in GAIN_RULES and dict(GAIN_RULES) == {n: r for n, r in before.items() if r is not dummy}
    with pytest.raises(InputError, match="got 'dummy-rule'") as err:
        DesignOptions(mode="dummy-rule")
    assert "'dummy-rule'" not in str(err.value).rsplit(", got", 1)[0] and "'mse'" in str(err.value)


def test_a_new_rule_is_one_object_and_its_filter_and_the_code_asks_the_rule():
    """A rule registered with the paper's capabilities (fixed σ, β, τ) and the paper's filter under its own name is
    designed, run and checked as the paper's, with nothing compared against the name 'paper': the batch dispatches on
    the filter registry, the options keep its σ, the first step refuses a σ beyond (28); a rule without a filter is
    refused by name; what only a rule with offline tables takes is refused for it."""
    import numpy as np

    from filters.consensus import run_consensus
    from filters.consensus_batch import register_filter, rule_filter, rule_filters, run_consensus_batch, \
        unregister_filter
    from studies.consensus_design import as_mode, check_first_step, consensus_design
    from studies.scenarios import load_scenario

    rule = register(GainRule("fixed-copy", "local", needs="what the paper's nodes need.", summary="the paper's gains",
                             fixed_multipliers=True))
    try:
        with pytest.raises(InputError, match="no filter applies gain rule 'fixed-copy'"):
            rule_filter("fixed-copy")
        assert set(rule_filters()) == set(GAIN_RULES) - {"fixed-copy"}  # every other rule has its filter
        register_filter("fixed-copy", rule_filter("paper"))
        sc = load_scenario("indoor-robot", {"steps": 4})
        assert as_mode(DesignOptions(sigma=0.05), "fixed-copy").sigma == 0.05  # the user's σ is kept
        with pytest.raises(InputError, match="exchange 'measurements' is a design of mode 'scheduled'"):
            DesignOptions(mode="fixed-copy", exchange="measurements")
        mine, paper = (consensus_design(sc, as_mode(None, m)) for m in ("fixed-copy", "paper"))
        assert mine.epsilon == paper.epsilon and mine.sigma == paper.sigma
        traj = sc.simulate(np.random.default_rng(1), 4, batch=2)
        a = run_consensus_batch(sc.model, sc.network, traj.z, mine, inputs=traj.inputs)
        b = run_consensus_batch(sc.model, sc.network, traj.z, paper, inputs=traj.inputs)
        np.testing.assert_array_equal(a.x_post, b.x_post)
        np.testing.assert_array_equal(a.phi_post, b.phi_post)
        assert a.violations == b.violations
        big = mine._replace(sigma=1e5)
        with pytest.raises(InputError, match="sigma must satisfy"):
            run_consensus(sc.model, sc.network, traj.z[0], big, inputs=traj.inputs)
        assert "sigma must satisfy" in check_first_step(sc, big, "mine")
        # the same rule choosing its own multipliers: no first-step refusal, σ dropped from the options
        unregister_filter("fixed-copy")
        unregister("fixed-copy")
        rule = register(GainRule("fixed-copy", "local", needs="x.", summary="y"))
        register_filter("fixed-copy", rule_filter("tuned"))
        assert as_mode(DesignOptions(sigma=0.05), "fixed-copy").sigma is None
        assert check_first_step(sc, big._replace(mode="fixed-copy"), "mine") is None
        with pytest.raises(InputError, match="sigma is chosen by the design in mode 'fixed-copy'"):
            DesignOptions(mode="fixed-copy", sigma=0.1)
        assert consensus_design(sc, as_mode(None, "fixed-copy")).epsilon != paper.epsilon  # ε of a rule that tunes
    finally:
        if "fixed-copy" in rule_filters():
            unregister_filter("fixed-copy")
        if rule.name in GAIN_RULES:
            unregister(rule.name)


@pytest.mark.parametrize("kwargs, match", [
    (dict(name="Bad Name", runtime="local"), "gain rule name must be"),
    (dict(name="ok", runtime="centralized"), r"runtime of gain rule 'ok' must be 'local', 'scheduled' or 'global'"),
    (dict(name="ok", runtime="local", needs=" "), "needs of gain rule 'ok' must be a non-empty sentence"),
])
def test_a_malformed_rule_is_refused(kwargs, match):
    before = dict(GAIN_RULES)
    with pytest.raises(InputError, match=match):
        GainRule(**{"needs": "its measurement", "summary": "a rule", **kwargs})
    assert dict(GAIN_RULES) == before


def test_schedule_json_records_the_gain_rule_and_round_trips(designs, tmp_path):
    for mode, (d, res) in designs.items():
        written = json.loads((d / "schedule.json").read_text())
        assert written["gain_rule"] == gain_rule(mode).describe() == res.gain_rule.describe()
        assert schemas.validate_output(d) == [d / "schedule.json"]
        again = load_schedule(d)
        assert again.gain_rule is gain_rule(mode) and again.to_json() == written
    # a file written before the gain rules declared their run time loads, and is written again with its rule
    old = tmp_path / "old"
    shutil.copytree(designs["mse"][0], old)
    record = json.loads((old / "schedule.json").read_text())
    record.pop("gain_rule")
    (old / "schedule.json").write_text(json.dumps(record))
    schemas.validate_output(old / "schedule.json")
    sch = load_schedule(old)
    assert sch.gain_rule.runtime == "global" and "gain_rule" not in sch.meta
    assert sch.to_json()["gain_rule"] == gain_rule("mse").describe()


@pytest.mark.parametrize("change, load_error, schema_error", [
    (lambda r: r["gain_rule"].update(runtime="local", deployable=True), "is not that of mode 'mse'",
     r"\$\.gain_rule\.runtime: 'local', but gain rule 'mse' has 'global'"),
    (lambda r: r["gain_rule"].update(deployable=True), None, r"\$\.gain_rule\.deployable: False was expected"),
    (lambda r: r.update(mode="bogus"), "mode of schedule .* must be 'paper', 'tuned'.* 'mse'.*, got 'bogus'",
     r"\$\.mode: 'bogus' is not a registered gain rule"),
])
def test_a_schedule_whose_rule_contradicts_the_registry_is_refused(designs, tmp_path, change, load_error,
                                                                   schema_error):
    d = tmp_path / "d"
    shutil.copytree(designs["mse"][0], d)
    record = json.loads((d / "schedule.json").read_text())
    change(record)
    (d / "schedule.json").write_text(json.dumps(record))
    if load_error is not None:
        with pytest.raises(InputError, match=load_error):
            load_schedule(d)
    with pytest.raises(InputError, match=schema_error):
        schemas.validate_output(d / "schedule.json")


def _head(md: str) -> str:
    """The report's first lines: everything before its summary."""
    return md.split("\n## Summary\n", 1)[0]


def test_the_design_report_opens_with_the_run_time_class(designs):
    oracle = _head((designs["mse"][0] / "report.md").read_text())
    assert "run time global" in oracle and "an oracle" in oracle and "not a design to deploy" in oracle
    assert "central computer" in oracle and "deployable on the nodes" not in oracle
    local = _head((designs["tuned"][0] / "report.md").read_text())
    assert "run time local: deployable on the nodes" in local and "oracle" not in local
    assert gain_rule("tuned").needs.rstrip(".") in local.replace("\\", "")
    # a schedule written before the field existed: the words come from the registry's rule of its mode
    record = json.loads((designs["mse"][0] / "schedule.json").read_text())
    record.pop("gain_rule")
    assert _head(render_design(record)) == oracle
    record["mode"] = "unknown-mode"  # neither a record nor a registered rule: no run-time words, no crash
    assert "run time" not in _head(render_design(record))


def test_the_design_summary_and_the_api_name_the_gain_rule(designs, tmp_path, capsys):
    assert main(["design", LINEAR, "--mode", "mse", "--seed", "2", "--steps", "6", "--out", str(tmp_path / "d")]) == 0
    out = capsys.readouterr().out
    first = out.splitlines()[0]
    assert "gain rule: mse (global: an oracle, not deployable)" in first
    assert "oracle" in out.splitlines()[-1]  # the verdict line says the certified design is a reference
    res = designs["mse"][1]
    assert res.gain_rule is gain_rule("mse") and not res.gain_rule.deployable
    assert designs["tuned"][1].gain_rule.runtime == "local" and "oracle" not in designs["tuned"][1].verdict_line()


@pytest.mark.slow
def test_consensus_robot_records_each_filters_run_time_and_never_picks_a_reference(tmp_path):
    """The mse design (a global oracle) and the fusion centre are references; a replayed schedule is applied by
    the step alone (scheduled), whatever rule made it; the pick is a filter the nodes can run."""
    sched = tmp_path / "design"
    api.design(LINEAR, mode="mse", seed=1, out=sched)
    out = tmp_path / "study"
    res = api.study("consensus-robot", LINEAR, out=out, runs=2, mode="mse", schedule=str(sched)).results
    runtimes = {n: f["runtime"] for n, f in res["filters"].items()}
    assert runtimes == {"consensus-EKF (mse)": "global", "consensus-EKF (paper, tau=0.01)": "local", "KCF": "local",
                        "HCMCI": "local", "local EKF per node": "local", "centralized EKF (all sensors)": "centralized",
                        "consensus-EKF (replayed mse schedule)": "scheduled"}
    pick = next(ln for ln in (out / "report.md").read_text().splitlines() if ln.startswith("**Which to pick"))
    picked = pick.partition("; for reference, ")[0]
    assert not any(n in picked for n, r in runtimes.items() if r in ("global", "centralized"))
