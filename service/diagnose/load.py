"""Turn a recording into regularly sampled arrays for the analysis, saying what was wrong with it.

:func:`load_recording` is the one entry: it tells a noiselab recording, a foreign JSON MCAP and a
ROS bag apart and calls the loader of each.

* noiselab recordings: the device's ``measurement`` (and ``command``, ``truth`` when present),
  aligned by seq; t = the payload's ``t``.
* foreign recordings: ``--measurement TOPIC:FIELD`` picks a field (dotted path, ``[i]`` for list
  items, a final ``.*`` for every numeric field below, e.g. ``/imu:linear_acceleration.x``,
  ``/joint_states:position[2]``, ``/imu:angular_velocity.*``); several FIELDs may be given
  comma-separated for a vector. One parser (:func:`parse_field_path`) serves both kinds:
  - a JSON MCAP: time from a field (``--time FIELD``, seconds, or ``FIELD_ns`` style integer ns
    when the name ends in ``_ns``, or a ``{sec, nanosec}`` stamp object, exact integer ns) or
    from the MCAP publish_time. A file's message is untrusted: parsed within the wire decoders'
    bounds (:func:`wire.loads`: size, nesting; NaN and Infinity are not JSON), its fields numbers
    within float64 (times in ns within int64), else one line naming the topic, the sample and
    the field. ``.*`` expands on the first message, in its key order.
  - a ROS bag (rosbag2 MCAP or SQLite3, a bag directory, a ROS 1 bag): decoded by
    :mod:`service.nodes.rosbag` (rosbags), time from ``header.stamp`` when the message has one,
    else ``--time FIELD``, else the bag's log time.
  Both then pass the same checks (magnitude, NaN, order, regular timing, the longest gap-free run).
  Without a model (``Ts`` None: the ``allan`` command) the sample period is the record's median
  step, said in a note; :attr:`Series.Ts` is the period the series was checked against.

Gaps (a missing seq, or a time step over 1.5 Ts) are never silently ignored: the analysis uses
the longest gap-free run and the notes say what was left out. A noiselab stream whose source
restarted (its seq went back: :class:`mcapio.TopicData` segments) is analysed one stream
segment at a time: the one with the longest gap-free run unless ``segment`` names another, and a
note gives every segment's length and when it began. Repeated messages (same seq, same sample) are
counted once and noted; the reader refuses a seq twice with different data that no restart explains. Without a
recorded command the analysis runs the model's own ``[command]``: ``Series.command`` and a note
say which. Irregular timing (steps that differ
from Ts by more than 0.1 % of Ts, or by more than 4 resolutions of the time field when that is
coarser) is reported; a recording whose median step differs from the model's Ts by more than 1 %
is rejected (wrong model or wrong field), noiselab recordings (payload ``t``) included.
Integer-ns times (publish_time, ``*_ns`` fields) stay integers until the first stamp is
subtracted (STYLE 13: epoch ns through float64 would keep only ~0.24 us).

Every value the analysis uses (measurement, command, truth) is at most
:data:`~service.bounds.MAGNITUDE_MAX` (1e50) in magnitude, the one bound of every number
noiselab computes with (a model file's too): the estimators square the data, sum the squares
over the record and square again (the spread of a variance estimate, the likelihood of a fit),
which must stay finite in float64. A larger value is refused here, naming the topic, the field
and the seq, instead of an overflow deep in an estimator.
"""

from __future__ import annotations

import re
import reprlib
from dataclasses import dataclass, field

import numpy as np

from ..bounds import MAGNITUDE_MAX
from ..nodes import mcapio, rosbag, wire
from .results import AnalysisError


@dataclass
class Series:
    t: np.ndarray                  # (N,) s, from the first kept sample's clock
    y: np.ndarray                  # (N, p)
    u: np.ndarray | None           # (N, m) recorded command or None
    truth: np.ndarray | None       # (N, n) or None
    source: str
    notes: list = field(default_factory=list)
    starts_at_rest: bool = False   # a noiselab stream from seq 0 (the emulator starts at rest)
    command: dict | None = None    # the command analysed (command_used), None when no model was given
    names: list | None = None      # a foreign recording's field per column of y (``.*`` expanded)
    units: list | None = None      # their units where the message type fixes them (ROS: REP 103), else None
    Ts: float | None = None        # s: the period the timing was checked against (the model's, or the median step)


