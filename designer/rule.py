"""The gain rule's interface: :class:`GainRule`, the base class of every design mode, and the run-time classes.

A gain rule (``cfdesign design --mode NAME``) is one package ``rules/<name>/`` (:mod:`rules`, the registry that
finds them); its object, a subclass of :class:`GainRule`, declares what a node needs at run time to apply its gains
and answers the code's questions about the rule through its hooks.  This module names no rule: the designer and the
filters take a rule object (``ConsensusDesign.rule``), which the command resolves once from its name
(:func:`rules.get`).

Every rule belongs to one run-time class of :data:`RUNTIMES`:

* ``local`` — the node computes its gains online from what it has: its own measurement,
  the packets it received and their senders' messages;
* ``scheduled`` — gains designed offline and applied with what the node itself observes or
  computes (the step, which neighbour packets arrived, its own estimate);
* ``global`` — the gains need the joint state of the network (e.g. the joint error covariance
  of all nodes and every link's realised packet losses), i.e. a central computer.  Such a rule is
  an **oracle**: a reference of what the structure can reach, not a design to deploy
  (``deployable`` is False).

:data:`FILTER_RUNTIMES` adds ``centralized`` for the filters of a fusion centre, which no node runs.

A rule's metadata (class attributes, checked when the class is defined)
------------------------------------------------------------------------
``name``, ``runtime``, ``needs`` (one plain sentence: what a node needs at run time), ``summary`` (one line: how it
chooses the gains, the command line's help), and its capabilities: ``fixed_multipliers`` (the user gives σ, β and
τ and the rule keeps them: they may break (28)/(29) at the first step), ``offline_tables`` (its design is a set of
tables computed offline and applied online: it chooses what the nodes exchange, the exchange rounds, a robustness
margin and a bank of operating points, and has a stationary certificate), ``joint_covariance`` (its filter carries
the joint error covariance of all nodes: (N n)² numbers per run, not mapped by the feasibility map), ``relays`` (its
packets relay the measurements over L exchange rounds per step), ``regional`` (its nodes may carry their regions
alone, :mod:`designer.regions`).

Its hooks (methods; the base class's answer follows from the capabilities)
--------------------------------------------------------------------------
Options: :meth:`GainRule.check_options`, :meth:`GainRule.check_design`, :meth:`GainRule.check_exchange`,
:meth:`GainRule.design_fields`, :meth:`GainRule.rounds`.  Design: :meth:`GainRule.tables` and
:meth:`GainRule.stationary_tables` (a rule of offline tables), :meth:`GainRule.stationary` (its stationary
certificate), :meth:`GainRule.tradeoff_parts` and :meth:`GainRule.tradeoff` (its accuracy-messages trade-off),
:meth:`GainRule.record_notes` (``schedule.json``'s words on where its gains come from).  Filters:
:meth:`GainRule.batch_filter` (over a batch of Monte Carlo runs), :meth:`GainRule.node_filter` (the filter one node
runs, and the network of them).  Words and costs: :attr:`GainRule.help` (the command line's),
:meth:`GainRule.report_settings` and :meth:`GainRule.report_margins` (the design report's),
:attr:`GainRule.study_label` and :attr:`GainRule.study_description` (``study comparison``'s),
:meth:`GainRule.memory_parts` (the memory estimate's), :meth:`GainRule.payload` (the numbers its packets carry per
step).  Automatic design: :meth:`GainRule.candidates` (the designs ``--mode auto`` tries).  Export:
:meth:`GainRule.c_export` (its node filter's C export, a :class:`designer.export_c.NodeExport`).
"""
from __future__ import annotations

import re
from types import MappingProxyType
from typing import Any, ClassVar, Mapping

import numpy as np

from .validation import InputError

__all__ = ["GainRule", "RUNTIMES", "FILTER_RUNTIMES", "DEPLOYABLE", "runtime_label", "caveat",
           "RULE_NAME", "CARRIES", "EXCHANGES", "ROBUSTNESS", "ROBUSTNESS_MAX", "ROUNDS_MAX", "BANK_MAX", "TABLE_KINDS"]

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
_SHORT = {"local": "computed online at each node", "scheduled": "designed offline, applied with what the node "
          "observes", "global": "an oracle, not deployable", "centralized": "a fusion centre, not a node's filter"}
