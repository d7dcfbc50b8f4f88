"""Property tests of the MCAP reader (hypothesis): whatever file it is given, every way of reading
it (read_recording, iter_messages, iter_time_ordered, recover, and the analysis' load_noiselab)
returns a result or raises a ValueError (McapIoError, WireError, SeriesError: the CLI's exit 2)
whose message is one line; never another exception. And what recover writes is a finished file
that reads back with the count it reported.

Inputs: arbitrary bytes (with and without the MCAP magic), real noiselab files mutated (bytes
flipped, cut at any offset, byte ranges and whole records duplicated), and files written with
mcap's own Writer holding odd channels (no schema, other encodings, odd topics, huge or negative
seqs, non-finite or mistyped fields, junk payloads). Real files in a temporary directory; the
example counts stay modest (the suite runs on 2 cores).
"""

import json
import struct

import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from mcap.writer import CompressionType, Writer

from noiselab import wire
from noiselab.recordings.errors import McapIoError, NotMcapError
from noiselab.recordings.load import load_noiselab
from noiselab.recordings.mcapformat import MAGIC
from noiselab.recordings.merge import iter_time_ordered
from noiselab.recordings.reader import read_recording
from noiselab.recordings.recording import Recording
from noiselab.recordings.salvage import RecoverStats, recover
from noiselab.recordings.scan import ScanReport, iter_messages
from noiselab.recordings.writer import RecordingWriter

