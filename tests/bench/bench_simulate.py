"""Simulation benchmarks (issue 2): noiselab's batch and step APIs against the seed lesson's loop.

Run on demand, not by pytest (``pyproject.toml`` ignores ``tests/bench``)::

    .venv/bin/python tests/bench/bench_simulate.py            # full run, ~2-3 min
    .venv/bin/python tests/bench/bench_simulate.py --write    # ... and update RESULTS.md
    .venv/bin/python tests/bench/bench_simulate.py --quick    # smoke test, a few seconds
    .venv/bin/python tests/bench/bench_simulate.py --profile  # + cProfile of the parts run
    .venv/bin/python tests/bench/bench_simulate.py --blas-threads 1 --only batch trials --write

What is measured (every ratio is taken against its peer *in the same run*):

1. ``batch``: ``load_model("seed").simulate(N, seed=1)`` (random numbers, plant, quantization, the
   whole Record) against the lesson's own loop ``tests/seed_reference.seed_loop(N)``, same N, at
   N = 1e5 and 1e6. Target: batch >= 50x faster per sample. The peer takes ~15 s at 1e6, so it is
   run ``--peer-repeat`` times (default 2) there.
2. ``step``: ``st = model.stepper(seed=1); st.step()`` in a Python loop, 1e5 steps, for ``seed``
   and for ``ALL_EFFECTS`` (a 2-state plant with every effect of the catalogue, checked against
   ``noiselab.model.effects.CATALOGUE`` at start-up). Target: < 20 us per sample (headroom for a
   10 kHz loop). The loop figure is total time / steps; the per-call percentiles come from a
   separate run that wraps each of ``--percall`` steps in ``time.perf_counter_ns``.
3. ``memory``: a 1e7-sample ``seed`` batch in a fresh subprocess: peak RSS minus the process's RSS
   after imports and model load, against the bytes of the returned arrays (t, x, u, drive, y); also
   the time of that batch. Peak and baseline are read from ``/proc/self/status`` (VmHWM, VmRSS):
   ``ru_maxrss`` is recorded too but is not usable as it stands, because Linux carries the maximum
   over ``execve`` and Python starts the child with vfork, so the child's ``ru_maxrss`` starts at
   the *parent's* peak (this benchmark's parent holds the 1e6 runs, ~240 MiB).
4. ``trials``: ``simulate(6000, trials=1000)`` time per sample-trial (informational, no target).
5. ``write``: ``noiselab simulate`` writing N = 1e6 samples of ``seed`` (3e6 messages: truth, command,
   measurement), ``write_simulation(..., fmt=F)`` for F = ``mcap`` (noiselab's JSON MCAP) and
   ``ros2`` (a rosbag2 bag: CDR ``sensor_msgs/JointState``), against the raw ``mcap.writer.Writer``
   writing *the same messages*: every message of the file just written (its bytes, channel,
   log/publish time, sequence, in file order) is read back and held in memory, then written by a
   bare ``add_message`` loop with the same profile, schemas, channels, chunk size (1 MiB) and
   compression (zstd). Ours includes everything ``simulate`` does (simulation, encoding, checks,
   writing, closing); the peer only writes. Target: ours >= 0.8x the peer's rate (peer time /
   our time), best runs; a 1e4-sample call of each side is the warm-up, and the two sides' runs
   alternate (ours, then peer and ours ``--repeat`` times) so that both meet the same load.

Timing: ``time.perf_counter`` around each call, one warm-up call first; every figure is repeated
and reported as best, median and [min, max]. Pass/fail uses the *best* run of each side (noise from
other processes only ever adds time); the median ratio is printed next to it. The machine has 2
cores and may be shared, so the load average at start and end is recorded too.

BLAS threads: the batch path's small matrix products (``(N, 2) @ (2, 2)``, real times complex in
the Schur propagator) go through OpenBLAS, whose worker threads spin when the 2 cores are shared
with other processes; that is the main source of run-to-run spread. ``--blas-threads N`` re-runs the
script with ``OPENBLAS_NUM_THREADS=OMP_NUM_THREADS=N`` (it must be set before numpy is imported).
The BLAS library and these variables are recorded with the results.

``--write`` replaces this configuration's generated block (BEGIN/END markers tagged with the BLAS
thread setting) in the "Simulation (issue 2)" section of RESULTS.md and keeps everything else,
hand-written notes included; a missing section or block is added. ``--quick`` never writes.
"""

