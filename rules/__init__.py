"""The gain rules, one package each: ``rules/<name>/`` is the rule called ``name``, and this module finds them.

A rule's package holds its :class:`designer.rule.GainRule` subclass and exposes its one instance as ``RULE`` in its
``__init__.py``, which stays small (its metadata and hooks; what a hook needs it imports when called), so that
listing the rules costs little.  The registry finds the packages without importing them (:func:`names`: the
sub-packages of this package's path); :func:`get` imports the one asked for.  The command resolves a mode's name
once, here, and the design carries the rule object (``ConsensusDesign.rule``): the code outside ``rules/`` asks the
object, never compares a name.

Adding a rule
-------------
One package: ``rules/<name>/__init__.py`` with ``RULE = Mine()``, ``class Mine(GainRule)`` declaring ``name`` (the
package's name), ``runtime``, ``needs``, ``summary``, its capabilities, and the hooks it answers (its filter:
:meth:`designer.rule.GainRule.batch_filter`; its node filter: :meth:`designer.rule.GainRule.node_filter`).  A rule
kept outside this repository lives in a folder of rule packages named by :func:`add_path`, or, for every
``cfdesign`` process (its workers too), by the environment variable ``CFDESIGN_RULE_PATH`` (folders separated by
``os.pathsep``); its package is imported as ``rules.<name>``, like the built-in ones.
"""
from __future__ import annotations

import importlib
import os
import pkgutil
import sys
from pathlib import Path

from designer.rule import RULE_NAME, GainRule
from designer.validation import InputError

__all__ = ["DEFAULT", "PUBLISHED", "RESERVED", "ENV_PATH", "names", "get", "find", "all_rules", "choices", "add_path",
           "remove_path", "paths"]

#: The rule a command that runs one rule's design takes when none is named (``--mode`` left out of ``feasibility``
#: and ``study``); ``cfdesign design`` without ``--mode`` runs the automatic design instead (:mod:`studies.auto`).
DEFAULT = "paper"
#: The seed paper's own rule (seed 003): the design its reproduction (``study consensus-robot``) compares against, and
#: the consensus filter that with σ = β = τ = 0 and no neighbours is the EKF (the studies' local and centralized EKFs).
PUBLISHED = "paper"
#: The environment variable naming folders of further rule packages (``os.pathsep``-separated).
ENV_PATH = "CFDESIGN_RULE_PATH"
_ORDER = ("paper", "tuned", "mse", "scheduled", "relay", "flood")  # the built-in rules, as the help lists them


def _env_paths() -> list[str]:
    return [str(Path(p).resolve()) for p in os.environ.get(ENV_PATH, "").split(os.pathsep) if p.strip()]


for _p in _env_paths():
    if _p not in __path__:
        __path__.append(_p)


def paths() -> tuple[str, ...]:
    """The folders searched for rule packages: this package's own first, then those added."""
    return tuple(__path__)


def add_path(folder) -> None:
    """Search ``folder`` for rule packages too (after this package's own); an existing folder is required."""
    p = Path(folder)
    if not p.is_dir():
        raise InputError(f"rule path must be an existing folder of rule packages, got {str(folder)!r}")
    p = str(p.resolve())
    if p not in __path__:
        __path__.append(p)


def remove_path(folder) -> None:
    """Stop searching ``folder`` (added by :func:`add_path`); the rules imported from it are forgotten."""
    p = str(Path(folder).resolve())
    if p in __path__[1:]:
        __path__.remove(p)
    for key, module in list(sys.modules.items()):
        if key.startswith(__name__ + ".") and str(getattr(module, "__file__", "") or "").startswith(p + os.sep):
            del sys.modules[key]


#: Names of ``--mode`` that are not gain rules (a package of that name is not a rule): ``auto``, the automatic design
#: that chooses among the rules (:mod:`studies.auto`).
RESERVED = ("auto",)


def names() -> tuple[str, ...]:
    """The rules' names, found without importing them: the built-in rules in their order, then the others by name."""
    found = {m.name for m in pkgutil.iter_modules(__path__) if m.ispkg and not m.name.startswith("_")
             and m.name not in RESERVED}
    return tuple(n for n in _ORDER if n in found) + tuple(sorted(found - set(_ORDER)))


def choices() -> str:
    """The rules' names as an error message lists them: ``'paper', 'tuned' or 'mse'``."""
    quoted = [repr(n) for n in names()]
    return quoted[0] if len(quoted) == 1 else ", ".join(quoted[:-1]) + " or " + quoted[-1]


def get(name, param: str = "mode") -> GainRule:
    """The rule called ``name`` (its package imported); :class:`InputError` naming ``param`` and the rules otherwise."""
    module = sys.modules.get(f"{__name__}.{name}") if isinstance(name, str) and RULE_NAME.fullmatch(name) else None
    if module is None:
        if not isinstance(name, str) or name not in names():
            raise InputError(f"{param} must be {choices()}, got {name!r}")
        module = importlib.import_module(f"{__name__}.{name}")
    rule = getattr(module, "RULE", None)
    if not isinstance(rule, GainRule) or rule.name != name:
        raise InputError(f"rule package {module.__name__!r} must define RULE, a GainRule named {name!r}, got "
                         f"{rule!r}")
    return rule


def find(name) -> GainRule | None:
    """The rule called ``name``, or None when no rule package has that name (a name read from a file, as data)."""
    return get(name) if isinstance(name, str) and name in names() else None


def all_rules() -> dict[str, GainRule]:
    """Every rule by name, in :func:`names`' order (each package imported)."""
    return {n: get(n) for n in names()}
