"""The reference controller node: closes the loop of a model whose command is ``external``.

It subscribes to ``noiselab/<name>/measurement`` and answers every measurement y_k (seq k, time
t_k) with the PID law of :mod:`noiselab.model.controller` on ``noiselab/<name>/control``, a
payload with the measurement's own ``seq`` and ``t``: the control stream's seqs are the
measurements' it answers. The emulator applies the latest control it has received from its next
sample on (zero-order hold), so an answer on time to y_k is the command of sample k + 1; before
the first answer the emulator applies zero. Measurements are taken in arrival order, one at a
time, by the node's own thread (the Zenoh callback only queues them).

Loop health (wire kind ``controller_health``, :data:`wire.CONTROLLER_HEALTH_FIELDS`), published
after the first answer, about once a second of wall time, and at the end (so a recorder, which
takes a stream's first message once its successor confirms it, records even a short run's), and
the summary printed at exit:

* ``late_replies``: answers put after a newer measurement had already arrived. The emulator
  stepped that newer sample before the answer could reach it, so the answer came too late for
  the sample it was meant for (a lower bound on the late ones: an answer also takes time on its way).
* ``missing_measurements``: seqs skipped by a jump ahead (lost, or never sent), and the tail an
  end of stream counts that never came.
* ``stale_measurements``: a seq not past the last one answered (repeated, or out of order):
  skipped. A step back whose successor follows it at once (seq + 1) is a restarted source: the
  PID starts again from the successor.
* ``rejected_measurements``: a payload that breaks the wire contract, a vector that is not one
  element long, an element beyond :data:`wire.MAGNITUDE_MAX`, or one whose answer would be
  beyond it: skipped (the PID's state is left as it was), never a crash.
* latency: from a measurement's arrival to its answer's put, us (p50, p99, max).

End: when the emulator's end of stream (``noiselab/<name>/end``) arrives, every measurement before
it has arrived too (same link, in order) and has been answered (one it counts that has not is
waited for, at most :data:`END_LINGER_NS`, then booked missing): the node publishes its last
health report, asks the recorders to acknowledge what it sent (:func:`transport.ask_recorders`:
its answers to the last measurements are then on file, not lost when its session closes), and
returns. An end that counts fewer measurements than were answered is not its source's: rejected.
SIGINT/SIGTERM or ``duration`` stop it too.
"""

from __future__ import annotations

import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .. import wire
from ..model.controller import ControllerSpec, Pid
from ..recordings.errors import shown
from . import transport

READY_MARK = "noiselab control: subscribed"
INBOX_MAX = 1 << 16      # measurements queued at most; beyond, arrivals are dropped (and show as missing)
HEALTH_EVERY_NS = 1_000_000_000
FLUSH_TIMEOUT_S = 10.0
END_LINGER_NS = 500_000_000
"""After the end of stream, the longest wait for measurements it counts that have not arrived
(measurements and the end come on one link, in order: a bound, not a synchronisation)."""


@dataclass
class ControllerSummary:
    name: str
    answered: int = 0
    first_seq: int | None = None
    last_seq: int | None = None
    late_replies: int = 0
    missing_measurements: int = 0
    stale_measurements: int = 0
    rejected_measurements: int = 0
    restarts: int = 0
    latency_us: dict = field(default_factory=dict)
    health_messages: int = 0
    ended: str | None = None           # the end of stream's reason, None if it did not come
    recorders: dict = field(default_factory=dict)
    wall_s: float = 0.0
    gains: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"node": "control", **{k: getattr(self, k) for k in self.__dataclass_fields__}}


class _Inbox:
    """What the Zenoh callbacks received, in arrival order: (kind, payload, arrival ns, index)."""

    def __init__(self):
        self.cond = threading.Condition()
        self.items: deque = deque()
        self.arrived = 0                 # measurements queued so far
        self.dropped = 0

    def put(self, kind: str, sample) -> None:
        payload, rx = sample.payload.to_bytes(), time.monotonic_ns()
        with self.cond:
            if len(self.items) >= INBOX_MAX:
                self.dropped += 1
                return
            if kind == "measurement":
                self.arrived += 1
            self.items.append((kind, payload, rx, self.arrived))
            self.cond.notify()

    def get(self, stop: threading.Event, until_ns: int | None):
        with self.cond:
            while not self.items:
                if stop.is_set() or (until_ns is not None and time.monotonic_ns() >= until_ns):
                    return None
                self.cond.wait(0.05)
            return self.items.popleft()


