"""What the viewers read from a :class:`~noiselab.diagnose.results.Comparison`: its outputs' names,
units and labels, where its data came from, what its model changed from the previous revision,
and the check of the shapes every viewer relies on (:func:`validate_comparisons`)."""

from __future__ import annotations

import re

import numpy as np

from noiselab.diagnose.results import VIEW_NAMES, VIEW_UNITS, Comparison, View


class ViewerInputError(ValueError):
    """Comparisons that cannot be drawn; the message names the field at fault."""


def view_unit(view_name: str, x_label: str = "") -> str:
    """Unit of a view's x values: the ``[...]`` of its x label, else the known unit of the view."""
    m = re.search(r"\[([^\]]+)\]", x_label or "")
    return m.group(1) if m else VIEW_UNITS.get(view_name, "")


def effect_ids(comparisons: list) -> list:
    """Every effect id with a contribution, in first-seen order (one colour per id everywhere)."""
    seen = []
    for c in comparisons:
        for v in c.views:
            for eid in v.contributions:
                if eid not in seen:
                    seen.append(eid)
    return seen


# -- what a Comparison says of its outputs, its recording and its model ----------------------------------
# ``output_names``, ``output_units`` (the model's ``[outputs]`` table), ``recording`` (where the data
# came from: "path [topic:field]" as the series loader words it) and ``model_effects`` ({effect id:
# parameters with the model file's names} of the compared model) are read where present, so that a
# Comparison without them is still drawn: its outputs are then ``out<i>`` in ``units``.
UNNAMED_OUTPUT = "out{}"
UNNAMED_UNIT = "units"      # the placeholder the views' labels carry (noiselab.diagnose.compare)


def output_names(c: Comparison) -> tuple:
    names = getattr(c, "output_names", None)
    p = np.asarray(c.y).shape[1]
    return tuple(names) if names is not None else tuple(UNNAMED_OUTPUT.format(j) for j in range(p))


def output_units(c: Comparison) -> tuple:
    units = getattr(c, "output_units", None)
    return tuple(units) if units is not None else (UNNAMED_UNIT,) * np.asarray(c.y).shape[1]


def output_label(c: Comparison, j: int) -> str:
    """``name [unit]`` of output ``j``."""
    return f"{output_names(c)[j]} [{output_units(c)[j]}]"


def with_unit(label: str, unit: str) -> str:
    """A view's axis label with the placeholder ``units`` replaced by the output's ``unit``: "PSD
    [units^2/Hz]" -> "PSD [(rad/s)^2/Hz]" (a compound unit is bracketed before a power)."""
    compound = any(ch in unit for ch in "/*· ^")

    def sub(m):
        return f"({unit}){m.group(1)}" if m.group(1) and compound else unit + (m.group(1) or "")

    return re.sub(r"\[([^\]]*)\]", lambda b: "[" + re.sub(r"\bunits\b(\^\d+)?", sub, b.group(1)) + "]", label)


def view_y_label(c: Comparison, v: View) -> str:
    return with_unit(v.y_label, output_units(c)[v.output])


def recording_of(c: Comparison) -> str | None:
    """Where the data came from (recording path, topic and field), when the comparison says."""
    src = getattr(c, "recording", None)
    return str(src) if src else None


def model_title(c: Comparison) -> str:
    """The compared model as the user named it (file or scenario), else its name."""
    return c.model_source if c.model_source and c.model_source != "<model>" else c.model_name


def _fmt_param(v) -> str:
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_fmt_param(x) for x in v) + "]"
    return f"{v:.4g}" if isinstance(v, (int, float, np.floating)) and not isinstance(v, bool) else str(v)


def _effects_of(c: Comparison) -> dict | None:
    eff = getattr(c, "model_effects", None)
    return dict(eff) if eff is not None else None


def model_changes(before: Comparison, after: Comparison) -> list:
    """What ``after``'s model has that ``before``'s has not, one phrase per effect: "+ sensor.tone
    (amplitude = 0.02, frequency_hz = 5)", "- actuator.white", "sensor.white: std 0.01 -> 0.012".
    Without ``model_effects`` the effect ids are those with a contribution in the views (no values)."""
    a, b = _effects_of(before), _effects_of(after)
    if a is None or b is None:
        a = {e: None for e in effect_ids([before])}
        b = {e: None for e in effect_ids([after])}
    out = []
    for eid, params in b.items():
        if eid not in a:
            vals = ", ".join(f"{k} = {_fmt_param(v)}" for k, v in (params or {}).items())
            out.append(f"+ {eid}" + (f" ({vals})" if vals else ""))
        elif params is not None and a[eid] is not None:
            ch = [f"{k} {_fmt_param(a[eid].get(k))} -> {_fmt_param(v)}" for k, v in params.items()
                  if _fmt_param(a[eid].get(k)) != _fmt_param(v)]
            if ch:
                out.append(f"{eid}: " + ", ".join(ch))
    out += [f"- {eid}" for eid in a if eid not in b]
    return out