_PATH_RE = re.compile(r"([^.\[\]]+)|\[(\d+)\]")
WILDCARD = rosbag.WILDCARD


def parse_field_path(path: str) -> tuple:
    """``a.b[2].c`` -> ``("a", "b", 2, "c")``; a final ``.*`` is :data:`WILDCARD` (every numeric
    field below). The one parser of field paths, JSON and ROS alike."""
    parts = tuple(int(idx) if idx else name for name, idx in _PATH_RE.findall(path))
    if not parts:
        raise AnalysisError(f"field {path!r}: empty field path")
    if WILDCARD in parts[:-1]:
        raise AnalysisError(f"field {path!r}: '*' stands only at the end of a path (e.g. linear_acceleration.*)")
    return parts


def _field_getter(path: str):
    """(JSON object -> the value at ``path``, its parts)."""
    parts = parse_field_path(path)
    return _getter_of(parts), parts


def _getter_of(parts: tuple):
    def get(obj):
        for p in parts:
            obj = obj[p]
        return obj
    return get


def _split_spec(spec: str) -> tuple[str, list[str]]:
    if ":" not in spec:
        raise AnalysisError(f"--measurement {spec!r}: expected TOPIC:FIELD (e.g. /imu:linear_acceleration.x)")
    topic, fields = spec.rsplit(":", 1)
    return topic, [f.strip() for f in fields.split(",") if f.strip()]


def noiselab_kinds(truth: bool = True) -> tuple[str, ...]:
    """The topics :func:`load_noiselab` reads."""
    return ("measurement", "command", "truth") if truth else ("measurement", "command")


def load_noiselab(path: str, device: str | None = None, truth: bool = True, Ts: float | None = None,
                  rec: mcapio.Recording | None = None, *, segment: int | None = None, model=None) -> Series:
    """``rec``: the file already read (``mcapio.read_recording(path, kinds=noiselab_kinds(truth))``).
    ``segment``: the stream segment to analyse (1-based, in file order; the CLI's ``--segment``)
    when the source restarted; None takes the one with the longest gap-free run. ``model``: the
    model the data are compared with (its Ts when ``Ts`` is None; its command is named when the
    recording has none)."""
    if Ts is None and model is not None:
        Ts = model.Ts
    if rec is None:
        rec = mcapio.read_recording(path, kinds=noiselab_kinds(truth))
    if not rec.devices:
        if not rec.complete:
            raise AnalysisError(_unfinished_without_measurement(path, rec))
        raise AnalysisError(f"{path}: no measurement topic (a topic ending in /measurement); for other "
                            "recordings give --measurement TOPIC:FIELD")
    try:
        dev = rec.device(device)
    except (KeyError, ValueError, mcapio.McapIoError):
        names = ", ".join(mcapio.shown(n) for n in sorted(rec.devices))
        raise AnalysisError(f"{path}: device {device!r} not found or ambiguous (devices: {names})") from None
    notes = [] if rec.complete else [f"the recording is unfinished: {rec.note}"]
    notes += [f"{mcapio.shown(td.topic)}: {td.duplicates} repeated message{'s' if td.duplicates > 1 else ''} "
              "(same seq, same sample) counted once" for td in dev.streams.values() if td.duplicates]
    if len(dev.measurement) < 2:
        raise AnalysisError(f"{path}: only {len(dev.measurement)} measurement samples")
    k, meas = _pick_segment(path, dev.measurement, segment, notes)
    seq = meas.seq
    keep = _longest_run(seq, notes, "measurement seq")
    y = meas.values[keep]
    t = meas.t[keep]
    if Ts is not None and t.size >= 2:
        _check_period(np.diff(t), Ts, f"{path}: {mcapio.shown(meas.topic)}", notes)
    u = _aligned(_same_segment(path, dev.command, dev.measurement, k, notes), seq[keep], notes, "command")
    x = _aligned(_same_segment(path, dev.truth, dev.measurement, k, notes), seq[keep], notes, "truth")
    if u is not None and np.isnan(u).any():
        raise AnalysisError(f"{path}: the command topic misses samples inside the analysed run")
    for td, v in ((meas, y), (dev.command, u), (dev.truth, x)):
        if v is not None:
            _check_magnitude(v, f"{path}: {mcapio.shown(td.topic)}", wire.VECTOR_FIELD[td.kind], seq[keep], "seq")
    command = command_used(model, None if u is None else dev.command.topic, notes)
    if Ts is None and t.size >= 2:       # the payload's t is the source's own k*Ts: its step is Ts
        Ts = float(np.median(np.diff(t)))
    return Series(t=t - t[0], y=y, u=u, truth=x, source=f"{path} [{mcapio.shown(dev.name)}]", notes=notes,
                  starts_at_rest=bool(seq[keep][0] == 0), command=command, Ts=Ts)


