"""ROS bags in: numeric fields of one topic as arrays, and every message as JSON for the replay.

Read with `rosbags <https://gitlab.com/ternaris/rosbags>`_ (``rosbags.highlevel.AnyReader``), which
decodes CDR (ROS 2) and ROS 1 serialization with the type store it builds from the message
definitions the bag carries (the standard ROS 2 types of its latest store stand in for a bag
without them, as rosbag2's SQLite3 storage wrote before Iron). Accepted: a rosbag2 directory
(``metadata.yaml`` and its storage files, split files included), one rosbag2 storage file (MCAP
with the ``ros2`` profile, or SQLite3 ``.db3``), a ROS 1 ``.bag``. :func:`bag_kind` tells them from
noiselab's own (JSON) MCAP files by their first bytes: the MCAP header's profile, the SQLite and
ROS 1 magic strings.

Field paths (parsed once, by the caller: :mod:`.foreign`) are resolved against the message
definition before any message is read, so a wrong path fails at once naming the fields the message
does have. ``name`` parts are fields, ``int`` parts index an array or a sequence, and a final
:data:`WILDCARD` stands for every numeric field below it, in message-definition order (``x, y, z`` of a
``geometry_msgs/msg/Vector3``; every element of a numeric array; a sequence's length is taken from
the first message and must not change).

Time: a ``builtin_interfaces/msg/Time`` (``header.stamp``, by default when the message has a
``std_msgs/msg/Header``, or a ``--time`` field of that type) is ``sec * 10**9 + nanosec`` in integer
ns, exact (float64 epoch ns would keep ~0.24 us); without either, the bag's log time (the receive
time the recorder wrote, ns). A header whose stamps are all equal (a driver that leaves them 0)
gives no time base: the log time is taken and a note says so.

Every problem is one line (:class:`RosbagError`, exit 2) naming the topic, its message type and
what is wrong: a topic not in the bag (the bag's topics and types are listed), no messages, a type
neither the bag nor the standard store defines, a missing or non-numeric field, a message that
does not decode or a storage rosbags cannot read (a truncated or corrupt file).
"""

from __future__ import annotations

import json
import math
import sqlite3
import struct
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cache, lru_cache
from operator import attrgetter, itemgetter
from pathlib import Path

import numpy as np

from ..errors import BadInput
from .fieldpaths import WILDCARD


ROS1_MAGIC = b"#ROSBAG V2.0\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
MCAP_MAGIC = b"\x89MCAP0\r\n"
TIME_TYPES = ("builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration")
NUMERIC = frozenset({"byte", "char", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64",
                     "float32", "float64"})
FIELD_UNITS = {
    ("sensor_msgs/msg/Imu", "angular_velocity"): "rad/s",
    ("sensor_msgs/msg/Imu", "linear_acceleration"): "m/s^2",
    ("sensor_msgs/msg/Imu", "orientation"): "1",
    ("sensor_msgs/msg/MagneticField", "magnetic_field"): "T",
    ("sensor_msgs/msg/Temperature", "temperature"): "degC",
    ("sensor_msgs/msg/FluidPressure", "fluid_pressure"): "Pa",
    ("sensor_msgs/msg/Range", "range"): "m",
    ("geometry_msgs/msg/TwistStamped", "twist.linear"): "m/s",
    ("geometry_msgs/msg/TwistStamped", "twist.angular"): "rad/s",
}
"""The units of standard messages' fields that their definitions fix (REP 103: SI units, rad/s
and m/s^2 for an IMU; the .msg files' comments for the others): (message type, field path
prefix) -> unit. A field not listed (a JointState's position is rad or m by joint) has none."""

_SUFFIX = {"rosbag2 MCAP file": ".mcap", "rosbag2 SQLite3 file": ".db3", "ROS 1 bag": ".bag"}


class RosbagError(BadInput):
    """A ROS bag, a topic or a field path that cannot be read, in one line."""


