"""Shared pieces of every study's results: error metrics, Monte Carlo intervals, tables, versions (their files:
:mod:`studies.outputs`; figures: :mod:`studies.figures`).

Metrics follow the particle-filter papers (seeds 000 and 002):
``RMSE_{p,k} = sqrt(mean over runs of |p_k - p̂_k|²)`` per step ``k = 1..K`` (the
curve), and the "average RMSE" of their tables is the mean of that curve over
``k``.  Its 95 % interval is a percentile bootstrap over runs (runs resampled with
replacement, the whole statistic recomputed).
"""
from __future__ import annotations

import platform
import sys
from typing import Mapping, Sequence

import numpy as np

__all__ = ["SCHEMA", "versions", "error_metrics", "curve_mean_ci", "bootstrap_rmse_ci", "markdown_table",
           "BOOTSTRAP", "rmse_with_ci", "study_header", "DIVERGENCE_SPREAD", "divergence_limit", "first_divergence",
           "cv_velocity_at_position_rmse", "better_than", "per_run_mse",
           "compared_with_local", "local_ratio_text", "MIN_RUNS_FOR_CHECK", "whole_bounds"]

SCHEMA = "cfdesign.study/1"
BOOTSTRAP = 1000  # bootstrap resamples of the runs for the intervals
#: a (node, step) is checked against its bound by the per-pair test (studies.consensus_robot.bound_check) when Φ is
#: a bound there in at least this many runs
MIN_RUNS_FOR_CHECK = 30


def whole_bounds(runs: int) -> bool:
    """Whether a study of ``runs`` runs keeps its designed filters' bounds Φ whole: only the per-pair test
    (:func:`studies.consensus_robot.bound_check`, from :data:`MIN_RUNS_FOR_CHECK` runs of a (node, step)) reads more
    than their traces.  With fewer runs the filters keep the diagonals alone (:class:`filters.engine.Diagonal`): on
    the 118-bus grid a run's bounds are 0.8 GB whole and 6.7 MB so, and an automatic design's validation runs can be
    batched.  Here, not beside the test, so that the studies' memory estimate (:mod:`studies.memory`) reads it too."""
    return int(runs) >= MIN_RUNS_FOR_CHECK


def versions() -> dict:
    """Software versions recorded in every results file."""
    import casadi
    import scipy

    out = {"python": sys.version.split()[0], "numpy": np.__version__, "scipy": scipy.__version__,
           "casadi": casadi.__version__, "platform": platform.platform()}
    try:
        import numba

        out["numba"] = numba.__version__
    except ImportError:  # pragma: no cover - numba is a dependency
        pass
    return out


def curve_mean_ci(e2: np.ndarray, rng: np.random.Generator) -> tuple[float, list[float]]:
    """Mean over steps of sqrt(mean over runs of e2) and its bootstrap 95 % interval; e2 is (runs, K).

    ``BOOTSTRAP`` resamples of the runs; each resample's mean over runs is the product of
    its counts matrix with ``e2`` rather than a gather of ``BOOTSTRAP x runs x K`` values
    (a tenth of a whole fast study's time at the encrypted-switching default size).
    """
    runs = e2.shape[0]
    value = float(np.sqrt(e2.mean(axis=0)).mean())
    if runs < 2:
        return value, [value, value]
    idx = rng.integers(0, runs, size=(BOOTSTRAP, runs))
    counts = np.bincount((idx + runs * np.arange(BOOTSTRAP)[:, None]).ravel(), minlength=BOOTSTRAP * runs)
    boot = np.sqrt((counts.reshape(BOOTSTRAP, runs).astype(np.float64) @ e2) / runs).mean(axis=1)
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return value, [float(lo), float(hi)]


