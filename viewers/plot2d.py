"""Statistics drawn as 2D plots in a Rerun ``Spatial2DView``: curves, band, flagged points, regions,
axes with ticks and a legend, and the model error per revision.

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

Which axes are logarithmic follows the View's ``log_x``/``log_y`` (compare.py sets both for psd
and allan). Not verified: how the viewer GUI finally lays the labels out (no display here); the
geometry and the blueprint are checked by reading the file back (tests/diagnose/test_viewers.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from noiselab.diagnose.results import VIEW_NAMES, View

from .comparisons import flag_mask, fmt_error, view_unit
from .style import COLORS, CONTRIB_COLORS, VIEW_COLORS, effect_color

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


def log_view_2d(rec, rr, base: str, view: View, regions: list, effects: list,
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
    flagged = flag_mask(view)
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


def log_error_chart(rec, rr, comps: list) -> None:
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
                                                      labels=[fmt_error(e) for e, ok in zip(overall, np.isfinite(
                                                          plot.xy(k, overall)).all(axis=1)) if ok],
                                                      show_labels=True, draw_order=11.0), static=True)
    legend.append(("1: within sampling noise", COLORS["reference"], "line"))
    _log_legend(rec, rr, base, legend)
    rec.log(base, rr.AnyValues(revision=np.array([c.revision for c in comps], np.int64), error=overall,
                               **{f"error_{n}": per[n] for n in VIEW_NAMES}, **plot.mapping()), static=True)
