"""A finished MCAP file's chunks read at the struct level: a chunk's records, CRC-checked, and the
wanted topics' payloads and times found from the chunk's message index (the fast read)."""

from __future__ import annotations

import os
import struct
import zlib
from collections import defaultdict
from dataclasses import dataclass

import numpy as np
from mcap.reader import SeekingReader

from .errors import CorruptRecordingError, salvage_hint
from .mcapformat import CHUNK_MAX, CORRUPTION_ERRORS, norm_topic
from .scan import ScanReport, check_magic, finished_file


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
class Packed:
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


MESSAGE_HEADER = 31        # opcode 1, length 8, channel 2, sequence 4, log_time 8, publish_time 8


def _read_span(f, offset: int, length: int) -> bytes | None:
    """``length`` bytes at ``offset``, or None when the span does not lie inside the file (a
    damaged index: reading it as asked would allocate whatever it says)."""
    size = os.fstat(f.fileno()).st_size
    if not (0 <= offset <= size and 0 <= length <= size - offset):
        return None
    f.seek(offset)
    return f.read(length)


def chunk_records(f, ci, path: str) -> bytes:
    """The decompressed, CRC-checked records of the chunk that ``ci`` (a ChunkIndex) points to."""
    buf = _read_span(f, ci.chunk_start_offset, ci.chunk_length)
    try:
        if buf is None:
            raise CorruptRecordingError("the index points outside the file")
        if buf[0] != 0x06:
            raise CorruptRecordingError("not a chunk record")
        _mst, _met, usize, ucrc = struct.unpack_from("<QQQI", buf, 9)
        if usize > CHUNK_MAX:
            raise CorruptRecordingError(f"an uncompressed size of {usize} bytes")
        off = 9 + 28
        (clen,) = struct.unpack_from("<I", buf, off)
        comp = buf[off + 4: off + 4 + clen].decode()
        off += 4 + clen
        (rlen,) = struct.unpack_from("<Q", buf, off)
        dec = _decompress(comp, buf[off + 8: off + 8 + rlen], usize)
    except Exception as e:      # struct.error, IndexError, UnicodeDecodeError, codec errors
        raise CorruptRecordingError(f"{path}: finished file with a damaged chunk at byte {ci.chunk_start_offset} "
                                    f"({type(e).__name__}); {salvage_hint(path)}") from None
    if ucrc and zlib.crc32(dec) != ucrc:
        raise CorruptRecordingError(f"{path}: finished file with a chunk at byte {ci.chunk_start_offset} that fails its CRC; "
                                    + salvage_hint(path))
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
        if pairs.size and pairs[:, 1].max() >= CHUNK_MAX:
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
    if offs.min() < 0 or offs.max() + MESSAGE_HEADER > n:
        return None
    if np.any(u8[offs] != 0x05):
        return None
    u64 = _at_every_byte(dec, "<u8")
    ch = _at_every_byte(dec, "<u2")[offs + 9]
    if not np.isin(ch, list(cids)).all():
        return None
    rl = u64[offs + 1]
    if np.any(rl < MESSAGE_HEADER - 9) or np.any(rl > n):
        return None
    ends = offs + 9 + rl.astype(np.int64)
    if ends[-1] > n or np.any(ends[:-1] > offs[1:]):
        return None
    return offs + MESSAGE_HEADER, ends, u64[offs + 15], u64[offs + 23]


def collect_fast(path: str, kinds: tuple[str, ...], report: ScanReport):
    """Payloads, log and publish times per topic of a *finished* file, read chunk by chunk at the
    struct level (mcap's dataclass reader costs ~20 us per message). Chunks that hold none of the
    wanted topics (per the chunk index) are skipped; in the others the wanted messages are found
    from the chunk's MessageIndex records (numpy), cross-checked against the summary's message
    counts and the records themselves; without an index (or when it disagrees) every record is
    walked in Python. Chunk CRCs are checked. Returns (raw, encodings), raw[topic] =
    (:class:`Packed`, log_time uint64, publish_time uint64), or None when the fast path does not
    apply (unfinished file, no chunk index): the caller then uses :func:`iter_messages`."""
    size = check_magic(path)
    with open(path, "rb") as f:
        ok, _why = finished_file(f, size)
        if not ok:
            return None
        f.seek(0)
        reader = SeekingReader(f, validate_crcs=False)
        try:
            summary = reader.get_summary()
        except (*CORRUPTION_ERRORS, OSError):
            return None
        if summary is None or not summary.chunk_indexes:
            return None
        encodings: dict[str, set[str]] = defaultdict(set)
        cids_of: dict[str, set[int]] = defaultdict(set)       # normalised topic -> channel ids
        for cid, c in summary.channels.items():
            topic = norm_topic(c.topic)
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
        except (*CORRUPTION_ERRORS, OSError):
            return None                        # a damaged metadata index: the stream reader says where
    report.complete = True
    return raw, encodings


def _collect_chunks(f, path, chunks, cids_of, use_index: bool):
    """One pass of :func:`collect_fast` over the chunks; None if an index turns out unusable."""
    parts: dict[str, tuple[list, list, list, list]] = {t: ([], [], [], []) for t in cids_of}
    counts: dict[int, int] = defaultdict(int)
    all_cids = {cid for cids in cids_of.values() for cid in cids}
    for ci in chunks:
        mio = ci.message_index_offsets
        present = [cid for cid in all_cids if cid in mio] if (use_index and mio) else sorted(all_cids)
        if use_index and mio and not present:
            continue                           # none of the wanted channels in this chunk
        dec = chunk_records(f, ci, path)
        u8 = np.frombuffer(dec, np.uint8)
        offs = _index_offsets(f, ci, present) if use_index else None
        if use_index and offs is None:
            return None
        if offs is None:
            walked = _walk_offsets(dec, set(present))
            if walked is None:
                raise CorruptRecordingError(f"{path}: finished file with a damaged chunk at byte "
                                            f"{ci.chunk_start_offset}; {salvage_hint(path)}")
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
                                            f"{ci.chunk_start_offset}; {salvage_hint(path)}")
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
        raw[topic] = (Packed(b"".join(blobs), np.concatenate(lens)), np.concatenate(log), np.concatenate(pub))
    return raw, counts


