"""The ``noiselab`` command line.

Exit codes (DESIGN.md): 0 success, 2 bad input (one line on stderr naming what is wrong),
1 a bug (a traceback). Every long-running command has a bound (``--duration``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from . import one_blas_thread
from .args import (
    SECONDS_MAX,
    add_transport_args,
    bounded,
    count_arg,
    seconds_arg,
    speed_arg,
)
from .errors import BadInput
from .model import ModelError
from .outfiles import check_out, check_out_dir, make_dir, png_path, writing
from .signals import stop_on_signals

one_blas_thread()          # before any command imports numpy: BLAS reads the thread count when numpy loads


def load_model(spec):
    """The model of ``spec`` (a file or a built-in scenario); the model package (scipy) is loaded
    here, by the commands that need it, not to read the flags."""
    from .model import load_model as _load

    return _load(spec)


__version__ = "0.1.0"


class _Lazy(Exception):
    """Stands in for an error class whose module was never imported (so nothing raised it)."""


def _loaded(module: str, name: str):
    mod = sys.modules.get(module)
    return getattr(mod, name) if mod is not None else _Lazy


def _bad_input_types():
    """The error classes the CLI prints as one line with exit 2. A class whose module no command
    imported cannot have been raised, and is not imported here to be caught (:class:`_Lazy`)."""
    McapIoError = _loaded("service.nodes.mcapio", "McapIoError")
    RecordingExistsError = _loaded("service.nodes.mcapio", "RecordingExistsError")
    TransportError = _loaded("service.nodes.transport", "TransportError")
    WireError = _loaded("service.nodes.wire", "WireError")
    AnalysisError = _loaded("service.diagnose.results", "AnalysisError")
    DemoError = _loaded("service.demo", "DemoError")
    StatsError = _loaded("service.stats.errors", "StatsError")
    return (ModelError, BadInput, WireError, McapIoError, RecordingExistsError, TransportError,
            AnalysisError, StatsError, DemoError,
            FileNotFoundError, IsADirectoryError, PermissionError)


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own errors: one line, exit 2
        self.exit(2, f"noiselab: {message}\n")


# -- numeric flags: every number on the command line is read by one of service.args' bounded types
_seed = bounded(0, None, integer=True, what="an integer seed")
_segment = bounded(1, None, integer=True, what="a segment number")
"""``--segment N``: a stream segment of a recording whose source restarted, 1 = the first; one
beyond the recording's segments is refused where they are known (the loader names their count)."""


# -- predict ------------------------------------------------------------------------------------
def _vec(v):
    """Per output, JSON-ready: NaN (no value at that output, e.g. where the plant integrates) as null."""
    import numpy as np

    return None if v is None else [float(x) if np.isfinite(x) else None for x in np.atleast_1d(v)]


def predict_report(model) -> dict:
    """The scriptable prediction (DESIGN.md, ``noiselab predict --json``)."""
    import numpy as np

    pr = model.predictor()
    st = pr.steady_state()
    modifiers = {}
    for eid, eff in model.effects.items():
        if eff.role == "modifier" and st.var_y is not None:
            other = model.without_effect(eid).predictor().steady_state()
            modifiers[eid] = None if other.var_y is None else _vec(st.var_y - other.var_y)
    return {
        "model": model.name,
        "source": model.source,
        "Ts": model.Ts,
        "discretization": model.discretization,
        "outputs": model.p,
        "output_names": list(model.output_names),
        "output_units": list(model.output_units),
        "var_y": _vec(st.var_y),
        "std_y": None if st.var_y is None else _vec(np.sqrt(st.var_y)),
        "bias_var_rate": _vec(st.bias_var_rate),
        "walk_var_rate": _vec(st.walk_var_rate),
        "P": None if st.P is None else st.P.tolist(),
        "state_names": list(model.plant.state_names),
        "contributions": {k: _vec(v) for k, v in st.contributions.items()},
        "modifiers": modifiers,
        "stable": st.stable,
        "notes": st.notes,
    }


def _fmt(v):
    return "null" if v is None else "  ".join("null" if x is None else f"{x:.4e}" for x in v)


