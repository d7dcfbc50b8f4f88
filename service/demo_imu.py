"""`noiselab demo imu`: a 6-axis IMU at rest, emulated live, diagnosed, exported for Kalibr.

The IMU engineer's story, with known truth:

1. Live: ``noiselab run imu`` (emulator, recorder and live analyzer as separate processes on
   127.0.0.1 over Zenoh, ``speed`` times faster than real time) writes ``demo-imu.mcap``; the
   live analyzer compares the stream with ``imu-nominal`` (white noise only, the published N).
   The ``imu`` scenario is an ADIS16448 with the EuRoC calibration: white noise (N), a bias
   random walk (K) and the data sheet's quantization on each axis.
2. ``noiselab diagnose`` against ``imu-nominal``: what the nominal model lacks is found and fitted
   (the bias walk, the quantization), the model error before and after.
3. The fitted model's IEEE Std 952 coefficients beside the true ones, and Kalibr's ``imu.yaml``
   written from the fitted model (``noiselab export --kalibr``), beside the one the true model gives.

Writes, under the output directory: the recording, the live ``.rrd``/PNG, the diagnosis ``.rrd``
and PNG, the fitted model, ``demo-imu-kalibr.yaml`` and ``demo-imu-summary.json`` (what ``--json``
prints).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from .diagnose.thresholds import MAX_EFFECTS

TRUE, NOMINAL = "imu", "imu-nominal"
DURATION_S = 600.0
"""Default seconds of samples: the walk's Allan line crosses the white noise's at
tau = sqrt(3) N / K, about 15 s for the gyros (N 1.7e-4 rad/s/sqrt(Hz), K 1.9e-5 rad/s^2/sqrt(Hz)),
so 600 s hold some 40 independent stretches of that length: K is found with an interval."""


def outputs(out_dir: Path) -> dict:
    stem = out_dir / "demo-imu"
    return {"recording": stem.with_suffix(".mcap"), "live_rrd": stem.with_suffix(".rrd"),
            "live_png": stem.with_suffix(".png"), "rrd": out_dir / "demo-imu-diagnosis.rrd",
            "png": out_dir / "demo-imu-diagnosis.png", "fitted": out_dir / "demo-imu-fitted.toml",
            "kalibr": out_dir / "demo-imu-kalibr.yaml", "summary": out_dir / "demo-imu-summary.json"}


def run_imu_demo(out_dir: Path, *, duration: float, speed: float, seed: int, force: bool,
                 max_effects: int = MAX_EFFECTS, log=sys.stderr) -> tuple[dict, list[str]]:
    from .commands.export import kalibr_values, kalibr_yaml
    from .demo import DemoError
    from .diagnose.diagnose import diagnose
    from .diagnose.report import diagnosis_json
    from .model import load_model, parse_model
    from .model.coefficients import model_coefficients
    from .nodes.runner import run_pipeline
    from .outfiles import writing
    from .recordings.load import load_noiselab

    outs = outputs(out_dir)
    if not force:
        for p in outs.values():
            if p.exists():
                raise DemoError(f"{p}: exists (use --force to overwrite)")
    truth, nominal = load_model(TRUE), load_model(NOMINAL)

    def say(s):
        print(f"noiselab demo imu: {s}", file=log, flush=True)

    say(f"1/3 live: emulating {truth.name} ({truth.p} axes at {1 / truth.Ts:g} Hz) for {duration:g} s of samples "
        f"at {speed:g}x real time over Zenoh on 127.0.0.1, recording to {outs['recording']}, live analysis "
        f"against {NOMINAL} ...")
    live = run_pipeline(TRUE, truth.name, duration=duration, seed=seed, out_dir=out_dir, force=force,
                        analyze=True, speed=speed, analyze_model=NOMINAL, window=min(duration, 300.0),
                        out_name="demo-imu")
    series = load_noiselab(str(outs["recording"]), truth=False, Ts=truth.Ts, model=nominal)
    say(f"2/3 diagnosing {series.y.shape[0]} samples x {series.y.shape[1]} axes against {NOMINAL} ...")
    rep = diagnose(nominal, series.t, series.y, series.u, at_rest=series.starts_at_rest, max_effects=max_effects)
    fitted = parse_model(rep["fitted_model"], str(outs["fitted"]))
    with writing(str(outs["fitted"])):
        outs["fitted"].write_text(rep["fitted_model"])
    comps = rep["comparisons"]
    for c in comps:
        c.recording = series.source
    from noiselab.viewers.rerun_log import log_comparisons
    from noiselab.viewers.summary_png import write_summary_png
    with writing(str(outs["rrd"])):
        log_comparisons(comps, str(outs["rrd"]))
    with writing(str(outs["png"])):
        write_summary_png(comps, str(outs["png"]))

    say("3/3 coefficients and Kalibr's imu.yaml ...")
    kal_fit, kal_true = kalibr_values(fitted), kalibr_values(truth)
    with writing(str(outs["kalibr"])):
        outs["kalibr"].write_text(kalibr_yaml(kal_fit, rostopic="/imu0", model=fitted))
    diag = diagnosis_json(rep, series)
    summary = {
        "recording": str(outs["recording"]),
        "live": {k: live.get(k) for k in ("emulator", "recorder", "analysis")},
        "diagnosis": diag,
        "true_coefficients": model_coefficients(truth),
        "kalibr": {"fitted": _kalibr_numbers(kal_fit), "true": _kalibr_numbers(kal_true)},
        "files": {k: str(v) for k, v in outs.items()},
    }
    with writing(str(outs["summary"])):
        outs["summary"].write_text(json.dumps(summary))
    return summary, _lines(summary, rep)


def _kalibr_numbers(v: dict) -> dict:
    return {k: x for k, x in v.items() if not k.endswith("_outputs")}


def _lines(s: dict, rep: dict) -> list[str]:
    from .nodes.runner import pipeline_lines

    emu, rec, an = (s["live"].get(k) or {} for k in ("emulator", "recorder", "analysis"))
    L = [("== 1. live: a 6-axis IMU at rest (ADIS16448, EuRoC calibration) emulated over Zenoh (127.0.0.1), "
          "recorded to MCAP =="), f"recording: {s['recording']}"]
    L += pipeline_lines(emu, rec)
    if an.get("error") is not None:
        L.append(f"  live analysis against {NOMINAL}: model error {an['error']:.3g}")
    d = s["diagnosis"]
    L += ["", f"== 2. diagnosis against {NOMINAL} (white noise only) =="]
    for i, m in enumerate(d["missing"], 1):
        L.append(f"   {i}. {m['effect']} ({m['mode'].replace('replace:', 'in place of ')}): {m['evidence']}")
    if not d["missing"]:
        L.append("   nothing missing found")
    L.append(f"model error {d['error_before']:.3g} -> {d['error_after']:.3g} (about 1 when the model explains the data)")
    L += ["", "== 3. IEEE Std 952 coefficients, fitted [95 % interval] against the truth =="]
    truth = s["true_coefficients"]
    for name, coefs in d["coefficients"].items():
        parts = []
        for c in ("N", "K"):
            fit, tru = coefs.get(c), truth.get(name, {}).get(c)
            if fit is None or fit["value"] is None:
                continue
            iv = fit.get("interval")
            ivs = f" [{iv[0]:.3g}, {iv[1]:.3g}]" if iv else ""
            parts.append(f"{c} = {fit['value']:.4g}{ivs} (true {tru['value']:.4g}) {fit['unit']}" if tru else
                         f"{c} = {fit['value']:.4g}{ivs} {fit['unit']}")
        if parts:
            L.append(f"   {name:<8} " + "; ".join(parts))
    kf, kt = s["kalibr"]["fitted"], s["kalibr"]["true"]
    L.append("Kalibr imu.yaml (largest of the axes; white density includes the quantization), fitted vs true:")
    for k in ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
              "accelerometer_random_walk"):
        L.append(f"   {k:<28} {kf[k]:.4g}   (true {kt[k]:.4g}, {100 * (kf[k] / kt[k] - 1):+.1f} %)")
    f = s["files"]
    L.append(f"wrote {f['rrd']}, {f['png']}, the fitted model {f['fitted']}, {f['kalibr']} and the summary {f['summary']}")
    return L


def cmd_imu_demo(args) -> int:
    summary, lines = run_imu_demo(Path(args.out), duration=args.duration if args.duration is not None else DURATION_S,
                                  speed=args.speed, seed=args.seed, force=args.force, max_effects=args.max_effects)
    if args.json:
        print(json.dumps(summary), flush=True)
    else:
        for line in lines:
            print(line, flush=True)
    return 0
