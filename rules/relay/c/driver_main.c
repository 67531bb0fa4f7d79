/* A relay or flood node exchanges measurements only: what reaches it is the log's (as it arrived), so the second
 * set of nodes, never re-synchronised and fed the same arrivals, is the network run. */
int main(int argc, char **argv) {
    static cfd_node nodes[CFD_NODES], net[CFD_NODES];
    static CFD_REAL z[CFD_ROWS_MAX], rec[CFD_ROWS_MAX], flags[CFD_BALL_MAX], u[CFD_NU + 1];
    static double x[CFD_NC], P[CFD_NC * CFD_NC], tol[TOLERANCES];
    static unsigned char arrived[CFD_BALL_MAX];
    static cfd_tally t;
    FILE *fh;
    int steps, k, j;
    fh = start(argc, argv, nodes, net, &steps);
    if (!fh) return 2;
    for (k = 0; k < steps; ++k) {
        for (j = 0; j < CFD_NODES; ++j) {
            const int *ball;
            int nb = cfd_ball(nodes[j].node, &ball), m_own = cfd_sensor_dim(ball[0]), m_rec = 0, b, e;
            for (b = 1; b < nb; ++b) m_rec += cfd_sensor_dim(ball[b]);
            if (read_tolerances(fh, tol) || read_reals(fh, z, m_own) || read_reals(fh, flags, nb - 1)
                    || read_reals(fh, rec, m_rec) || read_reals(fh, u, CFD_NU) || read_numbers(fh, x, CFD_NC)
                    || read_numbers(fh, P, CFD_NC * CFD_NC)) {
                return short_replay(argv[1], k, nodes[j].node);
            }
            at_row(&t, k, nodes[j].node, tol, 1);
            arrivals(flags, nb - 1, arrived, NULL);
            e = cfd_step(&nodes[j], z, arrived, rec, CFD_NU ? u : NULL);
            if (e) {
                fprintf(stderr, "step %d, node %d: cfd_step returned %d\n", k + 1, nodes[j].node, e);
                return 1;
            }
            check(&t, 1, "x", "P", nodes[j].x, nodes[j].P, x, P);
            resync(nodes[j].x, nodes[j].P, x, P);
            if (t.net_stopped) continue;
            e = cfd_step(&net[j], z, arrived, rec, CFD_NU ? u : NULL);
            if (e)
                network_stops(&t, k, nodes[j].node, "cfd_step", e);
            else
                check(&t, 0, "x", "P", net[j].x, net[j].P, x, P);
        }
    }
    return finish(fh, steps, &t);
}
