"""Analysis benchmarks (issue 4): offline analysis of 1e6 samples, Allan deviation of 1e7 samples,
CPU and memory of the live analyzer at 1 kHz.

Run on demand, not by pytest (``pyproject.toml`` ignores ``tests/bench``)::

    .venv/bin/python tests/bench/bench_analysis.py                  # full run, ~15 min
    .venv/bin/python tests/bench/bench_analysis.py --write          # ... and update RESULTS.md
    .venv/bin/python tests/bench/bench_analysis.py --quick          # smoke test, ~1-2 min, never writes
    .venv/bin/python tests/bench/bench_analysis.py --only live      # one part (offline, allan, live)
    .venv/bin/python tests/bench/bench_analysis.py --profile        # + cProfile of each part
    .venv/bin/python tests/bench/bench_analysis.py --wait-quiet 0.8 --workdir /tmp/ba --write \
        --live-source replay emulate --live-long 200 --live-profile --profile   # what RESULTS.md holds (~30 min)

The model is the built-in ``seed`` scenario (``service/scenarios/seed.toml``) with Ts = 1 ms and its
name changed to ``benchana``, written to a TOML file in the work directory. Recordings are made once
with ``noiselab simulate MODEL --duration D --out FILE`` (kept and reused with ``--workdir``).

Parts (ratios against a named peer measured in the same run):

1. ``offline``: ``noiselab analyze FILE --model MODEL --json`` on a 1000 s recording (1e6 samples,
   every view: variance, acf, psd, allan) as a subprocess, wall time best and median of
   ``--repeat`` runs (target < 10 s); the same with ``--rrd`` (Rerun file + PNG, which also reads
   the truth topic) as information. Then in this process, the split:
   ``noiselab.recordings.load.load_noiselab`` (without truth, as ``--json``; with truth, as ``--rrd``),
   ``compare()`` cold (its prediction caches cleared: what a fresh CLI process pays) and warm,
   ``noiselab.viewers.rerun_log.log_comparisons`` (.rrd) and ``noiselab.viewers.summary_png.write_summary_png``, and
   the interpreter start-up + imports of the CLI (``python -c "import noiselab.cli, ..."``).
   Peer for the reading part: the mcap library's own reader,
   ``mcap.reader.make_reader(f).iter_messages()`` over the same file with ``json.loads`` of every
   payload: all three topics (against the load with truth) and the two topics the ``--json``
   analysis reads (``topics=[measurement, command]``, against the load without truth).
2. ``allan``: ``tests/bench/bench_allan.py`` (overlapping Allan deviation of 1e7 samples at octave
   taus, noiselab against allantools), run as a subprocess and its printed figures parsed.
   Target (issue 4): at least as fast as allantools.
3. ``live``: ``noiselab analyze --live --model MODEL --window 60 --update 0.5 --json --listen P``
   fed by ``noiselab replay FILE --connect P`` of a 60 s recording at Ts = 1 ms (real time;
   ``--live-source emulate`` uses ``noiselab emulate MODEL --duration 60``, both: ``--live-source
   replay emulate``). FILE is the ``noiselab simulate`` recording as written (``simulate`` writes
   the topics sample by sample and ``replay`` publishes in publish_time order whatever the file's
   layout; before, the bench re-wrote the file because per-topic blocks replayed one topic first).
   ``--live-long S`` adds an S-second replay (S > window + warm-up = 124 s) to see memory once the
   ring buffer is full; ``--live-profile`` adds a replay with the analyzer under cProfile. This process
   subscribes to ``noiselab/benchana/analysis`` (the analyzer's published updates) and samples the
   analyzer every 0.25 s with psutil. Reported: CPU (user + system seconds from
   ``psutil.Process.cpu_times`` over the stream / wall seconds of the stream), RSS at stream times
   10/30/60 s, peak RSS (``VmHWM``), updates published while the stream ran against the expected
   duration / 0.5, their intervals and staleness (arrival - stream time of the newest analysed
   sample), and the ``updates`` / ``received`` of the analyzer's ``--json`` summary. The stream's
   start in wall time is estimated as min(arrival - t) over the updates. The analyzer is stopped
   with SIGINT as soon as the replay exits. Targets: updates at 2 Hz or faster (>= 98 % of the
   expected count while the stream runs); memory bounded: once the ring buffer is full (window +
   warm-up, 124 s here) RSS stops growing, i.e. RSS at the end within 10 % of RSS 30 s after the
   fill (checked on runs long enough, ``--live-long``; on shorter runs the growth over the last
   30 s is shown as information: the window is still filling).
   Diagnostic (in this process, no Zenoh): a ``LiveAnalyzer`` fed with the recording's payloads
   0.5 s at a time, the cost of ``drain()`` (decoding 0.5 s of messages) and of ``analyse()`` at
   several fill levels, and (full run) at the steady state where the ring buffer is full
   (window + 4 transients, ~124 s at Ts = 1 ms) and the prediction caches hit.

Timing: ``time.perf_counter`` (subprocesses: around ``subprocess.run``); best and median
reported, pass/fail on the best (noise from other processes only ever adds time). The machine has
2 cores and is shared: the 1-min load average is recorded at the start and end of every part;
``--wait-quiet L`` waits (up to 15 min) for it to fall below L before each part. Every node runs on
a free loopback port (``noiselab.nodes.runner.free_port``), never 7447.

``--write`` replaces the generated block (BEGIN/END markers) in the "Analysis" section
of RESULTS.md (re-read right before writing) and keeps everything else; a missing section is
appended at the end. ``--quick`` never writes.
"""

from __future__ import annotations

import argparse
import cProfile
import datetime as _dt
import io
import json
import os
import pstats
import re
import shutil
import signal
import statistics
import subprocess
import sys
import sysconfig
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
for p in (str(REPO), str(REPO / "tests"), str(HERE)):
    if p not in sys.path:
        sys.path.insert(0, p)

import numpy as np  # noqa: E402
import psutil  # noqa: E402

from bench_simulate import loadavg, machine, summary  # noqa: E402  (same helpers, same format)

RESULTS = HERE / "RESULTS.md"
SECTION = "## Analysis"
BEGIN = "<!-- BEGIN bench_analysis: generated by tests/bench/bench_analysis.py --write -->"
END = "<!-- END bench_analysis -->"
NAME = "benchana"
TARGET_OFFLINE_S = 10.0
TARGET_UPDATE_HZ = 2.0
UPDATES_FRACTION = 0.98      # updates while streaming / expected, to count as "2 Hz or faster"
RSS_GROWTH_MAX = 0.10        # RSS(end) / RSS(fill + 30 s) - 1 once the ring buffer is full
MIB = 2**20


