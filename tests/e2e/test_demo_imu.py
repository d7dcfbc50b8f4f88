"""`noiselab demo imu` end to end: real processes, Zenoh on 127.0.0.1, a real MCAP file, real .rrd.

The IMU story on a short run (120 s of samples at 200 Hz, 20x real time): the recording equals
the batch simulation of the `imu` scenario with the same seed; the diagnosis against
`imu-nominal` finds the data sheet's quantization on every axis, exactly; the white density it
reports is the published N of each axis within the estimator's spread; Kalibr's imu.yaml written
from the fitted model reads back with the same numbers the summary gives.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
from helpers.once import run_once
from helpers.readme import ROOT

from noiselab.model import load_model
from noiselab.recordings.load import load_noiselab

pytestmark = pytest.mark.slow   # live end-to-end runs: real processes and sessions

DURATION, SPEED, SEED = 120.0, 20.0, 4


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    def make(d):
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        res = subprocess.run([sys.executable, "-m", "noiselab.cli", "demo", "imu", "--duration", str(DURATION),
                              "--speed", str(SPEED), "--seed", str(SEED), "--out", str(d / "out"), "--json"],
                             capture_output=True, text=True, env=env, timeout=900)
        return {"returncode": res.returncode, "stdout": res.stdout, "stderr": res.stderr}

    d, run = run_once(tmp_path_factory, "demo-imu", make)
    assert run["returncode"] == 0, run["stderr"][-2000:]
    return d / "out", json.loads(run["stdout"])


def test_demo_imu_recording_is_the_scenarios_sample_path(demo):
    out, s = demo
    n = round(DURATION / 0.005)
    topics = s["live"]["recorder"]["topics"]
    b = topics["noiselab/imu/measurement"]
    assert b["count"] == n and not b["gaps"], b
    series = load_noiselab(s["recording"], truth=False, Ts=0.005)
    rec = load_model("imu").simulate(n, seed=SEED)
    np.testing.assert_array_equal(series.y, np.asarray(rec.y).reshape(n, -1))
    for name in ("demo-imu.mcap", "demo-imu-diagnosis.rrd", "demo-imu-diagnosis.png", "demo-imu-fitted.toml",
                 "demo-imu-kalibr.yaml", "demo-imu-summary.json"):
        assert (out / name).stat().st_size > 0, name


def test_demo_imu_finds_the_quantization_and_keeps_n(demo):
    _, s = demo
    d = s["diagnosis"]
    found = {m["effect"]: m for m in d["missing"]}
    assert "sensor.quantization" in found, d["missing"]
    truth = load_model("imu")
    steps = np.asarray(found["sensor.quantization"]["params"]["step"], float)
    np.testing.assert_allclose(steps, truth.effects["sensor.quantization"].param_dict()["step"], rtol=1e-9)
    assert d["error_after"] < d["error_before"]
    # N per axis: the white density the fitted model holds, against the published one. If the
    # diagnosis refits the white noise, its std comes from 24000 samples per axis: sd of a
    # variance estimate sqrt(2/n), of N half that, 0.46 %; 5 sd = 2.3 %.
    for name, coefs in d["coefficients"].items():
        j = truth.output_names.index(name)
        n_true = truth.effects["sensor.white"].coefficients()[0].value
        n_true = float(np.broadcast_to(n_true, (truth.p,))[j])
        assert coefs["N"]["value"] == pytest.approx(n_true, rel=5 * 0.5 * math.sqrt(2 / 24000)), name
        assert coefs["N"]["unit"] == f"{truth.output_units[j]}/sqrt(Hz)"


def test_demo_imu_kalibr_yaml_reads_back(demo):
    out, s = demo
    text = (out / "demo-imu-kalibr.yaml").read_text()
    values = {}
    for line in text.splitlines():
        line = line.split("#")[0].strip()
        if ":" in line:
            k, v = line.split(":", 1)
            values[k.strip()] = v.strip()
    fitted = s["kalibr"]["fitted"]
    for k in ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
              "accelerometer_random_walk", "update_rate"):
        assert float(values[k]) == fitted[k], k
    assert values["rostopic"] == "'/imu0'"
    # the published densities with the quantization's white part added (export's documented rule)
    true = s["kalibr"]["true"]
    assert true["gyroscope_noise_density"] == pytest.approx(math.hypot(1.6968e-4, 6.981317007977318e-4 *
                                                                      math.sqrt(0.005 / 12)), rel=1e-9)
