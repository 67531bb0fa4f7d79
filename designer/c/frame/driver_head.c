/* cfd_test.c: replay a run through every exported node and compare with the Python node filter.
 *
 * Each step starts from the Python node's state after the step before (the node is re-synchronised: its estimate
 * and covariance are set to the replay's), so what is compared is one step of the C against one step of Python
 * from the same input, which two correct implementations agree on to rounding even where the recursion is chaotic.
 * Each entry is compared on its own scale: an estimate's component x[i] on max(|x[i]|, sqrt(P[i][i])), a
 * covariance's entry P[i][j] on max(|P[i][j]|, sqrt(P[i][i] P[j][j])) (Python's values), so small variances and
 * cross terms are checked as closely as large ones.  Each row of the replay starts with its tolerances, a double
 * node's and a float node's (-DCFD_REAL=float): TOL (TOL scaled to float's rounding), or where the step itself is
 * ill-conditioned (Python measured how far it carries changes of its input by one unit of double's, of float's
 * rounding, and a float node's rank decisions) a multiple of that sensitivity, a double's at most TOL_CAP.  A
 * difference above the tolerance fails, naming the step, the node, the quantity and both values.  A second set of
 * nodes runs on its own, never re-synchronised, on the same inputs; how far it drifts is reported as information. */
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
    int step, node;    /* 1-based step, the network's node number */
    double tol;        /* this step's and node's tolerance (the replay row's first number) */
    double worst;      /* the largest difference relative to its entry's scale */
    double worst_tol;  /* the largest tolerance a step needed */
    int bad;           /* entries above their tolerance */
    double free_worst; /* the free-running nodes' largest difference (information) */
} cfd_tally;

/* start a row of the replay: its step, node and tolerance, the double's or the float's (0 or -1 for a replay that
 * ended) */
static int row(FILE *fh, cfd_tally *t, int k, int node) {
    double tol[2];
    if (read_numbers(fh, tol, 2) || !(tol[0] >= TOL && tol[0] <= TOL_CAP) || !(tol[1] >= TOL * PRECISION)
        || !(tol[1] < HUGE_VAL))
        return -1;
    t->step = k + 1;
    t->node = node;
    t->tol = tol[FLOAT_NODE ? 1 : 0];
    if (t->tol > t->worst_tol) t->worst_tol = t->tol;
    return 0;
}

static double scaled_difference(double got, double want, double scale) {
    if (got == want) return 0.0;
    return scale > 0.0 && fabs(got - want) == fabs(got - want) ? fabs(got - want) / scale : HUGE_VAL;
}

/* an entry's scale: the estimate's x[i] (j < 0) on max(|x[i]|, sqrt(P[i][i])), the covariance's P[i][j] on
 * max(|P[i][j]|, sqrt(P[i][i] P[j][j])), Python's values */
static double scale_of(const double *xw, const double *Pw, int i, int j) {
    double a = j < 0 ? fabs(xw[i]) : fabs(Pw[i * CFD_NC + j]);
    double c = sqrt(fabs(Pw[i * CFD_NC + i] * Pw[(j < 0 ? i : j) * CFD_NC + (j < 0 ? i : j)]));
    return a > c ? a : c;
}

/* one entry (index i, and j >= 0 for a matrix's) against Python's value on its scale: a failure is named; with
 * `counted` 0 (the free-running nodes) only the largest difference is kept, as information */
static void entry(cfd_tally *t, int counted, const char *what, int i, int j, double got, double want,
                  double scale) {
    double d = scaled_difference(got, want, scale);
    double *worst = counted ? &t->worst : &t->free_worst;
    if (d > *worst) *worst = d;
    if (!counted || d <= t->tol) return;
    if (t->bad < REPORTED) {
        if (j < 0)
            printf("step %d, node %d: %s[%d] is %.17g in C, %.17g in Python (difference %.3g of its scale %.3g)\n",
                   t->step, t->node, what, i, got, want, fabs(got - want), scale);
        else
            printf("step %d, node %d: %s[%d][%d] is %.17g in C, %.17g in Python (difference %.3g of its scale "
                   "%.3g)\n", t->step, t->node, what, i, j, got, want, fabs(got - want), scale);
    }
    t->bad += 1;
}

/* an estimate (or prediction) and its covariance against the Python node filter's, entry by entry, named x_name and
 * P_name in a failure ("x"/"P" the estimate, "x_pred"/"P_pred" a prediction); counted 0: the free-running nodes */
static void check(cfd_tally *t, int counted, const char *x_name, const char *P_name, const CFD_REAL *x,
                  const CFD_REAL *P, const double *xw, const double *Pw) {
    int i, j;
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

static int finish(FILE *fh, int steps, const cfd_tally *t) {
    fclose(fh);
    printf("%d steps x %d nodes, each step from the Python node's state: largest difference from the Python node "
           "filter %.3g (of each entry's scale), %d above the tolerance (%g; at most %.3g where a step is "
           "ill-conditioned)\n", steps, CFD_NODES, t->worst, t->bad, TOL * PRECISION, t->worst_tol);
    printf("information: the nodes left to run on their own, never re-synchronised, differ from Python by at most "
           "%.3g of each entry's scale over the %d steps\n", t->free_worst, steps);
    return t->bad ? 1 : 0;
}

/* a replay that ends before its header's steps and nodes: exit 2 */
static int short_replay(const char *name, int k, int node) {
    fprintf(stderr, "%s: short at step %d, node %d\n", name, k + 1, node);
    return 2;
}

/* open the replay named on the command line, check it is one of these nodes, start every node (and its free
 * twin) at the prior */
static FILE *start(int argc, char **argv, cfd_node *nodes, cfd_node *free_nodes, int *steps) {
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
        if (cfd_init(&nodes[j], cfd_exported_node(j)) || cfd_init(&free_nodes[j], cfd_exported_node(j)))
            return NULL;
    return fh;
}
