"""The public functions behind every command of the ``cfdesign`` command line.

Design scripts call these directly; the CLI is a thin layer over them and prints
what they return, so a script and the CLI give the same numbers.  Every function
takes what to run on as its first argument: a built-in scenario name, a model file
path (``"my_model.py"``), a built :class:`~studies.scenarios.Scenario`, or an
in-memory :class:`designer.Model` (then ``network=``, ``attacks=``, ``design_defaults=``,
``steps=``, ``x0=`` and ``inputs=`` play the part of the model file's ``NETWORK``,
``ATTACKS``, ``DESIGN``, ``STEPS``, ``X0`` and ``inputs``).

=========================  ==========================================================
``list_scenarios()``        ``cfdesign scenarios``
``simulate(...)``           ``cfdesign simulate``      -> :class:`Simulation`
``design(...)``             ``cfdesign design``        -> :class:`~studies.consensus_design.Design`
``feasibility(...)``        ``cfdesign feasibility``   -> :class:`~studies.feasibility_map.FeasibilityMap`
``study(...)``              ``cfdesign study``         -> :class:`~studies.pipeline.StudyResult`
``report(directory)``       ``cfdesign report``
=========================  ==========================================================

Every result object has ``.save(directory)`` (``Simulation.save(file)``), which writes
what the command writes.  Each function computes with BLAS and LAPACK on one thread
(:class:`designer.cores.one_blas_thread`), whatever ``OPENBLAS_NUM_THREADS`` says, as the
command line does: the same numbers in a script, a notebook and the shell.

Before anything is built or computed, every function checks the types of its arguments
(an :class:`~designer.validation.InputError` naming the parameter: a string for ``steps``,
a number for ``out``, ``"yes"`` for ``force``...) and then the memory the command will need
(:mod:`studies.memory`: refused, with the figure and what to reduce, when it exceeds the
memory available).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from designer.attacks import AttackSpec
from designer.cores import one_blas_thread
from designer.design import DesignOptions
from designer.fileio import check_output_file, replaced_outputs, write_npz, writing
from designer.network import SensorNetwork
from designer.validation import InputError, check_bool, check_int, check_path, check_strings, check_type

from . import memory
from .scenarios import CHANNEL_TYPES, SCENARIOS, Scenario, scenario_of

__all__ = ["list_scenarios", "simulate", "Simulation", "design", "feasibility", "study", "report",
           "DesignOptions"]


def list_scenarios() -> list[dict]:
    """Describe every built-in scenario: name, dimensions, source paper, parameters and assumptions."""
    return [spec.describe() for spec in SCENARIOS.values()]


def _check_arguments(*, out=None, network=None, attacks=None, design_defaults=None, inputs=None, overrides=None,
                     assignments=(), force=False, quiet=True, dask_security=None, channel=None) -> None:
    """The types of the arguments every command shares, checked before anything is built or computed (the
    values are checked where they are used)."""
    check_path("out", out, optional=True)
    check_type("network", network, SensorNetwork, "a designer.SensorNetwork", optional=True)
    check_type("attacks", attacks, AttackSpec, "a designer.AttackSpec", optional=True)
    check_type("design_defaults", design_defaults, DesignOptions, "a designer.DesignOptions", optional=True)
    if inputs is not None and not callable(inputs):
        raise InputError(f"inputs must be a function of the step count returning the (steps, n_u) known inputs, "
                         f"got {type(inputs).__name__}")
    check_type("overrides", overrides, Mapping, "a mapping {parameter name: value}", optional=True)
    check_strings("assignments", assignments, "'NAME=VALUE' strings")
    check_bool("force", force)
    check_bool("quiet", quiet)
    check_path("dask_security", dask_security, optional=True)
    check_type("channel", channel, CHANNEL_TYPES, "one of " + ", ".join(t.__name__ for t in CHANNEL_TYPES),
               optional=True)


def _scenario(scenario, network, attacks, design_defaults, steps, x0, inputs, overrides, assignments) -> Scenario:
    return scenario_of(scenario, network=network, attacks=attacks, design=design_defaults, steps=steps, x0=x0,
                       inputs=inputs, overrides=overrides, assignments=assignments)


def _options(options: DesignOptions | None, given: Mapping[str, Any]) -> DesignOptions:
    """``options`` with the keyword options that are set replacing its values."""
    if options is not None and not isinstance(options, DesignOptions):
        raise InputError(f"options must be a designer.DesignOptions, got {type(options).__name__}")
    kw = {k: v for k, v in given.items() if v is not None}
    return (options or DesignOptions()).merged(DesignOptions(**kw)) if kw else (options or DesignOptions())


@dataclass(frozen=True, eq=False)
class Simulation:
    """A seeded simulated run of a scenario (what ``cfdesign simulate`` writes).

    ``x`` (K+1, n_x) true states, ``z`` (K, n_z) stacked measurements (``z[k]`` measures
    ``x[k+1]``), ``y`` (K, sensors, max n_z_i) per sensor (NaN-padded), ``inputs``,
    ``modes`` (switching models, else None).
    """

    scenario: Scenario
    seed: int
    x: np.ndarray
    z: np.ndarray
    y: np.ndarray
    inputs: np.ndarray
    modes: np.ndarray | None

    def save(self, path) -> Path:
        """Write the ``.npz`` file (arrays above plus sensor and state names, scenario, seed, parameters)."""
        path = check_output_file("out", path, ".npz")
        sc = self.scenario
        arrays = dict(x=self.x, y=self.y, z=self.z, inputs=self.inputs,
                      sensor_names=np.array([s.name for s in sc.model.sensors]),
                      state_names=np.array(sc.model.state_names), scenario=np.array(sc.name),
                      seed=np.array(self.seed), params=np.array(json.dumps(dict(sc.params))))
        if self.modes is not None:
            arrays["modes"] = self.modes
        return write_npz(path, **arrays)


@one_blas_thread()
def simulate(scenario, *, steps: int | None = None, seed: int = 0, out: str | Path | None = None,
             network: SensorNetwork | None = None, attacks: AttackSpec | None = None, x0=None,
             inputs: Callable | None = None, overrides: Mapping[str, Any] | None = None,
             assignments: Sequence[str] = ()) -> Simulation:
    """Simulate a scenario (truth and measurements) from ``numpy.random.default_rng(SeedSequence(seed))``.

    Parameters
    ----------
    scenario : str, path, Scenario or designer.Model
    steps : int, optional
        Horizon (default: the scenario's).
    seed : int
        The run's seed; the same seed gives the same file bit for bit.
    out : path, optional
        Write the ``.npz`` file there (see :meth:`Simulation.save`).
    overrides, assignments
        Named scenario parameters (a mapping, or ``NAME=VALUE`` strings as ``--set``).

    Returns
    -------
    Simulation
    """
    seed = check_int("seed", seed, 0)
    if steps is not None:
        steps = check_int("steps", steps, 1)
    _check_arguments(out=out, network=network, attacks=attacks, inputs=inputs, overrides=overrides,
                     assignments=assignments)
    if out is not None:
        check_output_file("out", out, ".npz")
    sc = _scenario(scenario, network, attacks, None, None, x0, inputs, overrides, assignments)
    memory.check(memory.simulate_need(sc, sc.steps if steps is None else steps))
    traj = sc.simulate(np.random.default_rng(np.random.SeedSequence(seed)), steps)
    if not (np.all(np.isfinite(traj.x)) and np.all(np.isfinite(traj.z))):
        raise InputError("the simulated states or measurements are not finite; check X0, the prior and the model "
                         "(parameter x0 or the model's f and h)")
    sim = Simulation(sc, seed, traj.x, traj.z, traj.per_sensor(sc.model), traj.inputs, traj.modes)
    if out is not None:
        sim.save(out)
    return sim


@one_blas_thread()
def design(scenario, *, mode: str | None = None, steps: int | None = None, seed: int = 0,
           epsilon: float | None = None, sigma: float | None = None, beta: float | None = None,
           tau: float | None = None, dos: float | None = None, fdi: float | None = None,
           delta: float | None = None, amplitude: float | None = None, u_scale=None, v_scale=None,
           linearization: str | None = None, radius: float | None = None, gate: float | None = None,
           exchange: str | None = None, robustness: float | None = None, rounds: int | None = None,
           bank: int | None = None,
           options: DesignOptions | None = None, network: SensorNetwork | None = None, attacks: AttackSpec | None = None,
           design_defaults: DesignOptions | None = None, x0=None, inputs: Callable | None = None,
           overrides: Mapping[str, Any] | None = None, assignments: Sequence[str] = (),
           out: str | Path | None = None):
    """Design the consensus filter of a scenario along a seeded simulated run.

    Parameters
    ----------
    scenario : str, path, Scenario or designer.Model
        What to design for; it needs a sensor network (a model file's ``NETWORK``).
    mode : str, a gain rule of :data:`designer.gain_rules.GAIN_RULES`
        The paper's fixed choices or the convex tuning layer (both ``local``: computed online at
        each node), the mean-square-error gains (``global``: an oracle needing the network's
        joint state, a reference of what the structure can reach, not a design to deploy), or the
        gains designed offline for the attack statistics that every node applies with what it knows
        (``scheduled``, :mod:`designer.scheduled`) (default: paper).
    steps, seed : int
        Horizon of the run (default: the scenario's) and its seed (truth and measurements
        from ``SeedSequence(seed).spawn(2)[0]``, channel attacks from ``[1]``).
    epsilon, sigma, beta, tau, u_scale, v_scale, linearization, radius, gate, exchange, robustness, rounds, bank
        Design options (:class:`designer.DesignOptions`); ``None`` keeps the scenario's
        default, then the package's.
    dos, fdi, delta, amplitude
        Override the attack specification (every channel and uplink; the FDI bound; the
        injected signal's amplitude).
    options : DesignOptions, optional
        All of the above in one object; the keywords that are set replace its values.
    out : path, optional
        Write ``schedule.json``, ``schedule.npz`` and the design report there.

    Returns
    -------
    Design
        ``.gain_rule`` (:class:`designer.gain_rules.GainRule`: its ``runtime``, what a node ``needs``
        to apply it, ``deployable``), ``.feasible``, ``.violations``, ``.reason()``, ``.certified``,
        ``.verdict`` (``certified``, ``vacuous``, ``not steady`` or ``infeasible``:
        :mod:`designer.verdict`), ``.verdict_detail`` (the numbers behind it), ``.verdict_line()``,
        ``.trace_bound`` (nodes, steps), the
        ``.schedule`` (gains ``K``, ``C``, bounds ``Phi``, ``sigma``, ``beta``), the full
        ``.result`` of every node, and ``.save(directory)``.  A design that is infeasible or not
        certified is returned (and written), not raised: check ``.certified`` (the command line
        exits 1 on it).
    """
    from .consensus_design import run_design

    seed = check_int("seed", seed, 0)
    if steps is not None:
        steps = check_int("steps", steps, 1)
    _check_arguments(out=out, network=network, attacks=attacks, design_defaults=design_defaults, inputs=inputs,
                     overrides=overrides, assignments=assignments)
    opts = _options(options, dict(mode=mode, epsilon=epsilon, sigma=sigma, beta=beta, tau=tau, dos=dos, fdi=fdi,
                                  delta=delta, amplitude=amplitude, u_scale=u_scale, v_scale=v_scale,
                                  linearization=linearization, radius=radius, gate=gate, exchange=exchange,
                                  robustness=robustness, rounds=rounds, bank=bank))
    sc = _scenario(scenario, network, attacks, design_defaults, steps, x0, inputs, overrides, assignments)
    memory.check(memory.design_need(sc, opts, sc.steps if steps is None else steps))
    with writing(out):  # the one-writer lock, taken before any computation
        res = run_design(sc, opts, steps=steps, seed=seed)
        if out is not None:
            res.save(out)
    return res


@one_blas_thread()
def feasibility(scenario, grid: str | Sequence[str], *, mode: str | None = None, epsilon: float | None = None,
                sigma: float | None = None, beta: float | None = None, tau: float | None = None,
                dos: float | None = None, fdi: float | None = None, delta: float | None = None,
                amplitude: float | None = None, u_scale=None, v_scale=None, linearization: str | None = None,
                radius: float | None = None, gate: float | None = None, exchange: str | None = None,
                robustness: float | None = None, rounds: int | None = None, bank: int | None = None,
                options: DesignOptions | None = None,
                network: SensorNetwork | None = None, attacks: AttackSpec | None = None,
                design_defaults: DesignOptions | None = None, x0=None, inputs: Callable | None = None,
                overrides: Mapping[str, Any] | None = None, assignments: Sequence[str] = (),
                workers: int | None = None, dask: str | None = None, dask_security: str | None = None,
                backend=None, force: bool = False, quiet: bool = True, out: str | Path | None = None):
    """Map where the consensus design admits a bounded steady-state bound at the operating point.

    Parameters
    ----------
    scenario : str, path, Scenario or designer.Model
    grid : str or sequence of str
        ``NAME=START:STOP:COUNT`` per grid parameter (dos, fdi, delta, amplitude, tau, sigma,
        beta, epsilon, u_scale, v_scale); the grid's value replaces the option of that name.
        The values are the exact numbers meant (``dos=0:0.6:7``: 0, 0.1, ..., 0.6; see
        :mod:`studies.feasibility_map`).
    mode, epsilon, sigma, beta, tau, dos, fdi, delta, amplitude, u_scale, v_scale, linearization, radius, exchange,
    robustness, rounds, bank, options
        The same design options as :func:`design`, with the same defaults.
    workers, dask, dask_security, backend
        Where the chunks of grid points run (the map does not depend on it); ``dask_security``: a
        JSON file of TLS options for the Dask scheduler (:func:`studies.runner.load_security`).
    force, quiet
        Recompute points stored in ``out``; no progress bar.
    out : path, optional
        Write ``feasibility.csv``, ``feasibility.json``, the heat map and the report there; the
        finished chunks are kept under ``out/.chunks`` so that an interrupted map resumes.

    Returns
    -------
    FeasibilityMap
        ``.rows``, ``.feasible``, ``.trace_bound``, ``.verdict`` and ``.certified`` shaped like the grid,
        ``.verdict_counts``, ``.failures`` (the points
        whose design or iteration raised: not feasible, ``binding`` ``"failed: <reason>"``; the others
        are mapped), ``.save(directory)``.

    Notes
    -----
    :func:`design` checks the conditions along one simulated run; this checks the steady
    state of the recursion at the operating point with the expected DoS pattern.  See
    :mod:`studies.feasibility_map` for when the two disagree.
    """
    from .feasibility_map import run_feasibility
    from .runner import Backend, make_backend

    _check_arguments(out=out, network=network, attacks=attacks, design_defaults=design_defaults, inputs=inputs,
                     overrides=overrides, assignments=assignments, force=force, quiet=quiet,
                     dask_security=dask_security)
    check_type("backend", backend, Backend, "a studies.runner.Backend", optional=True)
    if gate:
        raise InputError("gate does not apply to feasibility: the maps iterate the bound at an operating point, "
                         "with no packets to test (use it with design or study)")
    opts = _options(options, dict(mode=mode, epsilon=epsilon, sigma=sigma, beta=beta, tau=tau, dos=dos, fdi=fdi,
                                  delta=delta, amplitude=amplitude, u_scale=u_scale, v_scale=v_scale,
                                  linearization=linearization, radius=radius, exchange=exchange,
                                  robustness=robustness, rounds=rounds, bank=bank))
    if backend is None:
        backend = make_backend(workers, dask, dask_security)
    elif workers is not None or dask is not None or dask_security is not None:
        raise InputError("give either backend or workers/dask, not both")
    sc = _scenario(scenario, network, attacks, design_defaults, None, x0, inputs, overrides, assignments)
    with writing(out):  # the one-writer lock, taken before any computation
        fmap = run_feasibility(sc, grid, opts, backend=backend, store=out, force=force, quiet=quiet)
        if out is not None:
            fmap.save(out)
    return fmap


@one_blas_thread()
def study(name: str, scenario=None, *, out: str | Path | None = None, runs: int | None = None,
          particles: int | None = None, seed: int = 0, workers: int | None = None, dask: str | None = None,
          dask_security: str | None = None, backend=None, force: bool = False, quiet: bool = True, options: DesignOptions | None = None,
          mode: str | None = None, dos: float | None = None, fdi: float | None = None,
          delta: float | None = None, amplitude: float | None = None, network: SensorNetwork | None = None,
          attacks: AttackSpec | None = None, design_defaults: DesignOptions | None = None, x0=None,
          inputs: Callable | None = None, channel=None, overrides: Mapping[str, Any] | None = None,
          assignments: Sequence[str] = (), **study_options):
    """Run the Monte Carlo study ``name`` on a scenario (or on its default scenarios).

    Parameters
    ----------
    name : str
        A study of :data:`studies.pipeline.STUDIES` (``comparison``, ``consensus-robot``,
        ``rrp-deception``, ...).
    scenario : str, path, Scenario, designer.Model or a sequence of them, optional
        What to run on (default: the study's own scenarios).
    runs, particles, seed
        Monte Carlo runs, particles of the particle filters, the study seed (default: the study's).
    workers, dask, dask_security, backend, force, quiet
        The Monte Carlo runner (identical numbers on every backend; ``dask_security``: a JSON file
        of TLS options for the Dask scheduler, :func:`studies.runner.load_security`; ``out`` keeps finished chunks
        so that an interrupted study resumes, ``force`` recomputes them).
    options, mode, dos, fdi, delta, amplitude
        Design options of the consensus designs and attack overrides (studies that use them).
    network, attacks, design_defaults, x0, inputs, channel
        For an in-memory model (as for :func:`design`; ``channel`` is a model file's ``CHANNEL``).
    study_options
        Options of that study only (e.g. ``engine`` of the particle-filter studies,
        ``schedule`` of consensus-robot); an option a study does not take is an error.
    out : path, optional
        Write ``results.json`` (schema ``cfdesign.study/1``), ``table.md``, the figures and the
        reports there.

    Returns
    -------
    StudyResult
        ``.results`` (the ``results.json`` content), ``.filters``, ``.arrays`` (the runner's
        per-run arrays), ``.save(directory)``.
    """
    from .pipeline import run_study
    from .runner import make_backend

    check_type("name", name, str, "the name of a study (studies.pipeline.STUDIES)")
    _check_arguments(out=out, network=network, attacks=attacks, design_defaults=design_defaults, inputs=inputs,
                     overrides=overrides, assignments=assignments, force=force, quiet=quiet,
                     dask_security=dask_security, channel=channel)
    if backend is None:  # none of them given: the study's default backend (Study.default_backend)
        if any(v is not None for v in (workers, dask, dask_security)):
            backend = make_backend(workers, dask, dask_security)
    elif workers is not None or dask is not None or dask_security is not None:
        raise InputError("give either backend or workers/dask, not both")
    opts = _options(options, dict(mode=mode, dos=dos, fdi=fdi, delta=delta, amplitude=amplitude))
    targets = None
    if scenario is not None:
        # names and model files are built by the pipeline (which routes overrides to the scenarios that have
        # them); models and scenarios built here
        in_memory = any(v is not None for v in (network, attacks, design_defaults, x0, inputs, channel))
        targets = [s if isinstance(s, (str, Path)) and not in_memory else
                   scenario_of(s, network=network, attacks=attacks, design=design_defaults, x0=x0, inputs=inputs,
                               channel=channel)
                   for s in (scenario if isinstance(scenario, (list, tuple)) else [scenario])]
        targets = [str(t) if isinstance(t, Path) else t for t in targets]
    return run_study(name, targets, out=out, runs=runs, particles=particles, seed=seed, backend=backend, force=force,
                     quiet=quiet, options=opts, overrides=overrides, assignments=assignments, **study_options)


def report(directory: str | Path) -> tuple[Path, Path]:
    """Write ``report.html`` (self-contained) and ``report.md`` for the results in ``directory``.

    ``directory`` is a study's (``results.json``), a design's (``schedule.json``) or a
    feasibility map's (``feasibility.csv``).  The commands write their reports already; this
    rebuilds them, e.g. after editing the output or for results of an older version.  It holds
    the directory's one-writer lock (a directory another command is writing is refused, naming
    it) and replaces the report's files as a whole (:func:`designer.fileio.replaced_outputs`).
    """
    from .reports import check_directory, write_report

    d = check_directory(directory)
    with writing(d, name="directory", replaces=()), replaced_outputs(d, keep_others=True) as stage:
        write_report(d, into=stage)
    return d / "report.html", d / "report.md"
