"""The report's entries of a diagnosis: each step, each effect found (its parameters as the model
file spells them, their intervals and equivalent spellings, its score, mode and sentence of
evidence) and each first-step candidate. Built by :func:`.diagnose.diagnose` from its fits."""

from __future__ import annotations

import numpy as np

from ..model.effects import CATALOGUE
from ..model.effects.base import _g
from .data import Data
from .lines import own_params
from .modes import REFIT
from .results import fmt_score
from .thresholds import THRESHOLD


def band_of(fit, eid: str, data: Data):
    """Frequencies (Hz) over which ``eid`` holds most of the fitted spectrum of the differenced
    residual: where it is the physical effect's signature."""
    if not fit.parts or eid not in fit.parts:
        return None
    parts = fit.scaled_parts() if fit.v is not None else fit.parts   # at the fitted values

    def power(E):          # per group: summed over outputs (the diagonal of cross-spectral matrices)
        return np.einsum("bii->b", E).real if E.ndim == 3 else np.sum(E, axis=1)

    share = power(parts[eid]) / np.maximum(power(sum(parts.values())), 1e-300)
    idx = np.flatnonzero(share > 0.5)
    if idx.size == 0:
        return None
    end = idx[0]
    while end + 1 < share.size and share[end + 1] > 0.5:
        end += 1
    f = (data.starts + 0.5 * (data.sizes - 1)) / (data.M * data.Ts)
    return float(f[idx[0]]), float(f[end])


def step_entry(c, model, error, Ts: float) -> dict:
    """A step's entry in the report: candidate ``c`` as fitted in ``model``, the model error after."""
    return {"effect": c.effect, "mode": str(c.mode), "score": float(c.score),
            "error": None if error is None else float(error), "accepted_by": "error" if c.by_error else "bic",
            "params": report_params(c.effect, own_params(c, model), Ts)}


def changes(old: dict, new: dict) -> str:
    """``k old -> new`` for the parameters a refit changed (as the model file spells them)."""
    out = [f"{k} {_g(old[k])} -> {_g(v)}" for k, v in new.items()
           if k in old and not np.allclose(np.asarray(old[k], float), np.asarray(v, float), rtol=1e-6, atol=0)]
    return ", ".join(out) or "the same values"


def report_intervals(eid: str, iv: dict, Ts: float) -> dict:
    """The intervals, and the same for the equivalent spellings (monotone maps of the ends)."""
    out = dict(iv)
    for k, (lo, hi) in iv.items():
        e_lo = CATALOGUE[eid].equivalents({k: lo}, Ts)
        e_hi = CATALOGUE[eid].equivalents({k: hi}, Ts)
        for name in e_lo:
            if name not in out and name in e_hi:
                a, b = e_lo[name], e_hi[name]
                if isinstance(a, (int, float)) and isinstance(b, (int, float)):
                    out[name] = [min(a, b), max(a, b)]
    return out


def report_intervals_per_output(eid: str, per: dict, Ts: float) -> dict:
    """Each output's intervals of the parameters fitted per output ({name: [[lo, hi] or None, one
    per output]}: :func:`.intervals.interval_tasks`), and the same for the equivalent spellings, as
    :func:`report_intervals` gives them for one interval."""
    n = max((len(v) for v in per.values()), default=0)
    each = [report_intervals(eid, {k: v[j] for k, v in per.items() if v[j] is not None}, Ts) for j in range(n)]
    return {k: [e.get(k) for e in each] for k in dict.fromkeys(k for e in each for k in e)}


def report_params(eid: str, params: dict, Ts: float) -> dict:
    out = dict(params)
    for k, v in CATALOGUE[eid].equivalents(params, Ts).items():
        out.setdefault(k, v)
    return out


def missing_entry(c, iv_c: dict, per_c: dict, cur, model, data: Data) -> dict:
    """Candidate ``c``'s entry in the report's ``missing``: its parameters as fitted in ``cur``, its
    intervals (``iv_c``, per output ``per_c``), score, mode and sentence of evidence."""
    params = own_params(c, cur.model)
    iv = report_intervals(c.effect, iv_c, model.Ts)
    iv_per = report_intervals_per_output(c.effect, per_c, model.Ts)
    band = band_of(cur, c.effect, data)
    alts = [{"effect": a.effect, "mode": str(a.mode), "score": float(a.score),
             "params": report_params(a.effect, a.fit.model.effects[a.effect].param_dict(), model.Ts)}
            for a in c.alternatives if a.effect in a.fit.model.effects]
    evidence = CATALOGUE[c.effect].explain(params, model.Ts, {"band": band} if band else None)
    if c.mode == REFIT and c.effect in model.effects:
        # a changed value: what the user's model said, and what the data say (the effect's own
        # sentence describes it as an excess over nothing, which a changed value is not)
        evidence = (f"the model's value does not fit the data ({changes(own_params(c, model), params)}); "
                    f"refitted: {evidence.rsplit(': ', 1)[-1]}")
    if c.by_error:
        e0, e1 = c.by_error
        evidence += (f"; added on the views' word: Delta BIC {fmt_score(c.score)} is under the threshold "
                     f"{THRESHOLD:g}, but it takes the model error from {e0:.3g} to {e1:.3g}")
    if alts:
        evidence += "; the data support " + " and ".join(
            f"{a.effect} ({', '.join(f'{k} = {_g(v)}' for k, v in a.fit.model.effects[a.effect].param_dict().items())})"
            for a in [a for a in c.alternatives if a.effect in a.fit.model.effects][:2]) + " as well"
    return {
        "effect": c.effect,
        "params": report_params(c.effect, params, model.Ts),
        "interval": {k: [float(a) for a in v] for k, v in iv.items()},
        "intervals_per_output": {k: [None if x is None else [float(a) for a in x] for x in v]
                                 for k, v in iv_per.items()},
        "score": float(c.score),
        "mode": str(c.mode),
        "accepted_by": "error" if c.by_error else "bic",
        "evidence": evidence,
        "alternatives": alts,
    }


def candidate_entry(c, Ts: float) -> dict:
    """A first step's candidate in the report's ``candidates``."""
    return {"effect": c.effect, "mode": str(c.mode), "score": float(c.score),
            "params": report_params(c.effect, c.fit.model.effects[c.effect].param_dict(), Ts)
            if c.effect in c.fit.model.effects else {}}
