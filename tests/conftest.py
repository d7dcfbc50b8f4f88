"""Fixtures shared by the test modules."""

from __future__ import annotations

import sys

import pytest

from livechild import Child


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
