"""Work shared by the processes of a test run: a lock every process on the machine shares, and
a result made once per run whichever xdist worker asks first."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import tempfile
from pathlib import Path


@contextlib.contextmanager
def machine_lock(name: str):
    """An exclusive lock every process on this machine shares (flock on a file in the temp dir):
    the suite's xdist workers, and another run of the suite, take turns inside it."""
    with open(Path(tempfile.gettempdir()) / f"noiselab-tests-{name}.lock", "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def run_once(tmp_path_factory, name: str, make):
    """``make(directory) -> JSON-able`` once per test run, whichever xdist worker asks first; the
    others wait for it and get the same directory and value (the run's shared temp root)."""
    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    d, done = root / f"once-{name}", root / f"once-{name}.json"
    with machine_lock(f"once-{root.name}-{name}"):
        if not done.exists():
            d.mkdir(exist_ok=True)
            done.write_text(json.dumps(make(d)))
    return d, json.loads(done.read_text())
