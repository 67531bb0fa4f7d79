"""docs/ stays true: every code block of every page runs as written or is marked for what it is, the links between
the pages (and from the README) resolve, and the papers are named by authors and title, not by a number.

A block's info string says what it is: ``sh`` (commands, run in order with the page's other blocks in a fresh
directory holding a copy of ``examples/``), ``python`` (run there, in order), ``python file=NAME`` (a file the page
asks you to write: written as NAME, then run), ``python fragment`` (a piece of a shipped file under ``examples/``)
and ``text`` (illustrative: a synopsis, or a command that takes minutes)."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [ROOT / "README.md", *DOCS]
KINDS = re.compile(r"(sh|text|python|python fragment|python file=[\w.-]+\.py)")


def blocks(page: Path) -> list[tuple[str, str]]:
    """The fenced blocks of a page, in order: (info string, text)."""
    return re.findall(r"^```([^\n`]*)\n(.*?)^```[ \t]*$", page.read_text(), flags=re.S | re.M)


def test_there_are_docs_and_every_block_says_what_it_is():
    assert {p.name for p in DOCS} >= {"tutorial.md", "model-files.md", "commands.md", "gain-rules.md", "export.md",
                                      "api.md", "studies.md", "speed.md", "scenarios.md", "layout.md"}
    for page in DOCS:
        for info, _ in blocks(page):
            assert KINDS.fullmatch(info), f"{page.name}: a block marked {info!r}"
    # the fences pair up: no block left open
    for page in PAGES:
        assert len(re.findall(r"^```", page.read_text(), flags=re.M)) % 2 == 0, page.name


def test_fragments_are_pieces_of_shipped_examples():
    shipped = [p.read_text() for p in (ROOT / "examples").glob("*.py")]
    fragments = [(page.name, code) for page in DOCS for info, code in blocks(page) if info == "python fragment"]
    assert fragments
    for name, code in fragments:
        assert any(code in text for text in shipped), f"{name}: a fragment found in no file of examples/:\n{code}"


def _env() -> dict:
    """The environment a reader has after the set-up: this Python's scripts (cfdesign) first on the PATH, and the
    tree under test importable."""
    bindir = Path(sys.executable).parent
    assert (bindir / "cfdesign").is_file()
    env = dict(os.environ, MPLBACKEND="Agg")
    env["PATH"] = os.pathsep.join([str(bindir), env.get("PATH", "")])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    return env


RUNNABLE = [p for p in DOCS if any(info == "sh" or info.startswith("python") and info != "python fragment"
                                   for info, _ in blocks(p))]


@pytest.mark.parametrize("page", RUNNABLE, ids=[p.stem for p in RUNNABLE])
def test_the_page_runs_as_written(page, tmp_path, monkeypatch):
    """Every sh and python block of the page, in order, in one fresh directory (a copy of examples/ beside)."""
    shutil.copytree(ROOT / "examples", tmp_path / "examples", ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.chdir(tmp_path)
    env = _env()
    for i, (info, code) in enumerate(blocks(page)):
        if info == "sh":
            proc = subprocess.run(["bash", "-c", "set -euo pipefail\n" + code], cwd=tmp_path, env=env,
                                  capture_output=True, text=True, timeout=300)
            assert proc.returncode == 0, f"{page.name}, block {i}:\n{code}\n{proc.stderr[-2000:]}"
        elif info == "python" or info.startswith("python file="):
            if info.startswith("python file="):
                (tmp_path / info.split("=", 1)[1]).write_text(code)
            exec(compile(code, f"{page.name}, block {i}", "exec"), {"__name__": "__doc_block__"})
    CLAIMS.get(page.name, lambda d: None)(tmp_path)


def _tutorial(tmp_path: Path) -> None:
    """What the tutorial says its commands wrote: a certified design (it exits 0 on it), a map with a verdict per
    grid point, estimates of steps + 1 x nodes x states, the C sources."""
    schedule = json.loads((tmp_path / "ring-design" / "schedule.json").read_text())
    assert schedule["certified"] is True and schedule["verdict"] == "certified"
    rows = (tmp_path / "ring-map" / "feasibility.csv").read_text().splitlines()
    assert len(rows) == 1 + 4 and "verdict" in rows[0] and "rule" in rows[0]
    for d in ("ring-kcf", "ring-designed"):
        with np.load(tmp_path / d / "estimates.npz") as z:
            assert z["x_hat"].shape == (31, 4, 2) and np.isfinite(z["x_hat"]).all()
    assert (tmp_path / "ring-c" / "cfd_node.c").is_file()


CLAIMS = {"tutorial.md": _tutorial}


def test_spec_example_runs(tmp_path, monkeypatch):
    """The model-file reference's SPEC example, with the --set command it names: the values reach the design."""
    spec = next(code for info, code in blocks(ROOT / "docs" / "model-files.md") if info == "python file=scalar.py")
    said = (ROOT / "docs" / "model-files.md").read_text()
    assert "cfdesign design scalar.py --set gain=0.8 --set dos=0.3 --out d" in said
    (tmp_path / "scalar.py").write_text(spec)
    monkeypatch.chdir(tmp_path)
    from studies.cli import main

    assert main(["design", "scalar.py", "--set", "gain=0.8", "--set", "dos=0.3", "--out", "d"]) in (0, 1)
    written = json.loads((tmp_path / "d" / "schedule.json").read_text())
    assert written["params"]["gain"] == 0.8 and written["params"]["dos"] == 0.3
    assert np.isfinite(written["epsilon"])


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation but '-' and '_' dropped, spaces to '-'."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = re.sub(r"^```.*?^```[ \t]*$", "", page.read_text(), flags=re.S | re.M)
    return {slug(h) for h in re.findall(r"^#{1,6} (.+)$", text, flags=re.M)}


