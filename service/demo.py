"""`noiselab demo`: the seed lesson, live, then diagnosed against the lesson's own prediction model.

1. Live: ``noiselab run seed`` (emulator, recorder and live analyzer as separate processes on
   127.0.0.1 over Zenoh; the emulator runs ``speed`` times faster than real time, the sample times
   stay on the Ts grid) writes ``recordings/demo-seed.mcap``; the live analyzer compares the stream
   with ``seed-nominal`` and writes ``demo-seed.rrd`` / ``.png``.
2. The lesson's check, as its program computes it (first 60 s, 10 s burn-in): the empirical
   variance of the measurement against the nominal model's mean predicted S_y,k. About 7x off.
3. Why, in three parts, each measured on the recording:
   - the command response: the lesson leaves the sine's deterministic response in the variance;
     noiselab compares the residual y - E[y] (E[y] = the model's mean response to the recorded
     command) with the predicted variance;
   - the actuator noise's color and the bias walk: ``noiselab diagnose`` against ``seed-nominal``
     finds them, adds them one by one (the model error after each step), and the predicted
     mean-square residual of each model is set beside the measured one.
4. Writes ``demo-seed-diagnosis.rrd`` (one revision per step), its PNG and the fitted model
   ``demo-seed-fitted.toml``, and the whole summary (what ``--json`` prints) as
   ``demo-seed-summary.json``, for scripts that ran the demo without ``--json``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from .diagnose.modes import ADD, Mode
from .diagnose.thresholds import MAX_EFFECTS

LESSON_N = 6000          # the lesson's program: N = 6000 samples (60 s at Ts = 0.01 s) ...
LESSON_BURN = 1000       # ... statistics after a burn-in of 1000 samples


class DemoError(ValueError):
    """Bad demo input (one line)."""


def outputs(out_dir: Path) -> dict:
    stem = out_dir / "demo-seed"
    return {"recording": stem.with_suffix(".mcap"), "live_rrd": stem.with_suffix(".rrd"),
            "live_png": stem.with_suffix(".png"), "rrd": out_dir / "demo-seed-diagnosis.rrd",
            "png": out_dir / "demo-seed-diagnosis.png", "fitted": out_dir / "demo-seed-fitted.toml",
            "summary": out_dir / "demo-seed-summary.json"}


def _lesson_check(nominal, y: np.ndarray, u: np.ndarray) -> dict:
    """The lesson's comparison (its section 10 program) on the first LESSON_N samples."""
    n = min(LESSON_N, y.shape[0])
    burn = min(LESSON_BURN, n // 2)
    pr = nominal.predictor()
    cov = pr.covariance(n, u[:n])
    mean = pr.mean_response(n, u[:n])
    y0 = y[burn:n, 0]
    emp = float(np.var(y0, ddof=1))
    pred = float(np.mean(cov.Sy[burn:n, 0]))
    cmd_var = float(np.var(mean.y[burn:n, 0], ddof=1))
    r = y0 - mean.y[burn:n, 0]
    return {"samples": n, "burn": burn, "empirical_var": emp, "predicted_var": pred, "ratio": emp / pred,
            "command_response_var": cmd_var, "residual_ms": float(np.mean(r**2)),
            "residual_ratio": float(np.mean(r**2)) / pred}


def _walk_id(model) -> str:
    """The effect whose variance grows with time (a ``walk`` spectral primitive: the bias walk)."""
    return next(eid for eid, e in model.effects.items()
                if hasattr(e, "spectral") and any(p[0] == "walk" for p in e.spectral()))


def _variance_story(models: list, y: np.ndarray, u: np.ndarray, Ts: float) -> list[dict]:
    """For each model: measured mean-square residual y - E[y] over the whole record against the
    model's predicted mean of S_y,k (steady state + the bias walk's k Q_b growth, the start-up
    transient neglected: a few seconds of a long record)."""
    n = y.shape[0]
    out = []
    for m in models:
        pr = m.predictor()
        mean = pr.mean_response(n, u)
        r = y[:, 0] - mean.y[:, 0]
        st = pr.steady_state()
        walk_mean = float(st.bias_var_rate[0]) * Ts * (n - 1) / 2.0       # mean over k of k Q_b
        pred = float(st.var_y[0]) + walk_mean
        parts = {eid: float(np.ravel(v)[0]) for eid, v in st.contributions.items() if v is not None}
        if walk_mean > 0:
            parts[_walk_id(m)] = walk_mean
        out.append({"model": m.name, "measured_ms": float(np.mean(r**2)), "predicted_ms": pred,
                    "ratio": float(np.mean(r**2)) / pred, "parts": parts})
    return out


def run_demo(out_dir: Path, *, duration: float, speed: float, seed: int, force: bool,
             max_effects: int = MAX_EFFECTS, log=sys.stderr, progress=None) -> tuple[dict, list[str]]:
    """The demo (the module docstring); ``progress``: a :class:`noiselab.progress.Steps` shown
    beside the narrative lines (the live run's time, the reading, each phase of the diagnosis
    with its fits counted, the files), or None."""
    from .diagnose.diagnose import diagnose
    from .diagnose.report import diagnosis_json
    from .model import load_model
    from .nodes.runner import run_pipeline
    from .outfiles import writing
    from .recordings.load import load_noiselab

    outs = outputs(out_dir)
    if not force:
        for p in outs.values():
            if p.exists():
                raise DemoError(f"{p}: exists (use --force to overwrite)")
    truth, nominal = load_model("seed"), load_model("seed-nominal")

    steps = progress if progress is not None and progress.enabled else None
    phase = steps if steps is not None else (lambda label, done=0, total=None: None)

    def say(s):
        if steps is not None:
            steps.close()                     # a narrative line on a line of its own, not inside a bar
        print(f"noiselab demo: {s}", file=log, flush=True)

    say(f"1/3 live: emulating {truth.name} (Ts = {truth.Ts:g} s) for {duration:g} s of samples at {speed:g}x real "
        f"time over Zenoh on 127.0.0.1, recording to {outs['recording']}, live analysis against seed-nominal ...")
    phase("live run")
    live = run_pipeline("seed", truth.name, duration=duration, seed=seed, out_dir=out_dir, force=force,
                        analyze=True, speed=speed, analyze_model="seed-nominal", window=120.0, out_name="demo-seed")
    phase(f"reading {outs['recording'].name}")
    series = load_noiselab(str(outs["recording"]), truth=True, Ts=truth.Ts, model=nominal)
    y, u = series.y, series.u
    say(f"2/3 diagnosing {y.shape[0]} samples against seed-nominal ...")
    rep = diagnose(nominal, series.t, y, u, at_rest=series.starts_at_rest, max_effects=max_effects, progress=steps)
    with writing(str(outs["fitted"])):          # each file written: a full disk is one line naming it
        outs["fitted"].write_text(rep["fitted_model"])
    comps = rep["comparisons"]
    for c in comps:
        c.truth = series.truth
    from noiselab.viewers.rerun_log import log_comparisons
    from noiselab.viewers.summary_png import write_summary_png
    phase(f"writing {outs['rrd'].name} and {outs['png'].name}")
    with writing(str(outs["rrd"])):
        log_comparisons(comps, str(outs["rrd"]))
    with writing(str(outs["png"])):
        write_summary_png(comps, str(outs["png"]))
    say("3/3 the variance story ...")
    lesson = _lesson_check(nominal, y, u)
    story = _variance_story(rep["step_models"], y, u, truth.Ts)
    story[0]["model"] = "seed-nominal (the lesson's model)"
    for s, st in zip(story[1:], rep["steps"]):
        mode = Mode.parse(st["mode"])
        s["model"] = f"+ {st['effect']}" + (f" ({mode.phrase()})" if mode != ADD else "")

    rec = live.get("recorder") or {}
    emu = live.get("emulator") or {}
    an = live.get("analysis") or {}
    summary = {
        "recording": str(outs["recording"]),
        "live": {"emulator": emu, "recorder": rec, "analysis": an},
        "lesson_check": lesson,
        "variance": story,
        "diagnosis": diagnosis_json(rep, series),
        "files": {k: str(v) for k, v in outs.items()},
    }
    with writing(str(outs["summary"])):
        outs["summary"].write_text(json.dumps(summary))
    if steps is not None:
        steps.close()
    return summary, _lines(summary, rep)


def _lines(s: dict, rep: dict) -> list[str]:
    L = []
    emu, rec, an = s["live"]["emulator"], s["live"]["recorder"], s["live"]["analysis"]
    L.append("== 1. live: seed lesson emulated, published over Zenoh (127.0.0.1), recorded to MCAP ==")
    from .nodes.runner import pipeline_lines
    L.append(f"recording: {s['recording']}")
    L += pipeline_lines(emu, rec)
    if an and an.get("error") is not None:
        L.append(f"  live analysis against seed-nominal (last {an.get('window_s', 120):g} s window): model error "
                 f"{an['error']:.3g}" + "".join(f"; wrote {an[k]}" for k in ("rrd", "png") if an.get(k)))
    ls = s["lesson_check"]
    L.append("")
    L.append("== 2. the lesson's check (its program: first 60 s, 10 s burn-in) ==")
    L.append(f"measured var(y) {ls['empirical_var']:.3e} m^2 against seed-nominal's predicted "
             f"{ls['predicted_var']:.3e} m^2: {ls['ratio']:.1f}x off")
    L.append("")
    L.append("== 3. why ==")
    L.append(f"a. the command response: the 0.8 N sine at 0.7 Hz moves the mass; its predicted mean response has "
             f"variance {ls['command_response_var']:.3e} m^2 ({100 * ls['command_response_var'] / ls['empirical_var']:.0f} % "
             f"of var(y)), which the lesson leaves in the measured variance. noiselab compares the residual "
             f"y - E[y]: its mean square {ls['residual_ms']:.3e} m^2, still {ls['residual_ratio']:.1f}x the prediction.")
    L.append("b. what the noise model lacks: noiselab diagnose against seed-nominal, the whole record "
             f"({rep['samples']} samples):")
    v = s["variance"]
    L.append(f"   {'model':<44} {'model error':>11} {'measured ms(y-E[y])':>20} {'predicted':>10} {'ratio':>6}")
    errs = [rep["error_before"]] + [st["error"] for st in rep["steps"]]
    for row, e in zip(v, errs):
        L.append(f"   {row['model']:<44} {e:>11.3g} {row['measured_ms']:>20.3e} {row['predicted_ms']:>10.3e} "
                 f"{row['ratio']:>6.2f}")
    for i, m in enumerate(rep["missing"], 1):
        what = Mode.parse(m["mode"]).phrase()
        ps = ", ".join(f"{k} = {val:.3g} [{m['interval'][k][0]:.3g}, {m['interval'][k][1]:.3g}]"
                       for k, val in m["params"].items() if k in m["interval"] and isinstance(val, float))
        L.append(f"   {i}. {m['effect']} ({what}): {ps}")
        L.append(f"      {m['evidence']}")
    if not rep["missing"]:
        L.append("   nothing missing found (the record may be too short for the walk: try --duration 1200)")
    L.append(f"model error {rep['error_before']:.3g} -> {rep['error_after']:.3g} (about 1 when the model explains the data)")
    f = s["files"]
    L.append(f"wrote {f['rrd']}, {f['png']}, the fitted model {f['fitted']} and the summary {f['summary']}")
    return L


def cmd_demo(args) -> int:
    from .progress import Steps, wanted

    with Steps("noiselab demo", wanted(args.progress, args.json), unit=" fits") as steps:
        summary, lines = run_demo(Path(args.out), duration=args.duration, speed=args.speed, seed=args.seed,
                                  force=args.force, max_effects=args.max_effects, progress=steps)
    if args.json:
        print(json.dumps(summary), flush=True)
    else:
        for line in lines:
            print(line, flush=True)
    return 0
