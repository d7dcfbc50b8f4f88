"""MCAP recordings: round trip, registered schemas, foreign files, unfinished files, recovery.

Real files in tmp_path, no mocks. Unfinished files are made the way a SIGKILL makes them:
by cutting a finished file's bytes (and once by really killing a writer process).
"""

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from helpers.recordings import DIMS, Ts, make_data, raw_file, write_sample
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk
from mcap.writer import Writer

from noiselab import wire
from noiselab.recordings.errors import (
    CorruptRecordingError,
    McapIoError,
    McapWriteError,
    NotMcapError,
    RecordingExistsError,
    SeriesError,
)
from noiselab.recordings.load import load_noiselab
from noiselab.recordings.mcapformat import COMPRESSIONS
from noiselab.recordings.merge import iter_time_ordered
from noiselab.recordings.output import PARTIAL_SUFFIX
from noiselab.recordings.reader import read_recording
from noiselab.recordings.recording import gaps
from noiselab.recordings.salvage import recover
from noiselab.recordings.scan import ScanReport, iter_messages
from noiselab.recordings.writer import RecordingWriter

REPO = Path(__file__).resolve().parents[2]


def same_bits(a, b) -> bool:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return a.shape == b.shape and np.array_equal(a.view(np.uint64), b.view(np.uint64))


def messages(path):
    """(topic, sequence, log_time, publish_time, data) of every message, in file order."""
    return [(c.topic, m.sequence, m.log_time, m.publish_time, m.data)
            for _, c, m in iter_messages(path)]


# ------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_round_trip_is_exact(tmp_path, compression):
    path = tmp_path / "run.mcap"
    n = 200
    data = write_sample(path, n, compression=compression, metadata={"model": "seed", "Ts": "0.01"})
    rec = read_recording(path)
    assert rec.complete and rec.note == ""
    assert list(rec.devices) == ["dev"]
    assert rec.metadata == {"noiselab": {"model": "seed", "Ts": "0.01"}}
    dev = rec.device()
    assert dev.prefix == "noiselab/dev"
    for kind in wire.KINDS:
        t, pub, log, vals = data[kind]
        s = dev.streams[kind]
        assert s.topic == f"noiselab/dev/{kind}" and len(s) == n and s.dim == DIMS[kind]
        assert s.seq.dtype == np.int64 and np.array_equal(s.seq, np.arange(n))
        assert s.publish_ns.dtype == np.int64 and s.publish_ns.tolist() == pub.tolist()
        assert s.log_ns.dtype == np.int64 and s.log_ns.tolist() == log.tolist()
        assert same_bits(s.t, t)
        assert same_bits(s.values, vals)
        assert s.gaps() == []
    assert dev.truth is dev.streams["truth"] and dev.command is dev.streams["command"]


def test_schemas_channels_and_statistics_as_registered(tmp_path):
    path = tmp_path / "run.mcap"
    write_sample(path, 50)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        header = reader.get_header()
    assert header.library.startswith("noiselab/")
    assert summary is not None and summary.statistics.message_count == 150
    schemas = {s.name: s for s in summary.schemas.values()}
    assert sorted(schemas) == sorted(wire.SCHEMA_NAMES[k] for k in wire.KINDS)
    by_topic = {c.topic: c for c in summary.channels.values()}
    assert sorted(by_topic) == sorted(wire.key("dev", k) for k in wire.KINDS)
    for kind in wire.KINDS:
        ch = by_topic[wire.key("dev", kind)]
        assert ch.message_encoding == "json"
        schema = summary.schemas[ch.schema_id]
        assert schema.encoding == "jsonschema"
        assert schema.name == wire.SCHEMA_NAMES[kind]
        assert json.loads(schema.data) == wire.schema(kind)
        assert summary.statistics.channel_message_counts[ch.id] == 50


def test_two_devices_and_metadata_records(tmp_path):
    path = tmp_path / "two.mcap"
    with RecordingWriter(path) as w:
        for name, scale in (("a", 1.0), ("b", 2.0)):
            payloads = wire.encode_batch("measurement", 0, np.arange(5) * Ts,
                                         scale * np.ones((5, 1)))
            w.write_batch(wire.key(name, "measurement"), "measurement", 0,
                          np.arange(5) * 10, np.arange(5) * 10, payloads)
        w.add_metadata("run", {"operator": "ci"})
        assert w.counts == {"noiselab/a/measurement": 5, "noiselab/b/measurement": 5}
    rec = read_recording(path)
    assert sorted(rec.devices) == ["a", "b"]
    assert rec.device("b").measurement.values.tolist() == [[2.0]] * 5
    assert rec.device("a").truth is None and rec.device("a").command is None
    assert rec.metadata == {"run": {"operator": "ci"}}
    with pytest.raises(McapIoError, match="2 devices"):
        rec.device()
    with pytest.raises(McapIoError, match="no device 'c'"):
        rec.device("c")


def test_sequence_past_uint32_wraps_in_mcap_but_payload_seq_is_exact(tmp_path):
    path = tmp_path / "wrap.mcap"
    seqs = [2**32 - 2, 2**32 - 1, 2**32, 2**32 + 1]
    with RecordingWriter(path) as w:
        for s in seqs:
            w.write("noiselab/dev/measurement", "measurement", s, s * 10, s * 10,
                    wire.encode(s, s * Ts, [1.0], kind="measurement"))
    assert [m[1] for m in messages(path)] == [2**32 - 2, 2**32 - 1, 0, 1]
    assert read_recording(path).device("dev").measurement.seq.tolist() == seqs


def test_exception_inside_with_still_finishes_the_file(tmp_path):
    path = tmp_path / "boom.mcap"
    with pytest.raises(RuntimeError, match="boom"):
        with RecordingWriter(path) as w:
            w.write("noiselab/dev/measurement", "measurement", 0, 0, 5,
                    wire.encode(0, 0.0, [3.0], kind="measurement"))
            raise RuntimeError("boom")
    assert w.closed
    rec = read_recording(path)
    assert rec.complete
    assert rec.device("dev").measurement.values.tolist() == [[3.0]]
    with pytest.raises(McapIoError, match="already finished"):
        w.write("noiselab/dev/measurement", "measurement", 1, 1, 6, b"{}")


def test_writer_refuses_bad_topics_and_times(tmp_path):
    with RecordingWriter(tmp_path / "x.mcap") as w:
        with pytest.raises(McapIoError, match="<prefix>/measurement"):
            w.channel("noiselab/dev/truth", "measurement")
        w.channel("/noiselab/dev/truth", "truth")  # leading '/' dropped
        with pytest.raises(McapIoError, match="registered as truth"):
            w.channel("noiselab/dev/truth", "command")
        with pytest.raises(McapIoError, match="publish_time_ns=-1"):
            w.write("noiselab/dev/truth", "truth", 0, -1, 0, b"{}")
        with pytest.raises(McapIoError, match="log_time_ns=1.5"):
            w.write("noiselab/dev/truth", "truth", 0, 0, 1.5, b"{}")
        with pytest.raises(McapIoError, match=r"shape \(2,\)"):
            w.write_batch("noiselab/dev/truth", "truth", 0, np.zeros(3, np.int64),
                          np.zeros(2, np.int64), [b"{}", b"{}"])
        with pytest.raises(McapIoError, match="must all be bytes"):
            w.write_batch("noiselab/dev/truth", "truth", 0, np.zeros(1, np.int64),
                          np.zeros(1, np.int64), ['{"seq":0}'])
    with pytest.raises(McapIoError, match="'gzip'"):
        RecordingWriter(tmp_path / "y.mcap", compression="gzip")
    assert not (tmp_path / "y.mcap").exists()
    assert [c.topic for _, c, _ in iter_messages(tmp_path / "x.mcap")] == []


