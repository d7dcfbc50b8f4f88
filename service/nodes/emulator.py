"""The emulator node: steps a model in real time at Ts and publishes truth, command and
measurement over Zenoh (DESIGN.md wire contract), plus its loop health at 1 Hz.

Timing: absolute deadlines d_k = t_0 + k Ts_ns on the monotonic clock (integer ns), so errors do
not accumulate; the loop sleeps until ``spin`` before the deadline and spins the rest. It never
skips a sample: when it falls behind it catches up and counts an *overrun* (work for sample k
finished after d_{k+1}). Lateness is the wake-up time minus the deadline.

Time base (wire contract, "Time"): ``start_time_ns`` is the wall-clock time (Unix ns) at which
sample 0 is due, read once beside the monotonic clock that sets the deadlines; every data and
health sample carries it as its attachment, so a recorder writes publish_time = start_time_ns +
round(k Ts 1e9) on the same wall clock as its receive times, and a late joiner learns it from
its first sample. Puts say Zenoh encoding ``application/json;<schema name>``.

Data streams are published with congestion control BLOCK (a slow subscriber slows the loop,
which the health shows, instead of losing recorded data), without ``express`` (with a subscriber
attached it tripled the cost of the three puts, ~110 -> ~31 us, and bought no latency).

End of stream: when the loop ends (duration reached or stopped) the emulator publishes
``noiselab/<name>/end`` with the number of messages it published per topic and waits (at most
``end_timeout`` s) until every recorder has acknowledged it (:func:`transport.end_stream`), so
closing the session afterwards loses nothing that was still queued or in flight.

Closed loop (``[command] kind = "external"``): the emulator subscribes to
``noiselab/<name>/control`` and applies the latest command it has received (zero-order hold).
Until the first one arrives, and whenever the last is older than ``stale_s``, it applies zero and
says so (stderr, and ``late_control`` in the health). Staleness is judged on the loop's own
clock: sample k is stale when its deadline d_k is more than ``stale_s`` after the last control's
arrival (or after d_0 when none came), so a loop that runs late does not count its lateness as
the controller's. The applied command is published on the
``command`` topic, so `noiselab simulate` with that command and the same seed reproduces the
measurement exactly: the live path is the step API's path.

A control comes from the network: one that breaks the wire contract (including an element
beyond :data:`wire.MAGNITUDE_MAX`) or whose length is not the model's input count is rejected
(the previous command stays), counted (``rejected_controls``) and the first one said on stderr.
A sample with a state, command or measurement element that is not finite or beyond
:data:`wire.MAGNITUDE_MAX` (an unstable plant that has diverged; a plant whose gain takes an
accepted control past the bound) is not published: the emulator says so once, ends its stream
at the sample before (end of stream as usual) and reports the sample (``diverged_at``). So every
sample it publishes is within the bound that the analysis of a recording accepts.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import zenoh

from .. import wire
from ..recordings.errors import shown
from . import transport

SPIN_NS = 300_000          # spin the last 0.3 ms before a deadline (sleep overshoots ~0.1 ms)


@dataclass
class EmulatorSummary:
    name: str
    samples: int
    Ts: float
    seed: int
    lateness_us: dict
    overruns: int
    wall_s: float
    stale_control_events: int = 0
    keys: dict = field(default_factory=dict)
    end: dict = field(default_factory=dict)
    speed: float = 1.0
    rejected_controls: int = 0
    diverged_at: int | None = None
    start_time_ns: int = 0

    def as_dict(self) -> dict:
        return {"node": "emulate", "name": self.name, "samples": self.samples, "Ts": self.Ts, "seed": self.seed, "speed": self.speed,
                "start_time_ns": self.start_time_ns,
                "lateness_us": self.lateness_us, "overruns": self.overruns, "wall_s": self.wall_s,
                "stale_control_events": self.stale_control_events, "rejected_controls": self.rejected_controls,
                "diverged_at": self.diverged_at, "keys": self.keys, "end": self.end}


class _Control:
    """Latest control input (zero-order hold), written by the Zenoh thread, read by the loop."""

    def __init__(self, m: int, name: str, log, stale_s: float):
        self.lock = threading.Lock()
        self.u = np.zeros(m)
        self.rx_ns = None
        self.count = 0
        self.bad = 0
        self.name, self.log = name, log
        self.stale_s, self.stale_ns = stale_s, stale_s * 1e9
        self.stale = False               # the loop's view (its thread only): the last sample had no fresh control
        self.stale_events = 0

    def on_sample(self, sample) -> None:
        key = str(sample.key_expr)
        try:
            obj = wire.decode(sample.payload.to_bytes(), "control", topic=key)
            u = np.asarray(obj["u"], float)
            if u.shape != self.u.shape:
                raise wire.WireError(f"{key}: u has {u.size} elements at seq {obj['seq']}, the model {self.u.size} inputs")
        except wire.WireError as exc:
            self.bad += 1
            if self.bad == 1:
                print(f"noiselab emulate: {self.name}: rejected a control, the previous command stays "
                      f"(further ones counted in 'rejected_controls'): {shown(exc)}", file=self.log, flush=True)
            return
        with self.lock:
            self.u = u
            self.rx_ns = time.monotonic_ns()
            self.count += 1

    def at(self, deadline: int, start_ns: int, k: int) -> np.ndarray:
        """The input of sample ``k``, due at ``deadline`` (monotonic ns; the stream started at
        ``start_ns``): the latest control, or zero before the first one and while it is stale.
        Stale: older than the timeout at the sample's deadline (not at the time the loop, maybe
        running late, gets to it). A change either way is said on the log."""
        with self.lock:
            rx, u_last = self.rx_ns, self.u
        age_ns = deadline - (start_ns if rx is None else rx)
        is_stale = age_ns > self.stale_ns
        if is_stale and not self.stale:
            self.stale_events += 1
            age = "no control received yet" if rx is None else f"last control {age_ns / 1e9:.3f} s old"
            print(f"noiselab emulate: {self.name}: control input stale ({age}, timeout {self.stale_s:g} s): "
                  f"applying zero from sample {k}", file=self.log, flush=True)
        elif self.stale and not is_stale:
            print(f"noiselab emulate: {self.name}: control input back at sample {k}", file=self.log, flush=True)
        self.stale = is_stale
        return np.zeros(u_last.size) if (is_stale or rx is None) else u_last


def _percentiles(values_ns: list[int]) -> tuple[float, float, float]:
    if not values_ns:
        return 0.0, 0.0, 0.0
    a = np.asarray(values_ns, dtype=np.float64) / 1e3
    return float(np.percentile(a, 50)), float(np.percentile(a, 99)), float(a.max())


def run_emulator(model, session: "zenoh.Session", *, duration: float | None, seed: int = 0,
                 stop: threading.Event | None = None, wait_subscribers: float = 0.0,
                 stale_s: float = 0.5, wait_peers: int = 0, end_timeout: float = 10.0,
                 speed: float = 1.0, log=sys.stderr) -> EmulatorSummary:
    """Run the real-time loop until ``duration`` seconds of samples are out or ``stop`` is set.

    ``wait_subscribers`` > 0: wait up to that many seconds for a subscriber of the measurement
    before the first sample (so a recorder started alongside gets sample 0). ``wait_peers``: first
    wait until that many peers are connected (several sinks on separate links: a match tells
    only that one of them has subscribed; their subscriptions come with their session).
    ``end_timeout``: longest wait for the recorders' acknowledgement of the end of stream (0: do
    not wait; the last messages may then be lost when the session closes). ``speed``: samples come
    every Ts / speed of wall time (a faster-than-real-time run; sample times t and publish_time
    stay on the model's Ts grid, lateness and overruns are measured against the wall period)."""
    stop = stop or threading.Event()
    name, Ts = model.name, model.Ts
    Ts_ns = wire.period_ns(Ts)
    if not (speed > 0 and np.isfinite(speed)):
        raise ValueError(f"speed must be a finite number > 0, got {speed!r}")
    wall_ns = Ts_ns / speed                       # wall-clock period (float ns; deadlines rounded per sample)
    n_total = None if duration is None else max(1, round(duration / Ts))
    keys, pubs, health_pub = _declare(session, name)
    started = [-1, -1]            # the last sample / health report whose puts have begun
    data_keys = [keys[kind] for kind in wire.KINDS]

    def first_seqs() -> dict:
        return {**{key: started[0] + 1 for key in data_keys}, keys[wire.HEALTH]: started[1] + 1}

    join = transport.serve_join(session, name, first_seqs)
    external = model.command.kind == "external"
    control = _Control(model.m, name, log, stale_s) if external else None
    sub = session.declare_subscriber(keys[wire.CONTROL], control.on_sample) if external else None
    _wait_start(session, pubs["measurement"], wait_peers, wait_subscribers, stop, log)
    stepper = model.stepper(seed=seed)
    lat_all: list[int] = []
    lat_period: list[int] = []
    overruns = 0
    diverged_at = None
    health_every = max(1, round(speed / Ts))   # about 1 Hz of wall time
    health_seq = 0
    t0 = time.monotonic_ns() + 2_000_000          # first deadline 2 ms from now
    start_ns = t0
    start_time_ns = time.time_ns() + (t0 - time.monotonic_ns())   # the wall clock when sample 0 is due
    anchor = wire.encode_anchor(start_time_ns)
    k = 0
    mono = time.monotonic_ns
    try:
        # a diverging plant overflows to inf: _beyond stops the stream there and says so (no numpy warning)
        with np.errstate(over="ignore", invalid="ignore"):
            while not stop.is_set() and (n_total is None or k < n_total):
                deadline = t0 + int(round(k * wall_ns))
                late = _wait_until(deadline, mono)
                lat_all.append(late)
                lat_period.append(late)
                u = control.at(deadline, start_ns, k) if external else None
                t, x, u_applied, y = stepper.step(u)
                beyond = _beyond(x, u_applied, y)
                if beyond is not None:
                    diverged_at = k
                    print(f"noiselab emulate: {name}: sample {k} has {beyond}, not finite or beyond "
                          f"{wire.MAGNITUDE_MAX:g}: the plant has diverged; ending the stream here", file=log, flush=True)
                    break
                tk = wire.sample_time(k, Ts)
                _put_sample(pubs, keys, k, tk, (x, u_applied, y), anchor, started)
                if mono() > deadline + wall_ns:
                    overruns += 1
                k += 1
                if k % health_every == 0:
                    stats = _health(k, lat_period, overruns, external and control.stale)
                    lat_period = []
                    started[1] = health_seq
                    health_pub.put(wire.encode_health(health_seq, tk, stats), attachment=anchor)
                    health_seq += 1
    finally:
        if sub is not None:
            sub.undeclare()
        join.undeclare()
    wall_s = (mono() - start_ns) / 1e9
    end = _end_stream(session, pubs[wire.END], name, Ts, k, n_total, health_seq, end_timeout, log)
    p50, p99, mx = _percentiles(lat_all)
    return EmulatorSummary(name=name, samples=k, Ts=Ts, seed=seed, speed=speed,
                           lateness_us={"p50": p50, "p99": p99, "max": mx}, overruns=overruns,
                           wall_s=wall_s, stale_control_events=control.stale_events if external else 0,
                           rejected_controls=control.bad if external else 0, diverged_at=diverged_at,
                           start_time_ns=start_time_ns, keys={k_: v for k_, v in keys.items()}, end=end)


def _declare(session: zenoh.Session, name: str) -> tuple[dict, dict, object]:
    """The device's keys by kind, its publishers (the data streams and the end of stream, with the
    data QoS: reliable, blocking) and its health publisher (dropped under congestion: a health
    report is never worth slowing the samples for)."""
    keys = {kind: wire.key(name, kind) for kind in (*wire.KINDS, wire.HEALTH, wire.CONTROL, wire.END)}
    pubs = {kind: transport.declare_stream(session, keys[kind], kind, **transport.DATA_QOS)
            for kind in (*wire.KINDS, wire.END)}
    health_pub = transport.declare_stream(session, keys[wire.HEALTH], wire.HEALTH,
                                          congestion_control=zenoh.CongestionControl.DROP)
    return keys, pubs, health_pub


def _wait_start(session: zenoh.Session, measurement_pub, wait_peers: int, wait_subscribers: float,
                stop: threading.Event, log) -> None:
    """Before the first sample: wait for ``wait_peers`` peers, then for a subscriber of the
    measurement (:func:`run_emulator`); either wait running out is said, and the run starts anyway."""
    if wait_peers > 0 and not transport.wait_peers(session, wait_peers, max(wait_subscribers, 5.0), stop) \
            and not stop.is_set():
        print(f"noiselab emulate: fewer than {wait_peers} peers connected: starting anyway", file=log, flush=True)
    if wait_subscribers > 0 and not transport.wait_matching([measurement_pub], wait_subscribers, stop) \
            and not stop.is_set():
        print(f"noiselab emulate: no subscriber matched within "
              f"{wait_subscribers:g} s: starting anyway", file=log, flush=True)


def _wait_until(deadline: int, mono) -> int:
    """Sleep, then spin the last :data:`SPIN_NS`, until ``deadline`` (``mono()`` ns); how late the
    wake-up was, ns."""
    now = mono()
    if deadline - now > SPIN_NS:
        time.sleep((deadline - now - SPIN_NS) / 1e9)
    while mono() < deadline:
        pass
    return mono() - deadline


def _put_sample(pubs: dict, keys: dict, k: int, tk: float, vectors: tuple, anchor: bytes, started: list) -> None:
    """Sample ``k`` (time ``tk`` s; ``vectors`` = x, u, y) on its three streams, in the order of
    :data:`wire.KINDS`: the payloads are encoded first (a WireError sends none of them), then
    ``started[0] = k`` (the join point :func:`transport.serve_join` answers), then the puts."""
    payloads = [wire.encode(k, tk, v, kind=kind, topic=keys[kind]) for kind, v in zip(wire.KINDS, vectors)]
    started[0] = k
    for kind, payload in zip(wire.KINDS, payloads):
        pubs[kind].put(payload, attachment=anchor)


def _health(k: int, lat_period: list[int], overruns: int, stale: bool) -> dict:
    """The health report after ``k`` samples (:data:`wire.HEALTH_FIELDS`): the lateness of the
    report period's wake-ups (us), the overruns since the start, whether the control is stale."""
    p50, p99, mx = _percentiles(lat_period)
    return {"k": k, "lateness_p50_us": p50, "lateness_p99_us": p99, "lateness_max_us": mx,
            "overruns": overruns, "late_control": int(stale)}


def _end_stream(session: zenoh.Session, end_pub, name: str, Ts: float, k: int, n_total: int | None,
                health_seq: int, end_timeout: float, log) -> dict:
    """Publish the end of stream (``k`` samples of each data kind, ``health_seq`` health reports),
    wait for the recorders' acknowledgements (:func:`transport.end_stream`) and say what went
    wrong; what the acknowledgements said."""
    counts = {kind: k for kind in wire.KINDS}
    counts[wire.HEALTH] = health_seq
    reason = "duration" if n_total is not None and k >= n_total else "stopped"
    end = transport.end_stream(session, end_pub,
                               wire.encode_end(0, wire.sample_time(max(k - 1, 0), Ts), k, counts, reason),
                               end_timeout)
    _report_end(name, end, counts, end_timeout, log)
    return end


def _beyond(*vectors) -> str | None:
    """The first element of ``vectors`` (x, u, y of a sample) that is not finite or beyond
    :data:`wire.MAGNITUDE_MAX`, named (``"x[1] = inf"``); None when every one is within."""
    if np.abs(np.concatenate(vectors)).max(initial=0.0) <= wire.MAGNITUDE_MAX:   # NaN compares False
        return None
    for what, v in zip(("x", "u", "y"), vectors):
        bad = np.flatnonzero(~(np.abs(v) <= wire.MAGNITUDE_MAX))
        if bad.size:
            return f"{what}[{bad[0]}] = {float(v[bad[0]]):g}"
    return None


def _report_end(name: str, end: dict, counts: dict, timeout: float, log) -> None:
    """Say on ``log`` what went wrong at the end of the stream (nothing when every recorder has
    acknowledged every message); ``end["acks"]`` have a recorder's shape
    (:func:`transport.end_stream` checks them), the same error said once with its count."""
    if end["timed_out"]:
        print(f"noiselab emulate: {name}: end of stream not acknowledged by every recorder within "
              f"{timeout:g} s: the last messages may be lost", file=log, flush=True)
    errors: dict[str, int] = {}
    for err in end["errors"]:
        if err != "Timeout":
            errors[err] = errors.get(err, 0) + 1
    for err, n in errors.items():
        print(f"noiselab emulate: {name}: end of stream: {err}" + (f" ({n} answers)" if n > 1 else ""),
              file=log, flush=True)
    for ack in end["acks"]:
        short = {kind: t["missing"] for kind, t in ack["topics"].items() if kind in counts and t["missing"]}
        if short:
            print(f"noiselab emulate: {name}: recorder {shown(ack['out'])} lacks "
                  + ", ".join(f"{n} {kind}" for kind, n in short.items()), file=log, flush=True)
