"""``noiselab run MODEL``: emulator, recorder (and the live analysis, and a controller for a model
whose command is ``external``) as separate processes on loopback."""

from __future__ import annotations

from pathlib import Path

from ..args import seconds_arg, speed_arg
from ..errors import BadInput
from ..outfiles import check_out_dir
from ._common import emit, load_model, seed_arg
from .control import add_controller_args, controller_spec, parse_controller


def register(sub) -> None:
    sn = sub.add_parser("run", help="emulator and recorder as separate processes on loopback")
    sn.add_argument("model", help="model file (TOML) or built-in scenario name")
    sn.add_argument("--duration", type=seconds_arg(), required=True, help="seconds of samples")
    sn.add_argument("--seed", type=seed_arg, default=0, help="random seed (default 0)")
    sn.add_argument("--out", default="recordings", help="output directory (default recordings/)")
    sn.add_argument("--force", action="store_true", help="overwrite an existing output file")
    sn.add_argument("--speed", type=speed_arg(), default=1.0, metavar="X",
                    help="emulate X times faster than real time (default 1)")
    sn.add_argument("--no-analyze", action="store_true", help="do not start the live analysis node")
    sn.add_argument("--controller", default=None, metavar="pid:KP,KI,KD",
                    help="closed loop (a model whose command is external): the controller started beside the "
                         "emulator (default: the model's [controller] table)")
    add_controller_args(sn)
    sn.add_argument("--json", action="store_true", help="machine-readable summary")
    sn.set_defaults(func=cmd_run)


def cmd_run(args) -> int:
    from ..nodes.runner import pipeline_lines, run_pipeline

    model = load_model(args.model)              # bad input fails here, before any process starts
    controller = _controller_flags(model, args)
    check_out_dir(args.out)
    rep = run_pipeline(args.model, model.name, duration=args.duration, seed=args.seed, out_dir=Path(args.out),
                       force=args.force, analyze=not args.no_analyze, speed=args.speed, controller=controller)
    emu, rec = rep["emulator"] or {}, rep["recorder"] or {}
    lines = [f"recording: {rep['recording']}"] + pipeline_lines(emu, rec, rep.get("controller"))
    an = rep.get("analysis") or {}
    if an.get("error") is not None:
        lines.append(f"analysis: model error {an['error']:.3g} against {args.model} ("
                     + ", ".join(f"{k} {v:.3g}" for k, v in an["error_per_view"].items()) + ")")
        lines += [f"wrote {an[k]}" for k in ("rrd", "png") if an.get(k)]
    lines += rep["emulator_log"]
    emit(args, rep, lines)
    return 0


def _controller_flags(model, args) -> list[str] | None:
    """The `noiselab control` flags of the run's controller (None: open loop). A model whose
    command is external needs one (`run` connects no other node to the emulator), and a
    controller needs such a model: either mismatch is bad input."""
    external = model.command.kind == "external"
    given = args.controller is not None or any(
        v is not None for v in (args.reference, args.amplitude, args.frequency_hz))
    if not external:
        if given:
            raise BadInput(f"{args.model}: --controller and --reference need a model whose [command] kind is "
                           f"\"external\", got {model.command.kind!r}")
        return None
    if args.controller is None and model.controller is None:
        raise BadInput(f"{args.model}: the command is external: give --controller pid:KP,KI,KD or a [controller] "
                       "table in the model")
    gains = None if args.controller is None else parse_controller(args.controller)
    spec = controller_spec(model, gains, args)
    flags = ["--pid", f"{spec.kp!r},{spec.ki!r},{spec.kd!r}", "--reference", spec.reference]
    if spec.reference in ("step", "sine"):
        flags += ["--amplitude", repr(spec.amplitude)]
    if spec.reference == "sine":
        flags += ["--frequency-hz", repr(spec.frequency_hz)]
    return flags
