"""C99 sources of a node's filter (``cfdesign export DESIGN_DIR --target c``): the home of the frame every node kind
shares, of the C templates' loader, and of :class:`NodeExport`, the interface of a gain rule's C export.

A rule whose node filter is exported answers :meth:`designer.rule.GainRule.c_export` with its :class:`NodeExport`,
which lives in the rule's package (``rules/<name>/export_c.py``, its C in ``rules/<name>/c/``): the relay rule's
(``relay``, and ``flood``, which builds on it: the node filter of :class:`rules.relay.filter.RelayNode`, one
``cfd_step`` with the relayed measurements that arrived, each node's ball and arrival and falsification moments as
data), the paper rule's (the two-phase consensus node of :class:`filters.consensus_node.ConsensusNode`,
``linearization='fixed'``: ``cfd_predict`` gives the packet the node sends, ``cfd_update`` takes what arrived; the
design's σ, β, τ, ε, U, V_i, δ and the channels' probabilities as data) and the scheduled rule's (the node of
:class:`rules.scheduled.filter.ScheduledNode`, ``cfd_predict``, ``cfd_update``, ``cfd_round``; each exported node's
tables as data, the per-link gains solved online as :func:`designer.joint.solve_gains` solves them).
:func:`studies.api.export` runs the node network over the replayed run, asks the export for each step's replay
record (:meth:`NodeExport.replay_step`) and has it write the files (:meth:`NodeExport.write`).

Into a directory each writes:

* ``cfd_model.c``, ``cfd_model.h`` — the model's ``f``, ``F = ∂f/∂x`` and every sensor's ``h_s``, ``H_s`` through
  CasADi's code generator (dense outputs; no allocation): :func:`model_code`;
* ``cfd_node.h``, ``cfd_node.c`` — the node filter, its documented API (``cfd_init``, the step, ``cfd_estimate``,
  ``cfd_bound``, ...) and the design's data; no mutable static data (a node's struct holds its state and its work
  memory: ``frame/work.h.in`` and each kind's ``cfd_work``), libc and libm only; the node's numbers are
  ``CFD_REAL`` (``double``, or ``float`` when every file is built with ``-DCFD_REAL=float``; the replay driver then
  checks at float's precision);
* ``cfd_test.c``, ``replay.txt`` — a test driver replaying a run through every exported node and comparing each
  step's numbers with what the Python node filter computed on the same run (written in ``replay.txt``: each
  kind's replay text, through :func:`replay_file`).  Each step starts from the Python node's state after the step
  before (re-synchronised), so one step of C is compared with one step of Python from the same input, which two
  correct implementations agree on to rounding even on a chaotic or ill-conditioned recursion; each entry is
  compared on its own scale (``x[i]`` on max(|x[i]|, sqrt(P[i][i])), ``P[i][j]`` on max(|P[i][j]|,
  sqrt(P[i][i] P[j][j]))), a failure names the step, the node, the quantity and both values; and a second
  set of nodes runs as a network from the prior (never re-synchronised, each node taking its neighbours' own C
  packets where the log says they arrived as sent: :func:`arrival_flag`), checked against the Python node network
  at the rounding drift of a perturbed copy of it (:func:`network_tolerances`);
* ``Makefile`` — ``make`` builds the driver and ``libcfd_node.a``; ``make test`` runs the replay and exits 0 when
  every entry agrees within :data:`REPLAY_TOLERANCE` of its scale.

The C is in files shipped as package data, read by :func:`template`: ``frame/`` (in :data:`C_TEMPLATES`) holds what
every node kind shares (the prelude of CasADi's file, the model's function tables, accessors and symmetric
eigen-decomposition, the linear algebra, the replay driver's head, the Makefile), and each exporting rule's package
its node's ``c/cfd_node.h.in``, ``c/cfd_node.c.in`` and ``c/driver_main.c`` (the driver's ``main``).  A
placeholder is ``@NAME@`` (capitals, digits, underscores), which C text does not contain; :func:`template` refuses
a placeholder without a value and a value without a placeholder.

The sources depend on the design only through their data: one generator serves every design of a rule.  No text
of a design directory (a file from elsewhere) reaches them: the design's verdict is stated as a word of
:data:`designer.verdict.VERDICTS` (``unknown`` for any other text), every other number and word comes from the
design's numbers or a fixed vocabulary, and the user's model's names (its name, its states') go through
:func:`c_text`, which no comment or string end, line splice or directive survives.  ``cfd_model.c`` is CasADi's;
every file compiles without a warning under ``-std=c99 -Wall -Wextra -pedantic`` (the Makefile's ``CFLAGS``).
"""
from __future__ import annotations

