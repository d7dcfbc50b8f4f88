"""Where a comparison's entities live in the Rerun recording (:mod:`noiselab.viewers.rerun_log` documents
the whole layout) and the blueprint that shows them on one screen.

The blueprint: a Tabs container with one tab per revision (the last one active) holding, per
output, the time series with its band and the variance (time series views on ``t``, x axes linked)
over the PSD, ACF and Allan plots; to the right the error chart over the report.
"""

from __future__ import annotations

import numpy as np

from noiselab.diagnose.results import Comparison

from .comparisons import (
    fmt_error,
    has_truth,
    output_label,
    output_names,
    validate_comparisons,
)
from .plot2d import BOX_H, BOX_W
from .style import VIEW_TITLES


def rev_path(c: Comparison) -> str:
    return f"/rev{c.revision}"


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

    return f"{rev_path(c)}/{escape_entity_path_part(output_names(c)[i])}"


def data_paths(comps: list) -> dict:
    """{(revision, output index): entity path of the data}: ``/data/<output name>`` when t, y and
    truth equal the first comparison's, else ``/rev<r>/<output name>/data``."""
    from rerun import escape_entity_path_part

    return {(c.revision, i): f"/data/{escape_entity_path_part(output_names(c)[i])}" if _same_data(c, comps[0])
            else f"{output_path(c, i)}/data" for c in comps for i in range(np.asarray(c.y).shape[1])}


def build_blueprint(comparisons: list, history: bool = False):
    """The one-screen blueprint for :func:`noiselab.viewers.rerun_log.log_comparisons`'s entity layout."""
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
                    return fmt_error(c.view(name, i).error)
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
        tabs.append(rrb.Vertical(content, name=f"rev {c.revision}: {c.model_name} (error {fmt_error(c.error)})"))
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