RULE_NAME = re.compile(r"[a-z][a-z0-9_]*")  # a rule's name: its package's (a Python identifier), its --mode


#: What a node carries (``--carry``): the whole state, or its region and what its measurements need (a rule whose
#: nodes may: GainRule.regional).
CARRIES = ("whole", "region")
EXCHANGES = ("measurements", "predictions")  # what a packet carries (a rule of offline tables): the first its default
#: The default robustness margin δ of a tabled design's link gains (:func:`rules.scheduled.design.link_gains`;
#: ``--robustness``).  With δ = 0 the gains are the MMSE ones for the tables, and they exploit the tables' correlations
#: between neighbours' errors to the last digit (per-link gains of norm 20-90 that cancel between links, conditioning
#: 1e7-1e8 on a range grid): where the state leaves the nominal geometry, those cancellations fail and the network
#: diverges (a 32-node range grid, 1150 m after 100 steps; 20 of 20 runs of a 28-node coordinated-turn model).  δ = 1
#: (each link's difference taken to carry an extra independent error as large as the node's own) removed every
#: divergence we measured and cost at most 5 % of accuracy on the nominal trajectories (README, "Robustness"): an
#: assumption of this design, chosen by those measurements, not by a theorem.
ROBUSTNESS = 1.0
#: The largest margin accepted (beyond it the links are all but ignored: a node alone is the local EKF).
ROBUSTNESS_MAX = 100.0
#: The most exchange rounds per step a design takes.
ROUNDS_MAX = 64
#: The most axes of a tabled design's bank of operating points (3^A - 1 points: 26 at A = 3).
BANK_MAX = 3
#: The kinds of a tabled design's tables (``--table-kind``): each step's own, or the stationary ones at every step
#: (:func:`rules.scheduled.design.own_steps`; unset: chosen by their size).
TABLE_KINDS = ("per-step", "stationary")


def runtime_label(runtime: str) -> str:
    """``"global: an oracle, not deployable"``: a run-time class of :data:`FILTER_RUNTIMES` with its short phrase."""
    if runtime not in FILTER_RUNTIMES:
        raise InputError(f"runtime must be {_listing(FILTER_RUNTIMES)}, got {runtime!r}")
    return f"{runtime}: {_SHORT[runtime]}"


def _listing(names) -> str:
    """``'a', 'b' or 'c'``."""
    quoted = [repr(n) for n in names]
    return quoted[0] if len(quoted) == 1 else ", ".join(quoted[:-1]) + " or " + quoted[-1]


def caveat(record: Mapping) -> str | None:
    """The clause a verdict adds for a rule that is not deployable, from its record (:meth:`GainRule.describe`,
    ``schedule.json``'s ``gain_rule``); None for a deployable rule."""
    if record.get("deployable", True):
        return None
    return (f"mode {record.get('name')} is a {record.get('runtime')} oracle, a reference of what the structure can "
            f"reach, not a deployable design: its gains need {str(record.get('needs', '')).rstrip('.')}")