def better_than(per_run, floor, rng: np.random.Generator) -> dict:
    """Whether a filter is better than a floor on the same runs (the nodes running alone: ``study comparison``,
    ``study consensus-robot`` and an automatic design's validation), paired: the runs' shared truth, noises and
    attacks cancel in the ratio of the two RMSEs over the same resampled runs, so a filter that is better in every
    run is called better even where the runs' spread makes the two intervals overlap.  The one definition of "better
    than the nodes alone" on errors: a point estimate below the floor's is not evidence of it.

    ``per_run``, ``floor``: (runs,) each run's mean squared error of the filter and of the floor (NaN: diverged).
    Returns ``better`` (None: not judged), ``ratio`` (the filter's RMSE over the floor's over the runs where both
    have one), ``ratio_ci95`` (its 95 % paired percentile bootstrap interval, ``BOOTSTRAP`` resamples of the runs
    from ``rng``), ``runs`` (the runs compared) and ``reason`` in words.  Better: the interval lies entirely below 1.
    A run where the filter diverged and the floor did not makes it not better whatever the others say; a run where
    the floor diverged is left out (as in the floor's own RMSE); fewer than 2 runs: not judged."""
    a, b = np.asarray(per_run, dtype=float), np.asarray(floor, dtype=float)
    both = ~np.isnan(a) & ~np.isnan(b)
    lost = int((np.isnan(a) & ~np.isnan(b)).sum())
    out = {"better": None, "ratio": None, "ratio_ci95": None, "runs": int(both.sum()), "reason": ""}
    if both.sum() >= 1 and b[both].mean() > 0:
        out["ratio"] = float(np.sqrt(a[both].mean() / b[both].mean()))
    if lost:
        return {**out, "better": False, "reason": f"it diverged in {lost} run{'s' * (lost > 1)} where the nodes "
                                                  "alone did not"}
    if both.sum() < 2 or out["ratio"] is None:
        n = int(both.sum())
        return {**out, "reason": f"{n} run{'s' * (n != 1)} with both errors: not judged"}
    a, b = a[both], b[both]
    idx = rng.integers(0, len(a), size=(BOOTSTRAP, len(a)))
    den = b[idx].mean(axis=1)
    boot = np.sqrt(a[idx].mean(axis=1) / np.where(den > 0, den, np.nan))
    lo, hi = np.nanpercentile(boot, [2.5, 97.5])
    better = bool(hi < 1.0)
    return {**out, "better": better, "ratio_ci95": [float(lo), float(hi)],
            "reason": f"its RMSE is {out['ratio']:.3g} times the nodes alone's on the same {len(a)} runs (95 % paired "
                      f"interval [{lo:.3g}, {hi:.3g}]{', entirely below 1' if better else ', not entirely below 1'})"}


def compared_with_local(per_run=None, floor=None, rng: np.random.Generator | None = None) -> dict:
    """A results row's comparison with the nodes alone (:func:`better_than`): ``better_than_local``,
    ``rmse_ratio_local`` and ``rmse_ratio_local_ci95``; all None without both filters' runs (the local EKFs
    themselves, a reference, a filter that did not run)."""
    if per_run is None or floor is None:
        return {"better_than_local": None, "rmse_ratio_local": None, "rmse_ratio_local_ci95": None}
    paired = better_than(per_run, floor, rng)
    return {"better_than_local": paired["better"], "rmse_ratio_local": paired["ratio"],
            "rmse_ratio_local_ci95": paired["ratio_ci95"]}


def local_ratio_text(f: dict) -> str:
    """A filter's RMSE over the local EKFs' (``rmse_ratio_local``) with its paired interval, in words: a results row
    of ``study comparison`` or ``study consensus-robot``, or an automatic design's validation's pick row."""
    ci = f.get("rmse_ratio_local_ci95")
    if ci is None and f.get("better_than_local") is False:  # judged without an interval: a run lost
        return "not compared: it diverged in a run where the nodes alone did not"
    if f.get("rmse_ratio_local") is None:
        return "no ratio"
    return f"{f['rmse_ratio_local']:.3g} x" + ("" if ci is None else f" [{ci[0]:.3g}, {ci[1]:.3g}]")


def per_run_mse(err2: np.ndarray) -> np.ndarray:
    """(runs,) each run's mean of ``err2`` (runs, ...) over its other axes, NaN where any is (a diverged run)."""
    return np.asarray(err2, dtype=float).reshape(len(err2), -1).mean(axis=1)


