"""The pool (``noiselab.parallel.Pool``: a fork-context ProcessPoolExecutor where a fork is safe,
else threads, or serially): the diagnosis' candidate maps give the report the threads and the
serial path give, the recording's topics are parsed to the same bits, whatever a child does not
deliver is computed in the parent, and an error is raised in the parent by the item that causes it.

Each check of the processes runs in a subprocess of its own: a fork is only safe from a process
that runs a single thread, which a pytest-xdist worker is not (``parallel.can_fork`` refuses there,
and the threads run).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _run(code: str, *args) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1")
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code), *map(str, args)], capture_output=True,
                       text=True, cwd=ROOT, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


_DIAGNOSE = """
    import json, sys
    sys.path.insert(0, "tests/bench")
    from hidden_set import make_case
    from noiselab import parallel
    from noiselab.diagnose import search
    from noiselab.diagnose.diagnose import diagnose
    from noiselab.model import parse_model
    parallel.POOL = "{pool}"
    case = make_case(27)                       # a walk and process noise, 115000 samples at 2 ms
    truth, nominal = parse_model(case.truth, "truth"), parse_model(case.nominal, "nominal")
    rec = truth.simulate(int(round(case.duration / truth.Ts)), seed=case.seed)
    assert len(rec.t) * truth.p >= search.PARALLEL_MIN
    rep = diagnose(nominal, rec.t, rec.y, rec.u)
    keep = {{k: v for k, v in rep.items() if k not in ("model", "before", "after", "seconds")}}
    print(json.dumps({{"report": keep, "forks": parallel.STATS}}, default=str))
