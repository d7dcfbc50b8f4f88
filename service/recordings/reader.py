"""Read every noiselab device of an MCAP recording into arrays (:func:`read_recording`)."""

from __future__ import annotations

import os
from collections import defaultdict
from collections.abc import Iterable

import numpy as np

from .. import parallel, wire
from .chunks import Packed, collect_fast
from .errors import McapIoError, shown
from .mcapformat import norm_topic
from .recording import DeviceData, Recording, split_streams
from .scan import ScanReport, iter_messages


def _as_i64(values, topic: str, what: str) -> np.ndarray:
    """list of ints or uint64 array -> int64 (times beyond 2**63 - 1 ns are refused)."""
    if isinstance(values, np.ndarray) and values.dtype == np.uint64:
        if values.size and int(values.max()) > 2**63 - 1:
            raise McapIoError(f"{topic}: {what} beyond 2**63 - 1 ns is not supported")
        return values.astype(np.int64)
    try:
        return np.array(values, dtype=np.int64)
    except OverflowError:
        raise McapIoError(f"{topic}: {what} beyond 2**63 - 1 ns is not supported") from None


PARALLEL_DECODE = 200_000   # messages over a recording's topics from which two are parsed at once (a fork)


def read_recording(path: str | os.PathLike, kinds: Iterable[str] = wire.KINDS) -> Recording:
    """Read every noiselab device of an MCAP file into arrays (see :class:`Recording`).

    Devices are found by topics ending in ``/measurement`` (leading ``/`` optional); their
    ``command`` and ``truth`` topics are read when present (``kinds`` limits which). Other
    topics are ignored. Payloads are validated (:func:`wire.decode_batch`); a device topic whose
    message encoding is not ``json`` raises McapIoError. Works on unfinished files
    (``complete=False``). Finished files take a fast chunk-level path.
    """
    path = os.fspath(path)
    kinds = tuple(k for k in wire.KINDS if k in set(kinds) | {"measurement"})
    report = ScanReport()
    fast = collect_fast(path, kinds, report)
    if fast is not None:
        raw, encodings = fast
    else:
        report = ScanReport()
        # per normalised topic: payloads, log_time, publish_time; and its encodings
        raw = {}
        encodings = defaultdict(set)
        for _schema, channel, msg in iter_messages(path, report=report):
            topic = norm_topic(channel.topic)
            lists = raw.get(topic)
            if lists is None:
                lists = raw[topic] = ([], [], [])
                encodings[topic].add(channel.message_encoding)
            lists[0].append(msg.data)
            lists[1].append(msg.log_time)
            lists[2].append(msg.publish_time)

    devices: dict[str, DeviceData] = {}
    jobs = []                                   # (device name, prefix, kind, topic), devices sorted
    names: dict[str, str] = {}
    for topic in sorted(t for t in raw if t.endswith("/measurement")):
        prefix = topic[: -len("/measurement")]
        name = prefix[len("noiselab/"):] if prefix.startswith("noiselab/") else prefix
        if name in names.values():  # e.g. both "noiselab/imu" and "imu": keep them apart
            name = prefix
        names[prefix] = name
        for kind in kinds:
            ktopic = f"{prefix}/{kind}"
            if ktopic not in raw:
                continue
            bad = encodings[ktopic] - {wire.MESSAGE_ENCODING}
            if bad:
                raise McapIoError(f"{path}: topic {ktopic!r} has message encoding "
                                  f"{sorted(bad)[0]!r}; noiselab reads 'json' only")
            jobs.append((name, prefix, kind, ktopic))

    def decode(job):
        kind, ktopic = job[2], job[3]
        payloads = raw[ktopic][0]
        if isinstance(payloads, Packed):
            return wire.decode_packed(payloads.blob, payloads.lens, kind, topic=shown(ktopic))
        return wire.decode_batch(payloads, kind, topic=shown(ktopic))

    sizes = [len(raw[j[3]][0]) for j in jobs]
    if len(jobs) >= 2 and sum(sizes) >= PARALLEL_DECODE:
        # parsing is C strtod under the GIL: two topics in two processes (a forked copy of this one)
        # where that is safe, else one after the other (threads would gain nothing)
        def caught(job):
            try:
                return decode(job)
            except wire.WireError as exc:          # raised below in the topics' order, as serially
                return exc
        decoded = parallel.Pool().map(caught, jobs, order=sorted(range(len(jobs)), key=lambda i: -sizes[i]),
                                      threads=False)
        for d in decoded:
            if isinstance(d, Exception):
                raise d
    else:
        decoded = [decode(j) for j in jobs]
    streams_of: dict[str, dict] = {}
    for (_name, prefix, kind, ktopic), (seq, t, values) in zip(jobs, decoded):
        log_a = _as_i64(raw[ktopic][1], ktopic, "log_time")
        pub_a = _as_i64(raw[ktopic][2], ktopic, "publish_time")
        streams_of.setdefault(prefix, {})[kind] = split_streams(path, ktopic, kind, seq, t, values, pub_a, log_a)
    for prefix, name in names.items():
        devices[name] = DeviceData(name, prefix, streams_of.get(prefix, {}))
    return Recording(path=path, devices=devices, metadata=report.metadata,
                     complete=bool(report.complete), note=report.note, messages=report.messages)


# --------------------------------------------------------------------------- recovery

