"""A child process of the live tests (``python -m noiselab.cli ...`` or a helper script) with its
stdout and stderr lines collected by threads, so a test waits for a line (an event) instead of
sleeping. The ``spawn`` fixture (tests/conftest.py) starts them and kills them at teardown."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


class Child:
    """A process with its stdout/stderr lines collected by threads. ``t_event``: the default bound
    (s) for "the next event happens"; never a pass condition."""

    def __init__(self, args: list[str], label: str, t_event: float = 30.0):
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.label = label
        self.t_event = t_event
        self.proc = subprocess.Popen([str(a) for a in args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, env=env, cwd=ROOT)
        self.out: list[str] = []
        self.err: list[str] = []
        self.cond = threading.Condition()
        self.err_eof = False
        self.threads = [threading.Thread(target=self._pump, args=(self.proc.stdout, self.out, False), daemon=True),
                        threading.Thread(target=self._pump, args=(self.proc.stderr, self.err, True), daemon=True)]
        for t in self.threads:
            t.start()

    def _pump(self, stream, sink, is_err):
        for line in stream:
            with self.cond:
                sink.append(line.rstrip("\n"))
                self.cond.notify_all()
        with self.cond:
            if is_err:
                self.err_eof = True
            self.cond.notify_all()

    def wait_line(self, text: str, timeout: float | None = None) -> str:
        """The first stderr line containing ``text``; fails if the child exits first or on timeout."""
        def found():
            return next((ln for ln in self.err if text in ln), None)
        with self.cond:
            self.cond.wait_for(lambda: found() is not None or self.err_eof, timeout or self.t_event)
            line = found()
        assert line is not None, (f"{self.label}: no stderr line with {text!r} "
                                  f"({'exited' if self.err_eof else 'timeout'}): {self.stderr_text()}")
        return line

    def finish(self, timeout: float | None = None) -> int:
        """Wait for exit (fail on timeout), then for the output threads; the exit code."""
        try:
            rc = self.proc.wait(timeout or self.t_event)
        except subprocess.TimeoutExpired:
            pytest.fail(f"{self.label} did not exit within {timeout or self.t_event} s: {self.stderr_text()}")
        for t in self.threads:
            t.join(self.t_event)
        return rc

    def interrupt(self, timeout: float | None = None) -> int:
        """SIGINT (the nodes' clean stop) and wait for exit."""
        self.proc.send_signal(signal.SIGINT)
        return self.finish(timeout)

    def json(self) -> dict:
        """The last JSON line on stdout (a node's summary)."""
        for line in reversed(self.out):
            if line.startswith("{"):
                return json.loads(line)
        pytest.fail(f"{self.label}: no JSON summary on stdout: {self.out} {self.stderr_text()}")

    def stderr_text(self) -> str:
        with self.cond:
            return " | ".join(self.err)[-3000:]

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        for t in self.threads:
            t.join(5)
