"""Reports people want to read: ``DIR/report.md`` and a self-contained ``DIR/report.html``.

:func:`write_report` looks at what an output directory holds and writes the report
that fits:

* ``results.json`` (schema ``cfdesign.study/1``, from ``cfdesign study``): the study
  report (:mod:`studies.reports.study`) — what the study compares, which filter to pick,
  the tables beside the paper's, intervals, sweeps, timings, figures, assumptions;
* ``schedule.json`` (+ ``schedule.npz``, from ``cfdesign design``): the design report
  (:mod:`studies.reports.design`) — feasible or not and why, which condition binds where,
  the bound and the margins over time, σ, β, gains per node, attacks, linearisation;
* ``feasibility.csv`` (+ ``feasibility.json``, from ``cfdesign feasibility``): the
  feasibility report (:mod:`studies.reports.feasibility`) — the grid, how many points are
  feasible, the heat map, and how this notion of feasibility differs from the design's.

Both files come from one Markdown document, so they say the same thing: the Markdown
(:mod:`studies.reports.text` writes it; every text from the results is escaped) is
written as is and rendered to HTML by markdown-it-py (:mod:`studies.reports.render`:
raw HTML disabled, figures inlined as ``data:`` URIs, inline CSS, no JavaScript, a
Content-Security-Policy that forbids loading anything).
"""
from __future__ import annotations

from functools import partial
from pathlib import Path

from designer.fileio import atomic_write, check_path
from designer.validation import InputError

from .render import markdown_to_html
from .study import render_markdown

__all__ = ["write_report", "check_directory", "report_figures", "render_markdown", "markdown_to_html"]

# what a directory must hold for each kind of report, in the order they are looked for
KINDS = (("results.json", "a study's, from `cfdesign study STUDY --out DIR`"),
         ("schedule.json", "a design's, from `cfdesign design SCENARIO --out DIR`"),
         ("feasibility.csv", "a feasibility map's, from `cfdesign feasibility SCENARIO --grid ... --out DIR`"))


def report_figures(directory) -> tuple[str, ...]:
    """The figures the report of ``directory`` draws itself and so owns, whether this report draws them or not: a
    design's (its bound, its margins, its candidates), which :func:`studies.api.report` removes where the report no
    longer draws them (a relay design has no margins: an older version's empty figure would stay beside the new
    report); none for a study's or a map's report, whose figures may come from the command that computed them."""
    d = Path(directory)
    if not (d / "results.json").is_file() and (d / "schedule.json").is_file():
        from .auto import CANDIDATES_FIGURE
        from .design import FIGURES

        return (*FIGURES, CANDIDATES_FIGURE)
    return ()


def check_directory(directory) -> Path:
    """``directory`` as a Path: a path (not empty) of an existing directory; else InputError naming it."""
    d = check_path("directory", directory)
    if not d.is_dir():
        raise InputError(f"directory {str(d)!r} does not exist or is not a directory")
    return d


def write_report(directory, into=None) -> tuple[Path, Path]:
    """Write ``report.html`` and ``report.md`` for the results in ``directory`` (into ``into``, default there).

    The report follows what ``directory`` holds (see the module docstring):
    ``results.json`` a study report, else ``schedule.json`` a design report (which
    also writes its figures ``fig_trace_bound.png`` and ``fig_margins.png`` from
    ``schedule.npz``), else ``feasibility.csv`` a feasibility report.
    ``report.md`` links the figures by file name; ``report.html`` is self-contained
    (figures inline as base64 ``data:`` URIs, inline CSS, no JavaScript).  Both are
    rendered before either is written, and each is written atomically (a temporary
    file in ``directory``, then renamed), so a reader sees the old report or the new one.

    Parameters
    ----------
    directory : str or path-like
        The output directory of ``cfdesign study``, ``cfdesign design`` or
        ``cfdesign feasibility``.
    into : path, optional
        Where the report and its figures are written (e.g. a staging directory,
        :func:`designer.fileio.replaced_outputs`); default: ``directory``.  This function
        takes no lock: :func:`studies.api.report` does.

    Returns
    -------
    (Path, Path)
        The paths of ``report.html`` and ``report.md``.

    Raises
    ------
    designer.validation.InputError
        ``directory`` does not exist, holds none of those files, or one of them cannot
        be read or is not what its name says (the message names ``directory``).
    """
    d = check_directory(directory)
    out = d if into is None else Path(into)
    if (d / "results.json").is_file():
        from .study import study_report as make
    elif (d / "schedule.json").is_file():
        from .design import design_report

        make = partial(design_report, into=out)
    elif (d / "feasibility.csv").is_file():
        from .feasibility import feasibility_report as make
    elif (d / "candidates.json").is_file():
        from .auto import auto_report

        make = partial(auto_report, into=out)
    else:
        wanted = "; ".join(f"{name} ({what})" for name, what in KINDS)
        raise InputError(f"directory {str(d)!r} has no results.json, schedule.json or feasibility.csv: nothing to "
                         f"report on (expected one of {wanted})")
    md, images, title = make(d)
    page = markdown_to_html(md, images, title=title)
    md_path = atomic_write(out / "report.md", lambda fh: fh.write(md.encode("utf-8")))
    html_path = atomic_write(out / "report.html", lambda fh: fh.write(page.encode("utf-8")))
    return html_path, md_path
