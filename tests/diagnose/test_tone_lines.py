"""Several lines, found one after another (``sensor.tone`` holds any number; the search offers one
more line beside those the model holds, :meth:`noiselab.diagnose.search.Search._tones`), and a line
whose frequency wanders over the record: its interval as wide as the record's halves say
(:func:`noiselab.diagnose.intervals._tone_intervals`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from noiselab.diagnose.diagnose import diagnose
from noiselab.model import parse_model

BASE = 'name = "g"\n[sampling]\nTs = 0.01\n[outputs]\nnames = ["gx"]\nunits = ["rad/s"]\n[sensor.white]\nstd = 0.002\n'
LINES = [(8e-4, 38.0), (5e-4, 12.3), (4e-4, 21.7)]


def test_three_lines_are_found_one_after_another():
    """A gyro at rest with three vibration lines; its model has the white noise only. Each line is
    added in turn (the strongest first), each planted frequency inside its interval and each
    amplitude within 30 %, the fitted model holds the three lines, the model error falls to about
    one; and each line's frequency interval is the Cramer-Rao bound's (the halves agree)."""
    (a0, f0), *rest = LINES
    more = ", ".join(f"{{amplitude = {a}, frequency_hz = {f}}}" for a, f in rest)
    truth = parse_model(BASE + f"[sensor.tone]\namplitude = {a0}\nfrequency_hz = {f0}\nlines = [{more}]\n")
    rec = truth.simulate(18_000, seed=3)
    logs = []
    rep = diagnose(parse_model(BASE), rec.t, rec.y, rec.u, log=logs.append)
    found = [m for m in rep["missing"] if m["effect"] == "sensor.tone"]
    assert [m["mode"] for m in found] == ["add"] * 3, [(m["effect"], m["mode"]) for m in rep["missing"]]
    assert [round(m["params"]["frequency_hz"], 1) for m in found] == [f for _, f in LINES], logs
    n = rec.t.size
    for m, (a, f) in zip(found, LINES):
        lo, hi = m["interval"]["frequency_hz"]
        assert lo <= f <= hi, (f, lo, hi)
        assert m["params"]["amplitude"] == pytest.approx(a, rel=0.3)
        # the steady line's Cramer-Rao width: sd = sqrt(24 S / (A^2 N^3)) / (2 pi Ts), S = std^2
        sd = math.sqrt(24 * 0.002**2 / (a**2 * n**3)) / (2 * math.pi * 0.01)
        assert (hi - lo) / (2 * 1.96 * sd) == pytest.approx(1.0, rel=0.25), (f, hi - lo, sd)
    fitted = parse_model(rep["fitted_model"]).effects["sensor.tone"]
    assert sorted(round(float(fl[0]), 1) for _, fl in fitted.all_lines()) == sorted(f for _, f in LINES)
    assert rep["error_before"] > 20 and rep["error_after"] <= 1.5


def test_a_line_whose_frequency_wanders_gets_the_interval_its_halves_support():
    """A vibration line whose frequency drifts from 30.00 to 30.04 Hz over 3 minutes (a motor
    warming up; no model of the catalogue draws it): the diagnosis fits one line, and its frequency
    interval covers both halves' mean frequencies (30.01 and 30.03 Hz), many times the Cramer-Rao
    width of a steady line, which would have excluded both."""
    Ts, n = 0.01, 18_000
    t = np.arange(n) * Ts
    f_t = 30.0 + 0.04 * t / t[-1]
    phase = 2 * np.pi * np.cumsum(f_t) * Ts
    rng = np.random.default_rng(5)
    a = 1.5e-3
    y = (a * np.sin(phase) + 0.002 * rng.standard_normal(n))[:, None]
    rep = diagnose(parse_model(BASE), t, y, None)
    (m,) = [m for m in rep["missing"] if m["effect"] == "sensor.tone"][:1]
    lo, hi = m["interval"]["frequency_hz"]
    assert lo <= 30.01 and hi >= 30.03, (lo, hi, m["params"])
    sd = math.sqrt(24 * 0.002**2 / (a**2 * n**3)) / (2 * math.pi * Ts)
    assert (hi - lo) > 10 * 2 * 1.96 * sd, (hi - lo, sd)