def _unfinished_without_measurement(path: str, rec: mcapio.Recording) -> str:
    """Why an unfinished file gives nothing to analyse: the reader's note (where it stopped), and
    the way to keep what it did read."""
    keep = (f"; `noiselab recover {path} --out FIXED.mcap` keeps the {rec.messages} messages read"
            if rec.messages else "")
    return f"{rec.note}; none of them is a measurement (a topic ending in /measurement){keep}"


ASSUMED_COMMAND = "no command topic in the recording: the analysis assumes"
"""How the note that names an assumed command begins (:func:`command_used`, :func:`command_note`)."""


def command_note(series: Series) -> str | None:
    """The note naming the command the analysis assumed for want of a recorded one, or None."""
    if not series.command or series.command.get("source") != "model":
        return None
    return next((n for n in series.notes if n.startswith(ASSUMED_COMMAND)), None)


def command_used(model, topic: str | None, notes: list) -> dict | None:
    """What the analysis takes as the plant's command, JSON-ready: ``{"source": "recording",
    "topic": ...}``, or ``{"source": "model", "kind": ..., <the [command] table's parameters>}``
    when the recording has no command topic (a sensor at rest has none); the latter is also said
    in ``notes``, since the model's own command then stands in for what was applied. None without
    a model, or when the model has no input."""
    if topic is not None:
        return {"source": "recording", "topic": topic}
    if model is None or model.m == 0:
        return None
    table = dict(model.to_dict().get("command") or {"kind": "none"})
    kind = table.pop("kind", "none")
    if kind in ("none", "external"):
        said = f"no command (zero input; the model's [command] kind = {kind!r})"
    else:
        said = f"the model's own command ([command] kind = {kind!r}, " + ", ".join(
            f"{k} = {v}" for k, v in table.items()) + ")"
    notes.append(f"{ASSUMED_COMMAND} {said}")
    return {"source": "model", "kind": kind, **table}


def _pick_segment(path: str, meas: mcapio.TopicData, segment: int | None, notes: list):
    """(index, TopicData) of the stream segment to analyse; a note when the source restarted."""
    segs = meas.segments
    if segment is not None and not (isinstance(segment, int) and 1 <= segment <= len(segs)):
        raise AnalysisError(f"{path}: --segment {segment!r} asked for, but {mcapio.shown(meas.topic)} has "
                            f"{len(segs)} stream segment{'s' if len(segs) > 1 else ''} (1..{len(segs)})")
    if len(segs) == 1:
        return 0, meas
    if segment is None:        # the longest gap-free run of all: a restart is a break (seq steps back)
        a = _best_run(meas.seq)[0]
        k = int(np.searchsorted(meas.starts, a, side="right")) - 1
    else:
        k = segment - 1
    notes.append(_restart_note(meas, k, chosen=segment is None))
    return k, meas.segment(k)


def _restart_note(td: mcapio.TopicData, k: int, chosen: bool) -> str:
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
    return (f"{mcapio.shown(td.topic)}: the source restarted {times} (seq back to {listed(back)} at log time "
            f"{listed(at, lambda s: f'{s:+.3f} s')} from the first message): {len(lens)} stream segments "
            f"of {listed(lens)} samples; analysed segment {k + 1} "
            + ("(the one with the longest gap-free run; --segment N takes segment N)" if chosen
               else f"(--segment {k + 1})"))


