"""The recorder node: subscribes to a key expression (default ``noiselab/**``) and writes every
sample it receives to MCAP (wire contract: one channel per key, JSON Schema, sequence = seq,
publish_time = the stream's wall-clock start + the sample time t, log_time = receive time, both in
ns on the wall clock: one time base per file).

* Time base (:mod:`wire`, "Time"): a source states its run's wall-clock start (``start_time_ns``)
  in its samples' attachment; the recorder writes publish_time = start_time_ns + round(t 1e9)
  for every topic of that source (``noiselab/<name>/...``). A source that states none is
  anchored at its first sample's arrival, max(0, log_time - round(t 1e9)). The first source's
  start is the file's ``start_time_ns`` (metadata record ``noiselab``, written before the first
  message); every source's is in ``noiselab.recorder`` (``starts``). An attachment that breaks
  the contract is ignored and counted (``bad_anchors``, once per change of a topic's attachment:
  a source repeats it on every sample), the sample with it recorded as usual.
  The anchor a source states is taken per batch (a few ms), so a source restarted with a new
  start has its new anchor from the batch its first sample comes in.

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
  decoders, with their size and nesting bounds) and continues its stream, as the topic's
  :class:`seqgate.SeqGate` judges it: the very next seq with the stream's vector length (a topic's
  length never changes within a recording). The stream's start and length, a jump ahead (a real
  gap), a step back (a restarted source) are recorded only once the message's successor
  confirms them, or the source's end of stream says that the message was its last; a repeat of
  the last seq is not recorded. So no single forged message (a wrong length before the stream
  starts, a seq far ahead, a past seq, a duplicate with other data) reaches the file. An end of
  stream that cannot be its source's (it counts fewer messages than are recorded, or comes twice)
  is not taken, and data going on past what an end counted undoes that end. Anything not
  recorded is skipped and counted per topic (``malformed``, ``malformed_topics``); the first few
  are said on stderr. Topics are printed with control characters escaped (one line each).
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

import numpy as np
import zenoh

from .. import wire
from ..recordings.errors import McapIoError, McapWriteError, shown
from ..recordings.writer import RecordingWriter
from . import seqgate, transport
from .recorder_summary import RecorderSummary, TopicBook, unended_text

CAPACITY = 16384     # samples the zenoh channel holds before zenoh stops reading the link
BATCH = 4096         # samples taken from the channel per batch, at most
IDLE_S = 0.002       # nothing queued: look again after this long
BATCH_DECODE_MIN = 16  # a topic's run in a batch at least this long is decoded with wire.decode_batch
QUIET_S = 0.25       # on stop: nothing arrived for this long and a source has not ended: finish
LIVE_S = 0.5         # on stop: caught up for this long with sources still streaming: finish
DRAIN_MAX_S = 10.0   # on stop: finish after this long whatever is still arriving
SEQ_AHEAD = 1        # a seq more than this past its topic's last is held for confirmation (seqgate.SeqGate)
VECTOR_KINDS = (*wire.KINDS, wire.CONTROL)
_END_KEY = "/" + wire.END


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
    if kind == wire.CONTROLLER_HEALTH:
        return wire.decode_controller_health(payload, topic=key)
    return wire.decode(payload, kind, topic=key)


def _seq_t(payload: bytes, kind: str, key: str) -> tuple[int, float]:
    """Validate one payload of ``kind``; its (seq, t)."""
    obj = _decoded(payload, kind, key)
    return obj["seq"], float(obj["t"])


class Ingest:
    """Decode, check, write and book batches of received samples (the recorder's main-thread
    work, without the transport: tests/bench calls it in-process)."""

    def __init__(self, writer: "RecordingWriter", out: str = "", log=sys.stderr,
                 metadata: dict[str, str] | None = None):
        self.w = writer
        self.out = out
        self.log = log
        self.metadata = metadata                 # the "noiselab" record, written before the first message
        self.starts: dict[str, int] = {}         # prefix -> its stream's wall-clock start, ns
        self.stated: set[str] = set()            # prefixes whose start their source stated
        self.bad_anchors = 0
        self.books: dict[str, TopicBook] = {}
        self.gates: dict[str, seqgate.SeqGate] = {}  # topic -> its gate (items: (seq, t, payload, rx_ns))
        self.malformed = 0
        self.malformed_topics: dict[str, int] = {}
        self.said: set[str] = set()              # reasons said once on the log
        self.messages = 0
        self.ends: dict[str, dict] = {}          # prefix -> its last end payload (stream ended)
        self.live: set[str] = set()              # prefixes with data whose end has not come
        self.join: dict[str, int] = {}           # topic -> first seq routed for sure (transport.join_points)
        self._held: dict[str, list] = {}         # topic -> [(seq, payload)] before its join point
        self.dropped_at_join: dict[str, tuple[int, int, int]] = {}   # topic -> (count, first, last seq)

    def _say(self, text: str) -> None:
        print(f"noiselab record: {shown(text)}", file=self.log, flush=True)

    def _skip(self, key: str, exc: Exception, n: int = 1, once: str | None = None) -> None:
        """Count ``n`` messages of ``key`` skipped; say the first few, and the first of a reason
        ``once`` whenever it comes."""
        self.malformed += n
        self.malformed_topics[key] = self.malformed_topics.get(key, 0) + n
        if self.malformed - n < 5 or (once is not None and once not in self.said):
            if once is not None:
                self.said.add(once)
            self._say(f"skipped a message: {exc}")

    def state(self, key: str, attachment: bytes) -> None:
        """A sample of ``key`` came with ``attachment``: its source's stream start
        (:func:`wire.decode_anchor`), taken for every topic of the source from the next batch on.
        One that breaks the contract is ignored and counted (the sample itself is judged apart)."""
        try:
            start = wire.decode_anchor(attachment, topic=key)
        except wire.WireError as exc:
            self.bad_anchors += 1
            if "anchor" not in self.said:
                self.said.add("anchor")
                self._say(f"ignored an attachment (further ones counted in 'bad_anchors'): {exc}")
            return
        prefix = key.rsplit("/", 1)[0]
        self.starts[prefix] = start
        self.stated.add(prefix)

    def _start(self, key: str, t: float, rx_ns: int) -> int:
        """The wall-clock start of ``key``'s stream: the one its source stated, else fixed now from
        this sample (time ``t`` s, received at ``rx_ns``) as ``max(0, rx_ns - round(t 1e9))``. The
        first start fixed is the file's: the ``noiselab`` metadata record is written with it."""
        prefix = key.rsplit("/", 1)[0]
        start = self.starts.get(prefix)
        if start is None:
            try:
                start = max(0, rx_ns - wire.anchored_ns(0, t))
            except wire.WireError:
                return 0                         # not a sample time: writing it fails and says why
            self.starts[prefix] = start
        if self.metadata is not None:
            self.w.add_metadata("noiselab", {**self.metadata, "start_time_ns": str(start)})
            self.metadata = None
        return start

    def starts_dict(self) -> dict:
        """{prefix: {"start_time_ns": int, "stated": bool}} of every source recorded."""
        return {p: {"start_time_ns": n, "stated": p in self.stated} for p, n in sorted(self.starts.items())}

    def _gate(self, key: str, kind: str) -> seqgate.SeqGate:
        gate = self.gates.get(key)
        if gate is None:
            gate = self.gates[key] = seqgate.SeqGate(SEQ_AHEAD, field=wire.VECTOR_FIELD.get(kind, "vector"))
        return gate

    def _dropped(self, key: str, dropped: list) -> None:
        for d in dropped:
            self._skip(key, wire.WireError(f"{key}: {d.text}: not recorded"))

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
            if key.endswith(_END_KEY):        # an end of stream is taken after what came before it, only
                self._add_groups(groups, rx_ns)
                groups = {}
        self._add_groups(groups, rx_ns)

    def _add_groups(self, groups: dict[str, list[bytes]], rx_ns: int) -> None:
        for key, payloads in groups.items():       # keys in order of first arrival
            kind = _kind_of_key(key)
            if kind is None:
                self._skip(key, wire.WireError(f"{key}: not a noiselab topic kind"), len(payloads))
                continue
            if kind in VECTOR_KINDS and len(payloads) >= BATCH_DECODE_MIN:
                self._add_run(key, kind, payloads, rx_ns)
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
        :meth:`flush_join`).

        A join point comes from any peer that answers the query, so the wait is bounded: a point
        more than :data:`CAPACITY` past the topic's first seq received is not waited for (a real
        one is a few samples past it: those the source sent while the subscriber was on its
        way), and a topic that has :data:`CAPACITY` samples waiting is written from there on."""
        kept = []
        for key, payload in items:
            first = self.join.get(key)
            if first is None:
                if key.endswith(_END_KEY):          # a source ended: its topics' joins end (held samples kept)
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
                held = self._held.get(key, [])
                if not held and first - seq > CAPACITY:
                    self.join.pop(key)
                    self._say(f"{key}: join point {first} is more than {CAPACITY} samples past the first seq "
                              f"received ({seq}): not waited for")
                else:
                    self._held[key] = held
                    held.append((seq, payload))
                    if len(held) >= CAPACITY:
                        self._say(f"{key}: {CAPACITY} samples waited for join point {first}: not waited for longer")
                        kept += self._release(key, None)
                    continue
            else:
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
            self._say(f"{key}: joined the stream at seq {nxt} (join point {point}); {len(drop)} "
                      f"sample(s) received before a hole left out (seqs {min(seqs)}..{max(seqs)}: the source sent them "
                      "before it knew this recorder's subscriber)")
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
        seq gate had no successor, so it is skipped. A file that got no message gets its
        ``noiselab`` metadata record now (without a start)."""
        self.flush_join()
        for key, gate in self.gates.items():
            self._dropped(key, gate.flush())
        if self.metadata is not None:
            self.w.add_metadata("noiselab", self.metadata)
            self.metadata = None

    def _add_run(self, key: str, kind: str, payloads: list[bytes], rx_ns: int) -> None:
        """Many payloads of one vector topic at once: decoded with ``wire.decode_batch``, and each
        run of consecutive seqs the gate takes whole (:meth:`seqgate.SeqGate.take_run`: the usual
        case) written with ``write_batch``; the others go message by message (:meth:`_add_one`),
        as do all of them when any breaks the contract (the slow path names it)."""
        try:
            seq, t, vals = wire.decode_batch(payloads, kind, topic=key)
        except wire.WireError:
            seq = None
        if seq is not None:
            rel = np.rint(t * 1e9)                      # wire.anchored_ns, for the whole run
            start = self._start(key, float(t[0]), rx_ns)
            if ((rel < 0) | (rel >= 2.0**63)).any() or int(rel.max()) > wire.SEQ_MAX - start:
                seq = None                              # not an int64 publish_time: _write names it
        if seq is None:
            for payload in payloads:
                self._add_one(key, kind, payload, rx_ns)
            return
        pub = rel.astype(np.int64) + np.int64(start)
        log = np.full(len(payloads), rx_ns, dtype=np.int64)
        gate, dim = self._gate(key, kind), vals.shape[1]
        breaks = np.flatnonzero(np.diff(seq) != 1) + 1
        for a, b in zip([0, *breaks.tolist()], [*breaks.tolist(), len(payloads)]):
            s0 = int(seq[a])
            if gate.take_run(s0, b - a, dim):
                self.w.write_batch(key, kind, s0, pub[a:b], log[a:b], payloads[a:b])
                self._book(key, kind, s0, b - a)
            else:
                for payload in payloads[a:b]:
                    self._add_one(key, kind, payload, rx_ns)

    def _add_one(self, key: str, kind: str, payload: bytes, rx_ns: int) -> None:
        try:
            obj = _decoded(payload, kind, key)
        except wire.WireError as exc:
            self._skip(key, exc)
            return
        item = (obj["seq"], float(obj["t"]), payload, rx_ns)
        self._start(key, item[1], rx_ns)
        if kind == wire.END:                     # one message per stream, each with seq 0
            doubt = self._doubtful_end(key, obj)
            if doubt:
                self._skip(key, wire.WireError(f"{key}: {doubt}: not taken"), once="end")
            else:
                self._write(key, kind, *item, end=obj)
            return
        field = wire.VECTOR_FIELD.get(kind)
        take, dropped = self._gate(key, kind).offer(obj["seq"], len(obj[field]) if field else 0, item)
        self._dropped(key, dropped)
        for it in take:
            self._write(key, kind, *it)

    def _write(self, key: str, kind: str, seq: int, t: float, payload: bytes, rx_ns: int,
               end: dict | None = None) -> None:
        """Write one message that has passed every check, and book it."""
        try:
            self.w.write(key, kind, seq, wire.anchored_ns(self._start(key, t, rx_ns), t), rx_ns, payload)
        except McapWriteError:
            raise                                # the file takes no more: not a bad message
        except (McapIoError, wire.WireError) as exc:   # this message cannot be written (its times)
            self._skip(key, exc)
            return
        if end is not None:
            self.books.setdefault(key, TopicBook()).see(seq)
            self.messages += 1
            self._end(key, end)
        else:
            self._book(key, kind, seq, 1)

    def _book(self, key: str, kind: str, seq0: int, n: int) -> None:
        """Book ``n`` written messages of ``key`` with consecutive seqs from ``seq0``."""
        book = self.books.get(key)
        if book is None:
            book = self.books[key] = TopicBook()
        prefix = key.rsplit("/", 1)[0]
        end = self.ends.get(prefix)
        late = kind in wire.KINDS and end is not None and book.last_seq is not None and seq0 > book.last_seq
        if late:                             # the stream goes on after its end of stream
            count = end["counts"].get(kind, 0)
            if seq0 >= count:
                self._unend(prefix, key, seq0, count)
            else:
                book.unend()                     # a message the end counted came after it: booked again below
        n_restarts = len(book.restarts)
        book.see_run(seq0, n)
        self.messages += n
        if late and prefix in self.ends:
            book.end(count)
        if kind in wire.KINDS and (len(book.restarts) > n_restarts or prefix not in self.ends):
            self.ends.pop(prefix, None)
            self.live.add(prefix)

    def _doubtful_end(self, key: str, end: dict) -> str | None:
        """Why an end of stream cannot be its source's (None if it can): it counts fewer messages
        of a topic than the seqs already recorded of its stream, or the stream has already ended
        (an end comes once per stream). Such an end (forged or stale) is skipped: it would end a
        source that is still streaming, or vouch for what the source never sent."""
        prefix = key.rsplit("/", 1)[0]
        if prefix in self.ends:
            return "a second end of stream for a stream that has ended"
        for kind, n in end["counts"].items():
            book = self.books.get(f"{prefix}/{kind}")
            if book is not None and book.last_seq is not None and n <= book.last_seq:
                return f"an end of stream counting {n} {kind} messages, but seq {book.last_seq} is recorded"
        return None

    def _unend(self, prefix: str, key: str, seq: int, count: int) -> None:
        """Data went on past what the prefix's end of stream counted: that end was not the
        source's last word (forged, or stale): the source is streaming again, and the end's
        bookkeeping (expected counts, the tail booked missing) is undone."""
        self.ends.pop(prefix, None)
        for k, book in self.books.items():
            if k.rsplit("/", 1)[0] == prefix:
                book.unend()
        if "unend" not in self.said:
            self.said.add("unend")
            self._say(f"{key}: seq {seq} came after an end of stream that counted {count}: that end is not "
                      "taken (the source streams on)")

    def _end(self, key: str, end: dict) -> None:
        """The end of a source's stream: everything it sent before has been written (same links,
        in order). A message held by its topic's seq gate is taken if the source says it published
        that seq. Book the tail that did not come as a gap, and say so."""
        prefix = key.rsplit("/", 1)[0]
        for kind, n in end["counts"].items():
            gate = self.gates.get(f"{prefix}/{kind}")
            if gate is not None:
                take, dropped = gate.vouch(n)
                self._dropped(f"{prefix}/{kind}", dropped)
                for item in take:
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
        self._say(f"{prefix} ended ({end['reason']}) after {end['samples']} samples: "
                  + ("every message recorded" if not short else "not recorded: " + ", ".join(short)))

    def unended(self) -> dict:
        """{prefix: {kind: last seq}} of every source whose data arrived and whose end of stream
        did not come after it (it vanished, or was still streaming)."""
        return {prefix: {key.rsplit("/", 1)[1]: b.last_seq for key, b in sorted(self.books.items())
                         if key.rsplit("/", 1)[0] == prefix and key.rsplit("/", 1)[1] in wire.KINDS}
                for prefix in sorted(self.live)}

    def say_unended(self) -> dict:
        """:meth:`unended`, each source said on the log (one line each)."""
        unended = self.unended()
        for prefix in sorted(unended):
            self._say(f"{prefix}: {unended_text(unended[prefix])}")
        return unended

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
    with RecordingWriter(out, force=force, chunk_size=chunk_size) as w:
        ing = Ingest(w, str(out), log, metadata=meta)
        # the queryable first: a source that sees the subscriber has seen it too
        queries = session.declare_queryable(key_expr, zenoh.handlers.FifoChannel(256))
        sub = session.declare_subscriber(key_expr, zenoh.handlers.FifoChannel(CAPACITY))
        join = transport.JoinRequest(session, key_expr)   # answered while the loop drains the channel
        waiting: list = []                    # samples taken before the join points came
        if ready is not None:
            ready(w.writing_path)
        recv, recv_query = sub.try_recv, queries.try_recv
        anchors: dict[str, bytes] = {}     # key -> the last attachment taken (most samples repeat it)
        pending: list[list] = []          # [query, samples still to take before it may be answered]
        last_flush = last_rx = time.monotonic()
        stop_at = caught_up_at = None
        try:
            while True:
                while (q := recv_query()) is not None:
                    pending.append([q, CAPACITY])     # what preceded it is in the channel, at most CAPACITY
                items = _take(recv, ing, anchors)
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
                    _answer_due(pending, len(items), empty, ing)
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
            summary = _summary(w, ing, str(out), time.monotonic() - t_start)
    return summary