def bootstrap_rmse_ci(per_run_mse: np.ndarray, rng: np.random.Generator) -> list[float]:
    """The 95 % percentile-bootstrap interval of ``sqrt(mean(per_run_mse))``: ``BOOTSTRAP`` resamples of the runs
    (each run's mean squared error), the root of each resample's mean."""
    per_run_mse = np.asarray(per_run_mse, dtype=float)
    idx = rng.integers(0, len(per_run_mse), size=(BOOTSTRAP, len(per_run_mse)))
    lo, hi = np.percentile(np.sqrt(per_run_mse[idx].mean(axis=1)), [2.5, 97.5])
    return [float(lo), float(hi)]


def error_metrics(err: np.ndarray, position: Sequence[int], velocity: Sequence[int],
                  rng: np.random.Generator) -> dict:
    """Metrics of estimation errors ``err`` (runs, K, n_x) at steps 1..K.

    Returns ``rmse_position``, ``rmse_velocity`` (averages of the per-step curves),
    their 95 % bootstrap intervals, ``rmse_state`` (per component, same averaging)
    and the curves ``rmse_position_curve``, ``rmse_velocity_curve``.
    """
    e2p = (err[..., list(position)] ** 2).sum(-1)
    e2v = (err[..., list(velocity)] ** 2).sum(-1)
    p, p_ci = curve_mean_ci(e2p, rng)
    v, v_ci = curve_mean_ci(e2v, rng)
    return {
        "rmse_position": p,
        "rmse_position_ci95": p_ci,
        "rmse_velocity": v,
        "rmse_velocity_ci95": v_ci,
        "rmse_state": [float(x) for x in np.sqrt((err**2).mean(axis=0)).mean(axis=0)],
        "rmse_position_curve": [float(x) for x in np.sqrt(e2p.mean(axis=0))],
        "rmse_velocity_curve": [float(x) for x in np.sqrt(e2v.mean(axis=0))],
    }


def _fmt(v) -> str:
    if v is None:
        return "—"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v).replace("|", "\\|")  # a cell's own bar (e.g. Phi_0|0 in a reason) must not split the row


def markdown_table(rows: Mapping[str, Mapping[str, object]], columns: Sequence[tuple[str, str]], first: str) -> str:
    """A Markdown table: one row per key of ``rows`` (the first column, headed ``first``: what the rows are),
    ``columns`` as (key, header) pairs."""
    if not first.strip():
        raise ValueError("a table's first column needs a header saying what its rows are")
    head = f"| {first} | " + " | ".join(h for _, h in columns) + " |"
    sep = "|---|" + "---:|" * len(columns)
    body = ["| " + name + " | " + " | ".join(_fmt(r.get(k)) for k, _ in columns) + " |" for name, r in rows.items()]
    return "\n".join([head, sep, *body]) + "\n"


def rmse_with_ci(f: Mapping) -> str:
    """``RMSE_p [lo, hi]`` for tables."""
    lo, hi = f["rmse_position_ci95"]
    return f"{f['rmse_position']:.4g} [{lo:.3g}, {hi:.3g}]"


DIVERGENCE_SPREAD = 100.0  # a run whose error leaves this many prior spreads has diverged (study option)


def divergence_limit(prior_cov: np.ndarray, spread: float) -> float:
    """The error norm beyond which a run counts as diverged: ``spread · sqrt(tr P_0)``, P_0 the prior covariance.

    An estimate 100 prior standard deviations away from the truth has left the problem's
    physical scale (the robot's room, the target's area) even when its numbers are finite.
    """
    return float(spread) * float(np.sqrt(np.trace(np.asarray(prior_cov, dtype=float))))


def first_divergence(err: np.ndarray, limit: float) -> tuple[int, int] | None:
    """``(step, node)`` where the error norm first exceeds ``limit`` (err (K + 1, nodes, n_x)), or None."""
    norm = np.linalg.norm(err, axis=-1)
    bad = ~(norm <= limit)  # NaN counts as beyond
    if not bad.any():
        return None
    k, i = map(int, np.argwhere(bad.reshape(norm.shape[0], -1))[0])
    return k, i


