"""Work run at the same time, one model: :mod:`concurrent.futures` executors behind :class:`Pool`.

:meth:`Pool.map` is ``[fn(x) for x in items]`` with ``workers`` at once; :meth:`Pool.beside` runs
one call beside the maps; :meth:`Pool.submit` computes one call in another process while this one
goes on. Where the work runs is chosen here, by :data:`POOL` and :func:`can_fork`, never by the
callers:

processes
    A :class:`~concurrent.futures.ProcessPoolExecutor` with the ``fork`` start method: its workers
    are copies of this process, so the function, its closures, the data and the caches they read
    come along by the fork, not pickled (the executor's queue carries only a job's key, see
    :func:`_run_job`), and this process takes its share of the items too. The work is mostly
    Python, which threads cannot run at once (the GIL). Only where a fork is safe: on Linux, while
    this process runs a single thread, in Python and in its libraries (a fork copies the memory
    but only the calling thread: a lock another thread held, in Zenoh's runtime or a BLAS worker,
    would stay held in the child). The ``forkserver`` start method is safe beside threads, but its
    workers start from a fresh interpreter: the work's closures would not pickle, and the record
    and the caches would have to cross on every map.
threads
    A :class:`~concurrent.futures.ThreadPoolExecutor` everywhere else (the transforms and the array
    arithmetic release the GIL; the caches the threads share are :class:`noiselab.memo.Memo`).
serial
    ``POOL = "serial"``: no pool at all (tests; a caller that wants none).

What a worker process sends back (results, exceptions, what its work left in caches) is pickled by
the executor between this process and its own children only, never read from a file or a socket.
Whatever a child does not deliver (it raised, was killed, or a result would not pickle) is
computed here, so an error is raised here, by the item that causes it, and no result goes missing.
"""

from __future__ import annotations

import itertools
import os
import signal
import sys
import threading
import time
import traceback
from concurrent.futures import Future, ThreadPoolExecutor

POOL = "processes"        # "processes" (forked workers where safe, else threads), "threads" or "serial"
STATS = {"maps": 0, "child_items": 0, "recomputed": 0, "side": 0, "calls": 0}   # what the processes did (tests)
SETTLE_S = 1.0            # longest wait for the executor's joined threads to leave the kernel's count

_JOBS: dict[int, object] = {}     # what a forked worker runs, by key: set before the fork, read in the child
_KEYS = itertools.count()


def can_fork() -> bool:
    """Whether the work may go to forked processes now: :data:`POOL` allows it, Linux, and a single
    thread, in Python and in the libraries (a BLAS's workers, Zenoh's or Rerun's runtime:
    ``/proc/self/task``)."""
    return (POOL == "processes" and sys.platform.startswith("linux") and hasattr(os, "fork")
            and threading.active_count() == 1 and _os_threads() == 1)


def _os_threads() -> int:
    """The threads of this process as the kernel counts them (0 when it cannot be read: no fork)."""
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return 0


def _run_job(key: int):
    """In a worker process: the job registered under ``key`` before the fork. A module-level
    function, so that the executor pickles only its name and the key."""
    return _JOBS[key]()


def _die_with_parent(parent: int) -> None:
    """In a worker process, before its first job: killed when its parent ends (Linux's
    ``prctl(PR_SET_PDEATHSIG, SIGKILL)``, linux/prctl.h), so that the workers of a worker that was
    stopped (a cancelled :meth:`Pool.submit` that had begun a map of its own) do not go on computing
    and then wait for work forever. The parent is the single thread that forked (:func:`can_fork`)."""
    try:
        import ctypes
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)      # 1: PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:              # the parent ended before the signal was armed
        os._exit(1)


def now(fn) -> Future:
    """fn() computed now, as a finished future (its exception raised here, at once)."""
    f = Future()
    f.set_result(fn())
    return f


