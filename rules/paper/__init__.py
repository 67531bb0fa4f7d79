"""Gain rule ``paper``: the seed paper's design — σ, β and τ fixed by the user, ``C = τ Φ_pred``, gain (30)."""
from __future__ import annotations

from designer.rule import GainRule

__all__ = ["RULE", "Paper", "LOCAL_NEEDS"]

#: What a node of a rule over Theorem 1's recursion needs at run time (the paper's and the tuned rule's).
LOCAL_NEEDS = ("its own measurement, the neighbours' predictions that arrived (as they arrived) and every "
               "neighbour's bound Φ_j each step, also when its prediction was lost ((27) weighs each bound by its "
               "channel's arrival probability: a reliable channel for the bounds is assumed)")


class Paper(GainRule):
    name = "paper"
    runtime = "local"
    needs = LOCAL_NEEDS + "; its gains are computed online at the node (C = τ Φ and the gain (30))."
    summary = "the published choices (sigma = beta = 0.1, C = tau Phi)"
    fixed_multipliers = True

    def report_settings(self, meta, fmt):
        return ["Paper mode, as in the paper: σ and β fixed at every node and step (the published 0.1 unless given), "
                "the consensus gain C = τ Φ_{k+1|k} and K by (30).", ""]

    def report_margins(self, meta):
        return ["In paper mode σ and β are fixed, so a margin falls as Φ grows; where one reaches 0 the node's "
                "bound ends.", ""]

    @property
    def study_description(self):
        """Its filter's line in ``study comparison``."""
        return ("distributed: the consensus EKF with the paper's fixed choices (sigma = beta = 0.1, C = 0.01 Phi)")

    def batch_filter(self):
        from .filter import STEPS

        return STEPS

    def node_filter(self):
        from filters.consensus_node import ConsensusNetwork, ConsensusNode

        return ConsensusNode, ConsensusNetwork

    def c_export(self):
        from .export_c import PaperExport

        return PaperExport()


RULE = Paper()
