"""The IMU engineer's vocabulary: ``sensor.white``'s ``density``, the IEEE Std 952 coefficients
of a model and of a diagnosis (``coefficients`` in ``diagnose --json``), ``noiselab export
--kalibr`` and the ``imu`` / ``imu-nominal`` scenarios."""

import json
import math
import re

import numpy as np
import pytest
from ruamel.yaml import YAML

from noiselab.cli import main
from noiselab.commands.export import yaml_float
from noiselab.model import load_model, parse_model
from noiselab.model.coefficients import model_coefficients, white_density
from noiselab.model.effects import CATALOGUE
from noiselab.model.errors import ModelError

TS = 0.005


def sensor_model(body: str, names=("gyro_x",), units=("rad/s",), name="imu_test", ts=TS) -> str:
    """A sensor-only model file (no [plant]: y = reference + sensor effects)."""
    return (f'name = "{name}"\n[sampling]\nTs = {ts}\n[outputs]\nnames = {json.dumps(list(names))}\n'
            f"units = {json.dumps(list(units))}\n{body}")


def error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("noiselab: "), err
    return err


# -- sensor.white: std or density --------------------------------------------------------------------
def test_density_is_std_times_sqrt_ts_and_simulates_the_same_noise():
    d = 1.6968e-4
    by_density = parse_model(sensor_model(f"[sensor.white]\ndensity = {d}\n"), "d")
    by_std = parse_model(sensor_model(f"[sensor.white]\nstd = {d / math.sqrt(TS)!r}\n"), "s")
    assert by_density.effects["sensor.white"].params["std"] == pytest.approx(d / math.sqrt(TS), rel=1e-15)
    a = by_density.simulate(4000, seed=7).y
    b = by_std.simulate(4000, seed=7).y
    np.testing.assert_allclose(a, b, rtol=1e-14, atol=0)
    va = by_density.predictor().steady_state().var_y
    assert va[0] == pytest.approx(d**2 / TS, rel=1e-13)


def test_a_density_is_written_back_as_a_density():
    text = sensor_model("[sensor.white]\ndensity = [1.6968e-4, 2.0e-3]\n", names=("gyro_x", "accel_x"),
                        units=("rad/s", "m/s^2"))
    m = parse_model(text, "d")
    out = m.to_toml()
    assert "density = [0.00016968, 0.002]" in out and "std" not in out
    again = parse_model(out, "again")
    assert again.effects["sensor.white"].param_dict() == {"density": [1.6968e-4, 2.0e-3]}
    # a value set under the catalogue's name (a diagnosis' refit) keeps the file's spelling
    eff = m.effects["sensor.white"]
    assert eff.respell({"std": [1.0, 2.0]}) == {"density": [math.sqrt(TS), 2 * math.sqrt(TS)]}
    plain = parse_model(sensor_model("[sensor.white]\nstd = 0.1\n"), "s").effects["sensor.white"]
    assert plain.respell({"std": 0.2}) == {"std": 0.2} and plain.param_dict() == {"std": 0.1}


def test_density_and_std_are_equivalent_spellings():
    eq = CATALOGUE["sensor.white"].equivalents
    assert eq({"std": 0.02}, TS)["density"] == pytest.approx(0.02 * math.sqrt(TS), rel=1e-15)
    assert eq({"density": [1e-3, 2e-3]}, TS)["std"] == pytest.approx([1e-3 / math.sqrt(TS), 2e-3 / math.sqrt(TS)])
    assert eq({"std": 1.0, "density": 1.0}, TS) == {}


@pytest.mark.parametrize("body, what", [
    ("[sensor.white]\nstd = 0.1\ndensity = 0.01\n", "exactly one of std"),
    ("[sensor.white]\n", "std: missing required key"),
    ("[sensor.white]\ndensity = -1e-3\n", "densities >= 0"),
    ("[sensor.white]\ndensity = 1e48\n", "at most 1e+50"),
])
def test_white_spelling_errors_are_one_line(body, what):
    ts = 1e-6 if "1e48" in body else TS
    with pytest.raises(ModelError) as exc:
        parse_model(sensor_model(body, ts=ts), "bad.toml")
    msg = str(exc.value)
    assert "\n" not in msg and "[sensor.white]" in msg and what in msg


