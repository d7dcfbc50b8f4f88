"""The least-recently-used, deep-sized Memo (service/memo.py) that the comparison's predictions
are kept in: a get makes its key the newest, values that are dicts, lists and tuples of arrays are
counted through, and its bounds hold under threads."""

from __future__ import annotations

import sys
import threading

import numpy as np

from noiselab.memo import Memo, deep_nbytes


def test_an_lru_memo_keeps_what_is_read_and_counts_nested_arrays():
    """Three entries of 80 bytes each in a memo of 3 entries: reading the oldest makes it the newest,
    so the next put evicts the second oldest; a plain Memo evicts the oldest put whatever was read.
    The bytes held are the arrays' inside dicts, lists and tuples; pop frees them."""
    value = {"a": np.zeros(5), "b": [np.zeros(3), (np.zeros(2), "text")]}
    assert deep_nbytes(value) == 80 and deep_nbytes(np.zeros(4)) == 32 and deep_nbytes("x") == 0
    for lru, kept in ((True, ["k0", "k2", "k3"]), (False, ["k1", "k2", "k3"])):
        m = Memo(3, lru=lru, sizeof=deep_nbytes)
        for i in range(3):
            m.put(f"k{i}", {"a": np.zeros(5), "b": [np.zeros(3), (np.zeros(2), "text")]})
        assert m.bytes == 240
        assert m.get("k0") is not None
        m.put("k3", value)
        assert sorted(m.keys()) == kept and m.bytes == 240
        m.pop("k3")
        m.pop("absent")
        assert "k3" not in m and m.bytes == 160
    # a byte bound: a value above it alone is not kept, the others go oldest-used first
    m = Memo(10, nbytes=200, lru=True, sizeof=deep_nbytes)
    m.put("a", [np.zeros(10)])
    m.put("b", [np.zeros(10)])
    m.get("a")
    m.put("c", (np.zeros(10),))
    assert sorted(m.keys()) == ["a", "c"] and m.bytes == 160
    m.put("big", [np.zeros(30)])
    assert "big" not in m and m.bytes == 160


def test_an_lru_memo_keeps_its_bounds_and_its_values_under_threads():
    """8 threads put, get and pop 1000 keys of 200 in an LRU memo of 40 entries and 3000 bytes of
    nested values, the GIL handed over every microsecond: no exception, every value read is its
    key's, and the bounds hold and the byte total is the sum of what is there afterwards."""
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        m = Memo(40, nbytes=3000, lru=True, sizeof=deep_nbytes)
        errors, wrong = [], []
        start = threading.Barrier(8)

        def val(k):
            return {"v": np.full(1 + k % 10, float(k)), "t": (np.full(2, float(k)),)}

        def work(i):
            try:
                start.wait()
                for k in np.random.default_rng(i).integers(0, 200, 1000):
                    k = int(k)
                    if k % 3 == 0:
                        m.put(k, val(k))
                    elif k % 3 == 1:
                        got = m.get(k)
                        if got is not None and not np.all(got["v"] == k):
                            wrong.append(k)
                    else:
                        m.pop(k)
            except Exception as exc:      # collected: an exception in a thread would not fail the test
                errors.append(exc)
        threads = [threading.Thread(target=work, args=(i,)) for i in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(old)
    assert not errors and not wrong
    items = m.items()
    assert len(items) <= 40 and m.bytes == sum(deep_nbytes(v) for _, v in items) <= 3000
