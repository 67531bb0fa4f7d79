"""Steady-state feasibility of the consensus-filter bounds at an operating point.

For a time-invariant linearisation (``F``, ``H_i`` at an operating point) and the
expected number of received packets ``s_i = Σ_j (1 - φ̄_ij)``, the bound recursion
of every node is the map ``Φ_{k|k} -> Φ_{k+1|k+1}`` of (26)-(27) with the tuned
(or the paper's) σ, β, C, K.  We iterate it from ``Φ_0`` as a fixed-point
iteration and decide:

* **feasible** — the iteration converges (relative change of every node's Φ below
  ``tol``) while (28)-(29) hold at every iterate: a bounded steady-state bound
  exists and is the reported ``trace_bound`` (mean over nodes of tr Φ);
* **infeasible** — (28) or (29) fails at some iterate, Φ leaves numerically
  meaningful values, the trace grows beyond ``1e4 x max(tr Φ_0, tr Q)``
  (``"unbounded"``), or no convergence within ``max_iter`` (``"no convergence"``).

The iteration is Anderson-accelerated (safeguarded: :class:`designer.anderson.Anderson`); the
plain iteration reaches the same fixed point (tested), only more slowly.  A map iterates
all its points at once (:func:`steady_state_batch`: every node of every point in one stacked
evaluation per iteration, each point with its own checks and acceleration), with the answers
:func:`steady_state` gives point by point.

Theorem 2's condition is evaluated at the fixed point and reported apart
(``theorem2``): it is a sufficient condition for mean-square boundedness of the
error, not a condition for the bound to exist.  ``binding`` names the condition
with the least relative slack at the fixed point, or the one that failed.
"""
from __future__ import annotations

from typing import Callable, NamedTuple, Sequence

import numpy as np

from .anderson import Anderson
from .bounds import (condition28_margin, condition29_margin, optimal_gain, prediction_bound, prediction_recursion,
                     theorem2_margin, update_bound)
from .network import SensorNetwork
from .validation import InputError
from .tuning import (MARGIN, lam_max, neighbour_groups, tune_prediction, tune_prediction_batch, tune_update,
                     tune_update_batch, tune_weighted)

__all__ = ["SteadyState", "steady_state", "steady_state_batch"]

_BLOWUP = 1e8
_UNBOUNDED = 1e4  # a steady-state trace beyond 1e4 x max(tr Φ_0, tr Q) is reported as unbounded


class SteadyState(NamedTuple):
    feasible: bool
    trace_bound: float  # mean over nodes of tr Φ at the fixed point (NaN when infeasible)
    binding: str
    iterations: int
    theorem2: bool
    phi: np.ndarray | None  # (N, n, n) fixed point


