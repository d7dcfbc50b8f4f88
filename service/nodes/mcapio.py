"""MCAP recordings of noiselab streams: write, read back, salvage an unfinished file.

Conventions (DESIGN.md, "Wire contract (Zenoh and MCAP)"):

- one channel per stream, topic = the Zenoh key without a leading ``/``
  (``noiselab/<name>/<kind>``), message encoding ``json``, one registered JSON Schema per kind
  (schema encoding ``jsonschema``, names :data:`wire.SCHEMA_NAMES`);
- MCAP ``sequence`` = payload ``seq``. MCAP's sequence is a uint32, so past 2**32 - 1 it wraps
  modulo 2**32; the payload ``seq`` stays exact and is the one the reader returns;
- ``publish_time`` = the stream's wall-clock start + the sample's time from it, in integer ns
  (:mod:`wire`, "Time"; the start is ``start_time_ns`` in the ``noiselab`` metadata record);
  ``log_time`` = receive time in integer ns. Readers order and pace by publish_time and take a
  sample's time from the payload ``t``; they must not assume that either time is wall-clock (a
  foreign file's need not be). All times stay Python ints / int64, never float64.

Readers accept topics with or without a leading ``/``, find devices by the ``/measurement``
suffix, and treat an absent ``truth`` topic as normal (real data has none).

A writer that is killed (SIGKILL, power loss) leaves a file with no footer and no summary.
:func:`read_recording` still reads every message of every chunk that was fully written, with
the non-seeking stream reader, and says so in ``Recording.complete`` / ``Recording.note``;
:func:`recover` rewrites those messages into a finished file.

Where a writer's bytes go (:class:`RecordingWriter`): straight to the named file when nothing is
there, so a killed writer's unfinished file has the name the user gave; when ``force`` replaces
an existing file, to ``<name>.partial`` beside it, renamed over the old file only once finished
(``RecordingWriter.writing_path`` says which). A failed or interrupted write never spoils the old
file, and what it wrote stays where a ``noiselab recover`` finds it.
"""

from __future__ import annotations

import itertools
import operator
import os
import stat
import struct
import zlib
from contextlib import contextmanager
from collections import defaultdict
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version

import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import (Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Message, Metadata,
                          MetadataIndex, Schema, Statistics, SummaryOffset)
from mcap.stream_reader import StreamReader
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from .. import parallel
from . import wire

try:  # mcap depends on both; tolerate a stripped-down install all the same
    import zstandard as _zstd
except ImportError:  # pragma: no cover
    _zstd = None
try:
    import lz4.frame as _lz4
except ImportError:  # pragma: no cover
    _lz4 = None

__all__ = [
    "COMPRESSIONS",
    "channel_topics",
    "DEFAULT_COMPRESSION",
    "CorruptRecordingError",
    "DeviceData",
    "McapIoError",
    "McapWriteError",
    "NotMcapError",
    "PARTIAL_SUFFIX",
    "RecordingExistsError",
    "RecordingWriter",
    "Recording",
    "RecoverStats",
    "ScanReport",
    "shown",
    "TopicData",
    "gaps",
    "iter_messages",
    "iter_time_ordered",
    "read_recording",
    "recover",
]

MAGIC = b"\x89MCAP0\r\n"
"""The 8 bytes that open and close every MCAP file."""

SEQUENCE_MODULUS = 2**32
"""MCAP message ``sequence`` is a uint32: the writer stores ``seq % SEQUENCE_MODULUS``."""

_U64 = 2**64

_AVAILABLE = {"zstd": _zstd is not None, "lz4": _lz4 is not None, "none": True}
COMPRESSIONS: tuple[str, ...] = tuple(c for c, ok in _AVAILABLE.items() if ok)
"""Chunk compressions usable with the installed packages."""

DEFAULT_COMPRESSION: str = COMPRESSIONS[0]
"""``"zstd"`` when zstandard is installed, else ``"lz4"``, else ``"none"``."""

_COMPRESSION_TYPES = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                      "none": CompressionType.NONE}

# What a truncated or damaged record can raise from inside the mcap reader: short reads
# (EndOfFile is an McapError), struct unpacking of short buffers, CRC mismatch (ValueError),
# bad UTF-8, zstd/lz4 decompression failures, absurd lengths, ids or offsets that point
# nowhere (found by flipping single bits of real files).
_CORRUPTION_ERRORS: tuple[type[BaseException], ...] = (
    McapError, struct.error, ValueError, EOFError, RuntimeError, MemoryError, OverflowError,
    KeyError, IndexError,
) + ((_zstd.ZstdError,) if _zstd is not None else ())


def shown(text: str) -> str:
    """``text`` fit for a one-line message: control characters (a newline in a foreign file's
    topic) escaped as Python writes them, everything else (non-ASCII letters too) as it is."""
    text = str(text)
    return text if text.isprintable() else "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


class McapIoError(ValueError):
    """A recording that cannot be written or read as noiselab data (one-line message: whatever a
    file's topics or a library's error text hold, control characters come out escaped)."""

    def __str__(self) -> str:
        return shown(super().__str__())


class McapWriteError(McapIoError):
    """The output file cannot be written (disk full, a vanished directory, ...): the writer has
    ended; every later write raises this again. Not a bad message: a caller that skips bad
    messages stops on this one."""


class NotMcapError(McapIoError):
    """The file is not an MCAP file at all (no MCAP magic at its start)."""


class CorruptRecordingError(McapIoError):
    """A finished MCAP file whose data section is damaged (try :func:`recover`)."""


def _salvage(path) -> str:
    """The way out a user types, named in every corruption message."""
    return f"`noiselab recover {path} --out FIXED.mcap` salvages what comes before it"


class RecordingExistsError(FileExistsError):
    """The output path exists and overwriting was not asked for (``force=True``)."""

    def __str__(self) -> str:
        return f"{self.filename}: already exists; pass force=True (--force) to overwrite it"


def _library() -> str:
    try:
        ours = version("noiselab")
    except PackageNotFoundError:
        ours = "unknown"
    return f"noiselab/{ours} {LIBRARY_IDENTIFIER}"


def _check_str_dict(data, what: str) -> dict[str, str]:
    if not isinstance(data, dict):
        raise McapIoError(f"{what} must be a dict of str to str, got {type(data).__name__}")
    for k, v in data.items():
        if not isinstance(k, str) or not isinstance(v, str):
            raise McapIoError(f"{what}: entry {k!r}: {v!r} is not str to str")
    return dict(data)


def _check_u64(value, what: str) -> int:
    if isinstance(value, bool):
        raise McapIoError(f"{what}={value!r} must be an integer")
    try:
        value = operator.index(value)
    except TypeError:
        raise McapIoError(f"{what}={value!r} must be an integer (ns or count)") from None
    if not 0 <= value < _U64:
        raise McapIoError(f"{what}={value} is outside [0, 2**64)")
    return value


PARTIAL_SUFFIX = ".partial"
"""Suffix of the file a writer fills while an older file of the same name is kept (see
:class:`_Output`): ``run.mcap`` is written as ``run.mcap.partial`` and renamed when finished."""


def _os_error(path: str, exc: OSError, doing: str) -> McapIoError:
    """An OSError as a one-line McapIoError naming the path and the OS error (errno text)."""
    why = exc.strerror or type(exc).__name__
    return McapIoError(f"{path}: {doing} ({why})")


