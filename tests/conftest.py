"""The test session's compiled-kernel cache: never the user's.

Every test process (and every command a test starts, which inherits the environment)
compiles into ``$CFDESIGN_TEST_CACHE_DIR`` if set — a developer may keep one between
sessions so that the numba kernels compile once — or else into a fresh directory
removed at the end of the session (CI: a fresh machine compiles cold anyway).  With
pytest-xdist (``-n 2``) the worker processes share the directory their controller made
(they inherit its environment), so a kernel compiles once per session; the controller,
which ends after its workers, removes it.  Set at import, before any test module imports
the kernels.
"""
from __future__ import annotations

import os
import shutil
import tempfile

_SHARED = "CFDESIGN_TEST_SESSION_CACHE"  # the controller's directory, seen by its xdist workers
_OWN = None
if os.environ.get("CFDESIGN_TEST_CACHE_DIR"):
    os.environ["CFDESIGN_CACHE_DIR"] = os.environ["CFDESIGN_TEST_CACHE_DIR"]
elif os.environ.get("PYTEST_XDIST_WORKER") and os.environ.get(_SHARED):
    os.environ["CFDESIGN_CACHE_DIR"] = os.environ[_SHARED]
else:
    _OWN = os.environ["CFDESIGN_CACHE_DIR"] = os.environ[_SHARED] = tempfile.mkdtemp(prefix="cfdesign-test-cache-")


def pytest_sessionfinish(session, exitstatus):
    if _OWN is not None:
        shutil.rmtree(_OWN, ignore_errors=True)