import copy
import re
from importlib.resources import files
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any, Iterable, Sequence

import casadi as ca
import numpy as np

from .validation import InputError

__all__ = ["NodeExport", "c_text", "template", "C_TEMPLATES", "PLACEHOLDER", "described", "c_array", "model_code",
           "common_code", "work_code", "linalg_code", "PREFIX", "check_prefix", "prefixed", "write_node",
           "replay_file", "REPLAY_TOLERANCE", "C_TEXT_MAX", "perturbed_twin", "replay_tolerances", "state_difference",
           "SENSITIVITY_SAFETY", "SENSITIVITY_TRIALS", "SENSITIVITY_SEED", "REPLAY_TOLERANCE_CAP", "FLOAT_EPSILON",
           "FLOAT_SEED", "arrival_flag", "perturb", "network_tolerances", "NETWORK_TOLERANCE_CAP", "REPLAY_TOLERANCES",
           "DRIFT_SEED", "DRIFT_TRIALS", "network_copy", "drift_tolerances"]

C_TEMPLATES = files(__package__) / "c"  # the frame's C files (frame/); a rule's node kind: its package's c/
_FRAME = C_TEMPLATES / "frame"
PLACEHOLDER = re.compile(r"@([A-Z][A-Z0-9_]*)@")  # a template's placeholder: @NAME@

#: make test: |C - Python| <= this times the entry's own scale, each step from the Python node's state (the frame's
#: driver_head.c says which scale)
REPLAY_TOLERANCE = 1e-12
#: a step whose own rounding sensitivity is larger (see :func:`replay_tolerances`) is checked at this many times it;
#: a step that would need more than REPLAY_TOLERANCE_CAP ends the replay (beyond, no check tells code from rounding)
SENSITIVITY_SAFETY = 100.0
REPLAY_TOLERANCE_CAP = 1e-6
#: a network run (the C nodes exchanging their own packets, never re-synchronised) is checked while its tolerance
#: (:func:`network_tolerances`: the rounding drift of perturbed Python networks) is at most this; beyond, information
NETWORK_TOLERANCE_CAP = 1e-2
REPLAY_TOLERANCES = 4  # the tolerances starting each row of replay.txt (:func:`replay_file`)
SENSITIVITY_TRIALS = 2  # perturbed twins of the node network a step (Kenney and Laub's small-sample estimate)
SENSITIVITY_SEED = 20261205  # their perturbations' stream: an export is the same file bit for bit every time
#: a float node's rounding unit (``-DCFD_REAL=float``): its tolerances (:func:`replay_tolerances`) are those of twins
#: perturbed at it (:meth:`NodeExport.float_twin`), with a stream of their own (the double's tolerances keep their bits)
FLOAT_EPSILON = float(np.finfo(np.float32).eps)
FLOAT_SEED = (SENSITIVITY_SEED, 32)
DRIFT_SEED = (SENSITIVITY_SEED, 1)  # the network run's drifting copies' stream (:func:`network_tolerances`)
DRIFT_TRIALS = 1  # its drifting copies, a double's and a float's (each costs a step of the network at every step)
PREFIX = "cfd"  # the generated sources' names: functions, types and files cfd_..., macros CFD_...
_PREFIX_SHAPE = re.compile(r"[a-z][a-z0-9]{0,15}")
_PREFIX_TAKEN = ("casadi",)  # CasADi's own names in cfd_model.c
C_TEXT_MAX = 120  # characters of a text c_text keeps (longer: cut, ending in "...")
# what c_text keeps: printable ASCII but for the characters of a comment's or string's end or a line splice
# ("*" of "*/" and "/*", the backslash, the double quote) and "?" (the trigraph ??/ is a backslash)
_C_TEXT_KEPT = frozenset(chr(c) for c in range(0x20, 0x7F)) - set('*\\"?')


