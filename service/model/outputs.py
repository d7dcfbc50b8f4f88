"""The ``[outputs]`` table: a name and a unit for every measured output.

Names label the outputs wherever a user reads them: reports, JSON fields, ``.rrd`` entity paths,
plot axes. A name is an identifier (letters, digits, ``_``; not starting with a digit) so that it
is a valid JSON key, Rerun path part and TOML bare key as it stands; names are unique. A unit is
free text of at most 32 printable characters (``"rad/s"``, ``"m/s^2"``, ``"deg/s"``).

Defaults with a plant (the table is optional there): the mass-spring-damper shorthand measures
``position`` in ``m``; a general plant's outputs are ``y0``, ``y1``, ... in ``units``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from .schema import Table

OUTPUT_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")
UNIT_MAX = 32
DEFAULT_UNIT = "units"


@dataclass(frozen=True)
class Outputs:
    names: tuple[str, ...]
    units: tuple[str, ...]
    given: bool = False        # written in the model file (then written back by to_dict)

    def label(self, j: int) -> str:
        """``name [unit]`` of output ``j``, for axes and report lines."""
        return f"{self.names[j]} [{self.units[j]}]"

    def to_dict(self) -> dict:
        return {"names": list(self.names), "units": list(self.units)}


def default_outputs(p: int, shorthand: bool) -> Outputs:
    if shorthand and p == 1:
        return Outputs(("position",), ("m",))
    return Outputs(tuple(f"y{j}" for j in range(p)), (DEFAULT_UNIT,) * p)


def _strings(t: Table, key: str, check, expect: str) -> list[str] | None:
    t._absent(key, None)
    if key not in t.data:
        return None
    v = t.data[key]
    if not (isinstance(v, list) and v and all(isinstance(x, str) and check(x) for x in v)):
        raise t.error(key, f"expected a list of {expect}, got {v!r:.60}")
    return v


def parse_outputs(t: Table | None, p: int | None, shorthand: bool) -> Outputs:
    """``[outputs]`` against the plant's number of outputs ``p`` (None: no plant, the table then
    says how many outputs there are and ``names`` is required)."""
    if t is None:
        return default_outputs(p, shorthand)
    names = _strings(t, "names", lambda s: bool(OUTPUT_NAME_RE.fullmatch(s)),
                     "output names (letters, digits and '_', not starting with a digit, at most 64)")
    units = _strings(t, "units", lambda s: 0 < len(s) <= UNIT_MAX and s.isprintable(),
                     f"units (printable text of 1 to {UNIT_MAX} characters)")
    t.done()
    if names is None:
        if p is None:
            raise t.error("names", "missing required key (a model without [plant] has one output per name)")
        names = list(default_outputs(p, shorthand).names)
    n = len(names) if p is None else p
    if len(names) != n:
        raise t.error("names", f"expected {n} names (one per output of the plant), got {len(names)}")
    if len(set(names)) != len(names):
        dup = next(x for x in names if names.count(x) > 1)
        raise t.error("names", f"expected unique names, got {dup!r} twice")
    if units is None:
        units = list(default_outputs(n, shorthand).units) if p is not None else [DEFAULT_UNIT] * n
    if len(units) != n:
        raise t.error("units", f"expected {n} units (one per output), got {len(units)}")
    return Outputs(tuple(names), tuple(units), given=True)