# -- helpers ----------------------------------------------------------------------------------------
def code_version() -> str:
    """git HEAD and the product files changed in the working tree (others edit concurrently)."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=REPO,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "service", "viewers"], capture_output=True,
                               text=True, cwd=REPO, check=True).stdout.split("\n")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    changed = [ln[3:] for ln in dirty if ln.strip()]
    return head + (f" + uncommitted changes in {', '.join(changed)}" if changed else "")


def load1() -> float:
    return os.getloadavg()[0]


def wait_quiet(limit: float | None, what: str, max_wait: float = 900.0) -> None:
    if not limit:
        return
    t0 = time.monotonic()
    while load1() >= limit and time.monotonic() - t0 < max_wait:
        time.sleep(10)
    print(f"  [{what}] load {loadavg()} (waited {time.monotonic() - t0:.0f} s for < {limit})", flush=True)


def cli_prefix() -> list[str]:
    """The installed ``noiselab`` console script next to this interpreter, else ``python -m``."""
    exe = Path(sys.executable).parent / "noiselab"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "noiselab.cli"]


def node_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "noiselab.cli", *args]


def child_env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def write_model(workdir: Path, Ts: float = 0.001) -> Path:
    src = (REPO / "service/scenarios/seed.toml").read_text()
    text, n1 = re.subn(r'(?m)^name = "seed"', f'name = "{NAME}"', src)
    text, n2 = re.subn(r"(?m)^Ts = [0-9.eE+-]+", f"Ts = {Ts!r}", text)
    if (n1, n2) != (1, 1):
        raise SystemExit("seed.toml: could not set name and Ts")
    path = workdir / f"{NAME}-Ts{Ts:g}.toml"
    if not path.exists() or path.read_text() != text:
        path.write_text(text)
    return path


def make_recording(model: Path, duration: float, workdir: Path) -> tuple[Path, float | None]:
    """``noiselab simulate`` once; reused when the file is newer than the model file."""
    out = workdir / f"{NAME}-{duration:g}s.mcap"
    if out.exists() and out.stat().st_mtime > model.stat().st_mtime:
        return out, None
    t0 = time.perf_counter()
    subprocess.run(cli_prefix() + ["simulate", str(model), "--duration", f"{duration:g}", "--out", str(out),
                                   "--force", "--json"], check=True, capture_output=True, text=True,
                   cwd=REPO, env=child_env())
    return out, time.perf_counter() - t0


def fill_seconds(model: Path, window: float) -> float:
    """Seconds of stream until the live analyzer's ring buffer is full (window + warm-up)."""
    from noiselab.nodes.analyzer import LiveAnalyzer
    an = LiveAnalyzer(str(model), device=None, window_s=window, log=io.StringIO())
    return an.meas.cap * an.model.Ts


def profiled_where(fname: str, line: int, func: str) -> str:
    """``file:line:function`` of a profiled function, its file relative to the repository, to
    site-packages or to the standard library: RESULTS.md holds no machine's absolute paths (a file
    under none of them is named by its base name)."""
    if not line:
        return func
    paths = sysconfig.get_paths()
    roots = {str(REPO)} | {paths[k] for k in ("purelib", "platlib", "stdlib", "platstdlib") if k in paths}
    for root in sorted(roots, key=len, reverse=True):      # site-packages before the stdlib that holds it
        base = root.rstrip("/") + "/"
        if fname.startswith(base):
            return f"{fname[len(base):]}:{line}:{func}"
    return f"{os.path.basename(fname) if os.path.isabs(fname) else fname}:{line}:{func}"


def top_functions(pr: cProfile.Profile, n: int = 12, key: str = "tottime") -> list[dict]:
    """The n most expensive functions as {where, tottime, cumtime, calls}."""
    st = pstats.Stats(pr)
    rows = []
    for (fname, line, func), (cc, nc, tt, ct, _callers) in st.stats.items():
        rows.append({"where": profiled_where(fname, line, func), "tottime": tt, "cumtime": ct, "calls": nc})
    rows.sort(key=lambda r: -r[key])
    return rows[:n]


def print_profile(label: str, pr: cProfile.Profile) -> str:
    buf = io.StringIO()
    buf.write(f"\n=== cProfile: {label} (sorted by tottime)\n")
    pstats.Stats(pr, stream=buf).sort_stats("tottime").print_stats(18)
    buf.write(f"=== cProfile: {label} (sorted by cumtime)\n")
    pstats.Stats(pr, stream=buf).sort_stats("cumtime").print_stats(18)
    return buf.getvalue()


def clear_compare_caches() -> None:
    from noiselab.diagnose import compare as cm
    cm.cache_clear()


# -- 1. offline ---------------------------------------------------------------------------------------
def run_cli_analyze(rec: Path, model: Path, extra: list[str]) -> tuple[float, dict]:
    t0 = time.perf_counter()
    cp = subprocess.run(cli_prefix() + ["analyze", str(rec), "--model", str(model), "--json", *extra],
                        capture_output=True, text=True, cwd=REPO, env=child_env())
    dt = time.perf_counter() - t0
    if cp.returncode != 0:
        raise SystemExit(f"noiselab analyze failed ({cp.returncode}): {cp.stderr.strip()[-400:]}")
    return dt, json.loads(cp.stdout.strip().splitlines()[-1])


def peer_read(rec: Path, topics: list[str] | None) -> int:
    from mcap.reader import make_reader
    n = 0
    loads = json.loads
    with open(rec, "rb") as f:
        for _schema, _channel, message in make_reader(f).iter_messages(topics=topics):
            loads(message.data)
            n += 1
    return n


