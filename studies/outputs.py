"""Every result directory's files, written: the home of the writing of a study's outputs (``results.json``,
``table.md``, the figures and the reports), a design's (``schedule.json``, ``schedule.npz`` and the reports), a
feasibility map's (``feasibility.csv``, ``feasibility.json``, ``feasibility.png`` and the reports) and a filter run's
(``estimates.npz``, ``estimates.csv``, ``fig_estimates.png`` and ``report.md``).

The computation returns result objects (:class:`studies.pipeline.StudyResult`,
:class:`studies.consensus_design.Design`, :class:`studies.feasibility_map.FeasibilityMap`,
:class:`studies.api.FilterRun`); their ``save`` hands them to the function here, imported there on first use (as
is the figure helper a study starts before it computes, :func:`figure_helper`).  This module imports the figures (:mod:`studies.figures`) and
the reports (:mod:`studies.reports`), and no computation: what it writes it takes from the result object it is given
(``FeasibilityMap.record`` is the content of ``feasibility.json``), so no import circle passes through it.
"""
from __future__ import annotations

import csv
import io
from functools import partial
from pathlib import Path
from typing import Callable, Mapping

import numpy as np

from designer.fileio import (atomic_write, check_apart, check_json_finite, replaced_outputs, write_json,
                             write_npz)
from designer.progress import phase

from .feasibility_terms import OUTPUTS
from .figures import TRADEOFF, FigureHelper, figure_batch, map_figure, plotting, save_figure, tradeoff_figure
from .reports import write_report
from .reports.study import summary_blocks
from .scenarios import model_inputs

__all__ = ["write_outputs", "study_figures", "figure_helper", "save_study", "save_design", "save_auto", "save_map",
           "filter_report"]


# ------------------------------------------------------------------------------------------------------ a study


def write_outputs(out, results: dict, figures: Callable[[Path], Callable[[], None] | None],
                  table: Callable[[dict], str]) -> Path:
    """Write the figures, ``table.md``, ``results.json`` and the reports into ``out`` (each atomically).

    ``figures(directory)`` writes the figures, or has another process draw them and returns
    a function that waits until they are written: ``table.md`` and ``results.json`` are
    written meanwhile.  The reports (``report.md`` and the self-contained ``report.html``,
    see :func:`studies.reports.write_report`) are written last, from the files just written.
    The results are checked for non-finite numbers first, and everything is written into a
    staging directory that then replaces the directory's last outputs as a whole
    (:func:`designer.fileio.replaced_outputs`).
    """
    check_json_finite(results, "results.json")
    text = table(results)
    with replaced_outputs(out) as stage:
        with figure_batch():
            pending = figures(stage)
        atomic_write(stage / "table.md", lambda fh: fh.write(text.encode()))
        write_json(stage / "results.json", results)
        if callable(pending):
            pending()
        write_report(stage)
    return Path(out)


def study_figures(study, out: Path, results: dict, scenarios: Mapping, arrays: Mapping) -> None:
    """Every figure of a study: the report summary's :func:`studies.figures.tradeoff_figure` (of the summary's
    blocks, :func:`studies.reports.study.summary_blocks`), then the study's own."""
    tradeoff_figure(Path(out) / TRADEOFF, summary_blocks(results, study.text))
    study.figures(Path(out), results, scenarios, arrays)


def figure_helper(study, scenarios: Mapping) -> FigureHelper | None:
    """A :class:`studies.figures.FigureHelper` started for ``study`` on ``scenarios`` (name -> Scenario, as they are
    before the study computes), which draws its figures (:func:`study_figures`) when the results arrive; None when
    none can be started."""
    return FigureHelper.start(partial(_draw, study, scenarios))


def _draw(study, scenarios: Mapping, out: Path, results: dict, arrays: Mapping) -> None:
    study_figures(study, out, results, scenarios, arrays)


def save_study(result, directory, helper: FigureHelper | None = None) -> Path:
    """Write a :class:`studies.pipeline.StudyResult`'s figures, ``table.md``, ``results.json`` and ``report.html`` /
    ``report.md`` into ``directory`` (:meth:`studies.pipeline.StudyResult.save`).

    ``helper``: a :class:`studies.figures.FigureHelper` started for this study (:func:`figure_helper`), which draws
    the figures (this process draws them if it cannot).  Refused when ``directory`` is, lies inside or contains a
    model file of the study's scenarios (:func:`designer.fileio.check_apart`).
    """
    check_apart("directory", directory, model_inputs(list(result.scenarios.values())))

    def draw(stage: Path) -> None:
        study_figures(result.study, stage, result.results, result.scenarios, result.arrays)

    def figures(stage: Path):
        if helper is None or not helper.send(stage, result.results, result.arrays):
            return draw(stage)

        def wait() -> None:  # the helper draws while the caller writes its other files
            if not helper.wait():
                with figure_batch():
                    draw(stage)
        return wait

    out = Path(directory)
    write_outputs(out, result.results, figures, result.study.table)
    return out