def bag_kind(path) -> str | None:
    """What ``path`` is, if a ROS bag: "rosbag2 directory", "rosbag2 MCAP file" (the MCAP header's
    profile is ``ros2``), "rosbag2 SQLite3 file", "ROS 1 bag"; None for anything else (noiselab's
    and other JSON MCAP files, a missing file)."""
    p = Path(path)
    if p.is_dir():
        return "rosbag2 directory" if (p / "metadata.yaml").is_file() else None
    try:
        with open(p, "rb") as f:
            head = f.read(len(ROS1_MAGIC))
            if head.startswith(ROS1_MAGIC):
                return "ROS 1 bag"
            if (head + f.read(len(SQLITE_MAGIC) - len(head))).startswith(SQLITE_MAGIC):
                return "rosbag2 SQLite3 file"
            if head.startswith(MCAP_MAGIC) and _mcap_profile(f) == "ros2":
                return "rosbag2 MCAP file"
    except OSError:
        return None
    return None


def _mcap_profile(f) -> str | None:
    """The profile of the MCAP header record (the file's first record), None if unreadable."""
    from mcap.exceptions import McapError
    from mcap.records import Header
    from mcap.stream_reader import StreamReader

    f.seek(0)
    try:
        first = next(iter(StreamReader(f, record_size_limit=1 << 16).records), None)
    except (McapError, EOFError, ValueError, struct.error, UnicodeDecodeError):
        return None
    return first.profile if isinstance(first, Header) else None


def _errors() -> tuple[type[BaseException], ...]:
    """What reading a truncated or corrupt bag raises: rosbags' own errors, and what its parsers let
    through on damaged bytes (found by corrupting bags of each storage: a length field read as a
    huge size gives OverflowError or MemoryError, a damaged ROS 1 index an AssertionError or a
    KeyError, a damaged SQLite page apsw's CorruptError)."""
    import apsw
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.serde import SerdeError
    from rosbags.typesys import TypesysError
    return (AnyReaderError, Reader1Error, Reader2Error, SerdeError, TypesysError, apsw.Error, sqlite3.Error,
            struct.error, EOFError, UnicodeDecodeError, KeyError, ValueError, OverflowError, AssertionError,
            MemoryError)


def _said(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:200] + "..."


@lru_cache(maxsize=1)
def standard_types():
    """rosbags' store of the standard ROS 2 message types (its latest distribution): the types of a
    bag that carries no definitions."""
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.LATEST)


@contextmanager
def open_bag(path):
    """An open ``AnyReader`` on the bag ``path``; what rosbags cannot open is a :class:`RosbagError`."""
    from rosbags.highlevel import AnyReader

    kind = bag_kind(path)
    if kind is None:
        raise RosbagError(f"{path}: not a ROS bag (a rosbag2 directory, .mcap with the ros2 profile or .db3 "
                          "file, or a ROS 1 .bag)")
    p = Path(path)
    want = _SUFFIX.get(kind)
    if want is not None and p.suffix != want:
        raise RosbagError(f"{path}: a {kind}, which rosbags reads only under a name ending in {want}")
    reader = AnyReader([p], default_typestore=standard_types())
    try:
        reader.open()
    except _errors() as e:
        raise RosbagError(f"{path}: a {kind} that rosbags cannot read (truncated or corrupt?): {_said(e)}") from None
    try:
        yield reader
    finally:
        try:
            reader.close()
        except _errors():
            pass


def topics(reader) -> dict[str, str]:
    """{topic: message type} of an open bag ("several types" when a topic carries more than one)."""
    return {name: info.msgtype or "several types" for name, info in sorted(reader.topics.items())}


def _listed(items: Sequence[str], most: int = 12) -> str:
    return ", ".join(items[:most]) + (f", ... ({len(items)} in all)" if len(items) > most else "")


