"""Bad input on the command line, in model files and in recordings: one line on stderr naming what
is wrong and exit 2, never a traceback, and nothing already recorded lost (DESIGN.md "Exit codes").

1. Model files: the sample period's range (1 us to a day), the magnitude of every number (at most
   1e50), correlation times whose rho rounds to 1; the predictions of models inside those bounds
   (far nonlinearity kinks, the finest Ts, a plant that diverges as discretized) are finite or say
   the plant is unstable, without numpy warnings; every built-in scenario still loads.
2. Recordings: a value beyond 1e50 is refused where the recording becomes arrays, naming topic,
   field and seq; values up to it are analysed.
3. Output paths: a file in the way, a path that cannot be created, a full disk (/dev/full; and a
   file-size limit mid-write, for simulate --force and for a live recorder, whose file up to the
   fault reads back and is recovered).
4. Every numeric flag of every command, walked: nan, inf, -5, 0, 1e308, text.
5. --config: zenoh's defaults do not come back for what the file does not set.
6. Property tests (hypothesis) of the model-file parser and of `noiselab predict`.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import resource
import signal
import subprocess
import sys
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from helpers.cli import assert_bad
from helpers.cli import cli_in_process as cli
from helpers.recordings import write_record

from noiselab.cli import build_parser
from noiselab.commands.predict import predict_report
from noiselab.model import ModelError, dumps_toml, load_model, parse_model, scenario_names
from noiselab.model.effects import CATALOGUE
from noiselab.model.model import TS_MAX, TS_MIN, _from_data, scenario_text
from noiselab.model.predict import HORIZON_MAX
from noiselab.nodes import transport
from noiselab.recordings.output import PARTIAL_SUFFIX
from noiselab.recordings.reader import read_recording
from noiselab.nodes.runner import READY_MARK, free_port

ROOT = Path(__file__).resolve().parents[2]

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






# -- 1. model files ---------------------------------------------------------------------------------
@pytest.mark.parametrize("Ts", [1e300, 1e-300, 86401.0, 9e-7])
def test_predict_refuses_a_sample_period_out_of_its_range(Ts, tmp_path, capsys):
    """The sample period is 1 us to a day: outside, one line naming the range (Ts = 1e300 overflows
    the mean response in lsim, Ts = 1e-300 asks numpy for a horizon of 6e301 samples)."""
    f = tmp_path / "ts.toml"
    f.write_text(edited(SEED, {("sampling", "Ts"): Ts}))
    line = assert_bad(cli(capsys, "predict", f), str(f), "[sampling] Ts", f"{TS_MIN:g}", f"{TS_MAX:g}")
    assert f"got {Ts!r}" in line


def test_predict_refuses_a_white_noise_whose_square_overflows(tmp_path, capsys):
    """sensor.white std = 1e300 (var_y = inf): every number of a model file is at most 1e50 in
    magnitude, and the message says why."""
    f = tmp_path / "loud.toml"
    f.write_text(edited(SEED, {("sensor", "white", "std"): 1e300}))
    assert_bad(cli(capsys, "predict", f), "[sensor.white] std", "magnitude at most 1e+50", "float64", "1e+300")


def test_the_ends_of_the_sample_periods_range_predict(capsys, tmp_path):
    """Ts = 1 us and a day are models: the seed at 1 us (its quantizer needs the mean response over
    the horizon, 60 s or at most HORIZON_MAX samples: 6e7 would be gigabytes) and at a day (its
    forward Euler unstable there: no steady state, said as such) both predict."""
    fine = parse_model(edited(SEED, {("sampling", "Ts"): TS_MIN}), "fine")
    assert fine.predictor().horizon == HORIZON_MAX
    rep = predict_report(fine)
    assert rep["var_y"][0] > 0 and np.isfinite(rep["var_y"][0])
    f = tmp_path / "slow.toml"
    f.write_text(edited(SEED, {("sampling", "Ts"): TS_MAX}))
    rc, out, err = cli(capsys, "predict", f, "--json")
    assert rc == 0, err
    assert '"stable": false' in out and '"var_y": null' in out


def test_simulate_of_a_plant_that_diverges_is_one_line(tmp_path, capsys):
    """The seed's spring made stiff (k = 2.5e10 N/m): stable, but forward Euler at 10 ms diverges.
    simulate says where in one line (the sample that is not finite), with no numpy overflow warning
    before it, and leaves no file; predict says the plant is not stable, also without warnings."""
    f = tmp_path / "stiff.toml"
    f.write_text(edited(SEED, {("plant", "k"): 2.5e10}))
    out = tmp_path / "stiff.mcap"
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        assert_bad(cli(capsys, "simulate", f, "--duration", "10", "--out", out), "noiselab/seed/truth", "not finite")
        rc, text, err = cli(capsys, "predict", f)
    assert not out.exists()
    assert rc == 0 and err == "" and "the plant is not stable" in text


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
    """A saturation at 1e20 beside a dead zone of 0.01 (colored actuator noise): a limit the drive
    never reaches is no limit, var_y equals the model's without the saturation (the slope past a
    kink at 1e20 must not be 0 / 0, its Hermite terms not 0 * inf, nor the dead zone's offset lost
    to the rounding of 1e20: 1.3e-5 of var_y)."""
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
    names = scenario_names() + scenario_names("hidden") + scenario_names("hidden-closed")
    assert len(names) >= 65
    for name in names:
        model = load_model(name)
        assert TS_MIN <= model.Ts <= TS_MAX, name
    for name in scenario_names():
        assert predict_report(load_model(name))["Ts"] > 0


# -- 2. recordings whose values the analysis cannot square --------------------------------------------
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
    rec = tmp_path / "loud.mcap"

    def scale(x, u, y):
        y *= 1e50 / np.max(np.abs(y))
    write_record(rec, seed_model, 3000, 2, scale)
    rc, out, err = cli(capsys, "analyze", rec, "--model", "seed", "--json")
    assert rc == 0, err
    rep = json.loads(out)
    assert np.isfinite(rep["error"]) and rep["error"] > 1e50


# -- 3. output paths: a file in the way, a path that cannot be written, a full disk -----------------------

@pytest.fixture(scope="module")
def small_record(tmp_path_factory, seed_model):
    rec = tmp_path_factory.mktemp("rec") / "seed.mcap"
    write_record(rec, seed_model, 3000, 5)
    return rec


def test_an_output_under_a_file_is_one_line(tmp_path, capsys):
    """simulate --out afile/x.mcap, record --out afile/x.mcap, run and demo --out afile/sub, afile a
    regular file (FileExistsError and NotADirectoryError from mkdir): one line naming the file in
    the way, before any work, and the file untouched."""
    afile = tmp_path / "afile"
    afile.write_text("keep")
    assert_bad(cli(capsys, "simulate", "seed", "--duration", "1", "--out", afile / "x.mcap"),
               f"{afile} is a file, not a directory")
    assert_bad(cli(capsys, "record", "--duration", "1", "--out", afile / "x.mcap"),
               f"{afile} is a file, not a directory")
    assert_bad(cli(capsys, "run", "seed", "--duration", "1", "--out", afile / "sub"),
               f"{afile / 'sub'}: {afile} is a file, not a directory")
    assert_bad(cli(capsys, "run", "seed", "--duration", "1", "--out", afile), f"{afile}: is a file, not a directory")
    assert_bad(cli(capsys, "demo", "--duration", "1", "--out", afile / "sub"), f"{afile} is a file, not a directory")
    assert afile.read_text() == "keep"


def test_an_rrd_that_cannot_be_created_is_refused_before_the_analysis(small_record, capsys):
    """analyze --rrd /proc/x.rrd (Rerun's RuntimeError once the analysis is done): one line with the
    OS's reason, before any work (no report on stdout)."""
    rc, out, err = cli(capsys, "analyze", small_record, "--model", "seed", "--rrd", "/proc/x.rrd")
    assert_bad((rc, out, err), "/proc/x.rrd: cannot write it (No such file or directory)")
    assert out == ""


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full")
@pytest.mark.parametrize("args", [
    ["simulate", "seed", "--duration", "1", "--out", "/dev/full"],
    ["analyze", "{rec}", "--model", "seed", "--png", "/dev/full"],
    ["analyze", "{rec}", "--model", "seed", "--rrd", "/dev/full", "--png", "{tmp}/summary.png"],
    ["diagnose", "{rec}", "--model", "seed", "--max-effects", "1", "--fit-out", "/dev/full"],
], ids=["simulate-out", "analyze-png", "analyze-rrd", "diagnose-fit-out"])
def test_a_full_disk_is_one_line_naming_the_path(args, small_record, tmp_path, capsys):
    """Every output written into a full disk (/dev/full: ENOSPC at write or close; the PNG's and
    the fitted model's OSError, Rerun's RuntimeError): one line naming the path and the OS error,
    exit 2. Without --force /dev/full exists and is not overwritten."""
    argv = [a.format(rec=small_record, tmp=tmp_path) for a in args]
    assert_bad(cli(capsys, *argv), "/dev/full", "exists", "--force")
    assert_bad(cli(capsys, *argv, "--force"), "/dev/full: cannot write it (No space left on device)")


def _file_limit(nbytes: int):
    """preexec_fn: files of this process at most ``nbytes`` (a write beyond fails with EFBIG, as a
    full disk fails with ENOSPC; SIGXFSZ ignored so the write returns the error)."""
    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, nbytes))
    return limit


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full")
@pytest.mark.parametrize("where", ["/dev/full", "file-size limit"])
def test_an_rrd_that_meets_a_full_disk_is_one_line_and_nothing_after_it(where, small_record, tmp_path):
    """analyze --rrd into a full disk, at its first byte (/dev/full) or half-way (a file-size limit
    on the process): exit 2 and exactly one line on stderr, also after the process ends (Rerun
    wrote the file from a thread of its own: its errors and an exit-time warning of the data it
    dropped came after our line, and a disk full half-way hung or gave a traceback); no report on
    stdout, no cut .rrd left."""
    rrd = "/dev/full" if where == "/dev/full" else str(tmp_path / "cut.rrd")
    r = subprocess.run([sys.executable, "-m", "noiselab.cli", "analyze", small_record, "--model", "seed", "--rrd", rrd,
                        "--png", tmp_path / "summary.png", "--force", "--json"], capture_output=True, text=True,
                       cwd=ROOT, timeout=300, preexec_fn=None if where == "/dev/full" else _file_limit(200_000))
    reason = "No space left on device" if where == "/dev/full" else "File too large"
    assert r.returncode == 2 and r.stdout == "", r.stderr[-3000:]
    assert r.stderr == f"noiselab: {rrd}: cannot write it ({reason})\n"
    assert where == "/dev/full" or not Path(rrd).exists()


