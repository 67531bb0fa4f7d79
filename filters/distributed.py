"""The distributed filters of the literature, as baselines: the Kalman consensus filter and HCMCI; and the local EKFs.

Both run at every node of the project's :class:`designer.network.SensorNetwork` on the
model layer's transition and sensors (extended, EKF-linearised forms: ``F``, ``H_i`` from
the model's CasADi Jacobians, angular residual components wrapped as in
:mod:`filters.consensus`), and face the same realised channel attacks
(:class:`filters.attacks.AttackPattern`) as the consensus EKF.

**KCF** — R. Olfati-Saber, "Distributed Kalman filtering for sensor networks", IEEE CDC
2007, in the form restated as Algorithm 1 of "Kalman-Consensus Filter: Optimality,
stability, and performance", IEEE CDC 2009.  Every node ``i`` sends one packet per step to
each neighbour: its measurement information ``u_i = H_iᵀ R_i⁻¹ (z_i - h_i(x̄_i) + H_i x̄_i)``,
``U_i = H_iᵀ R_i⁻¹ H_i`` (linearised at its own prediction ``x̄_i``) and its prediction
``x̄_i``.  With ``J_i`` = ``i`` and the neighbours whose packet arrived::

    y_i = Σ_{j∈J_i} u_j,   S_i = Σ_{j∈J_i} U_j,   M_i = (P_i⁻¹ + S_i)⁻¹
    x̂_i = x̄_i + M_i (y_i - S_i x̄_i) + γ_i M_i Σ_{j∈J_i, j≠i} (x̄_j - x̄_i),   γ_i = ε / (1 + ‖M_i‖_F)
    P_i ← F M_i Fᵀ + Q,   x̄_i ← f(x̂_i)

``M_i`` is the filter's covariance (the consensus term's effect on it is ignored, as in
the paper, which also ignores the cross-covariances between nodes).  A packet carries ``U_j`` as its square-root
factor ``L_j = R_j^{-1/2} H_j`` (``U_j = L_jᵀ L_j``: ``m_j n`` numbers in place of ``n (n + 1) / 2``, zero rows up to the
model's largest sensor), and a node forms ``S_i = L_Jᵀ L_J`` from the rows ``L_J`` of ``J_i``, in place of a sum of
``d_i`` dense ``U_j`` (on a 64-cell field, one row a sensor: 5 rows of 64 states).  ``M_i`` stays in information form
(two Cholesky inverses): the covariance form ``P_i - P_i L_Jᵀ (I + L_J P_i L_Jᵀ)⁻¹ L_J P_i`` would cost less, but
loses the digits of ``P_i``'s size over ``M_i``'s (measured: 7.8e-8 relative where a prediction is 1e8 times the
posterior).

**HCMCI** — G. Battistelli, L. Chisci, G. Mugnai, A. Farina, A. Graziano, "Consensus-based
linear and nonlinear filtering", IEEE TAC 60(5), 2015 (the hybrid of consensus on
measurements and consensus on information; G. Battistelli, L. Chisci, Automatica 50, 2014,
for the consensus on information).  Every node turns its prediction into an information pair
``Ω_i = P_i⁻¹``, ``q_i = Ω_i x̄_i`` and its measurement into ``δΩ_i = U_i``, ``δq_i = u_i``
(as above), then runs ``L`` consensus rounds on all four with the Metropolis weights
``π_ij = 1 / (1 + max(d_i, d_j))`` (``π_ii = 1 - Σ_j π_ij``), and combines::

    Ω_i ← Σ_j π_ij Ω_j,  q_i ← Σ_j π_ij q_j,  δΩ_i ← Σ_j π_ij δΩ_j,  δq_i ← Σ_j π_ij δq_j   (L times)
    Ω_i⁺ = Ω_i + ω_i δΩ_i,   q_i⁺ = q_i + ω_i δq_i,   x̂_i = (Ω_i⁺)⁻¹ q_i⁺,   P_i = (Ω_i⁺)⁻¹

``omega="size"`` (default) is the paper's ``ω_i = N``: as ``L → ∞`` the averaged measurement
information times ``N`` is the sum over all sensors, and from a common prior HCMCI becomes the
centralized (E)KF.  For small ``L`` it can count a measurement more than once
(``N π⁽ᴸ⁾_ij > 1``) and be overconfident.  ``omega="consistent"``: ``ω_i = 1 / max_j r_ij``,
``r_i`` node ``i``'s row of the product of the ``L`` rounds' (realised) weight matrices — the
largest scaling that counts no measurement more than once, so that for a linear model the
covariance stays consistent for every ``L`` (covariance intersection on the priors,
independent measurement noise), ``ω_i → N`` as ``L → ∞`` and ``ω_i = 1`` (the local filter)
when every channel of the node is lost.  A node can track ``r_i`` by running the same
consensus on the ``N``-vector ``e_i`` (``N`` more numbers per packet; not counted as packets).

**The local EKFs** — every node an EKF on its own sensor alone, nothing sent (the baseline a network must beat):
the prediction above, then the update of its sensor's rows whitened, ``L = R^{-1/2} H``, ``w = R^{-1/2} (z - h(x̄))``:
``S = L P Lᵀ + I``, ``G = P Lᵀ S⁻¹``, ``x̂ = x̄ + G w`` and Joseph's form rearranged (:func:`_local_update`).

Assumptions where the papers are silent (attacks are not part of either paper):

* **KCF gain**: the CDC 2009 Algorithm 1 consensus gain ``γ M_i`` with
  ``γ = ε / (1 + ‖M_i‖_F)``; default ``ε = 0.5 / d_max`` (an assumption: the papers give no value;
  with ``ε < 1 / d_max`` the consensus correction ``‖γ M_i‖ d_i < 1`` never overshoots).
* **DoS** (a lost packet; the receiver knows it): KCF leaves the neighbour out of ``J_i`` for that
  step (its measurement information and its prediction); HCMCI gives a lost link's Metropolis
  weight to the node itself for that round (rows stay stochastic: the consensus on information
  stays a convex combination, hence consistent; it is no longer an exact average).
* **One attack realisation per step**: the DoS / FDI state of channel ``j -> i`` and its signal
  ``ξ_ij`` hold for all ``L`` rounds of step ``k`` (``attacks.dos[k]``, ``fdi[k]``, ``xi[k]``), as
  if the channel were jammed or compromised for the whole step.
* **FDI** (the receiver cannot tell): a falsified packet is the one the neighbour would send if the
  state were displaced by ``ξ_ij`` (``falsify="packet"``, default): its estimate reads ``x_j + ξ_ij``
  and its measurement ``h_j(x + ξ_ij) ≈ z_j + H_j ξ_ij`` (the law of the comparison's uplinks,
  linearised), so every information pair ``(Y, y)`` in it becomes ``(Y, y + Y ξ_ij)`` — KCF:
  ``u_j + U_j ξ_ij`` and the prediction ``x̄_j + ξ_ij`` in the consensus term; HCMCI: ``q_j + Ω_j ξ_ij``
  and ``δq_j + δΩ_j ξ_ij`` in every round.  ``falsify="estimate"``: only what the estimate
  ``x_j + ξ_ij`` with the same covariance would give (``x̄_j + ξ_ij``; ``q_j + Ω_j ξ_ij``), the
  measurement information left intact (for a linear sensor it does not depend on the estimate:
  ``H_jᵀ R_j⁻¹ (z_j - H_j x̄_j + H_j x̄_j) = H_jᵀ R_j⁻¹ z_j``).  The matrices are never falsified.
* **Messages**: a packet is one transmission of one node's message to one neighbour;
  ``messages_per_step`` counts the packets sent (``2|E|`` per step for KCF, ``2|E| L`` for HCMCI;
  DoS does not stop the sender), ``delivered_per_step`` those that arrived.
* **Divergence**: a node whose estimate or covariance leaves finite numbers, whose estimate
  exceeds ``1e12``, or whose information matrix loses positive definiteness stops the run: a
  ``'diverged'`` violation (as :class:`filters.consensus_batch.ConsensusResult`) and NaN from that step on.

**One implementation.**  Each filter is one loop batched over runs (:func:`run_kcf_batch`,
:func:`run_hcmci_batch`: every step one stack over the runs and nodes, a run that diverges stops alone);
:func:`run_kcf` and :func:`run_hcmci` are a batch of one run of them (a run alone and the same run in a
batch are the same numbers).  Every received packet is formed first (:func:`kcf_packets`, :func:`hcmci_packets`)
and summed over each node's incoming channels (:class:`filters.consensus_batch.Exchange`), so that one node handed
the packets that arrived computes the batch's numbers bit for bit: the node filters :class:`KCFNode` (``predict``
with its measurement, then ``update``) and :class:`HCMCINode` (``predict``, then ``round`` per consensus round;
``omega='size'``), driven over a run by :class:`KCFNetwork`, :class:`HCMCINetwork`; the local EKFs' node filter is
:class:`LocalEKFNode` (``step``), :class:`LocalEKFNetwork` all of them.  The node-by-node loop they
replaced is the tests' independent reference (``tests/distributed_reference.py``).
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np
from scipy.linalg import lapack

from designer.model import Model
from designer.network import SensorNetwork
from designer.validation import InputError, check_finite, check_int

from .attacks import AttackPattern
from .consensus import check_run_inputs
from .consensus_batch import EdgeAttacks, Exchange, batch_inputs, edge_attacks, wrap_residuals
from .engine import Step, estimate_arrays, history, run_batch
from .node import NodeInputs, NodeNetwork, OwnRows
from .result import DIVERGED, DIVERGED_REASON, FilterResult, diverged_nodes

__all__ = ["DistributedResult", "DistributedBatchResult", "distributed_result", "run_kcf", "run_hcmci", "run_kcf_batch",
           "run_hcmci_batch", "kcf_payload", "hcmci_payload", "metropolis_weights", "OMEGA_CHOICES", "FALSIFY_CHOICES", "kcf_packets",
           "measurement_information", "measurement_rows", "whitening", "KCFPacket", "KCFNode", "KCFNetwork", "hcmci_packets", "hcmci_weights",
           "HCMCIPacket", "HCMCINode", "HCMCINetwork", "run_local_batch", "measurement_whitened",
           "isolated", "LocalEKFNode", "LocalEKFNetwork"]

OMEGA_CHOICES = ("size", "consistent")
FALSIFY_CHOICES = ("packet", "estimate")


class DistributedResult(NamedTuple):
    """A run of a distributed filter at every node.

    ``violations`` holds at most one ``{node, step, condition: 'diverged', margin, reason}``:
    the run stopped there and every array is NaN from that step on.
    """

    x_post: np.ndarray  # (steps+1, N, n_x)
    P_post: np.ndarray  # (steps+1, N, n_x, n_x)
    x_pred: np.ndarray  # (steps, N, n_x)
    P_pred: np.ndarray  # (steps, N, n_x, n_x)
    messages_per_step: np.ndarray  # (steps,) int: packets sent (every round counted)
    delivered_per_step: np.ndarray  # (steps,) int: packets received (sent minus DoS'ed)
    violations: list
    iterations: int  # consensus rounds per step (1 for KCF)
    omega: np.ndarray | None = None  # (steps, N) HCMCI's measurement scaling ω_i (None for KCF)

    @property
    def diverged(self) -> dict | None:
        """The ``'diverged'`` violation when the run stopped early (its arrays are NaN from that step)."""
        return next((v for v in self.violations if v["condition"] == "diverged"), None)


def kcf_payload(n_x: int, network, sensor_dims) -> int:
    """The numbers KCF sends per step: one packet per directed channel carrying ``u_j`` (n), ``U_j`` as its rows
    ``L_j`` (``m_j`` rows of n, ``sensor_dims[j]``) and the prediction ``x̄_j`` (n)."""
    adj = np.asarray(network.adjacency, dtype=bool)
    out_degree = adj.sum(axis=0)  # adjacency[i, j]: the channel j -> i
    return int(out_degree.sum()) * 2 * n_x + int(out_degree @ np.asarray(sensor_dims, dtype=int)) * n_x


def hcmci_payload(n_x: int, network, iterations: int) -> int:
    """The numbers HCMCI sends per step: one packet per directed channel and consensus round carrying ``q``, ``δq``
    (n each) and the distinct entries of ``Ω``, ``δΩ`` (n (n + 1) / 2 each)."""
    return int(np.asarray(network.adjacency, dtype=bool).sum()) * int(iterations) * (2 * n_x + n_x * (n_x + 1))


def metropolis_weights(network: SensorNetwork, lost: np.ndarray | None = None) -> np.ndarray:
    """Metropolis consensus weights ``π_ij = 1 / (1 + max(d_i, d_j))`` on the edges, ``π_ii = 1 - Σ_j π_ij``.

    ``lost`` (..., N, N) bool: channels ``j -> i`` whose packet did not arrive; their weight goes to ``π_ii``
    (a stack of them, e.g. one per run, gives one weight matrix each).
    """
    d = network.degrees
    W = np.where(network.adjacency, 1.0 / (1.0 + np.maximum(d[:, None], d[None, :])), 0.0)
    if lost is not None:
        W = np.where(lost, 0.0, W)
    diag = np.arange(network.n_nodes)
    W[..., diag, diag] = 1.0 - W.sum(axis=-1)
    return W


def _check_run(model: Model, network: SensorNetwork, z, inputs, attacks, x0, P0, falsify: str):
    """One run's inputs checked with the messages of a run (``z`` (steps, n_z), one AttackPattern), before the
    batch of one is built: returns ``(z, u, x0, P0)``."""
    _check_network(model, network)
    z, u, x0, P0 = check_run_inputs(model, z, inputs, x0, P0)
    steps, n = z.shape[0], network.n_nodes
    if steps < 1:
        raise InputError(f"z must have shape (steps, {model.n_z}) with steps >= 1, got {z.shape}")
    _check_falsify(falsify)
    if attacks is not None:
        if not isinstance(attacks, AttackPattern) or not attacks.fits(n, steps, model.n_x):
            raise InputError(f"attacks must be an AttackPattern with {AttackPattern.expected(n, steps, model.n_x)}")
    return z, u, x0, P0


def _check_network(model: Model, network: SensorNetwork) -> None:
    if not isinstance(network, SensorNetwork) or network.n_nodes != model.n_sensors:
        raise InputError(f"network must be a SensorNetwork with one node per sensor ({model.n_sensors}), got "
                         f"{getattr(network, 'n_nodes', type(network).__name__)}")


def _check_falsify(falsify: str) -> None:
    if falsify not in FALSIFY_CHOICES:
        raise InputError(f"falsify must be one of {', '.join(map(repr, FALSIFY_CHOICES))}, got {falsify!r}")


#: From this many states on, :func:`_spd_inverse` inverts each matrix by LAPACK's Cholesky inverse (``potrf`` then
#: ``potri``: n³ flops, a call per matrix) rather than NumPy's stacked Cholesky and triangular solve (5 n³, one call
#: for the stack); measured, 128 matrices of 64 x 64: 12.5 against 22.6 ms, while at a few states the calls cost more
#: than the flops.  A matrix's inverse depends on its size only, not on the stack it is in: a node filter's numbers
#: are the batch's.
SPD_LAPACK_MIN = 16


def _spd_inverse(A: np.ndarray) -> np.ndarray:
    """Inverses of symmetric positive-definite matrices ``(..., n, n)`` by Cholesky (raises LinAlgError if not)."""
    A = 0.5 * (A + np.swapaxes(A, -1, -2))
    n = A.shape[-1]
    if n < SPD_LAPACK_MIN:
        L = np.linalg.cholesky(A)
        Li = np.linalg.solve(L, np.broadcast_to(np.eye(n), A.shape))
        return np.swapaxes(Li, -1, -2) @ Li
    flat = A.reshape(-1, n, n)
    out = np.empty(flat.shape)
    lower = np.tril_indices(n, -1)
    for i, a in enumerate(flat):
        c, info = lapack.dpotrf(a, lower=1, clean=0)
        if info == 0:
            c, info = lapack.dpotri(c, lower=1)
        if info != 0:
            raise np.linalg.LinAlgError("Matrix is not positive definite")
        c[lower[1], lower[0]] = c[lower]  # potri fills the lower triangle: mirrored
        out[i] = c
    return out.reshape(A.shape)


def _not_positive_definite(*mats: np.ndarray) -> int:
    """The first node whose matrix in one of ``mats`` (each (N, n, n)) has no Cholesky factor (0 if none)."""
    for i in range(len(mats[0])):
        for A in mats:
            try:
                np.linalg.cholesky(A[i])
            except np.linalg.LinAlgError:
                return i
    return 0


def _kcf_epsilon(network: SensorNetwork, epsilon) -> float:
    """KCF's ``ε``, checked (default ``0.5 / d_max``; 0 without links)."""
    if epsilon is None:
        epsilon = 0.5 / network.d_max if network.d_max else 0.0
    eps = float(check_finite("epsilon", epsilon))
    if eps < 0:
        raise InputError(f"epsilon must be >= 0 (the consensus gain gamma = epsilon / (1 + ||M||_F)), got {epsilon!r}")
    return eps