# -- message types -----------------------------------------------------------------------------------
class _Topic:
    """One topic of an open bag with the store that decodes its type; ``where`` names it in errors."""

    def __init__(self, path, reader, topic: str):
        self.path = path
        have = topics(reader)
        name = next((t for t in have if t.lstrip("/") == topic.lstrip("/")), None)
        if name is None:
            listed = _listed([f"{t} ({m})" for t, m in have.items()]) or "none"
            raise RosbagError(f"{path}: no topic {topic!r} in the bag (topics: {listed})")
        self.name, self.msgtype = name, have[name]
        self.where = f"{path}: {name} ({self.msgtype})"
        if self.msgtype == "several types":
            types = sorted({c.msgtype for c in reader.connections if c.topic == name})
            raise RosbagError(f"{path}: {name} carries several message types ({', '.join(types)}): not read")
        self.connections = [c for c in reader.connections if c.topic == name]
        if not sum(c.msgcount for c in self.connections):
            raise RosbagError(f"{self.where}: no messages on the topic")
        self.store = store_for(reader, self.msgtype, self.where)
        self.decode = self.store.deserialize_cdr if reader.is2 else self.store.deserialize_ros1

    def fields(self, typename: str) -> list[tuple[str, tuple]]:
        return self.store.fielddefs[typename][1]


def store_for(reader, msgtype: str, where: str):
    """The type store that decodes ``msgtype``: the bag's own (its definitions), else the standard
    types; neither is a :class:`RosbagError`."""
    if msgtype in reader.typestore.fielddefs:
        return reader.typestore
    if msgtype in standard_types().fielddefs:
        return standard_types()
    raise RosbagError(f"{where}: the message type cannot be decoded: the bag holds no definition of it and it is "
                      "not a standard ROS 2 type")


def _node_name(node) -> str:
    from rosbags.interfaces import Nodetype
    kind, desc = node
    if kind == Nodetype.BASE:
        return desc[0]
    if kind == Nodetype.NAME:
        return desc
    sub, count = desc
    return f"{_node_name(sub)}[{count if kind == Nodetype.ARRAY else ''}]"


@dataclass
class _Leaf:
    """One column: its name, the steps from the message to it (attribute names, indices), the
    node it ends on; ``sequence``: a numeric sequence under ``.*``, one column per item (their
    count from the first message)."""
    text: str
    steps: tuple
    node: tuple
    sequence: bool = False


def _resolve(top: _Topic, text: str, parts: Sequence, what: str = "field") -> list[_Leaf]:
    """The leaves a field path names in ``top``'s message type (several for a final WILDCARD)."""
    from rosbags.interfaces import Nodetype
    from rosbags.typesys.base import normalize_fieldname

    node, steps, shown = (Nodetype.NAME, top.msgtype), [], ""
    for i, part in enumerate(parts):
        if part == WILDCARD:
            if i != len(parts) - 1:
                raise RosbagError(f"{top.where}: {what} {text!r}: '*' stands only at the end of a path")
            return _leaves(top, node, tuple(steps), shown, text)
        if isinstance(part, int):
            if node[0] not in (Nodetype.ARRAY, Nodetype.SEQUENCE):
                raise RosbagError(f"{top.where}: {what} {text!r}: {shown or 'the message'} is a {_node_name(node)}, "
                                  f"not an array: [{part}] does not apply")
            sub, count = node[1]
            if node[0] == Nodetype.ARRAY and part >= count:
                raise RosbagError(f"{top.where}: {what} {text!r}: {shown} has {count} items ([0]..[{count - 1}])")
            node, shown = sub, f"{shown}[{part}]"
            steps.append(part)
            continue
        if node[0] != Nodetype.NAME:
            raise RosbagError(f"{top.where}: {what} {text!r}: {shown} is a {_node_name(node)}, it has no field {part!r}")
        fields = top.fields(node[1])
        found = next((d for n, d in fields if n == part), None)
        if found is None:
            where = f"{shown} ({node[1]})" if shown else "the message"
            raise RosbagError(f"{top.where}: no {what} {text!r}: {where} has the fields "
                              f"{_listed([n for n, _ in fields], 20) or 'none'}")
        node, shown = found, f"{shown}.{part}" if shown else part
        steps.append(normalize_fieldname(part))
    return [_Leaf(text, tuple(steps), node)]


