"""C99 sources of a node's filter: ``cfdesign export DESIGN_DIR --target c``.

For a design whose gain rule relays (``relay``, ``flood``: run time ``local``, the gains computed online by the
node), :func:`write_relay_c` writes into a directory:

* ``cfd_model.c``, ``cfd_model.h`` — the model's ``f``, ``F = ∂f/∂x`` and every sensor's ``h_s``, ``H_s`` through
  CasADi's code generator (dense outputs; no allocation);
* ``cfd_node.h``, ``cfd_node.c`` — the node filter of :class:`filters.relay.RelayNode` in C: the API
  ``cfd_init``, ``cfd_step``, ``cfd_estimate``, ``cfd_bound``, ``cfd_ball``, each node's design data (its ball,
  the arrival and falsification moments of its rows, their hop depths), the relay rule's update
  (:func:`designer.relay.relay_update`: the pseudo-inverse by a symmetric eigen-decomposition, Householder
  tridiagonalisation and implicit QR steps) and the
  bound's recursion (the node's expected covariance); static memory only, libc and libm only;
* ``cfd_test.c``, ``replay.txt`` — a test driver replaying a run through every node and comparing each step's
  estimate and bound with what the Python node filter computed on the same run (written in ``replay.txt``);
* ``Makefile`` — ``make`` builds the driver and ``libcfd_node.a``; ``make test`` runs the replay and exits 0 when
  every estimate and bound agrees within 1e-10 of the largest magnitude of its vector or matrix.

The sources depend on the design only through their data: the same generator serves every relay design.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import casadi as ca
import numpy as np

from .validation import InputError

__all__ = ["write_relay_c", "REPLAY_TOLERANCE"]

REPLAY_TOLERANCE = 1e-10  # make test: |C - Python| <= this times the largest magnitude of the vector or matrix


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


def _array(name: str, values, ctype: str = "double") -> str:
    flat = np.asarray(values).reshape(-1)
    if ctype == "double":
        body = ", ".join(repr(float(v)) for v in flat) or "0.0"
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

    out = Path(out)
    n, nz_max = model.n_x, max(model.sensor_dims)
    signal = design.fdi_signal
    M = np.zeros((n, n)) if signal is None else signal.moment(n)
    mu = np.zeros(n) if signal is None else signal.mean(n)
    if not np.any(network.fdi_prob > 0):
        M, mu = np.zeros((n, n)), np.zeros(n)
    G = routes.hops + 1
    fns = _functions(model)
    cg = ca.CodeGenerator("cfd_model.c", {"with_header": True})
    for fn in fns:
        cg.add(fn)
    cg.generate(str(out) + "/")
    sz_arg = max(fn.sz_arg() for fn in fns)
    sz_res = max(fn.sz_res() for fn in fns)
    sz_iw = max(fn.sz_iw() for fn in fns)
    sz_w = max(fn.sz_w() for fn in fns)
    dims = np.asarray(model.sensor_dims, dtype=int)
    rinv = [sqrtm_psd(model.measurement_cov(s), inverse=True) for s in range(model.n_sensors)]
    rinv_start = np.concatenate([[0], np.cumsum(dims ** 2)])
    angle = np.zeros(int(dims.sum()), dtype=int)
    zoff = np.concatenate([[0], np.cumsum(dims)])
    for s, sen in enumerate(model.sensors):
        for c in sen.angles:
            angle[zoff[s] + c] = 1
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
                            ball_max=ball_max, rows_max=r_max, rounds=routes.hops, mode=design.mode,
                            node_list=", ".join(map(str, nodes)), received_max=r_max - 1 if r_max > 1 else 1,
                            verdict=verdict)
    data = "".join([
        _array("cfd_node_id", nodes, "int"), _array("cfd_ball_start", ball_start, "int"),
        _array("cfd_ball_sensor", ball, "int"), _array("cfd_row_start", row_start, "int"),
        _array("cfd_row_group", row_group, "int"), _array("cfd_p", p), _array("cfd_rr_start", rr_start, "int"),
        _array("cfd_A", A), _array("cfd_F1", F1), _array("cfd_F2", F2),
        _array("cfd_dim", dims, "int"), _array("cfd_zoff", zoff, "int"), _array("cfd_angle", angle, "int"),
        _array("cfd_rinv_start", rinv_start, "int"),
        _array("cfd_rinv", np.concatenate([r.reshape(-1) for r in rinv])),
        _array("cfd_Q", model.process_cov), _array("cfd_M", M), _array("cfd_mu", mu),
        _array("cfd_x0", model.prior.mean), _array("cfd_P0", model.prior.cov),
    ])
    hs = ", ".join(f"cfd_h{s}" for s in range(model.n_sensors))
    Hs = ", ".join(f"cfd_H{s}" for s in range(model.n_sensors))
    source = _SOURCE.format(data=data, hs=hs, Hs=Hs, sz_arg=max(sz_arg, 1), sz_res=max(sz_res, 1),
                            sz_iw=max(sz_iw, 1), sz_w=max(sz_w, 1), G=G, gn=gn, nzmax=nz_max,
                            use_f1=int(bool(np.any(M))), use_f2=int(bool(np.any(mu))))
    files = {"cfd_node.h": header, "cfd_node.c": source, "cfd_test.c": _DRIVER, "Makefile": _MAKEFILE}
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

{data}
typedef int (*cfd_fun)(const casadi_real **arg, casadi_real **res, casadi_int *iw, casadi_real *w, int mem);
static const cfd_fun cfd_h_fun[CFD_SENSORS] = {{{hs}}};
static const cfd_fun cfd_H_fun[CFD_SENSORS] = {{{Hs}}};

static const casadi_real *arg_[{sz_arg}];
static casadi_real *res_[{sz_res}];
static casadi_int iw_[{sz_iw}];
static casadi_real w_[{sz_w}];

/* the step's work (static: one node steps at a time) */
static double xp_[CFD_NX], F_[CFD_NX * CFD_NX], Pp_[CFD_NX * CFD_NX], T_[CFD_NX * CFD_NX];
static double Hw_[CFD_ROWS_MAX * CFD_NX], res0_[CFD_ROWS_MAX], hv_[NZMAX], Hv_[NZMAX * CFD_NX];
static double S_[CFD_ROWS_MAX * CFD_ROWS_MAX], HP_[CFD_ROWS_MAX * CFD_NX], HM_[CFD_ROWS_MAX * CFD_NX];
static double hmu_[CFD_ROWS_MAX], U_[CFD_ROWS_MAX * GN];
static double Sg_[CFD_NX * GN], Q_[GN * GN], V_[GN * GN], lam_[GN], Qp_[GN * GN], C_[CFD_NX * GN];
static double W_[CFD_NX * GN], y_[GN], Pn_[CFD_NX * CFD_NX];
static int act_[GN];

static int slot_of(int node) {{
    int j;
    for (j = 0; j < CFD_NODES; ++j)
        if (cfd_node_id[j] == node) return j;
    return -1;
}}

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

const double *cfd_estimate(const cfd_node *s) {{ return s->x; }}
const double *cfd_bound(const cfd_node *s) {{ return s->P; }}

int cfd_exported_node(int j) {{ return (j >= 0 && j < CFD_NODES) ? cfd_node_id[j] : -1; }}
int cfd_sensor_dim(int sensor) {{ return (sensor >= 0 && sensor < CFD_SENSORS) ? cfd_dim[sensor] : -1; }}

int cfd_ball(int node, const int **sensors) {{
    int slot = slot_of(node);
    if (slot < 0) return -1;
    *sensors = cfd_ball_sensor + cfd_ball_start[slot];
    return cfd_ball_start[slot + 1] - cfd_ball_start[slot];
}}

/* symmetric eigen-decomposition of the m x m matrix A (destroyed, left diagonal): lam, V (the eigenvectors in its
 * columns).  Householder reflections reduce A to a tridiagonal matrix, then implicit QR steps with Wilkinson's
 * shift (Givens rotations, applied to rows and columns k, k + 1 of the whole matrix) diagonalise each unreduced
 * block; a subdiagonal entry negligible beside its two diagonal neighbours is set to zero.  O(m^3). */
static int eigsym(int m, double *A, double *lam, double *V) {{
    static double v[GN], pv[GN], w[GN];
    int i, j, k, p, q, lo, hi, it = 0;
    for (i = 0; i < m; ++i)
        for (j = 0; j < m; ++j) V[i * m + j] = (i == j) ? 1.0 : 0.0;
    for (k = 0; k + 2 < m; ++k) {{ /* zero column k below its subdiagonal */
        double below = 0.0, norm, alpha, vtv = 0.0, beta, K = 0.0;
        for (i = k + 2; i < m; ++i) below += A[i * m + k] * A[i * m + k];
        if (below == 0.0) continue;
        norm = sqrt(below + A[(k + 1) * m + k] * A[(k + 1) * m + k]);
        alpha = A[(k + 1) * m + k] > 0.0 ? -norm : norm;
        for (i = 0; i < m; ++i) v[i] = i <= k ? 0.0 : A[i * m + k];
        v[k + 1] -= alpha;
        for (i = k + 1; i < m; ++i) vtv += v[i] * v[i];
        beta = 2.0 / vtv;
        for (i = k; i < m; ++i) {{ /* p = beta A v (rows above k are reduced already: zero there) */
            double t = 0.0;
            for (j = k + 1; j < m; ++j) t += A[i * m + j] * v[j];
            pv[i] = beta * t;
        }}
        for (i = k + 1; i < m; ++i) K += pv[i] * v[i];
        K *= 0.5 * beta;
        for (i = k; i < m; ++i) w[i] = pv[i] - K * v[i];
        for (i = k; i < m; ++i) /* A <- H A H = A - v w^T - w v^T, on the trailing block */
            for (j = k; j < m; ++j) A[i * m + j] -= v[i] * w[j] + w[i] * v[j];
        for (i = 0; i < m; ++i) {{ /* V <- V H */
            double t = 0.0;
            for (j = k + 1; j < m; ++j) t += V[i * m + j] * v[j];
            t *= beta;
            for (j = k + 1; j < m; ++j) V[i * m + j] -= t * v[j];
        }}
        for (i = k + 2; i < m; ++i) A[i * m + k] = A[k * m + i] = 0.0;
    }}
    q = m - 1;
    while (q > 0) {{
        double a, b, c2, dd, mu, x, z;
        for (i = 0; i < q; ++i) {{
            double e = fabs(A[(i + 1) * m + i]);
            if (e <= DBL_EPSILON * (fabs(A[i * m + i]) + fabs(A[(i + 1) * m + i + 1])) || e < DBL_MIN)
                A[(i + 1) * m + i] = A[i * m + i + 1] = 0.0;
        }}
        if (A[q * m + q - 1] == 0.0) {{
            --q;
            continue;
        }}
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
        for (k = p; k < q; ++k) {{
            double r, c, s;
            if (k > p) {{
                x = A[k * m + k - 1];
                z = A[(k + 1) * m + k - 1];
            }}
            r = sqrt(x * x + z * z);
            if (r == 0.0) continue;
            c = x / r;
            s = z / r;
            lo = k > p ? k - 1 : p;
            hi = k + 2 < q ? k + 2 : q;
            for (j = lo; j <= hi; ++j) {{ /* rows k, k + 1 (nonzero in columns k - 1 .. k + 2 only) */
                double tk = A[k * m + j], tl = A[(k + 1) * m + j];
                A[k * m + j] = c * tk + s * tl;
                A[(k + 1) * m + j] = -s * tk + c * tl;
            }}
            for (i = lo; i <= hi; ++i) {{ /* columns k, k + 1 */
                double tk = A[i * m + k], tl = A[i * m + k + 1];
                A[i * m + k] = c * tk + s * tl;
                A[i * m + k + 1] = -s * tk + c * tl;
            }}
            for (i = 0; i < m; ++i) {{ /* V's columns k, k + 1 */
                double vk = V[i * m + k], vl = V[i * m + k + 1];
                V[i * m + k] = c * vk + s * vl;
                V[i * m + k + 1] = -s * vk + c * vl;
            }}
            if (k > p) A[(k + 1) * m + k - 1] = A[(k - 1) * m + k + 1] = 0.0; /* the bulge chased */
        }}
    }}
    for (i = 0; i < m; ++i) lam[i] = A[i * m + i];
    return 0;
}}

static int call(cfd_fun fn, const double *x, double k, const double *u, double *out) {{
    arg_[0] = x;
    arg_[1] = &k;
    arg_[2] = u;
    res_[0] = out;
    return fn(arg_, res_, iw_, w_, 0);
}}

int cfd_step(cfd_node *s, const double *z, const unsigned char *arrived, const double *received, const double *u) {{
    const int n = CFD_NX, slot = s->slot;
    const int b0 = cfd_ball_start[slot], nb = cfd_ball_start[slot + 1] - b0;
    const int r = cfd_row_start[slot + 1] - cfd_row_start[slot], r0 = cfd_row_start[slot], rr0 = cfd_rr_start[slot];
    const double kk = (double)s->k, k1 = (double)(s->k + 1);
    int i, j, a, b, g, c, row, na, off;
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
    for (i = 0; i < na; ++i)
        for (j = 0; j < na; ++j) {{
            double t = 0.0;
            for (a = 0; a < na; ++a)
                if (lam_[a] > RTOL * lmax) t += V_[i * na + a] * V_[j * na + a] / lam_[a];
            Qp_[i * na + j] = t;
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

_DRIVER = r"""/* cfd_test.c: replay a run through every exported node and compare with the Python node filter. */
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

