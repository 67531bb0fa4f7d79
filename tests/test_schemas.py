"""Every writer validated against the JSON Schemas shipped in the package (studies/schemas).

The commands run at tiny sizes: ``cfdesign design`` (a feasible and an infeasible design),
``cfdesign feasibility`` (a 1-D and a 2-D grid), every study of ``studies.study_registry.STUDIES``
through ``studies.api.study`` and the comparison on a user's model file; each file they write
(results.json, schedule.json, feasibility.csv row by row, feasibility.json) is validated.
Negative controls show that the schemas reject what breaks the contract and name the path.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from importlib import resources
from pathlib import Path

import jsonschema
import pytest

from designer.validation import InputError
from studies import api, schemas
from studies.cli import main
from studies.study_registry import STUDIES, get_study
from test_api import MODEL  # the user's model of the API tests (a damped oscillator on a ring of four sensors)

ROOT = Path(__file__).resolve().parents[1]
LINEAR = str(ROOT / "examples" / "linear_network_model.py")
PARTICLES = 40


def _raises_at(pattern: str):
    return pytest.raises(InputError, match=pattern)


# ---------------------------------------------------------------------------------------------- the schema files
@pytest.mark.parametrize("name", list(schemas.SCHEMAS))
def test_schema_files_are_draft_2020_12(name):
    schema = schemas.load(name)
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    jsonschema.Draft202012Validator.check_schema(schema)
    assert schema["description"] and schema["title"]


def _property_schemas(node, path="$"):
    """(path, schema) of every declared property (properties, patternProperties) anywhere in a schema.

    The branches of a conditional rule (if/then/else) restate properties declared elsewhere: not declarations.
    """
    if isinstance(node, dict):
        for key in ("properties", "patternProperties"):
            for name, sub in node.get(key, {}).items():
                yield f"{path}.{key}.{name}", sub
        for key, sub in node.items():
            if key not in ("if", "then", "else"):
                yield from _property_schemas(sub, f"{path}.{key}")
    elif isinstance(node, list):
        for i, sub in enumerate(node):
            yield from _property_schemas(sub, f"{path}[{i}]")


@pytest.mark.parametrize("name", list(schemas.SCHEMAS))
def test_every_property_is_documented(name):
    props = list(_property_schemas(schemas.load(name)))
    assert props
    undocumented = [p for p, sub in props if not (isinstance(sub, dict) and sub.get("description")) and
                    not (isinstance(sub, dict) and "$ref" in sub and len(sub) == 1)]
    assert not undocumented, undocumented
    # a bare $ref must lead to a documented definition
    schema = schemas.load(name)
    for p, sub in props:
        if isinstance(sub, dict) and set(sub) == {"$ref"}:
            target = schema
            for part in sub["$ref"].removeprefix("#/").split("/"):
                target = target[part]
            assert target.get("description"), (p, sub["$ref"])


def test_shared_definitions_are_the_same_in_every_file():
    """Each schema file stands alone (other tools read one file); the definitions they share must not drift."""
    defs = {name: schemas.load(name).get("$defs", {}) for name in schemas.SCHEMAS}
    for shared in ("versions", "network", "attacks", "channel_list"):
        having = [defs[n][shared] for n in defs if shared in defs[n]]
        assert len(having) >= 2 and all(d == having[0] for d in having), shared


def test_contract_keys_are_required():
    """The keys DESIGN.md's contract names are required by the schemas."""
    assert set(schemas.load("study")["required"]) == {
        "schema", "study", "scenario", "runs", "particles", "steps", "seed", "assumptions", "wall_time_s",
        "versions", "filters"}
    assert set(schemas.load("schedule")["required"]) == {
        "schema", "scenario", "mode", "nodes", "steps", "epsilon", "feasible", "violations", "sigma", "beta",
        "trace_bound", "certified", "verdict", "verdict_detail", "bounded", "growing", "bounded_reason"}
    assert set(schemas.load("feasibility")["required"]) == {"feasible", "trace_bound", "binding", "theorem2",
                                                            "iterations", "verdict", "rule", "better_than_local"}
    from studies.feasibility_terms import GRID_PARAMETERS, OUTPUTS

    row = schemas.load("feasibility")["properties"]
    assert set(row) == set(GRID_PARAMETERS) | set(OUTPUTS)
    grid = schemas.load("feasibility_json")["properties"]["grids"]["items"]["properties"]["name"]
    assert set(grid["enum"]) == set(GRID_PARAMETERS)


