"""The live analysis node against a replayed recording (issue 4 "What it must show", item 6):
real processes (``noiselab analyze --live``, ``noiselab replay``), real Zenoh sessions on
127.0.0.1 with multicast scouting off, real MCAP files.

Topology: the replay listens on P; this test's own session listens on Q and subscribes to
``noiselab/seed/analysis``; the analyzer connects to both (``--connect-timeout`` long enough to
outlast the replay's start-up: its explicit connect retries until P is up). The replay waits for
the analyzer's subscribers (``--wait-subscribers``) before its first message.

Synchronisation is by events only: the analysis summaries received by this test's subscriber
(condition variable), the children's stderr lines, process exit. Every timeout is a failure bound.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from noiselab import wire
from noiselab.diagnose.compare import compare
from noiselab.model import load_model
from noiselab.nodes.runner import free_port
from noiselab.recordings.scan import iter_messages
from noiselab.recordings.writer import RecordingWriter

pytestmark = pytest.mark.slow   # live end-to-end runs: real processes and sessions

ROOT = Path(__file__).resolve().parents[2]
SCENARIOS = ROOT / "service" / "scenarios"
T_EVENT = 60.0           # bound for "the next event happens" on a shared 2-core machine; never a pass
FILE_SEED = 3            # see test_hot_reload for why this seed's numbers are well inside the bounds


# ------------------------------------------------------------------------------------ helpers
def ep(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


class Summaries:
    """Subscriber on the analysis topic: every summary (decoded) with its monotonic arrival time."""

    def __init__(self):
        self.cond = threading.Condition()
        self.items: list[tuple[float, dict]] = []

    def __call__(self, sample) -> None:
        obj = wire.decode_analysis(sample.payload.to_bytes(), topic=str(sample.key_expr))
        with self.cond:
            self.items.append((time.monotonic(), obj))
            self.cond.notify_all()

    def wait(self, pred, what: str, start: int = 0, timeout: float = T_EVENT) -> tuple[int, float, dict]:
        """The first summary at index >= ``start`` satisfying ``pred``: (index, arrival, summary)."""
        def find():
            return next((i for i in range(start, len(self.items)) if pred(self.items[i][1])), None)
        with self.cond:
            self.cond.wait_for(lambda: find() is not None, timeout)
            i = find()
            last = self.items[-1][1] if self.items else None
        assert i is not None, f"timeout ({timeout} s) waiting for {what}; last summary: {last}"
        return i, self.items[i][0], self.items[i][1]

    def __len__(self) -> int:
        with self.cond:
            return len(self.items)


def listening_session(port: int) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([ep(port)]))
    conf.insert_json5("connect/endpoints", "[]")
    return zenoh.open(conf)


def cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "noiselab.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=ROOT, timeout=timeout)


def write_blocks(model, n: int, seed: int, out: Path, block: int = 10) -> None:
    """The simulated record in the wire contract, written in blocks of ``block`` samples per topic
    (truth, command, measurement). With a small block the file order is nearly the emulator's;
    with a large one it is how ``noiselab simulate`` wrote before it interleaved (65,536-sample
    blocks per topic), which the replay must still publish in sample order."""
    rec = model.simulate(n, seed=seed)
    with RecordingWriter(out) as w:
        for k0 in range(0, n, block):
            nb = min(block, n - k0)
            t, pub = wire.sample_times(k0, nb, model.Ts)
            for kind, arr in (("truth", rec.x), ("command", rec.u), ("measurement", rec.y)):
                topic = wire.key(model.name, kind)
                w.write_batch(topic, kind, k0, pub, pub, wire.encode_batch(kind, k0, t, arr[k0:k0 + nb], topic=topic))


# ------------------------------------------------------------------------------------ tests
def test_live_equals_offline_on_a_replay(tmp_path, spawn):
    """A live analyzer fed a replay of a file, window longer than the file, ends with exactly the
    offline analysis' numbers (same floats), STYLE 9."""
    rec_path = tmp_path / "seed60.mcap"
    r = cli("simulate", "seed", "--duration", "60", "--seed", FILE_SEED, "--out", rec_path)
    assert r.returncode == 0, r.stderr
    count = 6000
    offline = cli("analyze", rec_path, "--model", "seed-nominal", "--json")
    assert offline.returncode == 0, offline.stderr
    off = json.loads(offline.stdout)
    assert off["samples"] == count

    p, q = free_port(), free_port()
    got = Summaries()
    with listening_session(q) as session:
        sub = session.declare_subscriber("noiselab/seed/analysis", got)
        an = spawn("analyze", "analyze", "--live", "--model", "seed-nominal", "--connect", ep(p), "--connect", ep(q),
                   "--connect-timeout", "30", "--window", "1000", "--json")
        rp = spawn("replay", "replay", rec_path, "--fast", "--listen", ep(p), "--wait-subscribers", "20", "--json")
        assert rp.finish() == 0, rp.stderr_text()
        assert not any("no subscriber matched" in ln for ln in rp.err), rp.stderr_text()
        assert rp.json()["messages"] == 3 * count
        # everything is in when a summary analysed every sample (and counted both topics)
        _, _, last = got.wait(lambda s: s["samples"] == count and s["received"] == 2 * count,
                               f"a summary with samples == {count}")
        assert an.interrupt() == 0, an.stderr_text()
        sub.undeclare()
    live = an.json()
    assert live["live"] and live["received"] == 2 * count and live["malformed"] == 0
    assert type(live["late_ticks"]) is int and live["late_ticks"] >= 0     # counted, not asserted: speed is benchmarked
    assert live["samples"] == count and live["revisions"] == 1
    # exactly the same floats as offline (JSON round-trips floats exactly)
    assert live["error"] == off["error"], (live["error"], off["error"])
    assert live["error_per_view"] == off["error_per_view"]
    assert last["error"] == off["error"] and last["error_per_view"] == off["error_per_view"]
    assert live["error"] > 10          # seed data against the nominal model: a real mismatch, not 1 == 1


