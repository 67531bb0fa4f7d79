"""Gain rule ``mse``: gains minimising the predicted mean-square error along one run — an oracle (global)."""
from __future__ import annotations

from designer.rule import GainRule

__all__ = ["RULE", "MSE"]


class MSE(GainRule):
    name = "mse"
    runtime = "global"
    needs = ("the joint error covariance of all nodes and every link's realised packet losses (the network's joint "
             "state), i.e. a central computer.")
    summary = ("gains minimising the predicted mean-square error along one run's realised packet losses, certified "
               "by the bound of the stacked error of all nodes")
    joint_covariance = True

    def batch_filter(self):
        from .filter import run_mse_batch

        return run_mse_batch


RULE = MSE()