from __future__ import annotations

import argparse
import cProfile
import datetime as _dt
import io
import json
import os
import platform
import pstats
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
for p in (str(REPO), str(REPO / "tests")):
    if p not in sys.path:
        sys.path.insert(0, p)

import numpy as np
import scipy
import seed_reference

from noiselab.model.effects import CATALOGUE
from noiselab.model.model import load_model, parse_model

RESULTS = HERE / "RESULTS.md"
SECTION = "## Simulation"
BLAS_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def run_tag() -> str:
    v = os.environ.get("OPENBLAS_NUM_THREADS")
    return "default BLAS threads" if v is None else f"OPENBLAS_NUM_THREADS={v}"


def markers(tag: str) -> tuple[str, str]:
    return (f"<!-- BEGIN bench_simulate [{tag}]: generated by tests/bench/bench_simulate.py --write -->",
            f"<!-- END bench_simulate [{tag}] -->")

TARGET_RATIO = 50.0     # batch vs lesson loop, per sample
TARGET_WRITE = 0.8      # simulate's writing rate / the raw mcap writer's, same messages
TARGET_STEP_US = 20.0   # step API, per sample

# Every effect of the catalogue on a 2-state plant (keys as the effect modules parse them).
# actuator.deadzone is in the catalogue too, so it is included: "every effect" means all 13.
ALL_EFFECTS = """
name = "bench-all-effects"
description = "2-state plant with every effect of the catalogue (benchmark only)"

[sampling]
Ts = 0.01
discretization = "zoh"

[plant]
m = 1.2
c = 0.35
k = 4.0

[command]
kind = "sine"
amplitude = 0.8
frequency_hz = 0.7

[process.white]
std = 0.20

[actuator.white]
std = 0.05

[actuator.ar1]
std = 0.08
rho = 0.97

[actuator.lag]
tau_s = 0.05

[actuator.saturation]
limit = 1.0

[actuator.deadzone]
width = 0.02

[sensor.scale_factor]
error = 0.02

[sensor.bias_walk]
std = 0.002
initial_std = 0.001

[sensor.bias_markov]
std = 0.003
tau_s = 5.0

[sensor.bias_instability]
B = 0.002

[sensor.white]
std = 0.01

[sensor.integral_white]
Q = 2e-5

[sensor.tone]
amplitude = 0.004
frequency_hz = 12.5
lines = [{amplitude = 0.002, frequency_hz = 31.0}]

[sensor.filter]
kind = "lowpass2"
cutoff_hz = 40.0

[sensor.jitter]
std_s = 0.0005

[sensor.quantization]
step = 0.001
"""


# -- helpers ----------------------------------------------------------------------------------
def timed(fn, repeat: int, warmup: int = 1) -> list[float]:
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def summary(ts: list[float]) -> dict:
    return {"runs": len(ts), "best": min(ts), "median": statistics.median(ts), "worst": max(ts)}


def loadavg() -> str:
    try:
        return " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


def machine() -> dict:
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        avail = len(os.sched_getaffinity(0))
    except AttributeError:
        avail = os.cpu_count()
    try:
        b = np.__config__.CONFIG["Build Dependencies"]["blas"]
        blas = f"{b['name']} {b['version']}"
    except (AttributeError, KeyError, TypeError):
        blas = "unknown"
    env = ", ".join(f"{k}={os.environ[k]}" for k in BLAS_VARS if k in os.environ) or "thread variables unset"
    return {"nproc": avail, "cpu": cpu, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "platform": platform.platform(), "blas": f"{blas} ({env})"}


def all_effects_model():
    model = parse_model(ALL_EFFECTS, "bench ALL_EFFECTS")
    missing = set(CATALOGUE) - set(model.effects)
    if missing:
        raise SystemExit(f"ALL_EFFECTS lacks catalogue effects: {sorted(missing)}")
    return model


