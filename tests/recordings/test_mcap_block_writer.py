"""The recordings' block writer writes the file mcap's own Writer writes, byte for byte.

``RecordingWriter`` builds a whole block's Message and MessageIndex records at once
(``noiselab.recordings.blockwriter.BlockWriter``) instead of calling ``mcap.writer.Writer.add_message`` per message. These
tests hold it to the reference: the same calls (schemas, channels, metadata, flushes, messages
with extreme times and sequences, empty payloads) through both writers give identical bytes, for
every compression and for chunk sizes from one byte (a chunk per message) to more than the file;
a RecordingWriter file equals mcap's for the same messages; and ``noiselab simulate``'s file holds,
sample by sample, the payloads of the single-message encoder ``wire.encode``, read back by mcap's
seeking and streaming readers and by ours. Real files, no mocks.
"""

import io
import random

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from noiselab import wire
from noiselab.model.model import load_model
from noiselab.recordings.blockwriter import BlockWriter
from noiselab.recordings.mcapformat import COMPRESSIONS, DEFAULT_COMPRESSION
from noiselab.recordings.reader import read_recording
from noiselab.recordings.simulated import write_simulation
from noiselab.recordings.writer import RecordingWriter, library_id

CT = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


def _script(seed: int):
    """A random sequence of writer calls: ("schema", ...), ("channel", ...), ("metadata", ...),
    ("flush",), ("messages", rows) with rows (channel, log, pub, seq, data)."""
    rng = random.Random(seed)
    ops, channels = [], 0
    for step in range(rng.randint(1, 25)):
        r = rng.random()
        if r < 0.15 or channels == 0:
            ops.append(("schema", f"s{step}", "jsonschema", bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 300)))))
            ops.append(("channel", f"t{step}", "json", channels + 1, {"k": str(step)}))
            channels += 1
        elif r < 0.2:
            ops.append(("metadata", f"m{step}", {"a": str(step), "b": "é"}))
        elif r < 0.25:
            ops.append(("flush",))
        else:
            rows = []
            for _ in range(rng.randint(0, 300)):
                log = rng.choice((0, 2**64 - 1, rng.randint(0, 2**64 - 1), rng.randint(0, 10**12)))
                rows.append((rng.randint(1, channels), log, rng.randint(0, 2**64 - 1),
                             rng.randint(0, 2**32 - 1), bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 120)))))
            ops.append(("messages", rows))
    return ops


def _reference(ops, chunk_size, compression) -> bytes:
    buf = io.BytesIO()
    w = Writer(buf, chunk_size=chunk_size, compression=CT[compression])
    w.start(profile="prof", library="lib")
    for op in ops:
        if op[0] == "schema":
            w.register_schema(*op[1:])
        elif op[0] == "channel":
            w.register_channel(*op[1:])
        elif op[0] == "metadata":
            w.add_metadata(*op[1:])
        elif op[0] == "flush":
            w.flush()
        else:
            for c, log, pub, seq, data in op[1]:
                w.add_message(channel_id=c, log_time=log, data=data, publish_time=pub, sequence=seq)
    w.finish()
    return buf.getvalue()


def _ours(ops, chunk_size, compression, single: bool) -> bytes:
    buf = io.BytesIO()
    w = BlockWriter(buf, chunk_size=chunk_size, compression=compression, profile="prof",
                            library="lib")
    for op in ops:
        if op[0] == "schema":
            w.register_schema(*op[1:])
        elif op[0] == "channel":
            w.register_channel(*op[1:])
        elif op[0] == "metadata":
            w.add_metadata(*op[1:])
        elif op[0] == "flush":
            w.flush()
        elif single:
            for c, log, pub, seq, data in op[1]:
                w.add_message(c, log, pub, seq, data)
        else:
            c, log, pub, seq, data = zip(*op[1]) if op[1] else ((),) * 5
            w.add_messages(np.array(c, np.uint16), np.array(log, np.uint64), np.array(pub, np.uint64),
                           np.array(seq, np.uint64), list(data))
    w.finish()
    return buf.getvalue()


@pytest.mark.parametrize("compression", COMPRESSIONS)
@pytest.mark.parametrize("chunk_size", [1, 97, 4096, 1 << 20])
def test_the_block_writer_writes_the_bytes_of_mcaps_writer(compression, chunk_size):
    for seed in range(25):
        ops = _script(seed)
        want = _reference(ops, chunk_size, compression)
        assert _ours(ops, chunk_size, compression, single=False) == want, f"blocks, script {seed}"
        assert _ours(ops, chunk_size, compression, single=True) == want, f"single, script {seed}"