def _same_segment(path: str, td: mcapio.TopicData | None, meas: mcapio.TopicData, k: int, notes: list):
    """``td``'s segment ``k``, which goes with the measurement's segment ``k`` (a source restarts all
    its topics together). A topic read as one segment holds every seq once, so it gives any
    segment's samples by seq (:func:`_aligned`): a restarted source that sent the same samples
    again on it, as a deterministic command does, had them read as repeats (mcapio._streams)."""
    if td is None or len(td.segments) == 1:
        return td
    if len(td.segments) == len(meas.segments):
        return td.segment(k)
    why = (f"{mcapio.shown(td.topic)} has {len(td.segments)} stream segments, {mcapio.shown(meas.topic)} "
           f"{len(meas.segments)}: "
           "which of its samples go with the analysed ones is unclear")
    if td.kind == "truth":
        notes.append(f"{why}; the truth is not used")
        return None
    raise AnalysisError(f"{path}: {why}")


def _check_magnitude(values: np.ndarray, where: str, field, index: np.ndarray, label: str) -> None:
    """Refuse a value beyond +-MAGNITUDE_MAX (the module docstring) in one line naming ``where``
    (path and topic), the field (``field[j]`` of a vector field, or the j-th of a list of field
    names) and the sample's ``label`` (seq, or sample) ``index[i]``."""
    bad = np.abs(values) > MAGNITUDE_MAX
    if not bad.any():
        return
    i, j = (int(a) for a in np.argwhere(bad)[0])
    name = field[j] if isinstance(field, (list, tuple)) else f"{field}[{j}]"
    raise AnalysisError(f"{where}: {name} = {values[i, j]:.6g} at {label} {int(index[i])} is beyond "
                        f"+-{MAGNITUDE_MAX:g}, more than the analysis can square in float64 (wrong units or "
                        "a corrupted sample?)")


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


def _best_run(seq: np.ndarray) -> tuple[int, int]:
    """(start, stop) of the longest run of consecutive seqs (the first of equal ones)."""
    breaks = np.flatnonzero(np.diff(seq) != 1)
    starts = np.concatenate([[0], breaks + 1])
    ends = np.concatenate([breaks + 1, [seq.size]])
    i = int(np.argmax(ends - starts))
    return int(starts[i]), int(ends[i])


def _longest_run(seq: np.ndarray, notes: list, what: str) -> slice:
    breaks = np.flatnonzero(np.diff(seq) != 1)
    if breaks.size == 0:
        return slice(0, seq.size)
    a, b = _best_run(seq)
    missing = int(np.sum(np.clip(np.diff(seq)[breaks] - 1, 0, None)))
    notes.append(f"{what}: {breaks.size} gaps ({missing} samples missing); analysed the longest gap-free run, "
                 f"samples {a}..{b - 1} of {seq.size}")
    return slice(a, b)


def load_recording(path: str, *, spec: str | None = None, time_field: str | None = None,
                   device: str | None = None, Ts: float | None = None, model=None, segment: int | None = None,
                   truth: bool = True, rec: mcapio.Recording | None = None) -> Series:
    """The series of any recording noiselab reads: a noiselab MCAP (``device``, ``segment``,
    ``truth``, ``rec`` as for :func:`load_noiselab`), or with ``spec`` (``TOPIC:FIELD[,FIELD...]``)
    a foreign JSON MCAP or a ROS bag (:func:`load_foreign`). ``Ts`` None and no ``model``: the
    record's own step (:attr:`Series.Ts`)."""
    if spec is None:
        if time_field is not None:
            raise AnalysisError(f"--time {time_field!r} is for foreign recordings (with --measurement TOPIC:FIELD)")
        kind = rosbag.bag_kind(path)
        if kind is not None:
            with rosbag.open_bag(path) as reader:
                have = rosbag.topics(reader)
            listed = ", ".join(f"{t} ({m})" for t, m in list(have.items())[:12]) + (
                f", ... ({len(have)} in all)" if len(have) > 12 else "")
            raise AnalysisError(f"{path}: a {kind}: give --measurement TOPIC:FIELD (topics: {listed or 'none'})")
        return load_noiselab(path, device, truth=truth, Ts=Ts, rec=rec, segment=segment, model=model)
    if segment is not None:
        raise AnalysisError("--segment takes a stream segment of a noiselab recording whose source restarted; "
                            "a foreign recording (--measurement) has none")
    return load_foreign(path, spec, time_field, Ts, model=model)


