"""Recorded data: a log of one run of a sensor network, and any filter of the comparison run on it.

A **log** (schema ``cfdesign.log/1``, ``studies/schemas/log.schema.json``) is what ``cfdesign simulate`` writes
(an ``.npz``), or what a testbed recorded in the same form, or its CSV form (one row per step and sensor:
:func:`read_log_csv`, ``log_csv.schema.json``).  Its arrays, ``K`` steps, ``N`` nodes (one per sensor), ``n_z``
stacked measurement components:

* ``z`` (K, n_z): each sensor's measurement, ``z[k]`` measuring the state at time ``k + 1`` (NaN: missing);
* ``inputs`` (K, n_u): the known inputs (needed when the model has inputs; absent or empty otherwise);
* ``channel_dos``, ``channel_fdi`` (K, N, N), 0/1: entry ``[k, i, j]`` says that node ``i``'s packet from its
  neighbour ``j`` at time ``k + 1`` was lost (denial of service) or falsified; ``channel_xi`` (K, N, N, n_x): the
  signal injected into a falsified packet (the packet its sender would send if the state were displaced by ``ξ``,
  as in the studies); absent: every packet arrived unaltered;
* ``uplink`` (K, n_z): what each sensor's uplink delivered to a fusion centre (NaN where the packet was lost;
  the falsified value where it was falsified); absent: ``z``, every uplink delivered;
* ``x`` (K + 1, n_x), optional: the true states, when the log knows them (a simulated run);
* ``seed``, ``run``, optional: the study seed and run the log reproduces (``simulate --run``), which also seed the
  particle filters (:func:`particle_seed`).

:func:`read_log` reads and checks a log against a scenario (every problem an :class:`InputError` naming the file
and the array, the step and the node where it lies); :func:`run_filter` runs a filter of a
:class:`studies.filter_registry.FilterRegistry` on it, as the comparison runs that filter on a run of its own.
"""
from __future__ import annotations

import json
import math
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from designer.design import DesignOptions
from designer.fileio import Slabs
from designer.validation import InputError
from filters.attacks import AttackPattern, attack_pattern, receive, uplink_attacks
from filters.result import FilterResult

import studies.memory as memory
from .filter_registry import Batch, FilterEntry, FilterRegistry
from .memory import LogSize, Need
from .scenarios import Scenario
from .schemas import decimal

__all__ = ["LOG_SCHEMA", "Log", "read_log", "read_log_csv", "write_log_csv", "check_log", "log_arrays",
           "realised_attacks", "uplinks_received", "particle_seed", "find_filter", "filter_keys", "run_filter",
           "clip_message", "read_design_record", "design_options_of", "recorded_design"]

LOG_SCHEMA = "cfdesign.log/1"


@dataclass(frozen=True, eq=False)
class Log:
    """One recorded run (see the module docstring): ``z``, ``inputs`` (or None), ``attacks`` (the channels' record,
    None: every packet arrived), ``uplink`` (K, n_z), ``x`` (or None), ``seed`` and ``run`` (or None) and the
    ``source`` it was read from."""

    z: np.ndarray
    inputs: np.ndarray | None
    attacks: AttackPattern | None
    uplink: np.ndarray
    x: np.ndarray | None = None
    seed: int | None = None
    run: int | None = None
    source: str = "<memory>"

    @property
    def steps(self) -> int:
        return int(self.z.shape[0])


def realised_attacks(sc: Scenario, u: np.ndarray, s: np.ndarray, x: np.ndarray, z: np.ndarray
                     ) -> tuple[AttackPattern, np.ndarray]:
    """The attacks that the channel draws ``u``, ``s`` (:func:`filters.attacks.channel_draws`) make on ``sc``'s
    channels and uplinks: the channels' :class:`AttackPattern` and what the uplinks delivered to a fusion centre
    from the truth ``x`` and the clean measurements ``z`` (:func:`filters.attacks.receive`: ``(K, n_z + N)``,
    values then each sensor's availability)."""
    return attack_pattern(sc.network, u, s, sc.model.n_x, sc.resolved_attacks.signal), uplinks_received(sc, u, s, x, z)


