"""The diagnosis as JSON (``noiselab diagnose --json``) and as text.

Each ``missing`` entry gives its fitted parameters' 95 % profile-likelihood intervals twice:

* ``interval``: {parameter: [lo, hi]}, one interval per parameter (and per equivalent spelling).
  For a parameter fitted one value per output it is the interval of the output whose value is the
  largest (as for one fitted per input: an actuator noise's of several inputs);
* ``intervals_per_output``: {parameter: [[lo, hi] or null, one per output, in the model's output
  order]} for the parameters fitted one value per output (a sensor noise's std, a scale factor,
  a tone's amplitude, a quantization step, on a model of several outputs): each output's own
  interval, from the profile over that output's value with every other free value re-optimized
  (:func:`.intervals.interval_tasks`); {} when no parameter is fitted per output (one output, or one
  value for all of them).

``coefficients`` (:func:`noiselab.model.coefficients.model_coefficients`) takes each output's
coefficient interval from its own interval.
"""

from __future__ import annotations

import numpy as np

from ..model.coefficients import model_coefficients
from .modes import Mode
from .results import VIEW_UNITS as UNITS
from .results import fmt_score


def _clean(v):
    """JSON-safe values: floats (NaN/inf -> None), lists, dicts."""
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_clean(x) for x in v]
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return f if np.isfinite(f) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


def diagnosis_json(rep: dict, series=None, extra: dict | None = None) -> dict:
    """DESIGN.md's fields (``error_before``, ``error_after``, ``missing``) and the extensions."""
    out = {k: rep[k] for k in ("error_before", "error_after", "missing", "steps", "candidates", "samples",
                               "Ts", "threshold", "seconds")}
    out["error_per_view_before"] = rep["before"].error_per_view
    out["error_per_view_after"] = rep["after"].error_per_view
    out["regions"] = [{"view": r.view, "output": r.output, "from": r.x_lo, "to": r.x_hi, "points": r.points,
                       "max_abs_z": r.max_abs_z, "direction": r.direction} for r in rep["before"].regions]
    out["model"] = rep["before"].model_name
    out["model_source"] = rep["before"].model_source
    out["notes"] = (list(series.notes) if series is not None else []) + list(rep.get("notes", []))
    if series is not None:
        out["recording"] = series.source
        out["command"] = series.command        # recorded, or the model's own assumed (load.command_used)
    out["coefficients"] = fitted_coefficients(rep)
    fb = rep.get("feedback")
    out["closed_loop"] = None if fb is None else {"F": fb.F, "p_value": fb.p_value, "r2": fb.r2,
                                                  "fed_back_hz": [float(f) for f in rep.get("fed_back", [])],
                                                  "scale_factor_reach": rep.get("scale_factor_reach")}
    out.update(extra or {})
    return _clean(out)


def fitted_coefficients(rep: dict) -> dict:
    """The IEEE Std 952 coefficients of the diagnosis' fitted model (``rep["model"]``: the input
    model with the effects found added or refitted), with the profile intervals of the parameters
    the diagnosis fitted, each output's own where it has one
    (:func:`noiselab.model.coefficients.model_coefficients`)."""
    return model_coefficients(rep["model"], {m["effect"]: m.get("interval") or {} for m in rep["missing"]},
                              {m["effect"]: m.get("intervals_per_output") or {} for m in rep["missing"]})


def coefficient_lines(coeffs: dict) -> list[str]:
    """The coefficients as report lines, one per output that has any."""
    lines = [f"  {name}: " + ", ".join(_coefficient_text(k, c) for k, c in cs.items())
             for name, cs in coeffs.items() if cs]
    return ["IEEE Std 952 coefficients of the fitted model ([95 % interval] where fitted):"] + lines if lines else []


def _coefficient_text(k: str, c: dict) -> str:
    v = "n/a" if c["value"] is None else _fmt(c["value"])
    iv = "" if c["interval"] is None else f" [{_fmt(c['interval'][0])}, {_fmt(c['interval'][1])}]"
    return f"{k} = {v}{iv} {c['unit']}"


def region_lines(regions, limit: int) -> list[str]:
    """Where the data leave the model, the strongest first (at most ``limit`` lines)."""
    if not regions:
        return []
    lines = ["where the data leave the model:"]
    lines += ["  " + r.describe(UNITS[r.view]) for r in sorted(regions, key=lambda r: -r.max_abs_z)[:limit]]
    if len(regions) > limit:
        lines.append(f"  (+{len(regions) - limit} more regions)")
    return lines


