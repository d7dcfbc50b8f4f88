"""``noiselab diagnose RECORDING --model MODEL``: which physical effect the model lacks: rank, fit, add."""

from __future__ import annotations

import sys
from pathlib import Path

from ..args import count_arg
from ..diagnose.thresholds import MAX_EFFECTS
from ..outfiles import check_out, png_path, writing
from ._common import emit, load_model, segment_arg
from ._recording import load_series, reading_early


def register(sub) -> None:
    sd = sub.add_parser("diagnose", help="which physical effect is missing from the model: rank, fit, add")
    sd.add_argument("recording", help="the .mcap to diagnose")
    sd.add_argument("--model", required=True, help="model file (TOML) or built-in scenario name")
    sd.add_argument("--fit-out", metavar="FITTED.toml", help="write the extended model file here")
    sd.add_argument("--rrd", help="write the Rerun recording (one revision per added effect) here")
    sd.add_argument("--png", help="write the PNG summary here (default: next to --rrd)")
    sd.add_argument("--max-effects", type=count_arg(), default=MAX_EFFECTS, metavar="K",
                    help=f"add at most K effects the model lacks (refits of its own are not counted; "
                         f"default {MAX_EFFECTS})")
    sd.add_argument("--device", help="device name in a noiselab recording with several devices")
    sd.add_argument("--measurement", metavar="TOPIC:FIELD",
                    help="foreign recordings (JSON MCAP or ROS bag): topic and field(s), e.g. /imu:angular_velocity.x")
    sd.add_argument("--time", metavar="FIELD",
                    help="foreign recordings: time field (s, ns if it ends in _ns, or a {sec, nanosec} stamp); default: "
                         "header.stamp (ROS), else log time (ROS) or publish_time (JSON)")
    sd.add_argument("--segment", type=segment_arg, metavar="N",
                    help="a recording whose source restarted (read as stream segments): analyse segment N, 1 = the "
                         "first (default: the one with the longest gap-free run)")
    sd.add_argument("--force", action="store_true", help="overwrite existing output files")
    sd.add_argument("--verbose", action="store_true", help="log the search on stderr")
    sd.add_argument("--json", action="store_true", help="machine-readable report")
    sd.add_argument("--progress", action="store_true",
                    help="show the progress on stderr even when it is not a terminal (never with --json or --verbose)")
    sd.set_defaults(func=cmd_diagnose)


def cmd_diagnose(args) -> int:
    return reading_early(args, _diagnose_cmd)


def _diagnose_cmd(args, read) -> int:
    from ..progress import Steps, wanted

    # --verbose logs the search on stderr line by line: no bar between its lines
    show = False if args.verbose else wanted(args.progress, args.json)
    with Steps("noiselab diagnose", show, unit=" fits") as steps:
        rep, lines = _diagnose(args, read, steps)
    emit(args, rep, lines)
    return 0


def _diagnose(args, read, steps) -> tuple[dict, list[str]]:
    """The diagnosis of ``args.recording``, its phases shown on ``steps``: (report, lines)."""
    from ..diagnose.diagnose import diagnose
    from ..diagnose.report import diagnosis_json, diagnosis_lines

    model = load_model(args.model)
    png = png_path(args)
    for out in (args.fit_out, args.rrd, png):
        check_out(out, args.force)
    series = load_series(args, model, truth=bool(args.rrd or png), read=read, steps=steps)
    log = (lambda s: print(f"noiselab diagnose: {s}", file=sys.stderr)) if args.verbose else None
    rep = diagnose(model, series.t, series.y, series.u, at_rest=series.starts_at_rest,
                   max_effects=args.max_effects, log=log, progress=steps if steps.enabled else None)
    extra = {}
    if args.fit_out:
        with writing(args.fit_out):
            Path(args.fit_out).write_text(rep["fitted_model"])
        extra["fit_out"] = args.fit_out
    comps = rep["comparisons"]
    for c in comps:
        c.recording = series.source
        if series.truth is not None:
            c.truth = series.truth
    if args.rrd:
        from noiselab.viewers.rerun_log import log_comparisons
        steps(f"writing {args.rrd}")
        with writing(args.rrd):
            log_comparisons(comps, args.rrd)
        extra["rrd"] = args.rrd
    if png:
        from noiselab.viewers.summary_png import write_summary_png
        steps(f"writing {png}")
        with writing(png):
            write_summary_png(comps, png)
        extra["png"] = png
    return diagnosis_json(rep, series, extra), diagnosis_lines(rep, series, extra)
