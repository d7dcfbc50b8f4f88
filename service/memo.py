"""Computed results remembered between calls, shared by the threads of one process.

The diagnosis fits its candidates in threads wherever it cannot fork (:func:`noiselab.parallel.can_fork`:
the process already runs other threads, e.g. a test runner's workers or the live analyzer's
sessions), and a comparison computes its views in threads; the caches of what they compute
(expected periodogram parts, mean responses, matrix exponentials, tapers) are shared by those
threads. Single reads and writes of a dict are atomic, but a bounded cache must also find what to
evict: summing its entries' sizes iterates it (another thread's insertion meanwhile raises
"dictionary changed size during iteration"), and popping its oldest key can find that key already
gone. :class:`Memo` keeps the dict and its bookkeeping behind one lock.
"""

from __future__ import annotations

import math
import threading


def _nbytes(value) -> int:
    """Bytes of an array value (``.nbytes``); 0 for anything else (tuples of arrays count 0: such
    caches are bounded by their count)."""
    return getattr(value, "nbytes", 0)


def deep_nbytes(value) -> int:
    """Bytes of the arrays in a value, counted through dicts, lists and tuples (a ``sizeof`` for
    a :class:`Memo` whose values are such structures)."""
    if isinstance(value, dict):
        return sum(deep_nbytes(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return sum(deep_nbytes(v) for v in value)
    return _nbytes(value)


class Memo:
    """A bounded map from a key to a computed value, safe to share between threads.

    The lock guards the entries, their order (oldest put first) and their running byte total:
    :meth:`get`, :meth:`put`, :meth:`update`, :meth:`items`, :meth:`clear` and ``len`` each take
    it, so no thread sees another's insertion or eviction half done. It is never held while a value
    is computed (:meth:`get_or_compute` computes outside it): two threads that miss one key at
    the same time both compute it, and the later put replaces the earlier value by an equal one.
    That is right only for what a cache may hold: a value that is a function of its key alone
    (a result, not a choice), shared and not copied, so never changed by the caller.

    Bounds: at most ``entries`` entries and ``nbytes`` bytes of array values (as ``sizeof`` counts
    them: a value's ``.nbytes`` by default, :func:`deep_nbytes` for values that are dicts, lists
    and tuples of arrays). Beyond them the oldest put go first (a key put again is the newest; a get
    does not reorder), or with ``lru`` the least recently used (a get makes its key the newest: a
    live analyzer's cache keeps the views it reads at every update however early they were put),
    or with ``flush`` all of them at once before a new key is put (the small caches of one
    diagnosis, which hold the few models of its current step: a full one means the search has
    moved on). A value larger than ``nbytes`` alone is not kept (it would push out every other).

    Keys: a model enters a key by its content (:meth:`noiselab.model.model.Model.cache_key`, or
    :func:`noiselab.model.mean_response.mean_key` for the part of it a mean response depends on),
    never by its ``id`` (a new model can reuse a freed one's).
    """

    def __init__(self, entries: int, nbytes: float = math.inf, flush: bool = False, lru: bool = False,
                 sizeof=_nbytes):
        self.entries, self.nbytes, self.flush, self.lru = entries, nbytes, flush, lru
        self._sizeof = sizeof
        self._lock = threading.Lock()
        self._d: dict = {}
        self._bytes = 0

    def get(self, key, default=None):
        with self._lock:
            if self.lru and key in self._d:
                self._d[key] = self._d.pop(key)          # the most recently used: the newest
            return self._d.get(key, default)

    def pop(self, key) -> None:
        """Forget ``key`` (if it is there)."""
        with self._lock:
            if key in self._d:
                self._bytes -= self._sizeof(self._d.pop(key))

    @property
    def bytes(self) -> int:
        """The bytes held (as ``sizeof`` counts them)."""
        with self._lock:
            return self._bytes

    def put(self, key, value) -> None:
        with self._lock:
            self._put(key, value)
            self._evict()

    def update(self, new) -> None:
        """Every entry of the mapping ``new`` put, in its order, then the oldest evicted (the same
        entries stay as when put one at a time: eviction only ever takes the oldest)."""
        with self._lock:
            for k, v in new.items():
                self._put(k, v)
            self._evict()

    def get_or_compute(self, key, compute):
        """The value of ``key``; on a miss ``compute()`` (outside the lock), put and returned."""
        got = self.get(key)
        if got is None:
            got = compute()
            self.put(key, got)
        return got

    def items(self) -> list:
        """A snapshot of the (key, value) pairs, oldest first."""
        with self._lock:
            return list(self._d.items())

    def keys(self) -> list:
        """A snapshot of the keys, oldest first."""
        with self._lock:
            return list(self._d)

    def clear(self) -> None:
        with self._lock:
            self._d.clear()
            self._bytes = 0

    def __len__(self) -> int:
        with self._lock:
            return len(self._d)

    def __contains__(self, key) -> bool:
        with self._lock:
            return key in self._d

    # -- under the lock ---------------------------------------------------------------------------
    def _put(self, key, value) -> None:
        if key in self._d:
            self._bytes -= self._sizeof(self._d.pop(key))
        elif self.flush and len(self._d) >= self.entries:
            self._d.clear()
            self._bytes = 0
        nb = self._sizeof(value)
        if nb <= self.nbytes:
            self._d[key] = value
            self._bytes += nb

    def _evict(self) -> None:
        while self._d and (len(self._d) > self.entries or self._bytes > self.nbytes):
            self._bytes -= self._sizeof(self._d.pop(next(iter(self._d))))
