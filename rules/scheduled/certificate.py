"""The scheduled design's stationary certificate: the home of :func:`stationary_certificate`, the bound at the fixed
point of the tables' recursion at one linearisation point (the operating point), and of its LMI.

The tables' recursion is run at that point until the gains stop changing (:func:`rules.scheduled.design.
stationary_gains`), then the bound's recursion (26) + expected (27) (:func:`designer.joint.certificate_predict`,
:func:`rules.scheduled.design.expected_certificate_update`) with those time-invariant gains until it reaches a fixed
point Φ̄, and the stationary inequality is checked as an LMI for that fixed point's σ, β (cvxpy + Clarabel), the
solver's Φ̄ checked again in NumPy.  The result is a :class:`designer.stationary.StationaryCertificate`.
"""
from __future__ import annotations

import warnings

import numpy as np

from designer.anderson import REACH_WINDOW, Anderson, out_of_reach
from designer.bounds import BOUND_LIMIT, symmetrize
from designer.cores import SOLVER_SETTINGS
from designer.joint import as_difference, certificate_predict, joint_predict, joint_prior
from designer.stationary import StationaryCertificate
from designer.verdict import NOT_COMPUTED

from .nodewise import nodewise_predict, nodewise_stationary, nodewise_update
from .design import (CERTIFICATE_MAX_DIM, Channels, blocks_of, diag_blocks, expected_certificate_update,
                     falsification_moment, falsification_parts, measurement_noise, prepare, remainder_reach,
                     scaled_remainders, stationary_gains, to_dense, transition_matrix, update_structure)

__all__ = ["stationary_certificate", "STATIONARY_CERT_MAX", "STATIONARY_GROWTH", "STATIONARY_CERT_TOL",
           "STATIONARY_CERT_MEMORY",
           "LMI_MAX_DIM", "LMI_MAX_TERMS"]

#: Iterations of the stationary bound recursion before it counts as not converging.
STATIONARY_CERT_MAX = 1000
#: A stationary bound this many times its first iterate's trace is taken as growing without limit.
STATIONARY_GROWTH = 1e8
#: Relative change of tr Φ̄ and of Φ̄ (Frobenius) from a point to its image below which the stationary recursion has
#: converged.
STATIONARY_CERT_TOL = 1e-9
#: The differences of past iterates the stationary recursion's Anderson acceleration keeps (:class:`designer.anderson.
#: Anderson`, as the relay rule's stationary recursion): on a 24-node bearings model (N n = 576) the plain recursion
#: took about 150 iterations to :data:`STATIONARY_CERT_TOL`, 27 s of a feasibility map's 100 s a point.
STATIONARY_CERT_MEMORY = 5
#: The largest N n for which the stationary LMI is solved (cvxpy + Clarabel; three N n x N n variables).
LMI_MAX_DIM = 160
#: The most coefficients of ``T̄ X T̄ᵀ`` (``nnz(T̄)²``) for which the stationary LMI is solved: the solver's cost
#: follows them, not N n alone.  Measured (2 cores): a 32-node ring of 2 states (N n = 64, nnz(T̄)² = 1.5e5) 14 s and
#: 1.1 GB; an 8-node ring of 8 coupled states (N n = 64 too, 2.8e6) had not finished after 5 minutes and held 10 GB.
#: An assumption, chosen from those: 2e5 (about 20 s).  Beyond, the fixed point stands without the LMI's
#: confirmation (its status says why).
LMI_MAX_TERMS = 200_000


