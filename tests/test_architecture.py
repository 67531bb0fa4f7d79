"""The house drawn from its imports: no import circles in ``designer``, ``filters``, ``studies`` (and ``rules`` when
it exists), lazy imports (inside functions) included, and the ``studies`` package face imported by none of its own
modules.

The graph is read from the source (:mod:`ast`), nothing is imported: an edge ``a -> b`` is an ``import b`` or a
``from b import ...`` anywhere in ``a`` (a ``from p import m`` whose ``m`` is a module is an edge to ``p.m`` too);
importing ``p.m`` is not counted as importing the package ``p`` itself (its ``__init__`` is only its face).
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("designer", "filters", "studies", "rules")


def modules(root: Path, packages=PACKAGES) -> dict[str, Path]:
    """Dotted module name -> its file, for every ``.py`` file under ``packages`` (a package is its ``__init__``)."""
    found = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


def import_graph(root: Path, packages=PACKAGES) -> dict[str, dict[str, list[int]]]:
    """Module -> {imported module of the same packages: the lines that import it}, every import statement counted
    (at the top, inside functions, under ``if``)."""
    mods = modules(root, packages)
    graph: dict[str, dict[str, list[int]]] = {m: {} for m in mods}
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[:len(package.split(".")) - node.level + 1]
                    source = ".".join(base + ([node.module] if node.module else []))
                else:
                    source = node.module
                targets = [source] + [f"{source}.{a.name}" for a in node.names]
            else:
                continue
            for target in targets:
                if target in mods and target != name:
                    graph[name].setdefault(target, []).append(node.lineno)
    return graph


def circles(graph: dict[str, dict[str, list[int]]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(graph[start]))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, successors = work[-1]
            w = next(successors, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(graph[w])))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == v:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def describe(graph, found) -> str:
    """Each circle's edges, ``a -> b (lines ...)``, for the failure message."""
    lines = []
    for component in found:
        lines.append(f"circle of {len(component)}:")
        members = set(component)
        lines += [f"  {a} -> {b} (lines {graph[a][b]})" for a in component for b in sorted(graph[a])
                  if b in members]
    return "\n".join(lines)


@pytest.fixture(scope="module")
def graph():
    drawn = import_graph(ROOT)
    assert "studies.api" in drawn and "designer" in drawn  # the tree was read
    return drawn


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_circles(graph, package):
    """No circle has a module of ``package`` in it (a circle across packages fails each package it touches)."""
    found = [c for c in circles(graph) if any(m.split(".")[0] == package for m in c)]
    assert not found, "import circles:\n" + describe(graph, found)


def test_the_studies_face_is_imported_by_none_of_its_modules(graph):
    """``studies/__init__.py`` re-exports the public API (importing :mod:`studies.api` on first use): a module of
    ``studies`` imports the module that defines a name, never the face."""
    users = sorted(m for m, targets in graph.items() if "studies" in targets and m != "studies")
    assert users == [], {m: graph[m]["studies"] for m in users}


def test_figures_import_no_report_and_the_writing_no_computation(graph):
    """Reports may import figures, never the reverse; :mod:`studies.outputs`, which writes every result directory,
    imports none of the modules whose result objects it writes (they import it, inside their ``save``)."""
    assert not [m for m in graph["studies.figures"] if m.startswith("studies.reports")]
    writers_users = sorted(m for m, targets in graph.items() if "studies.outputs" in targets)
    assert writers_users and not [m for m in graph["studies.outputs"] if m in writers_users]


#: The layers, lowest first: a module imports its own layer's and the lower ones' only.
LAYERS = ("designer", "filters", "rules", "studies")
#: The rules that build on another rule's package (flood on relay's class, tuned on the paper's needs text).
BUILDS_ON = {("flood", "relay"), ("tuned", "paper")}


def upward_and_across(graph) -> list[str]:
    """Every import of a higher layer (:data:`LAYERS`) and every import of one rule's package by another's that is
    not in :data:`BUILDS_ON`, as ``a -> b (lines ...)``."""
    found = []
    for a, targets in graph.items():
        for b, lines in targets.items():
            pa, pb = a.split(".")[0], b.split(".")[0]
            ra, rb = a.split(".")[1:2], b.split(".")[1:2]
            if LAYERS.index(pb) > LAYERS.index(pa) or (
                    pa == pb == "rules" and ra and rb and ra != rb and (ra[0], rb[0]) not in BUILDS_ON):
                found.append(f"{a} -> {b} (lines {lines})")
    return found


def test_the_layers_import_downwards_and_a_rule_only_what_it_builds_on(graph, tmp_path):
    """designer imports no filters, rules or studies; filters no rules or studies; rules no studies; a rule's package
    imports another rule's only where it builds on it.  The check finds both kinds of import."""
    assert upward_and_across(graph) == []
    for package in ("designer", "rules", "rules/relay", "rules/mse"):
        (tmp_path / package).mkdir(parents=True)
        (tmp_path / package / "__init__.py").write_text("")
    (tmp_path / "designer" / "a.py").write_text("def f():\n    from rules.relay import x\n")
    (tmp_path / "rules" / "mse" / "b.py").write_text("from ..relay import x\n")
    assert upward_and_across(import_graph(tmp_path, ("designer", "rules"))) == [
        "designer.a -> rules.relay (lines [2])", "rules.mse.b -> rules.relay (lines [1])"]


def test_the_circle_finder_sees_a_circle_through_a_lazy_import(tmp_path):
    """The checks above can fail: a circle closed by an import inside a function, a relative ``from . import``, and
    a package face are found; a chain without a way back is not a circle."""
    pkg = tmp_path / "studies"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .b import thing\n")
    (pkg / "b.py").write_text("def thing():\n    from . import c\n    return c\n")
    (pkg / "c.py").write_text("import studies.sub.d\n")
    (pkg / "sub" / "__init__.py").write_text("from .. import a\n")
    (pkg / "sub" / "d.py").write_text("x = 1\n")
    (pkg / "e.py").write_text("from studies.sub.d import x\n")
    graph = import_graph(tmp_path, ("studies",))
    assert graph["studies.b"] == {"studies": [2], "studies.c": [2]}
    assert circles(graph) == []  # a -> b -> c -> sub.d: no way back
    (pkg / "sub" / "d.py").write_text("def f():\n    from ..a import thing\n")
    graph = import_graph(tmp_path, ("studies",))
    (found,) = circles(graph)
    assert found == ["studies.a", "studies.b", "studies.c", "studies.sub.d"]
    assert "studies.sub.d -> studies.a (lines [2])" in describe(graph, [found])
