"""The summary PNG: the same story as the ``.rrd`` blueprint, for people without the Rerun viewer.

One figure (matplotlib, Agg backend, no display needed), ``16 x (7.4 p + 4.2)`` inches at 100 dpi
(:func:`figure_size_px`), for the **last** comparison (the latest model revision); earlier
revisions appear as the grey dashed "model, previous revision" line and in the error panel.
The title says what was compared with what (the recording with its topic and field, the model as
the user named it, file or scenario), the model error per revision and every effect the last
revision added, removed or refitted with its values. Outputs are named by the model's
``[outputs]`` names and units (``name [unit]``). Per output:

* row 1: the measurement, the truth (only when the recording has it), the predicted mean with the
  +-2 sd band | (records from rest: the level view |) window variance, data vs model with its band;
* row 2: PSD log-log | autocovariance | Allan deviation log-log, each with the model, its band,
  the per-effect contributions (thin dashed), flagged points (red crosses) and the Regions (red
  spans).

Last row: the model error per revision (overall, and per view, log scale, the line at 1 is
"explained within sampling noise"), the report text (errors, what each revision changed, regions,
notes; long lines wrapped, not cut) and the legend of the statistic panels.
"""

from __future__ import annotations

import itertools
import textwrap
from pathlib import Path

import numpy as np

from noiselab.diagnose.results import VIEW_NAMES, View

from .comparisons import (
    effect_ids,
    has_truth,
    model_changes,
    model_title,
    output_label,
    output_names,
    recording_of,
    truth_label,
    validate_comparisons,
    view_unit,
    view_y_label,
)
from .style import COLORS, VIEW_COLORS, VIEW_TITLES, effect_color

DPI = 100
WIDTH_PX = 1600
ROW_PX = 370            # one row of panels
LAST_ROW_PX = 420       # error per revision + report
YLABEL_CHARS = 30       # an axis label is wrapped past so many characters (a panel is ~250 px high)
TITLE_CHARS = 150       # the title's detail line, wrapped (12 pt bold over 1600 px)
REPORT_CHARS = 96       # the report panel's width in characters (8 pt monospace over ~700 px)
REPORT_LINES = 24       # lines that fit the report panel


def figure_size_px(p: int) -> tuple:
    """(width, height) in pixels of the summary PNG for p outputs."""
    return WIDTH_PX, 2 * ROW_PX * p + LAST_ROW_PX


def png_path_for(rrd_path: str) -> str:
    """The PNG written next to an .rrd: same name, ``.png`` suffix."""
    return str(Path(rrd_path).with_suffix(".png"))


def _c(name_or_rgb, alpha=None):
    rgb = COLORS[name_or_rgb] if isinstance(name_or_rgb, str) else name_or_rgb
    c = tuple(v / 255.0 for v in rgb)
    return c + (alpha,) if alpha is not None else c


def _fmt(v) -> str:
    return "n/a" if v is None or not np.isfinite(v) else f"{v:.3g}"


def _limits(series: list, log: bool, extra: list = (), max_extra_decades: float = 2.0):
    """y limits covering ``series``, extended towards ``extra`` (contributions) by at most
    ``max_extra_decades`` on a log axis, so a tiny effect does not squash the plot."""
    def vals(lst):
        a = np.concatenate([np.asarray(s, float).ravel() for s in lst]) if len(lst) else np.array([])
        a = a[np.isfinite(a)]
        return a[a > 0] if log else a

    core, ext = vals(series), vals(extra)
    if core.size == 0:
        return None
    lo, hi = core.min(), core.max()
    if ext.size:
        if log:
            lo = min(lo, max(ext.min(), lo / 10 ** max_extra_decades))
            hi = max(hi, min(ext.max(), hi * 10 ** max_extra_decades))
        else:
            lo, hi = min(lo, ext.min()), max(hi, ext.max())
    if log:
        return lo / 1.3, hi * 1.3
    pad = (hi - lo) * 0.05 or abs(hi) * 0.1 or 1.0
    return lo - pad, hi + pad