def test_schema_files_are_package_data():
    files = resources.files("studies.schemas")
    for name, file in schemas.SCHEMAS.items():
        res = files.joinpath(file)
        assert res.is_file(), file
        assert json.loads(res.read_text(encoding="utf-8")) == schemas.load(name)
    with _raises_at("unknown schema 'nope'"):
        schemas.load("nope")
    with _raises_at("unknown schema 'nope'"):
        schemas.validate("nope", {})


def _build(src: Path, lib: Path) -> None:
    for info in src.glob("*.egg-info"):  # a previous build's file list would bring its files along
        shutil.rmtree(info)
    r = subprocess.run([sys.executable, "-c", "import setuptools; setuptools.setup()", "-q", "build_py",
                        "--build-lib", str(lib)], cwd=src, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr


@pytest.mark.slow
def test_the_built_package_ships_the_schemas(tmp_path):
    """setuptools' build (what goes into a wheel) holds the JSON files, importable through importlib.resources."""
    src = tmp_path / "src"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", ".chunks")
    for d in ("designer", "filters", "rules", "studies"):
        shutil.copytree(ROOT / d, src / d, ignore=ignore)
    for f in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / f, src / f)
    lib = tmp_path / "lib"
    _build(src, lib)
    code = ("import json, studies.schemas as s\nfrom importlib import resources\nprint(s.__file__)\n"
            "print(json.dumps({n: json.loads(resources.files('studies.schemas').joinpath(f).read_text())['title']"
            " for n, f in s.SCHEMAS.items()}))\nprint(s.load('study')['required'][0])")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                       env={**os.environ, "PYTHONPATH": str(lib)})
    assert r.returncode == 0, r.stderr
    where, titles, first = r.stdout.splitlines()
    assert Path(where).resolve().is_relative_to(lib.resolve())  # the built copy, not the source tree
    assert json.loads(titles) == {n: schemas.load(n)["title"] for n in schemas.SCHEMAS}
    assert first == "schema"
    # negative control: without the schemas' line of the package-data table the build has no JSON files
    text = (src / "pyproject.toml").read_text()
    table = '[tool.setuptools.package-data]\n"studies.schemas" = ["*.json"]\n'
    assert table in text
    table = table.split("\n", 1)[1]  # the line alone: the table goes on for the C files
    (src / "pyproject.toml").write_text(text.replace(table, ""))
    _build(src, tmp_path / "bare")
    assert (tmp_path / "bare" / "studies" / "schemas" / "__init__.py").is_file()
    assert not list((tmp_path / "bare" / "studies" / "schemas").glob("*.json"))


# ---------------------------------------------------------------------------------------------- design, feasibility
@pytest.fixture(scope="module")
def designs(tmp_path_factory):
    """``cfdesign design``: the linear model's feasible design, the indoor robot's infeasible paper design and the
    range-bearing target's paper design, where a node diverges (a violation with a reason and a null margin)."""
    out = {w: tmp_path_factory.mktemp(f"design-{w}") for w in ("feasible", "infeasible", "diverged")}
    assert main(["design", LINEAR, "--mode", "paper", "--sigma", "0.01", "--beta", "0.01", "--u-scale", "0",
                 "--v-scale", "0", "--seed", "2", "--steps", "12", "--out", str(out["feasible"])]) == 0
    assert main(["design", "indoor-robot", "--mode", "paper", "--seed", "1", "--steps", "10", "--out",
                 str(out["infeasible"])]) == 1
    assert main(["design", "target-range-bearing", "--mode", "paper", "--seed", "0", "--steps", "12", "--out",
                 str(out["diverged"])]) == 1
    return out


