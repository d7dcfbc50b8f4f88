"""Command-line arguments shared by the command line and the nodes, standard library only (the
command line builds its parser from them without loading a command's libraries).

Bounded numbers: every number a flag takes is read by one of these (argparse ``type=``), so nan,
inf, a negative count or a duration no timer can wait is a one-line usage error (exit 2).

The transport flags (:func:`add_transport_args`) of every node that opens a Zenoh session; what
they mean is :func:`noiselab.nodes.transport.build_config`'s.
"""

from __future__ import annotations

import argparse
import math

SECONDS_MAX = 1e9
"""The longest duration, timeout or period a flag takes, s (about 32 years): beyond any run, and
inside the range of the OS's timers (``threading.TIMEOUT_MAX`` is 9.2e9 s on Linux), so that a wait
or a sample count (duration / Ts) computed from it never overflows."""
SPEED_MIN, SPEED_MAX = 1e-3, 1e6
"""The pace of an emulation or a replay, times real time: the wall-clock period Ts / speed (Ts up to
a day) stays under :data:`SECONDS_MAX`; a million times real time is no pace at all (``simulate``
and ``replay --fast`` run as fast as they can)."""
COUNT_MAX = 1000
"""The largest count a flag takes (``--max-effects``: the catalogue has 13 effects; ``--wait-peers``)."""
DEFAULT_PORT = 7447
"""Zenoh's registered TCP port."""
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
"""Where a source listens and a sink connects when no flag or config file says otherwise."""


def bounded(lo, hi, *, lo_open: bool = False, integer: bool = False, what: str = "a number"):
    """An argparse ``type``: a finite number (an integer when ``integer``) from ``lo`` (excluded when
    ``lo_open``) to ``hi`` (None: no upper bound). argparse names the flag in its message."""
    want = f"{what} {'>' if lo_open else '>='} {lo:g}" + ("" if hi is None else f" and <= {hi:g}")

    def conv(text):
        try:
            v = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {want}, got {text!r}") from None
        ok = (integer or math.isfinite(v)) and (v > lo if lo_open else v >= lo) and (hi is None or v <= hi)
        if not ok:
            raise argparse.ArgumentTypeError(f"expected {want}, got {text!r}")
        return v
    return conv


def seconds_arg(zero: bool = False):
    """Seconds, > 0 (>= 0 with ``zero``) and at most :data:`SECONDS_MAX`."""
    return bounded(0.0, SECONDS_MAX, lo_open=not zero, what="seconds")


def speed_arg():
    """A pace, times real time, from :data:`SPEED_MIN` to :data:`SPEED_MAX`."""
    return bounded(SPEED_MIN, SPEED_MAX, what="a factor (times real time)")


def count_arg(lo: int = 1):
    """An integer from ``lo`` to :data:`COUNT_MAX`."""
    return bounded(lo, COUNT_MAX, integer=True, what="an integer")


def add_transport_args(parser: argparse.ArgumentParser) -> None:
    """The Zenoh flags of a node (emulate, record, replay, router, analyze --live)."""
    g = parser.add_argument_group("transport (Zenoh)")
    g.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help=f"endpoint to connect to, e.g. {DEFAULT_ENDPOINT} (repeatable)")
    g.add_argument("--listen", action="append", metavar="ENDPOINT",
                   help="endpoint to listen on, e.g. tcp/127.0.0.1:7448 (repeatable)")
    g.add_argument("--config", metavar="FILE", help="Zenoh JSON5 configuration file")
    g.add_argument("--mode", choices=("peer", "client"), default=None,
                   help="Zenoh session mode (default peer; a router is always 'router')")
    g.add_argument("--connect-timeout", type=seconds_arg(zero=True), default=5.0, metavar="S",
                   help="seconds to reach --connect endpoints before giving up (default 5)")
