"""Rolling variance (noiselab.stats.rolling): the streaming form (live analysis node) equals the
batch form (offline analysis) on the same data, and both equal the definition."""

from __future__ import annotations

import numpy as np
import pytest

from noiselab.stats import RollingVariance, StatsError, rolling_variance


def reference(x: np.ndarray, window: int, ddof: int) -> np.ndarray:
    """Two-pass variance of the last min(k+1, window) samples, sample by sample."""
    out = np.full(x.size, np.nan)
    for k in range(x.size):
        seg = x[max(0, k - window + 1) : k + 1]
        if seg.size > ddof:
            out[k] = np.sum((seg - seg.mean()) ** 2) / (seg.size - ddof)
    return out


def sensor_like(n: int, seed: int) -> np.ndarray:
    """White noise on a large offset with a random-walk bias: the hard case for sums."""
    rng = np.random.default_rng(seed)
    return 1e4 + 0.05 * np.cumsum(rng.standard_normal(n)) + rng.standard_normal(n)


@pytest.mark.parametrize("window", [5, 16, 100, 1000])
@pytest.mark.parametrize("ddof", [0, 1])
def test_streaming_equals_batch(window, ddof):
    x = sensor_like(5000, window)
    rv = RollingVariance(window, ddof=ddof)
    stream = np.array([rv.update(v) for v in x])
    batch = rolling_variance(x, window, ddof=ddof)
    np.testing.assert_array_equal(np.isnan(stream), np.isnan(batch))
    # relative 1e-12 (NaN where both NaN; the single-sample ddof=0 variance is exactly 0 in both)
    np.testing.assert_allclose(stream, batch, rtol=1e-12, atol=0)
    # and both are the variance of the window
    np.testing.assert_allclose(batch, reference(x, window, ddof), rtol=1e-12, atol=0)
    assert rv.count == window
    assert rv.mean == pytest.approx(x[-window:].mean(), rel=1e-15)


def test_known_data():
    # 1, 2, ..., 10 with window 3: every full window is three consecutive integers, variance 1
    x = np.arange(1.0, 11.0)
    v = rolling_variance(x, 3)
    assert np.isnan(v[0])
    assert v[1] == 0.5  # {1, 2}
    np.testing.assert_array_equal(v[2:], 1.0)
    rv = RollingVariance(3)
    np.testing.assert_array_equal(rv.extend(x)[1:], v[1:])
    # population variance of {a, a + d}: d^2 / 4; window 1, ddof 0: zero
    np.testing.assert_array_equal(rolling_variance([2.0, 4.0, 8.0], 2, ddof=0), [0.0, 1.0, 4.0])
    np.testing.assert_array_equal(rolling_variance([2.0, 4.0, 8.0], 1, ddof=0), [0.0, 0.0, 0.0])
    assert np.all(np.isnan(rolling_variance([2.0, 4.0, 8.0], 1, ddof=1)))


def test_long_stream_does_not_drift():
    """The periodic exact refresh keeps a long stream at batch accuracy."""
    x = sensor_like(200_000, 3)
    window = 64
    rv = RollingVariance(window)
    for v in x:
        last = rv.update(v)
    assert last == pytest.approx(np.var(x[-window:], ddof=1), rel=1e-12)


@pytest.mark.parametrize(
    "call, culprit",
    [
        (lambda: RollingVariance(0), "window"),
        (lambda: RollingVariance(3, ddof=-1), "ddof"),
        (lambda: RollingVariance(3).update(float("nan")), "x"),
        (lambda: rolling_variance([1.0, 2.0], 2.5), "window"),
        (lambda: rolling_variance([[1.0, 2.0]], 2), "x"),
    ],
)
def test_bad_arguments_name_the_culprit(call, culprit):
    with pytest.raises(StatsError, match=f"^{culprit}:"):
        call()
