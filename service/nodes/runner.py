"""`noiselab run`: emulator and recorder as separate processes over Zenoh on loopback.

The recorder starts first and listens on a free 127.0.0.1 port; once it reports that it is
subscribed, the emulator connects to it and waits for the match before its first sample, so the
recording starts at seq 0. When the emulator has published its ``duration``, the recorder is
stopped with SIGINT (it finishes the file) and both summaries are combined.
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


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "service.cli", *args]


def _pump(stream, sink: list, ready: threading.Event | None = None, echo=None):
    for line in stream:
        sink.append(line)
        if ready is not None and READY_MARK in line:
            ready.set()
        if echo is not None:
            echo.write(line)
            echo.flush()


def _last_json(lines: list[str]) -> dict | None:
    for line in reversed(lines):
        line = line.strip()
        if line.startswith("{"):
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                continue
    return None


def run_pipeline(model_spec: str, model_name: str, *, duration: float, seed: int, out_dir: Path,
                 force: bool = False, log=sys.stderr) -> dict:
    out_dir.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out = out_dir / f"{model_name}-{stamp}.mcap"
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    rec = subprocess.Popen(_cli("record", "--key", f"noiselab/{model_name}/**", "--out", str(out),
                                "--listen", endpoint, "--json", *(["--force"] if force else [])),
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    rec_out, rec_err, ready = [], [], threading.Event()
    threads = [threading.Thread(target=_pump, args=(rec.stdout, rec_out), daemon=True),
               threading.Thread(target=_pump, args=(rec.stderr, rec_err, ready), daemon=True)]
    for t in threads:
        t.start()
    while not ready.wait(0.05):
        if rec.poll() is not None:
            for t in threads:
                t.join(2)
            raise RuntimeError("recorder exited before subscribing: " + "".join(rec_err).strip()[-500:])
    emu = subprocess.run(_cli("emulate", model_spec, "--duration", repr(duration), "--seed", str(seed),
                              "--connect", endpoint, "--wait-subscribers", "10", "--json"),
                         capture_output=True, text=True, env=env)
    rec.send_signal(signal.SIGINT)
    try:
        rec.wait(timeout=60)
    except subprocess.TimeoutExpired:
        rec.kill()
        rec.wait()
    for t in threads:
        t.join(5)
    if emu.returncode != 0:
        raise RuntimeError("emulator failed: " + emu.stderr.strip()[-500:])
    if rec.returncode != 0:
        raise RuntimeError("recorder failed: " + "".join(rec_err).strip()[-500:])
    return {"recording": str(out), "emulator": _last_json(emu.stdout.splitlines()),
            "recorder": _last_json(rec_out), "endpoint": endpoint,
            "emulator_log": emu.stderr.strip().splitlines()}
