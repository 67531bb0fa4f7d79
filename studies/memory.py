"""How much memory a command needs, estimated before it computes anything.

Every command estimates, from the sizes it was given, the bytes it holds at its peak, and
:func:`check` refuses (:class:`~designer.validation.InputError`, exit 2) one that cannot fit
in the memory available (Linux ``MemAvailable``), naming what it would hold, the sizes and
the parameters to reduce, instead of a ``MemoryError`` (or the machine's swap) after hours of
work.  One estimate per command and study, all here:

==========================  ===========================================================
:func:`simulate_need`        ``simulate``: the run's states and measurements
:func:`design_need`          ``design``: the Hessians of the ``'prior'`` scalings, then the
                             run with every node's bounds and gains and the written schedule
:func:`feasibility_need`     ``feasibility``: every grid point's row, and one chunk of points
                             (with its designs' Hessians) per worker
:func:`study_need`           every study (:data:`STUDY_NEEDS`): the designs' Hessians, one
                             chunk of runs per worker, and every run's stored results
:func:`filter_need`          ``filter``: the log's arrays (:class:`LogSize`, from the sizes an
                             ``.npz`` declares or a CSV's largest step), the design of the
                             filter's gain rule, then its run (the particles of a particle filter)
:func:`node_filter_need`     ``node_filter``: the design, then every node's matrices
==========================  ===========================================================

**What is counted.**  The arrays whose size grows with the parameters, their shapes read off
the code: the filters' per-step results ``(rows, steps, nodes, n_x, n_x)`` and their channel
attacks, the Hessians of the ``'prior'`` scalings ``(points, components, n_x, n_x)`` (and of
``linearization`` ``hessian``/``structured`` at every step), the joint covariance of mode ``mse``,
the particles, the per-run results the runner keeps, times the copies alive at the peak;
and the Python objects of what is written (the schedule's JSON, the rows of ``feasibility.csv``).
A phase that ends before the next begins (the Hessians, then the run) counts once: the need is
the largest phase.  The interpreter and the libraries already imported (a few hundred MB) are
not counted.

**How close.**  The copies and the bytes per written value were measured
(``benchmarks/bench_memory.py`` prints, for commands at sizes that run in seconds, the peak
resident memory above the imports, ``VmHWM``, beside :attr:`Need.nbytes`); the estimates lie
within about a factor of 2 of those peaks, mostly above them (the Hessians of a linear model, for
instance, are allocated but partly never touched).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Callable, Mapping, Sequence

import rules
from designer.validation import InputError

__all__ = ["Part", "Need", "available_memory", "check", "format_bytes", "simulate_need", "design_need",
           "feasibility_need", "study_need", "STUDY_NEEDS", "log_values", "LogSize", "log_need", "filter_need",
           "node_filter_need", "export_need"]

_D = 8  # bytes of a double
# Copies and sizes measured at the peak (benchmarks/bench_memory.py):
_RESULT_COPIES = 1.5  # a filter's per-step results, and the outputs made of them (the schedule, the runs' rows)
_STEP_MATRICES = 40  # (n_x, n_x) matrices per node and run alive within one step of a consensus filter
_FIXED_POINT_MATRICES = 20  # the same per node and grid point in an iteration of the steady-state recursion
_HESSIAN_COPIES = 2.0  # the components' Hessians and their stack (designer.model.Model.f_hessian)
_WHITENED_COPIES = 3.0  # the same, and their whitened products cov^1/2 H cov^1/2 (designer.design.whitened_scaling)
_JSON_VALUE = 60  # bytes per number written to JSON (a float in a list, its text, the report reading it again)
_TEXT = 30  # bytes per number written as C or replay text (its repr and separator, a string object a piece)
_ARRAY_OBJECT = 112  # bytes of a small NumPy array's object beside its data (a replayed step's record)
_POINT_BYTES = 3000  # a feasibility grid point: its dict, its row, the runner's arrays, the CSV and the report
_PARTICLE_DOUBLES = (5, 1, 4)  # doubles per particle and run: per state, per measurement component, fixed
_CENTRALIZED_PF_DOUBLES = (5, 5, 4)  # the same, the comparison's centralized PFs (filter, 16 measurement components)
_LOG_COPIES = 2.0  # a CSV log's arrays as parsed, and their float copies as checked (studies.recorded.check_log)

_STEPS = "fewer steps"
_SHORTER_LOG = "a shorter log (fewer steps)"
_SCALINGS = "the scalings u_scale and v_scale (--u-scale, --v-scale; the default 'prior' ones evaluate every Hessian)"


def available_memory() -> int | None:
    """Bytes of memory available to this process (Linux ``MemAvailable``), or None where unknown."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def format_bytes(n: float) -> str:
    """``n`` bytes in the largest binary unit it reaches, three significant digits or more (``121 GiB``,
    ``1010 GiB``, ``20.3 MiB``)."""
    for unit, size in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10), ("B", 1)):
        if n >= size or unit == "B":
            v = n / size
            return f"{v:.0f} {unit}" if v >= 100 else f"{v:.3g} {unit}"
    raise AssertionError("unreachable")