def c_text(text, limit: int = C_TEXT_MAX) -> str:
    """``text`` (a name from the user's model: its name, its states') as it may stand inside a C comment or string
    literal of the generated sources: printable ASCII only, each other character (a newline, a carriage return,
    NUL, a non-ASCII letter) and each of ``*``, ``\\``, ``"`` and ``?`` replaced by ``_``, so no byte sequence of
    it ends the comment or the string (``*/``, ``"``), splices a line (a backslash, the trigraph ``??/``) or
    starts a line (a preprocessor directive); at most ``limit`` characters (a longer text is cut, ending in
    ``...``)."""
    text = "".join(c if c in _C_TEXT_KEPT else "_" for c in str(text))
    return text if len(text) <= limit else text[:max(limit - 3, 0)] + "..."


def template(path: Traversable, **values: str | int | float) -> str:
    """The C file ``path`` (one of :data:`C_TEMPLATES`) with each placeholder ``@NAME@`` replaced by ``values[NAME]``
    as ``str.format`` writes it (a number as ``str``; a text as it is), in one pass: a value's own text is never
    read for placeholders.  A value is a number, a fixed word or text of the generator's (a model's name only
    through :func:`c_text`).  Raises ``ValueError`` naming a placeholder that has no value or a value that fills no
    placeholder (the template and its filler must agree), ``TypeError`` for a value neither text nor number."""
    text = path.read_text(encoding="utf-8")
    names = set(PLACEHOLDER.findall(text))
    missing, unused = sorted(names - values.keys()), sorted(values.keys() - names)
    if missing:
        raise ValueError(f"C template {path}: no value for placeholder @{missing[0]}@")
    if unused:
        raise ValueError(f"C template {path}: value {unused[0]} fills no placeholder (no @{unused[0]}@)")
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, (str, int, float, np.integer, np.floating)):
            raise TypeError(f"C template {path}: placeholder @{name}@ takes a text or a number, got "
                            f"{type(value).__name__}")
    return PLACEHOLDER.sub(lambda m: format(values[m.group(1)], ""), text)


def described(model, nodes: Sequence[int], verdict) -> dict:
    """What every header states beside the design's numbers (the values of its placeholders ``NODE_LIST``,
    ``VERDICT``, ``MODEL``, ``STATES``): the exported nodes, the design's verdict as a word of
    :data:`designer.verdict.VERDICTS` (else ``unknown``: never a file's text), the model's name and its states'
    names (the order of ``x``) through :func:`c_text`."""
    from .verdict import known_verdict

    return {"NODE_LIST": ", ".join(str(int(i)) for i in nodes), "VERDICT": known_verdict(verdict),
            "MODEL": c_text(model.name), "STATES": c_text(", ".join(map(str, model.state_names)), 4 * C_TEXT_MAX)}


def _functions(model) -> list[ca.Function]:
    """The model's functions as the node evaluates them, with dense outputs laid out row by row (CasADi writes
    column-major: each matrix transposed first)."""
    if model.n_modes:
        raise InputError(f"model {model.name!r} switches between {model.n_modes} modes: the C export takes models "
                         "without switching")
    x, k, u = model.x, model.k, model.u
    f = model.f_expr
    fns = [ca.Function("cfd_f", [x, k, u], [ca.densify(f)]),
           ca.Function("cfd_F", [x, k, u], [ca.densify(ca.jacobian(f, x).T)])]
    for i, s in enumerate(model.sensors):
        h = ca.vec(s.h)
        fns.append(ca.Function(f"cfd_h{i}", [x, k], [ca.densify(h)]))
        fns.append(ca.Function(f"cfd_H{i}", [x, k], [ca.densify(ca.jacobian(h, x).T)]))
    return fns


def _c_double(v: float) -> str:
    """A double as C reads it back exactly (``repr``), NaN and infinities as math.h's constants."""
    if np.isnan(v):
        return "NAN"
    if np.isinf(v):
        return "INFINITY" if v > 0 else "-INFINITY"
    return repr(v)


