"""``noiselab export MODEL --kalibr FILE.yaml``: a model's IMU noise in Kalibr's ``imu.yaml``.

Kalibr (ethz-asl/kalibr, wiki "IMU Noise Model") reads six keys: ``gyroscope_noise_density``
(rad/s/sqrt(Hz)), ``gyroscope_random_walk`` (rad/s^2/sqrt(Hz)), ``accelerometer_noise_density``
(m/s^2/sqrt(Hz)), ``accelerometer_random_walk`` (m/s^3/sqrt(Hz)), ``update_rate`` (Hz) and
``rostopic``. In IEEE Std 952 terms (:mod:`noiselab.model.coefficients`):

* noise density = the white density N of the model's white noise, with the quantization's white
  equivalent N_q added in quadrature (sqrt(N^2 + N_q^2): Kalibr models all white noise as one);
* random walk = K, the bias random walk's std (units/sqrt(s), the same as units/s/sqrt(Hz));
* update_rate = 1 / Ts.

Which outputs: the gyroscope's are the outputs whose names start with ``gyro`` and the
accelerometer's those starting with ``accel`` (``[outputs] names``), or the comma-separated names
of ``--gyro`` / ``--accel``. Kalibr takes one number per sensor for its three axes: this writes the
LARGEST of the axes (the most conservative: an estimator tuned with it trusts no axis more than
its noise allows), and says so in the file.

Units: a gyroscope output in rad/s is written as it is, one in deg/s converted (pi/180); an
accelerometer output in m/s^2 as it is, one in g converted (9.80665 m/s^2, standard gravity).
Any other unit is refused in one line, as is a model that lacks one of the four noise terms
(Kalibr needs all four), an output name the model does not have, or an output in both lists.

The file: an existing one is replaced only with ``--force``; it is written beside the target as
``FILE.partial`` and renamed over it when complete (:func:`noiselab.outfiles.write_replacing`), so
a failed write leaves any old file as it was. The YAML is plain (six scalars and comments); floats always carry a '.' and
an exponent sign, so YAML 1.1 readers (PyYAML, which Kalibr uses) read them as floats.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

from ..errors import BadInput
from ..outfiles import check_out, write_replacing

STANDARD_GRAVITY = 9.80665   # m/s^2 (ISO 80000-3; CGPM 1901)

GYRO_UNITS = {"rad/s": 1.0, "deg/s": math.pi / 180.0, "°/s": math.pi / 180.0}
ACCEL_UNITS = {"m/s^2": 1.0, "m/s2": 1.0, "m/s²": 1.0, "g": STANDARD_GRAVITY}

SENSORS = (   # (Kalibr's prefix, default output-name prefix, flag, units accepted, SI unit)
    ("gyroscope", "gyro", "--gyro", GYRO_UNITS, "rad/s"),
    ("accelerometer", "accel", "--accel", ACCEL_UNITS, "m/s^2"),
)

ROSTOPIC_RE = re.compile(r"^/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$")


def register(sub) -> None:
    p = sub.add_parser("export", help="write a (fitted) model's IMU noise for other tools (Kalibr's imu.yaml)")
    p.add_argument("model", help="model file (TOML) or built-in scenario name")
    p.add_argument("--kalibr", required=True, metavar="FILE.yaml",
                   help="write Kalibr's imu.yaml here (noise densities and random walks: the largest of the axes)")
    p.add_argument("--gyro", metavar="NAMES", help="comma-separated gyroscope outputs (default: names starting with 'gyro')")
    p.add_argument("--accel", metavar="NAMES",
                   help="comma-separated accelerometer outputs (default: names starting with 'accel')")
    p.add_argument("--rostopic", default="/imu0", metavar="TOPIC", help="the IMU's ROS topic (default /imu0)")
    p.add_argument("--force", action="store_true", help="overwrite an existing file")
    p.set_defaults(func=cmd_export)


def cmd_export(args) -> int:
    from ..model import load_model

    if not ROSTOPIC_RE.fullmatch(args.rostopic):
        raise BadInput(f"--rostopic {args.rostopic!r}: expected a ROS topic name (letters, digits, '_' and '/')")
    out = Path(args.kalibr)
    check_out(out, args.force)
    model = load_model(args.model)
    values = kalibr_values(model, gyro=_names(args.gyro, "--gyro"), accel=_names(args.accel, "--accel"))
    text = kalibr_yaml(values, rostopic=args.rostopic, model=model)
    write_replacing(out, text)
    print(f"wrote {out}: Kalibr imu.yaml of model {model.name} (gyroscope {', '.join(values['gyroscope_outputs'])}; "
          f"accelerometer {', '.join(values['accelerometer_outputs'])}; the largest of the axes)")
    return 0


def _names(text: str | None, flag: str) -> list[str] | None:
    if text is None:
        return None
    names = [s.strip() for s in text.split(",")]
    if not all(names):
        raise BadInput(f"{flag} {text!r}: expected comma-separated output names")
    return names


def kalibr_values(model, gyro: list[str] | None = None, accel: list[str] | None = None) -> dict:
    """The six numbers of Kalibr's imu.yaml from ``model`` (module docstring), plus the outputs
    used (``gyroscope_outputs``, ``accelerometer_outputs``). BadInput names what is wrong."""
    import numpy as np

    from ..model.coefficients import coefficient_values, white_density

    names = list(model.output_names)
    chosen = {"gyroscope": gyro, "accelerometer": accel}
    for kind, prefix, flag, _, _ in SENSORS:
        sel = chosen[kind]
        if sel is None:
            sel = [n for n in names if n.lower().startswith(prefix)]
            if not sel:
                raise BadInput(f"{model.source}: no {kind} outputs: no output name starts with {prefix!r} "
                               f"(outputs: {', '.join(names)}); choose them with {flag} NAMES")
        unknown = [n for n in sel if n not in names]
        if unknown:
            raise BadInput(f"{flag}: {unknown[0]!r} is not an output of {model.source} (outputs: {', '.join(names)})")
        chosen[kind] = sel
    both = sorted(set(chosen["gyroscope"]) & set(chosen["accelerometer"]))
    if both:
        raise BadInput(f"output {both[0]!r} is chosen as both gyroscope and accelerometer; choose with --gyro and --accel")
    white, walk = white_density(model), coefficient_values(model, "K")
    out: dict = {}
    missing = []
    for kind, _, _, units, si in SENSORS:
        idx = [names.index(n) for n in chosen[kind]]
        scale = []
        for j in idx:
            u = model.output_units[j].strip()
            if u not in units:
                raise BadInput(f"{model.source}: output {names[j]} is in {u!r}: Kalibr's {kind} is in {si} "
                               f"(accepted: {', '.join(units)}, converted); set [outputs] units")
            scale.append(units[u])
        scale = np.asarray(scale)
        if white is None:
            missing.append(f"{kind}_noise_density (no white noise, IEEE 952 N: add [sensor.white])")
        else:
            out[f"{kind}_noise_density"] = float(np.max(white[idx] * scale))
        if walk is None:
            missing.append(f"{kind}_random_walk (no bias random walk, IEEE 952 K: add [sensor.bias_walk])")
        else:
            out[f"{kind}_random_walk"] = float(np.max(walk[idx] * scale))
        out[f"{kind}_outputs"] = [names[j] for j in idx]
    if missing:
        raise BadInput(f"{model.source}: Kalibr's imu.yaml needs all four noise terms; missing " + "; ".join(missing))
    out["update_rate"] = 1.0 / model.Ts
    return out


def kalibr_yaml(values: dict, rostopic: str, model) -> str:
    """Kalibr's imu.yaml text (plain YAML: comments and six scalars)."""
    g, a = values["gyroscope_outputs"], values["accelerometer_outputs"]
    lines = [
        f"# Kalibr IMU noise model, written by noiselab export from model {model.name}",
        "# noise density: IEEE Std 952 N (white noise, quantization included), random walk: K (bias random walk);",
        f"# each the largest over the axes: gyroscope {', '.join(g)}; accelerometer {', '.join(a)}",
        f"accelerometer_noise_density: {yaml_float(values['accelerometer_noise_density'])}   # m/s^2/sqrt(Hz)",
        f"accelerometer_random_walk: {yaml_float(values['accelerometer_random_walk'])}   # m/s^3/sqrt(Hz)",
        f"gyroscope_noise_density: {yaml_float(values['gyroscope_noise_density'])}   # rad/s/sqrt(Hz)",
        f"gyroscope_random_walk: {yaml_float(values['gyroscope_random_walk'])}   # rad/s^2/sqrt(Hz)",
        f"rostopic: '{rostopic}'",
        f"update_rate: {yaml_float(values['update_rate'])}   # Hz",
    ]
    return "\n".join(lines) + "\n"


def yaml_float(v: float) -> str:
    """A finite float as YAML 1.1 and 1.2 read it: the shortest round-trip text with a '.' in the
    mantissa (YAML 1.1's float needs one: ``1e-05`` is a string there) and a signed exponent."""
    s = repr(float(v))
    if not math.isfinite(v):
        raise BadInput(f"cannot write the non-finite value {s} to imu.yaml")
    mant, _, exp = s.partition("e")
    if "." not in mant:
        mant += ".0"
    return f"{mant}e{exp}" if exp else mant
