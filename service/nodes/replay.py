"""The replay node: republishes a recording's messages under their keys (topic without a leading
'/', or ``prefix/topic``), paced by publish_time (``speed`` x real time) or as fast as possible,
with congestion control BLOCK, so everything downstream works on recorded data as on live data.

Messages go out in publish_time order across topics (the order a live source published them:
for one sample truth, command, measurement), each topic in its recorded order, whatever order
the file holds them in: :func:`iter_time_ordered` merges the topics as it reads (a
streaming k-way merge, memory about one chunk per topic). A file written with large per-topic
blocks (``noiselab simulate`` before it interleaved, or a foreign writer) thus replays like the
live stream it describes instead of one topic after another.

A ROS bag (rosbag2 directory, ``.mcap`` with the ``ros2`` profile or ``.db3``, ROS 1 ``.bag``:
:func:`rosbag_in.bag_kind`) is replayed too: each message of every topic, decoded by rosbags
(:func:`rosbag_in.iter_json`), is published as a JSON object of its fields by their ROS names
(nested messages as objects, so ``header.stamp`` is ``{"sec": ..., "nanosec": ...}``; arrays as
lists; NaN and infinities as null) under the topic without its leading '/', in log-time order and
paced by the bag's log time (the recorder's receive time, ns). Every message type is checked
decodable before the first put. These are not noiselab streams: no join point is served for them.

What a subscriber sees besides the payload (wire contract, "Zenoh encoding" and "Attachment"):
every put says its Zenoh encoding, a noiselab stream's ``application/json;<schema name>``
(:func:`transport.declare_stream`), a bag's message ``application/json;<ROS type>``, another MCAP
channel's from its message encoding and schema (:func:`_encoding`); and every sample of a noiselab
source carries the start this replay states for it (:class:`_Anchors`): the replay is a source
of its own, on today's wall clock, so a recorder of a replay writes publish_time = the replay's
start + round(t 1e9) beside its receive times, as it does for a live emulator."""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass

import zenoh

from .. import wire
from ..recordings import rosbag_in
from ..recordings.merge import iter_time_ordered
from ..recordings.scan import ScanReport, channel_topics, iter_messages
from . import transport


@dataclass
class ReplaySummary:
    path: str
    messages: int
    topics: dict
    wall_s: float
    complete: bool
    starts: dict        # device prefix (``noiselab/<name>``) -> start_time_ns this replay stated (the last)

    def as_dict(self) -> dict:
        return {"node": "replay", "path": self.path, "messages": self.messages, "topics": self.topics,
                "wall_s": self.wall_s, "complete": self.complete, "starts": self.starts}


ZENOH_ENCODINGS = {"json": "application/json", "protobuf": "application/protobuf", "cbor": "application/cbor",
                   "cdr": "application/cdr"}
"""MCAP message encodings (the MCAP registry's names) and the Zenoh encodings that name them; a
channel of any other encoding is put as Zenoh's default, ``zenoh/bytes``."""


def _encoding(message_encoding: str, schema_name: str | None) -> str | None:
    """The Zenoh encoding of a foreign channel's messages: ``<zenoh encoding>;<schema name>``
    (the schema suffix as noiselab's own puts carry it), None when Zenoh has no name for it."""
    enc = ZENOH_ENCODINGS.get(message_encoding)
    if enc is None or not schema_name:
        return enc
    return f"{enc};{schema_name}"


class _Anchors:
    """The start (wall-clock Unix ns) this replay states for each noiselab source it republishes,
    in the attachment of the source's samples (:func:`wire.encode_anchor`).

    A source's sample of time ``t`` (s from the source's start) is due, paced, at wall clock W;
    the source's start in the replay is W - t / speed, the wall clock at which its t = 0 falls
    (as fast as possible: W, the time of the put, t / speed -> 0). A recorder of the replay then
    writes publish_time = start + round(t 1e9): the replay's time base, at speed 1 each sample
    due when it is put. The start is fixed at the source's first message, and again where one of
    its streams begins again (its MCAP sequence goes back: a restarted source, which the reader
    gives segment after segment); a payload without a readable ``t`` counts as t = 0."""

    def __init__(self, speed: float | None):
        self.speed = speed
        self.starts: dict[str, int] = {}          # prefix -> start_time_ns
        self.attachment: dict[str, bytes] = {}    # prefix -> its encoded anchor
        self.last: dict[str, int] = {}            # key -> the MCAP sequence of its last message

    def of(self, key: str, kind: str, sequence: int | None, data: bytes, due_wall_ns: int) -> bytes | None:
        """The attachment of a message of noiselab stream ``key`` (of ``kind``) due at
        ``due_wall_ns``; None for the end of stream (anchored by its source's data, as the
        emulator sends it)."""
        if kind == wire.END:
            return None
        prefix = key.rsplit("/", 1)[0]
        last = self.last.get(key)
        if sequence is not None:
            self.last[key] = sequence
        if prefix in self.attachment and not (last is not None and sequence is not None and sequence <= last):
            return self.attachment[prefix]
        t = _time_of(data)
        rel = 0 if self.speed is None else round(t * 1e9 / self.speed)
        start = min(max(0, due_wall_ns - rel), wire.START_MAX)
        self.starts[prefix] = start
        att = self.attachment[prefix] = wire.encode_anchor(start)
        return att


