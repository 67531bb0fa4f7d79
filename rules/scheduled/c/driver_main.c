/* one step of a scheduled node from what the replay gives (its packets, then each later round's estimates): 0, a
 * node filter's error code, or 1 for a replay that ended */
static int scheduled_step(cfd_node *s, FILE *fh, const CFD_REAL *z, const CFD_REAL *u, const unsigned char *arrived,
                          const cfd_packet *got, CFD_REAL *rec, int d, int *short_read) {
    static cfd_packet mine;
    int r, e = cfd_predict(s, z, CFD_NU ? u : NULL, &mine);
    if (!e) e = cfd_update(s, arrived, got);
    for (r = 2; r <= CFD_ROUNDS && !e; ++r) {
        if (fh && (*short_read = read_reals(fh, rec + (r - 2) * d * CFD_NX, d * CFD_NX))) return 1;
        e = cfd_round(s, rec + (r - 2) * d * CFD_NX);
    }
    return e;
}

int main(int argc, char **argv) {
    static cfd_node nodes[CFD_NODES], free_nodes[CFD_NODES];
    static cfd_packet got[CFD_DEG_MAX];
    static CFD_REAL u[CFD_NU + 1], z[CFD_NZ], flags[CFD_DEG_MAX], rec[(CFD_ROUNDS + 1) * CFD_DEG_MAX * CFD_NX];
    static double x[CFD_NX], P[CFD_NX * CFD_NX];
    static unsigned char arrived[CFD_DEG_MAX];
    cfd_tally t = {0, 0, 0.0, 0.0, 0.0, 0, 0.0};
    FILE *fh;
    int steps, k, j, b;
    fh = start(argc, argv, nodes, free_nodes, &steps);
    if (!fh) return 2;
    for (k = 0; k < steps; ++k) {
        for (j = 0; j < CFD_NODES; ++j) {
            const int *senders;
            int d = cfd_neighbours(nodes[j].node, &senders), m = cfd_sensor_dim(nodes[j].node), e = 0;
            int short_read = row(fh, &t, k, nodes[j].node) || read_reals(fh, u, CFD_NU) || read_reals(fh, z, m)
                             || read_reals(fh, flags, d);
            for (b = 0; b < d && !short_read; ++b) short_read = read_reals(fh, got[b].x, CFD_NX);
            for (b = 0; b < d && !short_read && CFD_EXCHANGE; ++b) short_read = read_reals(fh, got[b].z, CFD_NZMAX);
            for (b = 0; b < d; ++b) arrived[b] = flags[b] != 0.0;
            if (!short_read) e = scheduled_step(&nodes[j], fh, z, u, arrived, got, rec, d, &short_read);
            if (short_read || read_numbers(fh, x, CFD_NX) || read_numbers(fh, P, CFD_NX * CFD_NX)) {
                return short_replay(argv[1], k, nodes[j].node);
            }
            if (e) {
                fprintf(stderr, "step %d, node %d: the node filter returned %d\n", k + 1, nodes[j].node, e);
                return 1;
            }
            check(&t, 1, "x", "P", nodes[j].x, nodes[j].P, x, P);
            resync(nodes[j].x, nodes[j].P, x, P);
            if (!scheduled_step(&free_nodes[j], NULL, z, u, arrived, got, rec, d, &short_read))
                check(&t, 0, "x", "P", free_nodes[j].x, free_nodes[j].P, x, P);
        }
    }
    return finish(fh, steps, &t);
}
