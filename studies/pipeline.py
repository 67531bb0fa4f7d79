"""One study pipeline: every study is a configuration of it.

A study is a :class:`Study` in its own module (``studies/<name>.py`` defines ``STUDY``),
registered by name in :data:`studies.study_registry.STUDIES`.  The configuration says what the study is about
(:class:`studies.study_registry.StudyText`, the report's words), which scenarios it runs on by default and
which it accepts, its default sizes and its own options, and four functions:

* ``plan(scenario, options) -> Plan`` — the Monte Carlo task of one scenario (a
  picklable callable of a chunk of runs), its configuration for the chunk store and
  anything to do in the parent first (compiling kernels that forked workers inherit);
* ``summarise(scenario, mc, options) -> dict`` — the scenario's results (filters,
  sweeps, the paper's numbers, ...) from the runner's per-run arrays;
* ``table(results) -> str`` — ``table.md``;
* ``figures(out, results, scenarios, arrays)`` — the PNG figures, made with :mod:`studies.figures`
  (with ``out``, drawn by a helper process forked before the study computes: it must need
  nothing the computation leaves on the scenarios).

:func:`run_study` does the rest the same way for every study: it checks the options
(an option a study does not take is an error, not silently ignored), builds the
scenarios (built-in names, model files, in-memory models), refuses a scenario the study
cannot run on with the reason, runs each scenario's task through :mod:`studies.runner`
(in this process, local processes or Dask; resumable from ``out``), stamps the results
header (``cfdesign.study/1``) and returns a :class:`StudyResult` whose ``save`` writes
``results.json``, ``table.md``, the figures and the reports.  A new study is one module
with a ``STUDY`` and one line in :data:`studies.study_registry.STUDIES`.
"""
from __future__ import annotations

import contextlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from designer.design import DesignOptions
from designer.fileio import writing
from designer.validation import ComputationError, InputError, NonFiniteError, check_int

from .invocation import study_invocation
from .runner import Backend, MonteCarloResult, every_core, monte_carlo
from .study_registry import StudyText, get_study

__all__ = ["Plan", "Study", "StudyOptions", "StudyResult", "run_study", "naming_filter"]

MAX_RUNS = 1_000_000  # beyond this the per-run results alone outgrow a machine's memory
MAX_PARTICLES = 10_000_000  # per filter; a particle filter's state is (particles x n_x) doubles several times over

@contextlib.contextmanager
def naming_filter(name: str | Sequence[str], runs: Sequence[int] | None = None):
    """A study's filter call: a :class:`~designer.validation.NonFiniteError` from it is re-raised naming the
    filter as the study's results name it (``name``, or ``name[row]`` for a call whose rows are several
    filters), and the study's run (``runs[row]``: the run of each row the call was given; None: not known) and
    step."""
    try:
        yield
    except NonFiniteError as exc:
        label = name if isinstance(name, str) else name[exc.row]
        where = "" if runs is None else f"run {int(runs[exc.row])}, "
        raise ComputationError(f"filter {label!r} failed at {where}step {exc.step}: {exc}") from exc


@dataclass(frozen=True)
class StudyOptions:
    """The checked options of one study run, as ``plan`` and ``summarise`` see them.

    ``extra`` holds the study's own options (its :attr:`Study.options` with the given
    values); ``design`` the design options of the consensus designs (studies that use them).
    """

    runs: int
    particles: int | None
    seed: int
    chunk_size: int
    backend: Backend
    design: DesignOptions
    extra: Mapping[str, Any]

    def __getitem__(self, name: str):
        return self.extra[name]


@dataclass(frozen=True)
class Plan:
    """One scenario's Monte Carlo work: the task, its store label and configuration."""

    task: Callable
    label: str
    config: Mapping[str, Any]
    runs: int | None = None  # default: the study's runs
    before: Callable[[], None] | None = None  # run in the parent first (not for Dask)
    shares: int = 1  # into how many shares the task can cut a chunk (studies.runner.monte_carlo's shares)