def c_array(name: str, values, ctype: str = "CFD_REAL") -> str:
    """A ``static const`` C array ``name`` of ``values`` (flattened row by row; one zero when empty): ``CFD_REAL``
    numbers as exact doubles (:func:`_c_double`; a float build rounds them), ``int`` as integers."""
    flat = np.asarray(values).reshape(-1)
    if ctype == "CFD_REAL":
        body = ", ".join(_c_double(float(v)) for v in flat) or "0.0"
    else:
        body = ", ".join(str(int(v)) for v in flat) or "0"
    return f"static const {ctype} {name}[{max(flat.size, 1)}] = {{{body}}};\n"


def model_code(model, out: Path) -> tuple[dict, np.ndarray, str]:
    """Generate ``cfd_model.c``/``.h`` in ``out`` (CasADi's code after the frame's ``model_prelude.c``); returns
    the work sizes of the model's functions, the sensors' dimensions and the C arrays of their layout
    (``cfd_dim``, ``cfd_zoff`` each sensor's first component in the stacked measurement, ``cfd_angle`` its angular
    components)."""
    fns = _functions(model)
    cg = ca.CodeGenerator("cfd_model.c", {"with_header": True})
    for fn in fns:
        cg.add(fn)
    cg.generate(str(out) + "/")
    code = out / "cfd_model.c"
    # CasADi's functions keep its calling convention, whose work and memory arguments a function may not use, and
    # its code generator has no option to mark them: -Wextra's unused-parameter warning is off in that file only
    code.write_text(template(_FRAME / "model_prelude.c") + code.read_text())
    sizes = {name: max(max(getattr(fn, name)() for fn in fns), 1) for name in ("sz_arg", "sz_res", "sz_iw", "sz_w")}
    dims = np.asarray(model.sensor_dims, dtype=int)
    zoff = model.sensor_offsets
    angle = np.zeros(int(dims.sum()), dtype=int)
    for s, sen in enumerate(model.sensors):
        for c in sen.angles:
            angle[zoff[s] + c] = 1
    return sizes, dims, c_array("cfd_dim", dims, "int") + c_array("cfd_zoff", zoff, "int") + c_array("cfd_angle",
                                                                                                      angle, "int")


def common_code(model) -> str:
    """The C every node filter shares (``frame/common.c.in``, the value of a source's ``COMMON``): the model's
    function tables, the accessors, the symmetric eigen-decomposition and the model's calls (their work memory the
    node's: :func:`work_code`)."""
    return template(_FRAME / "common.c.in", HS=", ".join(f"cfd_h{s}" for s in range(model.n_sensors)),
                    HHS=", ".join(f"cfd_H{s}" for s in range(model.n_sensors)))


def work_code(sizes: dict, eig_max: str) -> str:
    """The declaration of ``cfd_model_work`` (``frame/work.h.in``, a header's ``WORK``): the work memory of the
    model's calls (``sizes``: :func:`model_code`'s) and of the eigen-decomposition of matrices up to ``eig_max``
    rows (a constant expression of the kind's header, e.g. ``CFD_NX``), which each node kind's work struct holds, so
    that no node keeps mutable static data."""
    return template(_FRAME / "work.h.in", EIG_MAX=eig_max, **{name.upper(): value for name, value in sizes.items()})


def linalg_code() -> str:
    """The small dense linear algebra of the consensus-family nodes (``frame/linalg.c``, a source's ``LINALG``):
    products, symmetrisation, the finiteness check and Gaussian elimination."""
    return template(_FRAME / "linalg.c")


