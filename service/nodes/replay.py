"""The replay node: republishes a recording's messages under their keys (topic without a leading
'/', or ``prefix/topic``), paced by publish_time (``speed`` x real time) or as fast as possible,
with congestion control BLOCK, so everything downstream works on recorded data as on live data.

Messages go out in publish_time order across topics (the order a live source published them:
for one sample truth, command, measurement), each topic in its recorded order, whatever order
the file holds them in: :func:`mcapio.iter_time_ordered` merges the topics as it reads (a
streaming k-way merge, memory about one chunk per topic). A file written with large per-topic
blocks (``noiselab simulate`` before it interleaved, or a foreign writer) thus replays like the
live stream it describes instead of one topic after another."""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass

import zenoh

from . import mcapio, transport


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
    """The topics of a recording, from its summary (raises NotMcapError for a file that is not
    MCAP); an unfinished file is read for its devices' topics."""
    topics = mcapio.channel_topics(path)
    if topics is not None:
        return topics
    rec = mcapio.read_recording(path)
    return sorted({td.topic for dev in rec.devices.values() for td in dev.streams.values()})


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
    if wait_subscribers > 0 and not transport.wait_matching(pubs.values(), wait_subscribers, stop, every=False):
        if not stop.is_set():
            print(f"noiselab replay: no subscriber matched within "
                  f"{wait_subscribers:g} s: starting anyway", file=log, flush=True)
    t_wall0 = None
    pub0 = None
    n = 0
    start = time.monotonic()
    for schema, channel, message in mcapio.iter_time_ordered(path, report=report):
        if stop.is_set():
            break
        if speed is not None:
            if t_wall0 is None:
                t_wall0, pub0 = time.monotonic_ns(), message.publish_time
            due = t_wall0 + int((message.publish_time - pub0) / speed)
            delay = due - time.monotonic_ns()
            if delay > 0:
                time.sleep(delay / 1e9)
        publisher(channel.topic).put(message.data)
        counts[channel.topic] = counts.get(channel.topic, 0) + 1
        n += 1
    if not report.complete:
        print(f"noiselab replay: {path}: {report.note}", file=log, flush=True)
    return ReplaySummary(path=str(path), messages=n, topics=counts, wall_s=time.monotonic() - start,
                         complete=report.complete)