class Task:
    """fn() to be run once: as one more item of the next :meth:`Pool.map` that forks, in whichever
    process comes free for it, or here when its result is asked for first. Its value crosses from
    a child pickled, like the map's results; an exception it raises (caught where it ran) is
    raised by :meth:`result`."""

    def __init__(self, fn):
        self.fn = fn
        self.done = False
        self._out = None

    def run(self):
        """(True, value) or (False, exception): what crosses from a child."""
        try:
            return True, self.fn()
        except Exception as exc:
            return False, exc

    def settle(self, out) -> None:
        self._out, self.done, self.fn = out, True, None

    def cancel(self) -> None:
        """Not wanted after all (a submitted call's process is stopped: :meth:`Pool.submit`)."""

    def _get(self):
        if not self.done:
            self.settle(self.run())
        return self._out

    def result(self):
        ok, v = self._get()
        if not ok:
            raise v
        return v

    def exception(self):
        ok, v = self._get()
        return None if ok else v


class _Forked:
    """``n`` forked copies of this process (a fork-context ProcessPoolExecutor), each running
    ``job()`` once (:attr:`futures`); :meth:`close` shuts them down, :meth:`kill` stops them first.
    Raises OSError when no process is to be had (EAGAIN, ENOMEM)."""

    def __init__(self, job, n: int = 1):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor
        self._threads = _os_threads()
        key = next(_KEYS)
        _JOBS[key] = job
        before = set(multiprocessing.active_children())
        # with "fork" the executor starts its processes in the first submit(), before its own
        # threads: the children are copies of this single-threaded process
        self._ex = ProcessPoolExecutor(max_workers=n, mp_context=multiprocessing.get_context("fork"),
                                       initializer=_die_with_parent, initargs=(os.getpid(),))
        try:
            self.futures = [self._ex.submit(_run_job, key) for _ in range(n)]
        except BaseException:
            self._ex.shutdown(wait=True)
            raise
        finally:
            del _JOBS[key]                    # the children hold their copy
        self._procs = [p for p in multiprocessing.active_children() if p not in before]

    def outcome(self, future):
        """The job's value, or None when the child did not deliver it (raised, killed, not picklable)."""
        try:
            return future.result()
        except Exception:
            return None

    def kill(self) -> None:
        for p in self._procs:
            try:
                p.kill()
            except (OSError, ValueError, AttributeError):
                pass

    def close(self) -> None:
        """Shut the executor down (its children exit, its threads are joined) and wait, bounded,
        until the kernel no longer counts those threads (a joined thread's task may outlive
        join() by a moment), so that the next map may fork again."""
        self._ex.shutdown(wait=True)
        end = time.monotonic() + SETTLE_S
        while _os_threads() > self._threads and time.monotonic() < end:
            time.sleep(0.0005)


class Pool:
    """The one way work is run at the same time (see the module docstring). A pool holds the calls
    waiting to ride along with its next map (:meth:`beside`) and, where it cannot fork, the thread
    that runs them; :meth:`close` (or ``with``) ends that thread."""

    def __init__(self):
        self._side: list[Task] = []
        self._thread: ThreadPoolExecutor | None = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        if self._thread is not None:
            self._thread.shutdown(wait=True)
            self._thread = None

    def map(self, fn, items: list, *, workers: int = 2, order: list | None = None, portable=None,
            carry=None, processes: bool = True, threads: bool = True) -> list:
        """``[fn(x) for x in items]`` with ``workers`` at once, results in order. ``order``: the
        order the items are taken in (default as given; the costliest first balances best).
        ``processes``: forked workers where that is safe (:func:`can_fork`); ``threads``: else
        threads (False: the work holds the GIL, threads would gain nothing: serially). The calls
        of :meth:`beside` ride along as the map's first items when it forks. ``portable``: applied
        to each of a child's results before it is pickled (e.g. to drop a closure). ``carry``:
        (mark, take, give), what a child's work left in caches brought back here: mark() here
        before the fork returns a token, the child sends take(token) (picklable: e.g. the cache
        entries it added) beside its results, and give(payload) merges it here (a later map's
        work then finds what this one's child computed)."""
        side, self._side = [s for s in self._side if not s.done], []
        order = list(range(len(items))) if order is None else list(order)
        if workers > 1 and len(items) + len(side) >= 2 and processes and can_fork():
            return _process_map(fn, items, order, workers, portable, side, carry)
        self._side = side
        if workers <= 1 or len(items) < 2 or not threads or POOL == "serial":
            return [fn(x) for x in items]
        out = [None] * len(items)
        with ThreadPoolExecutor(max_workers=workers) as ex:
            futures = {i: ex.submit(fn, items[i]) for i in order}
            for i, f in futures.items():
                out[i] = f.result()
        return out

    def beside(self, fn, workers: int = 2):
        """fn() beside the maps: as one more item of the next map that forks (a process comes free
        for it there, where a process of its own would be a third on two cores), or when its
        result is asked for, whichever comes first; in a thread of this pool where it cannot
        fork; now with one worker or no pool. Returns what has .result() and .exception()."""
        if workers <= 1 or POOL == "serial":
            return now(fn)
        if can_fork():
            task = Task(fn)
            self._side.append(task)
            return task
        if self._thread is None:
            self._thread = ThreadPoolExecutor(max_workers=1)
        return self._thread.submit(fn)

    def submit(self, fn) -> Task:
        """fn() computed in a forked process while this one goes on (e.g. reading a recording
        while this one imports the analysis): a :class:`Task` whose result() waits for the
        child's value and whose cancel() stops the child. Whatever the child does not deliver is
        computed here by fn when the result is asked for, so an error is raised here, by fn, in
        the caller's order. Where it cannot fork (:func:`can_fork`): fn runs when asked."""
        if not can_fork():
            return Task(fn)
        try:
            forked = _Forked(fn)
        except OSError:
            return Task(fn)
        task = Task(None)

        def cancel():
            """The child's work is not wanted (the caller failed first, or was interrupted)."""
            if not task.done:
                forked.kill()
                forked.close()
                task.settle((False, RuntimeError("cancelled")))

        def collect():
            try:
                got = forked.futures[0].exception() is None
            except BaseException:            # interrupted while waiting: the child is not waited for
                forked.kill()
                forked.close()
                raise
            value = forked.outcome(forked.futures[0]) if got else None
            forked.close()
            STATS["calls"] += 1
            if got:
                return value
            STATS["recomputed"] += 1
            return fn()

        task.fn, task.cancel = collect, cancel
        return task


