"""Field paths of foreign messages, JSON and ROS alike: ``--measurement TOPIC:FIELD[,FIELD...]``.

A path is dotted names with ``[i]`` for list items (``/imu:linear_acceleration.x``,
``/joint_states:position[2]``); a final ``.*`` stands for every numeric field below it
(``/imu:angular_velocity.*``). One parser (:func:`parse_field_path`) serves both kinds.
"""

from __future__ import annotations

import re

from .errors import SeriesError

WILDCARD = "*"
"""The last part of a field path that stands for every numeric field below it (``.*``)."""

_PATH_RE = re.compile(r"([^.\[\]]+)|\[(\d+)\]")


def parse_field_path(path: str) -> tuple:
    """``a.b[2].c`` -> ``("a", "b", 2, "c")``; a final ``.*`` is :data:`WILDCARD` (every numeric
    field below). The one parser of field paths, JSON and ROS alike."""
    parts = tuple(int(idx) if idx else name for name, idx in _PATH_RE.findall(path))
    if not parts:
        raise SeriesError(f"field {path!r}: empty field path")
    if WILDCARD in parts[:-1]:
        raise SeriesError(f"field {path!r}: '*' stands only at the end of a path (e.g. linear_acceleration.*)")
    return parts


def field_getter(path: str):
    """(JSON object -> the value at ``path``, its parts)."""
    parts = parse_field_path(path)
    return getter_of(parts), parts


def getter_of(parts: tuple):
    def get(obj):
        for p in parts:
            obj = obj[p]
        return obj
    return get


def split_spec(spec: str) -> tuple[str, list[str]]:
    if ":" not in spec:
        raise SeriesError(f"--measurement {spec!r}: expected TOPIC:FIELD (e.g. /imu:linear_acceleration.x)")
    topic, fields = spec.rsplit(":", 1)
    return topic, [f.strip() for f in fields.split(",") if f.strip()]

