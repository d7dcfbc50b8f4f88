"""``noiselab allan``: the Allan table and the IEEE 952 slope readings, through the command line on
recordings written by ``noiselab simulate`` (and a foreign JSON MCAP of real OCXO data).

Tolerances of the readings come from the estimator: each reading's interval is one sigma
(conf 0.683) of the fitted line's offset, bounded as for fully correlated octaves
(:func:`noiselab.stats.ieee952.ieee952_readings`), so a right value lies within 3 of those sigmas.
"""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
from helpers.allan_reference import BOUNDS_RTOL, half_unit, ocxo_y, read_stable32
from helpers.cli import assert_bad, cli_in_process
from helpers.recordings import raw_json_mcap

from noiselab.cli import main
from noiselab.recordings.load import load_noiselab
from noiselab.stats import StatsError
from noiselab.stats.allan import oadev, oadev_from_phase

TS = 0.01
N_WHITE = 2e-3          # rad/s/sqrt(Hz): sensor.white std = N / sqrt(Ts) = 0.02 rad/s
N_WALK, K_WALK = 1e-3, 1e-3   # std 0.01 rad/s; bias walk 1e-3 rad/s/sqrt(s) (crossover sqrt(3) N/K = 1.7 s)


def gyro_toml(white_std: float, walk_std: float | None, p: int = 1) -> str:
    """A gyro at rest: a sensor-only model (no [plant]), p axes."""
    names = ", ".join(f'"gyro_{c}"' for c in "xyz"[:p])
    units = ", ".join('"rad/s"' for _ in range(p))
    walk = "" if walk_std is None else f"[sensor.bias_walk]\nstd = {walk_std!r}\n"
    return (f'name = "gyro"\n[sampling]\nTs = {TS!r}\n[outputs]\nnames = [{names}]\nunits = [{units}]\n'
            f'[command]\nkind = "none"\n[sensor.white]\nstd = {white_std!r}\n{walk}')






def run(capsys, *argv) -> tuple[int, str, str]:
    """``noiselab allan ARGV`` in this process."""
    return cli_in_process(capsys, "allan", *argv)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """Two simulated gyros at rest (seed fixed): white noise only, and white noise plus a bias walk."""
    d = tmp_path_factory.mktemp("allan")
    out = {}
    for name, white, walk, seconds in (("white", N_WHITE / math.sqrt(TS), None, 600),
                                       ("walk", N_WALK / math.sqrt(TS), K_WALK, 2000)):
        model = d / f"{name}.toml"
        model.write_text(gyro_toml(white, walk))
        rec = d / f"{name}.mcap"
        assert main(["simulate", str(model), "--duration", str(seconds), "--seed", "7", "--out", str(rec)]) == 0
        out[name] = (rec, model)
    return out


def sigma(reading) -> float:
    """The reading's one-sigma sd of ln(value), from its interval (z = 1.0 at conf 0.683)."""
    z = 1.0003  # norm.ppf(0.8415)
    return math.log(reading["interval"][1] / reading["value"]) / z


def test_white_noise_reads_its_density_and_nothing_else(recordings, capsys):
    rec, model = recordings["white"]
    code, out, err = run(capsys, rec, "--model", model, "--json")
    assert code == 0, err
    rep = json.loads(out)
    o = rep["outputs"]["gyro_x"]
    assert rep["Ts"] == TS and rep["samples"] == 60_000 and o["unit"] == "rad/s"
    # the table is the overlapping ADEV of the recorded series at octave taus up to N/4
    series = load_noiselab(str(rec), Ts=TS)
    ref = oadev(series.y[:, 0], 1 / TS, taus="octave")
    assert o["m"] == [2**k for k in range(14)] and o["tau"] == ref.taus.tolist()
    assert o["adev"] == ref.dev.tolist() and o["interval"] == [[a, b] for a, b in zip(ref.lo.tolist(), ref.hi.tolist())]
    assert set(o["noise_type"]) == {"white FM"}
    n = o["readings"]["N"]
    assert n["unit"] == "rad/s/sqrt(Hz)" and n["tau_range"] == [o["tau"][0], o["tau"][-1]]
    assert abs(math.log(n["value"] / N_WHITE)) < 3 * sigma(n), n
    assert sigma(n) < 0.01                                # 60,000 samples: N to about 0.5 %
    for key in ("K", "B"):
        assert o["readings"][key]["value"] is None and o["readings"][key]["reason"], o["readings"][key]
    assert "random walk FM" in o["readings"]["K"]["reason"]
    # the model's curve: white noise of variance std^2 has AVAR = std^2 / m exactly
    np.testing.assert_allclose(o["model_adev"], N_WHITE / np.sqrt(TS * np.array(o["m"])), rtol=1e-9)


