"""The live pipeline end to end (issue 3, "What it must show"): real processes, real Zenoh
sessions on 127.0.0.1 with multicast scouting off, real MCAP files read back.

Synchronisation is by events only: a child's stderr line ("noiselab record: subscribed",
"noiselab emulate: ...", "noiselab router: listening", "p_controller: ready"), a subscriber's
condition variable in this process, ``--wait-subscribers`` on the publishing side, process exit.
Every timeout is an upper bound that fails the test. Every child is killed in the fixture
teardown. Ports come from ``runner.free_port()``; only the default-endpoint test uses 7447.

What the numbers are checked against:
- the step API (``model.stepper(seed=S)``), which is exactly the emulator's path: payload bytes
  equal ``wire.encode`` of its values, bit for bit, for truth, command and measurement;
- the batch API (``model.simulate(N, seed=S)``): measurement and command bit for bit, truth to
  1e-12 relative (the batch path runs the plant in complex Schur coordinates).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import psutil
import pytest
import zenoh

from helpers.live import (CONTROLLER, DATA_KINDS, EMULATE_MARK, ROOT, ROUTER_MARK, T_EVENT, Collector,
                          check_end_acknowledged, check_recording, check_summary_topics, ep, expected_payloads,
                          file_messages, model_text, on_disk, poll_until, session_config, step_path,
                          waited_for_subscribers)
from helpers.models import LOOP_TOML
from helpers.processes import Child
from noiselab.model import load_model
from noiselab.nodes import transport
from noiselab import wire
from noiselab.recordings.reader import read_recording
from noiselab.recordings.writer import RecordingWriter
from noiselab.nodes.recorder import Ingest
from noiselab.nodes.recorder_summary import TopicBook
from noiselab.nodes.runner import READY_MARK, free_port

pytestmark = pytest.mark.slow   # live end-to-end runs: real processes and sessions


# ----------------------------------------------------------------------- shared recordings

N_FAST = 5000            # 5 s at Ts = 1 ms
SEED_FAST = 7


@pytest.fixture(scope="module")
def fast_model_file(tmp_path_factory) -> Path:
    f = tmp_path_factory.mktemp("models") / "fast.toml"
    f.write_text(model_text("fast", 0.001))
    return f


@pytest.fixture(scope="module")
def fast_model(fast_model_file):
    m = load_model(fast_model_file)
    assert m.Ts == 0.001 and m.name == "fast"
    return m


@pytest.fixture(scope="module")
def separate_recording(fast_model_file, tmp_path_factory):
    """record (listening) + emulate (connecting, --wait-subscribers) as separate processes:
    5 s at Ts = 1 ms. Returns (path, recorder summary, emulator summary)."""
    out = tmp_path_factory.mktemp("separate") / "fast.mcap"
    port = free_port()
    children = []
    try:
        rec = Child([sys.executable, "-m", "noiselab.cli", "record", "--listen", ep(port), "--out", str(out),
                     "--json"], "record")
        children.append(rec)
        rec.wait_line(READY_MARK)
        emu = Child([sys.executable, "-m", "noiselab.cli", "emulate", str(fast_model_file), "--duration", "5",
                     "--seed", str(SEED_FAST), "--connect", ep(port), "--wait-subscribers", "10", "--json"],
                    "emulate")
        children.append(emu)
        assert emu.finish(60) == 0, emu.stderr_text()
        assert waited_for_subscribers(emu), emu.stderr_text()
        assert rec.interrupt() == 0, rec.stderr_text()
        return out, rec.json(), emu.json()
    finally:
        for c in children:
            c.kill()


# ------------------------------------------------------------- 1. end to end, replay


def test_run_records_5000_consecutive_messages_equal_to_the_batch_simulation(fast_model_file, fast_model,
                                                                               tmp_path):
    """`noiselab run` at Ts = 1 ms for 5 s: 5,000 consecutive messages per topic, payloads equal
    to simulate(5000, seed) and to the step API; its --json summary says so too."""
    r = subprocess.run([sys.executable, "-m", "noiselab.cli", "run", str(fast_model_file), "--duration", "5",
                        "--seed", str(SEED_FAST), "--out", str(tmp_path / "rec"), "--json"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout.strip().splitlines()[-1])
    assert rep["emulator"]["samples"] == N_FAST and rep["emulator"]["seed"] == SEED_FAST
    assert rep["emulator"]["Ts"] == 0.001
    check_summary_topics(rep["recorder"]["topics"], "fast", N_FAST)
    check_end_acknowledged(rep["emulator"], "fast", N_FAST)
    health = rep["recorder"]["topics"]["noiselab/fast/health"]
    assert (health["first_seq"], health["last_seq"], health["gaps"]) == (0, 4, [])
    assert rep["recorder"]["ended"] == {"noiselab/fast": {"truth": N_FAST, "command": N_FAST,
                                                          "measurement": N_FAST, "health": 5}}
    path = Path(rep["recording"])
    assert path.parent == tmp_path / "rec" and path.is_file()
    check_recording(path, fast_model, SEED_FAST, N_FAST, start_time_ns=rep["emulator"]["start_time_ns"])


def test_separate_record_and_emulate_processes(separate_recording, fast_model):
    """record --listen P, then emulate --connect P --wait-subscribers 10: the same guarantees."""
    path, rec_summary, emu_summary = separate_recording
    assert emu_summary["samples"] == N_FAST
    assert rec_summary["malformed"] == 0
    check_summary_topics(rec_summary["topics"], "fast", N_FAST)
    check_end_acknowledged(emu_summary, "fast", N_FAST)
    check_recording(path, fast_model, SEED_FAST, N_FAST, start_time_ns=emu_summary["start_time_ns"])
    meta = read_recording(path).metadata["noiselab.recorder"]
    assert json.loads(meta["topics"]) == rec_summary["topics"]


def test_replay_fast_delivers_every_message_in_order(separate_recording, spawn):
    """replay --fast --wait-subscribers: a subscriber here gets every message of the file, per
    topic seq 0..N-1 in order, payload bytes identical to the file's."""
    path, _, _ = separate_recording
    in_file = {topic: [m.data for _, _, m in items] for topic, items in file_messages(path).items()}
    total = sum(len(v) for v in in_file.values())
    assert total == 3 * N_FAST + 5 + 1                  # + 5 health messages, the end of stream
    port = free_port()
    rp = spawn("replay", "replay", path, "--listen", ep(port), "--fast", "--wait-subscribers", "20", "--json")
    got = Collector()
    with zenoh.open(session_config(connect=[ep(port)])) as session:
        sub = session.declare_subscriber("noiselab/**", got)
        assert rp.finish(60) == 0, rp.stderr_text()
        got.wait_for(lambda: sum(len(v) for v in got.by_key.values()) >= total, f"{total} replayed messages")
        sub.undeclare()
    assert waited_for_subscribers(rp), rp.stderr_text()
    summary = rp.json()
    assert summary["messages"] == total and summary["complete"] is True
    assert set(got.by_key) == set(in_file)
    for topic, payloads in in_file.items():
        received = [p for p, _ in got.by_key[topic]]
        seqs = [json.loads(p)["seq"] for p in received]
        assert seqs == list(range(len(payloads))), f"{topic}: not in order / not complete"
        assert received == payloads, f"{topic}: payload bytes differ from the file"


