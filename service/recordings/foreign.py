"""A foreign recording's fields as a series: a JSON MCAP's or a ROS bag's (``TOPIC:FIELD``).

- A JSON MCAP: time from a field (``--time FIELD``, seconds, or ``FIELD_ns`` style integer ns
  when the name ends in ``_ns``, or a ``{sec, nanosec}`` stamp object, exact integer ns) or from
  the MCAP publish_time. A file's message is untrusted: parsed within the wire decoders' bounds
  (:func:`noiselab.wire.loads`: size, nesting; NaN and Infinity are not JSON), its fields numbers
  within float64 (times in ns within int64), else one line naming the topic, the sample and the
  field. ``.*`` expands on the first message, in its key order.
- A ROS bag (rosbag2 MCAP or SQLite3, a bag directory, a ROS 1 bag): decoded by
  :mod:`.rosbag_in` (rosbags), time from ``header.stamp`` when the message has one, else
  ``--time FIELD``, else the bag's log time.

Both then pass the same checks (:func:`_foreign_series`: magnitude, NaN, order, regular timing,
the longest gap-free run). Without a model (``Ts`` None: the ``allan`` command) the sample
period is the record's median step, said in a note. Integer-ns times (publish_time, ``*_ns``
fields) stay integers until the first stamp is subtracted (STYLE 13: epoch ns through float64
would keep only ~0.24 us).
"""

from __future__ import annotations

import reprlib

import numpy as np

from .. import wire
from . import rosbag_in
from .errors import SeriesError, shown
from .fieldpaths import WILDCARD, field_getter, getter_of, parse_field_path, split_spec
from .scan import ScanReport, iter_messages
from .series import Series, check_magnitude, command_used, record_step, regular_run


def load_foreign(path: str, spec: str, time_field: str | None, Ts: float | None = None, *, model=None) -> Series:
    """The fields ``spec`` names of a JSON MCAP or a ROS bag (the module docstring). ``Ts``: the
    sample period the timing is checked against (None: the model's, else the record's median
    step, noted). ``model``: as for :func:`load_noiselab` (a foreign recording's command is never
    read: the model's own command is named in a note)."""
    if Ts is None and model is not None:
        Ts = model.Ts
    topic, fields = split_spec(spec)
    paths = [(f, parse_field_path(f)) for f in fields]
    tpath = (time_field, parse_field_path(time_field)) if time_field else None
    if rosbag_in.bag_kind(path) is not None:
        got = rosbag_in.read_fields(path, topic, paths, tpath)
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
        raise SeriesError(f"{where}: sample {k}: {name} = {values[k].item()!r} is not a number"
                            + (" of ns within int64" if ns else " within float64"))
    return values.astype(np.int64) if ns else values.astype(np.float64)


def _load_json(path: str, spec: str, topic: str, paths: list, tpath, Ts: float | None, model) -> Series:
    """A JSON MCAP's fields (:func:`load_foreign`)."""
    want = topic.lstrip("/")
    topic = shown(topic)                               # as messages name it
    time_field = tpath[0] if tpath else None
    tget = field_getter(time_field)[0] if time_field else None
    ns_time = tget is None or time_field.endswith("_ns")      # integer ns: publish_time or a *_ns field
    stamp_time = None                                         # a {sec, nanosec} object: decided on the first message
    getters: list | None = None
    names: list[str] = []
    ys, ts = [], []
    found_topic = False
    report = ScanReport()
    for schema, channel, message in iter_messages(path, report=report):
        if channel.topic.lstrip("/") != want:
            continue
        found_topic = True
        where = f"{path}: {topic}: sample {len(ys)}"
        try:          # a file's message is untrusted: bounded size and nesting (wire.loads)
            obj = wire.loads(message.data, where)
        except wire.WireError as e:
            enc = channel.message_encoding
            why = ("" if enc == "json" else
                   f" (message encoding {shown(enc)!r}: only JSON topics are read"
                   + ("; a ROS 2 bag is read when its MCAP profile is 'ros2'" if enc == "cdr" else "") + ")")
            raise SeriesError(str(e) + why) from None
        if getters is None:
            names, getters = _json_fields(path, topic, obj, paths)
            named = list(zip(names, getters)) + ([(time_field, tget)] if tget else [])
        got = []
        for name, g in named:
            try:
                got.append(g(obj))
            except (KeyError, IndexError, TypeError):
                raise SeriesError(f"{path}: {topic}: field {name} not found in a message "
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
        raise SeriesError(f"{path}: no topic {topic!r} in the recording")
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
    return f"keys: {shown(listed)}"


def _json_fields(path: str, topic: str, obj, paths: list) -> tuple[list[str], list]:
    """(column names, getters) of the field paths on a JSON message ``obj`` (the first one): a final
    ``*`` becomes every number below it, in the object's key order (or every item of a list)."""
    names, getters = [], []
    for text, parts in paths:
        if parts[-1] != WILDCARD:
            names.append(text)
            getters.append(getter_of(parts))
            continue
        try:
            leaves = _json_leaves(getter_of(parts[:-1])(obj), parts[:-1])
        except (KeyError, IndexError, TypeError):
            raise SeriesError(f"{path}: {topic}: field {text} not found in a message ({_keys_of(obj)})") from None
        if not leaves:
            raise SeriesError(f"{path}: {topic}: field {text}: no number below {text[:-2] or 'the message'}")
        for at in leaves:
            names.append("".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in at).lstrip("."))
            getters.append(getter_of(at))
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
    raise SeriesError(f"{where}: {name} = {shown(reprlib.repr(v))} is not a {{sec, nanosec}} stamp "
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
        raise SeriesError(f"{where}: only {y.shape[0]} samples")
    if not np.all(np.isfinite(y)):
        k = int(np.flatnonzero(~np.all(np.isfinite(y), axis=1))[0])
        raise SeriesError(f"{where}: NaN or inf in the measurement (first at sample {k})")
    check_magnitude(y, where, names, np.arange(y.shape[0]), "sample")
    order = np.argsort(t, kind="stable")
    if np.any(order != np.arange(t.size)):
        notes.append(f"{what}: timestamps out of order; sorted by time")
        t, y = t[order], y[order]
    if Ts is None:
        Ts = record_step(t, where, what, notes)
    keep = regular_run(t, Ts, notes, what, resolution)
    t, y = t[keep], y[keep]
    return Series(t=t - t[0], y=y, u=None, truth=None, source=f"{path} [{spec}]", notes=notes,
                  command=command_used(model, None, notes), names=list(names), Ts=Ts)


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
        raise SeriesError(f"{where}: {name} = {shown(reprlib.repr(v))} is not a number"
                            + (" of ns within int64" if ns else " within float64")) from None