def uplinks_received(sc: Scenario, u: np.ndarray, s: np.ndarray, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """What the channel draws ``u``, ``s`` let ``sc``'s uplinks deliver to a fusion centre from the truth ``x`` and
    the clean measurements ``z`` (:func:`realised_attacks`' second value)."""
    m, att = sc.model, sc.resolved_attacks
    up = uplink_attacks(u, s, m.n_x, dos_prob=att.uplink_dos, fdi_prob=att.uplink_fdi, signal=att.signal)
    return receive(m, x, z, up)


def log_arrays(model, z, inputs, attacks: AttackPattern | None, received: np.ndarray | None) -> dict:
    """The arrays of a log (the module docstring's names) from a run's measurements, inputs, channel attacks and
    the uplinks' deliveries as :func:`realised_attacks` gives them (NaN where an uplink was lost)."""
    out = {"schema": np.array(LOG_SCHEMA), "z": np.asarray(z, float)}
    if inputs is not None:
        out["inputs"] = np.asarray(inputs, float)
    if attacks is not None:  # the signal step by step from the falsified entries: never the dense array whole
        K, N = attacks.dos.shape[:2]
        out.update(channel_dos=attacks.dos.astype(np.uint8), channel_fdi=attacks.fdi.astype(np.uint8),
                   channel_xi=Slabs((K, N, N, model.n_x), float, attacks.xi_of))
    if received is not None:
        values, avail = received[:, :model.n_z], received[:, model.n_z:] > 0.5
        lost = np.repeat(~avail, model.sensor_dims, axis=1)
        out["uplink"] = np.where(lost, np.nan, values)
    return out


def _fail(source: str, text: str) -> InputError:
    return InputError(f"log {source}: {text}")


def _array(data: dict, key: str, source: str, shape: tuple, *, optional: bool = False, nan: bool = False,
           flags: bool = False):
    """``data[key]`` as a float array of ``shape`` (None for a free axis), finite (NaN allowed with ``nan``): of an
    integer or floating-point dtype (``flags``: booleans too, as 0 and 1)."""
    if key not in data:
        if optional:
            return None
        raise _fail(source, f"array {key!r} is missing (a log holds {', '.join(LOG_KEYS)})")
    a = np.asarray(data[key])
    _check_kind(key, source, a.dtype, a.shape, shape, flags)
    a = a.astype(float)
    _check_values(key, source, a, nan)
    return a


def _check_kind(key: str, source: str, dtype, got: tuple, shape: tuple, flags: bool = False) -> None:
    """:func:`_array`'s checks of an array's dtype and shape (``got``; None in ``shape``: a free axis)."""
    if dtype.kind not in ("biuf" if flags else "iuf"):
        raise _fail(source, f"array {key!r} must hold numbers (an integer or floating-point dtype"
                            + (", or booleans" if flags else "") + f"), got dtype {dtype}"
                            + (" (booleans are not measurements)" if dtype.kind == "b" else ""))
    if len(got) != len(shape) or any(want is not None and g != want for g, want in zip(got, shape)):
        want = " x ".join("any" if w is None else str(w) for w in shape)
        raise _fail(source, f"array {key!r} must have shape {want}, got {' x '.join(map(str, got)) or 'scalar'}")


def _check_values(key: str, source: str, a: np.ndarray, nan: bool = False, at: tuple = ()) -> None:
    """:func:`_array`'s check of the values: finite (NaN too with ``nan``); ``at``: the index of ``a`` in its array."""
    bad = ~np.isfinite(a) & (np.isinf(a) if nan else True)
    if np.any(bad):
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        raise _fail(source, f"array {key!r} holds {a[where]} at index {list(at + where)}"
                            + (" (only NaN, a missing value, is allowed there)" if nan else " (values must be finite)"))


class _StreamedSignal:
    """A log's ``channel_xi`` in its ``.npz`` (:func:`read_log`), read step by step from the archive's member by
    :meth:`falsified`, so that the dense array (N x N x n_x a step, nearly all zeros: 0.8 GB for a run of the 118-bus
    grid) is never whole in memory: only the signals of the falsified entries are kept."""

    def __init__(self, zf: zipfile.ZipFile, info: zipfile.ZipInfo, shape: tuple, dtype):
        self.zf, self.info, self.shape, self.dtype = zf, info, shape, dtype

    def falsified(self, fdi: np.ndarray, source: str, shape: tuple) -> np.ndarray:
        """The signals at ``fdi``'s entries in row-major order (:class:`filters.attacks.AttackPattern`'s ``xi_fdi``),
        each step's slab checked as :func:`_array` checks the whole (dtype, ``shape``, finite values)."""
        _check_kind("channel_xi", source, self.dtype, self.shape, shape)
        per = math.prod(self.shape[1:])
        parts = []
        with self.zf.open(self.info) as fh:
            version = np.lib.format.read_magic(fh)
            (np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0)(fh)
            for k in range(self.shape[0]):
                raw = fh.read(per * self.dtype.itemsize)
                step = np.frombuffer(raw, self.dtype, count=per).reshape(self.shape[1:]).astype(float)
                _check_values("channel_xi", source, step, at=(k,))
                parts.append(step[fdi[k]])
        return np.concatenate(parts) if parts else np.zeros((0, shape[-1]))


LOG_KEYS = ("z", "inputs", "channel_dos", "channel_fdi", "channel_xi", "uplink", "x", "seed", "run")


def _flags(data: dict, key: str, source: str, shape: tuple, links: np.ndarray) -> np.ndarray | None:
    """A flag array, checked as :func:`_array` checks it, without its float copy (K x N x N, 8 bytes an entry)."""
    if key not in data:
        return None
    a = np.asarray(data[key])
    _check_kind(key, source, a.dtype, a.shape, shape, flags=True)
    _check_values(key, source, a)
    if np.any((a != 0) & (a != 1)):
        where = tuple(int(i) for i in np.argwhere((a != 0) & (a != 1))[0])
        raise _fail(source, f"array {key!r} must hold 0 or 1, got {float(a[where])} at index {list(where)}")
    off = (a == 1) & ~links[None]
    if np.any(off):
        k, i, j = (int(v) for v in np.argwhere(off)[0])
        raise _fail(source, f"array {key!r}[{k}, {i}, {j}] = 1 marks a packet from node {j} to node {i} at step "
                            f"{k + 1}, but the network has no link {j} -> {i}")
    return a == 1


def _integer(data: dict, key: str, source: str) -> int | None:
    if key not in data:
        return None
    a = np.asarray(data[key])
    if a.shape != () or a.dtype.kind not in "iu" or int(a) < 0:
        raise _fail(source, f"{key!r} must be a non-negative integer, got {a!r}")
    return int(a)


def read_log(path, sc: Scenario, need: Callable[[LogSize], Need] | None = None) -> Log:
    """The log at ``path`` (an ``.npz``, or its CSV form: :func:`read_log_csv`), checked against the scenario
    ``sc`` (its model and network): shapes, dtypes, values, flags only on the network's links, falsified packets
    with their signal.  Every problem is an :class:`InputError` naming the file, the array and where.

    Before any array is made, the memory is checked (:func:`studies.memory.check`): ``need(size)``, the need of the
    command that reads the log given its :class:`studies.memory.LogSize` (from the sizes an ``.npz``'s directory
    and headers declare, or a CSV's largest step), or without ``need`` the log's reading alone."""
    p = Path(path)
    source = str(p)
    if not p.is_file():
        raise _fail(source, "no such file")
    if p.suffix.lower() == ".csv":
        return read_log_csv(p, sc, need)
    if p.suffix.lower() != ".npz":
        raise _fail(source, f"must be an .npz or a .csv file (what cfdesign simulate writes), got suffix "
                            f"{p.suffix!r}")
    if not zipfile.is_zipfile(p):
        raise _fail(source, "is not an .npz archive (the file is damaged or not written by numpy.savez)")
    try:
        with zipfile.ZipFile(p) as zf:
            members = _npz_members(zf, source)
            shapes = {k: shape for k, (_, shape, _, _) in members.items()}
            z = shapes.get("z", ())
            steps = z[0] if z else 0
            streamed = "channel_xi" in members and not members["channel_xi"][3]  # C order: step by step
            log = memory.LogSize(source, steps, sum(math.prod(s) for s in shapes.values()),
                                 sum(info.file_size for info, _, _, _ in members.values()),
                                 math.prod(shapes["channel_xi"]) if "channel_xi" in shapes else 0, streamed)
            memory.check(memory.log_need(log, sc.network, sc.model.n_x) if need is None else need(log))
            data = {}
            for key, (info, shape, dtype, _) in members.items():
                if key == "channel_xi" and streamed:
                    data[key] = _StreamedSignal(zf, info, shape, dtype)
                    continue
                with zf.open(info) as fh:
                    data[key] = np.lib.format.read_array(fh, allow_pickle=False)
            return check_log(data, sc, source)  # the signal read from the archive, still open
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - a damaged or foreign file: one line
        raise _fail(source, f"cannot be read: {type(exc).__name__}: {exc}") from None


def _npz_members(zf: zipfile.ZipFile, source: str) -> dict[str, tuple[zipfile.ZipInfo, tuple[int, ...], np.dtype,
                                                                       bool]]:
    """The members of an ``.npz`` that a log reads (``schema`` and :data:`LOG_KEYS`; others are ignored, unread):
    each with the shape, dtype and Fortran order its ``.npy`` header declares, read from the zip directory and the
    headers alone.  A header that does not parse, an array of objects or records, or a shape that disagrees with the
    member's size (a damaged or forged file) is refused naming the array."""
    out = {}
    for key in ("schema", *LOG_KEYS):
        try:
            info = zf.getinfo(f"{key}.npy")
        except KeyError:
            continue
        try:
            with zf.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                read = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                    np.lib.format.read_array_header_2_0
                shape, fortran, dtype = read(fh)
                header = fh.tell()
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
            raise _fail(source, f"array {key!r} has no readable .npy header: {exc}") from None
        if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None:
            raise _fail(source, f"array {key!r} has dtype {dtype}: a log's arrays hold numbers (or the schema's "
                                "text), not objects or records")
        if header + math.prod(shape) * dtype.itemsize != info.file_size:
            raise _fail(source, f"array {key!r} declares shape {' x '.join(map(str, shape)) or 'scalar'} of "
                                f"{dtype} ({math.prod(shape) * dtype.itemsize} bytes), but the archive holds "
                                f"{info.file_size - header} bytes for it: the file is damaged")
        out[key] = (info, tuple(int(n) for n in shape), dtype, bool(fortran))
    return out


def check_log(data: dict, sc: Scenario, source: str = "<memory>") -> Log:
    """The log of the arrays ``data`` (the module docstring's names), checked against ``sc`` (see
    :func:`read_log`)."""
    m, net = sc.model, sc.network
    if "schema" in data:
        schema = np.asarray(data["schema"])
        if schema.shape != () or schema.dtype.kind != "U" or str(schema) != LOG_SCHEMA:
            shown = repr(str(schema)[:80]) if schema.shape == () and schema.dtype.kind == "U" else \
                f"an array of {schema.dtype}"
            raise _fail(source, f"has schema {shown}, expected {LOG_SCHEMA!r}")
    z = _array(data, "z", source, (None, m.n_z), nan=True)
    K = z.shape[0]
    if K < 1:
        raise _fail(source, "array 'z' has no step")
    inputs = _array(data, "inputs", source, (K, None), optional=True)
    if inputs is not None and inputs.shape[1] == 0:
        inputs = None
    if m.n_u and (inputs is None or inputs.shape[1] != m.n_u):
        got = "none" if inputs is None else f"{inputs.shape[1]} per step"
        raise _fail(source, f"array 'inputs' must give the model's {m.n_u} known inputs per step ({K} x {m.n_u}), "
                            f"got {got}")
    if not m.n_u and inputs is not None:
        raise _fail(source, f"array 'inputs' gives {inputs.shape[1]} inputs per step, but the model takes none")
    x = _array(data, "x", source, (K + 1, m.n_x), optional=True)
    uplink = _array(data, "uplink", source, (K, m.n_z), optional=True, nan=True)
    attacks = None
    if net is not None:
        N = net.n_nodes
        links = np.asarray(net.adjacency, bool)
        dos = _flags(data, "channel_dos", source, (K, N, N), links)
        fdi = _flags(data, "channel_fdi", source, (K, N, N), links)
        streamed = data.get("channel_xi")
        streamed = streamed if isinstance(streamed, _StreamedSignal) else None
        xi = None if streamed else _array(data, "channel_xi", source, (K, N, N, m.n_x), optional=True)
        if dos is not None or fdi is not None:
            dos = np.zeros((K, N, N), bool) if dos is None else dos
            fdi = np.zeros((K, N, N), bool) if fdi is None else fdi
            both = dos & fdi
            if np.any(both):
                k, i, j = (int(v) for v in np.argwhere(both)[0])
                raise _fail(source, f"the packet from node {j} to node {i} at step {k + 1} is marked both lost "
                                    "(channel_dos) and falsified (channel_fdi)")
            if xi is None and streamed is None and np.any(fdi):
                raise _fail(source, "array 'channel_xi' is missing: it gives the signal injected into each "
                                    "falsified packet (channel_fdi)")
            if streamed is not None:
                attacks = AttackPattern(dos, fdi, streamed.falsified(fdi, source, (K, N, N, m.n_x)))
            else:
                attacks = AttackPattern(dos, fdi, np.zeros((0, m.n_x))) if xi is None else \
                    AttackPattern.dense(dos, fdi, xi)
    return Log(z, inputs, attacks, z if uplink is None else uplink, x, _integer(data, "seed", source),
               _integer(data, "run", source), source)


def particle_seed(seed: int, run: int) -> np.random.SeedSequence:
    """The particle filters' seed of run ``run`` of a study with seed ``seed``: the third child of the run's
    seed (:func:`studies.runner.run_seed`), as in the comparison (truth, channels, particle filters)."""
    from .runner import run_seed

    return run_seed(seed, run).spawn(3)[2]


def filter_keys(registry: FilterRegistry) -> dict[str, str]:
    """Short names of the registry's filters for a command line: a designed filter's gain rule (``scheduled``,
    ``tuned``...), otherwise the name in lower case with every run of other characters than letters and digits one
    ``-`` (``kcf``, ``hcmci``, ``centralized-ekf-trusts-every-packet``)."""
    import re

    keys = {}
    for e in registry:
        key = e.mode if e.designed else re.sub(r"[^a-z0-9]+", "-", e.name.lower()).strip("-")
        keys.setdefault(key, e.name)
    return keys


def find_filter(registry: FilterRegistry, name: str) -> FilterEntry:
    """The registry's filter called ``name``: its name, its short name (:func:`filter_keys`) or the beginning of
    exactly one short name (``local`` for ``local-ekf-at-every-node-no-network``)."""
    if name in registry:
        return registry[name]
    keys = filter_keys(registry)
    key = name.lower()
    begins = [k for k in keys if k.startswith(key)] if key else []
    if key in keys or len(begins) == 1:
        return registry[keys[key if key in keys else begins[0]]]
    which = f"{name!r} begins {len(begins)} of them ({', '.join(begins)})" if begins else f"got {name!r}"
    raise InputError(f"filter must be one of {', '.join(keys)} (or a filter's full name: "
                     f"{'; '.join(registry.names())}); {which}")


def run_filter(sc: Scenario, log: Log, entry: FilterEntry, *, design=None, seed: int = 0, run: int = 0,
               particles: int = 500, iterations: int = 1) -> FilterResult:
    """``entry`` run on ``log`` as the comparison runs it on one of its runs at its main setting: ``design`` the
    design of its gain rule (for an entry with a ``mode``; derived as the entry derives it), the particle filters
    seeded by :func:`particle_seed` (``seed``, ``run``), ``particles`` of them, ``iterations`` consensus rounds per
    step for the filters that take them (HCMCI)."""
    m = sc.model
    if entry.runtime != "centralized" and np.any(np.isnan(log.z)):  # the fusion centre reads the uplinks instead
        k, c = (int(v) for v in np.argwhere(np.isnan(log.z))[0])
        raise _fail(log.source, f"z[{k}, {c}] is missing (NaN): filter {entry.name!r} needs every node's own "
                                "measurement at every step; the centralized filters (EKF, particle filters) "
                                "skip a missing one")
    lost = np.isnan(log.uplink)
    avail = ~np.add.reduceat(lost, m.sensor_offsets[:-1], axis=1).astype(bool)
    received = np.concatenate([np.where(lost, 0.0, log.uplink), avail.astype(float)], axis=1)
    N = sc.network.n_nodes
    attacks = log.attacks or AttackPattern(np.zeros((log.steps, N, N), bool), np.zeros((log.steps, N, N), bool),
                                           np.zeros((0, m.n_x)))
    batch = Batch((sc,), log.z[None], None if log.inputs is None else log.inputs[None], ((attacks,),),
                  received=((received,),), particle_seeds=(particle_seed(seed, run),), particles=particles,
                  iterations=iterations, run_ids=(run,))
    return entry.run(batch, [0], None if entry.mode is None else entry.design_for(design, m))


_RECORD_MESSAGE_MAX = 600  # characters of a message quoting a design directory's content
_SEED_MAX = 2**63 - 1


def clip_message(text: str) -> str:
    """A message quoting a file's content (a design directory's), at most :data:`_RECORD_MESSAGE_MAX` characters:
    a longer one keeps its start and its end (where the advice is), `` ... `` between."""
    if len(text) <= _RECORD_MESSAGE_MAX:
        return text
    tail = _RECORD_MESSAGE_MAX // 3
    return text[:_RECORD_MESSAGE_MAX - tail - 5] + " ... " + text[-tail:]


def _refuse_constant(token: str):
    raise ValueError(f"{token} is not a JSON number (cfdesign writes finite numbers only)")


def _finite_float(token: str) -> float:
    v = float(token)
    if not np.isfinite(v):
        raise ValueError(f"the number {clip_message(token)} is beyond a double's range")
    return v


def read_design_record(schedule_dir, name: str = "schedule") -> tuple[Path, dict]:
    """The path and the content of the ``schedule.json`` of a design directory written by ``cfdesign design``
    (``schedule_dir``: the directory or the file; ``name``: the parameter, for the messages), read as data from
    elsewhere: JSON only (nothing is imported or run), an object whose fields a command uses have their types
    (``scenario`` a string; ``source``, ``source_digest`` (64 hex digits), ``model_digest``, ``mode``,
    ``verdict`` strings or null; ``options`` and ``params`` objects; ``seed`` an integer in 0..2**63 - 1 or
    null), no NaN, no infinity, no number beyond a double's range; else :class:`InputError`, one line naming the
    file and the field (never quoting more than a few hundred characters of it)."""
    p = Path(schedule_dir)
    path = p / "schedule.json" if p.is_dir() else p
    if not path.is_file():
        raise InputError(f"{name} {str(p)!r} is not a design directory (no schedule.json): give the --out "
                         "directory of cfdesign design")
    try:
        meta = json.loads(path.read_bytes().decode("utf-8"), parse_constant=_refuse_constant,
                          parse_float=_finite_float)
    except (ValueError, RecursionError, OSError) as exc:  # JSONDecodeError, UnicodeDecodeError are ValueErrors
        what = "nested too deeply" if isinstance(exc, RecursionError) else clip_message(str(exc))
        raise InputError(f"{name} {str(path)!r} is not valid JSON: {what}") from None
    if not isinstance(meta, dict):
        raise InputError(f"{name} {str(path)!r} must hold a JSON object (a design's record), got "
                         f"{type(meta).__name__}")

    def refuse(field, what):
        raise InputError(f"{name} {str(path)!r}: {field} must be {what}, got {type(meta.get(field)).__name__}")

    if not isinstance(meta.get("scenario"), str):
        refuse("scenario", "a string (the scenario's name)")
    for field in ("source", "model_digest", "mode", "verdict"):
        if not isinstance(meta.get(field), (str, type(None))):
            refuse(field, "a string or null")
    digest = meta.get("source_digest")
    if digest is not None and not (isinstance(digest, str) and len(digest) == 64
                                   and all(c in "0123456789abcdef" for c in digest)):
        refuse("source_digest", "64 hexadecimal digits (a SHA-256) or null")
    for field in ("options", "params"):
        if not isinstance(meta.get(field, {}), (dict, type(None))):
            refuse(field, "an object or null")
    seed = meta.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= _SEED_MAX):
        raise InputError(f"{name} {str(path)!r}: seed must be an integer in 0..{_SEED_MAX} or null, got "
                         + (clip_message(repr(seed)) if isinstance(seed, (int, float)) else type(seed).__name__))
    return path, meta


