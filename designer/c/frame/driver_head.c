/* cfd_test.c: replay a run through every exported node and compare with the Python node filter, two ways.
 *
 * Step by step: each step starts from the Python node's state after the step before (the node is re-synchronised:
 * its estimate and covariance are set to the replay's), so what is compared is one step of the C against one step of
 * Python from the same input, which two correct implementations agree on to rounding even where the recursion is
 * chaotic.  Each entry is compared on its own scale: an estimate's component x[i] on max(|x[i]|, sqrt(P[i][i])), a
 * covariance's entry P[i][j] on max(|P[i][j]|, sqrt(P[i][i] P[j][j])) (Python's values), so small variances and
 * cross terms are checked as closely as large ones.  Each row of the replay starts with its tolerances: the step's, a
 * double node's and a float node's (-DCFD_REAL=float): TOL (TOL scaled to float's rounding), or where the step
 * itself is ill-conditioned (Python measured how far it carries changes of its input by one unit of double's, of
 * float's rounding, and a float node's rank decisions) a multiple of that sensitivity, a double's at most TOL_CAP,
 * or inf where it would need more (no check tells code from rounding there: that node step is information, counted
 * and reported, and the steps after it are checked from Python's state again); then the network run's, a double's
 * and a float's.  A difference above the tolerance fails, naming the step, the
 * node, the quantity and both values.
 *
 * As a network: a second set of nodes runs from the prior on its own, never re-synchronised, each node taking what
 * the other C nodes send it over the log's arrivals (a packet that arrived as sent is its sender's C packet, a
 * falsified one the log's; a sender not exported: the log's).  It is compared with the Python node network, whose
 * numbers are the batched filter's, at the network run's tolerance: the drift that rounding alone gives perturbed
 * copies of the Python network, run from the start (times the same safety factor), at least TOL.  Where that drift
 * passes NET_CAP (a chaotic or ill-conditioned run), the replay's tolerance is inf and the network run is reported
 * as information from there on. */
#include <float.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>

#include "cfd_node.h"

#ifndef CFD_NC
#define CFD_NC CFD_NX /* a node's estimate's length: the states it carries (a kind whose nodes carry the whole state) */
#endif

#define TOL @TOL@
#define TOL_CAP @TOL_CAP@
#define NET_CAP @NET_CAP@
#define TOLERANCES @TOLERANCES@ /* a row's tolerances: the step's (double, float), the network run's (double, float) */
#define REPORTED 10 /* failures printed in full; the rest are counted */
/* a float node (-DCFD_REAL=float): the rows' second tolerance, at least TOL as much looser as its rounding */
#define FLOAT_NODE (sizeof(CFD_REAL) < sizeof(double))
#define PRECISION ((double)(FLOAT_NODE ? FLT_EPSILON / DBL_EPSILON : 1.0))

static int read_numbers(FILE *fh, double *v, int count) {
    int i;
    for (i = 0; i < count; ++i)
        if (fscanf(fh, "%lf", &v[i]) != 1) return -1;
    return 0;
}

/* numbers the node takes (its inputs, what reached it), as CFD_REAL */
static int read_reals(FILE *fh, CFD_REAL *v, int count) {
    int i;
    double t;
    for (i = 0; i < count; ++i) {
        if (fscanf(fh, "%lf", &t) != 1) return -1;
        v[i] = (CFD_REAL)t;
    }
    return 0;
}

/* what a comparison is of, and what it found so far */
typedef struct {
    int step, node;     /* 1-based step, the network's node number */
    double tol;         /* this step's and node's tolerance from Python's state */
    double net_tol;     /* the network run's (HUGE_VAL: information only) */
    double worst;       /* the largest difference relative to its entry's scale */
    double worst_tol;   /* the largest tolerance a step needed */
    int bad;            /* entries above their tolerance */
    int info_rows;      /* node steps too ill-conditioned to check from Python's state (tolerance inf) */
    int info_step, info_node; /* the first of them (1-based step, node; 0: none) */
    double info;        /* their largest difference */
    double net_worst;   /* the network run's largest difference where it is checked */
    double net_worst_tol; /* its largest tolerance */
    int net_bad;        /* its entries above their tolerance */
    int net_rows;       /* the network run's node steps compared */
    int net_info_rows;  /* those of them information only */
    int net_info_from;  /* the first step (1-based) where the network run is information only (0: none) */
    double net_info;    /* its largest difference from there */
    int net_stopped;    /* the step (1-based) where a node of the network run returned an error (0: none) */
} cfd_tally;

