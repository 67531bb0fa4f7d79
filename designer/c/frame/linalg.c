/* out = a b (r x m times m x c), out = a b^T (r x m times c x m), out = (a + a^T) / 2 (n x n) */
/* mul: with 8 or more columns row by row, each row of b added into out's row in turn (contiguous, so that the
 * compiler vectorises over the columns: 2-4 x faster from 8 x 8 on), with fewer a dot product per entry (faster
 * there); each entry sums its terms from 0.0 in the order l = 0..m-1 either way, the same numbers (tested in
 * tests/test_c_linalg.py); out must not overlap a or b */
static inline void mul(const CFD_REAL *a, const CFD_REAL *b, CFD_REAL *out, int r, int m, int c) {
    int i, j, l;
    if (c < 8) {
        for (i = 0; i < r; ++i)
            for (j = 0; j < c; ++j) {
                CFD_REAL t = 0.0;
                for (l = 0; l < m; ++l) t += a[i * m + l] * b[l * c + j];
                out[i * c + j] = t;
            }
        return;
    }
    for (i = 0; i < r; ++i) {
        CFD_REAL *const o = out + (size_t)i * c;
        for (j = 0; j < c; ++j) o[j] = 0.0;
        for (l = 0; l < m; ++l) {
            const CFD_REAL f = a[i * m + l], *const bl = b + (size_t)l * c;
            for (j = 0; j < c; ++j) o[j] += f * bl[j];
        }
    }
}

static inline void mul_t(const CFD_REAL *a, const CFD_REAL *b, CFD_REAL *out, int r, int m, int c) {
    int i, j, l;
    for (i = 0; i < r; ++i)
        for (j = 0; j < c; ++j) {
            CFD_REAL t = 0.0;
            for (l = 0; l < m; ++l) t += a[i * m + l] * b[j * m + l];
            out[i * c + j] = t;
        }
}

static inline void sym(CFD_REAL *a, int n) {
    int i, j;
    for (i = 0; i < n; ++i)
        for (j = 0; j < i; ++j) a[i * n + j] = a[j * n + i] = 0.5 * (a[i * n + j] + a[j * n + i]);
}

static inline int finite_all(const CFD_REAL *a, int count) {
    int i;
    for (i = 0; i < count; ++i)
        if (!isfinite(a[i])) return 0;
    return 1;
}

/* solve S X = B (m x m, m x c) by Gaussian elimination with partial pivoting; S and B are destroyed */
static inline int solve(CFD_REAL *S, CFD_REAL *B, int m, int c) {
    int i, j, l, p;
    for (l = 0; l < m; ++l) {
        p = l;
        for (i = l + 1; i < m; ++i)
            if (fabs(S[i * m + l]) > fabs(S[p * m + l])) p = i;
        if (S[p * m + l] == 0.0) return -1;
        if (p != l) {
            for (j = 0; j < m; ++j) { CFD_REAL t = S[l * m + j]; S[l * m + j] = S[p * m + j]; S[p * m + j] = t; }
            for (j = 0; j < c; ++j) { CFD_REAL t = B[l * c + j]; B[l * c + j] = B[p * c + j]; B[p * c + j] = t; }
        }
        for (i = l + 1; i < m; ++i) {
            CFD_REAL f = S[i * m + l] / S[l * m + l];
            for (j = l; j < m; ++j) S[i * m + j] -= f * S[l * m + j];
            for (j = 0; j < c; ++j) B[i * c + j] -= f * B[l * c + j];
        }
    }
    for (i = m - 1; i >= 0; --i)
        for (j = 0; j < c; ++j) {
            CFD_REAL t = B[i * c + j];
            for (l = i + 1; l < m; ++l) t -= S[i * m + l] * B[l * c + j];
            B[i * c + j] = t / S[i * m + i];
        }
    return 0;
}
