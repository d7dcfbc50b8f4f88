"""The series the analysis and the diagnosis take, and the checks every series passes.

A :class:`Series` is a recording made regular: times from the first kept sample, the measurement
(and the command and the truth when recorded), and notes saying what was wrong with the record.
Gaps (a missing seq, or a time step over 1.5 Ts) are never silently ignored: the analysis uses
the longest gap-free run (:func:`longest_run`) and the notes say what was left out. Irregular
timing (steps that differ from Ts by more than 0.1 % of Ts, or by more than 4 resolutions of the
time field when that is coarser) is noted; a median step more than 1 % from the model's Ts is
refused (:func:`check_period`).

Every value the analysis uses (measurement, command, truth) is at most
:data:`~noiselab.bounds.MAGNITUDE_MAX` (1e50) in magnitude, the one bound of every number
noiselab computes with (a model file's too): the estimators square the data, sum the squares
over the record and square again (the spread of a variance estimate, the likelihood of a fit),
which must stay finite in float64. A larger value is refused (:func:`check_magnitude`), naming
the topic, the field and the seq, instead of an overflow deep in an estimator.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..bounds import MAGNITUDE_MAX
from .errors import SeriesError


@dataclass
class Series:
    """A recording made regular for the analysis and the diagnosis (the module docstring): the
    longest gap-free run of samples, times in s from its first one."""

    t: np.ndarray                  # (N,) s, from the first kept sample's clock
    y: np.ndarray                  # (N, p)
    u: np.ndarray | None           # (N, m) recorded command or None
    truth: np.ndarray | None       # (N, n) or None
    source: str
    notes: list = field(default_factory=list)
    starts_at_rest: bool = False   # a noiselab stream from seq 0 (the emulator starts at rest)
    command: dict | None = None    # the command analysed (command_used), None when no model was given
    names: list | None = None      # a foreign recording's field per column of y (``.*`` expanded)
    units: list | None = None      # their units where the message type fixes them (ROS: REP 103), else None
    Ts: float | None = None        # s: the period the timing was checked against (the model's, or the median step)


ASSUMED_COMMAND = "no command topic in the recording: the analysis assumes"
"""How the note that names an assumed command begins (:func:`command_used`, :func:`command_note`)."""


def command_note(series: Series) -> str | None:
    """The note naming the command the analysis assumed for want of a recorded one, or None."""
    if not series.command or series.command.get("source") != "model":
        return None
    return next((n for n in series.notes if n.startswith(ASSUMED_COMMAND)), None)


def command_used(model, topic: str | None, notes: list) -> dict | None:
    """What the analysis takes as the plant's command, JSON-ready: ``{"source": "recording",
    "topic": ...}``, or ``{"source": "model", "kind": ..., <the [command] table's parameters>}``
    when the recording has no command topic (a sensor at rest has none); the latter is also said
    in ``notes``, since the model's own command then stands in for what was applied. None without
    a model, or when the model has no input."""
    if topic is not None:
        return {"source": "recording", "topic": topic}
    if model is None or model.m == 0:
        return None
    table = dict(model.to_dict().get("command") or {"kind": "none"})
    kind = table.pop("kind", "none")
    if kind in ("none", "external"):
        said = f"no command (zero input; the model's [command] kind = {kind!r})"
    else:
        said = f"the model's own command ([command] kind = {kind!r}, " + ", ".join(
            f"{k} = {v}" for k, v in table.items()) + ")"
    notes.append(f"{ASSUMED_COMMAND} {said}")
    return {"source": "model", "kind": kind, **table}


def check_magnitude(values: np.ndarray, where: str, field, index: np.ndarray, label: str) -> None:
    """Refuse a value beyond +-MAGNITUDE_MAX (the module docstring) in one line naming ``where``
    (path and topic), the field (``field[j]`` of a vector field, or the j-th of a list of field
    names) and the sample's ``label`` (seq, or sample) ``index[i]``."""
    bad = np.abs(values) > MAGNITUDE_MAX
    if not bad.any():
        return
    i, j = (int(a) for a in np.argwhere(bad)[0])
    name = field[j] if isinstance(field, (list, tuple)) else f"{field}[{j}]"
    raise SeriesError(f"{where}: {name} = {values[i, j]:.6g} at {label} {int(index[i])} is beyond "
                        f"+-{MAGNITUDE_MAX:g}, more than the analysis can square in float64 (wrong units or "
                        "a corrupted sample?)")


def best_run(seq: np.ndarray) -> tuple[int, int]:
    """(start, stop) of the longest run of consecutive seqs (the first of equal ones)."""
    breaks = np.flatnonzero(np.diff(seq) != 1)
    starts = np.concatenate([[0], breaks + 1])
    ends = np.concatenate([breaks + 1, [seq.size]])
    i = int(np.argmax(ends - starts))
    return int(starts[i]), int(ends[i])


def longest_run(seq: np.ndarray, notes: list, what: str) -> slice:
    breaks = np.flatnonzero(np.diff(seq) != 1)
    if breaks.size == 0:
        return slice(0, seq.size)
    a, b = best_run(seq)
    missing = int(np.sum(np.clip(np.diff(seq)[breaks] - 1, 0, None)))
    notes.append(f"{what}: {breaks.size} gaps ({missing} samples missing); analysed the longest gap-free run, "
                 f"samples {a}..{b - 1} of {seq.size}")
    return slice(a, b)


def record_step(t: np.ndarray, where: str, what: str, notes: list) -> float:
    """The record's median sample step [s], the period of a series read without a model."""
    step = float(np.median(np.diff(t)))
    if not step > 0.0:
        raise SeriesError(f"{where}: the median step between sample times is 0 (repeated stamps): no sample "
                            "period; give --time FIELD or --model")
    notes.append(f"{what}: no model: the sample period is the record's median step, Ts = {step:.6g} s")
    return step


def check_period(dt: np.ndarray, Ts: float, what: str, notes: list) -> None:
    """The record's sample step against the model's Ts: more than 1 % apart is an error; more than
    0.1 % (the regular-timing tolerance) a note, since the model's dynamics, noise densities and
    lags are then evaluated at a period the data do not have (a clock 0.5 % off moves a resonance
    by 0.5 % and shows in the ACF and PSD views)."""
    med = float(np.median(dt))
    if not np.isclose(med, Ts, rtol=0.01):
        raise SeriesError(f"{what}: the median sample step is {med:.6g} s but the model's Ts is {Ts:g} s")
    ok = dt[dt < 1.5 * Ts]
    mean = float(np.mean(ok)) if ok.size else med
    if abs(mean / Ts - 1.0) > 1e-3:
        notes.append(f"{what}: the mean sample step is {mean:.6g} s, {(mean / Ts - 1.0) * 100:+.2g} % from the "
                     f"model's Ts = {Ts:g} s: the model is evaluated at its Ts (set [sampling] Ts to the "
                     "record's if its clock is right)")


def regular_run(t: np.ndarray, Ts: float, notes: list, what: str, resolution: float = 1e-9) -> slice:
    dt = np.diff(t)
    check_period(dt, Ts, what, notes)
    gaps = dt > 1.5 * Ts
    tol = max(1e-3 * Ts, 4.0 * resolution)
    jitter = np.abs(dt[~gaps] - Ts) > tol
    if np.any(jitter):
        notes.append(f"{what}: irregular timing: {int(jitter.sum())} steps differ from Ts by more than "
                     f"{tol / Ts * 100:.2g} % (std {np.std(dt[~gaps]) / Ts * 100:.2g} % of Ts, max "
                     f"{np.max(np.abs(dt[~gaps] - Ts)) / Ts * 100:.2g} %); analysed as if regular")
    if not np.any(gaps):
        return slice(0, t.size)
    seq = np.concatenate([[0], np.cumsum(np.where(gaps, np.round(dt / Ts), 1))]).astype(np.int64)
    return longest_run(seq, notes, f"{what} time")
