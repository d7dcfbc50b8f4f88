"""Sensor-only models: no [plant], each output y = reference + sensor effects.

Such a model is a plant with no states and a unit feedthrough (y = D u, D = I, the command is the
reference): parsing, the predictions' closed forms, simulation (batch, trials, step API, the live
emulator), the model file written back, the effects that need a plant refused, and analysis and
diagnosis end to end through the CLI on simulated recordings.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.cli import assert_bad
from helpers.cli import cli_in_process as cli
from helpers.live import check_recording
from helpers.recordings import write_record

from noiselab.model import ModelError, parse_model

GYRO = """name = "gyro"
[sampling]
Ts = 0.01
[outputs]
names = ["gyro_x"]
units = ["rad/s"]
[sensor.white]
std = 0.01
"""
WHITE_STD, WALK_STD = 0.01, 0.003          # rad/s per sample; rad/s/sqrt(s)
GYRO_WALK = GYRO + f"[sensor.bias_walk]\nstd = {WALK_STD}\n"

# two accelerometer axes on a rate table: a sine reference, gravity as the second axis' offset
AXES = """name = "axes"
[sampling]
Ts = 0.01
[outputs]
names = ["acc_x", "acc_z"]
units = ["m/s^2", "m/s^2"]
[command]
kind = "sine"
amplitude = [0.5, 0.1]
frequency_hz = 1.3
offset = [0.0, 9.81]
[sensor.scale_factor]
error = [0.01, -0.02]
[sensor.bias_walk]
std = 0.02
[sensor.bias_markov]
std = 0.02
tau_s = 0.5
[sensor.white]
std = 0.03
"""
# every sensor effect a sensor alone can have, for the bit-for-bit path checks
EVERY = AXES + """[sensor.tone]
amplitude = 0.01
frequency_hz = 20.0
[sensor.quantization]
step = 0.002
"""

NEED_PLANT = {
    "process.white": "std = 0.1",
    "actuator.white": "std = 0.1",
    "actuator.ar1": "std = 0.1\ntau_s = 0.5",
    "actuator.lag": "tau_s = 0.1",
    "actuator.saturation": "limit = 1.0",
    "actuator.deadzone": "width = 0.1",
    "sensor.jitter": "std_s = 1e-4",
}


def run_json(capsys, *argv) -> dict:
    rc, out, err = cli(capsys, *argv)
    assert rc == 0, err[-3000:]
    return json.loads(out)


# -- the model ---------------------------------------------------------------------------------------
def test_a_model_without_plant_is_a_plant_with_no_states_and_unit_feedthrough():
    m = parse_model(AXES)
    assert not m.has_plant and not m.predicts_level
    assert (m.n_x, m.m, m.p) == (0, 2, 2)
    assert m.Ad.shape == (0, 0) and m.Bd.shape == (0, 2) and m.Cy.shape == (2, 0)
    assert np.array_equal(m.Dy, np.eye(2))
    assert m.output_names == ("acc_x", "acc_z") and m.plant.state_names == ()
    # the mean is the reference through the sensor gain, exactly: (1 + e) (offset + A sin(2 pi f t))
    mean = m.predictor().mean_response(300)
    t = np.arange(300) * m.Ts
    ref = np.array([0.0, 9.81]) + np.array([0.5, 0.1]) * np.sin(2 * np.pi * 1.3 * t)[:, None]
    np.testing.assert_allclose(mean.y, ref * np.array([1.01, 0.98]), rtol=0, atol=1e-14)     # rounding of the sine argument
    assert not np.any(mean.ydot)


@pytest.mark.parametrize("eid", sorted(NEED_PLANT))
def test_effects_that_need_a_plant_are_a_one_line_error(eid, tmp_path, capsys):
    """Process and actuator effects act on a plant's states and input; the jitter's error is
    dy/dt * dt, and the reference is held over each sample. Without [plant]: one line naming the
    effect and why, exit 2."""
    text = GYRO + f"[{eid}]\n{NEED_PLANT[eid]}\n"
    with pytest.raises(ModelError, match=rf"^<model>: \[{eid}\]: not possible in a model without \[plant\]: "):
        parse_model(text)
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert_bad(cli(capsys, "predict", path), str(path), f"[{eid}]", "without [plant]")
    # and the same effect cannot be added to a sensor-only model in code either
    with pytest.raises(ModelError, match=rf"\[{eid}\]: not possible"):
        parse_model(GYRO).with_effect(eid, dict(parse_model(
            "name = 'p'\n[sampling]\nTs = 0.01\n[plant]\nm = 1.0\nc = 0.5\nk = 2.0\n"
            f"[{eid}]\n{NEED_PLANT[eid]}\n").effects[eid].param_dict()))


def test_without_plant_the_outputs_table_with_names_is_required(tmp_path, capsys):
    bare = "name = \"g\"\n[sampling]\nTs = 0.01\n[sensor.white]\nstd = 0.01\n"
    path = tmp_path / "bare.toml"
    path.write_text(bare)
    assert_bad(cli(capsys, "predict", path), "missing required table [plant]", "[outputs] with names")
    path.write_text(bare + "[outputs]\nunits = [\"m\"]\n")
    assert_bad(cli(capsys, "predict", path), "[outputs] names: missing required key")


def test_the_model_file_round_trips_without_a_plant_table():
    m = parse_model(EVERY)
    text = m.to_toml()
    assert "[plant]" not in text and "[outputs]" in text
    back = parse_model(text)
    assert back.to_dict() == m.to_dict() and not back.has_plant
    np.testing.assert_array_equal(back.predictor().steady_state().var_y, m.predictor().steady_state().var_y)
    # the diagnosis' edits keep it a sensor-only model
    for edited in (m.with_params("sensor.white", {"std": 0.05}), m.with_effect("sensor.white", {"std": 0.05}),
                   m.without_effect("sensor.tone")):
        assert not edited.has_plant and "plant" not in edited.to_dict()
        assert parse_model(edited.to_toml()).to_dict() == edited.to_dict()


# -- predictions ---------------------------------------------------------------------------------------
def test_predict_json_of_a_gyro_at_rest(tmp_path, capsys):
    """White noise: var_y = std^2; the bias walk: bias_var_rate = K^2 per second (DESIGN.md's
    contract). No states: P is the empty covariance [] (null would mean an unstable plant)."""
    path = tmp_path / "gyro.toml"
    path.write_text(GYRO_WALK)
    rep = run_json(capsys, "predict", path, "--json")
    assert rep["outputs"] == 1 and rep["stable"] is True
    np.testing.assert_allclose(rep["var_y"], [WHITE_STD**2], rtol=1e-12)
    np.testing.assert_allclose(rep["bias_var_rate"], [WALK_STD**2], rtol=1e-12)
    assert rep["P"] == [] and rep["state_names"] == []
    assert set(rep["contributions"]) == {"sensor.white"}
    np.testing.assert_allclose(rep["contributions"]["sensor.white"], [WHITE_STD**2], rtol=1e-12)


def test_spectra_of_a_gyro_at_rest_are_the_closed_forms():
    """One-sided PSD of white noise 2 Ts std^2; ACF std^2 at lag 0, 0 beyond; Allan variance of
    white std^2 / m and of the walk (increment variance q = K^2 Ts) q (2 m^2 + 1) / (6 m) (the
    sampled forms, module docstring of noiselab.model.spectra)."""
    m = parse_model(GYRO_WALK)
    pr = m.predictor()
    Ts = m.Ts
    psd, _ = pr.psd(np.array([0.1, 1.0, 10.0, 49.0]))
    np.testing.assert_allclose(psd["sensor.white"][:, 0], 2 * Ts * WHITE_STD**2, rtol=1e-12)
    acf = pr.acf(5)["sensor.white"][:, 0]
    np.testing.assert_allclose(acf, [WHITE_STD**2, 0, 0, 0, 0], rtol=1e-12, atol=1e-20)
    mm = np.array([1, 2, 10, 100, 1000])
    av = pr.allan(mm)
    # the Allan variance is a difference of prefix sums over 2m lags: ~1e-10 relative rounding at m = 1000
    np.testing.assert_allclose(av["sensor.white"][:, 0], WHITE_STD**2 / mm, rtol=1e-8)
    q = WALK_STD**2 * Ts
    np.testing.assert_allclose(av["sensor.bias_walk"][:, 0], q * (2 * mm**2 + 1) / (6 * mm), rtol=1e-8)


@pytest.mark.slow
def test_simulation_matches_the_predicted_mean_and_variance():
    """2000 independent trials of AXES (fixed seed): at samples k far apart (4 Markov times) the
    ensemble mean and variance of each output against the predicted E[y_k] and S_y,k (the bias
    walk's k Q_b and the Gauss-Markov bias' transient from 0 included). Tolerances are the
    estimators' own spreads: the mean's sd is sqrt(S / T), the variance ratio's sqrt(2 / (T - 1))
    for Gaussian y; 4.5 sd over 12 checks is a false alarm below 1e-4."""
    m = parse_model(AXES)
    T, N = 2000, 601
    rec = m.simulate(N, seed=11, trials=T)
    pr = m.predictor()
    mean = pr.mean_response(N).y
    S = pr.covariance(N).Sy
    for k in (100, 300, 600):
        ybar = rec.y[:, k].mean(axis=0)
        var = rec.y[:, k].var(axis=0, ddof=1)
        z = (ybar - mean[k]) / np.sqrt(S[k] / T)
        ratio = var / S[k]
        assert np.all(np.abs(z) < 4.5), (k, z)
        assert np.all(np.abs(ratio - 1) < 4.5 * np.sqrt(2 / (T - 1))), (k, ratio)
    # the walk is in S: by the last sample it is most of the first output's variance
    assert S[600, 0] > 2 * pr.steady_state().var_y[0]


def test_step_api_equals_batch_bit_for_bit():
    """The real-time step API and the batch simulation give the same floats for a sensor-only
    model, with its own reference and with a given one (the emulator's external commands)."""
    m = parse_model(EVERY)
    n = 5000                                # more than one of the stepper's noise buffers
    batch = m.simulate(n, seed=7)
    st = m.stepper(seed=7)
    steps = [st.step() for _ in range(n)]
    assert np.array_equal(np.array([s[3] for s in steps]), batch.y)
    assert np.array_equal(np.array([s[2] for s in steps]), batch.u)
    assert batch.x.shape == (n, 0) and all(s[1].shape == (0,) for s in steps)
    u = np.random.default_rng(3).normal(size=(n, 2))
    given = m.simulate(n, seed=8, command=u)
    st = m.stepper(seed=8)
    assert np.array_equal(np.array([st.step(u[k])[3] for k in range(n)]), given.y)
    trials = m.simulate(n, seed=7, trials=3)
    assert trials.y.shape == (3, n, 2) and trials.x.shape == (3, n, 0)


def test_the_emulator_streams_a_sensor_only_model(tmp_path, capsys):
    """`noiselab run` (emulator and recorder as processes, real Zenoh on loopback): the recording
    holds every sample, the payloads are the step API's bit for bit and the measurement the batch
    simulation's; the truth is the empty state."""
    path = tmp_path / "gyro.toml"
    path.write_text(GYRO_WALK)
    rep = run_json(capsys, "run", path, "--duration", "2", "--seed", "5", "--out", tmp_path / "rec",
                   "--no-analyze", "--json")
    check_recording(rep["recording"], parse_model(GYRO_WALK), 5, 200)


# -- analysis and diagnosis ---------------------------------------------------------------------------------
def test_diagnose_finds_the_bias_walk_of_a_gyro_at_rest(tmp_path, capsys):
    """A gyro at rest recorded by `noiselab simulate` with a bias walk, diagnosed against white
    noise alone: the walk is found, its interval holds the true K, the error falls to about 1
    (a correct model's error on this record length: 0.90 to 1.95 over 8 seeds, measured), and no
    effect a sensor alone cannot have is tried (the verbose log names every candidate)."""
    model, walk = tmp_path / "gyro.toml", tmp_path / "gyro-walk.toml"
    model.write_text(GYRO)
    walk.write_text(GYRO_WALK)
    rec, fitted = tmp_path / "walk.mcap", tmp_path / "fitted.toml"
    assert cli(capsys, "simulate", walk, "--duration", "300", "--seed", "1", "--out", rec)[0] == 0
    rc, out, err = cli(capsys, "diagnose", rec, "--model", model, "--json", "--fit-out", fitted, "--verbose")
    assert rc == 0, err[-3000:]
    rep = json.loads(out)
    assert [c["effect"] for c in rep["missing"]] == ["sensor.bias_walk"]
    lo, hi = rep["missing"][0]["interval"]["std"]
    assert lo < WALK_STD < hi
    assert rep["error_before"] > 100 and rep["error_after"] < 3.0
    for eid in ("process.", "actuator.", "sensor.jitter"):
        assert eid not in err and all(not c["effect"].startswith(eid) for c in rep["candidates"])
    fit = parse_model(fitted.read_text())
    assert not fit.has_plant and set(fit.effects) == {"sensor.bias_walk", "sensor.white"}
    # the true model explains the same record
    assert run_json(capsys, "analyze", rec, "--model", walk, "--json")["error"] < 3.0


def test_a_constant_offset_of_a_sensor_at_rest_is_not_a_missing_effect(tmp_path, capsys):
    """A sensor at rest reads its constant offset (a gyro's bias, gravity on an accelerometer
    axis), which a sensor-only model does not predict: white noise + 0.3 is analysed exactly as
    the same noise without it (no level view), and the diagnosis finds nothing missing."""
    model = tmp_path / "gyro.toml"
    model.write_text(GYRO)
    m = parse_model(GYRO)
    plain, offset = tmp_path / "plain.mcap", tmp_path / "offset.mcap"
    write_record(plain, m, 30_000, 5)
    write_record(offset, m, 30_000, 5, lambda x, u, y: y.__iadd__(0.3))
    a = run_json(capsys, "analyze", plain, "--model", model, "--json")
    b = run_json(capsys, "analyze", offset, "--model", model, "--json")
    assert "level" not in b["error_per_view"] and b["error"] < 3.0
    assert b["error"] == pytest.approx(a["error"], rel=1e-9)
    d = run_json(capsys, "diagnose", offset, "--model", model, "--json")
    assert d["missing"] == [] and d["error_after"] == pytest.approx(a["error"], rel=1e-9)