# ----------------------------------------------------------------------------------------------------- a design


def save_design(design, directory) -> Path:
    """Write a :class:`studies.consensus_design.Design`'s ``schedule.json``, ``schedule.npz``, the report's figures
    and ``report.html`` / ``report.md`` into ``directory`` (:meth:`studies.consensus_design.Design.save`; refused
    when it is, lies inside or contains the model's files: :func:`designer.fileio.check_apart`)."""
    check_apart("directory", directory, model_inputs(design.scenario))
    with replaced_outputs(directory) as stage:  # the directory's last outputs replaced as a whole
        with phase("writing the schedule"):
            design.schedule.write(stage)
        if design.validation is not None:
            write_json(stage / "validation.json", design.validation)
        with phase("writing the report"):
            write_report(stage)
    return Path(directory)


def save_auto(auto, directory) -> Path:
    """Write a :class:`studies.auto.AutoDesign` into ``directory``: its pick's files as :func:`save_design` writes them
    (none when no candidate was designed), ``candidates.json``, ``validation.json`` (after a validation) and the
    report, whose automatic-design section draws ``fig_candidates.png`` (:meth:`studies.auto.AutoDesign.save`;
    refused when the directory is, lies inside or contains the model's files)."""
    check_apart("directory", directory, model_inputs(auto.scenario))
    with replaced_outputs(directory) as stage:
        if auto.pick is not None:
            with phase("writing the schedule"):
                auto.pick.schedule.write(stage)
        write_json(stage / "candidates.json", auto.record())
        if auto.validation is not None:
            write_json(stage / "validation.json", auto.validation)
        with phase("writing the report"):
            write_report(stage)
    return Path(directory)


# ----------------------------------------------------------------------------------------------- a feasibility map


def save_map(fmap, directory) -> Path:
    """Write a :class:`studies.feasibility_map.FeasibilityMap`'s ``feasibility.csv``, ``feasibility.json``
    (:meth:`~studies.feasibility_map.FeasibilityMap.record`), ``feasibility.png`` (one or two grid parameters:
    :func:`studies.figures.map_figure`) and the reports into ``directory`` (replacing the directory's last outputs
    as a whole, :func:`designer.fileio.replaced_outputs`; refused when it is, lies inside or contains the model's
    files: :func:`designer.fileio.check_apart`)."""
    check_apart("directory", directory, model_inputs(fmap.scenario))
    with replaced_outputs(directory) as stage:
        _write_map_csv(stage / "feasibility.csv", fmap.rows, fmap.names)
        if len(fmap.grids) <= 2:
            save_figure(map_figure(fmap.rows, fmap.grids, fmap.scenario.name, fmap.mode),
                        stage / "feasibility.png")
        write_json(stage / "feasibility.json", fmap.record())
        write_report(stage)
    return Path(directory)


def _write_map_csv(path: Path, rows: list[dict], names: list[str]) -> None:
    """``feasibility.csv``: one row per grid point, the grid's values then :data:`OUTPUTS` (NaN: an empty cell)."""
    buf = io.StringIO()
    cols = names + list(OUTPUTS)
    w = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if isinstance(r[k], float) and np.isnan(r[k]) else r[k]) for k in cols})
    atomic_write(path, lambda fh: fh.write(buf.getvalue().encode()))


# ------------------------------------------------------------------------------------------------------ a filter run


