"""Validation of model-file tables in one place (STYLE 5 and 6).

A :class:`Table` wraps one TOML table. Each accessor validates one key (type, shape, range,
finiteness) and :meth:`Table.done` rejects every key that was not asked for, so a misspelled key is
an error, never a silent default. All messages are one line: ``<source>: [table] key: expected ...,
got ...``.

Every number of a model file is finite and at most :data:`MAGNITUDE_MAX` in magnitude: the
predictions and the analysis square a model's numbers (variances), sum the squares over a record
and take their squares again (the spread of a variance estimate is a fourth moment), and all of it
must stay finite in float64 (max 1.8e308): (1e50)^4 = 1e200 leaves 1e108 for the sums and the
plant's gains. No sensor or plant written in any unit system needs more.
"""

from __future__ import annotations

import math
import sys
from typing import Any, Callable, Sequence

import numpy as np

from ..bounds import MAGNITUDE_MAX
from .errors import ModelError

_MISSING = object()
_FLOAT_MAX = sys.float_info.max

_MAGNITUDE = f"of magnitude at most {MAGNITUDE_MAX:g} (its square and fourth power must stay finite in float64)"


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _is_number(v: Any) -> bool:
    # TOML integers are unbounded; one beyond float64's range is not a usable number (float() of
    # it would raise OverflowError instead of a ModelError).
    if isinstance(v, int) and not isinstance(v, bool):
        return abs(v) <= _FLOAT_MAX
    return isinstance(v, float)


class Table:
    """Validating view of one TOML table.

    ``source`` names the file (or scenario) and ``path`` the table, e.g. ``"actuator.ar1"``.
    """

    def __init__(self, data: Any, path: str, source: str):
        if not isinstance(data, dict):
            raise ModelError(f"{source}: [{path}]: expected a table, got {_show(data)}")
        self.data = data
        self.path = path
        self.source = source
        self._used: set[str] = set()

    # -- errors -------------------------------------------------------------------------------
    def error(self, key: str | None, what: str) -> ModelError:
        where = f"[{self.path}] {key}" if key else f"[{self.path}]"
        if not self.path:
            where = key or "top level"
        return ModelError(f"{self.source}: {where}: {what}")

    def has(self, key: str) -> bool:
        return key in self.data

    def _absent(self, key: str, default: Any) -> bool:
        """Mark ``key`` as known; True when it is absent (and optional), error when required."""
        self._used.add(key)
        if key in self.data:
            return False
        if default is _MISSING:
            extra = [k for k in self.data if k not in self._used and isinstance(k, str)]
            hint = f" (found unknown key {extra[0]!r}: misspelled?)" if extra else ""
            raise self.error(key, "missing required key" + hint)
        return True

    # -- scalars ------------------------------------------------------------------------------
    def number(self, key: str, default: Any = _MISSING, *,
               check: Callable[[float], bool] | None = None, expect: str = "a finite number") -> float:
        if self._absent(key, default):
            return default
        v = self.data[key]
        if not _is_number(v) or not math.isfinite(float(v)):
            raise self.error(key, f"expected {expect}, got {_show(v)}")
        v = float(v)
        if check is not None and not check(v):
            raise self.error(key, f"expected {expect}, got {_show(v)}")
        if abs(v) > MAGNITUDE_MAX:
            raise self.error(key, f"expected {expect} {_MAGNITUDE}, got {_show(v)}")
        return v

    def integer(self, key: str, default: Any = _MISSING, *,
                check: Callable[[int], bool] | None = None, expect: str = "an integer") -> int:
        if self._absent(key, default):
            return default
        v = self.data[key]
        if not isinstance(v, int) or isinstance(v, bool) or (check is not None and not check(v)):
            raise self.error(key, f"expected {expect}, got {_show(v)}")
        return int(v)

    def string(self, key: str, default: Any = _MISSING, *, choices: Sequence[str] | None = None,
               pattern: Callable[[str], bool] | None = None, expect: str = "a string") -> str:
        if self._absent(key, default):
            return default
        v = self.data[key]
        if not isinstance(v, str):
            raise self.error(key, f"expected {expect}, got {_show(v)}")
        if choices is not None and v not in choices:
            raise self.error(key, f"expected one of {', '.join(repr(c) for c in choices)}, got {_show(v)}")
        if pattern is not None and not pattern(v):
            raise self.error(key, f"expected {expect}, got {_show(v)}")
        return v

    # -- vectors and matrices -----------------------------------------------------------------
    def vector(self, key: str, n: int, default: Any = _MISSING, *,
               check: Callable[[np.ndarray], bool] | None = None,
               expect: str = "finite numbers") -> np.ndarray:
        """A number (broadcast to length ``n``) or a list of ``n`` numbers."""
        if self._absent(key, default):
            return None if default is None else np.broadcast_to(np.asarray(default, float), (n,)).copy()
        v = self.data[key]
        what = f"a number or a list of {n} numbers ({expect})"
        if _is_number(v):
            arr = np.full(n, float(v))
        elif isinstance(v, list) and all(_is_number(x) for x in v) and len(v) in (1, n):
            arr = np.broadcast_to(np.asarray(v, float), (n,)).copy()
        else:
            raise self.error(key, f"expected {what}, got {_show(v)}")
        if not np.all(np.isfinite(arr)) or (check is not None and not check(arr)):
            raise self.error(key, f"expected {what}, got {_show(v)}")
        if np.any(np.abs(arr) > MAGNITUDE_MAX):
            raise self.error(key, f"expected {what} {_MAGNITUDE}, got {_show(v)}")
        return arr

    def matrix(self, key: str, default: Any = _MISSING, *, rows: int | None = None,
               cols: int | None = None) -> np.ndarray:
        """A list of rows (a single row may be written flat), finite numbers, optional shape."""
        if self._absent(key, default):
            return default
        v = self.data[key]
        if isinstance(v, list) and v and all(_is_number(x) for x in v):
            v = [v]
        ok = (isinstance(v, list) and len(v) > 0 and all(isinstance(r, list) and len(r) > 0 for r in v)
              and all(_is_number(x) for r in v for x in r) and len({len(r) for r in v}) == 1)
        if not ok:
            raise self.error(key, f"expected a matrix (a list of equal-length rows of numbers), got {_show(v)}")
        arr = np.asarray(v, float)
        if not np.all(np.isfinite(arr)):
            raise self.error(key, f"expected finite numbers, got {_show(v)}")
        if np.any(np.abs(arr) > MAGNITUDE_MAX):
            raise self.error(key, f"expected numbers {_MAGNITUDE}, got {_show(v)}")
        if (rows is not None and arr.shape[0] != rows) or (cols is not None and arr.shape[1] != cols):
            want = f"{rows if rows is not None else 'any'} x {cols if cols is not None else 'any'}"
            raise self.error(key, f"expected shape {want}, got {arr.shape[0]} x {arr.shape[1]}")
        return arr

    def done(self) -> None:
        unknown = [k for k in self.data if k not in self._used]
        if unknown:
            known = ", ".join(sorted(self._used)) or "none"
            raise self.error(unknown[0], f"unknown key (this table takes: {known})")


def positive(v) -> bool:
    return bool(np.all(np.asarray(v) > 0))


def nonnegative(v) -> bool:
    return bool(np.all(np.asarray(v) >= 0))
