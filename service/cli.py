"""The ``noiselab`` command line: the entry point and the mapping of errors to exit codes.

Exit codes (DESIGN.md): 0 success, 2 bad input (one line on stderr naming what is wrong),
1 a bug (a traceback). Every long-running command has a bound (``--duration``). Each subcommand
is a module of :mod:`noiselab.commands` (its flags and its body); this module builds the parser
from them and runs the one asked for.
"""

from __future__ import annotations

import argparse
import os
import sys

from . import one_blas_thread
from .commands import register_all
from .errors import BadInput
from .model import ModelError

one_blas_thread()          # before any command imports numpy: BLAS reads the thread count when numpy loads

__version__ = "0.1.0"


class _Lazy(Exception):
    """Stands in for an error class whose module was never imported (so nothing raised it)."""


def _loaded(module: str, name: str):
    mod = sys.modules.get(module)
    return getattr(mod, name) if mod is not None else _Lazy


def _bad_input_types():
    """The error classes the CLI prints as one line with exit 2. A class whose module no command
    imported cannot have been raised, and is not imported here to be caught (:class:`_Lazy`)."""
    McapIoError = _loaded("noiselab.recordings.errors", "McapIoError")
    RecordingExistsError = _loaded("noiselab.recordings.errors", "RecordingExistsError")
    SeriesError = _loaded("noiselab.recordings.errors", "SeriesError")
    TransportError = _loaded("noiselab.nodes.transport", "TransportError")
    WireError = _loaded("noiselab.wire", "WireError")
    AnalysisError = _loaded("noiselab.diagnose.results", "AnalysisError")
    DemoError = _loaded("noiselab.demo", "DemoError")
    StatsError = _loaded("noiselab.stats.errors", "StatsError")
    return (ModelError, BadInput, WireError, McapIoError, RecordingExistsError, TransportError,
            AnalysisError, SeriesError, StatsError, DemoError,
            FileNotFoundError, IsADirectoryError, PermissionError)


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own errors: one line, exit 2
        self.exit(2, f"noiselab: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="noiselab", description="Live emulator and model checker for noisy sensors and actuators.")
    p.add_argument("--version", action="version", version=f"noiselab {__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
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
