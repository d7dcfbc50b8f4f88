"""Fixtures shared by the test modules (their helpers are in tests/helpers/)."""

from __future__ import annotations

import sys

from noiselab import one_blas_thread

# One BLAS thread per process (noiselab.one_blas_thread says why), set before numpy is imported and
# before xdist starts its workers, which inherit the environment, as the tests' subprocesses do.
one_blas_thread()

import pytest  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

from helpers.once import machine_lock  # noqa: E402
from helpers.processes import Child  # noqa: E402

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
    """``spawn(label, *cli_args)`` starts ``python -m noiselab.cli ...``; ``spawn(label, script, ...,
    script=True)`` a helper script. The requesting module's ``T_EVENT`` (default 30 s) bounds each
    wait. Every child is killed at teardown."""
    t_event = getattr(request.module, "T_EVENT", 30.0)
    children: list[Child] = []

    def start(label: str, *args: str, script: bool = False) -> Child:
        cmd = [sys.executable, *args] if script else [sys.executable, "-m", "noiselab.cli", *args]
        child = Child(cmd, label, t_event)
        children.append(child)
        return child

    yield start
    for child in children:
        child.kill()


@pytest.fixture
def default_endpoint():
    """For a test that must bind the default endpoint tcp/127.0.0.1:7447: such tests take turns
    (request it before ``spawn``, so that the children are killed before the turn ends)."""
    with machine_lock("port-7447"):
        yield
