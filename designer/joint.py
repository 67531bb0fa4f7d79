"""The joint error covariance of all nodes and the gains that minimise each node's mean-square error.

Theorem 1's bound (26)-(27) holds for *any* gains ``K_i``, ``C_i`` as long as (28)-(29)
hold; the gain (30) only makes the bound smallest.  A rule of the joint covariance (``rules/mse``) chooses the
gains for what the filter really does instead, and the scheduled rule's tables (``rules/scheduled``) are built on
the same joint recursion: at every step it propagates the linearised error
covariance of **all nodes jointly**, cross-covariances included, and gives each node the
gains that minimise its own mean-square error; the bound of the stacked error of all nodes
is then evaluated for those gains as the certificate (see **The certificate** below).

With ``e_i = x - x̂_i`` and the linearisations ``F_i`` (at node i's estimate) and ``H_i``
(at its prediction), every node's prediction error is ``e_i⁻ = F_i e_i + w`` (one process
noise for all: the plant is the same), so the joint prediction is

    P⁻_ij = F_i P_ij F_jᵀ + Q.

At the update node ``i`` knows which packets arrived (the set ``R_i``, ``s_i = |R_i|``); a
received packet is falsified with probability ``q_ij = γ̄_ij / (1 - φ̄_ij)``, by ``ξ`` with
second moment ``M = E[ξ ξᵀ] = E[g²] a aᵀ`` (:class:`designer.attacks.FDISignal`).  Its
update (7) is ``e_i⁺ = e_i⁻ - Z_i y_i`` with ``Z_i = [K_i  C_i]`` and the innovations

    y_i = [H_i e_i⁻ + v_i ;  Σ_{j∈R_i} (e_i⁻ - e_j⁻ + γ_ij ξ_ij)],

so the gains minimising ``tr E[e_i⁺ e_i⁺ᵀ]`` are the linear MMSE ones,
``Z_i = E[e_i⁻ y_iᵀ] E[y_i y_iᵀ]⁻¹``, with

    E[e_i⁻ y_iᵀ] = [P_ii H_iᵀ,  Σ_j (P_ii - P_ij)]
    E[y_i y_iᵀ]  = [[H_i P_ii H_iᵀ + R_i,  H_i Σ_j (P_ii - P_ij)],
                    [·ᵀ,  Σ_{j,l} (P_ii - P_il - P_ji + P_jl) + Σ_j q_ij M]]

(``C_i = 0`` is one choice, so each node's predicted error is never larger than a local
EKF's from the same prior covariance).  With the gains fixed, ``e⁺ = T e⁻ - noise``
with ``T_ii = I - K_i H_i - s_i C_i``, ``T_ij = C_i`` for ``j ∈ R_i``, and noises independent
between nodes, so

    P⁺ = T P⁻ Tᵀ + blockdiag(K_i R_i K_iᵀ + C_i (Σ_{j∈R_i} q_ij M) C_iᵀ).

The linearisation errors are not in this prediction (it is the EKF's own covariance, not a
bound); the certificate is.

**Difference form.**  The gains live on the *differences* between nodes: ``E[y yᵀ]``'s consensus
block is ``Σ_{j,l} (P_ii - P_il - P_ji + P_jl)``, which for nodes that share most of their error
(all of it at the start) is a small difference of large blocks.  Stored as absolute blocks
``P_ij``, every block carries a rounding error of about ``u |P|`` (``u = 1.1e-16``), that
difference keeps only ``u |P|`` of absolute accuracy, and the gains solved from it amplified
it: a consensus gain of 100 multiplies the next step's error by 10⁴, and after two steps of a
28-node design the gains were set by rounding noise (a relative error of 2.3 against the same
recursion in long double; one and two BLAS threads gave different designs).  So the covariance the gains are chosen for is kept as a :class:`JointCovariance`:
each node's own ``P_i = E[e_i e_iᵀ]`` and the pairwise ``G_ij = E[e_i (e_i - e_j)ᵀ] = P_ii - P_ij``
(``G_ii = 0``), propagated as such, so that ``G⁻_ij = F_i P_i (F_i - F_j)ᵀ + F_i G_ij F_jᵀ`` and the
update (:func:`joint_update`) are sums of terms that are themselves small where nodes agree: the
differences keep their relative accuracy, nodes with one error give exact zeros, and a
difference is never taken of two large numbers.  The consensus block is then
``Σ_{j,l} (G_il - G_jl + G_ji)``.  :func:`joint_predict`, :func:`joint_update` and
:func:`mse_gains` also take and give absolute arrays ``(..., N, N, n, n)`` (converted through
:func:`as_difference` / :func:`as_absolute`, for the certificate's fallback and for tests).

**The certificate** (:func:`certificate_predict`, :func:`certificate_update`) is the bound
(26)-(27) written for the *stacked* error ``e = [e_1; ...; e_N]`` of all nodes, so that the
cross-covariances are propagated instead of bounded by Cauchy-Schwarz across neighbours
(the per-node bound treats neighbours' errors as arbitrarily correlated, and for gains
that exploit their real correlation, as these do, it grows geometrically).  The remainders
``r_i = U_i Ω_i D_i e_i`` stack into ``U Ω D e`` with a block-diagonal ``Ω``, ``||Ω|| <= 1``,
so the same lemma gives, with one σ and one β for the network,

    Φ⁻ = F (Φ^-1 - (1+ε) σ DᵀD)^-1 Fᵀ + (εσ)^-1 U Uᵀ + 1 1ᵀ ⊗ Q          (28): Φ^-1 > (1+ε) σ DᵀD
    Φ⁺ = T (Φ⁻^-1 - β DᵀD)^-1 Tᵀ + β^-1 (K V)(K V)ᵀ + blockdiag(K_i R_i K_iᵀ) + B   (29): Φ⁻^-1 > β DᵀD

with ``F = blockdiag(F_i)``, ``T`` the transition above, ``K V = blockdiag(K_i V_i)``, and
``B`` the falsified packets' term ``b = [C_i Σ_{j∈R_i} γ_ij ξ_ij]``: its second moment is
``E[b_i b_kᵀ] = C_i [δ_ik (S_i - Σ_j q_ij² μμᵀ) + n_i n_k μμᵀ] C_kᵀ`` (``μ = E[ξ]``,
``n_i = Σ_{j∈R_i} q_ij``, channels independent); a zero-mean signal (the sine and uniform
laws) is independent of everything else at its step, so ``B = E[b bᵀ]`` adds without cross
terms; with ``μ ≠ 0`` the cross terms are bounded by ``(a + b)(a + b)ᵀ <= a aᵀ / (1 - π) +
b bᵀ / π`` with the ``π`` that makes the trace smallest.  Each node's bound is its diagonal
block.  For a linear model (``U = V = 0``) with a zero-mean signal the certificate *is* the
predicted covariance.

**Stacks.**  Every function also takes a stack of runs: joint arrays (..., N, N, n, n), per-node
arrays with the same leading axes, and the packets each node kept as a mask (..., N, N) instead of
index lists (:mod:`rules.mse.filter` runs many Monte Carlo runs so).  One run is a stack of none:
the per-run filter and the batched one take the same steps, so they agree to rounding.  The
multipliers σ and β are the roots of the trace's increasing slope (:func:`joint_multiplier`), one
eigendecomposition per matrix serving the margin, the search and the bound.

**Shared remainders** (``shared=True``, the scheduled design's certificate).  The blocks ``Ω_i`` above are
independent, as if each node's remainder were a function of its own; one σ on the stacked error then has to
respect the common direction (every node with the same error ``c``: ``λmax`` of the stacked Φ is about ``N``
times a node's), ``σ <= 1/(N λ)``, and every node's ``(εσ)⁻¹ U Uᵀ`` is ``N`` times its own remainder's size,
all of it in the nodes' *differences*, where the consensus gains amplify it (measured on a 24-node design:
that term was 60 % of the prediction's disagreement and the bound grew 2.2 times per step).  But every node
linearises the *same* ``f`` (the true state is common): ``r_i = φ(e_i)`` for one function φ, ``φ(0) = 0``,
with ``|U⁻¹ φ(y)| <= |y|`` on the ellipsoid where ``U`` was derived from the Hessian bound ``L``
(:func:`designer.linearization.component_scales`: ``|φ_j(y)| <= ½ L_j |y|²``), so that the same ``L`` bounds
its Jacobian, ``|∇φ_j(y)| <= L_j |y|``, and by the mean-value theorem ``|U⁻¹ (φ(a) - φ(b))| <= 2 |a - b|`` for
``a``, ``b`` in the ellipsoid (twice the scaling: the factor is tight for a quadratic remainder).  With the
nodes' mean error ``ē`` (in the ellipsoid when every ``e_i`` is: it is
convex) and the deviations ``δ = Π e`` (``Π = I - 1 1ᵀ/N ⊗ I``):

    r_i = φ(ē) + (φ(e_i) - φ(ē)) = U Ω_0 ē + 2 U Ω_i δ_i,        ||Ω_0||, ||Ω_i|| <= 1

one remainder for all nodes in the common direction and one per node in the differences, sized by the
differences.  With a multiplier ``σ`` on ``Ω_0`` and ``t σ`` on the ``Ω_i`` (the lemma for a block-diagonal
``Ω`` with one multiplier per block is the unstructured one for ``U Λ^{-1/2}``, ``Λ^{1/2} D``), (26) keeps its
form with ``DᵀD = 1 1ᵀ/N² ⊗ I + t Π`` and ``U Uᵀ = 1 1ᵀ ⊗ U Uᵀ + (4/t) I ⊗ U Uᵀ``; the measurement remainders
of (27) likewise (:func:`rules.scheduled.design.expected_certificate_update`: a sensor's remainder is one function
wherever it is evaluated, at its node and at the nodes that receive its measurement).  ``t`` is chosen so
that the common and the deviation blocks of ``D Φ Dᵀ`` have the same largest eigenvalue
(:func:`shared_structure`; any ``t > 0`` gives a bound).  It needs one ``U`` for every node.  The independent
blocks give a bound too, so each step keeps the one of smaller trace: the shared model is never looser.  It
removes the N-fold common-mode factor, not the relative inflation of the differences (``2 U`` on them, the
lemma's square-root balance): where the consensus contracts the differences by less than that per step, the
bound still grows (measured, :mod:`rules.scheduled.design`).
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np
from scipy.linalg import block_diag

from .bounds import eigh, eigvalsh, symmetrize
from .tuning import MARGIN, best_multiplier, increasing_root

__all__ = ["joint_prior", "joint_predict", "mse_gains", "joint_update", "certificate_predict", "certificate_update",
           "JointBound", "joint_multiplier", "node_blocks", "JointCovariance", "as_difference", "as_absolute",
           "difference_covariance", "solve_gains", "GAIN_RCOND", "ILL_CONDITIONED", "conditioning", "shared_structure",
           "shared_search", "SHARED_RATIO_MAX", "SHARED_STEPS", "SHARED_SPAN"]


# --------------------------------------------------------------------------- stacks of nodes
def _t(a: np.ndarray) -> np.ndarray:
    return np.swapaxes(a, -1, -2)


def _nodes(x, n_nodes: int) -> list:
    """One array per node: the items of a sequence, or the slices ``x[..., i, :, :]`` of an array (..., N, a, b)."""
    if isinstance(x, np.ndarray):
        return [x[..., i, :, :] for i in range(n_nodes)]
    return [np.asarray(v, dtype=float) for v in x]


def _per_node(x) -> np.ndarray:
    """One array (..., N, a, b): an array as it is, or a sequence of per-node arrays, leading axes broadcast."""
    if isinstance(x, np.ndarray):
        return x
    arrays = [np.asarray(v, dtype=float) for v in x]
    batch = np.broadcast_shapes(*(v.shape[:-2] for v in arrays))
    return np.stack([np.broadcast_to(v, batch + v.shape[-2:]) for v in arrays], axis=-3)


def _indices_mask(received, n_nodes: int) -> np.ndarray:
    """A mask (..., N) from a boolean mask or from one run's list of indices."""
    received = np.asarray(received)
    if received.dtype == bool:
        return received
    mask = np.zeros(n_nodes, dtype=bool)
    mask[received.astype(int)] = True
    return mask


