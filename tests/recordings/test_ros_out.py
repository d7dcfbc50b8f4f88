"""`simulate`'s output: the rosbag2 bag (noiselab.recordings.rosbag_out) and the wall-clock anchor of both
formats (noiselab.recordings.simulated). Real files: written, then read back with rosbags and mcap."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML

from noiselab import wire
from noiselab.errors import BadInput
from noiselab.model import load_model, parse_model
from noiselab.recordings import rosbag_out
from noiselab.recordings.simulated import write_simulation

STORE = get_typestore(Stores.ROS2_JAZZY)
START = 1_700_000_000_123_456_789           # a wall-clock anchor, ns since the Unix epoch

_EYE6 = "[" + ", ".join("[" + ", ".join("1.0" if i == j else "0.0" for j in range(6)) + "]"
                        for i in range(6)) + "]"
# six first-order states read one by one, outputs named as an IMU's: the bag's Imu message
IMU = f"""
name = "imu6"
[sampling]
Ts = 0.005
[plant]
A = {_EYE6.replace("1.0", "-2.0")}
B = {_EYE6}
C = {_EYE6}
[outputs]
names = ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
units = ["rad/s", "rad/s", "rad/s", "m/s^2", "m/s^2", "m/s^2"]
[command]
kind = "sine"
amplitude = 0.3
frequency_hz = 1.5
[process.white]
std = 0.05
[sensor.white]
std = [1e-3, 2e-3, 3e-3, 4e-3, 5e-3, 6e-3]
"""

# a plant that diverges (x grows as exp(t)): past ~70 000 samples at Ts = 0.01 it overflows to inf,
# in the second block of simulate_blocks (65 536 samples each)
DIVERGING = """
name = "boom"
[sampling]
Ts = 0.01
[plant]
A = [[1.0]]
B = [[1.0]]
C = [[1.0]]
[command]
kind = "none"
[process.white]
std = 1.0
"""

T = STORE.types
Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]


def _header(sec, nanosec, frame):
    return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame)


def _cdr(msg) -> bytes:
    return bytes(STORE.serialize_cdr(msg, msg.__msgtype__))


# -- the block encoder is byte for byte rosbags' serializer ----------------------------------------
_f64 = st.floats(allow_nan=False, allow_infinity=True, width=64)
_names = st.lists(st.text(st.characters(codec="utf-8", exclude_characters="\0"), max_size=9),
                  min_size=0, max_size=5)


@given(frame=st.text(st.characters(codec="utf-8", exclude_characters="\0"), max_size=11),
       sec=st.lists(st.integers(0, 2**31 - 1), min_size=1, max_size=4),
       data=st.data())
def test_imu_block_is_rosbags_cdr(frame, sec, data):
    n = len(sec)
    nanosec = data.draw(st.lists(st.integers(0, 999_999_999), min_size=n, max_size=n))
    cg = data.draw(st.lists(_f64, min_size=3, max_size=3))
    ca = data.draw(st.lists(_f64, min_size=3, max_size=3))
    vals = np.array(data.draw(st.lists(_f64, min_size=6 * n, max_size=6 * n))).reshape(n, 6)
    lay = rosbag_out.imu_layout(cg, ca, frame)
    got = lay.encode(np.array(sec), np.array(nanosec), angular_velocity=vals[:, :3],
                     linear_acceleration=vals[:, 3:])
    V3, Q, Imu = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"], T[rosbag_out.MSG_IMU]
    for i in range(n):
        oc = np.zeros(9)
        oc[0] = -1.0
        msg = Imu(header=_header(sec[i], nanosec[i], frame), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
                  orientation_covariance=oc, angular_velocity=V3(*vals[i, :3]),
                  angular_velocity_covariance=np.diag(cg).ravel(),
                  linear_acceleration=V3(*vals[i, 3:]),
                  linear_acceleration_covariance=np.diag(ca).ravel())
        assert got[i].tobytes() == _cdr(msg)


@given(frame=st.text(st.characters(codec="utf-8", exclude_characters="\0"), max_size=11),
       names=_names, field=st.sampled_from(["position", "effort"]),
       sec=st.lists(st.integers(0, 2**31 - 1), min_size=1, max_size=4), data=st.data())
def test_joint_state_block_is_rosbags_cdr(frame, names, field, sec, data):
    n, d = len(sec), len(names)
    nanosec = data.draw(st.lists(st.integers(0, 999_999_999), min_size=n, max_size=n))
    vals = np.array(data.draw(st.lists(_f64, min_size=n * d, max_size=n * d))).reshape(n, d)
    lay = rosbag_out.joint_state_layout(names, field, frame)
    got = lay.encode(np.array(sec), np.array(nanosec), **({field: vals} if d else {}))
    JS = T[rosbag_out.MSG_JOINT_STATE]
    empty = np.zeros(0)
    for i in range(n):
        arrays = {f: (vals[i] if f == field else empty) for f in ("position", "velocity", "effort")}
        msg = JS(header=_header(sec[i], nanosec[i], frame), name=list(names), **arrays)
        assert got[i].tobytes() == _cdr(msg)


# -- the bag, read back ------------------------------------------------------------------------
def _read_bag(path: Path):
    """Per topic: msgtype, stamps (header and bag timestamp), deserialized messages."""
    out = {}
    with AnyReader([path]) as r:
        for c in r.connections:
            out[c.topic] = {"type": c.msgtype, "count": c.msgcount, "ts": [], "stamp": [], "msgs": []}
        for c, ts, raw in r.messages():
            m = r.deserialize(raw, c.msgtype)
            o = out[c.topic]
            o["ts"].append(ts)
            o["stamp"].append(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)
            o["msgs"].append(m)
    return out


def _mcap_header_and_meta(path: Path):
    with open(path, "rb") as f:
        r = make_reader(f)
        header = r.get_header()
        meta = {m.name: dict(m.metadata) for m in r.iter_metadata()}
        schemas = {s.name: s.encoding for s in r.get_summary().schemas.values()}
        enc = {c.message_encoding for c in r.get_summary().channels.values()}
    return header, meta, schemas, enc


@pytest.mark.slow
def test_imu_bag_round_trip_is_exact(tmp_path):
    model = parse_model(IMU, "imu6.toml")
    n, seed = 65_600, 11                          # two blocks of simulate_blocks (65 536 each)
    bag = tmp_path / "imu_bag"
    rep = write_simulation(model, n, seed, bag, fmt="ros2", start_time_ns=START)
    assert rep["messages"] == {f"/imu6/{k}": n for k in ("truth", "command", "measurement")}
    assert sorted(p.name for p in bag.iterdir()) == ["imu_bag.mcap", "metadata.yaml"]

    rec = model.simulate(n, seed=seed)
    stamps = np.array([START + round(k * model.Ts * 1e9) for k in range(n)])      # the anchor contract
    got = _read_bag(bag)
    assert {t: (g["type"], g["count"]) for t, g in got.items()} == {
        "/imu6/measurement": ("sensor_msgs/msg/Imu", n),
        "/imu6/truth": ("sensor_msgs/msg/JointState", n),
        "/imu6/command": ("sensor_msgs/msg/JointState", n)}
    for g in got.values():
        assert np.array_equal(np.array(g["ts"]), stamps) and np.array_equal(np.array(g["stamp"]), stamps)
        assert {m.header.frame_id for m in g["msgs"]} == {rosbag_out.FRAME_ID}

    meas = got["/imu6/measurement"]["msgs"]
    gyro = np.array([[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for m in meas])
    acc = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]
                    for m in meas])
    assert np.array_equal(np.hstack([gyro, acc]), rec.y)       # bit for bit
    m0 = meas[0]
    assert m0.orientation_covariance[0] == -1.0                 # REP 145: no orientation
    var = model.predictor().steady_state().var_y
    assert np.array_equal(np.diag(m0.angular_velocity_covariance.reshape(3, 3)), var[:3])
    assert np.array_equal(np.diag(m0.linear_acceleration_covariance.reshape(3, 3)), var[3:])
    assert var[0] > 1e-6                                        # the white noise is in it

    truth = got["/imu6/truth"]["msgs"]
    assert list(truth[0].name) == list(model.plant.state_names)
    assert np.array_equal(np.array([m.position for m in truth]), rec.x)
    cmd = got["/imu6/command"]["msgs"]
    assert list(cmd[0].name) == [f"u{i}" for i in range(6)]
    assert np.array_equal(np.array([m.effort for m in cmd]), rec.u)
    assert len(cmd[0].position) == 0 and len(cmd[0].velocity) == 0

    # the file is a ROS 2 MCAP: profile, CDR, ros2msg schemas; the run is in custom_data
    header, meta, schemas, enc = _mcap_header_and_meta(bag / "imu_bag.mcap")
    assert header.profile == "ros2" and enc == {"cdr"}
    assert schemas == {"sensor_msgs/msg/Imu": "ros2msg", "sensor_msgs/msg/JointState": "ros2msg"}
    assert "rosbag2" in meta
    info = YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap"
    custom = info["custom_data"]
    in_mcap = YAML(typ="safe").load(meta["rosbag2"]["serialized_metadata"])
    assert in_mcap["custom_data"] == custom
    assert custom["noiselab.seed"] == str(seed) and custom["noiselab.start_time_ns"] == str(START)
    assert custom["noiselab.samples"] == str(n)
    again = parse_model(custom["noiselab.model_toml"], "from the bag")
    assert np.array_equal(again.simulate(200, seed=seed).y, rec.y[:200])


def test_plain_model_bag_is_joint_state(tmp_path):
    model = load_model("seed")
    n = 500
    bag = tmp_path / "seed_bag"
    write_simulation(model, n, 4, bag, fmt="ros2", start_time_ns=START)
    got = _read_bag(bag)
    rec = model.simulate(n, seed=4)
    meas = got["/seed/measurement"]
    assert meas["type"] == "sensor_msgs/msg/JointState" and meas["count"] == n
    assert list(meas["msgs"][0].name) == list(model.output_names) == ["position"]
    assert np.array_equal(np.array([m.position for m in meas["msgs"]]), rec.y)
    assert list(got["/seed/truth"]["msgs"][0].name) == ["position", "velocity"]
    assert np.array_equal(np.array([m.position for m in got["/seed/truth"]["msgs"]]), rec.x)


def test_topic_names_are_ros_2_names(tmp_path):
    assert [rosbag_out.ros_token(x) for x in ("imu-nominal", "seed", "a--b__c", "9axis")] == \
        ["imu_nominal", "seed", "a_b_c", "_9axis"]
    model = parse_model(IMU.replace('name = "imu6"', 'name = "imu-6"'), "imu-6.toml")
    write_simulation(model, 5, 0, tmp_path / "bag", fmt="ros2")
    assert sorted(_read_bag(tmp_path / "bag")) == [f"/imu_6/{k}" for k in ("command", "measurement", "truth")]


def test_imu_axes_convention():
    assert rosbag_out.imu_axes(["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]) == \
        ([0, 1, 2], [3, 4, 5])
    assert rosbag_out.imu_axes(["accel_x", "gyro_x", "accel_y", "gyro_y", "accel_z", "gyro_z"]) == \
        ([1, 3, 5], [0, 2, 4])
    assert rosbag_out.imu_axes(["gyro_x", "gyro_y", "gyro_z"]) is None              # not a 6-axis IMU
    assert rosbag_out.imu_axes(["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "temp"]) is None


# -- the JSON MCAP's wall-clock anchor ---------------------------------------------------------------
def test_json_mcap_is_anchored_at_the_start(tmp_path):
    model = load_model("seed")
    n, seed = 300, 2
    out = tmp_path / "run.mcap"
    rep = write_simulation(model, n, seed, out, start_time_ns=START)
    assert rep["start_time_ns"] == START and rep["format"] == "mcap"
    rec = model.simulate(n, seed=seed)
    with open(out, "rb") as f:
        r = make_reader(f)
        meta = {m.name: dict(m.metadata) for m in r.iter_metadata()}
        seen = {}
        for _s, ch, msg in r.iter_messages(log_time_order=False):
            kind = ch.topic.rsplit("/", 1)[1]
            k = seen.setdefault(kind, 0)
            assert msg.publish_time - START == round(k * model.Ts * 1e9) == msg.log_time - START
            vec = {"truth": rec.x, "command": rec.u, "measurement": rec.y}[kind][k]
            # the payload keeps t in s from the start, and is the wire encoder's bytes
            assert msg.data == wire.encode(k, k * model.Ts, vec, kind=kind)
            assert json.loads(msg.data)["t"] == k * model.Ts
            seen[kind] = k + 1
    assert seen == {"truth": n, "command": n, "measurement": n}
    nl = meta["noiselab"]
    assert nl["start_time_ns"] == str(START) and nl["seed"] == str(seed) and nl["samples"] == str(n)
    assert parse_model(nl["model_toml"], "meta").to_toml() == model.to_toml()


def test_anchor_defaults_to_now(tmp_path):
    import time
    before = time.time_ns()
    rep = write_simulation(load_model("seed"), 10, 0, tmp_path / "b", fmt="ros2")
    assert before <= rep["start_time_ns"] <= time.time_ns()
    got = _read_bag(tmp_path / "b")
    assert got["/seed/measurement"]["ts"][0] == rep["start_time_ns"]


# -- a bad --out ---------------------------------------------------------------------------------
def _bag_stamps(bag: Path) -> list[int]:
    return _read_bag(bag)["/seed/measurement"]["ts"]


def test_existing_out_needs_force_and_force_replaces(tmp_path):
    model = load_model("seed")
    bag = tmp_path / "bag"
    write_simulation(model, 20, 0, bag, fmt="ros2", start_time_ns=START)
    with pytest.raises(BadInput, match="already exists .*--force"):
        write_simulation(model, 30, 0, bag, fmt="ros2", start_time_ns=START)
    assert len(_bag_stamps(bag)) == 20
    write_simulation(model, 30, 0, bag, fmt="ros2", force=True, start_time_ns=START + 1)
    st = _bag_stamps(bag)
    assert len(st) == 30 and st[0] == START + 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag"]           # no staging left
    # a file in the bag's place: refused, then replaced with --force
    f = tmp_path / "file"
    f.write_text("not a bag")
    with pytest.raises(BadInput, match="already exists"):
        write_simulation(model, 5, 0, f, fmt="ros2")
    write_simulation(model, 5, 0, f, fmt="ros2", force=True)
    assert f.is_dir() and len(_bag_stamps(f)) == 5


def test_force_never_replaces_a_directory_that_is_not_a_bag(tmp_path):
    d = tmp_path / "mydata"
    d.mkdir()
    (d / "precious.txt").write_text("keep me")
    with pytest.raises(BadInput, match="not a rosbag2 bag"):
        write_simulation(load_model("seed"), 5, 0, d, fmt="ros2", force=True)
    assert (d / "precious.txt").read_text() == "keep me"


def test_a_failed_write_keeps_the_old_bag(tmp_path):
    bag = tmp_path / "bag"
    write_simulation(load_model("seed"), 20, 0, bag, fmt="ros2", start_time_ns=START)
    before = {p.name: p.read_bytes() for p in bag.iterdir()}
    with pytest.raises(BadInput, match=r"/boom/truth: x\[0\]=.* at sample \d+ is not finite"):
        write_simulation(parse_model(DIVERGING, "boom.toml"), 80_000, 1, bag, fmt="ros2", force=True)
    assert {p.name: p.read_bytes() for p in bag.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag"]           # the unfinished one is gone
    # and a new bag that fails leaves nothing
    with pytest.raises(BadInput, match="not finite"):
        write_simulation(parse_model(DIVERGING, "boom.toml"), 80_000, 1, tmp_path / "new", fmt="ros2")
    assert not (tmp_path / "new").exists()


def test_unfinished_staging_is_refused_not_overwritten(tmp_path):
    (tmp_path / "bag.partial").mkdir()
    with pytest.raises(BadInput, match=r"bag\.partial: exists"):
        write_simulation(load_model("seed"), 5, 0, tmp_path / "bag", fmt="ros2")
    assert (tmp_path / "bag.partial").is_dir() and not (tmp_path / "bag").exists()


def test_unknown_format_is_bad_input(tmp_path):
    with pytest.raises(BadInput, match="--format 'rosbag'"):
        write_simulation(load_model("seed"), 5, 0, tmp_path / "x", fmt="rosbag")
    assert not os.listdir(tmp_path)


# a 6-axis IMU at rest without [plant]: each output is the reference (the command) + sensor effects
IMU_AT_REST = """
name = "imu"
[sampling]
Ts = 0.005
[outputs]
names = ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
units = ["rad/s", "rad/s", "rad/s", "m/s^2", "m/s^2", "m/s^2"]
[command]
kind = "none"
[sensor.white]
density = [1.7e-4, 1.7e-4, 1.7e-4, 2.0e-3, 2.0e-3, 2.0e-3]
[sensor.bias_walk]
std = [1.9e-5, 1.9e-5, 1.9e-5, 3.0e-3, 3.0e-3, 3.0e-3]
"""


def test_sensor_only_imu_has_no_truth_topic(tmp_path):
    model = parse_model(IMU_AT_REST, "imu.toml")
    n = 400
    write_simulation(model, n, 9, tmp_path / "bag", fmt="ros2", start_time_ns=START)
    got = _read_bag(tmp_path / "bag")
    assert sorted(got) == ["/imu/command", "/imu/measurement"]       # no state, no truth
    rec = model.simulate(n, seed=9)
    meas = got["/imu/measurement"]["msgs"]
    y = np.array([[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z,
                   m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z] for m in meas])
    assert np.array_equal(y, rec.y)
    # the covariance: the white noise's per-sample variance density^2 / Ts (+ the bias' initial spread)
    cov = np.diag(meas[0].angular_velocity_covariance.reshape(3, 3))
    assert np.all(cov >= (1.7e-4) ** 2 / model.Ts)


def test_noiselab_reads_its_own_bag_back(tmp_path):
    """What `simulate --format ros2` writes, `analyze`/`diagnose` read back: the IMU's six axes bit
    for bit, the time from header.stamp (s from the first sample)."""
    from noiselab.recordings.load import load_recording

    model = parse_model(IMU, "imu6.toml")
    n = 3000
    write_simulation(model, n, 5, tmp_path / "bag", fmt="ros2", start_time_ns=START)
    s = load_recording(str(tmp_path / "bag"), spec="/imu6/measurement:angular_velocity.*,linear_acceleration.*",
                       model=model)
    assert np.array_equal(s.y, model.simulate(n, seed=5).y)
    assert s.names == [f"{v}.{a}" for v in ("angular_velocity", "linear_acceleration") for a in "xyz"]
    assert np.allclose(s.t, np.arange(n) * model.Ts, rtol=0, atol=1e-12)
    truth = load_recording(str(tmp_path / "bag"), spec="/imu6/truth:position.*", model=model)
    assert np.array_equal(truth.y, model.simulate(n, seed=5).x)


def test_json_mcap_payloads_are_the_wire_encoders_over_blocks(tmp_path):
    model = load_model("seed")
    n = 70_000                                    # two blocks of simulate_blocks
    write_simulation(model, n, 3, tmp_path / "run.mcap", start_time_ns=START)
    rec = model.simulate(n, seed=3)
    t, _ = wire.sample_times(0, n, model.Ts)
    want = wire.encode_batch("measurement", 0, t, rec.y)
    with open(tmp_path / "run.mcap", "rb") as f:
        got = [m.data for _s, _c, m in make_reader(f).iter_messages(topics=["noiselab/seed/measurement"],
                                                                     log_time_order=False)]
    assert got == want


def test_json_mcap_refuses_a_diverging_sample_in_one_line(tmp_path):
    with pytest.raises(wire.WireError, match=r"noiselab/boom/truth: x\[0\]=-?inf at seq \d+ is not finite"):
        write_simulation(parse_model(DIVERGING, "boom.toml"), 80_000, 1, tmp_path / "boom.mcap")