def load_foreign(path: str, spec: str, time_field: str | None, Ts: float | None = None, *, model=None) -> Series:
    """The fields ``spec`` names of a JSON MCAP or a ROS bag (the module docstring). ``Ts``: the
    sample period the timing is checked against (None: the model's, else the record's median
    step, noted). ``model``: as for :func:`load_noiselab` (a foreign recording's command is never
    read: the model's own command is named in a note)."""
    if Ts is None and model is not None:
        Ts = model.Ts
    topic, fields = _split_spec(spec)
    paths = [(f, parse_field_path(f)) for f in fields]
    tpath = (time_field, parse_field_path(time_field)) if time_field else None
    if rosbag.bag_kind(path) is not None:
        got = rosbag.read_fields(path, topic, paths, tpath)
        what = f"{got.topic} ({got.msgtype})"
        if got.time_ns:
            raw, ns = got.time, True
        else:                                     # a numeric --time field: s, or ns by the name's _ns
            ns = time_field.endswith("_ns")
            raw = _time_array(got.time, ns, f"{path}: {what}", time_field)
        series = _foreign_series(path, spec, what, got.names, got.values, raw, ns, Ts, model, got.notes)
        series.units = got.units
        return series
    return _load_json(path, spec, topic, paths, tpath, Ts, model)


def _time_array(values: np.ndarray, ns: bool, where: str, name: str) -> np.ndarray:
    """A numeric time field's values as int64 ns (``ns``) or float64 s; a value that is not finite,
    or beyond int64 as ns, is refused in one line naming the sample."""
    if ns and values.dtype.kind in "iu":
        bad = values > np.iinfo(np.int64).max if values.dtype.kind == "u" else np.zeros(values.shape, bool)
    else:
        f = values.astype(np.float64)
        bad = ~np.isfinite(f) | ((np.abs(f) >= 2.0**63) if ns else False)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise AnalysisError(f"{where}: sample {k}: {name} = {values[k].item()!r} is not a number"
                            + (" of ns within int64" if ns else " within float64"))
    return values.astype(np.int64) if ns else values.astype(np.float64)


def _load_json(path: str, spec: str, topic: str, paths: list, tpath, Ts: float | None, model) -> Series:
    """A JSON MCAP's fields (:func:`load_foreign`)."""
    want = topic.lstrip("/")
    topic = mcapio.shown(topic)                               # as messages name it
    time_field = tpath[0] if tpath else None
    tget = _field_getter(time_field)[0] if time_field else None
    ns_time = tget is None or time_field.endswith("_ns")      # integer ns: publish_time or a *_ns field
    stamp_time = None                                         # a {sec, nanosec} object: decided on the first message
    getters: list | None = None
    names: list[str] = []
    ys, ts = [], []
    found_topic = False
    report = mcapio.ScanReport()
    for schema, channel, message in mcapio.iter_messages(path, report=report):
        if channel.topic.lstrip("/") != want:
            continue
        found_topic = True
        where = f"{path}: {topic}: sample {len(ys)}"
        try:          # a file's message is untrusted: bounded size and nesting (wire.loads)
            obj = wire.loads(message.data, where)
        except wire.WireError as e:
            enc = channel.message_encoding
            why = ("" if enc == "json" else
                   f" (message encoding {mcapio.shown(enc)!r}: only JSON topics are read"
                   + ("; a ROS 2 bag is read when its MCAP profile is 'ros2'" if enc == "cdr" else "") + ")")
            raise AnalysisError(str(e) + why) from None
        if getters is None:
            names, getters = _json_fields(path, topic, obj, paths)
            named = list(zip(names, getters)) + ([(time_field, tget)] if tget else [])
        got = []
        for name, g in named:
            try:
                got.append(g(obj))
            except (KeyError, IndexError, TypeError):
                raise AnalysisError(f"{path}: {topic}: field {name} not found in a message "
                                    f"({_keys_of(obj)})") from None
        ys.append([_number(v, False, where, name) for v, name in zip(got, names)])
        if tget is None:
            ts.append(_number(message.publish_time, True, where, "publish_time"))
            continue
        if stamp_time is None:
            stamp_time = isinstance(got[-1], dict)
            ns_time = ns_time or stamp_time
        ts.append(_stamp_ns(got[-1], where, time_field) if stamp_time else _number(got[-1], ns_time, where, time_field))
    if not found_topic:
        raise AnalysisError(f"{path}: no topic {topic!r} in the recording")
    notes = [] if report.complete else [f"the recording is unfinished: {report.note}"]
    y = np.asarray(ys, float).reshape(len(ys), len(names) or len(paths))
    raw = np.asarray(ts, np.int64) if ns_time else np.asarray(ts, float)
    return _foreign_series(path, spec, topic, names or [f for f, _ in paths], y, raw, ns_time, Ts, model, notes)


