"""Subcommands that live in their own module, one module per command.

Each module here defines ``register(sub)``: it adds its parser to the ``noiselab`` subparsers
``sub`` and sets ``func`` (the command; it returns the exit code). :func:`register_all` finds
them, so a new command is a new module and no edit of the CLI. A command module raises
:class:`service.errors.BadInput` (or another ValueError the CLI maps) for bad input, never
imports :mod:`service.cli`.
"""

from __future__ import annotations

import importlib
import pkgutil


def register_all(sub) -> None:
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if not info.name.startswith("_"):
            importlib.import_module(f"{__name__}.{info.name}").register(sub)
