"""A record under feedback (service/diagnose/closed_loop.py): the diagnosis tells a closed-loop
record from an open-loop one (the command follows past measurements: Granger's test of the
residual's past on the command), says so, and takes a line the controller copied from the
measurement into the command for what it is, a sensor effect, where the open-loop rule (a residual
line at a command line is the mean response's error) refused it.

Records: the seed plant under a discrete PID on its measurement, offline
(tests/helpers/closed_loop.py: the command computed from the samples before it, as over the wire)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from helpers.closed_loop import closed_loop

from noiselab.diagnose.closed_loop import ALPHA, R2_MIN, feedback
from noiselab.diagnose.diagnose import diagnose
from noiselab.model import load_model, parse_model


def external(name: str):
    """Scenario ``name`` with its command external (a controller's)."""
    text = re.sub(r"\[command\][^\[]*", '[command]\nkind = "external"\n\n', load_model(name).to_toml())
    return parse_model(text, f"{name} (closed loop)")


NOMINAL = external("seed-nominal")
TONE = "\n[sensor.tone]\namplitude = 0.01\nfrequency_hz = 3.1\n"


def test_an_open_loop_command_does_not_follow_the_measurement():
    """The seed lesson's sine (open loop) and a PRBS: no feedback at ALPHA; the PD's command does,
    its residual's past explaining most of the command's broadband variance."""
    seed = load_model("seed")
    rec = seed.simulate(30_000, seed=3)
    v = rec.y - load_model("seed-nominal").predictor().mean_response(rec.y.shape[0], rec.u).y
    fb = feedback(rec.u, v, seed.Ts, [0.7])
    assert fb is None or (not fb.closed and fb.p_value > ALPHA), fb
    prbs = parse_model(re.sub(r"\[command\][^\[]*", '[command]\nkind = "prbs"\namplitude = 0.8\nbit_s = 0.2\n\n',
                              seed.to_toml()))
    rec = prbs.simulate(30_000, seed=3)
    v = rec.y - prbs.predictor().mean_response(rec.y.shape[0], rec.u).y
    fb = feedback(rec.u, v, prbs.Ts)
    assert fb is not None and not fb.closed and fb.r2 < 0.01, fb
    # a wrong mean response (the truth has an actuator lag the model lacks) puts a function of past
    # commands into the residual: the command's own past carries it, no feedback is read
    lagged = parse_model(prbs.to_toml() + "\n[actuator.lag]\ntau_s = 0.15\n")
    rec = lagged.simulate(30_000, seed=5)
    v = rec.y - prbs.predictor().mean_response(rec.y.shape[0], rec.u).y
    fb = feedback(rec.u, v, prbs.Ts)
    assert fb is not None and not fb.closed, fb
    # under a chirp (its frequency drifting, which no fixed 40-lag predictor of the command holds)
    # the missing lag's error carries a little of the command's longer past: significant at this
    # N (r2 0.5 %), but far below the materiality share R2_MIN
    truth, nominal = load_model("hidden/actuator.lag"), load_model("hidden/actuator.lag-nominal")
    rec = truth.simulate(90_000, seed=11)
    v = rec.y - nominal.predictor().mean_response(rec.y.shape[0], rec.u).y
    fb = feedback(rec.u, v, truth.Ts)
    assert fb is not None and fb.p_value < ALPHA and fb.r2 < R2_MIN / 5 and not fb.closed, fb
    cl = closed_loop(parse_model(NOMINAL.to_toml() + TONE), 30_000, kp=20.0, ki=0.0, kd=2.0, seed=4)
    v = cl.y - NOMINAL.predictor().mean_response(cl.y.shape[0], cl.u).y
    fb = feedback(cl.u, v, NOMINAL.Ts, [3.1])
    assert fb.closed and fb.p_value < 1e-12 and fb.r2 > 0.5, fb


@pytest.mark.parametrize("ki,ref", [(0.0, "sine"), (5.0, "step")])
def test_a_sensor_tone_the_controller_feeds_back_is_found_as_a_sensor_tone(ki, ref):
    """A PD (and a PI-D) on the seed plant whose sensor carries a 3.1 Hz tone: the controller copies
    the tone into the command, where the open-loop rule took the residual's line for the mean
    response's error and offered no tone (the diagnosis then refitted white noise and added colored
    noises, model error 45). Now the record is said to be closed-loop, the command's line at 3.1 Hz
    is the measurement's, and the tone is found: amplitude within 10 %, its frequency's interval
    holding 3.1 Hz, the model error about one."""
    truth = parse_model(NOMINAL.to_toml() + TONE)
    rec = closed_loop(truth, 30_000, kp=20.0, ki=ki, kd=2.0, seed=4, ref=ref, amplitude=0.1, frequency_hz=0.3)
    rep = diagnose(NOMINAL, rec.t, rec.y, rec.u, at_rest=True)
    assert any(n.startswith("the record looks closed-loop") for n in rep["notes"]), rep["notes"]
    assert rep["feedback"].closed and np.any(np.isclose(rep["fed_back"], 3.1, atol=0.01)), rep["fed_back"]
    (tone,) = [m for m in rep["missing"] if m["effect"] == "sensor.tone"]
    assert tone["params"]["amplitude"] == pytest.approx(0.01, rel=0.1)
    lo, hi = tone["interval"]["frequency_hz"]
    assert lo <= 3.1 <= hi, (lo, hi)
    assert [m["effect"] for m in rep["missing"]] == ["sensor.tone"], [(m["effect"], m["params"]) for m in rep["missing"]]
    assert rep["error_after"] <= 1.5 < rep["error_before"]


def test_a_closed_loop_null_record_reports_nothing_and_the_json_says_closed_loop(tmp_path):
    """The nominal model under the PD, diagnosed against itself: nothing reported, the record said
    to be closed-loop in the JSON (``closed_loop``)."""
    from noiselab.diagnose.report import diagnosis_json

    rec = closed_loop(NOMINAL, 30_000, kp=20.0, ki=0.0, kd=2.0, seed=9, ref="sine", amplitude=0.1, frequency_hz=0.3)
    rep = diagnose(NOMINAL, rec.t, rec.y, rec.u, at_rest=True)
    assert rep["missing"] == [], [(m["effect"], m["score"]) for m in rep["missing"]]
    js = diagnosis_json(rep)
    assert js["closed_loop"] is not None and js["closed_loop"]["p_value"] < ALPHA and js["closed_loop"]["r2"] > 0.5
    reach = js["closed_loop"]["scale_factor_reach"]
    assert reach == rep["scale_factor_reach"] > 0 and any("scale factor" in n for n in js["notes"])


@pytest.mark.slow
def test_the_scale_factor_a_closed_loop_record_shows_falls_as_its_reference_grows():
    """The smallest scale factor a closed-loop record shows (``scale_factor_reach``, from the fitted
    model's information on it) on the PI-D null servo, 90 s: with a sine reference the information
    is the reference response's, A^2 times a constant, plus the noise's shape, I0, which alone is
    what the loop with no reference has. So e_min(A) / e_min(2A) = sqrt((4 I_A + I0) / (I_A + I0)):
    2 where the reference dominates, 1 where it adds nothing. With I0 from the record without a
    reference, the ratios are within 5 % of that prediction (the information is a quadratic form
    in the record: its spread over records of 18,000 samples is a few % at most), and without a
    reference the reach is several times the 0.15 rad sine's."""
    from noiselab.model.controller import ControllerSpec, simulate_closed_loop

    def reach(amplitude):
        m = load_model("hidden-closed/null-pid")
        spec = ControllerSpec(m.controller.kp, m.controller.ki, m.controller.kd, reference="sine" if amplitude else "none",
                              amplitude=amplitude, frequency_hz=0.4 if amplitude else 0.0)
        o = simulate_closed_loop(m, 18_000, seed=3, spec=spec)
        rep = diagnose(m, o["t"], o["y"], o["u"], max_effects=1)
        assert rep["feedback"] is not None and rep["missing"] == []
        return rep["scale_factor_reach"]

    none = reach(0.0)
    e = {a: reach(a) for a in (0.15, 0.3, 0.6)}
    assert none > 2 * e[0.15], (none, e)
    for a in (0.15, 0.3):
        # information I = (THRESHOLD + ln n) / e_min^2; I0 the no-reference record's
        i_a, i0 = e[a] ** -2 - none ** -2, none ** -2
        predicted = math.sqrt((4 * i_a + i0) / (i_a + i0))
        assert abs(e[a] / e[2 * a] / predicted - 1) < 0.05, (a, e, none, predicted)


def test_an_external_command_is_averaged_over_the_record_it_drove():
    """A dead zone's gain P(|u + n| > w) and the variances it sets are averages over the command.
    An external command is zero as the model computes it; the diagnosis replays the recorded one
    (:meth:`Model.replaying`): over the same command, the steady state is
    the open-loop model's to rounding, while over zeros the dead zone passes almost none of the
    actuator's noise. The fitted model the report writes has the user's command back."""
    sine = load_model("seed-nominal").with_params("actuator.white", {"std": 0.3}).with_effect(
        "actuator.deadzone", {"width": 0.5})
    ext = parse_model(re.sub(r"\[command\][^\[]*", '[command]\nkind = "external"\n\n', sine.to_toml()), "external")
    n = sine.predictor().span                     # the open-loop model's horizon (60 s)
    u = sine.command.values(0, n, sine.Ts)
    assert sine.replaying(u) is sine             # its own command: nothing to replay
    got = ext.replaying(u)
    assert got.command.kind == "external" and "replay" in got.command.params
    a, b, zero = (m.predictor().steady_state().contributions["actuator.white"] for m in (sine, got, ext))
    np.testing.assert_allclose(b, a, rtol=1e-9)
    assert np.all(zero < a / 4), (zero, a)        # at u = 0 the noise rarely leaves the dead zone
    rec = sine.simulate(3000, seed=5)
    rep = diagnose(ext, rec.t, rec.y, rec.u, max_effects=0)
    assert 'kind = "external"' in rep["fitted_model"] and "replay" not in rep["fitted_model"]
    assert all("replay" not in m.command.params for m in [rep["model"], *rep["step_models"]])


def test_analyze_predicts_a_closed_loop_record_over_its_recorded_command():
    """The comparison (`noiselab analyze`) of a closed-loop record with a dead zone: its predicted
    variance is averaged over the recorded command, not over the external command's zeros, where
    the dead zone would pass almost none of the drive's noise; the model error is then about 1."""
    from noiselab.diagnose.compare import compare
    truth = load_model("hidden-closed/actuator.deadzone")
    rec = closed_loop(truth, 18_000, kp=truth.controller.kp, ki=truth.controller.ki, kd=truth.controller.kd,
                      seed=3, ref="sine", amplitude=0.3, frequency_hz=0.4)
    cmp = compare(truth, rec.t, rec.y, rec.u, level=True)
    assert cmp.error < 1.5, (cmp.error, cmp.error_per_view)
