"""Samples to payloads: one vector sample, or a batch of consecutive samples formatted in C, as
compact JSON whose floats round-trip exactly (package docstring, "Payload")."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from numbers import Real

import numpy as np

from .contract import (
    CONTROL,
    MAGNITUDE_MAX,
    SEQ_MAX,
    VECTOR_FIELD,
    WireError,
    check_seq,
    vector_field,
)


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
    field = vector_field(kind)
    seq = check_seq(seq)
    if isinstance(t, bool) or not isinstance(t, Real):
        raise WireError(f"{_where(kind, topic)}: t={t!r} is not a number (seq {seq})")
    t = float(t)
    vals = _vector(vec, kind, topic)
    nums = ",".join(map(float.__repr__, vals))
    # Finite float reprs use only digits . e + -: an 'n' means inf or nan somewhere.
    if "n" in nums or not math.isfinite(t):
        _raise_non_finite(kind, topic, seq, t, vals)
    if kind == CONTROL and vals and max(map(abs, vals)) > MAGNITUDE_MAX:
        raise_too_large(topic, seq, vals)
    return f'{{"seq":{seq},"t":{t!r},"{field}":[{nums}]}}'.encode()


def raise_too_large(topic, seq, vals):
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
    message with a single bytes %-format in C (no ``json.dumps`` per message; what remains is
    ``float.__repr__`` itself). Raises WireError (naming ``topic``, the
    seq and the element) if anything is NaN/inf or the shapes disagree.
    """
    field = vector_field(kind)
    seq0 = check_seq(seq0, "seq0")
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
        raise_too_large(topic, seq0 + row, m[row].tolist())
    if n and seq0 + n - 1 > SEQ_MAX:
        raise WireError(f"{_where(kind, topic)}: seq {seq0 + n - 1} exceeds 2**63-1")
    fmt = ('{"seq":%d,"t":%r,"' + field + '":[' + ",".join(["%r"] * dim) + "]}").encode()
    # tolist() yields Python floats, whose %r is float.__repr__ (numpy scalars would print
    # "np.float64(...)"); zip builds the argument tuple of each row without a Python loop body.
    return [fmt % row for row in zip(range(seq0, seq0 + n), t_arr.tolist(), *m.T.tolist())]


# ------------------------------------------------------------------------ decode