@dataclass(frozen=True)
class Part:
    """One thing a command holds: what it is, its bytes, the sizes they come from and what would shrink it."""

    what: str
    nbytes: float
    sizes: str = ""
    reduce: str = ""

    def __str__(self) -> str:
        return f"{self.what} ({self.sizes}): {format_bytes(self.nbytes)}" if self.sizes else \
            f"{self.what}: {format_bytes(self.nbytes)}"


@dataclass(frozen=True)
class Need:
    """The memory a command needs: ``phases``, each the parts held at once; the command needs the largest."""

    command: str
    phases: tuple

    @property
    def peak(self) -> tuple[Part, ...]:
        """The parts of the largest phase."""
        return max(self.phases, key=lambda ph: sum(p.nbytes for p in ph), default=())

    @property
    def nbytes(self) -> float:
        return float(sum(p.nbytes for p in self.peak))

    def message(self, available: float) -> str:
        """What the command would hold (its three largest parts) and what to reduce."""
        parts = sorted((p for p in self.peak if p.nbytes > 0), key=lambda p: -p.nbytes)[:3]
        big = [p for p in parts if p.nbytes >= 0.1 * self.nbytes] or parts[:1]
        advice = list(dict.fromkeys(p.reduce for p in big if p.reduce))
        return (f"{self.command} would need about {format_bytes(self.nbytes)} of memory, more than the "
                f"{format_bytes(available)} available: " + "; ".join(map(str, parts))
                + (f"; to fit, use {' or '.join(advice)}" if advice else ""))


def _need(command: str, *phases: Sequence[Part | None]) -> Need:
    return Need(command, tuple(tuple(p for p in ph if p is not None) for ph in phases))


def check(need: Need, available: float | None = None) -> None:
    """Refuse (InputError) a command whose :class:`Need` exceeds the memory available (where it is known)."""
    have = available_memory() if available is None else available
    if have is not None and need.nbytes > have:
        raise InputError(need.message(have))


# ------------------------------------------------------------------ building blocks
def _points(n_x: int) -> int:
    """Points of the ellipsoid the Hessian-derived scalings sample (designer.linearization.ellipsoid_points)."""
    return 2 * n_x + 1 + (2**n_x if n_x <= 6 else 0)


def _components(model) -> int:
    """The largest stack of Hessians evaluated at once: ``f``'s (every mode's) or one sensor's."""
    return max(model.n_x * max(model.n_modes, 1), *model.sensor_dims)


def _uses_prior(options) -> bool:
    """The ``'prior'`` scalings (designer.design.resolve_scaling): U or one V_i not given (None, 'prior')."""
    def prior(v) -> bool:
        if v is None or isinstance(v, str):
            return True
        if isinstance(v, Mapping):
            return "*" not in v or any(prior(x) for x in v.values())
        return isinstance(v, (list, tuple)) and any(isinstance(x, str) for x in v)
    return prior(options.u_scale) or prior(options.v_scale)


def _prior_hessians(model, options) -> Part | None:
    """The Hessians of ``f`` and of each sensor's ``h`` at the prior's ellipsoid points, one function at a time, each
    component's on its structural support (designer.model.Model.hessian_blocks)."""
    if not _uses_prior(options):
        return None
    from designer.design import whitened

    from .design_options import rule_of

    n_x, P = model.n_x, _points(model.n_x)
    if options.mode != "auto" and whitened(rule_of(options), options):  # in the prior's units: dense, n_x² each
        comps = _components(model)
        return Part("the Hessians of the 'prior' scalings U and V_i", _WHITENED_COPIES * P * comps * n_x**2 * _D,
                    f"{P} points x {comps} components x {n_x} x {n_x} states", _SCALINGS)
    entries = [max(model.n_modes, 1) * sum(S.size ** 2 for S in model.hessian_blocks()[0]),
               *(sum(S.size ** 2 for S in model.hessian_blocks(i)[0]) for i in range(model.n_sensors))]
    return Part("the Hessians of the 'prior' scalings U and V_i", _HESSIAN_COPIES * P * max(entries) * _D,
                f"{P} points x {max(entries)} entries of a function's Hessians on their supports", _SCALINGS)