def diagnosis_lines(rep: dict, series=None, extra: dict | None = None) -> list[str]:
    b, a = rep["before"], rep["after"]
    src = f"{series.source}: " if series is not None else ""
    lines = [f"{src}{rep['samples']} samples against model {b.model_name} ({b.model_source})",
             f"model error before: {b.error:.3g} (about 1 when the model explains the data; per view: "
             + ", ".join(f"{k} {v:.3g}" for k, v in b.error_per_view.items()) + ")"]
    lines += region_lines(b.regions, 8)
    if not rep["missing"]:
        lines.append(f"nothing missing: no effect of the catalogue improves the fit by Delta BIC > {rep['threshold']:g}")
        if rep["candidates"]:
            c = rep["candidates"][0]
            ps = ", ".join(f"{k} = {_fmt(v)}" for k, v in c["params"].items() if k in _file_keys(rep, c))
            lines.append(f"  (best candidate: {c['mode']} {c['effect']}, Delta BIC {fmt_score(c['score'])}"
                         + (f": {ps}" if ps else "") + ")")
    else:
        lines.append("missing, most likely first (Delta BIC; model error after adding it):")
        for i, (m, st) in enumerate(zip(rep["missing"], rep["steps"]), 1):
            ps = ", ".join(_param_text(k, v, m) for k, v in m["params"].items() if k in _file_keys(rep, m))
            what = Mode.parse(m["mode"]).phrase()
            lines.append(f"  {i}. [{m['effect']}] {what}: {ps}   (Delta BIC {fmt_score(m['score'])}; "
                         f"error {st['error']:.3g})")
            lines.append(f"     {m['evidence']}")
        lines.append(f"model error: {rep['error_before']:.3g} -> " + " -> ".join(f"{s['error']:.3g}" for s in rep["steps"])
                     + (f" (final joint fit {a.error:.3g})" if abs(a.error - rep['steps'][-1]['error']) > 1e-9 else ""))
    lines += coefficient_lines(fitted_coefficients(rep))
    for note in (list(series.notes) if series is not None else []) + list(rep.get("notes", [])):
        lines.append(f"note: {note}")
    for k in ("fit_out", "rrd", "png"):
        if extra and extra.get(k):
            lines.append(f"wrote {extra[k]}")
    return lines


def _file_keys(rep: dict, m: dict) -> set:
    """The parameters as the fitted model file spells them (the JSON also carries equivalents)."""
    eff = rep["model"].effects.get(m["effect"])
    return set(eff.param_dict()) if eff is not None else set(m["params"])


def _fmt(v, digits: int = 4) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x, digits) for x in v) + "]"
    return f"{float(v):.{digits}g}"


def _param_text(k: str, v, m: dict) -> str:
    """A fitted parameter with its interval: ``k = v [lo, hi]``; fitted per output,
    ``k = [v0 [lo0, hi0], v1 [lo1, hi1], ...]``, each output's value beside its own interval (a
    value that is its own interval, a quantization step found on the data's grid, alone)."""
    per = (m.get("intervals_per_output") or {}).get(k)
    if isinstance(v, list) and per is not None and len(per) == len(v):
        return f"{k} = [" + ", ".join(_fmt(x) if iv is None or iv[0] == iv[1] else _with_interval(None, x, iv)
                                      for x, iv in zip(v, per)) + "]"
    return _with_interval(k, v, m["interval"][k]) if k in m["interval"] else f"{k} = {_fmt(v)}"


def _with_interval(k: str | None, v, iv) -> str:
    """``k = v [lo, hi]`` (k None: ``v [lo, hi]``) with as many digits (4 to 10) as it takes to
    tell lo, v and hi apart (a tone's frequency interval is a few parts in 10^6 wide); where v sits
    on an end, lo and hi."""
    lo, hi = iv
    texts = [(_fmt(lo, d), _fmt(v, d), _fmt(hi, d)) for d in range(4, 11)]
    a, b, c = next((t for t in texts if len(set(t)) == 3), next((t for t in texts if t[0] != t[2]), texts[0]))
    return (f"{k} = " if k is not None else "") + f"{b} [{a}, {c}]"
