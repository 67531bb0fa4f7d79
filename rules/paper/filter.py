"""The paper rule's steps over Theorem 1's recursion, batched over stacked (run, node) items: σ and β fixed by the
user, ``C = τ Φ_pred``, the gain (30) and the bound (27) (run by
:func:`filters.consensus_batch.run_consensus_batch`)."""
from __future__ import annotations

import numpy as np

from designer.bounds import (Spectrum, condition29_margin, optimal_gain_from, prediction_bound, shifted_inverse,
                             update_bound_from)
from designer.design import ConsensusDesign
from filters.consensus_batch import NodeRule, PredictionChoice, UpdateChoice

__all__ = ["STEPS", "predict", "update"]


def predict(phi_post: Spectrum, F, U, Q, D, design: ConsensusDesign) -> PredictionChoice:
    """The bound (26) at the design's σ, and (28)."""
    if D is None and np.any(design.sigma):  # (26)'s shifted inverse takes Φ's eigenvectors: one eigh for it and (28)
        phi_post.eig()
    pb = prediction_bound(phi_post, F, U, Q, design.sigma, design.epsilon, D)
    return PredictionChoice(pb.phi_pred, pb.margin28, np.full(pb.margin28.shape, design.sigma))


def update(phi_pred: Spectrum, it: dict, D, design: ConsensusDesign) -> UpdateChoice:
    """(29) at β; where it holds, ``C = τ Φ_pred``, the gain (30) and the bound (27)."""
    m, n = phi_pred.phi.shape[:2]
    H, s, V, R, d, neighbour_terms = (it[key] for key in ("H", "s", "V", "R", "d", "nt"))
    if D is None and np.any(design.beta):  # M's shifted inverse takes Φ_pred's eigenvectors: one eigh for it and (29)
        phi_pred.eig()
    margin = condition29_margin(phi_pred, design.beta, D)
    ok = margin > 0
    if not ok.all():  # the rule on the items inside (29); NaN for the others (they take the fallback)
        out = UpdateChoice(margin, np.full(m, design.beta), np.full((m, n, H.shape[-2]), np.nan),
                           np.full((m, n, n), np.nan), np.full((m, n, n), np.nan))
        if ok.any():
            inner = update(phi_pred.take(ok), {key: v[ok] for key, v in it.items()}, D, design)
            out.K[ok], out.C[ok], out.phi_post[ok] = inner.K, inner.C, inner.phi_post
        return out
    C = design.tau * phi_pred.phi
    M = shifted_inverse(phi_pred, design.beta, D)
    K = optimal_gain_from(M, H, C, s, design.beta, V, R, d)
    phi = update_bound_from(M, H, K, C, s, design.beta, V, R, d, neighbour_terms)
    return UpdateChoice(margin, np.full(m, design.beta), K, C, phi)


STEPS = NodeRule(predict, update)
