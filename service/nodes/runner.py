"""`noiselab run`: emulator and recorder (and a controller) as separate processes over Zenoh on loopback.

The recorder starts first and listens on a free 127.0.0.1 port; once it reports that it is
subscribed, the emulator connects to it and waits for the match before its first sample, so the
recording starts at seq 0. When the emulator has published its ``duration`` it ends the stream
(``noiselab/<name>/end``) and exits once the recorder has acknowledged every message; the
recorder is then stopped with SIGINT (it finishes the file) once it has said that the stream
ended (bounded wait: without that line it still finishes, and reports what is missing as gaps),
and both summaries are combined.

Closed loop (``controller``: the controller's flags): the controller node starts after the
recorder, listens on its own port and connects to the recorder (its answers are recorded); the
emulator connects to it too and waits for every peer before its first sample. The controller
ends with the emulator's end of stream, once the recorder has acknowledged its last answers; it
is stopped (SIGINT) if it has not said so within :data:`END_WAIT_S`, and the recorder after it.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

READY_MARK = "noiselab record: subscribed"
END_WAIT_S = 15.0          # longest wait for the recorder's "<prefix> ended" line after the emulator exits
BIND_TRIES = 5
"""Ports a listening node is given before the run gives up: :func:`free_port` learns a free port by
binding and closing it, so another process on the machine may take it before the node binds
(the node then exits saying the address is in use) and the node is started again on a new one."""
ADDRESS_IN_USE = "Address already in use"


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "noiselab.cli", *args]


def _pump(stream, sink: list, ready: threading.Event | None = None, echo=None, mark: str = READY_MARK,
          cond: threading.Condition | None = None):
    """Collect ``stream``'s lines into ``sink``; with ``cond``, notify it on every line and append
    None at the end of the output."""
    for line in stream:
        if cond is not None:
            with cond:
                sink.append(line)
                cond.notify_all()
        else:
            sink.append(line)
        if ready is not None and mark in line:
            ready.set()
        if echo is not None:
            echo.write(line)
            echo.flush()
    if cond is not None:
        with cond:
            sink.append(None)
            cond.notify_all()


def _last_json(lines: list[str]) -> dict | None:
    for line in reversed(lines):
        line = line.strip()
        if line.startswith("{"):
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                continue
    return None


class _Listening:
    """A node that listens on a free 127.0.0.1 port (``make_argv(endpoint)`` its command line),
    started again on another port when the one it was given was taken before it bound it
    (:data:`BIND_TRIES`). ``children`` collects every process started, for the caller's cleanup."""

    def __init__(self, make_argv, mark, env, children: list):
        self.make_argv, self.mark, self.env, self.children = make_argv, mark, env, children
        self._start()

    def _start(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.child = _Child(self.make_argv(self.endpoint), self.mark, self.env)
        self.children.append(self.child)

    def wait_ready(self, what: str) -> _Child:
        for attempt in range(BIND_TRIES):
            try:
                self.child.wait_ready(what)
                return self.child
            except RuntimeError as exc:
                if ADDRESS_IN_USE not in str(exc) or attempt == BIND_TRIES - 1:
                    raise
                self._start()
        raise AssertionError("unreachable")


class _Child:
    """A node process whose stdout/stderr are pumped into lists; ``ready`` when its mark appears."""

    def __init__(self, argv, mark, env):
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        self.out, self.err, self.ready = [], [], threading.Event()
        self.cond = threading.Condition()
        self.threads = [threading.Thread(target=_pump, args=(self.proc.stdout, self.out, self.ready, None, mark), daemon=True),
                        threading.Thread(target=_pump, args=(self.proc.stderr, self.err, self.ready, None, mark, self.cond),
                                         daemon=True)]
        for t in self.threads:
            t.start()

    def wait_ready(self, what: str) -> None:
        while not self.ready.wait(0.05):
            if self.proc.poll() is not None:
                for t in self.threads:
                    t.join(2)
                raise RuntimeError(f"{what} exited before subscribing: " + "".join(ln for ln in self.err if ln is not None).strip()[-500:])

    def wait_err_line(self, text: str, timeout: float) -> bool:
        """Wait until a stderr line contains ``text`` (False on timeout or if the child exits)."""
        def seen():
            return any(ln is not None and text in ln for ln in self.err)
        with self.cond:
            self.cond.wait_for(lambda: seen() or (self.err and self.err[-1] is None), timeout)
            return seen()

    def wait_exit(self, timeout: float) -> None:
        """Wait up to ``timeout`` seconds for the child to exit by itself."""
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            pass

    def stop(self, what: str, timeout: float = 120) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for t in self.threads:
            t.join(5)
        if self.proc.returncode != 0:
            raise RuntimeError(f"{what} failed (exit {self.proc.returncode}): " + "".join(ln for ln in self.err if ln is not None).strip()[-500:])

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def run_pipeline(model_spec: str, model_name: str, *, duration: float, seed: int, out_dir: Path,
                 force: bool = False, analyze: bool = True, speed: float = 1.0,
                 analyze_model: str | None = None, window: float | None = None, out_name: str | None = None,
                 controller: list[str] | None = None, log=sys.stderr) -> dict:
    """Run the pipeline; ``speed`` > 1 runs the emulator faster than real time, ``analyze_model``
    is the model the live analyzer compares with (default the emulated one), ``window`` its
    rolling window in s of samples (default the whole run), ``out_name`` the recording's stem,
    ``controller`` the flags of a `noiselab control` node that closes the loop (None: none)."""
    from .analyzer import READY_MARK as ANALYZER_READY
    from .controller import READY_MARK as CONTROLLER_READY

    out_dir.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out = out_dir / f"{out_name or f'{model_name}-{stamp}'}.mcap"
    rrd = out.with_suffix(".rrd")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    force_flag = ["--force"] if force else []
    children = []
    try:
        rec_node = _Listening(lambda ep: _cli("record", "--key", f"noiselab/{model_name}/**", "--out", str(out),
                                              "--listen", ep, "--json", *force_flag), READY_MARK, env, children)
        an_node = None
        if analyze:
            an_node = _Listening(lambda ep: _cli("analyze", "--live", "--model", analyze_model or model_spec,
                                                 "--device", model_name, "--listen", ep, "--window",
                                                 repr(window or max(60.0, duration + 5)), "--rrd", str(rrd), "--json",
                                                 *force_flag), ANALYZER_READY, env, children)
        rec = rec_node.wait_ready("recorder")
        an = None if an_node is None else an_node.wait_ready("analyzer")
        rec_ep = rec_node.endpoint
        ctl = None
        if controller is not None:     # after the recorder is subscribed: its answers are recorded from the first
            ctl_node = _Listening(lambda ep: _cli("control", model_spec, *controller, "--listen", ep, "--connect", rec_ep,
                                                  "--json"), CONTROLLER_READY, env, children)
            ctl = ctl_node.wait_ready("controller")
        connect = ["--connect", rec_ep] + (["--connect", an_node.endpoint] if an is not None else []) \
            + (["--connect", ctl_node.endpoint] if ctl is not None else [])
        emu = subprocess.run(_cli("emulate", model_spec, "--duration", repr(duration), "--seed", str(seed),
                                  "--speed", repr(speed),
                                  *connect, "--wait-peers", str(len(connect) // 2), "--wait-subscribers", "10",
                                  "--json"),
                             capture_output=True, text=True, env=env)
        if emu.returncode != 0:
            raise RuntimeError("emulator failed: " + emu.stderr.strip()[-500:])
        # the emulator acknowledged its end with the recorder before exiting: this returns at once
        # unless the acknowledgement timed out; the recorder then reports the shortfall as gaps
        if ctl is not None:            # it ends with the stream, once the recorder has its last answers
            if ctl.wait_err_line(f"noiselab control: noiselab/{model_name} ended", END_WAIT_S):
                ctl.wait_exit(END_WAIT_S)     # no SIGINT while it exits: Python's finalization has restored the default
            ctl.stop("controller")
        rec.wait_err_line(f"noiselab record: noiselab/{model_name} ended", END_WAIT_S)
        rec.stop("recorder")
        if an is not None:
            an.stop("analyzer")
    finally:
        for c in children:
            c.kill()
    return {"recording": str(out), "emulator": _last_json(emu.stdout.splitlines()),
            "recorder": _last_json(rec.out), "analysis": _last_json(an.out) if an is not None else None,
            "controller": _last_json(ctl.out) if ctl is not None else None,
            "endpoint": rec_ep, "emulator_log": emu.stderr.strip().splitlines()}


def pipeline_lines(emu: dict, rec: dict, ctl: dict | None = None) -> list[str]:
    """Per-topic message counts and gaps (the recorder's summary ``rec``), the loop's timing (the
    emulator's ``emu``) and the controller's (``ctl``), of a :func:`run_pipeline` report: the
    lines `run` and `demo` print."""
    lines = []
    for topic, b in sorted((rec.get("topics") or {}).items()):
        gaps = "no gaps" if not b["gaps"] and not b["missing_at_start"] else \
            f"{b['missing']} missing in {len(b['gaps'])} gaps, first seq {b['first_seq']}"
        lines.append(f"  {topic}: {b['count']} messages, {gaps}")
    if emu:
        lat = emu["lateness_us"]
        speed = f", {emu['speed']:g}x real time" if emu.get("speed", 1) != 1 else ""
        lines.append(f"loop: {emu['samples']} samples at Ts = {emu['Ts']:g} s{speed} ({emu['wall_s']:.1f} s wall), "
                     f"lateness p50 {lat['p50']:.0f} us, p99 {lat['p99']:.0f} us, max {lat['max']:.0f} us, "
                     f"{emu['overruns']} overruns")
    if ctl:
        lat = ctl["latency_us"]
        lines.append(f"controller: answered {ctl['answered']} measurements, {ctl['late_replies']} late, "
                     f"{ctl['missing_measurements']} missing, {ctl['stale_measurements']} stale, "
                     f"{ctl['rejected_measurements']} rejected; latency p50 {lat['p50']:.0f} us, p99 {lat['p99']:.0f} us")
    return lines