def test_bias_walk_reads_K_beside_N(recordings, capsys):
    rec, model = recordings["walk"]
    code, out, err = run(capsys, rec, "--model", model, "--json")
    assert code == 0, err
    o = json.loads(out)["outputs"]["gyro_x"]
    k, n, b = o["readings"]["K"], o["readings"]["N"], o["readings"]["B"]
    assert k["unit"] == "rad/s/sqrt(s)" and k["tau_range"][0] > 1.7            # past the crossover
    assert abs(math.log(k["value"] / K_WALK)) < 3 * sigma(k), k
    assert abs(math.log(n["value"] / N_WALK)) < 3 * sigma(n), n
    assert n["tau_range"][1] < 1.7
    # the minimum between the two lines turns up: read as the floor, at the crossover
    assert b["value"] is not None and 0.5 < b["tau_range"][0] <= b["tau_range"][1] < 6
    m = np.array(o["m"], float)
    q = K_WALK**2 * TS                              # walk increment variance per sample
    avar = (N_WALK**2 / TS) / m + q * (2 * m**2 + 1) / (6 * m)   # predict.py's discrete forms
    np.testing.assert_allclose(o["model_adev"], np.sqrt(avar), rtol=1e-9)


def test_table_on_stdout_names_units_and_model(recordings, capsys):
    rec, model = recordings["walk"]
    code, out, err = run(capsys, rec, "--model", model)
    assert code == 0, err
    lines = out.splitlines()
    assert "gyro_x [rad/s]" in lines
    head = next(i for i, ln in enumerate(lines) if ln.lstrip().startswith("tau [s]"))
    assert "model ADEV" in lines[head] and "noise type" in lines[head]
    rows = lines[head + 1: head + 17]
    assert len({len(r) for r in rows}) == 1, rows                 # columns aligned
    assert any(ln.startswith("  N = ") and "rad/s/sqrt(Hz)" in ln and "model 1.0000e-03" in ln for ln in lines)
    assert any(ln.startswith("  K = ") and "rad/s/sqrt(s)" in ln for ln in lines)
    # without a model: the data alone, named by the recording
    code, out, err = run(capsys, rec)
    assert code == 0 and "y0 [units]" in out.splitlines() and "model ADEV" not in out


def test_csv_and_png_need_force_to_overwrite(recordings, capsys, tmp_path):
    rec, model = recordings["white"]
    csv_path, png = tmp_path / "t.csv", tmp_path / "sub" / "a.png"
    code, _, err = run(capsys, rec, "--model", model, "--csv", csv_path, "--png", png)
    assert code == 0, err
    rows = list(csv.DictReader(csv_path.open()))
    assert len(rows) == 14 and rows[0]["output"] == "gyro_x" and rows[0]["unit"] == "rad/s"
    assert float(rows[3]["tau_s"]) == 0.08 and rows[3]["noise_type"] == "white FM" and float(rows[3]["model_adev"]) > 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    before = csv_path.read_bytes(), png.read_bytes()
    assert_bad(run(capsys, rec, "--csv", csv_path), str(csv_path), "already exists", "--force")
    assert_bad(run(capsys, rec, "--png", png), str(png), "already exists")
    assert (csv_path.read_bytes(), png.read_bytes()) == before               # nothing lost
    code, _, err = run(capsys, rec, "--csv", csv_path, "--png", png, "--force")
    assert code == 0, err
    assert csv_path.read_bytes() != before[0] and "model_adev" in csv_path.read_text().splitlines()[0]
    assert not list(tmp_path.rglob("*.partial"))


