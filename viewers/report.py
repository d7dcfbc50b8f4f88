"""The text report of a set of comparisons, as markdown: the model error per revision, what each
revision changed, where the data leave the model, the notes."""

from __future__ import annotations

import numpy as np

from noiselab.diagnose.results import VIEW_NAMES

from .comparisons import (
    fmt_error,
    model_changes,
    model_title,
    output_label,
    output_names,
    recording_of,
    validate_comparisons,
    view_unit,
)


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
        per = [fmt_error(c.error_per_view.get(n, float("nan"))) for n in VIEW_NAMES]
        lines.append(f"| {c.revision} | {c.model_name} | **{fmt_error(c.error)}** | " + " | ".join(per) + " |")
    if len(comps) > 1:
        lines += ["", f"Error {fmt_error(comps[0].error)} (revision {comps[0].revision}) -> {fmt_error(last.error)} "
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