def test_refuses_to_overwrite_unless_forced(tmp_path):
    path = tmp_path / "run.mcap"
    path.write_bytes(b"precious")
    with pytest.raises(RecordingExistsError) as e:
        RecordingWriter(path)
    assert isinstance(e.value, FileExistsError)
    assert str(path) in str(e.value) and "force" in str(e.value) and "\n" not in str(e.value)
    assert path.read_bytes() == b"precious"
    with RecordingWriter(path, force=True) as w:
        w.write("noiselab/d/measurement", "measurement", 0, 0, 0,
                wire.encode(0, 0.0, [1.0], kind="measurement"))
    assert read_recording(path).device("d").measurement.values.tolist() == [[1.0]]


def one_message(w, value, seq=0, name="d"):
    w.write(wire.key(name, "measurement"), "measurement", seq, seq * 10_000_000, seq * 10_000_000,
            wire.encode(seq, seq * Ts, [value], kind="measurement"))


def test_a_forced_write_that_fails_leaves_the_old_file_as_it_was(tmp_path):
    """--force replaces the old file only once the new one is finished (write-then-rename): a body
    that raises keeps the old file, and the new messages in PATH.partial, named in a note."""
    path = tmp_path / "run.mcap"
    write_sample(path, 30)
    old = path.read_bytes()
    with pytest.raises(RuntimeError, match="boom") as err:
        with RecordingWriter(path, force=True) as w:
            one_message(w, 7.0)
            raise RuntimeError("boom")
    assert path.read_bytes() == old
    partial = tmp_path / "run.mcap.partial"
    assert w.writing_path == str(partial) == str(path) + PARTIAL_SUFFIX
    rec = read_recording(partial)
    assert rec.complete and rec.device("d").measurement.values.tolist() == [[7.0]]
    assert any(str(partial) in note and "1 messages" in note for note in err.value.__notes__)
    partial.unlink()
    # a writer that fails before its first message leaves nothing behind
    with pytest.raises(RuntimeError, match="early"):
        with RecordingWriter(path, force=True):
            raise RuntimeError("early")
    assert path.read_bytes() == old and not partial.exists()
    # a finished forced write replaces it, and no .partial stays
    with RecordingWriter(path, force=True) as w:
        one_message(w, 8.0)
    assert read_recording(path).device("d").measurement.values.tolist() == [[8.0]]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]


def test_an_unfinished_partial_of_an_earlier_run_is_not_overwritten(tmp_path):
    path = tmp_path / "run.mcap"
    write_sample(path, 5)
    old = path.read_bytes()
    partial = tmp_path / "run.mcap.partial"
    partial.write_bytes(b"what a killed recorder left")
    with pytest.raises(McapIoError) as e:
        RecordingWriter(path, force=True)
    msg = str(e.value)
    assert "\n" not in msg and str(partial) in msg and f"noiselab recover {partial}" in msg
    assert partial.read_bytes() == b"what a killed recorder left" and path.read_bytes() == old


def test_disk_full_is_one_line_naming_the_file(tmp_path):
    """/dev/full fails every write with ENOSPC: an McapIoError (exit 2), and the device stays."""
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full")
    with pytest.raises(McapIoError) as e:
        with RecordingWriter("/dev/full", force=True, chunk_size=1024) as w:
            for k in range(2000):
                one_message(w, float(k), seq=k)
    msg = str(e.value)
    assert msg.startswith("/dev/full: cannot write it (No space left on device)") and "\n" not in msg
    assert "recover" not in msg                      # nothing of it is on any disk
    assert not Path("/dev/full").is_file() and os.path.exists("/dev/full")
    assert isinstance(e.value, McapWriteError)   # not a bad message: callers stop on it
    with pytest.raises(McapWriteError, match="No space left"):
        one_message(w, 0.0)                          # the writer stays ended, with the same reason


def test_write_errors_of_a_regular_file_keep_the_old_file_and_what_was_written(tmp_path):
    """A real OS write error on a regular file (EFBIG past RLIMIT_FSIZE, in a child process)
    while --force replaces a recording: one line naming the .partial file and the old file's
    fate; the old file intact; the .partial holds what reached the disk, and recover reads it."""
    path = tmp_path / "run.mcap"
    write_sample(path, 40)
    old = path.read_bytes()
    script = textwrap.dedent(f"""
        import resource, signal, sys
        from noiselab import wire
        from noiselab.recordings.errors import McapIoError
        from noiselab.recordings.writer import RecordingWriter
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)     # EFBIG instead of the signal
        resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000))
        try:
            with RecordingWriter({str(path)!r}, force=True, chunk_size=1024) as w:
                for k in range(5000):
                    w.write("noiselab/d/measurement", "measurement", k, k, k,
                            wire.encode(k, k * 0.01, [float(k)], kind="measurement"))
        except McapIoError as e:
            print(e)
            sys.exit(3)
    """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, timeout=60,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True)
    assert path.read_bytes() == old
    assert proc.returncode == 3, proc.stderr
    partial = str(path) + ".partial"
    line = proc.stdout.strip()
    assert "\n" not in line and line.startswith(f"{partial}: cannot write it (File too large)")
    assert f"{path} is as it was" in line and f"noiselab recover {partial}" in line
    assert path.read_bytes() == old
    rec = read_recording(partial)
    assert not rec.complete
    m = rec.device("d").measurement
    assert len(m) > 0 and m.values[:, 0].tolist() == list(range(len(m)))
    assert recover(partial, tmp_path / "fixed.mcap").total == len(m)


def test_a_write_error_at_the_close_keeps_what_was_flushed(tmp_path):
    """The disk fills while the file is finished (its summary does not fit, as a recorder's last
    chunk and summary on a full disk): McapWriteError, and the file with the messages flushed
    before stays for recover (a recorder flushes every 0.25 s: that is the recording)."""
    path = tmp_path / "run.mcap"
    script = textwrap.dedent(f"""
        import os, resource, signal, sys
        from noiselab import wire
        from noiselab.recordings.errors import McapWriteError
        from noiselab.recordings.writer import RecordingWriter
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        w = RecordingWriter({str(path)!r}, chunk_size=1 << 20)
        for k in range(110):                  # the last chunk and the summary wait in the file's buffer
            w.write("noiselab/d/measurement", "measurement", k, k, k,
                    wire.encode(k, k * 0.01, [float(k)], kind="measurement"))
            if k == 99:
                w.flush()
                size = os.path.getsize({str(path)!r})
                resource.setrlimit(resource.RLIMIT_FSIZE, (size + 50, size + 50))
        try:
            w.close()
        except McapWriteError as e:
            print(e)
            sys.exit(3)
    """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, timeout=60,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True)
    assert proc.returncode == 3, proc.stderr
    assert proc.stdout.startswith(f"{path}: cannot write it (File too large)")
    m = read_recording(path).device("d").measurement
    assert m.seq.tolist()[:100] == list(range(100))


