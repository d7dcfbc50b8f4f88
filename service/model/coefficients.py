"""A model's IEEE Std 952 coefficients per output (``noiselab diagnose --json``'s ``coefficients``).

Each effect says which coefficients it has (:meth:`.effects.base.Effect.coefficients`: N from the
white noise, K from the bias walk, the quantization step, ...); this module only collects them,
by output name, with the unit written in the output's unit (``model.output_units``):

    {output name: {coefficient name: {"value": v, "interval": [lo, hi] or None, "unit": text}}}

Intervals: a fitted parameter's 95 % profile-likelihood interval (the diagnosis' ``missing``
entries), mapped end to end through the coefficient's increasing relation to the parameter. The
diagnosis profiles one channel of a per-output parameter, the one whose value is the largest
(:func:`service.diagnose.search.interval_tasks`): the interval is given for the outputs holding that
largest value (all of them when the parameter is one value for every output) and is None for the
others, and for every coefficient whose parameter the diagnosis did not fit. A quantization step
is found exactly on the data's grid: each output's interval is its own step.
"""

from __future__ import annotations

import math

import numpy as np


def model_coefficients(model, intervals: dict | None = None) -> dict:
    """The coefficients of ``model``'s effects per output (module docstring). ``intervals``:
    {effect id: {parameter: [lo, hi]}} of the fitted parameters (catalogue spellings)."""
    out: dict = {name: {} for name in model.output_names}
    for eid, eff in model.effects.items():
        fitted = (intervals or {}).get(eid) or {}
        for c in eff.coefficients():
            vals = np.broadcast_to(np.asarray(c.value, float), (model.p,))
            ivs = _intervals(eff, c, fitted.get(c.param), vals)
            for j, name in enumerate(model.output_names):
                out[name][c.name] = {
                    "value": _num(vals[j]),
                    "interval": ivs[j],
                    "unit": c.unit.replace("{u}", model.output_units[j]),
                }
    return out


def _intervals(eff, c, iv, vals: np.ndarray) -> list:
    """Each output's interval of coefficient ``c`` (values ``vals``) from the diagnosis' interval
    ``iv`` of its parameter: the profiled output's (the largest value: ``c.of`` is increasing, so
    the largest parameter's), None for the others. A parameter found exactly on the data's grid (a
    quantization step, fit kind ``grid``) is each output's own value, [v, v]: the diagnosis gives
    the range of the outputs' steps there, not an interval of one."""
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