def test_png_shows_the_lines(recordings, capsys, tmp_path):
    """The figure is drawn from the report: one panel, the band, the data, the model and the
    lines read (legend entries name N and K with their values)."""
    from noiselab.viewers.allan_png import allan_figure

    rec, model = recordings["walk"]
    code, out, err = run(capsys, rec, "--model", model, "--json")
    assert code == 0, err
    fig = allan_figure(json.loads(out))
    (ax,) = fig.axes
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any(lb.startswith("model") for lb in labels)
    for key in ("N", "K", "B"):
        assert any(f"{key} = " in lb for lb in labels), labels
    assert ax.get_xscale() == "log" and ax.get_yscale() == "log" and ax.get_ylabel() == "Allan deviation [rad/s]"


def test_ocxo_matches_stable32(tmp_path, capsys):
    """Real OCXO data (tests/data/ocxo, Stable32 1.60 tables) as a foreign JSON recording: the
    command's table is the validated estimator's (test_stats_allan) on the exact fractional
    frequency: ADEV at the octave taus the all-tau table holds to its printed digits, the noise
    type of every octave tau as Stable32 identified it, the interval's width as Stable32's."""
    y = ocxo_y()
    path = tmp_path / "ocxo.mcap"
    raw_json_mcap(path, "/ocxo", [(k * 1_000_000_000, json.dumps({"y": float(v)}).encode()) for k, v in enumerate(y)])
    code, out, err = run(capsys, path, "--measurement", "/ocxo:y", "--json")
    assert code == 0, err
    rep = json.loads(out)
    assert rep["Ts"] == 1.0 and rep["samples"] == y.size
    o = rep["outputs"]["y"]
    assert o["unit"] == "y"                                    # no model: the field stands for the unit
    octave = read_stable32("oadev_octave.txt")
    assert o["m"] == octave["m"].tolist()
    assert o["alpha"] == octave["alpha"].tolist()
    assert o["noise_type"][:5] == ["flicker PM", "flicker PM", "white FM", "flicker PM", "random walk FM"]
    every = read_stable32("stable32_oadev_alltau.txt")
    dev = np.array(o["adev"])
    for i, m in enumerate(o["m"]):
        at = np.flatnonzero(every["m"] == m)
        if at.size:
            assert abs(dev[i] - every["dev"][at[0]]) <= half_unit(every["dev"][at[0]], 5) * (1 + 1e-9), m
    lo, hi = np.array(o["interval"]).T
    np.testing.assert_allclose(lo / dev, octave["lo"] / octave["dev"], rtol=BOUNDS_RTOL)
    np.testing.assert_allclose(hi / dev, octave["hi"] / octave["dev"], rtol=BOUNDS_RTOL)
    # the flicker FM floor Stable32 identifies at 128-256 s (and 1024 s) holds the minimum
    b = o["readings"]["B"]
    assert b["tau_range"][0] <= 128 <= b["tau_range"][1] and b["value"] == pytest.approx(min(o["adev"]) / 0.6643, rel=1e-3)


@pytest.fixture(scope="module")
def foreign(tmp_path_factory):
    d = tmp_path_factory.mktemp("foreign")
    rng = np.random.default_rng(3)
    path = d / "imu.mcap"
    raw_json_mcap(path, "/imu", [(k * 10_000_000, json.dumps({"angular_velocity": {"x": float(v), "y": 0.0},
                                                                "header": {"stamp": "now"}}).encode())
                                  for k, v in enumerate(rng.standard_normal(400))])
    return path