def filter_report(run, directory: Path) -> None:
    """Write a :class:`studies.api.FilterRun` into ``directory``: ``estimates.npz``, ``estimates.csv``,
    ``report.md`` and ``fig_estimates.png`` (each node's estimate over time with the truth when known, and the trace
    of its bound or covariance)."""
    from designer.verdict import known_verdict

    directory = Path(directory)
    m = run.scenario.model
    K1, nodes, n_x = run.x_hat.shape
    key = "Phi" if run.cov_kind == "bound" else "P"
    arrays = {"x_hat": run.x_hat, **({} if run.cov is None else {key: run.cov}), "valid": run.valid,
              "messages": run.messages, "state_names": np.array(m.state_names)}
    if run.truth is not None:
        arrays["x"] = run.truth
    write_npz(directory / "estimates.npz", **arrays)
    trace = np.full(run.valid.shape, np.nan) if run.cov is None else \
        np.where(run.valid, np.trace(run.cov, axis1=-2, axis2=-1), np.nan)  # no covariance: no trace

    def csv(fh):
        head = ["step", "node", *m.state_names, f"trace_{key}"]
        fh.write((",".join(head) + "\n").encode())
        for k in range(K1):
            for i in range(nodes):
                row = [str(k), str(i), *(repr(float(v)) for v in run.x_hat[k, i]), repr(float(trace[k, i]))]
                fh.write((",".join(row) + "\n").encode())

    atomic_write(directory / "estimates.csv", csv)
    idx = list(m.position_index) or list(range(min(2, n_x)))
    fig, axs = plotting().subplots(1, 2, figsize=(12, 4.5))
    t = np.arange(K1)
    for c in idx[:2]:
        for i in range(nodes):
            axs[0].plot(t, run.x_hat[:, i, c], lw=0.8, alpha=0.6)
        if run.truth is not None:
            axs[0].plot(t, run.truth[:, c], "k-", lw=2, label=f"truth {m.state_names[c]}")
    axs[0].set(xlabel="time step k", ylabel="estimate", title=f"{run.name}: every node's estimate")
    if run.truth is not None:
        axs[0].legend(loc="best", fontsize=8)
    for i in range(nodes):
        axs[1].plot(t[1:], trace[1:, i], lw=0.8)
    axs[1].set(xlabel="time step k", ylabel=f"tr {key}", yscale="log",
               title="the bound each node certifies" if key == "Phi" else "the covariance each node believes")
    save_figure(fig, directory / "fig_estimates.png")
    rmse = run.rmse()
    lines = [f"# {run.name} on {run.log}", "",
             f"Scenario `{run.scenario.name}`, {K1 - 1} steps, {nodes} estimate{'s' if nodes > 1 else ''} "
             f"({'a fusion centre' if nodes == 1 else 'one per node'}); what it needs at run time: `{run.runtime}`"
             + (" (an oracle: a reference, not a filter to deploy)." if run.runtime == "global" else "."),
             ""]
    if run.design is not None:
        lines += [f"Design: gain rule `{run.design['gain_rule']}`"
                  + (f", from `{run.design['schedule']}` (verdict there: {known_verdict(run.design.get('verdict'))})"
                     if "schedule" in run.design else ", the scenario's design defaults") + ".", ""]
    if run.verdict is not None:
        lines += [f"Its bound's verdict over this log's horizon: **{run.verdict}** (designer.verdict: finite, "
                  "steady and below the open-loop covariance to be certified; properties of the bound itself, not a "
                  "check of it against this log's errors, which the table below compares).", ""]
    d = run.diverged
    if d is not None:
        lines += [f"**Diverged** at step {d['step']} (node {d['node']}): {d.get('reason', '')}; the estimates after "
                  "it are not numbers.", ""]
    if rmse is not None:
        over = "each node on its region, which it carries" if run.carried is not None else \
            "position" if run.scenario.model.position_index else "the whole state"
        lines += [f"RMSE against the log's truth ({over}, over steps 1..K and the nodes): {rmse:.4g}.", ""]
        region = None if run.carried is not None else run.rmse_region()
        if region is not None:  # the model's REGIONS: as the studies and a design's validation score every filter
            lines += [f"On each node's region (the model's `REGIONS`, over steps 1..K and the nodes): {region:.4g}.",
                      ""]
        per = run.per_node()
        what = "bound" if key == "Phi" else "believed covariance"
        lines += [f"Per node: its RMSE and the mean over the steps of its squared error over the trace of its {what} "
                  f"(`error² / tr {key}`; for a mean-square bound about 1 or less on average over runs, one run "
                  "scatters), with its final trace.", "",
                  f"| node | RMSE | error² / tr {key} | final tr {key} |", "|---|---|---|---|"]
        final = np.where(run.valid[-1], trace[-1], np.nan)
        for i in range(nodes):
            lines.append(f"| {i} | {per['rmse'][i]:.4g} | {per['energy'][i]:.3g} | {final[i]:.4g} |")
        lines.append("")
        above = int(np.sum(per["energy"] > 1.0))
        if above and key == "Phi":  # said plainly: a verdict is not a check on this run
            lines += [f"On this log the squared error exceeds the bound on average at {above} of {nodes} nodes. The "
                      "bound is a mean over runs (and its linearisation remainders are not in it): one run cannot "
                      "refute it, nor confirm it; `study consensus-robot` checks it on many runs.", ""]
    lines += [f"Messages per step: {float(np.mean(run.messages)):.4g}.", "",
              "Files: `estimates.npz` (`x_hat` (K + 1, nodes, n_x), " + f"`{key}`, `valid`, `messages`"
              + (", `x` the truth" if run.truth is not None else "") + "), `estimates.csv` (step, node, the "
              f"estimate's components, tr {key}), `fig_estimates.png`.", "", "![estimates](fig_estimates.png)", ""]
    atomic_write(directory / "report.md", lambda fh: fh.write("\n".join(lines).encode()))