def _hcmci_rounds(iterations, omega: str) -> int:
    """HCMCI's ``L``, checked with its ``omega`` choice."""
    L = check_int("iterations", iterations, 1)
    if omega not in OMEGA_CHOICES:
        raise InputError(f"omega must be one of {', '.join(map(repr, OMEGA_CHOICES))}, got {omega!r}")
    return L


def kcf_packets(u, L, x, fdi, xi, packet: bool = True):
    """What KCF's channels carry: the senders' measurement information ``u`` (..., n) (with ``U = Lᵀ L``, ``L``
    (..., m, n)) and predictions ``x`` (..., n), where ``fdi`` (...) falsified them (``xi`` (..., n); None: no attack)
    ``x + ξ`` and, with ``packet``, ``u + U ξ`` (the measurement read as ``h(x + ξ)``, linearised).  Every KCF forms a
    received packet this way first, then sums, so that a node handed the packet that arrived computes the batch's
    numbers."""
    if fdi is None or xi is None:
        return u, x
    f = np.asarray(fdi, dtype=bool)[..., None]
    u_t = np.where(f, u + _times_information(L, xi), u) if packet else u
    return u_t, np.where(f, x + xi, x)


def _times_information(L, v):
    """``Lᵀ (L v)`` (..., n): the information ``U = Lᵀ L`` of the rows ``L`` (..., m, n) times ``v`` (..., n)."""
    return (np.swapaxes(L, -1, -2) @ (L @ v[..., None]))[..., 0]


