"""Bad input on the command line, in model files and in recordings: one line on stderr naming what
is wrong and exit 2, never a traceback, and nothing already recorded lost (DESIGN.md "Exit codes").

1. Model files: the sample period's range (1 us to a day), the magnitude of every number (at most
   1e50), correlation times whose rho rounds to 1; the predictions of models inside those bounds
   (far nonlinearity kinks, the finest Ts) are finite; every built-in scenario still loads.
"""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from service.cli import main, predict_report
from service.model import dumps_toml, load_model, parse_model, scenario_names
from service.model.model import TS_MAX, TS_MIN, scenario_text
from service.model.predict import HORIZON_MAX

SEED = scenario_text("seed")


def edited(text: str, sets: dict, drops: tuple = ()) -> str:
    """``text`` with keys set (paths as tuples: ("sensor", "white", "std")) and tables dropped."""
    d = tomllib.loads(text)
    for path in drops:
        node = d
        for k in path[:-1]:
            node = node[k]
        del node[path[-1]]
    for path, value in sets.items():
        node = d
        for k in path[:-1]:
            node = node.setdefault(k, {})
        node[path[-1]] = value
    return dumps_toml(d)


def cli(capsys, *argv) -> tuple[int, str, str]:
    """``noiselab ARGV`` in this process: (exit code, stdout, stderr). argparse's own errors exit
    through SystemExit; anything else raised is a traceback and fails the test."""
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, err


def assert_bad(result, *parts: str) -> str:
    """Exit 2 and one line on stderr, ``noiselab: ...``, holding every one of ``parts``."""
    rc, out, err = result
    assert rc == 2, (rc, out, err[-3000:])
    lines = err.splitlines()
    assert len(lines) == 1 and err.endswith("\n") and lines[0].startswith("noiselab: "), err[-3000:]
    for part in parts:
        assert part in lines[0], (part, lines[0])
    return lines[0]


# -- 1. model files ---------------------------------------------------------------------------------
@pytest.mark.parametrize("Ts", [1e300, 1e-300, 86401.0, 9e-7])
def test_predict_refuses_a_sample_period_out_of_its_range(Ts, tmp_path, capsys):
    """Ts = 1e300 overflowed the mean response (OverflowError in lsim), Ts = 1e-300 asked numpy for
    a horizon of 6e301 samples (ValueError): both tracebacks; the range is 1 us to a day."""
    f = tmp_path / "ts.toml"
    f.write_text(edited(SEED, {("sampling", "Ts"): Ts}))
    line = assert_bad(cli(capsys, "predict", f), str(f), "[sampling] Ts", f"{TS_MIN:g}", f"{TS_MAX:g}")
    assert f"got {Ts!r}" in line


def test_predict_refuses_a_white_noise_whose_square_overflows(tmp_path, capsys):
    """sensor.white std = 1e300 was accepted and predicted var_y = inf; every number of a model file
    is at most 1e50 in magnitude, and the message says why."""
    f = tmp_path / "loud.toml"
    f.write_text(edited(SEED, {("sensor", "white", "std"): 1e300}))
    assert_bad(cli(capsys, "predict", f), "[sensor.white] std", "magnitude at most 1e+50", "float64", "1e+300")


def test_the_ends_of_the_sample_periods_range_predict(capsys, tmp_path):
    """Ts = 1 us and a day are models: the seed at 1 us (its quantizer needs the mean response over
    the horizon: 6e7 samples of 60 s before, now at most HORIZON_MAX) and at a day (its forward Euler
    unstable there: no steady state, said as such) both predict."""
    fine = parse_model(edited(SEED, {("sampling", "Ts"): TS_MIN}), "fine")
    assert fine.predictor().horizon == HORIZON_MAX
    rep = predict_report(fine)
    assert rep["var_y"][0] > 0 and np.isfinite(rep["var_y"][0])
    f = tmp_path / "slow.toml"
    f.write_text(edited(SEED, {("sampling", "Ts"): TS_MAX}))
    rc, out, err = cli(capsys, "predict", f, "--json")
    assert rc == 0, err
    assert '"stable": false' in out and '"var_y": null' in out


GENERAL = """\
name = "general"
[sampling]
Ts = 0.01
[plant]
A = [[0.0, 1.0, 0.0], [-4.0, -0.5, 1.0], [0.0, 0.0, -2.0]]
B = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]
C = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.5]]
L = [[0.0], [1.0], [0.5]]
[command]
kind = "sine"
amplitude = [0.8, 0.3]
frequency_hz = [0.7, 1.3]
[process.white]
psd = 0.04
[actuator.ar1]
std = [0.08, 0.04]
tau_s = [0.3, 0.1]
[actuator.lag]
tau_s = [0.02, 0.05]
[actuator.saturation]
limit = [5.0, 3.0]
[actuator.deadzone]
width = [0.01, 0.02]
[sensor.white]
std = [0.01, 0.02]
"""


@pytest.mark.parametrize("limit", [1e20, 1e50])
def test_a_saturation_that_never_clips_predicts_as_none(limit):
    """A saturation at 1e20 beside a dead zone of 0.01 (colored actuator noise): the prediction
    raised 'array must not contain infs or NaNs' (the slope past the kink at 1e20 came out 0 / 0,
    its Hermite terms 0 * inf) and, with that fixed, lost the dead zone's offset to the rounding of
    1e20 (var_y 1.3e-5 off). A limit the drive never reaches is no limit: var_y equals the model's
    without the saturation."""
    far = predict_report(parse_model(edited(GENERAL, {("actuator", "saturation", "limit"): limit}), "far"))
    none = predict_report(parse_model(edited(GENERAL, {}, drops=[("actuator", "saturation")]), "none"))
    np.testing.assert_allclose(far["var_y"], none["var_y"], rtol=1e-13)


