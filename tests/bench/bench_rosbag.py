"""Reading a ROS 2 bag into a series: noiselab's loader against rosbags' own reader loop.

Run on demand, not by pytest (``pyproject.toml`` ignores ``tests/bench``)::

    .venv/bin/python tests/bench/bench_rosbag.py                   # 10^6 messages, MCAP storage
    .venv/bin/python tests/bench/bench_rosbag.py --storage sqlite3
    .venv/bin/python tests/bench/bench_rosbag.py --quick           # 10^5 messages, smoke test

What is measured (the ratio is taken against its peer *in the same run*, on the same bag):

* the bag: ``N`` ``sensor_msgs/msg/Imu`` messages at 100 Hz on ``/imu``, written with rosbags'
  ``rosbag2.Writer`` (rosbag2 version 9, CDR) into a temporary directory; header stamps from an
  epoch start, log time 0.5 ms after each stamp, white noise on the three gyro axes.
* peer: rosbags' reader loop, ``AnyReader([bag])`` over the ``/imu`` connection, each message
  deserialized (``reader.deserialize``) and one field read (``angular_velocity.x``) into a list.
* noiselab: ``noiselab.recordings.load.load_recording(bag, spec="/imu:angular_velocity.x", Ts=0.01)``,
  the loader ``analyze`` and ``diagnose`` call: the same decoding, the header stamps to exact
  integer ns, and every check a foreign series passes (NaN, magnitude, order, regular timing,
  the longest gap-free run), the ``Series`` returned.

Target: noiselab / peer <= 1.5 (best of ``--repeat`` runs each, interleaved, one warm-up of
each first; noise from other processes only adds time, so the best runs are compared; the median
ratio is printed beside it). The load average at start and end is printed: the machine has 2
cores and may be shared.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import numpy as np

TARGET = 1.5
TS_NS = 10_000_000                  # 100 Hz
START_NS = 1_700_000_000_123_456_789


def write_bag(path: Path, n: int, storage: str) -> None:
    """``n`` Imu messages on /imu (see the module docstring)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    Imu, Header, Time = (ts.types[k] for k in ("sensor_msgs/msg/Imu", "std_msgs/msg/Header",
                                               "builtin_interfaces/msg/Time"))
    V3, Q = ts.types["geometry_msgs/msg/Vector3"], ts.types["geometry_msgs/msg/Quaternion"]
    gyro = np.random.default_rng(1).normal(0.0, 1e-3, (n, 3))
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    msg = Imu(Header(Time(0, 0), "imu"), Q(0.0, 0.0, 0.0, 1.0), np.zeros(9), V3(0.0, 0.0, 0.0), np.zeros(9),
              V3(0.0, 0.0, 9.81), np.zeros(9))
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conn = w.add_connection("/imu", Imu.__msgtype__, typestore=ts)
        for k in range(n):
            stamp = START_NS + k * TS_NS
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
            msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = gyro[k].tolist()
            w.write(conn, stamp + 500_000, ts.serialize_cdr(msg, Imu.__msgtype__))


def peer(bag: Path) -> int:
    """rosbags' reader loop: deserialize each /imu message, read angular_velocity.x."""
    from rosbags.highlevel import AnyReader

    out = []
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == "/imu"]
        for conn, _, raw in reader.messages(connections=conns):
            out.append(reader.deserialize(raw, conn.msgtype).angular_velocity.x)
    return len(out)


def ours(bag: Path) -> int:
    from noiselab.recordings.load import load_recording

    s = load_recording(str(bag), spec="/imu:angular_velocity.x", Ts=TS_NS * 1e-9)
    return s.y.shape[0]


def loadavg() -> str:
    try:
        return " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=1_000_000, help="messages in the bag (default 10^6)")
    ap.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    ap.add_argument("--repeat", type=int, default=3, help="timed runs of each side (default 3)")
    ap.add_argument("--quick", action="store_true", help="10^5 messages, 2 runs")
    a = ap.parse_args()
    n, repeat = (100_000, 2) if a.quick else (a.n, a.repeat)
    print(f"load average at start: {loadavg()}")
    with tempfile.TemporaryDirectory(prefix="bench_rosbag_") as tmp:
        bag = Path(tmp) / "imu_bag"
        t0 = time.perf_counter()
        write_bag(bag, n, a.storage)
        size = sum(f.stat().st_size for f in bag.iterdir())
        print(f"wrote {n} sensor_msgs/msg/Imu messages ({a.storage}, {size / 2**20:.0f} MiB) in "
              f"{time.perf_counter() - t0:.1f} s")
        # the loader reads the same rows as the peer (a check, not timed)
        assert ours(bag) == peer(bag) == n
        times: dict[str, list[float]] = {"peer": [], "noiselab": []}
        for _ in range(repeat):
            for name, fn in (("peer", peer), ("noiselab", ours)):
                t0 = time.perf_counter()
                fn(bag)
                times[name].append(time.perf_counter() - t0)
    for name, ts in times.items():
        print(f"{name:9s}: best {min(ts):.2f} s ({min(ts) / n * 1e6:.2f} us/message), median "
              f"{statistics.median(ts):.2f} s, runs {', '.join(f'{t:.2f}' for t in ts)}")
    best = min(times["noiselab"]) / min(times["peer"])
    med = statistics.median(times["noiselab"]) / statistics.median(times["peer"])
    ok = best <= TARGET
    print(f"ratio noiselab / rosbags loop: {best:.2f} (best), {med:.2f} (median); target <= {TARGET}: "
          f"{'PASS' if ok else 'FAIL'}")
    print(f"load average at end: {loadavg()}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
