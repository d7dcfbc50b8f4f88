"""`noiselab predict --json` and `noiselab simulate` against the contracts of DESIGN.md."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from noiselab import wire
from noiselab.cli import main
from noiselab.model import load_model
from noiselab.recordings.reader import read_recording

ROOT = Path(__file__).resolve().parents[2]


def test_predict_json_fields_and_values(capsys):
    assert main(["predict", "seed", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["P"][0][0] == pytest.approx(1.4341e-3, rel=5e-5)
    assert rep["var_y"][0] == pytest.approx(sum(v[0] for v in rep["contributions"].values()), rel=1e-12)
    assert rep["bias_var_rate"] == [pytest.approx(0.002**2)]
    assert set(rep["contributions"]) == {"actuator.ar1", "process.white", "sensor.white", "sensor.quantization"}
    assert rep["contributions"]["sensor.quantization"][0] == pytest.approx(0.001**2 / 12)
    assert main(["predict", "seed-nominal", "--json"]) == 0
    nominal = json.loads(capsys.readouterr().out)
    assert nominal["P"][0][0] == pytest.approx(1.8711e-4, rel=5e-5)
    assert nominal["bias_var_rate"] == [0.0]


def test_predict_json_unstable_plant_gives_null_P(tmp_path, capsys):
    f = tmp_path / "unstable.toml"
    f.write_text('name = "u"\n[sampling]\nTs = 0.01\n[plant]\nA = [[0.1]]\nB = [[1.0]]\nC = [[1.0]]\n'
                 "[process.white]\nstd = 0.1\n[sensor.white]\nstd = 0.2\n")
    assert main(["predict", str(f), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["P"] is None and rep["var_y"] is None and rep["stable"] is False
    assert rep["contributions"]["process.white"] is None
    assert rep["contributions"]["sensor.white"] == [pytest.approx(0.04)]


def test_predict_modifiers_report_the_change_they_cause(capsys):
    """A lag filters the actuator noise: its entry is the (negative) change of var_y."""
    f = ROOT / "service" / "scenarios" / "seed-nominal.toml"
    text = f.read_text() + "\n[actuator.lag]\ntau_s = 0.5\n"
    mdl = load_model("seed-nominal")
    from noiselab.commands.predict import predict_report
    from noiselab.model import parse_model
    rep = predict_report(parse_model(text, "lagged"))
    base = mdl.predictor().steady_state().var_y[0]
    assert rep["modifiers"]["actuator.lag"][0] == pytest.approx(rep["var_y"][0] - base, rel=1e-9)
    assert rep["modifiers"]["actuator.lag"][0] < 0


def test_simulate_writes_the_wire_contract(tmp_path, capsys):
    out = tmp_path / "seed.mcap"
    assert main(["simulate", "seed", "--duration", "3", "--seed", "5", "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["samples"] == 300
    rec = read_recording(out)
    assert rec.complete
    dev = rec.device("seed")
    batch = load_model("seed").simulate(300, seed=5)
    Ts_ns = wire.period_ns(0.01)
    meta = rec.metadata["noiselab"]
    start = int(meta["start_time_ns"])          # the run's wall-clock start (DESIGN.md wire contract)
    assert abs(start - summary["start_time_ns"]) == 0 and start > 1_600_000_000 * 10**9
    for kind, values in (("truth", batch.x), ("command", batch.u), ("measurement", batch.y)):
        td = getattr(dev, kind)
        assert td.topic == f"noiselab/seed/{kind}"
        np.testing.assert_array_equal(td.seq, np.arange(300))
        np.testing.assert_array_equal(td.values, values)          # JSON floats round-trip exactly
        np.testing.assert_array_equal(td.t, np.arange(300) * 0.01)
        np.testing.assert_array_equal(td.publish_ns - start, np.arange(300) * Ts_ns)
        np.testing.assert_array_equal(td.log_ns, td.publish_ns)        # one time base; offline, no receive time
        assert td.gaps() == []
    assert meta["seed"] == "5" and meta["model_name"] == "seed"
    assert load_model("seed").to_toml() == meta["model_toml"]
    with open(out, "rb") as fh:
        summary = make_reader(fh).get_summary()
    encodings = {s.encoding for s in summary.schemas.values()}
    assert encodings == {"jsonschema"}
    assert {c.message_encoding for c in summary.channels.values()} == {"json"}
    for s in summary.schemas.values():
        js = json.loads(s.data)
        assert set(js["required"]) >= {"seq", "t"}


@pytest.mark.slow
def test_simulate_refuses_existing_and_shows_progress(tmp_path):
    out = tmp_path / "x.mcap"
    out.write_bytes(b"precious")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-m", "noiselab.cli", "simulate", "seed", "--duration", "2",
                          "--out", str(out)], capture_output=True, text=True, env=env)
    assert res.returncode == 2 and out.read_bytes() == b"precious"
    assert res.stderr.count("\n") == 1 and "exists" in res.stderr
    res = subprocess.run([sys.executable, "-m", "noiselab.cli", "simulate", "seed", "--duration", "2",
                          "--out", str(out), "--force", "--progress"], capture_output=True, text=True, env=env)
    assert res.returncode == 0, res.stderr
    assert "100%" in res.stderr and "200/200" in res.stderr and "samples/s" in res.stderr
    assert read_recording(out).device("seed").measurement.seq.size == 200


def test_predict_json_integrating_plant_gives_its_walk_rate(capsys):
    """The motor scenario (a pole at 0): no steady state where the walk reaches y, its growth of
    Var(y) per second instead, (b / a)^2 sigma^2 Ts for a per-sample input noise sigma held over the
    sample; the effects that do not pass through the plant keep their variances."""
    assert main(["predict", "motor", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["P"] is None and rep["var_y"] is None and rep["stable"] is False
    assert rep["contributions"]["process.white"] is None
    assert rep["contributions"]["sensor.white"] == [pytest.approx(0.0005**2)]
    assert rep["walk_var_rate"] == [pytest.approx((8.0 / 4.0) ** 2 * 0.02**2 * 0.005, rel=1e-9)]
    assert any("integrates" in n for n in rep["notes"])
    assert main(["predict", "seed", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["walk_var_rate"] is None


def test_predict_json_angle_and_speed_of_a_motor_is_null_only_at_the_angle(capsys, tmp_path):
    """Per output: the angle (the walk reaches it) null, the speed its steady-state variance; the
    JSON stays JSON (no NaN token) and the text report prints null there."""
    text = (ROOT / "service" / "scenarios" / "motor.toml").read_text()
    f = tmp_path / "motor2.toml"
    f.write_text(text.replace("C = [[1.0, 0.0]]", "C = [[1.0, 0.0], [0.0, 1.0]]"))
    assert main(["predict", str(f), "--json"]) == 0
    out = capsys.readouterr().out
    assert "NaN" not in out
    rep = json.loads(out)
    assert rep["var_y"][0] is None and rep["var_y"][1] > 0 and rep["std_y"][0] is None
    assert rep["contributions"]["process.white"][0] is None
    assert rep["contributions"]["sensor.white"] == [pytest.approx(0.0005**2)] * 2
    assert rep["var_y"][1] == pytest.approx(sum(v[1] for v in rep["contributions"].values()), rel=1e-12)
    assert rep["walk_var_rate"] == [pytest.approx((8.0 / 4.0) ** 2 * 0.02**2 * 0.005, rel=1e-9), 0.0]
    assert main(["predict", str(f)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert any(ln.startswith("var_y (steady state)") and "null" in ln and "e-05" in ln for ln in lines)
