"""Data structures of a comparison between a recording and a model (pure data, no I/O).

The viewers (Rerun, PNG, text) and the JSON output are built from these; nothing else.
Units: time s, frequency Hz, lag s, tau s; PSD units^2/Hz (one-sided); ACF as autocovariance
units^2 (``normalized`` views divide by lag 0); Allan deviation units; variance units^2.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class AnalysisError(ValueError):
    """Data that cannot be analysed against the model (one-line message). Here, not in
    :mod:`.compare`, so that reading a recording (:mod:`.load`) does not import the analysis."""


VIEW_NAMES = ("variance", "acf", "psd", "allan", "level")   # level: records from rest only
VIEW_UNITS = {"variance": "s", "acf": "s", "psd": "Hz", "allan": "s", "level": "s"}   # of each view's x


@dataclass
class View:
    """One statistic of one output: empirical against predicted, with the estimator's band.

    ``predicted`` is what the estimator is expected to give if the model is right (the model's
    spectrum seen through the same window, etc.), ``lo``/``hi`` the band the empirical values
    should fall in at confidence ``conf``; ``contributions`` split ``predicted`` by effect id
    (they sum to it). ``z`` is each point's standardized deviation (about N(0, 1) under the
    model); ``flagged`` marks points outside the band; ``error`` = mean(z^2), about 1 when the
    model is right.
    """

    name: str                      # one of VIEW_NAMES
    output: int                    # measurement component
    x: np.ndarray                  # frequency [Hz] | lag [s] | tau [s] | window centre time [s] (variance, level)
    x_label: str
    y_label: str
    empirical: np.ndarray
    predicted: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    contributions: dict = field(default_factory=dict)   # effect id -> array like predicted
    z: np.ndarray = None
    flagged: np.ndarray = None
    error: float = float("nan")
    error_var: float = float("nan")    # variance of ``error`` under the model (weighs it in the model error)
    log_x: bool = False
    log_y: bool = False
    conf: float = 0.95
    notes: list = field(default_factory=list)
    x_lo: np.ndarray = None        # the points' extents where they stand for a band (the PSD's bands'
    x_hi: np.ndarray = None        # edges); the regions span these, else the points' x


@dataclass
class Region:
    """A contiguous run of flagged points of one view: where the data leave the model."""

    view: str
    output: int
    x_lo: float
    x_hi: float
    points: int
    max_abs_z: float
    direction: str                 # "above" (data exceed the model) or "below"
    output_name: str | None = None  # the model's name of the output ([outputs]), when known

    def describe(self, unit: str) -> str:
        who = self.output_name or f"output {self.output}"
        return (f"{self.view} ({who}): {self.x_lo:.4g}..{self.x_hi:.4g} {unit}, data "
                f"{self.direction} the model, |z| up to {self.max_abs_z:.1f} over {self.points} points")


@dataclass
class Comparison:
    """Everything one analysis found, for one model revision."""

    model_name: str
    model_source: str
    revision: int
    Ts: float
    t: np.ndarray                  # (N,) s
    y: np.ndarray                  # (N, p) measurement
    y_mean: np.ndarray             # (N, p) predicted mean response to the recorded command
    y_sd: np.ndarray               # (N, p) predicted std of y_k (sqrt S_y,k, bias walk growth included)
    truth: np.ndarray | None       # (N, n) or None (real data)
    views: list                    # of View
    error: float                   # the model error (mean over views of their errors)
    error_per_view: dict           # view name -> mean error over outputs
    regions: list                  # of Region
    notes: list = field(default_factory=list)   # data problems found (gaps, irregular timing, ...)
    output_names: tuple | None = None   # the model's [outputs] names and units, one per column of y
    output_units: tuple | None = None
    model_effects: dict | None = None   # {effect id: its parameters}: what each revision holds
    recording: str | None = None        # where the data came from (path [topic:field] or [device])

    def view(self, name: str, output: int = 0) -> View:
        for v in self.views:
            if v.name == name and v.output == output:
                return v
        raise KeyError((name, output))


def fmt_score(s: float) -> str:
    """A Delta BIC for a sentence: one decimal (as the threshold is read), 3 significant digits
    once it is so large that more say nothing."""
    return f"{s:.1f}" if abs(s) < 1e5 else f"{s:.3g}"