@dataclass(frozen=True)
class Study:
    """A study as a configuration of the pipeline (see the module docstring).

    Parameters
    ----------
    name, text
        The study's name and its report texts.
    scenarios : tuple of str
        The scenarios it runs on when none is given.
    runs : int or mapping
        Default Monte Carlo runs (a mapping: per default scenario, with key ``None`` for others).
    particles : int or None
        Default particles of its particle filters (None: it has none; ``particles`` is an error).
    chunk_size : int or callable ``(scenario, runs) -> int``
        Runs per stored chunk, or the study's rule for it from the scenario's size and the runs (part of the study
        and of the model: never derived from the backend).
    options : mapping
        The study's own options and their defaults (e.g. ``engine``, ``schedule``).
    uses_design : bool
        It takes the design options (``mode``, ``dos``, ``fdi``, ``delta``, ``amplitude``).
    many_scenarios : bool
        It runs on several scenarios at once (its ``combine`` merges their blocks).
    accepts : callable ``(scenario) -> str | None``
        Why a scenario cannot be studied (None: it can).
    combine : callable ``(blocks) -> dict``, optional
        Merge the per-scenario blocks (default: the single block).
    check : callable ``(options) -> None``, optional
        Further checks of the study's own options, before any computation.
    uses : callable ``(scenario, options) -> (gain rules, particles, gain rules at the main setting only)``, optional
        What the study's filters need on the scenario for these options, for its memory estimate
        (:func:`studies.memory.study_need`): the gain rules whose designs it makes, whether it runs particle
        filters and the rules whose filters it runs at its main setting only, not at a sweep's settings (default:
        every rule at every setting, and the particle filters when the study has them).
    min_runs : int
        Fewest runs the study's statistics need.
    every_core : bool
        With no backend given, its chunks run in one forked worker process per usable core
        (:func:`designer.cores.usable_cores`; :func:`default_backend`), not in the calling process alone: for
        a study whose default size keeps a core busy for minutes.  The numbers do not depend on it.
    """

    name: str
    text: StudyText
    scenarios: tuple[str, ...]
    runs: int | Mapping[str | None, int]
    particles: int | None
    chunk_size: int | Callable[[Any, int], int]
    plan: Callable[[Any, StudyOptions], Plan]
    summarise: Callable[[Any, MonteCarloResult, StudyOptions], dict]
    table: Callable[[dict], str]
    figures: Callable[[Path, dict, Mapping[str, Any], Mapping[str, Mapping[str, np.ndarray]]], None]
    options: Mapping[str, Any] = field(default_factory=dict)
    uses_design: bool = False
    many_scenarios: bool = False
    accepts: Callable[[Any], str | None] = lambda sc: None
    combine: Callable[[dict], dict] | None = None
    check: Callable[[StudyOptions], None] | None = None
    uses: Callable[[Any, StudyOptions], tuple] | None = None
    min_runs: int = 2
    every_core: bool = False

    def default_backend(self) -> Backend:
        """Where the chunks run when the caller gives no backend: this process, or for a study with
        ``every_core`` one worker process per usable core (this process when it may use one core only)."""
        return every_core() if self.every_core else Backend()

    def default_runs(self, scenario: str) -> int:
        if isinstance(self.runs, Mapping):
            return int(self.runs.get(scenario, self.runs.get(None, next(iter(self.runs.values())))))
        return int(self.runs)


@dataclass(frozen=True, eq=False)
class StudyResult:
    """What a study computed (what ``cfdesign study`` writes).

    Attributes
    ----------
    study : Study
    results : dict
        The content of ``results.json`` (schema ``cfdesign.study/1``).
    scenarios : dict
        Scenario name -> the Scenario it ran on.
    arrays : dict
        Scenario name -> the runner's per-run arrays (first axis: the run).
    """

    study: Study
    results: dict
    scenarios: Mapping[str, Any]
    arrays: Mapping[str, Mapping[str, np.ndarray]]

    @property
    def filters(self) -> dict:
        return self.results["filters"]

    def __getitem__(self, key):
        return self.results[key]

    def save(self, directory, helper=None) -> Path:
        """Write the figures, ``table.md``, ``results.json`` and ``report.html`` / ``report.md`` into ``directory``
        (:func:`studies.outputs.save_study`).

        ``helper``: a :class:`studies.figures.FigureHelper` started for this study, which draws the figures
        (this process draws them if it cannot).  Refused when ``directory`` is, lies inside or contains a model
        file of the study's scenarios (:func:`designer.fileio.check_apart`).
        """
        from .outputs import save_study

        return save_study(self, directory, helper)


