"""Gain rules (rules/, designer.rule): one package per rule behind one interface, what each needs at run time, and
where it goes (the registry, the mode errors, the command line, schedule.json, the design report, the API); a rule
added as one package, kept outside the repository, runs through the commands."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import rules
from designer.design import DesignOptions
from designer.rule import DEPLOYABLE, FILTER_RUNTIMES, RUNTIMES, GainRule
from designer.schedule import load_schedule
from designer.validation import InputError
from studies import api, schemas
from studies.cli import main
from studies.reports.design import render_design

ROOT = Path(__file__).resolve().parents[1]
LINEAR = str(ROOT / "examples" / "linear_network_model.py")
BUILT_IN = ("paper", "tuned", "mse", "scheduled", "relay", "flood")

# A rule kept outside the repository: the paper's filter under another name, as its package would hold it.
FIXED_COPY = '''
"""A rule of the tests: the paper's gains (fixed multipliers, C = tau Phi, the gain (30)) under its own name."""
from designer.rule import GainRule


class FixedCopy(GainRule):
    name = "fixed_copy"
    runtime = "local"
    needs = "what the paper's nodes need."
    summary = "the paper's gains, kept outside the repository"
    fixed_multipliers = True

    def batch_filter(self):
        from rules.paper.filter import STEPS  # a rule may build on another's steps

        return STEPS

    def node_filter(self):
        from filters.consensus_node import ConsensusNetwork, ConsensusNode

        return ConsensusNode, ConsensusNetwork


