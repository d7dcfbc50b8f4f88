"""``noiselab emulate MODEL``: the real-time emulator node, publishing over Zenoh."""

from __future__ import annotations

import sys

from ..args import add_transport_args, count_arg, seconds_arg, speed_arg
from ..signals import stop_on_signals
from ._common import emit, load_model, seed_arg


def register(sub) -> None:
    se = sub.add_parser("emulate", help="real-time emulator: publish truth, command, measurement over Zenoh")
    se.add_argument("model", help="model file (TOML) or built-in scenario name")
    se.add_argument("--duration", type=seconds_arg(), help="seconds of samples (default: until stopped)")
    se.add_argument("--seed", type=seed_arg, default=0, help="random seed (default 0)")
    se.add_argument("--wait-subscribers", type=seconds_arg(zero=True), default=0.0, metavar="S",
                    help="wait up to S seconds for a subscriber before the first sample")
    se.add_argument("--wait-peers", type=count_arg(lo=0), default=0, metavar="N",
                    help="before waiting for subscribers, wait until N peers are connected (several sinks)")
    se.add_argument("--stale", type=seconds_arg(), default=0.5, metavar="S",
                    help="closed loop: a control input older than S seconds is stale, zero is applied (default 0.5)")
    se.add_argument("--end-timeout", type=seconds_arg(), default=10.0, metavar="S",
                    help="at the end, wait up to S seconds for the recorders to acknowledge every message (default 10)")
    se.add_argument("--speed", type=speed_arg(), default=1.0, metavar="X",
                    help="run X times faster than real time (sample times stay on the Ts grid; default 1)")
    se.add_argument("--json", action="store_true", help="machine-readable summary on stdout")
    add_transport_args(se)
    se.set_defaults(func=cmd_emulate)


def cmd_emulate(args) -> int:
    from ..nodes import transport
    from ..nodes.emulator import run_emulator

    model = load_model(args.model)
    stop = stop_on_signals()
    with transport.open_session(args, "source") as session:
        ends = transport.endpoints_of(args, "source")
        print(f"noiselab emulate: {model.name} at Ts = {model.Ts:g} s on noiselab/{model.name}/* "
              f"(listen {ends['listen']}, connect {ends['connect']})", file=sys.stderr, flush=True)
        s = run_emulator(model, session, duration=args.duration, seed=args.seed, stop=stop,
                         wait_subscribers=args.wait_subscribers, stale_s=args.stale, wait_peers=args.wait_peers,
                         end_timeout=args.end_timeout, speed=args.speed)
    lat = s.lateness_us
    emit(args, s.as_dict(), [(f"emulated {s.samples} samples of {s.name} in {s.wall_s:.2f} s; lateness p50 "
                              f"{lat['p50']:.0f} us, p99 {lat['p99']:.0f} us, max {lat['max']:.0f} us; "
                              f"{s.overruns} overruns")])
    return 0
