"""The C nodes' dense linear algebra (``designer/c/frame``: ``cholesky``, ``tri_inverse``, ``spd_solve_rows`` and
``spd_solve_cols``, ``mul``), compiled as the exported Makefile compiles it, against the textbook's sums computed in
Python (the same additions in the same order: the same bits, as IEEE doubles without fused operations) and numpy, in
both of the forms ``CFD_ROW_FORM_MIN`` chooses between."""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

import designer.export_c

CC = shutil.which("cc") or shutil.which("gcc")
FRAME = Path(designer.export_c.__file__).parent / "c" / "frame"
SIZES = (1, 5, 39, 40, 57)  # around CFD_ROW_FORM_MIN's default (40), and beyond

pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler")


def frame_code() -> str:
    """The pure linear algebra of common.c.in (from CFD_ROW_FORM_MIN to the model's calls) and linalg.c."""
    common = (FRAME / "common.c.in").read_text()
    start, end = common.index("/* From this many rows"), common.index("static int call(")
    return (FRAME / "linalg.c").read_text() + "\n" + common[start:end]


def textbook_cholesky(A: list[list[float]]) -> list[list[float]] | None:
    m = len(A)
    L = [[0.0] * m for _ in range(m)]
    for j in range(m):
        t = A[j][j]
        for k in range(j):
            t -= L[j][k] * L[j][k]
        if not t > 0.0:
            return None
        L[j][j] = float(np.sqrt(t))
        for i in range(j + 1, m):
            v = A[i][j]
            for k in range(j):
                v -= L[i][k] * L[j][k]
            L[i][j] = v / L[j][j]
    return L


def textbook_tri_inverse(L: list[list[float]]) -> tuple[list[list[float]], float]:
    m = len(L)
    W = [row[:] for row in L]
    for j in range(m):
        W[j][j] = 1.0 / W[j][j]
        for i in range(j + 1, m):
            u = 0.0
            for k in range(j, i):
                u -= W[i][k] * W[k][j]
            W[i][j] = u / W[i][i]
    tri = 0.0
    for j in range(m):
        for i in range(j, m):
            tri += W[i][j] * W[i][j]
    return W, tri


def textbook_solve(Li: list[list[float]], v: list[float]) -> list[float]:
    """``L^-T L^-1 v`` as spd_solve_rows forms it."""
    m = len(v)
    v = v[:]
    for i in range(m - 1, -1, -1):
        t = 0.0
        for k in range(i + 1):
            t += Li[i][k] * v[k]
        v[i] = t
    for i in range(m):
        t = 0.0
        for k in range(i, m):
            t += Li[k][i] * v[k]
        v[i] = t
    return v


def textbook_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.empty((a.shape[0], b.shape[1]))
    for i in range(a.shape[0]):
        for j in range(b.shape[1]):
            t = 0.0
            for ll in range(a.shape[1]):
                t += float(a[i, ll]) * float(b[ll, j])
            out[i, j] = t
    return out


HARNESS = r"""
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#define CFD_REAL double
@CODE@
static void put(const double *a, int count) {
    int i;
    for (i = 0; i < count; ++i) printf("%a ", a[i]);
    printf("\n");
}

int main(void) {
    static double L[@MM@], Li[@MM@], X[@MC@], acc[@C@], Y[@MC@], P[@PP@], P3[@R@ * 3];
    static const double A[@MM@] = {@A@}, B[@MC@] = {@B@}, E[@MM@] = {@E@}, a[@RM@] = {@MA@}, b[@MC@] = {@MB@};
    static const double b3[@M@ * 3] = {@MB3@};
    double tri;
    int i, k;
    if (cholesky(@M@, A, L)) return 3;
    put(L, @MM@);
    memcpy(Li, L, sizeof L);
    tri = tri_inverse(@M@, Li);
    put(Li, @MM@);
    printf("%a\n", tri);
    memcpy(X, B, sizeof X); /* m x c, the right-hand sides as columns */
    spd_solve_cols(@M@, Li, X, @C@, acc);
    put(X, @MC@);
    for (k = 0; k < @C@; ++k) for (i = 0; i < @M@; ++i) Y[k * @M@ + i] = B[i * @C@ + k]; /* as rows */
    spd_solve_rows(@M@, Li, Y, @C@);
    put(Y, @MC@);
    printf("%d\n", cholesky(@M@, E, L)); /* not positive definite */
    mul(a, b, P, @R@, @M@, @C@); /* 9 columns: mul's row form */
    put(P, @PP@);
    mul(a, b3, P3, @R@, @M@, 3); /* 3: its dot products */
    put(P3, @R@ * 3);
    return 0;
}
"""