RULE = FixedCopy()
'''
# The tuned steps under another name: a rule that chooses its own multipliers.
TUNED_COPY = FIXED_COPY.replace("FixedCopy", "TunedCopy").replace('"fixed_copy"', '"tuned_copy"').replace(
    "    fixed_multipliers = True\n", "").replace("rules.paper.filter", "rules.tuned.filter")


@pytest.fixture
def extra_rules(tmp_path):
    """A folder of two rule packages, searched for the test's duration."""
    folder = tmp_path / "my_rules"
    for name, text in (("fixed_copy", FIXED_COPY), ("tuned_copy", TUNED_COPY)):
        (folder / name).mkdir(parents=True)
        (folder / name / "__init__.py").write_text(textwrap.dedent(text))
    rules.add_path(folder)
    try:
        yield folder
    finally:
        rules.remove_path(folder)


@pytest.fixture(scope="module")
def designs(tmp_path_factory):
    """Short designs of the small linear model, written with their reports: the oracle (mse) and a local rule."""
    out = {}
    for mode in ("mse", "tuned"):
        d = tmp_path_factory.mktemp(mode)
        out[mode] = (d, api.design(LINEAR, mode=mode, seed=2, steps=6, out=d))
    return out


def test_the_built_in_rules_and_their_run_time():
    assert rules.names() == BUILT_IN and list(rules.all_rules()) == list(BUILT_IN)
    assert set(RUNTIMES) == {"local", "scheduled", "global"} and set(FILTER_RUNTIMES) == {*RUNTIMES, "centralized"}
    for name, rule in rules.all_rules().items():
        assert rules.get(name) is rule and rule.name == name and isinstance(rule, GainRule)
        assert rule.deployable == (rule.runtime != "global") == (rule.runtime in DEPLOYABLE)
        assert rule.describe() == {"name": name, "runtime": rule.runtime, "needs": rule.needs,
                                   "deployable": rule.deployable}
        assert (rule.caveat is None) == rule.deployable
        assert rule.has_node_filter == rule.deployable  # every rule a node can run has its node filter
    assert [rules.get(n).runtime for n in ("paper", "tuned", "mse")] == ["local", "local", "global"]
    assert "oracle" in rules.get("mse").label and "not deployable" in rules.get("mse").label
    assert "central computer" in rules.get("mse").needs and "joint" in rules.get("mse").caveat
    with pytest.raises(AttributeError):  # a rule's metadata are its class's
        rules.get("mse").runtime = "local"  # type: ignore[misc]
    assert rules.get("flood") != rules.get("relay") and rules.get("flood").routing == "flood"


def test_a_rule_gives_its_c_export_or_says_why_it_has_none():
    """GainRule.c_export: the rules whose node filter is exported give their NodeExport (flood the relay rule's, which
    it builds on); the others an InputError saying why (an oracle; the tuned rule's convex problem online; a rule
    without one)."""
    from designer.export_c import NodeExport
    from rules.relay.export_c import RelayExport

    exporting = [name for name, rule in rules.all_rules().items() if rule.exports_c]
    assert exporting == ["paper", "scheduled", "relay", "flood"]
    assert all(isinstance(rules.get(name).c_export(), NodeExport) for name in exporting)
    assert type(rules.get("flood").c_export()) is type(rules.get("relay").c_export()) is RelayExport
    with pytest.raises(InputError, match="^gain rule 'mse' cannot be exported to C: an oracle: its gains need the "
                                         "network's joint state$"):
        rules.get("mse").c_export()
    with pytest.raises(InputError, match="^gain rule 'tuned' cannot be exported to C: its node solves a convex "
                                         "problem online at every step"):
        rules.get("tuned").c_export()

    class Plain(GainRule):
        name = "plain"
        runtime = "local"
        needs = "its own measurement."
        summary = "a rule without a C export"

    assert not Plain().exports_c
    with pytest.raises(InputError, match="^gain rule 'plain' cannot be exported to C: its node filter has no C "
                                         "export"):
        Plain().c_export()


def test_the_registry_finds_the_rules_without_importing_them():
    """Listing the rules imports none of them (the command line's start-up); asking for one imports it alone."""
    code = ("import sys, rules; n = rules.names(); before = sorted(m for m in sys.modules if m.startswith('rules.'));"
            "rules.get('relay'); after = sorted(m for m in sys.modules if m.startswith('rules.')); "
            "print(n, before, after)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT).stdout
    assert out.strip() == f"{BUILT_IN} [] ['rules.relay']"


def test_the_schemas_describe_the_same_run_time_classes():
    """The JSON Schemas are read by other tools: their run-time classes are the interface's."""
    rule = schemas.load("schedule")["properties"]["gain_rule"]["properties"]
    assert rule["runtime"]["enum"] == list(RUNTIMES)
    metrics = schemas.load("study")["$defs"]["metrics"]["properties"]
    assert metrics["runtime"]["enum"] == list(FILTER_RUNTIMES)


@pytest.mark.parametrize("call", [lambda: rules.get("bogus"), lambda: api.design(LINEAR, mode="bogus", steps=3)])
def test_an_unknown_mode_names_the_parameter_and_every_rule(call):
    with pytest.raises(InputError) as err:
        call()
    message = str(err.value)
    assert message.startswith("mode must be ") and message.endswith("got 'bogus'")
    assert all(repr(n) in message for n in BUILT_IN)


def test_a_mode_that_cannot_name_a_package_is_refused_when_given():
    with pytest.raises(InputError, match="mode must be the name of a gain rule"):
        DesignOptions(mode="Fixed Copy")


def test_the_command_line_offers_the_rules(capsys):
    assert main(["design", "indoor-robot", "--mode", "bogus", "--out", "/nonexistent/never-written"]) == 2
    err = capsys.readouterr().err
    assert "--mode" in err and all(n in err for n in BUILT_IN)
    assert not Path("/nonexistent/never-written").exists()
    assert main(["design", "--help"]) == 0
    helptext = " ".join(capsys.readouterr().out.split())
    for rule in rules.all_rules().values():
        assert f"{rule.name}: {' '.join(rule.summary.split())} [{rule.runtime}:" in helptext


def test_a_rule_added_as_one_package_is_designed_run_and_checked_as_its_capabilities_say(extra_rules):
    """A rule with the paper's capabilities (fixed σ, β, τ) and the paper's steps, in a package outside the
    repository, is designed, run and checked as the paper's, with nothing compared against the name 'paper': the
    batch dispatches on the design's rule, the options keep its σ, the first step refuses a σ beyond (28); the same
    steps in a rule that chooses its multipliers drop the σ and never refuse the first step."""
    from filters.consensus import run_consensus
    from filters.consensus_batch import run_consensus_batch
    from studies.consensus_design import check_first_step, consensus_design
    from studies.design_options import as_mode
    from studies.scenarios import load_scenario

    assert rules.names() == BUILT_IN + ("fixed_copy", "tuned_copy")
    mine = rules.get("fixed_copy")
    assert mine.name == "fixed_copy" and mine.deployable and mine.caveat is None and mine.has_node_filter
    sc = load_scenario("indoor-robot", {"steps": 4})
    assert as_mode(DesignOptions(sigma=0.05), "fixed_copy").sigma == 0.05  # the user's σ is kept
    with pytest.raises(InputError, match="exchange 'measurements' is a design of a rule of offline tables"):
        mine.check_options(DesignOptions(mode="fixed_copy", exchange="measurements"))
    copy, paper = (consensus_design(sc, as_mode(None, m)) for m in ("fixed_copy", "paper"))
    assert copy.rule is mine and copy.epsilon == paper.epsilon and copy.sigma == paper.sigma
    traj = sc.simulate(np.random.default_rng(1), 4, batch=2)
    a = run_consensus_batch(sc.model, sc.network, traj.z, copy, inputs=traj.inputs).detail
    b = run_consensus_batch(sc.model, sc.network, traj.z, paper, inputs=traj.inputs).detail
    np.testing.assert_array_equal(a.x_post, b.x_post)
    np.testing.assert_array_equal(a.phi_post, b.phi_post)
    assert a.violations == b.violations
    big = copy._replace(sigma=1e5)
    with pytest.raises(InputError, match="sigma must satisfy"):
        run_consensus(sc.model, sc.network, traj.z[0], big, inputs=traj.inputs)
    assert "sigma must satisfy" in check_first_step(sc, big, "mine")
    # the same steps in a rule that chooses its own multipliers: σ dropped from the options, no first-step refusal
    tuned = rules.get("tuned_copy")
    assert as_mode(DesignOptions(sigma=0.05), "tuned_copy").sigma is None
    assert check_first_step(sc, big._replace(rule=tuned), "mine") is None
    with pytest.raises(InputError, match="sigma is chosen by the design in mode 'tuned_copy'"):
        tuned.check_options(DesignOptions(mode="tuned_copy", sigma=0.1))
    assert consensus_design(sc, as_mode(None, "tuned_copy")).epsilon != paper.epsilon  # ε of a rule that tunes


@pytest.mark.slow
def test_a_rule_kept_outside_the_repository_runs_through_the_commands(extra_rules, tmp_path):
    """``CFDESIGN_RULE_PATH`` names the folder for every cfdesign process: the rule is a --mode of the command
    line, designs, writes its report and is driven as node filters, its numbers the paper's."""
    env = {**os.environ, rules.ENV_PATH: str(extra_rules), "MPLBACKEND": "Agg"}

    def cfdesign(*args):
        return subprocess.run([sys.executable, "-m", "studies", *args], capture_output=True, text=True, env=env,
                              cwd=tmp_path)

    helped = cfdesign("design", "--help")
    assert helped.returncode == 0 and "fixed_copy: the paper's gains, kept outside the repository" in \
        " ".join(helped.stdout.split())
    for mode in ("fixed_copy", "paper"):
        done = cfdesign("design", LINEAR, "--mode", mode, "--steps", "5", "--seed", "3", "--out", mode)
        assert done.returncode in (0, 1), done.stderr  # written: certified or not, the same verdict for both
    mine, paper = (json.loads((tmp_path / m / "schedule.json").read_text()) for m in ("fixed_copy", "paper"))
    assert mine["mode"] == "fixed_copy" and mine["gain_rule"]["name"] == "fixed_copy"
    assert mine["trace_bound"] == paper["trace_bound"] and mine["verdict"] == paper["verdict"]
    assert "Gain rule fixed_copy, run time local" in (tmp_path / "fixed_copy" / "report.md").read_text()
    # a recorded run filtered by its design, and the comparison with its filter beside the paper's
    assert cfdesign("simulate", LINEAR, "--steps", "5", "--seed", "4", "--out", "run.npz").returncode == 0
    ran = cfdesign("filter", LINEAR, "--data", "run.npz", "--schedule", "fixed_copy", "--out", "filtered")
    assert ran.returncode == 0, ran.stderr
    ref = cfdesign("filter", LINEAR, "--data", "run.npz", "--schedule", "paper", "--out", "filtered-paper")
    assert ref.returncode == 0, ref.stderr
    with np.load(tmp_path / "filtered" / "estimates.npz") as a, \
            np.load(tmp_path / "filtered-paper" / "estimates.npz") as b:
        numeric = [k for k in a.files if a[k].dtype.kind in "fiub"]
        assert sorted(a.files) == sorted(b.files) and "x_hat" in numeric
        assert all(np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f") for k in numeric)
    study = cfdesign("study", "comparison", LINEAR, "--runs", "2", "--particles", "20", "--quiet",
                     "--out", "compare")
    assert study.returncode == 0, study.stderr
    res = json.loads((tmp_path / "compare" / "results.json").read_text())
    rows = {name.split(": ", 1)[-1]: f for name, f in res["filters"].items()}
    mine, paper = rows["consensus EKF (fixed_copy design)"], rows["consensus EKF (paper design)"]
    assert mine["runtime"] == "local" and mine["rmse"] == paper["rmse"] and np.isfinite(mine["rmse"]).all()
    assert "consensus EKF (fixed\\_copy design)" in (tmp_path / "compare" / "report.md").read_text() or \
        "consensus EKF (fixed_copy design)" in (tmp_path / "compare" / "report.md").read_text()
    # in this process (the fixture added the folder): the node filters of its design are the paper's, bit for bit
    nodes = api.node_filter(LINEAR, schedule=str(tmp_path / "fixed_copy"))
    ref = api.node_filter(LINEAR, schedule=str(tmp_path / "paper"))
    sim = api.simulate(LINEAR, seed=5, steps=5)
    (xa, Pa), (xb, Pb) = nodes.run(sim.z, sim.attacks, sim.inputs), ref.run(sim.z, sim.attacks, sim.inputs)
    np.testing.assert_array_equal(xa, xb)
    np.testing.assert_array_equal(Pa, Pb)
    assert np.isfinite(xa).all()


@pytest.mark.parametrize("body, match", [
    ('name = "Bad Name"\n    runtime = "local"', "gain rule name must be"),
    ('name = "ok"\n    runtime = "centralized"', r"runtime of gain rule 'ok' must be 'local', 'scheduled' or 'global'"),
    ('name = "ok"\n    runtime = "local"\n    needs = " "', "needs of gain rule 'ok' must be a non-empty sentence"),
])
def test_a_malformed_rule_is_refused_when_its_class_is_defined(body, match):
    text = f'class Bad(GainRule):\n    needs = "its measurement"\n    summary = "a rule"\n    {body}\n'
    with pytest.raises(InputError, match=match):
        exec(text, {"GainRule": GainRule})


def test_a_rule_package_must_hold_its_rule(tmp_path):
    folder = tmp_path / "broken"
    (folder / "no_rule").mkdir(parents=True)
    (folder / "no_rule" / "__init__.py").write_text("X = 1\n")
    (folder / "other_name").mkdir()
    (folder / "other_name" / "__init__.py").write_text("from rules.paper import RULE\n")
    with pytest.raises(InputError, match="rule path must be an existing folder"):
        rules.add_path(tmp_path / "missing")
    rules.add_path(folder)
    try:
        for name in ("no_rule", "other_name"):
            with pytest.raises(InputError, match=f"rule package 'rules.{name}' must define RULE, a GainRule named"):
                rules.get(name)
    finally:
        rules.remove_path(folder)
    assert rules.names() == BUILT_IN


def test_schedule_json_records_the_gain_rule_and_round_trips(designs, tmp_path):
    for mode, (d, res) in designs.items():
        written = json.loads((d / "schedule.json").read_text())
        assert written["gain_rule"] == rules.get(mode).describe() == res.gain_rule.describe()
        assert schemas.validate_output(d) == [d / "schedule.json"]
        again = load_schedule(d, rules.get)
        assert again.rule is rules.get(mode) and again.to_json() == written
    # a file written before the gain rules declared their run time loads, and is written again with its rule
    old = tmp_path / "old"
    shutil.copytree(designs["mse"][0], old)
    record = json.loads((old / "schedule.json").read_text())
    record.pop("gain_rule")
    (old / "schedule.json").write_text(json.dumps(record))
    schemas.validate_output(old / "schedule.json")
    sch = load_schedule(old, rules.get)
    assert sch.rule.runtime == "global" and "gain_rule" not in sch.meta
    assert sch.to_json()["gain_rule"] == rules.get("mse").describe()


@pytest.mark.parametrize("change, load_error, schema_error", [
    (lambda r: r["gain_rule"].update(runtime="local", deployable=True), "is not that of mode 'mse'",
     r"\$\.gain_rule\.runtime: 'local', but gain rule 'mse' has 'global'"),
    (lambda r: r["gain_rule"].update(deployable=True), None, r"\$\.gain_rule\.deployable: False was expected"),
    (lambda r: r.update(mode="bogus"), "mode of schedule .* must be 'paper', 'tuned'.* 'mse'.*, got 'bogus'",
     r"\$\.mode: 'bogus' is not a gain rule"),
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
            load_schedule(d, rules.get)
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
    assert rules.get("tuned").needs.rstrip(".") in local.replace("\\", "")
    # a schedule written before the field existed: the words come from the rule of its mode
    record = json.loads((designs["mse"][0] / "schedule.json").read_text())
    record.pop("gain_rule")
    assert _head(render_design(record)) == oracle
    record["mode"] = "unknown_mode"  # neither a record nor a rule: no run-time words, no crash
    assert "run time" not in _head(render_design(record))


def test_the_design_summary_and_the_api_name_the_gain_rule(designs, tmp_path, capsys):
    assert main(["design", LINEAR, "--mode", "mse", "--seed", "2", "--steps", "6", "--out", str(tmp_path / "d")]) == 0
    out = capsys.readouterr().out
    first = out.splitlines()[0]
    assert "gain rule: mse (global: an oracle, not deployable)" in first
    assert "oracle" in out.splitlines()[-1]  # the verdict line says the certified design is a reference
    res = designs["mse"][1]
    assert res.gain_rule is rules.get("mse") and not res.gain_rule.deployable
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
