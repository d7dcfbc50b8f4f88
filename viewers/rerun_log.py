"""Comparisons (``service.diagnose.results``) -> one Rerun ``.rrd`` file whose blueprint tells the
story on one screen: the data against the model, where they part, and the model error falling
across revisions.

Every Rerun call here was checked against the installed rerun-sdk **0.41.0** (package source in
``site-packages/rerun``): ``rr.RecordingStream(app_id, recording_id=...)``, ``.binary_stream()``
(the .rrd encoded in memory; ``BinaryStream.read(flush=True)`` gives it, footer included),
``.send_blueprint(bp, make_active=False, make_default=True)`` (what ``.save(path,
default_blueprint=bp)`` sends), ``.send_columns(path, indexes=[rr.TimeColumn(name, duration=timedelta64[ns]
| sequence=ints)], columns=rr.Scalars.columns(scalars=...))`` (a (N, 2) array gives two scalars per
row; float seconds are *truncated* to ns by TimeColumn, so times are rounded here first),
``rr.Scalars`` / ``rr.SeriesLines`` / ``rr.SeriesPoints`` (the plural archetypes; ``rr.Scalar`` and
``rr.SeriesLine`` are gone),
``rr.LineStrips2D``, ``rr.Points2D``, ``rr.AnyValues``, ``rr.TextDocument(..., media_type=
rr.MediaType.MARKDOWN)``, ``rerun.blueprint`` (``Blueprint``, ``Horizontal``, ``Vertical``, ``Tabs``,
``TimeSeriesView``, ``Spatial2DView``, ``TextDocumentView``, ``TimeAxis``, ``VisualBounds2D``,
``TimePanel``), and ``.flush()`` + ``.disconnect()``. The bytes are written to the file by
Python, not by Rerun's file sink: a sink whose file fails (a full disk) hangs ``save``, raises a
RuntimeError without the OS's reason from ``flush``, logs its errors on stderr and warns at exit
of the data it dropped; an OSError from Python names the reason and leaves nothing behind.
``rerun.chunk.RrdReader(path).store()`` opens the file (it needs the footer, the manifest).

Entity layout (r = ``Comparison.revision``, o = output name, v = view name, e = effect id)
-----------------------------------------------------------------------------------------
Output names are the model's ``[outputs]`` names (identifiers, so valid path parts as they
stand; :func:`output_names`), units its units: axis labels read ``name [unit]`` and the views'
``units`` placeholder becomes the output's unit (:func:`with_unit`).

recording property ``source``       AnyValues ``recording`` (path, topic and field the data came
                                    from), ``model``, ``output_names``, ``output_units``
                                    (``/__properties/source`` when read back); the recording's name
                                    says "<recording> against <model>".
``/report``                         TextDocument (markdown): the recording, the outputs, model error
                                    per revision, what each revision changed (effects added with
                                    their fitted values, removed, refitted), the regions'
                                    ``describe()`` lines, notes. Static.
``/error/overall``, ``/error/<v>``  Scalars on the sequence timeline ``revision``: one row per
                                    revision (the model error and the per-view errors).
``/error/chart/...``                the same numbers as a 2D chart (log10 error vs revision, see below).
``/data/<o>/{measurement,truth}``   the data, once (the revisions compare models with the same
                                    recording; a comparison whose t, y or truth differ from the
                                    first one's gets its own ``/rev<r>/<o>/data``): Scalars on the
                                    duration timeline ``t`` (sample time, integer ns), sent with
                                    ``send_columns`` (one chunk per series, N rows). ``truth`` beside
                                    output i is state x[i] (the shorthand plant measures y = x[0]),
                                    logged when truth is present and i < n.
``/rev<r>``                         AnyValues: model name and source, error, the recording, the
                                    output names and units, ``changes`` from the previous revision.
``/rev<r>/<o>/series/{mean,band}``
                                    the model's predicted mean and the band mean -+ 2 sd (two
                                    scalars per row), on ``t`` likewise.
``/rev<r>/<o>/variance/{empirical,predicted,band,flagged,contrib/<e>}``
                                    Scalars on ``t`` (x = window centre time), ``flagged`` only at
                                    the flagged windows (red markers). Parent: raw View (AnyValues).
``/rev<r>/<o>/{acf,psd,allan}``  AnyValues: the View's raw arrays (x, z, flagged, error, ...) and
                                    the plot's axis mapping.
``/rev<r>/<o>/{acf,psd,allan}/plot/...``
                                    the 2D plot: ``empirical`` (+ ``empirical_points``),
                                    ``predicted``, ``band``, ``contrib/<e>``, ``previous`` (the
                                    previous revision's prediction, grey), ``flagged`` (red points),
                                    ``regions`` (red bars along the bottom, one per Region),
                                    ``axes/{frame,grid,ticks,titles}``, ``legend/...``. Each data
                                    entity also carries its raw values as AnyValues ``x``, ``y``
                                    (float64, exactly the Comparison's numbers), so a hover or the
                                    selection panel shows them and scripts can read them back.

Why 2D views for ACF, PSD, Allan deviation and the error chart
-------------------------------------------------------------
A Rerun TimeSeriesView has no logarithmic axis (open feature request rerun-io/rerun#6773;
``rrb.ScalarAxis`` only has ``range``/``zoom_lock`` in 0.41) and always plots against the timeline
selected in the time panel (rerun-io/rerun#6828, #8050). A frequency, lag or tau timeline would
therefore only show while it is selected, i.e. never on the same screen as the time series. So
those views are drawn as geometry in ``Spatial2DView`` s: every curve is a ``LineStrips2D`` of
(X, Y) = box coordinates of (log10 x, log10 y) (log axes) or (x, y) (linear axes), mapped into a
16 x 10 box. The box normalisation is needed because a spatial view keeps a 1:1 aspect ratio (lags
of seconds against autocovariances of 1e-6 units^2 would be a line); Y is flipped because Rerun's 2D
views are y-down (image convention; ``image_view_coordinates`` is RDF, rerun-io/rerun#1387 open).
Axes are drawn too: a frame, grid lines at decades (log) or at 1-2-5 steps (linear), tick labels
and axis titles as ``Points2D`` labels, and a legend to the right of the box. Lines use radii in UI
points (negative radii) so they do not scale with zoom. Non-positive values on a log axis and
points outside the plotted range are cut out of the strip (the strip is split there). The mapping
(``x_log``, ``x_lo``, ``x_hi`` ... in log10 units for log axes) is logged on the view entity, so the
plotted coordinates can be inverted: positions are float32 (``Position2D``), the raw AnyValues
and the Scalars are float64.

Which axes are logarithmic follows the View's ``log_x``/``log_y`` (:mod:`service.diagnose.compare.views`
sets both for psd and allan). Not verified: how the viewer GUI finally lays the labels out (no display here); the
geometry and the blueprint are checked by reading the file back (tests/diagnose/test_viewers.py).

The blueprint: a Tabs container with one tab per revision (the last one active) holding, per
output, the time series with its band and the variance (time series views on ``t``, x axes linked)
over the PSD, ACF and Allan plots; to the right the error chart over the report.
"""

