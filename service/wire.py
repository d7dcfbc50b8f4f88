"""The wire contract of noiselab, in one place: Zenoh keys, JSON payloads, JSON Schemas, time.

Every other node imports its keys, schemas, encoders and time conventions from here; nothing
else builds a key or a payload by hand (DESIGN.md, "Wire contract (Zenoh and MCAP)").

Keys
    ``noiselab/<name>/<kind>`` with ``<name>`` matching ``[A-Za-z0-9_-]+`` and ``<kind>`` one of
    :data:`KINDS`. MCAP topics are the same strings (no leading ``/``); readers also accept a
    leading ``/`` (see :func:`parse_key`).

Payload (UTF-8 JSON object, compact, key order ``seq``, ``t``, vector)
    ``seq``  int >= 0, per topic, from 0, consecutive (a missing number is a lost message).
    (``health`` payloads carry ``seq``, ``t`` and the loop statistics of :func:`health_schema`.)
    ``t``    float, seconds: the nominal sample time ``k * Ts`` since the stream started.
    vector   list of float: ``x`` (truth state) for ``truth``, ``u`` (applied command) for
             ``command``, ``y`` (measurement) for ``measurement``; see :data:`VECTOR_FIELD`.
    Floats are written with ``float.__repr__`` (shortest round-trip form), exactly as
    ``json.dumps(..., separators=(",", ":"))`` writes them, so a decoded float is bit-identical
    to the encoded one. NaN and +-inf are not JSON and are refused (:class:`WireError`).

Untrusted input (a payload comes from any peer on the network, or from a file)
    Every decoder checks the bounds below on the raw bytes BEFORE parsing, so no payload can
    make the parser recurse or allocate without limit; a payload beyond them is a WireError.
    ``MAX_PAYLOAD_BYTES`` (1 MiB): a noiselab payload is ~25 bytes per vector element, so a
    vector of some 40,000 elements, or an analysis summary (a few kB), fits many times over.
    ``MAX_DEPTH`` (32 nested arrays/objects): a sample is 2 deep, an analysis summary 6.
    ``seq`` must fit in int64 (:data:`SEQ_MAX`: every reader stores it so). A ``control``
    element must not exceed :data:`MAGNITUDE_MAX` in magnitude (it drives a simulation; the one
    bound of :mod:`service.bounds`, 1e50, which the models, the emulator's output, the recordings'
    loader and the live analyzer share). What the bytes cannot tell (a vector's length, a seq
    that does not continue its stream) is judged by the node that knows the stream, with
    :class:`service.nodes.seqgate.SeqGate`.

Time (integer nanoseconds end to end, STYLE.md 13)
    ``Ts_ns = round(Ts * 1e9)`` once (:func:`period_ns`). The payload ``t`` is the float
    ``k * Ts`` (:func:`sample_time`), the model's clock, from 0 at the stream's first sample.
    A live stream is anchored at its run's wall-clock start: ``start_time_ns``, the Unix-epoch
    time in integer ns at which sample 0 was due, stated by the source in every sample's
    attachment (below). The MCAP ``publish_time`` of sample k is ``start_time_ns +
    round(k * Ts * 1e9)`` (:func:`anchored_ns`, from the payload's ``t``), so viewers show the
    real date and ``publish_time`` and the recorder's wall-clock ``log_time`` share one time
    base; the recording's ``noiselab`` metadata record holds ``start_time_ns`` as a decimal
    string. A stream whose source states no anchor (a foreign publisher) is anchored by the
    recorder at its first sample's arrival, ``max(0, log_time - round(t * 1e9))``: the same
    time base, the latency of that one sample off.

Attachment of a sample (Zenoh, optional; a wire extension)
    ``{"start_time_ns":N}`` (compact UTF-8 JSON, :func:`encode_anchor`): N, int, 0 <= N <=
    :data:`START_MAX`, the stream's wall-clock start as above. A source sends it on every data
    and health sample, so a recorder that joins late learns it from whatever it receives first.
    A sample without one is as valid as ever; a malformed one is ignored (counted), never the
    sample with it.

Zenoh encoding
    Every noiselab put says ``application/json;<schema name>`` (:func:`zenoh_encoding`, e.g.
    ``application/json;noiselab.Measurement``), so a generic Zenoh tool decodes the payload.
    Receivers do not require it: a foreign publisher's ``zenoh/bytes`` sample with a valid
    payload is taken the same.
"""

from __future__ import annotations

import json
import math
import operator
import re
import sys
from collections.abc import Iterable, Sequence
from numbers import Real

import numpy as np

from .bounds import MAGNITUDE_MAX

__all__ = [
    "ALL_KINDS",
    "CONTROL",
    "HEALTH",
    "HEALTH_FIELDS",
    "KINDS",
    "SCHEMA_ENCODING",
    "MESSAGE_ENCODING",
    "SCHEMA_NAMES",
    "VECTOR_FIELD",
    "MAGNITUDE_MAX",
    "MAX_DEPTH",
    "MAX_PAYLOAD_BYTES",
    "SEQ_MAX",
    "WireError",
    "check_name",
    "decode",
    "decode_health",
    "decode_end",
    "encode_end",
    "end_schema",
    "END",
    "encode_health",
    "health_schema",
    "decode_batch",
    "decode_packed",
    "encode",
    "encode_batch",
    "key",
    "loads",
    "nesting_depth",
    "parse_key",
    "period_ns",
    "publish_time_ns",
    "START_MAX",
    "anchored_ns",
    "decode_anchor",
    "encode_anchor",
    "zenoh_encoding",
    "sample_time",
    "sample_times",
    "schema",
    "schema_bytes",
]

