"""Gain rule ``relay``: every measurement relayed over L hops along shortest-path routes; each node fuses its ball."""
from __future__ import annotations

from designer.rule import GainRule
from designer.validation import InputError

__all__ = ["RULE", "Relay"]


class Relay(GainRule):
    name = "relay"
    runtime = "local"
    needs = ("its own measurement, the measurements relayed to it over L hops that arrived (their values and "
             "sensors), its own estimate (the Jacobians of its ball's sensors there) and covariance, and its ball's "
             "arrival and falsification moments, computed offline from the network and the DoS and FDI "
             "probabilities (rules.relay.design); its gain is computed online at the node.")
    summary = ("every measurement relayed over L hops along fixed shortest-path routes; each node fuses its L-hop "
               "ball with one gain minimising the expected covariance over the attacks")
    relays = True
    regional = True  # a node fuses its ball without consensus on estimates: it may carry its region alone
    routing = "tree"  # which copy of a relayed measurement a node takes (design.ROUTINGS): its tree parent's

    def check_options(self, options):
        if options.exchange is not None:
            raise InputError(f"exchange is chosen by a rule of offline tables; mode {self.name!r} relays the "
                             "measurements (its exchange is 'relay'): do not give --exchange")
        super().check_options(options)

    def check_exchange(self, design):
        from .design import RELAY

        if design.gate:
            raise InputError(f"mode {self.name!r} does not take a gate (gate must be 0): its gain counts every "
                             "falsified measurement that arrives, from the falsification's statistics")
        if design.exchange != RELAY:
            raise InputError(f"exchange must be {RELAY!r} in mode {self.name!r} (it relays the measurements), got "
                             f"{design.exchange!r}")

    def design_fields(self, options):
        from .design import RELAY

        return {"exchange": RELAY, "robustness": 0.0, "bank": 0}

    def rounds(self, network, rounds: int | None = None) -> int:
        """The hops L of its design on ``network``: ``rounds`` when given, else :func:`rules.relay.design.default_hops`
        (the network's diameter, at most 8)."""
        if rounds is not None:
            return int(rounds)
        from .design import default_hops  # late: scipy's graph routines, not needed to list the rules

        return default_hops(network)

    def candidates(self, network):
        """Every hop count from 1 to its default (the network's diameter, at most 8): more hops, more of the network
        in each node's ball, more numbers relayed."""
        return [{"rounds": L} for L in range(1, self.rounds(network) + 1)]

    def payload(self, model, network, design):
        from .design import relay_payload

        return relay_payload(network, model.sensor_dims, design.rounds, self.routing)

    def record_notes(self):
        from .study import RECORD_NOTES

        return dict(RECORD_NOTES)

    def stationary(self, model, network, design, *, x, u, lmi=True):
        from .study import WHERE, stationary

        return stationary(model, network, design, x=x, u=u, lmi=lmi), WHERE

    def tradeoff_parts(self, model, network, design, steps, *, x, u, inputs_of, record):
        from .study import relay_tradeoff

        return relay_tradeoff(model, network, design, x=x, u=u, record=record)

    def tradeoff(self, network, n_x, design, steps, parts):
        return parts

    @property
    def study_label(self):
        return f"relay EKF ({self.name} design)"

    @property
    def study_description(self):
        """Its filter's line in ``study comparison``."""
        return ("distributed: every measurement relayed over L hops (the design's rounds, default the network's "
                'diameter up to 8) along fixed shortest-path routes; each node fuses the measurements of its L-hop '
                "ball that arrived with one gain minimising its expected covariance over the channels' DoS/FDI "
                'statistics (no consensus on estimates); 2|E| L packets per step')

    def batch_filter(self):
        from .filter import run_relay_design

        return run_relay_design

    def node_filter(self):
        from .filter import RelayNetwork, RelayNode

        return RelayNode, RelayNetwork

    def c_export(self):
        from .export_c import RelayExport

        return RelayExport(self)


RULE = Relay()
