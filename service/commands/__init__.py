"""The subcommands of ``noiselab``, one module per command.

Each module here defines ``register(sub)``: it adds its parser to the ``noiselab`` subparsers
``sub`` and sets ``func`` (the command; it returns the exit code). :func:`register_all` finds
them, so a new command is a new module and no edit of the CLI. A command module raises
:class:`noiselab.errors.BadInput` (or another ValueError the CLI maps) for bad input, never
imports :mod:`noiselab.cli`, and imports the libraries its command needs inside the command, so
that reading the flags (``noiselab --help``) loads none of them. Modules whose name starts with
``_`` are helpers shared by the commands, not commands.
"""

from __future__ import annotations

import importlib
import pkgutil

ORDER = ("predict", "simulate", "emulate", "control", "record", "recover", "replay", "router", "analyze", "diagnose",
         "demo", "run")
"""The order ``noiselab --help`` lists the commands in: the tour's order (model, recordings, live
nodes, analysis); any other command follows, by name."""


def register_all(sub) -> None:
    names = sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_"))
    for name in sorted(names, key=lambda n: (ORDER.index(n) if n in ORDER else len(ORDER), n)):
        importlib.import_module(f"{__name__}.{name}").register(sub)
