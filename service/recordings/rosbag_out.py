"""A simulated run as a ROS 2 bag (``noiselab simulate MODEL --format ros2 --out BAG``).

The bag is what ``ros2 bag record -s mcap`` makes: a directory ``BAG/`` holding ``metadata.yaml``
(rosbag2 metadata version 9) and one ``BAG.mcap`` (MCAP profile ``ros2``, message encoding
``cdr``, one ``ros2msg`` schema per message type, zstd-compressed chunks of 1 MiB). It is written
by ``rosbags.rosbag2.Writer`` with the ROS 2 Jazzy type store, so ``rosbags``, ``ros2 bag``
(Jazzy and later read version 9) and Foxglove open it.

The documented standard messages, for a model named ``<name>``, one message per sample ``k`` on
each topic (``<name>`` as a ROS 2 name token, :func:`ros_token`: ``imu-nominal`` gives
``/imu_nominal/measurement``):

``/<name>/measurement``
    An IMU model (exactly six outputs, three whose names start with ``gyro`` and three with
    ``accel``, e.g. ``gyro_x gyro_y gyro_z accel_x accel_y accel_z``; within each group the order
    in ``[outputs] names`` is x, y, z: the convention of the Kalibr export) as
    ``sensor_msgs/msg/Imu``: ``angular_velocity`` = the gyro outputs (rad/s),
    ``linear_acceleration`` = the accelerometer outputs (m/s^2), in the units the model gives
    them; ``orientation`` = identity with ``orientation_covariance[0] = -1`` (REP 145: the sensor
    gives no orientation); the diagonals of ``angular_velocity_covariance`` and
    ``linear_acceleration_covariance`` = the model's predicted steady-state variance of each axis
    (:func:`imu_covariance`), all zeros ("unknown", per the message's definition) where the model
    predicts none. Any other model as ``sensor_msgs/msg/JointState``: ``name`` = the output names,
    ``position`` = y, ``velocity`` and ``effort`` empty.
``/<name>/truth``
    ``sensor_msgs/msg/JointState``: ``name`` = the plant's state names, ``position`` = x.
    A sensor-only model (no ``[plant]``, no state) has no truth topic: what its outputs measure
    is the reference on the command topic.
``/<name>/command``
    ``sensor_msgs/msg/JointState``: ``name`` = ``u0``, ``u1``, ... (one per plant input),
    ``effort`` = u, ``position`` and ``velocity`` empty.

Every message's ``header.stamp`` is the sample's time anchored at the run's wall-clock start,
``start_time_ns + round(k * Ts * 1e9)`` ns (:mod:`.simulated`), and the
bag's receive timestamp is the same instant; ``header.frame_id`` is :data:`FRAME_ID`
(``imu_link``) on every topic. The run's description (generator, model name, the model as TOML,
Ts, seed, samples, ``start_time_ns``) is the bag's rosbag2 ``custom_data`` (in
``metadata.yaml`` and in the MCAP's ``rosbag2`` metadata record), keys prefixed ``noiselab.``.

Encoding: every message of a topic has the same layout (constant ``frame_id`` and names, fixed
array lengths), so a whole block of samples is encoded at once into a numpy array of messages
(:class:`CdrLayout`), byte for byte what ``rosbags``' ``serialize_cdr`` gives (checked by the
tests on random messages). CDR can carry NaN and inf; a sample that is not finite (a diverging
plant) is refused all the same, as the JSON recording refuses it, with one line naming it.

Output: the bag is written under ``<BAG>.partial/`` beside ``BAG`` and moved to ``BAG`` only once
finished, so a write that fails (or is killed) never spoils an existing bag; a failed write's
staging directory is removed (a simulation is reproduced by its seed). An existing ``BAG`` is
replaced only with ``force``, and then only if it is a file, an empty directory or a rosbag2 bag
(a directory with ``metadata.yaml``): never some other directory.
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import os
import re
import shutil
import struct
from pathlib import Path
from typing import Self

import numpy as np

from ..errors import BadInput

FRAME_ID = "imu_link"
"""``header.frame_id`` of every message: the emulated IMU's body frame (REP 145 names the frame
of the sensor's own axes ``imu_link``)."""

CHUNK_BYTES = 1 << 20
"""Bytes of a chunk of the bag's MCAP (``rosbags``' own, and the JSON recording's, chunk size)."""

