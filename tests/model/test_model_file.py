"""The model file (DESIGN.md "The model file"; STYLE 5 and 6): every bad file is one ModelError.

1. A catalogue of bad files, each rejected with a one-line message that names the source, the table
   and key, and what was expected.
2. A property test: garbled model files (raw text edits and structured TOML mutations) either parse
   to a Model (which then writes back to an equal model) or raise a one-line ModelError, nothing else.
3. The CLI: bad input exits 2 with one line on stderr; an existing output file is not overwritten.
4. Built-in scenarios by name and by path, Model.to_toml() round trips, with_effect/without_effect.
5. A general plant with two rows of C gives a vector measurement.
"""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from noiselab.model import ModelError, dumps_toml, load_model, parse_model, scenario_names
from noiselab.model.effects import CATALOGUE
from noiselab.model.model import scenario_text

SEED = scenario_text("seed")

# A general continuous plant, two inputs and two outputs, with every effect of the catalogue and
# channel-dependent (vector) parameters.
GENERAL = """\
name = "general-2x2"
description = "general A, B, C plant: two inputs, two outputs, every effect"

[sampling]
Ts = 0.01
discretization = "zoh"

[plant]
A = [[0.0, 1.0, 0.0], [-4.0, -0.5, 1.0], [0.0, 0.0, -2.0]]
B = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]
C = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.5]]
D = [[0.0, 0.0], [0.0, 0.1]]
L = [[0.0], [1.0], [0.5]]

[command]
kind = "sine"
amplitude = [0.8, 0.3]
frequency_hz = [0.7, 1.3]

[process.white]
psd = 0.04

[actuator.white]
std = [0.05, 0.02]

[actuator.ar1]
std = [0.08, 0.04]
tau_s = [0.3, 0.1]

[actuator.lag]
tau_s = [0.02, 0.05]

[actuator.saturation]
limit = [5.0, 3.0]

[actuator.deadzone]
width = [0.01, 0.02]

[sensor.scale_factor]
error = [0.02, -0.01]

[sensor.bias_walk]
std = [0.002, 0.001]
initial_std = [0.01, 0.0]

[sensor.bias_markov]
std = [0.003, 0.002]
tau_s = [2.0, 5.0]

[sensor.bias_instability]
B = [0.002, 0.001]
f_lo_hz = 0.001

[sensor.white]
std = [0.01, 0.02]

[sensor.integral_white]
Q = [2e-5, 1e-5]

[sensor.tone]
amplitude = [0.005, 0.002]
frequency_hz = [20.0, 12.5]

[sensor.filter]
kind = "lowpass2"
cutoff_hz = [30.0, 15.0]

[sensor.jitter]
std_s = 0.0005

[sensor.quantization]
step = [0.001, 0.002]
"""


def sub(text: str, old: str, new: str) -> str:
    """Replace the one occurrence of ``old`` (the test's own edit must hit exactly one place)."""
    assert text.count(old) == 1, f"{old!r} occurs {text.count(old)} times"
    return text.replace(old, new)


def edited(text: str, sets: dict | None = None, drops: tuple = ()) -> str:
    """The model file ``text`` with keys set or dropped, paths as tuples: ("sensor", "white", "std")."""
    d = tomllib.loads(text)
    for path in drops:
        node = d
        for k in path[:-1]:
            node = node[k]
        del node[path[-1]]
    for path, value in (sets or {}).items():
        node = d
        for k in path[:-1]:
            node = node.setdefault(k, {})
        node[path[-1]] = value
    return dumps_toml(d)


def assert_one_line_error(exc: ModelError, source: str, *parts: str) -> str:
    msg = str(exc)
    assert isinstance(exc, ValueError)
    assert "\n" not in msg and "\r" not in msg, msg
    assert msg.startswith(f"{source}: "), msg
    for part in parts:
        assert part in msg, f"{part!r} not in {msg!r}"
    return msg


def model_signature(m) -> dict:
    """Everything that defines a model's behaviour (not where it was read from)."""
    return {
        "name": m.name, "description": m.description, "Ts": m.Ts, "discretization": m.discretization,
        "plant": [m.plant.A, m.plant.B, m.plant.C, m.plant.D, m.plant.L],
        "command": (m.command.kind, m.command.m,
                    {k: np.asarray(v).tolist() for k, v in m.command.params.items()}),
        "effects": {eid: eff.param_dict() for eid, eff in m.effects.items()},
        "assembled": [m.Ac, m.Bc, m.Cy, m.Dy, m.L, m.Ad, m.Bd, m.S_proc, m.out_gain],
        "n_normals": m.n_normals,
    }


def assert_same_model(a, b) -> None:
    sa, sb = model_signature(a), model_signature(b)
    for key in sa:
        if key in ("plant", "assembled"):
            assert len(sa[key]) == len(sb[key])
            for x, y in zip(sa[key], sb[key]):
                np.testing.assert_array_equal(x, y, err_msg=key)
        else:
            assert sa[key] == sb[key], key


# -- 1. the catalogue of bad files ----------------------------------------------------------------
# an unstable pole at 1/s: over Ts = 400 s Van Loan's Q_d (about psd e^(2 Ts) / 2) overflows float64
# while A_d = e^Ts does not; over Ts = 1000 s A_d overflows too (Ts and psd within their bounds)
UNSTABLE = 'name = "unstable"\n[sampling]\nTs = 400.0\n[plant]\nA = [[1.0]]\nB = [[1.0]]\nC = [[1.0]]\n'
OVERFLOW_QD = UNSTABLE + "[process.white]\npsd = 1.0\n"
# a plain two-input, two-output plant without effects, two process-noise channels
PLAIN_2X2 = edited(GENERAL, {("plant", "L"): [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]},
                   drops=[("process",), ("actuator",), ("sensor",)])
