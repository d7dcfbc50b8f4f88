"""A second process for work that is mostly Python: a forked copy of this process takes half of a
list of items (:func:`fork_map`, with :class:`Task` objects riding along as extra items), or
computes one call while this process goes on (:func:`fork_call`), so two cores run what two
threads could not (the GIL).

Only where that is safe (:func:`can_fork`): on Linux, and while this process runs a single thread,
in Python and in its libraries (a fork copies the memory but only the calling thread: a lock another
thread held would stay held in the child). The command line qualifies: it runs one BLAS thread.
Elsewhere the callers use threads or run serially.

The child's results come back pickled through a pipe: between this process and its own fork only,
never from a file. Whatever the child does not deliver (it failed, was killed, or a result would
not pickle) is computed in the parent, so an error is raised in the parent, by the item that
causes it, and a result never goes missing.
"""

from __future__ import annotations

import os
import pickle
import signal
import sys
import threading
import traceback

ENABLED = True            # False: never fork (the callers' threads or serial paths run)
FORKS = {"maps": 0, "child_items": 0, "recomputed": 0, "bytes": 0, "side": 0, "calls": 0}   # what the forks did (tests)


def can_fork() -> bool:
    """Whether :func:`fork_map` may be used now: :data:`ENABLED`, Linux, and a single thread, in
    Python and in the libraries (a BLAS's workers, Zenoh's or Rerun's runtime: ``/proc/self/task``)."""
    return (ENABLED and sys.platform.startswith("linux") and hasattr(os, "fork")
            and threading.active_count() == 1 and _os_threads() == 1)


def _os_threads() -> int:
    """The threads of this process as the kernel counts them (0 when it cannot be read: no fork)."""
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return 0


def _flush_stdio() -> None:
    for stream in (sys.stdout, sys.stderr):     # nothing buffered is written twice
        try:
            stream.flush()
        except (AttributeError, ValueError, OSError):
            pass


def _child(r: int, w: int, compute) -> None:
    """In a forked child: compute(), pickled into the pipe's write end ``w``, then exit (0 when
    delivered, 1 on any error: the parent computes what is missing). Never returns."""
    code = 1
    try:
        os.close(r)
        blob = pickle.dumps(compute(), protocol=pickle.HIGHEST_PROTOCOL)
        with os.fdopen(w, "wb") as f:
            f.write(blob)
        code = 0
    except BaseException:
        pass
    finally:
        os._exit(code)


class Task:
    """fn() to be run once: as an extra item of a :func:`fork_map` it is handed to (``side``), in
    whichever process comes free for it, or in this process when its result is asked for first.
    Its value crosses from the child pickled, like the map's results; an exception it raises
    (caught where it ran) is raised by :meth:`result`."""

    def __init__(self, fn):
        self.fn = fn
        self.done = False
        self._out = None

    def run(self):
        """(True, value) or (False, exception): what crosses from the child."""
        try:
            return True, self.fn()
        except Exception as exc:
            return False, exc

    def settle(self, out) -> None:
        self._out, self.done, self.fn = out, True, None

    def cancel(self) -> None:
        """Not wanted after all (a forked call's child is stopped: :func:`fork_call`)."""

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


def fork_call(fn) -> Task:
    """fn() computed in a forked child while this process goes on (e.g. reading a recording while
    this one imports the analysis): a :class:`Task` whose result() waits for the child's value.
    Whatever the child does not deliver (fn raised there, the child was killed, the value would not
    pickle) is computed here by fn when the result is asked for, so an error is raised here, by fn,
    in the caller's order. Without :func:`can_fork`, or no process to be had: fn runs when asked."""
    if not can_fork():
        return Task(fn)
    _flush_stdio()
    r, w = os.pipe()
    try:
        pid = os.fork()
    except OSError:
        os.close(r)
        os.close(w)
        return Task(fn)
    if pid == 0:
        _child(r, w, fn)
    os.close(w)
    task = Task(None)
    open_ = {"fd": r, "pid": pid}                 # what is still to close and to reap

    def reap(kill: bool):
        """Close the pipe and reap the child (killed first when its work is not wanted), once."""
        status = None
        if open_["fd"] is not None:
            fd, open_["fd"] = open_["fd"], None
            os.close(fd)
        if open_["pid"] is not None:
            child, open_["pid"] = open_["pid"], None
            if kill:
                try:
                    os.kill(child, signal.SIGKILL)
                except OSError:
                    pass
            status = os.waitpid(child, 0)[1]
        return status

    def cancel():
        """The child's work is not wanted (the caller failed first, or was interrupted): stop it."""
        if not task.done:
            reap(kill=True)
            task.settle((False, RuntimeError("cancelled")))

    def collect():
        blob, read = b"", False
        try:
            f = os.fdopen(open_["fd"], "rb")
            open_["fd"] = None                    # the file owns it now
            with f:
                blob = f.read()
            read = True
        finally:
            status = reap(kill=not read)          # interrupted: the child is not waited for
        FORKS["calls"] += 1
        if blob and os.waitstatus_to_exitcode(status) == 0:
            try:
                return pickle.loads(blob)
            except Exception:
                pass
        FORKS["recomputed"] += 1
        return fn()

    task.fn, task.cancel = collect, cancel
    return task


