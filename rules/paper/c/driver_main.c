/* a flag (1 or 0) against Python's */
static void flag(cfd_tally *t, const char *what, int got, double want) {
    if ((got != 0) == (want != 0.0)) return;
    if (t->bad < REPORTED)
        printf("step %d, node %d: %s is %d in C, %d in Python\n", t->step, t->node, what, got != 0, want != 0.0);
    t->bad += 1;
}

int main(int argc, char **argv) {
    static cfd_node nodes[CFD_NODES], free_nodes[CFD_NODES];
    static cfd_packet bounds[CFD_DEG_MAX], mine;
    static CFD_REAL u[CFD_NU + 1], z[CFD_NZ], flags[CFD_DEG_MAX], rec[CFD_DEG_MAX * CFD_NX];
    static double ok[1];
    static double px[CFD_NX], pP[CFD_NX * CFD_NX], pok[1], x[CFD_NX], P[CFD_NX * CFD_NX];
    static unsigned char arrived[CFD_DEG_MAX];
    cfd_tally t = {0, 0, 0.0, 0.0, 0.0, 0, 0.0};
    FILE *fh;
    int steps, k, j, b;
    fh = start(argc, argv, nodes, free_nodes, &steps);
    if (!fh) return 2;
    for (k = 0; k < steps; ++k) {
        for (j = 0; j < CFD_NODES; ++j) {
            const int *senders;
            int d = cfd_neighbours(nodes[j].node, &senders), m = cfd_sensor_dim(nodes[j].node), e;
            int short_read = row(fh, &t, k, nodes[j].node) || read_reals(fh, u, CFD_NU) || read_reals(fh, z, m)
                             || read_reals(fh, flags, d) || read_reals(fh, rec, d * CFD_NX);
            for (b = 0; b < d && !short_read; ++b) {
                short_read = read_reals(fh, bounds[b].P, CFD_NX * CFD_NX) || read_numbers(fh, ok, 1);
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
            flag(&t, "the prediction's bound flag", mine.ok, pok[0]);
            check(&t, 1, "x_pred", "P_pred", mine.x, mine.P, px, pP);
            e = cfd_update(&nodes[j], z, arrived, rec, bounds);
            if (e) {
                fprintf(stderr, "step %d, node %d: cfd_update returned %d\n", k + 1, nodes[j].node, e);
                return 1;
            }
            check(&t, 1, "x", "P", nodes[j].x, nodes[j].P, x, P);
            resync(nodes[j].x, nodes[j].P, x, P);
            if (!cfd_predict(&free_nodes[j], CFD_NU ? u : NULL, &mine)
                    && !cfd_update(&free_nodes[j], z, arrived, rec, bounds))
                check(&t, 0, "x", "P", free_nodes[j].x, free_nodes[j].P, x, P);
        }
    }
    return finish(fh, steps, &t);
}
