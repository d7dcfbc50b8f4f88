"""Progress on stderr for the commands that run for tens of seconds (``tqdm``).

Where a bar is shown: on stderr only, never on stdout, and only when stderr is a terminal or the
command's ``--progress`` forces it (:func:`wanted`); a command with ``--json`` shows none (its
output is for a program, and so is its stderr's absence of bars).

Two shapes:

:class:`Progress`
    One bar of a known total (samples written, candidates evaluated), updated with the absolute
    count done.
:class:`Steps`
    A command's phases one after the other (reading the recording, the comparison, each step of
    a diagnosis): ``steps(label, done, total)`` shows the phase ``label`` with its count, closing
    the previous phase's bar when the label changes. A phase without a count (``total`` None)
    shows its label and, when it ends, its elapsed time. It is the diagnosis's progress callback
    (:func:`noiselab.diagnose.diagnose.diagnose`).

Both are safe where the diagnosis runs: tqdm's monitor thread is off (``monitor_interval = 0``),
so a process showing a bar stays single-threaded and may still fork
(:func:`noiselab.parallel.can_fork`); a bar is drawn only by the process that made it (a forked
child's copy ignores updates, which would draw over the parent's line); updates from worker
threads are serialised by a lock.
"""

from __future__ import annotations

import os
import sys
import threading
from typing import Self


def wanted(force: bool = False, json_output: bool = False) -> bool | None:
    """A command's ``enabled`` for its bars: False with ``--json``, True with ``--progress``, else
    None (shown when stderr is a terminal)."""
    if json_output:
        return False
    return True if force else None


def _shown(enabled: bool | None) -> bool:
    if enabled is not None:
        return bool(enabled)
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):       # no stderr, or closed
        return False


def _bar(**kwargs):
    """A tqdm bar on stderr without tqdm's monitor thread, as wide as the terminal (80 x 24 where
    it says 0 x 0, as a pseudo-terminal nobody sized does: tqdm would draw an empty line)."""
    from tqdm import tqdm

    class Bar(tqdm):
        monitor_interval = 0

    try:
        sized = os.get_terminal_size(sys.stderr.fileno()).columns > 0
    except (AttributeError, ValueError, OSError):     # not a terminal (a forced bar), or no fileno
        sized = False
    width = {"dynamic_ncols": True} if sized else {"ncols": 80, "nrows": 24}
    return Bar(file=sys.stderr, mininterval=0.2, **width, **kwargs)


class Progress:
    """A progress bar of ``total`` items on stderr (``tqdm``), labelled ``label``: shown when
    ``enabled`` is True, or when it is None and stderr is a terminal. ``unit``: what is counted
    (``unit_scale``: 1.2M rather than 1200000). ``leave``: the finished bar stays on its line.
    ``closes_at_total``: reaching ``total`` closes the bar (False: a total that may still
    :meth:`grow`; :meth:`close` ends it)."""

    def __init__(self, total: int | None, label: str, enabled: bool | None = None, *,
                 unit: str = " samples", unit_scale: bool = True, leave: bool = True,
                 closes_at_total: bool = True):
        self.total, self.label = total, label
        self.closes_at_total = closes_at_total
        self.enabled = _shown(enabled)
        self.done = 0
        self._pid = os.getpid()
        self._lock = threading.Lock()
        self._bar = None
        if self.enabled:
            fmt = "{desc} [{elapsed}]" if total is None else None
            self._bar = _bar(total=total, desc=label, unit=unit, unit_scale=unit_scale, leave=leave,
                             bar_format=fmt)

    def _mine(self) -> bool:
        return self._bar is not None and os.getpid() == self._pid

    def update(self, done: int) -> None:
        """``done`` items are finished so far (an absolute count; a smaller one than before is
        ignored). Reaching ``total`` closes the bar (``closes_at_total``)."""
        with self._lock:
            if done <= self.done:
                return
            if self._mine():
                self._bar.update(done - self.done)
            self.done = done
        if self.closes_at_total and self.total is not None and done >= self.total:
            self.close()

    def advance(self, n: int = 1) -> None:
        """``n`` more items are finished."""
        with self._lock:
            done = self.done + n
        self.update(done)

    def grow(self, n: int) -> None:
        """``n`` more items to do than the total said (a phase that learns its work as it goes)."""
        with self._lock:
            self.total = (self.total or 0) + n
            if self._mine():
                self._bar.total = self.total
                self._bar.bar_format = None           # the count, now that there is a total
                self._bar.refresh()

    def close(self) -> None:
        with self._lock:
            bar, self._bar = self._bar, None
        if bar is None:
            return
        if os.getpid() == self._pid:
            bar.close()
        else:
            bar.disable = True        # a forked child's copy: tqdm's close, and its __del__'s, draw nothing

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Steps:
    """A command's phases on stderr, one bar at a time, each ``prefix: label``: call
    ``steps(label, done=0, total=None)`` as a phase begins and as it advances; a new label ends
    the previous phase. Each finished phase stays as one line (its label, count and time), so
    the terminal keeps the run's outline. Thread-safe; ``enabled`` as :class:`Progress`'s;
    ``unit``: what a phase's count counts (e.g. " fits")."""

    def __init__(self, prefix: str, enabled: bool | None = None, unit: str = ""):
        self.prefix, self.unit = prefix, unit
        self.enabled = _shown(enabled)
        self._lock = threading.Lock()
        self._label: str | None = None
        self._bar: Progress | None = None

    def __call__(self, label: str, done: int = 0, total: int | None = None) -> None:
        if not self.enabled:
            return
        with self._lock:
            if label != self._label:
                if self._bar is not None:
                    self._bar.close()
                self._label = label
                self._bar = Progress(total, f"{self.prefix}: {label}", True, unit=self.unit, unit_scale=False,
                                     closes_at_total=False)
            bar = self._bar
            if total is not None and bar.total != total:
                bar.grow(total - (bar.total or 0))
        if done:
            bar.update(done)

    def close(self) -> None:
        """End the last phase."""
        with self._lock:
            bar, self._bar, self._label = self._bar, None, None
        if bar is not None:
            bar.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
