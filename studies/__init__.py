"""Scenarios, studies, results, the public API and the ``cfdesign`` command line.

The public functions of :mod:`studies.api` are re-exported here (imported on first use)::

    import studies
    d = studies.design("my_model.py", mode="tuned")
"""
from __future__ import annotations

_API = ("list_scenarios", "simulate", "design", "feasibility", "study", "report", "filter", "node_filter", "export",
        "Simulation", "FilterRun")
__all__ = list(_API)


def __getattr__(name: str):
    if name in _API:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'studies' has no attribute {name!r}")