def bench_offline(model: Path, rec: Path, repeat: int, peer_repeat: int, rrd_repeat: int, workdir: Path,
                  wait: float | None, prof: bool) -> dict:
    from noiselab.diagnose.compare import compare
    from noiselab.recordings.load import load_noiselab
    from noiselab.model import load_model
    from noiselab.viewers.rerun_log import log_comparisons
    from noiselab.viewers.summary_png import write_summary_png

    wait_quiet(wait, "offline")
    res: dict = {"load_start": loadavg(), "file_bytes": rec.stat().st_size}
    # CLI, --json (the target)
    runs, rep = [], None
    run_cli_analyze(rec, model, [])                              # warm-up: page cache, .pyc
    for _ in range(repeat):
        dt, rep = run_cli_analyze(rec, model, [])
        runs.append(dt)
    res["cli_json"] = summary(runs)
    res["load_after"] = {"cli_json": loadavg()}
    res["samples"] = rep["samples"]
    res["error"] = rep["error"]
    res["error_per_view"] = rep["error_per_view"]
    res["views"] = {k: sum(v["points"] for v in vs) for k, vs in rep["views"].items()}
    print(f"  analyze --json: best {min(runs):.2f} s, median {statistics.median(runs):.2f} s "
          f"({rep['samples']} samples analysed, model error {rep['error']:.3g}); load {loadavg()}", flush=True)
    # CLI, --rrd (information)
    runs = []
    for _ in range(rrd_repeat):
        out = workdir / "bench-analysis.rrd"
        dt, _ = run_cli_analyze(rec, model, ["--rrd", str(out), "--force"])
        runs.append(dt)
    if runs:
        res["cli_rrd"] = summary(runs)
        res["rrd_bytes"] = out.stat().st_size
        res["png_bytes"] = out.with_suffix(".png").stat().st_size
        res["load_after"]["cli_rrd"] = loadavg()
        print(f"  analyze --rrd: best {min(runs):.2f} s; load {loadavg()}", flush=True)
    # start-up + imports of the CLI process
    imp = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import noiselab.cli, noiselab.diagnose.compare, noiselab.recordings.load, "
                        "noiselab.model, noiselab.recordings.reader"], check=True, cwd=REPO, env=child_env())
        imp.append(time.perf_counter() - t0)
    res["startup_imports"] = summary(imp)
    # in-process split
    m = load_model(str(model))
    split = {k: [] for k in ("load", "load_truth", "compare_cold", "compare_warm", "rrd", "png")}
    load_noiselab(str(rec), truth=False)                         # warm-up
    for _ in range(repeat):
        t0 = time.perf_counter()
        s = load_noiselab(str(rec), truth=False)
        split["load"].append(time.perf_counter() - t0)
        clear_compare_caches()
        t0 = time.perf_counter()
        compare(m, s.t, s.y, s.u, burn=None)
        split["compare_cold"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        compare(m, s.t, s.y, s.u, burn=None)
        split["compare_warm"].append(time.perf_counter() - t0)
        del s
    for _ in range(max(1, rrd_repeat)):
        t0 = time.perf_counter()
        s = load_noiselab(str(rec), truth=True)
        split["load_truth"].append(time.perf_counter() - t0)
        c = compare(m, s.t, s.y, s.u, truth=s.truth, burn=None)
        t0 = time.perf_counter()
        log_comparisons([c], str(workdir / "bench-inproc.rrd"))
        split["rrd"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        write_summary_png([c], str(workdir / "bench-inproc.png"))
        split["png"].append(time.perf_counter() - t0)
        del s, c
    res["split"] = {k: summary(v) for k, v in split.items() if v}
    res["load_after"]["split"] = loadavg()
    print("  split (best): " + ", ".join(f"{k} {v['best']:.2f} s" for k, v in res["split"].items())
          + f"; load {loadavg()}", flush=True)
    # peer: the mcap library's reader + json.loads
    topics2 = [f"noiselab/{NAME}/measurement", f"noiselab/{NAME}/command"]
    peer = {"all": [], "two": []}
    for _ in range(peer_repeat):
        for key, topics in (("all", None), ("two", topics2)):
            t0 = time.perf_counter()
            n = peer_read(rec, topics)
            peer[key].append(time.perf_counter() - t0)
            res[f"peer_{key}_messages"] = n
    res["peer_all"] = summary(peer["all"])
    res["peer_two"] = summary(peer["two"])
    res["load_after"]["peer"] = loadavg()
    res["ratio_read_all"] = res["peer_all"]["best"] / res["split"]["load_truth"]["best"]
    res["ratio_read_two"] = res["peer_two"]["best"] / res["split"]["load"]["best"]
    print(f"  peer mcap reader + json.loads: all topics best {res['peer_all']['best']:.1f} s "
          f"(x{res['ratio_read_all']:.1f} of load with truth), 2 topics {res['peer_two']['best']:.1f} s "
          f"(x{res['ratio_read_two']:.1f} of load); load {loadavg()}", flush=True)
    if prof:
        clear_compare_caches()
        pr = cProfile.Profile()
        pr.enable()
        s = load_noiselab(str(rec), truth=False)
        compare(m, s.t, s.y, s.u, burn=None)
        pr.disable()
        res["profile_json"] = top_functions(pr)
        res["profile_json_cum"] = top_functions(pr, 16, "cumtime")
        res["profile_text"] = print_profile("offline: load_noiselab(truth=False) + compare (cold)", pr)
        pr = cProfile.Profile()
        pr.enable()
        s = load_noiselab(str(rec), truth=True)
        c = compare(m, s.t, s.y, s.u, truth=s.truth, burn=None)
        log_comparisons([c], str(workdir / "bench-inproc.rrd"))
        write_summary_png([c], str(workdir / "bench-inproc.png"))
        pr.disable()
        res["profile_rrd"] = top_functions(pr)
        res["profile_text"] += print_profile("offline --rrd: load (truth) + compare + rrd + png", pr)
    res["load_end"] = loadavg()
    return res


# -- 2. Allan (bench_allan.py) ---------------------------------------------------------------------------
def bench_allan_run(n: int, repeat: int, wait: float | None) -> dict:
    wait_quiet(wait, "allan")
    res = {"load_start": loadavg(), "n": n, "repeat": repeat}
    cmd = [sys.executable, str(HERE / "bench_allan.py"), "--n", str(n), "--repeat", str(repeat)]
    cp = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, env=child_env())
    res["stdout"] = cp.stdout
    if cp.returncode != 0:
        raise SystemExit(f"bench_allan.py failed: {cp.stdout}{cp.stderr}")
    num = r"([0-9.eE+-]+)"
    m1 = re.search(r"(\d+) octave taus", cp.stdout)
    m2 = re.search(rf"noiselab\s+{num} s", cp.stdout)
    m3 = re.search(rf"allantools\s*{num} s", cp.stdout)
    m4 = re.search(rf"ratio allantools/noiselab {num}x, max relative difference {num}", cp.stdout)
    if not (m1 and m2 and m3 and m4):
        raise SystemExit(f"bench_allan.py: unexpected output:\n{cp.stdout}")
    res.update(taus=int(m1.group(1)), noiselab=float(m2.group(1)), allantools=float(m3.group(1)),
               ratio=float(m4.group(1)), rel=float(m4.group(2)))
    res["load_end"] = loadavg()
    print(f"  allan N={n:.0e}: noiselab {res['noiselab']:.3f} s, allantools {res['allantools']:.3f} s, "
          f"x{res['ratio']:.2f}; load {res['load_end']}", flush=True)
    return res


# -- 3. live analyzer ---------------------------------------------------------------------------------
def _status(pid: int) -> dict:
    out = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            k = line.split(":", 1)[0]
            if k in ("VmRSS", "VmHWM"):
                out[k] = int(line.split()[1]) * 1024
    except OSError:
        pass
    return out


def _pump(stream, sink: list, mark: str | None = None, ev: threading.Event | None = None) -> None:
    for line in stream:
        sink.append(line)
        if mark and ev is not None and mark in line:
            ev.set()


def bench_live(model: Path, rec: Path, duration: float, window: float, update: float, source: str,
               wait: float | None, profile_to: Path | None = None, fill_s: float = 124.0) -> dict:
    from noiselab.nodes import transport
    from noiselab import wire
    from noiselab.nodes.runner import free_port

    wait_quiet(wait, "live")
    res: dict = {"load_start": loadavg(), "duration": duration, "window": window, "update": update,
                 "source": source}
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    env = child_env()
    ana_cmd = node_cmd("analyze", "--live", "--model", str(model), "--window", f"{window:g}",
                       "--update", f"{update:g}", "--json", "--listen", ep)
    if profile_to is not None:                       # the analyzer's main thread under cProfile
        ana_cmd = [sys.executable, "-m", "cProfile", "-o", str(profile_to)] + ana_cmd[1:]
        res["profiled"] = True
    res["analyzer_cmd"] = "noiselab " + " ".join(ana_cmd[ana_cmd.index("noiselab.cli") + 1:])
    ana = subprocess.Popen(ana_cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=env)
    out_lines, err_lines = [], []
    ready = threading.Event()
    threads = [threading.Thread(target=_pump, args=(ana.stdout, out_lines), daemon=True),
               threading.Thread(target=_pump, args=(ana.stderr, err_lines, "noiselab analyze: live on", ready),
                                daemon=True)]
    for th in threads:
        th.start()
    src = None
    try:
        if not ready.wait(60):
            raise SystemExit(f"analyzer did not start: {''.join(err_lines)[-400:]}")
        pana = psutil.Process(ana.pid)
        arrivals: list[tuple[float, dict]] = []

        def on_analysis(sample):
            arrivals.append((time.monotonic(), json.loads(sample.payload.to_bytes())))

        ns = argparse.Namespace(connect=[ep], listen=None, config=None, mode=None, connect_timeout=10.0)
        samples: list[dict] = []
        stop_sampling = threading.Event()
        psrc_box: list = [None]

        def sampler():
            while not stop_sampling.is_set():
                t = time.monotonic()
                try:
                    ct = pana.cpu_times()
                    row = {"t": t, "cpu": ct.user + ct.system, "rss": pana.memory_info().rss}
                except psutil.Error:
                    return
                ps = psrc_box[0]
                if ps is not None:
                    try:
                        c2 = ps.cpu_times()
                        row["src_cpu"] = c2.user + c2.system
                    except psutil.Error:
                        pass
                samples.append(row)
                stop_sampling.wait(0.25)

        with transport.open_session(ns, "sink") as session:
            sub = session.declare_subscriber(wire.key(NAME, wire.ANALYSIS), on_analysis)
            time.sleep(0.5)                                          # let the subscription propagate
            th = threading.Thread(target=sampler, daemon=True)
            th.start()
            if source == "replay":
                src_cmd = node_cmd("replay", str(rec), "--connect", ep, "--wait-subscribers", "20", "--json")
            else:
                src_cmd = node_cmd("emulate", str(model), "--duration", f"{duration:g}", "--connect", ep,
                                   "--wait-subscribers", "20", "--json")
            res["source_cmd"] = "noiselab " + " ".join(src_cmd[src_cmd.index("noiselab.cli") + 1:])
            t_src0 = time.monotonic()
            src = subprocess.Popen(src_cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                                   env=env)
            psrc_box[0] = psutil.Process(src.pid)
            src_out, src_err = src.communicate(timeout=duration * 3 + 120)
            t_end = time.monotonic()
            ct = pana.cpu_times()
            end_row = {"t": t_end, "cpu": ct.user + ct.system, "rss": pana.memory_info().rss}
            st = _status(ana.pid)
            n_arrivals_at_end = len(arrivals)
            ana.send_signal(signal.SIGINT)
            ana.wait(timeout=60)
            stop_sampling.set()
            th.join(5)
            sub.undeclare()
        for t in threads:
            t.join(5)
        if src.returncode != 0:
            raise SystemExit(f"{source} failed: {src_err[-400:]}")
        res["source_summary"] = json.loads(src_out.strip().splitlines()[-1])
        summ = None
        for line in reversed(out_lines):
            if line.strip().startswith("{"):
                summ = json.loads(line)
                break
        if summ is None:
            raise SystemExit(f"analyzer gave no JSON summary: {''.join(err_lines)[-400:]}")
        res["analyzer_summary"] = {k: summ.get(k) for k in ("updates", "received", "malformed", "samples", "error",
                                                            "error_per_view", "late_ticks")}
        during = arrivals[:n_arrivals_at_end]
        if not during:
            raise SystemExit("no analysis update received")
        t0 = min(a - float(p["t"]) for a, p in during)           # stream start in wall time
        during = [(a, p) for a, p in during if a >= t0]
        arr = np.array([a for a, _ in during])
        stream_wall = t_end - t0
        iv = np.diff(arr)
        stale = np.array([a - t0 - float(p["t"]) for a, p in during])
        expected = duration / update
        res.update(
            stream_wall=stream_wall, start_delay=t0 - t_src0, updates_during=len(during),
            updates_expected=expected, updates_ratio=len(during) / expected,
            rate_hz=(len(during) - 1) / (arr[-1] - arr[0]) if len(during) > 1 else 0.0,
            interval={"p50": float(np.median(iv)), "p90": float(np.percentile(iv, 90)), "max": float(iv.max())}
            if iv.size else {},
            staleness={"p50": float(np.median(stale)), "max": float(stale.max())},
            samples_last=int(during[-1][1].get("samples", 0)), received_last=int(during[-1][1].get("received", 0)))
        # CPU over the stream (sampler row at or just before the start estimate -> the row at the end)
        rows = [r for r in samples if r["t"] <= t0] or samples[:1]
        r0 = rows[-1]
        res["cpu"] = (end_row["cpu"] - r0["cpu"]) / (end_row["t"] - r0["t"])
        src_rows = [r for r in samples if "src_cpu" in r]
        if len(src_rows) >= 2:
            a = [r for r in src_rows if r["t"] <= t0] or src_rows[:1]
            b = src_rows[-1]
            res["src_cpu"] = (b["src_cpu"] - a[-1]["src_cpu"]) / (b["t"] - a[-1]["t"])
        res["rss_start"] = r0["rss"]
        res["rss_at"] = {}
        for ts in (10, 30, 60, 90, 120, 150, 180, 240, 300):
            if ts > duration + 1e-9:
                break
            near = min(samples + [end_row], key=lambda r: abs(r["t"] - (t0 + ts)))
            res["rss_at"][ts] = near["rss"]
        res["rss_end"] = end_row["rss"]
        res["vmhwm"] = st.get("VmHWM")
        res["fill_s"] = fill_s
        res["steady"] = duration >= fill_s + 60            # enough of the run after the ring is full
        half = fill_s + 30 if res["steady"] else max(duration - 30, duration / 2)
        near_half = min(samples, key=lambda r: abs(r["t"] - (t0 + half)))["rss"]
        res["rss_half_s"] = half
        res["rss_growth"] = end_row["rss"] / near_half - 1
        res["ok_updates"] = res["updates_ratio"] >= UPDATES_FRACTION
        res["ok_memory"] = res["rss_growth"] <= RSS_GROWTH_MAX if res["steady"] else None
        print(f"  live ({source}, {duration:g} s): {len(during)} updates during the stream / {expected:.0f} expected "
              f"({res['rate_hz']:.2f} Hz, interval p50 {res['interval'].get('p50', 0):.3f} s, max "
              f"{res['interval'].get('max', 0):.3f} s), CPU {res['cpu'] * 100:.0f} %, RSS "
              + ", ".join(f"{k} s {v / MIB:.0f}" for k, v in res["rss_at"].items())
              + f" MiB, VmHWM {res['vmhwm'] / MIB:.0f} MiB; load {loadavg()}", flush=True)
    finally:
        for proc in (src, ana):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
    res["load_end"] = loadavg()
    return res


def live_profile_split(path: Path) -> dict:
    """Where the profiled analyzer's main thread spent its time (cProfile of the whole process:
    Zenoh's callback threads are not in it)."""
    st = pstats.Stats(str(path))
    cum: dict[str, float] = {}
    for (fname, line, func), (_cc, _nc, _tt, ct, _c) in st.stats.items():
        for key, (suffix, name) in {"wait": ("threading.py", "wait"), "drain": ("analyzer.py", "drain"),
                                    "analyse": ("analyzer.py", "analyse"), "compare": ("compare.py", "compare"),
                                    "reload": ("analyzer.py", "maybe_reload"),
                                    "summary": ("analyzer.py", "summary_of"),
                                    "run_live": ("analyzer.py", "run_live")}.items():
            if fname.endswith(suffix) and func == name:
                cum[key] = max(cum.get(key, 0.0), ct)
    pr_rows = []
    for (fname, line, func), (_cc, nc, tt, ct, _c) in st.stats.items():
        pr_rows.append({"where": profiled_where(fname, line, func), "tottime": tt, "cumtime": ct, "calls": nc})
    return {"split": cum, "top_tottime": sorted(pr_rows, key=lambda r: -r["tottime"])[:12],
            "top_cumtime": [r for r in sorted(pr_rows, key=lambda r: -r["cumtime"])
                            if not any(w in r["where"] for w in _WRAPPERS)][:16]}


# start-up frames that hold the whole run (left out of the cumulative table)
_WRAPPERS = ("builtins.exec", "<string>", "runpy", "service/cli.py", "service/commands/analyze.py",
             "cmd_analyze_live")


def live_phases(model: Path, rec: Path, update: float, window: float, at: list[float], steady: int,
                prof: bool) -> dict:
    """A LiveAnalyzer (the product class) fed in this process with the recording's measurement and
    command payloads in sample order, ``update`` seconds at a time (as the Zenoh callback queues
    them), after its start-up warm-up (``warm()``, timed) as ``run_live`` does: drain() of every
    chunk and analyse() of every update timed (as the node, which analyses at every tick); reported
    at the stream times ``at``, as p50 / p90 / max while the window fills and once the ring buffer
    is full, and (``steady``) that many consecutive updates after the fill."""
    from noiselab.diagnose.compare import compare  # noqa: F401  (import cost outside the timing)
    from noiselab import wire
    from noiselab.recordings.scan import iter_messages
    from noiselab.nodes.analyzer import LiveAnalyzer

    clear_compare_caches()
    an = LiveAnalyzer(str(model), device=None, window_s=window, log=io.StringIO())
    t0 = time.perf_counter()
    an.warm()
    warm_s = time.perf_counter() - t0
    keys = {wire.key(NAME, k) for k in ("measurement", "command")}
    msgs = [(ch.topic, m.data, m.publish_time) for _s, ch, m in iter_messages(str(rec)) if ch.topic in keys]
    msgs.sort(key=lambda r: (r[2], r[0].endswith("measurement")))     # sample order, command first
    pub0 = msgs[0][2]
    step_ns = int(round(update * 1e9))
    cap_s = an.meas.cap * an.model.Ts
    res = {"cap_samples": an.meas.cap, "cap_s": cap_s, "warmup": an.warmup, "drain": [], "analyse": [],
           "steady": [], "warm_s": warm_s, "every": []}
    i, k = 0, 1
    at = sorted(at)
    steady_from = cap_s + 1.0
    prof_out = None
    while i < len(msgs):
        lim = pub0 + k * step_ns
        j = i
        while j < len(msgs) and msgs[j][2] < lim:
            j += 1
        for topic, data, _ in msgs[i:j]:
            an.q.put((topic, data))
        t0 = time.perf_counter()
        an.drain()
        res["drain"].append((j - i, time.perf_counter() - t0))
        ts = k * update
        i = j
        k += 1
        want_at = at and ts >= at[0] - 1e-9
        want_steady = steady and ts >= steady_from and len(res["steady"]) < steady
        pr = None
        if prof and want_at and at[0] == at[-1]:
            pr = cProfile.Profile()
            pr.enable()
        t0 = time.perf_counter()
        cmp = an.analyse()
        dt = time.perf_counter() - t0
        if pr is not None:
            pr.disable()
            prof_out = (ts, pr)
        n = 0 if cmp is None else int(cmp.t.size)
        res["every"].append({"t": ts, "n": n, "s": dt})
        if want_at:
            res["analyse"].append({"t": ts, "n": n, "s": dt})
            at.pop(0)
        elif want_steady:
            res["steady"].append({"t": ts, "n": n, "s": dt})
    d = np.array([s for _, s in res["drain"]])
    cnt = np.array([c for c, _ in res["drain"]])
    res["drain_per_update"] = {"p50": float(np.median(d)), "max": float(d.max()), "messages": int(np.median(cnt))}
    res["drain_us_per_msg"] = float(d.sum() / max(cnt.sum(), 1) * 1e6)
    for key, sel in (("fill_stats", lambda e: e["t"] < cap_s), ("steady_stats", lambda e: e["t"] >= cap_s)):
        v = np.array([e["s"] for e in res["every"] if sel(e)])
        if v.size:
            res[key] = {"updates": int(v.size), "p50": float(np.median(v)), "p90": float(np.percentile(v, 90)),
                        "max": float(v.max()), "over_half_update": int(np.sum(v > update / 2)),
                        "over_update": int(np.sum(v > update))}
    if prof_out is not None:
        res["profile"] = top_functions(prof_out[1])
        res["profile_cum"] = top_functions(prof_out[1], 16, "cumtime")
        res["profile_t"] = prof_out[0]
        res["profile_text"] = print_profile(f"live analyse() at t = {prof_out[0]:g} s", prof_out[1])
    print("  live phases: warm-up {:.2f} s; drain p50 {:.1f} ms / {} msgs ({:.1f} us/msg); analyse ".format(
        warm_s, res["drain_per_update"]["p50"] * 1e3, res["drain_per_update"]["messages"], res["drain_us_per_msg"])
        + " ".join(f"[{k}: p50 {v['p50']:.3f}, p90 {v['p90']:.3f}, max {v['max']:.3f} s over {v['updates']}]"
                   for k, v in ((k, res.get(k)) for k in ("fill_stats", "steady_stats")) if v) + "; "
        + ", ".join(f"t={a['t']:g}s {a['s']:.3f} s" for a in res["analyse"])
        + ("; steady " + ", ".join(f"{a['s']:.3f}" for a in res["steady"]) if res["steady"] else ""), flush=True)
    return res


# -- report ---------------------------------------------------------------------------------------------
def fmt_s(s: dict, digits: int = 2) -> str:
    return (f"{s['best']:.{digits}f} / {s['median']:.{digits}f} [{s['best']:.{digits}f}–{s['worst']:.{digits}f}] "
            f"×{s['runs']}")


def pf(ok: bool) -> str:
    return "**PASS**" if ok else "**FAIL**"


def table(res: dict) -> str:
    rows = ["| # | measure | figure (time: best / median [min–max] ×runs) | load 1-min (start → end) | target | result |",
            "|---|---|---|---|---|---|"]
    o = res.get("offline")
    if o:
        la = o.get("load_after", {})

        def ld_of(before: str, after: str) -> str:
            return f"{before.split()[0]} → {la[after].split()[0]}" if after in la else ""
        ld = ld_of(o["load_start"], "cli_json") or f"{o['load_start'].split()[0]} → {o['load_end'].split()[0]}"
        n = o["samples"]
        rows.append(f"| 1 | `noiselab analyze FILE --model M --json`, {n:,} samples, 4 views (variance, acf, psd, "
                    f"allan), subprocess wall | {fmt_s(o['cli_json'])} s | {ld} | "
                    f"< {TARGET_OFFLINE_S:.0f} s | {pf(o['cli_json']['best'] < TARGET_OFFLINE_S)} "
                    f"(median {'pass' if o['cli_json']['median'] < TARGET_OFFLINE_S else 'fail'}) |")
        if "cli_rrd" in o:
            rows.append(f"| 1 | `noiselab analyze FILE --model M --json --rrd OUT` (reads truth too, writes "
                        f".rrd {o['rrd_bytes'] / MIB:.0f} MiB + PNG) | {fmt_s(o['cli_rrd'])} s | "
                    f"{ld_of(la.get('cli_json', o['load_start']), 'cli_rrd')} | | info |")
        sp = o["split"]
        ld_split = ld_of(la.get("cli_rrd", la.get("cli_json", o["load_start"])), "split")
        rows.append(f"| 1 | ↳ interpreter start-up + imports (`python -c 'import noiselab.cli, ...'`) | "
                    f"{fmt_s(o['startup_imports'])} s | {ld_split} | | |")
        rows.append(f"| 1 | ↳ `load_noiselab(FILE, truth=False)` (measurement + command, as `--json`) | "
                    f"{fmt_s(sp['load'])} s | | | |")
        rows.append(f"| 1 | ↳ `compare()` cold (prediction caches cleared, as a fresh CLI) | "
                    f"{fmt_s(sp['compare_cold'])} s | | | |")
        rows.append(f"| 1 | ↳ `compare()` warm (caches hit) | {fmt_s(sp['compare_warm'])} s | | | info |")
        rows.append(f"| 1 | ↳ `load_noiselab(FILE, truth=True)` (three topics, as `--rrd`) | "
                    f"{fmt_s(sp['load_truth'])} s | | | |")
        if "rrd" in sp:
            rows.append(f"| 1 | ↳ `log_comparisons` (.rrd) / `write_summary_png` | {fmt_s(sp['rrd'])} s / "
                        f"{fmt_s(sp['png'])} s | | | |")
        rows.append(f"| 1 | peer: `mcap` `make_reader(f).iter_messages()` + `json.loads`, all 3 topics "
                    f"({o['peer_all_messages']:,} messages) | {fmt_s(o['peer_all'], 1)} s | "
                    f"{ld_of(la.get('split', o['load_start']), 'peer')} | | |")
        rows.append(f"| 1 | peer: the same, `topics=[measurement, command]` ({o['peer_two_messages']:,} messages) | "
                    f"{fmt_s(o['peer_two'], 1)} s | | | |")
        rows.append(f"| 1 | **ratio peer / `load_noiselab`** (best) | 3 topics (truth=True) **{o['ratio_read_all']:.1f}×**, "
                    f"2 topics (truth=False) **{o['ratio_read_two']:.1f}×** | | | info |")
    a = res.get("allan")
    if a:
        ld = f"{a['load_start'].split()[0]} → {a['load_end'].split()[0]}"
        rows.append(f"| 2 | `oadev` {a['n']:.0e} samples, {a['taus']} octave taus, best of {a['repeat']} "
                    f"(`bench_allan.py`) | noiselab {a['noiselab']:.3f} s (with noise ID, EDF, bounds), allantools "
                    f"{a['allantools']:.3f} s; **{a['ratio']:.2f}×**, max rel. difference {a['rel']:.1e} | {ld} | "
                    f"≥ 1× (as fast) | {pf(a['ratio'] >= 1.0)} |")
    for key in ("live", "live_replay", "live_emulate", "live_long", "live_profiled"):
        lv = res.get(key)
        if not lv:
            continue
        ld = f"{lv['load_start'].split()[0]} → {lv['load_end'].split()[0]}"
        s = lv["analyzer_summary"]
        iv = lv.get("interval", {})
        tag = {"live_long": " (long run)", "live_profiled": " (analyzer under cProfile: slower)"}.get(key, "")
        rows.append(f"| 3 | live analyzer{tag}, {lv['source']} at Ts = 1 ms for {lv['duration']:g} s "
                    f"(stream {lv['stream_wall']:.1f} s wall): updates while streaming / expected | "
                    f"{lv['updates_during']} / {lv['updates_expected']:.0f} ({lv['updates_ratio'] * 100:.0f} %), "
                    f"{lv['rate_hz']:.2f} Hz; interval p50 {iv.get('p50', 0):.3f} s, p90 {iv.get('p90', 0):.3f} s, "
                    f"max {iv.get('max', 0):.3f} s; staleness p50 {lv['staleness']['p50']:.2f} s, max "
                    f"{lv['staleness']['max']:.2f} s | {ld} | ≥ {TARGET_UPDATE_HZ:g} Hz (≥ "
                    f"{UPDATES_FRACTION * 100:.0f} % of expected) | {pf(lv['ok_updates'])} |")
        rows.append(f"| 3 | ↳ analyzer `--json` summary | updates {s['updates']} (incl. the final one after SIGINT), "
                    f"late (skipped) ticks {s.get('late_ticks', 'n/a')}, "
                    f"received {s['received']:,} of {int(2 * lv['duration'] / 0.001):,}, malformed {s['malformed']}, "
                    f"last window {s['samples']} samples, model error {s['error']:.3g} | | | info |")
        rows.append(f"| 3 | ↳ analyzer CPU (user+sys / wall over the stream) | **{lv['cpu'] * 100:.0f} %** of one core"
                    + (f" (source process: {lv['src_cpu'] * 100:.0f} %)" if "src_cpu" in lv else "") + " | | | info |")
        rss = ", ".join(f"{k} s: {v / MIB:.0f}" for k, v in lv["rss_at"].items())
        rows.append(f"| 3 | ↳ analyzer RSS (MiB) at stream time | start {lv['rss_start'] / MIB:.0f}, {rss}, end "
                    f"{lv['rss_end'] / MIB:.0f}; peak VmHWM {lv['vmhwm'] / MIB:.0f} | | | |")
        if lv.get("ok_memory") is None:
            rows.append(f"| 3 | ↳ RSS end / RSS at {lv['rss_half_s']:g} s − 1 (window still filling: the ring is full at "
                        f"{lv.get('fill_s', 124):.0f} s) | {lv['rss_growth'] * 100:+.1f} % | | | info |")
        else:
            rows.append(f"| 3 | ↳ memory bounded: RSS end / RSS at {lv['rss_half_s']:g} s (ring full at "
                        f"{lv['fill_s']:.0f} s, + 30 s) − 1 | {lv['rss_growth'] * 100:+.1f} % | | "
                        f"≤ {RSS_GROWTH_MAX * 100:.0f} % | {pf(lv['ok_memory'])} |")
        sp = (lv.get("profile") or {}).get("split")
        if sp:
            rows.append("| 3 | ↳ analyzer main thread (cProfile cumtime, s) | " + ", ".join(
                f"{k} {v:.1f}" for k, v in sorted(sp.items(), key=lambda kv: -kv[1])) + " | | | info |")
    ph = res.get("phases")
    if ph:
        an = ", ".join(f"{a['t']:g} s (n={a['n']:,}): {a['s']:.3f}" for a in ph["analyse"])
        rows.append(f"| 3 | ↳ in-process `LiveAnalyzer` (no Zenoh): `drain()` of {ph['drain_per_update']['messages']} "
                    f"messages (0.5 s) | p50 {ph['drain_per_update']['p50'] * 1e3:.1f} ms, max "
                    f"{ph['drain_per_update']['max'] * 1e3:.1f} ms ({ph['drain_us_per_msg']:.1f} µs/message) | | | info |")
        rows.append(f"| 3 | ↳ in-process `LiveAnalyzer.warm()` at start-up (predictions for the full window, before "
                    f"'live on') | {ph['warm_s']:.2f} s | | | info |")
        rows.append(f"| 3 | ↳ in-process `analyse()` (s) at stream time | {an} | | | info |")
        for key, label in (("fill_stats", "while the window fills"), ("steady_stats", "ring full")):
            v = ph.get(key)
            if v:
                rows.append(f"| 3 | ↳ in-process `analyse()` at every update, {label} | p50 {v['p50']:.3f} s, p90 "
                            f"{v['p90']:.3f} s, max {v['max']:.3f} s over {v['updates']} updates; over 0.25 s: "
                            f"{v['over_half_update']}, over 0.5 s: {v['over_update']} | | | info |")
        if ph["steady"]:
            st = ", ".join(f"{a['s']:.3f}" for a in ph["steady"])
            rows.append(f"| 3 | ↳ in-process `analyse()` at the steady state (ring full: {ph['cap_samples']:,} samples = "
                        f"{ph['cap_s']:.0f} s; {ph['steady'][0]['n']:,} analysed), consecutive updates (s) | {st} | | | info |")
    return "\n".join(rows)


def profile_md(rows: list[dict], title: str, n: int = 10) -> list[str]:
    out = [f"{title}:", "", "| function (file:line:name) | tottime s | cumtime s | calls |", "|---|---|---|---|"]
    for r in rows[:n]:
        out.append(f"| `{r['where']}` | {r['tottime']:.3f} | {r['cumtime']:.3f} | {r['calls']} |")
    return out + [""]


def markdown(res: dict, argv: list[str]) -> str:
    m = res["machine"]
    shown, skip = [], False
    for a in argv:                      # the command line without --json PATH
        if skip:
            skip = False
        elif a == "--json":
            skip = True
        elif a == "--workdir":          # a directory of this machine: a placeholder in RESULTS.md
            shown += [a, "WORKDIR"]
            skip = True
        elif a.startswith("--workdir="):
            shown.append("--workdir=WORKDIR")
        elif not a.startswith("--json="):
            shown.append(a)
    cmd = ".venv/bin/python tests/bench/bench_analysis.py " + " ".join(shown)
    lines = [
        BEGIN,
        f"Run: {res['date']} (local time). Wall clock {res['wall']:.0f} s.",
        "",
        f"Machine: nproc {m['nproc']}, CPU `{m['cpu']}`, {m['platform']}; Python {m['python']}, "
        f"numpy {m['numpy']}, scipy {m['scipy']}, BLAS {m['blas']}. Load average (1/5/15 min) at start "
        f"{res['load_start']}, at end {res['load_end']}; each part's 1-min load (start → end) is in the table "
        "(other processes were sharing the machine when it is near or above 1).",
        "",
        f"Code: git {res.get('code', 'unknown')}.",
        "",
        f"Model: `service/scenarios/seed.toml` with Ts = 1 ms, named `{NAME}`. Recordings by `noiselab simulate`.",
        "",
        table(res),
        "",
    ]
    for part, key, title in (("offline", "profile_json", "cProfile, offline `load_noiselab` + `compare` (cold), by tottime"),
                             ("offline", "profile_json_cum", "the same, by cumtime"),
                             ("phases", "profile", "cProfile, live `analyse()` at the end of the stream, by tottime"),
                             ("phases", "profile_cum", "the same, by cumtime"),
                             ("live_profiled", "top_tottime", "cProfile of the live analyzer process (main thread), by tottime"),
                             ("live_profiled", "top_cumtime", "the same, by cumtime")):
        got = res.get(part) or {}
        rows = got.get(key) or (got.get("profile") or {}).get(key)
        if rows:
            lines += profile_md(rows, title)
    lines += ["Reproduce (from the repository root):", "", "```", cmd.strip(), "```", END]
    return "\n".join(lines)


def write_results(block: str) -> None:
    text = RESULTS.read_text() if RESULTS.exists() else "# Benchmark results\n"   # re-read right before writing
    if BEGIN in text and END in text:
        a = text.index(BEGIN)
        b = text.index(END) + len(END)
        text = text[:a] + block + text[b:]
    elif SECTION in text:
        i = text.index(SECTION) + len(SECTION)
        text = text[:i] + "\n\n" + block + "\n" + text[i:]
    else:
        text = text.rstrip() + f"\n\n{SECTION}\n\n{block}\n"
    tmp = RESULTS.with_suffix(".md.tmp-analysis")
    tmp.write_text(text)
    os.replace(tmp, RESULTS)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small smoke sizes (1e5 samples, 10 s live); never writes")
    ap.add_argument("--only", nargs="+", choices=("offline", "allan", "live"), help="run only these parts")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each offline figure (default 3)")
    ap.add_argument("--peer-repeat", type=int, default=2, help="runs of the mcap-reader peer (~1 min each, default 2)")
    ap.add_argument("--rrd-repeat", type=int, default=1, help="runs of analyze --rrd (default 1)")
    ap.add_argument("--allan-repeat", type=int, default=3, help="bench_allan.py --repeat (default 3)")
    ap.add_argument("--live-duration", type=float, default=None, help="seconds of stream (default 60, quick 10)")
    ap.add_argument("--live-source", nargs="+", choices=("replay", "emulate"), default=["replay"],
                    help="stream source(s): replay of the simulate recording, or the emulator")
    ap.add_argument("--live-long", type=float, metavar="S",
                    help="also a replay of S seconds (> window + warm-up, e.g. 200) to see memory after the ring is full")
    ap.add_argument("--live-profile", action="store_true",
                    help="also a replay run with the analyzer process under cProfile (where its main thread spends time)")
    ap.add_argument("--no-phases", action="store_true", help="skip the in-process LiveAnalyzer diagnostic")
    ap.add_argument("--workdir", type=Path, help="keep model and recordings here and reuse them")
    ap.add_argument("--wait-quiet", type=float, metavar="L", help="before each part wait (<= 15 min) for 1-min load < L")
    ap.add_argument("--profile", action="store_true", help="cProfile the offline analysis and a live update")
    ap.add_argument("--write", action="store_true", help=f"update {RESULTS.relative_to(REPO)}")
    ap.add_argument("--json", type=Path, help="also dump the raw results as JSON here")
    args = ap.parse_args(argv)
    if args.quick and args.write:
        ap.error("--quick figures are smoke sizes: not written to RESULTS.md")

    parts = set(args.only or ("offline", "allan", "live"))
    q = args.quick
    n_off = 10**5 if q else 10**6
    live_d = args.live_duration or (10.0 if q else 60.0)
    tmp = None
    if args.workdir:
        workdir = args.workdir
        workdir.mkdir(parents=True, exist_ok=True)
    else:
        tmp = workdir = Path(tempfile.mkdtemp(prefix="bench_analysis-"))
    res: dict = {"date": _dt.datetime.now().strftime("%Y-%m-%d %H:%M"), "machine": machine(),
                 "load_start": loadavg(), "quick": q, "code": code_version()}
    mach = res["machine"]
    print(f"noiselab analysis bench{' (quick)' if q else ''}: {mach['cpu']}, nproc {mach['nproc']}, Python "
          f"{mach['python']}, numpy {mach['numpy']}; load {res['load_start']}; work dir {workdir}", flush=True)
    t_all = time.perf_counter()
    try:
        model = write_model(workdir)
        if "offline" in parts:
            rec, gen = make_recording(model, n_off * 0.001, workdir)
            if gen is not None:
                print(f"  simulate {n_off:.0e} samples: {gen:.1f} s -> {rec} ({rec.stat().st_size / MIB:.0f} MiB)",
                      flush=True)
            res["offline"] = bench_offline(model, rec, 2 if q else args.repeat, 1 if q else args.peer_repeat,
                                           args.rrd_repeat, workdir, args.wait_quiet, args.profile)
            res["offline"]["n_total"] = n_off
        if "allan" in parts:
            res["allan"] = bench_allan_run(10**6 if q else 10**7, 1 if q else args.allan_repeat, args.wait_quiet)
        if "live" in parts:
            rec, _ = make_recording(model, live_d, workdir)
            fill = fill_seconds(model, 60.0)
            for src in args.live_source:
                key = "live" if src == args.live_source[0] else f"live_{src}"
                res[key] = bench_live(model, rec, live_d, 60.0, 0.5, src, args.wait_quiet, fill_s=fill)
            if args.live_long:
                lrec, _ = make_recording(model, args.live_long, workdir)
                res["live_long"] = bench_live(model, lrec, args.live_long, 60.0, 0.5, "replay", args.wait_quiet,
                                              fill_s=fill)
            if args.live_profile:
                pfile = workdir / "analyzer.prof"
                res["live_profiled"] = bench_live(model, rec, live_d, 60.0, 0.5, "replay", args.wait_quiet,
                                                  profile_to=pfile, fill_s=fill)
                res["live_profiled"]["profile"] = live_profile_split(pfile)
            if not args.no_phases:
                steady = 0 if q else 6
                prec = rec
                if steady:
                    prec, _ = make_recording(model, 130.0, workdir)
                at = [t for t in (1, 10, 20, 30, 40, 50, 60) if t <= live_d]
                res["phases"] = live_phases(model, prec, 0.5, 60.0, at, steady, args.profile)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    res["wall"] = time.perf_counter() - t_all
    res["load_end"] = loadavg()
    print()
    print(table(res))
    print(f"\nload average at end: {res['load_end']}; wall {res['wall']:.0f} s")
    if args.profile:
        for part in ("offline", "phases"):
            txt = (res.get(part) or {}).get("profile_text")
            if txt:
                print(txt)
    if args.json:
        args.json.write_text(json.dumps(res, indent=1, default=float))
    if args.write:
        write_results(markdown(res, argv))
        print(f"updated {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