def _received_mask(received, n_nodes: int) -> np.ndarray:
    """The packets node i kept from node j, (..., N, N) bool: a mask, or one run's index list per node."""
    if isinstance(received, np.ndarray) and received.dtype == bool:
        return received
    return np.stack([_indices_mask(r, n_nodes) for r in received])


class JointCovariance(NamedTuple):
    """The joint error covariance of all nodes in difference form (module notes): ``P`` (..., N, n, n) each node's
    ``E[e_i e_iᵀ]``, ``G`` (..., N n, N n) the matrix of the blocks ``G_ij = E[e_i (e_i - e_j)ᵀ]`` (zero on the
    diagonal; :meth:`blocks` views them as (..., N, N, n, n))."""

    P: np.ndarray
    G: np.ndarray

    def take(self, index) -> "JointCovariance":
        """The runs ``index`` (a mask or indices over the leading axes) of a stack."""
        return JointCovariance(self.P[index], self.G[index])

    def blocks(self) -> np.ndarray:
        """``G`` as blocks (..., N, N, n, n) (a view)."""
        return _blocks(self.G, self.P.shape[-3])


def as_difference(P: np.ndarray) -> JointCovariance:
    """The :class:`JointCovariance` of absolute joint blocks ``P`` (..., N, N, n, n) (``G_ij = P_ii - P_ij``)."""
    if isinstance(P, JointCovariance):
        return P
    P = np.asarray(P, dtype=float)
    idx = np.arange(P.shape[-4])
    d = P[..., idx, idx, :, :]
    return JointCovariance(d.copy(), _dense(d[..., :, None, :, :] - P))


