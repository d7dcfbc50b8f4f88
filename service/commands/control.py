"""``noiselab control MODEL --pid KP,KI,KD``: the reference controller node (closed loop over Zenoh)."""

from __future__ import annotations

import math
import sys

from ..args import add_transport_args, bounded, seconds_arg
from ..bounds import MAGNITUDE_MAX
from ..errors import BadInput
from ._common import emit, load_model

REFERENCES = ("none", "step", "sine")


def parse_gains(text: str, flag: str = "--pid") -> tuple[float, float, float]:
    """``KP,KI,KD``: three finite numbers of magnitude at most 1e50 (else one line naming ``flag``).
    Parsed by the command, not by argparse: the flags argparse converts are single numbers."""
    try:
        gains = tuple(float(p) for p in text.split(","))
    except ValueError:
        gains = ()
    if len(gains) != 3 or not all(math.isfinite(g) and abs(g) <= MAGNITUDE_MAX for g in gains):
        raise BadInput(f"argument {flag}: expected KP,KI,KD (three finite numbers), got {text!r}")
    return gains


def parse_controller(text: str) -> tuple[float, float, float]:
    """``run --controller pid:KP,KI,KD`` (the one kind of controller there is)."""
    kind, sep, gains = text.partition(":")
    if kind != "pid" or not sep:
        raise BadInput(f"argument --controller: expected pid:KP,KI,KD, got {text!r}")
    return parse_gains(gains, "--controller")


def add_controller_args(parser) -> None:
    """The reference flags of a controller (``control``, and ``run`` with ``--controller``)."""
    parser.add_argument("--reference", choices=REFERENCES, default=None,
                        help="the reference r(t): none (0), step (amplitude from t = 0), sine (default: the "
                             "model's [controller] table, else none)")
    parser.add_argument("--amplitude", type=bounded(0, MAGNITUDE_MAX, lo_open=True), default=None, metavar="A",
                        help="reference amplitude > 0, output units (step, sine)")
    parser.add_argument("--frequency-hz", type=bounded(0, MAGNITUDE_MAX, lo_open=True), default=None, metavar="F",
                        help="reference frequency, Hz (sine)")


def controller_spec(model, gains, args):
    """The controller of ``model`` for the flags: ``gains`` (kp, ki, kd) or None for the model's
    ``[controller]`` table; the reference flags override the table's. Bad input: BadInput."""
    from dataclasses import replace

    from ..model.controller import ControllerSpec

    if model.command.kind != "external":
        raise BadInput(f"{model.source}: a controller needs [command] kind = \"external\", got {model.command.kind!r}")
    if (model.m, model.p) != (1, 1):
        raise BadInput(f"{model.source}: a PID controller needs one input and one output, got {model.m} and {model.p}")
    spec = model.controller
    if gains is not None:
        spec = ControllerSpec(*gains) if spec is None else replace(spec, kp=gains[0], ki=gains[1], kd=gains[2])
    if spec is None:
        raise BadInput(f"{model.source}: no controller: give its gains (KP,KI,KD) or a [controller] table in the model")
    ref = args.reference or spec.reference
    amp = args.amplitude if args.amplitude is not None else (spec.amplitude if ref == spec.reference else None)
    freq = args.frequency_hz if args.frequency_hz is not None else (spec.frequency_hz if ref == spec.reference else None)
    if ref in ("step", "sine") and amp is None:
        raise BadInput(f"--reference {ref} needs --amplitude")
    if ref == "sine" and freq is None:
        raise BadInput("--reference sine needs --frequency-hz")
    if ref == "none" and (args.amplitude is not None or args.frequency_hz is not None):
        raise BadInput("--amplitude and --frequency-hz need --reference step or sine")
    if ref == "step" and args.frequency_hz is not None:
        raise BadInput("--frequency-hz needs --reference sine")
    return replace(spec, reference=ref, amplitude=amp if ref != "none" else 0.0,
                   frequency_hz=freq if ref == "sine" else 0.0)


def register(sub) -> None:
    sc = sub.add_parser("control", help="reference controller: answer measurements with a PID's command (closed loop)")
    sc.add_argument("model", help="model file (TOML) or built-in scenario name, with [command] kind = \"external\"")
    sc.add_argument("--pid", default=None, metavar="KP,KI,KD",
                    help="PID gains (default: the model's [controller] table)")
    add_controller_args(sc)
    sc.add_argument("--duration", type=seconds_arg(), help="seconds of wall time at most (default: until the "
                                                            "stream's end, or stopped)")
    sc.add_argument("--json", action="store_true", help="machine-readable summary on stdout")
    add_transport_args(sc)
    sc.set_defaults(func=cmd_control)


def cmd_control(args) -> int:
    from ..nodes import transport
    from ..nodes.controller import READY_MARK, run_controller, summary_line
    from ..signals import stop_on_signals

    model = load_model(args.model)
    spec = controller_spec(model, None if args.pid is None else parse_gains(args.pid), args)
    stop = stop_on_signals()
    with transport.open_session(args, "sink") as session:
        ends = transport.endpoints_of(args, "sink")

        def ready() -> None:
            print(f"{READY_MARK} to noiselab/{model.name}/measurement: PID kp = {spec.kp:g}, ki = {spec.ki:g}, "
                  f"kd = {spec.kd:g}, reference {spec.reference}; answers on noiselab/{model.name}/control "
                  f"(listen {ends['listen']}, connect {ends['connect']})", file=sys.stderr, flush=True)

        s = run_controller(model, spec, session, duration=args.duration, stop=stop, ready=ready)
    emit(args, s.as_dict(), [summary_line(s)])
    return 0
