"""Stopping a long-running command cleanly: SIGINT (Ctrl-C) and SIGTERM set an event the nodes
wait on, so a recorder finishes its file and an analyzer writes its report instead of dying."""

from __future__ import annotations

import signal
import threading


def stop_on_signals() -> threading.Event:
    """SIGINT/SIGTERM set the returned event (nodes finish cleanly instead of dying). Call it from
    the main thread (Python runs signal handlers there)."""
    stop = threading.Event()

    def handler(signum, frame):
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop
