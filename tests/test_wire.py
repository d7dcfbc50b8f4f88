"""Wire contract: keys, JSON payloads (bit-exact floats), schemas, integer-ns time."""

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.nodes import wire
from service.nodes.wire import WireError

finite = st.floats(allow_nan=False, allow_infinity=False)


def same_bits(a, b) -> bool:
    """Bit-identical float64 arrays (distinguishes -0.0 from 0.0)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return a.shape == b.shape and np.array_equal(a.view(np.uint64), b.view(np.uint64))


def reference(kind, seq, t, vec) -> bytes:
    """What the contract says the bytes are: compact json.dumps with float vector."""
    obj = {"seq": seq, "t": float(t), wire.VECTOR_FIELD[kind]: [float(v) for v in vec]}
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


# ----------------------------------------------------------------------------- keys


@pytest.mark.parametrize("kind", wire.KINDS)
def test_key_and_parse_key_round_trip(kind):
    k = wire.key("imu_1-a", kind)
    assert k == f"noiselab/imu_1-a/{kind}"
    assert wire.parse_key(k) == ("imu_1-a", kind)
    assert wire.parse_key("/" + k) == ("imu_1-a", kind)


@pytest.mark.parametrize("name", ["", "a/b", "a b", "dev*", "dév", "a.b", None, 3])
def test_invalid_device_names_are_refused_with_one_line_message(name):
    with pytest.raises(WireError) as e:
        wire.key(name, "measurement")
    msg = str(e.value)
    assert "\n" not in msg and repr(name) in msg
    assert isinstance(e.value, ValueError)


def test_unknown_kind_and_malformed_keys():
    with pytest.raises(WireError, match="'state'"):
        wire.key("dev", "state")
    for bad in ["noiselab/dev", "other/dev/truth", "noiselab/dev/truth/x", "noiselab//truth"]:
        with pytest.raises(WireError):
            wire.parse_key(bad)


# -------------------------------------------------------------------------- schemas


@pytest.mark.parametrize("kind", wire.KINDS)
def test_schema_describes_the_payload(kind):
    s = wire.schema(kind)
    field = wire.VECTOR_FIELD[kind]
    assert s["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert s["title"] == wire.SCHEMA_NAMES[kind]
    assert s["type"] == "object"
    assert s["required"] == ["seq", "t", field]
    assert s["properties"]["seq"] == {**s["properties"]["seq"], "type": "integer", "minimum": 0}
    assert s["properties"]["t"]["type"] == "number"
    assert s["properties"][field]["items"] == {"type": "number"}
    # the payload has exactly the schema's properties, in the required order
    payload = json.loads(wire.encode(0, 0.0, [1.0], kind=kind))
    assert list(payload) == s["required"] == list(s["properties"])
    assert json.loads(wire.schema_bytes(kind)) == s


def test_schema_names_are_the_contract():
    assert wire.SCHEMA_NAMES == {"truth": "noiselab.Truth", "command": "noiselab.Command",
                                 "measurement": "noiselab.Measurement",
                                 # extensions for the live pipeline (README "Live pipeline")
                                 "control": "noiselab.Control", "health": "noiselab.Health",
                                 "analysis": "noiselab.Analysis", "end": "noiselab.End"}
    assert wire.VECTOR_FIELD == {"truth": "x", "command": "u", "measurement": "y", "control": "u"}


# ------------------------------------------------------------------------ encoding


@settings(max_examples=200, deadline=None)
@given(seq=st.integers(0, 2**63), t=finite, vec=st.lists(finite, max_size=6),
       kind=st.sampled_from(wire.KINDS))
def test_encode_equals_json_dumps_and_decodes_bit_exact(seq, t, vec, kind):
    data = wire.encode(seq, t, vec, kind=kind)
    assert data == reference(kind, seq, t, vec)
    back = wire.decode(data, kind)
    assert back["seq"] == seq
    assert same_bits(back["t"], t)
    assert same_bits(back[wire.VECTOR_FIELD[kind]], vec)


def test_encode_accepts_numpy_and_ints_and_writes_floats():
    vec = np.array([1, -2, 3], dtype=np.int32)
    assert wire.encode(np.int64(4), np.float64(0.04), vec, kind="command") == \
        b'{"seq":4,"t":0.04,"u":[1.0,-2.0,3.0]}'
    assert wire.encode(0, 0, [], kind="truth") == b'{"seq":0,"t":0.0,"x":[]}'


def tricky_matrix(rng, n, dim):
    """Random float64 with the hard cases: -0.0, subnormals, extremes, many digits."""
    m = rng.standard_normal((n, dim)) * 10.0 ** rng.integers(-300, 300, (n, dim))
    specials = [0.0, -0.0, 5e-324, -2.2250738585072014e-308, 1.7976931348623157e308, 0.1,
                1 / 3, 1e16, 123456789.0]
    m.flat[: len(specials)] = specials
    return m


@pytest.mark.parametrize("kind", wire.KINDS)
@pytest.mark.parametrize("dim", [0, 1, 2, 5])
def test_encode_batch_equals_encode_per_message(kind, dim):
    rng = np.random.default_rng(7)
    n = 300
    mat = tricky_matrix(rng, n, max(dim, 1))[:, :dim]
    t = np.arange(n) * 0.01
    out = wire.encode_batch(kind, 17, t, mat)
    assert out == [wire.encode(17 + i, t[i], mat[i], kind=kind) for i in range(n)]
    assert out == [reference(kind, 17 + i, t[i], mat[i]) for i in range(n)]
    seq, t_back, vals = wire.decode_batch(out, kind)
    assert np.array_equal(seq, np.arange(17, 17 + n)) and seq.dtype == np.int64
    assert same_bits(t_back, t)
    assert vals.shape == (n, dim) and same_bits(vals, mat)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_values_are_refused_naming_the_topic(bad):
    topic = "noiselab/dev/measurement"
    with pytest.raises(WireError, match=r"noiselab/dev/measurement: y\[1\]=.* at seq 9"):
        wire.encode(9, 0.09, [1.0, bad], kind="measurement", topic=topic)
    with pytest.raises(WireError, match=r"noiselab/dev/measurement: t="):
        wire.encode(9, bad, [1.0], kind="measurement", topic=topic)
    mat = np.zeros((5, 2))
    mat[3, 1] = bad
    with pytest.raises(WireError, match=r"noiselab/dev/measurement: y\[1\]=.* at seq 13 "):
        wire.encode_batch("measurement", 10, np.arange(5) * 0.1, mat, topic=topic)
    t = np.arange(5) * 0.1
    t[2] = bad
    with pytest.raises(WireError, match=r"t=.* at seq 12"):
        wire.encode_batch("measurement", 10, t, np.zeros((5, 2)), topic=topic)


@pytest.mark.parametrize("seq", [-1, 1.5, True, "3", None])
def test_bad_seq_refused(seq):
    with pytest.raises(WireError, match="seq"):
        wire.encode(seq, 0.0, [1.0], kind="truth")


@pytest.mark.parametrize("vec", [["1.0"], [True], [[1.0]], "12", None, np.array(["a"])])
def test_non_numbers_in_vector_refused(vec):
    with pytest.raises(WireError, match="noiselab/d/command"):
        wire.encode(0, 0.0, vec, kind="command", topic="noiselab/d/command")


def test_encode_batch_shape_mismatch():
    with pytest.raises(WireError, match=r"\(3,\).*\(4, 2\)"):
        wire.encode_batch("truth", 0, np.zeros(3), np.zeros((4, 2)))


# ------------------------------------------------------------------------ decoding


@pytest.mark.parametrize("payload, match", [
    (b'{"seq":0,"t":0.0,"y":[NaN]}', "NaN"),
    (b'{"seq":0,"t":Infinity,"y":[1.0]}', "Infinity"),
    (b'{"seq":0,"t":0.0,"y":[1e999]}', r"y\[0\]"),
    (b'{"seq":-1,"t":0.0,"y":[1.0]}', "seq=-1"),
    (b'{"seq":1.0,"t":0.0,"y":[1.0]}', "seq=1.0"),
    (b'{"seq":true,"t":0.0,"y":[1.0]}', "seq=True"),
    (b'{"seq":0,"t":"0","y":[1.0]}', "t='0'"),
    (b'{"seq":0,"t":0.0,"y":[true]}', r"y\[0\]=True"),
    (b'{"seq":0,"t":0.0,"y":["1"]}', r"y\[0\]='1'"),
    (b'{"seq":0,"t":0.0,"y":1.0}', "not a list"),
    (b'{"seq":0,"t":0.0}', "exactly one of x, u, y"),
    (b'{"seq":0,"t":0.0,"y":[1.0],"x":[1.0]}', "exactly one of x, u, y"),
    (b'{"seq":0,"t":0.0,"y":[1.0],"extra":1}', "unknown keys \\['extra'\\]"),
    (b'[1, 2]', "JSON object"),
    (b'{"seq":0,', "not valid JSON"),
    (b'\xff\xfe', "not valid JSON"),
])
def test_decode_rejects_contract_violations(payload, match):
    with pytest.raises(WireError, match=match) as e:
        wire.decode(payload, topic="noiselab/dev/measurement")
    assert str(e.value).startswith("noiselab/dev/measurement: ")
    assert "\n" not in str(e.value)


def test_decode_with_kind_requires_that_field():
    with pytest.raises(WireError, match=r"missing keys \['u'\]"):
        wire.decode(b'{"seq":0,"t":0.0,"y":[1.0]}', "command")


def test_decode_batch_slow_path_names_the_culprit():
    good = wire.encode_batch("measurement", 0, np.arange(4) * 0.1, np.ones((4, 2)))
    for bad, match in [(b'{"seq":2,"t":0.2,"y":[1.0,true]}', r"y\[1\]=True at seq 2"),
                       (b'{"seq":2,"t":0.2,"y":[1.0]}', "length 1 at seq 2"),
                       (b'{"seq":2,"t":0.2,"y":[1.0,null]}', r"y\[1\]=None"),
                       (b'{"seq":2,"t":0.2,"y":[1.0,"2"]}', r"y\[1\]='2'")]:
        with pytest.raises(WireError, match=match):
            wire.decode_batch(good[:2] + [bad] + good[3:], "measurement", topic="k")
    # a payload smuggling two objects must not shift the batch
    with pytest.raises(WireError, match="not valid JSON"):
        wire.decode_batch([good[0] + b"," + good[1]], "measurement")
    seq, t, vals = wire.decode_batch([], "truth")
    assert seq.shape == (0,) and t.shape == (0,) and vals.shape == (0, 0)


# ---------------------------------------------------------------------------- time


def test_publish_time_is_exact_integer_ns():
    Ts = 0.01
    Ts_ns = wire.period_ns(Ts)
    assert Ts_ns == 10_000_000 and isinstance(Ts_ns, int)
    ks = range(10**12, 10**12 + 100)  # about 317 years at 100 Hz, far beyond any run
    assert [wire.publish_time_ns(k, Ts_ns) for k in ks] == [k * 10_000_000 for k in ks]
    # the float route (k * Ts * 1e9) is already off by some ns here: the contract forbids it
    assert sum(int(k * Ts * 1e9) != k * 10_000_000 for k in ks) > 50
    assert all(wire.sample_time(k, Ts) == k * Ts for k in ks)


def test_sample_times_match_the_scalar_functions():
    Ts = 1 / 3
    t, pub = wire.sample_times(1000, 50, Ts)
    assert pub.dtype == np.int64 and t.dtype == np.float64
    Ts_ns = wire.period_ns(Ts)
    assert Ts_ns == 333_333_333
    assert pub.tolist() == [wire.publish_time_ns(k, Ts_ns) for k in range(1000, 1050)]
    assert same_bits(t, [wire.sample_time(k, Ts) for k in range(1000, 1050)])


@pytest.mark.parametrize("Ts", [0, -0.01, math.nan, math.inf, 1e-12, "0.01", True])
def test_period_ns_rejects_bad_periods(Ts):
    with pytest.raises(WireError, match="Ts="):
        wire.period_ns(Ts)


def test_health_payload_round_trip_and_validation():
    stats = {name: 1.5 for name in wire.HEALTH_FIELDS}
    stats["k"] = 1000
    data = wire.encode_health(3, 1.0, stats)
    obj = wire.decode_health(data)
    assert obj["seq"] == 3 and obj["k"] == 1000 and obj["lateness_p99_us"] == 1.5
    assert wire.schema("health")["required"] == ["seq", "t", *wire.HEALTH_FIELDS]
    assert wire.key("dev", "health") == "noiselab/dev/health"
    with pytest.raises(wire.WireError):
        wire.encode_health(0, 0.0, {**stats, "overruns": float("nan")})
    with pytest.raises(wire.WireError):
        wire.encode(0, 0.0, [1.0], kind="health")
    with pytest.raises(wire.WireError):
        wire.decode_health(b'{"seq":0,"t":0.0}')


def test_control_is_a_vector_kind():
    data = wire.encode(7, 0.07, [0.25], kind="control")
    assert wire.decode(data, "control") == {"seq": 7, "t": 0.07, "u": [0.25]}
    assert wire.key("dev", "control") == "noiselab/dev/control"


def test_decode_accepts_bytes_bytearray_memoryview_and_str():
    data = wire.encode(5, 0.005, [1.25, -0.5], kind="measurement")
    want = {"seq": 5, "t": 0.005, "y": [1.25, -0.5]}
    for form in (data, bytearray(data), memoryview(data), data.decode()):
        assert wire.decode(form, "measurement") == want
    # one shared decoder: a rejected constant does not leave it in a bad state
    with pytest.raises(WireError, match="NaN"):
        wire.decode(b'{"seq":0,"t":0.0,"y":[NaN]}')
    assert wire.decode(data) == want


@pytest.mark.parametrize("payload", [b"\xef\xbb\xbf" + wire.encode(0, 0.0, [1.0], kind="truth"),
                                     '{"seq":0,"t":0.0,"x":[1.0]}'.encode("utf-16")])
def test_decode_wants_utf8_without_bom(payload):
    with pytest.raises(WireError, match="not valid JSON"):
        wire.decode(payload, "truth", topic="noiselab/dev/truth")


def test_end_payload_round_trip_and_validation():
    counts = {"truth": 10, "command": 10, "measurement": 10, "health": 1}
    data = wire.encode_end(0, 0.009, 10, counts, "duration")
    assert data == (b'{"seq":0,"t":0.009,"samples":10,"counts":{"truth":10,"command":10,'
                    b'"measurement":10,"health":1},"reason":"duration"}')
    assert wire.decode_end(data) == json.loads(data)
    s = wire.schema("end")
    assert s["title"] == "noiselab.End" and s["required"] == list(json.loads(data)) == list(s["properties"])
    assert json.loads(wire.schema_bytes("end")) == s
    assert wire.key("dev", "end") == "noiselab/dev/end" and wire.parse_key("noiselab/dev/end") == ("dev", "end")
    with pytest.raises(WireError):
        wire.encode(0, 0.0, [1.0], kind="end")
    for bad in [dict(reason="crashed"), dict(counts={"state": 1}), dict(counts={"truth": -1}), dict(t=math.inf),
                dict(samples=-1)]:
        args = {"seq": 0, "t": 0.0, "samples": 1, "counts": counts, "reason": "stopped", **bad}
        with pytest.raises(WireError):
            wire.encode_end(**args)
    for bad, match in [(b'{"seq":0,"t":0.0,"samples":1,"counts":{},"reason":"stopped","x":1}', "must have keys"),
                       (b'{"seq":0,"t":0.0,"samples":1,"counts":{"truth":1.5},"reason":"stopped"}', "counts"),
                       (b'{"seq":0,"t":0.0,"samples":true,"counts":{},"reason":"stopped"}', "samples=True"),
                       (b'{"seq":0,"t":0.0,"samples":1,"counts":{},"reason":"over"}', "reason='over'"),
                       (b'{"seq":0,"t":NaN,"samples":1,"counts":{},"reason":"stopped"}', "NaN")]:
        with pytest.raises(WireError, match=match) as e:
            wire.decode_end(bad, topic="noiselab/dev/end")
        assert str(e.value).startswith("noiselab/dev/end: ")
