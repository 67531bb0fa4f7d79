"""Gain rule ``scheduled``: per-link gains designed offline for the attack statistics, applied at each node."""
from __future__ import annotations

from designer.rule import GainRule

__all__ = ["RULE", "Scheduled"]


class Scheduled(GainRule):
    name = "scheduled"
    runtime = "scheduled"
    needs = ("the step, its own estimate (its Jacobians F, H_i there and its own covariance), its measurement, which "
             "neighbour packets arrived and what they carried (their predictions, and their measurements with "
             "--exchange measurements), and the tables designed offline (designer.scheduled): the whitened "
             "covariance factors of its links per step.")
    summary = ("per-link gains designed offline for the attack statistics (expected joint covariance), applied at "
               "each node with its own Jacobians and covariance")
    offline_tables = True

    def batch_filter(self):
        from .filter import run_scheduled_batch

        return run_scheduled_batch

    def node_filter(self):
        from .filter import ScheduledNetwork, ScheduledNode

        return ScheduledNode, ScheduledNetwork

    def c_export(self):
        from .export_c import ScheduledExport

        return ScheduledExport()


RULE = Scheduled()
