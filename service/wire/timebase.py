"""Time on the wire, in integer nanoseconds end to end: the sample period, a sample's payload
time ``k * Ts``, its publish time anchored at the stream's wall-clock start, and the attachment
that states that start (package docstring, "Time" and "Attachment")."""

from __future__ import annotations

import math
import operator
from numbers import Real

import numpy as np

from .contract import SEQ_MAX, START_MAX, WireError, check_seq, short
from .decode import loads


def period_ns(Ts: float) -> int:
    """Sample period in integer ns, ``round(Ts * 1e9)``; ``Ts`` in s, finite and > 0."""
    if isinstance(Ts, bool) or not isinstance(Ts, Real) or not math.isfinite(Ts) or Ts <= 0:
        raise WireError(f"sample period Ts={Ts!r} s must be a finite number > 0")
    Ts_ns = round(float(Ts) * 1e9)
    if Ts_ns < 1:
        raise WireError(f"sample period Ts={Ts!r} s is shorter than 1 ns")
    return Ts_ns


def publish_time_ns(k: int, Ts_ns: int) -> int:
    """Sample ``k``'s offset from its stream's start on the exact integer grid ``k * Ts_ns`` (ns,
    no float). It equals ``round(k * Ts * 1e9)`` (:func:`anchored_ns`'s offset) when Ts is a
    whole number of ns, and differs by at most ``k * |Ts*1e9 - Ts_ns|`` ns otherwise."""
    return check_seq(k, "sample index") * operator.index(Ts_ns)


def anchored_ns(start_time_ns: int, t: float) -> int:
    """MCAP publish_time of a sample of time ``t`` (s, from the stream's start) in a stream that
    started at ``start_time_ns``: ``start_time_ns + round(t * 1e9)``, an int within int64; a
    WireError when ``t`` is negative, not finite or too late for int64."""
    rel = t * 1e9
    if not (0.0 <= rel < 2.0**63):                      # NaN fails too
        raise WireError(f"t={t!r} s is not a sample time from 0 that fits in int64 ns")
    ns = operator.index(start_time_ns) + round(rel)
    if ns > SEQ_MAX:
        raise WireError(f"publish time {ns} ns (start {start_time_ns} + t={t!r} s) exceeds 2**63-1")
    return ns


def encode_anchor(start_time_ns: int) -> bytes:
    """The attachment of a sample of a stream that started at ``start_time_ns`` (int, Unix ns)."""
    if isinstance(start_time_ns, bool) or not isinstance(start_time_ns, int) \
            or not 0 <= start_time_ns <= START_MAX:
        raise WireError(f"start_time_ns={start_time_ns!r} must be an integer from 0 to 2**62 (ns)")
    return b'{"start_time_ns":%d}' % start_time_ns


def decode_anchor(data: bytes | bytearray | memoryview | str, *, topic: str | None = None) -> int:
    """``start_time_ns`` of a sample's attachment (:func:`encode_anchor`), or a WireError."""
    where = f"{topic or 'sample'} attachment"
    obj = loads(data, where)
    if not isinstance(obj, dict) or set(obj) != {"start_time_ns"}:
        raise WireError(f"{where}: must be an object with start_time_ns only")
    start = obj["start_time_ns"]
    if type(start) is not int or not 0 <= start <= START_MAX:
        raise WireError(f"{where}: start_time_ns={short(start)} is not an integer from 0 to 2**62")
    return start


def sample_time(k: int, Ts: float) -> float:
    """Payload ``t`` of sample ``k``: the float ``k * Ts`` in s."""
    return check_seq(k, "sample index") * float(Ts)


def sample_times(k0: int, n: int, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """``(t, publish_ns)`` of samples ``k0 .. k0+n-1``.

    ``t`` float64 in s, equal element by element to :func:`sample_time`; ``publish_ns`` int64
    in ns, equal to :func:`publish_time_ns` with ``Ts_ns = period_ns(Ts)``.
    """
    k0 = check_seq(k0, "sample index")
    Ts_ns = period_ns(Ts)
    k = np.arange(k0, k0 + operator.index(n), dtype=np.int64)
    return k.astype(np.float64) * float(Ts), k * np.int64(Ts_ns)


# ------------------------------------------------------------------------ encode