"""


@pytest.mark.slow
def test_forked_candidate_maps_give_the_report_the_threads_and_the_serial_path_give():
    forked = _run(_DIAGNOSE.format(pool="processes"))
    threads = _run(_DIAGNOSE.format(pool="threads"))
    serial = _run(_DIAGNOSE.format(pool="serial"))
    f = forked["forks"]
    # the fork ran every map (screens, full fits, the backward pass, exchanges, intervals), and every
    # item the child took came back from it
    assert f["maps"] >= 8 and f["child_items"] >= 8 and f["recomputed"] == 0, f
    # the model comparisons (before, after each step) rode along with the maps, not run between them
    assert f["side"] >= 1 + len(forked["report"]["steps"]), f
    assert threads["forks"]["maps"] == 0 and serial["forks"]["maps"] == 0
    assert [m["effect"] for m in forked["report"]["missing"]], "the case has effects to find"
    # the same report, intervals and notes included, to rounding: a value the caches share (a
    # source's part, a mean response) may have been computed from another trial model that
    # shares it, in another order (so two runs on threads can differ in the last digit too)
    _same(forked["report"], threads["report"])
    _same(forked["report"], serial["report"])


def _same(a, b, path="report"):
    if isinstance(a, float) or isinstance(b, float):
        assert isinstance(a, (int, float)) and isinstance(b, (int, float)), path
        assert a == b or abs(a - b) <= 1e-9 * max(abs(a), abs(b)), (path, a, b)
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), (path, a, b)
        for k in a:
            _same(a[k], b[k], f"{path}/{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), (path, a, b)
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{path}[{i}]")
    else:
        assert a == b, (path, a, b)


_TOY = """
    import json, os, sys, threading
    from noiselab import parallel

    parent = os.getpid()
    sync_r = sync_w = back_r = back_w = None
    first = []

    def gate():
        # each process's first item waits until the other has taken one (pipes, no sleeping): the
        # child cannot take them all before the parent starts, nor the parent before the child
        if not first:
            first.append(1)
            if os.getpid() == parent:
                os.write(back_w, b"p")
                os.read(sync_r, 1)
            else:
                os.write(sync_w, b"c")
                os.read(back_r, 1)

    def square(x):
        gate()
        return x * x

    def child_fails(x):
        gate()
        if os.getpid() != parent:
            raise RuntimeError("child only")
        return x * x

    def child_unpicklable(x):
        gate()
        return lambda: x * x              # the child's will not pickle: the child delivers nothing

    stats = lambda before: {{k: parallel.STATS[k] - before[k] for k in parallel.STATS}}

    out = {{"threads": threading.active_count(), "can_fork": parallel.can_fork()}}
    # a second thread, Python's or a library's, and no fork
    stop = threading.Event()
    th = threading.Thread(target=stop.wait)
    th.start()
    out["with_a_thread"] = [parallel.can_fork(), len(os.listdir("/proc/self/task"))]
    stop.set()
    th.join()
    # a joined thread's kernel task may outlive join() by a moment: wait for it (yielding, bounded)
    for _ in range(1_000_000):
        if parallel.can_fork():
            break
        os.sched_yield()
    out["after_it"] = parallel.can_fork()
    items = list(range(12))
    order = items[::-1]
    for name, fn in (("square", square), ("child_fails", child_fails), ("child_unpicklable", child_unpicklable)):
        first.clear()
        sync_r, sync_w = os.pipe()          # fresh ones per map (a killed child's bytes stay in the old)
        back_r, back_w = os.pipe()
        before = dict(parallel.STATS)
        res = parallel.Pool().map(fn, items, order=order)
        for fd in (sync_r, sync_w, back_r, back_w):
            os.close(fd)
        res = [r() if callable(r) else r for r in res]
        out[name] = {{"ok": res == [x * x for x in items], "can_fork": parallel.can_fork(), **stats(before)}}

    # calls beside a pool's maps ride along with its next map: each run once, in whichever process
    # came free for it, its value or its exception settled when the map returns; one no map took
    # runs when asked for
    runs_r, runs_w = os.pipe()

    def side_value(v):
        os.write(runs_w, b"r")
        return v, os.getpid()

    def side_error():
        os.write(runs_w, b"r")
        gate()                        # one of the two in each process
        exc = ValueError("side task")
        exc.pid = os.getpid()
        raise exc

    pool = parallel.Pool()
    tasks = [pool.beside(side_error), pool.beside(side_error),
             pool.beside(lambda: side_value(1)), pool.beside(lambda: side_value(2))]
    done = pool.beside(lambda: side_value(0))
    done.result()                             # already done: the map does not run it again
    lone = parallel.Pool().beside(lambda: side_value(3))      # a pool that never maps
    first.clear()
    sync_r, sync_w = os.pipe()
    back_r, back_w = os.pipe()
    before = dict(parallel.STATS)
    res = pool.map(lambda x: x * x, items, order=order)
    for fd in (sync_r, sync_w, back_r, back_w):
        os.close(fd)
    settled = [t.done for t in tasks]
    os.set_blocking(runs_r, False)
    runs = len(os.read(runs_r, 100))
    vals = [tasks[2].result(), tasks[3].result()]
    errs = []
    for t in tasks[:2]:
        try:
            t.result()
            errs.append("no error")
        except ValueError as exc:
            errs.append(str(exc))
    # an exception from the child carries where it was raised as a note (its traceback does not
    # pickle); the one raised here keeps its traceback
    where = {{}}
    for t in tasks[:2]:
        exc = t.exception()
        notes = getattr(exc, "__notes__", [])
        if exc.pid != parent:
            where["child"] = any("in side_error" in n for n in notes)
        else:
            where["here"] = exc.__traceback__ is not None and not notes
    out["side"] = {{"ok": res == [x * x for x in items], "settled": settled, "runs": runs, "where": where,
                   "values": [v for v, _ in vals], "errors": errs, "exception": str(tasks[0].exception()),
                   "lone": list(lone.result()) == [3, parent], **stats(before)}}

    # what the child left in a cache comes back (``carry``): after the map this process holds every
    # item's entry, the child's included, whether the map has side tasks or not
    carried = {{}}
    for with_side in (False, True):
        cache = {{"old": os.getpid()}}

        def fill(x):
            gate()
            cache[x] = (x * x, os.getpid())
            return x

        carry = (lambda: set(cache), lambda mark: {{k: v for k, v in cache.items() if k not in mark}},
                 cache.update)
        first.clear()
        sync_r, sync_w = os.pipe()
        back_r, back_w = os.pipe()
        before = dict(parallel.STATS)
        pool = parallel.Pool()
        if with_side:
            pool.beside(lambda: 0)
        res = pool.map(fill, items, order=order, carry=carry)
        for fd in (sync_r, sync_w, back_r, back_w):
            os.close(fd)
        carried[str(with_side)] = {{"ok": res == items, "all": all(cache[x][0] == x * x for x in items),
                                   "from_child": sum(cache[x][1] != parent for x in items),
                                   "old_kept": cache["old"] == parent,
                                   "child_items": parallel.STATS["child_items"] - before["child_items"]}}
    out["carry"] = carried

    # a call computed in a forked child while this process goes on: its value comes back; what the
    # child does not deliver (it raised there) is computed here; a call not wanted is stopped
    before = dict(parallel.STATS)
    got = parallel.Pool().submit(lambda: (os.getpid(), list(range(100000)))).result()
    once = parallel.Pool().submit(lambda: os.getpid() if os.getpid() == parent else 1 / 0).result()
    hold_r, hold_w = os.pipe()
    stuck = parallel.Pool().submit(lambda: os.read(hold_r, 1))    # blocks until cancelled
    stuck.cancel()
    try:
        stuck.result()
        cancelled = "no error"
    except RuntimeError as exc:
        cancelled = str(exc)
    # a call cancelled while its child runs a map of its own (in the child and a grandchild): both
    # end (not only the child): every holder of ``dead_w``, an end this process then closes, is gone
    ready_r, ready_w = os.pipe()
    dead_r, dead_w = os.pipe()

    def blocked(x):
        os.write(ready_w, b"r")
        return os.read(hold_r, 1)                                  # blocks until killed

    nested = parallel.Pool().submit(lambda: parallel.Pool().map(blocked, [0, 1]))
    started = b""
    while len(started) < 2:                                        # the child's item and the grandchild's
        started += os.read(ready_r, 2 - len(started))
    nested.cancel()
    os.close(dead_w)
    nested_gone = os.read(dead_r, 1) == b""
    for fd in (ready_r, ready_w, dead_r):
        os.close(fd)
    # interrupted while it waits for the child (Ctrl-C): the child is killed and reaped at once, and
    # the caller's cancel() afterwards does nothing more
    slow = parallel.Pool().submit(lambda: os.read(hold_r, 1))

    def interrupt(*_):
        raise KeyboardInterrupt

    import signal
    signal.signal(signal.SIGALRM, interrupt)
    try:
        # the child never answers: result() is waiting when the alarm comes (on a busy machine it
        # may come before result() is called; it is still caught here, and cancel() stops the child)
        signal.setitimer(signal.ITIMER_REAL, 0.2)
        slow.result()
        interrupted = "no"
    except KeyboardInterrupt:
        interrupted = "yes"
    slow.cancel()
    os.close(hold_r)
    os.close(hold_w)
    parallel.POOL = "threads"
    here = parallel.Pool().submit(os.getpid).result()
    parallel.POOL = "processes"
    out["call"] = {{"child": got[0] != parent, "value": got[1] == list(range(100000)), "redone": once == parent,
                   "cancelled": cancelled, "disabled_here": here == parent, "interrupted": interrupted,
                   "nested_gone": nested_gone, "can_fork": parallel.can_fork(), **stats(before)}}

    def parent_fails(x):
        if os.getpid() == parent:
            os.write(sync_w, b"p")
            raise ValueError("parent item")
        os.read(sync_r, 1)        # the child's first item waits for the parent's: it cannot take them all
        return x

    sync_r, sync_w = os.pipe()
    try:
        parallel.Pool().map(parent_fails, items, order=order)
        out["parent_fails"] = "no error"
    except ValueError as exc:
        out["parent_fails"] = str(exc)
    os.close(sync_r)
    os.close(sync_w)
    try:
        os.waitpid(-1, os.WNOHANG)
        out["children_left"] = True
    except ChildProcessError:
        out["children_left"] = False

    def no_fork(process_obj):
        raise OSError(11, "Resource temporarily unavailable")    # what os.fork raises (EAGAIN)

    from multiprocessing import context
    fds = len(os.listdir("/proc/self/fd"))
    real, context.ForkProcess._Popen = context.ForkProcess._Popen, staticmethod(no_fork)
    before = dict(parallel.STATS)
    res = parallel.Pool().map(lambda x: x + 1, items, order=order)
    called = parallel.Pool().submit(os.getpid).result()
    context.ForkProcess._Popen = real
    out["no_fork"] = {{"ok": res == [x + 1 for x in items] and called == parent,
                      "maps": parallel.STATS["maps"] - before["maps"],
                      "fds_leaked": len(os.listdir("/proc/self/fd")) - fds, "can_fork": parallel.can_fork()}}
    print(json.dumps(out))