# -- the coefficients --------------------------------------------------------------------------------
def test_coefficients_follow_the_closed_forms():
    std_w, k, step, s_gm, rho = np.array([0.01, 0.03]), 2e-4, 1e-3, 5e-3, 0.998
    m = parse_model(sensor_model(
        f"[sensor.white]\nstd = [0.01, 0.03]\n[sensor.bias_walk]\nstd = {k}\n[sensor.quantization]\nstep = {step}\n"
        f"[sensor.bias_markov]\nstd = {s_gm}\nrho = {rho}\n[sensor.tone]\namplitude = 0.1\nfrequency_hz = 3.0\n",
        names=("gyro_z", "accel_x"), units=("deg/s", "m/s^2")), "c")
    c = model_coefficients(m)
    assert set(c) == {"gyro_z", "accel_x"}
    for j, out in enumerate(("gyro_z", "accel_x")):
        u = ("deg/s", "m/s^2")[j]
        cj = c[out]
        assert set(cj) == {"N", "K", "q", "N_q", "sigma_GM", "tau_GM"}      # the tone has none
        assert cj["N"] == {"value": pytest.approx(std_w[j] * math.sqrt(TS), rel=1e-15), "interval": None,
                           "unit": f"{u}/sqrt(Hz)"}
        assert cj["K"]["value"] == k and cj["K"]["unit"] == f"{u}/sqrt(s)"
        assert cj["q"]["value"] == step and cj["q"]["unit"] == u
        assert cj["N_q"]["value"] == pytest.approx(step * math.sqrt(TS / 12), rel=1e-15)
        assert cj["N_q"]["unit"] == f"{u}/sqrt(Hz)"
        assert cj["sigma_GM"]["value"] == s_gm and cj["sigma_GM"]["unit"] == u
        assert cj["tau_GM"]["value"] == pytest.approx(-TS / math.log(rho), rel=1e-12) and cj["tau_GM"]["unit"] == "s"
    # white noises add in quadrature: the one density a white-only tool reads
    np.testing.assert_allclose(white_density(m), np.sqrt(std_w**2 * TS + step**2 * TS / 12), rtol=1e-14)


def test_white_coefficient_is_the_allan_deviation_at_one_second():
    """N is where the white noise's Allan deviation, N / sqrt(tau), crosses tau = 1 s (IEEE 952):
    checked on a simulated record against the overlapping ADEV, within its estimator's spread."""
    from noiselab.stats.allan import oadev
    d = 2.0e-3
    m = parse_model(sensor_model(f"[sensor.white]\ndensity = {d}\n"), "w")
    y = m.simulate(200_000, seed=11).y.reshape(-1)
    res = oadev(y, 1.0 / TS, taus=np.array([1.0]))
    adev, edf = float(res.dev[0]), float(res.edf[0])
    # the deviation's relative sd is about 1 / sqrt(2 edf) (chi-squared with edf degrees of freedom)
    tol = 4.0 / math.sqrt(2.0 * edf)
    assert model_coefficients(m)["gyro_x"]["N"]["value"] == d
    assert adev == pytest.approx(d, rel=tol)


def test_intervals_map_through_the_relation_onto_the_profiled_output():
    m = parse_model(sensor_model("[sensor.white]\nstd = [0.01, 0.03]\n[sensor.bias_walk]\nstd = 1e-4\n",
                                 names=("a", "b"), units=("V", "V")), "i")
    c = model_coefficients(m, {"sensor.white": {"std": [0.02, 0.04]}, "sensor.bias_walk": {"std": [5e-5, 2e-4]}})
    rt = math.sqrt(TS)
    assert c["b"]["N"]["interval"] == pytest.approx([0.02 * rt, 0.04 * rt], rel=1e-15)
    assert c["a"]["N"]["interval"] is None          # the diagnosis profiles the largest output's value
    assert c["a"]["K"]["interval"] == c["b"]["K"]["interval"] == [5e-5, 2e-4]   # one value for both outputs


# -- export --kalibr -----------------------------------------------------------------------------------
def read_yaml(path):
    return YAML(typ="safe").load(path.read_text())


def test_export_kalibr_round_trip_of_the_imu_scenario(tmp_path, capsys):
    out = tmp_path / "sub" / "imu.yaml"
    assert main(["export", "imu", "--kalibr", str(out), "--rostopic", "/imu0"]) == 0
    assert "wrote" in capsys.readouterr().out
    y = read_yaml(out)
    assert set(y) == {"gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
                      "accelerometer_random_walk", "update_rate", "rostopic"}
    q_g, q_a = 0.04 * math.pi / 180, 9.80665 / 1200        # one LSB of the ADIS16448
    assert y["gyroscope_noise_density"] == pytest.approx(math.hypot(1.6968e-4, q_g * math.sqrt(TS / 12)), rel=1e-12)
    assert y["accelerometer_noise_density"] == pytest.approx(math.hypot(2.0e-3, q_a * math.sqrt(TS / 12)), rel=1e-12)
    assert y["gyroscope_random_walk"] == 1.9393e-5 and y["accelerometer_random_walk"] == 3.0e-3
    assert y["update_rate"] == 200.0 and y["rostopic"] == "/imu0"
    assert not list(tmp_path.rglob("*.partial"))
    # YAML 1.1 (PyYAML, which Kalibr uses) reads a float only with a '.' and a signed exponent
    yaml11_float = re.compile(r"^[-+]?([0-9][0-9_]*)?\.[0-9.]*([eE][-+][0-9]+)?$")
    for line in out.read_text().splitlines():
        if line and not line.startswith("#") and "rostopic" not in line:
            assert yaml11_float.match(line.split(":")[1].split("#")[0].strip()), line
    assert yaml_float(1e-5) == "1.0e-05" and float(yaml_float(1.9393e-05)) == 1.9393e-05