static double largest(const double *v, int count) {
    double m = 0.0;
    int i;
    for (i = 0; i < count; ++i)
        if (fabs(v[i]) > m) m = fabs(v[i]);
    return m;
}

int main(int argc, char **argv) {
    static cfd_node nodes[CFD_NODES];
    static double z[CFD_ROWS_MAX], rec[CFD_ROWS_MAX], flags[CFD_BALL_MAX], u[CFD_NU + 1];
    static double x[CFD_NX], P[CFD_NX * CFD_NX];
    static unsigned char arrived[CFD_BALL_MAX];
    FILE *fh;
    int steps, count, nu, k, j, i, bad = 0;
    double worst = 0.0;
    if (argc != 2) {
        fprintf(stderr, "usage: %s replay.txt\n", argv[0]);
        return 2;
    }
    fh = fopen(argv[1], "r");
    if (!fh || fscanf(fh, "%d %d %d", &steps, &count, &nu) != 3 || count != CFD_NODES || nu != CFD_NU) {
        fprintf(stderr, "%s: not a replay of these %d nodes\n", argv[1], CFD_NODES);
        return 2;
    }
    for (j = 0; j < CFD_NODES; ++j)
        if (cfd_init(&nodes[j], cfd_exported_node(j))) return 2;
    for (k = 0; k < steps; ++k) {
        for (j = 0; j < CFD_NODES; ++j) {
            const int *ball;
            int nb = cfd_ball(nodes[j].node, &ball), m_own = cfd_sensor_dim(ball[0]), m_rec = 0, b, e;
            double scale_x, scale_P;
            for (b = 1; b < nb; ++b) m_rec += cfd_sensor_dim(ball[b]);
            if (read_numbers(fh, z, m_own) || read_numbers(fh, flags, nb - 1) || read_numbers(fh, rec, m_rec)
                    || read_numbers(fh, u, CFD_NU) || read_numbers(fh, x, CFD_NX)
                    || read_numbers(fh, P, CFD_NX * CFD_NX)) {
                fprintf(stderr, "%s: short at step %d, node %d\n", argv[1], k + 1, nodes[j].node);
                return 2;
            }
            for (b = 0; b < nb - 1; ++b) arrived[b] = flags[b] != 0.0;
            e = cfd_step(&nodes[j], z, arrived, rec, CFD_NU ? u : NULL);
            if (e) {
                fprintf(stderr, "step %d, node %d: cfd_step returned %d\n", k + 1, nodes[j].node, e);
                return 1;
            }
            scale_x = largest(x, CFD_NX);
            scale_P = largest(P, CFD_NX * CFD_NX);
            for (i = 0; i < CFD_NX; ++i) {
                double d = fabs(nodes[j].x[i] - x[i]) / (scale_x > 0 ? scale_x : 1.0);
                if (d > worst) worst = d;
                if (d > TOL) bad += 1;
            }
            for (i = 0; i < CFD_NX * CFD_NX; ++i) {
                double d = fabs(nodes[j].P[i] - P[i]) / (scale_P > 0 ? scale_P : 1.0);
                if (d > worst) worst = d;
                if (d > TOL) bad += 1;
            }
        }
    }
    fclose(fh);
    printf("%d steps x %d nodes: largest difference from the Python node filter %.3g (relative), %d above %g\n",
           steps, CFD_NODES, worst, bad, TOL);
    return bad ? 1 : 0;
}
"""

_MAKEFILE = """# Generated by cfdesign export.  `make` builds the node filter library and the replay driver;
# `make test` replays replay.txt through every node and compares with the Python node filter
# (exit 0 when they agree within 1e-10).
CC ?= cc
CFLAGS ?= -std=c99 -O2 -Wall
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