NAN_ENTRY_A = "A = [[0.0, 1.0, 0.0], [-4.0, -0.5, 1.0], [0.0, 0.0, nan]]"
BAD_FILES = {
    # unknown keys and tables (STYLE 6)
    "unknown top-level key": (SEED + 'colour = "red"\n', ("colour", "unknown key")),
    "misplaced Ts at top level": (sub(SEED, 'name = "seed"', 'name = "seed"\nTs = 0.01'), ("Ts", "unknown key")),
    "unknown table": (SEED + "\n[extras]\nx = 1\n", ("extras", "unknown key")),
    "unknown group": (SEED + "\n[sensors.white]\nstd = 0.1\n", ("sensors", "unknown key")),
    "unknown effect": (SEED + "\n[sensor.foo]\nstd = 0.1\n", ("[sensor.foo]", "unknown effect", "sensor.white")),
    "unknown key in effect": (sub(SEED, "std = 0.01 ", "std = 0.01\nstdd = 0.02 "),
                              ("[sensor.white] stdd", "unknown key", "std")),
    "misspelled required key": (sub(SEED, "std = 0.01 ", "stdd = 0.01 "),
                                ("[sensor.white] std", "missing required key")),
    "unknown key in sampling": (sub(SEED, "Ts = 0.01", "Ts = 0.01\nts = 0.02"), ("[sampling] ts", "unknown key")),
    "unknown key in plant": (sub(SEED, "k = 4.0", "k = 4.0\nkk = 1.0"), ("[plant] kk", "unknown key")),
    "unknown key in command": (sub(SEED, 'kind = "sine"', 'kind = "sine"\nfreq = 1.0'),
                               ("[command] freq", "unknown key")),
    "effect is not a table": (edited(SEED, {("sensor", "tone"): 3}), ("[sensor.tone]", "expected a table")),
    "group is not a table": (edited(SEED, drops=[("sensor",)], sets={("sensor",): [1, 2]}),
                             ("sensor", "expected effect tables like [sensor.<effect>]")),
    # missing required keys
    "missing name": (edited(SEED, drops=[("name",)]), ("name", "missing required key")),
    "missing sampling": (edited(SEED, drops=[("sampling",)]), ("sampling", "missing required table")),
    "missing Ts": (edited(SEED, drops=[("sampling", "Ts")]), ("[sampling] Ts", "missing required key")),
    "missing plant": (edited(SEED, drops=[("plant",)]), ("plant", "missing required table")),
    "missing plant m": (edited(SEED, drops=[("plant", "m")]), ("[plant] m", "missing required key")),
    "missing plant B": (edited(GENERAL, drops=[("plant", "B")]), ("[plant] B", "missing required key")),
    "missing effect std": (edited(SEED, drops=[("actuator", "ar1", "std")]),
                           ("[actuator.ar1] std", "missing required key")),
    "missing tone frequency": (edited(GENERAL, drops=[("sensor", "tone", "frequency_hz")]),
                               ("[sensor.tone] frequency_hz", "missing required key")),
    "missing command amplitude": (edited(SEED, drops=[("command", "amplitude")]),
                                  ("[command] amplitude", "missing required key")),
    # wrong types
    "string Ts": (edited(SEED, {("sampling", "Ts"): "0.01"}), ("[sampling] Ts", "expected", "'0.01'")),
    "bool mass": (edited(SEED, {("plant", "m"): True}), ("[plant] m", "expected", "True")),
    "string std": (edited(SEED, {("sensor", "white", "std"): "small"}), ("[sensor.white] std", "expected")),
    "bool in matrix": (edited(GENERAL, {("plant", "C"): [[1.0, 0.0, True], [0.0, 1.0, 0.5]]}),
                       ("[plant] C", "expected a matrix")),
    "ragged matrix": (edited(GENERAL, {("plant", "A"): [[0.0, 1.0, 0.0], [-4.0, -0.5], [0.0, 0.0, -2.0]]}),
                      ("[plant] A", "equal-length rows")),
    "list of wrong length (output)": (edited(GENERAL, {("sensor", "white", "std"): [0.1, 0.2, 0.3]}),
                                      ("[sensor.white] std", "a list of 2 numbers")),
    "list of wrong length (input)": (edited(GENERAL, {("actuator", "white", "std"): [0.1, 0.2, 0.3]}),
                                     ("[actuator.white] std", "a list of 2 numbers")),
    "command amplitude of wrong length": (edited(GENERAL, {("command", "amplitude"): [1.0, 2.0, 3.0]}),
                                          ("[command] amplitude", "a list of 2 numbers")),
    "scalar jitter given a list": (edited(GENERAL, {("sensor", "jitter", "std_s"): [0.001, 0.001]}),
                                   ("[sensor.jitter] std_s", "expected")),
    "unknown discretization": (edited(SEED, {("sampling", "discretization"): "tustin"}),
                               ("[sampling] discretization", "'zoh'", "'euler'", "'tustin'")),
    "unknown command kind": (edited(SEED, {("command", "kind"): "square"}), ("[command] kind", "'sine'")),
    "integer beyond float64": (edited(SEED, {("sampling", "Ts"): 10**400}), ("[sampling] Ts", "expected")),
    "integer beyond float64 in a list": (edited(GENERAL, {("sensor", "white", "std"): [1, -(10**400)]}),
                                         ("[sensor.white] std", "expected")),
    # impossible values
    "Ts zero": (edited(SEED, {("sampling", "Ts"): 0.0}), ("[sampling] Ts", "> 0", "got 0.0")),
    "Ts negative": (edited(SEED, {("sampling", "Ts"): -0.01}), ("[sampling] Ts", "> 0", "got -0.01")),
    # out of the sample period's range, 1 us to a day: Ts = 1e300 overflowed the mean response
    # (OverflowError in lsim), Ts = 1e-300 asked numpy for its horizon's 6e301 samples (ValueError)
    "Ts huge": (edited(SEED, {("sampling", "Ts"): 1e300}), ("[sampling] Ts", "between 1e-06", "86400", "got 1e+300")),
    "Ts above a day": (edited(SEED, {("sampling", "Ts"): 86401.0}), ("[sampling] Ts", "86400", "got 86401.0")),
    "Ts tiny": (edited(SEED, {("sampling", "Ts"): 1e-300}), ("[sampling] Ts", "1e-06", "got 1e-300")),
    "Ts below 1 us": (edited(SEED, {("sampling", "Ts"): 9e-7}), ("[sampling] Ts", "1e-06", "got 9e-07")),
    # magnitudes whose squares or fourth powers overflow float64
    "sensor white std 1e300": (edited(SEED, {("sensor", "white", "std"): 1e300}),
                               ("[sensor.white] std", "magnitude at most 1e+50", "float64", "got 1e+300")),
    "one channel's std 1e51": (edited(GENERAL, {("sensor", "bias_markov", "std"): [0.1, 1e51]}),
                               ("[sensor.bias_markov] std", "magnitude at most 1e+50")),
    "mass 1e60": (edited(SEED, {("plant", "m"): 1e60}), ("[plant] m", "magnitude at most 1e+50", "got 1e+60")),
    "huge entry of A": (edited(GENERAL, {("plant", "A"): [[0.0, 1.0, 0.0], [-4.0, -0.5, 1.0], [0.0, 0.0, -1e51]]}),
                        ("[plant] A", "magnitude at most 1e+50")),
    "huge command amplitude": (edited(SEED, {("command", "amplitude"): -1e300}),
                               ("[command] amplitude", "magnitude at most 1e+50")),
    "integer of 60 digits": (edited(SEED, {("sensor", "quantization", "step"): 10**60}),
                             ("[sensor.quantization] step", "magnitude at most 1e+50")),
    # a correlation time whose rho = exp(-Ts / tau_s) rounds to 1 (a singular stationary covariance:
    # LinAlgError in the prediction)
    "markov tau_s beyond 1e15 Ts": (edited(GENERAL, {("sensor", "bias_markov", "tau_s"): 1e50}),
                                    ("[sensor.bias_markov] tau_s", "at most 1e+15 Ts")),
    "ar1 tau_s beyond 1e15 Ts": (edited(GENERAL, {("actuator", "ar1", "tau_s"): [0.3, 1e14]}),
                                 ("[actuator.ar1] tau_s", "at most 1e+15 Ts = 1e+13 s")),
    "prbs bit shorter than a sample": (edited(SEED, {("command",): {"kind": "prbs", "amplitude": 1.0, "bit_s": 1e-50}}),
                                       ("[command] bit_s", ">= Ts = 0.01")),
    "negative std": (edited(SEED, {("sensor", "white", "std"): -0.01}), ("[sensor.white] std", ">= 0")),
    "negative std in one channel": (edited(GENERAL, {("sensor", "bias_markov", "std"): [0.1, -0.1]}),
                                    ("[sensor.bias_markov] std", ">= 0")),
    "rho one": (edited(SEED, {("actuator", "ar1", "rho"): 1.0}), ("[actuator.ar1] rho", "|rho| < 1")),
    "rho minus one": (edited(SEED, {("actuator", "ar1", "rho"): -1.0}), ("[actuator.ar1] rho", "|rho| < 1")),
    "rho above one": (edited(SEED, {("actuator", "ar1", "rho"): 1.5}), ("[actuator.ar1] rho", "|rho| < 1")),
    "ar1 tau_s zero": (edited(GENERAL, {("actuator", "ar1", "tau_s"): 0.0}), ("[actuator.ar1] tau_s", "> 0")),
    "lag tau_s negative": (edited(GENERAL, {("actuator", "lag", "tau_s"): [0.1, -0.1]}),
                           ("[actuator.lag] tau_s", "> 0")),
    "markov tau_s zero": (edited(GENERAL, {("sensor", "bias_markov", "tau_s"): 0}),
                          ("[sensor.bias_markov] tau_s", "> 0")),
    "mass zero": (edited(SEED, {("plant", "m"): 0.0}), ("[plant] m", "> 0")),
    "mass negative": (edited(SEED, {("plant", "m"): -1.2}), ("[plant] m", "> 0")),
    "damping negative": (edited(SEED, {("plant", "c"): -0.1}), ("[plant] c", ">= 0")),
    "saturation limit zero": (edited(GENERAL, {("actuator", "saturation", "limit"): 0.0}),
                              ("[actuator.saturation] limit", "> 0")),
    "quantization step zero": (edited(SEED, {("sensor", "quantization", "step"): 0.0}),
                               ("[sensor.quantization] step", "> 0")),
    "scale factor -1": (edited(GENERAL, {("sensor", "scale_factor", "error"): -1.0}),
                        ("[sensor.scale_factor] error", "> -1")),
    "non-square A": (edited(GENERAL, {("plant", "A"): [[0.0, 1.0, 0.0], [-4.0, -0.5, 1.0]]}),
                     ("[plant] A", "square", "2 x 3")),
    "B rows != A rows": (edited(GENERAL, {("plant", "B"): [[0.0, 0.0], [1.0, 0.0]]}),
                         ("[plant] B", "shape 3 x any", "got 2 x 2")),
    "C cols != n": (edited(GENERAL, {("plant", "C"): [[1.0, 0.0], [0.0, 1.0]]}),
                    ("[plant] C", "shape any x 3", "got 2 x 2")),
    "D wrong shape": (edited(GENERAL, {("plant", "D"): [[0.0, 0.0, 0.0], [0.0, 0.1, 0.0]]}),
                      ("[plant] D", "shape 2 x 2", "got 2 x 3")),
    "L rows != n": (edited(GENERAL, {("plant", "L"): [[1.0], [0.5]]}), ("[plant] L", "shape 3 x any")),
    "empty matrix": (edited(GENERAL, {("plant", "A"): []}), ("[plant] A", "expected a matrix")),
    # NaN and inf (TOML literals)
    "Ts nan": (sub(SEED, "Ts = 0.01", "Ts = nan"), ("[sampling] Ts", "got nan")),
    "Ts inf": (sub(SEED, "Ts = 0.01", "Ts = inf"), ("[sampling] Ts", "got inf")),
    "mass inf": (sub(SEED, "m = 1.2", "m = +inf"), ("[plant] m", "got inf")),
    "std -inf": (sub(SEED, "std = 0.01 ", "std = -inf "), ("[sensor.white] std", "got -inf")),
    "std nan in a list": (sub(GENERAL, "std = [0.01, 0.02]", "std = [0.01, nan]"),
                          ("[sensor.white] std", "expected", "got [0.01, nan]")),
    "rho nan": (sub(SEED, "rho = 0.97", "rho = nan"), ("[actuator.ar1] rho", "nan")),
    "nan inside A": (sub(GENERAL, "A = [[0.0, 1.0, 0.0], [-4.0, -0.5, 1.0], [0.0, 0.0, -2.0]]", NAN_ENTRY_A),
                     ("[plant] A", "finite")),
    "inf inside B": (sub(GENERAL, "B = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]", "B = [[0.0, 0.0], [inf, 0.0], [0.0, 1.0]]"),
                     ("[plant] B", "finite")),
    "1e999 overflows to inf": (sub(SEED, "k = 4.0", "k = 1e999"), ("[plant] k", "got inf")),
    # one of two parameterisations, exactly
    "ar1 with rho and tau_s": (edited(SEED, {("actuator", "ar1", "tau_s"): 0.3}),
                               ("[actuator.ar1] rho", "exactly one of rho", "tau_s")),
    "ar1 with neither": (edited(SEED, drops=[("actuator", "ar1", "rho")]),
                         ("[actuator.ar1] rho", "exactly one of rho", "tau_s")),
    "markov with neither": (edited(GENERAL, drops=[("sensor", "bias_markov", "tau_s")]),
                            ("[sensor.bias_markov] rho", "exactly one")),
    "process white with std and psd": (edited(SEED, {("process", "white", "psd"): 0.1}),
                                       ("[process.white] std", "exactly one of std", "psd")),
    "process white with neither": (sub(SEED, "std = 0.20 ", ""),
                                   ("[process.white] std", "exactly one of std", "psd")),
    # sampling limits
    "tone above Nyquist": (edited(GENERAL, {("sensor", "tone", "frequency_hz"): [20.0, 60.0]}),
                           ("[sensor.tone] frequency_hz", "Nyquist frequency 50")),
    "tone at Nyquist": (edited(GENERAL, {("sensor", "tone", "frequency_hz"): 50.0}),
                        ("[sensor.tone] frequency_hz", "Nyquist")),
    "jitter std_s equal to Ts": (edited(GENERAL, {("sensor", "jitter", "std_s"): 0.01}),
                                 ("[sensor.jitter] std_s", "std_s < Ts = 0.01")),
    "jitter std_s above Ts": (edited(GENERAL, {("sensor", "jitter", "std_s"): 0.5}),
                              ("[sensor.jitter] std_s", "std_s < Ts")),
    "discretization overflows": (sub(UNSTABLE, "Ts = 400.0", "Ts = 1000.0"), ("[plant]", "[sampling] Ts", "finite")),
    "process noise covariance overflows": (OVERFLOW_QD, ("[process.white] psd", "finite")),
    # syntax and names
    "invalid TOML": (sub(SEED, "Ts = 0.01", "Ts = = 0.01"), ("invalid TOML", "line 8")),
    "unterminated table header": (SEED + "\n[sensor.white\n", ("invalid TOML",)),
    "duplicate key": (sub(SEED, "k = 4.0", "k = 4.0\nk = 5.0"), ("invalid TOML",)),
    "integer literal too long for Python": (sub(SEED, "k = 4.0", "k = 1" + "0" * 5000), ("invalid TOML",)),
    "arrays nested too deeply": (SEED + "\nx = " + "[" * 3000 + "]" * 3000 + "\n", ("invalid TOML", "nested")),
    "name with a slash": (sub(SEED, 'name = "seed"', 'name = "lab/seed"'), ("name", "device name", "'lab/seed'")),
    "name with a space": (sub(SEED, 'name = "seed"', 'name = "my seed"'), ("name", "device name")),
    "name with a trailing newline": (sub(SEED, 'name = "seed"', 'name = "seed\\n"'), ("name", "device name")),
    "empty name": (sub(SEED, 'name = "seed"', 'name = ""'), ("name", "device name")),
    "plant with m, c, k and A, B, C": (
        edited(GENERAL, {("plant", "m"): 1.0, ("plant", "c"): 0.1, ("plant", "k"): 1.0}),
        ("[plant] m", "either", "not both")),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_bad_model_file_is_one_line_error(case):
    text, parts = BAD_FILES[case]
    with pytest.raises(ModelError) as info:
        parse_model(text, "bad.toml")
    assert_one_line_error(info.value, "bad.toml", *parts)


def test_the_good_bases_parse():
    """The bad files above are edits of these; they must be valid, or the cases prove nothing."""
    seed = parse_model(SEED, "seed.toml")
    general = parse_model(GENERAL, "general.toml")
    assert set(seed.effects) == {"process.white", "actuator.ar1", "sensor.bias_walk", "sensor.white",
                                 "sensor.quantization"}
    assert set(general.effects) == set(CATALOGUE)
    assert (general.m, general.p, general.n_x) == (2, 2, 5)   # 3 plant + 2 lag states
    variant = parse_model(GENERAL_VARIANT, "variant.toml")
    assert set(variant.effects) == set(CATALOGUE) and variant.command.kind == "prbs"
    assert "rho" in variant.effects["actuator.ar1"].params and variant.effects["process.white"].mode == "std"
    assert parse_model(PLAIN_2X2, "plain.toml").effects == {}
    # the structural editor only changes what it is told to
    assert_same_model(parse_model(edited(GENERAL), "general.toml"), general)


def test_load_model_errors_name_the_spec(tmp_path):
    with pytest.raises(ModelError) as info:
        load_model(tmp_path / "missing.toml")
    assert_one_line_error(info.value, str(tmp_path / "missing.toml"), "no such model file", "seed")
    with pytest.raises(ModelError) as info:
        load_model("no-such-scenario")
    assert_one_line_error(info.value, "no-such-scenario", "built-in", "seed-nominal")
    (tmp_path / "binary.toml").write_bytes(b"\xff\xfe\x00bad")
    with pytest.raises(ModelError) as info:
        load_model(tmp_path / "binary.toml")
    assert_one_line_error(info.value, str(tmp_path / "binary.toml"), "cannot read")
    bad = tmp_path / "bad.toml"
    bad.write_text(sub(SEED, "std = 0.01 ", "stdd = 0.01 "))
    with pytest.raises(ModelError) as info:
        load_model(bad)
    assert_one_line_error(info.value, str(bad), "[sensor.white] std")


# -- 2. the property: garbled files give a Model or a one-line ModelError -------------------------
GENERAL_VARIANT = (
    GENERAL.replace('discretization = "zoh"', 'discretization = "euler"')
    .replace("psd = 0.04", "std = 0.2")
    .replace("std = [0.08, 0.04]\ntau_s = [0.3, 0.1]", "std = [0.08, 0.04]\nrho = [0.97, -0.5]")
    .replace("tau_s = [2.0, 5.0]", "rho = [0.999, 0.9]")
    .replace('kind = "sine"\namplitude = [0.8, 0.3]\nfrequency_hz = [0.7, 1.3]',
             'kind = "prbs"\namplitude = [0.8, 0.3]\nbit_s = 0.05\norder = 7')
)
assert GENERAL_VARIANT.count("rho") == 2 and "prbs" in GENERAL_VARIANT
BASES = [SEED, scenario_text("seed-nominal"), GENERAL, GENERAL_VARIANT]

KEYS = sorted({
    "name", "description", "sampling", "plant", "command", "process", "actuator", "sensor", "Ts",
    "discretization", "m", "c", "k", "A", "B", "C", "D", "L", "kind", "amplitude", "frequency_hz",
    "offset", "phase_rad", "time_s", "f0_hz", "f1_hz", "duration_s", "bit_s", "order", "std", "psd",
    "rho", "tau_s", "limit", "width", "initial_std", "step", "error", "std_s", "cutoff_hz", "taps", "foo",
    "stdd",
    *(eid.split(".")[1] for eid in CATALOGUE),
})
# literals for raw-text injection, including what the structured writer refuses to write
LITERALS = [
    "nan", "-nan", "inf", "-inf", "+inf", "1e999", "-1e999", "0", "-0.0", "1e-320", "5e-324", "1e308",
    "1" + "0" * 400, "-1" + "0" * 400, "1" + "0" * 5000, "true", "false", '"x"', '""', '"lab/seed"',
    "'lit'", "[]", "[[]]", "[1, 2, 3]", "[[1, 2], [3]]", "[[1.0, nan], [0.0, 1.0]]", '[1, "a"]',
    "[[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]", "{}", "{ a = 1 }", "[{ a = 1 }]", "1979-05-27T07:32:00Z",
    "1979-05-27", "07:32:00", "0x10", "0o7", "0b101", "1_000", "[" * 600 + "]" * 600, "-1", "0.97",
    "1.0", "-0.999999", "0.005", "100.0",
]

bare_keys = st.one_of(st.sampled_from(KEYS), st.from_regex(r"[A-Za-z_][A-Za-z0-9_-]{0,8}", fullmatch=True))
numbers = st.one_of(
    st.integers(-3, 3), st.integers(), st.integers(-(10**400), 10**400),
    st.floats(allow_nan=False, allow_infinity=False), st.sampled_from([0.0, -1.0, 1.0, 0.01, 0.5, 1e-300, 1e300]),
)
scalars = st.one_of(numbers, st.booleans(), st.text(max_size=8))
toml_values = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4),                                   # also matrices, ragged or not
        st.dictionaries(bare_keys, inner, max_size=3),                 # a sub-table
    ),
    max_leaves=8,
).filter(lambda v: not _dict_in_list(v))