def design_options_of(schedule_dir, sc: Scenario, record: tuple[Path, dict] | None = None
                      ) -> tuple[str, DesignOptions, dict]:
    """The gain rule, the design options and the ``schedule.json`` of a design directory written by
    ``cfdesign design`` for the scenario ``sc``: a design of another scenario, or of this one's model as it was
    before an edit (its recorded ``model_digest``), is refused.  The file is read as data
    (:func:`read_design_record`, or ``record``, what it returned already): nothing it names is imported."""
    p = Path(schedule_dir)
    path, meta = read_design_record(schedule_dir) if record is None else record
    opts = meta.get("options")
    if not isinstance(opts, dict) or "mode" not in opts:
        raise InputError(f"schedule {str(path)!r} records no design options (written by an older cfdesign "
                         "design?): design again")
    if meta["scenario"] != sc.name:
        raise InputError(clip_message(f"schedule {str(p)!r} was designed for scenario {meta['scenario']!r}, "
                                      f"not {sc.name!r}"))
    if meta.get("model_digest") not in (None, sc.digest):
        raise InputError(f"schedule {str(p)!r} was designed for another version of the model {sc.name!r} (its "
                         "content or parameters changed since): design again, or give the model and parameters it "
                         "was designed with")
    mode = opts["mode"] or meta.get("mode")  # the options as given (None: the default), the rule as designed
    if not isinstance(mode, str):
        raise InputError(f"schedule {str(path)!r} records no gain rule (mode): design again")
    known = set(DesignOptions().as_dict())
    try:
        options = DesignOptions(**{**{str(k): v for k, v in opts.items() if k in known}, "mode": mode})
    except InputError as exc:
        raise InputError(clip_message(f"schedule {str(path)!r}: its design options: {exc}")) from None
    return mode, options, meta


