"""``noiselab allan RECORDING``: the Allan table IMU users read, and the IEEE Std 952 slope readings.

Per output of the recording (a noiselab recording's measurement, or ``--measurement
TOPIC:FIELD[,FIELD...]`` of a foreign one):

* the fully overlapping Allan deviation (NIST SP 1065 eq. (11)) at octave taus, tau = m Ts with
  m = 1, 2, 4, ... up to N/4 (Stable32's list, :func:`noiselab.stats.allan.oadev`); its chi-squared
  interval at 68.3 % (Greenhall & Riley 2003 equivalent degrees of freedom, SP 1065 eq. (45)); the
  noise type identified at each tau (lag-1 autocorrelation, Riley & Greenhall 2004, with at least
  30 averages; Stable32's B1 / R(n) rule below that), named as SP 1065 names the power laws;
* the slope readings (:func:`noiselab.stats.ieee952.ieee952_readings`): Q at tau = sqrt(3) s on the
  -1 line (white PM), N at tau = 1 s on the -1/2 line, K at tau = 3 s on the +1/2 line, B = the
  floor / 0.664, each with the tau range it was read on, or null with the reason;
* with ``--model``: the model's predicted Allan deviation at the same taus (the exact discrete
  Allan variance of the sampled process, :meth:`noiselab.model.predict.Predictor.allan`, summed
  over its effects) and its IEEE 952 coefficients (:mod:`noiselab.model.coefficients`).

The data are taken as recorded (no mean response removed: a sensor at rest); the model's curve is
that of its noise, so a model with a command says so in a note. Units are the model's ``[outputs]``
units when a model is given; otherwise the output is named by its field, in the unit its ROS message
type fixes (REP 103, :data:`noiselab.recordings.rosbag_in.FIELD_UNITS`) or else the field name standing for
the unit. Ts is the model's, else the median step of the recording's times.

Output: the table on stdout; ``--json`` the same as one JSON document (keys below, stable);
``--csv FILE`` one row per output and tau; ``--png FILE`` the log-log figure
(:mod:`noiselab.viewers.allan_png`). An output file that exists needs ``--force``.

JSON: {"recording", "Ts", "samples", "conf", "estimator", "model", "notes", "outputs": {name:
{"unit", "tau", "m", "n_terms", "adev", "interval": [[lo, hi], ...], "edf", "alpha",
"noise_type", "readings": {"Q"|"N"|"K"|"B": {"value", "unit", "tau_range", "interval", "points",
"reason"}}, "model_adev": [...] or null, "model_coefficients": {name: {"value", "unit",
"interval"}} or null}}}.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

from ..errors import BadInput
from ..outfiles import check_out, write_replacing

CONF = 0.683  # Stable32's "Confidence Factor": one-sigma intervals
READING_UNITS = {"Q": "({u})*s", "N": "{u}/sqrt(Hz)", "K": "{u}/sqrt(s)", "B": "{u}"}
READING_TAUS = {"Q": "tau = sqrt(3) s on the -1 line", "N": "tau = 1 s on the -1/2 line",
                "K": "tau = 3 s on the +1/2 line", "B": "floor / 0.664"}
CSV_COLUMNS = ("output", "unit", "tau_s", "m", "n_terms", "adev", "adev_lo", "adev_hi", "edf", "alpha",
               "noise_type", "model_adev")


def register(sub) -> None:
    p = sub.add_parser("allan", help="the Allan deviation table (tau, ADEV, interval, noise type) and the "
                                     "IEEE 952 slope readings Q, N, K, B of a recording")
    p.add_argument("recording", help="the .mcap to read")
    p.add_argument("--measurement", metavar="TOPIC:FIELD",
                   help="foreign recordings: topic and field(s) of the rate data, e.g. /imu:angular_velocity.x")
    p.add_argument("--time", metavar="FIELD", help="foreign recordings: time field (s, or ns if it ends in _ns); "
                                                  "default publish_time")
    p.add_argument("--device", help="device name in a noiselab recording with several devices")
    p.add_argument("--model", help="model file (TOML) or built-in scenario name: its predicted Allan "
                                   "deviation, coefficients, output names and units")
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--json", action="store_true", help="machine-readable report on stdout")
    fmt.add_argument("--csv", metavar="FILE", help="write the table as CSV (one row per output and tau)")
    p.add_argument("--png", metavar="FILE", help="write the log-log figure here")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.set_defaults(func=cmd_allan)


# -- reading --------------------------------------------------------------------------------------
def _load(args, model):
    """(series, output names, units, Ts) of the recording, through the one loader."""
    from ..model.outputs import DEFAULT_UNIT
    from ..recordings.load import load_recording

    if args.measurement and args.device:
        raise BadInput("--device names a device of a noiselab recording; with --measurement give the topic")
    series = load_recording(args.recording, spec=args.measurement, time_field=args.time, device=args.device,
                            model=model, truth=False)
    p_data = series.y.shape[1]
    fields = series.names or [f"y{j}" for j in range(p_data)]
    if model is not None:
        if model.p != p_data:
            raise BadInput(f"--model {args.model}: the model has {model.p} output(s), the recording "
                           f"{p_data} ({', '.join(fields)})")
        return series, list(model.output_names), list(model.output_units), model.Ts
    # no model: a ROS field's unit where its message type fixes it (REP 103: an Imu's angular_velocity
    # is in rad/s); else a foreign field stands for its own unit; a noiselab output is y<j> in "units"
    known = series.units or [None] * p_data
    units = [k or f for k, f in zip(known, fields)] if series.names else [DEFAULT_UNIT] * p_data
    return series, fields, units, series.Ts


# -- the report -------------------------------------------------------------------------------------
def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def _reading_json(rd, unit: str) -> dict:
    return {"value": rd.value, "unit": unit,
            "tau_range": None if rd.tau_range is None else list(rd.tau_range),
            "interval": None if rd.interval is None else list(rd.interval),
            "points": rd.points, "reason": rd.reason}


def allan_report(series, names, units, Ts: float, model=None, model_label: str | None = None) -> dict:
    """The report (module docstring's JSON) of ``series`` (``y`` (N, p) rate data at ``Ts``)."""
    import numpy as np

    from ..stats.allan import oadev
    from ..stats.errors import StatsError
    from ..stats.ieee952 import NOISE_NAMES, ieee952_readings

    notes = list(series.notes)
    results = []
    for j, name in enumerate(names):
        try:
            results.append(oadev(series.y[:, j], 1.0 / Ts, taus="octave", conf=CONF))
        except StatsError as e:                     # the estimator's check, said of this recording
            raise BadInput(f"{series.source}: {name}: {e}") from None
    model_avar = coefficients = None
    if model is not None:
        from ..model.coefficients import model_coefficients

        m = results[0].m
        pr = model.predictor()
        parts = [a for a in pr.allan(m).values() if a is not None]
        model_avar = sum(parts) if parts else np.zeros((m.size, model.p))
        coefficients = model_coefficients(model)
        # the data's deviation includes whatever moves the mean (a constant, e.g. gravity on an
        # accelerometer axis, does not); the model's curve is that of its noise alone
        mean_y = pr.mean_response(series.y.shape[0]).y
        moving = [name for j, name in enumerate(names) if np.ptp(mean_y[:, j]) > 0.0]
        if moving:
            notes.append(f"the model's mean response ([command] {model.command.kind}) moves {', '.join(moving)} "
                         "over the record: the data's Allan deviation includes it, the model's curve is its noise alone")
    outputs = {}
    for j, (name, unit, r) in enumerate(zip(names, units, results)):
        rd = ieee952_readings(r)
        outputs[name] = {
            "unit": unit,
            "tau": r.taus.tolist(), "m": r.m.tolist(), "n_terms": r.n.tolist(),
            "adev": r.dev.tolist(), "interval": [[float(a), float(b)] for a, b in zip(r.lo, r.hi)],
            "edf": r.edf.tolist(), "alpha": r.alpha.tolist(),
            "noise_type": [NOISE_NAMES[int(a)] for a in r.alpha],
            "readings": {k: _reading_json(v, READING_UNITS[k].replace("{u}", unit)) for k, v in rd.items()},
            "model_adev": None if model_avar is None else [_num(np.sqrt(max(v, 0.0))) for v in model_avar[:, j]],
            "model_coefficients": None if coefficients is None else coefficients.get(name, {}),
        }
    return {"recording": series.source, "Ts": Ts, "samples": int(series.y.shape[0]), "conf": CONF,
            "estimator": "overlapping Allan deviation (NIST SP 1065 eq. 11), octave taus up to N/4",
            "model": model_label, "notes": notes, "outputs": outputs}


def _g(v, width: int = 10) -> str:
    return f"{'-':>{width}}" if v is None else f"{v:>{width}.4e}"


def report_lines(rep: dict) -> list[str]:
    """The table on stdout: per output, one row per tau, then the readings."""
    lines = [f"{rep['recording']}: {rep['samples']} samples at Ts = {rep['Ts']:g} s; {rep['estimator']}, "
             f"{100 * rep['conf']:.1f} % intervals (Greenhall edf, chi-squared)"
             + (f"; model {rep['model']}" if rep["model"] else "")]
    for name, o in rep["outputs"].items():
        has_model = o["model_adev"] is not None
        lines += ["", f"{name} [{o['unit']}]",
                  f"{'tau [s]':>10} {'m':>8} {'ADEV':>10} {'lo':>10} {'hi':>10}  {'noise type':<15}"
                  + (f" {'model ADEV':>10}" if has_model else "")]
        for i, tau in enumerate(o["tau"]):
            lo, hi = o["interval"][i]
            lines.append(f"{tau:>10.4g} {o['m'][i]:>8d} {_g(o['adev'][i])} {_g(lo)} {_g(hi)}  "
                         f"{o['noise_type'][i]:<15}" + (f" {_g(o['model_adev'][i])}" if has_model else ""))
        lines.append("IEEE 952 readings:")
        for key, rd in o["readings"].items():
            mc = (o["model_coefficients"] or {}).get(key)
            model_part = "" if not has_model else "   model " + (
                "-" if mc is None or mc.get("value") is None else f"{mc['value']:.4e} {mc['unit']}")
            if rd["value"] is None:
                lines.append(f"  {key} = -  ({rd['reason']})" + model_part)
                continue
            lo, hi = rd["interval"]
            t0, t1 = rd["tau_range"]
            lines.append(f"  {key} = {rd['value']:.4e} {rd['unit']}  [{lo:.4e}, {hi:.4e}]  {READING_TAUS[key]}, "
                         f"read on tau {t0:.4g} .. {t1:.4g} s ({rd['points']} taus)" + model_part)
    for note in rep["notes"]:
        lines.append(f"note: {note}")
    return lines


def _csv_rows(rep: dict):
    for name, o in rep["outputs"].items():
        for i, tau in enumerate(o["tau"]):
            yield [name, o["unit"], repr(tau), o["m"][i], o["n_terms"][i], repr(o["adev"][i]),
                   repr(o["interval"][i][0]), repr(o["interval"][i][1]), repr(o["edf"][i]), o["alpha"][i],
                   o["noise_type"][i], "" if o["model_adev"] is None or o["model_adev"][i] is None
                   else repr(o["model_adev"][i])]


def csv_text(rep: dict) -> str:
    f = io.StringIO(newline="")
    w = csv.writer(f)
    w.writerow(CSV_COLUMNS)
    w.writerows(_csv_rows(rep))
    return f.getvalue()


def cmd_allan(args) -> int:
    for out in (args.csv, args.png):
        check_out(out, args.force)
    if args.csv and args.png and Path(args.csv).resolve() == Path(args.png).resolve():
        raise BadInput(f"--csv and --png name the same file {args.csv}")
    model = None
    if args.model:
        from ..model import load_model
        model = load_model(args.model)
    series, names, units, Ts = _load(args, model)
    rep = allan_report(series, names, units, Ts, model, None if model is None else f"{model.name} ({model.source})")
    written = []
    if args.csv:
        write_replacing(args.csv, csv_text(rep))
        written.append(args.csv)
    if args.png:
        from noiselab.viewers.allan_png import allan_png_bytes
        write_replacing(args.png, allan_png_bytes(rep))
        written.append(args.png)
    if args.json:
        rep["written"] = written
        print(json.dumps(rep, indent=1))
    else:
        for line in report_lines(rep) + [f"wrote {w}" for w in written]:
            print(line)
    return 0
