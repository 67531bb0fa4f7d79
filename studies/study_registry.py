"""The studies by name, and a study's words for its report: :data:`STUDIES` (each study's module, imported on
first use), :func:`get_study`, :class:`StudyText` and :func:`study_text`.

A study is a :class:`studies.pipeline.Study` in its own module; this registry names the module without importing
it, so that the reports (:mod:`studies.reports.study`) find a study's words from its name in ``results.json``.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Any, Mapping

from designer.validation import InputError

__all__ = ["STUDIES", "StudyText", "get_study", "study_text"]

# study name -> the module that defines its STUDY (imported on first use)
STUDIES: dict[str, str] = {
    "rrp-deception": "studies.rrp_deception",
    "encrypted-switching": "studies.encrypted_switching",
    "binary-multi-attack": "studies.binary_multi_attack",
    "consensus-robot": "studies.consensus_robot",
    "fdi-four-tank": "studies.fdi_four_tank",
    "comparison": "studies.comparison",
}


@dataclass(frozen=True)
class StudyText:
    """The plain-language description of one study, for its report.

    Parameters
    ----------
    title : str
        One line: what is estimated, under what.
    summary : str
        What the study compares and the question it answers (Markdown text).
    filters : mapping of str to str
        A one-line description of each filter the study runs.
    attacks : str
        The attacks (or channel faults) the filters face.
    attack_params : tuple of str
        Scenario parameters that set the attacks (shown with their values).
    accuracy : tuple of (metric, label)
        Accuracy metrics of ``results["filters"]`` in order of importance (lower is better).
    references : tuple of str
        Filters that are benchmarks, not options (e.g. they see attack-free data): shown
        everywhere but left out of "which filter to pick".
    figures : mapping of str to str
        Caption of each figure file.
    paper : str
        The source paper.
    """

    title: str
    summary: str
    filters: Mapping[str, str] = field(default_factory=dict)
    attacks: str = ""
    attack_params: tuple[str, ...] = ()
    accuracy: tuple[tuple[str, str], ...] = ()
    references: tuple[str, ...] = ()
    figures: Mapping[str, str] = field(default_factory=dict)
    paper: str = ""


def get_study(name: str) -> Any:
    """The configuration of study ``name``: the :class:`studies.pipeline.Study` its module defines (``STUDY``)."""
    if name not in STUDIES:
        raise InputError(f"unknown study {name!r}; studies: {', '.join(STUDIES)}")
    return importlib.import_module(STUDIES[name]).STUDY


def study_text(name) -> StudyText | None:
    """The report texts of study ``name`` (None for an unknown name)."""
    if not isinstance(name, str) or name not in STUDIES:
        return None
    return get_study(name).text
