"""The design options a command designs with: the home of :func:`effective` (a scenario's design defaults merged with
the options given, its attacks overridden by theirs) and :func:`as_mode` (options fitted to one gain rule).

The design (:mod:`studies.consensus_design`), the feasibility map and the memory estimates (:mod:`studies.memory`)
all start from them.
"""
from __future__ import annotations

from dataclasses import replace

import rules
from designer.design import DesignOptions
from designer.validation import InputError

from .scenarios.base import Scenario

__all__ = ["effective", "as_mode", "rule_of"]


def rule_of(options: DesignOptions | None):
    """The gain rule of ``options`` (:func:`rules.get` of its mode; :data:`rules.DEFAULT` when it names none)."""
    return rules.get((options.mode if options is not None else None) or rules.DEFAULT)


def effective(sc: Scenario, options: DesignOptions | None) -> tuple[Scenario, DesignOptions]:
    """The scenario with the options' attack overrides applied, and its design defaults merged with ``options``.

    The scenario's own defaults (``Scenario.design``, a model file's ``DESIGN``) come first;
    every value ``options`` sets replaces them.  On a model that declares ``REGIONS`` the nodes of a rule that may
    carry their regions alone carry them (``carry='region'``) unless ``options`` says ``carry='whole'``.
    """
    if sc.network is None:
        raise InputError(f"scenario {sc.name!r} has no sensor network; the consensus design needs one "
                         "(a model file defines NETWORK)")
    base = sc.design or DesignOptions()
    if any(v is not None for v in base.attack_overrides().values()):
        raise InputError(f"scenario {sc.name!r}: DESIGN must not set dos, fdi, delta or amplitude; declare the "
                         "attacks in ATTACKS")
    opts = base.merged(options)
    rule = rule_of(opts)  # the mode given, else the model's default one, else the package's
    if options is not None:
        rule.check_options(options)  # what the user gave, before the defaults: a value the rule does not take
    # the defaults' values the rule does not take (a model's multipliers of the paper's design, a tabled design's
    # exchange) give way to the rule's own; the mode stays as given (None: the default rule), as the record keeps it
    opts = replace(as_mode(opts, rule.name), mode=opts.mode)
    if opts.carry is None and rule.regional and sc.regions is not None:  # REGIONS: the nodes carry their regions
        opts = replace(opts, carry="region")
    rule.check_options(opts)
    sc.model.check_finite_at(*sc.operating_point)  # every design linearises there: name a sensor that cannot be
    return sc.with_attacks(**opts.attack_overrides()), opts


def as_mode(options: DesignOptions | None, mode: str) -> DesignOptions:
    """``options`` for a design of ``mode`` (a rule that chooses its multipliers drops the paper-mode σ, β, τ; one
    without offline tables the scheduled design's exchange, robustness, bank and tables' kind, the rounds unless it relays, what a
    node carries unless it may carry its region alone)."""
    opts = options or DesignOptions()
    rule = rules.get(mode)
    if not rule.offline_tables:  # the exchange, the links' margin and the bank: a design of tables'
        opts = replace(opts, exchange=None, robustness=None, bank=None, table_kind=None)
    if not rule.takes_rounds:  # the exchange rounds: a design of tables' or of a rule that relays
        opts = replace(opts, rounds=None)
    if not rule.regional:  # a node carrying its region alone: a rule without consensus on estimates
        opts = replace(opts, carry=None)
    if rule.fixed_multipliers:
        return replace(opts, mode=mode)
    return replace(opts, mode=mode, sigma=None, beta=None, tau=None)