def test_foreign_recording_vector_and_time(foreign, capsys):
    code, out, err = run(capsys, foreign, "--measurement", "/imu:angular_velocity.x,angular_velocity.y", "--json")
    assert code == 0, err
    rep = json.loads(out)
    assert rep["Ts"] == pytest.approx(0.01, rel=1e-12)
    assert list(rep["outputs"]) == ["angular_velocity.x", "angular_velocity.y"]
    # a constant output: every deviation 0, nothing to read, no error
    yo = rep["outputs"]["angular_velocity.y"]
    assert yo["adev"] == [0.0] * len(yo["adev"])
    assert all(yo["readings"][k]["value"] is None and "constant" in yo["readings"][k]["reason"] for k in "NKB")


@pytest.mark.parametrize("argv, words", [
    (["{rec}x", "--model", "{model}"], ["No such file", "white.mcapx"]),
    (["{dir}"], ["is a directory"]),
    (["{foreign}", "--measurement", "imu.angular_velocity.x"], ["expected TOPIC:FIELD"]),
    (["{foreign}", "--measurement", "/gyro:angular_velocity.x"], ["no topic", "/gyro"]),
    (["{foreign}", "--measurement", "/imu:angular_velocity.w"], ["angular_velocity.w", "not found"]),
    (["{foreign}", "--measurement", "/imu:angular_velocity.x", "--time", "header.stamp"], ["header.stamp", "not a number"]),
    (["{foreign}", "--measurement", "/imu:angular_velocity.x", "--model", "{model}", "--device", "d"], ["--device"]),
    (["{rec}", "--time", "t"], ["--time", "foreign"]),
    (["{rec}", "--model", "{model2}"], ["2 output(s)", "recording 1"]),
    (["{rec}", "--model", "{model_ts}"], ["median sample step", "Ts is 0.02"]),
    (["{rec}", "--model", "nonexistent.toml"], ["nonexistent.toml"]),
    (["{rec}", "--csv", "{dir}"], ["is a directory"]),
    (["{rec}", "--csv", "{out}", "--png", "{out}"], ["same file"]),
    (["{rec}", "--json", "--csv", "{out}"], ["not allowed with"]),
    (["{rec}", "--device", "other"], ["device 'other'"]),
])
def test_bad_input_is_one_line_exit_2(recordings, foreign, tmp_path, capsys, argv, words):
    rec, model = recordings["white"]
    model2 = tmp_path / "two.toml"
    model2.write_text(gyro_toml(0.02, None, p=2))
    model_ts = tmp_path / "ts.toml"
    model_ts.write_text(gyro_toml(0.02, None).replace(f"Ts = {TS!r}", "Ts = 0.02"))
    subs = {"rec": rec, "model": model, "model2": model2, "model_ts": model_ts, "dir": tmp_path, "foreign": foreign,
            "out": tmp_path / "o.csv"}
    args = [a.format(**subs) for a in argv]
    if "--json" in args and "--csv" in args:           # argparse's own usage error: SystemExit(2)
        with pytest.raises(SystemExit) as e:
            main(["allan", *args])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and all(w in err for w in words), err
        return
    assert_bad(run(capsys, *args), *words)


def test_a_recording_too_short_for_a_tau(tmp_path, capsys):
    """Three samples give the one tau they can (m = 1: two adjacent means and the Greenhall edf
    of 4 phase points); two are refused in one line saying so, not by the edf's inner check."""
    for n in (3, 2):
        path = tmp_path / f"n{n}.mcap"
        raw_json_mcap(path, "/s", [(k * 1_000_000, json.dumps({"v": float(k % 2)}).encode()) for k in range(n)])
        result = run(capsys, path, "--measurement", "/s:v", "--json")
        if n == 3:
            assert result[0] == 0, result[2]
            assert json.loads(result[1])["outputs"]["v"]["m"] == [1]
        else:
            assert_bad(result, str(path), "v:", "at least 3 samples, found 2")
    with pytest.raises(StatsError, match="at least 4"):
        oadev_from_phase([0.0, 1.0, 0.0], 1.0)