def _study_assignments(study: Study, assignments) -> tuple[list, dict]:
    """Split ``NAME=VALUE`` assignments into the scenarios' and the study's own options (``study.options``).

    A study option's value is read as JSON (``3``, ``true``, ``[0, 0.2]``), else kept as the string.
    """
    rest, own = [], {}
    for a in assignments or ():
        name, sep, value = str(a).partition("=")
        name = name.strip()
        if sep and name in study.options:
            try:
                own[name] = json.loads(value)
            except json.JSONDecodeError:
                own[name] = value.strip()
        else:
            rest.append(a)
    return rest, own


def _route(names: Sequence[str], specs: Mapping[str, Any], assignments) -> dict[str, list[str]]:
    """Each ``NAME=VALUE`` to every scenario that has the parameter NAME; unknown names are an error."""
    have = {sc: {p.name for p in specs[sc].params} for sc in names}
    out: dict[str, list[str]] = {sc: [] for sc in names}
    for a in assignments or ():
        name = str(a).split("=", 1)[0].strip()
        hit = [sc for sc in names if name in have[sc]]
        if not hit:
            raise InputError(f"--set {name}: no parameter of that name in the scenarios ({', '.join(names)}); "
                             "see 'cfdesign scenarios'")
        for sc in hit:
            out[sc].append(a)
    return out


def _scenarios(study: Study, targets, overrides, assignments) -> list:
    """Build the scenarios to run on: names and model files (with overrides), or built scenarios."""
    from .scenarios import Scenario, get_spec, load_scenario

    targets = list(study.scenarios) if targets is None else list(targets)
    if not targets:
        raise InputError(f"study {study.name!r} needs at least one scenario")
    if len(targets) > 1 and not study.many_scenarios:
        raise InputError(f"study {study.name!r} runs on one scenario at a time, got {len(targets)}")
    names = [t for t in targets if not isinstance(t, Scenario)]
    specs = {str(t): get_spec(t) for t in names}
    routed = _route([str(t) for t in names], specs, assignments) if len(targets) > 1 else \
        {str(t): list(assignments or ()) for t in names}
    built = []
    for t in targets:
        if isinstance(t, Scenario):
            built.append(t)
            continue
        known = {p.name for p in specs[str(t)].params}
        ov = {k: v for k, v in (overrides or {}).items() if k in known or len(targets) == 1}
        built.append(load_scenario(t, ov, routed[str(t)]))
    seen = [sc.name for sc in built]
    if len(set(seen)) != len(seen):
        raise InputError(f"the scenarios must differ, got {seen}")
    for sc in built:
        why = study.accepts(sc)
        if why:
            raise InputError(f"study {study.name!r} cannot run on scenario {sc.name!r}: {why}")
    return built


def run_study(name: str, targets=None, *, out=None, runs: int | None = None, particles: int | None = None,
              seed: int = 0, backend: Backend | None = None, force: bool = False, quiet: bool = True,
              options: DesignOptions | None = None, overrides: Mapping[str, Any] | None = None, assignments=(),
              chunk_size: int | None = None, **study_options) -> StudyResult:
    """Run study ``name`` on ``targets`` (default: its own scenarios) and, with ``out``, write its outputs.

    See :func:`studies.api.study` for the parameters.  With ``out``, the directory's one-writer
    lock (:func:`designer.fileio.output_lock`) is held from before the first computation until
    the last file is written: a second process on the same ``out`` is refused, and ``force``
    never deletes under a running writer.
    """
    get_study(name)
    with writing(out):
        return _run_study(name, targets, out=out, runs=runs, particles=particles, seed=seed, backend=backend,
                          force=force, quiet=quiet, options=options, overrides=overrides, assignments=assignments,
                          chunk_size=chunk_size, **study_options)


