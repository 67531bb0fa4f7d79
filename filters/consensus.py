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
bound of the stacked error of all nodes for those gains (``'mse'``, :mod:`designer.joint`;
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
:mod:`rules.mse.filter` and mode scheduled to :mod:`rules.scheduled.filter`): a run alone and the same run
in a batch are the same numbers, and the result of a run (:class:`filters.consensus_batch.ConsensusResult`) is
a row of the batch's.  This module holds the run alone: its inputs checked (:func:`check_run_inputs`) and the
wrapped residual of one sensor (:func:`wrapped_residual`).  What every form shares lives below it: the χ² gate
on stacked channels in :mod:`filters.channels`, the constants :data:`filters.result.HARD_CONDITIONS` and
:data:`filters.result.DIVERGED` with the divergence bookkeeping in :mod:`filters.result`.
"""
from __future__ import annotations

import numpy as np

from designer.design import ConsensusDesign
from designer.model import Model
from designer.network import SensorNetwork
from designer.validation import InputError, check_covariance, check_finite

from .attacks import AttackPattern
from .consensus_batch import ConsensusResult, EdgeAttacks, run_consensus_batch
from .rrp import wrap_angles

__all__ = ["wrapped_residual", "run_consensus", "check_run_inputs"]


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
    attacks : AttackPattern or EdgeAttacks of one run, optional
        Realised channel attacks (none when omitted).
    x0, phi0 : initial estimate and ``Φ_{0|0}`` (default: the prior's mean and covariance).
    gains : (K, C) arrays of shape (steps, N, ...), optional
        Replay a fixed gain schedule instead of computing the gains (K as in the result:
        node ``i``'s gain in its first ``n_z_i`` columns); no bound is claimed.

    Sensors may differ in measurement dimension; the gains are then returned in one array
    of ``max n_z_i`` columns, zero beyond each node's own.
    """
    z, u, x0, phi0 = check_run_inputs(model, z, inputs, x0, phi0, "phi0")
    if attacks is not None and not isinstance(attacks, (AttackPattern, EdgeAttacks)):
        raise InputError(f"attacks must be a filters.attacks.AttackPattern or a filters.consensus_batch.EdgeAttacks "
                         f"of one run, got {type(attacks).__name__}")
    batch = [attacks] if isinstance(attacks, AttackPattern) else attacks  # None, or EdgeAttacks of one run
    return run_consensus_batch(model, network, z[None], design, inputs=u, x0=x0, phi0=phi0, attacks=batch,
                               gains=gains).detail.run(0)
