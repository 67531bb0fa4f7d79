"""Observability of the nodes and of the network at an operating point, and the steady-state Kalman references.

A consensus design is only as good as what each node can learn: a node whose sensor
cannot observe the state alone needs its neighbours, and a network whose sensors
together cannot observe it cannot be made to work by any gain.  At the operating point
(``x0``, the first input) the model is linearised (``F``, ``H_i`` from its CasADi
Jacobians), which gives

* per node, the rank of the observability matrix ``[H_i; H_i F; ...]`` (what ``control.obsv``
  builds): full rank ``n_x`` means the node observes the state alone;
* for the network, the rank with every sensor stacked (collective observability, the
  condition the distributed filters of the literature need);
* the steady-state Kalman filters of that linearisation: the centralized one with every
  sensor and the local one of each node (None when the pair is not detectable: an
  unobserved mode with ``|λ| >= 1``, the PBH test), as the references a steady-state bound
  can be held against.  Their covariance is the stabilising solution of the filter's
  discrete algebraic Riccati equation, ``scipy.linalg.solve_discrete_are(Fᵀ, Hᵀ, Q, R)``: the
  call python-control's ``dlqe`` makes (without Slycot), so the same numbers, without
  importing python-control (some 2 s of every ``cfdesign design``; the tests compare the two).
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import block_diag

from .regions import region_traces

__all__ = ["observability", "kalman_references"]


def _obsv(F: np.ndarray, H: np.ndarray) -> np.ndarray:
    """The observability matrix ``[H; H F; ...; H F^(n-1)]``."""
    rows = [np.atleast_2d(np.asarray(H, dtype=float))]
    for _ in range(F.shape[0] - 1):
        rows.append(rows[-1] @ F)
    return np.vstack(rows)


def _rank(F: np.ndarray, H: np.ndarray) -> int:
    O = _obsv(np.asarray(F, dtype=float), H)
    scale = max(float(np.abs(O).max()), 1e-300)
    return int(np.linalg.matrix_rank(O, tol=1e-9 * scale * max(O.shape)))


def _linearisation(model, x0, u0):
    F = model.F_expected(x0, 0, u0)
    xp = model.f_expected(x0, 0, u0)
    H = [model.H(i, xp, 1) for i in range(model.n_sensors)]
    return F, H


def observability(model, x0, u0=None) -> dict:
    """Which nodes observe the state alone, and whether the network does, at the operating point.

    Returns ``{"n_x", "nodes": [{"node", "sensor", "rank", "observable"}], "network": {"rank",
    "observable"}, "unobservable_nodes": [...]}``.
    """
    F, H = _linearisation(model, x0, u0)
    n = model.n_x
    nodes = []
    for i, (s, Hi) in enumerate(zip(model.sensors, H)):
        r = _rank(F, Hi)
        nodes.append({"node": i, "sensor": s.name, "rank": r, "observable": r == n})
    r_all = _rank(F, np.vstack(H))
    return {"n_x": n, "nodes": nodes, "network": {"rank": r_all, "observable": r_all == n},
            "unobservable_nodes": [d["node"] for d in nodes if not d["observable"]],
            "where": "linearisation at the operating point (x0 and the first input)"}


def _detectable(F: np.ndarray, H: np.ndarray) -> bool:
    """PBH test: every mode with ``|λ| >= 1`` is seen by ``H`` (``rank [λI - F; H] = n``)."""
    n = F.shape[0]
    for lam in np.linalg.eigvals(F):
        if abs(lam) >= 1.0 - 1e-9:
            M = np.vstack([lam * np.eye(n) - F, H])
            if np.linalg.matrix_rank(M, tol=1e-9 * max(1.0, float(np.abs(M).max())) * max(M.shape)) < n:
                return False
    return True


def _posterior(F, H, Q, R) -> np.ndarray | None:
    """``P⁺`` of the steady-state Kalman filter of (F, H, Q, R); None when it does not exist.

    ``P`` the predicted covariance: the stabilising solution of ``P = F P Fᵀ - F P Hᵀ (H P Hᵀ + R)⁻¹ H P Fᵀ + Q``
    (python-control's ``dlqe(F, I, H, Q, R)`` solves the same equation by the same SciPy call)."""
    from scipy.linalg import solve_discrete_are

    if not _detectable(F, H):
        return None
    try:
        P = solve_discrete_are(np.asarray(F, dtype=float).T, np.asarray(H, dtype=float).T, Q, R)
    except Exception:  # noqa: BLE001 - not detectable / not stabilisable: no steady state
        return None
    P = np.asarray(P)
    S = H @ P @ H.T + R
    post = P - P @ H.T @ np.linalg.solve(S, H @ P)
    tr = float(np.trace(post))
    return post if np.isfinite(tr) and tr >= 0 else None


def kalman_references(model, x0, u0=None, regions=None) -> dict:
    """Steady-state posterior ``tr P`` of the centralized and of each local Kalman filter at the operating point.

    ``regions`` (:mod:`designer.regions`, one index array per node): also ``"regions"``, per node the centralized and
    the node's own local posterior traced over its region only (None where no steady state exists)."""
    F, H = _linearisation(model, x0, u0)
    Q = model.process_cov
    R = [model.measurement_cov(i) for i in range(model.n_sensors)]
    central = _posterior(F, np.vstack(H), Q, block_diag(*R))
    local = [_posterior(F, Hi, Q, Ri) for Hi, Ri in zip(H, R)]

    def tr(P, regions=None):
        if P is None:
            return None
        return float(np.trace(P)) if regions is None else [float(v) for v in region_traces(P[None], regions)]

    out = {"centralized": tr(central), "local": [tr(P) for P in local],
           "where": "steady-state Kalman filters (the Riccati equation python-control dlqe solves) of the "
                    "linearisation at the operating point; "
                    "trace of the posterior error covariance; None: no steady state (pair not detectable)"}
    if regions is not None:
        out["regions"] = {"centralized": tr(central, regions) or [None] * len(regions),
                          "local": [None if P is None else tr(P, [r])[0] for P, r in zip(local, regions)]}
    return out
