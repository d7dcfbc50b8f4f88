"""The Allan deviation figure of ``noiselab allan --png``: one log-log panel per output.

Drawn from the command's report (:func:`noiselab.commands.allan.allan_report`, the ``--json``
document), so the figure shows exactly the numbers printed: the overlapping Allan deviation at
octave taus with its 68.3 % chi-squared band, the IEEE 952 lines read off it (sqrt(3) Q / tau
through Q at tau = sqrt(3) s, N / sqrt(tau) through N at tau = 1 s, K sqrt(tau / 3) through K at
tau = 3 s, the flicker floor 0.664 B), each drawn bold over the taus it was read on and thin beyond,
and the model's predicted curve when there is one.
Matplotlib's Agg canvas on a Figure (no pyplot, no display), as :mod:`noiselab.viewers.summary_png`.
"""

from __future__ import annotations

import io

import numpy as np

from noiselab.stats.ieee952 import FLICKER_FLOOR

DPI = 100
WIDTH_PX = 1100
PANEL_PX = 520

_DATA, _BAND, _MODEL = "#1f4e9c", "#9db8e3", "#c2410c"
_LINES = {"Q": ("#0e7490", "sqrt(3) Q / tau"), "N": ("#15803d", "N / sqrt(tau)"), "K": ("#7e22ce", "K sqrt(tau/3)"), "B": ("#a16207", "0.664 B")}


def _line(key: str, value: float, tau: np.ndarray) -> np.ndarray:
    if key == "Q":
        return np.sqrt(3.0) * value / tau
    if key == "N":
        return value / np.sqrt(tau)
    if key == "K":
        return value * np.sqrt(tau / 3.0)
    return np.full(tau.shape, value * FLICKER_FLOOR)


def allan_figure(rep: dict):
    """The figure (on its own Agg canvas) of an ``allan`` report."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    outs = rep["outputs"]
    p = max(len(outs), 1)
    fig = Figure(figsize=(WIDTH_PX / DPI, (PANEL_PX * p + 60) / DPI), dpi=DPI)
    FigureCanvasAgg(fig)
    fig.suptitle(f"Allan deviation: {rep['recording']}" + (f"  vs model {rep['model']}" if rep["model"] else ""),
                 fontsize=11, fontweight="bold")
    for i, (name, o) in enumerate(outs.items()):
        ax = fig.add_subplot(p, 1, i + 1)
        tau = np.asarray(o["tau"], float)
        dev = np.asarray(o["adev"], float)
        lo, hi = np.asarray(o["interval"], float).T
        ax.fill_between(tau, lo, hi, color=_BAND, alpha=0.6, lw=0, label=f"{100 * rep['conf']:.1f} % interval")
        ax.plot(tau, dev, "o-", color=_DATA, ms=4, lw=1.2, label="overlapping ADEV (data)")
        if o["model_adev"] is not None:
            md = np.array([np.nan if v is None else v for v in o["model_adev"]], float)
            ax.plot(tau, md, "-", color=_MODEL, lw=1.8, label="model (predicted)")
        text = []
        for key, rd in o["readings"].items():
            color, what = _LINES[key]
            if rd["value"] is None:
                text.append(f"{key}: none ({rd['reason']})")
                continue
            t0, t1 = rd["tau_range"]
            on = (tau >= t0) & (tau <= t1)
            ax.plot(tau, _line(key, rd["value"], tau), "--", color=color, lw=0.9)
            ax.plot(tau[on], _line(key, rd["value"], tau[on]), "-", color=color, lw=2.4, alpha=0.8,
                    label=f"{what}: {key} = {rd['value']:.3e} {rd['unit']}, read on tau {t0:.3g}-{t1:.3g} s")
        ax.set_xscale("log")
        ax.set_yscale("log")
        finite = np.concatenate([lo[lo > 0], hi[np.isfinite(hi)], dev[dev > 0]])
        if finite.size:
            ax.set_ylim(finite.min() / 2.0, finite.max() * 2.0)
        ax.set_xlim(tau.min() / 1.3, tau.max() * 1.3)
        ax.set_xlabel("tau [s]")
        ax.set_ylabel(f"Allan deviation [{o['unit']}]")
        ax.set_title(name, fontsize=10, loc="left")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="best", framealpha=0.85)
        if text:
            ax.text(0.01, 0.02, "\n".join(text), transform=ax.transAxes, fontsize=8, va="bottom", ha="left",
                    bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"}, wrap=True)
    fig.tight_layout(rect=(0, 0, 1, 1 - 40 / (PANEL_PX * p + 60)))
    return fig


def allan_png_bytes(rep: dict) -> bytes:
    """The PNG of :func:`allan_figure`."""
    buf = io.BytesIO()
    allan_figure(rep).savefig(buf, dpi=DPI, format="png")
    return buf.getvalue()
