"""Wire contract: keys, JSON payloads (bit-exact floats), schemas, integer-ns time."""

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from noiselab import wire
from noiselab.wire import WireError

from helpers.models import LOOP_TOML

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
                                 "analysis": "noiselab.Analysis", "end": "noiselab.End",
                                 "controller_health": "noiselab.ControllerHealth"}
    assert wire.VECTOR_FIELD == {"truth": "x", "command": "u", "measurement": "y", "control": "u"}


# ------------------------------------------------------------------------ encoding


@settings(max_examples=200)
@given(seq=st.integers(0, wire.SEQ_MAX), t=finite, vec=st.lists(finite, max_size=6),
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


def test_controller_health_payload_round_trip_and_validation():
    """A controller's health: the emulator's health's shape (seq, t, numbers), its own fields; a
    kind of its own, so neither decoder takes the other's payload."""
    stats = dict.fromkeys(wire.CONTROLLER_HEALTH_FIELDS, 0)
    stats.update(k=500, latency_p99_us=12.5, missing_measurements=2)
    data = wire.encode_controller_health(4, 5.0, stats)
    assert wire.decode_controller_health(data) == {"seq": 4, "t": 5.0, **stats}
    s = wire.schema("controller_health")
    assert s["required"] == ["seq", "t", *wire.CONTROLLER_HEALTH_FIELDS] and s["additionalProperties"] is False
    assert s["title"] == "noiselab.ControllerHealth" and json.loads(wire.schema_bytes("controller_health")) == s
    assert wire.key("dev", "controller_health") == "noiselab/dev/controller_health"
    with pytest.raises(WireError, match="late_replies"):
        wire.encode_controller_health(0, 0.0, {**stats, "late_replies": float("inf")})
    with pytest.raises(WireError, match="controller health payload must have keys"):
        wire.decode_controller_health(wire.encode_health(0, 0.0, dict.fromkeys(wire.HEALTH_FIELDS, 0)))
    with pytest.raises(WireError, match="health payload must have keys"):
        wire.decode_health(data)
    with pytest.raises(WireError, match="not vectors"):
        wire.encode(0, 0.0, [1.0], kind="controller_health")


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


# ------------------------------------------------------------------ untrusted input

DECODERS = {
    "decode": lambda p: wire.decode(p, "measurement", topic="noiselab/d/measurement"),
    "decode_health": lambda p: wire.decode_health(p, topic="noiselab/d/health"),
    "decode_end": lambda p: wire.decode_end(p, topic="noiselab/d/end"),
    "decode_analysis": lambda p: wire.decode_analysis(p, topic="noiselab/d/analysis"),
    "decode_batch": lambda p: wire.decode_batch([p], "measurement", topic="noiselab/d/measurement"),
    # in a batch among good payloads (the fast paths see the blob first)
    "decode_batch, 20": lambda p: wire.decode_batch(GOOD[:10] + [p] + GOOD[10:], "measurement"),
    "decode_packed, 20": lambda p: wire.decode_packed(*packed(GOOD[:10] + [p] + GOOD[10:]), "measurement"),
}
GOOD = wire.encode_batch("measurement", 0, np.arange(19) * 0.01, np.ones((19, 1)))


def packed(payloads: list[bytes]) -> tuple[bytes, np.ndarray]:
    """What the MCAP reader hands to decode_packed: payloads each followed by a newline."""
    return b"".join(p + b"\n" for p in payloads), np.array([len(p) for p in payloads])


DEEP = 200_000             # levels (each payload stays under MAX_PAYLOAD_BYTES: the depth is what is refused)
HOSTILE_DEEP = {
    "arrays": b"[" * DEEP + b"]" * DEEP,
    "objects": b'{"":' * DEEP + b"1" + b"}" * DEEP,
    "unclosed": b"[" * DEEP,
    "inside a sample": b'{"seq":0,"t":0.0,"y":' + b"[" * DEEP + b"]" * DEEP + b"}",
    # a closing bracket inside a string must not hide the real depth (string-aware scan)
    "behind strings": b'["]",' * (DEEP // 2) + b"1" + b"]" * (DEEP // 2),
    "behind escapes": b'["\\"]",' * (DEEP // 2) + b"1" + b"]" * (DEEP // 2),
}


@pytest.mark.parametrize("decoder", DECODERS)
@pytest.mark.parametrize("payload", HOSTILE_DEEP.values(), ids=HOSTILE_DEEP)
def test_deep_nesting_is_refused_before_parsing(decoder, payload):
    """JSON nested 200,000 deep: a WireError naming the bound, from every decode path (Python's
    parser would recurse out of its stack: RecursionError, a crash of the node that read it)."""
    with pytest.raises(WireError, match=f"deeper than {wire.MAX_DEPTH}") as e:
        DECODERS[decoder](payload)
    assert "\n" not in str(e.value) and len(str(e.value)) < 200


def test_nesting_up_to_the_bound_is_parsed():
    """The bound is on the depth, not on the number of brackets: an analysis summary of many
    small lists, strings full of brackets, and exactly MAX_DEPTH levels are parsed."""
    many = {"seq": 0, "t": 1.0, "error": 1.0, "regions": [[i, i + 1] for i in range(1000)],
            "note": "[[[[{{{{" * 100}
    assert wire.decode_analysis(json.dumps(many).encode())["regions"][999] == [999, 1000]
    nested = 1.0
    for _ in range(wire.MAX_DEPTH - 1):               # the payload object itself is one level
        nested = [nested]
    assert wire.decode_analysis(json.dumps({"seq": 0, "t": 1.0, "error": 1.0, "n": nested}).encode())
    with pytest.raises(WireError, match="deeper than"):
        wire.decode_analysis(json.dumps({"seq": 0, "t": 1.0, "error": 1.0, "n": [nested]}).encode())


json_leaves = (st.none() | st.booleans() | st.integers(-10**400, 10**400) | st.floats()
               | st.text(alphabet=st.sampled_from('ab[]{}"\\/:,\n é'), max_size=8))
json_values = st.recursive(json_leaves, lambda inner: st.lists(inner, max_size=4)
                           | st.dictionaries(st.text(alphabet='seqtxuy[]{}"\\', max_size=4), inner, max_size=4),
                           max_leaves=30)


def depth_of(v) -> int:
    if isinstance(v, list):
        return 1 + max(map(depth_of, v), default=0)
    if isinstance(v, dict):
        return 1 + max(map(depth_of, v.values()), default=0)
    return 0


@settings(max_examples=300)
@given(v=json_values)
def test_nesting_depth_of_json_is_exact(v):
    """The byte scan's depth equals the parsed value's, whatever the strings hold (brackets,
    quotes, backslashes), in compact and spaced layouts."""
    for text in (json.dumps(v), json.dumps(v, separators=(",", ":")), json.dumps(v, indent=1, ensure_ascii=False)):
        assert wire.nesting_depth(text.encode()) == depth_of(v)


def test_oversized_payload_is_refused_before_parsing():
    """A payload over MAX_PAYLOAD_BYTES (a 10^6-element vector, 4 MB) is refused by every path
    without parsing it; MAX_PAYLOAD_BYTES itself is parsed."""
    big = b'{"seq":0,"t":0.0,"y":[' + b",".join([b"0.1"] * 10**6) + b"]}"
    for name, decoder in DECODERS.items():
        with pytest.raises(WireError, match=f"{len(big)} bytes exceeds {wire.MAX_PAYLOAD_BYTES}"):
            decoder(big)
    pad = wire.MAX_PAYLOAD_BYTES - len(b'{"seq":0,"t":0.0,"y":[1.0]}')
    at_bound = b'{"seq":0,"t":0.0,"y":[1.0]}' + b" " * pad
    assert len(at_bound) == wire.MAX_PAYLOAD_BYTES
    assert wire.decode(at_bound)["y"] == [1.0]


@pytest.mark.parametrize("payload, match", [
    (b'{"seq":0,"t":1' + b"0" * 400 + b',"y":[1.0]}', "t=1000"),              # an int beyond float64
    (b'{"seq":0,"t":0.0,"y":[-1' + b"0" * 400 + b"]}", r"y\[0\]=-1000"),
    (b'{"seq":9223372036854775808,"t":0.0,"y":[1.0]}', "seq=9223372036854775808"),
    (b'{"seq":100000000000000000000000000,"t":0.0,"y":[1.0]}', "seq="),
    (b'{"seq":0,"t":0.0,"y":["' + b"a" * 500_000 + b'"]}', r"y\[0\]='aaaa"),   # named, not echoed
    (b'{"seq":0,"t":0.0,"y":[1.0],"' + b"k" * 500_000 + b'":1}', "unknown keys"),
])
def test_numbers_and_strings_beyond_range_are_refused_in_one_short_line(payload, match):
    for name in ("decode", "decode_batch, 20", "decode_packed, 20"):
        with pytest.raises(WireError, match=match) as e:
            DECODERS[name](payload)
        assert "\n" not in str(e.value) and len(str(e.value)) < 200, name


def test_health_and_end_refuse_ints_beyond_float64():
    stats = dict.fromkeys(wire.HEALTH_FIELDS, 1)
    health = json.dumps({"seq": 0, "t": 0.0, **stats, "overruns": 10**400}).encode()
    with pytest.raises(WireError, match="overruns=1000"):
        wire.decode_health(health)
    end = json.dumps({"seq": 0, "t": 10**400, "samples": 1, "counts": {}, "reason": "stopped"}).encode()
    with pytest.raises(WireError, match="t=1000"):
        wire.decode_end(end)


def test_seq_fits_in_int64_everywhere():
    assert wire.decode(wire.encode(wire.SEQ_MAX, 0.0, [1.0], kind="truth"))["seq"] == wire.SEQ_MAX
    for bad in (wire.SEQ_MAX + 1, 10**26):
        with pytest.raises(WireError, match="2\\*\\*63-1"):
            wire.encode(bad, 0.0, [1.0], kind="truth")
    with pytest.raises(WireError, match="exceeds 2\\*\\*63-1"):
        wire.encode_batch("truth", wire.SEQ_MAX, [0.0, 0.01], np.ones((2, 1)))


def test_control_elements_are_bounded_by_magnitude_max():
    """A control drives the emulator's plant: beyond MAGNITUDE_MAX it is refused on encode and on
    every decode path; the bound itself passes; measurements are not bounded by the contract."""
    ok = wire.encode(0, 0.0, [wire.MAGNITUDE_MAX, -wire.MAGNITUDE_MAX], kind="control")
    assert wire.decode(ok, "control")["u"] == [1e50, -1e50]
    with pytest.raises(WireError, match=r"u\[1\]=-1e\+51 at seq 3 exceeds 1e\+50"):
        wire.encode(3, 0.0, [0.0, -1e51], kind="control", topic="noiselab/d/control")
    mat = np.zeros((20, 1))
    mat[7, 0] = 1e308
    with pytest.raises(WireError, match="seq 7 exceeds"):
        wire.encode_batch("control", 0, np.arange(20) * 0.01, mat)
    hostile = b'{"seq":7,"t":0.07,"u":[1e308]}'
    good = wire.encode_batch("control", 0, np.arange(20) * 0.01, np.zeros((20, 1)))
    batch = good[:7] + [hostile] + good[8:]
    for decoder in (lambda: wire.decode(hostile, "control"), lambda: wire.decode_batch(batch, "control"),
                    lambda: wire.decode_packed(*packed(batch), "control")):
        with pytest.raises(WireError, match=r"u\[0\]=1e\+308 at seq 7 exceeds"):
            decoder()
    assert wire.decode(b'{"seq":7,"t":0.07,"u":[1e308]}', "command")["u"] == [1e308]


def test_decode_batch_fast_path_takes_nothing_decode_refuses():
    """The json fast path parses the batch as one array: a payload may not lend half an object to
    its neighbour, nor a non-scalar t pass as a column."""
    merged = [b'{"seq":0,"t":0,"y":[1,1]},{"seq":1,"t":0,"y":[1', b"2]}"] + \
        [json.dumps({"t": 0, "y": [1, 1], "seq": k}).encode() for k in range(2, 20)]
    with pytest.raises(WireError, match="not valid JSON"):
        wire.decode_batch(merged, "measurement")
    listed_t = [json.dumps({"t": [0.5], "y": [1.0], "seq": k}).encode() for k in range(20)]
    with pytest.raises(WireError, match=r"t=\[0.5\] at seq 0"):
        wire.decode_batch(listed_t, "measurement")


# ------------------------------------------------------------ properties of the decoders

ANY_DECODER = [lambda p: wire.decode(p), lambda p: wire.decode(p, "control"), wire.decode_health,
               wire.decode_end, wire.decode_analysis, wire.decode_controller_health]


def result_or_wire_error(fn, *args):
    """fn(*args), or None when it raises WireError; any other exception fails the test."""
    try:
        return fn(*args)
    except WireError as e:
        assert "\n" not in str(e) and len(str(e)) < 400, str(e)
        return None


@settings(max_examples=400)
@given(data=st.binary(max_size=200))
def test_any_bytes_give_a_result_or_a_wire_error(data):
    for decoder in ANY_DECODER:
        result_or_wire_error(decoder, data)
    result_or_wire_error(wire.decode_batch, [data] * 3, "measurement")
    result_or_wire_error(wire.decode_packed, *packed([data, data]), "truth")


numberish = st.floats() | st.integers(-10**400, 10**400)          # NaN/inf, and ints beyond float64
seqish = st.integers(-2, 2**64) | json_values
optional_extra = {"extra": json_values}
# payloads shaped like each kind's (the right keys, values valid or not), so that the decoders'
# checks past the parse are reached, not only the key check
vector_like = st.sampled_from("xuy").flatmap(lambda f: st.fixed_dictionaries(
    {"seq": seqish, "t": numberish | json_values, f: st.lists(numberish, max_size=3) | json_values},
    optional=optional_extra))
health_like = st.fixed_dictionaries(
    {"seq": seqish, "t": numberish, **{name: numberish | json_values for name in wire.HEALTH_FIELDS}},
    optional=optional_extra)
end_like = st.fixed_dictionaries(
    {"seq": seqish, "t": numberish | json_values, "samples": seqish,
     "counts": st.dictionaries(st.sampled_from([*wire.ALL_KINDS, "state"]), seqish, max_size=3) | json_values,
     "reason": st.sampled_from([*wire.END_REASONS, "crashed"]) | json_values}, optional=optional_extra)
analysis_like = st.fixed_dictionaries({"seq": seqish, "t": numberish | json_values, "error": json_values},
                                      optional=optional_extra)
sample_like = vector_like | health_like | end_like | analysis_like


@settings(max_examples=500)
@given(v=json_values | sample_like, spaced=st.booleans())
def test_any_json_value_gives_a_result_or_a_wire_error(v, spaced):
    data = json.dumps(v, separators=(", ", ": ") if spaced else (",", ":")).encode()
    for decoder in ANY_DECODER:
        result_or_wire_error(decoder, data)


def as_payload(draw_kind, obj, layout):
    if layout == "wire":
        return wire.encode(obj["seq"], obj["t"], obj["y"], kind="measurement")
    if layout == "spaced":
        return json.dumps(obj).encode()
    return json.dumps(dict(reversed(list(obj.items()))), separators=(",", ":")).encode()


good_sample = st.fixed_dictionaries({"seq": st.integers(0, wire.SEQ_MAX), "t": finite | st.integers(-2**70, 2**70),
                                     "y": st.lists(finite | st.integers(-2**70, 2**70), min_size=2, max_size=2)})
payloads = st.lists(st.one_of(
    st.tuples(good_sample, st.sampled_from(["wire", "spaced", "reordered"])).map(
        lambda a: as_payload(None, *a) if a[1] != "wire" else wire.encode(
            a[0]["seq"], a[0]["t"], a[0]["y"], kind="measurement")),
    (json_values | sample_like).map(lambda v: json.dumps(v).encode()),
    st.binary(max_size=40)), min_size=1, max_size=8)


@settings(max_examples=500)
@given(batch=payloads)
def test_decode_batch_and_packed_equal_decode_message_by_message(batch):
    """decode_batch (and decode_packed on the same payloads) either raises a WireError exactly
    when a payload fails decode or the lengths differ, or returns decode's values bit for bit."""
    single = [result_or_wire_error(wire.decode, p, "measurement") for p in batch]
    ok = all(d is not None for d in single) and len({len(d["y"]) for d in single}) == 1
    for got in (result_or_wire_error(wire.decode_batch, batch, "measurement"),
                result_or_wire_error(wire.decode_packed, *packed(batch), "measurement")):
        assert (got is not None) == ok, (batch, single)
        if ok:
            seq, t, vals = got
            assert seq.dtype == np.int64 and seq.tolist() == [d["seq"] for d in single]
            assert same_bits(t, [d["t"] for d in single])
            assert same_bits(vals, np.array([d["y"] for d in single], dtype=np.float64).reshape(len(batch), -1))


@settings(max_examples=200)
@given(seq0=st.integers(0, 2**62), n=st.integers(1, 30), dim=st.integers(1, 4), data=st.data(),
       kind=st.sampled_from([*wire.KINDS, wire.CONTROL]))
def test_batches_round_trip_exactly(seq0, n, dim, data, kind):
    elem = st.floats(-wire.MAGNITUDE_MAX, wire.MAGNITUDE_MAX) if kind == wire.CONTROL else finite
    t = np.array(data.draw(st.lists(finite, min_size=n, max_size=n)))
    mat = np.array(data.draw(st.lists(st.lists(elem, min_size=dim, max_size=dim), min_size=n, max_size=n)))
    enc = wire.encode_batch(kind, seq0, t, mat)
    for seq, tt, vals in (wire.decode_batch(enc, kind), wire.decode_packed(*packed(enc), kind)):
        assert seq.tolist() == list(range(seq0, seq0 + n))
        assert same_bits(tt, t) and same_bits(vals, mat)


@settings(max_examples=200)
@given(seq=st.integers(0, wire.SEQ_MAX), t=finite, samples=st.integers(0, wire.SEQ_MAX),
       counts=st.dictionaries(st.sampled_from(wire.ALL_KINDS), st.integers(0, wire.SEQ_MAX)),
       reason=st.sampled_from(wire.END_REASONS), stats=st.fixed_dictionaries(
           {name: finite | st.integers(-2**70, 2**70) for name in wire.HEALTH_FIELDS}))
def test_health_and_end_round_trip_exactly(seq, t, samples, counts, reason, stats):
    h = wire.decode_health(wire.encode_health(seq, t, stats))
    assert h["seq"] == seq and same_bits(h["t"], t)
    assert all(h[k] == v and type(h[k]) is type(v if isinstance(v, int) else float(v)) for k, v in stats.items())
    e = wire.decode_end(wire.encode_end(seq, t, samples, counts, reason))
    assert e == {"seq": seq, "t": e["t"], "samples": samples, "counts": counts, "reason": reason}
    assert same_bits(e["t"], t)


def test_one_magnitude_bound_from_the_wire_to_the_analysis(tmp_path):
    """One bound for every number noiselab computes with: the wire's (controls), the model files'
    and the recordings' loader are one value (1e50). A control of 1e60 is refused by the wire
    (accepted, it drove the plant to y ~ 4e55, a recording the loader refuses); a plant driven
    by the largest control the wire accepts, for one sample, gives a recording the loader
    analyses."""
    from noiselab import bounds
    from noiselab.model import parse_model, schema
    from noiselab.recordings import load
    from noiselab.recordings.series import MAGNITUDE_MAX as SERIES_MAX
    from noiselab.recordings.writer import RecordingWriter

    assert wire.MAGNITUDE_MAX is bounds.MAGNITUDE_MAX is schema.MAGNITUDE_MAX is SERIES_MAX
    with pytest.raises(WireError, match="exceeds 1e\\+50"):
        wire.decode(b'{"seq":0,"t":0.0,"u":[1e60]}', "control")
    model = parse_model(LOOP_TOML, "loop")
    largest = wire.decode(wire.encode(0, 0.0, [wire.MAGNITUDE_MAX], kind="control"), "control")["u"]
    stepper = model.stepper(seed=1)
    path = tmp_path / "u-max.mcap"
    with RecordingWriter(path) as w:
        for k in range(400):
            _, x, u, y = stepper.step(largest if k == 200 else [0.0])
            pub = wire.publish_time_ns(k, wire.period_ns(model.Ts))
            for kind, v in (("truth", x), ("command", u), ("measurement", y)):
                w.write(wire.key("loop", kind), kind, k, pub, pub, wire.encode(k, wire.sample_time(k, model.Ts), v, kind=kind))
    series = load.load_noiselab(path, model=model)
    assert series.y.shape == (400, 1) and np.abs(series.y).max() > 1e40


def test_zenoh_encoding_names_the_schema():
    for kind in wire.ALL_KINDS:
        assert wire.zenoh_encoding(kind) == f"application/json;{wire.SCHEMA_NAMES[kind]}"
    with pytest.raises(WireError, match="unknown"):
        wire.zenoh_encoding("state")


def test_anchor_round_trip_and_anchored_publish_time():
    """The attachment states the start; publish_time = start + round(t 1e9), exact in int64 (a
    float64 epoch in ns would keep only ~0.25 us), refused when t is negative or past int64."""
    start = 1_760_000_000_123_456_789
    assert wire.decode_anchor(wire.encode_anchor(start)) == start
    assert wire.encode_anchor(start) == json.dumps({"start_time_ns": start}, separators=(",", ":")).encode()
    for bad in (-1, wire.START_MAX + 1, 1.0, True):
        with pytest.raises(WireError, match="start_time_ns"):
            wire.encode_anchor(bad)
    Ts = 1 / 3
    assert [wire.anchored_ns(start, wire.sample_time(k, Ts)) for k in (0, 1, 3)] == [
        start, start + 333_333_333, start + 1_000_000_000]
    assert wire.anchored_ns(wire.START_MAX, 2**62 / 1e9 - 1) < 2**63
    for t in (-1e-9, math.nan, math.inf):
        with pytest.raises(WireError, match="sample time"):
            wire.anchored_ns(start, t)
    with pytest.raises(WireError, match="exceeds"):
        wire.anchored_ns(wire.SEQ_MAX - 5, 1.0)
