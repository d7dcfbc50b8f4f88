"""The file a recording writer fills, and what becomes of it when the writer finishes or fails."""

from __future__ import annotations

import os
import stat

from .errors import McapIoError, RecordingExistsError

PARTIAL_SUFFIX = ".partial"
"""Suffix of the file a writer fills while an older file of the same name is kept (see
:class:`Output`): ``run.mcap`` is written as ``run.mcap.partial`` and renamed when finished."""


def os_error(path: str, exc: OSError, doing: str) -> McapIoError:
    """An OSError as a one-line McapIoError naming the path and the OS error (errno text)."""
    why = exc.strerror or type(exc).__name__
    return McapIoError(f"{path}: {doing} ({why})")


class Output:
    """The file a writer fills, and what happens to it at the end.

    Nothing is ever lost: when ``path`` does not exist (always so without ``force``), the bytes go
    straight to ``path`` (created exclusively), so a writer killed mid-way leaves its unfinished
    file under the name the user gave, for :func:`recover`. When ``force`` replaces an existing
    regular file, the bytes go to ``path + PARTIAL_SUFFIX`` beside it and :meth:`commit` renames
    that over ``path`` (``os.replace``: atomic) only once the file is finished, so a write that
    fails leaves the old file as it was; a killed writer leaves the ``.partial`` file. A
    ``.partial`` that already exists is refused, not overwritten: it may be an unfinished recording
    of an earlier run (``suffix``: :func:`recover` uses its own, since the unfinished file it
    reads is often ``path.partial``). A ``path`` that is not a regular file (``/dev/null``, a FIFO) is written
    in place. OSErrors come out as one-line :class:`McapIoError` naming the path.
    """

    def __init__(self, path: str, force: bool, suffix: str = PARTIAL_SUFFIX) -> None:
        self.path = self.target = self.writing = path
        self.created = True
        if os.path.isdir(path):
            raise McapIoError(f"{path}: is a directory; give a file name")
        try:
            st = os.stat(path) if force else None
        except FileNotFoundError:
            st = None
        except OSError as e:
            raise os_error(path, e, "cannot write it") from None
        if st is not None and stat.S_ISREG(st.st_mode):
            self.target = os.path.realpath(path) if os.path.islink(path) else path
            self.writing = self.target + suffix
        mode = "wb" if st is not None and self.writing == path else "xb"
        self.created = mode == "xb"
        try:
            self.file = open(self.writing, mode)
        except FileExistsError:
            if self.writing == path:
                raise RecordingExistsError(17, "File exists", path) from None
            raise McapIoError(f"{self.writing}: exists (an unfinished recording of an earlier run?); "
                              f"salvage it with `noiselab recover {self.writing} --out FIXED.mcap` or "
                              f"delete it, then write {path} again") from None
        except OSError as e:
            raise os_error(self.writing, e, "cannot write it") from None

    @property
    def replaces(self) -> bool:
        """An older file at ``path`` is kept until :meth:`commit`."""
        return self.writing != self.target

    def commit(self) -> None:
        """Close the finished file (on disk first when it replaces one) and give it its name. An
        OSError is the caller's to handle (:meth:`abandon`: whether to keep the file is its call)."""
        if self.replaces:
            self.file.flush()
            os.fsync(self.file.fileno())
        self.file.close()
        if self.replaces:
            os.replace(self.writing, self.target)

    def abandon(self, keep: bool) -> None:
        """Close without committing; the file stays where it is if ``keep`` (else it is removed
        when this writer created it). An old file at ``path`` is never touched."""
        try:
            self.file.close()
        except OSError:
            pass
        if not keep and self.created:
            try:
                os.unlink(self.writing)
            except OSError:
                pass


# ------------------------------------------------------------------------------ writer

