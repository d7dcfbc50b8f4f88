"""The viewers' colours and view titles, shared by the Rerun recording and the summary PNG: RGB
chosen to read on Rerun's dark background and on a white PNG alike, one colour per effect id
wherever it appears."""

from __future__ import annotations

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


def effect_color(index: int) -> tuple:
    return CONTRIB_COLORS[index % len(CONTRIB_COLORS)]