def _plot_view(ax, view: View, previous: View | None, effects: list, regions: list, title: str, y_label: str,
               contributions: bool = True) -> None:
    x = np.asarray(view.x, float)
    log_x, log_y = bool(view.log_x), bool(view.log_y)
    ax.fill_between(x, view.lo, view.hi, color=_c("band", 0.35), lw=0, label=f"band ({view.conf:.3g})")
    for eid, arr in (view.contributions.items() if contributions else ()):
        k = effects.index(eid) if eid in effects else 0
        ax.plot(x, arr, "--", lw=1.0, color=_c(effect_color(k)), label=eid)
    if previous is not None and np.asarray(previous.x).shape == x.shape:
        ax.plot(previous.x, previous.predicted, ":", lw=1.6, color=_c((120, 120, 120)),
                label="model, previous revision")
    ax.plot(x, view.predicted, lw=2.0, color=_c("predicted"), label="model")
    ax.plot(x, view.empirical, ".-", lw=1.2, ms=4, color=_c("empirical"), label="data")
    fl = np.zeros(x.size, bool) if view.flagged is None else np.asarray(view.flagged, bool)
    if fl.any():
        ax.plot(x[fl], np.asarray(view.empirical)[fl], "x", ms=8, mew=2, color=_c("flagged"),
                label="outside the band", zorder=5)
    for rg in regions:
        a, b = rg.x_lo, rg.x_hi
        if a == b:      # one point: a visible sliver around it
            a, b = (a / 1.06, b * 1.06) if log_x else (a - 0.01 * np.ptp(x), b + 0.01 * np.ptp(x))
        ax.axvspan(a, b, color=_c("flagged", 0.12), lw=0)
    if log_x:
        ax.set_xscale("log")
    if log_y:
        ax.set_yscale("log")
    core = [view.empirical, view.predicted, view.lo, view.hi] + ([previous.predicted] if previous is not None else [])
    lim = _limits(core, log_y, extra=list(view.contributions.values()) if contributions else [])
    if lim is not None:
        ax.set_ylim(*lim)
    ax.set_xlabel(view.x_label)
    ax.set_ylabel(_wrap(y_label, YLABEL_CHARS))
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="major", alpha=0.35)
    if log_x or log_y:
        ax.grid(True, which="minor", alpha=0.12)


def _wrap(text: str, width: int, indent: str = "") -> str:
    return "\n".join(textwrap.wrap(text, width, subsequent_indent=indent, break_on_hyphens=False)) or text


def _report_text(comps: list, width: int = REPORT_CHARS, max_lines: int = REPORT_LINES,
                 max_regions: int = 8) -> str:
    """The report panel: the model error per revision, what each revision changed, where the data
    leave the model (at most ``max_regions`` lines) and the notes; long lines are wrapped, and past
    ``max_lines`` the rest is left to the .rrd's report, saying so."""
    last = comps[-1]
    lines = [f"{'revision':>8}  {'model':<18} {'error':>9}  " + "  ".join(f"{n:>9}" for n in VIEW_NAMES)]
    for c in comps:
        lines.append(f"{c.revision:>8}  {c.model_name[:18]:<18} {_fmt(c.error):>9}  "
                     + "  ".join(f"{_fmt(c.error_per_view.get(n, np.nan)):>9}" for n in VIEW_NAMES))
    changed = [(b, model_changes(a, b)) for a, b in itertools.pairwise(comps)]
    if changed:
        lines += ["", "what each revision changed:"]
        lines += [f"  {b.revision}: " + ("; ".join(ch) if ch else "no effect changed") for b, ch in changed]
    lines += ["", f"where the data leave the model (revision {last.revision}):"]
    names = output_names(last)
    regs = []
    for rg in last.regions:
        try:
            xl = last.view(rg.view, rg.output).x_label
        except KeyError:
            xl = ""
        who = "" if getattr(rg, "output_name", None) else f"{names[rg.output]}: "   # describe() names it
        regs.append(f"  {who}{rg.describe(view_unit(rg.view, xl))}")
    if len(regs) > max_regions:
        regs = regs[:max_regions - 1] + [f"  (+{len(regs) - max_regions + 1} more regions in the .rrd report)"]
    lines += regs or ["  nowhere: every point is within its band"]
    if last.notes:
        lines += ["", "notes:"] + [f"  {n}" for n in last.notes]
    out = [w for ln in lines for w in (_wrap(ln, width, "      ").split("\n") if len(ln) > width else [ln])]
    if len(out) > max_lines:
        out = out[: max_lines - 1] + [f"  ... ({len(out) - max_lines + 1} more lines in the .rrd report)"]
    return "\n".join(out)