/* read a row's tolerances (TOLERANCES numbers); -1 for a replay that ended or tolerances out of their range */
static int read_tolerances(FILE *fh, double *tol) {
    if (read_numbers(fh, tol, TOLERANCES) || !(tol[0] >= TOL && (tol[0] <= TOL_CAP || tol[0] == HUGE_VAL))
        || !(tol[1] >= TOL * PRECISION) || !(tol[1] < HUGE_VAL || tol[0] == HUGE_VAL)
        || !(tol[2] >= TOL) || !(tol[2] <= NET_CAP || tol[2] == HUGE_VAL)
        || !(tol[3] >= TOL * PRECISION) || !(tol[3] <= NET_CAP || tol[3] == HUGE_VAL))
        return -1;
    return 0;
}

/* the row of step k (0-based) and node `node` with its tolerances `tol` (read_tolerances): the comparisons that
 * follow are of it; `counted` 1 for its step from Python's state (its row counted once), 0 for the network run's */
static void at_row(cfd_tally *t, int k, int node, const double *tol, int counted) {
    t->step = k + 1;
    t->node = node;
    t->tol = tol[FLOAT_NODE ? 1 : 0];
    t->net_tol = tol[FLOAT_NODE ? 3 : 2];
    if (!counted) return;
    if (t->tol == HUGE_VAL) { /* too ill-conditioned to check: information */
        t->info_rows += 1;
        if (!t->info_step) {
            t->info_step = t->step;
            t->info_node = node;
        }
    } else if (t->tol > t->worst_tol) {
        t->worst_tol = t->tol;
    }
}

/* a replay row's d arrival flags (designer.export_c.arrival_flag: 0 lost, 1 arrived as sent, 2 arrived falsified) as
 * which arrived and, unless `falsified` is NULL, which of them were falsified */
static void arrivals(const CFD_REAL *flags, int d, unsigned char *arrived, unsigned char *falsified) {
    int b;
    for (b = 0; b < d; ++b) {
        arrived[b] = flags[b] != 0.0;
        if (falsified) falsified[b] = flags[b] == 2.0;
    }
}

#ifdef CFD_DEG_MAX /* nodes that exchange packets with their in-neighbours (a relay node takes measurements only) */
/* the exported slot of the network's node `node`, -1 for a node not exported */
static int slot_of(int node) {
    int j;
    for (j = 0; j < CFD_NODES; ++j)
        if (cfd_exported_node(j) == node) return j;
    return -1;
}
#endif

static double scaled_difference(double got, double want, double scale) {
    if (got == want) return 0.0;
    return scale > 0.0 && fabs(got - want) == fabs(got - want) ? fabs(got - want) / scale : HUGE_VAL;
}

/* an entry's scale: the estimate's x[i] (j < 0) on max(|x[i]|, sqrt(P[i][i])), the covariance's P[i][j] on
 * max(|P[i][j]|, sqrt(P[i][i] P[j][j])), Python's values */
static double scale_of(const double *xw, const double *Pw, int i, int j) {
    double a = j < 0 ? fabs(xw[i]) : fabs(Pw[i * CFD_NC + j]);
    double c = j < 0 ? sqrt(fabs(Pw[i * CFD_NC + i])) : sqrt(fabs(Pw[i * CFD_NC + i] * Pw[j * CFD_NC + j]));
    return a > c ? a : c;
}

/* one entry (index i, and j >= 0 for a matrix's) against Python's value on its scale: `counted` 1 a step from
 * Python's state, 0 the network run (checked at its tolerance, or kept as information); a failure is named */
static void entry(cfd_tally *t, int counted, const char *what, int i, int j, double got, double want,
                  double scale) {
    double d = scaled_difference(got, want, scale), tol = counted ? t->tol : t->net_tol;
    double *worst = counted ? (tol < HUGE_VAL ? &t->worst : &t->info) : tol < HUGE_VAL ? &t->net_worst : &t->net_info;
    if (d > *worst) *worst = d;
    if (d <= tol) return;
    if ((counted ? t->bad : t->net_bad) < REPORTED) {
        if (j < 0)
            printf("%sstep %d, node %d: %s[%d] is %.17g in C, %.17g in Python (difference %.3g of its scale %.3g)\n",
                   counted ? "" : "network run, ", t->step, t->node, what, i, got, want, fabs(got - want), scale);
        else
            printf("%sstep %d, node %d: %s[%d][%d] is %.17g in C, %.17g in Python (difference %.3g of its scale "
                   "%.3g)\n", counted ? "" : "network run, ", t->step, t->node, what, i, j, got, want,
                   fabs(got - want), scale);
    }
    if (counted)
        t->bad += 1;
    else
        t->net_bad += 1;
}

