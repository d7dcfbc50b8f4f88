"""The recorder node: subscribes to a key expression (default ``noiselab/**``) and writes every
sample it receives to MCAP (wire contract: one channel per key, JSON Schema, sequence = seq,
publish_time = the sample time t in ns, log_time = receive time, wall clock ns).

* Samples wait in a bounded zenoh FIFO channel (:data:`CAPACITY`); the main thread takes them in
  batches (whatever has arrived, at most :data:`BATCH`), so no Python code runs per message on
  zenoh's threads. When the recorder falls behind, the full channel stops zenoh reading the link
  and the source's BLOCK congestion control slows the source down: backpressure, bounded memory,
  nothing dropped. log_time is the wall-clock time the batch was taken from the channel (one
  reading per batch; at normal rates a batch is what arrived in the last ~2 ms).
* A batch is decoded topic by topic (``wire.decode_batch`` for long runs, ``wire.decode`` for a
  few messages, the same checks either way), written topic by topic, and its seqs are booked.
  A payload that breaks the contract is skipped and counted (never the rest of its batch).
* Untrusted input: a message is recorded only if it holds to the contract (:mod:`wire`'s
  decoders, with their size and nesting bounds), its vector has the length of its stream's
  first message (a topic's length never changes within a recording), and its seq continues
  its stream: a forward jump is recorded only once the next message of the topic confirms it
  (:class:`wire.SeqGate`; a real gap costs nothing, one forged seq is not recorded) or the
  source's end of stream says it published that seq. Anything else is skipped and counted per
  topic (``malformed``, ``malformed_topics``); the first few are said on stderr.
* The chunk in progress is flushed every ``flush_s`` (default 0.25 s), so a SIGKILLed recorder
  loses at most the last ~0.25 s plus what waited in the channel: the file lacks its footer, and
  `noiselab recover` (or any reader, which says the file is unfinished) gets every message up to
  the last flushed chunk.
* End of stream (README "Live pipeline"): a source publishes ``<prefix>/end`` with the number of
  messages it sent per topic, then queries that key. The recorder answers the query once it has
  written everything that arrived before it, with what it holds per topic; the messages the
  source sent but the recorder lacks at the end are reported as a gap after the last seq.
* SIGINT/SIGTERM, ``duration`` or ``stop`` finish the file (summary, footer) cleanly. The
  recorder first writes what is still queued, and goes on until every source it has heard has
  ended, or nothing arrived for :data:`QUIET_S` (a source gone without an end), or it has been
  caught up for :data:`LIVE_S` (a live stream: it stops there), or at most :data:`DRAIN_MAX_S`.
  Each source heard whose stream did not end is said on stderr, one line each, and listed in
  the summary and metadata (``unended``): it vanished, or was still streaming at the stop.
* Join point (README "Live pipeline"): right after subscribing, the recorder asks the sources
  where each topic's stream to it is complete (:class:`transport.JoinRequest`) and starts each
  topic's recording at its last hole before that point (:meth:`Ingest._from_join`).
* Sequence bookkeeping per topic: first and last seq, count, gaps (a forward jump: the seqs
  skipped; and the tail a source announced but that never came) and restarts (seq going back,
  e.g. a restarted emulator). A recorder started mid-stream reports the seqs before its first
  one as missing at start. They are printed on stop and stored in the file's metadata record
  ``noiselab.recorder`` (JSON strings).
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import zenoh

from . import mcapio, transport, wire

CAPACITY = 16384     # samples the zenoh channel holds before zenoh stops reading the link
BATCH = 4096         # samples taken from the channel per batch, at most
IDLE_S = 0.002       # nothing queued: look again after this long
BATCH_DECODE_MIN = 16  # a topic's run in a batch at least this long is decoded with wire.decode_batch
QUIET_S = 0.25       # on stop: nothing arrived for this long and a source has not ended: finish
LIVE_S = 0.5         # on stop: caught up for this long with sources still streaming: finish
DRAIN_MAX_S = 10.0   # on stop: finish after this long whatever is still arriving
SEQ_AHEAD = 1        # a seq more than this past its topic's last is held for confirmation (wire.SeqGate)
VECTOR_KINDS = (*wire.KINDS, wire.CONTROL)


@dataclass
class TopicBook:
    """Sequence bookkeeping of one topic."""

    first_seq: int | None = None
    last_seq: int | None = None
    count: int = 0
    gaps: list = field(default_factory=list)        # (after_seq, missing)
    restarts: list = field(default_factory=list)    # (from_seq, to_seq)
    expected: int | None = None                      # messages the source says it published
    missing_at_end: int = 0

    def see(self, seq: int) -> None:
        if self.first_seq is None:
            self.first_seq = seq
        elif seq > self.last_seq + 1:
            self.gaps.append((self.last_seq, seq - self.last_seq - 1))
        elif seq <= self.last_seq:
            self.restarts.append((self.last_seq, seq))
            self.expected, self.missing_at_end = None, 0      # a new stream: its end is to come
        self.last_seq = seq
        self.count += 1

    def see_run(self, seq0: int, n: int) -> None:
        """``n`` consecutive seqs from ``seq0`` (same as ``see`` on each)."""
        self.see(seq0)
        if n > 1:
            self.last_seq = seq0 + n - 1
            self.count += n - 1

    def end(self, expected: int) -> int:
        """The source published ``expected`` messages (seq 0..expected-1): book the tail that
        did not arrive as a gap after the last seq; returns it. A topic of which nothing arrived
        has all of them missing at start (a recorder started late cannot tell a loss from that)."""
        self.expected = expected
        self.missing_at_end = 0 if self.last_seq is None else max(0, expected - 1 - self.last_seq)
        if self.missing_at_end:
            self.gaps.append((self.last_seq, self.missing_at_end))
        return self.missing_at_end

    @property
    def missing(self) -> int:
        """Seqs skipped inside the stream and, once the source has ended, after its last seq."""
        return sum(m for _, m in self.gaps)

    @property
    def missing_at_start(self) -> int:
        return self.first_seq if self.first_seq is not None else (self.expected or 0)

    @property
    def lacks(self) -> int:
        """Every seq from 0 to the last one the source announced (or to the last seen) not recorded."""
        return self.missing_at_start + self.missing

    def as_dict(self) -> dict:
        return {"first_seq": self.first_seq, "last_seq": self.last_seq, "count": self.count,
                "missing_at_start": self.missing_at_start, "gaps": [list(g) for g in self.gaps],
                "missing": self.missing, "restarts": [list(r) for r in self.restarts],
                "expected": self.expected, "missing_at_end": self.missing_at_end}


@dataclass
class RecorderSummary:
    out: str
    topics: dict
    messages: int
    malformed: int
    wall_s: float
    ended: dict = field(default_factory=dict)
    malformed_topics: dict = field(default_factory=dict)   # key -> messages skipped
    unended: dict = field(default_factory=dict)            # prefix -> {kind: last seq}: no end of stream came

    def as_dict(self) -> dict:
        return {"node": "record", "out": self.out, "messages": self.messages, "malformed": self.malformed,
                "malformed_topics": self.malformed_topics, "wall_s": self.wall_s,
                "topics": {k: v.as_dict() for k, v in self.topics.items()}, "ended": self.ended,
                "unended": self.unended}

    def lines(self) -> list[str]:
        out = [f"recorded {self.messages} messages to {self.out} in {self.wall_s:.1f} s"]
        for topic, b in sorted(self.topics.items()):
            d = b.as_dict()
            text = f"  {topic}: " + (f"{b.count} messages, seq {b.first_seq}..{b.last_seq}" if b.count else
                                     f"no messages (the source published {b.expected})")
            if d["missing_at_start"] and b.count:
                text += f", started at seq {b.first_seq} (seqs 0..{b.first_seq - 1} not recorded)"
            text += f", {b.missing} missing in {len(b.gaps)} gaps" if b.gaps else ", no gaps"
            if b.missing_at_end:
                text += f" ({b.missing_at_end} at the end: the source published {b.expected})"
            if b.restarts:
                text += f", {len(b.restarts)} restarts (seq went back)"
            out.append(text)
        if self.malformed:
            out.append(f"  {self.malformed} malformed payloads skipped ("
                       + ", ".join(f"{n} on {k}" for k, n in sorted(self.malformed_topics.items())) + ")")
        for prefix in sorted(self.unended):
            out.append(f"  {prefix}: {_unended_text(self.unended[prefix])}")
        return out


def _unended_text(last: dict) -> str:
    return ("no end of stream (the source vanished, or was still streaming at the stop); last seq "
            + ", ".join(f"{kind} {seq}" for kind, seq in sorted(last.items())))


def _kind_of_key(key: str) -> str | None:
    kind = key.rsplit("/", 1)[-1]
    return kind if kind in wire.ALL_KINDS else None


def _decoded(payload: bytes, kind: str, key: str) -> dict:
    """Validate one payload of ``kind`` (WireError if it breaks the contract); the decoded object."""
    if kind == wire.HEALTH:
        return wire.decode_health(payload, topic=key)
    if kind == wire.ANALYSIS:
        return wire.decode_analysis(payload, topic=key)
    if kind == wire.END:
        return wire.decode_end(payload, topic=key)
    return wire.decode(payload, kind, topic=key)


def _seq_t(payload: bytes, kind: str, key: str) -> tuple[int, float]:
    """Validate one payload of ``kind``; its (seq, t)."""
    obj = _decoded(payload, kind, key)
    return obj["seq"], float(obj["t"])


class Ingest:
    """Decode, check, write and book batches of received samples (the recorder's main-thread
    work, without the transport: tests/bench calls it in-process)."""

    def __init__(self, writer: "mcapio.RecordingWriter", out: str = "", log=sys.stderr):
        self.w = writer
        self.out = out
        self.log = log
        self.books: dict[str, TopicBook] = {}
        self.gates: dict[str, wire.SeqGate] = {}  # topic -> its seq gate (held: (seq, t, payload, rx_ns, dim))
        self.dims: dict[str, int] = {}            # vector topic -> its vector's length (first message)
        self.malformed = 0
        self.malformed_topics: dict[str, int] = {}
        self.messages = 0
        self.ends: dict[str, dict] = {}          # prefix -> its last end payload (stream ended)
        self.live: set[str] = set()              # prefixes with data whose end has not come
        self.join: dict[str, int] = {}           # topic -> first seq routed for sure (transport.join_points)
        self._held: dict[str, list] = {}         # topic -> [(seq, payload)] before its join point
        self.dropped_at_join: dict[str, tuple[int, int, int]] = {}   # topic -> (count, first, last seq)

    def _skip(self, key: str, exc: Exception, n: int = 1) -> None:
        self.malformed += n
        self.malformed_topics[key] = self.malformed_topics.get(key, 0) + n
        if self.malformed - n < 5:
            print(f"noiselab record: skipped a message: {exc}", file=self.log, flush=True)

    def add(self, items: list[tuple[str, bytes]], rx_ns: int) -> None:
        """``items``: (key, payload) in arrival order, all taken from the channel at ``rx_ns``."""
        if self.join:
            items = self._from_join(items)
        groups: dict[str, list[bytes]] = {}
        for key, payload in items:
            g = groups.get(key)
            if g is None:
                groups[key] = [payload]
            else:
                g.append(payload)
        for key, payloads in groups.items():       # keys in order of first arrival
            kind = _kind_of_key(key)
            if kind is None:
                self._skip(key, wire.WireError(f"{key}: not a noiselab topic kind"), len(payloads))
                continue
            if kind in VECTOR_KINDS and len(payloads) >= BATCH_DECODE_MIN and self._add_run(key, kind, payloads, rx_ns):
                continue
            for payload in payloads:
                self._add_one(key, kind, payload, rx_ns)

    def _from_join(self, items: list[tuple[str, bytes]]) -> list[tuple[str, bytes]]:
        """Samples of a topic before its join point (:func:`transport.join_points`) wait until the
        point is reached: those that run without a hole up to it are kept (the usual case: the
        source had them routed here already), those before a hole are left out and counted (the
        source sent them before it knew this recorder's subscriber): the recording of the topic
        has no gap, and the seqs before it are missing at the start. A topic leaves :attr:`join`
        at its first sample at or after the point (or at its source's end of stream, or
        :meth:`flush_join`)."""
        kept = []
        for key, payload in items:
            first = self.join.get(key)
            if first is None:
                if key.endswith("/" + wire.END):    # a source ended: its topics' joins end (held samples kept)
                    prefix = key.rsplit("/", 1)[0]
                    for k in [k for k in self.join if k.rsplit("/", 1)[0] == prefix]:
                        kept += self._release(k, None)
                kept.append((key, payload))
                continue
            kind = _kind_of_key(key)
            try:
                seq = _seq_t(payload, kind, key)[0]
            except wire.WireError:
                kept.append((key, payload))      # Ingest skips and counts it; the join goes on
                continue
            if seq < first:
                self._held.setdefault(key, []).append((seq, payload))
                continue
            kept += self._release(key, first)
            kept.append((key, payload))
        return kept

    def _release(self, key: str, first: int | None) -> list[tuple[str, bytes]]:
        """End ``key``'s join: its held samples that run without a hole up to ``first`` (None: up to
        the last held one), the rest counted in :attr:`dropped_at_join` and said on the log."""
        point = self.join.pop(key, None)
        held = self._held.pop(key, [])
        keep = len(held)
        nxt = first if first is not None else (held[-1][0] + 1 if held else None)
        while keep > 0 and held[keep - 1][0] == nxt - 1:
            keep -= 1
            nxt -= 1
        out, drop = held[keep:], held[:keep]
        if drop:
            seqs = [q for q, _ in drop]
            self.dropped_at_join[key] = (len(drop), min(seqs), max(seqs))
            print(f"noiselab record: {key}: joined the stream at seq {nxt} (join point {point}); {len(drop)} "
                  f"sample(s) received before a hole left out (seqs {min(seqs)}..{max(seqs)}: the source sent them "
                  "before it knew this recorder's subscriber)", file=self.log, flush=True)
        return [(key, payload) for _, payload in out]

    def flush_join(self) -> None:
        """Write what still waits for a join point (the recorder stops)."""
        kept = []
        for key in list(self.join):
            kept += self._release(key, None)
        if kept:
            self.add(kept, time.time_ns())

    def finish(self) -> None:
        """The recorder stops: write what waits for a join point; a message still held by its
        seq gate had no successor, so it is skipped."""
        self.flush_join()
        for key, gate in self.gates.items():
            for seq, *_ in gate.flush():
                self._skip(key, self._jump_error(key, seq))

    def _jump_error(self, key: str, seq: int) -> wire.WireError:
        book = self.books.get(key)
        last = None if book is None else book.last_seq
        return wire.WireError(f"{key}: seq {seq} jumps from the stream's last seq {last} and no message "
                              "followed it: not recorded")

    def _add_run(self, key: str, kind: str, payloads: list[bytes], rx_ns: int) -> bool:
        """Many payloads of one vector topic at once; False (nothing written) when any of them
        breaks the contract, the stream's vector length, or jumps ahead (a seq to confirm), so
        the caller goes message by message and decides on each."""
        try:
            seq, t, vals = wire.decode_batch(payloads, kind, topic=key)
        except wire.WireError:
            return False
        gate = self.gates.get(key)
        if self.dims.get(key, vals.shape[1]) != vals.shape[1] or (gate is not None and (
                gate.held is not None or gate.far(int(seq[0])))) or (np.diff(seq) > SEQ_AHEAD).any():
            return False
        pub = np.rint(t * 1e9)
        if ((pub < 0) | (pub >= 2.0**63)).any():   # not a u64 publish_time: write() names it
            return False
        pub = pub.astype(np.int64)
        log = np.full(len(payloads), rx_ns, dtype=np.int64)
        # consecutive runs of seq (normally one): write_batch writes seq0..seq0+n-1
        breaks = np.flatnonzero(np.diff(seq) != 1) + 1
        book = self.books.get(key)
        if book is None:
            book = self.books[key] = TopicBook()
        restarted = False
        for a, b in zip([0, *breaks.tolist()], [*breaks.tolist(), len(payloads)]):
            s0 = int(seq[a])
            self.w.write_batch(key, kind, s0, pub[a:b], log[a:b], payloads[a:b])
            n_restarts = len(book.restarts)
            book.see_run(s0, b - a)
            restarted |= len(book.restarts) > n_restarts
        self.messages += len(payloads)
        self.dims[key] = vals.shape[1]
        if gate is None:
            gate = self.gates[key] = wire.SeqGate(SEQ_AHEAD)
        gate.last = int(seq[-1])
        self._data_seen(key, kind, restarted)
        return True

    def _add_one(self, key: str, kind: str, payload: bytes, rx_ns: int) -> None:
        n = None
        try:
            obj = _decoded(payload, kind, key)
            if kind in VECTOR_KINDS:
                n, dim = len(obj[wire.VECTOR_FIELD[kind]]), self.dims.get(key)
                if dim is not None and n != dim:
                    raise wire.WireError(f"{key}: {wire.VECTOR_FIELD[kind]} has {n} elements at seq {obj['seq']}; "
                                         f"the stream's have {dim}")
        except wire.WireError as exc:
            self._skip(key, exc)
            return
        item = (obj["seq"], float(obj["t"]), payload, rx_ns, n)
        if kind == wire.END:                     # one message per stream, each with seq 0
            self._write(key, kind, *item, end=obj)
            return
        gate = self.gates.get(key)
        if gate is None:
            gate = self.gates[key] = wire.SeqGate(SEQ_AHEAD)
        take, dropped = gate.offer(obj["seq"], item)
        for seq, *_ in dropped:
            self._skip(key, self._jump_error(key, seq))
        for it in take:
            self._write(key, kind, *it)

    def _write(self, key: str, kind: str, seq: int, t: float, payload: bytes, rx_ns: int, dim: int | None,
               end: dict | None = None) -> None:
        """Write one message that has passed every check (``dim``: its vector's length), and book it."""
        try:
            self.w.write(key, kind, seq, int(round(t * 1e9)), rx_ns, payload)
        except mcapio.McapWriteError:
            raise                                # the file takes no more: not a bad message
        except mcapio.McapIoError as exc:        # this message cannot be written (its times)
            self._skip(key, exc)
            return
        book = self.books.get(key)
        if book is None:
            book = self.books[key] = TopicBook()
        n_restarts = len(book.restarts)
        book.see(seq)
        self.messages += 1
        if dim is not None:
            self.dims.setdefault(key, dim)
        if end is not None:
            self._end(key, end)
        else:
            self._data_seen(key, kind, len(book.restarts) > n_restarts)

    def _data_seen(self, key: str, kind: str, restarted: bool) -> None:
        if kind not in wire.KINDS:
            return                                  # health, control, analysis: not a stream of its own
        prefix = key.rsplit("/", 1)[0]
        if restarted or prefix not in self.ends:
            self.ends.pop(prefix, None)
            self.live.add(prefix)

    def _end(self, key: str, end: dict) -> None:
        """The end of a source's stream: everything it sent before has been written (same links,
        in order). A message held by its topic's seq gate is taken if the source says it published
        that seq. Book the tail that did not come as a gap, and say so."""
        prefix = key.rsplit("/", 1)[0]
        for kind, n in end["counts"].items():
            gate = self.gates.get(f"{prefix}/{kind}")
            if gate is not None and gate.held is not None and gate.held[0] < n:
                for item in gate.take_held():
                    self._write(f"{prefix}/{kind}", kind, *item)
        self.ends[prefix] = end
        self.live.discard(prefix)
        short = []
        for kind, n in end["counts"].items():
            book = self.books.get(f"{prefix}/{kind}")
            if book is None:
                if not n:
                    continue
                book = self.books[f"{prefix}/{kind}"] = TopicBook()
            book.end(n)
            if book.lacks:
                where = ("none arrived" if not book.count else
                         ", ".join(f"{m} {w}" for m, w in ((book.missing_at_start, "at the start"),
                                                           (book.missing - book.missing_at_end, "in gaps"),
                                                           (book.missing_at_end, "at the end")) if m))
                short.append(f"{book.lacks} {kind} ({where})")
        text = (f"noiselab record: {prefix} ended ({end['reason']}) after {end['samples']} samples: "
                + ("every message recorded" if not short else "not recorded: " + ", ".join(short)))
        print(text, file=self.log, flush=True)

    def unended(self) -> dict:
        """{prefix: {kind: last seq}} of every source whose data arrived and whose end of stream
        did not come after it (it vanished, or was still streaming)."""
        return {prefix: {key.rsplit("/", 1)[1]: b.last_seq for key, b in sorted(self.books.items())
                         if key.rsplit("/", 1)[0] == prefix and key.rsplit("/", 1)[1] in wire.KINDS}
                for prefix in sorted(self.live)}

    def ack(self, prefix: str) -> dict:
        """What the recorder holds of ``prefix``'s topics (the answer to an end-of-stream query)."""
        end = self.ends.get(prefix)
        topics = {}
        for key, book in self.books.items():
            if key.rsplit("/", 1)[0] == prefix:
                topics[key.rsplit("/", 1)[1]] = {"count": book.count, "last_seq": book.last_seq,
                                                 "expected": book.expected, "missing": book.lacks}
        return {"node": "record", "out": self.out, "prefix": prefix, "ended": end is not None,
                "complete": end is not None and all(t["missing"] == 0 for t in topics.values()),
                "topics": topics}


def run_recorder(session: "zenoh.Session", key_expr: str, out: str, *, duration: float | None = None,
                 force: bool = False, stop: threading.Event | None = None, flush_s: float = 0.25,
                 chunk_size: int = 64 * 1024, ready: Callable[[str], None] | None = None,
                 log=sys.stderr) -> RecorderSummary:
    """Record until ``duration`` (wall seconds) or ``stop``. ``ready`` is called once subscribed,
    with the file the bytes go to until the recording is finished (``RecordingWriter.writing_path``:
    ``out``, or ``out`` + ``.partial`` while ``force`` keeps an older ``out``)."""
    stop = stop or threading.Event()
    t_start = time.monotonic()
    meta = {"generator": "noiselab record", "key_expr": key_expr, "started_unix_ns": str(time.time_ns())}
    with mcapio.RecordingWriter(out, force=force, chunk_size=chunk_size, metadata=meta) as w:
        ing = Ingest(w, str(out), log)
        # the queryable first: a source that sees the subscriber has seen it too
        queries = session.declare_queryable(key_expr, zenoh.handlers.FifoChannel(256))
        sub = session.declare_subscriber(key_expr, zenoh.handlers.FifoChannel(CAPACITY))
        join = transport.JoinRequest(session, key_expr)   # answered while the loop drains the channel
        waiting: list = []                    # samples taken before the join points came
        if ready is not None:
            ready(w.writing_path)
        recv, recv_query = sub.try_recv, queries.try_recv
        pending: list[list] = []          # [query, samples still to take before it may be answered]
        last_flush = last_rx = time.monotonic()
        stop_at = caught_up_at = None
        try:
            while True:
                while (q := recv_query()) is not None:
                    pending.append([q, CAPACITY])     # what preceded it is in the channel, at most CAPACITY
                items = []
                while len(items) < BATCH and (s := recv()) is not None:
                    items.append((str(s.key_expr), s.payload.to_bytes()))
                empty = len(items) < BATCH            # the channel ran dry: what preceded the queries is in
                now = time.monotonic()
                if join is not None:
                    if join.done.is_set() or stop_at is not None:
                        ing.join = dict(join.points) if join.done.is_set() else {}
                        items, waiting, join = waiting + items, [], None
                    else:
                        waiting += items
                        items = []
                        last_rx = now
                if items:
                    ing.add(items, time.time_ns())
                    last_rx = now
                if pending and join is None:
                    for p in pending:
                        p[1] -= len(items)
                    for p in [p for p in pending if empty or p[1] <= 0]:
                        pending.remove(p)
                        _answer(p[0], ing)
                if now - last_flush >= flush_s:
                    w.flush()
                    last_flush = now
                if stop_at is None and (stop.is_set() or (duration is not None and now - t_start >= duration)):
                    stop_at = now
                if stop_at is not None:
                    caught_up_at = (caught_up_at or now) if empty else None
                    if empty and (not ing.live or now - last_rx >= QUIET_S or now - caught_up_at >= LIVE_S):
                        break
                    if now - stop_at >= DRAIN_MAX_S:
                        print(f"noiselab record: still receiving {DRAIN_MAX_S:g} s after the stop: finishing",
                              file=log, flush=True)
                        break
                if empty:
                    time.sleep(IDLE_S)
        finally:
            sub.undeclare()
            if waiting:
                ing.add(waiting, time.time_ns())
            ing.finish()
            for p in pending:
                _answer(p[0], ing)
            queries.undeclare()
            unended = ing.unended()
            for prefix in sorted(unended):
                print(f"noiselab record: {prefix}: {_unended_text(unended[prefix])}", file=log, flush=True)
            summary = RecorderSummary(out=str(out), topics=ing.books, messages=ing.messages,
                                      malformed=ing.malformed, wall_s=time.monotonic() - t_start,
                                      ended={k: v["counts"] for k, v in ing.ends.items()},
                                      malformed_topics=dict(ing.malformed_topics), unended=unended)
            w.add_metadata("noiselab.recorder", {
                "topics": json.dumps({k: v.as_dict() for k, v in ing.books.items()}),
                "messages": str(ing.messages), "malformed": str(ing.malformed),
                "malformed_topics": json.dumps(ing.malformed_topics), "unended": json.dumps(unended),
                "stopped_unix_ns": str(time.time_ns())})
    return summary


def _answer(query: "zenoh.Query", ing: Ingest) -> None:
    """Answer an end-of-stream query (any other query on the recorded keys gets no answer)."""
    try:
        key = str(query.key_expr)
        if key.endswith("/" + wire.END) and "*" not in key:
            query.reply(key, json.dumps(ing.ack(key.rsplit("/", 1)[0])).encode())
    except zenoh.ZError as exc:                 # the querier gave up (timeout) or went away
        print(f"noiselab record: could not answer an end-of-stream query: {exc}", file=ing.log, flush=True)
    finally:
        query.drop()