def steady_state(F: np.ndarray, H: Sequence[np.ndarray], Q: np.ndarray, R: Sequence[np.ndarray],
                 network: SensorNetwork, *, epsilon: float, delta: float, U: np.ndarray, V,
                 fixed_multipliers: bool = False, sigma: float = 0.1, beta: float = 0.1, tau: float = 0.01,
                 phi0: np.ndarray | None = None, tol: float = 1e-8, max_iter: int = 400,
                 accelerate: bool = True, scaling: Callable | None = None, fdi_span=None,
                 weights: str = "paper") -> SteadyState:
    """Iterate the stationary bound recursion to its fixed point (see the module docstring).

    ``fixed_multipliers``: σ, β, τ as given (the rules of fixed multipliers: ``C = τ Φ_pred`` and the gain (30));
    else the design chooses them per node (:mod:`designer.tuning`).  Then ``weights='paper'`` iterates the tuned (27) with the paper's factors
    (1 + 2 d_i) and 3 (:func:`designer.tuning.tune_update`); ``weights='optimal'`` the weighted
    (27) of the run-time tuned filter (:func:`designer.tuning.tune_weighted`, one block step per
    iteration, the weights part of the iterate), with one group per neighbour (its ``Φ_pred``
    times the probability its packet arrives) and one for the falsified packets
    (``δ² E[(Σ_j γ_j)²] Π``, ``fdi_span`` = Π, default I).  The optimal weights give a much
    smaller bound but a recursion that contracts slowly (on the indoor robot: trace 0.42 vs
    9.3, in about 550 iterations and 13 s vs 30 iterations and 0.4 s), so the maps use the
    paper's factors (:func:`steady_state_batch` iterates those at many points at once).

    ``V``: one matrix for every sensor or one per sensor.  ``scaling``: for a Hessian-derived
    linearisation, ``scaling(i, phi_post_i, phi_pred_i) -> ((U, D_f), (V_i, D_h))`` at every
    iterate (``phi_pred_i`` None on the prediction call); None keeps ``U``, ``V`` fixed.
    """
    n_nodes, nx = network.n_nodes, F.shape[0]
    Vs = _per_sensor(V, n_nodes)
    pred_scale = [None] * n_nodes
    deg = network.degrees
    s, w_phi, w_xi = _expected_packets(network, delta)
    phi = _start(phi0, n_nodes, nx)
    sig = np.zeros(n_nodes)
    scale = _scale(phi, Q)
    accel = Anderson(1, memory=5)
    slack28 = np.zeros(n_nodes)
    slack29 = np.zeros(n_nodes)
    # Multipliers chosen: the weights of (27) are part of the iterate (one block step of tune_weighted per
    # iteration), so that the accelerated map is a function of its state alone.
    if weights not in ("paper", "optimal"):
        raise InputError(f"weights must be 'paper' or 'optimal', got {weights!r}")
    optimal = not fixed_multipliers and weights == "optimal"
    node_weights = [None] * n_nodes
    for it in range(1, max_iter + 1):
        pred = np.empty_like(phi)
        for i in range(n_nodes):
            Ui, Df = (U, None) if scaling is None else scaling(i, phi[i], None)[0]
            pred_scale[i] = Df
            if not fixed_multipliers:
                ch = tune_prediction(phi[i], F, Ui, Q, epsilon, D=Df)
                sig[i], pred[i] = ch.sigma, ch.phi_pred
            else:
                pb = prediction_bound(phi[i], F, Ui, Q, sigma, epsilon, Df)
                if pb.phi_pred is None:
                    return SteadyState(False, np.nan, "(28)", it, False, None)
                sig[i], pred[i] = sigma, pb.phi_pred
            lam = lam_max(phi[i], Df)
            slack28[i] = 1.0 - (1.0 + epsilon) * sig[i] * lam
        neigh = np.einsum("ij,jab->iab", w_phi, pred) + w_xi[:, None, None] * np.eye(nx)
        new = np.empty_like(phi)
        new_weights = [None] * n_nodes
        for i in range(n_nodes):
            Vi, Dh = (Vs[i], None) if scaling is None else scaling(i, phi[i], pred[i])[1]
            if not fixed_multipliers and not optimal:
                ch = tune_update(pred[i], H[i], s[i], Vi, R[i], int(deg[i]), neigh[i], D=Dh)
                b, new[i] = ch.beta, ch.phi_post
            elif not fixed_multipliers:
                nb = list(network.neighbours[i])
                groups = neighbour_groups(pred[nb], network.fdi_prob[i, nb], delta, 1.0 - network.dos_prob[i, nb],
                                          span=fdi_span)
                if node_weights[i] is None:
                    node_weights[i] = np.full(len(groups) + 1, 1.0 / (len(groups) + 1))
                ch = tune_weighted(pred[i], H[i], s[i], Vi, R[i], groups, D=Dh, weights=node_weights[i], tol=0.0,
                                   max_iter=1)
                b, new[i], new_weights[i] = ch.beta, ch.phi_post, ch.weights
            else:
                if condition29_margin(pred[i], beta, Dh) <= 0:
                    return SteadyState(False, np.nan, "(29)", it, False, None)
                C = tau * pred[i]
                K = optimal_gain(pred[i], H[i], C, s[i], beta, Vi, R[i], int(deg[i]), Dh)
                b, new[i] = beta, update_bound(pred[i], H[i], K, C, s[i], beta, Vi, R[i], int(deg[i]), neigh[i], Dh)
            slack29[i] = 1.0 - b * lam_max(pred[i], Dh)
        if not np.all(np.isfinite(new)) or np.trace(new, axis1=1, axis2=2).max() > _BLOWUP:
            return SteadyState(False, np.nan, "diverged", it, False, None)
        for i in range(n_nodes):
            if not condition28_margin(new[i], sig[i], epsilon, pred_scale[i]) > 0:  # NaN: no σ was found
                return SteadyState(False, np.nan, "(28)", it, False, None)
        change = max(np.abs(new[i] - phi[i]).max() / np.abs(new[i]).max() for i in range(n_nodes))
        if optimal:
            change = max(change, max(float(np.abs(a - b).max()) for a, b in zip(new_weights, node_weights)))
        if np.trace(new, axis1=1, axis2=2).max() > _UNBOUNDED * scale:
            return SteadyState(False, np.nan, "unbounded", it, False, None)
        if change < tol:
            th2 = all(theorem2_margin(new[i], sig[i], network.d_max) >= 0 for i in range(n_nodes))
            return _converged(new, th2, slack28, slack29, fixed_multipliers, it)
        if not optimal:
            phi = accel.step([0], phi[None], new[None])[0] if accelerate else new
            continue
        if not accelerate:
            phi, node_weights = new, new_weights
            continue
        cuts = np.cumsum([n_nodes * nx * nx] + [len(w) for w in node_weights])[:-1]

        def unpack(v):
            parts = np.split(v, cuts)
            return parts[0].reshape(phi.shape), parts[1:]

        def admissible(v):
            ph, ws = unpack(v)
            return (np.all(np.isfinite(v)) and np.all(np.linalg.eigvalsh(0.5 * (ph + np.swapaxes(ph, 1, 2)))[:, 0] > 0)
                    and all(np.all(w > 0) for w in ws))

        nxt = accel.step([0], np.concatenate([phi.ravel()] + node_weights)[None],
                         np.concatenate([new.ravel()] + new_weights)[None],
                         lambda c: np.array([admissible(v) for v in c]))[0]
        ph, ws = unpack(nxt)
        phi, node_weights = 0.5 * (ph + np.swapaxes(ph, 1, 2)), [w / w.sum() for w in ws]
    return _unconverged(phi, max_iter)