def write_node(out: Path, header: str, source: str, main: str, replay: str | None) -> list[Path]:
    """Write a node kind's ``cfd_node.h``, ``cfd_node.c``, its replay driver ``cfd_test.c`` (the frame's
    ``driver_head.c``, a blank line, the kind's ``main``), the frame's ``Makefile`` and, given, ``replay.txt``
    beside the model's files (:func:`model_code`) in ``out``; returns every file of the export."""
    driver = template(_FRAME / "driver_head.c", TOL=repr(REPLAY_TOLERANCE), TOL_CAP=repr(REPLAY_TOLERANCE_CAP),
                      NET_CAP=repr(NETWORK_TOLERANCE_CAP), TOLERANCES=REPLAY_TOLERANCES) \
        + "\n" + main
    texts = {"cfd_node.h": header, "cfd_node.c": source, "cfd_test.c": driver,
             "Makefile": template(_FRAME / "Makefile", TOL=repr(REPLAY_TOLERANCE))}
    if replay is not None:
        texts["replay.txt"] = replay
    written = [out / "cfd_model.c", out / "cfd_model.h"]
    for name, text in texts.items():
        (out / name).write_text(text)
        written.append(out / name)
    return written


def arrival_flag(sender: int, received, falsified) -> float:
    """A packet's arrival flag in ``replay.txt``: 0 lost (``sender`` not in ``received``), 1 arrived as it was sent, 2
    arrived falsified (``sender`` in ``falsified``).  The C network of ``make test`` feeds a node its neighbour's own
    C packet where the flag is 1 and the log's falsified packet where it is 2."""
    return 0.0 if sender not in received else 2.0 if sender in falsified else 1.0


def replay_file(steps: int, nodes: int, n_u: int, rows: Iterable[Sequence], tolerances) -> str:
    """The text of ``replay.txt``: ``steps nodes n_u``, then one line per row of numbers (a step's node, in the
    kind's order), each starting with the row's :data:`REPLAY_TOLERANCES` tolerances (``tolerances``, steps x nodes x
    4): the step's from Python's state, a double node's and a float node's (:func:`replay_tolerances` at the double's
    and at float's rounding), then the network run's, a double's and a float's (:func:`network_tolerances`; ``inf``
    where its check has ended); each number as Python's ``repr`` (exact)."""
    tol = np.asarray(tolerances, float).reshape(-1, REPLAY_TOLERANCES)
    lines = [f"{steps} {nodes} {n_u}"] + [" ".join(repr(float(v)) for v in (*t, *vals)) for t, vals in zip(tol, rows)]
    if len(lines) != steps * nodes + 1 or len(tol) != steps * nodes:
        raise ValueError(f"replay_file: {len(lines) - 1} rows and {len(tol)} tolerances for {steps} steps x {nodes} "
                         "nodes")
    return "\n".join(lines) + "\n"


#: The attributes of a node network and of its nodes that hold its configuration whatever their type (the design and
#: its tables are named tuples: containers by type, read-only by use).
CONFIGURATION = ("model", "network", "design", "tables")


def _configuration(net) -> dict:
    """deepcopy's memo sharing what a node network only reads (its model, network, design, tables, rules: every
    attribute of it and of its nodes named in :data:`CONFIGURATION` or that is an object rather than an array, a
    number, a text or a container), so a twin of it copies its state alone (not the design's tables: 7 of the 30-tank
    ring's 29 s of export when they were copied)."""
    plain = (np.ndarray, np.generic, list, tuple, dict, set, int, float, complex, bool, str, bytes, type(None))
    memo = {}
    for owner in (net, *net.nodes):
        for name, value in vars(owner).items():
            if name in CONFIGURATION or not isinstance(value, plain):
                memo[id(value)] = value
    return memo


def network_copy(net):
    """A copy of the node network ``net`` that steps on its own: its state copied, its configuration shared
    (:func:`_configuration`)."""
    return copy.deepcopy(net, _configuration(net))


def perturbed_twin(net, rng: np.random.Generator, eps: float = float(np.finfo(float).eps)):
    """A copy of the node network ``net`` (:func:`network_copy`) whose every node's estimate and covariance are moved
    by about one unit in the last place: each entry times ``1 + ε g`` (``ε`` the rounding unit, the double's machine
    epsilon unless given: :data:`FLOAT_EPSILON` for a float node; ``g`` standard normal; the covariance's
    perturbation symmetric)."""
    return perturb(network_copy(net), rng, eps)


