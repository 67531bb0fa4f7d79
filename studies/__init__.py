"""Scenarios, studies, results and the ``cfdesign`` command line."""
