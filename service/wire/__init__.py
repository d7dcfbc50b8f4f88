"""The wire contract of noiselab, in one place: Zenoh keys, JSON payloads, JSON Schemas, time.

Every other node imports its keys, schemas, encoders and time conventions from this package
(``from service import wire``; ``wire.key``, ``wire.encode``, ...); nothing else builds a
key or a payload by hand (DESIGN.md, "Wire contract (Zenoh and MCAP)"). Its modules: the
vocabulary, keys and bounds (:mod:`.contract`), the JSON Schemas (:mod:`.schemas`), the samples
encoded (:mod:`.encode`) and decoded from untrusted bytes (:mod:`.decode`), time
(:mod:`.timebase`), and the messages that are not samples: health, analysis, end (:mod:`.status`).

Keys
    ``noiselab/<name>/<kind>`` with ``<name>`` matching ``[A-Za-z0-9_-]+`` and ``<kind>`` one of
    :data:`KINDS`. MCAP topics are the same strings (no leading ``/``); readers also accept a
    leading ``/`` (see :func:`parse_key`).

Payload (UTF-8 JSON object, compact, key order ``seq``, ``t``, vector)
    ``seq``  int >= 0, per topic, from 0, consecutive (a missing number is a lost message).
    (``health`` and ``controller_health`` payloads carry ``seq``, ``t`` and the loop statistics
    of :func:`health_schema` and :func:`controller_health_schema`.)
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
    bound of :mod:`noiselab.bounds`, 1e50, which the models, the emulator's output, the recordings'
    loader and the live analyzer share). What the bytes cannot tell (a vector's length, a seq
    that does not continue its stream) is judged by the node that knows the stream, with
    :class:`noiselab.nodes.seqgate.SeqGate`.

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

from .contract import (
    ALL_KINDS,
    ANALYSIS,
    CONTROL,
    CONTROLLER_HEALTH,
    END,
    HEALTH,
    KINDS,
    MAGNITUDE_MAX,
    MAX_DEPTH,
    MAX_PAYLOAD_BYTES,
    MESSAGE_ENCODING,
    PREFIX,
    SCHEMA_ENCODING,
    SCHEMA_NAMES,
    SEQ_MAX,
    START_MAX,
    VECTOR_FIELD,
    ZENOH_JSON,
    WireError,
    check_kind,
    check_name,
    key,
    parse_key,
    zenoh_encoding,
)
from .decode import (
    decode,
    decode_batch,
    decode_packed,
    loads,
    nesting_depth,
)
from .encode import (
    encode,
    encode_batch,
)
from .schemas import (
    schema,
    schema_bytes,
)
from .status import (
    CONTROLLER_HEALTH_FIELDS,
    END_REASONS,
    HEALTH_FIELDS,
    analysis_schema,
    controller_health_schema,
    decode_analysis,
    decode_controller_health,
    decode_end,
    decode_health,
    encode_analysis,
    encode_controller_health,
    encode_end,
    encode_health,
    end_schema,
    health_schema,
)
from .timebase import (
    anchored_ns,
    decode_anchor,
    encode_anchor,
    period_ns,
    publish_time_ns,
    sample_time,
    sample_times,
)

__all__ = [
    "ALL_KINDS",
    "ANALYSIS",
    "CONTROL",
    "CONTROLLER_HEALTH",
    "CONTROLLER_HEALTH_FIELDS",
    "END",
    "END_REASONS",
    "HEALTH",
    "HEALTH_FIELDS",
    "KINDS",
    "MAGNITUDE_MAX",
    "MAX_DEPTH",
    "MAX_PAYLOAD_BYTES",
    "MESSAGE_ENCODING",
    "PREFIX",
    "SCHEMA_ENCODING",
    "SCHEMA_NAMES",
    "SEQ_MAX",
    "START_MAX",
    "VECTOR_FIELD",
    "ZENOH_JSON",
    "WireError",
    "analysis_schema",
    "controller_health_schema",
    "anchored_ns",
    "check_kind",
    "check_name",
    "decode",
    "decode_analysis",
    "decode_controller_health",
    "decode_anchor",
    "decode_batch",
    "decode_end",
    "decode_health",
    "decode_packed",
    "encode",
    "encode_analysis",
    "encode_controller_health",
    "encode_anchor",
    "encode_batch",
    "encode_end",
    "encode_health",
    "end_schema",
    "health_schema",
    "key",
    "loads",
    "nesting_depth",
    "parse_key",
    "period_ns",
    "publish_time_ns",
    "sample_time",
    "sample_times",
    "schema",
    "schema_bytes",
    "zenoh_encoding",
]
