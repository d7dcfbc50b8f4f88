"""Messages of an MCAP file one by one, in file order, through its index when it is finished and
with the stream reader when it is not (up to the first truncated or damaged record)."""

from __future__ import annotations

import os
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from .errors import CorruptRecordingError, NotMcapError, salvage_hint
from .mcapformat import CHUNK_MAX, CORRUPTION_ERRORS, MAGIC, lz4frame, norm_topic, zstd


@dataclass
class ScanReport:
    """Filled in by :func:`iter_messages` as it reads.

    ``complete``: the file has a valid footer and summary (None until known). ``note``: empty
    for a complete file, else what was found and where reading stopped. ``messages``: count
    of messages yielded. ``intact``: a sequential read went through to the footer without a
    damaged record (None when the file was read through its index instead). ``profile`` and
    ``library``: the file's header (``"ros2"`` for a rosbag2 file). ``channels``: every channel
    read, with its schema (None when schemaless), by channel id, whether or not a message of it
    was yielded (a topic may have none in the part of a damaged file that could be read).
    """

    complete: bool | None = None
    note: str = ""
    messages: int = 0
    intact: bool | None = None
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    profile: str = ""
    library: str = ""
    channels: dict[int, tuple[Schema | None, Channel]] = field(default_factory=dict)


