"""The channels of the consensus filters and the χ² gate on them: the home of what a channel carries.

A directed channel ``j -> i`` carries the sender's prediction ``x̂_j``, ``+ ξ`` where it was falsified
(:func:`channel_packets`); a receiver with a gate (``design.gate = α > 0``) tests every received packet against the
covariance of the difference it would have were nobody lying (:func:`channel_difference_covariance`) and drops what
fails (:func:`gate_channels`, counting :data:`GATE_COUNTS`); in mode mse the gains count what the falsified packets
that pass add (:func:`kept_fdi_moments`).  Every consensus filter (batched, and one node alone) forms and gates its
packets with these functions, so that a node filter computes the batch's numbers.
"""
from __future__ import annotations

import numpy as np

from designer.design import ConsensusDesign
from designer.joint import difference_covariance, node_blocks

__all__ = ["GATE_COUNTS", "channel_difference_covariance", "channel_packets", "gate_channels", "kept_fdi_moments"]


GATE_COUNTS = ("received", "rejected", "clean_rejected", "fdi_received", "fdi_passed")


def channel_difference_covariance(P, receiver: np.ndarray, sender: np.ndarray) -> np.ndarray:
    """``Cov(e_j - e_i) = P_ii - P_ij - P_ji + P_jj`` on the channels ``j = sender[e] -> i = receiver[e]``.

    ``P`` a :class:`designer.joint.JointCovariance` (the differences without cancellation,
    :func:`designer.joint.difference_covariance`) or absolute joint blocks (..., N, N, n, n); returns
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
