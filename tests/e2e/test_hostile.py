"""Messages from the network are untrusted input: every node (emulator, recorder, live analyzer)
survives anything a Zenoh peer on 127.0.0.1 publishes, and a hostile message never spoils a
recording. Real processes and real Zenoh sessions on loopback (multicast scouting off), real
MCAP files read back, as in tests/e2e/test_live.py, whose helpers this file uses.

Synchronisation is by events only (a child's stderr line, a subscriber's condition variable, a
recorder's answer to a query, process exit); every timeout is a failure bound, never a pass.
"""

from __future__ import annotations

import io
import json
import os
import random
import subprocess
import sys
import threading

import numpy as np
import pytest
import zenoh

from noiselab.recordings.load import load_noiselab
from noiselab.model import load_model
from noiselab.nodes import recorder, transport
from noiselab import wire
from noiselab.recordings.errors import McapWriteError
from noiselab.recordings.reader import read_recording
from noiselab.recordings.writer import RecordingWriter
from noiselab.nodes.analyzer import READY_MARK as ANALYZER_READY
from noiselab.nodes.analyzer import LiveAnalyzer
from noiselab.nodes.recorder import Ingest
from noiselab.nodes.recorder_summary import RecorderSummary
from noiselab.nodes.runner import READY_MARK, free_port
from helpers.live import (CONTROLLER, EMULATE_MARK, ROOT, ROUTER_MARK, Collector, check_summary_topics, ep,
                          file_messages, session_config, waited_for_subscribers)
from helpers.models import LOOP_TOML

pytestmark = pytest.mark.slow   # live end-to-end runs: real processes and sessions

T_EVENT = 60.0            # bound for "the next event happens" on a shared 2-core machine; never a pass
DEEP = 200_000            # nesting levels of the deep payloads (Python's JSON parser recurses ~1000)


def deep(levels: int = DEEP) -> bytes:
    return b"[" * levels + b"]" * levels


def sample(kind: str, seq: int, vec, Ts: float = 0.01) -> bytes:
    return wire.encode(seq, wire.sample_time(seq, Ts), vec, kind=kind)