class _Loop:
    """The controller's state between measurements (its thread only)."""

    def __init__(self, spec: ControllerSpec, model, summary: ControllerSummary, log):
        self.spec, self.model, self.s, self.log = spec, model, summary, log
        self.pid = Pid(spec, model.Ts)
        self.back: int | None = None        # a step back waiting for its successor (a restart?)
        self.lat: list[int] = []            # latencies of the current health period, ns
        self.lat_all: list[int] = []
        self.t_last = 0.0
        self.said: set[str] = set()

    def say_once(self, what: str, text: str) -> None:
        if what not in self.said:
            self.said.add(what)
            print(f"noiselab control: {self.s.name}: {shown(text)}", file=self.log, flush=True)

    def reject(self, text: str) -> None:
        self.s.rejected_measurements += 1
        self.say_once("reject", f"skipped a measurement (further ones counted in 'rejected_measurements'): {text}")

    def measurement(self, payload: bytes, topic: str):
        """The answer (seq, t, u) to one measurement, or None (skipped and counted)."""
        try:
            m = wire.decode(payload, "measurement", topic=topic)
        except wire.WireError as exc:
            self.reject(str(exc))
            return None
        seq, t, y = m["seq"], m["t"], m["y"]
        if len(y) != 1 or abs(y[0]) > wire.MAGNITUDE_MAX:
            self.reject(f"{topic}: y at seq {seq} is not one number within {wire.MAGNITUDE_MAX:g}")
            return None
        last = self.s.last_seq
        if last is not None and seq <= last:
            if self.back is not None and seq == self.back + 1:     # a step back confirmed: a new stream
                self.s.restarts += 1
                self.pid = Pid(self.spec, self.model.Ts)
                self.say_once("restart", f"{topic}: the stream restarted at seq {self.back}: the PID starts again")
                last = None
            else:
                self.back = seq
                self.s.stale_measurements += 1
                self.say_once("stale", f"{topic}: seq {seq} is not past the last answered {last}: skipped "
                                       "(further ones counted in 'stale_measurements')")
                return None
        self.back = None
        state = (self.pid.integral, self.pid.last)
        u = self.pid.step(seq, t, y[0])
        if not (np.isfinite(u) and abs(u) <= wire.MAGNITUDE_MAX):
            self.pid.integral, self.pid.last = state
            self.reject(f"{topic}: the answer to seq {seq} is {u!r}, beyond {wire.MAGNITUDE_MAX:g}")
            return None
        if last is not None and seq > last + 1:
            self.s.missing_measurements += seq - last - 1
        if self.s.first_seq is None:
            self.s.first_seq = seq
        self.s.last_seq = seq
        self.t_last = t
        return seq, t, u

    def health(self) -> dict:
        p50, p99, mx = _percentiles(self.lat)
        self.lat = []
        s = self.s
        return {"k": s.answered, "latency_p50_us": p50, "latency_p99_us": p99, "latency_max_us": mx,
                "late_replies": s.late_replies, "missing_measurements": s.missing_measurements,
                "stale_measurements": s.stale_measurements, "rejected_measurements": s.rejected_measurements}


def _percentiles(values_ns: list[int]) -> tuple[float, float, float]:
    if not values_ns:
        return 0.0, 0.0, 0.0
    a = np.asarray(values_ns, dtype=np.float64) / 1e3
    return float(np.percentile(a, 50)), float(np.percentile(a, 99)), float(a.max())


