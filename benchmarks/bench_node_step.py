"""One node filter step in C (``cfdesign export --target c``) against the Python node filter, its code size and the
memory a node needs.

A design of ``--scenario`` in each ``--mode`` (an exported gain rule: ``relay``, ``flood``, ``paper`` or
``scheduled``) is written and exported to C in a temporary directory; its ``replay.txt`` (the design's simulated run:
every node's measurement and what reached it at every step: the relayed measurements, or the neighbours' packets) is
replayed ``--repeat`` times:

* **C**: a driver compiled with ``cc -O3`` (the generated Makefile's optimisation) beside the exported sources calls
  ``cfd_step`` (paper: ``cfd_predict`` then ``cfd_update``; scheduled: and ``cfd_round`` for its rounds 2..L) for
  every node and step, the replay read
  into memory first (timed: the steps only, ``clock_gettime``), ``--repeat`` replays; the best of three timings;
* **Python**: the node filters (:class:`rules.relay.filter.RelayNode`, :class:`filters.consensus_node.ConsensusNode`,
  :class:`rules.scheduled.filter.ScheduledNode`) step every node on the same inputs (what the network's step delivered,
  computed before the timing), in this process, BLAS on one thread, one replay; the best of three.

Beside the C node, the same driver times a plain EKF step in C of as many states and measurement rows (the
prediction F P F^T + Q, then one Cholesky update; fixed data, no model evaluation) over the same steps: a relay
node's rows are its ball's, a paper node's its own measurement's, a scheduled node's its innovations (its
measurement's, then per link its neighbour's estimate's and, exchanged, measurement's); issue 41 asks for a node step
within ``EKF_TARGET`` = 3 x it (printed, not checked: not met yet).

Printed: microseconds per node step in each and their ratio (issue 27 expects >= ``TARGET_RATIO`` = 50), the
exported code's size (``size``: the text of ``cfd_node.o`` and ``cfd_model.o``, a scheduled design's constant tables
included), the static memory of the node filter (their data and bss as ``size`` counts them: the model's function
tables only, which are constant; the node keeps no mutable static data) and a node's memory (``sizeof(cfd_node)``:
its state and its step's work).  ``--check`` exits 1 below the target ratio.

``--field RxC`` runs a node at size instead: ``benchmarks/models/heat_field.py`` with R x C cells (R C states, a
node per cell); ``--ekf-max X`` makes ``--check`` also exit 1 where the node step is more than X times its plain EKF
step, ``--min-ratio`` sets the Python / C ratio it asks (default ``TARGET_RATIO``).  CI runs the 4 x 4 field's
scheduled and relay nodes at ``--ekf-max 6 --min-ratio 2``: 4.0 x and 1.7 x measured (2026-12-07); the scheduled node
was 8.3 x before its falsification term's a² n² products became a n² + a² n (a regression guard, not issue 41's 3 x;
at 16 states the Python node filter is only about 9 x slower than C).

Run: ``python benchmarks/bench_node_step.py [--scenario indoor-robot | --field 4x4] [--mode relay ...] [--repeat 200]
[--check [--min-ratio R] [--ekf-max X]]`` (CI: ``--mode relay paper scheduled``, and the field's).
"""
from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


TARGET_RATIO = 50.0
EKF_TARGET = 3.0  # issue 41: a node step in C at most this many times a plain EKF step of its states and rows

_BENCH_HEAD = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "cfd_node.h"

#include <math.h>
#include <string.h>

#define EKF_ROWS 512 /* most measurement rows of the baseline */

/* a replay row's tolerances in make test (designer.export_c.REPLAY_TOLERANCES): not inputs; 0, or -1 at its end */
static int skip_tolerances(FILE *fh) {
    double v;
    int i;
    for (i = 0; i < TOLERANCES; ++i)
        if (fscanf(fh, "%lf", &v) != 1) return -1;
    return 0;
}

