"""C99 sources of a node's filter: ``cfdesign export DESIGN_DIR --target c``.

Three node filters are exported: gains the node computes online (run time ``local``) or looks up in tables designed
offline (``scheduled``):

* a design whose gain rule relays (``relay``, ``flood``): :func:`write_relay_c`, the node filter of
  :class:`filters.relay.RelayNode` (one ``cfd_step`` with the relayed measurements that arrived: the relay rule's
  update, :func:`designer.relay.relay_update`, its pseudo-inverse by a symmetric eigen-decomposition, and the bound's
  recursion, the node's expected covariance), each node's ball and arrival and falsification moments as data;
* a ``paper`` design (the consensus EKF of the seed paper, ``linearization='fixed'``): :func:`write_consensus_c`, the
  two-phase node of :class:`filters.consensus_node.ConsensusNode` (``cfd_predict`` gives the packet the node sends,
  its prediction and bound (26) while (28) holds; ``cfd_update`` takes its measurement, the estimates that arrived
  and every neighbour's bound: the gate, the gain (30) with ``C = τ Φ⁻`` and the bound (27) while (29) holds, the
  fallback after), the design's σ, β, τ, ε, U, V_i, δ and the channels' probabilities as data;
* a ``scheduled`` design: :func:`write_scheduled_c`, the node of :class:`filters.scheduled.ScheduledNode`
  (``cfd_predict`` with its measurement, ``cfd_update`` the first round, ``cfd_round`` rounds 2..L), each exported
  node's tables as data (the whitened factors of its links per step and round, the stationary ones, the bank's and
  its points, the certificate per step), looked up by the step and the node's own prediction; the per-link gains
  (:func:`designer.scheduled.link_gains`) solved online as :func:`designer.mse.solve_gains` solves them.

Into a directory each writes:

* ``cfd_model.c``, ``cfd_model.h`` — the model's ``f``, ``F = ∂f/∂x`` and every sensor's ``h_s``, ``H_s`` through
  CasADi's code generator (dense outputs; no allocation);
* ``cfd_node.h``, ``cfd_node.c`` — the node filter, its documented API (``cfd_init``, the step, ``cfd_estimate``,
  ``cfd_bound``, ...) and the design's data; static memory only, libc and libm only;
* ``cfd_test.c``, ``replay.txt`` — a test driver replaying a run through every exported node and comparing each
  step's numbers with what the Python node filter computed on the same run (written in ``replay.txt``:
  :func:`replay_text`, :func:`consensus_replay_text`);
* ``Makefile`` — ``make`` builds the driver and ``libcfd_node.a``; ``make test`` runs the replay and exits 0 when
  every number agrees within 1e-10 of the largest magnitude of its vector or matrix.

The sources depend on the design only through their data: one generator serves every design of a rule.  No text
of a design directory (a file from elsewhere) reaches them: the design's verdict is stated as a word of
:data:`designer.verdict.VERDICTS` (``unknown`` for any other text), every other number and word comes from the
design's numbers or a fixed vocabulary, and the user's model's names (its name, its states') go through
:func:`c_text`, which no comment or string end, line splice or directive survives.  ``cfd_model.c`` is CasADi's;
every file compiles without a warning under ``-std=c99 -Wall -Wextra -pedantic`` (the Makefile's ``CFLAGS``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import casadi as ca
import numpy as np

from .validation import InputError

__all__ = ["c_text", "write_relay_c", "replay_text", "write_consensus_c", "consensus_replay_text", "write_scheduled_c",
           "scheduled_replay_text", "REPLAY_TOLERANCE"]

REPLAY_TOLERANCE = 1e-10  # make test: |C - Python| <= this times the largest magnitude of the vector or matrix
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


def _described(model, nodes: Sequence[int], verdict) -> dict:
    """What every header states beside the design's numbers: the exported nodes, the design's verdict as a word
    of :data:`designer.verdict.VERDICTS` (else ``unknown``: never a file's text), the model's name and its
    states' names (the order of ``x``) through :func:`c_text`."""
    from .verdict import known_verdict

    return {"node_list": ", ".join(str(int(i)) for i in nodes), "verdict": known_verdict(verdict),
            "model": c_text(model.name), "states": c_text(", ".join(map(str, model.state_names)), 4 * C_TEXT_MAX)}


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


def _array(name: str, values, ctype: str = "double") -> str:
    flat = np.asarray(values).reshape(-1)
    if ctype == "double":
        body = ", ".join(_c_double(float(v)) for v in flat) or "0.0"
    else:
        body = ", ".join(str(int(v)) for v in flat) or "0"
    return f"static const {ctype} {name}[{max(flat.size, 1)}] = {{{body}}};\n"


def write_relay_c(model, network, design, routes, moments: Sequence, out: Path, *, nodes: Sequence[int],
                  replay: str | None = None, verdict: str = "unknown") -> list[Path]:
    """Write the C sources of the node filter of the relay design ``design`` (``routes``, ``moments``: its
    :func:`designer.relay.relay_routes` and :func:`designer.relay.relay_moments`) for the nodes ``nodes`` into
    ``out``; ``replay``: the text of ``replay.txt`` (see :func:`replay_text`); ``verdict``: the design's
    (:mod:`designer.verdict`), stated in the header.  Returns the files written."""
    from .scheduled import sqrtm_psd

    rule = design.rule
    if not rule.relays:
        raise InputError(f"mode must be a relaying gain rule for the relay node's C export, got {rule.name!r}")
    out = Path(out)
    n, nz_max = model.n_x, max(model.sensor_dims)
    signal = design.fdi_signal
    M = np.zeros((n, n)) if signal is None else signal.moment(n)
    mu = np.zeros(n) if signal is None else signal.mean(n)
    if not np.any(network.fdi_prob > 0):
        M, mu = np.zeros((n, n)), np.zeros(n)
    G = routes.hops + 1
    sizes, dims, layout = _model_code(model, out)
    rinv = [sqrtm_psd(model.measurement_cov(s), inverse=True) for s in range(model.n_sensors)]
    rinv_start = np.concatenate([[0], np.cumsum(dims ** 2)])
    nodes = [int(i) for i in nodes]
    ball_start, ball, row_start, row_group, p, rr_start, A, F1, F2 = [0], [], [0], [], [], [0], [], [], []
    for i in nodes:
        mom = moments[i]
        ball += mom.sensors.tolist()
        ball_start.append(len(ball))
        r = mom.rows.size
        row_group += mom.groups.argmax(-1).tolist()
        p += mom.p.tolist()
        row_start.append(row_start[-1] + r)
        A += mom.A.reshape(-1).tolist()
        F1 += (mom.F1 if np.any(M) else np.zeros((r, r))).reshape(-1).tolist()
        F2 += (mom.F2 if np.any(mu) else np.zeros((r, r))).reshape(-1).tolist()
        rr_start.append(len(A))
    r_max = max(row_start[j + 1] - row_start[j] for j in range(len(nodes)))
    ball_max = max(ball_start[j + 1] - ball_start[j] for j in range(len(nodes)))
    gn = G * n
    header = _HEADER.format(n=n, nu=model.n_u, nz=int(dims.sum()), sensors=model.n_sensors, nodes=len(nodes),
                            ball_max=ball_max, rows_max=r_max, rounds=int(routes.hops), mode=rule.name,
                            received_max=r_max - 1 if r_max > 1 else 1, **_described(model, nodes, verdict))
    data = "".join([
        _array("cfd_node_id", nodes, "int"), _array("cfd_ball_start", ball_start, "int"),
        _array("cfd_ball_sensor", ball, "int"), _array("cfd_row_start", row_start, "int"),
        _array("cfd_row_group", row_group, "int"), _array("cfd_p", p), _array("cfd_rr_start", rr_start, "int"),
        _array("cfd_A", A), _array("cfd_F1", F1), _array("cfd_F2", F2),
        layout, _array("cfd_rinv_start", rinv_start, "int"),
        _array("cfd_rinv", np.concatenate([r.reshape(-1) for r in rinv])),
        _array("cfd_Q", model.process_cov), _array("cfd_M", M), _array("cfd_mu", mu),
        _array("cfd_x0", model.prior.mean), _array("cfd_P0", model.prior.cov),
    ])
    source = _SOURCE.format(common=_common(model, sizes), data=data, G=G, gn=gn, nzmax=nz_max,
                            use_f1=int(bool(np.any(M))), use_f2=int(bool(np.any(mu))))
    return _write(out, header, source, _DRIVER_HEAD + _DRIVER, replay)


def _model_code(model, out: Path) -> tuple[dict, np.ndarray, str]:
    """Generate ``cfd_model.c``/``.h`` in ``out``; returns the work sizes of the model's functions, the sensors'
    dimensions and the C arrays of their layout (``cfd_dim``, ``cfd_zoff`` each sensor's first component in the
    stacked measurement, ``cfd_angle`` its angular components)."""
    fns = _functions(model)
    cg = ca.CodeGenerator("cfd_model.c", {"with_header": True})
    for fn in fns:
        cg.add(fn)
    cg.generate(str(out) + "/")
    code = out / "cfd_model.c"
    code.write_text(_MODEL_PRELUDE + code.read_text())
    sizes = {name: max(max(getattr(fn, name)() for fn in fns), 1) for name in ("sz_arg", "sz_res", "sz_iw", "sz_w")}
    dims = np.asarray(model.sensor_dims, dtype=int)
    zoff = np.concatenate([[0], np.cumsum(dims)])
    angle = np.zeros(int(dims.sum()), dtype=int)
    for s, sen in enumerate(model.sensors):
        for c in sen.angles:
            angle[zoff[s] + c] = 1
    return sizes, dims, _array("cfd_dim", dims, "int") + _array("cfd_zoff", zoff, "int") + _array("cfd_angle", angle,
                                                                                                   "int")


# CasADi's functions keep its calling convention, whose work and memory arguments a function may not use, and its
# code generator has no option to mark them: -Wextra's unused-parameter warning is off in that file only
_MODEL_PRELUDE = """/* cfd_model.c (cfdesign export): the model's functions, by CasADi's code generator.  They keep
 * CasADi's calling convention (arg, res, iw, w, mem), whose work and memory arguments a function may not use,
 * and the generator has no option to mark them: GCC's and Clang's warning about unused parameters is off in
 * this file only (every other warning of -std=c99 -Wall -Wextra -pedantic stays on). */
#if defined(__GNUC__)
#pragma GCC diagnostic ignored "-Wunused-parameter"
#endif
"""


def _common(model, sizes: dict) -> str:
    """The C both node filters share: the model's function tables and work arrays, the accessors, the symmetric
    eigen-decomposition and the model's calls."""
    text = _COMMON.replace("@HS@", ", ".join(f"cfd_h{s}" for s in range(model.n_sensors)))
    text = text.replace("@HHS@", ", ".join(f"cfd_H{s}" for s in range(model.n_sensors)))
    for name, value in sizes.items():
        text = text.replace(f"@{name}@", str(value))
    return text


def _write(out: Path, header: str, source: str, driver: str, replay: str | None) -> list[Path]:
    files = {"cfd_node.h": header, "cfd_node.c": source, "cfd_test.c": driver, "Makefile": _MAKEFILE}
    if replay is not None:
        files["replay.txt"] = replay
    written = [out / "cfd_model.c", out / "cfd_model.h"]
    for name, text in files.items():
        (out / name).write_text(text)
        written.append(out / name)
    return written


def replay_text(nodes: Sequence[int], balls: Sequence[Sequence[int]], dims: Sequence[int], steps: list,
                n_u: int) -> str:
    """``replay.txt``: ``steps nodes n_u``, then per step and node (in ``nodes`` order) the node's measurement,
    one arrived flag per sensor of its ball after its own, the received measurements (zeros where not arrived), the
    step's inputs, the Python node filter's estimate and bound (row by row); numbers as Python's ``repr`` (exact).
    ``steps``: per step, ``(u, [(z_own, received {sensor: value}, x, P) per node])``."""
    lines = [f"{len(steps)} {len(nodes)} {n_u}"]
    for u, per_node in steps:
        for j, (own, got, x, P) in enumerate(per_node):
            vals = list(np.asarray(own, float))
            flags, rec = [], []
            for s in balls[j][1:]:
                v = got.get(int(s))
                flags.append(0 if v is None else 1)
                rec += [0.0] * dims[s] if v is None else list(np.asarray(v, float))
            vals += flags + rec + list(np.asarray(u, float).reshape(-1)) + list(np.asarray(x).reshape(-1)) \
                + list(np.asarray(P).reshape(-1))
            lines.append(" ".join(repr(float(v)) for v in vals))
    return "\n".join(lines) + "\n"


_HEADER = """/* cfd_node.h: the node filter of a cfdesign design (gain rule {mode}, {rounds} relay rounds), in C99.
 *
 * Generated by cfdesign export; the design's data are in cfd_node.c, the model's functions in cfd_model.c.
 * The design's verdict: {verdict} (a certified bound is finite, steady and informative; see its report).
 * The model: {model}; its states, in the order of x: {states}.
 * Nodes exported: {node_list} (node k of this file is cfd_node_id[k] of the network; cfd_init takes the
 * network's number).  Static memory only; link with -lm.
 *
 * Each step a node predicts with its own Jacobian, then fuses its own measurement and the measurements of its
 * ball that were relayed to it and arrived, with the relay rule's gain computed online from its design's arrival
 * and falsification moments; its bound is its expected covariance (the linearisation remainders not in it).
 */
#ifndef CFD_NODE_H
#define CFD_NODE_H

#define CFD_NX {n}            /* states */
#define CFD_NU {nu}            /* known inputs per step */
#define CFD_NZ {nz}            /* the sensors' stacked measurement components */
#define CFD_SENSORS {sensors}       /* sensors (= nodes of the network) */
#define CFD_NODES {nodes}         /* nodes exported */
#define CFD_BALL_MAX {ball_max}      /* most sensors in a node's ball (its own included) */
#define CFD_ROWS_MAX {rows_max}      /* most measurement rows a node fuses */

typedef struct {{
    int node;                  /* the network's node number */
    int slot;                  /* its place among the exported nodes */
    long k;                    /* steps taken: the next step measures the state at time k + 1 */
    double x[CFD_NX];          /* the estimate */
    double P[CFD_NX * CFD_NX]; /* its bound (expected covariance), row by row */
}} cfd_node;

/* Start node `node` at the prior (returns 0, or -1 for a node not exported). */
int cfd_init(cfd_node *s, int node);

/* One step.  z: the node's own measurement (its sensor's components).  arrived: one flag per sensor of its ball
 * after its own (cfd_ball order), 1 when that sensor's relayed measurement reached it this step.  received: those
 * measurements stacked in ball order, each sensor's components (any values where not arrived).  u: the step's
 * CFD_NU known inputs (NULL when CFD_NU is 0).  Returns 0, or a negative code (-2: the update broke down, the
 * state is left unchanged). */
int cfd_step(cfd_node *s, const double *z, const unsigned char *arrived, const double *received, const double *u);

/* The estimate (CFD_NX) and its bound (CFD_NX x CFD_NX, row by row). */
const double *cfd_estimate(const cfd_node *s);
const double *cfd_bound(const cfd_node *s);

/* The sensors of node `node`'s ball, its own first (returns their number, or -1; *sensors points at them). */
int cfd_ball(int node, const int **sensors);

/* The network's number of the j-th exported node (-1 beyond CFD_NODES); a sensor's measurement components. */
int cfd_exported_node(int j);
int cfd_sensor_dim(int sensor);

#endif
"""

_SOURCE = r"""/* cfd_node.c: the relay rule's node filter (see cfd_node.h), generated by cfdesign export. */
#include <float.h>
#include <math.h>
#include <string.h>

#include "cfd_model.h"
#include "cfd_node.h"

#define G_ {G}
#define GN {gn}
#define NZMAX {nzmax}
#define USE_F1 {use_f1}
#define USE_F2 {use_f2}
#define RTOL 1e-12
#define PI_ 3.14159265358979323846
#define EIG_MAX GN

{data}
{common}
/* the step's work (static: one node steps at a time) */
static double xp_[CFD_NX], F_[CFD_NX * CFD_NX], Pp_[CFD_NX * CFD_NX], T_[CFD_NX * CFD_NX];
static double Hw_[CFD_ROWS_MAX * CFD_NX], res0_[CFD_ROWS_MAX], hv_[NZMAX], Hv_[NZMAX * CFD_NX];
static double S_[CFD_ROWS_MAX * CFD_ROWS_MAX], HP_[CFD_ROWS_MAX * CFD_NX], HM_[CFD_ROWS_MAX * CFD_NX];
static double hmu_[CFD_ROWS_MAX], U_[CFD_ROWS_MAX * GN];
static double Sg_[CFD_NX * GN], Q_[GN * GN], V_[GN * GN], lam_[GN], Qp_[GN * GN], C_[CFD_NX * GN], ilam_[GN];
static double W_[CFD_NX * GN], y_[GN], Pn_[CFD_NX * CFD_NX];
static int act_[2 * GN];  /* the active columns of Hg, then the kept eigenvalues */


int cfd_init(cfd_node *s, int node) {{
    int slot = slot_of(node);
    if (slot < 0) return -1;
    s->node = node;
    s->slot = slot;
    s->k = 0;
    memcpy(s->x, cfd_x0, sizeof s->x);
    memcpy(s->P, cfd_P0, sizeof s->P);
    return 0;
}}



int cfd_ball(int node, const int **sensors) {{
    int slot = slot_of(node);
    if (slot < 0) return -1;
    *sensors = cfd_ball_sensor + cfd_ball_start[slot];
    return cfd_ball_start[slot + 1] - cfd_ball_start[slot];
}}

int cfd_step(cfd_node *s, const double *z, const unsigned char *arrived, const double *received, const double *u) {{
    const int n = CFD_NX, slot = s->slot;
    const int b0 = cfd_ball_start[slot], nb = cfd_ball_start[slot + 1] - b0;
    const int r = cfd_row_start[slot + 1] - cfd_row_start[slot], r0 = cfd_row_start[slot], rr0 = cfd_rr_start[slot];
    const double kk = (double)s->k, k1 = (double)(s->k + 1);
    int i, j, a, b, g, c, row, na, nk, off;
    double lmax;
    /* prediction with the node's own Jacobian */
    if (call(cfd_f, s->x, kk, u, xp_) || call(cfd_F, s->x, kk, u, F_)) return -2;
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j) {{
            double t = 0.0;
            for (a = 0; a < n; ++a) t += F_[i * n + a] * s->P[a * n + j];
            T_[i * n + j] = t;
        }}
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j) {{
            double t = 0.0;
            for (a = 0; a < n; ++a) t += T_[i * n + a] * F_[j * n + a];
            Pp_[i * n + j] = t + cfd_Q[i * n + j];
        }}
    for (i = 0; i < n; ++i)
        for (j = 0; j < i; ++j) Pp_[i * n + j] = Pp_[j * n + i] = 0.5 * (Pp_[i * n + j] + Pp_[j * n + i]);
    /* the ball's rows at the node's own prediction: whitened Jacobian rows and residuals (0 where not arrived) */
    row = 0;
    off = 0;
    for (b = 0; b < nb; ++b) {{
        const int sen = cfd_ball_sensor[b0 + b], m = cfd_dim[sen];
        const double *Ri = cfd_rinv + cfd_rinv_start[sen];
        const double *v = (b == 0) ? z : received + off;
        const int got = (b == 0) || arrived[b - 1];
        double rv[NZMAX];
        if (call(cfd_h_fun[sen], xp_, k1, 0, hv_) || call(cfd_H_fun[sen], xp_, k1, 0, Hv_)) return -2;
        for (c = 0; c < m; ++c) {{
            rv[c] = got ? v[c] - hv_[c] : 0.0;
            if (got && cfd_angle[cfd_zoff[sen] + c] && fabs(rv[c]) > PI_) {{
                double t = fmod(PI_ - rv[c], 2.0 * PI_);
                if (t < 0.0) t += 2.0 * PI_;
                rv[c] = PI_ - t;
            }}
        }}
        for (c = 0; c < m; ++c) {{
            double t = 0.0;
            for (a = 0; a < m; ++a) t += Ri[c * m + a] * rv[a];
            res0_[row + c] = got ? t : 0.0;
            for (j = 0; j < n; ++j) {{
                double h = 0.0;
                for (a = 0; a < m; ++a) h += Ri[c * m + a] * Hv_[a * n + j];
                Hw_[(row + c) * n + j] = h;
            }}
        }}
        row += m;
        if (b > 0) off += m;
    }}
    /* S = diag(p) + F1 o (Hw M Hw^T) + F2 o (Hw mu mu^T Hw^T) + A o (Hw P- Hw^T) */
    for (a = 0; a < r; ++a) {{
        double hm = 0.0;
        for (j = 0; j < n; ++j) {{
            double t = 0.0, u = 0.0;
            for (i = 0; i < n; ++i) {{
                t += Hw_[a * n + i] * Pp_[i * n + j];
                u += Hw_[a * n + i] * cfd_M[i * n + j];
            }}
            HP_[a * n + j] = t;
            HM_[a * n + j] = u;
            hm += Hw_[a * n + j] * cfd_mu[j];
        }}
        hmu_[a] = hm;
    }}
    for (a = 0; a < r; ++a)
        for (b = 0; b < r; ++b) {{
            double t = 0.0, sab;
            for (j = 0; j < n; ++j) t += HP_[a * n + j] * Hw_[b * n + j];
            sab = (a == b ? cfd_p[r0 + a] : 0.0) + cfd_A[rr0 + a * r + b] * t;
            if (USE_F1) {{
                double hm = 0.0;
                for (j = 0; j < n; ++j) hm += HM_[a * n + j] * Hw_[b * n + j];
                sab += cfd_F1[rr0 + a * r + b] * hm;
            }}
            if (USE_F2) sab += cfd_F2[rr0 + a * r + b] * hmu_[a] * hmu_[b];
            S_[a * r + b] = sab;
        }}
    /* Sg = sum_a p_a Hw_a^T Hg_a (n x G n); Q = Hg^T S Hg (G n x G n) through U = S Hg (r x G n) */
    memset(Sg_, 0, sizeof Sg_);
    memset(Q_, 0, sizeof Q_);
    memset(U_, 0, sizeof U_);
    for (a = 0; a < r; ++a) {{
        g = cfd_row_group[r0 + a];
        for (i = 0; i < n; ++i)
            for (j = 0; j < n; ++j) Sg_[i * GN + g * n + j] += cfd_p[r0 + a] * Hw_[a * n + i] * Hw_[a * n + j];
    }}
    for (a = 0; a < r; ++a)
        for (b = 0; b < r; ++b) {{
            const int gb = cfd_row_group[r0 + b];
            const double sab = S_[a * r + b];
            for (j = 0; j < n; ++j) U_[a * GN + gb * n + j] += sab * Hw_[b * n + j];
        }}
    for (a = 0; a < r; ++a) {{
        const int ga = cfd_row_group[r0 + a];
        for (i = 0; i < n; ++i) {{
            const double h = Hw_[a * n + i];
            if (h == 0.0) continue;
            for (j = 0; j < GN; ++j) Q_[(ga * n + i) * GN + j] += h * U_[a * GN + j];
        }}
    }}
    /* the columns of Hg that are zero throughout are left out of the pseudo-inverse */
    na = 0;
    for (g = 0; g < G_; ++g)
        for (j = 0; j < n; ++j) {{
            int seen = 0;
            for (a = 0; a < r; ++a)
                if (cfd_row_group[r0 + a] == g && Hw_[a * n + j] != 0.0) seen = 1;
            if (seen) act_[na++] = g * n + j;
        }}
    for (i = 0; i < na; ++i)
        for (j = 0; j < na; ++j)
            V_[i * na + j] = 0.5 * (Q_[act_[i] * GN + act_[j]] + Q_[act_[j] * GN + act_[i]]);
    memcpy(Qp_, V_, sizeof(double) * (size_t)(na * na));
    if (eigsym(na, Qp_, lam_, V_)) return -2;
    lmax = 0.0;
    for (i = 0; i < na; ++i)
        if (lam_[i] > lmax) lmax = lam_[i];
    /* Q+ = V diag(1 / lam) V^T over the eigenvalues above RTOL of the largest: the kept ones' reciprocals first,
     * the upper triangle computed and mirrored (Q+ is symmetric) */
    nk = 0;
    for (a = 0; a < na; ++a)
        if (lam_[a] > RTOL * lmax) {{
            act_[GN + nk] = a;
            ilam_[nk++] = 1.0 / lam_[a];
        }}
    for (i = 0; i < na; ++i)
        for (j = i; j < na; ++j) {{
            double t = 0.0;
            for (c = 0; c < nk; ++c) {{
                a = act_[GN + c];
                t += V_[i * na + a] * V_[j * na + a] * ilam_[c];
            }}
            Qp_[i * na + j] = Qp_[j * na + i] = t;
        }}
    /* C = P- Sg[:, act], W[:, act] = C Q+, P+ = P- - W[:, act] C^T */
    for (i = 0; i < n; ++i)
        for (j = 0; j < na; ++j) {{
            double t = 0.0;
            for (a = 0; a < n; ++a) t += Pp_[i * n + a] * Sg_[a * GN + act_[j]];
            C_[i * GN + j] = t;
        }}
    for (i = 0; i < n; ++i)
        for (j = 0; j < na; ++j) {{
            double t = 0.0;
            for (a = 0; a < na; ++a) t += C_[i * GN + a] * Qp_[a * na + j];
            W_[i * GN + j] = t;
        }}
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j) {{
            double t = 0.0;
            for (a = 0; a < na; ++a) t += W_[i * GN + a] * C_[j * GN + a];
            Pn_[i * n + j] = Pp_[i * n + j] - t;
        }}
    /* y = sum_a Hg_a res_a over the arrived rows; x+ = x- + W y */
    memset(y_, 0, sizeof y_);
    for (a = 0; a < r; ++a) {{
        g = cfd_row_group[r0 + a];
        for (j = 0; j < n; ++j) y_[g * n + j] += Hw_[a * n + j] * res0_[a];
    }}
    for (i = 0; i < n; ++i) {{
        double t = xp_[i];
        for (a = 0; a < na; ++a) t += W_[i * GN + a] * y_[act_[a]];
        if (!(fabs(t) < 1e300)) return -2;
        s->x[i] = t;
    }}
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j) s->P[i * n + j] = 0.5 * (Pn_[i * n + j] + Pn_[j * n + i]);
    s->k += 1;
    return 0;
}}
"""

_DRIVER_HEAD = r"""/* cfd_test.c: replay a run through every exported node and compare with the Python node filter. */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>

#include "cfd_node.h"

#define TOL 1e-10

static int read_numbers(FILE *fh, double *v, int count) {
    int i;
    for (i = 0; i < count; ++i)
        if (fscanf(fh, "%lf", &v[i]) != 1) return -1;
    return 0;
}

/* the largest difference of got from want relative to want's largest magnitude; *bad counts those above TOL */
static double compare(const double *got, const double *want, int count, int *bad) {
    double m = 0.0, worst = 0.0;
    int i;
    for (i = 0; i < count; ++i)
        if (fabs(want[i]) > m) m = fabs(want[i]);
    for (i = 0; i < count; ++i) {
        double d = fabs(got[i] - want[i]) / (m > 0 ? m : 1.0);
        if (d > worst) worst = d;
        if (!(d <= TOL)) *bad += 1;
    }
    return worst;
}

/* an estimate and its covariance against the Python node filter's: the worst difference so far, the count above */
static void check(const double *x, const double *P, const double *x_want, const double *P_want, double *worst,
                  int *bad) {
    double t = compare(x, x_want, CFD_NX, bad);
    if (t > *worst) *worst = t;
    t = compare(P, P_want, CFD_NX * CFD_NX, bad);
    if (t > *worst) *worst = t;
}

static int finish(FILE *fh, int steps, double worst, int bad) {
    fclose(fh);
    printf("%d steps x %d nodes: largest difference from the Python node filter %.3g (relative), %d above %g\n",
           steps, CFD_NODES, worst, bad, TOL);
    return bad ? 1 : 0;
}

/* a replay that ends before its header's steps and nodes: exit 2 */
static int short_replay(const char *name, int k, int node) {
    fprintf(stderr, "%s: short at step %d, node %d\n", name, k + 1, node);
    return 2;
}

/* open the replay named on the command line, check it is one of these nodes, start every node at the prior */
static FILE *start(int argc, char **argv, cfd_node *nodes, int *steps) {
    FILE *fh;
    int count, nu, j;
    if (argc != 2) {
        fprintf(stderr, "usage: %s replay.txt\n", argv[0]);
        return NULL;
    }
    fh = fopen(argv[1], "r");
    if (!fh || fscanf(fh, "%d %d %d", steps, &count, &nu) != 3 || count != CFD_NODES || nu != CFD_NU) {
        fprintf(stderr, "%s: not a replay of these %d nodes\n", argv[1], CFD_NODES);
        return NULL;
    }
    for (j = 0; j < CFD_NODES; ++j)
        if (cfd_init(&nodes[j], cfd_exported_node(j))) return NULL;
    return fh;
}
"""

_DRIVER = r"""
int main(int argc, char **argv) {
    static cfd_node nodes[CFD_NODES];
    static double z[CFD_ROWS_MAX], rec[CFD_ROWS_MAX], flags[CFD_BALL_MAX], u[CFD_NU + 1];
    static double x[CFD_NX], P[CFD_NX * CFD_NX];
    static unsigned char arrived[CFD_BALL_MAX];
    FILE *fh;
    int steps, k, j, bad = 0;
    double worst = 0.0;
    fh = start(argc, argv, nodes, &steps);
    if (!fh) return 2;
    for (k = 0; k < steps; ++k) {
        for (j = 0; j < CFD_NODES; ++j) {
            const int *ball;
            int nb = cfd_ball(nodes[j].node, &ball), m_own = cfd_sensor_dim(ball[0]), m_rec = 0, b, e;
            for (b = 1; b < nb; ++b) m_rec += cfd_sensor_dim(ball[b]);
            if (read_numbers(fh, z, m_own) || read_numbers(fh, flags, nb - 1) || read_numbers(fh, rec, m_rec)
                    || read_numbers(fh, u, CFD_NU) || read_numbers(fh, x, CFD_NX)
                    || read_numbers(fh, P, CFD_NX * CFD_NX)) {
                return short_replay(argv[1], k, nodes[j].node);
            }
            for (b = 0; b < nb - 1; ++b) arrived[b] = flags[b] != 0.0;
            e = cfd_step(&nodes[j], z, arrived, rec, CFD_NU ? u : NULL);
            if (e) {
                fprintf(stderr, "step %d, node %d: cfd_step returned %d\n", k + 1, nodes[j].node, e);
                return 1;
            }
            check(nodes[j].x, nodes[j].P, x, P, &worst, &bad);
        }
    }
    return finish(fh, steps, worst, bad);
}
"""

_MAKEFILE = """# Generated by cfdesign export.  `make` builds the node filter library and the replay driver;
# `make test` replays replay.txt through every node and compares with the Python node filter
# (exit 0 when they agree within 1e-10).
CC ?= cc
CFLAGS ?= -std=c99 -O3 -Wall -Wextra -pedantic
LDLIBS = -lm

all: libcfd_node.a cfd_test

libcfd_node.a: cfd_node.o cfd_model.o
\tar rcs $@ $^

cfd_node.o: cfd_node.c cfd_node.h cfd_model.h
cfd_model.o: cfd_model.c cfd_model.h

cfd_test: cfd_test.c libcfd_node.a cfd_node.h
\t$(CC) $(CFLAGS) -o $@ cfd_test.c libcfd_node.a $(LDLIBS)

test: cfd_test
\t./cfd_test replay.txt

clean:
\trm -f cfd_node.o cfd_model.o libcfd_node.a cfd_test

.PHONY: all test clean
"""

_COMMON = r"""typedef int (*cfd_fun)(const casadi_real **arg, casadi_real **res, casadi_int *iw, casadi_real *w,
                       int mem);
static const cfd_fun cfd_h_fun[CFD_SENSORS] = {@HS@};
static const cfd_fun cfd_H_fun[CFD_SENSORS] = {@HHS@};

static const casadi_real *arg_[@sz_arg@];
static casadi_real *res_[@sz_res@];
static casadi_int iw_[@sz_iw@];
static casadi_real w_[@sz_w@];

static int slot_of(int node) {
    int j;
    for (j = 0; j < CFD_NODES; ++j)
        if (cfd_node_id[j] == node) return j;
    return -1;
}

const double *cfd_estimate(const cfd_node *s) { return s->x; }
const double *cfd_bound(const cfd_node *s) { return s->P; }
int cfd_exported_node(int j) { return (j >= 0 && j < CFD_NODES) ? cfd_node_id[j] : -1; }
int cfd_sensor_dim(int sensor) { return (sensor >= 0 && sensor < CFD_SENSORS) ? cfd_dim[sensor] : -1; }

/* symmetric eigen-decomposition of the m x m matrix A (destroyed, left diagonal): lam, V (the eigenvectors in its
 * columns).  Householder reflections reduce A to a tridiagonal matrix, then implicit QR steps with Wilkinson's
 * shift (Givens rotations, applied to rows and columns k, k + 1 of the whole matrix) diagonalise each unreduced
 * block; a subdiagonal entry negligible beside its two diagonal neighbours is set to zero.  O(m^3). */
static int eigsym(int m, double *A, double *lam, double *V) {
    static double v[EIG_MAX], pv[EIG_MAX], w[EIG_MAX];
    int i, j, k, p, q, lo, hi, it = 0;
    for (i = 0; i < m; ++i)
        for (j = 0; j < m; ++j) V[i * m + j] = (i == j) ? 1.0 : 0.0;
    for (k = 0; k + 2 < m; ++k) { /* zero column k below its subdiagonal */
        double below = 0.0, norm, alpha, vtv = 0.0, beta, K = 0.0;
        for (i = k + 2; i < m; ++i) below += A[i * m + k] * A[i * m + k];
        if (below == 0.0) continue;
        norm = sqrt(below + A[(k + 1) * m + k] * A[(k + 1) * m + k]);
        alpha = A[(k + 1) * m + k] > 0.0 ? -norm : norm;
        for (i = 0; i < m; ++i) v[i] = i <= k ? 0.0 : A[i * m + k];
        v[k + 1] -= alpha;
        for (i = k + 1; i < m; ++i) vtv += v[i] * v[i];
        beta = 2.0 / vtv;
        for (i = k; i < m; ++i) { /* p = beta A v (rows above k are reduced already: zero there) */
            double t = 0.0;
            for (j = k + 1; j < m; ++j) t += A[i * m + j] * v[j];
            pv[i] = beta * t;
        }
        for (i = k + 1; i < m; ++i) K += pv[i] * v[i];
        K *= 0.5 * beta;
        for (i = k; i < m; ++i) w[i] = pv[i] - K * v[i];
        for (i = k; i < m; ++i) /* A <- H A H = A - v w^T - w v^T, on the trailing block */
            for (j = k; j < m; ++j) A[i * m + j] -= v[i] * w[j] + w[i] * v[j];
        for (i = 0; i < m; ++i) { /* V <- V H */
            double t = 0.0;
            for (j = k + 1; j < m; ++j) t += V[i * m + j] * v[j];
            t *= beta;
            for (j = k + 1; j < m; ++j) V[i * m + j] -= t * v[j];
        }
        for (i = k + 2; i < m; ++i) A[i * m + k] = A[k * m + i] = 0.0;
    }
    q = m - 1;
    while (q > 0) {
        double a, b, c2, dd, mu, x, z;
        for (i = 0; i < q; ++i) {
            double e = fabs(A[(i + 1) * m + i]);
            if (e <= DBL_EPSILON * (fabs(A[i * m + i]) + fabs(A[(i + 1) * m + i + 1])) || e < DBL_MIN)
                A[(i + 1) * m + i] = A[i * m + i + 1] = 0.0;
        }
        if (A[q * m + q - 1] == 0.0) {
            --q;
            continue;
        }
        if (++it > 60 * m) return -1;
        p = q - 1;
        while (p > 0 && A[p * m + p - 1] != 0.0) --p;
        a = A[(q - 1) * m + q - 1];
        b = A[q * m + q - 1];
        c2 = A[q * m + q];
        dd = 0.5 * (a - c2);
        mu = c2 - b * b / (dd + (dd >= 0.0 ? 1.0 : -1.0) * sqrt(dd * dd + b * b));
        x = A[p * m + p] - mu;
        z = A[(p + 1) * m + p];
        for (k = p; k < q; ++k) {
            double r, c, s;
            if (k > p) {
                x = A[k * m + k - 1];
                z = A[(k + 1) * m + k - 1];
            }
            r = sqrt(x * x + z * z);
            if (r == 0.0) continue;
            c = x / r;
            s = z / r;
            lo = k > p ? k - 1 : p;
            hi = k + 2 < q ? k + 2 : q;
            for (j = lo; j <= hi; ++j) { /* rows k, k + 1 (nonzero in columns k - 1 .. k + 2 only) */
                double tk = A[k * m + j], tl = A[(k + 1) * m + j];
                A[k * m + j] = c * tk + s * tl;
                A[(k + 1) * m + j] = -s * tk + c * tl;
            }
            for (i = lo; i <= hi; ++i) { /* columns k, k + 1 */
                double tk = A[i * m + k], tl = A[i * m + k + 1];
                A[i * m + k] = c * tk + s * tl;
                A[i * m + k + 1] = -s * tk + c * tl;
            }
            for (i = 0; i < m; ++i) { /* V's columns k, k + 1 */
                double vk = V[i * m + k], vl = V[i * m + k + 1];
                V[i * m + k] = c * vk + s * vl;
                V[i * m + k + 1] = -s * vk + c * vl;
            }
            if (k > p) A[(k + 1) * m + k - 1] = A[(k - 1) * m + k + 1] = 0.0; /* the bulge chased */
        }
    }
    for (i = 0; i < m; ++i) lam[i] = A[i * m + i];
    return 0;
}

static int call(cfd_fun fn, const double *x, double k, const double *u, double *out) {
    arg_[0] = x;
    arg_[1] = &k;
    arg_[2] = u;
    res_[0] = out;
    return fn(arg_, res_, iw_, w_, 0);
}
"""


# --------------------------------------------------------------------------- the consensus rule (paper)
def write_consensus_c(model, network, design, out: Path, *, nodes: Sequence[int], replay: str | None = None,
                      verdict: str = "unknown") -> list[Path]:
    """Write the C sources of the node filter of the ``paper`` consensus design ``design``
    (:class:`filters.consensus_node.ConsensusNode`: ``cfd_predict`` gives the packet a node sends, ``cfd_update``
    takes what arrived) for the nodes ``nodes`` into ``out``; ``replay``: the text of ``replay.txt``
    (:func:`consensus_replay_text`); ``verdict``: the design's, stated in the header.  Returns the files written.

    The rule's σ, β, τ, ε, U, V_i and δ are the design's numbers; its linearisation must be ``fixed`` (the Hessian
    scalings of ``hessian`` and ``structured`` are not exported) and its rule ``paper`` (``tuned`` solves a convex
    problem online at every step: not exported)."""
    from scipy.special import chdtri

    from .bounds import BOUND_LIMIT

    if not design.rule.fixed_multipliers:
        raise InputError(f"mode must be a rule of fixed multipliers (paper) for the consensus node's C export, got "
                         f"{design.mode!r}")
    if design.linearization != "fixed":
        raise InputError(f"linearization must be 'fixed' for the C export (the {design.linearization!r} scalings "
                         "come from the model's Hessians at every step, which the export does not generate)")
    out = Path(out)
    n = model.n_x
    sizes, dims, layout = _model_code(model, out)
    sigma, beta, eps = float(design.sigma), float(design.beta), float(design.epsilon)
    U = np.asarray(design.U, dtype=float)
    UU = U @ U.T / (eps * sigma) if np.any(U) else np.zeros((n, n))
    w_xi = 3.0 * design.delta**2 * (network.fdi_prob * network.adjacency).sum(axis=1)
    nodes = [int(i) for i in nodes]
    nb_start, nb, wphi, mat_start, R, VV = [0], [], [], [0], [], []
    for i in nodes:
        senders = np.flatnonzero(network.adjacency[i])
        nb += senders.tolist()
        wphi += (3.0 * (1.0 - network.dos_prob[i, senders])).tolist()
        nb_start.append(len(nb))
        Vi = np.asarray(design.V[i], dtype=float)
        R += model.measurement_cov(i).reshape(-1).tolist()
        VV += (Vi @ Vi.T / beta if np.any(Vi) else np.zeros_like(Vi)).reshape(-1).tolist()
        mat_start.append(len(R))
    d_max = max(nb_start[j + 1] - nb_start[j] for j in range(len(nodes)))
    header = _CONSENSUS_HEADER.format(n=n, nu=model.n_u, nz=int(dims.sum()), sensors=model.n_sensors,
                                      nodes=len(nodes), d_max=max(d_max, 1), sigma=sigma, beta=beta,
                                      tau=float(design.tau), gate=float(design.gate),
                                      **_described(model, nodes, verdict))
    data = "".join([
        _array("cfd_node_id", nodes, "int"), _array("cfd_nb_start", nb_start, "int"), _array("cfd_nb", nb, "int"),
        _array("cfd_wphi", wphi), _array("cfd_wxi", w_xi[nodes]),
        _array("cfd_deg", network.degrees[nodes], "int"), _array("cfd_mat_start", mat_start, "int"),
        _array("cfd_R", R), _array("cfd_VV", VV), _array("cfd_UU", UU), layout,
        _array("cfd_Q", model.process_cov), _array("cfd_x0", model.prior.mean), _array("cfd_P0", model.prior.cov),
    ])
    source = _CONSENSUS_SOURCE.format(
        common=_common(model, sizes), linalg=_LINALG, data=data, nzmax=int(dims.max()), sigma=repr(sigma),
        beta=repr(beta),
        tau=repr(float(design.tau)), eps=repr(eps), fixed=int(design.rule.fixed_multipliers),
        gate=repr(float(design.gate)), chi2=repr(float(chdtri(n, design.gate))) if design.gate else "0.0",
        bound_limit=repr(float(BOUND_LIMIT)), rcond=repr(1e-13), diverged=repr(1e12))
    return _write(out, header, source, _DRIVER_HEAD + _CONSENSUS_DRIVER, replay)


def consensus_replay_text(nodes: Sequence[int], senders: Sequence[Sequence[int]], n_u: int, steps: list) -> str:
    """``replay.txt`` of a consensus design: ``steps nodes n_u``, then per step and node (in ``nodes`` order) the
    step's inputs, the node's measurement, one arrived flag per in-neighbour (``senders`` order), the estimates that
    arrived (zeros where not), every in-neighbour's packet (its bound row by row, then 1 if it is a bound), then the
    Python node filter's packet (prediction, its covariance, its flag) and its estimate and covariance after the
    update.  ``steps``: per step, ``(u, [(z, received {j: x̃}, bounds {j: Packet}, packet, x, P) per node])``."""
    lines = [f"{len(steps)} {len(nodes)} {n_u}"]
    for u, per_node in steps:
        for j, (z, got, bounds, packet, x, P) in enumerate(per_node):
            vals = list(np.asarray(u, float).reshape(-1)) + list(np.asarray(z, float).reshape(-1))
            vals += [1.0 if s in got else 0.0 for s in senders[j]]
            n = np.asarray(x).size
            for s in senders[j]:
                vals += list(np.asarray(got[s], float).reshape(-1)) if s in got else [0.0] * n
            for s in senders[j]:
                vals += list(np.asarray(bounds[s].P, float).reshape(-1)) + [float(bool(bounds[s].ok))]
            vals += list(np.asarray(packet.x, float)) + list(np.asarray(packet.P, float).reshape(-1))
            vals += [float(bool(packet.ok))] + list(np.asarray(x, float)) + list(np.asarray(P, float).reshape(-1))
            lines.append(" ".join(repr(float(v)) for v in vals))
    return "\n".join(lines) + "\n"


_CONSENSUS_HEADER = """/* cfd_node.h: the node filter of a cfdesign design (gain rule paper: the seed paper's
 * consensus EKF), C99.
 *
 * Generated by cfdesign export; the design's data are in cfd_node.c, the model's functions in cfd_model.c.
 * The design's verdict: {verdict} (a certified bound is finite, steady and informative; see its report).
 * The model: {model}; its states, in the order of x: {states}.
 * Nodes exported: {node_list} (node k of this file is cfd_node_id[k] of the network; cfd_init takes the
 * network's number).  Static memory only; link with -lm.  sigma = {sigma}, beta = {beta}, tau = {tau}, gate = {gate}.
 *
 * A step has two phases.  cfd_predict: the node's prediction x- = f(x) and its bound Phi- by (26) while (28)
 * holds (the EKF's F P F^T + Q otherwise): the packet the node sends to its out-neighbours.  cfd_update: its
 * own measurement, the packets of its in-neighbours that arrived (the estimates they carried, falsified or not),
 * and every in-neighbour's bound, arrived or not (the bound (27) weighs each by its channel's arrival
 * probability: the rule assumes a node learns its neighbours' bounds every step); the gain (30) with C = tau Phi-
 * while (29) holds, the fallback gains (sigma = beta = 0) for good once (28) or (29) has failed.
 */
#ifndef CFD_NODE_H
#define CFD_NODE_H

#define CFD_NX {n}            /* states */
#define CFD_NU {nu}            /* known inputs per step */
#define CFD_NZ {nz}            /* the sensors' stacked measurement components */
#define CFD_SENSORS {sensors}       /* sensors (= nodes of the network) */
#define CFD_NODES {nodes}         /* nodes exported */
#define CFD_DEG_MAX {d_max}       /* most in-neighbours of an exported node */

typedef struct {{
    double x[CFD_NX];          /* the sender's prediction */
    double P[CFD_NX * CFD_NX]; /* its covariance, row by row */
    int ok;                    /* 1 when P is a bound */
}} cfd_packet;

typedef struct {{
    int node;                  /* the network's node number */
    int slot;                  /* its place among the exported nodes */
    long k;                    /* steps taken: the next step measures the state at time k + 1 */
    double x[CFD_NX];          /* the estimate */
    double P[CFD_NX * CFD_NX]; /* its covariance, row by row: a bound while valid */
    int proper;                /* still on Theorem 1's recursion */
    int valid;                 /* P is a bound */
    int predicted;             /* between cfd_predict and cfd_update */
    cfd_packet sent;           /* the packet of the current step */
}} cfd_node;

/* Start node `node` at the prior (returns 0, or -1 for a node not exported). */
int cfd_init(cfd_node *s, int node);

/* The prediction phase: fills *packet with what the node sends (returns 0; -2 when the model could not be
 * evaluated; -4 when the node has predicted already). */
int cfd_predict(cfd_node *s, const double *u, cfd_packet *packet);

/* The update phase.  z: the node's own measurement.  arrived: one flag per in-neighbour (cfd_neighbours order),
 * 1 when its packet arrived.  received: the estimates those packets carried, CFD_NX each, in that order (any
 * values where not arrived).  bounds: every in-neighbour's packet as it was sent (its P and ok are used).
 * Returns 0; -2: the estimate left finite numbers or 1e12 (the run must stop; the state holds what was
 * computed); -3: sigma or beta violates (28) or (29) at the first step (the state is left unchanged); -4: not
 * predicted. */
int cfd_update(cfd_node *s, const double *z, const unsigned char *arrived, const double *received,
               const cfd_packet *bounds);

/* The estimate (CFD_NX) and its covariance (CFD_NX x CFD_NX, row by row; a bound while cfd_valid). */
const double *cfd_estimate(const cfd_node *s);
const double *cfd_bound(const cfd_node *s);
int cfd_valid(const cfd_node *s);

/* The in-neighbours of node `node` (returns their number, or -1; *senders points at them). */
int cfd_neighbours(int node, const int **senders);

/* The network's number of the j-th exported node (-1 beyond CFD_NODES); a sensor's measurement components. */
int cfd_exported_node(int j);
int cfd_sensor_dim(int sensor);

#endif
"""

_CONSENSUS_SOURCE = r"""/* cfd_node.c: the paper rule's consensus node filter (see cfd_node.h), by cfdesign export. */
#include <float.h>
#include <math.h>
#include <string.h>

#include "cfd_model.h"
#include "cfd_node.h"

#define NZMAX {nzmax}
#define EIG_MAX CFD_NX
#define SIGMA {sigma}
#define BETA {beta}
#define TAU {tau}
#define EPS {eps}
#define FIXED {fixed}
#define GATE {gate}
#define CHI2 {chi2}
#define BOUND_LIMIT {bound_limit}
#define RCOND {rcond}
#define DIVERGED {diverged}
#define PI_ 3.14159265358979323846

{data}
{common}
/* the step's work (static: one node steps at a time) */
#define NN (CFD_NX * CFD_NX)
static double F_[NN], A_[NN], V_[NN], lam_[CFD_NX], M_[NN], T_[NN], C_[NN], N_[NN], B_[NN], Pn_[NN];
static double H_[NZMAX * CFD_NX], hv_[NZMAX], res_v[NZMAX], HM_[NZMAX * CFD_NX], S_[NZMAX * NZMAX];
static double X_[NZMAX * CFD_NX], K_[CFD_NX * NZMAX], KM_[CFD_NX * NZMAX], innov_[CFD_NX], xn_[CFD_NX];

int cfd_init(cfd_node *s, int node) {{
    int slot = slot_of(node);
    if (slot < 0) return -1;
    memset(s, 0, sizeof *s);
    s->node = node;
    s->slot = slot;
    s->proper = 1;
    s->valid = 1;
    memcpy(s->x, cfd_x0, sizeof s->x);
    memcpy(s->P, cfd_P0, sizeof s->P);
    return 0;
}}

int cfd_valid(const cfd_node *s) {{ return s->valid; }}

int cfd_neighbours(int node, const int **senders) {{
    int slot = slot_of(node);
    if (slot < 0) return -1;
    *senders = cfd_nb + cfd_nb_start[slot];
    return cfd_nb_start[slot + 1] - cfd_nb_start[slot];
}}

{linalg}
/* the spectrum of the symmetric P (n x n): V_, lam_; returns 1 / lambda_max, or -inf when P is not finite or not
 * numerically positive definite (lambda_min <= RCOND lambda_max) */
static double spectrum(const double *P) {{
    double lo, hi;
    int i;
    if (!finite_all(P, NN)) return -INFINITY;
    memcpy(A_, P, sizeof A_);
    if (eigsym(CFD_NX, A_, lam_, V_)) return -INFINITY;
    lo = hi = lam_[0];
    for (i = 1; i < CFD_NX; ++i) {{
        if (lam_[i] < lo) lo = lam_[i];
        if (lam_[i] > hi) hi = lam_[i];
    }}
    return lo > RCOND * hi ? 1.0 / hi : -INFINITY;
}}

/* M = (P^-1 - c I)^-1 = V diag(lam / (1 - c lam)) V^T from the spectrum (c = 0: P itself) */
static void shifted(const double *P, double c) {{
    int i, j, a;
    if (c == 0.0) {{
        memcpy(M_, P, sizeof M_);
        return;
    }}
    for (i = 0; i < CFD_NX; ++i)
        for (j = 0; j < CFD_NX; ++j) {{
            double t = 0.0;
            for (a = 0; a < CFD_NX; ++a) t += V_[i * CFD_NX + a] * (lam_[a] / (1.0 - c * lam_[a])) * V_[j * CFD_NX + a];
            M_[i * CFD_NX + j] = t;
        }}
    sym(M_, CFD_NX);
}}

int cfd_predict(cfd_node *s, const double *u, cfd_packet *packet) {{
    const int n = CFD_NX;
    double tr = 0.0;
    int i, pvalid = 0;
    if (s->predicted) return -4;
    if (call(cfd_f, s->x, (double)s->k, u, s->sent.x) || call(cfd_F, s->x, (double)s->k, u, F_)) return -2;
    memcpy(B_, s->P, sizeof B_);
    sym(B_, n);
    for (i = 0; i < n; ++i) tr += s->P[i * n + i];
    if (s->proper && tr < BOUND_LIMIT) {{
        const double c = (1.0 + EPS) * SIGMA;
        if (spectrum(B_) - c > 0.0) {{ /* (28); Phi- = F (Phi^-1 - c I)^-1 F^T + U U^T / (eps sigma) + Q */
            shifted(B_, c);
            mul(F_, M_, T_, n, n, n);
            mul_t(T_, F_, Pn_, n, n, n);
            for (i = 0; i < NN; ++i) Pn_[i] = Pn_[i] + cfd_UU[i] + cfd_Q[i];
            pvalid = 1;
        }}
    }}
    if (!pvalid) {{ /* the fallback: F P F^T + Q */
        mul(F_, B_, T_, n, n, n);
        mul_t(T_, F_, Pn_, n, n, n);
        for (i = 0; i < NN; ++i) Pn_[i] = Pn_[i] + cfd_Q[i];
    }}
    sym(Pn_, n);
    memcpy(s->sent.P, Pn_, sizeof Pn_);
    s->sent.ok = pvalid;
    s->predicted = 1;
    *packet = s->sent;
    packet->ok = pvalid && s->valid;
    return 0;
}}

int cfd_update(cfd_node *s, const double *z, const unsigned char *arrived, const double *received,
               const cfd_packet *bounds) {{
    const int n = CFD_NX, slot = s->slot, i_node = s->node, m = cfd_dim[i_node];
    const int e0 = cfd_nb_start[slot], d = cfd_nb_start[slot + 1] - e0, ms = cfd_mat_start[slot];
    const double k1 = (double)(s->k + 1), w = 1.0 + 2.0 * cfd_deg[slot];
    const double *xp = s->sent.x, *Pp = s->sent.P;
    const int pvalid = s->sent.ok;
    double count = 0.0, big = 0.0;
    int e, i, j, c, uvalid = 0, nb_ok = 1, v28, v29, bad;
    if (!s->predicted) return -4;
    /* the packets kept (the gate: (x~_j - x-_i)^T (2 (Phi_i + Phi_j))^+ (x~_j - x-_i) <= chi2), their sum */
    memset(innov_, 0, sizeof innov_);
    memset(N_, 0, sizeof N_);
    for (e = 0; e < d; ++e) {{
        const double *xj = received + e * n;
        int keep = arrived[e] != 0;
        if (keep && GATE > 0.0) {{
            double stat = 0.0, dv[CFD_NX], hi = 0.0;
            for (i = 0; i < NN; ++i) A_[i] = 2.0 * (Pp[i] + bounds[e].P[i]);
            for (i = 0; i < n; ++i) dv[i] = xj[i] - xp[i];
            if (finite_all(A_, NN) && finite_all(dv, n) && !eigsym(n, A_, lam_, V_)) {{
                for (i = 0; i < n; ++i) if (fabs(lam_[i]) > hi) hi = fabs(lam_[i]);
                for (i = 0; i < n; ++i) {{
                    double t = 0.0;
                    if (!(fabs(lam_[i]) > 1e-15 * hi)) continue;
                    for (j = 0; j < n; ++j) t += V_[j * n + i] * dv[j];
                    stat += t * t / lam_[i];
                }}
            }}
            keep = stat <= CHI2;
        }}
        if (keep) {{
            count += 1.0;
            for (i = 0; i < n; ++i) innov_[i] += xj[i];
        }}
        for (i = 0; i < NN; ++i) N_[i] += cfd_wphi[e0 + e] * bounds[e].P[i];
        if (!bounds[e].ok) nb_ok = 0;
    }}
    for (i = 0; i < n; ++i) innov_[i] -= count * xp[i];
    for (i = 0; i < n; ++i) N_[i * n + i] += cfd_wxi[slot];
    /* the residual at the prediction, angles wrapped */
    if (call(cfd_h_fun[i_node], xp, k1, 0, hv_) || call(cfd_H_fun[i_node], xp, k1, 0, H_)) return -2;
    for (c = 0; c < m; ++c) {{
        res_v[c] = z[c] - hv_[c];
        if (cfd_angle[cfd_zoff[i_node] + c] && fabs(res_v[c]) > PI_) {{
            double t = fmod(PI_ - res_v[c], 2.0 * PI_);
            if (t < 0.0) t += 2.0 * PI_;
            res_v[c] = PI_ - t;
        }}
    }}
    if (pvalid && spectrum(Pp) - BETA > 0.0) {{ /* (29): the gain (30), the bound (27) */
        shifted(Pp, BETA);
        uvalid = 1;
    }} else {{ /* the fallback: beta = 0, V = 0, the inflations (1 + 2 d) and 3 set to 1 */
        memcpy(M_, Pp, sizeof M_);
        for (i = 0; i < NN; ++i) N_[i] /= 3.0;
    }}
    for (i = 0; i < NN; ++i) C_[i] = TAU * Pp[i];
    /* K = (I - s C) (S^-1 H M)^T, S = H M H^T + V V^T / beta + R / w */
    mul(H_, M_, HM_, m, n, n);
    mul_t(HM_, H_, S_, m, n, m);
    for (i = 0; i < m; ++i)
        for (j = 0; j < m; ++j)
            S_[i * m + j] += uvalid ? cfd_VV[ms + i * m + j] + cfd_R[ms + i * m + j] / w : cfd_R[ms + i * m + j];
    sym(S_, m);
    memcpy(X_, HM_, sizeof(double) * (size_t)(m * n));
    if (solve(S_, X_, m, n)) return -2;
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j) T_[i * n + j] = (i == j ? 1.0 : 0.0) - count * C_[i * n + j];
    mul_t(T_, X_, K_, n, n, m);
    /* Phi+ = w A M A^T + C N C^T + K (w V V^T / beta + R) K^T, A = I - s C - K H (w = 1, no V in the fallback) */
    mul(K_, H_, A_, n, m, n);
    for (i = 0; i < NN; ++i) A_[i] = T_[i] - A_[i];
    mul(A_, M_, B_, n, n, n);
    mul_t(B_, A_, Pn_, n, n, n);
    mul(C_, N_, B_, n, n, n);
    mul_t(B_, C_, T_, n, n, n);
    for (i = 0; i < m; ++i)
        for (j = 0; j < m; ++j)
            S_[i * m + j] = uvalid ? w * cfd_VV[ms + i * m + j] + cfd_R[ms + i * m + j] : cfd_R[ms + i * m + j];
    mul(K_, S_, KM_, n, m, m);
    mul_t(KM_, K_, B_, n, m, n);
    for (i = 0; i < NN; ++i) Pn_[i] = (uvalid ? w : 1.0) * Pn_[i] + T_[i] + B_[i];
    sym(Pn_, n);
    /* x+ = x- + K res + C innovation */
    for (i = 0; i < n; ++i) {{
        double t = 0.0, u = 0.0;
        for (c = 0; c < m; ++c) t += K_[i * m + c] * res_v[c];
        for (j = 0; j < n; ++j) u += C_[i * n + j] * innov_[j];
        xn_[i] = xp[i] + t + u;
        if (fabs(xn_[i]) > big) big = fabs(xn_[i]);
    }}
    v28 = s->proper && !pvalid;
    v29 = pvalid && !uvalid;
    if (s->k == 0 && FIXED && (v28 || v29)) {{
        s->predicted = 0;
        return -3;
    }}
    bad = !(finite_all(xn_, n) && finite_all(Pn_, NN) && big < DIVERGED);
    s->valid = uvalid && pvalid && s->valid && nb_ok;
    s->proper = s->proper && !v28 && !v29;
    memcpy(s->x, xn_, sizeof xn_);
    memcpy(s->P, Pn_, sizeof Pn_);
    s->k += 1;
    s->predicted = 0;
    return bad ? -2 : 0;
}}
"""

_CONSENSUS_DRIVER = r"""
int main(int argc, char **argv) {
    static cfd_node nodes[CFD_NODES];
    static cfd_packet bounds[CFD_DEG_MAX], mine;
    static double u[CFD_NU + 1], z[CFD_NZ], flags[CFD_DEG_MAX], rec[CFD_DEG_MAX * CFD_NX], ok[1];
    static double px[CFD_NX], pP[CFD_NX * CFD_NX], pok[1], x[CFD_NX], P[CFD_NX * CFD_NX];
    static unsigned char arrived[CFD_DEG_MAX];
    FILE *fh;
    int steps, k, j, b, bad = 0;
    double worst = 0.0;
    fh = start(argc, argv, nodes, &steps);
    if (!fh) return 2;
    for (k = 0; k < steps; ++k) {
        for (j = 0; j < CFD_NODES; ++j) {
            const int *senders;
            int d = cfd_neighbours(nodes[j].node, &senders), m = cfd_sensor_dim(nodes[j].node), e;
            int short_read = read_numbers(fh, u, CFD_NU) || read_numbers(fh, z, m) || read_numbers(fh, flags, d)
                             || read_numbers(fh, rec, d * CFD_NX);
            for (b = 0; b < d && !short_read; ++b) {
                short_read = read_numbers(fh, bounds[b].P, CFD_NX * CFD_NX) || read_numbers(fh, ok, 1);
                bounds[b].ok = ok[0] != 0.0;
            }
            if (short_read || read_numbers(fh, px, CFD_NX) || read_numbers(fh, pP, CFD_NX * CFD_NX)
                    || read_numbers(fh, pok, 1) || read_numbers(fh, x, CFD_NX)
                    || read_numbers(fh, P, CFD_NX * CFD_NX)) {
                return short_replay(argv[1], k, nodes[j].node);
            }
            for (b = 0; b < d; ++b) arrived[b] = flags[b] != 0.0;
            e = cfd_predict(&nodes[j], CFD_NU ? u : NULL, &mine);
            if (e) {
                fprintf(stderr, "step %d, node %d: cfd_predict returned %d\n", k + 1, nodes[j].node, e);
                return 1;
            }
            if ((mine.ok != 0) != (pok[0] != 0.0)) bad += 1;
            check(mine.x, mine.P, px, pP, &worst, &bad);
            e = cfd_update(&nodes[j], z, arrived, rec, bounds);
            if (e) {
                fprintf(stderr, "step %d, node %d: cfd_update returned %d\n", k + 1, nodes[j].node, e);
                return 1;
            }
            check(nodes[j].x, nodes[j].P, x, P, &worst, &bad);
        }
    }
    return finish(fh, steps, worst, bad);
}
"""

_LINALG = r"""/* out = a b (r x m times m x c), out = a b^T (r x m times c x m), out = (a + a^T) / 2 (n x n) */
static inline void mul(const double *a, const double *b, double *out, int r, int m, int c) {
    int i, j, l;
    for (i = 0; i < r; ++i)
        for (j = 0; j < c; ++j) {
            double t = 0.0;
            for (l = 0; l < m; ++l) t += a[i * m + l] * b[l * c + j];
            out[i * c + j] = t;
        }
}

static inline void mul_t(const double *a, const double *b, double *out, int r, int m, int c) {
    int i, j, l;
    for (i = 0; i < r; ++i)
        for (j = 0; j < c; ++j) {
            double t = 0.0;
            for (l = 0; l < m; ++l) t += a[i * m + l] * b[j * m + l];
            out[i * c + j] = t;
        }
}

static inline void sym(double *a, int n) {
    int i, j;
    for (i = 0; i < n; ++i)
        for (j = 0; j < i; ++j) a[i * n + j] = a[j * n + i] = 0.5 * (a[i * n + j] + a[j * n + i]);
}

static inline int finite_all(const double *a, int count) {
    int i;
    for (i = 0; i < count; ++i)
        if (!isfinite(a[i])) return 0;
    return 1;
}

/* solve S X = B (m x m, m x c) by Gaussian elimination with partial pivoting; S and B are destroyed */
static inline int solve(double *S, double *B, int m, int c) {
    int i, j, l, p;
    for (l = 0; l < m; ++l) {
        p = l;
        for (i = l + 1; i < m; ++i)
            if (fabs(S[i * m + l]) > fabs(S[p * m + l])) p = i;
        if (S[p * m + l] == 0.0) return -1;
        if (p != l) {
            for (j = 0; j < m; ++j) { double t = S[l * m + j]; S[l * m + j] = S[p * m + j]; S[p * m + j] = t; }
            for (j = 0; j < c; ++j) { double t = B[l * c + j]; B[l * c + j] = B[p * c + j]; B[p * c + j] = t; }
        }
        for (i = l + 1; i < m; ++i) {
            double f = S[i * m + l] / S[l * m + l];
            for (j = l; j < m; ++j) S[i * m + j] -= f * S[l * m + j];
            for (j = 0; j < c; ++j) B[i * c + j] -= f * B[l * c + j];
        }
    }
    for (i = m - 1; i >= 0; --i)
        for (j = 0; j < c; ++j) {
            double t = B[i * c + j];
            for (l = i + 1; l < m; ++l) t -= S[i * m + l] * B[l * c + j];
            B[i * c + j] = t / S[i * m + i];
        }
    return 0;
}
"""


# --------------------------------------------------------------------------- the scheduled rule
def write_scheduled_c(model, network, design, out: Path, *, nodes: Sequence[int], replay: str | None = None,
                      verdict: str = "unknown") -> list[Path]:
    """Write the C sources of the node filter of the ``scheduled`` design ``design``
    (:class:`filters.scheduled.ScheduledNode`: ``cfd_predict`` with the node's measurement gives the packet it
    sends, ``cfd_update`` the first round with what arrived, ``cfd_round`` the exchange rounds 2..L) for the nodes
    ``nodes`` into ``out``: each exported node's tables (the whitened factors of its links per step and round, the
    stationary ones beyond the horizon, the bank's), its certificate per step, and the per-link gains'
    solve (:func:`designer.scheduled.link_gains`, :func:`designer.mse.solve_gains`) online.  ``replay``: the text of
    ``replay.txt`` (:func:`scheduled_replay_text`).  Returns the files written."""
    from .mse import GAIN_RCOND

    tables = design.tables
    if design.mode != "scheduled" or tables is None:
        raise InputError(f"mode must be 'scheduled' with its tables for this export, got {design.mode!r}")
    out = Path(out)
    n = model.n_x
    sizes, dims, layout = _model_code(model, out)
    nz = int(dims.max())
    ch = tables.channels
    chan, mask = ch.slots
    L = int(tables.rounds)
    T = tables.steps
    B = len(tables.bank_points) if tables.has_bank else 0
    nodes = [int(i) for i in nodes]
    R_pad = np.stack([np.pad(model.measurement_cov(i), ((0, nz - dims[i]), (0, nz - dims[i])))
                      + np.diag(np.r_[np.zeros(dims[i]), np.ones(nz - dims[i])]) for i in range(model.n_sensors)])
    nb_start, nb, p, q, tab_start = [0], [], [], [], [0]
    gam, sig = [], []  # per node: [step (T, then inf) and per bank point][round][slot...]
    for i in nodes:
        sl = chan[i][mask[i]]
        d = sl.size
        nb += ch.sender[sl].tolist()
        p += ch.p[sl].tolist()
        q += ch.q[sl].tolist()
        nb_start.append(len(nb))
        for k in range(T + 1):  # the step's own tables, k = T: beyond the horizon
            for r in range(1, L + 1):
                G, S = tables.tables(k) if r == 1 else tables.round_tables(k, r)
                gam.append(G[sl].reshape(-1))
                sig.append(S[i, :d, :d].reshape(-1))
        for b in range(B):
            for r in range(1, L + 1):
                G = tables.bank_Gamma[b] if r == 1 else tables.bank_round_Gamma[b, r - 2]
                S = tables.bank_Sigma[b] if r == 1 else tables.bank_round_Sigma[b, r - 2]
                gam.append(G[sl].reshape(-1))
                sig.append(S[i, :d, :d].reshape(-1))
        tab_start.append(len(gam))
    d_max = max(nb_start[j + 1] - nb_start[j] for j in range(len(nodes)))
    gam_off = np.concatenate([[0], np.cumsum([g.size for g in gam])])
    sig_off = np.concatenate([[0], np.cumsum([g.size for g in sig])])
    cert = np.where(tables.valid[:, None, None, None], tables.Phi, np.nan)[:, nodes]  # (T + 1, nodes, n, n)
    M = np.zeros((n, n)) if design.fdi_moment is None else np.asarray(design.fdi_moment, dtype=float)
    mu = np.zeros(n) if design.fdi_mean is None else np.asarray(design.fdi_mean, dtype=float)
    nominal = tables.nominal[np.minimum(np.arange(T + 1) + 1, T)]  # the step's own candidate point, k = 0..T
    header = _SCHEDULED_HEADER.format(n=n, nu=model.n_u, nz=int(dims.sum()), sensors=model.n_sensors,
                                      nodes=len(nodes), d_max=max(d_max, 1), rounds=L, steps=int(T), nzmax=nz,
                                      exch=int(bool(tables.exchange)),
                                      exchange="exchanged" if tables.exchange else "not exchanged",
                                      **_described(model, nodes, verdict))
    data = "".join([
        _array("cfd_node_id", nodes, "int"), _array("cfd_nb_start", nb_start, "int"), _array("cfd_nb", nb, "int"),
        _array("cfd_p", p), _array("cfd_q", q), _array("cfd_tab_start", tab_start, "int"),
        _array("cfd_gam_off", gam_off, "int"), _array("cfd_sig_off", sig_off, "int"),
        _array("cfd_gam", np.concatenate(gam) if gam else []), _array("cfd_sig", np.concatenate(sig) if sig else []),
        _array("cfd_cert", cert), _array("cfd_Rpad", R_pad), _array("cfd_M", M), _array("cfd_mu", mu),
        _array("cfd_nominal", nominal), _array("cfd_bank_points", tables.bank_points if B else []),
        _array("cfd_bank_metric", tables.bank_metric if B else []), layout,
        _array("cfd_Q", model.process_cov), _array("cfd_x0", model.prior.mean), _array("cfd_P0", model.prior.cov),
    ])
    source = _SCHEDULED_SOURCE.format(
        common=_common(model, sizes), linalg=_LINALG, data=data, nzmax=nz, exch=int(bool(tables.exchange)),
        rounds=L, T=T, B=B, A=0 if not B else int(tables.bank_metric.shape[0]), margin=repr(float(tables.robustness)),
        gain_rcond=repr(float(GAIN_RCOND)), diverged=repr(1e12))
    return _write(out, header, source, _DRIVER_HEAD + _SCHEDULED_DRIVER, replay)


def scheduled_replay_text(nodes: Sequence[int], senders: Sequence[Sequence[int]], n_u: int, nz: int,
                          exchange: bool, steps: list) -> str:
    """``replay.txt`` of a scheduled design: ``steps nodes n_u``, then per step and node (in ``nodes`` order) the
    step's inputs, the node's measurement, one arrived flag per in-neighbour, the predictions that arrived (zeros
    where not), with exchange the measurements that arrived (``nz`` each, zero-padded), for rounds 2..L the
    estimates that arrived, then the Python node filter's estimate and own covariance after the step.  ``steps``:
    per step, ``(u, [(z, received {j: ScheduledPacket}, [{j: x̃} per round 2..L], x, P) per node])``."""
    lines = [f"{len(steps)} {len(nodes)} {n_u}"]
    for u, per_node in steps:
        for j, (z, got, later, x, P) in enumerate(per_node):
            n = np.asarray(x).size
            vals = list(np.asarray(u, float).reshape(-1)) + list(np.asarray(z, float).reshape(-1))
            vals += [1.0 if s in got else 0.0 for s in senders[j]]
            for s in senders[j]:
                vals += list(np.asarray(got[s].x, float)) if s in got else [0.0] * n
            for s in senders[j] if exchange else ():
                zz = np.asarray(got[s].z, float).reshape(-1) if s in got else np.zeros(0)
                vals += list(zz) + [0.0] * (nz - zz.size)
            for rnd in later:
                for s in senders[j]:
                    vals += list(np.asarray(rnd[s], float)) if s in rnd else [0.0] * n
            vals += list(np.asarray(x, float)) + list(np.asarray(P, float).reshape(-1))
            lines.append(" ".join(repr(float(v)) for v in vals))
    return "\n".join(lines) + "\n"


_SCHEDULED_HEADER = """/* cfd_node.h: the node filter of a cfdesign design (gain rule scheduled: per-link gains
 * from tables designed offline), C99.
 *
 * Generated by cfdesign export; the design's data (each exported node's tables) are in cfd_node.c, the model's
 * functions in cfd_model.c.  The design's verdict: {verdict} (a certified bound is finite, steady and informative;
 * see its report).  Nodes exported: {node_list} (node k of this file is cfd_node_id[k] of the network; cfd_init
 * takes the network's number).  Static memory only; link with -lm.  {rounds} exchange round(s) a step; the
 * neighbours' measurements {exchange}; tables for {steps} steps, the stationary ones beyond.
 * The model: {model}; its states, in the order of x: {states}.
 *
 * A step: cfd_predict with the node's own measurement (its prediction f(x), its own covariance F P F^T + Q, its
 * choice of tables: the packet it sends, with its measurement when they are exchanged); cfd_update with which
 * in-neighbours' packets arrived and what they carried (the first round: the gains of each link from the step's
 * tables coloured by the node's own covariance, solved online); then cfd_round for rounds 2..L with the
 * neighbours' current estimates on the same channels.  cfd_certificate is the design's certificate at the node's
 * step (NULL where it certifies nothing); cfd_bound its own covariance.
 */
#ifndef CFD_NODE_H
#define CFD_NODE_H

#define CFD_NX {n}            /* states */
#define CFD_NU {nu}            /* known inputs per step */
#define CFD_NZ {nz}            /* the sensors' stacked measurement components */
#define CFD_NZMAX {nzmax}         /* the largest sensor's components (exchanged measurements are padded to it) */
#define CFD_SENSORS {sensors}       /* sensors (= nodes of the network) */
#define CFD_NODES {nodes}         /* nodes exported */
#define CFD_DEG_MAX {d_max}       /* most in-neighbours of an exported node */
#define CFD_ROUNDS {rounds}        /* exchange rounds a step */
#define CFD_EXCHANGE {exch}      /* 1: the packets carry the senders' measurements */

typedef struct {{
    double x[CFD_NX];          /* the sender's prediction (a later round: its current estimate) */
    double z[CFD_NZMAX];       /* its measurement, when exchanged (zero-padded) */
}} cfd_packet;

typedef struct {{
    int node;                  /* the network's node number */
    int slot;                  /* its place among the exported nodes */
    long k;                    /* steps taken: the next step measures the state at time k + 1 */
    double x[CFD_NX];          /* the estimate */
    double P[CFD_NX * CFD_NX]; /* its own covariance, row by row */
    int phase;                 /* 0: predict next; 1: update; r >= 2: round r */
    int choice;                /* the tables of this step: 0 the step's own, b > 0 bank point b - 1's */
    double z[CFD_NZMAX];       /* its measurement of this step */
    unsigned char arrived[CFD_DEG_MAX];
}} cfd_node;

/* Start node `node` at the prior (returns 0, or -1 for a node not exported). */
int cfd_init(cfd_node *s, int node);

/* The prediction with the node's own measurement z; fills *packet (returns 0; -2: the model could not be
 * evaluated; -4: out of phase). */
int cfd_predict(cfd_node *s, const double *z, const double *u, cfd_packet *packet);

/* The first round.  arrived: one flag per in-neighbour (cfd_neighbours order); received: their packets in that
 * order (any values where not arrived).  Returns 0; -2: the gains' solve broke down or the estimate left finite
 * numbers or 1e12 (the run must stop); -4: out of phase. */
int cfd_update(cfd_node *s, const unsigned char *arrived, const cfd_packet *received);

/* Round r = 2..CFD_ROUNDS: the neighbours' current estimates (CFD_NX each, in cfd_neighbours order) on the
 * channels whose first packet arrived.  Returns as cfd_update. */
int cfd_round(cfd_node *s, const double *received);

/* The estimate (CFD_NX), its own covariance (cfd_bound, CFD_NX x CFD_NX, row by row: what the node carries, not
 * a bound) and the design's certificate at its step (NULL where the design certifies nothing). */
const double *cfd_estimate(const cfd_node *s);
const double *cfd_bound(const cfd_node *s);
const double *cfd_certificate(const cfd_node *s);

/* The in-neighbours of node `node` (returns their number, or -1; *senders points at them). */
int cfd_neighbours(int node, const int **senders);

/* The network's number of the j-th exported node (-1 beyond CFD_NODES); a sensor's measurement components. */
int cfd_exported_node(int j);
int cfd_sensor_dim(int sensor);

#endif
"""

_SCHEDULED_SOURCE = r"""/* cfd_node.c: the scheduled rule's node filter (see cfd_node.h), by cfdesign export. */
#include <float.h>
#include <math.h>
#include <string.h>

#include "cfd_model.h"
#include "cfd_node.h"

#define NZMAX {nzmax}
#define EXCH {exch}
#define MZ (EXCH ? NZMAX : 0)
#define AA (MZ + CFD_NX)                /* a link's innovation: [its measurement ; the difference of estimates] */
#define WMAX (NZMAX + CFD_DEG_MAX * AA) /* the innovations of a node: its measurement, then every link's */
#define NN (CFD_NX * CFD_NX)
#define T_ {T}
#define B_ {B}
#define A_ {A}
#define MARGIN {margin}
#define GAIN_RCOND {gain_rcond}
#define DIVERGED {diverged}
#define PI_ 3.14159265358979323846
#define EIG_MAX WMAX

{data}
{common}
{linalg}
/* the step's work (static: one node steps at a time) */
static double F_[NN], T1_[NN], root_[NN], lamv_[CFD_NX], Vv_[NN], Gs_[CFD_DEG_MAX * NN],
    Ss_[CFD_DEG_MAX * CFD_DEG_MAX * NN];
static double Hown_[NZMAX * CFD_NX], rown_[NZMAX], hv_[NZMAX], Hv_[NZMAX * CFD_NX];
static double Hn_[CFD_DEG_MAX * NZMAX * CFD_NX], rn_[CFD_DEG_MAX * NZMAX];
static double ey_[CFD_NX * WMAX], yy_[WMAX * WMAX], yg_[WMAX * WMAX], sc_[WMAX], Z_[CFD_NX * WMAX];
static double Su_[WMAX * WMAX], bu_[CFD_NX * WMAX], lam_[WMAX], V_[WMAX * WMAX], A_w[WMAX * WMAX];
static double core_[AA * AA], J_[CFD_DEG_MAX * AA * CFD_NX], Jmu_[CFD_DEG_MAX * AA], crs_[CFD_DEG_MAX * CFD_NX * AA];
static double Pn_[NN], xn_[CFD_NX];
static int used_[WMAX];

int cfd_init(cfd_node *s, int node) {{
    int slot = slot_of(node);
    if (slot < 0) return -1;
    memset(s, 0, sizeof *s);
    s->node = node;
    s->slot = slot;
    memcpy(s->x, cfd_x0, sizeof s->x);
    memcpy(s->P, cfd_P0, sizeof s->P);
    return 0;
}}

const double *cfd_certificate(const cfd_node *s) {{
    const double *c;
    if (s->k > T_) return 0;
    c = cfd_cert + ((size_t)s->k * CFD_NODES + (size_t)s->slot) * NN;
    return isfinite(c[0]) ? c : 0;
}}

int cfd_neighbours(int node, const int **senders) {{
    int slot = slot_of(node);
    if (slot < 0) return -1;
    *senders = cfd_nb + cfd_nb_start[slot];
    return cfd_nb_start[slot + 1] - cfd_nb_start[slot];
}}

/* root = P^(1/2) of the symmetric positive semidefinite P (its eigenvalues below 0 taken as 0) */
static int sqrtm(const double *P) {{
    int i, j, a;
    memcpy(T1_, P, sizeof T1_);
    sym(T1_, CFD_NX);
    if (eigsym(CFD_NX, T1_, lamv_, Vv_)) return -1;
    for (i = 0; i < CFD_NX; ++i)
        for (j = 0; j < CFD_NX; ++j) {{
            double t = 0.0;
            for (a = 0; a < CFD_NX; ++a) t += Vv_[i * CFD_NX + a] * sqrt(lamv_[a] > 0.0 ? lamv_[a] : 0.0)
                                              * Vv_[j * CFD_NX + a];
            root_[i * CFD_NX + j] = t;
        }}
    sym(root_, CFD_NX);
    return 0;
}}

/* the slot tables of round r (1..L) of this step and choice, coloured by the root: Gs_ (d x n x n), Ss_ (d x d) */
static void coloured(const cfd_node *s, int r, int d) {{
    const int n = CFD_NX, kk = s->k < T_ ? (int)s->k : T_;
    const int entry = cfd_tab_start[s->slot] + (s->choice == 0 ? kk * CFD_ROUNDS : (T_ + 1) * CFD_ROUNDS
                                                 + (s->choice - 1) * CFD_ROUNDS) + (r - 1);
    const double *G = cfd_gam + cfd_gam_off[entry], *S = cfd_sig + cfd_sig_off[entry];
    int j;
    for (j = 0; j < d; ++j) {{
        mul(root_, G + j * NN, T1_, n, n, n);
        mul(T1_, root_, Gs_ + j * NN, n, n, n);
    }}
    for (j = 0; j < d * d; ++j) {{
        mul(root_, S + j * NN, T1_, n, n, n);
        mul(T1_, root_, Ss_ + j * NN, n, n, n);
    }}
}}

/* Z = E[e y^T] E[y y^T]+ in the units of the innovations' sizes, over the components that have a variance (as
 * designer.mse.solve_gains): an LU solve where every eigenvalue is above GAIN_RCOND of the largest, else the
 * pseudo-inverse without the others.  ey_ (n x w), yg_ (w x w), sc_ (w); Z_ (n x w). */
static int solve_gains(int w) {{
    const int n = CFD_NX;
    int i, j, a, u = 0, full = 1;
    double top = 0.0;
    memset(Z_, 0, sizeof(double) * (size_t)(n * w));
    for (i = 0; i < w; ++i) {{
        double di = sc_[i] > 0.0 ? sc_[i] : 1.0;
        if (yg_[i * w + i] / (di * di) != 0.0) used_[u++] = i;
    }}
    if (!u) return 0;
    for (i = 0; i < u; ++i) {{
        const int ii = used_[i];
        const double di = sc_[ii] > 0.0 ? sc_[ii] : 1.0;
        for (j = 0; j < u; ++j) {{
            const int jj = used_[j];
            const double dj = sc_[jj] > 0.0 ? sc_[jj] : 1.0;
            Su_[i * u + j] = yg_[ii * w + jj] / (di * dj);
        }}
        for (a = 0; a < n; ++a) bu_[a * u + i] = ey_[a * w + ii] / di;
    }}
    memcpy(A_w, Su_, sizeof(double) * (size_t)(u * u));
    if (eigsym(u, A_w, lam_, V_)) return -1;
    for (i = 0; i < u; ++i) if (lam_[i] > top) top = lam_[i];
    for (i = 0; i < u; ++i) if (!(lam_[i] > GAIN_RCOND * top)) full = 0;
    if (full) {{ /* Z_u^T = S^-1 b^T */
        static double Bt[WMAX * CFD_NX];
        for (i = 0; i < u; ++i) for (a = 0; a < n; ++a) Bt[i * n + a] = bu_[a * u + i];
        memcpy(A_w, Su_, sizeof(double) * (size_t)(u * u));
        if (solve(A_w, Bt, u, n)) return -1;
        for (a = 0; a < n; ++a) for (i = 0; i < u; ++i) bu_[a * u + i] = Bt[i * n + a];
    }} else {{ /* b V diag(1/lam kept) V^T */
        static double bV[CFD_NX * WMAX];
        for (a = 0; a < n; ++a)
            for (j = 0; j < u; ++j) {{
                double t = 0.0;
                for (i = 0; i < u; ++i) t += bu_[a * u + i] * V_[i * u + j];
                bV[a * u + j] = lam_[j] > GAIN_RCOND * top ? t / lam_[j] : 0.0;
            }}
        for (a = 0; a < n; ++a)
            for (i = 0; i < u; ++i) {{
                double t = 0.0;
                for (j = 0; j < u; ++j) t += bV[a * u + j] * V_[i * u + j];
                bu_[a * u + i] = t;
            }}
    }}
    for (i = 0; i < u; ++i) {{
        const int ii = used_[i];
        const double di = sc_[ii] > 0.0 ? sc_[ii] : 1.0;
        for (a = 0; a < n; ++a) Z_[a * w + ii] = bu_[a * u + i] / di;
    }}
    return 0;
}}

/* the per-link gains of a node (designer.scheduled.link_gains): P (n x n) its covariance, H (m x n) and R (m x m)
 * its padded measurement's (m = NZMAX; H = 0 in rounds 2..L), the coloured tables Gs_, Ss_ of its d links, p, q
 * theirs, with exchange Hn_ (d x NZMAX x n) and the senders' padded R; Z_ the gains [K, (K_n, C) per link] and Pn_
 * the expected posterior.  w = m + d a. */
static int link_gains(const double *P, const double *H, const double *R, const double *p, const double *q,
                      const int *snd, int d, int exch) {{
    const int n = CFD_NX, m = NZMAX, mz = exch ? NZMAX : 0, a = mz + n, w = m + d * a;
    int i, j, l, al, be, c;
    double has = 0.0;
    static double HP[NZMAX * CFD_NX], my[NZMAX * NZMAX], HPn[CFD_DEG_MAX * NZMAX * CFD_NX];
    mul(H, P, HP, m, n, n);
    mul_t(HP, H, my, m, n, m);
    for (i = 0; i < m * m; ++i) my[i] += R[i];
    sym(my, m);
    memset(ey_, 0, sizeof(double) * (size_t)(n * w));
    memset(yy_, 0, sizeof(double) * (size_t)(w * w));
    for (i = 0; i < n; ++i) for (j = 0; j < m; ++j) ey_[i * w + j] = HP[j * n + i];
    for (i = 0; i < m; ++i) for (j = 0; j < m; ++j) yy_[i * w + j] = my[i * m + j];
    for (j = 0; j < d; ++j) {{ /* J_j = [H_j ; I], J_j mu, E[e_i y_j^T] = [P H_j^T, G_j] */
        for (al = 0; al < a; ++al)
            for (c = 0; c < n; ++c)
                J_[(j * a + al) * n + c] = al < mz ? Hn_[(j * NZMAX + al) * n + c] : (al - mz == c ? 1.0 : 0.0);
        for (al = 0; al < a; ++al) {{
            double t = 0.0;
            for (c = 0; c < n; ++c) t += J_[(j * a + al) * n + c] * cfd_mu[c];
            Jmu_[j * a + al] = t;
        }}
        if (exch) mul(Hn_ + j * NZMAX * n, P, HPn + j * NZMAX * n, NZMAX, n, n);
        for (i = 0; i < n; ++i)
            for (al = 0; al < a; ++al)
                crs_[(j * n + i) * a + al] = al < mz ? HPn[(j * NZMAX + al) * n + i] : Gs_[j * NN + i * n + al - mz];
        if (p[j] > 0.0) has = 1.0;
    }}
    for (j = 0; j < d; ++j) /* E[e y_j^T] = p_j cross_j; E[y_0 y_j^T] = H (p_j cross_j) */
        for (al = 0; al < a; ++al) {{
            for (i = 0; i < n; ++i) ey_[i * w + m + j * a + al] = p[j] * crs_[(j * n + i) * a + al];
            for (i = 0; i < m; ++i) {{
                double t = 0.0;
                for (c = 0; c < n; ++c) t += H[i * n + c] * p[j] * crs_[(j * n + c) * a + al];
                yy_[i * w + m + j * a + al] = yy_[(m + j * a + al) * w + i] = t;
            }}
        }}
    for (j = 0; j < d; ++j)
        for (l = 0; l < d; ++l) {{ /* block (j, l): E[p_j p_l] core_jl + the falsifications' */
            const double epp = p[j] * p[l] + (j == l ? p[l] - p[l] * p[l] : 0.0);
            const double pqj = p[j] * q[j], pql = p[l] * q[l];
            for (al = 0; al < a; ++al)
                for (be = 0; be < a; ++be) {{
                    double cv;
                    if (al >= mz && be >= mz) cv = Ss_[(j * d + l) * NN + (al - mz) * n + be - mz];
                    else if (al < mz && be < mz) {{
                        double t = 0.0;
                        for (c = 0; c < n; ++c) t += HPn[(j * NZMAX + al) * n + c] * Hn_[(l * NZMAX + be) * n + c];
                        cv = t + (j == l ? cfd_Rpad[(size_t)snd[j] * NZMAX * NZMAX + al * NZMAX + be] : 0.0);
                    }} else if (al < mz) {{ /* H_j G_l */
                        double t = 0.0;
                        for (c = 0; c < n; ++c) t += Hn_[(j * NZMAX + al) * n + c] * Gs_[l * NN + c * n + be - mz];
                        cv = t;
                    }} else {{ /* (H_l G_j)^T */
                        double t = 0.0;
                        for (c = 0; c < n; ++c) t += Hn_[(l * NZMAX + be) * n + c] * Gs_[j * NN + c * n + al - mz];
                        cv = t;
                    }}
                    core_[al * a + be] = cv;
                }}
            for (al = 0; al < a; ++al)
                for (be = 0; be < a; ++be) {{
                    double f = 0.0;
                    if (j != l) f = pqj * pql * Jmu_[j * a + al] * Jmu_[l * a + be];
                    else {{
                        double t = 0.0;
                        int r1, r2;
                        for (r1 = 0; r1 < n; ++r1)
                            for (r2 = 0; r2 < n; ++r2)
                                t += J_[(j * a + al) * n + r1] * cfd_M[r1 * n + r2] * J_[(j * a + be) * n + r2];
                        f = pqj * t;
                    }}
                    yy_[(m + j * a + al) * w + m + l * a + be] = epp * core_[al * a + be] + f;
                }}
        }}
    sym(yy_, w);
    memcpy(yg_, yy_, sizeof(double) * (size_t)(w * w));
    if (MARGIN != 0.0)
        for (j = 0; j < d; ++j)
            for (al = mz; al < a; ++al)
                for (be = mz; be < a; ++be)
                    yg_[(m + j * a + al) * w + m + j * a + be] += MARGIN * p[j] * P[(al - mz) * n + be - mz];
    for (i = 0; i < m; ++i) sc_[i] = sqrt(fabs(my[i * m + i]));
    for (j = 0; j < d; ++j)
        for (al = mz; al < a; ++al) sc_[m + j * a + al] = sqrt(fabs(P[(al - mz) * n + al - mz]));
    if (exch) /* a link's measurement's size: its variance before the arrivals' expectation */
        for (j = 0; j < d; ++j)
            for (al = 0; al < mz; ++al) {{
                double t = 0.0;
                for (c = 0; c < n; ++c) t += HPn[(j * NZMAX + al) * n + c] * Hn_[(j * NZMAX + al) * n + c];
                sc_[m + j * a + al] = sqrt(fabs(t + cfd_Rpad[(size_t)snd[j] * NZMAX * NZMAX + al * NZMAX + al]));
            }}
    if (solve_gains(has > 0.0 ? w : m)) return -1;
    /* the expected posterior: P - Z ey^T - ey Z^T + Z yy Z^T */
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j) {{
            double ze = 0.0, ez = 0.0;
            for (c = 0; c < w; ++c) {{
                ze += Z_[i * w + c] * ey_[j * w + c];
                ez += ey_[i * w + c] * Z_[j * w + c];
            }}
            Pn_[i * n + j] = P[i * n + j] - ze - ez;
        }}
    mul(Z_, yy_, A_w, n, w, w);
    mul_t(A_w, Z_, T1_, n, w, n);
    for (i = 0; i < NN; ++i) Pn_[i] += T1_[i];
    sym(Pn_, n);
    return 0;
}}

static int choose(const double *xp, int kk) {{
    int b, c, a, best = 0;
    double bestv = 0.0;
    if (!B_) return 0;
    for (b = 0; b <= B_; ++b) {{
        const double *pt = b == 0 ? cfd_nominal + (size_t)kk * CFD_NX : cfd_bank_points + (size_t)(b - 1) * CFD_NX;
        double v = 0.0;
        for (a = 0; a < A_; ++a) {{
            double t = 0.0;
            for (c = 0; c < CFD_NX; ++c) t += (xp[c] - pt[c]) * cfd_bank_metric[a * CFD_NX + c];
            v += t * t;
        }}
        if (b == 0 || v < bestv) {{
            best = b;
            bestv = v;
        }}
    }}
    return best;
}}

int cfd_predict(cfd_node *s, const double *z, const double *u, cfd_packet *packet) {{
    const int n = CFD_NX;
    int i;
    if (s->phase != 0) return -4;
    if (call(cfd_f, s->x, (double)s->k, u, packet->x) || call(cfd_F, s->x, (double)s->k, u, F_)) return -2;
    mul(F_, s->P, T1_, n, n, n);
    mul_t(T1_, F_, Pn_, n, n, n);
    for (i = 0; i < NN; ++i) Pn_[i] += cfd_Q[i];
    sym(Pn_, n);
    memcpy(s->P, Pn_, sizeof Pn_);
    memcpy(s->x, packet->x, sizeof s->x);
    s->choice = choose(s->x, s->k < T_ ? (int)s->k : T_);
    memset(packet->z, 0, sizeof packet->z);
    memset(s->z, 0, sizeof s->z);
    for (i = 0; i < cfd_dim[s->node]; ++i) packet->z[i] = s->z[i] = z[i];
    s->phase = 1;
    return 0;
}}

static int finish(cfd_node *s) {{
    double big = 0.0;
    int i;
    for (i = 0; i < CFD_NX; ++i) if (fabs(xn_[i]) > big) big = fabs(xn_[i]);
    memcpy(s->x, xn_, sizeof xn_);
    memcpy(s->P, Pn_, sizeof Pn_);
    if (s->phase >= CFD_ROUNDS) {{
        s->phase = 0;
        s->k += 1;
    }} else s->phase += 1;
    return (finite_all(xn_, CFD_NX) && finite_all(Pn_, NN) && big < DIVERGED) ? 0 : -2;
}}

int cfd_update(cfd_node *s, const unsigned char *arrived, const cfd_packet *received) {{
    const int n = CFD_NX, slot = s->slot, me = s->node, m = cfd_dim[me];
    const int e0 = cfd_nb_start[slot], d = cfd_nb_start[slot + 1] - e0;
    const double k1 = (double)(s->k + 1);
    int i, j, c, mj;
    if (s->phase != 1) return -4;
    if (sqrtm(s->P)) return -2;
    coloured(s, 1, d);
    memset(Hown_, 0, sizeof Hown_);
    memset(rown_, 0, sizeof rown_);
    if (call(cfd_h_fun[me], s->x, k1, 0, hv_) || call(cfd_H_fun[me], s->x, k1, 0, Hv_)) return -2;
    for (c = 0; c < m; ++c) {{
        memcpy(Hown_ + c * n, Hv_ + c * n, sizeof(double) * n);
        rown_[c] = s->z[c] - hv_[c];
        if (cfd_angle[cfd_zoff[me] + c] && fabs(rown_[c]) > PI_) {{
            double t = fmod(PI_ - rown_[c], 2.0 * PI_);
            if (t < 0.0) t += 2.0 * PI_;
            rown_[c] = PI_ - t;
        }}
    }}
    memset(Hn_, 0, sizeof Hn_);
    memset(rn_, 0, sizeof rn_);
    if (EXCH)
        for (j = 0; j < d; ++j) {{ /* the neighbours' measurements at the node's own prediction */
            const int sj = cfd_nb[e0 + j];
            mj = cfd_dim[sj];
            if (call(cfd_h_fun[sj], s->x, k1, 0, hv_) || call(cfd_H_fun[sj], s->x, k1, 0, Hv_)) return -2;
            for (c = 0; c < mj; ++c) {{
                memcpy(Hn_ + (j * NZMAX + c) * n, Hv_ + c * n, sizeof(double) * n);
                if (arrived[j]) {{
                    double r = received[j].z[c] - hv_[c];
                    if (cfd_angle[cfd_zoff[sj] + c] && fabs(r) > PI_) {{
                        double t = fmod(PI_ - r, 2.0 * PI_);
                        if (t < 0.0) t += 2.0 * PI_;
                        r = PI_ - t;
                    }}
                    rn_[j * NZMAX + c] = r;
                }}
            }}
        }}
    if (link_gains(s->P, Hown_, cfd_Rpad + (size_t)me * NZMAX * NZMAX, cfd_p + e0, cfd_q + e0, cfd_nb + e0, d,
                   EXCH)) return -2;
    {{
        const int w = NZMAX + d * AA;
        for (i = 0; i < n; ++i) {{
            double t = s->x[i];
            for (c = 0; c < NZMAX; ++c) t += Z_[i * w + c] * rown_[c];
            for (j = 0; j < d; ++j) {{
                if (!arrived[j]) continue;
                for (c = 0; c < MZ; ++c) t += Z_[i * w + NZMAX + j * AA + c] * rn_[j * NZMAX + c];
                for (c = 0; c < n; ++c) t += Z_[i * w + NZMAX + j * AA + MZ + c] * (received[j].x[c] - s->x[c]);
            }}
            xn_[i] = t;
        }}
    }}
    for (j = 0; j < d; ++j) s->arrived[j] = arrived[j] != 0;
    return finish(s);
}}

int cfd_round(cfd_node *s, const double *received) {{
    const int n = CFD_NX, slot = s->slot, e0 = cfd_nb_start[slot], d = cfd_nb_start[slot + 1] - e0;
    static double zeroH[NZMAX * CFD_NX];
    int i, j, c;
    if (s->phase < 2) return -4;
    if (sqrtm(s->P)) return -2;
    coloured(s, s->phase, d);
    if (link_gains(s->P, zeroH, cfd_Rpad + (size_t)s->node * NZMAX * NZMAX, cfd_p + e0, cfd_q + e0, cfd_nb + e0, d,
                   0)) return -2;
    {{
        const int w = NZMAX + d * CFD_NX;
        for (i = 0; i < n; ++i) {{
            double t = s->x[i];
            for (j = 0; j < d; ++j)
                if (s->arrived[j])
                    for (c = 0; c < n; ++c) t += Z_[i * w + NZMAX + j * n + c] * (received[j * n + c] - s->x[c]);
            xn_[i] = t;
        }}
    }}
    return finish(s);
}}
"""

_SCHEDULED_DRIVER = r"""
int main(int argc, char **argv) {
    static cfd_node nodes[CFD_NODES];
    static cfd_packet got[CFD_DEG_MAX], mine;
    static double u[CFD_NU + 1], z[CFD_NZ], flags[CFD_DEG_MAX], rec[CFD_DEG_MAX * CFD_NX];
    static double x[CFD_NX], P[CFD_NX * CFD_NX];
    static unsigned char arrived[CFD_DEG_MAX];
    FILE *fh;
    int steps, k, j, b, r, bad = 0;
    double worst = 0.0;
    fh = start(argc, argv, nodes, &steps);
    if (!fh) return 2;
    for (k = 0; k < steps; ++k) {
        for (j = 0; j < CFD_NODES; ++j) {
            const int *senders;
            int d = cfd_neighbours(nodes[j].node, &senders), m = cfd_sensor_dim(nodes[j].node), e;
            int short_read = read_numbers(fh, u, CFD_NU) || read_numbers(fh, z, m) || read_numbers(fh, flags, d);
            for (b = 0; b < d && !short_read; ++b) short_read = read_numbers(fh, got[b].x, CFD_NX);
            for (b = 0; b < d && !short_read && CFD_EXCHANGE; ++b) short_read = read_numbers(fh, got[b].z, CFD_NZMAX);
            for (b = 0; b < d; ++b) arrived[b] = flags[b] != 0.0;
            e = short_read ? 0 : cfd_predict(&nodes[j], z, CFD_NU ? u : NULL, &mine);
            if (!short_read && !e) e = cfd_update(&nodes[j], arrived, got);
            for (r = 2; r <= CFD_ROUNDS && !short_read && !e; ++r) {
                short_read = read_numbers(fh, rec, d * CFD_NX);
                if (!short_read) e = cfd_round(&nodes[j], rec);
            }
            if (short_read || read_numbers(fh, x, CFD_NX) || read_numbers(fh, P, CFD_NX * CFD_NX)) {
                return short_replay(argv[1], k, nodes[j].node);
            }
            if (e) {
                fprintf(stderr, "step %d, node %d: the node filter returned %d\n", k + 1, nodes[j].node, e);
                return 1;
            }
            check(nodes[j].x, nodes[j].P, x, P, &worst, &bad);
        }
    }
    return finish(fh, steps, worst, bad);
}
"""