/* an estimate (or prediction) and its covariance against the Python node filter's, entry by entry, named x_name and
 * P_name in a failure ("x"/"P" the estimate, "x_pred"/"P_pred" a prediction); counted 0: the network run */
static void check(cfd_tally *t, int counted, const char *x_name, const char *P_name, const CFD_REAL *x,
                  const CFD_REAL *P, const double *xw, const double *Pw) {
    int i, j;
    if (!counted) {
        t->net_rows += 1;
        if (t->net_tol == HUGE_VAL) {
            t->net_info_rows += 1;
            if (!t->net_info_from) t->net_info_from = t->step;
        } else if (t->net_tol > t->net_worst_tol) {
            t->net_worst_tol = t->net_tol;
        }
    }
    for (i = 0; i < CFD_NC; ++i) entry(t, counted, x_name, i, -1, x[i], xw[i], scale_of(xw, Pw, i, -1));
    for (i = 0; i < CFD_NC; ++i)
        for (j = 0; j < CFD_NC; ++j)
            entry(t, counted, P_name, i, j, P[i * CFD_NC + j], Pw[i * CFD_NC + j], scale_of(xw, Pw, i, j));
}

/* set a node's estimate and covariance to Python's after the step: the next step starts from the same input */
static void resync(CFD_REAL *x, CFD_REAL *P, const double *xw, const double *Pw) {
    int i;
    for (i = 0; i < CFD_NC; ++i) x[i] = (CFD_REAL)xw[i];
    for (i = 0; i < CFD_NC * CFD_NC; ++i) P[i] = (CFD_REAL)Pw[i];
}

/* a node of the network run returned `e` at step k (0-based): the network run stops there */
static void network_stops(cfd_tally *t, int k, int node, const char *call, int e) {
    if (!t->net_stopped)
        printf("information: the network run stopped at step %d: node %d's %s returned %d\n", k + 1, node, call, e);
    t->net_stopped = k + 1;
}

static int finish(FILE *fh, int steps, const cfd_tally *t) {
    fclose(fh);
    printf("%d steps x %d nodes, each step from the Python node's state: largest difference from the Python node "
           "filter %.3g (of each entry's scale), %d above the tolerance (%g; at most %.3g where a step is "
           "ill-conditioned)\n", steps, CFD_NODES, t->worst, t->bad, TOL * PRECISION, t->worst_tol);
    printf("as a network (the nodes exchanging their own packets over the log's arrivals from the prior, never "
           "re-synchronised): largest difference from the Python node network %.3g (of each entry's scale), %d above "
           "its tolerance (rounding's drift: at most %.3g)\n", t->net_worst, t->net_bad, t->net_worst_tol);
    if (t->info_rows)
        printf("information: at %d of the %d node steps (the first at step %d, node %d) the step is too "
               "ill-conditioned for a check at %g of each entry's scale (changes of its input by one unit in the last "
               "place move it further: no check tells code from rounding), so they are not checked, and the steps "
               "after them are, from Python's state: their largest difference %.3g\n", t->info_rows,
               steps * CFD_NODES, t->info_step, t->info_node, TOL_CAP, t->info);
    if (t->net_info_rows)
        printf("information: at %d of its %d node steps (the first at step %d), rounding alone may carry the network "
               "run beyond %g of each entry's scale (a chaotic or ill-conditioned run, a float node's rank cuts), so "
               "they are not checked: their largest difference %.3g\n", t->net_info_rows, t->net_rows,
               t->net_info_from, NET_CAP, t->net_info);
    return t->bad || t->net_bad ? 1 : 0;
}

/* a replay that ends before its header's steps and nodes: exit 2 */
static int short_replay(const char *name, int k, int node) {
    fprintf(stderr, "%s: short at step %d, node %d\n", name, k + 1, node);
    return 2;
}

/* open the replay named on the command line, check it is one of these nodes, start every node (and its twin of the
 * network run) at the prior */
static FILE *start(int argc, char **argv, cfd_node *nodes, cfd_node *net, int *steps) {
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
        if (cfd_init(&nodes[j], cfd_exported_node(j)) || cfd_init(&net[j], cfd_exported_node(j)))
            return NULL;
    return fh;
}
