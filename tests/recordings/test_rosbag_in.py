"""ROS bags in: rosbag2 (MCAP and SQLite3 storage, a bag directory, a split bag, one storage file)
and ROS 1 bags, written here with rosbags' own writers, read by ``analyze``, ``diagnose``, the
loader (``noiselab.recordings.load``) and ``replay``.

What is checked: field paths (``a.b``, ``[i]``, a final ``.*``, comma lists), time (header.stamp
in exact integer ns by default, ``--time`` on a Time or a numeric field, the log time without a
header), every bad input as one line and exit 2 naming the topic and the message type, the
checks foreign series pass (NaN, timing, gaps), the JSON MCAP paths unchanged and their
``{sec, nanosec}`` stamps, and the replay of a bag as JSON over a real Zenoh session.
"""

from __future__ import annotations

import json
import shutil
import sqlite3
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import zenoh
from helpers.cli import assert_bad
from helpers.cli import cli_in_process as cli
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from ruamel.yaml import YAML

from noiselab.cli import main
from noiselab.nodes.replay import replay_topics, run_replay
from noiselab.nodes.runner import free_port
from noiselab.recordings import load, rosbag_in, series

TS_NS = 10_000_000                              # 100 Hz
START_NS = 1_700_000_000_123_456_789            # an epoch stamp whose last digits float64 ns cannot hold
N = 600
T_EVENT = 30.0

SAMPLE_MSG = "float64 value\nint64 t_ns\nfloat64 t_s\nbuiltin_interfaces/Time when\nstring label\n"
STORE = get_typestore(Stores.ROS2_JAZZY)
STORE.register(get_types_from_msg(SAMPLE_MSG, "noiselab_test/msg/Sample"))
STORE1 = get_typestore(Stores.ROS1_NOETIC)
T = STORE.types
Imu, Header, Time = T["sensor_msgs/msg/Imu"], T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
V3, Quat = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
JointState, Float64, Sample = T["sensor_msgs/msg/JointState"], T["std_msgs/msg/Float64"], T["noiselab_test/msg/Sample"]

GYRO_MODEL = """
name = "gyro-x"
[sampling]
Ts = 0.01
[plant]              # no dynamics: the sensor's own noise is all there is (y = 0 + sensor effects)
A = [[-1.0]]
B = [[0.0]]
C = [[0.0]]
[command]
kind = "none"
[sensor.white]
std = 0.01
"""


def stamps(n: int = N) -> np.ndarray:
    """Header stamps at 100 Hz from START_NS, each off the grid by a few ns (exactness shows)."""
    return START_NS + np.arange(n, dtype=np.int64) * TS_NS + (np.arange(n, dtype=np.int64) * 7919) % 13