MSG_IMU = "sensor_msgs/msg/Imu"
MSG_JOINT_STATE = "sensor_msgs/msg/JointState"
CDR_HEADER = b"\x00\x01\x00\x00"
"""The CDR encapsulation header of a little-endian plain-CDR message (what rosbag2 stores)."""

STAGING_SUFFIX = ".partial"


def _typestore():
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


# ------------------------------------------------------------------------- message layout


class CdrLayout:
    """One message type with a fixed layout, as a template of bytes and the offsets of its
    per-sample fields; :meth:`encode` writes a block of N messages at once.

    CDR (OMG CDR, XCDR1 little-endian, as ROS 2's rmw serializes): every primitive is aligned to
    its size counted from the end of the 4-byte encapsulation header; a string is a uint32 length
    (including the terminating NUL) and its bytes; a sequence is a uint32 count and its elements;
    a fixed array is its elements only.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.fields: dict[str, tuple[int, int]] = {}     # name -> (offset in the message, count)
        self.stamp: int | None = None

    def _align(self, n: int) -> None:
        self._buf += bytes(-len(self._buf) % n)

    def u32(self, v: int) -> None:
        self._align(4)
        self._buf += struct.pack("<I", v)

    def string(self, s: str) -> None:
        b = s.encode() + b"\0"
        self.u32(len(b))
        self._buf += b

    def header(self, frame_id: str) -> None:
        """``std_msgs/Header``: ``stamp`` (int32 sec, uint32 nanosec) per sample, ``frame_id``."""
        self._align(4)
        self.stamp = len(CDR_HEADER) + len(self._buf)
        self._buf += bytes(8)
        self.string(frame_id)

    def f64(self, values) -> None:
        """Constant float64 values (a fixed array, or the elements of a sequence)."""
        values = list(values)
        if values:
            self._align(8)
            self._buf += struct.pack(f"<{len(values)}d", *values)

    def f64_field(self, name: str, count: int) -> None:
        """``count`` float64 that change with every sample (filled by :meth:`encode`)."""
        if count:
            self._align(8)
            self.fields[name] = (len(CDR_HEADER) + len(self._buf), count)
            self._buf += bytes(8 * count)

    @property
    def template(self) -> bytes:
        return CDR_HEADER + bytes(self._buf)

    def encode(self, sec: np.ndarray, nanosec: np.ndarray, **values: np.ndarray) -> np.ndarray:
        """N messages as an (N, L) uint8 array, row i the bytes of message i: ``sec``/``nanosec``
        (N,) the stamps, ``values[name]`` (N, count) each per-sample field."""
        tpl = np.frombuffer(self.template, np.uint8)
        out = np.empty((sec.shape[0], tpl.size), np.uint8)
        out[:] = tpl
        s = self.stamp
        out[:, s:s + 4].view("<i4")[:, 0] = sec
        out[:, s + 4:s + 8].view("<u4")[:, 0] = nanosec
        for name, (off, count) in self.fields.items():
            out[:, off:off + 8 * count].view("<f8")[:] = values[name]
        return out


def imu_layout(cov_gyro, cov_accel, frame_id: str = FRAME_ID) -> CdrLayout:
    """``sensor_msgs/msg/Imu`` with the covariance diagonals given (3 each) and no orientation."""
    c = CdrLayout()
    c.header(frame_id)
    c.f64((0.0, 0.0, 0.0, 1.0))                               # orientation: identity quaternion
    c.f64((-1.0,) + (0.0,) * 8)                               # orientation_covariance, REP 145
    c.f64_field("angular_velocity", 3)
    c.f64(np.diag(np.asarray(cov_gyro, float)).ravel())
    c.f64_field("linear_acceleration", 3)
    c.f64(np.diag(np.asarray(cov_accel, float)).ravel())
    return c


def joint_state_layout(names, field: str, frame_id: str = FRAME_ID) -> CdrLayout:
    """``sensor_msgs/msg/JointState`` with constant ``names``; ``field`` (``position`` or
    ``effort``) holds one value per name, the other two sequences are empty."""
    c = CdrLayout()
    c.header(frame_id)
    c.u32(len(names))
    for nm in names:
        c.string(nm)
    for f in ("position", "velocity", "effort"):
        c.u32(len(names) if f == field else 0)
        if f == field:
            c.f64_field(f, len(names))
    return c


# ------------------------------------------------------------------------- the model's topics


def imu_axes(names) -> tuple[list[int], list[int]] | None:
    """Indices of the gyro and the accelerometer outputs (x, y, z each, in the order of
    ``names``) when the outputs are an IMU's (see the module docstring), else None."""
    names = list(names)
    gyro = [j for j, nm in enumerate(names) if nm.startswith("gyro")]
    accel = [j for j, nm in enumerate(names) if nm.startswith("accel")]
    if len(names) == 6 and len(gyro) == 3 and len(accel) == 3:
        return gyro, accel
    return None


