"""Rolling (moving-window) variance: a streaming O(1)-per-sample form for the live analysis node
and a vectorised batch form for offline analysis that give the same numbers on the same data.

Convention: after sample k (0-based) the window holds the last min(k + 1, window) samples and
the variance is sum (x_i - mean)^2 / (count - ddof) over them, ``ddof = 1`` (unbiased sample
variance) by default; NaN while count <= ddof. Per-sample (not per-second) quantity, in x units
squared.

Numerics:

* streaming: running sums of deviations from a shift K, s1 = sum (x - K) and
  s2 = sum (x - K)^2, updated by adding the new sample's terms and subtracting the oldest's
  (the "shifted data" algorithm; Chan, Golub & LeVeque 1983), M2 = s2 - s1^2 / count. Each time
  the ring buffer wraps (every ``window`` samples: amortised O(1)) K is reset to the window's
  mean and s1, s2 are recomputed exactly by two passes over the buffer, so rounding errors
  cannot accumulate over a long stream and K never lags the data by more than one window.
* batch: the series is cut into blocks of ``window`` samples; within a block, cumulative sums
  of deviations from the block's own mean give the mean and sum of squares of any head or
  tail of the block; a window is at most one block tail plus the next block's head, merged by
  the pairwise formula of Chan, Golub & LeVeque (1979): M2 = M2_a + M2_b + delta^2 n_a n_b / n.
  Every quantity is a sum over at most ``window`` samples of deviations from a nearby mean.

Both forms are accurate to a few ulps of sum (x - c)^2 over the window, c the shift or block
mean in use, i.e. to a few ulps of the variance unless the window's spread is much smaller
than its distance from c (two nearly equal samples in a window of 2, or a trend of many
standard deviations within one window); on such data the two forms may differ beyond 1e-12.
"""

from __future__ import annotations

import numpy as np

from .errors import StatsError, as_series, positive_int

__all__ = ["RollingVariance", "rolling_variance"]


class RollingVariance:
    """Streaming variance over the last ``window`` samples, O(1) per :meth:`update`.

    Args:
        window: number of samples in the window (>= 1).
        ddof: delta degrees of freedom (1: unbiased sample variance, 0: population).
    """

    def __init__(self, window: int, ddof: int = 1):
        self.window = positive_int(window, "window")
        self.ddof = positive_int(ddof, "ddof", minimum=0)
        self._buf = np.zeros(self.window)
        self._head = 0  # next write position (the oldest sample once full)
        self._count = 0
        self._shift = 0.0  # K
        self._s1 = 0.0  # sum (x - K)
        self._s2 = 0.0  # sum (x - K)^2

    @property
    def count(self) -> int:
        """Number of samples currently in the window."""
        return self._count

    @property
    def mean(self) -> float:
        """Mean of the samples in the window (NaN if empty)."""
        return self._shift + self._s1 / self._count if self._count else float("nan")

    @property
    def variance(self) -> float:
        """Variance of the samples in the window (NaN while count <= ddof)."""
        if self._count <= self.ddof:
            return float("nan")
        m2 = self._s2 - self._s1 * self._s1 / self._count
        return max(m2, 0.0) / (self._count - self.ddof)

    def update(self, x: float) -> float:
        """Add one sample (dropping the oldest once full) and return the new variance."""
        x = float(x)
        if not np.isfinite(x):
            raise StatsError(f"x: sample is not finite ({x!r})")
        if self._count == 0:
            self._shift = x
        d = x - self._shift
        if self._count < self.window:
            self._count += 1
            self._s1 += d
            self._s2 += d * d
        else:
            e = self._buf[self._head] - self._shift
            self._s1 += d - e
            self._s2 += (d - e) * (d + e)
        self._buf[self._head] = x
        self._head += 1
        if self._head == self.window:
            self._head = 0
            self._refresh()  # once per window: exact two-pass recomputation, amortised O(1)
        return self.variance

    def extend(self, xs) -> np.ndarray:
        """Feed several samples; return the variance after each."""
        arr = np.asarray(xs, dtype=np.float64).ravel()
        return np.array([self.update(v) for v in arr])

    def _refresh(self) -> None:
        data = self._buf[: self._count]
        self._shift = float(np.mean(data))
        dev = data - self._shift
        self._s1 = float(np.sum(dev))
        self._s2 = float(np.dot(dev, dev))


def rolling_variance(x, window: int, ddof: int = 1) -> np.ndarray:
    """Variance over the last ``window`` samples after each sample of ``x`` (vectorised).

    Equals :class:`RollingVariance` fed the same samples (to rounding), including the warm-up
    where fewer than ``window`` samples have been seen.
    """
    xx = as_series(x, "x", min_len=1)
    w = positive_int(window, "window")
    ddof = positive_int(ddof, "ddof", minimum=0)
    n = xx.size
    nb = -(-n // w)  # number of blocks
    pad = nb * w - n
    blocks = np.concatenate([xx, np.zeros(pad)]).reshape(nb, w)
    sizes = np.full(nb, w)
    sizes[-1] = w - pad
    valid = np.arange(w)[None, :] < sizes[:, None]
    centre = np.where(valid, blocks, 0.0).sum(axis=1) / sizes  # block means
    d = np.where(valid, blocks - centre[:, None], 0.0)
    c1 = np.cumsum(d, axis=1)  # head sums of deviations, positions 0..p
    c2 = np.cumsum(d * d, axis=1)
    pos = np.arange(w)
    # head of block b up to position p (inclusive): n_h = p + 1
    n_h = (pos + 1)[None, :].astype(np.float64)
    mean_h = c1 / n_h  # relative to this block's centre
    m2_h = c2 - c1 * c1 / n_h
    # tail of block b - 1 from position p + 1 to w - 1: n_t = w - 1 - p
    n_t = (w - 1 - pos)[None, :].astype(np.float64)
    tot1 = c1[:, -1:]
    tot2 = c2[:, -1:]
    t1 = tot1 - c1
    t2 = tot2 - c2
    safe_nt = np.where(n_t > 0, n_t, 1.0)
    mean_t = np.where(n_t > 0, t1 / safe_nt, 0.0)  # relative to that block's centre
    m2_t = np.where(n_t > 0, t2 - t1 * t1 / safe_nt, 0.0)
    # merge tail of the previous block with this block's head (Chan, Golub & LeVeque);
    # the difference of the two means is formed as (centre_b - centre_{b-1}) + (relative
    # means), the first an exact difference of nearby floats, so no large value is rounded
    mean_t = np.vstack([np.zeros((1, w)), mean_t[:-1]])
    m2_t = np.vstack([np.zeros((1, w)), m2_t[:-1]])
    nt = np.vstack([np.zeros((1, w)), np.broadcast_to(n_t, (nb - 1, w))]) if nb > 1 else np.zeros((1, w))
    dcentre = np.concatenate([[0.0], np.diff(centre)])[:, None]
    total = nt + n_h
    delta = dcentre + (mean_h - mean_t)
    m2 = m2_h + m2_t + np.where(nt > 0, delta * delta * nt * n_h / total, 0.0)
    m2 = np.maximum(m2, 0.0).ravel()[:n]
    count = total.ravel()[:n]
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(count > ddof, m2 / (count - ddof), np.nan)
    return out