def _step_hessians(model, centres: int, linearization: str | None, reduce: str) -> Part | None:
    """Per step of linearization 'hessian' or 'structured': the Hessians at the points around every estimate."""
    if linearization in (None, "fixed"):
        return None
    n_x, comps, P = model.n_x, _components(model), _points(model.n_x)
    return Part(f"the Hessians of linearization '{linearization}' at a step",
                _HESSIAN_COPIES * centres * P * comps * n_x**2 * _D,
                f"{centres} estimates x {P} points x {comps} components x {n_x} x {n_x} states",
                f"linearization 'fixed' or {reduce}")


def _consensus(model, network, rows: int, steps: int, mode: str | None, linearization: str | None, what: str,
               reduce: str, predictions: bool = True, dense: bool = True, variances: bool = False) -> list[Part]:
    """A consensus filter (or KCF, HCMCI) on ``rows`` runs at once: its per-step results, attacks and one step
    (``predictions``: with the record of every step's predicted covariance and gains, which a comparison does not
    keep: ``filters.consensus_batch.run_consensus_batch``'s ``predictions``; ``variances``: its bounds over the steps
    as their diagonals, as a comparison keeps them, and whole at one step; ``dense``: the attacks given as dense
    N x N patterns besides their channels', where a comparison gives its channels' alone)."""
    n_x, nz = model.n_x, max(model.sensor_dims)
    n = network.n_nodes
    channels = int(network.adjacency.sum())
    per_step = 3 * n_x * n_x + n_x * nz + n_x + 12 if predictions else n_x + 12
    bound = n_x if variances else n_x * n_x  # each node's bound at a step
    per_row = (steps * n * per_step + (steps + 1) * n * (bound + n_x + 3) + variances * n * n_x * n_x) * _D
    parts = [Part(f"{what}: the bounds, gains and estimates of every node and step", _RESULT_COPIES * rows * per_row,
                  f"{rows} runs x {steps} steps x {n} nodes x {n_x} x {n_x} states", reduce),
             Part(f"{what}: the channel attacks",  # a dense pattern: its flags, its signal where falsified
                  rows * steps * (channels * (n_x * _D + 2) + dense * (2 * n * n + channels * n_x * _D)),
                  f"{rows} runs x {steps} steps x " + (f"{n} x {n}" if dense else f"{channels}")
                  + f" channels x {n_x} states", reduce),
             Part(f"{what}: one step", rows * n * n_x * n_x * _D * _STEP_MATRICES,
                  f"{rows} runs x {n} nodes x {n_x} x {n_x} states", "a smaller model"),
             _step_hessians(model, rows * n, linearization, "a smaller model")]
    if mode is not None:  # what its gain rule's filter holds besides
        parts += [Part(f"{what}: {part}", nbytes, sizes, less)
                  for part, nbytes, sizes, less in rules.get(mode).memory_parts(network, n_x, rows, steps)]
    return [p for p in parts if p is not None]


def _particles(model, rows: int, particles: int, what: str, doubles: tuple = _PARTICLE_DOUBLES) -> Part:
    a, b, c = doubles
    return Part(f"{what}: the particles", rows * particles * (a * model.n_x + b * model.n_z + c) * _D,
                f"{rows} runs x {particles} particles x {model.n_x} states", "fewer particles (--particles)")


def _workers(backend, chunks: int) -> int:
    """Chunks computed at once in this machine's memory (forked workers; a Dask cluster's are elsewhere)."""
    if backend is None or getattr(backend, "kind", "batched") != "processes":
        return 1
    return max(1, min(int(backend.workers or 1), chunks))


def _per_worker(parts: Sequence[Part | None], workers: int) -> list[Part]:
    parts = [p for p in parts if p is not None]
    if workers == 1:
        return parts
    return [Part(f"{p.what}, in each of {workers} workers", p.nbytes * workers, p.sizes,
                 f"{p.reduce} or fewer workers (--workers)") for p in parts]