def _dict_in_list(v, in_list=False) -> bool:
    """The model writer writes tables of scalars and arrays; an array of tables is not in the schema."""
    if isinstance(v, dict):
        return in_list or any(_dict_in_list(x) for x in v.values())
    if isinstance(v, list):
        return any(_dict_in_list(x, True) for x in v)
    return False


def _slots(d: dict, path=()):
    """Every (table, key) in a parsed TOML document."""
    for k, v in d.items():
        yield d, k
        if isinstance(v, dict):
            yield from _slots(v, path + (k,))


def _tables(d: dict):
    yield d
    for v in d.values():
        if isinstance(v, dict):
            yield from _tables(v)


@st.composite
def structured_edit(draw, text: str) -> str:
    """tomllib -> mutate the dict -> dumps_toml: set, delete, rename, add, move or swap values."""
    try:
        d = tomllib.loads(text)
    except (ValueError, RecursionError):
        return text
    slots = list(_slots(d))
    tables = list(_tables(d))
    op = draw(st.sampled_from(["set", "delete", "rename", "add", "move", "swap"]))
    if not slots:
        op = "add"
    if op == "set":
        table, key = draw(st.sampled_from(slots))
        table[key] = draw(toml_values)
    elif op == "delete":
        table, key = draw(st.sampled_from(slots))
        del table[key]
    elif op == "rename":
        table, key = draw(st.sampled_from(slots))
        new = draw(bare_keys)
        table[new] = table.pop(key)
    elif op == "add":
        table = draw(st.sampled_from(tables))
        table[draw(bare_keys)] = draw(toml_values)
    elif op == "move":
        table, key = draw(st.sampled_from(slots))
        target = draw(st.sampled_from(tables))
        value = table.pop(key)
        if target is not value:
            target[key] = value
    else:
        (t1, k1), (t2, k2) = draw(st.sampled_from(slots)), draw(st.sampled_from(slots))
        v1, v2 = t1[k1], t2[k2]
        if not (isinstance(v1, dict) or isinstance(v2, dict)):   # no table inside itself
            t1[k1], t2[k2] = v2, v1
    try:
        return dumps_toml(d)
    except ModelError:   # a nan or inf put in by an earlier raw edit: the writer refuses those
        return text


