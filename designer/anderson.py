"""Anderson acceleration of fixed-point iterations ``x <- T(x)``, many at once, with a safeguard.

One home for the acceleration the design's recursions use: the steady state of the bound recursion
(:mod:`designer.feasibility`), the weights of the run-time tuned filter (:mod:`designer.tuning`, which keeps its
own history of log weights and calls :func:`least_squares`) and the relay rule's stationary recursion
(:func:`rules.relay.design.relay_stationary`).

Type II (Walker and Ni 2011, "Anderson acceleration for fixed-point iterations", SIAM J. Numer. Anal. 49(4)):
from the last ``memory + 1`` points ``x_j`` and their images ``g_j = T(x_j)``, the residuals ``f_j = g_j - x_j``;
``γ`` minimises ``|f_k - ΔF γ|`` over the differences of consecutive residuals and the next point is
``g_k - ΔG γ``.  The safeguard (:class:`Anderson`) keeps the iteration's answer a fixed point of the true map
whatever the extrapolation does: the caller evaluates ``T`` at every point it is given and declares convergence
only when ``T(x) = x`` to its tolerance.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

__all__ = ["Anderson", "least_squares", "positive_definite", "out_of_reach", "REACH_WINDOW", "REACH_MARGIN"]

#: Iterations over which :func:`out_of_reach` measures a fixed-point iteration's rate (it judges after two).
REACH_WINDOW = 100
#: How many times the iterations left :func:`out_of_reach` lets that rate need before it calls the tolerance out of
#: reach: an assumption, chosen so that only an iteration far from its tolerance stops (a scheduled design's
#: stationary recursion on my 21-zone greenhouse at DoS 0.4, FDI 0.2: a relative change stuck near 4e-3 from
#: iteration 200 to its limit of 1000, 90 s, then "did not settle").
REACH_MARGIN = 3.0


def out_of_reach(residuals, tol: float, budget: int, window: int = REACH_WINDOW,
                 margin: float = REACH_MARGIN) -> str | None:
    """Why a fixed-point iteration cannot reach ``tol`` within ``budget`` iterations in all, or None while it may.

    ``residuals``: its relative change from each point to its image, one per iteration, newest last.  From
    ``2 window`` iterations on, its rate over the last ``window`` (the smallest residual of the last tenth of the
    window against the smallest of the tenth a window before: the accelerated iteration's jumps smoothed) is
    extrapolated: where the residual has not shrunk, or shrinks too slowly to reach ``tol`` within ``margin`` times
    the iterations left, it is out of reach.  A prediction, used only to stop early an iteration that would end
    unsettled anyway: a verdict built on it can only be the weaker one (no fixed point), never a stronger one."""
    r = np.asarray(residuals, dtype=float)
    it = r.size
    if it < 2 * window or not np.isfinite(r[-1]):
        return None
    tenth = max(1, window // 10)
    now, then = float(np.min(r[-tenth:])), float(np.min(r[-window - tenth:-window]))
    if now <= tol:
        return None
    left = budget - it
    if now >= then:
        return (f"its change per iteration stopped shrinking ({now:.2g} relative, {then:.2g} {window} iterations "
                f"before), far from {tol:g}")
    need = np.log(tol / now) / np.log(now / then) * window
    if need <= margin * left:
        return None
    return (f"its change per iteration ({now:.2g} relative) shrank {then / now:.3g} x in its last {window} "
            f"iterations: at that rate about {need:.3g} more to {tol:g}, beyond the {budget} allowed")


def least_squares(gram: np.ndarray, rhs: np.ndarray, rows) -> np.ndarray:
    """The least-squares ``γ`` (m, c) of ``A γ ≈ b`` per item from its normal equations ``gram = Aᵀ A`` (m, c, c)
    and ``rhs = Aᵀ b`` (m, c): a Cholesky that drops a column whose part independent of the earlier ones is within
    rounding of zero (pivot <= ``(eps L)²`` times its squared norm, ``L`` the item's ``rows``, the length of its
    columns): a zero column (history not yet there) or a repeated one gets ``γ = 0``."""
    m, c = rhs.shape
    rows = np.broadcast_to(np.asarray(rows, dtype=float), (m,))
    cut = (np.finfo(float).eps * np.maximum(rows, c)) ** 2
    low = np.zeros((m, c, c))
    inv = np.zeros((m, c))
    for j in range(c):
        d = gram[:, j, j] - np.sum(low[:, j, :j] ** 2, axis=-1)
        keep = d > cut * gram[:, j, j]
        inv[:, j] = np.where(keep, 1.0 / np.sqrt(np.where(keep, d, 1.0)), 0.0)
        for i in range(j + 1, c):
            low[:, i, j] = (gram[:, i, j] - np.sum(low[:, i, :j] * low[:, j, :j], axis=-1)) * inv[:, j]
    y = np.zeros((m, c))
    for j in range(c):
        y[:, j] = (rhs[:, j] - np.sum(low[:, j, :j] * y[:, :j], axis=-1)) * inv[:, j]
    out = np.zeros((m, c))
    for j in reversed(range(c)):
        out[:, j] = (y[:, j] - np.sum(low[:, j + 1:, j] * out[:, j + 1:], axis=-1)) * inv[:, j]
    return out


def positive_definite(points: np.ndarray) -> np.ndarray:
    """(k,) whether every symmetric matrix of each item of ``points`` (k, ..., n, n) is finite and positive definite
    on the states it holds: a row and column exactly zero (a state a node does not carry, padded) is left out.  A
    Cholesky of the whole stack first (the common case, a third of an eigenvalue decomposition's work), the
    smallest eigenvalues when it fails."""
    k, n = points.shape[0], points.shape[-1]
    mats = points.reshape(k, -1, n, n)
    finite = np.isfinite(mats).all(axis=(1, 2, 3))
    empty = ~np.any(mats != 0.0, axis=-1)  # (k, ., n) the zero rows: a unit on the diagonal in their place
    mats = mats + empty[..., None] * np.eye(n)
    if finite.all():
        try:
            np.linalg.cholesky(mats)
            return np.ones(k, dtype=bool)
        except np.linalg.LinAlgError:
            pass
    ok = np.zeros(k, dtype=bool)
    ok[finite] = (np.linalg.eigvalsh(mats[finite])[..., 0] > 0).all(axis=-1)
    return ok


class Anderson:
    """Anderson acceleration (type II, ``memory`` differences) of ``k`` fixed-point iterations at once, each item
    with its own history, with a safeguard:

    * when an item's residual ``|T(x) - x|`` grew since its last point, its history is cleared and it takes the
      plain step ``T(x)``;
    * the extrapolated point is taken only when ``admissible`` (default :func:`positive_definite`: the items are
      symmetric matrices, or stacks of them), else the point 1/2 or 1/4 of the way from ``T(x)`` to it, else the
      plain step (and the history is cleared).

    The least squares are solved from their normal equations (:func:`least_squares`), the Gram matrices by one
    batched product: each item's numbers are those it gets alone."""

    def __init__(self, k: int, memory: int = 5,
                 admissible: Callable[[np.ndarray], np.ndarray] | None = None):
        self.k, self.memory = int(k), int(memory)
        self.admissible = positive_definite if admissible is None else admissible
        self.xs: np.ndarray | None = None  # (k, memory + 1, L) the last points, newest last
        self.gs: np.ndarray | None = None  # their images
        self.count = np.zeros(self.k, dtype=int)  # how many of the history's slots hold points
        self.res = np.full(self.k, np.inf)  # each item's residual at its last point
        self.extrapolated = np.zeros(self.k, dtype=bool)  # whether the item's last point was not its plain step

    def reset(self, idx) -> None:
        """Clear the histories of the items ``idx``."""
        self.count[idx] = 0
        self.res[idx] = np.inf

    def retreat(self, idx) -> np.ndarray:
        """The plain steps ``T(x)`` the items ``idx`` (each extrapolated at its last step: :attr:`extrapolated`)
        took their last points instead of, their histories cleared: where to go on when ``T`` misbehaves at an
        extrapolated point (flattened, (m, L))."""
        idx = np.asarray(idx, dtype=int)
        if not self.extrapolated[idx].all():
            raise ValueError("retreat: an item's last point was its plain step")
        out = self.gs[idx, -1].copy()
        self.reset(idx)
        self.extrapolated[idx] = False
        return out

    def step(self, idx, x: np.ndarray, gx: np.ndarray,
             admissible: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
        """The next points of the items ``idx`` (m,) from their points ``x`` and images ``gx`` (m, ...);
        ``admissible`` (candidates (e, ...) -> (e,) bool) in place of the one given at construction."""
        admissible = self.admissible if admissible is None else admissible
        idx = np.asarray(idx, dtype=int)
        m = idx.size
        shape = gx.shape
        xf, gf = x.reshape(m, -1), gx.reshape(m, -1)
        L = gf.shape[1]
        if self.xs is None:
            self.xs = np.zeros((self.k, self.memory + 1, L))
            self.gs = np.zeros((self.k, self.memory + 1, L))
        out = np.array(gf)
        self.extrapolated[idx] = False
        res = np.linalg.norm(gf - xf, axis=1)
        worse = (self.count[idx] > 0) & (res > self.res[idx])
        self.reset(idx[worse])
        go = ~worse
        j = idx[go]
        self.res[j] = res[go]
        self.xs[j, :-1], self.gs[j, :-1] = self.xs[j, 1:], self.gs[j, 1:]
        self.xs[j, -1], self.gs[j, -1] = xf[go], gf[go]
        self.count[j] = np.minimum(self.count[j] + 1, self.memory + 1)
        ext = go & (self.count[idx] >= 2)
        if not self.memory or not ext.any():
            return out.reshape(shape)
        j = idx[ext]
        there = np.arange(self.memory) >= self.memory + 1 - self.count[j][:, None]  # both ends of a difference
        F = self.gs[j] - self.xs[j]  # (e, memory + 1, L) residuals, newest last
        dF = np.where(there[..., None], np.diff(F, axis=1), 0.0)
        dG = np.where(there[..., None], np.diff(self.gs[j], axis=1), 0.0)
        gamma = least_squares(dF @ np.swapaxes(dF, -1, -2), (dF @ F[:, -1, :, None])[..., 0], L)
        cand = (gf[ext] - (gamma[:, None, :] @ dG)[:, 0]).reshape((-1,) + shape[1:])
        if len(shape) >= 3:
            cand = 0.5 * (cand + np.swapaxes(cand, -1, -2))
        plain = gf[ext].reshape(cand.shape)
        taken = np.zeros(j.size, dtype=bool)
        pick = plain.copy()
        for t in (1.0, 0.5, 0.25):  # towards the plain step until the point is admissible
            left = ~taken
            if not left.any():
                break
            c = plain[left] + t * (cand[left] - plain[left])
            ok = np.asarray(admissible(c), dtype=bool)
            rows = np.flatnonzero(left)[ok]
            pick[rows] = c[ok]
            taken[rows] = True
        self.reset(j[~taken])
        self.extrapolated[j[taken]] = True
        out[ext] = pick.reshape(j.size, -1)
        return out.reshape(shape)