def _time_of(data: bytes) -> float:
    """A payload's ``t`` (s, finite, >= 0; 0.0 when it has none: a replay does not judge payloads),
    read with the bounded parser."""
    try:
        obj = wire.loads(data, "replay")
    except ValueError:
        return 0.0
    t = obj.get("t") if isinstance(obj, dict) else None
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not (0.0 <= t < 2.0**62 / 1e9):
        return 0.0
    return float(t)


def replay_topics(path: str) -> list[str]:
    """The topics (without a leading ``/``) of a recording, from its summary (raises NotMcapError
    for a file that is not MCAP); an unfinished file is read for the topics of its intact messages.
    Payloads are not decoded: replay republishes them as recorded, whatever they hold. A ROS bag's
    topics, once every message type is known decodable (:func:`rosbag_in.bag_topics`)."""
    if rosbag_in.bag_kind(path) is not None:
        return rosbag_in.bag_topics(path)
    topics = channel_topics(path)
    if topics is not None:
        return topics
    return sorted({channel.topic.lstrip("/") for _, channel, _ in iter_messages(path)})


def _device_of(key: str) -> str | None:
    """The device name of a noiselab topic key, None for any other key."""
    try:
        return wire.parse_key(key)[0]
    except wire.WireError:
        return None


def _kind_of(key: str) -> str | None:
    """The kind of a noiselab topic key, None for any other key."""
    try:
        return wire.parse_key(key)[1]
    except wire.WireError:
        return None


def _joinable(key: str) -> bool:
    """A stream whose seq counts its messages (data kinds and health: not the end of stream)."""
    try:
        return wire.parse_key(key)[1] in (*wire.KINDS, wire.HEALTH, wire.CONTROL)
    except wire.WireError:
        return False


def _seq_matches(data: bytes, sequence: int | None) -> bool:
    """The message's MCAP sequence is its payload's seq (as noiselab's recorder writes it)."""
    if sequence is None:
        return False
    try:
        obj = wire.loads(data, "replay")
        return isinstance(obj, dict) and obj.get("seq") == sequence
    except ValueError:
        return False


def _messages(path: str, report: ScanReport):
    """(topic, pacing time ns, MCAP sequence or None, payload, Zenoh encoding or None) of every
    message in publish order: an MCAP file's as recorded, paced by publish_time, its channel's
    encoding (:func:`_encoding`); a ROS bag's as JSON, paced by log time, ``application/json;<type>``."""
    if rosbag_in.bag_kind(path) is not None:
        with rosbag_in.open_bag(path) as reader:
            types = rosbag_in.topics(reader)
        encodings = {topic: f"{wire.ZENOH_JSON};{msgtype}" if "/" in msgtype else wire.ZENOH_JSON
                     for topic, msgtype in types.items()}         # a ROS type has a '/'; "several types" none
        for topic, log_ns, data in rosbag_in.iter_json(path):
            yield topic, log_ns, None, data, encodings.get(topic, wire.ZENOH_JSON)
        return
    encodings: dict[int, str | None] = {}
    for schema, channel, message in iter_time_ordered(path, report=report):
        enc = encodings.get(channel.id, "")
        if enc == "":
            enc = encodings[channel.id] = _encoding(channel.message_encoding, schema.name if schema else None)
        yield channel.topic, message.publish_time, message.sequence, message.data, enc