@pytest.mark.parametrize("which", ["feasible", "infeasible", "diverged"])
@pytest.mark.slow
def test_design_writes_a_valid_schedule(designs, which):
    out = designs[which]
    assert schemas.validate_output(out) == [out / "schedule.json"]
    sched = json.loads((out / "schedule.json").read_text())
    assert sched["feasible"] is (which == "feasible")
    assert any(v["condition"] in ("(28)", "(29)", "diverged") for v in sched["violations"]) is (which != "feasible")
    if which == "diverged":
        assert any(v["condition"] == "diverged" and v["margin"] is None and v["reason"] for v in sched["violations"])


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    """``cfdesign feasibility``: a 1-D and a 2-D grid (the 2-D one has infeasible points with an empty trace bound)."""
    one, two = tmp_path_factory.mktemp("map-1d"), tmp_path_factory.mktemp("map-2d")
    assert main(["feasibility", LINEAR, "--grid", "dos=0:0.6:3", "--out", str(one)]) == 0
    assert main(["feasibility", LINEAR, "--grid", "dos=0:0.6:3", "--grid", "fdi=0:0.9:2", "--out", str(two)]) == 0
    return {"1d": one, "2d": two}


@pytest.mark.parametrize("which", ["1d", "2d"])
@pytest.mark.slow
def test_feasibility_writes_valid_rows_and_json(maps, which):
    out = maps[which]
    assert schemas.validate_output(out) == [out / "feasibility.csv", out / "feasibility.json"]
    rows = schemas.read_feasibility_csv(out / "feasibility.csv")
    meta = json.loads((out / "feasibility.json").read_text())
    assert len(rows) == meta["points"] == (3 if which == "1d" else 6)
    assert [g["name"] for g in meta["grids"]] == (["dos"] if which == "1d" else ["dos", "fdi"])
    for r in rows:
        assert isinstance(r["dos"], float) and r["feasible"] in (0, 1) and isinstance(r["iterations"], int)
        assert isinstance(r["binding"], str)
    if which == "2d":  # dos + fdi > 1: infeasible, the empty cell read as null
        assert any(r["feasible"] == 0 and r["trace_bound"] is None and r["verdict"] == "infeasible" for r in rows)
    assert meta["verdicts"] == {v: sum(r["verdict"] == v for r in rows)
                                for v in ("certified", "vacuous", "infeasible", "not computed")}


def test_read_feasibility_csv_types_the_cells(tmp_path):
    p = tmp_path / "feasibility.csv"
    p.write_text("dos,tau,feasible,trace_bound,binding,theorem2,iterations,verdict,rule,better_than_local\n"
                 "0.1,0.01,1,2.5,(28),1,7,certified,paper,1\n0.9,0.01,0,,diverged,0,3,infeasible,paper,0\n"
                 "0.5,nan,0,,(29),0,4,infeasible,paper,0\n")
    rows = schemas.read_feasibility_csv(p)
    assert rows[0] == {"dos": 0.1, "tau": 0.01, "feasible": 1, "trace_bound": 2.5, "binding": "(28)", "theorem2": 1,
                       "iterations": 7, "verdict": "certified", "rule": "paper", "better_than_local": 1}
    assert rows[1]["trace_bound"] is None and rows[2]["tau"] == "nan"
    with _raises_at(r"feasibility.csv row 2 \(line 4\) does not follow .*: \$\.tau: 'nan' is not of type 'number'"):
        schemas.validate_output(p)
    p.write_text("dos,feasible,trace_bound,binding,theorem2,iterations\n0.1,1,2.5,(28),1\n")
    with _raises_at("feasibility.csv line 2: 6 columns in the header"):
        schemas.read_feasibility_csv(p)
    p.write_text("")
    with _raises_at("no header row"):
        schemas.read_feasibility_csv(p)


# ---------------------------------------------------------------------------------------------- every study
SMALL = {"comparison": ["sweep_values=[0.2]"]}  # one sweep value: the sweeps' schema, not the five values' runs


@pytest.fixture(scope="module")
def study_dir(tmp_path_factory):
    """Run a study of the pipeline once at a tiny size (cached per module) and return its output directory."""
    done: dict[str, Path] = {}

    def run(name: str) -> Path:
        if name not in done:
            st = get_study(name)
            out = tmp_path_factory.mktemp(name)
            api.study(name, runs=max(2, st.min_runs), particles=None if st.particles is None else PARTICLES,
                      out=out, assignments=SMALL.get(name, ()))
            done[name] = out
        return done[name]

    return run


