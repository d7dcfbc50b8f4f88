"""The stream's messages that are not samples: the emulator's and a controller's loop health, the
live analyzer's summary, and the end of stream a source publishes after its last sample; each with its JSON
Schema, its encoder and its validating decoder."""

from __future__ import annotations

import json
import math
from numbers import Real

from .contract import (
    ALL_KINDS,
    ANALYSIS,
    CONTROLLER_HEALTH,
    END,
    HEALTH,
    SCHEMA_NAMES,
    SEQ_MAX,
    WireError,
    check_seq,
    short,
)
from .decode import check_seq_field, finite_number, loads

HEALTH_FIELDS: dict[str, str] = {
    "k": "samples stepped so far",
    "lateness_p50_us": "median wake-up lateness behind the absolute deadline k*Ts, us, over the last report period",
    "lateness_p99_us": "99th percentile of that lateness, us",
    "lateness_max_us": "largest lateness, us",
    "overruns": "samples (since start) whose work finished after the next deadline",
    "late_control": "1 when the last control input is older than the stale timeout (zero is applied), else 0",
}


CONTROLLER_HEALTH_FIELDS: dict[str, str] = {
    "k": "measurements answered so far",
    "latency_p50_us": "median time from a measurement's arrival to the control's put, us, over the last report period",
    "latency_p99_us": "99th percentile of that latency, us",
    "latency_max_us": "largest latency, us",
    "late_replies": "controls (since start) put after a newer measurement had already arrived: "
                    "the plant stepped past them on an older command",
    "missing_measurements": "measurement seqs (since start) skipped by a jump ahead: lost or never sent",
    "stale_measurements": "measurements (since start) whose seq is not past the last one answered: skipped",
    "rejected_measurements": "measurements (since start) that break the wire contract or the model's "
                             "output count: skipped",
}

_STATS = {HEALTH: (HEALTH_FIELDS, "health", "noiselab emulator loop health; see README 'Live pipeline'",
                   "nominal time (k-1)*Ts of the last sample stepped, s"),
          CONTROLLER_HEALTH: (CONTROLLER_HEALTH_FIELDS, "controller health",
                              "noiselab controller loop health; see README 'Closed loop'",
                              "time t of the last measurement answered, s")}


def _stats_schema(kind: str) -> dict:
    fields, _, description, t_desc = _STATS[kind]
    props = {"seq": {"type": "integer", "minimum": 0, "description": "per-topic counter"},
             "t": {"type": "number", "description": t_desc}}
    for name, desc in fields.items():
        props[name] = {"type": "number", "description": desc}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": SCHEMA_NAMES[kind],
        "description": description,
        "type": "object",
        "properties": props,
        "required": ["seq", "t", *fields],
        "additionalProperties": False,
    }


def _encode_stats(kind: str, seq: int, t: float, stats: dict) -> bytes:
    fields, what = _STATS[kind][:2]
    if set(stats) != set(fields):
        raise WireError(f"{what} payload needs exactly {sorted(fields)}, got {sorted(stats)}")
    obj = {"seq": check_seq(seq), "t": float(t)}
    for name in fields:
        v = stats[name]
        if isinstance(v, bool) or not isinstance(v, Real) or not math.isfinite(v):
            raise WireError(f"{what} field {name}={v!r} is not a finite number")
        obj[name] = v if isinstance(v, int) else float(v)
    return json.dumps(obj, separators=(",", ":")).encode()


def _decode_stats(kind: str, data, topic: str | None) -> dict:
    fields, what = _STATS[kind][:2]
    where = topic or f"{kind} topic"
    obj = loads(data, where)
    if not isinstance(obj, dict) or set(obj) != {"seq", "t", *fields}:
        raise WireError(f"{where}: {what} payload must have keys seq, t, {', '.join(fields)}")
    check_seq_field(obj, where)
    for name in ("t", *fields):
        v = obj[name]
        if not finite_number(v):
            raise WireError(f"{where}: {name}={short(v)} is not a finite number")
    return obj


def health_schema() -> dict:
    """JSON Schema of the emulator's health payload (``seq``, ``t`` and :data:`HEALTH_FIELDS`)."""
    return _stats_schema(HEALTH)


def encode_health(seq: int, t: float, stats: dict) -> bytes:
    """Compact JSON health payload; ``stats`` holds exactly :data:`HEALTH_FIELDS` (finite)."""
    return _encode_stats(HEALTH, seq, t, stats)


def decode_health(data: bytes | bytearray | memoryview | str, *, topic: str | None = None) -> dict:
    """Parse and validate a health payload."""
    return _decode_stats(HEALTH, data, topic or "health topic")


def controller_health_schema() -> dict:
    """JSON Schema of a controller's health payload (``seq``, ``t`` and
    :data:`CONTROLLER_HEALTH_FIELDS`): the same shape as the emulator's, its own fields."""
    return _stats_schema(CONTROLLER_HEALTH)


def encode_controller_health(seq: int, t: float, stats: dict) -> bytes:
    """Compact JSON controller health payload; ``stats`` holds exactly :data:`CONTROLLER_HEALTH_FIELDS`."""
    return _encode_stats(CONTROLLER_HEALTH, seq, t, stats)


def decode_controller_health(data, *, topic: str | None = None) -> dict:
    """Parse and validate a controller health payload."""
    return _decode_stats(CONTROLLER_HEALTH, data, topic)


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
    obj = {"seq": check_seq(seq), "t": float(t), **summary}
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
    except ValueError as exc:
        raise WireError(f"analysis summary: {exc}") from None


def decode_analysis(data, *, topic: str | None = None) -> dict:
    where = topic or "analysis topic"
    obj = loads(data, where)
    if not isinstance(obj, dict) or not {"seq", "t", "error"} <= set(obj):
        raise WireError(f"{where}: analysis payload must be an object with seq, t, error")
    check_seq_field(obj, where)
    if not finite_number(obj["t"]):
        raise WireError(f"{where}: t={short(obj['t'])} in an analysis payload is not a finite number")
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
    obj = {"seq": check_seq(seq), "t": float(t), "samples": check_seq(samples, "samples"),
           "counts": {k: check_seq(v, f"count of {k}") for k, v in counts.items()}, "reason": reason}
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
            raise WireError(f"{where}: {name}={short(obj[name])} is not an integer from 0 to 2**63-1")
    if not finite_number(obj["t"]):
        raise WireError(f"{where}: t={short(obj['t'])} is not a finite number")
    counts = obj["counts"]
    if not isinstance(counts, dict) or not all(k in ALL_KINDS and type(v) is int and 0 <= v <= SEQ_MAX
                                               for k, v in counts.items()):
        raise WireError(f"{where}: counts must map topic kinds to integers >= 0, got {short(counts)}")
    if type(obj["reason"]) is not str or obj["reason"] not in END_REASONS:
        raise WireError(f"{where}: reason={short(obj['reason'])} is not one of {', '.join(END_REASONS)}")
    obj["t"] = float(obj["t"])
    return obj