def _kcf_combine(eps: float, xp, Pp, rows, y, diff):
    """KCF's update from ``J_i``'s measurement rows ``rows`` (..., r, n) (``S_i = rowsᵀ rows``; a zero row adds
    nothing) and the sums over ``J_i`` ``y`` of ``u_j`` and ``diff`` of ``x̃_j - x̄_i``."""
    S = np.swapaxes(rows, -1, -2) @ rows
    M = _spd_inverse(_spd_inverse(Pp) + S)
    gamma = eps / (1.0 + np.linalg.norm(M, axis=(-2, -1)))
    innov = y - (S @ xp[..., None])[..., 0] + gamma[..., None] * diff
    return xp + (M @ innov[..., None])[..., 0], M


def _slots(ex: Exchange) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """The nodes by in-degree ``d``: ``(d, nodes (g,), channels (g, d))``, each node's incoming channels in the
    channels' order.  KCF stacks a node's own measurement rows and its ``d`` channels' as one (1 + d) m x n matrix,
    the nodes of one degree together."""
    deg = np.bincount(ex.receiver, minlength=ex.n)
    first = np.cumsum(deg) - deg
    return [(int(d), np.flatnonzero(deg == d), first[deg == d][:, None] + np.arange(d)) for d in np.unique(deg)]


def _kcf_update(ex: Exchange, slots: list, eps: float, packet: bool, xp, Pp, L, u, recv, fdi=None, xi=None):
    """KCF's update of every node from its prediction ``(xp, Pp)`` and the measurement rows and information
    ``(L, u)`` of all nodes (stacks over runs; ``L`` (runs, N, m, n), ``m`` the model's largest sensor, zero rows
    below a node's own); ``recv`` (runs, N, N) the packets that arrived, ``fdi`` (runs, E), ``xi`` (runs, E, n) the
    falsified ones and their signal on the channels (``ex``'s order; None: no attack).  The packets are formed per
    channel (:func:`kcf_packets`); their information is summed over each node's incoming channels (``ex``,
    :class:`filters.consensus_batch.Exchange`) and their rows stacked after the node's own (a lost packet's zero)."""
    rcv, snd = ex.receiver, ex.sender
    r = recv[..., rcv, snd].astype(float)  # (runs, E)
    u_t, x_t = kcf_packets(u[:, snd], L[:, snd], xp[:, snd], fdi, xi, packet)
    y = u + ex.sum(r[..., None] * u_t)
    diff = ex.sum(r[..., None] * x_t) - ex.sum(r)[..., None] * xp
    x, M = np.empty_like(xp), np.empty_like(Pp)
    a, m, n = L.shape[0], L.shape[-2], L.shape[-1]
    for d, nodes, chans in slots:  # J_i's rows: the node's own, then each channel's (zero where lost)
        heard = r[:, chans, None, None] * L[:, snd[chans]]  # (runs, g, d, m, n)
        rows = np.concatenate([L[:, nodes, None], heard], axis=2).reshape(a, nodes.size, (1 + d) * m, n)
        x[:, nodes], M[:, nodes] = _kcf_combine(eps, xp[:, nodes], Pp[:, nodes], rows, y[:, nodes], diff[:, nodes])
    return x, M, None


def hcmci_packets(O, q, dO, dq, fdi, xi, packet: bool = True):
    """What HCMCI's channels carry in a round: the senders' information pairs ``(Ω, q)`` and ``(δΩ, δq)``; where
    ``fdi`` falsified them (``xi``; None: no attack) ``q + Ω ξ`` and, with ``packet``, ``δq + δΩ ξ`` (the estimate and
    the measurement read as if the state were displaced by ξ).  The matrices are never falsified."""
    if fdi is None or xi is None:
        return q, dq
    f = np.broadcast_to(np.asarray(fdi, dtype=bool), np.shape(q)[:-1])
    q_t, dq_t = np.array(q, dtype=float), np.array(dq, dtype=float)
    if f.any():  # the products for the falsified channels alone
        q_t[f] = q_t[f] + np.einsum("...ab,...b->...a", O[f], xi[f])
        if packet:
            dq_t[f] = dq_t[f] + np.einsum("...ab,...b->...a", dO[f], xi[f])
    return q_t, dq_t


def hcmci_weights(network: SensorNetwork, receiver, sender, arrived):
    """The Metropolis weights ``π_ij = 1 / (1 + max(d_i, d_j))`` of the channels ``sender -> receiver`` whose packet
    ``arrived`` (..., E) (0 where lost: its weight goes to the node itself)."""
    d = network.degrees
    return np.where(arrived, 1.0 / (1.0 + np.maximum(d[receiver], d[sender])), 0.0)


def _information(Pp, xp):
    """``Ω = P⁻¹``, ``q = Ω x`` of predictions (stacks)."""
    O = _spd_inverse(Pp)
    return O, (O @ xp[..., None])[..., 0]


def _hcmci_combine(n: int, O, q, dO, dq):
    """HCMCI's posterior from the consensus rounds' information (``ω = N``)."""
    P = _spd_inverse(O + float(n) * dO)
    return (P @ (q + float(n) * dq)[..., None])[..., 0], P


