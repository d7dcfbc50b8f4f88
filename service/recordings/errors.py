"""The errors of reading and writing recordings, each a one-line message (the CLI's exit 2).

:class:`McapIoError` and its kinds for the MCAP files themselves; :class:`SeriesError` for a
recording that reads but cannot be made into the series the analysis takes (too few samples, a
sample period that is not the model's, a field that is not a number).
"""

from __future__ import annotations


def shown(text: str) -> str:
    """``text`` fit for a one-line message: control characters (a newline in a foreign file's
    topic) escaped as Python writes them, everything else (non-ASCII letters too) as it is."""
    text = str(text)
    return text if text.isprintable() else "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


class McapIoError(ValueError):
    """A recording that cannot be written or read as noiselab data (one-line message: whatever a
    file's topics or a library's error text hold, control characters come out escaped)."""

    def __str__(self) -> str:
        return shown(super().__str__())


class McapWriteError(McapIoError):
    """The output file cannot be written (disk full, a vanished directory, ...): the writer has
    ended; every later write raises this again. Not a bad message: a caller that skips bad
    messages stops on this one."""


class NotMcapError(McapIoError):
    """The file is not an MCAP file at all (no MCAP magic at its start)."""


class CorruptRecordingError(McapIoError):
    """A finished MCAP file whose data section is damaged (try :func:`recover`)."""


def salvage_hint(path) -> str:
    """The way out a user types, named in every corruption message."""
    return f"`noiselab recover {path} --out FIXED.mcap` salvages what comes before it"


class RecordingExistsError(FileExistsError):
    """The output path exists and overwriting was not asked for (``force=True``)."""

    def __str__(self) -> str:
        return f"{self.filename}: already exists; pass force=True (--force) to overwrite it"


class SeriesError(ValueError):
    """A recording that cannot be turned into a series for the analysis (one-line message)."""