from __future__ import annotations

import contextlib
import math
import re
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.diagnose.results import VIEW_NAMES, VIEW_UNITS, Comparison, View

RERUN_VERSION_CHECKED = "0.41.0"

# -- shared conventions (also used by summary_png) ----------------------------------------------------
# RGB, chosen to read on Rerun's dark background and on a white PNG alike.
COLORS = {
    "measurement": (150, 150, 150),
    "truth": (44, 170, 44),
    "mean": (255, 127, 14),
    "band": (255, 187, 120),
    "empirical": (70, 150, 230),
    "predicted": (255, 127, 14),
    "previous": (170, 170, 170),
    "flagged": (235, 45, 45),
    "frame": (190, 190, 190),
    "grid": (95, 95, 95),
    "text": (210, 210, 210),
    "reference": (150, 150, 150),
    "overall": (235, 235, 235),
}
CONTRIB_COLORS = [(148, 103, 189), (23, 190, 207), (227, 119, 194), (188, 189, 34), (140, 86, 75),
                  (120, 200, 120), (200, 160, 90), (100, 120, 220)]
VIEW_COLORS = {"variance": (148, 103, 189), "acf": (200, 160, 90), "psd": (70, 150, 230),
               "allan": (44, 170, 44), "level": (214, 39, 40)}
VIEW_TITLES = {"variance": "variance", "acf": "autocovariance", "psd": "PSD", "allan": "Allan deviation",
               "level": "level (window mean of y - E[y])"}


class ViewerInputError(ValueError):
    """Comparisons that cannot be drawn; the message names the field at fault."""


def view_unit(view_name: str, x_label: str = "") -> str:
    """Unit of a view's x values: the ``[...]`` of its x label, else the known unit of the view."""
    m = re.search(r"\[([^\]]+)\]", x_label or "")
    return m.group(1) if m else VIEW_UNITS.get(view_name, "")


def effect_color(index: int) -> tuple:
    return CONTRIB_COLORS[index % len(CONTRIB_COLORS)]


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
UNNAMED_UNIT = "units"      # the placeholder the views' labels carry (service.diagnose.compare)


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


def _flag_mask(view: View) -> np.ndarray:
    n = np.asarray(view.x).size
    return np.zeros(n, bool) if view.flagged is None else np.asarray(view.flagged, bool)


def _fmt(v: float) -> str:
    return "n/a" if v is None or not np.isfinite(v) else f"{v:.3g}"


# -- the text report ------------------------------------------------------------------------------------
def report_markdown(comparisons: list) -> str:
    """The report as markdown: model error per revision (overall and per view), then for each
    revision (latest first) the regions where the data leave the model and the notes."""
    comps = validate_comparisons(comparisons)
    last = comps[-1]
    src = recording_of(last)
    lines = [f"# noiselab model check: {model_title(comps[0])}", ""]
    if src:
        lines += [f"recording: `{src}`", ""]
    lines += ["outputs: " + ", ".join(output_label(last, j) for j in range(np.asarray(last.y).shape[1])), ""]
    lines += ["**Model error**: mean over the views of mean(z^2); about 1 when the model explains the "
              "data within the estimators' sampling noise, larger with the mismatch.", "",
             "| revision | model | error | " + " | ".join(VIEW_NAMES) + " |",
             "|---:|---|---:|" + "---:|" * len(VIEW_NAMES)]
    for c in comps:
        per = [_fmt(c.error_per_view.get(n, float("nan"))) for n in VIEW_NAMES]
        lines.append(f"| {c.revision} | {c.model_name} | **{_fmt(c.error)}** | " + " | ".join(per) + " |")
    if len(comps) > 1:
        lines += ["", f"Error {_fmt(comps[0].error)} (revision {comps[0].revision}) -> {_fmt(last.error)} "
                      f"(revision {last.revision})."]
    for k in range(len(comps) - 1, -1, -1):
        c = comps[k]
        lines += ["", f"## Revision {c.revision}: {c.model_name}", ""]
        if c.model_source:
            lines += [f"model source: `{c.model_source}`", ""]
        if k:
            changes = model_changes(comps[k - 1], c)
            lines += [f"**Changed from revision {comps[k - 1].revision}**: "
                      + ("; ".join(f"`{ch}`" for ch in changes) if changes else "no effect changed"), ""]
        lines += ["**Where the data leave the model**", ""]
        if c.regions:
            for rg in c.regions:
                try:
                    xl = c.view(rg.view, rg.output).x_label
                except KeyError:
                    xl = ""
                lines.append(f"- {rg.describe(view_unit(rg.view, xl))}")
        else:
            lines.append("- nowhere: every point is within its band")
        notes = list(c.notes) + [f"{v.name} ({output_names(c)[v.output]}): {n}" for v in c.views for n in v.notes]
        if notes:
            lines += ["", "**Notes**", ""] + [f"- {n}" for n in notes]
    return "\n".join(lines) + "\n"


