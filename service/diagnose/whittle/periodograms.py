"""The periodogram of the differenced residual: the taper, the Fourier bins, and the
expectation of a periodogram from an autocovariance (the package docstring gives the method)."""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from ...memo import Memo

TAPER = 0.2              # Tukey taper: the cosine parts cover 10 % of the record at each end


# -- periodogram of the differenced residual ---------------------------------------------------------------
def n_freqs(M: int) -> int:
    """Fourier frequencies used: f = 0..(M-1)//2 (DC included: for the differenced series it is the
    tapered total increment, the most direct evidence of a walk; no Nyquist). Index k is k / (M Ts)."""
    return (M - 1) // 2 + 1


_TAPERS = Memo(9, flush=True)           # by M


def taper(M: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Tukey taper w (M,) with sum w^2 = M, its autocorrelation c_w(h) = sum_q w_q w_{q+h}
    (h = 0..M-1) and kappa = M sum w^4 / (sum w^2)^2."""
    def compute():
        from scipy.signal.windows import tukey
        w = tukey(M, TAPER) if M > 2 else np.ones(M)
        w *= np.sqrt(M / np.sum(w**2))
        F = np.fft.rfft(w, 2 * M)
        cw = np.fft.irfft(np.abs(F) ** 2, 2 * M)[:M]
        kappa = float(M * np.sum(w**4) / np.sum(w**2) ** 2)
        return w, cw, kappa
    return _TAPERS.get_or_compute(M, compute)


def slope_power(yk: np.ndarray, cross: bool) -> np.ndarray:
    """The jitter's slope power as the tapered periodogram of the differenced record sees it:
    sum_q w_q^2 (y_q+1 y_q+1^T + y_q y_q^T) / (2 M) over the M differences of yk (M + 1, p), the
    matrix (``cross``) or its diagonal. For a white noise of variance s_k^2,
    E I_f = (2 - 2 cos w_f) sum_k w_k^2 s_k^2 / M (to first order in the taper's slope), so the
    jitter's std_s^2 multiplies this weighted mean, not the plain one: under a PRBS or a chirp the
    slope's power is not spread evenly over the record (the plain mean biased std_s by 2 % on a
    PRBS record)."""
    w2 = taper(yk.shape[0] - 1)[0] ** 2
    if cross:
        a, b = yk[1:] * w2[:, None], yk[:-1] * w2[:, None]
        return (a.T @ yk[1:] + b.T @ yk[:-1]) / (2 * w2.size)
    return (w2 @ (yk[1:] ** 2 + yk[:-1] ** 2)) / (2 * w2.size)


def periodogram(r: np.ndarray, k0: int = 0, cross: bool = False) -> np.ndarray:
    """I_f (nf, p) of the tapered d_q = r_{k0+q+1} - r_{k0+q}, f = 0..nf-1; ``cross``: the
    cross-periodogram matrices I_f = X_f X_f^H / M (nf, p, p), complex Hermitian."""
    d = np.diff(r[k0:], axis=0)
    M = d.shape[0]
    w = taper(M)[0]
    X = sfft.rfft(np.ascontiguousarray((d * w[:, None]).T), axis=-1).T[:n_freqs(M)]    # rows: one output each
    if cross:
        return X[:, :, None] * np.conj(X[:, None, :]) / M
    return (np.abs(X) ** 2) / M


def _from_acf(Rd: np.ndarray, M: int) -> np.ndarray:
    """E I_f from the differenced autocovariance Rd (K, p), K <= M (zero beyond):
    (1/M) sum_h c_w(|h|) Rd(h) e^{-i w h}."""
    K = min(Rd.shape[0], M)
    return _spectrum(Rd[:K] * (taper(M)[1][:K, None] / M), M)


def _spectrum(a: np.ndarray, M: int) -> np.ndarray:
    """a(0) + 2 sum_{h>=1} a(h) cos(w_f h) at the Fourier frequencies w_f = 2 pi f / M, f < nf."""
    K = a.shape[0]
    nf = n_freqs(M)
    if K <= 8:                                   # short (white): the cosine sum directly
        w = 2 * np.pi * np.arange(nf) / M
        E = np.broadcast_to(a[0], (nf, a.shape[1])).copy()
        for h in range(1, K):
            E += 2.0 * np.cos(w * h)[:, None] * a[h]
        return E
    E = 2.0 * sfft.rfft(np.ascontiguousarray(a.T), n=M, axis=-1).real.T - a[0]
    return E[:nf]


def _cross_spectrum(a: np.ndarray, M: int) -> np.ndarray:
    """S_f = a(0) + sum_{h>=1} [a(h) e^{-i w_f h} + a(h)^T e^{i w_f h}] (nf, p, p) from a(h)
    (K, p, p), a(h) the cross-covariance sequence Cov(x_{k+h}, x_k) (a(-h) = a(h)^T): C + C^H - a(0)
    with C_f = sum_{h>=0} a(h) e^{-i w_f h}."""
    K, p, _ = a.shape
    C = sfft.rfft(np.ascontiguousarray(a.reshape(K, p * p).T), n=M, axis=-1).T[:n_freqs(M)].reshape(-1, p, p)
    return C + np.conj(C.transpose(0, 2, 1)) - a[0]
