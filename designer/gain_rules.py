"""Gain rules: the design modes, each declaring what a node needs at run time to apply its gains.

Every design mode (``cfdesign design --mode NAME``, ``DesignOptions(mode=NAME)``) is a
:class:`GainRule` of this registry, and every rule belongs to one run-time class of
:data:`RUNTIMES`:

* ``local`` — the node computes its gains online from what it has: its own measurement,
  the packets it received and their senders' messages (``paper``, ``tuned``; ``relay`` with the measurements
  relayed to it over L hops);
* ``scheduled`` — gains designed offline and applied with what the node itself observes or
  computes (the step, which neighbour packets arrived, its own estimate);
* ``global`` — the gains need the joint state of the network (``mse``: the joint error
  covariance of all nodes and every link's realised packet losses), i.e. a central
  computer.  Such a rule is an **oracle**: a reference of what the structure can reach,
  not a design to deploy (``deployable`` is False).

Everything that lists, checks or reports the modes reads this registry: ``designer.design.MODES``
and the errors naming the allowed modes, the command line's ``--mode`` choices and help,
``schedule.json``'s ``gain_rule`` record (and its check in :func:`studies.schemas.validate`),
the design report's first lines, the ``cfdesign design`` summary, and the studies' ``runtime``
of each filter (with :data:`FILTER_RUNTIMES`, which adds ``centralized`` for the filters of a
fusion centre, which no node runs).

What a rule is, the code asks the rule, never its name: whether the user fixes its multipliers
σ, β, τ (``fixed_multipliers``: the paper's design; they may break (28)/(29) at the first step),
whether its design is a set of tables computed offline and applied online (``offline_tables``:
it chooses what the nodes exchange, the exchange rounds and a robustness margin, and has a
stationary certificate; its gains along one run are not the design) or a seeded run of the
filter (``seeded_design``), whether it holds the joint error covariance of all nodes
(``joint_covariance``: (N n)² memory per run, not mapped by the feasibility map), and whether its packets
relay the measurements over L exchange rounds per step (``relays``, :mod:`designer.relay`).

Adding a rule
-------------
One :func:`register` call beside the built-in rules at the end of this module, plus its
implementation: the filter that applies it over a batch of runs, registered under the rule's name in
``filters.consensus_batch`` (:func:`filters.consensus_batch.register_filter`; the
designer layer does not import the filters)::

    register(GainRule("mine", "scheduled", needs="the step and which neighbour packets arrived",
                      summary="gains designed offline for the attack statistics", offline_tables=True))

The command line's ``--mode`` choices and ``designer.design.MODES`` are read when they load, so a
rule belongs here; a rule registered later (a test's) is known to :func:`gain_rule` and to every
check that looks a mode up, and :func:`unregister` removes it.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from types import MappingProxyType
from typing import Mapping

from .validation import InputError

__all__ = ["GainRule", "RUNTIMES", "FILTER_RUNTIMES", "DEPLOYABLE", "GAIN_RULES", "register", "unregister",
           "gain_rule", "runtime_label", "choices", "caveat", "names_with", "ROUTINGS"]

# The run-time classes of the gain rules: what a node needs to apply the gains, one sentence each.
RUNTIMES: Mapping[str, str] = MappingProxyType({
    "local": "the node computes its gains online from its own measurement, the packets it received and their "
             "senders' messages (predictions and bounds); nothing else is needed at run time.",
    "scheduled": "gains designed offline and applied with what the node itself observes or computes: the step, "
                 "which neighbour packets arrived, its own estimate.",
    "global": "the gains need the joint state of the network (every node's errors and every link's realised "
              "packet losses), i.e. a central computer: an oracle, a reference of what the structure can reach, "
              "not a design to deploy.",
})
# What a study's filter runs on: the gain rules' classes, and a fusion centre (a filter no node can run alone).
FILTER_RUNTIMES: Mapping[str, str] = MappingProxyType({
    **RUNTIMES,
    "centralized": "a fusion centre receives every sensor's measurement over its uplink: not a filter a node can run "
                   "alone, a reference of what centralisation reaches.",
})
DEPLOYABLE = ("local", "scheduled")  # the classes a user can run on the nodes; the others are references
#: Which copy of a relayed measurement a node of a rule that relays takes (designer.relay.Routes): its shortest-path
#: tree parent's, or the first to arrive from any neighbour.
ROUTINGS = ("tree", "flood")
_SHORT = {"local": "computed online at each node", "scheduled": "designed offline, applied with what the node "
          "observes", "global": "an oracle, not deployable", "centralized": "a fusion centre, not a node's filter"}
_NAME = re.compile(r"[a-z][a-z0-9_-]*")


def runtime_label(runtime: str) -> str:
    """``"global: an oracle, not deployable"``: a run-time class of :data:`FILTER_RUNTIMES` with its short phrase."""
    if runtime not in FILTER_RUNTIMES:
        raise InputError(f"runtime must be {_listing(FILTER_RUNTIMES)}, got {runtime!r}")
    return f"{runtime}: {_SHORT[runtime]}"


@dataclass(frozen=True)
class GainRule:
    """A design mode and what a node needs at run time to apply its gains.

    Parameters
    ----------
    name : str
        The mode's name (``--mode NAME``): lower-case letters, digits, ``-`` and ``_``.
    runtime : {'local', 'scheduled', 'global'}
        Its run-time class (:data:`RUNTIMES`).
    needs : str
        One plain sentence: what a node needs at run time to apply the rule.
    summary : str
        One line: how the rule chooses the gains.
    fixed_multipliers : bool
        The user gives σ, β and τ (``--sigma``, ``--beta``, ``--tau``) and the rule keeps them (the paper's
        design): they may break (28)/(29) at the first step, where the design cannot start.  Otherwise the rule
        chooses them (and ε defaults to :func:`designer.tuning.tuned_epsilon`).
    offline_tables : bool
        Its design is a set of tables computed offline (:mod:`designer.scheduled`) and applied online by the
        nodes: it chooses what they exchange (``--exchange``), the exchange rounds (``--rounds``) and a
        robustness margin (``--robustness``), and has a stationary certificate; its gains along one run are
        not the design (they cannot be replayed).  Otherwise the design is a seeded run of the filter.
    joint_covariance : bool
        The filter carries the joint error covariance of all nodes ((N n)² numbers per run); the feasibility
        map does not map it (its gains come from that covariance along a run).
    relays : bool
        Its nodes relay every measurement over L hops per step (``--rounds L``) and fuse the L-hop ball that
        arrived (:mod:`designer.relay`); its design has a stationary certificate.
    routing : {'tree', 'flood'}
        For a rule that relays: which copy of a relayed measurement a node takes (:data:`ROUTINGS`): its
        shortest-path tree parent's, or the first to arrive from any neighbour.
    """

    name: str
    runtime: str
    needs: str
    summary: str
    fixed_multipliers: bool = False
    offline_tables: bool = False
    joint_covariance: bool = False
    relays: bool = False
    routing: str = "tree"

    def __post_init__(self):
        if not isinstance(self.name, str) or not _NAME.fullmatch(self.name):
            raise InputError(f"gain rule name must be lower-case letters, digits, '-' or '_' (starting with a letter), "
                             f"got {self.name!r}")
        if self.runtime not in RUNTIMES:
            raise InputError(f"runtime of gain rule {self.name!r} must be {_listing(RUNTIMES)}, got {self.runtime!r}")
        for field in ("needs", "summary"):
            if not isinstance(getattr(self, field), str) or not getattr(self, field).strip():
                raise InputError(f"{field} of gain rule {self.name!r} must be a non-empty sentence")
        for field in ("fixed_multipliers", "offline_tables", "joint_covariance", "relays"):
            if not isinstance(getattr(self, field), bool):
                raise InputError(f"{field} of gain rule {self.name!r} must be True or False, "
                                 f"got {getattr(self, field)!r}")
        if self.routing not in ROUTINGS:
            raise InputError(f"routing of gain rule {self.name!r} must be {_listing(ROUTINGS)}, got {self.routing!r}")

    @property
    def seeded_design(self) -> bool:
        """Its design is the filter run along a seeded simulated run (its gains there are the schedule)."""
        return not self.offline_tables

    @property
    def takes_rounds(self) -> bool:
        """Its design takes exchange rounds per step (``--rounds``): a rule of offline tables or one that relays."""
        return self.offline_tables or self.relays

    @property
    def stationary_certificate(self) -> bool:
        """Its design has a stationary certificate at the operating point (what the feasibility map maps for it):
        a rule of offline tables or one that relays."""
        return self.offline_tables or self.relays

    @property
    def mappable(self) -> bool:
        """The feasibility map maps it (not a rule whose gains come from the joint covariance of a run)."""
        return not self.joint_covariance

    @property
    def deployable(self) -> bool:
        """Whether a user can run the rule on the nodes (its run time is not ``global``)."""
        return self.runtime in DEPLOYABLE

    @property
    def label(self) -> str:
        """``"mse (global: an oracle, not deployable)"``: the name with its run-time class in words."""
        return f"{self.name} ({runtime_label(self.runtime)})"

    @property
    def caveat(self) -> str | None:
        """For a rule that is not deployable, the clause a verdict adds (None for a deployable rule)."""
        return caveat(self.describe())

    def describe(self) -> dict:
        """``schedule.json``'s ``gain_rule``: ``{name, runtime, needs, deployable}``."""
        return {"name": self.name, "runtime": self.runtime, "needs": self.needs, "deployable": self.deployable}