def cmd_predict(args) -> int:
    model = load_model(args.model)
    rep = predict_report(model)
    if args.json:
        print(json.dumps(rep, indent=2))
        return 0
    print(f"model {rep['model']} ({rep['source']}), Ts = {rep['Ts']:g} s, {rep['discretization']}")
    print("outputs: " + ", ".join(model.outputs.label(j) for j in range(model.p)))
    print(f"{'effect':<24} {'variance added to y (unit^2)':>32}   share")
    total = rep["var_y"]
    for eid, v in rep["contributions"].items():
        share = "" if v is None or total is None else "  ".join(
            "  -    " if a is None or b is None else f"{100 * a / b:5.1f} %" for a, b in zip(v, total))
        print(f"{eid:<24} {_fmt(v):>32}   {share}")
    for eid, v in rep["modifiers"].items():
        print(f"{eid:<24} {_fmt(v):>32}   (change of var_y it causes)")
    print(f"{'var_y (steady state)':<24} {_fmt(total):>32}")
    print(f"{'std_y':<24} {_fmt(rep['std_y']):>32}")
    print(f"{'bias_var_rate (per s)':<24} {_fmt(rep['bias_var_rate']):>32}")
    if rep["walk_var_rate"] is not None:
        print(f"{'walk_var_rate (per s)':<24} {_fmt(rep['walk_var_rate']):>32}   (the plant integrates)")
    if rep["P"] is None:
        print("P: null (the plant integrates: no steady state, stationary increments)" if rep["walk_var_rate"]
              is not None else "P: null (the plant is not stable: no steady state)")
    elif not rep["P"]:
        print("P: [] (no plant states: a sensor-only model, y = reference + sensor effects)")
    else:
        print("P (plant state covariance, " + ", ".join(rep["state_names"]) + "):")
        for row in rep["P"]:
            print("   " + "  ".join(f"{x: .4e}" for x in row))
    for note in rep["notes"]:
        print(f"note: {note}")
    return 0


# -- simulate -------------------------------------------------------------------------------------
def cmd_simulate(args) -> int:
    model = load_model(args.model)
    n = int(round(args.duration / model.Ts))
    if n < 1:
        raise BadInput(f"--duration {args.duration:g} s is shorter than one sample (Ts = {model.Ts:g} s)")
    from .nodes.simwrite import write_simulation

    ros2 = args.format == "ros2"
    out = Path(args.out) if args.out else Path("recordings") / (f"{model.name}-seed{args.seed}" + ("" if ros2 else ".mcap"))
    if ros2:                       # a bag is a directory: the writer checks what is there (only a bag is replaced)
        if out.exists() and not args.force:
            raise BadInput(f"{out}: already exists (use --force to overwrite)")
        make_dir(str(out), out.parent)
    else:
        check_out(str(out), args.force)
    t0 = time.perf_counter()
    from .progress import wanted
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


# -- live pipeline -----------------------------------------------------------------------------------
def _emit(args, summary: dict, lines: list[str]) -> None:
    if args.json:
        print(json.dumps(summary), flush=True)
    else:
        for line in lines:
            print(line, flush=True)


def cmd_emulate(args) -> int:
    from .nodes import transport
    from .nodes.emulator import run_emulator

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
    _emit(args, s.as_dict(), [f"emulated {s.samples} samples of {s.name} in {s.wall_s:.2f} s; lateness p50 "
                              f"{lat['p50']:.0f} us, p99 {lat['p99']:.0f} us, max {lat['max']:.0f} us; "
                              f"{s.overruns} overruns"])
    return 0


def cmd_record(args) -> int:
    from .nodes import transport
    from .nodes.recorder import run_recorder
    from .nodes.runner import READY_MARK

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
    _emit(args, s.as_dict(), s.lines())
    return 0


def cmd_recover(args) -> int:
    from .nodes import mcapio

    st = mcapio.recover(args.broken, args.out, force=args.force)
    rep = {"node": "recover", "input": args.broken, "output": args.out, "messages": st.messages,
           "total": st.total, "already_complete": st.already_complete, "note": st.note}
    lines = [f"recovered {st.total} messages from {args.broken} into {args.out}"
             + (" (the input was complete)" if st.already_complete else "")]
    lines += [f"  {topic}: {count}" for topic, count in sorted(st.messages.items())]
    if st.note:
        lines.append(f"  {st.note}")
    _emit(args, rep, lines)
    return 0


