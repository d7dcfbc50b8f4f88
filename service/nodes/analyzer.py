"""The live analysis node: subscribes to a device's measurement and command over Zenoh, keeps a
rolling window, and every ``update`` seconds compares it with the model (the same
:func:`noiselab.diagnose.compare.compare` as the offline analysis), publishes the summary on
``noiselab/<name>/analysis`` and prints it. On stop it writes the ``.rrd`` (the latest comparison
of every model revision plus the error over time) and prints its final report.

Timing: updates are paced by deadlines on the monotonic clock (tick k at t0 + k * update), not by
a pause after each update, so the period is ``update`` whatever an update costs as long as it
costs less; an update that overruns makes the loop skip the ticks it missed (counted as
``late_ticks``) instead of drifting. The predictions an update needs depend on the model and the
estimator sizes only and are cached per model revision (:mod:`noiselab.diagnose.compare`); at start
the analyzer computes them once for the full window, so the first full-window update is not slow.

Untrusted input: a measurement or command is analysed only if it holds to the wire contract
(:mod:`wire`'s decoders, with their size and nesting bounds), every element is within
:data:`wire.MAGNITUDE_MAX` (beyond it the statistics overflow), and it continues its stream as
the topic's :class:`seqgate.SeqGate` judges it (the recorder's rule): the model's vector length,
a seq past the stream's last by at most a ring's capacity. The stream's start, a jump further
ahead (a long loss) and any step back (a past seq, a duplicate, a restarted source) are taken
only once the message's successor confirms them; a confirmed step back is a restart, which
empties the ring (the new stream's samples are not mixed with the old one's). Anything else is
skipped and counted (``malformed``); the first of each reason is said on stderr.

Memory is bounded: ring buffers of ``window`` plus a warm-up, indexed by seq; a prediction cache
bounded in bytes; the error history thinned (every other entry) when it reaches
:data:`HISTORY_MAX` entries. The residual needs
the mean response, which depends on the command history: while the buffer still holds the
stream's start (seq 0, the emulator starts at rest) the mean is computed from rest exactly as
offline (so a replayed file gives the offline numbers); afterwards it is computed from zero over
a warm-up of 4 transient lengths before the window, where the forgotten initial state has
decayed below 1e-4 of its size, and the warm-up is not analysed.

Hot reload: when the model file changes, the next update loads it (a broken file is reported and
the previous model kept) and starts a new revision, so adding an effect shows the error falling.
"""

from __future__ import annotations

import queue
import sys
import threading
import time
from pathlib import Path

import numpy as np

from .. import wire
from ..diagnose.compare import AnalysisError, compare, transient_samples
from ..errors import BadInput
from ..model import ModelError, load_model
from ..outfiles import check_out, png_path, writing
from ..recordings.errors import shown
from ..signals import stop_on_signals
from . import seqgate, transport

READY_MARK = "noiselab analyze: live on"
HISTORY_MAX = 8192         # error-history entries kept (then thinned: ~2 h at 2 Hz before the first thinning)
WARM_MAX_SAMPLES = 400_000  # the start-up warm-up runs compare() on a synthetic window up to this size


class _Ring:
    """Samples by seq modulo capacity, for one vector topic; ``gate`` decides which seqs enter."""

    def __init__(self, capacity: int, dim: int, field: str):
        self.cap = capacity
        self.seq = np.full(capacity, -1, np.int64)
        self.t = np.zeros(capacity)
        self.v = np.zeros((capacity, dim))
        self.max_seq = -1
        self.gate = seqgate.SeqGate(ahead=capacity, dim=dim, field=field)

    def reset(self) -> None:
        """The stream restarted: forget the old one's samples."""
        self.seq[:] = -1
        self.max_seq = -1

    def put(self, seq: int, t: float, v) -> None:
        i = seq % self.cap
        self.seq[i], self.t[i], self.v[i] = seq, t, v
        if seq > self.max_seq:
            self.max_seq = seq

    def take(self, seqs: np.ndarray):
        i = seqs % self.cap
        ok = self.seq[i] == seqs
        return ok, self.t[i], self.v[i]


