"""Write noiselab streams to a new MCAP recording (:class:`RecordingWriter`)."""

from __future__ import annotations

import operator
import os
from collections import defaultdict
from collections.abc import Sequence
from contextlib import contextmanager
from importlib.metadata import PackageNotFoundError, version

import numpy as np
from mcap.writer import LIBRARY_IDENTIFIER

from .. import wire
from .blockwriter import BlockWriter
from .errors import McapIoError, McapWriteError
from .mcapformat import (
    AVAILABLE,
    COMPRESSION_TYPES,
    COMPRESSIONS,
    DEFAULT_COMPRESSION,
    SEQUENCE_MODULUS,
)
from .output import Output

_U64 = 2**64

def library_id() -> str:
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


class RecordingWriter:
    """Write noiselab streams to a new MCAP file; a context manager that always finishes it.

    Parameters
    ----------
    path : str or os.PathLike
        Output file. An existing file is refused (:class:`RecordingExistsError`) unless
        ``force``; with ``force`` it is replaced only when the new file is finished: until then
        the bytes go to :attr:`writing_path` (``path`` + :data:`PARTIAL_SUFFIX`), see
        :class:`Output`.
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
        if compression not in COMPRESSION_TYPES:
            raise McapIoError(f"compression {compression!r} is unknown: use one of "
                              f"{', '.join(COMPRESSION_TYPES)}")
        if not AVAILABLE[compression]:
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
        self._out = Output(self.path, force)
        self._file = self._out.file
        try:
            with self._io():
                self._writer = BlockWriter(self._file, chunk_size=chunk_size, compression=compression,
                                            profile="", library=library_id())
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
        wire.check_kind(kind)
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