def cmd_replay(args) -> int:
    from .nodes import transport
    from .nodes.replay import replay_topics, run_replay

    _check_recording(args.recording)
    replay_topics(args.recording)            # a file that is not MCAP fails here, before any I/O
    if args.prefix:
        transport.check_key_expr(args.prefix)
    stop = stop_on_signals()
    with transport.open_session(args, "source") as session:
        s = run_replay(session, args.recording, speed=None if args.fast else args.speed, prefix=args.prefix,
                       stop=stop, wait_subscribers=args.wait_subscribers)
    _emit(args, s.as_dict(), [f"replayed {s.messages} messages of {s.path} in {s.wall_s:.2f} s"])
    return 0


def cmd_router(args) -> int:
    from .nodes import transport

    stop = stop_on_signals()
    with transport.open_session(args, "router"):            # open while it routes
        ends = transport.endpoints_of(args, "router")
        print(f"noiselab router: listening on {', '.join(ends['listen']) or 'the config file endpoints'}",
              file=sys.stderr, flush=True)
        stop.wait(args.duration)
    return 0


def cmd_run(args) -> int:
    from .nodes.runner import pipeline_lines, run_pipeline

    model = load_model(args.model)              # bad input fails here, before any process starts
    check_out_dir(args.out)
    rep = run_pipeline(args.model, model.name, duration=args.duration, seed=args.seed, out_dir=Path(args.out),
                       force=args.force, analyze=not args.no_analyze, speed=args.speed)
    emu, rec = rep["emulator"] or {}, rep["recorder"] or {}
    lines = [f"recording: {rep['recording']}"] + pipeline_lines(emu, rec)
    an = rep.get("analysis") or {}
    if an.get("error") is not None:
        lines.append(f"analysis: model error {an['error']:.3g} against {args.model} ("
                     + ", ".join(f"{k} {v:.3g}" for k, v in an["error_per_view"].items()) + ")")
        lines += [f"wrote {an[k]}" for k in ("rrd", "png") if an.get(k)]
    lines += rep["emulator_log"]
    _emit(args, rep, lines)
    return 0


# -- analysis -----------------------------------------------------------------------------------------
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
    from .diagnose.report import region_lines

    lines = [f"{series.source}: {cmp.t.size} samples against model {cmp.model_name} ({cmp.model_source})",
             f"model error {cmp.error:.3g} (about 1 when the model explains the data; per view: "
             + ", ".join(f"{k} {v:.3g}" for k, v in cmp.error_per_view.items()) + ")"]
    lines += region_lines(cmp.regions, 12) or ["no region leaves the model's confidence band"]
    for note in series.notes + cmp.notes:
        lines.append(f"note: {note}")
    return lines


def load_series(args, model, truth: bool = True, read=None, steps=None):
    """``read``: the file's reading begun by :func:`_read_early` (or None). A command the analysis
    assumes (the recording has none: the model's own stands in) is said on stderr, whatever the
    output format, besides the report's notes and its ``command`` field. ``steps``: the
    command's :class:`~service.progress.Steps`, told of the reading (its phase ends when the
    next begins)."""
    from .diagnose import load as dload

    path = args.recording
    _check_recording(path)
    if steps is not None:
        steps(f"reading {Path(path).name}")
    series = dload.load_recording(path, spec=args.measurement, time_field=args.time, device=args.device,
                                  Ts=model.Ts, model=model, segment=args.segment, truth=truth,
                                  rec=None if read is None else read.result())
    note = dload.command_note(series)
    if note is not None:
        if steps is not None:
            steps.close()                   # the note on a line of its own, not inside a bar
        print(f"noiselab {args.command}: {note}", file=sys.stderr, flush=True)
    return series


def _read_early(args, truth: bool):
    """A noiselab recording read in a forked child (:meth:`service.parallel.Pool.submit`) while this
    process imports the analysis and loads the model: on 10^6 samples the reading takes 3 s and
    the imports 1.2 s, one after the other before (the series ready 1.0 s sooner, 5.2 s -> 4.1 s
    over 6 paired runs; the pickled arrays' trip costs 0.3 s). None for foreign recordings and missing files;
    an error in the reading is raised where :func:`load_series` would raise it (the child's
    failure is redone here), after the model's and the outputs' checks as before."""
    if args.measurement or args.time or not args.recording:
        return None
    try:
        _check_recording(args.recording)
    except BadInput:
        return None
    from .nodes.rosbag import bag_kind
    if bag_kind(args.recording) is not None:
        return None
    from . import parallel
    from .diagnose.load import noiselab_kinds
    from .nodes import mcapio
    path, kinds = args.recording, noiselab_kinds(truth)
    return parallel.Pool().submit(lambda: mcapio.read_recording(path, kinds=kinds))