def imu_covariance(model, axes) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis variance of the gyro and accelerometer outputs (units^2): the model's predicted
    steady-state variance of each centered output (``var_y`` of ``noiselab predict``, without the
    bias walk's growth); zeros ("unknown" in ``sensor_msgs/Imu``) where it predicts none."""
    try:
        var = model.predictor().steady_state().var_y
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):
        var = None
    if var is None:
        return np.zeros(3), np.zeros(3)
    var = np.where(np.isfinite(var), var, 0.0)
    return var[axes[0]], var[axes[1]]


def ros_token(name: str) -> str:
    """``name`` as one token of a ROS 2 topic name (letters, digits and single underscores, not
    starting with a digit: ROS 2's name rules): every run of other characters (``-``) becomes
    ``_``, repeated underscores one, and a leading digit gets a ``_`` before it."""
    token = re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", name))
    return f"_{token}" if token[:1].isdigit() else token


class _Topic:
    def __init__(self, topic: str, msgtype: str, layout: CdrLayout, kind: str, fields):
        self.topic, self.msgtype, self.layout, self.kind = topic, msgtype, layout, kind
        self.fields = fields               # field name -> column indices of the block's array
        self.conn = None


def model_topics(model) -> list[_Topic]:
    """The topics of ``model``'s bag, in the order their messages of one sample are written
    (truth, command, measurement: as the emulator publishes them)."""
    name = ros_token(model.name)
    topics = []
    state_names = tuple(model.plant.state_names)
    if state_names:
        topics.append(_Topic(f"/{name}/truth", MSG_JOINT_STATE,
                             joint_state_layout(state_names, "position"), "truth",
                             {"position": list(range(len(state_names)))}))
    inputs = [f"u{i}" for i in range(model.m)]
    topics.append(_Topic(f"/{name}/command", MSG_JOINT_STATE, joint_state_layout(inputs, "effort"),
                         "command", {"effort": list(range(model.m))}))
    axes = imu_axes(model.output_names)
    if axes is not None:
        layout = imu_layout(*imu_covariance(model, axes))
        topics.append(_Topic(f"/{name}/measurement", MSG_IMU, layout, "measurement",
                             {"angular_velocity": axes[0], "linear_acceleration": axes[1]}))
    else:
        topics.append(_Topic(f"/{name}/measurement", MSG_JOINT_STATE,
                             joint_state_layout(model.output_names, "position"), "measurement",
                             {"position": list(range(model.p))}))
    return topics


_VECTOR = {"truth": "x", "command": "u", "measurement": "y"}


def _check_finite(topic: _Topic, k0: int, arr: np.ndarray) -> None:
    bad = ~np.isfinite(arr)
    if bad.any():
        i, j = map(int, np.argwhere(bad)[0])
        raise BadInput(f"{topic.topic}: {_VECTOR[topic.kind]}[{j}]={arr[i, j]!r} at sample {k0 + i} "
                       "is not finite (a diverging plant?); nothing is written")


# ------------------------------------------------------------------------- the bag


def _is_bag_or_empty(p: Path) -> bool:
    return (p / "metadata.yaml").is_file() or not any(p.iterdir())


def check_out(out: Path, force: bool) -> None:
    """The bag directory ``out`` can be written (before any work): an existing path needs
    ``force``, and a directory is replaced only if it is a rosbag2 bag or empty."""
    out = Path(out)
    if out.exists() or out.is_symlink():
        if not force:
            raise BadInput(f"{out}: already exists (use --force to overwrite)")
        if out.is_dir() and not out.is_symlink() and not _is_bag_or_empty(out):
            raise BadInput(f"{out}: is a directory that is not a rosbag2 bag (no metadata.yaml); "
                           "not replacing it: give another --out")
    staging = out.with_name(out.name + STAGING_SUFFIX)
    if staging.exists():
        raise BadInput(f"{staging}: exists (the unfinished output of an earlier run?); delete it, "
                       f"then write {out} again")
    for q in (out.parent, *out.parent.parents):
        if q.exists():
            if not q.is_dir():
                raise BadInput(f"{out}: {q} is a file, not a directory")
            break


