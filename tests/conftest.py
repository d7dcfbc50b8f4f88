"""Fixtures shared by the test modules."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

from service import one_blas_thread

# One BLAS thread per process (service.one_blas_thread says why), set before numpy is imported and
# before xdist starts its workers, which inherit the environment, as the tests' subprocesses do.
one_blas_thread()

import pytest  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

from livechild import Child  # noqa: E402

# Hypothesis measures time in two checks, which would make a property test depend on the machine's
# speed: the deadline per example and the "too slow" health check on data generation. Both are off
# for every property test of the suite (a test's own @settings inherit this profile). Examples are
# drawn from a fixed seed (derandomize) and no example database is kept, so every run, here and in
# CI, tries the same inputs: a failure is reproducible and a pass is not luck of the draw.
settings.register_profile("noiselab", deadline=None, suppress_health_check=[HealthCheck.too_slow],
                          derandomize=True, database=None)
settings.load_profile("noiselab")


@pytest.fixture
def spawn(request):
    """``spawn(label, *cli_args)`` starts ``python -m service.cli ...``; ``spawn(label, script, ...,
    script=True)`` a helper script. The requesting module's ``T_EVENT`` (default 30 s) bounds each
    wait. Every child is killed at teardown."""
    t_event = getattr(request.module, "T_EVENT", 30.0)
    children: list[Child] = []

    def start(label: str, *args: str, script: bool = False) -> Child:
        cmd = [sys.executable, *args] if script else [sys.executable, "-m", "service.cli", *args]
        child = Child(cmd, label, t_event)
        children.append(child)
        return child

    yield start
    for child in children:
        child.kill()


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


@pytest.fixture
def default_endpoint():
    """For a test that must bind the default endpoint tcp/127.0.0.1:7447: such tests take turns
    (request it before ``spawn``, so that the children are killed before the turn ends)."""
    with machine_lock("port-7447"):
        yield


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


# -- bad input through the CLI, in this process ---------------------------------------------------
def cli_in_process(capsys, *argv) -> tuple[int, str, str]:
    """``noiselab ARGV`` in this process: (exit code, stdout, stderr). argparse's own errors exit
    through SystemExit; anything else raised is a traceback and fails the test."""
    from service.cli import main
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, err


def assert_bad(result, *parts: str) -> str:
    """Exit 2 and one line on stderr, ``noiselab: ...``, no traceback, holding every one of
    ``parts``; the line is returned."""
    rc, out, err = result
    assert rc == 2, (rc, out, err[-3000:])
    lines = err.splitlines()
    assert len(lines) == 1 and err.endswith("\n") and lines[0].startswith("noiselab: "), err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    for part in parts:
        assert part in lines[0], (part, lines[0])
    return lines[0]


# -- the README's main command ---------------------------------------------------------------------------------
ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def readme_blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README, flags=re.S)


def main_command_steps() -> list[str]:
    """The noiselab steps of the README's main command (its venv/pip steps are what CI itself runs)."""
    first = readme_blocks("sh")[0].strip()
    steps = [s.strip() for s in first.split("&&")]
    return [s.replace(".venv/bin/noiselab", "noiselab") for s in steps if ".venv/bin/noiselab" in s]


def run_noiselab(cmd: str, cwd: Path):
    """A README line ``noiselab ...`` run as ``python -m service.cli ...`` in ``cwd``, its words
    split as a POSIX shell splits them (quotes keep a field path's ``*`` from the shell's glob)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "service.cli", *shlex.split(cmd)[1:]], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=900)


def readme_main_command(tmp_path_factory):
    """The README's main command (``noiselab demo`` with its defaults, about 90 s), run once per
    test run in one directory: (the directory, [{cmd, returncode, stdout, stderr}] per step, up to
    the first that fails). test_readme checks the run as a user sees it, test_demo what it wrote."""
    def make(d: Path) -> list[dict]:
        (d / "service").symlink_to(ROOT / "service")       # README paths like service/scenarios/...
        runs = []
        for cmd in main_command_steps():
            res = run_noiselab(cmd, d)
            runs.append({"cmd": cmd, "returncode": res.returncode, "stdout": res.stdout, "stderr": res.stderr})
            if res.returncode:
                break
        return runs

    return run_once(tmp_path_factory, "readme-main", make)