def stationary_certificate(model, network, design, *, x, u=None, phi0=None, exchange: bool = True,
                           lmi: bool = True) -> StationaryCertificate:
    """The stationary certificate of the scheduled design at the point ``x`` (input ``u``): the tables' recursion
    run at that linearisation until the gains stop changing (from the prior covariance), then the bound's
    recursion (26) + expected (27) with those time-invariant gains until it reaches a fixed point Φ̄, and the
    stationary inequality checked as an LMI for that fixed point's σ, β (module docstring).

    By Schur complements, for fixed σ and β the stationary inequality Φ ⪰ E_ρ[T (Y⁻¹ - βI)⁻¹ Tᵀ] + W₂ with
    Y ⪰ F (Φ⁻¹ - (1+ε)σ I)⁻¹ Fᵀ + W₁ is linear in (Φ, Y, X):

        [[Y - W₁ - F Φ Fᵀ,  F Φ], [Φ Fᵀ,  I/((1+ε)σ) - Φ]] ⪰ 0,    [[X - Y,  Y], [Y,  I/β - Y]] ⪰ 0,
        Φ - T̄ X T̄ᵀ - Σ_e p_e (1 - p_e) B_e X B_eᵀ - W₂ ⪰ 0,

    and cvxpy + Clarabel minimise tr Φ over it.  The map from Φ to the next bound is monotone, so a Φ̄ that
    satisfies the inequality bounds every later bound once one lies below it.
    """
    st, U, V, Vn, phi0 = prepare(model, network, design, exchange, phi0)
    N, n = network.n_nodes, model.n_x
    if st.rounds > 1:
        return StationaryCertificate(False, None, np.nan, np.nan, 0,
                                     f"{NOT_COMPUTED}: the certificate covers one exchange round per step "
                                     f"({st.rounds} rounds designed)", None)
    ch = st.ch
    x = np.asarray(x, dtype=float)
    F = np.asarray(model.F_expected(x, 0, u), dtype=float)
    Fs = np.broadcast_to(F, (N, n, n))
    # the time-invariant gains: the expected covariance's recursion at x until the tables stop changing
    Pm, rule, _, _, _, _, _ = stationary_gains(st, as_difference(joint_prior(phi0, N)), Fs, x, 1, None)
    # the remainders at the stationary error's reach (rules.scheduled.design.remainder_reach), after the update and
    # after the prediction
    Us = remainder_reach(Pm.P, design.remainder_structure) * U
    Vs, Vns, _ = scaled_remainders(remainder_reach(joint_predict(Pm, Fs, st.Q).P, design.remainder_structure), V,
                                   Vn, None)
    # the bound's recursion with those gains (the independent remainder blocks: those the LMI states)
    W = design.remainder_structure
    if N * n > CERTIFICATE_MAX_DIM:  # as the design's certificate over the horizon: each node's own bound
        return _nodewise(phi0, F, Us, Vs, Vns, rule, ch, st, W, N, n)
    Wn = None if W is None else [W] * N
    idx = np.arange(N)
    acc = Anderson(1, STATIONARY_CERT_MEMORY)
    x = joint_prior(phi0, N)  # the point the map is applied to: the prior, then the accelerated iterates
    sigma = beta = np.nan
    first = None
    changes, traces = [], []  # the relative change from each point to its image (Frobenius), and its trace
    for it in range(1, STATIONARY_CERT_MAX + 1):
        jb = certificate_predict(x, Fs, Us, st.Q, design.epsilon, Wn, tight=True)
        ju, why = None, None
        if not (jb.margin > 0 and np.isfinite(jb.phi).all()):
            why = f"(28) fails at iteration {it} (margin {float(jb.margin):.3g})"
        else:
            ju = expected_certificate_update(jb.phi, rule, ch, Vs, Vns, st.M, st.mu, W=W)
            if not (ju.margin > 0 and np.isfinite(ju.phi).all()):
                why = f"(29) fails at iteration {it} (margin {float(ju.margin):.3g})"
        tr = np.inf if why else float(np.trace(ju.phi[idx, idx], axis1=-2, axis2=-1).sum())
        first = tr if first is None else first
        if why is None and not tr < min(BOUND_LIMIT, STATIONARY_GROWTH * first):
            why = f"the bound grows without settling ({tr / first:.3g} x its first value at iteration {it})"
        if why is not None:
            if acc.extrapolated[0]:  # an extrapolated point the map cannot take: back to the plain step
                x = blocks_of(acc.retreat([0])[0].reshape(N * n, N * n), N)
                continue
            return StationaryCertificate(False, None, float(jb.multiplier),
                                         np.nan if ju is None else float(ju.multiplier), it, why, None)
        Phi, sigma, beta = ju.phi, float(jb.multiplier), float(ju.multiplier)
        gd, xd = to_dense(Phi), to_dense(x)
        if (abs(tr - float(np.trace(x[idx, idx], axis1=-2, axis2=-1).sum())) <= STATIONARY_CERT_TOL * tr
                and np.linalg.norm(gd - xd) <= STATIONARY_CERT_TOL * np.linalg.norm(gd)):
            out = StationaryCertificate(True, Phi[idx, idx].copy(), sigma, beta, it, None, None)
            if lmi:
                out = out._replace(lmi=_stationary_lmi(Phi, rule, ch, F, Us, Vs, Vns, st, design.epsilon, sigma, beta,
                                                       W))
            return out
        changes.append(float(np.linalg.norm(gd - xd) / np.linalg.norm(gd)))
        traces.append(tr)
        stuck = out_of_reach(changes, STATIONARY_CERT_TOL, STATIONARY_CERT_MAX)
        if stuck is not None:  # it would end unsettled: said now, not after the iterations left
            grew = tr > traces[-1 - REACH_WINDOW]
            return StationaryCertificate(False, None, sigma, beta, it, (
                f"the bound grows without settling ({tr / first:.3g} x its first value at iteration {it}, "
                f"{tr / traces[-1 - REACH_WINDOW]:.3g} x over the last {REACH_WINDOW}; {stuck})" if grew else
                f"the bound did not settle: {stuck}"), None)
        x = blocks_of(acc.step([0], xd[None], gd[None])[0], N)
    return StationaryCertificate(False, None, sigma, beta, STATIONARY_CERT_MAX,
                                 f"the bound did not settle in {STATIONARY_CERT_MAX} iterations", None)