@pytest.mark.parametrize("name", list(STUDIES))
@pytest.mark.slow
def test_every_study_writes_valid_results(study_dir, name):
    out = study_dir(name)
    assert schemas.validate_output(out / "results.json") == [out / "results.json"]
    res = json.loads((out / "results.json").read_text())
    st = get_study(name)
    assert res["study"] == name and res["runs"] == max(2, st.min_runs) and res["filters"]
    assert res["particles"] == (None if st.particles is None else PARTICLES)


@pytest.mark.slow
def test_comparison_on_a_user_model_file(tmp_path):
    model = tmp_path / "oscillator.py"
    model.write_text(MODEL)
    res = api.study("comparison", model, runs=2, particles=PARTICLES, seed=1, out=tmp_path / "out")
    assert schemas.validate_output(tmp_path / "out") == [tmp_path / "out" / "results.json"]
    assert res.results["scenario"] == "oscillator"
    schemas.validate("study", res.results)  # the object in memory too


def test_the_literature_filters_results_are_typed(study_dir, tmp_path):
    """comparison and consensus-robot carry KCF and HCMCI; their packet counts are typed by the schema."""
    good = study_dir("comparison") / "results.json"
    res = json.loads(good.read_text())
    for sc in ("indoor-robot", "target-range-bearing"):
        hc = res["filters"][f"{sc}: HCMCI"]
        assert hc["consensus_iterations"] == 1 and 0 <= hc["delivered_per_step"] <= hc["messages_per_step"]
        assert res["filters"][f"{sc}: KCF"]["messages_per_step"] == hc["messages_per_step"]
    robot = json.loads((study_dir("consensus-robot") / "results.json").read_text())["filters"]
    assert robot["HCMCI"]["bound_check"] is None and robot["KCF"]["communications"] == 20

    def bad(r):
        r["filters"]["indoor-robot: HCMCI"]["consensus_iterations"] = 0

    with _raises_at(r"\$\.filters\['indoor-robot: HCMCI'\]\.consensus_iterations: 0 is less than the minimum of 1"):
        schemas.validate_output(_rewrite(good, tmp_path / "a" / "results.json", bad))


# ---------------------------------------------------------------------------------------------- negative controls
def _rewrite(src: Path, dst: Path, change) -> Path:
    obj = json.loads(src.read_text())
    change(obj)
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text(json.dumps(obj))
    return dst


def test_results_missing_key_or_wrong_type_are_rejected(study_dir, tmp_path):
    good = study_dir("consensus-robot") / "results.json"
    missing = _rewrite(good, tmp_path / "a" / "results.json", lambda r: r.pop("seed"))
    with _raises_at(r"results.json does not follow schema 'study' \(study.schema.json\): \$: 'seed' is a required "):
        schemas.validate_output(missing)
    as_text = _rewrite(good, tmp_path / "b" / "results.json", lambda r: r.update(runs=str(r["runs"])))
    with _raises_at(r"results.json .*: \$\.runs: '2' is not of type 'integer'"):
        schemas.validate_output(as_text)
    name = next(iter(json.loads(good.read_text())["filters"]))

    def bad_metric(r):
        r["filters"][name]["rmse_position"] = "0.5"

    metric = _rewrite(good, tmp_path / "c" / "results.json", bad_metric)
    with _raises_at(re.escape(f"$.filters['{name}'].rmse_position: '0.5' is not of type 'number', 'null'")):
        schemas.validate_output(metric)

    def bad_node(r):
        del r["filters"][name]["nodes"][1]["rmse_position"]

    node = _rewrite(good, tmp_path / "d" / "results.json", bad_node)
    with _raises_at(r"\.nodes\[1\]: 'rmse_position' is a required property"):
        schemas.validate_output(node)
    # NaN is no JSON: the writers write null, and a file with NaN is rejected
    nan = good.read_text().replace('"wall_time_s": ', '"wall_time_s": NaN, "x": ', 1)
    (tmp_path / "a" / "results.json").write_text(nan)
    with _raises_at("results.json holds NaN, which is not JSON"):
        schemas.validate_output(tmp_path / "a")


