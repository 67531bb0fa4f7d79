"""Gain rule ``flood``: the relay rule's fusion over measurements flooded within L hops (first copy from anyone)."""
from __future__ import annotations

from ..relay import Relay

__all__ = ["RULE", "Flood"]


class Flood(Relay):
    name = "flood"
    needs = ("its own measurement, the first copy of every measurement flooded to it within L hops that arrived (its "
             "value and sensor), its own estimate (the Jacobians of its ball's sensors there) and covariance, and "
             "its ball's arrival and falsification moments, computed offline by Monte Carlo of the network's DoS "
             "and FDI (rules.relay.design.flood_moments); its gain is computed online at the node.")
    summary = ("every measurement flooded over L hops (each node forwards the first copy it receives, from any "
               "neighbour); each node fuses its L-hop ball with one gain minimising the expected covariance over the "
               "attacks")
    routing = "flood"


    @property
    def study_description(self):
        """Its filter's line in ``study comparison``."""
        return ("distributed: every measurement flooded over L hops (the design's rounds, default the network's "
                'diameter up to 8): each node forwards the first copy it receives, from any neighbour, so that a '
                "measurement arrives when any path of the step's surviving channels is short enough; each node fuses "
                "its L-hop ball that arrived with one gain minimising its expected covariance over the channels' "
                'DoS/FDI statistics (moments by Monte Carlo); 2|E| L packets per step')


RULE = Flood()