/* The baseline: one plain EKF step of CFD_NX states with r measurement rows, as a textbook writes it: the prediction
 * x = F x, P = F P F^T + Q, then S = H P H^T + R, its Cholesky factor, K^T = S^-1 H P, x += K (z - H x),
 * P -= K H P, symmetrised.  F, Q, H, R are fixed data (the model's functions are not evaluated: their cost is the
 * node's). */
static double F_[CFD_NX * CFD_NX], Q_[CFD_NX * CFD_NX], H_[EKF_ROWS * CFD_NX], S_[EKF_ROWS * EKF_ROWS];
static double T_[CFD_NX * CFD_NX], HP_[EKF_ROWS * CFD_NX], v_[EKF_ROWS];

static void ekf_step(double *x, double *P, int r) {
    const int n = CFD_NX;
    int i, j, a;
    double t, u;
    for (i = 0; i < n; ++i) {
        for (t = 0.0, a = 0; a < n; ++a) t += F_[i * n + a] * x[a];
        v_[i] = t;
    }
    memcpy(x, v_, sizeof(double) * n);
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j) {
            for (t = 0.0, a = 0; a < n; ++a) t += F_[i * n + a] * P[a * n + j];
            T_[i * n + j] = t;
        }
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j) {
            for (t = Q_[i * n + j], a = 0; a < n; ++a) t += T_[i * n + a] * F_[j * n + a];
            P[i * n + j] = t;
        }
    for (i = 0; i < r; ++i)
        for (j = 0; j < n; ++j) {
            for (t = 0.0, a = 0; a < n; ++a) t += H_[i * n + a] * P[a * n + j];
            HP_[i * n + j] = t;
        }
    for (i = 0; i < r; ++i) /* S = H P H^T + R (R = I), its lower triangle */
        for (j = 0; j <= i; ++j) {
            for (t = i == j ? 1.0 : 0.0, a = 0; a < n; ++a) t += HP_[i * n + a] * H_[j * n + a];
            S_[i * r + j] = t;
        }
    for (j = 0; j < r; ++j) { /* S = L L^T */
        for (t = S_[j * r + j], a = 0; a < j; ++a) t -= S_[j * r + a] * S_[j * r + a];
        S_[j * r + j] = sqrt(t);
        for (i = j + 1; i < r; ++i) {
            for (u = S_[i * r + j], a = 0; a < j; ++a) u -= S_[i * r + a] * S_[j * r + a];
            S_[i * r + j] = u / S_[j * r + j];
        }
    }
    for (i = 0; i < r; ++i) { /* the innovation (z = 0) */
        for (t = 0.0, a = 0; a < n; ++a) t -= H_[i * n + a] * x[a];
        v_[i] = t;
    }
    for (i = 0; i < r; ++i) { /* L^-1 on the innovation and on H P */
        for (a = 0; a < i; ++a) {
            v_[i] -= S_[i * r + a] * v_[a];
            for (j = 0; j < n; ++j) HP_[i * n + j] -= S_[i * r + a] * HP_[a * n + j];
        }
        v_[i] /= S_[i * r + i];
        for (j = 0; j < n; ++j) HP_[i * n + j] /= S_[i * r + i];
    }
    for (i = 0; i < n; ++i) { /* x += (L^-1 H P)^T L^-1 v, P -= (L^-1 H P)^T (L^-1 H P) */
        for (t = 0.0, a = 0; a < r; ++a) t += HP_[a * n + i] * v_[a];
        x[i] += t;
    }
    for (i = 0; i < n; ++i)
        for (j = 0; j <= i; ++j) {
            for (t = 0.0, a = 0; a < r; ++a) t += HP_[a * n + i] * HP_[a * n + j];
            P[i * n + j] -= t;
            P[j * n + i] = P[i * n + j];
        }
}

