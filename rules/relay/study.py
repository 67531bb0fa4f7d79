"""What a relay (or flood) design records beside its run (its hooks of :class:`designer.rule.GainRule`): its
stationary certificate at the operating point and the trade-off of hops against accuracy."""
from __future__ import annotations

import numpy as np

__all__ = ["RECORD_NOTES", "RELAY_TRADEOFF_HOPS", "WHERE", "stationary", "relay_tradeoff"]

#: The relay hops whose stationary accuracy a relay design reports beside its own.
RELAY_TRADEOFF_HOPS = (1, 2, 4, 8)
#: A trade-off row whose stationary recursion costs more than this many times the design's own (per iteration, each
#: node's stacked gain of (L + 1) blocks of its carried width: Σ_i ((L + 1) m_i)³) and more than TRADEOFF_COST_FLOOR
#: is not computed, with its reason: on a grid of 118 buses whose nodes carry their regions, 4 hops cost 4.7 x the 3
#: hops of a design (30 s beside its own 12 s), 8 hops 185 x.  Assumptions, chosen: the design's own certificate is
#: what a user waits for; below the floor (a network of tens of states) every row takes a second or two.
TRADEOFF_COST_MAX = 4.0
TRADEOFF_COST_FLOOR = 1e9
#: Where the stationary certificate is computed, in words (schedule.json's stationary_certificate.where).
WHERE = ("at the operating point, every sensor's Jacobian there: each node's expected covariance recursion "
         "(rules.relay.design.relay_update) until it settles, then the LMI (cvxpy + Clarabel) of each node's "
         "expected update with the fixed point's gain held; the expected covariance of the linearised error "
         "(exact for a linear model, the linearisation remainders not in it)")

#: schedule.json's words on where the gains and the bound come from (GainRule.record_notes).
RECORD_NOTES = {
    "trajectory": "seeded simulated run of the scenario: truth and measurements from SeedSequence(seed).spawn(2)[0], "
                  "channel attacks from spawn(2)[1]; each node's gain and bound (its expected covariance over the "
                  "attacks, rules.relay.design.relay_update) along its own estimates and the realised arrivals",
    "replay": "the gains are not a schedule to replay: every node computes its gain and its bound online on any run, "
              "from its own estimate and covariance, the measurements relayed to it that arrived, and its ball's "
              "arrival and falsification moments (rules.relay.design); the bound is the expected covariance of the "
              "linearised error (exact for a linear model, the linearisation remainders not in it), validated on "
              "fresh runs by study consensus-robot and study comparison",
}


def stationary(model, network, design, *, x, u, lmi: bool = True):
    """The stationary certificate at the operating point ``x`` (input ``u``):
    :func:`rules.relay.design.relay_stationary` (``lmi`` False: without its LMI)."""
    from .design import relay_stationary

    return relay_stationary(model, network, design, x=x, u=u, lmi=lmi)


def _recursion_cost(model, routes, design) -> float:
    """Σ_i ((L + 1) m_i)³: one iteration of the stationary recursion's gains at L hops, ``m_i`` the states node i
    carries (its region's when the design carries regions, else every state)."""
    from .design import relay_carried

    width = (np.full(routes.n_nodes, model.n_x) if design.carried_regions is None else
             relay_carried(model, routes, design.carried_regions).used.sum(axis=1))
    return float((((routes.hops + 1) * width.astype(float)) ** 3).sum())


def relay_tradeoff(model, network, design, *, x, u, record: dict | None = None) -> dict:
    """The accuracy-messages trade-off of a relay design: for L in :data:`RELAY_TRADEOFF_HOPS` (up to the network's
    diameter, beyond which nothing more arrives) and the design's own hops, the packets per step (``2 |E| L``), the
    measurements forwarded per step over all channels, and the stationary expected RMSE of the nodes at the operating
    point (square root of the mean over nodes of tr Φ̄_i, over each node's region when the nodes carry their regions:
    :func:`rules.relay.design.relay_stationary` without its LMI); the design's own hops from its stationary ``record``
    (``schedule.json``'s ``stationary_certificate``) when given.  A row costing more than :data:`TRADEOFF_COST_MAX`
    times the design's own and more than :data:`TRADEOFF_COST_FLOOR` is not computed (its ``reason`` says so)."""
    from .design import diameter, relay_routes, relay_stationary

    routing = design.rule.routing
    hops = sorted({L for L in RELAY_TRADEOFF_HOPS if L <= diameter(network)} | {design.rounds})
    routes = {L: relay_routes(network, L, routing) for L in hops}  # once per L: its values per step, its certificate
    cost = {L: _recursion_cost(model, r, design) for L, r in routes.items()}
    rows = []
    for L in hops:
        if cost[L] > max(TRADEOFF_COST_MAX * cost[design.rounds], TRADEOFF_COST_FLOOR):
            rows.append({"rounds": L, "messages_per_step": network.messages_per_step(L),
                         "values_per_step": routes[L].values_per_step(), "expected_rmse": None, "designed": False,
                         "reason": f"not computed: its stationary recursion costs "
                                   f"{cost[L] / cost[design.rounds]:.3g} x the design's own per iteration (more than "
                                   f"{TRADEOFF_COST_MAX:g} x and {TRADEOFF_COST_FLOOR:.0e} operations)"})
            continue
        if record is not None and L == design.rounds:  # the certificate's own fixed point
            rmse = float(np.sqrt(np.mean(record["trace"]))) if record["converged"] else None
        else:
            cert = relay_stationary(model, network, design._replace(rounds=L), x=x, u=u, lmi=False, routes=routes[L])
            rmse = float(np.sqrt(cert.traces().mean())) if cert.converged else None
        rows.append({"rounds": L, "messages_per_step": network.messages_per_step(L),
                     "values_per_step": routes[L].values_per_step(), "expected_rmse": rmse,
                     "designed": L == design.rounds})
    return {"step": "stationary", "rows": rows, "note": "relay: the stationary expected RMSE at the operating point "
            "(rules.relay.design.relay_stationary), " + ("every state component" if design.carried_regions is None
                                                           else "each node's region (the nodes carry their regions)")}
