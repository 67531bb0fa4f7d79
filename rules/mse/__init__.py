"""Gain rule ``mse``: gains minimising the predicted mean-square error along one run — an oracle (global)."""
from __future__ import annotations

from designer.rule import GainRule

from .memory import JOINT_COPIES, MEMORY_BUDGET

__all__ = ["RULE", "MSE"]


class MSE(GainRule):
    name = "mse"
    runtime = "global"
    needs = ("the joint error covariance of all nodes and every link's realised packet losses (the network's joint "
             "state), i.e. a central computer.")
    summary = ("gains minimising the predicted mean-square error along one run's realised packet losses, certified "
               "by the bound of the stacked error of all nodes")
    joint_covariance = True

    def report_settings(self, meta, fmt):
        return ["MSE mode: K and C minimise every node's predicted mean-square error, from the joint linearised error "
                "covariance of all nodes with the channels' DoS and FDI statistics (`designer.joint`); the certificate "
                "is the bound (26)-(27) written for the stacked error of all nodes with those gains (it propagates "
                "the cross-covariances between nodes instead of bounding them; one σ and one β for the network, "
                "chosen to make it smallest). The gains serve accuracy and the bound certifies them.", ""]

    def report_margins(self, meta):
        return ["In mse mode one σ and one β for the whole network are chosen at every step to make the bound of "
                "the stacked error of all nodes smallest for the gains the mean-square-error design chose, keeping "
                "(28)-(29) with a small relative margin: the margins are the network's, shown at every node.", ""]

    @property
    def study_description(self):
        """Its filter's line in ``study comparison``."""
        return ('distributed: the consensus EKF whose gains minimise the predicted mean-square error of every node '
                "(joint error covariance with the channels' DoS/FDI statistics), certified by the bound of the "
                "stacked error of all nodes for them; a global oracle (its gains need the network's joint state): a "
                'reference, not a filter to deploy')

    def memory_parts(self, network, n_x, rows, steps):
        n_nodes = network.n_nodes
        per_run = JOINT_COPIES * 8 * (n_nodes * n_x) ** 2  # doubles
        return [("the joint error covariance of all nodes (mode mse)", min(rows * per_run, max(MEMORY_BUDGET, per_run)),
                 f"{JOINT_COPIES} x ({n_nodes} nodes x {n_x} states)^2 per run", "another mode")]

    def batch_filter(self):
        from .filter import run_mse_batch

        return run_mse_batch


RULE = MSE()