def _leaves(top: _Topic, node, steps: tuple, shown: str, text: str) -> list[_Leaf]:
    """Every numeric leaf below ``node`` in definition order (the expansion of ``shown.*``)."""
    from rosbags.interfaces import Nodetype
    from rosbags.typesys.base import normalize_fieldname

    out: list[_Leaf] = []

    def walk(node, steps, shown):
        kind, desc = node
        if kind == Nodetype.BASE:
            if desc[0] in NUMERIC:
                out.append(_Leaf(shown, steps, node))
        elif kind == Nodetype.NAME:
            for name, sub in top.fields(desc):
                walk(sub, (*steps, normalize_fieldname(name)), f"{shown}.{name}" if shown else name)
        elif kind == Nodetype.ARRAY:
            sub, count = desc
            for j in range(count):
                walk(sub, (*steps, j), f"{shown}[{j}]")
        elif desc[0][0] == Nodetype.BASE and desc[0][1][0] in NUMERIC:     # a numeric sequence
            out.append(_Leaf(shown, steps, node, sequence=True))
    walk(node, steps, shown)
    if not out:
        raise RosbagError(f"{top.where}: field {text!r}: {shown or 'the message'} ({_node_name(node)}) has no "
                          "numeric field")
    return out


def _getter(steps: tuple):
    """message -> the value at ``steps``: one ``attrgetter`` for a run of attribute names (C speed),
    an ``itemgetter`` for an index."""
    funcs, names = [], []
    for s in steps:
        if isinstance(s, int):
            if names:
                funcs.append(attrgetter(".".join(names)))
                names = []
            funcs.append(itemgetter(s))
        else:
            names.append(s)
    if names:
        funcs.append(attrgetter(".".join(names)))
    if len(funcs) == 1:
        return funcs[0]

    def get(m):
        for f in funcs:
            m = f(m)
        return m
    return get


def _row_getter(leaves: list[_Leaf]):
    """message -> tuple of the leaves' values (one ``attrgetter`` call when no leaf has an index)."""
    if all(not any(isinstance(s, int) for s in leaf.steps) for leaf in leaves):
        get = attrgetter(*(".".join(leaf.steps) for leaf in leaves))
        return get if len(leaves) > 1 else (lambda m: (get(m),))
    gets = [_getter(leaf.steps) for leaf in leaves]
    return lambda m: tuple(g(m) for g in gets)


def _is_numeric(node) -> bool:
    from rosbags.interfaces import Nodetype
    return node[0] == Nodetype.BASE and node[1][0] in NUMERIC


def _header_stamp(top: _Topic) -> tuple | None:
    """The steps to ``header.stamp`` when the message has a ``std_msgs/msg/Header``-like header
    (a field ``header`` whose ``stamp`` is a ``builtin_interfaces/msg/Time``), else None."""
    from rosbags.interfaces import Nodetype
    header = next((d for n, d in top.fields(top.msgtype) if n == "header"), None)
    if header is None or header[0] != Nodetype.NAME:
        return None
    stamp = next((d for n, d in top.fields(header[1]) if n == "stamp"), None)
    return ("header", "stamp") if stamp == (Nodetype.NAME, TIME_TYPES[0]) else None


# -- reading a topic's fields ----------------------------------------------------------------------------
@dataclass
class RosFields:
    """The numeric fields of one topic: ``values`` (N, p) float64, one column per entry of
    ``names``; ``time`` (N,), int64 ns when ``time_ns`` (a stamp, the log time), else the ``--time``
    field's own values (numbers; the caller reads their unit from the field's name)."""
    topic: str
    msgtype: str
    names: list[str]
    values: np.ndarray
    time: np.ndarray
    time_ns: bool
    time_source: str
    notes: list = field(default_factory=list)

    @property
    def units(self) -> list[str | None]:
        """Each column's unit where the message definition fixes it (:data:`FIELD_UNITS`), else None."""
        return [field_unit(self.msgtype, name) for name in self.names]


def field_unit(msgtype: str, path: str) -> str | None:
    """The unit of the field ``path`` (as written: ``angular_velocity.x``) of a ``msgtype`` message,
    when :data:`FIELD_UNITS` knows it."""
    for (mt, prefix), unit in FIELD_UNITS.items():
        if mt == msgtype and (path == prefix or path.startswith(prefix + ".") or path.startswith(prefix + "[")):
            return unit
    return None