class BagWriter:
    """Writes ``model``'s samples block by block into the bag directory ``out`` (see the module
    docstring); a context manager that finishes the bag and moves it into place on success."""

    def __init__(self, out, model, custom_data: dict[str, str], *, force: bool = False) -> None:
        from rosbags.rosbag2 import (
            CompressionFormat,
            CompressionMode,
            StoragePlugin,
            Writer,
        )

        self.out = Path(out)
        self.force = force
        check_out(self.out, force)
        self.topics = model_topics(model)
        self.counts = {t.topic: 0 for t in self.topics}
        self.staging = self.out.with_name(self.out.name + STAGING_SUFFIX)
        try:
            self.staging.parent.mkdir(parents=True, exist_ok=True)
            self.staging.mkdir()
        except OSError as e:
            raise BadInput(f"{self.out}: cannot write it ({e.strerror or e})") from None
        self._writer = Writer(self.staging / self.out.name, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        for key, value in custom_data.items():
            self._writer.set_custom_data(f"noiselab.{key}", value)

    def __enter__(self) -> Self:
        try:
            self._writer.open()
            store = _typestore()
            for t in self.topics:
                t.conn = self._writer.add_connection(t.topic, t.msgtype, typestore=store)
        except BaseException as exc:
            self._fail()
            if isinstance(exc, OSError):
                raise BadInput(f"{self.out}: cannot write it ({exc.strerror or exc})") from None
            raise
        return self

    def write_block(self, k0: int, stamp_ns: np.ndarray, arrays: dict[str, np.ndarray]) -> None:
        """Samples ``k0 .. k0+N-1``: ``stamp_ns`` (N,) int64 ns since the Unix epoch, ``arrays``
        the (N, dim) block of each kind (``truth`` x, ``command`` u, ``measurement`` y)."""
        stamp_ns = np.asarray(stamp_ns, np.int64)
        sec, nanosec = np.divmod(stamp_ns, np.int64(1_000_000_000))
        k = len(self.topics)
        datas = [b""] * (stamp_ns.size * k)     # sample by sample: message i of every topic in turn
        for j, t in enumerate(self.topics):
            arr = np.asarray(arrays[t.kind], np.float64)
            _check_finite(t, k0, arr)
            msgs = t.layout.encode(sec, nanosec, **{f: arr[:, cols] for f, cols in t.fields.items()})
            blob, size = msgs.tobytes(), msgs.shape[1]
            at = range(0, len(blob) + 1, size)
            datas[j::k] = map(blob.__getitem__, map(slice, at[:-1], at[1:]))
        conns = itertools.islice(itertools.cycle([t.conn for t in self.topics]), len(datas))
        try:
            # the writer's calls from C (map), not from a Python loop body
            collections.deque(map(self._writer.write, conns, np.repeat(stamp_ns, k).tolist(), datas), maxlen=0)
        except OSError as e:
            raise BadInput(f"{self.out}: cannot write it ({e.strerror or e}); {self.out} is as it was") from None
        for t in self.topics:
            self.counts[t.topic] += stamp_ns.size

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is not None:
            self._fail()
            return
        try:
            self._writer.close()
            self._commit()
        except OSError as e:
            self._fail()
            raise BadInput(f"{self.out}: cannot write it ({e.strerror or e}); {self.out} is as it was") from None

    def _commit(self) -> None:
        """Move the finished bag from the staging directory to ``out``; an old ``out`` is moved
        into the staging directory first (so it is never lost mid-way), then removed."""
        bag = self.staging / self.out.name
        if self.out.exists() or self.out.is_symlink():
            old = self.staging / (self.out.name + ".replaced")
            os.rename(self.out, old)
            os.rename(bag, self.out)
            if old.is_dir() and not old.is_symlink():
                shutil.rmtree(old)
            else:
                old.unlink()
        else:
            os.rename(bag, self.out)
        self.staging.rmdir()

    def _fail(self) -> None:
        """A failed write: the unfinished bag is dropped, an old ``out`` is untouched."""
        with contextlib.suppress(Exception):       # the body's own exception is the one to see
            self._writer.abort()
        shutil.rmtree(self.staging, ignore_errors=True)