def _reading_early(args, body) -> int:
    """``body(args, read)`` of a command that reads a recording (the truth only for the views: an
    .rrd or a PNG), its reading begun first (:func:`_read_early`) and stopped if not used."""
    read = _read_early(args, truth=bool(args.rrd or args.png))
    try:
        return body(args, read)
    finally:
        if read is not None:
            read.cancel()                   # not asked for (an error came first): the child stops


def _check_recording(path: str):
    """A recording is a file, or a rosbag2 bag directory (its ``metadata.yaml`` beside the storage files)."""
    p = Path(path)
    if p.is_dir():
        if (p / "metadata.yaml").is_file():
            return
        raise BadInput(f"{path}: is a directory, not an MCAP recording or a rosbag2 bag directory (no metadata.yaml)")
    if not p.is_file():
        raise BadInput(f"{path}: no such file")


def cmd_analyze(args) -> int:
    if args.live:
        from .nodes.analyzer import cmd_analyze_live
        return cmd_analyze_live(args)
    if not args.recording:
        raise BadInput("give a RECORDING.mcap (or --live)")
    return _reading_early(args, _analyze_cmd)


def _analyze_cmd(args, read) -> int:
    from .progress import Steps, wanted

    with Steps("noiselab analyze", wanted(args.progress, args.json)) as steps:
        rep, lines = _analyze(args, read, steps)
    _emit(args, rep, lines)
    return 0


def _analyze(args, read, steps) -> tuple[dict, list[str]]:
    """The analysis of ``args.recording``, its phases shown on ``steps``: (report, lines)."""
    from .diagnose.compare import auto_burn, compare

    model = load_model(args.model)
    png = png_path(args)
    check_out(args.rrd, args.force)
    check_out(png, args.force)
    series = load_series(args, model, truth=bool(args.rrd or png), read=read, steps=steps)
    burn = auto_burn(series.starts_at_rest, series.u) if args.burn == "auto" else \
        int(round(float(args.burn) / model.Ts))
    steps(f"comparing {series.y.shape[0]} samples with {Path(args.model).name}")
    cmp = compare(model, series.t, series.y, series.u, truth=series.truth, burn=burn,
                  level=series.starts_at_rest, free_start=not series.starts_at_rest)
    cmp.recording = series.source
    extra = {}
    if args.rrd:
        from viewers.rerun_log import log_comparisons
        steps(f"writing {args.rrd}")
        with writing(args.rrd):
            log_comparisons([cmp], args.rrd)
        extra["rrd"] = args.rrd
    if png:
        from viewers.summary_png import write_summary_png
        steps(f"writing {png}")
        with writing(png):
            write_summary_png([cmp], png)
        extra["png"] = png
    rep = analysis_report(cmp, series, extra)
    return rep, report_lines(cmp, series) + [f"wrote {extra[k]}" for k in ("rrd", "png") if k in extra]


# -- diagnosis ----------------------------------------------------------------------------------------
def cmd_diagnose(args) -> int:
    return _reading_early(args, _diagnose_cmd)


def _diagnose_cmd(args, read) -> int:
    from .progress import Steps, wanted

    # --verbose logs the search on stderr line by line: no bar between its lines
    show = False if args.verbose else wanted(args.progress, args.json)
    with Steps("noiselab diagnose", show, unit=" fits") as steps:
        rep, lines = _diagnose(args, read, steps)
    _emit(args, rep, lines)
    return 0


def _diagnose(args, read, steps) -> tuple[dict, list[str]]:
    """The diagnosis of ``args.recording``, its phases shown on ``steps``: (report, lines)."""
    from .diagnose.diagnose import diagnose
    from .diagnose.report import diagnosis_json, diagnosis_lines

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
        from viewers.rerun_log import log_comparisons
        steps(f"writing {args.rrd}")
        with writing(args.rrd):
            log_comparisons(comps, args.rrd)
        extra["rrd"] = args.rrd
    if png:
        from viewers.summary_png import write_summary_png
        steps(f"writing {png}")
        with writing(png):
            write_summary_png(comps, png)
        extra["png"] = png
    return diagnosis_json(rep, series, extra), diagnosis_lines(rep, series, extra)


