"""A proportional controller process for the closed-loop test (tests/e2e/test_live.py).

Subscribes ``noiselab/<name>/measurement`` and answers every measurement y_k with
``u = Kp (r - y_k)`` on ``noiselab/<name>/control`` (payload ``wire.encode(seq, t_k, [u],
kind="control")``, seq counting from 0). The answer is published from the subscriber callback,
so the emulator applies it at the next sample it steps after it arrives (zero-order hold).

Transport: the product's shared flags (``--connect``/``--listen``/``--mode``/``--config``, role
"sink": by default it connects to tcp/127.0.0.1:7447). Once its measurement subscriber and
control publisher are declared it prints ``p_controller: ready`` on stderr (tests wait on that
line); it may start before the emulator (e.g. as a client of a router). No first answer is lost:
the emulator declares its control subscriber before it publishes y_0, and declarations and data
travel in order on a link. It runs until SIGINT/SIGTERM or ``--duration`` seconds, then prints a
JSON summary (``{"controls": n, "bad": m}``) on stdout.

    python tests/live_helpers/p_controller.py --name loop --kp 8 --r 0.3 \
        --connect tcp/127.0.0.1:PORT --duration 60
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading

from noiselab import wire
from noiselab.nodes import transport

READY = "p_controller: ready"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--name", required=True, help="device name (keys noiselab/<name>/...)")
    p.add_argument("--kp", type=float, required=True, help="proportional gain Kp, N/m")
    p.add_argument("--r", type=float, required=True, help="position reference r, m")
    p.add_argument("--duration", type=float, required=True, help="upper bound on the run time, s")
    transport.add_transport_args(p)
    args = p.parse_args(argv)

    stop = threading.Event()
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *_: stop.set())
    lock = threading.Lock()
    counts = {"controls": 0, "bad": 0}
    try:
        session = transport.open_session(args, "sink")
    except transport.TransportError as exc:
        print(f"p_controller: {exc}", file=sys.stderr)
        return 2
    with session:
        pub = session.declare_publisher(wire.key(args.name, wire.CONTROL), **transport.DATA_QOS)

        def on_measurement(sample) -> None:
            try:
                msg = wire.decode(sample.payload.to_bytes(), "measurement")
                if len(msg["y"]) != 1:
                    raise wire.WireError(f"y has {len(msg['y'])} elements, not 1")
            except wire.WireError:
                with lock:
                    counts["bad"] += 1
                return
            u = args.kp * (args.r - msg["y"][0])        # u = Kp (r - y), N
            with lock:
                seq = counts["controls"]
                counts["controls"] += 1
                pub.put(wire.encode(seq, msg["t"], [u], kind="control"))

        sub = session.declare_subscriber(wire.key(args.name, "measurement"), on_measurement)
        print(READY, file=sys.stderr, flush=True)
        stop.wait(args.duration)
        sub.undeclare()
        pub.undeclare()
    with lock:
        print(json.dumps(counts), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