# -- 2D plots in a Spatial2DView ------------------------------------------------------------------------
BOX_W, BOX_H = 16.0, 10.0
LINE = 1.2          # line radius, UI points
LINE_THIN = 0.7


@dataclass
class _Axis:
    """One axis of a 2D plot: ``log`` axes work in log10 units; lo/hi bound the plotted range."""

    log: bool
    lo: float
    hi: float
    length: float

    def units(self, v) -> np.ndarray:
        v = np.asarray(v, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(v > 0, np.log10(np.where(v > 0, v, 1.0)), np.nan) if self.log else v.copy()
        u[~np.isfinite(u)] = np.nan
        return u

    def frac(self, v) -> np.ndarray:
        """0..1 across the plotted range, NaN where the value cannot be drawn or is out of range."""
        f = (self.units(v) - self.lo) / (self.hi - self.lo)
        f[(f < -1e-9) | (f > 1 + 1e-9)] = np.nan
        return f

    def ticks(self) -> list:
        """[(position in axis units, label)]: decades (1-2-5 within short spans) or 1-2-5 steps."""
        if self.log:
            k0, k1 = math.ceil(self.lo - 1e-9), math.floor(self.hi + 1e-9)
            step = max(1, math.ceil((k1 - k0 + 1) / 7))
            out = [(float(k), f"{10.0 ** k:g}") for k in range(k0, k1 + 1, step)]
            if len(out) < 2:
                out = []
                for k in range(math.floor(self.lo), math.ceil(self.hi) + 1):
                    for m in (1, 2, 5):
                        u = k + math.log10(m)
                        if self.lo - 1e-9 <= u <= self.hi + 1e-9:
                            out.append((u, f"{m * 10.0 ** k:g}"))
            return out
        span = self.hi - self.lo
        raw = span / 5
        mag = 10.0 ** math.floor(math.log10(raw))
        step = mag * next(s for s in (1, 2, 2.5, 5, 10) if s * mag >= raw * 0.999)
        first = math.ceil(self.lo / step - 1e-9) * step
        vals = np.arange(first, self.hi + step * 1e-6, step)
        return [(float(v), f"{(0.0 if abs(v) < step * 1e-9 else v):.3g}") for v in vals]


def _fit_axis(series: list, log: bool, length: float, extra: list = (), max_extra_decades: float = 2.0,
              pad: float = 0.04) -> _Axis:
    """Range covering ``series`` (in axis units), extended towards ``extra`` by at most
    ``max_extra_decades`` (log axes; linear axes take ``extra`` in full)."""
    probe = _Axis(log, 0.0, 1.0, length)
    core = np.concatenate([probe.units(s).ravel() for s in series]) if series else np.array([])
    core = core[np.isfinite(core)]
    if core.size == 0:
        lo, hi = (0.0, 1.0)
    else:
        lo, hi = float(core.min()), float(core.max())
    ext = np.concatenate([probe.units(s).ravel() for s in extra]) if len(extra) else np.array([])
    ext = ext[np.isfinite(ext)]
    if ext.size:
        if log:
            lo = min(lo, max(float(ext.min()), lo - max_extra_decades))
            hi = max(hi, min(float(ext.max()), hi + max_extra_decades))
        else:
            lo, hi = min(lo, float(ext.min())), max(hi, float(ext.max()))
    if hi - lo < 1e-12:
        d = 0.5 if log else (abs(lo) * 0.1 or 1.0)
        lo, hi = lo - d, hi + d
    p = (hi - lo) * pad
    return _Axis(log, lo - p, hi + p, length)


class _Plot2D:
    """Maps data to the box: X = frac_x * W, Y = (1 - frac_y) * H (Rerun 2D views are y-down)."""

    def __init__(self, xa: _Axis, ya: _Axis):
        self.xa, self.ya = xa, ya

    def xy(self, x, y) -> np.ndarray:
        fx, fy = self.xa.frac(x), self.ya.frac(y)
        return np.column_stack([fx * BOX_W, (1.0 - fy) * BOX_H]).astype(np.float32)

    def strips(self, x, y) -> list:
        """Runs of drawable consecutive points (>= 2 points each)."""
        pts = self.xy(x, y)
        ok = np.all(np.isfinite(pts), axis=1)
        out, i, n = [], 0, len(pts)
        while i < n:
            if not ok[i]:
                i += 1
                continue
            k = i
            while k + 1 < n and ok[k + 1]:
                k += 1
            if k > i:
                out.append(pts[i:k + 1])
            i = k + 1
        return out

    def points(self, x, y) -> np.ndarray:
        pts = self.xy(x, y)
        return pts[np.all(np.isfinite(pts), axis=1)]

    def mapping(self) -> dict:
        return {"x_log": self.xa.log, "x_lo": self.xa.lo, "x_hi": self.xa.hi, "y_log": self.ya.log,
                "y_lo": self.ya.lo, "y_hi": self.ya.hi, "box_w": BOX_W, "box_h": BOX_H,
                "mapping": "X = (u_x - x_lo)/(x_hi - x_lo) * box_w, Y = (1 - (u_y - y_lo)/(y_hi - y_lo)) * box_h, "
                           "u = log10(value) on log axes, value otherwise"}


def _ui(r: float) -> float:
    return -abs(r)          # negative radius = UI points (rerun.components.Radius, 0.41)


def _log_axes(rec, rr, base: str, plot: _Plot2D, x_title: str, y_title: str) -> None:
    W, H = BOX_W, BOX_H
    frame = np.array([[0, 0], [W, 0], [W, H], [0, H], [0, 0]], np.float32)
    rec.log(f"{base}/axes/frame", rr.LineStrips2D([frame], radii=_ui(0.8), colors=[COLORS["frame"]],
                                                  draw_order=5.0), static=True)
    xt, yt = plot.xa.ticks(), plot.ya.ticks()
    grid = []
    for u, _ in xt:
        X = (u - plot.xa.lo) / (plot.xa.hi - plot.xa.lo) * W
        grid.append(np.array([[X, 0], [X, H]], np.float32))
    for u, _ in yt:
        Y = (1 - (u - plot.ya.lo) / (plot.ya.hi - plot.ya.lo)) * H
        grid.append(np.array([[0, Y], [W, Y]], np.float32))
    if grid:
        rec.log(f"{base}/axes/grid", rr.LineStrips2D(grid, radii=_ui(0.4), colors=[COLORS["grid"]],
                                                     draw_order=1.0), static=True)
    pos, lab = [], []
    for u, s in xt:
        pos.append([(u - plot.xa.lo) / (plot.xa.hi - plot.xa.lo) * W, H + 0.1])
        lab.append(s)
    for u, s in yt:
        pos.append([-1.3, (1 - (u - plot.ya.lo) / (plot.ya.hi - plot.ya.lo)) * H - 0.55])
        lab.append(s)
    if pos:
        rec.log(f"{base}/axes/ticks", rr.Points2D(np.asarray(pos, np.float32), radii=_ui(0.01), labels=lab,
                                                  show_labels=True, colors=[COLORS["text"]]), static=True)
    rec.log(f"{base}/axes/titles",
            rr.Points2D(np.array([[W / 2, H + 1.3], [W * 0.2, -1.3]], np.float32), radii=_ui(0.01),
                        labels=[x_title + (" (log)" if plot.xa.log else ""),
                                y_title + (" (log)" if plot.ya.log else "")],
                        show_labels=True, colors=[COLORS["text"]]), static=True)


def _log_legend(rec, rr, base: str, entries: list) -> None:
    """entries: [(name, rgb, kind)] kind 'line' | 'point'. Right of the box, top down, a swatch with
    its name under it (Rerun draws a point's label centred just below the point); 11 per column."""
    for k, (name, rgb, kind) in enumerate(entries):
        x0 = BOX_W + 2.2 + 5.0 * (k // 11)
        y = 0.1 + (k % 11) * 1.2
        path = f"{base}/legend/{k:02d}"
        if kind == "point":
            rec.log(path, rr.Points2D(np.array([[x0, y]], np.float32), radii=_ui(3.5), colors=[rgb]), static=True)
        else:
            rec.log(path, rr.LineStrips2D([np.array([[x0 - 0.9, y], [x0 + 0.9, y]], np.float32)],
                                          radii=_ui(LINE + 0.3), colors=[rgb]), static=True)
        rec.log(f"{path}/label", rr.Points2D(np.array([[x0, y + 0.05]], np.float32), radii=_ui(0.01),
                                             labels=[name], show_labels=True, colors=[COLORS["text"]]),
                static=True)


def _curve(rec, rr, path: str, plot: _Plot2D, x, y, rgb, radius=LINE, draw_order=10.0, label=None) -> bool:
    strips = plot.strips(x, y)
    raw = rr.AnyValues(x=np.asarray(x, float), y=np.asarray(y, float))
    if strips:
        rec.log(path, rr.LineStrips2D(strips, radii=_ui(radius), colors=[rgb], draw_order=draw_order,
                                      labels=[label] * len(strips) if label else None), raw, static=True)
    else:
        rec.log(path, raw, static=True)
    return bool(strips)


def _log_view_2d(rec, rr, base: str, view: View, regions: list, effects: list,
                 previous: View | None, y_label: str) -> None:
    """One statistic as a 2D plot under ``base`` (the view entity) + ``base/plot``; ``y_label``
    is the view's with the output's unit (:func:`view_y_label`)."""
    log_x, log_y = bool(view.log_x), bool(view.log_y)
    core = [view.empirical, view.predicted, view.lo, view.hi]
    if previous is not None:
        core.append(previous.predicted)
    xa = _fit_axis([view.x], log_x, BOX_W, pad=0.02)
    ya = _fit_axis(core, log_y, BOX_H, extra=list(view.contributions.values()))
    plot = _Plot2D(xa, ya)
    flagged = _flag_mask(view)
    rec.log(base, rr.AnyValues(x_label=view.x_label, y_label=y_label, error=float(view.error),
                               conf=float(view.conf), output=int(view.output), n_flagged=int(flagged.sum()),
                               z=np.asarray(view.z if view.z is not None else np.full(flagged.size, np.nan), float),
                               flagged=flagged, **plot.mapping()), static=True)
    p = f"{base}/plot"
    _log_axes(rec, rr, f"{p}", plot, view.x_label, y_label)
    legend = [("data", COLORS["empirical"], "line"), ("model", COLORS["predicted"], "line"),
              (f"band ({view.conf:.3g})", COLORS["band"], "line")]
    band = plot.strips(view.x, view.lo) + plot.strips(view.x, view.hi)
    rec.log(f"{p}/band", rr.AnyValues(x=np.asarray(view.x, float), lo=np.asarray(view.lo, float),
                                       hi=np.asarray(view.hi, float)), static=True)
    if band:
        rec.log(f"{p}/band", rr.LineStrips2D(band, radii=_ui(LINE_THIN), colors=[COLORS["band"]], draw_order=8.0),
                static=True)
    for eid, arr in view.contributions.items():
        rgb = effect_color(effects.index(eid)) if eid in effects else CONTRIB_COLORS[0]
        if _curve(rec, rr, f"{p}/contrib/{rr.escape_entity_path_part(eid)}", plot, view.x, arr, rgb,
                  radius=LINE_THIN, draw_order=7.0, label=eid):
            legend.append((eid, rgb, "line"))
    if previous is not None and np.asarray(previous.x).shape == np.asarray(view.x).shape:
        if _curve(rec, rr, f"{p}/previous", plot, previous.x, previous.predicted, COLORS["previous"],
                  radius=LINE_THIN, draw_order=6.0):
            legend.append(("model, previous revision", COLORS["previous"], "line"))
    _curve(rec, rr, f"{p}/predicted", plot, view.x, view.predicted, COLORS["predicted"], draw_order=11.0)
    _curve(rec, rr, f"{p}/empirical", plot, view.x, view.empirical, COLORS["empirical"], draw_order=12.0)
    pts = plot.points(view.x, view.empirical)
    if len(pts):
        rec.log(f"{p}/empirical_points", rr.Points2D(pts, radii=_ui(2.0), colors=[COLORS["empirical"]],
                                                     draw_order=12.5), static=True)
    fx = np.asarray(view.x, float)[flagged]
    fy = np.asarray(view.empirical, float)[flagged]
    fpts = plot.xy(fx, fy)
    ok = np.all(np.isfinite(fpts), axis=1)
    rec.log(f"{p}/flagged", rr.AnyValues(x=fx, y=fy), static=True)
    if ok.any():
        z = np.asarray(view.z, float)[flagged] if view.z is not None else np.full(fx.size, np.nan)
        rec.log(f"{p}/flagged", rr.Points2D(fpts[ok], radii=_ui(4.5), colors=[COLORS["flagged"]], draw_order=20.0,
                                            labels=[f"z = {zz:.1f}" for zz in z[ok]], show_labels=False),
                static=True)
        legend.append(("outside the band", COLORS["flagged"], "point"))
    bars, texts = [], []
    for rg in regions:
        xs = plot.xa.frac([rg.x_lo, rg.x_hi]) * BOX_W
        if np.all(np.isfinite(xs)):
            a, b = float(xs[0]), float(xs[1])
            if b - a < 0.15:
                a, b = a - 0.075, b + 0.075
            bars.append(np.array([[a, BOX_H - 0.2], [b, BOX_H - 0.2]], np.float32))
            texts.append(rg.describe(view_unit(view.name, view.x_label)))
    if bars:
        rec.log(f"{p}/regions", rr.LineStrips2D(bars, radii=_ui(4.0), colors=[COLORS["flagged"]], labels=texts,
                                                show_labels=False, draw_order=19.0), static=True)
    _log_legend(rec, rr, p, legend)


def _log_error_chart(rec, rr, comps: list) -> None:
    base = "/error/chart"
    k = np.arange(len(comps), dtype=float)
    overall = np.array([c.error for c in comps], float)
    per = {n: np.array([c.error_per_view.get(n, np.nan) for c in comps], float) for n in VIEW_NAMES}
    xa = _fit_axis([k], False, BOX_W, pad=0.08) if len(comps) > 1 else _Axis(False, -0.5, 0.5, BOX_W)
    ya = _fit_axis([overall, np.ones(1)] + list(per.values()), True, BOX_H, pad=0.06)
    plot = _Plot2D(xa, ya)
    W, H = BOX_W, BOX_H
    rec.log(f"{base}/axes/frame", rr.LineStrips2D([np.array([[0, 0], [W, 0], [W, H], [0, H], [0, 0]], np.float32)],
                                                  radii=_ui(0.8), colors=[COLORS["frame"]]), static=True)
    yt = ya.ticks()
    grid = [np.array([[0, Y], [W, Y]], np.float32) for Y in ((1 - (u - ya.lo) / (ya.hi - ya.lo)) * H for u, _ in yt)]
    if grid:
        rec.log(f"{base}/axes/grid", rr.LineStrips2D(grid, radii=_ui(0.4), colors=[COLORS["grid"]], draw_order=1.0),
                static=True)
    pos = [[float(plot.xy([kk], [1.0])[0, 0]), H + 0.1] for kk in k]
    lab = [f"rev {c.revision}" for c in comps]
    pos += [[-1.3, (1 - (u - ya.lo) / (ya.hi - ya.lo)) * H - 0.55] for u, _ in yt]
    lab += [s for _, s in yt]
    pos += [[W / 2, H + 1.3], [W * 0.2, -1.3]]
    lab += ["model revision", "model error (log)"]
    rec.log(f"{base}/axes/ticks", rr.Points2D(np.asarray(pos, np.float32), radii=_ui(0.01), labels=lab,
                                              show_labels=True, colors=[COLORS["text"]]), static=True)
    ref_y = plot.xy([xa.lo], [1.0])[0, 1]
    if np.isfinite(ref_y):          # error = 1, dashed (LineStrips2D has no dash style: 0.4-unit dashes)
        dashes = [np.array([[a, ref_y], [min(a + 0.4, W), ref_y]], np.float32) for a in np.arange(0.0, W, 0.7)]
        rec.log(f"{base}/reference", rr.LineStrips2D(dashes, radii=_ui(LINE_THIN), colors=[COLORS["reference"]]),
                rr.AnyValues(meaning="model error 1: the model explains the data within the sampling noise"),
                static=True)
    legend = [("model error", COLORS["overall"], "line")]
    for n in VIEW_NAMES:
        rgb = VIEW_COLORS[n]
        _curve(rec, rr, f"{base}/{n}", plot, k, per[n], rgb, radius=LINE_THIN, draw_order=9.0)
        pts = plot.points(k, per[n])
        if len(pts):
            rec.log(f"{base}/{n}_points", rr.Points2D(pts, radii=_ui(2.5), colors=[rgb]), static=True)
        legend.append((n, rgb, "line"))
    _curve(rec, rr, f"{base}/overall", plot, k, overall, COLORS["overall"], radius=2.0, draw_order=10.0)
    pts = plot.points(k, overall)
    if len(pts):
        rec.log(f"{base}/overall_points", rr.Points2D(pts, radii=_ui(4.0), colors=[COLORS["overall"]],
                                                      labels=[_fmt(e) for e, ok in zip(overall, np.isfinite(
                                                          plot.xy(k, overall)).all(axis=1)) if ok],
                                                      show_labels=True, draw_order=11.0), static=True)
    legend.append(("1: within sampling noise", COLORS["reference"], "line"))
    _log_legend(rec, rr, base, legend)
    rec.log(base, rr.AnyValues(revision=np.array([c.revision for c in comps], np.int64), error=overall,
                               **{f"error_{n}": per[n] for n in VIEW_NAMES}, **plot.mapping()), static=True)


# -- time series (TimeSeriesView on the duration timeline "t") -------------------------------------------
def seconds_to_ns(t) -> np.ndarray:
    """Sample times in s -> integer ns, rounded. (``rr.TimeColumn(duration=float seconds)`` multiplies
    by 1e9 and truncates in 0.41, so 2.05 s would become 2049999999 ns; give it timedelta64[ns].)"""
    return np.rint(np.asarray(t, float) * 1e9).astype(np.int64).astype("timedelta64[ns]")


def _send_series(rec, rr, path: str, t: np.ndarray, values: np.ndarray) -> None:
    rec.send_columns(path, indexes=[rr.TimeColumn("t", duration=seconds_to_ns(t))],
                     columns=rr.Scalars.columns(scalars=np.asarray(values, float)))


def _style(rec, rr, path: str, names: list, rgb: tuple, width: float = 1.5) -> None:
    rec.log(path, rr.SeriesLines(names=names, colors=[rgb] * len(names), widths=[width] * len(names)), static=True)


def _same_data(a: Comparison, b: Comparison) -> bool:
    if not (np.array_equal(a.t, b.t) and np.array_equal(a.y, b.y)):
        return False
    if a.truth is None or b.truth is None:
        return a.truth is None and b.truth is None
    return np.array_equal(a.truth, b.truth)


def output_path(c: Comparison, i: int) -> str:
    """``/rev<r>/<output name>``: the entities of output ``i`` for ``c``'s revision. (Names are
    identifiers, valid path parts as they stand; the escape is for a caller's stray name.)"""
    from rerun import escape_entity_path_part

    return f"{_rev_path(c)}/{escape_entity_path_part(output_names(c)[i])}"


def data_paths(comps: list) -> dict:
    """{(revision, output index): entity path of the data}: ``/data/<output name>`` when t, y and
    truth equal the first comparison's, else ``/rev<r>/<output name>/data``."""
    from rerun import escape_entity_path_part

    return {(c.revision, i): f"/data/{escape_entity_path_part(output_names(c)[i])}" if _same_data(c, comps[0])
            else f"{output_path(c, i)}/data" for c in comps for i in range(np.asarray(c.y).shape[1])}


def has_truth(c: Comparison, i: int) -> bool:
    """Truth to draw beside output ``i``: the recording has truth and a state ``x[i]``."""
    return c.truth is not None and i < np.asarray(c.truth).shape[1]


def truth_label(i: int) -> str:
    """The truth drawn beside output ``i`` is the plant's state ``x[i]`` (the shorthand plant
    measures y = x[0]); the recording holds states, not noise-free outputs."""
    return f"truth: state x[{i}]"


def _log_data(rec, rr, p: str, c: Comparison, i: int) -> None:
    t = np.asarray(c.t, float)
    _send_series(rec, rr, f"{p}/measurement", t, np.asarray(c.y, float)[:, i])
    _style(rec, rr, f"{p}/measurement", [f"{output_label(c, i)} measured"], COLORS["measurement"], 1.0)
    if has_truth(c, i):
        _send_series(rec, rr, f"{p}/truth", t, np.asarray(c.truth, float)[:, i])
        _style(rec, rr, f"{p}/truth", [truth_label(i)], COLORS["truth"], 1.5)


def _log_time_series(rec, rr, base: str, c: Comparison, i: int) -> None:
    t = np.asarray(c.t, float)
    mean = np.asarray(c.y_mean, float)[:, i]
    sd = np.asarray(c.y_sd, float)[:, i]
    p = f"{base}/series"
    _send_series(rec, rr, f"{p}/mean", t, mean)
    _style(rec, rr, f"{p}/mean", ["predicted mean"], COLORS["mean"], 2.0)
    _send_series(rec, rr, f"{p}/band", t, np.column_stack([mean - 2 * sd, mean + 2 * sd]))
    _style(rec, rr, f"{p}/band", ["mean - 2 sd", "mean + 2 sd"], COLORS["band"], 1.0)


def _log_variance(rec, rr, base: str, v: View, effects: list, y_label: str) -> None:
    p = f"{base}/variance"
    x = np.asarray(v.x, float)
    flagged = _flag_mask(v)
    rec.log(p, rr.AnyValues(x_label=v.x_label, y_label=y_label, error=float(v.error), conf=float(v.conf),
                            x=x, z=np.asarray(v.z if v.z is not None else np.full(x.size, np.nan), float),
                            flagged=flagged), static=True)
    _send_series(rec, rr, f"{p}/empirical", x, v.empirical)
    _style(rec, rr, f"{p}/empirical", ["data (window variance)"], COLORS["empirical"], 1.5)
    _send_series(rec, rr, f"{p}/predicted", x, v.predicted)
    _style(rec, rr, f"{p}/predicted", ["model"], COLORS["predicted"], 2.0)
    _send_series(rec, rr, f"{p}/band", x, np.column_stack([np.asarray(v.lo, float), np.asarray(v.hi, float)]))
    _style(rec, rr, f"{p}/band", ["band low", "band high"], COLORS["band"], 1.0)
    for eid, arr in v.contributions.items():
        q = f"{p}/contrib/{rr.escape_entity_path_part(eid)}"
        _send_series(rec, rr, q, x, arr)
        _style(rec, rr, q, [eid], effect_color(effects.index(eid)) if eid in effects else CONTRIB_COLORS[0], 1.0)
    if flagged.any():
        _send_series(rec, rr, f"{p}/flagged", x[flagged], np.asarray(v.empirical, float)[flagged])
        rec.log(f"{p}/flagged", rr.SeriesPoints(names=["outside the band"], colors=[COLORS["flagged"]],
                                                markers=["cross"], marker_sizes=[5.0]), static=True)


# -- blueprint --------------------------------------------------------------------------------------------
def _rev_path(c: Comparison) -> str:
    return f"/rev{c.revision}"


def build_blueprint(comparisons: list, history: bool = False):
    """The one-screen blueprint for :func:`log_comparisons`'s entity layout."""
    import rerun.blueprint as rrb

    comps = validate_comparisons(comparisons)
    dpaths = data_paths(comps)
    link = rrb.TimeAxis(link=rrb.components.LinkAxis.LinkToGlobal)
    bounds = rrb.VisualBounds2D(x_range=[-3.0, BOX_W + 5.5], y_range=[-2.2, BOX_H + 2.6])
    tabs = []
    for c in comps:
        p = np.asarray(c.y).shape[1]
        blocks = []
        for i in range(p):
            base = output_path(c, i)
            lab = output_label(c, i)
            names = {v.name for v in c.views if v.output == i}

            def err(name, i=i):
                try:
                    return _fmt(c.view(name, i).error)
                except KeyError:
                    return "n/a"

            shown = "measured, truth, predicted mean" if has_truth(c, i) else "measured, predicted mean"
            top = [rrb.TimeSeriesView(origin=f"{base}/series",
                                      contents=["+ $origin/**", f"+ {dpaths[c.revision, i]}/**"],
                                      name=f"{lab}: {shown} +- 2 sd", axis_x=link)]
            if "variance" in names:
                top.append(rrb.TimeSeriesView(origin=f"{base}/variance",
                                              contents=["+ $origin/**", "- $origin/contrib/**"],
                                              name=f"variance of {lab}, data vs model (error {err('variance')})",
                                              axis_x=link))
            bottom = []
            for n in ("psd", "acf", "allan", "level"):
                if n in names:
                    v = c.view(n, i)
                    scale = {(True, True): " log-log", (True, False): " log x", (False, True): " log y"}.get(
                        (bool(v.log_x), bool(v.log_y)), "")
                    bottom.append(rrb.Spatial2DView(origin=f"{base}/{n}", visual_bounds=bounds,
                                                    name=f"{VIEW_TITLES[n]} {lab}{scale} (error {err(n)})"))
            rows = [rrb.Horizontal(*top, column_shares=[2, 1][:len(top)])]
            if bottom:
                rows.append(rrb.Horizontal(*bottom))
            blocks.append(rrb.Vertical(*rows, name=lab))
        content = blocks[0] if p == 1 else (rrb.Vertical(*blocks) if p == 2 else rrb.Tabs(*blocks))
        tabs.append(rrb.Vertical(content, name=f"rev {c.revision}: {c.model_name} (error {_fmt(c.error)})"))
    extra = [rrb.TimeSeriesView(origin="/error/history", name="model error over time (live analysis)")] \
        if history else []
    side = rrb.Vertical(
        *extra,
        rrb.Spatial2DView(origin="/error/chart", name="model error per revision (overall and per view)",
                          visual_bounds=bounds),
        rrb.TextDocumentView(origin="/report", name="report"),
        row_shares=[2, 3])
    root = rrb.Horizontal(rrb.Tabs(*tabs, active_tab=len(tabs) - 1), side, column_shares=[3, 1])
    return rrb.Blueprint(root, rrb.TimePanel(timeline="t", state="collapsed"),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))


# -- entry point ------------------------------------------------------------------------------------------
def log_comparisons(comparisons: list, path: str, *, app_id: str = "noiselab", history: list | None = None) -> None:
    """Write ``comparisons`` (one per model revision) to the Rerun file ``path`` with the blueprint.

    ``history`` (live analysis): [{"t": s, "revision": int, "error": float, "error_per_view": {...}}]
    is logged as the model error over time on the ``t`` timeline under ``/error/history``.

    The file is complete (footer included) when this returns. Parent directories are created.
    Rerun is put in strict mode for these calls (thread-local), so a bad argument raises instead
    of becoming a warning and a silently empty entity. A file that cannot be written (disk full,
    ...) raises the OSError, and a regular file cut short by it is removed.
    """
    import rerun as rr
    from rerun.error_utils import catch_and_log_exceptions   # thread-local strict mode (0.41 source)

    comps = validate_comparisons(comparisons)
    effects = effect_ids(comps)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(app_id, recording_id=uuid.uuid4())
    stream = rec.binary_stream()        # in memory; written to the file below (module docstring)
    try:
        with catch_and_log_exceptions("noiselab.viewers.log_comparisons", strict=True):
            rec.send_blueprint(build_blueprint(comps, history=bool(history)), make_active=False, make_default=True)
            if history:
                th = seconds_to_ns(np.array([h["t"] for h in history], float))
                rec.send_columns("/error/history/overall", indexes=[rr.TimeColumn("t", duration=th)],
                                 columns=rr.Scalars.columns(scalars=np.array([h["error"] for h in history], float)))
                rec.send_columns("/error/history/revision", indexes=[rr.TimeColumn("t", duration=th)],
                                 columns=rr.Scalars.columns(scalars=np.array([h["revision"] for h in history], float)))
                for n in VIEW_NAMES:
                    vals = np.array([h["error_per_view"].get(n, np.nan) for h in history], float)
                    rec.send_columns(f"/error/history/{n}", indexes=[rr.TimeColumn("t", duration=th)],
                                     columns=rr.Scalars.columns(scalars=vals))
            src = recording_of(comps[-1])
            rec.send_recording_name((f"{src} against " if src else "") + f"{model_title(comps[0])}: "
                                    f"{len(comps)} revision(s)")
            # where the data came from and what they are, for scripts and the viewer's recording panel
            rec.send_property("source", rr.AnyValues(
                recording=src or "", model=model_title(comps[0]), output_names=list(output_names(comps[-1])),
                output_units=list(output_units(comps[-1]))))
            rec.log("/report", rr.TextDocument(report_markdown(comps), media_type=rr.MediaType.MARKDOWN),
                    static=True)
            revs = np.array([c.revision for c in comps], np.int64)
            rec.send_columns("/error/overall", indexes=[rr.TimeColumn("revision", sequence=revs)],
                             columns=rr.Scalars.columns(scalars=np.array([c.error for c in comps], float)))
            _style(rec, rr, "/error/overall", ["model error"], COLORS["overall"], 2.5)
            for n in VIEW_NAMES:
                vals = np.array([c.error_per_view.get(n, np.nan) for c in comps], float)
                rec.send_columns(f"/error/{n}", indexes=[rr.TimeColumn("revision", sequence=revs)],
                                 columns=rr.Scalars.columns(scalars=vals))
                _style(rec, rr, f"/error/{n}", [f"{n} error"], VIEW_COLORS[n], 1.5)
            _log_error_chart(rec, rr, comps)
            prev = None
            dpaths = data_paths(comps)
            logged_data = set()
            for c in comps:
                rp = _rev_path(c)
                rec.log(rp, rr.AnyValues(revision=int(c.revision), model_name=c.model_name,
                                         model_source=str(c.model_source), Ts=float(c.Ts), error=float(c.error),
                                         n_regions=len(c.regions), recording=recording_of(c) or "",
                                         output_names=list(output_names(c)), output_units=list(output_units(c)),
                                         changes=model_changes(prev, c) if prev is not None else []),
                        static=True)
                for i in range(np.asarray(c.y).shape[1]):
                    if dpaths[c.revision, i] not in logged_data:
                        _log_data(rec, rr, dpaths[c.revision, i], c, i)
                        logged_data.add(dpaths[c.revision, i])
                    base = output_path(c, i)
                    _log_time_series(rec, rr, base, c, i)
                    for v in (v for v in c.views if v.output == i):
                        if v.name == "variance":
                            _log_variance(rec, rr, base, v, effects, view_y_label(c, v))
                            continue
                        pv = None
                        if prev is not None:
                            try:
                                pv = prev.view(v.name, i)
                            except KeyError:
                                pv = None
                        regs = [rg for rg in c.regions if rg.view == v.name and rg.output == i]
                        _log_view_2d(rec, rr, f"{base}/{v.name}", v, regs, effects, pv, view_y_label(c, v))
                prev = c
            rec.flush()
        data = stream.read(flush=True)
    finally:
        rec.disconnect()
        stream.read(flush=True)          # whatever an error left in the stream: nothing is dropped with a warning
    _write_file(out, data)


def _write_file(out: Path, data: bytes) -> None:
    """``data`` to ``out``; on an OSError after the file was opened (disk full), a regular file cut
    short is removed (a device such as /dev/full is left alone) and the error raised."""
    f = open(out, "wb")
    try:
        f.write(data)
        f.close()
    except OSError:
        with contextlib.suppress(OSError):
            f.close()                    # closed even when its last flush fails
        if out.is_file():
            out.unlink()
        raise