# ------------------------------------------------------------------ the commands
def simulate_need(sc, steps: int) -> Need:
    """``simulate``: the states, stacked and per-sensor measurements, inputs and modes of one run."""
    m = sc.model
    per_step = (m.n_x + m.n_z + m.n_sensors * max(m.sensor_dims) + m.n_u + 1) * _D
    return _need("simulate", [Part("the run's states and measurements", 1.5 * steps * per_step,
                                   f"{steps} steps x ({m.n_x} states + {m.n_z} measurements)",
                                   f"{_STEPS} (steps = {steps})")])


def design_need(sc, options, steps: int) -> Need:
    """``design`` of ``sc`` with ``options`` (merged with its DESIGN defaults): the Hessians of the 'prior'
    scalings; then one run of every node's filter and the schedule it writes."""
    from .design_options import effective

    sc, options = effective(sc, options)
    m, n = sc.model, sc.network.n_nodes
    reduce = f"{_STEPS} (steps = {steps})"
    run = _consensus(m, sc.network, 1, steps, options.mode, options.linearization, "the design's run", reduce)
    run.append(Part("the schedule's JSON and report", 6 * n * steps * _JSON_VALUE, f"{steps} steps x {n} nodes",
                    reduce))
    return _need("design", [_prior_hessians(m, options)], run)


def log_values(model, n_nodes: int) -> int:
    """Numbers per step of a log of ``model`` on ``n_nodes`` nodes holding every array (studies.recorded): ``z`` and
    ``uplink``, the channels' two flags and signal, the inputs and the truth."""
    return 2 * model.n_z + n_nodes * n_nodes * (2 + model.n_x) + model.n_u + model.n_x


@dataclass(frozen=True)
class LogSize:
    """A log's size known before its arrays are made (studies.recorded.read_log): its ``source``, its ``steps``, the
    ``values`` it holds and, for an ``.npz``, the bytes ``stored`` of its arrays (their decompressed sizes)."""

    source: str
    steps: int
    values: int
    stored: int = 0
    signal: int = 0  # of ``values``, the channels' injected signal as stored: dense, N x N x n_x a step
    streamed: bool = False  # the signal read step by step (an .npz's: studies.recorded.read_log), never whole

    def kept_signal(self, network, n_x: int) -> int:
        """The most numbers of the signal kept once read: its falsified entries alone
        (:class:`filters.attacks.AttackPattern`), at most ``n_x`` on each of ``network``'s channels at every step."""
        if not self.signal or network is None:
            return self.signal
        return min(self.signal, self.steps * int(network.adjacency.sum()) * n_x)

    def reading(self, network=None, n_x: int = 0) -> Part:
        """While it is read: an ``.npz``'s arrays as stored and their float copies (a streamed signal: one step's
        slab, read and as floats, and what it keeps, :meth:`kept_signal` on ``network``'s channels), or a CSV's
        arrays as parsed and their float copies (studies.recorded.check_log)."""
        if self.streamed and self.signal:
            slab = self.signal // max(self.steps, 1)
            kept = self.kept_signal(network, n_x)
            need = self.stored - self.signal * _D + (self.values - self.signal + 2 * slab + kept) * _D
            return Part(f"reading the arrays of log {self.source}", max(need, 0),
                        f"{self.steps} steps, {self.values} numbers", _SHORTER_LOG)
        return Part(f"reading the arrays of log {self.source}",
                    self.stored + (1 if self.stored else _LOG_COPIES) * self.values * _D,
                    f"{self.steps} steps, {self.values} numbers", _SHORTER_LOG)

    def held(self, network, n_x: int) -> Part:
        """Once read: one float copy of its arrays, the channels' signal as :meth:`kept_signal`."""
        kept = self.values - self.signal + self.kept_signal(network, n_x)
        return Part(f"the arrays of log {self.source}", kept * _D, f"{self.steps} steps, {kept} numbers", _SHORTER_LOG)


def log_need(log: LogSize, network=None, n_x: int = 0) -> Need:
    """Reading a log alone, where no command's need is given (``network``, ``n_x``: the scenario's, whose channels
    bound a streamed signal's falsified entries)."""
    return _need("reading the log", [log.reading(network, n_x)])


