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

The iteration is Anderson-accelerated (safeguarded, see :class:`_Anderson`); the
plain iteration reaches the same fixed point (tested), only more slowly.

Theorem 2's condition is evaluated at the fixed point and reported apart
(``theorem2``): it is a sufficient condition for mean-square boundedness of the
error, not a condition for the bound to exist.  ``binding`` names the condition
with the least relative slack at the fixed point, or the one that failed.
"""
from __future__ import annotations

from typing import Callable, NamedTuple, Sequence

import numpy as np

from .bounds import condition28_margin, condition29_margin, optimal_gain, prediction_bound, theorem2_margin, update_bound
from .network import SensorNetwork
from .validation import InputError
from .tuning import MARGIN, lam_max, neighbour_groups, tune_prediction, tune_update, tune_weighted

__all__ = ["SteadyState", "steady_state"]

_BLOWUP = 1e8
_UNBOUNDED = 1e4  # a steady-state trace beyond 1e4 x max(tr Φ_0, tr Q) is reported as unbounded


class _Anderson:
    """Anderson acceleration (type II) of the fixed-point iteration Φ <- T(Φ), with a safeguard.

    The candidate is used only when every node's matrix is symmetric positive
    definite, else the point 1/2 or 1/4 of the way from T(Φ) to it, else the plain step
    T(Φ) (and the memory is cleared); when the residual ``||T(Φ) - Φ||`` grew since the
    last point, the memory is cleared and the plain step taken.  The conditions are always
    checked on the points where the true map T is evaluated, and convergence is
    declared only when T(Φ) = Φ to the tolerance, so the answer is a fixed point
    of the recursion whatever the acceleration did.
    """

    def __init__(self, memory: int):
        self.memory = memory
        self.xs: list[np.ndarray] = []
        self.gs: list[np.ndarray] = []
        self.res = np.inf  # the residual ||T(Φ) - Φ|| at the last point taken

    def step(self, x: np.ndarray, gx: np.ndarray, admissible: Callable[[np.ndarray], bool] | None = None
             ) -> np.ndarray:
        """The next point from ``x`` and ``T(x)``; ``admissible(point)`` (default: every matrix of ``point``
        positive definite) decides whether an extrapolated point may be taken."""
        if admissible is None:
            def admissible(c):
                return np.all(np.isfinite(c)) and np.all(np.linalg.eigvalsh(c)[:, 0] > 0)
        res = float(np.linalg.norm(gx - x))
        if self.xs and res > self.res:  # the last extrapolation made things worse: restart from the plain step
            self.xs, self.gs, self.res = [], [], res
            return gx
        self.res = res
        self.xs.append(x.ravel().copy())
        self.gs.append(gx.ravel().copy())
        self.xs, self.gs = self.xs[-self.memory - 1:], self.gs[-self.memory - 1:]
        if len(self.xs) < 2:
            return gx
        F = np.array([g - xx for g, xx in zip(self.gs, self.xs)]).T  # residuals, one column per iterate
        dF = np.diff(F, axis=1)
        dG = np.diff(np.array(self.gs).T, axis=1)
        gamma, *_ = np.linalg.lstsq(dF, F[:, -1], rcond=None)
        cand = (self.gs[-1] - dG @ gamma).reshape(gx.shape)
        if cand.ndim == 3:
            cand = 0.5 * (cand + np.swapaxes(cand, -1, -2))
        for t in (1.0, 0.5, 0.25):  # backtrack towards the plain step until the point is admissible
            c = gx + t * (cand - gx)
            if admissible(c):
                return c
        self.xs, self.gs = [], []
        return gx


class SteadyState(NamedTuple):
    feasible: bool
    trace_bound: float  # mean over nodes of tr Φ at the fixed point (NaN when infeasible)
    binding: str
    iterations: int
    theorem2: bool
    phi: np.ndarray | None  # (N, n, n) fixed point


def steady_state(F: np.ndarray, H: Sequence[np.ndarray], Q: np.ndarray, R: Sequence[np.ndarray],
                 network: SensorNetwork, *, epsilon: float, delta: float, U: np.ndarray, V,
                 mode: str = "tuned", sigma: float = 0.1, beta: float = 0.1, tau: float = 0.01,
                 phi0: np.ndarray | None = None, tol: float = 1e-8, max_iter: int = 400,
                 accelerate: bool = True, scaling: Callable | None = None, fdi_span=None,
                 weights: str = "paper") -> SteadyState:
    """Iterate the stationary bound recursion to its fixed point (see the module docstring).

    Mode ``'tuned'``: ``weights='paper'`` iterates the tuned (27) with the paper's factors
    (1 + 2 d_i) and 3 (:func:`designer.tuning.tune_update`); ``weights='optimal'`` the weighted
    (27) of the run-time tuned filter (:func:`designer.tuning.tune_weighted`, one block step per
    iteration, the weights part of the iterate), with one group per neighbour (its ``Φ_pred``
    times the probability its packet arrives) and one for the falsified packets
    (``δ² E[(Σ_j γ_j)²] Π``, ``fdi_span`` = Π, default I).  The optimal weights give a much
    smaller bound but a recursion that contracts slowly (on the indoor robot: trace 0.42 vs
    9.3, in about 550 iterations and 13 s vs 30 iterations and 0.4 s), so the maps use the
    paper's factors until the iteration is batched.

    ``V``: one matrix for every sensor or one per sensor.  ``scaling``: for a Hessian-derived
    linearisation, ``scaling(i, phi_post_i, phi_pred_i) -> ((U, D_f), (V_i, D_h))`` at every
    iterate (``phi_pred_i`` None on the prediction call); None keeps ``U``, ``V`` fixed.
    """
    n_nodes, nx = network.n_nodes, F.shape[0]
    Vs = list(V) if isinstance(V, (list, tuple)) else [V] * n_nodes
    pred_scale = [None] * n_nodes
    deg = network.degrees
    s = ((1.0 - network.dos_prob) * network.adjacency).sum(axis=1)
    w_phi = 3.0 * (1.0 - network.dos_prob) * network.adjacency
    w_xi = 3.0 * delta**2 * (network.fdi_prob * network.adjacency).sum(axis=1)
    phi = np.broadcast_to(np.eye(nx) if phi0 is None else phi0, (n_nodes, nx, nx)).copy()
    sig = np.zeros(n_nodes)
    scale = max(float(np.trace(phi, axis1=1, axis2=2).max()), float(np.trace(Q)))
    accel = _Anderson(memory=5)
    slack28 = np.zeros(n_nodes)
    slack29 = np.zeros(n_nodes)
    # Mode tuned: the weights of (27) are part of the iterate (one block step of tune_weighted per
    # iteration), so that the accelerated map is a function of its state alone.
    if weights not in ("paper", "optimal"):
        raise InputError(f"weights must be 'paper' or 'optimal', got {weights!r}")
    optimal = mode == "tuned" and weights == "optimal"
    node_weights = [None] * n_nodes
    for it in range(1, max_iter + 1):
        pred = np.empty_like(phi)
        for i in range(n_nodes):
            Ui, Df = (U, None) if scaling is None else scaling(i, phi[i], None)[0]
            pred_scale[i] = Df
            if mode == "tuned":
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
            if mode == "tuned" and not optimal:
                ch = tune_update(pred[i], H[i], s[i], Vi, R[i], int(deg[i]), neigh[i], D=Dh)
                b, new[i] = ch.beta, ch.phi_post
            elif mode == "tuned":
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
            if condition28_margin(new[i], sig[i], epsilon, pred_scale[i]) <= 0:
                return SteadyState(False, np.nan, "(28)", it, False, None)
        change = max(np.abs(new[i] - phi[i]).max() / np.abs(new[i]).max() for i in range(n_nodes))
        if optimal:
            change = max(change, max(float(np.abs(a - b).max()) for a, b in zip(new_weights, node_weights)))
        if np.trace(new, axis1=1, axis2=2).max() > _UNBOUNDED * scale:
            return SteadyState(False, np.nan, "unbounded", it, False, None)
        if change < tol:
            phi = new
            d_max = network.d_max
            th2 = all(theorem2_margin(phi[i], sig[i], d_max) >= 0 for i in range(n_nodes))
            binding = "(28)" if slack28.min() <= slack29.min() else "(29)"
            if min(slack28.min(), slack29.min()) > MARGIN * (1 + 1e-6):
                binding = "none (interior optimum)" if mode == "tuned" else binding
            return SteadyState(True, float(np.trace(phi, axis1=1, axis2=2).mean()), binding, it, th2, phi)
        if not optimal:
            phi = accel.step(phi, new) if accelerate else new
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

        nxt = accel.step(np.concatenate([phi.ravel()] + node_weights), np.concatenate([new.ravel()] + new_weights),
                         admissible)
        ph, ws = unpack(nxt)
        phi, node_weights = 0.5 * (ph + np.swapaxes(ph, 1, 2)), [w / w.sum() for w in ws]
    return SteadyState(False, float(np.trace(phi, axis1=1, axis2=2).mean()), "no convergence", max_iter, False, None)