def test_a_recording_writers_file_equals_mcaps_for_the_same_messages(tmp_path):
    """write, write_batch and write_interleaved (int64 beside uint64 times near their limits,
    sequences across the uint32 wrap) against mcap's Writer fed message by message, in the order
    the contract states: interleaved sample by sample, MCAP sequence = seq mod 2**32."""
    path = tmp_path / "r.mcap"
    n = 700
    seq0 = 2**32 - 300
    pub_i64 = np.arange(n, dtype=np.int64) + np.int64(2**63 - 10**6)
    log_u64 = np.arange(n, dtype=np.uint64) + np.uint64(2**64 - 10**6)
    rng = np.random.default_rng(3)
    vals = {k: rng.standard_normal((n, d)) for k, d in (("truth", 2), ("command", 1), ("measurement", 1))}
    t = np.arange(n) * 0.01
    pay = {k: wire.encode_batch(k, seq0, t, v) for k, v in vals.items()}
    key = {k: wire.key("dev", k) for k in vals}
    meta = {"model_name": "dev", "start_time_ns": "1"}
    with RecordingWriter(path, chunk_size=5000, metadata=meta) as w:
        w.write(key["measurement"], "measurement", seq0, int(pub_i64[0]), int(log_u64[0]), pay["measurement"][0])
        w.write_batch(key["measurement"], "measurement", seq0 + 1, pub_i64[1:100], log_u64[1:100],
                      pay["measurement"][1:100])
        w.write_interleaved([(key[k], k, seq0 + 100, pub_i64[100:], log_u64[100:], pay[k][100:])
                             for k in ("truth", "command", "measurement")])

    buf = io.BytesIO()
    ref = Writer(buf, chunk_size=5000, compression=CT[DEFAULT_COMPRESSION])
    ref.start(profile="", library=library_id())
    ref.add_metadata("noiselab", meta)
    cid = {}

    def register(kind):         # on a topic's first message; write_interleaved's, all its topics first
        sid = ref.register_schema(wire.SCHEMA_NAMES[kind], wire.SCHEMA_ENCODING, wire.schema_bytes(kind))
        cid[kind] = ref.register_channel(key[kind], wire.MESSAGE_ENCODING, sid, {"noiselab.kind": kind})

    def add(kind, i):
        ref.add_message(channel_id=cid[kind], log_time=int(log_u64[i]), data=pay[kind][i],
                        publish_time=int(pub_i64[i]), sequence=(seq0 + i) % 2**32)

    register("measurement")
    for i in range(100):
        add("measurement", i)
    register("truth")
    register("command")
    for i in range(100, n):
        for kind in ("truth", "command", "measurement"):
            add(kind, i)
    ref.finish()
    assert path.read_bytes() == buf.getvalue()


@pytest.mark.slow
def test_simulate_writes_the_single_message_encoders_payloads_readable_by_every_reader(tmp_path):
    """More samples than one simulated block (65536), so chunks span two writes; every message
    of the file, in file order, is wire.encode's payload of its sample (truth, command,
    measurement of k, then of k + 1) with publish_time = log_time = start + round(k Ts 1e9) and
    MCAP sequence k; mcap's seeking and streaming readers and ours read the same."""
    model = load_model("seed")
    n, start = 70_000, 1_700_000_000_123_456_789
    out = tmp_path / "sim.mcap"
    write_simulation(model, n, 4, out, start_time_ns=start, progress=False)
    batch = model.simulate(n, seed=4)
    t, _ = wire.sample_times(0, n, model.Ts)
    stamp = start + np.rint(t * 1e9).astype(np.int64)
    vec = {"truth": batch.x, "command": batch.u, "measurement": batch.y}
    with open(out, "rb") as f:
        seeking = [(ch.topic, m) for _s, ch, m in make_reader(f).iter_messages(log_time_order=False)]
    assert len(seeking) == 3 * n
    for i, (topic, m) in enumerate(seeking):
        k, kind = divmod(i, 3)
        kind = ("truth", "command", "measurement")[kind]
        assert topic == wire.key("seed", kind)
        assert m.data == wire.encode(k, t[k], vec[kind][k], kind=kind), (k, kind)
        assert (m.sequence, m.publish_time, m.log_time) == (k, int(stamp[k]), int(stamp[k]))
    with open(out, "rb") as f:
        streamed = [r for r in StreamReader(f).records if isinstance(r, Message)]
    assert [(r.data, r.sequence, r.publish_time, r.log_time) for r in streamed] == \
        [(m.data, m.sequence, m.publish_time, m.log_time) for _t, m in seeking]
    rec = read_recording(out)
    assert rec.complete
    for kind, values in vec.items():
        td = getattr(rec.device("seed"), kind)
        np.testing.assert_array_equal(td.values, values)
        np.testing.assert_array_equal(td.seq, np.arange(n))
        np.testing.assert_array_equal(td.publish_ns, stamp)


def test_a_ros2_bag_holds_the_samples_interleaved_as_they_are_published(tmp_path):
    """simulate --format ros2 over two simulated blocks: in file order, truth, command and
    measurement of sample k (log_time = its anchored stamp), then of k + 1."""
    model = load_model("seed")
    n, start = 66_000, 1_700_000_000_000_000_007
    write_simulation(model, n, 2, tmp_path / "bag", fmt="ros2", start_time_ns=start, progress=False)
    t, _ = wire.sample_times(0, n, model.Ts)
    stamp = (start + np.rint(t * 1e9).astype(np.int64)).tolist()
    with open(tmp_path / "bag" / "bag.mcap", "rb") as f:
        got = [(ch.topic, m.log_time) for _s, ch, m in make_reader(f).iter_messages(log_time_order=False)]
    assert got == [(f"/seed/{kind}", s) for s in stamp for kind in ("truth", "command", "measurement")]
