"""The command line that computes a result again, recorded with the result.

``results.json`` (a study), ``schedule.json`` (a design) and ``feasibility.json`` (a map)
record ``invocation``: ``{"argv": [...], "note": ...}``, the ``cfdesign`` arguments (all but
``--out``) that give the same numbers, built from what the computation was given, whether
it came from the command line or from :mod:`studies.api`:

* what it ran on: a built-in scenario name or the model file's absolute path, and
  ``--set NAME=VALUE`` for every scenario parameter not at its default (a built-in's) or
  for every parameter (a model file's ``SPEC``, whose defaults live in the file);
* every design option that was set (``--mode``, ``--beta``, ``--amplitude``, ...);
* the sizes and seeds that were used (``--runs``, ``--particles``, ``--seed``, ``--steps``);
* a study's own options that differ from its defaults (``--engine``, ``--schedule``, else
  ``--set NAME=VALUE``); a map's ``--grid`` specifications as given.

Nothing else determines the numbers: where the chunks ran (``--workers``, ``--dask``) and on how many
threads (``threads``) do not, and are left out, so that two computations with the same numbers
record the same line.  An in-memory model
has no command line: ``argv`` is None and ``note`` says why.  Every report shows the line
(:func:`command_text`).
"""
from __future__ import annotations

import json
import shlex
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["study_invocation", "design_invocation", "feasibility_invocation", "command_text", "IN_MEMORY"]

IN_MEMORY = ("it ran on an in-memory model (a Model or Scenario built in Python), which no command line can name: "
             "run the design script again, or write the model to a model file")
_DESIGN_FLAGS = {"mode": "--mode", "epsilon": "--epsilon", "sigma": "--sigma", "beta": "--beta", "tau": "--tau",
                 "dos": "--dos", "fdi": "--fdi", "delta": "--delta", "amplitude": "--amplitude",
                 "u_scale": "--u-scale", "v_scale": "--v-scale", "linearization": "--linearization",
                 "radius": "--radius", "gate": "--gate", "exchange": "--exchange",
                 "robustness": "--robustness", "rounds": "--rounds", "bank": "--bank", "table_kind": "--table-kind",
                 "carry": "--carry"}
_INTEGER_FLAGS = ("rounds", "bank")  # the design options the command line reads as integers
_STUDY_FLAGS = {"engine": "--engine", "schedule": "--schedule"}
# a study's own options that say where or how wide it computes, not what: like --workers, left out of the line
_NOT_NUMBERS = ("threads",)


def _plain(v):
    """``v`` as JSON data (arrays and tuples as lists)."""
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.integer, np.floating, np.bool_)):
        return v.item()
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, Mapping):
        return {str(k): _plain(x) for k, x in v.items()}
    return v