def _process_map(fn, items: list, order: list, workers: int, portable, side: list, carry) -> list:
    """:meth:`Pool.map` in this process and ``workers - 1`` forked ones; ``side``: :class:`Task`
    objects run first, as extra items (each settled here when the map returns)."""
    if side:
        k = len(side)
        here = os.getpid()

        def one(it):
            if not it[0]:
                return fn(it[1])
            out = it[1].run()
            if not out[0] and os.getpid() != here:
                # a pickled exception loses its traceback: where it was raised goes along as a note
                out[1].add_note("raised in the forked child, at:\n" + "".join(traceback.format_tb(out[1].__traceback__)))
            return out

        got = _process_map(one, [(True, s) for s in side] + [(False, x) for x in items],
                           list(range(k)) + [k + i for i in order], workers, portable, [], carry)
        for s, r in zip(side, got[:k]):
            s.settle(r)
        STATS["side"] += k
        return got[k:]
    import multiprocessing
    n = len(items)
    nxt = multiprocessing.get_context("fork").Value("q", 0)     # the next place in ``order``, shared

    def take():
        with nxt.get_lock():
            k = nxt.value
            nxt.value = k + 1
        return order[k] if k < n else None

    mark = carry[0]() if carry is not None else None

    def drain():
        """In a child: items taken until none is left, then what its work left in the caches."""
        done = {}
        while (i := take()) is not None:
            v = fn(items[i])
            done[i] = portable(v) if portable is not None else v
        return done, (carry[1](mark) if carry is not None else None)

    try:
        forked = _Forked(drain, workers - 1)
    except OSError:                           # no process to be had: this one does it all
        return [fn(x) for x in items]
    out: dict = {}
    try:
        while (i := take()) is not None:
            out[i] = fn(items[i])
        delivered = [forked.outcome(f) for f in forked.futures]
    except BaseException:                     # an error here: the children's work is not wanted
        forked.kill()
        raise
    finally:
        forked.close()
    STATS["maps"] += 1
    for got in delivered:
        if got is None:
            continue
        child, brought = got
        if brought is not None:
            carry[2](brought)
        for i, v in child.items():
            if i not in out:
                out[i] = v
                STATS["child_items"] += 1
    for i in range(n):
        if i not in out:
            STATS["recomputed"] += 1
            out[i] = fn(items[i])
    return [out[i] for i in range(n)]