def _title(comps: list) -> tuple:
    """(headline, detail): what was compared with what, and the model error with what changed."""
    first, last = comps[0], comps[-1]
    src = recording_of(last)
    head = "noiselab: " + (f"{src} against {model_title(first)}" if src else model_title(first))
    if len(comps) == 1:
        return head, f"model error {_fmt(last.error)}"
    detail = f"model error {' -> '.join(_fmt(c.error) for c in comps)} (revisions {first.revision} to {last.revision})"
    changes = model_changes(first, last)
    if changes:
        # one change is not split across lines (no-break spaces inside it)
        detail += (f"\nrevision {last.revision} against revision {first.revision}: "
                   + _wrap("; ".join(ch.replace(" ", "\u00a0") for ch in changes), TITLE_CHARS))
    return head, detail


def _shared_legend(ax, effects: list, previous: bool) -> None:
    """One legend for the statistic panels (they share styles), drawn in its own empty axes."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    h = [Line2D([], [], marker=".", ms=6, lw=1.2, color=_c("empirical"), label="data (estimate)"),
         Line2D([], [], lw=2.0, color=_c("predicted"), label="model (expected estimate)"),
         Patch(color=_c("band", 0.35), label="band the data should fall in"),
         Line2D([], [], ls="", marker="x", ms=8, mew=2, color=_c("flagged"), label="outside the band"),
         Patch(color=_c("flagged", 0.12), label="region: data leave the model")]
    if previous:
        h.insert(3, Line2D([], [], ls=":", lw=1.6, color=_c((120, 120, 120)), label="model, previous revision"))
    h += [Line2D([], [], ls="--", lw=1.0, color=_c(effect_color(k)), label=f"effect {eid}")
          for k, eid in enumerate(effects)]
    ax.axis("off")
    ax.legend(handles=h, loc="upper left", fontsize=8, frameon=False, title="statistic panels",
              title_fontsize=9, alignment="left")


def write_summary_png(comparisons: list, path: str) -> None:
    """Write the one-figure summary of ``comparisons`` (one per model revision) to ``path``
    (PNG, :func:`figure_size_px` pixels). Parent directories are created."""
    comps = validate_comparisons(comparisons)
    fig = summary_figure(comps)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(str(out), dpi=DPI, format="png")


def summary_figure(comparisons: list):
    """The summary as a matplotlib Figure (on its own Agg canvas). Laid out by matplotlib's
    constrained layout, which sizes the gaps between panels to their axis labels and titles, so a
    long label does not run into the next panel."""
    # Figure + the Agg canvas directly: no pyplot, so no global figure state and no display
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    comps = validate_comparisons(comparisons)
    c = comps[-1]
    prev = comps[-2] if len(comps) > 1 else None
    effects = effect_ids(comps)
    p = np.asarray(c.y).shape[1]
    w_px, h_px = figure_size_px(p)
    fig = Figure(figsize=(w_px / DPI, h_px / DPI), dpi=DPI, layout="constrained")
    fig.get_layout_engine().set(w_pad=4 / DPI, h_pad=6 / DPI, wspace=0.03, hspace=0.04)
    FigureCanvasAgg(fig)
    ratios = [ROW_PX] * (2 * p) + [LAST_ROW_PX]
    # 12 columns: the measurement over 2/3 of a row beside the variance, or over 1/2 beside the
    # level view (records from rest) and the variance; psd, acf and allan a third each below
    has_level = any(v.name == "level" for v in c.views)
    gs = fig.add_gridspec(2 * p + 1, 12, height_ratios=ratios)
    head, detail = _title(comps)
    fig.suptitle(head + "\n" + detail, fontsize=12, fontweight="bold")
    for i in range(p):
        _plot_series(fig.add_subplot(gs[2 * i, 0:6] if has_level else gs[2 * i, 0:8]), c, i, has_level)
        slots = {"variance": gs[2 * i, 8:12], "psd": gs[2 * i + 1, 0:4], "acf": gs[2 * i + 1, 4:8],
                 "allan": gs[2 * i + 1, 8:12]}
        if has_level:
            slots["level"] = gs[2 * i, 6:9]
            slots["variance"] = gs[2 * i, 9:12]
        _plot_views(fig, slots, c, prev, i, effects)
    last = gs[2 * p, :].subgridspec(1, 3, width_ratios=[1.0, 1.4, 0.6])
    _plot_errors(fig.add_subplot(last[0, 0]), comps)
    ax = fig.add_subplot(last[0, 1])
    ax.axis("off")
    ax.text(0.0, 1.0, _report_text(comps), va="top", ha="left", family="monospace", fontsize=8,
            transform=ax.transAxes)
    _shared_legend(fig.add_subplot(last[0, 2]), effects, prev is not None)
    return fig


def _plot_series(ax, c, i: int, has_level: bool) -> None:
    """Output ``i``'s measurement (and truth) over time with the predicted mean and its 2-sigma band."""
    t = np.asarray(c.t, float)
    lab = output_label(c, i)
    names = output_names(c)
    mean, sd = np.asarray(c.y_mean, float)[:, i], np.asarray(c.y_sd, float)[:, i]
    ax.fill_between(t, mean - 2 * sd, mean + 2 * sd, color=_c("band", 0.45), lw=0, label="mean +- 2 sd")
    ax.plot(t, np.asarray(c.y, float)[:, i], lw=0.6, color=_c((110, 110, 110)), label=f"{names[i]} measured")
    if has_truth(c, i):
        ax.plot(t, np.asarray(c.truth, float)[:, i], lw=1.2, color=_c("truth"), label=truth_label(i))
    ax.plot(t, mean, lw=1.4, color=_c("mean"), label="predicted mean")
    ax.set_xlim(t[0], t[-1])
    ax.set_xlabel("time [s]")
    ax.set_ylabel(_wrap(lab, YLABEL_CHARS))
    shown = "measurement, truth, predicted mean" if has_truth(c, i) else "measurement, predicted mean"
    ax.set_title(lab if has_level else f"{lab}: {shown} with the 2-sigma band", fontsize=10, loc="left")
    ax.grid(True, alpha=0.35)
    ax.legend(fontsize=8, loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=4, frameon=False,
              borderaxespad=0.2)