@pytest.mark.slow
@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full")
def test_the_live_analyzer_meets_a_full_disk_at_its_end_in_one_line(spawn):
    """analyze --live --rrd /dev/full: the .rrd is written when the analyzer stops, after an
    update it has shown; the full disk is one line naming the file and the OS error, exit 2, no
    traceback."""
    port = free_port()
    an = spawn("analyze", "analyze", "--live", "--model", "seed", "--listen", f"tcp/127.0.0.1:{port}", "--update",
               "0.5", "--rrd", "/dev/full", "--png", "/dev/full", "--force")
    spawn("emulate", "emulate", "seed", "--connect", f"tcp/127.0.0.1:{port}", "--connect-timeout", "60",
          "--duration", "3600", "--wait-subscribers", "60")
    an.wait_line("model error")                  # an update was made: there is something to write
    assert an.interrupt() == 2, an.stderr_text()
    assert "Traceback" not in an.stderr_text()
    assert an.err[-1] == "noiselab: /dev/full: cannot write it (No space left on device)", an.stderr_text()


@pytest.mark.slow
@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full")
@pytest.mark.parametrize("name", ["demo-seed-fitted.toml", "demo-seed-diagnosis.rrd", "demo-seed-summary.json"])
def test_the_demo_meets_a_full_disk_in_one_line(name, tmp_path):
    """One of the files the demo writes after its live run is a full disk (a link to /dev/full):
    one line naming it and the OS error, exit 2, no traceback; the recording is kept."""
    (tmp_path / name).symlink_to("/dev/full")
    r = subprocess.run([sys.executable, "-m", "noiselab.cli", "demo", "--duration", "20", "--out", tmp_path, "--force"],
                       capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-3000:]
    assert r.stderr.splitlines()[-1] == f"noiselab: {tmp_path / name}: cannot write it (No space left on device)"
    assert read_recording(tmp_path / "demo-seed.mcap").complete