def _hcmci_update(ex: Exchange, network: SensorNetwork, L: int, omega: str, packet: bool, xp, Pp, dO, dq, recv,
                  fdi=None, xi=None):
    """HCMCI's ``L`` consensus rounds and combination at every node (arguments as :func:`_kcf_update`, with the
    measurement information ``(δΩ, δq)``); returns the posteriors and ``ω``.  Each round every channel's packet is
    formed first (:func:`hcmci_packets`) and summed over each node's incoming channels, the node's own share first."""
    n = network.n_nodes
    rcv, snd = ex.receiver, ex.sender
    arrived = recv[..., rcv, snd]
    w = hcmci_weights(network, rcv, snd, arrived)  # (runs, E)
    w_self = 1.0 - ex.sum(w)  # (runs, N): a lost link's weight stays with the node
    f = None if fdi is None else fdi & arrived
    O, q = _information(Pp, xp)
    hit = None if f is None or xi is None else np.nonzero(f)  # the falsified channels (run, channel)
    for _ in range(L):
        q_t, dq_t = q[:, snd], dq[:, snd]
        if hit is not None and hit[0].size:  # their packets alone formed (a sender's 64 x 64 Ω on every channel: 2 x
            rr, jj = hit[0], snd[hit[1]]     # 44 MB a round at 6 runs of a 64-cell field)
            q_t[hit], dq_t[hit] = hcmci_packets(O[rr, jj], q[rr, jj], dO[rr, jj], dq[rr, jj], True, xi[hit], packet)
        q, dq = (w_self[..., None] * q + ex.sum(w[..., None] * q_t),
                 w_self[..., None] * dq + ex.sum(w[..., None] * dq_t))
        O, dO = (w_self[..., None, None] * O + ex.weighted_sum(w, O),
                 w_self[..., None, None] * dO + ex.weighted_sum(w, dO))
    if omega == "size":
        x, P = _hcmci_combine(n, O, q, dO, dq)
        return x, P, np.full(xp.shape[:-1], float(n))
    W = metropolis_weights(network, network.adjacency & ~recv)
    om = 1.0 / np.linalg.matrix_power(W, L).max(axis=-1)
    P = _spd_inverse(O + om[..., None, None] * dO)
    return (P @ (q + om[..., None] * dq)[..., None])[..., 0], P, om


def run_kcf(model: Model, network: SensorNetwork, z: np.ndarray, *, inputs=None, attacks: AttackPattern | None = None,
            x0=None, P0=None, epsilon: float | None = None, falsify: str = "packet") -> DistributedResult:
    """Olfati-Saber's Kalman consensus filter (extended form) at every node over ``z`` (steps, n_z): a batch of one
    run of :func:`run_kcf_batch` (its inputs checked as one run's).

    Parameters
    ----------
    model, network : the model (one sensor per node) and the communication graph.
    z : ndarray, shape (steps, n_z)
        Stacked measurements; ``z[k]`` measures ``x_{k+1}``.
    inputs : ndarray, shape (steps, n_u), optional
    attacks : AttackPattern, optional
        Realised channel attacks (none when omitted); see the module docstring for their effect.
    x0, P0 : every node's initial estimate and covariance (default: the prior's mean and covariance).
    epsilon : float >= 0, optional
        ``ε`` of the consensus gain ``γ = ε / (1 + ‖M_i‖_F)`` (default ``0.5 / d_max``; 0 without links).
    falsify : {'packet', 'estimate'}
        What an FDI'd packet falsifies: the whole packet as if the state were displaced by ``ξ`` (default), or
        the estimate alone (see the module docstring).
    """
    z, u, x0, P0 = _check_run(model, network, z, inputs, attacks, x0, P0, falsify)
    return run_kcf_batch(model, network, z[None], inputs=u, attacks=None if attacks is None else [attacks], x0=x0,
                         P0=P0, epsilon=epsilon, falsify=falsify).detail.run(0)


def run_hcmci(model: Model, network: SensorNetwork, z: np.ndarray, *, iterations: int = 1, omega: str = "size",
              inputs=None, attacks: AttackPattern | None = None, x0=None, P0=None, falsify: str = "packet"
              ) -> DistributedResult:
    """Battistelli et al.'s hybrid consensus on measurements and information (extended form) at every node: a
    batch of one run of :func:`run_hcmci_batch` (its inputs checked as one run's).

    Parameters
    ----------
    model, network, z, inputs, attacks, x0, P0, falsify
        As :func:`run_kcf`.
    iterations : int >= 1
        ``L``, the consensus rounds per time step.
    omega : {'size', 'consistent'}
        The measurement scaling ``ω_i``: the network size ``N`` (the paper's), or the largest that counts no
        measurement more than once (see the module docstring).
    """
    z, u, x0, P0 = _check_run(model, network, z, inputs, attacks, x0, P0, falsify)
    return run_hcmci_batch(model, network, z[None], iterations=iterations, omega=omega, inputs=u,
                           attacks=None if attacks is None else [attacks], x0=x0, P0=P0, falsify=falsify).detail.run(0)


# --------------------------------------------------------------------------- many runs at once
class DistributedBatchResult(NamedTuple):
    """Many runs of a distributed filter: the fields of :class:`DistributedResult` with a leading runs axis
    (``violations`` one list per run); :meth:`run` gives run ``r`` as the per-run result."""

    x_post: np.ndarray  # (runs, steps+1, N, n_x)
    P_post: np.ndarray | None  # (runs, steps+1, N, n_x, n_x); None: run without its covariances' record
    x_pred: np.ndarray  # (runs, steps, N, n_x)
    P_pred: np.ndarray | None  # (runs, steps, N, n_x, n_x); None: as P_post
    messages_per_step: np.ndarray  # (runs, steps) int
    delivered_per_step: np.ndarray  # (runs, steps) int
    violations: list
    iterations: int
    omega: np.ndarray | None = None  # (runs, steps, N) HCMCI's ω_i (None for KCF)
    # (N, m) each node's carried states (-1: unused) when the nodes carry their regions (designer.regions): P_post
    # and P_pred are then in those coordinates, x_post and x_pred NaN where not carried
    carried: np.ndarray | None = None

    def run(self, r: int) -> DistributedResult:
        """Run ``r`` as the :class:`DistributedResult` of :func:`run_kcf` / :func:`run_hcmci`."""
        return DistributedResult(self.x_post[r], self.P_post[r], self.x_pred[r], self.P_pred[r],
                                 self.messages_per_step[r], self.delivered_per_step[r], self.violations[r],
                                 self.iterations, None if self.omega is None else self.omega[r])

    @property
    def diverged(self) -> list:
        """Per run, its ``'diverged'`` violation or None."""
        return [next((v for v in vs if v["condition"] == "diverged"), None) for vs in self.violations]



def distributed_result(detail: DistributedBatchResult) -> FilterResult:
    """The :class:`filters.result.FilterResult` a distributed filter returns (KCF, HCMCI, the relay filter): each
    node's estimate and its own covariance P (``cov_kind="covariance"``, not a bound; ``valid`` where finite), the
    packets sent per step (every round counted, ``2 |E| L``) and delivered, runtime ``local`` (a node needs only its
    neighbours' packets), ``detail`` the runs' :class:`DistributedBatchResult`; run without its covariances' record
    (``P_post`` None), no ``cov`` and ``valid`` where the estimates are finite."""
    valid = (np.isfinite(detail.x_post).all(axis=-1) if detail.P_post is None else
             np.isfinite(detail.P_post).all(axis=(-2, -1)))
    return FilterResult(detail.x_post, detail.P_post, "covariance", valid,
                        detail.violations, np.asarray(detail.messages_per_step, dtype=np.int64), "local",
                        delivered=np.asarray(detail.delivered_per_step, dtype=np.int64), detail=detail,
                        carried=detail.carried).check()


class _BatchInputs(NamedTuple):
    z: np.ndarray  # (runs, steps, n_z)
    u: np.ndarray  # (steps, n_u) shared or (runs, steps, n_u)
    x0: np.ndarray  # (runs, n_x)
    P0: np.ndarray  # (runs, n_x, n_x)
    attacks: EdgeAttacks | None  # on the network's channels: dos, fdi (runs, steps, E), xi (runs, steps, E, n_x)
    R_inv: list
    R_root: list  # per sensor W with Wᵀ W = R⁻¹ (the inverse of R's Cholesky factor)