def _plot_views(fig, slots: dict, c, prev, i: int, effects: list) -> None:
    """Output ``i``'s statistic panels, each in its grid slot (``slots``: view name -> slot), beside
    the previous revision's prediction (``prev``) where there is one."""
    names = output_names(c)
    for name, slot in slots.items():
        try:
            v = c.view(name, i)
        except KeyError:
            continue
        pv = None
        if prev is not None:
            try:
                pv = prev.view(name, i)
            except KeyError:
                pv = None
        regs = [rg for rg in c.regions if rg.view == name and rg.output == i]
        n_fl = int(np.sum(v.flagged)) if v.flagged is not None else 0
        _plot_view(fig.add_subplot(slot), v, pv, effects, regs,
                   f"{VIEW_TITLES[name]} {names[i]}{' (log-log)' if v.log_x and v.log_y else ''}: "
                   f"error {_fmt(v.error)}" + (f", {n_fl} flagged" if n_fl else ""), view_y_label(c, v),
                   contributions=name not in ("variance", "level"))


def _plot_errors(ax, comps: list) -> None:
    """The model error per revision, overall (labelled) and per view, on a log axis with the line 1."""
    k = np.arange(len(comps))
    for n in VIEW_NAMES:
        ax.plot(k, [cc.error_per_view.get(n, np.nan) for cc in comps], "o-", lw=1.2, ms=4,
                color=_c(VIEW_COLORS[n]), label=n)
    errs = [cc.error for cc in comps]
    ax.plot(k, errs, "o-", lw=2.8, ms=7, color="black", label="model error")
    for kk, e in zip(k, errs):
        if np.isfinite(e) and e > 0:
            ax.annotate(_fmt(e), (kk, e), textcoords="offset points", xytext=(8, -3), fontsize=9,
                        fontweight="bold")
    ax.axhline(1.0, ls="--", lw=1.0, color="0.4", label="1: within sampling noise")
    ax.set_yscale("log")
    ax.set_xticks(k, [f"rev {cc.revision}\n{cc.model_name[:16]}" for cc in comps], fontsize=8)
    ax.set_xlim(-0.4, len(comps) - 0.4)
    ax.set_ylabel("model error (mean z^2)")
    ax.set_title("model error per revision (overall and per view)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper right", framealpha=0.85)
