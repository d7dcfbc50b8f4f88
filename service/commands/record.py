"""``noiselab record``: the recorder node, Zenoh streams into an MCAP file."""

from __future__ import annotations

import sys
from pathlib import Path

from ..args import add_transport_args, seconds_arg
from ..outfiles import check_out
from ..signals import stop_on_signals
from ._common import emit


def register(sub) -> None:
    sr = sub.add_parser("record", help="record Zenoh streams to MCAP")
    sr.add_argument("--key", default="noiselab/**", help="key expression to record (default noiselab/**)")
    sr.add_argument("--out", required=True, help="output .mcap")
    sr.add_argument("--duration", type=seconds_arg(), help="seconds (default: until SIGINT/SIGTERM)")
    sr.add_argument("--force", action="store_true", help="overwrite an existing output file")
    sr.add_argument("--json", action="store_true", help="machine-readable summary on stdout")
    add_transport_args(sr)
    sr.set_defaults(func=cmd_record)


def cmd_record(args) -> int:
    from ..nodes import transport
    from ..nodes.recorder import run_recorder
    from ..nodes.runner import READY_MARK

    transport.check_key_expr(args.key)
    out = Path(args.out)
    check_out(args.out, args.force)
    stop = stop_on_signals()
    import threading
    ready = threading.Event()
    writing: list[str] = []

    def subscribed(path: str):
        writing.append(path)
        ready.set()

    def announce():
        ready.wait()
        where = writing[0] if writing[0] == str(out) else \
            f"{writing[0]} (it replaces {out} once the recording is finished)"       # --force over a file
        print(f"{READY_MARK} to {args.key}, writing {where}", file=sys.stderr, flush=True)

    threading.Thread(target=announce, daemon=True).start()
    with transport.open_session(args, "sink") as session:
        s = run_recorder(session, args.key, str(out), duration=args.duration, force=args.force, stop=stop,
                         ready=subscribed)
    emit(args, s.as_dict(), s.lines())
    return 0