PREFIX = "noiselab"
"""First segment of every noiselab key."""

KINDS: tuple[str, ...] = ("truth", "command", "measurement")
"""Topic kinds of a device's data streams, in the order a sample is produced."""

CONTROL = "control"
"""Closed loop: a controller publishes the command it wants on ``noiselab/<name>/control``
(vector ``u``); the emulator applies the latest one (zero-order hold)."""

HEALTH = "health"
"""The emulator's loop timing at a low rate on ``noiselab/<name>/health`` (not a vector)."""

ANALYSIS = "analysis"
"""The live analyzer's summary on ``noiselab/<name>/analysis`` (a JSON object with seq, t, the
model error, per-view errors and regions; see README 'Analysis')."""

END = "end"
"""End of stream on ``noiselab/<name>/end``: a source (the emulator) publishes it once, after its
last sample, with the number of messages it published per topic (see :func:`encode_end`), then
asks the recorders (a query on the same key) to acknowledge it before it closes its session."""

ALL_KINDS: tuple[str, ...] = KINDS + (CONTROL, HEALTH, ANALYSIS, END)

VECTOR_FIELD: dict[str, str] = {"truth": "x", "command": "u", "measurement": "y", "control": "u"}
"""Payload field holding the vector, per vector kind."""

SCHEMA_NAMES: dict[str, str] = {
    "truth": "noiselab.Truth",
    "command": "noiselab.Command",
    "measurement": "noiselab.Measurement",
    "control": "noiselab.Control",
    "health": "noiselab.Health",
    "analysis": "noiselab.Analysis",
    "end": "noiselab.End",
}
"""MCAP schema name per kind."""

SCHEMA_ENCODING = "jsonschema"
"""MCAP schema encoding of the registered schemas."""

MESSAGE_ENCODING = "json"
"""MCAP message encoding of every noiselab channel."""

_NAME_RE = re.compile(r"[A-Za-z0-9_-]+")
_VECTOR_DESCRIPTION = {
    "truth": "true plant state x_k (units of the model's states)",
    "command": "applied command u_k (units of the plant input)",
    "measurement": "measurement y_k (units of the model's outputs)",
    "control": "command requested by a controller (units of the plant input)",
}


class WireError(ValueError):
    """A key, payload or timestamp that breaks the wire contract (one-line message)."""


MAX_PAYLOAD_BYTES = 1 << 20
"""Largest payload a decoder parses, bytes (a sample is ~25 bytes per vector element)."""

MAX_DEPTH = 32
"""Deepest nesting of arrays and objects a decoder parses (a sample: 2, an analysis summary: 6);
far below the depth at which Python's JSON parser recurses out of its stack (~1000)."""

SEQ_MAX = 2**63 - 1
"""Largest ``seq``: readers hold seqs in int64 arrays."""

START_MAX = 2**62
"""Largest ``start_time_ns`` a stream may state (the year 2116): its publish times, ``start +
round(t * 1e9)``, stay within int64 for some 146 years of samples."""

ZENOH_JSON = "application/json"
"""The Zenoh encoding of every noiselab payload; its schema suffix names the payload's schema."""


def zenoh_encoding(kind: str) -> str:
    """The Zenoh encoding of a ``kind`` payload, ``application/json;<schema name>`` (Zenoh
    accepts the string wherever it takes an Encoding)."""
    return f"{ZENOH_JSON};{SCHEMA_NAMES[_check_kind(kind)]}"



# --------------------------------------------------------------------------- keys


def check_name(name: str) -> str:
    """Return ``name`` if it is a valid device name (``[A-Za-z0-9_-]+``), else raise WireError."""
    if not isinstance(name, str) or _NAME_RE.fullmatch(name) is None:
        raise WireError(f"device name {name!r} is invalid: use letters, digits, '_' or '-' only")
    return name


def _check_kind(kind: str) -> str:
    """A known topic kind (vector kinds and ``health``)."""
    if kind not in ALL_KINDS:
        raise WireError(f"topic kind {kind!r} is unknown: expected one of {', '.join(ALL_KINDS)}")
    return kind


def _vector_field(kind: str) -> str:
    """The vector field of a vector kind (``health`` and ``analysis`` are not)."""
    if _check_kind(kind) in (HEALTH, ANALYSIS, END):
        raise WireError(f"{kind} payloads are not vectors: use encode_{kind}/decode_{kind}")
    return VECTOR_FIELD[kind]


def key(name: str, kind: str) -> str:
    """Zenoh key expression (and MCAP topic) ``noiselab/<name>/<kind>`` of one stream."""
    return f"{PREFIX}/{check_name(name)}/{_check_kind(kind)}"


def parse_key(key_expr: str) -> tuple[str, str]:
    """Split ``[/]noiselab/<name>/<kind>`` into ``(name, kind)``; a leading ``/`` is accepted."""
    parts = key_expr.lstrip("/").split("/") if isinstance(key_expr, str) else []
    if len(parts) != 3 or parts[0] != PREFIX:
        raise WireError(f"key {key_expr!r} is not of the form noiselab/<name>/<kind>")
    return check_name(parts[1]), _check_kind(parts[2])


