"""One generated block of tests/bench/RESULTS.md, replaced in place between its markers (the
hand-written observations around it are kept), or appended under its heading the first time."""

from __future__ import annotations

from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "RESULTS.md"


def write_block(block: str, begin: str, end: str, heading: str, intro: str = "", path: Path = RESULTS) -> None:
    """``block`` (starting with ``begin``, ending with ``end``) in place of the one between those
    markers; without them, appended as ``heading``, ``intro`` (if any), ``block``."""
    text = path.read_text()
    if begin in text and end in text:
        a, b = text.index(begin), text.index(end) + len(end)
        text = text[:a] + block + text[b:]
    else:
        text = text.rstrip("\n") + "\n\n" + heading + "\n" + (intro + "\n" if intro else "\n") + block + "\n"
    path.write_text(text)