def test_export_takes_the_largest_axis_converts_units_and_obeys_names(tmp_path, capsys):
    f = tmp_path / "m.toml"
    f.write_text(sensor_model(
        "[sensor.white]\ndensity = [0.01, 0.02, 0.001, 0.003]\n[sensor.bias_walk]\nstd = [0.001, 0.004, 1e-4, 2e-4]\n",
        names=("rate_a", "rate_b", "acc_a", "acc_b"), units=("deg/s", "deg/s", "g", "g")))
    out = tmp_path / "k.yaml"
    assert main(["export", str(f), "--kalibr", str(out), "--gyro", "rate_a,rate_b", "--accel", "acc_a, acc_b"]) == 0
    y = read_yaml(out)
    rad = math.pi / 180
    assert y["gyroscope_noise_density"] == pytest.approx(0.02 * rad, rel=1e-14)
    assert y["gyroscope_random_walk"] == pytest.approx(0.004 * rad, rel=1e-14)
    assert y["accelerometer_noise_density"] == pytest.approx(0.003 * 9.80665, rel=1e-14)
    assert y["accelerometer_random_walk"] == pytest.approx(2e-4 * 9.80665, rel=1e-14)
    # an existing file is replaced only with --force
    assert main(["export", str(f), "--kalibr", str(out), "--gyro", "rate_a", "--accel", "acc_a"]) == 2
    assert "already exists (use --force" in error_line(capsys)
    assert read_yaml(out)["gyroscope_noise_density"] == pytest.approx(0.02 * rad, rel=1e-14)
    assert main(["export", str(f), "--kalibr", str(out), "--gyro", "rate_a", "--accel", "acc_a", "--force"]) == 0
    assert read_yaml(out)["gyroscope_noise_density"] == pytest.approx(0.01 * rad, rel=1e-14)


@pytest.mark.parametrize("model, args, what", [
    ("imu-nominal", [], "missing gyroscope_random_walk"),
    ("seed", [], "no gyroscope outputs"),
    ("imu", ["--gyro", "gyro_x,nope"], "'nope' is not an output"),
    ("imu", ["--gyro", "gyro_x,"], "expected comma-separated output names"),
    ("imu", ["--gyro", "gyro_x", "--accel", "gyro_x,accel_x"], "both gyroscope and accelerometer"),
    ("imu", ["--rostopic", "imu 0"], "--rostopic"),
    ("UNITS", [], "is in 'V'"),
    ("NOWHITE", [], "missing gyroscope_noise_density"),
])
def test_export_refusals_are_one_line(tmp_path, capsys, model, args, what):
    if model == "UNITS":
        model = tmp_path / "u.toml"
        model.write_text(sensor_model("[sensor.white]\nstd = 1.0\n[sensor.bias_walk]\nstd = 1.0\n",
                                      names=("gyro_x", "accel_x"), units=("V", "m/s^2")))
    elif model == "NOWHITE":
        model = tmp_path / "w.toml"
        model.write_text(sensor_model("[sensor.bias_walk]\nstd = 1.0\n", names=("gyro_x", "accel_x"),
                                      units=("rad/s", "m/s^2")))
    out = tmp_path / "x.yaml"
    assert main(["export", str(model), "--kalibr", str(out), *args]) == 2
    assert what in error_line(capsys)
    assert not out.exists() and not list(tmp_path.glob("*.partial"))


def test_export_to_a_directory_is_refused(tmp_path, capsys):
    assert main(["export", "imu", "--kalibr", str(tmp_path)]) == 2
    assert "is a directory" in error_line(capsys)


