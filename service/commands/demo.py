"""``noiselab demo [seed|imu]``: a story live (Zenoh, MCAP), diagnosed."""

from __future__ import annotations

from ..args import count_arg, seconds_arg, speed_arg
from ..diagnose.thresholds import MAX_EFFECTS
from ..outfiles import check_out_dir
from ._common import seed_arg


def register(sub) -> None:
    sm = sub.add_parser("demo", help="a story live (Zenoh, MCAP), diagnosed: the seed lesson against its own "
                                     "model, or an IMU against its white noise (demo imu)")
    sm.add_argument("story", nargs="?", choices=("seed", "imu"), default="seed",
                    help="seed (default): the seed lesson against seed-nominal; imu: a 6-axis IMU at rest against "
                         "imu-nominal, its IEEE 952 coefficients and Kalibr's imu.yaml")
    sm.add_argument("--duration", type=seconds_arg(), default=None,
                    help="seconds of samples (default: seed 1200, as the bias walk needs ~20 min of data to show; "
                         "imu 600)")
    sm.add_argument("--speed", type=speed_arg(), default=20.0, metavar="X",
                    help="emulate X times faster than real time (default 20)")
    sm.add_argument("--seed", type=seed_arg, default=1, help="random seed (default 1)")
    sm.add_argument("--out", default="recordings", help="output directory (default recordings/)")
    sm.add_argument("--max-effects", type=count_arg(), default=MAX_EFFECTS, metavar="K",
                    help=f"add at most K effects the model lacks (refits of its own are not counted; "
                         f"default {MAX_EFFECTS})")
    sm.add_argument("--force", action="store_true", help="overwrite existing demo files")
    sm.add_argument("--json", action="store_true", help="machine-readable summary")
    sm.add_argument("--progress", action="store_true",
                    help="show the progress on stderr even when it is not a terminal (never with --json)")
    sm.set_defaults(func=cmd_demo)


def cmd_demo(args) -> int:
    check_out_dir(args.out)
    if args.story == "imu":
        from ..demo_imu import cmd_imu_demo
        return cmd_imu_demo(args)
    from ..demo import cmd_demo as run
    if args.duration is None:
        args.duration = 1200.0
    return run(args)
