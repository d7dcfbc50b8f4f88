"""Frequency groups: the expected periodogram's group means without the full transform."""

from __future__ import annotations

import math

import numpy as np
import scipy.fft as sfft

from ...memo import Memo
from .periodograms import _cross_spectrum, _from_acf, _spectrum, n_freqs


# -- frequency groups: the expected periodogram's group means without the full transform ------------------
class Groups:
    """Fourier bins f = 0..nf-1 in groups at most ``rel`` f wide (single bins up to 1/rel), and the
    group means of an expected periodogram E_f = a(0) + 2 sum_{h>=1} a(h) cos(2 pi f h / M) computed
    exactly from a(h) without the length-M transform when a(h) is short:

    * above F_low = n / rel the groups are made of whole aligned blocks of n bins (n a divisor of
      M near sqrt(rel M)). The mean over block b (bins bn..bn+n-1) is
      a(0) + 2 Re sum_h a(h) D(h) e^{-i 2 pi b h / L}, L = M / n, D(h) = (1/n) sum_{j<n}
      e^{-i 2 pi j h / M}: the exponential is L-periodic in h, so a(h) D(h) folded modulo L and one
      length-L transform give every block mean;
    * the single bins below F_low (and the < n bins after the last whole block) by the chirp z
      transform (Bluestein 1970): a transform of length ~ K + F_low for a(h) of K lags.

    Every M gets the same group layout whatever the part, so the periodogram is grouped alike."""

    def __init__(self, M: int, rel: float):
        self.M, self.rel = M, rel
        nf = self.nf = n_freqs(M)
        target = math.sqrt(rel * M)
        n = max((d for d in range(1, int(target) + 1) if M % d == 0), default=1)
        if n < 4 or n / rel >= nf:
            n = 1
        self.n = n
        self.F_low = int(round(n / rel)) if n > 1 else nf
        F_low = self.F_low
        starts, i = [], 0
        while i < nf:
            starts.append(i)
            if i < F_low:
                i = min(i + max(1, int(i * rel)), F_low)
            else:
                i += n * max(1, int(i * rel) // n)
        self.starts = np.asarray(starts, np.int64)
        self.sizes = np.diff(np.append(self.starts, nf)).astype(float)
        if n > 1:
            self.L = M // n
            self.b0 = F_low // n                       # first block above F_low
            self.b1 = nf // n                          # one past the last whole block
            self.tail = nf - self.b1 * n               # bins after the last whole block
            # the units the groups are sums of: low bins (1 bin), blocks (n bins), tail bins (1 bin)
            unit_f = np.concatenate([np.arange(F_low), np.arange(self.b0, self.b1) * n,
                                     np.arange(self.b1 * n, nf)])
            self.unit_w = np.concatenate([np.ones(F_low), np.full(self.b1 - self.b0, float(n)),
                                          np.ones(self.tail)])
            self.unit_starts = np.searchsorted(unit_f, self.starts)
        self._D = np.ones(1, complex)
        self._chirps = Memo(17, flush=True)         # by (first bin, bins, length)
        self.white_unit = self.mean(_from_acf(np.array([[2.0], [-1.0]]), M))[:, 0]

    def mean(self, A: np.ndarray) -> np.ndarray:
        """Group means (nb, ...) of a full array (nf, ...)."""
        return np.add.reduceat(A, self.starts, axis=0) / self.sizes.reshape((-1,) + (1,) * (A.ndim - 1))

    def fast(self, K: int) -> bool:
        """Whether a(h) of K lags takes the fast path (chirp z and folded blocks)."""
        return self.n > 1 and K + self.F_low <= self.M // 8

    def spectrum(self, a: np.ndarray) -> np.ndarray:
        """Group means of E_f (nb, p) from a(h) (K, p), as ``mean(_spectrum(a, M))``."""
        if not self.fast(a.shape[0]):
            return self.mean(_spectrum(a, self.M))
        return 2.0 * self._sums(a).real - a[0]

    def cross(self, a: np.ndarray) -> np.ndarray:
        """Group means of the cross-spectrum S_f (nb, p, p) from a(h) (K, p, p), as
        ``mean(_cross_spectrum(a, M))``."""
        K, p, _ = a.shape
        if not self.fast(K):
            return self.mean(_cross_spectrum(a, self.M))
        C = self._sums(a.reshape(K, p * p)).reshape(-1, p, p)
        return C + np.conj(C.transpose(0, 2, 1)) - a[0]

    def _sums(self, a: np.ndarray) -> np.ndarray:
        """Group means of C_f = sum_{h>=0} a(h) e^{-i w_f h} (nb, q) complex, from a(h) (K, q)."""
        K, q = a.shape
        units = np.empty((self.unit_w.size, q), complex)
        units[:self.F_low] = self._czt(a, 0, self.F_low)
        # block means: a(h) D(h) folded modulo L, one transform
        D = self._kernel(K)
        g = np.zeros((-(-K // self.L) * self.L, q), complex)
        g[1:K] = a[1:K] * D[1:K, None]
        G = sfft.fft(g.reshape(-1, self.L, q).sum(axis=0), axis=0)
        nb = self.b1 - self.b0
        units[self.F_low:self.F_low + nb] = a[0] + G[self.b0:self.b1]
        if self.tail:
            units[self.F_low + nb:] = self._czt(a, self.b1 * self.n, self.tail)
        return np.add.reduceat(units * self.unit_w[:, None], self.unit_starts, axis=0) / self.sizes[:, None]

    def _kernel(self, K: int) -> np.ndarray:
        """D(h) = (1/n) sum_{j<n} e^{-i 2 pi j h / M}, h = 0..K-1 (cached, extended on demand).
        The one read of ``self._D`` is what is returned: another thread may replace it meanwhile,
        by a shorter one too (every length's values agree)."""
        D = self._D
        if D.size < K:
            size = 1 << int(K - 1).bit_length()
            h = np.arange(1, size)
            th = 2 * np.pi * h / self.M
            D = np.ones(size, complex)
            D[1:] = (1 - np.exp(-1j * self.n * th)) / (self.n * (1 - np.exp(-1j * th)))
            self._D = D
        return D

    def _czt(self, a: np.ndarray, f0: int, m: int) -> np.ndarray:
        """X_f = sum_h a(h) e^{-i 2 pi f h / M} for f = f0..f0+m-1 (m, p): Bluestein's chirp
        (f h = (f^2 + h^2 - (f - h)^2) / 2), the phases reduced modulo 2M in integers."""
        K = a.shape[0]
        size = 1 << int(K + m - 2).bit_length()
        M2 = 2 * self.M
        key = (f0, m, size)

        def chirp():
            # filter c(j) = e^{i pi j^2 / M} for j = f - h in [f0 - size + m, f0 + m); index j - (f0 - size + m)
            j = np.arange(f0 - size + m, f0 + m, dtype=np.int64)
            c = np.exp(1j * np.pi * ((j * j) % M2) / self.M)
            f = np.arange(f0, f0 + m, dtype=np.int64)
            return sfft.fft(c), np.exp(-1j * np.pi * ((f * f) % M2) / self.M)
        Cf, post = self._chirps.get_or_compute(key, chirp)
        h = np.arange(K, dtype=np.int64)
        x = np.zeros((size, a.shape[1]), complex)
        x[:K] = a * np.exp(-1j * np.pi * ((h * h) % M2) / self.M)[:, None]
        # y(f0 + i) = sum_h x(h) c(f0 + i - h): a circular convolution of length size >= K + m - 1,
        # free of wrap-around at the outputs i + size - m
        y = sfft.ifft(sfft.fft(x, axis=0) * Cf[:, None], axis=0)
        return y[size - m:] * post[:, None]