def _keys_of(obj) -> str:
    """A JSON message's keys, cut short, for a field-not-found message."""
    keys = sorted(obj) if isinstance(obj, dict) else []
    if not keys:
        return f"it is a {type(obj).__name__}"
    listed = ", ".join(k if len(k) <= 40 else k[:40] + "..." for k in keys[:12]) + (
        f", ... ({len(keys)} keys)" if len(keys) > 12 else "")
    return f"keys: {mcapio.shown(listed)}"


def _json_fields(path: str, topic: str, obj, paths: list) -> tuple[list[str], list]:
    """(column names, getters) of the field paths on a JSON message ``obj`` (the first one): a final
    ``*`` becomes every number below it, in the object's key order (or every item of a list)."""
    names, getters = [], []
    for text, parts in paths:
        if parts[-1] != WILDCARD:
            names.append(text)
            getters.append(_getter_of(parts))
            continue
        try:
            leaves = _json_leaves(_getter_of(parts[:-1])(obj), parts[:-1])
        except (KeyError, IndexError, TypeError):
            raise AnalysisError(f"{path}: {topic}: field {text} not found in a message ({_keys_of(obj)})") from None
        if not leaves:
            raise AnalysisError(f"{path}: {topic}: field {text}: no number below {text[:-2] or 'the message'}")
        for at in leaves:
            names.append("".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in at).lstrip("."))
            getters.append(_getter_of(at))
    return names, getters


def _json_leaves(v, at: tuple) -> list[tuple]:
    """The paths of the numbers in ``v`` (found at ``at``), depth first in key and item order."""
    if isinstance(v, dict):
        return [leaf for k, w in v.items() for leaf in _json_leaves(w, (*at, k))]
    if isinstance(v, list):
        return [leaf for j, w in enumerate(v) for leaf in _json_leaves(w, (*at, j))]
    return [at] if isinstance(v, (int, float)) and not isinstance(v, bool) else []


def _stamp_ns(v, where: str, name: str) -> int:
    """A ``{sec, nanosec}`` stamp object (ROS 2's ``builtin_interfaces/msg/Time`` as JSON; ROS 1's
    ``{secs, nsecs}`` too) as exact integer ns, sec * 10**9 + nanosec."""
    if isinstance(v, dict):
        sec, nsec = v.get("sec", v.get("secs")), v.get("nanosec", v.get("nsecs"))
        if (type(sec) is int and type(nsec) is int and 0 <= nsec < 1_000_000_000
                and -2**63 <= sec * 1_000_000_000 + nsec < 2**63):
            return sec * 1_000_000_000 + nsec
    raise AnalysisError(f"{where}: {name} = {mcapio.shown(reprlib.repr(v))} is not a {{sec, nanosec}} stamp "
                        "(integers, 0 <= nanosec < 10^9) as the first message's is")