/* the baseline's seconds for `reps` replays of `steps` steps of nodes with rows[j] measurement rows each */
static double plain_ekf(const int *rows, int steps, int reps) {
    static double x[CFD_NODES][CFD_NX], P[CFD_NODES][CFD_NX * CFD_NX];
    struct timespec t0, t1;
    int i, j, k, r;
    unsigned long seed = 12345;
    for (i = 0; i < CFD_NX * CFD_NX; ++i) {
        F_[i] = (i % (CFD_NX + 1) == 0) ? 1.0 : 0.01;
        Q_[i] = (i % (CFD_NX + 1) == 0) ? 0.01 : 0.0;
    }
    for (i = 0; i < EKF_ROWS * CFD_NX; ++i) {
        seed = seed * 6364136223846793005UL + 1442695040888963407UL;
        H_[i] = (double)(seed >> 40) / (double)(1UL << 24) - 0.5;
    }
    clock_gettime(CLOCK_MONOTONIC, &t0);
    for (r = 0; r < reps; ++r) {
        for (j = 0; j < CFD_NODES; ++j) {
            for (i = 0; i < CFD_NX; ++i) x[j][i] = 1.0;
            for (i = 0; i < CFD_NX * CFD_NX; ++i) P[j][i] = (i % (CFD_NX + 1) == 0) ? 1.0 : 0.0;
        }
        for (k = 0; k < steps; ++k)
            for (j = 0; j < CFD_NODES; ++j) ekf_step(x[j], P[j], rows[j] < EKF_ROWS ? rows[j] : EKF_ROWS);
    }
    clock_gettime(CLOCK_MONOTONIC, &t1);
    if (!(x[0][0] == x[0][0])) return -1.0;
    return (t1.tv_sec - t0.tv_sec) + 1e-9 * (t1.tv_nsec - t0.tv_nsec);
}

/* what the benchmark reads: the seconds the timed steps took, how many node steps, a node's state's size, and the
 * baseline's seconds for the same steps (rows[j]: node j's measurement rows) */
static int report(const struct timespec *t0, const struct timespec *t1, int calls, const int *rows, int steps,
                  int reps) {
    printf("%.9g %d\n", (t1->tv_sec - t0->tv_sec) + 1e-9 * (t1->tv_nsec - t0->tv_nsec), calls);
    printf("%d\n", (int)sizeof(cfd_node));
    printf("%.9g\n", plain_ekf(rows, steps, reps));
    return 0;
}
"""

_BENCH_C = r"""

int main(int argc, char **argv) {
    FILE *fh = fopen(argv[1], "r");
    int reps = atoi(argv[2]), steps, count, nu, k, j, b, r, total = 0, pos = 0;
    static cfd_node nodes[CFD_NODES];
    double *buf;
    struct timespec t0, t1;
    if (!fh || fscanf(fh, "%d %d %d", &steps, &count, &nu) != 3) return 2;
    buf = malloc(sizeof(double) * (size_t)steps * CFD_NODES * (3 * CFD_ROWS_MAX + CFD_BALL_MAX + CFD_NU
                                                                + CFD_NX + CFD_NX * CFD_NX));
    for (k = 0; k < steps; ++k)
        for (j = 0; j < CFD_NODES; ++j) {
            const int *ball;
            int nb = cfd_ball(cfd_exported_node(j), &ball), m = 0;
            for (b = 0; b < nb; ++b) m += cfd_sensor_dim(ball[b]);
            m += (nb - 1) + CFD_NU + CFD_NX + CFD_NX * CFD_NX;
            if (skip_tolerances(fh)) return 2;
            for (b = 0; b < m; ++b)
                if (fscanf(fh, "%lf", &buf[total + b]) != 1) return 2;
            total += m;
        }
    clock_gettime(CLOCK_MONOTONIC, &t0);
    for (r = 0; r < reps; ++r) {
        pos = 0;
        for (j = 0; j < CFD_NODES; ++j) cfd_init(&nodes[j], cfd_exported_node(j));
        for (k = 0; k < steps; ++k)
            for (j = 0; j < CFD_NODES; ++j) {
                const int *ball;
                int nb = cfd_ball(nodes[j].node, &ball), mo = cfd_sensor_dim(ball[0]), mr = 0;
                unsigned char arrived[CFD_BALL_MAX];
                for (b = 1; b < nb; ++b) mr += cfd_sensor_dim(ball[b]);
                for (b = 0; b < nb - 1; ++b) arrived[b] = buf[pos + mo + b] != 0.0;
                if (cfd_step(&nodes[j], buf + pos, arrived, buf + pos + mo + nb - 1, buf + pos + mo + nb - 1 + mr))
                    return 1;
                pos += mo + (nb - 1) + mr + CFD_NU + CFD_NX + CFD_NX * CFD_NX;
            }
    }
    clock_gettime(CLOCK_MONOTONIC, &t1);
    {
        static int rows[CFD_NODES]; /* the ball's rows */
        for (j = 0; j < CFD_NODES; ++j) {
            const int *ball;
            int nb = cfd_ball(cfd_exported_node(j), &ball);
            rows[j] = 0;
            for (b = 0; b < nb; ++b) rows[j] += cfd_sensor_dim(ball[b]);
        }
        return report(&t0, &t1, steps * CFD_NODES * reps, rows, steps, reps);
    }
}
"""


_BENCH_EXCHANGE = r"""
/* a record's beginning for a node that exchanges packets: its tolerances in make test (skipped), the step's inputs,
 * its measurement, one arrived flag per in-neighbour, into the slots of record `at`; returns its number of
 * in-neighbours, -1 for a short replay */
