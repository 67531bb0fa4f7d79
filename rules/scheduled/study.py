"""What a scheduled design records beside its run (its hooks of :class:`designer.rule.GainRule`): its stationary
certificate at the operating point and the trade-off of exchange rounds against accuracy."""
from __future__ import annotations

import numpy as np

from designer.verdict import json_number

__all__ = ["RECORD_NOTES", "TRADEOFF_ROUNDS", "TRADEOFF_STEPS", "WHERE", "WHERE_NODEWISE", "where", "stationary",
           "other_rounds", "rounds_tradeoff"]

#: The exchange rounds per step whose accuracy the scheduled design reports beside its own.
TRADEOFF_ROUNDS = (1, 2, 4)
#: The step at which the trade-off compares them (at most; the horizon when shorter).
TRADEOFF_STEPS = 20
#: Where the stationary certificate is computed, in words (schedule.json's stationary_certificate.where).
WHERE = ("at the operating point with the stationary gains of the tables' recursion there; the LMI (cvxpy + "
         "Clarabel) for the fixed point's sigma and beta")

#: The same beyond the joint certificate's size (rules.scheduled.nodewise).
WHERE_NODEWISE = ("at the operating point with the stationary gains of the tables' recursion there; the node-wise "
                  "certificate, each node's own "
                  "bound from its own and its neighbours' bounds (rules.scheduled.nodewise: no cross terms between "
                  "the nodes' errors, looser than the joint bound), its fixed point confirmed with its weights frozen "
                  "(no LMI: no multipliers); the stacked error has N n = {rows} rows, the joint certificate at most "
                  "{most}")


def where(model, network) -> str:
    """Where the stationary certificate of a design of ``model`` on ``network`` is computed, in words: the joint
    certificate's :data:`WHERE`, or beyond its size the node-wise one's."""
    from .design import CERTIFICATE_MAX_DIM

    rows = network.n_nodes * model.n_x
    return WHERE if rows <= CERTIFICATE_MAX_DIM else WHERE_NODEWISE.format(rows=rows, most=CERTIFICATE_MAX_DIM)


#: schedule.json's words on where the gains and the bound come from (GainRule.record_notes).
RECORD_NOTES = {
    "trajectory": "the tables (schedule.npz table_*) and the bound are designed offline along the nominal trajectory "
                  "(the operating point with the known inputs, no noise) for the DoS and FDI probabilities, not "
                  "along a run; K, C and the estimates are those of the nodes applying them on the seeded simulated "
                  "run (SeedSequence(seed).spawn(2)), C the sum of the gains of the links whose packets arrived",
    "replay": "every node applies the tables on any run with its own estimate, covariance and Jacobians and the "
              "packets that arrived (rules.scheduled.filter); the bound is the expected one over the attacks along the "
              "nominal linearisation with the remainders U, V_i (the stacked error's, or beyond "
              "rules.scheduled.design.CERTIFICATE_MAX_DIM rows each node's own: rules.scheduled.nodewise), validated "
              "on fresh runs by study consensus-robot",
    "robustness_note": "the link gains are chosen with the margin robustness = delta (schedule.json robustness): "
                  "each neighbour's difference taken to carry an extra independent error delta P_ii, so that the "
                  "nodes do not lean on the tables' correlations where the state leaves the nominal geometry; the "
                  "expected covariance and the bound are those of the gains so chosen (an assumption chosen by "
                  "measurement, designer.design.ROBUSTNESS)",
}


def stationary(model, network, design, *, x, u, lmi: bool = True):
    """The stationary certificate at the operating point ``x`` (input ``u``):
    :func:`rules.scheduled.certificate.stationary_certificate` with the design's exchange (``lmi`` False: without
    its LMI)."""
    from .certificate import stationary_certificate

    return stationary_certificate(model, network, design, x=x, u=u, exchange=design.exchange == "measurements",
                                  lmi=lmi)


def other_rounds(model, network, design, steps: int, *, x0, inputs) -> dict[int, float]:
    """The expected RMSE at step ``min(steps, TRADEOFF_STEPS)`` of the scheduled designs with the other exchange
    rounds of :data:`TRADEOFF_ROUNDS` (:func:`rounds_tradeoff`), by L; none where the stacked error has more than
    :data:`rules.scheduled.design.CERTIFICATE_MAX_DIM` rows.  ``inputs``: the known inputs of those steps."""
    from .design import CERTIFICATE_MAX_DIM, design_scheduled

    if network.n_nodes * model.n_x > CERTIFICATE_MAX_DIM:
        return {}
    at = min(int(steps), TRADEOFF_STEPS)
    out = {}
    for L in sorted(set(TRADEOFF_ROUNDS) - {design.rounds}):
        tab = design_scheduled(model, network, design._replace(rounds=L, tables=None), at, x0=x0, inputs=inputs,
                               exchange=design.exchange == "measurements", stationary=False)
        with np.errstate(over="ignore", invalid="ignore"):
            out[L] = json_number(np.sqrt(np.trace(tab.P_post[at], axis1=-2, axis2=-1).mean()))
    return out


def rounds_tradeoff(network, n_x: int, design, steps: int, others: dict) -> dict:
    """The accuracy-messages trade-off of the scheduled design: for L in :data:`TRADEOFF_ROUNDS` and the design's
    own rounds, the messages per step (``2 |E| L``) and the expected RMSE of the nodes at step
    ``min(steps, TRADEOFF_STEPS)`` (square root of the mean over nodes of tr P_ii, the design's expected
    covariance; for L > 1 its rounds' packet losses taken as fresh draws).  The other L are designed over those
    steps only, without stationary tables (the first steps of a design do not depend on its horizon), and only
    where the stacked error has at most :data:`rules.scheduled.design.CERTIFICATE_MAX_DIM` rows; ``others``: their
    expected RMSE as :func:`other_rounds` gives it."""
    from .design import CERTIFICATE_MAX_DIM

    N = network.n_nodes
    small = N * n_x <= CERTIFICATE_MAX_DIM
    at = min(int(steps), TRADEOFF_STEPS)
    own = np.trace(design.tables.P_post[at], axis1=-2, axis2=-1)
    with np.errstate(over="ignore", invalid="ignore"):  # a covariance that overflowed: no expected RMSE (null)
        rmse = {**others, design.rounds: json_number(np.sqrt(own.mean()))}
    rows = [{"rounds": L, "messages_per_step": network.messages_per_step(L), "expected_rmse": rmse[L],
             "designed": L == design.rounds} for L in sorted(rmse)]
    return {"step": at, "rows": rows, "note": None if small else (
        f"the other L are not designed here (N n = {N * n_x} > {CERTIFICATE_MAX_DIM}): design with --rounds L to "
        "compare")}