class _Output:
    """The file a writer fills, and what happens to it at the end.

    Nothing is ever lost: when ``path`` does not exist (always so without ``force``), the bytes go
    straight to ``path`` (created exclusively), so a writer killed mid-way leaves its unfinished
    file under the name the user gave, for :func:`recover`. When ``force`` replaces an existing
    regular file, the bytes go to ``path + PARTIAL_SUFFIX`` beside it and :meth:`commit` renames
    that over ``path`` (``os.replace``: atomic) only once the file is finished, so a write that
    fails leaves the old file as it was; a killed writer leaves the ``.partial`` file. A
    ``.partial`` that already exists is refused, not overwritten: it may be an unfinished recording
    of an earlier run (``suffix``: :func:`recover` uses its own, since the unfinished file it
    reads is often ``path.partial``). A ``path`` that is not a regular file (``/dev/null``, a FIFO) is written
    in place. OSErrors come out as one-line :class:`McapIoError` naming the path.
    """

    def __init__(self, path: str, force: bool, suffix: str = PARTIAL_SUFFIX) -> None:
        self.path = self.target = self.writing = path
        self.created = True
        if os.path.isdir(path):
            raise McapIoError(f"{path}: is a directory; give a file name")
        try:
            st = os.stat(path) if force else None
        except FileNotFoundError:
            st = None
        except OSError as e:
            raise _os_error(path, e, "cannot write it") from None
        if st is not None and stat.S_ISREG(st.st_mode):
            self.target = os.path.realpath(path) if os.path.islink(path) else path
            self.writing = self.target + suffix
        mode = "wb" if st is not None and self.writing == path else "xb"
        self.created = mode == "xb"
        try:
            self.file = open(self.writing, mode)
        except FileExistsError:
            if self.writing == path:
                raise RecordingExistsError(17, "File exists", path) from None
            raise McapIoError(f"{self.writing}: exists (an unfinished recording of an earlier run?); "
                              f"salvage it with `noiselab recover {self.writing} --out FIXED.mcap` or "
                              f"delete it, then write {path} again") from None
        except OSError as e:
            raise _os_error(self.writing, e, "cannot write it") from None

    @property
    def replaces(self) -> bool:
        """An older file at ``path`` is kept until :meth:`commit`."""
        return self.writing != self.target

    def commit(self) -> None:
        """Close the finished file (on disk first when it replaces one) and give it its name. An
        OSError is the caller's to handle (:meth:`abandon`: whether to keep the file is its call)."""
        if self.replaces:
            self.file.flush()
            os.fsync(self.file.fileno())
        self.file.close()
        if self.replaces:
            os.replace(self.writing, self.target)

    def abandon(self, keep: bool) -> None:
        """Close without committing; the file stays where it is if ``keep`` (else it is removed
        when this writer created it). An old file at ``path`` is never touched."""
        try:
            self.file.close()
        except OSError:
            pass
        if not keep and self.created:
            try:
                os.unlink(self.writing)
            except OSError:
                pass


# ------------------------------------------------------------------------------ writer


class _BlockWriter:
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
            packed = _zstd.compress(data)
        elif self._compression == "lz4":
            packed = _lz4.compress(data)
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