def perturb(net, rng: np.random.Generator, eps: float = float(np.finfo(float).eps)):
    """The node network ``net`` itself, every node's estimate and covariance moved by about one unit in the last
    place as :func:`perturbed_twin` moves its copy's (a network run's rounding at each step:
    :func:`network_tolerances`)."""
    for node in net.nodes:
        x, P = np.asarray(node.x, float), np.asarray(node.P, float)
        G = rng.standard_normal(P.shape)
        node.x = x * (1.0 + eps * rng.standard_normal(x.shape))
        node.P = P * (1.0 + eps * 0.5 * (G + G.T))
    return net


def state_difference(x, P, x_ref, P_ref) -> float:
    """The largest difference of an estimate and covariance from the reference's, each entry on its own scale as
    ``make test`` scales it (``x[i]`` on max(|x[i]|, sqrt(P[i][i])), ``P[i][j]`` on max(|P[i][j]|,
    sqrt(P[i][i] P[j][j])), the reference's values); infinite where a scale is 0 or a number not finite."""
    x, P, x_ref, P_ref = (np.asarray(a, float) for a in (x, P, x_ref, P_ref))
    s = np.sqrt(np.abs(np.diag(P_ref)))
    with np.errstate(divide="ignore", invalid="ignore"):
        dx = np.where(x == x_ref, 0.0, np.abs(x - x_ref) / np.maximum(np.abs(x_ref), s))
        dP = np.where(P == P_ref, 0.0, np.abs(P - P_ref) / np.maximum(np.abs(P_ref), np.outer(s, s)))
    d = np.concatenate([dx.reshape(-1), dP.reshape(-1)])
    return float(np.inf) if not np.all(np.isfinite(d)) else float(d.max(initial=0.0))


def replay_tolerances(net, twins: Sequence, nodes: Sequence[int], floor: float = REPLAY_TOLERANCE) -> np.ndarray:
    """Each exported node's tolerance in ``make test`` at the step just taken by ``net`` and its perturbed twins
    (:func:`perturbed_twin`, made before the step and stepped with it): ``floor`` (:data:`REPLAY_TOLERANCE`), or
    where the step itself moves one-ulp perturbations of its input further, :data:`SENSITIVITY_SAFETY` times the
    largest such movement (:func:`state_difference`).  A double node's tolerance above :data:`REPLAY_TOLERANCE_CAP`
    is a step too ill-conditioned to check: the export's replay stops before it.

    A float node's (twins perturbed at :data:`FLOAT_EPSILON`, ``floor`` the double's scaled to float's rounding) is
    not the double's scaled: where a step drops an eigenvalue below what float resolves (a relay node's
    pseudo-inverse keeps eigenvalues down to 1e-12 of the largest in double, 1e-5 in float), perturbations at
    float's rounding move its output by an amount one-ulp perturbations of a double do not show.

    Each step of ``make test`` starts from Python's state, read exactly, so what the C may differ by is its own
    rounding inside the step, carried to the output as the step's condition carries a perturbation of its input:
    where a step amplifies one-ulp changes of its input to 1e-10 (a radar's angles from a wide prior), no correct
    implementation agrees within 1e-12, and a check at 1e-12 would fail correct code."""
    out = np.full(len(nodes), floor)
    for j, i in enumerate(nodes):
        ref = net.nodes[i]
        moved = max((state_difference(t.nodes[i].x, t.nodes[i].P, ref.x, ref.P) for t in twins), default=0.0)
        out[j] = max(floor, SENSITIVITY_SAFETY * moved)
    return out