def time_of(ns: int):
    return Time(int(ns // 1_000_000_000), int(ns % 1_000_000_000))


def imu_messages(n: int = N, seed: int = 0, st=None, walk: float = 0.0) -> tuple[list, dict]:
    """(log time, Imu) pairs: gyro white noise (std 0.01) plus a bias walk of ``walk`` units/sqrt(s),
    accel about gravity, covariances 0..8; and the arrays written."""
    rng = np.random.default_rng(seed)
    st = stamps(n) if st is None else st
    gyro = rng.normal(0.0, 0.01, (n, 3))
    gyro[:, 0] += np.cumsum(rng.normal(0.0, walk * np.sqrt(TS_NS * 1e-9), n))
    acc = rng.normal(0.0, 0.02, (n, 3)) + [0.0, 0.0, 9.81]
    cov = np.arange(9.0)
    msgs = [(int(st[k]) + 400_000, Imu(Header(time_of(st[k]), "imu"), Quat(0.0, 0.0, 0.0, 1.0), cov.copy(),
                                       V3(*gyro[k]), cov.copy(), V3(*acc[k]), cov.copy())) for k in range(n)]
    return msgs, {"gyro": gyro, "acc": acc, "stamps": st}


def joint_messages(n: int = N) -> tuple[list, np.ndarray]:
    pos = np.random.default_rng(5).normal(0.0, 1e-3, (n, 3)) + [0.1, 0.2, 0.3]
    st = stamps(n)
    return [(int(st[k]), JointState(Header(time_of(st[k]), ""), ["a", "b", "c"], pos[k].copy(), np.zeros(0),
                                    np.zeros(0))) for k in range(n)], pos


def write_bag(path: Path, topics: dict, storage: str = "mcap") -> Path:
    """A rosbag2 bag (directory) of ``topics`` {name: (msgtype, [(log ns, message), ...])}."""
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = {name: w.add_connection(name, msgtype, typestore=STORE) for name, (msgtype, _) in topics.items()}
        merged = sorted((log, name, msg) for name, (_, items) in topics.items() for log, msg in items)
        for log, name, msg in merged:
            w.write(conns[name], log, STORE.serialize_cdr(msg, topics[name][0]))
    return path


def storage_file(bag: Path) -> Path:
    (f,) = [p for p in bag.iterdir() if p.suffix in (".mcap", ".db3")]
    return f






@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> dict:
    """The bags most tests read: one IMU + joint states + a header-less topic + a custom type, in
    MCAP and in SQLite3 storage."""
    d = tmp_path_factory.mktemp("bags")
    imu, arrays = imu_messages()
    joints, pos = joint_messages()
    st = stamps()
    plain = [(int(st[k]) + 1_000 * k, Float64(float(k) * 0.5)) for k in range(N)]   # log times off a grid
    samples = [(int(st[k]), Sample(float(k), int(st[k]) + 5, (st[k] - START_NS) * 1e-9 + 100.0, time_of(st[k] + 3),
                                   f"s{k}")) for k in range(N)]
    topics = {"/imu": ("sensor_msgs/msg/Imu", imu), "/joint_states": ("sensor_msgs/msg/JointState", joints),
              "/plain": ("std_msgs/msg/Float64", plain), "/sample": ("noiselab_test/msg/Sample", samples)}
    out = {"arrays": arrays, "pos": pos, "plain_log": np.array([log for log, _ in plain], np.int64),
           "stamps": st, "dir": d}
    for storage in ("mcap", "sqlite3"):
        out[storage] = write_bag(d / f"bag_{storage}", topics, storage)
    return out


def read(path, spec: str, time_field: str | None = None, Ts: float | None = 0.01) -> series.Series:
    return load.load_recording(str(path), spec=spec, time_field=time_field, Ts=Ts)


# -- 1. what a bag is -------------------------------------------------------------------------------------
def test_bag_kinds_are_told_from_their_first_bytes(bags, tmp_path):
    """A bag directory, its MCAP (ros2 profile) and SQLite3 files, a ROS 1 bag are ROS bags; a
    noiselab (JSON) MCAP, a directory without metadata.yaml, a missing file are not."""
    assert rosbag_in.bag_kind(bags["mcap"]) == "rosbag2 directory"
    assert rosbag_in.bag_kind(storage_file(bags["mcap"])) == "rosbag2 MCAP file"
    assert rosbag_in.bag_kind(storage_file(bags["sqlite3"])) == "rosbag2 SQLite3 file"
    ros1 = write_ros1(tmp_path / "r.bag", 10)
    assert rosbag_in.bag_kind(ros1) == "ROS 1 bag"
    json_mcap = tmp_path / "j.mcap"
    assert main(["simulate", "seed", "--duration", "0.1", "--out", str(json_mcap)]) == 0
    assert rosbag_in.bag_kind(json_mcap) is None
    (tmp_path / "empty_dir").mkdir()
    assert rosbag_in.bag_kind(tmp_path / "empty_dir") is None and rosbag_in.bag_kind(tmp_path / "absent") is None


# -- 2. field paths and time ----------------------------------------------------------------------------------
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("which", ["directory", "file"])
def test_a_field_and_its_header_stamp_exactly(bags, storage, which):
    """/imu:angular_velocity.x: the values written, in order; time from header.stamp as
    sec * 10^9 + nanosec in integer ns, exactly (the stamps carry odd ns a float64 epoch would
    round to 256 ns), with no note about time."""
    path = bags[storage] if which == "directory" else storage_file(bags[storage])
    got = rosbag_in.read_fields(str(path), "/imu", [("angular_velocity.x", ("angular_velocity", "x"))])
    assert got.time.dtype == np.int64 and np.array_equal(got.time, bags["stamps"])
    assert got.time_source == "header.stamp" and got.notes == []
    assert np.array_equal(got.values[:, 0], bags["arrays"]["gyro"][:, 0])
    s = read(path, "/imu:angular_velocity.x")
    assert np.array_equal(s.y[:, 0], bags["arrays"]["gyro"][:, 0]) and s.names == ["angular_velocity.x"]
    assert np.array_equal(s.t, (bags["stamps"] - bags["stamps"][0]).astype(float) * 1e-9)
    assert s.Ts == 0.01 and not [n for n in s.notes if "time" in n], s.notes


def test_wildcards_indices_and_lists(bags):
    """``.*`` of a Vector3 is x, y, z in definition order; of a float64[9] its 9 items; of a
    float64[] sequence its items (length from the first message); ``[i]`` picks one; comma lists
    keep their order; a topic named without its leading '/' is found."""
    a = bags["arrays"]
    s = read(bags["mcap"], "/imu:linear_acceleration.*")
    assert s.names == ["linear_acceleration.x", "linear_acceleration.y", "linear_acceleration.z"]
    assert np.array_equal(s.y, a["acc"])
    s = read(bags["mcap"], "imu:orientation_covariance.*")
    assert s.names == [f"orientation_covariance[{j}]" for j in range(9)] and np.array_equal(s.y[0], np.arange(9.0))
    s = read(bags["mcap"], "/imu:angular_velocity.z,angular_velocity.x,orientation_covariance[4]")
    assert np.array_equal(s.y, np.column_stack([a["gyro"][:, 2], a["gyro"][:, 0], np.full(N, 4.0)]))
    s = read(bags["sqlite3"], "/joint_states:position[2]")
    assert np.array_equal(s.y[:, 0], bags["pos"][:, 2])
    s = read(bags["sqlite3"], "/joint_states:position.*")
    assert s.names == ["position[0]", "position[1]", "position[2]"] and np.array_equal(s.y, bags["pos"])
    s = read(bags["mcap"], "/imu:header.*", Ts=None)         # the numbers of a header: stamp.sec, stamp.nanosec
    assert s.names == ["header.stamp.sec", "header.stamp.nanosec"]


def test_time_from_a_field_or_the_log_time(bags):
    """--time on a builtin_interfaces/msg/Time field: exact ns; on an int64 field ending in _ns:
    ns; on a float64 field: seconds; a message without a header: the bag's log time, said in a
    note; --time header.stamp named explicitly is the default's time."""
    st = bags["stamps"]
    got = rosbag_in.read_fields(str(bags["mcap"]), "/sample", [("value", ("value",))], ("when", ("when",)))
    assert got.time_ns and np.array_equal(got.time, st + 3)
    s = read(bags["mcap"], "/sample:value", "when")
    assert np.array_equal(s.t, (st - st[0]).astype(float) * 1e-9)
    s = read(bags["mcap"], "/sample:value", "t_ns")
    assert np.array_equal(s.t, (st - st[0]).astype(float) * 1e-9)
    s = read(bags["mcap"], "/sample:value", "t_s")
    assert np.allclose(s.t, (st - st[0]) * 1e-9, rtol=0, atol=1e-9)
    s = read(bags["mcap"], "/plain:data")
    log = bags["plain_log"]
    assert np.array_equal(s.t, (log - log[0]).astype(float) * 1e-9)
    assert any("has no header.stamp: time from the bag's log time" in n and "std_msgs/msg/Float64" in n
               for n in s.notes), s.notes
    assert np.array_equal(read(bags["mcap"], "/imu:angular_velocity.x", "header.stamp").t,
                          read(bags["mcap"], "/imu:angular_velocity.x").t)


def test_header_stamps_left_zero_fall_back_to_the_log_time(tmp_path):
    """A driver that never fills header.stamp (0 in every message): the log time, and a note."""
    msgs, _ = imu_messages(200, st=np.zeros(200, np.int64))
    msgs = [(START_NS + k * TS_NS, m) for k, (_, m) in enumerate(msgs)]
    bag = write_bag(tmp_path / "zero", {"/imu": ("sensor_msgs/msg/Imu", msgs)})
    s = read(bag, "/imu:angular_velocity.x")
    assert np.allclose(s.t, np.arange(200) * 0.01, rtol=0, atol=1e-12)
    assert any("header.stamp is 0 ns in every message: time from the bag's log time" in n for n in s.notes), s.notes


def test_without_a_model_the_period_is_the_median_step(bags):
    """load_recording(Ts=None, model=None), as the allan command calls it: Series.Ts is the
    record's median step, said in a note."""
    s = read(bags["mcap"], "/imu:angular_velocity.x", Ts=None)
    assert abs(s.Ts - 0.01) < 1e-8
    assert any("no model: the sample period is the record's median step, Ts = 0.01 s" in n for n in s.notes), s.notes


def test_a_split_bag_directory_reads_as_one(tmp_path):
    """A bag split in two storage files (as ``ros2 bag record --max-bag-size`` writes it: one
    metadata.yaml listing both): every message, in order."""
    msgs, arrays = imu_messages(400)
    halves = [write_bag(tmp_path / f"part{i}", {"/imu": ("sensor_msgs/msg/Imu", msgs[i * 200:(i + 1) * 200])})
              for i in (0, 1)]
    bag = tmp_path / "split"
    bag.mkdir()
    yaml = YAML(typ="safe")
    metas = [yaml.load((h / "metadata.yaml").read_text())["rosbag2_bagfile_information"] for h in halves]
    for i, h in enumerate(halves):
        shutil.move(storage_file(h), bag / f"split_{i}.mcap")
    meta = metas[0]
    meta["relative_file_paths"] = ["split_0.mcap", "split_1.mcap"]
    meta["files"] = [dict(m["files"][0], path=f"split_{i}.mcap") for i, m in enumerate(metas)]
    meta["message_count"] = 400
    meta["topics_with_message_count"][0]["message_count"] = 400
    meta["duration"]["nanoseconds"] = (metas[1]["starting_time"]["nanoseconds_since_epoch"]
                                       + metas[1]["duration"]["nanoseconds"]
                                       - meta["starting_time"]["nanoseconds_since_epoch"])
    with open(bag / "metadata.yaml", "w") as f:
        yaml.dump({"rosbag2_bagfile_information": meta}, f)
    s = read(bag, "/imu:angular_velocity.y")
    assert np.array_equal(s.y[:, 0], arrays["gyro"][:, 1])
    assert np.array_equal(s.t, (arrays["stamps"] - arrays["stamps"][0]).astype(float) * 1e-9)


def write_ros1(path: Path, n: int = N, seed: int = 0) -> Path:
    """A ROS 1 bag of sensor_msgs/Imu on /imu (ROS 1 serialization, its own type store)."""
    T1 = STORE1.types
    Imu1, Header1, Time1 = T1["sensor_msgs/msg/Imu"], T1["std_msgs/msg/Header"], T1["builtin_interfaces/msg/Time"]
    V31, Quat1 = T1["geometry_msgs/msg/Vector3"], T1["geometry_msgs/msg/Quaternion"]
    msgs, _ = imu_messages(n, seed)
    with Writer1(path) as w:
        conn = w.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=STORE1)
        for k, (log, m) in enumerate(msgs):
            st = m.header.stamp
            m1 = Imu1(Header1(k, Time1(st.sec, st.nanosec), "imu"), Quat1(0.0, 0.0, 0.0, 1.0), np.zeros(9),
                      V31(m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z), np.zeros(9),
                      V31(m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z), np.zeros(9))
            w.write(conn, log, STORE1.serialize_ros1(m1, "sensor_msgs/msg/Imu"))
    return path


def test_a_ros1_bag(tmp_path):
    """rosbags' ROS 1 writer's bag: the same fields and exact header stamps (a ROS 1 header has a
    seq too)."""
    bag = write_ros1(tmp_path / "imu.bag")
    _, arrays = imu_messages(N, 0)
    s = read(bag, "/imu:angular_velocity.x,linear_acceleration.z")
    assert np.array_equal(s.y, np.column_stack([arrays["gyro"][:, 0], arrays["acc"][:, 2]]))
    got = rosbag_in.read_fields(str(bag), "/imu", [("angular_velocity.x", ("angular_velocity", "x"))])
    assert got.time_source == "header.stamp" and np.array_equal(got.time, arrays["stamps"])


# -- 3. JSON MCAP: unchanged, and its {sec, nanosec} stamps ----------------------------------------------------
def json_mcap(path: Path, messages: list[tuple[int, dict]]) -> Path:
    from mcap.writer import Writer as McapWriter

    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start(profile="", library="noiselab tests")
        sid = w.register_schema(name="Imu", encoding="jsonschema", data=b'{"type": "object"}')
        cid = w.register_channel(topic="/imu", message_encoding="json", schema_id=sid)
        for i, (pub, obj) in enumerate(messages):
            w.add_message(channel_id=cid, log_time=pub, publish_time=pub, data=json.dumps(obj).encode(), sequence=i)
        w.finish()
    return path


def test_json_mcap_time_from_a_sec_nanosec_stamp(tmp_path):
    """A JSON copy of an Imu topic: --time header.stamp ({sec, nanosec} objects) gives exact ns
    (it was refused, the object not being a number); ``.*`` expands in key order; publish_time
    stays the default."""
    st = stamps(300)
    gyro = np.random.default_rng(2).normal(0, 0.01, (300, 3))
    msgs = [(k * 10_000_000 + 77, {"header": {"stamp": {"sec": int(st[k] // 10**9), "nanosec": int(st[k] % 10**9)},
                                              "frame_id": "imu"},
                                   "angular_velocity": dict(zip("xyz", gyro[k].tolist())), "ok": True})
            for k in range(300)]
    path = json_mcap(tmp_path / "imu_json.mcap", msgs)
    s = read(path, "/imu:angular_velocity.x", "header.stamp")
    assert np.array_equal(s.t, (st - st[0]).astype(float) * 1e-9) and np.array_equal(s.y[:, 0], gyro[:, 0])
    s = read(path, "/imu:angular_velocity.*", "header.stamp")
    assert s.names == ["angular_velocity.x", "angular_velocity.y", "angular_velocity.z"] and np.array_equal(s.y, gyro)
    s = read(path, "/imu:angular_velocity.x")
    assert np.allclose(s.t, np.arange(300) * 0.01, rtol=0, atol=1e-12)
    msgs[7][1]["header"]["stamp"] = {"sec": 1}
    bad = json_mcap(tmp_path / "bad_stamp.mcap", msgs)
    with pytest.raises(ValueError, match=r"/imu: sample 7: header.stamp = \{'sec': 1\} is not a \{sec, nanosec\}"):
        read(bad, "/imu:angular_velocity.x", "header.stamp")


# -- 4. end to end: analyze and diagnose a bag ---------------------------------------------------------------
@pytest.fixture(scope="module")
def gyro_bag(tmp_path_factory) -> tuple[Path, Path]:
    """5000 samples (50 s at 100 Hz) of a gyro at rest: white noise 0.01 and a bias walk of
    0.01 units/sqrt(s) on x that the model lacks; the model: white noise only."""
    d = tmp_path_factory.mktemp("gyro")
    msgs, _ = imu_messages(5000, seed=3, walk=0.01)
    bag = write_bag(d / "gyro_bag", {"/imu": ("sensor_msgs/msg/Imu", msgs)})
    model = d / "gyro.toml"
    model.write_text(GYRO_MODEL)
    return bag, model


def test_analyze_a_bag_directory(gyro_bag, capsys):
    """`noiselab analyze BAG --measurement /imu:angular_velocity.y --model M --json`: the white
    axis fits its white-noise model (model error within the sampling noise: 1 +- a few sd)."""
    bag, model = gyro_bag
    rc, out, err = cli(capsys, "analyze", bag, "--measurement", "/imu:angular_velocity.y", "--model", model, "--json")
    assert rc == 0, err
    rep = json.loads(out)
    assert rep["samples"] == 5000 and 0.2 < rep["error"] < 4.0, rep["error"]


def test_diagnose_a_bag_finds_the_bias_walk(gyro_bag, capsys):
    """`noiselab diagnose BAG/STORAGE.mcap --measurement /imu:angular_velocity.x`: the bias walk
    is the missing effect, its fitted std near the 0.01 written, and the error falls."""
    bag, model = gyro_bag
    rc, out, err = cli(capsys, "diagnose", storage_file(bag), "--measurement", "/imu:angular_velocity.x",
                       "--model", model, "--json")
    assert rc == 0, err
    rep = json.loads(out)
    assert rep["missing"] and rep["missing"][0]["effect"] == "sensor.bias_walk", rep["missing"]
    assert 0.003 < rep["missing"][0]["params"]["std"] < 0.03
    assert rep["error_after"] < rep["error_before"] / 3, (rep["error_before"], rep["error_after"])


# -- 5. bad input: one line, exit 2, naming the topic and the type -------------------------------------------
@pytest.fixture(scope="module")
def bad_bags(bags, tmp_path_factory) -> dict:
    d = tmp_path_factory.mktemp("bad_bags")
    out = {}
    # a type the bag does not define and the standard store does not know: the definition rows
    # removed, as rosbag2's SQLite3 storage wrote bags before Iron
    st = stamps(50)
    nodef = write_bag(d / "nodef", {"/sample": ("noiselab_test/msg/Sample", [
        (int(st[k]), Sample(1.0, 0, 0.0, time_of(st[k]), "")) for k in range(50)]),
        "/plain": ("std_msgs/msg/Float64", [(int(st[k]), Float64(float(k))) for k in range(50)])}, "sqlite3")
    with sqlite3.connect(storage_file(nodef)) as db:
        db.execute("DELETE FROM message_definitions")
    out["nodef"] = nodef
    with Writer(d / "empty", version=9, storage_plugin=StoragePlugin.MCAP) as w:    # a topic, no message
        w.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=STORE)
        c = w.add_connection("/plain", "std_msgs/msg/Float64", typestore=STORE)
        w.write(c, 1, STORE.serialize_cdr(Float64(1.0), "std_msgs/msg/Float64"))
    out["empty"] = d / "empty"
    for storage in ("mcap", "sqlite3"):
        data = storage_file(bags[storage]).read_bytes()
        cut = d / f"cut{storage_file(bags[storage]).suffix}"
        cut.write_bytes(data[:len(data) // 2])
        out[f"cut {storage}"] = cut
    ros1 = write_ros1(d / "whole.bag", 100)
    data = ros1.read_bytes()
    (d / "cut.bag").write_bytes(data[:len(data) // 2])
    out["cut ros1"] = d / "cut.bag"
    msgs, _ = imu_messages(100)
    msgs[40][1].angular_velocity.x = float("nan")
    out["nan"] = write_bag(d / "nan", {"/imu": ("sensor_msgs/msg/Imu", msgs)})
    joints, _ = joint_messages(100)
    joints[30][1].position = np.array([1.0, 2.0])
    out["short seq"] = write_bag(d / "short_seq", {"/joint_states": ("sensor_msgs/msg/JointState", joints)})
    (d / "no_bag").mkdir()
    out["no bag"] = d / "no_bag"
    with Writer(d / "garbled", version=9, storage_plugin=StoragePlugin.MCAP) as w:   # message 20 cut short
        c = w.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=STORE)
        for k, (log, m) in enumerate(imu_messages(50)[0]):
            raw = bytes(STORE.serialize_cdr(m, "sensor_msgs/msg/Imu"))
            w.write(c, log, raw[:30] if k == 20 else raw)
    out["garbled"] = d / "garbled"
    return out


def bad_cases(bags, bad) -> dict:
    imu = bags["mcap"]
    m = ["--measurement"]
    return {
        "unknown type": ([bad["nodef"], *m, "/sample:value"],
                         ["/sample (noiselab_test/msg/Sample)", "cannot be decoded", "no definition"]),
        "missing field": ([imu, *m, "/imu:angular_velocity.w"],
                          ["/imu (sensor_msgs/msg/Imu)", "'angular_velocity.w'",
                           "(geometry_msgs/msg/Vector3) has the fields x, y, z"]),
        "missing top field": ([imu, *m, "/imu:gyro.x"],
                              ["/imu (sensor_msgs/msg/Imu)", "'gyro.x'",
                               "the message has the fields header, orientation, orientation_covariance, angular_velocity"]),
        "empty topic": ([bad["empty"], *m, "/imu:angular_velocity.x"], ["/imu (sensor_msgs/msg/Imu)", "no messages"]),
        "topic not in the bag": ([imu, *m, "/gyro:x"],
                                 ["no topic '/gyro' in the bag", "/imu (sensor_msgs/msg/Imu)",
                                  "/joint_states (sensor_msgs/msg/JointState)", "/plain (std_msgs/msg/Float64)"]),
        "a string": ([imu, *m, "/imu:header.frame_id"],
                     ["/imu (sensor_msgs/msg/Imu)", "'header.frame_id' is a string, not a number"]),
        "a message": ([imu, *m, "/imu:angular_velocity"],
                      ["'angular_velocity' is a geometry_msgs/msg/Vector3, not a number",
                       "angular_velocity.* takes every numeric one"]),
        "index of a fixed array": ([imu, *m, "/imu:orientation_covariance[9]"],
                                   ["/imu (sensor_msgs/msg/Imu)", "orientation_covariance has 9 items"]),
        "index beyond a sequence": ([bad["short seq"], *m, "/joint_states:position[2]"],
                                    ["/joint_states (sensor_msgs/msg/JointState)", "sample 30", "position[2]"]),
        "sequence length changes": ([bad["short seq"], *m, "/joint_states:position.*"],
                                    ["/joint_states (sensor_msgs/msg/JointState)",
                                     "sample 30: position has 2 items, the first message 3"]),
        "undecodable message": ([bad["garbled"], *m, "/imu:angular_velocity.x"],
                                ["/imu (sensor_msgs/msg/Imu)", "message 20 cannot be read"]),
        "wildcard in the middle": ([imu, *m, "/imu:*.x"], ["'*' stands only at the end"]),
        "time field not a time": ([imu, *m, "/imu:angular_velocity.x", "--time", "header.frame_id"],
                                  ["/imu (sensor_msgs/msg/Imu)", "time field 'header.frame_id' is a string"]),
        "NaN in a field": ([bad["nan"], *m, "/imu:angular_velocity.x"],
                           ["/imu (sensor_msgs/msg/Imu)", "NaN or inf in the measurement (first at sample 40)"]),
        "truncated MCAP": ([bad["cut mcap"], *m, "/imu:angular_velocity.x"],
                           ["cut.mcap", "rosbag2 MCAP file that rosbags cannot read", "truncated or corrupt"]),
        "truncated SQLite3": ([bad["cut sqlite3"], *m, "/imu:angular_velocity.x"],
                              ["cut.db3", "cannot read", "truncated or corrupt"]),
        "truncated ROS 1": ([bad["cut ros1"], *m, "/imu:angular_velocity.x"],
                            ["cut.bag", "ROS 1 bag that rosbags cannot read"]),
        "no --measurement": ([imu], ["a rosbag2 directory: give --measurement TOPIC:FIELD", "/imu (sensor_msgs/msg/Imu)"]),
        "a directory that is no bag": ([bad["no bag"], *m, "/imu:x"],
                                       ["no_bag: is a directory, not an MCAP recording or a rosbag2 bag directory"]),
        "--segment": ([imu, *m, "/imu:angular_velocity.x", "--segment", "2"], ["--segment takes a stream segment"]),
    }


CASES = ["unknown type", "missing field", "missing top field", "empty topic", "topic not in the bag", "a string",
         "a message", "index of a fixed array", "index beyond a sequence", "sequence length changes",
         "undecodable message", "wildcard in the middle",
         "time field not a time", "NaN in a field", "truncated MCAP", "truncated SQLite3", "truncated ROS 1",
         "no --measurement", "a directory that is no bag", "--segment"]


@pytest.mark.parametrize("command", ["analyze", "diagnose"])
@pytest.mark.parametrize("case", CASES)
def test_bad_bag_input_is_one_line_and_exit_2(bags, bad_bags, tmp_path, capsys, command, case):
    args, words = bad_cases(bags, bad_bags)[case]
    model = tmp_path / "gyro.toml"
    model.write_text(GYRO_MODEL)
    line = assert_bad(cli(capsys, command, *args, "--model", model, "--json"), *words)
    assert len(line) < 600, line


def test_bad_input_cases_are_all_run(bags, bad_bags):
    assert sorted(bad_cases(bags, bad_bags)) == sorted(CASES)


def test_a_standard_type_decodes_without_the_bags_definitions(bad_bags):
    """The same old-style bag's std_msgs/msg/Float64 topic: rosbags' standard types decode it."""
    s = read(bad_bags["nodef"], "/plain:data")
    assert np.array_equal(s.y[:, 0], np.arange(50.0))


# -- 6. replay ------------------------------------------------------------------------------------------------
class Collector:
    def __init__(self):
        self.cond = threading.Condition()
        self.by_key: dict[str, list[bytes]] = defaultdict(list)

    def __call__(self, sample) -> None:
        with self.cond:
            self.by_key[str(sample.key_expr)].append(sample.payload.to_bytes())
            self.cond.notify_all()

    def wait_for(self, predicate, what: str) -> None:
        with self.cond:
            assert self.cond.wait_for(predicate, T_EVENT), f"timeout waiting for {what}: {dict(self.by_key)!r:.300}"


def session(listen=(), connect=()) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return zenoh.open(conf)


def test_replay_republishes_a_bag_as_json_paced_by_log_time(tmp_path):
    """Every message of every topic, as JSON ({sec, nanosec} stamps, arrays as lists, NaN as null),
    under the topic without its '/', in log-time order; paced: at speed 1 the replay lasts at least
    the bag's log-time span (a lower bound: pacing only waits)."""
    msgs, arrays = imu_messages(40)
    msgs[3][1].orientation_covariance[0] = float("nan")
    plain = [(log + 1, Float64(float(k))) for k, (log, _) in enumerate(msgs[::2])]
    bag = write_bag(tmp_path / "replay_bag", {"/imu": ("sensor_msgs/msg/Imu", msgs),
                                              "/plain": ("std_msgs/msg/Float64", plain)})
    assert replay_topics(str(bag)) == ["imu", "plain"]
    port = free_port()
    got = Collector()
    with session(listen=[f"tcp/127.0.0.1:{port}"]) as sub_s, session(connect=[f"tcp/127.0.0.1:{port}"]) as pub_s:
        sub = sub_s.declare_subscriber("**", got)
        t0 = time.monotonic()
        summary = run_replay(pub_s, str(bag), speed=1.0, wait_subscribers=T_EVENT)
        got.wait_for(lambda: len(got.by_key["imu"]) == 40 and len(got.by_key["plain"]) == 20, "60 messages")
        sub.undeclare()
    span = (msgs[-1][0] - msgs[0][0]) * 1e-9
    assert summary.messages == 60 and summary.topics == {"/imu": 40, "/plain": 20}
    assert summary.wall_s >= span * 0.999 and time.monotonic() - t0 >= span * 0.999
    imu = [json.loads(p) for p in got.by_key["imu"]]
    st = arrays["stamps"]
    assert [m["header"]["stamp"] for m in imu] == [{"sec": int(s // 10**9), "nanosec": int(s % 10**9)} for s in st]
    assert [m["angular_velocity"]["x"] for m in imu] == arrays["gyro"][:, 0].tolist()
    assert imu[3]["orientation_covariance"][0] is None and imu[0]["orientation_covariance"] == list(range(9))
    assert [json.loads(p) for p in got.by_key["plain"]] == [{"data": float(k)} for k in range(20)]


def test_replay_of_an_undecodable_bag_is_one_line(bad_bags, capsys):
    """A bag with a type nothing defines is refused before any put, in one line."""
    assert_bad(cli(capsys, "replay", bad_bags["nodef"], "--listen", f"tcp/127.0.0.1:{free_port()}"),
               "/sample (noiselab_test/msg/Sample)", "cannot be decoded")


def test_a_cdr_mcap_without_the_ros2_profile_is_named(tmp_path, capsys):
    """CDR messages in an MCAP whose header profile is not 'ros2' (rosbags refuses such a file):
    read as JSON, refused in one line that names the encoding and the profile rosbags needs."""
    from mcap.writer import Writer as McapWriter

    path = tmp_path / "cdr_no_profile.mcap"
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start(profile="", library="elsewhere")
        sid = w.register_schema(name="std_msgs/msg/Float64", encoding="ros2msg", data=b"float64 data")
        cid = w.register_channel(topic="/plain", message_encoding="cdr", schema_id=sid)
        for k in range(10):
            w.add_message(channel_id=cid, log_time=k, publish_time=k, sequence=k,
                          data=bytes(STORE.serialize_cdr(Float64(float(k)), "std_msgs/msg/Float64")))
        w.finish()
    assert rosbag_in.bag_kind(path) is None
    model = tmp_path / "gyro.toml"
    model.write_text(GYRO_MODEL)
    assert_bad(cli(capsys, "analyze", path, "--measurement", "/plain:data", "--model", model),
               "/plain: sample 0", "message encoding 'cdr'", "a ROS 2 bag is read when its MCAP profile is 'ros2'")