CHARS = st.one_of(st.sampled_from(list("[]=\".'{},#\n\\ -+e0123456789.abcnanif_")), st.characters())


@st.composite
def raw_edit(draw, text: str) -> str:
    """Edits of the text itself: characters, lines, swapped values, injected literals."""
    lines = text.split("\n")
    op = draw(st.sampled_from(["char", "delete_line", "duplicate_line", "swap_lines", "swap_values",
                               "literal", "truncate"]))
    if op == "char":
        i = draw(st.integers(0, len(text)))
        how = draw(st.sampled_from(["insert", "replace", "delete"]))
        c = draw(CHARS)
        if how == "insert":
            return text[:i] + c + text[i:]
        return text[:i] + (c if how == "replace" else "") + text[i + 1:]
    if op == "truncate":
        return text[:draw(st.integers(0, len(text)))]
    i = draw(st.integers(0, len(lines) - 1))
    if op == "delete_line":
        del lines[i]
    elif op == "duplicate_line":
        lines.insert(draw(st.integers(0, len(lines))), lines[i])
    elif op == "swap_lines":
        j = draw(st.integers(0, len(lines) - 1))
        lines[i], lines[j] = lines[j], lines[i]
    else:
        assigns = [n for n, line in enumerate(lines) if re.match(r"\s*[A-Za-z_]\w*\s*=", line)]
        if not assigns:
            return text
        a = draw(st.sampled_from(assigns))
        key_a, _, val_a = lines[a].partition("=")
        if op == "swap_values":
            b = draw(st.sampled_from(assigns))
            key_b, _, val_b = lines[b].partition("=")
            lines[a], lines[b] = f"{key_a}={val_b}", f"{key_b}={val_a}"
        else:
            lines[a] = f"{key_a}= {draw(st.sampled_from(LITERALS))}"
    return "\n".join(lines)


