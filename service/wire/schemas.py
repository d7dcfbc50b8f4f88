"""The JSON Schema (draft 2020-12) of every payload kind, as registered in MCAP so Foxglove and
PlotJuggler open a recording."""

from __future__ import annotations

import json

from .contract import ANALYSIS, CONTROLLER_HEALTH, END, HEALTH, SCHEMA_NAMES, VECTOR_FIELD, check_kind
from .status import analysis_schema, controller_health_schema, end_schema, health_schema

_VECTOR_DESCRIPTION = {
    "truth": "true plant state x_k (units of the model's states)",
    "command": "applied command u_k (units of the plant input)",
    "measurement": "measurement y_k (units of the model's outputs)",
    "control": "command requested by a controller (units of the plant input)",
}


def schema(kind: str) -> dict:
    """JSON Schema (draft 2020-12) of a payload of ``kind``, as a fresh dict."""
    if check_kind(kind) == HEALTH:
        return health_schema()
    if kind == ANALYSIS:
        return analysis_schema()
    if kind == END:
        return end_schema()
    if kind == CONTROLLER_HEALTH:
        return controller_health_schema()
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


def schema_bytes(kind: str) -> bytes:
    """:func:`schema` serialised as the UTF-8 bytes registered in MCAP (deterministic)."""
    return json.dumps(schema(kind), separators=(",", ":")).encode()


# -------------------------------------------------------------------------- time
