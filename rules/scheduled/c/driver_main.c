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
