"""Input validation for the estimators, in one place.

Every estimator validates its arguments once, on entry, through these helpers; a bad argument
raises :class:`StatsError` (a ``ValueError``) whose one-line message names the argument, what was
expected and what was found. Nothing here uses ``assert``.
"""

from __future__ import annotations

import numpy as np


class StatsError(ValueError):
    """An estimator argument is invalid. The message is one line naming the culprit."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))


def as_series(x, name: str, *, min_len: int = 2) -> np.ndarray:
    """Return ``x`` as a finite 1-D float64 array of at least ``min_len`` samples."""
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise StatsError(f"{name}: expected a 1-D array of numbers ({exc})") from None
    if arr.ndim != 1:
        raise StatsError(f"{name}: expected a 1-D array, found shape {arr.shape}")
    if arr.size < min_len:
        raise StatsError(f"{name}: expected at least {min_len} samples, found {arr.size}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.isfinite(arr))[0])
        raise StatsError(f"{name}: sample {bad} is not finite ({arr[bad]!r}); remove gaps first")
    return arr


def positive_float(value, name: str) -> float:
    """Return ``value`` as a finite float > 0."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise StatsError(f"{name}: expected a positive number, found {value!r}") from None
    if not np.isfinite(v) or v <= 0.0:
        raise StatsError(f"{name}: expected a positive number, found {value!r}")
    return v


def positive_int(value, name: str, *, minimum: int = 1) -> int:
    """Return ``value`` as an int >= ``minimum`` (bools and non-integral floats rejected)."""
    if isinstance(value, (bool, np.bool_)):
        raise StatsError(f"{name}: expected an integer >= {minimum}, found {value!r}")
    try:
        v = int(value)
    except (TypeError, ValueError):
        raise StatsError(f"{name}: expected an integer >= {minimum}, found {value!r}") from None
    if v != value or v < minimum:
        raise StatsError(f"{name}: expected an integer >= {minimum}, found {value!r}")
    return v


def probability(value, name: str) -> float:
    """Return ``value`` as a float strictly inside (0, 1)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise StatsError(f"{name}: expected a number in (0, 1), found {value!r}") from None
    if not 0.0 < v < 1.0:
        raise StatsError(f"{name}: expected a number in (0, 1), found {value!r}")
    return v


def choice(value, name: str, allowed: tuple[str, ...]) -> str:
    """Return ``value`` if it is one of ``allowed`` (exact string match)."""
    if not isinstance(value, str) or value not in allowed:
        raise StatsError(f"{name}: expected one of {', '.join(map(repr, allowed))}, found {value!r}")
    return value