SETTINGS = settings(max_examples=60, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def read_every_way(path, out):
    """Each reader on ``path``: its result, or the ValueError it raised (checked to be one line).
    Any other exception fails the test where it is raised."""
    readers = {
        "read_recording": lambda: read_recording(path),
        "iter_messages": lambda: sum(1 for _ in iter_messages(path)),
        "iter_time_ordered": lambda: sum(1 for _ in iter_time_ordered(path)),
        "load_noiselab": lambda: load_noiselab(str(path)),
        "recover": lambda: recover(path, out, force=True),
    }
    got = {}
    for name, read in readers.items():
        try:
            got[name] = read()
        except ValueError as e:
            msg = str(e)
            assert msg.strip() and "\n" not in msg and "\r" not in msg, (name, msg)
            got[name] = e
    stats = got["recover"]
    if isinstance(stats, RecoverStats):    # recover's output is finished and whole
        report = ScanReport()
        assert sum(1 for _ in iter_messages(out, report=report)) == stats.total
        assert report.complete and not report.note
    return got


# ------------------------------------------------------------------------------- arbitrary bytes


@SETTINGS
@given(body=st.binary(max_size=600), magic=st.booleans(), closing=st.booleans())
def test_arbitrary_bytes(tmp_path, body, magic, closing):
    path = tmp_path / "any.mcap"
    blob = (MAGIC if magic else b"") + body + (MAGIC if closing else b"")
    path.write_bytes(blob)
    got = read_every_way(path, tmp_path / "out.mcap")
    if not blob.startswith(MAGIC):
        assert all(isinstance(got[k], NotMcapError) for k in got if k != "load_noiselab")


# ------------------------------------------------------------------------ real files, mutated


def noiselab_file(path, compression, chunk_size, n=60):
    rng = np.random.default_rng(3)
    t, pub = wire.sample_times(0, n, 0.01)
    with RecordingWriter(path, force=True, compression=compression, chunk_size=chunk_size,
                                metadata={"model": "seed"}) as w:
        w.write_interleaved([(wire.key("dev", kind), kind, 0, pub, pub + 7,
                              wire.encode_batch(kind, 0, t, rng.standard_normal((n, dim))))
                             for kind, dim in (("truth", 2), ("command", 1), ("measurement", 1))])
    return path.read_bytes()


def records(blob: bytes) -> list[tuple[int, int]]:
    """(start, end) of the top-level records of a finished file (after the opening magic)."""
    out, pos = [], len(MAGIC)
    while pos + 9 <= len(blob) - len(MAGIC):
        (length,) = struct.unpack_from("<Q", blob, pos + 1)
        out.append((pos, pos + 9 + length))
        pos += 9 + length
    return out


_BASES: list = []


def base(which: int) -> tuple[bytes, list]:
    """Base file ``which`` (zstd or uncompressed, 512-byte or 1 MiB chunks) and its records,
    written once (a module-level cache, so that hypothesis' reports show the index, not the bytes)."""
    if not _BASES:
        import tempfile
        from pathlib import Path

        with tempfile.TemporaryDirectory() as d:
            for comp, chunk in (("zstd", 512), ("none", 512), ("zstd", 1 << 20), ("none", 1 << 20)):
                blob = noiselab_file(Path(d) / f"{comp}{chunk}.mcap", comp, chunk)
                _BASES.append((blob, records(blob)))
    return _BASES[which]


mutation = st.one_of(
    st.tuples(st.just("flip"), st.floats(0, 1, exclude_max=True), st.integers(1, 255)),
    st.tuples(st.just("cut"), st.floats(0, 1)),
    st.tuples(st.just("copy"), st.floats(0, 1, exclude_max=True), st.integers(1, 64), st.floats(0, 1)),
    st.tuples(st.just("record"), st.floats(0, 1, exclude_max=True), st.booleans()),
    st.tuples(st.just("word"), st.floats(0, 1, exclude_max=True),
              st.one_of(st.sampled_from([0, 1, 2**31, 2**32 - 1, 2**63 - 1, 2**63, 2**64 - 1]),
                        st.integers(0, 2**64 - 1))),
    st.tuples(st.just("nocrc"), st.floats(0, 1, exclude_max=True)),
)


def mutate(blob: bytes, recs, ops) -> bytes:
    b = bytearray(blob)
    for op in ops:
        if not b:
            break
        if op[0] == "flip":
            b[int(op[1] * len(b))] ^= op[2]
        elif op[0] == "cut":
            del b[int(op[1] * len(b)):]
        elif op[0] == "copy":                            # a byte range inserted again elsewhere
            a = int(op[1] * len(b))
            piece = b[a:a + op[2]]
            at = int(op[3] * len(b))
            b[at:at] = piece
        elif op[0] == "word":                            # a length, offset or time set to anything
            at = int(op[1] * len(b))
            b[at:at + 8] = op[2].to_bytes(8, "little")[:len(b) - at]
        elif op[0] == "nocrc":                           # a chunk's CRC zeroed: its records unchecked
            chunks = [r for r in recs if blob[r[0]] == 0x06 and r[0] + 37 <= len(b)]
            if chunks:
                start = chunks[int(op[1] * len(chunks))][0]
                b[start + 33:start + 37] = bytes(4)
        else:                                            # a whole record of the original, twice
            start, end = recs[int(op[1] * len(recs))]
            at = end if op[2] else start
            if at <= len(b):
                b[at:at] = blob[start:end]
    return bytes(b)


@SETTINGS
@given(which=st.integers(0, 3), ops=st.lists(mutation, min_size=1, max_size=5))
# cases found by this test, each an exception other than ValueError before the reader checked them:
@example(which=0, ops=[("flip", 0.9861467835556362, 145)])              # MemoryError (index length)
@example(which=1, ops=[("record", 0.875, False), ("flip", 0.95, 1)])     # MemoryError (index length)
@example(which=0, ops=[("word", 0.9660936904166955, 2**64 - 1)])        # OverflowError (index length)
@example(which=2, ops=[("word", 0.7327658089218658, 2**64 - 1)])        # IndexError (offset past 2**63)
@example(which=2, ops=[("word", 0.9790542617217443, 0)])                # McapError (metadata index)
@example(which=1, ops=[("word", 0.944049352921388, 2**31)])             # OSError (metadata index)
@example(which=2, ops=[("nocrc", 0.4918430023992272), ("flip", 0.9793803816179105, 238)])  # EndOfFile
def test_mutated_noiselab_files(tmp_path, which, ops):
    blob, recs = base(which)
    path = tmp_path / "mutated.mcap"
    path.write_bytes(mutate(blob, recs, ops))
    read_every_way(path, tmp_path / "out.mcap")


@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(which=st.integers(0, 3), at=st.floats(0, 1))
def test_cut_noiselab_files_keep_a_prefix(tmp_path, which, at):
    """A cut anywhere: the messages read are the first ones of the whole file, in order, and the
    measurement that read_recording gives is their measurements."""
    blob, _ = base(which)
    whole = tmp_path / "whole.mcap"
    whole.write_bytes(blob)
    full = [(c.topic, m.sequence, m.data) for _, c, m in iter_messages(whole)]
    path = tmp_path / "cut.mcap"
    path.write_bytes(blob[:int(at * len(blob))])
    got = read_every_way(path, tmp_path / "out.mcap")
    if isinstance(got["iter_messages"], int):
        kept = [(c.topic, m.sequence, m.data) for _, c, m in iter_messages(path)]
        assert kept == full[:len(kept)]
        rec = got["read_recording"]
        n_meas = sum(t.endswith("/measurement") for t, _, _ in kept)
        assert (len(rec.device("dev").measurement) if rec.devices else 0) == n_meas


# ------------------------------------------------------------------------- odd channels, odd data

TOPICS = st.one_of(
    st.sampled_from(["noiselab/d/measurement", "/noiselab/d/measurement", "d/measurement",
                     "noiselab/d/command", "noiselab/d/truth", "noiselab/e/measurement", "/measurement",
                     "noiselab//measurement", "x", "", "é/ü/measurement", "a/b/c/measurement"]),
    st.text(max_size=12).map(lambda s: s + "/measurement"),
    st.text(max_size=12),
)
NUMBER = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-2**70, 2**70),
                   st.sampled_from([1e308, -1e308, 5e-324, 0.0, -0.0]))