def test_imu_scenario_reads_its_published_densities(tmp_path, capsys):
    """The imu-nominal scenario (six axes, 200 Hz, EuRoC's ADIS16448 densities): N of every axis
    within 3 of its sigmas of the model's own, named and in the units of its [outputs]. Its
    command (gravity on accel_z from t = 0) is a constant: no note about a moving mean."""
    rec = tmp_path / "imu.mcap"
    assert main(["simulate", "imu-nominal", "--duration", "300", "--seed", "11", "--out", str(rec)]) == 0
    capsys.readouterr()
    code, out, err = run(capsys, rec, "--model", "imu-nominal", "--json")
    assert code == 0, err
    rep = json.loads(out)
    assert list(rep["outputs"]) == ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
    assert not any("mean response" in note for note in rep["notes"]), rep["notes"]
    for name, o in rep["outputs"].items():
        n, model_n = o["readings"]["N"], o["model_coefficients"]["N"]
        density = 1.6968e-4 if name.startswith("gyro") else 2.0e-3
        assert model_n["value"] == pytest.approx(density, rel=1e-12)
        assert n["unit"] == model_n["unit"] == ("rad/s/sqrt(Hz)" if name.startswith("gyro") else "m/s^2/sqrt(Hz)")
        assert abs(math.log(n["value"] / density)) < 3 * sigma(n), (name, n)


def test_a_moving_mean_is_noted(tmp_path, capsys):
    """The seed model's sine command moves its output: the data's deviation holds the sine, the
    model's curve only the noise, and a note says so."""
    rec = tmp_path / "seed.mcap"
    assert main(["simulate", "seed", "--duration", "60", "--out", str(rec)]) == 0
    capsys.readouterr()
    code, out, err = run(capsys, rec, "--model", "seed", "--json")
    assert code == 0, err
    notes = json.loads(out)["notes"]
    assert any("mean response ([command] sine) moves position" in note for note in notes), notes


def test_ros2_bag(tmp_path, capsys):
    """A rosbag2 bag of sensor_msgs/Imu (the emulator's own ROS 2 writer), read through the one
    loader: the bag directory, the six axes by two '.*' paths, time from header.stamp."""
    from noiselab.model import load_model
    from noiselab.recordings import rosbag_in
    from noiselab.recordings.simulated import write_simulation

    bag = tmp_path / "imu_bag"
    write_simulation(load_model("imu-nominal"), 20_000, 5, bag, fmt="ros2")
    with rosbag_in.open_bag(str(bag)) as reader:
        (topic,) = [t for t, msgtype in rosbag_in.topics(reader).items() if msgtype == "sensor_msgs/msg/Imu"]
    spec = f"{topic}:angular_velocity.*,linear_acceleration.*"
    code, out, err = run(capsys, bag, "--measurement", spec, "--model", "imu-nominal", "--json")
    assert code == 0, err
    rep = json.loads(out)
    assert rep["samples"] == 20_000 and rep["Ts"] == 0.005
    for name, o in rep["outputs"].items():
        n = o["readings"]["N"]
        assert abs(math.log(n["value"] / o["model_coefficients"]["N"]["value"])) < 3 * sigma(n), (name, n)
    # without a model: the fields name the outputs, the step of the stamps is Ts
    code, out, err = run(capsys, bag, "--measurement", f"{topic}:angular_velocity.z", "--json")
    assert code == 0, err
    rep = json.loads(out)
    assert list(rep["outputs"]) == ["angular_velocity.z"] and rep["Ts"] == pytest.approx(0.005, rel=1e-9)
    # ... in the unit the message type fixes (REP 103: an Imu's angular velocity is in rad/s)
    o = rep["outputs"]["angular_velocity.z"]
    assert o["unit"] == "rad/s" and o["readings"]["N"]["unit"] == "rad/s/sqrt(Hz)"
