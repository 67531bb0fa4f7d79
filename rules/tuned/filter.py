"""The tuned rule's steps over Theorem 1's recursion, batched over stacked (run, node) items: σ of (26), then β, C,
K and the weights of the weighted (27) from the convex tuning layer (:mod:`designer.tuning`), each node warm-started
from its previous weights (run by :func:`filters.consensus_batch.run_consensus_batch`)."""
from __future__ import annotations

import numpy as np

from designer.bounds import Spectrum, condition28_margin, condition29_margin
from designer.design import ConsensusDesign
from designer.tuning import tune_prediction_batch, tune_weighted_batch
from filters.consensus_batch import NodeRule, PredictionChoice, UpdateChoice

__all__ = ["STEPS", "predict", "update"]


def predict(phi_post: Spectrum, F, U, Q, D, design: ConsensusDesign) -> PredictionChoice:
    """The σ of (26) that makes its trace smallest (:func:`designer.tuning.tune_prediction_batch`), then (28)."""
    ch = tune_prediction_batch(phi_post, F, U, Q, design.epsilon, D=D)
    margin = condition28_margin(phi_post, ch.sigma, design.epsilon, D)
    return PredictionChoice(np.where((margin > 0)[:, None, None], ch.phi_pred, np.nan), margin, ch.sigma)


def update(phi_pred: Spectrum, it: dict, D, design: ConsensusDesign) -> UpdateChoice:
    """(β, C, K) and the weights of the weighted (27) (:func:`designer.tuning.tune_weighted_batch`, warm-started
    from each node's previous weights), then (29) at that β."""
    ch = tune_weighted_batch(phi_pred, it["H"], it["s"], it["V"], it["R"], it["groups"], it["present"], D=D,
                             weights=it["w0"])
    return UpdateChoice(condition29_margin(phi_pred, ch.beta, D), ch.beta, ch.K, ch.C, ch.phi_post, ch.weights)


STEPS = NodeRule(predict, update, weighted=True)
