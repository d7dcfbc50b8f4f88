"""MCAP recordings written for a test: noiselab's own (through its writer, on the wire contract)
and foreign ones (mcap's own Writer, as another tool would write them)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from mcap.writer import Writer

from noiselab import wire
from noiselab.recordings.writer import RecordingWriter

Ts = 0.01       # s, the sample period of write_sample's and raw_file's streams
DIMS = {"truth": 2, "command": 1, "measurement": 2}     # write_sample's vector sizes per kind


def write_record(path, model, n: int, seed: int, edit=None) -> None:
    """A noiselab recording of ``model`` (n samples of truth, command and measurement, the wire
    contract as ``simulate`` writes it), its arrays first given to ``edit(x, u, y)``."""
    b = model.simulate(n, seed=seed)
    x, u, y = b.x.copy(), b.u.copy(), b.y.copy()
    if edit is not None:
        edit(x, u, y)
    t, pub = wire.sample_times(0, n, model.Ts)
    with RecordingWriter(path) as w:
        w.write_interleaved([(wire.key(model.name, kind), kind, 0, pub, pub,
                              wire.encode_batch(kind, 0, t, arr, topic=wire.key(model.name, kind)))
                             for kind, arr in (("truth", x), ("command", u), ("measurement", y))])


def make_data(n, seed=1):
    """Per kind: (t, publish_ns, log_ns, values) of n samples, values with awkward floats."""
    rng = np.random.default_rng(seed)
    t, pub = wire.sample_times(0, n, Ts)
    out = {}
    for i, kind in enumerate(wire.KINDS):
        vals = rng.standard_normal((n, DIMS[kind])) * 10.0 ** rng.integers(-20, 20, (n, 1))
        vals[0, 0] = -0.0
        log = pub + 1_700_000_000_000_000_000 + rng.integers(0, 50_000, n) + i
        out[kind] = (t, pub, log, vals)
    return out


def write_sample(path, n=200, *, name="dev", chunk_size=64 * 1024, compression=None,
                 metadata=None):
    """Write n samples of the 3 topics: the first half message by message, the rest batched.

    Messages interleave truth, command, measurement per sample, as the emulator sends them.
    """
    data = make_data(n)
    kw = {} if compression is None else {"compression": compression}
    with RecordingWriter(path, chunk_size=chunk_size, metadata=metadata, **kw) as w:
        half = n // 2
        for k in range(half):
            for kind in wire.KINDS:
                t, pub, log, vals = data[kind]
                payload = wire.encode(k, t[k], vals[k], kind=kind)
                w.write(wire.key(name, kind), kind, k, int(pub[k]), int(log[k]), payload)
        for k0 in range(half, n, 10):
            for kind in wire.KINDS:
                t, pub, log, vals = data[kind]
                sl = slice(k0, min(k0 + 10, n))
                payloads = wire.encode_batch(kind, k0, t[sl], vals[sl])
                w.write_batch(wire.key(name, kind), kind, k0, pub[sl], log[sl], payloads)
    return data


def raw_file(path, topics, n=5, payload=None, schema=True):
    """A file written with mcap's own Writer, as another tool would."""
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        for topic in topics:
            kind = topic.rsplit("/", 1)[1]
            sid = (w.register_schema(wire.SCHEMA_NAMES[kind], "jsonschema",
                                     wire.schema_bytes(kind)) if schema and kind in wire.KINDS
                   else 0)
            cid = w.register_channel(topic, "json", sid)
            for k in range(n):
                if kind not in wire.KINDS:  # some other topic of the foreign tool
                    data = b'{"status":"ok"}'
                else:
                    data = payload if payload is not None else wire.encode(
                        k, k * Ts, [float(k), -float(k)], kind=kind)
                w.add_message(cid, log_time=k * 7, data=data, publish_time=k * 10_000_000,
                              sequence=k)
        w.finish()


def raw_json_mcap(path: Path, topic: str, messages: list[tuple[int, bytes]]) -> None:
    """A foreign recording: one JSON channel written with the raw mcap writer, each message
    ``(log and publish time ns, payload)``."""
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="noiselab tests")
        sid = w.register_schema(name="Foreign", encoding="jsonschema", data=b'{"type": "object"}')
        cid = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
        for i, (stamp, data) in enumerate(messages):
            w.add_message(channel_id=cid, log_time=stamp, publish_time=stamp, data=data, sequence=i)
        w.finish()
