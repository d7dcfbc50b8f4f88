"""The expected value of each spectral estimator under the model, exact for the sampled process.

Every prediction compared with a record is the expectation of the very estimator applied to it,
formed from the model's autocovariance R(d) or variogram gamma(d) = E[(y_{k+d} - y_k)^2] / 2:

- :func:`expected_welch`: E[Welch estimate] without segment-mean removal, from R(d) per effect;
- :func:`expected_welch_detrended`: E[Welch estimate] with each segment's mean removed (detrend
  "constant"), from gamma(d), which exists for a walk as well;
- :func:`expected_window_stats`: E[segment autocovariance] (biased, segment mean removed).

The periodogram's expectation for the Whittle likelihood is :mod:`noiselab.diagnose.whittle`'s.
Welch conventions are :func:`noiselab.stats.welch`'s: one-sided, units^2/Hz, at f_j = j / (L Ts),
every bin (DC and Nyquist too) doubled.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import get_window

from ..memo import Memo

# the kernels of the last few segment lengths (each (L/2 + 1, L): 67 MB at L = 4096), shared and read-only
_KERNELS = Memo(3, lru=True)


def expected_welch(acf: dict, nperseg: int, Ts: float, window: str = "hann") -> dict:
    """E[Welch estimate] per effect {id: (nperseg//2+1, p)} from its autocovariance ``acf``
    ({id: R (>= nperseg, p) or None}), without segment-mean removal.

    The predicted spectrum seen through the estimator's window, exact for the sampled process:
    E|sum_n w_n x_n e^{-i w n}|^2 = sum_d R(d) c_w(d) e^{-i w d}, c_w(d) = sum_n w_n w_{n+d}
    (Percival & Walden 1993, eq. 186e), divided by fs sum w^2 and doubled except at DC and
    Nyquist. Leakage at resonances and tones is thus in the prediction, not in the error.
    Segment-mean removal (detrend "constant") biases only the lowest two or three bins
    (:func:`expected_welch_detrended` has it).
    """
    from ..stats.psd import window_autocorrelation

    L = int(nperseg)
    w = get_window(window, L)
    c = window_autocorrelation(w)                        # c_w(d), d = 0..L-1
    out = {}
    for eid, R in acf.items():
        if R is None:
            out[eid] = None
            continue
        g = R * c[:, None]
        E = 2.0 * np.fft.rfft(g, axis=0).real - g[0]
        E *= 2.0 * Ts / np.sum(w**2)
        out[eid] = E
    return out


def expected_window_stats(gam: np.ndarray, M: int, max_lag: int) -> np.ndarray:
    """E[segment autocovariance] (biased, 1/M, segment mean removed) at lags 0..max_lag for each
    column of ``gam`` (variogram, rows d = 0..>=M-1). Returns (max_lag+1, K)."""
    g_ = gam[:M]
    S = np.cumsum(g_, axis=0)
    a = np.arange(M)
    g = (S[a] + S[M - 1 - a]) / M                    # g(a) = (1/M) sum_m gamma(|a - m|)
    G = g.mean(axis=0)
    Pg = np.concatenate([np.zeros((1,) + g.shape[1:]), np.cumsum(g, axis=0)])   # Pg[n] = sum_{i<n} g(i)
    d = np.arange(max_lag + 1)
    head = Pg[M - d]                                  # sum_{n=0}^{M-1-d} g(n)
    tail = Pg[M] - Pg[d]                              # sum_{n=d}^{M-1} g(n)
    cnt = (M - d)[:, None]
    return ((cnt * (-g_[d] - G)) + head + tail) / M


def _welch_kernel(L: int, window: str) -> np.ndarray:
    """:func:`_welch_kernel_uncached`, remembered for the last few (L, window) in :data:`_KERNELS`."""
    def compute():
        k = _welch_kernel_uncached(L, window)
        k.setflags(write=False)
        return k
    return _KERNELS.get_or_compute((int(L), window), compute)


def _welch_kernel_uncached(L: int, window: str) -> np.ndarray:
    """Re C_j(d), d = 0..L-1, of h_j(n) = w_n e_j(n) - a_j, e_j(n) = e^{-i w_j n}, a_j = W_j / L,
    for bins j = 0..L/2: (J, L). With c_w(d) = sum_n w_{n+d} w_n, the suffix sums
    S1(d) = sum_{m>=d} w_m e(m) and prefix sums S2(d) = sum_{n<=L-1-d} w_n conj(e(n)):
    C(d) = e^{-i w d} c_w(d) - conj(a) S1(d) - a S2(d) + |a|^2 (L - d)."""
    from ..stats.psd import window_autocorrelation

    w = get_window(window, L)
    n = np.arange(L)
    d = n
    cw = window_autocorrelation(w)
    J = L // 2 + 1
    out = np.empty((J, L))
    # a_j = W_j / L vanishes (to rounding) for most bins of a smooth window (Hann: all but j = 0, 1);
    # there C(d) = e^{-i w d} c_w(d), no sums needed
    A = np.fft.rfft(w) / L
    full = np.abs(A) > 1e-13 * abs(A[0])
    for j0 in range(0, J, 256):
        j = np.arange(j0, min(J, j0 + 256))[:, None]
        out[j0:j0 + j.size] = np.cos(2 * np.pi * ((j * n) % L) / L) * cw
    for j in np.flatnonzero(full):
        e = np.exp(-2j * np.pi * ((j * n) % L) / L)
        we = w * e
        a = we.sum() / L
        S1 = np.cumsum(we[::-1])[::-1]                 # sum_{m>=d}
        S2 = np.cumsum(np.conj(we))[::-1]              # sum_{n<=L-1-d}
        out[j] = (e * cw - np.conj(a) * S1 - a * S2 + np.abs(a) ** 2 * (L - d)).real
    return out


def _welch_kernel_fft(L: int, window: str) -> np.ndarray:
    """The same kernel by FFT autocorrelation of h_j (reference for the tests)."""
    w = get_window(window, L)
    n = np.arange(L)
    J = L // 2 + 1
    out = np.empty((J, L))
    for j0 in range(0, J, 256):
        j = np.arange(j0, min(J, j0 + 256))
        h = w * np.exp(-2j * np.pi * np.outer(j, n) / L)
        h -= h.sum(axis=1, keepdims=True) / L
        Hf = np.fft.fft(h, 2 * L, axis=1)
        out[j] = np.fft.ifft(np.abs(Hf) ** 2, axis=1).real[:, :L]
    return out


def expected_welch_detrended(gam: np.ndarray, L: int, Ts: float, window: str = "hann") -> np.ndarray:
    """E[Welch estimate] (segment mean removed, one-sided, every bin doubled) for each column of
    the variogram ``gam`` (rows d = 0..>=L-1): (L//2+1, K) in units^2/Hz."""
    K = _welch_kernel(L, window)
    w = get_window(window, L)
    EX2 = -2.0 * K[:, 1:] @ gam[1:L]                  # -sum_{d != 0} gamma(|d|) Re C(d)
    return 2.0 * EX2 * Ts / np.sum(w**2)