def recorded_design(schedule_dir, sc: Scenario, options: DesignOptions, *, steps: int | None = None):
    """The design a design directory recorded, for ``sc`` and its ``options`` (:func:`design_options_of`): the
    design the options make, with its rule's offline tables read from ``schedule.npz``
    (:meth:`designer.rule.GainRule.recorded_tables`, checked against the model, the network and the design) instead
    of designed again, unless the run is longer (``steps``) than the recorded horizon, whose tables and certificate
    must cover its steps: then they are designed for it (:func:`studies.consensus_design.consensus_design`).  A rule
    without tables: its design (nothing to read)."""
    import rules
    from designer.schedule import load_schedule

    from .consensus_design import consensus_design, effective_design

    sc_e, _, design = effective_design(sc, options)
    if not design.rule.offline_tables:
        return design
    sched = load_schedule(Path(schedule_dir), lambda name, param: rules.get(name))  # the arrays read safely, once
    if steps is not None and steps > sched.steps:
        return consensus_design(sc, options, steps=steps)
    arrays = {"Phi": sched.Phi, "valid": sched.valid, "sigma": sched.sigma, "beta": sched.beta,
              **({} if sched.margin28 is None else {"margin28": sched.margin28, "margin29": sched.margin29}),
              **{f"table_{k}": v for k, v in (sched.tables or {}).items()}}
    meta = {**sched.meta, "violations": sched.violations}
    return design._replace(tables=design.rule.recorded_tables(sc_e.model, sc_e.network, design, arrays, meta))