def as_absolute(J: JointCovariance) -> np.ndarray:
    """The absolute joint blocks ``P_ij = P_ii - G_ij`` (..., N, N, n, n) of a :class:`JointCovariance`."""
    if not isinstance(J, JointCovariance):
        return J
    P = J.P[..., :, None, :, :] - J.blocks()
    idx = np.arange(J.P.shape[-3])
    P[..., idx, idx, :, :] = J.P
    return _symmetric(P)


def node_blocks(P) -> np.ndarray:
    """Each node's covariance (..., N, n, n): the diagonal blocks ``P[..., i, i]`` of joint arrays (..., N, N, n, n),
    or ``P.P`` of a :class:`JointCovariance`."""
    if isinstance(P, JointCovariance):
        return P.P
    idx = np.arange(P.shape[-4])
    return P[..., idx, idx, :, :]


def difference_covariance(P, receiver: np.ndarray, sender: np.ndarray) -> np.ndarray:
    """``Cov(e_i - e_j) = G_ij + G_ji`` (..., E, n, n) for the pairs ``i = receiver[e]``, ``j = sender[e]``.

    ``P`` a :class:`JointCovariance` (no difference of large blocks) or absolute joint blocks.
    """
    G = as_difference(P).blocks()
    return symmetrize(G[..., receiver, sender, :, :] + G[..., sender, receiver, :, :])


def _dense(P: np.ndarray) -> np.ndarray:
    """(..., N, M, n, m) blocks -> (..., N n, M m) matrices."""
    N, M, n, m = P.shape[-4:]
    return np.swapaxes(P, -3, -2).reshape(P.shape[:-4] + (N * n, M * m))


def _blocks(A: np.ndarray, N: int) -> np.ndarray:
    n = A.shape[-1] // N
    return np.swapaxes(A.reshape(A.shape[:-2] + (N, n, N, n)), -3, -2)


def _left(B: np.ndarray, A: np.ndarray) -> np.ndarray:
    """``blockdiag(B) A`` for blocks ``B`` (..., N, a, b) and matrices ``A`` (..., N b, M), block row by block row."""
    N, a, b = B.shape[-3:]
    out = B @ A.reshape(A.shape[:-2] + (N, b, A.shape[-1]))
    return out.reshape(out.shape[:-3] + (N * a, A.shape[-1]))


def _sandwich(B: np.ndarray, A: np.ndarray) -> np.ndarray:
    """``blockdiag(B) A blockdiag(B)ᵀ`` for ``A`` (..., N n, N n)."""
    return _t(_left(B, _t(_left(B, A))))