def _check_batch(model: Model, network: SensorNetwork, z, inputs, attacks, x0, P0, falsify: str) -> _BatchInputs:
    _check_network(model, network)
    _check_falsify(falsify)
    z, u, x0, P0 = batch_inputs(model, z, inputs, x0, P0, "P0")
    runs, steps, n = z.shape[0], z.shape[1], network.n_nodes
    if attacks is not None and not isinstance(attacks, EdgeAttacks):
        if len(attacks) != runs or not all(isinstance(a, AttackPattern) and a.fits(n, steps, model.n_x)
                                           for a in attacks):
            raise InputError(f"attacks must hold one AttackPattern per run ({runs}), each with "
                             f"{AttackPattern.expected(n, steps, model.n_x)}")
    # on the channels alone (a dense pattern holds N² x n_x numbers a step: 0.8 GB a run on a 118-node grid)
    attacks = edge_attacks(network, attacks, runs, steps, model.n_x)
    return _BatchInputs(z, u, x0, P0, attacks, [_spd_inverse(model.measurement_cov(i)) for i in range(model.n_sensors)],
                        [whitening(model.measurement_cov(i)) for i in range(model.n_sensors)])


def whitening(R: np.ndarray) -> np.ndarray:
    """``W`` with ``Wᵀ W = R⁻¹``: the inverse of ``R``'s lower Cholesky factor (``W R Wᵀ = I``)."""
    R = np.asarray(R, dtype=float)
    return np.linalg.solve(np.linalg.cholesky(0.5 * (R + R.T)), np.eye(R.shape[-1]))


def _failures(x: np.ndarray, P: np.ndarray) -> np.ndarray:
    """The first node per run of stacks (a, N, ...) whose estimate or covariance is not finite or beyond the
    divergence threshold: N where none fails."""
    ok = np.isfinite(x).all(-1) & np.isfinite(P).all((-1, -2))
    ok &= np.abs(np.where(ok[..., None], x, 0.0)).max(-1) < DIVERGED
    return np.where(ok.all(-1), ok.shape[-1], np.argmin(ok, axis=-1))


def _predict(model: Model, x, P, k: int, u):
    """The EKF prediction of stacked nodes ``(a, g)`` at their own estimates: ``f(x)``, ``F P Fᵀ + Q``."""
    xp, F = model.f_expected(x, k, u), model.F_expected(x, k, u)
    Pp = model.propagate(F, P) + model.process_cov
    return xp, 0.5 * (Pp + np.swapaxes(Pp, -1, -2))


def measurement_rows(model: Model, i: int, x_pred, z, W, k: int):
    """Sensor ``i``'s information as rows: ``(L, u)`` = ``(W H, Lᵀ W (z - h(x̄) + H x̄))`` at the predictions ``x_pred``
    (a, n_x) for its measurements ``z`` (a, n_z_i) of the state at ``k + 1`` (angles wrapped), ``W`` its
    :func:`whitening` (``Lᵀ L = Hᵀ R⁻¹ H``, the ``U`` of :func:`measurement_information`)."""
    H = model.H(i, x_pred, k + 1)
    L = W @ H
    res = wrap_residuals(z - model.h(i, x_pred, k + 1), model.sensors[i].angles)
    return L, (np.swapaxes(L, -1, -2) @ (W @ (res + (H @ x_pred[..., None])[..., 0])[..., None]))[..., 0]


def measurement_whitened(model: Model, i: int, x_pred, z, W, k: int):
    """Sensor ``i``'s rows and residual whitened: ``(W H, W (z - h(x̄)))`` at the predictions ``x_pred`` (a, n_x) for
    its measurements ``z`` (a, n_z_i) of the state at ``k + 1`` (angles wrapped), ``W`` its :func:`whitening` (the
    rows' noise the identity): what the local EKF's covariance-form update takes."""
    H = model.H(i, x_pred, k + 1)
    res = wrap_residuals(z - model.h(i, x_pred, k + 1), model.sensors[i].angles)
    return W @ H, (W @ res[..., None])[..., 0]


def measurement_information(model: Model, i: int, x_pred, z, R_inv, k: int):
    """Sensor ``i``'s information ``(U, u)`` = ``(Hᵀ R⁻¹ H, Hᵀ R⁻¹ (z - h(x̄) + H x̄))`` at the predictions
    ``x_pred`` (a, n_x) for its measurements ``z`` (a, n_z_i) of the state at ``k + 1`` (angles wrapped)."""
    H = model.H(i, x_pred, k + 1)
    RiH = R_inv @ H
    res = wrap_residuals(z - model.h(i, x_pred, k + 1), model.sensors[i].angles)
    u = (np.swapaxes(RiH, -1, -2) @ (res + (H @ x_pred[..., None])[..., 0])[..., None])[..., 0]
    return np.swapaxes(H, -1, -2) @ RiH, u


def _filter_batch(model: Model, network: SensorNetwork, inp: _BatchInputs, update, rounds: int,
                  covariances: bool = True, measure: str = "information") -> DistributedBatchResult:
    """The step the baselines share (KCF, HCMCI, the local EKFs), run by :func:`filters.engine.run_batch` over many
    runs at once: every step, predict at every node of the runs still going, compute every node's measurement's
    terms, ``update`` them; a run stops at its first divergence (the others go on).  ``update(k, act, x_pred, P_pred,
    U, u, recv)`` takes stacks over the runs ``act`` (``recv`` (a, N, N)) and the terms ``measure`` names: its
    information ``U`` (a, N, n_x, n_x), ``u`` (a, N, n_x) (:func:`measurement_information`, ``"information"``), the
    information's rows ``L`` (a, N, m, n_x) in place of ``U`` (:func:`measurement_rows`, ``"rows"``), or those rows
    and the whitened residual (a, N, m) in place of ``u`` (:func:`measurement_whitened`, ``"whitened"``), zero below
    a sensor's own rows, ``m`` the largest sensor's; it returns their posteriors and ``ω`` (or None); where it
    raises ``LinAlgError``, the runs are updated one at a time to find those that break down.  Without
    ``covariances`` the nodes' covariances are kept at their latest step only (:class:`filters.engine.Latest`)."""
    n, nx = network.n_nodes, model.n_x
    runs, steps = inp.z.shape[:2]
    adj = network.adjacency
    out = estimate_arrays(runs, steps, n, nx, inp.x0, inp.P0, network.messages_per_step(rounds),
                          covariances=covariances)
    out["omega"] = np.full((runs, steps, n), np.nan)
    violations: list[list[dict]] = [[] for _ in range(runs)]
    offsets = model.sensor_offsets

    def step(k, act, at):
        if inp.attacks is None:
            recv = np.broadcast_to(adj, (act.size, n, n))
        else:
            recv = np.zeros((act.size, n, n), dtype=bool)
            recv[:, inp.attacks.receiver, inp.attacks.sender] = ~inp.attacks.dos[at, k]
        uk = inp.u[k] if inp.u.ndim == 2 else inp.u[at, k][:, None, :]
        xp, Pp = _predict(model, out["x_post"][at, k], out["P_post"][at, k], k, uk)
        bad = diverged_nodes(xp, Pp)
        reason = {r: "prediction: " + DIVERGED_REASON for r in np.flatnonzero(bad.any(axis=-1))}
        x_new, P_new, om_new = np.full(xp.shape, np.nan), np.full(Pp.shape, np.nan), np.full(xp.shape[:-1], np.nan)
        go = np.flatnonzero(~bad.any(axis=-1))
        if go.size:
            every = go.size == act.size
            xg, Pg, rg = (v if every else v[go] for v in (xp, Pp, recv))
            # every node's measurement information, linearised at its own prediction (stacked over the runs)
            m = max(model.sensor_dims)
            if measure == "information":
                U, u = np.empty(xg.shape + (nx,)), np.empty(xg.shape)
            else:
                U = np.zeros(xg.shape[:-1] + (m, nx))
                u = np.empty(xg.shape) if measure == "rows" else np.zeros(xg.shape[:-1] + (m,))
            zk = inp.z[act[go], k]
            for i in range(n):
                zi = zk[:, offsets[i]:offsets[i + 1]]
                d = zi.shape[-1]
                if measure == "information":
                    U[:, i], u[:, i] = measurement_information(model, i, xg[:, i], zi, inp.R_inv[i], k)
                elif measure == "rows":
                    U[:, i, :d], u[:, i] = measurement_rows(model, i, xg[:, i], zi, inp.R_root[i], k)
                else:
                    U[:, i, :d], u[:, i, :d] = measurement_whitened(model, i, xg[:, i], zi, inp.R_root[i], k)
            try:
                x, P, om = update(k, act[go], xg, Pg, U, u, rg)
            except np.linalg.LinAlgError:
                x, P, om = np.full(xg.shape, np.nan), np.full(Pg.shape, np.nan), np.full(xg.shape[:-1], np.nan)
                for j in range(go.size):
                    try:
                        xj, Pj, oj = update(k, act[go[j:j + 1]], xg[j:j + 1], Pg[j:j + 1], U[j:j + 1], u[j:j + 1],
                                            rg[j:j + 1])
                    except np.linalg.LinAlgError as exc:
                        bad[go[j], _not_positive_definite(Pg[j])] = True
                        reason[go[j]] = f"numerical breakdown: {exc}"
                    else:
                        x[j], P[j] = xj[0], Pj[0]
                        if oj is not None:
                            om[j] = oj[0]
            failed = diverged_nodes(x, P)
            for j in np.flatnonzero(failed.any(axis=-1)):
                if go[j] not in reason:
                    bad[go[j]], reason[go[j]] = failed[j], DIVERGED_REASON
            fine = np.array([g not in reason for g in go], dtype=bool)
            rows = go[fine]
            x_new[rows], P_new[rows] = x[fine], 0.5 * (P[fine] + np.swapaxes(P[fine], -1, -2))
            if om is not None:
                om_new[rows] = om[fine]
        return Step(dict(x_pred=xp, P_pred=Pp, delivered=recv.sum(axis=(1, 2)) * rounds, omega=om_new),
                    dict(x_post=x_new, P_post=P_new), bad, lambda r, node: reason[r])

    # a run that stops: everything from step k+1 on NaN and flagged, nothing carried on
    run_batch(step, out, violations, steps, nan_from=("x_post", "P_post"), nan_before=("x_pred", "P_pred"))
    return DistributedBatchResult(out["x_post"], history(out["P_post"]), out["x_pred"], history(out["P_pred"]),
                                  out["sent"], out["delivered"], violations, rounds, out["omega"])