@st.composite
def garbled(draw) -> str:
    text = draw(st.sampled_from(BASES))
    for _ in range(draw(st.integers(1, 4))):
        edit = draw(st.sampled_from([raw_edit, structured_edit]))
        text = draw(edit(text))
    return text


STIFF_PSD = sub(sub(SEED, 'discretization = "euler"', 'discretization = "zoh"'), "std = 0.20 ", "psd = 1.0 ") \
    + "\n[actuator.lag]\ntau_s = 1e-6\n"


@settings(max_examples=300, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much])
@given(text=garbled())
# regressions found by this test (each crashed with another exception before the fix):
@example(text=sub(SEED, "k = 4.0", "k = 1" + "0" * 400))       # OverflowError: int too large for float
@example(text=sub(SEED, "std = 0.01 ", "std = [1" + "0" * 400 + "]"))
@example(text=sub(SEED, "k = 4.0", "k = 1" + "0" * 5000))       # ValueError from tomllib (int digits)
@example(text=SEED + "\nx = " + "[" * 600 + "]" * 600 + "\n")   # RecursionError from tomllib
@example(text=STIFF_PSD)                                         # LinAlgError: eigh of a NaN Q_d
@example(text=sub(GENERAL, "Ts = 0.01", "Ts = 1e300"))          # non-finite A_d accepted
@example(text=sub(SEED, 'description = "mass', 'description = "tab\\there\\nnewline mass'))  # to_toml wrote bad TOML
@example(text=sub(SEED, 'name = "seed"', 'name = "seed\\n"'))   # a newline passed the name pattern
def test_garbled_model_file_gives_model_or_one_line_error(text):
    try:
        model = parse_model(text, "fuzz.toml")
    except ModelError as exc:
        assert_one_line_error(exc, "fuzz.toml")
        return
    # accepted: a usable model, and what it writes reads back as the same model
    assert re.fullmatch(r"[A-Za-z0-9_-]+", model.name)
    assert model.Ts > 0 and np.all(np.isfinite(model.Ad)) and np.all(np.isfinite(model.S_proc))
    assert_same_model(parse_model(model.to_toml(), "written.toml"), model)