# ------------------------------------------------------------------------- schemas


def schema(kind: str) -> dict:
    """JSON Schema (draft 2020-12) of a payload of ``kind``, as a fresh dict."""
    if _check_kind(kind) == HEALTH:
        return health_schema()
    if kind == ANALYSIS:
        return analysis_schema()
    if kind == END:
        return end_schema()
    field = VECTOR_FIELD[kind]
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": SCHEMA_NAMES[kind],
        "description": f"noiselab {kind} sample; see DESIGN.md 'Wire contract'",
        "type": "object",
        "properties": {
            "seq": {
                "type": "integer",
                "minimum": 0,
                "description": "per-topic message counter, from 0, consecutive",
            },
            "t": {
                "type": "number",
                "description": "nominal sample time k*Ts, in s since the stream started",
            },
            field: {
                "type": "array",
                "items": {"type": "number"},
                "description": _VECTOR_DESCRIPTION[kind],
            },
        },
        "required": ["seq", "t", field],
        "additionalProperties": False,
    }


HEALTH_FIELDS: dict[str, str] = {
    "k": "samples stepped so far",
    "lateness_p50_us": "median wake-up lateness behind the absolute deadline k*Ts, us, over the last report period",
    "lateness_p99_us": "99th percentile of that lateness, us",
    "lateness_max_us": "largest lateness, us",
    "overruns": "samples (since start) whose work finished after the next deadline",
    "late_control": "1 when the last control input is older than the stale timeout (zero is applied), else 0",
}


def health_schema() -> dict:
    """JSON Schema of the emulator's health payload (``seq``, ``t`` and :data:`HEALTH_FIELDS`)."""
    props = {"seq": {"type": "integer", "minimum": 0, "description": "per-topic counter"},
             "t": {"type": "number", "description": "nominal time (k-1)*Ts of the last sample stepped, s"}}
    for name, desc in HEALTH_FIELDS.items():
        props[name] = {"type": "number", "description": desc}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": SCHEMA_NAMES[HEALTH],
        "description": "noiselab emulator loop health; see README 'Live pipeline'",
        "type": "object",
        "properties": props,
        "required": ["seq", "t", *HEALTH_FIELDS],
        "additionalProperties": False,
    }


def encode_health(seq: int, t: float, stats: dict) -> bytes:
    """Compact JSON health payload; ``stats`` holds exactly :data:`HEALTH_FIELDS` (finite)."""
    if set(stats) != set(HEALTH_FIELDS):
        raise WireError(f"health payload needs exactly {sorted(HEALTH_FIELDS)}, got {sorted(stats)}")
    obj = {"seq": _check_seq(seq), "t": float(t)}
    for name in HEALTH_FIELDS:
        v = stats[name]
        if isinstance(v, bool) or not isinstance(v, Real) or not math.isfinite(v):
            raise WireError(f"health field {name}={v!r} is not a finite number")
        obj[name] = v if isinstance(v, int) else float(v)
    return json.dumps(obj, separators=(",", ":")).encode()


def decode_health(data: bytes | bytearray | memoryview | str, *, topic: str | None = None) -> dict:
    """Parse and validate a health payload."""
    where = topic or "health topic"
    obj = loads(data, where)
    if not isinstance(obj, dict) or set(obj) != {"seq", "t", *HEALTH_FIELDS}:
        raise WireError(f"{where}: health payload must have keys seq, t, {', '.join(HEALTH_FIELDS)}")
    _check_seq_field(obj, where)
    for name in ("t", *HEALTH_FIELDS):
        v = obj[name]
        if not _finite(v):
            raise WireError(f"{where}: {name}={_short(v)} is not a finite number")
    return obj


def analysis_schema() -> dict:
    """JSON Schema of the live analyzer's summary (open: more fields may be added)."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": SCHEMA_NAMES[ANALYSIS],
        "description": "noiselab live analysis summary; see README 'Analysis'",
        "type": "object",
        "properties": {
            "seq": {"type": "integer", "minimum": 0, "description": "per-topic counter"},
            "t": {"type": "number", "description": "time of the last analysed sample, s"},
            "revision": {"type": "integer", "description": "model revision (hot reloads)"},
            "error": {"type": "number", "description": "the model error (about 1: model explains the data)"},
            "error_per_view": {"type": "object"},
            "samples": {"type": "integer"},
            "regions": {"type": "array"},
        },
        "required": ["seq", "t", "revision", "error", "error_per_view", "samples", "regions"],
    }


def encode_analysis(seq: int, t: float, summary: dict) -> bytes:
    obj = {"seq": _check_seq(seq), "t": float(t), **summary}
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
    except ValueError as exc:
        raise WireError(f"analysis summary: {exc}") from None


def decode_analysis(data, *, topic: str | None = None) -> dict:
    where = topic or "analysis topic"
    obj = loads(data, where)
    if not isinstance(obj, dict) or not {"seq", "t", "error"} <= set(obj):
        raise WireError(f"{where}: analysis payload must be an object with seq, t, error")
    _check_seq_field(obj, where)
    if not _finite(obj["t"]):
        raise WireError(f"{where}: t={_short(obj['t'])} in an analysis payload is not a finite number")
    return obj


END_REASONS = ("duration", "stopped")


def end_schema() -> dict:
    """JSON Schema of the end-of-stream message (README 'Live pipeline', wire extension)."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": SCHEMA_NAMES[END],
        "description": "noiselab end of stream: what the source published; see README 'Live pipeline'",
        "type": "object",
        "properties": {
            "seq": {"type": "integer", "minimum": 0, "description": "per-topic counter (one per stream)"},
            "t": {"type": "number", "description": "nominal time of the last sample, s (0 if none)"},
            "samples": {"type": "integer", "minimum": 0, "description": "samples the source stepped"},
            "counts": {"type": "object", "additionalProperties": {"type": "integer", "minimum": 0},
                       "description": "messages published per topic kind (seq 0..count-1 each)"},
            "reason": {"enum": list(END_REASONS), "description": "duration reached, or stopped"},
        },
        "required": ["seq", "t", "samples", "counts", "reason"],
        "additionalProperties": False,
    }