def test_simulate_that_runs_out_of_space_keeps_the_recording_it_replaces(tmp_path):
    """simulate --force onto a recording, the disk full half-way: one line naming the file being
    written and the OS error, exit 2, and the old recording byte for byte (write-then-rename)."""
    old = tmp_path / "run.mcap"
    write_record(old, load_model("seed"), 500, 7)
    before = old.read_bytes()
    r = subprocess.run([sys.executable, "-m", "noiselab.cli", "simulate", "seed", "--duration", "100", "--out", old,
                        "--force"], preexec_fn=_file_limit(200_000), capture_output=True, text=True, cwd=ROOT,
                       timeout=300)
    assert_bad((r.returncode, r.stdout, r.stderr), str(old), "cannot write it (File too large)")
    assert old.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["run.mcap"]


def test_record_that_runs_out_of_space_keeps_what_reached_the_disk(tmp_path):
    """A recorder whose disk fills mid-stream (a real emulator on 127.0.0.1): exit 2, its last line
    names the file and the OS error, no traceback; every message that reached the disk reads back
    (the measurement's seqs 0..k with none missing) and `recover` makes a complete file of them."""
    port = free_port()
    out = tmp_path / "rec.mcap"
    rec = subprocess.Popen([sys.executable, "-m", "noiselab.cli", "record", "--connect", f"tcp/127.0.0.1:{port}",
                            "--connect-timeout", "60", "--out", out], preexec_fn=_file_limit(250_000), cwd=ROOT,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    emu = subprocess.Popen([sys.executable, "-m", "noiselab.cli", "emulate", "seed", "--listen",
                            f"tcp/127.0.0.1:{port}", "--duration", "3600", "--speed", "20", "--wait-subscribers", "60",
                            "--end-timeout", "1"], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        _, err = rec.communicate(timeout=300)           # it ends itself when the disk is full
    finally:
        emu.kill()
        emu.wait()
        if rec.poll() is None:
            rec.kill()
    assert rec.returncode == 2 and "Traceback" not in err, err[-3000:]
    last = err.splitlines()[-1]
    assert last.startswith(f"noiselab: {out}: cannot write it (File too large)"), err[-3000:]
    got = read_recording(out)
    assert not got.complete
    seq = got.device("seed").measurement.seq
    assert seq.size > 100 and np.array_equal(seq, np.arange(seq.size))
    fixed = tmp_path / "fixed.mcap"
    r = subprocess.run([sys.executable, "-m", "noiselab.cli", "recover", out, "-o", fixed], capture_output=True,
                       text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    back = read_recording(fixed)
    assert back.complete and np.array_equal(back.device("seed").measurement.seq, seq)


def test_record_over_a_file_names_the_file_it_fills(spawn, tmp_path):
    """record --force onto an existing recording fills OUT.partial and renames it over OUT only
    once finished (the old file is kept until then): its ready line names the file the bytes go
    to, not OUT. A new OUT is written as itself, and its ready line says so."""
    old = tmp_path / "run.mcap"
    write_record(old, load_model("seed"), 100, 1)
    before = old.read_bytes()
    partial = Path(f"{old}{PARTIAL_SUFFIX}")
    rec = spawn("record", "record", "--listen", f"tcp/127.0.0.1:{free_port()}", "--out", old, "--force", "--json")
    line = rec.wait_line(READY_MARK)
    assert line == f"{READY_MARK} to noiselab/**, writing {partial} (it replaces {old} once the recording is finished)"
    assert partial.exists() and old.read_bytes() == before
    assert rec.interrupt() == 0
    assert not partial.exists() and old.read_bytes() != before and read_recording(old).complete
    new = tmp_path / "new.mcap"
    rec = spawn("record", "record", "--listen", f"tcp/127.0.0.1:{free_port()}", "--out", new, "--json")
    assert rec.wait_line(READY_MARK) == f"{READY_MARK} to noiselab/**, writing {new}"
    assert rec.interrupt() == 0 and read_recording(new).complete


# -- 4. numeric flags of every command ------------------------------------------------------------------------
# flags where 0 means something (no wait, never, from the start, seed 0); everywhere else 0 is refused
ZERO_ALLOWED = {"--wait-subscribers", "--wait-peers", "--rank-every", "--burn", "--seed", "--connect-timeout"}
# what a command needs besides the flag under test to get as far as its flags (none of it is run)
REQUIRED = {"--duration": "1", "--model": "seed", "--out": "x.mcap", "--output": "y.mcap"}


def numeric_flags():
    """(command, flag, argv without the flag, the flag's type) for every option of every subcommand
    that converts its text (argparse ``type=``)."""
    parser = build_parser()
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    out = []
    for command, sp in subs.choices.items():
        for act in sp._actions:
            if not act.option_strings or act.type is None:
                continue
            flag = max(act.option_strings, key=len)
            argv = [command]
            for other in sp._actions:
                if other is act or not other.required:
                    continue
                if other.option_strings:
                    name = max(other.option_strings, key=len)
                    argv += [name, REQUIRED[name]]
                else:
                    argv.append("x")                        # a positional (model, recording): not opened
            out.append((command, flag, argv, act.type))
    return out


FLAGS = numeric_flags()


def test_the_walk_finds_every_numeric_flag_and_each_uses_the_shared_checks():
    found = {(c, f) for c, f, _, _ in FLAGS}
    assert {("emulate", "--wait-subscribers"), ("emulate", "--wait-peers"), ("replay", "--wait-subscribers"),
            ("emulate", "--connect-timeout"), ("emulate", "--stale"), ("emulate", "--end-timeout"),
            ("emulate", "--speed"), ("analyze", "--window"), ("analyze", "--update"), ("analyze", "--rank-every"),
            ("analyze", "--burn"), ("diagnose", "--max-effects"), ("demo", "--speed"), ("run", "--duration"),
            ("simulate", "--seed"), ("record", "--duration"), ("router", "--connect-timeout")} <= found
    assert len(FLAGS) >= 31
    for command, flag, _, kind in FLAGS:
        assert kind.__qualname__ in ("bounded.<locals>.conv", "_burn"), (command, flag)


def test_a_node_takes_the_bounded_flags_without_the_command_line():
    """The bounded numeric types live in noiselab.args, which the command line and the nodes both
    import: a node adding its flags (transport's --connect-timeout) does not import noiselab.cli,
    which imports the nodes (a cycle). In a fresh interpreter, so no other test's imports count."""
    code = ("import argparse, sys\n"
            "import noiselab.nodes.transport as t\n"
            "p = argparse.ArgumentParser()\n"
            "t.add_transport_args(p)\n"
            "assert p.parse_args(['--connect-timeout', '0']).connect_timeout == 0.0\n"
            "print(sorted(m for m in sys.modules if m == 'noiselab.cli' or m.startswith('noiselab.cli.')))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "[]", (r.stdout, r.stderr[-2000:])


@pytest.mark.parametrize("command, flag, argv, kind", FLAGS, ids=[f"{c} {f}" for c, f, _, _ in FLAGS])
def test_a_bad_number_on_any_flag_is_one_line_exit_2(command, flag, argv, kind, capsys):
    """nan, inf, -inf, -5, 1e308 (no timer waits that long; duration / Ts overflows), text, an empty
    string and 0 where it means nothing (emulate --wait-subscribers -5 and nan among them): refused
    by argparse before the command runs, one line naming the flag; 1, 2.5 and 0 where it means
    something are taken."""
    bad = ["nan", "inf", "-inf", "-5", "1e308", "abc", ""] + ([] if flag in ZERO_ALLOWED else ["0"])
    for value in bad:
        with pytest.raises(SystemExit) as info:
            build_parser().parse_args([*argv, f"{flag}={value}"])
        _, err = capsys.readouterr()
        assert info.value.code == 2, (flag, value)
        lines = err.splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"noiselab: argument {flag}: expected"), (value, err)
    for value in ["1", "2.5" if flag not in ("--wait-peers", "--max-effects", "--seed", "--segment") else "2"] + \
            (["0"] if flag in ZERO_ALLOWED else []):
        args = build_parser().parse_args([*argv, f"{flag}={value}"])
        assert args.command == command


def test_emulate_wait_subscribers_minus_5_from_the_shell():
    r = subprocess.run([sys.executable, "-m", "noiselab.cli", "emulate", "seed", "--wait-subscribers", "-5"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert_bad((r.returncode, r.stdout, r.stderr), "--wait-subscribers", "'-5'")


# -- 5. --config: the safe defaults hold for what the file does not set ---------------------------------------
def _config(tmp_path, text: str | None, role: str, **flags):
    path = None
    if text is not None:
        path = tmp_path / "zenoh.json5"
        path.write_text(text)
    args = argparse.Namespace(config=path and str(path), connect=flags.get("connect"), listen=flags.get("listen"),
                              mode=None, connect_timeout=5.0)
    conf = transport.build_config(args, role)

    def get(key):
        return json.loads(conf.get_json(key))
    return get, transport.endpoints_of(args, role)


UNRELATED = """{
  // a real JSON5 file: comments, unquoted keys, a trailing comma; it tunes queries only
  queries_default_timeout: 20000,
}
"""


@pytest.mark.parametrize("role", ["source", "sink", "router"])
def test_a_config_file_that_sets_something_else_keeps_the_safe_defaults(role, tmp_path):
    """--config with a file about something else: multicast scouting stays off and the endpoints are
    the defaults' (not zenoh's own tcp/[::]:0, every interface); the file's own setting is kept."""
    without, _ = _config(tmp_path, None, role)
    get, ends = _config(tmp_path, UNRELATED, role)
    assert get("queries_default_timeout") == 20000
    assert get("scouting/multicast/enabled") is False
    for key in ("listen/endpoints", "connect/endpoints"):
        assert get(key) == without(key), key
    if role == "sink":
        assert get("listen/endpoints") == [] and get("connect/endpoints") == ["tcp/127.0.0.1:7447"]
        assert ends == {"listen": [], "connect": ["tcp/127.0.0.1:7447"]}
    else:
        assert get("listen/endpoints") == ["tcp/127.0.0.1:7447"] and get("connect/endpoints") == []
        assert ends == {"listen": ["tcp/127.0.0.1:7447"], "connect": []}


def test_a_config_file_that_sets_scouting_and_endpoints_wins(tmp_path):
    text = "{ scouting: { multicast: { enabled: true } }, listen: { endpoints: ['tcp/0.0.0.0:7999'] } }"
    for role in ("source", "sink"):
        get, ends = _config(tmp_path, text, role)
        assert get("scouting/multicast/enabled") is True
        assert get("listen/endpoints") == ["tcp/0.0.0.0:7999"] and get("connect/endpoints") == []
        assert ends == {"listen": ["tcp/0.0.0.0:7999"], "connect": []}
    # command-line endpoints still win over the file's
    get, _ = _config(tmp_path, text, "sink", connect=["tcp/127.0.0.1:7001"])
    assert get("connect/endpoints") == ["tcp/127.0.0.1:7001"] and get("listen/endpoints") == ["tcp/0.0.0.0:7999"]


# -- 6. property tests of the model-file parser -----------------------------------------------------------------
# Any text, any bytes, any TOML-shaped table given to the model loader: a model, or a ValueError
# (ModelError) whose message is one line; never another exception. Numbers are drawn around the
# bounds (the sample period's range, 1e50) and far beyond them (1e308, 5e-324, nan, inf, integers of
# 400 digits), values of every TOML type where numbers belong, tables where values belong.

MODEL_KEYS = sorted({
    "name", "description", "sampling", "plant", "command", "process", "actuator", "sensor", "Ts",
    "discretization", "m", "c", "k", "A", "B", "C", "D", "L", "kind", "amplitude", "frequency_hz", "offset",
    "phase_rad", "time_s", "f0_hz", "f1_hz", "duration_s", "bit_s", "order", "std", "psd", "rho", "tau_s",
    "limit", "width", "initial_std", "step", "error", "std_s", "density", *(e.split(".")[1] for e in CATALOGUE),
})
keys = st.one_of(st.sampled_from(MODEL_KEYS), st.text(max_size=6))
numbers = st.one_of(
    st.floats(),                                                        # nan, inf, subnormals, 1.8e308
    st.integers(-(10**400), 10**400), st.integers(-3, 20),
    st.sampled_from([0.0, -0.0, 5e-324, 1e-300, 1e-50, 9e-7, 1e-6, 0.01, 0.97, 1.0, 86400.0, 86401.0, 1e15,
                     1e50, 1.0000000000000002e50, 1e51, 1e300, -1e300, -1.0, 7, 9]),
)
# magnitudes spread evenly over the whole range a model file allows, 1e-50 to 1e50, either sign
inside = st.builds(lambda e, sign: sign * 10.0**e, st.floats(-50, 50), st.sampled_from([1.0, 1.0, -1.0]))
scalars = st.one_of(numbers, numbers, st.booleans(), st.text(max_size=8),
                    st.sampled_from(["zoh", "euler", "sine", "prbs", "chirp", "step", "none", "external", "seed"]),
                    st.dates(), st.times(), st.datetimes(timezones=st.sampled_from([None, _dt.timezone.utc])))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(keys, inner, max_size=4)), max_leaves=10)
tables = st.dictionaries(keys, values, max_size=6)


def _toml_key(k: str) -> str:
    return _toml_str(k)


def _toml_str(s: str) -> str:
    out = []
    for ch in s:
        if ch in '"\\':
            out.append("\\" + ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _toml_value(v) -> str:
    """Any value of a TOML-shaped dict as TOML (nested tables inline, nan and inf as TOML spells them)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if v != v else ("inf" if v > 0 else "-inf") if v in (float("inf"), float("-inf")) else repr(v)
    if isinstance(v, str):
        return _toml_str(v)
    if isinstance(v, (_dt.date, _dt.time)):
        return v.isoformat()
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"


def toml_text(d: dict) -> str:
    return "".join(f"{_toml_key(k)} = {_toml_value(v)}\n" for k, v in d.items())


def _is_numeric(d: dict, path: tuple) -> bool:
    for k in path:
        d = d[k]
    flat = d if isinstance(d, list) else [d]
    flat = [x for row in flat for x in (row if isinstance(row, list) else [row])]
    return bool(flat) and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in flat)


def _leaves(d, path=()):
    for k, v in d.items():
        yield path + (k,)
        if isinstance(v, dict):
            yield from _leaves(v, path + (k,))


@st.composite
def model_shaped(draw) -> dict:
    """A valid model's table (the seed, or the general two-input plant with a nonlinear actuator)
    with 1 to 4 edits: a key set to any value (numbers mostly), a key deleted, a key added anywhere."""
    d = tomllib.loads(draw(st.sampled_from([SEED, GENERAL])))
    for _ in range(draw(st.integers(1, 4))):
        paths = list(_leaves(d))
        op = draw(st.sampled_from(["inside", "inside", "number", "number", "value", "delete", "add"]))
        numeric = [p for p in paths if _is_numeric(d, p)]
        path = draw(st.sampled_from(numeric if op in ("number", "inside") and numeric else paths))
        node = d
        for k in path[:-1]:
            node = node[k]
        if op == "delete":
            del node[path[-1]]
        elif op == "add":
            (node[path[-1]] if isinstance(node[path[-1]], dict) else node)[draw(keys)] = draw(values)
        else:
            node[path[-1]] = draw({"number": numbers, "inside": inside, "value": values}[op])
    return d


def model_or_one_line_error(load) -> object:
    """``load()``'s model, or None after checking its error is a one-line ValueError."""
    try:
        return load()
    except ValueError as exc:
        assert isinstance(exc, ModelError), type(exc)
        msg = str(exc)
        assert msg and "\n" not in msg and "\r" not in msg, msg
        return None


PROPERTY = settings(derandomize=True, database=None, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.filter_too_much, HealthCheck.function_scoped_fixture])


@settings(PROPERTY, max_examples=300)
@given(data=st.one_of(st.binary(max_size=300), st.text(max_size=300).map(str.encode)))
def test_any_bytes_give_a_model_or_one_line_error(data, tmp_path_factory):
    f = tmp_path_factory.mktemp("bytes", numbered=True) / "any.toml"
    f.write_bytes(data)
    model_or_one_line_error(lambda: load_model(f))


@settings(PROPERTY, max_examples=300)
@given(d=st.one_of(tables, model_shaped()))
def test_any_toml_table_gives_a_model_or_one_line_error(d):
    """The table as TOML text through the parser, and as a dict through the same validation (the
    diagnosis' trial models take that way)."""
    text = toml_text(d)
    assert tomllib.loads(text) == d or any(isinstance(v, float) and v != v for v in _all_values(d))
    a = model_or_one_line_error(lambda: parse_model(text, "prop.toml"))
    b = model_or_one_line_error(lambda: _from_data(d, "prop.toml", text))
    assert (a is None) == (b is None)
    if a is not None:
        assert TS_MIN <= a.Ts <= TS_MAX and np.all(np.isfinite(a.Ad)) and np.all(np.isfinite(a.S_proc))


def _all_values(d):
    for v in d.values():
        if isinstance(v, dict):
            yield from _all_values(v)
        elif isinstance(v, list):
            yield from _all_values({i: x for i, x in enumerate(v)})
        else:
            yield v


@settings(PROPERTY, max_examples=200)
@given(d=model_shaped())
# each a traceback before the bounds (OverflowError, ValueError, ValueError, LinAlgError) or inf
@example(d=tomllib.loads(edited(SEED, {("sampling", "Ts"): 1e300})))
@example(d=tomllib.loads(edited(SEED, {("sampling", "Ts"): 1e-300})))
@example(d=tomllib.loads(edited(GENERAL, {("actuator", "saturation", "limit"): 1e20})))
@example(d=tomllib.loads(edited(SEED, {("actuator",): {"ar1": {"std": 0.1, "tau_s": 1e50}}})))
@example(d=tomllib.loads(edited(SEED, {("sensor", "white", "std"): 1e300})))
# stable in continuous time, not as forward Euler at 10 ms: numpy's overflow warnings on stderr
@example(d=tomllib.loads(edited(SEED, {("plant", "k"): 2.5e10})))
def test_predict_of_any_edited_model_is_a_report_or_one_line_exit_2(d, tmp_path_factory, capsys):
    """`noiselab predict FILE` in this process: exit 0 with a report and nothing on stderr (no numpy
    warning either) when the file is a model (its numbers inside the bounds: a stable model's
    variances are finite numbers, not null), else exit 2 and one line naming the file."""
    f = tmp_path_factory.mktemp("predict", numbered=True) / "edited.toml"
    f.write_text(toml_text(d))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        rc, out, err = cli(capsys, "predict", f, "--json")
    if rc == 0:
        rep = json.loads(out)
        assert err == ""
        if rep["stable"]:
            assert None not in rep["var_y"] and all(None not in v for v in rep["contributions"].values()), rep
    else:
        assert_bad((rc, out, err), str(f))


@settings(PROPERTY, max_examples=3)
@given(d=model_shaped())
def test_predict_of_a_bad_model_file_from_the_shell(d, tmp_path_factory):
    """The same from the shell, a few files (each run pays the interpreter's start)."""
    text = toml_text(d)
    assume(model_or_one_line_error(lambda: parse_model(text, "bad.toml")) is None)
    f = tmp_path_factory.mktemp("shell", numbered=True) / "bad.toml"
    f.write_text(text)
    r = subprocess.run([sys.executable, "-m", "noiselab.cli", "predict", f], capture_output=True, text=True,
                       cwd=ROOT, timeout=120)
    assert_bad((r.returncode, r.stdout, r.stderr), str(f))
