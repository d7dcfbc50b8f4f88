"""An effect of several lines (``repeatable``: a tone's) in the diagnosis' steps, undo and report:
each line found is a candidate of its own, told from the others by its frequency (a line's
frequency moves a little in the joint refits after its step, never past another's)."""

from __future__ import annotations

import numpy as np


def line_hz(c) -> float:
    """The frequency (Hz, its largest over the outputs) of the line candidate ``c`` of a
    ``repeatable`` effect fitted: the line its fit holds as the fitted one (``all_lines()[0]``)."""
    return float(np.max(c.fit.model.effects[c.effect].all_lines()[0][1]))


def nearest_line(eff, hz: float) -> int:
    """The index in ``eff.all_lines()`` of the line nearest ``hz`` (a line's frequency moves a
    little in the joint refits after its step)."""
    return int(np.argmin([abs(float(np.max(f)) - hz) for _, f in eff.all_lines()]))


def lines_params(eff, hz: list, extra: list) -> dict:
    """The parameters of ``eff`` (``repeatable``) holding only its lines nearest the frequencies
    ``hz`` (the first the fitted one) and ``extra``, in that order."""
    lines = eff.all_lines()
    pick = [nearest_line(eff, h) for h in list(hz) + list(extra)]
    pick = list(dict.fromkeys(pick))                   # each line once
    scale = type(eff).fit.scale
    params = {k: v for k, v in eff.param_dict().items() if k not in (scale, "frequency_hz", "lines")}
    params[scale], params["frequency_hz"] = (plain_list(v) for v in lines[pick[0]])
    if len(pick) > 1:
        params["lines"] = [{scale: plain_list(lines[i][0]), "frequency_hz": plain_list(lines[i][1])} for i in pick[1:]]
    return params


def without_line(eff, hz: float) -> dict:
    """The parameters of ``eff`` (``repeatable``) without its line nearest ``hz``: that line put
    first (the fitted one) and popped (:meth:`.effects.base.Effect.pop_line` undoes a push)."""
    lines = eff.all_lines()
    i = nearest_line(eff, hz)
    keep = [ln for k, ln in enumerate(lines) if k != i]
    params = eff.param_dict()
    scale = type(eff).fit.scale
    params[scale], params["frequency_hz"] = (plain_list(v) for v in keep[0])
    if len(keep) > 1:
        params["lines"] = [{scale: plain_list(a), "frequency_hz": plain_list(f)} for a, f in keep[1:]]
    else:
        params.pop("lines", None)
    return params


def plain_list(v):
    v = np.asarray(v, float)
    return float(v[0]) if np.all(v == v[0]) else [float(x) for x in v]


def own_params(c, model) -> dict:
    """Candidate ``c``'s parameters in ``model``: the effect's, or for an effect of several lines
    (``repeatable``) the line ``c`` found (the nearest to its frequency)."""
    eff = model.effects[c.effect]
    if not type(eff).repeatable:
        return eff.param_dict()
    a, f = eff.all_lines()[nearest_line(eff, line_hz(c))]
    return {type(eff).fit.scale: plain_list(a), "frequency_hz": plain_list(f)}