def encode_end(seq: int, t: float, samples: int, counts: dict, reason: str) -> bytes:
    """Compact JSON end-of-stream payload; ``counts`` maps topic kinds to messages published."""
    if reason not in END_REASONS:
        raise WireError(f"end reason {reason!r} is not one of {', '.join(END_REASONS)}")
    if not isinstance(counts, dict) or not all(k in ALL_KINDS for k in counts):
        raise WireError(f"end counts must map topic kinds to counts, got {counts!r}")
    obj = {"seq": _check_seq(seq), "t": float(t), "samples": _check_seq(samples, "samples"),
           "counts": {k: _check_seq(v, f"count of {k}") for k, v in counts.items()}, "reason": reason}
    if not math.isfinite(obj["t"]):
        raise WireError(f"end t={t!r} is not finite")
    return json.dumps(obj, separators=(",", ":")).encode()


def decode_end(data, *, topic: str | None = None) -> dict:
    """Parse and validate an end-of-stream payload (:func:`end_schema`)."""
    where = topic or "end topic"
    obj = loads(data, where)
    if not isinstance(obj, dict) or set(obj) != {"seq", "t", "samples", "counts", "reason"}:
        raise WireError(f"{where}: end payload must have keys seq, t, samples, counts, reason")
    for name in ("seq", "samples"):
        if type(obj[name]) is not int or not 0 <= obj[name] <= SEQ_MAX:
            raise WireError(f"{where}: {name}={_short(obj[name])} is not an integer from 0 to 2**63-1")
    if not _finite(obj["t"]):
        raise WireError(f"{where}: t={_short(obj['t'])} is not a finite number")
    counts = obj["counts"]
    if not isinstance(counts, dict) or not all(k in ALL_KINDS and type(v) is int and 0 <= v <= SEQ_MAX
                                               for k, v in counts.items()):
        raise WireError(f"{where}: counts must map topic kinds to integers >= 0, got {_short(counts)}")
    if type(obj["reason"]) is not str or obj["reason"] not in END_REASONS:
        raise WireError(f"{where}: reason={_short(obj['reason'])} is not one of {', '.join(END_REASONS)}")
    obj["t"] = float(obj["t"])
    return obj


def schema_bytes(kind: str) -> bytes:
    """:func:`schema` serialised as the UTF-8 bytes registered in MCAP (deterministic)."""
    return json.dumps(schema(kind), separators=(",", ":")).encode()


# -------------------------------------------------------------------------- time


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
    return _check_seq(k, "sample index") * operator.index(Ts_ns)


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
        raise WireError(f"{where}: start_time_ns={_short(start)} is not an integer from 0 to 2**62")
    return start


def sample_time(k: int, Ts: float) -> float:
    """Payload ``t`` of sample ``k``: the float ``k * Ts`` in s."""
    return _check_seq(k, "sample index") * float(Ts)