def network_tolerances(net, drifting: Sequence, nodes: Sequence[int], previous, floor: float = REPLAY_TOLERANCE
                       ) -> np.ndarray:
    """Each exported node's tolerance in ``make test``'s network run at the step just taken by ``net``: the C nodes
    exchanging their own packets over the log's arrivals from the first step, never re-synchronised, against the
    Python node network.  ``drifting``: copies of ``net`` made at the start and run beside it, each perturbed by
    one unit in the last place before every step (:func:`perturb`), the network run's rounding; the tolerance is
    ``floor``, or :data:`SENSITIVITY_SAFETY` times how far they have drifted (:func:`state_difference`), never
    below ``previous`` (the step before's, None at the first step).  Where it exceeds :data:`NETWORK_TOLERANCE_CAP`
    (a chaotic or ill-conditioned run carries rounding that far) it is ``inf``: the network run is information
    from there on, the per-step check (:func:`replay_tolerances`) still holds."""
    out = np.full(len(nodes), floor) if previous is None else np.array(previous, float)
    for j, i in enumerate(nodes):
        ref = net.nodes[i]
        moved = max((state_difference(t.nodes[i].x, t.nodes[i].P, ref.x, ref.P) for t in drifting), default=0.0)
        out[j] = max(out[j], SENSITIVITY_SAFETY * moved)
    return np.where(out <= NETWORK_TOLERANCE_CAP, out, np.inf)


def drift_tolerances(net, exporter: "NodeExport", z: np.ndarray, attacks, u: np.ndarray, nodes: Sequence[int]
                     ) -> np.ndarray:
    """The network run's tolerances (:func:`network_tolerances`) at every step of the replayed run, a double node's
    and a float node's: (steps, nodes, 2).  ``net`` is the node network at the start, stepped here (a copy:
    :func:`network_copy`), beside its drifting copies (:data:`DRIFT_TRIALS` of each, perturbed before every step
    from :data:`DRIFT_SEED`'s stream); ``z`` (steps, n_z) the run's measurements, ``attacks`` its
    :class:`filters.consensus_batch.EdgeAttacks` (one run; None: none), ``u`` (steps, n_u) its inputs.  It ends where
    ``net`` stops (diverged), as the replay does.  Independent of the per-step twins (:func:`replay_tolerances`):
    the export computes it in a process of its own beside them (:class:`studies.runner.Background`), the same numbers."""
    import warnings

    rng = np.random.default_rng(DRIFT_SEED)
    drifting = [perturbed_twin(net, rng, 0.0) for _ in range(DRIFT_TRIALS)]
    drifting_float = [exporter.float_twin(net, rng) for _ in range(DRIFT_TRIALS)]
    to_float = FLOAT_EPSILON / np.finfo(float).eps
    tol = tol_float = None
    out = []
    for k in range(z.shape[0]):
        e = (None, None, None) if attacks is None else (attacks.dos[0, k], attacks.fdi[0, k], attacks.xi[0, k])
        for twin in drifting:
            perturb(twin, rng)
        for twin in drifting_float:
            perturb(twin, rng, FLOAT_EPSILON)
        with warnings.catch_warnings(), np.errstate(all="ignore"):  # the replay warns of the run's own troubles
            warnings.simplefilter("ignore")
            net.step(z[k], *e, u=u[k])
            if getattr(net, "stopped", False):
                break
            for twin in drifting + drifting_float:
                twin.step(z[k], *e, u=u[k])
        tol = network_tolerances(net, drifting, nodes, tol)
        floor = tol * to_float  # a float node's at least the double's, scaled to its rounding
        tol_float = network_tolerances(net, drifting_float, nodes,
                                       floor if tol_float is None else np.maximum(floor, tol_float))
        out.append(np.stack([tol, tol_float], -1))
    return np.reshape(out, (len(out), len(nodes), 2))


def check_prefix(prefix: str) -> str:
    """``prefix`` as :func:`prefixed` takes it: a lower-case C identifier of 1-16 letters and digits, starting with a
    letter, not one of CasADi's (:class:`InputError` naming it otherwise)."""
    if not isinstance(prefix, str) or not _PREFIX_SHAPE.fullmatch(prefix) or prefix in _PREFIX_TAKEN:
        raise InputError(f"prefix must be 1 to 16 lower-case letters and digits starting with a letter (the C names "
                         f"become PREFIX_..., the macros PREFIX_... in capitals), not {', '.join(_PREFIX_TAKEN)}; got "
                         f"{prefix!r}")
    return prefix


