"""The test session's compiled-kernel cache: never the user's.

Every test process (and every command a test starts, which inherits the environment)
compiles into ``$CFDESIGN_TEST_CACHE_DIR`` if set — a developer may keep one between
sessions so that the numba kernels compile once — or else into a fresh directory
removed at the end of the session (CI: a fresh machine compiles cold anyway).  Set at
import, before any test module imports the kernels.
"""
from __future__ import annotations

import os
import shutil
import tempfile

_OWN = None
if os.environ.get("CFDESIGN_TEST_CACHE_DIR"):
    os.environ["CFDESIGN_CACHE_DIR"] = os.environ["CFDESIGN_TEST_CACHE_DIR"]
else:
    _OWN = os.environ["CFDESIGN_CACHE_DIR"] = tempfile.mkdtemp(prefix="cfdesign-test-cache-")


def pytest_sessionfinish(session, exitstatus):
    if _OWN is not None:
        shutil.rmtree(_OWN, ignore_errors=True)