def _per_sensor(V, n_nodes: int) -> list:
    """``V``: one matrix for every sensor or one per sensor -> one per sensor."""
    return list(V) if isinstance(V, (list, tuple)) else [V] * n_nodes


def _expected_packets(network: SensorNetwork, delta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``s_i`` (the expected number of packets received), the neighbour weights ``3 (1 - φ̄_ij)`` of (27) and
    its FDI term ``3 δ² Σ_j γ̄_ij`` per node."""
    s = ((1.0 - network.dos_prob) * network.adjacency).sum(axis=1)
    w_phi = 3.0 * (1.0 - network.dos_prob) * network.adjacency
    w_xi = 3.0 * delta**2 * (network.fdi_prob * network.adjacency).sum(axis=1)
    return s, w_phi, w_xi


def _start(phi0, n_nodes: int, nx: int) -> np.ndarray:
    return np.broadcast_to(np.eye(nx) if phi0 is None else phi0, (n_nodes, nx, nx)).copy()


def _scale(phi: np.ndarray, Q: np.ndarray) -> float:
    """``max(tr Φ_0, tr Q)``: what a trace is "unbounded" against."""
    return max(float(np.trace(phi, axis1=1, axis2=2).max()), float(np.trace(Q)))


def _converged(phi, theorem2: bool, slack28, slack29, fixed_multipliers: bool, it: int) -> SteadyState:
    """The answer at a fixed point ``phi`` (N, n, n): the binding condition from the relative slacks."""
    binding = "(28)" if slack28.min() <= slack29.min() else "(29)"
    if min(slack28.min(), slack29.min()) > MARGIN * (1 + 1e-6):
        binding = binding if fixed_multipliers else "none (interior optimum)"
    return SteadyState(True, float(np.trace(phi, axis1=1, axis2=2).mean()), binding, it, bool(theorem2), phi)


def _unconverged(phi, max_iter: int) -> SteadyState:
    return SteadyState(False, float(np.trace(phi, axis1=1, axis2=2).mean()), "no convergence", max_iter, False, None)


def steady_state_batch(F: np.ndarray, H: Sequence[np.ndarray], Q: np.ndarray, R: Sequence[np.ndarray],
                       networks: Sequence[SensorNetwork], *, epsilon, delta, U, V, fixed_multipliers: bool = False, sigma=0.1,
                       beta=0.1, tau=0.01, phi0: np.ndarray | None = None, tol: float = 1e-8, max_iter: int = 400,
                       accelerate: bool = True, scaling: Callable | None = None) -> list[SteadyState]:
    """:func:`steady_state` (with the paper's weights where the multipliers are chosen) at many points at once: one answer per
    point, each the one :func:`steady_state` gives for that point alone.

    Point ``p`` has the network ``networks[p]`` (its attack probabilities; every network has the same nodes),
    ``epsilon``, ``delta``, ``sigma``, ``beta``, ``tau`` (a number for every point or one per point), ``U``
    ((n, n) or one per point) and ``V[p]`` (a sequence over the points of what :func:`steady_state` takes as
    ``V``).  Every iteration evaluates (26)-(27) at every node of every point not yet decided in one stacked
    computation (:func:`designer.tuning.tune_prediction_batch`, :func:`designer.tuning.tune_update_batch`,
    or the paper's choices through :mod:`designer.bounds`); the checks, the Anderson acceleration with its
    safeguards and restarts, and the convergence test are the point's own, so a point takes the steps it
    takes alone.  ``scaling(i, phi_post, phi_pred)`` as in :func:`steady_state`, called with node ``i``'s
    matrices at every point still iterating, stacked ``(m, n, n)``; it returns stacks (or one matrix) of U, V.
    """
    if not len(networks):
        return []
    pts = _Points(F, H, Q, R, networks, epsilon, delta, U, V, fixed_multipliers, sigma, beta, tau, scaling)
    P, N, nx = len(networks), pts.N, pts.nx
    phi = np.array(np.broadcast_to(_start(phi0, N, nx), (P, N, nx, nx)))
    scale = _scale(phi[0], Q)
    accel = Anderson(P, memory=5)
    out: list[SteadyState | None] = [None] * P
    live = np.arange(P)
    for it in range(1, max_iter + 1):
        if not live.size:
            break
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # a diverging bound: the checks below
            live, step = pts.iterate(live, phi, it, out)
            if step is None:
                continue
            ph, new, sig, e_it, Df, slack28, slack29, fail = step
            L = live.size
            trace = np.trace(new, axis1=-2, axis2=-1)
            diverged = ~np.isfinite(new).all(axis=(1, 2, 3)) | (trace.max(axis=1) > _BLOWUP)
            # NaN: the tuned σ search found none (e.g. tr U Uᵀ overflows); never a pass, as in the filters
            bad28 = ~(condition28_margin(new.reshape(-1, nx, nx), sig, e_it, Df) > 0).reshape(L, N).all(axis=1)
            change = (np.abs(new - ph).max(axis=(-2, -1)) / np.abs(new).max(axis=(-2, -1))).max(axis=1)
        sig = sig.reshape(L, N)
        going = np.zeros(L, dtype=bool)
        for k, p in enumerate(live):  # the point's own checks, in the order of steady_state
            why = ("(29)" if fail[k] else "diverged" if diverged[k] else "(28)" if bad28[k]
                   else "unbounded" if trace[k].max() > _UNBOUNDED * scale else None)
            if why is not None:
                out[p] = SteadyState(False, np.nan, why, it, False, None)
            elif change[k] < tol:
                th2 = np.all(theorem2_margin(new[k], sig[k], networks[p].d_max) >= 0)
                out[p] = _converged(new[k].copy(), th2, slack28[k], slack29[k], fixed_multipliers, it)
            else:
                phi[p] = accel.step([p], ph[k][None], new[k][None])[0] if accelerate else new[k]
                going[k] = True
        live = live[going]
    for p in live:
        out[p] = _unconverged(phi[p], max_iter)
    return out


class _Points:
    """What :func:`steady_state_batch` holds per point, and one step of the recursion at many points."""

    def __init__(self, F, H, Q, R, networks, epsilon, delta, U, V, fixed_multipliers, sigma, beta, tau, scaling):
        P = len(networks)
        self.N, self.nx = networks[0].n_nodes, F.shape[0]
        if any(net.n_nodes != self.N for net in networks):
            raise InputError("every point's network must have the same nodes")
        if len(V) != P:
            raise InputError(f"V must hold one entry per point ({P}), got {len(V)}")

        def per_point(x):
            return np.array(np.broadcast_to(np.asarray(x, dtype=float), (P,)))

        self.F, self.H, self.Q, self.R, self.fixed, self.scaling = F, H, Q, R, fixed_multipliers, scaling
        self.eps, delta, self.sigma, self.beta, self.tau = (per_point(x) for x in (epsilon, delta, sigma, beta, tau))
        self.U = np.broadcast_to(np.asarray(U, dtype=float), (P, self.nx, self.nx))
        self.V = [np.stack([np.asarray(_per_sensor(v, self.N)[i], dtype=float) for v in V])  # (P, nz_i, nz_i)
                  for i in range(self.N)]
        self.packets = [_expected_packets(net, d) for net, d in zip(networks, delta)]
        self.s = np.array([p[0] for p in self.packets])
        self.deg = np.array([net.degrees for net in networks])
        # the update runs over the nodes whose sensors share a dimension (with a scaling, node by node: the
        # structure of each node's remainder may differ)
        dims: dict[int, list[int]] = {}
        for i in range(self.N):
            dims.setdefault(int(np.shape(H[i])[0]), []).append(i)
        self.groups = [[i] for i in range(self.N)] if scaling is not None else list(dims.values())

    def iterate(self, live, phi, it, out):
        """Φ -> (26) -> (27) at every node of the points ``live``, stacked.

        Points whose prediction fails (28) (fixed multipliers) are decided here (``out``) and leave ``live``; returns
        the points left and, for them, ``(Φ, Φ', σ, ε, D_f, slack28, slack29, failed (29))`` (None when no point
        is left).
        """
        N, nx = self.N, self.nx
        L = live.size
        ph = phi[live]
        if self.scaling is None:
            U, Df = np.repeat(self.U[live], N, axis=0).reshape(L, N, nx, nx), None
        else:
            U = np.empty((L, N, nx, nx))
            for i in range(N):
                U[:, i], Df = self.scaling(i, ph[:, i], None)[0]
        eps = np.repeat(self.eps[live], N)
        if not self.fixed:
            ch = tune_prediction_batch(ph.reshape(-1, nx, nx), self.F, U.reshape(-1, nx, nx), self.Q, eps, D=Df)
            sig, pred = ch.sigma, ch.phi_pred
        else:  # the paper's sigma, where (28) holds at every node
            sig = np.repeat(self.sigma[live], N)
            fail = (condition28_margin(ph.reshape(-1, nx, nx), sig, eps, Df) <= 0).reshape(L, N).any(axis=1)
            for p in live[fail]:
                out[p] = SteadyState(False, np.nan, "(28)", it, False, None)
            if fail.any():
                on = np.repeat(~fail, N)
                live, ph, U, sig, eps = live[~fail], ph[~fail], U[~fail], sig[on], eps[on]
                L = live.size
            if not L:
                return live, None
            pred = prediction_recursion(ph.reshape(-1, nx, nx), self.F, U.reshape(-1, nx, nx), self.Q, sig, eps, Df)
        slack28 = (1.0 - (1.0 + eps) * sig * lam_max(ph.reshape(-1, nx, nx), Df)).reshape(L, N)
        pred = pred.reshape(L, N, nx, nx)
        neigh = np.array([np.einsum("ij,jab->iab", self.packets[p][1], pred[k])
                          + self.packets[p][2][:, None, None] * np.eye(nx) for k, p in enumerate(live)])
        new = np.empty_like(pred)
        b, lam29 = np.empty((L, N)), np.empty((L, N))
        fail = np.zeros(L, dtype=bool)
        for nodes in self.groups:
            b[:, nodes], lam29[:, nodes], new[:, nodes], bad = self._update(live, ph, pred, neigh, nodes)
            fail |= bad
        return live, (ph, new, sig, eps, Df, slack28, 1.0 - b * lam29, fail)

    def _update(self, live, ph, pred, neigh, nodes):
        """(27) at ``nodes`` (sensors of one dimension) of the points ``live``: β, λ_max(Φ_pred), Φ' per item and
        the points where (29) fails (fixed multipliers)."""
        L, k, nx = live.size, len(nodes), self.nx
        pg = pred[:, nodes].reshape(L * k, nx, nx)
        if self.scaling is None:
            V, Dh = np.stack([self.V[i][live] for i in nodes], axis=1), None
        else:
            Vi, Dh = self.scaling(nodes[0], ph[:, nodes[0]], pred[:, nodes[0]])[1]
            V = np.broadcast_to(Vi, (L,) + np.shape(Vi)[-2:])[:, None]
        nz = V.shape[-1]
        V = V.reshape(L * k, nz, nz)
        H = np.broadcast_to(np.stack([self.H[i] for i in nodes]), (L, k, nz, nx)).reshape(L * k, nz, nx)
        R = np.broadcast_to(np.stack([self.R[i] for i in nodes]), (L, k, nz, nz)).reshape(L * k, nz, nz)
        s, d = self.s[live][:, nodes].ravel(), self.deg[live][:, nodes].ravel()
        Nb = neigh[:, nodes].reshape(L * k, nx, nx)
        lam = lam_max(pg, Dh).reshape(L, k)
        if not self.fixed:
            ch = tune_update_batch(pg, H, s, V, R, d, Nb, D=Dh)
            return ch.beta.reshape(L, k), lam, ch.phi_post.reshape(L, k, nx, nx), np.zeros(L, dtype=bool)
        beta = np.repeat(self.beta[live], k)
        ok = ~(condition29_margin(pg, beta, Dh) <= 0)
        new = np.full((L * k, nx, nx), np.nan)
        if ok.any():  # C = tau Phi_pred, the gain (30) and the bound (27) where (29) holds
            D = None if Dh is None else np.broadcast_to(Dh, (L * k,) + np.shape(Dh)[-2:])[ok]
            C = np.repeat(self.tau[live], k)[ok][:, None, None] * pg[ok]
            K = optimal_gain(pg[ok], H[ok], C, s[ok], beta[ok], V[ok], R[ok], d[ok], D)
            new[ok] = update_bound(pg[ok], H[ok], K, C, s[ok], beta[ok], V[ok], R[ok], d[ok], Nb[ok], D)
        return beta.reshape(L, k), lam, new.reshape(L, k, nx, nx), ~ok.reshape(L, k).all(axis=1)
