"""Messages of an MCAP file merged across channels by publish time, as a live source sent them."""

from __future__ import annotations

import operator
import os
import struct
from collections import defaultdict
from collections.abc import Iterator

from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Schema

from .chunks import MESSAGE_HEADER, chunk_records
from .errors import CorruptRecordingError, salvage_hint
from .mcapformat import CORRUPTION_ERRORS, norm_topic
from .scan import ScanReport, check_magic, finished_file, scan

_KIND_RANK = {"truth": 0, "command": 1, "measurement": 2, "end": 4}
"""Order of the topics of one sample when publish times tie: the emulator's (truth, command,
measurement); other topics after them, by topic; the end of stream last (its source sends it
after everything else, the last health report of its final instant included)."""


def _tie_rank(channels: dict[int, Channel]) -> dict[int, int]:
    order = sorted(channels, key=lambda cid: (_KIND_RANK.get(norm_topic(channels[cid].topic).rsplit("/", 1)[-1], 3),
                                              norm_topic(channels[cid].topic), cid))
    return {cid: i for i, cid in enumerate(order)}


def iter_time_ordered(path: str | os.PathLike, *, report: ScanReport | None = None
                      ) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """Yield ``(schema, channel, message)`` of ``path`` merged across channels by publish_time
    (the sample time: the order a live source published them), each channel in file order; ties
    go truth, command, measurement, then other topics. A source that restarted (its sample times
    begin again: :class:`_Segments`) comes out one stream segment after the other.

    A streaming k-way merge (heapq.merge) of one iterator per channel. A finished file is read
    chunk by chunk through its chunk index: a chunk is decompressed once, when the first channel
    iterator reaches it, and dropped when the last one that needs it has taken its messages, so
    memory holds about one chunk per channel, however the writer grouped the topics (``noiselab
    simulate`` used to write 65,536-sample blocks per topic). An unfinished file (no summary) is
    read in one pass; a channel joins the merge when its first message appears, so a topic that
    starts late in such a file comes out late. Metadata, completeness and the message count go to
    ``report`` as for :func:`iter_messages`.
    """
    path = os.fspath(path)
    report = report if report is not None else ScanReport()
    size = check_magic(path)
    with open(path, "rb") as f:
        ok, _why = finished_file(f, size)
        summary = None
        if ok:
            f.seek(0)
            reader = SeekingReader(f, validate_crcs=False)
            try:
                summary = reader.get_summary()
                metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            except (*CORRUPTION_ERRORS, OSError):
                summary = None
    if summary is None or not summary.chunk_indexes:
        yield from _merge_stream(path, report)
        return
    report.complete = True
    report.metadata.update(metadata)
    with open(path, "rb") as f:
        yield from _merge_chunks(path, f, summary, report)


def _merge_chunks(path: str, f, summary, report: ScanReport):
    import heapq

    channels = summary.channels
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    chunks_of = {cid: [ci for ci in chunks if not ci.message_index_offsets or cid in ci.message_index_offsets]
                 for cid in channels}
    refs: dict[int, int] = defaultdict(int)
    for cis in chunks_of.values():
        for ci in cis:
            refs[ci.chunk_start_offset] += 1
    decoded: dict[int, dict[int, list]] = {}
    unpack = struct.Struct("<QHIQQ").unpack_from          # length, channel, sequence, log, publish

    def decode(ci) -> dict[int, list]:
        dec = chunk_records(f, ci, path)
        out: dict[int, list] = defaultdict(list)
        pos, n = 0, len(dec)
        try:
            while pos < n:
                rl, cid, seq, log, pub = unpack(dec, pos + 1) if dec[pos] == 0x05 else (
                    struct.unpack_from("<Q", dec, pos + 1)[0], None, 0, 0, 0)
                if cid is not None:
                    if cid not in channels or pos + 9 + rl > n:
                        raise CorruptRecordingError("message of an unknown channel or past the chunk")
                    out[cid].append(Message(channel_id=cid, log_time=log, publish_time=pub, sequence=seq,
                                            data=dec[pos + MESSAGE_HEADER: pos + 9 + rl]))
                pos += 9 + rl
        except (struct.error, CorruptRecordingError) as e:
            raise CorruptRecordingError(f"{path}: finished file with a damaged chunk at byte "
                                        f"{ci.chunk_start_offset} ({type(e).__name__}); {salvage_hint(path)}") from None
        return out

    def channel_messages(cid: int):
        schema = summary.schemas.get(channels[cid].schema_id)
        channel = channels[cid]
        segment = _Segments()
        for ci in chunks_of[cid]:
            off = ci.chunk_start_offset
            got = decoded.get(off)
            if got is None:
                got = decoded[off] = decode(ci)
            mine = got.pop(cid, ())
            refs[off] -= 1
            if refs[off] == 0:
                del decoded[off]
            r = rank[cid]
            for m in mine:
                yield (segment(m.publish_time), m.publish_time, r), (schema, channel, m)

    rank = _tie_rank(channels)
    for _key, item in heapq.merge(*(channel_messages(cid) for cid in channels), key=operator.itemgetter(0)):
        report.messages += 1
        yield item


class _Segments:
    """Numbers one channel's stream segments as its messages come, in file order: a publish_time
    (the sample time) that steps back to or below every earlier one starts a new segment (the
    source restarted from 0). Unlike :func:`split_streams` on seq, a restart whose first samples were
    lost is not told here from a late message: that needs the segment's sample times and payloads,
    memory the streaming merge does not hold, so such a recording's runs meet at their boundary
    in replay. The time-ordered merge keys on
    (segment, publish_time), so a restarted recording replays as it was recorded, one stream after
    the other, not the two streams' samples interleaved by their equal sample times."""

    __slots__ = ("n", "low", "prev")

    def __init__(self) -> None:
        self.n, self.low, self.prev = 0, None, None

    def __call__(self, pub: int) -> int:
        if self.prev is not None and pub < self.prev and pub <= self.low:
            self.n += 1
        self.low = pub if self.low is None or pub < self.low else self.low
        self.prev = pub
        return self.n


def _merge_stream(path: str, report: ScanReport):
    """One pass over a file without a chunk index: per-channel queues; the smallest head goes out
    whenever every channel seen so far has one, the rest (merged) at the end."""
    import heapq
    from collections import deque

    queues: dict[int, deque] = {}          # per channel: ((segment, publish_time), item)
    heads: list = []                       # heap of (segment, publish_time, tie rank, cid), one per non-empty queue
    ranks: dict[int, tuple] = {}
    segments: dict[int, _Segments] = {}

    def pop():
        *_, c = heapq.heappop(heads)
        q = queues[c]
        out = q.popleft()[1]
        if q:
            heapq.heappush(heads, (*q[0][0], ranks[c], c))
        return out

    for item in scan(path, None, report):
        channel = item[1]
        q = queues.get(channel.id)
        if q is None:
            q = queues[channel.id] = deque()
            segments[channel.id] = _Segments()
            topic = norm_topic(channel.topic)
            ranks[channel.id] = (_KIND_RANK.get(topic.rsplit("/", 1)[-1], 3), topic, channel.id)
        key = (segments[channel.id](item[2].publish_time), item[2].publish_time)
        if not q:
            heapq.heappush(heads, (*key, ranks[channel.id], channel.id))
        q.append((key, item))
        while len(heads) == len(queues):
            yield pop()
    while heads:
        yield pop()


# ---------------------------------------------------------------------------- reading