def cmd_demo(args) -> int:
    check_out_dir(args.out)
    if args.story == "imu":
        from .demo_imu import cmd_imu_demo
        return cmd_imu_demo(args)
    from .demo import cmd_demo as run
    if args.duration is None:
        args.duration = 1200.0
    return run(args)


def _burn(text):
    """'auto' or seconds >= 0 (:func:`seconds_arg`), kept as text."""
    if text != "auto":
        try:
            seconds_arg(zero=True)(text)
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(
                f"expected 'auto' or seconds >= 0 and <= {SECONDS_MAX:g}, got {text!r}") from None
    return text


# -- entry point --------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="noiselab", description="Live emulator and model checker for noisy sensors and actuators.")
    p.add_argument("--version", action="version", version=f"noiselab {__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    sp = sub.add_parser("predict", help="predicted steady-state statistics of a model")
    sp.add_argument("model", help="model file (TOML) or built-in scenario name (seed, seed-nominal, ...)")
    sp.add_argument("--json", action="store_true", help="machine-readable output")
    sp.set_defaults(func=cmd_predict)

    ss = sub.add_parser("simulate", help="simulate a model as fast as possible into an MCAP recording")
    ss.add_argument("model", help="model file (TOML) or built-in scenario name")
    ss.add_argument("--duration", type=seconds_arg(), required=True, help="seconds of signal")
    ss.add_argument("--seed", type=_seed, default=0, help="random seed (default 0)")
    ss.add_argument("--out", help="output .mcap, or the bag directory with --format ros2 "
                                  "(default recordings/<name>-seed<N>[.mcap])")
    ss.add_argument("--format", choices=("mcap", "ros2"), default="mcap",
                    help="mcap: noiselab's JSON MCAP (the wire contract); ros2: a rosbag2 bag (MCAP storage, CDR; "
                         "sensor_msgs/msg/Imu for an IMU model, sensor_msgs/msg/JointState otherwise)")
    ss.add_argument("--force", action="store_true", help="overwrite an existing output file")
    ss.add_argument("--progress", action="store_true", help="show the progress bar even when not on a terminal")
    ss.add_argument("--json", action="store_true", help="machine-readable summary")
    ss.set_defaults(func=cmd_simulate)

    se = sub.add_parser("emulate", help="real-time emulator: publish truth, command, measurement over Zenoh")
    se.add_argument("model", help="model file (TOML) or built-in scenario name")
    se.add_argument("--duration", type=seconds_arg(), help="seconds of samples (default: until stopped)")
    se.add_argument("--seed", type=_seed, default=0, help="random seed (default 0)")
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

    sr = sub.add_parser("record", help="record Zenoh streams to MCAP")
    sr.add_argument("--key", default="noiselab/**", help="key expression to record (default noiselab/**)")
    sr.add_argument("--out", required=True, help="output .mcap")
    sr.add_argument("--duration", type=seconds_arg(), help="seconds (default: until SIGINT/SIGTERM)")
    sr.add_argument("--force", action="store_true", help="overwrite an existing output file")
    sr.add_argument("--json", action="store_true", help="machine-readable summary on stdout")
    add_transport_args(sr)
    sr.set_defaults(func=cmd_record)

    sv = sub.add_parser("recover", help="salvage every intact message of an unfinished MCAP file")
    sv.add_argument("broken", help="the unfinished (or damaged) .mcap")
    sv.add_argument("--out", "-o", required=True, help="the repaired .mcap to write")
    sv.add_argument("--force", action="store_true", help="overwrite an existing output file")
    sv.add_argument("--json", action="store_true", help="machine-readable summary")
    sv.set_defaults(func=cmd_recover)

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

    so = sub.add_parser("router", help="a Zenoh router in this process")
    so.add_argument("--duration", type=seconds_arg(), help="seconds (default: until stopped)")
    add_transport_args(so)
    so.set_defaults(func=cmd_router)

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
    sa.add_argument("--segment", type=_segment, metavar="N",
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

    sd = sub.add_parser("diagnose", help="which physical effect is missing from the model: rank, fit, add")
    sd.add_argument("recording", help="the .mcap to diagnose")
    sd.add_argument("--model", required=True, help="model file (TOML) or built-in scenario name")
    sd.add_argument("--fit-out", metavar="FITTED.toml", help="write the extended model file here")
    sd.add_argument("--rrd", help="write the Rerun recording (one revision per added effect) here")
    sd.add_argument("--png", help="write the PNG summary here (default: next to --rrd)")
    sd.add_argument("--max-effects", type=count_arg(), default=3, metavar="K",
                    help="add at most K effects (default 3)")
    sd.add_argument("--device", help="device name in a noiselab recording with several devices")
    sd.add_argument("--measurement", metavar="TOPIC:FIELD",
                    help="foreign recordings (JSON MCAP or ROS bag): topic and field(s), e.g. /imu:angular_velocity.x")
    sd.add_argument("--time", metavar="FIELD",
                    help="foreign recordings: time field (s, ns if it ends in _ns, or a {sec, nanosec} stamp); default: "
                         "header.stamp (ROS), else log time (ROS) or publish_time (JSON)")
    sd.add_argument("--segment", type=_segment, metavar="N",
                    help="a recording whose source restarted (read as stream segments): analyse segment N, 1 = the "
                         "first (default: the one with the longest gap-free run)")
    sd.add_argument("--force", action="store_true", help="overwrite existing output files")
    sd.add_argument("--verbose", action="store_true", help="log the search on stderr")
    sd.add_argument("--json", action="store_true", help="machine-readable report")
    sd.add_argument("--progress", action="store_true",
                    help="show the progress on stderr even when it is not a terminal (never with --json or --verbose)")
    sd.set_defaults(func=cmd_diagnose)

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
    sm.add_argument("--seed", type=_seed, default=1, help="random seed (default 1)")
    sm.add_argument("--out", default="recordings", help="output directory (default recordings/)")
    sm.add_argument("--max-effects", type=count_arg(), default=3, metavar="K",
                    help="add at most K effects (default 3)")
    sm.add_argument("--force", action="store_true", help="overwrite existing demo files")
    sm.add_argument("--json", action="store_true", help="machine-readable summary")
    sm.add_argument("--progress", action="store_true",
                    help="show the progress on stderr even when it is not a terminal (never with --json)")
    sm.set_defaults(func=cmd_demo)

    sn = sub.add_parser("run", help="emulator and recorder as separate processes on loopback")
    sn.add_argument("model", help="model file (TOML) or built-in scenario name")
    sn.add_argument("--duration", type=seconds_arg(), required=True, help="seconds of samples")
    sn.add_argument("--seed", type=_seed, default=0, help="random seed (default 0)")
    sn.add_argument("--out", default="recordings", help="output directory (default recordings/)")
    sn.add_argument("--force", action="store_true", help="overwrite an existing output file")
    sn.add_argument("--speed", type=speed_arg(), default=1.0, metavar="X",
                    help="emulate X times faster than real time (default 1)")
    sn.add_argument("--no-analyze", action="store_true", help="do not start the live analysis node")
    sn.add_argument("--json", action="store_true", help="machine-readable summary")
    sn.set_defaults(func=cmd_run)

    from .commands import register_all
    register_all(sub)
    return p


_ZENOH_LOG = False


def _zenoh_log_to_stderr() -> None:
    """Zenoh's own log (``RUST_LOG=warn``, ``debug``, ...): it writes to file descriptor 1, so fd 1
    becomes stderr and Python's stdout keeps the real one (``--json`` output stays clean). Once per
    process, and only when stdout is the process's own (not replaced, e.g. by a test's capture)."""
    global _ZENOH_LOG
    if _ZENOH_LOG:
        return
    _ZENOH_LOG = True
    import zenoh
    if sys.stdout is sys.__stdout__ and sys.stdout is not None:
        sys.stdout.flush()
        enc, errors = sys.stdout.encoding, sys.stdout.errors
        out = os.dup(1)
        os.dup2(2, 1)
        sys.stdout = sys.__stdout__ = os.fdopen(out, "w", buffering=1, encoding=enc, errors=errors)
    zenoh.try_init_log_from_env()


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if os.environ.get("RUST_LOG"):
        _zenoh_log_to_stderr()
    try:
        return args.func(args)
    except _bad_input_types() as exc:
        print(f"noiselab: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("noiselab: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. `noiselab predict seed --json | head`
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