def test_replay_paced_and_prefixed(spawn, tmp_path):
    """replay --speed 10 of a recording spanning 39.96 s (1000 samples at Ts = 40 ms): its own wall_s
    is at least the 3.996 s the pace asks (a paced message is never published before it is due,
    whatever the machine's speed) and under the 39.96 s of real time (a bound only a 36 s stall could
    break: --speed is honoured); the last message cannot arrive before the pace allows, counted from
    before the replay was started (CLOCK_MONOTONIC is the machine's, shared by both processes), and
    the arrivals spread over less than real time; --prefix P publishes under P/noiselab/...,
    nothing under noiselab/... ."""
    from noiselab.recordings.simulated import write_simulation

    f = tmp_path / "paced.toml"
    f.write_text(model_text("paced", 0.04))
    path = tmp_path / "paced.mcap"
    write_simulation(load_model(f), 1000, 3, path)         # publish 0..39.96 s
    span, speed = 999 * 0.04, 10
    in_file = {topic: [m.data for _, _, m in items] for topic, items in file_messages(path).items()}
    port = free_port()
    started = time.monotonic()
    rp = spawn("replay", "replay", path, "--listen", ep(port), "--speed", str(speed), "--prefix", "lab/replayed",
               "--wait-subscribers", "20", "--json")
    prefixed, bare = Collector(), Collector()
    with zenoh.open(session_config(connect=[ep(port)])) as session:
        subs = [session.declare_subscriber("lab/replayed/**", prefixed),
                session.declare_subscriber("noiselab/**", bare)]
        assert rp.finish(60) == 0, rp.stderr_text()
        prefixed.wait_for(lambda: sum(len(v) for v in prefixed.by_key.values()) >= 3000, "3000 messages")
        for s in subs:
            s.undeclare()
    assert waited_for_subscribers(rp), rp.stderr_text()
    wall = rp.json()["wall_s"]
    assert span / speed - 1e-3 <= wall < span, f"--speed {speed} of a {span:g} s recording took {wall:.3f} s"
    assert set(prefixed.by_key) == {f"lab/replayed/{t}" for t in in_file}
    for topic, payloads in in_file.items():
        assert [p for p, _ in prefixed.by_key[f"lab/replayed/{topic}"]] == payloads
    arrivals = [a for v in prefixed.by_key.values() for _, a in v]
    last = max(arrivals) - started
    assert last >= span / speed - 1e-3, f"the last message came {last:.3f} s after the start (paced: {span / speed:.3f} s)"
    spread = max(arrivals) - min(arrivals)
    assert spread < span, f"arrivals spread over {spread:.3f} s (real time: {span:.3f} s)"
    assert not bare.by_key, f"published without the prefix: {sorted(bare.by_key)}"


class SampleMeta:
    """Subscriber callback: per key, every sample's (Zenoh encoding, attachment bytes or None)."""

    def __init__(self):
        self.cond = threading.Condition()
        self.by_key: dict[str, list[tuple[str, bytes | None]]] = defaultdict(list)

    def __call__(self, sample) -> None:
        att = sample.attachment
        with self.cond:
            self.by_key[str(sample.key_expr)].append((str(sample.encoding), None if att is None else att.to_bytes()))
            self.cond.notify_all()

    def wait_total(self, total: int) -> None:
        with self.cond:
            ok = self.cond.wait_for(lambda: sum(len(v) for v in self.by_key.values()) >= total, T_EVENT)
            counts = {k: len(v) for k, v in self.by_key.items()}
        assert ok, f"timeout ({T_EVENT} s) waiting for {total} samples; received {counts}"


