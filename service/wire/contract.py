"""The wire contract's vocabulary: the topic kinds and the keys built from them, the MCAP schema
names and encodings, the bounds a payload must keep, and :class:`WireError`, which every breach
of the contract raises (package docstring: the contract)."""

from __future__ import annotations

import operator
import re

from ..bounds import MAGNITUDE_MAX  # noqa: F401  (part of the contract: wire.MAGNITUDE_MAX)

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

CONTROLLER_HEALTH = "controller_health"
"""A controller's loop timing on ``noiselab/<name>/controller_health`` (not a vector): what it
answered, late, skipped and missed (:data:`noiselab.wire.status.CONTROLLER_HEALTH_FIELDS`)."""

ALL_KINDS: tuple[str, ...] = KINDS + (CONTROL, HEALTH, ANALYSIS, END, CONTROLLER_HEALTH)

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
    "controller_health": "noiselab.ControllerHealth",
}
"""MCAP schema name per kind."""

SCHEMA_ENCODING = "jsonschema"
"""MCAP schema encoding of the registered schemas."""

MESSAGE_ENCODING = "json"
"""MCAP message encoding of every noiselab channel."""

_NAME_RE = re.compile(r"[A-Za-z0-9_-]+")


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
    return f"{ZENOH_JSON};{SCHEMA_NAMES[check_kind(kind)]}"


def check_name(name: str) -> str:
    """Return ``name`` if it is a valid device name (``[A-Za-z0-9_-]+``), else raise WireError."""
    if not isinstance(name, str) or _NAME_RE.fullmatch(name) is None:
        raise WireError(f"device name {name!r} is invalid: use letters, digits, '_' or '-' only")
    return name


def check_kind(kind: str) -> str:
    """A known topic kind (vector kinds and ``health``)."""
    if kind not in ALL_KINDS:
        raise WireError(f"topic kind {kind!r} is unknown: expected one of {', '.join(ALL_KINDS)}")
    return kind


def vector_field(kind: str) -> str:
    """The vector field of a vector kind (``health`` and ``analysis`` are not)."""
    if check_kind(kind) in (HEALTH, ANALYSIS, END, CONTROLLER_HEALTH):
        raise WireError(f"{kind} payloads are not vectors: use encode_{kind}/decode_{kind}")
    return VECTOR_FIELD[kind]


def key(name: str, kind: str) -> str:
    """Zenoh key expression (and MCAP topic) ``noiselab/<name>/<kind>`` of one stream."""
    return f"{PREFIX}/{check_name(name)}/{check_kind(kind)}"


def parse_key(key_expr: str) -> tuple[str, str]:
    """Split ``[/]noiselab/<name>/<kind>`` into ``(name, kind)``; a leading ``/`` is accepted."""
    parts = key_expr.lstrip("/").split("/") if isinstance(key_expr, str) else []
    if len(parts) != 3 or parts[0] != PREFIX:
        raise WireError(f"key {key_expr!r} is not of the form noiselab/<name>/<kind>")
    return check_name(parts[1]), check_kind(parts[2])


def check_seq(seq: int, what: str = "seq") -> int:
    if isinstance(seq, bool):
        raise WireError(f"{what} must be an integer >= 0, got {seq!r}")
    try:
        seq = operator.index(seq)
    except TypeError:
        raise WireError(f"{what} must be an integer >= 0, got {seq!r}") from None
    if not 0 <= seq <= SEQ_MAX:
        raise WireError(f"{what} must be an integer from 0 to 2**63-1, got {seq}")
    return seq


def short(v, n: int = 40) -> str:
    """``repr(v)`` cut to ``n`` characters: an error names a hostile value without echoing it."""
    r = repr(v)
    return r if len(r) <= n else r[:n] + "..."