def test_a_dead_zone_wider_than_any_drive_passes_nothing():
    """A dead zone of 1e20 (the same 0 * inf): nothing of the command or the actuator noises reaches
    the plant, so var_y is the process noise's and the sensor's alone."""
    wide = predict_report(parse_model(edited(GENERAL, {("actuator", "deadzone", "width"): 1e20}), "wide"))
    still = predict_report(parse_model(edited(GENERAL, {("command",): {"kind": "none"}}, drops=[("actuator",)]),
                                       "still"))
    np.testing.assert_allclose(wide["var_y"], still["var_y"], rtol=1e-12)


def test_every_built_in_scenario_still_loads():
    names = scenario_names() + scenario_names("hidden")
    assert len(names) >= 30
    for name in names:
        model = load_model(name)
        assert TS_MIN <= model.Ts <= TS_MAX, name
    for name in scenario_names():
        assert predict_report(load_model(name))["Ts"] > 0


# -- 2. recordings whose values the analysis cannot square --------------------------------------------
def write_record(path, model, n: int, seed: int, edit=None) -> None:
    """A noiselab recording of ``model`` (n samples of truth, command and measurement, the wire
    contract as ``simulate`` writes it), its arrays first given to ``edit(x, u, y)``."""
    from service.nodes import mcapio, wire

    b = model.simulate(n, seed=seed)
    x, u, y = b.x.copy(), b.u.copy(), b.y.copy()
    if edit is not None:
        edit(x, u, y)
    t, pub = wire.sample_times(0, n, model.Ts)
    with mcapio.RecordingWriter(path) as w:
        w.write_interleaved([(wire.key(model.name, kind), kind, 0, pub, pub,
                              wire.encode_batch(kind, 0, t, arr, topic=wire.key(model.name, kind)))
                             for kind, arr in (("truth", x), ("command", u), ("measurement", y))])


@pytest.fixture(scope="module")
def seed_model():
    return load_model("seed")


def _set(arr, k, value):
    arr[k, 0] = value


@pytest.mark.parametrize("command, kind, k, value, field", [
    ("diagnose", "y", 100, 1e308, "y[0] = 1e+308 at seq 100"),      # 'min() arg is an empty sequence' in search
    ("analyze", "y", 2500, 1e300, "y[0] = 1e+300 at seq 2500"),     # 'cannot convert float NaN to integer' in allan
    ("analyze", "y", 10, -1e51, "y[0] = -1e+51 at seq 10"),
    ("diagnose", "u", 2999, 1e200, "u[0] = 1e+200 at seq 2999"),
])
def test_a_value_the_analysis_cannot_square_is_refused_at_load(command, kind, k, value, field, seed_model,
                                                              tmp_path, capsys):
    """One value beyond 1e50 in a recording: refused where the recording becomes arrays, naming the
    file, the topic, the field and the seq (both commands read it there)."""
    rec = tmp_path / "spike.mcap"
    write_record(rec, seed_model, 3000, 1, lambda x, u, y: _set({"y": y, "u": u}[kind], k, value))
    topic = "noiselab/seed/" + {"y": "measurement", "u": "command"}[kind]
    assert_bad(cli(capsys, command, rec, "--model", "seed"), str(rec), topic, field, "1e+50", "float64")


def test_a_foreign_field_beyond_the_bound_is_refused_naming_it(tmp_path, capsys):
    """A JSON MCAP of another source (--measurement TOPIC:FIELD): the field and the sample named."""
    from mcap.writer import Writer

    rec = tmp_path / "imu.mcap"
    with open(rec, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("imu", "jsonschema", b'{"type": "object"}')
        cid = w.register_channel("/imu", "json", sid)
        rng = np.random.default_rng(3)
        for k in range(2000):
            a = 1e60 if k == 1234 else float(rng.normal(0, 0.01))
            w.add_message(cid, log_time=k * 10_000_000, publish_time=k * 10_000_000, sequence=k,
                          data=f'{{"accel": {{"x": {a!r}}}}}'.encode())
        w.finish()
    assert_bad(cli(capsys, "analyze", rec, "--model", "seed", "--measurement", "/imu:accel.x"),
               str(rec), "/imu", "accel.x = 1e+60 at sample 1234", "1e+50")


def test_values_up_to_the_bound_are_analysed(seed_model, tmp_path, capsys):
    """The bound is where the estimators stay finite: a record scaled so its largest value is 1e50
    (the seed model then far off, by 1e100 in variance) is analysed, with a finite model error."""
    import json

    rec = tmp_path / "loud.mcap"

    def scale(x, u, y):
        y *= 1e50 / np.max(np.abs(y))
    write_record(rec, seed_model, 3000, 2, scale)
    rc, out, err = cli(capsys, "analyze", rec, "--model", "seed", "--json")
    assert rc == 0, err
    rep = json.loads(out)
    assert np.isfinite(rep["error"]) and rep["error"] > 1e50
