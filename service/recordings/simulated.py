"""``noiselab simulate``: a model simulated as fast as possible, written as a recording.

Two formats (``fmt``):

``"mcap"``
    noiselab's own MCAP recording in the wire contract (DESIGN.md, "Wire contract"): topics
    ``noiselab/<name>/{truth,command,measurement}``, JSON payloads ``{"seq", "t", x|u|y}`` with
    ``t`` = k Ts in s since the start, written sample by sample (truth, command, measurement of k,
    then of k + 1) as the emulator publishes them.
``"ros2"``
    A rosbag2 bag directory (:mod:`.rosbag_out`: ``sensor_msgs`` messages in CDR).

Times in both: the run is anchored at its wall-clock start ``start_time_ns`` (int ns since the
Unix epoch, taken when the write begins unless given), so viewers show the real date: sample k's
publish_time (MCAP) or ``header.stamp`` (ROS 2) is ``start_time_ns + round(k * Ts * 1e9)`` ns
(the wire contract's anchor, from the payload time t = k * Ts), and offline there is no receive time, so log_time is
the same instant (one time base per file; readers must not assume log_time is wall-clock).
``start_time_ns`` is written as a decimal string in the file's ``noiselab`` metadata record (the
bag's ``custom_data`` for ROS 2, as ``noiselab.start_time_ns``), beside the model (TOML), Ts and
the seed, so the run is reproduced from the file alone.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..progress import Progress

FORMATS = ("mcap", "ros2")
"""``simulate --format`` values: noiselab's JSON MCAP recording, or a rosbag2 bag."""



def _version() -> str:
    """noiselab's installed version (the generator's, in the file's metadata)."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("noiselab")
    except PackageNotFoundError:
        return "unknown"


def run_metadata(model, n: int, seed: int, start_time_ns: int, fmt: str) -> dict[str, str]:
    """What the file records of its run (all str): generator, model (name, source, TOML), Ts,
    seed, samples, the wall-clock anchor and the format."""
    return {"generator": "noiselab simulate", "version": _version(), "model_name": model.name,
            "model_source": model.source, "model_toml": model.to_toml(), "Ts": repr(model.Ts),
            "seed": str(seed), "samples": str(n), "start_time_ns": str(start_time_ns),
            "format": fmt}


def write_simulation(model, n: int, seed: int, out: Path, *, force: bool = False,
                     progress: bool | None = None, fmt: str = "mcap",
                     start_time_ns: int | None = None) -> dict:
    """Simulate ``n`` samples of ``model`` from ``seed`` (under its ``[controller]`` if it has one)
    and write them to ``out`` in ``fmt``
    (:data:`FORMATS`). ``start_time_ns``: the wall-clock anchor (default: now). Returns a
    summary: ``out``, ``samples``, ``format``, ``start_time_ns``, ``messages`` per topic.

    An existing ``out`` is refused without ``force``; with it, ``out`` is replaced only once the
    new file is finished, so a write that fails keeps the old one (:class:`RecordingWriter`,
    :class:`~.rosbag_out.BagWriter`). Bad input is a one-line ``ValueError``."""
    from ..errors import BadInput

    if fmt not in FORMATS:
        raise BadInput(f"--format {fmt!r}: expected one of {', '.join(FORMATS)}")
    out = Path(out)
    start = time.time_ns() if start_time_ns is None else int(start_time_ns)
    meta = run_metadata(model, n, seed, start, fmt)
    bar = Progress(n, f"simulate {model.name}", progress)
    try:
        # a diverging plant (unstable, or forward Euler over too long a Ts) overflows to inf: the
        # encoder refuses that sample in one line naming it; numpy's overflow warnings are no news
        with np.errstate(over="ignore", invalid="ignore"):
            write = _write_ros2 if fmt == "ros2" else _write_mcap
            counts = write(model, n, seed, out, force, meta, start, bar)
    finally:
        bar.close()
    return {"out": str(out), "samples": n, "format": fmt, "start_time_ns": start,
            "messages": counts}


def _blocks(model, n: int, seed: int, start: int):
    """``(k0, t, stamp_ns, block)`` of consecutive blocks: ``t`` the payload times (s since the
    start, :func:`noiselab.wire.sample_times`), ``stamp_ns`` the anchored publish times
    ``start + round(t * 1e9)`` (int64 ns; ``np.rint`` rounds half to even, as Python's ``round``)."""
    from .. import wire

    k0 = 0
    command = None
    if model.controller is not None:
        # a closed loop (an external command and a [controller]): the applied command is the
        # controller's answers, each from the next sample, as the live loop on time; the same
        # seed then gives the same noises and measurements (simulate_closed_loop)
        from ..model.controller import simulate_closed_loop
        command = simulate_closed_loop(model, n, seed=seed)["u"]
    for blk in model.simulate_blocks(n, seed=seed, command=command):
        t, _ = wire.sample_times(k0, blk.t.size, model.Ts)
        yield k0, t, np.int64(start) + np.rint(t * 1e9).astype(np.int64), blk
        k0 += blk.t.size


def _write_mcap(model, n, seed, out, force, meta, start, bar) -> dict[str, int]:
    from .. import wire
    from .writer import RecordingWriter

    topics = {kind: wire.key(model.name, kind) for kind in ("truth", "command", "measurement")}
    out.parent.mkdir(parents=True, exist_ok=True)
    with RecordingWriter(out, force=force, chunk_size=1 << 20, metadata=meta) as w:
        for k0, t, pub, blk in _blocks(model, n, seed, start):
            w.write_interleaved([(topics[kind], kind, k0, pub, pub,
                                  wire.encode_batch(kind, k0, t, arr, topic=topics[kind]))
                                 for kind, arr in (("truth", blk.x[0]), ("command", blk.u[0]),
                                                   ("measurement", blk.y[0]))])
            bar.update(k0 + blk.t.size)
        return w.counts


def _write_ros2(model, n, seed, out, force, meta, start, bar) -> dict[str, int]:
    from .rosbag_out import BagWriter

    with BagWriter(out, model, meta, force=force) as w:
        for k0, _t, stamp, blk in _blocks(model, n, seed, start):
            w.write_block(k0, stamp, {"truth": blk.x[0], "command": blk.u[0],
                                      "measurement": blk.y[0]})
            bar.update(k0 + blk.t.size)
        counts = w.counts
    return counts
