"""What several commands share: the model a command names, the two integer flags, and the way a
command prints its result (one JSON document with ``--json``, else text lines)."""

from __future__ import annotations

import json

from ..args import bounded

seed_arg = bounded(0, None, integer=True, what="an integer seed")
segment_arg = bounded(1, None, integer=True, what="a segment number")
"""``--segment N``: a stream segment of a recording whose source restarted, 1 = the first; one
beyond the recording's segments is refused where they are known (the loader names their count)."""


def load_model(spec):
    """The model of ``spec`` (a file or a built-in scenario); the model package (scipy) is loaded
    here, by the commands that need it, not to read the flags."""
    from ..model import load_model as _load

    return _load(spec)


def emit(args, summary: dict, lines: list[str]) -> None:
    if args.json:
        print(json.dumps(summary), flush=True)
    else:
        for line in lines:
            print(line, flush=True)