def foreign_mcap(path) -> None:
    """An MCAP file of no noiselab topic: a JSON channel with a schema, one of an encoding Zenoh has
    no name for."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="test")
        sid = w.register_schema("lab.Temp", "jsonschema", b'{"type":"object"}')
        temp = w.register_channel("/lab/temp", "json", sid)
        raw = w.register_channel("/lab/raw", "x-custom", 0)
        for k in range(5):
            w.add_message(temp, log_time=k * 10**6, publish_time=k * 10**6, data=b'{"c":%d}' % k, sequence=k)
            w.add_message(raw, log_time=k * 10**6, publish_time=k * 10**6, data=b"\x00\x01", sequence=k)
        w.finish()


def test_replay_puts_say_their_encoding_and_the_replays_own_start(separate_recording, tmp_path):
    """What a generic Zenoh subscriber sees of a replay, as of a live emulator: a noiselab stream's
    samples say application/json;<schema name>, and every data and health sample carries the
    replay's own start {"start_time_ns": N}, N the wall clock of its first put (the recording's
    samples begin at t = 0), not the recorded run's start; the end of stream says its encoding and
    no start. A ROS bag's messages, republished as JSON, say application/json;<ROS type>; a foreign
    MCAP channel says its message encoding and schema (JSON), or Zenoh's default for an encoding
    Zenoh has no name for; none of these carries a start."""
    from noiselab.nodes.replay import run_replay
    from noiselab.recordings.simulated import write_simulation

    path, _, emu = separate_recording
    bag = tmp_path / "bag"
    write_simulation(load_model("seed"), 20, 1, bag, fmt="ros2")
    other = tmp_path / "foreign.mcap"
    foreign_mcap(other)
    port = free_port()
    runs = {}
    with zenoh.open(session_config(listen=[ep(port)])) as sink, zenoh.open(session_config(connect=[ep(port)])) as src:
        for name, p in (("noiselab", path), ("bag", bag), ("foreign", other)):
            got = SampleMeta()
            sub = sink.declare_subscriber("**", got)
            before = time.time_ns()
            summary = run_replay(src, str(p), speed=None, wait_subscribers=T_EVENT, log=sys.stderr)
            after = time.time_ns()
            got.wait_total(summary.messages)
            sub.undeclare()
            runs[name] = (got.by_key, summary, before, after)

    got, summary, before, after = runs["noiselab"]
    start = summary.starts["noiselab/fast"]
    assert summary.starts == {"noiselab/fast": start} and before <= start <= after
    assert start > emu["start_time_ns"]                 # the replay's start, not the recorded run's
    for kind in (*wire.KINDS, wire.HEALTH, wire.END):
        samples = got[wire.key("fast", kind)]
        assert len(samples) == (1 if kind == wire.END else 5 if kind == wire.HEALTH else N_FAST), kind
        assert {enc for enc, _ in samples} == {f"application/json;{wire.SCHEMA_NAMES[kind]}"}, kind
        assert {att for _, att in samples} == ({None} if kind == wire.END else {wire.encode_anchor(start)}), kind

    got, summary, _, _ = runs["bag"]
    assert summary.starts == {} and set(got) == {"seed/truth", "seed/command", "seed/measurement"}
    for key, samples in got.items():
        assert samples == [("application/json;sensor_msgs/msg/JointState", None)] * 20, key

    got, summary, _, _ = runs["foreign"]
    assert summary.starts == {}
    assert got == {"lab/temp": [("application/json;lab.Temp", None)] * 5, "lab/raw": [("zenoh/bytes", None)] * 5}


def test_a_recorder_of_a_replay_writes_the_replays_time_base(separate_recording, fast_model, spawn, tmp_path):
    """record --listen P, then replay --connect P of a live recording at speed 1: the new file's
    start is the one the replay stated (its --json summary), not the recorded run's, and its
    publish times are that start + round(t 1e9), each received after it was due, the payloads
    those of the emulated run (check_recording)."""
    path, _, emu = separate_recording
    port = free_port()
    out = tmp_path / "of-replay.mcap"
    rec = spawn("record", "record", "--listen", ep(port), "--out", out, "--json")
    rec.wait_line(READY_MARK)
    rp = spawn("replay", "replay", path, "--connect", ep(port), "--wait-subscribers", "20", "--json")
    assert rp.finish(60) == 0, rp.stderr_text()
    assert waited_for_subscribers(rp), rp.stderr_text()
    rec.wait_line(f"noiselab record: noiselab/fast ended (duration) after {N_FAST} samples: every message recorded")
    assert rec.interrupt() == 0, rec.stderr_text()
    start = rp.json()["starts"]["noiselab/fast"]
    assert start != emu["start_time_ns"]
    check_recording(out, fast_model, SEED_FAST, N_FAST, start_time_ns=start)


# ---------------------------------------------------------------- 2. router + clients


def test_router_and_two_clients_carry_a_device(fast_model_file, fast_model, spawn, tmp_path):
    """router --listen R; record and emulate as clients of R: complete, gap-free recording."""
    port = free_port()
    router = spawn("router", "router", "--listen", ep(port), "--duration", "60")
    router.wait_line(ROUTER_MARK)
    out = tmp_path / "via_router.mcap"
    rec = spawn("record", "record", "--mode", "client", "--connect", ep(port), "--out", out, "--json")
    rec.wait_line(READY_MARK)
    emu = spawn("emulate", "emulate", fast_model_file, "--mode", "client", "--connect", ep(port),
                "--wait-subscribers", "10", "--duration", "2", "--seed", "11", "--json")
    assert emu.finish(60) == 0, emu.stderr_text()
    assert waited_for_subscribers(emu), emu.stderr_text()
    assert rec.interrupt() == 0, rec.stderr_text()
    assert router.interrupt() == 0, router.stderr_text()
    check_summary_topics(rec.json()["topics"], "fast", 2000)
    check_recording(out, fast_model, 11, 2000, batch=False, start_time_ns=emu.json()["start_time_ns"])


# ---------------------------------------------------------------------- 3. closed loop

KP, REF, K_SPRING = 8.0, 0.3, 4.0          # N/m, m, N/m
LOOP_SEED = 5
LOOP_N = 400                               # 4 s at Ts = 10 ms
WINDOW = 200                               # the last 2 s


def closed_loop_prediction(model, n: int, window: int, delay: int) -> tuple[float, float, float]:
    """Mean of y over the last ``window`` of ``n`` samples of the closed loop
    u_k = Kp (r - y_{k-delay}) (zero before the first answer), from rest at k = 0:
    (deterministic mean, std of the window mean from the noise, stationary std of y).

    Linear and exact for this model but for quantization, taken as white noise of variance
    step^2/12 added to the sensor noise. For each white source s (std sigma_s) with impulse
    response h_s to y, the window mean is sum_j g_j e_j with g_j = (1/W) sum_{k in window}
    h_s[k-j], so Var = sum_s sigma_s^2 sum_j g_j^2 (the finite-horizon form of
    Var(mean_T) = 2 sigma_y^2 tau_c / T, which defines the correlation time tau_c).
    """
    Ad, Bd, C = model.Ad, model.Bd, model.Cy
    S = model.S_proc                        # x_{k+1} += S e_k, e_k standard normal
    sig_v = float(np.sqrt(0.002**2 + 0.001**2 / 12))

    def response(x0, n0=0.0, r=0.0, gain=1.0):
        """y_k of the noise-free loop from state x0 at k = 0, sensor impulse n0 at k = 0."""
        x = np.array(x0, float)
        y = np.zeros(n)
        for k in range(n):
            y[k] = (C @ x)[0] + (n0 if k == 0 else 0.0)
            u = KP * (r - y[k - delay]) if k >= delay else 0.0
            x = Ad @ x + Bd[:, 0] * u
        return y

    det = response(np.zeros(model.n_x), r=REF)
    # impulse responses: a process impulse e_j enters x_{j+1}; a sensor impulse enters y_j
    h_proc = [np.concatenate([[0.0], response(S[:, i])[:-1]]) for i in range(S.shape[1])]
    h_sens = response(np.zeros(model.n_x), n0=1.0)
    var_mean, var_y = 0.0, 0.0
    for h, sig in [(h, 1.0) for h in h_proc] + [(h_sens, sig_v)]:
        H = np.concatenate([[0.0], np.cumsum(h)])           # H[m] = sum_{i<m} h[i]
        j = np.arange(n)
        hi = np.clip(n - j, 0, n)
        lo = np.clip(n - window - j, 0, n)
        g = (H[hi] - H[lo]) / window
        var_mean += sig**2 * float(np.sum(g**2))
        var_y += sig**2 * float(np.sum(h**2))
    return float(det[-window:].mean()), float(np.sqrt(var_mean)), float(np.sqrt(var_y))


def test_closed_loop_with_a_p_controller(spawn, tmp_path):
    """A controller process closes the loop: u = Kp (r - y), Kp = 8 N/m, r = 0.3 m.

    Predicted static position x = Kp r / (k + Kp) = 0.2 m (0 open loop). The mean of y over the
    last 2 s of a 4 s run is checked against it within |transient| + 4.5 sigma, both computed
    for the closed loop with the controller answering 1, 2 or 3 samples late (the larger).
    sigma: the noise std of the 2 s window mean from the predicted noise (force psd 1e-4 N^2/Hz,
    sensor 2 mm and 1 mm quantization) and the loop's correlation time: sigma_y = 3.9 mm,
    tau_c = 0.03 s (Var(mean_T) = 2 sigma_y^2 tau_c / T; short although the loop rings, zeta ~
    0.04, because the lobes of its oscillating ACF cancel), so sigma = 0.72 mm. The transient's
    share of the window mean is 1.1 mm, because the window spans one period of the 0.5 Hz
    closed-loop resonance. Tolerance 1.1 + 4.5 x 0.72 = 4.3 mm, against 200 mm open loop.

    The live path equals the batch path for the same commands: the recorded applied command
    re-simulated with simulate(N, seed, command=u) gives the recorded measurement bit for bit.

    How late the controller answers depends on the machine (on a busy one, 0.5 s at times): the
    emulator's stale timeout is set above the run (--stale 10), so every applied command is an
    answer, and the prediction also covers the largest lateness the recording shows (at least the
    smallest k - j with u_k = Kp (r - y_j)), so the check holds whatever the machine's speed; the
    tolerance of 1 to 3 samples is the one that must be far from the open-loop value.
    """
    f = tmp_path / "loop.toml"
    f.write_text(LOOP_TOML)
    model = load_model(f)
    assert model.command.kind == "external"
    # Both subscribers (controller, recorder) must be there before sample 0, and --wait-subscribers
    # starts the emulator at the first match of its measurement: so they are clients of a router
    # that knows them both before the emulator connects.
    port = free_port()
    router = spawn("router", "router", "--listen", ep(port), "--duration", "60")
    router.wait_line(ROUTER_MARK)
    client = ["--mode", "client", "--connect", ep(port)]
    ctl = spawn("p_controller", CONTROLLER, "--name", "loop", "--kp", repr(KP), "--r", repr(REF), *client,
                "--duration", "60", script=True)
    out = tmp_path / "loop.mcap"
    rec = spawn("record", "record", *client, "--out", out, "--json")
    ctl.wait_line("p_controller: ready")
    rec.wait_line(READY_MARK)
    controls = Collector()
    control_key = wire.key("loop", wire.CONTROL)
    with zenoh.open(session_config(connect=[ep(port)])) as session:
        sub = session.declare_subscriber(control_key, controls)
        emu = spawn("emulate", "emulate", f, *client, "--duration", "4", "--seed", str(LOOP_SEED), "--stale", "10",
                    "--wait-subscribers", "20", "--json")
        assert emu.finish(60) == 0, emu.stderr_text()
        assert rec.interrupt() == 0, rec.stderr_text()
        # the controller has answered all but the last measurement (its controls are in order: seq
        # LOOP_N - 2 is its (LOOP_N - 1)-th), however far behind a busy machine left it
        controls.wait_for(lambda: controls.last_seq(control_key) >= LOOP_N - 2, f"control seq {LOOP_N - 2}")
        sub.undeclare()
    assert ctl.interrupt() == 0, ctl.stderr_text()
    assert router.interrupt() == 0, router.stderr_text()
    assert waited_for_subscribers(emu), emu.stderr_text()
    summary = emu.json()
    assert summary["samples"] == LOOP_N
    assert summary["stale_control_events"] == 0, emu.stderr_text()
    assert not any("stale" in ln for ln in emu.err), emu.stderr_text()
    assert ctl.json()["controls"] >= LOOP_N - 1 and ctl.json()["bad"] == 0

    dev = read_recording(out).device("loop")
    for kind in DATA_KINDS:
        assert np.array_equal(dev.streams[kind].seq, np.arange(LOOP_N)), kind
    y = dev.measurement.values[:, 0]
    u = dev.command.values[:, 0]

    # every applied command is the controller's answer to an earlier measurement (ZOH of the latest
    # control), or zero before the first answer arrived; its lateness: at least the smallest k - j
    first = int(np.flatnonzero(u != 0.0)[0])
    assert 1 <= first and (u[:first] == 0.0).all(), f"first control applied at sample {first}"
    late = 1
    for k in range(first, LOOP_N):
        hits = np.flatnonzero(KP * (REF - y[:k]) == u[k])      # bitwise the controller's arithmetic
        assert hits.size, f"u[{k}] = {u[k]!r} is no Kp (r - y_j) with j < k"
        late = max(late, k - int(hits[-1]))

    # static closed-loop position
    x_static = KP * REF / (K_SPRING + KP)

    def tolerance(delays):
        preds = [closed_loop_prediction(model, LOOP_N, WINDOW, d) for d in delays]
        transient = max(abs(m - x_static) for m, _, _ in preds)
        sigma = max(s for _, s, _ in preds)
        sig_y = max(s for _, _, s in preds)
        tau_c = sigma**2 * WINDOW * model.Ts / (2 * sig_y**2)
        return transient + 4.5 * sigma, (f"transient {transient:.5f} m + 4.5 x {sigma:.5f} m; sigma_y {sig_y:.4f} m, "
                                         f"tau_c {tau_c:.2f} s; answers up to {max(delays)} samples late")
    tol, why = tolerance(range(1, max(3, late) + 1))
    mean_y = float(y[-WINDOW:].mean())
    assert abs(mean_y - x_static) <= tol, (
        f"mean y over the last 2 s = {mean_y:.5f} m, predicted {x_static:.5f} m, tolerance {tol:.5f} m ({why})")
    assert abs(0.0 - x_static) > 10 * tolerance((1, 2, 3))[0]      # the open-loop value is far outside

    # the live path is the batch path for the same commands, and the step path
    sim = model.simulate(LOOP_N, seed=LOOP_SEED, command=dev.command.values)
    assert np.array_equal(sim.u, dev.command.values)
    assert np.array_equal(sim.y, dev.measurement.values), "simulate(command=recorded u) != recorded y"
    steps = step_path(model, LOOP_SEED, LOOP_N, commands=dev.command.values)
    assert np.array_equal(steps["measurement"], dev.measurement.values)
    assert np.array_equal(steps["truth"], dev.truth.values)


def test_stale_control_applies_zero_and_says_so_once(spawn, tmp_path):
    """External command, no controller: one 'control input stale' line on stderr, zero applied
    throughout, late_control = 1 in every health report after the 0.2 s timeout."""
    f = tmp_path / "loop.toml"
    f.write_text(LOOP_TOML)
    port = free_port()
    emu = spawn("emulate", "emulate", f, "--listen", ep(port), "--duration", "2", "--stale", "0.2",
                "--wait-subscribers", "20", "--json")
    emu.wait_line(EMULATE_MARK)
    got = Collector()
    with zenoh.open(session_config(connect=[ep(port)])) as session:
        sub = session.declare_subscriber("noiselab/loop/**", got)
        assert emu.finish(60) == 0, emu.stderr_text()
        got.wait_for(lambda: got.count("noiselab/loop/command") >= 200 and got.count("noiselab/loop/health") >= 2,
                     "200 commands and 2 health reports")
        sub.undeclare()
    stale = [ln for ln in emu.err if "control input stale" in ln]
    assert len(stale) == 1, emu.stderr_text()
    assert stale[0].startswith("noiselab emulate: loop: control input stale (no control received yet")
    k_stale = int(stale[0].rsplit("sample ", 1)[1])
    assert 20 <= k_stale < 200, stale[0]             # not before 0.2 s of samples
    assert not any("control input back" in ln for ln in emu.err)
    assert emu.json()["stale_control_events"] == 1
    cmds = [wire.decode(p, "command") for p, _ in got.by_key["noiselab/loop/command"]]
    assert [c["seq"] for c in cmds] == list(range(200))
    assert all(c["u"] == [0.0] for c in cmds), "a non-zero command was applied"
    health = [wire.decode_health(p) for p, _ in got.by_key["noiselab/loop/health"]]
    assert [h["k"] for h in health] == [100, 200]
    assert all(h["late_control"] == 1 for h in health if h["t"] > 0.2), health


def test_stale_control_is_judged_on_the_loops_own_clock(spawn, tmp_path):
    """As above, with the emulator held still (SIGSTOP) for 0.6 s right after its first sample, as
    a busy machine can hold it, then let go: the loop catches up on the samples it owes, and
    the stale timeout is still counted on their deadlines k*Ts, not on the wall clock the late
    loop reads when it gets to them (which called sample 1 or 2 stale): the same one line,
    from sample 20 or later, zero applied, late_control in every report after 0.2 s."""
    f = tmp_path / "loop.toml"
    f.write_text(LOOP_TOML)
    port = free_port()
    emu = spawn("emulate", "emulate", f, "--listen", ep(port), "--duration", "2", "--stale", "0.2",
                "--wait-subscribers", "20", "--json")
    emu.wait_line(EMULATE_MARK)
    got = Collector()
    held = threading.Event()

    def hold_at_first_sample(sample) -> None:
        if not held.is_set() and json.loads(sample.payload.to_bytes())["seq"] == 0:
            os.kill(emu.proc.pid, signal.SIGSTOP)
            held.set()

    with zenoh.open(session_config(connect=[ep(port)])) as session:
        hold = session.declare_subscriber("noiselab/loop/measurement", hold_at_first_sample)
        sub = session.declare_subscriber("noiselab/loop/**", got)
        assert held.wait(T_EVENT), "no first sample"
        try:
            time.sleep(0.6)                 # the fault: how long a busy machine holds the process
        finally:
            os.kill(emu.proc.pid, signal.SIGCONT)
        assert emu.finish(60) == 0, emu.stderr_text()
        got.wait_for(lambda: got.count("noiselab/loop/command") >= 200 and got.count("noiselab/loop/health") >= 2,
                     "200 commands and 2 health reports")
        sub.undeclare()
        hold.undeclare()
    stale = [ln for ln in emu.err if "control input stale" in ln]
    assert len(stale) == 1, emu.stderr_text()
    k_stale = int(stale[0].rsplit("sample ", 1)[1])
    assert 20 <= k_stale < 200, stale[0]
    assert emu.json()["stale_control_events"] == 1 and emu.json()["overruns"] > 0
    cmds = [wire.decode(p, "command") for p, _ in got.by_key["noiselab/loop/command"]]
    assert [c["seq"] for c in cmds] == list(range(200)) and all(c["u"] == [0.0] for c in cmds)
    health = [wire.decode_health(p) for p, _ in got.by_key["noiselab/loop/health"]]
    assert all(h["late_control"] == 1 for h in health if h["t"] > 0.2), health


# ------------------------------------------------------------- 4. kill, recover, restart


def test_sigkilled_recorder_is_recovered_up_to_what_it_had_written(fast_model_file, fast_model, spawn, tmp_path):
    """SIGKILL the recorder at Ts = 1 ms once its file holds measurement seq 1130: `recover` gives
    every message 0..last on every topic, with last at least what the file held intact just before
    the kill (the recorder writes every 0.25 s; how far that is behind the stream depends on the
    machine's speed, what was written does not), payloads equal to the step API's; the broken file
    reads as incomplete."""
    port = free_port()
    emu = spawn("emulate", "emulate", fast_model_file, "--listen", ep(port), "--duration", "60", "--seed", "21",
                "--wait-subscribers", "20", "--json")
    emu.wait_line(EMULATE_MARK)
    broken = tmp_path / "broken.mcap"
    rec = spawn("record", "record", "--connect", ep(port), "--out", broken, "--json")
    rec.wait_line(READY_MARK)
    got = Collector()
    meas = "noiselab/fast/measurement"
    with zenoh.open(session_config(connect=[ep(port)])) as session:
        sub = session.declare_subscriber(meas, got)
        held: dict[str, int] = {}

        def written():
            held.update(on_disk(broken, "fast"))
            return held["measurement"] >= 1130
        poll_until(written, "measurement seq 1130 on disk")
        with got.cond:                        # no sample is taken in while we kill
            s_kill = got.last_seq(meas)
            rec.proc.kill()
        assert rec.finish() == -signal.SIGKILL
        assert emu.interrupt() == 0, emu.stderr_text()
        sub.undeclare()
    samples = emu.json()["samples"]
    assert samples > s_kill

    broken_rec = read_recording(broken)
    assert broken_rec.complete is False and "incomplete" in broken_rec.note
    fixed = tmp_path / "fixed.mcap"
    r = subprocess.run([sys.executable, "-m", "noiselab.cli", "recover", str(broken), "-o", str(fixed), "--json"],
                       capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["already_complete"] is False

    msgs = file_messages(fixed)
    assert read_recording(fixed).complete
    last = {topic: len(items) - 1 for topic, items in msgs.items()}
    steps = step_path(fast_model, 21, max(last.values()) + 1)
    for kind in DATA_KINDS:
        topic = wire.key("fast", kind)
        items = msgs.get(topic, [])
        seqs = [json.loads(m.data)["seq"] for _, _, m in items]
        assert seqs == list(range(len(items))), f"{topic}: not 0..last consecutively"
        assert last[topic] >= held[kind], f"{topic}: recovered up to {last[topic]}, the file held {held[kind]}"
        want = expected_payloads(fast_model, steps, kind, len(items))
        assert [m.data for _, _, m in items] == want, f"{topic}: corrupted payloads"
    health = [json.loads(m.data)["seq"] for _, _, m in msgs.get("noiselab/fast/health", [])]
    assert health == list(range(len(health)))
    assert rep["messages"] == {t: len(v) for t, v in msgs.items()}
    # the broken file itself reads the same intact messages
    for kind in DATA_KINDS:
        assert len(broken_rec.device("fast").streams[kind]) == last[wire.key("fast", kind)] + 1


def test_recorder_restarted_mid_stream(fast_model_file, spawn, tmp_path):
    """Recorder 1 stopped (SIGINT) mid-stream, recorder 2 started later: recorder 2 reports
    missing_at_start == its first seq; both files together cover exactly 0..end but for the seqs
    between recorder 1's last and recorder 2's first; neither has any other gap."""
    port = free_port()
    emu = spawn("emulate", "emulate", fast_model_file, "--listen", ep(port), "--duration", "60", "--seed", "4",
                "--wait-subscribers", "20", "--json")
    emu.wait_line(EMULATE_MARK)
    f1, f2 = tmp_path / "part1.mcap", tmp_path / "part2.mcap"
    rec1 = spawn("record1", "record", "--connect", ep(port), "--out", f1, "--json")
    rec1.wait_line(READY_MARK)
    got = Collector()
    meas = "noiselab/fast/measurement"
    with zenoh.open(session_config(connect=[ep(port)])) as session:
        sub = session.declare_subscriber(meas, got)
        got.wait_for(lambda: got.last_seq(meas) >= 500, "measurement seq 500")
        assert rec1.interrupt() == 0, rec1.stderr_text()
        rec2 = spawn("record2", "record", "--connect", ep(port), "--out", f2, "--json")
        rec2.wait_line(READY_MARK)
        s2 = got.last_seq(meas)
        got.wait_for(lambda: got.last_seq(meas) >= s2 + 500, f"measurement seq {s2 + 500}")
        assert emu.interrupt() == 0, emu.stderr_text()
        end = emu.json()["samples"] - 1
        got.wait_for(lambda: got.last_seq(meas) == end, f"the last measurement {end}")
        assert rec2.interrupt() == 0, rec2.stderr_text()
        sub.undeclare()
    t1, t2 = rec1.json()["topics"], rec2.json()["topics"]
    for summary in (t1, t2):
        for topic, b in summary.items():
            assert b["gaps"] == [] and b["missing"] == 0 and b["restarts"] == [], (topic, b)
    for kind in DATA_KINDS:
        topic = wire.key("fast", kind)
        b1, b2 = t1[topic], t2[topic]
        assert b1["first_seq"] == 0 and b1["missing_at_start"] == 0
        assert b2["first_seq"] > b1["last_seq"] + 1, (b1, b2)       # a real hole between them
        assert b2["missing_at_start"] == b2["first_seq"]
        assert b2["last_seq"] == end
        assert (b1["expected"], b2["expected"], b2["missing_at_end"]) == (None, end + 1, 0)   # only 2 saw the end
        seqs = []
        for f, b in ((f1, b1), (f2, b2)):
            s = [json.loads(m.data)["seq"] for _, _, m in file_messages(f)[topic]]
            assert s == list(range(b["first_seq"], b["last_seq"] + 1)) and len(s) == b["count"]
            seqs += s
        assert seqs == [k for k in range(end + 1) if not b1["last_seq"] < k < b2["first_seq"]]
    for topic, b in t2.items():                  # health too, when a report fell in its time
        if topic != "noiselab/fast/end":         # the end of stream: one message, seq 0
            assert b["missing_at_start"] == (b["first_seq"] if b["count"] else b["expected"]) > 0, (topic, b)
    assert t2["noiselab/fast/end"]["count"] == 1 and "noiselab/fast/end" not in t1


def test_join_points_of_a_live_emulator_and_a_replay(fast_model_file, separate_recording, spawn):
    """transport.join_points: a source answers, per topic, the first seq it had not started when the
    query came (the emulator: the same for its three data topics, its own count for health; a
    replay: its file's), after what a subscriber here saw before the query and within what the
    source published; only topics under the asker's key expression; nothing, at once, when no
    source serves @join (not after its timeout)."""
    port = free_port()
    emu = spawn("emulate", "emulate", fast_model_file, "--listen", ep(port), "--duration", "60", "--seed", "4", "--json")
    emu.wait_line(EMULATE_MARK)
    got = Collector()
    truth = "noiselab/fast/truth"
    with zenoh.open(session_config(connect=[ep(port)])) as session:
        sub = session.declare_subscriber("noiselab/fast/*", got)
        got.wait_for(lambda: got.last_seq(truth) >= 1200, "truth seq 1200")     # health (1 Hz) has reported
        before = got.last_seq(truth)
        joins = transport.join_points(session, "noiselab/**")
        got.wait_for(lambda: got.last_seq(truth) >= joins[truth], f"truth seq {joins[truth]}")
        assert transport.join_points(session, "noiselab/other/**") == {}
        sub.undeclare()
    assert emu.interrupt() == 0, emu.stderr_text()
    assert set(joins) == {f"noiselab/fast/{k}" for k in (*DATA_KINDS, "health")}, joins
    assert joins[truth] == joins["noiselab/fast/command"] == joins["noiselab/fast/measurement"]
    assert before + 1 <= joins[truth], (before, joins)             # it had started what we saw
    assert 1 <= joins["noiselab/fast/health"] <= joins[truth] // 1000 + 1
    assert joins[truth] <= emu.json()["samples"], (joins, emu.json()["samples"])   # no seq it never reached
    with zenoh.open(session_config()) as alone:                   # no source at all
        answered: list = []
        asking = threading.Thread(target=lambda: answered.append(
            transport.join_points(alone, "noiselab/**", timeout=20 * T_EVENT)), daemon=True)
        asking.start()
        asking.join(T_EVENT)
        assert answered == [{}], "join_points with no source to answer waited for its timeout"

    path, _, _ = separate_recording                              # a replay, paced: 5 s of samples
    port = free_port()
    rp = spawn("replay", "replay", path, "--listen", ep(port), "--wait-subscribers", "20", "--json")
    got = Collector()
    with zenoh.open(session_config(connect=[ep(port)])) as session:
        sub = session.declare_subscriber("noiselab/**", got)
        got.wait_for(lambda: got.last_seq(truth) >= 500, "replayed truth seq 500")
        before = got.last_seq(truth)
        joins = transport.join_points(session, "noiselab/**")
        sub.undeclare()
    assert rp.interrupt() == 0, rp.stderr_text()
    assert joins[truth] >= before + 1 and set(joins) <= {f"noiselab/fast/{k}" for k in (*DATA_KINDS, "health")}


def test_recorder_starts_each_topic_where_its_stream_has_no_hole(tmp_path):
    """Ingest with join points: a topic's samples before its point wait for it; those that run
    without a hole up to it are kept, those before a hole are left out and counted (the source sent
    them before it knew the subscriber), so no topic's recording has a gap; an end of stream ends
    its source's joins (a point never reached: the held run up to the last one is kept; the
    source's restart from 0 is recorded); a malformed sample does not end a join; what still
    waits when the recorder stops is written; other sources' topics are untouched."""
    def enc(kind, seqs, dev="d"):
        return [(f"noiselab/{dev}/{kind}", wire.encode(k, k * 0.01, [1.0], kind=kind)) for k in seqs]

    end = wire.encode_end(0, 0.2, 21, {"truth": 21, "command": 21, "measurement": 21, "health": 0}, "stopped")
    items = enc("truth", (10, 11)) + enc("command", (10, 11)) + enc("measurement", (5, 6))
    items += [("noiselab/d/truth", b'{"seq": 12, "t": 0.12, "x": [true]}')]              # malformed
    items += enc("truth", (14, 15, 16)) + enc("command", (12, 13)) + enc("measurement", (8,))
    items += enc("truth", (40, 41), dev="e")                                              # waits for 50
    items += enc("truth", (17, 18, 19, 20)) + [("noiselab/d/end", end)]
    items += enc("truth", (0, 1)) + enc("measurement", (0, 1))                            # restarted source
    path = tmp_path / "join.mcap"
    log = tmp_path / "log.txt"
    with RecordingWriter(path) as w, open(log, "w") as f:
        ing = Ingest(w, str(path), log=f)
        ing.join = {"noiselab/d/truth": 15, "noiselab/d/command": 12, "noiselab/d/measurement": 30,
                    "noiselab/d/health": 3, "noiselab/e/truth": 50}
        ing.add(items[:5], 1_000)
        ing.add(items[5:], 2_000)
        assert ing.join == {"noiselab/e/truth": 50}
        ing.flush_join()
    assert ing.join == {} and ing.malformed == 1
    assert ing.dropped_at_join == {"noiselab/d/truth": (2, 10, 11), "noiselab/d/measurement": (2, 5, 6)}
    seqs = {topic: [m.sequence for _, _, m in v] for topic, v in file_messages(path).items()}
    assert seqs["noiselab/d/truth"] == [14, 15, 16, 17, 18, 19, 20, 0, 1]
    assert seqs["noiselab/d/command"] == [10, 11, 12, 13]
    assert seqs["noiselab/d/measurement"] == [8, 0, 1]
    assert seqs["noiselab/e/truth"] == [40, 41]
    books = {k: b.as_dict() for k, b in ing.books.items()}
    tb = books["noiselab/d/truth"]
    assert (tb["first_seq"], tb["missing_at_start"], tb["restarts"]) == (14, 14, [[20, 0]])
    assert books["noiselab/d/command"]["first_seq"] == 10 and books["noiselab/d/command"]["missing_at_start"] == 10
    text = log.read_text()
    assert "noiselab/d/truth: joined the stream at seq 14 (join point 15); 2 sample(s) received before a hole " \
           "left out (seqs 10..11" in text
    assert "noiselab/d/measurement: joined the stream at seq 8 (join point 30); 2 sample(s)" in text
    assert "noiselab/d/command:" not in text and "noiselab/e/truth:" not in text      # nothing left out there


def test_rust_log_goes_to_stderr_and_json_stays_clean():
    """RUST_LOG turns on Zenoh's own log: on stderr; stdout keeps only the --json summary."""
    port = free_port()
    r = subprocess.run([sys.executable, "-m", "noiselab.cli", "emulate", "seed", "--duration", "0.1", "--listen",
                        ep(port), "--json"], capture_output=True, text=True, timeout=60,
                       env=dict(os.environ, RUST_LOG="info"))
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["samples"] == 10
    assert "zenoh::" in r.stderr and "zenoh::" not in r.stdout


def test_topicbook_counts_gaps_and_restarts():
    b = TopicBook()
    for s in [3, 4, 5, 8, 9, 9, 2, 3, 10]:
        b.see(s)
    d = b.as_dict()
    assert (d["first_seq"], d["last_seq"], d["count"]) == (3, 10, 9)
    assert d["missing_at_start"] == 3
    assert d["gaps"] == [[5, 2], [3, 6]] and d["missing"] == 8
    assert d["restarts"] == [[9, 9], [9, 2]]
    fresh = TopicBook()
    for s in range(5):
        fresh.see(s)
    assert fresh.as_dict() == {"first_seq": 0, "last_seq": 4, "count": 5, "missing_at_start": 0, "gaps": [],
                               "missing": 0, "restarts": [], "expected": None, "missing_at_end": 0}
    run = TopicBook()
    run.see_run(0, 5)
    assert run.as_dict() == fresh.as_dict()
    run.see_run(7, 3)                      # 5, 6 skipped
    assert (run.last_seq, run.count, run.gaps) == (9, 8, [(4, 2)])
    assert run.end(13) == 3                # the source sent 0..12: 10, 11, 12 never came
    d = run.as_dict()
    assert d["gaps"] == [[4, 2], [9, 3]] and d["missing"] == 5 and (d["expected"], d["missing_at_end"]) == (13, 3)
    assert run.lacks == 5
    late = TopicBook()                     # a recorder started at seq 3 of a source that sent 0..9
    for s in range(3, 8):
        late.see(s)
    assert late.end(10) == 2 and late.lacks == 3 + 2
    none = TopicBook()                     # nothing of the topic arrived
    assert none.end(4) == 0 and none.lacks == 4
    assert (none.as_dict()["missing_at_start"], none.as_dict()["gaps"], none.as_dict()["missing"]) == (4, [], 0)
    assert TopicBook().as_dict()["missing_at_start"] == 0


# ------------------------------------------------------------------ 4b. end of stream


def test_end_of_stream_is_answered_after_the_data_and_a_shortfall_is_a_gap(spawn, tmp_path):
    """A source in this process (a real session, the emulator's publisher options) puts 20,000
    measurements as fast as it can and 100 commands with one malformed payload among them, then
    ends its stream the emulator's way (transport.end_stream) claiming 20,005 measurements, 100
    commands and 3 truths it never sent. The recorder answers only once it has written all
    20,000 (its answer holds the count), books the 5 + 3 it never got as gaps at the end, says so
    on stderr and in its summary, skips only the malformed payload, and finishes on SIGINT."""
    n = 20_000
    port = free_port()
    out = tmp_path / "end.mcap"
    rec = spawn("record", "record", "--listen", ep(port), "--out", out, "--json")
    rec.wait_line(READY_MARK)
    meas = wire.encode_batch("measurement", 0, np.arange(n) * 1e-3, np.ones((n, 1)))
    cmds = wire.encode_batch("command", 0, np.arange(100) * 1e-3, np.zeros((100, 1)))
    claimed = {"measurement": n + 5, "command": 100, "truth": 3}
    with zenoh.open(session_config(connect=[ep(port)])) as session:
        pubs = {kind: session.declare_publisher(wire.key("src", kind), **transport.DATA_QOS)
                for kind in ("measurement", "command", "end")}
        assert transport.wait_matching(pubs.values(), T_EVENT), "the recorder did not match"
        # a foreign publisher: its puts say zenoh's default encoding and no attachment, and count the same
        assert str(pubs["measurement"].encoding) == "zenoh/bytes"
        for payload in meas:
            pubs["measurement"].put(payload)
        for k, payload in enumerate(cmds):
            if k == 50:
                pubs["command"].put(b'{"seq":50,"t":0.05,"u":[NaN]}')
            pubs["command"].put(payload)
        end = transport.end_stream(session, pubs["end"], wire.encode_end(0, (n - 1) * 1e-3, n + 5, claimed, "stopped"),
                                   T_EVENT)
    assert end["timed_out"] is False and end["errors"] == [] and len(end["acks"]) == 1, end
    ack = end["acks"][0]
    assert (ack["out"], ack["prefix"], ack["ended"], ack["complete"]) == (str(out), "noiselab/src", True, False)
    assert ack["topics"]["measurement"] == {"count": n, "last_seq": n - 1, "expected": n + 5, "missing": 5}
    assert ack["topics"]["command"] == {"count": 100, "last_seq": 99, "expected": 100, "missing": 0}
    assert ack["topics"]["truth"] == {"count": 0, "last_seq": None, "expected": 3, "missing": 3}
    line = rec.wait_line("noiselab record: noiselab/src ended")
    assert line == ("noiselab record: noiselab/src ended (stopped) after 20005 samples: "
                    "not recorded: 5 measurement (5 at the end), 3 truth (none arrived)"), line
    assert rec.interrupt() == 0, rec.stderr_text()
    summary = rec.json()
    assert summary["messages"] == n + 100 + 1 and summary["malformed"] == 1
    assert summary["ended"] == {"noiselab/src": claimed}
    topics = summary["topics"]
    m = topics["noiselab/src/measurement"]
    assert (m["count"], m["gaps"], m["missing"], m["expected"], m["missing_at_end"]) == (n, [[n - 1, 5]], 5, n + 5, 5)
    t = topics["noiselab/src/truth"]
    assert (t["count"], t["first_seq"], t["missing_at_start"], t["gaps"], t["missing"]) == (0, None, 3, [], 0)
    c = topics["noiselab/src/command"]
    assert (c["count"], c["gaps"], c["missing"], c["restarts"]) == (100, [], 0, [])
    msgs = file_messages(out)
    assert [m.data for _, _, m in msgs["noiselab/src/measurement"]] == meas
    assert [m.data for _, _, m in msgs["noiselab/src/command"]] == cmds
    assert [m.sequence for _, _, m in msgs["noiselab/src/measurement"]] == list(range(n))
    # a source that states no start is anchored at its first sample's arrival (t = 0 then)
    pub = [m.publish_time for _, _, m in msgs["noiselab/src/measurement"]]
    assert pub == [pub[0] + k * 1_000_000 for k in range(n)]
    assert pub[0] == msgs["noiselab/src/measurement"][0][2].log_time
    assert summary["starts"] == {"noiselab/src": {"start_time_ns": pub[0], "stated": False}}
    assert read_recording(out).metadata["noiselab"]["start_time_ns"] == str(pub[0])
    (schema, channel, end_msg), = msgs["noiselab/src/end"]
    assert schema.name == "noiselab.End" and wire.decode_end(end_msg.data)["counts"] == claimed
    assert "noiselab/src/truth" not in msgs


def test_emulator_at_10_khz_loses_nothing_at_the_end(spawn, tmp_path):
    """Ts = 0.1 ms for 2 s (60,000 messages; the emulator catches up when it falls behind, it never
    skips a sample) into a recorder process: the emulator exits only after the recorder has
    acknowledged its end of stream, and the file holds every sample of the step API's path."""
    f = tmp_path / "fast10k.toml"
    f.write_text(model_text("fast10k", 0.0001))
    model = load_model(f)
    n = 20_000
    port = free_port()
    out = tmp_path / "fast10k.mcap"
    rec = spawn("record", "record", "--listen", ep(port), "--out", out, "--json")
    rec.wait_line(READY_MARK)
    emu = spawn("emulate", "emulate", f, "--connect", ep(port), "--wait-subscribers", "20", "--duration", "2",
                "--seed", "3", "--json")
    assert emu.finish(120) == 0, emu.stderr_text()
    assert waited_for_subscribers(emu), emu.stderr_text()
    summary = emu.json()
    assert summary["samples"] == n
    check_end_acknowledged(summary, "fast10k", n)
    rec.wait_line("noiselab record: noiselab/fast10k ended (duration) after 20000 samples: every message recorded")
    assert rec.interrupt() == 0, rec.stderr_text()
    check_summary_topics(rec.json()["topics"], "fast10k", n)
    check_recording(out, model, 3, n, batch=False, start_time_ns=summary["start_time_ns"])


def test_recorder_batches_equal_message_by_message(tmp_path):
    """The recorder's work on a batch (runs decoded with wire.decode_batch and written with
    write_batch) gives the same file and books as message by message (wire.decode, write); a
    malformed payload in a long run costs only itself; a gap and a restart are booked the same."""
    rng = np.random.default_rng(0)
    meas = wire.encode_batch("measurement", 0, np.arange(300) * 0.01, rng.normal(size=(300, 2)))
    truth = wire.encode_batch("truth", 0, np.arange(300) * 0.01, rng.normal(size=(300, 2)))
    items = []
    for k in range(300):
        if k in (100, 101, 102):
            continue                                           # a gap
        items.append(("noiselab/d/truth", truth[k]))
        items.append(("noiselab/d/measurement", meas[k] if k != 150 else b'{"seq":150,"t":1.5,"y":[1.0,true]}'))
    items += [("noiselab/d/measurement", meas[5]), ("noiselab/d/truth", truth[5]),   # restarts, confirmed
              ("noiselab/d/measurement", meas[6]), ("noiselab/d/truth", truth[6]),   # by their successors
              ("noiselab/d/state", b"{}"), ("noiselab/d/health", b'{"seq":0}')]       # a foreign kind, a bad health
    books, files = [], []
    for mode in ("batch", "one by one"):
        path = tmp_path / f"{mode}.mcap"
        with RecordingWriter(path) as w:
            ing = Ingest(w, str(path), log=open(os.devnull, "w"))
            if mode == "batch":
                ing.add(items, 1_000)
            else:
                for item in items:
                    ing.add([item], 1_000)
        books.append(({k: b.as_dict() for k, b in ing.books.items()}, ing.messages, ing.malformed))
        files.append({topic: [(m.sequence, m.publish_time, m.log_time, m.data) for _, _, m in v]
                      for topic, v in file_messages(path).items()})
    assert books[0] == books[1] and files[0] == files[1]
    topics, messages, malformed = books[0]
    assert (messages, malformed) == (2 * 297 - 1 + 4, 3)
    tb = topics["noiselab/d/truth"]            # the batch path: decode_batch, runs split at the gap and the restart
    assert tb["gaps"] == [[99, 3]] and tb["restarts"] == [[299, 5]] and tb["count"] == 299
    mb = topics["noiselab/d/measurement"]
    assert mb["gaps"] == [[99, 3], [149, 1]] and mb["restarts"] == [[299, 5]] and mb["count"] == 298
    assert [s for s, _, _, _ in files[0]["noiselab/d/measurement"]] == [k for k in range(300) if k not in (100, 101, 102, 150)] + [5, 6]


# --------------------------------------------------------------------------- 5. errors


def _bound_socket():
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", 0))
    s.listen()
    return s


@pytest.mark.parametrize("case", ["connect_unreachable", "listen_in_use", "bad_key", "out_exists",
                                  "replay_not_mcap", "recover_not_mcap", "config_missing"])
def test_bad_input_is_one_line_exit_2(case, tmp_path):
    """Each failure: exit 2, one stderr line starting 'noiselab: ', no traceback, nothing on stdout."""
    held = None
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an MCAP file\n")
    out = tmp_path / "out.mcap"
    if case == "connect_unreachable":
        args = ["record", "--connect", ep(free_port()), "--connect-timeout", "1", "--out", str(out)]
        expect = "Unable to connect"
    elif case == "listen_in_use":
        held = _bound_socket()
        args = ["emulate", "seed", "--listen", ep(held.getsockname()[1]), "--duration", "1"]
        expect = "Address already in use"
    elif case == "bad_key":
        args = ["record", "--key", "noiselab/**/", "--out", str(out)]
        expect = "invalid key expression 'noiselab/**/'"
    elif case == "out_exists":
        out.write_bytes(b"precious")
        os.utime(out, ns=(1_000_000_000, 1_000_000_000))
        args = ["record", "--out", str(out), "--connect", ep(free_port())]
        expect = "exists"
    elif case == "replay_not_mcap":
        args = ["replay", str(junk), "--listen", ep(free_port())]
        expect = "not an MCAP file"
    elif case == "recover_not_mcap":
        args = ["recover", str(junk), "-o", str(out)]
        expect = "not an MCAP file"
    else:
        args = ["emulate", "seed", "--config", str(tmp_path / "missing.json5"), "--duration", "1"]
        expect = "missing.json5: no such file"
    try:
        r = subprocess.run([sys.executable, "-m", "noiselab.cli", *args], capture_output=True, text=True,
                           cwd=ROOT, timeout=60)
    finally:
        if held is not None:
            held.close()
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("noiselab: "), r.stderr
    assert "Traceback" not in r.stderr and expect in lines[0], r.stderr
    assert r.stdout == ""
    if case == "out_exists":
        assert out.read_bytes() == b"precious" and out.stat().st_mtime_ns == 1_000_000_000
    else:
        assert not out.exists(), "a failed command left an output file"


# ------------------------------------------------------------------ 6. safe by default


def test_default_endpoints_listen_on_loopback_only(default_endpoint, spawn):
    """With no endpoint flags the emulator listens on tcp/127.0.0.1:7447 and nothing else: every
    socket of the process is bound to 127.0.0.1 (none on 0.0.0.0 or ::), no UDP (no scouting)."""
    users = [c for c in psutil.net_connections(kind="inet")
             if c.laddr and c.laddr.port == 7447 and c.status in (psutil.CONN_LISTEN, psutil.CONN_NONE)]
    if users:
        pytest.skip(f"port 7447 (the default this test must use) is already bound by something else: "
                    f"{[(c.laddr.ip, c.pid) for c in users]}")
    emu = spawn("emulate", "emulate", "seed", "--duration", "60")
    line = emu.wait_line(EMULATE_MARK)
    assert "listen ['tcp/127.0.0.1:7447']" in line and "connect []" in line, line
    conns = psutil.Process(emu.proc.pid).net_connections(kind="inet")
    listening = [c for c in conns if c.status == psutil.CONN_LISTEN]
    assert listening, f"no listening socket: {conns}"
    assert {(c.laddr.ip, c.laddr.port) for c in listening} == {("127.0.0.1", 7447)}, listening
    assert all(c.laddr.ip == "127.0.0.1" for c in conns), f"sockets off loopback: {conns}"
    assert not [c for c in conns if c.type == socket.SOCK_DGRAM], f"UDP sockets (scouting?): {conns}"
    assert emu.interrupt() == 0, emu.stderr_text()


# ------------------------------------------------------------------------------ 7. health


def test_health_at_1_hz(fast_model_file, spawn):
    """A 2 s run at Ts = 1 ms: a health report every 1000 samples (k = 1000, 2000: 1 s of samples
    each, and the emulator keeps the samples' pace: its run lasts at least the 1.999 s to the last
    sample's deadline); lateness fields ordered, non-negative, within the run's wall time, and
    consistent with the emulator's final summary (the two reports cover every sample of the run:
    the overall max is their max, the overall median lies between theirs, the overrun count is the
    last one's); late_control 0. No real-time bound is asserted on the lateness itself, nor on
    when the reports arrive here: on a shared machine a competing process can hold the loop behind
    for a whole report period, and the health is there to say so."""
    port = free_port()
    emu = spawn("emulate", "emulate", fast_model_file, "--listen", ep(port), "--duration", "2",
                "--wait-subscribers", "20", "--json")
    emu.wait_line(EMULATE_MARK)
    got = Collector()
    with zenoh.open(session_config(connect=[ep(port)])) as session:
        sub = session.declare_subscriber("noiselab/fast/**", got)
        assert emu.finish(60) == 0, emu.stderr_text()
        got.wait_for(lambda: got.count("noiselab/fast/health") >= 2 and got.count("noiselab/fast/measurement") >= 2000,
                     "2 health reports and 2000 measurements")
        sub.undeclare()
    health = [(wire.decode_health(p), a) for p, a in got.by_key["noiselab/fast/health"]]
    assert [h["seq"] for h, _ in health] == [0, 1]
    assert [h["k"] for h, _ in health] == [1000, 2000]
    summary = emu.json()
    for h, _ in health:
        assert abs(h["t"] - h["k"] * 0.001) <= 0.001 + 1e-12, h
        assert 0 <= h["lateness_p50_us"] <= h["lateness_p99_us"] <= h["lateness_max_us"] <= summary["wall_s"] * 1e6, h
        assert 0 <= h["overruns"] <= h["k"] and h["late_control"] == 0, h
    (h1, _), (h2, _) = health
    assert summary["samples"] == 2000 and summary["wall_s"] >= 1.999, summary
    assert h1["overruns"] <= h2["overruns"] == summary["overruns"]
    lat = summary["lateness_us"]
    assert lat["max"] == max(h1["lateness_max_us"], h2["lateness_max_us"]), (lat, health)
    assert min(h1["lateness_p50_us"], h2["lateness_p50_us"]) <= lat["p50"] <= \
        max(h1["lateness_p50_us"], h2["lateness_p50_us"]), (lat, health)
    assert json.loads(got.by_key["noiselab/fast/measurement"][0][0])["seq"] == 0