# -- the scenarios -------------------------------------------------------------------------------------
def test_imu_scenarios_hold_the_published_numbers():
    imu, nominal = load_model("imu"), load_model("imu-nominal")
    for m in (imu, nominal):
        assert m.Ts == TS and m.output_units == ("rad/s",) * 3 + ("m/s^2",) * 3
        c = model_coefficients(m)
        assert [c[f"gyro_{a}"]["N"]["value"] for a in "xyz"] == [1.6968e-4] * 3
        assert [c[f"accel_{a}"]["N"]["value"] for a in "xyz"] == [2.0e-3] * 3
    c = model_coefficients(imu)
    assert c["gyro_y"]["K"]["value"] == 1.9393e-5 and c["accel_z"]["K"]["value"] == 3.0e-3
    assert c["gyro_x"]["q"]["value"] == pytest.approx(0.04 * math.pi / 180, rel=1e-15)
    assert c["accel_x"]["q"]["value"] == pytest.approx(9.80665 / 1200, rel=1e-15)
    assert set(nominal.effects) == {"sensor.white"}
    # at rest: gravity on accel_z alone
    rec = imu.simulate(400, seed=2)
    y = rec.y.reshape(400, 6)
    assert abs(np.mean(y[:, 5]) - 9.80665) < 0.01 and np.all(np.abs(np.mean(y[:, :5], axis=0)) < 0.01)


# -- diagnose --json: the fitted model's coefficients ---------------------------------------------------
@pytest.mark.slow
def test_diagnose_json_gives_the_fitted_coefficients(tmp_path, capsys):
    """A gyro axis at rest with the ADIS16448's N and K (EuRoC), 600 s at 200 Hz, diagnosed against a
    model whose white density is 1.5x too high and that has no bias walk: the white noise is refitted
    (its N within the estimator's spread of the truth, and still spelled as a density in the fitted
    file) and the bias walk found, its K's 95 % interval covering the truth."""
    n_true, k_true = 1.6968e-4, 1.9393e-5
    truth = tmp_path / "truth.toml"
    truth.write_text(sensor_model(f"[sensor.white]\ndensity = {n_true}\n[sensor.bias_walk]\nstd = {k_true}\n"))
    nominal = tmp_path / "nominal.toml"
    nominal.write_text(sensor_model(f"[sensor.white]\ndensity = {1.5 * n_true}\n"))
    rec = tmp_path / "gyro.mcap"
    assert main(["simulate", str(truth), "--duration", "600", "--seed", "3", "--out", str(rec)]) == 0
    capsys.readouterr()
    fitted = tmp_path / "fitted.toml"
    assert main(["diagnose", str(rec), "--model", str(nominal), "--json", "--fit-out", str(fitted)]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert {m["effect"] for m in rep["missing"]} == {"sensor.white", "sensor.bias_walk"}
    c = rep["coefficients"]["gyro_x"]
    n_samples = rep["samples"]
    # the white density's estimator: relative sd about 1 / sqrt(2 n) (a variance from n samples)
    assert c["N"]["value"] == pytest.approx(n_true, rel=5.0 / math.sqrt(2 * n_samples))
    assert c["N"]["unit"] == "rad/s/sqrt(Hz)" and c["N"]["interval"][0] < c["N"]["value"] < c["N"]["interval"][1]
    assert c["K"]["interval"][0] <= k_true <= c["K"]["interval"][1]
    assert c["K"]["unit"] == "rad/s/sqrt(s)"
    text = fitted.read_text()
    assert re.search(r"^density = ", text, re.MULTILINE) and "[sensor.bias_walk]" in text
    assert parse_model(text, "fitted").effects["sensor.white"].param_dict()["density"] == pytest.approx(c["N"]["value"])
    # the text report lists them
    assert main(["diagnose", str(rec), "--model", str(nominal)]) == 0
    out = capsys.readouterr().out
    assert "IEEE Std 952 coefficients of the fitted model" in out
    assert re.search(r"gyro_x: .*N = [0-9.e-]+ \[[0-9.e-]+, [0-9.e-]+\] rad/s/sqrt\(Hz\)", out)


def test_a_quantization_step_found_per_output_is_each_outputs_own():
    """The diagnosis finds a quantization step exactly on the data's grid and reports the range of
    the outputs' steps as its "interval" ([min, max]); each output's coefficient is its own step,
    not that range (which for an IMU spans [gyro step, accel step])."""
    m = parse_model(sensor_model("[sensor.quantization]\nstep = [0.001, 0.01]\n", names=("a", "b"), units=("V", "V")),
                    "q")
    c = model_coefficients(m, {"sensor.quantization": {"step": [0.001, 0.01]}})
    assert c["a"]["q"]["interval"] == [0.001, 0.001] and c["b"]["q"]["interval"] == [0.01, 0.01]
    rt = math.sqrt(TS / 12)
    assert c["b"]["N_q"]["interval"] == pytest.approx([0.01 * rt, 0.01 * rt], rel=1e-15)