def run_kcf_batch(model: Model, network: SensorNetwork, z: np.ndarray, *, inputs=None,
                  attacks: Sequence[AttackPattern] | EdgeAttacks | None = None, x0=None, P0=None,
                  epsilon: float | None = None, falsify: str = "packet", covariances: bool = True) -> FilterResult:
    """:func:`run_kcf` on many runs at once: ``z`` (runs, steps, n_z), ``attacks`` one AttackPattern per run (or
    :class:`filters.consensus_batch.EdgeAttacks` of the runs: the channels' alone).

    ``inputs`` (steps, n_u) shared or (runs, steps, n_u); ``x0`` (n_x,) or (runs, n_x), ``P0`` (n_x, n_x) or
    (runs, n_x, n_x); the other parameters as :func:`run_kcf`.  Every step is one stack over the runs and
    nodes; run ``r`` of the result is :func:`run_kcf` on run ``r`` (a batch of one: the same numbers, the same
    violations; a run that diverges stops alone).  Without ``covariances`` the result has none (``cov`` None: the
    estimates' numbers are the same; what a study that scores the estimates alone asks).  Returns
    :func:`distributed_result` of the runs.
    """
    inp = _check_batch(model, network, z, inputs, attacks, x0, P0, falsify)
    eps = _kcf_epsilon(network, epsilon)
    packet = falsify == "packet"

    ex = Exchange(network)
    slots = _slots(ex)

    def update(k, act, xp, Pp, L, u, recv):
        at = () if inp.attacks is None else (inp.attacks.fdi[act, k], inp.attacks.xi[act, k])
        return _kcf_update(ex, slots, eps, packet, xp, Pp, L, u, recv, *at)

    return distributed_result(_filter_batch(model, network, inp, update, 1, covariances, measure="rows"
                                            )._replace(omega=None))


def run_hcmci_batch(model: Model, network: SensorNetwork, z: np.ndarray, *, iterations: int = 1,
                    omega: str = "size", inputs=None, attacks: Sequence[AttackPattern] | EdgeAttacks | None = None,
                    x0=None, P0=None, falsify: str = "packet", covariances: bool = True) -> FilterResult:
    """:func:`run_hcmci` on many runs at once (the parameters of :func:`run_kcf_batch` and :func:`run_hcmci`);
    run ``r`` of the result's ``detail`` is :func:`run_hcmci` on run ``r`` (a batch of one); returns
    :func:`distributed_result` of the runs."""
    inp = _check_batch(model, network, z, inputs, attacks, x0, P0, falsify)
    L = _hcmci_rounds(iterations, omega)
    packet = falsify == "packet"

    ex = Exchange(network)

    def update(k, act, xp, Pp, dO, dq, recv):
        at = () if inp.attacks is None else (inp.attacks.fdi[act, k], inp.attacks.xi[act, k])
        return _hcmci_update(ex, network, L, omega, packet, xp, Pp, dO, dq, recv, *at)

    return distributed_result(_filter_batch(model, network, inp, update, L, covariances))


def isolated(n: int) -> SensorNetwork:
    """``n`` nodes without a link: the network of the local EKFs (every node alone)."""
    return SensorNetwork(n, np.zeros((n, n), int), require_connected=False)


def _local_update(xp, Pp, L, w):
    """The EKF update of stacked nodes (..., n_x) with their whitened rows ``L`` (..., m, n_x) and residuals ``w``
    (..., m) (:func:`measurement_whitened`; zero rows measure nothing): ``S = L P Lᵀ + I``, ``G = P Lᵀ S⁻¹``, ``x⁺ =
    x⁻ + G w`` and ``P⁺ = P - P Lᵀ Gᵀ + G Dᵀ`` with ``D = G S - P Lᵀ``: Joseph's form ``(I - G L) P (I - G L)ᵀ + G
    Gᵀ`` rearranged (the same for any ``G``, so an error in ``G`` enters to second order only: ``D`` vanishes at the
    exact gain), in ``n² m`` where Joseph's products take ``2 n³``."""
    PL = Pp @ np.swapaxes(L, -1, -2)
    S = L @ PL + np.eye(L.shape[-2])
    G = np.swapaxes(np.linalg.solve(S, np.swapaxes(PL, -1, -2)), -1, -2)
    D = G @ S - PL
    return xp + (G * w[..., None, :]).sum(axis=-1), Pp - PL @ np.swapaxes(G, -1, -2) + G @ np.swapaxes(D, -1, -2)


def run_local_batch(model: Model, z: np.ndarray, *, inputs=None, x0=None, P0=None,
                    covariances: bool = True) -> FilterResult:
    """An EKF at every node on its own sensor alone (the local EKFs: nothing sent, nothing attacked), on many runs at
    once: ``z`` (runs, steps, n_z), ``inputs``, ``x0``, ``P0`` and ``covariances`` as :func:`run_kcf_batch`.  Every
    step is one stack over the runs and nodes: the prediction of :func:`run_kcf_batch`, then the update of each node's
    sensor in covariance form (:func:`_local_update`); a run whose node diverges stops there, as KCF's.  Returns
    :func:`distributed_result` of the runs on the network without links (``messages`` 0, no packet counted:
    ``delivered`` None); :class:`LocalEKFNode` is one node of it, bit for bit."""
    alone = isolated(model.n_sensors)
    inp = _check_batch(model, alone, z, inputs, None, x0, P0, "packet")

    def update(k, act, xp, Pp, L, w, recv):
        return (*_local_update(xp, Pp, L, w), None)

    return distributed_result(_filter_batch(model, alone, inp, update, 1, covariances, measure="whitened"
                                            )._replace(omega=None))._replace(delivered=None)


# --------------------------------------------------------------------------- KCF's node filter
class KCFPacket(NamedTuple):
    """What a KCF node sends each step: its measurement information ``u`` (n_x,), ``U`` as its rows ``L`` (m, n_x),
    ``U = Lᵀ L`` (:func:`measurement_rows`; ``m`` the model's largest sensor, zero rows below the node's own) and its
    prediction ``x`` (n_x,)."""

    u: np.ndarray
    L: np.ndarray
    x: np.ndarray