def test_links_between_the_pages_resolve():
    seen = 0
    for page in PAGES:
        text = re.sub(r"^```.*?^```[ \t]*$", "", page.read_text(), flags=re.S | re.M)
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-z]+:", target):
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            assert dest.is_file(), f"{page.name}: a link to {target}, no such file"
            if anchor:
                assert anchor in anchors(dest), f"{page.name}: a link to {target}, no such heading"
            seen += 1
    assert seen > 30


def test_slug_is_githubs():
    assert slug("Overriding parameters (`--set`)") == "overriding-parameters---set"
    assert slug("Robustness δ of the scheduled design, measured") == "robustness-δ-of-the-scheduled-design-measured"
    assert slug("7. Export to C") == "7-export-to-c"


def test_the_readme_is_short_and_leads_to_every_page():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 300
    for page in DOCS:
        assert f"](docs/{page.name}" in readme, f"the README does not link {page.name}"


def test_papers_are_named_not_numbered():
    """The seed files' numbers (000-004) are the project's, not a reader's: a page names the paper."""
    for page in PAGES:
        text = page.read_text()
        found = re.findall(r"seed 00[0-4]|\b00[0-4]'s\b|\| 00[0-4] ", text)
        assert not found, f"{page.name}: {found}"


def test_equation_numbers_say_whose_they_are():
    """A page that quotes the consensus paper's bounds (26)-(27), conditions (28)-(29) or gain (30) names the paper
    (scenarios.md and studies.md quote other papers' equations, each beside its paper's name)."""
    for page in PAGES:
        text = page.read_text()
        if re.search(r"\(26\)|\(28\)[-/]\(29\)|gain \(30\)", text):
            assert "Gao, Wu and Zheng" in text, page.name
    gain_rules = (ROOT / "docs" / "gain-rules.md").read_text()
    for name in ("the prediction bound, equation (26)", "the update bound, equation (27)", "(28)", "(29)",
                 "the optimal gain,\n    equation (30)", "Theorem 1", "Theorem 2",
                 "*Distributed consensus filter design for a class of nonlinear systems under complex\ncooperative "
                 "attacks*, Control and Decision 2024"):
        assert name in gain_rules, name


def test_the_command_reference_names_every_command_and_option():
    """Every command of the click group (subcommands included) and every option it takes appear in commands.md."""
    import click

    from studies.cli import cli

    said = (ROOT / "docs" / "commands.md").read_text()

    def walk(cmd: click.Command, path: tuple[str, ...]):
        yield path, cmd
        if isinstance(cmd, click.Group):
            for name, sub in cmd.commands.items():
                yield from walk(sub, path + (name,))

    seen = 0
    for path, cmd in walk(cli, ()):
        if path:
            assert f"cfdesign {' '.join(path)}" in said, f"commands.md does not name `cfdesign {' '.join(path)}`"
        for param in cmd.params:
            for opt in getattr(param, "opts", []):
                if opt.startswith("--") and opt != "--help":
                    assert opt in said, f"commands.md does not name {opt} of {' '.join(path) or 'cfdesign'}"
                    seen += 1
    assert seen > 30