def test_hot_reload_changes_the_error(tmp_path, spawn):
    """The model file edited while the analyzer runs: a revision-1 summary follows, after which
    no revision-0 one, and it shows the right model's error; a broken edit keeps the revision (one
    line). How soon it follows (at the next update: the reload is checked before each) depends on
    the machine's speed and is printed, not asserted.

    Bound on the right model's error: a correct model's error on one record has mean 1 and a
    spread of sd ~0.65 on records of 1000-6000 samples (measured: 8 seeds x prefixes of 800..6000
    samples, mean 1.0, max 4.6), so < 3 is ~3 sd. For this file (seed 3) the right model's error on
    every prefix of 700..6000 samples (step 10) is <= 1.93, and the nominal model's error first
    exceeds 10 at 700 samples (offline, same compare()): the bounds hold wherever the reload lands.
    The check that carries the live machinery is exact: the revision-1 summary equals compare()
    on the same prefix of the file."""
    # the reload's latency is the rest of the current period (the updates are due at fixed ticks,
    # so up to one period) plus the reload update's own work, which a loaded machine stretches:
    # it is printed, not bounded
    update = 1.0
    seed_model = load_model("seed")
    n = 6000
    rec_path = tmp_path / "seed60.mcap"
    write_blocks(seed_model, n, FILE_SEED, rec_path)
    model_file = tmp_path / "model.toml"
    model_file.write_text((SCENARIOS / "seed-nominal.toml").read_text())

    def replace(text: str) -> None:            # an editor's atomic save
        tmp = tmp_path / "model.toml.new"
        tmp.write_text(text)
        os.replace(tmp, model_file)

    p, q = free_port(), free_port()
    got = Summaries()
    with listening_session(q) as session:
        sub = session.declare_subscriber("noiselab/seed/analysis", got)
        an = spawn("analyze", "analyze", "--live", "--model", model_file, "--connect", ep(p), "--connect", ep(q),
                   "--connect-timeout", "30", "--window", "1000", "--update", repr(update), "--json")
        rp = spawn("replay", "replay", rec_path, "--speed", "4", "--listen", ep(p), "--wait-subscribers", "20")
        i0, _, s0 = got.wait(lambda s: s["revision"] == 0 and s["error"] > 10, "revision 0 with error > 10")

        replace((SCENARIOS / "seed.toml").read_text())
        t_change = time.monotonic()
        i1, t1, s1 = got.wait(lambda s: s["revision"] == 1, "the first revision-1 summary", start=i0 + 1)
        latency = t1 - t_change
        an.wait_line("reloaded")
        assert all(s["revision"] == 0 for _, s in got.items[i0:i1])

        # the broken edit: one line, revision kept, summaries go on
        replace((SCENARIOS / "seed.toml").read_text() + "\n[sensor.whiet]\nstd = 0.01\n")
        line = an.wait_line("model file changed but is invalid")
        k = len(got)
        _, _, s2 = got.wait(lambda s: True, "a summary after the broken edit", start=k)
        assert all(s["revision"] == 1 for _, s in got.items[i1:]), [s["revision"] for _, s in got.items[i1:]]
        assert rp.interrupt() == 0, rp.stderr_text()
        assert an.interrupt() == 0, an.stderr_text()
        sub.undeclare()

    print(f"\nhot reload: revision 0 error {s0['error']:.3g} at {s0['samples']} samples; revision 1 summary "
          f"{latency:.3f} s after the file change (update every {update:g} s), error {s1['error']:.3g} at "
          f"{s1['samples']} samples")
    assert sum(ln.startswith("noiselab analyze: reloaded ") for ln in an.err) == 1, an.stderr_text()
    assert s1["error"] < 3, s1
    # the live number is compare() on the same prefix of the file (the stream starts at rest: burn auto)
    m = s1["samples"]
    data = seed_model.simulate(n, seed=FILE_SEED)
    ref = compare(seed_model, data.t[:m], data.y[:m], data.u[:m], burn=None, level=True)
    # (failed twice in about ten runs under load, live against offline: the message keeps both sides)
    assert s1["error"] == ref.error and s1["error_per_view"] == ref.error_per_view, (s1, ref.error_per_view, ref.notes)
    assert s1["model_source"] == str(model_file)
    # broken edit: kept revision 1, one line naming the problem, no traceback
    assert s2["revision"] == 1
    assert "keeping revision 1" in line and "sensor.whiet" in line
    assert sum("model file changed but is invalid" in ln for ln in an.err) == 1
    assert not any("Traceback" in ln for ln in an.err), an.stderr_text()
    final = an.json()
    assert final["revisions"] == 2 and final["revision"] == 1


