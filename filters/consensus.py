"""Distributed consensus EKF under DoS and FDI attacks on neighbour channels (seed 003): one run.

Every node ``i`` runs (3) and (7)::

    x_pred_i = f(x_post_i)
    x_post_i = x_pred_i + K_i [z_i - h_i(x_pred_i)]
               + C_i sum_{j in N_i} (1 - phi_ij) (x_pred_j + gamma_ij xi_ij - x_pred_i)

with ``F``, ``H_i`` from the model layer's CasADi Jacobians and, along the run,
the bound recursion (26)-(27), the gain (30) and the conditions (28)-(29) of
:mod:`designer.bounds`.  The node knows which of its channels were DoS'ed
(the paper's detector); it cannot tell an FDI'd packet from a clean one.

The gains: the paper's ``C = τ Φ_pred`` with (30) and the paper's (27) (``mode='paper'``);
the convex tuning of (β, C, K) that makes the bound smallest, the bound being (27) with the
factors (1 + 2 d_i) and 3 replaced by optimised weights over the node's own error, each
received neighbour's error and the falsified packets (``'tuned'``,
:func:`designer.tuning.tune_weighted_batch`); or the gains that make every node's predicted
mean-square error smallest, from the joint error covariance of all nodes, certified by the
bound of the stacked error of all nodes for those gains (``'mse'``, :mod:`designer.mse`;
one σ and one β for the network; :attr:`ConsensusResult.predicted_mse` holds the prediction).

**The gate** (``design.gate = α > 0``, :func:`gate_channels`): a node tests every received packet by
``(x̂_j - x̂_i)ᵀ Σ_ij⁻¹ (x̂_j - x̂_i) <= χ²_{n_x}(1 - α)`` and drops what fails as if it were
lost.  ``Σ_ij`` is the predicted covariance of that difference: from the joint covariance in
mode mse, ``2 (Φ_i + Φ_j)`` (an upper bound) otherwise, so a clean packet is dropped with
probability at most about α.  In mode mse the gains then count only what the falsified
packets that pass add (:func:`kept_fdi_moments`, from the signal's law against the gate),
and so does the certificate: which packets pass depends on the errors, so with a gate the
bound is a model that the Monte Carlo bound check validates, not a theorem.
:attr:`ConsensusResult.gate_counts` counts packets received, rejected, clean rejected,
falsified received and falsified passed at every step.

When (28) or (29) fails at a node, the violation is recorded (node, step,
condition, margin) and from then on that node runs the fallback recursion
σ = β = 0, U = V = 0 (the consensus EKF without linearisation multipliers, which
stays positive definite), with the bounding inflation factors (1 + 2 d_i) and 3 of
(27) set to 1, so that no indefinite matrix is ever carried on.  Its
Φ is then *not* a bound, and neither is the Φ of a node whose update used a
neighbour's non-bound ``Φ_{j,k+1|k}`` in (27): ``valid`` tracks both.

**One implementation.**  :func:`run_consensus` is a batch of one run of
:func:`filters.consensus_batch.run_consensus_batch` (which dispatches mode mse to
:mod:`filters.mse_batch` and mode scheduled to :mod:`filters.scheduled`): a run alone and the same run
in a batch are the same numbers.  This module holds what every form shares: the result type of a run
(:class:`ConsensusResult`), the χ² gate on stacked channels (:func:`gate_channels`, with
:func:`channel_difference_covariance` and :func:`kept_fdi_moments`), the wrapped residual and the
constants :data:`HARD_CONDITIONS`, :data:`DIVERGED` and :data:`GATE_COUNTS`.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from designer.design import ConsensusDesign
from designer.model import Model
from designer.network import SensorNetwork
from designer.mse import difference_covariance, node_blocks
from designer.validation import InputError, check_covariance, check_finite

from .attacks import AttackPattern
from .rrp import wrap_angles

__all__ = ["gate_channels", "channel_packets", "channel_difference_covariance", "kept_fdi_moments", "GATE_COUNTS",
           "wrapped_residual", "ConsensusResult", "run_consensus", "check_run_inputs", "HARD_CONDITIONS", "DIVERGED"]


HARD_CONDITIONS = ("(28)", "(29)", "diverged")  # any of these makes a design infeasible
DIVERGED = 1e12  # an estimate this large has left any physical meaning: stop, do not propagate (every filter)


GATE_COUNTS = ("received", "rejected", "clean_rejected", "fdi_received", "fdi_passed")


def channel_difference_covariance(P, receiver: np.ndarray, sender: np.ndarray) -> np.ndarray:
    """``Cov(e_j - e_i) = P_ii - P_ij - P_ji + P_jj`` on the channels ``j = sender[e] -> i = receiver[e]``.

    ``P`` a :class:`designer.mse.JointCovariance` (the differences without cancellation,
    :func:`designer.mse.difference_covariance`) or absolute joint blocks (..., N, N, n, n); returns
    (..., E, n, n), regularised by ``1e-12`` of the mean trace of each run's nodes (two nodes with one
    estimate have a zero difference).
    """
    d = node_blocks(P)
    eps = 1e-12 * np.maximum(np.trace(d, axis1=-2, axis2=-1).mean(axis=-1), 1e-300)
    return difference_covariance(P, receiver, sender) + eps[..., None, None, None] * np.eye(d.shape[-1])


def channel_packets(sent: np.ndarray, fdi: np.ndarray | None, xi: np.ndarray | None) -> np.ndarray:
    """What channels carry: the senders' predictions ``sent`` (..., n), ``+ ξ`` where ``fdi`` (...) falsified them
    (``xi`` (..., n); None: no attack).  Every filter forms a received packet this way first, then uses it, so that a
    node filter handed the packet that arrived computes the batched filter's numbers."""
    if fdi is None or xi is None:
        return sent
    return np.where(np.asarray(fdi, dtype=bool)[..., None], sent + xi, sent)