def fork_map(fn, items: list, order: list | None = None, portable=None, side=(), carry=None) -> list:
    """``[fn(x) for x in items]``, in this process and one forked child. Both take the next item of
    ``order`` (default: as given; the costliest first balances best) from a pipe that holds the
    items' indices, 4 bytes each (a pipe read of 4 bytes is atomic). ``portable``: applied to
    each of the child's results before it is pickled (e.g. to drop a closure). ``side``:
    :class:`Task` objects run first, as extra items (each settled here when the map returns).
    ``carry``: (mark, take, give), what the child's work left in caches brought back to this
    process: mark() here before the fork returns a token, the child sends take(token) (picklable:
    e.g. the cache entries it added) beside its results, and give(payload) merges it here (a later
    map's fits then find what this one's child computed). The caller checks :func:`can_fork`
    first."""
    side = [s for s in side if not s.done]
    if side:
        k = len(side)
        order = list(range(len(items))) if order is None else list(order)
        here = os.getpid()

        def one(it):
            if not it[0]:
                return fn(it[1])
            out = it[1].run()
            if not out[0] and os.getpid() != here:
                # a pickled exception loses its traceback: where it was raised goes along as a note
                out[1].add_note("raised in the forked child, at:\n" + "".join(traceback.format_tb(out[1].__traceback__)))
            return out

        got = fork_map(one, [(True, s) for s in side] + [(False, x) for x in items],
                       list(range(k)) + [k + i for i in order], portable, carry=carry)
        for s, r in zip(side, got[:k]):
            s.settle(r)
        FORKS["side"] += k
        return got[k:]
    n = len(items)
    order = list(range(n)) if order is None else list(order)
    tokens = b"".join(i.to_bytes(4, "little") for i in order)
    if len(tokens) > 16384:                       # far below a pipe's buffer: written before the fork
        return [fn(x) for x in items]
    q_r, q_w = os.pipe()
    os.write(q_w, tokens)
    os.close(q_w)

    def take():
        b = os.read(q_r, 4)
        return int.from_bytes(b, "little") if len(b) == 4 else None

    mark = carry[0]() if carry is not None else None
    _flush_stdio()
    r, w = os.pipe()
    try:
        pid = os.fork()
    except OSError:                               # no process to be had (EAGAIN, ENOMEM): one does it all
        for fd in (q_r, r, w):
            os.close(fd)
        return [fn(x) for x in items]
    if pid == 0:
        def mine():
            done = {}
            while (i := take()) is not None:
                v = fn(items[i])
                done[i] = portable(v) if portable is not None else v
            return done, (carry[1](mark) if carry is not None else None)
        _child(r, w, mine)
    os.close(w)
    out: dict = {}
    blob = b""
    try:
        while (i := take()) is not None:
            out[i] = fn(items[i])
        with os.fdopen(r, "rb") as f:
            r = None
            blob = f.read()
    finally:
        os.close(q_r)
        if r is not None:                         # an error here: the child's work is not wanted
            os.close(r)
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        os.waitpid(pid, 0)
    try:
        child, brought = pickle.loads(blob) if blob else ({}, None)
    except Exception:
        child, brought = {}, None
    if brought is not None:
        carry[2](brought)
    FORKS["maps"] += 1
    FORKS["bytes"] += len(blob)
    for i, v in child.items():
        if i not in out:
            out[i] = v
            FORKS["child_items"] += 1
    for i in range(n):
        if i not in out:
            FORKS["recomputed"] += 1
            out[i] = fn(items[i])
    return [out[i] for i in range(n)]