def validate_comparisons(comparisons) -> list:
    """Check the shapes the viewers rely on; return the comparisons as a list (input order kept).

    Raises ViewerInputError naming the comparison (by revision) and the field at fault.
    """
    if isinstance(comparisons, Comparison):
        raise ViewerInputError("comparisons must be a list of Comparison, got a single Comparison")
    comps = list(comparisons)
    if not comps:
        raise ViewerInputError("comparisons is empty: nothing to draw")
    revs = []
    for k, c in enumerate(comps):
        if not isinstance(c, Comparison):
            raise ViewerInputError(f"comparisons[{k}] is a {type(c).__name__}, not a Comparison")
        who = f"comparison revision {c.revision}"
        revs.append(c.revision)
        t = np.asarray(c.t)
        if t.ndim != 1 or t.size == 0:
            raise ViewerInputError(f"{who}: t must be a non-empty 1-D array, found shape {t.shape}")
        n = t.size
        y = np.asarray(c.y)
        if y.ndim != 2 or y.shape[0] != n:
            raise ViewerInputError(f"{who}: y must be (N, p) = ({n}, p), found shape {y.shape}")
        for name in ("y_mean", "y_sd"):
            a = np.asarray(getattr(c, name))
            if a.shape != y.shape:
                raise ViewerInputError(f"{who}: {name} must have the shape of y {y.shape}, found {a.shape}")
        for name in ("output_names", "output_units"):
            a = getattr(c, name, None)
            if a is not None and (isinstance(a, str) or len(a) != y.shape[1]
                                  or not all(isinstance(s, str) and s for s in a)):
                raise ViewerInputError(f"{who}: {name} must give one non-empty string per output "
                                       f"({y.shape[1]}), found {a!r:.80}")
        if len(set(output_names(c))) != y.shape[1]:
            raise ViewerInputError(f"{who}: output_names must be distinct, found {output_names(c)}")
        if c.truth is not None:
            tr = np.asarray(c.truth)
            if tr.ndim != 2 or tr.shape[0] != n:
                raise ViewerInputError(f"{who}: truth must be (N, n) with N = {n}, found shape {tr.shape}")
        for v in c.views:
            if not isinstance(v, View):
                raise ViewerInputError(f"{who}: views holds a {type(v).__name__}, not a View")
            if v.name not in VIEW_NAMES:
                raise ViewerInputError(f"{who}: view name {v.name!r} is not one of {VIEW_NAMES}")
            if not 0 <= v.output < y.shape[1]:
                raise ViewerInputError(f"{who}: view {v.name} has output {v.output}, y has {y.shape[1]} outputs")
            m = np.asarray(v.x).shape
            if len(m) != 1:
                raise ViewerInputError(f"{who}: view {v.name} output {v.output}: x must be 1-D, found {m}")
            for name in ("empirical", "predicted", "lo", "hi"):
                if np.asarray(getattr(v, name)).shape != m:
                    raise ViewerInputError(f"{who}: view {v.name} output {v.output}: {name} has shape "
                                           f"{np.asarray(getattr(v, name)).shape}, x has {m}")
            for name in ("z", "flagged"):
                a = getattr(v, name)
                if a is not None and np.asarray(a).shape != m:
                    raise ViewerInputError(f"{who}: view {v.name} output {v.output}: {name} has shape "
                                           f"{np.asarray(a).shape}, x has {m}")
            for eid, a in v.contributions.items():
                if np.asarray(a).shape != m:
                    raise ViewerInputError(f"{who}: view {v.name} output {v.output}: contribution {eid!r} "
                                           f"has shape {np.asarray(a).shape}, x has {m}")
    if len(set(revs)) != len(revs):
        raise ViewerInputError(f"revisions must be distinct, found {revs}")
    return comps


def flag_mask(view: View) -> np.ndarray:
    n = np.asarray(view.x).size
    return np.zeros(n, bool) if view.flagged is None else np.asarray(view.flagged, bool)


def fmt_error(v: float) -> str:
    return "n/a" if v is None or not np.isfinite(v) else f"{v:.3g}"


def has_truth(c: Comparison, i: int) -> bool:
    """Truth to draw beside output ``i``: the recording has truth and a state ``x[i]``."""
    return c.truth is not None and i < np.asarray(c.truth).shape[1]


def truth_label(i: int) -> str:
    """The truth drawn beside output ``i`` is the plant's state ``x[i]`` (the shorthand plant
    measures y = x[0]); the recording holds states, not noise-free outputs."""
    return f"truth: state x[{i}]"