def _text(v) -> str:
    """A value as the command line reads it back: ``--set`` (JSON, a choice as its text, a bool as true/false),
    a scale (JSON or ``prior``) or a number (its shortest exact repr)."""
    v = _plain(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return v
    if isinstance(v, float):
        return repr(v)
    return json.dumps(v, separators=(",", ":"))


def _target(sc) -> tuple[str, list[str]] | None:
    """The scenario's name or model file and its ``--set`` arguments; None for an in-memory scenario."""
    from .scenarios import SCENARIOS

    source = getattr(sc, "source", None)
    if not isinstance(source, str):
        return None
    spec = SCENARIOS.get(source)
    params = {p.name: p for p in spec.params} if spec is not None else None
    sets = []
    for name, value in (sc.params or {}).items():
        if params is not None:
            if name not in params:
                return None  # not a parameter --set can give: not what the name builds
            p = params[name]
            if _plain(p.validate(value)) == _plain(p.validate(p.default)):
                continue
        sets.append(f"{name}={_text(value)}")
    return source, sets


def _design_args(options) -> list[str]:
    args: list[str] = []
    if options is None:
        return args
    for key, value in options.as_dict().items():
        if value is None:
            continue
        flag = _DESIGN_FLAGS[key]
        if key == "v_scale" and isinstance(value, Mapping):
            for sensor, scale in value.items():
                args += [flag, _text(scale) if sensor == "*" else f"{sensor}={_text(scale)}"]
        elif isinstance(value, (int, np.integer)) and not isinstance(value, bool) and key in _INTEGER_FLAGS:
            args += [flag, str(int(value))]  # an integer option: click reads '2', not '2.0'
        elif isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
            args += [flag, repr(float(value)) if key not in ("u_scale", "v_scale") else _text(value)]
        else:
            args += [flag, _text(value)]
    return args


def _sets(sets: Sequence[str]) -> list[str]:
    return [a for s in sets for a in ("--set", s)]


def _record(argv: list[str] | None, note: str | None = None) -> dict:
    return {"argv": argv, "note": note}


def study_invocation(study, scenarios: Sequence, *, runs: Sequence[int], particles: int | None, seed: int,
                     design, options: Mapping[str, Any]) -> dict:
    """``invocation`` of a study on the built ``scenarios`` (before any attack override) with the runs each
    used, the particles, the seed, the design options and the study's own ``options`` (all of them)."""
    targets, sets = [], []
    for sc in scenarios:
        t = _target(sc)
        if t is None:
            return _record(None, IN_MEMORY)
        targets.append(t[0])
        sets += [s for s in t[1] if s not in sets]
    names = [s.split("=", 1)[0] for s in sets]
    if len(set(names)) != len(names):
        return _record(None, "its scenarios set the same parameter to different values, which one --set cannot say")
    argv = ["cfdesign", "study", study.name, *targets]
    if len(set(runs)) == 1:
        argv += ["--runs", str(int(runs[0]))]
    if particles is not None:
        argv += ["--particles", str(int(particles))]
    argv += ["--seed", str(int(seed)), *_design_args(design)]
    own = []
    for key, value in options.items():
        if key in _NOT_NUMBERS or _plain(value) == _plain(study.options.get(key)):
            continue
        if key == "schedule" and value is not None:
            value = str(Path(value).resolve())
        if key in _STUDY_FLAGS and value is not None:
            argv += [_STUDY_FLAGS[key], _text(value)]
        else:
            own.append(f"{key}={json.dumps(_plain(value), separators=(',', ':'))}")
    return _record(argv + _sets(own) + _sets(sets))


def design_invocation(sc, options, *, steps: int | None, seed: int) -> dict:
    """``invocation`` of ``cfdesign design`` on ``sc`` (as given, before its design defaults and attack overrides)
    with the given ``options``, ``steps`` (None: the scenario's) and ``seed``."""
    t = _target(sc)
    if t is None:
        return _record(None, IN_MEMORY)
    argv = ["cfdesign", "design", t[0], *_design_args(options)]
    if steps is not None:
        argv += ["--steps", str(int(steps))]
    return _record(argv + ["--seed", str(int(seed))] + _sets(t[1]))


def feasibility_invocation(sc, grids: Sequence[str], options) -> dict:
    """``invocation`` of ``cfdesign feasibility`` on ``sc`` over the ``grids`` (``NAME=START:STOP:COUNT`` as
    given) with the given ``options``."""
    t = _target(sc)
    if t is None:
        return _record(None, IN_MEMORY)
    argv = ["cfdesign", "feasibility", t[0], *[a for g in grids for a in ("--grid", str(g).strip())]]
    return _record(argv + _design_args(options) + _sets(t[1]))


def command_text(invocation, out: str = "DIR") -> str | None:
    """The shell command of a recorded ``invocation`` writing into ``out`` (quoted for a POSIX shell), or None
    when none was recorded or none can be."""
    if not isinstance(invocation, Mapping):
        return None
    argv = invocation.get("argv")
    if not isinstance(argv, list) or not argv or not all(isinstance(a, str) for a in argv):
        return None
    return shlex.join([*argv, "--out", out])
