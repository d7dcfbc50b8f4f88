"""What a comparison concludes: the model error over its views, and the regions where the data
leave the model (runs of flagged points)."""

from __future__ import annotations

import numpy as np

from ..results import Region, View


def model_error(views: list) -> float:
    """The model error: the views' errors (each mean(z^2), about 1 under the model) averaged with
    weights 1 / Var(error) under the model, so it is about 1 for a right model with the smallest
    spread the views allow (an ACF over a few correlation times or Allan deviations at long taus
    have few independent points and weigh less than a PSD over many independent bands)."""
    e = np.array([v.error for v in views], float)
    w = 1.0 / np.maximum(np.array([v.error_var for v in views], float), 1e-12)
    ok = np.isfinite(e) & np.isfinite(w)
    return float(np.sum(w[ok] * e[ok]) / np.sum(w[ok])) if ok.any() else float("nan")


def regions_of(view: View) -> list[Region]:
    """Runs of consecutive flagged points on one side of the model: a run whose z changes sign (an
    ACF above the model at short lags, below it at longer ones) is two regions, each with its own
    direction."""
    out = []
    f = view.flagged
    up = np.asarray(view.z) > 0
    i = 0
    while i < f.size:
        if not f[i]:
            i += 1
            continue
        k = i
        while k + 1 < f.size and f[k + 1] and up[k + 1] == up[i]:
            k += 1
        zz = view.z[i:k + 1]
        x0 = view.x[i] if view.x_lo is None else view.x_lo[i]
        x1 = view.x[k] if view.x_hi is None else view.x_hi[k]
        out.append(Region(view.name, view.output, float(x0), float(x1), k - i + 1,
                          float(np.max(np.abs(zz))), "above" if up[i] else "below"))
        i = k + 1
    return out

