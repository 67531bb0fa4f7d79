"""``cfdesign feasibility --mode auto`` (the default): at every grid point, the candidate ``design --mode auto`` would
pick, checked against the maps of every candidate computed one rule at a time by the named-mode path."""
from __future__ import annotations

import math
from pathlib import Path

import pytest

import studies.feasibility_map as fm
from designer.validation import InputError
from studies import api, schemas
from studies.cli import main

ROOT = Path(__file__).resolve().parents[1]
LINEAR = str(ROOT / "examples" / "linear_network_model.py")
GRID = ["dos=0:0.6:3", "fdi=0:0.3:2"]
KW = dict(u_scale=0, v_scale=0)  # the linear model: no remainders
_COLUMNS = ("feasible", "trace_bound", "binding", "theorem2", "iterations", "verdict")


@pytest.fixture(scope="module")
def auto_map(tmp_path_factory):
    out = tmp_path_factory.mktemp("auto")
    return out, api.feasibility(LINEAR, GRID, out=out, **KW)


@pytest.fixture(scope="module")
def per_candidate(auto_map):
    """Every mapped candidate's own map, by the named-mode path (its LMI solved at every point)."""
    _, fmap = auto_map
    return {c["label"]: (c, api.feasibility(LINEAR, GRID, mode=c["rule"], **c["options"], **KW).rows)
            for c in fmap.auto["candidates"] if c["status"] == "mapped"}


def _expected_pick(per_candidate, p: int, local: float) -> str:
    """The pick at point ``p`` by the rule written out here: certified and bounded, below the local EKFs, the smallest
    bound; bounds within 1 % of it go to the fewest bytes, then the fewest messages."""
    ok = [(rows[p]["trace_bound"], c["bytes_per_step"], c["messages_per_step"], label)
          for label, (c, rows) in per_candidate.items()
          if rows[p]["verdict"] == "certified" and rows[p]["feasible"] and rows[p]["trace_bound"] < local]
    assert ok, "the test model has an eligible candidate at every point"
    low = min(t for t, *_ in ok)
    return min((b, m, t, label) for t, b, m, label in ok if t <= low * 1.01)[3]


def test_every_point_shows_the_candidate_design_auto_would_pick(auto_map, per_candidate):
    _, fmap = auto_map
    local = fmap.references["local_mean"]
    assert len(per_candidate) >= 6  # paper, tuned, two scheduled, relay and flood at 1 and 2 hops
    picks = set()
    for p, row in enumerate(fmap.rows):
        label = _expected_pick(per_candidate, p, local)
        assert row["rule"] == label, (p, row["rule"], label)
        ref = per_candidate[label][1][p]
        assert {k: row[k] for k in _COLUMNS} == {k: ref[k] for k in _COLUMNS}  # the named map's row, LMI and all
        assert row["better_than_local"] == 1
        picks.add(label)
    counts = {c["label"]: c["picked_points"] for c in fmap.auto["candidates"]}
    assert sum(counts.values()) == len(fmap.rows)
    assert all(counts[lab] == sum(r["rule"] == lab for r in fmap.rows) for lab in counts)


def test_the_files_follow_their_schemas_and_the_report_names_the_picks(auto_map):
    out, fmap = auto_map
    schemas.validate_output(out)
    md = (out / "report.md").read_text()
    assert "The candidates" in md and "| pick |" in md.replace("pick | below local", "pick |")
    for c in fmap.auto["candidates"]:
        assert c["label"] in md


def test_a_pick_the_lmi_refuses_gives_way_to_the_next(monkeypatch, auto_map, per_candidate):
    """The screening ranks the candidates without their LMI; a pick whose LMI does not confirm it must not be shown:
    here the relay and flood designs' LMIs are made to refuse, so the pick moves to the best of the others."""
    _, fmap = auto_map
    real = fm.stationary_record

    def refusing(sc, design, *, lmi=True, regions=None):
        rec = real(sc, design, lmi=lmi, regions=regions)
        if lmi and design.rule.name in ("relay", "flood"):
            return {**rec, "verdict": "infeasible", "converged": False,
                    "reason": "the stationary LMI does not confirm the fixed point"}
        return rec

    monkeypatch.setattr(fm, "stationary_record", refusing)
    again = api.feasibility(LINEAR, GRID, **KW)
    local = fmap.references["local_mean"]
    others = {k: v for k, v in per_candidate.items() if not k.startswith(("relay", "flood"))}
    assert any(r["rule"].startswith(("relay", "flood")) for r in fmap.rows)  # what the refusal takes away
    for p, row in enumerate(again.rows):
        assert row["rule"] == _expected_pick(others, p, local)


def test_the_budget_caps_every_pick(tmp_path):
    fmap = api.feasibility(LINEAR, GRID, budget="kcf", **KW)
    cap = fmap.auto["budget"]["kcf_messages_per_step"]
    assert fmap.auto["budget"]["messages_per_step"] == cap
    by_label = {c["label"]: c for c in fmap.auto["candidates"]}
    outside = [c for c in by_label.values() if c["status"] == "outside the budget"]
    assert outside and all(c["messages_per_step"] > cap and c["picked_points"] == 0 for c in outside)
    assert all(by_label[r["rule"]]["messages_per_step"] <= cap for r in fmap.rows)
    small = min(c["bytes_per_step"] for c in by_label.values())
    tight = api.feasibility(LINEAR, GRID, budget_bytes=small, **KW)
    assert all(c["bytes_per_step"] <= small for c in tight.auto["candidates"] if c["status"] == "mapped")
    assert {r["rule"] for r in tight.rows} <= {c["label"] for c in tight.auto["candidates"] if c["status"] == "mapped"}


@pytest.mark.parametrize("kw, words", [
    (dict(grid=["sigma=0:1:3"]), "--grid sigma applies to a mode of fixed multipliers only"),
    (dict(mode="tuned", budget="kcf"), "budget and budget_bytes are options of mode 'auto'"),
    (dict(budget="lots"), "budget must be 'kcf' or a whole number"),
    (dict(budget_bytes=0), "budget_bytes"),
])
def test_bad_input_is_refused_before_any_point(kw, words):
    grid = kw.pop("grid", GRID)
    with pytest.raises(InputError, match=words.replace("(", r"\(")):
        api.feasibility(LINEAR, grid, **kw, **KW)


def test_the_command_line_maps_auto_by_default_and_refuses_a_paper_grid(tmp_path, capsys):
    assert main(["feasibility", LINEAR, "--grid", "dos=0:0.3:2", "--u-scale", "0", "--v-scale", "0",
                 "--out", str(tmp_path / "m"), "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "(auto design)" in said and "picked:" in said
    rows = schemas.read_feasibility_csv(tmp_path / "m" / "feasibility.csv")
    assert all(r["rule"] and r["better_than_local"] in (0, 1) for r in rows)
    assert main(["feasibility", LINEAR, "--grid", "beta=0:1:2", "--out", str(tmp_path / "b"), "--quiet"]) == 2
    assert not (tmp_path / "b" / "feasibility.csv").exists()


def test_better_than_local_is_the_bound_against_the_local_reference(auto_map):
    _, fmap = auto_map
    local = fmap.references["local_mean"]
    for r in fmap.rows:
        expected = math.isfinite(r["trace_bound"]) and r["trace_bound"] < local
        assert r["better_than_local"] == int(expected)