# --------------------------------------------------------------------------------------------------- the CSV form
# One row per step and sensor (schema log_csv, studies/schemas/log_csv.schema.json):
#   step      1..K: the row's measurement measures the state at time `step` (z[step - 1]); step 0 rows carry the
#             initial true state alone (x1..)
#   sensor    0..N-1, the sensor (= node) of the row
#   z1..zM    the sensor's measurement components (M: the largest sensor dimension; empty beyond its own, and an
#             empty cell within it: a missing measurement)
#   uplink1..uplinkM   optional: what the sensor's uplink delivered to a fusion centre (empty: lost); without these
#             columns every uplink delivered z
#   from_J    optional, one per node J: the packet node J sent to this row's node at this step: 1 received, 0 lost,
#             f:XI_1;...;XI_nx falsified with the injected signal XI; empty where J is not a neighbour
#   u1..u_nu  the known inputs of the step (the same on every row of the step), when the model has inputs
#   x1..x_nx  optional: the true state at time `step` (the same on every row of the step)
# A (step, sensor) row that is absent: the sensor's measurement is missing and the packets to its node were lost.
def _csv_columns(m, n_nodes: int, *, uplink: bool, channels: bool, truth: bool) -> list[str]:
    M = max(m.sensor_dims)
    cols = ["step", "sensor", *(f"z{c + 1}" for c in range(M))]
    cols += [f"uplink{c + 1}" for c in range(M)] if uplink else []
    cols += [f"from_{j}" for j in range(n_nodes)] if channels else []
    cols += [f"u{c + 1}" for c in range(m.n_u)]
    cols += [f"x{c + 1}" for c in range(m.n_x)] if truth else []
    return cols