class GainRule:
    """A gain rule: a design mode, what a node needs at run time to apply its gains, and its hooks.

    A rule is a subclass that sets the metadata below as class attributes (checked when the class is defined) and
    overrides the hooks it answers differently from the base class; its package ``rules/<name>/`` exposes one
    instance as ``RULE`` (:mod:`rules`).  Rules compare equal by class and name, so a design carrying one pickles
    to another process and back.

    Metadata
    --------
    name : str
        The mode's name (``--mode NAME``) and its package's: lower-case letters, digits and ``_``.
    runtime : {'local', 'scheduled', 'global'}
        Its run-time class (:data:`RUNTIMES`).
    needs : str
        One plain sentence: what a node needs at run time to apply the rule.
    summary : str
        One line: how the rule chooses the gains (the command line's help).
    fixed_multipliers : bool
        The user gives σ, β and τ (``--sigma``, ``--beta``, ``--tau``) and the rule keeps them: they may break
        (28)/(29) at the first step, where the design cannot start.  Otherwise the rule chooses them (and ε defaults
        to :func:`designer.tuning.tuned_epsilon`).
    offline_tables : bool
        Its design is a set of tables computed offline (:mod:`rules.scheduled.design`) and applied online by the
        nodes: it chooses what they exchange (``--exchange``), the exchange rounds (``--rounds``), a robustness
        margin (``--robustness``) and a bank of operating points (``--bank``), and has a stationary certificate; its
        gains along one run are not the design (they cannot be replayed).  Otherwise the design is a seeded run of
        the filter.
    joint_covariance : bool
        The filter carries the joint error covariance of all nodes ((N n)² numbers per run); the feasibility map does
        not map it (its gains come from that covariance along a run).
    relays : bool
        Its nodes relay every measurement over L hops per step (``--rounds L``) and fuse the L-hop ball that arrived
        (:mod:`rules.relay.design`); its design has a stationary certificate.
    solves_online : bool
        Its nodes solve an optimisation problem at every step (a convex tuning of their gains): of the filters a node
        runs, the costliest a step; the comparison runs it at its main setting only on a large network
        (:func:`studies.comparison.sweeps_left_out`).
    regional : bool
        Its nodes may carry only their regions' states (``--carry region``, ``ConsensusDesign.carried_regions``,
        :mod:`designer.regions`): it fuses measurements without consensus on estimates, so a node's filter on the
        states its region, its measurements and their dynamics need is its whole-state filter on them.
    """

    name: ClassVar[str]
    runtime: ClassVar[str]
    needs: ClassVar[str]
    summary: ClassVar[str]
    fixed_multipliers: ClassVar[bool] = False
    offline_tables: ClassVar[bool] = False
    joint_covariance: ClassVar[bool] = False
    relays: ClassVar[bool] = False
    regional: ClassVar[bool] = False
    solves_online: ClassVar[bool] = False

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        if "name" in cls.__dict__:  # a concrete rule (an intermediate base may leave its name to subclasses)
            cls.check_metadata()

    @classmethod
    def check_metadata(cls) -> None:
        """Check the class's metadata (:class:`InputError` naming the attribute and what it must be)."""
        name = getattr(cls, "name", None)
        if not isinstance(name, str) or not RULE_NAME.fullmatch(name):
            raise InputError(f"gain rule name must be lower-case letters, digits or '_', starting with a letter (the "
                             f"name of its package rules/<name>/), got {name!r}")
        if getattr(cls, "runtime", None) not in RUNTIMES:
            raise InputError(f"runtime of gain rule {name!r} must be {_listing(RUNTIMES)}, "
                             f"got {getattr(cls, 'runtime', None)!r}")
        for field in ("needs", "summary"):
            if not isinstance(getattr(cls, field, None), str) or not getattr(cls, field).strip():
                raise InputError(f"{field} of gain rule {name!r} must be a non-empty sentence")
        for field in ("fixed_multipliers", "offline_tables", "joint_covariance", "relays", "regional",
                      "solves_online"):
            if not isinstance(getattr(cls, field), bool):
                raise InputError(f"{field} of gain rule {name!r} must be True or False, got {getattr(cls, field)!r}")

    def __setattr__(self, key, value):
        raise AttributeError(f"gain rule {self.name!r} is fixed: its metadata are its class's")

    def __eq__(self, other) -> bool:
        return type(other) is type(self) and other.name == self.name

    def __hash__(self) -> int:
        return hash((type(self).__qualname__, self.name))

    def __repr__(self) -> str:
        return f"<gain rule {self.name!r}>"

    # ------------------------------------------------------------------------------------------ what it is
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
    def help(self) -> str:
        """The command line's line for the rule: ``"name: summary [runtime: in words]"``."""
        return f"{self.name}: {self.summary} [{runtime_label(self.runtime)}]"

    @property
    def study_label(self) -> str:
        """Its filter's name in a study that compares filters (``study comparison``)."""
        return f"consensus EKF ({self.name} design)"

    @property
    def study_description(self) -> str:
        """One line on its filter in a study that compares filters."""
        return f"{'distributed' if self.deployable else 'an oracle'}: {self.summary}"

    @property
    def caveat(self) -> str | None:
        """For a rule that is not deployable, the clause a verdict adds (None for a deployable rule)."""
        return caveat(self.describe())

    def describe(self) -> dict:
        """``schedule.json``'s ``gain_rule``: ``{name, runtime, needs, deployable}``."""
        return {"name": self.name, "runtime": self.runtime, "needs": self.needs, "deployable": self.deployable}

    # ------------------------------------------------------------------------------------------ hooks
    def check_options(self, options) -> None:
        """Refuse what ``options`` (a :class:`designer.design.DesignOptions`) sets that this rule does not take
        (:class:`InputError` naming the option); the options' own ranges are checked when they are made."""
        mode = repr(self.name)
        if options.exchange == "measurements" and not self.offline_tables:
            raise InputError(f"exchange 'measurements' is a design of a rule of offline tables; mode {mode} "
                             "exchanges predictions")
        if options.rounds is not None and options.rounds > 1 and not self.takes_rounds:
            raise InputError(f"rounds > 1 is a design of a rule of offline tables or one that relays; mode {mode} "
                             "exchanges once per step")
        if options.bank and not self.offline_tables:
            raise InputError(f"bank is the operating points of a rule of offline tables; mode {mode} has none")
        if options.table_kind is not None and not self.offline_tables:
            raise InputError(f"table_kind is the kind of a rule's offline tables; mode {mode} has none")
        if options.robustness is not None and not self.offline_tables:
            raise InputError(f"robustness is a margin of the link gains of a rule of offline tables; mode {mode} "
                             "has none")
        if options.carry == "region" and not self.regional:
            raise InputError(f"carry 'region': mode {mode} carries the whole state at every node (a node carries its "
                             "region alone in a rule that fuses its ball's measurements without consensus on "
                             "estimates: one that relays)")
        if not self.fixed_multipliers:
            for name in ("sigma", "beta", "tau"):
                if getattr(options, name) is not None:
                    raise InputError(f"{name} is chosen by the design in mode {mode}; do not give --{name}")

    def check_design(self, design) -> None:
        """Refuse a :class:`designer.design.ConsensusDesign` whose rule-dependent fields this rule does not take
        (:class:`InputError` naming the field and its range)."""
        mode = repr(self.name)
        self.check_exchange(design)
        rob = float(design.robustness)
        if not (0.0 <= rob <= ROBUSTNESS_MAX) or (rob and not self.offline_tables):
            raise InputError(f"robustness must lie in [0, {ROBUSTNESS_MAX:g}] in a rule of offline tables (0 in "
                             f"the others), got {design.robustness!r} in mode {mode}")
        if isinstance(design.rounds, bool) or not isinstance(design.rounds, (int, np.integer)) or not (
                1 <= design.rounds <= ROUNDS_MAX) or (design.rounds > 1 and not self.takes_rounds):
            raise InputError(f"rounds must be an integer in [1, {ROUNDS_MAX}] in a rule of offline tables or one "
                             f"that relays (1 in the others), got {design.rounds!r} in mode {mode}")
        if isinstance(design.bank, bool) or not isinstance(design.bank, (int, np.integer)) or not (
                0 <= design.bank <= BANK_MAX) or (design.bank and not self.offline_tables):
            raise InputError(f"bank must be an integer in [0, {BANK_MAX}] in a rule of offline tables (0 in the "
                             f"others), got {design.bank!r} in mode {mode}")
        if design.table_kind is not None and (design.table_kind not in TABLE_KINDS or not self.offline_tables):
            raise InputError(f"table_kind must be one of {', '.join(map(repr, TABLE_KINDS))} in a rule of offline "
                             f"tables (None: chosen by their size; None in the others), got {design.table_kind!r} "
                             f"in mode {mode}")

    def check_exchange(self, design) -> None:
        """Refuse a design whose packets carry what this rule does not exchange (``exchange``, ``gate``): its
        neighbours' predictions, and with offline tables their measurements too (:data:`EXCHANGES`)."""
        if design.exchange not in EXCHANGES or (design.exchange == "measurements" and not self.offline_tables):
            raise InputError(f"exchange must be 'predictions', or 'measurements' in a rule of offline tables, got "
                             f"{design.exchange!r} in mode {self.name!r}")

    def design_fields(self, options) -> dict[str, Any]:
        """The fields of a :class:`designer.design.ConsensusDesign` that follow from this rule and ``options``:
        what a packet carries (``exchange``), the links' margin (``robustness``), the bank's axes (``bank``) and the
        tables' kind (``table_kind``)."""
        if not self.offline_tables:
            return {"exchange": options.exchange or "predictions", "robustness": 0.0, "bank": 0, "table_kind": None}
        return {"exchange": options.exchange or EXCHANGES[0],
                "robustness": ROBUSTNESS if options.robustness is None else float(options.robustness),
                "bank": 0 if options.bank is None else int(options.bank), "table_kind": options.table_kind}

    def rounds(self, network, rounds: int | None = None) -> int:
        """The exchange rounds per step of this rule's design on ``network``: ``rounds`` when given, else the rule's
        default (1 here; a rule that relays: its hops)."""
        return 1 if rounds is None else int(rounds)

    def candidates(self, network) -> list[dict[str, Any]]:
        """The designs of this rule an automatic design (``--mode auto``, :mod:`studies.auto`) tries on ``network``:
        one dict of :class:`designer.design.DesignOptions` fields per design (e.g. ``{"rounds": 2}``; ``{}`` the rule
        with its defaults).  Here, a deployable rule's one design; an oracle (``global``) none, since it is no design
        to deploy."""
        return [{}] if self.deployable else []

    def payload(self, model, network, design) -> int:
        """The numbers its nodes send over the network per step with ``design`` (every packet attempted, as the
        messages are counted: a packet lost to DoS was sent).  Here, the consensus filter of (7): one packet per
        directed channel and round carrying the sender's prediction (n numbers) and, for a rule that does not
        design its gains offline, its predicted bound Φ_{j,k+1|k} (its n (n + 1) / 2 distinct entries: (27) uses the
        neighbours'); with offline tables and ``exchange='measurements'``, the first round carries the sender's
        measurement too."""
        n, rounds = int(model.n_x), int(design.rounds)
        adj = np.asarray(network.adjacency, dtype=bool)
        per_packet = n if self.offline_tables else n + n * (n + 1) // 2
        total = int(adj.sum()) * per_packet * rounds
        if self.offline_tables and design.exchange == "measurements":
            total += int(adj.sum(axis=0) @ np.asarray(model.sensor_dims))  # sender j's z_j on each of its channels
        return total

    def batch_filter(self):
        """Its filter over a batch of Monte Carlo runs: a :class:`filters.consensus_batch.NodeRule` (a prediction and
        an update each node applies on its own, run by :func:`filters.consensus_batch.run_consensus_batch`'s loop)
        or a function ``run(model, network, z, design, *, inputs, attacks, x0, phi0, predictions=True)`` returning a
        :class:`filters.result.FilterResult` (``detail``: its :class:`filters.consensus_batch.ConsensusBatchResult`,
        :func:`filters.consensus_batch.consensus_result`); without ``predictions`` it may leave the predictions' Φ
        and the gains out of the ``detail`` (None), never Φ, the estimates or their validity (a function that takes no
        ``predictions`` keeps them)."""
        raise InputError(f"no filter applies gain rule {self.name!r} (its GainRule.batch_filter gives one)")

    def record_notes(self) -> dict[str, str]:
        """``schedule.json``'s words on where the design's gains and bound come from (``trajectory``, ``replay``,
        ...): here, a seeded run of the filter."""
        return {"trajectory": "seeded simulated run of the scenario: truth and measurements from "
                              "SeedSequence(seed).spawn(2)[0], channel attacks from spawn(2)[1]; gains and bounds "
                              "along each node's own estimates and the realised DoS pattern",
                "replay": "a filter replaying this schedule on another run keeps the gains but not the guarantee: "
                          "the bound holds for the linearisation points and DoS pattern it was computed along"}

    def tables(self, model, network, design, steps: int, *, x0, inputs, stationary: bool = True):
        """Its offline tables for ``steps`` steps along the nominal trajectory from ``x0`` with the known ``inputs``
        (a rule of ``offline_tables``); ``stationary``: with the tables beyond the horizon."""
        raise InputError(f"gain rule {self.name!r} has no offline tables")

    def table_arrays(self, tables) -> dict:
        """Its offline tables (:meth:`tables`' result, a design's ``tables``) as the arrays ``schedule.npz`` records
        (``table_<name>``), which :meth:`recorded_tables` reads back (a rule of ``offline_tables``)."""
        raise InputError(f"gain rule {self.name!r} has no offline tables")

    def recorded_tables(self, model, network, design, arrays: Mapping, meta: Mapping):
        """Its offline tables as a design directory recorded them (``schedule.npz``'s arrays ``arrays`` and
        ``schedule.json``'s record ``meta``, read as data), checked against ``model``, ``network`` and ``design``
        (InputError naming what does not fit), for a filter, a node filter or an export to use instead of designing
        them again (a rule of ``offline_tables``)."""
        raise InputError(f"gain rule {self.name!r} has no offline tables")

    def stationary_tables(self, model, network, design, horizon, *, inputs) -> dict:
        """The tables beyond the horizon of ``horizon`` (its tables over the horizon, computed without them)."""
        raise InputError(f"gain rule {self.name!r} has no offline tables")

    def stationary(self, model, network, design, *, x, u, lmi: bool = True):
        """Its design's stationary certificate at the operating point ``x`` (input ``u``) and where it is computed,
        in words: ``(certificate, where)``, the certificate a :class:`designer.stationary.StationaryCertificate`;
        None for a rule without one (``stationary_certificate`` False).  ``lmi`` False: the fixed point without
        the LMI that confirms it (its ``lmi`` None: a screening, what the automatic map ranks candidates by before
        it confirms the best)."""
        return None

    def tradeoff_parts(self, model, network, design, steps: int, *, x, u, inputs_of, record):
        """What its accuracy-messages trade-off needs besides the design's own run, computed beside that run
        (``inputs_of(k)``: the known inputs of ``k`` steps; ``record``: its stationary record); None: it has none."""
        return None

    def tradeoff(self, network, n_x: int, design, steps: int, parts) -> dict | None:
        """``schedule.json``'s ``rounds_tradeoff`` from the design (with its tables) and :meth:`tradeoff_parts`'s
        result; None: no trade-off."""
        return None

    def report_settings(self, meta: Mapping, fmt) -> list[str]:
        """The design report's paragraphs on how this rule chose the gains (markdown lines, under "Design
        settings"), from ``schedule.json``'s record ``meta`` (a file from elsewhere: read it as data); ``fmt`` is
        the report's formatting (``fmt.fmt_num(v)``, ``fmt.md_escape(text)``: :mod:`studies.reports.text`)."""
        return []

    def report_margins(self, meta: Mapping) -> list[str]:
        """The design report's sentence on what the margins of (28)-(29) mean for this rule (markdown lines)."""
        return []

    def memory_parts(self, network, n_x: int, rows: int, steps: int) -> list[tuple[str, float, str, str]]:
        """What its filter (and its design's offline tables, for a rule that has them) holds beyond the consensus
        filter's arrays when it runs ``rows`` runs of ``steps`` steps at once on ``network`` (a
        :class:`designer.network.SensorNetwork`) of ``n_x`` states: ``(what, bytes, sizes in words, how to need
        less)`` per part (the memory estimate every command checks before computing, :mod:`studies.memory`)."""
        return []

    @property
    def has_node_filter(self) -> bool:
        """Whether a node can run this rule's designs on its own (:meth:`node_filter` gives its classes)."""
        try:
            self.node_filter()
        except InputError:
            return False
        return True

    def node_filter(self) -> tuple[type, type]:
        """The filter one node runs for this rule's designs, and the network of them: ``(node, network)`` classes,
        ``node(model, network, design, i, *, x0, P0)`` with ``step(z, received, u)`` and ``network(model, network,
        design, *, x0, P0)`` with ``step`` and ``run`` (:mod:`filters.node`)."""
        if not self.deployable:
            raise InputError(f"gain rule {self.name!r} has no node filter: it is an oracle, its gains need the joint "
                             "state of the network, which no node has (a reference, not a design to deploy)")
        raise InputError(f"gain rule {self.name!r} has no node filter yet; its filter runs in the studies and in "
                         "cfdesign filter")

    @property
    def exports_c(self) -> bool:
        """Whether its node filter is exported as C (:meth:`c_export` gives its export)."""
        try:
            self.c_export()
        except InputError:
            return False
        return True

    def c_export(self):
        """Its node filter's C export (``cfdesign export``): a :class:`designer.export_c.NodeExport`, imported when
        asked; :class:`InputError` saying why the rule has none (``gain rule NAME cannot be exported to C: why``)."""
        why = ("an oracle: its gains need the network's joint state" if not self.deployable else
               "its node filter has no C export (its GainRule.c_export gives one)")
        raise InputError(f"gain rule {self.name!r} cannot be exported to C: {why}")