class _InformationNode(OwnRows):
    """What the information-form baselines' node filters share (:class:`KCFNode`, :class:`HCMCINode`): the node, its
    in-neighbours, its sensor's information, its state, and the prediction with its measurement."""

    def __init__(self, model: Model, network: SensorNetwork, node: int, x0, P0, falsify: str):
        _check_network(model, network)
        _check_falsify(falsify)
        i = self.node = check_int("node", node, 0, network.n_nodes - 1)
        self.model, self.network, self.packet = model, network, falsify == "packet"
        self.senders = np.flatnonzero(network.adjacency[i])
        self._R_inv = _spd_inverse(model.measurement_cov(i))
        self._R_root = whitening(model.measurement_cov(i))
        _, _, x0, P0 = batch_inputs(model, np.zeros((1, 1, model.n_z)), np.zeros((1, model.n_u)), x0, P0, "P0")
        self.x, self.P = x0[0].copy(), P0[0].copy()
        self.k, self.diverged = 0, False

    def _predicted(self, z, u, rows: bool = False):
        """``(x̂⁻, P⁻, U, u)`` (stacks of one) of the next step with the node's measurement ``z`` (with ``rows``
        ``L`` (1, m, n_x) in place of ``U``, as the batch's)."""
        m, i = self.model, self.node
        chk = NodeInputs.of(self)
        z = chk.array("z", z, (m.sensor_dims[i],))
        u = chk.inputs(u, m.n_u)
        xp, Pp = _predict(m, self.x[None, None], self.P[None, None], self.k, u)
        if not rows:
            U, v = measurement_information(m, i, xp[:, 0], z[None], self._R_inv, self.k)
            return xp, Pp, U, v
        L = np.zeros((1, max(m.sensor_dims), m.n_x))
        L[:, :z.shape[-1]], v = measurement_rows(m, i, xp[:, 0], z[None], self._R_root, self.k)
        return xp, Pp, L, v

    def _posterior(self, combine, like: tuple, failed: bool) -> np.ndarray:
        """The step's end: ``combine()``, the posterior ``(x, P)`` (stacks of one, shaped as ``like``) as the batch
        computes it (NaN where it breaks down), becomes the node's state, marked diverged as the batch marks it
        (:func:`_failures`; ``failed``: the step's prediction did).  Returns the estimate."""
        try:
            x, P = combine()
        except np.linalg.LinAlgError:
            x, P = np.full_like(like[0], np.nan), np.full_like(like[1], np.nan)
        if failed or _failures(x, P)[0] < 1:
            self.diverged = True
        self.x, self.P = x[0, 0], 0.5 * (P[0, 0] + P[0, 0].T)
        self.k += 1
        return self.x

    def _packets(self, received, kind: type, fields: tuple) -> tuple[np.ndarray, list]:
        """``received`` ``{neighbour: packet}`` checked (:class:`filters.node.NodeInputs`: its keys in-neighbours,
        each packet a ``kind`` with ``fields`` ``((field, shape), ...)``): ``(arrived (d,) bool, [per channel its
        arrays, or None where nothing arrived])``."""
        chk = NodeInputs.of(self)
        senders = self.senders.tolist()
        received = chk.received("received", received, senders, f"an in-neighbour of node {self.node}")
        got = [chk.packet(f"received[{j}]", received[j], fields, kind) if j in received else None for j in senders]
        return np.array([g is not None for g in got], dtype=bool), got


class KCFNode(_InformationNode):
    """The Kalman consensus filter one node runs (:func:`run_kcf_batch` at node ``node``), in two phases:
    ``packet = node.predict(z, u)`` (its prediction ``f(x̂)``, ``F P Fᵀ + Q`` and its measurement's information at
    the prediction: what it sends), then ``node.update(received)`` with ``{neighbour: KCFPacket}`` for the packets
    that arrived, as they arrived.  Driven over a run through :class:`KCFNetwork`, the batch's numbers bit for bit
    (the same functions on its incoming channels)."""

    def __init__(self, model: Model, network: SensorNetwork, node: int, *, x0=None, P0=None,
                 epsilon: float | None = None, falsify: str = "packet"):
        super().__init__(model, network, node, x0, P0, falsify)
        self.eps = _kcf_epsilon(network, epsilon)
        self._pred = None

    def predict(self, z, u=None) -> KCFPacket:
        """The prediction phase with the node's measurement ``z``: the packet it sends."""
        if self._pred is not None:
            raise InputError(f"node {self.node} has predicted step {self.k} already: call update(received) next")
        xp, Pp, L, v = self._predicted(z, u, rows=True)
        self._pred = (xp, Pp, L[:, None], v[:, None])
        return KCFPacket(v[0], L[0], xp[0, 0])

    def update(self, received: dict | None = None) -> np.ndarray:
        """The update phase: ``received`` ``{neighbour: KCFPacket}`` as they arrived.  Returns the estimate (also
        ``self.x``; ``self.P`` its covariance ``M``)."""
        i = self.node
        if self._pred is None:
            raise InputError(f"node {i} must predict step {self.k} before its update: call predict(z, u) first")
        nx, d, m = self.model.n_x, self.senders.size, max(self.model.sensor_dims)
        arrived, got = self._packets(received, KCFPacket, (("L", (m, nx)), ("u", (nx,)), ("x", (nx,))))
        xp, Pp, L, v = self._pred
        r = arrived[None].astype(float)
        pu, px = np.zeros((1, d, nx)), np.zeros((1, d, nx))
        rows = np.zeros((1, 1, 1 + d, m, nx))  # J_i's rows as the batch stacks them: its own, then each channel's
        rows[0, 0, 0] = L[0, 0]
        for e, p in enumerate(got):
            if p is not None:
                pL, pu[0, e], px[0, e] = p  # in the order of the fields checked
                rows[0, 0, 1 + e] = r[0, e] * pL
        # the sums over its incoming channels as the batch adds them (a lost packet an exact zero there)
        y = v + Exchange.node_sum(r[..., None] * pu)[:, None]
        diff = Exchange.node_sum(r[..., None] * px)[:, None] - Exchange.node_sum(r)[:, None, None] * xp
        self._pred = None
        return self._posterior(lambda: _kcf_combine(self.eps, xp, Pp, rows.reshape(1, 1, (1 + d) * m, nx), y, diff),
                               (xp, Pp), _failures(xp, Pp)[0] < 1)


class KCFNetwork(NodeNetwork):
    """Every node of the network as a :class:`KCFNode`, driven over a run: each step every node predicts with its
    measurement, the packets cross the channels (DoS drops them; FDI: :func:`kcf_packets`), every node updates
    with what reached it.  Once a node diverges the run stops (NaN from then on), as the batch stops it."""

    def __init__(self, model: Model, network: SensorNetwork, *, x0=None, P0=None, epsilon: float | None = None,
                 falsify: str = "packet"):
        self.model, self.network = model, network
        self.nodes = [KCFNode(model, network, i, x0=x0, P0=P0, epsilon=epsilon, falsify=falsify)
                      for i in range(network.n_nodes)]

    def deliver(self, packets, dos=None, fdi=None, xi=None) -> list[dict]:
        """What the nodes' ``packets`` deliver to every node over the step's channels (``dos``, ``fdi`` (E,), ``xi``
        (E, n_x) in :class:`filters.consensus_batch.EdgeAttacks` order): per node ``{neighbour: KCFPacket}``."""
        def falsified(nd, j, p, f, x):
            u_t, x_t = kcf_packets(p.u, p.L, p.x, f, x, nd.packet)
            return KCFPacket(u_t, p.L, x_t)

        return self.carry(packets, dos, fdi, xi, falsified)

    def _exchange(self, z, dos, fdi, xi, u):
        packets = [nd.predict(z_i, u) for nd, z_i in zip(self.nodes, z)]
        if not self.sent_finite(packets):
            return packets, []
        delivered = self.deliver(packets, dos, fdi, xi)
        for nd, got in zip(self.nodes, delivered):
            nd.update(got)
        return packets, [delivered]


