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
``filter(...)``             ``cfdesign filter``        -> :class:`FilterRun` (a filter of the comparison on a log)
``node_filter(...)``        (Python only)              -> the filter one node runs, a step at a time
``export(...)``             ``cfdesign export``        -> the node filter's C sources (files written)
=========================  ==========================================================

Every result object has ``.save(directory)`` (``Simulation.save(file)``), which writes
what the command writes.  Each function computes with BLAS and LAPACK on one thread
(:class:`designer.cores.one_blas_thread`), whatever ``OPENBLAS_NUM_THREADS`` says, as the
command line does: the same numbers in a script, a notebook and the shell.

Before anything is built or computed, every function checks the types of its arguments
(an :class:`~designer.validation.InputError` naming the parameter: a string for ``steps``,
a number for ``out``, ``"yes"`` for ``force``...), that no output path is, lies inside or
contains one of its inputs (a design directory, a log, a model file and the modules it imports:
:func:`designer.fileio.check_apart`), and then the memory the command will need
(:mod:`studies.memory`: refused, with the figure and what to reduce, when it exceeds the
memory available).
"""
from __future__ import annotations

import functools
import json
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from designer.attacks import AttackSpec
from designer.cores import one_blas_thread
from designer.design import DesignOptions
from designer.fileio import check_apart, check_output_file, replaced_outputs, write_npz, writing
from designer.network import SensorNetwork
from designer.regions import Carried, region_error2
from designer.validation import InputError, check_bool, check_int, check_path, check_strings, check_type

import studies.memory as memory
from .scenarios import CHANNEL_TYPES, SCENARIOS, Scenario, model_inputs, scenario_of

__all__ = ["list_scenarios", "simulate", "Simulation", "design", "feasibility", "study", "report", "filter",
           "FilterRun", "node_filter", "export", "DesignOptions"]


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


_WHAT = {"data": "the log", "schedule": "the design directory", "design_dir": "the design directory",
         "dask_security": "the TLS options file"}  # what each input path is, in check_apart's messages


def _apart(out, scenario=None, *, kind: str = "directory", **inputs) -> None:
    """Refuse ``out`` equal to, inside or containing an input (the model's files, and each of ``inputs`` by its
    parameter's name), before anything is computed or written (:func:`designer.fileio.check_apart`)."""
    check_apart("out", out, [*model_inputs(scenario), *((k, _WHAT[k], v) for k, v in inputs.items())], kind=kind)


def _applies(filter, designed: str, **given) -> None:
    """Refuse an option of :func:`filter` or :func:`node_filter` that the filter named ``filter`` (None: the designed
    filter of the parameters ``designed`` names) does not use, naming the option and the filters it applies to:
    ``particles``, ``seed`` and ``run`` the particle filters', ``iterations`` HCMCI's consensus rounds
    (:class:`studies.filter_registry.FilterEntry`'s ``particles`` and ``rounds``)."""
    from .comparison import FILTER_REGISTRY
    from .recorded import find_filter

    entry = None if filter is None else find_filter(FILTER_REGISTRY, filter)
    uses = {"particles": "particles", "seed": "particles", "run": "particles", "iterations": "rounds"}
    for option, value in given.items():
        if value is not None and not (entry is not None and getattr(entry, uses[option])):
            having = ", ".join(repr(e.name) for e in FILTER_REGISTRY if getattr(e, uses[option]))
            chosen = f"the designed filter of {designed}" if entry is None else f"filter {entry.name!r}"
            raise InputError(f"{option} does not apply to {chosen}: it applies to {having} only")


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
    ``modes`` (switching models, else None); for a scenario with a sensor network, ``attacks`` (the
    channels' realised DoS/FDI, :class:`filters.attacks.AttackPattern`) and ``received`` (what the
    uplinks delivered to a fusion centre, :func:`studies.recorded.realised_attacks`); ``run``: the study
    run it reproduces (None: the seed's own run).  The file is a log for ``cfdesign filter``
    (:mod:`studies.recorded`).
    """

    scenario: Scenario
    seed: int
    x: np.ndarray
    z: np.ndarray
    y: np.ndarray
    inputs: np.ndarray
    modes: np.ndarray | None
    attacks: Any = None
    received: np.ndarray | None = None
    run: int | None = None

    def save(self, path) -> Path:
        """Write the ``.npz`` file: the arrays above, the log's arrays (:func:`studies.recorded.log_arrays`:
        ``channel_dos``, ``channel_fdi``, ``channel_xi``, ``uplink``), sensor and state names, scenario, seed,
        run and parameters."""
        from .recorded import log_arrays, write_log_csv

        path = check_output_file("out", path, _log_suffix(path))
        _apart(path, self.scenario, kind="file")
        sc = self.scenario
        if path.suffix == ".csv":
            return write_log_csv(path, dict(log_arrays(sc.model, self.z, self.inputs, self.attacks, self.received),
                                            x=self.x), sc.model, sc.network)
        arrays = dict(log_arrays(sc.model, self.z, self.inputs, self.attacks, self.received), x=self.x, y=self.y,
                      sensor_names=np.array([s.name for s in sc.model.sensors]),
                      state_names=np.array(sc.model.state_names), scenario=np.array(sc.name),
                      seed=np.array(self.seed), params=np.array(json.dumps(dict(sc.params))))
        if self.run is not None:
            arrays["run"] = np.array(self.run)
        if self.modes is not None:
            arrays["modes"] = self.modes
        return write_npz(path, **arrays)


def _log_suffix(path) -> str:
    """The suffix a simulated run is written with: ``.csv`` (the log's CSV form) or ``.npz`` (any other)."""
    return ".csv" if str(path).lower().endswith(".csv") else ".npz"


@one_blas_thread()
def simulate(scenario, *, steps: int | None = None, seed: int = 0, run: int | None = None,
             out: str | Path | None = None, network: SensorNetwork | None = None, attacks: AttackSpec | None = None,
             x0=None, inputs: Callable | None = None, overrides: Mapping[str, Any] | None = None,
             assignments: Sequence[str] = ()) -> Simulation:
    """Simulate a scenario: truth and measurements from ``numpy.random.default_rng(SeedSequence(seed))``, and on a
    sensor network the channels' and uplinks' attacks from ``SeedSequence(seed).spawn(2)[1]`` (the stream of
    ``design``'s channel attacks).

    Parameters
    ----------
    scenario : str, path, Scenario or designer.Model
    steps : int, optional
        Horizon (default: the scenario's).
    seed : int
        The run's seed; the same seed gives the same file bit for bit.
    run : int, optional
        Simulate run ``run`` of a study with seed ``seed`` instead: truth, measurements and attacks as
        ``study comparison --seed SEED`` draws that run (:func:`studies.comparison.realise`, from
        ``SeedSequence(seed, spawn_key=(run,)).spawn(3)``), so that ``filter`` on the file gives that run's numbers
        (its network's scenarios only).
    out : path, optional
        Write the ``.npz`` file there, or with a ``.csv`` suffix the log's CSV form (see :meth:`Simulation.save`).
    overrides, assignments
        Named scenario parameters (a mapping, or ``NAME=VALUE`` strings as ``--set``).

    Returns
    -------
    Simulation
    """
    seed = check_int("seed", seed, 0)
    if steps is not None:
        steps = check_int("steps", steps, 1)
    if run is not None:
        run = check_int("run", run, 0)
    _check_arguments(out=out, network=network, attacks=attacks, inputs=inputs, overrides=overrides,
                     assignments=assignments)
    if out is not None:
        check_output_file("out", out, _log_suffix(out))
        _apart(out, scenario, kind="file")
    sc = _scenario(scenario, network, attacks, None, None, x0, inputs, overrides, assignments)
    if run is not None and sc.network is None:
        raise InputError(f"run applies to a scenario with a sensor network (the comparison's runs); {sc.name!r} "
                         "has none")
    K = sc.steps if steps is None else steps
    memory.check(memory.simulate_need(sc, K))
    from filters.attacks import channel_draws

    from .recorded import realised_attacks
    from .runner import run_seed

    if run is None:
        traj = sc.simulate(np.random.default_rng(np.random.SeedSequence(seed)), steps)
        channels = np.random.SeedSequence(seed).spawn(2)[1]
    else:  # the comparison's run: studies.comparison.realise
        truth, channels, _ = run_seed(seed, run).spawn(3)
        traj = sc.simulate(np.random.default_rng(truth), K)
    if not (np.all(np.isfinite(traj.x)) and np.all(np.isfinite(traj.z))):
        raise InputError("the simulated states or measurements are not finite; check X0, the prior and the model "
                         "(parameter x0 or the model's f and h)")
    pattern = received = None
    if sc.network is not None:
        u, s = channel_draws(K, sc.network.n_nodes, np.random.default_rng(channels))
        pattern, received = realised_attacks(sc, u, s, traj.x, traj.z)
    sim = Simulation(sc, seed, traj.x, traj.z, traj.per_sensor(sc.model), traj.inputs, traj.modes, pattern,
                     received, run)
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
           bank: int | None = None, table_kind: str | None = None, carry: str | None = None,
           budget: int | str | None = None,
           budget_bytes: int | None = None,
           validate: int | None = None, auto_seconds: float | None = None,
           options: DesignOptions | None = None, network: SensorNetwork | None = None, attacks: AttackSpec | None = None,
           design_defaults: DesignOptions | None = None, x0=None, inputs: Callable | None = None,
           overrides: Mapping[str, Any] | None = None, assignments: Sequence[str] = (),
           out: str | Path | None = None):
    """Design the consensus filter of a scenario along a seeded simulated run.

    Parameters
    ----------
    scenario : str, path, Scenario or designer.Model
        What to design for; it needs a sensor network (a model file's ``NETWORK``).
    mode : str, ``'auto'`` or the name of a gain rule (:mod:`rules`)
        ``'auto'`` (the default, unless the model's ``DESIGN`` names a rule): every deployable rule's candidate
        designs, and the pick (:mod:`studies.auto`): the certified one inside the budget with the smallest predicted
        error.  A rule's name designs that rule: e.g. ``relay`` and ``flood`` (every measurement relayed over L hops,
        computed online at each node), ``scheduled`` (gains designed offline for the attack statistics), ``paper``
        and ``tuned`` (the consensus paper's fixed choices and the convex tuning of its conditions), ``mse`` (an
        oracle needing the network's joint state: a reference, not a design to deploy).
    budget, budget_bytes, auto_seconds
        Mode ``auto``: the most messages per step over the network (a whole number, or ``'kcf'``: no more than KCF
        sends), the most bytes per step, and the seconds the candidates may take (default
        :data:`studies.auto.AUTO_SECONDS`).
    validate : int, optional
        Fresh Monte Carlo runs of the design (mode ``auto``: of its pick) beside KCF, HCMCI, the local and the
        centralized EKF, ``.validation`` and ``validation.json`` (default: :data:`studies.auto.VALIDATE_RUNS` in mode
        ``auto``, fewer on a large network (:func:`studies.auto.default_validation`) and as many as fit in memory
        when fewer do, as its message says; 0 with a rule).  Runs given that do
        not fit are refused before any candidate is designed.
    steps, seed : int
        Horizon of the run (default: the scenario's) and its seed (truth and measurements
        from ``SeedSequence(seed).spawn(2)[0]``, channel attacks from ``[1]``).
    epsilon, sigma, beta, tau, u_scale, v_scale, linearization, radius, gate, exchange, robustness, rounds, bank,
    table_kind, carry
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
    Design or studies.auto.AutoDesign
        Mode ``auto``: an :class:`studies.auto.AutoDesign` (``.candidates``, ``.pick`` (a Design or None),
        ``.outcome``, ``.message``, ``.certified``, ``.validation``, ``.save(directory)``).  Otherwise a Design:
        ``.gain_rule`` (:class:`designer.rule.GainRule`: its ``runtime``, what a node ``needs``
        to apply it, ``deployable``), ``.feasible``, ``.violations``, ``.reason()``, ``.certified``, ``.bounded``,
        ``.growing``, ``.verdict`` (``certified``, ``vacuous``, ``infeasible`` or ``not computed``:
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
    _apart(out, scenario)
    opts = _options(options, dict(mode=mode, epsilon=epsilon, sigma=sigma, beta=beta, tau=tau, dos=dos, fdi=fdi,
                                  delta=delta, amplitude=amplitude, u_scale=u_scale, v_scale=v_scale,
                                  linearization=linearization, radius=radius, gate=gate, exchange=exchange,
                                  robustness=robustness, rounds=rounds, bank=bank, table_kind=table_kind,
                                  carry=carry))
    sc = _scenario(scenario, network, attacks, design_defaults, steps, x0, inputs, overrides, assignments)
    from .auto import AUTO

    auto = (opts.mode or (sc.design.mode if sc.design is not None else None) or AUTO) == AUTO
    if not auto:
        given = [k for k, v in (("budget", budget), ("budget_bytes", budget_bytes),
                                ("auto_seconds", auto_seconds)) if v is not None]
        if given:
            raise InputError(f"{', '.join(given)} {'is an option' if len(given) == 1 else 'are options'} of mode "
                             f"'auto' (the automatic design), not of mode {opts.mode or sc.design.mode!r}")
        memory.check(memory.design_need(sc, opts, sc.steps if steps is None else steps))
        validate = 0 if validate is None else check_int("validate", validate, 0)
    else:
        from .auto import check_auto

        check_auto(sc, budget, budget_bytes, validate, auto_seconds)
    with writing(out):  # the one-writer lock, taken before any computation
        if auto:
            from .auto import run_auto

            res = run_auto(sc, replace(opts, mode=None), steps=steps, seed=seed, budget=budget,
                           budget_bytes=budget_bytes, validate=validate, seconds=auto_seconds)
        else:
            res = run_design(sc, opts, steps=steps, seed=seed)
            if validate:
                from .auto import validation

                res = replace(res, validation=validation(res, validate, seed))
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
                table_kind: str | None = None,
                carry: str | None = None, options: DesignOptions | None = None, budget=None,
                budget_bytes: int | None = None,
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
    mode : str, ``'auto'`` or the name of a gain rule (:mod:`rules`)
        ``'auto'`` (the default, unless the model's ``DESIGN`` names a rule): at every grid point, the best
        candidate of every deployable rule the map maps (:func:`studies.feasibility_map.auto_rows`: certified,
        bounded and below the local EKFs, the smallest stationary bound, ties to the fewest bytes), each row naming
        its pick (``rule``); a rule's name maps that rule.
    budget, budget_bytes
        Mode ``auto``: the most messages per step over the network (a whole number, or ``'kcf'``) and bytes per step;
        the candidates outside are listed, not mapped.
    epsilon, sigma, beta, tau, dos, fdi, delta, amplitude, u_scale, v_scale, linearization, radius, exchange,
    robustness, rounds, bank, table_kind, carry, options
        The same design options as :func:`design`, with the same defaults: on a model with ``REGIONS`` the relay
        and flood nodes carry their regions and are judged on them, as their designs are (``carry='whole'``: the
        whole state), and the automatic map ranks every candidate on the regions, whatever its nodes carry, as
        ``design`` does.
    workers, dask, dask_security, backend
        Where the chunks of grid points run (the map does not depend on it; default: a worker process per usable
        core, :func:`studies.runner.every_core`); ``dask_security``: a
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
    from .runner import Backend, every_core, make_backend

    _check_arguments(out=out, network=network, attacks=attacks, design_defaults=design_defaults, inputs=inputs,
                     overrides=overrides, assignments=assignments, force=force, quiet=quiet,
                     dask_security=dask_security)
    _apart(out, scenario, dask_security=dask_security)
    check_type("backend", backend, Backend, "a studies.runner.Backend", optional=True)
    if gate:
        raise InputError("gate does not apply to feasibility: the maps iterate the bound at an operating point, "
                         "with no packets to test (use it with design or study)")
    opts = _options(options, dict(mode=mode, epsilon=epsilon, sigma=sigma, beta=beta, tau=tau, dos=dos, fdi=fdi,
                                  delta=delta, amplitude=amplitude, u_scale=u_scale, v_scale=v_scale,
                                  linearization=linearization, radius=radius, exchange=exchange,
                                  robustness=robustness, rounds=rounds, bank=bank,
                                  table_kind=table_kind, carry=carry))
    if backend is None:  # none given: a worker process per usable core (a point's candidates cost seconds each)
        given = workers is not None or dask is not None or dask_security is not None
        backend = make_backend(workers, dask, dask_security) if given else every_core()
    elif workers is not None or dask is not None or dask_security is not None:
        raise InputError("give either backend or workers/dask, not both")
    sc = _scenario(scenario, network, attacks, design_defaults, None, x0, inputs, overrides, assignments)
    with writing(out):  # the one-writer lock, taken before any computation
        fmap = run_feasibility(sc, grid, opts, backend=backend, store=out, force=force, quiet=quiet, budget=budget,
                               budget_bytes=budget_bytes)
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
        A study of :data:`studies.study_registry.STUDIES` (``comparison``, ``consensus-robot``,
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

    check_type("name", name, str, "the name of a study (studies.study_registry.STUDIES)")
    _check_arguments(out=out, network=network, attacks=attacks, design_defaults=design_defaults, inputs=inputs,
                     overrides=overrides, assignments=assignments, force=force, quiet=quiet,
                     dask_security=dask_security, channel=channel)
    _apart(out, scenario, dask_security=dask_security, schedule=study_options.get("schedule"))
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
    it) and replaces the report's files as a whole (:func:`designer.fileio.replaced_outputs`), a figure the
    report drew before and no longer draws included (:func:`studies.reports.report_figures`).
    """
    from .reports import check_directory, report_figures, write_report

    d = check_directory(directory)
    with writing(d, name="directory", replaces=()), replaced_outputs(d, keep_others=True,
                                                                     retire=report_figures(d)) as stage:
        write_report(d, into=stage)
    return d / "report.html", d / "report.md"


@dataclass(frozen=True, eq=False)
class FilterRun:
    """A filter of the comparison run on a recorded log (what ``cfdesign filter`` computes).

    ``name``: the filter's name in the comparison; ``runtime``: what it needs at run time (``local``,
    ``scheduled``, ``global`` (an oracle), ``centralized``); ``x_hat`` (K + 1, nodes, n_x): every node's estimate
    (one node, the fusion centre, for a centralized filter), ``x_hat[0]`` the prior mean; ``cov`` (K + 1, nodes,
    n_x, n_x): the bound ``Phi`` the filter certifies (``cov_kind == 'bound'``) or the covariance it believes
    (``'covariance'``), trusted where ``valid``, None for a filter that computes none; ``violations``: the design
    conditions broken (node, step, condition) and ``'diverged'``; ``verdict``: a designed filter's verdict of its
    bound on this log (``certified``, ``vacuous``, ``infeasible``, ``not computed``; None for the others);
    ``messages`` (K,): transmissions per step; ``truth`` (K + 1, n_x) when the log holds it; ``design``: the gain
    rule and options of the design it ran with; ``carried`` (nodes, m): when the nodes carry their regions
    (``--carry region``), each node's carried states (``cov`` in their coordinates, ``x_hat`` NaN elsewhere), and
    the RMSE is then over each node's region; ``regions``: each node's region (those its nodes carry, else the
    model's ``REGIONS``; None without), on which :meth:`rmse_region` scores every filter, as the studies do.
    """

    scenario: Scenario
    name: str
    runtime: str
    x_hat: np.ndarray
    cov: np.ndarray | None
    cov_kind: str
    valid: np.ndarray
    violations: list
    verdict: str | None
    messages: np.ndarray
    truth: np.ndarray | None
    log: str
    design: dict | None
    carried: np.ndarray | None = None
    regions: tuple | None = None  # each node's region (the states it answers for), where the model declares them

    @property
    def diverged(self) -> dict | None:
        """Its ``'diverged'`` violation (``node``, ``step``, ``reason``) or None."""
        return next((v for v in self.violations if v["condition"] == "diverged"), None)

    def errors(self) -> np.ndarray | None:
        """(K + 1, nodes, n_x) the truth minus each node's estimate (None: the log holds no truth)."""
        return None if self.truth is None else self.truth[:, None] - self.x_hat

    def rmse(self) -> float | None:
        """RMSE of the position (or of the whole state for a model without declared position components) over
        steps 1..K and the nodes, as the comparison scores a run (None without truth)."""
        e = self.errors()
        if e is None:
            return None
        if self.carried is not None:  # a node estimates its carried states only: scored on its region
            return float(np.sqrt(region_error2(e[1:], self.regions).mean()))
        m = self.scenario.model
        idx = list(m.position_index) or list(range(m.n_x))
        return float(np.sqrt((e[1:][..., idx] ** 2).sum(-1).mean()))

    def rmse_region(self) -> float | None:
        """RMSE of each node's error on its region (:func:`designer.regions.region_error2`) over steps 1..K and the
        nodes, as the studies' ``rmse_region`` scores every filter of a model with ``REGIONS`` (a centralized
        filter's one estimate on every node's region); None without truth or regions."""
        e = self.errors()
        if e is None or self.regions is None:
            return None
        return float(np.sqrt(region_error2(e[1:], self.regions).mean()))

    def per_node(self) -> dict[str, np.ndarray] | None:
        """Each node's errors against the log's truth (None without truth): ``rmse`` (nodes,) of the position (or
        the state) over steps 1..K, as :meth:`rmse` over one node; ``energy`` (nodes,) the mean over the steps
        where its covariance is valid of ``‖e‖² / tr P`` (the whole state; a mean-square bound that holds gives
        at most about 1 on average over runs; a believed covariance, its calibration)."""
        e = self.errors()
        if e is None:
            return None
        m = self.scenario.model
        idx = list(m.position_index) or list(range(m.n_x))
        if self.carried is not None:  # on each node's region; the energy on its carried states, as its bound
            rmse = np.sqrt(region_error2(e[1:], self.regions).mean(axis=0))
            e = Carried(self.carried, m.n_x).vector(e)
        else:
            rmse = np.sqrt((e[1:][..., idx] ** 2).sum(-1).mean(axis=0))
        trace = np.nan if self.cov is None else np.trace(self.cov[1:], axis1=-2, axis2=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.where(self.valid[1:], (e[1:] ** 2).sum(-1) / trace, np.nan)
            energy = np.nanmean(ratio, axis=0) if np.any(np.isfinite(ratio)) else np.full(ratio.shape[1], np.nan)
        return {"rmse": rmse, "energy": energy}

    def save(self, directory) -> Path:
        """Write ``estimates.npz`` (``x_hat``, ``Phi`` or ``P``, ``valid``, ``messages``, ``x`` when known),
        ``estimates.csv`` (step, node, the estimate's components) and ``report.md`` into ``directory``."""
        from .outputs import filter_report

        _apart(directory, self.scenario, data=None if self.log.startswith("<") else self.log,
               schedule=(self.design or {}).get("schedule"))
        with replaced_outputs(directory) as stage:
            filter_report(self, stage)
        return Path(directory)


@one_blas_thread()
def filter(scenario, data, *, filter: str | None = None, schedule: str | Path | None = None,
           seed: int | None = None, run: int | None = None, particles: int | None = None,
           iterations: int | None = None, out: str | Path | None = None, network: SensorNetwork | None = None,
           attacks: AttackSpec | None = None,
           design_defaults: DesignOptions | None = None, x0=None, inputs: Callable | None = None,
           overrides: Mapping[str, Any] | None = None, assignments: Sequence[str] = ()) -> FilterRun:
    """Run a filter of ``study comparison`` on the recorded log ``data`` (:mod:`studies.recorded`).

    Parameters
    ----------
    scenario : str, path, Scenario or designer.Model
        The model the log was recorded on (it needs a sensor network).
    data : path
        The log: an ``.npz`` as ``simulate`` writes it (``z``, ``inputs``, the channels' ``channel_dos``,
        ``channel_fdi``, ``channel_xi``, the uplinks' ``uplink``, optionally the truth ``x``).
    filter : str, optional
        A filter of :data:`studies.comparison.FILTER_REGISTRY`: its name or short name (``kcf``, ``hcmci``,
        ``scheduled``, ``tuned``, ... :func:`studies.recorded.filter_keys`).  Default: the designed filter of
        ``schedule``'s gain rule.
    schedule : path, optional
        A design directory written by ``design``: a designed filter runs with its gain rule and options
        (otherwise with the scenario's design defaults, as in the comparison).
    seed, run : int, optional
        The particle filters' study seed and run (default: the log's ``seed`` and ``run``, else 0): they draw from
        :func:`studies.recorded.particle_seed`, as in that run of ``study comparison``.
    particles, iterations
        The particle filters' particles (default 500) and HCMCI's consensus rounds per step (default 1); given
        for another filter, each is refused (as ``seed`` and ``run``).
    out : path, optional
        Write ``estimates.npz``, ``estimates.csv`` and ``report.md`` there.

    Returns
    -------
    FilterRun
    """
    from filters.result import HARD_CONDITIONS

    from .comparison import FILTER_REGISTRY, STUDY
    from .consensus_design import bound_verdicts, check_first_step, consensus_design
    from .design_options import as_mode
    from .recorded import design_options_of, find_filter, read_log, recorded_design, run_filter

    check_path("data", data)
    check_type("filter", filter, str, "a filter's name (e.g. kcf, scheduled)", optional=True)
    check_path("schedule", schedule, optional=True)
    if filter is not None or schedule is not None:  # options the chosen filter does not use are refused
        _applies(filter, "schedule", particles=particles, seed=seed, run=run, iterations=iterations)
    if seed is not None:
        seed = check_int("seed", seed, 0)
    if run is not None:
        run = check_int("run", run, 0)
    particles = check_int("particles", STUDY.particles if particles is None else particles, 2)
    iterations = check_int("iterations", 1 if iterations is None else iterations, 1)
    _check_arguments(out=out, network=network, attacks=attacks, design_defaults=design_defaults, inputs=inputs,
                     overrides=overrides, assignments=assignments)
    _apart(out, scenario, data=data, schedule=schedule)
    if filter is None and schedule is None:
        raise InputError("give the filter to run (filter, e.g. kcf or scheduled) or a design directory (schedule)")
    sc = _scenario(scenario, network, attacks, design_defaults, None, x0, inputs, overrides, assignments)
    if sc.network is None:
        raise InputError(f"scenario {sc.name!r} has no sensor network: the filters of the comparison need one (a "
                         "model file defines NETWORK)")
    options, design_meta = DesignOptions(), None
    if schedule is not None:
        mode, options, meta = design_options_of(schedule, sc)
        entry = find_filter(FILTER_REGISTRY, mode if filter is None else filter)
        if not entry.designed or entry.mode != mode:
            raise InputError(f"filter {entry.name!r} does not run the design of schedule {str(schedule)!r} (gain "
                             f"rule {mode!r}): give filter {mode!r} or leave it out")
        design_meta = {"schedule": str(schedule), "gain_rule": mode, "options": options.as_dict(),
                       "certified": meta.get("certified"), "verdict": meta.get("verdict")}
    else:
        entry = find_filter(FILTER_REGISTRY, filter)
    designed = None if entry.mode is None else as_mode(options, entry.mode)
    log = read_log(data, sc, lambda size: memory.filter_need(
        sc, size, options=designed, centralized=entry.runtime == "centralized",
        particles=particles if entry.particles else None))  # checked before the log's arrays are made
    seed = (log.seed or 0) if seed is None else seed
    run = (log.run or 0) if run is None else run
    design = None
    if entry.mode is not None:  # a design directory's own tables where it has them (not designed again)
        design = (consensus_design(sc, designed, steps=log.steps) if schedule is None else
                  recorded_design(schedule, sc, designed, steps=log.steps))
        why = check_first_step(sc, design, entry.name) if entry.start_check else None
        if why is not None:  # as the comparison reports it: not run
            raise InputError(f"filter {entry.name!r} cannot start on {sc.name!r}: {why}")
        design_meta = design_meta or {"gain_rule": entry.mode, "options": as_mode(options, entry.mode).as_dict()}
    with writing(out):
        res = run_filter(sc, log, entry, design=design, seed=seed, run=run, particles=particles,
                         iterations=iterations)
        verdict = None
        if entry.designed:
            ok = not any(v["condition"] in HARD_CONDITIONS for v in res.violations[0])
            verdict = bound_verdicts(sc, res.cov, res.valid, [ok], design, res.carried)[0].verdict
        done = FilterRun(sc, entry.name, res.runtime, res.x[0], None if res.cov is None else res.cov[0],
                         res.cov_kind, res.valid[0], res.violations[0], verdict, res.messages[0], log.x, log.source,
                         design_meta, res.carried, design.carried_regions if res.carried is not None else sc.regions)
        if out is not None:
            done.save(out)
    return done


@one_blas_thread()
def node_filter(scenario, *, schedule: str | Path | None = None, mode: str | None = None, filter: str | None = None,
                node: int | None = None, iterations: int | None = None, network: SensorNetwork | None = None,
                attacks: AttackSpec | None = None, design_defaults: DesignOptions | None = None, x0=None,
                inputs: Callable | None = None, overrides: Mapping[str, Any] | None = None,
                assignments: Sequence[str] = ()):
    """The filter a sensor node runs for a design (:mod:`filters.node`), to drive one step at a time.

    Parameters
    ----------
    scenario : str, path, Scenario or designer.Model
        The model (with its sensor network).
    schedule : path, optional
        A design directory written by ``design``: its gain rule with its options.
    mode : str, optional
        A gain rule instead (with the scenario's design defaults), e.g. ``paper``, ``scheduled``, ``relay``.
    filter : str, optional
        Or a filter of the comparison by its name or short name (:func:`studies.recorded.filter_keys`): ``kcf``
        (:class:`filters.distributed.KCFNode`), ``hcmci`` (:class:`filters.distributed.HCMCINode`, ``iterations``
        consensus rounds a step), the local EKFs (``local``: every node alone, an EKF on its own sensor,
        :class:`filters.distributed.LocalEKFNode`), or a designed consensus filter (as ``mode``).
    node : int, optional
        The node (0..N-1): its node filter (``step(z, received, u)`` for relay and flood; ``predict``, then
        ``update`` for paper, tuned and KCF; ``predict``, ``update``, then ``round`` per further exchange round for
        scheduled; ``predict``, then ``round`` per consensus round for HCMCI; ``step(z, u)`` for the local EKF).  Default: every node's, as a network
        to drive over a run (``run(z, attacks, inputs)`` or ``step(z, dos, fdi, xi, u)``; ``deliver`` says what
        reaches each node).
    """
    import rules
    from filters.node import node_filter as make_node, node_network

    from .comparison import FILTER_REGISTRY
    from .consensus_design import consensus_design
    from .recorded import design_options_of, find_filter, recorded_design

    check_path("schedule", schedule, optional=True)
    check_type("mode", mode, str, "a gain rule's name (e.g. relay, flood)", optional=True)
    _check_arguments(network=network, attacks=attacks, design_defaults=design_defaults, inputs=inputs,
                     overrides=overrides, assignments=assignments)
    check_type("filter", filter, str, "a filter's name (e.g. kcf, local)", optional=True)
    if sum(v is not None for v in (schedule, mode, filter)) != 1:
        raise InputError("give a design directory (schedule), a gain rule (mode) or a filter's name (filter), one of "
                         "them")
    _applies(filter, "schedule or mode", iterations=iterations)  # HCMCI's only
    sc = _scenario(scenario, network, attacks, design_defaults, None, x0, inputs, overrides, assignments)
    if sc.network is None:
        raise InputError(f"scenario {sc.name!r} has no sensor network: a node filter needs one (a model file "
                         "defines NETWORK)")
    if node is not None:
        node = check_int("node", node, 0, sc.network.n_nodes - 1)
    if filter is not None:
        entry = find_filter(FILTER_REGISTRY, filter)
        if entry.node_filters is None:
            having = [e.name for e in FILTER_REGISTRY if e.node_filters is not None
                      and not (e.designed and not rules.get(e.mode).has_node_filter)]
            raise InputError(f"filter {entry.name!r} has no node filter (filters with one: {', '.join(having)})")
        memory.check(memory.node_filter_need(sc, None if entry.mode is None else DesignOptions(mode=entry.mode)))
        design = None if entry.mode is None else entry.design_for(consensus_design(sc, DesignOptions(mode=entry.mode)),
                                                                  sc.model)
        rounds = check_int("iterations", 1 if iterations is None else iterations, 1)
        net = entry.node_filters(sc.model, sc.network, design, rounds)
        return net if node is None else net.nodes[node]
    if schedule is not None:
        _, options, _ = design_options_of(schedule, sc)
    else:
        options = DesignOptions(mode=mode)
    memory.check(memory.node_filter_need(sc, options))
    design = consensus_design(sc, options) if schedule is None else recorded_design(schedule, sc, options)
    if node is None:
        return node_network(sc.model, sc.network, design)
    return make_node(sc.model, sc.network, design, node)


def _recorded_source(design_dir, meta: dict) -> str:
    """The model a design directory records (its ``schedule.json`` ``meta``, read by
    :func:`studies.recorded.read_design_record`), to be built without the user naming it: a built-in scenario's
    name (:data:`studies.scenarios.SCENARIOS`), or a model file when the design directory was written by
    ``cfdesign design`` on this account (its ``source_seal`` verifies under this account's key:
    :func:`studies.provenance.sealed`) and the file's bytes and its local imports' bytes
    (:func:`designer.digest.source_files_digest`, read, never imported) are still the ``source_digest`` recorded
    at design time.  Anything else is refused before anything is imported: the user gives the model (``scenario``)
    after checking it."""
    from designer.digest import source_files_digest

    from .provenance import KeyUnavailable, sealed

    where = meta.get("source") or meta.get("scenario")
    if where in SCENARIOS:
        return where
    given = "give the model with --scenario MODEL.py (scenario=) after checking it is the design's"
    if not (where or "").endswith(".py") or not Path(where).is_absolute():  # design records a file's full path
        raise InputError(f"design_dir {str(design_dir)!r} does not record a built-in scenario or a model file's "
                         f"full path: {given}")
    shown = repr(where) if len(where) <= 200 else repr(where[:200]) + " ..."
    recorded = meta.get("source_digest")
    if recorded is None:
        raise InputError(f"design_dir {str(design_dir)!r} names the model file {shown} but records no digest of "
                         f"its content (source_digest), so it cannot be checked before it is imported: {given}")
    unsealed = (f"design_dir {str(design_dir)!r} names the model file {shown} but was not written by cfdesign "
                "design on this account")
    try:
        if not sealed(meta, meta.get("source_seal")):
            why = ("its seal does not verify with this account's key: sealed on another account, or its record "
                   "edited since" if meta.get("source_seal") is not None else
                   "it has no seal: written elsewhere or by an older cfdesign")
            raise InputError(f"{unsealed} ({why}): {given}")
    except KeyUnavailable as exc:
        raise InputError(f"{unsealed} as far as can be checked: {exc}; {given}") from None
    try:
        found = source_files_digest(where) if Path(where).is_file() else None
    except (OSError, ValueError):
        found = None
    if found is None:
        raise InputError(f"design_dir {str(design_dir)!r} names the model file {shown}, which cannot be read: "
                         f"{given}")
    if found != recorded:
        raise InputError(f"design_dir {str(design_dir)!r} names the model file {shown}, whose content is not the "
                         f"design's (it changed since: its digest differs from source_digest): {given}")
    return where


@one_blas_thread()
def export(design_dir, *, target: str = "c", out, nodes: Sequence[int] | None = None, data=None,
           scenario=None, overrides: Mapping[str, Any] | None = None, assignments: Sequence[str] = (),
           prefix: str = "cfd") -> list[Path]:
    """Export a design's node filter as C99 sources (``cfdesign export``; :mod:`designer.export_c`, the rule's
    export: :meth:`designer.rule.GainRule.c_export`).

    Parameters
    ----------
    design_dir : path
        A directory written by ``design`` for a gain rule whose node filter is exported: ``paper`` (with
        ``linearization='fixed'``, the two-phase consensus node of :class:`filters.consensus_node.ConsensusNode`),
        ``relay``, ``flood`` (:class:`rules.relay.filter.RelayNode`) or ``scheduled``
        (:class:`rules.scheduled.filter.ScheduledNode`, its tables exported with it).
    target : {'c'}
    out : path
        The directory of the sources, ``Makefile``, test driver and ``replay.txt``.
    nodes : sequence of int, optional
        The nodes to export (default: every node).
    data : path, optional
        A log (:mod:`studies.recorded`) to replay in ``make test``; default: the design's simulated run
        (``simulate`` with the design's seed).
    scenario, overrides, assignments
        The model.  Default: the design directory's own (its ``source``), built with the design's parameters, when
        it is a built-in's name, or a model file when the directory was written by ``design`` on this account (its
        ``source_seal``: :mod:`studies.provenance`) and the file's bytes still have the design's ``source_digest``
        (both checked before the file is imported: a design directory from elsewhere may name any file and its
        digest); otherwise the model must be given, and its content must be the design's (``model_digest``).
    prefix : str
        The sources' names (:func:`designer.export_c.prefixed`): functions, types and files ``prefix_...``, macros
        ``PREFIX_...`` (default ``cfd``), so that the exports of two designs link into one program.

    The design directory is read as data (:func:`studies.recorded.read_design_record`): no text of it reaches the
    C sources (the verdict is stated as a word of :data:`designer.verdict.VERDICTS`, else ``unknown``).

    Returns the files written.
    """
    import rules
    from designer.export_c import REPLAY_TOLERANCES, check_prefix, drift_tolerances, network_copy, prefixed
    from filters.consensus_batch import EdgeAttacks
    from filters.node import node_network

    from .design_options import effective
    from .recorded import clip_message, design_options_of, read_design_record, read_log, recorded_design
    from .runner import Background

    check_path("design_dir", design_dir)
    if target != "c":
        raise InputError(f"target must be 'c' (C99 sources), got {target!r}")
    check_path("out", out)
    check_path("data", data, optional=True)
    check_prefix(prefix)
    _check_arguments(out=out, overrides=overrides, assignments=assignments)
    _apart(out, scenario, design_dir=design_dir, data=data)
    record = read_design_record(design_dir, "design_dir")  # data only: nothing it names is imported here
    meta = record[1]
    if scenario is None:
        where = _recorded_source(design_dir, meta)
        _apart(out, where)  # the design's own model file, once it is known to be the design's
        try:
            sc = _scenario(where, None, None, None, None, None, None,
                           {**(meta.get("params") or {}), **(overrides or {})}, assignments)  # as designed
        except InputError as exc:  # its recorded parameters quoted, at most a few hundred characters of them
            raise InputError(clip_message(str(exc))) from None
    else:
        sc = _scenario(scenario, None, None, None, None, None, None, overrides, assignments)
    mode, options, _ = design_options_of(design_dir, sc, record)
    rule = rules.get(mode)
    try:
        exporter = rule.c_export()
    except InputError as exc:  # why, and the rules that export
        exported = ", ".join(name for name, other in rules.all_rules().items() if other.exports_c)
        raise InputError(f"{exc} (exported: {exported})") from None
    N = sc.network.n_nodes
    chosen = list(range(N)) if nodes is None else [check_int("nodes", i, 0, N - 1) for i in nodes]
    if not chosen or len(set(chosen)) != len(chosen):
        raise InputError(f"nodes must be distinct nodes of 0..{N - 1}, got {nodes!r}")
    # the memory, before the design is read (with a log: before its arrays are made), with what the rule's nodes record
    used = effective(sc, options)[1]
    record, numbers = exporter.replay_numbers(sc.model, sc.network, used,
                                              sc.regions if used.carry == "region" else None, chosen)
    need = functools.partial(memory.export_need, sc, options, sc.steps, record=record, data=numbers,
                             nodes=len(chosen))
    if data is None:
        memory.check(need())
    else:
        log = read_log(data, sc, need)
        if np.any(np.isnan(log.z)):
            raise InputError(f"data {str(data)!r} has missing measurements: the node filter needs each node's own")
    design = recorded_design(design_dir, sc, options)  # its recorded tables, not designed again
    exporter.check(design)
    if data is None:
        sim = simulate(sc, seed=meta.get("seed") or 0)
        z, attacks, u = sim.z, sim.attacks, sim.inputs
    else:
        z, attacks, u = log.z, log.attacks, (np.zeros((log.steps, 0)) if log.inputs is None else log.inputs)
    net = node_network(sc.model, sc.network, design)
    att = None if attacks is None else EdgeAttacks.from_patterns(sc.network, [attacks])
    # the network run's tolerances (copies run beside the network from the start, perturbed at every step: a double's,
    # a float's), in a process of their own beside this one's per-step twins: the same numbers (tested); their
    # network stops where this one does, and this one's replay may end sooner (an ill-conditioned step)
    with Background(drift_tolerances, network_copy(net), exporter, z, att, u, chosen) as drift:
        steps, tolerances = _replay(exporter, net, z, att, u, sc.model, chosen, mode)
        tolerances = np.concatenate([tolerances, drift.result()[:len(steps)]], axis=-1)
    verdict = meta.get("verdict")  # the writers state it as a word of designer.verdict's vocabulary only
    tolerances = np.reshape(tolerances, (len(steps), len(chosen), REPLAY_TOLERANCES))
    with replaced_outputs(out) as stage:
        written = prefixed(exporter.write(sc.model, sc.network, design, net, steps, stage, nodes=chosen,
                                          tolerances=tolerances, verdict=verdict), prefix)
    return [Path(out) / p.name for p in written]


def _replay(exporter, net, z, att, u, model, chosen, mode):
    """The export's replay of the run (:func:`export`): the node network ``net`` stepped over it, each step's replay
    record and each exported node's per-step tolerances, a double node's and a float node's (steps, nodes, 2), from
    twins of the network perturbed before the step (:func:`designer.export_c.replay_tolerances`); it ends before a
    step where the filter diverged (a warning says which).  A node step too ill-conditioned to check (its tolerance
    beyond :data:`designer.export_c.REPLAY_TOLERANCE_CAP`) has the tolerance ``inf``: ``make test`` keeps it as
    information and checks the steps after it, each from Python's state (a warning says how many and the first)."""
    from designer.export_c import (FLOAT_EPSILON, FLOAT_SEED, REPLAY_TOLERANCE_CAP, SENSITIVITY_SAFETY,
                                   SENSITIVITY_SEED, SENSITIVITY_TRIALS, perturbed_twin, replay_tolerances)
    from designer.progress import progress

    rng = np.random.default_rng(SENSITIVITY_SEED)  # the perturbed twins measuring each step's own sensitivity,
    rng_float = np.random.default_rng(FLOAT_SEED)  # at a double's rounding and at a float node's
    to_float = FLOAT_EPSILON / np.finfo(float).eps
    steps, tolerances = [], []
    first_ill, ill_count = None, 0  # (step, node, its sensitivity) of the first node step too ill-conditioned to check
    for k in progress(range(z.shape[0]), z.shape[0], False, "export: replaying the run"):
        e = (None, None, None) if att is None else (att.dos[0, k], att.fdi[0, k], att.xi[0, k])
        twins = [perturbed_twin(net, rng) for _ in range(SENSITIVITY_TRIALS)]
        floats = [exporter.float_twin(net, rng_float) for _ in range(SENSITIVITY_TRIALS)]
        net.step(z[k], *e, u=u[k])
        if getattr(net, "stopped", False):
            warnings.warn(f"the {mode} filter diverged at step {k + 1} of the replayed run: replay.txt holds the {k} "
                          "steps before", RuntimeWarning, stacklevel=2)
            break
        step = exporter.replay_step(net, k, u[k], [z[k, model.sensor_rows(i)] for i in chosen], chosen)
        with warnings.catch_warnings(), np.errstate(all="ignore"):  # a twin may break down where the run does not
            warnings.simplefilter("ignore")
            for twin in twins + floats:
                twin.step(z[k], *e, u=u[k])
        tol = replay_tolerances(net, twins, chosen)
        ill = ~(tol <= REPLAY_TOLERANCE_CAP)  # beyond, C and Python may differ by rounding alone: information
        if ill.any() and first_ill is None:
            j = int(np.argmax(ill))  # the first in the replay's row order, as make test names it
            first_ill = (k + 1, chosen[j], float(tol[j]) / SENSITIVITY_SAFETY)
        ill_count += int(ill.sum())
        steps.append(step)
        tol_float = np.maximum(tol * to_float, replay_tolerances(net, floats, chosen))
        tolerances.append(np.where(ill[:, None], np.inf, np.stack([tol, tol_float], -1)))
    if first_ill is not None:
        k1, node, moved = first_ill
        warnings.warn(f"the {mode} filter's replayed run is ill-conditioned at {ill_count} of its "
                      f"{len(steps) * len(chosen)} node steps, the first at step {k1}, node {node} (it moves one-ulp "
                      f"changes of its input by {moved:.3g} of their scale, beyond make test's check at "
                      f"{REPLAY_TOLERANCE_CAP:g}): make test keeps them as information and checks every other step "
                      f"from Python's state", RuntimeWarning, stacklevel=2)
    return steps, np.reshape(tolerances, (len(steps), len(chosen), 2))