def _consensus_design(sc, options, steps: int, reduce: str) -> list[list[Part]]:
    """The phases of a consensus design (studies.consensus_design.consensus_design) of ``options`` merged with
    ``sc``'s defaults: the Hessians of the 'prior' scalings; then, for a rule with offline tables (``scheduled``),
    the tables along ``steps`` steps, a consensus filter's run."""
    from .design_options import effective, rule_of

    sc, opts = effective(sc, options)
    phases = [[_prior_hessians(sc.model, opts)]]
    if rule_of(opts).offline_tables:
        phases.append(_consensus(sc.model, sc.network, 1, steps, opts.mode, opts.linearization,
                                 "the design's offline tables", reduce))
    return phases


def filter_need(sc, log: LogSize, *, options=None, centralized: bool = False, particles: int | None = None) -> Need:
    """``filter`` on the log of size ``log``: reading it; then, beside it, the design of ``options``'s gain rule
    (None: a filter without a design) and the filter's run: a consensus filter's per-step results at every node
    (with ``centralized``, one estimate), or with ``particles`` a particle filter's particles."""
    from .design_options import effective

    m, n_x, steps = sc.model, sc.model.n_x, log.steps
    if centralized or particles is not None:
        run = [Part("the filter's estimates and covariances", _RESULT_COPIES * (steps + 1) * (n_x + n_x**2 + 3) * _D,
                    f"{steps + 1} steps x {n_x} x {n_x} states", _SHORTER_LOG)]
        if particles is not None:
            run.append(_particles(m, 1, particles, "the particle filter", _CENTRALIZED_PF_DOUBLES))
    else:
        opts = None if options is None else effective(sc, options)[1]
        run = _consensus(m, sc.network, 1, steps, None if opts is None else opts.mode,
                         None if opts is None else opts.linearization, "the filter", _SHORTER_LOG,
                         predictions=opts is not None)  # KCF, HCMCI, the local EKFs: no gains recorded
    design = [] if options is None else _consensus_design(sc, options, steps, _SHORTER_LOG)
    if len(design) > 1:  # the offline tables are held through the run
        run = [*run, replace(design[-1][0], what="the design's offline tables, held through the run")]
    held = log.held(sc.network, n_x)
    return _need("filter", [log.reading(sc.network, n_x)],
                 *([held, *(p for p in ph if p is not None)] for ph in [*design, run]))


def node_filter_need(sc, options=None) -> Need:
    """``node_filter``: the design of ``options``'s gain rule over the scenario's horizon (None: a filter without a
    design), then every node's matrices (its filter and its neighbours' packets)."""
    m, net = sc.model, sc.network
    n, n_x = net.n_nodes, m.n_x
    nodes = Part("every node's matrices", n * (n + _STEP_MATRICES) * (n_x * n_x + n_x) * _D,
                 f"{n} nodes x {n} packets x {n_x} x {n_x} states", "a smaller network")
    design = [] if options is None else _consensus_design(sc, options, sc.steps, f"{_STEPS} (a model file's STEPS; "
                                                                              f"steps = {sc.steps})")
    return _need("node_filter", *design, [nodes])


def export_need(sc, options, steps: int, log: LogSize | None = None, *, record: int | None = None, data: int = 0,
                nodes: int | None = None) -> Need:
    """``export``: the design of ``options`` along ``steps`` steps (with its offline tables, for a rule that has
    them); then, beside the tables, the replayed run (simulated over ``steps``, or the log ``log`` read and held),
    every node's matrices as the node network steps, and the text of ``replay.txt`` and of the sources' data (every
    number written out, the tables' included, built in memory before the files are written).  ``record``: the
    numbers the exported nodes' replay records hold a step and ``data`` the numbers their sources' data add (the
    rule's :meth:`designer.export_c.NodeExport.replay_numbers`); None: ``nodes`` (default every node) each recording
    a packet from every node."""
    m, n_x = sc.model, sc.model.n_x
    n = sc.network.n_nodes
    exported = n if nodes is None else int(nodes)
    K = steps if log is None else log.steps
    reduce = f"{_STEPS} (steps = {steps})"
    design = _consensus_design(sc, options, steps, reduce)
    tables = design[-1][0] if len(design) > 1 else None
    run = [log.held(sc.network, n_x)] if log is not None else list(simulate_need(sc, K).peak)
    if record is None:
        record = exported * ((n + 2) * (n_x * n_x + n_x) + m.n_z)  # each node's packets, state and measurement
    replayed = K * record
    sizes = f"{K} steps x {exported} nodes, {record / exported:.0f} numbers a node and step"
    fewer = f"{reduce} or fewer nodes (--node)"
    parts = Part("the replayed steps' record", replayed * _D + K * exported * (n + 4) * _ARRAY_OBJECT, sizes, fewer)
    numbers = replayed + data + (tables.nbytes / _D if tables is not None else 0)
    text = Part("replay.txt and the sources' data as text (its pieces, then joined)", 2 * _TEXT * numbers,
                sizes + (" and the tables" if tables is not None else ""), fewer)
    nodes_held = node_filter_need(sc).peak
    return _need("export", *design, [*([tables] if tables is not None else []), *run, *nodes_held, parts, text])


