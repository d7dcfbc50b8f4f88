"""The replay node: republishes a recording's messages under their keys (topic without a leading
'/', or ``prefix/topic``), paced by publish_time (``speed`` x real time) or as fast as possible,
with congestion control BLOCK, so everything downstream works on recorded data as on live data.

Messages go out in publish_time order across topics (the order a live source published them:
for one sample truth, command, measurement), each topic in its recorded order, whatever order
the file holds them in: :func:`mcapio.iter_time_ordered` merges the topics as it reads (a
streaming k-way merge, memory about one chunk per topic). A file written with large per-topic
blocks (``noiselab simulate`` before it interleaved, or a foreign writer) thus replays like the
live stream it describes instead of one topic after another.

A ROS bag (rosbag2 directory, ``.mcap`` with the ``ros2`` profile or ``.db3``, ROS 1 ``.bag``:
:func:`rosbag.bag_kind`) is replayed too: each message of every topic, decoded by rosbags
(:func:`rosbag.iter_json`), is published as a JSON object of its fields by their ROS names
(nested messages as objects, so ``header.stamp`` is ``{"sec": ..., "nanosec": ...}``; arrays as
lists; NaN and infinities as null) under the topic without its leading '/', in log-time order and
paced by the bag's log time (the recorder's receive time, ns). Every message type is checked
decodable before the first put. These are not noiselab streams: no join point is served for them."""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass

import zenoh

from . import mcapio, rosbag, transport, wire


@dataclass
class ReplaySummary:
    path: str
    messages: int
    topics: dict
    wall_s: float
    complete: bool

    def as_dict(self) -> dict:
        return {"node": "replay", "path": self.path, "messages": self.messages, "topics": self.topics,
                "wall_s": self.wall_s, "complete": self.complete}


def replay_topics(path: str) -> list[str]:
    """The topics (without a leading ``/``) of a recording, from its summary (raises NotMcapError
    for a file that is not MCAP); an unfinished file is read for the topics of its intact messages.
    Payloads are not decoded: replay republishes them as recorded, whatever they hold. A ROS bag's
    topics, once every message type is known decodable (:func:`rosbag.bag_topics`)."""
    if rosbag.bag_kind(path) is not None:
        return rosbag.bag_topics(path)
    topics = mcapio.channel_topics(path)
    if topics is not None:
        return topics
    return sorted({channel.topic.lstrip("/") for _, channel, _ in mcapio.iter_messages(path)})


def _device_of(key: str) -> str | None:
    """The device name of a noiselab topic key, None for any other key."""
    try:
        return wire.parse_key(key)[0]
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


def _messages(path: str, report: mcapio.ScanReport):
    """(topic, pacing time ns, MCAP sequence or None, payload) of every message in publish order:
    an MCAP file's as recorded, paced by publish_time; a ROS bag's as JSON, paced by log time."""
    if rosbag.bag_kind(path) is not None:
        for topic, log_ns, data in rosbag.iter_json(path):
            yield topic, log_ns, None, data
        return
    for _, channel, message in mcapio.iter_time_ordered(path, report=report):
        yield channel.topic, message.publish_time, message.sequence, message.data


def run_replay(session: "zenoh.Session", path: str, *, speed: float | None = 1.0, prefix: str | None = None,
               stop: threading.Event | None = None, wait_subscribers: float = 0.0,
               log=sys.stderr) -> ReplaySummary:
    """Publish every message of ``path``; ``speed`` None = as fast as possible."""
    stop = stop or threading.Event()
    report = mcapio.ScanReport()
    pubs: dict[str, "zenoh.Publisher"] = {}
    counts: dict[str, int] = {}
    opts = dict(congestion_control=zenoh.CongestionControl.BLOCK)

    def publisher(topic: str):
        pub = pubs.get(topic)
        if pub is None:
            key = topic.lstrip("/")
            if prefix:
                key = f"{prefix.rstrip('/')}/{key}"
            pub = pubs[topic] = session.declare_publisher(key, **opts)
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
    if wait_subscribers > 0 and not transport.wait_matching(pubs.values(), wait_subscribers, stop, every=False):
        if not stop.is_set():
            print(f"noiselab replay: no subscriber matched within "
                  f"{wait_subscribers:g} s: starting anyway", file=log, flush=True)
    t_wall0 = None
    pub0 = None
    n = 0
    start = time.monotonic()
    for topic, at_ns, sequence, data in _messages(path, report):
        if stop.is_set():
            break
        if speed is not None:
            if t_wall0 is None:
                t_wall0, pub0 = time.monotonic_ns(), at_ns
            due = t_wall0 + int((at_ns - pub0) / speed)
            delay = due - time.monotonic_ns()
            if delay > 0:
                time.sleep(delay / 1e9)
        pub = publisher(topic)
        key = str(pub.key_expr)
        if key in started:
            started[key] = sequence
        elif key not in foreign and _joinable(key) and _seq_matches(data, sequence):
            with grow:
                started[key] = sequence
        else:
            foreign.add(key)                 # no join point: not a counted stream, or its MCAP sequence is not its seq
        pub.put(data)
        counts[topic] = counts.get(topic, 0) + 1
        n += 1
    for q in joins:
        q.undeclare()
    if not report.complete:
        print(f"noiselab replay: {path}: {report.note}", file=log, flush=True)
    return ReplaySummary(path=str(path), messages=n, topics=counts, wall_s=time.monotonic() - start,
                         complete=report.complete)
