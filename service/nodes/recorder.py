"""The recorder node: subscribes to a key expression (default ``noiselab/**``) and writes every
sample it receives to MCAP (wire contract: one channel per key, JSON Schema, sequence = seq,
publish_time = the sample time t in ns, log_time = receive time, wall clock ns).

* A Zenoh callback only queues (key, payload, receive ns); the main thread decodes and writes.
* The chunk in progress is flushed every ``flush_s`` (default 0.25 s), so a SIGKILLed recorder
  loses at most the last ~0.25 s: the file lacks its footer, and `noiselab recover` (or any
  reader, which says the file is unfinished) gets every message up to the last flushed chunk.
* SIGINT/SIGTERM, ``duration`` or ``stop`` finish the file (summary, footer) cleanly, after
  writing what is still arriving (until the stream is quiet for 0.2 s, at most 2 s).
* Sequence bookkeeping per topic: first and last seq, count, gaps (a forward jump: the seqs
  skipped) and restarts (seq going back, e.g. a restarted emulator). A recorder started
  mid-stream reports the seqs before its first one as missing at start. They are printed on
  stop and stored in the file's metadata record ``noiselab.recorder`` (JSON strings).
"""

from __future__ import annotations

import json
import queue
import sys
import threading
import time
from dataclasses import dataclass, field

import zenoh

from . import mcapio, wire

QUIET_S = 0.2        # on stop: keep writing until no message arrived for this long ...
DRAIN_MAX_S = 2.0    # ... but at most this long (a live stream never goes quiet)


@dataclass
class TopicBook:
    """Sequence bookkeeping of one topic."""

    first_seq: int | None = None
    last_seq: int | None = None
    count: int = 0
    gaps: list = field(default_factory=list)        # (after_seq, missing)
    restarts: list = field(default_factory=list)    # (from_seq, to_seq)

    def see(self, seq: int) -> None:
        if self.first_seq is None:
            self.first_seq = seq
        elif seq > self.last_seq + 1:
            self.gaps.append((self.last_seq, seq - self.last_seq - 1))
        elif seq <= self.last_seq:
            self.restarts.append((self.last_seq, seq))
        self.last_seq = seq
        self.count += 1

    @property
    def missing(self) -> int:
        return sum(m for _, m in self.gaps)

    def as_dict(self) -> dict:
        return {"first_seq": self.first_seq, "last_seq": self.last_seq, "count": self.count,
                "missing_at_start": self.first_seq or 0, "gaps": [list(g) for g in self.gaps],
                "missing": self.missing, "restarts": [list(r) for r in self.restarts]}


@dataclass
class RecorderSummary:
    out: str
    topics: dict
    messages: int
    malformed: int
    wall_s: float

    def as_dict(self) -> dict:
        return {"node": "record", "out": self.out, "messages": self.messages, "malformed": self.malformed,
                "wall_s": self.wall_s, "topics": {k: v.as_dict() for k, v in self.topics.items()}}

    def lines(self) -> list[str]:
        out = [f"recorded {self.messages} messages to {self.out} in {self.wall_s:.1f} s"]
        for topic, b in sorted(self.topics.items()):
            d = b.as_dict()
            text = f"  {topic}: {b.count} messages, seq {b.first_seq}..{b.last_seq}"
            if d["missing_at_start"]:
                text += f", started at seq {b.first_seq} (seqs 0..{b.first_seq - 1} not recorded)"
            text += f", {b.missing} missing in {len(b.gaps)} gaps" if b.gaps else ", no gaps"
            if b.restarts:
                text += f", {len(b.restarts)} restarts (seq went back)"
            out.append(text)
        if self.malformed:
            out.append(f"  {self.malformed} malformed payloads skipped")
        return out


def _kind_of_key(key: str) -> str | None:
    kind = key.rsplit("/", 1)[-1]
    return kind if kind in wire.ALL_KINDS else None


def _seq_t(payload: bytes, kind: str, key: str) -> tuple[int, float]:
    if kind == wire.HEALTH:
        obj = wire.decode_health(payload, topic=key)
        return obj["seq"], float(obj["t"])
    if kind == wire.ANALYSIS:
        obj = wire.decode_analysis(payload, topic=key)
        return obj["seq"], float(obj["t"])
    obj = wire.decode(payload, kind, topic=key)
    return obj["seq"], obj["t"]


def run_recorder(session: "zenoh.Session", key_expr: str, out: str, *, duration: float | None = None,
                 force: bool = False, stop: threading.Event | None = None, flush_s: float = 0.25,
                 chunk_size: int = 64 * 1024, ready: threading.Event | None = None,
                 log=sys.stderr) -> RecorderSummary:
    """Record until ``duration`` (wall seconds) or ``stop``. ``ready`` is set once subscribed."""
    stop = stop or threading.Event()
    q: queue.SimpleQueue = queue.SimpleQueue()

    def on_sample(sample) -> None:
        q.put((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

    books: dict[str, TopicBook] = {}
    malformed = 0
    messages = 0
    t_start = time.monotonic()
    meta = {"generator": "noiselab record", "key_expr": key_expr, "started_unix_ns": str(time.time_ns())}
    with mcapio.RecordingWriter(out, force=force, chunk_size=chunk_size, metadata=meta) as w:
        sub = session.declare_subscriber(key_expr, on_sample)
        if ready is not None:
            ready.set()
        last_flush = time.monotonic()
        stop_at = None
        try:
            while True:
                now = time.monotonic()
                done = stop.is_set() or (duration is not None and now - t_start >= duration)
                if done and stop_at is None:
                    stop_at = now
                if done and now - stop_at > DRAIN_MAX_S:
                    break
                try:
                    # once stopping, drain until the stream has been quiet for QUIET_S (what is still
                    # in flight from a fast sender), at most DRAIN_MAX_S
                    item = q.get(timeout=0.05 if not done else QUIET_S)
                except queue.Empty:
                    item = None
                if item is not None:
                    key, payload, rx_ns = item
                    kind = _kind_of_key(key)
                    try:
                        if kind is None:
                            raise wire.WireError(f"{key}: not a noiselab topic kind")
                        seq, t = _seq_t(payload, kind, key)
                        w.write(key, kind, seq, int(round(t * 1e9)), rx_ns, payload)
                    except (wire.WireError, mcapio.McapIoError) as exc:
                        malformed += 1
                        if malformed <= 5:
                            print(f"noiselab record: skipped a message: {exc}", file=log, flush=True)
                    else:
                        books.setdefault(key, TopicBook()).see(seq)
                        messages += 1
                if time.monotonic() - last_flush >= flush_s:
                    w.flush()
                    last_flush = time.monotonic()
                if done and item is None:
                    break
        finally:
            sub.undeclare()
            summary = RecorderSummary(out=str(out), topics=books, messages=messages, malformed=malformed,
                                      wall_s=time.monotonic() - t_start)
            w.add_metadata("noiselab.recorder", {
                "topics": json.dumps({k: v.as_dict() for k, v in books.items()}),
                "messages": str(messages), "malformed": str(malformed),
                "stopped_unix_ns": str(time.time_ns())})
    return summary
