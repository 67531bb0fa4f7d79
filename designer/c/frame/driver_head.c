/* cfd_test.c: replay a run through every exported node and compare with the Python node filter. */
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
