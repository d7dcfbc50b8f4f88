"""Caches shared by threads (service/memo.py and its users), and the pool's threads. The diagnosis
fits its candidates in threads wherever it cannot fork (a process that already runs other threads:
a pytest-xdist worker, the live analyzer), and a comparison computes its views in threads; every
cache of computed results they share must stay whole while they put, get and evict at once, and a
map in threads gives what the serial path gives, in order, its items' errors raised in the caller.

Each test starts its threads together (a barrier) with the interpreter's switch interval cut to
1 us, so that threads interleave inside the caches' bookkeeping as often as they can, and repeats
enough that an unguarded cache fails it (a plain dict evicting by iterating itself raises
"dictionary changed size during iteration" or pops a key another thread took). What is asserted
does not depend on the machine's speed: a slower machine interleaves less often, never
differently."""

from __future__ import annotations

import sys
import threading

import numpy as np
import pytest

from noiselab import parallel
from noiselab.diagnose import whittle as W
from noiselab.diagnose.data import Data
from noiselab.diagnose.search import Search
from noiselab.memo import Memo
from noiselab.model import load_model


@pytest.fixture
def switch_often():
    """The GIL handed over every microsecond (CPython's default is 5 ms)."""
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    yield
    sys.setswitchinterval(old)


def _together(n: int, work) -> list:
    """work(i) in n threads started at once; the exceptions they raised."""
    start = threading.Barrier(n)
    errors: list = []

    def run(i):
        try:
            start.wait()
            work(i)
        except Exception as exc:          # collected: an exception in a thread would not fail the test
            errors.append(exc)
    threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return errors


def _value(k: int) -> np.ndarray:
    """The value of key k: 1 to 20 float64s (8 to 160 bytes), all equal to k."""
    return np.full(1 + k % 20, float(k))


def test_a_memo_keeps_its_bounds_and_its_values_under_threads(switch_often):
    """8 threads each put, get and get-or-compute 2000 keys of 300 in one Memo of 50 entries and
    2000 bytes, so that nearly every put evicts (by count or by bytes), 20 rounds: no exception,
    every value read is the one put for its key, and after each round the bounds hold and the byte
    total is the sum of what is there."""
    for rnd in range(20):
        m = Memo(50, nbytes=2000)
        wrong: list = []

        def work(i):
            rng = np.random.default_rng(100 * rnd + i)
            for k in rng.integers(0, 300, 2000):
                k = int(k)
                op = k % 3
                if op == 0:
                    m.put(k, _value(k))
                elif op == 1:
                    got = m.get(k)
                    if got is not None and not np.array_equal(got, _value(k)):
                        wrong.append((k, got))
                else:
                    got = m.get_or_compute(k, lambda k=k: _value(k))
                    if not np.array_equal(got, _value(k)):
                        wrong.append((k, got))
                if k % 50 == 0:
                    m.update({k + 1: _value(k + 1), k + 2: _value(k + 2)})
                    for key, v in m.items():
                        if not np.array_equal(v, _value(key)):
                            wrong.append((key, v))
        errors = _together(8, work)
        assert not errors, (rnd, errors[:3])
        assert not wrong, (rnd, wrong[:3])
        items = m.items()
        assert 0 < len(items) <= 50
        total = sum(v.nbytes for _, v in items)
        assert total <= 2000
        assert m._bytes == total, rnd


def test_a_flushing_memo_forgets_all_when_full_and_a_big_value_is_not_kept():
    """flush: a new key put into a full Memo finds it emptied first; a key put again stays where it
    is counted (no flush). A value larger than the byte budget is not kept and pushes nothing out."""
    m = Memo(3, flush=True)
    for k in range(3):
        m.put(k, k)
    m.put(1, 1)
    assert m.keys() == [0, 2, 1]
    m.put(3, 3)
    assert m.keys() == [3]
    b = Memo(10, nbytes=100)
    b.put("a", np.zeros(5))
    b.put("big", np.zeros(20))
    assert b.keys() == ["a"] and "big" not in b


