"""The live pipeline's checks: Zenoh sessions on loopback (multicast scouting off), a subscriber
that collects what it receives, and what a finished recording of an emulator must hold, checked
against the step API (``model.stepper``, exactly the emulator's path: payload bytes equal
``wire.encode`` of its values) and the batch API (``model.simulate``)."""

from __future__ import annotations

import json
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import zenoh
from helpers.processes import Child

from noiselab import wire
from noiselab.recordings.errors import NotMcapError
from noiselab.recordings.reader import read_recording
from noiselab.recordings.scan import iter_messages

ROOT = Path(__file__).resolve().parents[2]
SEED_TOML = (ROOT / "service" / "scenarios" / "seed.toml").read_text()
CONTROLLER = ROOT / "tests" / "live_helpers" / "p_controller.py"
EMULATE_MARK = "noiselab emulate: "       # printed once the emulator's session is open
ROUTER_MARK = "noiselab router: listening"
DATA_KINDS = wire.KINDS                   # truth, command, measurement

# One bound for "a child reaches its next event"; generous because the machine is shared
# (2 cores, benchmarks may run alongside). A test never passes on a timeout.
T_EVENT = 30.0


def model_text(name: str, Ts: float) -> str:
    """seed.toml with another name and sample period (everything else unchanged)."""
    text = SEED_TOML.replace('name = "seed"', f'name = "{name}"', 1)
    text = text.replace("Ts = 0.01 ", f"Ts = {Ts!r} ", 1)
    assert f'name = "{name}"' in text and f"Ts = {Ts!r} " in text
    return text


def waited_for_subscribers(child: Child) -> bool:
    """The child's --wait-subscribers ended with a match (it did not start without one)."""
    return not any("no subscriber matched" in ln for ln in child.err)


