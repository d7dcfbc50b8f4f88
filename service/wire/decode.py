"""Payloads to samples, for untrusted bytes: the size and nesting bounds checked on the bytes
before any parsing, then the layout validated; and the batch decoders with their two fast paths
(noiselab's own layout parsed by one regex and one numpy call; any other by one ``json.loads``),
which fall back to the validating path to name the first culprit."""

from __future__ import annotations

import json
import math
import re
import sys
from collections.abc import Sequence

import numpy as np

from .contract import (
    CONTROL,
    KINDS,
    MAGNITUDE_MAX,
    MAX_DEPTH,
    MAX_PAYLOAD_BYTES,
    SEQ_MAX,
    VECTOR_FIELD,
    WireError,
    short,
    vector_field,
)
from .encode import raise_too_large


def reject_constant(name: str):
    raise WireError(f"payload contains {name}, which is not valid JSON")


_DECODER = json.JSONDecoder(parse_constant=reject_constant)
"""One decoder for every payload: ``json.loads(..., parse_constant=...)`` builds a new
JSONDecoder on every call (a keyword argument defeats its cached default decoder), which costs
more than the parsing itself."""


_STRUCTURE = b'[]{}"\\'
_NOT_STRUCTURE = bytes(sorted(set(range(256)) - set(_STRUCTURE)))
_STRING = re.compile(rb'"(?:[^"\\]++|\\.)*+"?', re.DOTALL)
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


def finite_number(v) -> bool:
    """A JSON number that is a finite float64: a float, or an int within float64's range (a
    longer int would overflow on conversion); not a bool."""
    t = type(v)
    return (t is float and math.isfinite(v)) or (t is int and -_FLOAT_MAX <= v <= _FLOAT_MAX)


def _kind_of(obj: dict, kind: str | None, where: str) -> str:
    if kind is not None:
        vector_field(kind)
        return kind
    found = [k for k in KINDS if VECTOR_FIELD[k] in obj]
    if len(found) != 1:
        raise WireError(f"{where}: payload must hold exactly one of x, u, y; keys are "
                        f"{short(sorted(obj))}")
    return found[0]


def check_seq_field(obj: dict, where: str) -> int:
    seq = obj["seq"]
    if type(seq) is not int or not 0 <= seq <= SEQ_MAX:
        raise WireError(f"{where}: seq={short(seq)} is not an integer from 0 to 2**63-1")
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
                        f"keys {short(extra)}")
    seq = check_seq_field(obj, where)
    t = obj["t"]
    if not finite_number(t):
        raise WireError(f"{where}: t={short(t)} at seq {seq} is not a finite number")
    vec = obj[field]
    if type(vec) is not list:
        raise WireError(f"{where}: {field} at seq {seq} is not a list")
    for i, v in enumerate(vec):
        if (type(v) is not float or not math.isfinite(v)) and not finite_number(v):   # floats: one test
            raise WireError(f"{where}: {field}[{i}]={short(v)} at seq {seq} is not a finite number")
    vals = [float(v) for v in vec]
    if kind == CONTROL and vals and max(map(abs, vals)) > MAGNITUDE_MAX:
        raise_too_large(where, seq, vals)
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
    field = vector_field(kind)
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
        objs = json.loads(blob, parse_constant=reject_constant)
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
    field = vector_field(kind)
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