"""


def test_a_forked_map_computes_here_what_the_child_did_not_deliver():
    out = _run(_TOY.format())
    assert out["threads"] == 1 and out["can_fork"] is (sys.platform.startswith("linux"))
    assert out["with_a_thread"] == [False, 2] and out["after_it"] is True
    sq = out["square"]
    assert sq["ok"] and sq["maps"] == 1 and sq["child_items"] >= 1 and sq["recomputed"] == 0, sq
    assert sq["child_items"] + sq["recomputed"] < 12            # the parent took its share too
    # each map's executor is shut and its threads gone when the map returns: the next may fork too
    assert all(out[name]["can_fork"] for name in ("square", "child_fails", "child_unpicklable"))
    for name in ("child_fails", "child_unpicklable"):
        r = out[name]
        # the child took at least one item (the parent's first waited for it) and delivered none
        assert r["ok"] and r["child_items"] == 0 and r["recomputed"] >= 1, (name, r)
    sd = out["side"]
    # the side tasks ran once each (the done one not again), in the map: settled when it returned
    assert sd["ok"] and sd["settled"] == [True] * 4 and sd["runs"] == 5, sd
    assert sd["where"] == {"child": True, "here": True}, sd
    assert sd["values"] == [1, 2] and sd["errors"] == ["side task"] * 2 and sd["exception"] == "side task", sd
    assert sd["maps"] == 1 and sd["side"] == 4 and sd["recomputed"] == 0 and sd["lone"], sd
    assert out["call"] == {"child": True, "value": True, "redone": True, "cancelled": "cancelled",
                           "disabled_here": True, "interrupted": "yes", "nested_gone": True, "can_fork": True, "maps": 0,
                           "child_items": 0, "recomputed": 1, "side": 0, "calls": 2}, out["call"]
    for with_side, c in out["carry"].items():
        # every entry here after the map, the child's items' from the child (its work not redone)
        assert c["ok"] and c["all"] and c["old_kept"] and c["from_child"] >= 1, (with_side, c)
        assert c["from_child"] <= c["child_items"], c             # (the side task may be one of them)
    assert out["parent_fails"] == "parent item"               # raised here, by the item that causes it
    assert out["children_left"] is False                      # and the child was reaped
    # no process to be had (EAGAIN): this one computes everything, and closes the executor's pipes
    assert out["no_fork"] == {"ok": True, "maps": 0, "fds_leaked": 0, "can_fork": True}


_READ = """
    import json, sys
    import numpy as np
    sys.path.insert(0, "tests")
    from helpers.recordings import raw_file, write_sample
    from noiselab import parallel
    from noiselab import wire
    from noiselab.recordings import reader
    from noiselab.recordings.reader import read_recording

    reader.PARALLEL_DECODE = 1000              # the threshold, not the parser, is what is small here
    d = sys.argv[1]
    write_sample(d + "/a.mcap", n=3000, name="a")
    out = {}
    for on in (True, False):
        parallel.POOL = "processes" if on else "serial"
        before = dict(parallel.STATS)
        rec = read_recording(d + "/a.mcap")
        got = {}
        for name, dev in rec.devices.items():
            for kind, td in dev.streams.items():
                got[name + "/" + kind] = [td.seq.tolist(), td.t.view(np.uint64).tolist(),
                                          td.values.view(np.uint64).tolist(), td.publish_ns.tolist(),
                                          td.log_ns.tolist()]
        out[str(on)] = {"data": got, "forks": {k: parallel.STATS[k] - before[k] for k in parallel.STATS}}
    # a bad payload on the second of two topics: the same one-line error either way
    raw_file(d + "/bad.mcap", ["noiselab/b/measurement"], n=1500)
    raw_file(d + "/bad2.mcap", ["noiselab/b/command"], n=1500, payload=b'{"seq":0,"t":0.0,"u":[NaN]}')
    # both topics in one file: copy the messages of the two
    from mcap.writer import Writer
    from mcap.reader import make_reader
    with open(d + "/both.mcap", "wb") as f:
        w = Writer(f)
        w.start()
        for src in ("bad.mcap", "bad2.mcap"):
            with open(d + "/" + src, "rb") as g:
                for schema, channel, msg in make_reader(g).iter_messages():
                    sid = w.register_schema(schema.name, schema.encoding, schema.data)
                    cid = w.register_channel(channel.topic, channel.message_encoding, sid)
                    w.add_message(cid, log_time=msg.log_time, data=msg.data, publish_time=msg.publish_time,
                                  sequence=msg.sequence)
        w.finish()
    errors = {}
    for on in (True, False):
        parallel.POOL = "processes" if on else "serial"
        try:
            read_recording(d + "/both.mcap")
            errors[str(on)] = None
        except wire.WireError as exc:
            errors[str(on)] = str(exc)
    out["errors"] = errors
    print(json.dumps(out))