def feasibility_need(sc, options, points: int, grid_parameters: int, chunk: int, backend=None) -> Need:
    """``feasibility``: every grid point's row; one chunk of points per worker, and each point's design."""
    from .design_options import effective

    sc, opts = effective(sc, options)
    m, n, n_x = sc.model, sc.network.n_nodes, sc.model.n_x
    batch = min(points, chunk)
    workers = _workers(backend, math.ceil(points / chunk))
    fewer = "fewer grid points (the COUNTs of --grid NAME=START:STOP:COUNT)"
    compute = [Part("the fixed-point iteration of a chunk of points",
                    batch * n * n_x * n_x * _D * _FIXED_POINT_MATRICES,
                    f"{batch} points x {n} nodes x {n_x} x {n_x} states", "a smaller model"),
               _step_hessians(m, batch * n, opts.linearization, "a smaller model")]
    rows = Part("the grid's rows", points * (_POINT_BYTES + 100 * grid_parameters), f"{points} points", fewer)
    return _need("feasibility", [rows, *_per_worker(compute, workers)],
                 [rows, *_per_worker([_prior_hessians(m, opts)], workers)])


# ------------------------------------------------------------------ the studies
def _results(runs: int, per_run: float, what: str, sizes: str) -> Part:
    """The per-run results of every run as the runner keeps them (each chunk's written into its runs' rows as it
    comes: once)."""
    return Part(f"the stored results of every run: {what}", runs * per_run, f"{runs} runs x {sizes}",
                "fewer runs (--runs)")


def _listed(v) -> list:
    return list(v) if isinstance(v, (list, tuple)) else [v]


def _designed(sc, so):
    """The scenario and the design options its consensus designs use (its DESIGN defaults merged)."""
    from .design_options import effective

    return effective(sc, so.design)


def _comparison(sc, so, uses=None) -> tuple[list, list, list]:
    sc, opts = _designed(sc, so)
    m, net = sc.model, sc.network
    n_x, n_z = m.n_x, m.n_z
    n, K = net.n_nodes, sc.steps
    R = min(so.runs, so.chunk_size)
    S = 1 + 2 * len(_listed(so["sweep_values"]))  # settings: the main one and both sweeps (at most)
    rows = R * S
    lin = opts.linearization
    channels = int(net.adjacency.sum())  # each setting's attacks on the channels alone, from draws of N x N a run
    data = Part("the chunk's runs, attacks and received measurements",
                rows * K * (channels * (n_x * _D + 2) + 2 * n_z * _D) + R * K * (n_x + n_z + 2 * n * n) * _D,
                f"{R} runs x {S} settings x {K} steps x {channels} channels", "fewer runs per chunk")
    reduce = f"{_STEPS} (a model file's STEPS)"
    modes, particles, main_only = (rules.names(), True, ()) if uses is None else uses  # the filters --filters leaves
    # each design's filter on the chunk's runs at every setting (at the main one alone: studies.comparison.
    # sweeps_left_out), without the record of its predictions (the comparison keeps the estimates and the bounds'
    # diagonals)
    designs = [_consensus(m, net, R if mode in main_only else rows, K, mode, lin, f"the {mode} design", reduce,
                          predictions=False, dense=False, variances=True) for mode in modes]
    sir = [_particles(m, 2 * rows, so.particles or 0, "the particle filters", _CENTRALIZED_PF_DOUBLES),
           Part("the particle filters' means and covariances", 2 * rows * (K + 1) * (n_x + n_x**2) * _D,
                f"{2 * rows} runs x {K + 1} steps x {n_x} x {n_x} states", reduce)] if particles else []
    filters = max((*designs, sir), key=lambda ps: sum(p.nbytes for p in ps)) if designs or sir else []
    per_run = (S * 9 * K + 10 * (K + 1) * n_x) * _D
    return ([_prior_hessians(m, opts)], [data, *filters],
            [_results(so.runs, per_run, "errors and estimates", f"{S} settings x {K} steps")])


