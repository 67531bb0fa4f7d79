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