class RecordingWriter:
    """Write noiselab streams to a new MCAP file; a context manager that always finishes it.

    Parameters
    ----------
    path : str or os.PathLike
        Output file. An existing file is refused (:class:`RecordingExistsError`) unless
        ``force``; with ``force`` it is replaced only when the new file is finished: until then
        the bytes go to :attr:`writing_path` (``path`` + :data:`PARTIAL_SUFFIX`), see
        :class:`_Output`.
    chunk_size : int
        Bytes of uncompressed records per chunk (default 64 KiB). A chunk reaches the disk when
        it is full or on :meth:`flush`; a killed writer loses at most the chunk in progress.
    compression : str
        ``"zstd"``, ``"lz4"`` or ``"none"`` (default :data:`DEFAULT_COMPRESSION`).
    metadata : dict[str, str] or None
        Written at once as a metadata record named ``"noiselab"`` (e.g. model name, Ts).

    Schemas and channels are registered lazily, on the first message of a topic. On exit, even
    on an exception, the summary and footer are written, so the file is complete; but after an
    exception the file replaces no older one (it stays at :attr:`writing_path`, the exception
    says so in a note) and a file that holds no message is removed. An OSError while writing
    (disk full, ...) ends the writer with a one-line :class:`McapIoError` naming the file; the
    unfinished file is then kept if it holds messages, for :func:`recover`.
    """

    def __init__(self, path: str | os.PathLike, *, force: bool = False,
                 chunk_size: int = 64 * 1024, compression: str = DEFAULT_COMPRESSION,
                 metadata: dict[str, str] | None = None) -> None:
        self.path = os.fspath(path)
        if compression not in _COMPRESSION_TYPES:
            raise McapIoError(f"compression {compression!r} is unknown: use one of "
                              f"{', '.join(_COMPRESSION_TYPES)}")
        if not _AVAILABLE[compression]:
            raise McapIoError(f"compression {compression!r} needs a package that is not "
                              f"installed; available: {', '.join(COMPRESSIONS)}")
        if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
            raise McapIoError(f"chunk_size={chunk_size!r} must be an integer >= 1 (bytes)")
        meta = None if metadata is None else _check_str_dict(metadata, "metadata")
        self.compression = compression
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self._counts: dict[str, int] = defaultdict(int)
        self._closed = False
        self._failure = ""                      # why the writer ended early (an OSError), if it did
        self._out = _Output(self.path, force)
        self._file = self._out.file
        try:
            with self._io():
                self._writer = _BlockWriter(self._file, chunk_size=chunk_size, compression=compression,
                                            profile="", library=_library())
        except BaseException:
            if not self._closed:
                self._closed = True
                self._out.abandon(keep=False)
            raise
        if meta is not None:
            self.add_metadata("noiselab", meta)

    @property
    def writing_path(self) -> str:
        """The file the bytes go to until :meth:`close`: ``path`` itself, or ``path`` +
        :data:`PARTIAL_SUFFIX` while an older file at ``path`` is kept (``force=True``). A
        killed writer leaves its unfinished file there, for :func:`recover`."""
        return self._out.writing

    @contextmanager
    def _io(self):
        """Run file writes; an OSError (disk full, a vanished directory, ...) ends the writer and
        comes out as one line naming the file. The unfinished file is kept when it holds messages
        (what reached the disk is salvaged by :func:`recover`), else removed; an older file at
        ``path`` is never touched."""
        try:
            yield
        except OSError as e:
            self._closed = True
            held = sum(self._counts.values())
            self._out.abandon(keep=held > 0)
            where = f"; {self.path} is as it was" if self._out.replaces else ""
            kept = (f"; what reached the disk of its {held} messages is salvaged by "
                    f"`noiselab recover {self.writing_path} --out FIXED.mcap`") if held and self._out.created else ""
            self._failure = (f"{self.writing_path}: cannot write it "
                             f"({e.strerror or type(e).__name__}){where}{kept}")
            raise McapWriteError(self._failure) from None

    # -- context manager
    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is None:
            self.close()
            return
        # the body failed: the file is still finished (nothing written is lost) but it does not
        # replace an older file, and a file without a message is not left behind
        if self._closed:
            return
        self._closed = True
        held = sum(self._counts.values())
        try:
            self._writer.finish()
        except OSError:
            self._out.abandon(keep=held > 0)
            return
        if self._out.replaces or not held:
            self._out.abandon(keep=held > 0)
            if held and hasattr(exc, "add_note"):
                exc.add_note(f"{self.writing_path}: the {held} messages written are kept there; "
                             f"{self.path} is as it was")
        else:
            try:
                self._out.commit()
            except OSError:                     # the body's own exception is the one to see
                self._out.abandon(keep=True)

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def counts(self) -> dict[str, int]:
        """Messages written so far, per topic."""
        return dict(self._counts)

    def _check_open(self) -> None:
        if self._closed:
            if self._failure:
                raise McapWriteError(self._failure)
            raise McapIoError(f"{self.path}: recording is already finished")

    def channel(self, topic: str, kind: str) -> int:
        """Channel id of ``topic`` (registering its schema and channel on first use).

        ``topic`` is a key ``.../<kind>`` (a leading ``/`` is dropped); its last segment must be
        ``kind`` so readers find it (``/measurement`` suffix).
        """
        self._check_open()
        topic = topic.lstrip("/") if isinstance(topic, str) else topic
        known = self._channels.get(topic)
        if known is not None:
            if known[1] != kind:
                raise McapIoError(f"topic {topic!r} is registered as {known[1]}, not {kind}")
            return known[0]
        wire._check_kind(kind)
        parts = topic.split("/") if isinstance(topic, str) else []
        if len(parts) < 2 or parts[-1] != kind or not all(parts):
            raise McapIoError(f"topic {topic!r} must look like <prefix>/{kind} "
                              f"(e.g. {wire.key('dev', kind)})")
        schema_id = self._schemas.get(kind)
        with self._io():
            if schema_id is None:
                schema_id = self._writer.register_schema(
                    name=wire.SCHEMA_NAMES[kind], encoding=wire.SCHEMA_ENCODING,
                    data=wire.schema_bytes(kind))
                self._schemas[kind] = schema_id
            channel_id = self._writer.register_channel(
                topic=topic, message_encoding=wire.MESSAGE_ENCODING, schema_id=schema_id,
                metadata={"noiselab.kind": kind})
        self._channels[topic] = (channel_id, kind)
        return channel_id

    def write(self, topic: str, kind: str, seq: int, publish_time_ns: int, log_time_ns: int,
              payload: bytes) -> None:
        """Append one message: ``seq`` (payload seq), times in integer ns, JSON ``payload``."""
        channel_id = self.channel(topic, kind)
        seq = _check_u64(seq, "seq")
        log_time_ns = _check_u64(log_time_ns, "log_time_ns")
        publish_time_ns = _check_u64(publish_time_ns, "publish_time_ns")
        with self._io():
            self._writer.add_message(channel_id, log_time_ns, publish_time_ns, seq % SEQUENCE_MODULUS,
                                     bytes(payload))
        self._counts[topic.lstrip("/")] += 1

    def write_batch(self, topic: str, kind: str, seq0: int, publish_ns: np.ndarray,
                    log_ns: np.ndarray, payloads: Sequence[bytes]) -> None:
        """Append N consecutive messages ``seq0 .. seq0+N-1`` of one topic.

        ``publish_ns`` and ``log_ns`` are integer arrays (N,) in ns (int64 or uint64);
        ``payloads`` N bytes objects (e.g. from :func:`wire.encode_batch`).
        """
        self.write_interleaved([(topic, kind, seq0, publish_ns, log_ns, payloads)])

    def write_interleaved(self, streams: Sequence[tuple[str, str, int, np.ndarray, np.ndarray,
                                                        Sequence[bytes]]]) -> None:
        """Append N consecutive messages of several topics sample by sample, as a live source
        publishes them: message 0 of every stream (in the order given), then message 1, ...

        ``streams``: ``(topic, kind, seq0, publish_ns, log_ns, payloads)`` per topic, all with the
        same N (arguments as :meth:`write_batch`). Readers and ``replay`` then meet the topics
        together, not in per-topic blocks.
        """
        if not streams:
            return
        n = len(streams[0][5])
        k = len(streams)
        cids, seqs, pubs, logs = [], [], [], []
        payloads = [b""] * (n * k)
        for j, (topic, kind, seq0, publish_ns, log_ns, data) in enumerate(streams):
            if len(data) != n:
                raise McapIoError(f"{topic}: {len(data)} payloads where the other streams have {n}")
            cids.append(self.channel(topic, kind))
            seq0 = _check_u64(seq0, "seq0")
            pub, log = self._check_times(topic, publish_ns, log_ns, n)
            if not all(type(p) is bytes for p in data):
                raise McapIoError(f"{topic}: payloads must all be bytes")
            seqs.append((np.arange(n, dtype=np.uint64) + np.uint64(seq0 % SEQUENCE_MODULUS))
                        % np.uint64(SEQUENCE_MODULUS))
            pubs.append(pub.astype(np.uint64))      # int64 and uint64 side by side would stack as float
            logs.append(log.astype(np.uint64))
            payloads[j::k] = data
        # sample by sample: row i of each (n, k) array, read in C order, is message i of every stream
        with self._io():
            self._writer.add_messages(np.tile(np.asarray(cids, np.uint16), n), np.column_stack(logs).ravel(),
                                      np.column_stack(pubs).ravel(), np.column_stack(seqs).ravel(), payloads)
        for topic, *_ in streams:
            self._counts[topic.lstrip("/")] += n

    @staticmethod
    def _check_times(topic: str, publish_ns, log_ns, n: int):
        pub = np.asarray(publish_ns)
        log = np.asarray(log_ns)
        for arr, what in ((pub, "publish_ns"), (log, "log_ns")):
            if arr.shape != (n,) or arr.dtype.kind not in "iu":
                raise McapIoError(f"{topic}: {what} must be an integer array of shape ({n},), "
                                  f"got {arr.dtype} {arr.shape}")
            if n and arr.dtype.kind == "i" and arr.min() < 0:
                raise McapIoError(f"{topic}: {what} has negative times")
        return pub, log

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Write a metadata record ``name`` with string keys and values."""
        self._check_open()
        if not isinstance(name, str) or not name:
            raise McapIoError(f"metadata name {name!r} must be a non-empty str")
        data = _check_str_dict(data, f"metadata {name!r}")
        with self._io():
            self._writer.add_metadata(name, data)

    def flush(self, *, fsync: bool = False) -> None:
        """Write the chunk in progress to the file now (bounds what a kill can lose).

        Every flush ends a chunk, so flushing much more often than every ``chunk_size`` bytes
        worsens compression. ``fsync=True`` also asks the OS to put it on disk.
        """
        self._check_open()
        with self._io():
            self._writer.flush()
            if fsync:
                os.fsync(self._file.fileno())

    def close(self) -> None:
        """Write summary, footer and closing magic, close the file and give it its name (it
        replaces an older file only now); idempotent."""
        if self._closed:
            return
        with self._io():
            self._writer.finish()
            self._out.commit()
        self._closed = True


# --------------------------------------------------------------------------- scanning


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


def _check_magic(path: str) -> int:
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


def _finished(f, size: int) -> tuple[bool, str]:
    """Does the open file end with a readable footer (and summary, when it has one)?"""
    if size < 2 * len(MAGIC) + 1:
        return False, "file ends before any footer"
    f.seek(size - len(MAGIC))
    if f.read(len(MAGIC)) != MAGIC:
        return False, "no closing magic (file not finished)"
    try:
        f.seek(0)
        SeekingReader(f).get_summary()
    except (*_CORRUPTION_ERRORS, OSError) as e:  # OSError: a damaged offset seeks before 0
        return False, f"footer or summary unreadable ({type(e).__name__}: {e})"
    return True, ""


def _norm(topic: str) -> str:
    return topic.lstrip("/")


def _scan(path: str, topics: Iterable[str] | None, report: ScanReport, *, stream: bool = False
          ) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """Messages of ``path`` in file order, with metadata collected into ``report``.

    A finished file is read through its index unless ``stream`` (used by :func:`recover`,
    which must salvage what precedes a damaged chunk even in a finished file).
    """
    size = _check_magic(path)
    wanted = None if topics is None else {_norm(t) for t in ([topics] if isinstance(topics, str)
                                                              else topics)}
    with open(path, "rb") as f:
        ok, why = _finished(f, size)
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
            mcap_topics = [c.topic for c in summary.channels.values() if _norm(c.topic) in wanted]
        for item in reader.iter_messages(topics=mcap_topics, log_time_order=False):
            if wanted is None or _norm(item[1].topic) in wanted:
                report.messages += 1
                yield item
        for m in reader.iter_metadata():
            report.metadata[m.name] = dict(m.metadata)
    except (*_CORRUPTION_ERRORS, OSError) as e:  # OSError: a damaged index seeks nowhere
        raise CorruptRecordingError(
            f"{path}: finished file with a damaged record after {report.messages} messages "
            f"({type(e).__name__}: {e}); {_salvage(path)}") from None


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
        except _CORRUPTION_ERRORS as e:
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
            if wanted is None or _norm(channel.topic) in wanted:
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
            elif wanted is None or _norm(channels[record.channel_id].topic) in wanted:
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
    limit = min(usize, _CHUNK_MAX)
    dec = b""
    try:
        if comp == "":
            dec = data[:limit]
        elif comp == "zstd" and _zstd is not None:
            import io
            out = bytearray()
            reader = _zstd.ZstdDecompressor().stream_reader(io.BytesIO(data))
            try:
                while len(out) < limit:
                    piece = reader.read(min(1 << 20, limit - len(out)))
                    if not piece:
                        break
                    out += piece
            except _zstd.ZstdError:
                pass                       # the blocks before the damage are kept
            dec = bytes(out)
        elif comp == "lz4" and _lz4 is not None:
            dec = _lz4.LZ4FrameDecompressor().decompress(data, max_length=limit)
    except (*_CORRUPTION_ERRORS, OSError):
        return
    from mcap.data_stream import ReadDataStream
    import io
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
        except _CORRUPTION_ERRORS:
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
    yield from _scan(os.fspath(path), topics, report if report is not None else ScanReport())


_KIND_RANK = {"truth": 0, "command": 1, "measurement": 2, "end": 4}
"""Order of the topics of one sample when publish times tie: the emulator's (truth, command,
measurement); other topics after them, by topic; the end of stream last (its source sends it
after everything else, the last health report of its final instant included)."""


def _tie_rank(channels: dict[int, Channel]) -> dict[int, int]:
    order = sorted(channels, key=lambda cid: (_KIND_RANK.get(_norm(channels[cid].topic).rsplit("/", 1)[-1], 3),
                                              _norm(channels[cid].topic), cid))
    return {cid: i for i, cid in enumerate(order)}


def channel_topics(path: str | os.PathLike) -> list[str] | None:
    """The topics (without a leading ``/``) of a finished file's channels, from its summary;
    None for a file without a readable summary. Raises NotMcapError for a file that is not MCAP."""
    path = os.fspath(path)
    size = _check_magic(path)
    with open(path, "rb") as f:
        ok, _why = _finished(f, size)
        if not ok:
            return None
        f.seek(0)
        try:
            summary = SeekingReader(f, validate_crcs=False).get_summary()
        except (*_CORRUPTION_ERRORS, OSError):
            return None
    if summary is None:
        return None
    return sorted({_norm(c.topic) for c in summary.channels.values()})


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
    size = _check_magic(path)
    with open(path, "rb") as f:
        ok, _why = _finished(f, size)
        summary = None
        if ok:
            f.seek(0)
            reader = SeekingReader(f, validate_crcs=False)
            try:
                summary = reader.get_summary()
                metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            except (*_CORRUPTION_ERRORS, OSError):
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
        dec = _chunk_records(f, ci, path)
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
                                            data=dec[pos + _MESSAGE_HEADER: pos + 9 + rl]))
                pos += 9 + rl
        except (struct.error, CorruptRecordingError) as e:
            raise CorruptRecordingError(f"{path}: finished file with a damaged chunk at byte "
                                        f"{ci.chunk_start_offset} ({type(e).__name__}); {_salvage(path)}") from None
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
    source restarted from 0). Unlike :func:`_streams` on seq, a restart whose first samples were
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

    for item in _scan(path, None, report):
        channel = item[1]
        q = queues.get(channel.id)
        if q is None:
            q = queues[channel.id] = deque()
            segments[channel.id] = _Segments()
            topic = _norm(channel.topic)
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


def gaps(seq_array) -> list[tuple[int, int]]:
    """Sequence gaps: ``[(after_seq, missing_count), ...]`` in order of appearance.

    ``seq_array`` is a 1-D integer sequence in arrival or sorted order. Every step
    ``s[i+1] - s[i] > 1`` is reported as ``(s[i], s[i+1] - s[i] - 1)``. Repeats and backward
    steps (duplicates, reordering) are not gaps and are not reported; sort first if the
    order may be shuffled. A stream that starts after 0 is not reported either: check
    ``s[0]`` for messages lost before the first one received.
    """
    s = np.asarray(seq_array)
    if s.ndim != 1 or (s.size and s.dtype.kind not in "iu"):
        raise McapIoError(f"gaps() needs a 1-D integer array, got {s.dtype} {s.shape}")
    if s.size < 2:
        return []
    s = s.astype(np.int64, copy=False)
    d = np.diff(s)
    idx = np.flatnonzero(d > 1)
    return [(int(s[i]), int(d[i]) - 1) for i in idx]


@dataclass(frozen=True, eq=False)
class TopicData:
    """One stream of a recording: its stream segments in file order, each sorted by payload seq
    (stable), every sample once.

    ``seq`` int64 (N,) payload seq; ``t`` float64 (N,) payload sample time in s;
    ``publish_ns`` int64 (N,) MCAP publish_time (sample time, ns); ``log_ns`` int64 (N,) MCAP
    log_time (receive time in ns, any clock); ``values`` float64 (N, dim): x, u or y.

    ``starts`` int64: the index where each stream segment begins (``[0]`` for a stream that never
    restarted). A segment begins where the source restarted: its seq stepped back, in file order,
    below every seq of the segment or to one the segment holds with another sample (a restarted
    emulator counts from 0 again; its first samples may be lost), see :func:`_streams`.
    ``duplicates``: messages dropped as repeats of a sample already read (same seq, same ``t`` and
    values, bit for bit); the first one read is kept.
    """

    topic: str
    kind: str
    seq: np.ndarray
    t: np.ndarray
    publish_ns: np.ndarray
    log_ns: np.ndarray
    values: np.ndarray
    starts: np.ndarray = field(default_factory=lambda: np.zeros(1, np.int64))
    duplicates: int = 0

    def __len__(self) -> int:
        return int(self.seq.shape[0])

    @property
    def dim(self) -> int:
        return int(self.values.shape[1])

    @property
    def segments(self) -> list[tuple[int, int]]:
        """``[(start, stop), ...]``: the index range of each stream segment, in file order."""
        ends = [*self.starts.tolist()[1:], len(self)]
        return list(zip(self.starts.tolist(), ends))

    def segment(self, i: int) -> TopicData:
        """Segment ``i`` (0-based) as a TopicData of one segment."""
        a, b = self.segments[i]
        return TopicData(self.topic, self.kind, self.seq[a:b], self.t[a:b], self.publish_ns[a:b],
                         self.log_ns[a:b], self.values[a:b])

    def gaps(self) -> list[tuple[int, int]]:
        """:func:`gaps` of ``seq``, segment by segment (a restart is not a gap)."""
        return [g for a, b in self.segments for g in gaps(self.seq[a:b])]


def _streams(path: str, topic: str, kind: str, seq: np.ndarray, t: np.ndarray, values: np.ndarray,
             pub: np.ndarray, log: np.ndarray) -> TopicData:
    """The TopicData of one topic's messages in file order: split where the source restarted,
    each segment sorted by seq, exact repeats dropped; a seq that comes twice with different data
    where no restart explains it raises McapIoError (the recording cannot say which sample is the
    real one).

    Messages are taken in file order, each continuing the current segment (one run of the source)
    unless it starts a new one. Only a step back (a seq below the one before it) can: it is

    * a repeat, dropped, when the segment holds that seq with the same sample, bit for bit (``t``
      and values: a re-sent or twice-routed message); except the segment's lowest seq sent again
      and followed by its successor, which is a source restarted that sends the same samples
      again (same seed): a new segment;
    * a late message, sorted into the segment, when the segment lacks that seq but holds a lower
      one (a reordered message fills its gap);
    * a restart, a new segment, when the segment holds that seq with another sample (the source
      counted again and the samples after its restart were lost before this one) or holds only
      higher seqs (it counted from below them): provided the file order tells the two runs apart,
      that is every message between the segment's copy of the seq and this one has a higher seq
      (the first run went on past it before the source counted again), and the message after
      this one does not go beyond every seq of the segment (which would be the first run going
      on, not a new one).

    A seq twice with different data that is not such a restart is ambiguous and refused: at once
    again with other data (no step back), reached again going forward, or two runs advancing side
    by side (two sources publishing on one key: the other run's lower seqs come between the two
    copies, or the first run goes on right after the second one's message). The rule reads only
    the messages, so a finished recording and the same one cut short (a killed recorder, whose
    metadata is never written) read alike.

    Vectorised: a stream without restarts, repeats or reordering (every seq step > 0) costs one
    np.diff; the others a stable sort, and a Python step per step back only (:func:`_restarts`).
    """
    n = seq.size
    d = np.diff(seq)
    if n < 2 or d.min() > 0:
        return TopicData(topic, kind, seq, t, pub, log, values)
    tb = np.ascontiguousarray(t, np.float64).view(np.uint64)
    vb = np.ascontiguousarray(values, np.float64).reshape(n, -1).view(np.uint64)

    def same(a, b):                              # rows a and b hold the same sample, bit for bit
        return (tb[a] == tb[b]) & (vb[a] == vb[b]).all(axis=-1)

    seg = np.zeros(n, np.int64)
    back = np.flatnonzero(d < 0) + 1
    if back.size:
        seg[_restarts(seq, back, same)] = 1
        np.cumsum(seg, out=seg)
    order = np.lexsort((seq, seg))                # stable: equal seqs keep their file order
    s2, g2 = seq[order], seg[order]
    twin = np.flatnonzero((s2[1:] == s2[:-1]) & (g2[1:] == g2[:-1]))
    if twin.size:
        a, b = order[twin], order[twin + 1]
        differ = ~same(a, b)
        if differ.any():
            bad = np.unique(seq[a[differ]])
            more = f" (and {bad.size - 1} more such seqs)" if bad.size > 1 else ""
            raise McapIoError(f"{path}: topic {topic!r}: seq {int(bad[0])} comes twice with different "
                              f"data{more}; the recording is ambiguous (two sources on one key?)")
        keep = np.ones(n, bool)
        keep[twin + 1] = False
        order, g2 = order[keep], g2[keep]
    starts = np.concatenate([[0], np.flatnonzero(np.diff(g2)) + 1]).astype(np.int64)
    return TopicData(topic, kind, seq[order], t[order], pub[order], log[order], values[order],
                     starts=starts, duplicates=int(twin.size))


def _restarts(seq: np.ndarray, back: np.ndarray, same) -> list[int]:
    """The file positions where a new stream segment begins, by :func:`_streams`' rule; ``back``:
    the positions of the steps back (``seq[i] < seq[i - 1]``), ascending; ``same(a, b)``: whether
    positions a and b hold the same sample.

    Between two steps back the seqs do not decrease, so the lowest seq of a stretch of the segment
    is its first one's or a step back's: the seqs between a copy at ``j`` and a step back at ``i``
    are all higher than ``v`` iff ``seq[j + 1]`` and every step back kept in the segment after
    ``j + 1`` are. The steps back kept are held as suffix minima (values rising with position), so
    that question costs a bisection. A copy of ``v`` in the segment is found in a stable argsort of
    the seqs (the positions of one seq ascending)."""
    from bisect import bisect_right

    n = int(seq.size)
    by_seq = np.argsort(seq, kind="stable")
    sorted_seq = seq[by_seq]
    starts: list[int] = []
    begin = 0                                   # the current segment's first position
    low = high = int(seq[0])                    # its lowest and highest seq so far
    kept_pos: list[int] = []                    # its steps back kept, as suffix minima
    kept_val: list[int] = []
    for i in back.tolist():
        v = int(seq[i])
        high = max(high, int(seq[i - 1]))
        a, b = np.searchsorted(sorted_seq, v, "left"), np.searchsorted(sorted_seq, v, "right")
        k = int(np.searchsorted(by_seq[a:b], i)) - 1      # the last copy of v before i
        j = int(by_seq[a + k]) if k >= 0 and by_seq[a + k] >= begin else None
        nxt = int(seq[i + 1]) if i + 1 < n else None
        if j is None:                           # below every seq of the segment, or a late message
            restart = v < low
        elif same(i, j):                        # a repeat, or the same samples from the start again
            restart = v == low and nxt == v + 1
        else:                                   # another sample: a restart if the runs are apart
            after = bisect_right(kept_pos, j + 1)
            between = min(int(seq[j + 1]), kept_val[after] if after < len(kept_val) else v + 1)
            restart = between > v
        if restart and nxt is not None and nxt > high:
            restart = False                     # the first run goes on after it: side by side
        if restart:
            starts.append(i)
            begin, low, high = i, v, v
            kept_pos.clear()
            kept_val.clear()
        else:
            low = min(low, v)
            while kept_val and kept_val[-1] >= v:
                kept_val.pop()
                kept_pos.pop()
            kept_pos.append(i)
            kept_val.append(v)
    return starts


@dataclass(frozen=True)
class DeviceData:
    """The streams of one device (found by its ``<prefix>/measurement`` topic), per kind."""

    name: str
    prefix: str
    streams: dict[str, TopicData]

    @property
    def measurement(self) -> TopicData:
        return self.streams["measurement"]

    @property
    def command(self) -> TopicData | None:
        return self.streams.get("command")

    @property
    def truth(self) -> TopicData | None:
        return self.streams.get("truth")


@dataclass(frozen=True)
class Recording:
    """What :func:`read_recording` found.

    ``devices`` by device name (``noiselab/<name>/...`` gives ``name``; a foreign prefix such as
    ``/robot/imu/measurement`` gives ``robot/imu``). ``metadata``: metadata records by name.
    ``complete``: the file had a valid footer and summary. ``note``: empty if complete, else
    why not and how far the salvage got. ``messages``: messages read, of every topic.
    """

    path: str
    devices: dict[str, DeviceData]
    metadata: dict[str, dict[str, str]]
    complete: bool
    note: str
    messages: int = 0

    def device(self, name: str | None = None) -> DeviceData:
        """The device ``name``; without a name, the only device (error if there are several)."""
        if name is None:
            if len(self.devices) == 1:
                return next(iter(self.devices.values()))
            raise McapIoError(f"{self.path}: holds {len(self.devices)} devices "
                              f"({', '.join(sorted(self.devices)) or 'none'}); name one")
        try:
            return self.devices[name]
        except KeyError:
            raise McapIoError(f"{self.path}: no device {name!r}; found "
                              f"{', '.join(sorted(self.devices)) or 'none'}") from None


def _as_i64(values, topic: str, what: str) -> np.ndarray:
    """list of ints or uint64 array -> int64 (times beyond 2**63 - 1 ns are refused)."""
    if isinstance(values, np.ndarray) and values.dtype == np.uint64:
        if values.size and int(values.max()) > 2**63 - 1:
            raise McapIoError(f"{topic}: {what} beyond 2**63 - 1 ns is not supported")
        return values.astype(np.int64)
    try:
        return np.array(values, dtype=np.int64)
    except OverflowError:
        raise McapIoError(f"{topic}: {what} beyond 2**63 - 1 ns is not supported") from None


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == "":
        return bytes(data)
    if compression == "zstd":
        import zstandard
        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if compression == "lz4":
        import lz4.frame
        return lz4.frame.decompress(data)
    raise CorruptRecordingError(f"unknown chunk compression {compression!r}")


@dataclass(frozen=True, eq=False)
class _Packed:
    """The payloads of one topic in one buffer: payload i is ``blob[starts[i]:starts[i] + lens[i]]``
    and every payload is followed by ``b"\\n"`` (the layout :func:`wire.decode_packed` parses)."""

    blob: bytes
    lens: np.ndarray

    def __len__(self) -> int:
        return int(self.lens.size)

    def payloads(self) -> list[bytes]:
        ends = np.cumsum(self.lens + 1) - 1
        starts = ends - self.lens
        return [self.blob[a:b] for a, b in zip(starts.tolist(), ends.tolist())]


PARALLEL_DECODE = 200_000   # messages over a recording's topics from which two are parsed at once (a fork)
_MESSAGE_HEADER = 31        # opcode 1, length 8, channel 2, sequence 4, log_time 8, publish_time 8


def _read_span(f, offset: int, length: int) -> bytes | None:
    """``length`` bytes at ``offset``, or None when the span does not lie inside the file (a
    damaged index: reading it as asked would allocate whatever it says)."""
    size = os.fstat(f.fileno()).st_size
    if not (0 <= offset <= size and 0 <= length <= size - offset):
        return None
    f.seek(offset)
    return f.read(length)


_CHUNK_MAX = 1 << 30
"""Bytes a chunk may decompress to (its header's uncompressed size is trusted up to this): chunks
are kilobytes to megabytes; a damaged size must not make the reader allocate it."""


def _chunk_records(f, ci, path: str) -> bytes:
    """The decompressed, CRC-checked records of the chunk that ``ci`` (a ChunkIndex) points to."""
    buf = _read_span(f, ci.chunk_start_offset, ci.chunk_length)
    try:
        if buf is None:
            raise CorruptRecordingError("the index points outside the file")
        if buf[0] != 0x06:
            raise CorruptRecordingError("not a chunk record")
        _mst, _met, usize, ucrc = struct.unpack_from("<QQQI", buf, 9)
        if usize > _CHUNK_MAX:
            raise CorruptRecordingError(f"an uncompressed size of {usize} bytes")
        off = 9 + 28
        (clen,) = struct.unpack_from("<I", buf, off)
        comp = buf[off + 4: off + 4 + clen].decode()
        off += 4 + clen
        (rlen,) = struct.unpack_from("<Q", buf, off)
        dec = _decompress(comp, buf[off + 8: off + 8 + rlen], usize)
    except Exception as e:      # struct.error, IndexError, UnicodeDecodeError, codec errors
        raise CorruptRecordingError(f"{path}: finished file with a damaged chunk at byte {ci.chunk_start_offset} "
                                    f"({type(e).__name__}); {_salvage(path)}") from None
    if ucrc and zlib.crc32(dec) != ucrc:
        raise CorruptRecordingError(f"{path}: finished file with a chunk at byte {ci.chunk_start_offset} that fails its CRC; "
                                    + _salvage(path))
    return dec


def _walk_offsets(dec: bytes, cids: set[int]) -> dict[int, list[int]] | None:
    """Offsets of the message records of channels ``cids`` in a chunk, by walking every record;
    None when a record's header is cut by the chunk's end."""
    unpack_q, unpack_h = struct.Struct("<Q").unpack_from, struct.Struct("<H").unpack_from
    out: dict[int, list[int]] = {cid: [] for cid in cids}
    pos, n = 0, len(dec)
    while pos < n:
        if pos + (11 if dec[pos] == 0x05 else 9) > n:
            return None
        (rl,) = unpack_q(dec, pos + 1)
        if dec[pos] == 0x05:
            got = out.get(unpack_h(dec, pos + 9)[0])
            if got is not None:
                got.append(pos)
        pos += 9 + rl
    return out


def _index_offsets(f, ci, cids: list[int]) -> dict[int, np.ndarray] | None:
    """Offsets of the message records of ``cids`` in a chunk from its MessageIndex records (one
    read, parsed with numpy); None when the chunk has no usable index."""
    mio = ci.message_index_offsets
    if not mio or not all(cid in mio for cid in cids):
        return None
    base = min(mio.values())
    sec = _read_span(f, base, ci.message_index_length)
    if sec is None:
        return None
    out = {}
    for cid in cids:
        at = mio[cid] - base
        if at < 0 or at + 15 > len(sec) or sec[at] != 0x07:
            return None
        (rec_len,) = struct.unpack_from("<Q", sec, at + 1)
        ch, nbytes = struct.unpack_from("<HI", sec, at + 9)
        if ch != cid or nbytes % 16 or at + 15 + nbytes > len(sec) or nbytes + 6 > rec_len:
            return None
        pairs = np.frombuffer(sec, dtype="<u8", count=nbytes // 8, offset=at + 15).reshape(-1, 2)
        if pairs.size and pairs[:, 1].max() >= _CHUNK_MAX:
            return None                        # an offset past any chunk: a damaged index
        out[cid] = np.sort(pairs[:, 1]).astype(np.int64)
    return out


def _at_every_byte(dec: bytes, dtype: str) -> np.ndarray:
    """A view of ``dec`` with one (unaligned) little-endian integer starting at every byte."""
    size = np.dtype(dtype).itemsize
    return np.ndarray(buffer=dec, dtype=dtype, shape=(max(len(dec) - size + 1, 0),), strides=(1,))


def _topic_messages(dec: bytes, u8: np.ndarray, offs: np.ndarray, cids: set[int]):
    """(starts, ends, log, pub) of the message records at ``offs`` (sorted), or None when they are
    not message records of ``cids`` that lie inside the chunk without overlapping."""
    n = len(dec)
    if offs.size == 0:
        e = np.empty(0, np.int64)
        return e, e, e.astype(np.uint64), e.astype(np.uint64)
    if offs.min() < 0 or offs.max() + _MESSAGE_HEADER > n:
        return None
    if np.any(u8[offs] != 0x05):
        return None
    u64 = _at_every_byte(dec, "<u8")
    ch = _at_every_byte(dec, "<u2")[offs + 9]
    if not np.isin(ch, list(cids)).all():
        return None
    rl = u64[offs + 1]
    if np.any(rl < _MESSAGE_HEADER - 9) or np.any(rl > n):
        return None
    ends = offs + 9 + rl.astype(np.int64)
    if ends[-1] > n or np.any(ends[:-1] > offs[1:]):
        return None
    return offs + _MESSAGE_HEADER, ends, u64[offs + 15], u64[offs + 23]


def _collect_fast(path: str, kinds: tuple[str, ...], report: ScanReport):
    """Payloads, log and publish times per topic of a *finished* file, read chunk by chunk at the
    struct level (mcap's dataclass reader costs ~20 us per message). Chunks that hold none of the
    wanted topics (per the chunk index) are skipped; in the others the wanted messages are found
    from the chunk's MessageIndex records (numpy), cross-checked against the summary's message
    counts and the records themselves; without an index (or when it disagrees) every record is
    walked in Python. Chunk CRCs are checked. Returns (raw, encodings), raw[topic] =
    (:class:`_Packed`, log_time uint64, publish_time uint64), or None when the fast path does not
    apply (unfinished file, no chunk index): the caller then uses :func:`iter_messages`."""
    size = _check_magic(path)
    with open(path, "rb") as f:
        ok, _why = _finished(f, size)
        if not ok:
            return None
        f.seek(0)
        reader = SeekingReader(f, validate_crcs=False)
        try:
            summary = reader.get_summary()
        except (*_CORRUPTION_ERRORS, OSError):
            return None
        if summary is None or not summary.chunk_indexes:
            return None
        encodings: dict[str, set[str]] = defaultdict(set)
        cids_of: dict[str, set[int]] = defaultdict(set)       # normalised topic -> channel ids
        for cid, c in summary.channels.items():
            topic = _norm(c.topic)
            if topic.rsplit("/", 1)[-1] in kinds:
                cids_of[topic].add(cid)
                encodings[topic].add(c.message_encoding)
        stats = summary.statistics
        expected = None if stats is None else {cid: stats.channel_message_counts.get(cid, 0)
                                                for cids in cids_of.values() for cid in cids}
        chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
        for use_index in ((True, False) if expected is not None else (False,)):
            got = _collect_chunks(f, path, chunks, cids_of, use_index)
            if got is None:
                continue
            raw, counts = got
            if use_index and any(counts.get(cid, 0) != k for cid, k in expected.items()):
                continue                       # the index does not account for every message: walk
            break
        report.messages += sum(counts.values())
        try:
            for m in reader.iter_metadata():
                report.metadata[m.name] = dict(m.metadata)
        except (*_CORRUPTION_ERRORS, OSError):
            return None                        # a damaged metadata index: the stream reader says where
    report.complete = True
    return raw, encodings


def _collect_chunks(f, path, chunks, cids_of, use_index: bool):
    """One pass of :func:`_collect_fast` over the chunks; None if an index turns out unusable."""
    parts: dict[str, tuple[list, list, list, list]] = {t: ([], [], [], []) for t in cids_of}
    counts: dict[int, int] = defaultdict(int)
    all_cids = {cid for cids in cids_of.values() for cid in cids}
    for ci in chunks:
        mio = ci.message_index_offsets
        present = [cid for cid in all_cids if cid in mio] if (use_index and mio) else sorted(all_cids)
        if use_index and mio and not present:
            continue                           # none of the wanted channels in this chunk
        dec = _chunk_records(f, ci, path)
        u8 = np.frombuffer(dec, np.uint8)
        offs = _index_offsets(f, ci, present) if use_index else None
        if use_index and offs is None:
            return None
        if offs is None:
            walked = _walk_offsets(dec, set(present))
            if walked is None:
                raise CorruptRecordingError(f"{path}: finished file with a damaged chunk at byte "
                                            f"{ci.chunk_start_offset}; {_salvage(path)}")
            offs = {cid: np.asarray(v, np.int64) for cid, v in walked.items()}
        for topic, cids in cids_of.items():
            here = [offs[c] for c in cids if c in offs]
            if not here:
                continue
            o = here[0] if len(here) == 1 else np.sort(np.concatenate(here))
            if o.size == 0:
                continue
            msgs = _topic_messages(dec, u8, o, cids)
            if msgs is None:
                if use_index:
                    return None
                raise CorruptRecordingError(f"{path}: finished file with a damaged chunk at byte "
                                            f"{ci.chunk_start_offset}; {_salvage(path)}")
            starts, ends, log, pub = msgs
            blob = b"\n".join(map(dec.__getitem__, map(slice, starts.tolist(), ends.tolist()))) + b"\n"
            acc = parts[topic]
            acc[0].append(blob)
            acc[1].append(ends - starts)
            acc[2].append(log)
            acc[3].append(pub)
            for c in cids:
                if c in offs:
                    counts[c] += int(offs[c].size)
    raw = {}
    for topic, (blobs, lens, log, pub) in parts.items():
        if not blobs:
            continue
        raw[topic] = (_Packed(b"".join(blobs), np.concatenate(lens)), np.concatenate(log), np.concatenate(pub))
    return raw, counts


def read_recording(path: str | os.PathLike, kinds: Iterable[str] = wire.KINDS) -> Recording:
    """Read every noiselab device of an MCAP file into arrays (see :class:`Recording`).

    Devices are found by topics ending in ``/measurement`` (leading ``/`` optional); their
    ``command`` and ``truth`` topics are read when present (``kinds`` limits which). Other
    topics are ignored. Payloads are validated (:func:`wire.decode_batch`); a device topic whose
    message encoding is not ``json`` raises McapIoError. Works on unfinished files
    (``complete=False``). Finished files take a fast chunk-level path.
    """
    path = os.fspath(path)
    kinds = tuple(k for k in wire.KINDS if k in set(kinds) | {"measurement"})
    report = ScanReport()
    fast = _collect_fast(path, kinds, report)
    if fast is not None:
        raw, encodings = fast
    else:
        report = ScanReport()
        # per normalised topic: payloads, log_time, publish_time; and its encodings
        raw = {}
        encodings = defaultdict(set)
        for _schema, channel, msg in iter_messages(path, report=report):
            topic = _norm(channel.topic)
            lists = raw.get(topic)
            if lists is None:
                lists = raw[topic] = ([], [], [])
                encodings[topic].add(channel.message_encoding)
            lists[0].append(msg.data)
            lists[1].append(msg.log_time)
            lists[2].append(msg.publish_time)

    devices: dict[str, DeviceData] = {}
    jobs = []                                   # (device name, prefix, kind, topic), devices sorted
    names: dict[str, str] = {}
    for topic in sorted(t for t in raw if t.endswith("/measurement")):
        prefix = topic[: -len("/measurement")]
        name = prefix[len("noiselab/"):] if prefix.startswith("noiselab/") else prefix
        if name in names.values():  # e.g. both "noiselab/imu" and "imu": keep them apart
            name = prefix
        names[prefix] = name
        for kind in kinds:
            ktopic = f"{prefix}/{kind}"
            if ktopic not in raw:
                continue
            bad = encodings[ktopic] - {wire.MESSAGE_ENCODING}
            if bad:
                raise McapIoError(f"{path}: topic {ktopic!r} has message encoding "
                                  f"{sorted(bad)[0]!r}; noiselab reads 'json' only")
            jobs.append((name, prefix, kind, ktopic))

    def decode(job):
        kind, ktopic = job[2], job[3]
        payloads = raw[ktopic][0]
        if isinstance(payloads, _Packed):
            return wire.decode_packed(payloads.blob, payloads.lens, kind, topic=shown(ktopic))
        return wire.decode_batch(payloads, kind, topic=shown(ktopic))

    sizes = [len(raw[j[3]][0]) for j in jobs]
    if len(jobs) >= 2 and sum(sizes) >= PARALLEL_DECODE:
        # parsing is C strtod under the GIL: two topics in two processes (a forked copy of this one)
        # where that is safe, else one after the other (threads would gain nothing)
        def caught(job):
            try:
                return decode(job)
            except wire.WireError as exc:          # raised below in the topics' order, as serially
                return exc
        decoded = parallel.Pool().map(caught, jobs, order=sorted(range(len(jobs)), key=lambda i: -sizes[i]),
                                      threads=False)
        for d in decoded:
            if isinstance(d, Exception):
                raise d
    else:
        decoded = [decode(j) for j in jobs]
    streams_of: dict[str, dict] = {}
    for (_name, prefix, kind, ktopic), (seq, t, values) in zip(jobs, decoded):
        log_a = _as_i64(raw[ktopic][1], ktopic, "log_time")
        pub_a = _as_i64(raw[ktopic][2], ktopic, "publish_time")
        streams_of.setdefault(prefix, {})[kind] = _streams(path, ktopic, kind, seq, t, values, pub_a, log_a)
    for prefix, name in names.items():
        devices[name] = DeviceData(name, prefix, streams_of.get(prefix, {}))
    return Recording(path=path, devices=devices, metadata=report.metadata,
                     complete=bool(report.complete), note=report.note, messages=report.messages)


# --------------------------------------------------------------------------- recovery


@dataclass(frozen=True)
class RecoverStats:
    """Outcome of :func:`recover`: messages salvaged per topic (as spelled in the file),
    whether the input was already a finished, undamaged file (then nothing was lost), and
    the reader's note (empty in that case)."""

    messages: dict[str, int]
    already_complete: bool
    note: str

    @property
    def total(self) -> int:
        return sum(self.messages.values())


def recover(broken_path: str | os.PathLike, out_path: str | os.PathLike, force: bool = False,
            *, compression: str = DEFAULT_COMPRESSION, chunk_size: int = 1024 * 1024
            ) -> RecoverStats:
    """Rewrite every intact message of ``broken_path`` into a new, finished MCAP file.

    The input is read sequentially (non-seeking stream reader) up to its end or its first
    truncated or damaged record, whether or not it has a footer. The repaired file is the same
    kind of file as the source: its header (profile, library: a rosbag2 file stays ``ros2``,
    which ROS tools check before anything else), schemas (name, encoding, data), channels
    (topic, message encoding, metadata such as rosbag2's QoS profiles; a channel read without
    any message too), metadata records, and per message sequence, log_time and publish_time
    (ns) and data, unchanged, in file order. ``out_path`` must differ from the input and must
    not exist unless ``force`` (an existing one is replaced only once the new file is finished,
    as :class:`RecordingWriter` does). On failure the partial output is removed.

    What is not copied: what the file's end cut off (a rosbag2 writer puts its ``rosbag2``
    metadata record, with the message counts, at the very end), and attachments. A rosbag2
    bag directory's ``metadata.yaml`` describes the whole bag (its file names and message
    counts), not the repaired file, so it is not the repaired file's: ROS 2 readers open a
    single ``.mcap`` file of profile ``ros2`` by itself (``rosbags``' ``Reader`` and
    ``AnyReader``, ``ros2 bag info FILE.mcap``).
    """
    src = os.fspath(broken_path)
    dst = os.fspath(out_path)
    _check_magic(src)
    if compression not in _COMPRESSION_TYPES or not _AVAILABLE[compression]:
        raise McapIoError(f"compression {compression!r} is not available; use one of "
                          f"{', '.join(COMPRESSIONS)}")
    if os.path.exists(dst) and os.path.samefile(src, dst):
        raise McapIoError(f"{dst}: output is the input file; write the recovery elsewhere")
    report = ScanReport()
    counts: dict[str, int] = defaultdict(int)
    target = _Output(dst, force, ".recovering")    # not .partial: that may be the input
    try:
        writer = Writer(target.file, chunk_size=chunk_size, compression=_COMPRESSION_TYPES[compression])
        messages = _scan(src, None, report, stream=True)
        first = next(messages, None)                # the header is read before the first message
        writer.start(profile=report.profile, library=report.library)
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}

        def channel_id(schema: Schema | None, channel: Channel) -> int:
            cid = channel_ids.get(channel.id)
            if cid is None:
                sid = 0
                if schema is not None:
                    sid = schema_ids.get(schema.id, 0)
                    if sid == 0:
                        sid = schema_ids[schema.id] = writer.register_schema(
                            schema.name, schema.encoding, schema.data)
                cid = channel_ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, sid, dict(channel.metadata))
            return cid

        if first is not None:
            for schema, channel, msg in itertools.chain([first], messages):
                writer.add_message(channel_id=channel_id(schema, channel), log_time=msg.log_time,
                                   data=msg.data, publish_time=msg.publish_time, sequence=msg.sequence)
                counts[channel.topic] += 1
        for schema, channel in report.channels.values():      # topics without an intact message
            channel_id(schema, channel)
        for name, data in report.metadata.items():
            writer.add_metadata(name, data)
        writer.finish()
        target.commit()
    except OSError as e:            # the output's disk or directory; the input is only read
        target.abandon(keep=False)
        raise _os_error(target.writing, e, "cannot write it") from None
    except BaseException:
        target.abandon(keep=False)
        raise
    return RecoverStats(messages=dict(counts),
                        already_complete=bool(report.complete and report.intact),
                        note=report.note)