# -- 1. batch vs the lesson's loop --------------------------------------------------------------
def bench_batch(sizes, repeat, peer_repeat_for) -> list[dict]:
    model = load_model("seed")
    rows = []
    for n in sizes:
        sim = timed(lambda n=n: model.simulate(n, seed=1), repeat)
        pr = peer_repeat_for(n)
        # the peer's warm-up is a small call (import, first-call costs), not a second full run
        seed_reference.seed_loop(1000)
        peer = timed(lambda n=n: seed_reference.seed_loop(n), pr, warmup=0)
        s, p = summary(sim), summary(peer)
        rows.append({"n": n, "sim": s, "peer": p,
                     "ratio_best": p["best"] / s["best"], "ratio_median": p["median"] / s["median"],
                     "ratio_worst_case": p["best"] / s["worst"]})
        print(f"  batch N={n:.0e}: sim best {s['best']:.4f} s, peer best {p['best']:.3f} s, "
              f"ratio {rows[-1]['ratio_best']:.1f}x", flush=True)
    return rows


# -- 2. step API ----------------------------------------------------------------------------------
def bench_step(models, steps, repeat, percall) -> list[dict]:
    rows = []
    for label, model in models:
        def loop(model=model):
            st = model.stepper(seed=1)
            step = st.step
            for _ in range(steps):
                step()
        ts = timed(loop, repeat)
        # per-call percentiles: a fresh stepper, warm-up, then each call timed on its own
        st = model.stepper(seed=1)
        for _ in range(1000):
            st.step()
        ns = np.empty(percall, dtype=np.int64)
        clock, step = time.perf_counter_ns, st.step
        for i in range(percall):
            t0 = clock()
            step()
            ns[i] = clock() - t0
        us = ns / 1e3
        s = summary(ts)
        rows.append({"model": label, "steps": steps, "loop": s,
                     "us_best": s["best"] / steps * 1e6, "us_median": s["median"] / steps * 1e6,
                     "us_worst": s["worst"] / steps * 1e6, "percall_n": percall,
                     "p50": float(np.percentile(us, 50)), "p90": float(np.percentile(us, 90)),
                     "p99": float(np.percentile(us, 99)), "max": float(us.max())})
        r = rows[-1]
        print(f"  step {label}: loop {r['us_best']:.2f} us/step (median {r['us_median']:.2f}), "
              f"per call p50 {r['p50']:.2f} p99 {r['p99']:.2f} us", flush=True)
    return rows


# -- 3. memory of a long batch, in a fresh process ------------------------------------------------
def _status_kib() -> dict:
    """VmRSS (current) and VmHWM (peak of this process image) in KiB, from /proc/self/status."""
    out = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        key = line.split(":", 1)[0]
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(line.split()[1])
    return out


def _mem_child(n: int) -> None:
    """Runs in the subprocess: prints one JSON line."""
    model = load_model("seed")
    base = _status_kib()                                            # after imports and model load
    base_maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB; see the module docstring
    t0 = time.perf_counter()
    rec = model.simulate(n, seed=1)
    dt = time.perf_counter() - t0
    peak = _status_kib()
    peak_maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    arrays = {f: getattr(rec, f) for f in ("t", "x", "u", "drive", "y")}
    out_bytes = int(sum(a.nbytes for a in arrays.values()))
    print(json.dumps({"n": n, "seconds": dt, "base_kib": base["VmRSS"], "peak_kib": peak["VmHWM"],
                      "rss_after_kib": peak["VmRSS"], "ru_maxrss_base_kib": base_maxrss,
                      "ru_maxrss_peak_kib": peak_maxrss, "out_bytes": out_bytes,
                      "shapes": {k: list(a.shape) for k, a in arrays.items()}}))


def bench_memory(n: int, repeat: int) -> dict:
    runs = []
    for _ in range(repeat):
        cp = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--_mem-child", str(n)],
                            capture_output=True, text=True, check=True, cwd=REPO)
        runs.append(json.loads(cp.stdout.strip().splitlines()[-1]))
    extra = [(r["peak_kib"] - r["base_kib"]) * 1024 for r in runs]
    out = runs[0]["out_bytes"]
    res = {"n": n, "runs": len(runs), "out_bytes": out, "shapes": runs[0]["shapes"],
           "base_bytes": runs[0]["base_kib"] * 1024,
           "extra_min": min(extra), "extra_median": statistics.median(extra), "extra_max": max(extra),
           "ratio_median": statistics.median(extra) / out,
           "rss_after_bytes": runs[0]["rss_after_kib"] * 1024,
           "ru_maxrss_base_bytes": runs[0]["ru_maxrss_base_kib"] * 1024,
           "ru_maxrss_peak_bytes": runs[0]["ru_maxrss_peak_kib"] * 1024,
           "time": summary([r["seconds"] for r in runs])}
    print(f"  memory N={n:.0e}: outputs {out / 2**20:.0f} MiB, peak-baseline "
          f"{res['extra_median'] / 2**20:.0f} MiB, ratio {res['ratio_median']:.2f}, "
          f"time best {res['time']['best']:.2f} s", flush=True)
    return res


