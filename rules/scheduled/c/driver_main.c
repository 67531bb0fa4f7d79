/* one node's row of a step, as the replay gives it */
typedef struct {
    double tol[TOLERANCES];
    CFD_REAL u[CFD_NU + 1], z[CFD_NZMAX];
    unsigned char arrived[CFD_DEG_MAX], falsified[CFD_DEG_MAX];
    cfd_packet got[CFD_DEG_MAX];                                /* the first round's packets that arrived */
    CFD_REAL later[(CFD_ROUNDS > 1 ? CFD_ROUNDS - 1 : 1) * CFD_DEG_MAX * CFD_NX]; /* rounds 2..L's estimates */
    double x[CFD_NX], P[CFD_NX * CFD_NX]; /* the Python node's estimate and own covariance after the step */
} replay_row;

/* read node `node`'s row into `r`: 0, or -1 for a replay that ended */
static int read_row(FILE *fh, replay_row *r, int node) {
    const int *senders;
    CFD_REAL flags[CFD_DEG_MAX];
    int d = cfd_neighbours(node, &senders), b;
    if (read_tolerances(fh, r->tol) || read_reals(fh, r->u, CFD_NU) || read_reals(fh, r->z, cfd_sensor_dim(node))
            || read_reals(fh, flags, d))
        return -1;
    for (b = 0; b < d; ++b)
        if (read_reals(fh, r->got[b].x, CFD_NX)) return -1;
    arrivals(flags, d, r->arrived, r->falsified);
    for (b = 0; b < d && CFD_EXCHANGE; ++b)
        if (read_reals(fh, r->got[b].z, CFD_NZMAX)) return -1;
    return read_reals(fh, r->later, (CFD_ROUNDS - 1) * d * CFD_NX) || read_numbers(fh, r->x, CFD_NX)
           || read_numbers(fh, r->P, CFD_NX * CFD_NX) ? -1 : 0;
}

int main(int argc, char **argv) {
    static cfd_node nodes[CFD_NODES], net[CFD_NODES];
    static replay_row rows[CFD_NODES];
    static cfd_packet sent[CFD_NODES], got[CFD_DEG_MAX], mine;
    static CFD_REAL current[CFD_NODES * CFD_NX], rec[CFD_DEG_MAX * CFD_NX];
    static cfd_tally t;
    FILE *fh;
    int steps, k, j, b, r, i;
    fh = start(argc, argv, nodes, net, &steps);
    if (!fh) return 2;
    for (k = 0; k < steps; ++k) {
        for (j = 0; j < CFD_NODES; ++j)
            if (read_row(fh, &rows[j], nodes[j].node)) return short_replay(argv[1], k, nodes[j].node);
        for (j = 0; j < CFD_NODES; ++j) { /* each node's step from the Python node's state */
            replay_row *w = &rows[j];
            const int *senders;
            int d = cfd_neighbours(nodes[j].node, &senders);
            int e = cfd_predict(&nodes[j], w->z, CFD_NU ? w->u : NULL, &mine);
            if (!e) e = cfd_update(&nodes[j], w->arrived, w->got);
            for (r = 2; r <= CFD_ROUNDS && !e; ++r) e = cfd_round(&nodes[j], w->later + (r - 2) * d * CFD_NX);
            if (e) {
                fprintf(stderr, "step %d, node %d: the node filter returned %d\n", k + 1, nodes[j].node, e);
                return 1;
            }
            at_row(&t, k, nodes[j].node, w->tol, 1);
            check(&t, 1, "x", "P", nodes[j].x, nodes[j].P, w->x, w->P);
            resync(nodes[j].x, nodes[j].P, w->x, w->P);
        }
        /* the network run: every node's packet first, then the first round's updates, then each later round's from
         * the estimates every node held after the round before */
        for (j = 0; j < CFD_NODES && !t.net_stopped; ++j) {
            int e = cfd_predict(&net[j], rows[j].z, CFD_NU ? rows[j].u : NULL, &sent[j]);
            if (e) network_stops(&t, k, net[j].node, "cfd_predict", e);
        }
        for (j = 0; j < CFD_NODES && !t.net_stopped; ++j) {
            const int *senders;
            int d = cfd_neighbours(net[j].node, &senders), e;
            for (b = 0; b < d; ++b) {
                int s = slot_of(senders[b]);
                got[b] = s >= 0 && rows[j].arrived[b] && !rows[j].falsified[b] ? sent[s] : rows[j].got[b];
            }
            e = cfd_update(&net[j], rows[j].arrived, got);
            if (e) network_stops(&t, k, net[j].node, "cfd_update", e);
        }
        for (r = 2; r <= CFD_ROUNDS && !t.net_stopped; ++r) {
            for (j = 0; j < CFD_NODES; ++j)
                for (i = 0; i < CFD_NX; ++i) current[j * CFD_NX + i] = net[j].x[i];
            for (j = 0; j < CFD_NODES && !t.net_stopped; ++j) {
                const int *senders;
                int d = cfd_neighbours(net[j].node, &senders), e;
                for (b = 0; b < d; ++b) {
                    int s = slot_of(senders[b]);
                    const CFD_REAL *x = s >= 0 && rows[j].arrived[b] && !rows[j].falsified[b]
                                        ? current + s * CFD_NX : rows[j].later + ((r - 2) * d + b) * CFD_NX;
                    for (i = 0; i < CFD_NX; ++i) rec[b * CFD_NX + i] = x[i];
                }
                e = cfd_round(&net[j], rec);
                if (e) network_stops(&t, k, net[j].node, "cfd_round", e);
            }
        }
        for (j = 0; j < CFD_NODES && !t.net_stopped; ++j) {
            at_row(&t, k, net[j].node, rows[j].tol, 0);
            check(&t, 0, "x", "P", net[j].x, net[j].P, rows[j].x, rows[j].P);
        }
    }
    return finish(fh, steps, &t);
}