def _right(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A blockdiag(B)ᵀ`` for matrices ``A`` (..., M, N b) and blocks ``B`` (..., N, a, b)."""
    return _t(_left(B, _t(A)))


def _pairwise(B: np.ndarray, D: np.ndarray) -> np.ndarray:
    """The matrix of the blocks ``B_i (D_i - D_j)ᵀ`` (..., N n, N n) for blocks ``B``, ``D`` (..., N, n, n): zero where
    ``D_i = D_j`` (the difference is taken first, of the small factors, never of two products)."""
    return _left(B, _dense(_t(D[..., :, None, :, :] - D[..., None, :, :, :])))


def _zero_diagonal(G: np.ndarray, N: int) -> np.ndarray:
    """``G`` (..., N n, N n) with its diagonal blocks set to zero, in place."""
    view = _blocks(G, N)
    idx = np.arange(N)
    view[..., idx, idx, :, :] = 0.0
    return G


def _add_diagonal_blocks(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A + blockdiag(B)`` in place for a new (contiguous) ``A`` (..., N n, N n) and blocks ``B`` (..., N, n, n)."""
    N, n = B.shape[-3], B.shape[-1]
    view = A.reshape(A.shape[:-2] + (N, n, N, n))
    for i in range(N):
        view[..., i, :, i, :] += B[..., i, :, :]
    return A


def _symmetric(P: np.ndarray) -> np.ndarray:
    """``(P + Pᵀ) / 2`` of joint arrays (block (i, j) with the transpose of block (j, i))."""
    return 0.5 * (P + _t(np.swapaxes(P, -4, -3)))


def _structure(D: Sequence[np.ndarray | None] | None, n: int) -> np.ndarray | None:
    if D is None or all(d is None for d in D):
        return None
    return block_diag(*[np.eye(n) if d is None else d for d in D])


def _item(x):
    """A plain number for one run (0-d), the array for a stack."""
    return float(x) if np.ndim(x) == 0 else x


# --------------------------------------------------------------------------- the joint covariance
def joint_prior(cov: np.ndarray, n_nodes: int) -> np.ndarray:
    """``P_ij = cov`` for every pair: every node starts at the same estimate, so their errors are one error.

    ``cov`` (n, n) gives (N, N, n, n); a stack (..., n, n) gives (..., N, N, n, n).
    """
    cov = np.asarray(cov, dtype=float)
    return np.broadcast_to(cov[..., None, None, :, :], cov.shape[:-2] + (n_nodes, n_nodes) + cov.shape[-2:]).copy()


def joint_predict(P, F, Q: np.ndarray):
    """``P⁻_ij = F_i P_ij F_jᵀ + Q`` (``F`` one (..., n, n) per node or (..., N, n, n)).

    In difference form (module notes) ``P⁻_i = F_i P_i F_iᵀ + Q`` and ``G⁻_ij = F_i P_i (F_i - F_j)ᵀ + F_i G_ij F_jᵀ``
    (the process noise, common to all nodes, leaves the differences).  ``P`` a :class:`JointCovariance`, or
    absolute blocks (..., N, N, n, n) (then so is the result).
    """
    if not isinstance(P, JointCovariance):
        return as_absolute(joint_predict(as_difference(P), F, Q))
    F = _per_node(F)
    FP = F @ P.P
    G = _sandwich(F, P.G)
    if np.any(F != F[..., :1, :, :]):  # with one F for every node (a nominal design's), F_i - F_j = 0: no such term
        G = _pairwise(FP, F) + G
    return JointCovariance(symmetrize(FP @ _t(F) + Q), _zero_diagonal(G, F.shape[-3]))


def _weighted_sum(w: np.ndarray, A: np.ndarray) -> np.ndarray:
    """``Σ_j w_j A_j`` over axis -3 of ``A`` (..., J, n, n), ``w`` (..., J) 0/1 (a block outside it never counts)."""
    return np.where(w[..., None, None], A, 0.0).sum(axis=-3)


def _moments(Pm: JointCovariance, i: int, w: np.ndarray, H: np.ndarray, R: np.ndarray, fdi_second):
    """``E[e_i⁻ y_iᵀ]``, ``E[y_i y_iᵀ]``, ``s_i`` and the innovations' scales for the packets ``w`` (..., N) node i
    kept (module docstring).  The scales (..., m + n) are the measurement's standard deviations and ``s_i``
    times those of the node's own error: the size of each innovation component were the nodes' errors
    independent, never a small difference (the unit of :func:`solve_gains`).

    In difference form: ``Σ_j (P_ii - P_ij) = Σ_j G_ij`` and ``Σ_{j,l} (P_ii - P_il - P_ji + P_jl) =
    s Σ_l G_il - Σ_j (Σ_l G_jl - s G_ji)``: sums of the small differences themselves, so that nodes whose
    errors are one error give exact zeros, not rounding noise that the solve would turn into gains.
    """
    cand = np.flatnonzero(w.reshape(-1, w.shape[-1]).any(axis=0))  # the packets any item kept
    wc = w[..., cand]
    s = wc.sum(axis=-1).astype(float)
    m = H.shape[-2]
    Pii, G = Pm.P[..., i, :, :], Pm.blocks()
    sum_diff = _weighted_sum(wc, G[..., i, cand, :, :])  # Σ_j G_ij
    Gcc = G[..., cand, :, :, :][..., cand, :, :]  # (..., c, c, n, n): G_jl
    inner = _weighted_sum(wc[..., None, :], Gcc) - s[..., None, None, None] * G[..., cand, i, :, :]
    dd = s[..., None, None] * sum_diff - _weighted_sum(wc, inner) + fdi_second
    HD = H @ sum_diff
    yy = np.concatenate([np.concatenate([H @ Pii @ _t(H) + R, HD], axis=-1),
                         np.concatenate([_t(HD), dd], axis=-1)], axis=-2)
    # the innovations' natural sizes: the measurement's standard deviation, and s times the node's own error's
    scale = np.concatenate([np.diagonal(yy[..., :m, :m], axis1=-2, axis2=-1),
                            np.maximum(s, 1.0)[..., None] ** 2 * np.diagonal(Pii, axis1=-2, axis2=-1)], axis=-1)
    return np.concatenate([Pii @ _t(H), sum_diff], axis=-1), symmetrize(yy), s, np.sqrt(np.abs(scale))


#: Directions of the unit-diagonal ``E[y yᵀ]`` below this fraction of its largest eigenvalue carry no information
#: for the gains (:func:`solve_gains`).
GAIN_RCOND = 1e-9


def solve_gains(ey: np.ndarray, yy: np.ndarray, scale: np.ndarray, has: np.ndarray, m: int | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """``Z = E[e yᵀ] E[y yᵀ]⁺`` per item, and the condition number of what was solved; items without packets
    (``~has``) solve the measurement block alone (its first ``m`` rows; ``m`` defaults to the width of ``ey`` less
    its rows, one consensus innovation of ``n`` components).

    In the units of ``scale`` (``S = D⁻¹ E[y yᵀ] D⁻¹``, ``D = diag(scale)``, the innovations' sizes were the
    nodes' errors independent, :func:`_moments`) the eigenvalues below :data:`GAIN_RCOND` of the largest are
    taken as zero: the (weighted) minimum-norm solution.  In such a direction the nodes' errors agree to
    within ``3e-5`` of their size, and its variance is a difference that the joint covariance carries to
    about ``1e-13`` of that size after earlier steps' gains (measured on a 28-node design): solved, it set
    the gains by rounding noise.  The condition number is ``λmax / λmin`` of ``S`` over the directions kept:
    the moments' relative errors grow into the gains by up to that factor.

    The padding (zero rows and columns: links and components a node does not have) is left out before anything is
    solved, items of one size together (a node of degree 5 among degree-8 ones solves a 37 x 37 system, not
    58 x 58), and an item that keeps every direction (its eigenvalues say so) is solved by an LU factorisation,
    the same ``Z`` to rounding; only items with a direction to drop get the eigendecomposition (the scheduled
    design's systems have condition numbers below 200; the joint mse gains meet such directions).  On a 28-node
    design this is 1.8 x less time than one eigendecomposition of every padded system.
    """
    shape = ey.shape
    m = shape[-1] - shape[-2] if m is None else int(m)  # ey is (n, m + n) unless told
    ey, yy = ey.reshape((-1,) + shape[-2:]), yy.reshape((-1,) + yy.shape[-2:])
    scale, has = scale.reshape(-1, scale.shape[-1]), np.reshape(has, -1)
    Z = np.zeros(ey.shape)
    kappa = np.ones(has.shape)
    finite = np.isfinite(yy).all(axis=(-2, -1)) & np.isfinite(ey).all(axis=(-2, -1)) & np.isfinite(scale).all(axis=-1)
    Z[~finite], kappa[~finite] = np.nan, np.nan  # a covariance beyond floats: no gains (the run diverges)
    for rows, width in ((np.flatnonzero(~has & finite), m), (np.flatnonzero(has & finite), shape[-1])):
        if not rows.size:
            continue
        d = np.asarray(scale[rows, :width], dtype=float)  # moments in long double too: solved in double
        d = np.where(d > 0, d, 1.0)
        Sc = np.asarray(yy[rows, :width, :width], dtype=float) / (d[:, :, None] * d[:, None, :])
        b = np.asarray(ey[rows, :, :width], dtype=float) / d[:, None, :]
        # the padding (components of zero variance: zero rows and columns, and a zero E[e yᵀ] by Cauchy-Schwarz,
        # so a zero gain either way) is left out: each item solves the components it has, items of one size at once
        used = np.diagonal(Sc, axis1=-2, axis2=-1) != 0.0
        size = used.sum(axis=-1)
        for s in np.unique(size):
            it = np.flatnonzero(size == s)
            if s == 0:
                continue  # nothing to solve: zero gains, condition 1
            idx = np.argsort(~used[it], axis=-1, kind="stable")[:, :s]  # (items, s) the used components, in order
            Zs, kappa[rows[it]] = _solve_kept(Sc[it[:, None, None], idx[:, :, None], idx[:, None, :]],
                                              np.take_along_axis(b[it], idx[:, None, :], axis=-1))
            Zi = np.zeros((it.size, Z.shape[1], width))
            np.put_along_axis(Zi, idx[:, None, :], Zs / np.take_along_axis(d[it], idx, axis=-1)[:, None, :], axis=-1)
            Z[rows[it], :, :width] = Zi
    return Z.reshape(shape), kappa.reshape(shape[:-2])


def _solve_kept(S: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``b S⁺`` for a stack of unit-scaled ``S`` (k, s, s), the eigenvalues below :data:`GAIN_RCOND` of the largest
    taken as zero, and ``λmax / λmin`` over the kept ones.  The eigenvalues (less than half the work of the
    eigenvectors) tell which items keep every direction: those are solved by an LU factorisation, the same to
    rounding; only the others get the eigendecomposition."""
    lam = eigvalsh(S)
    keep = lam > GAIN_RCOND * lam[:, -1:]
    kappa = lam[:, -1] / np.min(np.where(keep, lam, np.inf), axis=-1)
    Z = np.empty(b.shape)
    full = keep.all(axis=-1)
    if full.any():
        Z[full] = _t(np.linalg.solve(S[full], _t(b[full])))
    if not full.all():
        lam_p, V = eigh(S[~full])
        kp = lam_p > GAIN_RCOND * lam_p[:, -1:]
        inv = np.where(kp, 1.0 / np.where(kp, lam_p, 1.0), 0.0)
        Z[~full] = ((b[~full] @ V) * inv[:, None, :]) @ _t(V)
    return Z, kappa


#: A gain condition number beyond which a design is reported ill-conditioned: more than 6 of double precision's 16
#: digits lost at one step's solve (and the recursion compounds it over the steps).
ILL_CONDITIONED = 1e6


def conditioning(gain_condition: np.ndarray | None) -> dict:
    """``schedule.json``'s ``conditioning``: each node's largest gain condition number over the steps and where.

    ``gain_condition`` (steps, N) of :attr:`filters.consensus_batch.ConsensusResult.gain_condition` (mode mse), or None
    (the paper and tuned modes solve each node's own system, whose noise covariance keeps it regular, and record
    none).  ``ill_conditioned`` lists the nodes beyond :data:`ILL_CONDITIONED`.
    """
    out = {"threshold": ILL_CONDITIONED, "gain_condition": None, "gain_condition_step": None, "ill_conditioned": []}
    if gain_condition is None or not np.isfinite(gain_condition).any():
        return out
    kappa = np.where(np.isfinite(gain_condition), gain_condition, -np.inf)
    step = np.argmax(kappa, axis=0)
    worst = kappa[step, np.arange(kappa.shape[1])]
    out["gain_condition"] = [float(v) if np.isfinite(v) else None for v in worst]
    out["gain_condition_step"] = [int(k) if np.isfinite(v) else None for k, v in zip(step, worst)]
    out["ill_conditioned"] = [int(i) for i in np.flatnonzero(worst > ILL_CONDITIONED)]
    return out


def mse_gains(Pm, i: int, received, H: np.ndarray, R: np.ndarray, fdi_second: np.ndarray, condition: bool = False):
    """``(K_i, C_i)`` minimising node i's mean-square error given its received packets.

    ``Pm`` a :class:`JointCovariance` (or absolute joint blocks (..., N, N, n, n)); ``received``: the indices
    of the packets node i kept, or a mask (..., N) over a stack of runs (``H`` (..., m, n), ``R`` (m, m) or
    (..., m, m), ``fdi_second`` (..., n, n); the gains are then (..., n, m) and (..., n, n)).
    ``fdi_second``: ``Σ_{j∈R_i} q_ij M``, the second moment of what the attacker adds to the
    consensus innovation.  Without received packets ``C_i = 0`` and ``K_i`` is the EKF gain.
    A singular ``E[y yᵀ]`` (e.g. neighbours whose estimates equal node i's) is solved in the
    least-squares sense: the minimum-norm minimiser (:func:`solve_gains`).  ``condition=True`` also
    returns the condition number of the system solved, per item (a float for one run).
    """
    Pm = as_difference(Pm)
    H = np.asarray(H, dtype=float)
    N = Pm.P.shape[-3]
    w = np.broadcast_to(_indices_mask(received, N), Pm.P.shape[:-3] + (N,))
    ey, yy, s, scale = _moments(Pm, i, w, H, np.asarray(R, dtype=float), fdi_second)
    m = H.shape[-2]
    Z, kappa = solve_gains(ey, yy, scale, s > 0)
    if condition:
        return Z[..., :m], Z[..., m:], _item(kappa)
    return Z[..., :m], Z[..., m:]


def _transition(KH: np.ndarray, C: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """``T`` (..., N, N, n, n): ``T_ii = I - K_i H_i - s_i C_i``, ``T_ij = C_i`` for the kept ``j`` (``keep``)."""
    N, n = C.shape[-3], C.shape[-1]
    T = np.where(keep[..., None, None], C[..., :, None, :, :], 0.0)
    idx = np.arange(N)
    T[..., idx, idx, :, :] = np.eye(n) - KH - keep.sum(axis=-1)[..., None, None] * C
    return T


def _gain_products(K, C, H, received, n_nodes: int):
    """``T`` and each node's ``K_i`` as a list (sensors may differ in dimension) from the per-node gains."""
    Ks = _nodes(K, n_nodes)
    T = _transition(_per_node([k @ h for k, h in zip(Ks, _nodes(H, n_nodes))]), _per_node(C),
                    _received_mask(received, n_nodes))
    return T, Ks


def joint_update(Pm, K, C, H, R, received, fdi_second):
    """``P⁺ = T P⁻ Tᵀ + blockdiag(K_i R_i K_iᵀ + C_i S_i C_iᵀ)`` for the given gains (module docstring).

    Per node: ``K``, ``H``, ``R`` sequences of N arrays (sensors may differ in dimension; leading runs
    axes allowed), ``C`` and ``fdi_second`` sequences or arrays (..., N, n, n); ``received``: one index
    list per node, or the mask (..., N, N) of kept packets.  ``Pm`` a :class:`JointCovariance`, or
    absolute joint blocks (then so is the result).

    In difference form, with ``e_i⁺ = A_i e_i - C_i Δ_i + ν_i`` (``A_i = I - K_i H_i``, ``Δ_i = Σ_{j∈R_i} (e_i - e_j)``,
    ``ν_i`` the node's own noise of covariance ``N_i``), ``X_ik = E[e_i Δ_kᵀ]``, ``Y_ik = E[Δ_i Δ_kᵀ]`` and
    ``Z_ij = E[Δ_i (e_i - e_j)ᵀ]`` are sums of ``G`` blocks (with the kept packets' Laplacian ``L = diag(s) - W``,
    ``Λ = L ⊗ I``: ``X = -G Λᵀ``, ``Y = Λ X``, ``Z_ij = (Λ G)_ij + Σ_m W_im G_mi``), and

        P⁺_i  = B_i A_iᵀ + E_i,      B_i = A_i P_i - C_i X_iiᵀ,   E_i = C_i Y_ii C_iᵀ - A_i X_ii C_iᵀ + N_i
        G⁺_ij = B_i (A_i - A_j)ᵀ + (A_i G_ij - C_i Z_ij) A_jᵀ + (A_i X_ij - C_i Y_ij) C_jᵀ + E_i   (i ≠ j)

    with ``A_i - A_j = K_j H_j - K_i H_i``: every term is small where the nodes agree.
    """
    if not isinstance(Pm, JointCovariance):
        return as_absolute(joint_update(as_difference(Pm), K, C, H, R, received, fdi_second))
    N, n = Pm.P.shape[-3], Pm.P.shape[-1]
    Ks = _nodes(K, N)
    KH = _per_node([k @ h for k, h in zip(Ks, _nodes(H, N))])
    Cs = _per_node(C)
    W = _received_mask(received, N).astype(float)
    s = W.sum(axis=-1)
    A = np.eye(n) - KH
    noise = _per_node([k @ r @ _t(k) for k, r in zip(Ks, _nodes(R, N))]) + Cs @ _per_node(fdi_second) @ _t(Cs)
    Lam = np.kron(s[..., :, None] * np.eye(N) - W, np.eye(n))
    G = Pm.G
    X = -(G @ _t(Lam))
    Y = Lam @ X
    Z = Lam @ G
    idx = np.arange(N)
    Zb = _blocks(Z, N)
    Zb += np.einsum("...im,...miab->...iab", W, Pm.blocks())[..., :, None, :, :]
    Xd, Yd = _blocks(X, N)[..., idx, idx, :, :], _blocks(Y, N)[..., idx, idx, :, :]
    B = A @ Pm.P - Cs @ _t(Xd)
    E = Cs @ Yd @ _t(Cs) - A @ Xd @ _t(Cs) + noise
    Gn = _pairwise(B, -KH) + _right(_left(A, G) - _left(Cs, Z), A) + _right(_left(A, X) - _left(Cs, Y), Cs)
    Gb = _blocks(Gn, N)
    Gb += E[..., :, None, :, :]
    return JointCovariance(symmetrize(B @ _t(A) + E), _zero_diagonal(Gn, N))


# --------------------------------------------------------------------------- the certificate
class JointBound(NamedTuple):
    phi: np.ndarray  # (..., N, N, n, n) the bound of the stacked error; node i's bound is phi[..., i, i]
    multiplier: float | np.ndarray  # σ of (26) or β of (27), one for the network (one per run for a stack)
    margin: float | np.ndarray  # 1/λmax(D Φ Dᵀ) - (1+ε) σ, or 1/λmax(D Φ⁻ Dᵀ) - β: > 0 where the bound holds


def joint_multiplier(h, mu, a, c: float, xmax):
    """Per item, the ``x`` in ``(0, xmax]`` minimising ``Σ_k h_k c x / (1 - c x μ_k) + a / x``.

    This is the part of ``tr A (P⁻¹ - c x DᵀD)⁻¹ Aᵀ + a / x`` that depends on the multiplier, with
    ``D P Dᵀ = Σ_k μ_k q_k q_kᵀ`` and ``h_k = |A P Dᵀ q_k|²`` (Woodbury): the trace of (26) for σ
    (``c = 1 + ε``, ``a = tr U Uᵀ / ε``) and of the own term of (27) for β (``c = 1``,
    ``a = ||K V||²``).  It is convex, so the minimiser is the root of its increasing slope
    ``p(x) - a / x²``, ``p(x) = Σ_k h_k c / (1 - c x μ_k)²``, on ``[10⁻¹² xmax, xmax]``
    (:func:`designer.tuning.increasing_root`, all items at once, to ``10⁻¹¹`` relative); ``x = 0``
    where ``a = 0`` (the trace only grows with x).  As ``p`` increases, the root lies in
    ``[√(a / p(xmax)), √(a / p(0))]``, a bracket within a factor ``1 / margin`` that the search
    starts from.  An item whose slope leaves floats at an end falls back to the bounded scalar
    search of the trace (:func:`designer.tuning.best_multiplier`).  ``h``, ``mu`` (..., r), ``a``,
    ``xmax`` (...).
    """
    h, mu = np.asarray(h, dtype=float), np.asarray(mu, dtype=float)
    a = np.asarray(a, dtype=float)
    shape = a.shape
    h, mu = h.reshape(-1, h.shape[-1]), mu.reshape(-1, mu.shape[-1])
    a, xmax = a.reshape(-1), np.broadcast_to(np.asarray(xmax, dtype=float), shape).reshape(-1)
    out = np.zeros(a.shape)
    act = np.flatnonzero(a > 0)
    if act.size:
        def slope(x, idx):
            it = act[idx]
            return np.sum(h[it] * c / (1.0 - c * x[:, None] * mu[it]) ** 2, axis=-1) - a[it] / x**2

        top = xmax[act]
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            p0 = np.sum(h[act] * c, axis=-1)
            p1 = np.sum(h[act] * c / (1.0 - c * top[:, None] * mu[act]) ** 2, axis=-1)
            lo = np.minimum(np.maximum(top * 1e-12, np.sqrt(a[act] / p1)), top)
            hi = np.maximum(np.minimum(top, np.sqrt(a[act] / p0)), lo)
        lo = np.where(np.isfinite(lo), lo, top * 1e-12)  # p(xmax) beyond floats: the whole interval
        out[act] = increasing_root(slope, lo, np.where(np.isfinite(hi), hi, top), xtol=top * 1e-13, rtol=1e-11)
        for j in act[~np.isfinite(out[act])]:
            out[j] = best_multiplier(lambda x: float(np.sum(h[j] * c * x / (1.0 - c * x * mu[j])) + a[j] / x),
                                     float(xmax[j]), True)
    return out.reshape(shape)


def _woodbury(P: np.ndarray, D: np.ndarray | None):
    """``μ`` (ascending) and ``G = P Dᵀ Q`` with ``D P Dᵀ = Q diag(μ) Qᵀ``, so that
    ``(P⁻¹ - c DᵀD)⁻¹ = P + G diag(c / (1 - c μ)) Gᵀ`` (``D = I`` when None: ``G = Q diag(μ)``): one eigh
    per matrix serves the margin, the multiplier's search and the bound."""
    if D is None:  # the joint arrays are symmetric to the bit (eigh reads one triangle)
        mu, Q = eigh(P)
        return mu, Q * mu[..., None, :]
    PD = P @ D.T
    mu, Q = eigh(symmetrize(D @ PD))
    return mu, PD @ Q


#: The largest ratio ``t`` of the deviation multiplier to the common one (:func:`shared_structure`): where the nodes'
#: errors agree to rounding, the deviations' remainder is all but zero.
SHARED_RATIO_MAX = 1e12


def _top_eigenvalue(A: np.ndarray, iterations: int = 60) -> float:
    """An estimate from below of ``λmax`` of a symmetric positive semidefinite ``A`` (power iteration from the
    all-ones vector and its alternation; enough to balance two multipliers, never used as a bound)."""
    if not A.size:
        return 0.0
    x = np.ones(A.shape[0]) + 0.5 * (-1.0) ** np.arange(A.shape[0])
    lam = 0.0
    for _ in range(iterations):
        y = A @ x
        norm = float(np.linalg.norm(y))
        if not norm > 0 or not np.isfinite(norm):
            return lam if np.isfinite(norm) else np.inf
        lam = float(x @ y) / float(x @ x)
        x = y / norm
    return max(lam, float(x @ (A @ x)))


def _left_apply(M: np.ndarray, W: np.ndarray, N: int) -> np.ndarray:
    """``M (I ⊗ W)`` for a matrix ``M`` (r, N n) and ``W`` (n, n)."""
    n = W.shape[0]
    return (M.reshape(M.shape[0], N, n) @ W).reshape(M.shape)


def shared_structure(P: np.ndarray, N: int, common: float, copies: np.ndarray | None = None,
                     W: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """The two parts of the stacked structure of the shared remainders (module docstring) for the bound ``P``
    (N n, N n): ``A = (1ᵀ ⊗ I) / common`` (n, N n), ``Dd = B^{1/2} Π`` (N n, N n) with ``B = diag(copies) ⊗ I`` (how
    many remainder blocks act on each node's deviation; 1 without ``copies``), and the ratio ``t0`` that gives the
    common block ``A P Aᵀ`` and the deviation block ``t0 Dd P Ddᵀ`` the same largest eigenvalue (at most
    :data:`SHARED_RATIO_MAX`): where the search for ``t`` starts (:func:`shared_search`); ``D = [A ; √t Dd]``.
    ``W`` (n, n): the remainders act on ``W e`` (``W ē``, ``W δ_i``) instead of ``e``: ``A`` and ``Dd`` times
    ``I ⊗ W`` on the right."""
    n = P.shape[-1] // N
    A = np.kron(np.ones((1, N)), np.eye(n)) / common
    Pi = np.eye(N * n) - np.kron(np.full((N, N), 1.0 / N), np.eye(n))
    Dd = Pi if copies is None else np.repeat(np.sqrt(np.asarray(copies, dtype=float)), n)[:, None] * Pi
    if W is not None:
        A, Dd = _left_apply(A, W, N), _left_apply(Dd, W, N)
    lc = float(np.linalg.eigvalsh(symmetrize(A @ P @ A.T))[-1])
    ld = _top_eigenvalue(symmetrize(Dd @ P @ Dd.T))
    t = SHARED_RATIO_MAX if not ld > lc / SHARED_RATIO_MAX else lc / ld
    return A, Dd, float(t)


#: The search for the ratio t of the shared remainders' multipliers: golden-section steps over log t, within
#: ``SHARED_SPAN`` decades of the balanced start on either side.  0: the balanced start alone (measured on a ring,
#: the indoor robot and a 24-node model, ten steps made the bound's trace 0-8 % smaller for 11 eigendecompositions
#: per step instead of 1).
SHARED_STEPS = 0
SHARED_SPAN = 4.0


def shared_search(evaluate, t0: float):
    """The ``t`` in ``[t0 10^-SPAN, t0 10^SPAN]`` whose bound ``evaluate(t) -> (trace, result)`` has the smallest
    trace (golden section over ``log t``, :data:`SHARED_STEPS` steps, the best point seen kept): ``result``.
    Every ``t > 0`` gives a valid bound, so the search only makes it tighter."""
    g = (np.sqrt(5.0) - 1.0) / 2.0
    lo, hi = np.log10(t0) - SHARED_SPAN, np.log10(t0) + SHARED_SPAN
    seen = {}

    def f(x):
        if x not in seen:
            tr, res = evaluate(float(10.0 ** x))
            seen[x] = (tr if np.isfinite(tr) else np.inf, res)
        return seen[x][0]

    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    f(np.log10(t0))
    for _ in range(SHARED_STEPS):
        if f(a) <= f(b):
            hi, b = b, a
            a = hi - g * (hi - lo)
        else:
            lo, a = a, b
            b = lo + g * (hi - lo)
    best = min(seen, key=lambda x: seen[x][0])
    return seen[best][1]


def certificate_predict(Phi: np.ndarray, F, U, Q: np.ndarray, eps: float, D=None,
                        margin: float = MARGIN, shared: bool = False, tight: bool = False) -> JointBound:
    """(26) for the stacked error, σ minimising the trace with (28) at ``margin`` (module docstring).

    ``Phi`` (N, N, n, n) or a stack (..., N, N, n, n); ``F``, ``U`` one (..., n, n) per node (or
    (..., N, n, n)); ``D`` one structure per node (None: I), the same for every run.  ``shared``: the nodes'
    remainders are one function of their errors (module docstring, **Shared remainders**; one run, one ``D`` and
    one ``U`` for every node).  ``tight``: the remainder term ``((1+ε) σ)⁻¹ U Uᵀ`` of the paper's own lemma, the first
    inequality of its (31), instead of the ``(εσ)⁻¹ U Uᵀ`` that (26) loosens it to (``1/ε > 1/(1+ε)``; the loosening
    serves Theorem 2's conditions, not the bound): with σ chosen for the trace, ε then drops out.
    """
    N, n = Phi.shape[-4], Phi.shape[-1]
    P, Db = _dense(Phi), _structure(D, n)
    Fs, Us = _per_node(F), _per_node(U)
    UU = Us @ _t(Us)
    c = 1.0 + eps
    split = c if tight else eps  # the remainder term is U Uᵀ / (split σ)
    if shared:
        same = D is None or all(d is not None and np.array_equal(d, D[0]) for d in D)
        if P.ndim != 2 or not same or not np.all(Us == Us[:1]):
            raise ValueError("shared remainders take one run, one D and one U for every node")
        A, Dd, t0 = shared_structure(P, N, float(N), W=None if D is None else np.asarray(D[0], dtype=float))
        base = _sandwich(Fs, P) + _dense(np.broadcast_to(Q, (N, N, n, n)))
        UUc, UUd = np.kron(np.ones((N, N)), UU[0]), np.kron(np.eye(N), UU[0])

        def evaluate(t):
            Ds = np.vstack([A, np.sqrt(t) * Dd])
            mu, Qv = eigh(symmetrize(Ds @ P @ Ds.T))
            FG = _left(Fs, (P @ Ds.T) @ Qv)
            UUs = UUc + (4.0 / t) * UUd
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                sigma = float(joint_multiplier(np.sum(FG**2, axis=-2), mu, float(np.trace(UUs)) / split, c,
                                               (1.0 - margin) / (c * mu[-1])))
                d = c * sigma / (1.0 - c * sigma * mu)
                phi = base + (FG * d[None, :]) @ _t(FG) + (UUs / (split * sigma) if sigma > 0 else 0.0)
            return float(np.trace(phi)), (phi, sigma, float(1.0 / mu[-1] - c * sigma))

        phi, sigma, marg = shared_search(evaluate, t0)
        alone = certificate_predict(Phi, F, U, Q, eps, D, margin=margin, tight=tight)  # independent blocks: a bound
        if np.trace(_dense(alone.phi)) <= np.trace(phi) or not np.isfinite(np.trace(phi)):
            return alone
        return JointBound(_blocks(symmetrize(phi), N), sigma, marg)
    mu, G = _woodbury(P, Db)
    a = np.trace(UU, axis1=-2, axis2=-1).sum(axis=-1) / split
    FG = _left(Fs, G)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        sigma = joint_multiplier(np.sum(FG**2, axis=-2), mu, a, c, (1.0 - margin) / (c * mu[..., -1]))
        d = c * sigma[..., None] / (1.0 - c * sigma[..., None] * mu)
        phi = _sandwich(Fs, P) + (FG * d[..., None, :]) @ _t(FG) + _dense(np.broadcast_to(Q, (N, N, n, n)))
        lin = np.where(sigma > 0, 1.0 / (split * np.where(sigma > 0, sigma, 1.0)), 0.0)  # (εσ)⁻¹ U Uᵀ, 0 at σ = 0
        phi = _add_diagonal_blocks(phi, lin[..., None, None, None] * UU)
    return JointBound(_blocks(symmetrize(phi), N), _item(sigma), _item(1.0 / mu[..., -1] - c * sigma))


def _fdi_sums(q_fdi, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """``Σ_j q_ij`` and ``Σ_j q_ij²`` per node: from one array of the kept packets' q per node, or from
    an array (..., N, N) that is 0 outside them."""
    if isinstance(q_fdi, np.ndarray) and q_fdi.ndim >= 2 and q_fdi.shape[-2:] == (n_nodes, n_nodes):
        return q_fdi.sum(axis=-1), (q_fdi**2).sum(axis=-1)
    q = [np.asarray(qi, dtype=float) for qi in q_fdi]
    return np.array([np.sum(qi) for qi in q]), np.array([np.sum(qi**2) for qi in q])


def certificate_update(Pm: np.ndarray, K, C, H, R, V, received, fdi_second, fdi_mean, q_fdi, D=None,
                       margin: float = MARGIN) -> JointBound:
    """(27) for the stacked error and the given gains, β minimising the trace with (29) at ``margin``.

    ``fdi_second[i] = Σ_{j∈R_i} q_ij E[ξ ξᵀ]``, ``fdi_mean = E[ξ]`` (n,), ``q_fdi[i]`` the
    probabilities ``q_ij`` of node i's received packets (module docstring).  A stack of runs:
    ``Pm`` (..., N, N, n, n), per-node arrays with the same leading axes (as in :func:`joint_update`),
    ``received`` the mask (..., N, N) and ``q_fdi`` (..., N, N), zero outside the kept packets.
    """
    N, n = Pm.shape[-4], Pm.shape[-1]
    P, Db = _dense(Pm), _structure(D, n)
    T, Ks = _gain_products(K, C, H, received, N)
    T = _dense(T)
    Cs = _per_node(C)
    KV = [k @ v for k, v in zip(Ks, _nodes(V, N))]
    KVV = _per_node([kv @ _t(kv) for kv in KV])
    v = np.trace(KVV, axis1=-2, axis2=-1).sum(axis=-1)  # ||K V||²
    mu, G = _woodbury(P, Db)
    TG = T @ G
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        beta = joint_multiplier(np.sum(TG**2, axis=-2), mu, v, 1.0, (1.0 - margin) / mu[..., -1])
        d = beta[..., None] / (1.0 - beta[..., None] * mu)
        own = T @ P @ _t(T) + (TG * d[..., None, :]) @ _t(TG)
        own = _add_diagonal_blocks(own, np.where(v > 0, 1.0 / np.where(v > 0, beta, 1.0), 0.0)[..., None, None, None]
                                   * KVV)  # β⁻¹ (K V)(K V)ᵀ
        mean = np.zeros(n) if fdi_mean is None else np.asarray(fdi_mean, dtype=float)
        q1, q2 = _fdi_sums(q_fdi, N)
        c_mu = (q1[..., None] * (Cs @ mean)).reshape(Cs.shape[:-3] + (N * n,))
        fdi = _add_diagonal_blocks(c_mu[..., :, None] * c_mu[..., None, :],
                                   Cs @ (_per_node(fdi_second) - q2[..., None, None] * np.outer(mean, mean)) @ _t(Cs))
        biased = np.any(c_mu != 0, axis=-1)  # a biased signal: the cross terms by the split of the smallest trace
        if np.any(biased):
            ta = np.sqrt(np.maximum(np.trace(own, axis1=-2, axis2=-1), 0.0))
            tb = np.sqrt(np.maximum(np.trace(fdi, axis1=-2, axis2=-1), 0.0))
            pi = np.where(biased, tb / (ta + tb), 0.5)[..., None, None]
            own = np.where(biased[..., None, None], own / (1.0 - pi), own)
            fdi = np.where(biased[..., None, None], fdi / pi, fdi)
        out = _add_diagonal_blocks(own + fdi, _per_node([k @ r @ _t(k) for k, r in zip(Ks, _nodes(R, N))]))
    return JointBound(_blocks(symmetrize(out), N), _item(beta), _item(1.0 / mu[..., -1] - beta))