def ep(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def session_config(connect: list[str] = (), listen: list[str] = ()) -> zenoh.Config:
    """A peer on loopback, multicast scouting off; connect retries quickly until the peer listens."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("connect/retry", json.dumps({"period_init_ms": 50, "period_max_ms": 200,
                                                   "period_increase_factor": 1.5}))
    return conf


class Collector:
    """Subscriber callback: every sample's (payload bytes, monotonic arrival s), per key."""

    def __init__(self):
        self.cond = threading.Condition()
        self.by_key: dict[str, list[tuple[bytes, float]]] = defaultdict(list)

    def __call__(self, sample) -> None:
        item = (sample.payload.to_bytes(), time.monotonic())
        with self.cond:
            self.by_key[str(sample.key_expr)].append(item)
            self.cond.notify_all()

    def wait_for(self, predicate, what: str, timeout: float = T_EVENT) -> None:
        with self.cond:
            ok = self.cond.wait_for(predicate, timeout)
            counts = {k: len(v) for k, v in self.by_key.items()}
        assert ok, f"timeout ({timeout} s) waiting for {what}; received {counts}"

    def count(self, key: str) -> int:
        return len(self.by_key.get(key, ()))

    def last_seq(self, key: str) -> int:
        """Seq of the latest sample of ``key`` (-1 if none); call with ``cond`` held or not."""
        items = self.by_key.get(key)
        return -1 if not items else json.loads(items[-1][0])["seq"]


def poll_until(predicate, what: str, timeout: float = T_EVENT, every: float = 0.05) -> None:
    """Wait for a condition this process cannot be told of (a file another process writes): checked
    every ``every`` s until it holds; fails after ``timeout``, never passes on it."""
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"timeout ({timeout} s) waiting for {what}"
        time.sleep(every)


def on_disk(path, name: str) -> dict[str, int]:
    """Per data kind, the last seq of device ``name`` that a recording being written already holds
    intact on disk (-1: none yet, nor before the file has its header)."""
    try:
        dev = read_recording(path).devices.get(name)
    except (FileNotFoundError, NotMcapError):
        dev = None
    return {kind: int(dev.streams[kind].seq[-1]) if dev is not None and kind in dev.streams
            and len(dev.streams[kind]) else -1 for kind in DATA_KINDS}


def step_path(model, seed: int, n: int, commands=None) -> dict[str, np.ndarray]:
    """The step API's sample path (exactly the emulator's): t, x, u, y arrays of n samples."""
    st = model.stepper(seed=seed)
    xs, us, ys = [], [], []
    for k in range(n):
        _, x, u, y = st.step(None if commands is None else commands[k])
        xs.append(np.array(x))
        us.append(np.array(u))
        ys.append(np.array(y))
    return {"truth": np.array(xs), "command": np.array(us), "measurement": np.array(ys)}


def expected_payloads(model, path: dict[str, np.ndarray], kind: str, n: int) -> list[bytes]:
    return [wire.encode(k, wire.sample_time(k, model.Ts), path[kind][k], kind=kind) for k in range(n)]


def file_messages(path) -> dict[str, list]:
    """(schema, channel, message) per topic, in file order, from the MCAP file itself."""
    out: dict[str, list] = defaultdict(list)
    for schema, channel, message in iter_messages(path):
        out[channel.topic].append((schema, channel, message))
    return dict(out)


def recorded_start(path, name: str) -> int:
    """The wall-clock start of device ``name``'s stream in a recording: the file's start_time_ns
    (metadata record ``noiselab``), which the recorder took from the source (``stated``)."""
    meta = read_recording(path).metadata
    start = int(meta["noiselab"]["start_time_ns"])
    assert json.loads(meta["noiselab.recorder"]["starts"]) == {
        f"noiselab/{name}": {"start_time_ns": start, "stated": True}}
    return start


def check_recording(path, model, seed: int, n: int, *, batch: bool = True, start_time_ns: int | None = None) -> None:
    """A finished recording holds exactly samples 0..n-1 per data topic, on the wire contract,
    with the step API's payload bytes (and the batch API's values when ``batch``); its publish
    times are the source's start (``start_time_ns``, the emulator's summary, when given) + k Ts,
    on the wall clock of its receive times."""
    name = model.name
    start = recorded_start(path, name)
    if start_time_ns is not None:
        assert start == start_time_ns
    msgs = file_messages(path)
    steps = step_path(model, seed, n)
    for kind in DATA_KINDS:
        topic = wire.key(name, kind)
        got = msgs.get(topic, [])
        assert len(got) == n, f"{topic}: {len(got)} messages, expected {n}"
        schema, channel, _ = got[0]
        assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
        assert schema.name == wire.SCHEMA_NAMES[kind]
        seqs = [json.loads(m.data)["seq"] for _, _, m in got]
        assert seqs == list(range(n)), f"{topic}: not 0..{n - 1} in order"
        assert [m.sequence for _, _, m in got] == seqs
        assert [m.publish_time for _, _, m in got] == [start + round(k * model.Ts * 1e9) for k in range(n)]
        # one time base: every sample is received after it was due (it is put at its deadline or later)
        early = [m.sequence for _, _, m in got if m.log_time < m.publish_time]
        assert not early, f"{topic}: received before due (wall clock), first at seq {early[0]}"
        want = expected_payloads(model, steps, kind, n)
        bad = [k for k, (_, _, m) in enumerate(got) if m.data != want[k]]
        assert not bad, f"{topic}: {len(bad)} payloads differ from the step API, first at seq {bad[0]}"
    rec = read_recording(path)
    assert rec.complete, rec.note
    dev = rec.device(name)
    for kind in DATA_KINDS:
        td = dev.streams[kind]
        assert td.gaps() == [] and td.seq[0] == 0 and len(td) == n
        assert np.array_equal(td.t, [wire.sample_time(k, model.Ts) for k in range(n)])
    assert np.array_equal(dev.truth.values, steps["truth"]), "truth differs from the step API"
    if batch:
        sim = model.simulate(n, seed=seed)
        assert np.array_equal(dev.measurement.values, sim.y), "measurement differs from simulate"
        assert np.array_equal(dev.command.values, sim.u), "command differs from simulate"
        scale = np.abs(sim.x).max(axis=0)
        rel = np.abs(dev.truth.values - sim.x).max(axis=0) / scale     # ~3e-13 at 5000 samples
        assert (rel <= 1e-12).all(), f"truth vs simulate: max error / max |x| per state = {rel}"


def check_summary_topics(topics: dict, name: str, n: int) -> None:
    """A recorder --json summary: every data topic 0..n-1, no gaps, no restarts, and the source's
    end of stream says it published exactly n."""
    for kind in DATA_KINDS:
        b = topics[wire.key(name, kind)]
        assert (b["first_seq"], b["last_seq"], b["count"]) == (0, n - 1, n), (kind, b)
        assert b["missing_at_start"] == 0 and b["gaps"] == [] and b["missing"] == 0 and b["restarts"] == []
        assert (b["expected"], b["missing_at_end"]) == (n, 0), (kind, b)
    assert topics[wire.key(name, "end")]["count"] == 1


def check_end_acknowledged(emu_summary: dict, name: str, n: int, recorders: int = 1) -> None:
    """The emulator's --json summary: its end of stream was acknowledged by ``recorders``
    recorders holding every message."""
    end = emu_summary["end"]
    assert end["timed_out"] is False and end["errors"] == [], end
    assert len(end["acks"]) == recorders, end
    for ack in end["acks"]:
        assert ack["prefix"] == f"noiselab/{name}" and ack["ended"] and ack["complete"], ack
        for kind in DATA_KINDS:
            assert ack["topics"][kind] == {"count": n, "last_seq": n - 1, "expected": n, "missing": 0}, ack