def run_replay(session: zenoh.Session, path: str, *, speed: float | None = 1.0, prefix: str | None = None,
               stop: threading.Event | None = None, wait_subscribers: float = 0.0,
               log=sys.stderr) -> ReplaySummary:
    """Publish every message of ``path``; ``speed`` None = as fast as possible."""
    stop = stop or threading.Event()
    report = ScanReport()
    pubs: dict[str, zenoh.Publisher] = {}
    kinds: dict[str, str | None] = {}     # topic -> its noiselab kind (its publisher says the encoding), or None
    anchors = _Anchors(speed)
    encodings: dict[str, zenoh.Encoding] = {}
    counts: dict[str, int] = {}
    opts = {"congestion_control": zenoh.CongestionControl.BLOCK}

    def publisher(topic: str):
        """The topic's publisher: a noiselab stream's says its kind's encoding; another topic's
        puts say theirs, each put (:func:`_messages`)."""
        pub = pubs.get(topic)
        if pub is None:
            key = topic.lstrip("/")
            kind = _kind_of(key)
            if prefix:
                key = f"{prefix.rstrip('/')}/{key}"
            pub = pubs[topic] = (session.declare_publisher(key, **opts) if kind is None
                                 else transport.declare_stream(session, key, kind, **opts))
            kinds[topic] = kind
        return pub

    # declare every publisher first, so a subscriber can match them all before the first put
    for topic in replay_topics(path):
        publisher(topic)
    started: dict[str, int] = {}         # key -> the MCAP sequence (= payload seq) of its last put begun
    foreign: set[str] = set()
    grow = threading.Lock()               # a key added while the join queryable reads them

    def first_seqs() -> dict:
        with grow:
            return {k: s + 1 for k, s in started.items()}

    joins = [transport.serve_join(session, name, first_seqs)
             for name in sorted({_device_of(str(p.key_expr)) for p in pubs.values()} - {None})]
    if wait_subscribers > 0 and not transport.wait_matching(pubs.values(), wait_subscribers, stop, every=False) \
            and not stop.is_set():
        print(f"noiselab replay: no subscriber matched within {wait_subscribers:g} s: starting anyway",
              file=log, flush=True)
    pacer = _Pacer(speed)
    n = 0
    start = time.monotonic()
    for topic, at_ns, sequence, data, enc in _messages(path, report):
        if stop.is_set():
            break
        due_wall = pacer.wait(at_ns)
        pub = publisher(topic)
        key = str(pub.key_expr)
        if key in started:
            started[key] = sequence
        elif key not in foreign and _joinable(key) and _seq_matches(data, sequence):
            with grow:
                started[key] = sequence
        else:
            foreign.add(key)                 # no join point: not a counted stream, or its MCAP sequence is not its seq
        if (kind := kinds[topic]) is not None:
            pub.put(data, attachment=anchors.of(topic.lstrip("/"), kind, sequence, data, due_wall))
        else:
            _put_foreign(pub, data, enc, encodings)
        counts[topic] = counts.get(topic, 0) + 1
        n += 1
    for q in joins:
        q.undeclare()
    if not report.complete:
        print(f"noiselab replay: {path}: {report.note}", file=log, flush=True)
    return ReplaySummary(path=str(path), messages=n, topics=counts, wall_s=time.monotonic() - start,
                         complete=report.complete, starts=dict(anchors.starts))


class _Pacer:
    """The replay's pace: a message recorded at ``at_ns`` is put ``(at_ns - at_0) / speed`` after
    the first one (monotonic clock), ``speed`` None: at once. :meth:`wait` returns the wall-clock
    time (ns) it was due, beside the monotonic pacing: its stream's anchor."""

    def __init__(self, speed: float | None):
        self.speed = speed
        self.t_wall0 = self.pub0 = self.clock0 = None

    def wait(self, at_ns: int) -> int:
        if self.speed is None:
            return time.time_ns()
        if self.t_wall0 is None:
            self.t_wall0, self.pub0 = time.monotonic_ns(), at_ns
            self.clock0 = time.time_ns()           # the wall clock beside the monotonic pacing
        due = self.t_wall0 + int((at_ns - self.pub0) / self.speed)
        due_wall = self.clock0 + (due - self.t_wall0)
        delay = due - time.monotonic_ns()
        if delay > 0:
            time.sleep(delay / 1e9)
        return due_wall


def _put_foreign(pub: zenoh.Publisher, data: bytes, enc: str | None, encodings: dict[str, zenoh.Encoding]) -> None:
    """A message of a topic that is not a noiselab stream, with its own encoding (a
    ``zenoh.Encoding`` made once per string, kept in ``encodings``), or none."""
    if enc is None:
        pub.put(data)
        return
    if enc not in encodings:
        encodings[enc] = zenoh.Encoding(enc)
    pub.put(data, encoding=encodings[enc])
