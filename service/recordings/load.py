"""Any recording as a series for the analysis, saying what was wrong with it.

:func:`load_recording` is the one entry: it tells a noiselab recording, a foreign JSON MCAP and a
ROS bag apart and calls the loader of each.

* noiselab recordings (:func:`load_noiselab`): the device's ``measurement`` (and ``command``,
  ``truth`` when present), aligned by seq; t = the payload's ``t``.
* foreign recordings (:func:`.foreign.load_foreign`): ``--measurement TOPIC:FIELD[,FIELD...]``
  picks fields (:mod:`.fieldpaths`) of a JSON MCAP or a ROS bag.

Every series then passes the checks of :mod:`.series` (magnitude, period, regular timing, the
longest gap-free run). A noiselab stream whose source restarted (its seq went back:
:class:`.recording.TopicData` segments) is analysed one stream segment at a time: the one with
the longest gap-free run unless ``segment`` names another, and a note gives every segment's
length and when it began. Repeated messages (same seq, same sample) are counted once and noted;
the reader refuses a seq twice with different data that no restart explains. Without a recorded
command the analysis runs the model's own ``[command]``: ``Series.command`` and a note say which.
A recording whose median step differs from the model's Ts by more than 1 % is rejected (wrong
model or wrong field), noiselab recordings (payload ``t``) included.
"""

from __future__ import annotations

import numpy as np

from .. import wire
from . import rosbag_in
from .errors import McapIoError, SeriesError, shown
from .foreign import load_foreign
from .reader import read_recording
from .recording import Recording, TopicData
from .series import (
    Series,
    best_run,
    check_magnitude,
    check_period,
    command_used,
    longest_run,
)


def noiselab_kinds(truth: bool = True) -> tuple[str, ...]:
    """The topics :func:`load_noiselab` reads."""
    return ("measurement", "command", "truth") if truth else ("measurement", "command")


def load_noiselab(path: str, device: str | None = None, truth: bool = True, Ts: float | None = None,
                  rec: Recording | None = None, *, segment: int | None = None, model=None) -> Series:
    """``rec``: the file already read (``read_recording(path, kinds=noiselab_kinds(truth))``).
    ``segment``: the stream segment to analyse (1-based, in file order; the CLI's ``--segment``)
    when the source restarted; None takes the one with the longest gap-free run. ``model``: the
    model the data are compared with (its Ts when ``Ts`` is None; its command is named when the
    recording has none)."""
    if Ts is None and model is not None:
        Ts = model.Ts
    if rec is None:
        rec = read_recording(path, kinds=noiselab_kinds(truth))
    if not rec.devices:
        if not rec.complete:
            raise SeriesError(_unfinished_without_measurement(path, rec))
        raise SeriesError(f"{path}: no measurement topic (a topic ending in /measurement); for other "
                            "recordings give --measurement TOPIC:FIELD")
    try:
        dev = rec.device(device)
    except (KeyError, ValueError, McapIoError):
        names = ", ".join(shown(n) for n in sorted(rec.devices))
        raise SeriesError(f"{path}: device {device!r} not found or ambiguous (devices: {names})") from None
    notes = [] if rec.complete else [f"the recording is unfinished: {rec.note}"]
    notes += [f"{shown(td.topic)}: {td.duplicates} repeated message{'s' if td.duplicates > 1 else ''} "
              "(same seq, same sample) counted once" for td in dev.streams.values() if td.duplicates]
    if len(dev.measurement) < 2:
        raise SeriesError(f"{path}: only {len(dev.measurement)} measurement samples")
    k, meas = _pick_segment(path, dev.measurement, segment, notes)
    seq = meas.seq
    keep = longest_run(seq, notes, "measurement seq")
    y = meas.values[keep]
    t = meas.t[keep]
    if Ts is not None and t.size >= 2:
        check_period(np.diff(t), Ts, f"{path}: {shown(meas.topic)}", notes)
    u = _aligned(_same_segment(path, dev.command, dev.measurement, k, notes), seq[keep], notes, "command")
    x = _aligned(_same_segment(path, dev.truth, dev.measurement, k, notes), seq[keep], notes, "truth")
    if u is not None and np.isnan(u).any():
        raise SeriesError(f"{path}: the command topic misses samples inside the analysed run")
    for td, v in ((meas, y), (dev.command, u), (dev.truth, x)):
        if v is not None:
            check_magnitude(v, f"{path}: {shown(td.topic)}", wire.VECTOR_FIELD[td.kind], seq[keep], "seq")
    command = command_used(model, None if u is None else dev.command.topic, notes)
    if Ts is None and t.size >= 2:       # the payload's t is the source's own k*Ts: its step is Ts
        Ts = float(np.median(np.diff(t)))
    return Series(t=t - t[0], y=y, u=u, truth=x, source=f"{path} [{shown(dev.name)}]", notes=notes,
                  starts_at_rest=bool(seq[keep][0] == 0), command=command, Ts=Ts)


def _unfinished_without_measurement(path: str, rec: Recording) -> str:
    """Why an unfinished file gives nothing to analyse: the reader's note (where it stopped), and
    the way to keep what it did read."""
    keep = (f"; `noiselab recover {path} --out FIXED.mcap` keeps the {rec.messages} messages read"
            if rec.messages else "")
    return f"{rec.note}; none of them is a measurement (a topic ending in /measurement){keep}"