def _consensus_robot(sc, so) -> tuple[list, list, list]:
    from .results import whole_bounds

    sc, opts = _designed(sc, so)
    m, net = sc.model, sc.network
    n_x, n, K = m.n_x, net.n_nodes, sc.steps
    R = min(so.runs, so.chunk_size)
    # the designs checked against their bound and every variant; the study's design with its reference (the paper's
    # design, or in mode paper the paper's without consensus) unless the study leaves it out (option paper_reference:
    # an automatic design's validation)
    checked, variants = (1, 6) if so.extra.get("paper_reference", True) is False else (2, 7)
    reduce = f"{_STEPS} (a model file's STEPS)"
    whole = whole_bounds(so.runs)  # below the per-pair test's runs, the bounds' diagonals alone
    # the study's filters keep no record of their predictions (its batch's covariances: studies.consensus_robot._runs)
    chunk = _consensus(m, net, R, K, opts.mode, opts.linearization, "a consensus filter", reduce, predictions=False,
                       variances=not whole)
    # a run keeps, of each checked bound, two traces and, whole, its errors whitened by it (studies.consensus_robot.
    # bound_statistics); the bounds' sum over the runs is one n_x x n_x per node and step, in a chunk and in the total
    per_run = (K + 1) * n * (checked * (whole * n_x + 2) + variants * (n_x + 1)) * _D
    summed = whole * checked * (K + 1) * n * n_x * n_x * _D
    sizes = f"{K + 1} steps x {n} nodes x {n_x} states"
    return ([_prior_hessians(m, opts)],
            [*chunk, Part("the chunk's results", R * per_run + summed, f"{R} runs x {sizes}", reduce)],
            [_results(so.runs, per_run, f"{checked} bounds' traces and {variants} estimates per run", sizes),
             Part("the bounds' sum over the runs", 2 * summed, f"{checked} x {K + 1} steps x {n} nodes x {n_x} x "
                  f"{n_x}", reduce) if whole else None])


def _particle_study(sc, so) -> tuple[list, list, list]:
    m, K = sc.model, sc.steps
    R = min(so.runs, so.chunk_size)
    particles = max([so.particles or 0, *(int(v) for v in _listed(so.extra.get("table2_particles", ())))])
    filters = 24  # at most: a study's filter configurations (its tables' rows and its sweeps)
    per_run = filters * (K + 1) * (m.n_x + 1) * _D
    return ([], [_particles(m, R, particles, "a particle filter"),
                 Part("the chunk's runs and estimates", R * per_run, f"{R} runs x {filters} filters x {K + 1} steps",
                      "fewer steps")],
            [_results(so.runs, per_run, "every filter's estimates", f"{filters} filters x {K + 1} steps")])


# study name -> (scenario, StudyOptions) -> (what the plan holds, what a chunk holds, what the results hold)
STUDY_NEEDS: dict[str, Callable[[Any, Any], tuple[list, list, list]]] = {
    "comparison": _comparison,
    "consensus-robot": _consensus_robot,
    "rrp-deception": _particle_study,
    "encrypted-switching": _particle_study,
    "binary-multi-attack": _particle_study,
    "fdi-four-tank": _particle_study,
}


def study_need(name: str, sc, so, uses=None) -> Need:
    """Study ``name`` on ``sc`` with the checked options ``so`` (:class:`studies.pipeline.StudyOptions`): the
    designs built in the plan (their Hessians), then one chunk of runs in each worker beside every run's stored
    results.  A study without an entry in :data:`STUDY_NEEDS` needs nothing here (the runner checks its stored
    results after the first chunk).  ``uses``: what the study's filters need (its ``Study.uses``: the gain rules
    designed and whether particle filters run; None: all of them)."""
    if name not in STUDY_NEEDS:
        return _need(f"study {name}")
    plan, chunk, results = STUDY_NEEDS[name](sc, so, **({} if uses is None else {"uses": uses}))
    workers = _workers(so.backend, math.ceil(so.runs / so.chunk_size))  # each builds the designs, then its chunk
    return _need(f"study {name} on {sc.name!r}", [*_per_worker(plan, workers), *results],
                 [*_per_worker(chunk, workers), *results])