def _run_study(name: str, targets, *, out, runs, particles, seed, backend, force, quiet, options, overrides,
               assignments, chunk_size, **study_options) -> StudyResult:
    study = get_study(name)
    t_start = time.perf_counter()
    assignments, own = _study_assignments(study, assignments)
    study_options = {**own, **study_options}
    unknown = [k for k in study_options if k not in study.options]
    if unknown:
        known = ", ".join(study.options) or "none"
        raise InputError(f"option --{unknown[0].replace('_', '-')} does not apply to study {name!r} (its own "
                         f"options: {known})")
    if particles is not None and study.particles is None:
        raise InputError(f"option --particles does not apply to study {name!r} (it runs no particle filter)")
    design = options or DesignOptions()
    if not study.uses_design and any(v is not None for v in design.as_dict().values()):
        given = next(k for k, v in design.as_dict().items() if v is not None)
        raise InputError(f"option --{given.replace('_', '-')} does not apply to study {name!r}")
    seed = check_int("seed", seed, 0)
    chunk = None if chunk_size is None else check_int("chunk_size", chunk_size, 1)
    backend = backend or study.default_backend()
    if not isinstance(backend, Backend):
        raise InputError(f"backend must be a studies.runner.Backend, got {type(backend).__name__}")
    if runs is not None:
        runs = check_int("runs", runs, study.min_runs, MAX_RUNS)
    if particles is not None:
        particles = check_int("particles", particles, 2, MAX_PARTICLES)
    scenarios = _scenarios(study, targets, overrides, assignments)
    extra = {**study.options, **study_options}
    invocation = study_invocation(
        study, scenarios, runs=[runs if runs is not None else study.default_runs(sc.source or sc.name)
                                for sc in scenarios],
        particles=particles if particles is not None else study.particles, seed=seed, design=design, options=extra)
    attack = design.attack_overrides()
    if any(v is not None for v in attack.values()):  # --dos/--fdi/--delta/--amplitude: the scenarios' attacks
        scenarios = [sc.with_attacks(**attack) for sc in scenarios]
        design = DesignOptions(**{**design.as_dict(), **{k: None for k in attack}})
    if backend.kind == "dask":
        mem = [sc.name for sc in scenarios if sc.source is None]
        if mem:
            raise InputError(f"an in-memory model ({mem[0]}) cannot be sent to a Dask cluster; write it to a model "
                             "file")
    helper = None
    if out is not None:  # draws the figures, and imports matplotlib while the study computes
        from .outputs import figure_helper

        helper = figure_helper(study, {sc.name: sc for sc in scenarios})
    try:
        return _compute(study, name, scenarios, out=out, runs=runs, particles=particles, seed=seed, chunk=chunk,
                        backend=backend, design=design, extra=extra, force=force, quiet=quiet, t_start=t_start,
                        helper=helper, invocation=invocation)
    finally:
        if helper is not None:
            helper.close()


def _compute(study: Study, name: str, scenarios, *, out, runs, particles, seed, chunk, backend, design, extra,
             force, quiet, t_start, helper, invocation) -> StudyResult:
    from .results import study_header

    from .memory import check, study_need

    blocks, arrays, built = {}, {}, {}
    def options_of(sc):
        r = runs if runs is not None else study.default_runs(sc.source or sc.name)
        size = chunk if chunk is not None else study.chunk_size(sc, r) if callable(study.chunk_size) \
            else study.chunk_size
        return StudyOptions(r, particles if particles is not None else study.particles, seed,
                            check_int("chunk_size", size, 1), backend, design, extra)

    chosen = [(sc, options_of(sc)) for sc in scenarios]
    for sc, so in chosen:  # every scenario's options and memory before the first computes
        if study.check is not None:
            study.check(so)
        check(study_need(name, sc, so, None if study.uses is None else study.uses(sc, so)))
    for sc, so in chosen:
        plan = study.plan(sc, so)
        if plan.before is not None and backend.kind != "dask":
            plan.before()
        # the stored runs are those of this model's content (Scenario.digest), wherever its file lies
        mc = monte_carlo(plan.task, runs=plan.runs or so.runs, seed=seed, chunk_size=so.chunk_size, backend=backend,
                         store=out, label=plan.label, config={**plan.config, "model": sc.digest}, force=force,
                         quiet=quiet, shares=plan.shares)
        blocks[sc.name] = study.summarise(sc, mc, so)
        arrays[sc.name], built[sc.name] = mc.arrays, sc
    body = study.combine(blocks) if study.combine is not None else next(iter(blocks.values()))
    first = next(iter(blocks.values()))
    results = study_header(name, body.pop("scenario", ", ".join(blocks)), runs=body.pop("runs", first["runs"]),
                           particles=body.pop("particles", particles if particles is not None else study.particles),
                           steps=body.pop("steps", first["steps"]), seed=seed,
                           assumptions=body.pop("assumptions", []))
    results.update(body)
    results["invocation"] = invocation
    results["wall_time_s"] = time.perf_counter() - t_start
    res = StudyResult(study, results, built, arrays)
    if out is not None:
        res.save(out, helper)
    return res
