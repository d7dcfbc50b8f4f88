"""``noiselab replay RECORDING``: a recording republished over Zenoh, paced by its log times."""

from __future__ import annotations

from ..args import add_transport_args, seconds_arg, speed_arg
from ..signals import stop_on_signals
from ._common import emit
from ._recording import check_recording


def register(sub) -> None:
    sp2 = sub.add_parser("replay", help="republish a recording over Zenoh, paced by its publish times")
    sp2.add_argument("recording", help=".mcap to replay, or a ROS bag (rosbag2 directory, .mcap, .db3, ROS 1 .bag): "
                                       "each message republished as JSON, paced by log time")
    pace = sp2.add_mutually_exclusive_group()
    pace.add_argument("--speed", type=speed_arg(), default=1.0, help="playback speed (default 1)")
    pace.add_argument("--fast", action="store_true", help="as fast as possible")
    sp2.add_argument("--prefix", help="publish under PREFIX/<topic> instead of <topic>")
    sp2.add_argument("--wait-subscribers", type=seconds_arg(zero=True), default=0.0, metavar="S",
                     help="wait up to S seconds for subscribers before the first message")
    sp2.add_argument("--json", action="store_true", help="machine-readable summary on stdout")
    add_transport_args(sp2)
    sp2.set_defaults(func=cmd_replay)


def cmd_replay(args) -> int:
    from ..nodes import transport
    from ..nodes.replay import replay_topics, run_replay

    check_recording(args.recording)
    replay_topics(args.recording)            # a file that is not MCAP fails here, before any I/O
    if args.prefix:
        transport.check_key_expr(args.prefix)
    stop = stop_on_signals()
    with transport.open_session(args, "source") as session:
        s = run_replay(session, args.recording, speed=None if args.fast else args.speed, prefix=args.prefix,
                       stop=stop, wait_subscribers=args.wait_subscribers)
    emit(args, s.as_dict(), [f"replayed {s.messages} messages of {s.path} in {s.wall_s:.2f} s"])
    return 0