def read_fields(path, topic: str, fields: Sequence[tuple[str, tuple]],
                time_field: tuple[str, tuple] | None = None) -> RosFields:
    """The values of ``fields`` ((text, parts) of each field path) on ``topic`` of the bag ``path``,
    in the bag's log-time order, and their times (see the module docstring)."""
    from rosbags.interfaces import Nodetype

    with open_bag(path) as reader:
        top = _Topic(path, reader, topic)
        leaves = [leaf for text, parts in fields for leaf in _resolve(top, text, parts)]
        for leaf in leaves:
            if not leaf.sequence and not _is_numeric(leaf.node):
                raise RosbagError(f"{top.where}: field {leaf.text!r} is a {_node_name(leaf.node)}, not a number"
                                  + _hint(top, leaf))
        stamp, tget, source = None, None, "log time"
        if time_field is not None:
            (tleaf,) = _resolve(top, time_field[0], time_field[1], what="time field")
            if tleaf.node[0] == Nodetype.NAME and tleaf.node[1] in TIME_TYPES:
                stamp = tleaf.steps
            elif _is_numeric(tleaf.node):
                tget = _getter(tleaf.steps)
            else:
                raise RosbagError(f"{top.where}: time field {time_field[0]!r} is a {_node_name(tleaf.node)}, not a "
                                  "number or a builtin_interfaces/msg/Time")
            source = time_field[0]
        else:
            stamp = _header_stamp(top)
            source = "header.stamp" if stamp else source
        if stamp is not None:
            dotted = ".".join(stamp)
            tget = attrgetter(f"{dotted}.sec", f"{dotted}.nanosec")
        rows, times, n = _read(top, reader, leaves, tget)
    notes = []
    names = [name for leaf in leaves for name in
             ([f"{leaf.text}[{j}]" for j in range(n[leaf.text])] if leaf.sequence else [leaf.text])]
    values = np.asarray(rows, dtype=np.float64).reshape(len(rows), len(names))
    if stamp is not None:
        st = np.asarray(times, dtype=np.int64).reshape(len(times), 2)
        t = st[:, 0] * 1_000_000_000 + st[:, 1]
        if time_field is None and t.size > 1 and np.all(t == t[0]):
            notes.append(f"{top.name}: header.stamp is {int(t[0])} ns in every message: time from the bag's log "
                         "time (receive time) instead")
            t = np.asarray(_log_times(path, topic), np.int64)
            source = "log time"
        return RosFields(top.name, top.msgtype, names, values, t, True, source, notes)
    if tget is None:
        notes.append(f"{top.name} ({top.msgtype}) has no header.stamp: time from the bag's log time (receive "
                     "time; --time FIELD takes a field of the message)")
        return RosFields(top.name, top.msgtype, names, values, np.asarray(times, np.int64), True, source, notes)
    return RosFields(top.name, top.msgtype, names, values, np.asarray(times), False, source, notes)


def _hint(top: _Topic, leaf: _Leaf) -> str:
    from rosbags.interfaces import Nodetype
    if leaf.node[0] == Nodetype.NAME:
        subs = [n for n, d in top.fields(leaf.node[1])]
        return f" (its fields: {_listed(subs)}; {leaf.text}.* takes every numeric one)"
    if leaf.node[0] in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return f" ({leaf.text}[i] takes one item, {leaf.text}.* every item)"
    return ""


def _read(top: _Topic, reader, leaves: list[_Leaf], tget):
    """(rows, times, {sequence leaf: its length}) of every message on the topic; ``tget`` None = log time."""
    decode, msgtype = top.decode, top.msgtype
    rows: list = []
    times: list = []
    seqs = [leaf for leaf in leaves if leaf.sequence]
    lengths: dict[str, int] = {}
    try:
        messages = reader.messages(connections=top.connections)
        if not seqs:
            get = _row_getter(leaves)
            if tget is None:
                for _, log_ns, raw in messages:
                    rows.append(get(decode(raw, msgtype)))
                    times.append(log_ns)
            else:
                for _, _, raw in messages:
                    m = decode(raw, msgtype)
                    rows.append(get(m))
                    times.append(tget(m))
        else:
            gets = [(_getter(leaf.steps), leaf) for leaf in leaves]
            for _, log_ns, raw in messages:
                m = decode(raw, msgtype)
                row = []
                for g, leaf in gets:
                    v = g(m)
                    if leaf.sequence:
                        n = lengths.setdefault(leaf.text, len(v))
                        if len(v) != n:
                            raise RosbagError(f"{top.where}: sample {len(rows)}: {leaf.text} has {len(v)} items, the "
                                              f"first message {n} ({leaf.text}[i] takes one item)")
                        row.extend(v)
                    else:
                        row.append(v)
                rows.append(row)
                times.append(log_ns if tget is None else tget(m))
    except RosbagError:
        raise
    except IndexError:
        raise RosbagError(f"{top.where}: sample {len(rows)}: an index is beyond a sequence's length ("
                          f"{', '.join(leaf.text for leaf in leaves if any(isinstance(s, int) for s in leaf.steps))})"
                          ) from None
    except _errors() as e:
        raise RosbagError(f"{top.where}: message {len(rows)} cannot be read (truncated or corrupt bag?): "
                          f"{_said(e)}") from None
    return rows, times, lengths


