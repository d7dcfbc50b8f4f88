"""The reference controller (issue 45, part 1): its PID law against a hand computation, the
seed-closed loop's poles, the [controller] table, bad flags; and live, on 127.0.0.1 with real
MCAP: `noiselab run seed-closed` records a control stream that is the PID of the recorded
measurements, a live closed-loop recording is diagnosed, and a controller fed hostile
measurements counts them and answers the rest.

Live runs are short (2 s of samples at 10x real time). How late the controller's answers reach
the emulator depends on the machine, so the applied command is checked against the timing
contract, not a fixed delay: u_k is 0 before the first answer arrives, then the answer to some
earlier measurement j < k, with j never going back.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import zenoh

from helpers.cli import assert_bad
from helpers.cli import cli_in_process as cli
from helpers.live import Collector, ep, session_config
from helpers.models import LOOP_TOML
from noiselab import wire
from noiselab.model import ModelError, load_model, parse_model
from noiselab.model.controller import (ControllerSpec, Pid, closed_loop_matrix, closed_loop_poles,
                                       simulate_closed_loop)
from noiselab.nodes import transport
from noiselab.nodes.controller import READY_MARK
from noiselab.nodes.runner import free_port
from noiselab.recordings.reader import read_recording
from noiselab.recordings.scan import iter_messages

T_EVENT = 60.0


# -- the law -----------------------------------------------------------------------------------------------
def test_pid_law_against_a_hand_computation():
    """kp 2, ki 0.5, kd 0.1, Ts 0.1, a step r = 1; measurements y = 0, 0.5 (seq 0, 1), then 0.8 at
    seq 3 (seq 2 lost: the derivative spans 2 Ts):
      k=0: e = 1,   I = 0.05,  D = 0                          -> u = 2 + 0.05          = 2.05
      k=1: e = 0.5, I = 0.075, D = -0.1 (0.5 - 0) / 0.1 = -0.5 -> u = 1 + 0.075 - 0.5   = 0.575
      k=3: e = 0.2, I = 0.085, D = -0.1 (0.8 - 0.5) / 0.2 = -0.15 -> u = 0.4 + 0.085 - 0.15 = 0.335"""
    pid = Pid(ControllerSpec(2.0, 0.5, 0.1, reference="step", amplitude=1.0), 0.1)
    got = [pid.step(0, 0.0, 0.0), pid.step(1, 0.1, 0.5), pid.step(3, 0.3, 0.8)]
    assert got == pytest.approx([2.05, 0.575, 0.335], rel=1e-12, abs=1e-15)
    sine = ControllerSpec(1.0, 0.0, 0.0, reference="sine", amplitude=0.2, frequency_hz=0.5)
    assert sine.r(0.5) == pytest.approx(0.2) and sine.r(0.0) == 0.0
    # derivative on the measurement: a reference step alone moves u by kp Delta r, no kd Delta r / Ts kick
    a, b = Pid(ControllerSpec(1.0, 0.0, 5.0), 0.01), Pid(ControllerSpec(1.0, 0.0, 5.0, "step", 1.0), 0.01)
    assert b.step(0, 0.0, 0.0) - a.step(0, 0.0, 0.0) == 1.0 and b.step(1, 0.01, 0.0) - a.step(1, 0.01, 0.0) == 1.0


def test_closed_loop_matrix_is_the_loop_stepped_by_hand():
    """closed_loop_matrix(delay d) steps as the noise-free plant and the Pid class do, the answer to
    y_k applied at sample k + d."""
    model = load_model("seed-closed")
    spec = ControllerSpec(8.0, 4.0, 2.0)
    for d in (1, 3):
        A = closed_loop_matrix(model, spec, d)
        x, pid, queue = np.array([0.1, -0.2]), Pid(spec, model.Ts), [0.0] * d
        z = np.concatenate([x, queue, [0.0, 0.0]])
        z[-1] = (model.Cy @ x)[0]                                         # y_{-1} = y_0: no derivative at k = 0
        for k in range(50):
            y = (model.Cy @ x)[0]
            queue.append(pid.step(k, k * model.Ts, y))
            x = model.Ad @ x + model.Bd[:, 0] * queue.pop(0)
            z = A @ z
            assert np.allclose(z[:2], x, rtol=1e-12, atol=1e-14), (d, k)


def test_seed_closed_is_stable_with_margin():
    """The gains of seed-closed put every closed-loop pole inside |z| <= 0.997 (time constants
    <= 3.3 s) with the oscillating pair damped at zeta >= 0.2; the loop stays stable with the gains
    halved or doubled, and with answers up to 10 samples late."""
    model = load_model("seed-closed")
    spec = model.controller
    assert (spec.kp, spec.ki, spec.kd, spec.reference) == (8.0, 4.0, 2.0, "sine")
    z = closed_loop_poles(model, spec)
    assert np.abs(z).max() <= 0.997
    s = np.log(z[np.abs(z) > 1e-12].astype(complex)) / model.Ts
    slow = s[np.abs(s) < 50]                                              # the plant's and the integrator's
    assert (-slow.real / np.abs(slow)).min() >= 0.2, slow
    for scale in (0.5, 2.0):
        scaled = ControllerSpec(spec.kp * scale, spec.ki * scale, spec.kd * scale)
        assert np.abs(closed_loop_poles(model, scaled)).max() < 0.999, scale
    for d in range(1, 11):
        assert np.abs(closed_loop_poles(model, spec, d)).max() < 0.999, d


def test_the_loop_offline_is_the_step_and_batch_path():
    """simulate_closed_loop: the answer to y_k is applied at sample k + delay (zero before), it is
    the PID of y_0..y_k, and the batch simulation with the applied command gives the same y bit
    for bit (what a live run whose controller is never late records)."""
    model = load_model("seed-closed")
    for delay in (1, 4):
        run = simulate_closed_loop(model, 400, seed=5, delay=delay)
        u, y, c = run["u"][:, 0], run["y"], run["control"]
        assert (u[:delay] == 0.0).all() and np.array_equal(u[delay:], c[:-delay])
        pid = Pid(model.controller, model.Ts)
        assert np.array_equal(c, [pid.step(k, k * model.Ts, y[k, 0]) for k in range(400)])
        assert np.array_equal(model.simulate(400, seed=5, command=run["u"]).y, y)
    assert np.abs(run["y"][200:, 0]).max() < 1.0                        # it follows the 0.2 m sine, it does not diverge


# -- the [controller] table --------------------------------------------------------------------------------
CLOSED = LOOP_TOML + """
[controller]
kind = "pid"
kp = 8.0
ki = 0.0
kd = 1.5
reference = "step"
amplitude = 0.3
"""


def test_simulate_closes_the_loop_of_a_model_with_a_controller(capsys, tmp_path):
    """`noiselab simulate` of a model with a [controller] records the closed loop: the command on
    file is the controller's answers applied from the next sample (simulate_closed_loop), not the
    external command's zeros, and the measurements are the model's under that command."""
    out = tmp_path / "closed.mcap"
    rc, _, err = cli(capsys, "simulate", "seed-closed", "--duration", "5", "--seed", "4", "--out", out)
    assert rc == 0, err
    dev = read_recording(out).device("seed-closed")
    model = load_model("seed-closed")
    loop = simulate_closed_loop(model, 500, seed=4)
    np.testing.assert_array_equal(dev.command.values, loop["u"])
    np.testing.assert_array_equal(dev.measurement.values, loop["y"])
    assert np.std(loop["u"]) > 0.1


def test_controller_table_is_parsed_validated_and_written_back():
    m = parse_model(CLOSED, "closed")
    assert m.controller == ControllerSpec(8.0, 0.0, 1.5, reference="step", amplitude=0.3)
    back = parse_model(m.to_toml(), "back")
    assert back.controller == m.controller and "[controller]" in m.to_toml()
    assert parse_model(LOOP_TOML, "loop").controller is None
    assert load_model("seed-closed").controller.frequency_hz == 0.2
    bad = {
        CLOSED.replace('kind = "external"', 'kind = "none"'): "[controller]: a controller needs [command] kind = \"external\"",
        CLOSED.replace("kp = 8.0\n", ""): "[controller] kp: missing required key",
        CLOSED.replace('kind = "pid"', 'kind = "pd"'): "[controller] kind: expected one of 'pid'",
        CLOSED.replace("amplitude = 0.3", "amplitude = -0.3"): "[controller] amplitude: expected an amplitude > 0",
        CLOSED.replace('reference = "step"', 'reference = "sine"'): "[controller] frequency_hz: missing required key",
        CLOSED.replace("kd = 1.5", "kd = 1.5\ntau = 2"): "[controller] tau: unknown key",
        CLOSED.replace("ki = 0.0", 'ki = "fast"'): "[controller] ki: expected a finite number",
    }
    for text, msg in bad.items():
        with pytest.raises(ModelError) as e:
            parse_model(text, "closed")
        assert msg in str(e.value) and "\n" not in str(e.value), str(e.value)


# -- bad flags ---------------------------------------------------------------------------------------------
def test_bad_controller_flags_are_one_line_exit_2(capsys, tmp_path):
    loop = tmp_path / "loop.toml"
    loop.write_text(LOOP_TOML)                                           # external, no [controller]
    out = ["--out", tmp_path / "rec"]
    assert_bad(cli(capsys, "run", "seed", "--duration", "1", "--controller", "pid:1,2,3", *out),
               "--controller and --reference need a model whose [command] kind is \"external\"", "'sine'")
    assert_bad(cli(capsys, "run", loop, "--duration", "1", *out),
               "the command is external: give --controller pid:KP,KI,KD or a [controller] table")
    assert_bad(cli(capsys, "run", "seed-closed", "--duration", "1", "--controller", "pd:1,2,3", *out),
               "argument --controller: expected pid:KP,KI,KD, got 'pd:1,2,3'")
    assert_bad(cli(capsys, "run", "seed-closed", "--duration", "1", "--controller", "pid:1,nan,3", *out),
               "argument --controller: expected KP,KI,KD")
    assert_bad(cli(capsys, "run", "seed-closed", "--duration", "1", "--reference", "step", *out),
               "--reference step needs --amplitude")
    assert_bad(cli(capsys, "control", "seed", "--pid", "1,2,3"), "a controller needs [command] kind = \"external\"")
    assert_bad(cli(capsys, "control", "seed-closed", "--pid", "1,2"), "argument --pid: expected KP,KI,KD")
    assert_bad(cli(capsys, "control", loop), "no controller: give its gains")
    assert_bad(cli(capsys, "control", loop, "--pid", "1,0,0", "--amplitude", "2"),
               "--amplitude and --frequency-hz need --reference step or sine")
    assert_bad(cli(capsys, "control", "seed-closed", "--frequency-hz", "0"), "argument --frequency-hz: expected")
    assert not (tmp_path / "rec").exists()                                # refused before any process started


# -- live --------------------------------------------------------------------------------------------------
def _topics(path) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for _, channel, message in iter_messages(path):
        out.setdefault(channel.topic, []).append(json.loads(message.data))
    return out


def test_run_seed_closed_records_the_pid_of_the_recorded_measurements(capsys, tmp_path):
    """`noiselab run seed-closed`: every topic 0..N-1 without gaps; the control stream answers
    measurement j with seq j and the PID of y_0..y_j (bit for bit, the law recomputed from the
    file); the applied command is zero until the first answer arrives, then an earlier answer
    (the zero-order hold), never an older one than before; the controller's health is recorded
    and its summary says every measurement was answered; and the live path is the batch path
    for the recorded command."""
    n = 200
    rc, out, err = cli(capsys, "run", "seed-closed", "--duration", "2", "--speed", "10", "--seed", "3",
                       "--out", tmp_path, "--no-analyze", "--json")
    assert rc == 0, err
    rep = json.loads(out)
    ctl = rep["controller"]
    assert (ctl["answered"], ctl["first_seq"], ctl["last_seq"], ctl["ended"]) == (n, 0, n - 1, "duration"), ctl
    assert ctl["missing_measurements"] == ctl["stale_measurements"] == ctl["rejected_measurements"] == 0, ctl
    assert 0 <= ctl["late_replies"] <= n and ctl["recorders"]["acks"][0]["complete"], ctl
    model = load_model("seed-closed")
    topics = _topics(rep["recording"])
    key = {kind: wire.key("seed-closed", kind) for kind in (*wire.KINDS, wire.CONTROL, wire.CONTROLLER_HEALTH)}
    for kind in (*wire.KINDS, wire.CONTROL):
        assert [m["seq"] for m in topics[key[kind]]] == list(range(n)), kind
        assert rep["recorder"]["topics"][key[kind]]["gaps"] == [], kind
    meas, control = topics[key["measurement"]], topics[key[wire.CONTROL]]
    pid = Pid(model.controller, model.Ts)
    assert [c["u"][0] for c in control] == [pid.step(m["seq"], m["t"], m["y"][0]) for m in meas]
    assert [c["t"] for c in control] == [m["t"] for m in meas]
    c = np.array([m["u"][0] for m in control])
    u = np.array([m["u"][0] for m in topics[key["command"]]])
    first = int(np.flatnonzero(u != 0.0)[0])
    assert first >= 1 and (u[:first] == 0.0).all()
    j_prev = 0
    for k in range(first, n):
        hits = np.flatnonzero(c[:k] == u[k])
        assert hits.size and hits[-1] >= j_prev, f"u[{k}] = {u[k]!r} is no answer to y_j, j in {j_prev}..{k - 1}"
        j_prev = int(hits[-1])
    health = topics[key[wire.CONTROLLER_HEALTH]]
    assert len(health) >= 2 and health[-1]["k"] == n and health[-1]["missing_measurements"] == 0
    dev = read_recording(rep["recording"]).device("seed-closed")
    sim = model.simulate(n, seed=3, command=dev.command.values)
    assert np.array_equal(sim.y, dev.measurement.values)


def test_a_live_closed_loop_recording_is_diagnosed(capsys, tmp_path):
    """Emulator, controller and recorder live on 127.0.0.1 (`run hidden-closed/sensor.tone`: a servo
    under a PD, a 3.1 Hz sensor line inside the loop's bandwidth), then `diagnose` of the MCAP
    against the model without the line: the record is said to be closed-loop and the line is found
    as a sensor tone (frequency inside its interval, amplitude within 30 %), though the controller
    copies it into the command. However late the answers arrive, the record's command is the one
    the plant got, so the residual is the noise process."""
    rc, out, err = cli(capsys, "run", "hidden-closed/sensor.tone", "--duration", "40", "--speed", "10",
                       "--seed", "5", "--out", tmp_path, "--no-analyze", "--json")
    assert rc == 0, err
    rec = json.loads(out)["recording"]
    rc, out, err = cli(capsys, "diagnose", rec, "--model", "hidden-closed/sensor.tone-nominal", "--json")
    assert rc == 0, err
    rep = json.loads(out)
    assert rep["closed_loop"] is not None and rep["closed_loop"]["p_value"] < 1e-6, rep["closed_loop"]
    first = rep["missing"][0]
    assert first["effect"] == "sensor.tone", [(m["effect"], m["score"]) for m in rep["missing"]]
    lo, hi = first["interval"]["frequency_hz"]
    assert lo <= 3.1 <= hi and abs(first["params"]["amplitude"] / 1e-3 - 1) < 0.3, first
    assert rep["error_after"] < rep["error_before"] and rep["error_after"] <= 1.5


def test_a_controller_counts_and_skips_hostile_measurements(spawn):
    """Measurements that break the contract, have two elements, repeat or jump back, or lie
    beyond 1e50 are skipped and counted, never a crash; the good ones are answered with their
    seq (a jump counts the seqs skipped as missing); an end that counts fewer measurements than
    were answered is rejected; the stream's end stops the node (exit 0), its summary has it all."""
    port = free_port()
    ctl = spawn("control", "control", "seed-closed", "--pid", "1,0,0", "--reference", "none",
                "--listen", ep(port), "--json")
    ctl.wait_line(READY_MARK)
    meas_key, control_key = wire.key("seed-closed", "measurement"), wire.key("seed-closed", wire.CONTROL)
    answers = Collector()
    good = lambda seq, y: wire.encode(seq, seq * 0.01, [y], kind="measurement")   # noqa: E731
    sent = [good(0, 0.5), b"not json", b'{"seq":1,"t":0.01,"y":[1e400]}', good(1, 0.25),
            wire.encode(2, 0.02, [1.0, 2.0], kind="measurement"), good(1, 9.0), good(2, 1e60),
            b'{"seq":2,"t":0.02,"y":["x"]}', b"[" * 100000, good(2, -0.5), good(5, 0.125)]
    with zenoh.open(session_config(connect=[ep(port)])) as session:
        sub = session.declare_subscriber(control_key, answers)
        pub = session.declare_publisher(meas_key, **transport.DATA_QOS)          # BLOCK: none dropped on the way
        end_pub = session.declare_publisher(wire.key("seed-closed", wire.END), **transport.DATA_QOS)
        assert transport.wait_matching([pub], T_EVENT)
        for payload in sent:
            pub.put(payload)
        answers.wait_for(lambda: answers.count(control_key) >= 4, "4 answers")
        end_pub.put(wire.encode_end(0, 0.05, 6, {"measurement": 2}, "stopped"))      # fewer than answered
        end_pub.put(wire.encode_end(0, 0.06, 7, {"measurement": 7}, "stopped"))
        assert ctl.finish(T_EVENT) == 0, ctl.stderr_text()
        sub.undeclare()
    got = [wire.decode(p, "control") for p, _ in answers.by_key[control_key]]
    assert [(a["seq"], a["u"]) for a in got] == [(0, [-0.5]), (1, [-0.25]), (2, [0.5]), (5, [-0.125])]
    s = ctl.json()
    assert (s["answered"], s["stale_measurements"], s["ended"]) == (4, 1, "stopped"), s
    assert s["rejected_measurements"] == 7, s        # 5 malformed, 1e60 beyond the bound, the doubtful end
    assert s["missing_measurements"] == 2 + 1, s     # seqs 3, 4 skipped; seq 6 counted by the end, never sent
    said = [ln for ln in ctl.err if "skipped a measurement" in ln]
    assert len(said) == 1 and all(len(ln) < 400 for ln in ctl.err), ctl.err
    assert "ended (stopped) after 7 samples: answered 4" in ctl.stderr_text()


def test_the_stop_without_a_stream_leaves_a_clean_summary(spawn):
    """SIGINT before any measurement: exit 0, nothing answered, no recorder asked."""
    ctl = spawn("control", "control", "seed-closed", "--listen", ep(free_port()), "--json")
    ctl.wait_line(READY_MARK)
    assert ctl.interrupt(T_EVENT) == 0, ctl.stderr_text()
    s = ctl.json()
    assert s["answered"] == 0 and s["ended"] is None and s["recorders"] == {} and s["health_messages"] == 1
    assert math.isfinite(s["wall_s"])