def c_list(a: np.ndarray) -> str:
    return ", ".join(float(v).hex() for v in np.ravel(a))


def run_harness(tmp: Path, form_min: int, A, B, E, a, b, b3) -> list[list[float]]:
    m, c = B.shape
    r = a.shape[0]
    fill = {"CODE": frame_code(), "M": m, "C": c, "R": r, "MM": m * m, "MC": m * c, "RM": r * m, "PP": r * c,
            "A": c_list(A), "B": c_list(B), "E": c_list(E), "MA": c_list(a), "MB": c_list(b), "MB3": c_list(b3)}
    src = HARNESS
    for key, value in fill.items():
        src = src.replace(f"@{key}@", str(value))
    (tmp / "h.c").write_text(src)
    exe = tmp / f"h{form_min}"
    subprocess.run([CC, "-std=c99", "-O3", "-Wall", "-Wextra", "-pedantic", "-Werror", f"-DCFD_ROW_FORM_MIN={form_min}",
                    "-o", str(exe), str(tmp / "h.c"), "-lm"], check=True, capture_output=True, text=True)
    out = subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout
    return [[float.fromhex(t) for t in line.split()] for line in out.splitlines()]


@pytest.mark.parametrize("m", SIZES)
def test_both_forms_are_the_textbook_sums_bit_for_bit(tmp_path, m):
    rng = np.random.default_rng(m)
    G = rng.standard_normal((m, m + 3))
    A = G @ G.T + 0.1 * np.eye(m)  # symmetric positive definite, condition up to about 1e3
    A = 0.5 * (A + A.T)
    c = 9
    B = rng.standard_normal((m, c))
    E = A - (np.linalg.eigvalsh(A)[0] + 1.0) * np.eye(m)  # one eigenvalue -1: no Cholesky factor
    a, b, b3 = rng.standard_normal((3, m)), rng.standard_normal((m, c)), rng.standard_normal((m, 3))
    row, textbook = (run_harness(tmp_path, form, A, B, E, a, b, b3) for form in (0, 10**6))
    assert row == textbook  # the two forms: the same bits

    L = textbook_cholesky(A.tolist())
    Li, tri = textbook_tri_inverse(L)
    got_L, got_Li, (got_tri,), got_X, got_Y, (bad,), got_P, got_P3 = row
    assert got_L == [v for r in L for v in r]  # the upper triangle zeroed, the lower the textbook's
    assert got_Li == [Li[i][j] if j <= i else 0.0 for i in range(m) for j in range(m)]
    assert got_tri == tri
    solved = np.array([textbook_solve(Li, list(B[:, k])) for k in range(c)])  # (c, m)
    assert got_X == solved.T.ravel().tolist()
    assert got_Y == solved.ravel().tolist()
    assert bad == -1
    assert got_P == textbook_mul(a, b).ravel().tolist()
    assert got_P3 == textbook_mul(a, b3).ravel().tolist()

    # and what they compute: L L^T = A, L L^-1 = I, tr A^-1, A^-1 B, a b
    Lm, Lim = np.array(got_L).reshape(m, m), np.array(got_Li).reshape(m, m)
    scale = np.linalg.norm(A)
    np.testing.assert_allclose(Lm @ Lm.T, A, atol=1e-13 * scale)
    np.testing.assert_allclose(Lm @ Lim, np.eye(m), atol=1e-10)
    np.testing.assert_allclose(got_tri, np.trace(np.linalg.inv(A)), rtol=1e-9)
    np.testing.assert_allclose(np.array(got_X).reshape(m, c), np.linalg.solve(A, B), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(np.array(got_P).reshape(3, c), a @ b, rtol=1e-12, atol=1e-12)