def run_controller(model, spec: ControllerSpec, session, *, duration: float | None = None,
                   stop: threading.Event | None = None, ready=None, flush_timeout: float = FLUSH_TIMEOUT_S,
                   log=sys.stderr) -> ControllerSummary:
    """Answer the measurements of ``model``'s device until its end of stream, ``stop``, or
    ``duration`` seconds of wall time; ``ready()`` is called once subscribed."""
    stop = stop or threading.Event()
    name = model.name
    keys = {kind: wire.key(name, kind) for kind in ("measurement", wire.END, wire.CONTROL, wire.CONTROLLER_HEALTH)}
    s = ControllerSummary(name=name, gains={"kp": spec.kp, "ki": spec.ki, "kd": spec.kd, "reference": spec.reference,
                                            "amplitude": spec.amplitude, "frequency_hz": spec.frequency_hz})
    loop = _Loop(spec, model, s, log)
    inbox = _Inbox()
    pub = transport.declare_stream(session, keys[wire.CONTROL], wire.CONTROL, **transport.DATA_QOS)
    hpub = transport.declare_stream(session, keys[wire.CONTROLLER_HEALTH], wire.CONTROLLER_HEALTH, **transport.DATA_QOS)
    health_seq = [0]

    def first_seqs() -> dict:              # the join point of the node's own topics (transport.serve_join)
        return {keys[wire.CONTROL]: (s.last_seq + 1) if s.last_seq is not None else 0,
                keys[wire.CONTROLLER_HEALTH]: health_seq[0]}

    join = transport.serve_join(session, name, first_seqs)
    subs = [session.declare_subscriber(keys["measurement"], lambda smp: inbox.put("measurement", smp)),
            session.declare_subscriber(keys[wire.END], lambda smp: inbox.put(wire.END, smp))]
    if ready is not None:
        ready()
    t0 = time.monotonic_ns()
    until = None if duration is None else t0 + int(duration * 1e9)
    next_health = t0 + HEALTH_EVERY_NS

    def put_health() -> None:
        hpub.put(wire.encode_controller_health(health_seq[0], loop.t_last, loop.health()))
        health_seq[0] += 1

    end = None                             # the stream's end of stream, once taken
    try:
        while (item := inbox.get(stop, until)) is not None:
            kind, payload, rx, index = item
            if kind == wire.END:
                if end is None and (end := _end(loop, payload, keys[wire.END])) is not None:
                    if _answered_all(s, end):
                        break
                    linger = time.monotonic_ns() + END_LINGER_NS
                    until = linger if until is None else min(until, linger)
                continue
            answer = loop.measurement(payload, keys["measurement"])
            if answer is not None:
                seq, t, u = answer
                pub.put(wire.encode(seq, t, [u], kind=wire.CONTROL, topic=keys[wire.CONTROL]))
                done = time.monotonic_ns()
                s.answered += 1
                with inbox.cond:
                    newer = inbox.arrived > index
                s.late_replies += newer
                loop.lat.append(done - rx)
                loop.lat_all.append(done - rx)
            if time.monotonic_ns() >= next_health or (answer is not None and s.answered == 1):
                put_health()
                next_health = time.monotonic_ns() + HEALTH_EVERY_NS
            if end is not None and _answered_all(s, end):
                break
        if end is not None:
            _ended(loop, end)
        s.missing_measurements += inbox.dropped
        put_health()
        if s.answered:
            s.recorders = transport.ask_recorders(session, keys[wire.END], None, flush_timeout)
    finally:
        for sub in subs:
            sub.undeclare()
        join.undeclare()
    p50, p99, mx = _percentiles(loop.lat_all)
    s.latency_us = {"p50": p50, "p99": p99, "max": mx}
    s.health_messages = health_seq[0]
    s.wall_s = (time.monotonic_ns() - t0) / 1e9
    return s


def _end(loop: _Loop, payload: bytes, topic: str) -> dict | None:
    """An end of stream: the decoded end when it can be the stream's, else None (rejected and
    counted: it counts fewer measurements than were answered)."""
    s = loop.s
    try:
        end = wire.decode_end(payload, topic=topic)
        count = end["counts"].get("measurement", 0)
        if s.last_seq is not None and count <= s.last_seq:
            raise wire.WireError(f"{topic}: an end counting {count} measurements, but seq {s.last_seq} was answered")
    except wire.WireError as exc:
        loop.reject(str(exc))
        return None
    return end


def _answered_all(s: ControllerSummary, end: dict) -> bool:
    return (s.last_seq if s.last_seq is not None else -1) + 1 >= end["counts"].get("measurement", 0)


def _ended(loop: _Loop, end: dict) -> None:
    """The stream has ended: the measurements it counts that were not answered are missing."""
    s = loop.s
    count = end["counts"].get("measurement", 0)
    s.missing_measurements += max(0, count - (s.last_seq + 1 if s.last_seq is not None else 0))
    s.ended = end["reason"]
    print(f"noiselab control: {wire.PREFIX}/{s.name} ended ({end['reason']}) after {end['samples']} samples: "
          f"answered {s.answered}", file=loop.log, flush=True)


def summary_line(s: ControllerSummary) -> str:
    lat = s.latency_us
    seqs = f" (seq {s.first_seq}..{s.last_seq})" if s.answered else ""
    return (f"controlled {s.name}: answered {s.answered} measurements{seqs} in {s.wall_s:.2f} s; "
            f"{s.late_replies} late replies, {s.missing_measurements} missing, {s.stale_measurements} stale, "
            f"{s.rejected_measurements} rejected; latency p50 {lat.get('p50', 0):.0f} us, "
            f"p99 {lat.get('p99', 0):.0f} us, max {lat.get('max', 0):.0f} us")