def _pick_segment(path: str, meas: TopicData, segment: int | None, notes: list):
    """(index, TopicData) of the stream segment to analyse; a note when the source restarted."""
    segs = meas.segments
    if segment is not None and not (isinstance(segment, int) and 1 <= segment <= len(segs)):
        raise SeriesError(f"{path}: --segment {segment!r} asked for, but {shown(meas.topic)} has "
                            f"{len(segs)} stream segment{'s' if len(segs) > 1 else ''} (1..{len(segs)})")
    if len(segs) == 1:
        return 0, meas
    if segment is None:        # the longest gap-free run of all: a restart is a break (seq steps back)
        a = best_run(meas.seq)[0]
        k = int(np.searchsorted(meas.starts, a, side="right")) - 1
    else:
        k = segment - 1
    notes.append(_restart_note(meas, k, chosen=segment is None))
    return k, meas.segment(k)


def _restart_note(td: TopicData, k: int, chosen: bool) -> str:
    """One line: how often the source restarted, when (log time from the stream's first message),
    every segment's length, which one is analysed, and the flag that takes another."""
    starts = td.starts
    lens = np.diff(np.append(starts, len(td))).tolist()
    first_log = np.minimum.reduceat(td.log_ns, starts)          # each segment's first arrival, ns
    at = ((first_log[1:] - first_log[0]) / 1e9).tolist()
    back = td.seq[starts[1:]].tolist()

    def listed(xs, fmt=str, most=6):
        shown = ", ".join(fmt(x) for x in xs[:most])
        return shown + (f", ... ({len(xs)} in all)" if len(xs) > most else "")
    times = "once" if len(at) == 1 else f"{len(at)} times"
    return (f"{shown(td.topic)}: the source restarted {times} (seq back to {listed(back)} at log time "
            f"{listed(at, lambda s: f'{s:+.3f} s')} from the first message): {len(lens)} stream segments "
            f"of {listed(lens)} samples; analysed segment {k + 1} "
            + ("(the one with the longest gap-free run; --segment N takes segment N)" if chosen
               else f"(--segment {k + 1})"))


def _same_segment(path: str, td: TopicData | None, meas: TopicData, k: int, notes: list):
    """``td``'s segment ``k``, which goes with the measurement's segment ``k`` (a source restarts all
    its topics together). A topic read as one segment holds every seq once, so it gives any
    segment's samples by seq (:func:`_aligned`): a restarted source that sent the same samples
    again on it, as a deterministic command does, had them read as repeats (split_streams)."""
    if td is None or len(td.segments) == 1:
        return td
    if len(td.segments) == len(meas.segments):
        return td.segment(k)
    why = (f"{shown(td.topic)} has {len(td.segments)} stream segments, {shown(meas.topic)} "
           f"{len(meas.segments)}: "
           "which of its samples go with the analysed ones is unclear")
    if td.kind == "truth":
        notes.append(f"{why}; the truth is not used")
        return None
    raise SeriesError(f"{path}: {why}")


def _aligned(td, seq, notes, what):
    if td is None:
        return None
    if td.seq.size == seq.size and np.array_equal(td.seq, seq):
        return td.values
    j = np.clip(np.searchsorted(td.seq, seq), 0, td.seq.size - 1)    # td.seq is sorted
    idx = np.where(td.seq[j] == seq, j, -1)
    if np.any(idx < 0):
        notes.append(f"{what}: {int(np.sum(idx < 0))} samples of the analysed run are missing")
        if what == "truth":
            return None
        out = np.full((seq.size, td.values.shape[1]), np.nan)
        out[idx >= 0] = td.values[idx[idx >= 0]]
        return out
    return td.values[idx]


def load_recording(path: str, *, spec: str | None = None, time_field: str | None = None,
                   device: str | None = None, Ts: float | None = None, model=None, segment: int | None = None,
                   truth: bool = True, rec: Recording | None = None) -> Series:
    """The series of any recording noiselab reads: a noiselab MCAP (``device``, ``segment``,
    ``truth``, ``rec`` as for :func:`load_noiselab`), or with ``spec`` (``TOPIC:FIELD[,FIELD...]``)
    a foreign JSON MCAP or a ROS bag (:func:`load_foreign`). ``Ts`` None and no ``model``: the
    record's own step (:attr:`Series.Ts`)."""
    if spec is None:
        if time_field is not None:
            raise SeriesError(f"--time {time_field!r} is for foreign recordings (with --measurement TOPIC:FIELD)")
        kind = rosbag_in.bag_kind(path)
        if kind is not None:
            with rosbag_in.open_bag(path) as reader:
                have = rosbag_in.topics(reader)
            listed = ", ".join(f"{t} ({m})" for t, m in list(have.items())[:12]) + (
                f", ... ({len(have)} in all)" if len(have) > 12 else "")
            raise SeriesError(f"{path}: a {kind}: give --measurement TOPIC:FIELD (topics: {listed or 'none'})")
        return load_noiselab(path, device, truth=truth, Ts=Ts, rec=rec, segment=segment, model=model)
    if segment is not None:
        raise SeriesError("--segment takes a stream segment of a noiselab recording whose source restarted; "
                            "a foreign recording (--measurement) has none")
    return load_foreign(path, spec, time_field, Ts, model=model)


