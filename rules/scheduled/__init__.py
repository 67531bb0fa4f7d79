"""Gain rule ``scheduled``: per-link gains designed offline for the attack statistics, applied at each node."""
from __future__ import annotations

from designer.rule import GainRule

__all__ = ["RULE", "Scheduled"]


class Scheduled(GainRule):
    name = "scheduled"
    runtime = "scheduled"
    needs = ("the step, its own estimate (its Jacobians F, H_i there and its own covariance), its measurement, which "
             "neighbour packets arrived and what they carried (their predictions, and their measurements with "
             "--exchange measurements), and the tables designed offline (rules.scheduled.design): the whitened "
             "covariance factors of its links per step.")
    summary = ("per-link gains designed offline for the attack statistics (expected joint covariance), applied at "
               "each node with its own Jacobians and covariance")
    offline_tables = True

    def candidates(self, network):
        """One exchange round per step (the rounds it certifies), with and without the senders' measurements."""
        return [{"exchange": e, "rounds": 1} for e in ("measurements", "predictions")]

    def record_notes(self):
        from .study import RECORD_NOTES

        return dict(RECORD_NOTES)

    def tables(self, model, network, design, steps, *, x0, inputs, stationary=True):
        from .design import design_scheduled

        return design_scheduled(model, network, design, steps, x0=x0, inputs=inputs,
                                exchange=design.exchange == "measurements", stationary=stationary)

    def table_arrays(self, tables):
        from .design import table_arrays

        return table_arrays(tables)

    def recorded_tables(self, model, network, design, arrays, meta):
        from .design import recorded_tables

        return recorded_tables(model, network, design, arrays, meta)

    def stationary_tables(self, model, network, design, horizon, *, inputs):
        from .design import stationary_tables

        return stationary_tables(model, network, design, horizon, inputs=inputs)

    def stationary(self, model, network, design, *, x, u, lmi=True):
        from .study import stationary, where

        return stationary(model, network, design, x=x, u=u, lmi=lmi), where(model, network)

    def tradeoff_parts(self, model, network, design, steps, *, x, u, inputs_of, record):
        from .study import TRADEOFF_STEPS, other_rounds

        return other_rounds(model, network, design, steps, x0=x, inputs=inputs_of(min(int(steps), TRADEOFF_STEPS)))

    def memory_parts(self, network, n_x, rows, steps):
        from .design import table_memory

        return table_memory(network, n_x, steps)

    def tradeoff(self, network, n_x, design, steps, parts):
        from .study import rounds_tradeoff

        return None if design.tables is None else rounds_tradeoff(network, n_x, design, steps, parts)

    def report_settings(self, meta, fmt):
        from .report import settings

        return settings(meta, fmt)

    @property
    def study_description(self):
        """Its filter's line in ``study comparison``."""
        return ("distributed: the consensus EKF whose per-link gains are designed offline for the channels' DoS/FDI "
                'statistics (expected joint error covariance along the nominal trajectory) and applied at each node '
                "with its own Jacobians and covariance; packets carry the sender's prediction and measurement")

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
