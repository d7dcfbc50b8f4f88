"""The rate data's phase as a cumulative sum, and the sums of squared differences on it that the
Allan-family variances are (NIST SP 1065 eqs. (7), (11), (15)).

The phase is formed once by a cumulative sum of the mean-removed rate (every estimator is
invariant to a constant rate offset, and removing it keeps the cumulative sum small); each second
difference x_{i+2m} - 2x_{i+m} + x_i is then one vectorised expression, so each tau costs O(N)
whatever m is, and the modified variance's inner sums of m second differences are a moving sum
through one more cumulative sum. The absolute rounding error of a second difference is about
eps * max|sum (y - mean y)| (eps = 2.2e-16).
"""

from __future__ import annotations

import numpy as np

from .errors import as_series, positive_float

CHUNK = 1 << 15  # elements per in-cache block for sums of products


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """sum(a * b), accumulated in float64 one cache-sized block at a time.

    einsum rather than BLAS dot, which starts threads per call and is slow under CPU
    contention; blockwise accumulation also keeps the rounding error of long sums small."""
    total = 0.0
    for start in range(0, a.size, CHUNK):
        total += float(np.einsum("i,i->", a[start : start + CHUNK], b[start : start + CHUNK]))
    return total


class PhaseSums:
    """Phase of the rate data as a cumulative sum: s[0] = 0, s[k] = sum_{i<k} (y_i - mean y),
    so the phase is x_k = s[k] / rate (plus a line, which no estimator here sees)."""

    def __init__(self, s: np.ndarray, rate: float, yc: np.ndarray | None = None):
        self.s = s
        self.rate = rate
        self.n = s.size - 1  # number of rate samples N
        self._yc = yc  # the mean-removed rate itself, when known (block means at m = 1)
        self._chunk = np.empty(CHUNK, dtype=np.float64)

    def second_diff(self, m: int, out: np.ndarray | None = None) -> np.ndarray:
        """d_i = s[i+2m] - 2 s[i+m] + s[i], i = 0..N-2m.

        d_i / m is the difference of the two adjacent m-averages of y starting at i."""
        s = self.s
        k = s.size - 2 * m
        out = np.empty(k) if out is None else out[:k]
        np.subtract(s[2 * m :], s[m : m + k], out=out)
        out -= s[m : m + k]
        out += s[:k]
        return out

    def block_means(self, m: int) -> np.ndarray:
        """Non-overlapping m-averages of the (mean-removed) rate, floor(N/m) of them."""
        if m == 1 and self._yc is not None:
            return self._yc
        k = self.n // m
        return np.diff(self.s[: k * m + 1 : m]) / m

    def avar(self, m: int) -> tuple[float, int]:
        s = self.s[::m]
        d = s[2:] - 2.0 * s[1:-1] + s[:-2]
        return dot(d, d) / (2.0 * m * m * d.size), int(d.size)

    def oavar(self, m: int) -> tuple[float, int]:
        # sum of squared second differences, one cache-sized chunk at a time (no N-sized
        # temporaries: memory traffic is three streaming reads of s)
        s = self.s
        k = s.size - 2 * m
        total = 0.0
        for start in range(0, k, CHUNK):
            stop = min(k, start + CHUNK)
            b = self._chunk[: stop - start]
            np.subtract(s[start + 2 * m : stop + 2 * m], s[start + m : stop + m], out=b)
            b -= s[start + m : stop + m]
            b += s[start:stop]
            total += float(np.einsum("i,i->", b, b))
        return total / (2.0 * m * m * k), int(k)

    def mvar(self, m: int) -> tuple[float, int]:
        d = self.second_diff(m)
        if m == 1:
            w = d
        else:
            c = np.empty(d.size + 1)
            c[0] = 0.0
            np.cumsum(d, out=c[1:])
            w = np.subtract(c[m:], c[:-m], out=d[: d.size - m + 1])  # sums of m second differences
        return dot(w, w) / (2.0 * float(m) ** 4 * w.size), int(w.size)


def rate_sums(y, rate) -> PhaseSums:
    rate = positive_float(rate, "rate")
    # three rate samples (four phase points) at least: m = 1 needs two adjacent means, and the
    # Greenhall edf of the second difference needs L + 1 = 4 phase points
    yy = as_series(y, "y", min_len=3)
    yc = yy - yy.mean()
    s = np.empty(yy.size + 1)
    s[0] = 0.0
    np.cumsum(yc, out=s[1:])
    return PhaseSums(s, rate, yc)