def _nodewise(phi0, F, Us, Vs, Vns, rule, ch, st, W, N: int, n: int) -> StationaryCertificate:
    """The node-wise stationary certificate (:func:`rules.scheduled.nodewise.nodewise_stationary`): each node's bound
    iterated with the stationary gains to a fixed point, confirmed with its weights frozen (no LMI: no multipliers)."""

    fdi = falsification_parts(rule, ch, st.M, st.mu, N)  # the stationary gains': the same at every iteration

    def step(phi, weights=None):
        pb = nodewise_predict(phi, F, Us, st.Q, W, None if weights is None else weights[0])
        ub = nodewise_update(pb.phi, rule, ch, Vs, Vns, fdi, W, None if weights is None else weights[1])
        return ub.phi, (pb.weights[0], ub.weights[0])

    start = np.broadcast_to(np.asarray(phi0, dtype=float), (N, n, n))
    converged, phi, it, reason = nodewise_stationary(start, step, max_iterations=STATIONARY_CERT_MAX,
                                                     growth=STATIONARY_GROWTH)
    return StationaryCertificate(converged, phi, np.nan, np.nan, it, reason, None)


def _stationary_lmi(Phi_fp: np.ndarray, rule, ch: Channels, F, U, V, Vn, st, eps: float, sigma: float,
                    beta: float, W: np.ndarray | None = None) -> dict | None:
    """Minimise tr Φ over the stationary LMI for fixed σ, β (:func:`stationary_certificate`); the solver's Φ is
    checked against the inequality with NumPy (the residual is what the verdict trusts, not the solver's word).

    The remainders' structures are those of the recursion: ``D₁ = blockdiag(W)`` in (26) and ``D₂ =
    blockdiag(√(1 + d_i) W)`` in (27) (``1 + d_i`` remainder blocks on node i's error with measurement exchange;
    ``W`` the design's :attr:`~designer.design.ConsensusDesign.remainder_structure`, I when None), so that by
    Woodbury ``(Φ⁻¹ - s DᵀD)⁻¹ = Φ + Φ Dᵀ (I/s - D Φ Dᵀ)⁻¹ D Φ`` and the Schur complements read
    ``[[Y - W₁ - F Φ Fᵀ, F Φ D₁ᵀ], [D₁ Φ Fᵀ, I/((1+ε)σ) - D₁ Φ D₁ᵀ]] ⪰ 0`` and
    ``[[X - Y, Y D₂ᵀ], [D₂ Y, I/β - D₂ Y D₂ᵀ]] ⪰ 0``."""
    N, n = rule.A.shape[0], rule.A.shape[-1]
    D = N * n
    if D > LMI_MAX_DIM:
        return {"status": "not solved", "reason": f"N n = {D} > {LMI_MAX_DIM}", "trace": None, "max_residual": None}
    import cvxpy as cp

    c = 1.0 + eps
    I = np.eye(D)
    Fd = to_dense(diag_blocks(F, N))
    copies = np.ones(N) if rule.Kn is None else 1.0 + np.bincount(ch.receiver, minlength=N)
    D1 = np.eye(D) if W is None else np.kron(np.eye(N), W)
    D2 = update_structure(copies, W, n)
    UU = U @ np.swapaxes(U, -1, -2)
    W1 = np.kron(np.ones((N, N)), st.Q) + (to_dense(diag_blocks(UU, N)) / (c * sigma) if sigma > 0 else 0.0)
    KVV = np.stack([k @ v @ np.swapaxes(v, -1, -2) @ np.swapaxes(k, -1, -2) for k, v in zip(rule.K, V)])
    if rule.Kn is not None and ch.receiver.size:
        lv = rule.Kn @ Vn
        np.add.at(KVV, ch.receiver, ch.p[:, None, None] * (lv @ np.swapaxes(lv, -1, -2)))
    W2 = to_dense(measurement_noise(rule, ch, N) + falsification_moment(rule, ch, st.M, st.mu, N)) \
        + (to_dense(diag_blocks(KVV, N)) / beta if beta > 0 else 0.0)
    T = transition_matrix(rule, ch).toarray()
    terms = np.count_nonzero(T) ** 2
    if terms > LMI_MAX_TERMS:
        return {"status": "not solved", "reason": f"T X T^T has {terms:.3g} coefficients > {LMI_MAX_TERMS:.3g} (the "
                f"solver's time and memory grow with them)", "trace": None, "max_residual": None}
    Bs, ws = [], []
    for e in range(ch.receiver.size):  # B_e X B_eᵀ: B_e = -W_e on the receiver's own error, +C_e on the sender's
        if ch.p[e] * (1 - ch.p[e]) <= 0:
            continue
        B = np.zeros((n, D))
        i, j = ch.receiver[e], ch.sender[e]
        B[:, i * n:(i + 1) * n] -= rule.W[e]
        B[:, j * n:(j + 1) * n] += rule.C[e]
        E_i = np.zeros((D, n))
        E_i[i * n:(i + 1) * n] = np.eye(n)
        Bs.append(E_i @ B)
        ws.append(ch.p[e] * (1 - ch.p[e]))
    P, Y, X = (cp.Variable((D, D), symmetric=True) for _ in range(3))
    sym = lambda M: (M + M.T) / 2  # noqa: E731
    cons = [
        cp.bmat([[sym(Y - W1 - Fd @ P @ Fd.T), Fd @ P @ D1.T],
                 [D1 @ P @ Fd.T, sym(I / (c * sigma) - D1 @ P @ D1.T)]]) >> 0
        if sigma > 0 else sym(Y - W1 - Fd @ P @ Fd.T) >> 0,
        cp.bmat([[X - Y, Y @ D2.T], [D2 @ Y, sym(I / beta - D2 @ Y @ D2.T)]]) >> 0 if beta > 0 else X - Y >> 0,
        sym(P - T @ X @ T.T - sum(w * (B @ X @ B.T) for w, B in zip(ws, Bs)) - W2) >> 0,
    ]
    prob = cp.Problem(cp.Minimize(cp.trace(P)), cons)
    try:
        with warnings.catch_warnings():  # "may be inaccurate": the NumPy residual below is what is trusted
            warnings.simplefilter("ignore", UserWarning)
            prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11, **SOLVER_SETTINGS)
    except cp.error.SolverError as exc:
        return {"status": "solver error", "reason": str(exc), "trace": None, "max_residual": None}
    if P.value is None or prob.status not in ("optimal", "optimal_inaccurate"):
        return {"status": str(prob.status), "reason": None, "trace": None, "max_residual": None}
    Pv = 0.5 * (P.value + P.value.T)
    # an independent check in NumPy: one step of the recursion with these σ, β from Φ̄ must stay below it
    resid = float(np.max(np.linalg.eigvalsh(_fixed_step(Pv, Fd, W1, W2, T, Bs, ws, c * sigma, beta, D1, D2) - Pv)))
    top = max(float(np.max(np.linalg.eigvalsh(Pv))), 1e-300)
    return {"status": str(prob.status), "reason": None, "trace": float(np.trace(Pv)),
            "node_trace": [float(np.trace(Pv[i * n:(i + 1) * n, i * n:(i + 1) * n])) for i in range(N)],
            "max_residual": resid, "relative_residual": resid / top}


def _fixed_step(P, Fd, W1, W2, T, Bs, ws, s: float, beta: float, D1=None, D2=None) -> np.ndarray:
    """One step of the stacked bound's recursion for fixed multipliers ``s = (1+ε)σ`` and ``β`` (dense), the
    remainders' structures ``D1`` in (26) and ``D2`` in (27) (None: I)."""
    I = np.eye(P.shape[0])
    D1 = I if D1 is None else D1
    D2 = I if D2 is None else D2
    Pi = P if s == 0 else P + P @ D1.T @ np.linalg.solve(I / s - D1 @ P @ D1.T, D1 @ P)  # (P⁻¹ - s D₁ᵀD₁)⁻¹
    Y = symmetrize(Fd @ Pi @ Fd.T + W1)
    X = Y if beta == 0 else Y + Y @ D2.T @ np.linalg.solve(I / beta - D2 @ Y @ D2.T, D2 @ Y)  # (Y⁻¹ - β D₂ᵀD₂)⁻¹
    X = symmetrize(X)
    return symmetrize(T @ X @ T.T + sum(w * (B @ X @ B.T) for w, B in zip(ws, Bs)) + W2)
