"""The conventions of the tools users open noiselab's streams and files with: a live stream's
wall-clock time base (the source states its start in every sample's attachment; the recorder
writes publish_time = start + k Ts beside its wall-clock log_time, and start_time_ns in the file's
metadata) and the Zenoh encoding of every put (``application/json;<schema name>``).

Real Zenoh sessions on 127.0.0.1 (multicast scouting off), real MCAP files read back. Waits are
on events (a subscriber's condition, the emulator's match with the subscriber), never on time.
"""

from __future__ import annotations

import json
import io
import threading
import time
from collections import defaultdict

import pytest
import zenoh
from mcap.records import Message, Metadata
from mcap.stream_reader import StreamReader

from noiselab.model import parse_model
from noiselab.nodes import emulator
from noiselab import wire
from noiselab.recordings.writer import RecordingWriter
from noiselab.nodes.recorder import Ingest
from noiselab.nodes.runner import free_port

T_EVENT = 30.0
TOML = """
name = "tb"
[sampling]
Ts = 0.003
[plant]
m = 1.2
c = 0.35
k = 4.0
[command]
kind = "sine"
amplitude = 0.8
frequency_hz = 0.7
[sensor.white]
std = 0.01
"""


def session(listen=(), connect=()) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("connect/retry", json.dumps({"period_init_ms": 50, "period_max_ms": 200,
                                                   "period_increase_factor": 1.5}))
    return zenoh.open(conf)


def test_emulator_puts_say_json_with_the_schema_and_state_the_wall_clock_start():
    """What a generic Zenoh subscriber sees of a live emulator: every data and health sample has
    encoding application/json;<its schema name> and the attachment {"start_time_ns": N}, N the
    wall clock when sample 0 was due (between the run's start and its end, as the emulator's
    summary says)."""
    model = parse_model(TOML)
    n = 400                                           # 1.2 s: one health report
    ep = f"tcp/127.0.0.1:{free_port()}"
    got: dict[str, list] = defaultdict(list)
    cond = threading.Condition()

    def on_sample(s) -> None:
        att = s.attachment
        with cond:
            got[str(s.key_expr)].append((str(s.encoding), None if att is None else att.to_bytes()))
            cond.notify_all()

    with session(listen=[ep]) as src, session(connect=[ep]) as sink:
        sub = sink.declare_subscriber("noiselab/tb/**", on_sample)
        before = time.time_ns()
        summary = emulator.run_emulator(model, src, duration=n * model.Ts, wait_subscribers=T_EVENT,
                                        end_timeout=0, log=io.StringIO())
        after = time.time_ns()
        with cond:
            assert cond.wait_for(lambda: len(got["noiselab/tb/measurement"]) == n
                                 and got["noiselab/tb/end"], T_EVENT), {k: len(v) for k, v in got.items()}
        sub.undeclare()
    assert summary.samples == n and before <= summary.start_time_ns <= after
    anchor = wire.encode_anchor(summary.start_time_ns)
    for kind in (*wire.KINDS, wire.HEALTH, wire.END):
        samples = got[wire.key("tb", kind)]
        assert samples or kind == wire.HEALTH, kind   # health is sent with DROP: it may be dropped
        assert {enc for enc, _ in samples} == {f"application/json;{wire.SCHEMA_NAMES[kind]}"}, kind
        if kind != wire.END:                          # the end is anchored by its source's data
            assert {att for _, att in samples} == {anchor}, kind


def test_recorder_anchors_publish_time_at_the_stated_start_and_records_it_first(tmp_path):
    """Ingest (the recorder's work on what it received), fed what a source sends: its samples'
    publish_time is the stated start + round(t 1e9), the same whether the batch is written as a
    run or message by message; the file's noiselab metadata record, with start_time_ns, comes
    before the first message (so a recorder killed after its first flush leaves it for recover);
    a second source that states nothing is anchored at its first arrival; an attachment that is
    not an anchor is counted and ignored, the sample with it recorded."""
    start = 1_760_000_000_123_456_789
    Ts = 0.003
    meas = wire.encode_batch("measurement", 0, [k * Ts for k in range(40)], [[0.5]] * 40)
    other = [wire.encode(k, 5.0 + k * 0.01, [1.0], kind="measurement") for k in range(3)]
    files = []
    for mode in ("run", "one by one"):
        path = tmp_path / f"{mode}.mcap"
        with RecordingWriter(path) as w:
            ing = Ingest(w, str(path), log=io.StringIO(), metadata={"generator": "test"})
            ing.state("noiselab/a/measurement", wire.encode_anchor(start))
            ing.state("noiselab/b/measurement", b'{"start_time_ns":-5}')      # not an anchor
            items = [("noiselab/a/measurement", p) for p in meas] + [("noiselab/b/measurement", p) for p in other]
            if mode == "run":
                ing.add(items, 2_000_000_000_000_000_000)
            else:
                for item in items:
                    ing.add([item], 2_000_000_000_000_000_000)
            ing.finish()
        assert ing.bad_anchors == 1 and ing.messages == 43
        assert ing.starts_dict() == {
            "noiselab/a": {"start_time_ns": start, "stated": True},
            # first arrival at 2e18 ns of a sample of t = 5 s
            "noiselab/b": {"start_time_ns": 2_000_000_000_000_000_000 - 5_000_000_000, "stated": False}}
        with open(path, "rb") as f:
            records = [r for r in StreamReader(f).records if isinstance(r, (Message, Metadata))]
        assert isinstance(records[0], Metadata) and records[0].name == "noiselab"
        assert records[0].metadata == {"generator": "test", "start_time_ns": str(start)}
        msgs = [r for r in records if isinstance(r, Message)]
        files.append([(m.channel_id, m.publish_time, m.log_time, m.data) for m in msgs])
        pub = [m.publish_time for m in msgs]
        assert pub[:40] == [start + round(k * Ts * 1e9) for k in range(40)]
        assert pub[40:] == [2_000_000_000_000_000_000 + k * 10_000_000 for k in range(3)]
    assert files[0] == files[1]


@pytest.mark.parametrize("attachment", [b"", b"not json", b'{"start_time_ns":1.5}', b'{"start_time_ns":1,"x":2}',
                                        b'{"start_time_ns":4611686018427387905}', b"[" * 100])
def test_a_bad_attachment_is_a_wire_error(attachment):
    with pytest.raises(wire.WireError, match="attachment"):
        wire.decode_anchor(attachment, topic="noiselab/x/measurement")