def cli(*args, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "noiselab.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=ROOT, timeout=timeout)


# ------------------------------------------------------------------ the recorder's books


def test_recorder_skips_what_does_not_continue_its_stream(tmp_path):
    """Ingest (the recorder's work on what it received): a vector's length is fixed by its
    stream's first message, so wrong-length messages (injected with seq 0, empty, 10^3 elements)
    are skipped and counted, not booked as restarts or gaps; a seq that jumps ahead is held
    until the next message: not followed by its successor it is skipped (a forged seq), followed
    by it the gap is real and both are recorded, and an end of stream that counts it takes it;
    batches and single messages give the same file and books."""
    meas = [("noiselab/d/measurement", sample("measurement", k, [0.5])) for k in range(40)]
    items = meas[:10]
    hostile = [sample("measurement", 0, [0.1, 0.2]), sample("measurement", 0, []),
               sample("measurement", 10, [0.0] * 1000), sample("measurement", 10**12, [0.5]),
               b'{"seq":10,"t":0.1,"y":' + deep() + b"}"]
    items += [("noiselab/d/measurement", p) for p in hostile]
    items += meas[10:20] + meas[23:40]                    # a real gap: 20..22 lost on the way
    items += [("noiselab/d/truth", sample("truth", k, [1.0, 2.0])) for k in range(5)]
    items += [("noiselab/d/truth", sample("truth", 9, [1.0, 2.0]))]        # ahead, then the end says 10
    end = wire.encode_end(0, 0.39, 40, {"measurement": 40, "truth": 10}, "duration")
    items += [("noiselab/d/end", end)]
    results = []
    for mode in ("batch", "one by one"):
        path = tmp_path / f"{mode}.mcap"
        with RecordingWriter(path) as w, open(tmp_path / f"{mode}.log", "w") as log:
            ing = Ingest(w, str(path), log=log)
            if mode == "batch":
                ing.add(items, 1_000)
            else:
                for item in items:
                    ing.add([item], 1_000)
            ing.finish()
        results.append(({k: b.as_dict() for k, b in ing.books.items()}, ing.messages, ing.malformed,
                         ing.malformed_topics, {t: [m.data for _, _, m in v] for t, v in file_messages(path).items()}))
    assert results[0] == results[1]
    books, messages, malformed, per_topic, files = results[0]
    assert (malformed, per_topic) == (5, {"noiselab/d/measurement": 5})
    m = books["noiselab/d/measurement"]
    assert (m["count"], m["gaps"], m["restarts"], m["expected"], m["missing"]) == (37, [[19, 3]], [], 40, 3)
    assert files["noiselab/d/measurement"] == [p for _, p in meas[:20] + meas[23:]]
    tb = books["noiselab/d/truth"]
    assert (tb["count"], tb["gaps"], tb["last_seq"], tb["missing_at_end"]) == (6, [[4, 4]], 9, 0)
    assert messages == 37 + 6 + 1
    rec = read_recording(tmp_path / "batch.mcap")
    assert rec.device("d").measurement.values.shape == (37, 1)
    text = (tmp_path / "batch.log").read_text()
    assert "y has 2 elements at seq 0; the stream's have 1" in text
    assert "seq 1000000000000 jumps from the stream's last seq 9 and no message followed it" in text
    assert f"deeper than {wire.MAX_DEPTH}" in text


def test_recorder_tells_a_bad_message_from_a_file_that_takes_none():
    """A message the writer refuses (a sample time before the epoch; its successor confirms the
    stream's start) is skipped and counted; a file that takes no more (a full disk: /dev/full)
    stops the recorder with McapWriteError instead of counting every later message as
    malformed."""
    with RecordingWriter("/dev/full", force=True, chunk_size=1024) as w:
        ing = Ingest(w, "/dev/full", log=open(os.devnull, "w"))
        ing.add([("noiselab/d/measurement", b'{"seq":0,"t":-1.0,"y":[0.5]}'),
                 ("noiselab/d/measurement", sample("measurement", 1, [0.5]))], 1_000)
        assert (ing.malformed, ing.messages) == (1, 1)
        with pytest.raises(McapWriteError, match="No space left"):
            for k in range(2, 1000):
                ing.add([("noiselab/d/measurement", sample("measurement", k, [0.5]))], 1_000)
        assert ing.malformed == 1


def test_recorder_says_which_sources_vanished_without_an_end_of_stream(spawn, tmp_path):
    """Two sources: one ends its stream, the other closes its session without an end of stream.
    On stop the recorder says so for the second, one line, and lists it in its summary and in
    the file's metadata (with the last seq it got of each topic); the first is not listed."""
    port = free_port()
    out = tmp_path / "vanished.mcap"
    rec = spawn("record", "record", "--listen", ep(port), "--out", out, "--json")
    rec.wait_line(READY_MARK)
    with zenoh.open(session_config(connect=[ep(port)])) as session:
        pubs = {(dev, kind): session.declare_publisher(wire.key(dev, kind), **transport.DATA_QOS)
                for dev in ("gone", "done") for kind in ("measurement", "command", "end")}
        assert transport.wait_matching(pubs.values(), T_EVENT), "the recorder did not match"
        for k in range(50):
            for dev in ("gone", "done"):
                pubs[dev, "measurement"].put(sample("measurement", k, [0.5]))
                if k < 30:
                    pubs[dev, "command"].put(sample("command", k, [0.0]))
        end = transport.end_stream(session, pubs["done", "end"],
                                   wire.encode_end(0, 0.49, 50, {"measurement": 50, "command": 30}, "duration"), T_EVENT)
        assert len(end["acks"]) == 1 and end["acks"][0]["complete"], end
    assert rec.interrupt() == 0, rec.stderr_text()
    lines = [ln for ln in rec.err if "no end of stream" in ln]
    assert lines == ["noiselab record: noiselab/gone: no end of stream (the source vanished, or was still "
                     "streaming at the stop); last seq command 29, measurement 49"], rec.stderr_text()
    summary = rec.json()
    assert summary["unended"] == {"noiselab/gone": {"measurement": 49, "command": 29}}
    assert summary["malformed"] == 0
    meta = read_recording(out).metadata["noiselab.recorder"]
    assert json.loads(meta["unended"]) == summary["unended"]


def ingest(tmp_path, items, mode: str = "batch", name: str = "rec"):
    """``items`` through the recorder's Ingest (one batch, or one message per batch), finished:
    ``(ingest, file, log text)``."""
    path, log = tmp_path / f"{name}.mcap", io.StringIO()
    with RecordingWriter(path) as w:
        ing = Ingest(w, str(path), log=log)
        for batch in ([items] if mode == "batch" else [[item] for item in items]):
            ing.add(batch, 1_000)
        ing.finish()
    return ing, path, log.getvalue()


@pytest.mark.parametrize("mode", ["batch", "one by one"])
def test_a_forged_first_message_fixes_neither_the_length_nor_the_start(tmp_path, mode):
    """The recorder starts before its sources, so a topic's first message may be a forged one:
    y = [0.1, 0.2] with seq 0, then y = [0.3] with seq 10^12, before the source's 200 samples of
    one element. A stream's length and start are trusted only once a successor confirms them:
    the 200 are recorded, the two forged ones skipped and counted, the file is one stream
    without gaps."""
    key = "noiselab/dev/measurement"
    genuine = [(key, sample("measurement", k, [float(np.sin(k))])) for k in range(200)]
    items = [(key, sample("measurement", 0, [0.1, 0.2])), (key, sample("measurement", 10**12, [0.3]))] + genuine
    ing, path, log = ingest(tmp_path, items, mode)
    assert (ing.messages, ing.malformed, ing.malformed_topics) == (200, 2, {key: 2})
    td = read_recording(path).device("dev").measurement
    assert td.seq.tolist() == list(range(200)) and td.gaps() == [] and td.segments == [(0, 200)]
    assert [m.data for _, _, m in file_messages(path)[key]] == [p for _, p in genuine]
    assert "y has 2 elements at seq 0; the stream's have 1" in log
    assert "seq 1000000000000 would start the stream and no message followed it" in log


@pytest.mark.parametrize("mode", ["batch", "one by one"])
@pytest.mark.parametrize("forged", [50, 0, 149, 150], ids=["past", "zero", "recorded", "last"])
def test_a_forged_past_or_repeated_seq_never_reaches_the_file(tmp_path, forged, mode):
    """One valid-looking measurement with a past seq (50), seq 0, a seq already recorded (149) or
    the last recorded one (150), with other data, after seq 150 of a 200-sample stream: it is
    skipped and counted, and the file holds the genuine stream, one segment without gaps (the
    forged one, recorded, would make the file unreadable: "seq 50 comes twice with different data").
    The source then restarts (0, 1, ...): confirmed by its successors, that is a restart."""
    key = "noiselab/dev/measurement"
    genuine = [(key, sample("measurement", k, [float(np.sin(k))])) for k in range(200)]
    restart = [(key, sample("measurement", k, [float(np.cos(k))])) for k in range(30)]
    items = genuine[:151] + [(key, sample("measurement", forged, [9.0]))] + genuine[151:] + restart
    ing, path, log = ingest(tmp_path, items, mode)
    assert (ing.messages, ing.malformed, ing.malformed_topics) == (230, 1, {key: 1})
    book = ing.books[key].as_dict()
    assert (book["gaps"], book["restarts"]) == ([], [[199, 0]])
    td = read_recording(path).device("dev").measurement
    assert td.segments == [(0, 200), (200, 230)] and td.gaps() == []
    assert 9.0 not in td.values
    assert f"seq {forged} " in log


def test_a_recording_with_a_forged_seq_0_is_analysable(tmp_path):
    """The seed model's 3000 samples (command and measurement) with one forged measurement of
    seq 0 at sample 2000: the recording loads as one stream of 3000 samples (the forged one,
    recorded as a restart, would split the measurement into two stream segments against the
    command's one)."""
    model = load_model("seed")
    n = 3000
    sim = model.simulate(n, seed=2)
    items = []
    for k in range(n):
        items += [("noiselab/seed/command", sample("command", k, sim.u[k])),
                  ("noiselab/seed/measurement", sample("measurement", k, sim.y[k]))]
        if k == 2000:
            items.append(("noiselab/seed/measurement", sample("measurement", 0, [0.123])))
    ing, path, _ = ingest(tmp_path, items)
    assert (ing.messages, ing.malformed) == (2 * n, 1)
    series = load_noiselab(path, model=model)
    assert series.y.shape == (n, 1) and np.array_equal(series.y, sim.y)


def test_an_end_of_stream_that_cannot_be_the_sources_is_not_taken(tmp_path):
    """Well-formed ends of stream from a peer that is not the source: one counting fewer messages
    than are recorded (5 after seq 99) is skipped, counted and said once, and the source stays
    live; one counting more than came (160 after seq 149) is taken until data go on past its
    count (seq 160), which undoes it (its tail booked missing, the source ended); the source's
    own end then books a complete stream, and a second end is skipped."""
    key, end_key = "noiselab/d/measurement", "noiselab/d/end"
    meas = [(key, sample("measurement", k, [0.5])) for k in range(300)]

    def end(n):
        return [(end_key, wire.encode_end(0, (n - 1) * 0.01, n, {"measurement": n}, "stopped"))]

    path, log = tmp_path / "ends.mcap", io.StringIO()
    with RecordingWriter(path) as w:
        ing = Ingest(w, str(path), log=log)
        ing.add(meas[:100] + end(5), 1_000)
        assert ing.live == {"noiselab/d"} and ing.ends == {} and ing.books[key].expected is None
        ing.add(meas[100:150] + end(160) + meas[150:160], 1_000)
        assert ing.live == set() and ing.books[key].missing_at_end == 0      # 150..159 came: nothing missing yet
        ing.add(meas[160:300], 1_000)
        assert ing.live == {"noiselab/d"} and ing.books[key].expected is None
        ing.add(end(300) + end(300), 1_000)
        ing.finish()
        assert ing.ack("noiselab/d")["complete"]
    book = ing.books[key].as_dict()
    assert (book["count"], book["gaps"], book["expected"], book["missing"]) == (300, [], 300, 0)
    assert (ing.malformed, ing.malformed_topics) == (2, {end_key: 2})
    assert ing.live == set() and ing.unended() == {}
    text = log.getvalue()
    assert text.count("an end of stream counting 5 measurement messages, but seq 99 is recorded") == 1
    assert text.count("seq 160 came after an end of stream that counted 160") == 1
    assert "noiselab record: noiselab/d ended (stopped) after 300 samples: every message recorded" in text
    assert "a second end of stream for a stream that has ended" in text
    assert [wire.decode(m.data)["seq"] for _, _, m in file_messages(path)[key]] == list(range(300))


def test_a_join_point_from_any_peer_does_not_hold_the_recording(tmp_path, monkeypatch):
    """A join point comes from any peer that answers the recorder's query: one far past the stream
    (2**62, well formed) would hold every sample in memory until the recorder stops (nothing on
    disk: a SIGKILL would lose it all). A point more than the channel's capacity past a topic's
    first seq is not waited for, and a topic with that many samples waiting is written from
    there: the samples are written as they come (the capacity made 64 here)."""
    monkeypatch.setattr(recorder, "CAPACITY", 64)
    far, near = "noiselab/d/measurement", "noiselab/d/command"
    path, log = tmp_path / "join.mcap", io.StringIO()
    with RecordingWriter(path) as w:
        ing = Ingest(w, str(path), log=log)
        ing.join = {far: 2**62, near: 64}
        for k0 in range(0, 64, 16):
            ing.add([(key, sample(kind, k, [0.5])) for k in range(k0, k0 + 16)
                     for key, kind in ((far, "measurement"), (near, "command"))], 1_000)
        assert ing.books[far].count == 64 and ing.books[near].count == 64 and ing.join == {}
    text = log.getvalue()
    assert f"{far}: join point {2**62} is more than 64 samples past the first seq received (0): not waited for" in text
    assert f"{near}: 64 samples waited for join point 64" in text


def test_recorder_prints_a_hostile_key_on_one_line(tmp_path):
    """Zenoh takes a newline and ESC in a key: the recorder's lines about such a topic (a skipped
    message, a source without an end of stream, the summary) are one line each, the control
    characters escaped."""
    key = "noiselab/a\nb\x1b[2J/measurement"
    items = [(key, b"{")] + [(key, sample("measurement", k, [0.5])) for k in range(3)]
    path, log = tmp_path / "keys.mcap", io.StringIO()
    with RecordingWriter(path) as w:
        ing = Ingest(w, str(path), log=log)
        ing.add(items, 1_000)
        ing.finish()
        unended = ing.say_unended()
    lines = log.getvalue().splitlines()
    assert len(lines) == 2 and all(ln.startswith("noiselab record: ") and "\x1b" not in ln for ln in lines), lines
    assert "noiselab/a\\nb\\x1b[2J/measurement" in lines[0] and "noiselab/a\\nb\\x1b[2J: no end of stream" in lines[1]
    summary = RecorderSummary(out=str(path), topics=ing.books, messages=ing.messages, malformed=ing.malformed,
                              wall_s=0.0, malformed_topics=ing.malformed_topics, unended=unended)
    assert all("\n" not in ln and "\x1b" not in ln for ln in summary.lines()), summary.lines()


def test_join_answers_beyond_int64_are_ignored():
    """A join answer from any peer: a point beyond int64 (10^30) is no seq of any stream and is
    left out; the answering source's other points are taken."""
    port = free_port()
    with zenoh.open(session_config(listen=[ep(port)])) as source, \
            zenoh.open(session_config(connect=[ep(port)])) as sink:
        q = transport.serve_join(source, "d", lambda: {"noiselab/d/measurement": 10**30, "noiselab/d/truth": 7})
        # a sample from the source comes after its declaration of the queryable on the same link
        got = Collector()
        sub = sink.declare_subscriber("noiselab/d/ping", got)
        pub = source.declare_publisher("noiselab/d/ping")
        assert transport.wait_matching([pub], T_EVENT), "the sink's subscriber did not reach the source"
        pub.put(b"1")
        got.wait_for(lambda: got.count("noiselab/d/ping") == 1, "the source's sample")
        sub.undeclare()
        points = transport.join_points(sink, "noiselab/**", timeout=T_EVENT)
        q.undeclare()
    assert points == {"noiselab/d/truth": 7}


# -------------------------------------------------------------- one hostile message, each node


def test_live_analyzer_counts_and_skips_hostile_samples_and_keeps_updating(spawn, tmp_path):
    """A live analyzer fed the seed model's 1200 samples (measurement and command) from a session
    here, with hostile messages after sample 599: JSON nested 200,000 deep (beyond the depth
    Python's parser can recurse to), seq 10^26 (beyond int64, the ring's index), a valid-looking
    seq 10^12 (a window moved there would hold no sample), vectors of the wrong length (2, 0 and
    10^6 elements), and finite samples of 1e308 (their squares overflow the statistics). It keeps
    updating to the last sample, analyses all 1200 (none of the hostile ones took a place),
    counts each hostile message once, says each reason once, and exits 0."""
    model = load_model("seed")
    n, cut = 1200, 600
    sim = model.simulate(n, seed=4)
    good = {kind: wire.encode_batch(kind, 0, sim.t, values) for kind, values in
            (("measurement", sim.y), ("command", sim.u))}
    hostile = [("measurement", deep()), ("command", b'{"":' * DEEP + b"1" + b"}" * DEEP),
               ("measurement", b'{"seq":100000000000000000000000000,"t":6.0,"y":[0.1]}'),
               ("measurement", sample("measurement", 10**12, [0.1])),
               ("measurement", sample("measurement", cut, [0.1, 0.2])), ("measurement", sample("measurement", cut, [])),
               ("measurement", b'{"seq":600,"t":6.0,"y":[' + b",".join([b"0.1"] * 10**6) + b"]}"),
               ("measurement", sample("measurement", cut, [1e308])), ("command", sample("command", cut, [1e308]))]
    port = free_port()
    got = Collector()
    with zenoh.open(session_config(listen=[ep(port)])) as session:
        sub = session.declare_subscriber("noiselab/seed/analysis", got)
        an = spawn("analyze", "analyze", "--live", "--model", "seed", "--connect", ep(port), "--window", "20",
                   "--update", "0.5", "--json")
        an.wait_line(ANALYZER_READY)
        pubs = {kind: session.declare_publisher(wire.key("seed", kind), **transport.DATA_QOS)
                for kind in ("measurement", "command")}
        assert transport.wait_matching(pubs.values(), T_EVENT), "the analyzer did not match"
        for k in range(n):
            if k == cut:
                for kind, payload in hostile:
                    pubs[kind].put(payload)
            pubs["command"].put(good["command"][k])
            pubs["measurement"].put(good["measurement"][k])

        def done():
            return any((s := json.loads(p))["samples"] == n and s["received"] == 2 * n and s["malformed"] == len(hostile)
                       for p, _ in got.by_key.get("noiselab/seed/analysis", []))
        got.wait_for(done, f"a summary of all {n} samples with {len(hostile)} malformed")
        assert an.interrupt() == 0, an.stderr_text()
        sub.undeclare()
    last = json.loads(got.by_key["noiselab/seed/analysis"][-1][0])
    assert last["t"] == sim.t[-1]                     # it analysed up to the last sample
    final = an.json()
    assert (final["samples"], final["received"], final["malformed"]) == (n, 2 * n, len(hostile))
    said = [ln for ln in an.err if "skipped a message" in ln]
    assert len(said) == 4, an.stderr_text()        # one line per reason: contract, length, seq, magnitude
    assert any("seq 1000000000000 jumps from the stream's last seq 599 and no message followed it" in ln
               for ln in said), said
    assert not any("Traceback" in ln for ln in an.err), an.stderr_text()


def test_live_analyzer_takes_a_past_seq_or_a_restart_only_when_confirmed():
    """The live analyzer's window (a ring indexed by seq) takes a message by the recorder's rule:
    a past seq within the window with other data (250 after 299) and a lone seq 0 mid-stream
    would overwrite genuine samples; they are skipped and counted. A restart before the window is
    full (0, 1, ... from the source again) empties the ring instead of mixing two streams."""
    an = LiveAnalyzer("seed", device=None, window_s=5.0, log=io.StringIO())
    key = "noiselab/seed/measurement"

    def put(seqs, y):
        for k in seqs:
            an.q.put((key, sample("measurement", k, [y])))

    put(range(300), 0.5)
    put([250, 0], 9.0)
    put(range(300, 310), 0.5)
    an.drain()
    assert 310 < an.meas.cap                                   # the window is not full
    ok, _, v = an.meas.take(np.arange(310))
    assert ok.all() and (v == 0.5).all() and (an.received, an.bad) == (310, 2)
    put(range(50), -1.0)
    an.drain()
    ok, _, v = an.meas.take(np.arange(310))
    assert an.meas.max_seq == 49 and ok[:50].all() and not ok[50:].any() and (v[:50] == -1.0).all()
    assert (an.received, an.bad) == (360, 2)


def test_emulator_rejects_hostile_controls_says_so_once_and_keeps_running(spawn, tmp_path):
    """An emulator in closed loop (external command) receives controls of 1e308 (finite JSON, which
    would overflow the plant), nested 200,000 deep, of the wrong length, and of 10^6 elements;
    then a valid one. It rejects
    the five (the previous command stays), says so once, counts them in its summary, applies
    the valid one, ends its run at its duration and exits 0; every command it applied is
    finite and one it was given."""
    f = tmp_path / "loop.toml"
    f.write_text(LOOP_TOML)
    port = free_port()
    emu = spawn("emulate", "emulate", f, "--listen", ep(port), "--duration", "3", "--stale", "30",
                "--wait-subscribers", "20", "--json")
    emu.wait_line(EMULATE_MARK)
    got = Collector()
    cmd = "noiselab/loop/command"
    with zenoh.open(session_config(connect=[ep(port)])) as session:
        sub = session.declare_subscriber("noiselab/loop/**", got)
        pub = session.declare_publisher(wire.key("loop", wire.CONTROL), **transport.DATA_QOS)
        got.wait_for(lambda: got.last_seq(cmd) >= 5, "command seq 5")
        for payload in (b'{"seq":0,"t":0.0,"u":[1e308]}', deep(), sample("control", 0, [1.0, 2.0]),
                        sample("control", 0, []), b'{"seq":0,"t":0.0,"u":[' + b",".join([b"1"] * 10**6) + b"]}",
                        sample("control", 1, [0.5])):
            pub.put(payload)
        got.wait_for(lambda: any(wire.decode(p)["u"] == [0.5] for p, _ in got.by_key[cmd]), "the valid control applied")
        assert emu.finish() == 0, emu.stderr_text()
        got.wait_for(lambda: got.count("noiselab/loop/end") == 1, "the end of stream")
        sub.undeclare()
    summary = emu.json()
    assert summary["samples"] == 300 and summary["rejected_controls"] == 5 and summary["diverged_at"] is None
    said = [ln for ln in emu.err if "rejected a control" in ln]
    assert len(said) == 1 and "u[0]=1e+308 at seq 0 exceeds 1e+50" in said[0], emu.stderr_text()
    assert not any("Traceback" in ln for ln in emu.err), emu.stderr_text()
    applied = [wire.decode(p)["u"][0] for p, _ in got.by_key[cmd]]
    assert len(applied) == 300 and set(applied) == {0.0, 0.5}


UNSTABLE_TOML = """
name = "unstable"
[sampling]
Ts = 0.01
[plant]            # x' = 2000 x + u: grows e^20 per sample, past float64 within some 40 samples
A = [[2000.0]]
B = [[1.0]]
C = [[1.0]]
[command]
kind = "sine"
amplitude = 1.0
frequency_hz = 1.0
[sensor.white]
std = 0.01
"""


def test_emulator_ends_its_stream_where_the_plant_diverges(spawn, tmp_path):
    """An unstable plant grows past every bound: the emulator publishes no sample with an element
    beyond wire.MAGNITUDE_MAX (the bound the analysis of a recording accepts; non-finite ones
    included), says once where it stopped, ends its stream at the sample before (the end of
    stream counts what it published) and exits 0, its summary naming the sample."""
    f = tmp_path / "unstable.toml"
    f.write_text(UNSTABLE_TOML)
    port = free_port()
    emu = spawn("emulate", "emulate", f, "--listen", ep(port), "--duration", "5", "--wait-subscribers", "20",
                "--json")
    emu.wait_line(EMULATE_MARK)
    got = Collector()
    with zenoh.open(session_config(connect=[ep(port)])) as session:
        sub = session.declare_subscriber("noiselab/unstable/**", got)
        assert emu.finish() == 0, emu.stderr_text()
        got.wait_for(lambda: got.count("noiselab/unstable/end") == 1, "the end of stream")
        sub.undeclare()
    summary = emu.json()
    k = summary["diverged_at"]
    assert k is not None and summary["samples"] == k and 0 < k < 500, summary
    end = wire.decode_end(got.by_key["noiselab/unstable/end"][0][0])
    assert end["counts"]["measurement"] == end["counts"]["truth"] == k and end["reason"] == "stopped"
    got.wait_for(lambda: got.count("noiselab/unstable/measurement") == got.count("noiselab/unstable/truth") == k,
                 f"{k} measurements and states")
    ys = np.array([wire.decode(p)["y"][0] for p, _ in got.by_key["noiselab/unstable/measurement"]])
    xs = np.array([wire.decode(p)["x"][0] for p, _ in got.by_key["noiselab/unstable/truth"]])
    # the state grows e^20 per sample: the last one published is within a factor e^20 of the bound
    assert np.abs(np.r_[ys, xs]).max() <= wire.MAGNITUDE_MAX and abs(xs[-1]) > wire.MAGNITUDE_MAX * np.exp(-21)
    said = [ln for ln in emu.err if "the plant has diverged" in ln]
    assert len(said) == 1 and f"sample {k} has " in said[0] and "beyond 1e+50" in said[0], emu.stderr_text()
    assert not any("Warning" in ln or "Traceback" in ln for ln in emu.err), emu.stderr_text()


def test_analyze_of_a_recording_nested_deep_is_one_line_exit_2(tmp_path):
    """`noiselab analyze` of a file whose y at one seq is nested 100,000 deep: one line naming the
    topic and the bound, exit 2 (the decoder checks the nesting before it parses)."""
    model = load_model("seed")
    n = 1000
    sim = model.simulate(n, seed=1)
    path = tmp_path / "deep.mcap"
    with RecordingWriter(path) as w:
        for k in range(n):
            pub = wire.publish_time_ns(k, wire.period_ns(model.Ts))
            for kind, values in (("command", sim.u), ("measurement", sim.y)):
                payload = sample(kind, k, values[k])
                if kind == "measurement" and k == 500:
                    payload = b'{"seq":500,"t":5.0,"y":' + deep(100_000) + b"}"
                w.write(wire.key("seed", kind), kind, k, pub, pub, payload)
    r = cli("analyze", path, "--model", "seed", "--json")
    assert r.returncode == 2, r.stderr
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("noiselab: "), r.stderr
    assert "noiselab/seed/measurement" in lines[0] and f"deeper than {wire.MAX_DEPTH}" in lines[0], lines[0]
    assert r.stdout == ""


# ------------------------------------------------------------------------------- the fuzz test

FUZZ_SEED = 41
FAR = 10**9               # a valid-looking seq this far ahead of its stream's is a forged one
MARK = 2.0**-10           # every element of a forged valid-looking vector: no quantized (step 0.001) measurement
HOSTILE_KINDS = ("control", "measurement", "command", "truth", "health", "end")
# Valid-looking forged messages: they hold to the contract and the stream's length, and only
# their seq does not continue the stream. The past seqs are below those every stream has reached
# before the first burst (measurement 20, control 10) and two apart, so no two forged ones of a
# topic are consecutive (a forged consecutive pair is what no rule on seqs can tell from a
# restart: SeqGate's docstring).
VALID_LOOKING = {"far ahead": None, "seq 0 mid-stream": 0, "past seq": 5, "duplicate seq, other data": 8}
BEFORE_START = "wrong length before the stream starts"


def hostile_messages(rng: random.Random, kind: str, dim: int) -> list[tuple[str, bytes]]:
    """Malformed and hostile payloads for topic ``kind`` (vector length ``dim`` where it has one),
    each tagged with what makes it bad; every one breaks the wire contract or the stream's vector
    length, or (:data:`VALID_LOOKING`, the data topics and control) holds to both with a seq that
    does not continue the stream (far ahead, 0 mid-stream, past, recorded already with other
    data), so a recorder must skip each. Generated from ``rng``: the list is the same for a seed."""
    field = wire.VECTOR_FIELD.get(kind)
    if kind == "health":
        base = {"seq": 0, "t": 0.5, **{name: rng.choice([0, 1, 12.5]) for name in wire.HEALTH_FIELDS}}
        slot = "lateness_p50_us"
    elif kind == "end":
        base = {"seq": 0, "t": 0.5, "samples": 50, "counts": {"measurement": 50}, "reason": "stopped"}
        slot = "samples"
    else:
        base = {"seq": 0, "t": 0.5, field: [round(rng.uniform(-1, 1), 6) for _ in range(dim)]}
        slot = field

    def with_(**changes) -> bytes:
        obj = {**base, **changes}
        return json.dumps({k: v for k, v in obj.items() if v is not ...}, separators=(",", ":")).encode()

    good = with_()
    out = [("truncated", good[:rng.randrange(1, len(good))]) for _ in range(2)]
    out += [("wrong type", with_(seq=v)) for v in rng.sample(["1", 1.5, True, None, [1], {}], 2)]
    out += [("wrong type", with_(t=v)) for v in rng.sample(["0.1", True, None, [0.1]], 2)]
    out += [("wrong type", with_(**{slot: v})) for v in rng.sample(["0.1", {"a": 1}, ["0.1"], [True], [None], [[0.1]]], 2)]
    out += [("missing key", with_(t=...))]
    out += [("NaN literal", good.replace(b'"t":0.5', b'"t":' + rng.choice([b"NaN", b"Infinity", b"-Infinity"])))]
    out += [("huge number", good.replace(b'"t":0.5', b'"t":1e400')),
            ("huge number", good.replace(b'"t":0.5', b'"t":1' + b"0" * 400)),
            ("huge number", good.replace(b'"t":0.5', b'"t":1' + b"0" * 5000))]
    out += [("huge string", with_(note="x" * (2 << 20))), ("huge string", with_(**{slot: "y" * 100_000}))]
    out += [("deep nesting", deep()), ("deep nesting", b'{"":' * DEEP + b"1" + b"}" * DEEP),
            ("deep nesting", with_(**{slot: "DEEP"}).replace(b'"DEEP"', deep(50_000)))]
    out += [("seq out of range", with_(seq=v)) for v in (-1, -10**20, 10**26, 2**63)]
    out += [("unknown key", with_(z=1)), ("not an object", rng.choice([b"[1,2]", b'"sample"', b"null", b"42"])),
            ("binary garbage", bytes(rng.randrange(256) for _ in range(rng.randrange(1, 300)))),
            ("binary garbage", b"\xff\xfe" + good), ("empty", b"")]
    if field is not None:
        out += [("wrong length", with_(**{field: v})) for v in ([], [0.1] * (dim + 1), [0.25] * 1000)]
        out += [("wrong length", b'{"seq":0,"t":0.5,"' + field.encode() + b'":[' + b",".join([b"0.1"] * 10**6) + b"]}")]
        forged = [MARK] * dim
        out += [("far ahead", with_(seq=FAR + 1000 * i + rng.randrange(1000), t=float(FAR), **{field: forged}))
                for i in range(2)]
        out += [(why, with_(seq=seq, t=wire.sample_time(seq, 0.01), **{field: forged}))
                for why, seq in VALID_LOOKING.items() if seq is not None]
    if kind == "control":
        out += [("beyond magnitude", with_(u=[v])) for v in (1e60, rng.choice([1e308, -1e150, -1e51]))]
    if kind == "health":               # a health stream's first report may still wait for its second: nothing near
        out += [("far ahead", with_(seq=FAR + 1000 * i + rng.randrange(1000), t=float(FAR))) for i in range(2)]
    if kind == "end":                  # well formed, but it counts fewer messages than the recorder holds
        out += [("end counting too few", wire.encode_end(0, 0.04, 5, {k: 5 for k in wire.KINDS}, "stopped"))]
    for why, payload in out:           # the generator's own check: each one is bad, as tagged
        assert why in VALID_LOOKING or why == "end counting too few" or not_a_sample(kind, payload, dim), \
            (why, payload[:80])
    rng.shuffle(out)
    return out


def before_start(dims: dict) -> list[tuple[str, bytes]]:
    """A vector of the wrong length with seq 0 on each vector topic, for before the stream starts
    (the recorder is listening, no source yet): the first message a recorder hears of a topic."""
    return [(kind, sample(kind, 0, [MARK] * (dims[kind] + 1))) for kind in ("control", "measurement", "command", "truth")]


def not_a_sample(kind: str, payload: bytes, dim: int) -> bool:
    """``payload`` breaks the wire contract of ``kind``, or (a vector kind) has not ``dim`` elements."""
    decoders = {"health": wire.decode_health, "end": wire.decode_end}
    try:
        obj = decoders[kind](payload) if kind in decoders else wire.decode(payload, kind)
    except wire.WireError:
        return True
    return kind in wire.VECTOR_FIELD and len(obj[wire.VECTOR_FIELD[kind]]) != dim


class GenuineStream(Collector):
    """A Collector of the genuine streams only (the hostile messages published alongside are
    left out: those that break the contract or the vector length, and the forged ones, far
    ahead or all MARK)."""

    def __init__(self, dims: dict):
        super().__init__()
        self.dims = dims

    def __call__(self, sample) -> None:
        kind = str(sample.key_expr).rsplit("/", 1)[1]
        payload = sample.payload.to_bytes()
        try:
            obj = wire.decode_health(payload) if kind == "health" else wire.decode(payload, kind)
        except wire.WireError:
            return
        vec = obj.get(wire.VECTOR_FIELD.get(kind))
        if obj["seq"] < FAR and (kind == "health" or (len(vec) == self.dims[kind] and vec != [MARK] * len(vec))):
            super().__call__(sample)


def client_config(port: int) -> zenoh.Config:
    conf = session_config(connect=[ep(port)])
    conf.insert_json5("mode", '"client"')
    return conf


BAD_ACKS = [b"[1]", b'"ok"', b'{"topics":{"measurement":5}}']


def test_fuzz_hostile_messages_into_a_live_closed_loop(spawn, tmp_path):
    """A closed loop on a router (emulator with an external command, a P controller, a recorder,
    a live analyzer, all separate processes) while a session here publishes, in three bursts as
    the stream goes on, malformed and hostile messages generated with a fixed seed (truncated
    JSON, wrong types, NaN literals, huge numbers and strings, deep nesting, wrong lengths,
    seqs out of range, unknown keys, binary garbage, empty payloads, controls beyond the bound
    (1e60 among them), and valid-looking messages: far ahead, seq 0 mid-stream, a past seq, a
    recorded seq with other data, an end of stream counting too few) onto the control,
    measurement, command, truth, health and end topics. Before the stream starts it publishes a
    vector of the wrong length on each vector topic, and it answers the recorder's join query
    (points far past any stream, one beyond int64) and the emulator's end-of-stream query
    (answers that are not a recorder's).

    Each node keeps running and ends cleanly (exit 0, no traceback); the recording holds every
    message of the emulator and of the controller with no gap and nothing else on those topics,
    and is analysable; the recorder counts exactly the messages it was sent, per topic; the live
    analyzer exactly those on its two topics; the emulator exactly the controls it had to reject
    and the answers to its end of stream that are not a recorder's. The bursts wait on the
    stream's progress, the counts on the nodes' own answers: no sleep."""
    rng = random.Random(FUZZ_SEED)
    f = tmp_path / "loop.toml"
    f.write_text(LOOP_TOML)
    model = load_model(f)
    dims = {"control": model.m, "measurement": model.p, "command": model.m, "truth": model.n_x,
            "health": 0, "end": 0}
    sent = {kind: hostile_messages(rng, kind, dims[kind]) for kind in HOSTILE_KINDS}
    early = before_start(dims)
    bursts = [[], [], []]
    for kind, msgs in sent.items():
        for i, (_, payload) in enumerate(msgs):
            bursts[i % 3].append((kind, payload))
    for b in bursts:
        rng.shuffle(b)
    per_topic = {wire.key("loop", kind): len(msgs) for kind, msgs in sent.items()}
    for kind, _ in early:
        per_topic[wire.key("loop", kind)] += 1
    to_analyzer = len(sent["measurement"]) + len(sent["command"]) + 2
    rejected_controls = sum(why not in VALID_LOOKING for why, _ in sent["control"])
    assert sum(per_topic.values()) > 200 and {why for msgs in sent.values() for why, _ in msgs} >= {
        "truncated", "wrong type", "NaN literal", "huge number", "huge string", "deep nesting", "wrong length",
        "seq out of range", "unknown key", "binary garbage", "empty", "beyond magnitude", "end counting too few",
        *VALID_LOOKING}
    joins = {"noiselab/loop/measurement": 10**30, "noiselab/loop/truth": 2**62, "noiselab/loop/command": 10**6,
             "noiselab/loop/control": 10**5, "noiselab/loop/health": 2**40}

    port = free_port()
    router = spawn("router", "router", "--listen", ep(port), "--duration", "120")
    router.wait_line(ROUTER_MARK)
    client = ["--mode", "client", "--connect", ep(port)]
    out = tmp_path / "fuzzed.mcap"
    watch = GenuineStream(dims)
    summaries = Collector()
    meas, ctrl, health = (wire.key("loop", k) for k in ("measurement", "control", "health"))
    with zenoh.open(client_config(port)) as observer, zenoh.open(client_config(port)) as attacker:
        # the attacker answers the join query of the recorder (before any source serves one) and
        # the emulator's end-of-stream query
        forged_join = transport.serve_join(attacker, "loop", lambda: joins)
        bad_acks = attacker.declare_queryable(wire.key("loop", wire.END),
                                              lambda q: [q.reply(q.key_expr, a) for a in BAD_ACKS])
        ctl = spawn("p_controller", CONTROLLER, "--name", "loop", "--kp", "8", "--r", "0.3", *client,
                    "--duration", "120", script=True)
        rec = spawn("record", "record", *client, "--out", out, "--json")
        an = spawn("analyze", "analyze", "--live", "--model", f, "--device", "loop", *client,
                   "--window", "30", "--update", "0.5", "--json")
        ctl.wait_line("p_controller: ready")
        rec.wait_line(READY_MARK)
        an.wait_line(ANALYZER_READY)
        pubs = {kind: attacker.declare_publisher(wire.key("loop", kind), **transport.DATA_QOS) for kind in HOSTILE_KINDS}
        assert transport.wait_matching([pubs[k] for k in ("measurement", "command")], T_EVENT, every=True)

        def recorder_has_taken_all() -> None:
            """The recorder answers a query only once it has taken everything that came before it on
            the same link (here: an end-of-stream query of no source)."""
            replies = list(attacker.get("noiselab/fuzz/end", target=zenoh.QueryTarget.ALL,
                                        consolidation=zenoh.ConsolidationMode.NONE, timeout=T_EVENT,
                                        priority=zenoh.Priority.DATA, **transport.DATA_QOS))
            assert [json.loads(r.ok.payload.to_bytes())["out"] for r in replies if r.ok is not None] == [str(out)], \
                replies

        for kind, payload in early:
            pubs[kind].put(payload)
        recorder_has_taken_all()
        # the emulator runs until stopped (SIGINT ends its stream cleanly): the test goes at the
        # stream's pace, whatever the machine's speed
        emu = spawn("emulate", "emulate", f, *client, "--duration", "600", "--seed", "9",
                    "--wait-subscribers", "20", "--json")
        subs = [observer.declare_subscriber(k, watch) for k in (meas, ctrl, health)]
        subs.append(observer.declare_subscriber(wire.key("loop", wire.ANALYSIS), summaries))
        # every stream has begun at the recorder and the analyzer before the first hostile message
        # (their link from the router carries the stream's first messages before this burst)
        watch.wait_for(lambda: watch.last_seq(meas) >= 20 and watch.last_seq(ctrl) >= 10 and watch.count(health) >= 1,
                       "measurement seq 20, control seq 10 and a health report")
        for burst in bursts:
            k = watch.last_seq(meas)
            for kind, payload in burst:
                pubs[kind].put(payload)
            watch.wait_for(lambda: watch.last_seq(meas) >= k + 50, f"measurement seq {k + 50}")
        recorder_has_taken_all()
        # a second summary too: the recorder takes a stream's first message once its successor came
        summaries.wait_for(lambda: any(json.loads(p)["malformed"] == to_analyzer and json.loads(p)["seq"] >= 1
                                       for p, _ in summaries.by_key[wire.key("loop", wire.ANALYSIS)]),
                           f"a second analysis summary, counting {to_analyzer} malformed", timeout=T_EVENT)
        assert emu.interrupt() == 0, emu.stderr_text()
        for s in subs:
            s.undeclare()
        bad_acks.undeclare()
        forged_join.undeclare()
    rec.wait_line("noiselab record: noiselab/loop ended")
    for child in (rec, an, ctl, router):
        assert child.interrupt() == 0, child.stderr_text()
    for child in (emu, rec, an, ctl):
        assert not any("Traceback" in ln for ln in child.err), child.stderr_text()

    # the emulator: ran in closed loop, rejected exactly the bad controls, its end acknowledged by
    # the recorder alone
    es = emu.json()
    n = es["samples"]
    assert waited_for_subscribers(emu) and n > 150 and es["diverged_at"] is None
    assert es["rejected_controls"] == rejected_controls, (es["rejected_controls"], rejected_controls)
    assert sum("rejected a control" in ln for ln in emu.err) == 1, emu.stderr_text()
    assert len(es["end"]["acks"]) == 1 and es["end"]["acks"][0]["complete"], es["end"]
    assert es["end"]["errors"] == ["an acknowledgement that is not a recorder's answer"] * len(BAD_ACKS), es["end"]
    # the recorder: every message of the emulator and the controller, no gap, and the counts right
    rs = rec.json()
    check_summary_topics(rs["topics"], "loop", n)
    c = rs["topics"][ctrl]
    assert (c["first_seq"], c["gaps"], c["restarts"]) == (0, [], []) and c["count"] == c["last_seq"] + 1, c
    assert rs["malformed"] == sum(per_topic.values()) and rs["malformed_topics"] == per_topic, \
        f"recorder counted {rs['malformed_topics']}, sent {per_topic}"
    assert rs["unended"] == {}
    assert sum("not waited for" in ln for ln in rec.err) == len(joins) - 1, rec.stderr_text()
    dev = read_recording(out).device("loop")
    for kind in ("truth", "command", "measurement"):
        assert np.array_equal(dev.streams[kind].seq, np.arange(n)) and dev.streams[kind].segments == [(0, n)], kind
    assert not (dev.measurement.values == MARK).any()
    controls = [wire.decode(m.data, "control") for _, _, m in file_messages(out)[ctrl]]
    assert [u["seq"] for u in controls] == list(range(c["count"]))
    # the live analyzer: counted each hostile message on its topics once, analysed the stream
    fa = an.json()
    assert fa["malformed"] == to_analyzer and fa["updates"] > 0, fa
    # the recording is analysable offline
    r = cli("analyze", out, "--model", f, "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["samples"] > 0


def test_emulator_survives_hostile_answers_to_its_end_of_stream(spawn):
    """A peer answers the emulator's end-of-stream query (as a recorder would) with JSON nested
    200,000 deep, JSON that is not a recorder's answer ([1], "ok", topics without their fields)
    and a recorder-shaped answer whose file name holds a newline. The emulator takes only the
    last as an acknowledgement, counts the others as errors of its end of stream and says each
    kind once, with its count; every line is one line; it exits 0 (the deep answer is beyond the
    depth the parser can recurse to, the others lack the fields the emulator reads)."""
    port = free_port()
    answered = threading.Event()
    shaped = {"node": "record", "out": "x\ny.mcap", "complete": False, "topics": {"measurement": {"missing": 3}}}
    answers = [deep(), b"[1]", b'"ok"', b'{"topics":{"measurement":5}}', json.dumps(shaped).encode()]

    def answer(query) -> None:
        for payload in answers:
            query.reply(query.key_expr, payload)
        answered.set()

    with zenoh.open(session_config(listen=[ep(port)])) as session:
        queryable = session.declare_queryable("noiselab/seed/end", answer)
        emu = spawn("emulate", "emulate", "seed", "--connect", ep(port), "--duration", "0.2", "--json")
        assert emu.finish() == 0, emu.stderr_text()
        queryable.undeclare()
    assert answered.is_set(), "the emulator did not query its end of stream"
    end = emu.json()["end"]
    assert end["acks"] == [shaped], end
    assert sorted(end["errors"]) == ["an acknowledgement that is not JSON"] + 3 * ["an acknowledgement that is not a "
                                                                                    "recorder's answer"], end
    said = [ln for ln in emu.err if "end of stream" in ln or "lacks" in ln]
    assert sorted(said) == sorted(["noiselab emulate: seed: end of stream: an acknowledgement that is not JSON",
                                   "noiselab emulate: seed: end of stream: an acknowledgement that is not a "
                                   "recorder's answer (3 answers)",
                                   "noiselab emulate: seed: recorder x\\ny.mcap lacks 3 measurement"]), emu.stderr_text()
    assert not any("Traceback" in ln for ln in emu.err), emu.stderr_text()


def test_replay_of_a_file_with_a_deep_payload_republishes_it(tmp_path):
    """`noiselab replay` looks at the first payload of each stream (is its seq the MCAP
    sequence?) with the bounded parser: a crafted file whose first payload is nested 100,000
    deep is republished as it is, that payload included (a replay does not judge payloads: the
    sinks do), and replay exits 0."""
    path = tmp_path / "deep-first.mcap"
    with RecordingWriter(path) as w:
        w.write("noiselab/d/measurement", "measurement", 0, 0, 0, b'{"seq":0,"t":0.0,"y":' + deep(100_000) + b"}")
        for k in range(1, 5):
            w.write("noiselab/d/measurement", "measurement", k, k * 10**7, k * 10**7, sample("measurement", k, [0.5]))
    r = cli("replay", path, "--fast", "--listen", ep(free_port()), "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["messages"] == 5 and "Traceback" not in r.stderr