class LiveAnalyzer:
    def __init__(self, model_spec: str, *, device: str | None, window_s: float, log=sys.stderr):
        self.spec = model_spec
        self.path = Path(model_spec) if Path(model_spec).is_file() else None
        self.mtime = self.path.stat().st_mtime_ns if self.path else None
        self.model = load_model(model_spec)
        self.revision = 0
        self.device = device or self.model.name
        self.window = max(64, int(round(window_s / self.model.Ts)))
        self.warmup = 4 * transient_samples(self.model)
        cap = self.window + self.warmup
        self.meas = _Ring(cap, self.model.p, "y")
        self.cmd = _Ring(cap, self.model.m, "u")
        self.q: queue.SimpleQueue = queue.SimpleQueue()
        self.log = log
        self.latest: dict[int, object] = {}       # revision -> latest Comparison
        self.history: list[dict] = []
        self.received = 0
        self.bad = 0
        self.said: set[str] = set()               # reasons for skipping a message already said

    def warm(self) -> None:
        """Compute the predictions of a full-window update now (they are cached per model), so
        the update that first sees a full window is as fast as the next ones. Skipped for windows
        over :data:`WARM_MAX_SAMPLES` (the predictions are then computed by the first updates)."""
        n = self.meas.cap
        if n > WARM_MAX_SAMPLES:
            return
        # what analyse() passes at the steady state (ring full, stream start forgotten); the data
        # are synthetic: the predictions do not depend on them
        y = np.random.default_rng(0).standard_normal((n, self.model.p))
        try:
            compare(self.model, np.arange(n) * self.model.Ts, y, np.zeros((n, self.model.m)),
                    burn=min(self.warmup, n // 2))
        except AnalysisError:
            pass                                    # the first update says what is wrong

    def add_history(self, entry: dict) -> None:
        """Append to the error history; at HISTORY_MAX entries keep every other one (and the first
        of every revision), so a long run keeps its whole time span at a coarser step."""
        self.history.append(entry)
        if len(self.history) >= HISTORY_MAX:
            h = self.history
            self.history = [e for i, e in enumerate(h)
                            if i % 2 == 0 or i == len(h) - 1 or e["revision"] != h[i - 1]["revision"]]

    # Zenoh callback: only queue
    def on_sample(self, sample) -> None:
        key = str(sample.key_expr)
        if key.rsplit("/", 1)[-1] in ("measurement", "command"):
            self.q.put((key, sample.payload.to_bytes()))

    def skip(self, reason: str, text: str, n: int = 1) -> None:
        """Count ``n`` skipped messages; say the first of each ``reason``."""
        self.bad += n
        if reason not in self.said:
            self.said.add(reason)
            print(f"noiselab analyze: skipped a message (further ones counted in 'malformed'): {shown(text)}",
                  file=self.log, flush=True)

    def drain(self) -> None:
        while True:
            try:
                key, payload = self.q.get_nowait()
            except queue.Empty:
                return
            kind = key.rsplit("/", 1)[-1]
            ring = self.meas if kind == "measurement" else self.cmd
            try:
                obj = wire.decode(payload, kind, topic=key)
            except wire.WireError as exc:
                self.skip("contract", str(exc))
                continue
            vec = obj[wire.VECTOR_FIELD[kind]]
            if vec and max(map(abs, vec)) > wire.MAGNITUDE_MAX:
                self.skip("magnitude", f"{key}: seq {obj['seq']} has an element beyond {wire.MAGNITUDE_MAX:g}")
                continue
            take, dropped = ring.gate.offer(obj["seq"], len(vec), (obj["seq"], obj["t"], vec))
            self._dropped(key, dropped)
            if ring.gate.restarted:
                ring.reset()
            for seq, t, v in take:
                ring.put(seq, t, v)
                self.received += 1

    def _dropped(self, key: str, dropped: list) -> None:
        """Count what a gate dropped; say the first of each reason (the model's length, or seq)."""
        for d in dropped:
            self.skip(d.reason, f"{key}: {d.text}" + (" (the model's)" if d.reason == "length" else ""))

    def finish(self) -> None:
        """The stream is over: what the seq gates still hold had no successor (skipped)."""
        self.drain()
        for kind, ring in (("measurement", self.meas), ("command", self.cmd)):
            self._dropped(f"noiselab/{self.device}/{kind}", ring.gate.flush())

    def maybe_reload(self) -> None:
        if self.path is None:
            return
        try:
            mtime = self.path.stat().st_mtime_ns
        except OSError:
            return
        if mtime == self.mtime:
            return
        self.mtime = mtime
        try:
            new = load_model(str(self.path))
        except ModelError as exc:
            print(f"noiselab analyze: model file changed but is invalid, keeping revision {self.revision}: {exc}",
                  file=self.log, flush=True)
            return
        if (new.p, new.m, new.Ts) != (self.model.p, self.model.m, self.model.Ts):
            print("noiselab analyze: the reloaded model changes Ts or the number of inputs/outputs; "
                  f"keeping revision {self.revision}", file=self.log, flush=True)
            return
        self.model = new
        self.revision += 1
        print(f"noiselab analyze: reloaded {self.path} as revision {self.revision}", file=self.log, flush=True)

    def analyse(self):
        """Compare the buffered run ending at the newest complete sample (measurement and, when
        the stream has one, command); None if too little data."""
        top = self.meas.max_seq
        if top < 0:
            return None
        lo = max(0, top - self.meas.cap + 1)
        seqs = np.arange(lo, top + 1)
        ok, t, y = self.meas.take(seqs)
        have_cmd = self.cmd.max_seq >= 0
        if have_cmd:
            okc, _, u = self.cmd.take(seqs)
            ok &= okc
        else:
            u = None
        # the newest samples may still miss their other topic (measurement and command arrive on
        # separate subscriber threads): end at the newest complete sample, not before it
        done = np.flatnonzero(ok)
        if not done.size:
            return None
        end = int(done[-1]) + 1
        ok, seqs, t, y = ok[:end], seqs[:end], t[:end], y[:end]
        u = None if u is None else u[:end]
        top = int(seqs[-1])
        # the newest contiguous run of complete samples
        bad = np.flatnonzero(~ok)
        start = bad[-1] + 1 if bad.size else 0
        t, y = t[start:], y[start:]
        u = None if u is None else u[start:]
        first = int(seqs[start])
        n = t.size
        if n < 256:
            return None
        if first == 0:
            burn = None                                   # from rest, exactly as offline
        else:
            burn = min(self.warmup, n // 2)
        self.last_data = {"t": t, "y": y, "u": u, "at_rest": first == 0, "revision": self.revision,
                          "model": self.model}
        try:
            return compare(self.model, t, y, u, burn=burn, revision=self.revision, level=first == 0,
                           free_start=first != 0, notes=[] if not bad.size else [f"analysed seq {first}..{top} (incomplete samples before)"])
        except AnalysisError as exc:
            print(f"noiselab analyze: {exc}", file=self.log, flush=True)
            return None


def rank(data: dict) -> dict:
    """The diagnosis' ranking on a window (``noiselab diagnose`` with one step): the most likely
    missing effect with its fitted parameters, intervals and evidence, and the top candidates."""
    from ..diagnose.diagnose import diagnose
    from ..model import parse_model

    # a model object of its own: predictions are cached on the model, and the 2 Hz updates use
    # theirs concurrently on the other thread
    model = parse_model(data["model"].to_toml(), data["model"].source)
    with COMPUTE:       # the prediction caches are shared by model text: one computation at a time
        rep = diagnose(model, data["t"], data["y"], data["u"], at_rest=data["at_rest"], max_effects=1)
    return {"revision": data["revision"], "t": float(data["t"][-1]), "samples": int(data["t"].size),
            "missing": [{k: m[k] for k in ("effect", "mode", "params", "interval", "score", "accepted_by", "evidence")}
                        for m in rep["missing"]],
            "candidates": [{k: c[k] for k in ("effect", "mode", "score")} for c in rep["candidates"][:5]],
            "threshold": rep["threshold"], "seconds": rep["seconds"]}


COMPUTE = threading.Lock()


class _Ranker(threading.Thread):
    """Re-ranks the candidate missing effects on the latest window every ``every_s`` seconds (in
    the background: the 2 Hz updates go on), skipping a window already ranked."""

    def __init__(self, an: "LiveAnalyzer", every_s: float, stop: threading.Event, log):
        super().__init__(daemon=True, name="noiselab-ranker")
        self.an, self.every_s, self.stop, self.log = an, every_s, stop, log
        self.latest = None
        self.done_key = None

    def once(self):
        data = getattr(self.an, "last_data", None)
        if data is None:
            return
        key = (data["revision"], float(data["t"][-1]), int(data["t"].size))
        if key == self.done_key:
            return
        try:
            self.latest = _clean(rank(data))
        except Exception as exc:          # a ranking failure must not stop the analysis: say it
            print(f"noiselab analyze: ranking failed: {exc}", file=self.log, flush=True)
            return
        self.done_key = key

    def run(self):
        while not self.stop.wait(self.every_s):
            self.once()


def _clean(v):
    from ..diagnose.report import _clean as c
    return c(v)


def summary_of(cmp, analyzer: LiveAnalyzer, ranking: dict | None = None) -> dict:
    extra = {"ranking": ranking} if ranking is not None and ranking["revision"] == cmp.revision else {}
    return {**extra, "revision": cmp.revision, "model_source": cmp.model_source, "error": cmp.error,
            "error_per_view": cmp.error_per_view, "samples": int(cmp.t.size),
            "regions": [{"view": r.view, "output": r.output, "from": r.x_lo, "to": r.x_hi,
                         "max_abs_z": r.max_abs_z, "direction": r.direction}
                        for r in sorted(cmp.regions, key=lambda r: -r.max_abs_z)[:10]],
            "received": analyzer.received, "malformed": analyzer.bad}


def run_live(session, model_spec: str, *, device: str | None, window_s: float, update_s: float,
             duration: float | None, stop: threading.Event, rrd: str | None, quiet: bool = False,
             rank_s: float = 0.0, log=sys.stderr, png: str | None = None) -> dict:
    """``png``: the summary PNG written with the ``rrd`` (default: beside it)."""
    an = LiveAnalyzer(model_spec, device=device, window_s=window_s, log=log)
    an.warm()
    rank_stop = threading.Event()
    ranker = _Ranker(an, rank_s, rank_stop, log) if rank_s > 0 else None
    if ranker is not None:
        ranker.start()
    # one declaration for the device's streams: a publisher that waits for a subscriber (replay,
    # emulate) then sees measurement and command matched at once. Two declarations let a replay
    # that waits for any match start between them and lose the first commands (seq 0 incomplete:
    # the analysis no longer starts at rest). The other kinds (truth, our own analysis) are ignored.
    subs = [session.declare_subscriber(f"{wire.PREFIX}/{wire.check_name(an.device)}/*", an.on_sample)]
    pub = transport.declare_stream(session, wire.key(an.device, wire.ANALYSIS), wire.ANALYSIS)
    print(f"{READY_MARK} noiselab/{an.device}/measurement, window {window_s:g} s, "
          f"update every {update_s:g} s, model {an.model.source}", file=log, flush=True)
    t_start = time.monotonic()
    seq = 0
    last = None
    tick = 1                                   # the next update is due at t_start + tick * update_s
    late = 0
    try:
        while True:
            due = t_start + tick * update_s
            if duration is not None:
                due = min(due, t_start + duration)
            done = stop.wait(max(0.0, due - time.monotonic())) or \
                (duration is not None and time.monotonic() - t_start >= duration)
            an.drain()
            an.maybe_reload()
            with COMPUTE:
                cmp = an.analyse()
            if cmp is not None:
                last = cmp
                an.latest[cmp.revision] = cmp
                summ = summary_of(cmp, an, ranker.latest if ranker is not None else None)
                an.add_history({"t": float(cmp.t[-1]), "revision": cmp.revision, "error": cmp.error,
                                "error_per_view": dict(cmp.error_per_view)})
                pub.put(wire.encode_analysis(seq, float(cmp.t[-1]), summ))
                seq += 1
                if not quiet:
                    print(f"noiselab analyze: t = {cmp.t[-1]:.1f} s, revision {cmp.revision}, model error "
                          f"{cmp.error:.3g} (" + ", ".join(f"{k} {v:.3g}" for k, v in cmp.error_per_view.items())
                          + ")", file=log, flush=True)
            if done:
                break
            # next tick; ticks that passed during this update are skipped (and counted), not made up
            now_tick = int((time.monotonic() - t_start) // update_s)
            if now_tick > tick:
                late += now_tick - tick
                tick = now_tick
            tick += 1
    finally:
        for s in subs:
            s.undeclare()
        an.finish()
        if ranker is not None:
            rank_stop.set()
            ranker.join()
    if ranker is not None and last is not None:
        ranker.once()                    # the final window ranked too (a no-op if it already is)
    out = {"node": "analyze", "live": True, "updates": seq, "received": an.received, "malformed": an.bad,
           "revisions": an.revision + 1, "late_ticks": late}
    if last is not None:
        out.update(summary_of(last, an, ranker.latest if ranker is not None else None))
        out["notes"] = last.notes
        if rrd:
            from noiselab.viewers.rerun_log import log_comparisons
            from noiselab.viewers.summary_png import write_summary_png

            comps = [an.latest[r] for r in sorted(an.latest)]
            with writing(rrd):                  # a full disk: one line naming the file, as offline
                log_comparisons(comps, rrd, history=an.history)
            png = png or str(Path(rrd).with_suffix(".png"))
            with writing(png):
                write_summary_png(comps, png)
            out["rrd"], out["png"] = rrd, png
    return out


def cmd_analyze_live(args) -> int:
    import json

    if args.recording:
        raise BadInput("--live analyses a Zenoh stream: give no RECORDING")
    if args.rrd:                          # checked before the run, the PNG beside it too
        check_out(args.rrd, args.force)
        check_out(png_path(args), args.force)
    stop = stop_on_signals()
    with transport.open_session(args, "sink") as session:
        rep = run_live(session, args.model, device=args.device, window_s=args.window, update_s=args.update,
                       duration=args.duration, stop=stop, rrd=args.rrd, quiet=args.json,
                       rank_s=args.rank_every, png=png_path(args) if args.rrd else None)
    if args.json:
        print(json.dumps(rep), flush=True)
    else:
        err = rep.get("error")
        print(f"live analysis: {rep['updates']} updates, {rep['received']} messages, final model error "
              + ("n/a" if err is None else f"{err:.3g}") + (f"; wrote {rep['rrd']}" if rep.get("rrd") else ""))
    return 0