static int read_node_step(FILE *fh, int at, int node, double *u, double *z, unsigned char *arrived) {
    const int *senders;
    int d = cfd_neighbours(node, &senders), m = cfd_sensor_dim(node), b, c;
    double v;
    if (skip_tolerances(fh)) return -1;
    for (c = 0; c < CFD_NU; ++c) if (fscanf(fh, "%lf", &u[at * (CFD_NU + 1) + c]) != 1) return -1;
    for (c = 0; c < m; ++c) if (fscanf(fh, "%lf", &z[at * (CFD_NZ + 1) + c]) != 1) return -1;
    for (b = 0; b < d; ++b) {
        if (fscanf(fh, "%lf", &v) != 1) return -1;
        arrived[at * CFD_DEG_MAX + b] = v != 0.0;
    }
    return d;
}
"""

_BENCH_PAPER_C = r"""

#define NN (CFD_NX * CFD_NX)

int main(int argc, char **argv) {
    FILE *fh = fopen(argv[1], "r");
    int reps = atoi(argv[2]), steps, count, nu, k, j, b, c, r;
    static cfd_node nodes[CFD_NODES];
    cfd_packet *bounds, mine;
    double *u, *z, *rec;
    unsigned char *arrived;
    double skip;
    struct timespec t0, t1;
    if (!fh || fscanf(fh, "%d %d %d", &steps, &count, &nu) != 3) return 2;
    u = malloc(sizeof(double) * (size_t)steps * CFD_NODES * (CFD_NU + 1));
    z = malloc(sizeof(double) * (size_t)steps * CFD_NODES * (CFD_NZ + 1));
    rec = malloc(sizeof(double) * (size_t)steps * CFD_NODES * CFD_DEG_MAX * CFD_NX);
    arrived = malloc((size_t)steps * CFD_NODES * CFD_DEG_MAX);
    bounds = malloc(sizeof(cfd_packet) * (size_t)steps * CFD_NODES * CFD_DEG_MAX);
    for (k = 0; k < steps; ++k)
        for (j = 0; j < CFD_NODES; ++j) {
            const int at = k * CFD_NODES + j;
            int d = read_node_step(fh, at, cfd_exported_node(j), u, z, arrived);
            double v;
            if (d < 0) return 2;
            for (c = 0; c < d * CFD_NX; ++c)
                if (fscanf(fh, "%lf", &rec[at * CFD_DEG_MAX * CFD_NX + c]) != 1) return 2;
            for (b = 0; b < d; ++b) {
                cfd_packet *p = &bounds[at * CFD_DEG_MAX + b];
                for (c = 0; c < NN; ++c) if (fscanf(fh, "%lf", &p->P[c]) != 1) return 2;
                if (fscanf(fh, "%lf", &v) != 1) return 2;
                p->ok = v != 0.0;
            }
            for (c = 0; c < 2 * (CFD_NX + NN) + 1; ++c) if (fscanf(fh, "%lf", &skip) != 1) return 2;
        }
    clock_gettime(CLOCK_MONOTONIC, &t0);
    for (r = 0; r < reps; ++r) {
        for (j = 0; j < CFD_NODES; ++j) cfd_init(&nodes[j], cfd_exported_node(j));
        for (k = 0; k < steps; ++k)
            for (j = 0; j < CFD_NODES; ++j) {
                const int at = k * CFD_NODES + j;
                if (cfd_predict(&nodes[j], CFD_NU ? u + at * (CFD_NU + 1) : NULL, &mine)
                        || cfd_update(&nodes[j], z + at * (CFD_NZ + 1), arrived + at * CFD_DEG_MAX,
                                      rec + at * CFD_DEG_MAX * CFD_NX, bounds + at * CFD_DEG_MAX))
                    return 1;
            }
    }
    clock_gettime(CLOCK_MONOTONIC, &t1);
    {
        static int rows[CFD_NODES]; /* its own measurement's */
        for (j = 0; j < CFD_NODES; ++j) rows[j] = cfd_sensor_dim(cfd_exported_node(j));
        return report(&t0, &t1, steps * CFD_NODES * reps, rows, steps, reps);
    }
}
"""


_BENCH_SCHEDULED_C = r"""