"""


def test_a_recordings_topics_parsed_in_two_processes_are_the_same_bits(tmp_path):
    out = _run(_READ, tmp_path)
    forked, serial = out["True"], out["False"]
    assert set(forked["data"]) == {"a/truth", "a/command", "a/measurement"}
    assert forked["data"] == serial["data"]                 # seq, t, values, both times: every bit
    assert forked["forks"]["maps"] == 1 and forked["forks"]["recomputed"] == 0, forked["forks"]
    assert serial["forks"]["maps"] == 0
    err = out["errors"]
    assert err["True"] == err["False"] and err["True"].startswith("noiselab/b/command: "), err


def test_no_fork_beside_a_librarys_own_threads():
    """OpenBLAS with two threads runs a worker the interpreter does not know of: the kernel does."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="2", OMP_NUM_THREADS="2")
    code = textwrap.dedent("""
        import json, os, threading
        import numpy as np
        from noiselab import parallel
        a = np.random.default_rng(0).standard_normal((400, 400))
        a @ a                                           # the BLAS starts its workers
        blas = str(np.__config__.CONFIG.get("Build Dependencies", {}).get("blas", {}).get("name", ""))
        print(json.dumps([threading.active_count(), len(os.listdir("/proc/self/task")), parallel.can_fork(), blas]))
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    py_threads, tasks, can, blas = json.loads(r.stdout.strip().splitlines()[-1])
    assert py_threads == 1
    if "openblas" in blas.lower():          # numpy's wheels: OpenBLAS, which starts its workers here
        assert tasks == 2, tasks
    assert can is (tasks == 1)              # a library's worker: no fork


_CLI = """
    import contextlib, io, json, sys
    from noiselab import cli, parallel

    d = sys.argv[1]
    assert cli.main(["simulate", "hidden/sensor.bias_walk", "--duration", "60", "--seed", "3",
                     "--out", d + "/walk.mcap"]) == 0
    with open(d + "/walk.mcap", "rb") as f:
        head = f.read(4096)
    with open(d + "/cut.mcap", "wb") as f:                   # read (unfinished), but no sample whole
        f.write(head)
    with open(d + "/bad.mcap", "wb") as f:                   # the reader rejects it
        f.write(b"not an mcap file")
    out = {}
    for on in (True, False):
        parallel.POOL = "processes" if on else "serial"
        runs = {}
        for name, cmd, args in (("walk", "diagnose", [d + "/walk.mcap", "--model", "hidden/sensor.bias_walk-nominal"]),
                                ("cut", "diagnose", [d + "/cut.mcap", "--model", "hidden/sensor.bias_walk-nominal"]),
                                ("bad", "diagnose", [d + "/bad.mcap", "--model", "hidden/sensor.bias_walk-nominal"]),
                                ("bad_model", "diagnose", [d + "/walk.mcap", "--model", "nope-model"]),
                                ("analyze", "analyze", [d + "/walk.mcap", "--model", "hidden/sensor.bias_walk-nominal"]),
                                ("analyze_bad", "analyze", [d + "/bad.mcap", "--model", "hidden/sensor.bias_walk-nominal"])):
            before = dict(parallel.STATS)
            so, se = io.StringIO(), io.StringIO()
            with contextlib.redirect_stdout(so), contextlib.redirect_stderr(se):
                code = cli.main([cmd, *args, "--json"])
            rep = json.loads(so.getvalue()) if code == 0 else None
            if rep is not None:
                rep.pop("seconds", None)
            runs[name] = {"code": code, "report": rep, "stderr": se.getvalue(),
                          "forks": {k: parallel.STATS[k] - before[k] for k in ("calls", "recomputed")}}
        out[str(on)] = runs
    print(json.dumps(out))
"""


def test_the_command_line_reads_the_recording_in_a_child_while_it_imports(tmp_path):
    """`noiselab diagnose` and `noiselab analyze` read a noiselab recording in a forked child while
    they import the analysis (:meth:`noiselab.parallel.Pool.submit`): the same report as read in this
    process; a file the reader rejects, or one it reads with no whole sample, gives the same
    one-line error (the child's failure redone here); a bad model is reported first, as before,
    and the child's reading stopped."""
    out = _run(_CLI, tmp_path)
    forked, here = out["True"], out["False"]
    assert forked["walk"]["code"] == 0 and forked["walk"]["forks"] == {"calls": 1, "recomputed": 0}, forked["walk"]
    assert here["walk"]["forks"] == {"calls": 0, "recomputed": 0}
    assert [m["effect"] for m in forked["walk"]["report"]["missing"]] == ["sensor.bias_walk"]
    _same(forked["walk"]["report"], here["walk"]["report"])
    ana = forked["analyze"]
    assert ana["code"] == 0 and ana["forks"] == {"calls": 1, "recomputed": 0}, ana
    _same(ana["report"], here["analyze"]["report"])
    assert ana["report"]["error"] > 2, ana["report"]["error"]          # the nominal misses the walk
    for name, redone in (("cut", 0), ("bad", 1), ("analyze_bad", 1)):
        got = forked[name]
        assert got["code"] == 2 and got["forks"] == {"calls": 1, "recomputed": redone}, (name, got)
        assert len(got["stderr"].strip().splitlines()) == 1 and got["stderr"] == here[name]["stderr"], (got, here[name])
    bad = forked["bad_model"]
    assert bad["code"] == 2 and "no such model" in bad["stderr"] and bad["stderr"] == here["bad_model"]["stderr"]
    assert bad["forks"] == {"calls": 0, "recomputed": 0}          # stopped, never collected
