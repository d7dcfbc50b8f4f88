"""The recording a command names: checked, read (begun early in a child process) and turned into a
series."""

from __future__ import annotations

import sys
from pathlib import Path

from ..errors import BadInput


def load_series(args, model, truth: bool = True, read=None, steps=None):
    """``read``: the file's reading begun by :func:`read_early` (or None). A command the analysis
    assumes (the recording has none: the model's own stands in) is said on stderr, whatever the
    output format, besides the report's notes and its ``command`` field. ``steps``: the
    command's :class:`~noiselab.progress.Steps`, told of the reading (its phase ends when the
    next begins)."""
    from ..recordings.load import load_recording
    from ..recordings.series import command_note

    path = args.recording
    check_recording(path)
    if steps is not None:
        steps(f"reading {Path(path).name}")
    series = load_recording(path, spec=args.measurement, time_field=args.time, device=args.device,
                            Ts=model.Ts, model=model, segment=args.segment, truth=truth,
                            rec=None if read is None else read.result())
    note = command_note(series)
    if note is not None:
        if steps is not None:
            steps.close()                   # the note on a line of its own, not inside a bar
        print(f"noiselab {args.command}: {note}", file=sys.stderr, flush=True)
    return series


def read_early(args, truth: bool):
    """A noiselab recording read in a forked child (:meth:`noiselab.parallel.Pool.submit`) while this
    process imports the analysis and loads the model, so the two overlap instead of following
    each other (on a long recording the reading is the larger part). None for foreign recordings
    and missing files; an error in the reading is raised where :func:`load_series` would raise it
    (the child's failure is redone here), after the model's and the outputs' checks."""
    if args.measurement or args.time or not args.recording:
        return None
    try:
        check_recording(args.recording)
    except BadInput:
        return None
    from ..recordings.rosbag_in import bag_kind
    if bag_kind(args.recording) is not None:
        return None
    from .. import parallel
    from ..recordings.load import noiselab_kinds
    from ..recordings.reader import read_recording
    path, kinds = args.recording, noiselab_kinds(truth)
    return parallel.Pool().submit(lambda: read_recording(path, kinds=kinds))


def reading_early(args, body) -> int:
    """``body(args, read)`` of a command that reads a recording (the truth only for the views: an
    .rrd or a PNG), its reading begun first (:func:`read_early`) and stopped if not used."""
    read = read_early(args, truth=bool(args.rrd or args.png))
    try:
        return body(args, read)
    finally:
        if read is not None:
            read.cancel()                   # not asked for (an error came first): the child stops


def check_recording(path: str):
    """A recording is a file, or a rosbag2 bag directory (its ``metadata.yaml`` beside the storage files)."""
    p = Path(path)
    if p.is_dir():
        if (p / "metadata.yaml").is_file():
            return
        raise BadInput(f"{path}: is a directory, not an MCAP recording or a rosbag2 bag directory (no metadata.yaml)")
    if not p.is_file():
        raise BadInput(f"{path}: no such file")