def _take(recv, ing: Ingest, anchors: dict[str, bytes]) -> list[tuple[str, bytes]]:
    """Up to :data:`BATCH` samples from the channel (``recv``), as (key, payload). An attachment
    that differs from the last one taken on its key (``anchors``, updated) is given to
    :meth:`Ingest.state` first: most samples repeat their source's."""
    items = []
    while len(items) < BATCH and (s := recv()) is not None:
        key = str(s.key_expr)
        if (att := s.attachment) is not None and (att := att.to_bytes()) != anchors.get(key):
            anchors[key] = att
            ing.state(key, att)
        items.append((key, s.payload.to_bytes()))
    return items


def _answer_due(pending: list[list], taken: int, empty: bool, ing: Ingest) -> None:
    """Answer each pending end-of-stream query ([query, samples still to take before it]) whose
    preceding samples are all taken: ``taken`` more were, or the channel ran dry (``empty``)."""
    for p in pending:
        p[1] -= taken
    for p in [p for p in pending if empty or p[1] <= 0]:
        pending.remove(p)
        _answer(p[0], ing)


def _summary(w: RecordingWriter, ing: Ingest, out: str, wall_s: float) -> RecorderSummary:
    """The recording's summary, also stored in its metadata record ``noiselab.recorder``; each
    source whose stream did not end is said on the log."""
    unended = ing.say_unended()
    summary = RecorderSummary(out=out, topics=ing.books, messages=ing.messages,
                              malformed=ing.malformed, wall_s=wall_s,
                              ended={k: v["counts"] for k, v in ing.ends.items()},
                              malformed_topics=dict(ing.malformed_topics), unended=unended,
                              starts=ing.starts_dict(), bad_anchors=ing.bad_anchors)
    w.add_metadata("noiselab.recorder", {
        "topics": json.dumps({k: v.as_dict() for k, v in ing.books.items()}),
        "messages": str(ing.messages), "malformed": str(ing.malformed),
        "malformed_topics": json.dumps(ing.malformed_topics), "unended": json.dumps(unended),
        "starts": json.dumps(ing.starts_dict()), "bad_anchors": str(ing.bad_anchors),
        "stopped_unix_ns": str(time.time_ns())})
    return summary


def _answer(query: "zenoh.Query", ing: Ingest) -> None:
    """Answer an end-of-stream query (any other query on the recorded keys gets no answer)."""
    try:
        key = str(query.key_expr)
        if key.endswith("/" + wire.END) and "*" not in key:
            query.reply(key, json.dumps(ing.ack(key.rsplit("/", 1)[0])).encode())
    except zenoh.ZError as exc:                 # the querier gave up (timeout) or went away
        ing._say(f"could not answer an end-of-stream query: {exc}")
    finally:
        query.drop()