def gate_channels(x_pred: np.ndarray, receiver: np.ndarray, sender: np.ndarray, received: np.ndarray,
                  fdi: np.ndarray | None, xi: np.ndarray | None, cov_diff: np.ndarray | None, alpha: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The χ² gate on stacked directed channels (of one run or of a batch of runs).

    Channel ``e`` carries ``x̂_j (+ ξ_e)`` from ``j = sender[e]`` to ``i = receiver[e]``; ``x_pred``
    (..., N, n) the predictions, ``received`` (..., E) the packets that arrived, ``fdi`` (..., E)
    the falsified ones and ``xi`` (..., E, n) their signal (None: no attack), ``cov_diff``
    (..., E, n, n) the covariance of ``x̂_j - x̂_i`` when nobody lies (None will do at ``α = 0``).
    A received packet is kept when ``dᵀ Σ⁺ d <= χ²_n(1 - α)`` (``d = x̂_j (+ ξ) - x̂_i``; a
    covariance or difference beyond floats cannot judge: kept).  Returns the mask of kept packets
    (..., E) and the counts (..., 5) of :data:`GATE_COUNTS`.
    """
    from scipy.special import chdtri

    received = np.asarray(received, dtype=bool)
    fdi = np.zeros_like(received) if fdi is None else np.asarray(fdi, dtype=bool)
    keep = received.copy()
    if alpha > 0:
        idx = np.nonzero(received)
        runs, e = idx[:-1], idx[-1]
        sent = x_pred[runs + (sender[e],)]
        d = (sent if xi is None else channel_packets(sent, fdi[idx], xi[idx])) - x_pred[runs + (receiver[e],)]
        S = cov_diff[idx]
        ok = np.all(np.isfinite(S), axis=(1, 2)) & np.all(np.isfinite(d), axis=1)
        stat = np.zeros(e.size)
        if ok.any():
            stat[ok] = np.einsum("ea,ea->e", d[ok], (np.linalg.pinv(S[ok], hermitian=True) @ d[ok][..., None])[..., 0])
        keep[idx] = stat <= chdtri(x_pred.shape[-1], alpha)
    rejected = received & ~keep
    counts = np.stack([received.sum(-1), rejected.sum(-1), (rejected & ~fdi).sum(-1), (received & fdi).sum(-1),
                       (keep & fdi).sum(-1)], axis=-1)
    return keep, counts


def kept_fdi_moments(design: ConsensusDesign, keep: np.ndarray, q: np.ndarray, cov_diff: np.ndarray,
                     receiver: np.ndarray, n_nodes: int) -> np.ndarray:
    """``S_i = Σ_{j kept} P(FDI | kept) E[ξ ξᵀ | FDI, kept]`` (..., N, n, n): what the falsified packets that pass
    the gate add, on stacked channels.

    For a kept packet ``P(FDI, kept) = q P(pass | FDI)`` and ``P(kept) = q P(pass | FDI) + (1 - q)(1 - α)``,
    with ``P(pass | FDI)`` and ``E[g² 1{pass}]`` from :meth:`designer.attacks.FDISignal.passing` against the
    clean difference's covariance (the clean part taken as independent of the signal).  ``keep`` (..., E) the
    kept packets, ``q`` (E,) each channel's probability that a received packet is falsified (or (..., E): per
    run), ``cov_diff`` (..., E, n, n) the clean difference's covariance the gate tests against, ``receiver``
    (E,) each channel's receiving node.
    """
    from scipy.special import chdtri

    nx = cov_diff.shape[-1]
    a = design.fdi_signal.amplitudes(nx)
    out = np.zeros(keep.shape[:-1] + (n_nodes, nx, nx))
    idx = np.nonzero(keep)
    if idx[-1].size and np.any(a):
        c = np.einsum("a,eab,b->e", a, np.linalg.pinv(cov_diff[idx], hermitian=True), a)
        p_pass, g2_pass = design.fdi_signal.passing(c, chdtri(nx, design.gate), nx)
        qe = np.broadcast_to(q, keep.shape)[idx]
        weight = qe * g2_pass / np.maximum(qe * p_pass + (1.0 - qe) * (1.0 - design.gate), 1e-300)
        # one packet after the other, in channel order (the per-run sum's order)
        np.add.at(out, idx[:-1] + (receiver[idx[-1]],), weight[:, None, None] * np.outer(a, a))
    return out



def wrapped_residual(model: Model, i: int, z_i, x_pred, k1: int) -> np.ndarray:
    """``z_i - h_i(x_pred)``, with angular components (``Sensor.angles``) beyond ±π wrapped into (-π, π].

    Residuals already inside (-π, π] are left as they are (wrapping them would change their last bit).
    """
    r = np.asarray(z_i, dtype=float) - model.h(i, x_pred, k1)
    angles = list(model.sensors[i].angles)
    if angles:
        r = np.where(np.isin(np.arange(r.size), angles) & (np.abs(r) > np.pi), wrap_angles(r, angles), r)
    return r



def check_run_inputs(model: Model, z, inputs, x0, cov0, cov_name: str = "P0"):
    """A filter run's ``z`` (steps, n_z), ``inputs`` (steps, n_u), ``x0`` and initial covariance, checked.

    ``x0`` and ``cov0`` default to the prior's mean and covariance; returns ``(z, u, x0, cov0)``
    (``u`` of shape ``(steps, 0)`` without inputs).  Errors name the parameter (``cov_name`` for
    the covariance).
    """
    z = check_finite("z", z)
    if z.ndim != 2 or z.shape[1] != model.n_z:
        raise InputError(f"z must have shape (steps, {model.n_z}), got {z.shape}")
    steps = z.shape[0]
    u = np.zeros((steps, 0)) if inputs is None else check_finite("inputs", inputs)
    if u.ndim != 2 or u.shape[0] != steps:
        raise InputError(f"inputs must have shape ({steps}, n_u), one row per step, got {u.shape}")
    x0 = model.prior.mean if x0 is None else check_finite("x0", x0)
    if x0.shape != (model.n_x,):
        raise InputError(f"x0 must have shape ({model.n_x},), got {x0.shape}")
    return z, u, x0, check_covariance(cov_name, model.prior.cov if cov0 is None else cov0, model.n_x)


class ConsensusResult(NamedTuple):
    """A run of the consensus filter over all nodes.

    Φ entries whose ``valid`` flag is False come from the fallback recursion and
    are *not* bounds.  ``violations`` lists ``{node, step, condition, margin}``:
    condition ``'(28)'`` is checked on ``Φ_{k|k}`` (reported at step k),
    ``'(29)'`` on ``Φ_{k+1|k}`` (step k+1), ``'theorem2'`` on ``Φ_{k|k}``; ``'diverged'``
    (with a ``reason``) when a node's estimate or covariance left finite numbers: the run
    stops there and every array is NaN from that step on.
    """

    x_post: np.ndarray  # (steps+1, N, n_x)
    x_pred: np.ndarray  # (steps, N, n_x)
    phi_post: np.ndarray  # (steps+1, N, n_x, n_x)
    phi_pred: np.ndarray  # (steps, N, n_x, n_x)
    K: np.ndarray  # (steps, N, n_x, max n_z_i): node i's gain in K[..., :n_z_i], zero beyond
    C: np.ndarray  # (steps, N, n_x, n_x)
    valid: np.ndarray  # (steps+1, N) bool: phi_post[k, i] is a bound
    margin28: np.ndarray  # (steps, N)
    margin29: np.ndarray  # (steps, N)
    theorem2: np.ndarray  # (steps+1, N)
    violations: list
    sigma: np.ndarray  # (steps, N) σ used in (26) at each node and step (NaN on the fallback)
    beta: np.ndarray  # (steps, N) β used in (27)
    predicted_mse: np.ndarray | None = None  # (steps+1, N) mode 'mse': tr P_ii of the joint error covariance
    gate_counts: np.ndarray | None = None  # (steps, 5) packets per step: GATE_COUNTS (received, rejected, ...)
    # (steps, N) mode 'mse': the condition number of the system each node's gains were solved from
    # (designer.mse.mse_gains); NaN where none was solved
    gain_condition: np.ndarray | None = None

    @property
    def feasible(self) -> bool:
        return not any(v["condition"] in HARD_CONDITIONS for v in self.violations)

    @property
    def diverged(self) -> dict | None:
        """The ``'diverged'`` violation when the run stopped early (its arrays are NaN from that step)."""
        return next((v for v in self.violations if v["condition"] == "diverged"), None)



def run_consensus(model: Model, network: SensorNetwork, z: np.ndarray, design: ConsensusDesign, *,
                  inputs=None, attacks: AttackPattern | None = None, x0=None, phi0=None,
                  gains: tuple[np.ndarray, np.ndarray] | None = None) -> ConsensusResult:
    """Run the consensus filter at every node over the measurements ``z`` (steps, n_z): a batch of one run of
    :func:`filters.consensus_batch.run_consensus_batch`.

    Parameters
    ----------
    model, network : the model (one sensor per node) and the communication graph.
    z : ndarray, shape (steps, n_z)
        Stacked measurements; ``z[k]`` measures ``x_{k+1}``.
    design : ConsensusDesign
    inputs : ndarray, shape (steps, n_u), optional
    attacks : AttackPattern, optional
        Realised channel attacks (none when omitted).
    x0, phi0 : initial estimate and ``Φ_{0|0}`` (default: the prior's mean and covariance).
    gains : (K, C) arrays of shape (steps, N, ...), optional
        Replay a fixed gain schedule instead of computing the gains (K as in the result:
        node ``i``'s gain in its first ``n_z_i`` columns); no bound is claimed.

    Sensors may differ in measurement dimension; the gains are then returned in one array
    of ``max n_z_i`` columns, zero beyond each node's own.
    """
    from .consensus_batch import run_consensus_batch  # late: it builds on this module

    z, u, x0, phi0 = check_run_inputs(model, z, inputs, x0, phi0, "phi0")
    if attacks is not None and not isinstance(attacks, AttackPattern):
        raise InputError(f"attacks must be a filters.attacks.AttackPattern, got {type(attacks).__name__}")
    return run_consensus_batch(model, network, z[None], design, inputs=u, x0=x0, phi0=phi0,
                               attacks=None if attacks is None else [attacks], gains=gains).run(0)