def sample_times(k0: int, n: int, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """``(t, publish_ns)`` of samples ``k0 .. k0+n-1``.

    ``t`` float64 in s, equal element by element to :func:`sample_time`; ``publish_ns`` int64
    in ns, equal to :func:`publish_time_ns` with ``Ts_ns = period_ns(Ts)``.
    """
    k0 = _check_seq(k0, "sample index")
    Ts_ns = period_ns(Ts)
    k = np.arange(k0, k0 + operator.index(n), dtype=np.int64)
    return k.astype(np.float64) * float(Ts), k * np.int64(Ts_ns)


# ------------------------------------------------------------------------ encode


def _check_seq(seq: int, what: str = "seq") -> int:
    if isinstance(seq, bool):
        raise WireError(f"{what} must be an integer >= 0, got {seq!r}")
    try:
        seq = operator.index(seq)
    except TypeError:
        raise WireError(f"{what} must be an integer >= 0, got {seq!r}") from None
    if not 0 <= seq <= SEQ_MAX:
        raise WireError(f"{what} must be an integer from 0 to 2**63-1, got {seq}")
    return seq


def _where(kind: str, topic: str | None) -> str:
    return topic if topic is not None else f"{kind} topic"


def _vector(vec, kind: str, topic: str | None) -> list[float]:
    """The vector as a list of Python floats (numbers only: no str, bool or nested lists)."""
    field = VECTOR_FIELD[kind]
    if isinstance(vec, np.ndarray):
        if vec.ndim != 1 or vec.dtype.kind not in "fiu":
            raise WireError(
                f"{_where(kind, topic)}: {field} must be a 1-D numeric array, "
                f"got shape {vec.shape} dtype {vec.dtype}"
            )
        return [float(v) for v in vec.tolist()]
    if isinstance(vec, (str, bytes)) or not isinstance(vec, Iterable):
        raise WireError(f"{_where(kind, topic)}: {field} must be a sequence of numbers")
    out = []
    for i, v in enumerate(vec):
        if isinstance(v, bool) or not isinstance(v, Real):
            raise WireError(f"{_where(kind, topic)}: {field}[{i}]={v!r} is not a number")
        out.append(float(v))
    return out


def encode(seq: int, t: float, vec: Sequence[float] | np.ndarray, *, kind: str,
           topic: str | None = None) -> bytes:
    """One payload ``{"seq":seq,"t":t,"<x|u|y>":[...]}`` as compact UTF-8 JSON bytes.

    ``seq`` int >= 0; ``t`` in s (finite); ``vec`` the vector of ``kind`` (its field name is
    ``VECTOR_FIELD[kind]``). The bytes equal ``json.dumps(obj, separators=(",", ":")).encode()``
    with every number of ``vec`` converted to float. ``topic`` (the key) only names the culprit
    in errors. Raises WireError for a bad seq, a non-number, or NaN/inf anywhere.
    """
    field = _vector_field(kind)
    seq = _check_seq(seq)
    if isinstance(t, bool) or not isinstance(t, Real):
        raise WireError(f"{_where(kind, topic)}: t={t!r} is not a number (seq {seq})")
    t = float(t)
    vals = _vector(vec, kind, topic)
    nums = ",".join(map(float.__repr__, vals))
    # Finite float reprs use only digits . e + -: an 'n' means inf or nan somewhere.
    if "n" in nums or not math.isfinite(t):
        _raise_non_finite(kind, topic, seq, t, vals)
    if kind == CONTROL and vals and max(map(abs, vals)) > MAGNITUDE_MAX:
        _raise_too_large(topic, seq, vals)
    return f'{{"seq":{seq},"t":{t!r},"{field}":[{nums}]}}'.encode()


def _raise_too_large(topic, seq, vals):
    i = next(i for i, v in enumerate(vals) if abs(v) > MAGNITUDE_MAX)
    raise WireError(f"{_where(CONTROL, topic)}: u[{i}]={vals[i]!r} at seq {seq} exceeds "
                    f"{MAGNITUDE_MAX:g} in magnitude")


def _raise_non_finite(kind, topic, seq, t, vals):
    if not math.isfinite(t):
        raise WireError(f"{_where(kind, topic)}: t={t!r} at seq {seq} is not finite; "
                        "NaN/inf are not valid JSON")
    i = next(i for i, v in enumerate(vals) if not math.isfinite(v))
    raise WireError(f"{_where(kind, topic)}: {VECTOR_FIELD[kind]}[{i}]={vals[i]!r} at seq {seq} "
                    "is not finite; NaN/inf are not valid JSON")


def encode_batch(kind: str, seq0: int, t_array, mat, *,
                 topic: str | None = None) -> list[bytes]:
    """Payloads of ``N`` consecutive samples: seq ``seq0 .. seq0+N-1``.

    ``t_array`` (N,) in s; ``mat`` (N, dim), row i is the vector of sample i. Element by element
    the result equals ``[encode(seq0 + i, t_array[i], mat[i], kind=kind) ...]``; it formats each
    message with a single bytes %-format in C (about 3x faster than ``json.dumps`` per message;
    the remaining cost is ``float.__repr__`` itself). Raises WireError (naming ``topic``, the
    seq and the element) if anything is NaN/inf or the shapes disagree.
    """
    field = _vector_field(kind)
    seq0 = _check_seq(seq0, "seq0")
    t_arr = np.asarray(t_array)
    m = np.asarray(mat)
    if t_arr.dtype.kind not in "fiu" or m.dtype.kind not in "fiu":
        raise WireError(f"{_where(kind, topic)}: t and {field} must be numeric arrays, "
                        f"got dtypes {t_arr.dtype} and {m.dtype}")
    if t_arr.ndim != 1 or m.ndim != 2 or m.shape[0] != t_arr.shape[0]:
        raise WireError(f"{_where(kind, topic)}: expected t of shape (N,) and {field} of shape "
                        f"(N, dim), got {t_arr.shape} and {m.shape}")
    t_arr = t_arr.astype(np.float64, copy=False)
    m = m.astype(np.float64, copy=False)
    n, dim = m.shape
    bad_t = ~np.isfinite(t_arr)
    bad_m = ~np.isfinite(m)
    if bad_t.any() or bad_m.any():
        row = int(np.argmax(bad_t | bad_m.any(axis=1)))
        _raise_non_finite(kind, topic, seq0 + row, float(t_arr[row]), m[row].tolist())
    if kind == CONTROL and m.size and np.abs(m).max() > MAGNITUDE_MAX:
        row = int(np.argmax((np.abs(m) > MAGNITUDE_MAX).any(axis=1)))
        _raise_too_large(topic, seq0 + row, m[row].tolist())
    if n and seq0 + n - 1 > SEQ_MAX:
        raise WireError(f"{_where(kind, topic)}: seq {seq0 + n - 1} exceeds 2**63-1")
    fmt = ('{"seq":%d,"t":%r,"' + field + '":[' + ",".join(["%r"] * dim) + "]}").encode()
    # tolist() yields Python floats, whose %r is float.__repr__ (numpy scalars would print
    # "np.float64(...)"); zip builds the argument tuple of each row without a Python loop body.
    return [fmt % row for row in zip(range(seq0, seq0 + n), t_arr.tolist(), *m.T.tolist())]


# ------------------------------------------------------------------------ decode


def _reject_constant(name: str):
    raise WireError(f"payload contains {name}, which is not valid JSON")


_DECODER = json.JSONDecoder(parse_constant=_reject_constant)
"""One decoder for every payload: ``json.loads(..., parse_constant=...)`` builds a new
JSONDecoder on every call (a keyword argument defeats its cached default decoder), which cost
more than the parsing itself (8.6 -> 2.3 us per payload; tests/bench/RESULTS.md)."""


_STRUCTURE = b'[]{}"\\'
_NOT_STRUCTURE = bytes(sorted(set(range(256)) - set(_STRUCTURE)))
_STRING = re.compile(rb'"(?:[^"\\]++|\\.)*+"?', re.S)
"""A JSON string from its opening quote: to its closing quote, or to the end of the bytes when
it has none (so a scan never goes back: linear time on any input)."""
_NEST_STEP = np.zeros(256, np.int8)
_NEST_STEP[[ord("["), ord("{")]] = 1
_NEST_STEP[[ord("]"), ord("}")]] = -1


def nesting_depth(data: bytes) -> int:
    """Deepest nesting of arrays and objects in ``data``, from a byte scan (no parsing).

    Brackets inside strings do not count. Exact for valid JSON; for any other bytes it is at
    least the depth a JSON parser reaches before it stops at the first error (up to that point
    both see the same strings). Cost: a ``bytes.translate`` that keeps only ``[]{}"\\``, and
    when a string holds a bracket or an escape, one regex pass that cuts the strings out."""
    s = data.translate(None, _NOT_STRUCTURE)
    if b'"' in s:
        bare = s.replace(b'""', b"")            # strings without brackets or escapes: all of them, usually
        if b'"' in bare or b"\\" in s:
            bare = _STRING.sub(b"", data).translate(None, _NOT_STRUCTURE)
        s = bare
    if not s:
        return 0
    return int(np.cumsum(_NEST_STEP[np.frombuffer(s, np.uint8)], dtype=np.int64).max())


def _check_bounds(data: bytes) -> None:
    """:data:`MAX_PAYLOAD_BYTES` and :data:`MAX_DEPTH`, checked on the bytes before any parsing."""
    if len(data) > MAX_PAYLOAD_BYTES:
        raise WireError(f"payload of {len(data)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    # an array or object opens with [ or {: no more than MAX_DEPTH of them cannot nest deeper
    if data.count(b"[") + data.count(b"{") > MAX_DEPTH and nesting_depth(data) > MAX_DEPTH:
        raise WireError(f"payload nests arrays/objects deeper than {MAX_DEPTH}")


def loads(data: bytes | bytearray | memoryview | str, where: str):
    """Parse untrusted UTF-8 JSON (a payload, a reply to a query, a message read from a file)
    within :data:`MAX_PAYLOAD_BYTES` and :data:`MAX_DEPTH`, NaN/Infinity refused: the value, or
    a one-line WireError naming ``where``."""
    try:
        raw = data.encode("utf-8") if isinstance(data, str) else bytes(data)
        _check_bounds(raw)
        # payloads are UTF-8 (the contract); json.loads would also sniff UTF-16/32
        return _DECODER.decode(raw.decode("utf-8"))
    except WireError as e:
        raise WireError(f"{where}: {e}") from None
    except (ValueError, UnicodeError) as e:
        raise WireError(f"{where}: payload is not valid JSON ({e})") from None


_FLOAT_MAX = sys.float_info.max


def _finite(v) -> bool:
    """A JSON number that is a finite float64: a float, or an int within float64's range (a
    longer int would overflow on conversion); not a bool."""
    t = type(v)
    return (t is float and math.isfinite(v)) or (t is int and -_FLOAT_MAX <= v <= _FLOAT_MAX)


def _kind_of(obj: dict, kind: str | None, where: str) -> str:
    if kind is not None:
        _vector_field(kind)
        return kind
    found = [k for k in KINDS if VECTOR_FIELD[k] in obj]
    if len(found) != 1:
        raise WireError(f"{where}: payload must hold exactly one of x, u, y; keys are "
                        f"{_short(sorted(obj))}")
    return found[0]


def _short(v, n: int = 40) -> str:
    """``repr(v)`` cut to ``n`` characters: an error names a hostile value without echoing it."""
    r = repr(v)
    return r if len(r) <= n else r[:n] + "..."


def _check_seq_field(obj: dict, where: str) -> int:
    seq = obj["seq"]
    if type(seq) is not int or not 0 <= seq <= SEQ_MAX:
        raise WireError(f"{where}: seq={_short(seq)} is not an integer from 0 to 2**63-1")
    return seq


def _validate(obj, kind: str | None, where: str) -> dict:
    if not isinstance(obj, dict):
        raise WireError(f"{where}: payload must be a JSON object, got {type(obj).__name__}")
    kind = _kind_of(obj, kind, where)
    field = VECTOR_FIELD[kind]
    keys = set(obj)
    if keys != {"seq", "t", field}:
        missing = sorted({"seq", "t", field} - keys)
        extra = sorted(keys - {"seq", "t", field})
        raise WireError(f"{where}: {kind} payload has missing keys {missing} and unknown "
                        f"keys {_short(extra)}")
    seq = _check_seq_field(obj, where)
    t = obj["t"]
    if not _finite(t):
        raise WireError(f"{where}: t={_short(t)} at seq {seq} is not a finite number")
    vec = obj[field]
    if type(vec) is not list:
        raise WireError(f"{where}: {field} at seq {seq} is not a list")
    for i, v in enumerate(vec):
        if (type(v) is not float or not math.isfinite(v)) and not _finite(v):   # floats: one test
            raise WireError(f"{where}: {field}[{i}]={_short(v)} at seq {seq} is not a finite number")
    vals = [float(v) for v in vec]
    if kind == CONTROL and vals and max(map(abs, vals)) > MAGNITUDE_MAX:
        _raise_too_large(where, seq, vals)
    return {"seq": seq, "t": float(t), field: vals}


def decode(data: bytes | bytearray | memoryview | str, kind: str | None = None, *,
           topic: str | None = None) -> dict:
    """Parse and validate one payload; return ``{"seq": int, "t": float, field: list[float]}``.

    ``kind`` (optional) fixes the expected vector field; otherwise it is inferred from which of
    ``x``/``u``/``y`` is present. Unknown keys, a missing key, a non-integer or negative seq,
    a non-finite ``t`` (s) or vector element, and NaN/Infinity literals raise WireError naming
    ``topic`` (or the kind) and the seq.
    """
    where = topic if topic is not None else (f"{kind} topic" if kind else "payload")
    return _validate(loads(data, where), kind, where)


# A JSON number (RFC 8259), possessive: numbers are followed by "," or "]" so nothing is given back.
_NUM = rb"-?+(?:0|[1-9][0-9]*+)(?:\.[0-9]++)?+(?:[eE][+-]?+[0-9]++)?+"
_ROWS: dict[tuple[str, int], re.Pattern] = {}
_TEMPLATE_DIM_MAX = 64
"""Longest vector the template path takes: its row pattern is compiled once per (field, length)
and kept, so a payload's length must not choose an unbounded regex or cache (longer vectors,
rare, take the json path)."""
_NL_TO_COMMA = bytes.maketrans(b"\n", b",")


def _rows_pattern(field: str, dim: int) -> re.Pattern:
    """Any number of rows ``{"seq":S,"t":T,"<field>":[V1,...,Vdim]}\\n`` (compiled once)."""
    pat = _ROWS.get((field, dim))
    if pat is None:
        vec = rb"\[" + rb",".join([_NUM] * dim) + rb"\]"
        row = rb'\{"seq":(?:0|[1-9][0-9]*+),"t":' + _NUM + rb',"' + field.encode() + rb'":' + vec + rb"\}\n"
        pat = _ROWS[(field, dim)] = re.compile(rb"(?:" + row + rb")*+")
    return pat


def _decode_template_blob(blob: bytes, n: int, field: str):
    """Fast path for ``n`` payloads exactly in noiselab's own layout ``{"seq":S,"t":T,"<field>":[...]}``
    (the encoder's output), each followed by ``\\n`` in ``blob``: one regex match over the whole blob
    checks the exact layout (JSON numbers only, the same vector length everywhere, an integer
    seq), the template is stripped (one bytes.replace, one bytes.translate) and every number
    parsed in one numpy call (C strtod, correctly rounded: the floats equal json's). Returns None
    (use the validating path) on any deviation."""
    cut = blob.find(b"\n")
    if n < 1 or cut < 0 or not blob.endswith(b"\n"):
        return None
    first = blob[:cut]
    mid = b',"' + field.encode() + b'":['
    if not first.startswith(b'{"seq":') or mid not in first:
        return None
    dim = first.count(b",") - 1 if not first.endswith(b"[]}") else 0
    if not 1 <= dim <= _TEMPLATE_DIM_MAX:
        return None
    m = _rows_pattern(field, dim).match(blob)
    if m is None or m.end() != len(blob):
        return None
    if b"-0," in blob or b"-0]" in blob:       # JSON's integer -0 is 0 (json.loads), strtod gives -0.0
        return None
    # {"seq":S,"t":T,"y":[V1,V2]}\n -> S,T,V1,V2,  (the layout is known: only template bytes go)
    body = blob.replace(b'{"seq":', b"").translate(_NL_TO_COMMA, b'"t:[]}' + field.encode())
    vals = np.fromstring(body[:-1].decode("ascii"), dtype=np.float64, sep=",")
    if vals.size != n * (dim + 2):
        return None
    vals = vals.reshape(n, dim + 2)
    if not np.all(np.isfinite(vals)) or np.any(vals[:, 0] > 2**53):
        return None
    return vals[:, 0].astype(np.int64), vals[:, 1].copy(), vals[:, 2:].copy()


def _decode_template(payloads: Sequence[bytes], field: str):
    """:func:`_decode_template_blob` of a list of payloads."""
    return _decode_template_blob(b"\n".join(payloads) + b"\n", len(payloads), field)


def decode_packed(blob: bytes, lens, kind: str, *, topic: str | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`decode_batch` of payloads packed in one buffer, each followed by ``b"\\n"``:
    payload i is ``blob[s_i:s_i + lens[i]]``, s_i = sum_{j<i} (lens[j] + 1) (what the MCAP
    reader collects). Same results and validation as :func:`decode_batch`."""
    field = _vector_field(kind)
    lens = np.asarray(lens, np.int64)
    n = int(lens.size)
    if n and int(lens.sum()) + n == len(blob) and int(lens.max()) <= MAX_PAYLOAD_BYTES:
        fast = _checked(kind, _decode_template_blob(blob, n, field))
        if fast is not None:
            return fast
    ends = np.cumsum(lens + 1) - 1
    starts = ends - lens
    return decode_batch([blob[a:b] for a, b in zip(starts.tolist(), ends.tolist())], kind, topic=topic)


def _checked(kind: str, fast):
    """A fast path's result, or None when it holds what only the validating path may name: a
    ``control`` element beyond :data:`MAGNITUDE_MAX`."""
    if fast is not None and kind == CONTROL and fast[2].size and np.abs(fast[2]).max() > MAGNITUDE_MAX:
        return None
    return fast


def _decode_json_batch(payloads: Sequence[bytes], field: str):
    """Fast path for payloads in another layout (spacing, key order, integers): the whole batch
    parsed with one ``json.loads`` and checked with numpy; None (use the validating path) when
    anything looks off. Every payload must open with ``{`` and close with ``}``: then the
    parsed array has one object per payload (two payloads could only merge through a string
    holding the ``},{`` between them, and no key or value of a valid sample is such a string)."""
    if not all(p[:1] == b"{" and p[-1:] == b"}" for p in payloads):
        return None
    blob = b"[" + b",".join(payloads) + b"]"
    # Literals that numpy would silently coerce (true -> 1.0, null -> nan) take the slow path;
    # the batch array adds one level to the payloads' nesting.
    if b"true" in blob or b"false" in blob or b"null" in blob or nesting_depth(blob) > MAX_DEPTH + 1:
        return None
    try:
        objs = json.loads(blob, parse_constant=_reject_constant)
    except (ValueError, UnicodeDecodeError):
        return None
    n = len(payloads)
    if len(objs) != n:
        return None
    expected = {"seq", "t", field}
    try:
        if not all(type(o) is dict and o.keys() == expected for o in objs):
            return None
        seq_list = [o["seq"] for o in objs]
        if not all(type(s) is int for s in seq_list):
            return None
        seq = np.array(seq_list, dtype=np.int64)
        t = np.array([o["t"] for o in objs])
        vals = np.array([o[field] for o in objs])
    except (ValueError, OverflowError):
        return None                     # ragged vectors, huge ints: the slow path names the culprit
    if vals.ndim == 1 and vals.size == 0:
        vals = vals.reshape(n, 0)
    if (t.ndim == 1 and t.dtype.kind in "fi" and vals.dtype.kind in "fi" and vals.ndim == 2
            and vals.shape[0] == n and (seq >= 0).all()
            and np.isfinite(t).all() and np.isfinite(vals).all()):
        return seq, t.astype(np.float64), vals.astype(np.float64)
    return None


def decode_batch(payloads: Sequence[bytes], kind: str, *, topic: str | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode many payloads of one topic at once: ``(seq int64 (N,), t float64 (N,) in s,
    values float64 (N, dim))``.

    Same validation as :func:`decode` (and all vectors must have the same length). Two fast
    paths (noiselab's own layout: :func:`_decode_template`; any other: :func:`_decode_json_batch`)
    check the batch as a whole; when anything looks off it falls back to :func:`decode` per
    message to name the first culprit.
    """
    field = _vector_field(kind)
    where = topic if topic is not None else f"{kind} topic"
    n = len(payloads)
    if n == 0:
        return (np.empty(0, np.int64), np.empty(0, np.float64), np.empty((0, 0), np.float64))
    if max(map(len, payloads)) <= MAX_PAYLOAD_BYTES:
        fast = _decode_template(payloads, field)
        if fast is None:
            fast = _decode_json_batch(payloads, field)
        fast = _checked(kind, fast)
        if fast is not None:
            return fast
    decoded = [decode(p, kind, topic=topic) for p in payloads]
    dims = {len(d[field]) for d in decoded}
    if len(dims) != 1:
        first = decoded[0]
        bad = next(d for d in decoded if len(d[field]) != len(first[field]))
        raise WireError(f"{where}: {field} has length {len(bad[field])} at seq {bad['seq']} but "
                        f"{len(first[field])} at seq {first['seq']}")
    seq = np.array([d["seq"] for d in decoded], dtype=np.int64)
    t = np.array([d["t"] for d in decoded], dtype=np.float64)
    vals = np.array([d[field] for d in decoded], dtype=np.float64).reshape(n, dims.pop())
    return seq, t, vals