def test_threaded_candidate_fits_share_the_parts_cache_while_it_evicts(monkeypatch, switch_often):
    """The diagnosis' candidate map in 8 threads (as where it cannot fork) on one record, its parts
    cache bounded at 1000 entries and 256 kB and filled to the count with small entries first, so
    that every part the fits compute evicts (the oldest filler, by count; later, by bytes, many):
    12 rounds, each with a fresh search. Every round completes, the cache keeps its bounds, the
    fillers were evicted, and the candidates' scores are bit-identical to the serial map's (a cache
    holds results, not choices)."""
    monkeypatch.setattr(parallel, "POOL", "threads")
    monkeypatch.setattr(W.parts, "PARTS_CACHE", 1000)
    monkeypatch.setattr(W.parts, "PARTS_CACHE_BYTES", 256 << 10)
    truth, nominal = load_model("hidden/sensor.bias_markov"), load_model("hidden/sensor.bias_markov-nominal")
    rec = truth.simulate(4000, seed=3)
    data = Data(rec.y, rec.u, truth.Ts, True, 0)

    def scores(workers: int, fill: int):
        S = Search(nominal, data)
        S.workers = workers
        S.H.ev._parts.update({("filler", i): np.zeros(1) for i in range(fill)})
        out = [(c.effect, c.mode, c.score, c.fit.loglik) for c in S.candidates(S.start())]
        return out, S.H.ev._parts

    serial, _ = scores(1, 0)
    assert serial
    for _ in range(12):
        got, cache = scores(8, 1000)
        assert got == serial
        keys = cache.keys()
        assert len(keys) <= 1000
        assert sum(v.nbytes for _, v in cache.items()) <= 256 << 10
        assert ("filler", 0) not in keys and any(k[0] != "filler" for k in keys)


def test_a_predictor_shared_by_threads_gives_each_the_whole_steady_state(switch_often):
    """One predictor (as the comparison shares one per model) asked for its autocovariances by 8
    threads at once, before anything is computed: each gets every source's, equal to a serial
    predictor's, 200 times (the per-source covariances must be published whole: a thread that read
    them while another filled them would find a source missing and get None for it)."""
    model = load_model("hidden/sensor.bias_markov")
    ref = model.predictor().acf(64)
    assert all(v is not None for v in ref.values())
    wrong: list = []
    for _ in range(200):
        pr = model.predictor()

        def work(i):
            got = pr.acf(64)
            for k, v in ref.items():
                if got.get(k) is None or not np.array_equal(got[k], v):
                    wrong.append(k)
        errors = _together(8, work)
        assert not errors, errors[:3]
    assert not wrong, wrong[:3]


@pytest.mark.parametrize("pool", ["threads", "serial"])
def test_a_map_in_threads_or_serially_gives_every_result_in_order_and_raises_an_items_error(monkeypatch, pool):
    """``Pool.map`` where it cannot fork (this test's process may run other threads; the pool is
    told to use threads, or none): 4 workers over 200 items taken in reverse, each item's result
    in its place; an item that raises raises its own error in the caller; a call beside the maps
    runs (in a thread of the pool, or at once serially) and close() leaves no thread behind."""
    monkeypatch.setattr(parallel, "POOL", pool)
    items = list(range(200))
    seen: list = []
    lock = threading.Lock()

    def square(x):
        with lock:
            seen.append((x, threading.get_ident()))
        return x * x

    with parallel.Pool() as p:
        assert p.map(square, items, workers=4, order=items[::-1]) == [x * x for x in items]
        assert sorted(x for x, _ in seen) == items                   # each item once
        if pool == "serial":
            assert {t for _, t in seen} == {threading.get_ident()}

        def fails(x):
            if x == 57:
                raise ValueError(f"item {x}")
            return x
        with pytest.raises(ValueError, match="item 57"):
            p.map(fails, items, workers=4)
        before = threading.active_count()
        side = p.beside(threading.get_ident, workers=2)
        assert (side.result() == threading.get_ident()) is (pool == "serial")
        err = p.beside(lambda: 1 / 0, workers=2) if pool == "threads" else None
    assert threading.active_count() <= before
    if err is not None:
        assert isinstance(err.exception(), ZeroDivisionError)
