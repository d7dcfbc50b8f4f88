"""``sensor.tone`` with several lines (service/model/effects/sensor_tone.py): the file's ``lines``,
their one-line errors, the round trip, the simulation and every prediction as the sum of the lines
(variance sum A_i^2 / 2, autocovariance sum (A_i^2 / 2) cos(2 pi f_i tau), one PSD line each), and
the diagnosis' hooks that add a line and take it back (``push_line``, ``pop_line``)."""

from __future__ import annotations

import numpy as np
import pytest

from noiselab.model import ModelError, parse_model

BASE = 'name = "g"\n[sampling]\nTs = 0.01\n[outputs]\nnames = ["gx"]\nunits = ["rad/s"]\n[sensor.white]\nstd = 0.002\n'
LINES = [(8e-4, 38.0), (5e-4, 12.3), (4e-4, 21.7)]


def three_lines(extra: str = "") -> str:
    (a0, f0), *rest = LINES
    more = ", ".join(f"{{amplitude = {a}, frequency_hz = {f}}}" for a, f in rest)
    return BASE + f"[sensor.tone]\namplitude = {a0}\nfrequency_hz = {f0}\nlines = [{more}]\n{extra}"


def test_lines_round_trip_and_sum_in_every_prediction():
    m = parse_model(three_lines())
    e = m.effects["sensor.tone"]
    assert [(float(a[0]), float(f[0])) for a, f in e.all_lines()] == LINES
    assert parse_model(m.to_toml()).to_toml() == m.to_toml()
    assert "lines = [{amplitude = 0.0005, frequency_hz = 12.3}, {amplitude = 0.0004, frequency_hz = 21.7}]" in m.to_toml()
    pr = m.predictor()
    tone_var = sum(a**2 / 2 for a, _ in LINES)
    np.testing.assert_allclose(pr.steady_state().contributions["sensor.tone"], [tone_var], rtol=1e-12)
    np.testing.assert_allclose(pr.covariance(5).parts["sensor.tone"], np.full((5, 1), tone_var), rtol=1e-12)
    lag = np.arange(40)
    acf = pr.acf(40)["sensor.tone"][:, 0]
    want = sum(a**2 / 2 * np.cos(2 * np.pi * f * lag * 0.01) for a, f in LINES)
    np.testing.assert_allclose(acf, want, rtol=1e-9, atol=1e-18)
    _, lines = pr.psd(np.array([1.0, 2.0]))
    assert sorted((round(f, 6), round(v, 15)) for eid, f, v, _ in lines if eid == "sensor.tone") == \
        sorted((f, round(a**2 / 2, 15)) for a, f in LINES)


def test_simulation_holds_each_line_and_steps_as_the_batch():
    m = parse_model(three_lines())
    y = m.simulate(100_000, seed=4).y[:, 0]
    X = np.abs(np.fft.rfft(y)) / (y.size / 2)          # a sinusoid on a bin: its amplitude
    f = np.fft.rfftfreq(y.size, 0.01)
    for a, fl in LINES:
        k = int(np.argmin(np.abs(f - fl)))
        assert X[k] == pytest.approx(a, rel=0.05), (fl, X[k], a)
    st = m.stepper(seed=7)
    assert np.array_equal(np.array([st.step()[3] for _ in range(3000)]), m.simulate(3000, seed=7).y)


def test_a_pushed_line_pops_back():
    one = parse_model(BASE + "[sensor.tone]\namplitude = 8e-4\nfrequency_hz = 38.0\n")
    y = one.simulate(2000, seed=9).y[:, 0]
    e = one.effects["sensor.tone"]
    assert e.param_dict() == {"amplitude": 8e-4, "frequency_hz": 38.0}
    pushed = one.with_params("sensor.tone", dict(e.push_line(), amplitude=5e-4, frequency_hz=12.3))
    assert [(float(a[0]), float(f[0])) for a, f in pushed.effects["sensor.tone"].all_lines()] == [(5e-4, 12.3), (8e-4, 38.0)]
    back = pushed.with_params("sensor.tone", pushed.effects["sensor.tone"].pop_line())
    assert back.to_toml() == one.to_toml()
    assert np.array_equal(back.simulate(2000, seed=9).y[:, 0], y)


@pytest.mark.parametrize("body,parts", [
    ("lines = 3", ("[sensor.tone] lines", "list of at most 64 tables")),
    ("lines = [{amplitude = 1e-4}]", ("[sensor.tone.lines[0]] frequency_hz", "missing")),
    ("lines = [{amplitude = 1e-4, frequency_hz = 80.0}]", ("[sensor.tone.lines[0]] frequency_hz", "Nyquist frequency 50")),
    ("lines = [{amplitude = -1e-4, frequency_hz = 8.0}]", ("[sensor.tone.lines[0]] amplitude", ">= 0")),
    ("lines = [{amplitude = 1e-4, frequency_hz = 8.0, phase = 1.0}]", ("[sensor.tone.lines[0]] phase", "unknown key")),
    ("lines = [3.0]", ("[sensor.tone.lines[0]]", "expected a table")),
])
def test_a_bad_line_is_a_one_line_error(body, parts):
    text = BASE + f"[sensor.tone]\namplitude = 8e-4\nfrequency_hz = 38.0\n{body}\n"
    with pytest.raises(ModelError) as info:
        parse_model(text, "bad.toml")
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith("bad.toml: "), msg
    for part in parts:
        assert part in msg, (part, msg)
