"""An MCAP writer that takes a whole block of messages per call (:class:`BlockWriter`)."""

from __future__ import annotations

import struct
import zlib
from collections.abc import Sequence

import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from .mcapformat import MAGIC, lz4frame, zstd


class BlockWriter:
    """An MCAP writer (https://mcap.dev/spec) that takes a whole block of messages per call.

    It writes the very file ``mcap.writer.Writer`` (default options) writes for the same calls,
    byte for byte: the same records, the same chunking rule (a chunk is closed after the message
    that takes its uncompressed records past ``chunk_size``; schemas and channels go into the
    chunk in progress), the same message indexes, summary groups, statistics and CRCs
    (tests/nodes/test_mcap_block_writer.py compares the two). What differs is the cost:
    ``Writer.add_message`` builds each Message record field by field in Python calls (as costly
    as simulating and encoding the message), whereas :meth:`add_messages` packs a block's
    record headers (opcode 0x05, record length, channel_id u16, sequence u32,
    log_time u64, publish_time u64) in one numpy array, joins them with the payloads in one
    ``bytes.join`` and builds each chunk's MessageIndex records (0x07: channel_id u16, then
    (log_time u64, offset u64) pairs) from arrays. The rarer records are mcap's own classes.
    """

    _HEAD = np.dtype([("op", "u1"), ("length", "<u8"), ("channel", "<u2"), ("sequence", "<u4"),
                      ("log", "<u8"), ("pub", "<u8")])
    """A Message record up to its data: 31 bytes (a packed structured dtype has no padding)."""
    _HEAD_SIZE = _HEAD.itemsize
    _PACK_HEAD = struct.Struct("<BQHIQQ")
    """The same header for one message."""

    def __init__(self, stream, *, chunk_size: int, compression: str, profile: str, library: str):
        self._f = stream
        self._limit = chunk_size
        self._compression = "" if compression == "none" else compression
        self._rb = RecordBuilder()
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._stats = Statistics(attachment_count=0, channel_count=0, channel_message_counts={},
                                 chunk_count=0, message_count=0, message_end_time=0,
                                 message_start_time=0, metadata_count=0, schema_count=0)
        # the chunk in progress: its records, and its messages' channel ids, log times, offsets
        self._records: list[bytes] = []
        self._fill = 0
        self._cid: list[int] = []
        self._log: list[int] = []
        self._off: list[int] = []
        self._f.write(MAGIC)
        Header(profile=profile, library=library).write(self._rb)
        self._emit()

    def _emit(self) -> None:
        self._f.write(self._rb.end())

    def _to_chunk(self, record) -> None:
        rb = RecordBuilder()
        record.write(rb)
        data = rb.end()
        self._records.append(data)
        self._fill += len(data)
        if self._fill > self._limit:
            self._finish_chunk()

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        self._stats.schema_count += 1
        self._to_chunk(schema)
        return schema.id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int,
                         metadata: dict[str, str]) -> int:
        channel = Channel(id=len(self._channels) + 1, topic=topic, message_encoding=message_encoding,
                          schema_id=schema_id, metadata=metadata)
        self._channels.append(channel)
        self._stats.channel_count += 1
        self._to_chunk(channel)
        return channel.id

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        offset = self._f.tell()
        Metadata(name=name, metadata=data).write(self._rb)
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=self._rb.count, name=name))
        self._stats.metadata_count += 1
        self._emit()

    def add_message(self, channel: int, log: int, pub: int, sequence: int, data: bytes) -> None:
        """Append one message (a live recorder's): :meth:`add_messages` without its numpy setup,
        which costs more than one message."""
        st = self._stats
        st.message_start_time = log if st.message_count == 0 else min(st.message_start_time, log)
        st.message_end_time = max(st.message_end_time, log)
        st.message_count += 1
        st.channel_message_counts[channel] = st.channel_message_counts.get(channel, 0) + 1
        self._cid.append(channel)
        self._log.append(log)
        self._off.append(self._fill)
        self._records += (self._PACK_HEAD.pack(0x05, self._HEAD_SIZE - 9 + len(data), channel, sequence,
                                               log, pub), data)
        self._fill += self._HEAD_SIZE + len(data)
        if self._fill > self._limit:
            self._finish_chunk()

    def add_messages(self, channel, log, pub, sequence, payloads: Sequence[bytes]) -> None:
        """Append ``len(payloads)`` messages in this order; ``channel``, ``log``, ``pub`` (ns)
        and ``sequence`` are arrays (or sequences) of one value per message, already checked."""
        n = len(payloads)
        if n == 0:
            return
        log = np.asarray(log, np.uint64)
        channel = np.asarray(channel, np.uint16)
        size = np.fromiter(map(len, payloads), np.int64, n) + self._HEAD_SIZE
        head = np.empty(n, self._HEAD)
        head["op"] = 0x05
        head["length"] = size - 9                       # a record's length excludes opcode and length
        head["channel"] = channel
        head["sequence"] = sequence
        head["log"] = log
        head["pub"] = pub
        heads = head.tobytes()
        at = range(0, n * self._HEAD_SIZE + 1, self._HEAD_SIZE)
        pieces = [b""] * (2 * n)
        pieces[0::2] = map(heads.__getitem__, map(slice, at[:-1], at[1:]))
        pieces[1::2] = payloads
        self._count(channel, log)
        end = np.cumsum(size)
        start = end - size
        i = 0
        while i < n:
            # the chunk closes after the first message whose end passes the limit
            j = int(np.searchsorted(end, self._limit - self._fill + start[i], side="right"))
            k = min(j + 1, n)
            self._records.append(b"".join(pieces[2 * i: 2 * k]))
            self._cid += channel[i:k].tolist()
            self._log += log[i:k].tolist()
            self._off += (start[i:k] - start[i] + self._fill).tolist()
            self._fill += int(end[k - 1] - start[i])
            i = k
            if j < n:
                self._finish_chunk()

    def _count(self, channel: np.ndarray, log: np.ndarray) -> None:
        """Statistics of a block: message counts per channel (keyed in order of first message, as
        Writer's), first and last log_time."""
        st = self._stats
        st.message_start_time = int(log.min()) if st.message_count == 0 \
            else min(st.message_start_time, int(log.min()))
        st.message_end_time = max(st.message_end_time, int(log.max()))
        st.message_count += log.size
        ids, first, counts = np.unique(channel, return_index=True, return_counts=True)
        for i in np.argsort(first, kind="stable").tolist():
            cid = int(ids[i])
            st.channel_message_counts[cid] = st.channel_message_counts.get(cid, 0) + int(counts[i])

    def _finish_chunk(self) -> None:
        if not self._cid:                       # schemas and channels alone wait for a message
            return
        data = b"".join(self._records)
        if self._compression == "zstd":
            packed = zstd.compress(data)
        elif self._compression == "lz4":
            packed = lz4frame.compress(data)
        else:
            packed = data
        cids = np.array(self._cid, np.uint16)
        log = np.array(self._log, np.uint64)
        off = np.array(self._off, np.uint64)
        chunk = Chunk(compression=self._compression, data=packed, message_start_time=int(log.min()),
                      message_end_time=int(log.max()), uncompressed_crc=zlib.crc32(data),
                      uncompressed_size=len(data))
        chunk_start = self._f.tell()
        chunk.write(self._rb)
        chunk_length = self._rb.count
        self._emit()
        index_start = pos = chunk_start + chunk_length
        ids, first = np.unique(cids, return_index=True)
        offsets, records = {}, []
        for cid in ids[np.argsort(first)].tolist():     # channels in order of first message
            mine = cids == cid
            pairs = np.column_stack((log[mine], off[mine])).astype("<u8").tobytes()
            records.append(struct.pack("<BQHI", 0x07, 6 + len(pairs), cid, len(pairs)) + pairs)
            offsets[cid] = pos
            pos += len(records[-1])
        self._f.write(b"".join(records))
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=chunk.message_start_time, message_end_time=chunk.message_end_time,
            chunk_start_offset=chunk_start, chunk_length=chunk_length, message_index_offsets=offsets,
            message_index_length=pos - index_start, compression=chunk.compression,
            compressed_size=len(packed), uncompressed_size=len(data)))
        self._stats.chunk_count += 1
        self._records, self._fill, self._cid, self._log, self._off = [], 0, [], [], []

    def flush(self) -> None:
        """Close the chunk in progress (if it holds a message) and flush the stream."""
        self._finish_chunk()
        self._f.flush()

    def finish(self) -> None:
        """The last chunk, DataEnd, the summary (schemas, channels, statistics, chunk indexes,
        attachment and metadata indexes, each group's SummaryOffset) and the footer, whose CRC
        covers the summary and the footer's own fields up to it."""
        self._finish_chunk()
        DataEnd(data_section_crc=0).write(self._rb)
        self._emit()
        summary_start = self._f.tell()
        sb = RecordBuilder()
        groups = []
        for opcode, records in ((Opcode.SCHEMA, self._schemas), (Opcode.CHANNEL, self._channels),
                                (Opcode.STATISTICS, [self._stats]),
                                (Opcode.CHUNK_INDEX, self._chunk_indexes), (Opcode.ATTACHMENT_INDEX, []),
                                (Opcode.METADATA_INDEX, self._metadata_indexes)):
            at = sb.count
            for r in records:
                r.write(sb)
            groups.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + at,
                                        group_length=sb.count - at))
        offsets_start = summary_start + sb.count
        for g in groups:
            g.write(sb)
        summary = sb.end()
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, offsets_start),
                         zlib.crc32(summary))
        self._f.write(summary)
        Footer(summary_start=summary_start, summary_offset_start=offsets_start, summary_crc=crc).write(self._rb)
        self._emit()
        self._f.write(MAGIC)

