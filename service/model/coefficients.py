"""A model's IEEE Std 952 coefficients per output (``noiselab diagnose --json``'s ``coefficients``).

Each effect says which coefficients it has (:meth:`.effects.base.Effect.coefficients`: N from the
white noise, K from the bias walk, the quantization step, ...); this module only collects them,
by output name, with the unit written in the output's unit (``model.output_units``):

    {output name: {coefficient name: {"value": v, "interval": [lo, hi] or None, "unit": text}}}

Intervals: a fitted parameter's 95 % profile-likelihood interval, mapped end to end through the
coefficient's increasing relation to the parameter. A parameter fitted one value per output (a
sensor noise's std of a model of several outputs) has each output's own interval, from the
profile over that output's value (the diagnosis' ``missing[i].intervals_per_output``:
:func:`noiselab.diagnose.intervals.interval_tasks`), and each output's coefficient gets its own. A
parameter fitted as one value (or one factor) for every output has one interval (``missing[i].
interval``), given to every output holding the largest value (all of them when the value is one);
without the per-output intervals, only those outputs get one. None for every coefficient whose
parameter the diagnosis did not fit. A quantization step is found exactly on the data's grid:
each output's interval is its own step.
"""

from __future__ import annotations

import math

import numpy as np


def model_coefficients(model, intervals: dict | None = None, per_output: dict | None = None) -> dict:
    """The coefficients of ``model``'s effects per output (module docstring). ``intervals``:
    {effect id: {parameter: [lo, hi]}} of the fitted parameters (catalogue spellings);
    ``per_output``: {effect id: {parameter: [[lo, hi] or None, one per output]}} of those fitted
    per output."""
    out: dict = {name: {} for name in model.output_names}
    for eid, eff in model.effects.items():
        fitted = (intervals or {}).get(eid) or {}
        each = (per_output or {}).get(eid) or {}
        for c in eff.coefficients():
            vals = np.broadcast_to(np.asarray(c.value, float), (model.p,))
            own = each.get(c.param)
            ivs = [_mapped(c, iv) for iv in own] if own is not None and len(own) == model.p else \
                _intervals(eff, c, fitted.get(c.param), vals)
            for j, name in enumerate(model.output_names):
                out[name][c.name] = {
                    "value": _num(vals[j]),
                    "interval": ivs[j],
                    "unit": c.unit.replace("{u}", model.output_units[j]),
                }
    return out


def _intervals(eff, c, iv, vals: np.ndarray) -> list:
    """Each output's interval of coefficient ``c`` (values ``vals``) from the diagnosis' one
    interval ``iv`` of its parameter: the outputs' holding the largest value (the one it is of:
    ``c.of`` is increasing, so the largest parameter's), None for the others. A parameter found
    exactly on the data's grid (a quantization step, fit kind ``grid``) is each output's own
    value, [v, v]: the diagnosis gives the range of the outputs' steps there, not an interval of
    one."""
    p = vals.size
    if iv is None:
        return [None] * p
    if type(eff).fit.kind == "grid" and c.param in eff.params:
        own = np.broadcast_to(np.asarray(eff.params[c.param], float), (p,))
        return [_mapped(c, [v, v]) for v in own]
    mapped = _mapped(c, iv)
    top = float(np.max(vals))
    return [mapped if v == top else None for v in vals]


def _mapped(c, iv) -> list | None:
    if iv is None or len(iv) != 2 or any(x is None for x in iv):
        return None
    lo, hi = (float(np.asarray(c.of(np.asarray(float(x)))).ravel()[0]) for x in iv)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return None
    return [min(lo, hi), max(lo, hi)]


def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def coefficient_values(model, name: str) -> np.ndarray | None:
    """Coefficient ``name``'s values per output (p,); None when no effect of the model has it."""
    for eff in model.effects.values():
        for c in eff.coefficients():
            if c.name == name:
                return np.broadcast_to(np.asarray(c.value, float), (model.p,)).copy()
    return None


def white_density(model) -> np.ndarray | None:
    """The white-noise density per output (p,), units/sqrt(Hz): the white coefficients (N, the
    quantization's N_q) added in quadrature, sqrt(sum N_i^2), as independent white noises add; what
    a tool that models only white noise at the sample rate calls the noise density (Kalibr). None
    when the model has no white noise."""
    parts = [np.broadcast_to(np.asarray(c.value, float), (model.p,))
             for eff in model.effects.values() for c in eff.coefficients() if c.white]
    return np.sqrt(np.sum(np.square(parts), axis=0)) if parts else None