def _num(v: float) -> str:
    return "" if np.isnan(v) else repr(float(v))


def write_log_csv(path, data: dict, model, network) -> Path:
    """Write the log arrays ``data`` (:func:`log_arrays`, with ``x`` when known) as the CSV form, atomically
    (``network`` None: a model without one, no channel columns)."""
    from designer.fileio import atomic_write

    m = model
    z, K = np.asarray(data["z"], float), data["z"].shape[0]
    N = m.n_sensors
    dims = list(m.sensor_dims)
    off = m.sensor_offsets
    up, x = data.get("uplink"), data.get("x")
    has_ch = "channel_dos" in data and network is not None
    cols = _csv_columns(m, N, uplink=up is not None, channels=has_ch, truth=x is not None)
    M = max(dims)
    adj = np.zeros((N, N), bool) if network is None else np.asarray(network.adjacency, bool)
    u = data.get("inputs")

    def row_cells(k: int, i: int) -> list[str]:
        a, b = off[i], off[i + 1]
        cells = [str(k + 1), str(i), *(_num(v) for v in z[k, a:b]), *([""] * (M - dims[i]))]
        if up is not None:
            cells += [*(_num(v) for v in up[k, a:b]), *([""] * (M - dims[i]))]
        if has_ch:
            for j in range(N):
                if not adj[i, j]:
                    cells.append("")
                elif data["channel_dos"][k, i, j]:
                    cells.append("0")
                elif data["channel_fdi"][k, i, j]:
                    cells.append("f:" + ";".join(repr(float(v)) for v in data["channel_xi"][k, i, j]))
                else:
                    cells.append("1")
        if m.n_u:
            cells += [repr(float(v)) for v in u[k]]
        if x is not None:
            cells += [repr(float(v)) for v in x[k + 1]]
        return cells

    def write(fh):
        fh.write((",".join(cols) + "\n").encode())
        if x is not None:
            first = ["0", ""] + [""] * (len(cols) - 2 - m.n_x) + [repr(float(v)) for v in x[0]]
            fh.write((",".join(first) + "\n").encode())
        for k in range(K):
            for i in range(N):
                fh.write((",".join(row_cells(k, i)) + "\n").encode())

    return atomic_write(Path(path), write)


