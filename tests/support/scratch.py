"""Folders the tests' apps keep their job stores in, all under one temporary folder of the test
process that is removed when the process ends (a job store holds request files and a database; a
test run leaves none of them behind in the system's temporary folder).

>>> from pathlib import Path
>>> a, b = job_store_dir(), job_store_dir()
>>> a != b and Path(a).parent == Path(b).parent and Path(a).is_dir()
True
"""

from __future__ import annotations

import tempfile

_RUN_ROOT = tempfile.TemporaryDirectory(prefix="svrnet-test-")   # removed at interpreter exit


def job_store_dir() -> str:
    """A fresh, empty folder for one app's job store, inside the test process's own temporary folder."""
    return tempfile.mkdtemp(prefix="store-", dir=_RUN_ROOT.name)