# --------------------------------------------------------------------------- the local EKF's node filter
class LocalEKFNode(_InformationNode):
    """The EKF one node runs on its own sensor alone (:func:`run_local_batch` at node ``node``): ``node.step(z, u)``
    with its measurement ``z``; it sends and receives nothing.  Driven over a run through :class:`LocalEKFNetwork`, the
    batch's numbers bit for bit (the same functions on a stack of one)."""

    def __init__(self, model: Model, node: int, *, x0=None, P0=None):
        super().__init__(model, isolated(model.n_sensors), node, x0, P0, "packet")

    def step(self, z, u=None) -> np.ndarray:
        """The prediction and the update with the node's measurement ``z``.  Returns the estimate (also ``self.x``;
        ``self.P`` its covariance)."""
        m, i = self.model, self.node
        chk = NodeInputs.of(self)
        z = chk.array("z", z, (m.sensor_dims[i],))
        u = chk.inputs(u, m.n_u)
        xp, Pp = _predict(m, self.x[None, None], self.P[None, None], self.k, u)
        L, w = np.zeros((1, 1, max(m.sensor_dims), m.n_x)), np.zeros((1, 1, max(m.sensor_dims)))
        L[:, 0, :z.size], w[:, 0, :z.size] = measurement_whitened(m, i, xp[:, 0], z[None], self._R_root, self.k)
        return self._posterior(lambda: _local_update(xp, Pp, L, w), (xp, Pp), _failures(xp, Pp)[0] < 1)


class LocalEKFNetwork(NodeNetwork):
    """Every node as a :class:`LocalEKFNode`, driven over a run (``run``, ``step``): nothing crosses a channel.  Once
    a node diverges the run stops (NaN from then on), as the batch stops it."""

    def __init__(self, model: Model, *, x0=None, P0=None):
        self.model, self.network = model, isolated(model.n_sensors)
        self.nodes = [LocalEKFNode(model, i, x0=x0, P0=P0) for i in range(model.n_sensors)]

    def _exchange(self, z, dos, fdi, xi, u):
        for nd, z_i in zip(self.nodes, z):
            nd.step(z_i, u)
        return [None] * len(self.nodes), []


# --------------------------------------------------------------------------- HCMCI's node filter
class HCMCIPacket(NamedTuple):
    """What an HCMCI node sends in a consensus round: its information pairs ``(O, q)`` (the prior's) and ``(dO, dq)``
    (the measurements')."""

    O: np.ndarray
    q: np.ndarray
    dO: np.ndarray
    dq: np.ndarray


class HCMCINode(_InformationNode):
    """HCMCI at one node (:func:`run_hcmci_batch` at node ``node``, ``omega='size'``), in ``L`` consensus rounds a step:
    ``packet = node.predict(z, u)`` (its prediction's information and its measurement's: what it sends in the first
    round), then ``packet = node.round(received)`` ``L`` times with ``{neighbour: HCMCIPacket}`` as they arrived (the
    same neighbours every round: a step's channels are attacked once), each returning what it sends next; after the
    ``L``-th the node combines (``x``, ``P``).  Driven over a run through :class:`HCMCINetwork`, the batch's numbers
    bit for bit."""

    def __init__(self, model: Model, network: SensorNetwork, node: int, *, iterations: int = 1, omega: str = "size",
                 x0=None, P0=None, falsify: str = "packet"):
        self.rounds = _hcmci_rounds(iterations, omega)
        if omega != "size":
            raise InputError("omega must be 'size' for a node filter ('consistent' needs each node's row of the "
                             "product of the rounds' weight matrices: consensus on N-vectors, not built)")
        super().__init__(model, network, node, x0, P0, falsify)
        self._state, self._round, self._heard = None, 0, None

    def predict(self, z, u=None) -> HCMCIPacket:
        """The prediction with the node's measurement ``z``: the packet of the first round."""
        if self._state is not None:
            raise InputError(f"node {self.node} has predicted step {self.k} already: call round(received) next (round "
                             f"{self._round} of {self.rounds})")
        xp, Pp, dO, dq = self._predicted(z, u)
        if _failures(xp, Pp)[0] < 1:
            self.diverged = True
            O, q = np.full_like(Pp, np.nan), np.full_like(xp, np.nan)
        else:
            try:
                O, q = _information(Pp, xp)
            except np.linalg.LinAlgError:
                self.diverged = True
                O, q = np.full_like(Pp, np.nan), np.full_like(xp, np.nan)
        self._state, self._round, self._heard = (O, q, dO[:, None], dq[:, None]), 1, None
        return HCMCIPacket(O[0, 0], q[0, 0], dO[0], dq[0])

    def round(self, received=None) -> HCMCIPacket | None:
        """A consensus round with ``{neighbour: HCMCIPacket}`` as they arrived: what the node sends in the next round,
        or None after the last (then ``x``, ``P`` are the step's posterior)."""
        i, nx = self.node, self.model.n_x
        if self._state is None:
            raise InputError(f"node {i} must predict step {self.k} before its rounds: call predict(z, u) first")
        arrived, got = self._packets(received, HCMCIPacket, (("O", (nx, nx)), ("q", (nx,)), ("dO", (nx, nx)),
                                                             ("dq", (nx,))))
        heard = tuple(arrived.tolist())
        if self._heard is not None and heard != self._heard:
            raise InputError(f"round {self._round} of node {i} at step {self.k} must hear the neighbours of its first "
                             "round (a step's channels are attacked once)")
        self._heard = heard
        d = self.senders.size
        w = hcmci_weights(self.network, np.full(d, i), self.senders, arrived)[None]  # (1, d)
        w_self = 1.0 - Exchange.node_sum(w)  # (1,)
        pO, pq, pdO, pdq = (np.zeros((1, d, nx, nx)), np.zeros((1, d, nx)), np.zeros((1, d, nx, nx)),
                            np.zeros((1, d, nx)))
        for e, p in enumerate(got):
            if p is not None:
                pO[0, e], pq[0, e], pdO[0, e], pdq[0, e] = p
        O, q, dO, dq = self._state
        q, dq = (w_self[:, None, None] * q + Exchange.node_sum(w[..., None] * pq)[:, None],
                 w_self[:, None, None] * dq + Exchange.node_sum(w[..., None] * pdq)[:, None])
        O, dO = (w_self[:, None, None, None] * O + Exchange.node_sum(w[..., None, None] * pO)[:, None],
                 w_self[:, None, None, None] * dO + Exchange.node_sum(w[..., None, None] * pdO)[:, None])
        self._state = (O, q, dO, dq)
        if self._round < self.rounds:
            self._round += 1
            return HCMCIPacket(O[0, 0], q[0, 0], dO[0, 0], dq[0, 0])
        self._state = None
        self._posterior(lambda: _hcmci_combine(self.network.n_nodes, O, q, dO, dq), (q, O), self.diverged)
        return None


class HCMCINetwork(NodeNetwork):
    """Every node as an :class:`HCMCINode`, driven over a run: each step every node predicts, then ``L`` rounds in
    which the packets cross the channels (DoS drops them, the same channels every round; FDI: :func:`hcmci_packets`)
    and every node combines what reached it.  Once a node diverges the run stops (NaN from then on)."""

    def __init__(self, model: Model, network: SensorNetwork, *, iterations: int = 1, x0=None, P0=None,
                 falsify: str = "packet"):
        self.model, self.network = model, network
        self.nodes = [HCMCINode(model, network, i, iterations=iterations, x0=x0, P0=P0, falsify=falsify)
                      for i in range(network.n_nodes)]

    def deliver(self, packets, dos=None, fdi=None, xi=None) -> list[dict]:
        """What the nodes' ``packets`` (one :class:`HCMCIPacket` each) deliver over the step's channels (``dos``,
        ``fdi`` (E,), ``xi`` (E, n_x) in :class:`filters.consensus_batch.EdgeAttacks` order): per node ``{neighbour:
        HCMCIPacket}``."""
        def falsified(nd, j, p, f, x):
            q_t, dq_t = hcmci_packets(p.O, p.q, p.dO, p.dq, f, x, nd.packet)
            return HCMCIPacket(p.O, q_t, p.dO, dq_t)

        return self.carry(packets, dos, fdi, xi, falsified)

    def _exchange(self, z, dos, fdi, xi, u):
        first = packets = [nd.predict(z_i, u) for nd, z_i in zip(self.nodes, z)]
        rounds = []
        for _ in range(self.nodes[0].rounds):
            if not self.sent_finite(packets):
                return first, rounds
            rounds.append(self.deliver(packets, dos, fdi, xi))
            packets = [nd.round(got) for nd, got in zip(self.nodes, rounds[-1])]
        return first, rounds
