"""``noiselab simulate MODEL``: the model simulated as fast as possible into a recording (MCAP, or a
rosbag2 bag)."""

from __future__ import annotations

import json
import time
from pathlib import Path

from ..args import seconds_arg
from ..errors import BadInput
from ..outfiles import check_out, make_dir
from ._common import load_model, seed_arg


def register(sub) -> None:
    ss = sub.add_parser("simulate", help="simulate a model as fast as possible into an MCAP recording")
    ss.add_argument("model", help="model file (TOML) or built-in scenario name")
    ss.add_argument("--duration", type=seconds_arg(), required=True, help="seconds of signal")
    ss.add_argument("--seed", type=seed_arg, default=0, help="random seed (default 0)")
    ss.add_argument("--out", help="output .mcap, or the bag directory with --format ros2 "
                                  "(default recordings/<name>-seed<N>[.mcap])")
    ss.add_argument("--format", choices=("mcap", "ros2"), default="mcap",
                    help="mcap: noiselab's JSON MCAP (the wire contract); ros2: a rosbag2 bag (MCAP storage, CDR; "
                         "sensor_msgs/msg/Imu for an IMU model, sensor_msgs/msg/JointState otherwise)")
    ss.add_argument("--force", action="store_true", help="overwrite an existing output file")
    ss.add_argument("--progress", action="store_true", help="show the progress bar even when not on a terminal")
    ss.add_argument("--json", action="store_true", help="machine-readable summary")
    ss.set_defaults(func=cmd_simulate)


def cmd_simulate(args) -> int:
    model = load_model(args.model)
    n = round(args.duration / model.Ts)
    if n < 1:
        raise BadInput(f"--duration {args.duration:g} s is shorter than one sample (Ts = {model.Ts:g} s)")
    from ..recordings.simulated import write_simulation

    ros2 = args.format == "ros2"
    out = Path(args.out) if args.out else Path("recordings") / (f"{model.name}-seed{args.seed}" + ("" if ros2 else ".mcap"))
    if ros2:                       # a bag is a directory: the writer checks what is there (only a bag is replaced)
        if out.exists() and not args.force:
            raise BadInput(f"{out}: already exists (use --force to overwrite)")
        make_dir(str(out), out.parent)
    else:
        check_out(str(out), args.force)
    t0 = time.perf_counter()
    from ..progress import wanted
    rep = write_simulation(model, n, args.seed, out, force=args.force, progress=wanted(args.progress, args.json),
                           fmt=args.format)
    dt = time.perf_counter() - t0
    rep["seconds"] = dt
    if args.json:
        print(json.dumps(rep))
    else:
        topics = len(rep.get("messages") or {}) or 3
        print(f"wrote {rep['out']} ({'a rosbag2 bag' if ros2 else 'MCAP'}): {n} samples x {topics} topics of {model.name} "
              f"({args.duration:g} s at Ts = {model.Ts:g} s) in {dt:.2f} s")
    return 0