def study_header(study: str, scenario: str, *, runs: int, particles: int | None, steps: int, seed: int,
                 assumptions: Sequence[str], **extra) -> dict:
    """The keys every ``results.json`` starts with (``cfdesign.study/1``); ``wall_time_s`` is set on writing."""
    return {"schema": SCHEMA, "study": study, "scenario": scenario, "runs": int(runs),
            "particles": None if particles is None else int(particles), "steps": int(steps), "seed": int(seed),
            **extra, "assumptions": list(assumptions), "wall_time_s": None, "versions": versions()}


def cv_velocity_at_position_rmse(accel_var: float, period: float, rmse_position: float) -> float:
    """Velocity RMSE of the steady-state Kalman filter of a 2-D constant-velocity target whose position is
    measured directly (both axes, noise variance ``r`` each, every step), with ``r`` chosen so that its position
    RMSE equals ``rmse_position``.

    A consistency reference for published (RMSE_p, RMSE_v) pairs: with the paper's own process noise, an
    optimal filter that is as accurate in position is this accurate in velocity.  Position RMSE grows
    monotonically with ``r`` (from 0 to infinity), so ``log10 r`` is its root in [-12, 12], found by bisection
    (an RMSE outside what this range reaches takes the nearer end); each ``r``'s steady state is
    :func:`_cv_posterior` (NumPy only: SciPy's Riccati solver and root finder cost a study a fifth of a second of
    imports).
    """
    T = float(period)

    def excess(log_r: float) -> float:
        return float(np.sqrt(2 * _cv_posterior(accel_var, T, 10**log_r)[0, 0]) - rmse_position)

    lo, hi = -12.0, 12.0  # log10 r
    if excess(lo) >= 0:
        log_r = lo
    elif excess(hi) <= 0:
        log_r = hi
    else:
        while hi - lo > 1e-13:
            mid = 0.5 * (lo + hi)
            if mid in (lo, hi):
                break
            lo, hi = (mid, hi) if excess(mid) < 0 else (lo, mid)
        log_r = 0.5 * (lo + hi)
    return float(np.sqrt(2 * _cv_posterior(accel_var, T, 10**log_r)[1, 1]))


def _cv_posterior(q: float, T: float, r: float) -> np.ndarray:
    """Steady-state covariance after the measurement update of the Kalman filter of one axis of a
    constant-velocity target, ``x' = F x + w`` (``F = [[1, T], [0, 1]]``, ``Q = q [[T^3/3, T^2/2], [T^2/2, T]]``),
    ``y = x[0] + v`` (variance ``r``).

    The predicted covariance ``P`` solves ``P = F P F' - F P H' (H P H' + r)^-1 H P F' + Q``, i.e. the control
    Riccati equation ``X = A' X (I + G X)^-1 A + Q`` with ``A = F'``, ``G = H' H / r``; it is found by the
    structure-preserving doubling algorithm (Chu, Fan and Lin 2005: quadratic convergence, no eigenvalue
    problem), tested against python-control's ``dlqe``.
    """
    A = np.array([[1.0, 0.0], [T, 1.0]])  # F'
    G = np.array([[1.0 / r, 0.0], [0.0, 0.0]])
    X = q * np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]])
    eye = np.eye(2)
    for _ in range(200):
        WV = np.linalg.solve(eye + G @ X, np.hstack([A, G]))  # (I + G X)^-1 [A, G]
        W = WV[:, :2]
        X_next = X + A.T @ X @ W
        G = G + A @ WV[:, 2:] @ A.T
        A = A @ W
        done = np.abs(X_next - X).max() <= 1e-15 * np.abs(X_next).max()
        X = 0.5 * (X_next + X_next.T)
        if done:
            break
    return X - np.outer(X[:, 0], X[0, :]) / (X[0, 0] + r)
