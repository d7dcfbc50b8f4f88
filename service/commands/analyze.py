"""``noiselab analyze RECORDING --model MODEL``: a recording (or, ``--live``, a Zenoh stream) compared
with a model: the model error per view and the regions where the data leave it."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..args import SECONDS_MAX, add_transport_args, seconds_arg
from ..errors import BadInput
from ..outfiles import check_out, png_path, writing
from ._common import emit, load_model, segment_arg
from ._recording import load_series, reading_early


def register(sub) -> None:
    sa = sub.add_parser("analyze", help="compare a recording (or a live stream) with a model")
    sa.add_argument("recording", nargs="?", help="the .mcap to analyse (omit with --live)")
    sa.add_argument("--model", required=True, help="model file (TOML) or built-in scenario name")
    sa.add_argument("--rrd", help="write the Rerun recording here (and a PNG summary next to it)")
    sa.add_argument("--png", help="write the PNG summary here (default: next to --rrd)")
    sa.add_argument("--device", help="device name in a noiselab recording with several devices")
    sa.add_argument("--measurement", metavar="TOPIC:FIELD",
                    help="foreign recordings (JSON MCAP or ROS bag): topic and field(s) of the measurement, e.g. "
                         "/imu:angular_velocity.x, /joint_states:position[2], /imu:linear_acceleration.* (every numeric "
                         "field), or a comma list")
    sa.add_argument("--time", metavar="FIELD",
                    help="foreign recordings: time field in s (ns if it ends in _ns; exact ns for a {sec, nanosec} "
                         "stamp); default: a ROS message's header.stamp, else the log time (ROS) or publish_time (JSON)")
    sa.add_argument("--segment", type=segment_arg, metavar="N",
                    help="a recording whose source restarted (read as stream segments): analyse segment N, 1 = the "
                         "first (default: the one with the longest gap-free run)")
    sa.add_argument("--burn", type=_burn, default="auto",
                    help="seconds to skip at the start ('auto': the model's transient when the stream starts at rest)")
    sa.add_argument("--force", action="store_true", help="overwrite existing output files")
    sa.add_argument("--json", action="store_true", help="machine-readable report")
    sa.add_argument("--progress", action="store_true",
                    help="show the progress on stderr even when it is not a terminal (never with --json)")
    sa.add_argument("--live", action="store_true", help="analyse a live Zenoh stream instead of a file")
    sa.add_argument("--window", type=seconds_arg(), default=60.0, metavar="S",
                    help="live: rolling window in seconds (default 60)")
    sa.add_argument("--update", type=seconds_arg(), default=0.5, metavar="S",
                    help="live: seconds between updates (default 0.5)")
    sa.add_argument("--duration", type=seconds_arg(), help="live: stop after S seconds")
    sa.add_argument("--rank-every", type=seconds_arg(zero=True), default=0.0, metavar="S",
                    help="live: re-rank the candidate missing effects on the window every S s (default 0: never)")
    add_transport_args(sa)
    sa.set_defaults(func=cmd_analyze)


def _burn(text):
    """'auto' or seconds >= 0 (:func:`seconds_arg`), kept as text."""
    if text != "auto":
        try:
            seconds_arg(zero=True)(text)
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(
                f"expected 'auto' or seconds >= 0 and <= {SECONDS_MAX:g}, got {text!r}") from None
    return text


def analysis_report(cmp, series, extra: dict | None = None) -> dict:
    """The scriptable analysis result (``noiselab analyze --json``)."""
    import numpy as np

    views = {}
    for v in cmp.views:
        views.setdefault(v.name, []).append({"output": v.output, "error": v.error, "points": int(v.x.size),
                                             "flagged": int(np.sum(v.flagged)), "x_label": v.x_label})
    rep = {"recording": series.source, "model": cmp.model_name, "model_source": cmp.model_source,
           "samples": int(cmp.t.size), "Ts": cmp.Ts, "error": cmp.error, "error_per_view": cmp.error_per_view,
           "views": views, "command": series.command,
           "regions": [{"view": r.view, "output": r.output, "from": r.x_lo, "to": r.x_hi, "points": r.points,
                        "max_abs_z": r.max_abs_z, "direction": r.direction} for r in cmp.regions],
           "notes": series.notes + cmp.notes}
    rep.update(extra or {})
    return rep


def report_lines(cmp, series) -> list[str]:
    from ..diagnose.report import region_lines

    lines = [f"{series.source}: {cmp.t.size} samples against model {cmp.model_name} ({cmp.model_source})",
             f"model error {cmp.error:.3g} (about 1 when the model explains the data; per view: "
             + ", ".join(f"{k} {v:.3g}" for k, v in cmp.error_per_view.items()) + ")"]
    lines += region_lines(cmp.regions, 12) or ["no region leaves the model's confidence band"]
    for note in series.notes + cmp.notes:
        lines.append(f"note: {note}")
    return lines


def cmd_analyze(args) -> int:
    if args.live:
        from ..nodes.analyzer import cmd_analyze_live
        return cmd_analyze_live(args)
    if not args.recording:
        raise BadInput("give a RECORDING.mcap (or --live)")
    return reading_early(args, _analyze_cmd)


def _analyze_cmd(args, read) -> int:
    from ..progress import Steps, wanted

    with Steps("noiselab analyze", wanted(args.progress, args.json)) as steps:
        rep, lines = _analyze(args, read, steps)
    emit(args, rep, lines)
    return 0


def _analyze(args, read, steps) -> tuple[dict, list[str]]:
    """The analysis of ``args.recording``, its phases shown on ``steps``: (report, lines)."""
    from ..diagnose.compare import auto_burn, compare

    model = load_model(args.model)
    png = png_path(args)
    check_out(args.rrd, args.force)
    check_out(png, args.force)
    series = load_series(args, model, truth=bool(args.rrd or png), read=read, steps=steps)
    burn = auto_burn(series.starts_at_rest, series.u) if args.burn == "auto" else \
        round(float(args.burn) / model.Ts)
    steps(f"comparing {series.y.shape[0]} samples with {Path(args.model).name}")
    cmp = compare(model, series.t, series.y, series.u, truth=series.truth, burn=burn,
                  level=series.starts_at_rest, free_start=not series.starts_at_rest)
    cmp.recording = series.source
    extra = {}
    if args.rrd:
        from noiselab.viewers.rerun_log import log_comparisons
        steps(f"writing {args.rrd}")
        with writing(args.rrd):
            log_comparisons([cmp], args.rrd)
        extra["rrd"] = args.rrd
    if png:
        from noiselab.viewers.summary_png import write_summary_png
        steps(f"writing {png}")
        with writing(png):
            write_summary_png([cmp], png)
        extra["png"] = png
    rep = analysis_report(cmp, series, extra)
    return rep, report_lines(cmp, series) + [f"wrote {extra[k]}" for k in ("rrd", "png") if k in extra]
