"""The stationary certificate's result type: the home of :class:`StationaryCertificate`, a design's bound at the
fixed point of its recursion at one linearisation point (the operating point).

A rule with a stationary certificate (:attr:`designer.rule.GainRule.stationary_certificate`: a rule of offline
tables, or one that relays) computes it in its own package (``rules/<name>/``) and returns this type; the design's
record (``schedule.json``'s ``stationary``) and the feasibility map read it alike, whichever rule computed it.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .verdict import NOT_COMPUTED

__all__ = ["StationaryCertificate"]


class StationaryCertificate(NamedTuple):
    """A design's bound at the fixed point of its recursion at one linearisation point.

    ``converged``: the recursion of the bound with the stationary gains reached a fixed point ``Phi`` (N, n, n
    per node) within ``iterations``; ``sigma``, ``beta`` its multipliers (NaN for a rule that has none);
    ``reason`` why not otherwise (starting with ``"not computed: "`` where it was not computed at all:
    :data:`designer.verdict.NOT_COMPUTED`).  ``lmi``:
    the convex check (cvxpy + Clarabel) of the stationary inequality: ``status``, ``trace`` (the smallest total
    trace of a Φ̄ satisfying it, whose node blocks bound every later Φ once a Φ lies below it), ``max_residual``
    (the largest violation of the inequality by the solver's Φ̄, checked independently), or ``None`` where it was
    not solved (the problem too large, or no fixed point).  ``carried`` (N, m) and ``positions``: when the nodes
    carry their regions (:mod:`designer.regions`), ``Phi`` is in their carried coordinates and ``positions[i]``
    are node i's region's places there; its ``trace`` (:meth:`describe`) is then over each node's region.
    """

    converged: bool
    Phi: np.ndarray | None
    sigma: float
    beta: float
    iterations: int
    reason: str | None
    lmi: dict | None
    carried: np.ndarray | None = None
    positions: tuple | None = None

    def traces(self) -> np.ndarray | None:
        """(N,) each node's tr Φ at the fixed point, over its region when the nodes carry their regions."""
        if self.Phi is None:
            return None
        if self.positions is None:
            return np.trace(self.Phi, axis1=-2, axis2=-1)
        from .regions import region_traces

        return region_traces(self.Phi, self.positions)

    @property
    def not_computed(self) -> bool:
        """Whether the rule did not compute the certificate (its reason starts with ``"not computed: "``): its verdict
        is ``not computed``, never ``infeasible``."""
        return self.reason is not None and self.reason.startswith(f"{NOT_COMPUTED}: ")

    def describe(self) -> dict:
        tr = None if self.Phi is None else [float(v) for v in self.traces()]
        def num(v):
            return float(v) if np.isfinite(v) else None

        return {"converged": self.converged, "trace": tr, "sigma": num(self.sigma), "beta": num(self.beta),
                "iterations": self.iterations, "reason": self.reason, "lmi": self.lmi}
