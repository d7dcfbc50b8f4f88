"""Command signals u_c,k (the applied command before actuator effects), one column per input.

Kinds (``[command] kind``): ``sine`` (amplitude, frequency_hz, optional offset, phase_rad), ``step``
(amplitude, optional time_s, offset), ``chirp`` (amplitude, f0_hz, f1_hz, duration_s: linear sweep,
repeated), ``prbs`` (amplitude, bit_s, optional order = 7..15: a maximal-length LFSR sequence of
+-amplitude, deterministic), ``none`` (zero), ``external`` (commands arrive over Zenoh; zero offline
unless a command sequence is given, or a recorded one replayed: :func:`replay`). Amplitudes may be a list with one value per input.
Sample k is at t_k = k Ts.

In a sensor-only model (no [plant]) the command is the reference each output measures, one input
per output, in the outputs' units: a rate table's sine for a gyro, ``offset`` for gravity on an
accelerometer axis; ``none`` is a sensor at rest.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from .schema import Table

KINDS = ("sine", "step", "chirp", "prbs", "none", "external")

# Feedback taps of maximal-length Fibonacci LFSRs (x^order + x^tap + 1).
_PRBS_TAPS = {7: 6, 9: 5, 10: 7, 11: 9, 15: 14}


# Recorded commands an ``external`` command replays (:func:`replay`), by the digest of their bytes:
# a model's command is text (its file, and every edit of the diagnosis re-parses it), so the
# recording travels as its key, ``replay = "<digest>"``. The last few are kept (a diagnosis holds
# one; forked workers inherit them).
_REPLAYS: OrderedDict[str, np.ndarray] = OrderedDict()
_REPLAYS_KEPT = 8
_REPLAYS_LOCK = threading.Lock()


def replay(u: np.ndarray) -> str:
    """Register the recorded command ``u`` (N, m) and return its key, for an ``external``
    command's ``replay`` parameter: such a model's own command is then the record's (the
    nonlinearities' gains, the jitter's slope and the quantizer's spread are averaged over the
    command the record carries, not over zeros). Read-only copy; the last few are kept."""
    a = np.array(u, dtype=float, order="C")
    a = a.reshape(len(a), -1)
    key = hashlib.sha256(a.tobytes() + repr(a.shape).encode()).hexdigest()[:24]
    a.setflags(write=False)
    with _REPLAYS_LOCK:
        _REPLAYS[key] = a
        _REPLAYS.move_to_end(key)
        while len(_REPLAYS) > _REPLAYS_KEPT:
            _REPLAYS.popitem(last=False)
    return key


def replayed(key: str) -> np.ndarray | None:
    """The recorded command of ``key`` (:func:`replay`), or None."""
    with _REPLAYS_LOCK:
        return _REPLAYS.get(key)


@dataclass(frozen=True)
class Command:
    kind: str
    m: int
    params: dict = field(default_factory=dict)

    def values(self, k0: int, n: int, Ts: float) -> np.ndarray:
        """Commands for samples k0 .. k0+n-1, shape (n, m)."""
        k = np.arange(k0, k0 + n, dtype=np.float64)
        t = k * Ts
        p = self.params
        if self.kind == "external" and "replay" in p:
            # the recorded command; zero beyond its end, as before its start
            rec, out = replayed(p["replay"]), np.zeros((n, self.m))
            lo, hi = max(k0, 0), min(k0 + n, 0 if rec is None else rec.shape[0])
            if hi > lo:
                out[lo - k0:hi - k0] = rec[lo:hi]
            return out
        if self.kind in ("none", "external"):
            return np.zeros((n, self.m))
        if self.kind == "sine":
            arg = 2.0 * np.pi * np.outer(t, p["frequency_hz"]) + p["phase_rad"]
            return p["offset"] + p["amplitude"] * np.sin(arg)
        if self.kind == "step":
            on = (t >= p["time_s"]).astype(float)[:, None]
            return p["offset"] + p["amplitude"] * on
        if self.kind == "chirp":
            T = p["duration_s"]
            tau = np.mod(t, T)[:, None]
            f0, f1 = p["f0_hz"], p["f1_hz"]
            phase = 2.0 * np.pi * (f0 * tau + 0.5 * (f1 - f0) / T * tau**2)
            return p["amplitude"] * np.sin(phase)
        if self.kind == "prbs":
            bits = prbs_bits(p["order"])
            idx = np.floor(t / p["bit_s"] + 1e-9).astype(np.int64) % bits.size
            return p["amplitude"] * (2.0 * bits[idx] - 1.0)[:, None]
        raise AssertionError(self.kind)  # unreachable: kinds are validated


def prbs_bits(order: int) -> np.ndarray:
    """One period (2^order - 1 bits) of a maximal-length LFSR sequence, as 0/1."""
    tap = _PRBS_TAPS[order]
    state = [1] * order
    out = np.empty(2**order - 1)
    for i in range(out.size):
        bit = state[order - 1] ^ state[tap - 1]
        out[i] = state[order - 1]
        state = [bit] + state[:-1]
    return out


def parse_command(t: Table | None, m: int, Ts: float) -> Command:
    if t is None:
        return Command("none", m)
    kind = t.string("kind", "none", choices=KINDS)
    p: dict = {}
    if kind == "sine":
        p["amplitude"] = t.vector("amplitude", m)
        p["frequency_hz"] = t.vector("frequency_hz", m, check=lambda v: bool(np.all(v >= 0)),
                                     expect="frequencies in Hz >= 0")
        p["offset"] = t.vector("offset", m, 0.0)
        p["phase_rad"] = t.vector("phase_rad", m, 0.0)
    elif kind == "step":
        p["amplitude"] = t.vector("amplitude", m)
        p["time_s"] = t.number("time_s", 0.0)
        p["offset"] = t.vector("offset", m, 0.0)
    elif kind == "chirp":
        p["amplitude"] = t.vector("amplitude", m)
        p["f0_hz"] = t.number("f0_hz", check=lambda v: v >= 0, expect="a frequency in Hz >= 0")
        p["f1_hz"] = t.number("f1_hz", check=lambda v: v >= 0, expect="a frequency in Hz >= 0")
        p["duration_s"] = t.number("duration_s", check=lambda v: v > 0, expect="a sweep duration in s > 0")
    elif kind == "prbs":
        p["amplitude"] = t.vector("amplitude", m)
        # a bit shorter than a sample is held for no sample (and t / bit_s would leave int64)
        p["bit_s"] = t.number("bit_s", check=lambda v: v >= Ts, expect=f"a bit duration in s >= Ts = {Ts:g}")
        p["order"] = t.integer("order", 9, check=lambda v: v in _PRBS_TAPS,
                               expect=f"one of {sorted(_PRBS_TAPS)}")
    elif kind == "external" and t.has("replay"):
        # internal (the diagnosis' replay of a record's command, :func:`replay`), never in a file
        # a user writes: only a key this process registered, of m inputs
        key = t.string("replay", pattern=lambda v: (replayed(v) is not None and replayed(v).shape[1] == m),
                       expect="the key of a command recorded in this process (an internal parameter)")
        p["replay"] = key
    t.done()
    return Command(kind, m, p)