def test_schedule_with_a_trace_bound_of_the_wrong_shape_is_rejected(designs, tmp_path):
    good = designs["infeasible"] / "schedule.json"
    flat = _rewrite(good, tmp_path / "schedule.json",
                    lambda s: s.update(trace_bound=[v for row in s["trace_bound"] for v in row]))
    with _raises_at(r"schedule.json does not follow schema 'schedule' .*: \$\.trace_bound\[\d+\]: .* is not of type "
                    r"'array'"):
        schemas.validate_output(flat)
    short = _rewrite(good, tmp_path / "schedule.json", lambda s: s.update(trace_bound=s["trace_bound"][:-1]))
    with _raises_at(r"\$\.trace_bound: trace_bound \(nodes x steps\) has 7 rows, expected 8"):
        schemas.validate_output(short)
    ragged = _rewrite(good, tmp_path / "schedule.json", lambda s: s["sigma"][3].pop())
    with _raises_at(r"\$\.sigma\[3\]: row 3 of sigma \(nodes x steps\) has 9 entries, expected 10"):
        schemas.validate_output(ragged)
    liar = _rewrite(good, tmp_path / "schedule.json", lambda s: s.update(feasible=True, verdict="vacuous"))
    with _raises_at(r"\$\.violations\[\d+\]\.condition: '\(2[89]\)' should not be valid"):
        schemas.validate_output(liar)


def test_a_schedule_whose_verdict_contradicts_itself_is_rejected(designs, tmp_path):
    """certified and verdict agree, feasible and infeasible agree, and the detail has one entry per node and the
    file's verdict."""
    good = designs["feasible"] / "schedule.json"
    assert json.loads(good.read_text())["verdict"] == "certified"
    cases = [
        (lambda s: s.update(certified=False), r"\$\.verdict: 'certified' should not be valid"),
        (lambda s: s.update(verdict="vacuous"), r"\$\.verdict: 'certified' was expected"),
        (lambda s: s.update(verdict="infeasible", certified=False), r"\$\.verdict: 'infeasible' should not be valid"),
        (lambda s: s.update(verdict="unsure"), r"\$\.verdict: 'unsure' is not one of"),
        (lambda s: s.update(verdict="not steady"), r"\$\.verdict: 'not steady' is not one of"),
        (lambda s: s.update(bounded=not s["bounded"]), r"\$\.verdict_detail\.bounded: .* but the file's bounded is"),
        (lambda s: s.pop("growing"), r"\$: 'growing' is a required property"),
        (lambda s: s["verdict_detail"]["final_trace"].pop(), r"\$\.verdict_detail\.final_trace: 2 entries for a "
                                                             r"network of 3 nodes"),
        (lambda s: s["verdict_detail"].update(verdict="vacuous"), r"\$\.verdict_detail\.verdict: 'vacuous' but the "
                                                                  r"file's verdict is 'certified'"),
        (lambda s: s["verdict_detail"].update(horizon=99), r"\$\.verdict_detail\.horizon: horizon 99 of a run of 12"),
        (lambda s: s.pop("verdict_detail"), r"\$: 'verdict_detail' is a required property"),
    ]
    for i, (change, message) in enumerate(cases):
        with _raises_at(message):
            schemas.validate_output(_rewrite(good, tmp_path / f"{i}" / "schedule.json", change))
    bad = designs["infeasible"] / "schedule.json"
    liar = _rewrite(bad, tmp_path / "liar" / "schedule.json", lambda s: s.update(verdict="certified", certified=True))
    with _raises_at(r"\$\.verdict: 'infeasible' was expected"):
        schemas.validate_output(liar)