_RULES: dict[str, GainRule] = {}
GAIN_RULES: Mapping[str, GainRule] = MappingProxyType(_RULES)  # name -> rule, in the order registered (read-only)


def _listing(names) -> str:
    """``'paper', 'tuned' or 'mse'``."""
    quoted = [repr(n) for n in names]
    return quoted[0] if len(quoted) == 1 else ", ".join(quoted[:-1]) + " or " + quoted[-1]


def names_with(flag: str) -> str:
    """The registered rules whose attribute ``flag`` is true, as an error message lists them: ``'scheduled'``."""
    return _listing([name for name, rule in _RULES.items() if getattr(rule, flag)] or ["(none)"])


def choices() -> str:
    """The registered rules' names as an error message lists them: ``'paper', 'tuned' or 'mse'``."""
    return _listing(_RULES)


def caveat(record: Mapping) -> str | None:
    """The clause a verdict adds for a rule that is not deployable, from its record (:meth:`GainRule.describe`,
    ``schedule.json``'s ``gain_rule``); None for a deployable rule."""
    if record.get("deployable", True):
        return None
    return (f"mode {record.get('name')} is a {record.get('runtime')} oracle, a reference of what the structure can "
            f"reach, not a deployable design: its gains need {str(record.get('needs', '')).rstrip('.')}")