def _csv_error(source: str, line: int, column: str | None, text: str) -> InputError:
    return _fail(source, f"line {line}" + (f", column {column!r}" if column else "") + f": {text}")


def read_log_csv(path, sc: Scenario, need: Callable[[LogSize], Need] | None = None) -> Log:
    """The CSV form of a log (see the comment above :func:`write_log_csv`), checked against ``sc``: every problem
    an :class:`InputError` naming the file, the line and the column.  A UTF-8 BOM and CRLF line ends are read; a
    number is decimal only (:func:`studies.schemas.decimal`).  The memory its arrays need (``K`` steps, the
    largest step) is checked as :func:`read_log` does, before they are made."""
    import csv

    m, net = sc.model, sc.network
    p = Path(path)
    source = str(p)
    N = net.n_nodes
    dims = list(m.sensor_dims)
    off = m.sensor_offsets
    adj = np.asarray(net.adjacency, bool)
    try:
        fh = p.open(newline="", encoding="utf-8-sig")  # skips a UTF-8 BOM (as spreadsheets write)
    except OSError as exc:
        raise _fail(source, f"cannot be read: {exc.strerror or exc}") from None
    with fh:
        reader = csv.reader(fh)
        try:
            header = next(reader)
        except StopIteration:
            raise _fail(source, "is empty (a CSV log starts with its header row)") from None
        except (csv.Error, UnicodeDecodeError) as exc:
            raise _fail(source, f"is not a CSV file: {exc}") from None
        header = [h.strip() for h in header]
        M = max(dims)
        known = set(_csv_columns(m, N, uplink=True, channels=True, truth=True))
        for c in header:
            if c not in known:
                raise _csv_error(source, 1, c, "unknown column (a log's columns: step, sensor, z1..z"
                                 f"{M}, uplink1..uplink{M}, from_0..from_{N - 1}"
                                 + (f", u1..u{m.n_u}" if m.n_u else "") + f", x1..x{m.n_x})")
        for c in ("step", "sensor", *(f"z{c + 1}" for c in range(M)), *(f"u{c + 1}" for c in range(m.n_u))):
            if c not in header:
                raise _csv_error(source, 1, None, f"column {c!r} is missing")
        if len(set(header)) != len(header):
            dup = next(c for c in header if header.count(c) > 1)
            raise _csv_error(source, 1, dup, "appears twice in the header")
        col = {c: header.index(c) for c in header}
        has_up = "uplink1" in col
        if has_up and any(f"uplink{c + 1}" not in col for c in range(M)):
            raise _csv_error(source, 1, None, f"the uplink columns must be all of uplink1..uplink{M}, or none")
        has_ch = any(c.startswith("from_") for c in col)
        if has_ch and any(f"from_{j}" not in col for j in range(N)):
            raise _csv_error(source, 1, None, f"the channel columns must be all of from_0..from_{N - 1}, or none")
        has_x = "x1" in col
        if has_x and any(f"x{c + 1}" not in col for c in range(m.n_x)):
            raise _csv_error(source, 1, None, f"the truth columns must be all of x1..x{m.n_x}, or none")
        rows: dict[tuple[int, int], dict] = {}
        x0, per_step = None, {}
        try:
            for line, cells in enumerate(reader, start=2):
                if not cells or all(not c.strip() for c in cells):
                    continue
                if len(cells) != len(header):
                    raise _csv_error(source, line, None, f"{len(cells)} cells, the header has {len(header)}")

                def number(name, cells=cells, line=line, empty_ok=True):
                    t = cells[col[name]].strip()
                    if t == "":
                        if empty_ok:
                            return np.nan
                        raise _csv_error(source, line, name, "is empty")
                    v = decimal(t)
                    if v is None and t.lower().lstrip("+-") in ("nan", "inf", "infinity"):
                        v = np.nan
                    elif v is None:
                        raise _csv_error(source, line, name, f"{t!r} is not a number (a decimal number: digits "
                                                             "with an optional sign, point and exponent)")
                    if not np.isfinite(v):
                        raise _csv_error(source, line, name, f"{t!r} is not a finite number (leave the cell "
                                                             "empty for a missing value)")
                    return v

                def integer(name, low, high, cells=cells, line=line):
                    t = cells[col[name]].strip()
                    if not (t.isascii() and t.isdigit() and len(t) <= 12) or not low <= int(t) <= high:
                        raise _csv_error(source, line, name, f"{t!r} is not an integer in [{low}, {high}]")
                    return int(t)

                k = integer("step", 0, 10**9)
                if k == 0:
                    if not has_x:
                        raise _csv_error(source, line, "step", "step 0 carries the initial true state (x1..), "
                                                               "but the log has no truth columns")
                    x0 = np.array([number(f"x{c + 1}", empty_ok=False) for c in range(m.n_x)])
                    continue
                i = integer("sensor", 0, N - 1)
                if (k, i) in rows:
                    raise _csv_error(source, line, "sensor", f"a second row for step {k} and sensor {i} "
                                                             f"(first on line {rows[(k, i)]['line']})")
                zi = [number(f"z{c + 1}") for c in range(M)]
                if any(not np.isnan(v) for v in zi[dims[i]:]):
                    c = next(c for c in range(dims[i], M) if not np.isnan(zi[c]))
                    raise _csv_error(source, line, f"z{c + 1}", f"sensor {i} measures {dims[i]} component"
                                     f"{'s' if dims[i] > 1 else ''}: the cell must be empty")
                rec = {"line": line, "z": zi[:dims[i]]}
                if has_up:
                    rec["uplink"] = [number(f"uplink{c + 1}") for c in range(dims[i])]
                if has_ch:
                    flags = []
                    for j in range(N):
                        name = f"from_{j}"
                        t = cells[col[name]].strip()
                        if not adj[i, j]:
                            if t:
                                raise _csv_error(source, line, name, f"node {j} is not a neighbour of node {i}: "
                                                                     "the cell must be empty")
                            flags.append(None)
                        elif t in ("0", "1"):
                            flags.append(int(t))
                        elif t.startswith("f:"):
                            xi = [decimal(v.strip()) for v in t[2:].split(";")]
                            if len(xi) != m.n_x or None in xi or not np.all(np.isfinite(xi)):
                                raise _csv_error(source, line, name, f"{t!r}: a falsified packet is f: and its "
                                                                     f"injected signal, {m.n_x} finite numbers "
                                                                     "separated by ;")
                            flags.append(np.array(xi))
                        else:
                            raise _csv_error(source, line, name, f"{t!r} must be 1 (received), 0 (lost) or "
                                                                 "f:XI_1;...;XI_nx (falsified)")
                    rec["from"] = flags
                for group, n in (("u", m.n_u), ("x", m.n_x if has_x else 0)):
                    if n:
                        vals = np.array([number(f"{group}{c + 1}", empty_ok=False) for c in range(n)])
                        seen = per_step.setdefault((group, k), (vals, line))
                        if not np.array_equal(seen[0], vals):
                            what = "inputs" if group == "u" else "true state"
                            raise _csv_error(source, line, f"{group}1", f"the {what} of step {k} differ from line "
                                                                        f"{seen[1]}'s")
                rows[(k, i)] = rec
        except csv.Error as exc:
            raise _fail(source, f"line {reader.line_num}: {exc}") from None
    if not rows:
        raise _fail(source, "holds no measurement row")
    K = max(k for k, _ in rows)
    log = memory.LogSize(source, K, K * memory.log_values(m, N) + m.n_x, signal=K * N * N * m.n_x)
    memory.check(memory.log_need(log, net, m.n_x) if need is None else need(log))
    z = np.full((K, m.n_z), np.nan)
    uplink = np.full((K, m.n_z), np.nan) if has_up else None
    dos = np.zeros((K, N, N), bool)
    fdi = np.zeros((K, N, N), bool)
    xi = np.zeros((K, N, N, m.n_x))
    for (k, i), rec in rows.items():
        a, b = off[i], off[i + 1]
        z[k - 1, a:b] = rec["z"]
        if has_up:
            uplink[k - 1, a:b] = rec["uplink"]
        for j, f in enumerate(rec.get("from", [])):
            if isinstance(f, np.ndarray):
                fdi[k - 1, i, j], xi[k - 1, i, j] = True, f
            elif f == 0:
                dos[k - 1, i, j] = True
    for k in range(1, K + 1):  # an absent row: the sensor's measurement missing, the packets to its node lost
        for i in range(N):
            if (k, i) not in rows:
                dos[k - 1, i] = adj[i]
    data = {"z": z}
    if has_ch or len(rows) < K * N:
        data.update(channel_dos=dos, channel_fdi=fdi, channel_xi=xi)
    if has_up:
        data["uplink"] = uplink
    if m.n_u:
        missing = [k for k in range(1, K + 1) if ("u", k) not in per_step]
        if missing:
            raise _fail(source, f"step {missing[0]} has no row, so no inputs (u1..): every step needs one row")
        data["inputs"] = np.stack([per_step[("u", k)][0] for k in range(1, K + 1)])
    if has_x:
        missing = [k for k in range(1, K + 1) if ("x", k) not in per_step]
        if x0 is None or missing:
            raise _fail(source, f"the truth columns need a step-0 row (the initial state) and one row per step; "
                                f"{'step 0' if x0 is None else f'step {missing[0]}'} has none")
        data["x"] = np.stack([x0] + [per_step[("x", k)][0] for k in range(1, K + 1)])
    return check_log(data, sc, source)
