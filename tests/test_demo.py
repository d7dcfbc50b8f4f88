"""`noiselab demo` end to end: real processes, Zenoh on 127.0.0.1, a real MCAP file, real .rrd files.

The demo runs the seed lesson live (300 s of samples at 30x real time here; the README's command
uses the default 1200 s at 20x) and diagnoses it against ``seed-nominal``. Checked against theory:
the recording equals the batch simulation of the same seed; the lesson's check reproduces its
program's estimator; the diagnosis puts AR(1) actuator noise in place of the white one with the
true parameters inside its intervals; the model error falls to about 1.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import run_once
from service.diagnose.load import load_noiselab
from service.model import load_model, parse_model

ROOT = Path(__file__).resolve().parents[1]
DURATION, SPEED, SEED = 300.0, 30.0, 1


def cli(*args, cwd=None):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "service.cli", *map(str, args)], capture_output=True, text=True,
                          env=env, cwd=cwd, timeout=600)


def _run_demo(d: Path) -> dict:
    r = cli("demo", "--duration", DURATION, "--speed", SPEED, "--seed", SEED, "--out", d / "recordings", "--json")
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The demo (about 40 s), run once for the whole test run even when the tests here are spread
    over xdist's workers."""
    d, summary = run_once(tmp_path_factory, "demo", _run_demo)
    return d / "recordings", summary


def test_demo_recording_is_the_lesson_sample_path(demo):
    out, s = demo
    n = int(DURATION / 0.01)
    topics = s["live"]["recorder"]["topics"]
    for kind in ("truth", "command", "measurement"):
        b = topics[f"noiselab/seed/{kind}"]
        assert b["count"] == n and not b["gaps"] and not b["missing_at_start"], (kind, b)
    series = load_noiselab(s["recording"], truth=True, Ts=0.01)
    rec = load_model("seed").simulate(n, seed=SEED)
    np.testing.assert_array_equal(series.y, np.asarray(rec.y).reshape(n, -1))
    assert s["live"]["emulator"]["speed"] == SPEED


def test_demo_lesson_check_and_why(demo):
    out, s = demo
    ls = s["lesson_check"]
    # the lesson's estimator, recomputed: var(y) after 1000 samples of the first 6000, ddof 1
    series = load_noiselab(s["recording"], truth=False, Ts=0.01)
    y = series.y[:6000, 0]
    assert ls["empirical_var"] == pytest.approx(np.var(y[1000:], ddof=1), rel=1e-12)
    nominal = load_model("seed-nominal")
    cov = nominal.predictor().covariance(6000, series.u[:6000])
    assert ls["predicted_var"] == pytest.approx(np.mean(cov.Sy[1000:6000, 0]), rel=1e-12)
    assert ls["ratio"] > 4          # several times off (the lesson's run: about 7x)
    # the command response is a large part of var(y) and removing it leaves the ratio well above 1
    assert 0.2 < ls["command_response_var"] / ls["empirical_var"] < 0.6
    assert 2 < ls["residual_ratio"] < ls["ratio"]


def test_demo_diagnosis_finds_the_colored_actuator_noise(demo):
    out, s = demo
    d = s["diagnosis"]
    first = d["missing"][0]
    assert first["effect"] == "actuator.ar1" and first["mode"] == "replace:actuator.white"
    # the issue's criterion, within 30 % (the intervals' coverage is checked over many seeds by the
    # scenario-pair tests and bench_noise_density; on one record a 95 % interval misses 1 time in 20:
    # here std 0.089 [0.080, 0.101] against 0.08, rho 0.962 [0.943, 0.973] against 0.97, along the
    # std-rho ridge of equal low-frequency power)
    for k, true in (("std", 0.08), ("rho", 0.97)):
        lo, hi = first["interval"][k]
        assert lo < first["params"][k] < hi and abs(first["params"][k] / true - 1) < 0.3, (k, first)
    errs = [d["error_before"]] + [st["error"] for st in d["steps"]]
    assert errs[0] > 10 and all(b < a for a, b in zip(errs, errs[1:])) and d["error_after"] < 1.5, errs
    # the variance story: the nominal's prediction misses most of the residual, the fitted one does not
    v = s["variance"]
    assert v[0]["ratio"] > 3 and 0.7 < v[-1]["ratio"] < 1.5, v


def test_demo_files(demo):
    from rerun.chunk import RrdReader

    out, s = demo
    f = s["files"]
    fitted = parse_model(Path(f["fitted"]).read_text(), "fitted")
    assert "actuator.ar1" in fitted.effects and "actuator.white" not in fitted.effects
    for key in ("rrd", "live_rrd"):
        ents = {c.entity_path for c in RrdReader(f[key]).stream()}
        assert any("psd" in e for e in ents) and any("allan" in e for e in ents), (key, sorted(ents)[:20])
    for key in ("png", "live_png"):
        assert Path(f[key]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_demo_refuses_to_overwrite(demo):
    out, s = demo
    before = Path(s["recording"]).stat().st_size
    r = cli("demo", "--duration", 1, "--out", out)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "exists" in r.stderr, r.stderr
    assert Path(s["recording"]).stat().st_size == before