def prefixed(files: Sequence[Path], prefix: str) -> list[Path]:
    """The export's ``files`` renamed to ``prefix`` (checked: :func:`check_prefix`): every name ``cfd_...`` of their
    text (functions, types, the model's functions, the library ``libcfd_node.a``, the files themselves) becomes
    ``prefix_...`` and every ``CFD_...`` (macros, the header guard, ``CFD_REAL``) ``PREFIX_...``, so that exports of
    two designs link into one program.  CasADi's own names (``casadi_...``) stay.  Returns the files as renamed."""
    prefix = check_prefix(prefix)
    if prefix == PREFIX:
        return list(files)
    lower = re.compile(r"\b(lib)?" + PREFIX + "_")
    upper = re.compile(r"\b" + PREFIX.upper() + "_")
    out = []
    for path in files:
        path = Path(path)
        text = path.read_text()
        text = upper.sub(prefix.upper() + "_", lower.sub(lambda m: (m.group(1) or "") + prefix + "_", text))
        target = path.with_name(lower.sub(lambda m: (m.group(1) or "") + prefix + "_", path.name))
        target.write_text(text)
        if target != path:
            path.unlink()
        out.append(target)
    return out


class NodeExport:
    """A gain rule's C export of its node filter (:meth:`designer.rule.GainRule.c_export`): what
    :func:`studies.api.export` asks of it, in order.

    :meth:`check` refuses a design the export cannot write; then, at each step of the replayed run, after the node
    network's step (:func:`filters.node.node_network`), :meth:`replay_step` gives the step's replay record (the
    replay stops before a step too ill-conditioned to check: :func:`replay_tolerances`); :meth:`write` writes the
    sources, the Makefile, the driver and ``replay.txt`` from those records. A subclass overrides
    :meth:`replay_step` and :meth:`write`.
    """

    def check(self, design) -> None:
        """Refuse (:class:`InputError` naming what) a design of the rule that this export cannot write; the base
        class takes every design."""

    def replay_numbers(self, model, network, options, regions, nodes: Sequence[int]) -> tuple[int, int]:
        """At most how many numbers the replay records of the exported ``nodes`` hold a step, and how many numbers
        the sources' data add for them beyond the model's and the offline tables (which the estimate counts
        itself), from the model, the network, the design's effective options and the regions its nodes carry
        (None: the whole state) alone: the memory estimate's (:func:`studies.memory.export_need`), made before the
        design is read.  The base class: each node a packet from every node, each an estimate and its covariance,
        and two more (its state and prediction) besides its measurement and its row's tolerances, the most any node
        kind records; no data."""
        n, n_x = network.n_nodes, model.n_x
        return len(nodes) * ((n + 2) * (n_x * n_x + n_x) + model.n_z + REPLAY_TOLERANCES), 0

    def float_twin(self, net, rng: np.random.Generator):
        """A twin of the node network ``net`` stepping as a float node would (``-DCFD_REAL=float``), before the step:
        its float tolerance in ``make test`` is how far the step moves it (:func:`replay_tolerances`).  The base
        class: :func:`perturbed_twin` at float's rounding, :data:`FLOAT_EPSILON`; a kind whose float node decides
        differently (a rank cut at float's resolution) sets its twin's nodes to decide so too."""
        return perturbed_twin(net, rng, FLOAT_EPSILON)

    def replay_step(self, net, k: int, u: np.ndarray, z: Sequence[np.ndarray], nodes: Sequence[int]) -> Any:
        """The replay record of step ``k`` (0-based) from the node network ``net`` after its step: ``u`` the step's
        inputs, ``z`` each exported node's own measurement (in ``nodes`` order)."""
        raise NotImplementedError(f"{type(self).__name__}.replay_step")

    def write(self, model, network, design, net, steps: list, out: Path, *, nodes: Sequence[int], tolerances,
              verdict=None) -> list[Path]:
        """Write the export of ``design`` for the nodes ``nodes`` into ``out`` (the node network ``net`` after the
        replayed run, ``steps`` the records of :meth:`replay_step`, ``tolerances`` each step's and node's
        tolerances in ``make test``, steps x nodes x 2 (a double node's, a float node's: :func:`replay_tolerances`),
        written through :func:`replay_file`; ``verdict``: the design's, stated as a word of
        :data:`designer.verdict.VERDICTS`); returns the files written."""
        raise NotImplementedError(f"{type(self).__name__}.write")