def test_mse_schedule_records_its_conditioning(tmp_path):
    """An mse design records each node's largest gain condition number (paper designs: null); the schema's checks
    reject entries of the wrong length and an ill-conditioned list that does not match the numbers."""
    out = tmp_path / "mse"
    assert main(["design", LINEAR, "--mode", "mse", "--seed", "2", "--steps", "6", "--out", str(out)]) == 0
    assert schemas.validate_output(out) == [out / "schedule.json"]
    sched = json.loads((out / "schedule.json").read_text())
    cond = sched["conditioning"]
    assert len(cond["gain_condition"]) == sched["nodes"] and all(v >= 1 for v in cond["gain_condition"])
    assert all(0 <= k < sched["steps"] for k in cond["gain_condition_step"])
    assert cond["ill_conditioned"] == [i for i, v in enumerate(cond["gain_condition"]) if v > cond["threshold"]]
    good = out / "schedule.json"
    short = _rewrite(good, tmp_path / "a" / "schedule.json", lambda s: s["conditioning"]["gain_condition"].pop())
    with _raises_at(r"\$\.conditioning\.gain_condition: 2 entries for a network of 3 nodes"):
        schemas.validate_output(short)
    liar = _rewrite(good, tmp_path / "b" / "schedule.json", lambda s: s["conditioning"].update(ill_conditioned=[1]))
    with _raises_at(r"\$\.conditioning\.ill_conditioned\[0\]: node 1 is not one whose gain condition number exceeds"):
        schemas.validate_output(liar)

    def hidden(s):
        s["conditioning"]["gain_condition"][2] = 10 * s["conditioning"]["threshold"]

    unlisted = _rewrite(good, tmp_path / "c" / "schedule.json", hidden)
    with _raises_at(r"\$\.conditioning\.gain_condition\[2\]: node 2's gain condition number .* is not listed"):
        schemas.validate_output(unlisted)


def test_feasibility_row_with_feasible_2_is_rejected(maps, tmp_path):
    text = (maps["1d"] / "feasibility.csv").read_text().splitlines()
    header, first = text[0].split(","), text[1].split(",")
    first[header.index("feasible")] = "2"
    (tmp_path / "feasibility.csv").write_text("\n".join([text[0], ",".join(first), *text[2:]]) + "\n")
    with _raises_at(r"feasibility.csv row 0 \(line 2\) does not follow schema 'feasibility' "
                    r"\(feasibility.schema.json\): \$\.feasible: 2 is not one of \[0, 1\]"):
        schemas.validate_output(tmp_path / "feasibility.csv")
    row = schemas.read_feasibility_csv(maps["1d"] / "feasibility.csv")[0]
    with _raises_at(r"\$: Additional properties are not allowed \('gamma' was unexpected\)"):
        schemas.validate("feasibility", {**row, "gamma": 0.5})
    with _raises_at(r"\$\.trace_bound: None is not of type 'number'"):  # a feasible point has a bound
        schemas.validate("feasibility", {**row, "feasible": 1, "trace_bound": None})
    with _raises_at(r"\$\.verdict: 'not computed' is not one of \['certified', 'vacuous'\]"):  # a fixed point
        schemas.validate("feasibility", {**row, "feasible": 1, "verdict": "not computed"})
    with _raises_at(r"\$\.verdict: 'not steady' is not one of"):  # the earlier version's word is not written
        schemas.validate("feasibility", {**row, "verdict": "not steady"})
    meta = maps["2d"] / "feasibility.json"
    wrong = _rewrite(meta, tmp_path / "feasibility.json", lambda m: m.update(points=m["points"] + 1))
    with _raises_at(r"feasibility.json .*: \$\.points: 7 points, but the grids have 6"):
        schemas.validate_output(wrong)

    def miscount(m):
        m["verdicts"]["certified"] += 1
    wrong = _rewrite(meta, tmp_path / "v" / "feasibility.json", miscount)
    with _raises_at(r"feasibility.json .*: \$\.verdicts: 7 verdicts for 6 points"):
        schemas.validate_output(wrong)


def test_validate_output_names_what_it_cannot_validate(tmp_path):
    with _raises_at("holds none of results.json"):
        schemas.validate_output(tmp_path)
    with _raises_at("'table.md' has no schema"):
        schemas.validate_output(tmp_path / "table.md")
    with _raises_at("does not exist"):
        schemas.validate_output(tmp_path / "results.json")