@pytest.mark.parametrize("layout", ["simulate", "per_topic_blocks"])
def test_replay_interleaves_the_topics_of_a_file(tmp_path, spawn, layout):
    """replay of a ``noiselab simulate`` file, and of a file holding 700-sample blocks per topic
    (how simulate wrote before; foreign writers may too): a subscriber receives command and
    measurement interleaved, sample by sample (command k, then measurement k), as from the live
    emulator, never a block of one topic before the other. Every message once, bytes unchanged."""
    n = 2000
    path = tmp_path / f"{layout}.mcap"
    if layout == "simulate":
        r = cli("simulate", "seed", "--duration", "20", "--seed", FILE_SEED, "--out", path)
        assert r.returncode == 0, r.stderr
    else:
        write_blocks(load_model("seed"), n, FILE_SEED, path, block=700)
    in_file = {}
    for _, c, m in iter_messages(path):
        in_file.setdefault(c.topic, []).append(m.data)
    got: list[tuple[str, int, bytes]] = []
    cond = threading.Condition()

    def on_sample(sample):
        kind = str(sample.key_expr).rsplit("/", 1)[-1]
        if kind not in ("command", "measurement"):
            return
        data = sample.payload.to_bytes()
        with cond:
            got.append((kind, json.loads(data)["seq"], data))
            cond.notify_all()

    q = free_port()
    with listening_session(q) as session:
        # one subscriber for every topic: Zenoh runs each subscriber's callbacks on its own
        # thread, so only one callback sees the arrival order across topics
        subs = [session.declare_subscriber("noiselab/seed/*", on_sample)]
        rp = spawn("replay", "replay", path, "--fast", "--connect", ep(q), "--wait-subscribers", "20", "--json")
        assert rp.finish() == 0, rp.stderr_text()
        with cond:
            assert cond.wait_for(lambda: len(got) >= 2 * n, T_EVENT), f"{len(got)} of {2 * n} messages"
        for sub in subs:
            sub.undeclare()
    assert rp.json()["messages"] == 3 * n
    # sample by sample: c0 m0 c1 m1 ... (ties at one publish time go command, then measurement)
    assert [(k, s) for k, s, _ in got] == [(k, s) for s in range(n) for k in ("command", "measurement")]
    for kind in ("command", "measurement"):
        assert [d for k, _, d in got if k == kind] == in_file[f"noiselab/seed/{kind}"]


def test_live_ranking_names_the_missing_effect_like_the_offline_diagnosis(tmp_path, spawn):
    """Issue 5 item 4: the live analyzer re-ranks the candidate missing effects on its window; fed
    a replay of a file (window longer than the file), its final ranking is the offline diagnosis'
    first step on the same samples (same floats), and the summaries on Zenoh carry it."""
    from noiselab.diagnose.diagnose import diagnose
    from noiselab.recordings.load import load_noiselab

    rec_path = tmp_path / "ar1.mcap"
    r = cli("simulate", "hidden/actuator.ar1", "--duration", "60", "--seed", FILE_SEED, "--out", rec_path)
    assert r.returncode == 0, r.stderr
    count = 6000
    nominal = load_model("hidden/actuator.ar1-nominal")
    s = load_noiselab(str(rec_path), truth=False, Ts=nominal.Ts)
    off = diagnose(nominal, s.t, s.y, s.u, at_rest=True, max_effects=1)
    assert off["missing"] and off["missing"][0]["effect"] == "actuator.ar1"

    p, q = free_port(), free_port()
    got = Summaries()
    with listening_session(q) as session:
        sub = session.declare_subscriber("noiselab/msd/analysis", got)
        an = spawn("analyze", "analyze", "--live", "--model", "hidden/actuator.ar1-nominal", "--connect", ep(p),
                   "--connect", ep(q), "--connect-timeout", "30", "--window", "1000", "--rank-every", "1", "--json")
        rp = spawn("replay", "replay", rec_path, "--speed", "10", "--listen", ep(p), "--wait-subscribers", "20")
        assert rp.finish() == 0, rp.stderr_text()
        _, _, last = got.wait(lambda x: "ranking" in x and x["samples"] == count and x["ranking"]["samples"] == count,
                              "a summary ranked on every sample")
        assert an.interrupt() == 0, an.stderr_text()
        sub.undeclare()
    live = an.json()
    rk = live["ranking"]
    assert rk["samples"] == count and rk["revision"] == 0
    m, o = rk["missing"][0], off["missing"][0]
    assert m["effect"] == o["effect"] == "actuator.ar1" and m["mode"] == o["mode"]
    assert m["params"] == o["params"] and m["score"] == o["score"] and m["accepted_by"] == o["accepted_by"] == "bic"
    assert last["ranking"]["missing"][0]["effect"] == "actuator.ar1"