def check_magic(path: str) -> int:
    """Raise NotMcapError unless ``path`` starts with the MCAP magic; return the file size."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(MAGIC))
            size = os.fstat(f.fileno()).st_size
    except IsADirectoryError:
        raise NotMcapError(f"{path}: is a directory, not an MCAP file") from None
    if head != MAGIC:
        what = "empty file" if not head else "does not start with the MCAP magic"
        raise NotMcapError(f"{path}: not an MCAP file ({what})")
    return size


def finished_file(f, size: int) -> tuple[bool, str]:
    """Does the open file end with a readable footer (and summary, when it has one)?"""
    if size < 2 * len(MAGIC) + 1:
        return False, "file ends before any footer"
    f.seek(size - len(MAGIC))
    if f.read(len(MAGIC)) != MAGIC:
        return False, "no closing magic (file not finished)"
    try:
        f.seek(0)
        SeekingReader(f).get_summary()
    except (*CORRUPTION_ERRORS, OSError) as e:  # OSError: a damaged offset seeks before 0
        return False, f"footer or summary unreadable ({type(e).__name__}: {e})"
    return True, ""


def scan(path: str, topics: Iterable[str] | None, report: ScanReport, *, stream: bool = False
          ) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """Messages of ``path`` in file order, with metadata collected into ``report``.

    A finished file is read through its index unless ``stream`` (used by :func:`recover`,
    which must salvage what precedes a damaged chunk even in a finished file).
    """
    size = check_magic(path)
    wanted = None if topics is None else {norm_topic(t) for t in ([topics] if isinstance(topics, str)
                                                              else topics)}
    with open(path, "rb") as f:
        ok, why = finished_file(f, size)
        report.complete = ok
        if ok and not stream:
            yield from _scan_seeking(path, f, wanted, report)
        else:
            yield from _scan_stream(path, f, size, wanted, report, ok, why)


def _scan_seeking(path, f, wanted, report):
    f.seek(0)
    reader = SeekingReader(f, validate_crcs=True)
    try:
        header = reader.get_header()
        report.profile, report.library = header.profile, header.library
        summary = reader.get_summary()
        if summary is not None:
            report.channels = {cid: (summary.schemas.get(c.schema_id), c)
                               for cid, c in summary.channels.items()}
        mcap_topics = None
        if wanted is not None and summary is not None:
            mcap_topics = [c.topic for c in summary.channels.values() if norm_topic(c.topic) in wanted]
        for item in reader.iter_messages(topics=mcap_topics, log_time_order=False):
            if wanted is None or norm_topic(item[1].topic) in wanted:
                report.messages += 1
                yield item
        for m in reader.iter_metadata():
            report.metadata[m.name] = dict(m.metadata)
    except (*CORRUPTION_ERRORS, OSError) as e:  # OSError: a damaged index seeks nowhere
        raise CorruptRecordingError(
            f"{path}: finished file with a damaged record after {report.messages} messages "
            f"({type(e).__name__}: {e}); {salvage_hint(path)}") from None


def _scan_stream(path, f, size, wanted, report, finished, why):
    f.seek(0)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    records = StreamReader(f, validate_crcs=True).records
    stop = "reached the footer"
    report.intact = True
    cut_chunk = None                 # (start, end) of a chunk that the file's end cuts
    while True:
        at = f.tell()                # where the next top-level record starts (inside a chunk: its end)
        try:
            record = next(records)
        except StopIteration:
            break
        except CORRUPTION_ERRORS as e:
            report.intact = False
            cut = _cut_record(f, at, size)
            if cut is None:
                reason = "file ends mid-record" if isinstance(e, (McapError, EOFError, struct.error)) \
                    else "bad record"
                stop = f"stopped at byte {f.tell()} of {size}: {reason} ({type(e).__name__})"
                break
            opcode, end = cut
            stop = (f"stopped at byte {at} of {size}: the file ends inside a "
                    f"{_OPCODE_NAMES.get(opcode, f'0x{opcode:02x}')} record that needs {end - at} bytes")
            if opcode == 0x06:
                cut_chunk = (at, end)
            break
        if isinstance(record, Message):
            channel = channels.get(record.channel_id)
            if channel is None:
                stop = (f"stopped at a message of unknown channel {record.channel_id} "
                        f"(byte {f.tell()} of {size})")
                report.intact = False
                break
            if wanted is None or norm_topic(channel.topic) in wanted:
                report.messages += 1
                yield schemas.get(channel.schema_id), channel, record
        elif isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
            report.channels[record.id] = (schemas.get(record.schema_id), record)
        elif isinstance(record, Metadata):
            report.metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Header):
            report.profile, report.library = record.profile, record.library
    if cut_chunk is not None:
        # the chunk in progress when the writer died: its records up to the cut are intact (a
        # truncation, not a corruption), though its CRC, over the whole chunk, cannot be checked
        before = report.messages
        for record in _cut_chunk_records(f, cut_chunk[0], size):
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
                report.channels[record.id] = (schemas.get(record.schema_id), record)
            elif record.channel_id not in channels:
                break
            elif wanted is None or norm_topic(channels[record.channel_id].topic) in wanted:
                report.messages += 1
                channel = channels[record.channel_id]
                yield schemas.get(channel.schema_id), channel, record
        stop += f" ({report.messages - before} of the messages read come from its intact start)"
    if not finished:
        report.note = (f"{path}: incomplete MCAP ({why}; unfinished recording, e.g. the writer "
                       f"was killed): read {report.messages} intact messages, {stop}")
    elif not report.intact:
        report.note = (f"{path}: finished MCAP with a damaged record: read {report.messages} "
                       f"intact messages, {stop}")


_OPCODE_NAMES = {0x01: "header", 0x02: "footer", 0x03: "schema", 0x04: "channel", 0x05: "message",
                 0x06: "chunk", 0x07: "message index", 0x08: "chunk index", 0x09: "attachment",
                 0x0A: "attachment index", 0x0B: "statistics", 0x0C: "metadata",
                 0x0D: "metadata index", 0x0E: "summary offset", 0x0F: "data end"}


def _cut_record(f, at: int, size: int) -> tuple[int, int] | None:
    """(opcode, end) of the record at byte ``at`` when the file's end cuts it, else None (the
    reader failed on damage, not on the end of the file)."""
    if at < len(MAGIC) or at >= size:
        return None
    f.seek(at)
    head = f.read(9)
    if len(head) < 9:
        return head[0], size + 1
    opcode, length = struct.unpack("<BQ", head)
    end = at + 9 + length
    return (opcode, end) if end > size else None


def _cut_chunk_records(f, at: int, size: int) -> Iterator:
    """Schema, Channel and Message records of the chunk at ``at`` that the file's end cuts, up to
    the first one the cut (or damage) reaches: the compressed prefix is decompressed as far as
    it goes (zstd and lz4 give every whole block; an uncompressed chunk every byte)."""
    f.seek(at)
    buf = f.read(size - at)
    try:
        _mst, _met, usize, _crc, clen = struct.unpack_from("<QQQII", buf, 9)
        off = 9 + 32
        comp = buf[off: off + clen].decode()
        off += clen
        (rlen,) = struct.unpack_from("<Q", buf, off)
    except (struct.error, UnicodeDecodeError):
        return
    data = buf[off + 8: off + 8 + rlen]
    limit = min(usize, CHUNK_MAX)
    dec = b""
    try:
        if comp == "":
            dec = data[:limit]
        elif comp == "zstd" and zstd is not None:
            import io
            out = bytearray()
            reader = zstd.ZstdDecompressor().stream_reader(io.BytesIO(data))
            try:
                while len(out) < limit:
                    piece = reader.read(min(1 << 20, limit - len(out)))
                    if not piece:
                        break
                    out += piece
            except zstd.ZstdError:
                pass                       # the blocks before the damage are kept
            dec = bytes(out)
        elif comp == "lz4" and lz4frame is not None:
            dec = lz4frame.LZ4FrameDecompressor().decompress(data, max_length=limit)
    except (*CORRUPTION_ERRORS, OSError):
        return
    import io

    from mcap.data_stream import ReadDataStream
    pos, n = 0, len(dec)
    while pos + 9 <= n:
        opcode, length = struct.unpack_from("<BQ", dec, pos)
        end = pos + 9 + length
        if end > n or opcode not in (0x03, 0x04, 0x05):
            return
        stream = ReadDataStream(io.BytesIO(dec[pos + 9: end]))
        try:
            yield (Schema.read(stream) if opcode == 0x03 else Channel.read(stream) if opcode == 0x04
                   else Message.read(stream, length))
        except CORRUPTION_ERRORS:
            return
        pos = end


def iter_messages(path: str | os.PathLike, topics: Iterable[str] | str | None = None, *,
                  report: ScanReport | None = None
                  ) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """Yield ``(schema, channel, message)`` mcap records of ``path`` in file order.

    ``topics`` filters by topic, with or without a leading ``/`` on either side. A finished
    file is read through its index; an unfinished one (no valid footer/summary) with the
    non-seeking stream reader, stopping at the first truncated or corrupt record. Pass a
    :class:`ScanReport` to learn which happened and to collect the metadata records.
    Raises NotMcapError if the file is not MCAP, CorruptRecordingError if a finished file has
    a damaged chunk.
    """
    yield from scan(os.fspath(path), topics, report if report is not None else ScanReport())


def channel_topics(path: str | os.PathLike) -> list[str] | None:
    """The topics (without a leading ``/``) of a finished file's channels, from its summary;
    None for a file without a readable summary. Raises NotMcapError for a file that is not MCAP."""
    path = os.fspath(path)
    size = check_magic(path)
    with open(path, "rb") as f:
        ok, _why = finished_file(f, size)
        if not ok:
            return None
        f.seek(0)
        try:
            summary = SeekingReader(f, validate_crcs=False).get_summary()
        except (*CORRUPTION_ERRORS, OSError):
            return None
    if summary is None:
        return None
    return sorted({norm_topic(c.topic) for c in summary.channels.values()})
