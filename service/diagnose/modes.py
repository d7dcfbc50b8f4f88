"""How a candidate changes the model: its mode.

* ``add``: the effect is not in the model; it is added with its fitted values;
* ``refit``: the effect is in the model but a value is wrong; its parameters are freed and refitted;
* ``replace``: the effect takes the place of one the model has (``FitSpec.replaces``: colored
  actuator noise for the white actuator noise the user wrote);
* ``add`` of a line (``line``): one more line of an effect that holds several (``repeatable``: a
  tone's), beside those the model has; undone by removing that line alone.

The JSON report spells a mode as ``"add"``, ``"refit"`` or ``"replace:<effect id>"`` (``str(mode)``;
:meth:`Mode.parse` reads it back).
"""

from __future__ import annotations

from dataclasses import dataclass

MODE_RANK = {"replace": 0, "refit": 1, "add": 2}
"""Near-ties (the data cannot tell the candidates apart) are ranked by mode: a replacement, then a
changed value, then an addition (the fewest effects: a wrong value of an effect the user has
explains the data with no new physics)."""

EXACT_RANK = {"replace": 0, "add": 1, "refit": 2}
"""On an exact tie (identical spectra) an addition goes before a changed value: nothing in the data
contradicts the user's value, so it is kept."""


@dataclass(frozen=True)
class Mode:
    kind: str                       # "add" | "refit" | "replace"
    replaces: str | None = None     # the effect id replaced (kind "replace")
    line: bool = False              # an added line of a repeatable effect (kind "add")

    def __post_init__(self):
        if self.kind not in MODE_RANK or (self.kind == "replace") != (self.replaces is not None) \
                or (self.line and self.kind != "add"):
            raise ValueError(f"not a candidate mode: {self.kind!r} {self.replaces!r} {self.line!r}")

    @classmethod
    def parse(cls, text: str) -> Mode:
        """The mode a JSON report spells ``text`` (``"replace:actuator.white"``)."""
        kind, _, rep = text.partition(":")
        return cls(kind, rep or None)

    @property
    def rank(self) -> int:
        """:data:`MODE_RANK` of the kind (lower first)."""
        return MODE_RANK[self.kind]

    @property
    def exact_rank(self) -> int:
        """:data:`EXACT_RANK` of the kind (lower first)."""
        return EXACT_RANK[self.kind]

    def phrase(self) -> str:
        """The mode in a sentence: ``add``, ``add a line``, ``refit``, ``in place of <effect id>``."""
        if self.line:
            return "add a line"
        return self.kind if self.replaces is None else f"in place of {self.replaces}"

    def __str__(self) -> str:
        return self.kind if self.replaces is None else f"{self.kind}:{self.replaces}"


ADD = Mode("add")
ADD_LINE = Mode("add", line=True)
REFIT = Mode("refit")


def replacing(eid: str) -> Mode:
    """The mode of a candidate that takes the place of effect ``eid``."""
    return Mode("replace", eid)