def test_bad_output_paths_are_one_line_errors(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    cases = [(tmp_path, "is a directory"), (afile / "x.mcap", "Not a directory"),
             (tmp_path / "no" / "such" / "x.mcap", "No such file or directory")]
    if os.path.isdir("/sys/kernel"):
        cases.append((Path("/sys/noiselab-test.mcap"), "Permission denied"))  # EACCES, even for root
    for path, why in cases:
        for force in (False, True):
            with pytest.raises(McapIoError) as e:
                RecordingWriter(path, force=force)
            assert str(e.value).startswith(f"{path}: ") and why in str(e.value), (path, force)
            assert "\n" not in str(e.value)
    assert afile.read_text() == "x"


def test_killed_forced_writer_leaves_the_old_file_and_a_recoverable_partial(tmp_path):
    """SIGKILL while --force replaces a recording: the old file is intact and the new messages
    flushed so far are in PATH.partial (the name RecordingWriter.writing_path gives), which
    recover turns into the finished file."""
    path = tmp_path / "run.mcap"
    write_sample(path, 10)
    old = path.read_bytes()
    script = textwrap.dedent(f"""
        import os, signal
        import numpy as np
        from noiselab import wire
        from noiselab.recordings.writer import RecordingWriter
        w = RecordingWriter({str(path)!r}, force=True, chunk_size=1 << 20)
        print(getattr(w, "writing_path", None), flush=True)
        t, pub = wire.sample_times(0, 65, 0.01)
        key = wire.key("dev", "measurement")
        p = wire.encode_batch("measurement", 0, t, np.arange(65.0).reshape(65, 1))
        w.write_batch(key, "measurement", 0, pub[:40], pub[:40], p[:40])
        w.flush()
        w.write_batch(key, "measurement", 40, pub[40:], pub[40:], p[40:])
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, timeout=60,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert path.read_bytes() == old
    partial = str(path) + ".partial"
    assert proc.stdout.strip() == partial
    rec = read_recording(partial)
    assert not rec.complete and rec.device("dev").measurement.seq.tolist() == list(range(40))
    stats = recover(partial, path, force=True)
    assert stats.total == 40 and read_recording(path).complete
    assert read_recording(path).device("dev").measurement.values[:, 0].tolist() == list(range(40))


# --------------------------------------------------------------- foreign topic spellings


def test_reader_accepts_topics_with_a_leading_slash(tmp_path):
    path = tmp_path / "slash.mcap"
    raw_file(path, ["/noiselab/dev/measurement", "/noiselab/dev/command"])
    rec = read_recording(path)
    assert list(rec.devices) == ["dev"]
    dev = rec.device("dev")
    assert dev.measurement.topic == "noiselab/dev/measurement"
    assert dev.measurement.values.tolist() == [[k, -k] for k in range(5)]
    assert dev.command.publish_ns.tolist() == [k * 10_000_000 for k in range(5)]
    assert dev.truth is None
    # topic filters match either spelling
    assert len(list(iter_messages(path, topics=["noiselab/dev/command"]))) == 5
    assert len(list(iter_messages(path, topics="/noiselab/dev/measurement"))) == 5


def test_foreign_file_with_only_measurements_and_no_schema(tmp_path):
    path = tmp_path / "imu.mcap"
    raw_file(path, ["/robot/imu/measurement", "/robot/imu/status"], schema=False)
    rec = read_recording(path)
    assert list(rec.devices) == ["robot/imu"]
    dev = rec.device()
    assert set(dev.streams) == {"measurement"} and dev.truth is None and dev.command is None
    assert dev.measurement.log_ns.tolist() == [k * 7 for k in range(5)]


def test_bad_payload_in_a_recording_names_the_topic(tmp_path):
    path = tmp_path / "nan.mcap"
    raw_file(path, ["noiselab/dev/measurement"], payload=b'{"seq":0,"t":0.0,"y":[NaN]}')
    with pytest.raises(wire.WireError, match="^noiselab/dev/measurement: "):
        read_recording(path)


def test_out_of_order_messages_are_sorted_and_gaps_reported(tmp_path):
    path = tmp_path / "gaps.mcap"
    order = [0, 1, 3, 2, 7, 8, 12]
    with RecordingWriter(path) as w:
        for s in order:
            w.write("noiselab/dev/measurement", "measurement", s, s * 10, s,
                    wire.encode(s, s * Ts, [float(s)], kind="measurement"))
    m = read_recording(path).device().measurement
    assert m.seq.tolist() == sorted(order)
    assert m.values[:, 0].tolist() == sorted(order)
    assert m.log_ns.tolist() == sorted(order)
    assert m.gaps() == [(3, 3), (8, 3)]


# ------------------------------------------------------ repeats, conflicts, restarts


def write_stream(path, items, name="dev", kinds=("measurement",)):
    """``items``: (seq, value) in file order; every kind gets the sample (value, and -value for a
    2-vector), log_time grows by 1 ms per message as a recorder's receive time does."""
    with RecordingWriter(path) as w:
        for i, (seq, value) in enumerate(items):
            for kind in kinds:
                vec = [value] if DIMS[kind] == 1 else [value, -value]
                w.write(wire.key(name, kind), kind, seq, seq * 10_000_000, 1_000_000 * i,
                        wire.encode(seq, seq * Ts, vec, kind=kind))


def test_exact_repeats_are_one_sample_and_not_gaps(tmp_path):
    """A message read twice (same seq, same sample: a re-sent or twice-routed message) is one
    sample: no gap, no data dropped; the first copy is kept and the repeats are counted."""
    path = tmp_path / "rep.mcap"
    items = [(k, float(k) * 0.5) for k in range(100)]
    items.insert(11, (10, 5.0))            # right after itself
    items.insert(72, (50, 25.0))           # re-sent 20 messages later
    items.append((0, 0.0))                 # the first message again, at the end
    write_stream(path, items)
    m = read_recording(path).device("dev").measurement
    assert m.seq.tolist() == list(range(100)) and m.values[:, 0].tolist() == [k * 0.5 for k in range(100)]
    assert m.duplicates == 3 and m.gaps() == [] and m.segments == [(0, 100)]
    assert m.log_ns[50] == 1_000_000 * 51              # the first copy's receive time
    series = load_noiselab(str(path))
    assert series.y.shape == (100, 2)                    # all of it analysed, not the longest run
    assert not any("gap" in n for n in series.notes)
    assert "noiselab/dev/measurement: 3 repeated messages (same seq, same sample) counted once" in series.notes


def test_a_seq_that_comes_twice_with_different_data_is_an_error(tmp_path, capsys):
    path = tmp_path / "conflict.mcap"
    items = [(k, float(k)) for k in range(100)]
    items.insert(60, (40, 123.0))
    items.insert(80, (70, 7.5))
    write_stream(path, items)
    with pytest.raises(McapIoError) as e:
        read_recording(path)
    msg = str(e.value)
    assert msg.startswith(f"{path}: topic 'noiselab/dev/measurement': seq 40 comes twice with different data")
    assert "1 more" in msg and "\n" not in msg
    from noiselab.cli import main
    assert main(["analyze", str(path), "--model", "seed"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "seq 40 comes twice" in err


def test_a_restarted_source_is_read_as_stream_segments(tmp_path):
    """The source restarted mid-file (seq back to 0, e.g. the emulator restarted while the recorder
    ran): two segments in file order, each sorted, gaps counted inside a segment only."""
    path = tmp_path / "restart.mcap"
    first = [(k, float(k)) for k in range(120)]
    second = [(k, 1000.0 + k) for k in range(80) if not 30 <= k < 33]
    second[5], second[6] = second[6], second[5]          # reordered inside the segment: sorted
    write_stream(path, first + second)
    m = read_recording(path).device("dev").measurement
    assert m.segments == [(0, 120), (120, 197)] and m.duplicates == 0
    assert m.seq.tolist() == list(range(120)) + [k for k in range(80) if not 30 <= k < 33]
    assert m.values[120:, 0].tolist() == [1000.0 + k for k in range(80) if not 30 <= k < 33]
    assert m.gaps() == [(29, 3)]
    assert m.log_ns[120] == 1_000_000 * 120
    seg = m.segment(1)
    assert seg.seq.tolist() == m.seq[120:].tolist() and seg.segments == [(0, 77)]
    # a source restarted with the same seed sends the same samples again: still a restart
    same = tmp_path / "same.mcap"
    write_stream(same, [(k, float(k)) for k in range(10)] + [(k, float(k)) for k in range(5)])
    m = read_recording(same).device("dev").measurement
    assert m.segments == [(0, 10), (10, 15)] and m.duplicates == 0
    # but the first message sent again and nothing after it is a repeat
    again = tmp_path / "again.mcap"
    write_stream(again, [(k, float(k)) for k in range(10)] + [(0, 0.0)])
    m = read_recording(again).device("dev").measurement
    assert m.segments == [(0, 10)] and m.duplicates == 1


def test_analysis_of_a_restarted_recording_takes_one_segment_and_says_so(tmp_path):
    """load_noiselab analyses one stream segment (the longest gap-free run's, or the one asked
    for), with the command and truth of that same segment, and a note names the restart."""
    path = tmp_path / "restart.mcap"
    first = [(k, float(k)) for k in range(300)]
    second = [(k, 1000.0 + k) for k in range(500)]
    write_stream(path, first + second, kinds=("truth", "command", "measurement"))
    s = load_noiselab(str(path))
    assert s.y[:, 0].tolist() == [1000.0 + k for k in range(500)]
    assert s.u[:, 0].tolist() == s.y[:, 0].tolist() and s.truth[:, 0].tolist() == s.y[:, 0].tolist()
    assert s.starts_at_rest
    note, = [n for n in s.notes if "restarted" in n]
    assert note == ("noiselab/dev/measurement: the source restarted once (seq back to 0 at log time +0.300 s "
                    "from the first message): 2 stream segments of 300, 500 samples; analysed segment 2 "
                    "(the one with the longest gap-free run; --segment N takes segment N)")
    s1 = load_noiselab(str(path), segment=1)
    assert s1.y[:, 0].tolist() == [float(k) for k in range(300)] and s1.u[:, 0].tolist() == s1.y[:, 0].tolist()
    assert any(n.endswith("analysed segment 1 (--segment 1)") for n in s1.notes)
    with pytest.raises(SeriesError, match=r"segment 3 asked for, but noiselab/dev/measurement has 2 stream "
                                            r"segments \(1\.\.2\)"):
        load_noiselab(str(path), segment=3)


def write_runs(path, model, runs, kinds=("truth", "command", "measurement")):
    """Runs of ``model`` one after the other in one file, as a recorder writes a source that
    restarted: ``runs`` = (seed, n, first) per run, samples ``first..n-1`` of a stream of ``n`` from
    rest (``first`` > 0: the run's first samples were lost); receive times go on across runs."""
    with RecordingWriter(path) as w:
        log0 = 0
        for seed, n, first in runs:
            b = model.simulate(n, seed=seed)
            t, pub = wire.sample_times(0, n, model.Ts)
            arrays = {"truth": b.x, "command": b.u, "measurement": b.y}
            log = log0 + pub[first:]
            w.write_interleaved([(wire.key(model.name, kind), kind, first, pub[first:], log,
                                  wire.encode_batch(kind, first, t[first:], arrays[kind][first:]))
                                 for kind in kinds])
            log0 = int(log[-1]) + 10**9


def test_a_restart_whose_first_samples_were_lost_is_a_new_segment(tmp_path):
    """A source restarted and its first samples after the restart never reached the file (seq 0..199,
    then 5..199 with other data): the step back to a seq the stream already holds with another
    sample is a restart, not a seq twice with different data; in every topic, and again for a
    second restart; a late message in the first run does not hide it."""
    path = tmp_path / "lossy.mcap"
    write_stream(path, [(k, float(k)) for k in range(200)] + [(k, 1000.0 + k) for k in range(5, 200)],
                 kinds=("truth", "command", "measurement"))
    dev = read_recording(path).device("dev")
    for td in dev.streams.values():
        assert td.segments == [(0, 200), (200, 395)] and td.duplicates == 0, td.topic
        assert td.seq.tolist() == list(range(200)) + list(range(5, 200))
        assert td.values[:, 0].tolist() == [float(k) for k in range(200)] + [1000.0 + k for k in range(5, 200)]
        assert td.gaps() == []
    # three runs, the later two missing their starts; the first run with a late message (51 after 52)
    again = tmp_path / "twice.mcap"
    first = [(k, float(k)) for k in range(100)]
    first[51], first[52] = first[52], first[51]
    write_stream(again, first + [(k, 500.0 + k) for k in range(5, 100)] + [(k, 900.0 + k) for k in range(40, 81)])
    m = read_recording(again).device("dev").measurement
    assert m.segments == [(0, 100), (100, 195), (195, 236)] and m.duplicates == 0
    assert m.seq.tolist() == list(range(100)) + list(range(5, 100)) + list(range(40, 81))
    assert m.values[195:, 0].tolist() == [900.0 + k for k in range(40, 81)]
    # a source restarted with the same samples that lost its first ones: the same data, read once
    same = tmp_path / "same.mcap"
    write_stream(same, [(k, float(k)) for k in range(100)] + [(k, float(k)) for k in range(5, 100)])
    m = read_recording(same).device("dev").measurement
    assert m.segments == [(0, 100)] and m.duplicates == 95 and m.seq.tolist() == list(range(100))


def test_two_sources_side_by_side_on_one_key_are_refused(tmp_path):
    """A seq twice with different data that no restart explains is still refused: two sources
    publishing on one key at once (their messages interleaved: equal seqs together, one a few seqs
    ahead, or in bursts), or one forged message amid a stream that goes on."""
    a = [(k, float(k)) for k in range(100)]              # one source
    b = [(k, 1000.0 + k) for k in range(100)]            # another one, on the same key
    cases = {
        "together": [m for pair in zip(a, b) for m in pair],
        "ahead": [m for pair in zip(a[5:], b) for m in pair],
        "ahead by one": [m for pair in zip(a[1:], b) for m in pair],
        "bursts": [m for k in range(0, 90, 3) for m in a[k + 9:k + 12] + b[k:k + 3]],
        "forged": a[:60] + [(40, 123.0)] + a[60:],
    }
    for name, items in cases.items():
        path = tmp_path / f"{name}.mcap"
        write_stream(path, items)
        with pytest.raises(McapIoError, match="comes twice with different data; |comes twice with "
                                                     r"different data \(and \d+ more such seqs\); "):
            read_recording(path)
            pytest.fail(name)


def test_analyze_takes_each_run_of_a_lossy_restart_with_segment(tmp_path, capsys):
    """noiselab analyze of a recording whose source restarted and lost the first 5 samples of its
    second run: each run is a stream segment, analysed as the same run recorded alone would be
    (--segment 1, 2; by default the longer one), and the note names the restart."""
    from noiselab.cli import main
    from noiselab.model import load_model

    seed = load_model("seed")
    runs = [(3, 1500, 0), (4, 3000, 5)]
    both = tmp_path / "restarted.mcap"
    write_runs(both, seed, runs)

    def analyze(path, *extra):
        assert main(["analyze", str(path), "--model", "seed", "--json", *extra]) == 0
        out = capsys.readouterr()
        return json.loads(out.out)

    for i, run in enumerate(runs):
        alone = tmp_path / f"run{i + 1}.mcap"
        write_runs(alone, seed, [run])
        want = analyze(alone)
        for extra in (["--segment", str(i + 1)], [] if i == 1 else None):
            if extra is None:
                continue
            rep = analyze(both, *extra)
            assert (rep["error"], rep["samples"]) == (want["error"], want["samples"]), (i, extra)
            note, = [n for n in rep["notes"] if "restarted" in n]
            assert "restarted once (seq back to 5 " in note and "2 stream segments of 1500, 2995 samples" in note
            assert note.endswith(f"analysed segment {i + 1} " + ("(--segment 2)" if extra[-1:] == ["2"] else
                                 "(--segment 1)" if extra else
                                 "(the one with the longest gap-free run; --segment N takes segment N)"))


def test_without_a_command_topic_the_assumed_command_is_named(tmp_path):
    from noiselab.model import load_model

    seed = load_model("seed")
    bare = tmp_path / "bare.mcap"
    write_stream(bare, [(k, float(k)) for k in range(50)])
    s = load_noiselab(str(bare), model=seed)
    assert s.u is None
    assert s.command == {"source": "model", "kind": "sine", "amplitude": 0.8, "frequency_hz": 0.7,
                         "offset": 0.0, "phase_rad": 0.0}
    assert ("no command topic in the recording: the analysis assumes the model's own command ([command] "
            "kind = 'sine', amplitude = 0.8, frequency_hz = 0.7, offset = 0.0, phase_rad = 0.0)") in s.notes
    from noiselab.recordings.load import load_foreign
    s = load_foreign(str(bare), "noiselab/dev/measurement:y[0]", None, seed.Ts, model=seed)   # a foreign file
    assert s.u is None and s.command["source"] == "model" and any("assumes the model's own" in n for n in s.notes)
    full = tmp_path / "full.mcap"
    write_stream(full, [(k, float(k)) for k in range(50)], kinds=("command", "measurement"))
    s = load_noiselab(str(full), model=seed)
    assert s.command == {"source": "recording", "topic": "noiselab/dev/command"}
    assert not any("command" in n for n in s.notes)


def test_replay_topics_of_an_unfinished_file_do_not_depend_on_its_payloads(tmp_path):
    """replay republishes messages as recorded: the topics of a cut file whose measurements a
    reader refuses (a bad payload, a seq twice with different data) are still listed."""
    from noiselab.nodes.replay import replay_topics

    full = tmp_path / "full.mcap"
    with RecordingWriter(full, chunk_size=1 << 20, compression="none") as w:
        for k in range(20):
            one_message(w, float(k), seq=k, name="dev")
            w.write(wire.key("dev", "command"), "command", k, k, k, wire.encode(k, k * Ts, [0.0], kind="command"))
        one_message(w, 99.0, seq=3, name="dev")                                  # seq 3 again, other data
        w.write("noiselab/odd/measurement", "measurement", 0, 0, 0, b'{"seq": 0, "t": "soon"}')
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full.read_bytes()[:-200])                                    # no summary: read in full
    with pytest.raises(ValueError):
        read_recording(cut)
    assert replay_topics(str(cut)) == ["noiselab/dev/command", "noiselab/dev/measurement",
                                       "noiselab/odd/measurement"]


# ---------------------------------------------------------------------------- gaps()


@pytest.mark.parametrize("seq, expected", [
    ([], []),
    ([5], []),
    ([0, 1, 2, 3], []),
    ([0, 1, 2, 5, 6, 9], [(2, 2), (6, 2)]),
    ([3, 4, 10], [(4, 5)]),          # a late start is not a gap
    ([0, 1, 1, 2], []),              # duplicate
    ([0, 1, 5, 2, 3], [(1, 3)]),     # reordering: only forward jumps count
    (np.array([2**40, 2**40 + 3], dtype=np.uint64), [(2**40, 2)]),
])
def test_gaps_on_hand_made_sequences(seq, expected):
    assert gaps(seq) == expected
    assert all(type(a) is int and type(b) is int for a, b in gaps(seq))


def test_gaps_refuses_non_integer_input():
    with pytest.raises(McapIoError, match="1-D integer"):
        gaps([0.0, 1.0])
    with pytest.raises(McapIoError, match="1-D integer"):
        gaps([[0, 1]])


# ---------------------------------------------------------------- unfinished recordings


def top_level_chunks(path):
    """[(start, end, [(topic, sequence, log_time, publish_time, data), ...], compression, [end byte
    of each message record, or None]), ...] per chunk, from the finished file's chunk index (the
    ground truth of what a cut keeps). A message record's end byte is known in an uncompressed
    chunk only: the records lie in the file as they are, after the chunk's 49-byte header."""
    out = []
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        topics = {c.id: c.topic for c in summary.channels.values()}
        for ci in summary.chunk_indexes:
            f.seek(ci.chunk_start_offset + 1 + 8)
            chunk = Chunk.read(ReadDataStream(f))
            msgs = [(topics[r.channel_id], r.sequence, r.log_time, r.publish_time, r.data)
                    for r in breakup_chunk(chunk) if isinstance(r, Message)]
            ends = [None] * len(msgs)
            if chunk.compression == "":
                ends, pos, base = [], 0, ci.chunk_start_offset + 49
                while pos < len(chunk.data):
                    opcode, length = chunk.data[pos], int.from_bytes(chunk.data[pos + 1: pos + 9], "little")
                    pos += 9 + length
                    if opcode == 0x05:
                        ends.append(base + pos)
            out.append((ci.chunk_start_offset, ci.chunk_start_offset + ci.chunk_length, msgs,
                        chunk.compression, ends))
    return out


def expected_after_cut(chunks, cut):
    """The messages a cut at byte ``cut`` keeps: every whole chunk's, and of the chunk it cuts the
    messages before the cut (exactly known in an uncompressed chunk; in a compressed one those of
    its whole compressed blocks: the count is then checked by ``is_prefix`` instead)."""
    whole = [m for start, end, ms, _, _ in chunks if end <= cut for m in ms]
    cut_chunk = next(((ms, comp, ends) for start, end, ms, comp, ends in chunks if start < cut < end), None)
    return whole, cut_chunk


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_cut_file_reads_every_intact_message_and_recovers(tmp_path, compression):
    """A file cut anywhere (as a SIGKILL or a full disk leaves it): the reader and recover give
    every message of every whole chunk, and of the chunk the cut goes through its intact start
    (all the messages before the cut in an uncompressed chunk; the whole blocks of a compressed
    one): a prefix of the file's messages, nothing invented."""
    full = tmp_path / "full.mcap"
    write_sample(full, 120, chunk_size=1024, compression=compression,
                 metadata={"model": "seed"})
    blob = full.read_bytes()
    chunks = top_level_chunks(full)
    assert len(chunks) >= 6
    all_msgs = [m for _, _, ms, _, _ in chunks for m in ms]
    assert messages(full) == all_msgs
    ends = [c[1] for c in chunks]
    mid0 = (chunks[0][0] + ends[0]) // 2
    cuts = sorted({
        8,                          # magic only
        mid0,                       # the middle of the first chunk
        ends[0] - 1,                # inside the first chunk
        ends[0],                    # exactly after the first chunk
        ends[0] + 5,                # inside the message index after it
        (ends[2] + ends[3]) // 2,   # mid-file
        ends[3] - 1,                # chunk 3 lacks one byte
        ends[-1] - 1,               # last chunk lacks one byte
        ends[-1] + 3,               # all chunks whole, message indexes / data end cut
        len(blob) - 30,             # inside the summary
        len(blob) - 1,              # the closing magic lacks one byte
    })
    for cut in cuts:
        cut_path = tmp_path / f"cut{cut}.mcap"
        cut_path.write_bytes(blob[:cut])
        whole, cut_chunk = expected_after_cut(chunks, cut)
        got = messages(cut_path)
        assert got == all_msgs[:len(got)] and len(got) >= len(whole), cut    # a prefix, nothing lost
        if cut_chunk is None:
            assert got == whole, cut
        elif cut_chunk[1] == "":
            assert got == whole + [m for m, e in zip(cut_chunk[0], cut_chunk[2]) if e <= cut], cut
        expected = got
        rec = read_recording(cut_path)
        assert not rec.complete, cut
        assert "incomplete MCAP" in rec.note and f"read {len(expected)} intact" in rec.note
        n_meas = sum(1 for m in expected if m[0].endswith("/measurement"))
        if n_meas:
            meas = rec.device("dev").measurement
            assert meas.seq.tolist() == list(range(n_meas))
            assert meas.publish_ns.tolist() == [m[3] for m in expected
                                                if m[0].endswith("/measurement")]
        # the metadata record is written right after the header, before the first chunk
        has_meta = cut >= chunks[0][0]
        assert rec.metadata == ({"noiselab": {"model": "seed"}} if has_meta else {})

        out = tmp_path / f"rec{cut}.mcap"
        stats = recover(cut_path, out)
        assert not stats.already_complete and stats.total == len(expected)
        assert stats.note == rec.note
        with open(out, "rb") as f:  # the seeking reader accepts it: footer and summary present
            reader = make_reader(f)
            summary = reader.get_summary()
            assert summary is not None
            assert summary.statistics.message_count == len(expected)
            got = [(c.topic, m.sequence, m.log_time, m.publish_time, m.data)
                   for _, c, m in reader.iter_messages(log_time_order=False)]
            assert {s.name for s in summary.schemas.values()} <= set(wire.SCHEMA_NAMES.values())
        assert got == expected
        rec2 = read_recording(out)
        assert rec2.complete and rec2.metadata == rec.metadata
    if compression == "none":   # one byte short, chunk 3 keeps all its messages but the last
        n3 = len(messages(tmp_path / f"cut{ends[3] - 1}.mcap"))
        assert n3 == sum(len(c[2]) for c in chunks[:4]) - 1 and len(chunks[3][2]) >= 3


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_a_cut_single_chunk_file_says_it_is_unfinished_and_its_start_is_recovered(tmp_path, compression):
    """A one-chunk recording (simulate writes 1 MiB chunks) cut at several bytes: the reader gives
    the messages of the chunk's intact start and says the file is unfinished; an analysis that
    finds no measurement among them says so and names recover, not 'no measurement topic'; recover
    writes exactly those messages into a finished file."""
    full = tmp_path / "one.mcap"
    write_sample(full, 3000, chunk_size=8 << 20, compression=compression, metadata={"model": "seed"})
    blob = full.read_bytes()
    (start, end, msgs, comp, rec_ends), = top_level_chunks(full)
    cuts = sorted({20, start, start + 20, *(start + (end - start) * q // 100 for q in (3, 25, 50, 75, 99)),
                   end + 5, len(blob) - 30})
    salvaged = {}
    for cut in cuts:
        path = tmp_path / f"cut{cut}.mcap"
        path.write_bytes(blob[:cut])
        got = messages(path)
        assert got == msgs[:len(got)], cut                      # the intact start, nothing else
        if comp == "":
            assert len(got) == sum(e <= cut for e in rec_ends), cut
        if cut > end:
            assert got == msgs
        salvaged[cut] = len(got)
        rec = read_recording(path)
        assert not rec.complete and "incomplete MCAP" in rec.note, cut
        if start < cut < end:
            assert "the file ends inside a chunk record" in rec.note
        n_meas = sum(m[0].endswith("/measurement") for m in got)
        if n_meas >= 2:
            s = load_noiselab(str(path))
            assert len(s.y) == n_meas and any("the recording is unfinished" in n for n in s.notes)
        elif n_meas == 0:
            with pytest.raises(SeriesError) as e:
                load_noiselab(str(path))
            msg = str(e.value)
            assert "incomplete MCAP" in msg and "none of them is a measurement" in msg and "\n" not in msg
            assert ("noiselab recover" in msg) == (len(got) > 0)
        out = tmp_path / f"rec{cut}.mcap"
        stats = recover(path, out)
        assert stats.total == len(got) and messages(out) == got and read_recording(out).complete
    mid = [salvaged[c] for c in cuts if start + (end - start) // 2 <= c < end]
    assert all(k > 0 for k in mid), salvaged                  # from half the chunk on, its start is kept


def test_analyze_of_a_cut_file_without_a_measurement_names_recover(tmp_path, capsys):
    """The CLI's line for a file cut before its first measurement (a truth message came first)."""
    full = tmp_path / "one.mcap"
    write_sample(full, 300, chunk_size=8 << 20, compression="none")
    (start, end, msgs, comp, rec_ends), = top_level_chunks(full)
    path = tmp_path / "cut.mcap"
    path.write_bytes(full.read_bytes()[:rec_ends[1]])          # the first truth and command messages
    from noiselab.cli import main
    assert main(["analyze", str(path), "--model", "seed"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "incomplete MCAP" in err and "read 2 intact messages" in err
    assert f"`noiselab recover {path} --out FIXED.mcap` keeps the 2 messages read" in err


def test_recover_of_a_finished_file_copies_it(tmp_path):
    src = tmp_path / "ok.mcap"
    write_sample(src, 30)
    stats = recover(src, tmp_path / "copy.mcap")
    assert stats.already_complete and stats.note == ""
    assert stats.messages == {wire.key("dev", k): 30 for k in wire.KINDS}
    assert messages(tmp_path / "copy.mcap") == messages(src)


def test_damaged_chunk_in_finished_file(tmp_path):
    """A flipped byte inside chunk 3: reading refuses (CRC), recover keeps chunks 0-2."""
    src = tmp_path / "ok.mcap"
    write_sample(src, 120, chunk_size=1024)
    chunks = top_level_chunks(src)
    blob = bytearray(src.read_bytes())
    start, end = chunks[3][:2]
    blob[(start + end) // 2] ^= 0x10
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(blob))
    with pytest.raises(CorruptRecordingError, match=f"^{bad}: finished file") as err:
        read_recording(bad)
    # the message names the command that salvages it, as the user types it
    assert f"`noiselab recover {bad} --out FIXED.mcap`" in str(err.value)
    stats = recover(bad, tmp_path / "salvaged.mcap")
    expected = [m for _, _, ms, _, _ in chunks[:3] for m in ms]
    assert not stats.already_complete and stats.total == len(expected)
    assert "damaged record" in stats.note
    assert messages(tmp_path / "salvaged.mcap") == expected


def test_recover_refuses_existing_output_and_itself(tmp_path):
    src = tmp_path / "ok.mcap"
    write_sample(src, 5)
    dst = tmp_path / "out.mcap"
    dst.write_bytes(b"keep")
    with pytest.raises(RecordingExistsError):
        recover(src, dst)
    assert dst.read_bytes() == b"keep"
    assert recover(src, dst, force=True).total == 15
    with pytest.raises(McapIoError, match="is the input"):
        recover(src, src, force=True)
    assert read_recording(src).complete


def test_killed_writer_process_keeps_what_was_flushed(tmp_path):
    """A real SIGKILL: 40 samples flushed, 25 more in the chunk in progress are lost."""
    path = tmp_path / "killed.mcap"
    script = textwrap.dedent(f"""
        import os, signal, sys
        import numpy as np
        from noiselab import wire
        from noiselab.recordings.writer import RecordingWriter
        w = RecordingWriter({str(path)!r}, chunk_size=1 << 20)
        t, pub = wire.sample_times(0, 65, 0.01)
        y = np.arange(65.0).reshape(65, 1)
        key = wire.key("dev", "measurement")
        p = wire.encode_batch("measurement", 0, t, y)
        w.write_batch(key, "measurement", 0, pub[:40], pub[:40], p[:40])
        w.flush()
        w.write_batch(key, "measurement", 40, pub[40:], pub[40:], p[40:])
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, timeout=60,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()
    rec = read_recording(path)
    assert not rec.complete and "read 40 intact messages" in rec.note
    m = rec.device("dev").measurement
    assert m.seq.tolist() == list(range(40)) and m.values[:, 0].tolist() == list(range(40))


# ------------------------------------------------------------------------- not MCAP


@pytest.mark.parametrize("content", [b"", b"\x89MCA", b"hello, this is text\n" * 3,
                                     b"PAR1" + bytes(100)])
def test_non_mcap_file_raises_not_mcap_error(tmp_path, content):
    path = tmp_path / "data.bin"
    path.write_bytes(content)
    with pytest.raises(NotMcapError) as e:
        read_recording(path)
    msg = str(e.value)
    assert isinstance(e.value, ValueError)
    assert str(path) in msg and "not an MCAP file" in msg and "\n" not in msg
    with pytest.raises(NotMcapError):
        recover(path, tmp_path / "out.mcap")
    assert not (tmp_path / "out.mcap").exists()


# ------------------------------------------- fast reader: any layout, same numbers as the peer


def peer_arrays(path):
    """What the mcap library's own reader and json.loads give, per topic (file order kept per
    topic; the payload seq sorts it as read_recording does): the reference for the fast path."""
    per: dict = {}
    with open(path, "rb") as f:
        for _, c, m in make_reader(f).iter_messages(log_time_order=False):
            obj = json.loads(m.data)
            field = next(k for k in obj if k not in ("seq", "t"))
            per.setdefault(c.topic.lstrip("/"), []).append((obj["seq"], obj["t"], obj[field], m.publish_time,
                                                             m.log_time))
    out = {}
    for topic, rows in per.items():
        rows.sort(key=lambda r: r[0])
        out[topic] = (np.array([r[0] for r in rows]), np.array([r[1] for r in rows], float),
                      np.array([r[2] for r in rows], float), [r[3] for r in rows], [r[4] for r in rows])
    return out


def assert_reads_like_the_peer(path, kinds=wire.KINDS):
    rec = read_recording(path, kinds=kinds)
    ref = peer_arrays(path)
    got = {td.topic: td for dev in rec.devices.values() for td in dev.streams.values()}
    assert set(got) == {t for t in ref if t.rsplit("/", 1)[-1] in set(kinds) | {"measurement"}}
    for topic, td in got.items():
        seq, t, vals, pub, log = ref[topic]
        assert td.seq.tolist() == seq.tolist(), topic
        assert same_bits(td.t, t) and same_bits(td.values, vals), topic
        assert td.publish_ns.tolist() == pub and td.log_ns.tolist() == log, topic
    return rec


def blocked_file(path, n=3000, block=700, chunk_size=4096, name="dev", **writer_kw):
    """Per-topic blocks of ``block`` samples (how ``noiselab simulate`` wrote before it
    interleaved), written with mcap's Writer so that its index options can be switched off."""
    data = make_data(n)
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=chunk_size, **writer_kw)
        w.start()
        cids = {}
        for kind in wire.KINDS:
            sid = w.register_schema(wire.SCHEMA_NAMES[kind], "jsonschema", wire.schema_bytes(kind))
            cids[kind] = w.register_channel(wire.key(name, kind), "json", sid)
        for k0 in range(0, n, block):
            for kind in wire.KINDS:
                t, pub, log, vals = data[kind]
                sl = slice(k0, min(k0 + block, n))
                for k, p in zip(range(k0, sl.stop), wire.encode_batch(kind, k0, t[sl], vals[sl])):
                    w.add_message(cids[kind], log_time=int(log[k]), data=p, publish_time=int(pub[k]), sequence=k)
        w.finish()
    return data


@pytest.mark.parametrize("layout", ["interleaved", "blocked", "blocked_no_message_index",
                                    "blocked_no_statistics", "one_chunk_uncompressed"])
def test_fast_reader_equals_the_mcap_reader_on_every_layout(tmp_path, layout):
    """read_recording's chunk-level path (message indexes, numpy, packed payloads) gives exactly
    the peer's numbers whatever the file's layout and index options; --json's read without truth
    skips the truth topic and still gives the same measurement and command."""
    from mcap.writer import CompressionType, IndexType

    path = tmp_path / f"{layout}.mcap"
    if layout == "interleaved":
        write_sample(path, 500, chunk_size=2048)
    elif layout == "blocked":
        blocked_file(path)
    elif layout == "blocked_no_message_index":
        blocked_file(path, index_types=IndexType.CHUNK | IndexType.METADATA | IndexType.ATTACHMENT)
    elif layout == "blocked_no_statistics":
        blocked_file(path, use_statistics=False)
    else:
        blocked_file(path, n=400, chunk_size=1 << 24, compression=CompressionType.NONE)
    rec = assert_reads_like_the_peer(path)
    assert rec.complete
    rec2 = assert_reads_like_the_peer(path, kinds=("measurement", "command"))
    assert set(rec2.device().streams) == {"measurement", "command"}


def message_index_records(path):
    """(file offset, channel id, records length) of every MessageIndex record of a finished file."""
    out = []
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        for ci in summary.chunk_indexes:
            for cid, off in ci.message_index_offsets.items():
                f.seek(off)
                head = f.read(15)
                assert head[0] == 0x07
                out.append((off, cid, int.from_bytes(head[11:15], "little")))
    return out


@pytest.mark.parametrize("damage", ["offset_points_elsewhere", "entry_missing"])
def test_fast_reader_does_not_trust_a_wrong_message_index(tmp_path, damage):
    """Message indexes carry no CRC. One pointing into the middle of a record, or one that leaves
    a message out (the summary's counts then disagree), makes the reader walk the records
    instead: same numbers as the peer, which ignores the indexes."""
    path = tmp_path / "blocked.mcap"
    blocked_file(path)
    blob = bytearray(path.read_bytes())
    off, cid, nbytes = message_index_records(path)[3]
    if damage == "offset_points_elsewhere":
        first = off + 15 + 8                     # offset field of the first (timestamp, offset) pair
        blob[first:first + 8] = (int.from_bytes(blob[first:first + 8], "little") + 3).to_bytes(8, "little")
    else:
        blob[off + 11:off + 15] = (nbytes - 16).to_bytes(4, "little")   # one pair fewer
    path.write_bytes(bytes(blob))
    with open(path, "rb") as f:                  # the damage is really there
        summary = make_reader(f).get_summary()
    assert summary is not None
    assert_reads_like_the_peer(path)


@pytest.mark.parametrize("payload, ok", [
    (b'{"seq":0,"t":0.0,"y":[1e-05,-0.0]}', True),
    (b'{"seq":0,"t":1E+300,"y":[12345678901234567890,2.5e-320]}', True),
    (b'{"seq":0,"t":0,"y":[-1,0]}', True),
    (b'{"seq":0,"t":-0,"y":[-0,1e-0]}', True),          # integer -0: json gives 0, not -0.0
    (b'{"seq":0,"t":0.0,"y":[+1,0]}', False),          # not JSON numbers: the template path must
    (b'{"seq":0,"t":0.0,"y":[01,0]}', False),          # not accept what json refuses
    (b'{"seq":0,"t":0.0,"y":[.5,0]}', False),
    (b'{"seq":0,"t":0.0,"y":[1.,0]}', False),
    (b'{"seq":0,"t":0.0,"y":[1e,0]}', False),
    (b'{"seq":0,"t":0.0,"y":[NaN,0]}', False),
    (b'{"seq":0,"t":0.0,"y":[Infinity,0]}', False),
    (b'{"seq":0,"t":0.0,"y":[true,0]}', False),
    (b'{"seq":-1,"t":0.0,"y":[1,0]}', False),
    (b'{"seq":0.0,"t":0.0,"y":[1,0]}', False),
    (b'{"seq":0,"t":0.0,"y":[1,0],"t":1}', True),       # duplicate key: json keeps the last
    (b'{"seq":0,"t":0.0,"y":[1,0]}\n{"seq":0,"t":0.0,"y":[1,0]}', False),
    (b'{"seq":0, "t":0.0,"y":[1,0]}', True),           # valid JSON, not the template: slow path
    (b'{"t":0.0,"seq":0,"y":[1,0]}', True),
])
def test_packed_decode_agrees_with_json_on_odd_payloads(payload, ok):
    """wire.decode_packed (the reader's path) on 50 good payloads with one odd one in the middle:
    exactly json's values when the odd one is valid, a WireError naming the topic when not."""
    good = wire.encode_batch("measurement", 0, np.arange(50) * Ts, np.arange(100.0).reshape(50, 2) / 7)
    payloads = good[:20] + [payload] + good[21:]
    blob = b"".join(p + b"\n" for p in payloads)
    lens = np.array([len(p) for p in payloads])
    if not ok:
        with pytest.raises(wire.WireError, match="^dev/measurement: "):
            wire.decode_packed(blob, lens, "measurement", topic="dev/measurement")
        return
    seq, t, vals = wire.decode_packed(blob, lens, "measurement", topic="dev/measurement")
    objs = [json.loads(p) for p in payloads]
    assert seq.tolist() == [o["seq"] for o in objs]
    assert same_bits(t, [o["t"] for o in objs]) and same_bits(vals, [o["y"] for o in objs])


# ----------------------------------------------------------- time-ordered reading (replay)


def test_iter_time_ordered_merges_blocked_topics_with_bounded_memory(tmp_path):
    """iter_time_ordered on a file of 2000-sample per-topic blocks: publish_time never goes back,
    each topic comes in its own order, a sample's topics come truth, command, measurement; every
    message once, bytes unchanged (hashed as they come). Memory: it decodes chunk by chunk (one
    per topic in flight): what it holds at the first message (the summary's chunk index and a
    chunk per topic) is a fraction of the payload bytes, and it does not grow after that."""
    import hashlib
    import tracemalloc

    path = tmp_path / "blocked.mcap"
    n = 24000
    blocked_file(path, n=n, block=8000, chunk_size=8192)
    ref = {}
    for _, c, m in iter_messages(path):
        ref.setdefault(c.topic, hashlib.sha256()).update(m.data)
    with open(path, "rb") as f:
        total_bytes = sum(len(m.data) for _, _, m in make_reader(f).iter_messages())
    order = {"truth": 0, "command": 1, "measurement": 2}
    got = {t: hashlib.sha256() for t in ref}
    seqs = {t: [] for t in ref}
    last = (-1, -1)
    report = ScanReport()
    held = first = 0
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    for i, (_, c, m) in enumerate(iter_time_ordered(path, report=report)):
        if i == 0:
            first = tracemalloc.get_traced_memory()[0] - base
        key = (m.publish_time, order[c.topic.rsplit("/", 1)[-1]])
        assert key > last, (i, key, last)
        last = key
        got[c.topic].update(m.data)
        if i % 250 == 0:
            held = max(held, tracemalloc.get_traced_memory()[0] - base)
        if m.sequence % 4000 == 0:
            seqs[c.topic].append(m.sequence)
    tracemalloc.stop()
    assert {t: h.digest() for t, h in got.items()} == {t: h.digest() for t, h in ref.items()}
    assert all(s == list(range(0, n, 4000)) for s in seqs.values())
    assert report.complete and report.messages == 3 * n
    print(f"\nmerge memory: {first} B at the first message, +{held - first} B after; payloads {total_bytes} B")
    assert first < total_bytes / 4, (first, total_bytes)
    assert held - first < total_bytes / 20, (held, first, total_bytes)


def test_iter_time_ordered_on_an_unfinished_file(tmp_path):
    """Without a summary (a cut file) the merge reads in one pass: the same time order."""
    full = tmp_path / "full.mcap"
    write_sample(full, 300, chunk_size=1024)
    blob = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(blob[: len(blob) // 2])
    report = ScanReport()
    items = [(c.topic, m.publish_time, m.sequence) for _, c, m in iter_time_ordered(cut, report=report)]
    assert not report.complete and items
    order = {"truth": 0, "command": 1, "measurement": 2}
    keys = [(p, order[t.rsplit("/", 1)[-1]]) for t, p, _ in items]
    assert keys == sorted(keys)
    assert sorted(items) == sorted((c.topic, m.publish_time, m.sequence) for _, c, m in iter_messages(cut))


def test_iter_time_ordered_replays_a_restarted_source_one_stream_after_the_other(tmp_path):
    """A recording in which the source restarted (sample times begin again): replay's order is
    the recorded one, stream after stream, not the two streams' samples merged by their equal
    sample times; in a finished file and in a cut one."""
    path = tmp_path / "restart.mcap"
    items = [(k, float(k)) for k in range(30)] + [(k, 100.0 + k) for k in range(20)]
    write_stream(path, items, kinds=("truth", "command", "measurement"))
    recorded = [(c.topic, m.data) for _, c, m in iter_messages(path)]
    assert [(c.topic, m.data) for _, c, m in iter_time_ordered(path)] == recorded
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-100])
    report = ScanReport()
    assert [(c.topic, m.data) for _, c, m in iter_time_ordered(cut, report=report)] == recorded
    assert not report.complete


def test_write_interleaved_puts_the_topics_of_a_sample_together(tmp_path):
    """RecordingWriter.write_interleaved (noiselab simulate's writer): file order is truth,
    command, measurement of sample k, then k + 1; the data read back exactly."""
    path = tmp_path / "inter.mcap"
    data = make_data(40)
    with RecordingWriter(path, chunk_size=512) as w:
        w.write_interleaved([(wire.key("dev", kind), kind, 0, data[kind][1], data[kind][2],
                              wire.encode_batch(kind, 0, data[kind][0], data[kind][3])) for kind in wire.KINDS])
        with pytest.raises(McapIoError, match="payloads where the other streams have"):
            w.write_interleaved([("noiselab/dev/truth", "truth", 40, np.zeros(1, np.int64), np.zeros(1, np.int64),
                                  [b"{}"]), ("noiselab/dev/command", "command", 40, np.zeros(0, np.int64),
                                             np.zeros(0, np.int64), [])])
    assert [(t.rsplit("/", 1)[1], s) for t, s, *_ in messages(path)] == \
        [(kind, k) for k in range(40) for kind in wire.KINDS]
    assert_reads_like_the_peer(path)


def test_recover_keeps_the_sources_header_schemas_channels_and_metadata(tmp_path):
    """A foreign file (its own profile and library, a ROS-like schema, channel metadata, a topic
    that has no message in the part that survives, metadata records) cut inside its second chunk:
    the repaired file is the same kind of file, not a noiselab one."""
    src = tmp_path / "foreign.mcap"
    with open(src, "wb") as f:
        w = Writer(f, chunk_size=2048)
        w.start(profile="x-test", library="some-writer 4.2")
        sid = w.register_schema("pkg/msg/Thing", "ros2msg", b"float64 x\n")
        busy = w.register_channel("/busy", "cdr", sid, {"offered_qos_profiles": "- depth: 10\n"})
        w.register_channel("/quiet", "json", 0, {"why": "schemaless, never written"})
        w.add_metadata("about", {"site": "lab 3"})
        for k in range(400):
            w.add_message(busy, log_time=1_700_000_000_000_000_000 + k, data=k.to_bytes(8, "little"),
                          publish_time=1_700_000_000_000_000_000 + k, sequence=k)
        w.finish()
    (start, end, *_), = top_level_chunks(src)[1:2]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(src.read_bytes()[:(start + end) // 2])
    stats = recover(cut, tmp_path / "fixed.mcap")
    assert 0 < stats.total < 400 and not stats.already_complete
    with open(tmp_path / "fixed.mcap", "rb") as f:
        reader = make_reader(f)
        header, summary = reader.get_header(), reader.get_summary()
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert (header.profile, header.library) == ("x-test", "some-writer 4.2")
    chans = {c.topic: c for c in summary.channels.values()}
    assert set(chans) == {"/busy", "/quiet"}
    assert chans["/busy"].message_encoding == "cdr"
    assert chans["/busy"].metadata == {"offered_qos_profiles": "- depth: 10\n"}
    assert chans["/quiet"].schema_id == 0 and chans["/quiet"].metadata == {"why": "schemaless, never written"}
    schema = summary.schemas[chans["/busy"].schema_id]
    assert (schema.name, schema.encoding, schema.data) == ("pkg/msg/Thing", "ros2msg", b"float64 x\n")
    assert meta == {"about": {"site": "lab 3"}}
    got = messages(tmp_path / "fixed.mcap")
    assert len(got) == stats.total and got == messages(src)[:stats.total]


def test_a_recovered_truncated_ros2_bag_is_still_a_ros2_bag(tmp_path):
    """A rosbag2 MCAP bag (rosbags' own writer, sensor_msgs/msg/Imu) cut as a killed `ros2 bag
    record` leaves it, recovered: rosbags opens the repaired .mcap as a ROS 2 bag by itself and
    decodes every recovered message as the source's. (The bag directory's metadata.yaml counts the
    whole bag, so it is not the repaired file's; a single .mcap of profile ros2 needs none.)"""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as BagWriter
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    Imu = T["sensor_msgs/msg/Imu"]
    bag = tmp_path / "bag"
    t0 = 1_700_000_000_000_000_000
    with BagWriter(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/imu", Imu.__msgtype__, typestore=store)
        for k in range(2000):
            stamp = T["builtin_interfaces/msg/Time"](k // 100, (k % 100) * 10_000_000)
            msg = Imu(T["std_msgs/msg/Header"](stamp, "imu"), T["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0),
                      np.zeros(9), T["geometry_msgs/msg/Vector3"](0.001 * k, -0.5, 0.25), np.zeros(9),
                      T["geometry_msgs/msg/Vector3"](0.0, 0.0, 9.81), np.zeros(9))
            w.write(conn, t0 + k * 10_000_000, store.serialize_cdr(msg, Imu.__msgtype__))
    whole = next(bag.glob("*.mcap")).read_bytes()
    cut = tmp_path / "killed.mcap"
    cut.write_bytes(whole[: len(whole) * 2 // 3])
    fixed = tmp_path / "fixed.mcap"
    stats = recover(cut, fixed)
    assert 0 < stats.total < 2000

    def read(path):
        with AnyReader([path]) as r:
            return [(c.topic, c.msgtype, t, r.deserialize(raw, c.msgtype).angular_velocity.x)
                    for c, t, raw in r.messages()]

    got = read(fixed)
    assert len(got) == stats.total
    assert got == read(bag)[:stats.total]
    assert got[-1][2] == t0 + (stats.total - 1) * 10_000_000