# -- 4. Monte Carlo trials --------------------------------------------------------------------------
def bench_trials(n: int, trials: int, repeat: int) -> dict:
    model = load_model("seed")
    s = summary(timed(lambda: model.simulate(n, seed=1, trials=trials), repeat))
    res = {"n": n, "trials": trials, "t": s, "ns_best": s["best"] / (n * trials) * 1e9,
           "ns_median": s["median"] / (n * trials) * 1e9}
    print(f"  trials {n}x{trials}: best {s['best']:.3f} s, {res['ns_best']:.1f} ns/sample-trial", flush=True)
    return res


# -- 5. simulate's writers against the raw mcap writer ----------------------------------------------
WRITE_START_NS = 1_700_000_000_000_000_000          # a fixed wall-clock anchor: the same bytes every run


def _file_of(out: Path, fmt: str) -> Path:
    return out / f"{out.name}.mcap" if fmt == "ros2" else out


def _held_messages(path: Path):
    """Everything the raw writer needs to write ``path``'s messages again, held in memory."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        r = make_reader(f)
        header = r.get_header()
        summary = r.get_summary()
        rows = [(ch.id, m.log_time, m.data, m.publish_time, m.sequence)
                for _s, ch, m in r.iter_messages(log_time_order=False)]
    return header.profile, summary.schemas, summary.channels, rows


def _raw_write(path: Path, profile, schemas, channels, rows) -> None:
    from mcap.writer import CompressionType, Writer

    with open(path, "wb") as f:
        w = Writer(f, chunk_size=1 << 20, compression=CompressionType.ZSTD)
        w.start(profile=profile, library="bench peer")
        sid = {i: w.register_schema(s.name, s.encoding, s.data) for i, s in schemas.items()}
        cid = {i: w.register_channel(c.topic, c.message_encoding, sid[c.schema_id], c.metadata)
               for i, c in channels.items()}
        add = w.add_message
        for c, log, data, pub, seq in rows:
            add(channel_id=cid[c], log_time=log, data=data, publish_time=pub, sequence=seq)
        w.finish()


def bench_write(n: int, repeat: int) -> list[dict]:
    import shutil
    import tempfile

    from noiselab.recordings.simulated import write_simulation

    model = load_model("seed")
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for fmt in ("mcap", "ros2"):
            out = Path(d) / f"sim-{fmt}"

            def ours(k=n, out=out, fmt=fmt):
                if out.is_dir():
                    shutil.rmtree(out)
                elif out.exists():
                    out.unlink()
                write_simulation(model, k, 1, out, fmt=fmt, start_time_ns=WRITE_START_NS)

            ours(10**4)                               # warm-up (imports, first calls)
            mine = timed(ours, 1, warmup=0)           # this run's file holds the peer's messages
            held = _held_messages(_file_of(out, fmt))
            peer_path = Path(d) / "peer.mcap"
            _raw_write(peer_path, *held[:3], held[3][:10**4])

            def peer_once(held=held, peer_path=peer_path):
                _raw_write(peer_path, *held)

            peer = []
            for _ in range(repeat):                   # alternated: both sides meet the same load
                peer += timed(peer_once, 1, warmup=0)
                mine += timed(ours, 1, warmup=0)
            s, p = summary(mine), summary(peer)
            rows.append({"fmt": fmt, "n": n, "messages": len(held[3]), "ours": s, "peer": p,
                         "bytes": _file_of(out, fmt).stat().st_size, "peer_bytes": peer_path.stat().st_size,
                         "ratio_best": p["best"] / s["best"], "ratio_median": p["median"] / s["median"]})
            held = peer_once = None                   # the next format's messages take their place
            r = rows[-1]
            print(f"  write {fmt} N={n:.0e}: ours best {s['best']:.2f} s, raw writer best {p['best']:.2f} s, "
                  f"ratio {r['ratio_best']:.2f}x (median {r['ratio_median']:.2f}x)", flush=True)
    return rows


def profile_write(n: int) -> str:
    import tempfile

    from noiselab.recordings.simulated import write_simulation

    buf = io.StringIO()
    model = load_model("seed")
    with tempfile.TemporaryDirectory() as d:
        for fmt in ("mcap", "ros2"):
            pr = cProfile.Profile()
            pr.enable()
            write_simulation(model, n, 1, Path(d) / f"p-{fmt}", fmt=fmt, start_time_ns=WRITE_START_NS)
            pr.disable()
            buf.write(f"\n=== cProfile: write_simulation(seed, {n}, fmt={fmt!r}) (sorted by tottime)\n")
            pstats.Stats(pr, stream=buf).sort_stats("tottime").print_stats(15)
    return buf.getvalue()


# -- profile ---------------------------------------------------------------------------------------
def profile(n_batch: int, n_step: int) -> str:
    buf = io.StringIO()
    seed = load_model("seed")
    allm = all_effects_model()
    seed.simulate(n_batch, seed=1)
    for label, stmt, ns in (
            (f"batch seed simulate({n_batch})", lambda: seed.simulate(n_batch, seed=1), None),
            (f"step seed x{n_step}", None, seed),
            (f"step all-effects x{n_step}", None, allm)):
        pr = cProfile.Profile()
        if stmt is not None:
            pr.enable()
            stmt()
            pr.disable()
        else:
            st = ns.stepper(seed=1)
            pr.enable()
            for _ in range(n_step):
                st.step()
            pr.disable()
        buf.write(f"\n=== cProfile: {label} (sorted by tottime)\n")
        pstats.Stats(pr, stream=buf).sort_stats("tottime").print_stats(15)
    return buf.getvalue()


# -- report ----------------------------------------------------------------------------------------
def fmt_s(s: dict, unit: float = 1.0, digits: int = 3) -> str:
    return (f"{s['best'] * unit:.{digits}f} / {s['median'] * unit:.{digits}f} "
            f"[{s['best'] * unit:.{digits}f}–{s['worst'] * unit:.{digits}f}] ×{s['runs']}")


def table(res: dict) -> str:
    rows = [("| # | measure | N | time best / median [min–max] ×runs | per sample (best / median) | "
            "target | result |"),
            "|---|---|---|---|---|---|---|"]
    for b in res.get("batch", []):
        n = b["n"]
        s, p = b["sim"], b["peer"]
        rows.append(f"| 1 | batch `seed` `simulate(N, seed=1)` | {n:.0e} | {fmt_s(s, 1, 4)} s | "
                    f"{s['best'] / n * 1e6:.3f} / {s['median'] / n * 1e6:.3f} µs | | |")
        rows.append(f"| 1 | peer `seed_loop(N)` (lesson loop) | {n:.0e} | {fmt_s(p, 1, 3)} s | "
                    f"{p['best'] / n * 1e6:.2f} / {p['median'] / n * 1e6:.2f} µs | | |")
        ok = b["ratio_best"] >= TARGET_RATIO
        rows.append(f"| 1 | **ratio peer/batch** | {n:.0e} | best {b['ratio_best']:.1f}×, median "
                    f"{b['ratio_median']:.1f}×, worst batch {b['ratio_worst_case']:.1f}× | | ≥ {TARGET_RATIO:.0f}× | "
                    f"**{'PASS' if ok else 'FAIL'}** |")
    for s in res.get("step", []):
        ok = s["us_best"] < TARGET_STEP_US
        rows.append(f"| 2 | step `{s['model']}` loop | {s['steps']:.0e} | {fmt_s(s['loop'], 1, 3)} s | "
                    f"{s['us_best']:.2f} / {s['us_median']:.2f} µs | < {TARGET_STEP_US:.0f} µs | "
                    f"**{'PASS' if ok else 'FAIL'}** |")
        rows.append(f"| 2 | step `{s['model']}` per call (perf_counter_ns) | {s['percall_n']:.0e} | "
                    f"p50 {s['p50']:.2f}, p90 {s['p90']:.2f}, p99 {s['p99']:.2f}, max {s['max']:.0f} µs | | "
                    f"< {TARGET_STEP_US:.0f} µs (p50) | {'pass' if s['p50'] < TARGET_STEP_US else 'fail'} |")
    m = res.get("memory")
    if m:
        mib = 2**20
        rows.append(f"| 3 | memory `seed` `simulate(N)`, subprocess | {m['n']:.0e} | {fmt_s(m['time'], 1, 2)} s | "
                    f"{m['time']['best'] / m['n'] * 1e9:.0f} / {m['time']['median'] / m['n'] * 1e9:.0f} ns | | |")
        rows.append(f"| 3 | peak RSS (VmHWM) − baseline (VmRSS after imports) / output arrays | {m['n']:.0e} | "
                    f"{m['extra_median'] / mib:.0f} MiB [{m['extra_min'] / mib:.0f}–{m['extra_max'] / mib:.0f}] "
                    f"×{m['runs']} / {m['out_bytes'] / mib:.0f} MiB (baseline {m['base_bytes'] / mib:.0f} MiB; "
                    f"RSS after, outputs held: {m['rss_after_bytes'] / mib:.0f} MiB) | "
                    f"ratio **{m['ratio_median']:.2f}** | | info |")
        rows.append(f"| 3 | (ru_maxrss, inherited over exec: not used) | {m['n']:.0e} | "
                    f"{m['ru_maxrss_base_bytes'] / mib:.0f} MiB after imports → {m['ru_maxrss_peak_bytes'] / mib:.0f} "
                    f"MiB after the batch | | | — |")
    t = res.get("trials")
    if t:
        rows.append(f"| 4 | `simulate({t['n']}, trials={t['trials']})` | {t['n'] * t['trials']:.0e} "
                    f"sample-trials | {fmt_s(t['t'], 1, 3)} s | {t['ns_best']:.1f} / {t['ns_median']:.1f} "
                    f"ns per sample-trial | | info |")
    for w in res.get("write", []):
        n, s, p = w["n"], w["ours"], w["peer"]
        what = {"mcap": "JSON MCAP", "ros2": "rosbag2 (CDR)"}[w["fmt"]]
        rows.append(f"| 5 | `simulate` → {what}, `write_simulation(fmt={w['fmt']!r})` | {n:.0e} samples, "
                    f"{w['messages']:.0e} msgs | {fmt_s(s, 1, 2)} s | "
                    f"{s['best'] / w['messages'] * 1e6:.2f} / {s['median'] / w['messages'] * 1e6:.2f} µs per message | | |")
        rows.append(f"| 5 | peer: raw `mcap.writer.Writer`, the same messages | {w['messages']:.0e} msgs | "
                    f"{fmt_s(p, 1, 2)} s | {p['best'] / w['messages'] * 1e6:.2f} / "
                    f"{p['median'] / w['messages'] * 1e6:.2f} µs per message | | |")
        ok = w["ratio_best"] >= TARGET_WRITE
        rows.append(f"| 5 | **rate ratio ours/peer** ({what}) | {n:.0e} | best {w['ratio_best']:.2f}×, median "
                    f"{w['ratio_median']:.2f}× | | ≥ {TARGET_WRITE}× | **{'PASS' if ok else 'FAIL'}** |")
    return "\n".join(rows)


def markdown(res: dict, argv: list[str]) -> str:
    m = res["machine"]
    shown, skip = [], False
    for a in argv:                      # the command line without --json PATH
        if skip:
            skip = False
        elif a == "--json":
            skip = True
        elif not a.startswith("--json="):
            shown.append(a)
    cmd = ".venv/bin/python tests/bench/bench_simulate.py " + " ".join(shown)
    begin, end = markers(res["tag"])
    lines = [
        begin,
        f"### Run [{res['tag']}]",
        "",
        f"Run: {res['date']} (local time). Wall clock {res['wall']:.0f} s.",
        "",
        (f"Machine: nproc {m['nproc']}, CPU `{m['cpu']}`, {m['platform']}; Python {m['python']}, "
        f"numpy {m['numpy']}, scipy {m['scipy']}, BLAS {m['blas']}. Load average (1/5/15 min) at start "
        f"{res['load_start']}, at end {res['load_end']} (other processes were sharing the machine "
        "if the 1-min figure is near or above 1)."),
        "",
        ("Times: best / median [min–max] ×runs. Ratios are against the peer in the same run; "
        "pass/fail uses the best run of each side."),
        "",
        table(res),
        "",
        "Reproduce (from the repository root):",
        "",
        "```",
        cmd.strip(),
        "```",
        end,
    ]
    return "\n".join(lines)


def write_results(block: str, tag: str) -> None:
    begin, end = markers(tag)
    text = RESULTS.read_text() if RESULTS.exists() else "# Benchmark results\n"
    if begin in text and end in text:
        a = text.index(begin)
        b = text.index(end) + len(end)
        text = text[:a] + block + text[b:]
    elif SECTION in text:
        i = text.index(SECTION) + len(SECTION)
        text = text[:i] + "\n\n" + block + "\n" + text[i:]
    else:
        text = text.rstrip() + f"\n\n{SECTION}\n\n{block}\n"
    RESULTS.write_text(text)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small smoke sizes (seconds); never writes")
    ap.add_argument("--only", nargs="+", choices=("batch", "step", "memory", "trials", "write"),
                    help="run only these parts")
    ap.add_argument("--repeat", type=int, default=None, help="runs per batch/step figure (default 7, quick 2)")
    ap.add_argument("--peer-repeat", type=int, default=2, help="runs of the lesson loop at N=1e6 (~15 s each)")
    ap.add_argument("--percall", type=int, default=20000, help="steps timed one by one for percentiles")
    ap.add_argument("--mem-repeat", type=int, default=3, help="subprocess runs of the 1e7 batch")
    ap.add_argument("--write", action="store_true", help=f"update {RESULTS.relative_to(REPO)}")
    ap.add_argument("--profile", action="store_true", help="print cProfile of the batch and step paths")
    ap.add_argument("--json", type=Path, help="also dump the raw results as JSON here")
    ap.add_argument("--blas-threads", type=int, help="re-run with OPENBLAS_NUM_THREADS=OMP_NUM_THREADS=N")
    ap.add_argument("--_mem-child", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args._mem_child:
        _mem_child(args._mem_child)
        return 0
    if args.blas_threads is not None and os.environ.get("OPENBLAS_NUM_THREADS") != str(args.blas_threads):
        env = dict(os.environ, OPENBLAS_NUM_THREADS=str(args.blas_threads), OMP_NUM_THREADS=str(args.blas_threads))
        sys.stdout.flush()
        os.execve(sys.executable, [sys.executable, str(Path(__file__).resolve()), *argv], env)
    if args.quick and args.write:
        ap.error("--quick figures are smoke sizes: not written to RESULTS.md")

    parts = set(args.only or ("batch", "step", "memory", "trials", "write"))
    q = args.quick
    repeat = args.repeat or (2 if q else 7)
    sizes = (10**4,) if q else (10**5, 10**6)
    steps = 10**4 if q else 10**5
    percall = min(args.percall, 2000) if q else args.percall
    mem_n = 10**5 if q else 10**7
    tr_n, tr_k = (600, 100) if q else (6000, 1000)
    write_n = 10**5 if q else 10**6

    res: dict = {"date": _dt.datetime.now().strftime("%Y-%m-%d %H:%M"), "machine": machine(),
                 "load_start": loadavg(), "quick": q, "tag": run_tag()}
    mach = res["machine"]
    print(f"noiselab simulation bench{' (quick)' if q else ''} [{res['tag']}]: {mach['cpu']}, "
          f"nproc {mach['nproc']}, Python {mach['python']}, numpy {mach['numpy']}, BLAS {mach['blas']}; "
          f"load {res['load_start']}", flush=True)
    t_all = time.perf_counter()
    if "batch" in parts:
        res["batch"] = bench_batch(sizes, repeat,
                                   lambda n: args.peer_repeat if n >= 10**6 else (2 if q else 3))
    if "step" in parts:
        res["step"] = bench_step([("seed", load_model("seed")), ("all-effects", all_effects_model())],
                                 steps, max(3, repeat // 2) if not q else repeat, percall)
    if "memory" in parts:
        res["memory"] = bench_memory(mem_n, 1 if q else args.mem_repeat)
    if "trials" in parts:
        res["trials"] = bench_trials(tr_n, tr_k, repeat if q else 5)
    if "write" in parts:
        res["write"] = bench_write(write_n, 2 if q else 3)
    res["wall"] = time.perf_counter() - t_all
    res["load_end"] = loadavg()
    print()
    print(table(res))
    print(f"\nload average at end: {res['load_end']}; wall {res['wall']:.0f} s")
    if args.profile:
        if parts & {"batch", "step"}:
            print(profile(10**5 if q else 10**6, steps))
        if "write" in parts:
            print(profile_write(write_n))
    if args.json:
        args.json.write_text(json.dumps(res, indent=1, default=float))
    if args.write:
        write_results(markdown(res, argv), res["tag"])
        print(f"updated {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