int main(int argc, char **argv) {
    FILE *fh = fopen(argv[1], "r");
    int reps = atoi(argv[2]), steps, count, nu, k, j, b, c, r, rr;
    static cfd_node nodes[CFD_NODES];
    cfd_packet *got, mine;
    double *u, *z, *later, skip;
    unsigned char *arrived;
    struct timespec t0, t1;
    if (!fh || fscanf(fh, "%d %d %d", &steps, &count, &nu) != 3) return 2;
    u = malloc(sizeof(double) * (size_t)steps * CFD_NODES * (CFD_NU + 1));
    z = malloc(sizeof(double) * (size_t)steps * CFD_NODES * (CFD_NZ + 1));
    got = malloc(sizeof(cfd_packet) * (size_t)steps * CFD_NODES * CFD_DEG_MAX);
    arrived = malloc((size_t)steps * CFD_NODES * CFD_DEG_MAX);
    later = malloc(sizeof(double) * (size_t)steps * CFD_NODES * CFD_ROUNDS * CFD_DEG_MAX * CFD_NX);
    for (k = 0; k < steps; ++k)
        for (j = 0; j < CFD_NODES; ++j) {
            const int at = k * CFD_NODES + j;
            int d = read_node_step(fh, at, cfd_exported_node(j), u, z, arrived);
            if (d < 0) return 2;
            for (b = 0; b < d; ++b)
                for (c = 0; c < CFD_NX; ++c) if (fscanf(fh, "%lf", &got[at * CFD_DEG_MAX + b].x[c]) != 1) return 2;
            for (b = 0; b < d && CFD_EXCHANGE; ++b)
                for (c = 0; c < CFD_NZMAX; ++c) if (fscanf(fh, "%lf", &got[at * CFD_DEG_MAX + b].z[c]) != 1) return 2;
            for (r = 2; r <= CFD_ROUNDS; ++r)
                for (c = 0; c < d * CFD_NX; ++c)
                    if (fscanf(fh, "%lf", &later[((size_t)at * CFD_ROUNDS + r) * CFD_DEG_MAX * CFD_NX + c]) != 1)
                        return 2;
            for (c = 0; c < CFD_NX + CFD_NX * CFD_NX; ++c) if (fscanf(fh, "%lf", &skip) != 1) return 2;
        }
    clock_gettime(CLOCK_MONOTONIC, &t0);
    for (rr = 0; rr < reps; ++rr) {
        for (j = 0; j < CFD_NODES; ++j) cfd_init(&nodes[j], cfd_exported_node(j));
        for (k = 0; k < steps; ++k)
            for (j = 0; j < CFD_NODES; ++j) {
                const int at = k * CFD_NODES + j;
                if (cfd_predict(&nodes[j], z + at * (CFD_NZ + 1), CFD_NU ? u + at * (CFD_NU + 1) : NULL, &mine)
                        || cfd_update(&nodes[j], arrived + at * CFD_DEG_MAX, got + at * CFD_DEG_MAX))
                    return 1;
                for (r = 2; r <= CFD_ROUNDS; ++r)
                    if (cfd_round(&nodes[j], later + ((size_t)at * CFD_ROUNDS + r) * CFD_DEG_MAX * CFD_NX)) return 1;
            }
    }
    clock_gettime(CLOCK_MONOTONIC, &t1);
    {
        static int rows[CFD_NODES]; /* its innovations: its measurement's, per link its estimate's (and measurement) */
        for (j = 0; j < CFD_NODES; ++j) {
            const int *senders;
            int d = cfd_neighbours(cfd_exported_node(j), &senders);
            rows[j] = cfd_sensor_dim(cfd_exported_node(j)) + d * (CFD_NX + (CFD_EXCHANGE ? CFD_NZMAX : 0));
        }
        return report(&t0, &t1, steps * CFD_NODES * reps, rows, steps, reps);
    }
}
"""


def _size(objects: list[Path]) -> tuple[int, int]:
    """(text, data + bss) bytes of the object files (``size``; without it, the files' sizes and 0)."""
    tool = shutil.which("size")
    if tool is None:
        return sum(p.stat().st_size for p in objects), 0
    out = subprocess.run([tool, *map(str, objects)], capture_output=True, text=True, check=True).stdout
    text = data = 0
    for line in out.splitlines()[1:]:
        cols = line.split()
        text, data = text + int(cols[0]), data + int(cols[1]) + int(cols[2])
    return text, data


def measure(scenario: str, mode: str, repeat: int, folder: Path) -> dict:
    import studies
    from designer.export_c import REPLAY_TOLERANCES

    design, c = folder / "design", folder / "c"
    studies.design(scenario, mode=mode, out=design)
    studies.export(design, out=c)
    cc = shutil.which("cc") or shutil.which("gcc")
    driver = {"paper": _BENCH_EXCHANGE + _BENCH_PAPER_C, "scheduled": _BENCH_EXCHANGE + _BENCH_SCHEDULED_C}
    (c / "bench.c").write_text(f"#define TOLERANCES {REPLAY_TOLERANCES}\n" + _BENCH_HEAD + driver.get(mode, _BENCH_C))
    for src in ("cfd_node.c", "cfd_model.c"):
        subprocess.run([cc, "-std=c99", "-O3", "-c", src], cwd=c, check=True)
    subprocess.run([cc, "-std=c99", "-O3", "-o", "bench", "bench.c", "cfd_node.o", "cfd_model.o", "-lm"], cwd=c,
                   check=True)
    c_us, ekf_us = [], []
    for _ in range(3):  # the best of three: the machine is shared
        run = subprocess.run(["./bench", "replay.txt", str(repeat)], cwd=c, capture_output=True, text=True,
                             check=True)
        timing, state, ekf = run.stdout.split("\n")[:3]
        secs, calls = timing.split()
        c_us.append(float(secs) / int(calls) * 1e6)
        ekf_us.append(float(ekf) / int(calls) * 1e6)
    c_us, ekf_us = min(c_us), min(ekf_us)
    text, data = _size([c / "cfd_node.o", c / "cfd_model.o"])
    # Python: the same steps through the node filters (inputs prepared first: the C replays the steps replay.txt
    # holds, so does Python)
    steps = int((c / "replay.txt").read_text().split(None, 1)[0])
    sim = studies.simulate(scenario, seed=0)
    from filters.consensus_batch import EdgeAttacks

    net = studies.node_filter(scenario, schedule=design)
    att = EdgeAttacks.from_patterns(net.network, [sim.attacks])
    given = []  # per step and node what the node is fed: computed by the network's step (its last exchange)
    for k in range(steps):
        net.step(sim.z[k], att.dos[0, k], att.fdi[0, k], att.xi[0, k], u=sim.inputs[k])
        _, rounds = net.last
        z_of = [sim.z[k, net.model.sensor_rows(i)] for i in range(len(net.nodes))]
        if mode == "paper":
            given.append([(z_of[i], *rounds[0][i]) for i in range(len(z_of))])
        elif mode == "scheduled":
            given.append([(z_of[i], [r[i] for r in rounds]) for i in range(len(z_of))])
        else:
            given.append(rounds[0])
    py_secs = []
    for _ in range(3):  # the best of three
        fresh = studies.node_filter(scenario, schedule=design)  # built outside the timing, as the C nodes are
        t0 = time.perf_counter()
        for k, per_node in enumerate(given):
            for nd, args in zip(fresh.nodes, per_node):
                if mode == "paper":
                    nd.predict(sim.inputs[k])
                    nd.update(*args)
                elif mode == "scheduled":
                    nd.predict(args[0], sim.inputs[k])
                    nd.update(args[1][0])
                    for got in args[1][1:]:
                        nd.round(got)
                else:
                    nd.step(*args, sim.inputs[k])
        py_secs.append(time.perf_counter() - t0)
    py_us = min(py_secs) / (len(given) * len(net.nodes)) * 1e6
    return {"scenario": scenario, "mode": mode, "nodes": len(net.nodes), "steps": len(given), "c_us": c_us,
            "python_us": py_us, "ratio": py_us / c_us, "ekf_us": ekf_us, "code_bytes": text, "static_bytes": data,
            "state_bytes": int(state)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="indoor-robot")
    ap.add_argument("--field", metavar="RxC", help="in place of --scenario: benchmarks/models/heat_field.py with "
                                                  "ROWS, COLS = R, C (a node at size: R C states)")
    ap.add_argument("--mode", nargs="+", default=["relay"], choices=("relay", "flood", "paper", "scheduled"))
    ap.add_argument("--repeat", type=int, default=200, help="replays of the run per C timing")
    ap.add_argument("--check", action="store_true")
    ap.add_argument("--min-ratio", type=float, default=TARGET_RATIO,
                    help=f"--check: the least Python / C ratio [default: {TARGET_RATIO:g}]")
    ap.add_argument("--ekf-max", type=float, default=None,
                    help="--check: the most node / plain EKF ratio [default: not checked]")
    a = ap.parse_args(argv)
    from designer.cores import one_blas_thread

    failed = 0
    for mode in a.mode:
        with tempfile.TemporaryDirectory() as tmp, one_blas_thread():
            scenario = a.scenario
            if a.field:
                from bench_design_scale import field_file

                rows, cols = (int(v) for v in a.field.lower().split("x"))
                scenario = str(field_file(Path(tmp), rows, cols))
            r = measure(scenario, mode, a.repeat, Path(tmp))
        print(f"{r['scenario']} ({r['mode']}, {r['nodes']} nodes, {r['steps']} steps): one node step in C "
              f"{r['c_us']:.2f} us, in Python {r['python_us']:.1f} us: {r['ratio']:.0f} x (target >= "
              f"{TARGET_RATIO:g}); a plain EKF step with as many states and rows {r['ekf_us']:.2f} us: the node "
              f"{r['c_us'] / r['ekf_us']:.1f} x (issue 41: <= {EKF_TARGET:g})")
        print(f"exported code {r['code_bytes']} bytes of text (the design's tables for {r['nodes']} nodes included); "
              f"static data {r['static_bytes']} bytes (the model's function tables); a node's state and work "
              f"{r['state_bytes']} bytes")
        if a.check and not r["ratio"] >= a.min_ratio:
            print(f"FAIL: the C step is {r['ratio']:.1f} x the Python node filter's, below {a.min_ratio:g}")
            failed = 1
        if a.check and a.ekf_max is not None and not r["c_us"] <= a.ekf_max * r["ekf_us"]:
            print(f"FAIL: the C step is {r['c_us'] / r['ekf_us']:.1f} x a plain EKF step of its states and rows, "
                  f"above {a.ekf_max:g}")
            failed = 1
    return failed


if __name__ == "__main__":
    sys.exit(main())