def _log_times(path, topic: str) -> list[int]:
    """The log times (ns) of ``topic``'s messages, in the bag's order (no decoding)."""
    with open_bag(path) as reader:
        top = _Topic(path, reader, topic)
        try:
            return [log_ns for _, log_ns, _ in reader.messages(connections=top.connections)]
        except _errors() as e:
            raise RosbagError(f"{top.where}: the bag cannot be read (truncated or corrupt?): {_said(e)}") from None


# -- every message as JSON (replay) ----------------------------------------------------------------------
def bag_topics(path) -> list[str]:
    """The topics of the bag (without a leading '/'), every message type checked decodable first."""
    with open_bag(path) as reader:
        for c in reader.connections:
            store_for(reader, c.msgtype, f"{path}: {c.topic} ({c.msgtype})")
        return sorted({c.topic.lstrip("/") for c in reader.connections})


def iter_json(path) -> Iterator[tuple[str, int, bytes]]:
    """(topic, log time ns, the decoded message as compact JSON) of every message in log-time order.
    A message is a JSON object of its fields by their ROS names, nested messages as objects (so a
    ``header.stamp`` is ``{"sec": ..., "nanosec": ...}``), arrays as lists; NaN and infinities,
    which JSON cannot hold, are written null."""
    with open_bag(path) as reader:
        stores = {c.msgtype: store_for(reader, c.msgtype, f"{path}: {c.topic} ({c.msgtype})")
                  for c in reader.connections}
        decoders = {t: (s.deserialize_cdr if reader.is2 else s.deserialize_ros1) for t, s in stores.items()}
        dumps = json.JSONEncoder(separators=(",", ":"), allow_nan=False).encode
        names = {t: _field_names(s) for t, s in stores.items()}
        n = 0
        try:
            for con, log_ns, raw in reader.messages():
                obj = _jsonable(decoders[con.msgtype](raw, con.msgtype), names[con.msgtype])
                n += 1
                yield con.topic, log_ns, dumps(obj).encode()
        except _errors() as e:
            raise RosbagError(f"{path}: message {n} cannot be read (truncated or corrupt bag?): {_said(e)}") from None


def _jsonable(v, names):
    """``v`` as JSON-ready data; ``names(msgtype)``: (ROS name, attribute) of its fields."""
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, (bool, int, str)) or v is None:
        return v
    if isinstance(v, np.ndarray):
        if v.dtype.kind == "f" and not np.all(np.isfinite(v)):
            return [x if math.isfinite(x) else None for x in v.tolist()]
        return v.tolist()
    if isinstance(v, (list, tuple)):
        return [_jsonable(x, names) for x in v]
    if isinstance(v, np.generic):
        return _jsonable(v.item(), names)
    return {name: _jsonable(getattr(v, attr), names) for name, attr in names(v.__msgtype__)}


def _field_names(store):
    """msgtype -> (ROS name, Python attribute) of each of its fields, cached (a field named like a
    Python keyword has an attribute with a trailing underscore)."""
    from rosbags.typesys.base import normalize_fieldname

    @cache
    def names(msgtype: str) -> tuple[tuple[str, str], ...]:
        return tuple((n, normalize_fieldname(n)) for n, _ in store.fielddefs[msgtype][1])
    return names