FIELD = st.one_of(NUMBER, st.text(max_size=5), st.none(), st.booleans(),
                  st.lists(NUMBER, max_size=4), st.lists(st.lists(NUMBER, max_size=2), max_size=2),
                  st.dictionaries(st.text(max_size=3), NUMBER, max_size=2))
SEQ = st.one_of(st.integers(0, 50), st.integers(-2**70, 2**70), st.sampled_from([2**32, 2**53 + 1, 2**63, 2**64]),
                NUMBER, st.text(max_size=3))


@st.composite
def payloads(draw):
    kind = draw(st.sampled_from(["payload", "junk", "json"]))
    if kind == "junk":
        return draw(st.binary(max_size=40))
    if kind == "json":
        return json.dumps(draw(FIELD)).encode()
    obj = {"seq": draw(SEQ), "t": draw(st.one_of(NUMBER, FIELD))}
    for key in draw(st.lists(st.sampled_from(["x", "u", "y", "extra"]), min_size=1, max_size=2, unique=True)):
        obj[key] = draw(st.one_of(st.lists(st.floats(-10, 10), min_size=1, max_size=3), FIELD))
    if draw(st.booleans()):
        del obj["seq"]
    return json.dumps(obj).encode()


channel = st.fixed_dictionaries({
    "topic": TOPICS,
    "encoding": st.sampled_from(["json", "json", "cdr", "protobuf", "", "JSON"]),
    "schema": st.sampled_from(["none", "jsonschema", "other"]),
})
message = st.tuples(st.integers(0, 3), payloads(), st.integers(0, 2**64 - 1), st.integers(0, 2**64 - 1),
                    st.integers(0, 2**32 - 1))


@SETTINGS
@given(channels=st.lists(channel, min_size=1, max_size=4), msgs=st.lists(message, max_size=25),
       compression=st.sampled_from([CompressionType.ZSTD, CompressionType.NONE]),
       chunk_size=st.sampled_from([64, 1024, 1 << 20]))
@example(channels=[{"topic": "a\n/measurement", "encoding": "json", "schema": "none"}],   # a topic with a
         msgs=[(0, b"{}", 0, 0, 0)], compression=CompressionType.NONE, chunk_size=1024)  # newline, echoed
def test_odd_channels_and_messages(tmp_path, channels, msgs, compression, chunk_size):
    path = tmp_path / "odd.mcap"
    with open(path, "wb") as f:
        w = Writer(f, compression=compression, chunk_size=chunk_size)
        w.start()
        ids = []
        for ch in channels:
            sid = 0
            if ch["schema"] == "jsonschema":
                sid = w.register_schema(wire.SCHEMA_NAMES["measurement"], "jsonschema",
                                        wire.schema_bytes("measurement"))
            elif ch["schema"] == "other":
                sid = w.register_schema("pkg/Msg", "ros2msg", b"float64 y")
            ids.append(w.register_channel(ch["topic"], ch["encoding"], sid))
        for i, data, log, pub, seq in msgs:
            w.add_message(ids[i % len(ids)], log_time=log, data=data, publish_time=pub, sequence=seq)
        w.finish()
    read_every_way(path, tmp_path / "out.mcap")


@SETTINGS
@given(seqs=st.lists(st.integers(0, 12), min_size=2, max_size=40), same=st.lists(st.booleans(), min_size=40,
                                                                                max_size=40))
def test_repeated_and_restarted_seqs(tmp_path, seqs, same):
    """Seqs in any order, repeated with the same or another sample: the reader keeps each
    (segment, seq) once, sorted inside each segment, or refuses a seq that comes twice with
    different data."""
    path = tmp_path / "seqs.mcap"
    with RecordingWriter(path, force=True) as w:
        for i, s in enumerate(seqs):
            value = float(s) if same[i] else float(s) + 0.5
            w.write("noiselab/d/measurement", "measurement", s, s, i,
                    wire.encode(s, s * 0.01, [value], kind="measurement"))
    got = read_every_way(path, tmp_path / "out.mcap")
    rec = got["read_recording"]
    if isinstance(rec, Recording):
        m = rec.device("d").measurement
        assert len(m) == len(seqs) - m.duplicates
        for a, b in m.segments:
            assert np.all(np.diff(m.seq[a:b]) > 0)
        assert sorted(m.log_ns.tolist()) == sorted(set(m.log_ns.tolist()))
    else:
        assert isinstance(rec, McapIoError) and "comes twice with different data" in str(rec)
