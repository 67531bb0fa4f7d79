/* a flag (1 or 0) against Python's */
static void flag(cfd_tally *t, const char *what, int got, double want) {
    if ((got != 0) == (want != 0.0)) return;
    if (t->bad < REPORTED)
        printf("step %d, node %d: %s is %d in C, %d in Python\n", t->step, t->node, what, got != 0, want != 0.0);
    t->bad += 1;
}

/* one node's row of a step, as the replay gives it */
typedef struct {
    double tol[TOLERANCES];
    CFD_REAL u[CFD_NU + 1], z[CFD_NZMAX], rec[CFD_DEG_MAX * CFD_NX];
    unsigned char arrived[CFD_DEG_MAX], falsified[CFD_DEG_MAX];
    cfd_packet bounds[CFD_DEG_MAX];                  /* every in-neighbour's packet: its bound and flag */
    double px[CFD_NX], pP[CFD_NX * CFD_NX], pok[1]; /* the Python node's packet */
    double x[CFD_NX], P[CFD_NX * CFD_NX];           /* its estimate and covariance after the update */
} replay_row;

/* read node `node`'s row into `r`: 0, or -1 for a replay that ended */
static int read_row(FILE *fh, replay_row *r, int node) {
    const int *senders;
    CFD_REAL flags[CFD_DEG_MAX];
    double ok[1];
    int d = cfd_neighbours(node, &senders), b;
    if (read_tolerances(fh, r->tol) || read_reals(fh, r->u, CFD_NU) || read_reals(fh, r->z, cfd_sensor_dim(node))
            || read_reals(fh, flags, d) || read_reals(fh, r->rec, d * CFD_NX))
        return -1;
    for (b = 0; b < d; ++b) {
        if (read_reals(fh, r->bounds[b].P, CFD_NX * CFD_NX) || read_numbers(fh, ok, 1)) return -1;
        r->bounds[b].ok = ok[0] != 0.0;
    }
    arrivals(flags, d, r->arrived, r->falsified);
    return read_numbers(fh, r->px, CFD_NX) || read_numbers(fh, r->pP, CFD_NX * CFD_NX) || read_numbers(fh, r->pok, 1)
           || read_numbers(fh, r->x, CFD_NX) || read_numbers(fh, r->P, CFD_NX * CFD_NX) ? -1 : 0;
}

int main(int argc, char **argv) {
    static cfd_node nodes[CFD_NODES], net[CFD_NODES];
    static replay_row rows[CFD_NODES];
    static cfd_packet sent[CFD_NODES], bounds[CFD_DEG_MAX], mine;
    static CFD_REAL rec[CFD_DEG_MAX * CFD_NX];
    static cfd_tally t;
    FILE *fh;
    int steps, k, j, b, i;
    fh = start(argc, argv, nodes, net, &steps);
    if (!fh) return 2;
    for (k = 0; k < steps; ++k) {
        for (j = 0; j < CFD_NODES; ++j)
            if (read_row(fh, &rows[j], nodes[j].node)) return short_replay(argv[1], k, nodes[j].node);
        for (j = 0; j < CFD_NODES; ++j) { /* each node's step from the Python node's state */
            replay_row *r = &rows[j];
            int e = cfd_predict(&nodes[j], CFD_NU ? r->u : NULL, &mine);
            at_row(&t, k, nodes[j].node, r->tol, 1);
            if (e) {
                fprintf(stderr, "step %d, node %d: cfd_predict returned %d\n", k + 1, nodes[j].node, e);
                return 1;
            }
            flag(&t, "the prediction's bound flag", mine.ok, r->pok[0]);
            check(&t, 1, "x_pred", "P_pred", mine.x, mine.P, r->px, r->pP);
            e = cfd_update(&nodes[j], r->z, r->arrived, r->rec, r->bounds);
            if (e) {
                fprintf(stderr, "step %d, node %d: cfd_update returned %d\n", k + 1, nodes[j].node, e);
                return 1;
            }
            check(&t, 1, "x", "P", nodes[j].x, nodes[j].P, r->x, r->P);
            resync(nodes[j].x, nodes[j].P, r->x, r->P);
        }
        /* the network run: every node's packet first, then each node's update with its neighbours' */
        for (j = 0; j < CFD_NODES && !t.net_stopped; ++j) {
            int e = cfd_predict(&net[j], CFD_NU ? rows[j].u : NULL, &sent[j]);
            if (e) network_stops(&t, k, net[j].node, "cfd_predict", e);
        }
        for (j = 0; j < CFD_NODES && !t.net_stopped; ++j) {
            replay_row *r = &rows[j];
            const int *senders;
            int d = cfd_neighbours(net[j].node, &senders), e;
            for (b = 0; b < d; ++b) {
                int s = slot_of(senders[b]);
                const CFD_REAL *x = s >= 0 && r->arrived[b] && !r->falsified[b] ? sent[s].x : r->rec + b * CFD_NX;
                for (i = 0; i < CFD_NX; ++i) rec[b * CFD_NX + i] = x[i];
                bounds[b] = s >= 0 ? sent[s] : r->bounds[b];
            }
            e = cfd_update(&net[j], r->z, r->arrived, rec, bounds);
            if (e) {
                network_stops(&t, k, net[j].node, "cfd_update", e);
            } else {
                at_row(&t, k, net[j].node, r->tol, 0);
                check(&t, 0, "x", "P", net[j].x, net[j].P, r->x, r->P);
            }
        }
    }
    return finish(fh, steps, &t);
}