# -- 3. the CLI -------------------------------------------------------------------------------------------
def _cli(args, cwd):
    return subprocess.Popen([sys.executable, "-m", "noiselab.cli", *args], cwd=cwd, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _assert_bad_input(result, *parts):
    rc, out, err = result
    assert rc == 2, (rc, out, err)
    assert "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1 and err.endswith("\n"), err
    assert lines[0].startswith("noiselab: "), err
    for part in parts:
        assert part in lines[0], (part, err)


def test_cli_has_a_module_entry_point():
    """`python -m noiselab.cli` runs the command line, and a usage error a node raises (imported from
    noiselab.cli, not __main__) is still a one-line error with exit 2 (it was a traceback)."""
    from pathlib import Path
    root = Path(__file__).resolve().parents[2]
    ok = subprocess.run([sys.executable, "-m", "noiselab.cli", "--version"], capture_output=True, text=True, cwd=root)
    assert ok.returncode == 0 and ok.stdout.startswith("noiselab "), (ok.returncode, ok.stdout, ok.stderr)
    bad = subprocess.run([sys.executable, "-m", "noiselab.cli", "analyze", "--live", "some.mcap", "--model", "seed"],
                         capture_output=True, text=True, cwd=root)
    assert bad.returncode == 2 and bad.stderr.strip() == "noiselab: --live analyses a Zenoh stream: give no RECORDING", \
        (bad.returncode, bad.stderr[-2000:])


@pytest.fixture(scope="module")
def cli_runs(tmp_path_factory):
    """The bad-input CLI runs, started together (each pays the interpreter's import time)."""
    tmp = tmp_path_factory.mktemp("cli")
    (tmp / "bad.toml").write_text(sub(SEED, "std = 0.01 ", "std = 0.01\nstdd = 0.02 "))
    (tmp / "overflow.toml").write_text(OVERFLOW_QD)    # numpy overflow inside: still one line
    (tmp / "exists.mcap").write_bytes(b"keep these bytes\n")
    runs = {
        "predict bad": ["predict", "bad.toml"],
        "simulate bad": ["simulate", "overflow.toml", "--duration", "1", "--out", str(tmp / "x.mcap")],
        "predict missing": ["predict", "missing.toml"],
        "simulate unknown scenario": ["simulate", "no-such-scenario", "--duration", "1",
                                      "--out", str(tmp / "y.mcap")],
        "simulate onto existing": ["simulate", "seed", "--duration", "1", "--out", str(tmp / "exists.mcap")],
    }
    procs = {k: _cli(a, tmp) for k, a in runs.items()}
    results = {}
    for k, p in procs.items():
        out, err = p.communicate(timeout=120)
        results[k] = (p.returncode, out, err)
    return tmp, results


def test_cli_predict_bad_file(cli_runs):
    tmp, res = cli_runs
    _assert_bad_input(res["predict bad"], "bad.toml", "[sensor.white] stdd", "unknown key")
    assert res["predict bad"][1] == ""


def test_cli_simulate_bad_file_writes_nothing(cli_runs):
    tmp, res = cli_runs
    _assert_bad_input(res["simulate bad"], "overflow.toml", "[process.white] psd")
    assert not (tmp / "x.mcap").exists()


def test_cli_missing_file_and_unknown_scenario(cli_runs):
    tmp, res = cli_runs
    _assert_bad_input(res["predict missing"], "missing.toml", "no such model file")
    _assert_bad_input(res["simulate unknown scenario"], "no-such-scenario", "built-in", "seed")
    assert not (tmp / "y.mcap").exists()


def test_cli_simulate_keeps_an_existing_file_unless_forced(cli_runs):
    tmp, res = cli_runs
    out = tmp / "exists.mcap"
    _assert_bad_input(res["simulate onto existing"], str(out), "already exists", "--force")
    assert out.read_bytes() == b"keep these bytes\n"
    p = _cli(["simulate", "seed", "--duration", "1", "--out", str(out), "--force", "--json"], tmp)
    stdout, stderr = p.communicate(timeout=120)
    assert p.returncode == 0, stderr
    assert out.read_bytes().startswith(b"\x89MCAP")
    assert '"samples": 100' in stdout


# -- 4. scenarios by name and path; writing back; editing ------------------------------------------------
@pytest.mark.parametrize("name", ["seed", "seed-nominal"])
def test_scenario_by_name_equals_by_path(name, tmp_path):
    assert name in scenario_names()
    copy = tmp_path / f"{name}.toml"
    copy.write_text(scenario_text(name))
    by_name, by_path = load_model(name), load_model(copy)
    assert by_name.source == f"scenario {name}" and by_path.source == str(copy)
    assert_same_model(by_name, by_path)
    assert_same_model(parse_model(by_name.to_toml(), "written.toml"), by_name)


# per-effect parameters that differ by channel
EFFECT_PARAMS = [
    ("process.white", {"std": [0.2, 0.1]}),
    ("process.white", {"psd": [0.04, 0.01]}),
    ("actuator.white", {"std": [0.05, 0.02]}),
    ("actuator.ar1", {"std": [0.08, 0.04], "rho": [0.97, -0.5]}),
    ("actuator.ar1", {"std": [0.08, 0.04], "tau_s": [0.3, 0.1]}),
    ("actuator.lag", {"tau_s": [0.02, 0.05]}),
    ("actuator.saturation", {"limit": [5.0, 3.0]}),
    ("actuator.deadzone", {"width": [0.01, 0.02]}),
    ("sensor.scale_factor", {"error": [0.02, -0.01]}),
    ("sensor.bias_walk", {"std": [0.002, 0.001]}),
    ("sensor.bias_walk", {"std": [0.002, 0.001], "initial_std": [0.01, 0.0]}),
    ("sensor.bias_markov", {"std": [0.003, 0.002], "tau_s": [2.0, 5.0]}),
    ("sensor.bias_markov", {"std": [0.003, 0.002], "rho": [0.999, 0.9]}),
    ("sensor.bias_instability", {"B": [0.002, 0.001]}),
    ("sensor.bias_instability", {"B": 0.002, "f_lo_hz": 0.01, "f_hi_hz": 2.0}),
    ("sensor.white", {"std": [0.01, 0.02]}),
    ("sensor.integral_white", {"Q": [2e-5, 1e-5]}),
    ("sensor.tone", {"amplitude": [0.005, 0.002], "frequency_hz": [20.0, 12.5]}),
    ("sensor.filter", {"kind": "lowpass1", "cutoff_hz": [30.0, 15.0]}),
    ("sensor.filter", {"kind": "average", "taps": 4}),
    ("sensor.jitter", {"std_s": 0.0005}),
    ("sensor.quantization", {"step": [0.001, 0.002]}),
]


def test_effect_params_cover_the_catalogue():
    assert {eid for eid, _ in EFFECT_PARAMS} == set(CATALOGUE)


@pytest.mark.parametrize("eid,params", EFFECT_PARAMS, ids=[f"{e}-{'-'.join(p)}" for e, p in EFFECT_PARAMS])
def test_every_effect_table_round_trips(eid, params):
    plain = parse_model(PLAIN_2X2, "plain.toml")
    assert plain.effects == {} and (plain.m, plain.p, plain.plant.nw) == (2, 2, 2)
    model = plain.with_effect(eid, params)
    assert list(model.effects) == [eid]
    assert model.effects[eid].param_dict() == params
    text = model.to_toml()
    group, sub_id = eid.split(".")
    assert f"[{eid}]" in text and tomllib.loads(text)[group][sub_id] == params
    again = parse_model(text, "written.toml")
    assert_same_model(again, model)
    assert again.without_effect(eid).effects == {}
    assert_same_model(parse_model(again.without_effect(eid).to_toml(), "w.toml"), plain)


def test_model_with_every_effect_round_trips():
    model = parse_model(GENERAL, "general.toml")
    text = model.to_toml()
    assert_same_model(parse_model(text, "written.toml"), model)
    # and writing is stable: the written file writes itself
    assert parse_model(text, "written.toml").to_toml() == text


def test_with_effect_and_without_effect():
    seed = load_model("seed")
    nominal = seed.without_effect("sensor.bias_walk")
    assert "sensor.bias_walk" not in nominal.effects and "[sensor.bias_walk]" not in nominal.to_toml()
    assert set(nominal.effects) == set(seed.effects) - {"sensor.bias_walk"}
    for eid, eff in nominal.effects.items():
        assert eff.param_dict() == seed.effects[eid].param_dict()
    np.testing.assert_array_equal(nominal.Ad, seed.Ad)
    # adding the table back gives the seed again
    back = nominal.with_effect("sensor.bias_walk", {"std": 0.002})
    assert list(back.effects) == list(seed.effects)
    assert_same_model(back, seed)
    # a new table: its parameters are validated like a file's, and named in the error
    toned = seed.with_effect("sensor.tone", {"amplitude": 0.01, "frequency_hz": 5.0})
    assert toned.effects["sensor.tone"].param_dict() == {"amplitude": 0.01, "frequency_hz": 5.0}
    assert "[sensor.tone]" in toned.to_toml()
    with pytest.raises(ModelError) as info:
        seed.with_effect("sensor.tone", {"amplitude": 0.01, "frequency_hz": 500.0})
    assert_one_line_error(info.value, "scenario seed + [sensor.tone]", "[sensor.tone] frequency_hz", "Nyquist")
    # an empty table is an effect without its parameters, not nothing
    with pytest.raises(ModelError) as info:
        seed.with_effect("sensor.tone", {})
    assert_one_line_error(info.value, "scenario seed + [sensor.tone]", "[sensor.tone] amplitude", "missing")
    # removing the last effect of a group removes the group
    bare = seed
    for eid in list(seed.effects):
        bare = bare.without_effect(eid)
    assert bare.effects == {}
    assert not {"process", "actuator", "sensor"} & set(tomllib.loads(bare.to_toml()))
    # removing an absent effect changes nothing
    assert_same_model(seed.without_effect("sensor.tone"), seed)


# -- 5. several outputs: a vector measurement ---------------------------------------------------------
def test_general_plant_with_two_outputs_gives_vector_measurement():
    model = parse_model(GENERAL, "general.toml")
    assert model.p == 2 and model.Cy.shape == (2, model.n_x)
    rec = model.simulate(100, seed=1)
    assert rec.y.shape == (100, 2) and rec.u.shape == (100, 2)
    assert np.all(np.isfinite(rec.y))
    assert not np.allclose(rec.y[:, 0], rec.y[:, 1])
    st_ = model.predictor().steady_state()
    assert np.shape(st_.var_y) == (2,)
    assert np.all(np.isfinite(st_.var_y)) and np.all(st_.var_y > 0)
    # and reproducible: the same seed, the same record
    np.testing.assert_array_equal(model.simulate(100, seed=1).y, rec.y)


def test_two_outputs_linear_plant_variances_are_per_output():
    """Without nonlinear effects: the second output sees only its own white noise's variance added."""
    base = parse_model(edited(PLAIN_2X2, {("process", "white", "std"): 0.2}), "p.toml")
    noisy = base.with_effect("sensor.white", {"std": [0.0, 0.05]})
    v0, v1 = base.predictor().steady_state().var_y, noisy.predictor().steady_state().var_y
    assert np.shape(v1) == (2,)
    np.testing.assert_allclose(v1 - v0, [0.0, 0.05**2], rtol=1e-9, atol=1e-15)


def test_scenario_files_are_in_the_package():
    """Addressable by name needs the files shipped with the package (pyproject package-data)."""
    import noiselab.scenarios as pkg
    from pathlib import Path
    here = {p.stem for p in Path(pkg.__file__).parent.glob("*.toml")}
    assert {"seed", "seed-nominal"} <= here == set(scenario_names())
