"""``noiselab router``: a Zenoh router in this process."""

from __future__ import annotations

import sys

from ..args import add_transport_args, seconds_arg
from ..signals import stop_on_signals


def register(sub) -> None:
    so = sub.add_parser("router", help="a Zenoh router in this process")
    so.add_argument("--duration", type=seconds_arg(), help="seconds (default: until stopped)")
    add_transport_args(so)
    so.set_defaults(func=cmd_router)


def cmd_router(args) -> int:
    from ..nodes import transport

    stop = stop_on_signals()
    with transport.open_session(args, "router"):            # open while it routes
        ends = transport.endpoints_of(args, "router")
        print(f"noiselab router: listening on {', '.join(ends['listen']) or 'the config file endpoints'}",
              file=sys.stderr, flush=True)
        stop.wait(args.duration)
    return 0