def _foreign_series(path: str, spec: str, what: str, names: list[str], y: np.ndarray, raw: np.ndarray,
                    ns_time: bool, Ts: float | None, model, notes: list) -> Series:
    """The checks every foreign series passes, JSON or ROS: sample count, NaN, magnitude, time
    order, the period (``Ts``, or the median step when None), regular timing and the longest
    gap-free run. ``what``: the topic as messages name it (and its type); ``raw``: the times,
    int64 ns (``ns_time``) or float s."""
    where = f"{path}: {what}"
    if ns_time:                                   # subtract in integers, then to s
        t = (raw - raw.min()).astype(float) * 1e-9 if raw.size else raw.astype(float)
        resolution = 1e-9
    else:
        t = raw - raw.min() if raw.size else raw
        resolution = float(np.spacing(np.max(np.abs(raw)))) if raw.size else 0.0
    if y.shape[0] < 2:
        raise AnalysisError(f"{where}: only {y.shape[0]} samples")
    if not np.all(np.isfinite(y)):
        k = int(np.flatnonzero(~np.all(np.isfinite(y), axis=1))[0])
        raise AnalysisError(f"{where}: NaN or inf in the measurement (first at sample {k})")
    _check_magnitude(y, where, names, np.arange(y.shape[0]), "sample")
    order = np.argsort(t, kind="stable")
    if np.any(order != np.arange(t.size)):
        notes.append(f"{what}: timestamps out of order; sorted by time")
        t, y = t[order], y[order]
    if Ts is None:
        Ts = _record_step(t, where, what, notes)
    keep = _regular_run(t, Ts, notes, what, resolution)
    t, y = t[keep], y[keep]
    return Series(t=t - t[0], y=y, u=None, truth=None, source=f"{path} [{spec}]", notes=notes,
                  command=command_used(model, None, notes), names=list(names), Ts=Ts)


def _record_step(t: np.ndarray, where: str, what: str, notes: list) -> float:
    """The record's median sample step [s], the period of a series read without a model."""
    step = float(np.median(np.diff(t)))
    if not step > 0.0:
        raise AnalysisError(f"{where}: the median step between sample times is 0 (repeated stamps): no sample "
                            "period; give --time FIELD or --model")
    notes.append(f"{what}: no model: the sample period is the record's median step, Ts = {step:.6g} s")
    return step


def _number(v, ns: bool, where: str, name: str):
    """A foreign field's value as a float, or as integer ns (``ns``; numbers written as text
    too): anything else, or a value beyond float64 (int64 for ns), is refused in one line naming
    the field and the sample, its value cut short."""
    try:
        out = int(v) if ns else float(v)
        if ns and not -2**63 <= out < 2**63:
            raise OverflowError
        return out
    except (TypeError, ValueError, OverflowError):
        raise AnalysisError(f"{where}: {name} = {mcapio.shown(reprlib.repr(v))} is not a number"
                            + (" of ns within int64" if ns else " within float64")) from None


def _check_period(dt: np.ndarray, Ts: float, what: str, notes: list) -> None:
    """The record's sample step against the model's Ts: more than 1 % apart is an error; more than
    0.1 % (the regular-timing tolerance) a note, since the model's dynamics, noise densities and
    lags are then evaluated at a period the data do not have (a clock 0.5 % off moves a resonance
    by 0.5 % and shows in the ACF and PSD views)."""
    med = float(np.median(dt))
    if not np.isclose(med, Ts, rtol=0.01):
        raise AnalysisError(f"{what}: the median sample step is {med:.6g} s but the model's Ts is {Ts:g} s")
    ok = dt[dt < 1.5 * Ts]
    mean = float(np.mean(ok)) if ok.size else med
    if abs(mean / Ts - 1.0) > 1e-3:
        notes.append(f"{what}: the mean sample step is {mean:.6g} s, {(mean / Ts - 1.0) * 100:+.2g} % from the "
                     f"model's Ts = {Ts:g} s: the model is evaluated at its Ts (set [sampling] Ts to the "
                     "record's if its clock is right)")


def _regular_run(t: np.ndarray, Ts: float, notes: list, what: str, resolution: float = 1e-9) -> slice:
    dt = np.diff(t)
    _check_period(dt, Ts, what, notes)
    gaps = dt > 1.5 * Ts
    tol = max(1e-3 * Ts, 4.0 * resolution)
    jitter = np.abs(dt[~gaps] - Ts) > tol
    if np.any(jitter):
        notes.append(f"{what}: irregular timing: {int(jitter.sum())} steps differ from Ts by more than "
                     f"{tol / Ts * 100:.2g} % (std {np.std(dt[~gaps]) / Ts * 100:.2g} % of Ts, max "
                     f"{np.max(np.abs(dt[~gaps] - Ts)) / Ts * 100:.2g} %); analysed as if regular")
    if not np.any(gaps):
        return slice(0, t.size)
    seq = np.concatenate([[0], np.cumsum(np.where(gaps, np.round(dt / Ts), 1))]).astype(np.int64)
    return _longest_run(seq, notes, f"{what} time")
