"""Output files of every command and node: checked before any work, written so that a failure is
one line naming the file.

* :func:`check_out` (a file) and :func:`check_out_dir` (a directory, ``run`` and ``demo``): a
  directory or a file in the way, an existing file without ``--force``, a parent that cannot be
  made or a place where no file can be created is bad input (:class:`~noiselab.errors.BadInput`,
  exit 2) before the run, not after it.
* :func:`writing`: the OS errors of a write (disk full, ...) as one line naming the file.
* :func:`write_replacing`: a whole file written beside its target as ``<name>.partial`` and renamed
  over it when complete (``os.replace`` is atomic on POSIX), so a failed write leaves an existing
  file as it was and no partial file behind.
* :func:`png_path`: where the summary PNG of an ``--rrd`` goes.

Standard library only: the command line imports this module to read its flags.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from .errors import BadInput

PARTIAL_SUFFIX = ".partial"


def make_dir(path: str, d: Path) -> None:
    """Make directory ``d`` (and its parents) for the output ``path``: a file in the way, or a
    directory that cannot be made, is bad input naming it, before any work."""
    blocker = next((q for q in (d, *d.parents) if q.exists()), None)
    if blocker is not None and not blocker.is_dir():
        where = "is a file" if blocker == Path(path) else f"{blocker} is a file"
        raise BadInput(f"{path}: {where}, not a directory")
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise BadInput(f"{path}: cannot make its directory {d} ({e.strerror or e})") from None


def check_out_dir(path: str) -> None:
    """An output directory (``run``, ``demo``), made now if missing."""
    make_dir(path, Path(path))


def check_out(path: str | os.PathLike | None, force: bool) -> None:
    """An output file, checked before any work: a directory in its place, a parent that cannot be
    made, an existing file (without ``force``) or a file that cannot be created there (``/proc``, a
    read-only file system: tried by creating and removing it) is bad input now, not after the
    run. A missing parent directory is made. None or "" (no such output asked for) passes."""
    if not path:
        return
    path = str(path)
    p = Path(path)
    if p.is_dir():
        raise BadInput(f"{path}: is a directory; give a file name")
    make_dir(path, p.parent)
    if p.exists() and not force:
        raise BadInput(f"{path}: already exists (use --force to overwrite)")
    try:
        if p.exists():
            os.close(os.open(p, os.O_WRONLY | os.O_APPEND | os.O_NONBLOCK))   # opened, not changed
        else:
            os.close(os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))
            os.unlink(p)
    except OSError as e:
        raise BadInput(f"{path}: cannot write it ({e.strerror or e})") from None


@contextlib.contextmanager
def writing(path: str | os.PathLike):
    """Writing the output ``path`` (an .rrd, a PNG, a fitted model): an OS error (disk full, ...)
    is bad input naming the path and the error. (An .rrd's bytes are written by Python too,
    :func:`noiselab.viewers.rerun_log.log_comparisons`, so its errors are OSErrors.)"""
    try:
        yield
    except OSError as e:
        raise BadInput(f"{path}: cannot write it ({e.strerror or e})") from None


def write_replacing(path: str | os.PathLike, data: bytes | str) -> None:
    """``data`` (text is written as UTF-8) into ``path`` through ``<path>.partial`` beside it,
    renamed over ``path`` when complete: an existing file is replaced whole or not at all, and a
    failed write leaves no partial file. An OS error is one line naming ``path``."""
    part = Path(f"{path}{PARTIAL_SUFFIX}")
    raw = data.encode("utf-8") if isinstance(data, str) else data
    with writing(path):
        try:
            part.write_bytes(raw)
            os.replace(part, path)
        except OSError:
            part.unlink(missing_ok=True)
            raise


def png_path(args) -> str | None:
    """The summary PNG of a command with ``--rrd`` and ``--png``: ``--png``, else beside the
    ``--rrd`` (None without either); an .rrd path with no file name (``/``, ``.``) is bad input,
    not a traceback."""
    png = getattr(args, "png", None)
    if png or not args.rrd:
        return png or None
    try:
        return str(Path(args.rrd).with_suffix(".png"))
    except ValueError:
        raise BadInput(f"{args.rrd}: is a directory; give a file name") from None
