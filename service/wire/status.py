"""The stream's messages that are not samples: the emulator's loop health, the live analyzer's
summary, and the end of stream a source publishes after its last sample; each with its JSON
Schema, its encoder and its validating decoder."""

from __future__ import annotations

import json
import math
from numbers import Real

from .contract import (
    ALL_KINDS,
    ANALYSIS,
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
    obj = {"seq": check_seq(seq), "t": float(t)}
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
    check_seq_field(obj, where)
    for name in ("t", *HEALTH_FIELDS):
        v = obj[name]
        if not finite_number(v):
            raise WireError(f"{where}: {name}={short(v)} is not a finite number")
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
