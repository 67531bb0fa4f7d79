"""Gain rule ``tuned``: σ, β, C and K from a small convex problem each node solves online at every step."""
from __future__ import annotations

from designer.rule import GainRule
from designer.validation import InputError

from ..paper import LOCAL_NEEDS

__all__ = ["RULE", "Tuned"]


class Tuned(GainRule):
    name = "tuned"
    runtime = "local"
    needs = LOCAL_NEEDS + "; its σ, β and gains come from a small convex problem it solves online at every step."
    summary = "gains minimising the bound (convex tuning, optimised weights)"
    solves_online = True

    def report_settings(self, meta, fmt):
        return ["Tuned mode: the convex tuning layer chooses σ, β, C and K at every node and step (minimising the "
                "trace of the bounds while keeping (28)-(29)), with the update bound (27)'s factors (1 + 2 d_i) and 3 "
                "replaced by weights optimised with them (the node's own error, each received neighbour's and the "
                "falsified packets, `designer.tuning.tune_weighted`).", ""]

    def report_margins(self, meta):
        return ["In tuned mode σ and β are chosen at every node and step to keep (28)-(29) with a small relative "
                "margin (see `designer.tuning`): the margins show how much room the tuning left.", ""]

    @property
    def study_description(self):
        """Its filter's line in ``study comparison``."""
        return ('distributed: each node runs the consensus EKF with sigma, beta and gains tuned by convex '
                'optimisation (Clarabel) at every step; exchanges estimates with its neighbours')

    def batch_filter(self):
        from .filter import STEPS

        return STEPS

    def node_filter(self):
        from filters.consensus_node import ConsensusNetwork, ConsensusNode

        return ConsensusNode, ConsensusNetwork

    def c_export(self):
        raise InputError(f"gain rule {self.name!r} cannot be exported to C: its node solves a convex problem online "
                         "at every step, which the export does not generate (its node filter runs in Python: "
                         "studies.node_filter)")


RULE = Tuned()