def register(rule: GainRule) -> GainRule:
    """Add ``rule`` to :data:`GAIN_RULES` (after the others) and return it; a name may be registered once."""
    if not isinstance(rule, GainRule):
        raise InputError(f"register takes a GainRule, got {type(rule).__name__}")
    if rule.name in _RULES:
        raise InputError(f"gain rule {rule.name!r} is registered already")
    _RULES[rule.name] = rule
    return rule


def unregister(name: str) -> GainRule:
    """Remove the rule ``name`` from :data:`GAIN_RULES` and return it."""
    return _RULES.pop(gain_rule(name, "name").name)


def gain_rule(name, param: str = "mode") -> GainRule:
    """The rule called ``name``; :class:`InputError` naming ``param`` and the registered rules otherwise."""
    rule = _RULES.get(name) if isinstance(name, str) else None
    if rule is None:
        raise InputError(f"{param} must be {choices()}, got {name!r}")
    return rule


_LOCAL_NEEDS = ("its own measurement, the neighbours' predictions that arrived (as they arrived) and every "
                "neighbour's bound Φ_j each step, also when its prediction was lost ((27) weighs each bound by its "
                "channel's arrival probability: a reliable channel for the bounds is assumed)")
register(GainRule(
    "paper", "local",
    needs=_LOCAL_NEEDS + "; its gains are computed online at the node (C = τ Φ and the gain (30)).",
    summary="the published choices (sigma = beta = 0.1, C = tau Phi)", fixed_multipliers=True))
register(GainRule(
    "tuned", "local",
    needs=_LOCAL_NEEDS + "; its σ, β and gains come from a small convex problem it solves online at every step.",
    summary="gains minimising the bound (convex tuning, optimised weights)"))
register(GainRule(
    "mse", "global",
    needs="the joint error covariance of all nodes and every link's realised packet losses (the network's joint "
          "state), i.e. a central computer.",
    summary="gains minimising the predicted mean-square error along one run's realised packet losses, certified by "
            "the bound of the stacked error of all nodes", joint_covariance=True))
register(GainRule(
    "scheduled", "scheduled",
    needs="the step, its own estimate (its Jacobians F, H_i there and its own covariance), its measurement, which "
          "neighbour packets arrived and what they carried (their predictions, and their measurements with "
          "--exchange measurements), and the tables designed offline (designer.scheduled): the whitened covariance "
          "factors of its links per step.",
    summary="per-link gains designed offline for the attack statistics (expected joint covariance), applied at each "
            "node with its own Jacobians and covariance", offline_tables=True))
register(GainRule(
    "relay", "local",
    needs="its own measurement, the measurements relayed to it over L hops that arrived (their values and sensors), "
          "its own estimate (the Jacobians of its ball's sensors there) and covariance, and its ball's arrival "
          "and falsification moments, computed offline from the network and the DoS and FDI probabilities "
          "(designer.relay); its gain is computed online at the node.",
    summary="every measurement relayed over L hops along fixed shortest-path routes; each node fuses its L-hop "
            "ball with one gain minimising the expected covariance over the attacks", relays=True))
register(GainRule(
    "flood", "local",
    needs="its own measurement, the first copy of every measurement flooded to it within L hops that arrived (its "
          "value and sensor), its own estimate (the Jacobians of its ball's sensors there) and covariance, and its "
          "ball's arrival and falsification moments, computed offline by Monte Carlo of the network's DoS and FDI "
          "(designer.relay.flood_moments); its gain is computed online at the node.",
    summary="every measurement flooded over L hops (each node forwards the first copy it receives, from any "
            "neighbour); each node fuses its L-hop ball with one gain minimising the expected covariance over the "
            "attacks", relays=True, routing="flood"))
